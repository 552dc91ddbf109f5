//! Front end: the pest grammar and the AST with source spans.
pub mod ast;
pub mod parser;
pub mod variant;

pub use parser::{decode, parse};
