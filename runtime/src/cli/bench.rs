//! `softc bench`: forward speed of every backend on the canonical benchmark scene
//! (`examples/benchmark-{1k,10k,50k}.soft`, shared/BENCHMARK.md).
//!
//! For each size and backend: the one-off compile time, forward steps/s as the median of
//! `--repeats` timed runs of `--steps` steps after one untimed warm-up run, and the tip's mean
//! z-displacement after those steps (a correctness check beside the speed). Speed ratios are
//! taken against the reference measured in the same invocation. A row is one (size, backend);
//! the cpu rows also time one forward+backward pass (`--grad` with the default checkpointing)
//! over the same steps: forward+backward steps/s (median), the bytes of states it stored, its
//! recompute ratio and d loss / d p_peak.

use crate::engine::scene::Scene;
use crate::engine::{Backend, Cpu, Interpreter, Simulation};
use clap::Args;
use softc_compiler::back::Precision;
use std::io::Write;
use std::path::PathBuf;
use std::time::Instant;

#[derive(Args, Debug)]
pub struct BenchArgs {
    /// Comma-separated sizes of the benchmark scene: 1k, 10k, 50k.
    #[arg(long, default_value = "1k,10k,50k")]
    pub sizes: String,
    /// Timed runs per backend (the median is reported).
    #[arg(long, default_value_t = 3)]
    pub repeats: usize,
    /// Steps per timed run.
    #[arg(long, default_value_t = 200)]
    pub steps: u64,
    /// Threads of the cpu backend (default: its own choice).
    #[arg(long)]
    pub threads: Option<usize>,
    /// The folder holding benchmark-SIZE.soft.
    #[arg(long, default_value = "examples")]
    pub examples: PathBuf,
    /// Also write the results as JSON to this file (written atomically).
    #[arg(long)]
    pub json: Option<PathBuf>,
}

/// One (size, backend) measurement.
#[derive(Debug, Clone, serde::Serialize)]
pub struct Row {
    pub size: String,
    pub backend: String,
    pub compile_seconds: f64,
    pub forward_steps_per_second: f64,
    /// Forward speed over the reference's on the same size (same run of `softc bench`).
    pub forward_speedup_vs_reference: Option<f64>,
    pub steps: u64,
    /// Mean z-displacement of the `tip` node set after `steps` steps, m.
    pub tip_mean_z: f64,
    /// Steps / wall time of one forward and backward pass (cpu rows).
    pub forward_backward_steps_per_second: Option<f64>,
    /// Bytes of the states the backward pass stored at most.
    pub adjoint_stored_bytes: Option<usize>,
    /// Forward steps the forward+backward pass ran, over `steps`.
    pub recompute_ratio: Option<f64>,
    /// d loss / d p_peak, per Pa.
    pub gradient_p_peak: Option<f64>,
}

/// Warm up once, then time `repeats` forward+backward passes of the adjoint module on the cpu.
fn time_gradient(
    scene: &Scene,
    precision: Precision,
    args: &BenchArgs,
) -> Result<(f64, usize, f64, f64), String> {
    let module = &scene.lowered.adjoint.module;
    let run = || -> Result<(f64, crate::engine::adjoint::GradientReport), String> {
        let cpu = Cpu::new(module, precision, args.threads)?;
        let mut sim = Simulation::new(scene, cpu);
        let start = Instant::now();
        let g = sim
            .gradient(None, Some(args.steps), &Default::default())
            .map_err(|e| e.0)?;
        Ok((args.steps as f64 / start.elapsed().as_secs_f64(), g))
    };
    run()?;
    let mut speeds = Vec::new();
    let mut last = None;
    for _ in 0..args.repeats.max(1) {
        let (sps, g) = run()?;
        speeds.push(sps);
        last = Some(g);
    }
    let g = last.expect("at least one run");
    Ok((
        median(speeds),
        g.stored_states * g.state_bytes,
        g.recompute_ratio,
        g.gradients.get("param.p_peak").copied().unwrap_or(f64::NAN),
    ))
}

fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(f64::total_cmp);
    let n = v.len();
    if n % 2 == 1 {
        v[n / 2]
    } else {
        0.5 * (v[n / 2 - 1] + v[n / 2])
    }
}

fn tip_mean_z(scene: &Scene, x: &[[f64; 3]]) -> Result<f64, String> {
    let (_, tip) = scene
        .node_sets
        .iter()
        .find(|(n, _)| n == "tip")
        .ok_or("the benchmark scene has no node set `tip`")?;
    if tip.is_empty() {
        return Err("the node set `tip` is empty".into());
    }
    Ok(tip
        .iter()
        .map(|&n| x[n as usize][2] - scene.mesh.nodes[n as usize][2])
        .sum::<f64>()
        / tip.len() as f64)
}

/// Warm up once, then time `repeats` runs: (median steps/s, tip mean z of the last run).
fn time_engine<B: Backend>(
    scene: &Scene,
    make: &dyn Fn() -> Result<B, String>,
    args: &BenchArgs,
) -> Result<(f64, f64), String> {
    let run = || -> Result<(f64, Vec<[f64; 3]>), String> {
        let mut sim = Simulation::new(scene, make()?);
        let start = Instant::now();
        let s = sim.run(None, Some(args.steps)).map_err(|e| e.0)?;
        Ok((args.steps as f64 / start.elapsed().as_secs_f64(), s.x))
    };
    run()?;
    let mut speeds = Vec::new();
    let mut last = Vec::new();
    for _ in 0..args.repeats.max(1) {
        let (sps, x) = run()?;
        speeds.push(sps);
        last = x;
    }
    Ok((median(speeds), tip_mean_z(scene, &last)?))
}

fn time_reference(scene: &Scene, args: &BenchArgs) -> Result<(f64, f64, f64), String> {
    let start = Instant::now();
    crate::reference::Reference::new(scene)?;
    let setup = start.elapsed().as_secs_f64();
    let mut speeds = Vec::new();
    let mut last = Vec::new();
    // No JIT to warm up; still one untimed run for caches, as for the others.
    for i in 0..=args.repeats.max(1) {
        let start = Instant::now();
        let s = crate::reference::run(scene, None, Some(args.steps))?;
        if i > 0 {
            speeds.push(args.steps as f64 / start.elapsed().as_secs_f64());
            last = s.x;
        }
    }
    Ok((setup, median(speeds), tip_mean_z(scene, &last)?))
}

/// Measure every backend on one size.
fn bench_size(size: &str, args: &BenchArgs) -> Result<Vec<Row>, String> {
    let path = args.examples.join(format!("benchmark-{size}.soft"));
    let scene = Scene::load(&path, &[]).map_err(|e| e.0)?;
    let module = &scene.lowered.module;
    let mut rows = Vec::new();
    let row = |backend: &str, compile: f64, (sps, z): (f64, f64)| Row {
        size: size.to_string(),
        backend: backend.to_string(),
        compile_seconds: compile,
        forward_steps_per_second: sps,
        forward_speedup_vs_reference: None,
        steps: args.steps,
        tip_mean_z: z,
        forward_backward_steps_per_second: None,
        adjoint_stored_bytes: None,
        recompute_ratio: None,
        gradient_p_peak: None,
    };
    for (name, precision) in [("cpu-f64", Precision::F64), ("cpu-f32", Precision::F32)] {
        let start = Instant::now();
        Cpu::new(module, precision, args.threads)?;
        let compile = start.elapsed().as_secs_f64();
        let timed = time_engine(&scene, &|| Cpu::new(module, precision, args.threads), args)?;
        let (sps, bytes, ratio, g) = time_gradient(&scene, precision, args)?;
        rows.push(Row {
            forward_backward_steps_per_second: Some(sps),
            adjoint_stored_bytes: Some(bytes),
            recompute_ratio: Some(ratio),
            gradient_p_peak: Some(g),
            ..row(name, compile, timed)
        });
    }
    // The IR interpreter is the semantics, not a fast path: only on the smallest scene.
    if size == "1k" {
        let timed = time_engine(&scene, &|| Ok(Interpreter::new(module)), args)?;
        rows.push(row("interp", 0.0, timed));
    }
    let (setup, sps, z) = time_reference(&scene, args)?;
    rows.push(row("reference", setup, (sps, z)));
    let reference = sps;
    for r in &mut rows {
        r.forward_speedup_vs_reference = Some(r.forward_steps_per_second / reference);
    }
    Ok(rows)
}

pub fn run(args: BenchArgs, out: &mut dyn Write, err: &mut dyn Write) -> i32 {
    let sizes: Vec<&str> = args.sizes.split(',').map(str::trim).collect();
    if let Some(bad) = sizes.iter().find(|s| !["1k", "10k", "50k"].contains(s)) {
        let _ = writeln!(
            err,
            "error: unknown benchmark size `{bad}`; use 1k, 10k or 50k (e.g. --sizes 1k,10k)"
        );
        return 2;
    }
    let mut rows = Vec::new();
    for size in &sizes {
        match bench_size(size, &args) {
            Ok(r) => rows.extend(r),
            Err(e) => {
                let _ = writeln!(err, "error: benchmark-{size}: {e}");
                return 1;
            }
        }
    }
    let _ = writeln!(
        out,
        "{:<5} {:<10} {:>10} {:>14} {:>12} {:>16} {:>16} {:>12} {:>10} {:>14}",
        "size",
        "backend",
        "compile_s",
        "fwd_steps/s",
        "x_reference",
        "tip_mean_z_m",
        "fwd+bwd_steps/s",
        "adj_bytes",
        "recompute",
        "dloss/dp_peak"
    );
    for r in &rows {
        let _ = writeln!(
            out,
            "{:<5} {:<10} {:>10.3} {:>14.1} {:>12.2} {:>16.6e} {:>16} {:>12} {:>10} {:>14}",
            r.size,
            r.backend,
            r.compile_seconds,
            r.forward_steps_per_second,
            r.forward_speedup_vs_reference.unwrap_or(f64::NAN),
            r.tip_mean_z,
            r.forward_backward_steps_per_second
                .map_or("-".into(), |v| format!("{v:.1}")),
            r.adjoint_stored_bytes.map_or("-".into(), |v| v.to_string()),
            r.recompute_ratio.map_or("-".into(), |v| format!("{v:.2}")),
            r.gradient_p_peak.map_or("-".into(), |v| format!("{v:.6e}")),
        );
    }
    let _ = writeln!(
        out,
        "median of {} timed runs of {} steps after a warm-up; tip_mean_z after those steps; \
         x_reference = speed over the reference in this run",
        args.repeats.max(1),
        args.steps
    );
    if let Some(path) = &args.json {
        let json = serde_json::json!({
            "steps": args.steps,
            "repeats": args.repeats.max(1),
            "rows": rows,
        });
        let text = serde_json::to_string_pretty(&json).unwrap_or_default();
        if let Err(e) = super::write_atomically(path, text.as_bytes()) {
            let _ = writeln!(err, "error: cannot write `{}`: {e}", path.display());
            return 1;
        }
    }
    0
}
