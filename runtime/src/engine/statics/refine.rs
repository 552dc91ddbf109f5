//! f32 static equilibria refined in f64 (issue 29 item 4): the residual of positions held in
//! f64 is evaluated by the same kernels compiled for f64 on the CPU, and corrected by Newton
//! steps preconditioned by the f32 tangent's factorization.

use super::{Goal, Linear, SolverReport, Tangent};
use crate::devices::Backend;
use crate::engine::{RunError, Simulation};
use softc_compiler::back::Precision;

/// Newton steps with f64 residuals that refine an f32 equilibrium, at most (each at least
/// halves the residual; two or three reach the goal).
const REFINE_STEPS: u64 = 8;

impl<'s, B: Backend> Simulation<'s, B> {
    /// f32 kernels stop Newton at their own round-off: relative residuals of 1e-4–1e-3 at
    /// everyday loads, and no step at all from rest for a load at the round-off of the
    /// internal forces (1 Pa: the rest state, 1/140 of the answer). Iterative refinement:
    /// the residual of positions held in f64 is evaluated by the same kernels compiled for
    /// f64 on the CPU, and Newton steps on the f32 tangent (its last factorization) correct
    /// them towards an f64 solve's tolerance while each at least halves that residual. The
    /// refined positions are stored, rounded to f32, with the f32 forces at them. Returns
    /// the refined state's f64 residual norm and the largest change the rounding made to a
    /// displacement, relative to the largest displacement.
    pub(super) fn refine_in_f64(
        &mut self,
        tangent: &mut Tangent,
        report: &mut SolverReport,
        (t, load): (f64, f64),
        goal: Goal,
    ) -> Result<(f64, f64), RunError> {
        let scene: &'s crate::engine::scene::Scene = self.scene;
        let mut twin = match self.f64_twin.take() {
            Some(twin) => twin,
            None => {
                let cpu =
                    crate::devices::cpu::Cpu::new(&scene.lowered.module, Precision::F64, None)
                        .map_err(|e| RunError(format!("the f64 kernels do not compile: {e}")))?;
                Box::new(Simulation::new(scene, cpu))
            }
        };
        twin.uniforms = self.uniforms.clone();
        twin.upload_fields();
        // The contact nodes' areas, as `prepare_contact` filled them here.
        for c in (self.scene.lowered.contacts.iter()).flat_map(|c| &c.pairs) {
            twin.backend.set(c.area, &self.backend.get(c.area));
        }
        // An f64 solve's goal (goal_at): the stored positions are then the f32 rounding of
        // the equilibrium, as close as f32 holds it.
        let target = (1e-10 * goal.scale).max(1e-12 * self.force_scale());
        let norm = |v: &[f64]| v.iter().map(|x| x * x).sum::<f64>().sqrt();
        let mut x = self.backend.get(self.ids.x);
        let mut best: Option<(Vec<f64>, f64)> = None;
        let outcome = (|| {
            for _ in 0..=REFINE_STEPS {
                twin.backend.set(twin.ids.x, &x);
                let r = twin.residual(t, load)?;
                let n = norm(&r);
                let contracted = best.as_ref().is_none_or(|(_, b)| n <= 0.5 * b);
                if n.is_finite() && best.as_ref().is_none_or(|(_, b)| n < *b) {
                    best = Some((x.clone(), n));
                }
                // Not contracting: the f32 tangent is too far from f64's for more steps to
                // help.
                if !contracted || n <= target {
                    break;
                }
                report.refinement_steps += 1;
                let dx = match f64_newton_step(tangent, report, &mut twin, &x, &r, (t, load))? {
                    Some(dx) => dx,
                    None => {
                        self.newton_direction(tangent, report, &r, false, 1e-8)
                            .map_err(RunError)?
                            .0
                    }
                };
                for (xi, d) in x.iter_mut().zip(&dx) {
                    *xi += d;
                }
            }
            Ok::<(), RunError>(())
        })();
        self.f64_twin = Some(twin);
        outcome?;
        let Some((mut x, r_norm)) = best else {
            return Ok((f64::NAN, f64::NAN));
        };
        if tangent.pattern.rigid() {
            x = tangent.pattern.align(&scene.mesh.nodes, &x);
        }
        self.backend.set(self.ids.x, &x);
        self.residual(t, load)?;
        let stored = self.backend.get(self.ids.x);
        let rest = scene.mesh.nodes.iter().flatten();
        let largest = x
            .iter()
            .zip(rest)
            .fold(0.0f64, |m, (a, b)| m.max((a - b).abs()));
        let rounding = x
            .iter()
            .zip(&stored)
            .fold(0.0f64, |m, (a, b)| m.max((a - b).abs()));
        let round_off = if largest > 0.0 {
            rounding / largest
        } else {
            0.0
        };
        Ok((r_norm, round_off))
    }
}

/// A Newton step of the f64 residual at `x` (whose residual `r` is): GMRES on the f64
/// tangent's products, taken by central differences of the twin's residual (no f64 matrix
/// is assembled), preconditioned by the f32 tangent's factorization. The chord step on the
/// f32 factorization alone stalls at relative residuals of ~5e-6: its round-off is
/// amplified along the soft (bending) modes. A free body's step, as Newton's, has no rigid
/// motion (the pinned support takes no reaction). `None` where there is no factorization to
/// precondition with: the chord step is taken there.
fn f64_newton_step(
    tangent: &Tangent,
    report: &mut SolverReport,
    twin: &mut Simulation<'_, crate::devices::cpu::Cpu>,
    x: &[f64],
    r: &[f64],
    (t, load): (f64, f64),
) -> Result<Option<Vec<f64>>, RunError> {
    let Linear::Direct {
        lu, factored: true, ..
    } = &tangent.linear
    else {
        return Ok(None);
    };
    let pattern = &tangent.pattern;
    let norm = |v: &[f64]| v.iter().map(|a| a * a).sum::<f64>().sqrt();
    let scale = norm(x).max(f64::MIN_POSITIVE);
    let mut residual_at = |v: &[f64], h: f64| -> Result<Vec<f64>, String> {
        let full = pattern.extend(v);
        let shifted: Vec<f64> = x.iter().zip(&full).map(|(a, d)| a + h * d).collect();
        twin.backend.set(twin.ids.x, &shifted);
        Ok(pattern.restrict(&twin.residual(t, load).map_err(|e| e.0)?))
    };
    // K v = −∂r/∂x · v, by central differences with a step of ~1e-6 of the positions'
    // scale (truncation and round-off both ~1e-11 of the product).
    let apply = |v: &[f64]| -> Result<Vec<f64>, String> {
        let h = 1e-6 * scale / norm(v).max(f64::MIN_POSITIVE);
        let ahead = residual_at(v, h)?;
        let behind = residual_at(v, -h)?;
        Ok(ahead
            .iter()
            .zip(&behind)
            .map(|(a, b)| (b - a) / (2.0 * h))
            .collect())
    };
    let precondition = |v: &[f64]| {
        let mut y = v.to_vec();
        lu.solve(&mut y);
        y
    };
    let limits = crate::solvers::krylov::KrylovLimits {
        rtol: 1e-9,
        restart: 20,
        max_iterations: 20,
    };
    let mut r = r.to_vec();
    pattern.remove_rigid_motion(x, &mut r);
    let (dx, stats) =
        crate::solvers::krylov::gmres(&pattern.restrict(&r), apply, precondition, limits)
            .map_err(RunError)?;
    report.krylov_iterations += stats.iterations as u64;
    report.krylov_products += stats.products as u64;
    if stats.relative_residual >= 0.5 {
        return Ok(None);
    }
    let mut dx = pattern.extend(&dx);
    pattern.remove_rigid_motion(x, &mut dx);
    Ok(Some(dx))
}
