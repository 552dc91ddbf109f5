//! The loss of a run: the compiler's loss kernels ([`LossKernels`], lowered once when the scene
//! is bound to its mesh) evaluated on the host at the end of the run or at every step of its
//! window (thesis eq. 7.1), with the run's `t_end` and `dt`.

use super::scene::Scene;
use crate::devices::Uniforms;
use softc_compiler::driver::{LossArg, LossKernels};
use softc_compiler::ir::{UniformId, interp};
use std::cell::OnceCell;

pub use softc_compiler::driver::LossWindow;

pub struct Loss<'s> {
    kernels: &'s LossKernels,
    t_end: f64,
    dt: f64,
    pub window: LossWindow,
    /// The id of each `LossArg::Uniform` argument's uniform (in argument order), resolved by
    /// name at the first evaluation: a `Loss` serves one run, so one table of uniforms.
    ids: OnceCell<Vec<Option<UniformId>>>,
}

impl<'s> Loss<'s> {
    /// The script's loss for a run of `steps` steps of `dt`; `None` without a loss.
    pub fn build(scene: &'s Scene, dt: f64, steps: u64) -> Result<Option<Loss<'s>>, String> {
        let t_end = steps as f64 * dt;
        let Some(kernels) = scene.loss.as_ref() else {
            return Ok(None);
        };
        let loss = Loss {
            kernels,
            t_end,
            dt,
            window: kernels.window(t_end, dt),
            ids: OnceCell::new(),
        };
        // A window that holds none of the run's states (t = k·dt, k = 1..steps) would sum
        // nothing: a loss and gradient of 0 that look like an answer (issue 31 item 2).
        if let LossWindow::Over { from, to } = loss.window
            && steps >= 1
        {
            let first = ((from - 0.5 * dt) / dt).ceil().max(1.0);
            let last = ((to + 0.5 * dt) / dt).floor().min(steps as f64);
            if !(first <= last
                && (first as u64..=last as u64).any(|k| loss.in_window(k as f64 * dt, dt)))
            {
                return Err(format!(
                    "the loss window [{from:e} s, {to:e} s] holds none of the run's states: they \
                     are at t = {dt:e} s, {:e} s, … {t_end:e} s ({steps} states, {dt:e} s apart); \
                     move the window (`loss = … over [a, b]`) into the run, or run longer",
                    2.0 * dt
                ));
            }
        }
        Ok(Some(loss))
    }

    /// The loss term at one state: positions and velocities (flat, 3 per node), time, and the
    /// other uniforms (params, inputs).
    pub fn eval(&self, scene: &Scene, x: &[f64], v: &[f64], t: f64, uniforms: &Uniforms) -> f64 {
        interp::eval(
            &self.kernels.func,
            &self.arg_values(scene, x, v, t, uniforms),
        )[0]
    }

    /// The loss term and its derivative with respect to each argument ([`Loss::args`]).
    pub fn eval_grad(
        &self,
        scene: &Scene,
        x: &[f64],
        v: &[f64],
        t: f64,
        uniforms: &Uniforms,
    ) -> (f64, Vec<f64>) {
        let out = interp::eval(
            &self.kernels.grad,
            &self.arg_values(scene, x, v, t, uniforms),
        );
        (out[0], out[1..].to_vec())
    }

    /// What each argument reads.
    pub fn args(&self) -> &[LossArg] {
        &self.kernels.args
    }

    fn arg_values(
        &self,
        scene: &Scene,
        x: &[f64],
        v: &[f64],
        t: f64,
        uniforms: &Uniforms,
    ) -> Vec<f64> {
        let ids = self.ids.get_or_init(|| {
            self.kernels
                .args
                .iter()
                .filter_map(|a| match a {
                    LossArg::Uniform(name) => Some(uniforms.id(name)),
                    _ => None,
                })
                .collect()
        });
        let mut ids = ids.iter();
        self.kernels
            .args
            .iter()
            .map(|a| {
                host_arg(a, scene, (x, v), [t, self.t_end, self.dt], |_| {
                    ids.next()
                        .copied()
                        .flatten()
                        .and_then(|id| uniforms.value(id))
                        .unwrap_or(f64::NAN)
                })
            })
            .collect()
    }

    /// Whether the step ending at time `t` contributes (windowed losses).
    pub fn in_window(&self, t: f64, dt: f64) -> bool {
        match self.window {
            LossWindow::End => false,
            // Half a step of slack so a window end that is a multiple of dt is included.
            LossWindow::Over { from, to } => t >= from - 0.5 * dt && t <= to + 0.5 * dt,
        }
    }
}

/// The value of one argument of a host function (the loss, a closed-loop sensor) at the
/// state (`x`, `v`) and `times` = [t, t_end, dt]; `uniform` gives a param's or input's value.
pub(super) fn host_arg(
    a: &LossArg,
    scene: &Scene,
    (x, v): (&[f64], &[f64]),
    [t, t_end, dt]: [f64; 3],
    uniform: impl FnOnce(&str) -> f64,
) -> f64 {
    match a {
        LossArg::X { node, d } => x[3 * node + d],
        LossArg::V { node, d } => v[3 * node + d],
        LossArg::X0 { node, d } => scene.mesh.nodes[*node][*d],
        LossArg::T => t,
        LossArg::TEnd => t_end,
        LossArg::Dt => dt,
        LossArg::Uniform(name) => uniform(name),
    }
}

/// A loss that is not a finite number is an error, not a result: the state was checked finite
/// at every step, so the loss expression itself is undefined there (the run stops with this
/// message instead of reporting `"loss": null` and a gradient of it).
pub fn require_finite(value: f64, window: LossWindow, steps: u64, dt: f64) -> Result<f64, String> {
    if value.is_finite() {
        return Ok(value);
    }
    let what = if value.is_nan() { "NaN" } else { "infinite" };
    let when = match window {
        LossWindow::End => format!(
            "at the end of the run (step {steps}, t = {:e} s)",
            steps as f64 * dt
        ),
        LossWindow::Over { from, to } => {
            format!("summed over its window [{from:e} s, {to:e} s]")
        }
    };
    Err(format!(
        "the loss is {what} {when} while the state is finite: the `loss` expression is not \
         defined there (a logarithm or root of a negative number, a division by zero, an \
         overflow); fix the expression, e.g. take `abs(…)` or add a small offset"
    ))
}
