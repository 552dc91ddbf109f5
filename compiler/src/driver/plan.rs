//! The `optimize` block and the `input` declarations, resolved: the update rule and its
//! settings as numbers, the stop condition as a compiled function of the loss, the gradient
//! norm and the iteration, and every input's per-scene values.

use super::{const_scalar, const_values};
use crate::ir::{Domain, Func, KernelBuilder, interp};
use crate::lower::expr::{Env, ExprLowerer, Program};
use crate::sema::ParamInfo;
use crate::sema::hir::{Arg, Expr, ExprKind, StmtKind, named_arg};
use crate::sema::types::{Len, Ty};

/// The update rule and its coefficients.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum OptimizerSpec {
    Gd,
    Sgd { momentum: f64 },
    Adam { beta1: f64, beta2: f64, eps: f64 },
    Nadam { beta1: f64, beta2: f64, eps: f64 },
}

/// `lr_schedule = …`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum LrScheduleSpec {
    Constant,
    Exponential { gamma: f64 },
    StepDecay { every: u64, gamma: f64 },
    Cosine { floor: f64 },
}

/// `normalize = …`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum NormalizeSpec {
    None,
    Auto,
    Magnitude { m: f64 },
}

/// `stop when COND`: a function of `loss`, `grad_norm` and `iteration`.
#[derive(Debug, Clone)]
pub struct StopCondition {
    func: Func,
    /// What each argument of `func` reads: 0 loss, 1 grad_norm, 2 iteration.
    args: Vec<usize>,
}

impl StopCondition {
    fn compile(program: &Program, e: &Expr) -> Result<StopCondition, String> {
        const NAMES: [&str; 3] = ["loss", "grad_norm", "iteration"];
        let mut lw = ExprLowerer::new(program);
        lw.runtime_names = NAMES.to_vec();
        let mut k = KernelBuilder::new("stop", Domain::Single, "stop");
        let v = lw
            .lower(&mut k, &Env::new(), e)
            .and_then(|v| v.scalar())
            .map_err(|e| format!("`stop when` cannot be evaluated: {e}"))?;
        k.b.func.outputs.push(v);
        let (srcs, mut func) = k.into_parts();
        func.n_args = srcs.sources.len() as u32;
        let args = srcs
            .sources
            .iter()
            .map(|s| {
                let n = srcs.uniform_name(s)?;
                NAMES.iter().position(|m| *m == n)
            })
            .collect::<Option<Vec<_>>>()
            .ok_or("`stop when` is not a constant condition")?;
        Ok(StopCondition { func, args })
    }

    /// Whether the condition holds.
    pub fn holds(&self, loss: f64, grad_norm: f64, iteration: u64) -> bool {
        let values = [loss, grad_norm, iteration as f64];
        let args: Vec<f64> = self.args.iter().map(|&i| values[i]).collect();
        interp::eval(&self.func, &args)[0] != 0.0
    }
}

/// Where an input's per-scene values come from.
#[derive(Debug, Clone, PartialEq)]
pub enum InputSource {
    /// One value (flattened) per scene.
    Values(Vec<Vec<f64>>),
    /// `circle_quadrants(radius, plane, center, seed)`: a fresh target in each quadrant per
    /// iteration. `seed` unset: the optimize block's.
    CircleQuadrants {
        radius: f64,
        axes: [usize; 2],
        center: [f64; 3],
        seed: Option<u64>,
    },
}

/// An `input NAME: TYPE = SOURCE` declaration.
#[derive(Debug, Clone)]
pub struct InputDecl {
    pub name: String,
    /// The physical dimension of every entry (`input p: pressure` → pressure), as checked.
    pub dim: crate::sema::units::Dim,
    pub shape: Vec<usize>,
    /// The uniform of each entry (`input.target.0`, …).
    pub uniforms: Vec<String>,
    pub source: InputSource,
    /// The values of a plain run's first scene (a generator's centre is zero).
    pub first: Vec<f64>,
}

/// The optimize block.
#[derive(Debug, Clone)]
pub struct OptimizeSpec {
    /// The trained params, in the order the block lists them.
    pub targets: Vec<String>,
    pub optimizer: OptimizerSpec,
    pub lr: f64,
    pub schedule: LrScheduleSpec,
    /// `for N iterations`.
    pub iterations: Option<u64>,
    pub normalize: NormalizeSpec,
    pub clip: Option<f64>,
    /// Scenes per iteration.
    pub batch: usize,
    pub seed: u64,
    pub stop: Option<StopCondition>,
    /// `validate INPUT from VALUES`: the input's index and its held-out values.
    pub validate: Option<(usize, Vec<Vec<f64>>)>,
}

impl OptimizeSpec {
    pub(super) fn resolve(
        program: &Program,
        params: &[ParamInfo],
        inputs: &[InputDecl],
    ) -> Result<Option<OptimizeSpec>, String> {
        let Some(decl) = &program.optimize else {
            return Ok(None);
        };
        let konst = |e: &Expr| const_scalar(program, e);
        let opt_arg = |args: &[Arg], name: &str, default: f64| {
            named_arg(args, name).map_or(Ok(default), konst)
        };
        let mut targets = Vec::new();
        for target in &decl.targets {
            if !params.iter().any(|p| p.name == *target) {
                return Err(format!("`{target}` is not a param"));
            }
            targets.push(target.clone());
        }
        let (name, args) = decl
            .optimizer
            .builtin_call()
            .ok_or_else(|| "the optimizer must be gd, sgd, adam or nadam".to_string())?;
        let lr = opt_arg(args, "lr", 0.01)?;
        let optimizer = match name {
            "gd" => OptimizerSpec::Gd,
            "sgd" => OptimizerSpec::Sgd {
                momentum: opt_arg(args, "momentum", 0.0)?,
            },
            "adam" | "nadam" => {
                let (beta1, beta2, eps) = (
                    opt_arg(args, "beta1", 0.9)?,
                    opt_arg(args, "beta2", 0.999)?,
                    opt_arg(args, "eps", 1e-8)?,
                );
                if name == "adam" {
                    OptimizerSpec::Adam { beta1, beta2, eps }
                } else {
                    OptimizerSpec::Nadam { beta1, beta2, eps }
                }
            }
            other => return Err(format!("unknown optimizer `{other}`")),
        };
        let setting = |n: &str| program.optimize_setting(n);
        let schedule = match setting("lr_schedule").and_then(Expr::builtin_call) {
            None | Some(("constant", _)) => LrScheduleSpec::Constant,
            Some(("exponential", a)) => LrScheduleSpec::Exponential {
                gamma: opt_arg(a, "gamma", 1.0)?,
            },
            Some(("step_decay", a)) => LrScheduleSpec::StepDecay {
                every: opt_arg(a, "every", 1.0)?.max(1.0) as u64,
                gamma: opt_arg(a, "gamma", 1.0)?,
            },
            Some(("cosine", a)) => LrScheduleSpec::Cosine {
                floor: opt_arg(a, "floor", 0.0)?,
            },
            Some((other, _)) => return Err(format!("unknown lr_schedule `{other}`")),
        };
        let normalize = match setting("normalize").and_then(Expr::builtin_call) {
            None | Some(("none", _)) => NormalizeSpec::None,
            Some(("auto", _)) => NormalizeSpec::Auto,
            Some(("magnitude", a)) => NormalizeSpec::Magnitude {
                m: opt_arg(a, "m", 0.1)?,
            },
            Some((other, _)) => return Err(format!("unknown normalize `{other}`")),
        };
        let clip = setting("clip").map(konst).transpose()?;
        let batch = setting("batch")
            .map(konst)
            .transpose()?
            .unwrap_or(1.0)
            .max(1.0) as usize;
        let seed = setting("seed")
            .map(konst)
            .transpose()?
            .unwrap_or(0.0)
            .max(0.0) as u64;
        let mut stop = None;
        let mut validate = None;
        for s in &decl.body {
            match &s.kind {
                StmtKind::Stop(e) => stop = Some(StopCondition::compile(program, e)?),
                StmtKind::Validate { input, source } => {
                    let index = inputs
                        .iter()
                        .position(|i| i.name == *input)
                        .ok_or_else(|| format!("`{input}` is not an input"))?;
                    let per = inputs[index].uniforms.len().max(1);
                    let all = const_values(program, source)?;
                    validate = Some((index, all.chunks(per).map(|c| c.to_vec()).collect()));
                }
                _ => {}
            }
        }
        let iterations = match &decl.iterations {
            Some(e) => Some(konst(e)?.max(1.0) as u64),
            None => None,
        };
        Ok(Some(OptimizeSpec {
            targets,
            optimizer,
            lr,
            schedule,
            iterations,
            normalize,
            clip,
            batch,
            seed,
            stop,
            validate,
        }))
    }
}

/// The script's inputs with their per-scene values.
pub(super) fn inputs(program: &Program) -> Result<Vec<InputDecl>, String> {
    let mut out = Vec::new();
    for d in program.user_decls() {
        let crate::sema::hir::DeclKind::Input(decl) = &d.kind else {
            continue;
        };
        let shape = shape_of(&decl.ty);
        let per: usize = shape.iter().product::<usize>().max(1);
        let uniforms: Vec<String> = (0..per)
            .map(|i| uniform_name(&format!("input.{}", d.name), &shape, i))
            .collect();
        let source = match decl.source.builtin_call() {
            Some(("circle_quadrants", args)) => {
                let radius = named_arg(args, "radius")
                    .map(|e| const_scalar(program, e))
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
                        let c = const_values(program, e)?;
                        [c[0], c[1], c[2]]
                    }
                    None => [0.0; 3],
                };
                let seed = named_arg(args, "seed")
                    .map(|e| const_scalar(program, e))
                    .transpose()?
                    .map(|s| s as u64);
                InputSource::CircleQuadrants {
                    radius,
                    axes,
                    center,
                    seed,
                }
            }
            _ => {
                let all = const_values(program, &decl.source)?;
                InputSource::Values(all.chunks(per).map(|c| c.to_vec()).collect())
            }
        };
        // A plain run's scene: a literal list's first entry; a generator's centre (zero).
        let first = match &decl.source.kind {
            ExprKind::Array { items, .. } => {
                let all = const_values(program, &decl.source)?;
                all[..all.len() / items.len().max(1)].to_vec()
            }
            _ => vec![0.0; per],
        };
        out.push(InputDecl {
            name: d.name.clone(),
            dim: decl.ty.dim().unwrap_or(crate::sema::units::Dim::NONE),
            shape,
            uniforms,
            source,
            first,
        });
    }
    Ok(out)
}

/// The fixed lengths of a declared type's shape (0 for a set axis).
pub(super) fn shape_of(ty: &Ty) -> Vec<usize> {
    (ty.shape().iter())
        .map(|s| match s {
            Len::Fixed(n) => *n,
            _ => 0,
        })
        .collect()
}

/// `prefix.i.j` for the flat index of a row-major array of the given shape.
pub fn uniform_name(prefix: &str, shape: &[usize], flat: usize) -> String {
    let mut name = prefix.to_string();
    let mut rest = flat;
    let mut strides: Vec<usize> = shape
        .iter()
        .rev()
        .scan(1, |acc, &n| {
            let s = *acc;
            *acc *= n;
            Some(s)
        })
        .collect();
    strides.reverse();
    for s in strides {
        name.push_str(&format!(".{}", rest / s));
        rest %= s;
    }
    name
}
