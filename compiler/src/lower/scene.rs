//! A scene's kernels: one element force kernel per material in use, one pressure kernel per
//! chamber with a pressure, and the node kernel that gathers forces and integrates. Only what
//! the scene uses is generated: no pressure code without chambers, damping and gravity folded
//! away when absent, constants folded into the code.

use super::LowerError;
use super::contact::{contact_kernels, node_contact_force, node_friction_force};
use super::expr::{Env, ExprLowerer, Program};
use super::fem::{
    FemBuffers, element_diagnostics_kernel, element_force_kernel, material_fields,
    material_is_isochoric,
};
use super::springs::{SpringBuffers, spring_force_kernel};
use crate::ir::{ArgSource, BufferId, CmpOp, Domain, ElementOrder, KernelBuilder, Module, V};
use crate::passes::adjoint::{Adjoint, adjoint};
use crate::passes::simplify::simplify_module;
use crate::passes::tangent::{JacobianPart, directional_derivative, force_jacobian};
use crate::sema::hir::{Callee, DeclKind, Expr, ExprKind, StmtKind, arg};

/// The module of a scene plus what the host needs to run it.
#[derive(Debug, Clone)]
pub struct SceneModule {
    pub module: Module,
    /// Materials in kernel order (element kernel `i` runs over the elements of material `i`).
    pub materials: Vec<String>,
    /// Chambers in kernel order (pressure kernel `i` runs over the triangles of chamber `i`).
    pub chambers: Vec<String>,
    /// The adjoint of a step: `module` followed by the reverse-step kernels.
    pub adjoint: Adjoint,
    /// `model = springs(…)`: the element kernels are spring-mesh kernels (they read the
    /// `edge_l0` buffer and write no `elem_energy`).
    pub springs: bool,
    /// Per material (kernel order): whether its elements may pass through inversion (a FEM
    /// material whose W is written in I1 and J, evaluated without isochoric factors); the
    /// runtime then stops only on non-finite values, not at J <= 0.
    pub inversion_safe: Vec<bool>,
    /// Per material (kernel order): the per-element params (fields) its constants read, each
    /// from the element buffer `param.NAME`. The runtime applies such a material only to
    /// elements of the field's set.
    pub material_fields: Vec<Vec<String>>,
    /// Per material (kernel order), FEM only: the kernel that writes `elem_energy` and `elem_j`
    /// at the current positions (after the step's kernels; the same index in `module` and in
    /// `adjoint.module`). The step's element kernels write forces only, so whatever reads
    /// energy or J (a state check, a VTK frame) runs these first. Empty for the spring mesh,
    /// whose step kernels write `elem_j` themselves.
    pub diagnostics: Vec<usize>,
    /// The buffers the host fills or reads, by role.
    pub buffers: SceneBuffers,
    /// `integrator = quasi_static`: the equilibrium solve's kernels.
    pub statics: Option<StaticKernels>,
    /// `contact … with …` statements: their buffers and the kernels that report them and
    /// limit Newton steps (the step limit serves static and implicit solves).
    pub contacts: Option<super::contact::Contacts>,
    /// Closed-loop control: the reductions over node or element sets that pressures and
    /// damping read; the kernels read sensor `i` as the uniforms `sensor.i.C`
    /// ([`ExprLowerer::sensors`]).
    pub sensors: Vec<Expr>,
}

/// The sim block's scope for its expressions: its lets, and the sensors found so far.
struct SimScope {
    lets: std::collections::HashMap<String, Expr>,
    sensors: Vec<Expr>,
}

impl SimScope {
    fn of(program: &Program) -> Self {
        SimScope {
            lets: program.sim_lets(),
            sensors: Vec::new(),
        }
    }

    /// A lowerer of the block's expressions; [`SimScope::keep`] takes its sensors back.
    fn lowerer<'p>(&mut self, program: &'p Program) -> ExprLowerer<'p> {
        let mut lw = ExprLowerer::new(program);
        lw.sim_lets = self.lets.clone();
        lw.sensors = Some(std::mem::take(&mut self.sensors));
        lw
    }

    fn keep(&mut self, lw: ExprLowerer) {
        self.sensors = lw.sensors.unwrap_or_default();
    }
}

/// The ids of the buffers the host fills or reads (resolved once, when the scene is lowered).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SceneBuffers {
    pub x: BufferId,
    pub v: BufferId,
    pub x_next: BufferId,
    pub v_next: BufferId,
    pub mass: BufferId,
    pub fixed: BufferId,
    pub vol0: BufferId,
    pub elem_force: BufferId,
    pub elem_j: BufferId,
    /// FEM only: G = Dm⁻¹·Dm⁻ᵀ and det Dm⁻¹ per element (rows from `fem::rest_shape`).
    pub rest_shape: Option<BufferId>,
    /// FEM only.
    pub elem_energy: Option<BufferId>,
    /// The spring mesh only.
    pub edge_l0: Option<BufferId>,
}

impl SceneBuffers {
    fn of(m: &Module) -> Result<SceneBuffers, LowerError> {
        let id = |n: &str| {
            m.buffer_named(n)
                .ok_or_else(|| LowerError::new(format!("the step has no buffer `{n}`")))
        };
        Ok(SceneBuffers {
            x: id("x")?,
            v: id("v")?,
            x_next: id("x_next")?,
            v_next: id("v_next")?,
            mass: id("mass")?,
            fixed: id("fixed")?,
            vol0: id("vol0")?,
            elem_force: id("elem_force")?,
            elem_j: id("elem_j")?,
            rest_shape: m.buffer_named("rest_shape"),
            elem_energy: m.buffer_named("elem_energy"),
            edge_l0: m.buffer_named("edge_l0"),
        })
    }
}

/// The element order a checked script's mesh declaration asks for: `load(…, order: 2)` is
/// quadratic, anything else (no `order`, `order: 1`) linear.
pub fn element_order(program: &Program) -> ElementOrder {
    let order = program.mesh().and_then(|mesh| match &mesh.kind {
        ExprKind::Call { args, .. } => hir_named(args, "order"),
        _ => None,
    });
    match order.map(|e| &e.kind) {
        // An order with a unit is refused by the checker.
        Some(ExprKind::Num(value)) if *value == 2.0 => ElementOrder::Quadratic,
        _ => ElementOrder::Linear,
    }
}

use crate::sema::hir::named_arg as hir_named;

/// Lower the scene described by a checked program.
pub fn lower_scene(program: &Program) -> Result<SceneModule, LowerError> {
    if !program.has_sim {
        return Err(LowerError::new("the script has no sim block"));
    }
    let sim = &program.sim;
    let integrator = (program.sim_setting("integrator"))
        .and_then(Expr::implicit_name)
        .unwrap_or("semi_implicit_euler");
    let quasi_static = integrator == "quasi_static";
    // Per-element params: one value per element of one set.
    for decl in program.user_decls() {
        if let DeclKind::Param(p) = &decl.kind
            && let Some(set) = p.field_set()
            && p.ty.shape().len() != 1
        {
            return Err(LowerError::new(format!(
                "the per-element param `{}` has more than one axis; a per-element param has \
                 exactly one, its element set (`{}[{}]`), and one scalar value per element",
                decl.name, decl.name, set
            )));
        }
    }
    let mut module = Module {
        order: element_order(program),
        ..Module::default()
    };
    let materials = scene_materials(program)?;
    let model = force_model(program)?;
    if module.order == ElementOrder::Quadratic && !matches!(model, ForceModel::Fem) {
        return Err(LowerError::new(
            "the spring mesh works on linear tetrahedra: use `model = fem` with `order: 2`, \
             or load the mesh with `order: 1`",
        ));
    }
    // The spring mesh declares its own buffers (no rest shape, no elem_energy).
    let x_buf = match model {
        ForceModel::Fem => FemBuffers::declare(&mut module).x,
        ForceModel::Springs { .. } => SpringBuffers::declare(&mut module).x,
    };
    let mut inversion_safe = Vec::new();
    let mut fields_of = Vec::new();
    let mut diagnostic_kernels = Vec::new();
    for m in &materials {
        fields_of.push(material_fields(program, m)?);
        let k = match model {
            ForceModel::Fem => {
                diagnostic_kernels.push(element_diagnostics_kernel(program, &mut module, m)?);
                element_force_kernel(program, &mut module, m)?
            }
            ForceModel::Springs { volume_stiffness } => {
                spring_force_kernel(program, &mut module, m, volume_stiffness)?
            }
        };
        module.push_kernel(k);
        // Only FEM evaluates W at the element's own J; the spring mesh inverts like any other.
        inversion_safe
            .push(matches!(model, ForceModel::Fem) && !material_is_isochoric(program, m)?);
    }

    let mut scope = SimScope::of(program);
    let mut chambers = Vec::new();
    let tri_force = module.buffer(
        "tri_force",
        Domain::Triangle,
        3 * module.order.triangle_nodes(),
        "pressure force per triangle corner, N",
    );
    for s in sim {
        if let StmtKind::Pressure { chamber, value } = &s.kind {
            module.push_kernel(pressure_kernel(
                program,
                module.order,
                x_buf,
                tri_force,
                chamber,
                value,
                quasi_static,
                &mut scope,
            )?);
            chambers.push(chamber.clone());
        }
    }
    if chambers.is_empty() {
        module.buffers.retain(|b| b.name != "tri_force");
    }
    // The diagnostics kernels follow the node kernel: not part of a step, and writing no buffer
    // a step reads, so the adjoint pass copies them (same indices) and derives nothing from them.
    let diagnostics;
    let contacts;
    let (mut adjoint, statics) = if quasi_static {
        let node = equilibrium_kernel(program, &mut module, !chambers.is_empty())?;
        module.push_kernel(node);
        diagnostics = push_all(&mut module, &mut diagnostic_kernels);
        contacts = contact_kernels(program, &mut module)?;
        simplify_module(&mut module);
        let mut adjoint = adjoint(&module, &[("x", "residual")], &[]).map_err(LowerError::new)?;
        let statics = StaticKernels::add(
            &mut adjoint.module,
            materials.len(),
            chambers.len(),
            false,
            contacts.is_some(),
        )?;
        (adjoint, Some(statics))
    } else if integrator == "implicit_euler" {
        let node = implicit_euler_kernel(program, &mut module, !chambers.is_empty(), &mut scope)?;
        module.push_kernel(node);
        diagnostics = push_all(&mut module, &mut diagnostic_kernels);
        contacts = contact_kernels(program, &mut module)?;
        simplify_module(&mut module);
        // The step's inputs besides the iterate x: the state it starts from. Their adjoints
        // (∂residual/∂x_prev, ∂residual/∂v_prev transposed) carry the gradient back a step;
        // the "next" buffers only pair them for the pass and are never written.
        for b in ["x_prev_next", "v_prev_next"] {
            module.buffer(
                b,
                Domain::Node,
                3,
                "unused: pairs a step input for the adjoint",
            );
        }
        let mut adjoint = adjoint(
            &module,
            &[
                ("x", "residual"),
                ("x_prev", "x_prev_next"),
                ("v_prev", "v_prev_next"),
            ],
            &[],
        )
        .map_err(LowerError::new)?;
        let statics = StaticKernels::add(
            &mut adjoint.module,
            materials.len(),
            chambers.len(),
            true,
            contacts.is_some(),
        )?;
        (adjoint, Some(statics))
    } else {
        let node = node_kernel(program, &mut module, !chambers.is_empty(), &mut scope)?;
        module.push_kernel(node);
        diagnostics = push_all(&mut module, &mut diagnostic_kernels);
        contacts = contact_kernels(program, &mut module)?;
        simplify_module(&mut module);
        let mut scale = Vec::new();
        if let Some(e) = program.optimize_setting("gradient_scale") {
            scale.push(("v", constant(program, e, "gradient_scale")?));
        }
        let adjoint = adjoint(&module, &[("x", "x_next"), ("v", "v_next")], &scale)
            .map_err(LowerError::new)?;
        (adjoint, None)
    };
    let buffers = SceneBuffers::of(&module)?;
    // Algebraic simplification and strength reduction: the forward kernels above were
    // simplified before the adjoint and the Jacobians differentiate them (so the coupled
    // neo-Hookean's J^(2/3)·Ī1 is I1 there too, and its adjoint needs no cube root); once more
    // now, the forward module and the adjoint module alike, so that the forward kernels at the
    // head of the adjoint module stay exactly the forward module's.
    simplify_module(&mut module);
    simplify_module(&mut adjoint.module);
    Ok(SceneModule {
        buffers,
        module,
        materials,
        chambers,
        adjoint,
        springs: !matches!(model, ForceModel::Fem),
        inversion_safe,
        material_fields: fields_of,
        diagnostics,
        statics,
        contacts,
        sensors: scope.sensors,
    })
}

/// Push `kernels` (emptied) onto `module`; their indices.
fn push_all(module: &mut Module, kernels: &mut Vec<crate::ir::BuiltKernel>) -> Vec<usize> {
    kernels.drain(..).map(|k| module.push_kernel(k)).collect()
}

/// What a quasi-static scene adds to its adjoint module: the force Jacobians a Newton solve
/// assembles. Its forward module's node kernel is [`equilibrium_kernel`] (no time step), its
/// adjoint is that of x ↦ residual, and the `load` uniform scales every load (continuation).
#[derive(Debug, Clone, PartialEq)]
pub struct StaticKernels {
    /// Net force on each node (node × 3), 0 at fixed nodes: equilibrium is residual = 0.
    pub residual: BufferId,
    /// Per material (kernel order): the kernel writing its elements' ∂f/∂x (element × 144).
    pub element_jacobians: Vec<usize>,
    pub elem_dforce: BufferId,
    /// Per chamber (kernel order): the kernel writing its triangles' ∂f/∂x (triangle × 81).
    pub chamber_jacobians: Vec<usize>,
    pub tri_dforce: Option<BufferId>,
    /// `integrator = implicit_euler`: the state a step starts from (node × 3 each).
    pub implicit: Option<ImplicitStep>,
    /// The residual's own dependence on each node's position (node × 9): inertia and damping
    /// of an implicit step, contact with obstacles. `None` where it has none.
    pub node_jacobian: Option<NodeJacobian>,
    /// What a matrix-free (Krylov) solve runs instead of assembling the tangent.
    pub matrix_free: MatrixFree,
}

/// The kernels of a matrix-free Newton–Krylov solve: the product of ∂r/∂x with a vector (a
/// directional derivative of the force and residual kernels, never the matrix) and the 3×3
/// diagonal blocks of ∂r/∂x for a block-Jacobi preconditioner.
#[derive(Debug, Clone, PartialEq)]
pub struct MatrixFree {
    /// The vector v (node × 3) the product is taken with.
    pub direction: BufferId,
    /// (∂r/∂x)·v (node × 3), 0 at fixed nodes.
    pub product: BufferId,
    /// Per material, then per chamber (kernel order): J_e·v of each entity's forces.
    pub element_products: Vec<usize>,
    pub chamber_products: Vec<usize>,
    /// Gathers those into `product`.
    pub node_product: usize,
    /// Per material, then per chamber: each corner's 3×3 block ∂f_c/∂x_c.
    pub element_blocks: Vec<usize>,
    pub elem_dblock: BufferId,
    pub chamber_blocks: Vec<usize>,
    pub tri_dblock: Option<BufferId>,
}

/// What a backward Euler step adds to the equilibrium machinery.
#[derive(Debug, Clone, PartialEq)]
pub struct ImplicitStep {
    pub x_prev: BufferId,
    pub v_prev: BufferId,
}

/// The kernel writing ∂residual_n/∂x_n of each node into `dforce` (node × 9).
#[derive(Debug, Clone, PartialEq)]
pub struct NodeJacobian {
    pub kernel: usize,
    pub dforce: BufferId,
}

impl StaticKernels {
    /// Append the Jacobian kernels of the forward kernels (materials, then chambers) to `m`.
    fn add(
        m: &mut Module,
        materials: usize,
        chambers: usize,
        implicit: bool,
        contact: bool,
    ) -> Result<Self, LowerError> {
        let id = |m: &Module, n: &str| {
            m.buffer_named(n)
                .ok_or_else(|| LowerError::new(format!("the solve has no buffer `{n}`")))
        };
        let (x, residual, elem_force) = (id(m, "x")?, id(m, "residual")?, id(m, "elem_force")?);
        let mut element_jacobians = Vec::new();
        for k in 0..materials {
            let built = force_jacobian(m, k, elem_force, x, "elem_dforce", JacobianPart::Full)
                .map_err(LowerError::new)?;
            element_jacobians.push(m.push_kernel(built));
        }
        let mut chamber_jacobians = Vec::new();
        let tri_dforce = if chambers > 0 {
            let tri_force = id(m, "tri_force")?;
            for c in 0..chambers {
                let built = force_jacobian(
                    m,
                    materials + c,
                    tri_force,
                    x,
                    "tri_dforce",
                    JacobianPart::Full,
                )
                .map_err(LowerError::new)?;
                chamber_jacobians.push(m.push_kernel(built));
            }
            m.buffer_named("tri_dforce")
        } else {
            None
        };
        let node_jacobian = if implicit || contact {
            let node = materials + chambers;
            let built = force_jacobian(m, node, residual, x, "node_dforce", JacobianPart::Full)
                .map_err(LowerError::new)?;
            Some(NodeJacobian {
                kernel: m.push_kernel(built),
                dforce: id(m, "node_dforce")?,
            })
        } else {
            None
        };
        let implicit = if implicit {
            Some(ImplicitStep {
                x_prev: id(m, "x_prev")?,
                v_prev: id(m, "v_prev")?,
            })
        } else {
            None
        };
        let matrix_free = MatrixFree::add(m, materials, chambers)?;
        Ok(StaticKernels {
            residual,
            element_jacobians,
            elem_dforce: id(m, "elem_dforce")?,
            chamber_jacobians,
            tri_dforce,
            implicit,
            node_jacobian,
            matrix_free,
        })
    }
}

impl MatrixFree {
    fn add(m: &mut Module, materials: usize, chambers: usize) -> Result<Self, LowerError> {
        let id = |m: &Module, n: &str| {
            m.buffer_named(n)
                .ok_or_else(|| LowerError::new(format!("the solve has no buffer `{n}`")))
        };
        let (x, residual, elem_force) = (id(m, "x")?, id(m, "residual")?, id(m, "elem_force")?);
        let tri_force = m.buffer_named("tri_force").filter(|_| chambers > 0);
        let direction = m.buffer(
            "dir",
            Domain::Node,
            3,
            "a vector v the tangent is multiplied with (Newton–Krylov), m",
        );
        let product = m.buffer("residual_dir", Domain::Node, 3, "(∂residual/∂x)·v, N");
        let elem_dir = m.buffer(
            "elem_force_dir",
            Domain::Element,
            3 * m.order.element_nodes(),
            "(∂elem_force/∂x)·v per element, N",
        );
        let tri_dir = tri_force.map(|_| {
            m.buffer(
                "tri_force_dir",
                Domain::Triangle,
                3 * m.order.triangle_nodes(),
                "(∂tri_force/∂x)·v per chamber triangle, N",
            )
        });
        let mut products = Vec::new();
        for k in 0..materials + chambers {
            let (force, out) = match (k < materials, tri_force.zip(tri_dir)) {
                (true, _) => (elem_force, elem_dir),
                (false, Some(pair)) => pair,
                (false, None) => return Err(LowerError::new("a chamber kernel without tri_force")),
            };
            let built =
                directional_derivative(m, k, &[(x, direction)], &[(force, out)], &["sensor."])
                    .map_err(LowerError::new)?;
            products.push(m.push_kernel(built));
        }
        let mut directions = vec![(x, direction), (elem_force, elem_dir)];
        directions.extend(tri_force.zip(tri_dir));
        let node = materials + chambers;
        let built =
            directional_derivative(m, node, &directions, &[(residual, product)], &["sensor."])
                .map_err(LowerError::new)?;
        let node_product = m.push_kernel(built);
        let mut blocks = Vec::new();
        for k in 0..materials + chambers {
            let (force, out) = match (k < materials, tri_force) {
                (true, _) => (elem_force, "elem_dblock"),
                (false, Some(f)) => (f, "tri_dblock"),
                (false, None) => return Err(LowerError::new("a chamber kernel without tri_force")),
            };
            let built = force_jacobian(m, k, force, x, out, JacobianPart::DiagonalBlocks)
                .map_err(LowerError::new)?;
            blocks.push(m.push_kernel(built));
        }
        let chamber_products = products.split_off(materials);
        let chamber_blocks = blocks.split_off(materials);
        Ok(MatrixFree {
            direction,
            product,
            element_products: products,
            chamber_products,
            node_product,
            element_blocks: blocks,
            elem_dblock: id(m, "elem_dblock")?,
            chamber_blocks,
            tri_dblock: m.buffer_named("tri_dblock"),
        })
    }
}

/// The materials a scene uses, in kernel order: as the sim block's `use` lines first name them,
/// or the script's one material when it has no `use`.
pub fn scene_materials(program: &Program) -> Result<Vec<String>, LowerError> {
    let mut materials: Vec<String> = Vec::new();
    for s in &program.sim {
        if let StmtKind::Use { material, .. } = &s.kind
            && !materials.contains(material)
        {
            materials.push(material.clone());
        }
    }
    if materials.is_empty() {
        let declared: Vec<&str> = (program.user_decls())
            .filter_map(|d| match &d.kind {
                DeclKind::Material(m) if m.params.is_none() => Some(d.name.as_str()),
                _ => None,
            })
            .collect();
        match declared.as_slice() {
            [one] => materials.push(one.to_string()),
            _ => return Err(LowerError::new("the sim block assigns no material")),
        }
    }
    Ok(materials)
}

/// The chambers with a pressure, in kernel order (the sim block's order).
pub fn scene_chambers(program: &Program) -> Vec<String> {
    (program.sim.iter())
        .filter_map(|s| match &s.kind {
            StmtKind::Pressure { chamber, .. } => Some(chamber.clone()),
            _ => None,
        })
        .collect()
}

/// The value of a constant setting.
pub(super) fn constant(program: &Program, e: &Expr, what: &str) -> Result<f64, LowerError> {
    let mut k = KernelBuilder::new("constant", Domain::Single, what);
    let v = ExprLowerer::new(program)
        .lower(&mut k, &Env::new(), e)?
        .scalar()?;
    k.b.func
        .constant(v)
        .ok_or_else(|| LowerError::new(format!("`{what}` must be a constant")))
}

/// The sim block's `model` setting.
enum ForceModel<'a> {
    Fem,
    Springs { volume_stiffness: &'a Expr },
}

fn force_model(program: &Program) -> Result<ForceModel<'_>, LowerError> {
    let Some(model) = program.sim_setting("model") else {
        return Ok(ForceModel::Fem);
    };
    match &model.kind {
        ExprKind::Name(n) if n.implicit() == Some("fem") => Ok(ForceModel::Fem),
        ExprKind::Call {
            callee: Callee::Builtin(f),
            args,
        } if f == "springs" => {
            let alpha = arg(args, "volume_stiffness", 0).ok_or_else(|| {
                    LowerError::new(
                        "`springs(…)` needs its volume stiffness, e.g. `springs(volume_stiffness: 1 kPa/mm)`",
                    )
                })?;
            Ok(ForceModel::Springs {
                volume_stiffness: alpha,
            })
        }
        _ => Err(LowerError::new(
            "`model` is `fem` or `springs(volume_stiffness: …)`",
        )),
    }
}

/// Follower pressure load (thesis eq. 2.15): each corner of a chamber triangle gets
/// p·A·n/3 = p/6 · (x1 − x0) × (x2 − x0), with triangles wound so the normal points into
/// the solid. The pressure expression is evaluated in the kernel (it depends on `t` and params).
#[allow(clippy::too_many_arguments)]
fn pressure_kernel(
    program: &Program,
    order: ElementOrder,
    x_buf: crate::ir::BufferId,
    tri_force: crate::ir::BufferId,
    chamber: &str,
    pressure: &Expr,
    load_factor: bool,
    scope: &mut SimScope,
) -> Result<crate::ir::BuiltKernel, LowerError> {
    let mut k = KernelBuilder::new(
        &format!("pressure_{chamber}"),
        Domain::Triangle,
        &format!("pressure {chamber}"),
    );
    let mut lw = scope.lowerer(program);
    let p = lw.lower(&mut k, &Env::new(), pressure);
    scope.keep(lw);
    let mut p = p?.scalar()?;
    if load_factor {
        let load = k.uniform("load");
        p = k.b.mul(load, p);
    }
    if order == ElementOrder::Quadratic {
        super::quadratic::store_pressure_forces(&mut k, x_buf, tri_force, p);
        return Ok(k.finish());
    }
    let xs = k.corner_vectors(x_buf, 3);
    let e1 = [0, 1, 2].map(|d| k.b.sub(xs[1][d], xs[0][d]));
    let e2 = [0, 1, 2].map(|d| k.b.sub(xs[2][d], xs[0][d]));
    let cross = |k: &mut KernelBuilder, i: usize, j: usize| {
        let a = k.b.mul(e1[i], e2[j]);
        let b = k.b.mul(e1[j], e2[i]);
        k.b.sub(a, b)
    };
    let n = [
        cross(&mut k, 1, 2),
        cross(&mut k, 2, 0),
        cross(&mut k, 0, 1),
    ];
    let p6 = k.b.scale(1.0 / 6.0, p);
    let f = n.map(|c| k.b.mul(p6, c));
    for corner in 0..3 {
        for (d, &fd) in f.iter().enumerate() {
            k.store(tri_force, 3 * corner + d as u32, fd);
        }
    }
    Ok(k.finish())
}

/// The `damping` rate in kernel `k` (it may follow a schedule or, closed-loop, a sensor).
fn damping_rate(
    program: &Program,
    k: &mut KernelBuilder,
    scope: &mut SimScope,
) -> Result<Option<V>, LowerError> {
    let Some(e) = program.sim_setting("damping") else {
        return Ok(None);
    };
    let mut lw = scope.lowerer(program);
    let beta = lw.lower(k, &Env::new(), e);
    scope.keep(lw);
    Ok(Some(beta?.scalar()?))
}

/// Semi-implicit Euler (thesis eq. 2.2 with mass damping eq. 2.17):
/// v' = (v + dt·(F/m − β·v + g))·(1 − fixed), x' = x + dt·v', F the gathered element and
/// pressure forces. Writes the next state into separate buffers: no state is overwritten
/// while it may still be read (the adjoint depends on that).
fn node_kernel(
    program: &Program,
    module: &mut Module,
    pressure: bool,
    scope: &mut SimScope,
) -> Result<crate::ir::BuiltKernel, LowerError> {
    let x = module.buffer("x", Domain::Node, 3, "node positions, m");
    let v = module.buffer("v", Domain::Node, 3, "node velocities, m/s");
    let x_next = module.buffer("x_next", Domain::Node, 3, "positions after the step, m");
    let v_next = module.buffer("v_next", Domain::Node, 3, "velocities after the step, m/s");
    let mass = module.buffer("mass", Domain::Node, 1, "lumped (scaled) mass, kg");
    let fixed = module.buffer("fixed", Domain::Node, 1, "1 for fixed nodes, else 0");
    let elem_force = module.buffer_named("elem_force").expect("declared");
    let tri_force = module.buffer_named("tri_force");
    let mut k = KernelBuilder::new("integrate", Domain::Node, "sim");
    let beta = damping_rate(program, &mut k, scope)?;
    let mut lw = ExprLowerer::new(program);
    let gravity = program.sim_setting("gravity");
    // Gravity acts on the physical mass: with `mass_scaling = s` the scaled inertia m·s
    // meets the force m·g, an acceleration g/s (the steady state does not depend on s).
    let scaling = match program.sim_setting("mass_scaling") {
        Some(e) => constant(program, e, "mass_scaling")?,
        None => 1.0,
    };
    let g = match gravity {
        Some(e) => {
            let g = super::expr::flatten(&lw.lower(&mut k, &Env::new(), e)?);
            let s = k.b.constant(scaling);
            Some(g.into_iter().map(|gd| k.b.div(gd, s)).collect::<Vec<_>>())
        }
        None => None,
    };
    let dt = k.uniform("dt");
    let m = k.load(ArgSource::Own {
        buffer: mass,
        component: 0,
    });
    let is_fixed = k.load(ArgSource::Own {
        buffer: fixed,
        component: 0,
    });
    let zero = k.b.constant(0.0);
    let free = k.b.cmp(CmpOp::Eq, is_fixed, zero);
    let (mut x_new, mut v_new) = ([zero; 3], [zero; 3]);
    let mut x_now = [zero; 3];
    for d in 0..3u32 {
        let f = gathered_force(&mut k, elem_force, tri_force.filter(|_| pressure), d);
        let xv = k.load(ArgSource::Own {
            buffer: x,
            component: d,
        });
        let vv = k.load(ArgSource::Own {
            buffer: v,
            component: d,
        });
        let mut a = k.b.div(f, m);
        if let Some(beta) = beta {
            let bv = k.b.mul(beta, vv);
            a = k.b.sub(a, bv);
        }
        if let Some(g) = &g {
            a = k.b.add(a, g[d as usize]);
        }
        let dv = k.b.mul(dt, a);
        let v1 = k.b.add(vv, dv);
        let v1 = k.b.select(free, v1, zero);
        let dx = k.b.mul(dt, v1);
        x_new[d as usize] = k.b.add(xv, dx);
        v_new[d as usize] = v1;
        x_now[d as usize] = xv;
    }
    // Contact is implicit in the positions: the predicted step is projected to where the
    // barrier's force balances the inertia of the normal correction.
    let state = super::contact::Predicted {
        x: x_now,
        x_new,
        v_new,
        mass: m,
        dt,
        free,
    };
    if let Some((x1, v1)) = super::contact::project_step(program, module, &mut k, state)? {
        (x_new, v_new) = (x1, v1);
    }
    for d in 0..3u32 {
        k.store(x_next, d, x_new[d as usize]);
        k.store(v_next, d, v_new[d as usize]);
    }
    Ok(k.finish())
}

/// The quasi-static counterpart of [`node_kernel`]: the net force on each free node,
/// residual = F_elements + F_pressure + load·m·g (0 at fixed nodes), with no time step. A
/// Newton solve drives it to zero; the adjoint of x ↦ residual gives the transposed
/// Jacobian-vector products and the ∂residual/∂param products the implicit-function adjoint
/// needs. `load` scales gravity as the pressure kernels scale pressure. The dynamic state
/// buffers are declared (the host fills them alike) but not used.
fn equilibrium_kernel(
    program: &Program,
    module: &mut Module,
    pressure: bool,
) -> Result<crate::ir::BuiltKernel, LowerError> {
    let x = module.buffer("x", Domain::Node, 3, "node positions, m");
    module.buffer(
        "v",
        Domain::Node,
        3,
        "node velocities, m/s (unused by a static solve)",
    );
    module.buffer("x_next", Domain::Node, 3, "unused by a static solve");
    module.buffer("v_next", Domain::Node, 3, "unused by a static solve");
    let mass = module.buffer("mass", Domain::Node, 1, "lumped mass, kg");
    let fixed = module.buffer("fixed", Domain::Node, 1, "1 for fixed nodes, else 0");
    let residual = module.buffer(
        "residual",
        Domain::Node,
        3,
        "net force on the node (0 at fixed nodes), N",
    );
    let elem_force = module.buffer_named("elem_force").expect("declared");
    let tri_force = module.buffer_named("tri_force");
    let mut k = KernelBuilder::new("equilibrium", Domain::Node, "sim");
    let mut lw = ExprLowerer::new(program);
    let g = match program.sim_setting("gravity") {
        Some(e) => Some(super::expr::flatten(&lw.lower(&mut k, &Env::new(), e)?)),
        None => None,
    };
    let is_fixed = k.load(ArgSource::Own {
        buffer: fixed,
        component: 0,
    });
    let zero = k.b.constant(0.0);
    let free = k.b.cmp(CmpOp::Eq, is_fixed, zero);
    let mg = g.map(|g| {
        let m = k.load(ArgSource::Own {
            buffer: mass,
            component: 0,
        });
        let load = k.uniform("load");
        let lm = k.b.mul(load, m);
        g.into_iter().map(|gd| k.b.mul(lm, gd)).collect::<Vec<_>>()
    });
    let contact = node_contact_force(program, module, &mut k, x)?;
    for d in 0..3u32 {
        let mut f = gathered_force(&mut k, elem_force, tri_force.filter(|_| pressure), d);
        if let Some(mg) = &mg {
            f = k.b.add(f, mg[d as usize]);
        }
        if let Some(c) = &contact {
            f = k.b.add(f, c[d as usize]);
        }
        let r = k.b.select(free, f, zero);
        k.store(residual, d, r);
    }
    Ok(k.finish())
}

/// Backward Euler (`integrator = implicit_euler`) as a residual: with the step's start state
/// (x_prev, v_prev) and the step h = dt, the end positions x solve
///   R(x) = F(x) + m·g/s − m·(x − x_prev − h·v_prev)/h² − β·m·(x − x_prev)/h = 0
/// on free nodes (m the scaled mass, as in [`node_kernel`]: gravity acts on the physical mass,
/// damping is mass-proportional); then v = (x − x_prev)/h. R is the negative gradient of the
/// incremental potential, so the same Newton solve and tangent as a static equilibrium serve,
/// the inertia adding m(1/h² + β/h) to the diagonal.
fn implicit_euler_kernel(
    program: &Program,
    module: &mut Module,
    pressure: bool,
    scope: &mut SimScope,
) -> Result<crate::ir::BuiltKernel, LowerError> {
    let x = module.buffer(
        "x",
        Domain::Node,
        3,
        "node positions (the step's iterate), m",
    );
    module.buffer("v", Domain::Node, 3, "node velocities, m/s");
    module.buffer("x_next", Domain::Node, 3, "unused by an implicit step");
    module.buffer("v_next", Domain::Node, 3, "unused by an implicit step");
    let x_prev = module.buffer(
        "x_prev",
        Domain::Node,
        3,
        "positions at the step's start, m",
    );
    let v_prev = module.buffer(
        "v_prev",
        Domain::Node,
        3,
        "velocities at the step's start, m/s",
    );
    let mass = module.buffer("mass", Domain::Node, 1, "lumped (scaled) mass, kg");
    let fixed = module.buffer("fixed", Domain::Node, 1, "1 for fixed nodes, else 0");
    let residual = module.buffer(
        "residual",
        Domain::Node,
        3,
        "backward Euler residual (0 at fixed nodes), N",
    );
    let elem_force = module.buffer_named("elem_force").expect("declared");
    let tri_force = module.buffer_named("tri_force");
    let mut k = KernelBuilder::new("implicit_euler", Domain::Node, "sim");
    let beta = damping_rate(program, &mut k, scope)?;
    let mut lw = ExprLowerer::new(program);
    let scaling = match program.sim_setting("mass_scaling") {
        Some(e) => constant(program, e, "mass_scaling")?,
        None => 1.0,
    };
    let g = match program.sim_setting("gravity") {
        Some(e) => Some(super::expr::flatten(&lw.lower(&mut k, &Env::new(), e)?)),
        None => None,
    };
    let h = k.uniform("dt");
    let m = k.load(ArgSource::Own {
        buffer: mass,
        component: 0,
    });
    let is_fixed = k.load(ArgSource::Own {
        buffer: fixed,
        component: 0,
    });
    let zero = k.b.constant(0.0);
    let free = k.b.cmp(CmpOp::Eq, is_fixed, zero);
    let h2 = k.b.mul(h, h);
    let contact = node_contact_force(program, module, &mut k, x)?;
    let friction = node_friction_force(program, module, &mut k, (x, x_prev))?;
    for d in 0..3u32 {
        let own = |k: &mut KernelBuilder, buffer| {
            k.load(ArgSource::Own {
                buffer,
                component: d,
            })
        };
        let (xd, xp, vp) = (own(&mut k, x), own(&mut k, x_prev), own(&mut k, v_prev));
        let mut f = gathered_force(&mut k, elem_force, tri_force.filter(|_| pressure), d);
        if let Some(c) = &contact {
            f = k.b.add(f, c[d as usize]);
        }
        if let Some(c) = &friction {
            f = k.b.add(f, c[d as usize]);
        }
        if let Some(g) = &g {
            let gs = k.b.scale(1.0 / scaling, g[d as usize]);
            let mg = k.b.mul(m, gs);
            f = k.b.add(f, mg);
        }
        let dx = k.b.sub(xd, xp);
        let hv = k.b.mul(h, vp);
        let miss = k.b.sub(dx, hv);
        let mm = k.b.mul(m, miss);
        let inertia = k.b.div(mm, h2);
        f = k.b.sub(f, inertia);
        if let Some(beta) = beta {
            let bm = k.b.mul(beta, m);
            let bmdx = k.b.mul(bm, dx);
            let damp = k.b.div(bmdx, h);
            f = k.b.sub(f, damp);
        }
        let r = k.b.select(free, f, zero);
        k.store(residual, d, r);
    }
    Ok(k.finish())
}

/// Component `d` of the force the elements (and, with `tri_force`, the chamber triangles) put
/// on a node, gathered over its incident entities in CSR order.
fn gathered_force(
    k: &mut KernelBuilder,
    elem_force: BufferId,
    tri_force: Option<BufferId>,
    d: u32,
) -> V {
    let f = k.load(ArgSource::Gather {
        buffer: elem_force,
        over: Domain::Element,
        stride: 3,
        component: d,
    });
    match tri_force {
        Some(tf) => {
            let fp = k.load(ArgSource::Gather {
                buffer: tf,
                over: Domain::Triangle,
                stride: 3,
                component: d,
            });
            k.b.add(f, fp)
        }
        None => f,
    }
}
