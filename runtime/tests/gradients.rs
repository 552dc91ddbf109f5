//! Gradients from the adjoint kernels: every kind of parameter against central finite
//! differences in f64, every example, checkpoint schedules bit-identical to storing every
//! state, the interpreter bit-identical to the Cranelift code, and clear errors.

use softc::devices::Backend;
use softc::devices::cpu::Cpu;
use softc::devices::interp::Interpreter;
use softc::engine::Simulation;
use softc::engine::adjoint::{Checkpointing, GradOptions, GradientReport};
use softc::engine::scene::Scene;
use softc_compiler::back::Precision;
use std::path::{Path, PathBuf};

fn root() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .parent()
        .unwrap()
        .to_path_buf()
}

fn load(path: &str) -> Scene {
    let full = if Path::new(path).is_absolute() {
        PathBuf::from(path)
    } else {
        root().join(path)
    };
    Scene::load(&full, &[]).unwrap_or_else(|e| panic!("{path}: {e}"))
}

/// A copy of an example with one piece of text replaced, its mesh paths made absolute.
fn variant(example: &str, from: &str, to: &str) -> String {
    let text = std::fs::read_to_string(root().join("examples").join(example)).unwrap();
    assert!(text.contains(from), "{example}: {from}");
    // Without the studies' mass scaling: these short rollouts were tuned (steps, windows,
    // finite-difference steps) for the physical masses and dt = auto of those.
    let text = text
        .replace(from, to)
        .replace("  mass_scaling = 100\n", "")
        .replace("\"../meshes/", &format!("\"{}/meshes/", root().display()));
    let dir = std::env::temp_dir().join(format!("softc-grad-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let path = dir.join(example);
    std::fs::write(&path, text).unwrap();
    path.display().to_string()
}

fn gradient(scene: &Scene, steps: u64, options: &GradOptions) -> GradientReport {
    let cpu = Cpu::new(&scene.lowered.adjoint.module, Precision::F64, Some(1)).unwrap();
    let mut sim = Simulation::new(scene, cpu);
    sim.gradient(None, Some(steps), options).unwrap()
}

/// The loss of a forward run with one uniform changed.
fn loss_with(scene: &Scene, steps: u64, uniform: &str, value: f64) -> f64 {
    let cpu = Cpu::new(&scene.lowered.module, Precision::F64, Some(1)).unwrap();
    let mut sim = Simulation::new(scene, cpu);
    sim.uniforms.set_named(uniform, value);
    sim.run(None, Some(steps)).unwrap().loss.unwrap()
}

/// Central difference of the loss with respect to one uniform, step `h`.
fn central(scene: &Scene, steps: u64, uniform: &str, h: f64) -> f64 {
    let p = scene.uniforms[uniform];
    (loss_with(scene, steps, uniform, p + h) - loss_with(scene, steps, uniform, p - h)) / (2.0 * h)
}

/// Every param's adjoint derivative against a central difference with a relative step `rel`
/// (an absolute step `rel` for params that are 0; of arrays, the components `keep` accepts).
fn check_params(path: &str, steps: u64, rel: f64, tol: f64, keep: impl Fn(&str) -> bool) {
    let scene = load(path);
    let g = gradient(&scene, steps, &GradOptions::default());
    assert!(!g.gradients.is_empty(), "{path}: no params");
    let mut report = Vec::new();
    for (name, &adj) in g.gradients.iter().filter(|(n, _)| keep(n)) {
        let p = scene.uniforms[name];
        // Zero-initialised params (controller weights) take an absolute step.
        let h = if p == 0.0 { rel } else { rel * p.abs() };
        let fd = central(&scene, steps, name, h);
        let err = (adj - fd).abs() / fd.abs().max(1e-300);
        report.push(format!(
            "{name}: adjoint {adj:e}, central {fd:e}, rel err {err:.1e}"
        ));
        assert!(adj != 0.0, "{path}: {name} has a zero gradient");
        assert!(err < tol, "{path}:\n{}", report.join("\n"));
    }
    eprintln!("{path}:\n{}", report.join("\n"));
}

fn check_all_params(path: &str, steps: u64, rel: f64, tol: f64) {
    check_params(path, steps, rel, tol, |_| true)
}

#[test]
fn every_parameter_kind_matches_central_differences() {
    // A chamber pressure, a material constant (Yeoh c10), per-window damping (4 windows),
    // controller weights fed by an input, and a windowed loss on positions and velocities.
    check_all_params(
        "runtime/tests/fixtures/grad/all_kinds.soft",
        200,
        1e-4,
        1e-5,
    );
}

#[test]
fn benchmark_gradient_over_4000_steps_matches_central_differences() {
    // The canonical scene's full horizon (BENCHMARK.md): 4000 steps of 40 µs, d loss/d p_peak.
    let scene = load("examples/benchmark-1k.soft");
    // A budget of 40 states: `auto` checkpoints (without one it stores all 4000 states).
    let options = GradOptions {
        memory_budget: Some(40 * 48 * scene.mesh.nodes.len() as u64),
        ..GradOptions::default()
    };
    let g = gradient(&scene, 4000, &options);
    let adj = g.gradients["param.p_peak"];
    let fd = central(&scene, 4000, "param.p_peak", 1.0);
    assert!(
        adj.is_finite() && adj < 0.0,
        "more pressure bends the tip down: {adj:e}"
    );
    assert!(
        (adj - fd).abs() < 1e-6 * fd.abs(),
        "adjoint {adj:e}, central {fd:e}"
    );
    // The memory is a small multiple of one state, at a bounded recomputation.
    assert!(g.stored_states <= 40, "{} states", g.stored_states);
    assert!(g.recompute_ratio <= 3.0, "{}", g.recompute_ratio);
}

#[test]
fn benchmark_and_spring_mesh_example_gradients_match_central_differences() {
    // The other examples with a loss: the benchmark at 10k and 50k tets and the spring-mesh
    // model, over short rollouts with the target at 0 (see the test below for why). 50k tets
    // take ~10 ms a step on one thread, so its rollout is the shortest that lifts the tip
    // clear of round-off.
    for (example, steps) in [
        ("benchmark-10k.soft", 300),
        ("benchmark-50k.soft", 40),
        ("spring_mesh.soft", 300),
    ] {
        let path = variant(example, "+ 10 mm)^2", ")^2");
        check_all_params(&path, steps, 1e-3, 1e-5);
    }
}

#[test]
fn example_gradients_match_central_differences() {
    // Short rollouts of the examples with a loss (the cuboid: 11,520 tets). In a few hundred
    // steps the tip moves nanometres: against the 10 mm target the loss would change in its
    // 12th digit and a central difference would drown in round-off, so the target is 0 here
    // (same kernels, same shape of loss). The positions' own round-off (1e-18 m against
    // displacements of 1e-7 m) bounds the central difference's accuracy to about 1e-6.
    let pressure = variant("pressure_optimization_explicit.soft", "+ 10 mm)^2", ")^2");
    check_all_params(&pressure, 60, 1e-3, 1e-5);
    // Meta-optimization with 1 ms windows so that 5 of its 12 damping windows are in the run.
    let meta = variant("meta_optimization.soft", "+ 10 mm)^2", ")^2");
    let meta = std::fs::read_to_string(&meta)
        .unwrap()
        .replace("window(t, 50 ms)", "window(t, 1 ms)")
        .replace("duration = 0.6 s", "duration = 12 ms")
        // The study's smaller safety factor is for its full pressure; these 300 steps at
        // dt = auto reach the windows checked below (at 0.4 they end before window 2).
        .replace("dt = auto(safety: 0.4)", "dt = auto");
    let path =
        std::env::temp_dir().join(format!("softc-grad-{}/meta-1ms.soft", std::process::id()));
    std::fs::write(&path, meta).unwrap();
    let path = path.display().to_string();
    // Damping changes the loss weakly (dlnL/dlnβ ~ 0.1), and β₀ acts only in the first
    // millisecond, when the beam has barely moved: its central difference is round-off
    // limited. Measured (dt = auto, 300 steps): relative steps 1e-3, 3e-3, 1e-2, 3e-2, 5e-2,
    // 1e-1, 2e-1 scatter by 2.2e-4, 1.8e-4, 5.6e-5, 1.8e-5, 3.3e-7, 1.0e-5, 3.5e-6 around the
    // adjoint — noise, not a trend (with the earlier power-iteration stable-step estimate,
    // a slightly larger dt = auto, the 1e-2 figure was 4e-6). The adjoint itself is
    // bit-identical across schedules and backends (other tests here).
    check_params(&path, 300, 1e-2, 1e-4, |n| {
        ["param.beta.0", "param.beta.2", "param.beta.4"].contains(&n)
    });
    // Controller synthesis (the coarse endoscope, 13,998 tets) with one fixed target instead of
    // the sampled batch: the weights of the two nonzero features of that target.
    let controller = variant(
        "controller_synthesis_explicit.soft",
        "from circle_quadrants(radius: 40 um, plane: \"yz\", seed: 7)",
        "from [[0, 20, 34.64]] um",
    );
    // The weights start at 0. A step of 125 /m moves the sigmoid's argument by 0.0025 (the
    // features are 20 and 34.64 µm): the central difference's truncation error is then about
    // 5e-7 (h^2 sigma'''/(6 sigma')), and 200 steps lift the response above the round-off.
    check_params(&controller, 200, 125.0, 1e-5, |n| {
        ["param.w.0.0", "param.w.2.2"].contains(&n)
    });
    // Windows after the run cannot matter: their derivative is exactly 0.
    let g = gradient(&load(&path), 300, &GradOptions::default());
    assert_eq!(g.gradients["param.beta.11"], 0.0);
    assert!(g.gradients["param.beta.1"] != 0.0);
}

#[test]
fn checkpoint_schedules_give_bit_identical_gradients() {
    let scene = load("runtime/tests/fixtures/grad/all_kinds.soft");
    let with = |c, memory_budget| {
        gradient(
            &scene,
            200,
            &GradOptions {
                checkpoint: c,
                memory_budget,
                ..GradOptions::default()
            },
        )
    };
    let all = with(Checkpointing::StoreAll, None);
    assert_eq!(all.recompute_ratio, 1.0);
    // Without a budget `auto` stores every state that fits in 1 GiB: all 200 here.
    let auto = with(Checkpointing::Auto, None);
    assert_eq!(
        (auto.recompute_ratio, auto.stored_states),
        (1.0, all.stored_states)
    );
    // A budget of 10 states makes it checkpoint.
    let ten = Some(10 * all.state_bytes as u64);
    for (c, budget) in [
        (Checkpointing::Revolve(1), None),
        (Checkpointing::Revolve(4), None),
        (Checkpointing::Periodic(7), None),
        (Checkpointing::Auto, ten),
    ] {
        let other = with(c, budget);
        assert!(other.stored_states < all.stored_states);
        assert_eq!(
            other.summary.loss.unwrap().to_bits(),
            all.summary.loss.unwrap().to_bits()
        );
        for (name, g) in &all.gradients {
            assert_eq!(
                other.gradients[name].to_bits(),
                g.to_bits(),
                "{c:?}: {name} differs from store_all"
            );
        }
    }
}

#[test]
fn interpreter_and_cranelift_gradients_are_bit_identical() {
    let scene = load("runtime/tests/fixtures/grad/all_kinds.soft");
    let cpu = gradient(&scene, 30, &GradOptions::default());
    let mut sim = Simulation::new(&scene, Interpreter::new(&scene.lowered.adjoint.module));
    let interp = sim
        .gradient(None, Some(30), &GradOptions::default())
        .unwrap();
    for (name, g) in &cpu.gradients {
        assert_eq!(interp.gradients[name].to_bits(), g.to_bits(), "{name}");
    }
    // And with two threads.
    let two = Cpu::new(&scene.lowered.adjoint.module, Precision::F64, Some(2)).unwrap();
    let mut sim = Simulation::new(&scene, two);
    let threaded = sim
        .gradient(None, Some(30), &GradOptions::default())
        .unwrap();
    for (name, g) in &cpu.gradients {
        assert_eq!(threaded.gradients[name].to_bits(), g.to_bits(), "{name}");
    }
}

#[test]
fn truncation_keeps_only_the_last_steps() {
    let scene = load("examples/benchmark-1k.soft");
    let full = gradient(&scene, 100, &GradOptions::default());
    let cut = gradient(
        &scene,
        100,
        &GradOptions {
            truncate: Some(10),
            ..GradOptions::default()
        },
    );
    assert_eq!(cut.reversed_steps, 10);
    let (a, b) = (
        full.gradients["param.p_peak"],
        cut.gradients["param.p_peak"],
    );
    assert!(
        b != 0.0 && b.abs() < a.abs(),
        "truncated {b:e} vs full {a:e}"
    );
}

#[test]
fn a_budget_too_small_for_the_schedule_is_a_clear_error() {
    let scene = load("examples/benchmark-1k.soft");
    let cpu = Cpu::new(&scene.lowered.adjoint.module, Precision::F64, Some(1)).unwrap();
    let mut sim = Simulation::new(&scene, cpu);
    let e = sim
        .gradient(
            None,
            Some(100),
            &GradOptions {
                checkpoint: Checkpointing::StoreAll,
                memory_budget: Some(100_000),
                truncate: None,
            },
        )
        .unwrap_err();
    assert!(
        e.0.contains("memory_budget") && e.0.contains("store_all"),
        "{}",
        e.0
    );
    // `auto` fits the budget instead.
    let g = gradient(
        &scene,
        100,
        &GradOptions {
            memory_budget: Some(100_000),
            ..GradOptions::default()
        },
    );
    assert!(g.stored_states * g.state_bytes <= 100_000 + g.state_bytes);
}

/// The field fixture with its loss or its `mu` declaration edited (mesh path made absolute).
fn field_variant(name: &str, edits: &[(&str, &str)]) -> String {
    let mut text =
        std::fs::read_to_string(root().join("runtime/tests/fixtures/grad/field.soft")).unwrap();
    for (from, to) in edits {
        assert!(text.contains(from), "field.soft: {from}");
        text = text.replace(from, to);
    }
    let text = text.replace(
        "\"../../../../meshes/",
        &format!("\"{}/meshes/", root().display()),
    );
    let dir = std::env::temp_dir().join(format!("softc-grad-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let path = dir.join(format!("{name}.soft"));
    std::fs::write(&path, text).unwrap();
    path.display().to_string()
}

/// Entry indices of `param.mu.*` ordered by decreasing |gradient|.
fn by_magnitude(g: &GradientReport) -> Vec<(usize, f64)> {
    let mut v: Vec<(usize, f64)> = g
        .gradients
        .iter()
        .filter_map(|(k, &d)| Some((k.strip_prefix("param.mu.")?.parse().ok()?, d)))
        .collect();
    v.sort_by(|a, b| b.1.abs().total_cmp(&a.1.abs()));
    v
}

#[test]
fn per_element_param_matches_central_differences() {
    // d loss / d mu[e] for single elements of a per-element shear modulus, against central
    // differences that perturb that element's value alone.
    let scene = load("runtime/tests/fixtures/grad/field.soft");
    let field = &scene.fields[0];
    assert_eq!(field.name, "mu");
    let n = field.elements.len();
    assert!(
        n > 100 && n < scene.mesh.tets.len(),
        "{n} elements in `near`"
    );
    let g = gradient(&scene, 200, &GradOptions::default());
    // One entry per element of the set, each its own derivative.
    let entries = by_magnitude(&g);
    assert_eq!(entries.len(), n);
    assert!(entries.iter().all(|(_, d)| d.is_finite()));
    let nonzero = entries.iter().filter(|(_, d)| *d != 0.0).count();
    assert!(
        nonzero > n / 2,
        "only {nonzero} of {n} entries have a gradient"
    );
    // The three most influential elements, one of middling influence, and p0.
    let picks = [entries[0].0, entries[1].0, entries[2].0, entries[n / 4].0];
    let mut report = Vec::new();
    for i in picks {
        let name = format!("param.mu.{i}");
        let adj = g.gradients[&name];
        let p = scene.uniforms[&name];
        let fd = central(&scene, 200, &name, 1e-3 * p);
        let err = (adj - fd).abs() / fd.abs();
        report.push(format!(
            "{name} (element {}): adjoint {adj:e}, central {fd:e}, rel err {err:.1e}",
            field.elements[i]
        ));
        assert!(err < 1e-5, "{}", report.join("\n"));
    }
    let adj = g.gradients["param.p0"];
    let fd = central(&scene, 200, "param.p0", 1e-4 * scene.uniforms["param.p0"]);
    report.push(format!("param.p0: adjoint {adj:e}, central {fd:e}"));
    assert!((adj - fd).abs() < 1e-5 * fd.abs(), "{}", report.join("\n"));
    eprintln!("{}", report.join("\n"));
}

#[test]
fn a_per_element_param_with_equal_entries_is_the_scalar_param() {
    // The same scene with `mu` one scalar param: the forward run is bit-identical (the kernel
    // reads the same value from a buffer instead of a uniform) and d loss / d mu is the sum of
    // the per-element derivatives.
    let field = load("runtime/tests/fixtures/grad/field.soft");
    let scalar = load(&field_variant(
        "field-scalar",
        &[("param mu: pressure[near]", "param mu: pressure")],
    ));
    assert!(scalar.fields.is_empty());
    let gf = gradient(&field, 100, &GradOptions::default());
    let gs = gradient(&scalar, 100, &GradOptions::default());
    assert_eq!(
        gf.summary.loss.unwrap().to_bits(),
        gs.summary.loss.unwrap().to_bits()
    );
    for (a, b) in gf.summary.x.iter().zip(&gs.summary.x) {
        assert_eq!(a.map(f64::to_bits), b.map(f64::to_bits));
    }
    let sum: f64 = by_magnitude(&gf).iter().map(|(_, d)| d).sum();
    let want = gs.gradients["param.mu"];
    assert!(
        (sum - want).abs() < 1e-10 * want.abs(),
        "sum of entries {sum:e}, scalar {want:e}"
    );
    assert_eq!(
        gf.gradients["param.p0"].to_bits(),
        gs.gradients["param.p0"].to_bits()
    );
}

#[test]
fn a_loss_reading_field_entries_adds_their_direct_derivative() {
    // `mu[e]` in the loss: each entry gets 2 (mu - 10 kPa) · (1 um / 1 MPa)^2 on top of its
    // derivative through the simulation. The entries are made unequal first.
    let plain = load("runtime/tests/fixtures/grad/field.soft");
    let mut with = load(&field_variant(
        "field-regularized",
        &[(
            "(x[n].z - x0[n].z)^2 at end",
            "(x[n].z - x0[n].z)^2 + sum(e in near) ((mu[e] - 10 kPa) / 1 MPa * 1 um)^2 at end",
        )],
    ));
    let mut plain = plain;
    for scene in [&mut plain, &mut with] {
        for (i, v) in scene
            .uniforms
            .iter_mut()
            .filter(|(k, _)| k.starts_with("param.mu."))
            .enumerate()
        {
            *v.1 = 20e3 + 100.0 * (i % 7) as f64;
        }
    }
    let a = gradient(&plain, 50, &GradOptions::default());
    let b = gradient(&with, 50, &GradOptions::default());
    let mut checked = 0;
    for (name, &d) in &a.gradients {
        let Some(_) = name.strip_prefix("param.mu.") else {
            continue;
        };
        let mu = with.uniforms[name];
        let direct = 2.0 * (mu - 10e3) * (1e-6 / 1e6_f64).powi(2);
        let got = b.gradients[name] - d;
        // The difference of two sums is exact up to the round-off of the larger term.
        assert!(
            (got - direct).abs() <= 1e-9 * direct.abs() + 1e-15 * d.abs(),
            "{name}: {got:e} vs {direct:e}"
        );
        checked += 1;
    }
    assert_eq!(checked, plain.fields[0].elements.len());
    let extra: f64 = (0..checked)
        .map(|i| ((with.uniforms[&format!("param.mu.{i}")] - 10e3) / 1e6 * 1e-6).powi(2))
        .sum();
    let (la, lb) = (a.summary.loss.unwrap(), b.summary.loss.unwrap());
    assert!(
        ((lb - la) - extra).abs() <= 1e-9 * extra,
        "{la:e} {lb:e} {extra:e}"
    );
}

#[test]
fn per_element_gradients_are_bit_identical_across_backends_and_schedules() {
    let scene = load("runtime/tests/fixtures/grad/field.soft");
    let cpu = gradient(&scene, 30, &GradOptions::default());
    let mut sim = Simulation::new(&scene, Interpreter::new(&scene.lowered.adjoint.module));
    let interp = sim
        .gradient(None, Some(30), &GradOptions::default())
        .unwrap();
    let two = Cpu::new(&scene.lowered.adjoint.module, Precision::F64, Some(2)).unwrap();
    let threaded = Simulation::new(&scene, two)
        .gradient(None, Some(30), &GradOptions::default())
        .unwrap();
    let revolve = gradient(
        &scene,
        30,
        &GradOptions {
            checkpoint: Checkpointing::Revolve(3),
            ..GradOptions::default()
        },
    );
    assert!(cpu.gradients.len() > 100);
    for (name, g) in &cpu.gradients {
        for (other, what) in [
            (&interp, "interp"),
            (&threaded, "2 threads"),
            (&revolve, "revolve"),
        ] {
            assert_eq!(
                other.gradients[name].to_bits(),
                g.to_bits(),
                "{what}: {name}"
            );
        }
    }
}

#[test]
fn a_material_with_a_field_outside_its_set_is_refused() {
    let path = field_variant(
        "field-everywhere",
        &[("  use gel\n  use graded in near\n", "  use graded\n")],
    );
    let e = Scene::load(Path::new(&path), &[]).unwrap_err();
    assert!(
        e.0.contains("material `graded` takes `mu` per element of `near`")
            && e.0.contains("use graded in near"),
        "{}",
        e.0
    );
}

#[test]
fn a_field_reduction_in_a_pressure_is_a_sensor_with_exact_gradients() {
    // `mean(e in near) mu[e]` needs the set's elements, known only once the mesh is loaded:
    // the host evaluates it (a closed-loop sensor, here of params only), and each entry's
    // gradient adds the path through the pressure to the one through the material (it was
    // E0325 before closed-loop control).
    let path = field_variant(
        "field-in-pressure",
        &[(
            "p0 * ramp(t, 1 ms)",
            "p0 * ramp(t, 1 ms) * mean(e in near) mu[e] / 20 kPa",
        )],
    );
    let scene = load(&path);
    assert_eq!(scene.sensors.len(), 1);
    let g = gradient(&scene, 60, &GradOptions::default());
    // The same entries' gradients through the material alone (the pressure without the mean).
    let plain = load(
        root()
            .join("runtime/tests/fixtures/grad/field.soft")
            .to_str()
            .unwrap(),
    );
    let material_only = gradient(&plain, 60, &GradOptions::default());
    for entry in ["param.mu.0", "param.mu.7"] {
        let fd = central(&scene, 60, entry, 20.0);
        let adj = g.gradients[entry];
        assert!(
            (adj - fd).abs() < 1e-6 * fd.abs(),
            "{entry}: adjoint {adj:e}, central {fd:e}"
        );
        // The path through the pressure is a visible share of it.
        let through_pressure = adj - material_only.gradients[entry];
        assert!(
            through_pressure.abs() > 1e-3 * fd.abs(),
            "{entry}: through the pressure {through_pressure:e} of {adj:e}"
        );
    }
}

#[test]
fn set_broadcasts_to_every_entry_of_a_field() {
    let path = root().join("runtime/tests/fixtures/grad/field.soft");
    let scene = Scene::load(&path, &[("mu".to_string(), 35e3)]).unwrap();
    let n = scene.fields[0].elements.len();
    assert_eq!(
        scene
            .uniforms
            .iter()
            .filter(|(k, v)| k.starts_with("param.mu.") && **v == 35e3)
            .count(),
        n
    );
}

#[test]
fn set_reaches_single_entries_of_arrays_and_fields() {
    // `--set beta.2=…` / `--set mu.3=…` (and `--params`, which expands to such names) override
    // one entry; an entry override wins over a whole-param one, whatever their order.
    let path = root().join("runtime/tests/fixtures/grad/all_kinds.soft");
    let scene = Scene::load(
        &path,
        &[("beta.2".to_string(), 5.0), ("w.1".to_string(), 0.5)],
    )
    .unwrap();
    let u = &scene.uniforms;
    assert_eq!(u["param.beta.2"], 5.0);
    assert_eq!(
        [u["param.beta.0"], u["param.beta.1"], u["param.beta.3"]],
        [20.0; 3]
    );
    assert_eq!([u["param.w.0"], u["param.w.1"]], [200.0, 0.5]);
    let path = root().join("runtime/tests/fixtures/grad/field.soft");
    let scene = Scene::load(
        &path,
        &[("mu".to_string(), 35e3), ("mu.3".to_string(), 40e3)],
    )
    .unwrap();
    assert_eq!(scene.uniforms["param.mu.3"], 40e3);
    assert_eq!(scene.uniforms["param.mu.2"], 35e3);
}

#[test]
fn initial_state_gradients_match_central_differences() {
    // d loss / d x(0) and d loss / d v(0) of single nodes: the adjoint of state 0 that the
    // backward pass ends with. The loss's `x0` is the mesh's rest position (a constant), so
    // perturbing the simulation's initial state is an initial deformation or kick.
    let scene = load("examples/benchmark-1k.soft");
    let steps = 200;
    let g = gradient(&scene, steps, &GradOptions::default());
    let (gx, gv) = g
        .initial_state
        .clone()
        .expect("the whole horizon was reversed");
    let m = &scene.lowered.module;
    let loss_from = |field: &str, index: usize, delta: f64| {
        let cpu = Cpu::new(m, Precision::F64, Some(1)).unwrap();
        let mut sim = Simulation::new(&scene, cpu);
        let id = m.buffer_named(field).unwrap();
        let mut data = if field == "x" {
            scene
                .mesh
                .nodes
                .iter()
                .flatten()
                .copied()
                .collect::<Vec<f64>>()
        } else {
            vec![0.0; 3 * scene.mesh.nodes.len()]
        };
        data[index] += delta;
        sim.backend.set(id, &data);
        sim.run(None, Some(steps)).unwrap().loss.unwrap()
    };
    let tip = scene.node_sets.iter().find(|(n, _)| n == "tip").unwrap().1[0] as usize;
    // A free node halfway along the beam.
    let mid = (0..scene.mesh.nodes.len())
        .find(|&i| !scene.fixed[i] && (scene.mesh.nodes[i][0] - 0.03).abs() < 1e-3)
        .unwrap();
    for (field, grad, node, h) in [
        ("v", &gv, tip, 1e-3),
        ("v", &gv, mid, 1e-3),
        ("x", &gx, mid, 1e-7),
    ] {
        let i = 3 * node + 2;
        let fd = (loss_from(field, i, h) - loss_from(field, i, -h)) / (2.0 * h);
        let err = (grad[i] - fd).abs() / fd.abs();
        eprintln!(
            "d loss/d {field}0[{node}].z: adjoint {:e}, central {fd:e}, rel err {err:.1e}",
            grad[i]
        );
        assert!(
            err < 1e-5,
            "{field} node {node}: adjoint {:e}, central {fd:e}",
            grad[i]
        );
    }
    // Fixed nodes cannot move: their initial velocity has no effect.
    let fixed = scene.fixed.iter().position(|f| *f).unwrap();
    assert_eq!(gv[3 * fixed + 2], 0.0);
    // A truncated pass does not reach state 0.
    let t = gradient(
        &scene,
        steps,
        &GradOptions {
            truncate: Some(50),
            ..GradOptions::default()
        },
    );
    assert!(t.initial_state.is_none());
}
