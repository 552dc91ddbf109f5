//! No input may panic the front end, hang it, or take long to diagnose: random bytes, random
//! token soups, and the classic pathological inputs (deep nesting, huge numbers, long chains,
//! invalid UTF-8, binary garbage).

use proptest::prelude::*;
use softc_compiler::sema::CheckOptions;
use softc_tests::run_bench_1k;
use std::time::{Duration, Instant};

/// Check and format an input; both must return (diagnostics or a result), never panic.
fn front_end(bytes: &[u8]) -> usize {
    let (text, checked) = softc_compiler::check_bytes(bytes, &CheckOptions::default());
    let file = softc_compiler::diag::SourceFile::new("fuzz.soft", &text);
    for d in &checked.diagnostics {
        // Rendering must cope with any span the checker produces.
        let _ = file.render(d);
        let _ = file.render_json(d);
    }
    if let Ok(t) = std::str::from_utf8(bytes)
        && let Ok(formatted) = softc_compiler::fmt::format_source(t)
    {
        // What fmt prints must parse again, to the same canonical text.
        let again =
            softc_compiler::fmt::format_source(&formatted).expect("formatted output parses");
        assert_eq!(again, formatted, "fmt is not idempotent on {t:?}");
    }
    checked.diagnostics.len()
}

/// Tokens of the language, valid and nearly valid, for token-soup inputs.
const TOKENS: &[&str] = &[
    "mesh",
    "material",
    "region",
    "chamber",
    "nodes",
    "elements",
    "param",
    "input",
    "let",
    "fn",
    "controller",
    "sim",
    "loss",
    "optimize",
    "with",
    "for",
    "iterations",
    "in",
    "from",
    "at",
    "end",
    "over",
    "fix",
    "pressure",
    "use",
    "output",
    "every",
    "steps",
    "stop",
    "when",
    "validate",
    "if",
    "then",
    "else",
    "and",
    "or",
    "not",
    "true",
    "false",
    "body",
    "tip",
    "p",
    "x",
    "t",
    "v",
    "x0",
    "W",
    "I1bar",
    "J",
    "yeoh",
    "load",
    "box",
    "select",
    "sum",
    "mean",
    "ramp",
    "window",
    "sigmoid",
    "auto",
    "=",
    "==",
    "<",
    ">=",
    "+",
    "-",
    "*",
    "/",
    "^",
    "@",
    "..",
    ".",
    ",",
    ":",
    ";",
    "->",
    "(",
    ")",
    "[",
    "]",
    "{",
    "}",
    "0",
    "1",
    "3.5",
    "1e3",
    "1e999",
    "kPa",
    "mm",
    "/s",
    "kg/m^3",
    "\"tet.msh\"",
    "\"",
    "#",
    "\n",
    " ",
    "µm",
];

proptest! {
    #![proptest_config(ProptestConfig { cases: 3000, .. ProptestConfig::default() })]

    #[test]
    fn random_bytes_never_panic(bytes in proptest::collection::vec(any::<u8>(), 0..400)) {
        front_end(&bytes);
    }

    #[test]
    fn random_token_sequences_never_panic(
        picks in proptest::collection::vec((0..TOKENS.len(), any::<bool>()), 0..80)
    ) {
        let mut s = String::new();
        for (i, space) in picks {
            s.push_str(TOKENS[i]);
            if space { s.push(' '); }
        }
        front_end(s.as_bytes());
    }
}

/// Runs a pathological input and checks it is diagnosed (with an error) quickly.
fn diagnosed_quickly(name: &str, bytes: &[u8]) {
    let start = Instant::now();
    let n = front_end(bytes);
    let took = start.elapsed();
    assert!(n > 0, "{name}: no diagnostic");
    // A hang guard only: speed is measured (printed here, `--nocapture`), not asserted; on an
    // idle 2-core machine each of these inputs is diagnosed in well under a second.
    assert!(took < Duration::from_secs(60), "{name}: took {took:?}");
    eprintln!("{name}: {} bytes diagnosed in {took:?}", bytes.len());
}

#[test]
fn one_megabyte_of_nested_parentheses() {
    let mut s = String::from("let a = ");
    s.push_str(&"(".repeat(1 << 20));
    diagnosed_quickly("nested parens", s.as_bytes());
}

#[test]
fn one_megabyte_of_balanced_nesting() {
    let depth = 1 << 19;
    let s = format!("let a = {}1{}", "(".repeat(depth), ")".repeat(depth));
    diagnosed_quickly("balanced nesting", s.as_bytes());
}

#[test]
fn long_operator_chains() {
    let s = format!("let a = 1{}", " + 1".repeat(250_000));
    diagnosed_quickly("long sum", s.as_bytes());
    let s = format!("let a = 2{}", "^2".repeat(250_000));
    diagnosed_quickly("long power tower", s.as_bytes());
    let s = format!("let a = {}1", "-".repeat(1 << 20));
    diagnosed_quickly("many minus signs", s.as_bytes());
    let s = format!("let a = {}true", "not ".repeat(200_000));
    diagnosed_quickly("many nots", s.as_bytes());
}

#[test]
fn huge_numbers_and_powers() {
    diagnosed_quickly("1e999999", b"let a = 1e999999");
    diagnosed_quickly("unit power", b"let a = 1 m^99999999999");
    let digits = "9".repeat(1 << 20);
    diagnosed_quickly("a million digits", format!("let a = {digits}").as_bytes());
}

#[test]
fn invalid_utf8_and_binary_garbage() {
    diagnosed_quickly("invalid utf-8", b"mesh body = load(\"a\xff\xfe.msh\")");
    let mut garbage = Vec::with_capacity(1 << 20);
    let mut x: u32 = 12345;
    for _ in 0..(1 << 20) {
        x = x.wrapping_mul(1_664_525).wrapping_add(1_013_904_223);
        garbage.push((x >> 24) as u8);
    }
    diagnosed_quickly("binary garbage", &garbage);
    diagnosed_quickly("NUL bytes", &[0u8; 4096]);
}

#[test]
fn empty_and_whitespace_only_files_are_diagnosed() {
    diagnosed_quickly("empty", b"");
    diagnosed_quickly("whitespace", b"   \n\n\t  # just a comment\n");
}

#[test]
fn many_declarations() {
    let mut s = String::new();
    for i in 0..50_000 {
        s.push_str(&format!("let a{i} = {i} mm\n"));
    }
    diagnosed_quickly("50k lets", s.as_bytes());
}

#[test]
fn the_binary_survives_pathological_input() {
    // The real binary runs the front end on a large-stack thread; in-process runs use the test
    // thread's stack, so this also shows the limits keep recursion shallow.
    let dir = std::env::temp_dir().join(format!("softc-robust-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let path = dir.join("deep.soft");
    std::fs::write(&path, format!("let a = {}", "[".repeat(100_000))).unwrap();
    let (code, _, err) = softc_tests::softc(&["check", path.to_str().unwrap()]);
    assert_eq!(code, 1, "{err}");
    assert!(err.contains("E0002"), "{err}");
    std::fs::remove_dir_all(&dir).ok();
}

// ---- The command line under hostile use (issue 20) ----

/// A scratch folder of this test process.
fn scratch(tag: &str) -> std::path::PathBuf {
    softc_tests::scratch("hostile", tag)
}

#[test]
fn set_and_dt_values_need_the_dimension_of_what_they_set() {
    // Issue 20 item 1: `p_peak=3mm` ran at 0.003 Pa, `p_peak=3` and `p_peak=3/s` at 3 Pa,
    // `--dt 40mm` at 0.04 s.
    for (flag, said) in [
        ("p_peak=3mm", "is a length"),
        ("p_peak=3", "has no unit"),
        ("p_peak=3/s", "is a rate"),
    ] {
        let (code, _, err) = run_bench_1k(&["--set", flag]);
        assert_eq!(code, 2, "{flag}: {err}");
        assert!(
            err.contains(&format!("--set {flag}"))
                && err.contains(said)
                && err.contains("pressure"),
            "{flag}: {err}"
        );
        assert!(
            err.contains("p_peak=3Pa"),
            "{flag}: the fix is shown: {err}"
        );
    }
    for (flag, said) in [("40mm", "is a length"), ("40", "has no unit")] {
        let (code, _, err) = run_bench_1k(&["--dt", flag]);
        assert_eq!(code, 2, "--dt {flag}: {err}");
        assert!(
            err.contains(&format!("--dt {flag}")) && err.contains(said),
            "{err}"
        );
    }
    // The right dimension runs, negative values parse (and meet the param's bounds).
    let (code, _, err) = run_bench_1k(&["--set", "p_peak=4.5kPa", "--dt", "40us"]);
    assert_eq!(code, 0, "{err}");
    let (value, _) = softc::session::parse_quantity("-3kPa").unwrap();
    assert_eq!(value, -3000.0);
    // A negative value reaches the bounds check as -3 kPa (p_peak is declared in [0, 50 kPa]).
    let (code, _, err) = run_bench_1k(&["--set", "p_peak=-3kPa"]);
    assert_eq!(code, 2, "{err}");
    assert!(
        err.contains("-3e3") && err.contains("outside the bounds"),
        "{err}"
    );
}

#[test]
fn arguments_that_are_not_utf8_are_usage_errors() {
    // Issue 20 item 12 (the binary itself: runtime/tests/mesh_cli.rs).
    use std::ffi::OsString;
    use std::os::unix::ffi::OsStringExt;
    let script = softc_tests::root().join("examples/benchmark-1k.soft");
    let bad = OsString::from_vec(b"p_peak=3\xffkPa".to_vec());
    let args: Vec<OsString> = vec![
        "softc".into(),
        "run".into(),
        script.into(),
        "--set".into(),
        bad,
    ];
    let (mut out, mut err) = (Vec::new(), Vec::new());
    let code = softc::cli::run(&args, &mut out, &mut err);
    let err = String::from_utf8_lossy(&err);
    assert_eq!(code, 2, "{err}");
    assert!(
        err.contains("argument 4") && err.contains("p_peak=3"),
        "{err}"
    );
    // A script name that is not UTF-8 is a name like any other.
    let missing = OsString::from_vec(b"/nonexistent/\xff.soft".to_vec());
    let args: Vec<OsString> = vec!["softc".into(), "check".into(), missing];
    let (mut out, mut err) = (Vec::new(), Vec::new());
    let code = softc::cli::run(&args, &mut out, &mut err);
    let err = String::from_utf8_lossy(&err);
    assert_eq!(code, 2, "{err}");
    assert!(err.contains("cannot read `/nonexistent/"), "{err}");
}

#[test]
fn fmt_writes_through_a_symbolic_link() {
    // Issue 20 item 7: `softc fmt link.soft` replaced the link with a formatted file and left
    // the script it points to as it was.
    let d = scratch("fmt-link");
    let real = d.join("real.soft");
    std::fs::write(&real, "let   a =   3 mm\n").unwrap();
    let link = d.join("link.soft");
    std::os::unix::fs::symlink(&real, &link).unwrap();
    let (code, _, err) = softc_tests::softc(&["fmt", link.to_str().unwrap()]);
    assert_eq!(code, 0, "{err}");
    assert!(
        std::fs::symlink_metadata(&link)
            .unwrap()
            .file_type()
            .is_symlink()
    );
    assert_eq!(std::fs::read_to_string(&real).unwrap(), "let a = 3 mm\n");
    std::fs::remove_dir_all(&d).ok();
}

#[test]
fn unwritable_outputs_are_refused_before_the_run() {
    // Issue 20 item 6: an unwritable `--json` path was found after the run, and its results
    // were lost.
    let d = scratch("outputs");
    let file = d.join("a-file");
    std::fs::write(&file, "x").unwrap();
    let in_file = file.join("out.json");
    let proc_dir = "/proc/softc-cannot-create-this";
    for (flag, path, said) in [
        ("--json", in_file.to_str().unwrap(), "does not exist"),
        ("--json", d.to_str().unwrap(), "is a folder"),
        ("--vtk", proc_dir, "cannot be created"),
        ("--out", proc_dir, "cannot be created"),
    ] {
        let (code, out, err) = run_bench_1k(&[flag, path]);
        assert_eq!(code, 2, "{flag} {path}: {err}");
        assert!(
            err.contains(&format!("{flag} {path}")) && err.contains(said),
            "{err}"
        );
        assert!(!err.contains("steps of"), "refused before the run: {err}");
        assert!(out.is_empty());
    }
    std::fs::remove_dir_all(&d).ok();
}

#[test]
fn usage_errors_exit_2_before_any_work() {
    // Issue 20 item 18: a folder or an unreadable script, bad --checkpoint/--memory-budget
    // values (refused only after the stable-step estimate) and --csv into a file exited 1.
    let d = scratch("usage");
    let (code, _, err) = softc_tests::softc(&["run", d.to_str().unwrap()]);
    assert_eq!(code, 2, "{err}");
    assert!(err.contains("is a folder"), "{err}");
    let file = d.join("a-file");
    std::fs::write(&file, "x").unwrap();
    let file = file.to_str().unwrap();
    for (flags, said) in [
        (
            &["--grad", "--checkpoint", "sometimes"][..],
            "--checkpoint sometimes",
        ),
        (
            &["--grad", "--checkpoint", "periodic:0"][..],
            "--checkpoint periodic:0",
        ),
        (
            &["--grad", "--memory-budget", "12 mm"][..],
            "--memory-budget 12 mm",
        ),
        (
            &["--grad", "--memory-budget", "-5MB"][..],
            "--memory-budget -5MB",
        ),
        (&["--csv", file][..], "is a file, not a folder"),
    ] {
        let (code, _, err) = run_bench_1k(flags);
        assert_eq!(code, 2, "{flags:?}: {err}");
        assert!(err.contains(said), "{flags:?}: {err}");
        assert!(
            !err.contains("stable step estimate"),
            "before any work: {err}"
        );
    }
    std::fs::remove_dir_all(&d).ok();
}

#[test]
fn a_step_count_beyond_the_limit_is_refused_unless_asked_for() {
    // Issue 20 item 14: `dt = 1e-12 s` with `duration = 1 s` started 10¹² steps silently.
    let d = scratch("steps");
    let text = std::fs::read_to_string(softc_tests::root().join("examples/benchmark-1k.soft"))
        .unwrap()
        .replace(
            "../meshes/",
            &format!("{}/meshes/", softc_tests::root().display()),
        )
        .replace(
            "dt = 40 us\n  steps = 4000",
            "dt = 1e-12 s\n  duration = 1 s",
        );
    let script = d.join("tiny-dt.soft");
    std::fs::write(&script, text).unwrap();
    let script = script.to_str().unwrap();
    let start = Instant::now();
    let (code, _, err) = softc_tests::softc(&["run", script]);
    assert_eq!(code, 1, "{err}");
    assert!(
        err.contains("1000000000000 steps") && err.contains("--steps 1000000000000"),
        "{err}"
    );
    assert!(start.elapsed() < Duration::from_secs(60));
    // Asked for, a count runs.
    let (code, _, err) = softc_tests::softc(&["run", script, "--steps", "3"]);
    assert_eq!(code, 0, "{err}");
    std::fs::remove_dir_all(&d).ok();
}

#[test]
fn smaller_defects_of_messages_and_outputs() {
    // Issue 20 item 19.
    let d = scratch("smaller");
    let pressure = softc_tests::root().join("runtime/tests/fixtures/optim/pressure.soft");
    let pressure = pressure.to_str().unwrap();
    // A bounds message in the script's terms, not Rust's debug text `Both(0.0, 50000.0)`.
    let (code, _, err) =
        softc_tests::softc(&["run", pressure, "--iterations", "1", "--set", "p_peak=0kPa"]);
    assert_eq!(code, 1, "{err}");
    assert!(
        err.contains("[0, 50000]") && !err.contains("Both("),
        "{err}"
    );
    // A backend change on --resume names the backend.
    let out = d.join("out");
    let out = out.to_str().unwrap();
    let (code, _, err) = softc_tests::softc(&["run", pressure, "--iterations", "1", "--out", out]);
    assert_eq!(code, 0, "{err}");
    let (code, _, err) = softc_tests::softc(&[
        "run",
        pressure,
        "--iterations",
        "2",
        "--resume",
        out,
        "--backend",
        "interp",
    ]);
    assert_eq!(code, 2, "{err}");
    assert!(
        err.contains("--backend cpu (saved) vs interp (now)"),
        "{err}"
    );
    // `--dt 0s` was run and reported as "estimate 0 s".
    for dt in ["0s", "-1us"] {
        let (code, _, err) = run_bench_1k(&["--dt", dt]);
        assert_eq!(code, 2, "{err}");
        assert!(
            err.contains(&format!("--dt {dt}")) && err.contains("positive"),
            "{err}"
        );
    }
    // A read-only --out folder was found after the first iteration, the message naming no
    // path.
    let (code, _, err) = softc_tests::softc(&["run", pressure, "--out", "/proc/softc-out"]);
    assert_eq!(code, 2, "{err}");
    assert!(
        err.contains("--out /proc/softc-out") && !err.contains("iteration 1/"),
        "{err}"
    );
    // A 1 B --memory-budget was silently exceeded; it is a usage error (issue 31 item 13).
    let (code, _, err) = run_bench_1k(&["--grad", "--memory-budget", "1B"]);
    assert_eq!(code, 2, "{err}");
    assert!(
        err.contains("--memory-budget 1B") && err.contains("give at least"),
        "{err}"
    );
    // The VTU wrote points in mm and displacement in m, unlabelled: one unit system (SI), and
    // every array's name says its unit.
    let vtk = d.join("vtk");
    let (code, _, err) = run_bench_1k(&["--vtk", vtk.to_str().unwrap()]);
    assert_eq!(code, 0, "{err}");
    let last = vtk.join("benchmark-1k_000001.vtu");
    let text = String::from_utf8_lossy(&std::fs::read(&last).unwrap()).into_owned();
    for name in [
        "displacement_m",
        "velocity_m_per_s",
        "strain_energy_density_J_per_m3",
        "length unit: m",
    ] {
        assert!(text.contains(name), "{name}");
    }
    let mesh = softc::mesh::read(&last, softc::mesh::LengthUnit::Metre).unwrap();
    let max_x = mesh.nodes.iter().map(|n| n[0]).fold(f64::MIN, f64::max);
    assert!(
        (max_x - 0.06).abs() < 1e-6,
        "points in metres: the 60 mm beam ends at {max_x}"
    );
    std::fs::remove_dir_all(&d).ok();
}

// ---- Property test: random flag values and random meshes through the command line ----

/// `softc ARGS` in-process on a thread with the binary's large stack: its exit status, stdout
/// and stderr. A panic or a run past `limit` fails the test, naming the arguments.
fn softc_limited(args: &[std::ffi::OsString], limit: Duration) -> (i32, String, String) {
    let mut argv: Vec<std::ffi::OsString> = vec!["softc".into()];
    argv.extend(args.iter().cloned());
    let shown = format!("{argv:?}");
    let (tx, rx) = std::sync::mpsc::channel();
    let worker = std::thread::Builder::new()
        .stack_size(64 << 20)
        .spawn(move || {
            let (mut out, mut err) = (Vec::new(), Vec::new());
            let code = softc::cli::run(&argv, &mut out, &mut err);
            let _ = tx.send((
                code,
                String::from_utf8_lossy(&out).into_owned(),
                String::from_utf8_lossy(&err).into_owned(),
            ));
        })
        .unwrap();
    match rx.recv_timeout(limit) {
        Ok(r) => {
            worker.join().unwrap();
            r
        }
        // The sender went away without a result: the thread panicked.
        Err(std::sync::mpsc::RecvTimeoutError::Disconnected) => {
            let _ = worker.join();
            panic!("softc panicked on {shown}")
        }
        Err(std::sync::mpsc::RecvTimeoutError::Timeout) => {
            panic!("softc ran past {limit:?} on {shown} (a hang)")
        }
    }
}

/// A fixed seed: the same cases on every run and machine.
fn deterministic_runner(cases: u32) -> proptest::test_runner::TestRunner {
    use proptest::test_runner::{Config, RngAlgorithm, TestRng, TestRunner};
    let config = Config {
        cases,
        failure_persistence: None,
        ..Config::default()
    };
    TestRunner::new_with_rng(config, TestRng::deterministic_rng(RngAlgorithm::ChaCha))
}

/// The small fixture meshes of every format softc reads, by extension.
const MESH_FIXTURES: &[&str] = &[
    "cube_v41.msh",
    "cube_v22.msh",
    "gmsh_cube_v41_bin.msh",
    "cube.vtk",
    "cube_binary.vtk",
    "cube_ascii.vtu",
    "cube_binary.vtu",
    "cube.inp",
    "cube.node",
];

/// Random bytes, or a fixture mesh corrupted: truncated, bytes overwritten, a range repeated.
fn mesh_bytes() -> impl Strategy<Value = (usize, bool, Vec<u8>)> {
    let random = (
        0..MESH_FIXTURES.len(),
        proptest::collection::vec(any::<u8>(), 0..2000),
    )
        .prop_map(|(k, b)| (k, true, b));
    let corrupted = (
        0..MESH_FIXTURES.len(),
        any::<proptest::sample::Index>(),
        proptest::collection::vec((any::<proptest::sample::Index>(), any::<u8>()), 0..6),
        0..3u8,
    )
        .prop_map(|(k, cut, flips, how)| {
            let dir = softc_tests::root().join("runtime/tests/fixtures/mesh");
            let mut b = std::fs::read(dir.join(MESH_FIXTURES[k])).unwrap();
            let at = cut.index(b.len().max(1));
            match how {
                0 => b.truncate(at),
                1 => {
                    let copy = b[at..].to_vec();
                    b.extend_from_slice(&copy[..copy.len().min(200)]);
                }
                _ => {}
            }
            for (i, byte) in flips {
                if !b.is_empty() {
                    let i = i.index(b.len());
                    b[i] = byte;
                }
            }
            (k, false, b)
        });
    prop_oneof![random, corrupted]
}

#[test]
fn random_meshes_through_the_command_line_are_refused_by_name() {
    let d = scratch("prop-mesh");
    let mut runner = deterministic_runner(96);
    let counter = std::sync::atomic::AtomicUsize::new(0);
    let result = runner.run(&mesh_bytes(), |(k, random, bytes)| {
        let case = counter.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
        let ext = MESH_FIXTURES[k].rsplit('.').next().unwrap();
        let name = format!("case{case}.{ext}");
        let mesh = d.join(&name);
        std::fs::write(&mesh, &bytes).unwrap();
        if ext == "node" {
            // tetgen's elements beside the nodes, as the fixture has them.
            let ele = softc_tests::root().join("runtime/tests/fixtures/mesh/cube.ele");
            std::fs::copy(ele, mesh.with_extension("ele")).unwrap();
        }
        let info: Vec<std::ffi::OsString> = vec!["mesh".into(), "info".into(), mesh.clone().into()];
        let (code, _, err) = softc_limited(&info, Duration::from_secs(30));
        prop_assert!(
            (code == 1 || (code == 0 && !random)),
            "mesh info {name}: exit {code}: {err}"
        );
        if code != 0 {
            prop_assert!(
                err.contains(&name),
                "mesh info {name}: the message names no file: {err}"
            );
        }
        // The same mesh through a script.
        let script = d.join(format!("case{case}.soft"));
        std::fs::write(
            &script,
            format!(
                "mesh body = load(\"{name}\")\n\
                 material rubber = neo_hookean(mu: 100 kPa, kappa: 1 MPa, density: 1070 kg/m^3)\n\
                 region clamp = box(min: [-1, -1, -1] mm, max: [0.1, 100, 100] mm)\n\
                 sim {{\n  dt = 1 us\n  steps = 2\n  damping = 20 /s\n  fix clamp\n}}\n"
            ),
        )
        .unwrap();
        let run: Vec<std::ffi::OsString> = vec!["run".into(), script.into()];
        let (code, _, err) = softc_limited(&run, Duration::from_secs(30));
        prop_assert!(
            (code == 1 || (code == 0 && !random)),
            "run with {name}: exit {code}: {err}"
        );
        if code != 0 {
            prop_assert!(
                err.contains(&name),
                "run with {name}: the message names no file: {err}"
            );
        }
        Ok(())
    });
    if let Err(e) = result {
        panic!("{e}");
    }
    std::fs::remove_dir_all(&d).ok();
}

/// Numbers, units and the rest of what flag values are made of.
const NUMBERS: &[&str] = &[
    "0",
    "1",
    "-1",
    "2.5",
    "-3",
    "40",
    "1e308",
    "1e-308",
    "1e400",
    "nan",
    "inf",
    "-0",
    "007",
    "99999999999999999999",
    "0x10",
    "1_000",
    ".5",
    "5.",
    "1e",
    "",
];
const UNITS: &[&str] = &[
    "", "s", "us", "ms", " us", "mm", "kPa", "Pa", "/s", "B", "MB", "GiB", "kg/m^3", "%", "µs",
    "kPa/s", "m^2",
];
const OTHER: &[&str] = &[
    "=",
    ":",
    ",",
    "..",
    "-",
    "--",
    "p_peak",
    "p_peak=",
    "p_peak.1=",
    "periodic:",
    "revolve:",
    "store_all",
    "auto",
    "cpu",
    "interp",
    "reference",
    "f32",
    "f64",
    "\"",
    "\\",
    "(",
    "\u{202e}",
    "\u{0}",
    "\n",
    "é",
    " ",
];

/// The flags of `softc run` whose values are drawn, each with values it may well take (not
/// `--steps`, kept at 2 so no case runs long, nor outputs, which get paths of their own, nor
/// `--backend gpu`, slow on a software adapter).
const VALUE_FLAGS: &[(&str, &[&str])] = &[
    ("--set", &[]),
    ("--dt", &[]),
    (
        "--threads",
        &["0", "1", "2", "64", "100000", "18446744073709551615"],
    ),
    (
        "--checkpoint",
        &[
            "auto",
            "store_all",
            "periodic:1",
            "periodic:3",
            "revolve:1",
            "revolve:2",
        ],
    ),
    ("--memory-budget", &[]),
    ("--backend", &["cpu", "interp", "reference"]),
    ("--precision", &["f32", "f64"]),
    ("--adapter", &["", "lavapipe", "x"]),
    ("--iterations", &["0", "1", "3"]),
];

/// A value: a number with a unit (`--set` with a name), one the flag may well take, or pieces
/// of anything.
fn flag_value(flag: usize) -> impl Strategy<Value = String> {
    let quantity = (0..NUMBERS.len(), 0..UNITS.len()).prop_map(move |(n, u)| {
        let name = if VALUE_FLAGS[flag].0 == "--set" {
            "p_peak="
        } else {
            ""
        };
        format!("{name}{}{}", NUMBERS[n], UNITS[u])
    });
    let known = VALUE_FLAGS[flag].1;
    let plausible = (0..known.len().max(1))
        .prop_map(move |i| known.get(i).map_or(String::new(), |v| v.to_string()));
    let pieces = proptest::collection::vec(
        prop_oneof![
            (0..NUMBERS.len()).prop_map(|i| NUMBERS[i]),
            (0..UNITS.len()).prop_map(|i| UNITS[i]),
            (0..OTHER.len()).prop_map(|i| OTHER[i]),
        ],
        1..4,
    )
    .prop_map(|v| v.concat());
    if known.is_empty() {
        prop_oneof![3 => quantity, 1 => pieces].boxed()
    } else {
        prop_oneof![3 => plausible, 1 => quantity, 1 => pieces].boxed()
    }
}

/// One to three different flags with values, each maybe with `--grad`.
fn flag_values() -> impl Strategy<Value = Vec<(usize, String, bool)>> {
    proptest::sample::subsequence((0..VALUE_FLAGS.len()).collect::<Vec<_>>(), 1..4).prop_flat_map(
        |flags| {
            flags
                .into_iter()
                .map(|f| (Just(f), flag_value(f), any::<bool>()))
                .collect::<Vec<_>>()
        },
    )
}

#[test]
fn random_flag_values_are_refused_by_name_or_run() {
    let script = softc_tests::root().join("examples/benchmark-1k.soft");
    let mut runner = deterministic_runner(80);
    let result = runner.run(&flag_values(), |flags| {
        let mut args: Vec<std::ffi::OsString> = vec![
            "run".into(),
            script.clone().into(),
            "--steps".into(),
            "2".into(),
        ];
        let mut given = Vec::new();
        for (f, value, grad) in flags {
            args.push(VALUE_FLAGS[f].0.into());
            args.push(value.clone().into());
            if grad && !args.iter().any(|a| a == "--grad") {
                args.push("--grad".into());
            }
            given.push((VALUE_FLAGS[f].0, value));
        }
        let (code, _, err) = softc_limited(&args, Duration::from_secs(60));
        prop_assert!((0..=2).contains(&code), "{args:?}: exit {code}: {err}");
        if code != 0 {
            // The message names a flag or a value it was given (clap's included), or the script.
            let named = given.iter().any(|(f, v)| {
                err.contains(f) || (!v.trim().is_empty() && err.contains(v.trim()))
            }) || err.contains("benchmark-1k.soft")
                || err.contains("--grad")
                // clap's own word for a value it read as flags (`-00` as `-0`): a part of it.
                || err.split("unexpected argument '").nth(1).is_some_and(|rest| {
                    let arg = rest.split('\'').next().unwrap_or_default();
                    !arg.is_empty() && given.iter().any(|(_, v)| v.contains(arg))
                });
            prop_assert!(
                named,
                "{args:?}: exit {code}, the message names no input: {err}"
            );
        }
        Ok(())
    });
    if let Err(e) = result {
        panic!("{e}");
    }
}

// ---- issue 20 (hostile input), items 3, 13, 17, 5, 8, 9, 16, 15, 11 ----

/// A scratch folder for one test.
fn scratch_dir(tag: &str) -> std::path::PathBuf {
    let d = std::env::temp_dir().join(format!("softc-h20-{tag}-{}", std::process::id()));
    std::fs::remove_dir_all(&d).ok();
    std::fs::create_dir_all(&d).unwrap();
    d
}

/// Run the CLI on another thread; a hang fails the test instead of blocking it.
fn softc_within(secs: u64, args: &[&str]) -> (i32, String, String) {
    let args: Vec<String> = args.iter().map(|s| s.to_string()).collect();
    let (tx, rx) = std::sync::mpsc::channel();
    let moved = args.clone();
    std::thread::spawn(move || {
        let a: Vec<&str> = moved.iter().map(String::as_str).collect();
        let _ = tx.send(softc_tests::softc(&a));
    });
    rx.recv_timeout(Duration::from_secs(secs))
        .unwrap_or_else(|_| panic!("softc {args:?} did not finish in {secs} s"))
}

/// A 4×4×4 mm cube of Kuhn cells (no cavity).
fn cube_mesh() -> softc::mesh::Mesh {
    use softc::mesh::kuhn::{KuhnSpec, kuhn_grid};
    let spec = KuhnSpec {
        n: [4, 4, 4],
        min: [0.0; 3],
        max: [4.0; 3],
        cavity_min: [0.0; 3],
        cavity_max: [0.0; 3],
    };
    kuhn_grid(&spec, softc::mesh::LengthUnit::Millimetre).unwrap()
}

/// A script on `mesh` (a file name beside it): the cube clamped at x = 0, no load.
fn cube_script(mesh: &str) -> String {
    format!(
        "mesh body = load(\"{mesh}\")\n\
         material rubber = neo_hookean(mu: 0.1 MPa, kappa: 1 MPa, density: 1070 kg/m^3)\n\
         region clamp = box(min: [-1, -1, -1] mm, max: [0.1, 5, 5] mm)\n\
         nodes top = select(body, z > 3.9 mm)\n\
         sim {{\n  dt = auto\n  steps = 20\n  damping = 20 /s\n  fix clamp\n}}\n\
         loss = sum(n in top) (x[n].z - x0[n].z)^2 at end\n"
    )
}

#[test]
fn issue20_item3_a_tangled_mesh_is_refused_by_check_and_run() {
    let d = scratch_dir("tangled");
    let mut m = cube_mesh();
    let n = m
        .nodes
        .iter()
        .position(|p| p.iter().all(|c| (c - 1e-3).abs() < 1e-12))
        .unwrap();
    m.nodes[n][0] = 2.6e-3; // past its neighbour at x = 2 mm
    softc::mesh::save(&m, &d.join("t.msh"), softc::mesh::LengthUnit::Millimetre).unwrap();
    let script = d.join("t.soft");
    std::fs::write(&script, cube_script("t.msh")).unwrap();
    for cmd in ["check", "run"] {
        let (code, _, err) = softc_within(120, &[cmd, script.to_str().unwrap()]);
        assert_eq!(code, 1, "{cmd}: {err}");
        assert!(
            err.contains("E0319") && err.contains("inverted") && err.contains("element"),
            "{cmd}: {err}"
        );
    }
    std::fs::remove_dir_all(&d).ok();
}

#[cfg(unix)]
#[test]
fn issue20_item13_special_files_are_refused_not_read() {
    let d = scratch_dir("special");
    let fifo = d.join("pipe.msh");
    let made = std::process::Command::new("mkfifo").arg(&fifo).status();
    assert!(made.is_ok_and(|s| s.success()), "mkfifo");
    std::os::unix::fs::symlink("/dev/zero", d.join("zero.msh")).unwrap();
    for name in ["pipe.msh", "zero.msh"] {
        // Through the mesh loader...
        let e =
            softc::mesh::load(&d.join(name), softc::mesh::LengthUnit::Millimetre).expect_err(name);
        let s = e.to_string();
        assert!(s.contains(name) && s.contains("not a regular file"), "{s}");
        // ...and through a script (it said "not found").
        let script = d.join(format!("{name}.soft"));
        std::fs::write(&script, cube_script(name)).unwrap();
        let (code, _, err) = softc_within(60, &["check", script.to_str().unwrap()]);
        assert_eq!(code, 1, "{err}");
        assert!(
            err.contains("E0319") && err.contains("not a regular file"),
            "{err}"
        );
    }
    // A script that is a FIFO: a usage error, at once.
    let sfifo = d.join("script.soft");
    let made = std::process::Command::new("mkfifo").arg(&sfifo).status();
    assert!(made.is_ok_and(|s| s.success()), "mkfifo");
    for cmd in ["check", "run"] {
        let (code, _, err) = softc_within(60, &[cmd, sfifo.to_str().unwrap()]);
        assert_ne!(code, 0, "{cmd}: {err}");
        assert!(
            err.contains("script.soft") && err.contains("FIFO"),
            "{cmd}: {err}"
        );
    }
    std::fs::remove_dir_all(&d).ok();
}

/// A small optimization on the cube: the damping `c` trained against the sag under gravity.
fn cube_optimization(mesh: &str) -> String {
    format!(
        "mesh body = load(\"{mesh}\")\n\
         material rubber = neo_hookean(mu: 0.1 MPa, kappa: 1 MPa, density: 1070 kg/m^3)\n\
         region clamp = box(min: [-1, -1, -1] mm, max: [0.1, 5, 5] mm)\n\
         nodes top = select(body, z > 3.9 mm)\n\
         param c: rate = 20 /s in [1 /s, 100 /s]\n\
         sim {{\n  dt = auto\n  steps = 20\n  damping = c\n  gravity = [0, 0, -9.81] m/s^2\n  fix clamp\n}}\n\
         loss = sum(n in top) (x[n].z - x0[n].z)^2 at end\n\
         optimize c with adam(lr: 0.1) for 2 iterations\n"
    )
}

/// The cube mesh and its optimization script in `d`; the script's path.
fn cube_optimization_files(d: &std::path::Path) -> std::path::PathBuf {
    softc::mesh::save(
        &cube_mesh(),
        &d.join("c.msh"),
        softc::mesh::LengthUnit::Millimetre,
    )
    .unwrap();
    let script = d.join("opt.soft");
    std::fs::write(&script, cube_optimization("c.msh")).unwrap();
    script
}

#[test]
fn issue20_item5_resume_refuses_a_changed_mesh() {
    let d = scratch_dir("resume-mesh");
    let script = cube_optimization_files(&d);
    let (s, out) = (script.to_str().unwrap(), d.join("out"));
    let out = out.to_str().unwrap();
    let (code, _, err) = softc_within(300, &["run", s, "--out", out, "--iterations", "1"]);
    assert_eq!(code, 0, "{err}");
    // A comment in the mesh file is no change...
    let msh = d.join("c.msh");
    let text = std::fs::read_to_string(&msh).unwrap();
    let text = text.replacen(
        "$EndMeshFormat\n",
        "$EndMeshFormat\n$Comments\nedited\n$EndComments\n",
        1,
    );
    std::fs::write(&msh, text).unwrap();
    let (code, _, err) = softc_within(300, &["run", s, "--resume", out, "--iterations", "2"]);
    assert_eq!(code, 0, "{err}");
    // ...a moved node is.
    let mut m = cube_mesh();
    m.nodes[5][2] += 1e-5;
    softc::mesh::save(&m, &msh, softc::mesh::LengthUnit::Millimetre).unwrap();
    let (code, _, err) = softc_within(300, &["run", s, "--resume", out, "--iterations", "3"]);
    assert_ne!(code, 0, "{err}");
    assert!(
        err.contains("different mesh") && err.contains("c.msh"),
        "{err}"
    );
    std::fs::remove_dir_all(&d).ok();
}

#[test]
fn issue20_item8_an_inconsistent_state_json_is_refused_naming_the_field() {
    let d = scratch_dir("state");
    let script = cube_optimization_files(&d);
    let s = script.to_str().unwrap();
    let good = d.join("good");
    let (code, _, err) = softc_within(
        300,
        &[
            "run",
            s,
            "--out",
            good.to_str().unwrap(),
            "--iterations",
            "1",
        ],
    );
    assert_eq!(code, 0, "{err}");
    let text = std::fs::read_to_string(good.join("state.json")).unwrap();
    let json: serde_json::Value = serde_json::from_str(&text).unwrap();
    let edit = |f: &dyn Fn(&mut serde_json::Value)| {
        let mut j = json.clone();
        f(&mut j);
        j.to_string()
    };
    let cases: Vec<(&str, String, &str)> = vec![
        (
            "duplicate",
            text.replacen(
                "\"params\":{\"param.c\":",
                "\"params\":{\"param.c\":1.0,\"param.c\":",
                1,
            ),
            "given twice",
        ),
        (
            "iteration",
            edit(&|j| j["iteration"] = 5.into()),
            "`iteration` is 5",
        ),
        ("dt", edit(&|j| j["dt"] = 1e-3.into()), "`dt`"),
        (
            "moment",
            edit(&|j| j["method"]["v"][0] = (-1.0).into()),
            "method.v[0]",
        ),
    ];
    assert!(cases[0].1 != text, "the duplicate was not written");
    for (name, body, needle) in cases {
        let dir = d.join(name);
        std::fs::create_dir_all(&dir).unwrap();
        std::fs::write(dir.join("state.json"), &body).unwrap();
        let (code, _, err) = softc_within(
            300,
            &[
                "run",
                s,
                "--resume",
                dir.to_str().unwrap(),
                "--iterations",
                "2",
            ],
        );
        assert_ne!(code, 0, "{name}: {err}");
        assert!(err.contains(needle), "{name}: {err}");
        // The state is left as it was.
        assert_eq!(
            std::fs::read_to_string(dir.join("state.json")).unwrap(),
            body
        );
    }
    std::fs::remove_dir_all(&d).ok();
}

#[test]
fn issue20_item9_iterations_0_and_params_files_are_checked() {
    let d = scratch_dir("params");
    let script = cube_optimization_files(&d);
    let s = script.to_str().unwrap();
    // --iterations 0 ran one iteration.
    let (code, _, err) = softc_within(60, &["run", s, "--iterations", "0"]);
    assert_eq!(code, 2, "{err}");
    assert!(err.contains("--iterations") && err.contains('0'), "{err}");
    // Negative damping through --params bypassed the bounds [1/s, 100/s].
    let p = d.join("p.json");
    std::fs::write(&p, r#"{"params": {"c": -5}}"#).unwrap();
    let (code, _, err) = softc_within(
        120,
        &["run", s, "--no-optimize", "--params", p.to_str().unwrap()],
    );
    assert_eq!(code, 2, "{err}");
    assert!(
        err.contains("outside the bounds") && err.contains("`c`"),
        "{err}"
    );
    // A short array was applied in part.
    let arr = d.join("arr.soft");
    std::fs::write(
        &arr,
        cube_optimization("c.msh")
            .replace(
                "param c: rate = 20 /s in [1 /s, 100 /s]",
                "param w: rate[3] = 20 /s in [1 /s, 100 /s]",
            )
            .replace("damping = c", "damping = w[0] + w[1] + w[2]")
            .replace("optimize c", "optimize w"),
    )
    .unwrap();
    std::fs::write(&p, r#"{"params": {"w": [10, 20]}}"#).unwrap();
    let (code, _, err) = softc_within(
        120,
        &[
            "run",
            arr.to_str().unwrap(),
            "--no-optimize",
            "--params",
            p.to_str().unwrap(),
        ],
    );
    assert_eq!(code, 2, "{err}");
    assert!(
        err.contains("`w` has 2 value(s)") && err.contains('3'),
        "{err}"
    );
    std::fs::write(&p, r#"{"params": {"w": [10, 20, 30]}}"#).unwrap();
    let (code, _, err) = softc_within(
        120,
        &[
            "run",
            arr.to_str().unwrap(),
            "--no-optimize",
            "--params",
            p.to_str().unwrap(),
        ],
    );
    assert_eq!(code, 0, "{err}");
    std::fs::remove_dir_all(&d).ok();
}

#[test]
fn issue20_item11_a_run_still_moving_at_end_is_reported() {
    let d = scratch_dir("moving");
    softc::mesh::save(
        &cube_mesh(),
        &d.join("c.msh"),
        softc::mesh::LengthUnit::Millimetre,
    )
    .unwrap();
    // 20 steps under gravity: the cube has only started to sag.
    let script = d.join("s.soft");
    std::fs::write(
        &script,
        cube_script("c.msh").replace(
            "  fix clamp\n",
            "  gravity = [0, 0, -9.81] m/s^2\n  fix clamp\n",
        ),
    )
    .unwrap();
    let (code, out, err) = softc_within(120, &["run", script.to_str().unwrap()]);
    assert_eq!(code, 0, "{err}");
    let json: serde_json::Value = serde_json::from_str(&out).unwrap();
    let ke = json["kinetic_energy"].as_f64().unwrap();
    let vmax = json["max_speed"].as_f64().unwrap();
    assert!(ke > 0.0 && vmax > 0.0, "{json}");
    assert!(err.contains("still") && err.contains("at end"), "{err}");
    // At rest (no load) there is nothing to report.
    std::fs::write(&script, cube_script("c.msh")).unwrap();
    let (code, out, err) = softc_within(120, &["run", script.to_str().unwrap()]);
    assert_eq!(code, 0, "{err}");
    let json: serde_json::Value = serde_json::from_str(&out).unwrap();
    assert!(json["max_speed"].as_f64().unwrap() < 1e-9, "{json}");
    assert!(!err.contains("still"), "{err}");
    std::fs::remove_dir_all(&d).ok();
}

#[test]
fn issue20_item16_a_division_by_zero_in_a_prelude_call_is_e0208_at_the_call() {
    let d = scratch_dir("lame");
    softc::mesh::save(
        &cube_mesh(),
        &d.join("c.msh"),
        softc::mesh::LengthUnit::Millimetre,
    )
    .unwrap();
    let script = d.join("s.soft");
    let text = cube_script("c.msh").replace(
        "material rubber = neo_hookean(mu: 0.1 MPa, kappa: 1 MPa, density: 1070 kg/m^3)",
        "let nu = 0.5\nmaterial rubber = neo_hookean_ln(mu: lame_mu(0.3 MPa, nu), \
         lambda: lame_lambda(0.3 MPa, nu), density: 1070 kg/m^3)",
    );
    std::fs::write(&script, &text).unwrap();
    for cmd in ["check", "run"] {
        let (code, _, err) = softc_within(60, &[cmd, script.to_str().unwrap()]);
        assert_eq!(code, 1, "{cmd}: {err}");
        assert!(
            err.contains("E0208") && err.contains("lame_lambda") && err.contains("s.soft:3:"),
            "{cmd}: {err}"
        );
    }
    // ν = 0.45 folds to a value and checks clean.
    std::fs::write(&script, text.replace("let nu = 0.5", "let nu = 0.45")).unwrap();
    let (code, _, err) = softc_within(60, &["check", script.to_str().unwrap()]);
    assert_eq!(code, 0, "{err}");
    std::fs::remove_dir_all(&d).ok();
}

/// The cube script with the sim block's `dt = auto` and `steps = 20` replaced, and a material
/// and extra sim lines of the test's choosing.
fn blowup_script(material: &str, dt: &str, steps: u64, extra: &str) -> String {
    cube_script("c.msh")
        .replace(
            "material rubber = neo_hookean(mu: 0.1 MPa, kappa: 1 MPa, density: 1070 kg/m^3)",
            &format!("material rubber = {material}"),
        )
        .replace(
            "  dt = auto\n  steps = 20\n",
            &format!("  dt = {dt}\n  steps = {steps}\n{extra}"),
        )
}

/// Run `text` as a script beside the cube mesh in `d`: (exit status, stderr).
fn run_text(d: &std::path::Path, text: &str, extra_args: &[&str]) -> (i32, String) {
    let script = d.join("b.soft");
    std::fs::write(&script, text).unwrap();
    let mut args = vec!["run", script.to_str().unwrap()];
    args.extend(extra_args);
    let (code, _, err) = softc_within(300, &args);
    (code, err)
}

/// The first number after `at step ` in a message.
fn step_in(msg: &str) -> u64 {
    let rest = &msg[msg
        .find("at step ")
        .unwrap_or_else(|| panic!("no step: {msg}"))
        + 8..];
    rest.split(|c: char| !c.is_ascii_digit())
        .next()
        .unwrap()
        .parse()
        .unwrap()
}

#[test]
fn issue20_item15_a_blow_up_names_its_step_and_cause() {
    let d = scratch_dir("blowup");
    softc::mesh::save(
        &cube_mesh(),
        &d.join("c.msh"),
        softc::mesh::LengthUnit::Millimetre,
    )
    .unwrap();
    let rubber = "neo_hookean(mu: 0.1 MPa, kappa: 1 MPa, density: 1070 kg/m^3)";
    let gravity = "  gravity = [0, 0, -9.81] m/s^2\n";
    // (a) dt 3x the stable step (~20 us): unstable, blamed on dt with a smaller one, at the
    // step where it happened (not a 50-step check boundary), and the run up to the step before
    // that is finite.
    let (code, err) = run_text(&d, &blowup_script(rubber, "60 us", 400, gravity), &[]);
    assert_eq!(code, 1, "{err}");
    println!("(a) {err}");
    assert!(err.contains("unstable") && err.contains("dt <="), "{err}");
    let s = step_in(&err);
    assert!(s % 50 != 1 && s > 0, "a check boundary: {err}");
    let ok = (s - 1).to_string();
    let (code, e2) = run_text(
        &d,
        &blowup_script(rubber, "60 us", 400, gravity),
        &["--steps", &ok],
    );
    assert_eq!(code, 0, "--steps {ok}: {e2}\n(first run: {err})");
    let (code, _) = run_text(
        &d,
        &blowup_script(rubber, "60 us", 400, gravity),
        &["--steps", &(s + 1).to_string()],
    );
    assert_eq!(code, 1);
    // (b) A negative modulus: the material, not dt.
    let (code, err) = run_text(
        &d,
        &blowup_script(
            "neo_hookean(mu: -0.1 MPa, kappa: 1 MPa, density: 1070 kg/m^3)",
            "10 us",
            2000,
            gravity,
        ),
        &[],
    );
    assert_eq!(code, 1, "{err}");
    println!("(b) {err}");
    assert!(err.contains("material constants are not physical"), "{err}");
    assert!(!err.contains("dt <="), "{err}");
    // (c) Damping of 1e9 /s: the damping, not the elastic step.
    let (code, err) = run_text(
        &d,
        &blowup_script(
            rubber,
            "10 us",
            400,
            &format!("{gravity}  damping = 1e9 /s\n"),
        )
        .replace("  damping = 20 /s\n", ""),
        &[],
    );
    assert_eq!(code, 1, "{err}");
    println!("(c) {err}");
    assert!(err.contains("damping is too strong"), "{err}");
    assert!(!err.contains("dt <="), "{err}");
    // (d) A load far beyond what the material carries (gravity of 3e5 m/s²): the load, at
    // the element and step where it inverts, not dt.
    let (code, err) = run_text(
        &d,
        &blowup_script(rubber, "10 us", 400, "  gravity = [0, 0, -3e5] m/s^2\n"),
        &[],
    );
    println!("(d) {err}");
    assert_eq!(code, 1, "{err}");
    assert!(
        err.contains("inverted at step") && err.contains("not the cause") && err.contains("load"),
        "{err}"
    );
    assert!(!err.contains("dt <="), "{err}");
    std::fs::remove_dir_all(&d).ok();
}

/// The reference oracle computes in f64 only: asking it for f32 is a usage error, not a
/// silently ignored flag.
#[test]
fn the_reference_backend_refuses_f32() {
    let script = softc_tests::root().join("examples/benchmark-1k.soft");
    let (code, _, err) = softc_tests::softc(&[
        "run",
        script.to_str().unwrap(),
        "--backend",
        "reference",
        "--precision",
        "f32",
        "--steps",
        "2",
    ]);
    assert_eq!(code, 2, "{err}");
    assert!(
        err.contains("--precision") && err.contains("f64 only"),
        "{err}"
    );
}

#[test]
fn issue31_item11_a_warm_start_list_for_another_batch_is_refused() {
    let d = scratch_dir("warm");
    let script = softc_tests::root().join("examples/pressure_optimization.soft");
    let s = script.to_str().unwrap();
    let out = d.join("out");
    let out = out.to_str().unwrap();
    let (code, _, err) = softc_within(300, &["run", s, "--out", out, "--iterations", "1"]);
    assert_eq!(code, 0, "{err}");
    let state = d.join("out/state.json");
    let text = std::fs::read_to_string(&state).unwrap();
    let mut json: serde_json::Value = serde_json::from_str(&text).unwrap();
    // One scene: one starting state. Two are a state from another batch.
    let warm = json["warm_starts"].as_array().unwrap().clone();
    assert_eq!(
        warm.len(),
        1,
        "a static study saves its next starting state"
    );
    json["warm_starts"] = serde_json::Value::Array(vec![warm[0].clone(), warm[0].clone()]);
    let body = json.to_string();
    std::fs::write(&state, &body).unwrap();
    let (code, _, err) = softc_within(300, &["run", s, "--resume", out, "--iterations", "2"]);
    assert_ne!(code, 0, "{err}");
    assert!(
        err.contains("`warm_starts` holds 2 starting states") && err.contains("1 scene(s)"),
        "{err}"
    );
    assert_eq!(std::fs::read_to_string(&state).unwrap(), body);
    std::fs::remove_dir_all(&d).ok();
}
