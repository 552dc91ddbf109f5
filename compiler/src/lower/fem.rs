//! Tetrahedral FEM forces from a strain energy W(Ī1, Ī2, J).
//!
//! For a linear tet with rest edge matrix Dm (columns x1−x0, x2−x0, x3−x0 at rest) and current
//! edge matrix Ds, the deformation gradient is F = Ds·Dm⁻¹ (thesis eq. 2.9), J = det F,
//! C = FᵀF, I1 = tr C, I2 = ½(I1² − tr C²), Ī1 = J^(−2/3)·I1, Ī2 = J^(−4/3)·I2 (eq. 2.10–2.13).
//! The compiler writes Ī1 and Ī2 into W as those powers of J times I1 and I2, simplifies the
//! result (a coupled law's J^(2/3)·Ī1 is I1 again), differentiates it (reverse mode on the
//! IR) to W_I1 = ∂W/∂I1, W_I2 = ∂W/∂I2, W_J = ∂W/∂J at fixed I1, I2, and assembles the first
//! Piola–Kirchhoff stress from the chain rule
//!
//!   P = 2·W_I1·F + 2·W_I2·(I1·F − F·C) + W_J·cof F,
//!
//! (the thesis' eq. 2.14 states the Cauchy form with typos; this is derived directly from W).
//! The isochoric terms a coupled law's Ī1-form would carry (−⅔·I1·F⁻ᵀ against J-derivative
//! terms) cancel symbolically this way instead of in floating point.
//! The nodal forces are f = −∂(V₀·W)/∂x: the columns of H = −V₀·P·Dm⁻ᵀ act on nodes 1–3 and
//! node 0 takes minus their sum. Terms of W that a material does not have (no Ī2 in Yeoh) are
//! not generated. A W written in I1 = tr C and J (an inversion-safe law such as the prelude's
//! stable neo-Hookean) gets P = W_I1·2F + W_J·cof F: no J^(−2/3), no F⁻ᵀ, finite for J ≤ 0.
//!
//! The kernels never form F. With G = Dm⁻¹·Dm⁻ᵀ and d = det Dm⁻¹ precomputed per element
//! (the `rest_shape` buffer, [`rest_shape`]) and K = Ds·G = F·Dm⁻ᵀ:
//!
//!   F·Dm⁻ᵀ = K,   cof(F)·Dm⁻ᵀ = d·cof(Ds),   J = d·det Ds,   I1 = Σ K∘Ds,
//!   b = F·Fᵀ = K·Dsᵀ (tr C² = tr b²),   F·C·Dm⁻ᵀ = b·K,
//!
//! so H = −V₀·(2·W_I1·K + 2·W_I2·(I1·K − b·K) + W_J·d·cof Ds): the same forces in exact
//! arithmetic, with F, F·Dm⁻ᵀ's second product and cof F's nine extra products gone (the
//! benchmark's element kernel: 175 → 131 operations, its adjoint shrinks with it).
//!
//! A material constant given by a per-element param (`neo_hookean(mu: mu, …)` with `param mu:
//! pressure[soft_part]`) is read per element from the buffer `param.mu` (element × 1, kernel
//! element order), declared here for the fields the material reads ([`material_fields`]).

use super::LowerError;
use super::expr::{Env, ExprLowerer, LVal, Program};
use crate::ir::{ArgSource, BufferId, Builder, Domain, KernelBuilder, Module, V, ad};
use crate::sema::hir::{Callee, DeclKind, Expr, ExprKind, MaterialBody, Name, Stmt, StmtKind};
use std::collections::HashMap;

/// Per-element params readable in an element kernel: the buffer of each, by param name.
pub type Fields = HashMap<String, BufferId>;

/// Declare the element buffer `param.NAME` of every per-element param a material reads, and
/// return them for [`ExprLowerer::element_fields`].
pub fn declare_fields(
    program: &Program,
    module: &mut Module,
    material: &str,
) -> Result<Fields, LowerError> {
    Ok(material_fields(program, material)?
        .into_iter()
        .map(|f| {
            let b = module.buffer(
                &format!("param.{f}"),
                Domain::Element,
                1,
                &format!("per-element param {f} (SI), one value per element"),
            );
            (f, b)
        })
        .collect())
}

/// The per-element params (fields) a material's constants read, by name, in the order they
/// appear: names in its template arguments (or its body), through `let`s and `fn`s.
pub fn material_fields(program: &Program, material: &str) -> Result<Vec<String>, LowerError> {
    let m = material_decl(program, material)?;
    let mut found = Vec::new();
    let mut stack: Vec<(&Expr, usize)> = Vec::new();
    match &m.body {
        MaterialBody::Instance(e) => stack.push((e, 0)),
        MaterialBody::Block(stmts) => {
            for s in stmts {
                match &s.kind {
                    StmtKind::Let { value, .. } | StmtKind::Assign { value, .. } => {
                        stack.push((value, 0))
                    }
                    StmtKind::Energy { body, .. } => stack.push((body, 0)),
                    _ => {}
                }
            }
        }
    }
    while let Some((e, depth)) = stack.pop() {
        if depth > 64 {
            return Err(LowerError::new("definitions nested too deeply"));
        }
        // Names and callees: the declarations they read.
        let id = match &e.kind {
            ExprKind::Name(Name::Global(id))
            | ExprKind::Call {
                callee: Callee::Decl(id),
                ..
            } => Some(*id),
            _ => None,
        };
        if let Some(id) = id {
            let decl = program.decl(id);
            match &decl.kind {
                DeclKind::Param(p) if p.field_set().is_some() && !found.contains(&decl.name) => {
                    found.push(decl.name.clone());
                }
                DeclKind::Let(value) => stack.push((value, depth + 1)),
                DeclKind::Fn(f) => stack.push((&f.body, depth + 1)),
                _ => {}
            }
        }
        e.for_each_child(|c| stack.push((c, depth)));
    }
    Ok(found)
}

/// The declaration of the material `name`.
fn material_decl<'p>(
    program: &'p Program,
    name: &str,
) -> Result<&'p crate::sema::hir::Material, LowerError> {
    let (_, decl) = program
        .find(name)
        .ok_or_else(|| LowerError::new(format!("unknown material `{name}`")))?;
    let DeclKind::Material(m) = &decl.kind else {
        return Err(LowerError::new(format!("`{name}` is not a material")));
    };
    Ok(m)
}

/// Stand-ins for the field buffers of a material whose constants are evaluated outside an
/// element kernel (its density, the form of its W): the reads they give are never run.
fn placeholder_fields(program: &Program, material: &str) -> Result<Fields, LowerError> {
    Ok(material_fields(program, material)?
        .into_iter()
        .map(|f| (f, BufferId(u32::MAX)))
        .collect())
}

/// The buffers the element force kernel uses.
pub struct FemBuffers {
    /// Current node positions (node × 3).
    pub x: BufferId,
    /// G = Dm⁻¹·Dm⁻ᵀ's upper triangle and det Dm⁻¹ per element (element × 7, [`rest_shape`]).
    pub rest_shape: BufferId,
    /// Rest volume per element (element × 1).
    pub vol0: BufferId,
    /// Forces on the 4 corners per element, corner-major (element × 12).
    pub force: BufferId,
    /// Strain energy V₀·W per element (element × 1).
    pub energy: BufferId,
    /// Volume ratio J = det F per element (element × 1), for inversion checks.
    pub j: BufferId,
}

impl FemBuffers {
    pub fn declare(m: &mut Module) -> Self {
        let corners = m.order.element_nodes();
        let x = m.buffer("x", Domain::Node, 3, "node positions, m");
        let rest_shape = match m.order {
            crate::ir::ElementOrder::Linear => m.buffer(
                "rest_shape",
                Domain::Element,
                REST_SHAPE_WIDTH,
                "Dm^-1 Dm^-T (G00 G01 G02 G11 G12 G22, 1/m^2) and det Dm^-1 (1/m^3)",
            ),
            crate::ir::ElementOrder::Quadratic => m.buffer(
                "rest_shape",
                Domain::Element,
                super::quadratic::tet_rule().len() as u32 * super::quadratic::REST_PER_POINT,
                "per quadrature point: Dm^-1 Dm^-T (G00 G01 G02 G11 G12 G22, 1/m^2), \
                 det Dm^-1 (1/m^3) and its volume w*det Dm (m^3)",
            ),
        };
        FemBuffers {
            x,
            rest_shape,
            vol0: m.buffer("vol0", Domain::Element, 1, "rest volume, m^3"),
            force: m.buffer(
                "elem_force",
                Domain::Element,
                3 * corners,
                "internal force per corner, N",
            ),
            energy: m.buffer("elem_energy", Domain::Element, 1, "strain energy V0*W, J"),
            j: m.buffer("elem_j", Domain::Element, 1, "volume ratio det F"),
        }
    }
}

/// Values per element of the `rest_shape` buffer.
pub const REST_SHAPE_WIDTH: u32 = 7;

/// An element's row of the `rest_shape` buffer from its Dm⁻¹ (row-major): the upper triangle
/// of G = Dm⁻¹·Dm⁻ᵀ (G00, G01, G02, G11, G12, G22) and d = det Dm⁻¹, in f64 (a device in f32
/// rounds each once).
pub fn rest_shape(dm_inv: &[[f64; 3]; 3]) -> [f64; REST_SHAPE_WIDTH as usize] {
    let g = |r: usize, c: usize| (0..3).map(|k| dm_inv[r][k] * dm_inv[c][k]).sum::<f64>();
    let m = dm_inv;
    let det = m[0][0] * (m[1][1] * m[2][2] - m[1][2] * m[2][1])
        - m[0][1] * (m[1][0] * m[2][2] - m[1][2] * m[2][0])
        + m[0][2] * (m[1][0] * m[2][1] - m[1][1] * m[2][0]);
    [g(0, 0), g(0, 1), g(0, 2), g(1, 1), g(1, 2), g(2, 2), det]
}

/// Build the element force kernel of one material: the forces on its corners, nothing else
/// (the step runs it every step; see [`element_diagnostics_kernel`] for W and J).
pub fn element_force_kernel(
    program: &Program,
    module: &mut Module,
    material: &str,
) -> Result<crate::ir::BuiltKernel, LowerError> {
    element_kernel(program, module, material, false)
}

/// Build the element diagnostics kernel of one material: the strain energy V₀·W
/// (`elem_energy`) and the volume ratio J (`elem_j`) of each element at the current positions.
/// Not part of a step: the runtime runs it only where something reads them (a state check's
/// inversion test, a VTK frame), so the step's force kernel neither computes W nor stores
/// either (model only what is used).
pub fn element_diagnostics_kernel(
    program: &Program,
    module: &mut Module,
    material: &str,
) -> Result<crate::ir::BuiltKernel, LowerError> {
    element_kernel(program, module, material, true)
}

fn element_kernel(
    program: &Program,
    module: &mut Module,
    material: &str,
    diagnostics: bool,
) -> Result<crate::ir::BuiltKernel, LowerError> {
    if module.order == crate::ir::ElementOrder::Quadratic {
        return super::quadratic::element_kernel(program, module, material, diagnostics);
    }
    let bufs = FemBuffers::declare(module);
    let fields = declare_fields(program, module, material)?;
    let (name, origin) = if diagnostics {
        (
            format!("fem_{material}_diagnostics"),
            format!("material {material} (energy and J)"),
        )
    } else {
        (format!("fem_{material}"), format!("material {material}"))
    };
    let mut k = KernelBuilder::new(&name, Domain::Element, &origin);
    let xs = k.corner_vectors(bufs.x, 4);
    // G = Dm⁻¹·Dm⁻ᵀ (symmetric: its upper triangle is stored) and d = det Dm⁻¹.
    const UPPER: [[usize; 3]; 3] = [[0, 1, 2], [1, 3, 4], [2, 4, 5]];
    let g_row: Vec<V> = (0..6)
        .map(|c| {
            k.load(ArgSource::Own {
                buffer: bufs.rest_shape,
                component: c,
            })
        })
        .collect();
    let g: [[V; 3]; 3] = [0, 1, 2].map(|r| [0, 1, 2].map(|c| g_row[UPPER[r][c]]));
    let d = k.load(ArgSource::Own {
        buffer: bufs.rest_shape,
        component: 6,
    });
    let vol0 = k.load(ArgSource::Own {
        buffer: bufs.vol0,
        component: 0,
    });
    // Ds[r][c] = x_{c+1}[r] − x_0[r]
    let ds: [[V; 3]; 3] = [0, 1, 2].map(|r| [0, 1, 2].map(|c| k.b.sub(xs[c + 1][r], xs[0][r])));
    // The stress comes scaled by −V0 (folded into its scalar factors: three products per
    // element instead of nine), and times Dm⁻ᵀ: H = −V0 · P · Dm⁻ᵀ directly.
    let nv0 = k.b.neg(vol0);
    let (w, h, j) = energy_and_forces(program, &mut k, material, &ds, &g, d, &fields, nv0)?;
    if diagnostics {
        // The forces are dead code here: pruned when the kernel is finished.
        let e = k.b.mul(vol0, w);
        k.store(bufs.energy, 0, e);
        k.store(bufs.j, 0, j);
        return Ok(k.finish());
    }
    // Corner 0 takes minus the sum of the others (momentum balance); corner c+1 gets column c.
    for (d, row) in h.iter().enumerate() {
        let row_sum = k.b.sum(row);
        let f0 = k.b.neg(row_sum);
        k.store(bufs.force, d as u32, f0);
    }
    for c in 0..3u32 {
        for (d, row) in h.iter().enumerate() {
            k.store(bufs.force, 3 * (c + 1) + d as u32, row[c as usize]);
        }
    }
    Ok(k.finish())
}

fn matmul(b: &mut Builder, a: &[[V; 3]; 3], c: &[[V; 3]; 3]) -> [[V; 3]; 3] {
    [0, 1, 2].map(|r| {
        [0, 1, 2].map(|col| {
            let t: Vec<V> = (0..3).map(|k| b.mul(a[r][k], c[k][col])).collect();
            b.sum(&t)
        })
    })
}

fn transpose(a: &[[V; 3]; 3]) -> [[V; 3]; 3] {
    [0, 1, 2].map(|r| [0, 1, 2].map(|c| a[c][r]))
}

/// W, `scale` times H = P·Dm⁻ᵀ (P = ∂W/∂F, the first Piola–Kirchhoff stress) and J of a
/// material at edge matrix `ds`, from the rest shape G = Dm⁻¹·Dm⁻ᵀ (`g`) and d = det Dm⁻¹
/// (the module docs give the identities).
#[allow(clippy::too_many_arguments)]
pub(super) fn energy_and_forces(
    program: &Program,
    k: &mut KernelBuilder,
    material: &str,
    ds: &[[V; 3]; 3],
    g: &[[V; 3]; 3],
    d: V,
    fields: &Fields,
    scale: V,
) -> Result<(V, [[V; 3]; 3], V), LowerError> {
    let b = &mut k.b;
    // cof(Ds)[r][c] = Ds_{r+1,c+1} Ds_{r+2,c+2} − Ds_{r+1,c+2} Ds_{r+2,c+1}; cof F·Dm⁻ᵀ = d·cof Ds.
    let mut cof = [[V(0); 3]; 3];
    for (r, row) in cof.iter_mut().enumerate() {
        for (c, cell) in row.iter_mut().enumerate() {
            let (r1, r2) = ((r + 1) % 3, (r + 2) % 3);
            let (c1, c2) = ((c + 1) % 3, (c + 2) % 3);
            let p = b.mul(ds[r1][c1], ds[r2][c2]);
            let q = b.mul(ds[r1][c2], ds[r2][c1]);
            *cell = b.sub(p, q);
        }
    }
    let jt: Vec<V> = (0..3).map(|c| b.mul(ds[0][c], cof[0][c])).collect();
    let det_ds = b.sum(&jt);
    let j = b.mul(d, det_ds);
    // K = Ds·G = F·Dm⁻ᵀ; I1 = tr(F·Fᵀ) = Σ K∘Ds.
    let kk = matmul(b, ds, g);
    let i1t: Vec<V> = (0..9)
        .map(|e| b.mul(kk[e / 3][e % 3], ds[e / 3][e % 3]))
        .collect();
    let i1 = b.sum(&i1t);
    // Isochoric invariants only for a W written in them: a W of I1 = tr C and J (an
    // inversion-safe law) gets no J^(-2/3) factor, so it stays finite for J <= 0.
    let isochoric = material_is_isochoric(program, material)?;
    // b = F·Fᵀ = K·Dsᵀ (symmetric): tr C² = tr b², and F·C·Dm⁻ᵀ = b·K.
    let left_cg = matmul(b, &kk, &transpose(ds));
    let i2 = if isochoric {
        let i1sq = b.mul(i1, i1);
        let bb = matmul(b, &left_cg, &left_cg);
        let tr_bb = b.sum(&[bb[0][0], bb[1][1], bb[2][2]]);
        let diff = b.sub(i1sq, tr_bb);
        b.scale(0.5, diff)
    } else {
        b.constant(0.0)
    };

    // W as a function of independent I1, I2 and J (Ī1 = J^(−2/3)·I1 and Ī2 = J^(−4/3)·I2
    // written into it), simplified before it is differentiated: a coupled law's J^(2/3)·Ī1
    // is I1 there, so its stress is 2·W_I1·F + W_J·cof(F) with no isochoric terms that
    // cancel only in exact arithmetic. Then inlined at this element's invariants.
    let mut sub = KernelBuilder::new("W", Domain::Element, material);
    let inv = [sub.uniform("I1"), sub.uniform("I2"), sub.uniform("J")];
    let (i1b, i2b) = if isochoric {
        let j23 = sub.b.powf(inv[2], -2.0 / 3.0);
        let j43 = sub.b.powf(inv[2], -4.0 / 3.0);
        (sub.b.mul(j23, inv[0]), sub.b.mul(j43, inv[1]))
    } else {
        let zero = sub.b.constant(0.0);
        (zero, zero)
    };
    let w = material_energy(
        program,
        &mut sub,
        material,
        Invariants {
            i1: inv[0],
            i1b,
            i2b,
            j: inv[2],
        },
        fields,
    )?;
    let (sub_args, mut func) = sub.into_parts();
    func.outputs = vec![w];
    let func = crate::passes::simplify::simplify(&func);
    let w = func.outputs[0];
    // The invariants' values in the simplified body (an argument W does not read is added
    // back, and its derivative is zero).
    let mut sb = Builder::extend(func);
    let wrt = [0, 1, 2].map(|a| sb.arg(a));
    let (mut func, grad) = ad::gradient(sb.finish(), w, &wrt);
    func.outputs = vec![w, grad[0], grad[1], grad[2]];
    let outs = k.inline(&sub_args, &func, &[i1, i2, j]);
    let (w, wi1, wi2, wj) = (outs[0], outs[1], outs[2], outs[3]);
    let b = &mut k.b;

    let mut h = [[V(0); 3]; 3];
    let used = |b: &Builder, v: V| b.func.constant(v) != Some(0.0);
    // The factors 2 of ∂I1/∂F and ∂I2/∂F, the caller's scale and d go on the scalar
    // derivatives (the 2 exactly: a power of two), not on each of the nine components.
    let two_wi1 = b.scale(2.0, wi1);
    let two_wi2 = b.scale(2.0, wi2);
    let (two_wi1, two_wi2, wj) = (
        b.mul(scale, two_wi1),
        b.mul(scale, two_wi2),
        b.mul(scale, wj),
    );
    let wj_d = b.mul(wj, d);
    let bk = matmul(b, &left_cg, &kk);
    for r in 0..3 {
        for col in 0..3 {
            let mut terms = Vec::new();
            if used(b, wi1) {
                // W_I1 ∂I1/∂F·Dm⁻ᵀ = 2·W_I1·K
                terms.push(b.mul(two_wi1, kk[r][col]));
            }
            if used(b, wi2) {
                // W_I2 ∂I2/∂F·Dm⁻ᵀ = 2·W_I2·(I1 K − b K)
                let i1k = b.mul(i1, kk[r][col]);
                let s = b.sub(i1k, bk[r][col]);
                terms.push(b.mul(two_wi2, s));
            }
            if used(b, wj) {
                // W_J ∂J/∂F·Dm⁻ᵀ = W_J·d·cof(Ds)
                terms.push(b.mul(wj_d, cof[r][col]));
            }
            h[r][col] = b.sum(&terms);
        }
    }
    Ok((w, h, j))
}

/// The inverse of a 3×3 matrix of determinant `det` (≠ 0), row-major.
pub(super) fn inverse3(m: &[[f64; 3]; 3], det: f64) -> [[f64; 3]; 3] {
    let c = |r: usize, col: usize| {
        let (r1, r2) = ((r + 1) % 3, (r + 2) % 3);
        let (c1, c2) = ((col + 1) % 3, (col + 2) % 3);
        m[r1][c1] * m[r2][c2] - m[r1][c2] * m[r2][c1]
    };
    // inverse = cofactorᵀ / det
    [0, 1, 2].map(|r| [0, 1, 2].map(|col| c(col, r) / det))
}

/// The values a strain energy may read: I1 = tr(FᵀF), the isochoric Ī1, Ī2, and J.
#[derive(Clone, Copy, Debug)]
pub struct Invariants {
    pub i1: V,
    pub i1b: V,
    pub i2b: V,
    pub j: V,
}

/// Whether a material's W is written in the isochoric invariants (`I1bar`, `I2bar`); one
/// written in `I1` and `J` is not (the checker forbids mixing them) and is evaluated without
/// the J^(−2/3) factors, so it stays finite through inversion.
pub fn material_is_isochoric(program: &Program, material: &str) -> Result<bool, LowerError> {
    let mut k = KernelBuilder::new("W", Domain::Single, material);
    let fields = placeholder_fields(program, material)?;
    let (stmts, _) = material_body(program, &mut k, material, &fields)?;
    Ok(!stmts.iter().any(|s| match &s.kind {
        StmtKind::Energy { args, .. } => args.iter().any(|a| a == "I1"),
        _ => false,
    }))
}

/// Lower a material's strain energy at the given invariants; `fields` are the buffers of the
/// per-element params it reads ([`declare_fields`]).
pub fn material_energy(
    program: &Program,
    k: &mut KernelBuilder,
    material: &str,
    inv: Invariants,
    fields: &Fields,
) -> Result<V, LowerError> {
    let (stmts, env) = material_body(program, k, material, fields)?;
    let mut lw = ExprLowerer::new(program);
    lw.element_fields = fields.clone();
    let mut env = env;
    for s in stmts {
        match &s.kind {
            StmtKind::Let { name, value } => {
                let v = lw.lower(k, &env, value)?;
                env.insert(name.clone(), v);
            }
            StmtKind::Energy { args, body } => {
                for a in args {
                    let v = match a.as_str() {
                        "I1bar" => inv.i1b,
                        "I2bar" => inv.i2b,
                        "I1" => inv.i1,
                        _ => inv.j,
                    };
                    env.insert(a.clone(), LVal::S(v));
                }
                return lw.lower(k, &env, body)?.scalar();
            }
            _ => {}
        }
    }
    Err(LowerError::new(format!(
        "material `{material}` has no strain energy"
    )))
}

/// A material's density in kg/m³ (a constant).
pub fn material_density(program: &Program, material: &str) -> Result<f64, LowerError> {
    let mut k = KernelBuilder::new("density", Domain::Single, material);
    let fields = placeholder_fields(program, material)?;
    let (stmts, mut env) = material_body(program, &mut k, material, &fields)?;
    let mut lw = ExprLowerer::new(program);
    lw.element_fields = fields;
    for s in stmts {
        match &s.kind {
            StmtKind::Let { name, value } => {
                let v = lw.lower(&mut k, &env, value)?;
                env.insert(name.clone(), v);
            }
            StmtKind::Assign { name, value } if name == "density" => {
                let v = lw.lower(&mut k, &env, value)?.scalar()?;
                return k.b.func.constant(v).ok_or_else(|| {
                    LowerError::new(format!("the density of `{material}` must be a constant"))
                });
            }
            _ => {}
        }
    }
    Err(LowerError::new(format!(
        "material `{material}` has no density"
    )))
}

/// The statements of a material's body and the bindings of its template parameters.
fn material_body<'p>(
    program: &'p Program,
    k: &mut KernelBuilder,
    material: &str,
    fields: &Fields,
) -> Result<(&'p [Stmt], Env), LowerError> {
    match &material_decl(program, material)?.body {
        MaterialBody::Block(stmts) => Ok((stmts, Env::new())),
        MaterialBody::Instance(e) => {
            let ExprKind::Call {
                callee: Callee::Decl(t),
                args,
            } = &e.kind
            else {
                return Err(LowerError::new(
                    "a material is a call to a material template",
                ));
            };
            let template = program.decl(*t);
            let DeclKind::Material(tm) = &template.kind else {
                return Err(LowerError::new(format!(
                    "`{}` is not a material template",
                    template.name
                )));
            };
            let (Some(params), MaterialBody::Block(stmts)) = (&tm.params, &tm.body) else {
                return Err(LowerError::new(format!(
                    "`{}` is not a material template",
                    template.name
                )));
            };
            let ps: Vec<(&str, Option<&Expr>)> = params
                .iter()
                .map(|p| (p.name.as_str(), p.default.as_ref()))
                .collect();
            let mut lw = ExprLowerer::new(program);
            lw.element_fields = fields.clone();
            let env = lw.bind(k, &Env::new(), &ps, args)?;
            Ok((stmts, env))
        }
    }
}
