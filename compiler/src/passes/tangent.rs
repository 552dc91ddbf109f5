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

use crate::ir::{ArgSource, BufferId, BuiltKernel, Domain, KernelBuilder, Module, ad};

/// The corners of an entity of `d`.
fn corners(d: Domain) -> u32 {
    match d {
        Domain::Element => 4,
        Domain::Triangle => 3,
        _ => 1,
    }
}

/// The Jacobian kernel of forward kernel `kernel` of `module`: the forces it stores in `force`
/// (entity × 3·corners) differentiated with respect to the positions it reads from `x` (node ×
/// 3) at its corners (a node kernel: its own position; the implicit integrator's inertia and
/// damping terms). Declares the output buffer `out` (entity × (3·corners)²) in `module`.
pub fn force_jacobian(
    module: &mut Module,
    kernel: usize,
    force: BufferId,
    x: BufferId,
    out: &str,
) -> Result<BuiltKernel, String> {
    let k = module.kernels[kernel].clone();
    let n = 3 * corners(k.domain);
    if module.buffers[force.0 as usize].width != n {
        return Err(format!(
            "kernel `{}`: the force buffer has {} components, not 3 per corner",
            k.name, module.buffers[force.0 as usize].width
        ));
    }
    let jac = module.buffer(
        out,
        k.domain,
        n * n,
        &format!(
            "∂f_i/∂x_j per {}: force component i, corner coordinate j (row-major), N/m",
            match k.domain {
                Domain::Triangle => "chamber triangle",
                Domain::Node => "node",
                _ => "element",
            }
        ),
    );
    let mut kb = KernelBuilder::in_module(
        module,
        &format!("jac_{}", k.name),
        k.domain,
        &format!("force Jacobian of {}", k.origin),
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
            kb.store(jac, s.component * n + j, d);
        }
    }
    let mut built = kb.finish();
    built.kernel.drop_unused_args();
    Ok(built)
}
