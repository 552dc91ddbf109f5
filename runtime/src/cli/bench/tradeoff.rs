//! `softc bench --tradeoff SCRIPT`: how much accuracy each choice buys and what it costs.
//!
//! For a quasi-static scene (loads that settle to a steady state), one output — the mean
//! displacement of a node set along one axis — is computed by variants of the script that differ
//! in one knob at a time: mesh resolution (the script's mesh regenerated from the `.toml` spec
//! beside it at scaled cell counts), precision, time step (safety factor on the stable-step
//! estimate), FEM or spring mesh, and the settling tolerance that decides how many steps reach
//! the steady state. Each variant's error is taken against a converged reference and set
//! against its wall time; the points that no other point beats on both are the Pareto front.
//!
//! The reference is a Richardson extrapolation of the f64 FEM output over the resolutions (with
//! the order observed from the three finest), or, when that is not possible or not credible,
//! the finest f64 FEM solution; the report says which. Every variant is written as a script
//! under `OUT/variants/` (absolute mesh path, its settings in the `sim` block) so any point can
//! be rerun with `softc run`.

use crate::devices::cpu::Cpu;
use crate::engine::Simulation;
use crate::engine::scene::Scene;
use crate::mesh::mesher::{MeshSpec, generate};
use softc_compiler::Variant;
use softc_compiler::back::Precision;
use std::io::Write;
use std::path::{Path, PathBuf};
use std::time::Instant;

/// What the tradeoff sweeps; parsed from `softc bench --tradeoff` options.
#[derive(Debug, Clone)]
pub struct Sweep {
    pub script: PathBuf,
    /// Node set and axis of the output (`tip.z`).
    pub set: String,
    pub axis: usize,
    /// Mesh refinement factors (1 = the script's own mesh).
    pub resolutions: Vec<f64>,
    pub precisions: Vec<Precision>,
    /// dt = safety × stable-step estimate.
    pub safeties: Vec<f64>,
    /// Relative settling tolerances (see `Simulation::run_to_steady_state`).
    pub settle: Vec<f64>,
    /// Element orders (1 linear, 2 quadratic tets); the first is the baseline's.
    pub orders: Vec<u32>,
    /// Volume stiffness α of the spring-mesh variants (N/m³); none: FEM only.
    pub springs: Option<String>,
    /// The integrators compared (the explicit runs carry every other knob).
    pub integrators: Vec<Solver>,
    pub overrides: Vec<(String, f64)>,
    /// The `--set` flags behind `overrides`, with their units' dimensions.
    pub sets: Vec<crate::session::SetFlag>,
    pub threads: Option<usize>,
    pub out: PathBuf,
}

/// How a variant reaches its steady state.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Solver {
    /// Explicit steps until the settling criterion holds.
    Explicit,
    /// One static solve at the script's end time.
    QuasiStatic,
    /// [`IMPLICIT_STEPS`] backward Euler steps over the script's duration.
    ImplicitEuler,
}

/// Backward Euler steps of an `implicit_euler` variant: steps 10⁴× the explicit one or more,
/// enough to show how far numerical damping gets it towards the steady state.
const IMPLICIT_STEPS: u32 = 20;

impl Solver {
    fn name(self) -> &'static str {
        match self {
            Solver::Explicit => "explicit",
            Solver::QuasiStatic => "quasi_static",
            Solver::ImplicitEuler => "implicit_euler",
        }
    }
}

/// One variant and what it measured.
#[derive(Debug, Clone, serde::Serialize)]
pub struct Point {
    pub label: String,
    /// `explicit`, `quasi_static` or `implicit_euler`.
    pub solver: String,
    pub resolution: f64,
    pub tets: usize,
    pub precision: String,
    pub model: String,
    /// Element order: 1 linear, 2 quadratic tets.
    pub order: u32,
    /// Nodes of the mesh (mid-edge nodes included).
    pub nodes: usize,
    pub safety: f64,
    pub settle: f64,
    pub dt: f64,
    pub steps: u64,
    pub settled: bool,
    /// The output (m).
    pub value: f64,
    /// |value − reference| / |reference|.
    pub error: f64,
    /// Wall time of the run: stable-step estimate and time steps, not the one-off compile.
    pub seconds: f64,
    pub compile_seconds: f64,
    pub pareto: bool,
    pub script: PathBuf,
}

#[derive(Debug, Clone, Copy, PartialEq)]
struct Config {
    solver: Solver,
    resolution: f64,
    precision: Precision,
    springs: bool,
    order: u32,
    safety: f64,
    settle: f64,
}

/// The prefix of an error that is a usage error (a bad flag, exit status 2), not a problem in
/// the script.
pub const USAGE: &str = "usage: ";

/// Run the sweep; prints progress to `err`, the table to `out`; writes JSON and the plot.
pub fn run(sweep: &Sweep, out: &mut dyn Write, err: &mut dyn Write) -> Result<(), String> {
    let (points, reference, _) = sweep_points(sweep, err)?;
    print_table(&points, &reference, sweep, out);
    write_outputs(&points, &reference, sweep)
}

/// `softc mesh converge`: the sweep's table, then how far the script's own answer (resolution
/// 1, the order it declares) is from the converged reference, how much each order's answer moves
/// between its two finest resolutions, and how far the orders are apart on one mesh.
pub fn converge(sweep: &Sweep, out: &mut dyn Write, err: &mut dyn Write) -> Result<(), String> {
    let (points, reference, script_order) = sweep_points(sweep, err)?;
    print_table(&points, &reference, sweep, out);
    write_outputs(&points, &reference, sweep)?;
    let rel = |a: f64, b: f64| (a - b).abs() / b.abs().max(f64::MIN_POSITIVE);
    let own = points
        .iter()
        .find(|p| p.resolution == 1.0 && p.order == script_order)
        .or_else(|| {
            points
                .iter()
                .find(|p| p.resolution == 1.0 && p.order == sweep.orders[0])
        });
    let _ = writeln!(out, "\nconvergence of {}:", output_name(sweep));
    for &order in &sweep.orders {
        let mut series: Vec<&Point> = points.iter().filter(|p| p.order == order).collect();
        series.sort_by(|a, b| a.resolution.total_cmp(&b.resolution));
        if let [.., a, b] = series[..] {
            let _ = writeln!(
                out,
                "  {}: {:+.3} % from resolution {} to {} ({} → {} nodes)",
                order_name(order),
                100.0 * (b.value - a.value) / a.value.abs().max(f64::MIN_POSITIVE),
                a.resolution,
                b.resolution,
                a.nodes,
                b.nodes
            );
        }
    }
    let mut resolutions: Vec<f64> = points.iter().map(|p| p.resolution).collect();
    resolutions.sort_by(f64::total_cmp);
    resolutions.dedup();
    for r in resolutions {
        let at: Vec<&Point> = points.iter().filter(|p| p.resolution == r).collect();
        if let (Some(l), Some(q)) = (
            at.iter().find(|p| p.order == 1),
            at.iter().find(|p| p.order == 2),
        ) {
            let _ = writeln!(
                out,
                "  resolution {r}: linear {:.6e}, quadratic {:.6e}: {:.3} % apart",
                l.value,
                q.value,
                100.0 * rel(l.value, q.value)
            );
        }
    }
    let Some(p) = own else {
        return Ok(());
    };
    let error = rel(p.value, reference.value);
    let _ = writeln!(
        out,
        "  {} ({}, resolution 1): {:.6e}",
        if p.order == script_order {
            "the script's own answer"
        } else {
            "the answer on the script's mesh"
        },
        order_name(p.order),
        p.value
    );
    let is_reference = reference.order.is_none() && p.value == reference.value;
    // The other element order on the same mesh, when the script's own answer is the finest of
    // its series: the two orders' distance is all there is to judge it by.
    let other_order = points
        .iter()
        .find(|o| o.resolution == p.resolution && o.order != p.order);
    let verdict = if let (true, Some(o)) = (is_reference, other_order) {
        let apart = rel(p.value, o.value);
        format!(
            "the {} answer on the same mesh is {:.3} % away: {}",
            order_name(o.order),
            100.0 * apart,
            if apart > 0.05 {
                "not converged; refine the mesh (a finer spec `resolution` or `[extrude] \
                 wall`) or load it with `order: 2`, and add resolutions (--resolutions 1,0.75,0.5) \
                 for an error estimate"
            } else if apart > 0.01 {
                "within a few % if the finer order is close to converged; add resolutions for an \
                 error estimate"
            } else {
                "the orders agree to 1 %; add resolutions for an error estimate"
            }
        )
    } else if is_reference {
        "its error is not estimated: it is the finest answer here. Add resolutions (a spec \
         beside the mesh and --resolutions 1,1.5,2) for an extrapolation, or the other order \
         (--orders 1,2) for a comparison"
            .to_string()
    } else {
        let refine = "refine the mesh (a finer spec `resolution` or `[extrude] wall`) or load \
                      it with `order: 2`";
        match reference.order {
            Some(_) if error > 0.05 => {
                format!(
                    "estimated error {:.3} %: not converged; {refine}",
                    100.0 * error
                )
            }
            Some(_) => format!(
                "estimated error {:.3} %: within {} %",
                100.0 * error,
                if error > 0.01 { 5 } else { 1 }
            ),
            // Against a finer answer that is not converged itself: a lower bound.
            None => format!(
                "at least {:.3} % from the converged answer (the finest answer here is that \
                 far from it); {}",
                100.0 * error,
                if error > 0.01 {
                    refine
                } else {
                    "add resolutions to estimate the error itself"
                }
            ),
        }
    };
    let _ = writeln!(out, "  verdict: {verdict}");
    let _ = writeln!(out, "  reference: {}", reference.method);
    Ok(())
}

fn order_name(order: u32) -> &'static str {
    if order == 2 { "quadratic" } else { "linear" }
}

fn output_name(sweep: &Sweep) -> String {
    match sweep.set.as_str() {
        LOSS => "the script's loss".to_string(),
        set => format!(
            "the mean {} displacement of `{set}`",
            ["x", "y", "z"][sweep.axis]
        ),
    }
}

/// `--output loss`: the script's loss at the steady state instead of a node set's mean.
pub const LOSS: &str = "loss";

/// Every variant of the sweep, measured, with the reference their errors are taken against.
/// Also the element order the script declares.
fn sweep_points(
    sweep: &Sweep,
    err: &mut dyn Write,
) -> Result<(Vec<Point>, Reference, u32), String> {
    let base = Scene::load(&sweep.script, &sweep.overrides).map_err(|e| e.0)?;
    crate::session::check_set_dims(&base.resolved, &sweep.sets)
        .map_err(|e| format!("{USAGE}{e}"))?;
    if base.resolved.mesh.span.is_none() {
        return Err("the script's mesh is not `load(\"FILE\")`".into());
    }
    let spec_path = base.resolved.mesh.written.with_extension("toml");
    let spec_path = base_dir(&sweep.script).join(&spec_path);
    // Other resolutions are regenerated from the spec beside the mesh; resolution 1 is the
    // script's own mesh, which needs none.
    let spec = if sweep.resolutions.iter().all(|r| *r == 1.0) {
        None
    } else {
        Some(MeshSpec::from_file(&spec_path).map_err(|e| {
            format!(
                "{e}\n  other resolutions are regenerated from the spec beside the script's \
                 mesh ({}); give the mesh a spec or use --resolutions 1",
                spec_path.display()
            )
        })?)
    };
    std::fs::create_dir_all(sweep.out.join("meshes"))
        .and_then(|_| std::fs::create_dir_all(sweep.out.join("variants")))
        .map_err(|e| format!("cannot create {}: {e}", sweep.out.display()))?;
    let set_index = match sweep.set.as_str() {
        LOSS if base.loss.is_none() => return Err("the script has no loss".into()),
        LOSS => None,
        set => Some(
            base.node_sets
                .iter()
                .position(|(n, _)| *n == set)
                .ok_or_else(|| format!("the script has no node set `{set}`"))?,
        ),
    };
    let configs = configs(sweep);
    // The script's end time: its `duration`, or its fixed `dt` times its `steps`.
    let sim = &base.resolved.sim;
    let duration = match (sim.duration, sim.dt, sim.steps) {
        (Some(d), _, _) => d,
        (None, softc_compiler::driver::DtChoice::Given(dt), Some(n)) => dt * n as f64,
        _ => 0.0,
    };
    if duration <= 0.0 && sweep.integrators.contains(&Solver::ImplicitEuler) {
        return Err(format!(
            "{USAGE}the implicit_euler variant divides the script's `duration` into \
             {IMPLICIT_STEPS} steps, and this script has none; leave it out with \
             --integrators explicit,quasi_static"
        ));
    }
    let mut meshes: Vec<(f64, PathBuf)> = Vec::new();
    let mut points = Vec::new();
    for (i, c) in configs.iter().enumerate() {
        let mesh = match (meshes.iter().find(|(r, _)| *r == c.resolution), &spec) {
            (Some((_, p)), _) => Some(p.clone()),
            (None, Some(spec)) => {
                let p = refined_mesh(spec, &spec_path, c.resolution, &sweep.out)?;
                meshes.push((c.resolution, p.clone()));
                Some(p)
            }
            // Resolution 1 without a spec: the script's own mesh.
            (None, None) => None,
        };
        let label = label(c);
        let variant = Variant {
            mesh,
            sim_settings: sim_settings(c, sweep, duration, sim.duration.is_some()),
            order: Some(c.order),
        };
        let scene = Scene::load_with(&sweep.script, &sweep.overrides, Some(&variant))
            .map_err(|e| format!("{label}: {e}"))?;
        // The variant as a script of its own, so any point can be rerun with `softc run`.
        let script = sweep.out.join("variants").join(format!("{label}.soft"));
        let text = format!(
            "# softc bench --tradeoff variant of {}\n{}",
            sweep.script.display(),
            scene.source
        );
        crate::outputs::atomic::write_atomically(&script, text.as_bytes())
            .map_err(|e| format!("cannot write {}: {e}", script.display()))?;
        let _ = writeln!(err, "[{}/{}] {label}", i + 1, configs.len());
        let p = measure(&scene, &script, &label, c, sweep, set_index)?;
        let _ = writeln!(
            err,
            "        {} tets, dt {:.3e} s, {} steps{}, {:.1} s: {} = {:.6e} m",
            p.tets,
            p.dt,
            p.steps,
            if p.settled { "" } else { " (not settled)" },
            p.seconds,
            sweep.set,
            p.value
        );
        points.push(p);
    }
    let reference = reference(&points);
    for p in &mut points {
        p.error = ((p.value - reference.value) / reference.value).abs();
    }
    mark_pareto(&mut points);
    let script_order = match base.order() {
        softc_compiler::ir::ElementOrder::Linear => 1,
        softc_compiler::ir::ElementOrder::Quadratic => 2,
    };
    Ok((points, reference, script_order))
}

/// The converged value every error is measured against, and how it was obtained.
#[derive(Debug, Clone, serde::Serialize)]
pub struct Reference {
    pub value: f64,
    pub method: String,
    /// Observed convergence order in the cell size (Richardson only).
    pub order: Option<f64>,
}

fn base_dir(script: &Path) -> PathBuf {
    script
        .parent()
        .filter(|p| !p.as_os_str().is_empty())
        .unwrap_or(Path::new("."))
        .to_path_buf()
}

/// Every configuration: the baseline (resolution 1, first precision, FEM, first safety,
/// tightest settling), then one knob varied at a time; resolution × precision in full.
fn configs(s: &Sweep) -> Vec<Config> {
    let tight = s.settle.iter().copied().fold(f64::INFINITY, f64::min);
    let base = Config {
        solver: Solver::Explicit,
        resolution: 1.0,
        precision: s.precisions[0],
        springs: false,
        order: s.orders[0],
        safety: s.safeties[0],
        settle: tight,
    };
    let mut all = Vec::new();
    let mut push = |c: Config| {
        if !all.contains(&c) && s.integrators.contains(&c.solver) {
            all.push(c);
        }
    };
    for &precision in &s.precisions {
        for &resolution in &s.resolutions {
            push(Config {
                resolution,
                precision,
                ..base
            });
        }
    }
    for &safety in &s.safeties {
        push(Config { safety, ..base });
    }
    for &settle in &s.settle {
        push(Config { settle, ..base });
    }
    if s.springs.is_some() {
        for &resolution in &s.resolutions {
            push(Config {
                resolution,
                springs: true,
                ..base
            });
        }
    }
    // The implicit solvers take no time-step safety or settling tolerance (0 in the table).
    let implicit = Config {
        safety: 0.0,
        settle: 0.0,
        ..base
    };
    for &order in &s.orders {
        for &precision in &s.precisions {
            for &resolution in &s.resolutions {
                if order != base.order {
                    push(Config {
                        resolution,
                        precision,
                        order,
                        ..base
                    });
                }
                push(Config {
                    solver: Solver::QuasiStatic,
                    resolution,
                    precision,
                    order,
                    ..implicit
                });
            }
        }
    }
    push(Config {
        solver: Solver::ImplicitEuler,
        ..implicit
    });
    all
}

/// The force model as the table and labels name it: `fem` (linear tets), `fem2` (quadratic
/// tets) or `springs`.
fn model_name(c: &Config) -> &'static str {
    match (c.springs, c.order) {
        (true, _) => "springs",
        (false, 2) => "fem2",
        _ => "fem",
    }
}

fn label(c: &Config) -> String {
    let model = model_name(c);
    if c.solver != Solver::Explicit {
        return format!(
            "res{}-{}-{}-{}",
            c.resolution,
            match c.precision {
                Precision::F32 => "f32",
                _ => "f64",
            },
            model,
            c.solver.name()
        );
    }
    format!(
        "res{}-{}-{}-dt{}-settle{:e}",
        c.resolution,
        match c.precision {
            Precision::F32 => "f32",
            _ => "f64",
        },
        model,
        c.safety,
        c.settle
    )
}

/// Generate the spec's mesh with cell counts (or lattice spacing) scaled by `factor`.
fn refined_mesh(
    spec: &MeshSpec,
    spec_path: &Path,
    factor: f64,
    out: &Path,
) -> Result<PathBuf, String> {
    let mut spec = spec.clone();
    let resolution = match &mut spec.kuhn {
        Some(k) => {
            k.n = k.n.map(|n| ((n as f64 * factor).round() as usize).max(1));
            None
        }
        // The extruded mesher's resolution is its wall edge (interior and layer scale alike).
        None => Some(
            spec.extrude
                .as_ref()
                .map(|x| x.wall)
                .or(spec.resolution)
                .ok_or("the mesh spec has none of [kuhn], [extrude] and `resolution`")?
                / factor,
        ),
    };
    let unit = spec.unit().map_err(|e| e.to_string())?;
    let g = generate(&spec, resolution, &base_dir(spec_path)).map_err(|e| e.to_string())?;
    let path = out.join("meshes").join(format!("res{factor}.msh"));
    crate::mesh::save(&g.mesh, &path, unit).map_err(|e| e.to_string())?;
    Ok(std::fs::canonicalize(&path).unwrap_or(path))
}

/// The variant's `sim` settings: its integrator, time step, precision and model.
/// `duration`: the script's end time (the implicit steps divide it; the static solve is of
/// that one time), 0 where it has none.
fn sim_settings(
    c: &Config,
    sweep: &Sweep,
    duration: f64,
    has_duration: bool,
) -> Vec<(String, String)> {
    let step = match c.solver {
        Solver::Explicit => ("dt".to_string(), format!("auto(safety: {})", c.safety)),
        Solver::QuasiStatic => ("integrator".to_string(), "quasi_static".to_string()),
        Solver::ImplicitEuler => (
            "dt".to_string(),
            format!("{:e} s", duration / IMPLICIT_STEPS as f64),
        ),
    };
    let mut settings = vec![
        step,
        (
            "precision".to_string(),
            match c.precision {
                Precision::F32 => "f32".into(),
                _ => "f64".into(),
            },
        ),
    ];
    match c.solver {
        Solver::ImplicitEuler => {
            settings.push(("integrator".into(), "implicit_euler".into()));
            // A script's `steps` (it has no `duration` then) would count steps of the new dt.
            if !has_duration {
                settings.push(("steps".into(), IMPLICIT_STEPS.to_string()));
            }
        }
        // One state, at the end: the script's `steps` would be as many equilibrium states
        // (4,000 solves of the benchmark beam for the one value measured).
        Solver::QuasiStatic if duration > 0.0 => {
            settings.push(("duration".into(), format!("{duration:e} s")));
            settings.push(("steps".into(), "1".into()));
        }
        _ => {}
    }
    if c.springs {
        let alpha = sweep.springs.clone().unwrap_or_default();
        settings.push((
            "model".into(),
            format!("springs(volume_stiffness: {alpha})"),
        ));
    } else {
        settings.push(("model".into(), "fem".into()));
    }
    settings
}

/// Run one compiled variant to its steady state.
fn measure(
    scene: &Scene,
    script: &Path,
    label: &str,
    c: &Config,
    sweep: &Sweep,
    set_index: Option<usize>,
) -> Result<Point, String> {
    let t0 = Instant::now();
    // The implicit solvers' tangent kernels are in the adjoint module.
    let module = match c.solver {
        Solver::Explicit => &scene.lowered.module,
        _ => &scene.lowered.adjoint.module,
    };
    let cpu = Cpu::new(module, c.precision, sweep.threads)?;
    let compile_seconds = t0.elapsed().as_secs_f64();
    let mut sim = Simulation::new(scene, cpu);
    let t1 = Instant::now();
    let run = match c.solver {
        Solver::Explicit => {
            let (dt, steps) = sim.time_steps(None, None).map_err(|e| e.0)?;
            sim.run_to_steady_state(Some(dt), 4 * steps, c.settle)
        }
        _ => sim.run(None, None).map(|summary| crate::engine::SteadyRun {
            settled: summary.solver.as_ref().is_some_and(|s| s.converged),
            summary,
        }),
    }
    .map_err(|e| format!("{label}: {e}"))?;
    let dt = run.summary.dt;
    let seconds = t1.elapsed().as_secs_f64();
    let value = match set_index {
        Some(i) => {
            let (_, nodes) = &scene.node_sets[i];
            let [mean, _, _] =
                crate::outputs::set_displacement(nodes, &scene.mesh.nodes, |n| run.summary.x[n]);
            mean[sweep.axis]
        }
        None => run
            .summary
            .loss
            .ok_or_else(|| format!("{label}: the run computed no loss"))?,
    };
    Ok(Point {
        label: label.to_string(),
        solver: c.solver.name().to_string(),
        resolution: c.resolution,
        tets: scene.mesh.tets.len(),
        precision: match c.precision {
            Precision::F32 => "f32".into(),
            _ => "f64".into(),
        },
        model: model_name(c).into(),
        order: c.order,
        nodes: scene.mesh.nodes.len(),
        safety: c.safety,
        settle: c.settle,
        dt,
        steps: run.summary.steps,
        settled: run.settled,
        value,
        error: f64::NAN,
        seconds,
        compile_seconds,
        pareto: false,
        script: script.to_path_buf(),
    })
}

/// Richardson extrapolation over the f64 FEM resolution series of one integrator (explicit at
/// its first settings, else the quasi-static solves, else implicit Euler: whichever the sweep
/// ran) at the baseline's element order, with the order observed from the three finest; else
/// the finest of them.
fn reference(points: &[Point]) -> Reference {
    let fem = points
        .iter()
        .map(|p| p.model.as_str())
        .find(|m| m.starts_with("fem"))
        .unwrap_or("fem");
    let accurate = |p: &Point| p.precision == "f64" && p.model == fem;
    let solver = ["explicit", "quasi_static", "implicit_euler"]
        .into_iter()
        .find(|s| points.iter().any(|p| accurate(p) && p.solver == *s));
    // An explicit series keeps one safety and settle tolerance (the first listed).
    let base = points
        .iter()
        .find(|p| accurate(p) && Some(p.solver.as_str()) == solver);
    let mut series: Vec<&Point> = points
        .iter()
        .filter(|p| match base {
            Some(b) => {
                accurate(p) && p.solver == b.solver && p.safety == b.safety && p.settle == b.settle
            }
            None => true,
        })
        .collect();
    series.sort_by(|a, b| a.resolution.total_cmp(&b.resolution));
    series.dedup_by(|a, b| a.resolution == b.resolution);
    let finest = series.last().copied().unwrap_or(&points[0]);
    let what = match base {
        Some(b) => format!(
            "{} f64 {}",
            b.solver,
            if b.order == 2 { "quadratic FEM" } else { "FEM" }
        ),
        // Only f32 or spring runs: the finest of them is all there is.
        None => format!("{} {} {}", finest.solver, finest.precision, finest.model),
    };
    let fallback = |why: &str| Reference {
        value: finest.value,
        method: format!(
            "the finest {what} solution (resolution {}, {} tets): {why}",
            finest.resolution, finest.tets
        ),
        order: None,
    };
    let n = series.len();
    if n < 3 {
        return fallback("fewer than three resolutions to extrapolate from");
    }
    let (a, b, c) = (series[n - 3], series[n - 2], series[n - 1]);
    // Cell size h ∝ 1/resolution; u(h) = u* + C·h^p.
    let (h1, h2, h3) = (1.0 / a.resolution, 1.0 / b.resolution, 1.0 / c.resolution);
    let (u1, u2, u3) = (a.value, b.value, c.value);
    let ratio = (u1 - u2) / (u2 - u3);
    if !ratio.is_finite() || ratio <= 1.0 {
        return fallback("the three finest resolutions do not converge monotonically");
    }
    let f = |p: f64| (h1.powf(p) - h2.powf(p)) / (h2.powf(p) - h3.powf(p)) - ratio;
    let (mut lo, mut hi) = (0.05, 8.0);
    if f(lo) * f(hi) > 0.0 {
        return fallback("no convergence order in (0.05, 8) fits the three finest resolutions");
    }
    for _ in 0..100 {
        let mid = 0.5 * (lo + hi);
        if f(lo) * f(mid) <= 0.0 {
            hi = mid;
        } else {
            lo = mid;
        }
    }
    let p = 0.5 * (lo + hi);
    let cst = (u2 - u3) / (h2.powf(p) - h3.powf(p));
    let value = u3 - cst * h3.powf(p);
    if !(0.3..=4.0).contains(&p) {
        return fallback(&format!("the observed order {p:.2} is not credible"));
    }
    Reference {
        value,
        method: format!(
            "Richardson extrapolation of the {what} solutions at resolutions {}, {}, {} \
             (observed order {p:.2} in the cell size)",
            a.resolution, b.resolution, c.resolution
        ),
        order: Some(p),
    }
}

/// A point is on the Pareto front when no other point is at least as fast and as accurate and
/// strictly better in one.
fn mark_pareto(points: &mut [Point]) {
    let flags: Vec<bool> = points
        .iter()
        .map(|p| {
            !points.iter().any(|q| {
                q.seconds <= p.seconds
                    && q.error <= p.error
                    && (q.seconds < p.seconds || q.error < p.error)
            })
        })
        .collect();
    for (p, f) in points.iter_mut().zip(flags) {
        p.pareto = f;
    }
}

fn print_table(points: &[Point], reference: &Reference, sweep: &Sweep, out: &mut dyn Write) {
    let _ = writeln!(
        out,
        "{:<14} {:<6} {:>7} {:>7} {:<4} {:<8} {:>6} {:>8} {:>10} {:>8} {:>8} {:>14} {:>10} {:>9}  pareto",
        "solver",
        "res",
        "tets",
        "nodes",
        "prec",
        "model",
        "safety",
        "settle",
        "dt_s",
        "steps",
        "wall_s",
        "value_m",
        "rel_err",
        "settled"
    );
    let mut sorted: Vec<&Point> = points.iter().collect();
    sorted.sort_by(|a, b| a.seconds.total_cmp(&b.seconds));
    for p in sorted {
        let _ = writeln!(
            out,
            "{:<14} {:<6} {:>7} {:>7} {:<4} {:<8} {:>6} {:>8.0e} {:>10.3e} {:>8} {:>8.2} {:>14.6e} {:>10.2e} {:>9}  {}",
            p.solver,
            p.resolution,
            p.tets,
            p.nodes,
            p.precision,
            p.model,
            p.safety,
            p.settle,
            p.dt,
            p.steps,
            p.seconds,
            p.value,
            p.error,
            if p.settled { "yes" } else { "no" },
            if p.pareto { "*" } else { "" }
        );
    }
    let _ = writeln!(
        out,
        "output: {}; reference {:.6e} = {}",
        output_name(sweep),
        reference.value,
        reference.method
    );
    let _ = writeln!(
        out,
        "wall_s: stable-step estimate + time steps, or the static / implicit solve, on the cpu \
         backend (compile excluded); safety and settle are 0 for the implicit solvers; \
         * = Pareto front (no other run is both faster and more accurate)"
    );
}

fn write_outputs(points: &[Point], reference: &Reference, sweep: &Sweep) -> Result<(), String> {
    let json = serde_json::json!({
        "script": sweep.script,
        "output": format!("{}.{}", sweep.set, ["x", "y", "z"][sweep.axis]),
        "reference": reference,
        "points": points,
    });
    let path = sweep.out.join("tradeoff.json");
    crate::outputs::atomic::write_atomically(
        &path,
        serde_json::to_string_pretty(&json)
            .unwrap_or_default()
            .as_bytes(),
    )
    .map_err(|e| format!("cannot write {}: {e}", path.display()))?;
    let scatter: Vec<crate::optim::plot::ScatterPoint> = points
        .iter()
        .map(|p| crate::optim::plot::ScatterPoint {
            x: p.seconds,
            y: p.error,
            group: format!("{} {}", p.model, p.precision),
            label: short_label(p),
            highlight: p.pareto,
        })
        .collect();
    crate::optim::plot::write_scatter(
        &sweep.out.join("tradeoff"),
        &format!(
            "{}: error of {}.{} vs wall time",
            sweep.script.display(),
            sweep.set,
            ["x", "y", "z"][sweep.axis]
        ),
        "wall time (s)",
        "relative error",
        &scatter,
    )?;
    Ok(())
}

fn short_label(p: &Point) -> String {
    format!("r{} s{} e{:.0e}", p.resolution, p.safety, p.settle)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn point(resolution: f64, value: f64) -> Point {
        Point {
            label: String::new(),
            solver: "explicit".into(),
            resolution,
            tets: 0,
            precision: "f64".into(),
            model: "fem".into(),
            order: 1,
            nodes: 0,
            safety: 0.9,
            settle: 1e-4,
            dt: 1e-4,
            steps: 1,
            settled: true,
            value,
            error: f64::NAN,
            seconds: resolution,
            compile_seconds: 0.0,
            pareto: false,
            script: PathBuf::new(),
        }
    }

    #[test]
    fn richardson_recovers_the_limit_and_the_order() {
        // u(h) = 2 + 3 h^2 with h = 1/resolution, at non-uniform refinements.
        let points: Vec<Point> = [0.5, 1.0, 1.5]
            .iter()
            .map(|&r| point(r, 2.0 + 3.0 / (r * r)))
            .collect();
        let r = reference(&points);
        assert!((r.value - 2.0).abs() < 1e-9, "{r:?}");
        assert!((r.order.unwrap() - 2.0).abs() < 1e-6, "{r:?}");
        // Oscillating values are not extrapolated.
        let points = vec![point(0.5, 1.0), point(1.0, 3.0), point(1.5, 2.0)];
        let r = reference(&points);
        assert_eq!(r.value, 2.0);
        assert!(r.method.contains("finest"), "{r:?}");
    }

    /// Issue 31 item 5: a sweep of static solves only took its first listed resolution as
    /// "the finest" (the coarsest, with --resolutions 1,1.5,2), so that mesh got error 0.
    #[test]
    fn a_static_only_sweep_is_measured_against_its_own_finest_series() {
        let statics = |rs: &[f64]| -> Vec<Point> {
            rs.iter()
                .map(|&r| Point {
                    solver: "quasi_static".into(),
                    safety: 0.0,
                    settle: 0.0,
                    ..point(r, 2.0 + 3.0 / (r * r))
                })
                .collect()
        };
        // Three resolutions, listed coarse to fine: extrapolated.
        let r = reference(&statics(&[1.0, 1.5, 2.0]));
        assert!((r.value - 2.0).abs() < 1e-9, "{r:?}");
        assert!(r.method.contains("quasi_static f64 FEM"), "{r:?}");
        // Two, listed fine to coarse: the finest, not the first listed.
        let r = reference(&statics(&[2.0, 1.0]));
        assert_eq!(r.value, 2.0 + 3.0 / 4.0, "{r:?}");
        assert!(r.method.contains("resolution 2,"), "{r:?}");
        // Explicit runs are preferred where the sweep has them.
        let mut mixed = statics(&[1.0, 1.5, 2.0]);
        mixed.push(point(1.0, 7.0));
        assert_eq!(reference(&mixed).value, 7.0);
    }

    #[test]
    fn the_pareto_front_holds_the_points_nothing_beats() {
        let mut points = vec![point(1.0, 0.0), point(2.0, 0.0), point(3.0, 0.0)];
        for (p, e) in points.iter_mut().zip([0.1, 0.2, 0.01]) {
            p.error = e;
        }
        mark_pareto(&mut points);
        let flags: Vec<bool> = points.iter().map(|p| p.pareto).collect();
        assert_eq!(flags, [true, false, true]);
    }
}
