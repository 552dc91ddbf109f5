#![allow(clippy::needless_range_loop)] // small fixed-size loops read clearer with indices

//! Quadratic (10-node) tetrahedra and 6-node chamber triangles: the element kernel is the exact
//! negative gradient of its quadrature energy Σ V_q·W(F_q), also on curved elements; an affine
//! deformation gives the linear element's energy and no force under rigid motion; the follower
//! pressure on a curved 6-node triangle equals an independent high-order integration.

use softc_compiler::driver::quadratic_rest_shape;
use softc_compiler::front::parse;
use softc_compiler::ir::{ArgSource, Domain, ElementOrder, Kernel, KernelBuilder, Module, interp};
use softc_compiler::lower::fem::{element_diagnostics_kernel, element_force_kernel};
use softc_compiler::lower::quadratic::store_pressure_forces;
use softc_compiler::passes::simplify::simplify_module;
use softc_compiler::sema;

mod common;
use common::{MATERIALS, NAMES};

/// (name, module, force kernel, diagnostics kernel) per material, for `order`.
fn kernels(order: ElementOrder) -> Vec<(String, Module, Kernel, Kernel)> {
    let ast = parse(MATERIALS).unwrap();
    let (checked, diags) = sema::check(&ast, &Default::default());
    assert!(diags.iter().all(|d| !d.is_error()), "{diags:?}");
    let program = checked.program;
    NAMES
        .iter()
        .map(|n| {
            let mut m = Module {
                order,
                ..Module::default()
            };
            let k = element_force_kernel(&program, &mut m, n).unwrap();
            let i = m.push_kernel(k);
            let d = element_diagnostics_kernel(&program, &mut m, n).unwrap();
            let j = m.push_kernel(d);
            simplify_module(&mut m);
            let (k, d) = (m.kernels[i].clone(), m.kernels[j].clone());
            (n.to_string(), m, k, d)
        })
        .collect()
}

/// Run an element kernel on one element: (forces per node, energy, J).
fn run(module: &Module, k: &Kernel, rest: &[f64], vol0: f64, x: &[[f64; 3]]) -> Outputs {
    let args: Vec<f64> = k
        .args
        .iter()
        .map(|a| match a {
            ArgSource::Corner {
                corner, component, ..
            } => x[*corner as usize][*component as usize],
            ArgSource::Own { buffer, component } => {
                match module.buffers[buffer.0 as usize].name.as_str() {
                    "rest_shape" => rest[*component as usize],
                    "vol0" => vol0,
                    other => panic!("unexpected buffer {other}"),
                }
            }
            other => panic!("unexpected argument {other:?}"),
        })
        .collect();
    let out = interp::eval(&k.body, &args);
    let mut o = Outputs {
        f: vec![[0.0; 3]; x.len()],
        energy: f64::NAN,
        j: f64::NAN,
    };
    for st in &k.stores {
        let v = out[st.output];
        match module.buffers[st.buffer.0 as usize].name.as_str() {
            "elem_force" => o.f[st.component as usize / 3][st.component as usize % 3] = v,
            "elem_energy" => o.energy = v,
            "elem_j" => o.j = v,
            _ => {}
        }
    }
    o
}

struct Outputs {
    f: Vec<[f64; 3]>,
    energy: f64,
    j: f64,
}

const MM: f64 = 1e-3;
/// VTK's node order (`VTK_QUADRATIC_TETRA`, `VTK_QUADRATIC_TRIANGLE`), written out here.
const TET_EDGES: [[usize; 2]; 6] = [[0, 1], [1, 2], [0, 2], [0, 3], [1, 3], [2, 3]];
const TRI_EDGES: [[usize; 2]; 3] = [[0, 1], [1, 2], [2, 0]];

fn corners() -> [[f64; 3]; 4] {
    [
        [0.0, 0.0, 0.0],
        [2.0, 0.1, 0.0],
        [0.3, 1.7, 0.2],
        [0.2, 0.4, 1.9],
    ]
    .map(|p| p.map(|c: f64| c * MM))
}

/// The 10 nodes of a straight-sided element on `c`, mid-edge nodes at the midpoints.
fn straight(c: [[f64; 3]; 4]) -> Vec<[f64; 3]> {
    let mut x = c.to_vec();
    for [i, j] in TET_EDGES {
        x.push([0, 1, 2].map(|d| 0.5 * (c[i][d] + c[j][d])));
    }
    x
}

/// A curved element: the mid-edge nodes moved off their edges by up to 8 % of an edge.
fn curved() -> Vec<[f64; 3]> {
    let mut x = straight(corners());
    let bumps = [
        [0.05, -0.08, 0.1],
        [-0.1, 0.04, 0.06],
        [0.07, 0.09, -0.05],
        [-0.06, 0.03, 0.12],
        [0.1, -0.07, 0.02],
        [0.02, 0.11, -0.09],
    ];
    for (m, b) in bumps.iter().enumerate() {
        for d in 0..3 {
            x[4 + m][d] += b[d] * MM;
        }
    }
    x
}

/// A finite, non-affine deformation of `rest`.
fn deform(rest: &[[f64; 3]]) -> Vec<[f64; 3]> {
    let f = [[1.15, 0.08, -0.05], [0.03, 0.92, 0.1], [-0.04, 0.06, 1.05]];
    let mut x: Vec<[f64; 3]> = rest
        .iter()
        .map(|p| [0, 1, 2].map(|r| f[r][0] * p[0] + f[r][1] * p[1] + f[r][2] * p[2]))
        .collect();
    x[2][0] += 0.07 * MM;
    x[5][1] -= 0.05 * MM;
    x[9][2] += 0.04 * MM;
    x
}

fn rest_of(x: &[[f64; 3]]) -> Vec<f64> {
    quadratic_rest_shape(&x.try_into().unwrap()).expect("a valid element")
}

#[test]
fn quadratic_forces_are_the_negative_gradient_of_the_quadrature_energy() {
    for rest in [straight(corners()), curved()] {
        let rs = rest_of(&rest);
        let vol: f64 = rs.chunks(8).map(|p| p[7]).sum();
        let x = deform(&rest);
        for (name, m, k, d) in kernels(ElementOrder::Quadratic) {
            let f = run(&m, &k, &rs, vol, &x).f;
            let scale = f.iter().flatten().fold(0.0f64, |a, b| a.max(b.abs()));
            let h = 1e-9;
            let mut worst: f64 = 0.0;
            for a in 0..10 {
                for dim in 0..3 {
                    let (mut plus, mut minus) = (x.clone(), x.clone());
                    plus[a][dim] += h;
                    minus[a][dim] -= h;
                    let ep = run(&m, &d, &rs, vol, &plus).energy;
                    let em = run(&m, &d, &rs, vol, &minus).energy;
                    worst = worst.max((-(ep - em) / (2.0 * h) - f[a][dim]).abs() / scale);
                }
            }
            assert!(worst < 1e-6, "{name}: force vs -dE/dx {worst:e}");
            for dim in 0..3 {
                let s: f64 = f.iter().map(|fa| fa[dim]).sum();
                assert!(s.abs() < 1e-12 * scale, "{name}: net force {s}");
            }
        }
    }
}

#[test]
fn an_affine_deformation_has_the_linear_elements_energy_and_rigid_motion_no_force() {
    let c = corners();
    let rest = straight(c);
    let rs = rest_of(&rest);
    let vol = common::signed_volume(c);
    // The quadrature volumes add up to the element's volume.
    let sum: f64 = rs.chunks(8).map(|p| p[7]).sum();
    assert!((sum - vol).abs() < 1e-14 * vol, "{sum} vs {vol}");
    let f = [[1.1, 0.05, -0.02], [0.0, 0.95, 0.07], [0.03, -0.01, 1.04]];
    let affine = |p: &[f64; 3]| [0, 1, 2].map(|r| f[r][0] * p[0] + f[r][1] * p[1] + f[r][2] * p[2]);
    let x: Vec<[f64; 3]> = rest.iter().map(affine).collect();
    let linear = kernels(ElementOrder::Linear);
    for ((name, m, k, d), (_, lm, _, ld)) in
        kernels(ElementOrder::Quadratic).into_iter().zip(linear)
    {
        let q = run(&m, &d, &rs, vol, &x);
        let l = run(&lm, &ld, &common::rest_shape(c), vol, &x[..4]);
        assert!(
            (q.energy - l.energy).abs() <= 1e-12 * l.energy.abs(),
            "{name}: quadratic {} vs linear {}",
            q.energy,
            l.energy
        );
        assert!((q.j - l.j).abs() < 1e-13, "{name}: J {} vs {}", q.j, l.j);
        // A rotation by 30° about z and a translation: no force.
        let (s, co) = (30f64.to_radians().sin(), 30f64.to_radians().cos());
        let rot: Vec<[f64; 3]> = rest
            .iter()
            .map(|p| {
                [
                    co * p[0] - s * p[1] + 0.01,
                    s * p[0] + co * p[1],
                    p[2] - 0.02,
                ]
            })
            .collect();
        for v in run(&m, &k, &rs, vol, &rot).f.iter().flatten() {
            assert!(v.abs() < 1e-8, "{name}: force under rotation {v}");
        }
        for v in run(&m, &k, &rs, vol, &rest).f.iter().flatten() {
            assert!(v.abs() < 1e-9, "{name}: force at rest {v}");
        }
    }
}

/// The pressure forces of the compiler's 6-node triangle kernel at positions `x`, pressure p.
fn pressure_forces(x: &[[f64; 3]; 6], p: f64) -> [[f64; 3]; 6] {
    let mut m = Module {
        order: ElementOrder::Quadratic,
        ..Module::default()
    };
    let xb = m.buffer("x", Domain::Node, 3, "");
    let tf = m.buffer("tri_force", Domain::Triangle, 18, "");
    let mut k = KernelBuilder::new("pressure", Domain::Triangle, "test");
    let pv = k.uniform("p");
    store_pressure_forces(&mut k, xb, tf, pv);
    let built = k.finish();
    let kernel = built.kernel;
    let args: Vec<f64> = kernel
        .args
        .iter()
        .map(|a| match a {
            ArgSource::Corner {
                corner, component, ..
            } => x[*corner as usize][*component as usize],
            ArgSource::Uniform(_) => p,
            other => panic!("unexpected argument {other:?}"),
        })
        .collect();
    let out = interp::eval(&kernel.body, &args);
    let mut f = [[0.0; 3]; 6];
    for st in &kernel.stores {
        f[st.component as usize / 3][st.component as usize % 3] = out[st.output];
    }
    f
}

/// p·∫ Nₐ (x_ξ × x_η) dξ dη by a 12 × 12 Gauss product rule on the collapsed square (exact
/// far beyond the integrand's degree 4), written here without the compiler's shape code.
fn pressure_by_product_rule(x: &[[f64; 3]; 6], p: f64) -> [[f64; 3]; 6] {
    let (gx, gw) = gauss_legendre(12);
    let mut f = [[0.0; 3]; 6];
    for (i, &u) in gx.iter().enumerate() {
        for (j, &v) in gx.iter().enumerate() {
            // (u, v) in [0, 1]²: ξ = u, η = (1 − u)·v, dξ dη = (1 − u) du dv.
            let (xi, eta) = (u, (1.0 - u) * v);
            let w = gw[i] * gw[j] * (1.0 - u);
            let l = [1.0 - xi - eta, xi, eta];
            let n = [
                l[0] * (2.0 * l[0] - 1.0),
                l[1] * (2.0 * l[1] - 1.0),
                l[2] * (2.0 * l[2] - 1.0),
                4.0 * l[0] * l[1],
                4.0 * l[1] * l[2],
                4.0 * l[2] * l[0],
            ];
            // ∂N/∂ξ and ∂N/∂η.
            let dxi = [
                -(4.0 * l[0] - 1.0),
                4.0 * l[1] - 1.0,
                0.0,
                4.0 * (l[0] - l[1]),
                4.0 * l[2],
                -4.0 * l[2],
            ];
            let deta = [
                -(4.0 * l[0] - 1.0),
                0.0,
                4.0 * l[2] - 1.0,
                -4.0 * l[1],
                4.0 * l[1],
                4.0 * (l[0] - l[2]),
            ];
            let t1 = [0, 1, 2].map(|d| (0..6).map(|a| x[a][d] * dxi[a]).sum::<f64>());
            let t2 = [0, 1, 2].map(|d| (0..6).map(|a| x[a][d] * deta[a]).sum::<f64>());
            let c = [
                t1[1] * t2[2] - t1[2] * t2[1],
                t1[2] * t2[0] - t1[0] * t2[2],
                t1[0] * t2[1] - t1[1] * t2[0],
            ];
            for a in 0..6 {
                for d in 0..3 {
                    f[a][d] += p * w * n[a] * c[d];
                }
            }
        }
    }
    f
}

/// Gauss–Legendre points and weights on [0, 1] (Newton on the Legendre polynomial).
fn gauss_legendre(n: usize) -> (Vec<f64>, Vec<f64>) {
    let (mut xs, mut ws) = (Vec::new(), Vec::new());
    for i in 0..n {
        let mut z = (std::f64::consts::PI * (i as f64 + 0.75) / (n as f64 + 0.5)).cos();
        for _ in 0..100 {
            let (mut p0, mut p1) = (1.0, z);
            for k in 2..=n {
                let p2 = ((2 * k - 1) as f64 * z * p1 - (k - 1) as f64 * p0) / k as f64;
                p0 = p1;
                p1 = p2;
            }
            let dp = n as f64 * (z * p1 - p0) / (z * z - 1.0);
            let dz = p1 / dp;
            z -= dz;
            if dz.abs() < 1e-16 {
                let (mut q0, mut q1) = (1.0, z);
                for k in 2..=n {
                    let q2 = ((2 * k - 1) as f64 * z * q1 - (k - 1) as f64 * q0) / k as f64;
                    q0 = q1;
                    q1 = q2;
                }
                let dq = n as f64 * (z * q1 - q0) / (z * z - 1.0);
                xs.push(0.5 * (1.0 - z));
                ws.push(1.0 / ((1.0 - z * z) * dq * dq));
                break;
            }
        }
    }
    (xs, ws)
}

#[test]
fn six_node_pressure_is_exact_on_curved_triangles_and_loads_only_mid_edges_when_flat() {
    let c = [[0.0, 0.0, 0.0], [3.0, 0.2, 0.0], [0.5, 2.5, 0.1]].map(|p| p.map(|v: f64| v * MM));
    let mut x = [[0.0; 3]; 6];
    x[..3].copy_from_slice(&c);
    for (m, [i, j]) in TRI_EDGES.into_iter().enumerate() {
        x[3 + m] = [0, 1, 2].map(|d| 0.5 * (c[i][d] + c[j][d]));
    }
    let p = 20e3;
    // Flat: corners carry nothing, each mid-edge node p·A·n/3.
    let flat = pressure_forces(&x, p);
    let e1 = [0, 1, 2].map(|d| c[1][d] - c[0][d]);
    let e2 = [0, 1, 2].map(|d| c[2][d] - c[0][d]);
    let an = [
        0.5 * (e1[1] * e2[2] - e1[2] * e2[1]),
        0.5 * (e1[2] * e2[0] - e1[0] * e2[2]),
        0.5 * (e1[0] * e2[1] - e1[1] * e2[0]),
    ];
    let scale = p * an.iter().map(|v| v * v).sum::<f64>().sqrt();
    for a in 0..6 {
        for d in 0..3 {
            let want = if a < 3 { 0.0 } else { p * an[d] / 3.0 };
            assert!(
                (flat[a][d] - want).abs() < 1e-13 * scale,
                "node {a}: {} vs {want}",
                flat[a][d]
            );
        }
    }
    // Curved: against the product rule.
    x[3][2] += 0.3 * MM;
    x[4][0] -= 0.2 * MM;
    x[5][2] -= 0.25 * MM;
    let got = pressure_forces(&x, p);
    let want = pressure_by_product_rule(&x, p);
    for a in 0..6 {
        for d in 0..3 {
            assert!(
                (got[a][d] - want[a][d]).abs() < 1e-12 * scale,
                "node {a} dim {d}: {} vs {}",
                got[a][d],
                want[a][d]
            );
        }
    }
}
