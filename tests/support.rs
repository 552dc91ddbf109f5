//! Shared helpers for the cross-cutting tests.

use std::path::{Path, PathBuf};

/// The repository root.
pub fn root() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .parent()
        .unwrap()
        .to_path_buf()
}

/// Run the `softc` command line in-process; returns (exit status, stdout, stderr).
pub fn softc(args: &[&str]) -> (i32, String, String) {
    let mut argv = vec!["softc".to_string()];
    argv.extend(args.iter().map(|s| s.to_string()));
    let mut out = Vec::new();
    let mut err = Vec::new();
    let code = softc::cli::run(&argv, &mut out, &mut err);
    (
        code,
        String::from_utf8_lossy(&out).into_owned(),
        String::from_utf8_lossy(&err).into_owned(),
    )
}

/// Whether the generated kernels' golden files (tests/golden.rs) should be rewritten instead of
/// compared (`SOFTC_BLESS=1`). The diagnostics corpus uses insta (`INSTA_UPDATE=always`).
pub fn bless() -> bool {
    std::env::var_os("SOFTC_BLESS").is_some_and(|v| v != "0")
}

/// Files with the given extension in a directory, sorted.
pub fn files_with_ext(dir: &Path, ext: &str) -> Vec<PathBuf> {
    let mut v: Vec<PathBuf> = std::fs::read_dir(dir)
        .unwrap_or_else(|e| panic!("{}: {e}", dir.display()))
        .map(|e| e.unwrap().path())
        .filter(|p| p.extension().is_some_and(|e| e == ext))
        .collect();
    v.sort();
    v
}

/// A scratch folder for test `tag` of the suite `suite`, unique to this process.
pub fn scratch(suite: &str, tag: &str) -> PathBuf {
    let d = std::env::temp_dir().join(format!("softc-{suite}-{tag}-{}", std::process::id()));
    std::fs::create_dir_all(&d).unwrap();
    d
}

/// The 1k benchmark scene, run for a few steps with extra flags.
pub fn run_bench_1k(extra: &[&str]) -> (i32, String, String) {
    let script = root().join("examples/benchmark-1k.soft");
    let mut args = vec!["run", script.to_str().unwrap(), "--steps", "5"];
    args.extend_from_slice(extra);
    softc(&args)
}

/// The files under `dir` (recursively) whose extension is `ext`, sorted.
pub fn files_under(dir: &Path, ext: &str) -> Vec<PathBuf> {
    let mut out = Vec::new();
    let mut stack = vec![dir.to_path_buf()];
    while let Some(d) = stack.pop() {
        for entry in std::fs::read_dir(&d).unwrap_or_else(|e| panic!("{}: {e}", d.display())) {
            let path = entry.unwrap().path();
            if path.is_dir() {
                stack.push(path);
            } else if path.extension().is_some_and(|e| e == ext) {
                out.push(path);
            }
        }
    }
    out.sort();
    out
}
