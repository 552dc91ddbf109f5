//! softc compiler: front end (pest grammar → AST with spans), semantic analysis (names, types,
//! units, bounds), the formatter, editor support, the kernel IR with its passes (folding,
//! sharing, pruning, reverse-mode AD), lowering from scripts to kernels, and the backends.

pub mod back;
pub mod diag;
pub mod driver;
pub mod fmt;
pub mod front;
pub mod ide;
pub mod ir;
pub mod lower;
pub mod passes;
pub mod sema;

/// The shipped example scripts, `(path, text)` in name order, for the unit tests that check
/// something on every one of them.
#[cfg(test)]
pub(crate) fn example_scripts() -> Vec<(std::path::PathBuf, String)> {
    let dir = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../examples");
    let mut paths: Vec<_> = (std::fs::read_dir(&dir).unwrap())
        .map(|entry| entry.unwrap().path())
        .filter(|p| p.extension().is_some_and(|e| e == "soft"))
        .collect();
    paths.sort();
    assert!(
        paths.len() >= 15,
        "{} examples in {}",
        paths.len(),
        dir.display()
    );
    (paths.into_iter())
        .map(|p| {
            let text = std::fs::read_to_string(&p).unwrap();
            (p, text)
        })
        .collect()
}

pub use driver::{CompileFailure, CompileOptions, Compiled, compile};
pub use front::decode;
/// A script with some of its values rewritten at their places (`bench --solvers`, `--tradeoff`).
pub use front::variant::Variant;
pub use sema::CheckOptions;

use diag::Diagnostic;
use sema::CheckedScript;
use std::borrow::Cow;

/// The outcome of checking one script.
#[derive(Debug)]
pub struct Checked {
    /// Errors and warnings, sorted by position.
    pub diagnostics: Vec<Diagnostic>,
    /// What the checker learned; `None` when the script did not parse.
    pub script: Option<CheckedScript>,
}

impl Checked {
    pub fn has_errors(&self) -> bool {
        self.diagnostics.iter().any(Diagnostic::is_error)
    }
}

/// Parse and check a script given as raw bytes. Returns the text to render diagnostics against
/// (invalid UTF-8 is replaced, which keeps the offsets of the valid prefix).
pub fn check_bytes<'a>(bytes: &'a [u8], options: &CheckOptions) -> (Cow<'a, str>, Checked) {
    match front::decode(bytes) {
        Ok(text) => (Cow::Borrowed(text), check_source(text, options)),
        Err(d) => (
            String::from_utf8_lossy(bytes),
            Checked {
                diagnostics: vec![d],
                script: None,
            },
        ),
    }
}

/// Parse and check a script.
pub fn check_source(text: &str, options: &CheckOptions) -> Checked {
    match front::parse(text) {
        Err(d) => Checked {
            diagnostics: vec![d],
            script: None,
        },
        Ok(ast) => {
            let (script, diagnostics) = sema::check(&ast, options);
            Checked {
                diagnostics,
                script: Some(script),
            }
        }
    }
}
