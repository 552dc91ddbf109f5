//! Closed-loop control: pressures and damping that read reductions over node or element sets
//! (`mean(n in tip) x[n].z`). The compiler turns each such reduction into a *sensor*: the
//! kernels read its scalars as uniforms `sensor.I.C`, and a host function (compiled like the
//! loss, with its derivative) evaluates it.
//!
//! - Explicit steps read the sensors at the state the step starts from (the controller
//!   measures, then acts for one step). The reverse step reads ∂L/∂sensor from the adjoint
//!   kernels' sensor accumulators and adds (∂sensor/∂state)ᵀ of it to the state's adjoint —
//!   the chain rule through the measurement.
//! - Static and implicit solves read the sensors at the iterate: the load depends on the
//!   positions, so the tangent is K − A Bᵀ, A = ∂r/∂sensor (the matrix-free product kernels
//!   along a sensor direction) and B = ∂sensor/∂x. Direct solves apply it by the Woodbury
//!   identity on K's factorization, matrix-free ones in the products; the adjoint solve is the
//!   transpose, and ∂sensor/∂param adds μᵀA ∂sensor/∂param to the gradient.

use super::{RunError, Simulation};
use crate::devices::Backend;
use crate::text::Sig;
use softc_compiler::driver::{LossArg, SensorKernels};
use softc_compiler::ir::interp;
use std::collections::BTreeMap;

/// The columns of a low-rank term (one vector per sensor).
pub(super) type Columns = Vec<Vec<f64>>;

/// The derivative of one sensor scalar at a state: sparse in positions and velocities
/// (node-major entries), and its direct derivatives by params.
#[derive(Clone, Debug, Default)]
pub(super) struct SensorGradient {
    pub x: Vec<(usize, f64)>,
    pub v: Vec<(usize, f64)>,
    pub params: Vec<(String, f64)>,
}

impl SensorGradient {
    /// ∂sensor/∂x as a dense node-major vector, zero at fixed nodes.
    fn dense_x(&self, n: usize, fixed: &[bool]) -> Vec<f64> {
        let mut out = vec![0.0; n];
        for &(i, d) in &self.x {
            if !fixed[i / 3] {
                out[i] += d;
            }
        }
        out
    }
}

impl<B: Backend> Simulation<'_, B> {
    /// Whether pressures or damping read sensors (closed-loop control).
    pub(super) fn has_sensors(&self) -> bool {
        !self.scene.sensors.is_empty()
    }

    /// The arguments of a sensor at the state (`x`, `v`) and time `t`.
    fn sensor_args(&self, s: &SensorKernels, x: &[f64], v: &[f64], t: f64) -> Vec<f64> {
        // `t_end` is refused when the scene is bound: a sensor has no run to end.
        let times = [t, f64::NAN, self.uniforms.get(self.ids.dt)];
        (s.args.iter())
            .map(|a| {
                super::loss::host_arg(a, self.scene, (x, v), times, |name| {
                    self.uniforms.named(name).unwrap_or(f64::NAN)
                })
            })
            .collect()
    }

    /// Evaluate every sensor at the current state and time and set its uniform; a value that
    /// is not finite stops the run.
    pub(super) fn set_sensors(&mut self) -> Result<(), RunError> {
        if !self.has_sensors() {
            return Ok(());
        }
        let (x, v) = self.sensed_state();
        let t = self.uniforms.get(self.ids.t);
        for s in &self.scene.sensors {
            let value = interp::eval(&s.func, &self.sensor_args(s, &x, &v, t))[0];
            if !value.is_finite() {
                return Err(RunError(format!(
                    "closed-loop control: the reduction at {} that a pressure or damping reads \
                     is {value} at t = {} s (the state is finite): the expression is not \
                     defined there",
                    self.sensor_location(s),
                    Sig(t)
                )));
            }
            let id = self.uniforms.intern(&s.uniform);
            self.uniforms.set(id, value);
        }
        Ok(())
    }

    /// The positions, and the velocities where a sensor reads them (else empty): read back
    /// from the device at every step of a closed-loop run.
    fn sensed_state(&self) -> (Vec<f64>, Vec<f64>) {
        let v = match self.scene.sensors.iter().any(SensorKernels::reads_velocity) {
            true => self.backend.get(self.ids.v),
            false => Vec::new(),
        };
        (self.backend.get(self.ids.x), v)
    }

    /// `line:column` of a sensor's reduction in the script.
    fn sensor_location(&self, s: &SensorKernels) -> String {
        let upto = &self.scene.source[..s.span.start.min(self.scene.source.len())];
        let line = upto.matches('\n').count() + 1;
        let column = upto.len() - upto.rfind('\n').map_or(0, |i| i + 1) + 1;
        format!("{}:{line}:{column}", self.scene.script.display())
    }

    /// Each sensor's derivative at the current state and time.
    pub(super) fn sensor_gradients(&self) -> Vec<SensorGradient> {
        let (x, v) = self.sensed_state();
        let t = self.uniforms.get(self.ids.t);
        self.scene
            .sensors
            .iter()
            .map(|s| {
                let out = interp::eval(&s.grad, &self.sensor_args(s, &x, &v, t));
                let mut g = SensorGradient::default();
                for (arg, &d) in s.args.iter().zip(&out[1..]) {
                    if d == 0.0 {
                        continue;
                    }
                    match arg {
                        LossArg::X { node, d: c } => g.x.push((3 * node + c, d)),
                        LossArg::V { node, d: c } => g.v.push((3 * node + c, d)),
                        LossArg::Uniform(name) if name.starts_with("param.") => {
                            g.params.push((name.clone(), d))
                        }
                        _ => {}
                    }
                }
                g
            })
            .collect()
    }

    /// ∂L/∂sensor from the adjoint kernels' sensor accumulators (entities summed in order), in
    /// [`Scene::sensors`](super::scene::Scene) order; the accumulators are zeroed.
    pub(super) fn take_sensor_adjoints(&mut self) -> Vec<f64> {
        let mut out = vec![0.0; self.scene.sensors.len()];
        let (sums, read) = self.accumulator_sums(&self.scene.lowered.adjoint.sensors);
        for (name, sum) in sums {
            if let Some(i) = self.scene.sensors.iter().position(|s| s.uniform == name) {
                out[i] += sum;
            }
        }
        for (b, len) in read {
            self.backend.set(b, &vec![0.0; len]);
        }
        out
    }

    /// After reversing the explicit step that starts at the current state: the chain rule
    /// through the sensors it read, ∂L/∂state += (∂sensor/∂state)ᵀ ∂L/∂sensor (into the
    /// adjoint of this state, `adj_*_next` after the swap) and ∂L/∂param into `direct`.
    pub(super) fn add_sensor_adjoint(&mut self, direct: &mut BTreeMap<String, f64>) {
        if !self.has_sensors() {
            return;
        }
        let bars = self.take_sensor_adjoints();
        if bars.iter().all(|&b| b == 0.0) {
            return;
        }
        let grads = self.sensor_gradients();
        let adj = &self.scene.lowered.adjoint;
        let (ax, av) = (adj.state[0].adj_next, adj.state[1].adj_next);
        let mut gx = self.backend.get(ax);
        let mut gv = self.backend.get(av);
        for (bar, g) in bars.iter().zip(&grads) {
            for &(i, d) in &g.x {
                gx[i] += bar * d;
            }
            for &(i, d) in &g.v {
                gv[i] += bar * d;
            }
            for (name, d) in &g.params {
                *direct.entry(name.clone()).or_insert(0.0) += bar * d;
            }
        }
        self.backend.set(ax, &gx);
        self.backend.set(av, &gv);
    }

    /// After the transposed solve and the adjoint kernels of a static or implicit state
    /// (∂L/∂residual = μ): the sensors' direct param derivatives, μᵀ ∂r/∂sensor ·
    /// ∂sensor/∂param, into `direct`.
    pub(super) fn add_sensor_param_gradients(&mut self, direct: &mut BTreeMap<String, f64>) {
        if !self.has_sensors() {
            return;
        }
        let bars = self.take_sensor_adjoints();
        for (bar, g) in bars.iter().zip(self.sensor_gradients()) {
            for (name, d) in g.params {
                *direct.entry(name).or_insert(0.0) += bar * d;
            }
        }
    }

    /// Set the sensor directions of the tangent-product kernels (`dir.sensor.*`).
    pub(super) fn set_sensor_directions(&mut self, values: &[f64]) {
        for (s, &d) in self.scene.sensors.iter().zip(values) {
            let id = self.uniforms.intern(&format!("dir.{}", s.uniform));
            self.uniforms.set(id, d);
        }
    }

    /// The closed-loop part of the tangent at the current iterate: A = ∂r/∂sensor (one
    /// product along each sensor direction, node-major, zero at fixed nodes) and B =
    /// ∂sensor/∂x (dense, zero at fixed nodes).
    pub(super) fn closed_loop_terms(&mut self) -> Result<(Columns, Columns), String> {
        let n = 3 * self.scene.mesh.nodes.len();
        let m = self.scene.sensors.len();
        let mf = &self.static_kernels().map_err(|e| e.0)?.matrix_free;
        self.backend.set(mf.direction, &vec![0.0; n]);
        let mut a = Vec::with_capacity(m);
        for j in 0..m {
            let unit: Vec<f64> = (0..m).map(|i| if i == j { 1.0 } else { 0.0 }).collect();
            self.set_sensor_directions(&unit);
            self.run_per_force_kernel(&mf.element_products, &mf.chamber_products)?;
            let nodes = 0..self.scene.mesh.nodes.len();
            self.backend.run(mf.node_product, nodes, &self.uniforms)?;
            let mut aj = self.backend.get(mf.product);
            for (node, &fixed) in self.scene.fixed.iter().enumerate() {
                if fixed {
                    aj[3 * node..3 * node + 3].fill(0.0);
                }
            }
            a.push(aj);
        }
        self.set_sensor_directions(&vec![0.0; m]);
        let b = (self.sensor_gradients().iter())
            .map(|g| g.dense_x(n, &self.scene.fixed))
            .collect();
        Ok((a, b))
    }
}

/// Solve (M − U Vᵀ) x = rhs given `solve`, which overwrites a vector with M⁻¹ of it (the
/// Woodbury identity: x = y + Z (I − VᵀZ)⁻¹ Vᵀ y with y = M⁻¹ rhs, Z = M⁻¹ U). `u` and `v`
/// hold the m columns of U and V.
pub(super) fn woodbury(
    mut solve: impl FnMut(&mut [f64]),
    u: &[Vec<f64>],
    v: &[Vec<f64>],
    rhs: &[f64],
) -> Result<Vec<f64>, String> {
    let dot = |a: &[f64], b: &[f64]| a.iter().zip(b).map(|(x, y)| x * y).sum::<f64>();
    let mut y = rhs.to_vec();
    solve(&mut y);
    let m = u.len();
    if m == 0 {
        return Ok(y);
    }
    let z: Vec<Vec<f64>> = u
        .iter()
        .map(|uj| {
            let mut zj = uj.clone();
            solve(&mut zj);
            zj
        })
        .collect();
    // S = I − VᵀZ (m × m), c = S⁻¹ Vᵀ y.
    let mut s: Vec<Vec<f64>> = (0..m)
        .map(|i| {
            (0..m)
                .map(|j| (i == j) as u8 as f64 - dot(&v[i], &z[j]))
                .collect()
        })
        .collect();
    let mut c: Vec<f64> = v.iter().map(|vi| dot(vi, &y)).collect();
    crate::solvers::dense::solve(&mut s, &mut c).ok_or_else(|| {
        "the closed-loop tangent is singular: the controller's feedback cancels the stiffness \
         along some displacement (lower the feedback gain)"
            .to_string()
    })?;
    for (zj, cj) in z.iter().zip(&c) {
        for (yi, zi) in y.iter_mut().zip(zj) {
            *yi += cj * zi;
        }
    }
    Ok(y)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn woodbury_solves_a_low_rank_update() {
        // M = diag(2, 3, 4), U = [1, 0, 1]ᵀ, V = [0.5, 1, 0]ᵀ: (M − U Vᵀ) x = r.
        let m = [2.0, 3.0, 4.0];
        let u = vec![vec![1.0, 0.0, 1.0]];
        let v = vec![vec![0.5, 1.0, 0.0]];
        let r = [1.0, -2.0, 0.5];
        let x = woodbury(
            |y: &mut [f64]| y.iter_mut().zip(m).for_each(|(a, d)| *a /= d),
            &u,
            &v,
            &r,
        )
        .unwrap();
        // Check the residual of the dense system.
        let vx: f64 = v[0].iter().zip(&x).map(|(a, b)| a * b).sum();
        for i in 0..3 {
            let lhs = m[i] * x[i] - u[0][i] * vx;
            assert!((lhs - r[i]).abs() < 1e-13, "row {i}: {lhs} vs {}", r[i]);
        }
    }

    #[test]
    fn a_singular_update_is_refused() {
        // M = I, U = V = e1: M − U Vᵀ has a zero row.
        let u = vec![vec![1.0, 0.0]];
        let r = woodbury(|_: &mut [f64]| {}, &u, &u, &[1.0, 1.0]);
        assert!(r.unwrap_err().contains("singular"));
    }
}
