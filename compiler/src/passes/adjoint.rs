//! The adjoint of one time step, as kernels of the same IR.
//!
//! A forward step runs kernels that read the state (`x`, `v`), buffers written earlier in the
//! step (`elem_force`, `tri_force`) and uniforms (`t`, params), and write the next state
//! (`x_next`, `v_next`). The reverse step runs, in reverse order, one adjoint kernel per forward
//! kernel over the same entities: it recomputes the forward body, takes the adjoint ("bar") of
//! each value it stored, and by reverse-mode AD ([`crate::ir::ad`]) the adjoint of each value it
//! read. Those adjoints leave by the transpose of the way the value came in, so the adjoint
//! code has no scatter either:
//!
//! | forward read | adjoint write (same kernel) | read back by |
//! |---|---|---|
//! | `Own` `B[self]` | partial `adj_B@G[self]` | `Own` in B's domain |
//! | `Corner` `B[node k]` | partial `adj_B@G[self][k]` | `Gather` over this domain (CSR) |
//! | `Gather` of `B` (node kernel) | `adjg_B@G[node]` | `Corner` in B's domain |
//! | `Uniform` `param.*` | `grad@G[self] += …` | the host, summed in entity order |
//! | `Uniform` `sensor.*` | `grad_sensor@G[self] += …` | the host, per reverse step |
//! | `Own` `param.F[self]` (a per-element param) | `grad_param.F[self] += …` | the host, per entity |
//!
//! (`G` names the group of forward kernels that write the same buffer over disjoint entity
//! ranges, e.g. one element kernel per material: they share partial buffers.) Finally one node
//! kernel per state variable sums every partial of it into `adj_x` — ∂L/∂x of this step's
//! state — from `adj_x_next`, ∂L/∂x of the next. Everything is a fixed-order sum, so adjoints
//! are as reproducible as the forward run.

use crate::ir::{
    ArgSource, BufferId, Builder, BuiltKernel, Domain, Kernel, KernelBuilder, Module, UniformId, V,
    ad,
};
use std::collections::{BTreeMap, BTreeSet};

/// The adjoint of a step, added to a copy of the forward module.
#[derive(Clone, Debug, PartialEq)]
pub struct Adjoint {
    /// The forward module's buffers and kernels (same ids) followed by the adjoint ones.
    pub module: Module,
    /// How many kernels (the first ones) are forward kernels.
    pub forward_kernels: usize,
    /// How many buffers (the first ones) are the forward module's.
    pub forward_buffers: usize,
    /// The kernels of one reverse step, in the order they run.
    pub reverse: Vec<ReverseKernel>,
    /// The state variables and their adjoints.
    pub state: Vec<AdjointState>,
    /// Where the partial derivatives with respect to each param uniform accumulate.
    pub params: Vec<ParamGradient>,
    /// Where those with respect to each sensor uniform (closed-loop control) accumulate, for
    /// one reverse step: the host reads and zeroes them after each.
    pub sensors: Vec<ParamGradient>,
    /// Per-element params (buffers `param.NAME` the step reads but never writes): where the
    /// derivative with respect to each entity's value accumulates.
    pub fields: Vec<FieldGradient>,
    /// Whether the reverse kernels read buffers the forward kernels compute within a step
    /// (then the forward kernels run again at that step's state first).
    pub needs_forward: bool,
}

#[derive(Clone, Debug, PartialEq)]
pub struct ReverseKernel {
    /// Index in [`Adjoint::module`]'s kernels.
    pub kernel: usize,
    /// The forward kernel whose entity range it runs over; `None`: its whole domain.
    pub range_of: Option<usize>,
}

#[derive(Clone, Debug, PartialEq)]
pub struct AdjointState {
    pub name: String,
    /// The state buffer and the next-state buffer of the forward step.
    pub state: BufferId,
    pub next: BufferId,
    /// ∂L/∂state (written by a reverse step) and ∂L/∂next (read by it).
    pub adj: BufferId,
    pub adj_next: BufferId,
}

/// `Σ over entities of buffer[entity][component]` is ∂L/∂(uniform), summed over steps.
#[derive(Clone, Debug, PartialEq)]
pub struct ParamGradient {
    pub uniform: UniformId,
    /// The uniform's name (`param.w.1`), for messages and printing.
    pub name: String,
    pub buffer: BufferId,
    pub component: u32,
}

/// `buffer[entity]` summed over steps is ∂L/∂(the param's value at that entity): no sum over
/// entities, each one is its own parameter.
#[derive(Clone, Debug, PartialEq)]
pub struct FieldGradient {
    /// The param's name (`mu` for the buffer `param.mu`).
    pub param: String,
    /// The forward buffer of its values.
    pub values: BufferId,
    /// The accumulator, same domain and width.
    pub buffer: BufferId,
}

/// How the adjoint of a buffer's value at one entity is read: the sum of every contribution.
#[derive(Clone, Debug)]
enum Contribution {
    /// `partial[self][component]`, partial in the buffer's own domain.
    Own(BufferId),
    /// The sum over incident entities of `partial[entity][corner * stride + component]`.
    Gather {
        partial: BufferId,
        over: Domain,
        stride: u32,
    },
    /// `partial[node (component / stride) of self][component % stride]`.
    Corner { partial: BufferId, stride: u32 },
}

/// Build the adjoint of a step made of `module`'s kernels run in order. `state` names the
/// (state, next state) buffer pairs: the step reads the first and writes the second. `scale`
/// multiplies the adjoint of a state variable by a constant at every reverse step (thesis
/// eq. 5.4 scales the velocity's).
pub fn adjoint(
    module: &Module,
    state: &[(&str, &str)],
    scale: &[(&str, f64)],
) -> Result<Adjoint, String> {
    let mut m = module.clone();
    let forward_kernels = m.kernels.len();
    let forward_buffers = m.buffers.len();
    let id = |m: &Module, n: &str| {
        m.buffer_named(n)
            .ok_or_else(|| format!("the step has no buffer `{n}`"))
    };
    let mut states = Vec::new();
    for (s, next) in state {
        let (sb, nb) = (id(&m, s)?, id(&m, next)?);
        let (domain, width) = {
            let b = &m.buffers[sb.0 as usize];
            (b.domain, b.width)
        };
        let adj = m.buffer(
            &format!("adj_{s}"),
            domain,
            width,
            &format!("∂L/∂{s} of the step's state"),
        );
        let adj_next = m.buffer(
            &format!("adj_{next}"),
            domain,
            width,
            &format!("∂L/∂{s} of the next state"),
        );
        states.push(AdjointState {
            name: s.to_string(),
            state: sb,
            next: nb,
            adj,
            adj_next,
        });
    }
    let state_in: BTreeSet<BufferId> = states.iter().map(|s| s.state).collect();
    let written: BTreeSet<BufferId> = module.kernels[..forward_kernels]
        .iter()
        .flat_map(|k| k.stores.iter().map(|s| s.buffer))
        .collect();
    let read: BTreeSet<BufferId> = module
        .kernels
        .iter()
        .flat_map(|k| k.args.iter().filter_map(buffer_of))
        .collect();
    let active = |b: BufferId| states.iter().any(|s| s.next == b) || read.contains(&b);
    let differentiable =
        |b: BufferId| state_in.contains(&b) || (written.contains(&b) && !is_next(&states, b));
    let field_param = |m: &Module, b: BufferId| {
        m.buffers[b.0 as usize]
            .name
            .strip_prefix("param.")
            .filter(|_| !written.contains(&b))
            .map(str::to_string)
    };

    // Groups: kernels writing the same (first active) buffer run over disjoint entities.
    let group_of = |k: &Kernel| -> String {
        k.stores
            .iter()
            .find(|s| active(s.buffer))
            .map(|s| module.buffers[s.buffer.0 as usize].name.clone())
            .unwrap_or_else(|| k.name.clone())
    };
    // Params accumulate over the steps; sensors (closed-loop control's `sensor.*`, which
    // the host sets per step) in accumulators of their own, which the host reads and zeroes
    // at every reverse step.
    let is_param = |u: UniformId| module.uniform_name(u).starts_with("param.");
    let is_sensor = |u: UniformId| module.uniform_name(u).starts_with("sensor.");
    let mut group_params: BTreeMap<(String, bool), Vec<UniformId>> = BTreeMap::new();
    for k in &module.kernels {
        for a in &k.args {
            if let ArgSource::Uniform(u) = a
                && (is_param(*u) || is_sensor(*u))
            {
                let g = group_params
                    .entry((group_of(k), is_sensor(*u)))
                    .or_default();
                if !g.contains(u) {
                    g.push(*u);
                }
            }
        }
    }

    let mut contributions: BTreeMap<BufferId, Vec<Contribution>> = BTreeMap::new();
    let mut reverse = Vec::new();
    let mut params = Vec::new();
    let mut sensors = Vec::new();
    let mut fields: Vec<FieldGradient> = Vec::new();
    for (ki, k) in module.kernels.iter().enumerate().rev() {
        let active_stores: Vec<_> = k.stores.iter().filter(|s| active(s.buffer)).collect();
        if active_stores.is_empty() {
            continue;
        }
        let group = group_of(k);
        let mut kb = KernelBuilder::in_module(
            &m,
            &format!("adj_{}", k.name),
            k.domain,
            &format!("adjoint of {}", k.origin),
        );
        let args: Vec<V> = k.args.iter().map(|a| kb.load(a.clone())).collect();
        let outputs = kb.inline_sources(&k.args, &m.uniforms, &k.body, &args);
        // s = Σ output · bar: its gradient is the vector-Jacobian product.
        let mut terms = Vec::new();
        for st in &active_stores {
            let bar = match states.iter().find(|s| s.next == st.buffer) {
                Some(s) => kb.load(ArgSource::Own {
                    buffer: s.adj_next,
                    component: st.component,
                }),
                None => read_adjoint(&mut kb, contributions.get(&st.buffer), st.component),
            };
            if kb.b.func.constant(bar) == Some(0.0) {
                continue;
            }
            terms.push(kb.b.mul(outputs[st.output], bar));
        }
        let s = kb.b.sum(&terms);
        let func = std::mem::take(&mut kb.b.func);
        let (func, grads) = ad::gradient(func, s, &args);
        kb.b = Builder::extend(func);
        let mut stored_any = false;
        for (a, &g) in k.args.iter().zip(&grads) {
            if kb.b.func.constant(g) == Some(0.0) {
                continue;
            }
            match a {
                ArgSource::Own { buffer, component } if differentiable(*buffer) => {
                    let w = m.buffers[buffer.0 as usize].width;
                    let p = partial(&mut m, "adj", *buffer, &group, k.domain, w);
                    add_contribution(&mut contributions, *buffer, Contribution::Own(p));
                    kb.store(p, *component, g);
                }
                ArgSource::Corner {
                    buffer,
                    corner,
                    component,
                } if differentiable(*buffer) => {
                    let w = m.buffers[buffer.0 as usize].width;
                    let width = m.corners(k.domain).unwrap_or(1) * w;
                    let p = partial(&mut m, "adj", *buffer, &group, k.domain, width);
                    add_contribution(
                        &mut contributions,
                        *buffer,
                        Contribution::Gather {
                            partial: p,
                            over: k.domain,
                            stride: w,
                        },
                    );
                    kb.store(p, corner * w + component, g);
                }
                ArgSource::Gather {
                    buffer,
                    stride,
                    component,
                    ..
                } if differentiable(*buffer) => {
                    let p = partial(&mut m, "adjg", *buffer, &group, k.domain, *stride);
                    add_contribution(
                        &mut contributions,
                        *buffer,
                        Contribution::Corner {
                            partial: p,
                            stride: *stride,
                        },
                    );
                    kb.store(p, *component, g);
                }
                ArgSource::Own { buffer, component } if field_param(&m, *buffer).is_some() => {
                    let param = field_param(&m, *buffer).expect("checked");
                    let (domain, width) = {
                        let b = &m.buffers[buffer.0 as usize];
                        (b.domain, b.width)
                    };
                    if domain != k.domain {
                        return Err(format!(
                            "kernel `{}` reads the per-element param `{param}` outside its domain",
                            k.name
                        ));
                    }
                    let acc = m.buffer(
                        &format!("grad_param.{param}"),
                        domain,
                        width,
                        &format!("∂L/∂{param} summed over steps, per entity"),
                    );
                    if !fields.iter().any(|f| f.buffer == acc) {
                        fields.push(FieldGradient {
                            param,
                            values: *buffer,
                            buffer: acc,
                        });
                    }
                    let before = kb.load(ArgSource::Own {
                        buffer: acc,
                        component: *component,
                    });
                    let sum = kb.b.add(before, g);
                    kb.store(acc, *component, sum);
                }
                ArgSource::Corner { buffer, .. } | ArgSource::Gather { buffer, .. }
                    if field_param(&m, *buffer).is_some() =>
                {
                    return Err(format!(
                        "kernel `{}` reads the per-element buffer `{}` at another entity; its \
                         adjoint is not defined",
                        k.name, m.buffers[buffer.0 as usize].name
                    ));
                }
                ArgSource::Uniform(u) if is_param(*u) || is_sensor(*u) => {
                    let sensor = is_sensor(*u);
                    let ids = &group_params[&(group.clone(), sensor)];
                    let c = ids.iter().position(|n| n == u).expect("collected") as u32;
                    let names: Vec<&str> = ids.iter().map(|&id| module.uniform_name(id)).collect();
                    let (name, doc) = match sensor {
                        false => (format!("grad@{group}"), "∂L/∂param summed over steps"),
                        true => (format!("grad_sensor@{group}"), "∂L/∂sensor of one step"),
                    };
                    let buffer = m.buffer(
                        &name,
                        k.domain,
                        ids.len() as u32,
                        &format!("{doc}, per entity ({})", names.join(", ")),
                    );
                    let list = if sensor { &mut sensors } else { &mut params };
                    if !list
                        .iter()
                        .any(|p: &ParamGradient| p.buffer == buffer && p.uniform == *u)
                    {
                        list.push(ParamGradient {
                            uniform: *u,
                            name: module.uniform_name(*u).to_string(),
                            buffer,
                            component: c,
                        });
                    }
                    let before = kb.load(ArgSource::Own {
                        buffer,
                        component: c,
                    });
                    let sum = kb.b.add(before, g);
                    kb.store(buffer, c, sum);
                }
                _ => continue,
            }
            stored_any = true;
        }
        if !stored_any {
            continue;
        }
        let kernel = m.push_kernel(finish_compact(kb));
        reverse.push(ReverseKernel {
            kernel,
            range_of: Some(ki),
        });
    }
    // ∂L/∂state: every partial, in a fixed order.
    for s in &states {
        let (domain, width) = {
            let b = &m.buffers[s.state.0 as usize];
            (b.domain, b.width)
        };
        let mut kb = KernelBuilder::in_module(
            &m,
            &format!("adj_state_{}", s.name),
            domain,
            &format!("adjoint of the state {}", s.name),
        );
        let factor = scale.iter().find(|(n, _)| *n == s.name).map(|(_, f)| *f);
        for c in 0..width {
            let mut v = read_adjoint(&mut kb, contributions.get(&s.state), c);
            if let Some(f) = factor {
                v = kb.b.scale(f, v);
            }
            kb.store(s.adj, c, v);
        }
        let kernel = m.push_kernel(finish_compact(kb));
        reverse.push(ReverseKernel {
            kernel,
            range_of: None,
        });
    }
    let needs_forward = reverse.iter().any(|r| {
        m.kernels[r.kernel]
            .args
            .iter()
            .any(|a| buffer_of(a).is_some_and(|b| written.contains(&b) && !is_next(&states, b)))
    });
    Ok(Adjoint {
        module: m,
        forward_kernels,
        forward_buffers,
        reverse,
        state: states,
        params,
        sensors,
        fields,
        needs_forward,
    })
}

fn is_next(states: &[AdjointState], b: BufferId) -> bool {
    states.iter().any(|s| s.next == b)
}

fn buffer_of(a: &ArgSource) -> Option<BufferId> {
    match a {
        ArgSource::Own { buffer, .. }
        | ArgSource::Corner { buffer, .. }
        | ArgSource::Gather { buffer, .. } => Some(*buffer),
        ArgSource::Uniform(_) => None,
    }
}

fn add_contribution(map: &mut BTreeMap<BufferId, Vec<Contribution>>, b: BufferId, c: Contribution) {
    let list = map.entry(b).or_default();
    let same = |x: &Contribution| match (x, &c) {
        (Contribution::Own(a), Contribution::Own(b)) => a == b,
        (Contribution::Gather { partial: a, .. }, Contribution::Gather { partial: b, .. }) => {
            a == b
        }
        (Contribution::Corner { partial: a, .. }, Contribution::Corner { partial: b, .. }) => {
            a == b
        }
        _ => false,
    };
    if !list.iter().any(same) {
        list.push(c);
    }
}

/// The partial-adjoint buffer of `buffer` written by the kernels of `group`.
fn partial(
    m: &mut Module,
    prefix: &str,
    buffer: BufferId,
    group: &str,
    domain: Domain,
    width: u32,
) -> BufferId {
    let name = m.buffers[buffer.0 as usize].name.clone();
    m.buffer(
        &format!("{prefix}_{name}@{group}"),
        domain,
        width,
        &format!("partial ∂L/∂{name} from the adjoint of {group}"),
    )
}

/// The adjoint of `buffer[self][component]`: the sum of its contributions (0 without any).
fn read_adjoint(
    kb: &mut KernelBuilder,
    contributions: Option<&Vec<Contribution>>,
    component: u32,
) -> V {
    let mut terms = Vec::new();
    for c in contributions.into_iter().flatten() {
        let src = match *c {
            Contribution::Own(p) => ArgSource::Own {
                buffer: p,
                component,
            },
            Contribution::Gather {
                partial,
                over,
                stride,
            } => ArgSource::Gather {
                buffer: partial,
                over,
                stride,
                component,
            },
            Contribution::Corner { partial, stride } => ArgSource::Corner {
                buffer: partial,
                corner: component / stride,
                component: component % stride,
            },
        };
        terms.push(kb.load(src));
    }
    kb.b.sum(&terms)
}

/// Finish a kernel and drop the arguments its pruned body no longer reads (the recomputed
/// forward values an adjoint does not need, e.g. the forces in the integrator's adjoint).
fn finish_compact(kb: KernelBuilder) -> BuiltKernel {
    let mut k = kb.finish();
    k.kernel.drop_unused_args();
    k
}
