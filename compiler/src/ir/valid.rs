//! Validation of kernels against their module, shared by every backend.

use super::{ArgSource, Domain, Inst, Kernel, Module};

/// Check that a kernel is well formed against its module: every access it makes stays inside
/// buffers laid out as `Module::buffers` says. The run-time checks (buffer lengths, entity
/// ranges, connectivity) then make the generated code memory safe.
pub fn validate_kernel(m: &Module, k: &Kernel) -> Result<(), String> {
    let err = |msg: String| Err(format!("kernel `{}`: {msg}", k.name));
    if k.body.n_args as usize != k.args.len() {
        return err(format!(
            "body has {} arguments but {} argument sources",
            k.body.n_args,
            k.args.len()
        ));
    }
    let buf = |id: crate::ir::BufferId| m.buffers.get(id.0 as usize);
    // Offsets inside a row (up to 4 lanes of rows) are 32-bit immediates.
    if let Some(b) = m.buffers.iter().find(|b| b.width > 1 << 24) {
        return err(format!(
            "buffer `{}` is {} wide; at most 2^24 components",
            b.name, b.width
        ));
    }
    for (i, a) in k.args.iter().enumerate() {
        match a {
            ArgSource::Own { buffer, component } => {
                let Some(b) = buf(*buffer) else {
                    return err(format!("argument {i} reads an undeclared buffer"));
                };
                if b.domain != k.domain {
                    return err(format!(
                        "argument {i} reads `{}` ({:?}) per {:?}",
                        b.name, b.domain, k.domain
                    ));
                }
                if *component >= b.width {
                    return err(format!(
                        "argument {i} reads component {component} of `{}` (width {})",
                        b.name, b.width
                    ));
                }
            }
            ArgSource::Corner {
                buffer,
                corner,
                component,
            } => {
                let Some(nc) = m.corners(k.domain) else {
                    return err(format!(
                        "argument {i}: corner loads need an element or triangle kernel"
                    ));
                };
                let Some(b) = buf(*buffer) else {
                    return err(format!("argument {i} reads an undeclared buffer"));
                };
                if b.domain != Domain::Node {
                    return err(format!(
                        "argument {i}: corner load from non-node buffer `{}`",
                        b.name
                    ));
                }
                if *corner >= nc || *component >= b.width {
                    return err(format!(
                        "argument {i} reads corner {corner}, component {component} of `{}` (width {})",
                        b.name, b.width
                    ));
                }
            }
            ArgSource::Uniform(u) => {
                if m.uniforms.get(u.0 as usize).is_none() {
                    return err(format!("argument {i} reads an undeclared uniform"));
                }
            }
            ArgSource::Gather {
                buffer,
                over,
                stride,
                component,
            } => {
                if k.domain != Domain::Node {
                    return err(format!("argument {i}: gathers need a node kernel"));
                }
                let Some(nc) = m.corners(*over) else {
                    return err(format!(
                        "argument {i}: gathers run over elements or triangles"
                    ));
                };
                let Some(b) = buf(*buffer) else {
                    return err(format!("argument {i} reads an undeclared buffer"));
                };
                if b.domain != *over {
                    return err(format!(
                        "argument {i}: gather over {over:?} from `{}` ({:?})",
                        b.name, b.domain
                    ));
                }
                let last = (nc as u64 - 1) * *stride as u64 + *component as u64;
                if last >= b.width as u64 {
                    return err(format!(
                        "argument {i}: gather reads component {last} of `{}` (width {})",
                        b.name, b.width
                    ));
                }
            }
        }
    }
    for (n, inst) in k.body.insts.iter().enumerate() {
        let ok = match *inst {
            Inst::Arg(a) => a < k.body.n_args,
            _ => crate::ir::operands(inst).iter().all(|v| (v.0 as usize) < n),
        };
        if !ok {
            return err(format!("instruction v{n} uses a value it cannot"));
        }
    }
    for o in &k.body.outputs {
        if o.0 as usize >= k.body.insts.len() {
            return err(format!("output v{} does not exist", o.0));
        }
    }
    for s in &k.stores {
        let Some(b) = buf(s.buffer) else {
            return err("store to an undeclared buffer".into());
        };
        if b.domain != k.domain || s.component >= b.width {
            return err(format!(
                "store to `{}` ({:?}, width {}) component {} per {:?}",
                b.name, b.domain, b.width, s.component, k.domain
            ));
        }
        if s.output >= k.body.outputs.len() {
            return err(format!("store of output {} that does not exist", s.output));
        }
    }
    Ok(())
}

/// Check every kernel of a module ([`validate_kernel`]), in order; the first error is returned.
pub fn validate_module(m: &Module) -> Result<(), String> {
    for k in &m.kernels {
        validate_kernel(m, k)?;
    }
    Ok(())
}
