//! The backward pass: d loss / d param for every param, by running the adjoint kernels of the
//! scene (`passes::adjoint`) step by step in reverse, with states recomputed from checkpoints
//! as a [`Schedule`] says.
//!
//! The forward run is the schedule's prefix; it also evaluates the loss. Reversing step k needs
//! state k in the buffers and ∂L/∂(state k+1) in `adj_*_next`; it leaves ∂L/∂(state k) there
//! (after the swap), to which the loss's own derivative at state k is added for windowed
//! losses. Param derivatives accumulate per entity in the `grad@…` buffers and are summed on
//! the host in entity order, so the result is deterministic and the same for every schedule.
//! A per-element param's derivatives accumulate in `grad_param.NAME`, one entry per element,
//! which is reported as is: `param.NAME.i` for the set's `i`-th element.

use super::checkpoint::{Action, Schedule, StateStore};
use super::loss::{Loss, LossWindow};
use super::{CHECK_EVERY, RunError, RunSummary, Simulation};
use crate::devices::{Backend, domain_len};
use softc_compiler::back::Precision;
use softc_compiler::driver::LossArg;
use std::collections::BTreeMap;

/// What `Checkpointing::Auto` may store without a memory budget: every state when they fit in
/// 1 GiB (10k tets: 126 kB a state, 8,500 steps), which recomputes nothing; the checkpointed
/// schedules cost 1.8-2.8 extra forward steps per reversed step (issue 18).
pub const AUTO_STORE_ALL_BYTES: u64 = 1 << 30;

/// The least memory budget a backward pass can keep: two states (the current one and one
/// stored) of `nodes` nodes, stored as f32 when `single`.
pub fn least_budget(nodes: usize, single: bool) -> u64 {
    2 * 2 * 3 * nodes as u64 * if single { 4 } else { 8 }
}

/// Which states the backward pass keeps.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Checkpointing {
    /// Every state when they fit in the budget (without one, [`AUTO_STORE_ALL_BYTES`]); else
    /// the fewest snapshots that keep recomputation within 3 forward runs, within the budget.
    Auto,
    StoreAll,
    Periodic(u64),
    Revolve(usize),
}

#[derive(Clone, Debug)]
pub struct GradOptions {
    pub checkpoint: Checkpointing,
    /// Bytes the stored states may take (host copies of x and v).
    pub memory_budget: Option<u64>,
    /// Differentiate through at most this many of the last steps (truncated back-propagation).
    pub truncate: Option<u64>,
}

impl Default for GradOptions {
    fn default() -> Self {
        GradOptions {
            checkpoint: Checkpointing::Auto,
            memory_budget: None,
            truncate: None,
        }
    }
}

/// The adjoint's size at one point of the backward pass.
#[derive(Clone, Debug, PartialEq)]
pub struct HealthSample {
    /// The state whose adjoint this is (∂L/∂x_step, ∂L/∂v_step).
    pub step: u64,
    pub adj_x_norm: f64,
    pub adj_v_norm: f64,
}

#[derive(Clone, Debug)]
pub struct GradientReport {
    pub summary: RunSummary,
    /// d loss / d uniform for every `param.*` uniform of the scene (SI units).
    pub gradients: BTreeMap<String, f64>,
    /// The schedule used (`revolve(snapshots: 27)`).
    pub schedule: String,
    /// States stored at once at most, and the bytes of one state.
    pub stored_states: usize,
    pub state_bytes: usize,
    /// Forward steps run in all (forward run + recomputation) over the run's steps.
    pub recompute_ratio: f64,
    /// Steps reversed (fewer than the run's with `truncate`).
    pub reversed_steps: u64,
    pub forward_seconds: f64,
    pub backward_seconds: f64,
    /// Norms of ∂L/∂x and ∂L/∂v every [`CHECK_EVERY`] reversed steps, from the last step back.
    pub health: Vec<HealthSample>,
    /// ∂L/∂x and ∂L/∂v of the initial state (3 per node; the velocity part includes
    /// `gradient_scale`), when the whole horizon was reversed (no `truncate` cut).
    pub initial_state: Option<(Vec<f64>, Vec<f64>)>,
}

impl GradientReport {
    /// Growth of the adjoint's norm per 1000 reversed steps (a factor; > 1 grows), from the
    /// first and last nonzero health samples.
    pub fn growth_per_1000_steps(&self) -> Option<f64> {
        let norm = |h: &HealthSample| h.adj_x_norm.hypot(h.adj_v_norm);
        let first = self.health.iter().find(|h| norm(h) > 0.0)?;
        let last = self.health.iter().rev().find(|h| norm(h) > 0.0)?;
        let span = first.step.checked_sub(last.step).filter(|s| *s > 0)? as f64;
        Some((norm(last) / norm(first)).powf(1000.0 / span))
    }
}

/// A buffer and its length (entries).
pub(super) type BufferLen = (softc_compiler::ir::BufferId, usize);

/// Positions and velocities copied to the host.
type HostState = (Vec<f64>, Vec<f64>);

/// Steps of a run "store state k in slot k, advance to k + 1" at the start of `actions`,
/// state `current` current.
fn storing_run(actions: &[Action], current: u64) -> u64 {
    let mut m = 0u64;
    while let [Action::Store { slot }, Action::Advance { to }, ..] = actions[2 * m as usize..] {
        if slot as u64 != current + m || to != current + m + 1 {
            break;
        }
        m += 1;
    }
    m
}

/// Steps of a run "restore state k from slot k, reverse step k, free slot k" from step `from`
/// down (the first restore may be missing: state `from` is current), at most down to `stop`,
/// ending after the first step a health sample is due at; and the actions it takes. Only
/// steps whose state `holds(k)` in slot k count.
fn reversing_run(
    actions: &[Action],
    from: u64,
    stop: u64,
    holds: impl Fn(u64) -> bool,
) -> (u64, usize) {
    let (mut m, mut at) = (0u64, 0usize);
    loop {
        let k = from - m;
        if !holds(k) {
            break;
        }
        let mut j = at;
        if actions.get(j) == Some(&Action::Restore { slot: k as usize }) {
            j += 1;
        } else if m > 0 {
            break;
        }
        if actions.get(j) != Some(&Action::Reverse { step: k }) {
            break;
        }
        j += 1;
        if actions.get(j) == Some(&Action::Free { slot: k as usize }) {
            j += 1;
        }
        m += 1;
        at = j;
        if k == stop || k.is_multiple_of(CHECK_EVERY) {
            break;
        }
    }
    (m, at)
}

impl<B: Backend> Simulation<'_, B> {
    fn save_state(&self) -> HostState {
        (self.backend.get(self.ids.x), self.backend.get(self.ids.v))
    }

    fn load_state(&mut self, s: &HostState) {
        self.backend.set(self.ids.x, &s.0);
        self.backend.set(self.ids.v, &s.1);
    }

    /// Steps `from..to` with each step's state stored on the device first (slot = step): one
    /// stretch of the backend's time loop where it has one, else one by one.
    fn advance_storing(&mut self, from: u64, to: u64, dt: f64) -> Result<(), RunError> {
        let (launches, swaps) = self.step_plan();
        let stepped = crate::devices::Stepped {
            launches: &launches,
            swaps: &swaps,
            first: from,
            n: to - from,
            dt,
            uniforms: &self.uniforms,
            reverse: false,
            states: Some(crate::devices::StateCopy::Store {
                x: self.ids.x,
                v: self.ids.v,
            }),
        };
        if to > from
            && !self.has_sensors()
            && self.backend.run_stepped(&stepped).map_err(RunError)?
        {
            return Ok(());
        }
        for k in from..to {
            self.backend
                .store_state(k as usize, self.ids.x, self.ids.v)
                .map_err(RunError)?;
            self.step(k, dt)?;
        }
        Ok(())
    }

    /// Reverse steps `from` down to `from + 1 - n`, each step's state restored from its
    /// device slot (slot = step) first: one stretch of the backend's time loop where it has
    /// one, else one by one.
    fn reverse_restoring(&mut self, from: u64, n: u64, dt: f64) -> Result<(), RunError> {
        let adj = &self.scene.lowered.adjoint;
        let mut launches = Vec::new();
        if adj.needs_forward {
            let forces = self.scene.material_ranges.len() + self.scene.chamber_ranges.len();
            launches.extend((0..forces).map(|k| (k, self.kernel_range(k))));
        }
        for rk in &adj.reverse {
            let range = match rk.range_of {
                Some(f) => self.kernel_range(f),
                None => 0..domain_len(self.scene, adj.module.kernels[rk.kernel].domain),
            };
            launches.push((rk.kernel, range));
        }
        let swaps: Vec<_> = adj.state.iter().map(|s| (s.adj, s.adj_next)).collect();
        let stepped = crate::devices::Stepped {
            launches: &launches,
            swaps: &swaps,
            first: from,
            n,
            dt,
            uniforms: &self.uniforms,
            reverse: true,
            states: Some(crate::devices::StateCopy::Restore {
                x: self.ids.x,
                v: self.ids.v,
            }),
        };
        if n > 0 && !self.has_sensors() && self.backend.run_stepped(&stepped).map_err(RunError)? {
            return Ok(());
        }
        for j in 0..n {
            let k = from - j;
            self.backend
                .restore_state(k as usize, self.ids.x, self.ids.v)
                .map_err(RunError)?;
            self.reverse_step(k, dt)?;
        }
        Ok(())
    }

    /// Keep the current state (step `current`) in slot `slot`: on the device, or copied to
    /// the host store.
    fn store(
        &mut self,
        host: &mut StateStore,
        device_steps: &mut [Option<u64>],
        on_device: bool,
        slot: usize,
        current: u64,
    ) -> Result<(), RunError> {
        if on_device {
            self.backend
                .store_state(slot, self.ids.x, self.ids.v)
                .map_err(RunError)?;
            device_steps[slot] = Some(current);
        } else {
            let (x, v) = host.slot_mut(slot, current);
            self.backend.get_into(self.ids.x, x);
            self.backend.get_into(self.ids.v, v);
        }
        Ok(())
    }

    /// Add the loss's own derivative at the current state (state `k`, time `t`) to the
    /// adjoint of that state, and its direct param derivatives to `direct`.
    fn add_loss_gradient(&mut self, l: &Loss, t: f64, direct: &mut BTreeMap<String, f64>) -> f64 {
        let adj = &self.scene.lowered.adjoint;
        let (x, v) = self.save_state();
        let (value, ds) = l.eval_grad(self.scene, &x, &v, t, &self.uniforms);
        let (ax, av) = (adj.state[0].adj_next, adj.state[1].adj_next);
        let mut gx = self.backend.get(ax);
        let mut gv = self.backend.get(av);
        for (arg, d) in l.args().iter().zip(ds) {
            match arg {
                LossArg::X { node, d: c } => gx[3 * node + c] += d,
                LossArg::V { node, d: c } => gv[3 * node + c] += d,
                LossArg::Uniform(name) if name.starts_with("param.") => {
                    *direct.entry(name.clone()).or_insert(0.0) += d;
                }
                _ => {}
            }
        }
        self.backend.set(ax, &gx);
        self.backend.set(av, &gv);
        value
    }

    /// The buffers where the param derivatives accumulate (`grad@…`, `grad_param.…`).
    pub(super) fn gradient_accumulators(&self) -> Vec<softc_compiler::ir::BufferId> {
        let adj = &self.scene.lowered.adjoint;
        let mut b: Vec<_> = (adj.params.iter().chain(&adj.sensors))
            .map(|p| p.buffer)
            .collect();
        b.extend(adj.fields.iter().map(|f| f.buffer));
        b.sort();
        b.dedup();
        b
    }

    /// Zero the accumulators of the param derivatives.
    pub(super) fn zero_gradient_accumulators(&mut self) {
        let adj = &self.scene.lowered.adjoint;
        for b in self.gradient_accumulators() {
            let buf = &adj.module.buffers[b.0 as usize];
            let len = domain_len(self.scene, buf.domain) * buf.width as usize;
            self.backend.set(b, &vec![0.0; len]);
        }
    }

    /// d loss / d param for every param: the accumulators' per-entity partial sums added up
    /// in entity order, plus the loss's direct derivatives.
    pub(super) fn collect_gradients(
        &self,
        direct: BTreeMap<String, f64>,
    ) -> Result<BTreeMap<String, f64>, RunError> {
        let adj = &self.scene.lowered.adjoint;
        // Param derivatives: per-entity partial sums, added up in entity order.
        let mut gradients: BTreeMap<String, f64> = self
            .scene
            .uniforms
            .keys()
            .filter(|k| k.starts_with("param."))
            .map(|k| (k.clone(), 0.0))
            .collect();
        for (name, sum) in self.accumulator_sums(&adj.params).0 {
            *gradients.entry(name).or_insert(0.0) += sum;
        }
        // Per-element params: each element's accumulator is the derivative of its entry.
        for f in &adj.fields {
            let data = self.backend.get(f.buffer);
            let field = self
                .scene
                .fields
                .iter()
                .find(|s| s.name == f.param)
                .ok_or_else(|| {
                    RunError(format!("the scene has no per-element param `{}`", f.param))
                })?;
            for (i, &e) in field.elements.iter().enumerate() {
                *gradients
                    .entry(format!("param.{}.{i}", f.param))
                    .or_insert(0.0) += data[e as usize];
            }
        }
        for (name, d) in direct {
            *gradients.entry(name).or_insert(0.0) += d;
        }
        Ok(gradients)
    }

    /// Each accumulator's sum over its entities (in entity order), by uniform name; and the
    /// buffers read, with their lengths.
    pub(super) fn accumulator_sums(
        &self,
        list: &[softc_compiler::passes::adjoint::ParamGradient],
    ) -> (Vec<(String, f64)>, Vec<BufferLen>) {
        let adj = &self.scene.lowered.adjoint;
        let mut cache: BTreeMap<_, Vec<f64>> = BTreeMap::new();
        let mut sums = Vec::with_capacity(list.len());
        for p in list {
            let width = adj.module.buffers[p.buffer.0 as usize].width as usize;
            let data = cache
                .entry(p.buffer)
                .or_insert_with(|| self.backend.get(p.buffer));
            let sum: f64 = data.iter().skip(p.component as usize).step_by(width).sum();
            sums.push((p.name.clone(), sum));
        }
        let read = cache.into_iter().map(|(b, d)| (b, d.len())).collect();
        (sums, read)
    }

    /// The adjoint kernels of one reverse step, in order, each over its forward kernel's
    /// entities.
    pub(super) fn run_reverse_kernels(&mut self) -> Result<(), RunError> {
        let adj = &self.scene.lowered.adjoint;
        for rk in &adj.reverse {
            let range = match rk.range_of {
                Some(f) => self.kernel_range(f),
                None => 0..domain_len(self.scene, adj.module.kernels[rk.kernel].domain),
            };
            self.backend
                .run(rk.kernel, range, &self.uniforms)
                .map_err(RunError)?;
        }
        Ok(())
    }

    /// The adjoint of step `k`: state `k` is current, ∂L/∂(state k+1) in `adj_*_next`.
    fn reverse_step(&mut self, k: u64, dt: f64) -> Result<(), RunError> {
        let adj = &self.scene.lowered.adjoint;
        self.uniforms.set(self.ids.t, k as f64 * dt);
        self.set_sensors()?;
        if adj.needs_forward {
            self.run_force_kernels()?;
        }
        self.run_reverse_kernels()?;
        for s in &adj.state {
            self.backend.swap(s.adj, s.adj_next);
        }
        Ok(())
    }

    /// Norms of ∂L/∂x and ∂L/∂v of state `k`; a non-finite value stops the pass.
    fn adjoint_health(&mut self, k: u64, dt: f64) -> Result<HealthSample, RunError> {
        let read = self.start_health(k);
        self.finish_health(read, dt)
    }

    /// Start reading ∂L/∂x and ∂L/∂v of state `k` back, without waiting (a GPU goes on
    /// reversing steps meanwhile).
    fn start_health(&mut self, k: u64) -> (u64, crate::devices::PendingRead) {
        let adj = &self.scene.lowered.adjoint;
        let bufs: Vec<_> = adj.state.iter().take(2).map(|s| s.adj_next).collect();
        (k, self.backend.read_later(&bufs))
    }

    /// The health sample of a [`Simulation::start_health`].
    fn finish_health(
        &mut self,
        (k, read): (u64, crate::devices::PendingRead),
        dt: f64,
    ) -> Result<HealthSample, RunError> {
        let adj = &self.scene.lowered.adjoint;
        let values = self.backend.collect(read);
        let mut norms = [0.0; 2];
        for (i, (s, g)) in adj.state.iter().zip(&values).enumerate() {
            if let Some(p) = g.iter().position(|x| !x.is_finite()) {
                return Err(RunError(format!(
                    "the gradient became non-finite in the backward pass at step {k} \
                     (t = {:.6} s): ∂loss/∂{} of node {} is {}. The adjoint grew without bound: \
                     differentiate through fewer steps (`truncate = N` in the optimize block), \
                     lower `gradient_scale`, or use f64",
                    k as f64 * dt,
                    s.name,
                    p / 3,
                    g[p]
                )));
            }
            norms[i] = g.iter().map(|x| x * x).sum::<f64>().sqrt();
        }
        Ok(HealthSample {
            step: k,
            adj_x_norm: norms[0],
            adj_v_norm: norms[1],
        })
    }

    /// One forward run and one backward pass: the loss and its gradient with respect to every
    /// param. The backend must have been built from the scene's adjoint module.
    pub fn gradient(
        &mut self,
        dt_override: Option<f64>,
        steps_override: Option<u64>,
        options: &GradOptions,
    ) -> Result<GradientReport, RunError> {
        if self.scene.lowered.statics.is_some() {
            return self.static_gradient(dt_override, steps_override);
        }
        let start = std::time::Instant::now();
        self.upload_fields();
        self.prepare_contact()?;
        let (dt, estimate) = self.resolve_dt(dt_override)?;
        let steps = steps_override.unwrap_or_else(|| self.scene.steps_for(dt));
        self.uniforms.set(self.ids.dt, dt);
        let loss = Loss::build(self.scene, dt, steps)
            .map_err(RunError)?
            .ok_or_else(|| {
                RunError(
                    "the script has no `loss`: there is nothing to differentiate. Add e.g. \
                     `loss = sum(n in tip) (x[n].z - x0[n].z)^2 at end`"
                        .into(),
                )
            })?;
        let adj = &self.scene.lowered.adjoint;
        let n_nodes = self.scene.mesh.nodes.len();
        // An f32 device's states are kept as f32 (exact).
        let single = self.backend.precision() == Precision::F32;
        let value_bytes = if single { 4 } else { 8 };
        let state_bytes = 2 * 3 * n_nodes * value_bytes;
        let reversed = options.truncate.map_or(steps, |t| t.min(steps));
        let schedule = {
            // The current state is held besides the stored ones: a budget that holds fewer than
            // two states cannot be kept (it was exceeded silently, issue 20).
            let budget_states = match options.memory_budget {
                Some(b) => match (b / state_bytes.max(1) as u64) as usize {
                    fits @ 2.. => Some(fits - 1),
                    _ => {
                        return Err(RunError(format!(
                            "a memory budget of {b} bytes (--memory-budget or memory_budget) \
                             holds less than the {} bytes of two states of this scene ({} bytes \
                             each: the current one and one stored); give at least {} bytes",
                            2 * state_bytes,
                            state_bytes,
                            2 * state_bytes
                        )));
                    }
                },
                None => None,
            };
            let s = match options.checkpoint {
                Checkpointing::StoreAll => Schedule::store_all(steps),
                Checkpointing::Periodic(k) => Schedule::periodic(steps, k),
                Checkpointing::Revolve(n) => Schedule::revolve(steps, n),
                Checkpointing::Auto => {
                    // Every state when they fit (the budget, else AUTO_STORE_ALL_BYTES): no
                    // step is recomputed. Otherwise the fewest snapshots within three forward
                    // runs.
                    let cap = budget_states
                        .unwrap_or((AUTO_STORE_ALL_BYTES / state_bytes.max(1) as u64) as usize);
                    if steps < cap as u64 {
                        let mut s = Schedule::store_all(steps);
                        s.kind = "auto: store_all".into();
                        s
                    } else {
                        Schedule::auto(steps, budget_states.unwrap_or(usize::MAX))
                    }
                }
            };
            if let Some(max) = budget_states
                && s.slots > max
            {
                return Err(RunError(format!(
                    "the checkpoint schedule {} stores {} states of {} bytes, more than \
                     memory_budget allows ({max} states); use `checkpoint = auto` or a larger budget",
                    s.kind, s.slots, state_bytes
                )));
            }
            s
        };
        // Every state on the device when the backend can hold them there (a GPU: no state
        // crosses to the host, nothing is recomputed) unless a budget or an explicit schedule
        // says otherwise; else the host store.
        let len = 3 * n_nodes;
        let (schedule, on_device) = match (options.checkpoint, options.memory_budget) {
            (Checkpointing::Auto, None) if steps >= 1 => {
                match self
                    .backend
                    .device_states(steps as usize + 1, len)
                    .map_err(RunError)?
                {
                    Some(bytes) => {
                        let mut s = Schedule::store_all(steps);
                        s.kind = format!(
                            "auto: store_all on the device ({} states, {:.1} MB of the {:.1} MB \
                             allowed)",
                            steps + 1,
                            bytes as f64 / 1e6,
                            crate::devices::gpu::device_state_limit() as f64 / 1e6
                        );
                        (s, true)
                    }
                    None => (schedule, false),
                }
            }
            _ => {
                let on_device = self
                    .backend
                    .device_states(schedule.slots + 1, len)
                    .map_err(RunError)?
                    .is_some();
                (schedule, on_device)
            }
        };
        // Zero the adjoint state and the param accumulators.
        for s in &adj.state {
            let len = domain_len(self.scene, adj.module.buffers[s.adj.0 as usize].domain)
                * adj.module.buffers[s.adj.0 as usize].width as usize;
            self.backend.set(s.adj, &vec![0.0; len]);
            self.backend.set(s.adj_next, &vec![0.0; len]);
        }
        self.zero_gradient_accumulators();

        // The forward run: the schedule's prefix, then the last step.
        let prefix = schedule.forward_prefix();
        let mut slots = StateStore::new(
            if on_device { 0 } else { schedule.slots + 1 },
            3 * n_nodes,
            single,
        );
        // The step each device slot holds.
        let mut device_steps: Vec<Option<u64>> = vec![None; schedule.slots + 1];
        let mut pending_check = None;
        let mut current = 0u64;
        // A blow-up before the first state check is run again from the initial state.
        self.last_good = Some((
            0,
            self.backend.get(self.ids.x),
            self.backend.get(self.ids.v),
        ));
        let mut loss_sum = 0.0;
        let mut direct = BTreeMap::new();
        let mut forward_steps = 0u64;
        let every = self.check_every();
        let mut i = 0;
        while i < prefix {
            let mut action = schedule.actions[i];
            i += 1;
            // On the device, "store state k in slot k, advance to k + 1" over and over (the
            // store-all schedule) runs as the time loop, each step's state copied into its
            // slot before the step.
            let mut store_each = false;
            if on_device
                && action
                    == (Action::Store {
                        slot: current as usize,
                    })
            {
                let run = storing_run(&schedule.actions[i - 1..prefix], current);
                if run > 0 {
                    i += 2 * run as usize - 1;
                    action = Action::Advance { to: current + run };
                    store_each = true;
                }
            }
            match action {
                Action::Advance { to } => {
                    while current < to {
                        // Up to the next step after which the host has work, at once.
                        let end = super::stretch_end(current, to, |j| {
                            j % every == 0 || loss.in_window((j + 1) as f64 * dt, dt)
                        });
                        if store_each {
                            self.advance_storing(current, end - 1, dt)?;
                            for k in current..end {
                                device_steps[k as usize] = Some(k);
                            }
                            self.backend
                                .store_state(end as usize - 1, self.ids.x, self.ids.v)
                                .map_err(RunError)?;
                        } else {
                            self.advance(current, end - 1, dt)?;
                        }
                        forward_steps += end - 1 - current;
                        current = end - 1;
                        if current.is_multiple_of(every) {
                            // The check below reads the J of this step's start state.
                            self.run_diagnostics()?;
                        }
                        self.step(current, dt)?;
                        current += 1;
                        forward_steps += 1;
                        loss_sum += self.loss_term(&loss, current, dt);
                        if current % every == 1 {
                            // Checked when the next check starts: the device runs on.
                            let started = self.start_check(current - 1);
                            if let Some(earlier) = pending_check.replace(started) {
                                self.finish_check(earlier, dt)?;
                            }
                        }
                        self.tick("forward", current, steps)?;
                    }
                }
                Action::Store { slot } => {
                    self.store(&mut slots, &mut device_steps, on_device, slot, current)?
                }
                _ => unreachable!("the prefix only advances and stores"),
            }
        }
        let t_end = steps as f64 * dt;
        let loss_value;
        let final_state;
        if steps > 0 {
            if current + 1 != steps {
                return Err(RunError(format!(
                    "internal error: the checkpoint schedule's forward run ends at step {current}, not {}",
                    steps - 1
                )));
            }
            self.settle_check(&mut pending_check, dt)?;
            let before_last = self.save_state();
            self.run_diagnostics()?;
            self.step(current, dt)?;
            forward_steps += 1;
            self.check_state(current, dt)?;
            final_state = self.save_state();
            let in_window = loss.in_window(t_end, dt) || loss.window == LossWindow::End;
            let value = if in_window {
                self.add_loss_gradient(&loss, t_end, &mut direct)
            } else {
                0.0
            };
            loss_value = match loss.window {
                LossWindow::End => value,
                LossWindow::Over { .. } => loss_sum + value,
            };
            self.load_state(&before_last);
        } else {
            final_state = self.save_state();
            loss_value = self.add_loss_gradient(&loss, 0.0, &mut direct);
        }
        let loss_value =
            super::loss::require_finite(loss_value, loss.window, steps, dt).map_err(RunError)?;
        let forward_seconds = start.elapsed().as_secs_f64();

        // The backward pass.
        let back_start = std::time::Instant::now();
        let stop_at = steps - reversed;
        let mut health = Vec::new();
        if steps > 0 {
            health.push(self.adjoint_health(steps, dt)?);
        }
        let mut done = false;
        let mut initial_state = None;
        let mut pending_health = None;
        let mut i = prefix;
        while i < schedule.actions.len() {
            if done {
                break;
            }
            let mut action = schedule.actions[i];
            i += 1;
            let mut reversed = false;
            // On the device, with no loss terms on the way, "restore state k, reverse step
            // k" down to the next health sample runs as the time loop (the store-all
            // schedule's backward pass).
            if on_device && loss.window == LossWindow::End && !self.has_sensors() {
                let from = match action {
                    Action::Reverse { step } if step == current => Some(step),
                    Action::Restore { slot } if device_steps[slot] == Some(slot as u64) => {
                        Some(slot as u64)
                    }
                    _ => None,
                };
                if let Some(from) = from {
                    let holds = |k: u64| device_steps.get(k as usize) == Some(&Some(k));
                    let (m, taken) =
                        reversing_run(&schedule.actions[i - 1..], from, stop_at, holds);
                    if m > 0 {
                        self.reverse_restoring(from, m, dt)?;
                        for k in from + 1 - m..=from {
                            device_steps[k as usize] = None;
                        }
                        i += taken - 1;
                        current = from + 1 - m;
                        // The last step's bookkeeping below.
                        action = Action::Reverse { step: current };
                        reversed = true;
                    }
                }
            }
            match action {
                Action::Advance { to } => {
                    if current < to {
                        self.advance(current, to, dt)?;
                        forward_steps += to - current;
                        current = to;
                    }
                }
                Action::Store { slot } => {
                    self.store(&mut slots, &mut device_steps, on_device, slot, current)?
                }
                Action::Restore { slot } => {
                    if on_device {
                        current = device_steps[slot]
                            .ok_or_else(|| RunError(format!("slot {slot} was never stored")))?;
                        self.backend
                            .restore_state(slot, self.ids.x, self.ids.v)
                            .map_err(RunError)?;
                    } else {
                        let (k, x, v) = slots
                            .slot(slot)
                            .expect("the schedule restores a stored slot");
                        self.backend.set_from(self.ids.x, x);
                        self.backend.set_from(self.ids.v, v);
                        current = k;
                    }
                }
                Action::Free { slot } => {
                    if on_device {
                        device_steps[slot] = None;
                    } else {
                        slots.free(slot);
                    }
                }
                Action::Reverse { step } => {
                    debug_assert_eq!(current, step);
                    if !reversed {
                        self.reverse_step(step, dt)?;
                    }
                    // Through the sensors the step read at its start state (closed loop).
                    self.add_sensor_adjoint(&mut direct);
                    if step >= 1 && loss.window != LossWindow::End {
                        let t = step as f64 * dt;
                        if loss.in_window(t, dt) {
                            self.add_loss_gradient(&loss, t, &mut direct);
                        }
                    }
                    if step % CHECK_EVERY == 0 || step == stop_at {
                        // Checked when the next sample starts: the device reverses on.
                        let started = self.start_health(step);
                        if let Some(earlier) = pending_health.replace(started) {
                            health.push(self.finish_health(earlier, dt)?);
                        }
                        if step == stop_at
                            && let Some(last) = pending_health.take()
                        {
                            health.push(self.finish_health(last, dt)?);
                        }
                        self.tick("backward", steps - step, steps - stop_at)?;
                    }
                    if step == stop_at {
                        if step == 0 {
                            initial_state = Some((
                                self.backend.get(adj.state[0].adj_next),
                                self.backend.get(adj.state[1].adj_next),
                            ));
                        }
                        done = true;
                    }
                }
            }
        }
        if let Some(last) = pending_health.take() {
            health.push(self.finish_health(last, dt)?);
        }
        let gradients = self.collect_gradients(direct)?;
        let backward_seconds = back_start.elapsed().as_secs_f64();
        // The contact at the final state, as a forward run reports it; the positions the
        // backward pass left are kept (a next gradient starts from them).
        let contact = if self.scene.lowered.contacts.is_some() {
            let left = self.backend.get(self.ids.x);
            self.backend.set(self.ids.x, &final_state.0);
            let report = self.contact_report(steps as f64 * dt);
            self.backend.set(self.ids.x, &left);
            report?
        } else {
            Vec::new()
        };
        Ok(GradientReport {
            summary: RunSummary {
                contact,
                loss: Some(loss_value),
                steps,
                dt,
                dt_stable_estimate: estimate,
                wall_seconds: start.elapsed().as_secs_f64(),
                x: final_state
                    .0
                    .chunks(3)
                    .map(|c| [c[0], c[1], c[2]])
                    .collect(),
                v: final_state
                    .1
                    .chunks(3)
                    .map(|c| [c[0], c[1], c[2]])
                    .collect(),
                solver: None,
            },
            gradients,
            schedule: schedule.kind.clone(),
            stored_states: schedule.slots + 1,
            state_bytes,
            recompute_ratio: forward_steps as f64 / steps.max(1) as f64,
            reversed_steps: reversed,
            forward_seconds,
            backward_seconds,
            health,
            initial_state,
        })
    }
}
