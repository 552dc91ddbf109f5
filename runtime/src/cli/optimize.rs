//! `softc run` on a script with an `optimize` block: the training loop with a progress bar and a
//! log line per iteration, the state saved atomically into `--out DIR` after every iteration
//! (`--resume DIR` continues it), plots, the final optimized run's VTK series and the JSON
//! summary with `history` and `params`.

use super::RunArgs;
use crate::devices::{Backend, BackendChoice};
use crate::engine::Simulation;
use crate::engine::scene::Scene;
use crate::optim::Plan;
use crate::optim::train::{Record, SceneRecord, Stopped, TrainState, Trainer};
use crate::outputs::json::{gradients_json, summary_json};
use std::collections::BTreeMap;
use std::io::{IsTerminal, Write};
use std::path::{Path, PathBuf};

const STATE_FILE: &str = "state.json";
/// Trained entries drawn in the plots (all are in the JSON history).
const PLOTTED_ENTRIES: usize = 12;

/// Run the optimization; the exit status.
pub fn optimize(
    args: &RunArgs,
    scene: &Scene,
    mut plan: Plan,
    dt: Option<f64>,
    out: &mut dyn Write,
    err: &mut dyn Write,
) -> i32 {
    if let Some(n) = args.iterations {
        // At least 1 (clap refuses `--iterations 0`).
        plan.iterations = n;
    }
    let dir = args.resume.as_ref().or(args.out.as_ref()).cloned();
    // One run per folder, held for the whole run: a second one would overwrite this one's
    // state and results (issue 20). Locked before the state is read or checked.
    let lock = match (&args.resume, &args.out) {
        (Some(d), _) if !d.is_dir() => {
            let _ = writeln!(
                err,
                "softc: --resume {}: no such folder; give the --out folder of an earlier run",
                d.display()
            );
            return 2;
        }
        (Some(d), _) => crate::outputs::lock::lock_folder(d, "--resume").map(Some),
        (None, Some(d)) => crate::outputs::lock::lock_folder(d, "--out").map(Some),
        (None, None) => Ok(None),
    };
    let _lock = match lock {
        Ok(l) => l,
        Err(e) => {
            let _ = writeln!(err, "softc: {e}");
            return 2;
        }
    };
    let resume = match &args.resume {
        Some(d) => match load_state(d) {
            Ok(s) => Some(s),
            Err(e) => {
                let _ = writeln!(err, "softc: --resume {}: {e}", d.display());
                return 2;
            }
        },
        None => None,
    };
    if let (Some(d), Some(state)) = (&args.resume, &resume)
        && let Some(changed) = changed_settings(&state.settings, &run_settings(args))
    {
        let _ = writeln!(
            err,
            "softc: --resume {}: the saved run was made with other settings: {changed}; resume \
             with the saved ones, or start afresh with --out NEW_FOLDER",
            d.display()
        );
        return 2;
    }
    if let Some(d) = &args.out
        && args.resume.is_none()
        && d.join(STATE_FILE).exists()
    {
        let _ = writeln!(
            err,
            "softc: `{}` already holds an optimization run; continue it with `--resume {}` \
             or choose another --out folder",
            d.display(),
            d.display()
        );
        return 2;
    }
    let ctx = Context {
        args,
        scene,
        dir,
        dt,
        resume,
    };
    let members = plan.scenes_per_iteration();
    let module = &scene.lowered.adjoint.module;
    let result = match args.backend {
        BackendChoice::Reference => Err(
            "the optimization needs gradients: use --backend cpu, interp or gpu (the reference \
             oracle runs forward only)"
                .to_string(),
        ),
        _ => crate::devices::open(&args.device(), scene, module, members)
            .and_then(|devices| train(&ctx, plan, members, || devices.make(), err)),
    };
    let json = match result {
        Ok(j) => j,
        Err(e) if e.is_empty() => return 2,
        Err(e) => {
            let _ = writeln!(err, "{}: {e}", args.file.display());
            return 1;
        }
    };
    let text = serde_json::to_string_pretty(&json).unwrap_or_default();
    let mut status = 0;
    let mut on_stdout = args.json.is_none();
    if let Some(d) = &ctx.dir {
        let path = d.join("result.json");
        if let Err(e) = crate::outputs::atomic::write_atomically(&path, text.as_bytes()) {
            let _ = writeln!(err, "softc: cannot write `{}`: {e}", path.display());
            (status, on_stdout) = (2, true);
        }
    }
    if let Some(path) = &args.json
        && let Err(e) = crate::outputs::atomic::write_atomically(path, text.as_bytes())
    {
        let _ = writeln!(err, "softc: cannot write `{}`: {e}", path.display());
        (status, on_stdout) = (2, true);
    }
    if on_stdout {
        if status != 0 {
            let _ = writeln!(err, "softc: the JSON result follows on stdout");
        }
        let _ = writeln!(out, "{text}");
    }
    status
}

struct Context<'a> {
    args: &'a RunArgs,
    scene: &'a Scene,
    dir: Option<PathBuf>,
    dt: Option<f64>,
    resume: Option<TrainState>,
}

fn load_state(dir: &Path) -> Result<TrainState, String> {
    let path = dir.join(STATE_FILE);
    let text = crate::files::read_regular_text(&path)
        .map_err(|e| format!("cannot read `{}`: {e}", path.display()))?;
    serde_json::from_str(&text).map_err(|e| {
        format!(
            "`{}` is not a softc optimization state ({e}); it was not written by `softc run --out`",
            path.display()
        )
    })
}

/// The command line's settings a resumed run must keep, by flag, as the state records them.
fn run_settings(args: &RunArgs) -> BTreeMap<String, String> {
    let default = |v: Option<String>| v.unwrap_or_else(|| "(not given)".into());
    let mut m = BTreeMap::new();
    m.insert(
        "--backend".into(),
        format!("{:?}", args.backend).to_lowercase(),
    );
    m.insert(
        "--precision".into(),
        default(args.precision.map(|p| format!("{p:?}").to_lowercase())),
    );
    m.insert(
        "--linear-solver".into(),
        format!("{:?}", args.linear_solver).to_lowercase(),
    );
    m.insert("--dt".into(), default(args.dt.clone()));
    m.insert("--steps".into(), default(args.steps.map(|s| s.to_string())));
    m.insert(
        "--set".into(),
        default((!args.set.is_empty()).then(|| args.set.join(" "))),
    );
    m.insert(
        "--params".into(),
        default(args.params.as_ref().map(|p| p.display().to_string())),
    );
    m
}

/// Which recorded settings differ from this run's: `--backend cpu (saved) vs interp (now)`.
fn changed_settings(
    saved: &BTreeMap<String, String>,
    now: &BTreeMap<String, String>,
) -> Option<String> {
    let changed: Vec<String> = saved
        .iter()
        .filter_map(|(flag, was)| {
            let is = now.get(flag)?;
            (is != was).then(|| format!("{flag} {was} (saved) vs {is} (now)"))
        })
        .collect();
    (!changed.is_empty()).then(|| changed.join(", "))
}

/// FNV-1a over a sequence of byte strings (each followed by a separator).
struct Fnv(u64);

impl Fnv {
    fn new() -> Self {
        Fnv(0xcbf2_9ce4_8422_2325)
    }
    fn feed(&mut self, bytes: &[u8]) {
        for b in bytes {
            self.0 ^= *b as u64;
            self.0 = self.0.wrapping_mul(0x0100_0000_01b3);
        }
        self.0 ^= 0xff;
        self.0 = self.0.wrapping_mul(0x0100_0000_01b3);
    }
}

/// The mesh as the run uses it (positions in metres, tets, tags, chambers, named sets): a
/// resumed run must see the same mesh, whatever its file's comments or layout (issue 20 item 5:
/// only the script was hashed, so a different mesh file was resumed silently).
fn mesh_fingerprint(scene: &Scene) -> String {
    let m = &scene.mesh;
    let mut h = Fnv::new();
    for p in &m.nodes {
        for c in p {
            h.feed(&c.to_bits().to_le_bytes());
        }
    }
    for (t, tag) in m.tets.iter().zip(&m.tet_tags) {
        for n in t {
            h.feed(&n.to_le_bytes());
        }
        h.feed(&tag.to_le_bytes());
    }
    for (t, tag) in m.tris.iter().zip(&m.tri_tags) {
        for n in t {
            h.feed(&n.to_le_bytes());
        }
        h.feed(&tag.to_le_bytes());
    }
    for p in &m.names {
        h.feed(format!("{} {} {}", p.dim, p.tag, p.name).as_bytes());
    }
    for (name, nodes) in m.node_sets.iter().chain(&m.element_sets) {
        h.feed(name.as_bytes());
        for n in nodes {
            h.feed(&n.to_le_bytes());
        }
    }
    format!("{:016x}", h.0)
}

/// What a resumed run must agree with: the script, the overrides and the numerics (not the
/// number of iterations: `--resume DIR --iterations N` extends a finished run), then, after a
/// `/`, the mesh ([`mesh_fingerprint`]).
fn fingerprint(args: &RunArgs, scene: &Scene) -> String {
    let mut h = Fnv::new();
    let mut feed = |bytes: &[u8]| h.feed(bytes);
    feed(scene.source.as_bytes());
    for s in &args.set {
        feed(s.as_bytes());
    }
    if let Some(p) = &args.params {
        feed(&crate::files::read_regular(p).unwrap_or_default());
    }
    feed(format!("{:?}", args.dt).as_bytes());
    feed(format!("{:?}", args.steps).as_bytes());
    feed(format!("{:?} {:?}", args.backend, args.precision).as_bytes());
    format!("{:016x}/{}", h.0, mesh_fingerprint(scene))
}

/// A short rendering of the trained values: `p_max = 1523.4` or `w = [0.1, -0.2, … 12 values]`.
fn describe(params: &BTreeMap<String, f64>) -> String {
    let mut by: BTreeMap<&str, Vec<f64>> = BTreeMap::new();
    for (k, v) in params {
        let name = k.trim_start_matches("param.");
        by.entry(name.split('.').next().unwrap_or(name))
            .or_default()
            .push(*v);
    }
    by.into_iter()
        .map(|(name, vs)| match vs.as_slice() {
            [v] => format!("{name} = {v:.6e}"),
            _ => {
                let shown: Vec<String> = vs.iter().take(3).map(|v| format!("{v:.3e}")).collect();
                format!("{name} = [{}, … {} values]", shown.join(", "), vs.len())
            }
        })
        .collect::<Vec<_>>()
        .join(", ")
}

fn log_line(r: &Record, total: u64) -> String {
    // A batch's loss is the mean of its scenes' (one per quadrant for `circle_quadrants`): each
    // scene's loss follows it, so a lagging one shows while the run goes.
    let per_scene = if r.scenes.len() > 1 {
        let l: Vec<String> = r.scenes.iter().map(|s| format!("{:.2e}", s.loss)).collect();
        format!(" (scenes {})", l.join(", "))
    } else {
        String::new()
    };
    format!(
        "iteration {}/{}: loss {:.6e}{per_scene}, {}, grad_norm {:.3e}, lr {:.3e}, {:.2} s",
        r.iteration + 1,
        total,
        r.loss,
        describe(&r.params),
        r.grad_norm,
        r.lr,
        r.seconds
    )
}

fn train<B: Backend + Send>(
    ctx: &Context,
    plan: Plan,
    members: usize,
    make: impl Fn() -> Result<B, String>,
    err: &mut dyn Write,
) -> Result<serde_json::Value, String> {
    let (args, scene) = (ctx.args, ctx.scene);
    let mut sims = Vec::new();
    for _ in 0..members {
        let mut sim = Simulation::new(scene, make()?);
        sim.linear_solver = args.linear_solver;
        sims.push(sim);
    }
    let iterations = plan.iterations;
    let script_name = scene
        .script
        .file_name()
        .map_or("script".into(), |n| n.to_string_lossy().into_owned());
    let mut trainer = Trainer::new(
        plan,
        sims,
        args.grad_options(scene)?,
        ctx.dt,
        args.steps,
        fingerprint(args, scene),
        ctx.resume.clone(),
    )
    .map_err(|e| e.0)?;
    trainer.state.settings = run_settings(args);
    crate::session::check_step_count(
        scene,
        trainer.state.dt,
        trainer.state.steps,
        args.steps.is_some(),
        None,
    )?;
    let _ = writeln!(
        err,
        "optimizing {} values with {} over {} scene(s) per iteration: {} steps of {:e} s each{}",
        trainer.plan.entries.len(),
        trainer.plan.method.name(),
        members,
        trainer.state.steps,
        crate::text::Sig(trainer.state.dt),
        if trainer.state.iteration > 0 {
            format!(", resuming after iteration {}", trainer.state.iteration)
        } else {
            String::new()
        }
    );
    let bar = if std::io::stderr().is_terminal() {
        let b = indicatif::ProgressBar::new(iterations);
        b.set_style(
            indicatif::ProgressStyle::with_template(
                "{bar:30} {pos}/{len} iterations, {elapsed} elapsed, ~{eta} left  {msg}",
            )
            .unwrap_or_else(|_| indicatif::ProgressStyle::default_bar()),
        );
        b.set_position(trainer.state.iteration);
        Some(b)
    } else {
        None
    };
    while !trainer.finished() {
        let record = match trainer.step() {
            Ok(r) => r.clone(),
            Err(e) => return Err(with_saved_state(e.0, ctx.dir.as_deref(), &trainer.state)),
        };
        let line = log_line(&record, iterations);
        match &bar {
            Some(b) => {
                b.println(&line);
                b.set_position(record.iteration + 1);
                b.set_message(format!("loss {:.3e}", record.loss));
            }
            None => {
                let _ = writeln!(err, "{line}");
            }
        }
        if let Some(d) = &ctx.dir {
            let text = serde_json::to_string(&trainer.state).map_err(|e| e.to_string())?;
            let path = d.join(STATE_FILE);
            crate::outputs::atomic::write_atomically(&path, text.as_bytes()).map_err(|e| {
                format!(
                    "cannot save the optimization state to `{}`: {e}",
                    path.display()
                )
            })?;
            write_plots(d, &script_name, &trainer.state.history, &trainer)?;
        }
    }
    if let Some(b) = bar {
        b.finish_and_clear();
    }
    match &trainer.state.stopped {
        Some(Stopped::Condition { iteration }) => {
            let _ = writeln!(
                err,
                "stopped at iteration {}: `stop when` holds",
                iteration + 1
            );
        }
        _ => {
            let _ = writeln!(err, "finished {} iterations", trainer.state.iteration);
        }
    }

    // The optimized run: its VTK series and the summary.
    let vtk: Option<Box<dyn crate::engine::StateSeries>> = match &ctx.dir {
        Some(d) => {
            let folder = d.join("vtk");
            std::fs::create_dir_all(&folder)
                .map_err(|e| format!("cannot create `{}`: {e}", folder.display()))?;
            Some(Box::new(crate::outputs::vtk::VtkOutput::new(
                &folder,
                "optimized",
                crate::session::vtk_every(scene).unwrap_or(100),
            )))
        }
        None => None,
    };
    let first_inputs = trainer
        .state
        .history
        .first()
        .and_then(|r| r.scenes.first())
        .map(|s| s.inputs.clone())
        .unwrap_or_default();
    // The script's `output csv(SET)` logs of the optimized run: into --csv DIR if given, else
    // into the --out folder's `csv/`.
    let mut csv_args = ctx.args.clone();
    if csv_args.csv.is_none() {
        csv_args.csv = ctx.dir.as_ref().map(|d| d.join("csv"));
    }
    let csv = crate::session::csv_outputs(csv_args.csv.as_deref(), scene, trainer.state.dt, err)?;
    let summary = trainer.forward(&first_inputs, vtk, csv).map_err(|e| e.0)?;
    if let Some(w) = crate::session::run_warning(scene, &summary) {
        let _ = writeln!(err, "the optimized run: {w}");
    }
    let validation = trainer.validate().map_err(|e| e.0)?;
    for v in &validation {
        let _ = writeln!(
            err,
            "held-out scene {:?}: loss {:.6e}",
            v.inputs.values().collect::<Vec<_>>(),
            v.loss
        );
    }
    let mut json = summary_json(
        scene,
        &summary,
        &format!("{:?}", args.backend).to_lowercase(),
    );
    let history: Vec<serde_json::Value> = trainer
        .state
        .history
        .iter()
        .map(|r| {
            serde_json::json!({
                "iteration": r.iteration,
                "loss": r.loss,
                "params": gradients_json(&scene.slots, &r.params),
                "gradients": gradients_json(&scene.slots, &r.gradient),
                "scaled_gradient": r.scaled_gradient,
                "grad_norm": r.grad_norm,
                "lr": r.lr,
                "scenes": r.scenes.iter().map(scene_json).collect::<Vec<_>>(),
                "seconds": r.seconds,
            })
        })
        .collect();
    json["history"] = history.into();
    json["params"] = gradients_json(&scene.slots, &trainer.result());
    json["iterations"] = trainer.state.history.len().into();
    json["stopped"] = match &trainer.state.stopped {
        Some(Stopped::Condition { iteration }) => {
            serde_json::json!({"reason": "stop when", "iteration": iteration})
        }
        _ => serde_json::json!({"reason": "iterations"}),
    };
    json["validation"] = validation.iter().map(scene_json).collect::<Vec<_>>().into();
    Ok(json)
}

fn scene_json(s: &SceneRecord) -> serde_json::Value {
    serde_json::json!({"inputs": s.inputs, "loss": s.loss})
}

/// `optimization.png`/`.svg` in the output folder: loss (mean and per scene), the trained
/// values, the raw gradient and the step the optimizer received, per iteration (thesis
/// Fig. 5.2, 5.3, 6.2, 7.1, 7.2). Rewritten after every iteration.
fn write_plots<B: Backend + Send>(
    dir: &Path,
    name: &str,
    history: &[Record],
    trainer: &Trainer<B>,
) -> Result<(), String> {
    use crate::optim::plot::{Panel, Series, write_figure};
    let entries: Vec<&str> = trainer
        .plan
        .entries
        .iter()
        .map(|e| e.uniform.as_str())
        .collect();
    let label = |u: &str| u.trim_start_matches("param.").to_string();
    let mut loss = vec![Series {
        label: if history.first().is_some_and(|r| r.scenes.len() > 1) {
            "batch mean".into()
        } else {
            "loss".into()
        },
        values: history.iter().map(|r| r.loss).collect(),
    }];
    let scenes = history.first().map_or(0, |r| r.scenes.len());
    let quadrants = trainer.plan.inputs.iter().any(|i| {
        matches!(
            i.source,
            crate::optim::batch::InputSource::CircleQuadrants { .. }
        )
    });
    if scenes > 1 {
        for k in 0..scenes {
            loss.push(Series {
                label: if quadrants {
                    format!("quadrant {}", k % 4 + 1)
                } else {
                    format!("scene {}", k + 1)
                },
                values: history
                    .iter()
                    .map(|r| r.scenes.get(k).map_or(f64::NAN, |s| s.loss))
                    .collect(),
            });
        }
    }
    // Per-element fields have hundreds of entries: the plots show the first few.
    let per_entry = |f: &dyn Fn(&Record, usize, &str) -> f64| -> Vec<Series> {
        entries
            .iter()
            .enumerate()
            .take(PLOTTED_ENTRIES)
            .map(|(i, u)| Series {
                label: label(u),
                values: history.iter().map(|r| f(r, i, u)).collect(),
            })
            .collect()
    };
    let panels = [
        Panel {
            title: "loss".into(),
            y_label: "loss (SI)".into(),
            log_y: true,
            series: loss,
        },
        Panel {
            title: "trained values".into(),
            y_label: "value (SI)".into(),
            log_y: false,
            series: per_entry(&|r, _, u| r.params.get(u).copied().unwrap_or(f64::NAN)),
        },
        Panel {
            title: "|d loss / d param| (unscaled)".into(),
            y_label: "|gradient| (SI)".into(),
            log_y: true,
            series: per_entry(&|r, _, u| r.gradient.get(u).map_or(f64::NAN, |g| g.abs())),
        },
        Panel {
            title: "step direction (normalized, clipped gradient w.r.t. u)".into(),
            y_label: "scaled gradient".into(),
            log_y: false,
            series: per_entry(&|r, i, _| r.scaled_gradient.get(i).copied().unwrap_or(f64::NAN)),
        },
    ];
    let title = format!(
        "{} — {} over {} scene(s) per iteration",
        name,
        trainer.plan.method.name(),
        scenes.max(1)
    );
    write_figure(&dir.join("optimization"), &title, &panels).map(|_| ())
}

/// A failed iteration's error, told what the saved state keeps: the last iteration that
/// succeeded (written before the failing one started), or that nothing was saved.
fn with_saved_state(error: String, dir: Option<&Path>, state: &TrainState) -> String {
    match dir {
        Some(d) if state.iteration > 0 => format!(
            "{error}\n`{}` keeps the {} iteration(s) that succeeded, their params and losses \
             in its `history`",
            d.join(STATE_FILE).display(),
            state.iteration
        ),
        Some(_) => format!("{error}\nno iteration succeeded: nothing was saved"),
        None => error,
    }
}
