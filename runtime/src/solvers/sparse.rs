//! The tangent stiffness of a scene as a sparse matrix over its free degrees of freedom, and
//! its sparse direct factorization (faer).
//!
//! The pattern is fixed by the mesh: one 3×3 block for every pair of free nodes that share an
//! element or a chamber triangle, stored column by column (CSC, as faer factors it). It is
//! built once, with the position in the value array of every entry of every element's and
//! triangle's Jacobian, so refilling the values for a new state is one pass over the entities
//! in their kernel order (a fixed summation order: assembly is deterministic). Fixed nodes are
//! eliminated: their rows and columns are not in the matrix. The symbolic factorization
//! (fill-reducing ordering, elimination structure) is computed once; each Newton step only
//! refactors numerically.
//!
//! A body with no fixed node (a free body under balanced loads) has a tangent that is
//! singular along its six rigid modes. Six of its degrees of freedom are pinned (a statically
//! determinate "3-2-1" support: all of one node, two of a far node, one of a third off their
//! line) — identity rows and columns in the same pattern, no dense row — and each solution is
//! made free of rigid motion afterwards by projection ([`BlockPattern::remove_rigid_motion`]).
//! Balanced loads put no reaction on such a support, so the step is the one the six
//! constraints Σ Δx = 0, Σ (x − x̄) × Δx = 0 define; the matrix keeps the stiffness's symmetry
//! (Cholesky where it is definite) and its fill. (Six Lagrange multipliers, the former
//! approach, are six dense rows and columns: their fill made a 15.6k-dof sphere unsolvable.)

use faer::Side;
use faer::dyn_stack::{MemBuffer, MemStack};
use faer::linalg::solvers::Solve;
use faer::sparse::linalg::cholesky::{
    IntranodeLbltRef, LdltRef, LltRef, SymbolicCholesky, SymmetricOrdering,
    factorize_symbolic_cholesky,
};
use faer::sparse::linalg::solvers::{Lu, SymbolicLu};
use faer::sparse::{SparseColMatRef, SymbolicSparseColMat};

/// Marks an entry of a fixed node (not in the matrix).
const NONE: u32 = u32::MAX;

/// The sparsity pattern of the assembled tangent over the free degrees of freedom.
pub struct BlockPattern {
    /// Free degrees of freedom (3 per free node).
    pub n: usize,
    /// Which rigid motions the fixed nodes leave free (`None`: none, or not held). As many
    /// dofs as there are such motions are pinned and solutions are made free of those motions
    /// (see the module's docs).
    pub free_motion: Option<FreeMotion>,
    /// The pinned dofs of a free body (six), else empty.
    pinned: Vec<u32>,
    /// Per free dof, the position of its diagonal entry.
    diag: Vec<u32>,
    /// `node·3 + d` → free dof index, or [`NONE`] for a fixed node.
    dof: Vec<u32>,
    col_ptr: Vec<usize>,
    row_idx: Vec<usize>,
    /// Per element, the value index of its Jacobian's entry `i·3n + j` (n its nodes; [`NONE`]:
    /// fixed).
    elem_pos: Vec<u32>,
    /// Per chamber triangle, the value index of entry `i·3n + j`.
    tri_pos: Vec<u32>,
    /// Per node, the value index of entry `i·3 + j` of its diagonal block.
    node_pos: Vec<u32>,
    /// Quadratic elements: per node, the ends of the edge a mid-edge node sits on (`None` for
    /// a corner), for the multigrid's first coarsening (quadratic → linear interpolation).
    edge_ends: Option<Vec<Option<[u32; 2]>>>,
    /// The rest position of each free node, in dof order (the fill-reducing ordering's
    /// geometry).
    free_rest: Vec<[f64; 3]>,
}

impl BlockPattern {
    /// `hold_rigid_modes`: a static solve, where a body with no fixed node has its rigid
    /// modes held (an implicit step's inertia already makes its matrix regular); `rest`: the
    /// node positions the pinned dofs are chosen by. `elems` and `tris` are the connectivity
    /// as the kernels read it (`elem_nodes` and `tri_nodes` per entity: 4 and 3, or 10 and 6
    /// for quadratic elements).
    pub fn new(
        fixed: &[bool],
        (elems, elem_nodes): (&[u32], usize),
        (tris, tri_nodes): (&[u32], usize),
        hold_rigid_modes: bool,
        rest: &[[f64; 3]],
    ) -> Result<Self, String> {
        let n_nodes = fixed.len();
        let free_motion = match hold_rigid_modes {
            true => FreeMotion::of(fixed, rest),
            false => None,
        };
        let mut dof = vec![NONE; 3 * n_nodes];
        let mut n = 0u32;
        for (node, &f) in fixed.iter().enumerate() {
            if !f {
                for d in 0..3 {
                    dof[3 * node + d] = n;
                    n += 1;
                }
            }
        }
        // Free neighbours of each free node (itself included), sorted.
        let mut nbrs: Vec<Vec<u32>> = vec![Vec::new(); n_nodes];
        let mut link = |nodes: &[u32]| {
            for &a in nodes {
                if fixed[a as usize] {
                    continue;
                }
                for &b in nodes {
                    if !fixed[b as usize] {
                        nbrs[a as usize].push(b);
                    }
                }
            }
        };
        elems.chunks(elem_nodes).for_each(&mut link);
        tris.chunks(tri_nodes).for_each(&mut link);
        for l in &mut nbrs {
            l.sort_unstable();
            l.dedup();
        }
        // Column (b, db) holds rows (a, da) for a in nbrs(b), da in 0..3.
        let mut col_ptr = Vec::with_capacity(n as usize + 1);
        let mut row_idx = Vec::new();
        let mut col_start = vec![0usize; n_nodes];
        let mut free: Vec<(u32, u8)> = Vec::new();
        col_ptr.push(0);
        for b in 0..n_nodes {
            if fixed[b] {
                continue;
            }
            col_start[b] = row_idx.len();
            for db in 0..3 {
                for &a in &nbrs[b] {
                    for da in 0..3 {
                        row_idx.push(dof[3 * a as usize + da] as usize);
                    }
                }
                free.push((b as u32, db as u8));
                col_ptr.push(row_idx.len());
            }
        }
        if row_idx.len() >= NONE as usize {
            return Err(format!(
                "the tangent has {} nonzeros, more than this solver indexes",
                row_idx.len()
            ));
        }
        let position = |a: u32, da: usize, b: u32, db: usize| -> u32 {
            if fixed[a as usize] || fixed[b as usize] {
                return NONE;
            }
            let list = &nbrs[b as usize];
            let k = list.binary_search(&a).expect("neighbours are linked");
            (col_start[b as usize] + db * 3 * list.len() + 3 * k + da) as u32
        };
        let positions = |nodes: &[u32]| {
            let m = 3 * nodes.len();
            let mut out = Vec::with_capacity(m * m);
            for i in 0..m {
                for j in 0..m {
                    out.push(position(nodes[i / 3], i % 3, nodes[j / 3], j % 3));
                }
            }
            out
        };
        let elem_pos = elems.chunks(elem_nodes).flat_map(positions).collect();
        let tri_pos = tris.chunks(tri_nodes).flat_map(positions).collect();
        let node_pos = (0..n_nodes as u32).flat_map(|n| positions(&[n])).collect();
        let diag = free
            .iter()
            .map(|&(b, d)| position(b, d as usize, b, d as usize))
            .collect();
        let pinned = match &free_motion {
            Some(motion) => motion.support(rest)?.into_iter().map(|i| dof[i]).collect(),
            None => Vec::new(),
        };
        Ok(BlockPattern {
            n: n as usize,
            free_motion,
            pinned,
            diag,
            dof,
            col_ptr,
            row_idx,
            elem_pos,
            tri_pos,
            node_pos,
            edge_ends: None,
            free_rest: (0..n_nodes)
                .filter(|&i| !fixed[i])
                .map(|i| rest[i])
                .collect(),
        })
    }

    /// Declare the nodes that are mid-edge nodes of quadratic elements (`ends[node]`: the
    /// edge's corners), so that [`BlockPattern::linear_coarsening`] can interpolate them.
    pub fn with_edge_ends(mut self, ends: Vec<Option<[u32; 2]>>) -> Self {
        self.edge_ends = Some(ends);
        self
    }

    /// For quadratic elements: the interpolation P from the corners' free dofs to all free
    /// dofs (a corner's dof is itself, a mid-edge node's the mean of its edge's corners'; a
    /// fixed corner contributes nothing), the coarse dofs' node blocks, and the near-null
    /// space `modes` on the corners. `None` for linear elements and for bodies held by pinned
    /// dofs (their pins need not be corners). The multigrid solver's first coarsening: the
    /// linear problem on the same mesh, which smoothed aggregation then coarsens.
    pub fn linear_coarsening(
        &self,
        modes: &[Vec<f64>],
    ) -> Option<(crate::solvers::amg::Csr, Vec<usize>, Vec<Vec<f64>>)> {
        let ends = self.edge_ends.as_ref()?;
        if !self.pinned.is_empty() {
            return None;
        }
        // Coarse index of each corner's free dofs, in free-dof order.
        let mut coarse = vec![NONE; self.dof.len()];
        let mut corners_fine = Vec::new();
        for (i, &d) in self.dof.iter().enumerate() {
            if d != NONE && ends[i / 3].is_none() {
                coarse[i] = corners_fine.len() as u32;
                corners_fine.push(d as usize);
            }
        }
        let m = corners_fine.len();
        let mut rows: Vec<Vec<(u32, f64)>> = vec![Vec::new(); self.n];
        for (i, &d) in self.dof.iter().enumerate() {
            if d == NONE {
                continue;
            }
            let (node, comp) = (i / 3, i % 3);
            rows[d as usize] = match ends[node] {
                None => vec![(coarse[i], 1.0)],
                Some([a, b]) => [a, b]
                    .iter()
                    .map(|&e| coarse[3 * e as usize + comp])
                    .filter(|&c| c != NONE)
                    .map(|c| (c, 0.5))
                    .collect(),
            };
        }
        let mut ptr = vec![0usize];
        let (mut idx, mut val) = (Vec::new(), Vec::new());
        for mut r in rows {
            r.sort_by_key(|e| e.0);
            for (c, v) in r {
                idx.push(c);
                val.push(v);
            }
            ptr.push(idx.len());
        }
        let p = crate::solvers::amg::Csr {
            rows: self.n,
            cols: m,
            ptr,
            idx,
            val,
        };
        let blocks = (0..=m / 3).map(|i| 3 * i).collect();
        let coarse_modes = modes
            .iter()
            .map(|mode| corners_fine.iter().map(|&d| mode[d]).collect())
            .collect();
        Some((p, blocks, coarse_modes))
    }

    /// Whether the body is free to move rigidly (no fixed node, or fixed nodes at one point or
    /// on one line) and the solve holds those motions.
    pub fn rigid(&self) -> bool {
        self.free_motion.is_some()
    }

    /// Nonzeros of the matrix.
    pub fn nnz(&self) -> usize {
        self.row_idx.len()
    }

    /// The free dof of `node·3 + d`, if the node is free.
    pub fn dof(&self, i: usize) -> Option<usize> {
        let d = self.dof[i];
        (d != NONE).then_some(d as usize)
    }

    /// The matrix's order: the free dofs.
    pub fn size(&self) -> usize {
        self.n
    }

    /// Free-dof entries of a node-major vector (3 per node), zeros at a free body's pinned
    /// dofs.
    pub fn restrict(&self, full: &[f64]) -> Vec<f64> {
        let mut out = vec![0.0; self.size()];
        for (i, &d) in self.dof.iter().enumerate() {
            if d != NONE {
                out[d as usize] = full[i];
            }
        }
        for &p in &self.pinned {
            out[p as usize] = 0.0;
        }
        out
    }

    /// K·v for the matrix with these values (the pattern's order), over the free dofs.
    pub fn multiply(&self, values: &[f64], v: &[f64]) -> Vec<f64> {
        multiply_csc((&self.col_ptr, &self.row_idx), values, v)
    }

    /// Remove the rigid motion from a node-major vector `v` of a free body at positions `x`:
    /// `v − R (RᵀR)⁻¹ Rᵀ v`, R the three translations and the three rotations about the
    /// centroid. A Newton step so has no mean translation or rotation; a right-hand side so
    /// has no part the pinned support would take as a reaction. Nothing for a body that is
    /// not free.
    pub fn remove_rigid_motion(&self, x: &[f64], v: &mut [f64]) {
        let Some(motion) = &self.free_motion else {
            return;
        };
        let modes = motion.modes(x);
        project_out(&modes, &modes, v);
    }

    /// Positions `x` (node-major) moved by the free rigid motion to the pose that best
    /// matches `rest` in least squares ([`align_to`]; about the fixed point or line where the
    /// body is held there). Unchanged for a body with no free motion.
    pub fn align(&self, rest: &[[f64; 3]], x: &[f64]) -> Vec<f64> {
        match &self.free_motion {
            Some(FreeMotion::Rigid) => align_to(rest, x),
            Some(FreeMotion::AboutPoint { centre, .. }) => rotate_about(rest, x, *centre),
            Some(FreeMotion::AboutLine { point, axis, .. }) => {
                turn_about_axis(rest, x, *point, *axis)
            }
            None => x.to_vec(),
        }
    }

    /// A node-major vector (3 per node, 0 at fixed nodes) from free-dof entries.
    pub fn extend(&self, free: &[f64]) -> Vec<f64> {
        self.dof
            .iter()
            .map(|&d| if d == NONE { 0.0 } else { free[d as usize] })
            .collect()
    }

    /// The sensitivity ∂L/∂x of a free body's equilibrium at positions `x` as its adjoint
    /// needs it: the equilibrium is posed by [`align_to`] its rest shape `rest`, so its
    /// derivative dx keeps Σ dx = 0 and Σ dx × (X − X̄) = 0 (C(X)ᵀ dx = 0, C the rigid modes
    /// at rest) while a solve gives it up to a rigid motion R(x)·a; then g·dx = ĝ·dx_any with
    /// ĝ = g − C (RᵀC)⁻¹ Rᵀ g. Nothing for a body that is not free.
    pub fn pose_free_sensitivity(&self, rest: &[[f64; 3]], x: &[f64], g: &mut [f64]) {
        let Some(motion) = &self.free_motion else {
            return;
        };
        let flat: Vec<f64> = rest.iter().flatten().copied().collect();
        project_out(&motion.modes(x), &motion.modes(&flat), g);
    }

    /// The stiffness K = −∂residual/∂x from the element Jacobians (element × (3n)², ∂f/∂x, n
    /// its nodes), the chamber triangles' (triangle × (3n)²) and the nodes' own (node × 9: an implicit step's
    /// inertia; empty for a static solve), summed entity by entity in kernel order.
    ///
    /// A free body's pinned dofs get identity rows and columns, scaled to the stiffness's
    /// mean diagonal so the factorization stays well conditioned (their right-hand side is 0).
    pub fn assemble(
        &self,
        elem_jac: &[f64],
        tri_jac: &[f64],
        node_jac: &[f64],
        values: &mut Vec<f64>,
    ) {
        values.clear();
        values.resize(self.nnz(), 0.0);
        for (pos, jac) in [
            (&self.elem_pos, elem_jac),
            (&self.tri_pos, tri_jac),
            (&self.node_pos, node_jac),
        ] {
            for (&p, &v) in pos.iter().zip(jac) {
                if p != NONE {
                    values[p as usize] -= v;
                }
            }
        }
        if self.rigid() {
            self.pin(values);
        }
    }
}

impl BlockPattern {
    /// Per entry, the position of its transpose (the pattern is structurally symmetric).
    pub fn transpose_map(&self) -> Result<Vec<usize>, String> {
        // Entry k is (row_idx[k], column j); its transpose is (j, row_idx[k]).
        let mut transpose = vec![0usize; self.row_idx.len()];
        for j in 0..self.n {
            for (k, &i) in self
                .row_idx
                .iter()
                .enumerate()
                .take(self.col_ptr[j + 1])
                .skip(self.col_ptr[j])
            {
                let col = &self.row_idx[self.col_ptr[i]..self.col_ptr[i + 1]];
                let at = col
                    .binary_search(&j)
                    .map_err(|_| "the tangent's pattern is not symmetric".to_string())?;
                transpose[k] = self.col_ptr[i] + at;
            }
        }
        Ok(transpose)
    }

    /// The matrix with these values (the pattern's order) by rows — or its transpose with
    /// `transposed` — for the multigrid solver. `transpose` is [`BlockPattern::transpose_map`].
    pub fn to_csr(
        &self,
        values: &[f64],
        transpose: &[usize],
        transposed: bool,
    ) -> crate::solvers::amg::Csr {
        // Column j of the CSC arrays lists row j of the transpose; the pattern's symmetry
        // makes the same arrays row j of the matrix once each value is taken from its mirror.
        let val = match transposed {
            true => values.to_vec(),
            false => transpose.iter().map(|&t| values[t]).collect(),
        };
        crate::solvers::amg::Csr {
            rows: self.n,
            cols: self.n,
            ptr: self.col_ptr.clone(),
            idx: self.row_idx.iter().map(|&i| i as u32).collect(),
            val,
        }
    }

    /// The six rigid-body modes at positions `x` (node-major) over the free dofs (zero at a
    /// free body's pinned ones): the near-null space of the stiffness, which a multigrid
    /// hierarchy must represent on its coarse levels.
    pub fn near_null_space(&self, x: &[f64]) -> Vec<Vec<f64>> {
        rigid_modes(x).iter().map(|m| self.restrict(m)).collect()
    }

    /// The free dofs grouped by node (three each): `blocks[i]..blocks[i + 1]`.
    pub fn node_blocks(&self) -> Vec<usize> {
        (0..=self.n / 3).map(|i| 3 * i).collect()
    }

    fn pin(&self, values: &mut [f64]) {
        let scale = self
            .diag
            .iter()
            .map(|&p| values[p as usize].abs())
            .sum::<f64>()
            / self.diag.len().max(1) as f64;
        let is_pinned = |d: usize| self.pinned.contains(&(d as u32));
        for col in 0..self.n {
            let col_pinned = is_pinned(col);
            let range = self.col_ptr[col]..self.col_ptr[col + 1];
            for (value, &row) in values[range.clone()].iter_mut().zip(&self.row_idx[range]) {
                if col_pinned || is_pinned(row) {
                    *value = if row == col { scale } else { 0.0 };
                }
            }
        }
    }
}

/// Positions `x` (node-major) moved rigidly to the pose that best matches `rest` in least
/// squares: the centroids coincide and the rotation is the Kabsch solution (the SVD of the
/// cross-covariance, a proper rotation).
pub fn align_to(rest: &[[f64; 3]], x: &[f64]) -> Vec<f64> {
    use nalgebra::Vector3;
    let n = rest.len().max(1) as f64;
    let mut cx = Vector3::zeros();
    let mut cr = Vector3::zeros();
    for (p, q) in x.chunks(3).zip(rest) {
        cx += Vector3::new(p[0], p[1], p[2]) / n;
        cr += Vector3::new(q[0], q[1], q[2]) / n;
    }
    kabsch(rest, x, cx, cr)
}

/// Positions `x` rotated about `from` and moved to `to`, by the proper rotation that best maps
/// x − from onto rest − to in least squares (Kabsch: the SVD of the cross-covariance).
fn kabsch(
    rest: &[[f64; 3]],
    x: &[f64],
    from: nalgebra::Vector3<f64>,
    to: nalgebra::Vector3<f64>,
) -> Vec<f64> {
    use nalgebra::{Matrix3, Vector3};
    let mut h = Matrix3::zeros();
    for (p, q) in x.chunks(3).zip(rest) {
        h += (Vector3::new(p[0], p[1], p[2]) - from) * (Vector3::from(*q) - to).transpose();
    }
    let svd = h.svd(true, true);
    let (Some(u), Some(vt)) = (svd.u, svd.v_t) else {
        return x.to_vec();
    };
    let mut d = Matrix3::identity();
    if (vt.transpose() * u.transpose()).determinant() < 0.0 {
        d[(2, 2)] = -1.0;
    }
    let q = vt.transpose() * d * u.transpose();
    x.chunks(3)
        .flat_map(|p| {
            let y = q * (Vector3::new(p[0], p[1], p[2]) - from) + to;
            [y[0], y[1], y[2]]
        })
        .collect()
}

/// The rigid motions a static body's fixed nodes leave free.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum FreeMotion {
    /// No fixed node: all six rigid motions.
    Rigid,
    /// The fixed nodes are at one point (`node`, index into the mesh): three rotations about it.
    AboutPoint { centre: [f64; 3], node: usize },
    /// The fixed nodes lie on one line (through nodes `ends`): the rotation about it.
    AboutLine {
        point: [f64; 3],
        axis: [f64; 3],
        ends: (usize, usize),
    },
}

fn sub(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [a[0] - b[0], a[1] - b[1], a[2] - b[2]]
}

fn dot3(a: [f64; 3], b: [f64; 3]) -> f64 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}

fn cross(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [
        a[1] * b[2] - a[2] * b[1],
        a[2] * b[0] - a[0] * b[2],
        a[0] * b[1] - a[1] * b[0],
    ]
}

fn norm3(a: [f64; 3]) -> f64 {
    dot3(a, a).sqrt()
}

/// The index of a vector's largest component (in magnitude).
fn largest_axis(v: [f64; 3]) -> usize {
    (0..3)
        .max_by(|&i, &j| v[i].abs().total_cmp(&v[j].abs()))
        .unwrap_or(2)
}

impl FreeMotion {
    /// Its name in the JSON (`free_motion_kind`).
    pub fn kind(&self) -> &'static str {
        match self {
            FreeMotion::Rigid => "all",
            FreeMotion::AboutPoint { .. } => "point",
            FreeMotion::AboutLine { .. } => "line",
        }
    }

    /// The rigid motions `fixed` (per node) leaves free at rest positions `rest`: all of them
    /// without a fixed node, the rotations about a point or a line where the fixed nodes are
    /// there (to 1e-6 of the body's size), else none.
    pub fn of(fixed: &[bool], rest: &[[f64; 3]]) -> Option<FreeMotion> {
        let held: Vec<usize> = (0..fixed.len()).filter(|&n| fixed[n]).collect();
        let Some(&first) = held.first() else {
            return Some(FreeMotion::Rigid);
        };
        let (mut lo, mut hi) = ([f64::INFINITY; 3], [f64::NEG_INFINITY; 3]);
        for p in rest {
            for d in 0..3 {
                lo[d] = lo[d].min(p[d]);
                hi[d] = hi[d].max(p[d]);
            }
        }
        let tolerance = 1e-6 * norm3(sub(hi, lo));
        let p0 = rest[first];
        let (far, distance) = held
            .iter()
            .map(|&n| (n, norm3(sub(rest[n], p0))))
            .fold((first, 0.0), |a, b| if b.1 > a.1 { b } else { a });
        if distance <= tolerance {
            return Some(FreeMotion::AboutPoint {
                centre: p0,
                node: first,
            });
        }
        let axis = sub(rest[far], p0).map(|c| c / distance);
        let off_line = held.iter().any(|&n| {
            let r = sub(rest[n], p0);
            norm3(sub(r, axis.map(|c| c * dot3(r, axis)))) > tolerance
        });
        (!off_line).then_some(FreeMotion::AboutLine {
            point: p0,
            axis,
            ends: (first, far),
        })
    }

    /// The free motions as velocity fields at positions `x` (node-major), scaled by the
    /// body's size.
    pub fn modes(&self, x: &[f64]) -> Vec<Vec<f64>> {
        let rotations = |centre: [f64; 3], axes: &[[f64; 3]]| {
            let size = x
                .chunks(3)
                .map(|p| norm3(sub([p[0], p[1], p[2]], centre)))
                .fold(0.0f64, f64::max)
                .max(f64::MIN_POSITIVE);
            axes.iter()
                .map(|&axis| {
                    x.chunks(3)
                        .flat_map(|p| {
                            let r = sub([p[0], p[1], p[2]], centre).map(|c| c / size);
                            cross(axis, r)
                        })
                        .collect()
                })
                .collect()
        };
        match *self {
            FreeMotion::Rigid => rigid_modes(x),
            FreeMotion::AboutPoint { centre, .. } => {
                rotations(centre, &[[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]])
            }
            FreeMotion::AboutLine { point, axis, .. } => rotations(point, &[axis]),
        }
    }

    /// A statically determinate support of the free motions (node-major dofs `3·node + d`),
    /// which puts no force on loads those motions do no work against.
    fn support(&self, rest: &[[f64; 3]]) -> Result<Vec<usize>, String> {
        let farthest = |from: &dyn Fn([f64; 3]) -> f64| {
            (0..rest.len())
                .max_by(|&i, &j| from(rest[i]).total_cmp(&from(rest[j])))
                .unwrap_or(0)
        };
        match *self {
            FreeMotion::Rigid => three_two_one(rest),
            FreeMotion::AboutPoint { centre, .. } => {
                // b: the node farthest from the centre, held across the line to it (its two
                // components least aligned with that line); c: the node farthest from that
                // line, held along the normal of the plane through the three.
                let b = farthest(&|p| norm3(sub(p, centre)));
                let cb = sub(rest[b], centre);
                let off = |p: [f64; 3]| norm3(cross(sub(p, centre), cb)) / norm3(cb).max(1e-300);
                let c = farthest(&off);
                if norm3(cb) == 0.0 || off(rest[c]) <= 1e-6 * norm3(cb) {
                    return Err("a body held at one point must span a volume".into());
                }
                let mut axes = [0usize, 1, 2];
                axes.sort_by(|&i, &j| cb[i].abs().total_cmp(&cb[j].abs()));
                let normal = cross(cb, sub(rest[c], centre));
                Ok(vec![
                    3 * b + axes[0],
                    3 * b + axes[1],
                    3 * c + largest_axis(normal),
                ])
            }
            FreeMotion::AboutLine { point, axis, .. } => {
                // The node farthest from the line, held along its motion about it.
                let off = |p: [f64; 3]| norm3(cross(axis, sub(p, point)));
                let e = farthest(&off);
                if off(rest[e]) == 0.0 {
                    return Err("a body held along a line must reach off it".into());
                }
                Ok(vec![3 * e + largest_axis(cross(axis, sub(rest[e], point)))])
            }
        }
    }
}

/// Positions `x` rotated about `centre` (which stays) to the pose that best matches `rest`
/// in least squares (Kabsch about a fixed point).
fn rotate_about(rest: &[[f64; 3]], x: &[f64], centre: [f64; 3]) -> Vec<f64> {
    let c = nalgebra::Vector3::from(centre);
    kabsch(rest, x, c, c)
}

/// Positions `x` turned about the line through `point` along the unit `axis` by the angle
/// that best matches `rest` in least squares: θ = atan2(Σ v·(a×u), Σ v·u⊥) for u = x − p,
/// v = X − p.
fn turn_about_axis(rest: &[[f64; 3]], x: &[f64], point: [f64; 3], axis: [f64; 3]) -> Vec<f64> {
    let (mut c, mut s) = (0.0, 0.0);
    for (p, q) in x.chunks(3).zip(rest) {
        let u = sub([p[0], p[1], p[2]], point);
        let v = sub(*q, point);
        let u_perp = sub(u, axis.map(|a| a * dot3(u, axis)));
        c += dot3(v, u_perp);
        s += dot3(v, cross(axis, u));
    }
    let theta = s.atan2(c);
    let (sin, cos) = theta.sin_cos();
    x.chunks(3)
        .flat_map(|p| {
            let u = sub([p[0], p[1], p[2]], point);
            let along = dot3(u, axis);
            let w = cross(axis, u);
            [0, 1, 2]
                .map(|d| point[d] + axis[d] * along + cos * (u[d] - axis[d] * along) + sin * w[d])
        })
        .collect()
}

/// Whether `values` form a symmetric matrix to `relative` round-off of their largest entry.
pub fn symmetric(transpose: &[usize], relative: f64, values: &[f64]) -> bool {
    let scale = values.iter().fold(0.0f64, |m, v| m.max(v.abs()));
    let tol = relative * scale;
    values
        .iter()
        .zip(transpose)
        .all(|(v, &t)| (v - values[t]).abs() <= tol)
}

/// The negative eigenvalues of an LBLᵀ factorization's block diagonal B: a 1×1 pivot's
/// sign, and a 2×2 pivot [[d₁, b], [b, d₂]] has one when its determinant is negative, two when
/// it is positive and d₁ < 0.
fn lblt_negative_pivots(symbolic: &SymbolicCholesky<usize>, f: &Lblt) -> usize {
    use faer::sparse::linalg::cholesky::SymbolicCholeskyRaw;
    // B's diagonal: in a supernodal factor, the diagonal of each supernode's column-major
    // block (its columns, then its pattern's rows); in a simplicial one, each column's
    // diagonal entry (no pivoting: no 2×2 blocks).
    let diagonal: Vec<f64> = match symbolic.raw() {
        SymbolicCholeskyRaw::Supernodal(s) => {
            let mut d = Vec::with_capacity(s.nrows());
            for k in 0..s.n_supernodes() {
                let (begin, end) = (s.supernode_begin()[k], s.supernode_end()[k]);
                let size = end - begin;
                let rows = size + s.supernode(k).pattern().len();
                let start = s.col_ptr_for_val()[k];
                d.extend((0..size).map(|j| f.values[start + j * rows + j]));
            }
            d
        }
        SymbolicCholeskyRaw::Simplicial(s) => (0..s.nrows())
            .map(|j| {
                let (col_ptr, row_idx) = (s.col_ptr(), s.row_idx());
                (col_ptr[j]..col_ptr[j + 1])
                    .find(|&k| row_idx[k] == j)
                    .map_or(0.0, |k| f.values[k])
            })
            .collect(),
    };
    let mut negative = 0;
    let mut j = 0;
    while j < diagonal.len() {
        let b = f.subdiag[j];
        if b == 0.0 || j + 1 == diagonal.len() {
            negative += usize::from(diagonal[j] < 0.0);
            j += 1;
        } else {
            let det = diagonal[j] * diagonal[j + 1] - b * b;
            negative += if det < 0.0 {
                1
            } else if diagonal[j] < 0.0 {
                2
            } else {
                0
            };
            j += 2;
        }
    }
    negative
}

/// The product of the square CSC matrix (`col_ptr`, `row_idx`, `values`) with `v`, column by
/// column (a fixed summation order).
fn multiply_csc((col_ptr, row_idx): (&[usize], &[usize]), values: &[f64], v: &[f64]) -> Vec<f64> {
    let size = col_ptr.len() - 1;
    let mut out = vec![0.0; size];
    for (col, &vc) in v.iter().enumerate().take(size) {
        let range = col_ptr[col]..col_ptr[col + 1];
        for (a, &row) in values[range.clone()].iter().zip(&row_idx[range]) {
            out[row] += a * vc;
        }
    }
    out
}

fn dot(a: &[f64], b: &[f64]) -> f64 {
    a.iter().zip(b).map(|(x, y)| x * y).sum()
}

/// The six rigid modes at positions `x` (node-major): translations along x, y, z, and
/// rotations about the axes through the centroid, scaled by the body's size.
pub(crate) fn rigid_modes(x: &[f64]) -> Vec<Vec<f64>> {
    let n = x.len() / 3;
    let mut centre = [0.0; 3];
    for p in x.chunks(3) {
        for d in 0..3 {
            centre[d] += p[d] / n as f64;
        }
    }
    let size = x
        .chunks(3)
        .flat_map(|p| (0..3).map(move |d| (p[d] - centre[d]).abs()))
        .fold(0.0f64, f64::max)
        .max(f64::MIN_POSITIVE);
    let mut modes = vec![vec![0.0; x.len()]; 6];
    for (i, p) in x.chunks(3).enumerate() {
        let r = [0, 1, 2].map(|d| (p[d] - centre[d]) / size);
        for d in 0..3 {
            modes[d][3 * i + d] = 1.0;
        }
        // e_c × r for the rotation about axis c.
        let rot = [[0.0, -r[2], r[1]], [r[2], 0.0, -r[0]], [-r[1], r[0], 0.0]];
        for c in 0..3 {
            for d in 0..3 {
                modes[3 + c][3 * i + d] = rot[d][c];
            }
        }
    }
    modes
}

/// `v − C (RᵀC)⁻¹ Rᵀ v` (the columns of R and C given as vectors): the part of `v` that R's
/// columns do not see, along C's. With C = R the orthogonal projection off R. Unchanged where
/// RᵀC is singular.
fn project_out(r: &[Vec<f64>], c: &[Vec<f64>], v: &mut [f64]) {
    let mut rc: Vec<Vec<f64>> = r
        .iter()
        .map(|ri| c.iter().map(|cj| dot(ri, cj)).collect())
        .collect();
    let mut coefficients: Vec<f64> = r.iter().map(|ri| dot(ri, v)).collect();
    if crate::solvers::dense::solve(&mut rc, &mut coefficients).is_none() {
        return;
    }
    for (cj, aj) in c.iter().zip(coefficients) {
        for (vi, ci) in v.iter_mut().zip(cj) {
            *vi -= aj * ci;
        }
    }
}

/// A statically determinate support of a free body (node-major dof indices `3·node + d`): all
/// three dofs of the node nearest the centroid's opposite corner (`a`), the two dofs of the
/// node farthest from it (`b`) across the line ab, and the one dof of the node farthest from
/// that line (`c`) along the normal of the plane abc. It fixes the six rigid modes and puts no
/// force on a balanced load.
fn three_two_one(rest: &[[f64; 3]]) -> Result<Vec<usize>, String> {
    let sub = |p: &[f64; 3], q: &[f64; 3]| [p[0] - q[0], p[1] - q[1], p[2] - q[2]];
    let norm = |v: [f64; 3]| (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt();
    let farthest = |from: &dyn Fn(&[f64; 3]) -> f64| {
        (0..rest.len())
            .max_by(|&i, &j| from(&rest[i]).total_cmp(&from(&rest[j])))
            .unwrap_or(0)
    };
    let centre = {
        let mut c = [0.0; 3];
        for p in rest {
            for d in 0..3 {
                c[d] += p[d] / rest.len().max(1) as f64;
            }
        }
        c
    };
    let a = farthest(&|p| norm(sub(p, &centre)));
    let b = farthest(&|p| norm(sub(p, &rest[a])));
    let ab = sub(&rest[b], &rest[a]);
    let lab = norm(ab);
    let off_line = |p: &[f64; 3]| {
        let ap = sub(p, &rest[a]);
        let t =
            (ap[0] * ab[0] + ap[1] * ab[1] + ap[2] * ab[2]) / (lab * lab).max(f64::MIN_POSITIVE);
        norm([ap[0] - t * ab[0], ap[1] - t * ab[1], ap[2] - t * ab[2]])
    };
    let c = farthest(&off_line);
    if lab == 0.0 || off_line(&rest[c]) <= 1e-6 * lab {
        return Err(
            "a body with no fixed node must span a volume (its nodes lie on one line)".into(),
        );
    }
    // b: the two components least aligned with ab (ab itself stays free).
    let mut axes = [0usize, 1, 2];
    axes.sort_by(|&i, &j| ab[i].abs().total_cmp(&ab[j].abs()));
    let ac = sub(&rest[c], &rest[a]);
    let normal = [
        ab[1] * ac[2] - ab[2] * ac[1],
        ab[2] * ac[0] - ab[0] * ac[2],
        ab[0] * ac[1] - ab[1] * ac[0],
    ];
    let along = (0..3)
        .max_by(|&i, &j| normal[i].abs().total_cmp(&normal[j].abs()))
        .unwrap_or(2);
    Ok(vec![
        3 * a,
        3 * a + 1,
        3 * a + 2,
        3 * b + axes[0],
        3 * b + axes[1],
        3 * c + along,
    ])
}

/// The factorization of the assembled tangent: Cholesky (LLᵀ) when it is symmetric positive
/// definite — a stable equilibrium of a conservative load, the common case, several times
/// faster than LU; a symmetric indefinite one (a Newton iterate away from equilibrium, a free
/// body's linearized rotations under load, a state past a limit point) by LBLᵀ with
/// Bunch–Kaufman pivoting inside the supernodes, on the same symbolic factorization, when a
/// test solve shows it accurate; else LU with partial pivoting (an open pressurised surface).
/// Symbolic parts are computed once and reused.
pub struct SparseSolver {
    symbolic: SymbolicSparseColMat<usize>,
    /// The position of each entry's transpose (the pattern is structurally symmetric).
    transpose: Vec<usize>,
    /// Relative tolerance of the symmetry test (the entries' round-off).
    symmetry: f64,
    /// The rest position of each free node, in dof order: the geometry of the symmetric
    /// factorizations' fill-reducing order ([`crate::solvers::ordering::dof_order`]), computed
    /// with their symbolic factorization.
    free_rest: Vec<[f64; 3]>,
    /// The symbolic Cholesky factorization that Cholesky and LBLᵀ share.
    symbolic_cholesky: Option<SymbolicCholesky<usize>>,
    symbolic_lu: Option<SymbolicLu<usize>>,
    factor: Option<Factor>,
    /// Whether the matrix can be positive definite (always, since a free body's rigid modes
    /// are pinned rather than held by multipliers).
    may_be_definite: bool,
    /// The inertia of the last factorization: its number of negative eigenvalues (0 for a
    /// Cholesky factorization; `None` for LU, which does not tell).
    negative_eigenvalues: Option<usize>,
}

enum Factor {
    /// L's values.
    Llt(Vec<f64>),
    Lblt(Lblt),
    Lu(Box<Lu<usize, f64>>),
}

/// The numeric part of an LDLᵀ factorization, or of an LBLᵀ one (faer's intranode
/// Bunch–Kaufman): L's values, B's subdiagonal (its 2×2 pivots, zero for LDLᵀ) and the
/// pivoting permutation (empty for LDLᵀ).
struct Lblt {
    values: Vec<f64>,
    subdiag: Vec<f64>,
    forward: Vec<usize>,
    inverse: Vec<usize>,
}

/// The largest relative error of an LBLᵀ solve accepted: above it, unpivoted-across-supernodes
/// elimination lost accuracy, and LU is used.
const LBLT_TEST_TOLERANCE: f64 = 1e-8;

impl SparseSolver {
    pub fn new(p: &BlockPattern, symmetry: f64) -> Result<Self, String> {
        let symbolic = SymbolicSparseColMat::new_checked(
            p.size(),
            p.size(),
            p.col_ptr.clone(),
            None,
            p.row_idx.clone(),
        );
        Ok(SparseSolver {
            symbolic,
            transpose: p.transpose_map()?,
            symmetry,
            free_rest: p.free_rest.clone(),
            symbolic_cholesky: None,
            symbolic_lu: None,
            factor: None,
            may_be_definite: true,
            negative_eigenvalues: None,
        })
    }

    /// Whether the matrix with these values is symmetric (to the solver's tolerance).
    pub fn symmetric(&self, values: &[f64]) -> bool {
        symmetric(&self.transpose, self.symmetry, values)
    }

    /// Factor the matrix with these values (the pattern's order). Returns which
    /// factorization was used (`"cholesky"`, `"lblt"` or `"lu"`).
    pub fn factor(&mut self, values: &[f64]) -> Result<&'static str, String> {
        let was_indefinite = self.negative_eigenvalues.is_some_and(|n| n > 0);
        self.negative_eigenvalues = None;
        // An indefinite tangent (Newton away from equilibrium) is usually followed by another:
        // LBLᵀ first then, rather than a Cholesky factorization that fails part way.
        if was_indefinite && self.symmetric(values) && self.factor_lblt(values)? {
            return Ok("lblt");
        }
        if self.may_be_definite && self.symmetric(values) {
            self.symbolic_cholesky()?;
            let symbolic = self.symbolic_cholesky.as_ref().expect("computed");
            let mut l = vec![0.0; symbolic.len_val()];
            let par = faer::Par::Seq;
            let scratch = symbolic.factorize_numeric_llt_scratch::<f64>(par, Default::default());
            let mut buffer = MemBuffer::try_new(scratch).map_err(|e| format!("{e:?}"))?;
            let mat = SparseColMatRef::new(self.symbolic.as_ref(), values);
            let llt = symbolic.factorize_numeric_llt(
                &mut l,
                mat,
                Side::Lower,
                Default::default(),
                par,
                MemStack::new(&mut buffer),
                Default::default(),
            );
            if llt.is_ok() {
                self.factor = Some(Factor::Llt(l));
                self.negative_eigenvalues = Some(0);
                return Ok("cholesky");
            }
            if !was_indefinite && self.factor_lblt(values)? {
                return Ok("lblt");
            }
        }
        if self.symbolic_lu.is_none() {
            self.symbolic_lu = Some(
                SymbolicLu::try_new(self.symbolic.as_ref())
                    .map_err(|e| format!("symbolic LU factorization failed: {e:?}"))?,
            );
        }
        let symbolic = self.symbolic_lu.clone().expect("computed");
        let mat = SparseColMatRef::new(self.symbolic.as_ref(), values);
        let lu = Lu::try_new_with_symbolic(symbolic, mat).map_err(|e| format!("{e:?}"))?;
        self.factor = Some(Factor::Lu(Box::new(lu)));
        Ok("lu")
    }

    /// Factor a symmetric matrix by LBLᵀ and keep it if a test solve (of K·1) is accurate;
    /// whether it was kept.
    fn factor_lblt(&mut self, values: &[f64]) -> Result<bool, String> {
        self.symbolic_cholesky()?;
        let symbolic = self.symbolic_cholesky.as_ref().expect("computed");
        let n = symbolic.nrows();
        let mut f = Lblt {
            values: vec![0.0; symbolic.len_val()],
            subdiag: vec![0.0; n],
            forward: Vec::new(),
            inverse: Vec::new(),
        };
        let mat = SparseColMatRef::new(self.symbolic.as_ref(), values);
        // LDLᵀ without pivoting first: the same supernodal kernels as Cholesky. Bunch–Kaufman
        // pivoting (inside supernodes) where it meets a zero pivot or loses accuracy.
        let par = faer::Par::Seq;
        let scratch = symbolic.factorize_numeric_ldlt_scratch::<f64>(par, Default::default());
        let mut buffer = MemBuffer::try_new(scratch).map_err(|e| format!("{e:?}"))?;
        let ldlt = symbolic.factorize_numeric_ldlt(
            &mut f.values,
            mat,
            Side::Lower,
            Default::default(),
            par,
            MemStack::new(&mut buffer),
            Default::default(),
        );
        if ldlt.is_err() {
            f.forward = vec![0; n];
            f.inverse = vec![0; n];
            let scratch = symbolic.factorize_numeric_intranode_lblt_scratch::<f64>(
                faer::Par::Seq,
                Default::default(),
            );
            let mut buffer = MemBuffer::try_new(scratch).map_err(|e| format!("{e:?}"))?;
            symbolic.factorize_numeric_intranode_lblt(
                &mut f.values,
                &mut f.subdiag,
                &mut f.forward,
                &mut f.inverse,
                mat,
                Side::Lower,
                faer::Par::Seq,
                MemStack::new(&mut buffer),
                Default::default(),
            );
        }
        let negative = lblt_negative_pivots(symbolic, &f);
        let previous = self.factor.replace(Factor::Lblt(f));
        // The test: K·1 solved back to 1.
        let ones = vec![1.0; n];
        let csc = (self.symbolic.col_ptr(), self.symbolic.row_idx());
        let mut y = multiply_csc(csc, values, &ones);
        self.solve(&mut y);
        let error = y.iter().fold(0.0f64, |m, v| m.max((v - 1.0).abs()));
        if error.is_finite() && error <= LBLT_TEST_TOLERANCE {
            self.negative_eigenvalues = Some(negative);
            return Ok(true);
        }
        self.factor = previous;
        Ok(false)
    }

    /// Whether faer chose its supernodal factorization for these values (tests).
    #[cfg(test)]
    fn symbolic_lblt_raw_is_supernodal(&mut self, values: &[f64]) -> Option<bool> {
        use faer::sparse::linalg::cholesky::SymbolicCholeskyRaw;
        self.factor_lblt(values).ok()?;
        let raw = self.symbolic_cholesky.as_ref()?.raw();
        Some(matches!(raw, SymbolicCholeskyRaw::Supernodal(_)))
    }

    /// The number of negative eigenvalues of the last factored matrix (Sylvester's law of
    /// inertia: those of LBLᵀ's block diagonal B), when the factorization tells: Cholesky (0)
    /// and LBLᵀ do, LU does not.
    pub fn negative_eigenvalues(&self) -> Option<usize> {
        self.negative_eigenvalues
    }

    /// Solve K·y = b in place.
    pub fn solve(&self, b: &mut [f64]) {
        let n = b.len();
        let rhs = faer::MatMut::from_column_major_slice_mut(b, n, 1);
        match self.factor.as_ref().expect("factored") {
            Factor::Llt(l) => self.solve_llt(l, rhs),
            Factor::Lblt(f) => self.solve_lblt(f, rhs),
            Factor::Lu(f) => f.solve_in_place(rhs),
        }
    }

    /// Solve Kᵀ·y = b in place.
    pub fn solve_transpose(&self, b: &mut [f64]) {
        let n = b.len();
        let rhs = faer::MatMut::from_column_major_slice_mut(b, n, 1);
        match self.factor.as_ref().expect("factored") {
            Factor::Llt(l) => self.solve_llt(l, rhs),
            // Symmetric: Kᵀ = K.
            Factor::Lblt(f) => self.solve_lblt(f, rhs),
            Factor::Lu(f) => f.solve_transpose_in_place(rhs),
        }
    }

    /// The symbolic Cholesky factorization (computed on first use) in the fill-reducing
    /// order.
    fn symbolic_cholesky(&mut self) -> Result<(), String> {
        if self.symbolic_cholesky.is_none() {
            let (col_ptr, row_idx) = (self.symbolic.col_ptr(), self.symbolic.row_idx());
            let (forward, inverse) =
                crate::solvers::ordering::dof_order((col_ptr, row_idx), &self.free_rest);
            let order = faer::perm::PermRef::new_checked(&forward, &inverse, forward.len());
            self.symbolic_cholesky = Some(
                factorize_symbolic_cholesky(
                    self.symbolic.as_ref(),
                    Side::Lower,
                    SymmetricOrdering::Custom(order),
                    Default::default(),
                )
                .map_err(|e| format!("symbolic Cholesky factorization failed: {e:?}"))?,
            );
        }
        Ok(())
    }

    fn solve_llt(&self, l: &[f64], rhs: faer::MatMut<'_, f64>) {
        let symbolic = self
            .symbolic_cholesky
            .as_ref()
            .expect("factored by Cholesky");
        let mut buffer = MemBuffer::new(symbolic.solve_in_place_scratch::<f64>(1, faer::Par::Seq));
        LltRef::new(symbolic, l).solve_in_place_with_conj(
            faer::Conj::No,
            rhs,
            faer::Par::Seq,
            MemStack::new(&mut buffer),
        );
    }

    fn solve_lblt(&self, f: &Lblt, rhs: faer::MatMut<'_, f64>) {
        let symbolic = self.symbolic_cholesky.as_ref().expect("factored by LBLᵀ");
        let n = symbolic.nrows();
        let mut buffer = MemBuffer::new(symbolic.solve_in_place_scratch::<f64>(1, faer::Par::Seq));
        let stack = MemStack::new(&mut buffer);
        if f.forward.is_empty() {
            LdltRef::new(symbolic, &f.values).solve_in_place_with_conj(
                faer::Conj::No,
                rhs,
                faer::Par::Seq,
                stack,
            );
            return;
        }
        let perm = faer::perm::PermRef::new_checked(&f.forward, &f.inverse, n);
        IntranodeLbltRef::new(symbolic, &f.values, &f.subdiag, perm).solve_in_place_with_conj(
            faer::Conj::No,
            rhs,
            faer::Par::Seq,
            stack,
        );
    }
}

#[cfg(test)]
mod rigid_tests {
    use super::*;

    /// A symmetric, strictly diagonally dominant matrix on the pattern of a 12³-cell grid of
    /// 8-node cells (6,591 dofs, large enough for faer's supernodal factorization): its
    /// eigenvalues have the signs of its diagonal (shrinking the off-diagonal part to zero never
    /// makes it singular), so `negative` diagonal entries are its inertia.
    fn dominant(negative: &dyn Fn(usize) -> bool) -> (BlockPattern, Vec<f64>) {
        let n = 13;
        let node = |i: usize, j: usize, k: usize| (i + n * (j + n * k)) as u32;
        let mut cells = Vec::new();
        for k in 0..n - 1 {
            for j in 0..n - 1 {
                for i in 0..n - 1 {
                    for (a, b, c) in [(0, 0, 0), (1, 0, 0), (0, 1, 0), (1, 1, 0)] {
                        cells.push(node(i + a, j + b, k + c));
                    }
                    for (a, b, c) in [(0, 0, 1), (1, 0, 1), (0, 1, 1), (1, 1, 1)] {
                        cells.push(node(i + a, j + b, k + c));
                    }
                }
            }
        }
        let rest: Vec<[f64; 3]> = (0..n * n * n)
            .map(|p| [(p % n) as f64, ((p / n) % n) as f64, (p / (n * n)) as f64])
            .collect();
        let mut fixed = vec![false; rest.len()];
        fixed[0] = true;
        let pattern = BlockPattern::new(&fixed, (&cells, 8), (&[], 3), false, &rest).unwrap();
        let column_of = |k: usize| pattern.col_ptr.partition_point(|&p| p <= k) - 1;
        let values = (pattern.row_idx.iter().enumerate())
            .map(|(k, &row)| {
                let col = column_of(k);
                let (a, b) = (row.min(col) as f64, row.max(col) as f64);
                match row == col {
                    true if negative(row) => -100.0,
                    true => 100.0,
                    // At most 81 of them per row, each under 0.5 in size.
                    false => 0.45 * (0.7 * a + 1.3 * b).sin(),
                }
            })
            .collect();
        (pattern, values)
    }

    #[test]
    fn an_indefinite_symmetric_tangent_is_factored_by_lblt_with_its_inertia() {
        let negative = |row: usize| row % 97 == 5;
        let (pattern, values) = dominant(&negative);
        let want = (0..pattern.size()).filter(|&r| negative(r)).count();
        let mut solver = SparseSolver::new(&pattern, 1e-12).unwrap();
        assert!(matches!(
            solver.symbolic_lblt_raw_is_supernodal(&values),
            Some(true)
        ));
        for _ in 0..2 {
            // The second time straight by LBLᵀ (the last one was indefinite).
            assert_eq!(solver.factor(&values).unwrap(), "lblt");
            assert_eq!(solver.negative_eigenvalues(), Some(want));
            let x: Vec<f64> = (0..pattern.size()).map(|i| (i as f64).cos()).collect();
            let mut b = pattern.multiply(&values, &x);
            solver.solve_transpose(&mut b);
            let error = b
                .iter()
                .zip(&x)
                .fold(0.0f64, |m, (p, q)| m.max((p - q).abs()));
            assert!(error < 1e-12, "{error}");
        }
        // A definite one goes back to Cholesky.
        let (_, definite) = dominant(&|_| false);
        assert_eq!(solver.factor(&definite).unwrap(), "lblt");
        assert_eq!(solver.negative_eigenvalues(), Some(0));
        assert_eq!(solver.factor(&definite).unwrap(), "cholesky");
    }

    fn rest() -> Vec<[f64; 3]> {
        vec![
            [0.0, 0.0, 0.0],
            [2.0, 0.1, 0.0],
            [0.2, 1.5, 0.3],
            [0.1, 0.2, 1.0],
            [1.0, 1.0, 1.0],
        ]
    }

    #[test]
    fn multiply_is_the_product_with_the_matrix_the_values_fill() {
        let pattern = BlockPattern::new(
            &[false; 5],
            (&[0, 1, 2, 3, 1, 2, 3, 4], 4),
            (&[], 3),
            false,
            &rest(),
        )
        .unwrap();
        let values: Vec<f64> = (0..pattern.nnz())
            .map(|k| (k as f64 * 0.37).cos())
            .collect();
        let v: Vec<f64> = (0..15).map(|i| (i as f64 * 1.3).sin()).collect();
        // The dense matrix entry by entry from the CSC arrays.
        let mut dense = vec![vec![0.0; 15]; 15];
        for (col, bounds) in pattern.col_ptr.windows(2).enumerate() {
            for k in bounds[0]..bounds[1] {
                dense[pattern.row_idx[k]][col] += values[k];
            }
        }
        let product = pattern.multiply(&values, &v);
        for (row, p) in dense.iter().zip(&product) {
            assert!((dot(row, &v) - p).abs() < 1e-12);
        }
    }

    #[test]
    fn align_to_undoes_a_rigid_motion() {
        let rest = rest();
        let (c, s) = (0.3f64.cos(), 0.3f64.sin());
        // A rotation about z and a translation.
        let moved: Vec<f64> = rest
            .iter()
            .flat_map(|p| {
                [
                    c * p[0] - s * p[1] + 5.0,
                    s * p[0] + c * p[1] - 2.0,
                    p[2] + 1.0,
                ]
            })
            .collect();
        let back = align_to(&rest, &moved);
        for (a, b) in back.chunks(3).zip(&rest) {
            for d in 0..3 {
                assert!((a[d] - b[d]).abs() < 1e-12, "{a:?} vs {b:?}");
            }
        }
    }

    #[test]
    fn fixed_nodes_at_a_point_or_on_a_line_leave_rotations_that_their_support_holds() {
        let rest = rest();
        let mut fixed = [false; 5];
        fixed[0] = true;
        let point = FreeMotion::of(&fixed, &rest).unwrap();
        assert!(matches!(point, FreeMotion::AboutPoint { node: 0, .. }));
        fixed[3] = true;
        let line = FreeMotion::of(&fixed, &rest).unwrap();
        assert!(matches!(line, FreeMotion::AboutLine { ends: (0, 3), .. }));
        fixed[1] = true;
        assert_eq!(FreeMotion::of(&fixed, &rest), None);
        assert_eq!(FreeMotion::of(&[false; 5], &rest), Some(FreeMotion::Rigid));
        let flat: Vec<f64> = rest.iter().flatten().copied().collect();
        for (motion, count) in [(point, 3), (line, 1), (FreeMotion::Rigid, 6)] {
            let pins = motion.support(&rest).unwrap();
            assert_eq!(pins.len(), count);
            // The pinned dofs see every free motion: the modes restricted to them are
            // independent (a nonsingular square matrix).
            let modes = motion.modes(&flat);
            let mut m: Vec<Vec<f64>> = pins
                .iter()
                .map(|&p| modes.iter().map(|mode| mode[p]).collect())
                .collect();
            let mut b = vec![1.0; count];
            assert!(
                crate::solvers::dense::solve(&mut m, &mut b).is_some(),
                "{motion:?}"
            );
        }
    }

    #[test]
    fn the_pose_about_a_point_or_a_line_undoes_a_rotation_about_it() {
        let rest = rest();
        let (c, s) = (0.4f64.cos(), 0.4f64.sin());
        // A rotation about the z axis through node 0 (the origin).
        let turned: Vec<f64> = rest
            .iter()
            .flat_map(|p| [c * p[0] - s * p[1], s * p[0] + c * p[1], p[2]])
            .collect();
        let back_line = turn_about_axis(&rest, &turned, [0.0; 3], [0.0, 0.0, 1.0]);
        let back_point = rotate_about(&rest, &turned, [0.0; 3]);
        for back in [back_line, back_point] {
            for (a, b) in back.chunks(3).zip(&rest) {
                for d in 0..3 {
                    assert!((a[d] - b[d]).abs() < 1e-12, "{a:?} vs {b:?}");
                }
            }
        }
    }

    #[test]
    fn the_support_pins_six_distinct_dofs_of_three_nodes() {
        let pins = three_two_one(&rest()).unwrap();
        let mut sorted = pins.clone();
        sorted.sort();
        sorted.dedup();
        assert_eq!(sorted.len(), 6);
        let nodes: std::collections::BTreeSet<_> = pins.iter().map(|p| p / 3).collect();
        assert_eq!(nodes.len(), 3);
        // Nodes on one line have no determinate support.
        let line: Vec<[f64; 3]> = (0..4).map(|i| [i as f64, 0.0, 0.0]).collect();
        assert!(three_two_one(&line).is_err());
    }

    #[test]
    fn the_pose_free_sensitivity_has_no_part_along_the_rigid_modes_at_the_state() {
        let rest = rest();
        let pattern = BlockPattern::new(
            &[false; 5],
            (&[0, 1, 2, 3, 1, 2, 3, 4], 4),
            (&[], 3),
            true,
            &rest,
        )
        .unwrap();
        let x: Vec<f64> = rest
            .iter()
            .flat_map(|p| [p[0] * 1.01, p[1], p[2] + 0.02 * p[0]])
            .collect();
        let mut g: Vec<f64> = (0..15).map(|i| (i as f64 * 0.7).sin()).collect();
        pattern.pose_free_sensitivity(&rest, &x, &mut g);
        for mode in rigid_modes(&x) {
            assert!(dot(&mode, &g).abs() < 1e-12, "{}", dot(&mode, &g));
        }
    }
}
