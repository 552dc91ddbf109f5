//! softc as a library: a script compiled once and then run many times with other values of its
//! params and inputs — what the Python package (`python/`) calls. A run takes the same steps
//! through the engine as `softc run` does (the same device, the same stable-step estimate, the
//! same checks, the same JSON summary), so its numbers are bit-identical to the command line's
//! with the same settings; the kernels are compiled once per model and reused.

use crate::devices::{BackendChoice, Device, DeviceChoice, open};
use crate::engine::adjoint::{GradOptions, GradientReport};
use crate::engine::scene::{Scene, SceneError};
use crate::engine::statics::LinearSolver;
use crate::engine::{RunSummary, Simulation};
use crate::outputs::json::{adjoint_json, gradients_json, summary_json};
use softc_compiler::back::Precision;
use softc_compiler::driver::{CompileFailure, SlotKind};
use std::collections::BTreeMap;
use std::path::Path;

/// The device a model runs on (as `--backend`, `--precision`, `--adapter`, `--threads` and
/// `--linear-solver` of `softc run`).
#[derive(Clone, Debug)]
pub struct Settings {
    pub backend: BackendChoice,
    /// `None`: the script's `precision`, else the backend's default.
    pub precision: Option<Precision>,
    pub adapter: Option<String>,
    pub threads: Option<usize>,
    pub linear_solver: LinearSolver,
    /// Static solves start from the previous run's equilibrium (as an optimization in
    /// `softc run` does) instead of from rest: an optimization loop's solves then cost a few
    /// Newton iterations, but a run's result depends on the one before it to the solver's
    /// tolerance (not bit for bit `softc run`'s).
    pub warm_start: bool,
}

impl Default for Settings {
    fn default() -> Self {
        Settings {
            backend: BackendChoice::Cpu,
            precision: None,
            adapter: None,
            threads: None,
            linear_solver: LinearSolver::Auto,
            warm_start: false,
        }
    }
}

/// Why a model could not be made.
#[derive(Debug)]
pub enum LoadError {
    /// The script has errors: its diagnostics, with the text they point into.
    Compile(CompileFailure),
    /// Anything else (an unreadable file, a broken mesh, a device that does not open); the
    /// message is ready to print.
    Other(String),
}

impl std::fmt::Display for LoadError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            LoadError::Compile(c) => f.write_str(&c.render()),
            LoadError::Other(m) => f.write_str(m),
        }
    }
}

/// A param or input of the script as a caller sees it.
#[derive(Clone, Debug)]
pub struct Slot {
    pub name: String,
    /// `param`, `field` (one entry per element of a set) or `input`.
    pub kind: &'static str,
    /// Row-major shape (empty for a scalar; a field: its number of elements).
    pub shape: Vec<usize>,
    /// The SI unit of every entry (`Pa`, `1/m`).
    pub unit: String,
    pub lower: Option<f64>,
    pub upper: Option<f64>,
    /// The script's values (a plain run's first scene for an input), SI, row-major.
    pub initial: Vec<f64>,
    /// A field's element set.
    pub set: Option<String>,
}

/// Values for the params and inputs of one run, by name, in SI units, row-major: one value sets
/// every entry (as `--set w=…` does), else one per entry.
pub type Values = [(String, Vec<f64>)];

/// What a run asks for beyond the values: `--steps`, `--dt` (seconds), `--grad` with its
/// backward-pass settings, and whether the final state comes back.
#[derive(Clone, Debug, Default)]
pub struct Request {
    pub steps: Option<u64>,
    pub dt: Option<f64>,
    pub grad: Option<GradOptions>,
    pub keep_state: bool,
    /// Set from another thread to stop the run at its next check (the error is
    /// [`crate::engine::INTERRUPTED`]); the model stays usable.
    pub interrupt: Option<std::sync::Arc<std::sync::atomic::AtomicBool>>,
}

/// The outcome of a run.
#[derive(Clone, Debug)]
pub struct Outcome {
    /// The summary `softc run` prints (with `gradients` and `adjoint` after a backward pass;
    /// several scenes: the first one's, `loss` their mean and `scenes` each one's).
    pub json: serde_json::Value,
    pub loss: Option<f64>,
    /// d loss / d param for every param (its entries row-major, SI); several scenes: the mean of
    /// theirs, as the loss.
    pub gradients: Vec<(String, Vec<usize>, Vec<f64>)>,
    /// Final positions and velocities, 3 per node (the last scene's), when asked for.
    pub state: Option<(Vec<f64>, Vec<f64>)>,
}

/// A compiled script bound to its mesh and a device, ready to run with any param values.
pub struct Model {
    scene: Scene,
    settings: Settings,
    /// The script's values of params and inputs (`scene.uniforms` is reset to them per run).
    initial: BTreeMap<String, f64>,
    /// The devices, compiled on first use: forward kernels, and the adjoint module (a superset,
    /// which also runs forward passes of static solves and of runs with gradients).
    forward: Option<Device>,
    adjoint: Option<Device>,
    /// The last static solve's equilibrium, where [`Settings::warm_start`] asks for it.
    equilibrium: Option<Vec<f64>>,
}

impl std::fmt::Debug for Model {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Model")
            .field("script", &self.scene.script)
            .field("settings", &self.settings)
            .finish()
    }
}

impl Model {
    /// Compile a script through the one compiler driver and bind it to its mesh. The device
    /// opens at the first run.
    pub fn compile(path: &Path, settings: Settings) -> Result<Model, LoadError> {
        if settings.backend == BackendChoice::Reference {
            return Err(LoadError::Other(
                "the reference oracle is a test oracle, not a device: use backend \"cpu\", \
                 \"interp\" or \"gpu\""
                    .into(),
            ));
        }
        if settings.threads == Some(0) {
            return Err(LoadError::Other(
                "threads must be at least 1 (or left out: the backend's own choice)".into(),
            ));
        }
        let scene = Scene::load_checked(path, &[]).map_err(|e| match e {
            crate::engine::scene::LoadFailure::Compile(c) => LoadError::Compile(c),
            crate::engine::scene::LoadFailure::Other(SceneError(m)) => LoadError::Other(m),
        })?;
        Ok(Model {
            initial: scene.uniforms.clone(),
            scene,
            settings,
            forward: None,
            adjoint: None,
            equilibrium: None,
        })
    }

    pub fn scene(&self) -> &Scene {
        &self.scene
    }

    pub fn settings(&self) -> &Settings {
        &self.settings
    }

    /// The params (source order), then the inputs.
    pub fn slots(&self) -> Vec<Slot> {
        self.scene
            .slots
            .iter()
            .map(|s| Slot {
                name: s.name.clone(),
                kind: match s.kind {
                    SlotKind::Param => "param",
                    SlotKind::Field { .. } => "field",
                    SlotKind::Input => "input",
                },
                shape: s.shape.clone(),
                unit: self
                    .scene
                    .resolved
                    .value_dim(&s.name)
                    .map_or_else(|| "1".into(), |d| d.si_unit()),
                lower: s.lower,
                upper: s.upper,
                initial: s
                    .uniforms
                    .iter()
                    .map(|u| self.initial.get(u).copied().unwrap_or(f64::NAN))
                    .collect(),
                set: match &s.kind {
                    SlotKind::Field { set } => Some(set.clone()),
                    _ => None,
                },
            })
            .collect()
    }

    /// The uniforms a run's values set, checked: names the script declares, one value or one
    /// per entry, finite, within a param's bounds. Errors name the value and the fix.
    fn assignments(&self, values: &Values) -> Result<Vec<(String, f64)>, String> {
        let mut out = Vec::new();
        for (name, v) in values {
            let Some(slots) = self.scene.slots.iter().find(|s| &s.name == name) else {
                let known: Vec<&str> = self.scene.slots.iter().map(|s| s.name.as_str()).collect();
                return Err(format!(
                    "the script has no param or input `{name}` (it has: {})",
                    if known.is_empty() {
                        "none".to_string()
                    } else {
                        known.join(", ")
                    }
                ));
            };
            let n = slots.uniforms.len();
            if v.len() != 1 && v.len() != n {
                return Err(format!(
                    "`{name}` has shape {:?} ({n} entries); {} value(s) were given: give one \
                     value for every entry or one per entry (row-major)",
                    slots.shape,
                    v.len()
                ));
            }
            for (i, uniform) in slots.uniforms.iter().enumerate() {
                let x = if v.len() == 1 { v[0] } else { v[i] };
                let entry = uniform.split_once('.').map_or(uniform.as_str(), |(_, e)| e);
                let below = slots.lower.is_some_and(|lo| x < lo);
                let above = slots.upper.is_some_and(|hi| x > hi);
                if !x.is_finite() || below || above {
                    let bound =
                        |b: Option<f64>| b.map_or("unbounded".to_string(), |b| format!("{b:e}"));
                    return Err(format!(
                        "{entry} = {x:e} (SI) is {} for `{name}`: [{}, {}] (SI); give a finite \
                         value within them",
                        if x.is_finite() {
                            "outside the bounds the script declares"
                        } else {
                            "not a finite number, and the bounds are"
                        },
                        bound(slots.lower),
                        bound(slots.upper)
                    ));
                }
                out.push((uniform.clone(), x));
            }
        }
        Ok(out)
    }

    /// Run the script with `values` (others at the script's), as `softc run --no-optimize` with
    /// `--set` would (and `--grad` when the request has grad options). A script that lists
    /// several scenes of its inputs runs each of them unless the values set an input.
    pub fn run(&mut self, values: &Values, request: &Request) -> Result<Outcome, String> {
        let assigned = self.assignments(values)?;
        if let Some(steps) = request.steps
            && steps == 0
        {
            return Err("steps must be at least 1".into());
        }
        if let Some(dt) = request.dt
            && !(dt > 0.0 && dt.is_finite())
        {
            return Err(format!(
                "dt = {dt:e} s: the time step must be positive and finite"
            ));
        }
        let input_given = values.iter().any(|(n, _)| {
            self.scene
                .slots
                .iter()
                .any(|s| &s.name == n && s.kind == SlotKind::Input)
        });
        let scenes = if input_given {
            Vec::new()
        } else {
            crate::optim::plain_run_scenes(&self.scene)?
        };
        self.scene.uniforms = self.initial.clone();
        for (u, x) in &assigned {
            self.scene.uniforms.insert(u.clone(), *x);
        }
        if scenes.len() < 2 {
            let (summary, grad, backend) = self.run_one(request)?;
            return Ok(self.outcome(summary, grad, backend, request));
        }
        // Every scene of the script's inputs in turn, as `softc run` does on the cpu.
        let mut results = Vec::new();
        let mut outcomes = Vec::new();
        for assignment in &scenes {
            for (name, value) in assignment {
                self.scene.uniforms.insert(name.clone(), *value);
            }
            let (summary, grad, backend) = self.run_one(request)?;
            let o = self.outcome(summary, grad, backend, request);
            let mut json = o.json.clone();
            if let Some(obj) = json.as_object_mut() {
                obj.remove("adjoint");
            }
            json["inputs"] = assignment
                .iter()
                .map(|(n, v)| (n.trim_start_matches("input.").to_string(), (*v).into()))
                .collect::<serde_json::Map<_, _>>()
                .into();
            results.push(json);
            outcomes.push(o);
        }
        let json = crate::outputs::json::scenes_json(results);
        let mut first = outcomes[0].clone();
        first.loss = json["loss"].as_f64();
        let n = outcomes.len() as f64;
        for (k, (_, _, g)) in first.gradients.iter_mut().enumerate() {
            for (i, gi) in g.iter_mut().enumerate() {
                *gi = outcomes.iter().map(|o| o.gradients[k].2[i]).sum::<f64>() / n;
            }
        }
        first.json = json;
        first.state = outcomes.pop().and_then(|o| o.state);
        Ok(first)
    }

    /// One scene with `scene.uniforms` as set: the device compiled on first use, the same
    /// calls as `softc run`'s (stable-step estimate, time steps, step-count check, run).
    fn run_one(
        &mut self,
        request: &Request,
    ) -> Result<(RunSummary, Option<GradientReport>, &'static str), String> {
        let adjoint = request.grad.is_some() || self.scene.lowered.statics.is_some();
        let slot = if adjoint {
            &mut self.adjoint
        } else {
            &mut self.forward
        };
        let device = match slot.take() {
            Some(d) => d,
            None => {
                let module = if adjoint {
                    &self.scene.lowered.adjoint.module
                } else {
                    &self.scene.lowered.module
                };
                let choice = DeviceChoice {
                    backend: self.settings.backend,
                    precision: self.settings.precision,
                    adapter: self.settings.adapter.as_deref(),
                    threads: self.settings.threads,
                };
                open(&choice, &self.scene, module, 1)?.make()?
            }
        };
        let name = crate::devices::Backend::name(&device);
        let mut sim = Simulation::new(&self.scene, device);
        sim.linear_solver = self.settings.linear_solver;
        sim.interrupt = request.interrupt.clone();
        if self.settings.warm_start {
            sim.warm_start = self.equilibrium.clone();
        }
        let result = (|| {
            if self.scene.lowered.statics.is_none() {
                sim.stable_dt_estimate().map_err(|e| e.0)?;
            }
            crate::session::checked_time_steps(&mut sim, request.dt, request.steps)?;
            match &request.grad {
                Some(options) => {
                    let g = sim
                        .gradient(request.dt, request.steps, options)
                        .map_err(|e| e.0)?;
                    Ok((g.summary.clone(), Some(g)))
                }
                None => sim
                    .run(request.dt, request.steps)
                    .map(|s| (s, None))
                    .map_err(|e| e.0),
            }
        })();
        if self.settings.warm_start
            && let Some(x) = sim.warm_start.take()
        {
            self.equilibrium = Some(x);
        }
        // The device is kept for the next run, also after a failed one (`Simulation::new`
        // prepares its buffers afresh).
        let device = sim.backend;
        if adjoint {
            self.adjoint = Some(device);
        } else {
            self.forward = Some(device);
        }
        result.map(|(s, g)| (s, g, name))
    }

    fn outcome(
        &self,
        summary: RunSummary,
        grad: Option<GradientReport>,
        backend: &str,
        request: &Request,
    ) -> Outcome {
        let mut json = summary_json(&self.scene, &summary, backend);
        let mut gradients = Vec::new();
        if let Some(g) = &grad {
            json["gradients"] = gradients_json(&self.scene.slots, &g.gradients);
            json["adjoint"] = adjoint_json(g);
            for s in self
                .scene
                .slots
                .iter()
                .filter(|s| s.kind != SlotKind::Input)
            {
                let values = s
                    .uniforms
                    .iter()
                    .map(|u| g.gradients.get(u).copied().unwrap_or(0.0))
                    .collect();
                gradients.push((s.name.clone(), s.shape.clone(), values));
            }
        }
        let state = request.keep_state.then(|| {
            (
                summary.x.iter().flatten().copied().collect(),
                summary.v.iter().flatten().copied().collect(),
            )
        });
        Outcome {
            json,
            loss: summary.loss,
            gradients,
            state,
        }
    }
}
