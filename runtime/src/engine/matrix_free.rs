//! Matrix-free linear solves for Newton and its adjoint: GMRES ([`crate::solvers::krylov`]) on
//! products with the tangent K = −∂r/∂x that the compiled scene computes on the device —
//! K·v by the directional-derivative kernels ([`softc_compiler::driver::MatrixFree`]), Kᵀ·v
//! by the adjoint kernels the gradient already uses (∂r/∂x transposed times a residual
//! adjoint) — preconditioned by the inverses of K's 3×3 diagonal blocks (block Jacobi), which
//! the diagonal-block kernels give. No matrix is assembled or factored: memory stays that of
//! the state, and on the GPU backend every product runs as WGSL kernels.
//!
//! Vectors are node-major (3 per node) and zero at fixed nodes, which are thereby eliminated:
//! a direction never moves them, and no product has a component there.

use super::Simulation;
use super::statics::SolverReport;
use crate::devices::Backend;
use crate::solvers::krylov::{KrylovLimits, KrylovStats, gmres};
use softc_compiler::back::Precision;

/// Basis vectors of GMRES before a restart.
const RESTART: usize = 200;
/// Products per linear solve before it gives up (and the solve falls back to the direct
/// solver).
const MAX_KRYLOV_ITERATIONS: usize = 3000;

impl<'s, B: Backend> Simulation<'s, B> {
    /// The finest relative residual a linear solve asks for: products computed in f32 carry
    /// ~1e-7 of round-off, so asking for less than ~1e-6 stalls.
    fn krylov_floor(&self) -> f64 {
        match self.backend.precision() {
            Precision::F64 => 1e-12,
            Precision::F32 => 1e-6,
        }
    }

    /// K·v at the current positions (and uniforms, as the last residual set them).
    /// `sensors`: the closed-loop sensors' derivatives at this state (empty without).
    fn tangent_product(
        &mut self,
        v: &[f64],
        sensors: &[super::sensors::SensorGradient],
    ) -> Result<Vec<f64>, String> {
        let mf = &self.static_kernels().map_err(|e| e.0)?.matrix_free;
        // Closed loop: each sensor moves as Bᵀv, which adds A Bᵀ v to the product.
        if self.has_sensors() {
            let moves: Vec<f64> = (sensors.iter())
                .map(|g| g.x.iter().map(|&(i, d)| d * v[i]).sum())
                .collect();
            self.set_sensor_directions(&moves);
        }
        self.backend.set(mf.direction, v);
        self.run_per_force_kernel(&mf.element_products, &mf.chamber_products)?;
        let nodes = 0..self.scene.mesh.nodes.len();
        self.backend.run(mf.node_product, nodes, &self.uniforms)?;
        let mut kv = self.backend.get(mf.product);
        self.set_sensor_directions(&vec![0.0; self.scene.sensors.len()]);
        self.free_only(&mut kv, -1.0);
        self.device_check()?;
        Ok(kv)
    }

    /// Kᵀ·v at the current state: the adjoint kernels with ∂L/∂residual = v give
    /// (∂r/∂x)ᵀ·v as ∂L/∂x. (They also add to the param accumulators: the caller restores
    /// those.)
    fn tangent_transpose_product(
        &mut self,
        v: &[f64],
        sensors: &[super::sensors::SensorGradient],
    ) -> Result<Vec<f64>, String> {
        let state = &self.scene.lowered.adjoint.state[0];
        self.backend.set(state.adj_next, v);
        self.take_sensor_adjoints();
        self.run_reverse_kernels().map_err(|e| e.0)?;
        let mut ktv = self.backend.get(state.adj);
        self.free_only(&mut ktv, -1.0);
        // Closed loop: Kᵀv − B Aᵀv, Aᵀv = vᵀ ∂r/∂sensor from the sensor accumulators.
        if self.has_sensors() {
            let atv = self.take_sensor_adjoints();
            for (g, c) in sensors.iter().zip(atv) {
                for &(i, d) in &g.x {
                    if !self.scene.fixed[i / 3] {
                        ktv[i] -= d * c;
                    }
                }
            }
        }
        self.device_check()?;
        Ok(ktv)
    }

    fn device_check(&self) -> Result<(), String> {
        match self.backend.device_error() {
            Some(e) => Err(e),
            None => Ok(()),
        }
    }

    /// Scale a node-major vector by `scale` and zero its fixed nodes' entries.
    fn free_only(&self, v: &mut [f64], scale: f64) {
        for (node, &fixed) in self.scene.fixed.iter().enumerate() {
            for d in 0..3 {
                let e = &mut v[3 * node + d];
                *e = if fixed { 0.0 } else { scale * *e };
            }
        }
    }

    /// The inverses of K's 3×3 diagonal blocks (row-major; transposed for a transposed solve),
    /// per node; zero at fixed nodes. A block that cannot be inverted is replaced by the
    /// inverse of its diagonal, or left out.
    fn block_jacobi(&mut self, transpose: bool) -> Result<Vec<[f64; 9]>, String> {
        let statics = self.static_kernels().map_err(|e| e.0)?;
        let mf = &statics.matrix_free;
        self.run_per_force_kernel(&mf.element_blocks, &mf.chamber_blocks)?;
        let nodes = self.scene.mesh.nodes.len();
        let mut blocks = vec![[0.0f64; 9]; nodes];
        let elem = self.backend.get(mf.elem_dblock);
        let order = self.scene.order();
        let mut subtract = |conn: &[u32], nc: usize, dblocks: &[f64]| {
            for (e, corners) in conn.chunks(nc).enumerate() {
                for (c, &node) in corners.iter().enumerate() {
                    for i in 0..9 {
                        blocks[node as usize][i] -= dblocks[(e * nc + c) * 9 + i];
                    }
                }
            }
        };
        subtract(
            &self.scene.elem_conn(),
            order.element_nodes() as usize,
            &elem,
        );
        if let Some(tri_dblock) = mf.tri_dblock {
            let tri = self.backend.get(tri_dblock);
            subtract(
                &self.scene.tri_conn(),
                order.triangle_nodes() as usize,
                &tri,
            );
        }
        if let Some(jacobian) = &statics.node_jacobian {
            self.backend
                .run(jacobian.kernel, 0..nodes, &self.uniforms)?;
            let own = self.backend.get(jacobian.dforce);
            for (n, block) in blocks.iter_mut().enumerate() {
                for i in 0..9 {
                    block[i] -= own[n * 9 + i];
                }
            }
        }
        self.device_check()?;
        Ok(blocks
            .iter()
            .zip(&self.scene.fixed)
            .map(|(b, &fixed)| {
                if fixed {
                    return [0.0; 9];
                }
                let b = if transpose { transposed(b) } else { *b };
                invert(&b).unwrap_or_else(|| {
                    let mut d = [0.0; 9];
                    for i in 0..3 {
                        let v = b[4 * i];
                        d[4 * i] = if v != 0.0 && v.is_finite() {
                            1.0 / v
                        } else {
                            0.0
                        };
                    }
                    d
                })
            })
            .collect())
    }

    /// Solve K x = rhs (or Kᵀ x = rhs) at the current state to `rtol` (never finer than the
    /// precision allows). The adjoint kernels a transposed solve runs leave the param
    /// accumulators as they found them.
    pub(super) fn krylov_solve(
        &mut self,
        report: &mut SolverReport,
        rhs: &[f64],
        transpose: bool,
        rtol: f64,
    ) -> Result<(Vec<f64>, KrylovStats), String> {
        let blocks = self.block_jacobi(transpose)?;
        let precondition = |v: &[f64]| -> Vec<f64> {
            let mut out = vec![0.0; v.len()];
            for (n, m) in blocks.iter().enumerate() {
                for i in 0..3 {
                    out[3 * n + i] = (0..3).map(|j| m[3 * i + j] * v[3 * n + j]).sum();
                }
            }
            out
        };
        let limits = KrylovLimits {
            rtol: rtol.max(self.krylov_floor()),
            restart: RESTART,
            max_iterations: MAX_KRYLOV_ITERATIONS,
        };
        let mut rhs = rhs.to_vec();
        self.free_only(&mut rhs, 1.0);
        // The sensors' derivatives hold for the whole solve (the state does not move).
        let sensors = match self.has_sensors() {
            true => self.sensor_gradients(),
            false => Vec::new(),
        };
        let saved = if transpose {
            Some(self.param_accumulators())
        } else {
            None
        };
        let solved = if transpose {
            gmres(
                &rhs,
                |v| self.tangent_transpose_product(v, &sensors),
                precondition,
                limits,
            )
        } else {
            gmres(
                &rhs,
                |v| self.tangent_product(v, &sensors),
                precondition,
                limits,
            )
        };
        if let Some(saved) = saved {
            for (b, data) in saved {
                self.backend.set(b, &data);
            }
        }
        let (x, stats) = solved?;
        report.krylov_iterations += stats.iterations as u64;
        report.krylov_products += stats.products as u64;
        report.linear_relative_residual = stats.relative_residual;
        Ok((x, stats))
    }

    /// The param accumulators' contents (to restore after products by the adjoint kernels).
    fn param_accumulators(&self) -> Vec<(softc_compiler::ir::BufferId, Vec<f64>)> {
        self.gradient_accumulators()
            .into_iter()
            .map(|b| (b, self.backend.get(b)))
            .collect()
    }
}

fn transposed(b: &[f64; 9]) -> [f64; 9] {
    [b[0], b[3], b[6], b[1], b[4], b[7], b[2], b[5], b[8]]
}

/// The inverse of a 3×3 matrix (row-major), if it is far enough from singular.
fn invert(m: &[f64; 9]) -> Option<[f64; 9]> {
    let c = |i: usize, j: usize| m[3 * i + j];
    let cof = [
        c(1, 1) * c(2, 2) - c(1, 2) * c(2, 1),
        c(0, 2) * c(2, 1) - c(0, 1) * c(2, 2),
        c(0, 1) * c(1, 2) - c(0, 2) * c(1, 1),
        c(1, 2) * c(2, 0) - c(1, 0) * c(2, 2),
        c(0, 0) * c(2, 2) - c(0, 2) * c(2, 0),
        c(0, 2) * c(1, 0) - c(0, 0) * c(1, 2),
        c(1, 0) * c(2, 1) - c(1, 1) * c(2, 0),
        c(0, 1) * c(2, 0) - c(0, 0) * c(2, 1),
        c(0, 0) * c(1, 1) - c(0, 1) * c(1, 0),
    ];
    let det = c(0, 0) * cof[0] + c(0, 1) * cof[3] + c(0, 2) * cof[6];
    let scale = m.iter().fold(0.0f64, |a, v| a.max(v.abs()));
    if !det.is_finite() || det.abs() <= 1e-12 * scale * scale * scale {
        return None;
    }
    Some(cof.map(|v| v / det))
}

#[cfg(test)]
mod tests {
    use super::invert;

    #[test]
    fn inverts_a_block() {
        let m = [4.0, 1.0, 0.5, 0.2, 3.0, -1.0, 0.0, 0.7, 5.0];
        let inv = invert(&m).unwrap();
        for i in 0..3 {
            for j in 0..3 {
                let p: f64 = (0..3).map(|k| m[3 * i + k] * inv[3 * k + j]).sum();
                let want = if i == j { 1.0 } else { 0.0 };
                assert!((p - want).abs() < 1e-14, "{i}{j}: {p}");
            }
        }
        assert!(invert(&[1.0, 2.0, 3.0, 2.0, 4.0, 6.0, 0.0, 0.0, 1.0]).is_none());
    }
}
