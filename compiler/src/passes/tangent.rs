//! Force Jacobians, as kernels of the same IR: the tangent stiffness a static or implicit
//! solve assembles.
//!
//! For a kernel that stores forces on the corners of its entity (an element's 4 corners, a
//! chamber triangle's 3) from the positions of those corners, [`force_jacobian`] builds a
//! kernel over the same entities that stores ∂f_i/∂x_j for every force component i and every
//! corner coordinate j (row-major, `i·n + j`, n = 3 × corners): the element's force Jacobian,
//! the negative of its stiffness matrix. It is the forward-mode derivative ([`ad::tangent`]) of
//! the force kernel's own body, one unit direction per corner coordinate, so every material —
//! prelude or user-written W, the spring mesh, follower pressure (whose per-triangle Jacobian
//! is not symmetric) — gets its tangent from the one definition of its forces, and the
//! tangents share the force body's code. What a force does not depend on generates no code.
//!
//! A matrix-free solve (the GPU's Newton–Krylov) needs less: [`JacobianPart::DiagonalBlocks`]
//! keeps only each corner's 3×3 block (its preconditioner), and [`directional_derivative`]
//! gives the product of the Jacobian with a vector — one forward-mode sweep whose direction is
//! read from a buffer, so the tangent stiffness is never formed.

use crate::ir::{ArgSource, BufferId, BuiltKernel, Domain, KernelBuilder, Module, ad};

/// Which entries of a force Jacobian a kernel stores.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum JacobianPart {
    /// Every ∂f_i/∂x_j: entity × (3·corners)², row-major (`i·n + j`).
    Full,
    /// Only the derivative of each corner's force with respect to that corner's position:
    /// entity × corners × 9, corner-major, each block row-major (force component, coordinate).
    /// Summed per node they are the diagonal blocks of the tangent (block-Jacobi).
    DiagonalBlocks,
}

/// What an entity of `d` is called in buffer docs.
fn entity(d: Domain) -> &'static str {
    match d {
        Domain::Triangle => "chamber triangle",
        Domain::Node => "node",
        _ => "element",
    }
}

/// The Jacobian kernel of forward kernel `kernel` of `module`: the forces it stores in `force`
/// (entity × 3·corners) differentiated with respect to the positions it reads from `x` (node ×
/// 3) at its corners (a node kernel: its own position; the implicit integrator's inertia and
/// damping terms). Declares the output buffer `out` (its width as `part` says) in `module`.
pub fn force_jacobian(
    module: &mut Module,
    kernel: usize,
    force: BufferId,
    x: BufferId,
    out: &str,
    part: JacobianPart,
) -> Result<BuiltKernel, String> {
    let k = module.kernels[kernel].clone();
    let n = 3 * module.corners(k.domain).unwrap_or(1);
    if module.buffers[force.0 as usize].width != n {
        return Err(format!(
            "kernel `{}`: the force buffer has {} components, not 3 per corner",
            k.name, module.buffers[force.0 as usize].width
        ));
    }
    let (width, doc, prefix, what) = match part {
        JacobianPart::Full => (
            n * n,
            format!(
                "∂f_i/∂x_j per {}: force component i, corner coordinate j (row-major), N/m",
                entity(k.domain)
            ),
            "jac",
            "force Jacobian",
        ),
        JacobianPart::DiagonalBlocks => (
            3 * n,
            format!(
                "∂f/∂x of each corner's force by its own position, per {} (corner-major 3×3 \
                 blocks, row-major), N/m",
                entity(k.domain)
            ),
            "jacdiag",
            "diagonal blocks of the force Jacobian",
        ),
    };
    let jac = module.buffer(out, k.domain, width, &doc);
    let mut kb = KernelBuilder::in_module(
        module,
        &format!("{prefix}_{}", k.name),
        k.domain,
        &format!("{what} of {}", k.origin),
    );
    let args: Vec<_> = k.args.iter().map(|a| kb.load(a.clone())).collect();
    let outputs = kb.inline_sources(&k.args, &module.uniforms, &k.body, &args);
    let upto = kb.b.func.insts.len();
    let one = kb.b.constant(1.0);
    let zero = kb.b.constant(0.0);
    let force_stores: Vec<_> = k.stores.iter().filter(|s| s.buffer == force).collect();
    for j in 0..n {
        let (corner, component) = (j / 3, j % 3);
        let seeds: Vec<_> = k
            .args
            .iter()
            .zip(&args)
            .filter(|(a, _)| match **a {
                // An entity with corners reads each corner's position; a node its own.
                ArgSource::Corner {
                    buffer,
                    corner: c,
                    component: d,
                } => buffer == x && c == corner && d == component,
                ArgSource::Own {
                    buffer,
                    component: d,
                } => k.domain == Domain::Node && buffer == x && d == component,
                _ => false,
            })
            .map(|(_, &v)| (v, one))
            .collect();
        let tan = if seeds.is_empty() {
            vec![None; upto]
        } else {
            ad::tangent(&mut kb.b, upto, &seeds)
        };
        for s in &force_stores {
            let d = tan[outputs[s.output].0 as usize].unwrap_or(zero);
            match part {
                JacobianPart::Full => kb.store(jac, s.component * n + j, d),
                JacobianPart::DiagonalBlocks if s.component / 3 == corner => {
                    kb.store(jac, corner * 9 + (s.component % 3) * 3 + component, d)
                }
                JacobianPart::DiagonalBlocks => {}
            }
        }
    }
    let mut built = kb.finish();
    built.kernel.drop_unused_args();
    Ok(built)
}

/// The derivative of forward kernel `kernel` of `module` along a direction: every value it
/// reads from buffer `b` varies as the same entry of `d`, for each `(b, d)` of `directions`,
/// and the kernel stores the derivative of what it stores in `s` into `t` (same entity and
/// component), for each `(s, t)` of `outputs` (declared by the caller, as wide as `s`). With
/// `x` ↦ a direction, an element kernel's forces give J_e·v; a node kernel that gathers
/// forces, with the forces ↦ those products, gives the assembled product — the tangent
/// stiffness times a vector without the matrix. A uniform named `u` varies as the uniform
/// `dir.u` where `u` starts with one of `uniform_prefixes` (closed-loop control's sensors,
/// whose dependence on the state the host adds through those directions).
pub fn directional_derivative(
    module: &mut Module,
    kernel: usize,
    directions: &[(BufferId, BufferId)],
    outputs: &[(BufferId, BufferId)],
    uniform_prefixes: &[&str],
) -> Result<BuiltKernel, String> {
    let k = module.kernels[kernel].clone();
    for &(s, t) in outputs {
        let (ws, wt) = (
            module.buffers[s.0 as usize].width,
            module.buffers[t.0 as usize].width,
        );
        if ws != wt {
            return Err(format!(
                "kernel `{}`: the derivative's buffer has {wt} components, the value's {ws}",
                k.name
            ));
        }
    }
    let mut kb = KernelBuilder::in_module(
        module,
        &format!("dir_{}", k.name),
        k.domain,
        &format!("Jacobian-vector product of {}", k.origin),
    );
    let args: Vec<_> = k.args.iter().map(|a| kb.load(a.clone())).collect();
    let values = kb.inline_sources(&k.args, &module.uniforms, &k.body, &args);
    let upto = kb.b.func.insts.len();
    let direction_of = |a: &ArgSource| -> Option<ArgSource> {
        let to = |b: BufferId| directions.iter().find(|(from, _)| *from == b).map(|p| p.1);
        Some(match *a {
            ArgSource::Own { buffer, component } => ArgSource::Own {
                buffer: to(buffer)?,
                component,
            },
            ArgSource::Corner {
                buffer,
                corner,
                component,
            } => ArgSource::Corner {
                buffer: to(buffer)?,
                corner,
                component,
            },
            ArgSource::Gather {
                buffer,
                over,
                stride,
                component,
            } => ArgSource::Gather {
                buffer: to(buffer)?,
                over,
                stride,
                component,
            },
            ArgSource::Uniform(_) => return None,
        })
    };
    let mut seeds: Vec<_> = k
        .args
        .iter()
        .zip(&args)
        .filter_map(|(a, &v)| direction_of(a).map(|d| (v, kb.load(d))))
        .collect();
    for (a, &v) in k.args.iter().zip(&args) {
        if let ArgSource::Uniform(u) = a {
            let name = module.uniform_name(*u).to_string();
            if uniform_prefixes.iter().any(|p| name.starts_with(p)) {
                seeds.push((v, kb.uniform(&format!("dir.{name}"))));
            }
        }
    }
    let tan = ad::tangent(&mut kb.b, upto, &seeds);
    let zero = kb.b.constant(0.0);
    for s in &k.stores {
        if let Some(&(_, t)) = outputs.iter().find(|(from, _)| *from == s.buffer) {
            let d = tan[values[s.output].0 as usize].unwrap_or(zero);
            kb.store(t, s.component, d);
        }
    }
    let mut built = kb.finish();
    built.kernel.drop_unused_args();
    Ok(built)
}
