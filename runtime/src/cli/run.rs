//! `softc run`: simulate a script and report a JSON summary.

use crate::engine::scene::Scene;
use crate::engine::{Cpu, Interpreter, RunSummary, Simulation};
use clap::{Args, ValueEnum};
use softc_compiler::back::Precision;
use std::io::Write;
use std::path::PathBuf;

#[derive(Args, Debug)]
pub struct RunArgs {
    /// The script to run.
    pub file: PathBuf,
    /// Which backend runs the kernels.
    #[arg(long, value_enum, default_value_t = BackendChoice::Cpu)]
    pub backend: BackendChoice,
    /// Floating-point precision of the kernels (cpu: default f64; gpu: default f32; the
    /// interpreter is f64). The script's `precision` setting applies when this is not given.
    #[arg(long, value_enum)]
    pub precision: Option<PrecisionChoice>,
    /// The GPU adapter of `--backend gpu`: a case-insensitive part of its name (or a backend
    /// name such as `vulkan`); default: a discrete GPU, else integrated, else software.
    #[arg(long, value_name = "NAME")]
    pub adapter: Option<String>,
    /// Worker threads of the cpu backend (default: all cores for launches of 8,000+ entities, else 1).
    #[arg(long)]
    pub threads: Option<usize>,
    /// Override a param's value, with its unit: `--set p_max=2.5kPa`.
    #[arg(long = "set", value_name = "NAME=VALUE")]
    pub set: Vec<String>,
    /// Override the number of steps.
    #[arg(long)]
    pub steps: Option<u64>,
    /// Override the time step, with its unit: `--dt 20us`.
    #[arg(long)]
    pub dt: Option<String>,
    /// Write the JSON summary here (SI units).
    #[arg(long)]
    pub json: Option<PathBuf>,
    /// Write a ParaView series (`.pvd` + `.vtu`) into this folder, every N steps as the
    /// script's `output vtk every N steps` says (default 100).
    #[arg(long)]
    pub vtk: Option<PathBuf>,
}

#[derive(Copy, Clone, Debug, PartialEq, Eq, ValueEnum)]
pub enum PrecisionChoice {
    F32,
    F64,
}

#[derive(Copy, Clone, Debug, PartialEq, Eq, ValueEnum)]
pub enum BackendChoice {
    /// Native code through Cranelift, multi-threaded, deterministic.
    Cpu,
    /// The kernel-IR interpreter: the reference semantics of the kernels, slow.
    Interp,
    /// The plain-Rust f64 reference simulator (the test oracle).
    Reference,
    /// WGSL kernels on a GPU through wgpu (Vulkan, Metal, DX12; lavapipe without a GPU).
    Gpu,
}

/// Parse a value with its unit (`2.5kPa`, `20 us`) with the language's own front end.
fn parse_quantity(text: &str) -> Result<(f64, softc_compiler::sema::units::Dim), String> {
    let src = format!("let __value = {text}");
    let ast = softc_compiler::front::parse(&src).map_err(|d| format!("`{text}`: {}", d.message))?;
    let Some(softc_compiler::front::ast::Item {
        kind: softc_compiler::front::ast::ItemKind::Let(l),
        ..
    }) = ast.items.first()
    else {
        return Err(format!("`{text}` is not a value"));
    };
    let (num, dim) = match &l.value.kind {
        softc_compiler::front::ast::ExprKind::Number { value, unit, .. } => {
            let mut factor = 1.0;
            let mut dim = softc_compiler::sema::units::Dim::NONE;
            for f in unit.iter().flat_map(|u| &u.factors) {
                let (k, d) = softc_compiler::sema::units::unit(&f.name)
                    .ok_or_else(|| format!("unknown unit `{}` in `{text}`", f.name))?;
                factor *= k.powi(f.power);
                dim = dim.times(d.powi(f.power).unwrap_or(d));
            }
            (value * factor, dim)
        }
        _ => return Err(format!("`{text}` is not a number with a unit")),
    };
    Ok((num, dim))
}

pub fn run(args: RunArgs, out: &mut dyn Write, err: &mut dyn Write) -> i32 {
    if let Err(e) = std::fs::metadata(&args.file) {
        let _ = writeln!(err, "softc: cannot read `{}`: {e}", args.file.display());
        return 2;
    }
    let mut overrides = Vec::new();
    for s in &args.set {
        let Some((name, value)) = s.split_once('=') else {
            let _ = writeln!(err, "softc: --set expects NAME=VALUE, found `{s}`");
            return 2;
        };
        match parse_quantity(value) {
            Ok((v, _)) => overrides.push((name.trim().to_string(), v)),
            Err(e) => {
                let _ = writeln!(err, "softc: --set {name}: {e}");
                return 2;
            }
        }
    }
    let dt = match args.dt.as_deref().map(parse_quantity).transpose() {
        Ok(v) => v.map(|(x, _)| x),
        Err(e) => {
            let _ = writeln!(err, "softc: --dt: {e}");
            return 2;
        }
    };
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
                .is_some_and(|rest| rest == name || rest.starts_with(&format!("{name}.")))
        });
        if !known {
            let _ = writeln!(err, "softc: --set {name}: the script has no param `{name}`");
            return 2;
        }
    }
    let result = match args.backend {
        BackendChoice::Reference => {
            crate::reference::run(&scene, dt, args.steps).and_then(|mut s| {
                // The oracle's own job is the state; an at-end loss is evaluated on its final state.
                if let Some(l) = crate::engine::loss::Loss::build(&scene, s.dt, s.steps)?
                    && l.window == crate::engine::loss::LossWindow::End
                {
                    let x: Vec<f64> = s.x.iter().flatten().copied().collect();
                    let v: Vec<f64> = s.v.iter().flatten().copied().collect();
                    s.loss = Some(l.eval(&scene, &x, &v, s.steps as f64 * s.dt, &scene.uniforms));
                }
                Ok((s, "reference"))
            })
        }
        BackendChoice::Interp => {
            let mut sim = Simulation::new(&scene, Interpreter::new(&scene.lowered.module));
            sim.vtk = match vtk_output(&args, &scene, err) {
                Ok(v) => v,
                Err(code) => return code,
            };
            if let Err(e) = announce_dt(&mut sim, dt, err) {
                let _ = writeln!(err, "{}: {e}", args.file.display());
                return 1;
            }
            sim.run(dt, args.steps)
                .map(|s| (s, "interp"))
                .map_err(|e| e.0)
        }
        BackendChoice::Gpu => {
            let precision = match (args.precision, scene.precision_setting()) {
                (Some(PrecisionChoice::F64), _) | (None, Some("f64")) => Precision::F64,
                _ => Precision::F32,
            };
            let gpu = match crate::devices::gpu::Gpu::new(
                &scene.lowered.module,
                precision,
                args.adapter.as_deref(),
            ) {
                Ok(g) => g,
                Err(e) => {
                    let _ = writeln!(err, "{}: {e}", args.file.display());
                    return 1;
                }
            };
            let _ = writeln!(err, "adapter: {}; kernels in {precision}", gpu.adapter());
            let mut sim = Simulation::new(&scene, gpu);
            sim.vtk = match vtk_output(&args, &scene, err) {
                Ok(v) => v,
                Err(code) => return code,
            };
            if let Err(e) = announce_dt(&mut sim, dt, err) {
                let _ = writeln!(err, "{}: {e}", args.file.display());
                return 1;
            }
            sim.run(dt, args.steps).map(|s| (s, "gpu")).map_err(|e| e.0)
        }
        _ => {
            let precision = match (args.precision, scene.precision_setting()) {
                (Some(PrecisionChoice::F32), _) | (None, Some("f32")) => Precision::F32,
                _ => Precision::F64,
            };
            let cpu = match Cpu::new(&scene.lowered.module, precision, args.threads) {
                Ok(c) => c,
                Err(e) => {
                    let _ = writeln!(
                        err,
                        "{}: the kernels do not compile: {e}",
                        args.file.display()
                    );
                    return 1;
                }
            };
            let mut sim = Simulation::new(&scene, cpu);
            sim.vtk = match vtk_output(&args, &scene, err) {
                Ok(v) => v,
                Err(code) => return code,
            };
            if let Err(e) = announce_dt(&mut sim, dt, err) {
                let _ = writeln!(err, "{}: {e}", args.file.display());
                return 1;
            }
            sim.run(dt, args.steps).map(|s| (s, "cpu")).map_err(|e| e.0)
        }
    };
    let (summary, backend_name) = match result {
        Ok(s) => s,
        Err(e) => {
            let _ = writeln!(err, "{}: {e}", args.file.display());
            return 1;
        }
    };
    let json = summary_json(&scene, &summary, backend_name);
    let text = serde_json::to_string_pretty(&json).unwrap_or_default();
    let _ = writeln!(
        err,
        "{}: {} steps of {:e} s in {:.3} s ({:.0} steps/s, backend {})",
        args.file.display(),
        summary.steps,
        summary.dt,
        summary.wall_seconds,
        summary.steps as f64 / summary.wall_seconds.max(1e-12),
        backend_name
    );
    match &args.json {
        Some(path) => {
            if let Err(e) = super::write_atomically(path, text.as_bytes()) {
                let _ = writeln!(err, "softc: cannot write `{}`: {e}", path.display());
                return 2;
            }
        }
        None => {
            let _ = writeln!(out, "{text}");
        }
    }
    0
}

/// Print the stable-step estimate before a run, and warn when the step exceeds it.
fn announce_dt<B: crate::engine::Backend>(
    sim: &mut Simulation<B>,
    dt: Option<f64>,
    err: &mut dyn Write,
) -> Result<(), String> {
    let est = sim.stable_dt_estimate().map_err(|e| e.0)?;
    let chosen = match (dt, sim.scene.dt) {
        (Some(d), _) => Some(d),
        (None, crate::engine::scene::DtChoice::Given(d)) => Some(d),
        (None, crate::engine::scene::DtChoice::Auto { safety }) => Some(safety * est),
    };
    let _ = writeln!(
        err,
        "stable step estimate (2/omega_max of M^-1 K at rest): {est:e} s; dt = {:e} s",
        chosen.unwrap_or(est)
    );
    if let Some(d) = chosen
        && d > est
    {
        let _ = writeln!(
            err,
            "warning: dt = {d:e} s exceeds the stable step {est:e} s of this mesh and material; \
             the run will likely blow up. Use `dt = auto` or dt <= {:e} s",
            0.9 * est
        );
    }
    Ok(())
}

/// The VTK series asked for with `--vtk DIR`.
fn vtk_output(
    args: &RunArgs,
    scene: &Scene,
    err: &mut dyn Write,
) -> Result<Option<crate::engine::VtkOutput>, i32> {
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
    Ok(Some(crate::engine::VtkOutput {
        series: crate::mesh::writers::PvdSeries::new(
            dir,
            &name,
            crate::mesh::LengthUnit::Millimetre,
        ),
        every,
    }))
}

/// `output vtk every N steps` in the sim block.
fn vtk_every(scene: &Scene) -> Option<u64> {
    use softc_compiler::front::ast::{ExprKind, ItemKind, StmtKind};
    scene.ast.items.iter().find_map(|i| match &i.kind {
        ItemKind::Sim(stmts) => stmts.iter().find_map(|s| match &s.kind {
            StmtKind::Output {
                what,
                every,
                steps: true,
            } if matches!(&what.kind, ExprKind::Name(n) if n.name == "vtk") => match &every.kind {
                ExprKind::Number { value, .. } => Some(*value as u64),
                _ => None,
            },
            _ => None,
        }),
        _ => None,
    })
}

/// The JSON summary: SI units throughout.
pub fn summary_json(scene: &Scene, s: &RunSummary, backend: &str) -> serde_json::Value {
    let mut sets = serde_json::Map::new();
    for (name, nodes) in &scene.node_sets {
        let mut mean = [0.0; 3];
        let mut min = [f64::INFINITY; 3];
        let mut max = [f64::NEG_INFINITY; 3];
        for &n in nodes {
            let (x, x0) = (s.x[n as usize], scene.mesh.nodes[n as usize]);
            for d in 0..3 {
                let u = x[d] - x0[d];
                mean[d] += u / nodes.len().max(1) as f64;
                min[d] = min[d].min(u);
                max[d] = max[d].max(u);
            }
        }
        sets.insert(
            name.clone(),
            serde_json::json!({
                "nodes": nodes.len(),
                "mean_displacement": mean,
                "min_displacement": min,
                "max_displacement": max,
            }),
        );
    }
    serde_json::json!({
        "script": scene.script.display().to_string(),
        "backend": backend,
        "loss": s.loss,
        "steps": s.steps,
        "dt": s.dt,
        "dt_stable_estimate": s.dt_stable_estimate,
        "simulated_time": s.steps as f64 * s.dt,
        "wall_seconds": s.wall_seconds,
        "steps_per_second": s.steps as f64 / s.wall_seconds.max(1e-12),
        "nodes": scene.mesh.nodes.len(),
        "elements": scene.mesh.tets.len(),
        "sets": sets,
    })
}
