//! Quadratic (10-node) tetrahedra in the mesh layer (issue 30): shape functions in VTK's node
//! order, the isoparametric Jacobian and its check, quadrature, HRZ lumped masses, and dropping
//! the mid-edge nodes again (`softc mesh convert --order 1`).
//!
//! Node order: corners 0–3, then the mid-edge nodes of edges 0-1, 1-2, 0-2, 0-3, 1-3, 2-3
//! ([`QUAD_TET_EDGES`], VTK type 24). With barycentric coordinates `L0 = 1 − ξ − η − ζ`,
//! `L1 = ξ`, `L2 = η`, `L3 = ζ`, corner `i` has `N = Lᵢ(2Lᵢ − 1)` and the mid-edge node of edge
//! `(i, j)` has `N = 4 Lᵢ Lⱼ`.

use super::model::{Mesh, QUAD_TET_EDGES, cross, dot};
use super::validate::{IssueKind, MeshIssue, Severity};

/// The 4-point rule (degree 2) in barycentric coordinates: `(a, b, b, b)` and its permutations,
/// each of weight 1/4 of the volume.
pub const RULE4_A: f64 = 0.5854101966249685;
/// See [`RULE4_A`].
pub const RULE4_B: f64 = 0.1381966011250105;

/// The points of the 4-point rule, barycentric.
pub fn rule4_points() -> [[f64; 4]; 4] {
    let (a, b) = (RULE4_A, RULE4_B);
    [[a, b, b, b], [b, a, b, b], [b, b, a, b], [b, b, b, a]]
}

/// Where validation evaluates the Jacobian: the 4-point rule's points and the 4 corners.
pub fn jacobian_check_points() -> [[f64; 4]; 8] {
    let g = rule4_points();
    [
        g[0],
        g[1],
        g[2],
        g[3],
        [1.0, 0.0, 0.0, 0.0],
        [0.0, 1.0, 0.0, 0.0],
        [0.0, 0.0, 1.0, 0.0],
        [0.0, 0.0, 0.0, 1.0],
    ]
}

/// A 6-node triangle's share (1/3)∫ x·n dA of the volume a closed surface encloses (corners,
/// then the mid-edge nodes of edges 0-1, 1-2, 2-0; n along (p1 − p0) × (p2 − p0)). The
/// integrand is a polynomial of degree 4 in the reference coordinates; the collapsed 3 × 3
/// Gauss–Legendre rule (ξ, η = (1 − ξ)·t, exact to degree 5) integrates it exactly.
pub fn curved_triangle_volume(p: &[[f64; 3]; 6]) -> f64 {
    const T: [f64; 3] = [0.112_701_665_379_258_3, 0.5, 0.887_298_334_620_741_7];
    const W: [f64; 3] = [5.0 / 18.0, 8.0 / 18.0, 5.0 / 18.0];
    let mut volume = 0.0;
    for (&xi, &wx) in T.iter().zip(&W) {
        for (&t, &wt) in T.iter().zip(&W) {
            let eta = (1.0 - xi) * t;
            let l = [1.0 - xi - eta, xi, eta];
            // Shape functions and their derivatives along ξ and η (∂l/∂ξ = (−1, 1, 0),
            // ∂l/∂η = (−1, 0, 1)).
            let dl = [[-1.0, 1.0, 0.0], [-1.0, 0.0, 1.0]];
            let edges = [[0, 1], [1, 2], [2, 0]];
            let mut n = [0.0; 6];
            let mut dn = [[0.0; 6]; 2];
            for i in 0..3 {
                n[i] = l[i] * (2.0 * l[i] - 1.0);
                for d in 0..2 {
                    dn[d][i] = (4.0 * l[i] - 1.0) * dl[d][i];
                }
            }
            for (m, [i, j]) in edges.into_iter().enumerate() {
                n[3 + m] = 4.0 * l[i] * l[j];
                for d in 0..2 {
                    dn[d][3 + m] = 4.0 * (dl[d][i] * l[j] + l[i] * dl[d][j]);
                }
            }
            let combine =
                |w: &[f64; 6]| [0, 1, 2].map(|k| (0..6).map(|a| w[a] * p[a][k]).sum::<f64>());
            let (x, dxi, deta) = (combine(&n), combine(&dn[0]), combine(&dn[1]));
            let cross = [
                dxi[1] * deta[2] - dxi[2] * deta[1],
                dxi[2] * deta[0] - dxi[0] * deta[2],
                dxi[0] * deta[1] - dxi[1] * deta[0],
            ];
            let dot = x[0] * cross[0] + x[1] * cross[1] + x[2] * cross[2];
            volume += wx * wt * (1.0 - xi) * dot / 3.0;
        }
    }
    volume
}

/// The 10 shape functions at barycentric coordinates `l`.
pub fn shape(l: [f64; 4]) -> [f64; 10] {
    let mut n = [0.0; 10];
    for i in 0..4 {
        n[i] = l[i] * (2.0 * l[i] - 1.0);
    }
    for (k, e) in QUAD_TET_EDGES.iter().enumerate() {
        n[4 + k] = 4.0 * l[e[0]] * l[e[1]];
    }
    n
}

/// `∂Nₐ/∂(ξ, η, ζ)` at barycentric coordinates `l` (`L1 = ξ`, `L2 = η`, `L3 = ζ`,
/// `L0 = 1 − ξ − η − ζ`).
pub fn shape_grad(l: [f64; 4]) -> [[f64; 3]; 10] {
    // ∂N/∂Lᵢ per node, then ∂/∂ξₖ = ∂/∂Lₖ − ∂/∂L0.
    let mut d = [[0.0f64; 4]; 10];
    for i in 0..4 {
        d[i][i] = 4.0 * l[i] - 1.0;
    }
    for (k, e) in QUAD_TET_EDGES.iter().enumerate() {
        d[4 + k][e[0]] = 4.0 * l[e[1]];
        d[4 + k][e[1]] = 4.0 * l[e[0]];
    }
    d.map(|g| [g[1] - g[0], g[2] - g[0], g[3] - g[0]])
}

/// The determinant of `∂x/∂(ξ, η, ζ)` of the element with nodes `p` (corners, then mid-edge
/// nodes) at barycentric coordinates `l`: 6 × the volume for a straight-sided tet.
pub fn jacobian_det(p: &[[f64; 3]; 10], l: [f64; 4]) -> f64 {
    let g = shape_grad(l);
    // Columns ∂x/∂ξₖ.
    let mut c = [[0.0f64; 3]; 3];
    for (pa, ga) in p.iter().zip(&g) {
        for k in 0..3 {
            for r in 0..3 {
                c[k][r] += pa[r] * ga[k];
            }
        }
    }
    dot(c[0], cross(c[1], c[2]))
}

/// The 10 node positions of tet `e` of a quadratic mesh (corners, then mid-edge nodes).
pub fn element_points(mesh: &Mesh, e: usize) -> Option<[[f64; 3]; 10]> {
    let q = mesh.mid_edges.as_ref()?;
    let (t, m) = (mesh.tets[e], q.tets[e]);
    let mut p = [[0.0; 3]; 10];
    for i in 0..4 {
        p[i] = mesh.nodes[t[i] as usize];
    }
    for k in 0..6 {
        p[4 + k] = mesh.nodes[m[k] as usize];
    }
    Some(p)
}

/// The Grundmann–Möller rule of degree `2s + 1` on a tetrahedron: barycentric points and
/// weights as fractions of the volume (they sum to 1; some are negative). Exact for
/// polynomials of that degree.
pub fn grundmann_moeller(s: usize) -> Vec<([f64; 4], f64)> {
    const N: usize = 3;
    let d = 2 * s + 1;
    let fact = |k: usize| (1..=k).map(|x| x as f64).product::<f64>();
    let mut out = Vec::new();
    for i in 0..=s {
        let denom = (d + N - 2 * i) as f64;
        let w =
            (if i % 2 == 0 { 1.0 } else { -1.0 }) * 2f64.powi(-2 * s as i32) * denom.powi(d as i32)
                / (fact(i) * fact(d + N - i))
                * fact(N);
        // Compositions β of s − i into 4 parts.
        let m = s - i;
        for b0 in 0..=m {
            for b1 in 0..=m - b0 {
                for b2 in 0..=m - b0 - b1 {
                    let b3 = m - b0 - b1 - b2;
                    let l = [b0, b1, b2, b3].map(|b| (2 * b + 1) as f64 / denom);
                    out.push((l, w));
                }
            }
        }
    }
    out
}

/// The diagonal of the element's consistent mass matrix per unit density, `∫ Nₐ² dV`, and
/// its volume `∫ dV`, over the isoparametric element with nodes `p`. The integrands are
/// polynomials of degree ≤ 7 in (ξ, η, ζ) (`Nₐ²` of degree 4 times `det J` of degree ≤ 3), so
/// the degree-7 Grundmann–Möller rule integrates them exactly, curved or straight-sided.
pub fn mass_diagonal(p: &[[f64; 3]; 10]) -> ([f64; 10], f64) {
    let mut diag = [0.0; 10];
    let mut vol = 0.0;
    for (l, w) in grundmann_moeller(3) {
        let dv = w * jacobian_det(p, l) / 6.0;
        vol += dv;
        for (d, n) in diag.iter_mut().zip(shape(l)) {
            *d += n * n * dv;
        }
    }
    (diag, vol)
}

/// HRZ (Hinton–Rock–Zienkiewicz) lumped masses per unit density: the consistent mass
/// diagonal scaled so that the element's masses sum to its volume. Row-sum lumping gives a
/// 10-node tet negative corner masses (−V/20 each); HRZ keeps every mass positive. For a
/// straight-sided tet: corners 6/216 · V, mid-edge nodes 32/216 · V.
pub fn hrz_lumped(p: &[[f64; 3]; 10]) -> [f64; 10] {
    let (diag, vol) = mass_diagonal(p);
    let sum: f64 = diag.iter().sum();
    diag.map(|d| d * vol / sum)
}

impl Mesh {
    /// The volume of element `e`: of its curved shape for a 10-node tet (`∫ det J`, exact by
    /// the degree-3 Grundmann–Möller rule: `det J` has degree ≤ 3), else of its corners' tet.
    pub fn element_volume(&self, e: usize) -> f64 {
        let nn = self.nodes.len();
        let in_range = |ids: &[u32]| ids.iter().all(|&n| (n as usize) < nn);
        match &self.mid_edges {
            Some(q) if in_range(&q.tets[e]) && in_range(&self.tets[e]) => {
                let p = element_points(self, e).expect("a quadratic mesh");
                grundmann_moeller(1)
                    .into_iter()
                    .map(|(l, w)| w * jacobian_det(&p, l) / 6.0)
                    .sum()
            }
            _ => self.tet_volume(e),
        }
    }

    /// The element order: 1 (4-node tets) or 2 (10-node tets).
    pub fn order(&self) -> u8 {
        if self.is_quadratic() { 2 } else { 1 }
    }

    /// How many distinct nodes are mid-edge nodes and no element's corner (0 for a linear
    /// mesh).
    pub fn mid_edge_node_count(&self) -> usize {
        let Some(q) = &self.mid_edges else {
            return 0;
        };
        let mut corner = vec![false; self.nodes.len()];
        for &v in self.tets.iter().flatten().chain(self.tris.iter().flatten()) {
            if let Some(c) = corner.get_mut(v as usize) {
                *c = true;
            }
        }
        let mut mids: Vec<u32> = q
            .tets
            .iter()
            .flatten()
            .chain(q.tris.iter().flatten())
            .copied()
            .filter(|&v| !corner.get(v as usize).copied().unwrap_or(false))
            .collect();
        mids.sort_unstable();
        mids.dedup();
        mids.len()
    }

    /// The linear mesh under a quadratic one: the corners only, without the mid-edge nodes
    /// (nodes that are a mid-edge node of some element and a corner of none are removed, the
    /// rest renumbered in their order; node sets lose the removed nodes). A linear mesh is
    /// returned as it is.
    pub fn without_mid_edges(&self) -> Mesh {
        let Some(q) = &self.mid_edges else {
            return self.clone();
        };
        let n = self.nodes.len();
        let mut corner = vec![false; n];
        for &v in self.tets.iter().flatten().chain(self.tris.iter().flatten()) {
            corner[v as usize] = true;
        }
        let mut drop = vec![false; n];
        for &v in q.tets.iter().flatten().chain(q.tris.iter().flatten()) {
            if !corner[v as usize] {
                drop[v as usize] = true;
            }
        }
        let mut new_of = vec![u32::MAX; n];
        let mut next = 0u32;
        for (i, d) in drop.iter().enumerate() {
            if !d {
                new_of[i] = next;
                next += 1;
            }
        }
        let mut out = self.clone();
        out.mid_edges = None;
        out.nodes = (0..n)
            .filter(|&i| !drop[i])
            .map(|i| self.nodes[i])
            .collect();
        if !self.ids.nodes.is_empty() {
            out.ids.nodes = (0..n)
                .filter(|&i| !drop[i])
                .map(|i| self.ids.nodes[i])
                .collect();
            out.ids.nodes = super::model::FileIds::compact(std::mem::take(&mut out.ids.nodes));
        }
        for t in &mut out.tets {
            *t = t.map(|v| new_of[v as usize]);
        }
        for t in &mut out.tris {
            *t = t.map(|v| new_of[v as usize]);
        }
        for set in out.node_sets.values_mut() {
            set.retain(|&v| !drop[v as usize]);
            for v in set.iter_mut() {
                *v = new_of[*v as usize];
            }
        }
        out
    }

    /// The checks only a quadratic mesh needs: one mid-edge node list per tet and tagged
    /// triangle, mid-edge nodes in range and distinct from their element's other nodes, one
    /// node per edge (shared by every tet and triangle on it), and a positive Jacobian
    /// determinant at the 4-point rule's points and the corners of every tet. The bool is
    /// false when indices are broken (the caller stops there).
    pub(crate) fn quadratic_issues(&self) -> (Vec<MeshIssue>, bool) {
        let mut out = Vec::new();
        let Some(q) = &self.mid_edges else {
            return (out, true);
        };
        let nn = self.nodes.len();
        if q.tets.len() != self.tets.len() || q.tris.len() != self.tris.len() {
            out.push(MeshIssue {
                severity: Severity::Error,
                kind: IssueKind::MidEdgeCount {
                    tets: self.tets.len(),
                    tet_mids: q.tets.len(),
                    tris: self.tris.len(),
                    tri_mids: q.tris.len(),
                },
                message: format!(
                    "the mesh has {} tets and {} tagged triangles but mid-edge nodes for {} and \
                     {}; every element of a quadratic mesh needs its mid-edge nodes",
                    self.tets.len(),
                    self.tris.len(),
                    q.tets.len(),
                    q.tris.len()
                ),
            });
            return (out, false);
        }
        let mut range_ok = true;
        let mut bad = 0;
        for (e, (t, m)) in self.tets.iter().zip(&q.tets).enumerate() {
            for (k, &v) in m.iter().enumerate() {
                let why = if v as usize >= nn {
                    range_ok = false;
                    format!("is node index {v}, but the mesh has {nn} nodes")
                } else if t.contains(&v) {
                    format!(
                        "is node {}, a corner of the element",
                        self.node_id(v as usize)
                    )
                } else if m[..k].contains(&v) {
                    format!(
                        "is node {}, also on another of its edges",
                        self.node_id(v as usize)
                    )
                } else {
                    continue;
                };
                bad += 1;
                if bad <= super::validate::MAX_PER_KIND {
                    let ed = QUAD_TET_EDGES[k];
                    out.push(MeshIssue {
                        severity: Severity::Error,
                        kind: IssueKind::BadMidEdgeNode {
                            element: e,
                            node: v,
                        },
                        message: format!(
                            "the mid-edge node of element {}'s edge {}-{} (nodes {}) {why}; \
                             re-export the mesh (gmsh: Mesh.ElementOrder = 2) or use order 1",
                            self.tet_id(e),
                            ed[0],
                            ed[1],
                            self.node_list(&[t[ed[0]], t[ed[1]]])
                        ),
                    });
                }
            }
        }
        for (f, m) in q.tris.iter().enumerate() {
            if let Some(&v) = m.iter().find(|&&v| v as usize >= nn) {
                range_ok = false;
                out.push(MeshIssue {
                    severity: Severity::Error,
                    kind: IssueKind::BadTriangle { face: f, nodes: *m },
                    message: format!(
                        "surface triangle {} has mid-edge node index {v}, but the mesh has {nn} \
                         nodes",
                        self.tri_id(f)
                    ),
                });
            }
        }
        if !range_ok {
            return (out, false);
        }
        out.extend(self.nonconforming_mid_edges());
        // The Jacobian, relative to the straight-sided tet's (6V): a small positive ratio is a
        // badly curved but valid element, zero or negative a folded one.
        let mut folded = 0;
        for e in 0..self.tets.len() {
            let v6 = 6.0 * self.tet_volume(e);
            if v6 <= 0.0 {
                continue; // reported as inverted or degenerate
            }
            let p = element_points(self, e).expect("a quadratic mesh");
            let worst = jacobian_check_points()
                .iter()
                .map(|&l| jacobian_det(&p, l) / v6)
                .fold(f64::INFINITY, f64::min);
            // NaN (a non-finite node) counts as folded.
            if worst.is_nan() || worst <= 0.0 {
                folded += 1;
                if folded <= super::validate::MAX_PER_KIND {
                    out.push(MeshIssue {
                        severity: Severity::Error,
                        kind: IssueKind::NonPositiveJacobian {
                            element: e,
                            ratio: worst,
                        },
                        message: format!(
                            "quadratic element {} (corners {}) is folded: its Jacobian \
                             determinant falls to {worst:.3} × the straight-sided tet's; move \
                             its mid-edge nodes toward the edge midpoints, refine the mesh where \
                             the boundary is curved, or use order 1",
                            self.tet_id(e),
                            self.node_list(&self.tets[e])
                        ),
                    });
                }
            }
        }
        (out, true)
    }

    /// Edges whose tets and triangles do not share one mid-edge node (the elements do not
    /// connect there).
    fn nonconforming_mid_edges(&self) -> Vec<MeshIssue> {
        let Some(q) = &self.mid_edges else {
            return Vec::new();
        };
        // (edge, mid node, which element: tet index or !triangle index)
        let mut all: Vec<([u32; 2], u32, usize)> =
            Vec::with_capacity(q.tets.len() * 6 + q.tris.len() * 3);
        for (e, (t, m)) in self.tets.iter().zip(&q.tets).enumerate() {
            for (k, ed) in QUAD_TET_EDGES.iter().enumerate() {
                let (a, b) = (t[ed[0]], t[ed[1]]);
                all.push(([a.min(b), a.max(b)], m[k], e));
            }
        }
        for (f, (t, m)) in self.tris.iter().zip(&q.tris).enumerate() {
            for (k, ed) in super::model::QUAD_TRI_EDGES.iter().enumerate() {
                let (a, b) = (t[ed[0]], t[ed[1]]);
                all.push(([a.min(b), a.max(b)], m[k], !f));
            }
        }
        all.sort_unstable();
        let name = |w: usize| {
            if w > usize::MAX / 2 {
                format!("surface triangle {}", self.tri_id(!w))
            } else {
                format!("element {}", self.tet_id(w))
            }
        };
        let mut out = Vec::new();
        for w in all.windows(2) {
            if w[0].0 == w[1].0 && w[0].1 != w[1].1 {
                if out.len() >= super::validate::MAX_PER_KIND {
                    break;
                }
                out.push(MeshIssue {
                    severity: Severity::Error,
                    kind: IssueKind::NonConformingMidEdge {
                        edge: w[0].0,
                        mids: [w[0].1, w[1].1],
                    },
                    message: format!(
                        "the edge between nodes {} has two mid-edge nodes, {} in {} and {} in {}; \
                         elements sharing an edge must share its mid-edge node — merge \
                         duplicate nodes (gmsh: Coherence) or re-export",
                        self.node_list(&w[0].0),
                        self.node_id(w[0].1 as usize),
                        name(w[0].2),
                        self.node_id(w[1].1 as usize),
                        name(w[1].2)
                    ),
                });
            }
        }
        out
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::mesh::kuhn::{KuhnSpec, kuhn_grid};
    use crate::mesh::model::LengthUnit;

    fn unit_tet() -> Mesh {
        Mesh::from_tets(
            vec![
                [0.0, 0.0, 0.0],
                [1.0, 0.0, 0.0],
                [0.0, 1.0, 0.0],
                [0.0, 0.0, 1.0],
            ],
            vec![[0, 1, 2, 3]],
        )
        .with_mid_edges()
    }

    #[test]
    fn shape_functions_interpolate_and_partition_unity() {
        let m = unit_tet();
        let p = element_points(&m, 0).unwrap();
        // Nₐ(x_b) = δ_ab at the nodes (barycentric of node b).
        for (b, pb) in p.iter().enumerate() {
            let l = [1.0 - pb[0] - pb[1] - pb[2], pb[0], pb[1], pb[2]];
            let n = shape(l);
            for (a, na) in n.iter().enumerate() {
                assert_eq!(*na, if a == b { 1.0 } else { 0.0 }, "N{a} at node {b}");
            }
        }
        // Σ Nₐ = 1 and Σ ∇Nₐ = 0 anywhere; ∇N by central differences.
        let l = [0.1, 0.2, 0.3, 0.4];
        assert!((shape(l).iter().sum::<f64>() - 1.0).abs() < 1e-15);
        let g = shape_grad(l);
        for k in 0..3 {
            assert!(g.iter().map(|r| r[k]).sum::<f64>().abs() < 1e-14);
        }
        let h = 1e-6;
        for k in 0..3 {
            let (mut lp, mut lm) = (l, l);
            lp[k + 1] += h;
            lp[0] -= h;
            lm[k + 1] -= h;
            lm[0] += h;
            let (np, nm) = (shape(lp), shape(lm));
            for a in 0..10 {
                let fd = (np[a] - nm[a]) / (2.0 * h);
                assert!(
                    (fd - g[a][k]).abs() < 1e-8,
                    "node {a} dir {k}: {fd} vs {}",
                    g[a][k]
                );
            }
        }
    }

    #[test]
    fn grundmann_moeller_integrates_degree_seven_exactly() {
        // ∫ L0^a L1^b L2^c L3^d dV / V = a! b! c! d! 3! / (a + b + c + d + 3)!.
        let fact = |k: u32| (1..=k).map(f64::from).product::<f64>();
        let rule = grundmann_moeller(3);
        assert_eq!(rule.len(), 35);
        for e in [
            [0, 0, 0, 0],
            [2, 0, 0, 0],
            [4, 0, 0, 0],
            [2, 2, 0, 0],
            [1, 2, 3, 1],
            [0, 0, 0, 7],
        ] {
            let q: f64 = rule
                .iter()
                .map(|(l, w)| w * (0..4).map(|i| l[i].powi(e[i] as i32)).product::<f64>())
                .sum();
            let exact =
                e.iter().map(|&k| fact(k)).product::<f64>() * 6.0 / fact(e.iter().sum::<u32>() + 3);
            assert!(
                (q - exact).abs() < 1e-14 * exact.max(1e-3),
                "{e:?}: {q} vs {exact}"
            );
        }
    }

    #[test]
    fn straight_sided_jacobian_is_six_volumes_everywhere() {
        let m = unit_tet();
        let p = element_points(&m, 0).unwrap();
        for l in jacobian_check_points() {
            assert!((jacobian_det(&p, l) - 1.0).abs() < 1e-14);
        }
    }

    #[test]
    fn hrz_masses_are_6_and_32_over_216_of_the_volume_for_a_straight_tet() {
        let m = unit_tet();
        let p = element_points(&m, 0).unwrap();
        let v = 1.0 / 6.0;
        let (diag, vol) = mass_diagonal(&p);
        assert!((vol - v).abs() < 1e-15);
        // Consistent diagonal: corners V/70 = 6V/420, mid-edge nodes 32V/420.
        for a in 0..4 {
            assert!((diag[a] - 6.0 * v / 420.0).abs() < 1e-15, "{diag:?}");
        }
        for a in 4..10 {
            assert!((diag[a] - 32.0 * v / 420.0).abs() < 1e-15, "{diag:?}");
        }
        let lumped = hrz_lumped(&p);
        for (a, m) in lumped.iter().enumerate() {
            let want = if a < 4 { 6.0 } else { 32.0 } * v / 216.0;
            assert!((m - want).abs() < 1e-15, "{lumped:?}");
        }
        assert!((lumped.iter().sum::<f64>() - v).abs() < 1e-15);
    }

    #[test]
    fn a_curved_element_keeps_its_volume_and_positive_masses() {
        let mut m = unit_tet();
        // Bulge the mid-edge node of edge 1-2 (on the face x + y = 1) outwards.
        let mid = m.mid_edges.as_ref().unwrap().tets[0][1] as usize;
        m.nodes[mid] = [0.6, 0.6, 0.0];
        let p = element_points(&m, 0).unwrap();
        let (_, vol) = mass_diagonal(&p);
        // x = x₀ + δ·N₅ with δ = (0.1, 0.1, 0): the volume grows by ∮ N₅ δ·n dA over the
        // straight faces, nonzero on face 1-2-3 only: (0.2/√3) · (area √3/2) / 3 = 1/30.
        assert!((vol - (1.0 / 6.0 + 1.0 / 30.0)).abs() < 1e-15, "{vol}");
        // `mesh info` and the quality report count the curved volume, not the corners' tet.
        assert!((m.element_volume(0) - vol).abs() < 1e-15);
        assert!((m.quality(None).volume - vol).abs() < 1e-15);
        assert!(hrz_lumped(&p).iter().all(|&x| x > 0.0));
        assert!(m.validate().is_empty(), "{:?}", m.validate());
    }

    #[test]
    fn a_folded_element_is_refused_by_its_id_with_what_to_do() {
        let mut m = unit_tet();
        m.ids.tets = vec![42];
        // Pull the mid-edge node of edge 0-1 far past corner 1: the element folds.
        let mid = m.mid_edges.as_ref().unwrap().tets[0][0] as usize;
        m.nodes[mid] = [1.2, 0.0, 0.0];
        let issues = m.validate();
        let i = issues
            .iter()
            .find(|i| matches!(i.kind, IssueKind::NonPositiveJacobian { element: 0, .. }))
            .unwrap_or_else(|| panic!("{issues:?}"));
        assert!(i.message.contains("element 42"), "{}", i.message);
        assert!(
            i.message.contains("toward the edge midpoints"),
            "{}",
            i.message
        );
        assert!(i.message.contains("order 1"), "{}", i.message);
    }

    #[test]
    fn mid_edge_nodes_that_are_corners_or_disagree_are_refused() {
        let mut m = unit_tet();
        m.mid_edges.as_mut().unwrap().tets[0][2] = 3;
        let issues = m.validate();
        assert!(
            issues.iter().any(|i| matches!(
                i.kind,
                IssueKind::BadMidEdgeNode {
                    element: 0,
                    node: 3
                }
            ) && i.message.contains("a corner")),
            "{issues:?}"
        );
        // Two tets sharing a face with their own mid-edge nodes on a shared edge.
        let k = kuhn_grid(&KuhnSpec::benchmark(3, 2, 2), LengthUnit::Millimetre).unwrap();
        let mut q = k.with_mid_edges();
        assert!(
            q.validate().iter().all(|i| i.severity != Severity::Error),
            "{:?}",
            q.validate()
        );
        let extra = q.nodes.len() as u32;
        let mids = q.mid_edges.as_mut().unwrap();
        let old = mids.tets[0][0];
        mids.tets[0][0] = extra;
        let p = q.nodes[old as usize];
        q.nodes.push(p);
        let issues = q.validate();
        assert!(
            issues
                .iter()
                .any(|i| matches!(i.kind, IssueKind::NonConformingMidEdge { .. })),
            "{issues:?}"
        );
        // Out of range: refused without indexing past the nodes.
        q.mid_edges.as_mut().unwrap().tets[1][3] = 10_000;
        assert!(q.validate().iter().any(|i| matches!(
            i.kind,
            IssueKind::BadMidEdgeNode {
                element: 1,
                node: 10_000
            }
        )));
    }

    #[test]
    fn dropping_mid_edges_restores_the_linear_mesh() {
        let k = kuhn_grid(&KuhnSpec::benchmark(3, 2, 2), LengthUnit::Millimetre).unwrap();
        let q = k.with_mid_edges();
        assert!(q.is_quadratic() && q.nodes.len() > k.nodes.len());
        let back = q.without_mid_edges();
        assert!(!back.is_quadratic());
        assert_eq!(back.nodes, k.nodes);
        assert_eq!(back.tets, k.tets);
        assert_eq!(back.tris, k.tris);
        assert_eq!(back.node_sets, k.node_sets);
        assert_eq!(back.ids, k.ids);
        assert_eq!(k.without_mid_edges(), k);
    }
}
