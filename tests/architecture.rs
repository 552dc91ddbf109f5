//! Architecture rules checked on the source tree (ARCHITECTURE.md): the runtime executes what
//! the compiler resolved and does not read scripts itself; the two backends share only the IR
//! and `compiler/src/back/mod.rs`; nothing below the CLI imports it; no source file grows past
//! 1,500 lines.

use softc_tests::{files_under, root};
use std::path::{Path, PathBuf};

/// The most lines a source file may have.
const MAX_LINES: usize = 1500;

/// Every `.rs` file under `dir` (relative to the workspace root), recursively, sorted. Fails
/// when there is none, so a moved folder cannot make a rule pass vacuously.
fn rust_files(dir: &str) -> Vec<PathBuf> {
    let out = files_under(&root().join(dir), "rs");
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
    let dirs = [
        "compiler/src",
        "compiler/tests",
        "runtime/src",
        "runtime/tests",
        "tests",
    ];
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

/// The code of a file: comment lines dropped (a doc comment may name any module).
fn code_lines(path: &Path) -> Vec<(usize, String)> {
    read(path)
        .lines()
        .enumerate()
        .filter(|(_, l)| !l.trim_start().starts_with("//"))
        .map(|(i, l)| (i + 1, l.to_string()))
        .collect()
}

/// Where the files under `dir` (but not under `except`) name one of the compiler's `layers`:
/// a path `softc_compiler::LAYER` or a grouped import `softc_compiler::{…LAYER…}`.
fn uses_of_layers(dir: &str, except: &[&str], layers: &[&str]) -> Vec<String> {
    let mut found = Vec::new();
    for file in rust_files(dir) {
        let name = rel(&file);
        if except.iter().any(|e| name.starts_with(e)) {
            continue;
        }
        let lines = code_lines(&file);
        let code: String = lines
            .iter()
            .map(|(_, l)| l.as_str())
            .collect::<Vec<_>>()
            .join("\n");
        let mut hits: Vec<String> = Vec::new();
        for layer in layers {
            let direct = format!("softc_compiler::{layer}");
            for (n, l) in &lines {
                if l.contains(&direct) {
                    hits.push(format!("{name}:{n}: {}", l.trim()));
                }
            }
        }
        // Grouped imports may span lines: `use softc_compiler::{\n    front::ast, …};`.
        let mut rest = code.as_str();
        while let Some(at) = rest.find("softc_compiler::{") {
            let group = &rest[at..];
            let end = group.find('}').unwrap_or(group.len());
            let inside = &group["softc_compiler::{".len()..end];
            for layer in layers {
                if inside
                    .split(|c: char| !c.is_alphanumeric() && c != '_')
                    .any(|w| w == *layer)
                {
                    hits.push(format!("{name}: `softc_compiler::{{…{layer}…}}`"));
                }
            }
            rest = &group[end.min(group.len())..];
            if rest.is_empty() {
                break;
            }
            rest = &rest[1.min(rest.len())..];
        }
        found.extend(hits);
    }
    found
}

/// The runtime consumes the compiled program (`softc_compiler::{compile, driver, ir, back, …}`)
/// and never re-does the compiler's work from the syntax tree. Exceptions: the language server
/// (editor tooling over the IDE layer) and the reference oracle, which reads the script itself
/// on purpose so that it does not share the lowering it checks.
#[test]
fn the_runtime_does_not_import_the_front_end_sema_or_lowering() {
    let found = uses_of_layers(
        "runtime/src",
        &["runtime/src/lsp/", "runtime/src/reference/"],
        &["front", "sema", "lower"],
    );
    assert!(
        found.is_empty(),
        "runtime code reaches into the compiler's front end, sema or lowering; use \
         softc_compiler::compile and the resolved program (softc_compiler::driver) instead:\n{}",
        found.join("\n")
    );
}

/// The Python package is a front end like the CLI: it calls the runtime's embedding API and
/// never re-does the compiler's work (nor goes through the CLI).
#[test]
fn the_python_package_uses_the_embedding_api_only() {
    let mut found = uses_of_layers("python/src", &[], &["front", "sema", "lower"]);
    for file in rust_files("python/src") {
        for (n, l) in code_lines(&file) {
            if l.contains("softc::cli") {
                found.push(format!("{}:{n}: {}", rel(&file), l.trim()));
            }
        }
    }
    assert!(
        !rust_files("python/src").is_empty(),
        "python/src has no Rust files"
    );
    assert!(found.is_empty(), "{}", found.join("\n"));
}

/// The check itself finds both spellings (it must be able to fail).
#[test]
fn the_layer_check_sees_direct_and_grouped_imports() {
    let dir = std::env::temp_dir().join(format!("softc-arch-{}", std::process::id()));
    std::fs::create_dir_all(dir.join("src")).unwrap();
    std::fs::write(
        dir.join("src/a.rs"),
        "use softc_compiler::sema::CheckOptions;\n// softc_compiler::lower in a comment\n",
    )
    .unwrap();
    std::fs::write(
        dir.join("src/b.rs"),
        "use softc_compiler::{\n    driver::Variant,\n    front::ast::Script,\n};\n",
    )
    .unwrap();
    let rel_dir = dir.join("src");
    let found = uses_of_layers(rel_dir.to_str().unwrap(), &[], &["front", "sema", "lower"]);
    std::fs::remove_dir_all(&dir).unwrap();
    assert_eq!(found.len(), 2, "{found:?}");
    assert!(
        found[0].ends_with("use softc_compiler::sema::CheckOptions;"),
        "{found:?}"
    );
    assert!(found[1].contains("front"), "{found:?}");
}

/// The CLI only parses flags and calls library code: nothing below it imports it, and its
/// files reach each other only through `cli/mod.rs`.
#[test]
fn nothing_below_the_cli_imports_it() {
    let mut found = Vec::new();
    for file in rust_files("runtime/src") {
        let name = rel(&file);
        if name.starts_with("runtime/src/cli/") || name.starts_with("runtime/src/bin/") {
            continue;
        }
        for (n, l) in code_lines(&file) {
            if l.contains("crate::cli") || l.contains("softc::cli") {
                found.push(format!("{name}:{n}: {}", l.trim()));
            }
        }
    }
    for file in rust_files("runtime/src/cli") {
        let name = rel(&file);
        if name == "runtime/src/cli/mod.rs" {
            continue;
        }
        for (n, l) in code_lines(&file) {
            for sibling in ["run", "optimize", "bench", "mesh"] {
                if l.contains(&format!("super::{sibling}::")) {
                    found.push(format!("{name}:{n}: {}", l.trim()));
                }
            }
        }
    }
    assert!(
        found.is_empty(),
        "imports of the CLI from below it, or between CLI files (move the shared code into a \
         library module such as session.rs or outputs/):\n{}",
        found.join("\n")
    );
}

/// Outputs depend on the engine, never the reverse: the engine, the solvers, the devices and
/// the optimizer hand states to the engine's sink traits (`engine::sinks`) and know no file
/// format; `outputs` implements those traits and formats the engine's results (JSON, VTK, CSV).
#[test]
fn the_engine_knows_no_output_format() {
    let mut found = Vec::new();
    for dir in [
        "runtime/src/engine",
        "runtime/src/solvers",
        "runtime/src/devices",
        "runtime/src/optim",
    ] {
        for file in rust_files(dir) {
            for (n, l) in code_lines(&file) {
                if l.contains("crate::outputs") || l.contains("softc::outputs") {
                    found.push(format!("{}:{n}: {}", rel(&file), l.trim()));
                }
            }
        }
    }
    assert!(
        found.is_empty(),
        "the engine side names `outputs`; give it a trait in engine::sinks for `outputs` to \
         implement instead:\n{}",
        found.join("\n")
    );
}

/// The editor support answers from the checker's resolution table (`sema::Resolution`): it
/// keeps no scopes of its own, so what an editor shows cannot drift from what `softc check`
/// resolved.
#[test]
fn the_ide_layer_has_no_resolver_of_its_own() {
    let found = mentions(
        "compiler/src/ide",
        &["scopes", "fn use_name", "struct Resolver"],
    );
    assert!(
        found.is_empty(),
        "compiler/src/ide resolves names itself; read sema's resolution table instead:\n{}",
        found.join("\n")
    );
}

/// Lowering and the driver read sema's checked program (`sema::hir`: declarations by id, names
/// resolved once by the checker, expressions typed), never the syntax tree: what they compile
/// is what the checker checked, and a new construct is added to the checked program once.
#[test]
fn lowering_and_the_driver_do_not_read_the_syntax_tree() {
    let mut found = mentions(
        "compiler/src/lower",
        &["front::ast", "ast::", "front::parse"],
    );
    found.extend(mentions(
        "compiler/src/driver",
        &["front::ast", "ast::", "front::parse"],
    ));
    assert!(
        found.is_empty(),
        "lower/ or driver/ reads the syntax tree; read sema's checked program (sema::hir) \
         instead:\n{}",
        found.join("\n")
    );
}
