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

/// The loss of one scene of an iteration.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct SceneRecord {
    /// The input values of the scene (`input.target.1` → metres).
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
    pub params: BTreeMap<String, f64>,
    /// d loss / d param (SI), the batch mean.
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
}

pub const STATE_FORMAT: u32 = 1;

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
                    "param `{}`: {m}; a trained param must start strictly inside its bounds",
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
                        "the saved state does not record its mesh (an older softc wrote it);                          run without --resume to start afresh"
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
                }
            }
        };
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
                RunError(format!(
                    "iteration {it}{}: {e}",
                    if inputs.is_empty() {
                        String::new()
                    } else {
                        format!(" (scene {inputs:?})")
                    }
                ))
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
                "iteration {it}: the loss is {loss}; the params were {:?}",
                self.params()
            )));
        }
        if let Some((k, g)) = gradient.iter().find(|(_, g)| !g.is_finite()) {
            return Err(RunError(format!(
                "iteration {it}: d loss/d {} is {g}; try `gradient_scale`, `truncate` or `clip` \
                 in the optimize block",
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
        let params = self.params();
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
        vtk: Option<crate::outputs::vtk::VtkOutput>,
        csv: Vec<crate::outputs::csv::CsvOutput>,
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
