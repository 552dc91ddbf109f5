//! Quadratic (10-node) tetrahedra and 6-node chamber triangles for the reference simulator,
//! derived here from the shape functions (not from the compiler's lowering).
//!
//! Nodes: the 4 corners, then the mid-edge nodes of edges 0-1, 1-2, 0-2, 0-3, 1-3, 2-3 (VTK's
//! order); a triangle's corners, then its edges 0-1, 1-2, 2-0. With barycentrics
//! L = (1 − ξ − η − ζ, ξ, η, ζ), corner i has Nᵢ = Lᵢ(2Lᵢ − 1) and edge (i, j) has 4LᵢLⱼ.
//!
//! - **Rest data** per quadrature point q of the 4-point degree-2 rule (barycentric (a, b, b, b)
//!   and permutations, a = (5 + 3√5)/20, b = (5 − √5)/20, weight 1/24 on the reference tet of
//!   volume 1/6): the isoparametric Jacobian J_q = Σₐ Xₐ ⊗ ∇_ξNₐ, the gradients
//!   ∇_X Nₐ = J_q⁻ᵀ ∇_ξNₐ and the point's volume V_q = w_q·det J_q ([`rest_points`]).
//! - **Forces**: F_q = Σₐ xₐ ⊗ ∇_X Nₐ, fₐ = −Σ_q V_q·P(F_q)·∇_X Nₐ ([`forces`]).
//! - **Follower pressure** on a 6-node triangle: fₐ = p ∫ Nₐ (x,ξ × x,η) dξ dη by Radon's
//!   7-point rule of degree 5 (exact: the integrand has degree 4), [`pressure_forces`].
//! - **Masses**: HRZ lumping, the consistent diagonal ∫ρNₐ² dV scaled to the element's mass
//!   ρ·∫det J, integrated by a collapsed 5×5×5 Gauss–Legendre product rule, exact for curved
//!   elements too (Nₐ² det J has degree 7), [`hrz_masses`].

use nalgebra::{Matrix3, Vector3};

type Vec3 = Vector3<f64>;

/// The tet's mid-edge nodes 4–9 as corner pairs.
pub const TET_EDGES: [[usize; 2]; 6] = [[0, 1], [1, 2], [0, 2], [0, 3], [1, 3], [2, 3]];
/// The triangle's mid-edge nodes 3–5 as corner pairs.
pub const TRI_EDGES: [[usize; 2]; 3] = [[0, 1], [1, 2], [2, 0]];

/// ∂Lᵢ/∂(ξ, η, ζ).
fn dl() -> [Vec3; 4] {
    [
        Vec3::new(-1.0, -1.0, -1.0),
        Vec3::new(1.0, 0.0, 0.0),
        Vec3::new(0.0, 1.0, 0.0),
        Vec3::new(0.0, 0.0, 1.0),
    ]
}

fn barycentric(xi: [f64; 3]) -> [f64; 4] {
    [1.0 - xi[0] - xi[1] - xi[2], xi[0], xi[1], xi[2]]
}

/// The 10 shape functions at reference point ξ.
pub fn tet_shape(xi: [f64; 3]) -> [f64; 10] {
    let l = barycentric(xi);
    std::array::from_fn(|a| {
        if a < 4 {
            l[a] * (2.0 * l[a] - 1.0)
        } else {
            let [i, j] = TET_EDGES[a - 4];
            4.0 * l[i] * l[j]
        }
    })
}

/// ∇_ξ of the 10 shape functions at reference point ξ.
pub fn tet_shape_gradients(xi: [f64; 3]) -> [Vec3; 10] {
    let l = barycentric(xi);
    let d = dl();
    std::array::from_fn(|a| {
        if a < 4 {
            d[a] * (4.0 * l[a] - 1.0)
        } else {
            let [i, j] = TET_EDGES[a - 4];
            (d[i] * l[j] + d[j] * l[i]) * 4.0
        }
    })
}

/// The 4-point degree-2 rule: reference points ξ and weights (summing to 1/6).
pub fn tet_rule() -> [([f64; 3], f64); 4] {
    let s5 = 5f64.sqrt();
    let a = (5.0 + 3.0 * s5) / 20.0;
    let b = (5.0 - s5) / 20.0;
    std::array::from_fn(|q| {
        let mut l = [b; 4];
        l[q] = a;
        ([l[1], l[2], l[3]], 1.0 / 24.0)
    })
}

/// Rest data of one quadrature point.
#[derive(Clone, Debug)]
pub struct RestPoint {
    /// ∇_X Nₐ, 1/m.
    pub grad: [Vec3; 10],
    /// w_q·det J_q, m³.
    pub volume: f64,
}

/// J = Σₐ (Xₐ − X₀) ⊗ ∇_ξNₐ (Σₐ ∇_ξNₐ = 0).
fn jacobian(x: &[Vec3; 10], g: &[Vec3; 10]) -> Matrix3<f64> {
    let mut j = Matrix3::zeros();
    for a in 1..10 {
        j += (x[a] - x[0]) * g[a].transpose();
    }
    j
}

/// The rest data at the 4 points of an element with rest positions `x`; `Err(det J)` with the
/// smallest det J if it is not positive (or not finite) at some point.
pub fn rest_points(x: &[Vec3; 10]) -> Result<[RestPoint; 4], f64> {
    let rule = tet_rule();
    let mut out = Vec::with_capacity(4);
    let mut worst = f64::INFINITY;
    for (xi, w) in rule {
        let g = tet_shape_gradients(xi);
        let j = jacobian(x, &g);
        let det = j.determinant();
        worst = worst.min(det);
        let inv_t = match j.try_inverse() {
            Some(inv) if det > 0.0 && det.is_finite() => inv.transpose(),
            _ => continue,
        };
        out.push(RestPoint {
            grad: g.map(|ga| inv_t * ga),
            volume: w * det,
        });
    }
    match <[RestPoint; 4]>::try_from(out) {
        Ok(points) => Ok(points),
        Err(_) => Err(if worst.is_nan() { f64::NAN } else { worst }),
    }
}

/// F = Σₐ (xₐ − x₀) ⊗ ∇_X Nₐ at one point.
pub fn deformation_gradient(p: &RestPoint, x: &[Vec3; 10]) -> Matrix3<f64> {
    jacobian(x, &p.grad)
}

/// Add −V_q·P_q·∇_X Nₐ to each node's force.
pub fn forces(p: &RestPoint, piola: &Matrix3<f64>, out: &mut [Vec3; 10]) {
    let h = piola * (-p.volume);
    for (f, g) in out.iter_mut().zip(&p.grad) {
        *f += h * g;
    }
}

/// The element's volume ∫ det J and its HRZ lumped masses per unit density (summing to the
/// volume).
pub fn hrz_masses(x: &[Vec3; 10]) -> (f64, [f64; 10]) {
    let mut volume = 0.0;
    let mut diag = [0.0; 10];
    for (xi, w) in collapsed_rule() {
        let det = jacobian(x, &tet_shape_gradients(xi)).determinant();
        volume += w * det;
        for (d, n) in diag.iter_mut().zip(tet_shape(xi)) {
            *d += w * det * n * n;
        }
    }
    let s: f64 = diag.iter().sum();
    (volume, diag.map(|d| d * volume / s))
}

/// Gauss–Legendre points and weights of 5 points on [0, 1] (closed forms).
fn gauss5() -> [(f64, f64); 5] {
    let r = (10.0f64 / 7.0).sqrt();
    let (x1, x2) = ((5.0 - 2.0 * r).sqrt() / 3.0, (5.0 + 2.0 * r).sqrt() / 3.0);
    let s70 = 70f64.sqrt();
    let (w1, w2) = ((322.0 + 13.0 * s70) / 900.0, (322.0 - 13.0 * s70) / 900.0);
    [
        (0.0, 128.0 / 225.0),
        (-x1, w1),
        (x1, w1),
        (-x2, w2),
        (x2, w2),
    ]
    .map(|(x, w)| (0.5 * (1.0 + x), 0.5 * w))
}

/// A rule on the reference tet from the cube by ξ = u, η = v(1 − u), ζ = w(1 − u)(1 − v)
/// (Jacobian (1 − u)²(1 − v)): exact to degree 7.
fn collapsed_rule() -> Vec<([f64; 3], f64)> {
    let g = gauss5();
    let mut out = Vec::with_capacity(125);
    for &(u, wu) in &g {
        for &(v, wv) in &g {
            for &(w, ww) in &g {
                let xi = [u, v * (1.0 - u), w * (1.0 - u) * (1.0 - v)];
                out.push((xi, wu * wv * ww * (1.0 - u) * (1.0 - u) * (1.0 - v)));
            }
        }
    }
    out
}

/// Radon's 7-point rule of degree 5 on the reference triangle: barycentrics and weights
/// (summing to 1/2), in closed form.
fn triangle_rule() -> [([f64; 3], f64); 7] {
    let s15 = 15f64.sqrt();
    let (a1, b1) = ((6.0 - s15) / 21.0, (9.0 + 2.0 * s15) / 21.0);
    let (a2, b2) = ((6.0 + s15) / 21.0, (9.0 - 2.0 * s15) / 21.0);
    let (w1, w2) = ((155.0 - s15) / 1200.0, (155.0 + s15) / 1200.0);
    let third = 1.0 / 3.0;
    let mut out = [([third; 3], 0.5 * 9.0 / 40.0); 7];
    for k in 0..3 {
        let mut p = [a1; 3];
        p[k] = b1;
        out[1 + k] = (p, 0.5 * w1);
        let mut p = [a2; 3];
        p[k] = b2;
        out[4 + k] = (p, 0.5 * w2);
    }
    out
}

/// The 6 shape functions of a triangle and their (ξ, η) derivatives at barycentrics `l`.
fn tri_shape(l: [f64; 3]) -> ([f64; 6], [[f64; 2]; 6]) {
    let d = [[-1.0, -1.0], [1.0, 0.0], [0.0, 1.0]];
    let mut n = [0.0; 6];
    let mut g = [[0.0; 2]; 6];
    for i in 0..3 {
        n[i] = l[i] * (2.0 * l[i] - 1.0);
        g[i] = d[i].map(|di| di * (4.0 * l[i] - 1.0));
    }
    for (k, [i, j]) in TRI_EDGES.into_iter().enumerate() {
        n[3 + k] = 4.0 * l[i] * l[j];
        g[3 + k] = [0, 1].map(|c| 4.0 * (d[i][c] * l[j] + d[j][c] * l[i]));
    }
    (n, g)
}

/// The follower load p ∫ Nₐ (x,ξ × x,η) dξ dη on the 6 nodes of a triangle at positions `x`
/// (the linear triangle's p/6·(x1 − x0) × (x2 − x0) per corner is the same integral).
pub fn pressure_forces(x: &[Vec3; 6], p: f64) -> [Vec3; 6] {
    let mut out = [Vec3::zeros(); 6];
    for (l, w) in triangle_rule() {
        let (n, g) = tri_shape(l);
        let (mut dxi, mut deta) = (Vec3::zeros(), Vec3::zeros());
        for a in 1..6 {
            let r = x[a] - x[0];
            dxi += r * g[a][0];
            deta += r * g[a][1];
        }
        let normal = dxi.cross(&deta) * (p * w);
        for (f, na) in out.iter_mut().zip(n) {
            *f += normal * na;
        }
    }
    out
}

/// A straight-sided element: mid-edge nodes at the midpoints of the corners `c`.
pub fn straight(c: &[Vec3; 4]) -> [Vec3; 10] {
    std::array::from_fn(|a| {
        if a < 4 {
            c[a]
        } else {
            let [i, j] = TET_EDGES[a - 4];
            (c[i] + c[j]) * 0.5
        }
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn corners() -> [Vec3; 4] {
        [
            Vec3::new(0.1, -0.2, 0.05),
            Vec3::new(1.3, 0.1, -0.1),
            Vec3::new(0.2, 1.1, 0.3),
            Vec3::new(0.3, 0.2, 0.9),
        ]
    }

    /// A curved element: the straight one with its mid-edge nodes moved off their edges.
    fn curved() -> [Vec3; 10] {
        let mut x = straight(&corners());
        for (a, p) in x.iter_mut().enumerate().skip(4) {
            let s = a as f64;
            *p += Vec3::new(
                0.03 * s.sin(),
                -0.04 * (1.7 * s).cos(),
                0.02 * (0.3 * s).sin(),
            );
        }
        x
    }

    /// Nₐ(X_b) = δ_ab at the 10 nodes, Σ Nₐ = 1 and Σ ∇Nₐ = 0 elsewhere.
    #[test]
    fn shape_functions_interpolate_their_nodes() {
        let nodes: [[f64; 3]; 10] = std::array::from_fn(|a| {
            let c = |i: usize| -> [f64; 3] {
                let mut p = [0.0; 3];
                if i > 0 {
                    p[i - 1] = 1.0;
                }
                p
            };
            if a < 4 {
                c(a)
            } else {
                let [i, j] = TET_EDGES[a - 4];
                let (p, q) = (c(i), c(j));
                [0, 1, 2].map(|k| 0.5 * (p[k] + q[k]))
            }
        });
        for (b, xi) in nodes.iter().enumerate() {
            for (a, n) in tet_shape(*xi).into_iter().enumerate() {
                assert_eq!(n, if a == b { 1.0 } else { 0.0 }, "N{a}(X{b})");
            }
        }
        let xi = [0.21, 0.17, 0.33];
        assert!((tet_shape(xi).iter().sum::<f64>() - 1.0).abs() < 1e-15);
        assert!(tet_shape_gradients(xi).iter().sum::<Vec3>().norm() < 1e-15);
        // Gradients against central differences.
        let h = 1e-6;
        for k in 0..3 {
            let (mut p, mut m) = (xi, xi);
            p[k] += h;
            m[k] -= h;
            let (np, nm) = (tet_shape(p), tet_shape(m));
            for (a, g) in tet_shape_gradients(xi).iter().enumerate() {
                assert!(((np[a] - nm[a]) / (2.0 * h) - g[k]).abs() < 1e-9);
            }
        }
    }

    /// The rules integrate what they claim: the 4-point rule monomials of degree 2, the
    /// triangle rule of degree 5, the collapsed rule of degree 7 (exact integrals over the
    /// reference simplex: a!b!c!/(a+b+c+d)! with d = 3 or 2).
    #[test]
    fn rules_are_exact_to_their_degree() {
        let fact = |n: u32| (1..=n).map(f64::from).product::<f64>();
        for (rule, degree) in [(tet_rule().to_vec(), 2), (collapsed_rule(), 7)] {
            for a in 0..=degree {
                for b in 0..=degree - a {
                    for c in 0..=degree - a - b {
                        let exact = fact(a) * fact(b) * fact(c) / fact(a + b + c + 3);
                        let q: f64 = rule
                            .iter()
                            .map(|(x, w)| {
                                w * x[0].powi(a as i32) * x[1].powi(b as i32) * x[2].powi(c as i32)
                            })
                            .sum();
                        assert!(
                            (q - exact).abs() < 1e-15,
                            "x^{a} y^{b} z^{c}: {q} vs {exact}"
                        );
                    }
                }
            }
        }
        for a in 0..=5 {
            for b in 0..=5 - a {
                let exact = fact(a) * fact(b) / fact(a + b + 2);
                let q: f64 = triangle_rule()
                    .iter()
                    .map(|(l, w)| w * l[1].powi(a as i32) * l[2].powi(b as i32))
                    .sum();
                assert!((q - exact).abs() < 1e-16, "x^{a} y^{b}: {q} vs {exact}");
            }
        }
    }

    /// HRZ on a straight-sided element: corners 1/36, mid-edge nodes 4/27 of its volume; on a
    /// curved one, positive and summing to ∫ det J.
    #[test]
    fn hrz_masses_of_straight_and_curved_elements() {
        let c = corners();
        let x = straight(&c);
        let v = Matrix3::from_columns(&[c[1] - c[0], c[2] - c[0], c[3] - c[0]]).determinant() / 6.0;
        let (vol, m) = hrz_masses(&x);
        assert!((vol - v).abs() < 1e-14 * v);
        for (a, m) in m.iter().enumerate() {
            let f = if a < 4 { 1.0 / 36.0 } else { 4.0 / 27.0 };
            assert!((m - f * v).abs() < 1e-14 * v, "{a}: {}", m / v);
        }
        let (vol, m) = hrz_masses(&curved());
        let rest = rest_points(&curved()).unwrap();
        let v4: f64 = rest.iter().map(|p| p.volume).sum();
        assert!(m.iter().all(|&m| m > 0.0));
        assert!((m.iter().sum::<f64>() - vol).abs() < 1e-14 * vol);
        // The 4-point rule is not exact for a curved element's volume (det J is cubic).
        assert!((v4 - vol).abs() < 0.05 * vol && v4 != vol, "{v4} {vol}");
    }

    /// A flat 6-node triangle under uniform pressure: p·A/3 along the normal on each mid-edge
    /// node, nothing on the corners; on a curved one, the total is p times the projected area
    /// vector (1/2)(x1 − x0) × (x2 − x0) (∫ x,ξ × x,η is that of the corners' plane: Stokes).
    #[test]
    fn pressure_on_six_node_triangles() {
        let c = [
            Vec3::new(0.0, 0.0, 0.0),
            Vec3::new(2.0, 0.1, 0.2),
            Vec3::new(0.3, 1.5, -0.1),
        ];
        let mut x: [Vec3; 6] = std::array::from_fn(|a| {
            if a < 3 {
                c[a]
            } else {
                let [i, j] = TRI_EDGES[a - 3];
                (c[i] + c[j]) * 0.5
            }
        });
        let area = (c[1] - c[0]).cross(&(c[2] - c[0])) * 0.5;
        let f = pressure_forces(&x, 3.0);
        for (a, f) in f.iter().enumerate() {
            let want = if a < 3 { Vec3::zeros() } else { area };
            assert!((f - want).norm() < 1e-14, "{a}: {f:?}");
        }
        x[3] += Vec3::new(0.05, -0.1, 0.3);
        x[5] += Vec3::new(-0.2, 0.02, -0.15);
        // Curved: the total is p times the vector area ½∮ x × dx over the three parabolic
        // edges (3-point Gauss per edge, exact: the integrand has degree 3).
        let mut vector_area = Vec3::zeros();
        let g = 0.6f64.sqrt();
        for (k, [i, j]) in TRI_EDGES.into_iter().enumerate() {
            for (t, w) in [(-g, 5.0 / 18.0), (0.0, 8.0 / 18.0), (g, 5.0 / 18.0)] {
                let t = 0.5 * (1.0 + t);
                let p = x[i] * ((1.0 - t) * (1.0 - 2.0 * t))
                    + x[j] * (t * (2.0 * t - 1.0))
                    + x[3 + k] * (4.0 * t * (1.0 - t));
                let dp =
                    x[i] * (4.0 * t - 3.0) + x[j] * (4.0 * t - 1.0) + x[3 + k] * (4.0 - 8.0 * t);
                vector_area += p.cross(&dp) * (0.5 * w);
            }
        }
        assert!((vector_area - area).norm() > 0.01);
        let total: Vec3 = pressure_forces(&x, 3.0).iter().sum();
        assert!(
            (total - vector_area * 3.0).norm() < 1e-14,
            "{total:?} {vector_area:?}"
        );
    }

    /// The patch test: an affine motion x = A·X + c of a mesh of straight-sided elements gives
    /// F = A at every point and, with any stress P(F), zero net force on the interior nodes.
    /// The mesh: the unit cube as 6 Kuhn tets, with a distorted interior node, repeated 2×2×2.
    #[test]
    fn affine_motion_passes_the_patch_test() {
        let n = 3;
        let idx = |i: usize, j: usize, k: usize| (i * n + j) * n + k;
        let mut corner_nodes: Vec<Vec3> = Vec::new();
        for i in 0..n {
            for j in 0..n {
                for k in 0..n {
                    corner_nodes.push(Vec3::new(i as f64, j as f64, k as f64) * 0.5);
                }
            }
        }
        corner_nodes[idx(1, 1, 1)] += Vec3::new(0.07, -0.05, 0.04);
        let mut tets: Vec<[usize; 4]> = Vec::new();
        let kuhn = [
            [0, 1, 3, 7],
            [0, 1, 5, 7],
            [0, 2, 3, 7],
            [0, 2, 6, 7],
            [0, 4, 5, 7],
            [0, 4, 6, 7],
        ];
        for i in 0..n - 1 {
            for j in 0..n - 1 {
                for k in 0..n - 1 {
                    let v = |b: usize| idx(i + (b >> 2 & 1), j + (b >> 1 & 1), k + (b & 1));
                    for t in kuhn {
                        let mut t = t.map(v);
                        let p = t.map(|a| corner_nodes[a]);
                        let d = Matrix3::from_columns(&[p[1] - p[0], p[2] - p[0], p[3] - p[0]]);
                        if d.determinant() < 0.0 {
                            t.swap(2, 3);
                        }
                        tets.push(t);
                    }
                }
            }
        }
        // Mid-edge nodes shared between elements.
        let mut nodes = corner_nodes.clone();
        let mut mids = std::collections::BTreeMap::new();
        let conn: Vec<[usize; 10]> = tets
            .iter()
            .map(|t| {
                std::array::from_fn(|a| {
                    if a < 4 {
                        return t[a];
                    }
                    let [i, j] = TET_EDGES[a - 4];
                    let key = (t[i].min(t[j]), t[i].max(t[j]));
                    *mids.entry(key).or_insert_with(|| {
                        nodes.push((corner_nodes[key.0] + corner_nodes[key.1]) * 0.5);
                        nodes.len() - 1
                    })
                })
            })
            .collect();
        let a = Matrix3::new(1.1, 0.2, -0.1, 0.05, 0.9, 0.15, -0.2, 0.1, 1.2);
        let shift = Vec3::new(0.3, -0.2, 0.1);
        let x: Vec<Vec3> = nodes.iter().map(|p| a * p + shift).collect();
        // Any stress: a Saint Venant–Kirchhoff P = F·S(E).
        let piola = |f: &Matrix3<f64>| {
            let e = (f.transpose() * f - Matrix3::identity()) * 0.5;
            f * (e * 2.0 + Matrix3::identity() * (0.7 * e.trace()))
        };
        let mut total = vec![Vec3::zeros(); nodes.len()];
        for c in &conn {
            let rest = rest_points(&c.map(|a| nodes[a])).unwrap();
            let xe = c.map(|a| x[a]);
            let mut f = [Vec3::zeros(); 10];
            for p in &rest {
                let fq = deformation_gradient(p, &xe);
                assert!((fq - a).norm() < 1e-13, "{fq}");
                forces(p, &piola(&fq), &mut f);
            }
            for (&a, f) in c.iter().zip(f) {
                total[a] += f;
            }
        }
        let scale = total.iter().map(|f| f.norm()).fold(0.0, f64::max);
        let boundary = |p: &Vec3| {
            p.iter()
                .any(|&c| c.abs() < 1e-12 || (c - 1.0).abs() < 1e-12)
        };
        let mut interior = 0;
        for (p, f) in nodes.iter().zip(&total) {
            if !boundary(p) {
                interior += 1;
                assert!(f.norm() < 1e-13 * scale, "{p:?}: {f:?} of {scale}");
            }
        }
        assert!(interior > 10 && scale > 0.01, "{interior} {scale}");
    }
}
