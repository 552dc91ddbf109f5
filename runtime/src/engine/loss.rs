//! The loss of a run: the script's `loss` expression lowered to one kernel-IR function over the
//! node state of the sets it reduces over (unrolled in node order, so sums are reproducible),
//! evaluated on the host at the end of the run or at every step of its window (thesis eq. 7.1).
//! The same function is what reverse-mode AD will differentiate for the adjoint.

use super::scene::Scene;
use softc_compiler::front::ast::{ItemKind, LossWhen};
use softc_compiler::ir::{ArgSource, Domain, Func, KernelBuilder, ad, interp};
use softc_compiler::lower::expr::{Env, ExprLowerer};
use std::collections::HashMap;

/// When the loss is taken.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum LossWindow {
    /// At the final state.
    End,
    /// Summed over every step whose end time lies in `[from, to]`.
    Over { from: f64, to: f64 },
}

pub struct Loss {
    func: Func,
    /// `func` followed by the derivative of the loss with respect to each argument.
    grad: Func,
    /// The uniform each argument reads (`state.x.N.d`, `t`, `param.p`, …).
    args: Vec<String>,
    pub window: LossWindow,
}

impl Loss {
    /// Lower the script's loss for a run of `steps` steps of `dt`; `None` without a loss.
    pub fn build(scene: &Scene, dt: f64, steps: u64) -> Result<Option<Loss>, String> {
        let Some(decl) = scene.ast.items.iter().find_map(|i| match &i.kind {
            ItemKind::Loss(l) => Some(l),
            _ => None,
        }) else {
            return Ok(None);
        };
        let program = scene.program();
        let t_end = steps as f64 * dt;
        let mut lw = ExprLowerer::new(&program);
        lw.constants.insert("t_end".into(), t_end);
        lw.constants.insert("dt".into(), dt);
        lw.node_sets = scene.node_sets.iter().cloned().collect::<HashMap<_, _>>();
        lw.element_sets = scene
            .element_sets
            .iter()
            .cloned()
            .collect::<HashMap<_, _>>();
        let mut k = KernelBuilder::new("loss", Domain::Single, "loss");
        let v = lw
            .lower(&mut k, &Env::new(), &decl.value)
            .and_then(|v| v.scalar())
            .map_err(|e| format!("the loss cannot be evaluated: {e}"))?;
        k.b.func.outputs.push(v);
        let (srcs, mut func) = k.into_parts();
        func.n_args = srcs.len() as u32;
        let wrt: Vec<_> = (0..func.n_args)
            .map(|i| {
                func.insts
                    .iter()
                    .position(|inst| *inst == softc_compiler::ir::Inst::Arg(i))
                    .map(|p| softc_compiler::ir::V(p as u32))
            })
            .collect();
        let present: Vec<_> = wrt.iter().flatten().copied().collect();
        let (mut grad, ds) = ad::gradient(func.clone(), v, &present);
        let mut ds = ds.into_iter();
        let zero = {
            let mut b = softc_compiler::ir::Builder::extend(grad);
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
            .into_iter()
            .map(|s| match s {
                ArgSource::Uniform(n) => Ok(n),
                other => Err(format!("the loss reads {other:?}")),
            })
            .collect::<Result<_, _>>()?;
        let window = match &decl.when {
            LossWhen::Default | LossWhen::AtEnd(_) => LossWindow::End,
            LossWhen::Over { from, to, .. } => {
                let mut c = ExprLowerer::new(&program);
                c.constants.insert("t_end".into(), t_end);
                c.constants.insert("dt".into(), dt);
                let mut kb = KernelBuilder::new("window", Domain::Single, "loss window");
                let mut end = |e| -> Result<f64, String> {
                    let v = c
                        .lower(&mut kb, &Env::new(), e)
                        .and_then(|v| v.scalar())
                        .map_err(|e| e.to_string())?;
                    kb.b.func
                        .constant(v)
                        .ok_or_else(|| "the loss window must be constant".to_string())
                };
                LossWindow::Over {
                    from: end(from)?,
                    to: end(to)?,
                }
            }
        };
        Ok(Some(Loss {
            func,
            grad,
            args,
            window,
        }))
    }

    /// The loss term at one state: positions and velocities (flat, 3 per node), time, and the
    /// other uniforms (params, inputs).
    pub fn eval(
        &self,
        scene: &Scene,
        x: &[f64],
        v: &[f64],
        t: f64,
        uniforms: &std::collections::BTreeMap<String, f64>,
    ) -> f64 {
        interp::eval(&self.func, &self.arg_values(scene, x, v, t, uniforms))[0]
    }

    /// The loss term and its derivative with respect to each argument ([`Loss::args`]).
    pub fn eval_grad(
        &self,
        scene: &Scene,
        x: &[f64],
        v: &[f64],
        t: f64,
        uniforms: &std::collections::BTreeMap<String, f64>,
    ) -> (f64, Vec<f64>) {
        let out = interp::eval(&self.grad, &self.arg_values(scene, x, v, t, uniforms));
        (out[0], out[1..].to_vec())
    }

    /// The uniform each argument reads (`state.x.N.d`, `state.v.N.d`, `param.p`, `t`, …).
    pub fn args(&self) -> &[String] {
        &self.args
    }

    fn arg_values(
        &self,
        scene: &Scene,
        x: &[f64],
        v: &[f64],
        t: f64,
        uniforms: &std::collections::BTreeMap<String, f64>,
    ) -> Vec<f64> {
        self.args
            .iter()
            .map(|name| {
                if let Some(rest) = name.strip_prefix("state.") {
                    let mut parts = rest.split('.');
                    let field = parts.next().unwrap_or("x");
                    let node: usize = parts.next().and_then(|p| p.parse().ok()).unwrap_or(0);
                    let d: usize = parts.next().and_then(|p| p.parse().ok()).unwrap_or(0);
                    match field {
                        "x" => x[3 * node + d],
                        "v" => v[3 * node + d],
                        _ => scene.mesh.nodes[node][d],
                    }
                } else if name == "t" {
                    t
                } else {
                    uniforms.get(name).copied().unwrap_or(f64::NAN)
                }
            })
            .collect()
    }

    /// Whether the step ending at time `t` contributes (windowed losses).
    pub fn in_window(&self, t: f64, dt: f64) -> bool {
        match self.window {
            LossWindow::End => false,
            // Half a step of slack so a window end that is a multiple of dt is included.
            LossWindow::Over { from, to } => t >= from - 0.5 * dt && t <= to + 0.5 * dt,
        }
    }
}
