//! The stable-step estimate: the largest step of semi-implicit Euler at rest, from the top
//! eigenvalue of M⁻¹K (Lanczos on finite differences of the element forces). `dt = auto` runs
//! at a safety factor times it; a blow-up re-estimates it at the last finite state.

use super::{Backend, RunError, Simulation};
use softc_compiler::back::Precision;

impl<B: Backend> Simulation<'_, B> {
    /// Internal forces per node at the current positions (host gather, for the dt estimate).
    fn internal_forces(&mut self) -> Result<Vec<f64>, RunError> {
        self.run_element_kernels()?;
        let ef = self.backend.get(self.ids.elem_force);
        let n = self.scene.mesh.nodes.len();
        let width = 3 * self.scene.order().element_nodes() as usize;
        let mut f = vec![0.0; 3 * n];
        for (node, fnode) in f.chunks_mut(3).enumerate() {
            for &(e, c) in self.scene.node_elements.of(node) {
                for (d, fd) in fnode.iter_mut().enumerate() {
                    *fd += ef[width * e as usize + 3 * c as usize + d];
                }
            }
        }
        Ok(f)
    }

    /// The largest stable step of semi-implicit Euler at rest, 2/ω_max with ω_max² the largest
    /// eigenvalue of M⁻¹K over the free nodes, with K·u from finite differences of the element
    /// forces.
    pub fn stable_dt_estimate(&mut self) -> Result<f64, RunError> {
        if let Some(e) = self.estimate {
            return Ok(e);
        }
        let e = self.compute_stable_dt()?;
        self.estimate = Some(e);
        Ok(e)
    }

    /// K·q at the rest state `x0` (element forces `f0` there), by a forward difference of
    /// length `scale` along q/‖q‖; zero on fixed nodes.
    fn stiffness_times(
        &mut self,
        x0: &[f64],
        f0: &[f64],
        q: &[f64],
        scale: f64,
    ) -> Result<Vec<f64>, RunError> {
        let norm = q.iter().map(|x| x * x).sum::<f64>().sqrt();
        if norm == 0.0 {
            return Ok(vec![0.0; q.len()]);
        }
        let xs: Vec<f64> = x0
            .iter()
            .zip(q)
            .map(|(a, b)| a + scale * b / norm)
            .collect();
        self.backend.set(self.ids.x, &xs);
        let f1 = self.internal_forces()?;
        let fixed = &self.scene.fixed;
        Ok((0..q.len())
            .map(|i| {
                if fixed[i / 3] {
                    0.0
                } else {
                    -(f1[i] - f0[i]) / scale * norm
                }
            })
            .collect())
    }

    /// ω_max² by the Lanczos method on M⁻¹K (self-adjoint in the mass inner product), with
    /// full reorthogonalization, from a deterministic rough start.
    ///
    /// A Ritz value θ approaches ω_max² from below, so 2/√θ alone overestimates the limit
    /// until it has converged (plain power iteration, used before, was 0.5 % too large on the
    /// 1k benchmark grid after 60 iterations: a run at that step diverged). The estimate uses
    /// θ + ‖r‖ instead, r = M⁻¹K·y − θ·y the residual of the top Ritz pair in the mass norm
    /// (‖r‖ = β_k·|s_k|, no extra force evaluation): some eigenvalue lies within ‖r‖ of θ, and
    /// the top Ritz value approximates the top eigenvalue, so the step errs on the safe side.
    /// Measured against bisected limits in `tests/extremes.rs`. Damping (−β·v) lowers the
    /// limit by about √(1 − β·dt/2), and deformation may stiffen the mesh: `dt = auto` keeps
    /// a safety factor.
    pub(super) fn compute_stable_dt(&mut self) -> Result<f64, RunError> {
        let Some((_, theta, residual)) = self.stiffness_extremes()? else {
            return Ok(f64::INFINITY);
        };
        if !theta.is_finite() || !residual.is_finite() {
            return Err(RunError(format!(
                "the stable-step estimate failed: the stiffness probe gave ω² = {theta:e} \
                 (residual {residual:e}); the rest state's forces are not finite — check the \
                 material constants (a fixed `dt` does not help: the first step would not be \
                 finite either)"
            )));
        }
        let omega2 = theta + residual;
        Ok(if omega2 <= 0.0 {
            f64::INFINITY
        } else {
            2.0 / omega2.sqrt()
        })
    }

    /// The smallest and largest Ritz values of M⁻¹K at the current positions (free nodes) by
    /// [`Self::compute_stable_dt`]'s Lanczos iteration, with the residual of the largest;
    /// `None` when there is nothing free to move.
    pub(super) fn stiffness_extremes(&mut self) -> Result<Option<(f64, f64, f64)>, RunError> {
        const STEPS: usize = 60;
        let n = self.scene.mesh.nodes.len();
        let x0 = self.backend.get(self.ids.x);
        let f0 = self.internal_forces()?;
        let scene = self.scene;
        let mass = &scene.pre.mass;
        let free: Vec<bool> = scene.fixed.iter().map(|f| !f).collect();
        let dot_m = |a: &[f64], b: &[f64]| -> f64 {
            (0..3 * n)
                .filter(|&i| free[i / 3])
                .map(|i| mass[i / 3] * a[i] * b[i])
                .sum()
        };
        // A deterministic, rough start vector.
        let mut q: Vec<f64> = (0..3 * n)
            .map(|i| {
                if free[i / 3] {
                    ((i * 7919 % 1000) as f64 / 1000.0) - 0.5
                } else {
                    0.0
                }
            })
            .collect();
        let scale = scene
            .pre
            .min_altitude
            .iter()
            .copied()
            .fold(f64::INFINITY, f64::min)
            .max(1e-12)
            // The probe must be resolved by the kernels' arithmetic: positions of ~0.1 m carry
            // ~1e-8 m of f32 round-off, so 1e-6 of an element would be noise in f32 (dt = auto
            // then blew up on the GPU). 1e-3 of an element is thousands of f32 ulps, and its
            // linearization error (~1e-3 relative) is far inside dt = auto's safety factor.
            * match self.backend.precision() {
                Precision::F32 => 1e-3,
                _ => 1e-6,
            };
        let norm = dot_m(&q, &q).sqrt();
        let mut basis: Vec<Vec<f64>> = Vec::new();
        let (mut alpha, mut beta) = (Vec::new(), Vec::new());
        if norm > 0.0 {
            q.iter_mut().for_each(|x| *x /= norm);
            for _ in 0..STEPS.min(3 * n) {
                let kq = self.stiffness_times(&x0, &f0, &q, scale)?;
                let mut w: Vec<f64> = (0..3 * n)
                    .map(|i| {
                        if free[i / 3] {
                            kq[i] / mass[i / 3]
                        } else {
                            0.0
                        }
                    })
                    .collect();
                alpha.push(dot_m(&w, &q));
                basis.push(q);
                // Gram–Schmidt against the whole basis, twice ("twice is enough").
                for _ in 0..2 {
                    for b in &basis {
                        let c = dot_m(&w, b);
                        w.iter_mut().zip(b).for_each(|(x, y)| *x -= c * y);
                    }
                }
                let b = dot_m(&w, &w).sqrt();
                beta.push(b);
                let size = alpha.iter().fold(0.0f64, |m, a| m.max(a.abs()));
                if b.is_nan() || b <= 1e-10 * size {
                    // An invariant subspace (few free nodes): the Ritz values are exact.
                    break;
                }
                q = w.into_iter().map(|x| x / b).collect();
            }
        }
        self.backend.set(self.ids.x, &x0);
        self.run_element_kernels()?;
        let k = alpha.len();
        if k == 0 {
            return Ok(None);
        }
        let t = nalgebra::DMatrix::from_fn(k, k, |i, j| {
            if i == j {
                alpha[i]
            } else if i + 1 == j || j + 1 == i {
                beta[i.min(j)]
            } else {
                0.0
            }
        });
        let eig = t.symmetric_eigen();
        let (top, theta) = eig.eigenvalues.iter().copied().enumerate().fold(
            (0, f64::NEG_INFINITY),
            |a, (i, v)| if v > a.1 { (i, v) } else { a },
        );
        let residual = beta[k - 1] * eig.eigenvectors[(k - 1, top)].abs();
        let lowest = eig
            .eigenvalues
            .iter()
            .copied()
            .fold(f64::INFINITY, f64::min);
        Ok(Some((lowest, theta, residual)))
    }
}
