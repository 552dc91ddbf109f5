//! How a run of a script is set up, below the command line that asks for it: values with
//! their units (`--set`, `--dt`, `--memory-budget`), the backward pass's settings and the
//! script's own `output` statements. Shared by `softc run`, its optimization and `softc bench`.

use crate::engine::adjoint::{Checkpointing, GradOptions};
use crate::engine::scene::Scene;
use crate::outputs::csv::CsvOutput;
use std::io::Write;
use std::path::Path;

/// Parse a value with its unit (`2.5kPa`, `20 us`) with the language's own front end.
pub fn parse_quantity(text: &str) -> Result<(f64, softc_compiler::sema::units::Dim), String> {
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

/// The backward pass's settings: the optimize block's `checkpoint`, `memory_budget` and
/// `truncate`, overridden by `checkpoint` (`--checkpoint`) and `memory_budget`
/// (`--memory-budget`).
pub fn grad_options(
    scene: &Scene,
    checkpoint: Option<&str>,
    memory_budget: Option<&str>,
) -> Result<GradOptions, String> {
    use softc_compiler::front::ast::ExprKind;
    let mut o = GradOptions::default();
    let program = scene.program();
    let constant = |e: &softc_compiler::front::ast::Expr| crate::optim::constant(&program, e);
    if let Some(e) = scene.ast.optimize_setting("checkpoint") {
        o.checkpoint = match &e.kind {
            ExprKind::Name(n) if n.name == "store_all" => Checkpointing::StoreAll,
            ExprKind::Call { callee, args } => {
                let k = args
                    .first()
                    .map(|a| constant(&a.value))
                    .transpose()?
                    .unwrap_or(1.0)
                    .max(1.0) as u64;
                match &callee.kind {
                    ExprKind::Name(n) if n.name == "periodic" => Checkpointing::Periodic(k),
                    _ => Checkpointing::Revolve(k as usize),
                }
            }
            _ => Checkpointing::Auto,
        };
    }
    if let Some(e) = scene.ast.optimize_setting("memory_budget") {
        o.memory_budget = Some(constant(e)? as u64);
    }
    if let Some(e) = scene.ast.optimize_setting("truncate") {
        o.truncate = Some(constant(e)?.max(1.0) as u64);
    }
    if let Some(c) = checkpoint {
        let number = |s: &str| {
            s.trim()
                .parse::<u64>()
                .ok()
                .filter(|n| *n >= 1)
                .ok_or_else(|| format!("--checkpoint {c}: expected a positive integer after `:`"))
        };
        o.checkpoint = match c.split_once(':') {
            None if c == "auto" => Checkpointing::Auto,
            None if c == "store_all" => Checkpointing::StoreAll,
            Some(("periodic", k)) => Checkpointing::Periodic(number(k)?),
            Some(("revolve", n)) => Checkpointing::Revolve(number(n)? as usize),
            _ => {
                return Err(format!(
                    "--checkpoint {c}: expected auto, store_all, periodic:K or revolve:N"
                ));
            }
        };
    }
    if let Some(m) = memory_budget {
        let (bytes, dim) = parse_quantity(m).map_err(|e| format!("--memory-budget: {e}"))?;
        if dim != softc_compiler::sema::units::Dim::MEMORY || bytes <= 0.0 {
            return Err(format!(
                "--memory-budget {m}: expected a positive memory size such as 512MB or 2GiB"
            ));
        }
        o.memory_budget = Some(bytes as u64);
    }
    Ok(o)
}

/// The node-set logs of the script's `output csv(SET) every …` statements, written into
/// `dir` (`--csv DIR`); without it, a note says how to get them.
pub fn csv_outputs(
    dir: Option<&Path>,
    scene: &Scene,
    dt: f64,
    err: &mut dyn Write,
) -> Result<Vec<CsvOutput>, String> {
    use softc_compiler::front::ast::{ExprKind, ItemKind, StmtKind};
    let mut outputs = Vec::new();
    let program = scene.program();
    for item in &scene.ast.items {
        let ItemKind::Sim(stmts) = &item.kind else {
            continue;
        };
        for stmt in stmts {
            let StmtKind::Output { what, every, steps } = &stmt.kind else {
                continue;
            };
            let ExprKind::Call { callee, args: call } = &what.kind else {
                continue;
            };
            let (ExprKind::Name(f), Some(ExprKind::Name(set))) =
                (&callee.kind, call.first().map(|a| &a.value.kind))
            else {
                continue;
            };
            if f.name != "csv" {
                continue;
            }
            let Some(dir) = dir else {
                let _ = writeln!(
                    err,
                    "note: the script logs `{}` (`output csv`); add --csv DIR to write it",
                    set.name
                );
                continue;
            };
            let interval = crate::optim::constant(&program, every)?;
            let every_steps = if *steps {
                interval.round().max(1.0) as u64
            } else {
                (interval / dt).round().max(1.0) as u64
            };
            let nodes = scene
                .node_sets
                .iter()
                .find(|(n, _)| *n == set.name)
                .map(|(_, nodes)| nodes.clone())
                .ok_or_else(|| format!("`output csv({})`: no node set of that name", set.name))?;
            std::fs::create_dir_all(dir)
                .map_err(|e| format!("cannot create `{}`: {e}", dir.display()))?;
            outputs.push(CsvOutput::new(
                dir.join(format!("{}.csv", set.name)),
                nodes,
                every_steps,
            ));
        }
    }
    Ok(outputs)
}

/// `output vtk every N steps` in the sim block.
pub fn vtk_every(scene: &Scene) -> Option<u64> {
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
