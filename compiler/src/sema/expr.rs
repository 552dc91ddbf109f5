//! Expression checking: types, units, variability and constant folding.

use super::types::{Len, Obj, Ty, Typed, Value, Var};
use super::units::{self, Dim};
use super::{Checker, SymKind};
use crate::diag::{Diagnostic, did_you_mean};
use crate::front::ast::*;

impl Checker {
    /// Check an expression. A constant that overflows or is undefined (`1e308 * 10`,
    /// `(-8)^(1/3)`) is an error here, so no infinity or NaN reaches the simulation.
    pub(super) fn check_expr(&mut self, e: &Expr) -> Typed {
        let t = self.check_expr_kind(e);
        let key = (self.in_prelude, e.span.start, e.span.end);
        self.hir.types.entry(key).or_insert_with(|| t.ty.clone());
        if let Some(v) = &t.value {
            let mut xs = Vec::new();
            v.flatten(&mut xs);
            if xs.iter().any(|x| !x.is_finite()) {
                let what = if xs.iter().any(|x| x.is_nan()) {
                    "is undefined (NaN)"
                } else {
                    "overflows to infinity"
                };
                self.err(
                    Diagnostic::error("E0004", e.span, format!("this constant {what}"))
                        .with_hint("check the magnitudes and signs of the values involved"),
                );
                return Typed::error();
            }
        }
        if let Some(d) = t.ty.dim()
            && d.is_extreme()
        {
            self.err(Diagnostic::error(
                "E0205",
                e.span,
                "the unit of this expression has an exponent beyond ±64",
            ));
            return Typed::error();
        }
        t
    }

    fn check_expr_kind(&mut self, e: &Expr) -> Typed {
        match &e.kind {
            ExprKind::Number {
                value,
                is_int,
                unit,
                ..
            } => match unit {
                None => {
                    let ty = if *is_int {
                        Ty::int()
                    } else {
                        Ty::scalar(Dim::NONE)
                    };
                    Typed::constant(ty, Value::Num(*value))
                }
                Some(u) => match self.resolve_unit(u) {
                    Some((factor, dim)) => {
                        Typed::constant(Ty::scalar(dim), Value::Num(value * factor))
                    }
                    None => Typed::error(),
                },
            },
            ExprKind::Array { items, unit } => self.check_array(e, items, unit.as_ref()),
            ExprKind::Str(s) => Typed::constant(Ty::Str, Value::Str(s.clone())),
            ExprKind::Bool(b) => Typed::constant(Ty::Bool, Value::Bool(*b)),
            ExprKind::Name(id) => self.check_name(id),
            ExprKind::Paren(inner) => self.check_expr(inner),
            ExprKind::Unary { op, operand } => {
                let t = self.check_expr(operand);
                match (op, &t.ty) {
                    (_, Ty::Error) => t,
                    (UnaryOp::Neg, Ty::Num { .. }) => Typed {
                        value: t.value.as_ref().and_then(|v| v.map(&|x| -x)),
                        ..t
                    },
                    (UnaryOp::Not, Ty::Bool) => Typed {
                        value: match t.value {
                            Some(Value::Bool(b)) => Some(Value::Bool(!b)),
                            _ => None,
                        },
                        ..t
                    },
                    (UnaryOp::Neg, other) => {
                        let msg = format!("cannot negate {other}");
                        self.err(Diagnostic::error("E0203", e.span, msg));
                        Typed::error()
                    }
                    (UnaryOp::Not, other) => {
                        let msg = format!("`not` needs a condition, found {other}");
                        self.err(Diagnostic::error("E0207", e.span, msg));
                        Typed::error()
                    }
                }
            }
            ExprKind::Binary { op, lhs, rhs } => self.check_binary(e, *op, lhs, rhs),
            ExprKind::Call { callee, args } => self.check_call(e, callee, args),
            ExprKind::Index { base, indices } => self.check_index(e, base, indices),
            ExprKind::Field { base, field } => {
                let t = self.check_expr(base);
                match &t.ty {
                    Ty::Error => t,
                    Ty::Num { dim, shape, .. }
                        if shape.len() == 1
                            && shape[0] == Len::Fixed(3)
                            && ["x", "y", "z"].contains(&field.name.as_str()) =>
                    {
                        let i = ["x", "y", "z"]
                            .iter()
                            .position(|c| *c == field.name)
                            .unwrap();
                        let value = match &t.value {
                            Some(Value::Array(items)) => items.get(i).cloned(),
                            _ => None,
                        };
                        Typed {
                            ty: Ty::scalar(*dim),
                            var: t.var,
                            value,
                        }
                    }
                    other => {
                        let msg = if matches!(other, Ty::Num { shape, .. } if shape.len() == 1 && shape[0] == Len::Fixed(3))
                        {
                            format!("unknown component `.{}`", field.name)
                        } else {
                            format!("`.{}` needs a 3-vector, found {other}", field.name)
                        };
                        self.err(
                            Diagnostic::error("E0203", field.span, msg)
                                .with_hint("3-vectors have the components .x, .y and .z"),
                        );
                        Typed::error()
                    }
                }
            }
            ExprKind::Reduce {
                op,
                var,
                domain,
                body,
            } => self.check_reduce(*op, var, domain, body, e.span),
            ExprKind::If {
                cond,
                then,
                otherwise,
            } => {
                let c = self.check_expr(cond);
                if !matches!(c.ty, Ty::Bool | Ty::Error) {
                    let msg = format!(
                        "the condition of `if` must be true or false, found {}",
                        c.ty
                    );
                    self.err(Diagnostic::error("E0207", cond.span, msg));
                }
                let a = self.check_expr(then);
                let b = self.check_expr(otherwise);
                let ty = if a.ty.is_error() || b.ty.is_error() {
                    Ty::Error
                } else if !same_type(&a.ty, &b.ty) {
                    let msg = format!(
                        "the branches of `if` differ: {} and {}",
                        self.describe(then, &a.ty),
                        self.describe(otherwise, &b.ty)
                    );
                    self.err(Diagnostic::error("E0201", e.span, msg));
                    Ty::Error
                } else {
                    a.ty.clone()
                };
                let value = match c.value {
                    Some(Value::Bool(true)) => a.value.clone(),
                    Some(Value::Bool(false)) => b.value.clone(),
                    _ => None,
                };
                Typed {
                    ty,
                    var: c.var.max(a.var).max(b.var),
                    value,
                }
            }
        }
    }

    /// A description for messages: the dimension, with the unit when the user wrote one.
    pub(super) fn describe(&self, e: &Expr, ty: &Ty) -> String {
        match &e.kind {
            ExprKind::Number { unit: Some(u), .. } | ExprKind::Array { unit: Some(u), .. } => {
                format!("{ty} ({u})")
            }
            ExprKind::Paren(inner) => self.describe(inner, ty),
            _ => ty.to_string(),
        }
    }

    pub(super) fn resolve_unit(&mut self, u: &Unit) -> Option<(f64, Dim)> {
        let mut factor = 1.0;
        let mut dim = Dim::NONE;
        let mut ok = true;
        for f in &u.factors {
            match units::unit(&f.name) {
                Some((k, d)) => {
                    factor *= k.powi(f.power);
                    dim = dim.times(d.powi(f.power).unwrap_or(Dim::NONE));
                }
                None => {
                    ok = false;
                    let mut d =
                        Diagnostic::error("E0103", f.span, format!("unknown unit `{}`", f.name));
                    let digits = f.name.trim_start_matches(|c: char| !c.is_ascii_digit());
                    let stem = &f.name[..f.name.len() - digits.len()];
                    if let Some(h) = units::unit_hint(&f.name) {
                        d = d.with_hint(h);
                    } else if !digits.is_empty()
                        && digits.bytes().all(|b| b.is_ascii_digit())
                        && units::unit(stem).is_some()
                    {
                        d = d.with_hint(format!("powers of units need `^`: `{stem}^{digits}`"));
                    } else if self.globals.contains_key(&f.name)
                        || super::builtins::FUNCTIONS.contains(&f.name.as_str())
                        || super::RESERVED_NAMES.contains(&f.name.as_str())
                    {
                        d = d.with_hint(format!(
                            "a name right after a number is read as a unit; to multiply, write `* {}`",
                            f.name
                        ));
                    } else if let Some(s) = did_you_mean(&f.name, units::UNIT_NAMES.iter().copied())
                    {
                        d = d.with_hint(format!("did you mean `{s}`?"));
                    } else {
                        d = d.with_hint(format!("known units: {}", units::UNIT_NAMES.join(", ")));
                    }
                    self.err(d);
                }
            }
        }
        ok.then_some((factor, dim))
    }

    fn check_array(&mut self, e: &Expr, items: &[Expr], unit: Option<&Unit>) -> Typed {
        let (factor, unit_dim) = match unit {
            Some(u) => match self.resolve_unit(u) {
                Some(x) => x,
                None => return Typed::error(),
            },
            None => (1.0, Dim::NONE),
        };
        if items.is_empty() {
            self.err(
                Diagnostic::error("E0204", e.span, "empty array")
                    .with_hint("arrays need at least one entry"),
            );
            return Typed::error();
        }
        let mut elem: Option<(Ty, &Expr)> = None;
        let mut var = Var::Const;
        let mut values = Some(Vec::new());
        let mut failed = false;
        for it in items {
            let t = self.check_expr(it);
            var = var.max(t.var);
            if t.ty.is_error() {
                failed = true;
                continue;
            }
            if let Some(u) = unit
                && !matches!(t.ty.dim(), Some(d) if d.is_none())
            {
                if failed {
                    continue; // one report for the whole array
                }
                let msg = format!(
                    "this entry already has a unit ({}), and the array has the unit `{u}`",
                    self.describe(it, &t.ty),
                );
                self.err(
                    Diagnostic::error("E0201", it.span, msg)
                        .with_hint("give the unit once: after the array, or on every entry"),
                );
                failed = true;
                continue;
            }
            if !matches!(t.ty, Ty::Num { .. }) {
                let msg = format!("array entries must be numbers, found {}", t.ty);
                self.err(Diagnostic::error("E0203", it.span, msg));
                failed = true;
                continue;
            }
            match &elem {
                None => elem = Some((t.ty.clone(), it)),
                Some((first, first_expr)) => {
                    if first.dim() != t.ty.dim() {
                        let msg = format!(
                            "array entries differ in dimension: {} and {}",
                            self.describe(first_expr, first),
                            self.describe(it, &t.ty)
                        );
                        self.err(Diagnostic::error("E0201", it.span, msg));
                        failed = true;
                    } else if first.shape() != t.ty.shape() {
                        let msg = format!("array entries differ in shape: {} and {}", first, t.ty);
                        self.err(Diagnostic::error("E0204", it.span, msg));
                        failed = true;
                    }
                }
            }
            match (&mut values, &t.value) {
                (Some(vs), Some(v)) => vs.push(v.clone()),
                _ => values = None,
            }
        }
        if failed {
            return Typed::error();
        }
        let (first, _) = elem.unwrap();
        let (dim, inner_shape, int) = match first {
            Ty::Num { dim, shape, int } => (dim, shape, int),
            _ => unreachable!(),
        };
        let mut shape = vec![Len::Fixed(items.len())];
        shape.extend(inner_shape);
        let ty = Ty::Num {
            dim: if unit.is_some() { unit_dim } else { dim },
            shape,
            int: int && unit.is_none(),
        };
        let value = values.map(|vs| {
            let arr = Value::Array(vs);
            if unit.is_some() {
                arr.map(&|x| x * factor).unwrap_or(arr)
            } else {
                arr
            }
        });
        Typed { ty, var, value }
    }

    fn check_name(&mut self, id: &Ident) -> Typed {
        let name = id.name.as_str();
        if let Some((t, def, implicit)) = self.lookup_local_def(name) {
            self.record_use(id, def);
            let to = if implicit {
                super::hir::Name::Implicit(name.to_string())
            } else {
                super::hir::Name::Local(name.to_string())
            };
            self.resolve_name(id, to);
            return t;
        }
        // Not a local: the script can only have declared it as a global (implicit names such
        // as `t` and `x` are reserved).
        match self.globals.get(name).copied() {
            Some(g) => {
                self.record_global_use(id, g);
                self.resolve_name(id, super::hir::Name::Global(g));
            }
            None => {
                self.record_use(id, None);
                self.resolve_name(id, super::hir::Name::Implicit(name.to_string()));
            }
        }
        match name {
            "t" if self.ctx.time => return Typed::of(Ty::scalar(Dim::TIME), Var::Time),
            "x" | "y" | "z" if self.ctx.coords => {
                return Typed::of(Ty::scalar(Dim::LENGTH), Var::Const);
            }
            "x" | "x0" | "v" if self.ctx.state => {
                return Typed::of(Ty::Obj(Obj::StateField), Var::State);
            }
            "t_end" | "dt" if self.sim.defining_duration => {
                let msg =
                    format!("`{name}` is defined by the sim block's `dt`, `steps` and `duration`");
                self.err(
                    Diagnostic::error("E0120", id.span, msg)
                        .with_hint("give `dt`, `steps` and `duration` as plain values"),
                );
                return Typed::error();
            }
            "dt" => {
                return match self.sim.dt {
                    Some(d) => Typed::constant(Ty::scalar(Dim::TIME), Value::Num(d)),
                    None => Typed::of(Ty::scalar(Dim::TIME), Var::Const),
                };
            }
            "t_end" => {
                return match self.sim.duration {
                    Some(d) => Typed::constant(Ty::scalar(Dim::TIME), Value::Num(d)),
                    None => Typed::of(Ty::scalar(Dim::TIME), Var::Const),
                };
            }
            "pi" => {
                return Typed::constant(Ty::scalar(Dim::NONE), Value::Num(std::f64::consts::PI));
            }
            _ => {}
        }
        if let Some(&gid) = self.globals.get(name) {
            self.syms[gid].used = true;
            return match self.syms[gid].kind {
                SymKind::Fn | SymKind::Controller => {
                    let msg = format!("`{name}` is a function; call it with arguments");
                    self.err(Diagnostic::error("E0110", id.span, msg));
                    Typed::error()
                }
                _ => self.global_typed_at(gid, Some(id.span)),
            };
        }
        if let Some((_, obj)) = super::builtins::CONSTANTS.iter().find(|(n, _)| *n == name) {
            return Typed::constant(Ty::Obj(*obj), Value::Str(name.to_string()));
        }
        let d = match name {
            "t" => Diagnostic::error(
                "E0320",
                id.span,
                "the time `t` cannot be used here: it changes during the simulation",
            )
            .with_hint("`t` is read in the sim block, the loss, `let`s and controllers; geometry, materials and parameter values are fixed before the run"),
            "x" | "x0" | "v" => Diagnostic::error(
                "E0320",
                id.span,
                format!("the node state `{name}` cannot be used here: it belongs to the simulation"),
            )
            .with_hint("node state is read in the sim block, the loss, `let`s and controllers, as `x[n]` with `n` bound by `sum(n in set)`"),
            "y" | "z" => Diagnostic::error(
                "E0320",
                id.span,
                format!("the coordinate `{name}` is only available inside `select(mesh, …)`"),
            ),
            "I1bar" | "I2bar" | "J" => Diagnostic::error(
                "E0320",
                id.span,
                format!("the invariant `{name}` is only available in a strain energy `W(…)`"),
            )
            .with_hint("list it in the energy's arguments: `W(I1bar, I2bar, J) = …`"),
            _ if super::builtins::FUNCTIONS.contains(&name) => Diagnostic::error(
                "E0110",
                id.span,
                format!("`{name}` is a built-in function; call it with arguments"),
            ),
            _ => self.unknown_name(name, id.span),
        };
        self.err(d);
        Typed::error()
    }

    fn check_binary(&mut self, e: &Expr, op: BinOp, lhs: &Expr, rhs: &Expr) -> Typed {
        let l = self.check_expr(lhs);
        let r = self.check_expr(rhs);
        if l.ty.is_error() || r.ty.is_error() {
            return Typed::error();
        }
        let var = l.var.max(r.var);
        match op {
            BinOp::And | BinOp::Or => {
                for (t, x) in [(&l, lhs), (&r, rhs)] {
                    if t.ty != Ty::Bool {
                        let msg = format!(
                            "`{}` needs conditions on both sides, found {}",
                            op.symbol(),
                            self.describe(x, &t.ty)
                        );
                        self.err(Diagnostic::error("E0207", x.span, msg));
                        return Typed::error();
                    }
                }
                let value = match (&l.value, &r.value) {
                    (Some(Value::Bool(a)), Some(Value::Bool(b))) => {
                        Some(Value::Bool(if op == BinOp::And {
                            *a && *b
                        } else {
                            *a || *b
                        }))
                    }
                    _ => None,
                };
                Typed {
                    ty: Ty::Bool,
                    var,
                    value,
                }
            }
            BinOp::Eq | BinOp::Ne | BinOp::Lt | BinOp::Le | BinOp::Gt | BinOp::Ge => {
                let (Some(ld), Some(rd)) = (l.ty.dim(), r.ty.dim()) else {
                    let msg = format!(
                        "cannot compare {} with {}",
                        self.describe(lhs, &l.ty),
                        self.describe(rhs, &r.ty)
                    );
                    self.err(Diagnostic::error("E0203", e.span, msg));
                    return Typed::error();
                };
                if ld != rd {
                    let msg = format!(
                        "cannot compare {} with {}",
                        self.describe(lhs, &l.ty),
                        self.describe(rhs, &r.ty)
                    );
                    self.err(
                        Diagnostic::error("E0201", e.span, msg)
                            .with_hint("both sides of a comparison need the same dimension"),
                    );
                    return Typed::error();
                }
                if !l.ty.is_scalar_num() || !r.ty.is_scalar_num() {
                    let msg = format!("comparisons need scalars, found {} and {}", l.ty, r.ty);
                    self.err(Diagnostic::error("E0204", e.span, msg));
                    return Typed::error();
                }
                let value = match (l.num(), r.num()) {
                    (Some(a), Some(b)) => Some(Value::Bool(match op {
                        BinOp::Eq => a == b,
                        BinOp::Ne => a != b,
                        BinOp::Lt => a < b,
                        BinOp::Le => a <= b,
                        BinOp::Gt => a > b,
                        _ => a >= b,
                    })),
                    _ => None,
                };
                Typed {
                    ty: Ty::Bool,
                    var,
                    value,
                }
            }
            BinOp::Range => {
                for (t, x) in [(&l, lhs), (&r, rhs)] {
                    if !t.ty.is_int_scalar() {
                        let d = self.integer_error(x, t, "a range end");
                        self.err(d);
                        return Typed::error();
                    }
                }
                Typed::of(Ty::Obj(Obj::Range), var)
            }
            BinOp::Add | BinOp::Sub | BinOp::Mul | BinOp::Div | BinOp::MatMul | BinOp::Pow => {
                self.check_arith(e, op, lhs, rhs, l, r)
            }
        }
    }

    fn check_arith(
        &mut self,
        e: &Expr,
        op: BinOp,
        lhs: &Expr,
        rhs: &Expr,
        l: Typed,
        r: Typed,
    ) -> Typed {
        let var = l.var.max(r.var);
        let (
            Ty::Num {
                dim: ld,
                shape: ls,
                int: li,
            },
            Ty::Num {
                dim: rd,
                shape: rs,
                int: ri,
            },
        ) = (&l.ty, &r.ty)
        else {
            let verb = match op {
                BinOp::Add => "add",
                BinOp::Sub => "subtract",
                BinOp::Mul | BinOp::MatMul => "multiply",
                BinOp::Div => "divide",
                _ => "raise",
            };
            let msg = format!(
                "cannot {verb} {} and {}",
                self.describe(lhs, &l.ty),
                self.describe(rhs, &r.ty)
            );
            self.err(Diagnostic::error("E0203", e.span, msg));
            return Typed::error();
        };
        let (ld, rd) = (*ld, *rd);
        match op {
            BinOp::Add | BinOp::Sub => {
                if ld != rd {
                    let verb = if op == BinOp::Add { "add" } else { "subtract" };
                    let (a, b) = (self.describe(lhs, &l.ty), self.describe(rhs, &r.ty));
                    let msg = if op == BinOp::Add {
                        format!("cannot {verb} {a} and {b}")
                    } else {
                        format!("cannot {verb} {b} from {a}")
                    };
                    self.err(
                        Diagnostic::error("E0201", e.span, msg)
                            .with_hint("both sides of `+` and `-` need the same dimension"),
                    );
                    return Typed::error();
                }
                let Some(shape) = self.broadcast(e, ls, rs) else {
                    return Typed::error();
                };
                let value = fold2(&l, &r, |a, b| if op == BinOp::Add { a + b } else { a - b });
                Typed {
                    ty: Ty::Num {
                        dim: ld,
                        shape,
                        int: *li && *ri,
                    },
                    var,
                    value,
                }
            }
            BinOp::Mul | BinOp::Div => {
                let Some(shape) = self.broadcast(e, ls, rs) else {
                    return Typed::error();
                };
                if op == BinOp::Div && r.num() == Some(0.0) {
                    self.err(Diagnostic::error("E0208", rhs.span, "division by zero"));
                    return Typed::error();
                }
                let dim = if op == BinOp::Mul {
                    ld.times(rd)
                } else {
                    ld.per(rd)
                };
                let value = fold2(&l, &r, |a, b| if op == BinOp::Mul { a * b } else { a / b });
                Typed {
                    ty: Ty::Num {
                        dim,
                        shape,
                        int: *li && *ri && op == BinOp::Mul,
                    },
                    var,
                    value,
                }
            }
            BinOp::MatMul => {
                let inner_ok = match (ls.len(), rs.len()) {
                    (2, 1) | (2, 2) => ls[1] == rs[0],
                    _ => false,
                };
                if !inner_ok {
                    let msg = format!(
                        "`@` needs a matrix on the left and a matching vector or matrix on the right, found {} @ {}",
                        l.ty, r.ty
                    );
                    self.err(Diagnostic::error("E0204", e.span, msg));
                    return Typed::error();
                }
                let mut shape = vec![ls[0].clone()];
                if rs.len() == 2 {
                    shape.push(rs[1].clone());
                }
                Typed {
                    ty: Ty::Num {
                        dim: ld.times(rd),
                        shape,
                        int: false,
                    },
                    var,
                    value: None,
                }
            }
            _ => {
                // Pow
                if !rd.is_none() || !rs.is_empty() {
                    let msg = format!(
                        "the exponent must be a dimensionless scalar, found {}",
                        self.describe(rhs, &r.ty)
                    );
                    self.err(Diagnostic::error("E0205", rhs.span, msg));
                    return Typed::error();
                }
                let dim = if ld.is_none() {
                    Dim::NONE
                } else {
                    match r.num() {
                        None => {
                            let msg = format!(
                                "{} can only be raised to a constant power",
                                self.describe(lhs, &l.ty)
                            );
                            self.err(Diagnostic::error("E0205", rhs.span, msg).with_hint(
                                "the result's unit must be known when the script is compiled",
                            ));
                            return Typed::error();
                        }
                        Some(p) => match ld.powf(p) {
                            Some(d) => d,
                            None => {
                                let msg = format!(
                                    "{} raised to {p} has no representable unit",
                                    self.describe(lhs, &l.ty)
                                );
                                self.err(Diagnostic::error("E0205", rhs.span, msg).with_hint(
                                    "powers of dimensioned values must be multiples of 1/6",
                                ));
                                return Typed::error();
                            }
                        },
                    }
                };
                let value = fold2(&l, &r, f64::powf);
                let int = *li && *ri && r.num().is_some_and(|p| p >= 0.0);
                Typed {
                    ty: Ty::Num {
                        dim,
                        shape: ls.clone(),
                        int,
                    },
                    var,
                    value,
                }
            }
        }
    }

    /// Shapes of an elementwise operation: equal, or one side scalar.
    fn broadcast(&mut self, e: &Expr, a: &[Len], b: &[Len]) -> Option<Vec<Len>> {
        if a.is_empty() {
            Some(b.to_vec())
        } else if b.is_empty() || a == b || b.contains(&Len::Any) || a.contains(&Len::Any) {
            Some(a.to_vec())
        } else {
            let msg = format!(
                "shapes differ: [{}] and [{}]",
                a.iter()
                    .map(|l| l.to_string())
                    .collect::<Vec<_>>()
                    .join(", "),
                b.iter()
                    .map(|l| l.to_string())
                    .collect::<Vec<_>>()
                    .join(", ")
            );
            self.err(
                Diagnostic::error("E0204", e.span, msg)
                    .with_hint("elementwise operations need equal shapes or a scalar"),
            );
            None
        }
    }

    fn check_index(&mut self, e: &Expr, base: &Expr, indices: &[Expr]) -> Typed {
        let b = self.check_expr(base);
        let idx: Vec<Typed> = indices.iter().map(|i| self.check_expr(i)).collect();
        if b.ty.is_error() || idx.iter().any(|t| t.ty.is_error()) {
            return Typed::error();
        }
        let mut var = b.var;
        for t in &idx {
            var = var.max(t.var);
        }
        // Node state: x[n], x0[n], v[n].
        if b.ty == Ty::Obj(Obj::StateField) {
            let name = match &base.kind {
                ExprKind::Name(id) => id.name.as_str(),
                _ => "x",
            };
            if idx.len() != 1 || idx[0].ty != Ty::Obj(Obj::Node) {
                let msg = format!(
                    "`{name}[…]` is indexed by one node bound in `sum(n in set)`, `mean(n in set)`, …"
                );
                self.err(
                    Diagnostic::error("E0314", e.span, msg)
                        .with_hint(format!("for example `sum(n in tip) {name}[n].z`")),
                );
                return Typed::error();
            }
            let dim = if name == "v" {
                Dim::LENGTH.per(Dim::TIME)
            } else {
                Dim::LENGTH
            };
            let var = if name == "x0" { Var::Const } else { Var::State };
            return Typed::of(Ty::vec3(dim), var.max(idx[0].var.min(Var::Param)));
        }
        let Ty::Num { dim, shape, int } = &b.ty else {
            let msg = format!("cannot index {}", b.ty);
            self.err(Diagnostic::error("E0203", e.span, msg));
            return Typed::error();
        };
        if indices.len() > shape.len() {
            let msg = format!(
                "{} has {} index{}, but {} were given",
                b.ty,
                shape.len(),
                if shape.len() == 1 { "" } else { "es" },
                indices.len()
            );
            self.err(Diagnostic::error("E0204", e.span, msg));
            return Typed::error();
        }
        let mut value = b.value.clone();
        for (k, (t, ie)) in idx.iter().zip(indices).enumerate() {
            let per_element = matches!(&shape[k], Len::PerElement(_));
            let ok = if per_element {
                t.ty == Ty::Obj(Obj::Element)
            } else {
                t.ty.is_int_scalar()
            };
            if !ok {
                let d = if per_element {
                    let msg = format!(
                        "a per-element field is indexed by an element bound in `sum(e in {})`, found {}",
                        shape[k], t.ty
                    );
                    Diagnostic::error("E0322", ie.span, msg)
                } else {
                    self.integer_error(ie, t, "an index")
                };
                self.err(d);
                return Typed::error();
            }
            if let (Len::Fixed(n), Some(i)) = (&shape[k], t.num())
                && (i < 0.0 || i >= *n as f64)
            {
                let msg = format!("index {i} is out of range for length {n}");
                self.err(
                    Diagnostic::error("E0206", ie.span, msg)
                        .with_hint(format!("indices start at 0; the last is {}", n - 1)),
                );
                return Typed::error();
            }
            value = match (value, t.num()) {
                (Some(Value::Array(items)), Some(i)) => items.get(i as usize).cloned(),
                _ => None,
            };
        }
        Typed {
            ty: Ty::Num {
                dim: *dim,
                shape: shape[indices.len()..].to_vec(),
                int: *int,
            },
            var,
            value,
        }
    }

    fn check_reduce(
        &mut self,
        op: ReduceOp,
        var: &Ident,
        domain: &Expr,
        body: &Expr,
        whole: Span,
    ) -> Typed {
        let d = self.check_expr(domain);
        let binder = match &d.ty {
            Ty::Error => Typed::error(),
            other if op == ReduceOp::AreaMean && *other != Ty::Obj(Obj::NodeSet) => {
                let msg = format!(
                    "`area_mean` runs over a node set (the boundary surface it covers), found \
                     {other}"
                );
                self.err(Diagnostic::error("E0203", domain.span, msg));
                Typed::error()
            }
            Ty::Obj(Obj::NodeSet) => Typed::of(Ty::Obj(Obj::Node), Var::Const),
            Ty::Obj(Obj::ElementSet) => Typed::of(Ty::Obj(Obj::Element), Var::Const),
            Ty::Obj(Obj::Range) => Typed::of(Ty::int(), d.var),
            other => {
                let msg = format!(
                    "`{}` runs over a node set, an element set or a range `a..b`, found {other}",
                    op.name()
                );
                self.err(Diagnostic::error("E0203", domain.span, msg));
                Typed::error()
            }
        };
        self.push_scope();
        let def = self.define(var, super::DefKind::ReduceVar, whole, None);
        self.declare_local(&var.name, var.span, binder, false, def);
        let b = self.check_expr(body);
        self.pop_scope();
        match &b.ty {
            Ty::Error => b,
            Ty::Num { dim, shape, int } => Typed::of(
                Ty::Num {
                    dim: *dim,
                    shape: shape.clone(),
                    int: *int && !matches!(op, ReduceOp::Mean | ReduceOp::AreaMean),
                },
                b.var.max(d.var),
            ),
            other => {
                let msg = format!("`{}` needs a numeric body, found {other}", op.name());
                self.err(Diagnostic::error("E0203", body.span, msg));
                Typed::error()
            }
        }
    }

    fn check_call(&mut self, e: &Expr, callee: &Expr, args: &[Arg]) -> Typed {
        let ExprKind::Name(id) = &callee.kind else {
            // Report the callee's own mistake first (`3 kPa*ramp(…)` reads `kPa*ramp` as a unit).
            let t = self.check_expr(callee);
            if !t.ty.is_error() {
                self.err(Diagnostic::error(
                    "E0110",
                    callee.span,
                    "only named functions can be called",
                ));
            }
            return Typed::error();
        };
        let name = id.name.as_str();
        if let Some((_, def, _)) = self.lookup_local_def(name) {
            self.record_use(id, def);
            self.resolve_name(id, super::hir::Name::Local(name.to_string()));
            let msg = format!("`{name}` is a value, not a function");
            self.err(Diagnostic::error("E0110", id.span, msg));
            return Typed::error();
        }
        if let Some(&gid) = self.globals.get(name) {
            self.record_global_use(id, gid);
            self.resolve_name(id, super::hir::Name::Global(gid));
            self.syms[gid].used = true;
            let kind = self.syms[gid].kind;
            return match kind {
                SymKind::Fn | SymKind::Controller | SymKind::MaterialTemplate => {
                    self.check_user_call(e, gid, args)
                }
                k => {
                    let msg = format!("`{name}` is {}, not a function", k.with_article());
                    self.err(Diagnostic::error("E0110", id.span, msg));
                    Typed::error()
                }
            };
        }
        self.record_use(id, None);
        self.resolve_name(id, super::hir::Name::Implicit(name.to_string()));
        if super::builtins::FUNCTIONS.contains(&name) {
            return self.check_builtin(e, id, args);
        }
        let d = self.unknown_function(name, id.span);
        self.err(d);
        // Check the arguments anyway so their own mistakes are reported.
        for a in args {
            self.check_expr(&a.value);
        }
        Typed::error()
    }

    fn unknown_function(&self, name: &str, span: Span) -> Diagnostic {
        let mut candidates: Vec<&str> = super::builtins::FUNCTIONS.to_vec();
        let user: Vec<&str> = self
            .globals
            .iter()
            .filter(|(_, g)| {
                matches!(
                    self.syms[**g].kind,
                    SymKind::Fn | SymKind::Controller | SymKind::MaterialTemplate
                )
            })
            .map(|(n, _)| n.as_str())
            .collect();
        candidates.extend(user);
        let mut d = Diagnostic::error("E0104", span, format!("unknown function `{name}`"));
        if let Some(s) = did_you_mean(name, candidates) {
            d = d.with_hint(format!("did you mean `{s}`?"));
        }
        d
    }

    /// Bind call arguments to parameter slots by position and name.
    pub(super) fn bind<'e>(
        &mut self,
        fname: &str,
        call_span: Span,
        params: &[(&str, bool)],
        args: &'e [Arg],
    ) -> Option<Vec<Option<&'e Expr>>> {
        let mut slots: Vec<Option<&Expr>> = vec![None; params.len()];
        let mut ok = true;
        let mut seen_named = false;
        let mut next_pos = 0;
        for a in args {
            match &a.name {
                None => {
                    if seen_named {
                        self.err(Diagnostic::error(
                            "E0107",
                            a.value.span,
                            "positional arguments must come before named ones",
                        ));
                        ok = false;
                        continue;
                    }
                    if next_pos >= params.len() {
                        let msg = format!(
                            "`{fname}` takes {} argument{}, but more were given",
                            params.len(),
                            if params.len() == 1 { "" } else { "s" }
                        );
                        self.err(Diagnostic::error("E0107", a.value.span, msg));
                        ok = false;
                        continue;
                    }
                    slots[next_pos] = Some(&a.value);
                    next_pos += 1;
                }
                Some(n) => {
                    seen_named = true;
                    match params.iter().position(|(p, _)| *p == n.name) {
                        None => {
                            let mut d = Diagnostic::error(
                                "E0105",
                                n.span,
                                format!("`{fname}` has no argument named `{}`", n.name),
                            );
                            let names: Vec<&str> = params.iter().map(|(p, _)| *p).collect();
                            d = match did_you_mean(&n.name, names.iter().copied()) {
                                Some(s) => d.with_hint(format!("did you mean `{s}`?")),
                                None => d.with_hint(format!(
                                    "the arguments of `{fname}` are: {}",
                                    names.join(", ")
                                )),
                            };
                            self.err(d);
                            ok = false;
                        }
                        Some(i) if slots[i].is_some() => {
                            let msg = format!("argument `{}` is given twice", n.name);
                            self.err(Diagnostic::error("E0107", n.span, msg));
                            ok = false;
                        }
                        Some(i) => slots[i] = Some(&a.value),
                    }
                }
            }
        }
        let missing: Vec<&str> = params
            .iter()
            .zip(&slots)
            .filter(|((_, required), s)| *required && s.is_none())
            .map(|((p, _), _)| *p)
            .collect();
        if !missing.is_empty() && ok {
            let list = missing
                .iter()
                .map(|m| format!("`{m}`"))
                .collect::<Vec<_>>()
                .join(", ");
            let msg = format!(
                "`{fname}` is missing the argument{} {list}",
                if missing.len() == 1 { "" } else { "s" }
            );
            self.err(Diagnostic::error("E0106", call_span, msg));
            ok = false;
        }
        if !ok {
            for a in args {
                self.check_expr(&a.value);
            }
            return None;
        }
        Some(slots)
    }

    fn check_user_call(&mut self, e: &Expr, gid: usize, args: &[Arg]) -> Typed {
        // Make sure the signature exists (checks the declaration on first use).
        self.global_typed(gid);
        let Some(sig) = self.sigs.get(&gid).cloned() else {
            for a in args {
                self.check_expr(&a.value);
            }
            return Typed::error();
        };
        let name = self.syms[gid].name.clone();
        let kind = self.syms[gid].kind;
        if kind == SymKind::Controller && !self.ctx.time {
            let msg = format!(
                "the controller `{name}` runs with the simulation: call it in the sim block, the loss, a `let` or another controller"
            );
            self.err(Diagnostic::error("E0320", e.span, msg));
            return Typed::error();
        }
        let params: Vec<(&str, bool)> = sig
            .params
            .iter()
            .map(|p| (p.name.as_str(), !p.has_default))
            .collect();
        let Some(slots) = self.bind(&name, e.span, &params, args) else {
            return Typed::error();
        };
        let mut var = sig.body_var;
        let mut failed = false;
        // Each argument's constant value (`None` when not given: its default).
        let mut given: Vec<Option<Option<Value>>> = Vec::new();
        for (p, slot) in sig.params.iter().zip(slots) {
            let Some(arg) = slot else {
                given.push(None);
                continue;
            };
            let t = self.check_expr(arg);
            given.push(Some(t.value.clone()));
            var = var.max(t.var);
            // A material constant may vary per element: a per-element field (`param mu:
            // pressure[core]`) fits a scalar material parameter.
            let per_element = kind == SymKind::MaterialTemplate
                && p.ty.is_scalar_num()
                && matches!(t.ty.shape(), [Len::PerElement(_)])
                && t.ty.dim() == p.ty.dim();
            if !per_element
                && !self.expect_type(
                    &t,
                    &p.ty,
                    arg,
                    &format!("argument `{}` of `{name}`", p.name),
                )
            {
                failed = true;
            }
        }
        if failed {
            return Typed::error();
        }
        if kind == SymKind::Fn && var == Var::Const {
            return self.fold_call(e, gid, &sig, given);
        }
        Typed::of(sig.ret.clone(), var)
    }

    /// A call of a `fn` (the prelude's `lame_lambda` included) whose arguments are constants:
    /// evaluated once per function and argument values ([`Checker::folded`]); at most
    /// [`MAX_FOLDS`] evaluations with distinct arguments, beyond which the outermost call is
    /// E0002 (SPEC §13).
    ///
    /// its body evaluated with their values, so the call has a value like the same expression
    /// written inline, and a division by zero inside it is E0208 at the call (issue 20 item
    /// 16: `lame_lambda(E, 0.5)` passed the check and failed at run time with no location).
    fn fold_call(
        &mut self,
        e: &Expr,
        gid: usize,
        sig: &super::Signature,
        given: Vec<Option<Option<Value>>>,
    ) -> Typed {
        let plain = Typed::of(sig.ret.clone(), Var::Const);
        const MAX_DEPTH: u32 = 32;
        if sig.ret.is_error() || self.fold_depth >= MAX_DEPTH {
            return plain;
        }
        let (prelude, index) = (self.syms[gid].prelude, self.syms[gid].item);
        let ItemKind::Fn(f) = self.item(prelude, index).kind else {
            return plain;
        };
        let name = self.syms[gid].name.clone();
        // The arguments' values, and the defaults of those not given.
        let mark = self.diags.len();
        let mut values = Vec::new();
        // The defaults are the function's code (perhaps the prelude's).
        let saved_prelude = std::mem::replace(&mut self.in_prelude, prelude);
        for (p, v) in f.params.iter().zip(given) {
            let v = match (v, &p.default) {
                (Some(v), _) => v,
                (None, Some(d)) => self.check_expr(d).value,
                (None, None) => None,
            };
            values.push(v);
        }
        self.in_prelude = saved_prelude;
        self.diags.truncate(mark);
        if values.iter().any(Option::is_none) || values.len() != f.params.len() {
            return plain;
        }
        let mut bits = Vec::new();
        for v in values.iter().flatten() {
            value_bits(v, &mut bits);
        }
        let key = (gid, bits);
        let folded = match self.folded.get(&key) {
            Some(done) => done.clone(),
            None => {
                if self.folds >= MAX_FOLDS {
                    self.folds_exhausted = true;
                    return plain;
                }
                self.folds += 1;
                let saved_prelude = std::mem::replace(&mut self.in_prelude, prelude);
                let done = self.evaluate_call(&f, sig, values);
                self.in_prelude = saved_prelude;
                self.folded.insert(key, done.clone());
                done
            }
        };
        if self.fold_depth == 0 && std::mem::take(&mut self.folds_exhausted) {
            self.err(
                Diagnostic::error(
                    "E0002",
                    e.span,
                    format!(
                        "`{name}` is too complex to evaluate: its calls expand to more than \
                         {MAX_FOLDS} calls of functions with distinct arguments"
                    ),
                )
                .with_hint(
                    "a function that calls another several times with different arguments \
                     doubles the work at each level; compute the shared part once, in a `let`",
                ),
            );
            return Typed::error();
        }
        if folded.divided_by_zero {
            let shown: Vec<String> = f.params.iter().map(|p| p.name.name.clone()).collect();
            self.err(
                Diagnostic::error(
                    "E0208",
                    e.span,
                    format!(
                        "division by zero in `{name}({})` with these arguments",
                        shown.join(", ")
                    ),
                )
                .with_hint(format!(
                    "`{name}` divides by an expression of its parameters that is 0 for these \
                     values; change the arguments (e.g. Poisson's ratio ν < 0.5)"
                )),
            );
            return Typed::error();
        }
        Typed {
            value: folded.value,
            ..plain
        }
    }

    /// The body of `f` checked with its parameters bound to constant `values`.
    fn evaluate_call(
        &mut self,
        f: &FnDecl,
        sig: &super::Signature,
        values: Vec<Option<Value>>,
    ) -> Folded {
        let mark = self.diags.len();
        // The body sees its parameters and the globals only, in a function's context.
        let scopes = std::mem::take(&mut self.scopes);
        let ctx = std::mem::take(&mut self.ctx);
        self.fold_depth += 1;
        self.push_scope();
        for ((p, value), sp) in f.params.iter().zip(values).zip(&sig.params) {
            let typed = Typed {
                ty: sp.ty.clone(),
                var: Var::Const,
                value,
            };
            let def = self.param_def(&f.name, p);
            self.declare_local(&p.name.name, p.name.span, typed, false, def);
        }
        let body = self.check_expr(&f.body);
        self.pop_scope();
        self.fold_depth -= 1;
        self.ctx = ctx;
        self.scopes = scopes;
        let divided_by_zero = self.diags[mark..].iter().any(|d| d.code == "E0208");
        self.diags.truncate(mark);
        Folded {
            value: body.value,
            divided_by_zero,
        }
    }

    /// Check that `t` fits the declared type `want` (dimension, shape); report otherwise.
    pub(super) fn expect_type(&mut self, t: &Typed, want: &Ty, e: &Expr, what: &str) -> bool {
        if t.ty.is_error() || want.is_error() {
            return true;
        }
        let fits = match (&t.ty, want) {
            (
                Ty::Num {
                    dim: d1, shape: s1, ..
                },
                Ty::Num {
                    dim: d2,
                    shape: s2,
                    int: i2,
                },
            ) => {
                if d1 != d2 {
                    let msg = format!("{what} must be {}, found {}", want, self.describe(e, &t.ty));
                    let mut d = Diagnostic::error("E0202", e.span, msg);
                    if let Some(h) = unit_suggestion(*d2) {
                        d = d.with_hint(h);
                    }
                    self.err(d);
                    return false;
                }
                if *i2 && !t.ty.is_int_scalar() {
                    let d = self.integer_error(e, t, what);
                    self.err(d);
                    return false;
                }
                shapes_fit(s1, s2)
            }
            (a, b) => a == b,
        };
        if !fits {
            let msg = format!("{what} must be {want}, found {}", self.describe(e, &t.ty));
            self.err(Diagnostic::error("E0203", e.span, msg));
        }
        fits
    }

    /// Require a compile-time constant (geometry, settings, bounds).
    pub(super) fn expect_const(&mut self, t: &Typed, e: &Expr, what: &str) -> bool {
        if t.ty.is_error() || t.var == Var::Const {
            return true;
        }
        // Point at the name that makes it vary, when there is one.
        if let Some((span, why)) = self.varying_name(e) {
            let msg = format!("{what} must be a constant, but {why}");
            self.err(
                Diagnostic::error("E0321", span, msg)
                    .with_hint("it is fixed before the simulation starts"),
            );
            return false;
        }
        let why = match t.var {
            Var::Param => "depends on a param or input",
            Var::Time => "depends on the time `t`",
            _ => "depends on the simulation state",
        };
        let msg = format!("{what} must be a constant, but this {why}");
        self.err(
            Diagnostic::error("E0321", e.span, msg)
                .with_hint("it is fixed before the simulation starts"),
        );
        false
    }

    /// The first name in `e` that is not constant: a param, an input, `t` or the node state.
    fn varying_name(&self, e: &Expr) -> Option<(Span, String)> {
        let mut stack = vec![e];
        while let Some(x) = stack.pop() {
            if let ExprKind::Name(id) = &x.kind {
                let local = self.scopes.iter().any(|s| s.contains_key(&id.name));
                if !local {
                    match id.name.as_str() {
                        "t" => return Some((id.span, "`t` is the simulation time".into())),
                        "x" | "v" => {
                            return Some((id.span, format!("`{}` is the node state", id.name)));
                        }
                        _ => {}
                    }
                    if let Some(&g) = self.globals.get(&id.name) {
                        let k = self.syms[g].kind;
                        if matches!(k, SymKind::Param | SymKind::Input) {
                            let msg = format!("`{}` is {}", id.name, k.with_article());
                            return Some((id.span, msg));
                        }
                    }
                }
            }
            let mut children = Vec::new();
            x.for_each_child(|c| children.push(c));
            stack.extend(children.into_iter().rev());
        }
        None
    }

    /// "must be an integer" with what was written instead.
    pub(super) fn integer_error(&self, e: &Expr, t: &Typed, what: &str) -> Diagnostic {
        match (t.num(), t.ty.dim()) {
            (Some(v), Some(d)) if d.is_none() && t.ty.is_scalar_num() => {
                let d = Diagnostic::error(
                    "E0322",
                    e.span,
                    format!("{what} must be an integer, found the decimal number {v}"),
                );
                if v.fract() == 0.0 && v.abs() < 1e15 {
                    d.with_hint(format!(
                        "write it without a decimal point or exponent: `{}`",
                        v as i64
                    ))
                } else {
                    d.with_hint("use a whole number")
                }
            }
            _ => Diagnostic::error(
                "E0322",
                e.span,
                format!(
                    "{what} must be an integer, found {}",
                    self.describe(e, &t.ty)
                ),
            ),
        }
    }
}

fn fold2(l: &Typed, r: &Typed, f: impl Fn(f64, f64) -> f64) -> Option<Value> {
    match (&l.value, &r.value) {
        (Some(a), Some(b)) => a.map2(b, &f),
        _ => None,
    }
}

fn same_type(a: &Ty, b: &Ty) -> bool {
    match (a, b) {
        (
            Ty::Num {
                dim: d1, shape: s1, ..
            },
            Ty::Num {
                dim: d2, shape: s2, ..
            },
        ) => d1 == d2 && s1 == s2,
        _ => a == b,
    }
}

/// Whether a value of shape `have` fits a declared shape `want` (`*` matches any length).
pub(super) fn shapes_fit(have: &[Len], want: &[Len]) -> bool {
    have.len() == want.len()
        && have
            .iter()
            .zip(want)
            .all(|(h, w)| w == &Len::Any || h == &Len::Any || h == w)
}

pub(super) fn unit_suggestion(d: Dim) -> Option<String> {
    let examples: &[(&str, &str)] = &[
        ("pressure", "3 kPa"),
        ("length", "10 mm"),
        ("time", "0.5 s"),
        ("rate", "20 /s"),
        ("density", "1070 kg/m^3"),
        ("acceleration", "9.81 m/s^2"),
        ("memory", "512 MB"),
        ("1/pressure", "1.0 /MPa"),
    ];
    let name = d.name();
    examples
        .iter()
        .find(|(n, _)| *n == name)
        .map(|(_, ex)| format!("write {} with its unit, e.g. `{ex}`", with_article(&name)))
}

/// "a length", "an acceleration".
pub(super) fn with_article(noun: &str) -> String {
    let vowel = noun.starts_with(['a', 'e', 'i', 'o', 'u']);
    format!("{} {noun}", if vowel { "an" } else { "a" })
}

/// The most calls of functions with distinct constant arguments one check evaluates (SPEC
/// §13): each costs a check of the function's body.
pub(super) const MAX_FOLDS: usize = 200_000;

/// What a constant call evaluated to.
#[derive(Clone, Debug)]
pub(super) struct Folded {
    value: Option<Value>,
    divided_by_zero: bool,
}

/// A value's exact bits, tagged by kind: a key for calls with equal arguments.
fn value_bits(v: &Value, out: &mut Vec<u64>) {
    match v {
        Value::Num(x) => out.extend([0, x.to_bits()]),
        Value::Bool(b) => out.extend([1, *b as u64]),
        Value::Str(s) => {
            out.extend([2, s.len() as u64]);
            out.extend(s.bytes().map(u64::from));
        }
        Value::Array(items) => {
            out.extend([3, items.len() as u64]);
            for item in items {
                value_bits(item, out);
            }
        }
    }
}
