//! `softc bench --solvers`: the static and implicit solvers on the canonical benchmark scene.
//!
//! For each size the scene's loads at its end time (4000 steps of 40 µs: t = 0.16 s) are
//! solved three ways on the cpu backend in f64: one static equilibrium (`quasi_static`), its
//! gradient (d loss / d p_peak by one transposed solve), and the same 0.16 s of dynamics by 40
//! backward Euler steps of 4 ms (100× the scene's explicit step). With `--krylov` the static
//! solve and the implicit steps run again matrix-free (GMRES on the kernels' tangent products),
//! on the cpu backend so the two linear solvers compare on one device; with `--amg` the static
//! solve, its gradient and the implicit steps run again by multigrid-preconditioned CG. A row reports the wall time (median of `--repeats` after a warm-up), Newton
//! iterations, factorizations or GMRES iterations and where the time goes, the tangent's size,
//! and the growth of peak resident memory during one solve.

use super::{BenchArgs, median, peak_rss, reset_peak_rss, tip_mean_z};
use crate::devices::cpu::Cpu;
use crate::engine::Simulation;
use crate::engine::scene::Scene;
use crate::engine::statics::LinearSolver;
use softc_compiler::Variant;
use softc_compiler::back::Precision;
use std::io::Write;
use std::time::Instant;

#[derive(Debug, Clone, serde::Serialize)]
pub struct SolverRow {
    pub size: String,
    pub solver: String,
    pub elements: usize,
    pub dofs: usize,
    pub nonzeros: usize,
    pub compile_seconds: f64,
    /// Median wall time of one solve (all its states or steps).
    pub wall_seconds: f64,
    pub newton_iterations: u64,
    pub factorizations: u64,
    pub factorization: String,
    /// GMRES iterations (matrix-free rows), CG or GMRES iterations (multigrid rows).
    pub krylov_iterations: u64,
    /// Multigrid hierarchies built (multigrid rows).
    pub multigrid_setups: u64,
    pub assembly_seconds: f64,
    pub factor_seconds: f64,
    pub tip_mean_z: f64,
    /// d loss / d p_peak (the gradient row).
    pub gradient_p_peak: Option<f64>,
    pub peak_rss_bytes: Option<u64>,
}

/// The benchmark scene of `size` as `integrator` with these sim settings.
fn variant(args: &BenchArgs, size: &str, settings: &[(&str, &str)]) -> Result<Scene, String> {
    let path = args.examples.join(format!("benchmark-{size}.soft"));
    let variant = Variant {
        mesh: None,
        sim_settings: settings
            .iter()
            .map(|(k, v)| (k.to_string(), v.to_string()))
            .collect(),
        order: None,
    };
    Scene::load_with(&path, &[], Some(&variant)).map_err(|e| e.0)
}

fn measure(
    args: &BenchArgs,
    size: &str,
    solver: &str,
    scene: &Scene,
    gradient: bool,
    linear: LinearSolver,
) -> Result<SolverRow, String> {
    let module = &scene.lowered.adjoint.module;
    let start = Instant::now();
    Cpu::new(module, Precision::F64, args.threads)?;
    let compile = start.elapsed().as_secs_f64();
    let once = || -> Result<(f64, crate::engine::RunSummary, Option<f64>), String> {
        let cpu = Cpu::new(module, Precision::F64, args.threads)?;
        let mut sim = Simulation::new(scene, cpu);
        sim.linear_solver = linear;
        let start = Instant::now();
        let (summary, g) = if gradient {
            let r = sim
                .gradient(None, None, &Default::default())
                .map_err(|e| e.0)?;
            let g = r.gradients.get("param.p_peak").copied();
            (r.summary, g)
        } else {
            (sim.run(None, None).map_err(|e| e.0)?, None)
        };
        Ok((start.elapsed().as_secs_f64(), summary, g))
    };
    let before = reset_peak_rss();
    once()?;
    let peak = before.and_then(|b| peak_rss().map(|p| p.saturating_sub(b)));
    let mut times = Vec::new();
    let mut last = None;
    for _ in 0..args.repeats.max(1) {
        let (t, s, g) = once()?;
        times.push(t);
        last = Some((s, g));
    }
    let (summary, g) = last.expect("at least one run");
    let report = summary
        .solver
        .clone()
        .ok_or("the solve reported no solver")?;
    Ok(SolverRow {
        size: size.to_string(),
        solver: solver.to_string(),
        elements: scene.mesh.tets.len(),
        dofs: report.dofs,
        nonzeros: report.nonzeros,
        compile_seconds: compile,
        wall_seconds: median(times),
        newton_iterations: report.newton_iterations,
        factorizations: report.factorizations,
        factorization: report.factorization.to_string(),
        krylov_iterations: report.krylov_iterations,
        multigrid_setups: report.multigrid_setups,
        assembly_seconds: report.assembly_seconds,
        factor_seconds: report.factor_seconds,
        tip_mean_z: tip_mean_z(scene, &summary.x)?,
        gradient_p_peak: g,
        peak_rss_bytes: peak,
    })
}

/// Every row of one size.
pub fn bench_size(size: &str, args: &BenchArgs) -> Result<Vec<SolverRow>, String> {
    let statics = variant(
        args,
        size,
        &[
            ("integrator", "quasi_static"),
            ("steps", "1"),
            ("duration", "160 ms"),
        ],
    )?;
    let implicit = variant(
        args,
        size,
        &[
            ("integrator", "implicit_euler"),
            ("dt", "4 ms"),
            ("steps", "40"),
        ],
    )?;
    let direct = LinearSolver::Direct;
    let mut rows = vec![
        measure(args, size, "quasi_static", &statics, false, direct)?,
        measure(args, size, "quasi_static+grad", &statics, true, direct)?,
        measure(args, size, "implicit_euler x40", &implicit, false, direct)?,
    ];
    if args.krylov {
        let krylov = LinearSolver::Krylov;
        rows.push(measure(
            args,
            size,
            "quasi_static krylov",
            &statics,
            false,
            krylov,
        )?);
        rows.push(measure(
            args,
            size,
            "implicit x40 krylov",
            &implicit,
            false,
            krylov,
        )?);
    }
    if args.amg {
        let amg = LinearSolver::Amg;
        rows.extend([
            measure(args, size, "quasi_static amg", &statics, false, amg)?,
            measure(args, size, "quasi_static+grad amg", &statics, true, amg)?,
            measure(args, size, "implicit x40 amg", &implicit, false, amg)?,
        ]);
    }
    Ok(rows)
}

pub fn run(args: &BenchArgs, sizes: &[&str], out: &mut dyn Write) -> Result<(), String> {
    let mut rows = Vec::new();
    for size in sizes {
        rows.extend(bench_size(size, args).map_err(|e| format!("benchmark-{size}: {e}"))?);
    }
    let _ = writeln!(
        out,
        "{:<5} {:<21} {:>7} {:>7} {:>9} {:>9} {:>7} {:>7} {:>7} {:>9} {:>9} {:>9} {:>14} {:>10}",
        "size",
        "solver",
        "tets",
        "dofs",
        "nonzeros",
        "wall_s",
        "newton",
        "factor",
        "krylov",
        "assemb_s",
        "factor_s",
        "compile_s",
        "tip_mean_z_m",
        "rss_MB"
    );
    for r in &rows {
        let _ = writeln!(
            out,
            "{:<5} {:<21} {:>7} {:>7} {:>9} {:>9.3} {:>7} {:>7} {:>7} {:>9.3} {:>9.3} {:>9.3} {:>14.6e} {:>10}",
            r.size,
            r.solver,
            r.elements,
            r.dofs,
            r.nonzeros,
            r.wall_seconds,
            r.newton_iterations,
            r.factorizations + r.multigrid_setups,
            r.krylov_iterations,
            r.assembly_seconds,
            r.factor_seconds,
            r.compile_seconds,
            r.tip_mean_z,
            r.peak_rss_bytes
                .map_or("-".to_string(), |b| format!("{:.1}", b as f64 / 1e6)),
        );
    }
    if let Some(p) = &args.json {
        let text = serde_json::to_string_pretty(&rows).unwrap_or_default();
        crate::outputs::atomic::write_atomically(p, text.as_bytes())
            .map_err(|e| format!("cannot write `{}`: {e}", p.display()))?;
    }
    Ok(())
}
