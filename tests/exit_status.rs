//! The exit-status table (docs/src/reference/exit-status.md) is a contract: 0 success, 1 a problem in the input (script
//! or mesh), 2 a usage error (bad flags, an unreadable file, a flag that does not fit the
//! scene). Issue 31 item 13 found commands that answered 1 where the table says 2; this walks
//! one case of each kind per command.

use softc_tests::{root, softc};

fn code(args: &[&str]) -> (i32, String) {
    let (code, _, err) = softc(args);
    (code, err)
}

#[test]
fn exit_statuses_follow_the_readme_table() {
    let ex = |name: &str| root().join("examples").join(name).display().to_string();
    let mesh = root().join("meshes/bench_1k.msh").display().to_string();
    let dir = std::env::temp_dir().join(format!("softc-exit-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let bad_mesh = dir.join("bad.msh");
    std::fs::write(
        &bad_mesh,
        "$MeshFormat\n4.1 0 8\n$EndMeshFormat\n$Nodes\n1 2 3\n",
    )
    .unwrap();
    let bad_mesh = bad_mesh.display().to_string();
    let missing = dir.join("missing.msh").display().to_string();
    let unwritable = dir.join("no-such-folder/out.vtu").display().to_string();
    let bench = ex("benchmark-1k.soft");
    let statics = ex("verification_static.soft");
    let cases: Vec<(Vec<&str>, i32, &str)> = vec![
        (vec!["mesh", "info", &mesh], 0, "a valid mesh"),
        (
            vec!["mesh", "info", &bad_mesh],
            1,
            "a malformed mesh is bad input",
        ),
        (vec!["mesh", "info", &missing], 2, "an unreadable mesh file"),
        (
            vec!["mesh", "convert", &missing, &unwritable],
            2,
            "an unreadable input",
        ),
        (
            vec!["mesh", "convert", &mesh, &unwritable],
            2,
            "an output path that cannot be written",
        ),
        (
            vec![
                "bench",
                "--examples",
                &missing,
                "--sizes",
                "1k",
                "--backends",
                "cpu-f32",
            ],
            2,
            "bench --examples on a missing folder",
        ),
        (vec!["run", &bench, "--steps", "0"], 2, "--steps 0"),
        (
            vec!["run", &statics, "--dt", "1ms"],
            2,
            "--dt on a quasi-static scene",
        ),
        (
            vec![
                "run",
                &bench,
                "--grad",
                "--steps",
                "5",
                "--memory-budget",
                "1B",
            ],
            2,
            "a memory budget below two states",
        ),
        (vec!["run", &missing], 2, "an unreadable script"),
        (
            vec!["run", &statics, "--backend", "reference"],
            2,
            "the explicit oracle on a quasi-static scene (issue 31 item 1)",
        ),
        (vec!["run", &bench, "--steps", "5"], 0, "a short run"),
    ];
    let mut wrong = Vec::new();
    for (args, want, what) in &cases {
        let (got, err) = code(args);
        if got != *want {
            wrong.push(format!(
                "{what}: `softc {}` exited {got}, the table says {want}\n{err}",
                args.join(" ")
            ));
        }
    }
    std::fs::remove_dir_all(&dir).unwrap();
    assert!(wrong.is_empty(), "{}", wrong.join("\n"));
}

/// Issue 31 item 2: a loss window that holds none of the run's states summed nothing and
/// reported loss 0 and gradient 0. Now the run stops (bad input, exit 1) saying where the
/// window is and where the states are — for an explicit run and for a static load path.
#[test]
fn a_loss_window_with_no_state_in_it_is_an_error() {
    let dir = std::env::temp_dir().join(format!("softc-window-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let variant = |example: &str, from: &str, to: &str, name: &str| {
        let text = std::fs::read_to_string(root().join("examples").join(example)).unwrap();
        assert!(text.contains(from), "{example}");
        let text = text
            .replace(from, to)
            .replace("\"../meshes/", &format!("\"{}/meshes/", root().display()));
        let path = dir.join(name);
        std::fs::write(&path, text).unwrap();
        path.display().to_string()
    };
    let explicit = variant(
        "benchmark-1k.soft",
        "at end",
        "over [0.1 s, 0.15 s]",
        "explicit.soft",
    );
    let statics = variant(
        "pressure_optimization.soft",
        "at end",
        "over [0 s, 0.1 s]",
        "static.soft",
    );
    for (script, extra) in [(&explicit, "--steps"), (&statics, "--grad")] {
        let args: Vec<&str> = if extra == "--steps" {
            vec!["run", script, "--steps", "10", "--grad"]
        } else {
            vec!["run", script, "--grad"]
        };
        let (code, out, err) = softc(&args);
        assert_eq!(code, 1, "{script}: {out}\n{err}");
        assert!(err.contains("holds none of the run's states"), "{err}");
    }
    // A window that does hold states runs.
    let inside = variant(
        "benchmark-1k.soft",
        "at end",
        "over [0.2 ms, 0.3 ms]",
        "inside.soft",
    );
    let (code, _, err) = softc(&["run", &inside, "--steps", "10"]);
    assert_eq!(code, 0, "{err}");
    std::fs::remove_dir_all(&dir).unwrap();
}

/// Issue 31 item 12: flags that had no effect were taken silently. `bench`'s trade-off knobs
/// without `--tradeoff` are a usage error; `--linear-solver krylov` on an explicit scene and
/// `--initial-state` on a quasi-static one run with a warning naming the flag and why.
#[test]
fn flags_without_effect_are_named() {
    let ex = |name: &str| root().join("examples").join(name).display().to_string();
    let examples = root().join("examples").display().to_string();
    let (code, _, err) = softc(&[
        "bench",
        "--integrators",
        "explicit",
        "--examples",
        &examples,
        "--sizes",
        "1k",
        "--backends",
        "cpu-f32",
    ]);
    assert_eq!(code, 2, "{err}");
    assert!(err.contains("--tradeoff"), "{err}");
    let bench = ex("benchmark-1k.soft");
    let (code, _, err) = softc(&["run", &bench, "--steps", "5", "--linear-solver", "krylov"]);
    assert_eq!(code, 0, "{err}");
    assert!(
        err.contains("warning: --linear-solver has no effect") && err.contains("explicit"),
        "{err}"
    );
    let statics = ex("pressure_optimization.soft");
    let (code, out, err) = softc(&["run", &statics, "--grad", "--initial-state"]);
    assert_eq!(code, 0, "{err}");
    assert!(
        err.contains("warning: --initial-state has no effect"),
        "{err}"
    );
    assert!(out.contains("\"initial_state_gradients\": null"), "{out}");
    // Where they apply, no warning.
    let (_, _, err) = softc(&["run", &bench, "--steps", "5", "--grad", "--initial-state"]);
    assert!(!err.contains("no effect"), "{err}");
}
