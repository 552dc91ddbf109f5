//! The loss and the `optimize` block: its targets, optimizer, settings and statements.

use super::builtins::Interval;
use super::items::{OPTIMIZE_SETTINGS, duplicate_setting};
use super::types::{Obj, Ty, Typed, Var};
use super::units::Dim;
use super::{Checker, SymKind};
use crate::diag::{Diagnostic, did_you_mean};
use crate::front::ast::*;
use std::collections::HashMap;

impl Checker {
    pub(super) fn check_loss(&mut self, loss: &LossDecl) {
        self.ctx.time = true;
        self.ctx.state = true;
        self.ctx.loss_state = true;
        let t = self.check_expr(&loss.value);
        self.ctx = Default::default();
        match &t.ty {
            Ty::Error => {}
            Ty::Num { shape, .. } if shape.is_empty() => self.loss_ty = Some(t.ty.clone()),
            other => {
                let msg = format!("the loss must be a scalar, found {other}");
                self.err(
                    Diagnostic::error("E0204", loss.value.span, msg)
                        .with_hint("reduce it with `sum(n in set) …` or `norm(…)`"),
                );
            }
        }
        if let LossWhen::Over { from, to, span } = &loss.when {
            let mut ends = Vec::new();
            for e in [from, to] {
                let t = self.check_expr(e);
                if self.expect_type(&t, &Ty::scalar(Dim::TIME), e, "the loss window")
                    && self.expect_const(&t, e, "the loss window")
                {
                    ends.push(t.num());
                }
            }
            if let [Some(a), Some(b)] = ends[..] {
                if a < 0.0 {
                    self.err(Diagnostic::error(
                        "E0321",
                        *span,
                        "the loss window starts before the simulation (t < 0)",
                    ));
                } else if a > b {
                    self.err(Diagnostic::error(
                        "E0321",
                        *span,
                        "the loss window ends before it starts",
                    ));
                } else if let Some(d) = self.sim.duration
                    && b > d * (1.0 + 1e-12)
                {
                    let msg = format!(
                        "the loss window [{a} s, {b} s] reaches past the end of the simulation ({d} s)"
                    );
                    self.err(
                        Diagnostic::error("E0321", *span, msg)
                            .with_hint("use `t_end` to refer to the end of the run"),
                    );
                }
            }
        }
    }

    pub(super) fn check_optimize(&mut self, opt: &OptimizeDecl, span: Span, has_loss: bool) {
        if !has_loss {
            self.err(
                Diagnostic::error(
                    "E0313",
                    Span::new(span.start, span.start + 8),
                    "`optimize` needs a loss",
                )
                .with_hint(
                    "declare it, e.g. `loss = sum(n in tip) (x[n].z - x0[n].z + 10 mm)^2 at end`",
                ),
            );
        }
        for t in &opt.targets {
            match self.globals.get(&t.name).copied() {
                Some(g) => self.record_global_use(t, g),
                None => self.record_use(t, None),
            }
            match self.globals.get(&t.name).map(|&g| (g, self.syms[g].kind)) {
                Some((g, SymKind::Param)) => {
                    self.syms[g].used = true;
                    if self.optimized.contains(&t.name) {
                        let msg = format!("`{}` is listed twice", t.name);
                        self.err(Diagnostic::error("E0305", t.span, msg));
                    }
                    self.optimized.push(t.name.clone());
                }
                Some((g, k)) => {
                    self.syms[g].used = true;
                    let msg = format!(
                        "only params can be optimized, but `{}` is {}",
                        t.name,
                        k.with_article()
                    );
                    self.err(Diagnostic::error("E0304", t.span, msg).with_hint(format!(
                        "declare it as `param {}: TYPE = VALUE in [LOWER, UPPER]`",
                        t.name
                    )));
                }
                None => {
                    let d = self.unknown_name(&t.name, t.span);
                    self.err(d);
                }
            }
        }
        let o = self.check_expr(&opt.optimizer);
        if !o.ty.is_error() && o.ty != Ty::Obj(Obj::Optimizer) {
            let msg = format!(
                "expected an optimizer (`gd`, `sgd`, `adam` or `nadam`), found {}",
                o.ty
            );
            self.err(Diagnostic::error("E0203", opt.optimizer.span, msg));
        }
        if let Some(it) = &opt.iterations {
            self.check_count(it, "the iteration count");
        }
        let Some(body) = &opt.body else { return };
        let mut seen: HashMap<&str, Span> = HashMap::new();
        for s in body {
            match &s.kind {
                StmtKind::Assign { name, value } => {
                    if let Some(prev) = seen.insert(name.name.as_str(), name.span) {
                        self.err(duplicate_setting(&name.name, name.span, prev));
                        continue;
                    }
                    self.check_optimize_setting(name, value);
                }
                StmtKind::Stop(cond) => {
                    self.push_scope();
                    let loss_ty = self.loss_ty.clone().unwrap_or(Ty::Error);
                    for (n, ty) in [
                        ("loss", loss_ty),
                        ("grad_norm", Ty::scalar(Dim::NONE)),
                        ("iteration", Ty::int()),
                    ] {
                        self.scopes.last_mut().unwrap().insert(
                            n.to_string(),
                            super::Local {
                                typed: Typed::of(ty, Var::State),
                                span: s.span,
                                used: false,
                                warn_unused: false,
                                def: None,
                                implicit: true,
                            },
                        );
                    }
                    let t = self.check_expr(cond);
                    self.pop_scope();
                    if !matches!(t.ty, Ty::Bool | Ty::Error) {
                        let msg = format!(
                            "`stop when` needs a condition such as `loss < 0.01 mm^2`, found {}",
                            t.ty
                        );
                        self.err(Diagnostic::error("E0207", cond.span, msg));
                    }
                }
                StmtKind::Validate { input, source } => {
                    match self.globals.get(&input.name).copied() {
                        Some(g) => self.record_global_use(input, g),
                        None => self.record_use(input, None),
                    }
                    match self
                        .globals
                        .get(&input.name)
                        .map(|&g| (g, self.syms[g].kind))
                    {
                        Some((g, SymKind::Input)) => {
                            let ty = self.global_typed(g).ty;
                            let ty = (!ty.is_error()).then_some(ty);
                            self.check_batch_source(source, ty.as_ref(), &input.name);
                        }
                        Some((_, k)) => {
                            self.wrong_kind(input, k, "`validate` takes an input", None);
                        }
                        None => {
                            let d = self.unknown_name(&input.name, input.span);
                            self.err(d);
                        }
                    }
                }
                _ => {}
            }
        }
    }

    fn check_optimize_setting(&mut self, name: &Ident, value: &Expr) {
        match name.name.as_str() {
            "batch" | "truncate" => {
                self.check_count(value, &format!("`{}`", name.name));
            }
            "seed" => {
                self.check_count_or_zero(value, "`seed`");
            }
            "gradient_scale" => {
                if let Some(s) = self.check_fraction(
                    value,
                    "`gradient_scale` (s, thesis eq. 5.4)",
                    Interval::UpToOne,
                ) && s < 1.0
                {
                    self.err(
                            Diagnostic::warning(
                                "W0003",
                                value.span,
                                {
                                    let window = (1.0 / (1.0 - s)).round().max(1.0);
                                    format!(
                                        "`gradient_scale = {s}` does not rescale the gradient: it forgets adjoint contributions older than about {window} step{}",
                                        if window == 1.0 { "" } else { "s" }
                                    )
                                },
                            )
                            .with_hint("the default 1 gives the exact gradient; to tame its magnitude use `normalize = magnitude(m: …)` or `clip`"),
                        );
                }
            }
            "clip" => {
                self.check_fraction(value, "`clip` (global gradient norm)", Interval::Positive);
            }
            "normalize" | "lr_schedule" | "checkpoint" => {
                let t = self.check_expr(value);
                let (ok, options) = match name.name.as_str() {
                    "normalize" => (
                        matches!(t.ty, Ty::Obj(Obj::Normalizer | Obj::Auto | Obj::None)),
                        "`magnitude(m: …)`, `auto` or `none`",
                    ),
                    "lr_schedule" => (
                        t.ty == Ty::Obj(Obj::Schedule),
                        "`constant`, `exponential(gamma: …)`, `step_decay(every: …, gamma: …)` or `cosine(floor: …)`",
                    ),
                    _ => (
                        matches!(t.ty, Ty::Obj(Obj::Checkpoint | Obj::Auto)),
                        "`auto`, `store_all`, `periodic(steps: …)` or `revolve(snapshots: …)`",
                    ),
                };
                if !ok && !t.ty.is_error() {
                    let msg = format!("`{}` must be {options}, found {}", name.name, t.ty);
                    self.err(Diagnostic::error("E0203", value.span, msg));
                }
            }
            "memory_budget" => {
                let t = self.check_expr(value);
                if self.expect_type(&t, &Ty::scalar(Dim::MEMORY), value, "`memory_budget`")
                    && self.expect_const(&t, value, "`memory_budget`")
                    && t.num().is_some_and(|v| v <= 0.0)
                {
                    self.err(Diagnostic::error(
                        "E0321",
                        value.span,
                        "`memory_budget` must be positive",
                    ));
                }
            }
            other => {
                self.check_expr(value);
                let mut d = Diagnostic::error(
                    "E0108",
                    name.span,
                    format!("unknown optimize setting `{other}`"),
                );
                d = match did_you_mean(other, OPTIMIZE_SETTINGS.iter().copied()) {
                    Some(s) => d.with_hint(format!("did you mean `{s}`?")),
                    None => d.with_hint(format!(
                        "the optimize settings are: {}",
                        OPTIMIZE_SETTINGS.join(", ")
                    )),
                };
                self.err(d);
            }
        }
    }
}
