//! Declarations: registering and checking the global items, and the whole-script checks.

use super::expr::{shapes_fit, unit_suggestion};
use super::types::{Len, Obj, Ty, Typed, Var};
use super::units::{self, Dim};
use super::{Checker, GState, Global, ParamInfo, SigParam, Signature, SymKind, reserved_name};
use crate::diag::{Diagnostic, did_you_mean};
use crate::front::ast::*;

/// What the sim block fixed, for later checks (windows, `t_end`, chambers with pressure).
#[derive(Debug, Default)]
pub(super) struct SimInfo {
    pub duration: Option<f64>,
    pub dt: Option<f64>,
    /// Set while `dt`, `steps` and `duration` are checked: they may not refer to `t_end`/`dt`.
    pub defining_duration: bool,
    /// `window(t, width)` uses: width and span.
    pub windows: Vec<(f64, Span)>,
    pub pressured: Vec<String>,
    /// The (body, obstacle) pairs of the `contact` statements so far.
    pub contacts: Vec<(String, String)>,
    pub seen: bool,
    /// The integrator solves for the state (`implicit_euler`, `quasi_static`): closed-loop
    /// sensors are evaluated at its iterates, which have positions only.
    pub solves_state: Option<&'static str>,
    /// The mesh is loaded with `order: 2` (quadratic elements).
    pub quadratic: bool,
}

/// Largest number of entries of a fixed-shape value (params, inputs, lets).
const MAX_ENTRIES: usize = 10_000_000;

/// The settings of the `sim` block.
pub const SIM_SETTINGS: &[&str] = &[
    "dt",
    "steps",
    "duration",
    "integrator",
    "damping",
    "model",
    "gravity",
    "mass_scaling",
    "precision",
];

/// The settings of an `optimize` body.
pub const OPTIMIZE_SETTINGS: &[&str] = &[
    "batch",
    "seed",
    "gradient_scale",
    "normalize",
    "clip",
    "lr_schedule",
    "memory_budget",
    "checkpoint",
    "truncate",
];

impl Checker {
    /// Collect the global declarations of a script (pass 1).
    pub(super) fn register(&mut self, items: &[Item], prelude: bool) {
        if prelude {
            self.prelude_items = items.to_vec();
        } else {
            self.user_items = items.to_vec();
        }
        self.in_prelude = prelude;
        for (index, item) in items.iter().enumerate() {
            let Some((name, kind)) = SymKind::of_item(item) else {
                continue;
            };
            // The declaration as written, for editors (every one, clashes included).
            let written = match &item.kind {
                ItemKind::Param(p) => Some(p.ty.clone()),
                ItemKind::Input(i) => Some(i.ty.clone()),
                ItemKind::Let(l) => l.ty.clone(),
                ItemKind::Fn(f) => f.ret.clone(),
                _ => None,
            };
            let def = self.define(name, super::DefKind::Global(kind), item.span, written);
            if super::RESERVED_NAMES.contains(&name.name.as_str()) {
                self.err(reserved_name(&name.name, name.span));
                continue;
            }
            // Declarations may shadow built-in functions (`region clamp`), not constants.
            if super::builtins::CONSTANTS
                .iter()
                .any(|(n, _)| *n == name.name)
            {
                let msg = format!("`{}` is a built-in name and cannot be declared", name.name);
                self.err(
                    Diagnostic::error("E0111", name.span, msg).with_hint("choose another name"),
                );
                continue;
            }
            if let Some(&prev) = self.globals.get(&name.name) {
                let p = &self.syms[prev];
                let d = if p.prelude {
                    Diagnostic::error(
                        "E0111",
                        name.span,
                        format!(
                            "`{}` is a built-in {} from the prelude",
                            name.name,
                            p.kind.describe()
                        ),
                    )
                    .with_hint("choose another name")
                } else {
                    Diagnostic::error(
                        "E0102",
                        name.span,
                        format!("`{}` is declared twice", name.name),
                    )
                    .with_note(p.span, "first declared here")
                };
                // One report for the clash; no "unused" warning for the first declaration.
                self.syms[prev].used = true;
                self.err(d);
                continue;
            }
            self.globals.insert(name.name.clone(), self.syms.len());
            if let Some(d) = def {
                self.global_defs.insert(self.syms.len(), d);
            }
            self.syms.push(Global {
                name: name.name.clone(),
                kind,
                span: name.span,
                prelude,
                used: false,
                item: index,
                state: GState::Unchecked,
            });
        }
    }

    /// Check every item (pass 2). The sim block goes first: the loss needs its duration.
    pub(super) fn check_items(&mut self, items: &[Item], prelude: bool) {
        self.in_prelude = prelude;
        let ids: Vec<usize> = (0..self.syms.len())
            .filter(|&i| self.syms[i].prelude == prelude)
            .collect();
        let mut sims = Vec::new();
        let mut losses = Vec::new();
        let mut optimizes = Vec::new();
        for item in items {
            match &item.kind {
                ItemKind::Sim(s) => sims.push((item.span, s)),
                ItemKind::Loss(l) => losses.push((item.span, l)),
                ItemKind::Optimize(o) => optimizes.push((item.span, o)),
                _ => {}
            }
        }
        // The mesh first: checks of surfaces, selections and fixed regions need it.
        for &id in &ids {
            if self.syms[id].kind == SymKind::Mesh {
                self.global_typed(id);
            }
        }
        for (i, (span, stmts)) in sims.iter().enumerate() {
            if i > 0 {
                self.err(duplicate_block("sim", *span, sims[0].0));
                continue;
            }
            self.check_sim(stmts, *span);
        }
        for id in ids {
            self.global_typed(id);
        }
        for (i, (span, loss)) in losses.iter().enumerate() {
            if i > 0 {
                self.err(duplicate_block("loss", *span, losses[0].0));
                continue;
            }
            self.check_loss(loss);
        }
        for (i, (span, opt)) in optimizes.iter().enumerate() {
            if i > 0 {
                self.err(duplicate_block("optimize", *span, optimizes[0].0));
                continue;
            }
            self.check_optimize(opt, *span, !losses.is_empty());
        }
    }

    /// Check one global declaration; records signatures of functions and templates.
    pub(super) fn check_decl(&mut self, id: usize, item: &Item) -> Typed {
        match &item.kind {
            ItemKind::Decl {
                kind: DeclKind::Obstacle,
                value,
                ..
            } => self.check_obstacle(value),
            ItemKind::Decl { kind, name, value } => {
                let errors_before = self.diags.len();
                // What the value's region or surface call records is this declaration's.
                self.last_shape = None;
                self.last_surface = None;
                self.last_selector = None;
                let t = self.check_expr(value);
                let clean = self.diags.len() == errors_before;
                let (want, what) = match kind {
                    DeclKind::Mesh => (Obj::Mesh, "`load(\"file.msh\")`"),
                    DeclKind::Region => (Obj::Region, "`box(min: …, max: …)` or `sphere(…)`"),
                    DeclKind::Chamber => (Obj::Surface, "`surface(mesh, \"name\")`"),
                    DeclKind::Obstacle => (Obj::Obstacle, "`plane(…)` or `sphere(…)`"),
                    DeclKind::Nodes | DeclKind::Elements => (
                        Obj::Selection,
                        "`select(mesh, condition)`, `named(mesh, \"name\")`, `tagged(mesh, tag)` or `inside(mesh, region)`",
                    ),
                };
                let ok = t.ty.is_error() || t.ty == Ty::Obj(want);
                if !ok {
                    let msg = format!(
                        "{} is declared with {what}, found {}",
                        super::expr::with_article(kind.noun()),
                        t.ty
                    );
                    self.err(Diagnostic::error("E0203", value.span, msg));
                    return Typed::error();
                }
                match kind {
                    DeclKind::Region => {
                        if let Some(shape) = self.last_shape.take() {
                            self.out.mesh_refs.regions.insert(name.name.clone(), shape);
                        }
                    }
                    DeclKind::Chamber => {
                        if let Some(surface) = self.last_surface.take() {
                            self.out
                                .mesh_refs
                                .surfaces
                                .insert(name.name.clone(), surface);
                        }
                    }
                    _ => {}
                }
                if matches!(kind, DeclKind::Nodes | DeclKind::Elements) {
                    if let Some(selector) = self.last_selector.take()
                        && !self.out.mesh_refs.sets.iter().any(|s| s.name == name.name)
                    {
                        self.out
                            .mesh_refs
                            .sets
                            .push(super::mesh_probe::DeclaredSet {
                                name: name.name.clone(),
                                elements: *kind == DeclKind::Elements,
                                selector,
                            });
                    }
                    if clean {
                        self.check_selection_nonempty(name, *kind, value);
                    }
                }
                let obj = match kind {
                    DeclKind::Mesh => Obj::Mesh,
                    DeclKind::Region => Obj::Region,
                    DeclKind::Chamber => Obj::Surface,
                    DeclKind::Obstacle => Obj::Obstacle,
                    DeclKind::Nodes => Obj::NodeSet,
                    DeclKind::Elements => Obj::ElementSet,
                };
                Typed::of(Ty::Obj(obj), Var::Const)
            }
            ItemKind::Material(m) => self.check_material(id, m),
            ItemKind::Param(p) => self.check_param(p),
            ItemKind::Input(i) => self.check_input(i),
            ItemKind::Let(l) => {
                // A top-level let may name a derived quantity of the run (`t`, node state); its
                // variability says where it may be used.
                self.ctx.time = true;
                self.ctx.state = true;
                self.ctx.loss_state = true;
                let t = self.check_expr(&l.value);
                self.ctx = Default::default();
                if matches!(t.ty, Ty::Obj(Obj::StateField | Obj::Node | Obj::Element)) {
                    let msg = format!(
                        "`{}` would name {}, which only exists inside an expression",
                        l.name.name, t.ty
                    );
                    self.err(Diagnostic::error("E0314", l.value.span, msg).with_hint(
                        "index the node state with a node bound by a reduction, e.g. `let dz = mean(n in tip) (x[n].z - x0[n].z)`",
                    ));
                    return Typed::error();
                }
                self.check_let_type(l, t)
            }
            ItemKind::Fn(f) => self.check_fn(id, f),
            _ => Typed::error(),
        }
    }

    /// Check a let's value against its declared type; the let takes the declared type either
    /// way, so a mismatch is reported once, here, and not again at every use.
    pub(super) fn check_let_type(&mut self, l: &LetDecl, t: Typed) -> Typed {
        let Some(te) = &l.ty else { return t };
        let Some(want) = self.resolve_type(te, false) else {
            return Typed::error();
        };
        if self.expect_type(&t, &want, &l.value, &format!("`{}`", l.name.name)) {
            Typed { ty: want, ..t }
        } else {
            Typed::of(want, t.var)
        }
    }

    /// Turn a written type into a [`Ty`]; `template` allows `*` lengths.
    pub(super) fn resolve_type(&mut self, te: &TypeExpr, template: bool) -> Option<Ty> {
        self.record_type_names(te);
        let dim = self.resolve_dim(&te.dim)?;
        let mut shape = Vec::new();
        for s in &te.shape {
            shape.push(match s {
                ShapeItem::Any(sp) => {
                    if !template {
                        self.err(
                            Diagnostic::error(
                                "E0204",
                                *sp,
                                "`*` lengths are only allowed in material template parameters",
                            )
                            .with_hint("give the length, e.g. `pressure[3]`"),
                        );
                        return None;
                    }
                    Len::Any
                }
                ShapeItem::Len(text, sp) => match text.parse::<usize>() {
                    Ok(n) if (1..=1_000_000).contains(&n) => Len::Fixed(n),
                    _ => {
                        let msg = format!("a length must lie between 1 and 1000000, found {text}");
                        self.err(Diagnostic::error("E0204", *sp, msg));
                        return None;
                    }
                },
                ShapeItem::Set(id) => {
                    match self.globals.get(&id.name).map(|&g| (g, self.syms[g].kind)) {
                        Some((g, SymKind::Elements)) => {
                            self.syms[g].used = true;
                            Len::PerElement(id.name.clone())
                        }
                        Some((g, k)) => {
                            self.syms[g].used = true;
                            self.wrong_kind(
                                id,
                                k,
                                "a per-element shape names an element set",
                                None,
                            );
                            return None;
                        }
                        None => {
                            let d = self.unknown_name(&id.name, id.span);
                            self.err(d);
                            return None;
                        }
                    }
                }
            });
        }
        let total = shape.iter().try_fold(1usize, |acc, l| match l {
            Len::Fixed(n) => acc.checked_mul(*n),
            _ => Some(acc),
        });
        if total.is_none_or(|n| n > MAX_ENTRIES) {
            let msg = format!("this type has more than {MAX_ENTRIES} entries");
            self.err(Diagnostic::error("E0204", te.span, msg).with_hint(
                "for one value per element use a per-element shape, e.g. `pressure[core]`",
            ));
            return None;
        }
        Some(Ty::Num {
            dim,
            shape,
            int: false,
        })
    }

    /// Enter a type's dimension names and element-set names in the resolution table, all of
    /// them, whether or not the type checks.
    fn record_type_names(&mut self, te: &TypeExpr) {
        if self.in_prelude {
            return;
        }
        let mut stack = vec![&te.dim];
        while let Some(d) = stack.pop() {
            for f in std::iter::once(&d.first).chain(d.rest.iter().map(|(_, f)| f)) {
                match &f.base {
                    DimBase::One => {}
                    DimBase::Named(id) => {
                        if self.seen_uses.insert((id.span.start, id.span.end)) {
                            self.out.resolution.dims.push(id.clone());
                        }
                    }
                    DimBase::Group(g) => stack.push(g),
                }
            }
        }
        for s in &te.shape {
            if let ShapeItem::Set(id) = s {
                match self.globals.get(&id.name).copied() {
                    Some(g) => self.record_global_use(id, g),
                    None => self.record_use(id, None),
                }
            }
        }
    }

    fn resolve_dim(&mut self, d: &DimExpr) -> Option<Dim> {
        let mut acc = self.resolve_dim_factor(&d.first)?;
        for (op, f) in &d.rest {
            let x = self.resolve_dim_factor(f)?;
            acc = match op {
                DimOp::Mul => acc.times(x),
                DimOp::Div => acc.per(x),
            };
        }
        Some(acc)
    }

    fn resolve_dim_factor(&mut self, f: &DimFactor) -> Option<Dim> {
        let base = match &f.base {
            DimBase::One => Dim::NONE,
            DimBase::Group(g) => self.resolve_dim(g)?,
            DimBase::Named(id) => match units::named_dim(&id.name) {
                Some(d) => d,
                None => {
                    let mut d = Diagnostic::error(
                        "E0101",
                        id.span,
                        format!("unknown dimension `{}`", id.name),
                    );
                    let names: Vec<&str> = units::NAMED_DIMS.iter().map(|(n, _)| *n).collect();
                    if let Some((_, dim)) = units::unit(&id.name) {
                        d = d.with_hint(format!(
                            "types name dimensions, not units: write `{}`",
                            dim.name()
                        ));
                    } else if let Some(s) = did_you_mean(&id.name, names.iter().copied()) {
                        d = d.with_hint(format!("did you mean `{s}`?"));
                    } else {
                        d = d.with_hint(format!("the dimensions are: {}", names.join(", ")));
                    }
                    self.err(d);
                    return None;
                }
            },
        };
        match &f.power {
            None => Some(base),
            Some((text, sp)) => match text.parse::<i32>().ok().and_then(|p| base.powi(p)) {
                Some(d) if !d.is_extreme() => Some(d),
                _ => {
                    self.err(Diagnostic::error(
                        "E0004",
                        *sp,
                        "dimension power out of range",
                    ));
                    None
                }
            },
        }
    }

    fn check_param(&mut self, p: &ParamDecl) -> Typed {
        let Some(ty) = self.resolve_type(&p.ty, false) else {
            self.check_expr(&p.init);
            return Typed::error();
        };
        let what = format!("the initial value of `{}`", p.name.name);
        let init = self.check_expr(&p.init);
        let mut ok = self.expect_init(&init, &ty, &p.init, &what);
        ok &= self.expect_const(&init, &p.init, &what);
        let dim = ty.dim().unwrap();
        let scalar = Ty::scalar(dim);
        let mut lower = None;
        let mut upper = None;
        if let Some(b) = &p.bounds {
            for (end, slot, name) in [
                (&b.lower, &mut lower, "lower"),
                (&b.upper, &mut upper, "upper"),
            ] {
                if let Some(e) = end {
                    let t = self.check_expr(e);
                    let what = format!("the {name} bound of `{}`", p.name.name);
                    if self.expect_type(&t, &scalar, e, &what) && self.expect_const(&t, e, &what) {
                        *slot = t.num();
                    } else {
                        ok = false;
                    }
                }
            }
            if b.lower.is_none() && b.upper.is_none() {
                self.err(
                    Diagnostic::error("E0302", b.span, "bounds `[.., ..]` bound nothing")
                        .with_hint("remove them, or give at least one end"),
                );
            }
            if let (Some(lo), Some(hi)) = (lower, upper)
                && lo >= hi
            {
                self.err(
                        Diagnostic::error(
                            "E0302",
                            b.span,
                            format!("the bounds of `{}` are empty: the lower bound is not below the upper bound", p.name.name),
                        )
                        .with_hint("write `in [lower, upper]` with lower < upper"),
                    );
                ok = false;
            }
        }
        let mut init_values = Vec::new();
        if let Some(v) = &init.value {
            v.flatten(&mut init_values);
        }
        if ok && p.bounds.is_some() {
            let si = dim.si_unit();
            for v in &init_values {
                let below = lower.is_some_and(|lo| *v <= lo);
                let above = upper.is_some_and(|hi| *v >= hi);
                if below || above {
                    let fmt_b =
                        |b: Option<f64>| b.map(|x| format!("{x} {si}")).unwrap_or("..".into());
                    let msg = format!(
                        "the initial value of `{}` ({v} {si}) is not strictly inside its bounds [{}, {}]",
                        p.name.name,
                        fmt_b(lower),
                        fmt_b(upper)
                    );
                    self.err(
                        Diagnostic::error("E0301", p.init.span, msg).with_hint(
                            "bounded params are optimized through a smooth transform that never reaches the bounds; start strictly inside them",
                        ),
                    );
                    break;
                }
            }
        }
        self.out.params.push(ParamInfo {
            name: p.name.name.clone(),
            ty: ty.clone(),
            init: init_values,
            lower,
            upper,
        });
        Typed::of(ty, Var::Param)
    }

    /// A param's initial value: its declared type, or a scalar broadcast over its shape.
    fn expect_init(&mut self, init: &Typed, ty: &Ty, e: &Expr, what: &str) -> bool {
        if init.ty.is_scalar_num() && !ty.shape().is_empty() {
            return self.expect_type(init, &Ty::scalar(ty.dim().unwrap()), e, what);
        }
        self.expect_type(init, ty, e, what)
    }

    fn check_input(&mut self, i: &InputDecl) -> Typed {
        let ty = self.resolve_type(&i.ty, false);
        self.check_batch_source(&i.source, ty.as_ref(), &i.name.name);
        match ty {
            Some(ty) => Typed::of(ty, Var::Param),
            None => Typed::error(),
        }
    }

    /// A batch of scene inputs: an array with one entry per scene, or a generator.
    pub(super) fn check_batch_source(&mut self, source: &Expr, ty: Option<&Ty>, name: &str) {
        let t = self.check_expr(source);
        let Some(ty) = ty else { return };
        if t.ty.is_error() {
            return;
        }
        if t.ty == Ty::Obj(Obj::BatchSource) {
            if *ty != Ty::vec3(Dim::LENGTH) {
                let msg =
                    format!("`circle_quadrants` yields length[3] points, but `{name}` is {ty}");
                self.err(Diagnostic::error("E0202", source.span, msg));
            }
            return;
        }
        self.expect_const(&t, source, &format!("the values of `{name}`"));
        let fits = match &t.ty {
            Ty::Num { dim, shape, .. } => {
                Some(*dim) == ty.dim() && !shape.is_empty() && shapes_fit(&shape[1..], ty.shape())
            }
            _ => false,
        };
        if !fits {
            let msg = format!(
                "`{name}` takes one {ty} per scene, so its values must be an array of {ty}, found {}",
                self.describe(source, &t.ty)
            );
            let mut d = Diagnostic::error("E0202", source.span, msg);
            if let Some(h) = ty.dim().and_then(unit_suggestion) {
                d = d.with_hint(h);
            }
            self.err(d);
        }
    }

    fn check_fn(&mut self, id: usize, f: &FnDecl) -> Typed {
        self.push_scope();
        let mut params = Vec::new();
        let mut ok = true;
        for p in &f.params {
            let ty = self.resolve_type(&p.ty, false);
            if let Some(d) = &p.default {
                let t = self.check_expr(d);
                if let Some(ty) = &ty {
                    self.expect_type(&t, ty, d, &format!("the default of `{}`", p.name.name));
                }
            }
            let ty = ty.unwrap_or(Ty::Error);
            ok &= !ty.is_error();
            let def = self.param_def(&f.name, p);
            self.declare_local(
                &p.name.name,
                p.name.span,
                Typed::of(ty.clone(), Var::Const),
                false,
                def,
            );
            params.push(SigParam {
                name: p.name.name.clone(),
                ty,
                has_default: p.default.is_some(),
            });
        }
        self.ctx.time = f.is_controller;
        self.ctx.state = f.is_controller;
        self.ctx.in_controller = f.is_controller;
        let body = self.check_expr(&f.body);
        self.ctx = Default::default();
        let mut ret = body.ty.clone();
        if let Some(rt) = &f.ret {
            match self.resolve_type(rt, false) {
                Some(want) => {
                    self.expect_type(
                        &body,
                        &want,
                        &f.body,
                        &format!("the result of `{}`", f.name.name),
                    );
                    ret = want;
                }
                None => ret = Ty::Error,
            }
        }
        if matches!(ret, Ty::Obj(_)) {
            let msg = format!(
                "functions return numbers or conditions, but `{}` returns {ret}",
                f.name.name
            );
            self.err(Diagnostic::error("E0203", f.body.span, msg));
            ret = Ty::Error;
        }
        // Parameters were declared Const, so the body's variability is what it reads besides them.
        self.pop_scope();
        self.sigs.insert(
            id,
            Signature {
                params,
                ret: if ok { ret } else { Ty::Error },
                body_var: body.var,
            },
        );
        Typed::error()
    }

    fn check_material(&mut self, id: usize, m: &MaterialDecl) -> Typed {
        if let Some(params) = &m.params {
            // A template: check the body once with typed parameters.
            self.push_scope();
            let mut sig = Vec::new();
            for p in params {
                let ty = self.resolve_type(&p.ty, true).unwrap_or(Ty::Error);
                if let Some(d) = &p.default {
                    let t = self.check_expr(d);
                    self.expect_type(&t, &ty, d, &format!("the default of `{}`", p.name.name));
                }
                let def = self.param_def(&m.name, p);
                self.declare_local(
                    &p.name.name,
                    p.name.span,
                    Typed::of(ty.clone(), Var::Const),
                    false,
                    def,
                );
                sig.push(SigParam {
                    name: p.name.name.clone(),
                    ty,
                    has_default: p.default.is_some(),
                });
            }
            match &m.body {
                MaterialBody::Block(stmts) => self.check_material_block(&m.name, stmts),
                MaterialBody::Expr(e) => {
                    self.err(Diagnostic::error(
                        "E0315",
                        e.span,
                        "a material template needs a body `{ density = …; W(…) = … }`",
                    ));
                }
            }
            self.pop_scope();
            self.sigs.insert(
                id,
                Signature {
                    params: sig,
                    ret: Ty::Obj(Obj::Material),
                    body_var: Var::Const,
                },
            );
            return Typed::of(Ty::Obj(Obj::MaterialTemplate), Var::Const);
        }
        match &m.body {
            MaterialBody::Expr(e) => {
                let t = self.check_expr(e);
                match &t.ty {
                    Ty::Error | Ty::Obj(Obj::Material) => {}
                    other => {
                        let msg = format!(
                            "a material is a built-in material like `yeoh(…)` or a block `{{ density = …; W(…) = … }}`, found {other}"
                        );
                        self.err(Diagnostic::error("E0203", e.span, msg));
                    }
                }
                if t.var > Var::Param {
                    self.err(Diagnostic::error(
                        "E0321",
                        e.span,
                        "material constants may depend on params, not on time or state",
                    ));
                }
            }
            MaterialBody::Block(stmts) => {
                self.push_scope();
                self.check_material_block(&m.name, stmts);
                self.pop_scope();
            }
        }
        Typed::of(Ty::Obj(Obj::Material), Var::Const)
    }

    fn check_material_block(&mut self, name: &Ident, stmts: &[Stmt]) {
        let mut density = None;
        let mut energy = None;
        for s in stmts {
            match &s.kind {
                StmtKind::Let(l) => {
                    let t = self.check_expr(&l.value);
                    let t = self.check_let_type(l, t);
                    let def = self.define(&l.name, super::DefKind::LocalLet, s.span, l.ty.clone());
                    self.declare_local(&l.name.name, l.name.span, t, true, def);
                }
                StmtKind::Assign {
                    name: setting,
                    value,
                } if setting.name == "density" => {
                    if let Some(prev) = density.replace(setting.span) {
                        self.err(duplicate_setting("density", setting.span, prev));
                    }
                    let t = self.check_expr(value);
                    let want = Ty::scalar(units::named_dim("density").unwrap());
                    if self.expect_type(&t, &want, value, "`density`") {
                        if t.var > Var::Param {
                            self.err(Diagnostic::error(
                                "E0321",
                                value.span,
                                "the density must not depend on time or state",
                            ));
                        }
                        if t.num().is_some_and(|v| v <= 0.0) {
                            self.err(Diagnostic::error(
                                "E0321",
                                value.span,
                                "the density must be positive",
                            ));
                        }
                    }
                }
                StmtKind::Assign {
                    name: setting,
                    value,
                } => {
                    self.check_expr(value);
                    let mut d = Diagnostic::error(
                        "E0108",
                        setting.span,
                        format!("unknown material setting `{}`", setting.name),
                    )
                    .with_hint("a material block has `density = …` and `W(I1bar, I2bar, J) = …`");
                    if let Some(sug) = did_you_mean(&setting.name, ["density"]) {
                        d = d.with_hint(format!("did you mean `{sug}`?"));
                    }
                    self.err(d);
                }
                StmtKind::Energy {
                    name: w,
                    args,
                    body,
                } => {
                    if let Some(prev) = energy.replace(w.span) {
                        self.err(duplicate_setting("W", w.span, prev));
                    }
                    if w.name != "W" {
                        let msg = format!("the strain energy is named `W`, found `{}`", w.name);
                        self.err(Diagnostic::error("E0315", w.span, msg));
                    }
                    self.push_scope();
                    let has = |n: &str| args.iter().any(|a| a.name == n);
                    if has("I1") && (has("I1bar") || has("I2bar")) {
                        let at = args.iter().find(|a| a.name == "I1").expect("listed");
                        self.err(
                            Diagnostic::error(
                                "E0315",
                                at.span,
                                "W takes either the isochoric invariants (`I1bar`, `I2bar`) or `I1`, not both",
                            )
                            .with_hint("`I1 = J^(2/3) * I1bar`: write W in `I1bar, I2bar, J`, or in `I1, J` for an inversion-safe law"),
                        );
                    }
                    for a in args {
                        let invariants = ["I1bar", "I2bar", "J", "I1"];
                        if !invariants.contains(&a.name.as_str()) {
                            let msg = format!("`{}` is not an invariant", a.name);
                            let hint = match did_you_mean(&a.name, invariants) {
                                Some(s) => format!(
                                    "did you mean `{s}`? W takes any of I1bar, I2bar and J (thesis eq. 2.10–2.13), or I1 and J"
                                ),
                                None => "W takes any of I1bar, I2bar and J (thesis eq. 2.10–2.13), or I1 and J"
                                    .into(),
                            };
                            self.err(Diagnostic::error("E0315", a.span, msg).with_hint(hint));
                            // Still declare it, so its uses in W are not reported again.
                        }
                        if self.scopes.last().unwrap().contains_key(&a.name) {
                            let msg = format!("`{}` is listed twice", a.name);
                            self.err(Diagnostic::error("E0102", a.span, msg));
                            continue;
                        }
                        self.scopes.last_mut().unwrap().insert(
                            a.name.clone(),
                            super::Local {
                                typed: Typed::of(Ty::scalar(Dim::NONE), Var::State),
                                span: a.span,
                                used: false,
                                // Listing all three invariants and using two is fine.
                                warn_unused: false,
                                def: None,
                                implicit: false,
                            },
                        );
                    }
                    let t = self.check_expr(body);
                    self.pop_scope();
                    let pressure = Ty::scalar(units::named_dim("pressure").unwrap());
                    self.expect_type(&t, &pressure, body, "the strain energy density W");
                }
                _ => {
                    self.err(Diagnostic::error(
                        "E0315",
                        s.span,
                        "only `let`, `density = …` and `W(…) = …` belong in a material block",
                    ));
                }
            }
        }
        if density.is_none() {
            let msg = format!("the material `{}` has no density", name.name);
            self.err(
                Diagnostic::error("E0315", name.span, msg)
                    .with_hint("add `density = 1070 kg/m^3` (or the material's density)"),
            );
        }
        if energy.is_none() {
            let msg = format!("the material `{}` has no strain energy", name.name);
            self.err(
                Diagnostic::error("E0315", name.span, msg)
                    .with_hint("add `W(I1bar, I2bar, J) = …`, or use a built-in such as `yeoh(…)`"),
            );
        }
    }

    /// E0110: a name of the wrong kind where `rule` says what belongs there.
    pub(super) fn wrong_kind(&mut self, id: &Ident, k: SymKind, rule: &str, hint: Option<&str>) {
        let msg = format!("{rule}, but `{}` is {}", id.name, k.with_article());
        let mut d = Diagnostic::error("E0110", id.span, msg);
        if let Some(h) = hint {
            d = d.with_hint(h);
        }
        self.err(d);
    }

    pub(super) fn global_kind(&mut self, id: &Ident) -> Option<SymKind> {
        match self.globals.get(&id.name) {
            Some(&g) => {
                self.record_global_use(id, g);
                self.syms[g].used = true;
                let t = self.global_typed_at(g, Some(id.span));
                // A let naming a region, a set or a material stands for it (`let s = clamp`).
                Some(match (self.syms[g].kind, &t.ty) {
                    (SymKind::Let, Ty::Obj(Obj::Region)) => SymKind::Region,
                    (SymKind::Let, Ty::Obj(Obj::NodeSet)) => SymKind::Nodes,
                    (SymKind::Let, Ty::Obj(Obj::ElementSet)) => SymKind::Elements,
                    (SymKind::Let, Ty::Obj(Obj::Material)) => SymKind::Material,
                    (k, _) => k,
                })
            }
            None => {
                self.record_use(id, None);
                let d = self.unknown_name(&id.name, id.span);
                self.err(d);
                None
            }
        }
    }

    /// The declaration a global name stands for: itself, or what a chain of `let`s naming
    /// one another leads to (`let clamp = base`, at most 8 links).
    pub(super) fn declaration_behind(&self, name: &str) -> String {
        let mut name = name.to_string();
        for _ in 0..8 {
            let next = self.user_items.iter().find_map(|i| match &i.kind {
                ItemKind::Let(l) if l.name.name == name => match &l.value.kind {
                    ExprKind::Name(id) => Some(id.name.clone()),
                    _ => None,
                },
                _ => None,
            });
            match next {
                Some(n) => name = n,
                None => break,
            }
        }
        name
    }

    /// Whether the mesh file exists and has a known format (reported otherwise).
    pub(super) fn check_mesh_path(&mut self, path: &str, span: Span) -> bool {
        let Some(base) = self.options.base_dir.clone() else {
            return false;
        };
        let full = base.join(path);
        if full.is_dir() {
            let msg = format!("`{path}` is a folder, not a mesh file");
            self.err(
                Diagnostic::error("E0319", span, msg)
                    .with_hint("name the mesh file, e.g. \"meshes/cuboid.msh\""),
            );
            return false;
        }
        if full.exists() && !full.is_file() {
            // A FIFO or device: reading it would block or never end (issue 20 item 13).
            let msg = format!("`{path}` is not a regular file (a named pipe, device or socket)");
            self.err(
                Diagnostic::error("E0319", span, msg)
                    .with_hint("name a mesh file, e.g. \"meshes/cuboid.msh\""),
            );
            return false;
        }
        if !full.is_file() {
            let msg = format!("mesh file `{path}` not found");
            self.err(Diagnostic::error("E0319", span, msg).with_hint(format!(
                "looked for {}; paths are relative to the script's folder. Generate meshes with `softc mesh generate SPEC.toml -o FILE.msh`",
                full.display()
            )));
            return false;
        }
        let known = ["msh", "vtk", "vtu", "node", "ele", "inp"];
        let ext = full.extension().and_then(|e| e.to_str()).unwrap_or("");
        if !known.contains(&ext) {
            let msg = format!("unsupported mesh format `.{ext}`");
            let hint = if ext.eq_ignore_ascii_case("stl") {
                "an STL file is a surface: make a tet mesh with `softc mesh generate`".to_string()
            } else {
                format!("softc reads {}", known.map(|k| format!(".{k}")).join(", "))
            };
            self.err(Diagnostic::error("E0319", span, msg).with_hint(hint));
            return false;
        }
        true
    }

    /// Checks that need the whole script: the mesh, the sim block, unused declarations.
    pub(super) fn finish(&mut self, items: &[Item]) {
        let meshes: Vec<Span> = self
            .syms
            .iter()
            .filter(|g| !g.prelude && g.kind == SymKind::Mesh)
            .map(|g| g.span)
            .collect();
        let start = Span::new(0, 0);
        if meshes.is_empty() {
            self.err(
                Diagnostic::error(
                    "E0310",
                    items
                        .first()
                        .map_or(start, |i| Span::new(i.span.start, i.span.start)),
                    "the script declares no mesh",
                )
                .with_hint("add `mesh body = load(\"meshes/cuboid.msh\")`"),
            );
        }
        for extra in meshes.iter().skip(1) {
            self.err(
                Diagnostic::error("E0310", *extra, "only one mesh per script is supported")
                    .with_note(meshes[0], "the first mesh")
                    .with_hint("put all bodies into one mesh file; select parts with element sets"),
            );
        }
        if !self.sim.seen {
            self.err(
                Diagnostic::error(
                    "E0311",
                    items
                        .first()
                        .map_or(start, |i| Span::new(i.span.start, i.span.start)),
                    "the script has no sim block",
                )
                .with_hint("add `sim { dt = auto; duration = 1 s; fix …; pressure … = … }`"),
            );
        }
        if let Some(d) = self.sim.duration {
            self.out.duration = Some(d);
        }
        for g in 0..self.syms.len() {
            let s = &self.syms[g];
            if s.prelude || s.used || s.name.starts_with('_') {
                continue;
            }
            let d = match s.kind {
                SymKind::Mesh => continue,
                SymKind::Chamber => {
                    if self.sim.pressured.contains(&s.name) {
                        continue;
                    }
                    Diagnostic::warning(
                        "W0002",
                        s.span,
                        format!("the chamber `{}` has no pressure; it stays at 0 Pa", s.name),
                    )
                    .with_hint(format!(
                        "set it in the sim block: `pressure {} = …`",
                        s.name
                    ))
                }
                SymKind::Param => Diagnostic::warning(
                    "W0001",
                    s.span,
                    format!("the param `{}` is neither used nor optimized", s.name),
                )
                .with_hint("use it in an expression or list it after `optimize`"),
                k => Diagnostic::warning(
                    "W0001",
                    s.span,
                    format!(
                        "the {} `{}` is declared but never used",
                        k.describe(),
                        s.name
                    ),
                )
                .with_hint("remove it, or prefix the name with `_` to keep it"),
            };
            self.err(d);
        }
        for g in 0..self.syms.len() {
            let s = &self.syms[g];
            if !s.prelude
                && s.kind == SymKind::Chamber
                && s.used
                && !self.sim.pressured.contains(&s.name)
            {
                let d = Diagnostic::warning(
                    "W0002",
                    s.span,
                    format!("the chamber `{}` has no pressure; it stays at 0 Pa", s.name),
                )
                .with_hint(format!(
                    "set it in the sim block: `pressure {} = …`",
                    s.name
                ));
                self.err(d);
            }
        }
    }
}

fn duplicate_block(what: &str, span: Span, first: Span) -> Diagnostic {
    Diagnostic::error(
        "E0311",
        Span::new(span.start, span.start + what.len()),
        format!("a second `{what}` block"),
    )
    .with_note(
        Span::new(first.start, first.start + what.len()),
        "the first one",
    )
    .with_hint(format!("a script has at most one `{what}`; merge them"))
}

pub(super) fn duplicate_setting(name: &str, span: Span, first: Span) -> Diagnostic {
    Diagnostic::error("E0109", span, format!("`{name}` is set twice"))
        .with_note(first, "first set here")
}
