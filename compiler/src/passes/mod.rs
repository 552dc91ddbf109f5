//! Passes over whole kernel modules (per-body folding, sharing and pruning happen as bodies are
//! built, in [`crate::ir`]).

pub mod adjoint;
pub mod tangent;
