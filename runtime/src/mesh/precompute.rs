//! Data the simulation kernels need, computed once from a mesh and per-element densities.

use super::error::MeshError;
use super::model::{Mesh, TET_EDGES, norm, sub};

/// Node → element adjacency in CSR form: the incidences of node `n` are
/// `entries[offsets[n]..offsets[n+1]]`, each `(element, corner)`, sorted by element then
/// corner (deterministic gather order for force accumulation without atomics). The compiler's
/// one connectivity type.
pub use softc_compiler::back::NodeCsr as NodeElementCsr;

/// A unique edge of the tet mesh (spring mesh, thesis eq. 2.3).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Edge {
    /// Node indices, `nodes[0] < nodes[1]`.
    pub nodes: [u32; 2],
    /// Rest length, m.
    pub rest_length: f64,
    /// Sum of the rest volumes of the tets sharing the edge, m³.
    pub volume: f64,
}

/// Triangles of one tagged surface, wound with normals into the solid.
#[derive(Debug, Clone, PartialEq)]
pub struct SurfaceTris {
    pub tag: i32,
    pub name: Option<String>,
    /// Whether the surface is a chamber (see [`Mesh::chamber_tags`]).
    pub chamber: bool,
    pub tris: Vec<[u32; 3]>,
}

/// Precomputed per-mesh data.
#[derive(Debug, Clone, PartialEq)]
pub struct Precomputed {
    /// Rest volume per tet, m³.
    pub rest_volume: Vec<f64>,
    /// Smallest altitude per tet, `3V / (largest face area)`, m — the element length of the
    /// explicit stable-time-step estimate `dt ≈ h_min / c_d`. For a quadratic (10-node) tet,
    /// half its corner tet's smallest altitude: the mid-edge nodes halve the distance between
    /// nodes, and with it the element length the stable step scales with.
    pub min_altitude: Vec<f64>,
    /// `Dm⁻¹` per tet, row-major, with `Dm = [x1−x0, x2−x0, x3−x0]` (columns).
    pub dm_inv: Vec<[[f64; 3]; 3]>,
    /// Lumped mass per node, kg: `ρ_e·V_e/4` from each adjacent tet. For a quadratic mesh,
    /// HRZ lumping (row sums give 10-node tets negative corner masses): each element's
    /// consistent-mass diagonal `∫ρNₐ² dV` (integrated exactly, curved elements included),
    /// scaled so that the element's masses sum to `ρ_e·V_e` (its isoparametric volume) —
    /// corners `6/216·ρV` and mid-edge nodes `32/216·ρV` on a straight-sided tet.
    pub mass: Vec<f64>,
    /// Node → element adjacency.
    pub node_elements: NodeElementCsr,
    /// Tagged surfaces (chambers and others), sorted by tag.
    pub surfaces: Vec<SurfaceTris>,
    /// Unique edges sorted by node pair.
    pub edges: Vec<Edge>,
}

/// Inverse of a 3×3 matrix (row-major), `None` if singular.
pub fn inverse3(m: [[f64; 3]; 3]) -> Option<[[f64; 3]; 3]> {
    let c00 = m[1][1] * m[2][2] - m[1][2] * m[2][1];
    let c01 = m[1][2] * m[2][0] - m[1][0] * m[2][2];
    let c02 = m[1][0] * m[2][1] - m[1][1] * m[2][0];
    let det = m[0][0] * c00 + m[0][1] * c01 + m[0][2] * c02;
    if det == 0.0 || !det.is_finite() {
        return None;
    }
    let d = 1.0 / det;
    Some([
        [
            c00 * d,
            (m[0][2] * m[2][1] - m[0][1] * m[2][2]) * d,
            (m[0][1] * m[1][2] - m[0][2] * m[1][1]) * d,
        ],
        [
            c01 * d,
            (m[0][0] * m[2][2] - m[0][2] * m[2][0]) * d,
            (m[0][2] * m[1][0] - m[0][0] * m[1][2]) * d,
        ],
        [
            c02 * d,
            (m[0][1] * m[2][0] - m[0][0] * m[2][1]) * d,
            (m[0][0] * m[1][1] - m[0][1] * m[1][0]) * d,
        ],
    ])
}

impl Precomputed {
    /// Build from a mesh and one density (kg/m³) per tet. Fails on a density count mismatch
    /// or a non-positive / singular tet (validate the mesh first).
    #[allow(clippy::needless_range_loop)]
    pub fn new(mesh: &Mesh, density: &[f64]) -> Result<Self, MeshError> {
        let ne = mesh.tets.len();
        if density.len() != ne {
            return Err(MeshError::spec(format!(
                "{} densities given for {ne} elements",
                density.len()
            )));
        }
        let nn = mesh.nodes.len();
        let mut rest_volume = Vec::with_capacity(ne);
        let mut dm_inv = Vec::with_capacity(ne);
        let mut min_altitude = Vec::with_capacity(ne);
        let mut mass = vec![0.0; nn];
        for e in 0..ne {
            if mesh.tets[e].iter().any(|&n| n as usize >= nn) {
                return Err(MeshError::parse(format!(
                    "element {} uses a node index out of range ({nn} nodes)",
                    mesh.tet_id(e)
                )));
            }
            let p = mesh.tet_points(e);
            let v = mesh.tet_volume(e);
            if v <= 0.0 || !v.is_finite() {
                return Err(MeshError::parse(format!(
                    "element {} has volume {v:.3e} m³ ≤ 0; run validation and fix the mesh",
                    mesh.tet_id(e)
                )));
            }
            let c1 = sub(p[1], p[0]);
            let c2 = sub(p[2], p[0]);
            let c3 = sub(p[3], p[0]);
            let dm = [
                [c1[0], c2[0], c3[0]],
                [c1[1], c2[1], c3[1]],
                [c1[2], c2[2], c3[2]],
            ];
            let inv = inverse3(dm).ok_or_else(|| {
                MeshError::parse(format!(
                    "element {} has a singular Dm matrix",
                    mesh.tet_id(e)
                ))
            })?;
            let amax = super::model::TET_FACES
                .iter()
                .map(|f| norm(super::model::area_vector(p[f[0]], p[f[1]], p[f[2]])))
                .fold(0.0, f64::max);
            rest_volume.push(v);
            dm_inv.push(inv);
            if let Some(q) = &mesh.mid_edges {
                let mids = q
                    .tets
                    .get(e)
                    .filter(|m| m.iter().all(|&n| (n as usize) < nn));
                let Some(m) = mids else {
                    return Err(MeshError::parse(format!(
                        "element {} has no valid mid-edge nodes; run validation and fix the mesh",
                        mesh.tet_id(e)
                    )));
                };
                let p = super::quadratic::element_points(mesh, e).expect("mid-edge nodes in range");
                min_altitude.push(1.5 * v / amax);
                let lumped = super::quadratic::hrz_lumped(&p);
                for (&n, l) in mesh.tets[e].iter().chain(m).zip(lumped) {
                    mass[n as usize] += density[e] * l;
                }
            } else {
                min_altitude.push(3.0 * v / amax);
                let m = density[e] * v / 4.0;
                for &n in &mesh.tets[e] {
                    mass[n as usize] += m;
                }
            }
        }
        let node_elements = NodeElementCsr::build(nn, mesh.tets.iter());
        let chambers = mesh.chamber_tags();
        let surfaces = mesh
            .surface_tags()
            .into_iter()
            .map(|tag| SurfaceTris {
                tag,
                name: mesh.tag_name(2, tag).map(str::to_string),
                chamber: chambers.contains(&tag),
                tris: mesh.surface(tag),
            })
            .collect();
        let mut raw: Vec<([u32; 2], f64)> = Vec::with_capacity(ne * 6);
        for (e, t) in mesh.tets.iter().enumerate() {
            for ed in TET_EDGES {
                let a = t[ed[0]];
                let b = t[ed[1]];
                raw.push(([a.min(b), a.max(b)], rest_volume[e]));
            }
        }
        raw.sort_by_key(|x| x.0);
        let mut edges: Vec<Edge> = Vec::new();
        for (k, v) in raw {
            match edges.last_mut() {
                Some(last) if last.nodes == k => last.volume += v,
                _ => edges.push(Edge {
                    nodes: k,
                    rest_length: norm(sub(mesh.nodes[k[0] as usize], mesh.nodes[k[1] as usize])),
                    volume: v,
                }),
            }
        }
        Ok(Precomputed {
            rest_volume,
            min_altitude,
            dm_inv,
            mass,
            node_elements,
            surfaces,
            edges,
        })
    }

    /// Same density everywhere.
    pub fn with_uniform_density(mesh: &Mesh, density: f64) -> Result<Self, MeshError> {
        Self::new(mesh, &vec![density; mesh.tets.len()])
    }

    /// The surface with tag `tag`.
    pub fn surface(&self, tag: i32) -> Option<&SurfaceTris> {
        self.surfaces.iter().find(|s| s.tag == tag)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::mesh::kuhn::{KuhnSpec, kuhn_grid};
    use crate::mesh::model::LengthUnit;

    #[test]
    fn quadratic_masses_are_hrz_positive_and_sum_to_rho_v() {
        let lin = kuhn_grid(&KuhnSpec::benchmark(6, 4, 4), LengthUnit::Millimetre).unwrap();
        let quad = lin.with_mid_edges();
        let rho = 1070.0;
        let (pl, pq) = (
            Precomputed::with_uniform_density(&lin, rho).unwrap(),
            Precomputed::with_uniform_density(&quad, rho).unwrap(),
        );
        let total = rho * lin.total_volume();
        let sum: f64 = pq.mass.iter().sum();
        assert!((sum - total).abs() < 1e-12 * total, "{sum} vs {total}");
        assert!(pq.mass.iter().all(|&m| m > 0.0), "a non-positive mass");
        assert_eq!(pq.mass.len(), quad.nodes.len());
        // Per element: corners 6/216 and mid-edge nodes 32/216 of ρV (straight-sided).
        let one = Mesh::from_tets(lin.tet_points(0).to_vec(), vec![[0, 1, 2, 3]]).with_mid_edges();
        let p1 = Precomputed::with_uniform_density(&one, rho).unwrap();
        let rv = rho * one.tet_volume(0);
        for (a, m) in p1.mass.iter().enumerate() {
            let want = if a < 4 { 6.0 } else { 32.0 } / 216.0 * rv;
            assert!((m - want).abs() < 1e-13 * rv, "node {a}: {m} vs {want}");
        }
        // Volumes, Dm⁻¹ and the CSR come from the corners, as for the linear mesh; the element
        // length is halved.
        assert_eq!(pq.rest_volume, pl.rest_volume);
        assert_eq!(pq.dm_inv, pl.dm_inv);
        for n in 0..lin.nodes.len() {
            assert_eq!(pq.node_elements.of(n), pl.node_elements.of(n));
        }
        for (q, l) in pq.min_altitude.iter().zip(&pl.min_altitude) {
            assert!((q - 0.5 * l).abs() <= 1e-15 * l);
        }
    }
}
