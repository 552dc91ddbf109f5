//! Frictionless contact of the mesh's surface nodes with rigid obstacles (SPEC §6.7), as a
//! smooth barrier energy in the node kernels, so that static and implicit solves stay energy
//! minimizations and their tangents, adjoints and Jacobian products come from the same passes;
//! explicit steps solve the same barrier implicitly for each node's normal motion
//! ([`project_step`]), after a closed-form test of each node's path over the step against the
//! obstacle ([`stop_at_entry`]: no node crosses a thin obstacle in one step).
//!
//! Node n of contact i (its lumped boundary area A_n > 0, filled by the host in the buffer
//! `contact_area.i`) at signed distance d from obstacle i gets the energy κ_n·b(d) of IPC's
//! clamped log barrier (Li et al. 2020), with gap ĝ:
//!
//!   b(d) = −(d − ĝ)²·ln(d/ĝ) for 0 < d < ĝ, 0 beyond;   κ_n = k·A_n/ĝ,
//!
//! k the contact stiffness (a pressure: the uniform `contact.i.stiffness`). Its force is
//! −κ_n·b'(d)·∇d = k·A_n·g(d/ĝ)·∇d with g(r) = (1 − r)(1/r − 1 − 2 ln r): the contact pressure
//! at gap d is k·g(d/ĝ), zero and flat at d = ĝ (b is C² there), unbounded as d → 0.
//! Obstacles: a plane, d = n̂·(x − p), ∇d = n̂; a sphere, d = ‖x − c‖ − r, ∇d = (x − c)/‖x − c‖;
//! an axis-aligned box and a capped cylinder, the signed distance to a convex solid
//! ([`solid_distance`]: the Euclidean distance outside, minus the depth to the nearest face
//! inside; outside it is C¹ with rounded edges). Every distance is convex in x, so
//! d(x + α·v) ≥ d(x) + α·∇d·v: the step limit [`step_kernel`] computes from that line is
//! conservative.

use super::LowerError;
use super::expr::{Env, ExprLowerer, Program, flatten};
use crate::ir::{ArgSource, BinOp, BufferId, CmpOp, Domain, KernelBuilder, Module, UnOp, V};
use crate::sema::hir::{Callee, DeclKind, Expr, ExprKind, StmtKind, arg};

/// The fraction of the linearized distance to an obstacle a Newton step may cover.
pub const STEP_FRACTION: f64 = 0.8;

/// The step limit where no obstacle limits a node (finite: WGSL has no infinity literal).
pub const NO_LIMIT: f64 = 1e30;

/// The uniform holding statement `i`'s contact stiffness k (Pa), which the host sets.
pub fn stiffness_uniform(i: usize) -> String {
    format!("contact.{i}.stiffness")
}

/// One `contact BODY with OBSTACLE` statement, as the host needs it.
#[derive(Debug, Clone, PartialEq)]
pub struct Contact {
    pub body: String,
    pub obstacle: String,
    /// ĝ, m.
    pub gap: f64,
    /// k as written (Pa); `None`: the host estimates it from the materials.
    pub stiffness: Option<f64>,
    /// Node × 1: the lumped boundary area of each contact node (m²), 0 for other nodes.
    pub area: BufferId,
    /// The uniform holding k.
    pub stiffness_uniform: String,
    /// Node × 3 and node × 1: each node's contact force (N) and signed distance (m), written
    /// by `report_kernel` (an index in the scene's module and in its adjoint module).
    pub force: BufferId,
    pub distance: BufferId,
    pub report_kernel: usize,
}

/// The contacts of a scene and the kernel limiting Newton steps to stay clear of obstacles.
#[derive(Debug, Clone, PartialEq)]
pub struct Contacts {
    pub pairs: Vec<Contact>,
    /// Node × 3: the step v a position update x + α·v takes (the host fills it).
    pub step: BufferId,
    /// Node × 1: the largest α that keeps each contact node clear ([`NO_LIMIT`] where none limits it).
    pub step_limit: BufferId,
    pub step_kernel: usize,
}

/// A `contact` statement's body, as binding to the mesh needs it.
#[derive(Debug, Clone, PartialEq)]
pub struct ContactBody {
    /// The mesh or a node set.
    pub body: String,
}

/// The contact nodes of one statement (node indices, ascending) and the lumped boundary area of
/// each (m²), as binding to the mesh finds them; the host fills `contact_area.i` from them and
/// `force(…)` in the loss sums over them.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct ContactNodes {
    pub nodes: Vec<u32>,
    pub areas: Vec<f64>,
}

/// The bodies of the scene's `contact` statements, in order.
pub fn bodies(program: &Program) -> Vec<ContactBody> {
    (program.sim.iter())
        .filter_map(|s| match &s.kind {
            StmtKind::Contact { body, .. } => Some(ContactBody { body: body.clone() }),
            _ => None,
        })
        .collect()
}

/// The total force (N) obstacle `obstacle` exerts through its statements' contact nodes at the
/// positions `state.x.N.d` (the loss's reading of the node state): `force(OBSTACLE)`, or with
/// `on` only through the contact nodes in that set: `force(OBSTACLE, on: SET)`.
pub fn total_force(
    program: &Program,
    k: &mut KernelBuilder,
    obstacle: &str,
    nodes: &[ContactNodes],
    on: Option<&std::collections::HashSet<u32>>,
) -> Result<[V; 3], LowerError> {
    let zero = k.b.constant(0.0);
    let mut total = [zero; 3];
    let statements = statements(program)?;
    if !statements.iter().any(|st| st.obstacle == obstacle) {
        return Err(LowerError::new(format!(
            "`force({obstacle})` is always zero: the sim block has no `contact … with {obstacle}`"
        )));
    }
    for (i, st) in statements.iter().enumerate() {
        if st.obstacle != obstacle {
            continue;
        }
        let set = nodes
            .get(i)
            .ok_or_else(|| LowerError::new("a contact without its nodes"))?;
        for (&n, &a) in set.nodes.iter().zip(&set.areas) {
            if on.is_some_and(|members| !members.contains(&n)) {
                continue;
            }
            let pos = [0, 1, 2].map(|d| k.uniform(&format!("state.x.{n}.{d}")));
            let area = k.b.constant(a);
            let (f, _) = barrier(program, k, i, st, pos, area)?;
            total = [0, 1, 2].map(|d| k.b.add(total[d], f[d]));
        }
    }
    Ok(total)
}

/// A statement's shape before lowering: what the node kernels need.
struct Statement<'p> {
    shape: &'p Expr,
    gap: f64,
    stiffness: Option<f64>,
    /// Coulomb's coefficient μ (explicit runs; sema refuses it elsewhere).
    friction: Option<f64>,
    body: String,
    obstacle: String,
}

fn statements(program: &Program) -> Result<Vec<Statement<'_>>, LowerError> {
    let mut out = Vec::new();
    for s in &program.sim {
        let StmtKind::Contact {
            body,
            obstacle,
            args,
        } = &s.kind
        else {
            continue;
        };
        let shape = (program.find(obstacle))
            .and_then(|(_, d)| match &d.kind {
                DeclKind::Obstacle(e) => Some(e),
                _ => None,
            })
            .ok_or_else(|| LowerError::new(format!("`{obstacle}` is not an obstacle")))?;
        let number = |name: &str, i: usize| -> Result<Option<f64>, LowerError> {
            arg(args, name, i)
                .map(|e| match &e.kind {
                    ExprKind::Num(v) => Ok(*v),
                    _ => super::scene::constant(program, e, name),
                })
                .transpose()
        };
        let gap = number("gap", 0)?.ok_or_else(|| LowerError::new("`contact` needs its `gap`"))?;
        out.push(Statement {
            shape,
            gap,
            stiffness: number("stiffness", 1)?,
            friction: number("friction", 2)?.filter(|&mu| mu > 0.0),
            body: body.clone(),
            obstacle: obstacle.clone(),
        });
    }
    Ok(out)
}

fn area_buffer(module: &mut Module, i: usize) -> BufferId {
    module.buffer(
        &format!("contact_area.{i}"),
        Domain::Node,
        1,
        "lumped boundary area of each contact node (0 elsewhere), m^2",
    )
}

/// An obstacle's shape: its name and its arguments, lowered on demand.
struct Shape<'p> {
    name: &'p str,
    args: &'p [crate::sema::hir::Arg],
    lowerer: ExprLowerer<'p>,
}

impl<'p> Shape<'p> {
    fn of(program: &'p Program, shape: &'p Expr) -> Result<Self, LowerError> {
        let ExprKind::Call {
            callee: Callee::Builtin(name),
            args,
        } = &shape.kind
        else {
            return Err(LowerError::new(
                "an obstacle is `plane(…)`, `sphere(…)`, `box(…)` or `cylinder(…)`",
            ));
        };
        Ok(Shape {
            name,
            args,
            lowerer: ExprLowerer::new(program),
        })
    }

    /// The components of argument `pname` (at position `i`).
    fn vector(
        &mut self,
        k: &mut KernelBuilder,
        pname: &str,
        i: usize,
    ) -> Result<Vec<V>, LowerError> {
        let e = arg(self.args, pname, i)
            .ok_or_else(|| LowerError::new(format!("the obstacle has no `{pname}`")))?;
        Ok(flatten(&self.lowerer.lower(k, &Env::new(), e)?))
    }
}

/// An obstacle's signed distance d and its gradient ∇d at the node position `x`.
fn distance(
    program: &Program,
    k: &mut KernelBuilder,
    shape: &Expr,
    x: [V; 3],
) -> Result<(V, [V; 3]), LowerError> {
    let mut shape = Shape::of(program, shape)?;
    let name = shape.name;
    let mut vector = |k: &mut KernelBuilder, pname: &str, i: usize| shape.vector(k, pname, i);
    let tiny = k.b.constant(1e-30);
    match name {
        "plane" => {
            let p = vector(k, "point", 0)?;
            let n = vector(k, "normal", 1)?;
            let len = norm(k, &n);
            let unit = [0, 1, 2].map(|d| k.b.div(n[d], len));
            let r = [0, 1, 2].map(|d| k.b.sub(x[d], p[d]));
            Ok((dot(k, unit, r), unit))
        }
        "sphere" => {
            let c = vector(k, "center", 0)?;
            let r = vector(k, "radius", 1)?[0];
            let rel = [0, 1, 2].map(|d| k.b.sub(x[d], c[d]));
            let rho = norm(k, &rel);
            let rho = k.b.bin(BinOp::Max, rho, tiny);
            let grad = rel.map(|c| k.b.div(c, rho));
            Ok((k.b.sub(rho, r), grad))
        }
        "box" => {
            let lo = vector(k, "min", 0)?;
            let hi = vector(k, "max", 1)?;
            // Per axis: the side of the centre the node is on, and its excess over the half
            // size.
            let axes = [0, 1, 2].map(|d| {
                let mid = k.b.add(lo[d], hi[d]);
                let mid = k.b.scale(0.5, mid);
                let half = k.b.sub(hi[d], lo[d]);
                let half = k.b.scale(0.5, half);
                let rel = k.b.sub(x[d], mid);
                let a = k.b.un(UnOp::Abs, rel);
                (sign(k, rel), k.b.sub(a, half))
            });
            let (d, g) = solid_distance(k, &axes.map(|(_, q)| q));
            let grad = [0, 1, 2].map(|a| k.b.mul(axes[a].0, g[a]));
            Ok((d, grad))
        }
        "cylinder" => {
            let (a, unit, len, r) = cylinder_frame(k, &mut vector)?;
            // Axial position from the middle, radial vector and its length.
            let rel = [0, 1, 2].map(|d| k.b.sub(x[d], a[d]));
            let along = dot(k, unit, rel);
            let half = k.b.scale(0.5, len);
            let from_mid = k.b.sub(along, half);
            let radial = [0, 1, 2].map(|d| {
                let on_axis = k.b.mul(along, unit[d]);
                k.b.sub(rel[d], on_axis)
            });
            let rho = norm(k, &radial);
            let rho_safe = k.b.bin(BinOp::Max, rho, tiny);
            let out_radially = k.b.sub(rho, r);
            let axial = k.b.un(UnOp::Abs, from_mid);
            let out_axially = k.b.sub(axial, half);
            let (d, g) = solid_distance(k, &[out_radially, out_axially]);
            let end_side = sign(k, from_mid);
            let g_axis = k.b.mul(g[1], end_side);
            let grad = [0, 1, 2].map(|d| {
                let towards = k.b.div(radial[d], rho_safe);
                let radial_part = k.b.mul(g[0], towards);
                let axial_part = k.b.mul(g_axis, unit[d]);
                k.b.add(radial_part, axial_part)
            });
            Ok((d, grad))
        }
        other => Err(LowerError::new(format!(
            "`{other}(…)` is not an obstacle shape"
        ))),
    }
}

/// Where a node's straight path x₀ + t·v (t ∈ [0, 1], one explicit step) first enters an
/// obstacle inflated by `rho`, as explicit contact's collision detection needs it: `hit` (1 where
/// the path enters within the step, else 0), the entry's t and the inflated shape's outward
/// normal there. `None` for a plane: a half-space cannot be passed through, the projection
/// brings back a node from any depth. A box inflates to a box, a cylinder to a capped cylinder
/// of radius and half-length grown by `rho`, a sphere to a sphere; each is the intersection of
/// convex pieces (slabs, an infinite cylinder, a ball) whose entry and exit parameters along the
/// line are closed-form (linear or quadratic), so the test is O(1) per node: the path enters at
/// the last of the pieces' entries if that comes before the first of their exits.
fn swept_entry(
    program: &Program,
    k: &mut KernelBuilder,
    shape: &Expr,
    (x0, v): ([V; 3], [V; 3]),
    rho: V,
) -> Result<Option<SweptEntry>, LowerError> {
    let mut shape = Shape::of(program, shape)?;
    let name = shape.name;
    let mut vector = |k: &mut KernelBuilder, pname: &str, i: usize| shape.vector(k, pname, i);
    let pieces = match name {
        "plane" => return Ok(None),
        "box" => {
            let lo = vector(k, "min", 0)?;
            let hi = vector(k, "max", 1)?;
            (0..3)
                .map(|a| {
                    let lo = k.b.sub(lo[a], rho);
                    let hi = k.b.add(hi[a], rho);
                    let axis = std::array::from_fn(|d| if d == a { 1.0 } else { 0.0 });
                    let axis = axis.map(|c| k.b.constant(c));
                    slab_crossing(&mut k.b, (x0[a], v[a]), (lo, hi), axis)
                })
                .collect::<Vec<_>>()
        }
        "sphere" => {
            let c = vector(k, "center", 0)?;
            let r = vector(k, "radius", 1)?[0];
            let radius = k.b.add(r, rho);
            let rel = [0, 1, 2].map(|d| k.b.sub(x0[d], c[d]));
            vec![ball_crossing(&mut k.b, rel, v, radius)]
        }
        "cylinder" => {
            let (a, unit, len, r) = cylinder_frame(k, &mut vector)?;
            let half = k.b.scale(0.5, len);
            let mid = [0, 1, 2].map(|d| {
                let h = k.b.mul(half, unit[d]);
                k.b.add(a[d], h)
            });
            let rel = [0, 1, 2].map(|d| k.b.sub(x0[d], mid[d]));
            let along = dot(k, unit, rel);
            let speed_along = dot(k, unit, v);
            let across = |k: &mut KernelBuilder, w: [V; 3], s: V| {
                [0, 1, 2].map(|d| {
                    let on_axis = k.b.mul(s, unit[d]);
                    k.b.sub(w[d], on_axis)
                })
            };
            let rel_across = across(k, rel, along);
            let v_across = across(k, v, speed_along);
            let radius = k.b.add(r, rho);
            let reach = k.b.add(half, rho);
            let low = k.b.neg(reach);
            vec![
                ball_crossing(&mut k.b, rel_across, v_across, radius),
                slab_crossing(&mut k.b, (along, speed_along), (low, reach), unit),
            ]
        }
        other => {
            return Err(LowerError::new(format!(
                "`{other}(…)` is not an obstacle shape"
            )));
        }
    };
    let b = &mut k.b;
    let mut enter = pieces[0].enter;
    let mut leave = pieces[0].leave;
    let mut normal = pieces[0].normal;
    for p in &pieces[1..] {
        let later = b.cmp(CmpOp::Gt, p.enter, enter);
        normal = [0, 1, 2].map(|d| b.select(later, p.normal[d], normal[d]));
        enter = b.bin(BinOp::Max, enter, p.enter);
        leave = b.bin(BinOp::Min, leave, p.leave);
    }
    let (zero, one) = (b.constant(0.0), b.constant(1.0));
    let crosses = b.cmp(CmpOp::Le, enter, leave);
    let after_start = b.cmp(CmpOp::Ge, enter, zero);
    let within_step = b.cmp(CmpOp::Le, enter, one);
    let hit = b.mul(crosses, after_start);
    let hit = b.mul(hit, within_step);
    Ok(Some(SweptEntry {
        hit,
        t: enter,
        normal,
    }))
}

/// [`swept_entry`]'s answer.
struct SweptEntry {
    hit: V,
    t: V,
    normal: [V; 3],
}

/// Where a line enters and leaves one convex piece of an inflated obstacle, and the piece's
/// outward normal at the entry. A line that never meets the piece enters at +[`NO_LIMIT`]; one
/// that never leaves it (parallel inside) enters at −[`NO_LIMIT`].
struct Crossing {
    enter: V,
    leave: V,
    normal: [V; 3],
}

/// Motion below this (m per step) counts as parallel to a slab or an axis.
const PARALLEL: f64 = 1e-20;

/// The slab lo ≤ s ≤ hi of the coordinate s₀ + t·ṡ along the unit `axis`.
fn slab_crossing(
    b: &mut crate::ir::Builder,
    (s0, rate): (V, V),
    (lo, hi): (V, V),
    axis: [V; 3],
) -> Crossing {
    let (zero, one, far, near) = (
        b.constant(0.0),
        b.constant(1.0),
        b.constant(NO_LIMIT),
        b.constant(-NO_LIMIT),
    );
    let speed = b.un(UnOp::Abs, rate);
    let parallel_limit = b.constant(PARALLEL);
    let moving = b.cmp(CmpOp::Gt, speed, parallel_limit);
    let safe = b.select(moving, rate, one);
    let per_rate = b.div(one, safe);
    let to_lo = b.sub(lo, s0);
    let to_lo = b.mul(to_lo, per_rate);
    let to_hi = b.sub(hi, s0);
    let to_hi = b.mul(to_hi, per_rate);
    let first = b.bin(BinOp::Min, to_lo, to_hi);
    let last = b.bin(BinOp::Max, to_lo, to_hi);
    // Parallel: inside the slab for every t, or never.
    let above_lo = b.cmp(CmpOp::Ge, s0, lo);
    let below_hi = b.cmp(CmpOp::Le, s0, hi);
    let inside = b.mul(above_lo, below_hi);
    let parallel_enter = b.select(inside, near, far);
    let enter = b.select(moving, first, parallel_enter);
    let leave = b.select(moving, last, far);
    // It enters through the face it moves towards: the normal is against the motion.
    let up = b.cmp(CmpOp::Gt, rate, zero);
    let minus = b.constant(-1.0);
    let side = b.select(up, minus, one);
    Crossing {
        enter,
        leave,
        normal: axis.map(|c| b.mul(side, c)),
    }
}

/// The ball ‖w₀ + t·ẇ‖ ≤ `radius` (a sphere, or a cylinder's cross-section with w its radial
/// vector).
fn ball_crossing(b: &mut crate::ir::Builder, w0: [V; 3], rate: [V; 3], radius: V) -> Crossing {
    let (zero, one, far, near) = (
        b.constant(0.0),
        b.constant(1.0),
        b.constant(NO_LIMIT),
        b.constant(-NO_LIMIT),
    );
    let squares = |b: &mut crate::ir::Builder, p: [V; 3], q: [V; 3]| {
        let terms: Vec<V> = (0..3).map(|d| b.mul(p[d], q[d])).collect();
        b.sum(&terms)
    };
    // A t² + 2 B t + C = 0.
    let a = squares(b, rate, rate);
    let half_b = squares(b, w0, rate);
    let r2 = b.mul(radius, radius);
    let c = squares(b, w0, w0);
    let c = b.sub(c, r2);
    let parallel_limit = b.constant(PARALLEL * PARALLEL);
    let moving = b.cmp(CmpOp::Gt, a, parallel_limit);
    let bb = b.mul(half_b, half_b);
    let ac = b.mul(a, c);
    let disc = b.sub(bb, ac);
    let meets = b.cmp(CmpOp::Ge, disc, zero);
    let disc = b.bin(BinOp::Max, disc, zero);
    let root = b.un(UnOp::Sqrt, disc);
    let safe_a = b.select(moving, a, one);
    let per_a = b.div(one, safe_a);
    let minus_b = b.neg(half_b);
    let first = b.sub(minus_b, root);
    let first = b.mul(first, per_a);
    let last = b.add(minus_b, root);
    let last = b.mul(last, per_a);
    let first = b.select(meets, first, far);
    let last = b.select(meets, last, near);
    let inside = b.cmp(CmpOp::Le, c, zero);
    let parallel_enter = b.select(inside, near, far);
    let enter = b.select(moving, first, parallel_enter);
    let leave = b.select(moving, last, far);
    // The outward normal where the line enters (finite where it is not taken).
    let t = b.select(meets, first, zero);
    let at = [0, 1, 2].map(|d| {
        let s = b.mul(t, rate[d]);
        b.add(w0[d], s)
    });
    let tiny = b.constant(1e-30);
    let safe_r = b.bin(BinOp::Max, radius, tiny);
    Crossing {
        enter,
        leave,
        normal: at.map(|c| b.div(c, safe_r)),
    }
}

/// A cylinder obstacle's start, unit axis, length and radius.
fn cylinder_frame(
    k: &mut KernelBuilder,
    vector: &mut impl FnMut(&mut KernelBuilder, &str, usize) -> Result<Vec<V>, LowerError>,
) -> Result<(Vec<V>, [V; 3], V, V), LowerError> {
    let a = vector(k, "start", 0)?;
    let b = vector(k, "end", 1)?;
    let r = vector(k, "radius", 2)?[0];
    let axis = [0, 1, 2].map(|d| k.b.sub(b[d], a[d]));
    let len = norm(k, &axis);
    let unit = [0, 1, 2].map(|d| k.b.div(axis[d], len));
    Ok((a, unit, len, r))
}

/// The Euclidean norm of `v`.
fn norm(k: &mut KernelBuilder, v: &[V]) -> V {
    let sq: Vec<V> = v.iter().map(|&c| k.b.mul(c, c)).collect();
    let n2 = k.b.sum(&sq);
    k.b.un(UnOp::Sqrt, n2)
}

/// +1 where `v ≥ 0`, else −1.
fn sign(k: &mut KernelBuilder, v: V) -> V {
    let zero = k.b.constant(0.0);
    let (plus, minus) = (k.b.constant(1.0), k.b.constant(-1.0));
    let up = k.b.cmp(CmpOp::Ge, v, zero);
    k.b.select(up, plus, minus)
}

/// The signed distance to a convex solid that is the intersection of slabs, from each slab's
/// `excess` q_i (how far outside it the point is, negative inside): outside,
/// d = ‖max(q, 0)‖ and ∂d/∂q_i = max(q_i, 0)/d; inside, d = max_i q_i (minus the depth to the
/// nearest face) and ∂d/∂q is that face's unit vector (the first of equals).
fn solid_distance<const N: usize>(k: &mut KernelBuilder, excess: &[V; N]) -> (V, [V; N]) {
    let zero = k.b.constant(0.0);
    let one = k.b.constant(1.0);
    let tiny = k.b.constant(1e-30);
    let pos = excess.map(|q| k.b.bin(BinOp::Max, q, zero));
    let outside_d = norm(k, &pos);
    let outside_safe = k.b.bin(BinOp::Max, outside_d, tiny);
    let deepest = excess[1..]
        .iter()
        .fold(excess[0], |m, &q| k.b.bin(BinOp::Max, m, q));
    let outside = k.b.cmp(CmpOp::Gt, deepest, zero);
    let d = k.b.select(outside, outside_d, deepest);
    // Inside: the first slab whose excess is the largest.
    let mut taken = zero;
    let grad = std::array::from_fn(|i| {
        let is_max = k.b.cmp(CmpOp::Ge, excess[i], deepest);
        let free = k.b.sub(one, taken);
        let face = k.b.mul(is_max, free);
        taken = k.b.add(taken, face);
        let out = k.b.div(pos[i], outside_safe);
        k.b.select(outside, out, face)
    });
    (d, grad)
}

/// a·b, leaving out the products with a constant zero of `a` (a plane's normal along an axis
/// reads one coordinate).
fn dot(k: &mut KernelBuilder, a: [V; 3], b: [V; 3]) -> V {
    let kept: Vec<usize> = (0..3)
        .filter(|&d| k.b.func.constant(a[d]) != Some(0.0))
        .collect();
    let terms: Vec<V> = kept.into_iter().map(|d| k.b.mul(a[d], b[d])).collect();
    k.b.sum(&terms)
}

/// The node's own position, component by component.
fn own_position(k: &mut KernelBuilder, x: BufferId) -> [V; 3] {
    [0, 1, 2].map(|d| {
        k.load(ArgSource::Own {
            buffer: x,
            component: d,
        })
    })
}

/// The barrier's pressure law g(r) = (1 − r)·q, q = 1/r − 1 − 2 ln r (the contact pressure
/// over k at r = d/ĝ), with q and 1/r, which its derivative reuses.
struct PressureLaw {
    g: V,
    q: V,
    inv: V,
}

fn pressure_law(b: &mut crate::ir::Builder, r: V) -> PressureLaw {
    let one = b.constant(1.0);
    let inv = b.div(one, r);
    let ln = b.un(UnOp::Ln, r);
    let two_ln = b.scale(2.0, ln);
    let q = b.sub(inv, one);
    let q = b.sub(q, two_ln);
    let s = b.sub(one, r);
    PressureLaw {
        g: b.mul(s, q),
        q,
        inv,
    }
}

/// The contact force (and d) of statement `i` on the node at `x`, zero off the contact set
/// and beyond the gap. A contact node at d ≤ 0 (inside the obstacle) gets a non-finite force.
fn barrier_force(
    program: &Program,
    module: &mut Module,
    k: &mut KernelBuilder,
    i: usize,
    st: &Statement,
    x: [V; 3],
) -> Result<([V; 3], V), LowerError> {
    let area_buf = area_buffer(module, i);
    let area = k.load(ArgSource::Own {
        buffer: area_buf,
        component: 0,
    });
    barrier(program, k, i, st, x, area)
}

/// [`barrier_force`] for a node of boundary area `area`.
fn barrier(
    program: &Program,
    k: &mut KernelBuilder,
    i: usize,
    st: &Statement,
    x: [V; 3],
    area: V,
) -> Result<([V; 3], V), LowerError> {
    let (d, grad) = distance(program, k, st.shape, x)?;
    let magnitude = barrier_magnitude(k, i, st, d, area);
    Ok((grad.map(|c| k.b.mul(magnitude, c)), d))
}

/// The barrier's force k·A·g(d/ĝ) on a node at distance `d` of boundary area `area` (zero off
/// the contact set and beyond the gap).
fn barrier_magnitude(k: &mut KernelBuilder, i: usize, st: &Statement, d: V, area: V) -> V {
    let stiffness = k.uniform(&stiffness_uniform(i));
    let b = &mut k.b;
    let zero = b.constant(0.0);
    let one = b.constant(1.0);
    let r = b.scale(1.0 / st.gap, d);
    let near = b.cmp(CmpOp::Lt, r, one);
    let member = b.cmp(CmpOp::Gt, area, zero);
    let active = b.select(member, near, zero);
    // Off the set or beyond the gap r = 1, where g(1) = 0: no ln or 1/r of a distance that
    // may be anything (a node the contact does not concern may be anywhere).
    let r = b.select(active, r, one);
    let g = pressure_law(b, r).g;
    let ka = b.mul(stiffness, area);
    b.mul(ka, g)
}

/// The summed contact force on the node at `x` (the static and implicit node kernels add it to
/// the net force), or `None` without contact. Quadratic meshes have no contact yet.
pub fn node_contact_force(
    program: &Program,
    module: &mut Module,
    k: &mut KernelBuilder,
    x: BufferId,
) -> Result<Option<[V; 3]>, LowerError> {
    let statements = statements(program)?;
    if statements.is_empty() {
        return Ok(None);
    }
    linear_only(module)?;
    let pos = own_position(k, x);
    let mut total: Option<[V; 3]> = None;
    for (i, st) in statements.iter().enumerate() {
        let (f, _) = barrier_force(program, module, k, i, st, pos)?;
        total = Some(match total {
            None => f,
            Some(t) => [0, 1, 2].map(|d| k.b.add(t[d], f[d])),
        });
    }
    Ok(total)
}

/// The fraction of the gap a contact node may slip in one implicit step while friction holds it
/// (the smoothing length of [`node_friction_force`]).
pub const STICK_SLIP_FRACTION: f64 = 1e-3;

/// Coulomb friction on the node at `x` in a backward Euler step from `x_prev` (the step's
/// slip Δx_t: the step's motion less its component along the obstacle's normal ∇d at x), or
/// `None` without a contact that has friction. With λ the barrier's normal force on the node
/// at x, the force is −μ·λ·f₁(‖Δx_t‖/ε)·Δx_t/‖Δx_t‖ with IPC's smoothing f₁(y) = 2y − y² for
/// y < 1, 1 beyond (Li et al. 2020), ε = [`STICK_SLIP_FRACTION`]·ĝ: sliding nodes feel μ·λ
/// against their slip, sticking ones a stiff spring that lets them creep by less than ε per
/// step. It is evaluated at the step's end, like every force of the step; not a potential,
/// so the tangent is not symmetric (LU).
pub fn node_friction_force(
    program: &Program,
    module: &mut Module,
    k: &mut KernelBuilder,
    (x, x_prev): (BufferId, BufferId),
) -> Result<Option<[V; 3]>, LowerError> {
    let statements = statements(program)?;
    let pos = own_position(k, x);
    let start = own_position(k, x_prev);
    let mut total: Option<[V; 3]> = None;
    for (i, st) in statements.iter().enumerate() {
        let Some(mu) = st.friction else { continue };
        let (d, normal) = distance(program, k, st.shape, pos)?;
        let area = k.load(ArgSource::Own {
            buffer: area_buffer(module, i),
            component: 0,
        });
        let lambda = barrier_magnitude(k, i, st, d, area);
        let b = &mut k.b;
        let (one, two) = (b.constant(1.0), b.constant(2.0));
        let moved = [0, 1, 2].map(|c| b.sub(pos[c], start[c]));
        let eps = STICK_SLIP_FRACTION * st.gap;
        // ‖Δx_t‖ kept off zero by 10⁻⁶ ε.
        let (slip, s) = tangential_part(b, moved, normal, (1e-6 * eps).powi(2));
        // f₁(y)/‖Δx_t‖: (2 − y)/ε below ε, 1/‖Δx_t‖ beyond (finite at zero slip).
        let y = b.scale(1.0 / eps, s);
        let sticking = b.cmp(CmpOp::Lt, y, one);
        let below = b.sub(two, y);
        let below = b.scale(1.0 / eps, below);
        let eps_v = b.constant(eps);
        let s_safe = b.bin(BinOp::Max, s, eps_v);
        let beyond = b.div(one, s_safe);
        let per_slip = b.select(sticking, below, beyond);
        let coefficient = b.mul(lambda, per_slip);
        let coefficient = b.scale(-mu, coefficient);
        let f = slip.map(|c| b.mul(coefficient, c));
        total = Some(match total {
            None => f,
            Some(t) => [0, 1, 2].map(|c| k.b.add(t[c], f[c])),
        });
    }
    Ok(total)
}

fn linear_only(module: &Module) -> Result<(), LowerError> {
    if module.order != crate::ir::ElementOrder::Linear {
        return Err(LowerError::new(
            "contact works on linear tetrahedra for now: load the mesh with `order: 1`",
        ));
    }
    Ok(())
}

/// Newton iterations of an explicit step's contact projection (unrolled in the node kernel).
pub const PROJECTION_ITERATIONS: usize = 12;

/// What a semi-implicit Euler step predicts for one node before contact: its position now, the
/// step's new position and velocity, its (scaled) mass, the step and whether it is free.
pub struct Predicted {
    pub x: [V; 3],
    pub x_new: [V; 3],
    pub v_new: [V; 3],
    pub mass: V,
    pub dt: V,
    pub free: V,
}

/// A node's position and velocity after an explicit step's contact projection.
pub type Projected = ([V; 3], [V; 3]);

/// An explicit step's contact, implicit in the positions (so no step size limit of its own and
/// no node ever inside an obstacle): for each statement in turn, a contact node predicted at
/// r̃ = d̃/ĝ < 1 moves by s = ĝ·(r − r̃) along the obstacle's normal ∇d at the predicted
/// position, where r solves the balance of the correction's inertia and the barrier's force
/// there, m·s/dt² = k·A·g(r):
///
///   h(r) = r − r̃ − c·g(r) = 0,   c = dt²·k·A/(m·ĝ),
///
/// h increasing and concave on (0, 1) with h(1) > 0, so the root is in (0, 1). Newton from the
/// left climbs to it monotonically and from the right lands left of it; it starts at the
/// node's distance before the step and never goes below a tenth of its last iterate (positive).
/// The velocity gains s/dt along the normal (a perfectly inelastic normal impulse, as backward
/// Euler's). Returns the new position and velocity, or `None` without contact.
pub fn project_step(
    program: &Program,
    module: &mut Module,
    k: &mut KernelBuilder,
    state: Predicted,
) -> Result<Option<Projected>, LowerError> {
    let statements = statements(program)?;
    if statements.is_empty() {
        return Ok(None);
    }
    linear_only(module)?;
    let (mut x1, mut v1) = (state.x_new, state.v_new);
    for (i, st) in statements.iter().enumerate() {
        let (d_now, _) = distance(program, k, st.shape, state.x)?;
        let area = k.load(ArgSource::Own {
            buffer: area_buffer(module, i),
            component: 0,
        });
        let stopped = stop_at_entry(program, k, st, &state, (d_now, area), (&mut x1, &mut v1))?;
        let (d_new, normal) = distance(program, k, st.shape, x1)?;
        let stiffness = k.uniform(&stiffness_uniform(i));
        let b = &mut k.b;
        let (zero, one, tenth) = (b.constant(0.0), b.constant(1.0), b.constant(0.1));
        let r_new = b.scale(1.0 / st.gap, d_new);
        let member = b.cmp(CmpOp::Gt, area, zero);
        let near = b.cmp(CmpOp::Lt, r_new, one);
        let active = b.select(member, near, zero);
        let active = b.select(state.free, active, zero);
        let dt2 = b.mul(state.dt, state.dt);
        let ka = b.mul(stiffness, area);
        let pull = b.mul(dt2, ka);
        let mg = b.scale(st.gap, state.mass);
        let c = b.div(pull, mg);
        // Start where the node is, inside (0, 1]; 0.5 where the projection is not taken (its
        // value is discarded, but must stay finite).
        let r_now = b.scale(1.0 / st.gap, d_now);
        let start = b.bin(BinOp::Min, r_now, one);
        let floor = b.constant(1e-6);
        let start = b.bin(BinOp::Max, start, floor);
        let half = b.constant(0.5);
        let mut r = b.select(active, start, half);
        let target = b.select(active, r_new, half);
        for _ in 0..PROJECTION_ITERATIONS {
            let PressureLaw { g, q, inv } = pressure_law(b, r);
            let s = b.sub(one, r);
            // g'(r) = −q − (1 − r)(1/r² + 2/r)
            let inv2 = b.mul(inv, inv);
            let two_inv = b.scale(2.0, inv);
            let w = b.add(inv2, two_inv);
            let sw = b.mul(s, w);
            let qsw = b.add(q, sw);
            let dg = b.neg(qsw);
            let cg = b.mul(c, g);
            let h = b.sub(r, target);
            let h = b.sub(h, cg);
            let cdg = b.mul(c, dg);
            let dh = b.sub(one, cdg);
            let step = b.div(h, dh);
            let next = b.sub(r, step);
            let low = b.mul(tenth, r);
            r = b.bin(BinOp::Max, next, low);
        }
        let moved = b.sub(r, r_new);
        let shift = b.scale(st.gap, moved);
        let shift = b.select(active, shift, zero);
        for d in 0..3 {
            let dx = b.mul(shift, normal[d]);
            x1[d] = b.add(x1[d], dx);
            let dv = b.div(dx, state.dt);
            v1[d] = b.add(v1[d], dv);
        }
        if let Some(mu) = st.friction {
            // The normal impulse of the step: the projection's and the stop's.
            let impulse = match stopped {
                Some(push) => b.add(shift, push),
                None => shift,
            };
            (x1, v1) = coulomb_friction(b, (x1, v1), normal, (mu, impulse), state.dt);
        }
    }
    Ok(Some((x1, v1)))
}

/// Explicit contact's collision detection (SPEC §6.7): a contact node whose straight path over
/// the step enters the obstacle inflated by ρ = min(ĝ, d₀)/2 (d₀ its distance before the step)
/// has its predicted position moved back along the inflated shape's normal n at the entry onto
/// the tangent plane there, by (1 − t)·(−n·Δx), and its velocity by that over dt: a node fast
/// enough to cross a thin obstacle in one step stops on the side it came from, at least ρ
/// clear of it (the plane supports the convex inflated shape), and the projection then
/// resolves the gap as for any other node. The part of the motion along the tangent plane is
/// kept. Returns the push (m, zero where the path does not enter), or `None` for a plane.
fn stop_at_entry(
    program: &Program,
    k: &mut KernelBuilder,
    st: &Statement,
    state: &Predicted,
    (d_now, area): (V, V),
    (x1, v1): (&mut [V; 3], &mut [V; 3]),
) -> Result<Option<V>, LowerError> {
    let motion = [0, 1, 2].map(|d| k.b.sub(x1[d], state.x[d]));
    let half_gap = k.b.constant(0.5 * st.gap);
    let half_now = k.b.scale(0.5, d_now);
    let rho = k.b.bin(BinOp::Min, half_gap, half_now);
    let Some(entry) = swept_entry(program, k, st.shape, (state.x, motion), rho)? else {
        return Ok(None);
    };
    let approach = dot(k, entry.normal, motion);
    let b = &mut k.b;
    let (zero, one) = (b.constant(0.0), b.constant(1.0));
    let member = b.cmp(CmpOp::Gt, area, zero);
    let clear = b.cmp(CmpOp::Gt, rho, zero);
    let takes = b.mul(entry.hit, member);
    let takes = b.mul(takes, clear);
    let takes = b.mul(takes, state.free);
    let rest = b.sub(one, entry.t);
    let push = b.mul(rest, approach);
    let push = b.neg(push);
    let push = b.bin(BinOp::Max, push, zero);
    let push = b.select(takes, push, zero);
    for d in 0..3 {
        let dx = b.mul(push, entry.normal[d]);
        x1[d] = b.add(x1[d], dx);
        let dv = b.div(dx, state.dt);
        v1[d] = b.add(v1[d], dv);
    }
    Ok(Some(push))
}

/// The part of `v` across the unit `normal`, and its length kept off zero
/// (√(‖v_t‖² + `floor`)) so that its derivative stays finite where v_t vanishes (a node at
/// rest, no slip).
fn tangential_part(
    b: &mut crate::ir::Builder,
    v: [V; 3],
    normal: [V; 3],
    floor: f64,
) -> ([V; 3], V) {
    let along: Vec<V> = (0..3).map(|d| b.mul(v[d], normal[d])).collect();
    let along = b.sum(&along);
    let across = [0, 1, 2].map(|d| {
        let n = b.mul(along, normal[d]);
        b.sub(v[d], n)
    });
    let squares: Vec<V> = across.iter().map(|&c| b.mul(c, c)).collect();
    let length2 = b.sum(&squares);
    let floor = b.constant(floor);
    let length2 = b.add(length2, floor);
    (across, b.un(UnOp::Sqrt, length2))
}

/// Coulomb friction on an explicit step's contact projection (SPEC §6.7): the normal impulse
/// per unit mass of the step's projection is `shift`/dt (zero where the node is not in
/// contact), and friction changes the node's tangential velocity v_t by at most μ times that,
/// against it: v_t·max(0, 1 − μ·shift/(dt·‖v_t‖)). A node whose tangential speed friction can
/// take away sticks (v_t = 0) for the step; else it slides, slowed by μ·N. This is the
/// impulse of the exact (non-smoothed) Coulomb law over one step, as implicit in the step as
/// the normal projection is, so it adds no time step limit of its own. The position follows
/// the velocity change (x_new = x + dt·v_new).
fn coulomb_friction(
    b: &mut crate::ir::Builder,
    (mut x1, mut v1): Projected,
    normal: [V; 3],
    (mu, shift): (f64, V),
    dt: V,
) -> Projected {
    let (zero, one) = (b.constant(0.0), b.constant(1.0));
    let (tangential, speed) = tangential_part(b, v1, normal, 1e-24);
    let impulse = b.div(shift, dt);
    let budget = b.scale(mu, impulse);
    let ratio = b.div(budget, speed);
    let kept = b.sub(one, ratio);
    let kept = b.bin(BinOp::Max, kept, zero);
    // The velocity change −(1 − kept)·v_t.
    let lost = b.sub(kept, one);
    for d in 0..3 {
        let dv = b.mul(lost, tangential[d]);
        v1[d] = b.add(v1[d], dv);
        let dx = b.mul(dv, dt);
        x1[d] = b.add(x1[d], dx);
    }
    (x1, v1)
}

/// The contact kernels that are not part of a step, pushed onto `module` (after its node
/// kernel, like the element diagnostics: they write no buffer a step reads): per statement the
/// report of each node's force and distance, and the Newton step limit.
pub fn contact_kernels(
    program: &Program,
    module: &mut Module,
) -> Result<Option<Contacts>, LowerError> {
    let statements = statements(program)?;
    if statements.is_empty() {
        return Ok(None);
    }
    let x = module.buffer("x", Domain::Node, 3, "node positions, m");
    let mut pairs = Vec::new();
    for (i, st) in statements.iter().enumerate() {
        let force = module.buffer(
            &format!("contact_force.{i}"),
            Domain::Node,
            3,
            "force of the obstacle on each node, N",
        );
        let distance = module.buffer(
            &format!("contact_distance.{i}"),
            Domain::Node,
            1,
            "signed distance of each node from the obstacle, m",
        );
        let mut k = KernelBuilder::new(
            &format!("contact_report_{i}"),
            Domain::Node,
            &format!("contact {} with {}", st.body, st.obstacle),
        );
        let pos = own_position(&mut k, x);
        let (f, d) = barrier_force(program, module, &mut k, i, st, pos)?;
        for (c, &fc) in f.iter().enumerate() {
            k.store(force, c as u32, fc);
        }
        k.store(distance, 0, d);
        let report_kernel = module.push_kernel(k.finish());
        pairs.push(Contact {
            body: st.body.clone(),
            obstacle: st.obstacle.clone(),
            gap: st.gap,
            stiffness: st.stiffness,
            area: area_buffer(module, i),
            stiffness_uniform: stiffness_uniform(i),
            force,
            distance,
            report_kernel,
        });
    }
    let step = module.buffer(
        "contact_step",
        Domain::Node,
        3,
        "a position update the step limit is computed for, m",
    );
    let step_limit = module.buffer(
        "contact_step_limit",
        Domain::Node,
        1,
        "largest fraction of the update that keeps the node clear of every obstacle",
    );
    let mut k = KernelBuilder::new("contact_step_limit", Domain::Node, "contact");
    let pos = own_position(&mut k, x);
    let v = own_position(&mut k, step);
    let mut limit = k.b.constant(NO_LIMIT);
    for (i, st) in statements.iter().enumerate() {
        let (d, grad) = distance(program, &mut k, st.shape, pos)?;
        let area = k.load(ArgSource::Own {
            buffer: area_buffer(module, i),
            component: 0,
        });
        let slope = dot(&mut k, grad, v);
        let b = &mut k.b;
        let zero = b.constant(0.0);
        let approaching = b.cmp(CmpOp::Lt, slope, zero);
        let member = b.cmp(CmpOp::Gt, area, zero);
        let limited = b.select(member, approaching, zero);
        // Guard the quotient where it is not taken: slope −1 there.
        let minus_one = b.constant(-1.0);
        let safe = b.select(limited, slope, minus_one);
        let reach = b.div(d, safe);
        let reach = b.scale(-STEP_FRACTION, reach);
        let inf = b.constant(NO_LIMIT);
        let alpha = b.select(limited, reach, inf);
        limit = b.bin(BinOp::Min, limit, alpha);
    }
    k.store(step_limit, 0, limit);
    let step_kernel = module.push_kernel(k.finish());
    Ok(Some(Contacts {
        pairs,
        step,
        step_limit,
        step_kernel,
    }))
}
