//! The optimization loop (SPEC §8): what the `optimize` block asks for ([`Plan`]), the update
//! rules ([`method`]), bounded parameters ([`transform`]), batches of scenes ([`batch`]) and the
//! resumable training loop ([`train`]).

pub mod batch;
pub mod method;
pub mod plot;
pub mod train;
pub mod transform;

use crate::engine::scene::Scene;
use batch::{Input, InputSource};
use method::{LrSchedule, Method, Normalize};
use softc_compiler::front::ast::{Expr, ExprKind, ItemKind, StmtKind};
use softc_compiler::lower::expr::Program;
use transform::Bounds;

/// Iterations when the block gives neither `for N iterations` nor `stop when`… and also the cap
/// when it only gives `stop when`.
pub const DEFAULT_ITERATIONS: u64 = 100;

/// One trained scalar: an entry of a param.
#[derive(Clone, Debug, PartialEq)]
pub struct Entry {
    /// The uniform it sets (`param.w.1.2`).
    pub uniform: String,
    /// The param it belongs to (`w`).
    pub param: String,
    pub bounds: Bounds,
}

/// The optimize block, evaluated.
#[derive(Clone, Debug)]
pub struct Plan {
    pub entries: Vec<Entry>,
    pub method: Method,
    pub lr: f64,
    pub schedule: LrSchedule,
    pub iterations: u64,
    pub normalize: Normalize,
    pub clip: Option<f64>,
    /// Scenes per iteration.
    pub batch: usize,
    pub seed: u64,
    pub inputs: Vec<Input>,
    /// Scenes the constant inputs enumerate (`None` with only generators or no inputs).
    pub scenes: Option<usize>,
    pub stop: Option<Expr>,
    /// `validate INPUT from VALUES`: the input's index and its held-out values.
    pub validate: Option<(usize, Vec<Vec<f64>>)>,
}

/// A constant of the script (SI units).
pub fn constant(program: &Program, e: &Expr) -> Result<f64, String> {
    crate::engine::scene::const_values(program, e)
        .map_err(|e| e.0)?
        .first()
        .copied()
        .ok_or_else(|| "expected a number".to_string())
}

fn named_arg<'a>(args: &'a [softc_compiler::front::ast::Arg], name: &str) -> Option<&'a Expr> {
    args.iter()
        .find(|a| a.name.as_ref().is_some_and(|n| n.name == name))
        .map(|a| &a.value)
}

fn call_parts(e: &Expr) -> Option<(&str, &[softc_compiler::front::ast::Arg])> {
    match &e.kind {
        ExprKind::Call { callee, args } => match &callee.kind {
            ExprKind::Name(n) => Some((n.name.as_str(), args.as_slice())),
            _ => None,
        },
        ExprKind::Name(n) => Some((n.name.as_str(), &[])),
        _ => None,
    }
}

impl Plan {
    /// The script's optimize block; `None` without one.
    pub fn from_scene(scene: &Scene) -> Result<Option<Plan>, String> {
        let Some(decl) = scene.ast.items.iter().find_map(|i| match &i.kind {
            ItemKind::Optimize(o) => Some(o),
            _ => None,
        }) else {
            return Ok(None);
        };
        let program = scene.program();
        let konst = |e: &Expr| constant(&program, e);
        let opt_arg = |args: &[softc_compiler::front::ast::Arg], name: &str, default: f64| {
            named_arg(args, name).map_or(Ok(default), &konst)
        };

        // Trained entries, in the order the block lists the params.
        let mut entries = Vec::new();
        for target in &decl.targets {
            let info = scene
                .params
                .iter()
                .find(|p| p.name == target.name)
                .ok_or_else(|| format!("`{}` is not a param", target.name))?;
            let bounds = Bounds::new(info.lower, info.upper);
            let prefix = format!("param.{}", info.name);
            let names: Vec<&String> = scene
                .uniforms
                .keys()
                .filter(|k| *k == &prefix || k.starts_with(&format!("{prefix}.")))
                .collect();
            if names.is_empty() {
                return Err(format!(
                    "the param `{}` has no entries to train (an empty element set?)",
                    info.name
                ));
            }
            // Uniform names sort lexicographically (`w.10` before `w.2`): order by index.
            let mut names: Vec<(Vec<usize>, String)> = names
                .into_iter()
                .map(|n| {
                    let idx = n[prefix.len()..]
                        .split('.')
                        .filter_map(|s| s.parse().ok())
                        .collect();
                    (idx, n.clone())
                })
                .collect();
            names.sort();
            for (_, uniform) in names {
                entries.push(Entry {
                    uniform,
                    param: info.name.clone(),
                    bounds,
                });
            }
        }

        let (name, args) = call_parts(&decl.optimizer)
            .ok_or_else(|| "the optimizer must be gd, sgd, adam or nadam".to_string())?;
        let lr = opt_arg(args, "lr", 0.01)?;
        let method = match name {
            "gd" => Method::Gd,
            "sgd" => Method::Sgd {
                momentum: opt_arg(args, "momentum", 0.0)?,
            },
            "adam" | "nadam" => {
                let (beta1, beta2, eps) = (
                    opt_arg(args, "beta1", 0.9)?,
                    opt_arg(args, "beta2", 0.999)?,
                    opt_arg(args, "eps", 1e-8)?,
                );
                if name == "adam" {
                    Method::Adam { beta1, beta2, eps }
                } else {
                    Method::Nadam { beta1, beta2, eps }
                }
            }
            other => return Err(format!("unknown optimizer `{other}`")),
        };

        let setting = |n: &str| scene.ast.optimize_setting(n);
        let schedule = match setting("lr_schedule").and_then(call_parts) {
            None | Some(("constant", _)) => LrSchedule::Constant,
            Some(("exponential", a)) => LrSchedule::Exponential {
                gamma: opt_arg(a, "gamma", 1.0)?,
            },
            Some(("step_decay", a)) => LrSchedule::StepDecay {
                every: opt_arg(a, "every", 1.0)?.max(1.0) as u64,
                gamma: opt_arg(a, "gamma", 1.0)?,
            },
            Some(("cosine", a)) => LrSchedule::Cosine {
                floor: opt_arg(a, "floor", 0.0)?,
            },
            Some((other, _)) => return Err(format!("unknown lr_schedule `{other}`")),
        };
        let normalize = match setting("normalize").and_then(call_parts) {
            None | Some(("none", _)) => Normalize::None,
            Some(("auto", _)) => Normalize::Auto,
            Some(("magnitude", a)) => Normalize::Magnitude {
                m: opt_arg(a, "m", 0.1)?,
            },
            Some((other, _)) => return Err(format!("unknown normalize `{other}`")),
        };
        let clip = setting("clip").map(&konst).transpose()?;
        let batch = setting("batch")
            .map(&konst)
            .transpose()?
            .unwrap_or(1.0)
            .max(1.0) as usize;
        let seed = setting("seed")
            .map(&konst)
            .transpose()?
            .unwrap_or(0.0)
            .max(0.0) as u64;

        let inputs = inputs(scene, &program, seed)?;
        let counts: Vec<(String, usize)> = inputs
            .iter()
            .filter_map(|i| i.count().map(|c| (i.name.clone(), c)))
            .collect();
        if let Some((first, n)) = counts.first()
            && let Some((other, m)) = counts.iter().find(|(_, m)| m != n)
        {
            return Err(format!(
                "the inputs `{first}` ({n} scenes) and `{other}` ({m} scenes) enumerate different \
                 numbers of scenes; give every constant input one value per scene"
            ));
        }
        let scenes = counts.first().map(|(_, n)| *n);

        let mut stop = None;
        let mut validate = None;
        for s in decl.body.iter().flatten() {
            match &s.kind {
                StmtKind::Stop(e) => stop = Some(e.clone()),
                StmtKind::Validate { input, source } => {
                    let index = inputs
                        .iter()
                        .position(|i| i.name == input.name)
                        .ok_or_else(|| format!("`{}` is not an input", input.name))?;
                    let per = inputs[index].uniforms.len().max(1);
                    let all =
                        crate::engine::scene::const_values(&program, source).map_err(|e| e.0)?;
                    validate = Some((index, all.chunks(per).map(|c| c.to_vec()).collect()));
                }
                _ => {}
            }
        }
        let iterations = match &decl.iterations {
            Some(e) => konst(e)?.max(1.0) as u64,
            None => DEFAULT_ITERATIONS,
        };
        Ok(Some(Plan {
            entries,
            method,
            lr,
            schedule,
            iterations,
            normalize,
            clip,
            batch,
            seed,
            inputs,
            scenes,
            stop,
            validate,
        }))
    }

    /// Scenes per iteration (the number of simulations a [`train::Trainer`] needs).
    pub fn scenes_per_iteration(&self) -> usize {
        if self.inputs.is_empty() {
            1
        } else {
            batch::members(self.scenes, self.batch, 0, self.seed, false).len()
        }
    }

    /// Whether the stop condition holds for this iteration's loss and gradient norm.
    pub fn should_stop(
        &self,
        scene: &Scene,
        loss: f64,
        grad_norm: f64,
        iteration: u64,
    ) -> Result<bool, String> {
        let Some(e) = &self.stop else {
            return Ok(false);
        };
        let program = scene.program();
        let mut lw = softc_compiler::lower::expr::ExprLowerer::new(&program);
        lw.constants.insert("loss".into(), loss);
        lw.constants.insert("grad_norm".into(), grad_norm);
        lw.constants.insert("iteration".into(), iteration as f64);
        let mut k = softc_compiler::ir::KernelBuilder::new(
            "stop",
            softc_compiler::ir::Domain::Single,
            "stop",
        );
        let v = lw
            .lower(&mut k, &softc_compiler::lower::expr::Env::new(), e)
            .and_then(|v| v.scalar())
            .map_err(|e| format!("`stop when` cannot be evaluated: {e}"))?;
        let value =
            k.b.func
                .constant(v)
                .ok_or_else(|| "`stop when` is not a constant condition".to_string())?;
        Ok(value != 0.0)
    }
}

/// The scenes a plain run (no optimization) covers: one uniform assignment per scene when the
/// script's inputs are constant lists of two or more scenes, else none (the one scene of
/// [`Scene::uniforms`]). A generator input (`circle_quadrants`) has no fixed scenes.
pub fn plain_run_scenes(scene: &Scene) -> Result<Vec<Vec<(String, f64)>>, String> {
    let program = Program::new(&scene.ast, softc_compiler::sema::prelude_ast());
    let inputs = inputs(scene, &program, 0)?;
    let Some(n) = inputs.iter().filter_map(Input::count).max() else {
        return Ok(Vec::new());
    };
    if n < 2 || inputs.iter().any(|i| i.count().is_some_and(|m| m != n)) {
        return Ok(Vec::new());
    }
    Ok((0..n)
        .map(|k| {
            inputs
                .iter()
                .flat_map(|i| {
                    let value = i.value(0, k);
                    i.uniforms.iter().cloned().zip(value).collect::<Vec<_>>()
                })
                .collect()
        })
        .collect())
}

/// The script's inputs with their per-scene values.
fn inputs(scene: &Scene, program: &Program, seed: u64) -> Result<Vec<Input>, String> {
    let mut out = Vec::new();
    for item in &scene.ast.items {
        let ItemKind::Input(decl) = &item.kind else {
            continue;
        };
        let shape = crate::engine::scene::shape_of(&decl.ty);
        let per: usize = shape.iter().product::<usize>().max(1);
        let uniforms: Vec<String> = (0..per)
            .map(|i| {
                crate::engine::scene::uniform_name(&format!("input.{}", decl.name.name), &shape, i)
            })
            .collect();
        let source = match call_parts(&decl.source) {
            Some(("circle_quadrants", args)) => {
                let radius = named_arg(args, "radius")
                    .map(|e| constant(program, e))
                    .transpose()?
                    .ok_or("circle_quadrants needs a radius")?;
                let plane = match named_arg(args, "plane").map(|e| &e.kind) {
                    Some(ExprKind::Str(s)) => s.as_str(),
                    _ => "xy",
                };
                let axes = match plane {
                    "xz" => [0, 2],
                    "yz" => [1, 2],
                    _ => [0, 1],
                };
                let center = match named_arg(args, "center") {
                    Some(e) => {
                        let c = crate::engine::scene::const_values(program, e).map_err(|e| e.0)?;
                        [c[0], c[1], c[2]]
                    }
                    None => [0.0; 3],
                };
                let own_seed = named_arg(args, "seed")
                    .map(|e| constant(program, e))
                    .transpose()?
                    .map_or(seed, |s| s as u64);
                InputSource::CircleQuadrants {
                    radius,
                    axes,
                    center,
                    seed: own_seed,
                }
            }
            _ => {
                let all =
                    crate::engine::scene::const_values(program, &decl.source).map_err(|e| e.0)?;
                InputSource::Values(all.chunks(per).map(|c| c.to_vec()).collect())
            }
        };
        out.push(Input {
            name: decl.name.name.clone(),
            uniforms,
            source,
        });
    }
    Ok(out)
}
