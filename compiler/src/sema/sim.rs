//! The `sim` block: its statements and settings, and the `window(t, width)` checks.

use super::builtins::Interval;
use super::items::{SIM_SETTINGS, duplicate_setting};
use super::types::{Len, Obj, Ty, Typed};
use super::units::{self, Dim};
use super::{Checker, GState, SymKind};
use crate::diag::{Diagnostic, did_you_mean};
use crate::front::ast::*;
use std::collections::HashMap;

impl Checker {
    pub(super) fn check_sim(&mut self, stmts: &[Stmt], span: Span) {
        self.sim.seen = true;
        let mut seen: HashMap<&str, Span> = HashMap::new();
        let mut assigns = Vec::new();
        // Durations first: pressures and windows refer to them.
        for s in stmts {
            if let StmtKind::Assign { name, value } = &s.kind {
                if let Some(prev) = seen.insert(name.name.as_str(), name.span) {
                    self.err(duplicate_setting(&name.name, name.span, prev));
                    continue;
                }
                assigns.push((name, value));
            }
        }
        // A static solve has no time step: `duration` places its loads in time and `steps`
        // counts the equilibrium states along it (one, at the end, by default).
        let quasi_static = assigns.iter().any(|(n, v)| {
            n.name == "integrator"
                && matches!(&v.kind, ExprKind::Name(i) if i.name == "quasi_static")
        });
        self.sim.solves_state = assigns.iter().find_map(|(n, v)| match &v.kind {
            ExprKind::Name(i) if n.name == "integrator" => match i.name.as_str() {
                "quasi_static" => Some("quasi_static"),
                "implicit_euler" => Some("implicit_euler"),
                _ => None,
            },
            _ => None,
        });
        let mut dt = None;
        let mut steps = None;
        self.push_scope();
        self.sim.defining_duration = true;
        for (name, value) in &assigns {
            match name.name.as_str() {
                "dt" => {
                    if let Some(v) = self.positive_time(value, "`dt`") {
                        dt = Some(v);
                    }
                }
                "steps" => {
                    steps = self.check_count(value, "`steps`");
                }
                "duration" => {
                    if let Some(v) = self.positive_time(value, "`duration`") {
                        self.sim.duration = Some(v);
                    }
                }
                _ => {}
            }
        }
        self.sim.defining_duration = false;
        if quasi_static {
            for setting in ["dt", "damping", "mass_scaling"] {
                // `steps` and `dt` without `duration` do define the states' times.
                let defines_times = setting == "dt" && !seen.contains_key("duration");
                if let Some(&at) = seen.get(setting).filter(|_| !defines_times) {
                    self.err(
                        Diagnostic::warning(
                            "W0005",
                            at,
                            format!("`{setting}` does not affect a quasi-static solve"),
                        )
                        .with_hint(
                            "`integrator = quasi_static` finds equilibrium states directly; \
                             remove the setting, or use `integrator = semi_implicit_euler` for dynamics",
                        ),
                    );
                }
            }
            // States at t_end·k/steps: `dt` in expressions is their spacing.
            if let Some(d) = self.sim.duration {
                dt = Some(d / steps.unwrap_or(1.0));
            } else if let (Some(n), Some(dt)) = (steps, dt) {
                self.sim.duration = Some(n * dt);
            }
            self.sim.dt = dt;
        } else {
            self.sim.dt = dt;
            if let (Some(n), Some(dt)) = (steps, dt) {
                self.sim.duration = Some(n * dt);
            }
        }
        // A misspelt setting (`durration`) is reported as unknown with a suggestion; do not also
        // report the setting it was meant to be as missing.
        let misspelt = |want: &[&str]| {
            assigns.iter().any(|(n, _)| {
                !SIM_SETTINGS.contains(&n.name.as_str())
                    && did_you_mean(&n.name, SIM_SETTINGS.iter().copied())
                        .is_some_and(|s| want.contains(&s))
            })
        };
        let steps_misspelt = misspelt(&["steps", "duration"]);
        let dt_misspelt = misspelt(&["dt"]);
        match (seen.get("steps"), seen.get("duration")) {
            (Some(_), None) if quasi_static && !seen.contains_key("dt") => self.err(
                Diagnostic::error(
                    "E0312",
                    Span::new(span.start, span.start + 3),
                    "a quasi-static sim block needs `duration`: the time at which its loads \
                     are taken (`steps` counts the equilibrium states along it)",
                )
                .with_hint("add e.g. `duration = 1 s`"),
            ),
            (Some(_), Some(_)) if quasi_static => {}
            (Some(&a), Some(&b)) => self.err(
                Diagnostic::error(
                    "E0312",
                    a.max_by_start(b),
                    "give either `steps` or `duration`, not both",
                )
                .with_hint("`duration = steps × dt`"),
            ),
            (None, None) if !steps_misspelt => self.err(
                Diagnostic::error(
                    "E0312",
                    Span::new(span.start, span.start + 3),
                    "the sim block sets neither `steps` nor `duration`",
                )
                .with_hint("add e.g. `duration = 2 s`"),
            ),
            _ => {}
        }
        if !seen.contains_key("dt") && !dt_misspelt && !quasi_static {
            self.err(
                Diagnostic::error(
                    "E0312",
                    Span::new(span.start, span.start + 3),
                    "the sim block has no time step `dt`",
                )
                .with_hint(
                    "add `dt = auto` (the largest stable step, estimated) or e.g. `dt = 20 us`",
                ),
            );
        }
        // The remaining settings and statements, in order, with `t` in scope.
        self.ctx.time = true;
        self.ctx.state = true;
        let mut materials_used = false;
        let mut whole_mesh_use = false;
        // The block's lets, for [`Checker::node_set_reduction`].
        let sim_lets: HashMap<String, Expr> = stmts
            .iter()
            .filter_map(|st| match &st.kind {
                StmtKind::Let(l) => Some((l.name.name.clone(), l.value.clone())),
                _ => None,
            })
            .collect();
        for s in stmts {
            match &s.kind {
                StmtKind::Assign { name, value } => {
                    if seen.get(name.name.as_str()) != Some(&name.span) {
                        continue; // duplicate, already reported
                    }
                    self.check_sim_setting(name, value, &sim_lets);
                }
                StmtKind::Let(l) => {
                    let t = self.check_expr(&l.value);
                    let t = self.check_let_type(l, t);
                    let def = self.define(&l.name, super::DefKind::LocalLet, s.span, l.ty.clone());
                    self.declare_local(&l.name.name, l.name.span, t, true, def);
                }
                StmtKind::Fix(names) => {
                    for n in names {
                        let kind = self.global_kind(n);
                        if matches!(kind, Some(SymKind::Region | SymKind::Nodes)) {
                            self.out.mesh_refs.fixed.push(super::mesh_probe::FixTarget {
                                name: self.declaration_behind(&n.name),
                                region: kind == Some(SymKind::Region),
                            });
                        }
                        match kind {
                            Some(SymKind::Region) => self.check_region_nonempty(n),
                            Some(SymKind::Nodes) | None => {}
                            Some(k) => {
                                self.wrong_kind(n, k, "`fix` takes regions or node sets", None);
                            }
                        }
                    }
                }
                StmtKind::Pressure { chamber, value } => {
                    match self.global_kind(chamber) {
                        Some(SymKind::Chamber) => {
                            if self.sim.pressured.contains(&chamber.name) {
                                let msg =
                                    format!("the pressure of `{}` is set twice", chamber.name);
                                self.err(Diagnostic::error("E0317", chamber.span, msg));
                            }
                            self.sim.pressured.push(chamber.name.clone());
                        }
                        Some(k) => {
                            self.wrong_kind(
                                chamber,
                                k,
                                "`pressure` applies to chambers",
                                Some("declare it with `chamber NAME = surface(mesh, \"name\")`"),
                            );
                        }
                        None => {}
                    }
                    let t = self.check_expr(value);
                    let p = Ty::scalar(units::named_dim("pressure").unwrap());
                    let what = format!("the pressure of `{}`", chamber.name);
                    self.expect_type(&t, &p, value, &what);
                    self.check_closed_loop(value, &what, &sim_lets);
                }
                StmtKind::Contact {
                    body,
                    obstacle,
                    args,
                } => {
                    let mut seen = std::mem::take(&mut self.sim.contacts);
                    self.check_contact(body, obstacle, args, s.span, &mut seen);
                    self.sim.contacts = seen;
                }
                StmtKind::Use { material, set } => {
                    self.out
                        .mesh_refs
                        .uses
                        .push((material.name.clone(), set.as_ref().map(|s| s.name.clone())));
                    materials_used = true;
                    whole_mesh_use |= set.is_none();
                    match self.global_kind(material) {
                        Some(SymKind::Material) | None => {}
                        Some(SymKind::MaterialTemplate) => {
                            let msg = format!(
                                "`{}` is a material template; give its constants first",
                                material.name
                            );
                            self.err(Diagnostic::error("E0110", material.span, msg).with_hint(
                                format!(
                                    "declare `material silicone = {}(…)` and `use silicone`",
                                    material.name
                                ),
                            ));
                        }
                        Some(k) => {
                            self.wrong_kind(material, k, "`use` takes a material", None);
                        }
                    }
                    if let Some(set) = set {
                        match self.global_kind(set) {
                            Some(SymKind::Elements) | None => {}
                            Some(k) => {
                                self.wrong_kind(
                                    set,
                                    k,
                                    "materials are assigned to element sets",
                                    Some("declare it with `elements NAME = select(mesh, …)`"),
                                );
                            }
                        }
                    }
                }
                StmtKind::Output { what, every, steps } => {
                    let t = self.check_expr(what);
                    if !t.ty.is_error() && t.ty != Ty::Obj(Obj::OutputKind) {
                        let msg =
                            format!("`output` takes `vtk` or `csv(node_set)`, found {}", t.ty);
                        self.err(Diagnostic::error("E0203", what.span, msg));
                    }
                    if *steps {
                        self.check_count(every, "the output interval");
                    } else {
                        let t = self.check_expr(every);
                        if t.ty.is_int_scalar() {
                            self.err(
                                Diagnostic::error(
                                    "E0202",
                                    every.span,
                                    "an output interval needs a unit",
                                )
                                .with_hint("write `every 100 steps` or `every 10 ms`"),
                            );
                        } else if self.expect_type(
                            &t,
                            &Ty::scalar(Dim::TIME),
                            every,
                            "the output interval",
                        ) && self.expect_const(&t, every, "the output interval")
                            && t.num().is_some_and(|v| v <= 0.0)
                        {
                            self.err(Diagnostic::error(
                                "E0321",
                                every.span,
                                "the output interval must be positive",
                            ));
                        }
                    }
                }
                _ => {}
            }
        }
        self.ctx = Default::default();
        self.pop_scope();
        let sim_kw = Span::new(span.start, span.start + 3);
        if materials_used && !whole_mesh_use {
            self.err(
                Diagnostic::warning(
                    "W0004",
                    sim_kw,
                    "materials are assigned only to element sets; elements outside them get none",
                )
                .with_hint("add `use NAME` (the whole mesh) before the `use NAME in SET` lines"),
            );
        }
        if !materials_used {
            let materials: Vec<usize> = (0..self.syms.len())
                .filter(|&i| !self.syms[i].prelude && self.syms[i].kind == SymKind::Material)
                .collect();
            let declared = self
                .user_items
                .iter()
                .filter(|i| matches!(&i.kind, ItemKind::Material(m) if m.params.is_none()))
                .count();
            match materials.len() {
                1 => self.syms[materials[0]].used = true,
                // A material whose declaration failed was reported already.
                0 if declared > 0 => {}
                0 => self.err(
                    Diagnostic::error("E0318", sim_kw, "no material is declared").with_hint(
                        "declare one, e.g. `material silicone = yeoh(c10: 0.11 MPa, d1: 1.0 /MPa, density: 1070 kg/m^3)`",
                    ),
                ),
                _ => {
                    self.err(
                        Diagnostic::error(
                            "E0318",
                            sim_kw,
                            "several materials are declared but the sim block assigns none",
                        )
                        .with_hint(
                            "add `use NAME` for the whole mesh and `use NAME in SET` for element sets",
                        ),
                    );
                    // The error says it; no "unused" warning per material.
                    for m in materials {
                        self.syms[m].used = true;
                    }
                }
            }
        }
        // Windowed schedules must cover the simulated time.
        let windows = std::mem::take(&mut self.sim.windows);
        if let Some(duration) = self.sim.duration {
            for (width, sp) in &windows {
                let count = (duration / width - 1e-9).ceil().max(1.0) as usize;
                self.check_window_lengths(count, *width, *sp);
            }
        }
    }

    /// A constant positive time (`dt`, `duration`); `None` for `auto` or an invalid value
    /// (reported).
    fn positive_time(&mut self, value: &Expr, what: &str) -> Option<f64> {
        let t = self.check_expr(value);
        if t.ty == Ty::Obj(Obj::Auto) && what == "`dt`" {
            return None;
        }
        if !self.expect_type(&t, &Ty::scalar(Dim::TIME), value, what)
            || !self.expect_const(&t, value, what)
        {
            return None;
        }
        match t.num() {
            Some(v) if v <= 0.0 => {
                let msg = format!("{what} must be positive");
                self.err(Diagnostic::error("E0321", value.span, msg));
                None
            }
            v => v,
        }
    }

    /// Every param vector indexed by `window(t, width)` — directly or through `let`s — must
    /// have one entry per window of the simulated time.
    fn check_window_lengths(&mut self, count: usize, width: f64, sp: Span) {
        let mut roots: Vec<Expr> = Vec::new();
        let mut lets: HashMap<String, Expr> = HashMap::new();
        for item in &self.user_items {
            match &item.kind {
                ItemKind::Sim(stmts) => {
                    for st in stmts {
                        match &st.kind {
                            StmtKind::Assign { value, .. } | StmtKind::Pressure { value, .. } => {
                                roots.push(value.clone())
                            }
                            StmtKind::Let(l) => {
                                roots.push(l.value.clone());
                                lets.insert(l.name.name.clone(), l.value.clone());
                            }
                            _ => {}
                        }
                    }
                }
                ItemKind::Let(l) => {
                    roots.push(l.value.clone());
                    lets.insert(l.name.name.clone(), l.value.clone());
                }
                ItemKind::Fn(f) => roots.push(f.body.clone()),
                ItemKind::Loss(l) => roots.push(l.value.clone()),
                _ => {}
            }
        }
        let mut reported = Vec::new();
        for root in &roots {
            let mut stack = vec![root];
            while let Some(e) = stack.pop() {
                if let ExprKind::Index { base, indices } = &e.kind
                    && let (ExprKind::Name(id), [idx]) = (&base.kind, indices.as_slice())
                    && is_window_index(idx, sp, &lets, 0)
                    && !reported.contains(&e.span)
                {
                    reported.push(e.span);
                    self.check_window_param(id, e.span, count, width);
                }
                e.for_each_child(|c| stack.push(c));
            }
        }
    }

    /// Closed-loop control: a pressure or damping may read reductions over node or element
    /// sets (`mean(n in tip) x[n].z`, directly or through a `let`, function or controller);
    /// the host evaluates each as a sensor at the state a step starts from (or at a static
    /// or implicit iterate). E0325 where a reduction cannot be evaluated apart from the
    /// kernel: it reads an argument of the function or controller it is in (or the variable
    /// of an enclosing reduction over a range), or the velocities `v` where the integrator
    /// solves for positions.
    fn check_closed_loop(&mut self, value: &Expr, what: &str, sim_lets: &HashMap<String, Expr>) {
        let mut seen = Vec::new();
        let mut problems = Vec::new();
        self.sensor_problems(value, sim_lets, &[], &mut seen, &mut problems);
        if let Some((set, why)) = problems.into_iter().next() {
            let msg = format!(
                "{what} reads a reduction over the set `{set}` (here or in a `let`, function or \
                 controller it uses) that cannot be evaluated as a sensor of closed-loop \
                 control: {why}"
            );
            self.err(Diagnostic::error("E0325", value.span, msg).with_hint(
                "write the reduction with the state, params, inputs, `t` and lets only (e.g. \
                 `controller err(goal: length) = goal - tip_z()` with `controller tip_z() = \
                 mean(n in tip) x[n].z`)",
            ));
        }
    }

    /// The reductions over sets in `e` that cannot be sensors, following the names it uses
    /// into the sim block's lets, global lets, functions and controllers; `locals` are the
    /// names bound around `e` (arguments of the function it is in, range variables).
    fn sensor_problems(
        &self,
        e: &Expr,
        sim_lets: &HashMap<String, Expr>,
        locals: &[String],
        seen: &mut Vec<String>,
        problems: &mut Vec<(String, String)>,
    ) {
        let set_of = |domain: &Expr| match &domain.kind {
            ExprKind::Name(set)
                if matches!(
                    self.globals.get(&set.name).map(|&g| self.syms[g].kind),
                    Some(SymKind::Nodes | SymKind::Elements)
                ) =>
            {
                Some(set.name.clone())
            }
            _ => None,
        };
        match &e.kind {
            ExprKind::Reduce {
                var, domain, body, ..
            } => {
                if let Some(set) = set_of(domain) {
                    let mut names = Vec::new();
                    free_names(body, &mut names);
                    if let Some(local) = names.iter().find(|n| locals.contains(n)) {
                        problems.push((
                            set,
                            format!(
                                "it reads `{local}`, which is bound outside the reduction (an \
                                 argument of the function or controller it is in, or an \
                                 enclosing reduction's variable), and the host evaluates it \
                                 apart from the kernel"
                            ),
                        ));
                    } else if let Some(integrator) = self.sim.solves_state
                        && names.iter().any(|n| n == "v")
                    {
                        problems.push((
                            set,
                            format!(
                                "it reads the velocities `v`, and `integrator = {integrator}` \
                                 evaluates sensors at the positions it solves for; read \
                                 positions (`x`, `x0`) only"
                            ),
                        ));
                    }
                    // What the body calls is evaluated with it.
                    let mut inner = locals.to_vec();
                    inner.push(var.name.clone());
                    self.sensor_problems(body, sim_lets, &inner, seen, problems);
                } else {
                    self.sensor_problems(domain, sim_lets, locals, seen, problems);
                    let mut inner = locals.to_vec();
                    inner.push(var.name.clone());
                    self.sensor_problems(body, sim_lets, &inner, seen, problems);
                }
                return;
            }
            ExprKind::Name(id) => self.follow(&id.name, sim_lets, locals, seen, problems),
            ExprKind::Call { callee, .. } => {
                if let ExprKind::Name(id) = &callee.kind {
                    self.follow(&id.name, sim_lets, locals, seen, problems);
                }
            }
            _ => {}
        }
        e.for_each_child(|c| self.sensor_problems(c, sim_lets, locals, seen, problems));
    }

    /// [`Checker::sensor_problems`] in the definition a name refers to.
    fn follow(
        &self,
        name: &str,
        sim_lets: &HashMap<String, Expr>,
        locals: &[String],
        seen: &mut Vec<String>,
        problems: &mut Vec<(String, String)>,
    ) {
        if locals.iter().any(|l| l == name) || seen.iter().any(|s| s == name) {
            return;
        }
        seen.push(name.to_string());
        if let Some(v) = sim_lets.get(name) {
            self.sensor_problems(v, sim_lets, &[], seen, problems);
        } else if let Some(&g) = self.globals.get(name) {
            match self.item(self.syms[g].prelude, self.syms[g].item).kind {
                ItemKind::Let(l) => self.sensor_problems(&l.value, sim_lets, &[], seen, problems),
                ItemKind::Fn(f) => {
                    let args: Vec<String> = f.params.iter().map(|p| p.name.name.clone()).collect();
                    self.sensor_problems(&f.body, sim_lets, &args, seen, problems);
                }
                _ => {}
            }
        }
    }

    fn check_window_param(&mut self, id: &Ident, span: Span, count: usize, width: f64) {
        let Some(&g) = self.globals.get(&id.name) else {
            return;
        };
        let GState::Done(t) = &self.syms[g].state else {
            return;
        };
        if let Some(Len::Fixed(n)) = t.ty.shape().first()
            && *n != count
        {
            let n = *n;
            let msg = format!(
                "`{}` has {n} entries, but the simulation spans {count} windows of {} s",
                id.name, width
            );
            self.err(Diagnostic::error("E0316", span, msg).with_hint(format!(
                "declare `{}` with {count} entries, or change the window width or the duration",
                id.name
            )));
        }
    }

    fn check_sim_setting(&mut self, name: &Ident, value: &Expr, sim_lets: &HashMap<String, Expr>) {
        let obj_setting = |want: Obj| move |t: &Typed| t.ty.is_error() || t.ty == Ty::Obj(want);
        match name.name.as_str() {
            "dt" | "steps" | "duration" => {}
            "integrator" | "model" | "precision" => {
                let options: &[&str] = match name.name.as_str() {
                    "integrator" => &["semi_implicit_euler", "implicit_euler", "quasi_static"],
                    "model" => &["fem", "springs"],
                    _ => &["f32", "f64"],
                };
                if self.unknown_option(value, &name.name, options) {
                    return;
                }
                let t = self.check_expr(value);
                let (want, options) = match name.name.as_str() {
                    "integrator" => (
                        Obj::Integrator,
                        "`semi_implicit_euler`, `implicit_euler` or `quasi_static`",
                    ),
                    "model" => (Obj::ForceModel, "`fem` or `springs(volume_stiffness: …)`"),
                    _ => (Obj::Precision, "`f32` or `f64`"),
                };
                if !obj_setting(want)(&t) {
                    let msg = format!("`{}` must be {options}, found {}", name.name, t.ty);
                    self.err(Diagnostic::error("E0203", value.span, msg));
                } else if name.name == "model"
                    && self.sim.quadratic
                    && matches!(&value.kind, ExprKind::Call { callee, .. }
                        if matches!(&callee.kind, ExprKind::Name(n) if n.name == "springs"))
                {
                    self.err(
                        Diagnostic::error(
                            "E0321",
                            value.span,
                            "the spring mesh works on linear tetrahedra, and the mesh is loaded \
                             with `order: 2`",
                        )
                        .with_hint("use `model = fem`, or load the mesh with `order: 1`"),
                    );
                }
            }
            "damping" => {
                self.check_damping_param_bounds(value);
                let t = self.check_expr(value);
                self.expect_type(
                    &t,
                    &Ty::scalar(Dim::TIME.inv()),
                    value,
                    "`damping` (β, thesis eq. 2.17)",
                );
                self.check_closed_loop(value, "`damping`", sim_lets);
                if t.num().is_some_and(|v| v < 0.0) {
                    self.err(Diagnostic::error(
                        "E0321",
                        value.span,
                        "`damping` must not be negative",
                    ));
                }
            }
            "gravity" => {
                let t = self.check_expr(value);
                let acc = Dim::LENGTH.per(Dim::TIME.powi(2).unwrap());
                if self.expect_type(&t, &Ty::vec3(acc), value, "`gravity`") {
                    self.expect_const(&t, value, "`gravity`");
                }
            }
            "mass_scaling" => {
                if let Some(v) = self.check_fraction(value, "`mass_scaling`", Interval::Positive)
                    && v < 1.0
                {
                    self.err(
                        Diagnostic::error("E0321", value.span, "`mass_scaling` must be at least 1")
                            .with_hint(
                                "mass scaling multiplies the masses to allow a larger stable dt",
                            ),
                    );
                }
            }
            other => {
                self.check_expr(value);
                let mut d =
                    Diagnostic::error("E0108", name.span, format!("unknown sim setting `{other}`"));
                d = match did_you_mean(other, SIM_SETTINGS.iter().copied()) {
                    Some(s) => d.with_hint(format!("did you mean `{s}`?")),
                    None if other == "pressure" => {
                        d.with_hint("chamber pressures are written `pressure CHAMBER = …`")
                    }
                    None => {
                        d.with_hint(format!("the sim settings are: {}", SIM_SETTINGS.join(", ")))
                    }
                };
                self.err(d);
            }
        }
    }

    /// A setting given a bare name that means nothing: list the setting's options.
    fn unknown_option(&mut self, value: &Expr, setting: &str, options: &[&str]) -> bool {
        let ExprKind::Name(id) = &value.kind else {
            return false;
        };
        let known = self.globals.contains_key(&id.name)
            || super::builtins::CONSTANTS
                .iter()
                .any(|(n, _)| *n == id.name)
            || super::builtins::FUNCTIONS.contains(&id.name.as_str());
        if known {
            return false;
        }
        let list = options
            .iter()
            .map(|o| format!("`{o}`"))
            .collect::<Vec<_>>()
            .join(", ");
        let mut d = Diagnostic::error("E0101", id.span, format!("unknown {setting} `{}`", id.name));
        d = match did_you_mean(&id.name, options.iter().copied()) {
            Some(s) => d.with_hint(format!("did you mean `{s}`? The options are {list}")),
            None => d.with_hint(format!("the options are {list}")),
        };
        self.err(d);
        true
    }

    /// A damping param that the optimizer could drive below zero would make the run blow up.
    fn check_damping_param_bounds(&mut self, value: &Expr) {
        let mut names = Vec::new();
        let mut stack = vec![value];
        while let Some(e) = stack.pop() {
            if let ExprKind::Name(id) = &e.kind {
                names.push(id.clone());
            }
            e.for_each_child(|c| stack.push(c));
        }
        for name in names {
            self.check_damping_param(&name);
        }
    }

    fn check_damping_param(&mut self, name: &Ident) {
        let Some(&g) = self.globals.get(&name.name) else {
            return;
        };
        if self.syms[g].kind != SymKind::Param {
            return;
        }
        self.global_typed(g);
        let Some(p) = self.out.params.iter().find(|p| p.name == name.name) else {
            return;
        };
        let negative_start = p.init.iter().any(|v| *v < 0.0);
        if negative_start || p.lower.is_none_or(|lo| lo < 0.0) {
            let msg = format!("the damping param `{}` may become negative", name.name);
            self.err(Diagnostic::error("E0303", name.span, msg).with_hint(format!(
                "negative damping adds energy and the run blows up: bound it, e.g. `param {}: rate = 20 /s in [0 /s, 200 /s]`",
                name.name
            )));
        }
    }
}

trait SpanExt {
    fn max_by_start(self, other: Span) -> Span;
}

impl SpanExt for Span {
    fn max_by_start(self, other: Span) -> Span {
        if self.start >= other.start {
            self
        } else {
            other
        }
    }
}

/// Whether an index expression is the `window(t, width)` call whose width argument is at `sp`,
/// possibly through `let`s.
fn is_window_index(idx: &Expr, sp: Span, lets: &HashMap<String, Expr>, depth: usize) -> bool {
    match &idx.kind {
        ExprKind::Paren(inner) => is_window_index(inner, sp, lets, depth),
        ExprKind::Call { callee, args } => {
            matches!(&callee.kind, ExprKind::Name(c) if c.name == "window")
                && args.len() == 2
                && args[1].value.span == sp
        }
        ExprKind::Name(n) if depth < 16 => lets
            .get(&n.name)
            .is_some_and(|v| is_window_index(v, sp, lets, depth + 1)),
        _ => false,
    }
}

/// The names `e` reads that it does not bind itself (reduction variables).
fn free_names(e: &Expr, out: &mut Vec<String>) {
    match &e.kind {
        ExprKind::Name(id) => out.push(id.name.clone()),
        ExprKind::Reduce {
            var, domain, body, ..
        } => {
            free_names(domain, out);
            let mut inner = Vec::new();
            free_names(body, &mut inner);
            out.extend(inner.into_iter().filter(|n| *n != var.name));
        }
        ExprKind::Call { args, .. } => {
            // A callee is a global; its arguments are read here.
            for a in args {
                free_names(&a.value, out);
            }
        }
        _ => e.for_each_child(|c| free_names(c, out)),
    }
}
