//! Built-in functions and constants: their signatures and type rules.

use super::Checker;
use super::types::{Len, Obj, Ty, Typed, Value, Var};
use super::units::Dim;
use crate::diag::Diagnostic;
use crate::front::ast::*;

/// Named constants of non-numeric kinds (`integrator = semi_implicit_euler`).
pub const CONSTANTS: &[(&str, Obj)] = &[
    ("auto", Obj::Auto),
    ("none", Obj::None),
    ("fem", Obj::ForceModel),
    ("semi_implicit_euler", Obj::Integrator),
    ("quasi_static", Obj::Integrator),
    ("implicit_euler", Obj::Integrator),
    ("f32", Obj::Precision),
    ("f64", Obj::Precision),
    ("vtk", Obj::OutputKind),
    ("store_all", Obj::Checkpoint),
    ("constant", Obj::Schedule),
];

pub const FUNCTIONS: &[&str] = &[
    // math
    "sqrt",
    "abs",
    "exp",
    "ln",
    "log10",
    "sin",
    "cos",
    "tan",
    "tanh",
    "sigmoid",
    "floor",
    "ceil",
    "min",
    "max",
    "clamp",
    "norm",
    "dot",
    "cross",
    "len",
    // time
    "ramp",
    "window",
    "step",
    // geometry and selections
    "load",
    "box",
    "sphere",
    "cylinder",
    "surface",
    "select",
    "named",
    "tagged",
    "inside",
    // simulation
    "force",
    "stretch",
    "auto",
    "springs",
    "csv",
    // optimization
    "gd",
    "sgd",
    "adam",
    "nadam",
    "magnitude",
    "exponential",
    "step_decay",
    "cosine",
    "periodic",
    "revolve",
    "circle_quadrants",
];

/// Allowed range of a dimensionless constant argument.
#[derive(Clone, Copy)]
pub(super) enum Interval {
    Positive,
    /// [0, 1): momentum, Adam betas.
    BelowOne,
    /// (0, 1]: safety factors, decay rates.
    UpToOne,
}

fn length() -> Ty {
    Ty::scalar(Dim::LENGTH)
}

impl Checker {
    pub(super) fn check_builtin(&mut self, e: &Expr, id: &Ident, args: &[Arg]) -> Typed {
        let name = id.name.as_str();
        let sp = e.span;
        match name {
            "sqrt" | "abs" | "exp" | "ln" | "log10" | "sin" | "cos" | "tan" | "tanh"
            | "sigmoid" | "floor" | "ceil" => {
                let Some(s) = self.bind(name, sp, &[("x", true)], args) else {
                    return Typed::error();
                };
                let arg = s[0].unwrap();
                let t = self.check_expr(arg);
                let Ty::Num { dim, shape, .. } = t.ty.clone() else {
                    if !t.ty.is_error() {
                        let msg = format!("`{name}` needs a number, found {}", t.ty);
                        self.err(Diagnostic::error("E0203", arg.span, msg));
                    }
                    return Typed::error();
                };
                let (out_dim, f): (Dim, fn(f64) -> f64) = match name {
                    "sqrt" => match dim.powf(0.5) {
                        Some(d) => (d, f64::sqrt),
                        None => {
                            let msg =
                                format!("the square root of {} has no representable unit", t.ty);
                            self.err(Diagnostic::error("E0205", arg.span, msg));
                            return Typed::error();
                        }
                    },
                    "abs" => (dim, f64::abs),
                    _ => {
                        if !dim.is_none() {
                            let msg = format!(
                                "`{name}` needs a dimensionless argument, found {}",
                                self.describe(arg, &t.ty)
                            );
                            self.err(
                                Diagnostic::error("E0202", arg.span, msg).with_hint(
                                    "divide by a reference value to make it dimensionless",
                                ),
                            );
                            return Typed::error();
                        }
                        let f: fn(f64) -> f64 = match name {
                            "exp" => f64::exp,
                            "ln" => f64::ln,
                            "log10" => f64::log10,
                            "sin" => f64::sin,
                            "cos" => f64::cos,
                            "tan" => f64::tan,
                            "tanh" => f64::tanh,
                            "floor" => f64::floor,
                            "ceil" => f64::ceil,
                            _ => |x| 1.0 / (1.0 + (-x).exp()),
                        };
                        (Dim::NONE, f)
                    }
                };
                if name == "ln" || name == "log10" || name == "sqrt" {
                    let mut vals = Vec::new();
                    if let Some(v) = &t.value {
                        v.flatten(&mut vals);
                    }
                    let bad = vals
                        .iter()
                        .any(|v| if name == "sqrt" { *v < 0.0 } else { *v <= 0.0 });
                    if bad {
                        let msg = format!(
                            "`{name}` of a {} value",
                            if name == "sqrt" {
                                "negative"
                            } else {
                                "non-positive"
                            }
                        );
                        self.err(Diagnostic::error("E0209", arg.span, msg));
                        return Typed::error();
                    }
                }
                let int = matches!(name, "floor" | "ceil");
                Typed {
                    ty: Ty::Num {
                        dim: out_dim,
                        shape,
                        int,
                    },
                    var: t.var,
                    value: t.value.as_ref().and_then(|v| v.map(&f)),
                }
            }
            "min" | "max" => {
                let Some(s) = self.bind(name, sp, &[("a", true), ("b", true)], args) else {
                    return Typed::error();
                };
                let (a, b) = (s[0].unwrap(), s[1].unwrap());
                let ta = self.check_expr(a);
                let tb = self.check_expr(b);
                self.same_dim_pair(name, e, a, &ta, b, &tb, |x, y| {
                    if name == "min" { x.min(y) } else { x.max(y) }
                })
            }
            "clamp" => {
                let Some(s) = self.bind(name, sp, &[("x", true), ("lo", true), ("hi", true)], args)
                else {
                    return Typed::error();
                };
                let (x, lo, hi) = (s[0].unwrap(), s[1].unwrap(), s[2].unwrap());
                let tx = self.check_expr(x);
                let tlo = self.check_expr(lo);
                let thi = self.check_expr(hi);
                let low = self.same_dim_pair(name, e, x, &tx, lo, &tlo, f64::max);
                if low.ty.is_error() {
                    return low;
                }
                self.same_dim_pair(name, e, x, &low, hi, &thi, f64::min)
            }
            "norm" | "len" => {
                let Some(s) = self.bind(name, sp, &[("v", true)], args) else {
                    return Typed::error();
                };
                let arg = s[0].unwrap();
                let t = self.check_expr(arg);
                match &t.ty {
                    Ty::Error => t,
                    Ty::Num { dim, shape, .. } if !shape.is_empty() => {
                        if name == "len" {
                            let value = match &shape[0] {
                                Len::Fixed(n) => Some(Value::Num(*n as f64)),
                                _ => None,
                            };
                            let var = if value.is_some() {
                                Var::Const
                            } else {
                                t.var.max(Var::Const)
                            };
                            return Typed {
                                ty: Ty::int(),
                                var,
                                value,
                            };
                        }
                        let value = match &t.value {
                            Some(v) => {
                                let mut xs = Vec::new();
                                v.flatten(&mut xs);
                                Some(Value::Num(xs.iter().map(|x| x * x).sum::<f64>().sqrt()))
                            }
                            None => None,
                        };
                        Typed {
                            ty: Ty::scalar(*dim),
                            var: t.var,
                            value,
                        }
                    }
                    other => {
                        let msg = format!("`{name}` needs a vector, found {other}");
                        self.err(Diagnostic::error("E0204", arg.span, msg));
                        Typed::error()
                    }
                }
            }
            "force" => self.check_contact_force(e, args),
            "stretch" => self.check_stretch(e, args),
            "dot" | "cross" => {
                let Some(s) = self.bind(name, sp, &[("a", true), ("b", true)], args) else {
                    return Typed::error();
                };
                let (a, b) = (s[0].unwrap(), s[1].unwrap());
                let ta = self.check_expr(a);
                let tb = self.check_expr(b);
                if ta.ty.is_error() || tb.ty.is_error() {
                    return Typed::error();
                }
                let want_len = if name == "cross" { Some(3) } else { None };
                let ok = match (&ta.ty, &tb.ty) {
                    (Ty::Num { shape: sa, .. }, Ty::Num { shape: sb, .. }) => {
                        sa.len() == 1 && sa == sb && want_len.is_none_or(|n| sa[0] == Len::Fixed(n))
                    }
                    _ => false,
                };
                if !ok {
                    let msg = format!(
                        "`{name}` needs two vectors of the same length{}, found {} and {}",
                        if name == "cross" { " 3" } else { "" },
                        ta.ty,
                        tb.ty
                    );
                    self.err(Diagnostic::error("E0204", e.span, msg));
                    return Typed::error();
                }
                let dim = ta.ty.dim().unwrap().times(tb.ty.dim().unwrap());
                let ty = if name == "dot" {
                    Ty::scalar(dim)
                } else {
                    Ty::vec3(dim)
                };
                Typed::of(ty, ta.var.max(tb.var))
            }
            "ramp" | "window" | "step" => {
                let second = match name {
                    "ramp" => "duration",
                    "window" => "width",
                    _ => "at",
                };
                let Some(s) = self.bind(name, sp, &[("t", true), (second, true)], args) else {
                    return Typed::error();
                };
                let t = self.check_expr(s[0].unwrap());
                let w = self.check_expr(s[1].unwrap());
                let time = Ty::scalar(Dim::TIME);
                let ok1 = self.expect_type(
                    &t,
                    &time,
                    s[0].unwrap(),
                    &format!("the first argument of `{name}`"),
                );
                let ok2 = self.expect_type(&w, &time, s[1].unwrap(), &format!("`{second}`"));
                if !(ok1 && ok2) {
                    return Typed::error();
                }
                if name != "step" && w.num().is_some_and(|v| v <= 0.0) {
                    let msg = format!("`{second}` must be positive");
                    self.err(Diagnostic::error("E0321", s[1].unwrap().span, msg));
                    return Typed::error();
                }
                let ty = if name == "window" {
                    Ty::int()
                } else {
                    Ty::scalar(Dim::NONE)
                };
                if name == "window"
                    && let Some(width) = w.num()
                {
                    self.sim.windows.push((width, s[1].unwrap().span));
                }
                Typed::of(ty, t.var.max(w.var))
            }
            "load" => {
                let Some(s) = self.bind(
                    name,
                    sp,
                    &[("path", true), ("unit", false), ("order", false)],
                    args,
                ) else {
                    return Typed::error();
                };
                if let Some(o) = s[2] {
                    let t = self.check_expr(o);
                    if self.expect_type(&t, &Ty::int(), o, "`order`")
                        && self.expect_const(&t, o, "the element order")
                        && !matches!(t.num(), Some(v) if v == 1.0 || v == 2.0)
                        && t.num().is_some()
                    {
                        self.err(
                            Diagnostic::error("E0321", o.span, "the element order must be 1 or 2")
                                .with_hint(
                                    "`order: 1` for linear (4-node) tetrahedra, `order: 2` for \
                                 quadratic (10-node) ones",
                                ),
                        );
                    }
                    self.sim.quadratic = t.num() == Some(2.0);
                }
                let mut unit = 1e-3;
                if let Some(u) = s[1] {
                    let t = self.check_expr(u);
                    if self.expect_type(&t, &length(), u, "`unit`") {
                        self.expect_const(&t, u, "the mesh unit");
                        match t.num() {
                            Some(v) if v <= 0.0 => self.err(Diagnostic::error(
                                "E0321",
                                u.span,
                                "the mesh unit must be positive",
                            )),
                            Some(v) => unit = v,
                            None => {}
                        }
                    }
                }
                let p = self.check_expr(s[0].unwrap());
                if self.expect_type(&p, &Ty::Str, s[0].unwrap(), "the mesh path")
                    && let Some(Value::Str(path)) = &p.value
                    && self.check_mesh_path(path, s[0].unwrap().span)
                {
                    self.probe_mesh(path, unit, s[0].unwrap().span);
                }
                Typed::of(Ty::Obj(Obj::Mesh), Var::Const)
            }
            "box" | "sphere" | "cylinder" => {
                let params: &[(&str, bool)] = match name {
                    "box" => &[("min", true), ("max", true)],
                    "sphere" => &[("center", true), ("radius", true)],
                    _ => &[("start", true), ("end", true), ("radius", true)],
                };
                let Some(s) = self.bind(name, sp, params, args) else {
                    return Typed::error();
                };
                let mut vals = Vec::new();
                for ((pname, _), slot) in params.iter().zip(&s) {
                    let arg = slot.unwrap();
                    let t = self.check_expr(arg);
                    let want = if *pname == "radius" {
                        length()
                    } else {
                        Ty::vec3(Dim::LENGTH)
                    };
                    if self.expect_type(&t, &want, arg, &format!("`{pname}`")) {
                        self.expect_const(&t, arg, "a region");
                    }
                    vals.push((t, arg));
                }
                if name == "box" {
                    if let (Some(Value::Array(lo)), Some(Value::Array(hi))) =
                        (&vals[0].0.value, &vals[1].0.value)
                    {
                        for (axis, (a, b)) in ["x", "y", "z"].iter().zip(lo.iter().zip(hi)) {
                            if let (Some(a), Some(b)) = (a.as_f64(), b.as_f64())
                                && a >= b
                            {
                                let msg =
                                    format!("the box is empty: min.{axis} is not below max.{axis}");
                                self.err(
                                    Diagnostic::error("E0321", e.span, msg)
                                        .with_hint("swap min and max, or widen the box"),
                                );
                                break;
                            }
                        }
                    }
                } else if let Some(r) = vals.last().and_then(|(t, _)| t.num())
                    && r <= 0.0
                {
                    let arg = vals.last().unwrap().1;
                    self.err(Diagnostic::error(
                        "E0321",
                        arg.span,
                        "the radius must be positive",
                    ));
                }
                let values: Vec<_> = vals.iter().map(|(t, _)| t.value.clone()).collect();
                self.last_shape = super::mesh_probe::Shape::from_call(name, &values);
                Typed::of(Ty::Obj(Obj::Region), Var::Const)
            }
            "surface" => {
                let Some(s) = self.bind(
                    name,
                    sp,
                    &[("mesh", true), ("name", false), ("tag", false)],
                    args,
                ) else {
                    return Typed::error();
                };
                self.expect_mesh(s[0].unwrap());
                let mut given = 0;
                for (slot, want) in s[1..].iter().zip(["name", "tag"]) {
                    let Some(arg) = slot else { continue };
                    given += 1;
                    let t = self.check_expr(arg);
                    // A positional second argument may be a name or a tag.
                    let is_tag = t.ty.is_int_scalar();
                    let is_name = t.ty == Ty::Str;
                    if !(t.ty.is_error() || is_name || is_tag)
                        || (want == "tag" && !is_tag && !t.ty.is_error())
                    {
                        let msg = format!(
                            "a surface is chosen by its name (a string) or tag (an integer), found {}",
                            t.ty
                        );
                        self.err(Diagnostic::error("E0203", arg.span, msg));
                    } else if let Some(v) = &t.value
                        && (is_name || is_tag)
                    {
                        self.last_surface = match v {
                            Value::Str(s) => Some(super::mesh_probe::SurfaceRef::Name(s.clone())),
                            Value::Num(t) => Some(super::mesh_probe::SurfaceRef::Tag(*t as i32)),
                            _ => None,
                        };
                        self.check_surface_exists(arg, v);
                    }
                }
                if given != 1 {
                    self.err(
                        Diagnostic::error(
                            "E0106",
                            e.span,
                            if given == 0 {
                                "`surface` needs the surface's name or its tag"
                            } else {
                                "`surface` takes the surface's name or its tag, not both"
                            },
                        )
                        .with_hint("e.g. `surface(body, \"cavity\")` or `surface(body, tag: 2)`"),
                    );
                }
                Typed::of(Ty::Obj(Obj::Surface), Var::Const)
            }
            "select" | "named" | "tagged" | "inside" => {
                let second = match name {
                    "select" => "where",
                    "named" => "name",
                    "tagged" => "tag",
                    _ => "region",
                };
                let Some(s) = self.bind(name, sp, &[("mesh", true), (second, true)], args) else {
                    return Typed::error();
                };
                self.expect_mesh(s[0].unwrap());
                let arg = s[1].unwrap();
                let saved = self.ctx;
                self.ctx.coords = name == "select";
                self.ctx.time = false;
                self.ctx.state = false;
                let t = self.check_expr(arg);
                self.ctx = saved;
                let want = match name {
                    "select" => Ty::Bool,
                    "named" => Ty::Str,
                    "tagged" => Ty::int(),
                    _ => Ty::Obj(Obj::Region),
                };
                if self.expect_type(&t, &want, arg, &format!("`{second}`"))
                    && self.expect_const(&t, arg, "a selection")
                {
                    use super::mesh_probe::Selector;
                    self.last_selector = match (name, &t.value, &arg.kind) {
                        ("select", ..) => Some(Selector::Condition),
                        ("named", Some(Value::Str(n)), _) => Some(Selector::Named(n.clone())),
                        ("tagged", Some(Value::Num(tag)), _) => Some(Selector::Tagged(*tag as i32)),
                        ("inside", _, ExprKind::Name(r)) => Some(Selector::Inside(r.name.clone())),
                        _ => None,
                    };
                    match (name, &t.value) {
                        ("named", Some(Value::Str(n))) => self.check_name_exists(arg, n),
                        ("tagged", Some(Value::Num(tag))) => {
                            self.check_region_tag_exists(arg, *tag)
                        }
                        _ => {}
                    }
                }
                Typed::of(Ty::Obj(Obj::Selection), Var::Const)
            }
            "auto" => {
                let Some(s) = self.bind(name, sp, &[("safety", true)], args) else {
                    return Typed::error();
                };
                self.check_fraction(s[0].unwrap(), "`safety`", Interval::UpToOne);
                Typed::constant(Ty::Obj(Obj::Auto), Value::Str("auto".into()))
            }
            "springs" => {
                let Some(s) = self.bind(name, sp, &[("volume_stiffness", true)], args) else {
                    return Typed::error();
                };
                let arg = s[0].unwrap();
                let t = self.check_expr(arg);
                let want = Ty::scalar(Dim([6, -12, -12, 0]));
                if self.expect_type(&t, &want, arg, "`volume_stiffness` (thesis eq. 2.16, α)") {
                    self.expect_const(&t, arg, "the volume stiffness");
                }
                Typed::of(Ty::Obj(Obj::ForceModel), Var::Const)
            }
            "csv" => {
                let Some(s) = self.bind(name, sp, &[("set", true)], args) else {
                    return Typed::error();
                };
                let arg = s[0].unwrap();
                let t = self.check_expr(arg);
                self.expect_type(&t, &Ty::Obj(Obj::NodeSet), arg, "the argument of `csv`");
                Typed::of(Ty::Obj(Obj::OutputKind), Var::Const)
            }
            "gd" | "sgd" | "adam" | "nadam" => {
                let params: &[(&str, bool)] = match name {
                    "gd" => &[("lr", true)],
                    "sgd" => &[("lr", true), ("momentum", false)],
                    _ => &[
                        ("lr", true),
                        ("beta1", false),
                        ("beta2", false),
                        ("eps", false),
                    ],
                };
                let Some(s) = self.bind(name, sp, params, args) else {
                    return Typed::error();
                };
                for ((pname, _), slot) in params.iter().zip(&s) {
                    if let Some(arg) = slot {
                        let range = if matches!(*pname, "momentum" | "beta1" | "beta2") {
                            Interval::BelowOne
                        } else {
                            Interval::Positive
                        };
                        self.check_fraction(arg, &format!("`{pname}`"), range);
                    }
                }
                Typed::of(Ty::Obj(Obj::Optimizer), Var::Const)
            }
            "magnitude" => {
                let Some(s) = self.bind(name, sp, &[("m", true)], args) else {
                    return Typed::error();
                };
                self.check_fraction(
                    s[0].unwrap(),
                    "the threshold `m` (thesis eq. 5.5)",
                    Interval::Positive,
                );
                Typed::of(Ty::Obj(Obj::Normalizer), Var::Const)
            }
            "exponential" | "cosine" => {
                let pname = if name == "exponential" {
                    "gamma"
                } else {
                    "floor"
                };
                let Some(s) = self.bind(name, sp, &[(pname, name == "exponential")], args) else {
                    return Typed::error();
                };
                if let Some(arg) = s[0] {
                    let range = if name == "exponential" {
                        Interval::UpToOne
                    } else {
                        Interval::BelowOne
                    };
                    self.check_fraction(arg, &format!("`{pname}`"), range);
                }
                Typed::of(Ty::Obj(Obj::Schedule), Var::Const)
            }
            "step_decay" => {
                let Some(s) = self.bind(name, sp, &[("every", true), ("gamma", true)], args) else {
                    return Typed::error();
                };
                self.check_count(s[0].unwrap(), "`every`");
                self.check_fraction(s[1].unwrap(), "`gamma`", Interval::UpToOne);
                Typed::of(Ty::Obj(Obj::Schedule), Var::Const)
            }
            "periodic" | "revolve" => {
                let pname = if name == "periodic" {
                    "steps"
                } else {
                    "snapshots"
                };
                let Some(s) = self.bind(name, sp, &[(pname, true)], args) else {
                    return Typed::error();
                };
                self.check_count(s[0].unwrap(), &format!("`{pname}`"));
                Typed::of(Ty::Obj(Obj::Checkpoint), Var::Const)
            }
            "circle_quadrants" => {
                let params = [
                    ("radius", true),
                    ("plane", false),
                    ("center", false),
                    ("seed", false),
                ];
                let Some(s) = self.bind(name, sp, &params, args) else {
                    return Typed::error();
                };
                let r = self.check_expr(s[0].unwrap());
                if self.expect_type(&r, &length(), s[0].unwrap(), "`radius`")
                    && r.num().is_some_and(|v| v <= 0.0)
                {
                    self.err(Diagnostic::error(
                        "E0321",
                        s[0].unwrap().span,
                        "the radius must be positive",
                    ));
                }
                if let Some(p) = s[1] {
                    let t = self.check_expr(p);
                    if self.expect_type(&t, &Ty::Str, p, "`plane`")
                        && let Some(Value::Str(v)) = &t.value
                        && !["xy", "xz", "yz"].contains(&v.as_str())
                    {
                        let msg = format!("unknown plane \"{v}\"");
                        self.err(
                            Diagnostic::error("E0321", p.span, msg)
                                .with_hint("the planes are \"xy\", \"xz\" and \"yz\""),
                        );
                    }
                }
                if let Some(c) = s[2] {
                    let t = self.check_expr(c);
                    self.expect_type(&t, &Ty::vec3(Dim::LENGTH), c, "`center`");
                }
                if let Some(seed) = s[3] {
                    self.check_count_or_zero(seed, "`seed`");
                }
                Typed::of(Ty::Obj(Obj::BatchSource), Var::Const)
            }
            _ => unreachable!("builtin {name} without a rule"),
        }
    }

    #[allow(clippy::too_many_arguments)]
    fn same_dim_pair(
        &mut self,
        name: &str,
        e: &Expr,
        a: &Expr,
        ta: &Typed,
        b: &Expr,
        tb: &Typed,
        f: impl Fn(f64, f64) -> f64,
    ) -> Typed {
        if ta.ty.is_error() || tb.ty.is_error() {
            return Typed::error();
        }
        let (Some(da), Some(db)) = (ta.ty.dim(), tb.ty.dim()) else {
            let msg = format!("`{name}` needs numbers, found {} and {}", ta.ty, tb.ty);
            self.err(Diagnostic::error("E0203", e.span, msg));
            return Typed::error();
        };
        if da != db {
            let msg = format!(
                "`{name}` needs arguments of one dimension, found {} and {}",
                self.describe(a, &ta.ty),
                self.describe(b, &tb.ty)
            );
            self.err(Diagnostic::error("E0201", e.span, msg));
            return Typed::error();
        }
        let shape = if ta.ty.shape().is_empty() {
            tb.ty.shape().to_vec()
        } else {
            ta.ty.shape().to_vec()
        };
        if !ta.ty.shape().is_empty() && !tb.ty.shape().is_empty() && ta.ty.shape() != tb.ty.shape()
        {
            let msg = format!(
                "`{name}` needs equal shapes or a scalar, found {} and {}",
                ta.ty, tb.ty
            );
            self.err(Diagnostic::error("E0204", e.span, msg));
            return Typed::error();
        }
        let value = match (&ta.value, &tb.value) {
            (Some(x), Some(y)) => x.map2(y, &f),
            _ => None,
        };
        Typed {
            ty: Ty::Num {
                dim: da,
                shape,
                int: ta.ty.is_int_scalar() && tb.ty.is_int_scalar(),
            },
            var: ta.var.max(tb.var),
            value,
        }
    }

    fn expect_mesh(&mut self, arg: &Expr) {
        let t = self.check_expr(arg);
        self.expect_type(&t, &Ty::Obj(Obj::Mesh), arg, "the first argument");
    }

    /// A positive dimensionless constant (`below_one`: in [0, 1)).
    pub(super) fn check_fraction(
        &mut self,
        arg: &Expr,
        what: &str,
        range: Interval,
    ) -> Option<f64> {
        let t = self.check_expr(arg);
        if !self.expect_type(&t, &Ty::scalar(Dim::NONE), arg, what)
            || !self.expect_const(&t, arg, what)
        {
            return None;
        }
        let v = t.num()?;
        let (bad, rule) = match range {
            Interval::Positive => (v <= 0.0, "be positive"),
            Interval::BelowOne => (!(0.0..1.0).contains(&v), "lie in [0, 1)"),
            Interval::UpToOne => (!(v > 0.0 && v <= 1.0), "lie in (0, 1]"),
        };
        if bad {
            let msg = format!("{what} must {rule}, found {v}");
            self.err(Diagnostic::error("E0321", arg.span, msg));
            return None;
        }
        Some(v)
    }

    /// A positive integer constant.
    pub(super) fn check_count(&mut self, arg: &Expr, what: &str) -> Option<f64> {
        let v = self.check_count_or_zero(arg, what)?;
        if v < 1.0 {
            let msg = format!("{what} must be at least 1, found {v}");
            self.err(Diagnostic::error("E0321", arg.span, msg));
            return None;
        }
        Some(v)
    }

    pub(super) fn check_count_or_zero(&mut self, arg: &Expr, what: &str) -> Option<f64> {
        let t = self.check_expr(arg);
        if !self.expect_type(&t, &Ty::int(), arg, what) || !self.expect_const(&t, arg, what) {
            return None;
        }
        let v = t.num()?;
        if v < 0.0 {
            let msg = format!("{what} must not be negative, found {v}");
            self.err(Diagnostic::error("E0321", arg.span, msg));
            return None;
        }
        Some(v)
    }
}
