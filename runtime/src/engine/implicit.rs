//! Backward Euler dynamics (`integrator = implicit_euler`): one Newton solve per step on the
//! same tangent and solver as a static equilibrium, at steps far above the explicit limit.
//!
//! The compiler's `implicit_euler` node kernel is the step's residual R(x; x_prev, v_prev)
//! (forces minus inertia and damping; see `lower::scene`), its Jacobian kernels give K plus
//! the inertia diagonal m(1/h² + β/h), and its adjoint carries a vector μ back to the step's
//! inputs. A step: x_prev, v_prev ← the state; x ← x_prev + h·v_prev (the predictor); Newton
//! on R(x) = 0; v ← (x − x_prev)/h.
//!
//! Gradients (every state is stored; implicit runs take few steps): with λx, λv the loss's
//! sensitivities to state k+1, g = λx + λv/h and K_ieᵀ μ = g at x_{k+1}; the adjoint kernels
//! with ∂L/∂R = μ give ∂L/∂x_prev = (∂R/∂x_prev)ᵀμ, ∂L/∂v_prev = (∂R/∂v_prev)ᵀμ and
//! μᵀ ∂R/∂θ into the param accumulators; then λx ← ∂L/∂x_prev − λv/h, λv ← ∂L/∂v_prev.

use super::loss::{Loss, LossWindow};
use super::statics::{Newton, SolverReport, StaticRun, Tangent};
use super::{RunError, RunSummary, Simulation};
use crate::devices::Backend;
use crate::text::Sig;
use softc_compiler::driver::LossArg;
use std::collections::BTreeMap;
use std::time::Instant;

/// Positions and velocities of one state (node-major, 3 per node).
type State = (Vec<f64>, Vec<f64>);

/// A stored state of an implicit run: where the backward pass starts each substep from.
struct Stored {
    state: State,
    /// The substep that ended here (0 for the initial state) and its end time.
    h: f64,
    t: f64,
    /// The step this state ends (`k + 1` for step `k`), when it ends one.
    step: Option<usize>,
}

/// A step whose Newton solve fails is retried as two halves, each again as two, down to
/// 1/`SUBSTEPS` of the step; after a substep succeeds the next one doubles again (up to the
/// whole rest of the step). Positions within a step count in units of 1/`SUBSTEPS`, so
/// substeps end exactly on the step's end.
const SUBSTEPS: u64 = 64;

impl<B: Backend> Simulation<'_, B> {
    /// Run the scene by backward Euler steps; with `gradient`, also d loss / d every param.
    pub fn solve_implicit(
        &mut self,
        gradient: bool,
        dt_override: Option<f64>,
        steps_override: Option<u64>,
    ) -> Result<StaticRun, RunError> {
        let start = Instant::now();
        let scene = self.scene;
        if self.static_kernels()?.implicit.is_none() {
            return Err(RunError(
                "internal error: the scene was not compiled for implicit steps".into(),
            ));
        }
        self.upload_fields();
        let (h, estimate) = self.resolve_dt(dt_override)?;
        let steps = steps_override.unwrap_or_else(|| scene.steps_for(h));
        let load = self.uniforms.intern("load");
        self.uniforms.set(load, 1.0);
        let (loss, mut tangent, mut report) =
            self.start_solve("implicit_euler", h, steps, gradient)?;
        report.converged = true;
        let rtol = match self.backend.precision() {
            softc_compiler::back::Precision::F64 => 1e-10,
            softc_compiler::back::Precision::F32 => 1e-5,
        };
        // The residual a step need not go below in f64: the round-off of the internal forces
        // (f64 positions carry ~1e-14 of strain, 1e-11 of the forces of a 0.1 % deformation).
        // Near a steady state the predictor's residual, which the tolerance is relative to,
        // vanishes, and Newton chased round-off (and reported a failure). In f32 the round-off
        // is so close to the loads of small deformations that Newton's own test (a step that
        // moves nothing beyond round-off) decides.
        let floor = match self.backend.precision() {
            softc_compiler::back::Precision::F64 => 1e-12 * self.force_scale(),
            softc_compiler::back::Precision::F32 => 0.0,
        };
        let rest = &scene.mesh.nodes;
        let mut stored: Vec<Stored> = Vec::new();
        if gradient {
            stored.push(Stored {
                state: (self.backend.get(self.ids.x), self.backend.get(self.ids.v)),
                h: 0.0,
                t: 0.0,
                step: Some(0),
            });
        }
        let mut loss_sum = 0.0;
        for k in 0..steps {
            let (x, v) = (self.backend.get(self.ids.x), self.backend.get(self.ids.v));
            if !self.csv.is_empty() {
                for c in self.csv.iter_mut().filter(|c| k % c.every() == 0) {
                    c.record(k, k as f64 * h, rest, &x);
                }
            }
            if let Some(vtk) = &self.vtk
                && k % vtk.every().max(1) == 0
            {
                self.uniforms.set(self.ids.t, k as f64 * h);
                self.write_vtk(k as f64 * h)?;
            }
            let t = (k + 1) as f64 * h;
            // The step, as one substep or, where Newton fails, several (`SUBSTEPS`).
            let unit = h / SUBSTEPS as f64;
            let (mut at, mut size) = (0u64, SUBSTEPS);
            let (mut xs, mut vs) = (x, v);
            while at < SUBSTEPS {
                let hs = size as f64 * unit;
                let ts = k as f64 * h + (at + size) as f64 * unit;
                let tolerance = (rtol, floor);
                match self.implicit_substep(
                    &mut tangent,
                    &mut report,
                    &xs,
                    &vs,
                    ts,
                    hs,
                    tolerance,
                )? {
                    Ok(next) => {
                        at += size;
                        (xs, vs) = next;
                        if gradient {
                            stored.push(Stored {
                                state: (xs.clone(), vs.clone()),
                                h: hs,
                                t: ts,
                                step: (at == SUBSTEPS).then_some(k as usize + 1),
                            });
                        }
                        // Grow again where the position allows a step twice the size.
                        if at.is_multiple_of(2 * size) && at + 2 * size <= SUBSTEPS {
                            size *= 2;
                        }
                        size = size.min(SUBSTEPS - at);
                    }
                    Err(_) if size > 1 => {
                        report.rejected_load_steps += 1;
                        size /= 2;
                    }
                    Err(why) => {
                        return Err(RunError(format!(
                            "implicit Euler step {} (t = {t} s) found no solution, also in \
                             {SUBSTEPS} substeps of {} s: {why}. Use a smaller dt (now {} s), \
                             or lower the loads",
                            k + 1,
                            Sig(unit),
                            Sig(h)
                        )));
                    }
                }
            }
            self.uniforms.set(self.ids.dt, h);
            let (x1, v1) = (xs, vs);
            if let Some(l) = &loss
                && l.window != LossWindow::End
                && l.in_window(t, h)
            {
                loss_sum += l.eval(scene, &x1, &v1, t, &self.uniforms);
            }
            self.tick("implicit", k + 1, steps)?;
        }
        let (x, v) = (self.backend.get(self.ids.x), self.backend.get(self.ids.v));
        let t_end = steps as f64 * h;
        for c in &mut self.csv {
            c.record(steps, t_end, rest, &x);
        }
        for c in &self.csv {
            c.finish().map_err(RunError)?;
        }
        if self.vtk.is_some() {
            self.write_vtk(t_end)?;
        }
        let loss_value = loss
            .as_ref()
            .map(|l| {
                let value = match l.window {
                    LossWindow::End => l.eval(scene, &x, &v, t_end, &self.uniforms),
                    LossWindow::Over { .. } => loss_sum,
                };
                super::loss::require_finite(value, l.window, steps, h)
            })
            .transpose()
            .map_err(RunError)?;
        let gradients = match (&loss, gradient) {
            (Some(l), true) => {
                Some(self.implicit_backward(&mut tangent, &mut report, l, &stored, h)?)
            }
            _ => None,
        };
        let contact = self.contact_report(t_end)?;
        Ok(StaticRun {
            summary: RunSummary {
                contact,
                loss: loss_value,
                steps,
                dt: h,
                dt_stable_estimate: estimate,
                wall_seconds: start.elapsed().as_secs_f64(),
                x: x.chunks(3).map(|c| [c[0], c[1], c[2]]).collect(),
                v: v.chunks(3).map(|c| [c[0], c[1], c[2]]).collect(),
                solver: Some(report),
            },
            gradients,
        })
    }

    /// One backward Euler substep of `hs` from the state (`x`, `v`) to time `t`, to `rtol` of
    /// its predictor's residual but no lower than `floor` (N): the new state, or why Newton
    /// found none (the positions are then back at `x`). The report keeps
    /// the worst substep's residual, absolute and relative to its predictor's.
    #[allow(clippy::too_many_arguments)]
    fn implicit_substep(
        &mut self,
        tangent: &mut Tangent,
        report: &mut SolverReport,
        x: &[f64],
        v: &[f64],
        t: f64,
        hs: f64,
        (rtol, floor): (f64, f64),
    ) -> Result<Result<State, String>, RunError> {
        let step_bufs = self.static_kernels()?.implicit.as_ref().expect("implicit");
        self.uniforms.set(self.ids.dt, hs);
        self.backend.set(step_bufs.x_prev, x);
        self.backend.set(step_bufs.v_prev, v);
        let predicted: Vec<f64> = x.iter().zip(v).map(|(a, b)| a + hs * b).collect();
        self.backend.set(self.ids.x, &predicted);
        let r0 = self.residual(t, 1.0)?;
        let scale = r0.iter().map(|r| r * r).sum::<f64>().sqrt();
        let tolerance = (rtol * scale).max(floor);
        report.load_steps += 1;
        match self.newton(tangent, report, t, 1.0, tolerance, 1e3 * tolerance)? {
            // The worst substep's residual, absolute and relative to its predictor's (issue
            // 31 item 14: it said 0).
            Newton::Converged { residual, .. } => {
                report.residual_norm = report.residual_norm.max(residual);
                let relative = if scale > 0.0 { residual / scale } else { 0.0 };
                report.relative_residual = report.relative_residual.max(relative);
                let x1 = self.backend.get(self.ids.x);
                let v1: Vec<f64> = x1.iter().zip(x).map(|(a, b)| (a - b) / hs).collect();
                self.backend.set(self.ids.v, &v1);
                Ok(Ok((x1, v1)))
            }
            Newton::Failed { why } => {
                self.backend.set(self.ids.x, x);
                Ok(Err(why))
            }
        }
    }

    /// The backward pass over the stored states of an implicit run, substep by substep (each
    /// with its own size `h`); the loss reads the states that end a step of `h`.
    fn implicit_backward(
        &mut self,
        tangent: &mut Tangent,
        report: &mut SolverReport,
        l: &Loss,
        stored: &[Stored],
        h: f64,
    ) -> Result<BTreeMap<String, f64>, RunError> {
        let scene = self.scene;
        let adj = &scene.lowered.adjoint;
        let step_bufs = self.static_kernels()?.implicit.as_ref().expect("implicit");
        let steps = stored.last().and_then(|s| s.step).unwrap_or(0);
        let n = stored[0].state.0.len();
        let (mut lx, mut lv) = (vec![0.0; n], vec![0.0; n]);
        let mut direct = BTreeMap::new();
        let add_loss = |sim: &Self,
                        at: &Stored,
                        lx: &mut [f64],
                        lv: &mut [f64],
                        direct: &mut BTreeMap<String, f64>| {
            let Some(k) = at.step else { return };
            let t = k as f64 * h;
            let contributes = match l.window {
                LossWindow::End => k == steps,
                LossWindow::Over { .. } => k >= 1 && l.in_window(t, h),
            };
            if !contributes {
                return;
            }
            let (x, v) = &at.state;
            let (_, ds) = l.eval_grad(scene, x, v, t, &sim.uniforms);
            for (arg, d) in l.args().iter().zip(ds) {
                match arg {
                    LossArg::X { node, d: c } => lx[3 * node + c] += d,
                    LossArg::V { node, d: c } => lv[3 * node + c] += d,
                    LossArg::Uniform(name) if name.starts_with("param.") => {
                        *direct.entry(name.clone()).or_insert(0.0) += d;
                    }
                    _ => {}
                }
            }
        };
        let last = stored.len() - 1;
        add_loss(self, &stored[last], &mut lx, &mut lv, &mut direct);
        for j in (0..last).rev() {
            let (from, to) = (&stored[j], &stored[j + 1]);
            let hs = to.h;
            self.uniforms.set(self.ids.dt, hs);
            self.backend.set(self.ids.x, &to.state.0);
            self.backend.set(step_bufs.x_prev, &from.state.0);
            self.backend.set(step_bufs.v_prev, &from.state.1);
            self.residual(to.t, 1.0)?;
            let g: Vec<f64> = lx.iter().zip(&lv).map(|(a, b)| a + b / hs).collect();
            let mu = self
                .transposed_solve(tangent, report, &g)
                .map_err(|e| RunError(format!("the backward pass at t = {} s: {e}", Sig(to.t))))?;
            self.backend.set(adj.state[0].adj_next, &mu);
            self.take_sensor_adjoints();
            self.run_reverse_kernels()?;
            self.add_sensor_param_gradients(&mut direct);
            let ax = self.backend.get(adj.state[1].adj);
            let av = self.backend.get(adj.state[2].adj);
            for i in 0..n {
                // Fixed nodes never move: nothing flows through their positions.
                let free = tangent.pattern.dof(i).is_some();
                lx[i] = if free { ax[i] - lv[i] / hs } else { 0.0 };
                lv[i] = if free { av[i] } else { 0.0 };
            }
            add_loss(self, from, &mut lx, &mut lv, &mut direct);
            if let Some(k) = from.step {
                self.tick("backward", (steps - k) as u64, steps as u64)?;
            }
        }
        self.uniforms.set(self.ids.dt, h);
        self.collect_gradients(direct)
    }
}
