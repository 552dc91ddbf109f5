//! The reference simulator (`softc::reference`) against the kernel-IR engine and against
//! independent facts: short rollouts of every example and of variants (gravity, several
//! materials, windowed damping, a controller) agree to 1e-6 relative in f64; element forces
//! equal the finite-difference derivative of the energy; the benchmark's tip displacement and
//! stable step match BENCHMARK.md.

use softc::devices::cpu::Cpu;
use softc::devices::interp::Interpreter;
use softc::engine::scene::Scene;
use softc::engine::{RunSummary, Simulation};
use softc::reference::{self, Reference};
use softc_compiler::back::Precision;
use std::path::{Path, PathBuf};

fn root() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("..")
}

fn mesh(name: &str) -> String {
    root()
        .join("meshes")
        .join(name)
        .canonicalize()
        .unwrap()
        .display()
        .to_string()
}

/// Write a script into a fresh temp dir.
fn script(name: &str, text: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("softc-reference-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let path = dir.join(format!("{name}.soft"));
    std::fs::write(&path, text).unwrap();
    path
}

fn load(path: &Path) -> Scene {
    Scene::load(path, &[]).unwrap_or_else(|e| panic!("{}: {e}", path.display()))
}

fn interp(scene: &Scene, dt: Option<f64>, steps: u64) -> RunSummary {
    Simulation::new(scene, Interpreter::new(&scene.lowered.module))
        .run(dt, Some(steps))
        .unwrap()
}

/// max |x_ref − x_ir| / max |x_ir − x0| over all nodes (and the same for velocities).
fn relative_difference(scene: &Scene, a: &RunSummary, b: &RunSummary) -> (f64, f64) {
    let d = |p: [f64; 3], q: [f64; 3]| (0..3).map(|k| (p[k] - q[k]).powi(2)).sum::<f64>().sqrt();
    let mut scale_x: f64 = 0.0;
    let mut diff_x: f64 = 0.0;
    let mut scale_v: f64 = 0.0;
    let mut diff_v: f64 = 0.0;
    for i in 0..a.x.len() {
        scale_x = scale_x.max(d(b.x[i], scene.mesh.nodes[i]));
        diff_x = diff_x.max(d(a.x[i], b.x[i]));
        scale_v = scale_v.max(d(b.v[i], [0.0; 3]));
        diff_v = diff_v.max(d(a.v[i], b.v[i]));
    }
    assert!(scale_x > 0.0, "nothing moved");
    (diff_x / scale_x, diff_v / scale_v)
}

/// Run both simulators for `steps` steps and check that positions agree to 1e-6 relative to the
/// largest displacement, velocities to `v_tol` relative to the largest speed.
fn agree_to(path: &Path, dt: Option<f64>, steps: u64, v_tol: f64) -> f64 {
    let scene = load(path);
    let ir = interp(&scene, dt, steps);
    let rf = reference::run(&scene, dt, Some(steps)).unwrap();
    assert_eq!(rf.steps, steps);
    assert_eq!(rf.dt, ir.dt);
    let (dx, dv) = relative_difference(&scene, &rf, &ir);
    eprintln!(
        "{}: {steps} steps, max relative difference x {dx:.2e}, v {dv:.2e}",
        path.display()
    );
    assert!(
        dx < 1e-6 && dv < v_tol,
        "{}: x {dx:e}, v {dv:e}",
        path.display()
    );
    dx
}

fn agree(path: &Path, dt: Option<f64>, steps: u64) -> f64 {
    agree_to(path, dt, steps, 1e-6)
}

fn example(name: &str) -> PathBuf {
    root().join("examples").join(format!("{name}.soft"))
}

#[test]
fn benchmark_1k_agrees_with_the_engine() {
    agree(&example("benchmark-1k"), None, 400);
}

#[test]
fn benchmark_10k_agrees_with_the_engine() {
    agree(&example("benchmark-10k"), None, 60);
}

#[test]
fn benchmark_50k_agrees_with_the_engine() {
    agree(&example("benchmark-50k"), None, 20);
}

// The cuboid (9600 tets) and the endoscope (37828 tets) are slow in the IR interpreter: short
// rollouts. `dt = auto` scripts get an explicit dt just below their stable step. In the first
// few dozen steps the ramped pressure is still tiny (≈ 0.01–0.1 Pa), so the round-off noise of
// the stress at rest (≈ 1e-16·κ in both simulators, summed in different orders) is not
// negligible against the velocities yet: positions are held to 1e-6, velocities to 1e-5 there
// (the longer rollouts below hold both to 1e-6).
#[test]
fn pressure_optimization_agrees_with_the_engine() {
    agree_to(
        &example("pressure_optimization_explicit"),
        Some(135e-6),
        40,
        1e-5,
    );
}

#[test]
fn verification_agrees_with_the_engine() {
    agree_to(&example("verification"), Some(13.5e-6), 40, 1e-5);
}

#[test]
fn meta_optimization_agrees_with_the_engine() {
    agree_to(&example("meta_optimization"), Some(135e-6), 40, 1e-5);
}

#[test]
fn controller_synthesis_agrees_with_the_engine() {
    agree_to(
        &example("controller_synthesis_explicit"),
        Some(55e-6),
        20,
        1e-5,
    );
}

/// Steps of the variants below (30 µs each: 7.5 ms, the load ramps over 4–5 ms).
const VARIANT_STEPS: u64 = 250;

/// The benchmark beam with its material written in a different way, plus `extra` sim lines.
fn bench_variant(name: &str, materials: &str, sim: &str, extra_items: &str) -> PathBuf {
    script(
        name,
        &format!(
            r#"mesh body = load("{}")
{materials}
chamber cavity = surface(body, "cavity")
nodes base = named(body, "base")
nodes tip = named(body, "tip")
elements front = select(body, x < 20 mm)
elements top = select(body, x >= 20 mm and z > 5 mm)
param p_peak: pressure = 20 kPa in [0 kPa, 50 kPa]
{extra_items}
sim {{
  dt = 30 us
  steps = 400
  fix base
{sim}
}}
"#,
            mesh("bench_1k.msh")
        ),
    )
}

const RUBBER: &str = r#"let E = 0.3 MPa
let nu = 0.45
material rubber = neo_hookean_ln(mu: lame_mu(E, nu), lambda: lame_lambda(E, nu), density: 1070 kg/m^3)"#;

#[test]
fn gravity_and_mass_scaling_agree() {
    let p = bench_variant(
        "gravity",
        RUBBER,
        "  damping = 5 /s\n  mass_scaling = 3\n  gravity = [0, 0.5, -9.81] m/s^2\n  pressure cavity = p_peak * ramp(t, 5 ms)",
        "",
    );
    agree(&p, None, VARIANT_STEPS);
}

/// No damping and no pressure (a chamber is declared but not pressurised): gravity alone.
#[test]
fn gravity_alone_agrees() {
    let p = bench_variant("falling", RUBBER, "  gravity = [0, 0, -9.81] m/s^2", "");
    let scene = load(&p);
    assert!(scene.lowered.chambers.is_empty());
    drop(scene);
    agree(&p, None, 150);
}

#[test]
fn several_materials_agree() {
    let materials = format!(
        r#"{RUBBER}
material gel {{
  let mu = lame_mu(0.2 MPa, 0.45)
  density = 1.2 g/cm^3
  W(I1bar, I2bar, J) = mu / 2 * (I1bar - 3) + 0.02 MPa * (I2bar - 3) + 0.01 MPa * (I1bar - 3) * (I2bar - 3) + bulk_modulus(0.2 MPa, 0.45) / 2 * (J - 1)^2
}}
material mr = mooney_rivlin(c10: 0.05 MPa, c01: 0.02 MPa, c11: 0.005 MPa, d1: 5 /MPa, density: 1000 kg/m^3)
material series = yeoh_series(c: [0.08, 0.03, -0.001] MPa, d: [2.0, 8.0] /MPa, density: 1100 kg/m^3)"#
    );
    let p = bench_variant(
        "materials",
        &materials,
        "  damping = 10 /s\n  mass_scaling = 2.5\n  use rubber\n  use gel in front\n  use mr in top\n  use series in tipzone\n  pressure cavity = p_peak * ramp(t, 4 ms)",
        "elements tipzone = select(body, x > 50 mm)",
    );
    let scene = load(&p);
    assert_eq!(scene.lowered.materials.len(), 4);
    assert!(scene.material_ranges.iter().all(|r| !r.is_empty()));
    // The reference's own rest volumes and lumped masses (with `mass_scaling`) equal the
    // scene's precomputation.
    let r = Reference::new(&scene).unwrap();
    for (a, b) in r.rest_volumes().iter().zip(&scene.pre.rest_volume) {
        assert!((a - b).abs() <= 1e-12 * b, "{a} {b}");
    }
    for (a, b) in r.masses().iter().zip(&scene.pre.mass) {
        assert!((a - b).abs() <= 1e-12 * b, "{a} {b}");
    }
    drop(r);
    drop(scene);
    agree(&p, None, VARIANT_STEPS);
}

#[test]
fn spring_mesh_example_agrees_with_the_engine() {
    agree(&example("spring_mesh"), Some(60e-6), 400);
}

/// The spring mesh with several materials: edges shared by tets of two materials get each
/// side's stiffness weighted by its volume (the reference sums per unique edge, the kernels
/// per tet), and a material with Ī2.
#[test]
fn spring_mesh_with_several_materials_agrees() {
    let materials = format!(
        r#"{RUBBER}
material mr = mooney_rivlin(c10: 0.05 MPa, c01: 0.02 MPa, c11: 0.005 MPa, d1: 5 /MPa, density: 1000 kg/m^3)
material silicone = yeoh(c10: 0.11 MPa, c20: 0.02 MPa, d1: 1.0 /MPa, density: 1070 kg/m^3)"#
    );
    let p = bench_variant(
        "springs",
        &materials,
        "  damping = 10 /s\n  model = springs(volume_stiffness: 2 kPa/mm)\n  use rubber\n  use mr in front\n  use silicone in top\n  pressure cavity = p_peak * ramp(t, 4 ms)",
        "",
    );
    let scene = load(&p);
    assert!(scene.lowered.springs);
    assert_eq!(scene.lowered.materials.len(), 3);
    drop(scene);
    agree(&p, None, VARIANT_STEPS);
}

/// The inversion-safe stable neo-Hookean (W in I1 and J) agrees as well.
#[test]
fn stable_neo_hookean_agrees() {
    let p = bench_variant(
        "snh",
        "material rubber = stable_neo_hookean(mu: lame_mu(0.3 MPa, 0.45), lambda: lame_lambda(0.3 MPa, 0.45), density: 1070 kg/m^3)",
        "  damping = 10 /s\n  pressure cavity = p_peak * ramp(t, 4 ms)",
        "",
    );
    let scene = load(&p);
    assert_eq!(scene.lowered.inversion_safe, vec![true]);
    drop(scene);
    agree(&p, None, VARIANT_STEPS);
}

#[test]
fn windowed_damping_agrees() {
    let p = bench_variant(
        "windows",
        RUBBER,
        "  damping = beta[window(t, 1 ms)] + 2 /s * abs(sin(t / 1 ms))\n  pressure cavity = p_peak * ramp(t, 5 ms) * (1 + 0.2 * step(t, 4 ms))",
        "param beta: rate[12] = [50, 5, 120, 1, 30, 80, 10, 150, 2, 60, 20, 90] /s in [0 /s, 200 /s]",
    );
    agree(&p, None, VARIANT_STEPS);
}

#[test]
fn controller_with_matrix_param_agrees() {
    let p = bench_variant(
        "controller",
        RUBBER,
        "  damping = 10 /s\n  pressure cavity = (pressures(target)[0] + clamp(pressures(target)[1], 1 kPa, 5 kPa) + max(pressures(target)[2], 0 Pa)) * ramp(t, 5 ms)",
        r#"input target: length[3] from [[0, 2.5, 4.33], [0, -4.33, 2.5]] mm
param w: 1/length[3, 4] = [[1, -2, 0.5, 0], [0, 1, -1, 2], [-1, 0, 2, 1]] /mm in [-10 /mm, 10 /mm]
let gain = sum(i in 0..3) (i + 1) * 0.5
fn features(p: length[3]) -> length[4] = [max(0 mm, p.y), min(0 mm, p.y), max(0 mm, p.z), min(0 mm, p.z)]
controller pressures(goal: length[3]) -> pressure[3] = 4 kPa * sigmoid(w @ features(goal)) / gain * (if norm(goal) > 1 mm then 3 else 1)"#,
    );
    let scene = load(&p);
    assert_eq!(scene.uniforms["param.w.1.3"], 2000.0);
    assert!((scene.uniforms["input.target.2"] - 4.33e-3).abs() < 1e-15);
    drop(scene);
    agree(&p, None, VARIANT_STEPS);
}

/// Two fields: the shear modulus of a Yeoh-form neo-Hookean near the clamp and the
/// coefficient c10 of a Yeoh material at the free end, each entry a different value (set on
/// the scene directly), with a third material between them; `model` adds a sim line. Runs
/// Cranelift (f64) and the reference for `steps` steps; returns their relative difference.
fn fields_agree(name: &str, model: &str, steps: u64) -> (f64, f64) {
    let p = bench_variant(
        name,
        r#"elements near = select(body, x < 20 mm)
elements far = select(body, x > 40 mm)
param mu: pressure[near] = 20 kPa in [1 kPa, 1 MPa]
param c10: pressure[far] = 0.1 MPa in [0.01 MPa, 1 MPa]
material graded = neo_hookean(mu: mu, kappa: 0.2 MPa, density: 1070 kg/m^3)
material tip_gel = yeoh(c10: c10, c20: 0.02 MPa, c30: 0 MPa, d1: 10 /MPa, density: 1100 kg/m^3)
material middle = neo_hookean(mu: 30 kPa, kappa: 0.2 MPa, density: 1000 kg/m^3)"#,
        &format!(
            "  damping = 10 /s\n{model}  use middle\n  use graded in near\n  use tip_gel in far\n  pressure cavity = p_peak * ramp(t, 2 ms)"
        ),
        "",
    );
    let mut scene = load(&p);
    assert_eq!(scene.fields.len(), 2);
    assert_eq!(
        scene.lowered.material_fields,
        [vec![], vec!["mu".to_string()], vec!["c10".to_string()]]
    );
    // Unequal entries: a wrong element order would show.
    for (k, v) in scene.uniforms.iter_mut() {
        if let Some(i) = k.strip_prefix("param.mu.") {
            let i: f64 = i.parse().unwrap();
            *v = 20e3 * (1.0 + 0.8 * (0.37 * i).sin());
        } else if let Some(i) = k.strip_prefix("param.c10.") {
            let i: f64 = i.parse().unwrap();
            *v = 0.1e6 * (1.0 + 0.5 * (1.3 * i).cos());
        }
    }
    let cpu = softc::engine::Cpu::new(
        &scene.lowered.module,
        softc_compiler::back::Precision::F64,
        Some(1),
    )
    .unwrap();
    let ir = Simulation::new(&scene, cpu).run(None, Some(steps)).unwrap();
    let rf = reference::run(&scene, None, Some(steps)).unwrap();
    let (dx, dv) = relative_difference(&scene, &rf, &ir);
    eprintln!("{name}: {steps} steps, max relative difference x {dx:.2e}, v {dv:.2e}");
    // The field values matter: equal entries give a different motion.
    let uniform = interp(&load(&p), None, steps);
    let (ux, _) = relative_difference(&scene, &uniform, &ir);
    assert!(ux > 1e-3, "{ux:e}");
    (dx, dv)
}

#[test]
fn per_element_params_agree() {
    // FEM: both differentiate W exactly (reverse mode on the IR, dual numbers), so a short
    // rollout agrees to round-off (measured 2e-14 in x, 1e-12 in v).
    let (dx, dv) = fields_agree("fields", "", 150);
    assert!(dx < 1e-9 && dv < 1e-9, "x {dx:e}, v {dv:e}");
}

#[test]
fn per_element_params_agree_in_the_spring_mesh() {
    // The spring mesh weights each element's own curve E(λ) (the reference: per unique edge,
    // its tangent modulus by central differences, ~1e-8 relative). Mass scaling keeps these
    // soft springs from inverting at 30 µs.
    let (dx, dv) = fields_agree(
        "fields-springs",
        "  model = springs(volume_stiffness: 2 kPa/mm)\n  mass_scaling = 10\n",
        100,
    );
    assert!(dx < 1e-6 && dv < 1e-6, "x {dx:e}, v {dv:e}");
}

/// The tip's mean z-displacement of the benchmark after 4000 steps at 40 µs: −0.015146 mm
/// (BENCHMARK.md).
#[test]
fn benchmark_1k_tip_displacement() {
    let scene = load(&example("benchmark-1k"));
    let s = reference::run(&scene, None, None).unwrap();
    assert_eq!(s.steps, 4000);
    assert!((s.dt - 40e-6).abs() < 1e-18);
    let tip = &scene.node_sets.iter().find(|(n, _)| n == "tip").unwrap().1;
    let z = tip
        .iter()
        .map(|&n| s.x[n as usize][2] - scene.mesh.nodes[n as usize][2])
        .sum::<f64>()
        / tip.len() as f64;
    eprintln!(
        "benchmark-1k tip mean z after 4000 steps: {:.6} mm",
        z * 1e3
    );
    assert!((z - -0.015146e-3).abs() < 0.5e-9, "{z}");
}

/// The largest stable step of the benchmark at 1k is 52 µs (BENCHMARK.md): the reference's own
/// estimate (power iteration on M⁻¹K) agrees with it and with the engine's, and `dt = auto`
/// runs at the safety factor times it.
#[test]
fn auto_dt_uses_a_stable_step_estimate_that_matches_the_benchmark() {
    let p = bench_variant(
        "auto",
        RUBBER,
        "  damping = 20 /s\n  pressure cavity = p_peak * ramp(t, 5 ms)",
        "",
    );
    let text = std::fs::read_to_string(&p)
        .unwrap()
        .replace("dt = 30 us", "dt = auto(safety: 0.5)");
    std::fs::write(&p, text).unwrap();
    let scene = load(&p);
    let s = reference::run(&scene, None, Some(10)).unwrap();
    let est = s.dt_stable_estimate.unwrap();
    assert!((s.dt - 0.5 * est).abs() < 1e-15);
    let engine = Simulation::new(&scene, Interpreter::new(&scene.lowered.module))
        .stable_dt_estimate()
        .unwrap();
    eprintln!("stable dt: reference {est:e} s, engine {engine:e} s");
    assert!((est - 52e-6).abs() < 1e-6, "{est}");
    assert!((est - engine).abs() < 0.02 * est, "{est} vs {engine}");
}

#[test]
fn a_step_beyond_the_stable_limit_stops_with_a_clear_message() {
    let scene = load(&example("benchmark-1k"));
    let e = reference::run(&scene, Some(0.5e-3), Some(200)).unwrap_err();
    assert!(
        e.contains("step") && (e.contains("inverted") || e.contains("non-finite")),
        "{e}"
    );
    eprintln!("{e}");
}

/// Element forces are −∂(V0·W)/∂x: central differences of the reference's own energy.
#[test]
fn element_forces_are_the_energy_gradient() {
    let p = script(
        "element",
        &format!(
            r#"mesh body = load("{}")
material yeo = yeoh(c10: 0.24162 MPa, c20: 0.19977 MPa, c30: -0.00541 MPa, d1: 1.0 /MPa, density: 1070 kg/m^3)
material mr = mooney_rivlin(c10: 0.1 MPa, c01: 0.05 MPa, c11: 0.01 MPa, d1: 2 /MPa, density: 1070 kg/m^3)
material user {{
  density = 1000 kg/m^3
  W(I1bar, I2bar, J) = 0.1 MPa * (I1bar - 3) + 0.03 MPa * (I2bar - 3)^2 + 0.02 MPa * exp(0.5 * (I2bar - 3)) + 1 MPa * (J - 1)^2 - 0.02 MPa * ln(J)
}}
elements a = select(body, x < 20 mm)
elements b = select(body, x > 40 mm)
chamber cavity = surface(body, "cavity")
nodes base = named(body, "base")
sim {{
  dt = 10 us
  steps = 1
  fix base
  use yeo
  use mr in a
  use user in b
  pressure cavity = 1 kPa
}}
"#,
            mesh("bench_1k.msh")
        ),
    );
    let scene = load(&p);
    let mut r = Reference::new(&scene).unwrap();
    let mut rng: u64 = 12345;
    let mut rnd = || {
        rng = rng
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        (rng >> 11) as f64 / (1u64 << 53) as f64 - 0.5
    };
    for (m, range) in scene.material_ranges.iter().enumerate() {
        for e in [range.start, range.start + range.len() / 2] {
            let rest = scene.mesh.tets[e].map(|n| scene.mesh.nodes[n as usize]);
            let size = scene.pre.min_altitude[e];
            // A finite deformation: about 15 % of the element size at each corner.
            let x: [[f64; 3]; 4] = rest.map(|p| p.map(|c| c + 0.3 * size * rnd()));
            let res = r.element(e, &x).unwrap();
            assert!(res.j > 0.5, "{}", res.j);
            let fmax = res
                .forces
                .iter()
                .flatten()
                .fold(0.0_f64, |a, f| a.max(f.abs()));
            assert!(fmax > 0.0);
            let h = 1e-6 * size;
            let mut net = [0.0; 3];
            for c in 0..4 {
                for d in 0..3 {
                    net[d] += res.forces[c][d];
                    let mut xp = x;
                    let mut xm = x;
                    xp[c][d] += h;
                    xm[c][d] -= h;
                    let ep = r.element(e, &xp).unwrap().energy;
                    let em = r.element(e, &xm).unwrap().energy;
                    let fd = -(ep - em) / (2.0 * h);
                    let err = (fd - res.forces[c][d]).abs() / fmax;
                    assert!(
                        err < 1e-6,
                        "material {} element {e} corner {c} dim {d}: force {} vs finite difference {fd} ({err:e})",
                        scene.lowered.materials[m],
                        res.forces[c][d]
                    );
                }
            }
            assert!(net.iter().all(|f| f.abs() < 1e-12 * fmax.max(1.0)));
        }
    }
}

/// Stepping by hand gives the same state as `run`, and the state moves every step.
#[test]
fn stepping_matches_run() {
    let scene = load(&example("benchmark-1k"));
    let mut r = Reference::new(&scene).unwrap();
    let mut st = r.initial_state();
    let mut last = st.x.clone();
    for step in 0..30 {
        r.step(&mut st, step, 40e-6).unwrap();
        if step > 0 {
            assert!(st.x != last, "step {step} did not move");
        }
        last = st.x.clone();
    }
    let s = reference::run(&scene, Some(40e-6), Some(30)).unwrap();
    for (a, b) in s.x.iter().zip(&st.x) {
        assert_eq!(*a, [b[0], b[1], b[2]]);
    }
}

/// Under a homogeneous deformation x = F·X the stress equals the closed forms of the two
/// neo-Hookean laws: P = μ(F − F⁻ᵀ) + λ ln J F⁻ᵀ (coupled ln J form) and
/// P = μ J^(−2/3)(F − I1/3 F⁻ᵀ) + κ (J − 1) J F⁻ᵀ (decoupled form).
#[test]
fn stress_matches_closed_forms() {
    let p = script(
        "closed",
        &format!(
            r#"mesh body = load("{}")
material coupled = neo_hookean_ln(mu: 0.1 MPa, lambda: 0.9 MPa, density: 1070 kg/m^3)
material decoupled = neo_hookean(mu: 0.1 MPa, kappa: 1.5 MPa, density: 1070 kg/m^3)
elements half = select(body, x < 30 mm)
nodes base = named(body, "base")
sim {{
  dt = 10 us
  steps = 1
  fix base
  use coupled
  use decoupled in half
}}
"#,
            mesh("bench_1k.msh")
        ),
    );
    let scene = load(&p);
    let mut r = Reference::new(&scene).unwrap();
    let f = nalgebra::Matrix3::new(1.2, 0.1, -0.05, 0.03, 0.9, 0.2, -0.1, 0.04, 1.1);
    let j = f.determinant();
    let finv_t = f.try_inverse().unwrap().transpose();
    let i1 = (f.transpose() * f).trace();
    assert!(scene.material_ranges.iter().all(|r| !r.is_empty()));
    for (m, range) in scene.material_ranges.iter().enumerate() {
        let e = range.start;
        let x = scene.mesh.tets[e].map(|n| {
            let p = f * nalgebra::Vector3::from(scene.mesh.nodes[n as usize]);
            [p[0], p[1], p[2]]
        });
        let res = r.element(e, &x).unwrap();
        let expected = match scene.lowered.materials[m].as_str() {
            "coupled" => (f - finv_t) * 0.1e6 + finv_t * (0.9e6 * j.ln()),
            _ => {
                (f - finv_t * (i1 / 3.0)) * (0.1e6 * j.powf(-2.0 / 3.0))
                    + finv_t * (1.5e6 * (j - 1.0) * j)
            }
        };
        for rr in 0..3 {
            for c in 0..3 {
                let (a, b) = (res.piola[rr][c], expected[(rr, c)]);
                assert!(
                    (a - b).abs() < 1e-9 * expected.abs().max(),
                    "{}: P[{rr}][{c}] = {a} vs {b}",
                    scene.lowered.materials[m]
                );
            }
        }
        assert!((res.j - j).abs() < 1e-12);
    }
}

/// At rest every material is stress-free.
#[test]
fn rest_is_stress_free() {
    let scene = load(&example("pressure_optimization_explicit"));
    let mut r = Reference::new(&scene).unwrap();
    for e in [0, scene.mesh.tets.len() - 1] {
        let x = scene.mesh.tets[e].map(|n| scene.mesh.nodes[n as usize]);
        let res = r.element(e, &x).unwrap();
        assert!((res.j - 1.0).abs() < 1e-12);
        assert!(
            res.piola.iter().flatten().all(|p| p.abs() < 1e-6),
            "{:?}",
            res.piola
        );
    }
}

/// `softc run --backend reference` prints the same JSON summary as the engine.
#[test]
fn cli_runs_the_reference_backend() {
    let bench = example("benchmark-1k");
    let args: Vec<String> = ["softc", "run", "--backend", "reference", "--steps", "20"]
        .iter()
        .map(|s| s.to_string())
        .chain([bench.display().to_string()])
        .collect();
    let (mut out, mut err) = (Vec::new(), Vec::new());
    let code = softc::cli::run(&args, &mut out, &mut err);
    let err = String::from_utf8_lossy(&err);
    assert_eq!(code, 0, "{err}");
    let json: serde_json::Value = serde_json::from_slice(&out).unwrap();
    assert_eq!(json["backend"], "reference");
    assert_eq!(json["steps"], 20);
    assert!(
        json["sets"]["tip"]["mean_displacement"][2]
            .as_f64()
            .unwrap()
            < 0.0
    );
}

/// The benchmark beam as quadratic (10-node) tets, straight-sided (`order: 2` on a linear
/// mesh): neo-Hookean (ln J form) with a Yeoh zone and an Ī2 material, a ramped pressure.
fn quadratic_bench(name: &str, sim: &str) -> PathBuf {
    let materials = format!(
        r#"{RUBBER}
material soft = yeoh(c10: 0.05 MPa, c20: 0.01 MPa, c30: 0.002 MPa, d1: 4 /MPa, density: 1100 kg/m^3)
material mr = mooney_rivlin(c10: 0.05 MPa, c01: 0.02 MPa, c11: 0.005 MPa, d1: 5 /MPa, density: 1000 kg/m^3)"#
    );
    let p = bench_variant(
        name,
        &materials,
        sim,
        "elements tipzone = select(body, x > 40 mm)",
    );
    let text = std::fs::read_to_string(&p)
        .unwrap()
        .replace(".msh\")", ".msh\", order: 2)");
    std::fs::write(&p, text).unwrap();
    p
}

const QUADRATIC_SIM: &str = "  damping = 10 /s\n  mass_scaling = 2\n  use rubber\n  use soft in tipzone\n  use mr in front\n  pressure cavity = p_peak * ramp(t, 3 ms)";

fn cpu_run(scene: &Scene, dt: Option<f64>, steps: u64) -> RunSummary {
    let cpu = Cpu::new(&scene.lowered.module, Precision::F64, Some(1)).unwrap();
    Simulation::new(scene, cpu).run(dt, Some(steps)).unwrap()
}

/// Quadratic elements: the reference's own 10-node forces, 6-node follower pressure and HRZ
/// masses against the compiled kernels (CPU, f64) over 400 steps of an inflation. Both
/// integrate the same 4-point rule and exact (different) triangle rules, so they differ only
/// by round-off, amplified by the dynamics: measured 2e-13 relative in positions and 1e-11
/// in velocities (relative to the largest speed, still small early in the ramp); held to
/// 1e-10 and 1e-9.
#[test]
fn quadratic_elements_agree_with_the_cpu_backend() {
    let p = quadratic_bench("quadratic", QUADRATIC_SIM);
    let scene = load(&p);
    assert_eq!(scene.order(), softc_compiler::ir::ElementOrder::Quadratic);
    assert_eq!(scene.lowered.materials.len(), 3);
    assert!(scene.material_ranges.iter().all(|r| !r.is_empty()));
    // Masses: the reference's HRZ lumping (its own quadrature) against the scene's.
    let r = Reference::new(&scene).unwrap();
    let mut worst_mass: f64 = 0.0;
    for (a, b) in r.masses().iter().zip(&scene.pre.mass) {
        worst_mass = worst_mass.max((a - b).abs() / b);
    }
    drop(r);
    eprintln!("quadratic masses: max relative difference {worst_mass:.1e}");
    assert!(worst_mass < 1e-12, "{worst_mass}");
    let (dt, steps) = (Some(10e-6), 400);
    let cpu = cpu_run(&scene, dt, steps);
    let rf = reference::run(&scene, dt, Some(steps)).unwrap();
    let (dx, dv) = relative_difference(&scene, &rf, &cpu);
    let tip = &scene.node_sets.iter().find(|(n, _)| n == "tip").unwrap().1;
    let z = |s: &RunSummary| {
        tip.iter()
            .map(|&n| s.x[n as usize][2] - scene.mesh.nodes[n as usize][2])
            .sum::<f64>()
            / tip.len() as f64
    };
    eprintln!(
        "quadratic, {steps} steps: tip mean z {:.6e} m (cpu {:.6e} m); max relative difference x {dx:.2e}, v {dv:.2e}",
        z(&rf),
        z(&cpu)
    );
    assert!(z(&rf).abs() > 1e-6, "the load did little: {}", z(&rf));
    assert!(dx < 1e-10 && dv < 1e-9, "x {dx:e}, v {dv:e}");
}

/// Curved quadratic elements: every mid-edge node of the beam moved off its edge by up to
/// 0.2 mm (edges are 2.5–5 mm), the scene's rest data and masses recomputed, then the same
/// comparison as above. Here the rest Jacobians vary over each element and the chamber's
/// 6-node triangles are curved, so the reference's isoparametric gradients, its degree-7 HRZ
/// quadrature and its 7-point face rule are checked against the scene's and the kernels'.
/// Measured: masses 1e-14, positions 2e-13 relative; held to 1e-12 and 1e-10.
#[test]
fn curved_quadratic_elements_agree_with_the_cpu_backend() {
    let p = quadratic_bench("quadratic_curved", QUADRATIC_SIM);
    let mut scene = load(&p);
    let mids: std::collections::BTreeSet<u32> = scene
        .mesh
        .mid_edges
        .as_ref()
        .unwrap()
        .tets
        .iter()
        .flatten()
        .copied()
        .collect();
    for &n in &mids {
        let s = n as f64;
        let d = [(1.7 * s).sin(), (2.3 * s).cos(), (0.9 * s).sin()];
        for (c, d) in scene.mesh.nodes[n as usize].iter_mut().zip(d) {
            *c += 0.2e-3 / 3f64.sqrt() * d;
        }
    }
    let mut rho = vec![0.0; scene.mesh.tets.len()];
    for (m, range) in scene.material_ranges.iter().enumerate() {
        rho[range.clone()].fill(scene.resolved.densities[m]);
    }
    let mut pre = softc::mesh::precompute::Precomputed::new(&scene.mesh, &rho).unwrap();
    pre.mass
        .iter_mut()
        .for_each(|m| *m *= scene.resolved.sim.mass_scaling);
    scene.pre = pre;
    let conn = scene.elem_conn();
    scene.rest_shape = conn
        .chunks(10)
        .flat_map(|c| {
            let x: [[f64; 3]; 10] = std::array::from_fn(|a| scene.mesh.nodes[c[a] as usize]);
            softc_compiler::driver::quadratic_rest_shape(&x).expect("a valid curved element")
        })
        .collect();
    let r = Reference::new(&scene).unwrap();
    let mut worst_mass: f64 = 0.0;
    for (a, b) in r.masses().iter().zip(&scene.pre.mass) {
        worst_mass = worst_mass.max((a - b).abs() / b);
    }
    drop(r);
    let (dt, steps) = (Some(10e-6), 400);
    let cpu = cpu_run(&scene, dt, steps);
    let rf = reference::run(&scene, dt, Some(steps)).unwrap();
    let (dx, dv) = relative_difference(&scene, &rf, &cpu);
    eprintln!("curved quadratic, {steps} steps: masses {worst_mass:.1e}, x {dx:.2e}, v {dv:.2e}");
    assert!(worst_mass < 1e-12, "{worst_mass}");
    assert!(dx < 1e-10 && dv < 1e-9, "x {dx:e}, v {dv:e}");
}

/// Quadratic element forces are −∂E/∂x with E = Σ_q V_q·W(F_q): central differences of the
/// reference's own energy at a perturbed configuration, for each material.
#[test]
fn quadratic_element_forces_are_the_energy_gradient() {
    let p = quadratic_bench("quadratic_fd", QUADRATIC_SIM);
    let scene = load(&p);
    let mut r = Reference::new(&scene).unwrap();
    for range in &scene.material_ranges {
        let e = range.start;
        let nodes = r.element_nodes(e);
        assert_eq!(nodes.len(), 10);
        let mut x: [[f64; 3]; 10] = std::array::from_fn(|a| scene.mesh.nodes[nodes[a] as usize]);
        for (a, p) in x.iter_mut().enumerate() {
            for (k, c) in p.iter_mut().enumerate() {
                *c += 5e-5 * ((3 * a + k) as f64 * 1.3).sin();
            }
        }
        let res = r.element_quadratic(e, &x).unwrap();
        assert!(res.j.iter().all(|&j| j > 0.5 && j < 1.5), "{:?}", res.j);
        let scale = res
            .forces
            .iter()
            .flatten()
            .fold(0.0_f64, |m, f| m.max(f.abs()));
        let h = 1e-8;
        for a in 0..10 {
            for k in 0..3 {
                let (mut xp, mut xm) = (x, x);
                xp[a][k] += h;
                xm[a][k] -= h;
                let ep = r.element_quadratic(e, &xp).unwrap().energy;
                let em = r.element_quadratic(e, &xm).unwrap().energy;
                let fd = -(ep - em) / (2.0 * h);
                assert!(
                    (fd - res.forces[a][k]).abs() < 1e-5 * scale,
                    "element {e}, node {a}, {k}: fd {fd:e} vs {:e} (scale {scale:e})",
                    res.forces[a][k]
                );
            }
        }
        // Momentum balance.
        for k in 0..3 {
            let s: f64 = res.forces.iter().map(|f| f[k]).sum();
            assert!(s.abs() < 1e-12 * scale, "{s}");
        }
    }
}

/// The quadratic beam's stable step: the reference's power iteration on its own M⁻¹K and the
/// engine's Lanczos estimate agree (2 %).
#[test]
fn quadratic_stable_dt_agrees_with_the_engine() {
    let p = quadratic_bench("quadratic_dt", QUADRATIC_SIM);
    let scene = load(&p);
    let est = Reference::new(&scene)
        .unwrap()
        .stable_dt_estimate()
        .unwrap();
    let cpu = Cpu::new(&scene.lowered.module, Precision::F64, Some(1)).unwrap();
    let engine = Simulation::new(&scene, cpu).stable_dt_estimate().unwrap();
    eprintln!("stable dt (quadratic): reference {est:e} s, engine {engine:e} s");
    assert!((est - engine).abs() < 0.02 * est, "{est} vs {engine}");
}
