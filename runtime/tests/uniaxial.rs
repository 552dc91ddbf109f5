//! Uniaxial tension of a free cube against the closed form, for every prelude material family.
//!
//! Equal and opposite tractions (a negative follower pressure on two opposite faces) stretch a
//! cube with no support. A homogeneous deformation is an exact equilibrium of linear tets under
//! consistent face loads (the patch test), so the simulated steady state must be homogeneous,
//! whatever the mesh, and its stretches must equal the closed form of the material's law:
//! for b̄ = diag(a, c, c) and Cauchy stress diag(s, 0, 0),
//!     σ = (2/J) dev[(W₁ + Ī₁W₂) b̄ − W₂ b̄²] + W_J I
//! gives W_J(J) = s/3 (which fixes J) and (2/J)(m_a − m_c) = s with
//! m = (W₁ + Ī₁W₂) b̄ − W₂ b̄², solved for λ₁ (λ₂² = J/λ₁) by bisection.

use softc::devices::cpu::Cpu;
use softc::engine::Simulation;
use softc::engine::scene::Scene;
use softc_compiler::back::Precision;
use std::path::{Path, PathBuf};

fn fixture(name: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("tests/fixtures/uniaxial")
        .join(name)
}

/// A material's law through its derivatives: W₁(Ī₁, Ī₂), W₂(Ī₁, Ī₂) and W_J(J).
struct Law {
    material: &'static str,
    w1: fn(f64, f64) -> f64,
    w2: fn(f64, f64) -> f64,
    wj: fn(f64) -> f64,
}

const KPA: f64 = 1e3;

fn laws() -> Vec<Law> {
    vec![
        Law {
            material: "neo_hookean(mu: 100 kPa, kappa: 1 MPa, density: 1000 kg/m^3)",
            w1: |_, _| 50.0 * KPA,
            w2: |_, _| 0.0,
            wj: |j| 1000.0 * KPA * (j - 1.0),
        },
        Law {
            // The thesis' silicone (eq. 2.18 coefficients of §6), with its negative c30.
            material: "yeoh(c10: 0.24162 MPa, c20: 0.19977 MPa, c30: -0.00541 MPa, d1: 1.0 /MPa, density: 1070 kg/m^3)",
            w1: |i1, _| {
                let x = i1 - 3.0;
                241.62 * KPA + 2.0 * 199.77 * KPA * x - 3.0 * 5.41 * KPA * x * x
            },
            w2: |_, _| 0.0,
            wj: |j| 2.0 * (j - 1.0) / 1e-6,
        },
        Law {
            material: "mooney_rivlin(c10: 60 kPa, c01: 15 kPa, c11: 5 kPa, d1: 2 /MPa, density: 1000 kg/m^3)",
            w1: |_, i2| 60.0 * KPA + 5.0 * KPA * (i2 - 3.0),
            w2: |i1, _| 15.0 * KPA + 5.0 * KPA * (i1 - 3.0),
            wj: |j| 2.0 * (j - 1.0) / 2e-6,
        },
    ]
}

/// Axial and lateral stretch of the law under Cauchy stress `s`.
fn closed_form(law: &Law, s: f64) -> (f64, f64) {
    let bisect = |f: &dyn Fn(f64) -> f64, mut lo: f64, mut hi: f64| {
        assert!(f(lo) * f(hi) < 0.0, "no sign change in [{lo}, {hi}]");
        for _ in 0..200 {
            let mid = 0.5 * (lo + hi);
            if f(lo) * f(mid) <= 0.0 {
                hi = mid;
            } else {
                lo = mid;
            }
        }
        0.5 * (lo + hi)
    };
    let j = bisect(&|j| (law.wj)(j) - s / 3.0, 0.5, 1.5);
    let stress_diff = |l1: f64| {
        let l2sq = j / l1;
        let (a, c) = (j.powf(-2.0 / 3.0) * l1 * l1, j.powf(-2.0 / 3.0) * l2sq);
        let (i1, i2) = (a + 2.0 * c, 2.0 * a * c + c * c);
        let (w1, w2) = ((law.w1)(i1, i2), (law.w2)(i1, i2));
        let m = |b: f64| (w1 + i1 * w2) * b - w2 * b * b;
        2.0 / j * (m(a) - m(c)) - s
    };
    let l1 = bisect(&stress_diff, 1.0, 2.0);
    (l1, (j / l1).sqrt())
}

/// The affine map x = F X + c that fits the nodes best (least squares), and the largest
/// distance of a node from it.
fn fit_affine(rest: &[[f64; 3]], x: &[[f64; 3]]) -> (nalgebra::Matrix3<f64>, f64) {
    let n = rest.len();
    let a = nalgebra::DMatrix::from_fn(n, 4, |i, k| if k < 3 { rest[i][k] } else { 1.0 });
    let b = nalgebra::DMatrix::from_fn(n, 3, |i, k| x[i][k]);
    let sol = a
        .clone()
        .svd(true, true)
        .solve(&b, 1e-14)
        .expect("least squares");
    let fitted = &a * &sol;
    let residual = (0..n)
        .map(|i| {
            (0..3)
                .map(|k| (fitted[(i, k)] - b[(i, k)]).powi(2))
                .sum::<f64>()
                .sqrt()
        })
        .fold(0.0, f64::max);
    let f = nalgebra::Matrix3::from_fn(|r, c| sol[(c, r)]);
    (f, residual)
}

#[test]
fn a_free_cube_under_uniaxial_tension_stretches_as_the_closed_form_for_every_material() {
    let template = std::fs::read_to_string(fixture("uniaxial.soft")).unwrap();
    let dir = std::env::temp_dir().join(format!("softc-uniaxial-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let s = 30.0 * KPA;
    for (k, law) in laws().iter().enumerate() {
        let text = template
            .replace("MATERIAL", law.material)
            .replace("\"cube.msh\"", &format!("{:?}", fixture("cube.msh")));
        let path = dir.join(format!("uniaxial{k}.soft"));
        std::fs::write(&path, text).unwrap();
        let scene = Scene::load(&path, &[]).unwrap_or_else(|e| panic!("{}: {e}", law.material));
        let cpu = Cpu::new(&scene.lowered.module, Precision::F64, Some(1)).unwrap();
        let run = Simulation::new(&scene, cpu)
            .run_to_steady_state(None, 400_000, 1e-8)
            .unwrap();
        assert!(run.settled, "{}: did not settle", law.material);
        let (f, residual) = fit_affine(&scene.mesh.nodes, &run.summary.x);
        let u_max = scene
            .mesh
            .nodes
            .iter()
            .zip(&run.summary.x)
            .map(|(p, q)| ((0..3).map(|d| (q[d] - p[d]).powi(2)).sum::<f64>()).sqrt())
            .fold(0.0, f64::max);
        // Stretches from C = FᵀF (free of any rigid rotation the body may have taken).
        let c = f.transpose() * f;
        let (want1, want2) = closed_form(law, s);
        let (l1, l2, l3) = (c[(0, 0)].sqrt(), c[(1, 1)].sqrt(), c[(2, 2)].sqrt());
        let strain_error = [(l1, want1), (l2, want2), (l3, want2)]
            .iter()
            .map(|(got, want)| (got - want).abs() / (want - 1.0).abs())
            .fold(0.0, f64::max);
        eprintln!(
            "{}: stretches {l1:.8} {l2:.8} {l3:.8}, closed form {want1:.8} {want2:.8} \
             (strain error {strain_error:.1e}); off-affine {:.2e} of the largest displacement; \
             {} steps",
            law.material,
            residual / u_max,
            run.summary.steps
        );
        assert!(residual < 1e-9 * u_max, "{}: not homogeneous", law.material);
        for (got, want) in [(l1, want1), (l2, want2), (l3, want2)] {
            assert!(
                (got - want).abs() < 1e-9 * (want - 1.0).abs(),
                "{}: stretch {got}, closed form {want}",
                law.material
            );
        }
        for (r, col) in [(0, 1), (0, 2), (1, 2)] {
            assert!(c[(r, col)].abs() < 1e-8, "{}: shear in C", law.material);
        }
    }
}
