//! Passes over whole kernel modules (per-body folding, sharing and pruning happen as bodies are
//! built, in [`crate::ir`]; [`simplify`] runs over every finished kernel before the backends).

pub mod adjoint;
pub mod simplify;
pub mod tangent;
