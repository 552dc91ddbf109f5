//! The spring-mesh model (thesis §2.3.1 and §2.5): every mesh edge is a spring whose stiffness
//! follows the material's stress–strain curve, plus a volume-conservation force per tet.
//!
//! Edge i with rest length l₀ and current length l has stiffness (eq. 2.3)
//!
//!   kᵢ = E(λ) · V₀ / l₀²,   λ = l / l₀,
//!
//! V₀ the rest volume of all tets that share the edge, and pulls its two nodes together with
//! |f| = kᵢ·(l − l₀) (eq. 2.4–2.5). E(λ) = dP/dλ is the slope of the material's nominal
//! stress–strain curve in incompressible uniaxial tension (eq. 2.6–2.7: λ₁ = λ, λ₂ = λ₃ = λ^(−½),
//! so Ī1 = λ² + 2/λ, Ī2 = 2λ + 1/λ², J = 1, and P = dW/dλ): the compiler differentiates W twice.
//!
//! No new domain is needed: since V₀ is a sum over the edge's tets, each tet adds the spring
//! force of its own six edges with its own volume, E(λ)·V_tet/l₀²·(l − l₀); summed over the tets
//! of an edge this is exactly eq. 2.3–2.4 (and an edge between two materials gets each side's
//! curve weighted by its volume). Node forces gather through the element CSR as for FEM.
//!
//! The volume-conservation force (eq. 2.16) on corner n of a tet with current volume V is
//! α·(V − V₀)·(x_BC − xₙ)/‖x_BC − xₙ‖, x_BC the tet's barycentre and α the `volume_stiffness`.

use super::LowerError;
use super::expr::{Env, ExprLowerer, Program};
use super::fem::{Invariants, declare_fields, material_energy};
use crate::ir::{ArgSource, BufferId, Domain, KernelBuilder, Module, V, ad};
use crate::sema::hir::Expr;

/// The six edges of a tet as corner pairs, in the order of the `edge_l0` buffer.
pub const TET_EDGES: [(u32, u32); 6] = [(0, 1), (0, 2), (0, 3), (1, 2), (1, 3), (2, 3)];

/// The buffers of the spring-mesh kernels (the same names as FEM's where they agree; no
/// `rest_shape` and no `elem_energy`: these forces derive from no energy).
pub struct SpringBuffers {
    pub x: BufferId,
    pub vol0: BufferId,
    /// Rest length of the six edges per element (element × 6, [`TET_EDGES`] order).
    pub edge_l0: BufferId,
    pub force: BufferId,
    pub j: BufferId,
}

impl SpringBuffers {
    pub fn declare(m: &mut Module) -> Self {
        SpringBuffers {
            x: m.buffer("x", Domain::Node, 3, "node positions, m"),
            vol0: m.buffer("vol0", Domain::Element, 1, "rest volume, m^3"),
            edge_l0: m.buffer(
                "edge_l0",
                Domain::Element,
                6,
                "rest length of each tet edge (01 02 03 12 13 23), m",
            ),
            force: m.buffer(
                "elem_force",
                Domain::Element,
                12,
                "internal force per corner, N",
            ),
            j: m.buffer("elem_j", Domain::Element, 1, "volume ratio det F"),
        }
    }
}

/// The element kernel of the spring mesh for one material; `alpha` is the volume stiffness
/// expression (force per volume, a constant or a param).
pub fn spring_force_kernel(
    program: &Program,
    module: &mut Module,
    material: &str,
    alpha: &Expr,
) -> Result<crate::ir::BuiltKernel, LowerError> {
    let bufs = SpringBuffers::declare(module);
    let fields = declare_fields(program, module, material)?;
    let l0_buf = bufs.edge_l0;
    let mut k = KernelBuilder::new(
        &format!("springs_{material}"),
        Domain::Element,
        &format!("material {material} (spring mesh)"),
    );
    let mut lw = ExprLowerer::new(program);
    let alpha = lw.lower(&mut k, &Env::new(), alpha)?.scalar()?;

    // E(λ) as a function of one argument: W along incompressible uniaxial tension,
    // differentiated twice.
    let mut sub = KernelBuilder::new("E", Domain::Element, material);
    let lam = sub.uniform("lambda");
    let b = &mut sub.b;
    let one = b.constant(1.0);
    let lam2 = b.mul(lam, lam);
    let inv_lam = b.div(one, lam);
    let two_inv = b.scale(2.0, inv_lam);
    let i1b = b.add(lam2, two_inv);
    let two_lam = b.scale(2.0, lam);
    let inv_lam2 = b.mul(inv_lam, inv_lam);
    let i2b = b.add(two_lam, inv_lam2);
    let w = material_energy(
        program,
        &mut sub,
        material,
        Invariants {
            i1: i1b,
            i1b,
            i2b,
            j: one,
        },
        &fields,
    )?;
    let (sub_args, func) = sub.into_parts();
    let (func, dw) = ad::gradient(func, w, &[lam]);
    let (mut func, d2w) = ad::gradient(func, dw[0], &[lam]);
    func.outputs = vec![d2w[0]];

    let xs = k.corner_vectors(bufs.x, 4);
    let vol0 = k.load(ArgSource::Own {
        buffer: bufs.vol0,
        component: 0,
    });
    let zero = k.b.constant(0.0);
    let mut f = [[zero; 3]; 4];
    for (e, &(a, c)) in TET_EDGES.iter().enumerate() {
        let l0 = k.load(ArgSource::Own {
            buffer: l0_buf,
            component: e as u32,
        });
        let (a, c) = (a as usize, c as usize);
        let d = [0, 1, 2].map(|i| k.b.sub(xs[c][i], xs[a][i]));
        let sq: Vec<V> = d.iter().map(|&x| k.b.mul(x, x)).collect();
        let l2 = k.b.sum(&sq);
        let l = k.b.un(crate::ir::UnOp::Sqrt, l2);
        let lambda = k.b.div(l, l0);
        let stiff = k.inline(&sub_args, &func, &[lambda])[0];
        // s = E·V/l0² · (l − l0) / l: the force on `a` is s·(x_c − x_a), on `c` its negative.
        let l0sq = k.b.mul(l0, l0);
        let kv = k.b.mul(stiff, vol0);
        let ke = k.b.div(kv, l0sq);
        let dl = k.b.sub(l, l0);
        let t = k.b.mul(ke, dl);
        let s = k.b.div(t, l);
        for i in 0..3 {
            let fi = k.b.mul(s, d[i]);
            f[a][i] = k.b.add(f[a][i], fi);
            f[c][i] = k.b.sub(f[c][i], fi);
        }
    }
    // Current volume V = det(Ds)/6 and J = V/V0.
    let ds: [[V; 3]; 3] = [0, 1, 2].map(|r| [0, 1, 2].map(|c| k.b.sub(xs[c + 1][r], xs[0][r])));
    let b = &mut k.b;
    let mut cof = [V(0); 3];
    for (c, cell) in cof.iter_mut().enumerate() {
        let (c1, c2) = ((c + 1) % 3, (c + 2) % 3);
        let p = b.mul(ds[1][c1], ds[2][c2]);
        let q = b.mul(ds[1][c2], ds[2][c1]);
        *cell = b.sub(p, q);
    }
    let dt: Vec<V> = (0..3).map(|c| b.mul(ds[0][c], cof[c])).collect();
    let det = b.sum(&dt);
    let vol = b.scale(1.0 / 6.0, det);
    let j = b.div(vol, vol0);
    // Volume conservation (eq. 2.16).
    let dv = b.sub(vol, vol0);
    let g = b.mul(alpha, dv);
    let bc = [0, 1, 2].map(|i| {
        let s = b.sum(&[xs[0][i], xs[1][i], xs[2][i], xs[3][i]]);
        b.scale(0.25, s)
    });
    for (n, fnode) in f.iter_mut().enumerate() {
        let r = [0, 1, 2].map(|i| b.sub(bc[i], xs[n][i]));
        let sq: Vec<V> = r.iter().map(|&x| b.mul(x, x)).collect();
        let r2 = b.sum(&sq);
        let rl = b.un(crate::ir::UnOp::Sqrt, r2);
        let gr = b.div(g, rl);
        for i in 0..3 {
            let fi = b.mul(gr, r[i]);
            fnode[i] = b.add(fnode[i], fi);
        }
    }
    for (c, fc) in f.iter().enumerate() {
        for (d, &v) in fc.iter().enumerate() {
            k.store(bufs.force, 3 * c as u32 + d as u32, v);
        }
    }
    k.store(bufs.j, 0, j);
    Ok(k.finish())
}
