//! Scenes of quadratic (10-node) tetrahedra (`load(…, order: 2)`): a coarse cantilever bends as
//! beam theory says where linear tets lock; gradients of every param kind match central
//! differences through explicit runs and static solves; the interpreter and the Cranelift
//! backend give the same bits.

mod common;

use softc::devices::cpu::Cpu;
use softc::devices::interp::Interpreter;
use softc::engine::Simulation;
use softc::engine::adjoint::GradOptions;
use softc::engine::scene::Scene;
use softc::mesh::kuhn::{KuhnSpec, kuhn_grid};
use softc::mesh::{LengthUnit, save};
use softc_compiler::back::Precision;
use softc_compiler::ir::ElementOrder;
use std::path::{Path, PathBuf};

fn scratch(name: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("softc-quadratic-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    dir.join(name)
}

/// The tip's mean z displacement of a static cantilever 60 × 10 × 10 mm of `cells` Kuhn cells,
/// clamped at x = 0, under its weight at g/10 (E = 1 MPa, ν = 0.3, ρ = 1000 kg/m³).
fn cantilever_tip(cells: [usize; 3], order: u32) -> f64 {
    let spec = KuhnSpec {
        n: cells,
        min: [0.0; 3],
        max: [60.0, 10.0, 10.0],
        // No cavity: a solid beam.
        cavity_min: [100.0; 3],
        cavity_max: [101.0; 3],
    };
    let mesh = kuhn_grid(&spec, LengthUnit::Millimetre).unwrap();
    let name = format!("beam_{}_{}_{}", cells[0], cells[1], cells[2]);
    static_loss(
        &mesh,
        &name,
        order,
        "material m = neo_hookean(mu: 384.615385 kPa, kappa: 833.333333 kPa, density: 1000 kg/m^3)\n\
         nodes base = named(body, \"base\")\n\
         nodes tip = named(body, \"tip\")\n\
         sim {\n  integrator = quasi_static\n  duration = 1 s\n  gravity = [0, 0, -0.981] m/s^2\n  \
         precision = f64\n  use m\n  fix base\n}\n\
         loss = mean(n in tip) (x[n].z - x0[n].z)\n",
    )
}

/// The loss of a static scene on `mesh` loaded at `order` (written as `NAME.msh` and
/// `NAME_ORDER.soft` in the scratch folder), `rest` the script after its `mesh` line; the
/// solve must converge.
fn static_loss(mesh: &softc::mesh::Mesh, name: &str, order: u32, rest: &str) -> f64 {
    let msh = scratch(&format!("{name}.msh"));
    save(mesh, &msh, LengthUnit::Millimetre).unwrap();
    let script = scratch(&format!("{name}_{order}.soft"));
    let text = format!(
        "mesh body = load(\"{}\", order: {order})\n{rest}",
        msh.display()
    );
    std::fs::write(&script, text).unwrap();
    let scene = Scene::load(&script, &[]).unwrap();
    let want = if order == 2 {
        ElementOrder::Quadratic
    } else {
        ElementOrder::Linear
    };
    assert_eq!(scene.order(), want);
    let cpu = Cpu::new(&scene.lowered.adjoint.module, Precision::F64, None).unwrap();
    let out = Simulation::new(&scene, cpu).run(None, None).unwrap();
    assert!(out.solver.as_ref().unwrap().converged);
    out.loss.unwrap()
}

/// Two cells through the depth: linear tets lock (about half the deflection), quadratic ones
/// reach Timoshenko's uniformly loaded cantilever, δ = qL⁴/(8EI) + qL²/(2κGA), within a few
/// per cent (the clamped face, held in all directions, stiffens the 3-D beam slightly).
#[test]
fn a_coarse_quadratic_cantilever_bends_as_beam_theory_says_where_linear_tets_lock() {
    let (e, nu, rho, g, l, h): (f64, f64, f64, f64, f64, f64) =
        (1e6, 0.3, 1000.0, 0.981, 0.06, 0.01);
    let (a, i) = (h * h, h * h * h * h / 12.0);
    let q = rho * g * a;
    let shear = q * l * l / (2.0 * (5.0 / 6.0) * e / (2.0 * (1.0 + nu)) * a);
    let timoshenko = q * l.powi(4) / (8.0 * e * i) + shear;
    let linear = -cantilever_tip([12, 2, 2], 1);
    let quadratic = -cantilever_tip([12, 2, 2], 2);
    eprintln!(
        "tip deflection: Timoshenko {timoshenko:e} m, linear tets {linear:e} ({:.1} %), \
         quadratic {quadratic:e} ({:.1} %)",
        100.0 * linear / timoshenko,
        100.0 * quadratic / timoshenko
    );
    // Measured: linear 50.6 %, quadratic 97.7 %.
    assert!(
        linear < 0.6 * timoshenko,
        "linear tets did not lock: {linear}"
    );
    assert!(
        (quadratic / timoshenko - 1.0).abs() < 0.04,
        "quadratic {quadratic} vs Timoshenko {timoshenko}"
    );
}

/// The gradient tests' every-param-kind scene with elements of `order`, `edits` applied.
fn every_kind(order: u32, name: &str, edits: &[(&str, &str)]) -> PathBuf {
    let mut text = common::script_at_order("runtime/tests/fixtures/grad/all_kinds.soft", order);
    for (from, to) in edits {
        assert!(text.contains(from), "{from}");
        text = text.replace(from, to);
    }
    assert!(text.contains(&format!("order: {order}")));
    let path = scratch(name);
    std::fs::write(&path, text).unwrap();
    path
}

/// The every-param-kind scene on quadratic elements.
fn all_kinds(name: &str, edits: &[(&str, &str)]) -> PathBuf {
    every_kind(2, name, edits)
}

/// The every-param-kind scene as one static solve: damping has no effect there (its window
/// params go), the controller and the material stay.
const STATIC: [(&str, &str); 5] = [
    ("param beta: rate[4] = 20 /s in [0 /s, 200 /s]\n", ""),
    ("  damping = beta[window(t, 1 ms)]\n", ""),
    (
        "  dt = 20 us\n  steps = 200\n",
        "  integrator = quasi_static\n  duration = 4 ms\n",
    ),
    (" over [0.5 * t_end, t_end]", " at end"),
    (" + (v[n].z * 1 ms)^2", ""),
];

fn loss_with(scene: &Scene, uniform: &str, value: f64) -> f64 {
    let module = match scene.lowered.statics {
        Some(_) => &scene.lowered.adjoint.module,
        None => &scene.lowered.module,
    };
    let cpu = Cpu::new(module, Precision::F64, Some(1)).unwrap();
    let mut sim = Simulation::new(scene, cpu);
    sim.uniforms.set_named(uniform, value);
    sim.run(None, None).unwrap().loss.unwrap()
}

/// The worst relative difference between the adjoint's gradients and central differences
/// (step `rel` of each value, or `rel` itself for a zero one).
fn worst_gradient_error(path: &Path, rel: f64) -> f64 {
    let scene = Scene::load(path, &[]).unwrap();
    let cpu = Cpu::new(&scene.lowered.adjoint.module, Precision::F64, Some(1)).unwrap();
    let g = Simulation::new(&scene, cpu)
        .gradient(None, None, &GradOptions::default())
        .unwrap();
    assert!(g.gradients.len() >= 4, "{:?}", g.gradients);
    let mut worst: f64 = 0.0;
    for (name, &adj) in &g.gradients {
        let p = scene.uniforms[name];
        let h = if p == 0.0 { rel } else { rel * p.abs() };
        let fd = (loss_with(&scene, name, p + h) - loss_with(&scene, name, p - h)) / (2.0 * h);
        let err = (adj - fd).abs() / fd.abs().max(1e-30);
        eprintln!("{name}: adjoint {adj:e}, central {fd:e}, relative {err:.1e}");
        assert!(adj != 0.0, "{name} has a zero gradient");
        worst = worst.max(err);
    }
    worst
}

#[test]
fn quadratic_explicit_gradients_of_every_param_kind_match_central_differences() {
    let worst = worst_gradient_error(&all_kinds("explicit.soft", &[]), 1e-4);
    assert!(worst < 1e-5, "worst relative error {worst:e}");
}

#[test]
fn quadratic_static_gradients_match_central_differences() {
    let path = all_kinds("static.soft", &STATIC);
    let worst = worst_gradient_error(&path, 1e-4);
    assert!(worst < 1e-5, "worst relative error {worst:e}");
}

#[test]
fn the_interpreter_and_cranelift_step_quadratic_elements_to_the_same_bits() {
    let path = all_kinds("bits.soft", &[]);
    let scene = Scene::load(&path, &[]).unwrap();
    let cpu = Cpu::new(&scene.lowered.module, Precision::F64, Some(1)).unwrap();
    let a = Simulation::new(&scene, cpu).run(None, Some(50)).unwrap();
    let interp = Interpreter::new(&scene.lowered.module);
    let b = Simulation::new(&scene, interp).run(None, Some(50)).unwrap();
    assert!(a.x.iter().flatten().any(|&v| v != 0.0));
    assert_eq!(a.x, b.x);
    assert_eq!(a.loss.map(f64::to_bits), b.loss.map(f64::to_bits));
}

/// The multigrid solver's first coarsening of quadratic elements is the linear problem on the
/// same mesh (mid-edge nodes interpolated from their edges' corners): the static solve it gives
/// is the factored one's, in few conjugate-gradient iterations.
#[test]
fn multigrid_solves_quadratic_tangents_through_the_linear_problem() {
    use softc::engine::statics::LinearSolver;
    let path = all_kinds("multigrid.soft", &STATIC);
    let scene = Scene::load(&path, &[]).unwrap();
    let solve = |linear: LinearSolver| {
        let cpu = Cpu::new(&scene.lowered.adjoint.module, Precision::F64, Some(1)).unwrap();
        let mut sim = Simulation::new(&scene, cpu);
        sim.linear_solver = linear;
        sim.run(None, None).unwrap()
    };
    let direct = solve(LinearSolver::Direct);
    let amg = solve(LinearSolver::Amg);
    let report = amg.solver.clone().unwrap();
    assert_eq!(report.linear_solver, "amg");
    assert!(report.multigrid_levels >= 2, "{report:?}");
    let per_newton = report.krylov_iterations as f64 / report.newton_iterations.max(1) as f64;
    eprintln!(
        "{} dofs: {} levels, {per_newton:.1} CG iterations per Newton iteration",
        report.dofs, report.multigrid_levels
    );
    assert!(per_newton < 40.0, "{report:?}");
    let scale = direct
        .x
        .iter()
        .zip(&scene.mesh.nodes)
        .flat_map(|(x, x0)| (0..3).map(move |d| (x[d] - x0[d]).abs()))
        .fold(0.0, f64::max);
    let diff = direct
        .x
        .iter()
        .zip(&amg.x)
        .flat_map(|(a, b)| (0..3).map(move |d| (a[d] - b[d]).abs()))
        .fold(0.0, f64::max);
    assert!(diff < 1e-8 * scale, "{diff:e} of {scale:e}");
}

/// Node sets of a quadratic scene hold the mid-edge nodes they contain: a named surface's
/// (its 6-node triangles'), a region's (its elements'), a selection by position.
#[test]
fn node_sets_of_a_quadratic_scene_include_their_mid_edge_nodes() {
    let path = all_kinds(
        "sets.soft",
        &[(
            "nodes tip = named(body, \"tip\")\n",
            "nodes tip = named(body, \"tip\")\nnodes all = tagged(body, 1)\n\
             nodes far = select(body, x > 59.9 mm)\n",
        )],
    );
    let scene = Scene::load(&path, &[]).unwrap();
    let set = |name: &str| {
        let (_, nodes) = scene.node_sets.iter().find(|(n, _)| n == name).unwrap();
        nodes.clone()
    };
    let corners = scene.mesh.tets.iter().flatten().max().unwrap() + 1;
    assert!(scene.mesh.nodes.len() > corners as usize);
    assert_eq!(set("all").len(), scene.mesh.nodes.len());
    let (tip, far) = (set("tip"), set("far"));
    assert!(
        tip.iter().any(|&n| n >= corners),
        "no mid-edge node on the tip"
    );
    assert_eq!(tip, far, "the tip face is x = 60 mm");
}

/// `area_mean` weighs each node by the integral of its shape function over the boundary
/// triangles the set covers: on quadratic elements it integrates y² over the 10 × 10 mm tip face
/// exactly (100/3 mm²); on linear ones it integrates the linear interpolant (100/3 + h²/6 for
/// the 2.5 mm grid); a plain node mean is neither.
#[test]
fn area_mean_integrates_over_the_sets_boundary_surface() {
    let loss = |order: u32, reduction: &str| {
        let path = every_kind(
            order,
            &format!("area_{order}_{reduction}.soft"),
            &[(
                "loss = sum(n in tip) ((x[n].z - x0[n].z + 0.1 mm)^2 + (v[n].z * 1 ms)^2) \
                 over [0.5 * t_end, t_end]",
                &format!("loss = {reduction}(n in tip) (x0[n].y / 1 mm)^2"),
            )],
        );
        let scene = Scene::load(&path, &[]).unwrap();
        let cpu = Cpu::new(&scene.lowered.module, Precision::F64, Some(1)).unwrap();
        Simulation::new(&scene, cpu)
            .run(None, Some(1))
            .unwrap()
            .loss
            .unwrap()
    };
    let exact = 100.0 / 3.0;
    let quadratic = loss(2, "area_mean");
    assert!((quadratic - exact).abs() < 1e-12 * exact, "{quadratic}");
    let linear = loss(1, "area_mean");
    let interpolant = exact + 2.5 * 2.5 / 6.0;
    assert!((linear - interpolant).abs() < 1e-12 * exact, "{linear}");
    let plain = loss(2, "mean");
    assert!((plain - exact).abs() > 1e-2, "{plain}");
}

#[test]
fn quadratic_implicit_euler_gradients_match_central_differences() {
    let path = all_kinds(
        "implicit.soft",
        &[(
            "  dt = 20 us\n  steps = 200\n",
            "  dt = 0.5 ms\n  steps = 8\n  integrator = implicit_euler\n",
        )],
    );
    let worst = worst_gradient_error(&path, 1e-4);
    assert!(worst < 1e-5, "worst relative error {worst:e}");
}

/// A per-element param (one shear modulus per element of half the beam) on quadratic
/// elements: its largest gradient entries and the pressure's match central differences.
#[test]
fn a_per_element_param_of_quadratic_elements_matches_central_differences() {
    let text = common::script_at_order("runtime/tests/fixtures/grad/field.soft", 2);
    assert!(text.contains("order: 2"));
    let path = scratch("field.soft");
    std::fs::write(&path, text).unwrap();
    let scene = Scene::load(&path, &[]).unwrap();
    let cpu = Cpu::new(&scene.lowered.adjoint.module, Precision::F64, Some(1)).unwrap();
    let g = Simulation::new(&scene, cpu)
        .gradient(None, None, &GradOptions::default())
        .unwrap();
    let mut entries: Vec<(&String, f64)> = g
        .gradients
        .iter()
        .filter(|(n, _)| n.starts_with("param.mu."))
        .map(|(n, &v)| (n, v))
        .collect();
    assert!(entries.len() > 100, "one entry per element of `near`");
    entries.sort_by(|a, b| b.1.abs().total_cmp(&a.1.abs()));
    let mut checked: Vec<(&String, f64)> = entries[..3].to_vec();
    let p0 = "param.p0".to_string();
    checked.push((&p0, g.gradients[&p0]));
    for (name, adj) in checked {
        let p = scene.uniforms[name.as_str()];
        // One element's modulus moves the loss little: a larger step keeps round-off out.
        let h = if name.starts_with("param.mu.") {
            1e-3
        } else {
            1e-4
        } * p.abs();
        let fd = (loss_with(&scene, name, p + h) - loss_with(&scene, name, p - h)) / (2.0 * h);
        let err = (adj - fd).abs() / fd.abs();
        eprintln!("{name}: adjoint {adj:e}, central {fd:e}, relative {err:.1e}");
        assert!(err < 1e-5, "{name}: adjoint {adj:e}, central {fd:e}");
    }
}

/// The inner wall's radial displacement of a free hollow sphere (radii 5 and 10 mm, μ = 10 kPa,
/// κ = 50 kPa) under an internal pressure small enough (1 mPa) for linear elasticity: meshed by
/// isosurface stuffing at `order`, with order 2 putting the mid-edge nodes of both spheres on
/// the exact surfaces (`order = 2` in the spec), its area mean over the chamber, over Lamé's
/// u(a) = p a³/(b³ − a³) (a/(3K) + b³/(4G a²)).
fn sphere_inner_displacement_ratio(h: f64, order: u32) -> f64 {
    use softc::mesh::mesher::{MeshSpec, generate};
    let spec = MeshSpec::from_toml(
        &format!(
            "unit = \"mm\"\nresolution = {h}\norder = {order}\n[body]\nshape = \"sphere\"\n\
             center = [0, 0, 0]\nradius = 10\n[[cavity]]\nname = \"inner\"\ntag = 2\n\
             shape = \"sphere\"\ncenter = [0, 0, 0]\nradius = 5\n"
        ),
        Path::new("sphere.toml"),
    )
    .unwrap();
    let mesh = generate(&spec, None, Path::new(".")).unwrap().mesh;
    assert!(!softc::mesh::has_errors(&mesh.validate()));
    let loss = static_loss(
        &mesh,
        &format!("sphere_{h}_{order}"),
        order,
        "material gel = neo_hookean(mu: 10 kPa, kappa: 50 kPa, density: 1000 kg/m^3)\n\
         chamber inner = surface(body, \"inner\")\n\
         nodes wall = named(body, \"inner\")\n\
         sim {\n  integrator = quasi_static\n  duration = 1 s\n  precision = f64\n  \
         use gel\n  pressure inner = 0.001 Pa * ramp(t, 1 s)\n}\n\
         loss = area_mean(n in wall) dot(x[n] - x0[n], x0[n]) / norm(x0[n]) at end\n",
    );
    let (p, a, b, g, k) = (1e-3, 5e-3f64, 10e-3f64, 10e3, 50e3);
    let lame =
        p * a.powi(3) / (b.powi(3) - a.powi(3)) * (a / (3.0 * k) + b.powi(3) / (4.0 * g * a * a));
    loss / lame
}

/// **Convergence order.** Quadratic tets with curved boundaries converge on the hollow sphere
/// at an observed order ≥ 2 in the wall displacement from h = 10/3 to 5/3 mm (measured:
/// errors −0.93 % and −0.093 %, order 3.3), where linear tets on the same meshes are −33 % and
/// −9.4 % off (order 1.8). The stuffed meshes are not nested, so the order is taken over one
/// halving, not fitted.
#[test]
fn quadratic_tets_converge_at_order_two_or_more_on_a_curved_smooth_problem() {
    let coarse = (sphere_inner_displacement_ratio(10.0 / 3.0, 2) - 1.0).abs();
    let fine = (sphere_inner_displacement_ratio(5.0 / 3.0, 2) - 1.0).abs();
    let order = (coarse / fine).log2();
    println!("quadratic: errors {coarse:.3e} → {fine:.3e}, observed order {order:.2}");
    assert!(order >= 2.0, "observed order {order}");
    assert!(fine < 2e-3, "error {fine} at h = 5/3 mm");
    // Linear tets on the coarse mesh are far worse than quadratic ones.
    let linear = (sphere_inner_displacement_ratio(10.0 / 3.0, 1) - 1.0).abs();
    assert!(
        linear > 10.0 * coarse,
        "linear {linear}, quadratic {coarse}"
    );
}

/// Nearly incompressible materials are warned about on linear tetrahedra only: 10-node tets
/// are what the warning recommends (K/μ of the every-param-kind scene's Yeoh made ~10⁵).
#[test]
fn the_locking_warning_is_for_linear_tetrahedra_only() {
    use softc::engine::incompressibility::{bulk_to_shear, locking_warning};
    let stiff = [("d1: 10 /MPa", "d1: 0.001 /MPa")];
    for (order, warned) in [(1, true), (2, false)] {
        let path = every_kind(order, &format!("incompressible_{order}.soft"), &stiff);
        let scene = Scene::load(&path, &[]).unwrap();
        assert!(bulk_to_shear(&scene)[0].ratio > 1e4, "order {order}");
        assert_eq!(locking_warning(&scene).is_some(), warned, "order {order}");
    }
}
