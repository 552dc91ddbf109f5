//! Quasi-static solves (`integrator = quasi_static`): the equilibrium agrees with a settled
//! explicit run, gradients by the implicit function theorem agree with central differences of
//! static solves for every param kind, and a load past what the body can carry stops with the
//! last equilibrium named.

use softc::devices::Backend;
use softc::devices::cpu::Cpu;
use softc::engine::Simulation;
use softc::engine::adjoint::{GradOptions, GradientReport};
use softc::engine::scene::Scene;
use softc_compiler::back::Precision;
use std::path::{Path, PathBuf};

fn root() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .parent()
        .unwrap()
        .to_path_buf()
}

fn scratch(name: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("softc-statics-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    dir.join(name)
}

/// A script on the 1k benchmark beam: `sim` is the sim block's body.
fn beam_script(name: &str, params: &str, sim: &str, loss: &str) -> PathBuf {
    let path = scratch(name);
    let text = format!(
        "mesh body = load(\"{}/meshes/bench_1k.msh\")\n\
         chamber cavity = surface(body, \"cavity\")\n\
         nodes base = named(body, \"base\")\n\
         nodes tip = named(body, \"tip\")\n\
         {params}\n\
         sim {{\n{sim}\n  fix base\n}}\n{loss}\n",
        root().display()
    );
    std::fs::write(&path, text).unwrap();
    path
}

fn static_loss(scene: &Scene, uniform: &str, value: f64) -> f64 {
    let cpu = Cpu::new(&scene.lowered.adjoint.module, Precision::F64, Some(1)).unwrap();
    let mut sim = Simulation::new(scene, cpu);
    sim.uniforms.set_named(uniform, value);
    sim.run(None, None).unwrap().loss.unwrap()
}

/// The largest relative difference between `gradients` and central differences (step 1e-4
/// of the value) of the solve's loss, over `params` (name, value).
fn worst_against_central_differences(
    scene: &Scene,
    gradients: &std::collections::BTreeMap<String, f64>,
    params: &[(&str, f64)],
) -> f64 {
    let mut worst: f64 = 0.0;
    for &(name, value) in params {
        let h = 1e-4 * f64::abs(value);
        let fd =
            (static_loss(scene, name, value + h) - static_loss(scene, name, value - h)) / (2.0 * h);
        let ad = gradients[name];
        let rel = ((ad - fd) / fd).abs();
        eprintln!("{name}: adjoint {ad:e}, central differences {fd:e}, relative {rel:e}");
        assert!(fd.abs() > 0.0, "{name} does not change the loss");
        worst = worst.max(rel);
    }
    worst
}

/// The gradient tests' every-param-kind scene as 8 backward Euler steps of 0.5 ms.
fn all_kinds_implicit(name: &str) -> PathBuf {
    let text = std::fs::read_to_string(root().join("runtime/tests/fixtures/grad/all_kinds.soft"))
        .unwrap()
        .replace(
            "  dt = 20 us\n  steps = 200\n",
            "  dt = 0.5 ms\n  steps = 8\n  integrator = implicit_euler\n",
        )
        .replace(
            "\"../../../../meshes/",
            &format!("\"{}/meshes/", root().display()),
        );
    assert!(text.contains("implicit_euler"));
    let path = scratch(name);
    std::fs::write(&path, text).unwrap();
    path
}

fn tip_mean_z(scene: &Scene, x: &[[f64; 3]]) -> f64 {
    let (_, tip) = scene.node_sets.iter().find(|(n, _)| n == "tip").unwrap();
    tip.iter()
        .map(|&i| x[i as usize][2] - scene.mesh.nodes[i as usize][2])
        .sum::<f64>()
        / tip.len() as f64
}

/// The static solve finds the state an explicit run settles to: the beam under pressure and
/// gravity, a damped explicit run of 150,000 steps (its motion died out long before), against
/// one static solve.
#[test]
fn the_static_equilibrium_is_where_an_explicit_run_settles() {
    let params = "material gel = neo_hookean(mu: 20 kPa, kappa: 0.2 MPa, density: 1070 kg/m^3)";
    let loads = "  use gel\n  gravity = [0, 0, -9.81] m/s^2\n  pressure cavity = 3 kPa";
    let explicit = beam_script(
        "explicit.soft",
        params,
        &format!("  dt = auto\n  duration = 1 s\n  damping = 60 /s\n  mass_scaling = 100\n{loads}"),
        "",
    );
    let quasi = beam_script(
        "static.soft",
        params,
        &format!("  integrator = quasi_static\n  duration = 1 s\n{loads}"),
        "",
    );
    let e_scene = Scene::load(&explicit, &[]).unwrap();
    let cpu = Cpu::new(&e_scene.lowered.module, Precision::F64, Some(1)).unwrap();
    let settled = Simulation::new(&e_scene, cpu)
        .run_to_steady_state(None, 150_000, 1e-7)
        .unwrap();
    let s_scene = Scene::load(&quasi, &[]).unwrap();
    let cpu = Cpu::new(&s_scene.lowered.adjoint.module, Precision::F64, Some(1)).unwrap();
    let solved = Simulation::new(&s_scene, cpu).run(None, None).unwrap();
    let solver = solved.solver.clone().unwrap();
    assert!(solver.converged, "{solver:?}");
    let (ze, zs) = (
        tip_mean_z(&e_scene, &settled.summary.x),
        tip_mean_z(&s_scene, &solved.x),
    );
    let rel = ((ze - zs) / zs).abs();
    eprintln!(
        "tip mean z: explicit {ze:e} m ({} steps, settled: {}), static {zs:e} m ({} Newton iterations); \
         relative difference {rel:e}",
        settled.summary.steps, settled.settled, solver.newton_iterations
    );
    // Large deformation (the tip moves ~17 mm); measured: 4.7e-12 after 400,000 steps.
    assert!(zs.abs() > 1e-3, "the load moved the tip: {zs}");
    assert!(rel < 1e-6, "explicit {ze} vs static {zs}: {rel:e}");
    // Every node, not only the tip's mean.
    let worst = settled
        .summary
        .x
        .iter()
        .zip(&solved.x)
        .map(|(a, b)| (0..3).map(|d| (a[d] - b[d]).abs()).fold(0.0, f64::max))
        .fold(0.0, f64::max);
    assert!(
        worst < 1e-6 * zs.abs() * 10.0,
        "largest node difference {worst:e} m"
    );
}

/// d loss / d param of a path of static states, by one transposed solve per state, against
/// central differences of static solves: a pressure, a material constant and controller
/// weights (through the pressure), with gravity and a windowed loss.
#[test]
fn static_gradients_match_central_differences_for_every_param_kind() {
    let path = root().join("runtime/tests/fixtures/grad/static.soft");
    let scene = Scene::load(&path, &[]).unwrap();
    let cpu = Cpu::new(&scene.lowered.adjoint.module, Precision::F64, Some(1)).unwrap();
    let report = Simulation::new(&scene, cpu)
        .gradient(None, None, &GradOptions::default())
        .unwrap();
    assert!(report.summary.solver.as_ref().unwrap().converged);
    let worst = worst_against_central_differences(
        &scene,
        &report.gradients,
        &[
            ("param.p0", 2e3),
            ("param.c10", 0.1e6),
            ("param.w.0", 200.0),
            ("param.w.1", -100.0),
        ],
    );
    assert!(worst < 1e-6, "worst relative difference {worst:e}");
}

/// A per-element param (a shear modulus per element of the half next to the clamp): the
/// derivative of each element's entry against central differences.
#[test]
fn static_gradients_of_a_per_element_param_match_central_differences() {
    let text = std::fs::read_to_string(root().join("runtime/tests/fixtures/grad/field.soft"))
        .unwrap()
        .replace(
            "  dt = 20 us\n  steps = 200\n  damping = 20 /s\n",
            "  integrator = quasi_static\n  duration = 2 ms\n",
        )
        .replace(
            "\"../../../../meshes/",
            &format!("\"{}/meshes/", root().display()),
        );
    assert!(text.contains("quasi_static"));
    let path = scratch("field_static.soft");
    std::fs::write(&path, text).unwrap();
    let scene = Scene::load(&path, &[]).unwrap();
    let cpu = Cpu::new(&scene.lowered.adjoint.module, Precision::F64, Some(1)).unwrap();
    let report = Simulation::new(&scene, cpu)
        .gradient(None, None, &GradOptions::default())
        .unwrap();
    let n = scene.fields[0].elements.len();
    let mut worst: f64 = 0.0;
    for i in [0, n / 2, n - 1] {
        let name = format!("param.mu.{i}");
        let (value, h) = (20e3, 2.0);
        let fd = (static_loss(&scene, &name, value + h) - static_loss(&scene, &name, value - h))
            / (2.0 * h);
        let ad = report.gradients[&name];
        let rel = ((ad - fd) / fd).abs();
        eprintln!("{name}: adjoint {ad:e}, central differences {fd:e}, relative {rel:e}");
        worst = worst.max(rel);
    }
    assert!(worst < 1e-5, "worst relative difference {worst:e}");
}

/// A pressure far beyond what the walls carry: the continuation stalls, and the error names
/// the last load at which an equilibrium was found instead of running on or crashing, and
/// what the tangent there says.
#[test]
fn a_load_beyond_the_limit_point_names_the_last_equilibrium() {
    let path = beam_script(
        "balloon.soft",
        "material gel = neo_hookean(mu: 5 kPa, kappa: 50 kPa, density: 1070 kg/m^3)",
        "  integrator = quasi_static\n  duration = 1 s\n  use gel\n  pressure cavity = 500 kPa",
        "",
    );
    let scene = Scene::load(&path, &[]).unwrap();
    let fail = |linear| {
        let cpu = Cpu::new(&scene.lowered.adjoint.module, Precision::F64, Some(1)).unwrap();
        let mut sim = Simulation::new(&scene, cpu);
        sim.linear_solver = linear;
        sim.run(None, None).unwrap_err().0
    };
    use softc::engine::statics::LinearSolver;
    let err = fail(LinearSolver::Direct);
    eprintln!("{err}");
    assert!(err.contains("no equilibrium found beyond"), "{err}");
    assert!(err.contains("% of the loads at t = 1 s"), "{err}");
    // An element turns inside out first, while the tangent keeps 14 % of its stiffness at
    // rest along the loads: not called a limit point outright (issue 29 item 1).
    assert!(
        err.contains("inverts element") && err.contains("may be approaching a limit point"),
        "{err}"
    );
    // Multigrid on the way to the limit point (its tangent turns indefinite): the same
    // last equilibrium, to the percent the message prints.
    let amg = fail(LinearSolver::Amg);
    let last = |e: &str| e.split(" % of the loads").next().unwrap().to_string();
    assert_eq!(last(&amg), last(&err), "{amg}");
}

/// Settings that do not affect a static solve are warned about, not silently ignored, and a
/// static script needs no `dt`.
#[test]
fn a_static_script_needs_no_time_step_and_is_warned_about_dynamic_settings() {
    let params = "material gel = neo_hookean(mu: 20 kPa, kappa: 0.2 MPa, density: 1070 kg/m^3)";
    let ok = beam_script(
        "no_dt.soft",
        params,
        "  integrator = quasi_static\n  duration = 1 s\n  use gel\n  pressure cavity = 1 kPa",
        "",
    );
    let text = std::fs::read_to_string(&ok).unwrap();
    let report = softc_compiler::check_source(&text, &Default::default());
    assert!(!report.has_errors(), "{:?}", report.diagnostics);
    let warned = beam_script(
        "damped.soft",
        params,
        "  integrator = quasi_static\n  duration = 1 s\n  damping = 20 /s\n  use gel\n  pressure cavity = 1 kPa",
        "",
    );
    let text = std::fs::read_to_string(&warned).unwrap();
    let report = softc_compiler::check_source(&text, &Default::default());
    assert!(
        report
            .diagnostics
            .iter()
            .any(|d| d.code == "W0005" && d.message.contains("`damping`")),
        "{:?}",
        report.diagnostics
    );
}

/// The gradient tests' every-kind scene (pressure, material constant, per-window damping,
/// controller weights, a windowed loss on positions and velocities) stepped by backward Euler
/// at 25× the explicit step: every derivative against central differences of implicit runs.
#[test]
fn implicit_euler_gradients_match_central_differences_for_every_param_kind() {
    let path = all_kinds_implicit("all_kinds_implicit.soft");
    let scene = Scene::load(&path, &[]).unwrap();
    let cpu = Cpu::new(&scene.lowered.adjoint.module, Precision::F64, Some(1)).unwrap();
    let report = Simulation::new(&scene, cpu)
        .gradient(None, None, &GradOptions::default())
        .unwrap();
    let solver = report.summary.solver.clone().unwrap();
    assert_eq!(solver.kind, "implicit_euler");
    let worst = worst_against_central_differences(
        &scene,
        &report.gradients,
        &[
            ("param.p0", 2e3),
            ("param.c10", 0.1e6),
            ("param.w.0", 200.0),
            ("param.w.1", -100.0),
            ("param.beta.0", 20.0),
            ("param.beta.3", 20.0),
        ],
    );
    assert!(worst < 1e-6, "worst relative difference {worst:e}");
}

/// Backward Euler is (at least) first order: halving dt halves its distance to a fine explicit
/// run of the same damped, ramp-loaded scene, from a step ~100× the explicit one.
#[test]
fn implicit_euler_converges_at_first_order_to_the_explicit_solution() {
    let params = "material gel = neo_hookean(mu: 20 kPa, kappa: 0.2 MPa, density: 1070 kg/m^3)";
    let loads = "  use gel\n  damping = 100 /s\n  pressure cavity = 1 kPa * ramp(t, 40 ms)";
    let tip = |path: &Path, dt: Option<f64>| {
        let scene = Scene::load(path, &[]).unwrap();
        let module = match scene.lowered.statics {
            Some(_) => &scene.lowered.adjoint.module,
            None => &scene.lowered.module,
        };
        let cpu = Cpu::new(module, Precision::F64, Some(1)).unwrap();
        let s = Simulation::new(&scene, cpu).run(dt, None).unwrap();
        tip_mean_z(&scene, &s.x)
    };
    let explicit = beam_script(
        "explicit_dyn.soft",
        params,
        &format!("  dt = auto(safety: 0.5)\n  duration = 40 ms\n{loads}"),
        "",
    );
    let implicit = beam_script(
        "implicit_dyn.soft",
        params,
        &format!("  dt = 2 ms\n  duration = 40 ms\n  integrator = implicit_euler\n{loads}"),
        "",
    );
    let reference = tip(&explicit, None);
    let errors: Vec<f64> = [2e-3, 1e-3, 0.5e-3]
        .iter()
        .map(|&dt| ((tip(&implicit, Some(dt)) - reference) / reference).abs())
        .collect();
    eprintln!("implicit Euler relative errors at dt = 2, 1, 0.5 ms: {errors:?}");
    let orders: Vec<f64> = errors.windows(2).map(|w| (w[0] / w[1]).log2()).collect();
    eprintln!("observed orders {orders:?}");
    // Measured: 2.2 %, 0.89 %, 0.30 % (orders 1.3 and 1.6: the ramp's transient is still
    // resolved better than first order predicts at these steps, ω·dt ≈ 0.1–0.4).
    assert!(errors[2] < 0.005, "{errors:?}");
    assert!(
        orders.iter().all(|&p| p > 0.9),
        "not first order: {orders:?}"
    );
}

/// A free body (no fixed node): a cube with a closed inner cavity, inflated. Its equilibrium
/// is defined up to a rigid motion; the solver holds the mean translation and rotation, so
/// it converges, the mean displacement is zero, the cube expands symmetrically, and the
/// gradient still matches central differences. Gravity on a free body is refused by name.
#[test]
fn a_free_body_under_balanced_loads_is_solved_and_unbalanced_ones_are_refused() {
    use softc::mesh::kuhn::{KuhnSpec, kuhn_grid};
    let spec = KuhnSpec {
        n: [6, 6, 6],
        min: [0.0; 3],
        max: [12.0; 3],
        cavity_min: [4.0; 3],
        cavity_max: [8.0; 3],
    };
    let mesh = kuhn_grid(&spec, softc::mesh::LengthUnit::Millimetre).unwrap();
    let file = scratch("hollow_cube.msh");
    softc::mesh::save(&mesh, &file, softc::mesh::LengthUnit::Millimetre).unwrap();
    let script = |name: &str, extra: &str| {
        let path = scratch(name);
        std::fs::write(
            &path,
            format!(
                "mesh body = load(\"{}\")\n\
                 material gel = neo_hookean(mu: 20 kPa, kappa: 0.2 MPa, density: 1070 kg/m^3)\n\
                 chamber cavity = surface(body, \"cavity\")\n\
                 nodes corner = select(body, x > 11.9 mm and y > 11.9 mm and z > 11.9 mm)\n\
                 param p: pressure = 4 kPa in [0 kPa, 20 kPa]\n\
                 sim {{\n  integrator = quasi_static\n  duration = 1 s\n  use gel\n  \
                 pressure cavity = p\n{extra}}}\n\
                 loss = sum(n in corner) (x[n].x - x0[n].x - 0.1 mm)^2 at end\n",
                file.display()
            ),
        )
        .unwrap();
        Scene::load(&path, &[]).unwrap()
    };
    let scene = script("free.soft", "");
    let cpu = Cpu::new(&scene.lowered.adjoint.module, Precision::F64, Some(1)).unwrap();
    let report = Simulation::new(&scene, cpu)
        .gradient(None, None, &GradOptions::default())
        .unwrap();
    let solver = report.summary.solver.clone().unwrap();
    assert!(solver.converged, "{solver:?}");
    // The pinned support keeps the stiffness symmetric and definite (multipliers made it
    // indefinite: LU).
    assert_eq!(solver.factorization, "cholesky");
    let n = scene.mesh.nodes.len() as f64;
    let u: Vec<[f64; 3]> = report
        .summary
        .x
        .iter()
        .zip(&scene.mesh.nodes)
        .map(|(x, x0)| [x[0] - x0[0], x[1] - x0[1], x[2] - x0[2]])
        .collect();
    let largest = u.iter().flatten().fold(0.0f64, |m, v| m.max(v.abs()));
    let mean: Vec<f64> = (0..3)
        .map(|d| u.iter().map(|v| v[d]).sum::<f64>() / n)
        .collect();
    eprintln!("free body: largest displacement {largest:e} m, mean {mean:?}, {solver:?}");
    assert!(largest > 1e-5, "the cavity pressure moved nothing");
    assert!(mean.iter().all(|m| m.abs() < 1e-9 * largest), "{mean:?}");
    // The far corner moves out equally along x, y and z (the cube's symmetry).
    let corner = scene.node_sets.iter().find(|(n, _)| n == "corner").unwrap();
    let c = &u[corner.1[0] as usize];
    assert!(c[0] > 0.0 && (c[0] - c[1]).abs() < 1e-6 * c[0] && (c[0] - c[2]).abs() < 1e-6 * c[0]);
    let worst = worst_against_central_differences(&scene, &report.gradients, &[("param.p", 4e3)]);
    assert!(worst < 1e-6, "worst relative difference {worst:e}");
    // Multigrid on the pinned support: the same pose and gradient.
    let cpu = Cpu::new(&scene.lowered.adjoint.module, Precision::F64, Some(1)).unwrap();
    let mut sim = Simulation::new(&scene, cpu);
    sim.linear_solver = softc::engine::statics::LinearSolver::Amg;
    let amg = sim.gradient(None, None, &GradOptions::default()).unwrap();
    assert_eq!(amg.summary.solver.clone().unwrap().linear_solver, "amg");
    assert_same_solution(&scene, &report, &amg, "amg");
    // f32, refined in f64 (issue 29 item 4) with steps free of rigid motion: the f64 pose's
    // displacements to what f32 positions hold (measured 3.7e-6 of the largest, the rounding;
    // chord steps stalled at a relative residual of 7e-6).
    let cpu = Cpu::new(&scene.lowered.adjoint.module, Precision::F32, Some(1)).unwrap();
    let f32_run = Simulation::new(&scene, cpu).run(None, None).unwrap();
    let f32_solver = f32_run.solver.unwrap();
    assert!(
        f32_solver.converged && f32_solver.relative_residual < 1e-8,
        "{f32_solver:?}"
    );
    let error = f32_run
        .x
        .iter()
        .flatten()
        .zip(report.summary.x.iter().flatten())
        .fold(0.0f64, |m, (a, b)| m.max((a - b).abs()));
    eprintln!(
        "f32 free body: error {:e} of the largest, {f32_solver:?}",
        error / largest
    );
    assert!(
        error < 1e-5 * largest,
        "f32 free body: {:e} of the largest",
        error / largest
    );

    let heavy = script("free_gravity.soft", "  gravity = [0, 0, -9.81] m/s^2\n");
    let cpu = Cpu::new(&heavy.lowered.adjoint.module, Precision::F64, Some(1)).unwrap();
    let err = Simulation::new(&heavy, cpu).run(None, None).unwrap_err().0;
    assert!(
        err.contains("no fixed node") && err.contains("do not balance"),
        "{err}"
    );
}

/// The iterative linear solvers find the direct solver's states and gradients, for a static
/// path of states and for backward Euler steps, every param kind: the matrix-free one (GMRES on
/// the tangent products the compiled kernels compute, block-Jacobi preconditioned: what the GPU
/// backend runs) and the multigrid one (CG on the assembled tangent preconditioned by
/// smoothed-aggregation AMG; GMRES for the closed loop's non-symmetric tangent).
#[test]
fn the_iterative_solvers_agree_with_the_direct_one() {
    use softc::engine::statics::LinearSolver;
    let closed_loop = root().join("runtime/tests/fixtures/closed_loop/static.soft");
    for (path, solvers) in [
        (
            root().join("runtime/tests/fixtures/grad/static.soft"),
            &[LinearSolver::Krylov, LinearSolver::Amg][..],
        ),
        (
            all_kinds_implicit("all_kinds_implicit_krylov.soft"),
            &[LinearSolver::Krylov, LinearSolver::Amg][..],
        ),
        (closed_loop, &[LinearSolver::Amg][..]),
    ] {
        let scene = Scene::load(&path, &[]).unwrap();
        let solve = |linear: LinearSolver| {
            let cpu = Cpu::new(&scene.lowered.adjoint.module, Precision::F64, Some(1)).unwrap();
            let mut sim = Simulation::new(&scene, cpu);
            sim.linear_solver = linear;
            sim.gradient(None, None, &GradOptions::default()).unwrap()
        };
        let direct = solve(LinearSolver::Direct);
        assert_eq!(
            direct.summary.solver.clone().unwrap().linear_solver,
            "direct"
        );
        for &linear in solvers {
            let iterative = solve(linear);
            let report = iterative.summary.solver.clone().unwrap();
            eprintln!("{}: {report:?}", path.display());
            let name = match linear {
                LinearSolver::Krylov => "krylov",
                _ => "amg",
            };
            assert_eq!(report.linear_solver, name);
            assert_eq!(report.factorizations, 0);
            assert!(report.converged && report.krylov_iterations > 0);
            if linear == LinearSolver::Amg {
                assert!(report.multigrid_setups >= 1 && report.multigrid_levels >= 1);
            }
            assert_same_solution(&scene, &direct, &iterative, name);
        }
    }
}

/// States within 1e-8 of the largest displacement, gradients within 1e-6 relative.
fn assert_same_solution(
    scene: &Scene,
    direct: &GradientReport,
    other: &GradientReport,
    name: &str,
) {
    let scale = direct
        .summary
        .x
        .iter()
        .zip(&scene.mesh.nodes)
        .map(|(x, x0)| (0..3).map(|d| (x[d] - x0[d]).abs()).fold(0.0, f64::max))
        .fold(0.0, f64::max);
    let moved = direct
        .summary
        .x
        .iter()
        .zip(&other.summary.x)
        .map(|(a, b)| (0..3).map(|d| (a[d] - b[d]).abs()).fold(0.0, f64::max))
        .fold(0.0, f64::max);
    assert!(
        moved <= 1e-8 * scale,
        "{name}: states differ by {moved:e} (scale {scale:e})"
    );
    for (param, d) in &direct.gradients {
        let k = other.gradients[param];
        let rel = (k - d).abs() / d.abs().max(1e-300);
        assert!(rel < 1e-6, "{param}: {name} {k:e}, direct {d:e}");
    }
}

/// The soft endoscope (meshes/endoscope_soft*.toml, Ecoflex 00-30) reaches the thesis' 5 mm
/// circle within the 20 kPa cap where its reach is least: between the bending directions of a
/// single chamber (c2) and of a pair (c2 + c3), here along +y (c2 at the cap, c3 at 15 kPa).
/// One static solve on the coarsest mesh of the design, the one `controller_synthesis_soft.soft`
/// trains on. Measured: 7.42 mm at -4.3 deg (7.40 mm at 0.5 deg with c3 at 16 kPa).
#[test]
fn the_soft_endoscope_reaches_the_thesis_circle_within_the_cap() {
    let path = scratch("soft_endoscope.soft");
    let text = format!(
        "mesh body = load(\"{}/meshes/endoscope_soft_coarse.msh\")\n\
         material ecoflex = neo_hookean(mu: 39.4 kPa, kappa: 1 MPa, density: 1070 kg/m^3)\n\
         chamber c2 = surface(body, \"c2\")\n\
         chamber c3 = surface(body, \"c3\")\n\
         nodes base = named(body, \"base\")\n\
         nodes tip = named(body, \"tip\")\n\
         sim {{\n  integrator = quasi_static\n  duration = 1 s\n  use ecoflex\n  fix base\n  \
         pressure c2 = 20 kPa\n  pressure c3 = 15 kPa\n}}\n",
        root().display()
    );
    std::fs::write(&path, text).unwrap();
    let scene = Scene::load(&path, &[]).unwrap();
    let cpu = Cpu::new(&scene.lowered.adjoint.module, Precision::F64, Some(1)).unwrap();
    let solved = Simulation::new(&scene, cpu).run(None, None).unwrap();
    let solver = solved.solver.clone().unwrap();
    assert!(solver.converged, "{solver:?}");
    let (_, tip) = scene.node_sets.iter().find(|(n, _)| n == "tip").unwrap();
    let mean = |d: usize| {
        tip.iter()
            .map(|&i| solved.x[i as usize][d] - scene.mesh.nodes[i as usize][d])
            .sum::<f64>()
            / tip.len() as f64
    };
    let (dy, dz) = (mean(1), mean(2));
    let angle = dz.atan2(dy).to_degrees();
    eprintln!(
        "tip mean displacement y {:.3} mm, z {:.3} mm ({angle:.1} deg); {} Newton iterations",
        dy * 1e3,
        dz * 1e3,
        solver.newton_iterations
    );
    assert!(
        angle.abs() < 15.0,
        "not between c2's and c2 + c3's directions: {angle} deg"
    );
    assert!(
        dy.hypot(dz) > 5e-3,
        "the tip moves only {} mm",
        dy.hypot(dz) * 1e3
    );
}

/// Issue 31 item 14: an implicit Euler run reported a residual of 0.0 whatever its steps
/// reached. The report now holds the worst step's residual, absolute and relative to that
/// step's predictor.
#[test]
fn implicit_euler_reports_its_worst_steps_residual() {
    let path = all_kinds_implicit("all_kinds_implicit_residual.soft");
    let scene = Scene::load(&path, &[]).unwrap();
    let cpu = Cpu::new(&scene.lowered.adjoint.module, Precision::F64, Some(1)).unwrap();
    let summary = Simulation::new(&scene, cpu).run(None, None).unwrap();
    let solver = summary.solver.unwrap();
    assert_eq!(solver.kind, "implicit_euler");
    assert!(solver.converged);
    assert!(
        solver.residual_norm > 0.0 && solver.residual_norm.is_finite(),
        "{}",
        solver.residual_norm
    );
    assert!(
        solver.relative_residual > 0.0 && solver.relative_residual <= 1e-6,
        "{}",
        solver.relative_residual
    );
}

/// A log line sink the test reads back.
#[derive(Clone, Default)]
struct Log(std::sync::Arc<std::sync::Mutex<Vec<u8>>>);

impl std::io::Write for Log {
    fn write(&mut self, b: &[u8]) -> std::io::Result<usize> {
        self.0.lock().unwrap().extend_from_slice(b);
        Ok(b.len())
    }
    fn flush(&mut self) -> std::io::Result<()> {
        Ok(())
    }
}

/// Issue 31 item 10: static and implicit runs of any length started silently (no progress,
/// no estimate of the time left), unlike explicit ones. Here the progress shows at once.
#[test]
fn static_and_implicit_runs_report_their_progress() {
    use softc::outputs::progress::Progress;
    use std::time::Duration;
    let static_path = beam_script(
        "progress_static.soft",
        "material rubber = neo_hookean(mu: 100 kPa, kappa: 1 MPa, density: 1070 kg/m^3)",
        "  integrator = quasi_static\n  duration = 1 s\n  steps = 3\n  \
         pressure cavity = 1 kPa * ramp(t, 1 s)",
        "",
    );
    let implicit_path = all_kinds_implicit("progress_implicit.soft");
    for (path, gradient, want) in [
        (
            &static_path,
            false,
            &[
                "quasi-static step 1/3",
                "quasi-static step 3/3",
                "Newton iteration 1, residual",
            ][..],
        ),
        (
            &implicit_path,
            true,
            &[
                "implicit step 1/8",
                "implicit step 8/8",
                "backward step 8/8",
            ][..],
        ),
    ] {
        let scene = Scene::load(path, &[]).unwrap();
        let cpu = Cpu::new(&scene.lowered.adjoint.module, Precision::F64, Some(1)).unwrap();
        let mut sim = Simulation::new(&scene, cpu);
        let log = Log::default();
        sim.progress = Some(Box::new(Progress::to_log(
            "run",
            Box::new(log.clone()),
            Duration::ZERO,
            Duration::ZERO,
        )));
        if gradient {
            sim.gradient(None, None, &GradOptions::default()).unwrap();
        } else {
            sim.run(None, None).unwrap();
        }
        let text = String::from_utf8(log.0.lock().unwrap().clone()).unwrap();
        for w in want {
            assert!(text.contains(w), "`{w}` missing from:\n{text}");
        }
        assert!(text.contains("s left"), "{text}");
    }
}

/// Issue 31 item 14, the static half: a converged solve whose loads are zero reported a
/// relative residual of 1.0 (its residual over the round-off of the rest forces). It is now
/// relative to the internal forces of a small deformation, and Newton does not chase
/// round-off.
#[test]
fn a_zero_load_static_solve_reports_a_small_relative_residual() {
    let path = beam_script(
        "zero_load.soft",
        "material rubber = neo_hookean(mu: 100 kPa, kappa: 1 MPa, density: 1070 kg/m^3)",
        "  integrator = quasi_static\n  duration = 1 s\n  steps = 2\n  \
         pressure cavity = 0 kPa * ramp(t, 1 s)",
        "",
    );
    let scene = Scene::load(&path, &[]).unwrap();
    let cpu = Cpu::new(&scene.lowered.adjoint.module, Precision::F64, Some(1)).unwrap();
    let summary = Simulation::new(&scene, cpu).run(None, None).unwrap();
    let solver = summary.solver.unwrap();
    assert!(solver.converged);
    assert!(
        solver.relative_residual < 1e-10,
        "relative residual {} (residual {} N)",
        solver.relative_residual,
        solver.residual_norm
    );
    assert_eq!(solver.newton_iterations, 0, "the rest state is the answer");
    let moved = summary
        .x
        .iter()
        .zip(&scene.mesh.nodes)
        .map(|(x, x0)| (0..3).map(|d| (x[d] - x0[d]).abs()).fold(0.0, f64::max))
        .fold(0.0, f64::max);
    assert!(moved < 1e-15, "moved {moved} m");
}

/// Issue 29, hostile case 1: static (and implicit) solves never checked the material: E = 0
/// returned the rest state with "converged", E < 0 and ν = 0.7 unstable stationary points, all
/// with exit 0. Now the solve refuses to start, naming the constants to check.
#[test]
fn static_and_implicit_solves_refuse_non_physical_materials() {
    for (i, (constants, integrator)) in [
        ("mu: 0 kPa, kappa: 0 MPa", "quasi_static"),
        ("mu: -100 kPa, kappa: 1 MPa", "quasi_static"),
        (
            "mu: lame_mu(100 kPa, 0.7), kappa: bulk_modulus(100 kPa, 0.7)",
            "quasi_static",
        ),
        (
            "mu: lame_mu(100 kPa, -1.5), kappa: bulk_modulus(100 kPa, -1.5)",
            "implicit_euler",
        ),
    ]
    .into_iter()
    .enumerate()
    {
        let time = if integrator == "quasi_static" {
            "duration = 1 s"
        } else {
            "dt = 10 ms\n  steps = 4"
        };
        let path = beam_script(
            &format!("non_physical_{i}.soft"),
            &format!("material rubber = neo_hookean({constants}, density: 1070 kg/m^3)"),
            &format!(
                "  integrator = {integrator}\n  {time}\n  pressure cavity = 3 kPa * ramp(t, 1 s)"
            ),
            "",
        );
        let scene = Scene::load(&path, &[]).unwrap();
        let cpu = Cpu::new(&scene.lowered.adjoint.module, Precision::F64, Some(1)).unwrap();
        let e = Simulation::new(&scene, cpu).run(None, None).unwrap_err().0;
        assert!(
            e.contains(&format!("the {integrator} solve cannot start"))
                && e.contains("material constants are not physical"),
            "{constants}: {e}"
        );
    }
}

/// A static body held at one node, or along one line of nodes, is free to rotate about it
/// (it returned an arbitrary rotation, then was refused): the solve holds that rotation, warns,
/// and poses the equilibrium to best match the rest shape about the fixed nodes. Its
/// deformation is the free body's (balanced loads put no reaction on the fixed nodes): moved
/// rigidly onto the rest shape, both answers coincide. The gradient follows the pose
/// convention (central differences), and a load with a moment about the fixed point is refused.
#[test]
fn a_static_body_free_to_rotate_about_its_fixed_nodes_is_held_and_posed() {
    use softc::solvers::sparse::{BlockPattern, align_to};
    let material = "material rubber = neo_hookean(mu: 100 kPa, kappa: 1 MPa, density: 1070 kg/m^3)";
    let script = |name: &str, pin: Option<&str>, extra: &str| {
        let path = scratch(name);
        let (nodes, fix) = match pin {
            Some(pin) => (format!("nodes pin = select(body, {pin})\n"), "  fix pin\n"),
            None => (String::new(), ""),
        };
        let text = format!(
            "mesh body = load(\"{}/meshes/bench_1k.msh\")\n{material}\n\
             chamber cavity = surface(body, \"cavity\")\n{nodes}\
             nodes far = select(body, x > 59.9 mm)\n\
             param p: pressure = 20 kPa in [0 kPa, 50 kPa]\n\
             sim {{\n  integrator = quasi_static\n  duration = 1 s\n{fix}{extra}  \
             pressure cavity = p * ramp(t, 1 s)\n}}\n\
             loss = mean(n in far) (x[n].z - x0[n].z)^2 at end\n",
            root().display()
        );
        std::fs::write(&path, text).unwrap();
        Scene::load(&path, &[]).unwrap()
    };
    let solve = |scene: &Scene| {
        let cpu = Cpu::new(&scene.lowered.adjoint.module, Precision::F64, Some(1)).unwrap();
        Simulation::new(scene, cpu)
            .gradient(None, None, &GradOptions::default())
            .unwrap()
    };
    let free = solve(&script("free_1k.soft", None, ""));
    let rest = &script("free_1k.soft", None, "").mesh.nodes.clone();
    let flat = |x: &[[f64; 3]]| x.iter().flatten().copied().collect::<Vec<f64>>();
    for (i, (pin, kind)) in [
        ("x < 0.1 mm and y < 0.1 mm and z < 0.1 mm", "point"),
        ("x < 0.1 mm and y < 0.1 mm", "line"),
    ]
    .into_iter()
    .enumerate()
    {
        let scene = script(&format!("pinned_{i}.soft"), Some(pin), "");
        let report = solve(&scene);
        let solver = report.summary.solver.clone().unwrap();
        assert!(solver.converged, "{solver:?}");
        assert_eq!(solver.free_motion_kind, Some(kind));
        let warning = softc::session::run_warning(&scene, &report.summary).unwrap();
        assert!(warning.contains("free to rotate"), "{warning}");
        let x = flat(&report.summary.x);
        let reference = flat(&free.summary.x);
        let largest = reference
            .iter()
            .zip(flat(rest))
            .map(|(a, b)| (a - b).abs())
            .fold(0.0, f64::max);
        let apart = |a: &[f64], b: &[f64]| {
            a.iter()
                .zip(b)
                .map(|(p, q)| (p - q).abs())
                .fold(0.0, f64::max)
        };
        // Posed: the best rotation about the fixed nodes onto the rest shape is the identity.
        let pattern = BlockPattern::new(
            &scene.fixed,
            (&scene.elem_conn(), 4),
            (&scene.tri_conn(), 3),
            true,
            rest,
        )
        .unwrap();
        let again = apart(&pattern.align(rest, &x), &x);
        assert!(again < 1e-9 * largest, "{kind}: {again:e} of {largest:e}");
        // One fixed node takes no reaction from balanced loads: moved rigidly onto the rest
        // shape, the answer is the free body's (a fixed line also holds the edge's length).
        if kind == "point" {
            let d = apart(&align_to(rest, &x), &reference);
            assert!(d < 1e-6 * largest, "{kind}: {d:e} of {largest:e}");
        }
        let worst =
            worst_against_central_differences(&scene, &report.gradients, &[("param.p", 20e3)]);
        assert!(worst < 1e-6, "{kind}: worst relative difference {worst:e}");
    }
    // A load with a moment about the fixed point has no equilibrium.
    let heavy = script(
        "pinned_gravity.soft",
        Some("x < 0.1 mm and y < 0.1 mm and z < 0.1 mm"),
        "  gravity = [0, 0, -9.81] m/s^2\n",
    );
    let cpu = Cpu::new(&heavy.lowered.adjoint.module, Precision::F64, Some(1)).unwrap();
    let err = Simulation::new(&heavy, cpu).run(None, None).unwrap_err().0;
    assert!(
        err.contains("one point") && err.contains("do not balance"),
        "{err}"
    );
}

/// Issue 29, hostile case 2 and build item 4: an f32 static solve at 1 Pa stopped at the rest
/// state (1/140 of the answer) and said `converged: true`; at 3 kPa it "converged" at a
/// relative residual of 5.6e-4 against the stated 1e-5. f32 equilibria are now refined with
/// residuals evaluated in f64: `converged` means the stated tolerance is met, and the stored
/// displacements equal the f64 solve's to what f32 positions hold.
#[test]
fn an_f32_static_solve_meets_its_stated_tolerance_by_refinement_in_f64() {
    let solve = |pressure: &str, precision: Precision| {
        let path = beam_script(
            &format!("f32_{}.soft", pressure.replace(' ', "")),
            "material rubber = neo_hookean(mu: 100 kPa, kappa: 1 MPa, density: 1070 kg/m^3)",
            &format!(
                "  integrator = quasi_static\n  duration = 1 s\n  \
                 pressure cavity = {pressure} * ramp(t, 1 s)"
            ),
            "",
        );
        let scene = Scene::load(&path, &[]).unwrap();
        let cpu = Cpu::new(&scene.lowered.adjoint.module, precision, Some(1)).unwrap();
        let mut sim = Simulation::new(&scene, cpu);
        let summary = sim.run(None, None).unwrap();
        let warning = softc::session::run_warning(&scene, &summary);
        let rest = scene.mesh.nodes.iter().flatten();
        let u: Vec<f64> = sim
            .backend
            .get(scene.lowered.buffers.x)
            .iter()
            .zip(rest)
            .map(|(x, x0)| x - x0)
            .collect();
        (summary.solver.unwrap(), warning, u)
    };
    for pressure in ["1 Pa", "3 kPa", "20 kPa"] {
        let (f64_solve, warning, u64) = solve(pressure, Precision::F64);
        assert!(
            f64_solve.converged && f64_solve.relative_residual < 1e-8,
            "{f64_solve:?}"
        );
        assert!(warning.is_none());
        let (f32_solve, warning, u32) = solve(pressure, Precision::F32);
        // The largest displacement error against the largest displacement.
        let largest = u64.iter().fold(0.0f64, |m, v| m.max(v.abs()));
        let error = u64
            .iter()
            .zip(&u32)
            .fold(0.0f64, |m, (a, b)| m.max((a - b).abs()))
            / largest;
        eprintln!("{pressure}: f32 displacement error {error:e} of the largest, {f32_solve:?}");
        assert!(f32_solve.refinement_steps >= 1, "{pressure}: {f32_solve:?}");
        // The refined equilibrium meets the stated tolerance; storing it in f32 rounds it.
        assert!(
            f32_solve.relative_residual <= 1e-5,
            "{pressure}: {f32_solve:?}"
        );
        assert!(
            error <= 1.5 * f32_solve.position_round_off,
            "{pressure}: {error:e} against {:e}",
            f32_solve.position_round_off
        );
        if pressure == "1 Pa" {
            // Displacements of ~1e-8 m on coordinates of centimetres: f32 holds them to ~8 %
            // (unrefined: the rest state, 99.5 % off).
            assert!(!f32_solve.converged, "{f32_solve:?}");
            assert!(error < 0.2, "{error:e}");
            assert!(
                warning
                    .is_some_and(|w| w.contains("round-off of f32 positions") && w.contains("f64")),
                "no warning"
            );
        } else {
            // Unrefined, 3 kPa stopped at 7.6e-4 of its loads and 2.8e-4 of its displacements.
            assert!(f32_solve.converged, "{pressure}: {f32_solve:?}");
            assert!(error < 1e-4, "{pressure}: {error:e}");
            assert!(warning.is_none(), "{pressure}: {warning:?}");
        }
    }
}

/// Issue 29, hostile case 5: implicit Euler gave up on a step whose Newton solve failed ("use
/// a smaller dt"). A failing step is now retried in halves (down to 1/64 of the step) and the
/// size grows back; the gradient follows the substeps taken. Here a step load of 25 kPa on a
/// soft beam at dt = 50 ms needs them (it failed at step 1 before).
#[test]
fn implicit_euler_halves_a_step_newton_cannot_take_and_differentiates_the_substeps() {
    let path = beam_script(
        "implicit_substeps.soft",
        "material rubber = neo_hookean(mu: 30 kPa, kappa: 0.3 MPa, density: 1070 kg/m^3)\n\
         param p_peak: pressure = 25 kPa in [0 kPa, 50 kPa]",
        "  integrator = implicit_euler\n  dt = 50 ms\n  duration = 0.5 s\n  \
         pressure cavity = p_peak",
        "loss = mean(n in tip) (x[n].z - x0[n].z)^2 at end",
    );
    let scene = Scene::load(&path, &[]).unwrap();
    let run = |p: f64| {
        let cpu = Cpu::new(&scene.lowered.adjoint.module, Precision::F64, Some(1)).unwrap();
        let mut sim = Simulation::new(&scene, cpu);
        sim.uniforms.set_named("param.p_peak", p);
        let s = sim.run(None, None).unwrap();
        (s.loss.unwrap(), s.solver.unwrap().rejected_load_steps)
    };
    let cpu = Cpu::new(&scene.lowered.adjoint.module, Precision::F64, Some(1)).unwrap();
    let report = Simulation::new(&scene, cpu)
        .gradient(None, None, &GradOptions::default())
        .unwrap();
    let solver = report.summary.solver.clone().unwrap();
    assert!(solver.rejected_load_steps > 0, "no substeps: {solver:?}");
    assert_eq!(report.summary.steps, 10);
    // Which steps Newton fails on depends on the load; central differences are taken where
    // both sides take the same substeps as the run.
    let g = report.gradients["param.p_peak"];
    let (_, rejected) = run(25e3);
    let mut compared = false;
    for h in [2.5e-3, 2.5e-4, 2.5e-5] {
        let ((lo, r_lo), (hi, r_hi)) = (run(25e3 - h), run(25e3 + h));
        if r_lo != rejected || r_hi != rejected {
            continue;
        }
        let fd = (hi - lo) / (2.0 * h);
        assert!(
            ((g - fd) / fd).abs() < 1e-5,
            "adjoint {g:e}, central differences {fd:e}"
        );
        compared = true;
        break;
    }
    assert!(compared, "no step with the run's substeps on both sides");
}

/// Issue 29, hostile case 4: a stiff insert (1 GPa in 0.1 MPa rubber, a strain-limiting layer)
/// stopped at "no equilibrium beyond 0.0 % of the loads … a limit point" under a linear-range
/// load: Newton chased the round-off of the insert's large internal forces. Now the tolerance
/// has that round-off as its floor, and the state is found.
#[test]
fn a_stiff_insert_in_soft_rubber_solves_statically() {
    let path = beam_script(
        "stiff_insert.soft",
        "material rubber = neo_hookean(mu: lame_mu(0.1 MPa, 0.45), kappa: bulk_modulus(0.1 MPa, 0.45), density: 1070 kg/m^3)\n\
         material stiff = neo_hookean(mu: lame_mu(1 GPa, 0.3), kappa: bulk_modulus(1 GPa, 0.3), density: 1070 kg/m^3)\n\
         elements insert = select(body, x > 20 mm and x < 40 mm and z < 3 mm)",
        "  integrator = quasi_static\n  duration = 1 s\n  use rubber\n  use stiff in insert\n  \
         pressure cavity = 3 kPa * ramp(t, 1 s)",
        "",
    );
    let scene = Scene::load(&path, &[]).unwrap();
    let cpu = Cpu::new(&scene.lowered.adjoint.module, Precision::F64, Some(1)).unwrap();
    let summary = Simulation::new(&scene, cpu).run(None, None).unwrap();
    let solver = summary.solver.unwrap();
    assert!(
        solver.converged && solver.relative_residual < 1e-8,
        "{solver:?}"
    );
    let tip = tip_mean_z(&scene, &summary.x);
    // The insert sits under the cavity: the beam still bends down (-0.15 mm measured).
    assert!(tip < -1e-4 && tip > -2e-4, "tip {tip} m");
}

/// The material check runs once per material values: an optimization whose trained param is a
/// material constant is checked again when it changes (and one that trains pressures is not).
#[test]
fn the_material_check_follows_a_trained_material_constant() {
    let path = beam_script(
        "trained_mu.soft",
        "param mu: pressure = 100 kPa\n\
         material rubber = neo_hookean(mu: mu, kappa: 1 MPa, density: 1070 kg/m^3)",
        "  integrator = quasi_static\n  duration = 1 s\n  pressure cavity = 1 kPa * ramp(t, 1 s)",
        "",
    );
    let scene = Scene::load(&path, &[]).unwrap();
    let cpu = Cpu::new(&scene.lowered.adjoint.module, Precision::F64, Some(1)).unwrap();
    let mut sim = Simulation::new(&scene, cpu);
    assert!(sim.run(None, None).is_ok());
    sim.uniforms.set_named("param.mu", -100e3);
    let e = sim.run(None, None).unwrap_err().0;
    assert!(e.contains("material constants are not physical"), "{e}");
    sim.uniforms.set_named("param.mu", 50e3);
    assert!(sim.run(None, None).is_ok());
}

/// `--linear-solver auto` (the default) factors a tangent up to the threshold and solves a
/// larger one by multigrid; for quadratic elements of a nearly incompressible material (where
/// multigrid's CG crawls) up to a larger one; an explicit choice stays what it is.
#[test]
fn auto_factors_small_tangents_and_uses_multigrid_beyond_the_threshold() {
    use softc::engine::statics::{
        AUTO_DIRECT_BULK_TO_SHEAR, AUTO_MULTIGRID_DOFS, AUTO_MULTIGRID_DOFS_NEARLY_INCOMPRESSIBLE,
        AUTO_MULTIGRID_DOFS_QUADRATIC, LinearSolver,
    };
    use softc_compiler::ir::ElementOrder::{Linear, Quadratic};
    assert_eq!(LinearSolver::default(), LinearSolver::Auto);
    let auto = LinearSolver::Auto;
    let everyday = || 4.0;
    let nearly_incompressible = || AUTO_DIRECT_BULK_TO_SHEAR;
    let unasked = || -> f64 { panic!("K/μ asked for where it does not decide") };
    assert_eq!(
        auto.resolve(AUTO_MULTIGRID_DOFS, Linear, unasked),
        LinearSolver::Direct
    );
    assert_eq!(
        auto.resolve(AUTO_MULTIGRID_DOFS + 1, Linear, unasked),
        LinearSolver::Amg
    );
    // Quadratic tangents fill more when factored: multigrid from fewer dofs on.
    const { assert!(AUTO_MULTIGRID_DOFS_QUADRATIC < AUTO_MULTIGRID_DOFS) };
    assert_eq!(
        auto.resolve(AUTO_MULTIGRID_DOFS_QUADRATIC, Quadratic, unasked),
        LinearSolver::Direct
    );
    assert_eq!(
        auto.resolve(AUTO_MULTIGRID_DOFS_QUADRATIC + 1, Quadratic, everyday),
        LinearSolver::Amg
    );
    // Unless the material is nearly incompressible.
    assert_eq!(
        auto.resolve(
            AUTO_MULTIGRID_DOFS_QUADRATIC + 1,
            Quadratic,
            nearly_incompressible
        ),
        LinearSolver::Direct
    );
    assert_eq!(
        auto.resolve(
            AUTO_MULTIGRID_DOFS_NEARLY_INCOMPRESSIBLE + 1,
            Quadratic,
            nearly_incompressible
        ),
        LinearSolver::Amg
    );
    assert_eq!(
        LinearSolver::Direct.resolve(10 * AUTO_MULTIGRID_DOFS, Quadratic, unasked),
        LinearSolver::Direct
    );
    assert_eq!(
        LinearSolver::Amg.resolve(9, Linear, unasked),
        LinearSolver::Amg
    );
}

/// Issue 29, hostile case 4's other half: ν → 0.5 with linear tetrahedra converged to a locked
/// answer with exit 0 (the verification cuboid's tip at ν = 0.4999: +0.7 µm against −8.5 µm
/// with quadratic elements). The run now warns, naming the material and its measured K/μ,
/// for any strain energy (a built-in or a script's own `W`); not at everyday ratios, nor for
/// quadratic elements.
#[test]
fn nearly_incompressible_linear_tetrahedra_are_warned_about() {
    use softc::engine::incompressibility::{bulk_to_shear, locking_warning};
    let scene_for = |name: &str, material: &str| {
        let path = beam_script(
            name,
            material,
            "  integrator = quasi_static\n  duration = 1 s\n  \
             pressure cavity = 1 kPa * ramp(t, 1 s)",
            "",
        );
        Scene::load(&path, &[]).unwrap()
    };
    for (nu, warned) in [(0.45, false), (0.49, false), (0.499, true), (0.4999, true)] {
        let scene = scene_for(
            &format!("nu_{nu}.soft"),
            &format!(
                "material rubber = neo_hookean(mu: lame_mu(1 MPa, {nu}), kappa: \
                 bulk_modulus(1 MPa, {nu}), density: 1070 kg/m^3)"
            ),
        );
        let exact = 2.0 * (1.0 + nu) / (3.0 * (1.0 - 2.0 * nu));
        let measured = bulk_to_shear(&scene);
        assert_eq!(measured.len(), 1);
        assert_eq!(measured[0].material, "rubber");
        let ratio = measured[0].ratio;
        eprintln!("ν = {nu}: K/μ {ratio} against {exact}");
        assert!(
            (ratio / exact - 1.0).abs() < 1e-3,
            "ν = {nu}: {ratio} against {exact}"
        );
        assert!(
            (measured[0].poisson() - nu).abs() < 1e-4,
            "{}",
            measured[0].poisson()
        );
        let warning = locking_warning(&scene);
        assert_eq!(warning.is_some(), warned, "ν = {nu}: {warning:?}");
        if let Some(w) = warning {
            assert!(w.contains("`rubber`") && w.contains("order 2"), "{w}");
        }
    }
    // A script's own W with the same small-strain moduli (μ = 100 kPa, K = 500 MPa).
    let own = scene_for(
        "own_w.soft",
        "material gel {\n  density = 1000 kg/m^3\n  \
         W(I1bar, J) = 50 kPa * (I1bar - 3) + 250 MPa * (J - 1)^2\n}",
    );
    let ratio = bulk_to_shear(&own)[0].ratio;
    assert!((ratio / 5000.0 - 1.0).abs() < 1e-3, "{ratio}");
    assert!(locking_warning(&own).is_some());
    // At a run's param values (what `auto` decides by): a trained shear modulus.
    let trained = scene_for(
        "trained_mu.soft",
        "param mu: pressure = 100 kPa
         material rubber = neo_hookean(mu: mu, kappa: 1 MPa, density: 1070 kg/m^3)",
    );
    let cpu = Cpu::new(&trained.lowered.adjoint.module, Precision::F64, Some(1)).unwrap();
    let mut sim = Simulation::new(&trained, cpu);
    sim.uniforms.set_named("param.mu", 1e3);
    let at = |u| softc::engine::incompressibility::bulk_to_shear_at(&trained, u)[0].ratio;
    assert!((at(None) / 10.0 - 1.0).abs() < 1e-3, "{}", at(None));
    assert!((at(Some(&sim.uniforms)) / 1000.0 - 1.0).abs() < 1e-3);
}
