//! The optimization loop end to end: a short study converges, bounds hold, batches average
//! their scenes, circle_quadrants draws one target per quadrant, and a run killed with SIGKILL
//! resumes to exactly the result of an uninterrupted one.

use softc::devices::cpu::Cpu;
use softc::engine::Simulation;
use softc::engine::adjoint::GradOptions;
use softc::engine::scene::Scene;
use softc::optim::Plan;
use softc::optim::train::Trainer;
use softc_compiler::back::Precision;
use std::path::{Path, PathBuf};
use std::process::Command;

fn root() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .parent()
        .unwrap()
        .to_path_buf()
}

fn fixture(name: &str) -> PathBuf {
    root().join("runtime/tests/fixtures/optim").join(name)
}

/// A fresh scratch folder for this test.
fn scratch(name: &str) -> PathBuf {
    let d = std::env::temp_dir().join(format!("softc-optim-{}-{name}", std::process::id()));
    let _ = std::fs::remove_dir_all(&d);
    std::fs::create_dir_all(&d).unwrap();
    d
}

/// A copy of a fixture with text replaced (the mesh path made absolute).
fn variant(name: &str, edits: &[(&str, &str)], dir: &Path) -> PathBuf {
    let mut text = std::fs::read_to_string(fixture(name)).unwrap();
    for (from, to) in edits {
        assert!(text.contains(from), "{name}: `{from}`");
        text = text.replace(from, to);
    }
    let text = text.replace(
        "\"../../../../meshes/",
        &format!("\"{}/meshes/", root().display()),
    );
    let path = dir.join(name);
    std::fs::write(&path, text).unwrap();
    path
}

fn softc(args: &[&str]) -> (i32, String, String) {
    let out = Command::new(env!("CARGO_BIN_EXE_softc"))
        .args(args)
        .output()
        .unwrap();
    (
        out.status.code().unwrap_or(-1),
        String::from_utf8_lossy(&out.stdout).into_owned(),
        String::from_utf8_lossy(&out.stderr).into_owned(),
    )
}

fn read_json(path: &Path) -> serde_json::Value {
    serde_json::from_str(&std::fs::read_to_string(path).unwrap()).unwrap()
}

fn losses(json: &serde_json::Value) -> Vec<f64> {
    json["history"]
        .as_array()
        .unwrap()
        .iter()
        .map(|r| r["loss"].as_f64().unwrap())
        .collect()
}

#[test]
fn a_short_pressure_optimization_reaches_its_target() {
    let dir = scratch("converge");
    let json = dir.join("run.json");
    let out = dir.join("out");
    let (code, _, err) = softc(&[
        "run",
        fixture("pressure.soft").to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
        "--json",
        json.to_str().unwrap(),
    ]);
    assert_eq!(code, 0, "{err}");
    let j = read_json(&json);
    let l = losses(&j);
    // Measured: 5.36e-10 → 7.96e-12 m² at iteration 14, where `stop when` (8e-6 mm²) holds.
    assert!(l[0] / l[l.len() - 1] > 50.0, "losses {l:?}");
    assert_eq!(j["stopped"]["reason"], "stop when", "{err}");
    assert!(*l.last().unwrap() < 8e-12);
    assert!(l.len() < 30, "took {} iterations", l.len());
    // The history has what a plot needs, and the progress was logged per iteration.
    let h0 = &j["history"][0];
    assert_eq!(h0["iteration"], 0);
    assert_eq!(h0["params"]["p_peak"], 1000.0);
    assert!(h0["gradients"]["p_peak"].as_f64().unwrap() < 0.0);
    assert!(err.contains("iteration 1/30: loss 5.357"), "{err}");
    let p = j["params"]["p_peak"].as_f64().unwrap();
    assert!((3500.0..4800.0).contains(&p), "p_peak = {p}");
    // Everything went into --out.
    for f in [
        "state.json",
        "result.json",
        "vtk/optimized.pvd",
        "optimization.png",
        "optimization.svg",
    ] {
        assert!(out.join(f).is_file(), "{f} missing in --out");
    }
    assert_eq!(read_json(&out.join("result.json")), j);
    // The script's `output csv(tip)` log of the optimized run: a row every 50 steps, ending at
    // the optimized tip displacement the summary reports.
    let csv = std::fs::read_to_string(out.join("csv/tip.csv")).expect("csv/tip.csv in --out");
    let rows: Vec<&str> = csv.lines().collect();
    assert_eq!(rows.len(), 1 + 750 / 50 + 1, "{csv}");
    let last_mean_z: f64 = rows
        .last()
        .unwrap()
        .split(',')
        .nth(4)
        .unwrap()
        .parse()
        .unwrap();
    let reported = j["sets"]["tip"]["mean_displacement"][2].as_f64().unwrap();
    assert_eq!(last_mean_z, reported);
    // The trained design runs again from result.json (`--params`), to the same loss bit for bit.
    let again = dir.join("again.json");
    let (code, _, err) = softc(&[
        "run",
        fixture("pressure.soft").to_str().unwrap(),
        "--no-optimize",
        "--params",
        out.join("result.json").to_str().unwrap(),
        "--json",
        again.to_str().unwrap(),
    ]);
    assert_eq!(code, 0, "{err}");
    assert_eq!(read_json(&again)["loss"], j["loss"]);
    // A params file that does not fit the script is refused with the entry it names.
    for (text, expected) in [
        (
            r#"{"params": {"p_peak": [1000, 2000]}}"#,
            "no param or input `p_peak.0`",
        ),
        (
            r#"{"params": {"p_peak": "3 kPa"}}"#,
            "`p_peak`: expected a number",
        ),
        ("not json", "not JSON"),
    ] {
        let bad = dir.join("bad-params.json");
        std::fs::write(&bad, text).unwrap();
        let (code, _, err) = softc(&[
            "run",
            fixture("pressure.soft").to_str().unwrap(),
            "--no-optimize",
            "--params",
            bad.to_str().unwrap(),
        ]);
        assert_eq!(code, 2, "{text}: {err}");
        assert!(err.contains(expected), "{text}: {err}");
    }
    // A second --out into the same folder refuses to overwrite the run.
    let (code, _, err) = softc(&[
        "run",
        fixture("pressure.soft").to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
    ]);
    assert_eq!(code, 2);
    assert!(err.contains("--resume"), "{err}");
}

#[test]
fn bounded_params_never_leave_their_bounds() {
    // The optimum (~4 kPa) lies beyond the upper bound: the iterates crowd against it from below.
    let dir = scratch("bounds");
    let script = variant(
        "pressure.soft",
        &[
            ("in [0 kPa, 50 kPa]", "in [0 kPa, 2 kPa]"),
            ("nadam(lr: 0.2) for 30", "gd(lr: 5.0) for 12"),
        ],
        &dir,
    );
    let json = dir.join("run.json");
    let (code, _, err) = softc(&[
        "run",
        script.to_str().unwrap(),
        "--json",
        json.to_str().unwrap(),
    ]);
    assert_eq!(code, 0, "{err}");
    let j = read_json(&json);
    let ps: Vec<f64> = j["history"]
        .as_array()
        .unwrap()
        .iter()
        .map(|r| r["params"]["p_peak"].as_f64().unwrap())
        .collect();
    for p in ps.iter().chain([&j["params"]["p_peak"].as_f64().unwrap()]) {
        assert!(
            *p > 0.0 && *p < 2000.0,
            "p_peak = {p} left [0, 2 kPa]: {ps:?}"
        );
    }
    assert!(*ps.last().unwrap() > 1900.0, "{ps:?}");
}

#[test]
fn a_killed_run_resumes_to_the_uninterrupted_result() {
    let dir = scratch("resume");
    // No stop condition: both runs take all 10 iterations.
    let script = variant(
        "pressure.soft",
        &[
            ("  stop when loss < 8e-6 mm^2\n", ""),
            ("for 30 iterations", "for 10 iterations"),
        ],
        &dir,
    );
    let script = script.to_str().unwrap();
    let whole = dir.join("whole");
    let (code, _, err) = softc(&["run", script, "--out", whole.to_str().unwrap()]);
    assert_eq!(code, 0, "{err}");

    // Kill -9 the second run once it has saved a few iterations.
    let part = dir.join("part");
    let mut child = Command::new(env!("CARGO_BIN_EXE_softc"))
        .args(["run", script, "--out", part.to_str().unwrap()])
        .stdout(std::process::Stdio::null())
        .stderr(std::process::Stdio::null())
        .spawn()
        .unwrap();
    let state = part.join("state.json");
    let deadline = std::time::Instant::now() + std::time::Duration::from_secs(120);
    loop {
        // The state file is replaced atomically: whenever it exists it parses.
        if state.exists() {
            let s = read_json(&state);
            if s["iteration"].as_u64().unwrap() >= 3 {
                break;
            }
        }
        assert!(std::time::Instant::now() < deadline, "no progress");
        std::thread::sleep(std::time::Duration::from_millis(20));
    }
    child.kill().unwrap(); // SIGKILL
    child.wait().unwrap();
    let saved = read_json(&state)["iteration"].as_u64().unwrap();
    assert!(saved < 10, "the run finished before it could be killed");

    // `--iterations` at the saved count ends the run there: no further iteration, only the
    // final run and its outputs.
    let at = saved.to_string();
    let (code, _, err) = softc(&[
        "run",
        script,
        "--resume",
        part.to_str().unwrap(),
        "--iterations",
        &at,
    ]);
    assert_eq!(code, 0, "{err}");
    assert_eq!(
        read_json(&state)["iteration"].as_u64(),
        Some(saved),
        "{err}"
    );
    assert!(part.join("result.json").exists());
    let (code, _, err) = softc(&["run", script, "--resume", part.to_str().unwrap()]);
    assert_eq!(code, 0, "{err}");
    assert!(
        err.contains(&format!("resuming after iteration {saved}")),
        "{err}"
    );
    let (a, b) = (
        read_json(&whole.join("result.json")),
        read_json(&part.join("result.json")),
    );
    // Bit for bit: the same params, losses and gradients at every iteration.
    assert_eq!(a["params"], b["params"]);
    assert_eq!(a["loss"], b["loss"]);
    let strip = |j: &serde_json::Value| {
        j["history"]
            .as_array()
            .unwrap()
            .iter()
            .map(|r| {
                (
                    r["loss"].clone(),
                    r["params"].clone(),
                    r["gradients"].clone(),
                )
            })
            .collect::<Vec<_>>()
    };
    assert_eq!(strip(&a), strip(&b));

    // A changed script cannot resume the old state.
    let changed = variant(
        "pressure.soft",
        &[("+ 0.03 mm)^2", "+ 0.04 mm)^2")],
        &dir.join("part"),
    );
    let (code, _, err) = softc(&[
        "run",
        changed.to_str().unwrap(),
        "--resume",
        part.to_str().unwrap(),
    ]);
    assert_eq!(code, 1);
    assert!(err.contains("different script"), "{err}");
}

/// A trainer on the CPU backend with one simulation per scene of the batch.
fn trainer(scene: &Scene) -> Trainer<'_, Cpu> {
    let plan = Plan::from_scene(scene).unwrap().unwrap();
    let n = plan.scenes_per_iteration();
    let sims = (0..n)
        .map(|_| {
            let cpu = Cpu::new(&scene.lowered.adjoint.module, Precision::F64, Some(1)).unwrap();
            Simulation::new(scene, cpu)
        })
        .collect();
    Trainer::new(
        plan,
        sims,
        GradOptions::default(),
        None,
        None,
        String::new(),
        None,
    )
    .unwrap()
}

#[test]
fn a_batch_averages_loss_and_gradient_over_its_scenes() {
    let scene = Scene::load(&fixture("batch.soft"), &[]).unwrap();
    let mut t = trainer(&scene);
    assert_eq!(t.plan.batch, 3);
    let r = t.step().unwrap().clone();
    assert_eq!(r.scenes.len(), 3);
    // Each scene alone, through the plain gradient path.
    let mut mean_loss = 0.0;
    let mut mean_grad = 0.0;
    for s in &r.scenes {
        let cpu = Cpu::new(&scene.lowered.adjoint.module, Precision::F64, Some(1)).unwrap();
        let mut sim = Simulation::new(&scene, cpu);
        for (k, v) in &s.inputs {
            sim.uniforms.set_named(k, *v);
        }
        let g = sim.gradient(None, None, &GradOptions::default()).unwrap();
        assert_eq!(g.summary.loss.unwrap(), s.loss);
        mean_loss += s.loss / 3.0;
        mean_grad += g.gradients["param.p_peak"] / 3.0;
    }
    let goals: Vec<f64> = r.scenes.iter().map(|s| s.inputs["input.goal"]).collect();
    assert_eq!(goals, vec![-0.01e-3, -0.03e-3, -0.05e-3]);
    assert_eq!(r.loss, mean_loss);
    assert_eq!(r.gradient["param.p_peak"], mean_grad);
    // Mini-batches: with batch = 2 of 3 scenes, SGD draws a different pair each iteration.
    let dir = scratch("minibatch");
    let script = variant("batch.soft", &[("batch = 3", "batch = 2")], &dir);
    let scene = Scene::load(&script, &[]).unwrap();
    let mut t = trainer(&scene);
    let mut pairs = std::collections::BTreeSet::new();
    for _ in 0..4 {
        let r = t.step().unwrap();
        assert_eq!(r.scenes.len(), 2);
        let mut g: Vec<i64> = r
            .scenes
            .iter()
            .map(|s| (s.inputs["input.goal"] * 1e8).round() as i64)
            .collect();
        g.sort();
        pairs.insert(g);
    }
    assert!(pairs.len() >= 2, "{pairs:?}");
}

#[test]
fn circle_quadrants_trains_on_one_target_per_quadrant() {
    let scene = Scene::load(&fixture("quadrants.soft"), &[]).unwrap();
    let mut t = trainer(&scene);
    let first = t.step().unwrap().clone();
    let second = t.step().unwrap().clone();
    for r in [&first, &second] {
        assert_eq!(r.scenes.len(), 4);
        for (q, s) in r.scenes.iter().enumerate() {
            let (y, z) = (s.inputs["input.target.1"], s.inputs["input.target.2"]);
            assert_eq!(s.inputs["input.target.0"], 0.0);
            assert!(y.hypot(z) <= 0.05e-3 + 1e-15);
            let expected = [(1.0, 1.0), (-1.0, 1.0), (-1.0, -1.0), (1.0, -1.0)][q];
            assert!(
                y * expected.0 >= 0.0 && z * expected.1 >= 0.0,
                "scene {q}: {y}, {z}"
            );
        }
    }
    // Fresh targets every iteration.
    assert_ne!(first.scenes[0].inputs, second.scenes[0].inputs);
    // The weights got a nonzero gradient (a controller fed by the target).
    assert!(
        first.gradient.values().any(|g| *g != 0.0),
        "{:?}",
        first.gradient
    );
    // Held-out targets are evaluated with the trained weights.
    let v = t.validate().unwrap();
    assert_eq!(v.len(), 2);
    assert!(v.iter().all(|s| s.loss.is_finite() && s.loss > 0.0));
}

/// `softc run` on a variant of an example with fewer steps and iterations.
fn short_study(example: &str, edits: &[(&str, &str)], steps: &str, iterations: &str) -> Vec<f64> {
    let dir = scratch(example);
    let mut text = std::fs::read_to_string(root().join("examples").join(example)).unwrap();
    for (from, to) in edits {
        assert!(text.contains(from), "{example}: `{from}`");
        text = text.replace(from, to);
    }
    let path = dir.join(example);
    std::fs::write(
        &path,
        text.replace("\"../meshes/", &format!("\"{}/meshes/", root().display())),
    )
    .unwrap();
    let json = dir.join("run.json");
    let (code, _, err) = softc(&[
        "run",
        path.to_str().unwrap(),
        "--steps",
        steps,
        "--iterations",
        iterations,
        "--json",
        json.to_str().unwrap(),
    ]);
    assert_eq!(code, 0, "{example}: {err}");
    losses(&read_json(&json))
}

#[test]
fn short_versions_of_the_studies_lower_their_loss() {
    // The full studies take many minutes per iteration on a laptop (README). Here each runs a
    // few iterations over its first steps, with the pressure ramped within them so the loss
    // responds to the params. The 10 mm target is far out of reach in 41 ms, so the cuboid
    // studies' losses move little, but every iteration must lower them. The controller's
    // 40 µm targets are within reach of its 2 ms ramp in 120 steps. Ratios first/best
    // measured on the CPU backend: pressure 1.00025, meta 1.000033, controller 2.85.
    let fast_ramp = [("ramp(t, 0.5 s)", "ramp(t, 5 ms)")];
    let controller_ramp = [("ramp(t, 0.1 s)", "ramp(t, 2 ms)")];
    for (example, edits, steps, iterations, factor, monotone) in [
        (
            "pressure_optimization_explicit.soft",
            &fast_ramp[..],
            "300",
            "4",
            1.0002,
            true,
        ),
        (
            "meta_optimization.soft",
            &fast_ramp[..],
            "300",
            "4",
            1.00003,
            true,
        ),
        (
            "controller_synthesis_explicit.soft",
            &controller_ramp[..],
            "120",
            "3",
            2.5,
            false,
        ),
    ] {
        let l = short_study(example, edits, steps, iterations);
        let best = l.iter().copied().fold(f64::INFINITY, f64::min);
        assert!(l[0] / best > factor, "{example}: {l:?}");
        if monotone {
            assert!(l.windows(2).all(|w| w[1] < w[0]), "{example}: {l:?}");
        }
    }
}

#[test]
fn a_per_element_field_is_trained_like_any_param() {
    // 516 shear moduli, one per element of the clamp-side half: d loss/d mu[e] from the
    // per-element adjoint accumulators, each entry bounded on its own. Measured losses
    // 7.30e-8, 7.11e-8, 6.93e-8, 6.77e-8 m².
    let scene = Scene::load(&fixture("stiffness.soft"), &[]).unwrap();
    let mut t = trainer(&scene);
    assert_eq!(t.plan.entries.len(), 516);
    let mut losses = Vec::new();
    while !t.finished() {
        let r = t.step().unwrap();
        losses.push(r.loss);
        assert!(r.gradient.values().filter(|g| **g != 0.0).count() > 400);
    }
    assert!(losses.windows(2).all(|w| w[1] < w[0]), "{losses:?}");
    assert!(losses[0] / losses[3] > 1.05, "{losses:?}");
    let result = t.result();
    assert!(result.values().all(|mu| (1e3..1e6).contains(mu)));
    // The entries moved apart: the design is graded, not uniform.
    let (lo, hi) = result
        .values()
        .fold((f64::INFINITY, 0.0f64), |(a, b), v| (a.min(*v), b.max(*v)));
    assert!(hi / lo > 1.01, "{lo} .. {hi}");
}

/// A loss that is not a number is an error naming when it was taken, never a result: no
/// `"loss": null` with exit 0, and no gradient of it.
#[test]
fn a_non_finite_loss_stops_the_run_with_an_error() {
    let dir = scratch("nan-loss");
    // The tip moves down (negative z displacement): the square root of it is NaN.
    let script = variant(
        "pressure.soft",
        &[(
            "loss = mean(n in tip) (x[n].z - x0[n].z + 0.03 mm)^2 at end",
            "loss = mean(n in tip) sqrt((x[n].z - x0[n].z) / 1 mm) * 1 mm^2 at end",
        )],
        &dir,
    );
    let s = script.to_str().unwrap();
    for extra in [&[][..], &["--grad"][..]] {
        let mut args = vec!["run", s, "--no-optimize", "--steps", "50"];
        args.extend_from_slice(extra);
        let (code, out, err) = softc(&args);
        assert_eq!(
            code, 1,
            "{extra:?}: exit {code}\nstdout: {out}\nstderr: {err}"
        );
        assert!(
            err.contains("the loss is NaN at the end of the run (step 50"),
            "{extra:?}: {err}"
        );
        assert!(!out.contains("\"gradients\""), "{extra:?}: {out}");
    }
}

/// A solve that fails inside an optimization names the failing iteration as the progress log
/// numbers it, with the params it ran with, and the saved state keeps the iterations before it
/// (issue 31 item 4: the error named the previous iteration, without its params).
#[test]
fn a_failing_iteration_is_named_with_its_params_and_the_good_ones_are_kept() {
    let dir = scratch("failing-iteration");
    // A learning rate so large that the second iteration's pressure inverts an element.
    let script = variant(
        "pressure.soft",
        &[
            ("in [0 kPa, 50 kPa]", "in [0 kPa, 100 MPa]"),
            ("nadam(lr: 0.2)", "nadam(lr: 3)"),
        ],
        &dir,
    );
    let out = dir.join("out");
    let (code, _, err) = softc(&[
        "run",
        script.to_str().unwrap(),
        "--steps",
        "200",
        "--iterations",
        "3",
        "--out",
        out.to_str().unwrap(),
    ]);
    assert_eq!(code, 1, "{err}");
    assert!(err.contains("iteration 1/3: loss "), "{err}");
    let state = read_json(&out.join("state.json"));
    assert_eq!(state["iteration"], 1, "{err}");
    // The params the failing iteration ran with: the update after iteration 1.
    let u = state["u"][0].as_f64().unwrap();
    let failed = err
        .lines()
        .find(|l| l.contains("iteration 2/3 failed with p_peak = "))
        .unwrap_or_else(|| panic!("{err}"));
    let p: f64 = failed
        .split("p_peak = ")
        .nth(1)
        .and_then(|r| r.split(':').next())
        .and_then(|v| v.parse().ok())
        .unwrap_or_else(|| panic!("{failed}"));
    assert!(p > 50e3, "p_peak = {p} (u = {u})");
    assert!(failed.contains("inverted at step"), "{failed}");
    // Shown to seven digits, not as 3.9999999999999996e-5.
    assert!(failed.contains("dt = 4e-5 s"), "{failed}");
    assert!(
        err.contains("state.json` keeps the 1 iteration(s) that succeeded"),
        "{err}"
    );
}
