//! Backends: code generated from the kernel IR ([`crate::ir`]).
//!
//! - [`cranelift`]: native CPU code through the Cranelift JIT, f64 or f32, bit-identical to
//!   the IR interpreter in f64, run on any number of threads with identical results.
//! - [`wgsl`]: WGSL compute shaders for wgpu (any GPU, or lavapipe), f32 or f64.

pub mod cranelift;
pub mod wgsl;

/// The floating-point type of every value and buffer of a compiled module.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum Precision {
    F32,
    F64,
}

impl Precision {
    /// Bytes per value.
    pub fn size(self) -> usize {
        match self {
            Precision::F32 => 4,
            Precision::F64 => 8,
        }
    }
}

impl std::fmt::Display for Precision {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            Precision::F32 => "f32",
            Precision::F64 => "f64",
        })
    }
}
