//! The forward simulation through the kernel IR: the canonical benchmark scene reproduces the
//! tip displacement other systems report (shared/BENCHMARK.md), the stable-step estimate
//! matches the measured limit, instability is reported instead of NaNs, a scene without load
//! stays at rest, and runs are deterministic.

use softc::devices::interp::Interpreter;
use softc::engine::Simulation;
use softc::engine::scene::Scene;
use std::path::{Path, PathBuf};

fn root() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .parent()
        .unwrap()
        .to_path_buf()
}

/// A copy of an example with some lines replaced, written next to the meshes it loads.
fn variant(example: &str, edits: &[(&str, &str)]) -> PathBuf {
    let mut text = std::fs::read_to_string(root().join("examples").join(example)).unwrap();
    for (from, to) in edits {
        assert!(text.contains(from), "{from}");
        text = text.replace(from, to);
    }
    let dir = std::env::temp_dir().join(format!("softc-engine-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let text = text.replace("\"../meshes/", &format!("\"{}/meshes/", root().display()));
    static COUNT: std::sync::atomic::AtomicUsize = std::sync::atomic::AtomicUsize::new(0);
    let n = COUNT.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
    let path = dir.join(format!("{}-{n}.soft", example.trim_end_matches(".soft")));
    std::fs::write(&path, text).unwrap();
    path
}

fn tip_mean_z(scene: &Scene, x: &[[f64; 3]]) -> f64 {
    let (_, tip) = scene.node_sets.iter().find(|(n, _)| n == "tip").unwrap();
    tip.iter()
        .map(|&n| x[n as usize][2] - scene.mesh.nodes[n as usize][2])
        .sum::<f64>()
        / tip.len() as f64
}

#[test]
fn benchmark_1k_tip_displacement_matches_the_published_value() {
    // BENCHMARK.md: tip mean z-displacement after 4000 steps at dt = 40 µs, 1k mesh:
    // −0.015146 mm (f64, other systems).
    let scene = Scene::load(&root().join("examples/benchmark-1k.soft"), &[]).unwrap();
    let mut sim = Simulation::new(&scene, Interpreter::new(&scene.lowered.module));
    let s = sim.run(None, None).unwrap();
    assert_eq!(s.steps, 4000);
    let uz = tip_mean_z(&scene, &s.x);
    assert!(
        (uz - (-0.015146e-3)).abs() < 0.000002e-3,
        "tip mean uz = {uz:e} m"
    );
}

#[test]
fn stable_step_estimate_is_the_measured_limit() {
    // BENCHMARK.md: largest stable dt of the 1k scene is 52 µs (0.98x stable, 1.02x diverges).
    let scene = Scene::load(&root().join("examples/benchmark-1k.soft"), &[]).unwrap();
    let mut sim = Simulation::new(&scene, Interpreter::new(&scene.lowered.module));
    let est = sim.stable_dt_estimate().unwrap();
    assert!((est - 52e-6).abs() < 1.5e-6, "estimate {est:e}");
    // 1.04x the estimate diverges, and the engine says so with the step and a suggestion.
    let mut sim = Simulation::new(&scene, Interpreter::new(&scene.lowered.module));
    let e = sim.run(Some(1.04 * est), Some(3000)).unwrap_err().0;
    assert!(
        e.contains("unstable") && e.contains("step") && e.contains("dt"),
        "{e}"
    );
}

#[test]
fn without_pressure_the_beam_stays_at_rest() {
    let path = variant(
        "benchmark-1k.soft",
        &[(
            "pressure cavity = p_peak * ramp(t, 0.5 s)",
            "pressure cavity = 0 * p_peak",
        )],
    );
    let scene = Scene::load(&path, &[]).unwrap();
    let mut sim = Simulation::new(&scene, Interpreter::new(&scene.lowered.module));
    let s = sim.run(None, Some(300)).unwrap();
    for (x, x0) in s.x.iter().zip(&scene.mesh.nodes) {
        for d in 0..3 {
            assert!((x[d] - x0[d]).abs() < 1e-15, "moved: {x:?} vs {x0:?}");
        }
    }
}

#[test]
fn runs_are_bit_identical_and_param_overrides_apply() {
    let path = root().join("examples/benchmark-1k.soft");
    let run = |overrides: &[(String, f64)]| {
        let scene = Scene::load(&path, overrides).unwrap();
        let mut sim = Simulation::new(&scene, Interpreter::new(&scene.lowered.module));
        sim.run(None, Some(200)).unwrap().x
    };
    let a = run(&[]);
    let b = run(&[]);
    assert!(
        a.iter()
            .flatten()
            .zip(b.iter().flatten())
            .all(|(p, q)| p.to_bits() == q.to_bits())
    );
    // Doubling the peak pressure roughly doubles the (small, linear-range) displacement.
    let c = run(&[("p_peak".to_string(), 6e3)]);
    let scene = Scene::load(&path, &[]).unwrap();
    let (ua, uc) = (tip_mean_z(&scene, &a), tip_mean_z(&scene, &c));
    assert!((uc / ua - 2.0).abs() < 0.01, "{ua:e} -> {uc:e}");
}

#[test]
fn every_example_sets_up_a_scene() {
    for ex in [
        "verification.soft",
        "pressure_optimization_explicit.soft",
        "meta_optimization.soft",
        "controller_synthesis_explicit.soft",
        "benchmark-10k.soft",
    ] {
        let scene = Scene::load(&root().join("examples").join(ex), &[])
            .unwrap_or_else(|e| panic!("{ex}: {e}"));
        assert!(scene.fixed.iter().any(|&f| f), "{ex}: nothing fixed");
        assert!(!scene.tris.is_empty(), "{ex}: no chamber triangles");
        assert!(
            scene.node_sets.iter().all(|(_, n)| !n.is_empty()),
            "{ex}: empty node set"
        );
    }
}

#[test]
fn cranelift_backend_is_bit_identical_to_the_interpreter_and_thread_independent() {
    use softc::devices::cpu::Cpu;
    use softc_compiler::back::Precision;
    for example in [
        "benchmark-1k.soft",
        "meta_optimization.soft",
        "controller_synthesis_explicit.soft",
        "spring_mesh.soft",
    ] {
        let scene = Scene::load(&root().join("examples").join(example), &[]).unwrap();
        let dt = Some(2e-6);
        let reference = Simulation::new(&scene, Interpreter::new(&scene.lowered.module))
            .run(dt, Some(60))
            .unwrap();
        for threads in [1, 2, 3] {
            let cpu = Cpu::new(&scene.lowered.module, Precision::F64, Some(threads)).unwrap();
            let s = Simulation::new(&scene, cpu).run(dt, Some(60)).unwrap();
            let same =
                s.x.iter()
                    .flatten()
                    .zip(reference.x.iter().flatten())
                    .all(|(a, b)| a.to_bits() == b.to_bits());
            assert!(
                same,
                "{example}: cpu ({threads} threads) differs from the interpreter"
            );
        }
    }
}

#[test]
fn f32_kernels_stay_close_to_f64() {
    use softc::devices::cpu::Cpu;
    use softc_compiler::back::Precision;
    let scene = Scene::load(&root().join("examples/benchmark-1k.soft"), &[]).unwrap();
    let run = |p| {
        let cpu = Cpu::new(&scene.lowered.module, p, Some(1)).unwrap();
        Simulation::new(&scene, cpu).run(None, Some(1000)).unwrap()
    };
    let (a, b) = (run(Precision::F64), run(Precision::F32));
    let (ua, ub) = (tip_mean_z(&scene, &a.x), tip_mean_z(&scene, &b.x));
    // f32 positions of ~60 mm carry ~4 nm of rounding per step against µm displacements: a
    // relative error of a few 1e-3 on the tip displacement is the expected f32 accuracy.
    assert!(
        (ub - ua).abs() < 5e-3 * ua.abs(),
        "f64 {ua:e} vs f32 {ub:e}"
    );
}

#[test]
fn the_loss_is_the_scripts_expression_at_the_end_or_summed_over_its_window() {
    let scene = Scene::load(&root().join("examples/benchmark-1k.soft"), &[]).unwrap();
    let s = Simulation::new(&scene, Interpreter::new(&scene.lowered.module))
        .run(None, Some(300))
        .unwrap();
    // loss = sum(n in tip) (x[n].z - x0[n].z + 10 mm)^2 at end, computed here by hand.
    let (_, tip) = scene.node_sets.iter().find(|(n, _)| n == "tip").unwrap();
    let want: f64 = tip
        .iter()
        .map(|&n| (s.x[n as usize][2] - scene.mesh.nodes[n as usize][2] + 0.01).powi(2))
        .sum();
    let got = s.loss.unwrap();
    assert!((got - want).abs() <= 1e-14 * want, "{got} vs {want}");
    // A window holding only the last step gives the same value; one holding the last two
    // steps adds the previous state's term.
    let last = variant(
        "benchmark-1k.soft",
        &[("+ 10 mm)^2 at end", "+ 10 mm)^2 over [t_end, t_end]")],
    );
    let scene2 = Scene::load(&last, &[]).unwrap();
    let s2 = Simulation::new(&scene2, Interpreter::new(&scene2.lowered.module))
        .run(None, Some(300))
        .unwrap();
    assert_eq!(s2.loss.unwrap().to_bits(), got.to_bits());
    let two = variant(
        "benchmark-1k.soft",
        &[("+ 10 mm)^2 at end", "+ 10 mm)^2 over [t_end - dt, t_end]")],
    );
    let scene3 = Scene::load(&two, &[]).unwrap();
    let s3 = Simulation::new(&scene3, Interpreter::new(&scene3.lowered.module))
        .run(None, Some(300))
        .unwrap();
    let prev = Simulation::new(&scene, Interpreter::new(&scene.lowered.module))
        .run(None, Some(299))
        .unwrap()
        .loss
        .unwrap();
    assert!(
        (s3.loss.unwrap() - (got + prev)).abs() <= 1e-14 * got,
        "{} vs {}",
        s3.loss.unwrap(),
        got + prev
    );
}

/// `integrator = quasi_static` on a dynamic script (it used to be refused as unimplemented):
/// the scene compiles to an equilibrium solve with its tangent kernels, and the dynamic
/// setting it ignores is a warning, not silently dropped.
#[test]
fn a_quasi_static_variant_compiles_to_an_equilibrium_solve_and_warns_about_damping() {
    let path = variant(
        "benchmark-1k.soft",
        &[(
            "damping = 20 /s",
            "damping = 20 /s\n  integrator = quasi_static",
        )],
    );
    let scene = Scene::load(&path, &[]).unwrap();
    let statics = scene.lowered.statics.as_ref().expect("a static solve");
    assert!(statics.implicit.is_none());
    assert_eq!(statics.element_jacobians.len(), 1);
    assert_eq!(statics.chamber_jacobians.len(), 1);
    let warned: Vec<&str> = scene.resolved.warnings.iter().map(|d| d.code).collect();
    assert!(warned.contains(&"W0005"), "{warned:?}");
}

/// A unit cube of 6 Kuhn tets with one corner pushed through the opposite corner, so that
/// elements start inverted (J < 0), then released (no load, damped).
fn inverted_cube_run(material: &str) -> Result<(Scene, softc::engine::RunSummary), String> {
    use softc::mesh::kuhn::{KuhnSpec, kuhn_grid};
    let dir = std::env::temp_dir().join(format!("softc-invert-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let spec = KuhnSpec {
        n: [1, 1, 1],
        min: [0.0; 3],
        max: [10.0; 3],
        cavity_min: [-2.0; 3],
        cavity_max: [-1.0; 3],
    };
    let mesh = kuhn_grid(&spec, softc::mesh::LengthUnit::Millimetre).unwrap();
    let file = dir.join("cube.msh");
    softc::mesh::save(&mesh, &file, softc::mesh::LengthUnit::Millimetre).unwrap();
    let script = dir.join(format!("cube-{material}.soft"));
    std::fs::write(
        &script,
        format!(
            "mesh body = load(\"{}\")\n\
             material gel = {material}(mu: 10 kPa, {}: 40 kPa, density: 1000 kg/m^3)\n\
             sim {{\n  dt = 20 us\n  steps = 6000\n  damping = 200 /s\n}}\n",
            file.display(),
            if material == "neo_hookean" {
                "kappa"
            } else {
                "lambda"
            }
        ),
    )
    .unwrap();
    let scene = Scene::load(&script, &[]).unwrap();
    // The corner at the origin goes past the far face x = 10 mm: some of its tets invert.
    let mut x: Vec<f64> = scene.mesh.nodes.iter().flatten().copied().collect();
    let corner = scene
        .mesh
        .nodes
        .iter()
        .position(|p| p.iter().all(|c| c.abs() < 1e-12))
        .unwrap();
    x[3 * corner..3 * corner + 3].copy_from_slice(&PUSHED);
    let id = scene.lowered.module.buffer_named("x").unwrap();
    let s = {
        let mut sim = Simulation::new(&scene, Interpreter::new(&scene.lowered.module));
        softc::engine::Backend::set(&mut sim.backend, id, &x);
        sim.run(None, None).map_err(|e| e.0)
    };
    s.map(|s| (scene, s))
}

/// Where the corner at the origin is pushed, m.
const PUSHED: [f64; 3] = [0.015, 0.002, 0.003];

fn volume_ratios(scene: &Scene, x: &[[f64; 3]]) -> Vec<f64> {
    let vol = |p: [[f64; 3]; 4]| {
        let a = [0, 1, 2].map(|k| p[1][k] - p[0][k]);
        let b = [0, 1, 2].map(|k| p[2][k] - p[0][k]);
        let c = [0, 1, 2].map(|k| p[3][k] - p[0][k]);
        (a[0] * (b[1] * c[2] - b[2] * c[1]) - a[1] * (b[0] * c[2] - b[2] * c[0])
            + a[2] * (b[0] * c[1] - b[1] * c[0]))
            / 6.0
    };
    scene
        .mesh
        .tets
        .iter()
        .map(|t| vol(t.map(|n| x[n as usize])) / vol(t.map(|n| scene.mesh.nodes[n as usize])))
        .collect()
}

#[test]
fn an_inverted_element_recovers_with_the_inversion_safe_material_only() {
    // The start state really is inverted.
    let (scene, s) = inverted_cube_run("stable_neo_hookean").unwrap();
    let mut x0 = scene.mesh.nodes.clone();
    let corner = x0
        .iter()
        .position(|p| p.iter().all(|c| c.abs() < 1e-12))
        .unwrap();
    x0[corner] = PUSHED;
    let j0 = volume_ratios(&scene, &x0);
    assert!(j0.iter().any(|&j| j < 0.0), "{j0:?}");
    // Stable neo-Hookean: the run goes through, and every element is back near its rest
    // volume (the cube is free, so it may have moved rigidly).
    let j = volume_ratios(&scene, &s.x);
    assert!(j.iter().all(|&j| (j - 1.0).abs() < 0.02), "{j:?}");
    // The same start with the classic (isochoric) neo-Hookean stops with the inversion error.
    let e = inverted_cube_run("neo_hookean").unwrap_err();
    assert!(e.contains("inverted") && e.contains("element"), "{e}");
}

/// A clamped neo-Hookean column (10 × 2 × 2 mm, ν = 0) on an `n` Kuhn grid, hanging under
/// 0.01 g along +x with `sim_extra` added to its sim block; returns the tip's mean x
/// displacement after `duration`.
fn hanging_column_tip(dir: &Path, n: [usize; 3], duration: f64, sim_extra: &str) -> f64 {
    use softc::devices::cpu::Cpu;
    use softc::mesh::kuhn::{KuhnSpec, kuhn_grid};
    use softc_compiler::back::Precision;
    let spec = KuhnSpec {
        n,
        min: [0.0, 0.0, 0.0],
        max: [10.0, 2.0, 2.0],
        // No cell centre lies in this box: a solid column.
        cavity_min: [-2.0, -2.0, -2.0],
        cavity_max: [-1.0, -1.0, -1.0],
    };
    let mesh = kuhn_grid(&spec, softc::mesh::LengthUnit::Millimetre).unwrap();
    let file = dir.join(format!("column{}.msh", n[0]));
    softc::mesh::save(&mesh, &file, softc::mesh::LengthUnit::Millimetre).unwrap();
    let script = dir.join(format!("column{}-{}.soft", n[0], sim_extra.len()));
    std::fs::write(
        &script,
        format!(
            "mesh body = load(\"{}\")\n\
             material gel = neo_hookean_ln(mu: 5 kPa, lambda: 0 kPa, density: 1000 kg/m^3)\n\
             nodes base = named(body, \"base\")\n\
             nodes tip = named(body, \"tip\")\n\
             sim {{\n  dt = auto\n  duration = {duration} s\n  damping = 300 /s\n  \
             {sim_extra}gravity = [0.0981, 0, 0] m/s^2\n  fix base\n}}\n",
            file.display()
        ),
    )
    .unwrap();
    let scene = Scene::load(&script, &[]).unwrap();
    let cpu = Cpu::new(&scene.lowered.module, Precision::F64, Some(1)).unwrap();
    let s = Simulation::new(&scene, cpu).run(None, None).unwrap();
    let (_, tip) = scene.node_sets.iter().find(|(n, _)| n == "tip").unwrap();
    tip.iter()
        .map(|&i| s.x[i as usize][0] - scene.mesh.nodes[i as usize][0])
        .sum::<f64>()
        / tip.len() as f64
}

/// A column hanging under its own weight (clamped at x = 0, gravity along +x), ν = 0: small
/// strain theory gives the free end's displacement ρ g L² / (2E). The explicit run is damped to
/// its steady state; the result converges to the closed form as the mesh is refined.
#[test]
fn hanging_column_matches_the_closed_form_and_converges() {
    let dir = std::env::temp_dir().join(format!("softc-column-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    // A small load (0.01 g) keeps strains at 1e-4, where the small-strain closed form holds.
    let (rho, g, e, l) = (1000.0, 0.0981, 10e3, 0.01);
    let exact = rho * g * l * l / (2.0 * e);
    let mut errors = Vec::new();
    for n in [[5, 1, 1], [10, 2, 2], [20, 4, 4]] {
        let ux = hanging_column_tip(&dir, n, 0.12, "");
        errors.push(((ux - exact) / exact).abs());
    }
    eprintln!("hanging column: relative errors {errors:?} (exact {exact:e} m)");
    // Measured: 4.6e-4, 3.2e-5, 2.4e-5 (the finest is limited by the remaining settling and
    // finite-strain terms, ~2e-5).
    assert!(errors[2] < 1e-4, "{errors:?}");
    assert!(
        errors[1] < errors[0] / 5.0,
        "no convergence under refinement: {errors:?}"
    );
    std::fs::remove_dir_all(&dir).ok();
}

/// A cantilever (20 × 2 × 2 mm, clamped at x = 0, ν = 0) sagging under a small gravity load:
/// Euler–Bernoulli gives the tip deflection q L⁴ / (8 E I) = 3 ρ g L⁴ / (2 E h²). Linear Kuhn
/// tets lock in bending, so coarse meshes are too stiff; the test asserts that the error falls
/// under refinement and that the finest mesh (4 elements through the thickness) is within the
/// tolerance stated below.
#[test]
fn cantilever_deflection_converges_to_beam_theory() {
    use softc::devices::cpu::Cpu;
    use softc::mesh::kuhn::{KuhnSpec, kuhn_grid};
    use softc_compiler::back::Precision;
    let dir = std::env::temp_dir().join(format!("softc-cantilever-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let (rho, g, e, l, h): (f64, f64, f64, f64, f64) = (1000.0, 0.005, 10e3, 0.02, 0.002);
    let exact = 1.5 * rho * g * l.powi(4) / (e * h * h);
    let mut errors = Vec::new();
    for n in [[10, 1, 1], [20, 2, 2], [40, 4, 4]] {
        let spec = KuhnSpec {
            n,
            min: [0.0, 0.0, 0.0],
            max: [20.0, 2.0, 2.0],
            cavity_min: [-2.0, -2.0, -2.0],
            cavity_max: [-1.0, -1.0, -1.0],
        };
        let mesh = kuhn_grid(&spec, softc::mesh::LengthUnit::Millimetre).unwrap();
        let file = dir.join(format!("beam{}.msh", n[0]));
        softc::mesh::save(&mesh, &file, softc::mesh::LengthUnit::Millimetre).unwrap();
        let script = dir.join(format!("beam{}.soft", n[0]));
        // Damping near critical for the first bending mode (f1 ≈ 2.5 Hz): settled in 1 s.
        std::fs::write(
            &script,
            format!(
                "mesh body = load(\"{}\")\n\
                 material gel = neo_hookean_ln(mu: 5 kPa, lambda: 0 kPa, density: 1000 kg/m^3)\n\
                 nodes base = named(body, \"base\")\n\
                 nodes tip = named(body, \"tip\")\n\
                 sim {{\n  dt = auto\n  duration = 1 s\n  damping = 30 /s\n  \
                 gravity = [0, 0, -0.005] m/s^2\n  fix base\n}}\n",
                file.display()
            ),
        )
        .unwrap();
        let scene = Scene::load(&script, &[]).unwrap();
        let cpu = Cpu::new(&scene.lowered.module, Precision::F64, Some(1)).unwrap();
        let s = Simulation::new(&scene, cpu).run(None, None).unwrap();
        let uz = -tip_mean_z(&scene, &s.x);
        errors.push(((uz - exact) / exact).abs());
    }
    eprintln!("cantilever: relative errors {errors:?} (exact {exact:e} m)");
    // Measured: 0.75, 0.45, 0.17 (the same to 1e-7 with a 2 s run: settled). Shear locking of
    // linear tets makes the coarse beams far too stiff; each halving of the element size must
    // cut the error by at least 1.5x, and 4 elements through the thickness must be within 20%.
    assert!(
        errors[1] < errors[0] / 1.5 && errors[2] < errors[1] / 1.5,
        "no convergence under refinement: {errors:?}"
    );
    assert!(errors[2] < 0.2, "{errors:?}");
    std::fs::remove_dir_all(&dir).ok();
}

#[test]
fn a_run_to_steady_state_stops_once_settled_and_matches_a_long_run() {
    use softc::devices::cpu::Cpu;
    use softc_compiler::back::Precision;
    // The benchmark beam as a quasi-static scene: heavy nodes, the step from the estimate.
    let path = variant(
        "benchmark-1k.soft",
        &[(
            "  dt = 40 us\n  steps = 4000\n",
            "  dt = auto\n  duration = 2 s\n  mass_scaling = 100\n",
        )],
    );
    let scene = Scene::load(&path, &[]).unwrap();
    let cpu = Cpu::new(&scene.lowered.module, Precision::F64, None).unwrap();
    let mut sim = Simulation::new(&scene, cpu);
    let (dt, steps) = sim.time_steps(None, None).unwrap();
    let steady = sim.run_to_steady_state(Some(dt), 4 * steps, 1e-4).unwrap();
    assert!(steady.settled);
    // The ramp ends at 0.5 s: settling cannot be declared during it.
    let settled_at = steady.summary.steps as f64 * dt;
    assert!(
        settled_at > 0.5 && steady.summary.steps < 4 * steps,
        "{settled_at}"
    );
    sim.reset();
    let long = sim.run(Some(dt), Some(4 * steps)).unwrap();
    let (a, b) = (
        tip_mean_z(&scene, &steady.summary.x),
        tip_mean_z(&scene, &long.x),
    );
    println!(
        "settled after {settled_at:.3} s: tip {a:e} m; after {:.1} s: {b:e} m",
        4.0 * steps as f64 * dt
    );
    assert!(((a - b) / b).abs() < 1e-3, "{a} vs {b}");
    // A loose tolerance stops earlier and is less accurate.
    sim.reset();
    let loose = sim.run_to_steady_state(Some(dt), 4 * steps, 1e-1).unwrap();
    assert!(loose.settled && loose.summary.steps < steady.summary.steps);
}

#[test]
fn the_compiled_time_loop_gives_the_bits_of_launch_by_launch_stepping() {
    // Stretches of steps between host work run as one call of a Cranelift-compiled time loop
    // (t and the double-buffered state handled inside). Forward runs (with a VTK-free,
    // windowed-loss scene) and checkpointed gradients, whose backward pass recomputes
    // segments through the loop, must equal stepping launch by launch to the bit.
    use softc::devices::cpu::Cpu;
    use softc::engine::adjoint::{Checkpointing, GradOptions};
    use softc_compiler::back::Precision;
    let scene = Scene::load(
        &root().join("runtime/tests/fixtures/grad/all_kinds.soft"),
        &[],
    )
    .unwrap();
    let module = &scene.lowered.adjoint.module;
    let options = GradOptions {
        checkpoint: Checkpointing::Periodic(37),
        ..GradOptions::default()
    };
    for precision in [Precision::F64, Precision::F32] {
        let cpu = |looped: bool| {
            let mut c = Cpu::new(module, precision, Some(1)).unwrap();
            c.set_step_loop(looped);
            c
        };
        let fwd = |looped| {
            Simulation::new(&scene, cpu(looped))
                .run(None, Some(230))
                .unwrap()
        };
        let (a, b) = (fwd(true), fwd(false));
        assert_eq!(a.x, b.x, "{precision}: positions");
        assert_eq!(a.v, b.v, "{precision}: velocities");
        assert_eq!(a.loss.unwrap().to_bits(), b.loss.unwrap().to_bits());
        assert!(a.x != scene.mesh.nodes, "the scene moved");
        let grad = |looped| {
            Simulation::new(&scene, cpu(looped))
                .gradient(None, Some(230), &options)
                .unwrap()
        };
        let (ga, gb) = (grad(true), grad(false));
        assert!(ga.recompute_ratio > 1.0, "segments were recomputed");
        for (name, g) in &gb.gradients {
            assert_eq!(
                ga.gradients[name].to_bits(),
                g.to_bits(),
                "{precision}: {name}"
            );
        }
    }
    // Steady-state runs step between their checks through the loop too.
    let scene = Scene::load(&root().join("examples/benchmark-1k.soft"), &[]).unwrap();
    let module = &scene.lowered.module;
    let steady = |looped: bool| {
        let mut c = Cpu::new(module, Precision::F64, Some(1)).unwrap();
        c.set_step_loop(looped);
        Simulation::new(&scene, c)
            .run_to_steady_state(None, 3000, 1e-3)
            .unwrap()
    };
    let (a, b) = (steady(true), steady(false));
    assert_eq!(a.summary.steps, b.summary.steps);
    assert_eq!(a.summary.x, b.summary.x);
    // The loop on several threads (each launch in chunks claimed by whichever thread is free,
    // a chunk starting when the launches before it are done) equals one thread to the bit.
    for precision in [Precision::F64, Precision::F32] {
        let run = |threads| {
            let c = Cpu::new(module, precision, Some(threads)).unwrap();
            Simulation::new(&scene, c).run(None, Some(230)).unwrap()
        };
        let one = run(1);
        for threads in [2, 3] {
            let r = run(threads);
            assert_eq!(r.x, one.x, "{precision}, {threads} threads: positions");
            assert_eq!(r.v, one.v, "{precision}, {threads} threads: velocities");
        }
    }
}

/// Forward speed with and without the compiled time loop (a measurement, not a check):
/// `cargo test -p softc --test engine -- --ignored --nocapture time_loop_speed`.
#[test]
#[ignore]
fn time_loop_speed() {
    use softc::devices::cpu::Cpu;
    use softc_compiler::back::Precision;
    // The uniaxial cube (384 tets), where a step's host work weighs most.
    let fixtures = root().join("runtime/tests/fixtures/uniaxial");
    let cube = std::env::temp_dir().join(format!("softc-cube-{}.soft", std::process::id()));
    let text = std::fs::read_to_string(fixtures.join("uniaxial.soft")).unwrap();
    let text = text
        .replace(
            "MATERIAL",
            "neo_hookean(mu: 100 kPa, kappa: 1 MPa, density: 1000 kg/m^3)",
        )
        .replace("\"cube.msh\"", &format!("{:?}", fixtures.join("cube.msh")));
    std::fs::write(&cube, text).unwrap();
    for (script, steps) in [
        (cube.to_str().unwrap(), 20000),
        ("runtime/tests/fixtures/grad/all_kinds.soft", 4000),
        ("examples/benchmark-1k.soft", 4000),
    ] {
        let scene = Scene::load(&root().join(script), &[]).unwrap();
        for precision in [Precision::F64, Precision::F32] {
            let mut rates = Vec::new();
            for looped in [false, true, false, true] {
                let mut c = Cpu::new(&scene.lowered.module, precision, Some(1)).unwrap();
                c.set_step_loop(looped);
                let mut sim = Simulation::new(&scene, c);
                sim.run(None, Some(200)).unwrap();
                sim.reset();
                let t = std::time::Instant::now();
                sim.run(None, Some(steps)).unwrap();
                rates.push(steps as f64 / t.elapsed().as_secs_f64());
            }
            eprintln!(
                "{script} {precision}: launch by launch {:.0} / {:.0} steps/s, time loop {:.0} / {:.0} steps/s",
                rates[0], rates[2], rates[1], rates[3]
            );
        }
    }
}

/// Mass scaling changes inertia only: a column hanging under gravity settles where it settles
/// without it (gravity acts on the physical mass; a scaled weight would stretch it 4× as far).
#[test]
fn mass_scaling_leaves_the_steady_state_under_gravity_unchanged() {
    let dir = std::env::temp_dir().join(format!("softc-scaled-column-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let plain = hanging_column_tip(&dir, [5, 1, 1], 0.12, "");
    // Four times the inertia: modes 2× slower, the overdamped ones 4× slower to settle.
    let scaled = hanging_column_tip(&dir, [5, 1, 1], 0.6, "mass_scaling = 4\n  ");
    std::fs::remove_dir_all(&dir).ok();
    let rel = ((scaled - plain) / plain).abs();
    assert!(
        rel < 1e-4,
        "mass_scaling = 4 moved the steady state: {scaled:e} m against {plain:e} m (rel. {rel:e})"
    );
}
