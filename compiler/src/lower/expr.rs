//! Lowering of checked expressions (sema's checked program, [`crate::sema::hir`]) into kernel IR.
//!
//! The checker has already established types and units and resolved every name, so lowering
//! works on SI numbers: arrays become lists of scalars, functions and lets are inlined, `if`
//! becomes `select`, reductions over integer ranges are unrolled. A local name takes its value
//! from the bindings of the definition being inlined (or the sim block's lets), a declaration's
//! from the declaration; params and inputs become uniforms of the kernel (`param.NAME[.i]`,
//! `input.NAME[.i]`), `t` becomes the uniform `t`.
//!
//! A per-element param (`param mu: pressure[soft_part]`, a *field*) has two forms: passed whole
//! (a material constant), it is an `Own` read of the element buffer `param.NAME` — available
//! only where the caller provides that buffer ([`ExprLowerer::element_fields`], the element
//! force kernels); indexed by an element of a reduction over an element set (`mu[e]` in a loss
//! or let), it is the uniform `param.NAME.i`, `i` the element's position in the field's set.

use super::LowerError;
use crate::ir::{ArgSource, BinOp, BufferId, CmpOp, KernelBuilder, UnOp, V};
use crate::sema::hir::{self, Arg, Callee, DeclKind, Expr, ExprKind, Name, ReduceOp, UnaryOp};
use crate::sema::types::Len;
use std::collections::HashMap;

/// The fraction of a window's width before its start from which `window(t, w)` counts `t` in
/// it, and the same relative to `t` (f32's rounding of `t/w` grows with it): see the
/// lowering of `window`.
const WINDOW_SLACK: f64 = 1e-4;
/// See [`WINDOW_SLACK`].
const WINDOW_SLACK_RELATIVE: f64 = 1e-6;

/// A lowered value: a scalar or an array of values (vectors, matrices).
#[derive(Clone, Debug, PartialEq, Eq, Hash)]
pub enum LVal {
    S(V),
    A(Vec<LVal>),
}

impl LVal {
    pub fn scalar(&self) -> Result<V, LowerError> {
        match self {
            LVal::S(v) => Ok(*v),
            LVal::A(_) => Err(LowerError::new("expected a scalar, found an array")),
        }
    }
    fn items(&self) -> Result<&[LVal], LowerError> {
        match self {
            LVal::A(a) => Ok(a),
            LVal::S(_) => Err(LowerError::new("expected an array, found a scalar")),
        }
    }
}

/// The checked program names resolve to (sema's [`hir::Program`]).
pub use crate::sema::hir::Program;

/// Local bindings (function parameters, template parameters, invariants, reduction variables).
pub type Env = HashMap<String, LVal>;

/// The uniform of component `c` of sensor `index` ([`ExprLowerer::sensors`]).
pub fn sensor_uniform(index: usize, c: usize) -> String {
    format!("sensor.{index}.{c}")
}

/// `v` with its scalars replaced, in order, by `f(0)`, `f(1)`, …
fn relabel(v: &LVal, next: &mut usize, f: &mut impl FnMut(usize) -> V) -> LVal {
    match v {
        LVal::S(_) => {
            *next += 1;
            LVal::S(f(*next - 1))
        }
        LVal::A(items) => LVal::A(items.iter().map(|i| relabel(i, next, f)).collect()),
    }
}

/// Inlining depth bound: the checker rejects cycles, this only guards against surprises.
const MAX_INLINE: usize = 64;

/// The most function calls and lets one lowering inlines (SPEC §13). Calls repeated with the
/// same arguments are inlined once ([`ExprLowerer::inlined`]), so this bounds only definitions
/// that expand to as many distinct values: 24 functions that each call the previous one twice
/// with different arguments are 16 million.
pub const MAX_INLINED: usize = 200_000;

/// A call (or a let) already inlined into one kernel: the kernel builder, the definition, its
/// bound arguments and the reduction variables bound where it was lowered.
#[derive(PartialEq, Eq, Hash)]
struct Inlined {
    builder: u64,
    name: String,
    args: Vec<(String, LVal)>,
    binders: Vec<(String, u32, bool)>,
}

pub struct ExprLowerer<'p> {
    pub program: &'p Program,
    /// Constants the scene fixes (e.g. `t_end`, `dt`), by name.
    pub constants: HashMap<String, f64>,
    /// Names whose values are known only when the code runs (`t_end` and `dt` in a loss,
    /// `loss` in a stop condition): each becomes the uniform of its own name.
    pub runtime_names: Vec<&'static str>,
    /// Node sets by name (for reductions over nodes in losses): node indices.
    pub node_sets: HashMap<String, Vec<u32>>,
    /// Per node set, each node's area weight (`area_mean`), in the set's order.
    pub node_weights: HashMap<String, Vec<f64>>,
    /// Element sets by name (for reductions over elements, `mu[e]`): element indices of the
    /// mesh, in the set's order.
    pub element_sets: HashMap<String, Vec<u32>>,
    /// Per-element params readable whole in this kernel (an element kernel): the buffer of
    /// each, by param name.
    pub element_fields: HashMap<String, BufferId>,
    /// Reduction variables currently bound to a node.
    node_binders: HashMap<String, u32>,
    /// Reduction variables currently bound to an element (a mesh element index).
    element_binders: HashMap<String, u32>,
    depth: usize,
    /// Calls and lets already inlined, with their values: the IR builder numbers equal
    /// values alike, so a repeated call's value is the same and is not expanded again (a
    /// definition calling another twice doubles the work at every level otherwise).
    inlined: HashMap<Inlined, LVal>,
    /// Definitions inlined so far (at most [`MAX_INLINED`]).
    expansions: usize,
    /// The sim block's lets, visible in the sim block's expressions and the lets' values.
    pub sim_lets: HashMap<String, Expr>,
    /// Whether names resolve through [`ExprLowerer::sim_lets`] here (not inside a function
    /// body or a global let).
    in_sim_scope: bool,
    /// Closed-loop control: where `Some`, a reduction over a node or element set (which a
    /// simulation kernel cannot evaluate: it runs per entity, before the mesh is known)
    /// becomes the uniforms `sensor.I.C`, I the reduction's index in this list and C the
    /// component; the host evaluates the reduction at the state a step starts from (or at a
    /// static iterate) and sets them ([`crate::driver::SensorKernels`]).
    pub sensors: Option<Vec<Expr>>,
    /// The loss: each `contact` statement's nodes, over which `force(OBSTACLE)` sums.
    pub contact_nodes: Option<Vec<super::contact::ContactNodes>>,
    /// The loss: each element's corners and the rest positions of the nodes, from which
    /// `stretch(e)` computes the element's deformation.
    pub elements: Option<ElementShapes<'p>>,
}

/// Each element's corners and every node's rest position (the mesh's, borrowed).
pub type ElementShapes<'m> = (&'m [[u32; 4]], &'m [[f64; 3]]);

impl<'p> ExprLowerer<'p> {
    pub fn new(program: &'p Program) -> Self {
        ExprLowerer {
            program,
            constants: HashMap::new(),
            runtime_names: Vec::new(),
            node_sets: HashMap::new(),
            node_weights: HashMap::new(),
            element_sets: HashMap::new(),
            element_fields: HashMap::new(),
            node_binders: HashMap::new(),
            element_binders: HashMap::new(),
            depth: 0,
            inlined: HashMap::new(),
            expansions: 0,
            sim_lets: HashMap::new(),
            in_sim_scope: true,
            sensors: None,
            contact_nodes: None,
            elements: None,
        }
    }

    /// The uniforms of the sensor `e` (a reduction over a set, [`ExprLowerer::sensors`]), in
    /// the shape of its value.
    fn sensor(&mut self, k: &mut KernelBuilder, e: &Expr, set: &str) -> Result<LVal, LowerError> {
        // The value's shape: the reduction lowered with every set holding one entity, in a
        // scratch kernel and with no local bindings — a reduction that reads a function's
        // arguments cannot be evaluated apart from the kernel (the checker reports it).
        let mut probe = ExprLowerer::new(self.program);
        probe.sim_lets = self.sim_lets.clone();
        probe.in_sim_scope = self.in_sim_scope;
        for (name, elements) in self.program.sets() {
            let sets = if elements {
                &mut probe.element_sets
            } else {
                &mut probe.node_sets
            };
            sets.insert(name.to_string(), vec![0]);
        }
        let mut scratch = KernelBuilder::new("sensor", crate::ir::Domain::Single, "sensor");
        let shape = probe.lower(&mut scratch, &Env::new(), e).map_err(|err| {
            LowerError::new(format!(
                "the reduction over `{set}` in the sim block cannot be evaluated by the host \
                 ({}): it may read the node state, params, inputs, `t` and lets, not the \
                 arguments of the function or controller it is in",
                err.message
            ))
        })?;
        let sensors = self.sensors.as_mut().expect("sensor mode");
        let index = match sensors.iter().position(|s| s == e) {
            Some(i) => i,
            None => {
                sensors.push(e.clone());
                sensors.len() - 1
            }
        };
        let mut next = 0;
        Ok(relabel(&shape, &mut next, &mut |c| {
            k.uniform(&sensor_uniform(index, c))
        }))
    }

    pub fn lower(
        &mut self,
        k: &mut KernelBuilder,
        env: &Env,
        e: &Expr,
    ) -> Result<LVal, LowerError> {
        match &e.kind {
            ExprKind::Num(value) => Ok(LVal::S(k.b.constant(*value))),
            ExprKind::Array { items, scale } => {
                let mut out = Vec::with_capacity(items.len());
                for it in items {
                    let v = self.lower(k, env, it)?;
                    out.push(map_scalars(k, &v, &mut |k, x| k.b.scale(*scale, x))?);
                }
                Ok(LVal::A(out))
            }
            ExprKind::Bool(b) => Ok(LVal::S(k.b.constant(if *b { 1.0 } else { 0.0 }))),
            ExprKind::Str(_) => Err(LowerError::new("strings have no value in a kernel")),
            ExprKind::Name(name) => self.name(k, env, name),
            ExprKind::Unary { op, operand } => {
                let v = self.lower(k, env, operand)?;
                map_scalars(k, &v, &mut |k, x| match op {
                    UnaryOp::Neg => k.b.neg(x),
                    UnaryOp::Not => {
                        let zero = k.b.constant(0.0);
                        k.b.cmp(CmpOp::Eq, x, zero)
                    }
                })
            }
            ExprKind::Binary { op, lhs, rhs } => {
                let l = self.lower(k, env, lhs)?;
                let r = self.lower(k, env, rhs)?;
                self.binary(k, *op, &l, &r)
            }
            ExprKind::If {
                cond,
                then,
                otherwise,
            } => {
                let c = self.lower(k, env, cond)?.scalar()?;
                let a = self.lower(k, env, then)?;
                let b = self.lower(k, env, otherwise)?;
                zip_scalars(k, &a, &b, &mut |k, x, y| k.b.select(c, x, y))
            }
            ExprKind::Field { base, axis } => {
                let b = self.lower(k, env, base)?;
                b.items()?
                    .get(*axis)
                    .cloned()
                    .ok_or_else(|| LowerError::new("component of a vector shorter than 3"))
            }
            ExprKind::Index { base, indices } => {
                // Node state `x[n]`, `x0[n]`, `v[n]` of a node bound by a reduction: uniforms
                // `state.x.NODE.d` the host fills in.
                if let (ExprKind::Name(Name::Implicit(b)), [index]) =
                    (&base.kind, indices.as_slice())
                    && ["x", "x0", "v"].contains(&b.as_str())
                    && let ExprKind::Name(Name::Local(n)) = &index.kind
                    && let Some(&node) = self.node_binders.get(n)
                {
                    return Ok(LVal::A(
                        (0..3)
                            .map(|d| LVal::S(k.uniform(&format!("state.{b}.{node}.{d}"))))
                            .collect(),
                    ));
                }
                // A field at an element bound by a reduction: `param.NAME.i`.
                if let (ExprKind::Name(Name::Global(id)), [index]) =
                    (&base.kind, indices.as_slice())
                    && let DeclKind::Param(p) = &self.program.decl(*id).kind
                    && let Some(set) = p.field_set()
                {
                    let name = &self.program.decl(*id).name;
                    let ExprKind::Name(Name::Local(ev)) = &index.kind else {
                        return Err(LowerError::new(format!(
                            "the per-element param `{name}` is indexed by an element of a reduction"
                        )));
                    };
                    let element = *self.element_binders.get(ev).ok_or_else(|| {
                        LowerError::new(format!(
                            "`{ev}` is not an element bound by a reduction over an element set"
                        ))
                    })?;
                    let members = self.element_sets.get(set).ok_or_else(|| {
                        LowerError::new(format!("the element set `{set}` has no elements here"))
                    })?;
                    let i = members.iter().position(|&m| m == element).ok_or_else(|| {
                        LowerError::new(format!(
                            "element {element} is not in `{set}`, the set of the per-element param `{name}`"
                        ))
                    })?;
                    return Ok(LVal::S(k.uniform(&format!("param.{name}.{i}"))));
                }
                let mut v = self.lower(k, env, base)?;
                for ie in indices {
                    let i = self.lower(k, env, ie)?.scalar()?;
                    v = match k.b.func.constant(i) {
                        Some(c) => v
                            .items()?
                            .get(c as usize)
                            .cloned()
                            .ok_or_else(|| LowerError::new("index out of range"))?,
                        None => select_index(k, v.items()?, i)?,
                    };
                }
                Ok(v)
            }
            ExprKind::Reduce {
                op,
                var,
                domain,
                body,
            } => {
                if self.sensors.is_some()
                    && let Some(set) = self.program.set_reduction(e)
                    && !self.node_sets.contains_key(set)
                    && !self.element_sets.contains_key(set)
                {
                    return self.sensor(k, e, set);
                }
                self.reduce(k, env, *op, var, domain, body)
            }
            ExprKind::Call { callee, args } => self.call(k, env, callee, args),
        }
    }

    fn name(&mut self, k: &mut KernelBuilder, env: &Env, name: &Name) -> Result<LVal, LowerError> {
        match name {
            Name::Local(n) => {
                if let Some(v) = env.get(n) {
                    return Ok(v.clone());
                }
                if self.in_sim_scope
                    && let Some(value) = self.sim_lets.get(n).cloned()
                {
                    return self.inline(k, &format!("sim.{n}"), &Env::new(), &value);
                }
                Err(LowerError::new(format!("`{n}` has no value in a kernel")))
            }
            Name::Implicit(n) => {
                // Coordinates inside `select` are bound by the caller.
                if let Some(v) = env.get(n) {
                    return Ok(v.clone());
                }
                if let Some(c) = self.constants.get(n) {
                    return Ok(LVal::S(k.b.constant(*c)));
                }
                if self.runtime_names.contains(&n.as_str()) {
                    return Ok(LVal::S(k.uniform(n)));
                }
                match n.as_str() {
                    "t" | "dt" => Ok(LVal::S(k.uniform(n))),
                    "pi" => Ok(LVal::S(k.b.constant(std::f64::consts::PI))),
                    _ => Err(LowerError::new(format!("`{n}` has no value in a kernel"))),
                }
            }
            Name::Global(id) => self.global(k, *id),
        }
    }

    /// The value of the declaration `id` read by name.
    fn global(&mut self, k: &mut KernelBuilder, id: hir::DeclId) -> Result<LVal, LowerError> {
        let program = self.program;
        let decl = program.decl(id);
        let name = decl.name.as_str();
        match &decl.kind {
            DeclKind::Let(value) => self.inline_global(k, name, &Env::new(), value),
            DeclKind::Param(p) => {
                if p.field_set().is_some() {
                    let buffer = self.element_fields.get(name).ok_or_else(|| {
                        LowerError::new(format!(
                            "the per-element param `{name}` has a value only in an element's \
                             material (a material constant) or at an element bound by a \
                             reduction over its set (`{name}[e]`)"
                        ))
                    })?;
                    return Ok(LVal::S(k.load(ArgSource::Own {
                        buffer: *buffer,
                        component: 0,
                    })));
                }
                Ok(uniforms(k, &format!("param.{name}"), p.ty.shape()))
            }
            DeclKind::Input(i) => Ok(uniforms(k, &format!("input.{name}"), i.ty.shape())),
            _ => Err(LowerError::new(format!(
                "`{name}` has no value in a kernel"
            ))),
        }
    }

    /// [`ExprLowerer::inline`] of a global definition: the sim block's lets are out of scope
    /// in its body.
    fn inline_global(
        &mut self,
        k: &mut KernelBuilder,
        name: &str,
        env: &Env,
        e: &Expr,
    ) -> Result<LVal, LowerError> {
        let scope = std::mem::replace(&mut self.in_sim_scope, false);
        let r = self.inline(k, name, env, e);
        self.in_sim_scope = scope;
        r
    }

    /// The value of definition `name` (a function's body `e` with its arguments bound in `env`,
    /// or a let's value), inlined once per kernel and arguments.
    fn inline(
        &mut self,
        k: &mut KernelBuilder,
        name: &str,
        env: &Env,
        e: &Expr,
    ) -> Result<LVal, LowerError> {
        if self.depth >= MAX_INLINE {
            return Err(LowerError::new("definitions nested too deeply"));
        }
        let mut args: Vec<(String, LVal)> =
            env.iter().map(|(n, v)| (n.clone(), v.clone())).collect();
        args.sort_by(|a, b| a.0.cmp(&b.0));
        let mut binders: Vec<(String, u32, bool)> = (self.node_binders.iter())
            .map(|(n, &i)| (n.clone(), i, false))
            .chain(
                self.element_binders
                    .iter()
                    .map(|(n, &i)| (n.clone(), i, true)),
            )
            .collect();
        binders.sort();
        let key = Inlined {
            builder: k.id(),
            name: name.to_string(),
            args,
            binders,
        };
        if let Some(v) = self.inlined.get(&key) {
            return Ok(v.clone());
        }
        self.expansions += 1;
        if self.expansions > MAX_INLINED {
            return Err(LowerError::new(format!(
                "the expression is too complex: its definitions expand to more than \
                 {MAX_INLINED} calls with distinct arguments (here in `{name}`); simplify the \
                 functions that call others several times"
            )));
        }
        self.depth += 1;
        let r = self.lower(k, env, e);
        self.depth -= 1;
        let v = r?;
        self.inlined.insert(key, v.clone());
        Ok(v)
    }

    fn binary(
        &mut self,
        k: &mut KernelBuilder,
        op: BinOp_,
        l: &LVal,
        r: &LVal,
    ) -> Result<LVal, LowerError> {
        use hir::BinOp as A;
        let ir = match op {
            A::Add => BinOp::Add,
            A::Sub => BinOp::Sub,
            A::Mul => BinOp::Mul,
            A::Div => BinOp::Div,
            A::Pow => BinOp::Pow,
            A::MatMul => return matmul(k, l, r),
            A::And | A::Or => {
                let (a, b) = (l.scalar()?, r.scalar()?);
                let zero = k.b.constant(0.0);
                let na = k.b.cmp(CmpOp::Ne, a, zero);
                let nb = k.b.cmp(CmpOp::Ne, b, zero);
                return Ok(LVal::S(if op == A::And {
                    k.b.mul(na, nb)
                } else {
                    k.b.bin(BinOp::Max, na, nb)
                }));
            }
            A::Eq | A::Ne | A::Lt | A::Le | A::Gt | A::Ge => {
                let c = match op {
                    A::Eq => CmpOp::Eq,
                    A::Ne => CmpOp::Ne,
                    A::Lt => CmpOp::Lt,
                    A::Le => CmpOp::Le,
                    A::Gt => CmpOp::Gt,
                    _ => CmpOp::Ge,
                };
                return Ok(LVal::S(k.b.cmp(c, l.scalar()?, r.scalar()?)));
            }
            A::Range => return Err(LowerError::new("a range has no value")),
        };
        zip_scalars(k, l, r, &mut |k, x, y| k.b.bin(ir, x, y))
    }

    fn reduce(
        &mut self,
        k: &mut KernelBuilder,
        env: &Env,
        op: ReduceOp,
        var: &str,
        domain: &Expr,
        body: &Expr,
    ) -> Result<LVal, LowerError> {
        let mut terms = Vec::new();
        if op == ReduceOp::AreaMean {
            return self.area_mean(k, env, var, domain, body);
        }
        let set = match &domain.kind {
            ExprKind::Name(Name::Global(id)) => Some(self.program.decl(*id)),
            _ => None,
        };
        if let Some(set) = set
            && let Some(elements) = self.element_sets.get(&set.name).cloned()
        {
            // Over the elements of a set, in the set's order.
            for element in elements {
                self.element_binders.insert(var.to_string(), element);
                let t = self.lower(k, env, body);
                self.element_binders.remove(var);
                terms.push(t?);
            }
        } else if let Some(set) = set
            && let Some(nodes) = self.node_sets.get(&set.name).cloned()
        {
            // Over the nodes of a set, in index order (a fixed order: reproducible sums).
            for node in nodes {
                self.node_binders.insert(var.to_string(), node);
                let t = self.lower(k, env, body);
                self.node_binders.remove(var);
                terms.push(t?);
            }
        } else {
            let ExprKind::Binary {
                op: hir::BinOp::Range,
                lhs,
                rhs,
            } = &domain.kind
            else {
                if let Some(set) = set
                    && matches!(set.kind, DeclKind::Nodes(_) | DeclKind::Elements(_))
                {
                    return Err(LowerError::new(format!(
                        "a reduction over the {} `{}` is evaluated only in the loss (and the \
                         lets it uses): the simulation's kernels are compiled before the mesh \
                         says which entities the set holds",
                        set.kind.noun(),
                        set.name
                    )));
                }
                return Err(LowerError::new(
                    "the reduction's domain is not a known node set or range",
                ));
            };
            let lo = self.lower(k, env, lhs)?.scalar()?;
            let hi = self.lower(k, env, rhs)?.scalar()?;
            let (Some(lo), Some(hi)) = (k.b.func.constant(lo), k.b.func.constant(hi)) else {
                return Err(LowerError::new("a range reduction needs constant bounds"));
            };
            for i in (lo as i64)..(hi as i64) {
                let mut inner = env.clone();
                inner.insert(var.to_string(), LVal::S(k.b.constant(i as f64)));
                terms.push(self.lower(k, &inner, body)?);
            }
        }
        let Some(first) = terms.first().cloned() else {
            return Ok(LVal::S(k.b.constant(0.0)));
        };
        let mut acc = first;
        for t in &terms[1..] {
            acc = zip_scalars(k, &acc, t, &mut |k, x, y| match op {
                ReduceOp::Sum | ReduceOp::Mean | ReduceOp::AreaMean => k.b.add(x, y),
                ReduceOp::Max => k.b.bin(BinOp::Max, x, y),
                ReduceOp::Min => k.b.bin(BinOp::Min, x, y),
            })?;
        }
        if op == ReduceOp::Mean {
            let n = terms.len() as f64;
            acc = map_scalars(k, &acc, &mut |k, x| k.b.scale(1.0 / n, x))?;
        }
        Ok(acc)
    }

    /// Σ wₙ·body(n) / Σ wₙ over a node set's nodes of nonzero area weight.
    fn area_mean(
        &mut self,
        k: &mut KernelBuilder,
        env: &Env,
        var: &str,
        domain: &Expr,
        body: &Expr,
    ) -> Result<LVal, LowerError> {
        let ExprKind::Name(Name::Global(id)) = &domain.kind else {
            return Err(LowerError::new("`area_mean` runs over a node set"));
        };
        let set = self.program.decl(*id);
        let (Some(nodes), Some(weights)) = (
            self.node_sets.get(&set.name).cloned(),
            self.node_weights.get(&set.name).cloned(),
        ) else {
            return Err(LowerError::new(format!(
                "`area_mean` over `{}` is evaluated only in the loss",
                set.name
            )));
        };
        let total: f64 = weights.iter().sum();
        if total <= 0.0 {
            return Err(LowerError::new(format!(
                "the node set `{}` covers no whole boundary triangle, so `area_mean` has no \
                 area to average over; select the nodes of a boundary face (e.g. \
                 `named(body, \"tip\")`), or use `mean`",
                set.name
            )));
        }
        let mut acc: Option<LVal> = None;
        for (node, w) in nodes.into_iter().zip(weights) {
            if w == 0.0 {
                continue;
            }
            self.node_binders.insert(var.to_string(), node);
            let t = self.lower(k, env, body);
            self.node_binders.remove(var);
            let t = map_scalars(k, &t?, &mut |k, x| k.b.scale(w / total, x))?;
            acc = Some(match acc {
                None => t,
                Some(a) => zip_scalars(k, &a, &t, &mut |k, x, y| k.b.add(x, y))?,
            });
        }
        Ok(acc.expect("a positive total weight has a term"))
    }

    /// `force(OBSTACLE)` in the loss: the total force of the obstacle on the body, summed over
    /// the contact nodes of its statements at the state's positions.
    fn contact_force(&mut self, k: &mut KernelBuilder, args: &[Arg]) -> Result<LVal, LowerError> {
        let obstacle = match args.first().map(|a| &a.value.kind) {
            Some(ExprKind::Name(Name::Global(id))) => self.program.decl(*id).name.clone(),
            _ => return Err(LowerError::new("`force` takes an obstacle")),
        };
        let nodes = self.contact_nodes.as_ref().ok_or_else(|| {
            LowerError::new("`force(…)` reads the contact at a state: the loss may read it")
        })?;
        let on = match crate::sema::hir::arg(args, "on", 1).map(|e| &e.kind) {
            None => None,
            Some(ExprKind::Name(Name::Global(id))) => {
                let set = &self.program.decl(*id).name;
                let members = self.node_sets.get(set).ok_or_else(|| {
                    LowerError::new(format!(
                        "`force(…, on: {set})` is evaluated only in the loss"
                    ))
                })?;
                Some(
                    members
                        .iter()
                        .copied()
                        .collect::<std::collections::HashSet<u32>>(),
                )
            }
            Some(_) => return Err(LowerError::new("`on:` takes a node set")),
        };
        let f = super::contact::total_force(self.program, k, &obstacle, nodes, on.as_ref())?;
        Ok(LVal::A(f.iter().map(|&v| LVal::S(v)).collect()))
    }

    /// `stretch(e)` in the loss: the largest principal stretch of the element bound to `e`.
    fn stretch(&mut self, k: &mut KernelBuilder, args: &[Arg]) -> Result<LVal, LowerError> {
        let element = match args.first().map(|a| &a.value.kind) {
            Some(ExprKind::Name(Name::Local(var))) => self.element_binders.get(var).copied(),
            _ => None,
        }
        .ok_or_else(|| LowerError::new("`stretch` takes an element bound by `sum(e in SET)`"))?;
        let (tets, rest) = self.elements.as_ref().ok_or_else(|| {
            LowerError::new("`stretch(…)` reads the deformation at a state: the loss may read it")
        })?;
        let corners = tets[element as usize];
        let at_rest = corners.map(|n| rest[n as usize]);
        Ok(LVal::S(super::stretch::largest_stretch(
            k, corners, at_rest,
        )?))
    }

    fn call(
        &mut self,
        k: &mut KernelBuilder,
        env: &Env,
        callee: &Callee,
        args: &[Arg],
    ) -> Result<LVal, LowerError> {
        let program = self.program;
        let name = match callee {
            Callee::Builtin(name) => name.as_str(),
            // User functions and controllers: inline with their parameters bound.
            Callee::Decl(id) => {
                let decl = program.decl(*id);
                let DeclKind::Fn(f) = &decl.kind else {
                    return Err(LowerError::new(format!(
                        "`{}` cannot be evaluated inside a kernel",
                        decl.name
                    )));
                };
                let params: Vec<(&str, Option<&Expr>)> = f
                    .params
                    .iter()
                    .map(|p| (p.name.as_str(), p.default.as_ref()))
                    .collect();
                let bound = self.bind(k, env, &params, args)?;
                return self.inline_global(k, &decl.name, &bound, &f.body);
            }
        };
        if name == "force" {
            return self.contact_force(k, args);
        }
        if name == "stretch" {
            return self.stretch(k, args);
        }
        let vals: Vec<LVal> = args
            .iter()
            .map(|a| self.lower(k, env, &a.value))
            .collect::<Result<_, _>>()?;
        let un = |k: &mut KernelBuilder, op: UnOp, v: &LVal| {
            map_scalars(k, v, &mut |k, x| k.b.un(op, x))
        };
        Ok(match (name, vals.as_slice()) {
            ("sqrt", [v]) => un(k, UnOp::Sqrt, v)?,
            ("abs", [v]) => un(k, UnOp::Abs, v)?,
            ("exp", [v]) => un(k, UnOp::Exp, v)?,
            ("ln", [v]) => un(k, UnOp::Ln, v)?,
            ("log10", [v]) => map_scalars(k, v, &mut |k, x| {
                let l = k.b.un(UnOp::Ln, x);
                k.b.scale(1.0 / std::f64::consts::LN_10, l)
            })?,
            ("sin", [v]) => un(k, UnOp::Sin, v)?,
            ("cos", [v]) => un(k, UnOp::Cos, v)?,
            ("tan", [v]) => un(k, UnOp::Tan, v)?,
            ("tanh", [v]) => un(k, UnOp::Tanh, v)?,
            ("floor", [v]) => un(k, UnOp::Floor, v)?,
            ("ceil", [v]) => un(k, UnOp::Ceil, v)?,
            ("sigmoid", [v]) => map_scalars(k, v, &mut |k, x| {
                // 1 / (1 + exp(-x))
                let nx = k.b.neg(x);
                let e = k.b.un(UnOp::Exp, nx);
                let one = k.b.constant(1.0);
                let d = k.b.add(one, e);
                k.b.div(one, d)
            })?,
            ("min", [a, b]) => zip_scalars(k, a, b, &mut |k, x, y| k.b.bin(BinOp::Min, x, y))?,
            ("max", [a, b]) => zip_scalars(k, a, b, &mut |k, x, y| k.b.bin(BinOp::Max, x, y))?,
            ("clamp", [x, lo, hi]) => {
                let l = zip_scalars(k, x, lo, &mut |k, a, b| k.b.bin(BinOp::Max, a, b))?;
                zip_scalars(k, &l, hi, &mut |k, a, b| k.b.bin(BinOp::Min, a, b))?
            }
            ("len", [v]) => LVal::S(k.b.constant(v.items()?.len() as f64)),
            ("norm", [v]) => {
                let xs = flatten(v);
                let sq: Vec<V> = xs.iter().map(|&x| k.b.mul(x, x)).collect();
                let s = k.b.sum(&sq);
                LVal::S(k.b.un(UnOp::Sqrt, s))
            }
            ("dot", [a, b]) => {
                let (xa, xb) = (flatten(a), flatten(b));
                let prods: Vec<V> = xa.iter().zip(&xb).map(|(&x, &y)| k.b.mul(x, y)).collect();
                LVal::S(k.b.sum(&prods))
            }
            ("cross", [a, b]) => {
                let (a, b) = (flatten(a), flatten(b));
                let c = |k: &mut KernelBuilder, i: usize, j: usize| {
                    let p = k.b.mul(a[i], b[j]);
                    let q = k.b.mul(a[j], b[i]);
                    k.b.sub(p, q)
                };
                LVal::A(vec![
                    LVal::S(c(k, 1, 2)),
                    LVal::S(c(k, 2, 0)),
                    LVal::S(c(k, 0, 1)),
                ])
            }
            // ramp(t, T) = min(t / T, 1) for t ≥ 0.
            ("ramp", [t, d]) => {
                let q = k.b.div(t.scalar()?, d.scalar()?);
                let one = k.b.constant(1.0);
                let zero = k.b.constant(0.0);
                let m = k.b.bin(BinOp::Min, q, one);
                LVal::S(k.b.bin(BinOp::Max, m, zero))
            }
            // window(t, w) = ⌊t/w·(1 + 10⁻⁶) + 10⁻⁴⌋: a t that lands on a window's start (as
            // t = k·dt does when dt divides w) is in that window whatever the rounding of t
            // and of t/w — f32's, or a GPU's division, which Vulkan lets be 2.5 ulp off
            // (NVIDIA's 0.003f/0.001f is 2.9999998). Without the slack, a boundary step's
            // damping gradient went to the previous window's param on one backend only.
            ("window", [t, w]) => {
                let q = k.b.div(t.scalar()?, w.scalar()?);
                let q = k.b.scale(1.0 + WINDOW_SLACK_RELATIVE, q);
                let slack = k.b.constant(WINDOW_SLACK);
                let q = k.b.add(q, slack);
                LVal::S(k.b.un(UnOp::Floor, q))
            }
            ("step", [t, at]) => LVal::S(k.b.cmp(CmpOp::Ge, t.scalar()?, at.scalar()?)),
            _ => {
                return Err(LowerError::new(format!(
                    "`{name}` cannot be evaluated inside a kernel"
                )));
            }
        })
    }

    /// Bind call arguments (positional, then named, then defaults) to parameter names.
    pub fn bind(
        &mut self,
        k: &mut KernelBuilder,
        env: &Env,
        params: &[(&str, Option<&Expr>)],
        args: &[Arg],
    ) -> Result<Env, LowerError> {
        let mut bound = Env::new();
        let mut pos = 0;
        for a in args {
            let pname = match &a.name {
                Some(n) => n.clone(),
                None => {
                    let p = params
                        .get(pos)
                        .ok_or_else(|| LowerError::new("too many arguments"))?;
                    pos += 1;
                    p.0.to_string()
                }
            };
            let v = self.lower(k, env, &a.value)?;
            bound.insert(pname, v);
        }
        for (p, default) in params {
            if bound.contains_key(*p) {
                continue;
            }
            let d = default.ok_or_else(|| LowerError::new(format!("missing argument `{p}`")))?;
            let v = self.lower(k, &Env::new(), d)?;
            bound.insert(p.to_string(), v);
        }
        Ok(bound)
    }
}

type BinOp_ = hir::BinOp;

/// Uniforms for a param or input of the given declared shape: `NAME` or `NAME.i.j`.
fn uniforms(k: &mut KernelBuilder, prefix: &str, shape: &[Len]) -> LVal {
    let dims: Vec<usize> = shape
        .iter()
        .map(|s| match s {
            Len::Fixed(n) => *n,
            _ => 0,
        })
        .collect();
    fn build(k: &mut KernelBuilder, prefix: &str, dims: &[usize]) -> LVal {
        match dims.split_first() {
            None => LVal::S(k.uniform(prefix)),
            Some((&n, rest)) => LVal::A(
                (0..n)
                    .map(|i| build(k, &format!("{prefix}.{i}"), rest))
                    .collect(),
            ),
        }
    }
    build(k, prefix, &dims)
}

pub fn flatten(v: &LVal) -> Vec<V> {
    match v {
        LVal::S(x) => vec![*x],
        LVal::A(items) => items.iter().flat_map(flatten).collect(),
    }
}

fn map_scalars(
    k: &mut KernelBuilder,
    v: &LVal,
    f: &mut dyn FnMut(&mut KernelBuilder, V) -> V,
) -> Result<LVal, LowerError> {
    Ok(match v {
        LVal::S(x) => LVal::S(f(k, *x)),
        LVal::A(items) => LVal::A(
            items
                .iter()
                .map(|i| map_scalars(k, i, f))
                .collect::<Result<_, _>>()?,
        ),
    })
}

/// Elementwise with scalar broadcast.
fn zip_scalars(
    k: &mut KernelBuilder,
    a: &LVal,
    b: &LVal,
    f: &mut dyn FnMut(&mut KernelBuilder, V, V) -> V,
) -> Result<LVal, LowerError> {
    Ok(match (a, b) {
        (LVal::S(x), LVal::S(y)) => LVal::S(f(k, *x, *y)),
        (LVal::A(xs), LVal::S(_)) => LVal::A(
            xs.iter()
                .map(|x| zip_scalars(k, x, b, f))
                .collect::<Result<_, _>>()?,
        ),
        (LVal::S(_), LVal::A(ys)) => LVal::A(
            ys.iter()
                .map(|y| zip_scalars(k, a, y, f))
                .collect::<Result<_, _>>()?,
        ),
        (LVal::A(xs), LVal::A(ys)) if xs.len() == ys.len() => LVal::A(
            xs.iter()
                .zip(ys)
                .map(|(x, y)| zip_scalars(k, x, y, f))
                .collect::<Result<_, _>>()?,
        ),
        _ => return Err(LowerError::new("shapes differ")),
    })
}

fn matmul(k: &mut KernelBuilder, a: &LVal, b: &LVal) -> Result<LVal, LowerError> {
    let rows: Vec<Vec<V>> = a.items()?.iter().map(flatten).collect();
    match b {
        LVal::A(items) if items.iter().all(|i| matches!(i, LVal::S(_))) => {
            let x = flatten(b);
            Ok(LVal::A(
                rows.iter()
                    .map(|r| {
                        let p: Vec<V> = r.iter().zip(&x).map(|(&u, &w)| k.b.mul(u, w)).collect();
                        LVal::S(k.b.sum(&p))
                    })
                    .collect(),
            ))
        }
        LVal::A(brows) => {
            let bm: Vec<Vec<V>> = brows.iter().map(flatten).collect();
            let cols = bm.first().map_or(0, |r| r.len());
            Ok(LVal::A(
                rows.iter()
                    .map(|r| {
                        LVal::A(
                            (0..cols)
                                .map(|j| {
                                    let p: Vec<V> = r
                                        .iter()
                                        .enumerate()
                                        .map(|(i, &u)| k.b.mul(u, bm[i][j]))
                                        .collect();
                                    LVal::S(k.b.sum(&p))
                                })
                                .collect(),
                        )
                    })
                    .collect(),
            ))
        }
        LVal::S(_) => Err(LowerError::new("`@` needs a vector or matrix on the right")),
    }
}

/// `items[i]` for an index known only at run time (a windowed schedule `beta[window(t, w)]`):
/// a chain of selects, clamped to the last entry past the end.
fn select_index(k: &mut KernelBuilder, items: &[LVal], i: V) -> Result<LVal, LowerError> {
    let Some(last) = items.last() else {
        return Err(LowerError::new("index into an empty array"));
    };
    let mut acc = last.clone();
    for (j, item) in items.iter().enumerate().rev().skip(1) {
        let jv = k.b.constant(j as f64);
        let here = k.b.cmp(CmpOp::Le, i, jv);
        acc = zip_scalars(k, item, &acc, &mut |k, a, b| k.b.select(here, a, b))?;
    }
    Ok(acc)
}
