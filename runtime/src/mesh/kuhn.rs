//! The structured Kuhn/Freudenthal benchmark grid of `BENCHMARK.md`: a box of NX×NY×NZ cells
//! minus the cells whose centres lie strictly inside a cavity box, each solid cell split into
//! six tets sharing the cell diagonal (0,0,0)→(1,1,1); chamber faces are the quads between
//! solid and cavity cells, split along the same diagonal as the Kuhn tets.

use super::error::MeshError;
use super::model::{LengthUnit, Mesh, signed_volume};

/// Geometry of a Kuhn grid (millimetres or any unit given to [`kuhn_grid`]).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct KuhnSpec {
    pub n: [usize; 3],
    pub min: [f64; 3],
    pub max: [f64; 3],
    pub cavity_min: [f64; 3],
    pub cavity_max: [f64; 3],
}

/// Region tag of the solid, surface tags of the cavity, clamp face (x = min) and tip face
/// (x = max) in generated benchmark meshes.
pub const SOLID_TAG: i32 = 1;
pub const CAVITY_TAG: i32 = 2;
pub const BASE_TAG: i32 = 10;
pub const TIP_TAG: i32 = 11;

impl KuhnSpec {
    /// The benchmark scene (mm): box [0,60]×[0,10]×[0,10], cavity [5,55]×[2.5,7.5]×[4,8].
    pub fn benchmark(nx: usize, ny: usize, nz: usize) -> Self {
        KuhnSpec {
            n: [nx, ny, nz],
            min: [0.0, 0.0, 0.0],
            max: [60.0, 10.0, 10.0],
            cavity_min: [5.0, 2.5, 4.0],
            cavity_max: [55.0, 7.5, 8.0],
        }
    }

    fn h(&self) -> [f64; 3] {
        [
            (self.max[0] - self.min[0]) / self.n[0] as f64,
            (self.max[1] - self.min[1]) / self.n[1] as f64,
            (self.max[2] - self.min[2]) / self.n[2] as f64,
        ]
    }

    /// Whether cell `(i, j, k)` is cavity: its centre lies strictly inside the open cavity box.
    pub fn is_cavity(&self, c: [usize; 3]) -> bool {
        let h = self.h();
        (0..3).all(|a| {
            let x = self.min[a] + (c[a] as f64 + 0.5) * h[a];
            x > self.cavity_min[a] && x < self.cavity_max[a]
        })
    }
}

/// The six permutations of the axes; tet = 000 → +e_a → +e_a+e_b → 111.
const PERMS: [[usize; 3]; 6] = [
    [0, 1, 2],
    [0, 2, 1],
    [1, 0, 2],
    [1, 2, 0],
    [2, 0, 1],
    [2, 1, 0],
];

/// Build the Kuhn grid; coordinates given in `unit` are converted to metres. Tags: region
/// [`SOLID_TAG`] "solid", surfaces [`CAVITY_TAG`] "cavity", [`BASE_TAG`] "base" (x = min),
/// [`TIP_TAG`] "tip" (x = max). Node sets "base" and "tip" hold the nodes on those planes.
pub fn kuhn_grid(spec: &KuhnSpec, unit: LengthUnit) -> Result<Mesh, MeshError> {
    let [nx, ny, nz] = spec.n;
    if nx == 0 || ny == 0 || nz == 0 || nx * ny * nz > 50_000_000 {
        return Err(MeshError::spec(format!(
            "grid {nx}×{ny}×{nz}: each count must be ≥ 1 and the product ≤ 5·10⁷"
        )));
    }
    if (0..3).any(|a| spec.max[a] <= spec.min[a]) {
        return Err(MeshError::spec("the box needs max > min on every axis"));
    }
    let h = spec.h();
    let s = unit.to_metres();
    let solid = |i: usize, j: usize, k: usize| !spec.is_cavity([i, j, k]);
    let gid = |i: usize, j: usize, k: usize| i + (nx + 1) * (j + (ny + 1) * k);
    let ngrid = (nx + 1) * (ny + 1) * (nz + 1);
    // Tets on grid ids first, then compact the used nodes.
    let mut tets_g: Vec<[usize; 4]> = Vec::new();
    for k in 0..nz {
        for j in 0..ny {
            for i in 0..nx {
                if !solid(i, j, k) {
                    continue;
                }
                for p in PERMS {
                    let mut c = [0usize; 3];
                    let v0 = gid(i, j, k);
                    c[p[0]] = 1;
                    let v1 = gid(i + c[0], j + c[1], k + c[2]);
                    c[p[1]] = 1;
                    let v2 = gid(i + c[0], j + c[1], k + c[2]);
                    let v3 = gid(i + 1, j + 1, k + 1);
                    tets_g.push([v0, v1, v2, v3]);
                }
            }
        }
    }
    // Chamber quads between a solid cell and a cavity cell, on grid ids, oriented into the
    // solid: for the face normal to axis a between cells lo (cavity) and hi (solid) the
    // normal must be +e_a, and −e_a for the opposite case.
    let mut tris_g: Vec<([usize; 3], i32)> = Vec::new();
    for k in 0..nz {
        for j in 0..ny {
            for i in 0..nx {
                let c = [i, j, k];
                for a in 0..3 {
                    if c[a] + 1 >= spec.n[a] {
                        continue;
                    }
                    let mut d = c;
                    d[a] += 1;
                    let (s0, s1) = (solid(c[0], c[1], c[2]), solid(d[0], d[1], d[2]));
                    if s0 == s1 {
                        continue;
                    }
                    // Quad in the plane x_a = c[a]+1, spanned by axes b < c' (cyclic u, v).
                    let (u, v) = ((a + 1) % 3, (a + 2) % 3);
                    let corner = |du: usize, dv: usize| {
                        let mut q = d;
                        q[u] += du;
                        q[v] += dv;
                        gid(q[0], q[1], q[2])
                    };
                    let (p00, p10, p11, p01) =
                        (corner(0, 0), corner(1, 0), corner(1, 1), corner(0, 1));
                    // (u, v, a) is right-handed, so (p00, p10, p11) has normal +e_a.
                    let (t1, t2) = if s1 {
                        ([p00, p10, p11], [p00, p11, p01])
                    } else {
                        ([p00, p11, p10], [p00, p01, p11])
                    };
                    tris_g.push((t1, CAVITY_TAG));
                    tris_g.push((t2, CAVITY_TAG));
                }
            }
        }
    }
    // Base and tip faces: x = min and x = max planes of solid cells, normal into the solid.
    for k in 0..nz {
        for j in 0..ny {
            for (i, tag) in [(0usize, BASE_TAG), (nx - 1, TIP_TAG)] {
                if !solid(i, j, k) {
                    continue;
                }
                let x = if tag == BASE_TAG { 0 } else { nx };
                let p00 = gid(x, j, k);
                let p10 = gid(x, j + 1, k);
                let p11 = gid(x, j + 1, k + 1);
                let p01 = gid(x, j, k + 1);
                // (y, z) plane: (p00, p10, p11) has normal +x: into the solid at the base.
                if tag == BASE_TAG {
                    tris_g.push(([p00, p10, p11], tag));
                    tris_g.push(([p00, p11, p01], tag));
                } else {
                    tris_g.push(([p00, p11, p10], tag));
                    tris_g.push(([p00, p01, p11], tag));
                }
            }
        }
    }
    let mut map = vec![u32::MAX; ngrid];
    let mut nodes = Vec::new();
    for t in &tets_g {
        for &g in t {
            if map[g] == u32::MAX {
                map[g] = 0;
            }
        }
    }
    for (g, m) in map.iter_mut().enumerate() {
        if *m == 0 {
            *m = nodes.len() as u32;
            let i = g % (nx + 1);
            let j = (g / (nx + 1)) % (ny + 1);
            let k = g / ((nx + 1) * (ny + 1));
            nodes.push([
                (spec.min[0] + i as f64 * h[0]) * s,
                (spec.min[1] + j as f64 * h[1]) * s,
                (spec.min[2] + k as f64 * h[2]) * s,
            ]);
        }
    }
    let mut mesh = Mesh::from_tets(nodes, Vec::with_capacity(tets_g.len()));
    for t in &tets_g {
        let mut v = [map[t[0]], map[t[1]], map[t[2]], map[t[3]]];
        let p = [0, 1, 2, 3].map(|c| mesh.nodes[v[c] as usize]);
        if signed_volume(p) < 0.0 {
            v.swap(2, 3);
        }
        mesh.tets.push(v);
    }
    mesh.tet_tags = vec![SOLID_TAG; mesh.tets.len()];
    for (t, tag) in tris_g {
        mesh.tris.push([map[t[0]], map[t[1]], map[t[2]]]);
        mesh.tri_tags.push(tag);
    }
    mesh.set_name(3, SOLID_TAG, "solid");
    if mesh.tri_tags.contains(&CAVITY_TAG) {
        mesh.set_name(2, CAVITY_TAG, "cavity");
    }
    mesh.set_name(2, BASE_TAG, "base");
    mesh.set_name(2, TIP_TAG, "tip");
    let base = mesh.surface_nodes(BASE_TAG);
    let tip = mesh.surface_nodes(TIP_TAG);
    mesh.node_sets.insert("base".into(), base);
    mesh.node_sets.insert("tip".into(), tip);
    Ok(mesh)
}
