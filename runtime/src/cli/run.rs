//! `softc run`: simulate a script and report a JSON summary.

use crate::devices::{Backend, BackendChoice, DeviceChoice, PrecisionChoice};
use crate::engine::adjoint::{GradOptions, GradientReport};
use crate::engine::scene::Scene;
use crate::engine::statics::LinearSolver;
use crate::engine::{RunSummary, Simulation};
use crate::outputs::json::{adjoint_json, gradients_json, summary_json};
use crate::session::{
    check_set_dims, csv_outputs, grad_options, parse_checkpoint, parse_dt, parse_memory_budget,
    parse_set, vtk_every,
};
use crate::text::Sig;
use clap::Args;
use std::io::Write;
use std::path::PathBuf;

#[derive(Args, Debug, Clone)]
pub struct RunArgs {
    /// The script to run.
    pub file: PathBuf,
    /// Which backend runs the kernels.
    #[arg(long, value_enum, default_value_t = BackendChoice::Cpu, allow_hyphen_values = true)]
    pub backend: BackendChoice,
    /// Floating-point precision of the kernels (cpu: default f64; gpu: default f32; the
    /// interpreter is f64). The script's `precision` setting applies when this is not given.
    #[arg(long, value_enum, allow_hyphen_values = true)]
    pub precision: Option<PrecisionChoice>,
    /// The GPU adapter of `--backend gpu`: a case-insensitive part of its name (or a backend
    /// name such as `vulkan`); default: a discrete GPU, else integrated, else software.
    #[arg(long, value_name = "NAME")]
    pub adapter: Option<String>,
    /// How static and implicit solves solve Newton's linear systems: `auto` (default) is
    /// `direct` up to 100,000 free dofs (20,000 for quadratic elements, 80,000 for those of
    /// a nearly incompressible material) and `amg` beyond;
    /// `direct` assembles the sparse
    /// tangent and factors it on the host; `amg` solves the assembled tangent by conjugate
    /// gradients preconditioned by algebraic multigrid (memory about linear in the mesh);
    /// `krylov` runs matrix-free GMRES on tangent products computed by the backend's kernels
    /// (block-Jacobi preconditioned; far slower on the shipped scenes, but no matrix in
    /// memory).
    #[arg(long, value_enum, default_value_t = LinearSolver::Auto)]
    pub linear_solver: LinearSolver,
    /// Worker threads of the cpu backend (default: stretches of steps of 8,000+ entities are
    /// timed on one thread and on all cores and run on the faster; single launches of 8,000+
    /// entities use all cores). Results are the same bits for any count.
    #[arg(long, allow_hyphen_values = true)]
    pub threads: Option<usize>,
    /// Override a param's value, with its unit: `--set p_max=2.5kPa`.
    #[arg(long = "set", value_name = "NAME=VALUE", allow_hyphen_values = true)]
    pub set: Vec<String>,
    /// Set params to the values of a JSON file's `params` object (SI units; arrays nested as
    /// `softc run --json` writes them), e.g. an optimization's `result.json`: run the trained
    /// design again, longer or with other outputs. `--set` wins over it
    #[arg(long, value_name = "JSON")]
    pub params: Option<PathBuf>,
    /// Override the number of steps (at least 1).
    #[arg(long, allow_hyphen_values = true, value_parser = clap::value_parser!(u64).range(1..))]
    pub steps: Option<u64>,
    /// Override the time step, with its unit: `--dt 20us`.
    #[arg(long, allow_hyphen_values = true)]
    pub dt: Option<String>,
    /// Write the JSON summary here (SI units).
    #[arg(long)]
    pub json: Option<PathBuf>,
    /// Write a ParaView series (`.pvd` + `.vtu`) into this folder, every N steps as the
    /// script's `output vtk every N steps` says (default 100).
    #[arg(long)]
    pub vtk: Option<PathBuf>,
    /// Write the script's `output csv(SET) every …` logs into this folder as `SET.csv` (time,
    /// mean, min and max displacement of the set, SI units).
    #[arg(long, value_name = "DIR")]
    pub csv: Option<PathBuf>,
    /// Also run the backward pass: d loss / d param for every param (`gradients` in the JSON).
    #[arg(long)]
    pub grad: bool,
    /// Which states the backward pass stores (overrides the optimize block's `checkpoint`):
    /// `auto`, `store_all`, `periodic:K` (every K-th state) or `revolve:N` (N snapshots).
    #[arg(long, value_name = "SCHEDULE", allow_hyphen_values = true)]
    pub checkpoint: Option<String>,
    /// Memory for the stored states of the backward pass, e.g. `512MB` (overrides the optimize
    /// block's `memory_budget`).
    #[arg(long, value_name = "BYTES", allow_hyphen_values = true)]
    pub memory_budget: Option<String>,
    /// With `--grad`: also report d loss / d (initial position) and d loss / d (initial
    /// velocity) of every node (`initial_state_gradients` in the JSON).
    #[arg(long, requires = "grad")]
    pub initial_state: bool,
    /// Write every output of an optimization into this folder: the optimizer state (saved
    /// atomically after every iteration), plots, the final run's VTK series and `result.json`.
    #[arg(long, value_name = "DIR", conflicts_with = "resume")]
    pub out: Option<PathBuf>,
    /// Continue the optimization saved in this folder (by `--out DIR`) where it stopped.
    #[arg(long, value_name = "DIR")]
    pub resume: Option<PathBuf>,
    /// Override the optimize block's number of iterations (at least 1).
    #[arg(long, allow_hyphen_values = true, value_parser = clap::value_parser!(u64).range(1..))]
    pub iterations: Option<u64>,
    /// Run the simulation once with the params' initial values even if the script has an
    /// `optimize` block.
    #[arg(long)]
    pub no_optimize: bool,
}

impl RunArgs {
    /// The device `--backend`, `--precision`, `--adapter` and `--threads` ask for.
    pub fn device(&self) -> DeviceChoice<'_> {
        DeviceChoice {
            backend: self.backend,
            precision: self.precision.map(Into::into),
            adapter: self.adapter.as_deref(),
            threads: self.threads,
        }
    }

    /// The backward pass's settings: the script's, overridden by `--checkpoint` and
    /// `--memory-budget`.
    pub fn grad_options(&self, scene: &Scene) -> Result<GradOptions, String> {
        grad_options(
            scene,
            self.checkpoint.as_deref(),
            self.memory_budget.as_deref(),
        )
    }
}

/// The params of a `--params` file against the script (issue 20 item 9): a param given there has
/// all of its entries (a short array was applied in part), and every value given by `--set` or
/// `--params` lies within the param's declared bounds (they bypassed the script's check).
fn check_overrides(
    scene: &Scene,
    overrides: &[(String, f64)],
    from_file: &[(String, f64)],
) -> Result<(), String> {
    for slots in &scene.slots {
        let given = from_file
            .iter()
            .filter(|(n, _)| {
                n == &slots.name
                    || n.strip_prefix(slots.name.as_str())
                        .is_some_and(|r| r.starts_with('.'))
            })
            .count();
        if given > 0 && given != slots.uniforms.len() {
            return Err(format!(
                "--params: `{}` has {given} value(s) in the file, the script's `{}` has {} \
                 (shape {:?}); give all of them",
                slots.name,
                slots.name,
                slots.uniforms.len(),
                slots.shape
            ));
        }
    }
    for (name, v) in overrides {
        let base = name.split('.').next().unwrap_or(name);
        let Some(slots) = scene.slots.iter().find(|s| s.name == base) else {
            continue;
        };
        let below = slots.lower.is_some_and(|lo| *v < lo);
        let above = slots.upper.is_some_and(|hi| *v > hi);
        if below || above || !v.is_finite() {
            let bound = |b: Option<f64>| b.map_or("unbounded".to_string(), |b| format!("{b:e}"));
            return Err(format!(
                "--set/--params {name} = {v:e} (SI) is outside the bounds the script declares \
                 for `{base}`: [{}, {}] (SI); give a value within them",
                bound(slots.lower),
                bound(slots.upper)
            ));
        }
    }
    Ok(())
}

/// The entries of a JSON file's `params` object (or of the file's top-level object), flattened
/// to `NAME`, `NAME.i`, `NAME.i.j` as `--set` names them.
fn params_file(path: &std::path::Path) -> Result<Vec<(String, f64)>, String> {
    let text = crate::files::read_regular_text(path).map_err(|e| e.to_string())?;
    let json: serde_json::Value =
        serde_json::from_str(&text).map_err(|e| format!("not JSON: {e}"))?;
    let params = json.get("params").unwrap_or(&json);
    let Some(params) = params.as_object() else {
        return Err("expected an object of params (or a `params` object)".into());
    };
    fn flatten(
        name: String,
        v: &serde_json::Value,
        out: &mut Vec<(String, f64)>,
    ) -> Result<(), String> {
        match v {
            serde_json::Value::Number(n) => {
                out.push((name, n.as_f64().unwrap_or(f64::NAN)));
                Ok(())
            }
            serde_json::Value::Array(items) => items
                .iter()
                .enumerate()
                .try_for_each(|(i, x)| flatten(format!("{name}.{i}"), x, out)),
            _ => Err(format!(
                "`{name}`: expected a number or an array of numbers"
            )),
        }
    }
    let mut out = Vec::new();
    for (name, v) in params {
        flatten(name.clone(), v, &mut out)?;
    }
    Ok(out)
}

/// Flags that do not fit the scene they are given with (usage errors, exit 2): `--dt` for a
/// quasi-static solve, which has no time step; a `--memory-budget` below the two states of
/// the scene a backward pass holds at least.
fn check_scene_flags(args: &RunArgs, scene: &Scene, dt: Option<f64>) -> Result<(), String> {
    let statics = scene.lowered.statics.as_ref();
    if args.backend == BackendChoice::Reference
        && let Some(s) = statics
    {
        // The oracle steps explicitly: it would answer another problem (issue 31 item 1).
        return Err(format!(
            "--backend reference: the reference oracle runs explicit steps only, and {} is \
             solved with `integrator = {}`; use --backend cpu (or gpu) for its solver",
            args.file.display(),
            if s.implicit.is_some() {
                "implicit_euler"
            } else {
                "quasi_static"
            }
        ));
    }
    if dt.is_some() && statics.is_some_and(|s| s.implicit.is_none()) {
        return Err(format!(
            "--dt: {} is solved quasi-statically, which has no time step; leave --dt out \
             (`--steps N` sets the number of equilibrium states)",
            args.file.display()
        ));
    }
    if let Some(m) = args.memory_budget.as_deref()
        && statics.is_none()
    {
        let budget = parse_memory_budget(m)?;
        let precision = crate::devices::precision(
            args.backend,
            args.precision.map(Into::into),
            scene.resolved.sim.precision,
        );
        let single = precision == softc_compiler::back::Precision::F32
            && args.backend != BackendChoice::Interp;
        let least = crate::engine::adjoint::least_budget(scene.mesh.nodes.len(), single);
        if budget < least {
            return Err(format!(
                "--memory-budget {m}: holds less than the {least} bytes of two states of this \
                 scene (the current one and one stored); give at least {least} bytes"
            ));
        }
    }
    Ok(())
}

/// Flags that have no effect on the scene they are given with: a warning naming each and
/// why, so that a run does not quietly differ from what was asked (issue 31 item 12).
fn warn_ignored_flags(args: &RunArgs, scene: &Scene, err: &mut dyn Write) {
    let statics = scene.lowered.statics.as_ref();
    let chosen = !matches!(
        args.linear_solver,
        LinearSolver::Direct | LinearSolver::Auto
    );
    if chosen && statics.is_none() {
        let _ = writeln!(
            err,
            "softc: warning: --linear-solver has no effect: {} runs explicit steps, which solve \
             no linear systems (it applies to `integrator = quasi_static` and `implicit_euler`)",
            args.file.display()
        );
    }
    if args.initial_state && statics.is_some() {
        let _ = writeln!(
            err,
            "softc: warning: --initial-state has no effect: {} is solved by {}, whose gradient \
             has no derivative with respect to the initial state (`initial_state_gradients` is \
             null); it applies to explicit runs",
            args.file.display(),
            if statics.is_some_and(|s| s.implicit.is_some()) {
                "implicit Euler"
            } else {
                "a quasi-static solve"
            }
        );
    }
}

pub fn run(args: RunArgs, out: &mut dyn Write, err: &mut dyn Write) -> i32 {
    // An unreadable script or a folder is a usage error (exit 2), found before anything else.
    let readable = std::fs::metadata(&args.file).and_then(|_| {
        match crate::files::not_regular(&args.file) {
            // A folder, a FIFO, a device: say which.
            Some(why) => Err(std::io::Error::other(format!("it {why}"))),
            None => std::fs::File::open(&args.file).map(|_| ()),
        }
    });
    if let Err(e) = readable {
        let _ = writeln!(err, "softc: cannot read `{}`: {e}", args.file.display());
        return 2;
    }
    // Every flag's value is checked before the script is compiled and run.
    let checked = (args.checkpoint.as_deref().map(parse_checkpoint).transpose()).and(
        args.memory_budget
            .as_deref()
            .map(parse_memory_budget)
            .transpose(),
    );
    if let Err(e) = checked {
        let _ = writeln!(err, "softc: {e}");
        return 2;
    }
    if args.backend == BackendChoice::Reference
        && args.precision.is_some_and(|p| p != PrecisionChoice::F64)
    {
        let _ = writeln!(
            err,
            "softc: --precision: the reference oracle computes in f64 only; leave --precision \
             out, or use `--backend cpu --precision f32`"
        );
        return 2;
    }
    let mut sets = Vec::new();
    for s in &args.set {
        match parse_set(s) {
            Ok(flag) => sets.push(flag),
            Err(e) => {
                let _ = writeln!(err, "softc: {e}");
                return 2;
            }
        }
    }
    let mut overrides: Vec<(String, f64)> = Vec::new();
    let mut from_file = Vec::new();
    if let Some(path) = &args.params {
        match params_file(path) {
            Ok(values) => {
                from_file.clone_from(&values);
                overrides.extend(values);
            }
            Err(e) => {
                let _ = writeln!(err, "softc: --params {}: {e}", path.display());
                return 2;
            }
        }
    }
    // `--set` wins over `--params`: the first entry of a name is the one applied.
    let from_set: Vec<(String, f64)> = sets.iter().map(|s| (s.name.clone(), s.value)).collect();
    overrides.splice(0..0, from_set);
    let dt = match args.dt.as_deref().map(parse_dt).transpose() {
        Ok(v) => v,
        Err(e) => {
            let _ = writeln!(err, "softc: {e}");
            return 2;
        }
    };
    if let Err(e) = check_outputs(&args) {
        let _ = writeln!(err, "softc: {e}");
        return 2;
    }
    let scene = match Scene::load(&args.file, &overrides) {
        Ok(s) => s,
        Err(e) => {
            let _ = writeln!(err, "{e}");
            return 1;
        }
    };
    for (name, _) in &overrides {
        let known = scene.uniforms.keys().any(|k| {
            k.strip_prefix("param.")
                .or_else(|| k.strip_prefix("input."))
                .is_some_and(|rest| rest == name || rest.starts_with(&format!("{name}.")))
        });
        if !known {
            let _ = writeln!(
                err,
                "softc: --set/--params {name}: the script has no param or input `{name}`"
            );
            return 2;
        }
    }
    if let Err(e) = check_set_dims(&scene.resolved, &sets) {
        let _ = writeln!(err, "softc: {e}");
        return 2;
    }
    if let Err(e) = check_overrides(&scene, &overrides, &from_file) {
        let _ = writeln!(err, "softc: {e}");
        return 2;
    }
    if let Err(e) = check_scene_flags(&args, &scene, dt) {
        let _ = writeln!(err, "softc: {e}");
        return 2;
    }
    warn_ignored_flags(&args, &scene, err);
    // No output inside a folder another run holds (its own folder lock covers only that folder).
    let outputs: Vec<(&str, &std::path::Path)> = [
        ("--json", &args.json),
        ("--vtk", &args.vtk),
        ("--csv", &args.csv),
        ("--out", &args.out),
        ("--resume", &args.resume),
    ]
    .into_iter()
    .filter_map(|(flag, p)| p.as_deref().map(|p| (flag, p)))
    .collect();
    if let Err(e) = crate::outputs::lock::check_outputs(&outputs) {
        let _ = writeln!(err, "softc: {e}");
        return 2;
    }
    if !args.grad && !args.no_optimize {
        match crate::optim::Plan::from_scene(&scene) {
            Ok(Some(plan)) => return super::optimize(&args, &scene, plan, dt, out, err),
            Ok(None) => {}
            Err(e) => {
                let _ = writeln!(err, "{}: optimize: {e}", args.file.display());
                return 1;
            }
        }
    }
    // A plain run's output folders are held for the run, as an optimization's --out folder.
    let mut _locks = Vec::new();
    let mut locked: Vec<PathBuf> = Vec::new();
    for (flag, dir) in [("--vtk", &args.vtk), ("--csv", &args.csv)] {
        let Some(d) = dir else { continue };
        let same = |p: &PathBuf| {
            d.canonicalize()
                .is_ok_and(|c| p.canonicalize().is_ok_and(|q| q == c))
        };
        if locked.iter().any(same) {
            continue;
        }
        match crate::outputs::lock::lock_folder(d, flag) {
            Ok(l) => _locks.push(l),
            Err(e) => {
                let _ = writeln!(err, "softc: {e}");
                return 2;
            }
        }
        locked.push(d.clone());
    }
    if args.grad && args.backend == BackendChoice::Reference {
        let _ = writeln!(
            err,
            "softc: --grad runs on the cpu, interp and gpu backends (the reference oracle is forward only)"
        );
        return 2;
    }
    // A script whose inputs list several scenes (`input p: pressure from [2 kPa, 3 kPa]`) runs
    // each of them; `--set` on an input runs just that one.
    let input_given = overrides.iter().any(|(n, _)| {
        scene
            .uniforms
            .keys()
            .any(|k| k.starts_with(&format!("input.{n}")))
    });
    let scenes = match crate::optim::plain_run_scenes(&scene) {
        Ok(_) if input_given => Vec::new(),
        Ok(s) => s,
        Err(e) => {
            let _ = writeln!(err, "{}: {e}", args.file.display());
            return 1;
        }
    };
    if scenes.len() > 1 {
        return run_scenes(scene, &args, dt, &scenes, out, err);
    }
    let result = run_scene(&scene, &args, dt, err);
    let ((summary, grad), backend_name) = match result {
        Ok(s) => s,
        Err(e) if e.is_empty() => return 2,
        Err(e) => {
            let _ = writeln!(err, "{}: {e}", args.file.display());
            return 1;
        }
    };
    if let Some(w) = crate::session::run_warning(&scene, &summary) {
        let _ = writeln!(err, "{}: {w}", args.file.display());
    }
    let mut json = summary_json(&scene, &summary, backend_name);
    if let Some(g) = &grad {
        json["gradients"] = gradients_json(&scene.slots, &g.gradients);
        json["adjoint"] = adjoint_json(g);
        if args.initial_state {
            let nodes = |v: &[f64]| v.chunks(3).map(|c| c.to_vec()).collect::<Vec<_>>();
            json["initial_state_gradients"] = match &g.initial_state {
                Some((x, v)) => serde_json::json!({"x": nodes(x), "v": nodes(v)}),
                None => serde_json::Value::Null,
            };
        }
        let _ = writeln!(
            err,
            "{}: backward pass over {} steps in {:.3} s ({}; {} states of {} bytes stored at most; \
             {:.2} forward steps per step)",
            args.file.display(),
            g.reversed_steps,
            g.backward_seconds,
            g.schedule,
            g.stored_states,
            g.state_bytes,
            g.recompute_ratio
        );
    }
    let text = serde_json::to_string_pretty(&json).unwrap_or_default();
    let _ = writeln!(
        err,
        "{}: {} steps of {:e} s in {:.3} s ({:.0} steps/s, backend {})",
        args.file.display(),
        summary.steps,
        Sig(summary.dt),
        summary.wall_seconds,
        summary.steps as f64 / summary.wall_seconds.max(1e-12),
        backend_name
    );
    emit_json(args.json.as_deref(), &text, out, err)
}

/// Every output a run writes (`--json`, `--vtk`, `--csv`, `--out`, `--resume`) checked before
/// the work: a run is not lost to an output found unwritable at its end.
fn check_outputs(args: &RunArgs) -> Result<(), String> {
    use crate::outputs::atomic::{check_writable_dir, check_writable_file};
    if let Some(p) = &args.json {
        check_writable_file(p).map_err(|e| format!("--json {}: {e}", p.display()))?;
    }
    let dirs = [
        ("--vtk", &args.vtk),
        ("--csv", &args.csv),
        ("--out", &args.out),
        ("--resume", &args.resume),
    ];
    for (flag, dir) in dirs {
        if let Some(d) = dir {
            check_writable_dir(d).map_err(|e| format!("{flag} {}: {e}", d.display()))?;
        }
    }
    Ok(())
}

/// The JSON summary into `--json PATH` (atomically) or onto stdout. If the file cannot be
/// written after all, the JSON goes to stdout instead of being lost (and the status is 2).
fn emit_json(
    path: Option<&std::path::Path>,
    text: &str,
    out: &mut dyn Write,
    err: &mut dyn Write,
) -> i32 {
    match path {
        Some(path) => {
            if let Err(e) = crate::outputs::atomic::write_atomically(path, text.as_bytes()) {
                let _ = writeln!(
                    err,
                    "softc: cannot write `{}`: {e}; the JSON follows on stdout",
                    path.display()
                );
                let _ = writeln!(out, "{text}");
                return 2;
            }
        }
        None => {
            let _ = writeln!(out, "{text}");
        }
    }
    0
}

/// The kernels a run needs: with `--grad` the adjoint module (a superset of the forward one).
fn kernel_module<'a>(scene: &'a Scene, args: &RunArgs) -> &'a softc_compiler::ir::Module {
    // A quasi-static solve's tangent kernels are in the adjoint module.
    if args.grad || scene.lowered.statics.is_some() {
        &scene.lowered.adjoint.module
    } else {
        &scene.lowered.module
    }
}

/// A scene's summary, with its gradients after `--grad`.
type SceneRun = (RunSummary, Option<GradientReport>);
type SceneResult = Result<(SceneRun, &'static str), String>;

/// One scene on the chosen backend: the forward run, or forward and backward with `--grad`.
fn run_scene(scene: &Scene, args: &RunArgs, dt: Option<f64>, err: &mut dyn Write) -> SceneResult {
    match args.backend {
        BackendChoice::Reference => {
            crate::reference::run(scene, dt, args.steps).and_then(|mut s| {
                // The oracle's own job is the state; an at-end loss is evaluated on its final state.
                if let Some(l) = crate::engine::loss::Loss::build(scene, s.dt, s.steps)?
                    && l.window == crate::engine::loss::LossWindow::End
                {
                    let x: Vec<f64> = s.x.iter().flatten().copied().collect();
                    let v: Vec<f64> = s.v.iter().flatten().copied().collect();
                    let u = crate::devices::Uniforms::new(&[], &scene.uniforms);
                    s.loss = Some(l.eval(scene, &x, &v, s.steps as f64 * s.dt, &u));
                }
                Ok(((s, None), "reference"))
            })
        }
        _ => {
            // The adjoint kernels are compiled only when the backward pass runs.
            let module = kernel_module(scene, args);
            let devices = crate::devices::open(&args.device(), scene, module, 1)?;
            let device = devices.make()?;
            if let Some(adapter) = device.adapter() {
                let _ = writeln!(err, "adapter: {adapter}; kernels in {}", devices.precision);
            }
            let name = device.name();
            simulate(scene, device, args, dt, err).map(|o| (o, name))
        }
    }
}

/// Every scene of the script's inputs in turn; the JSON is the first scene's summary with the
/// mean loss over the scenes, and `scenes`: each scene's inputs and summary.
fn run_scenes(
    mut scene: Scene,
    args: &RunArgs,
    dt: Option<f64>,
    scenes: &[Vec<(String, f64)>],
    out: &mut dyn Write,
    err: &mut dyn Write,
) -> i32 {
    let mut results = Vec::new();
    // On the GPU the scenes run as one batch; elsewhere one after another.
    let mut batched: Option<Vec<Option<SceneRun>>> = None;
    if args.backend == BackendChoice::Gpu {
        match run_gpu_batch(&scene, args, dt, scenes, err) {
            Ok(v) => batched = Some(v.into_iter().map(Some).collect()),
            Err(e) if e.is_empty() => return 2,
            Err(e) => {
                let _ = writeln!(err, "{}: {e}", args.file.display());
                return 1;
            }
        }
    }
    for (k, assignment) in scenes.iter().enumerate() {
        for (name, value) in assignment {
            scene.uniforms.insert(name.clone(), *value);
        }
        let mut a = args.clone();
        a.vtk = args.vtk.as_ref().map(|d| d.join(format!("scene{k}")));
        a.csv = args.csv.as_ref().map(|d| d.join(format!("scene{k}")));
        let inputs: serde_json::Map<String, serde_json::Value> = assignment
            .iter()
            .map(|(n, v)| (n.trim_start_matches("input.").to_string(), (*v).into()))
            .collect();
        let _ = writeln!(
            err,
            "scene {k}: {}",
            serde_json::Value::Object(inputs.clone())
        );
        let result = match batched.as_mut() {
            Some(runs) => runs[k]
                .take()
                .map(|r| (r, "gpu"))
                .ok_or_else(|| "no result".to_string()),
            None => run_scene(&scene, &a, dt, err),
        };
        match result {
            Ok(((summary, grad), backend)) => {
                let _ = writeln!(
                    err,
                    "{}: scene {k}: {} steps of {:e} s in {:.3} s (backend {backend})",
                    args.file.display(),
                    summary.steps,
                    Sig(summary.dt),
                    summary.wall_seconds
                );
                if let Some(w) = crate::session::run_warning(&scene, &summary) {
                    let _ = writeln!(err, "{}: scene {k}: {w}", args.file.display());
                }
                let mut json = summary_json(&scene, &summary, backend);
                if let Some(g) = &grad {
                    json["gradients"] = gradients_json(&scene.slots, &g.gradients);
                }
                json["inputs"] = serde_json::Value::Object(inputs);
                results.push(json);
            }
            Err(e) if e.is_empty() => return 2,
            Err(e) => {
                let _ = writeln!(err, "{}: scene {k}: {e}", args.file.display());
                return 1;
            }
        }
    }
    let json = crate::outputs::json::scenes_json(results);
    let text = serde_json::to_string_pretty(&json).unwrap_or_default();
    emit_json(args.json.as_deref(), &text, out, err)
}

/// Print the stable-step estimate before a run, and warn when the step exceeds it.
fn announce_dt<B: Backend>(
    sim: &mut Simulation<B>,
    dt: Option<f64>,
    err: &mut dyn Write,
) -> Result<(), String> {
    if sim.scene.lowered.statics.is_some() {
        return Ok(());
    }
    let est = sim.stable_dt_estimate().map_err(|e| e.0)?;
    let chosen = match (dt, sim.scene.dt) {
        (Some(d), _) => Some(d),
        (None, crate::engine::scene::DtChoice::Given(d)) => Some(d),
        (None, crate::engine::scene::DtChoice::Auto { safety }) => Some(safety * est),
    };
    let _ = writeln!(
        err,
        "stable step estimate (2/omega_max of M^-1 K at rest): {} s; dt = {} s",
        Sig(est),
        Sig(chosen.unwrap_or(est))
    );
    if let Some(d) = chosen
        && d > est
    {
        let _ = writeln!(
            err,
            "warning: dt = {} s exceeds the stable step {} s of this mesh and material; \
             the run will likely blow up. Use `dt = auto` or dt <= {} s",
            Sig(d),
            Sig(est),
            Sig(0.9 * est)
        );
    }
    Ok(())
}

/// The VTK series asked for with `--vtk DIR`.
fn vtk_output(
    args: &RunArgs,
    scene: &Scene,
    err: &mut dyn Write,
) -> Result<Option<Box<dyn crate::engine::StateSeries>>, i32> {
    let Some(dir) = &args.vtk else {
        return Ok(None);
    };
    if let Err(e) = std::fs::create_dir_all(dir) {
        let _ = writeln!(err, "softc: cannot create `{}`: {e}", dir.display());
        return Err(2);
    }
    let every = vtk_every(scene).unwrap_or(100);
    let name = scene
        .script
        .file_stem()
        .map(|s| s.to_string_lossy().into_owned())
        .unwrap_or_else(|| "run".into());
    Ok(Some(Box::new(crate::outputs::vtk::VtkOutput::new(
        dir, &name, every,
    ))))
}

/// A forward run, or with `--grad` a forward and backward pass, on one backend. An empty error
/// means the message was already printed (a usage error).
fn simulate<B: Backend>(
    scene: &Scene,
    backend: B,
    args: &RunArgs,
    dt: Option<f64>,
    err: &mut dyn Write,
) -> Result<SceneRun, String> {
    let mut sim = prepare(scene, backend, &[], args, dt, err)?;
    let options = args.grad.then(|| args.grad_options(scene)).transpose()?;
    execute(&mut sim, args, dt, options.as_ref())
}

/// A simulation as `softc run` sets it up: the inputs' values, the VTK and CSV outputs, the
/// stable step announced.
fn prepare<'s, B: Backend>(
    scene: &'s Scene,
    backend: B,
    inputs: &[(String, f64)],
    args: &RunArgs,
    dt: Option<f64>,
    err: &mut dyn Write,
) -> Result<Simulation<'s, B>, String> {
    let mut sim = Simulation::new(scene, backend);
    sim.linear_solver = args.linear_solver;
    for (name, value) in inputs {
        sim.uniforms.set_named(name, *value);
    }
    sim.vtk = match vtk_output(args, scene, err) {
        Ok(v) => v,
        Err(_) => return Err(String::new()),
    };
    announce_dt(&mut sim, dt, err)?;
    let (step, _) = crate::session::checked_time_steps(&mut sim, dt, args.steps)?;
    sim.progress = Some(Box::new(crate::outputs::progress::Progress::new(
        args.file.display().to_string(),
    )));
    sim.csv = csv_outputs(args.csv.as_deref(), scene, step, err)?;
    Ok(sim)
}

/// The forward run, or forward and backward with `grad` options.
fn execute<B: Backend>(
    sim: &mut Simulation<B>,
    args: &RunArgs,
    dt: Option<f64>,
    grad: Option<&GradOptions>,
) -> Result<SceneRun, String> {
    match grad {
        Some(options) => {
            let g = sim.gradient(dt, args.steps, options).map_err(|e| e.0)?;
            Ok((g.summary.clone(), Some(g)))
        }
        None => sim.run(dt, args.steps).map(|s| (s, None)).map_err(|e| e.0),
    }
}

/// The scenes of a plain run as one GPU batch: each set up in turn, then all run on threads
/// in lockstep, every kernel launch one dispatch for all of them.
fn run_gpu_batch(
    scene: &Scene,
    args: &RunArgs,
    dt: Option<f64>,
    scenes: &[Vec<(String, f64)>],
    err: &mut dyn Write,
) -> Result<Vec<SceneRun>, String> {
    let module = kernel_module(scene, args);
    let batch = crate::devices::open(&args.device(), scene, module, scenes.len())?;
    if let Some(adapter) = batch.adapter() {
        let _ = writeln!(
            err,
            "adapter: {adapter}; kernels in {}; {} scenes in one batch",
            batch.precision,
            scenes.len()
        );
    }
    let options = args.grad.then(|| args.grad_options(scene)).transpose()?;
    let mut sims = Vec::new();
    let mut scene_args = Vec::new();
    for (k, assignment) in scenes.iter().enumerate() {
        let mut a = args.clone();
        a.vtk = args.vtk.as_ref().map(|d| d.join(format!("scene{k}")));
        a.csv = args.csv.as_ref().map(|d| d.join(format!("scene{k}")));
        let _ = writeln!(err, "scene {k}:");
        sims.push(prepare(scene, batch.make()?, assignment, &a, dt, err)?);
        scene_args.push(a);
    }
    let options = options.as_ref();
    crate::engine::in_lockstep(&mut sims, |k, sim| {
        execute(sim, &scene_args[k], dt, options).map_err(crate::engine::RunError)
    })
    .into_iter()
    .enumerate()
    .map(|(k, r)| r.map_err(|e| format!("scene {k}: {}", e.0)))
    .collect()
}
