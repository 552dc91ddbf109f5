//! `stretch(e)` in the loss (SPEC §7): each element's largest principal stretch equals the
//! eigen-decomposition of its right Cauchy–Green tensor at the solved state, and its gradient
//! through a static solve equals central differences.

use softc::devices::cpu::Cpu;
use softc::engine::Simulation;
use softc::engine::adjoint::GradOptions;
use softc::engine::scene::Scene;
use softc_compiler::back::Precision;
use std::path::{Path, PathBuf};

/// The 1k benchmark beam inflated by a static solve, with `loss` as its loss.
fn scene_with_loss(name: &str, loss: &str) -> PathBuf {
    let mesh = Path::new(env!("CARGO_MANIFEST_DIR")).join("../meshes/bench_1k.msh");
    let text = format!(
        "mesh body = load(\"{}\")\n\
         material silicone = neo_hookean(mu: 40 kPa, kappa: 2 MPa, density: 1070 kg/m^3)\n\
         chamber cavity = surface(body, \"cavity\")\n\
         nodes base = named(body, \"base\")\n\
         elements all = select(body, x > -1 mm)\n\
         elements free_end = select(body, x > 40 mm)\n\
         param p: pressure = 10 kPa in [0 kPa, ..]\n\
         sim {{\n  integrator = quasi_static\n  duration = 1 s\n  use silicone\n  fix base\n  \
         pressure cavity = p * ramp(t, 1 s)\n}}\n\
         loss = {loss}\n",
        mesh.display()
    );
    let dir = std::env::temp_dir().join(format!("softc-stretch-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let path = dir.join(name);
    std::fs::write(&path, text).unwrap();
    path
}

fn simulation(scene: &Scene) -> Simulation<'_, Cpu> {
    let cpu = Cpu::new(&scene.lowered.adjoint.module, Precision::F64, Some(1)).unwrap();
    Simulation::new(scene, cpu)
}

/// √(largest eigenvalue of FᵀF) of tet `e` at positions `x`.
fn largest_stretch(scene: &Scene, x: &[[f64; 3]], e: usize) -> f64 {
    let t = scene.mesh.tets[e];
    let edges = |p: &dyn Fn(usize) -> [f64; 3]| {
        nalgebra::Matrix3::from_fn(|r, c| p(t[c + 1] as usize)[r] - p(t[0] as usize)[r])
    };
    let rest = edges(&|n| scene.mesh.nodes[n]);
    let now = edges(&|n| x[n]);
    let f = now * rest.try_inverse().unwrap();
    let c = f.transpose() * f;
    c.symmetric_eigenvalues().max().sqrt()
}

#[test]
fn stretch_is_the_largest_principal_stretch_with_exact_gradients() {
    let scene = Scene::load(
        &scene_with_loss("max.soft", "max(e in all) stretch(e)"),
        &[],
    )
    .unwrap();
    let run = simulation(&scene).run(None, None).unwrap();
    let expected = (0..scene.mesh.tets.len())
        .map(|e| largest_stretch(&scene, &run.x, e))
        .fold(f64::MIN, f64::max);
    let loss = run.loss.unwrap();
    assert!(
        (loss - expected).abs() < 1e-10,
        "stretch {loss} against the eigenvalues' {expected}"
    );
    // The inflated chamber's walls stretch by some per cent.
    assert!(loss > 1.02 && loss < 1.5, "{loss}");

    // A strain-limit penalty over part of the body: the adjoint through the static solve
    // against a central difference.
    let scene = Scene::load(
        &scene_with_loss(
            "limit.soft",
            "sum(e in free_end) max(stretch(e) - 1.01, 0)^2",
        ),
        &[],
    )
    .unwrap();
    let g = simulation(&scene)
        .gradient(None, None, &GradOptions::default())
        .unwrap();
    let loss_at = |v: f64| {
        let mut sim = simulation(&scene);
        sim.uniforms.set_named("param.p", v);
        sim.run(None, None).unwrap().loss.unwrap()
    };
    let p = scene.uniforms["param.p"];
    let step = 1.0;
    let fd = (loss_at(p + step) - loss_at(p - step)) / (2.0 * step);
    let adj = g.gradients["param.p"];
    assert!(fd > 0.0, "{fd}");
    assert!(
        (adj - fd).abs() < 1e-6 * fd,
        "adjoint {adj:e}, central {fd:e}"
    );
}
