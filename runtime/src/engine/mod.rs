//! The time loop: a scene's kernels run step after step on a backend.
//!
//! State is double-buffered: the node kernel reads `x`, `v` and writes `x_next`, `v_next`,
//! which are swapped after the step, so no kernel ever reads a value overwritten in the same
//! step. Every few steps the engine checks the state: a non-finite position or an inverted
//! element (J ≤ 0) stops the run with the step, time, node or element and a suggested `dt`,
//! never with silent NaNs.

pub mod adjoint;
pub mod checkpoint;
pub mod contact;
pub mod implicit;
pub mod incompressibility;
pub mod loss;
mod matrix_free;
pub mod profile;
pub mod scene;
mod sensors;
pub mod sinks;
mod stable_dt;
pub mod statics;

// `softc::engine::Backend` and `softc::engine::Cpu`: paths from before the devices had a
// module of their own, still named in full by tests.
pub use crate::devices::Backend;
pub use crate::devices::cpu::Cpu;

use crate::devices::{Launch, Lockstep, Uniforms};
use crate::text::Sig;
use scene::{DtChoice, Scene};
pub use sinks::{Frame, NodeSetLog, ProgressReport, StateSeries};
use softc_compiler::back::Precision;
use softc_compiler::ir::{BufferId, UniformId};
use std::ops::Range;

/// The end (exclusive) of the stretch of steps from `from` before `limit` that ends at the
/// first step `j` after which the host has work (`due(j)`), or at `limit`.
fn stretch_end(from: u64, limit: u64, due: impl Fn(u64) -> bool) -> u64 {
    let mut j = from;
    while j + 1 < limit && !due(j) {
        j += 1;
    }
    j + 1
}

/// Run `work(i, sim)` for each simulation on a thread of its own, the backends in lockstep
/// ([`Backend::lockstep`]): every member joins before any starts and leaves when its work
/// ends. Results in simulation order; a thread that panicked gives an error.
pub fn in_lockstep<'s, B, T, W>(sims: &mut [Simulation<'s, B>], work: W) -> Vec<Result<T, RunError>>
where
    B: Backend + Send,
    T: Send,
    W: Fn(usize, &mut Simulation<'s, B>) -> Result<T, RunError> + Sync,
{
    let tokens: Vec<Lockstep> = sims.iter().map(|s| s.backend.lockstep()).collect();
    let work = &work;
    std::thread::scope(|s| {
        let handles: Vec<_> = sims
            .iter_mut()
            .zip(tokens)
            .enumerate()
            .map(|(i, (sim, token))| {
                s.spawn(move || {
                    let _member = token;
                    work(i, sim)
                })
            })
            .collect();
        handles
            .into_iter()
            .map(|h| {
                h.join()
                    .unwrap_or_else(|_| Err(RunError("a simulation thread panicked".into())))
            })
            .collect()
    })
}

/// Rest length of the six edges of every tet (spring mesh, `edge_l0`), in
/// `softc_compiler::driver::TET_EDGES` order.
fn edge_rest_lengths(scene: &Scene) -> Vec<f64> {
    let nodes = &scene.mesh.nodes;
    scene
        .mesh
        .tets
        .iter()
        .flat_map(|t| {
            softc_compiler::driver::TET_EDGES.map(|(a, b)| {
                let (p, q) = (nodes[t[a as usize] as usize], nodes[t[b as usize] as usize]);
                ((q[0] - p[0]).powi(2) + (q[1] - p[1]).powi(2) + (q[2] - p[2]).powi(2)).sqrt()
            })
        })
        .collect()
}

/// A failure during a run, with where and why.
#[derive(Debug)]
pub struct RunError(pub String);

impl std::fmt::Display for RunError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(&self.0)
    }
}

/// What a finished run reports.
#[derive(Debug, Clone)]
pub struct RunSummary {
    /// The script's loss for this run (`None` without a loss).
    pub loss: Option<f64>,
    pub steps: u64,
    pub dt: f64,
    pub dt_stable_estimate: Option<f64>,
    pub wall_seconds: f64,
    /// Final positions and velocities.
    pub x: Vec<[f64; 3]>,
    pub v: Vec<[f64; 3]>,
    /// What the equilibrium solver did (`integrator = quasi_static` only).
    pub solver: Option<statics::SolverReport>,
    /// Each `contact` statement's forces and distances at the final state.
    pub contact: Vec<contact::ContactReport>,
}

/// How much a run's final state still moves (issue 20 item 11: a run past a limit point ended
/// with a normal summary while its surface still moved 50 % in the last 5 ms).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Motion {
    /// ½ Σ m v² of the simulated system (masses as simulated, `mass_scaling` included), J.
    pub kinetic_energy: f64,
    /// The largest node speed, m/s, and its node (index).
    pub max_speed: f64,
    pub fastest: usize,
    /// The largest node displacement from the rest positions, m.
    pub max_displacement: f64,
}

/// A loss taken `at end` stands for a steady state; the state counts as still moving when, at
/// the final speed, the fastest node would move more than this fraction of the largest
/// displacement over the last tenth of the simulated time (the window the settling criterion
/// of `bench --tradeoff` averages over).
pub const STILL_MOVING: f64 = 0.01;

impl Motion {
    pub fn of(scene: &Scene, s: &RunSummary) -> Motion {
        let mut m = Motion {
            kinetic_energy: 0.0,
            max_speed: 0.0,
            fastest: 0,
            max_displacement: 0.0,
        };
        let norm = |a: [f64; 3]| (a[0] * a[0] + a[1] * a[1] + a[2] * a[2]).sqrt();
        for (i, (v, (x, x0))) in
            s.v.iter()
                .zip(s.x.iter().zip(&scene.mesh.nodes))
                .enumerate()
        {
            let speed = norm(*v);
            m.kinetic_energy += 0.5 * scene.pre.mass.get(i).copied().unwrap_or(0.0) * speed * speed;
            if speed > m.max_speed {
                m.max_speed = speed;
                m.fastest = i;
            }
            m.max_displacement =
                m.max_displacement
                    .max(norm([x[0] - x0[0], x[1] - x0[1], x[2] - x0[2]]));
        }
        m
    }

    /// The warning for a run whose loss is taken `at end` while the state still moves
    /// ([`STILL_MOVING`]), or `None`.
    pub fn still_moving(&self, scene: &Scene, s: &RunSummary) -> Option<String> {
        let t = s.steps as f64 * s.dt;
        let window = 0.1 * t;
        let moved = self.max_speed * window;
        // (`moved` may be NaN for a non-finite state: then nothing is claimed.)
        if moved.is_nan() || moved <= STILL_MOVING * self.max_displacement || t <= 0.0 {
            return None;
        }
        // Round-off chatter of positions at rest is not motion.
        let extent = scene
            .mesh
            .nodes
            .iter()
            .flatten()
            .fold(0.0f64, |a, c| a.max(c.abs()));
        if moved <= 64.0 * f64::EPSILON * extent {
            return None;
        }
        Some(format!(
            "warning: the loss is taken `at end` (a steady state), but the final state still \
             moves: node {} at {:.3e} m/s would move {:.3e} m over the last tenth of the run \
             ({window:.3e} s), {:.1} % of the largest displacement {:.3e} m (kinetic energy \
             {:.3e} J). Run longer (duration/steps), add damping, or lower the load — past a \
             limit point nothing settles",
            scene.mesh.node_id(self.fastest),
            self.max_speed,
            moved,
            100.0 * moved / self.max_displacement.max(f64::MIN_POSITIVE),
            self.max_displacement,
            self.kinetic_energy
        ))
    }
}

/// `x` rounded down to two significant digits (a safety factor that stays on the safe side).
fn two_digits_down(x: f64) -> f64 {
    let inverse_scale = 10f64.powf(1.0 - x.log10().floor());
    (x * inverse_scale).floor() / inverse_scale
}

/// A run to a steady state ([`Simulation::run_to_steady_state`]).
#[derive(Debug, Clone)]
pub struct SteadyRun {
    pub summary: RunSummary,
    /// Whether the settling criterion was met before the step limit.
    pub settled: bool,
}

/// A scene bound to a backend: buffers allocated and initialised.
pub struct Simulation<'s, B: Backend> {
    pub scene: &'s Scene,
    pub backend: B,
    pub uniforms: Uniforms,
    /// Write a series of states (ParaView) while running.
    pub vtk: Option<Box<dyn StateSeries>>,
    /// Node-set logs (`output csv(SET)`) written by `run`.
    pub csv: Vec<Box<dyn NodeSetLog>>,
    /// Progress of a long run (`softc run`: on stderr), updated at the host's checks.
    pub progress: Option<Box<dyn ProgressReport>>,
    /// Set from another thread to stop the run at its next check ([`INTERRUPTED`]): the
    /// Python package's Ctrl-C, while the run holds no GIL.
    pub interrupt: Option<std::sync::Arc<std::sync::atomic::AtomicBool>>,
    /// The stable-step estimate, once computed (reused by `run`).
    estimate: Option<f64>,
    /// A quasi-static scene's first equilibrium from the previous solve: the next solve (an
    /// optimization's next iteration, params a step away) starts Newton from it instead of
    /// from rest. An optimization saves it with its state, so a resumed run starts where an
    /// uninterrupted one would.
    pub warm_start: Option<Vec<f64>>,
    /// How static and implicit solves solve their linear systems.
    pub linear_solver: statics::LinearSolver,
    /// The material values ([`Simulation::material_values`]) that passed
    /// [`Simulation::material_at_rest`] before a static or implicit solve, and the internal
    /// forces of a small deformation with them (the force scale of round-off and of states
    /// without loads): neither is computed again until the material changes.
    material_checked: Option<(Vec<Option<f64>>, f64)>,
    /// The state (positions, velocities) at the last state check that passed, and its step:
    /// a blow-up is run again step by step from there to find where it went wrong.
    last_good: Option<(u64, Vec<f64>, Vec<f64>)>,
    /// An f32 static solve's twin: the same kernels compiled for f64 on the CPU, which
    /// evaluates the residuals that refine its equilibria ([`statics`]); made at the first
    /// refinement and kept for the next solves.
    f64_twin: Option<Box<Simulation<'s, crate::devices::cpu::Cpu>>>,
    ids: Ids,
}

/// Buffers and uniforms the host reads or writes, resolved once when the simulation is made.
struct Ids {
    x: BufferId,
    v: BufferId,
    x_next: BufferId,
    v_next: BufferId,
    elem_force: BufferId,
    elem_j: BufferId,
    elem_energy: Option<BufferId>,
    t: UniformId,
    dt: UniformId,
    /// Per-element params: the index in `Scene::fields`, the buffer `param.NAME` and the
    /// uniform of each set element's value.
    fields: Vec<(usize, BufferId, Vec<UniformId>)>,
}

/// A state check whose buffers are being read back ([`Simulation::start_check`]).
pub(crate) struct PendingCheck {
    step: u64,
    read: crate::devices::PendingRead,
}

/// How often the state is checked for blow-ups and inversions (in steps) on a backend that
/// runs on the host, and how often the backward pass samples the adjoint's health.
const CHECK_EVERY: u64 = 50;

/// How often the state is checked on a backend whose steps run ahead of the host (a GPU,
/// [`Backend::runs_ahead`]). A check reads the state back and scans it on the host: at the
/// 420k-tet benchmark that is about 4 ms, while 50 steps are about 2 ms of an H200's time,
/// so checking every 50 steps kept the GPU waiting for the host most of the time (6,455
/// against 21,835 steps/s for the same kernels without checks, 2026-11-27). A blow-up is
/// still reported at the step where it happened: the stretch since the last good check is
/// run again step by step ([`Simulation::diagnose`]).
pub const CHECK_EVERY_RUNNING_AHEAD: u64 = 500;

impl<'s, B: Backend> Simulation<'s, B> {
    /// Steps between two state checks on this simulation's backend.
    pub(crate) fn check_every(&self) -> u64 {
        if self.backend.runs_ahead() {
            CHECK_EVERY_RUNNING_AHEAD
        } else {
            CHECK_EVERY
        }
    }

    /// `done` of `total` steps of `phase` are done: the progress shown, and where a run stops
    /// when it was interrupted.
    pub(crate) fn tick(&mut self, phase: &str, done: u64, total: u64) -> Result<(), RunError> {
        if let Some(p) = &mut self.progress {
            p.update(phase, done, total);
        }
        self.check_interrupt()
    }

    /// [`INTERRUPTED`] once [`Simulation::interrupt`] is set.
    pub(crate) fn check_interrupt(&self) -> Result<(), RunError> {
        match &self.interrupt {
            Some(flag) if flag.load(std::sync::atomic::Ordering::Relaxed) => {
                Err(RunError(INTERRUPTED.into()))
            }
            _ => Ok(()),
        }
    }

    /// Bind a scene to a backend: buffers allocated and filled with the initial state.
    pub fn new(scene: &'s Scene, mut backend: B) -> Self {
        let m = &scene.lowered.module;
        backend
            .prepare(scene)
            .unwrap_or_else(|e| panic!("backend {}: {e}", backend.name()));
        let bufs = scene.lowered.buffers;
        // The adjoint module extends the forward one: same uniform table, more kernels.
        let mut uniforms = Uniforms::new(&scene.lowered.adjoint.module.uniforms, &scene.uniforms);
        let (t, dt) = (uniforms.intern("t"), uniforms.intern("dt"));
        uniforms.set(t, 0.0);
        uniforms.set(dt, 0.0);
        // Contact stiffnesses: set per solve (`prepare_contact`); none before.
        for c in (scene.lowered.contacts.iter()).flat_map(|c| &c.pairs) {
            let id = uniforms.intern(&c.stiffness_uniform);
            uniforms.set(id, 0.0);
        }
        // Closed-loop sensors and their tangent directions: set before any kernel reads
        // them (a sensor at each step's or iterate's state; a direction where a product asks).
        for s in &scene.sensors {
            for name in [s.uniform.clone(), format!("dir.{}", s.uniform)] {
                let id = uniforms.intern(&name);
                uniforms.set(id, 0.0);
            }
        }
        let fields = scene
            .fields
            .iter()
            .enumerate()
            .filter_map(|(index, f)| {
                let b = m.buffer_named(&format!("param.{}", f.name))?;
                let ids = (0..f.elements.len())
                    .map(|i| uniforms.intern(&format!("param.{}.{i}", f.name)))
                    .collect();
                Some((index, b, ids))
            })
            .collect();
        let ids = Ids {
            x: bufs.x,
            v: bufs.v,
            x_next: bufs.x_next,
            v_next: bufs.v_next,
            elem_force: bufs.elem_force,
            elem_j: bufs.elem_j,
            elem_energy: bufs.elem_energy,
            t,
            dt,
            fields,
        };
        let mut fill = |b: Option<BufferId>, data: Vec<f64>| {
            if let Some(b) = b {
                backend.set(b, &data);
            }
        };
        fill(
            Some(bufs.x),
            scene.mesh.nodes.iter().flatten().copied().collect(),
        );
        fill(Some(bufs.mass), scene.pre.mass.clone());
        fill(
            Some(bufs.fixed),
            scene
                .fixed
                .iter()
                .map(|&f| if f { 1.0 } else { 0.0 })
                .collect(),
        );
        fill(Some(bufs.vol0), scene.pre.rest_volume.clone());
        if bufs.rest_shape.is_some() {
            fill(bufs.rest_shape, scene.rest_shape.clone());
        }
        if bufs.edge_l0.is_some() {
            fill(bufs.edge_l0, edge_rest_lengths(scene));
        }
        let mut sim = Simulation {
            scene,
            backend,
            uniforms,
            vtk: None,
            csv: Vec::new(),
            progress: None,
            interrupt: None,
            estimate: None,
            warm_start: None,
            linear_solver: statics::LinearSolver::Auto,
            material_checked: None,
            last_good: None,
            f64_twin: None,
            ids,
        };
        sim.upload_fields();
        sim
    }

    /// Copy the per-element params' values from [`Simulation::uniforms`] (`param.NAME.i`, the
    /// set's `i`-th element) into their element buffers `param.NAME`, in kernel element order.
    /// Elements outside the set get NaN: no kernel reads them there (a material reading a field
    /// is applied only within its set). `run` and `gradient` call this first, so a changed
    /// uniform takes effect in the next run.
    pub fn upload_fields(&mut self) {
        for (index, b, ids) in &self.ids.fields {
            let f = &self.scene.fields[*index];
            let mut data = vec![f64::NAN; self.scene.mesh.tets.len()];
            for (&e, &id) in f.elements.iter().zip(ids) {
                data[e as usize] = self.uniforms.get(id);
            }
            self.backend.set(*b, &data);
        }
    }

    /// Back to the initial state (rest positions, zero velocity, t = 0), keeping the buffers,
    /// the compiled kernels and the stable-step estimate: the next run starts afresh.
    pub fn reset(&mut self) {
        let x: Vec<f64> = self.scene.mesh.nodes.iter().flatten().copied().collect();
        let zeros = vec![0.0; x.len()];
        self.backend.set(self.ids.x, &x);
        self.backend.set(self.ids.v, &zeros);
        self.uniforms.set(self.ids.t, 0.0);
        self.last_good = None;
    }

    fn run_element_kernels(&mut self) -> Result<(), RunError> {
        for (k, range) in self.scene.material_ranges.iter().enumerate() {
            self.backend
                .run(k, range.clone(), &self.uniforms)
                .map_err(RunError)?;
        }
        Ok(())
    }

    /// Element energy and J (`elem_energy`, `elem_j`) at the current positions: the FEM
    /// diagnostics kernels, which no step runs (a step computes forces only). Run before
    /// whatever reads them — a state check (on the state a checked step starts from), a VTK
    /// frame, an inversion test of a static solve. The spring mesh has none: its step writes J.
    pub(crate) fn run_diagnostics(&mut self) -> Result<(), RunError> {
        let diagnostics = &self.scene.lowered.diagnostics;
        for (k, range) in self.scene.material_ranges.iter().enumerate() {
            if let Some(&d) = diagnostics.get(k) {
                self.backend
                    .run(d, range.clone(), &self.uniforms)
                    .map_err(RunError)?;
            }
        }
        Ok(())
    }

    /// The step size of a run and the stable-step estimate it used (if any).
    fn resolve_dt(&mut self, dt_override: Option<f64>) -> Result<(f64, Option<f64>), RunError> {
        let estimate = match (self.scene.dt, dt_override, self.estimate) {
            (_, _, Some(e)) => Some(e),
            (DtChoice::Auto { .. }, None, None) => Some(self.stable_dt_estimate()?),
            _ => None,
        };
        let dt = match (dt_override, self.scene.dt, estimate) {
            (Some(dt), _, _) => dt,
            (None, DtChoice::Given(dt), _) => dt,
            (None, DtChoice::Auto { safety }, Some(est)) => safety * est,
            _ => unreachable!(),
        };
        if !dt.is_finite() || dt <= 0.0 {
            return Err(RunError(format!("no usable time step (estimate {dt} s)")));
        }
        Ok((dt, estimate))
    }

    /// The step size and number of steps a run would use.
    pub fn time_steps(
        &mut self,
        dt_override: Option<f64>,
        steps_override: Option<u64>,
    ) -> Result<(f64, u64), RunError> {
        let (dt, _) = self.resolve_dt(dt_override)?;
        Ok((
            dt,
            steps_override.unwrap_or_else(|| self.scene.steps_for(dt)),
        ))
    }

    /// The entities forward kernel `k` runs over.
    fn kernel_range(&self, k: usize) -> Range<usize> {
        let n_mat = self.scene.material_ranges.len();
        let n_ch = self.scene.chamber_ranges.len();
        if k < n_mat {
            self.scene.material_ranges[k].clone()
        } else if k < n_mat + n_ch {
            self.scene.chamber_ranges[k - n_mat].clone()
        } else {
            0..self.scene.mesh.nodes.len()
        }
    }

    /// Element and pressure forces at the current state and time.
    fn run_force_kernels(&mut self) -> Result<(), RunError> {
        self.run_element_kernels()?;
        let n_mat = self.scene.material_ranges.len();
        for c in 0..self.scene.chamber_ranges.len() {
            let range = self.scene.chamber_ranges[c].clone();
            self.backend
                .run(n_mat + c, range, &self.uniforms)
                .map_err(RunError)?;
        }
        Ok(())
    }

    /// The launches of one step in order (element, pressure, node kernels over their
    /// entities) and the state swaps that end it.
    fn step_plan(&self) -> (Vec<Launch>, [(BufferId, BufferId); 2]) {
        let n = self.scene.material_ranges.len() + self.scene.chamber_ranges.len() + 1;
        (
            (0..n).map(|k| (k, self.kernel_range(k))).collect(),
            [(self.ids.x, self.ids.x_next), (self.ids.v, self.ids.v_next)],
        )
    }

    /// Steps `from..to` with no host work between them: in one call of the backend's compiled
    /// time loop where it has one, else one by one (the same bits either way).
    fn advance(&mut self, from: u64, to: u64, dt: f64) -> Result<(), RunError> {
        // Sensors are evaluated by the host at every step: no compiled time loop.
        if to > from + 1 && !self.has_sensors() {
            let (launches, swaps) = self.step_plan();
            let ran = self
                .backend
                .run_steps(&launches, &swaps, from, to - from, dt, &self.uniforms)
                .map_err(RunError)?;
            if ran {
                // As `step` leaves it after the last step.
                self.uniforms.set(self.ids.t, (to - 1) as f64 * dt);
                return Ok(());
            }
        }
        for s in from..to {
            self.step(s, dt)?;
        }
        Ok(())
    }

    /// One step from state `step` to `step + 1`.
    fn step(&mut self, step: u64, dt: f64) -> Result<(), RunError> {
        self.uniforms.set(self.ids.t, step as f64 * dt);
        self.set_sensors()?;
        self.run_force_kernels()?;
        let node_kernel = self.scene.material_ranges.len() + self.scene.chamber_ranges.len();
        self.backend
            .run(node_kernel, 0..self.scene.mesh.nodes.len(), &self.uniforms)
            .map_err(RunError)?;
        self.backend.swap(self.ids.x, self.ids.x_next);
        self.backend.swap(self.ids.v, self.ids.v_next);
        Ok(())
    }

    /// Run the whole simulation.
    pub fn run(
        &mut self,
        dt_override: Option<f64>,
        steps_override: Option<u64>,
    ) -> Result<RunSummary, RunError> {
        if let Some(statics) = &self.scene.lowered.statics {
            let run = if statics.implicit.is_some() {
                self.solve_implicit(false, dt_override, steps_override)
            } else {
                self.solve_static(false, dt_override, steps_override)
            };
            return run.map(|r| r.summary);
        }
        let start = std::time::Instant::now();
        self.upload_fields();
        self.prepare_contact()?;
        let (dt, estimate) = self.resolve_dt(dt_override)?;
        let steps = steps_override.unwrap_or_else(|| self.scene.steps_for(dt));
        self.uniforms.set(self.ids.dt, dt);
        let loss_fn = loss::Loss::build(self.scene, dt, steps).map_err(RunError)?;
        let stepped = self.run_steps(dt, steps, loss_fn.as_ref());
        // The logs are written whether or not the run finished: a blow-up keeps its history.
        let written: Result<Vec<()>, RunError> = self
            .csv
            .iter()
            .map(|c| c.finish().map_err(RunError))
            .collect();
        let loss_sum = stepped?;
        written?;
        if self.vtk.is_some() {
            self.write_vtk(steps as f64 * dt)?;
        }
        let mut summary = self.summary(steps, dt, estimate, start);
        summary.contact = self.contact_report(steps as f64 * dt)?;
        summary.loss = loss_fn
            .map(|l| {
                let value = match l.window {
                    loss::LossWindow::End => {
                        let (x, v) = (self.backend.get(self.ids.x), self.backend.get(self.ids.v));
                        l.eval(self.scene, &x, &v, steps as f64 * dt, &self.uniforms)
                    }
                    loss::LossWindow::Over { .. } => loss_sum,
                };
                loss::require_finite(value, l.window, steps, dt)
            })
            .transpose()
            .map_err(RunError)?;
        Ok(summary)
    }

    /// The current state as a run's summary (no loss).
    fn summary(
        &self,
        steps: u64,
        dt: f64,
        estimate: Option<f64>,
        start: std::time::Instant,
    ) -> RunSummary {
        let xs = self.backend.get(self.ids.x);
        let vs = self.backend.get(self.ids.v);
        RunSummary {
            loss: None,
            steps,
            dt,
            dt_stable_estimate: estimate,
            wall_seconds: start.elapsed().as_secs_f64(),
            x: xs.chunks(3).map(|c| [c[0], c[1], c[2]]).collect(),
            v: vs.chunks(3).map(|c| [c[0], c[1], c[2]]).collect(),
            solver: None,
            contact: Vec::new(),
        }
    }

    /// The time loop of `run`: steps, outputs, the windowed loss's sum and state checks.
    fn run_steps(
        &mut self,
        dt: f64,
        steps: u64,
        loss_fn: Option<&loss::Loss>,
    ) -> Result<f64, RunError> {
        let scene = self.scene;
        let rest = &scene.mesh.nodes;
        let mut loss_sum = 0.0;
        let csv_due =
            |csv: &[Box<dyn NodeSetLog>], k: u64| csv.iter().any(|c| k.is_multiple_of(c.every()));
        let vtk_due = |vtk: &Option<Box<dyn StateSeries>>, k: u64| {
            vtk.as_ref()
                .is_some_and(|o| k.is_multiple_of(o.every().max(1)))
        };
        // The initial state is the first good one (a blow-up before the first check is run
        // again from here).
        self.last_good = Some((
            0,
            self.backend.get(self.ids.x),
            self.backend.get(self.ids.v),
        ));
        let mut step = 0;
        // The check under way: finished when the next one starts (the GPU runs the stretch
        // between meanwhile), before any output reads the state, and at the end.
        let mut pending: Option<PendingCheck> = None;
        let every = self.check_every();
        while step < steps {
            let outputs_due = csv_due(&self.csv, step) || vtk_due(&self.vtk, step);
            if outputs_due || loss_fn.is_some_and(|l| l.in_window((step + 1) as f64 * dt, dt)) {
                self.settle_check(&mut pending, dt)?;
            }
            if csv_due(&self.csv, step) {
                let x = self.backend.get(self.ids.x);
                for c in self.csv.iter_mut().filter(|c| step % c.every() == 0) {
                    c.record(step, step as f64 * dt, rest, &x);
                }
            }
            if vtk_due(&self.vtk, step) {
                self.uniforms.set(self.ids.t, step as f64 * dt);
                self.write_vtk(step as f64 * dt)?;
            }
            // The steps up to the next one after which the host has work (a state check, an
            // output, a loss term) go at once; that last one alone.
            let end = stretch_end(step, steps, |j| {
                j % every == 0
                    || csv_due(&self.csv, j + 1)
                    || vtk_due(&self.vtk, j + 1)
                    || loss_fn.is_some_and(|l| l.in_window((j + 1) as f64 * dt, dt))
            });
            self.advance(step, end - 1, dt)?;
            let last = end - 1;
            let check = last % every == 0 || last + 1 == steps;
            if check {
                // The check reads the J of the state this step starts from.
                self.run_diagnostics()?;
            }
            self.step(last, dt)?;
            if let Some(l) = loss_fn {
                loss_sum += self.loss_term(l, last + 1, dt);
            }
            if check {
                let started = self.start_check(last);
                if let Some(earlier) = pending.replace(started) {
                    self.finish_check(earlier, dt)?;
                }
            }
            self.tick("forward", end, steps)?;
            step = end;
        }
        self.settle_check(&mut pending, dt)?;
        if !self.csv.is_empty() {
            let x = self.backend.get(self.ids.x);
            for c in &mut self.csv {
                c.record(steps, steps as f64 * dt, rest, &x);
            }
        }
        Ok(loss_sum)
    }

    /// Run until the state settles or `max_steps` steps, whichever comes first: the steps to a
    /// steady state of a quasi-static scene. Settled means s × elapsed time ≤ `tol` × max node
    /// displacement, with s the largest mean node speed over the last tenth of the elapsed time
    /// (a dimensionless ratio, ~1 while a load ramps and → 0 as the motion dies out; the mean
    /// over a window ignores turning points of oscillations and round-off chatter), checked
    /// every [`CHECK_EVERY`] steps. A mean speed below the round-off floor of the precision (32
    /// ulps of the positions over the window) also counts as settled.
    /// Writes no VTK and evaluates no loss (`loss` is `None`).
    pub fn run_to_steady_state(
        &mut self,
        dt_override: Option<f64>,
        max_steps: u64,
        tol: f64,
    ) -> Result<SteadyRun, RunError> {
        let start = std::time::Instant::now();
        self.upload_fields();
        let (dt, estimate) = self.resolve_dt(dt_override)?;
        self.uniforms.set(self.ids.dt, dt);
        let rest: Vec<f64> = self.scene.mesh.nodes.iter().flatten().copied().collect();
        let max_norm = |a: &[f64], b: Option<&[f64]>| {
            a.chunks(3)
                .enumerate()
                .map(|(i, c)| {
                    let o = b.map_or([0.0; 3], |b| [b[3 * i], b[3 * i + 1], b[3 * i + 2]]);
                    ((c[0] - o[0]).powi(2) + (c[1] - o[1]).powi(2) + (c[2] - o[2]).powi(2)).sqrt()
                })
                .fold(0.0, f64::max)
        };
        let eps = match self.backend.precision() {
            Precision::F32 => f32::EPSILON as f64,
            _ => f64::EPSILON,
        };
        // Positions at earlier checks: the motion is measured as the mean speed over the last
        // tenth of the elapsed time, which averages out oscillations and round-off.
        let mut history: std::collections::VecDeque<(f64, Vec<f64>)> =
            std::collections::VecDeque::new();
        let mut steps = max_steps;
        let mut settled = false;
        self.last_good = Some((
            0,
            self.backend.get(self.ids.x),
            self.backend.get(self.ids.v),
        ));
        let mut next = 0;
        while next < max_steps {
            let end = stretch_end(next, max_steps, |j| (j + 1) % CHECK_EVERY == 0);
            self.advance(next, end - 1, dt)?;
            let step = end - 1;
            self.run_diagnostics()?;
            self.step(step, dt)?;
            next = end;
            self.check_state(step, dt)?;
            let t = (step + 1) as f64 * dt;
            let x = self.backend.get(self.ids.x);
            let window = (0.1 * t).max(2.0 * CHECK_EVERY as f64 * dt);
            while history.len() > 1 && history[1].0 <= t - window {
                history.pop_front();
            }
            if let Some((t0, x0)) = history.front()
                && *t0 <= t - window
            {
                let speed = max_norm(&x, Some(x0)) / (t - t0);
                // Positions at rest chatter by round-off (f32: 10-15 ulps measured on the free
                // end of a beam): 32 ulps over the window is not motion.
                let floor = 32.0 * eps * max_norm(&x, None) / (t - t0);
                if speed * t <= tol * max_norm(&x, Some(&rest)) || speed <= floor {
                    settled = true;
                    steps = step + 1;
                    break;
                }
            }
            history.push_back((t, x));
            if history.len() > 64 {
                // Thin the history (keeping the newest): its span is all that matters.
                let newest = history.pop_back();
                let kept: Vec<_> = history.drain(..).step_by(2).collect();
                history.extend(kept);
                history.extend(newest);
            }
        }
        Ok(SteadyRun {
            summary: self.summary(steps, dt, estimate, start),
            settled,
        })
    }

    /// The windowed loss's term at state `k` (the state after `k` steps), 0 outside the
    /// window and for losses taken at the end.
    fn loss_term(&self, l: &loss::Loss, k: u64, dt: f64) -> f64 {
        let t = k as f64 * dt;
        if !l.in_window(t, dt) {
            return 0.0;
        }
        let (x, v) = (self.backend.get(self.ids.x), self.backend.get(self.ids.v));
        l.eval(self.scene, &x, &v, t, &self.uniforms)
    }

    /// A VTK frame of the current state, its element fields (energy, J) computed for it.
    fn write_vtk(&mut self, t: f64) -> Result<(), RunError> {
        self.run_diagnostics()?;
        let scene = self.scene;
        let x = self.backend.get(self.ids.x);
        let v = self.backend.get(self.ids.v);
        let energy = self
            .ids
            .elem_energy
            .map(|b| self.backend.get(b))
            .unwrap_or_default();
        let j = self.backend.get(self.ids.elem_j);
        let contact_pressure = self.contact_pressure(t)?;
        let frame = Frame {
            t,
            x: &x,
            v: &v,
            energy: &energy,
            j: &j,
            contact_pressure: &contact_pressure,
        };
        let out = self.vtk.as_mut().expect("vtk output");
        out.write_frame(&scene.mesh, &scene.pre.rest_volume, &frame)
            .map_err(RunError)
    }

    fn check_state(&mut self, step: u64, dt: f64) -> Result<(), RunError> {
        let check = self.start_check(step);
        self.finish_check(check, dt)
    }

    /// Start the state check after step `step` (see [`Simulation::check_state`]): its
    /// buffers are read back without waiting, so a GPU goes on with the next steps while
    /// they come; [`Simulation::finish_check`] checks them.
    fn start_check(&mut self, step: u64) -> PendingCheck {
        let read = self
            .backend
            .read_later(&[self.ids.elem_j, self.ids.x, self.ids.v]);
        PendingCheck { step, read }
    }

    /// Check the state a [`Simulation::start_check`] read: a problem is diagnosed from the
    /// last good state as [`Simulation::check_state`] does (the steps run since are
    /// discarded), a good state becomes the last good one.
    fn finish_check(&mut self, check: PendingCheck, dt: f64) -> Result<(), RunError> {
        let step = check.step;
        let t = (step + 1) as f64 * dt;
        let mut values = self.backend.collect(check.read).into_iter();
        if let Some(e) = self.backend.device_error() {
            return Err(RunError(format!(
                "the device failed by step {} (t = {t:.6} s): {e}",
                step + 1
            )));
        }
        let (js, xs, vs) = match (values.next(), values.next(), values.next()) {
            (Some(j), Some(x), Some(v)) => (j, x, v),
            _ => {
                return Err(RunError(
                    "internal error: a state check read nothing".into(),
                ));
            }
        };
        match self.first_problem(&js, &xs) {
            None => {
                self.last_good = Some((step + 1, xs, vs));
                Ok(())
            }
            Some(p) => Err(RunError(self.diagnose(step, dt, p))),
        }
    }

    /// Finish a state check under way, if any.
    fn settle_check(
        &mut self,
        pending: &mut Option<PendingCheck>,
        dt: f64,
    ) -> Result<(), RunError> {
        match pending.take() {
            Some(c) => self.finish_check(c, dt),
            None => Ok(()),
        }
    }

    /// What is wrong with a state, if anything: an inverted element (J ≤ 0; inversion-safe
    /// materials may pass through it) is named first, as it is usually why positions went
    /// non-finite (J^(-2/3) of a negative J); then a non-finite position, then a non-finite J.
    /// `js` are the element volume ratios of the state before the step that made `xs`.
    fn first_problem(&self, js: &[f64], xs: &[f64]) -> Option<Problem> {
        let safe = |e: usize| {
            let lowered = &self.scene.lowered;
            self.scene
                .material_ranges
                .iter()
                .position(|r| r.contains(&e))
                .is_some_and(|m| lowered.inversion_safe.get(m).copied().unwrap_or(false))
        };
        if let Some((e, &j)) = js.iter().enumerate().find(|&(e, j)| *j <= 0.0 && !safe(e)) {
            return Some(Problem::Inverted { element: e, j });
        }
        if let Some(i) = xs.iter().position(|v| !v.is_finite()) {
            return Some(Problem::NonFinite { node: i / 3 });
        }
        js.iter()
            .enumerate()
            .find(|(_, j)| !j.is_finite())
            .map(|(e, &j)| Problem::NonFiniteJ { element: e, j })
    }

    /// The report of a failed state check after step `step` (issue 20 item 15). The state is
    /// checked every [`CHECK_EVERY`] steps; the stretch since the last good check is run again
    /// step by step from its state, so the report names the step where it went wrong, the
    /// element or node, and the state before it. Then the cause: non-physical material
    /// constants (the stiffness at rest is not positive), mass damping too strong for the step
    /// (β·dt > 2, measured by probing one step), a time step above the stable step estimated at
    /// the last finite state (`dt` is blamed only then), else the load.
    /// Runs only after a failure: runs that do not blow up are not touched.
    fn diagnose(&mut self, step: u64, dt: f64, seen: Problem) -> String {
        // The states of the rerun, newest last (at most three kept): (step, x, v).
        let mut states: Vec<(u64, Vec<f64>, Vec<f64>)> = Vec::new();
        let mut found = (step, seen);
        let start = self.last_good.as_ref().map_or(0, |l| l.0);
        // Where the stable step is re-estimated: the state of the last passing check, before
        // the blow-up deformed it (a state a step before an inversion can be so crushed that
        // any dt looks too large there, also when a load too large is the cause).
        let checked = self.last_good.as_ref().map(|l| l.1.clone());
        if let Some((k, x, v)) = self.last_good.take() {
            self.backend.set(self.ids.x, &x);
            self.backend.set(self.ids.v, &v);
            states.push((k, x, v));
            for s in k..=step {
                if self.run_diagnostics().is_err() || self.step(s, dt).is_err() {
                    break;
                }
                let js = self.backend.get(self.ids.elem_j);
                let xs = self.backend.get(self.ids.x);
                if let Some(p) = self.first_problem(&js, &xs) {
                    found = (s, p);
                    break;
                }
                let vs = self.backend.get(self.ids.v);
                states.push((s + 1, xs, vs));
                if states.len() > 3 {
                    states.remove(0);
                }
            }
        }
        let (s, problem) = found;
        // An element found inverted (or non-finite) at state `s` makes `s` unusable: the last
        // finite state is the one before it, where there is one.
        if !matches!(problem, Problem::NonFinite { .. }) && states.len() > 1 {
            states.pop();
        }
        let last = states.pop();
        let mesh = &self.scene.mesh;
        let what = match problem {
            // J is the volume ratio of state `s`, evaluated by step `s`.
            Problem::Inverted { element, j } => format!(
                "element {} inverted at step {s} (t = {:.6} s): J = {j}",
                mesh.tet_id(element),
                s as f64 * dt,
                j = Sig(j)
            ),
            Problem::NonFiniteJ { element, j } => format!(
                "element {} became non-finite at step {s} (t = {:.6} s): J = {j}",
                mesh.tet_id(element),
                s as f64 * dt,
                j = Sig(j)
            ),
            Problem::NonFinite { node } => format!(
                "the simulation became unstable at step {} (t = {:.6} s): node {} has a \
                 non-finite position",
                s + 1,
                (s + 1) as f64 * dt,
                mesh.node_id(node)
            ),
        };
        let (Some((good, _, _)), Some(x)) = (last, checked) else {
            return format!(
                "{what}. Reduce dt (now {dt} s) or the load rate; `dt = auto` estimates the \
                 stable step",
                dt = Sig(dt)
            );
        };
        let cause = self.cause(dt, s, start, &x, &problem);
        let from = if good > start {
            format!("; the last finite state is step {good}")
        } else {
            String::new()
        };
        format!(
            "{what} (found by running again step by step from step {start}, the last state checked{from}). {cause}"
        )
    }

    /// Why the material constants are not physical, if they are not: the stiffness at the
    /// current (rest) positions is not positive, by the Lanczos extremes of M⁻¹K.
    pub(crate) fn material_at_rest(&mut self) -> Result<Option<String>, RunError> {
        Ok(match self.stiffness_extremes()? {
            Some((lowest, highest, _)) if highest <= 0.0 || lowest < -1e-2 * highest.abs() => {
                Some(format!(
                    "material constants are not physical: the stiffness at rest is not \
                     positive (a deformation mode with ω² = {} /s², against {} /s² for the \
                     stiffest); check the moduli (E > 0, μ > 0, a bulk modulus > 0) and \
                     Poisson's ratio (−1 < ν < 0.5)",
                    Sig(lowest.min(highest)),
                    Sig(highest)
                ))
            }
            _ => None,
        })
    }

    /// What the material constants are made of: the uniforms the element force kernels read
    /// and the entries of the per-element fields. An optimization of controller weights or
    /// pressures does not change it, so its solves check the material once (60 force
    /// evaluations with reorthogonalization: a second per solve on a 67k-dof mesh).
    pub(crate) fn material_values(&self) -> Vec<Option<f64>> {
        let module = &self.scene.lowered.adjoint.module;
        let kernels = module.kernels.iter().take(self.scene.material_ranges.len());
        let uniforms = kernels.flat_map(|k| k.uniforms());
        let fields = self
            .ids
            .fields
            .iter()
            .flat_map(|(_, _, ids)| ids.iter().copied());
        uniforms
            .chain(fields)
            .map(|id| self.uniforms.value(id))
            .collect()
    }

    /// β·dt of the mass damping at step `step`: one step from the rest positions with
    /// velocity u and with 2u (the elastic forces are the same in both), the difference of the
    /// new velocities is (1 − β·dt)·u.
    fn damping_per_step(&mut self, step: u64, dt: f64) -> Result<f64, RunError> {
        let rest: Vec<f64> = self.scene.mesh.nodes.iter().flatten().copied().collect();
        let fixed = &self.scene.fixed;
        let u: Vec<f64> = (0..rest.len())
            .map(|i| if fixed[i / 3] { 0.0 } else { 1e-3 })
            .collect();
        let mut probe = |k: f64| -> Result<Vec<f64>, RunError> {
            self.backend.set(self.ids.x, &rest);
            let v: Vec<f64> = u.iter().map(|c| k * c).collect();
            self.backend.set(self.ids.v, &v);
            self.step(step, dt)?;
            Ok(self.backend.get(self.ids.v))
        };
        let (a, b) = (probe(1.0)?, probe(2.0)?);
        let uu: f64 = u.iter().map(|c| c * c).sum();
        if uu == 0.0 {
            return Ok(0.0);
        }
        let du: f64 = (0..u.len()).map(|i| (b[i] - a[i]) * u[i]).sum();
        Ok(1.0 - du / uu)
    }

    /// Why a run blew up, with what to do ([`Simulation::diagnose`]): it failed in step
    /// `failed`; `x` is the state of the last passing check (step `good`).
    fn cause(&mut self, dt: f64, failed: u64, good: u64, x: &[f64], problem: &Problem) -> String {
        // The stiffness at rest: not positive for non-physical material constants.
        let rest: Vec<f64> = self.scene.mesh.nodes.iter().flatten().copied().collect();
        self.backend.set(self.ids.x, &rest);
        if let Ok(Some(why)) = self.material_at_rest() {
            return format!("The {why}. A smaller dt does not help");
        }
        // Mass damping: v ← (1 − β·dt)·v + …, unstable by itself for β·dt > 2 whatever the
        // elastic step.
        if let Ok(bdt) = self.damping_per_step(failed, dt)
            && bdt > 2.0
        {
            let beta = bdt / dt;
            return format!(
                "The damping is too strong for this time step: β = {beta:.3e} /s at that time, \
                 and β·dt = {bdt:.3e} > 2 makes every velocity flip sign and grow each step \
                 (the elastic forces alone would be stable up to dt = {} s). Lower the damping \
                 below {:.3e} /s, or dt below {:.3e} s",
                Sig(self.estimate.unwrap_or(f64::NAN)),
                2.0 / dt,
                2.0 / beta
            );
        }
        // The time step against the stable step at the last finite state.
        self.backend.set(self.ids.x, x);
        let here = match self.compute_stable_dt() {
            Ok(e) if e.is_finite() && e > 0.0 => e,
            _ => {
                return format!(
                    "The stable step could not be estimated there; try a smaller dt, e.g. {} s",
                    Sig(dt / 4.0)
                );
            }
        };
        // The estimate is of the undamped step and has its own error: within 0.9 of it, dt is
        // not the cause.
        if dt > 0.9 * here {
            let suggested = 0.8 * here;
            return match self.estimate {
                // Both estimates have their own error: only a clearly smaller step is the
                // material stiffening.
                Some(rest) if here < 0.95 * rest => format!(
                    "The run is unstable because the time step dt = {dt} s is too large: the \
                     material stiffens as it \
                     deforms, the stable step is {here} s at step {good} (the last state \
                     checked), against {rest} s at rest where `dt = auto` estimates it. Use dt \
                     <= {suggested} s, e.g. `dt = auto(safety: {})`",
                    two_digits_down((suggested / rest).min(0.9)),
                    dt = Sig(dt),
                    here = Sig(here),
                    rest = Sig(rest),
                    suggested = Sig(suggested)
                ),
                _ => format!(
                    "The run is unstable because the time step dt = {dt} s is too large for \
                     this mesh and material: the \
                     stable step at step {good} (the last state checked) is {here} s; use dt \
                     <= {suggested} s",
                    dt = Sig(dt),
                    here = Sig(here),
                    suggested = Sig(suggested)
                ),
            };
        }
        let load = "lower the load (pressures, gravity) or ramp it more slowly, refine the mesh \
                    there, or use an inversion-safe material such as `stable_neo_hookean`";
        match problem {
            Problem::Inverted { .. } => format!(
                "The time step is not the cause (dt = {dt} s is within the stable step \
                 {here} s at step {good}, the last state checked): the load deforms the element past \
                 inversion — {load}",
                dt = Sig(dt),
                here = Sig(here)
            ),
            _ => format!(
                "The time step is not the cause (dt = {dt} s is within the stable step \
                 {here} s at step {good}, the last state checked): the forces grew without bound — {load}",
                dt = Sig(dt),
                here = Sig(here)
            ),
        }
    }
}

/// The error of a run stopped by [`Simulation::interrupt`].
pub const INTERRUPTED: &str = "interrupted";

/// What a failed state check found.
#[derive(Debug, Clone, Copy)]
enum Problem {
    Inverted { element: usize, j: f64 },
    NonFinite { node: usize },
    NonFiniteJ { element: usize, j: f64 },
}
