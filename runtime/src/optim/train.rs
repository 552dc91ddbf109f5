//! The training loop: every iteration sets the params from the unconstrained values, runs the
//! forward and backward pass of each scene of the batch (in parallel, one simulation each), averages
//! loss and gradient in scene order, normalizes, clips and updates.
//!
//! Everything an iteration depends on is in [`TrainState`] — the unconstrained values, the
//! optimizer's moments, the time step and the history — and the scenes are drawn from
//! (seed, iteration), so a run resumed from a saved state continues bit for bit as if it had
//! never stopped.

use super::batch;
use super::method::{self, MethodState};
use super::{Entry, Plan};
use crate::devices::Backend;
use crate::engine::adjoint::GradOptions;
use crate::engine::{RunError, RunSummary, Simulation};
use serde::{Deserialize, Serialize};
use softc_compiler::ir::UniformId;
use std::collections::BTreeMap;

/// A JSON object of numbers in which no key appears twice (serde would keep the last of two
/// values silently: issue 20 item 8).
fn unique_keys<'de, D: serde::Deserializer<'de>>(d: D) -> Result<BTreeMap<String, f64>, D::Error> {
    struct Unique;
    impl<'de> serde::de::Visitor<'de> for Unique {
        type Value = BTreeMap<String, f64>;
        fn expecting(&self, f: &mut std::fmt::Formatter) -> std::fmt::Result {
            f.write_str("an object of numbers")
        }
        fn visit_map<A: serde::de::MapAccess<'de>>(
            self,
            mut a: A,
        ) -> Result<Self::Value, A::Error> {
            let mut out = BTreeMap::new();
            while let Some((k, v)) = a.next_entry::<String, f64>()? {
                if out.contains_key(&k) {
                    return Err(serde::de::Error::custom(format!("`{k}` is given twice")));
                }
                out.insert(k, v);
            }
            Ok(out)
        }
    }
    d.deserialize_map(Unique)
}

/// The loss of one scene of an iteration.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct SceneRecord {
    /// The input values of the scene (`input.target.1` → metres).
    #[serde(deserialize_with = "unique_keys")]
    pub inputs: BTreeMap<String, f64>,
    pub loss: f64,
}

/// One iteration, as the history keeps it.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Record {
    pub iteration: u64,
    /// The batch's mean loss at `params`.
    pub loss: f64,
    /// The trained entries' values this iteration ran with (SI).
    #[serde(deserialize_with = "unique_keys")]
    pub params: BTreeMap<String, f64>,
    /// d loss / d param (SI), the batch mean.
    #[serde(deserialize_with = "unique_keys")]
    pub gradient: BTreeMap<String, f64>,
    /// The step direction the optimizer received: d loss / d u after normalization and clipping.
    pub scaled_gradient: Vec<f64>,
    /// Norm of the normalized gradient with respect to u, before clipping (`grad_norm`).
    pub grad_norm: f64,
    pub lr: f64,
    pub scenes: Vec<SceneRecord>,
    pub seconds: f64,
}

/// Why a run ended.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub enum Stopped {
    /// All `for N iterations` ran.
    Iterations,
    /// `stop when` held at this iteration (its params are the result).
    Condition { iteration: u64 },
}

/// Everything needed to continue a run.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct TrainState {
    pub format: u32,
    /// Identifies the script and settings the state belongs to, then (after `/`) the mesh.
    pub fingerprint: String,
    /// The trained uniforms, in order.
    pub entries: Vec<String>,
    pub dt: f64,
    pub steps: u64,
    /// Iterations completed.
    pub iteration: u64,
    /// Unconstrained values for the next iteration.
    pub u: Vec<f64>,
    pub method: MethodState,
    pub history: Vec<Record>,
    pub stopped: Option<Stopped>,
    /// The command line's settings the run was made with (`--backend cpu`, …), so a resume
    /// with other settings is told which one differs (absent from older states).
    #[serde(default, skip_serializing_if = "BTreeMap::is_empty")]
    pub settings: BTreeMap<String, String>,
    /// Quasi-static scenes: each simulation's last equilibrium (node positions, m), where its
    /// next solve starts; a resumed run restores them to continue bit for bit.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub warm_starts: Vec<Vec<f64>>,
}

pub const STATE_FORMAT: u32 = 1;

/// Check a saved state for internal consistency before a run continues from it (issue 20
/// item 8): every vector has one value per trained entry, values are finite, second moments
/// are not negative, the iteration count matches the history, and the time step is the one the
/// script gives (`dt`, `steps`: what a fresh run computes). The message names the field.
pub fn check_state(s: &TrainState, dt: f64, steps: u64) -> Result<(), String> {
    let n = s.entries.len();
    let mut seen = std::collections::BTreeSet::new();
    if let Some(dup) = s.entries.iter().find(|e| !seen.insert(e.as_str())) {
        return Err(format!("`entries` lists `{dup}` twice"));
    }
    let finite = |name: &str, v: &[f64]| -> Result<(), String> {
        if v.len() != n {
            return Err(format!(
                "`{name}` has {} values for {n} trained entries",
                v.len()
            ));
        }
        match v.iter().position(|x| !x.is_finite()) {
            Some(i) => Err(format!("`{name}[{i}]` is {}", v[i])),
            None => Ok(()),
        }
    };
    finite("u", &s.u)?;
    let m = &s.method;
    finite("method.m", &m.m)?;
    finite("method.v", &m.v)?;
    finite("method.mean_abs_g", &m.mean_abs_g)?;
    if let Some(i) = m.v.iter().position(|&x| x < 0.0) {
        return Err(format!(
            "`method.v[{i}]` (a second moment, a mean of squares) is {} < 0",
            m.v[i]
        ));
    }
    if let Some(i) = m.mean_abs_g.iter().position(|&x| x < 0.0) {
        return Err(format!(
            "`method.mean_abs_g[{i}]` is {} < 0",
            m.mean_abs_g[i]
        ));
    }
    if m.z_g.len() != n {
        return Err(format!(
            "`method.z_g` has {} values for {n} trained entries",
            m.z_g.len()
        ));
    }
    if let Some(i) = m
        .z_g
        .iter()
        .position(|z| z.is_some_and(|z| !(z.is_finite() && z > 0.0)))
    {
        return Err(format!(
            "`method.z_g[{i}]` is {:?}, not a positive number",
            m.z_g[i]
        ));
    }
    if !(m.mean_weight.is_finite() && m.mean_weight >= 0.0) {
        return Err(format!("`method.mean_weight` is {}", m.mean_weight));
    }
    if m.step > s.iteration {
        return Err(format!(
            "`method.step` ({}) counts more updates than `iteration` ({})",
            m.step, s.iteration
        ));
    }
    if s.history.len() as u64 != s.iteration {
        return Err(format!(
            "`iteration` is {} but `history` holds {} iterations",
            s.iteration,
            s.history.len()
        ));
    }
    let keys: std::collections::BTreeSet<&str> = s.entries.iter().map(String::as_str).collect();
    for (i, r) in s.history.iter().enumerate() {
        if r.iteration != i as u64 {
            return Err(format!("`history[{i}].iteration` is {}", r.iteration));
        }
        if !r.loss.is_finite() {
            return Err(format!("`history[{i}].loss` is {}", r.loss));
        }
        for (what, map) in [("params", &r.params), ("gradient", &r.gradient)] {
            let k: std::collections::BTreeSet<&str> = map.keys().map(String::as_str).collect();
            if k != keys {
                return Err(format!(
                    "`history[{i}].{what}` names {k:?}, not the trained entries {keys:?}"
                ));
            }
            if let Some((name, v)) = map.iter().find(|(_, v)| !v.is_finite()) {
                return Err(format!("`history[{i}].{what}.{name}` is {v}"));
            }
        }
    }
    if let Some(Stopped::Condition { iteration }) = s.stopped
        && iteration + 1 != s.iteration
    {
        return Err(format!(
            "`stopped` names iteration {iteration}, but the history ends at {}",
            s.iteration.saturating_sub(1)
        ));
    }
    if s.dt.to_bits() != dt.to_bits() || s.steps != steps {
        return Err(format!(
            "`dt` = {:e} s and `steps` = {} differ from the script's {dt:e} s and {steps} (with \
             this --dt/--steps); a saved state cannot change the time step",
            s.dt, s.steps
        ));
    }
    Ok(())
}

pub struct Trainer<'s, B: Backend> {
    pub plan: Plan,
    sims: Vec<Simulation<'s, B>>,
    grad: GradOptions,
    pub state: TrainState,
    /// Each entry's natural size in u (for `normalize = auto`).
    natural: Vec<f64>,
    /// Per simulation, the uniform of each trained entry (resolved once: an iteration sets
    /// the params by id).
    entry_ids: Vec<Vec<UniformId>>,
}

/// The unconstrained value of every entry from the scene's (initial or `--set`) values.
fn initial_u(entries: &[Entry], uniforms: &BTreeMap<String, f64>) -> Result<Vec<f64>, String> {
    entries
        .iter()
        .map(|e| {
            let p = uniforms[&e.uniform];
            e.bounds.to_unconstrained(p).map_err(|m| {
                format!(
                    "param `{}`: {m} (SI units); a trained param must start strictly inside \
                     its bounds: change its initial value, or the value --set/--params give it",
                    e.uniform.trim_start_matches("param.")
                )
            })
        })
        .collect()
}

impl<'s, B: Backend + Send> Trainer<'s, B> {
    /// Bind the plan to one simulation per scene of a batch. `resume` continues a saved state
    /// (checked against `fingerprint`).
    pub fn new(
        plan: Plan,
        mut sims: Vec<Simulation<'s, B>>,
        grad: GradOptions,
        dt_override: Option<f64>,
        steps_override: Option<u64>,
        fingerprint: String,
        resume: Option<TrainState>,
    ) -> Result<Self, RunError> {
        let first = sims
            .first_mut()
            .ok_or_else(|| RunError("no simulation to train".into()))?;
        let scene = first.scene;
        let u0 = initial_u(&plan.entries, &scene.uniforms).map_err(RunError)?;
        let natural = plan
            .entries
            .iter()
            .zip(&u0)
            .map(|(e, u)| match e.bounds {
                super::transform::Bounds::Free => u.abs(),
                _ => 1.0,
            })
            .collect();
        let entries: Vec<String> = plan.entries.iter().map(|e| e.uniform.clone()).collect();
        let state = match resume {
            Some(s) => {
                if s.format != STATE_FORMAT {
                    return Err(RunError(format!(
                        "the saved state has format {}, this softc writes {STATE_FORMAT}; start afresh",
                        s.format
                    )));
                }
                // `SCRIPT/MESH`: a changed mesh alone gets a message of its own.
                let script_part = |f: &str| f.split('/').next().unwrap_or("").to_string();
                if !s.fingerprint.contains('/') {
                    return Err(RunError(
                        "the saved state does not record its mesh (an older softc wrote it); \
                         run without --resume to start afresh"
                            .into(),
                    ));
                }
                if s.entries == entries
                    && script_part(&s.fingerprint) == script_part(&fingerprint)
                    && s.fingerprint != fingerprint
                {
                    return Err(RunError(format!(
                        "the saved state was made with a different mesh: `{}` changed since \
                         (positions, elements, tags or sets); run without --resume to start \
                         afresh, or restore the mesh file",
                        scene.resolved.mesh.path.display()
                    )));
                }
                if s.fingerprint != fingerprint || s.entries != entries {
                    return Err(RunError(
                        "the saved state belongs to a different script or different settings \
                         (script text, --set, --params, --dt, --steps or the optimize block changed); \
                         run without --resume to start afresh, or restore the script"
                            .into(),
                    ));
                }
                let (dt, steps) = first.time_steps(dt_override, steps_override)?;
                check_state(&s, dt, steps)
                    .map_err(|e| RunError(format!("the saved state is inconsistent: {e}")))?;
                let mut s = s;
                // `--iterations` may extend a finished run, or end an unfinished one early.
                if s.stopped == Some(Stopped::Iterations) && s.iteration < plan.iterations {
                    s.stopped = None;
                }
                if s.stopped.is_none() && s.iteration >= plan.iterations {
                    s.stopped = Some(Stopped::Iterations);
                }
                s
            }
            None => {
                // The time step is fixed by the initial params for the whole run, so the loss
                // stays a smooth function of the params (a changing dt would change the number
                // of steps).
                let (dt, steps) = first.time_steps(dt_override, steps_override)?;
                TrainState {
                    format: STATE_FORMAT,
                    fingerprint,
                    entries,
                    dt,
                    steps,
                    iteration: 0,
                    method: MethodState::new(u0.len()),
                    u: u0,
                    history: Vec::new(),
                    stopped: None,
                    settings: BTreeMap::new(),
                    warm_starts: Vec::new(),
                }
            }
        };
        // One starting state per scene of the batch, or none (issue 31 item 11).
        if !state.warm_starts.is_empty() && state.warm_starts.len() != sims.len() {
            return Err(RunError(format!(
                "the saved state is inconsistent: `warm_starts` holds {} starting states (one \
                 per scene), but the batch has {} scene(s); run without --resume to start afresh",
                state.warm_starts.len(),
                sims.len()
            )));
        }
        for (i, (sim, w)) in sims.iter_mut().zip(&state.warm_starts).enumerate() {
            if w.is_empty() {
                continue;
            }
            let want = 3 * sim.scene.mesh.nodes.len();
            if w.len() != want || w.iter().any(|v| !v.is_finite()) {
                return Err(RunError(format!(
                    "the saved state is inconsistent: `warm_starts[{i}]` holds {} values (finite: \
                     {}), not the {want} positions of the mesh's nodes; run without --resume to \
                     start afresh",
                    w.len(),
                    w.iter().all(|v| v.is_finite())
                )));
            }
            sim.warm_start = Some(w.clone());
        }
        let entry_ids = sims
            .iter_mut()
            .map(|sim| {
                plan.entries
                    .iter()
                    .map(|e| sim.uniforms.intern(&e.uniform))
                    .collect()
            })
            .collect();
        Ok(Trainer {
            plan,
            sims,
            grad,
            state,
            natural,
            entry_ids,
        })
    }

    pub fn finished(&self) -> bool {
        self.state.stopped.is_some()
    }

    /// The trained entries' values for unconstrained values `u`.
    pub fn params_of(&self, u: &[f64]) -> BTreeMap<String, f64> {
        self.plan
            .entries
            .iter()
            .zip(u)
            .map(|(e, &u)| (e.uniform.clone(), e.bounds.to_param(u)))
            .collect()
    }

    /// The current values of the trained entries.
    pub fn params(&self) -> BTreeMap<String, f64> {
        self.params_of(&self.state.u)
    }

    fn set_params(&mut self) {
        let values: Vec<f64> = self
            .plan
            .entries
            .iter()
            .zip(&self.state.u)
            .map(|(e, &u)| e.bounds.to_param(u))
            .collect();
        for (sim, ids) in self.sims.iter_mut().zip(&self.entry_ids) {
            for (&id, &v) in ids.iter().zip(&values) {
                sim.uniforms.set(id, v);
            }
        }
    }

    /// The input values of scene `index` of iteration `iteration`.
    fn scene_inputs(&self, iteration: u64, index: usize) -> BTreeMap<String, f64> {
        let mut out = BTreeMap::new();
        for input in &self.plan.inputs {
            for (name, v) in input.uniforms.iter().zip(input.value(iteration, index)) {
                out.insert(name.clone(), v);
            }
        }
        out
    }

    /// One iteration: loss and gradient over the batch, then the update (unless `stop when`
    /// holds). Returns the record it appended to the history.
    pub fn step(&mut self) -> Result<&Record, RunError> {
        let start = std::time::Instant::now();
        let it = self.state.iteration;
        self.set_params();
        let params = self.params();
        let shuffle = !matches!(self.plan.method, super::method::Method::Gd);
        let members: Vec<usize> = if self.plan.inputs.is_empty() {
            vec![0]
        } else {
            batch::members(
                self.plan.scenes,
                self.plan.batch,
                it,
                self.plan.seed,
                shuffle,
            )
        };
        let assignments: Vec<BTreeMap<String, f64>> =
            members.iter().map(|&m| self.scene_inputs(it, m)).collect();
        let (dt, steps) = (self.state.dt, self.state.steps);
        let grad = &self.grad;
        // Each scene on its own thread and simulation (a batch backend's scenes in lockstep);
        // results are combined in scene order.
        let n_scenes = assignments.len().min(self.sims.len());
        let results = crate::engine::in_lockstep(&mut self.sims[..n_scenes], |i, sim| {
            for (k, v) in &assignments[i] {
                sim.uniforms.set_named(k, *v);
            }
            sim.reset();
            sim.gradient(Some(dt), Some(steps), grad)
        });
        // Where each simulation's next static solve starts, saved with the state.
        if self.sims.iter().any(|s| s.warm_start.is_some()) {
            self.state.warm_starts = self
                .sims
                .iter()
                .map(|s| s.warm_start.clone().unwrap_or_default())
                .collect();
        }
        let n = results.len() as f64;
        let mut loss = 0.0;
        let mut gradient: BTreeMap<String, f64> = self
            .plan
            .entries
            .iter()
            .map(|e| (e.uniform.clone(), 0.0))
            .collect();
        let mut scenes = Vec::new();
        for (r, inputs) in results.into_iter().zip(assignments) {
            let report = r.map_err(|e| {
                let scene = if inputs.is_empty() {
                    String::new()
                } else {
                    format!(", scene {}", listed(&inputs))
                };
                RunError(format!("{}{scene}: {e}", self.failing(it, &params)))
            })?;
            let l = report.summary.loss.unwrap_or(f64::NAN);
            loss += l / n;
            for (k, g) in gradient.iter_mut() {
                *g += report.gradients.get(k).copied().unwrap_or(0.0) / n;
            }
            scenes.push(SceneRecord { inputs, loss: l });
        }
        if !loss.is_finite() {
            return Err(RunError(format!(
                "{}: the loss is {loss}",
                self.failing(it, &params)
            )));
        }
        if let Some((k, g)) = gradient.iter().find(|(_, g)| !g.is_finite()) {
            return Err(RunError(format!(
                "{}: d loss/d {} is {g}; try `gradient_scale`, `truncate` or `clip` in the \
                 optimize block",
                self.failing(it, &params),
                k.trim_start_matches("param.")
            )));
        }
        // Chain rule to the unconstrained values, then normalization and clipping.
        let g_u: Vec<f64> = self
            .plan
            .entries
            .iter()
            .zip(&self.state.u)
            .map(|(e, &u)| gradient[&e.uniform] * e.bounds.dp_du(u))
            .collect();
        let mut scaled = method::normalize(
            self.plan.normalize,
            &mut self.state.method,
            &g_u,
            &self.state.u,
            &self.natural,
        );
        let grad_norm = method::clip(&mut scaled, self.plan.clip);
        let lr = self
            .plan
            .schedule
            .at(self.plan.lr, it, self.plan.iterations);
        let first = &self.sims[0];
        let stop = self
            .plan
            .should_stop(first.scene, loss, grad_norm, it)
            .map_err(RunError)?;
        if stop {
            self.state.stopped = Some(Stopped::Condition { iteration: it });
        } else {
            method::update(
                self.plan.method,
                &mut self.state.method,
                &mut self.state.u,
                &scaled,
                lr,
            );
            // A non-finite value must not be saved over the last good state (JSON writes it
            // as `null`): stop before the state is written.
            if let Some(k) = self.state.u.iter().position(|u| !u.is_finite()) {
                return Err(RunError(format!(
                    "{}: the update made `{}` non-finite — lower the learning rate or clip the \
                     gradient",
                    self.failing(it, &params),
                    self.plan.entries[k].uniform.trim_start_matches("param.")
                )));
            }
        }
        self.state.iteration += 1;
        if !stop && self.state.iteration >= self.plan.iterations {
            self.state.stopped = Some(Stopped::Iterations);
        }
        self.state.history.push(Record {
            iteration: it,
            loss,
            params,
            gradient,
            scaled_gradient: scaled,
            grad_norm,
            lr,
            scenes,
            seconds: start.elapsed().as_secs_f64(),
        });
        Ok(self.state.history.last().expect("just pushed"))
    }

    /// How an error names the iteration `it` (0-based) that failed: its number as the progress
    /// log prints it and the param values it ran with, so the failure can be reproduced.
    fn failing(&self, it: u64, params: &BTreeMap<String, f64>) -> String {
        format!(
            "iteration {}/{} failed with {}",
            it + 1,
            self.plan.iterations,
            listed(params)
        )
    }

    /// The params the run ends with: those of the stopping iteration, else the last update.
    pub fn result(&self) -> BTreeMap<String, f64> {
        match &self.state.stopped {
            Some(Stopped::Condition { .. }) => self
                .state
                .history
                .last()
                .map(|r| r.params.clone())
                .unwrap_or_else(|| self.params()),
            _ => self.params(),
        }
    }

    /// A forward run of the first simulation with the resulting params and the given inputs
    /// (the scene's own when empty).
    pub fn forward(
        &mut self,
        inputs: &BTreeMap<String, f64>,
        vtk: Option<Box<dyn crate::engine::StateSeries>>,
        csv: Vec<Box<dyn crate::engine::NodeSetLog>>,
    ) -> Result<RunSummary, RunError> {
        let params = self.result();
        let (dt, steps) = (self.state.dt, self.state.steps);
        let sim = &mut self.sims[0];
        for (k, v) in params.iter().chain(inputs) {
            sim.uniforms.set_named(k, *v);
        }
        sim.reset();
        sim.vtk = vtk;
        sim.csv = csv;
        let r = sim.run(Some(dt), Some(steps));
        sim.vtk = None;
        sim.csv = Vec::new();
        r
    }

    /// The loss on every held-out value of `validate` with the resulting params.
    pub fn validate(&mut self) -> Result<Vec<SceneRecord>, RunError> {
        let Some((index, values)) = self.plan.validate.clone() else {
            return Ok(Vec::new());
        };
        let names = self.plan.inputs[index].uniforms.clone();
        let mut out = Vec::new();
        for v in values {
            let inputs: BTreeMap<String, f64> = names.iter().cloned().zip(v).collect();
            let s = self.forward(&inputs, None, Vec::new())?;
            out.push(SceneRecord {
                inputs,
                loss: s.loss.unwrap_or(f64::NAN),
            });
        }
        Ok(out)
    }
}

/// `a = 1.5e3, b = 2e0, …` for an error message: the first few values of a map of uniforms
/// (a controller may train hundreds), the rest counted.
fn listed(values: &BTreeMap<String, f64>) -> String {
    const SHOWN: usize = 6;
    let mut parts: Vec<String> = values
        .iter()
        .take(SHOWN)
        .map(|(k, v)| format!("{} = {v:e}", k.trim_start_matches("param.")))
        .collect();
    if values.len() > SHOWN {
        parts.push(format!("and {} more", values.len() - SHOWN));
    }
    parts.join(", ")
}
