//! Why a static continuation stalled (issue 29 item 1): the tangent at the last equilibrium,
//! against the rest state's, tells a limit point from Newton failing for another reason.

use super::{AUTO_MULTIGRID_DOFS, Linear, SolverReport, Tangent};
use crate::devices::Backend;
use crate::engine::{RunError, Simulation};

/// A tangent left with less than this fraction of its stiffness at rest along the loads
/// (Bergan's current stiffness parameter): it is turning singular, a limit point.
const LIMIT_POINT_STIFFNESS: f64 = 0.05;
/// Below this fraction (and above [`LIMIT_POINT_STIFFNESS`]) the load path may be approaching
/// one (a ballooning wall at 14 %, its Newton stopped by an element turning inside out).
const APPROACHING_LIMIT_STIFFNESS: f64 = 0.5;

/// What the tangent at the last equilibrium of a stalled continuation says about why.
pub(super) enum StiffnessLost {
    /// Not positive definite (or singular): the equilibrium is unstable, past a limit or
    /// bifurcation point; with the number of negative eigenvalues (the inertia of its LBLᵀ
    /// factorization) where known.
    Indefinite(Option<usize>),
    /// Positive definite, with this fraction of its stiffness at rest along the loads.
    Kept(f64),
    /// Not examined: too large to factor again, matrix-free, or not symmetric (an open
    /// pressurised surface: LU does not tell definiteness).
    NotExamined,
}

/// Below this load increment a failed continuation step asks the tangent at the last
/// equilibrium whether it is at a limit point before bisecting further: near one every failed
/// attempt costs Newton's damped iterations (the free sphere past its limit: 12 attempts of 4–7
/// iterations between 1/64 and 1/4096, two thirds of the solve).
pub(super) const LIMIT_CHECK_INCREMENT: f64 = 1.0 / 64.0;

impl StiffnessLost {
    /// Whether the tangent has turned singular (or unstable): the load path cannot go on.
    pub(super) fn at_limit(&self) -> bool {
        match *self {
            StiffnessLost::Indefinite(_) => true,
            StiffnessLost::Kept(kept) => kept < LIMIT_POINT_STIFFNESS,
            StiffnessLost::NotExamined => false,
        }
    }
    pub(super) fn explain(&self) -> String {
        const DYNAMICS: &str = "Lower the loads, or simulate the dynamics with `integrator = \
                                semi_implicit_euler`";
        const NEWTON_FAILS: &str = "an element turning inside out (refine the mesh where it \
                                    deforms most), a material or loads that change abruptly, \
                                    or an ill-conditioned tangent (a stiff insert, ν close to \
                                    0.5: use `precision = f64`)";
        match *self {
            StiffnessLost::Indefinite(negative) => format!(
                "The tangent stiffness there is not positive definite{}: the load path has a \
                 limit point (a snap-through, a ballooning cavity) or a buckling point, which \
                 a pressure-controlled static solve cannot pass. {DYNAMICS}",
                match negative {
                    Some(1) => " (one negative eigenvalue)".to_string(),
                    Some(n) if n > 1 => format!(" ({n} negative eigenvalues)"),
                    _ => String::new(),
                }
            ),
            StiffnessLost::Kept(kept) if kept < LIMIT_POINT_STIFFNESS => format!(
                "The tangent there keeps {:.1} % of its stiffness at rest along the loads: it is \
                 turning singular, a limit point of the load path (a snap-through, a \
                 ballooning cavity) that a pressure-controlled static solve cannot pass. \
                 {DYNAMICS}",
                100.0 * kept
            ),
            StiffnessLost::Kept(kept) if kept < APPROACHING_LIMIT_STIFFNESS => format!(
                "The tangent there keeps {:.0} % of its stiffness at rest along the loads: the \
                 load path may be approaching a limit point (a snap-through, a ballooning \
                 cavity), but Newton failed before it. Likely causes: {NEWTON_FAILS}. \
                 {DYNAMICS}",
                100.0 * kept
            ),
            StiffnessLost::Kept(kept) => format!(
                "This is not a limit point: the tangent there keeps {:.0} % of its stiffness at \
                 rest along the loads. Newton failed for another reason: {NEWTON_FAILS}. \
                 Smaller load increments did not help; `integrator = semi_implicit_euler` does \
                 not need Newton",
                100.0 * kept
            ),
            StiffnessLost::NotExamined => format!(
                "The load path may have a limit point there (a snap-through, a ballooning \
                 cavity), which a pressure-controlled static solve cannot pass, or the loads \
                 are too large for the material. {DYNAMICS}"
            ),
        }
    }
}

impl<'s, B: Backend> Simulation<'s, B> {
    /// After a failed continuation step from the equilibrium at `ok` (time, load factor; the
    /// current positions) towards `bad`: the error that ends the continuation, if it ends —
    /// when asked (`ask`) and the tangent there is at a limit point, or when the increments are
    /// `exhausted`, with what the tangent says.
    pub(super) fn stall_verdict(
        &mut self,
        tangent: &mut Tangent,
        report: &mut SolverReport,
        (ok, bad): ((f64, f64), (f64, f64)),
        why: &str,
        (ask, exhausted): (bool, bool),
    ) -> Result<Option<RunError>, RunError> {
        if !ask && !exhausted {
            return Ok(None);
        }
        // Leave the last equilibrium's forces in place for outputs.
        self.residual(ok.0, ok.1)?;
        let lost = self.stiffness_lost(tangent, report, ok)?;
        self.residual(ok.0, ok.1)?;
        if !exhausted && !lost.at_limit() {
            return Ok(None);
        }
        Ok(Some(RunError(format!(
            "no equilibrium found beyond {:.1} % of the loads at t = {} s (the last \
             equilibrium; at {:.1} % / t = {} s: {why}). {}",
            100.0 * ok.1,
            ok.0,
            100.0 * bad.1,
            bad.0,
            lost.explain()
        ))))
    }

    /// How the tangent's compliance along the loads at the current positions (the last
    /// equilibrium, at `at`) compares with the rest state's: Bergan's current stiffness
    /// parameter, what tells a limit point (the tangent turns singular along the load path:
    /// the compliance along the loads grows without bound) from Newton failing for another
    /// reason. Each tangent is factored by a direct solver of its own; a tangent too large to
    /// factor ([`AUTO_MULTIGRID_DOFS`]) or solved matrix-free is not examined.
    pub(super) fn stiffness_lost(
        &mut self,
        tangent: &mut Tangent,
        report: &mut SolverReport,
        (t, load): (f64, f64),
    ) -> Result<StiffnessLost, RunError> {
        if tangent.pattern.size() > AUTO_MULTIGRID_DOFS || matches!(tangent.linear, Linear::Krylov)
        {
            return Ok(StiffnessLost::NotExamined);
        }
        let direct =
            Linear::direct(&tangent.pattern, self.backend.precision()).map_err(RunError)?;
        let newton = std::mem::replace(&mut tangent.linear, direct);
        let x = self.backend.get(self.ids.x);
        let rest: Vec<f64> = self.scene.mesh.nodes.iter().flatten().copied().collect();
        let mut probe = || -> Result<StiffnessLost, String> {
            let (last, symmetric, negative) = self.load_compliance(tangent, report, (t, load))?;
            self.backend.set(self.ids.x, &rest);
            let (at_rest, ..) = self.load_compliance(tangent, report, (t, 0.0))?;
            Ok(match symmetric {
                false => StiffnessLost::NotExamined,
                true if negative != Some(0) => StiffnessLost::Indefinite(negative),
                true => StiffnessLost::Kept(at_rest / last),
            })
        };
        let lost = probe();
        self.backend.set(self.ids.x, &x);
        tangent.linear = newton;
        // A tangent that does not factor because it is singular is as telling; one that
        // cannot be examined (non-finite entries) tells nothing.
        Ok(match lost {
            Ok(lost) => lost,
            Err(e) if e.contains("singular") => StiffnessLost::Indefinite(None),
            Err(_) => StiffnessLost::NotExamined,
        })
    }

    /// The tangent's compliance along the loads at the current positions, time `t` and load
    /// factor `load` (f·K⁻¹f / f·f, m/N, f the loads at full scale at these positions),
    /// whether the tangent is symmetric, and its number of negative eigenvalues (0: positive
    /// definite; from Cholesky or LBLᵀ, `None` after LU).
    fn load_compliance(
        &mut self,
        tangent: &mut Tangent,
        report: &mut SolverReport,
        (t, load): (f64, f64),
    ) -> Result<(f64, bool, Option<usize>), String> {
        let full = self.residual(t, 1.0).map_err(|e| e.0)?;
        let none = self.residual(t, 0.0).map_err(|e| e.0)?;
        // The tangent of this load factor.
        self.residual(t, load).map_err(|e| e.0)?;
        self.factor_tangent(tangent, report)?;
        let Linear::Direct { lu, values, .. } = &tangent.linear else {
            return Err("internal error: no factored tangent".into());
        };
        let pattern = &tangent.pattern;
        let mut f: Vec<f64> = full.iter().zip(&none).map(|(a, b)| a - b).collect();
        if pattern.rigid() {
            pattern.remove_rigid_motion(&self.backend.get(self.ids.x), &mut f);
        }
        let f = pattern.restrict(&f);
        let mut u = f.clone();
        lu.solve(&mut u);
        let dot = |a: &[f64], b: &[f64]| a.iter().zip(b).map(|(p, q)| p * q).sum::<f64>();
        Ok((
            dot(&f, &u) / dot(&f, &f),
            lu.symmetric(values),
            lu.negative_eigenvalues(),
        ))
    }
}
