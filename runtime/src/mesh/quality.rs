//! Element quality: dihedral angles and the radius-ratio aspect.

use super::model::{Mesh, TET_EDGES, TET_FACES, cross, dot, norm, signed_volume, sub};

/// Quality of a tet mesh.
///
/// `worst_aspect_ratio` is the largest `R / (3 r)` over all tets, where `R` is the
/// circumradius and `r` the inradius: 1 for a regular tet, growing without bound as a tet
/// flattens (infinite for a degenerate one).
#[derive(Debug, Clone, PartialEq)]
pub struct QualityReport {
    pub nodes: usize,
    pub tets: usize,
    /// Total volume in m³.
    pub volume: f64,
    pub min_dihedral_deg: f64,
    pub max_dihedral_deg: f64,
    pub worst_aspect_ratio: f64,
    /// Tet with the smallest dihedral angle.
    pub worst_dihedral_element: usize,
    /// Tet with the worst aspect ratio.
    pub worst_aspect_element: usize,
    /// Shortest and longest edge, m.
    pub min_edge: f64,
    pub max_edge: f64,
    /// `(mesh volume − reference) / reference`, when a reference volume is known (generated
    /// meshes: the analytic volume of the input geometry).
    pub volume_error: Option<f64>,
}

/// The six dihedral angles (radians) of a tet, ordered as [`TET_EDGES`].
pub fn dihedral_angles(p: [[f64; 3]; 4]) -> [f64; 6] {
    // Outward normals of the faces opposite each corner.
    let sign = if signed_volume(p) >= 0.0 { 1.0 } else { -1.0 };
    let mut n = [[0.0; 3]; 4];
    for (c, f) in TET_FACES.iter().enumerate() {
        let v = cross(sub(p[f[1]], p[f[0]]), sub(p[f[2]], p[f[0]]));
        let l = norm(v).max(f64::MIN_POSITIVE);
        n[c] = [sign * v[0] / l, sign * v[1] / l, sign * v[2] / l];
    }
    let mut out = [0.0; 6];
    for (k, e) in TET_EDGES.iter().enumerate() {
        // The faces containing edge (i, j) are those opposite the other two corners.
        let others: Vec<usize> = (0..4).filter(|c| *c != e[0] && *c != e[1]).collect();
        let c = dot(n[others[0]], n[others[1]]).clamp(-1.0, 1.0);
        out[k] = std::f64::consts::PI - c.acos();
    }
    out
}

/// `R / (3 r)` of a tet (1 for regular, ∞ for degenerate).
pub fn aspect_ratio(p: [[f64; 3]; 4]) -> f64 {
    let v = signed_volume(p).abs();
    if v == 0.0 {
        return f64::INFINITY;
    }
    let area: f64 = TET_FACES
        .iter()
        .map(|f| 0.5 * norm(cross(sub(p[f[1]], p[f[0]]), sub(p[f[2]], p[f[0]]))))
        .sum();
    let r = 3.0 * v / area;
    let u = sub(p[1], p[0]);
    let w1 = sub(p[2], p[0]);
    let w2 = sub(p[3], p[0]);
    let a = cross(w1, w2);
    let b = cross(w2, u);
    let c = cross(u, w1);
    let (lu, l1, l2) = (dot(u, u), dot(w1, w1), dot(w2, w2));
    let den = 2.0 * dot(u, a);
    let o = [
        (lu * a[0] + l1 * b[0] + l2 * c[0]) / den,
        (lu * a[1] + l1 * b[1] + l2 * c[1]) / den,
        (lu * a[2] + l1 * b[2] + l2 * c[2]) / den,
    ];
    norm(o) / (3.0 * r)
}

impl Mesh {
    /// Quality over all tets; `reference_volume` (m³) adds the volume error.
    pub fn quality(&self, reference_volume: Option<f64>) -> QualityReport {
        let mut q = QualityReport {
            nodes: self.nodes.len(),
            tets: self.tets.len(),
            volume: 0.0,
            min_dihedral_deg: f64::INFINITY,
            max_dihedral_deg: 0.0,
            worst_aspect_ratio: 0.0,
            worst_dihedral_element: 0,
            worst_aspect_element: 0,
            min_edge: f64::INFINITY,
            max_edge: 0.0,
            volume_error: None,
        };
        let nn = self.nodes.len();
        for (e, t) in self.tets.iter().enumerate() {
            if t.iter().any(|&n| n as usize >= nn) {
                continue;
            }
            let p = self.tet_points(e);
            // A curved 10-node tet's own volume, not its corners'.
            q.volume += self.element_volume(e);
            for a in dihedral_angles(p) {
                let d = a.to_degrees();
                if d < q.min_dihedral_deg {
                    q.min_dihedral_deg = d;
                    q.worst_dihedral_element = e;
                }
                q.max_dihedral_deg = q.max_dihedral_deg.max(d);
            }
            let ar = aspect_ratio(p);
            if ar > q.worst_aspect_ratio {
                q.worst_aspect_ratio = ar;
                q.worst_aspect_element = e;
            }
            for ed in TET_EDGES {
                let l = norm(sub(p[ed[0]], p[ed[1]]));
                q.min_edge = q.min_edge.min(l);
                q.max_edge = q.max_edge.max(l);
            }
        }
        if self.tets.is_empty() {
            q.min_dihedral_deg = 0.0;
            q.min_edge = 0.0;
        }
        if let Some(r) = reference_volume
            && r != 0.0
        {
            q.volume_error = Some((q.volume - r) / r);
        }
        q
    }
}
