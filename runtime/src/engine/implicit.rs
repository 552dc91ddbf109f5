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
use softc_compiler::driver::LossArg;
use std::collections::BTreeMap;
use std::time::Instant;

/// Positions and velocities of one state (node-major, 3 per node).
type State = (Vec<f64>, Vec<f64>);

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
        let step_bufs = self.static_kernels()?.implicit.as_ref().ok_or_else(|| {
            RunError("internal error: the scene was not compiled for implicit steps".into())
        })?;
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
        let rest = &scene.mesh.nodes;
        let mut stored: Vec<State> = Vec::new();
        if gradient {
            stored.push((self.backend.get(self.ids.x), self.backend.get(self.ids.v)));
        }
        let mut loss_sum = 0.0;
        for k in 0..steps {
            let (x, v) = (self.backend.get(self.ids.x), self.backend.get(self.ids.v));
            if !self.csv.is_empty() {
                for c in self.csv.iter_mut().filter(|c| k % c.every == 0) {
                    c.record(k, k as f64 * h, rest, &x);
                }
            }
            if let Some(vtk) = &self.vtk
                && k % vtk.every.max(1) == 0
            {
                self.uniforms.set(self.ids.t, k as f64 * h);
                self.write_vtk(k as f64 * h)?;
            }
            self.backend.set(step_bufs.x_prev, &x);
            self.backend.set(step_bufs.v_prev, &v);
            let predicted: Vec<f64> = x.iter().zip(&v).map(|(a, b)| a + h * b).collect();
            self.backend.set(self.ids.x, &predicted);
            let t = (k + 1) as f64 * h;
            let r0 = self.residual(t, 1.0)?;
            let scale = r0.iter().map(|r| r * r).sum::<f64>().sqrt();
            let tolerance = rtol * scale;
            report.load_steps += 1;
            match self.newton(
                &mut tangent,
                &mut report,
                t,
                1.0,
                tolerance,
                1e3 * tolerance,
            )? {
                // The report gives the worst step's residual, absolute and relative to
                // its predictor's (issue 31 item 14: it said 0).
                Newton::Converged { residual, .. } => {
                    report.residual_norm = report.residual_norm.max(residual);
                    let relative = if scale > 0.0 { residual / scale } else { 0.0 };
                    report.relative_residual = report.relative_residual.max(relative);
                }
                Newton::Failed { why } => {
                    return Err(RunError(format!(
                        "implicit Euler step {} (t = {t} s) found no solution: {why}. Use a \
                         smaller dt (now {h:e} s), or lower the loads",
                        k + 1
                    )));
                }
            }
            let x1 = self.backend.get(self.ids.x);
            let v1: Vec<f64> = x1.iter().zip(&x).map(|(a, b)| (a - b) / h).collect();
            self.backend.set(self.ids.v, &v1);
            if let Some(l) = &loss
                && l.window != LossWindow::End
                && l.in_window(t, h)
            {
                loss_sum += l.eval(scene, &x1, &v1, t, &self.uniforms);
            }
            if gradient {
                stored.push((x1, v1));
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
        Ok(StaticRun {
            summary: RunSummary {
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

    /// The backward pass over the stored states of an implicit run.
    fn implicit_backward(
        &mut self,
        tangent: &mut Tangent,
        report: &mut SolverReport,
        l: &Loss,
        states: &[State],
        h: f64,
    ) -> Result<BTreeMap<String, f64>, RunError> {
        let scene = self.scene;
        let adj = &scene.lowered.adjoint;
        let step_bufs = self.static_kernels()?.implicit.as_ref().expect("implicit");
        let steps = states.len() - 1;
        let n = states[0].0.len();
        let (mut lx, mut lv) = (vec![0.0; n], vec![0.0; n]);
        let mut direct = BTreeMap::new();
        let add_loss = |sim: &Self,
                        k: usize,
                        lx: &mut [f64],
                        lv: &mut [f64],
                        direct: &mut BTreeMap<String, f64>| {
            let t = k as f64 * h;
            let contributes = match l.window {
                LossWindow::End => k == steps,
                LossWindow::Over { .. } => k >= 1 && l.in_window(t, h),
            };
            if !contributes {
                return;
            }
            let (x, v) = &states[k];
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
        add_loss(self, steps, &mut lx, &mut lv, &mut direct);
        for k in (0..steps).rev() {
            let t = (k + 1) as f64 * h;
            self.backend.set(self.ids.x, &states[k + 1].0);
            self.backend.set(step_bufs.x_prev, &states[k].0);
            self.backend.set(step_bufs.v_prev, &states[k].1);
            self.residual(t, 1.0)?;
            let g: Vec<f64> = lx.iter().zip(&lv).map(|(a, b)| a + b / h).collect();
            let mu = self
                .transposed_solve(tangent, report, &g)
                .map_err(|e| RunError(format!("the backward pass at step {}: {e}", k + 1)))?;
            self.backend.set(adj.state[0].adj_next, &mu);
            self.run_reverse_kernels()?;
            let ax = self.backend.get(adj.state[1].adj);
            let av = self.backend.get(adj.state[2].adj);
            for i in 0..n {
                // Fixed nodes never move: nothing flows through their positions.
                let free = tangent.pattern.dof(i).is_some();
                lx[i] = if free { ax[i] - lv[i] / h } else { 0.0 };
                lv[i] = if free { av[i] } else { 0.0 };
            }
            add_loss(self, k, &mut lx, &mut lv, &mut direct);
            self.tick("backward", (steps - k) as u64, steps as u64)?;
        }
        self.collect_gradients(direct)
    }
}
