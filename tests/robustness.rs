//! No input may panic the front end, hang it, or take long to diagnose: random bytes, random
//! token soups, and the classic pathological inputs (deep nesting, huge numbers, long chains,
//! invalid UTF-8, binary garbage).

use proptest::prelude::*;
use softc_compiler::sema::CheckOptions;
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

// ---- issue 20 (hostile input), items 3, 13, 17, 5, 8, 9, 16, 15, 11 ----

/// A scratch folder for one test.
fn scratch(tag: &str) -> std::path::PathBuf {
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
    let d = scratch("tangled");
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
    let d = scratch("special");
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
    let d = scratch("resume-mesh");
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
    let d = scratch("state");
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
    let d = scratch("params");
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
    let d = scratch("moving");
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
    let d = scratch("lame");
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
    let d = scratch("blowup");
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
