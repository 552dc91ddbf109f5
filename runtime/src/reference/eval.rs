//! A small tree-walking evaluator of the script's expressions, over [`Dual`] numbers.
//!
//! It works on the parsed AST directly (never on the kernel IR): numbers with units in SI,
//! arrays, names (locals, `let`s, params and inputs from the scene's uniform values, `t`, `dt`,
//! `pi`), user `fn`s and `controller`s with positional, named and default arguments, arithmetic
//! with scalar broadcast, comparisons and logic (1 for true, 0 for false), `if`, `@`, indexing
//! (a run-time index picks the first entry whose position is not below it, the last past the
//! end), `.x/.y/.z`, reductions over integer ranges and the built-in functions. A per-element
//! param (a field) has a value at the current element ([`Evaluator::element`]): the uniform
//! `param.NAME.i` of that element's entry `i` in the field's set.

use super::dual::Dual;
use softc_compiler::front::ast::*;
use softc_compiler::sema::units;
use std::collections::{BTreeMap, HashMap};

/// A value: a scalar or an array of values (vectors, matrices).
#[derive(Clone, Debug, PartialEq)]
pub enum Val {
    S(Dual),
    A(Vec<Val>),
}

impl Val {
    pub fn scalar(&self) -> Result<Dual, String> {
        match self {
            Val::S(x) => Ok(*x),
            Val::A(_) => Err("expected a scalar, found an array".into()),
        }
    }

    pub fn items(&self) -> Result<&[Val], String> {
        match self {
            Val::A(a) => Ok(a),
            Val::S(_) => Err("expected an array, found a scalar".into()),
        }
    }

    /// Every scalar, row-major.
    pub fn flat(&self) -> Vec<Dual> {
        match self {
            Val::S(x) => vec![*x],
            Val::A(items) => items.iter().flat_map(Val::flat).collect(),
        }
    }

    fn map(&self, f: &mut dyn FnMut(Dual) -> Dual) -> Val {
        match self {
            Val::S(x) => Val::S(f(*x)),
            Val::A(items) => Val::A(items.iter().map(|i| i.map(f)).collect()),
        }
    }
}

fn num(x: f64) -> Val {
    Val::S(Dual::constant(x))
}

fn truth(b: bool) -> Dual {
    Dual::constant(if b { 1.0 } else { 0.0 })
}

/// A reduction's running value with one more term.
fn combine(acc: Option<Val>, term: Val, op: ReduceOp) -> Result<Val, String> {
    match acc {
        None => Ok(term),
        Some(a) => zip(&a, &term, &mut |x, y| match op {
            ReduceOp::Sum | ReduceOp::Mean | ReduceOp::AreaMean => x + y,
            ReduceOp::Max => x.max(y),
            ReduceOp::Min => x.min(y),
        }),
    }
}

/// Elementwise with scalar broadcast.
fn zip(a: &Val, b: &Val, f: &mut dyn FnMut(Dual, Dual) -> Dual) -> Result<Val, String> {
    Ok(match (a, b) {
        (Val::S(x), Val::S(y)) => Val::S(f(*x, *y)),
        (Val::A(xs), Val::S(_)) => {
            Val::A(xs.iter().map(|x| zip(x, b, f)).collect::<Result<_, _>>()?)
        }
        (Val::S(_), Val::A(ys)) => {
            Val::A(ys.iter().map(|y| zip(a, y, f)).collect::<Result<_, _>>()?)
        }
        (Val::A(xs), Val::A(ys)) if xs.len() == ys.len() => Val::A(
            xs.iter()
                .zip(ys)
                .map(|(x, y)| zip(x, y, f))
                .collect::<Result<_, _>>()?,
        ),
        _ => return Err("array shapes differ".into()),
    })
}

/// Local bindings, chained: a scope sees its parent's names unless it shadows them.
pub struct Scope<'s> {
    pub vars: Vec<(&'s str, Val)>,
    pub parent: Option<&'s Scope<'s>>,
}

impl<'s> Scope<'s> {
    pub fn root() -> Scope<'s> {
        Scope {
            vars: Vec::new(),
            parent: None,
        }
    }

    fn get(&self, name: &str) -> Option<&Val> {
        let mut s = Some(self);
        while let Some(sc) = s {
            if let Some((_, v)) = sc.vars.iter().rev().find(|(n, _)| *n == name) {
                return Some(v);
            }
            s = sc.parent;
        }
        None
    }
}

/// The SI factor of a unit as written (`kg/m^3`).
pub fn unit_factor(u: &Unit) -> Result<f64, String> {
    let mut f = 1.0;
    for fac in &u.factors {
        let (k, _) =
            units::unit(&fac.name).ok_or_else(|| format!("unknown unit `{}`", fac.name))?;
        f *= k.powi(fac.power);
    }
    Ok(f)
}

/// Nesting bound for inlined lets and calls (the checker rejects recursion).
const MAX_DEPTH: usize = 64;

/// Evaluates expressions of one script (plus the prelude) at a time `t`.
pub struct Evaluator<'a> {
    items: HashMap<&'a str, &'a Item>,
    uniforms: &'a BTreeMap<String, f64>,
    pub t: f64,
    pub dt: f64,
    /// The element (kernel order) whose material constants are being evaluated, if any.
    pub element: Option<usize>,
    /// Per field: the entry of each element (kernel order), `None` outside its set.
    fields: HashMap<String, Vec<Option<usize>>>,
    /// How many field values were read (to tell per-element material constants apart).
    pub field_reads: usize,
    depth: usize,
    /// The sim block's lets (in scope in its expressions, not in functions or global lets).
    pub sim_lets: HashMap<&'a str, &'a Expr>,
    sim_scope: bool,
    /// Closed-loop control: the node state reductions over node sets read (positions,
    /// velocities, rest positions), and the sets.
    pub state: Option<NodeState>,
    pub node_sets: HashMap<String, Vec<u32>>,
    /// Reduction variables bound to a node.
    node_binders: Vec<(String, usize)>,
}

/// The node state a closed-loop expression reads (3 per node).
#[derive(Clone, Debug, Default)]
pub struct NodeState {
    pub x: Vec<[f64; 3]>,
    pub v: Vec<[f64; 3]>,
    pub x0: Vec<[f64; 3]>,
}

fn item_name(i: &Item) -> Option<&str> {
    Some(match &i.kind {
        ItemKind::Decl { name, .. } => &name.name,
        ItemKind::Material(m) => &m.name.name,
        ItemKind::Param(p) => &p.name.name,
        ItemKind::Input(p) => &p.name.name,
        ItemKind::Let(l) => &l.name.name,
        ItemKind::Fn(f) => &f.name.name,
        _ => return None,
    })
}

impl<'a> Evaluator<'a> {
    /// Names resolve in the user's script first, then in the prelude.
    pub fn new(
        script: &'a Script,
        prelude: &'a Script,
        uniforms: &'a BTreeMap<String, f64>,
    ) -> Self {
        let mut items = HashMap::new();
        for i in script.items.iter().chain(prelude.items.iter()) {
            if let Some(n) = item_name(i) {
                items.entry(n).or_insert(i);
            }
        }
        Evaluator {
            items,
            uniforms,
            t: 0.0,
            dt: 0.0,
            element: None,
            fields: HashMap::new(),
            field_reads: 0,
            depth: 0,
            sim_lets: HashMap::new(),
            sim_scope: true,
            state: None,
            node_sets: HashMap::new(),
            node_binders: Vec::new(),
        }
    }

    /// Evaluate a global definition's body: the sim block's lets are out of its scope.
    fn global(&mut self, env: &Scope, e: &'a Expr) -> Result<Val, String> {
        let scope = std::mem::replace(&mut self.sim_scope, false);
        let r = self.nested(env, e);
        self.sim_scope = scope;
        r
    }

    /// `x[n]`, `v[n]` or `x0[n]` of a node bound by a reduction over a node set.
    fn node_value(&self, env: &Scope, base: &Expr, indices: &[Expr]) -> Option<Val> {
        let (ExprKind::Name(b), [index]) = (&base.kind, indices) else {
            return None;
        };
        let ExprKind::Name(n) = &index.kind else {
            return None;
        };
        if env.get(&b.name).is_some() {
            return None;
        }
        let &(_, node) = self.node_binders.iter().rev().find(|(v, _)| *v == n.name)?;
        let state = self.state.as_ref()?;
        let p = match b.name.as_str() {
            "x" => state.x[node],
            "v" => state.v[node],
            "x0" => state.x0[node],
            _ => return None,
        };
        Some(Val::A(p.iter().map(|&c| num(c)).collect()))
    }

    /// Declare a per-element param: `entries[e]` is the entry of element `e` (kernel order).
    pub fn add_field(&mut self, name: &str, entries: Vec<Option<usize>>) {
        self.fields.insert(name.to_string(), entries);
    }

    pub fn find(&self, name: &str) -> Option<&'a Item> {
        self.items.get(name).copied()
    }

    pub fn eval(&mut self, env: &Scope, e: &'a Expr) -> Result<Val, String> {
        match &e.kind {
            ExprKind::Number { value, unit, .. } => {
                let f = unit.as_ref().map(unit_factor).transpose()?.unwrap_or(1.0);
                Ok(num(value * f))
            }
            ExprKind::Array { items, unit } => {
                let f = unit.as_ref().map(unit_factor).transpose()?.unwrap_or(1.0);
                let c = Dual::constant(f);
                let mut out = Vec::with_capacity(items.len());
                for it in items {
                    let v = self.eval(env, it)?;
                    out.push(if unit.is_some() {
                        v.map(&mut |x| x * c)
                    } else {
                        v
                    });
                }
                Ok(Val::A(out))
            }
            ExprKind::Bool(b) => Ok(Val::S(truth(*b))),
            ExprKind::Str(_) => Err("a string has no numeric value".into()),
            ExprKind::Paren(inner) => self.eval(env, inner),
            ExprKind::Name(id) => self.name(env, &id.name),
            ExprKind::Unary { op, operand } => {
                let v = self.eval(env, operand)?;
                Ok(match op {
                    UnaryOp::Neg => v.map(&mut |x| -x),
                    UnaryOp::Not => v.map(&mut |x| truth(x.v == 0.0)),
                })
            }
            ExprKind::Binary { op, lhs, rhs } => {
                let l = self.eval(env, lhs)?;
                let r = self.eval(env, rhs)?;
                // Scalar arithmetic, the common case, without the broadcasting machinery.
                if let (Val::S(x), Val::S(y)) = (&l, &r) {
                    let (x, y) = (*x, *y);
                    match op {
                        BinOp::Add => return Ok(Val::S(x + y)),
                        BinOp::Sub => return Ok(Val::S(x - y)),
                        BinOp::Mul => return Ok(Val::S(x * y)),
                        BinOp::Div => return Ok(Val::S(x / y)),
                        BinOp::Pow => return Ok(Val::S(x.pow(y))),
                        _ => {}
                    }
                }
                binary(*op, &l, &r)
            }
            ExprKind::If {
                cond,
                then,
                otherwise,
            } => {
                if self.eval(env, cond)?.scalar()?.v != 0.0 {
                    self.eval(env, then)
                } else {
                    self.eval(env, otherwise)
                }
            }
            ExprKind::Field { base, field } => {
                let b = self.eval(env, base)?;
                let i = match field.name.as_str() {
                    "x" => 0,
                    "y" => 1,
                    "z" => 2,
                    other => return Err(format!("no component `.{other}`")),
                };
                b.items()?
                    .get(i)
                    .cloned()
                    .ok_or_else(|| format!("`.{}` of a vector shorter than 3", field.name))
            }
            ExprKind::Index { base, indices } => {
                if let Some(v) = self.node_value(env, base, indices) {
                    return Ok(v);
                }
                let mut v = self.eval(env, base)?;
                for ie in indices {
                    let i = self.eval(env, ie)?.scalar()?.v;
                    let items = v.items()?;
                    if items.is_empty() {
                        return Err("index into an empty array".into());
                    }
                    // The first position j with i ≤ j; the last entry past the end.
                    let j = if i.is_nan() {
                        items.len() - 1
                    } else if i <= 0.0 {
                        0
                    } else {
                        (i.ceil() as usize).min(items.len() - 1)
                    };
                    v = items[j].clone();
                }
                Ok(v)
            }
            ExprKind::Reduce {
                op,
                var,
                domain,
                body,
            } => {
                if let ExprKind::Name(set) = &domain.kind
                    && let Some(nodes) = self.node_sets.get(&set.name).cloned()
                {
                    return self.node_reduction(env, *op, &var.name, &nodes, body);
                }
                let ExprKind::Binary {
                    op: BinOp::Range,
                    lhs,
                    rhs,
                } = &domain.kind
                else {
                    return Err(
                        "the reference oracle evaluates reductions over node sets and ranges \
                         in the simulation, not over element sets"
                            .into(),
                    );
                };
                let lo = self.eval(env, lhs)?.scalar()?.v as i64;
                let hi = self.eval(env, rhs)?.scalar()?.v as i64;
                let mut acc: Option<Val> = None;
                for i in lo..hi {
                    let inner = Scope {
                        vars: vec![(var.name.as_str(), num(i as f64))],
                        parent: Some(env),
                    };
                    let term = self.eval(&inner, body)?;
                    acc = Some(combine(acc, term, *op)?);
                }
                let n = (hi - lo).max(0) as f64;
                Ok(match (acc, op) {
                    (None, _) => num(0.0),
                    (Some(a), ReduceOp::Mean) => {
                        let inv = Dual::constant(1.0 / n);
                        a.map(&mut |x| x * inv)
                    }
                    (Some(a), _) => a,
                })
            }
            ExprKind::Call { callee, args } => {
                let ExprKind::Name(f) = &callee.kind else {
                    return Err("only named functions can be called".into());
                };
                self.call(env, &f.name, args)
            }
        }
    }

    /// A reduction over the nodes of a set (in the set's order) of the current node state.
    fn node_reduction(
        &mut self,
        env: &Scope,
        op: ReduceOp,
        var: &str,
        nodes: &[u32],
        body: &'a Expr,
    ) -> Result<Val, String> {
        if self.state.is_none() {
            return Err("a reduction over a node set needs the node state".into());
        }
        if op == ReduceOp::AreaMean {
            return Err(
                "the reference oracle does not evaluate `area_mean` (a loss it does not \
                 compare); use `mean` to check a scene against it"
                    .into(),
            );
        }
        let mut acc: Option<Val> = None;
        for &node in nodes {
            self.node_binders.push((var.to_string(), node as usize));
            let term = self.eval(env, body);
            self.node_binders.pop();
            acc = Some(combine(acc, term?, op)?);
        }
        Ok(match (acc, op) {
            (None, _) => num(0.0),
            (Some(a), ReduceOp::Mean) => {
                let inv = Dual::constant(1.0 / nodes.len() as f64);
                a.map(&mut |x| x * inv)
            }
            (Some(a), _) => a,
        })
    }

    fn nested(&mut self, env: &Scope, e: &'a Expr) -> Result<Val, String> {
        if self.depth >= MAX_DEPTH {
            return Err("definitions nested too deeply".into());
        }
        self.depth += 1;
        let r = self.eval(env, e);
        self.depth -= 1;
        r
    }

    fn name(&mut self, env: &Scope, name: &str) -> Result<Val, String> {
        if let Some(v) = env.get(name) {
            return Ok(v.clone());
        }
        match name {
            "t" => return Ok(num(self.t)),
            "dt" => return Ok(num(self.dt)),
            "pi" => return Ok(num(std::f64::consts::PI)),
            _ => {}
        }
        if self.sim_scope
            && let Some(&e) = self.sim_lets.get(name)
        {
            return self.nested(&Scope::root(), e);
        }
        let item = self
            .find(name)
            .ok_or_else(|| format!("`{name}` has no value in the simulation"))?;
        match &item.kind {
            ItemKind::Let(l) => self.global(&Scope::root(), &l.value),
            ItemKind::Param(p) => {
                if p.ty.shape.iter().any(|s| matches!(s, ShapeItem::Set(_))) {
                    let Some(e) = self.element else {
                        return Err(format!(
                            "the per-element param `{name}` has a value only at an element"
                        ));
                    };
                    let entry = self
                        .fields
                        .get(name)
                        .and_then(|f| f.get(e).copied().flatten())
                        .ok_or_else(|| {
                            format!("the per-element param `{name}` has no value at element {e}")
                        })?;
                    self.field_reads += 1;
                    let key = format!("param.{name}.{entry}");
                    return self
                        .uniforms
                        .get(&key)
                        .map(|&x| num(x))
                        .ok_or_else(|| format!("`{key}` has no value"));
                }
                self.uniform(&format!("param.{name}"), &p.ty)
            }
            ItemKind::Input(i) => self.uniform(&format!("input.{name}"), &i.ty),
            _ => Err(format!("`{name}` has no value in the simulation")),
        }
    }

    /// A param's or input's value from the scene's uniforms `PREFIX` or `PREFIX.i.j`.
    fn uniform(&self, prefix: &str, ty: &TypeExpr) -> Result<Val, String> {
        let dims: Vec<usize> = ty
            .shape
            .iter()
            .map(|s| match s {
                ShapeItem::Len(n, _) => n.parse().unwrap_or(0),
                _ => 0,
            })
            .collect();
        fn build(u: &BTreeMap<String, f64>, prefix: &str, dims: &[usize]) -> Result<Val, String> {
            match dims.split_first() {
                None => u
                    .get(prefix)
                    .map(|&x| num(x))
                    .ok_or_else(|| format!("`{prefix}` has no value")),
                Some((&n, rest)) => Ok(Val::A(
                    (0..n)
                        .map(|i| build(u, &format!("{prefix}.{i}"), rest))
                        .collect::<Result<_, _>>()?,
                )),
            }
        }
        build(self.uniforms, prefix, &dims)
    }

    /// Bind call arguments (positional, then named, then defaults evaluated in an empty scope).
    pub fn bind(
        &mut self,
        env: &Scope,
        params: &'a [FnParam],
        args: &'a [Arg],
    ) -> Result<Scope<'a>, String> {
        let mut vars: Vec<(&'a str, Val)> = Vec::new();
        let mut pos = 0;
        for a in args {
            let pname: &'a str = match &a.name {
                Some(n) => n.name.as_str(),
                None => {
                    let p = params.get(pos).ok_or("too many arguments")?;
                    pos += 1;
                    p.name.name.as_str()
                }
            };
            let v = self.eval(env, &a.value)?;
            vars.push((pname, v));
        }
        for p in params {
            if vars.iter().any(|(n, _)| *n == p.name.name) {
                continue;
            }
            let d = p
                .default
                .as_ref()
                .ok_or_else(|| format!("missing argument `{}`", p.name.name))?;
            let v = self.eval(&Scope::root(), d)?;
            vars.push((p.name.name.as_str(), v));
        }
        Ok(Scope { vars, parent: None })
    }

    fn call(&mut self, env: &Scope, name: &str, args: &'a [Arg]) -> Result<Val, String> {
        if let Some(item) = self.find(name)
            && let ItemKind::Fn(f) = &item.kind
        {
            let bound = self.bind(env, &f.params, args)?;
            return self.global(&bound, &f.body);
        }
        let vals: Vec<Val> = args
            .iter()
            .map(|a| self.eval(env, &a.value))
            .collect::<Result<_, _>>()?;
        let s = |v: &Val| v.scalar();
        Ok(match (name, vals.as_slice()) {
            ("sqrt", [v]) => v.map(&mut Dual::sqrt),
            ("abs", [v]) => v.map(&mut Dual::abs),
            ("exp", [v]) => v.map(&mut Dual::exp),
            ("ln", [v]) => v.map(&mut Dual::ln),
            ("log10", [v]) => v.map(&mut |x| x.ln() / Dual::constant(std::f64::consts::LN_10)),
            ("sin", [v]) => v.map(&mut Dual::sin),
            ("cos", [v]) => v.map(&mut Dual::cos),
            ("tan", [v]) => v.map(&mut Dual::tan),
            ("tanh", [v]) => v.map(&mut Dual::tanh),
            ("floor", [v]) => v.map(&mut Dual::floor),
            ("ceil", [v]) => v.map(&mut Dual::ceil),
            ("sigmoid", [v]) => v.map(&mut Dual::sigmoid),
            ("min", [a, b]) => zip(a, b, &mut Dual::min)?,
            ("max", [a, b]) => zip(a, b, &mut Dual::max)?,
            ("clamp", [x, lo, hi]) => {
                let l = zip(x, lo, &mut Dual::max)?;
                zip(&l, hi, &mut Dual::min)?
            }
            ("len", [v]) => num(v.items()?.len() as f64),
            ("norm", [v]) => {
                let sq = v
                    .flat()
                    .into_iter()
                    .fold(Dual::constant(0.0), |acc, x| acc + x * x);
                Val::S(sq.sqrt())
            }
            ("dot", [a, b]) => {
                let (xa, xb) = (a.flat(), b.flat());
                if xa.len() != xb.len() {
                    return Err("`dot` of vectors of different lengths".into());
                }
                Val::S(
                    xa.iter()
                        .zip(&xb)
                        .fold(Dual::constant(0.0), |acc, (&x, &y)| acc + x * y),
                )
            }
            ("cross", [a, b]) => {
                let (a, b) = (a.flat(), b.flat());
                if a.len() != 3 || b.len() != 3 {
                    return Err("`cross` needs two 3-vectors".into());
                }
                let c = |i: usize, j: usize| Val::S(a[i] * b[j] - a[j] * b[i]);
                Val::A(vec![c(1, 2), c(2, 0), c(0, 1)])
            }
            // ramp(t, T) = min(t / T, 1), and 0 before t = 0.
            ("ramp", [t, d]) => Val::S(
                (s(t)? / s(d)?)
                    .min(Dual::constant(1.0))
                    .max(Dual::constant(0.0)),
            ),
            // The index of the window of width w that t lies in; a t within 10⁻⁴ of a width
            // (and 10⁻⁶ of t/w) before a window's start counts as in it (SPEC.md: steps on a
            // boundary belong to the window they start, whatever the rounding).
            ("window", [t, w]) => {
                let q = s(t)? / s(w)?;
                Val::S((q * Dual::constant(1.0 + 1e-6) + Dual::constant(1e-4)).floor())
            }
            ("step", [t, at]) => Val::S(truth(s(t)?.v >= s(at)?.v)),
            _ => {
                return Err(format!(
                    "`{name}` with {} argument(s) cannot be evaluated in the simulation",
                    vals.len()
                ));
            }
        })
    }
}

fn binary(op: BinOp, l: &Val, r: &Val) -> Result<Val, String> {
    let cmp = |f: fn(f64, f64) -> bool| -> Result<Val, String> {
        Ok(Val::S(truth(f(l.scalar()?.v, r.scalar()?.v))))
    };
    match op {
        BinOp::Add => zip(l, r, &mut |x, y| x + y),
        BinOp::Sub => zip(l, r, &mut |x, y| x - y),
        BinOp::Mul => zip(l, r, &mut |x, y| x * y),
        BinOp::Div => zip(l, r, &mut |x, y| x / y),
        BinOp::Pow => zip(l, r, &mut Dual::pow),
        BinOp::MatMul => matmul(l, r),
        BinOp::And => Ok(Val::S(truth(l.scalar()?.v != 0.0 && r.scalar()?.v != 0.0))),
        BinOp::Or => Ok(Val::S(truth(l.scalar()?.v != 0.0 || r.scalar()?.v != 0.0))),
        BinOp::Eq => cmp(|a, b| a == b),
        BinOp::Ne => cmp(|a, b| a != b),
        BinOp::Lt => cmp(|a, b| a < b),
        BinOp::Le => cmp(|a, b| a <= b),
        BinOp::Gt => cmp(|a, b| a > b),
        BinOp::Ge => cmp(|a, b| a >= b),
        BinOp::Range => Err("a range has no value".into()),
    }
}

/// Matrix × vector or matrix × matrix.
fn matmul(a: &Val, b: &Val) -> Result<Val, String> {
    let rows: Vec<Vec<Dual>> = a.items()?.iter().map(Val::flat).collect();
    let dot = |r: &[Dual], c: &mut dyn Iterator<Item = Dual>| -> Result<Dual, String> {
        let mut acc = Dual::constant(0.0);
        let mut n = 0;
        for (x, y) in r.iter().zip(c) {
            acc = acc + *x * y;
            n += 1;
        }
        if n != r.len() {
            return Err("`@`: inner dimensions differ".into());
        }
        Ok(acc)
    };
    match b {
        Val::A(items) if items.iter().all(|i| matches!(i, Val::S(_))) => {
            let x = b.flat();
            if rows.iter().any(|r| r.len() != x.len()) {
                return Err("`@`: inner dimensions differ".into());
            }
            Ok(Val::A(
                rows.iter()
                    .map(|r| dot(r, &mut x.iter().copied()).map(Val::S))
                    .collect::<Result<_, _>>()?,
            ))
        }
        Val::A(brows) => {
            let bm: Vec<Vec<Dual>> = brows.iter().map(Val::flat).collect();
            let cols = bm.first().map_or(0, Vec::len);
            Ok(Val::A(
                rows.iter()
                    .map(|r| {
                        Ok(Val::A(
                            (0..cols)
                                .map(|j| dot(r, &mut bm.iter().map(|row| row[j])).map(Val::S))
                                .collect::<Result<_, String>>()?,
                        ))
                    })
                    .collect::<Result<_, String>>()?,
            ))
        }
        Val::S(_) => Err("`@` needs a vector or matrix on the right".into()),
    }
}
