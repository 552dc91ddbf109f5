//! The `sim` block's settings and the backward pass's settings, resolved to SI numbers, and the
//! mesh a script loads.

use super::const_scalar;
use crate::back::Precision;
use crate::lower::expr::Program;
use crate::sema::hir::{Callee, Expr, ExprKind, Name, StmtKind, arg};
use std::path::{Path, PathBuf};

/// How the time step is chosen.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum DtChoice {
    Given(f64),
    /// `dt = auto(safety: s)`: s × the estimated largest stable step.
    Auto {
        safety: f64,
    },
}

/// The element model of the sim block (`model = fem | springs(…)`).
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum ForceModelKind {
    Fem,
    /// A spring mesh with this volume stiffness (SI).
    Springs {
        volume_stiffness: f64,
    },
}

/// `output csv(SET) every …`: a node set's log.
#[derive(Debug, Clone, PartialEq)]
pub struct CsvLog {
    pub set: String,
    /// The interval: seconds, or steps when `in_steps`.
    pub every: f64,
    pub in_steps: bool,
}

/// The sim block, resolved.
#[derive(Debug, Clone)]
pub struct SimSettings {
    /// `semi_implicit_euler` steps, or `quasi_static` equilibrium states: then `dt` is the
    /// spacing of the states (`duration / steps`) and `steps` their number.
    pub integrator: Integrator,
    pub dt: DtChoice,
    pub steps: Option<u64>,
    /// The simulated duration in seconds, when the script fixes it.
    pub duration: Option<f64>,
    /// Inertia scaling (1 without the setting).
    pub mass_scaling: f64,
    /// `precision = f32|f64`.
    pub precision: Option<Precision>,
    pub model: ForceModelKind,
    /// `output vtk every N steps`.
    pub vtk_every: Option<u64>,
    pub csv: Vec<CsvLog>,
}

impl SimSettings {
    pub(super) fn resolve(program: &Program, duration: Option<f64>) -> Result<SimSettings, String> {
        let setting = |name: &str| {
            program
                .sim_setting(name)
                .map(|e| const_scalar(program, e))
                .transpose()
        };
        let integrator = match program
            .sim_setting("integrator")
            .and_then(Expr::implicit_name)
        {
            Some("quasi_static") => Integrator::QuasiStatic,
            Some("implicit_euler") => Integrator::ImplicitEuler,
            _ => Integrator::SemiImplicitEuler,
        };
        if integrator == Integrator::QuasiStatic {
            let steps = setting("steps")?.map(|s| s as u64).unwrap_or(1).max(1);
            let t_end = match (duration, program.sim_setting("dt")) {
                (Some(d), _) => d,
                (None, Some(dt)) => const_scalar(program, dt)? * steps as f64,
                (None, None) => return Err("a quasi-static sim block needs `duration`".into()),
            };
            return Ok(SimSettings {
                integrator,
                dt: DtChoice::Given(t_end / steps as f64),
                steps: Some(steps),
                duration: Some(t_end),
                mass_scaling: 1.0,
                ..Self::outputs_and_model(program)?
            });
        }
        let dt = match program.sim_setting("dt") {
            None => return Err("the sim block has no `dt`".into()),
            Some(e) => match e.builtin_call() {
                Some(("auto", [])) => DtChoice::Auto { safety: 0.9 },
                Some(("auto", args)) => DtChoice::Auto {
                    safety: const_scalar(program, &args[0].value)?,
                },
                _ => DtChoice::Given(const_scalar(program, e)?),
            },
        };
        let steps = setting("steps")?.map(|s| s as u64);
        let mass_scaling = setting("mass_scaling")?.unwrap_or(1.0);
        Ok(SimSettings {
            integrator,
            dt,
            steps,
            duration,
            mass_scaling,
            ..Self::outputs_and_model(program)?
        })
    }

    /// The settings both integrators read: precision, force model, outputs.
    fn outputs_and_model(program: &Program) -> Result<SimSettings, String> {
        let precision = match program
            .sim_setting("precision")
            .and_then(Expr::implicit_name)
        {
            Some("f64") => Some(Precision::F64),
            Some("f32") => Some(Precision::F32),
            _ => None,
        };
        let model = match program.sim_setting("model").map(|e| &e.kind) {
            Some(ExprKind::Call { args, .. }) => {
                let alpha = arg(args, "volume_stiffness", 0)
                    .map(|a| const_scalar(program, a))
                    .transpose()?
                    .unwrap_or(0.0);
                ForceModelKind::Springs {
                    volume_stiffness: alpha,
                }
            }
            _ => ForceModelKind::Fem,
        };
        let mut vtk_every = None;
        let mut csv = Vec::new();
        for stmt in &program.sim {
            let StmtKind::Output { what, every, steps } = &stmt.kind else {
                continue;
            };
            match &what.kind {
                ExprKind::Name(n)
                    if n.implicit() == Some("vtk") && *steps && vtk_every.is_none() =>
                {
                    // A count of steps has no unit: its number is as written.
                    if let ExprKind::Num(value) = &every.kind {
                        vtk_every = Some(*value as u64);
                    }
                }
                ExprKind::Call {
                    callee: Callee::Builtin(f),
                    args,
                } if f == "csv" => {
                    let Some(ExprKind::Name(Name::Global(set))) =
                        args.first().map(|a| &a.value.kind)
                    else {
                        continue;
                    };
                    csv.push(CsvLog {
                        set: program.decl(*set).name.clone(),
                        every: const_scalar(program, every)?,
                        in_steps: *steps,
                    });
                }
                _ => {}
            }
        }
        Ok(SimSettings {
            integrator: Integrator::SemiImplicitEuler,
            dt: DtChoice::Given(f64::NAN),
            steps: None,
            duration: None,
            mass_scaling: 1.0,
            precision,
            model,
            vtk_every,
            csv,
        })
    }

    /// The number of steps for a time step `dt`.
    pub fn steps_for(&self, dt: f64) -> u64 {
        match (self.steps, self.duration) {
            (Some(n), _) => n,
            (None, Some(d)) => (d / dt - 1e-9).ceil().max(1.0) as u64,
            _ => 1,
        }
    }
}

/// How a run advances.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum Integrator {
    /// Explicit time steps (thesis eq. 2.2).
    #[default]
    SemiImplicitEuler,
    /// Equilibrium states found by Newton's method on the assembled tangent.
    QuasiStatic,
    /// Backward Euler: one Newton solve on M/dt² + K per step.
    ImplicitEuler,
}

/// The optimize block's `checkpoint` setting.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum CheckpointSpec {
    Auto,
    StoreAll,
    Periodic(u64),
    Revolve(usize),
}

/// The backward pass's settings from the optimize block (the CLI may override them).
#[derive(Debug, Clone, Default, PartialEq)]
pub struct GradSettings {
    pub checkpoint: Option<CheckpointSpec>,
    /// Bytes.
    pub memory_budget: Option<u64>,
    /// Steps.
    pub truncate: Option<u64>,
}

impl GradSettings {
    pub(super) fn resolve(program: &Program) -> Result<GradSettings, String> {
        let constant = |e: &Expr| const_scalar(program, e);
        let mut o = GradSettings::default();
        if let Some(e) = program.optimize_setting("checkpoint") {
            o.checkpoint = Some(match &e.kind {
                ExprKind::Name(n) if n.implicit() == Some("store_all") => CheckpointSpec::StoreAll,
                ExprKind::Call { callee, args } => {
                    let k = args
                        .first()
                        .map(|a| constant(&a.value))
                        .transpose()?
                        .unwrap_or(1.0)
                        .max(1.0) as u64;
                    match callee {
                        Callee::Builtin(n) if n == "periodic" => CheckpointSpec::Periodic(k),
                        _ => CheckpointSpec::Revolve(k as usize),
                    }
                }
                _ => CheckpointSpec::Auto,
            });
        }
        if let Some(e) = program.optimize_setting("memory_budget") {
            o.memory_budget = Some(constant(e)? as u64);
        }
        if let Some(e) = program.optimize_setting("truncate") {
            o.truncate = Some(constant(e)?.max(1.0) as u64);
        }
        Ok(o)
    }
}

/// The script's `mesh … = load("FILE", unit: …)`, or `mesh_override` in its place.
pub(super) fn mesh_decl(program: &Program, base: &Path) -> Result<super::MeshDecl, String> {
    let value = program.mesh().ok_or("the script declares no mesh")?;
    let ExprKind::Call { args, .. } = &value.kind else {
        return Err("the mesh is not loaded".into());
    };
    let path_arg = arg(args, "path", 0);
    let (written, span) = match path_arg.map(|e| (&e.kind, e.span)) {
        Some((ExprKind::Str(s), span)) => (PathBuf::from(s), Some((span.start, span.end))),
        _ => return Err("the mesh path is not a string".into()),
    };
    let unit = match arg(args, "unit", 1) {
        Some(u) => const_scalar(program, u)?,
        None => 1e-3,
    };
    Ok(super::MeshDecl {
        path: base.join(&written),
        written,
        unit,
        order: crate::lower::scene::element_order(program),
        span,
    })
}
