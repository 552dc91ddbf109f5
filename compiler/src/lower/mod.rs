//! Lowering from a checked script to kernel IR: materials to strain energies, strain energies
//! to element force kernels (the compiler differentiates W), and the other forces of a scene.

pub mod contact;
pub mod expr;
pub mod fem;
pub mod quadratic;
pub mod scene;
pub mod springs;
pub mod stretch;

use std::fmt;

/// A construct the lowering cannot turn into kernel code (the checker accepted it, but this
/// backend stage does not support it yet, or a definition is malformed).
#[derive(Debug, Clone, PartialEq)]
pub struct LowerError {
    pub message: String,
}

impl LowerError {
    pub fn new(message: impl Into<String>) -> Self {
        LowerError {
            message: message.into(),
        }
    }
}

impl fmt::Display for LowerError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(&self.message)
    }
}

impl std::error::Error for LowerError {}
