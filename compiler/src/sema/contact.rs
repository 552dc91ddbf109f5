//! Checking of rigid obstacles (`obstacle NAME = plane(…)`, `sphere(…)`, `box(…)`,
//! `cylinder(…)`) and of the sim
//! block's `contact BODY with OBSTACLE (…)` statements (SPEC 5.11, 6.6).
//!
//! An obstacle's shape is its own call, not a region: its position may follow the time `t`
//! (a moving plate) or a param (a trainable pose), which a region's constant geometry may not.

use super::types::{Obj, Ty, Typed, Var};
use super::units::Dim;
use super::{Checker, SymKind};
use crate::diag::Diagnostic;
use crate::front::ast::{Arg, Expr, ExprKind, Ident};

/// The shapes an obstacle can have, with their arguments (all required).
/// `box` and `cylinder` take a region's arguments (SPEC 5.3).
const SHAPES: &[(&str, &[&str])] = &[
    ("plane", &["point", "normal"]),
    ("sphere", &["center", "radius"]),
    ("box", &["min", "max"]),
    ("cylinder", &["start", "end", "radius"]),
];

impl Checker {
    /// The type of an obstacle declaration's value: `Obj::Obstacle`, or an error reported.
    pub(super) fn check_obstacle(&mut self, value: &Expr) -> Typed {
        let call = match &value.kind {
            ExprKind::Call { callee, args } => match &callee.kind {
                ExprKind::Name(id) => Some((id, args)),
                _ => None,
            },
            _ => None,
        };
        let shape = call.and_then(|(id, args)| {
            let (_, params) = SHAPES.iter().find(|(n, _)| *n == id.name)?;
            Some((id, *params, args))
        });
        let Some((id, params, args)) = shape else {
            let found = match call {
                Some((id, _)) => format!("`{}(…)`", id.name),
                None => "something else".to_string(),
            };
            self.err(
                Diagnostic::error(
                    "E0203",
                    value.span,
                    format!(
                        "an obstacle is declared with `plane(point: …, normal: …)`, \
                         `sphere(center: …, radius: …)`, `box(min: …, max: …)` or \
                         `cylinder(start: …, end: …, radius: …)`, found {found}"
                    ),
                )
                .with_hint("e.g. `obstacle floor = plane(point: [0, 0, 0] mm, normal: [0, 0, 1])`"),
            );
            return Typed::error();
        };
        let slots: Vec<(&str, bool)> = params.iter().map(|p| (*p, true)).collect();
        let Some(bound) = self.bind(&id.name, value.span, &slots, args) else {
            return Typed::error();
        };
        let mut ok = true;
        // Constant corner or end points, for the checks between them.
        let mut points: Vec<Option<Vec<f64>>> = Vec::new();
        for (pname, slot) in params.iter().zip(bound) {
            let arg = slot.expect("required");
            // An obstacle may move: its geometry may read `t`.
            let outer = std::mem::replace(&mut self.ctx.time, true);
            let t = self.check_expr(arg);
            self.ctx.time = outer;
            let want = match *pname {
                "radius" => Ty::scalar(Dim::LENGTH),
                "normal" => Ty::vec3(Dim::NONE),
                _ => Ty::vec3(Dim::LENGTH),
            };
            let what = format!("the obstacle's `{pname}`");
            if !self.expect_type(&t, &want, arg, &what) {
                ok = false;
                continue;
            }
            if t.var == Var::State {
                self.err(Diagnostic::error(
                    "E0321",
                    arg.span,
                    format!(
                        "{what} may follow the time `t` or a param, but not the simulation state"
                    ),
                ));
                ok = false;
            }
            if matches!(*pname, "min" | "max" | "start" | "end") {
                points.push(t.value.as_ref().map(|v| {
                    let mut xs = Vec::new();
                    v.flatten(&mut xs);
                    xs
                }));
            }
            match (*pname, &t.value) {
                ("radius", _) if t.num().is_some_and(|r| r <= 0.0) => {
                    self.err(Diagnostic::error(
                        "E0321",
                        arg.span,
                        "the radius must be positive",
                    ));
                    ok = false;
                }
                ("normal", Some(v)) => {
                    let mut xs = Vec::new();
                    v.flatten(&mut xs);
                    if xs.iter().all(|c| *c == 0.0) {
                        self.err(
                            Diagnostic::error("E0321", arg.span, "the normal is zero")
                                .with_hint("the normal points from the plane into the free side"),
                        );
                        ok = false;
                    }
                }
                _ => {}
            }
        }
        if let [Some(a), Some(b)] = &points[..]
            && a.len() == 3
            && b.len() == 3
        {
            let problem = match id.name.as_str() {
                "box" => (0..3).find(|&i| a[i] >= b[i]).map(|i| {
                    let axis = ["x", "y", "z"][i];
                    (
                        format!("the box is empty: min.{axis} is not below max.{axis}"),
                        "swap min and max, or widen the box",
                    )
                }),
                _ if a == b => Some((
                    "the cylinder's start and end are the same point".to_string(),
                    "its axis runs from `start` to `end`: give two different points",
                )),
                _ => None,
            };
            if let Some((message, hint)) = problem {
                self.err(Diagnostic::error("E0321", value.span, message).with_hint(hint));
                ok = false;
            }
        }
        let key = (self.in_prelude, value.span.start, value.span.end);
        let ty = if ok {
            Ty::Obj(Obj::Obstacle)
        } else {
            Ty::Error
        };
        self.hir.types.entry(key).or_insert_with(|| ty.clone());
        self.hir
            .types
            .entry((self.in_prelude, id.span.start, id.span.end))
            .or_insert(Ty::Error);
        Typed::of(ty, Var::Const)
    }

    /// `force(OBSTACLE)`: the total force (N, force[3]) the obstacle exerts on the bodies in
    /// contact with it, at the state the loss reads; `force(OBSTACLE, on: SET)` on the nodes of
    /// a node set only (one finger of a gripper).
    pub(super) fn check_contact_force(&mut self, e: &Expr, args: &[Arg]) -> Typed {
        let Some(s) = self.bind("force", e.span, &[("obstacle", true), ("on", false)], args) else {
            return Typed::error();
        };
        if let Some(on) = s[1]
            && !self.names_a(
                on,
                SymKind::Nodes,
                "`on:` takes the name of a node set, e.g. `force(table, on: left_finger)`",
                "`force(…, on: …)` takes a node set",
            )
        {
            return Typed::error();
        }
        let arg = s[0].expect("required");
        if !self.names_a(
            arg,
            SymKind::Obstacle,
            "`force` takes the name of an obstacle, e.g. `force(table)`",
            "`force` takes an obstacle",
        ) {
            return Typed::error();
        }
        if !self.in_loss_state(e, "`force(…)`", "the contact force") {
            return Typed::error();
        }
        let force = super::units::named_dim("force").expect("a dimension");
        Typed::of(Ty::vec3(force), Var::State)
    }

    /// Whether `call` stands where the loss's state is read (the loss, a top-level `let`);
    /// else E0320 for `what`, which is `quantity` at that state.
    fn in_loss_state(&mut self, call: &Expr, what: &str, quantity: &str) -> bool {
        if !self.ctx.loss_state {
            self.err(
                Diagnostic::error(
                    "E0320",
                    call.span,
                    format!(
                        "{what} cannot be used here: it is {quantity} at a state the loss reads"
                    ),
                )
                .with_hint("read it in the loss (or a top-level `let` the loss uses)"),
            );
        }
        self.ctx.loss_state
    }

    /// Whether `arg` names a declaration of kind `kind` (reporting `not_a_name` or
    /// `wrong_kind` otherwise, or nothing for an unknown name, which the name check reports).
    fn names_a(&mut self, arg: &Expr, kind: SymKind, not_a_name: &str, wrong_kind: &str) -> bool {
        let ExprKind::Name(id) = &arg.kind else {
            self.err(Diagnostic::error("E0203", arg.span, not_a_name));
            return false;
        };
        match self.global_kind(id) {
            Some(k) if k == kind => {
                self.check_expr(arg);
                true
            }
            Some(k) => {
                self.wrong_kind(id, k, wrong_kind, None);
                false
            }
            None => {
                self.check_expr(arg);
                false
            }
        }
    }

    /// `stretch(e)`: the largest principal stretch (dimensionless) of the element `e` of a
    /// reduction, at the state the loss reads.
    pub(super) fn check_stretch(&mut self, e: &Expr, args: &[Arg]) -> Typed {
        let Some(s) = self.bind("stretch", e.span, &[("element", true)], args) else {
            return Typed::error();
        };
        let arg = s[0].expect("required");
        let t = self.check_expr(arg);
        if t.ty.is_error() {
            return Typed::error();
        }
        if t.ty != Ty::Obj(Obj::Element) {
            let msg = format!(
                "`stretch` takes an element bound by a reduction, e.g. \
                 `max(e in walls) stretch(e)`, found {}",
                t.ty
            );
            self.err(Diagnostic::error("E0204", arg.span, msg));
            return Typed::error();
        }
        if !self.in_loss_state(e, "`stretch(…)`", "the deformation") {
            return Typed::error();
        }
        Typed::of(Ty::scalar(Dim::NONE), Var::State)
    }

    /// `contact BODY with OBSTACLE (gap: …, stiffness: …)`; `seen` the pairs already declared.
    pub(super) fn check_contact(
        &mut self,
        body: &Ident,
        obstacle: &Ident,
        args: &[Arg],
        span: crate::front::ast::Span,
        seen: &mut Vec<(String, String)>,
    ) {
        match self.global_kind(body) {
            Some(SymKind::Mesh | SymKind::Nodes) | None => {}
            Some(k) => self.wrong_kind(
                body,
                k,
                "`contact` takes the mesh or a node set (its surface nodes touch the obstacle)",
                None,
            ),
        }
        match self.global_kind(obstacle) {
            Some(SymKind::Obstacle) | None => {}
            Some(k) => self.wrong_kind(
                obstacle,
                k,
                "`contact … with` takes an obstacle",
                Some("declare it with `obstacle NAME = plane(point: …, normal: …)`"),
            ),
        }
        let pair = (body.name.clone(), obstacle.name.clone());
        if seen.contains(&pair) {
            let msg = format!(
                "the contact of `{}` with `{}` is declared twice",
                body.name, obstacle.name
            );
            self.err(Diagnostic::error("E0326", span, msg));
        }
        seen.push(pair);
        // `gap` is required, but reported here (with a hint), not by `bind`.
        let params = [("gap", false), ("stiffness", false), ("friction", false)];
        let Some(bound) = self.bind("contact", span, &params, args) else {
            return;
        };
        if bound[0].is_none() {
            self.err(
                Diagnostic::error(
                    "E0106",
                    span,
                    "`contact` needs its `gap`: the distance within which the barrier acts",
                )
                .with_hint(format!(
                    "e.g. `contact {} with {} (gap: 0.1 mm)`, a fraction of the smallest element",
                    body.name, obstacle.name
                )),
            );
        }
        let wants = [
            ("gap", Ty::scalar(Dim::LENGTH)),
            (
                "stiffness",
                Ty::scalar(super::units::named_dim("pressure").unwrap()),
            ),
        ];
        for ((pname, want), slot) in wants.iter().zip(&bound) {
            let Some(arg) = slot else { continue };
            let t = self.check_expr(arg);
            let what = format!("the contact's `{pname}`");
            if self.expect_type(&t, want, arg, &what)
                && self.expect_const(&t, arg, &what)
                && t.num().is_some_and(|v| v <= 0.0)
            {
                let msg = format!("{what} must be positive");
                self.err(Diagnostic::error("E0321", arg.span, msg));
            }
        }
        if let Some(friction) = bound[2] {
            let t = self.check_expr(friction);
            let what = "the contact's `friction` coefficient";
            if self.expect_type(&t, &Ty::scalar(Dim::NONE), friction, what)
                && self.expect_const(&t, friction, what)
            {
                if t.num().is_some_and(|v| v < 0.0) {
                    let msg = format!("{what} must not be negative");
                    self.err(Diagnostic::error("E0321", friction.span, msg));
                } else if let Some(integrator) =
                    self.sim.solves_state.filter(|&i| i == "quasi_static")
                {
                    self.err(
                        Diagnostic::error(
                            "E0326",
                            friction.span,
                            format!(
                                "friction in contact is supported in dynamic runs only \
                                 (`semi_implicit_euler`, `implicit_euler`), not with \
                                 `{integrator}`: a static solve keeps no slip history"
                            ),
                        )
                        .with_hint(
                            "remove `friction` (the obstacle then pushes along its normal \
                             only), or simulate the motion with `integrator = implicit_euler`",
                        ),
                    );
                }
            }
        }
    }
}
