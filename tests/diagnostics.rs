//! Every script in tests/diagnostics/ is wrong on purpose. Its diagnostics (code, line:column,
//! message) must match the snapshot `NAME.snap` beside it (insta's format: a short header, then
//! the lines), and `softc check` must exit with 1.
//!
//! A mismatch prints a diff and, outside CI, stores the new output as `NAME.snap.new` (review it
//! with `cargo insta review` if cargo-insta is installed). Accept every change at once with:
//!     INSTA_UPDATE=always cargo test -p softc-tests --test diagnostics
//! and review the diff. With `CI=true` nothing is written.

use softc_compiler::diag::SourceFile;
use softc_compiler::sema::CheckOptions;
use softc_tests::{files_with_ext, root, softc};

fn render(path: &std::path::Path) -> (String, bool) {
    let bytes = std::fs::read(path).unwrap();
    let options = CheckOptions {
        base_dir: Some(path.parent().unwrap().to_path_buf()),
        mesh_probe: Some(std::sync::Arc::new(softc::mesh::probe::FileProbe)),
    };
    let (text, checked) = softc_compiler::check_bytes(&bytes, &options);
    let name = path.file_name().unwrap().to_string_lossy().into_owned();
    let file = SourceFile::new(&name, &text);
    let mut out = String::new();
    for d in &checked.diagnostics {
        out.push_str(&file.render_short(d));
        out.push('\n');
    }
    (out, checked.has_errors())
}

#[test]
fn wrong_scripts_match_their_golden_diagnostics() {
    let dir = root().join("tests/diagnostics");
    let scripts = files_with_ext(&dir, "soft");
    let mut settings = insta::Settings::clone_current();
    settings.set_snapshot_path("diagnostics");
    settings.set_prepend_module_to_snapshot(false);
    settings.set_omit_expression(true);
    let _bound = settings.bind_to_scope();
    let mut failures = Vec::new();
    for script in &scripts {
        let (actual, has_errors) = render(script);
        if !has_errors {
            failures.push(format!("{}: no error reported", script.display()));
        }
        // Every script is compared (insta prints each diff) before the test fails.
        let name = script.file_stem().unwrap().to_string_lossy().into_owned();
        let compared =
            std::panic::catch_unwind(|| insta::assert_snapshot!(name.as_str(), actual.as_str()));
        if compared.is_err() {
            // (insta's "Stopped on the first failure" is about that one script.)
            failures.push(format!(
                "{}: differs from {name}.snap (diff above)",
                script.display()
            ));
        }
    }
    assert!(failures.is_empty(), "{}", failures.join("\n"));
    assert!(
        scripts.len() >= 40,
        "only {} diagnostic scripts",
        scripts.len()
    );
}

#[test]
fn check_exits_with_status_1_on_every_wrong_script() {
    let dir = root().join("tests/diagnostics");
    for script in files_with_ext(&dir, "soft") {
        let (code, _, err) = softc(&["check", script.to_str().unwrap()]);
        assert_eq!(code, 1, "{}:\n{err}", script.display());
        // The human format starts with FILE:LINE:COL: error[CODE].
        let first = err.lines().next().unwrap_or("");
        assert!(
            first.contains(": error[E") || first.contains(": warning[W"),
            "{}: unexpected first line {first:?}",
            script.display()
        );
    }
}

#[test]
fn json_format_gives_one_object_per_diagnostic() {
    let script = root().join("tests/diagnostics/add_pressure_and_length.soft");
    let (code, out, _) = softc(&[
        "check",
        "--message-format",
        "json",
        script.to_str().unwrap(),
    ]);
    assert_eq!(code, 1);
    let lines: Vec<&str> = out.lines().collect();
    assert!(!lines.is_empty());
    for l in &lines {
        let v: serde_json::Value = serde_json::from_str(l).unwrap();
        for key in ["file", "severity", "code", "message", "start", "end"] {
            assert!(v.get(key).is_some(), "missing {key} in {l}");
        }
    }
    let first: serde_json::Value = serde_json::from_str(lines[0]).unwrap();
    assert_eq!(first["code"], "E0201");
    assert_eq!(first["severity"], "error");
    assert!(first["message"].as_str().unwrap().contains("kPa"));
    assert!(first["message"].as_str().unwrap().contains("mm"));
}
