//! How a run of a script is set up, below the command line that asks for it: values with
//! their units (`--set`, `--dt`, `--memory-budget`), the backward pass's settings and the
//! script's own `output` statements. Shared by `softc run`, its optimization and `softc bench`.

use crate::engine::adjoint::{Checkpointing, GradOptions};
use crate::engine::scene::Scene;
use crate::outputs::csv::CsvOutput;
use std::io::Write;
use std::path::Path;

/// Parse a value with its unit (`2.5kPa`, `20 us`) with the language's own front end.
pub fn parse_quantity(text: &str) -> Result<(f64, softc_compiler::driver::Dim), String> {
    softc_compiler::driver::parse_quantity(text)
}

/// A `--set NAME=VALUE` flag, read: the value in SI units and the dimension its unit has.
#[derive(Clone, Debug)]
pub struct SetFlag {
    pub name: String,
    /// As written after `=`.
    pub text: String,
    pub value: f64,
    pub dim: softc_compiler::driver::Dim,
}

/// Read a `--set NAME=VALUE` flag (`p_max=2.5kPa`, `p=-3kPa`, `beta.3=15/s`); the value's
/// dimension is checked against the script's declaration by [`check_set_dims`].
pub fn parse_set(flag: &str) -> Result<SetFlag, String> {
    let Some((name, text)) = flag.split_once('=') else {
        return Err(format!(
            "--set expects NAME=VALUE with a unit, e.g. `--set p_max=2.5kPa`; found `{flag}`"
        ));
    };
    let name = name.trim();
    if name.is_empty() {
        return Err(format!("--set {flag}: the name before `=` is missing"));
    }
    let (value, dim) = parse_quantity(text.trim()).map_err(|e| format!("--set {name}: {e}"))?;
    if !value.is_finite() {
        return Err(format!(
            "--set {name}={text}: the value is not a finite number"
        ));
    }
    Ok(SetFlag {
        name: name.to_string(),
        text: text.trim().to_string(),
        value,
        dim,
    })
}

/// `--set` values must have the dimension of the param or input they set: `p_peak=3mm` is a
/// length, not a pressure, and a bare `p_peak=3` has no unit (units are required). Names the
/// script does not declare are left to the caller.
pub fn check_set_dims(
    resolved: &softc_compiler::driver::Resolved,
    sets: &[SetFlag],
) -> Result<(), String> {
    for s in sets {
        let Some(want) = resolved.value_dim(&s.name) else {
            continue;
        };
        if want == s.dim {
            continue;
        }
        let si = want.si_unit();
        let example = format!(
            "--set {}={}{}",
            s.name,
            s.text
                .trim_end_matches(|c: char| !(c.is_ascii_digit() || c == '.'))
                .trim(),
            si.strip_prefix('1').unwrap_or(&si)
        );
        let base = s.name.split('.').next().unwrap_or(&s.name);
        let want_a = with_article(&want.name());
        return Err(if s.dim.is_none() {
            format!(
                "--set {}={}: the value has no unit, and `{base}` is {want_a}: write it with a \
                 unit of {want} (SI: {si}), e.g. `{example}`",
                s.name, s.text
            )
        } else {
            format!(
                "--set {}={}: `{}` is {}, but `{base}` is {want_a}: give a value in a unit of \
                 {want} (SI: {si}), e.g. `{example}`",
                s.name,
                s.text,
                s.text,
                with_article(&s.dim.name())
            )
        });
    }
    Ok(())
}

/// `a length`, `an acceleration`.
fn with_article(noun: &str) -> String {
    let vowel = noun.starts_with(|c: char| "aeiou".contains(c));
    format!("{} {noun}", if vowel { "an" } else { "a" })
}

/// `--dt VALUE`: a positive, finite time with its unit (`20us`).
pub fn parse_dt(text: &str) -> Result<f64, String> {
    let (dt, dim) = parse_quantity(text.trim()).map_err(|e| format!("--dt: {e}"))?;
    if dim != softc_compiler::driver::Dim::TIME {
        return Err(if dim.is_none() {
            format!("--dt {text}: the value has no unit; write a time, e.g. `--dt 20us`")
        } else {
            format!(
                "--dt {text}: `{text}` is {}, not a time; write a time, e.g. `--dt 20us`",
                with_article(&dim.name())
            )
        });
    }
    if !(dt > 0.0 && dt.is_finite()) {
        return Err(format!(
            "--dt {text}: the time step must be positive and finite, e.g. `--dt 20us`"
        ));
    }
    Ok(dt)
}

/// The most steps a run takes without being asked for them: a step count from the script's
/// `duration` and a tiny dt (`dt = 1e-12 s`, 10¹² steps over 1 s) would run for days
/// silently. 10 million steps of the 1k benchmark scene are about 20 minutes on one core.
pub const MAX_UNASKED_STEPS: u64 = 10_000_000;

/// Refuse a step count over [`MAX_UNASKED_STEPS`] that comes from `duration / dt`, unless it
/// was asked for (`--steps`, or the script's `steps =`). `estimate` is the stable step.
pub fn check_step_count(
    scene: &Scene,
    dt: f64,
    steps: u64,
    steps_flag: bool,
    estimate: Option<f64>,
) -> Result<(), String> {
    let sim = &scene.resolved.sim;
    if steps_flag || sim.steps.is_some() || steps <= MAX_UNASKED_STEPS {
        return Ok(());
    }
    let duration = sim.duration.unwrap_or(steps as f64 * dt);
    let auto = estimate.map_or(String::new(), |e| {
        format!(" (`dt = auto` takes 0.9 of the stable step, {e:.3e} s here)")
    });
    Err(format!(
        "dt = {dt:e} s over duration = {duration:e} s makes {steps} steps, more than the \
         {MAX_UNASKED_STEPS} softc runs unless asked: use a larger dt{auto} or a shorter \
         duration, or ask for the steps with --steps {steps}"
    ))
}

/// The step size and step count a run of `sim` will take, refused as [`check_step_count`]
/// says when the count is too large and was not asked for (`steps`).
pub fn checked_time_steps<B: crate::devices::Backend>(
    sim: &mut crate::engine::Simulation<B>,
    dt: Option<f64>,
    steps: Option<u64>,
) -> Result<(f64, u64), String> {
    let (step, n) = sim.time_steps(dt, steps).map_err(|e| e.0)?;
    let estimate = sim.stable_dt_estimate().ok();
    check_step_count(sim.scene, step, n, steps.is_some(), estimate)?;
    Ok((step, n))
}

/// The backward pass's settings: the optimize block's `checkpoint`, `memory_budget` and
/// `truncate`, overridden by `checkpoint` (`--checkpoint`) and `memory_budget`
/// (`--memory-budget`).
pub fn grad_options(
    scene: &Scene,
    checkpoint: Option<&str>,
    memory_budget: Option<&str>,
) -> Result<GradOptions, String> {
    use softc_compiler::driver::CheckpointSpec;
    let mut o = GradOptions::default();
    let script = &scene.resolved.grad;
    if let Some(c) = script.checkpoint {
        o.checkpoint = match c {
            CheckpointSpec::Auto => Checkpointing::Auto,
            CheckpointSpec::StoreAll => Checkpointing::StoreAll,
            CheckpointSpec::Periodic(k) => Checkpointing::Periodic(k),
            CheckpointSpec::Revolve(n) => Checkpointing::Revolve(n),
        };
    }
    if script.memory_budget.is_some() {
        o.memory_budget = script.memory_budget;
    }
    if script.truncate.is_some() {
        o.truncate = script.truncate;
    }
    if let Some(c) = checkpoint {
        o.checkpoint = parse_checkpoint(c)?;
    }
    if let Some(m) = memory_budget {
        o.memory_budget = Some(parse_memory_budget(m)?);
    }
    Ok(o)
}

/// `--checkpoint auto|store_all|periodic:K|revolve:N`.
pub fn parse_checkpoint(c: &str) -> Result<Checkpointing, String> {
    let number = |s: &str| {
        s.trim()
            .parse::<u64>()
            .ok()
            .filter(|n| *n >= 1)
            .ok_or_else(|| format!("--checkpoint {c}: expected a positive integer after `:`"))
    };
    Ok(match c.split_once(':') {
        None if c == "auto" => Checkpointing::Auto,
        None if c == "store_all" => Checkpointing::StoreAll,
        Some(("periodic", k)) => Checkpointing::Periodic(number(k)?),
        Some(("revolve", n)) => Checkpointing::Revolve(number(n)? as usize),
        _ => {
            return Err(format!(
                "--checkpoint {c}: expected auto, store_all, periodic:K or revolve:N"
            ));
        }
    })
}

/// `--memory-budget 512MB`: a positive memory size, in bytes.
pub fn parse_memory_budget(m: &str) -> Result<u64, String> {
    let (bytes, dim) = parse_quantity(m).map_err(|e| format!("--memory-budget: {e}"))?;
    if dim != softc_compiler::driver::Dim::MEMORY || !(bytes >= 1.0 && bytes.is_finite()) {
        return Err(format!(
            "--memory-budget {m}: expected a positive memory size such as 512MB or 2GiB"
        ));
    }
    Ok(bytes as u64)
}

/// The node-set logs of the script's `output csv(SET) every …` statements, written into
/// `dir` (`--csv DIR`); without it, a note says how to get them.
pub fn csv_outputs(
    dir: Option<&Path>,
    scene: &Scene,
    dt: f64,
    err: &mut dyn Write,
) -> Result<Vec<Box<dyn crate::engine::NodeSetLog>>, String> {
    let mut outputs: Vec<Box<dyn crate::engine::NodeSetLog>> = Vec::new();
    for log in &scene.resolved.sim.csv {
        let Some(dir) = dir else {
            let _ = writeln!(
                err,
                "note: the script logs `{}` (`output csv`); add --csv DIR to write it",
                log.set
            );
            continue;
        };
        let every_steps = if log.in_steps {
            log.every.round().max(1.0) as u64
        } else {
            (log.every / dt).round().max(1.0) as u64
        };
        let nodes = scene
            .node_sets
            .iter()
            .find(|(n, _)| *n == log.set)
            .map(|(_, nodes)| nodes.clone())
            .ok_or_else(|| format!("`output csv({})`: no node set of that name", log.set))?;
        std::fs::create_dir_all(dir)
            .map_err(|e| format!("cannot create `{}`: {e}", dir.display()))?;
        outputs.push(Box::new(CsvOutput::new(
            dir.join(format!("{}.csv", log.set)),
            nodes,
            every_steps,
        )));
    }
    Ok(outputs)
}

/// `output vtk every N steps` in the sim block.
pub fn vtk_every(scene: &Scene) -> Option<u64> {
    scene.resolved.sim.vtk_every
}

/// The warnings for a run that ended without error but whose answer is doubtful or rests on
/// a convention, each a sentence without the `warning: ` the CLI prints before it: a static
/// body held at one point or along one line (free to rotate: the answer is the one without
/// that rotation), linear tetrahedra of a nearly incompressible material (they lock), a static
/// or implicit solve whose last state did not reach its residual (a load below what the
/// precision resolves), or a run whose loss is taken `at end` while its final state still
/// moves. The JSON summary lists them (`warnings`), the Python package warns with them.
pub fn run_warnings(
    scene: &crate::engine::scene::Scene,
    summary: &crate::engine::RunSummary,
) -> Vec<String> {
    let held = summary
        .solver
        .as_ref()
        .filter(|s| matches!(s.free_motion_kind, Some("point" | "line")))
        .and_then(|s| s.free_motion.as_deref())
        .map(|m| {
            format!(
                "warning: the body is free to rotate ({m}); the static solve held that \
                 rotation and posed the equilibrium to best match the rest shape about the \
                 fixed nodes. Fix a region that spans the body's support (three or more nodes \
                 not on one line) if the body is meant to be held"
            )
        });
    [
        held,
        crate::engine::incompressibility::locking_warning(scene),
        doubtful(scene, summary),
    ]
    .into_iter()
    .flatten()
    .map(|w| w.trim_start_matches("warning: ").to_string())
    .collect()
}

/// [`run_warnings`] as the CLI prints them: one line each, after `warning: `.
pub fn run_warning(
    scene: &crate::engine::scene::Scene,
    summary: &crate::engine::RunSummary,
) -> Option<String> {
    let warnings = run_warnings(scene, summary);
    (!warnings.is_empty()).then(|| {
        warnings
            .iter()
            .map(|w| format!("warning: {w}"))
            .collect::<Vec<_>>()
            .join("\n")
    })
}

fn doubtful(
    scene: &crate::engine::scene::Scene,
    summary: &crate::engine::RunSummary,
) -> Option<String> {
    if let Some(solver) = &summary.solver
        && !solver.converged
    {
        if solver.position_round_off >= 1e-2 {
            return Some(format!(
                "warning: the {} solve's displacements are at the round-off of f32 positions: \
                 storing its equilibrium (refined in f64) in f32 changed a displacement by \
                 {:.1} % of the largest (`converged`: false); use `precision = f64` or \
                 larger loads",
                solver.kind,
                100.0 * solver.position_round_off
            ));
        }
        return Some(format!(
            "warning: the {} solve did not resolve its last state: the residual is {} N, {:.1} % of its \
             loads (`converged`: false) — the loads are at the round-off of the internal forces \
             in this precision; use `precision = f64` or larger loads",
            solver.kind,
            crate::text::Sig(solver.residual_norm),
            100.0 * solver.relative_residual
        ));
    }
    let loss = scene.loss.as_ref()?;
    let end = loss.window(summary.steps as f64 * summary.dt, summary.dt)
        == softc_compiler::driver::LossWindow::End;
    if !end {
        return None;
    }
    crate::engine::Motion::of(scene, summary).still_moving(scene, summary)
}
