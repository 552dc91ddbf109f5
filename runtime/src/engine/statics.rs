//! Quasi-static solves (`integrator = quasi_static`): equilibrium states found directly by
//! Newton's method, and their gradients by the implicit function theorem.
//!
//! The compiler gives a quasi-static scene an `equilibrium` node kernel (the net force on each
//! free node, the residual r(x)) instead of the integrator, force-Jacobian kernels for every
//! force kernel ([`softc_compiler::passes::tangent`]), and the adjoint of x ↦ r. A state is
//! found by Newton's method on the assembled sparse tangent K = −∂r/∂x (fixed nodes
//! eliminated, LU by faer with the symbolic factorization reused), with a backtracking line
//! search on ‖r‖ that refuses steps which invert an element, and load continuation: the
//! `load` uniform scales pressures and gravity from 0 to 1 towards the first state, time
//! advances towards the later ones, in increments that halve after a failed solve and grow
//! after quick ones. Each state starts from the previous one (warm start).
//!
//! Gradients: at an equilibrium r(x*(θ), θ) = 0, so for a loss L(x, θ)
//! dL/dθ = ∂L/∂θ + μᵀ ∂r/∂θ with Kᵀ μ = ∂L/∂x — one transposed solve with the factorized
//! tangent at the converged state, then the adjoint kernels with ∂L/∂residual = μ produce
//! μᵀ ∂r/∂θ for every param kind (uniform params, per-element fields), as in an explicit
//! backward pass. A path of states sums the per-state terms: each state depends on the params
//! only, not on the states before it (elastic equilibria are path-independent).

use super::loss::{Loss, LossWindow};
use super::{RunError, RunSummary, Simulation};
use crate::devices::Backend;
use crate::solvers::amg::MultigridSolver;
use crate::solvers::sparse::{BlockPattern, FreeMotion, SparseSolver};
use crate::text::Sig;
use softc_compiler::back::Precision;
use softc_compiler::driver::LossArg;
use softc_compiler::driver::StaticKernels;
use softc_compiler::ir::ElementOrder;
use std::collections::BTreeMap;
use std::time::Instant;

mod predict;
mod refine;
mod stall;

/// Newton iterations per load increment before it counts as failed.
const MAX_NEWTON: u64 = 40;
/// Damped Newton steps in a row (each along a fresh tangent) that must at least halve the
/// residual, or the load step is abandoned for a smaller one.
const CRAWL_STEPS: u64 = 6;
/// A step that shrinks the residual by less than this factor asks for the tangent of the new
/// state (below it, the last factorization is reused as it is: a chord step costs a solve,
/// not an assembly).
const REFRESH_CONTRACTION: f64 = 0.25;
/// GMRES iterations on a reused factorization (as preconditioner) before a fresh one is
/// made instead ([`Simulation::reuse_factorization`]).
const REUSE_ITERATIONS: usize = 25;
/// A reuse that took more GMRES iterations than this asks for a fresh factorization at the
/// next step (measured on the soft endoscope, 67k dofs: an iteration costs ~1/25 of a
/// factorization; on a 13.7k-dof sphere ~1/35).
const REUSE_WORTH: usize = 10;
/// Continuation increments (as a fraction of a state's load path) below which the solve gives
/// up: no equilibrium beyond.
const MIN_INCREMENT: f64 = 1.0 / 4096.0;
/// `--linear-solver auto` factors tangents up to this many free dofs and solves larger ones by
/// multigrid-preconditioned conjugate gradients (measured, `softc bench --solvers --amg`).
pub const AUTO_MULTIGRID_DOFS: usize = 100_000;

/// As [`AUTO_MULTIGRID_DOFS`] for quadratic elements, whose tangents have twice the nonzeros
/// per dof and fill far more when factored, while the multigrid solver's first coarsening is
/// the linear problem on the same mesh (measured, f64, 2 cores: the verification cuboid's
/// 46.7k dofs in 29 s factored against 11 s by multigrid; 5.7k dofs 2.1 s against 2.3 s).
pub const AUTO_MULTIGRID_DOFS_QUADRATIC: usize = 20_000;

/// As [`AUTO_MULTIGRID_DOFS_QUADRATIC`] for nearly incompressible materials (K/μ at least
/// [`AUTO_DIRECT_BULK_TO_SHEAR`]), where multigrid-preconditioned CG needs many more iterations
/// (measured, quadratic verification cuboid, 46.7k dofs, 3 kPa, 2 cores, wall seconds direct
/// against amg: K/μ = 10: 4.7 / 5.5; 50: 3.6 / 7.1; 100: 5.7 / 11.2; 500: 7.8 / 30.6; 5,000:
/// 31 / no equilibrium after 280 s, crawling at 75 % of the load; direct takes 1.0 GB there,
/// amg 0.4 GB).
pub const AUTO_MULTIGRID_DOFS_NEARLY_INCOMPRESSIBLE: usize = 80_000;
/// The K/μ from which `auto` factors quadratic tangents up to
/// [`AUTO_MULTIGRID_DOFS_NEARLY_INCOMPRESSIBLE`] dofs.
pub const AUTO_DIRECT_BULK_TO_SHEAR: f64 = 50.0;

/// What the solver did, for the JSON summary.
#[derive(Clone, Debug, Default, serde::Serialize)]
pub struct SolverReport {
    pub kind: &'static str,
    /// Equilibrium states solved (the `steps` of the script).
    pub states: u64,
    /// Accepted load increments, over all states.
    pub load_steps: u64,
    /// Increments that failed and were retried smaller.
    pub rejected_load_steps: u64,
    pub newton_iterations: u64,
    /// f32: Newton steps with residuals evaluated in f64 that refined the equilibria.
    pub refinement_steps: u64,
    /// f32: the largest change that storing a refined equilibrium's positions in f32 made
    /// to a displacement, relative to the largest displacement (0 in f64).
    pub position_round_off: f64,
    pub factorizations: u64,
    /// The last factorization: `cholesky` (symmetric positive definite) or `lu`; for `amg`
    /// the Krylov method of the last solve (`cg`, or `gmres` for a non-symmetric tangent).
    pub factorization: &'static str,
    /// ‖residual‖ (N) of the last state, and relative to its applied load (to the internal
    /// forces of a 0.1 % deformation where the loads vanish).
    pub residual_norm: f64,
    pub relative_residual: f64,
    pub converged: bool,
    pub dofs: usize,
    /// The rigid motions the fixed nodes leave free (a static solve), which the solve holds
    /// and poses the answer against: `null` for a body held against all of them.
    pub free_motion: Option<String>,
    /// Which: `all` (no fixed node), `point` or `line`.
    pub free_motion_kind: Option<&'static str>,
    pub nonzeros: usize,
    pub assembly_seconds: f64,
    pub factor_seconds: f64,
    /// How Newton's linear systems were solved: `direct` (assembled, factored), `amg`
    /// (assembled, multigrid-preconditioned CG) or `krylov` (matrix-free GMRES on the
    /// device's tangent products).
    pub linear_solver: &'static str,
    /// GMRES iterations and tangent products, over all solves (`krylov` only).
    pub krylov_iterations: u64,
    pub krylov_products: u64,
    /// The last linear solve's relative residual (`krylov` and `amg`).
    pub linear_relative_residual: f64,
    /// Multigrid hierarchies built (`amg` only), their levels and operator complexity (the
    /// hierarchy's nonzeros over the tangent's).
    pub multigrid_setups: u64,
    pub multigrid_levels: usize,
    pub operator_complexity: f64,
}

/// How a static or implicit solve solves its linear systems ([`Simulation::linear_solver`]).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, clap::ValueEnum)]
pub enum LinearSolver {
    /// Assemble the sparse tangent and factor it (faer), on every backend (the GPU computes
    /// the element Jacobians, the host factors). Measured on the benchmark scenes it is
    /// 200–500× faster than the matrix-free solve (`softc bench --solvers --krylov`), whose
    /// block-Jacobi preconditioner leaves thousands of GMRES iterations per solve.
    Direct,
    /// Conjugate gradients (GMRES where the tangent is not symmetric) on the assembled tangent,
    /// preconditioned by smoothed-aggregation algebraic multigrid with the rigid-body modes as
    /// its near-null space: memory and time about linear in the mesh, for meshes too large to
    /// factor.
    Amg,
    /// `direct` up to [`AUTO_MULTIGRID_DOFS`] free dofs, `amg` beyond (measured: `softc bench
    /// --solvers`); for quadratic elements up to [`AUTO_MULTIGRID_DOFS_QUADRATIC`], or
    /// [`AUTO_MULTIGRID_DOFS_NEARLY_INCOMPRESSIBLE`] for nearly incompressible materials. The
    /// default.
    #[default]
    Auto,
    /// Matrix-free GMRES with a block-Jacobi preconditioner on the backend's tangent products:
    /// no matrix in memory, no Jacobian read back from a GPU. Falls back to the direct solver
    /// when GMRES does not converge; a body with no fixed node needs the direct solver.
    Krylov,
}

impl LinearSolver {
    /// The solver `auto` stands for on a tangent of `dofs` free dofs of elements of `order`
    /// (others: themselves); `bulk_to_shear` gives the materials' largest K/μ, asked for only
    /// where it decides.
    pub fn resolve(
        self,
        dofs: usize,
        order: ElementOrder,
        bulk_to_shear: impl FnOnce() -> f64,
    ) -> LinearSolver {
        let limit = match order {
            ElementOrder::Linear => AUTO_MULTIGRID_DOFS,
            ElementOrder::Quadratic
                if dofs > AUTO_MULTIGRID_DOFS_QUADRATIC
                    && self == LinearSolver::Auto
                    && bulk_to_shear() >= AUTO_DIRECT_BULK_TO_SHEAR =>
            {
                AUTO_MULTIGRID_DOFS_NEARLY_INCOMPRESSIBLE
            }
            ElementOrder::Quadratic => AUTO_MULTIGRID_DOFS_QUADRATIC,
        };
        match self {
            LinearSolver::Auto if dofs > limit => LinearSolver::Amg,
            LinearSolver::Auto => LinearSolver::Direct,
            other => other,
        }
    }
}

/// A finished quasi-static run.
#[derive(Clone, Debug)]
pub struct StaticRun {
    /// Its `solver` field holds what the solver did.
    pub summary: RunSummary,
    /// d loss / d param (SI) when a gradient was asked for.
    pub gradients: Option<BTreeMap<String, f64>>,
}

/// How Newton's linear systems are solved, and the state of that solver.
pub(super) struct Tangent {
    pub(super) pattern: BlockPattern,
    linear: Linear,
}

enum Linear {
    /// The assembled tangent, solved by multigrid-preconditioned Krylov iterations.
    Multigrid {
        solver: Box<MultigridSolver>,
        values: Vec<f64>,
    },
    /// The assembled tangent and its factorization.
    Direct {
        lu: Box<SparseSolver>,
        values: Vec<f64>,
        /// Whether `lu` holds a factorization (of some earlier state of this solve).
        factored: bool,
        /// GMRES iterations of the last solve that reused the factorization
        /// ([`Simulation::reuse_factorization`]): past [`REUSE_WORTH`] the preconditioner has
        /// drifted from the tangent, and the next step factors afresh.
        reused_iterations: usize,
    },
    /// Matrix-free ([`super::matrix_free`]).
    Krylov,
}

impl Tangent {
    /// The tangent's solver for `choice` (resolved: not `auto`).
    pub(super) fn new(
        pattern: BlockPattern,
        precision: Precision,
        choice: LinearSolver,
    ) -> Result<Self, RunError> {
        let linear = match choice {
            LinearSolver::Krylov => Linear::Krylov,
            LinearSolver::Amg => Linear::Multigrid {
                solver: Box::new(
                    MultigridSolver::new(&pattern, symmetry_tolerance(precision))
                        .map_err(RunError)?,
                ),
                values: Vec::new(),
            },
            LinearSolver::Direct | LinearSolver::Auto => {
                Linear::direct(&pattern, precision).map_err(RunError)?
            }
        };
        Ok(Tangent { pattern, linear })
    }
}

impl Linear {
    fn direct(pattern: &BlockPattern, precision: Precision) -> Result<Self, String> {
        Ok(Linear::Direct {
            lu: Box::new(SparseSolver::new(pattern, symmetry_tolerance(precision))?),
            values: Vec::new(),
            factored: false,
            reused_iterations: 0,
        })
    }
}

/// How far from symmetric (relative to the largest entry) a tangent may be and still be
/// treated as symmetric: entries computed in f32 are symmetric only to f32 round-off.
fn symmetry_tolerance(precision: Precision) -> f64 {
    match precision {
        Precision::F64 => 1e-10,
        Precision::F32 => 1e-5,
    }
}

/// The residual a state must reach, and the norm of its loads it is relative to, or of the
/// internal forces of a small deformation where the loads vanish (computed once per state:
/// each is a force evaluation near the rest positions).
#[derive(Clone, Copy)]
struct Goal {
    scale: f64,
    tolerance: f64,
}

/// How one Newton solve ended.
pub(super) enum Newton {
    /// Converged, with the residual's norm (N) at the converged state.
    Converged {
        iterations: u64,
        residual: f64,
    },
    Failed {
        why: String,
    },
}

impl<'s, B: Backend> Simulation<'s, B> {
    /// The scene's solver kernels (borrowed from the scene, not the simulation).
    pub(super) fn static_kernels(&self) -> Result<&'s StaticKernels, RunError> {
        let scene: &'s super::scene::Scene = self.scene;
        scene.lowered.statics.as_ref().ok_or_else(|| {
            RunError("internal error: the scene was not compiled for a quasi-static solve".into())
        })
    }

    /// The residual (node-major, 0 at fixed nodes) at the current positions, time `t` and
    /// load factor `load`; leaves the element forces of this state in place.
    pub(super) fn residual(&mut self, t: f64, load: f64) -> Result<Vec<f64>, RunError> {
        let residual = self.static_kernels()?.residual;
        self.uniforms.set(self.ids.t, t);
        let load_id = self.uniforms.intern("load");
        self.uniforms.set(load_id, load);
        // Closed loop: the load at this iterate reads the sensors there.
        self.set_sensors()?;
        self.run_force_kernels()?;
        let node_kernel = self.scene.material_ranges.len() + self.scene.chamber_ranges.len();
        self.backend
            .run(node_kernel, 0..self.scene.mesh.nodes.len(), &self.uniforms)
            .map_err(RunError)?;
        Ok(self.backend.get(residual))
    }

    /// Run one kernel per material over its elements (`elements`, kernel order) and one per
    /// chamber over its triangles (`chambers`): the kernels derived from the force kernels.
    pub(super) fn run_per_force_kernel(
        &mut self,
        elements: &[usize],
        chambers: &[usize],
    ) -> Result<(), String> {
        for (k, &kernel) in elements.iter().enumerate() {
            let range = self.scene.material_ranges[k].clone();
            self.backend.run(kernel, range, &self.uniforms)?;
        }
        for (c, &kernel) in chambers.iter().enumerate() {
            let range = self.scene.chamber_ranges[c].clone();
            self.backend.run(kernel, range, &self.uniforms)?;
        }
        Ok(())
    }

    /// The first element (kernel order) whose material cannot pass through inversion and
    /// whose volume ratio is not positive, at the current positions.
    fn inverted_element(&mut self) -> Result<Option<usize>, RunError> {
        self.run_diagnostics()?;
        let j = self.backend.get(self.ids.elem_j);
        for (k, range) in self.scene.material_ranges.iter().enumerate() {
            if self.scene.lowered.inversion_safe[k] {
                continue;
            }
            if let Some(e) = range.clone().find(|&e| j[e].is_nan() || j[e] <= 0.0) {
                return Ok(Some(e));
            }
        }
        Ok(None)
    }

    /// Assemble K = −∂r/∂x at the current positions (uniforms as set) and factor it.
    pub(super) fn factor_tangent(
        &mut self,
        tangent: &mut Tangent,
        report: &mut SolverReport,
    ) -> Result<(), String> {
        self.assemble_tangent(tangent, report)?;
        let factor_start = Instant::now();
        let Linear::Direct {
            lu,
            values,
            factored,
            reused_iterations,
        } = &mut tangent.linear
        else {
            return Err("internal error: a matrix-free solve has no tangent to factor".into());
        };
        *factored = false;
        let kind = lu
            .factor(values)
            .map_err(|e| format!("the tangent stiffness is singular ({e})"))?;
        *factored = true;
        report.factorization = kind;
        *reused_iterations = 0;
        report.factor_seconds += factor_start.elapsed().as_secs_f64();
        report.factorizations += 1;
        Ok(())
    }

    /// Assemble K = −∂r/∂x at the current positions (uniforms as set) into the direct
    /// solver's values, leaving its factorization (of an earlier state) as it is.
    fn assemble_tangent(
        &mut self,
        tangent: &mut Tangent,
        report: &mut SolverReport,
    ) -> Result<(), String> {
        let start = Instant::now();
        let statics = self.static_kernels().map_err(|e| e.0)?;
        self.run_per_force_kernel(&statics.element_jacobians, &statics.chamber_jacobians)?;
        let elem = self.backend.get(statics.elem_dforce);
        let tri = statics
            .tri_dforce
            .map(|b| self.backend.get(b))
            .unwrap_or_default();
        let node = match &statics.node_jacobian {
            Some(own) => {
                let nodes = 0..self.scene.mesh.nodes.len();
                self.backend.run(own.kernel, nodes, &self.uniforms)?;
                self.backend.get(own.dforce)
            }
            None => Vec::new(),
        };
        let values = match &mut tangent.linear {
            Linear::Direct { values, .. } | Linear::Multigrid { values, .. } => values,
            Linear::Krylov => {
                return Err(
                    "internal error: a matrix-free solve has no tangent to assemble".into(),
                );
            }
        };
        tangent.pattern.assemble(&elem, &tri, &node, values);
        if let Some(i) = values.iter().position(|v| !v.is_finite()) {
            return Err(format!(
                "the tangent stiffness has a non-finite entry (entry {i})"
            ));
        }
        report.assembly_seconds += start.elapsed().as_secs_f64();
        Ok(())
    }

    /// The solution of K_eff·y = rhs at the current state from an earlier state's
    /// factorization: the tangent is assembled afresh (cheap) and GMRES runs on it with the
    /// old factorization as preconditioner, which leaves a few iterations while the tangent
    /// has changed little. `None` when that does not reach `rtol` within
    /// [`REUSE_ITERATIONS`]: then the caller factors afresh. `rhs` and the result are in the
    /// free dofs; `a`, `b` the closed-loop columns (K_eff = K − A Bᵀ), restricted likewise.
    #[allow(clippy::too_many_arguments)]
    fn reuse_factorization(
        &mut self,
        tangent: &mut Tangent,
        report: &mut SolverReport,
        rhs: &[f64],
        a: &[Vec<f64>],
        b: &[Vec<f64>],
        rtol: f64,
    ) -> Result<Option<Vec<f64>>, String> {
        self.assemble_tangent(tangent, report)?;
        let start = Instant::now();
        let Linear::Direct { lu, values, .. } = &tangent.linear else {
            return Ok(None);
        };
        let pattern = &tangent.pattern;
        let dot = |u: &[f64], v: &[f64]| u.iter().zip(v).map(|(x, y)| x * y).sum::<f64>();
        // K_eff v = K v − A (Bᵀ v).
        let apply = |v: &[f64]| -> Result<Vec<f64>, String> {
            let mut out = pattern.multiply(values, v);
            for (l, r) in a.iter().zip(b) {
                let c = dot(r, v);
                for (o, li) in out.iter_mut().zip(l) {
                    *o -= c * li;
                }
            }
            Ok(out)
        };
        let precondition = |v: &[f64]| -> Vec<f64> {
            super::sensors::woodbury(|y| lu.solve(y), a, b, v).unwrap_or_else(|_| v.to_vec())
        };
        let limits = crate::solvers::krylov::KrylovLimits {
            rtol,
            restart: REUSE_ITERATIONS,
            max_iterations: REUSE_ITERATIONS,
        };
        let (y, stats) = crate::solvers::krylov::gmres(rhs, apply, precondition, limits)?;
        report.krylov_iterations += stats.iterations as u64;
        report.krylov_products += stats.products as u64;
        report.factor_seconds += start.elapsed().as_secs_f64();
        if let Linear::Direct {
            reused_iterations, ..
        } = &mut tangent.linear
        {
            *reused_iterations = stats.iterations;
        }
        Ok(stats.converged.then_some(y))
    }

    /// Newton's method at time `t` and load factor `load` from the current positions. A free
    /// body's equilibrium is then moved rigidly to the pose that best matches its rest shape
    /// (least squares over the nodes): a convention that does not depend on the path Newton
    /// took, and keeps a symmetric body's answer symmetric.
    pub(super) fn newton(
        &mut self,
        tangent: &mut Tangent,
        report: &mut SolverReport,
        t: f64,
        load: f64,
        tolerance: f64,
        floor: f64,
    ) -> Result<Newton, RunError> {
        let outcome = self.newton_iterations(tangent, report, t, load, tolerance, floor)?;
        if tangent.pattern.rigid() && matches!(outcome, Newton::Converged { .. }) {
            let x = self.backend.get(self.ids.x);
            let aligned = tangent.pattern.align(&self.scene.mesh.nodes, &x);
            self.backend.set(self.ids.x, &aligned);
            self.residual(t, load)?;
        }
        Ok(outcome)
    }

    fn newton_iterations(
        &mut self,
        tangent: &mut Tangent,
        report: &mut SolverReport,
        t: f64,
        load: f64,
        tolerance: f64,
        floor: f64,
    ) -> Result<Newton, RunError> {
        let norm = |v: &[f64]| v.iter().map(|x| x * x).sum::<f64>().sqrt();
        self.check_interrupt()?;
        let mut r = self.residual(t, load)?;
        if let Some(e) = self.inverted_element()? {
            return Ok(Newton::Failed {
                why: format!("element {} is inverted", e),
            });
        }
        let mut r_norm = norm(&r);
        if !r_norm.is_finite() {
            return Ok(Newton::Failed {
                why: "the forces are not finite".into(),
            });
        }
        // Whether the factorization is of the current positions; a stale one (an earlier
        // iterate's, or the previous load step's) serves while it still contracts fast.
        let mut fresh = false;
        let mut refresh = false;
        // Consecutive damped steps along fresh tangents, and the residual before the first.
        let mut crawl: (u64, f64) = (0, r_norm);
        for it in 0..MAX_NEWTON {
            if r_norm <= tolerance {
                return Ok(Newton::Converged {
                    iterations: it,
                    residual: r_norm,
                });
            }
            report.newton_iterations += 1;
            // A large tangent's iteration takes seconds: an interrupt stops it here, and the
            // progress says where the solve is (issue 29 item 7).
            self.check_interrupt()?;
            if let Some(p) = &mut self.progress {
                let work = match report.linear_solver {
                    "amg" => format!(
                        "{} multigrid setups and {} CG iterations",
                        report.multigrid_setups, report.krylov_iterations
                    ),
                    "krylov" => format!("{} GMRES iterations", report.krylov_iterations),
                    _ => format!("{} factorizations", report.factorizations),
                };
                p.note(&format!(
                    "at t = {} s, {:.1} % of its loads: Newton iteration {}, residual {} N \
                     (goal {} N), {work} so far",
                    Sig(t),
                    100.0 * load,
                    it + 1,
                    Sig(r_norm),
                    Sig(tolerance),
                ));
            }
            // Inexact Newton: a matrix-free solve need only be as accurate as the step can
            // use, a fraction of the way from here to the tolerance — but no looser than
            // 1e-4, so the state Newton stops at is as close to the equilibrium as a direct
            // solve's (it stops at the first iterate within the tolerance).
            let rtol = (0.01 * tolerance / r_norm).clamp(1e-6, 1e-4);
            let dx = match self.newton_direction(tangent, report, &r, refresh, rtol) {
                Ok((dx, is_fresh)) => {
                    fresh |= is_fresh;
                    dx
                }
                Err(why) => return Ok(Newton::Failed { why }),
            };
            // A Newton step that moves no node by more than round-off of the body's size:
            // converged, whatever the residual's round-off floor is (the net force of large
            // element forces cancels only to their round-off). A stale tangent's step cannot
            // tell: refresh it first.
            if dx.iter().fold(0.0f64, |m, d| m.max(d.abs())) <= self.round_off_length() {
                if fresh {
                    return Ok(Newton::Converged {
                        iterations: it + 1,
                        residual: r_norm,
                    });
                }
                refresh = true;
                continue;
            }
            let x0 = self.backend.get(self.ids.x);
            // Backtracking on ‖r‖; steps that invert an element or make a force non-finite
            // are refused.
            // No step may carry a node into an obstacle (the barrier is infinite there).
            let mut alpha = self.contact_step_limit(&dx)?;
            let mut accepted = None;
            let mut why = String::from("the residual stopped decreasing");
            for _ in 0..12 {
                let x: Vec<f64> = x0.iter().zip(&dx).map(|(a, d)| a + alpha * d).collect();
                self.backend.set(self.ids.x, &x);
                let r_new = self.residual(t, load)?;
                let n_new = norm(&r_new);
                if let Some(e) = self.inverted_element()? {
                    why = format!("every step towards equilibrium inverts element {}", e);
                } else if n_new.is_finite()
                    && (n_new <= (1.0 - 1e-4 * alpha) * r_norm || n_new <= tolerance)
                {
                    accepted = Some((r_new, n_new));
                    break;
                }
                alpha *= 0.5;
            }
            match accepted {
                Some((r_new, n_new)) => {
                    // Newton far from its quadratic region creeps along damped steps (the
                    // soft endoscope at 20 kPa in one load step: 5 % less residual per
                    // iteration, 20 s each, for 40 iterations). A smaller load step is
                    // cheaper: give up once CRAWL_STEPS damped steps in a row have not
                    // halved the residual, and let the continuation cut the step.
                    if alpha < 1.0 && fresh {
                        crawl.0 += 1;
                        if crawl.0 >= CRAWL_STEPS && n_new > 0.5 * crawl.1 {
                            return Ok(Newton::Failed {
                                why: format!(
                                    "{CRAWL_STEPS} damped Newton steps in a row reduced the \
                                     residual only from {} N to {} N",
                                    Sig(crawl.1),
                                    Sig(n_new)
                                ),
                            });
                        }
                    } else {
                        crawl = (0, n_new);
                    }
                    refresh = n_new > REFRESH_CONTRACTION * r_norm;
                    r = r_new;
                    r_norm = n_new;
                    fresh = false;
                }
                None if !fresh => {
                    // The stale tangent's direction does not descend: refresh and retry.
                    self.backend.set(self.ids.x, &x0);
                    self.residual(t, load)?;
                    refresh = true;
                }
                None => {
                    self.backend.set(self.ids.x, &x0);
                    // At the round-off floor no step decreases the residual further.
                    if r_norm <= floor {
                        self.residual(t, load)?;
                        return Ok(Newton::Converged {
                            iterations: it + 1,
                            residual: r_norm,
                        });
                    }
                    return Ok(Newton::Failed { why });
                }
            }
        }
        if r_norm <= tolerance {
            return Ok(Newton::Converged {
                iterations: MAX_NEWTON,
                residual: r_norm,
            });
        }
        Ok(Newton::Failed {
            why: format!("no convergence in {MAX_NEWTON} Newton iterations"),
        })
    }

    /// The Newton step dx with K dx = r at the current positions, and whether it is of the
    /// current tangent: the last factorization's chord step unless `refresh`; else GMRES on
    /// the freshly assembled tangent preconditioned by the last factorization while that
    /// converges in a few iterations, or a fresh factorization; matrix-free, by GMRES to
    /// `rtol`.
    fn newton_direction(
        &mut self,
        tangent: &mut Tangent,
        report: &mut SolverReport,
        r: &[f64],
        refresh: bool,
        rtol: f64,
    ) -> Result<(Vec<f64>, bool), String> {
        if let Linear::Krylov = tangent.linear {
            let (dx, stats) = self.krylov_solve(report, r, false, rtol)?;
            // A direction that reduces the linearized residual is worth a line search.
            if stats.relative_residual < 0.5 {
                return Ok((dx, true));
            }
            self.abandon_iterative(tangent, report)?;
        }
        let (a, b) = match self.has_sensors() {
            true => self.closed_loop_terms()?,
            false => Default::default(),
        };
        let x = match tangent.pattern.rigid() {
            true => self.backend.get(self.ids.x),
            false => Vec::new(),
        };
        // Closed loop: K_eff = K − A Bᵀ (A = ∂r/∂sensor, B = ∂sensor/∂x), by Woodbury.
        let restrict = |v: &Vec<f64>| tangent.pattern.restrict(v);
        let (a, b): (Vec<_>, Vec<_>) = (
            a.iter().map(restrict).collect(),
            b.iter().map(restrict).collect(),
        );
        let mut r = r.to_vec();
        tangent.pattern.remove_rigid_motion(&x, &mut r);
        let rhs = tangent.pattern.restrict(&r);
        if let Linear::Multigrid { .. } = tangent.linear {
            self.assemble_tangent(tangent, report)?;
            let positions = self.backend.get(self.ids.x);
            // A direction that reduces the linearized residual a hundredfold is worth a line
            // search; a tangent multigrid cannot solve that well (indefinite, near a limit
            // point) is factored for the rest of the solve.
            let accuracy = (rtol, 1e-2);
            let solve = (&a[..], &b[..]);
            match self.multigrid_solve(tangent, report, &positions, &rhs, solve, accuracy, false) {
                Ok(dx) => {
                    let mut dx = tangent.pattern.extend(&dx);
                    tangent.pattern.remove_rigid_motion(&x, &mut dx);
                    return Ok((dx, true));
                }
                Err(_) => self.abandon_iterative(tangent, report)?,
            }
        }
        // Reuse while it stays cheap (the preconditioner degrades as the state moves away from
        // the factored one).
        let (factored, reusable) = match tangent.linear {
            Linear::Direct {
                factored,
                reused_iterations,
                ..
            } => (factored, reused_iterations <= REUSE_WORTH),
            Linear::Krylov | Linear::Multigrid { .. } => (false, false),
        };
        // While steps contract well, the last factorization's chord step; when one did not,
        // the Newton step of the current tangent with that factorization as GMRES's
        // preconditioner (no factoring while that converges in a few iterations); else a
        // fresh factorization.
        let reused = match (factored, refresh, reusable) {
            (true, true, true) => self.reuse_factorization(tangent, report, &rhs, &a, &b, rtol)?,
            _ => None,
        };
        let chord = factored && !refresh;
        if reused.is_none() && !chord {
            self.factor_tangent(tangent, report)?;
        }
        let fresh = !chord;
        let dx = match reused {
            Some(dx) => dx,
            None => {
                let Linear::Direct { lu, .. } = &tangent.linear else {
                    unreachable!("checked above");
                };
                super::sensors::woodbury(|y| lu.solve(y), &a, &b, &rhs)?
            }
        };
        let mut dx = tangent.pattern.extend(&dx);
        // A free body: the step without rigid motion (the pinned support's is arbitrary).
        tangent.pattern.remove_rigid_motion(&x, &mut dx);
        Ok((dx, fresh))
    }

    /// K_eff y = rhs (K_effᵀ with `transposed`) by the multigrid solver, on the tangent as
    /// last assembled; `closed_loop` the columns (U, W) of K_eff = K − U Wᵀ (swapped by the
    /// caller for the transpose), restricted to the free dofs. `(rtol, usable)`: the relative
    /// residual aimed at, and the largest one accepted when the Krylov solve stops short.
    #[allow(clippy::too_many_arguments)]
    fn multigrid_solve(
        &mut self,
        tangent: &mut Tangent,
        report: &mut SolverReport,
        positions: &[f64],
        rhs: &[f64],
        closed_loop: (&[Vec<f64>], &[Vec<f64>]),
        (rtol, usable): (f64, f64),
        transposed: bool,
    ) -> Result<Vec<f64>, String> {
        let start = Instant::now();
        let Linear::Multigrid { solver, values } = &mut tangent.linear else {
            return Err("internal error: not a multigrid solve".into());
        };
        let solve = solver.solve(
            &tangent.pattern,
            values,
            positions,
            rhs,
            closed_loop,
            (rtol, usable),
            transposed,
        )?;
        report.factor_seconds += start.elapsed().as_secs_f64();
        report.multigrid_setups += solve.setups as u64;
        report.krylov_iterations += solve.stats.iterations as u64;
        report.krylov_products += solve.stats.products as u64;
        report.linear_relative_residual = solve.stats.relative_residual;
        if let Some((complexity, levels)) = solver.shape() {
            report.multigrid_levels = levels;
            report.operator_complexity = complexity;
        }
        report.factorization = solve.method;
        let usable = solve.stats.relative_residual <= usable; // (false for NaN)
        if !usable {
            return Err(format!(
                "the multigrid-preconditioned {} solve did not converge ({} iterations, \
                 relative residual {}); try `--linear-solver direct`",
                solve.method,
                solve.stats.iterations,
                Sig(solve.stats.relative_residual)
            ));
        }
        Ok(solve.x)
    }

    /// An iterative solve did not converge (block Jacobi too weak for this tangent, or a
    /// tangent multigrid cannot precondition: indefinite near a limit point): the rest of the
    /// solve assembles and factors instead — slower per step, and memory that grows faster
    /// with the mesh, but an answer, where a failed linear solve would read as a failed Newton
    /// step and end the continuation at a load the body can carry.
    fn abandon_iterative(
        &mut self,
        tangent: &mut Tangent,
        report: &mut SolverReport,
    ) -> Result<(), String> {
        report.linear_solver = match tangent.linear {
            Linear::Multigrid { .. } => "amg, then direct",
            _ => "krylov, then direct",
        };
        tangent.linear = Linear::direct(&tangent.pattern, self.backend.precision())?;
        report.nonzeros = tangent.pattern.nnz();
        Ok(())
    }

    /// μ with Kᵀ μ = g at the current state (the converged one: exact gradients need the
    /// tangent where the equilibrium is, not Newton's last factorization).
    pub(super) fn transposed_solve(
        &mut self,
        tangent: &mut Tangent,
        report: &mut SolverReport,
        g: &[f64],
    ) -> Result<Vec<f64>, String> {
        if let Linear::Krylov = tangent.linear {
            // f32 products carry round-off of the order of f32's epsilon times the
            // tangent's condition: GMRES stalls there, and a gradient that accurate is
            // still a descent direction. Accept what it reaches within `usable`.
            let (rtol, usable) = match self.backend.precision() {
                Precision::F64 => (1e-11, 1e-6),
                Precision::F32 => (1e-6, 1e-2),
            };
            let (mu, stats) = self.krylov_solve(report, g, true, rtol)?;
            if stats.converged || stats.relative_residual < usable {
                return Ok(mu);
            }
            self.abandon_iterative(tangent, report)?;
        }
        let (a, b) = match self.has_sensors() {
            true => self.closed_loop_terms()?,
            false => Default::default(),
        };
        let x = match tangent.pattern.rigid() {
            true => self.backend.get(self.ids.x),
            false => Vec::new(),
        };
        // A free body: the sensitivity without the part the pose convention takes (the
        // pinned dofs' adjoint is then 0, as their step is).
        let mut g = g.to_vec();
        tangent
            .pattern
            .pose_free_sensitivity(&self.scene.mesh.nodes, &x, &mut g);
        // Closed loop: K_effᵀ = Kᵀ − B Aᵀ.
        let restrict = |v: &Vec<f64>| tangent.pattern.restrict(v);
        let (a, b): (Vec<_>, Vec<_>) = (
            a.iter().map(restrict).collect(),
            b.iter().map(restrict).collect(),
        );
        let rhs = tangent.pattern.restrict(&g);
        if let Linear::Multigrid { .. } = tangent.linear {
            self.assemble_tangent(tangent, report)?;
            let positions = self.backend.get(self.ids.x);
            // Gradients want the adjoint to about the accuracy of a direct solve; GMRES may
            // stall a little short of the goal at the products' round-off.
            let accuracy = match self.backend.precision() {
                Precision::F64 => (1e-11, 1e-8),
                Precision::F32 => (1e-6, 1e-3),
            };
            let solve = (&b[..], &a[..]);
            match self.multigrid_solve(tangent, report, &positions, &rhs, solve, accuracy, true) {
                Ok(mu) => return Ok(tangent.pattern.extend(&mu)),
                Err(_) => self.abandon_iterative(tangent, report)?,
            }
        }
        // A fresh factorization at this state: reusing Newton's last one as GMRES's
        // preconditioner to the accuracy gradients need cost more than it saved (controller
        // study: 22.1 s against 17.3 s).
        self.factor_tangent(tangent, report)?;
        let Linear::Direct { lu, .. } = &tangent.linear else {
            unreachable!("a direct solver");
        };
        let mu = super::sensors::woodbury(|y| lu.solve_transpose(y), &b, &a, &rhs)?;
        Ok(tangent.pattern.extend(&mu))
    }

    /// A displacement at the round-off level of the positions: the body's size times a few
    /// ulps of the backend's precision.
    fn round_off_length(&self) -> f64 {
        let nodes = &self.scene.mesh.nodes;
        let mut size = 0.0f64;
        for d in 0..3 {
            let (lo, hi) = nodes.iter().fold((f64::MAX, f64::MIN), |(lo, hi), p| {
                (lo.min(p[d]), hi.max(p[d]))
            });
            size = size.max(hi - lo);
        }
        let eps = match self.backend.precision() {
            Precision::F64 => f64::EPSILON,
            Precision::F32 => f32::EPSILON as f64,
        };
        64.0 * eps * size
    }

    /// The norm of the loads (pressure forces and gravity on free nodes) at `t` and `load`:
    /// the residual at the rest positions, where the elastic forces vanish, less that residual
    /// without loads (their round-off).
    fn load_norm(&mut self, t: f64, load: f64) -> Result<f64, RunError> {
        let x = self.backend.get(self.ids.x);
        let rest: Vec<f64> = self.scene.mesh.nodes.iter().flatten().copied().collect();
        self.backend.set(self.ids.x, &rest);
        let loaded = self.residual(t, load);
        let unloaded = self.residual(t, 0.0);
        self.backend.set(self.ids.x, &x);
        // The loads alone: the same internal forces (the round-off of the rest state, in f32
        // not small) are in both residuals, bit for bit, and cancel.
        Ok(loaded?
            .iter()
            .zip(&unloaded?)
            .map(|(a, b)| (a - b) * (a - b))
            .sum::<f64>()
            .sqrt())
    }

    /// [`Simulation::small_strain_forces`] for the material of this solve (computed when
    /// `start_solve` checked it).
    pub(super) fn force_scale(&self) -> f64 {
        self.material_checked
            .as_ref()
            .map_or(0.0, |(_, scale)| *scale)
    }

    /// The norm of the internal forces (N) of a small deformation: a rough displacement of
    /// 0.1 % of the mean edge length on every free node, at the rest positions and no loads.
    /// The force scale of a state whose loads vanish, and of the forces' round-off.
    fn small_strain_forces(&mut self) -> Result<f64, RunError> {
        let mesh = &self.scene.mesh;
        let edge = |a: u32, b: u32| {
            let (p, q) = (mesh.nodes[a as usize], mesh.nodes[b as usize]);
            ((p[0] - q[0]).powi(2) + (p[1] - q[1]).powi(2) + (p[2] - q[2]).powi(2)).sqrt()
        };
        let mean_edge =
            mesh.tets.iter().map(|t| edge(t[0], t[1])).sum::<f64>() / mesh.tets.len().max(1) as f64;
        let fixed = &self.scene.fixed;
        // A deterministic pattern in [-1, 1] (Knuth's multiplicative hash of the dof).
        let rough = |i: usize| ((i as u64 * 2_654_435_761) % 2001) as f64 / 1000.0 - 1.0;
        let probe: Vec<f64> = mesh
            .nodes
            .iter()
            .flatten()
            .enumerate()
            .map(|(i, &x)| {
                if fixed[i / 3] {
                    x
                } else {
                    x + 1e-3 * mean_edge * rough(i)
                }
            })
            .collect();
        let x = self.backend.get(self.ids.x);
        self.backend.set(self.ids.x, &probe);
        let r = self.residual(0.0, 0.0);
        self.backend.set(self.ids.x, &x);
        Ok(r?
            .iter()
            .enumerate()
            .filter(|(i, _)| !fixed[i / 3])
            .map(|(_, v)| v * v)
            .sum::<f64>()
            .sqrt())
    }

    /// Newton at `to` straight from the positions `warm` (the last solve's equilibrium); if it
    /// does not converge there, from rest by continuation as without a warm start.
    fn solve_from(
        &mut self,
        tangent: &mut Tangent,
        report: &mut SolverReport,
        warm: &[f64],
        from: (f64, f64),
        to: (f64, f64),
    ) -> Result<(), RunError> {
        let goal = self.goal_at(to)?;
        self.backend.set(self.ids.x, warm);
        if let Newton::Converged { .. } =
            self.newton(tangent, report, to.0, to.1, goal.tolerance, goal.tolerance)?
        {
            report.load_steps += 1;
            return self.finish_state(tangent, report, to, goal);
        }
        report.rejected_load_steps += 1;
        let rest: Vec<f64> = self.scene.mesh.nodes.iter().flatten().copied().collect();
        self.backend.set(self.ids.x, &rest);
        self.continue_to(tangent, report, from, to, goal)
    }

    /// What a state at (t, load) must reach: a fraction of the norm of its loads.
    fn goal_at(&mut self, (t, load): (f64, f64)) -> Result<Goal, RunError> {
        let rtol = match self.backend.precision() {
            Precision::F64 => 1e-10,
            Precision::F32 => 1e-5,
        };
        let loads = self.load_norm(t, load)?;
        // A state whose loads vanish (its pressures at zero) would be measured against the
        // round-off of the rest forces (a converged state read 1.0): it is measured against
        // the forces of a small deformation instead. Loads that are merely small keep their
        // own norm, so a load below what the precision resolves reads as unresolved.
        let internal = self.force_scale();
        let scale = if loads > 0.0 { loads } else { internal };
        // In f64 no lower than the round-off of the internal forces (positions carry ~1e-14
        // of strain: 1e-11 of the forces of a 0.1 % deformation). A stiff insert (1 GPa in
        // 0.1 MPa rubber) or ν → 0.5 makes those forces large against the loads: Newton chased
        // their round-off and called the first load step a limit point. In f32 Newton's own
        // round-off test decides (its round-off is close to small loads' forces).
        let floor = match self.backend.precision() {
            Precision::F64 => 1e-12 * internal,
            Precision::F32 => 0.0,
        };
        Ok(Goal {
            scale,
            tolerance: (rtol * scale).max(floor).max(f64::MIN_POSITIVE),
        })
    }

    /// Record the converged state's residual (left in place for outputs). An f32 state is
    /// first refined with f64 residuals ([`Simulation::refine_in_f64`]).
    fn finish_state(
        &mut self,
        tangent: &mut Tangent,
        report: &mut SolverReport,
        (t, load): (f64, f64),
        goal: Goal,
    ) -> Result<(), RunError> {
        // f32: the refined state's f64 residual (the refinement leaves the f32 forces in
        // place); f64: this state's own.
        let (r_norm, round_off) = match self.backend.precision() {
            Precision::F32 => self.refine_in_f64(tangent, report, (t, load), goal)?,
            Precision::F64 => {
                let r = self.residual(t, load)?;
                (r.iter().map(|v| v * v).sum::<f64>().sqrt(), 0.0)
            }
        };
        report.position_round_off = report.position_round_off.max(round_off);
        report.residual_norm = r_norm;
        report.relative_residual = if goal.scale > 0.0 {
            r_norm / goal.scale
        } else {
            0.0
        };
        report.converged = match self.backend.precision() {
            // Refined in f64: the stated tolerance met, and displacements that f32 positions
            // hold to better than 1 % (at 1 Pa the rounding is 9 % of them).
            Precision::F32 => r_norm <= goal.tolerance && round_off < 1e-2,
            // Newton converged (by the residual, or by steps at the round-off of positions:
            // the net force of large element forces cancels only to their round-off). A load
            // so small that the round-off is a percent of it or more is not resolved.
            Precision::F64 => report.relative_residual < 1e-2,
        };
        Ok(())
    }

    /// Move the equilibrium from (t0, load0), where the current positions are one, to
    /// (t1, load1) by continuation.
    fn continue_to(
        &mut self,
        tangent: &mut Tangent,
        report: &mut SolverReport,
        from: (f64, f64),
        to: (f64, f64),
        goal: Goal,
    ) -> Result<(), RunError> {
        let tolerance = goal.tolerance;
        let at = |s: f64| (from.0 + s * (to.0 - from.0), from.1 + s * (to.1 - from.1));
        let (mut s, mut ds) = (0.0f64, 1.0f64);
        let mut path = predict::Path::new(self.backend.get(self.ids.x));
        // The equilibrium whose tangent was last asked about a limit point.
        let mut checked: Option<f64> = None;
        while s < 1.0 {
            let s_try = (s + ds).min(1.0);
            let (t, load) = at(s_try);
            self.secant_start(&path, (s, s_try), (t, load))?;
            match self.newton(tangent, report, t, load, tolerance, tolerance)? {
                Newton::Converged { iterations, .. } => {
                    s = s_try;
                    path.reached(s, self.backend.get(self.ids.x));
                    report.load_steps += 1;
                    if iterations <= 4 {
                        ds = (2.0 * ds).min(1.0);
                    }
                }
                Newton::Failed { why, .. } => {
                    self.backend.set(self.ids.x, &path.good);
                    report.rejected_load_steps += 1;
                    ds *= 0.5;
                    // Near a limit point, ask the tangent before bisecting on (once per
                    // equilibrium).
                    let ask = ds < stall::LIMIT_CHECK_INCREMENT && checked != Some(s);
                    if ask {
                        checked = Some(s);
                    }
                    let exhausted = ds < MIN_INCREMENT;
                    let steps = (at(s), at(s_try));
                    if let Some(stalled) =
                        self.stall_verdict(tangent, report, steps, &why, (ask, exhausted))?
                    {
                        return Err(stalled);
                    }
                }
            }
        }
        self.finish_state(tangent, report, to, goal)
    }

    /// A body with no fixed node is in equilibrium only under loads with no net force (a
    /// closed pressurised cavity): refuse others before Newton fails on them. The loads at
    /// rest, where the elastic forces vanish, at the end time.
    fn require_balanced_loads(
        &mut self,
        t_end: f64,
        motion: Option<FreeMotion>,
    ) -> Result<(), RunError> {
        let Some(motion) = motion else {
            return Ok(());
        };
        let rest: Vec<f64> = self.scene.mesh.nodes.iter().flatten().copied().collect();
        self.backend.set(self.ids.x, &rest);
        let r = self.residual(t_end, 1.0)?;
        // The work of the loads along each free motion, against the largest it could be.
        let (mut worst, mut unbalanced) = (0.0f64, Vec::new());
        for mode in motion.modes(&rest) {
            let work: f64 = mode.iter().zip(&r).map(|(m, f)| m * f).sum();
            let scale: f64 = mode.iter().zip(&r).map(|(m, f)| (m * f).abs()).sum();
            unbalanced.push(work);
            worst = worst.max(work.abs() / scale.max(f64::MIN_POSITIVE));
        }
        if worst <= 1e-6 {
            return Ok(());
        }
        let what = match motion {
            FreeMotion::Rigid => {
                let mut net = [0.0f64; 3];
                for f in r.chunks(3) {
                    for d in 0..3 {
                        net[d] += f[d];
                    }
                }
                if net.iter().all(|&c| c == 0.0) {
                    "a net moment".to_string()
                } else {
                    format!(
                        "a net force of [{:.3e}, {:.3e}, {:.3e}] N",
                        net[0], net[1], net[2]
                    )
                }
            }
            _ => "a net moment about it".to_string(),
        };
        Err(RunError(format!(
            "this body is free to move rigidly ({}), and its loads at t = {t_end} s do not \
             balance along that motion: {what} (gravity, or a pressure on an open surface) has \
             no static equilibrium. Fix a region that holds the body (`fix REGION` in the sim \
             block: three or more nodes not on one line), or simulate the motion with \
             `integrator = implicit_euler`",
            free_motion_description(self.scene, Some(motion))
        )))
    }

    /// What a static or implicit run sets up: the spacing `h` of its states, the loss, the
    /// tangent's pattern and solver, the report, the initial state and (for a gradient)
    /// zeroed param accumulators.
    pub(super) fn start_solve(
        &mut self,
        kind: &'static str,
        h: f64,
        steps: u64,
        gradient: bool,
    ) -> Result<(Option<Loss<'s>>, Tangent, SolverReport), RunError> {
        let scene = self.scene;
        self.uniforms.set(self.ids.dt, h);
        let loss = Loss::build(scene, h, steps).map_err(RunError)?;
        if gradient && loss.is_none() {
            return Err(RunError(
                "the script has no `loss`: there is nothing to differentiate".into(),
            ));
        }
        let static_solve = kind == "quasi_static";
        let order = scene.order();
        let mut pattern = BlockPattern::new(
            &scene.fixed,
            (&scene.elem_conn(), order.element_nodes() as usize),
            (&scene.tri_conn(), order.triangle_nodes() as usize),
            static_solve,
            &scene.mesh.nodes,
        )
        .map_err(RunError)?;
        if let Some(q) = &scene.mesh.mid_edges {
            let mut ends = vec![None; scene.mesh.nodes.len()];
            for (corners, mids) in scene.mesh.tets.iter().zip(&q.tets) {
                for (&m, [a, b]) in mids.iter().zip(crate::mesh::model::QUAD_TET_EDGES) {
                    ends[m as usize] = Some([corners[a], corners[b]]);
                }
            }
            pattern = pattern.with_edge_ends(ends);
        }
        let bulk_to_shear = || {
            super::incompressibility::bulk_to_shear_at(scene, Some(&self.uniforms))
                .iter()
                .fold(0.0, |m, b| b.ratio.max(m))
        };
        let choice = match self
            .linear_solver
            .resolve(pattern.size(), order, bulk_to_shear)
        {
            LinearSolver::Krylov if pattern.rigid() => {
                return Err(RunError(format!(
                    "the matrix-free linear solver cannot hold a body's free rigid motions \
                     ({}): use the direct solver (`--linear-solver direct`)",
                    free_motion_description(scene, pattern.free_motion)
                )));
            }
            other => other,
        };
        let report = SolverReport {
            kind,
            states: steps,
            dofs: pattern.n,
            free_motion: pattern
                .free_motion
                .map(|_| free_motion_description(scene, pattern.free_motion)),
            free_motion_kind: pattern.free_motion.map(|m| m.kind()),
            nonzeros: match choice {
                LinearSolver::Krylov => 0,
                _ => pattern.nnz(),
            },
            linear_solver: match choice {
                LinearSolver::Krylov => "krylov",
                LinearSolver::Amg => "amg",
                _ => "direct",
            },
            ..Default::default()
        };
        let tangent = Tangent::new(pattern, self.backend.precision(), choice)?;
        self.reset();
        self.refuse_free_contact(report.free_motion.clone())?;
        self.prepare_contact()?;
        // Non-physical constants (E ≤ 0, ν out of (−1, 0.5)) have no stable equilibrium: a
        // solve returned the rest state (E = 0) or an unstable stationary point with exit 0.
        let material = self.material_values();
        if self
            .material_checked
            .as_ref()
            .is_none_or(|(m, _)| *m != material)
        {
            if let Some(why) = self.material_at_rest()? {
                return Err(RunError(format!(
                    "the {kind} solve cannot start: the {why}"
                )));
            }
            let scale = self.small_strain_forces()?;
            self.material_checked = Some((material, scale));
        }
        if gradient {
            self.zero_gradient_accumulators();
        }
        Ok((loss, tangent, report))
    }

    /// Solve the scene's equilibrium states (`steps` of them, at t_end·k/steps); with
    /// `gradient`, also d loss / d every param.
    pub fn solve_static(
        &mut self,
        gradient: bool,
        dt_override: Option<f64>,
        steps_override: Option<u64>,
    ) -> Result<StaticRun, RunError> {
        let start = Instant::now();
        let scene = self.scene;
        self.upload_fields();
        let t_end = scene.duration.ok_or_else(|| {
            RunError("internal error: a quasi-static scene has no duration".into())
        })?;
        let steps = steps_override.or(scene.steps).unwrap_or(1).max(1);
        let h = t_end / steps as f64;
        // The optimizer passes back the spacing it was told (`time_steps`); anything else is a
        // time step the user asked for, which a static solve does not have.
        if let Some(dt) = dt_override
            && (dt - h).abs() > 1e-12 * h
        {
            return Err(RunError(
                "a quasi-static solve has no time step: `--dt` does not apply (`--steps N` \
                 sets the number of equilibrium states)"
                    .into(),
            ));
        }
        let (loss, mut tangent, mut report) =
            self.start_solve("quasi_static", h, steps, gradient)?;
        self.require_balanced_loads(t_end, tangent.pattern.free_motion)?;
        let mut direct = BTreeMap::new();
        let mut loss_sum = 0.0;
        let mut end_value = None;
        let rest = &scene.mesh.nodes;
        let warm = self.warm_start.take();
        for k in 1..=steps {
            let t = k as f64 * h;
            // The first state's loads grow from rest; a moving obstacle moves from where it
            // was at t = 0 too (the rest state is clear of it only there).
            let contact = scene.lowered.contacts.is_some();
            let from = match k {
                1 if contact => (0.0, 0.0),
                1 => (t, 0.0),
                _ => (t - h, 1.0),
            };
            let solved = match warm
                .as_ref()
                .filter(|w| k == 1 && w.len() == 3 * scene.mesh.nodes.len())
            {
                Some(w) => self.solve_from(&mut tangent, &mut report, w, from, (t, 1.0)),
                None => self.goal_at((t, 1.0)).and_then(|goal| {
                    self.continue_to(&mut tangent, &mut report, from, (t, 1.0), goal)
                }),
            };
            if k == 1 && solved.is_ok() {
                self.warm_start = Some(self.backend.get(self.ids.x));
            }
            if let Err(e) = solved {
                // The last equilibrium is an answer too: write it where outputs were asked.
                if self.vtk.is_some() {
                    self.write_vtk(t)?;
                }
                for c in &self.csv {
                    c.finish().map_err(RunError)?;
                }
                return Err(e);
            }
            self.tick("quasi-static", k, steps)?;
            if !self.csv.is_empty() {
                let x = self.backend.get(self.ids.x);
                for c in &mut self.csv {
                    c.record(k, t, rest, &x);
                }
            }
            if let Some(vtk) = &self.vtk
                && (k % vtk.every().max(1) == 0 || k == steps)
            {
                self.write_vtk(t)?;
            }
            let Some(l) = &loss else { continue };
            let contributes = match l.window {
                LossWindow::End => k == steps,
                LossWindow::Over { .. } => l.in_window(t, h),
            };
            if !contributes {
                continue;
            }
            let value = if gradient {
                self.static_adjoint(&mut tangent, &mut report, l, t, &mut direct)?
            } else {
                let x = self.backend.get(self.ids.x);
                let v = vec![0.0; x.len()];
                l.eval(scene, &x, &v, t, &self.uniforms)
            };
            match l.window {
                LossWindow::End => end_value = Some(value),
                LossWindow::Over { .. } => loss_sum += value,
            }
        }
        for c in &self.csv {
            c.finish().map_err(RunError)?;
        }
        let loss_value = loss
            .as_ref()
            .map(|l| {
                let value = match l.window {
                    LossWindow::End => end_value.unwrap_or(f64::NAN),
                    LossWindow::Over { .. } => loss_sum,
                };
                super::loss::require_finite(value, l.window, steps, h)
            })
            .transpose()
            .map_err(RunError)?;
        let gradients = if gradient {
            Some(self.collect_gradients(direct)?)
        } else {
            None
        };
        let contact = self.contact_report(t_end)?;
        let x = self.backend.get(self.ids.x);
        Ok(StaticRun {
            summary: RunSummary {
                contact,
                loss: loss_value,
                steps,
                dt: h,
                dt_stable_estimate: None,
                wall_seconds: start.elapsed().as_secs_f64(),
                x: x.chunks(3).map(|c| [c[0], c[1], c[2]]).collect(),
                v: vec![[0.0; 3]; x.len() / 3],
                solver: Some(report),
            },
            gradients,
        })
    }

    /// At an equilibrium state (time `t`, full load): the loss term, with μᵀ ∂r/∂θ added to
    /// the param accumulators (Kᵀ μ = ∂L/∂x) and ∂L/∂θ to `direct`.
    fn static_adjoint(
        &mut self,
        tangent: &mut Tangent,
        report: &mut SolverReport,
        l: &Loss,
        t: f64,
        direct: &mut BTreeMap<String, f64>,
    ) -> Result<f64, RunError> {
        let scene = self.scene;
        let adj = &scene.lowered.adjoint;
        let x = self.backend.get(self.ids.x);
        let v = vec![0.0; x.len()];
        let (value, ds) = l.eval_grad(scene, &x, &v, t, &self.uniforms);
        let mut g = vec![0.0; x.len()];
        for (arg, d) in l.args().iter().zip(ds) {
            match arg {
                LossArg::X { node, d: c } => g[3 * node + c] += d,
                LossArg::Uniform(name) if name.starts_with("param.") => {
                    *direct.entry(name.clone()).or_insert(0.0) += d;
                }
                _ => {}
            }
        }
        self.residual(t, 1.0)?;
        let mu = self.transposed_solve(tangent, report, &g).map_err(|e| {
            RunError(format!(
                "the gradient needs the tangent at the equilibrium at t = {t} s: {e}"
            ))
        })?;
        let state = &adj.state[0];
        self.backend.set(state.adj_next, &mu);
        self.take_sensor_adjoints();
        self.run_reverse_kernels()?;
        self.add_sensor_param_gradients(direct);
        Ok(value)
    }

    /// [`Simulation::gradient`] of a quasi-static scene: the states and the loss, and its
    /// gradient by one transposed solve per state that the loss reads.
    pub(super) fn static_gradient(
        &mut self,
        dt_override: Option<f64>,
        steps_override: Option<u64>,
    ) -> Result<super::adjoint::GradientReport, RunError> {
        let start = Instant::now();
        let implicit = self.static_kernels()?.implicit.is_some();
        let run = if implicit {
            self.solve_implicit(true, dt_override, steps_override)?
        } else {
            self.solve_static(true, dt_override, steps_override)?
        };
        let seconds = start.elapsed().as_secs_f64();
        let reversed = run.summary.steps;
        Ok(super::adjoint::GradientReport {
            gradients: run.gradients.unwrap_or_default(),
            schedule: if implicit {
                "every state stored; one transposed solve per step".into()
            } else {
                "implicit function theorem (one transposed solve per state)".into()
            },
            stored_states: 1,
            state_bytes: 3 * self.scene.mesh.nodes.len() * std::mem::size_of::<f64>(),
            recompute_ratio: 1.0,
            reversed_steps: reversed,
            forward_seconds: seconds,
            backward_seconds: 0.0,
            health: Vec::new(),
            initial_state: None,
            summary: run.summary,
        })
    }
}

/// What rigid motion a body is free to make, in a user's terms.
fn free_motion_description(scene: &super::scene::Scene, motion: Option<FreeMotion>) -> String {
    let id = |n: usize| scene.mesh.node_id(n);
    match motion {
        None => "none".into(),
        Some(FreeMotion::Rigid) => "it has no fixed node: three translations and three \
                                   rotations"
            .into(),
        Some(FreeMotion::AboutPoint { node, .. }) => format!(
            "the fixed nodes hold it at one point, node {}: three rotations about it",
            id(node)
        ),
        Some(FreeMotion::AboutLine { ends, .. }) => format!(
            "the fixed nodes lie on one line, through nodes {} and {}: the rotation about it",
            id(ends.0),
            id(ends.1)
        ),
    }
}
