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

mod solvers;
mod tradeoff;

use crate::devices::{Backend, BackendChoice, DeviceChoice, Devices};
use crate::engine::Simulation;
use crate::engine::scene::Scene;
use clap::Args;
use softc_compiler::back::Precision;
use softc_compiler::ir::Module;
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
    /// Steps of each timed forward+backward pass.
    #[arg(long, default_value_t = 1000)]
    pub grad_steps: u64,
    /// A previous run's `--json` (e.g. `runtime/benches/baseline.json`, kept in the
    /// repository): each row's speed over the same size and backend there is printed and put
    /// in the JSON (`vs_baseline`), so a slowdown shows.
    #[arg(long, value_name = "JSON")]
    pub baseline: Option<PathBuf>,
    /// Threads of the cpu backend (default: its own choice).
    #[arg(long)]
    pub threads: Option<usize>,
    /// Scenes of the batched GPU rows (`gpu-f32 xN`: N copies of the scene in one batch,
    /// each launch one dispatch for all); 0 or 1 leaves them out.
    #[arg(long, default_value_t = 4)]
    pub batch: usize,
    /// The folder holding benchmark-SIZE.soft.
    #[arg(long, default_value = "examples")]
    pub examples: PathBuf,
    /// Also write the results as JSON to this file (written atomically).
    #[arg(long)]
    pub json: Option<PathBuf>,
    /// Comma-separated rows to measure: cpu-f64, cpu-f32, gpu, interp, reference (default:
    /// all that this machine has). Leaving out the reference leaves `x_reference` empty.
    #[arg(long, default_value = "cpu-f64,cpu-f32,gpu,interp,reference")]
    pub backends: String,
    /// Instead of the benchmark table: where the time of a step goes on the cpu backend (f64
    /// and f32) — per kernel its share of the time, the bytes it moves and the bandwidth that
    /// achieves — against this machine's memory bandwidth measured by a streaming triad.
    #[arg(long, conflicts_with = "tradeoff")]
    pub profile: bool,
    /// Instead of the benchmark table: speed against accuracy for a quasi-static SCRIPT. One
    /// output (`--output`) at steady state from variants that differ in one knob at a time —
    /// mesh resolution, precision, dt, FEM or spring mesh, settling tolerance — each with its
    /// error against a converged reference and its wall time; the Pareto front is marked.
    /// Writes a table, `OUT/tradeoff.json`, `OUT/tradeoff.png`/`.svg` and every variant as a
    /// script under `OUT/variants/`.
    #[arg(long, value_name = "SCRIPT")]
    pub tradeoff: Option<PathBuf>,
    /// Instead of the benchmark table: the static and implicit solvers on the benchmark scene
    /// of each size — one static solve, its gradient, and 40 backward Euler steps of 4 ms —
    /// with Newton iterations, assembly and factorization time, tangent size and memory.
    #[arg(long, conflicts_with_all = ["tradeoff", "profile"])]
    pub solvers: bool,
    /// With --solvers: also the static solve and the implicit steps by the matrix-free linear
    /// solver (GMRES on the kernels' tangent products, `--linear-solver krylov`).
    #[arg(long, requires = "solvers")]
    pub krylov: bool,
    /// With --solvers: also the static solve, its gradient and the implicit steps by
    /// multigrid-preconditioned conjugate gradients (`--linear-solver amg`).
    #[arg(long, requires = "solvers")]
    pub amg: bool,
    /// With --tradeoff: the output, a node set and an axis (mean displacement).
    #[arg(
        long,
        value_name = "SET.AXIS",
        default_value = "tip.z",
        requires = "tradeoff"
    )]
    pub output: String,
    /// With --tradeoff: mesh refinement factors (cell counts of the mesh's `.toml` spec scaled).
    #[arg(long, default_value = "0.5,1,1.5", requires = "tradeoff")]
    pub resolutions: String,
    /// With --tradeoff: precisions (the first is the baseline's).
    #[arg(long, default_value = "f64,f32", requires = "tradeoff")]
    pub precisions: String,
    /// With --tradeoff: dt = SAFETY × the stable-step estimate (the first is the baseline's).
    #[arg(long, default_value = "0.9,0.5,0.25", requires = "tradeoff")]
    pub safeties: String,
    /// With --tradeoff: settling tolerances — settled when max speed × time ≤ TOL × max
    /// displacement (the smallest is the baseline's).
    #[arg(long, default_value = "1e-2,1e-3,1e-4", requires = "tradeoff")]
    pub settle: String,
    /// With --tradeoff: the integrators compared — `explicit` (settled explicit runs, every
    /// knob above), `quasi_static` (one static solve per resolution and precision),
    /// `implicit_euler` (the baseline mesh in 20 backward Euler steps over the duration).
    #[arg(
        long,
        default_value = "explicit,quasi_static,implicit_euler",
        requires = "tradeoff"
    )]
    pub integrators: String,
    /// With --tradeoff: element orders (`1,2`: linear and quadratic tets; the first is the
    /// baseline's, and its f64 series gives the reference); each further order adds its
    /// resolution × precision series, explicit and static.
    #[arg(long, default_value = "1", requires = "tradeoff")]
    pub orders: String,
    /// With --tradeoff: also spring-mesh variants with this volume stiffness (`1kPa/mm`).
    #[arg(long, value_name = "ALPHA", requires = "tradeoff")]
    pub springs: Option<String>,
    /// With --tradeoff: a param or input value, with its unit (`--set p_peak=3kPa`).
    #[arg(long = "set", value_name = "NAME=VALUE", requires = "tradeoff")]
    pub set: Vec<String>,
    /// With --tradeoff: the output folder.
    #[arg(long, value_name = "DIR", default_value = "tradeoff")]
    pub out: PathBuf,
}

/// One (size, backend) measurement.
#[derive(Debug, Clone, serde::Serialize)]
pub struct Row {
    pub size: String,
    pub backend: String,
    pub compile_seconds: f64,
    pub forward_steps_per_second: f64,
    /// Forward speed of the cpu rows on one thread, where the row itself ran on the backend's
    /// own choice of threads and this machine has more than one core.
    pub forward_steps_per_second_one_thread: Option<f64>,
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
    /// Growth of peak resident memory during one forward+backward pass (Linux), bytes.
    pub forward_backward_peak_rss_bytes: Option<u64>,
    /// Operations (instructions other than arguments and constants) of the element kernel
    /// and of its adjoint, as the backends receive them.
    pub element_ops: usize,
    pub adjoint_element_ops: usize,
    /// Forward and forward+backward speed over the `--baseline` row of the same size and
    /// backend.
    pub vs_baseline: Option<[Option<f64>; 2]>,
    /// GPU rows: host and GPU time per forward step, submissions per 1000 steps.
    pub gpu_cost: Option<GpuCost>,
}

/// What a GPU row's device did per step in its last timed forward run.
#[derive(Clone, Copy, Debug, serde::Serialize)]
pub struct GpuCost {
    /// Host time recording a step's commands, µs per step (queue submissions excluded).
    pub host_us_per_step: f64,
    /// Host time inside the driver's queue submissions, µs per step (a software driver such
    /// as lavapipe runs the kernels there).
    pub submit_us_per_step: f64,
    /// GPU time of the compute passes (timestamp queries), µs per step, where the adapter
    /// has them.
    pub gpu_us_per_step: Option<f64>,
    /// Queue submissions per 1000 steps.
    pub submissions_per_1000_steps: f64,
}

/// The forward speed of a GPU device, as [`time_engine`], and what the device did per step
/// in the last timed run.
fn time_gpu_engine(
    scene: &Scene,
    make: &dyn Fn() -> Result<crate::devices::Device, String>,
    args: &BenchArgs,
) -> Result<((f64, f64), GpuCost), String> {
    let cost = std::cell::Cell::new(None);
    let run = || -> Result<(f64, Vec<[f64; 3]>), String> {
        let mut sim = Simulation::new(scene, make()?);
        let timed = sim.backend.enable_gpu_timing();
        let before = sim.backend.gpu_stats().unwrap_or_default();
        let start = Instant::now();
        let s = sim.run(None, Some(args.steps)).map_err(|e| e.0)?;
        let wall = start.elapsed().as_secs_f64();
        let after = sim.backend.gpu_stats().unwrap_or_default();
        let steps = args.steps.max(1) as f64;
        cost.set(Some(GpuCost {
            host_us_per_step: (after.host_seconds - before.host_seconds) / steps * 1e6,
            submit_us_per_step: (after.submit_seconds - before.submit_seconds) / steps * 1e6,
            gpu_us_per_step: match (timed, after.gpu_seconds, before.gpu_seconds) {
                (true, Some(a), b) => Some((a - b.unwrap_or(0.0)) / steps * 1e6),
                _ => None,
            },
            submissions_per_1000_steps: (after.submissions - before.submissions) as f64 / steps
                * 1000.0,
        }));
        Ok((args.steps as f64 / wall, s.x))
    };
    let timed = warm_median(scene, args, run)?;
    let cost = cost.get().ok_or("no timed run")?;
    Ok((timed, cost))
}

/// Instructions of a kernel body that compute (not arguments or constants).
fn operations(k: &softc_compiler::ir::Kernel) -> usize {
    use softc_compiler::ir::Inst;
    k.body
        .insts
        .iter()
        .filter(|i| !matches!(i, Inst::Arg(_) | Inst::Const(_)))
        .count()
}

/// Forward and forward+backward speed of `row` over the baseline's row of the same size and
/// backend (a previous `bench --json`).
fn against_baseline(baseline: &serde_json::Value, row: &Row) -> Option<[Option<f64>; 2]> {
    let old = baseline["rows"]
        .as_array()?
        .iter()
        .find(|r| r["size"] == row.size.as_str() && r["backend"] == row.backend.as_str())?;
    let ratio = |new: Option<f64>, key: &str| Some(new? / old[key].as_f64().filter(|v| *v > 0.0)?);
    Some([
        ratio(
            Some(row.forward_steps_per_second),
            "forward_steps_per_second",
        ),
        ratio(
            row.forward_backward_steps_per_second,
            "forward_backward_steps_per_second",
        ),
    ])
}

/// What one timed forward+backward configuration measured.
struct GradientTiming {
    steps_per_second: f64,
    stored_bytes: usize,
    recompute_ratio: f64,
    gradient: f64,
    /// Growth of the process's peak resident memory during one pass (Linux), bytes.
    peak_rss_bytes: Option<u64>,
}

/// Warm up once, then time `repeats` forward+backward passes of `--grad-steps` steps.
fn time_gradient<B: Backend>(
    scene: &Scene,
    make: &dyn Fn() -> Result<B, String>,
    args: &BenchArgs,
) -> Result<GradientTiming, String> {
    let steps = args.grad_steps;
    let run = || -> Result<(f64, crate::engine::adjoint::GradientReport), String> {
        let mut sim = Simulation::new(scene, make()?);
        let start = Instant::now();
        let g = sim
            .gradient(None, Some(steps), &Default::default())
            .map_err(|e| e.0)?;
        Ok((steps as f64 / start.elapsed().as_secs_f64(), g))
    };
    // The peak memory of one pass: reset the high-water mark, run, read it back.
    let before = reset_peak_rss();
    run()?;
    let peak_rss_bytes = before.and_then(|b| peak_rss().map(|p| p.saturating_sub(b)));
    let mut speeds = Vec::new();
    let mut last = None;
    for _ in 0..args.repeats.max(1) {
        let (sps, g) = run()?;
        speeds.push(sps);
        last = Some(g);
    }
    let g = last.expect("at least one run");
    Ok(GradientTiming {
        steps_per_second: median(speeds),
        stored_bytes: g.stored_states * g.state_bytes,
        recompute_ratio: g.recompute_ratio,
        gradient: g.gradients.get("param.p_peak").copied().unwrap_or(f64::NAN),
        peak_rss_bytes,
    })
}

/// Reset the kernel's peak-RSS mark of this process (Linux `clear_refs` 5) and return the
/// current resident size, the baseline the next peak is measured from.
fn reset_peak_rss() -> Option<u64> {
    std::fs::write("/proc/self/clear_refs", "5").ok()?;
    status_kib("VmRSS:")
}

fn peak_rss() -> Option<u64> {
    status_kib("VmHWM:")
}

fn status_kib(key: &str) -> Option<u64> {
    let status = std::fs::read_to_string("/proc/self/status").ok()?;
    let line = status.lines().find(|l| l.starts_with(key))?;
    let kib: u64 = line[key.len()..]
        .trim()
        .trim_end_matches("kB")
        .trim()
        .parse()
        .ok()?;
    Some(kib * 1024)
}

fn with_gradient(row: Row, g: GradientTiming) -> Row {
    Row {
        forward_backward_steps_per_second: Some(g.steps_per_second),
        adjoint_stored_bytes: Some(g.stored_bytes),
        recompute_ratio: Some(g.recompute_ratio),
        gradient_p_peak: Some(g.gradient),
        forward_backward_peak_rss_bytes: g.peak_rss_bytes,
        ..row
    }
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
    warm_median(scene, args, run)
}

/// One untimed warm-up run, then the median speed of `--repeats` timed runs and the tip's
/// mean z after the last.
fn warm_median(
    scene: &Scene,
    args: &BenchArgs,
    mut run: impl FnMut() -> Result<(f64, Vec<[f64; 3]>), String>,
) -> Result<(f64, f64), String> {
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

/// Forward scene-steps per second of `scenes` copies of the scene as one GPU batch, each on
/// its own thread in lockstep (as an optimization runs its batch), and the first scene's tip.
fn time_batch(
    scene: &Scene,
    module: &softc_compiler::ir::Module,
    precision: Precision,
    scenes: usize,
    args: &BenchArgs,
) -> Result<(f64, f64), String> {
    let batch = device(
        scene,
        module,
        BackendChoice::Gpu,
        precision,
        scenes,
        args.threads,
    )?;
    let mut sims = Vec::new();
    for _ in 0..scenes {
        sims.push(Simulation::new(scene, batch.make()?));
    }
    let run = || -> Result<(f64, Vec<[f64; 3]>), String> {
        let start = Instant::now();
        let results = crate::engine::in_lockstep(&mut sims, |_, sim| {
            sim.reset();
            sim.run(None, Some(args.steps))
        });
        let wall = start.elapsed().as_secs_f64();
        let mut first = None;
        for r in results {
            let summary = r.map_err(|e| e.0)?;
            first.get_or_insert(summary.x);
        }
        Ok((
            (scenes as u64 * args.steps) as f64 / wall,
            first.unwrap_or_default(),
        ))
    };
    warm_median(scene, args, run)
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

/// The device of a row for `members` scenes, opened as `softc run --backend BACKEND
/// --precision PRECISION` opens it.
fn device<'m>(
    scene: &Scene,
    module: &'m Module,
    backend: BackendChoice,
    precision: Precision,
    members: usize,
    threads: Option<usize>,
) -> Result<Devices<'m>, String> {
    let choice = DeviceChoice {
        backend,
        precision: Some(precision),
        adapter: None,
        threads,
    };
    crate::devices::open(&choice, scene, module, members)
}

/// Measure every backend on one size.
fn bench_size(size: &str, args: &BenchArgs) -> Result<Vec<Row>, String> {
    let path = args.examples.join(format!("benchmark-{size}.soft"));
    let scene = Scene::load(&path, &[]).map_err(|e| e.0)?;
    let module = &scene.lowered.module;
    let element = &module.kernels[0];
    let element_ops = operations(element);
    let adjoint_element_ops = scene
        .lowered
        .adjoint
        .module
        .kernels
        .iter()
        .find(|k| k.name == format!("adj_{}", element.name))
        .map_or(0, operations);
    let mut rows = Vec::new();
    let row = |backend: &str, compile: f64, (sps, z): (f64, f64)| Row {
        size: size.to_string(),
        backend: backend.to_string(),
        compile_seconds: compile,
        forward_steps_per_second: sps,
        forward_steps_per_second_one_thread: None,
        forward_speedup_vs_reference: None,
        steps: args.steps,
        tip_mean_z: z,
        forward_backward_steps_per_second: None,
        adjoint_stored_bytes: None,
        recompute_ratio: None,
        gradient_p_peak: None,
        forward_backward_peak_rss_bytes: None,
        element_ops,
        adjoint_element_ops,
        vs_baseline: None,
        gpu_cost: None,
    };
    let adjoint = &scene.lowered.adjoint.module;
    let wanted = |b: &str| args.backends.split(',').any(|w| w.trim() == b);
    for (name, precision) in [("cpu-f64", Precision::F64), ("cpu-f32", Precision::F32)] {
        if !wanted(name) {
            continue;
        }
        let cpu = |m, threads| device(&scene, m, BackendChoice::Cpu, precision, 1, threads);
        let forward = cpu(module, args.threads)?;
        let backward = cpu(adjoint, args.threads)?;
        let start = Instant::now();
        forward.make()?;
        let compile = start.elapsed().as_secs_f64();
        let timed = time_engine(&scene, &|| forward.make(), args)?;
        let g = time_gradient(&scene, &|| backward.make(), args)?;
        let mut r = with_gradient(row(name, compile, timed), g);
        let cores = std::thread::available_parallelism().map_or(1, |n| n.get());
        if args.threads.is_none() && cores > 1 {
            let one = cpu(module, Some(1))?;
            r.forward_steps_per_second_one_thread =
                Some(time_engine(&scene, &|| one.make(), args)?.0);
        }
        rows.push(r);
    }
    // The GPU rows, when this machine has an adapter (lavapipe counts: it is one).
    for (name, precision) in [("gpu-f32", Precision::F32), ("gpu-f64", Precision::F64)] {
        if !wanted("gpu") {
            continue;
        }
        let forward = device(
            &scene,
            module,
            BackendChoice::Gpu,
            precision,
            1,
            args.threads,
        )?;
        let backward = device(
            &scene,
            adjoint,
            BackendChoice::Gpu,
            precision,
            1,
            args.threads,
        )?;
        let start = Instant::now();
        if let Err(e) = forward.make() {
            eprintln!("note: no {name} row: {e}");
            continue;
        }
        let compile = start.elapsed().as_secs_f64();
        let (timed, cost) = time_gpu_engine(&scene, &|| forward.make(), args)?;
        let g = time_gradient(&scene, &|| backward.make(), args)?;
        rows.push(Row {
            gpu_cost: Some(cost),
            ..with_gradient(row(name, compile, timed), g)
        });
        if args.batch > 1 && precision == Precision::F32 {
            let timed = time_batch(&scene, module, precision, args.batch, args)?;
            rows.push(row(&format!("{name} x{}", args.batch), compile, timed));
        }
    }
    // The IR interpreter is the semantics, not a fast path: only on the smallest scene.
    if size == "1k" && wanted("interp") {
        let interp = device(
            &scene,
            module,
            BackendChoice::Interp,
            Precision::F64,
            1,
            args.threads,
        )?;
        let timed = time_engine(&scene, &|| interp.make(), args)?;
        rows.push(row("interp", 0.0, timed));
    }
    if wanted("reference") {
        let (setup, sps, z) = time_reference(&scene, args)?;
        rows.push(row("reference", setup, (sps, z)));
        let reference = sps;
        for r in &mut rows {
            r.forward_speedup_vs_reference = Some(r.forward_steps_per_second / reference);
        }
    }
    Ok(rows)
}

pub fn run(args: BenchArgs, out: &mut dyn Write, err: &mut dyn Write) -> i32 {
    // Outputs are checked before the (long) measurements.
    if let Some(p) = &args.json
        && let Err(e) = crate::outputs::atomic::check_writable_file(p)
    {
        let _ = writeln!(err, "error: --json {}: {e}", p.display());
        return 2;
    }
    if args.tradeoff.is_some()
        && let Err(e) = crate::outputs::atomic::check_writable_dir(&args.out)
    {
        let _ = writeln!(err, "error: --out {}: {e}", args.out.display());
        return 2;
    }
    // The sizes and the folder of the benchmark scripts are checked before any work.
    let sizes: Vec<&str> = args.sizes.split(',').map(str::trim).collect();
    if let Some(bad) = sizes.iter().find(|s| !["1k", "10k", "50k"].contains(s)) {
        let _ = writeln!(
            err,
            "error: unknown benchmark size `{bad}`; use 1k, 10k or 50k (e.g. --sizes 1k,10k)"
        );
        return 2;
    }
    if args.tradeoff.is_none() && !args.examples.is_dir() {
        let _ = writeln!(
            err,
            "error: --examples {}: not a folder (it should hold benchmark-SIZE.soft)",
            args.examples.display()
        );
        return 2;
    }
    if args.profile {
        return match profile(&args, out) {
            Ok(()) => 0,
            Err(e) => {
                let _ = writeln!(err, "error: {e}");
                1
            }
        };
    }
    if let Some(script) = &args.tradeoff {
        return tradeoff_command(&args, script, tradeoff::run, out, err);
    }
    if args.solvers {
        return match solvers::run(&args, &sizes, out) {
            Ok(()) => 0,
            Err(e) => {
                let _ = writeln!(err, "error: {e}");
                1
            }
        };
    }
    let baseline = match &args.baseline {
        Some(p) => match std::fs::read_to_string(p)
            .map_err(|e| e.to_string())
            .and_then(|t| serde_json::from_str::<serde_json::Value>(&t).map_err(|e| e.to_string()))
        {
            Ok(v) => Some(v),
            Err(e) => {
                let _ = writeln!(err, "error: --baseline {}: {e}", p.display());
                return 2;
            }
        },
        None => None,
    };
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
    if let Some(b) = &baseline {
        for r in &mut rows {
            r.vs_baseline = against_baseline(b, r);
        }
    }
    let _ = writeln!(
        out,
        "{:<5} {:<10} {:>10} {:>14} {:>10} {:>12} {:>16} {:>16} {:>12} {:>12} {:>10} {:>14} {:>8} {:>8} {:>13} {:>12} {:>10} {:>11} {:>8}",
        "size",
        "backend",
        "compile_s",
        "fwd_steps/s",
        "fwd_1thr",
        "x_reference",
        "tip_mean_z_m",
        "fwd+bwd_steps/s",
        "adj_bytes",
        "peak_rss_MB",
        "recompute",
        "dloss/dp_peak",
        "elem_ops",
        "adj_ops",
        "vs_baseline",
        "host_us/step",
        "submit_us",
        "gpu_us/step",
        "subm/1k"
    );
    for r in &rows {
        let _ = writeln!(
            out,
            "{:<5} {:<10} {:>10.3} {:>14.1} {:>10} {:>12.2} {:>16.6e} {:>16} {:>12} {:>12} {:>10} {:>14} {:>8} {:>8} {:>13} {:>12} {:>10} {:>11} {:>8}",
            r.size,
            r.backend,
            r.compile_seconds,
            r.forward_steps_per_second,
            r.forward_steps_per_second_one_thread
                .map_or("-".into(), |v| format!("{v:.1}")),
            r.forward_speedup_vs_reference.unwrap_or(f64::NAN),
            r.tip_mean_z,
            r.forward_backward_steps_per_second
                .map_or("-".into(), |v| format!("{v:.1}")),
            r.adjoint_stored_bytes.map_or("-".into(), |v| v.to_string()),
            r.forward_backward_peak_rss_bytes
                .map_or("-".into(), |v| format!("{:.1}", v as f64 / 1e6)),
            r.recompute_ratio.map_or("-".into(), |v| format!("{v:.2}")),
            r.gradient_p_peak.map_or("-".into(), |v| format!("{v:.6e}")),
            r.element_ops,
            r.adjoint_element_ops,
            match r.vs_baseline {
                Some([f, b]) => format!(
                    "{}/{}",
                    f.map_or("-".into(), |v| format!("{v:.2}")),
                    b.map_or("-".into(), |v| format!("{v:.2}"))
                ),
                None => "-".into(),
            },
            r.gpu_cost
                .map_or("-".into(), |c| format!("{:.2}", c.host_us_per_step)),
            r.gpu_cost
                .map_or("-".into(), |c| format!("{:.2}", c.submit_us_per_step)),
            r.gpu_cost
                .and_then(|c| c.gpu_us_per_step)
                .map_or("-".into(), |v| format!("{v:.2}")),
            r.gpu_cost.map_or("-".into(), |c| format!(
                "{:.1}",
                c.submissions_per_1000_steps
            )),
        );
    }
    let _ = writeln!(
        out,
        "median of {} timed runs of {} steps (forward+backward: {} steps) after a warm-up; \
         fwd_1thr = the cpu rows' forward on one thread (the rows themselves: the backend's own choice); \
         tip_mean_z after those steps; x_reference = speed over the reference in this run; \
         peak_rss_MB = growth of the process's peak resident memory during one forward+backward pass; \
         xN rows: N copies of the scene in one GPU batch, fwd_steps/s counting each scene's steps; \
         elem_ops/adj_ops = operations of the element kernel and its adjoint; \
         vs_baseline = forward/forward+backward speed over --baseline's row; \
         gpu rows: host_us/step = host time recording a forward step's commands, \
         submit_us = host time per step inside the driver's queue submissions (lavapipe runs the kernels there), \
         gpu_us/step = GPU time of its compute passes (timestamp queries; - where the adapter has none), \
         subm/1k = queue submissions per 1000 steps",
        args.repeats.max(1),
        args.steps,
        args.grad_steps
    );
    if let Some(path) = &args.json {
        let json = serde_json::json!({
            "steps": args.steps,
            "grad_steps": args.grad_steps,
            "repeats": args.repeats.max(1),
            "rows": rows,
        });
        let text = serde_json::to_string_pretty(&json).unwrap_or_default();
        if let Err(e) = crate::outputs::atomic::write_atomically(path, text.as_bytes()) {
            // Not lost: the rows go to stdout.
            let _ = writeln!(
                err,
                "error: cannot write `{}`: {e}; the JSON follows on stdout",
                path.display()
            );
            let _ = writeln!(out, "{text}");
            return 2;
        }
    }
    0
}

/// `softc mesh converge`: `bench --tradeoff` restricted to f64 static solves, with the
/// convergence verdict.
#[allow(clippy::too_many_arguments)]
pub fn mesh_converge(
    script: &std::path::Path,
    orders: &str,
    resolutions: &str,
    output: &str,
    set: &[String],
    threads: Option<usize>,
    folder: &std::path::Path,
    out: &mut dyn Write,
    err: &mut dyn Write,
) -> i32 {
    let mut argv: Vec<String> = [
        "bench",
        "--integrators",
        "quasi_static",
        "--precisions",
        "f64",
        "--orders",
        orders,
        "--resolutions",
        resolutions,
        "--output",
        output,
    ]
    .map(String::from)
    .to_vec();
    argv.extend(["--tradeoff".into(), script.display().to_string()]);
    argv.extend(["--out".into(), folder.display().to_string()]);
    for s in set {
        argv.extend(["--set".into(), s.clone()]);
    }
    if let Some(t) = threads {
        argv.extend(["--threads".into(), t.to_string()]);
    }
    #[derive(clap::Parser)]
    struct Bench {
        #[command(flatten)]
        args: BenchArgs,
    }
    match <Bench as clap::Parser>::try_parse_from(argv) {
        Ok(b) => tradeoff_command(&b.args, script, tradeoff::converge, out, err),
        Err(e) => {
            let _ = writeln!(err, "error: {e}");
            2
        }
    }
}

/// Run a sweep (`bench --tradeoff`, `mesh converge`): exit 0, 1 for a problem in the script
/// or a run, 2 for a bad flag.
pub fn tradeoff_command(
    args: &BenchArgs,
    script: &std::path::Path,
    what: fn(&tradeoff::Sweep, &mut dyn Write, &mut dyn Write) -> Result<(), String>,
    out: &mut dyn Write,
    err: &mut dyn Write,
) -> i32 {
    let sweep = match sweep(args, script) {
        Ok(s) => s,
        Err(e) => {
            let _ = writeln!(err, "error: {}: {e}", script.display());
            return 2;
        }
    };
    match what(&sweep, out, err) {
        Ok(()) => 0,
        Err(e) => {
            // A bad flag found once the script is read (a `--set` of the wrong dimension).
            let (code, e) = match e.strip_prefix(tradeoff::USAGE) {
                Some(e) => (2, e.to_string()),
                None => (1, e),
            };
            let _ = writeln!(err, "error: {}: {e}", script.display());
            code
        }
    }
}

/// The `--tradeoff` options as a sweep.
fn sweep(args: &BenchArgs, script: &std::path::Path) -> Result<tradeoff::Sweep, String> {
    fn list<T>(
        what: &str,
        text: &str,
        parse: impl Fn(&str) -> Option<T>,
    ) -> Result<Vec<T>, String> {
        let v: Vec<T> = text
            .split(',')
            .map(|s| parse(s.trim()).ok_or_else(|| format!("--{what}: cannot read `{s}`")))
            .collect::<Result<_, _>>()?;
        if v.is_empty() {
            return Err(format!("--{what} needs at least one value"));
        }
        Ok(v)
    }
    let positive = |s: &str| s.parse::<f64>().ok().filter(|v| *v > 0.0 && v.is_finite());
    let (set, axis) = match args.output.as_str() {
        tradeoff::LOSS => (tradeoff::LOSS, 0),
        o => o
            .rsplit_once('.')
            .and_then(|(set, a)| Some((set, ["x", "y", "z"].iter().position(|x| *x == a)?)))
            .ok_or_else(|| format!("--output `{o}`: expected SET.x, SET.y, SET.z or loss"))?,
    };
    let sets: Vec<crate::session::SetFlag> = args
        .set
        .iter()
        .map(|s| crate::session::parse_set(s))
        .collect::<Result<_, _>>()?;
    let overrides = sets.iter().map(|s| (s.name.clone(), s.value)).collect();
    let safeties = list("safeties", &args.safeties, positive)?;
    if safeties.iter().any(|s| *s > 1.0) {
        return Err("--safeties: a safety factor is at most 1".into());
    }
    Ok(tradeoff::Sweep {
        script: script.to_path_buf(),
        set: set.to_string(),
        axis,
        resolutions: list("resolutions", &args.resolutions, positive)?,
        precisions: list("precisions", &args.precisions, |s| match s {
            "f64" => Some(Precision::F64),
            "f32" => Some(Precision::F32),
            _ => None,
        })?,
        safeties,
        settle: list("settle", &args.settle, positive)?,
        integrators: list("integrators", &args.integrators, |s| match s {
            "explicit" => Some(tradeoff::Solver::Explicit),
            "quasi_static" => Some(tradeoff::Solver::QuasiStatic),
            "implicit_euler" => Some(tradeoff::Solver::ImplicitEuler),
            _ => None,
        })?,
        orders: list("orders", &args.orders, |s| match s {
            "1" => Some(1),
            "2" => Some(2),
            _ => None,
        })?,
        springs: args.springs.clone(),
        overrides,
        sets,
        threads: args.threads,
        out: args.out.clone(),
    })
}

/// `--profile`: per-kernel time and bytes of `--steps` steps of each size on the cpu backend.
fn profile(args: &BenchArgs, out: &mut dyn Write) -> Result<(), String> {
    use crate::engine::profile::{Profiled, memory_bandwidth};
    let threads_all = std::thread::available_parallelism().map_or(1, |n| n.get());
    let (bw1, bw_all) = (memory_bandwidth(1), memory_bandwidth(threads_all));
    let _ = writeln!(
        out,
        "memory bandwidth (triad a = b + s*c over 3 x 64 MiB, best of 5): {:.1} GB/s on 1 thread, \
         {:.1} GB/s on {threads_all}",
        bw1 / 1e9,
        bw_all / 1e9
    );
    for size in args.sizes.split(',').map(str::trim) {
        let path = args.examples.join(format!("benchmark-{size}.soft"));
        let scene = Scene::load(&path, &[]).map_err(|e| e.0)?;
        let module = &scene.lowered.module;
        for precision in [Precision::F64, Precision::F32] {
            let cpu = device(
                &scene,
                module,
                BackendChoice::Cpu,
                precision,
                1,
                args.threads,
            )?
            .make()?;
            let mut sim = Simulation::new(&scene, Profiled::new(cpu, module, &scene));
            // One untimed run for the JIT and caches, then the profiled one.
            sim.run(None, Some(args.steps.min(50))).map_err(|e| e.0)?;
            sim.reset();
            sim.backend.reset_costs();
            let start = Instant::now();
            sim.run(None, Some(args.steps)).map_err(|e| e.0)?;
            let wall = start.elapsed().as_secs_f64();
            let costs = &sim.backend.costs;
            let kernel_time: f64 = costs.iter().map(|c| c.time.as_secs_f64()).sum();
            let bytes: u64 = costs.iter().map(|c| c.bytes).sum();
            let steps = args.steps as f64;
            let _ = writeln!(
                out,
                "\nbenchmark-{size} ({} nodes, {} tets), cpu {precision}, {} steps: {:.1} steps/s; \
                 kernels {:.0} % of the wall time, the rest host work (state checks, swaps)",
                scene.mesh.nodes.len(),
                scene.mesh.tets.len(),
                args.steps,
                steps / wall,
                100.0 * kernel_time / wall
            );
            let _ = writeln!(
                out,
                "{:<28} {:<8} {:>10} {:>8} {:>12} {:>10}",
                "kernel", "domain", "us/step", "share", "bytes/step", "GB/s"
            );
            for c in costs.iter().filter(|c| c.launches > 0) {
                let t = c.time.as_secs_f64();
                let _ = writeln!(
                    out,
                    "{:<28} {:<8} {:>10.1} {:>7.1}% {:>12} {:>10.2}",
                    c.name,
                    c.domain,
                    1e6 * t / steps,
                    100.0 * t / kernel_time.max(1e-12),
                    c.bytes / args.steps.max(1),
                    c.bytes as f64 / t.max(1e-12) / 1e9
                );
            }
            let achieved = bytes as f64 / kernel_time.max(1e-12);
            let _ = writeln!(
                out,
                "total: {} bytes/step moved at {:.2} GB/s = {:.0} % of the 1-thread and {:.0} % of \
                 the all-thread bandwidth",
                bytes / args.steps.max(1),
                achieved / 1e9,
                100.0 * achieved / bw1,
                100.0 * achieved / bw_all
            );
        }
    }
    Ok(())
}
