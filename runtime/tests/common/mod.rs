//! Helpers shared by the runtime's test binaries (each includes this with `mod common;`).

use std::path::{Path, PathBuf};

/// The repository root.
pub fn repo_root() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .parent()
        .unwrap()
        .to_path_buf()
}

/// The script at `rel` (from the repository root) with its `load("MESH")` made absolute (so
/// the text runs from anywhere) and its elements of `order` (1 linear, 2 quadratic tets).
pub fn script_at_order(rel: &str, order: u32) -> String {
    let path = repo_root().join(rel);
    let text = std::fs::read_to_string(&path).unwrap();
    let start = text.find("load(\"").expect("the script loads a mesh") + "load(\"".len();
    let end = start + text[start..].find("\")").expect("load(\"…\") is closed");
    let mesh = path.parent().unwrap().join(&text[start..end]);
    let mesh = std::fs::canonicalize(&mesh).unwrap_or(mesh);
    format!(
        "{}{}\", order: {order}{}",
        &text[..start],
        mesh.display(),
        &text[end + 1..]
    )
}
