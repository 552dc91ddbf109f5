//! One run per output folder (issue 20 item 2, issue 31 item 8): a run holds the folders it
//! writes, and a second run may write neither into them nor anywhere below them.

use softc_tests::run_bench_1k;

fn scratch(tag: &str) -> std::path::PathBuf {
    softc_tests::scratch("locks", tag)
}

#[test]
fn a_second_run_on_an_out_folder_in_use_is_refused() {
    // Issue 20 item 2: two optimizations on one `--out DIR` were both accepted, and one
    // silently overwrote the other. A run holds the folder's lock for its life; here this test
    // holds it, as a first run would.
    let d = scratch("lock");
    let out = d.join("out");
    std::fs::create_dir_all(&out).unwrap();
    let first = std::fs::File::create(out.join(".softc.lock")).unwrap();
    first.try_lock().unwrap();
    let script = softc_tests::root().join("runtime/tests/fixtures/optim/pressure.soft");
    let script = script.to_str().unwrap();
    let args = [
        "run",
        script,
        "--iterations",
        "1",
        "--out",
        out.to_str().unwrap(),
    ];
    let (code, _, err) = softc_tests::softc(&args);
    assert_eq!(code, 2, "{err}");
    assert!(
        err.contains("in use by another softc run") && err.contains("--out"),
        "{err}"
    );
    assert!(!out.join("state.json").exists());
    let (code, _, err) = softc_tests::softc(&["run", script, "--resume", out.to_str().unwrap()]);
    assert_eq!(code, 2, "{err}");
    assert!(err.contains("in use by another softc run"), "{err}");
    // Once the first run is over, the folder is free.
    drop(first);
    let (code, _, err) = softc_tests::softc(&args);
    assert_eq!(code, 0, "{err}");
    assert!(out.join("state.json").exists());
    std::fs::remove_dir_all(&d).ok();
}

#[test]
fn no_output_path_inside_a_held_folder_is_accepted() {
    // Issue 31 item 8: while an optimization held `D`, `--json D/result.json` and another
    // optimization's `--out D/vtk` were accepted and overwrote its files.
    let d = scratch("lock-inside");
    let held = d.join("held");
    std::fs::create_dir_all(&held).unwrap();
    let first = std::fs::File::create(held.join(".softc.lock")).unwrap();
    first.try_lock().unwrap();
    let script = softc_tests::root().join("runtime/tests/fixtures/optim/pressure.soft");
    let script = script.to_str().unwrap();
    let inside = |p: &str| held.join(p).to_str().unwrap().to_string();
    let (json, vtk, csv) = (inside("result.json"), inside("vtk"), inside("logs/csv"));
    for args in [
        vec!["--iterations", "1", "--json", &json],
        vec!["--iterations", "1", "--out", &vtk],
        vec!["--no-optimize", "--steps", "10", "--vtk", &vtk],
        vec!["--no-optimize", "--steps", "10", "--csv", &csv],
    ] {
        let mut full = vec!["run", script];
        full.extend(&args);
        let (code, _, err) = softc_tests::softc(&full);
        assert_eq!(code, 2, "{args:?}: {err}");
        assert!(
            err.contains(args[args.len() - 2]) && err.contains("in use by another softc run"),
            "{args:?}: {err}"
        );
    }
    assert_eq!(
        std::fs::read_dir(&held).unwrap().count(),
        1,
        "only the lock file"
    );
    drop(first);
    let (code, _, err) = softc_tests::softc(&["run", script, "--iterations", "1", "--json", &json]);
    assert_eq!(code, 0, "{err}");
    std::fs::remove_dir_all(&d).ok();
}

#[test]
fn a_plain_run_holds_its_output_folders() {
    // The sibling of item 2 for plain runs: `--vtk DIR` and `--csv DIR` of two runs.
    let d = scratch("lock-vtk");
    let first = std::fs::File::create(d.join(".softc.lock")).unwrap();
    first.try_lock().unwrap();
    let (code, _, err) = run_bench_1k(&["--vtk", d.to_str().unwrap()]);
    assert_eq!(code, 2, "{err}");
    assert!(
        err.contains("--vtk") && err.contains("in use by another softc run"),
        "{err}"
    );
    drop(first);
    // One folder for both outputs is one run's.
    let dir = d.to_str().unwrap();
    let (code, _, err) = run_bench_1k(&["--vtk", dir, "--csv", dir]);
    assert_eq!(code, 0, "{err}");
    std::fs::remove_dir_all(&d).ok();
}
