#![allow(clippy::needless_range_loop)] // small fixed-size loops read clearer with indices

//! The element force kernel the compiler generates from a strain energy W must be the exact
//! negative gradient of the element's energy V0·W (checked against central finite differences
//! in f64), vanish at rest, and reproduce closed-form stresses.

use softc_compiler::front::parse;
use softc_compiler::ir::{ArgSource, Kernel, Module, interp};
use softc_compiler::lower::fem::{
    element_diagnostics_kernel, element_force_kernel, material_density,
};
use softc_compiler::passes::simplify::simplify_module;
use softc_compiler::sema;

mod common;
use common::{MATERIALS, NAMES};

struct Tet {
    rest: [[f64; 3]; 4],
    x: [[f64; 3]; 4],
}

impl Tet {
    fn rest_shape(&self) -> [f64; 7] {
        common::rest_shape(self.rest)
    }
    fn vol0(&self) -> f64 {
        common::signed_volume(self.rest)
    }
}

/// Run an element force kernel and the diagnostics kernel of `module` on one tet: (forces
/// [corner][dim], energy).
fn run(module: &Module, k: &Kernel, tet: &Tet) -> ([[f64; 3]; 4], f64) {
    let (f, _) = run_one(module, k, tet);
    let (_, e) = run_one(module, module.kernels.last().expect("diagnostics"), tet);
    (f, e)
}

fn run_one(module: &Module, k: &Kernel, tet: &Tet) -> ([[f64; 3]; 4], f64) {
    let rest = tet.rest_shape();
    let args: Vec<f64> = k
        .args
        .iter()
        .map(|a| match a {
            ArgSource::Corner {
                buffer,
                corner,
                component,
            } => {
                assert_eq!(module.buffers[buffer.0 as usize].name, "x");
                tet.x[*corner as usize][*component as usize]
            }
            ArgSource::Own { buffer, component } => {
                match module.buffers[buffer.0 as usize].name.as_str() {
                    "rest_shape" => rest[*component as usize],
                    "vol0" => tet.vol0(),
                    other => panic!("unexpected buffer {other}"),
                }
            }
            other => panic!("unexpected argument {other:?}"),
        })
        .collect();
    let out = interp::eval(&k.body, &args);
    let mut f = [[0.0; 3]; 4];
    let mut e = f64::NAN;
    for st in &k.stores {
        let name = &module.buffers[st.buffer.0 as usize].name;
        let v = out[st.output];
        match name.as_str() {
            "elem_force" => f[st.component as usize / 3][st.component as usize % 3] = v,
            "elem_energy" => e = v,
            _ => {}
        }
    }
    (f, e)
}

fn kernels() -> Vec<(String, Module, Kernel)> {
    let ast = parse(MATERIALS).unwrap();
    let (checked, diags) = sema::check(&ast, &Default::default());
    assert!(diags.iter().all(|d| !d.is_error()), "{diags:?}");
    let program = checked.program;
    NAMES
        .iter()
        .map(|n| {
            let mut m = Module::default();
            let k = element_force_kernel(&program, &mut m, n).unwrap();
            let i = m.push_kernel(k);
            let d = element_diagnostics_kernel(&program, &mut m, n).unwrap();
            m.push_kernel(d);
            // As the backends get them: simplified (the checks hold for the rewritten bodies).
            simplify_module(&mut m);
            let k = m.kernels[i].clone();
            (n.to_string(), m, k)
        })
        .collect()
}

/// A skewed tet in millimetres and a finite deformation of it (stretch, shear, compression).
fn sample_tet() -> Tet {
    let mm = 1e-3;
    let rest = [
        [0.0, 0.0, 0.0],
        [2.0, 0.1, 0.0],
        [0.3, 1.7, 0.2],
        [0.2, 0.4, 1.9],
    ]
    .map(|p| p.map(|c: f64| c * mm));
    let f = [[1.15, 0.08, -0.05], [0.03, 0.92, 0.1], [-0.04, 0.06, 1.05]];
    let x = rest.map(|p| {
        [0, 1, 2].map(|r| f[r][0] * p[0] + f[r][1] * p[1] + f[r][2] * p[2] + 0.1 * mm * r as f64)
    });
    // A non-affine wobble on one node so the test is not special.
    let mut x = x;
    x[2][0] += 0.07 * mm;
    x[3][1] -= 0.05 * mm;
    Tet { rest, x }
}

#[test]
fn forces_are_the_negative_energy_gradient() {
    for (name, module, k) in kernels() {
        let tet = sample_tet();
        let (f, _) = run(&module, &k, &tet);
        let h = 1e-9; // 1 nm on mm-sized elements
        let mut worst: f64 = 0.0;
        let scale = f.iter().flatten().fold(0.0f64, |a, b| a.max(b.abs()));
        for c in 0..4 {
            for d in 0..3 {
                let mut plus = Tet {
                    rest: tet.rest,
                    x: tet.x,
                };
                let mut minus = Tet {
                    rest: tet.rest,
                    x: tet.x,
                };
                plus.x[c][d] += h;
                minus.x[c][d] -= h;
                let fd = -(run(&module, &k, &plus).1 - run(&module, &k, &minus).1) / (2.0 * h);
                worst = worst.max((fd - f[c][d]).abs() / scale);
            }
        }
        assert!(
            worst < 1e-6,
            "{name}: force vs -dE/dx relative error {worst:e}"
        );
        // Momentum balance: internal forces sum to zero.
        for d in 0..3 {
            let s: f64 = (0..4).map(|c| f[c][d]).sum();
            assert!(s.abs() < 1e-12 * scale.max(1.0), "{name}: net force {s}");
        }
    }
}

#[test]
fn no_force_at_rest_and_under_rigid_rotation() {
    for (name, module, k) in kernels() {
        let tet = sample_tet();
        let rest = Tet {
            rest: tet.rest,
            x: tet.rest,
        };
        let (f, e) = run(&module, &k, &rest);
        for c in f.iter().flatten() {
            assert!(c.abs() < 1e-9, "{name}: force at rest {c}");
        }
        assert!(e.abs() < 1e-15, "{name}: energy at rest {e}");
        // A rotation by 30° about z plus a translation: stress-free as well.
        let (s, co) = (30f64.to_radians().sin(), 30f64.to_radians().cos());
        let rot = Tet {
            rest: tet.rest,
            x: tet.rest.map(|p| {
                [
                    co * p[0] - s * p[1] + 0.01,
                    s * p[0] + co * p[1],
                    p[2] - 0.02,
                ]
            }),
        };
        let (f, _) = run(&module, &k, &rot);
        for c in f.iter().flatten() {
            assert!(c.abs() < 1e-8, "{name}: force under rotation {c}");
        }
    }
}

#[test]
fn neo_hookean_stress_matches_the_closed_form_under_triaxial_stretch() {
    // Unit right-angled tet (Dm = I, V0 = 1/6) stretched by F = diag(a, b, c): the forces on
    // nodes 1..3 are the columns of −P/6, so P = −6 f.
    let (mu, kappa) = (0.2e6, 2e6);
    let (a, b, c) = (1.3, 0.9, 0.95);
    let rest = [
        [0.0, 0.0, 0.0],
        [1.0, 0.0, 0.0],
        [0.0, 1.0, 0.0],
        [0.0, 0.0, 1.0],
    ];
    let x = rest.map(|p: [f64; 3]| [a * p[0], b * p[1], c * p[2]]);
    let (_, module, k) = kernels().into_iter().find(|(n, _, _)| n == "nh").unwrap();
    let (f, _) = run(&module, &k, &Tet { rest, x });
    let j = a * b * c;
    let i1 = a * a + b * b + c * c;
    // P = mu J^(-2/3) (F − I1/3 F^-T) + kappa (J − 1) J F^-T, diagonal for a diagonal F.
    for (i, s) in [a, b, c].into_iter().enumerate() {
        let p = mu * j.powf(-2.0 / 3.0) * (s - i1 / (3.0 * s)) + kappa * (j - 1.0) * j / s;
        let got = -6.0 * f[i + 1][i];
        assert!(
            (got - p).abs() < 1e-9 * p.abs().max(1.0),
            "P[{i}][{i}] = {got}, closed form {p}"
        );
    }
}

#[test]
fn stable_neo_hookean_has_the_lame_parameters_at_small_strain_and_no_isochoric_factor() {
    // Unit right-angled tet (P = −6 f on nodes 1..3): at F = I + εG the stress is the linear
    // elastic 2μ·sym(εG) + λ·tr(εG)·I of the Lamé parameters given, up to O(ε²).
    let (mu, lambda) = (0.3e6 / 2.9, 0.3e6 * 0.45 / (1.45 * 0.1));
    let eps = 1e-6;
    let g = [[0.3, -0.7, 0.2], [0.5, 0.1, -0.4], [0.9, 0.6, -0.2]];
    let rest = [
        [0.0, 0.0, 0.0],
        [1.0, 0.0, 0.0],
        [0.0, 1.0, 0.0],
        [0.0, 0.0, 1.0],
    ];
    let x = rest.map(|p: [f64; 3]| {
        [0, 1, 2].map(|r| p[r] + eps * (0..3).map(|c| g[r][c] * p[c]).sum::<f64>())
    });
    let (_, module, k) = kernels().into_iter().find(|(n, _, _)| n == "snh").unwrap();
    let (f, _) = run(&module, &k, &Tet { rest, x });
    let tr = eps * (g[0][0] + g[1][1] + g[2][2]);
    for r in 0..3 {
        for c in 0..3 {
            let lin = mu * eps * (g[r][c] + g[c][r]) + if r == c { lambda * tr } else { 0.0 };
            // Column c of −P/6 acts on node c+1.
            let got = -6.0 * f[c + 1][r];
            assert!(
                (got - lin).abs() < 1e-5 * (mu * eps),
                "P[{r}][{c}] = {got}, linear elasticity {lin}"
            );
        }
    }
    // Written in I1 and J: the kernel has no cube root (J^(-2/3)) and no division by J.
    let ir = format!("{:?}", k.body.insts);
    assert!(!ir.contains("Pow"), "isochoric factor generated for snh");
}

#[test]
fn materials_without_i2bar_generate_no_i2bar_terms() {
    // Specialization is visible in the kernel: Yeoh has no W2 term, Mooney-Rivlin does.
    let count = |name: &str| {
        kernels()
            .into_iter()
            .find(|(n, _, _)| n == name)
            .map(|(_, _, k)| k.body.insts.len())
            .unwrap()
    };
    assert!(
        count("yeoh3") < count("mr"),
        "yeoh {} vs mooney-rivlin {}",
        count("yeoh3"),
        count("mr")
    );
}

#[test]
fn densities_are_constants_in_si() {
    let ast = parse(MATERIALS).unwrap();
    let program = sema::check(&ast, &Default::default()).0.program;
    assert_eq!(material_density(&program, "yeoh3").unwrap(), 1070.0);
    assert!((material_density(&program, "custom").unwrap() - 1200.0).abs() < 1e-9);
}
