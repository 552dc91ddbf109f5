//! The script's loss, compiled once per bound scene: one kernel-IR function over the node state
//! of the sets it reduces over (unrolled in node order, so sums are reproducible), and the same
//! function followed by its derivative with respect to every argument (reverse-mode AD). The
//! run's length is not known here (`dt = auto` is estimated on the device): `t_end` and `dt`
//! are arguments, and so are the loss window's ends.

use crate::ir::{Builder, Domain, Func, Inst, KernelBuilder, V, ad, interp};
use crate::lower::expr::{Env, ExprLowerer, Program};
use crate::sema::hir::{Expr, LossWhen, Span};
use std::collections::HashMap;

/// What one argument of the loss reads.
#[derive(Debug, Clone, PartialEq)]
pub enum LossArg {
    /// Component `d` of node `node`'s position.
    X { node: usize, d: usize },
    /// Component `d` of node `node`'s velocity.
    V { node: usize, d: usize },
    /// Component `d` of node `node`'s rest position.
    X0 { node: usize, d: usize },
    /// The time of the state.
    T,
    /// The run's end time.
    TEnd,
    /// The time step.
    Dt,
    /// A param or input entry, by its uniform (`param.p`, `input.target.1`).
    Uniform(String),
}

impl LossArg {
    fn of(name: &str) -> LossArg {
        if let Some(rest) = name.strip_prefix("state.") {
            let mut parts = rest.split('.');
            let field = parts.next().unwrap_or("x");
            let node: usize = parts.next().and_then(|p| p.parse().ok()).unwrap_or(0);
            let d: usize = parts.next().and_then(|p| p.parse().ok()).unwrap_or(0);
            return match field {
                "x" => LossArg::X { node, d },
                "v" => LossArg::V { node, d },
                _ => LossArg::X0 { node, d },
            };
        }
        match name {
            "t" => LossArg::T,
            "t_end" => LossArg::TEnd,
            "dt" => LossArg::Dt,
            _ => LossArg::Uniform(name.to_string()),
        }
    }
}

/// When the loss is taken, for a run of known length.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum LossWindow {
    /// At the final state.
    End,
    /// Summed over every step whose end time lies in `[from, to]`.
    Over { from: f64, to: f64 },
}

/// A window end: a function of `t_end` and `dt`.
#[derive(Debug, Clone)]
struct WindowEnd {
    func: Func,
    /// Per argument: true for `dt`, false for `t_end`.
    reads_dt: Vec<bool>,
}

impl WindowEnd {
    fn at(&self, t_end: f64, dt: f64) -> f64 {
        let args: Vec<f64> = self
            .reads_dt
            .iter()
            .map(|&is_dt| if is_dt { dt } else { t_end })
            .collect();
        interp::eval(&self.func, &args)[0]
    }
}

/// The compiled loss.
#[derive(Debug, Clone)]
pub struct LossKernels {
    /// The loss term from its arguments.
    pub func: Func,
    /// `func` followed by the derivative of the loss with respect to each argument.
    pub grad: Func,
    /// What each argument reads.
    pub args: Vec<LossArg>,
    window: Option<(WindowEnd, WindowEnd)>,
}

impl LossKernels {
    /// The window for a run that ends at `t_end` with steps of `dt`.
    pub fn window(&self, t_end: f64, dt: f64) -> LossWindow {
        match &self.window {
            None => LossWindow::End,
            Some((from, to)) => LossWindow::Over {
                from: from.at(t_end, dt),
                to: to.at(t_end, dt),
            },
        }
    }
}

/// A scalar `v` of `k` (a host function of the state, params and time) as a function of its
/// arguments, the same followed by its derivative with respect to each argument, and what
/// each argument reads.
fn host_function(
    mut k: KernelBuilder,
    v: V,
    what: &str,
) -> Result<(Func, Func, Vec<LossArg>), String> {
    k.b.func.outputs.push(v);
    let (srcs, mut func) = k.into_parts();
    func.n_args = srcs.sources.len() as u32;
    let wrt: Vec<_> = (0..func.n_args)
        .map(|i| {
            func.insts
                .iter()
                .position(|inst| *inst == Inst::Arg(i))
                .map(|p| V(p as u32))
        })
        .collect();
    let present: Vec<_> = wrt.iter().flatten().copied().collect();
    let (mut grad, ds) = ad::gradient(func.clone(), v, &present);
    let mut ds = ds.into_iter();
    let zero = {
        let mut b = Builder::extend(grad);
        let z = b.constant(0.0);
        grad = b.finish();
        z
    };
    grad.outputs = std::iter::once(v)
        .chain(wrt.iter().map(|w| match w {
            Some(_) => ds.next().expect("one derivative per present argument"),
            None => zero,
        }))
        .collect();
    let args = srcs
        .sources
        .iter()
        .map(|s| match srcs.uniform_name(s) {
            Some(n) => Ok(LossArg::of(n)),
            None => Err(format!("{what} reads {s:?}")),
        })
        .collect::<Result<_, _>>()?;
    Ok((func, grad, args))
}

/// One scalar of a sensor of closed-loop control (a reduction over a node or element set that
/// a pressure or damping reads, [`crate::lower::expr::ExprLowerer::sensors`]): the kernels
/// read it as the uniform `uniform`, the host evaluates it at each state a step starts from
/// (or each static iterate) and differentiates it for the tangent and the adjoint.
#[derive(Debug, Clone)]
pub struct SensorKernels {
    /// `sensor.I.C`.
    pub uniform: String,
    /// Where the reduction is written (for messages).
    pub span: Span,
    /// Its value from its arguments, and the value followed by the derivatives.
    pub func: Func,
    pub grad: Func,
    pub args: Vec<LossArg>,
}

impl SensorKernels {
    /// Whether it reads node velocities.
    pub fn reads_velocity(&self) -> bool {
        self.args.iter().any(|a| matches!(a, LossArg::V { .. }))
    }
}

/// Lower the scene's sensors over the mesh's sets, one per scalar of each.
pub(super) fn lower_sensors(
    program: &Program,
    sensors: &[Expr],
    node_sets: &[(String, Vec<u32>)],
    element_sets: &[(String, Vec<u32>)],
    node_weights: &HashMap<String, Vec<f64>>,
) -> Result<Vec<SensorKernels>, String> {
    let sim_lets = program.sim_lets();
    // A sensor lowered into a fresh function (each scalar gets its own: its own arguments).
    let lower = |e: &Expr| {
        let mut lw = ExprLowerer::new(program);
        lw.runtime_names = vec!["t_end", "dt"];
        lw.sim_lets = sim_lets.clone();
        lw.node_sets = node_sets.iter().cloned().collect();
        lw.node_weights = node_weights.clone();
        lw.element_sets = element_sets.iter().cloned().collect();
        let mut k = KernelBuilder::new("sensor", Domain::Single, "sensor");
        let value = lw
            .lower(&mut k, &Env::new(), e)
            .map_err(|err| format!("a sensor of the sim block cannot be evaluated: {err}"))?;
        Ok::<_, String>((k, value))
    };
    let mut out = Vec::new();
    for (i, e) in sensors.iter().enumerate() {
        let n = crate::lower::expr::flatten(&lower(e)?.1).len();
        for c in 0..n {
            let (k, value) = lower(e)?;
            let v = crate::lower::expr::flatten(&value)[c];
            let (func, grad, args) = host_function(k, v, "a sensor")?;
            if args.contains(&LossArg::TEnd) {
                return Err(
                    "a reduction that a pressure or damping reads cannot read `t_end`: \
                            closed-loop control measures the state as it runs"
                        .into(),
                );
            }
            out.push(SensorKernels {
                uniform: crate::lower::expr::sensor_uniform(i, c),
                span: e.span,
                func,
                grad,
                args,
            });
        }
    }
    Ok(out)
}

/// Lower the script's loss; `None` without one.
pub(super) fn lower_loss(
    program: &Program,
    node_sets: &[(String, Vec<u32>)],
    element_sets: &[(String, Vec<u32>)],
    node_weights: &HashMap<String, Vec<f64>>,
    contacts: &[crate::lower::contact::ContactNodes],
    mesh: &dyn super::bind::MeshView,
) -> Result<Option<LossKernels>, String> {
    let Some(decl) = &program.loss else {
        return Ok(None);
    };
    let mut lw = ExprLowerer::new(program);
    lw.contact_nodes = Some(contacts.to_vec());
    lw.elements = Some((mesh.tets(), mesh.nodes()));
    lw.runtime_names = vec!["t_end", "dt"];
    lw.node_sets = node_sets.iter().cloned().collect::<HashMap<_, _>>();
    lw.node_weights = node_weights.clone();
    lw.element_sets = element_sets.iter().cloned().collect::<HashMap<_, _>>();
    let mut k = KernelBuilder::new("loss", Domain::Single, "loss");
    let v = lw
        .lower(&mut k, &Env::new(), &decl.value)
        .and_then(|v| v.scalar())
        .map_err(|e| format!("the loss cannot be evaluated: {e}"))?;
    let (func, grad, args) = host_function(k, v, "the loss")?;
    let window = match &decl.when {
        LossWhen::AtEnd => None,
        LossWhen::Over { from, to } => {
            let end = |e| -> Result<WindowEnd, String> {
                let mut c = ExprLowerer::new(program);
                c.runtime_names = vec!["t_end", "dt"];
                let mut kb = KernelBuilder::new("window", Domain::Single, "loss window");
                let v = c
                    .lower(&mut kb, &Env::new(), e)
                    .and_then(|v| v.scalar())
                    .map_err(|e| e.to_string())?;
                kb.b.func.outputs.push(v);
                let (srcs, mut func) = kb.into_parts();
                func.n_args = srcs.sources.len() as u32;
                let reads_dt = srcs
                    .sources
                    .iter()
                    .map(|s| match srcs.uniform_name(s) {
                        Some("dt") => Some(true),
                        Some("t_end") => Some(false),
                        _ => None,
                    })
                    .collect::<Option<Vec<_>>>()
                    .ok_or("the loss window must be constant")?;
                Ok(WindowEnd { func, reads_dt })
            };
            Some((end(from)?, end(to)?))
        }
    };
    Ok(Some(LossKernels {
        func,
        grad,
        args,
        window,
    }))
}
