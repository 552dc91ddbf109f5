//! Architecture rules checked on the source tree: the two backends share only the IR and
//! `compiler/src/back/mod.rs`, and no source file grows past 1,500 lines.

use softc_tests::root;
use std::path::{Path, PathBuf};

/// The most lines a source file may have.
const MAX_LINES: usize = 1500;

/// Every `.rs` file under `dir` (relative to the workspace root), recursively, sorted. Fails
/// when there is none, so a moved folder cannot make a rule pass vacuously.
fn rust_files(dir: &str) -> Vec<PathBuf> {
    let mut out = Vec::new();
    let mut stack = vec![root().join(dir)];
    while let Some(d) = stack.pop() {
        let entries = std::fs::read_dir(&d).unwrap_or_else(|e| panic!("{}: {e}", d.display()));
        for entry in entries {
            let path = entry
                .unwrap_or_else(|e| panic!("{}: {e}", d.display()))
                .path();
            if path.is_dir() {
                stack.push(path);
            } else if path.extension().is_some_and(|e| e == "rs") {
                out.push(path);
            }
        }
    }
    out.sort();
    assert!(!out.is_empty(), "no .rs files under {dir}");
    out
}

/// A path relative to the workspace root, for messages.
fn rel(path: &Path) -> String {
    path.strip_prefix(root())
        .unwrap_or(path)
        .display()
        .to_string()
}

fn read(path: &Path) -> String {
    std::fs::read_to_string(path).unwrap_or_else(|e| panic!("{}: {e}", path.display()))
}

/// The lines of the files under `dir` that mention any of `needles`, as `FILE:LINE: TEXT`.
fn mentions(dir: &str, needles: &[&str]) -> Vec<String> {
    let mut found = Vec::new();
    for file in rust_files(dir) {
        for (i, line) in read(&file).lines().enumerate() {
            if needles.iter().any(|n| line.contains(n)) {
                found.push(format!("{}:{}: {}", rel(&file), i + 1, line.trim()));
            }
        }
    }
    found
}

/// Neither backend uses the other: what both need (IR validation, the precision, the
/// connectivity layout) lives in `compiler/src/ir` or `compiler/src/back/mod.rs`.
#[test]
fn backends_share_only_the_ir() {
    let wgsl_uses_cranelift = mentions(
        "compiler/src/back/wgsl",
        &["cranelift::", "back::cranelift", "super::cranelift"],
    );
    assert!(
        wgsl_uses_cranelift.is_empty(),
        "the WGSL backend refers to the Cranelift backend (move what both need to compiler/src/ir \
         or compiler/src/back/mod.rs):\n{}",
        wgsl_uses_cranelift.join("\n")
    );
    let cranelift_uses_wgsl = mentions(
        "compiler/src/back/cranelift",
        &["wgsl::", "back::wgsl", "super::wgsl"],
    );
    assert!(
        cranelift_uses_wgsl.is_empty(),
        "the Cranelift backend refers to the WGSL backend (move what both need to compiler/src/ir \
         or compiler/src/back/mod.rs):\n{}",
        cranelift_uses_wgsl.join("\n")
    );
}

#[test]
fn no_source_file_over_1500_lines() {
    // The compiler's sources; runtime/src joins this list once its split has landed.
    let dirs = ["compiler/src"];
    let mut too_long = Vec::new();
    for dir in dirs {
        for file in rust_files(dir) {
            let lines = read(&file).lines().count();
            if lines > MAX_LINES {
                too_long.push(format!("{}: {lines} lines", rel(&file)));
            }
        }
    }
    assert!(
        too_long.is_empty(),
        "source files over {MAX_LINES} lines (split them by concern):\n{}",
        too_long.join("\n")
    );
}
