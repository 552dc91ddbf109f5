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

use faer::Side;
use faer::linalg::solvers::Solve;
use faer::sparse::linalg::solvers::{Llt, Lu, SymbolicLlt, SymbolicLu};
use faer::sparse::{SparseColMatRef, SymbolicSparseColMat};

/// Marks an entry of a fixed node (not in the matrix).
const NONE: u32 = u32::MAX;

/// The sparsity pattern of the assembled tangent over the free degrees of freedom.
pub struct BlockPattern {
    /// Free degrees of freedom (3 per free node).
    pub n: usize,
    /// A body without fixed nodes: 6 Lagrange multipliers hold its mean translation and
    /// rotation (the matrix is n + 6 square, symmetric indefinite).
    pub rigid: bool,
    /// Per free dof, its node and component.
    free: Vec<(u32, u8)>,
    /// Per free dof j, the position of entry (n, j): the constraint rows n..n+6 follow it.
    con_row: Vec<u32>,
    /// The position of entry (0, n): the constraint columns, n entries each.
    con_col: usize,
    /// Per free dof, the position of its diagonal entry.
    diag: Vec<u32>,
    /// `node·3 + d` → free dof index, or [`NONE`] for a fixed node.
    dof: Vec<u32>,
    col_ptr: Vec<usize>,
    row_idx: Vec<usize>,
    /// Per element, the value index of its Jacobian's entry `i·12 + j` ([`NONE`]: fixed).
    elem_pos: Vec<u32>,
    /// Per chamber triangle, the value index of entry `i·9 + j`.
    tri_pos: Vec<u32>,
    /// Per node, the value index of entry `i·3 + j` of its diagonal block.
    node_pos: Vec<u32>,
}

impl BlockPattern {
    /// `hold_rigid_modes`: a static solve, where a body with no fixed node gets the 6
    /// constraints (an implicit step's inertia already makes its matrix regular).
    pub fn new(
        fixed: &[bool],
        tets: &[[u32; 4]],
        tris: &[[u32; 3]],
        hold_rigid_modes: bool,
    ) -> Result<Self, String> {
        let n_nodes = fixed.len();
        let rigid = hold_rigid_modes && fixed.iter().all(|f| !f);
        let extra = if rigid { 6 } else { 0 };
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
        tets.iter().for_each(|t| link(t));
        tris.iter().for_each(|t| link(t));
        for l in &mut nbrs {
            l.sort_unstable();
            l.dedup();
        }
        // Column (b, db) holds rows (a, da) for a in nbrs(b), da in 0..3.
        let mut col_ptr = Vec::with_capacity(n as usize + 1);
        let mut row_idx = Vec::new();
        let mut col_start = vec![0usize; n_nodes];
        let mut free = Vec::new();
        let mut con_row = Vec::new();
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
                con_row.push(row_idx.len() as u32);
                row_idx.extend((0..extra).map(|c| n as usize + c));
                col_ptr.push(row_idx.len());
            }
        }
        let con_col = row_idx.len();
        for _ in 0..extra {
            row_idx.extend(0..n as usize);
            col_ptr.push(row_idx.len());
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
            (col_start[b as usize] + db * (3 * list.len() + extra) + 3 * k + da) as u32
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
        let elem_pos = tets.iter().flat_map(|t| positions(t)).collect();
        let tri_pos = tris.iter().flat_map(|t| positions(t)).collect();
        let node_pos = (0..n_nodes as u32).flat_map(|n| positions(&[n])).collect();
        let diag = free
            .iter()
            .map(|&(b, d)| position(b, d as usize, b, d as usize))
            .collect();
        Ok(BlockPattern {
            n: n as usize,
            rigid,
            free,
            con_row,
            con_col,
            diag,
            dof,
            col_ptr,
            row_idx,
            elem_pos,
            tri_pos,
            node_pos,
        })
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

    /// The matrix's order: the free dofs, and the multipliers of a free body.
    pub fn size(&self) -> usize {
        self.n + if self.rigid { 6 } else { 0 }
    }

    /// Free-dof entries of a node-major vector (3 per node), zeros for the multipliers.
    pub fn restrict(&self, full: &[f64]) -> Vec<f64> {
        let mut out = vec![0.0; self.size()];
        for (i, &d) in self.dof.iter().enumerate() {
            if d != NONE {
                out[d as usize] = full[i];
            }
        }
        out
    }

    /// A node-major vector (3 per node, 0 at fixed nodes) from free-dof entries.
    pub fn extend(&self, free: &[f64]) -> Vec<f64> {
        self.dof
            .iter()
            .map(|&d| if d == NONE { 0.0 } else { free[d as usize] })
            .collect()
    }

    /// The stiffness K = −∂residual/∂x from the element Jacobians (element × 144, ∂f/∂x), the
    /// chamber triangles' (triangle × 81) and the nodes' own (node × 9: an implicit step's
    /// inertia; empty for a static solve), summed entity by entity in kernel order.
    ///
    /// A free body's constraint rows hold Σ Δx_i = 0 and Σ (x_i − x̄) × Δx_i = 0 at the
    /// positions `x`: no mean translation or rotation in a Newton step. They are scaled to the
    /// stiffness's diagonal so the factorization stays well conditioned; their right-hand side
    /// is 0, so the scale does not change the solution.
    pub fn assemble(
        &self,
        elem_jac: &[f64],
        tri_jac: &[f64],
        node_jac: &[f64],
        x: &[f64],
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
        if self.rigid {
            self.fill_constraints(x, values);
        }
    }
}

impl BlockPattern {
    fn fill_constraints(&self, x: &[f64], values: &mut [f64]) {
        let m = self.free.len().max(1) as f64;
        let scale = self
            .diag
            .iter()
            .map(|&p| values[p as usize].abs())
            .sum::<f64>()
            / m;
        let mut centre = [0.0; 3];
        for &(node, d) in self.free.iter() {
            centre[d as usize] += x[3 * node as usize + d as usize] / (m / 3.0);
        }
        let size = self
            .free
            .iter()
            .map(|&(node, d)| (x[3 * node as usize + d as usize] - centre[d as usize]).abs())
            .fold(0.0f64, f64::max)
            .max(f64::MIN_POSITIVE);
        for (j, &(node, d)) in self.free.iter().enumerate() {
            let r = |c: usize| (x[3 * node as usize + c] - centre[c]) / size;
            let d = d as usize;
            // Row c < 3: translation along c. Row 3 + c: (e_c × r)·Δx, the rotation about c.
            let mut row = [0.0; 6];
            row[d] = 1.0;
            let (r0, r1, r2) = (r(0), r(1), r(2));
            let rot = [[0.0, -r2, r1], [r2, 0.0, -r0], [-r1, r0, 0.0]];
            for c in 0..3 {
                row[3 + c] = rot[c][d];
            }
            for (c, v) in row.iter().enumerate() {
                values[self.con_row[j] as usize + c] = scale * v;
                values[self.con_col + c * self.n + j] = scale * v;
            }
        }
    }
}

/// The factorization of the assembled tangent: Cholesky (LLᵀ) when it is symmetric positive
/// definite — a stable equilibrium of a conservative load, the common case, several times
/// faster than LU — else LU with partial pivoting (an open pressurised surface, an unstable
/// state). Symbolic parts are computed once and reused.
pub struct SparseSolver {
    symbolic: SymbolicSparseColMat<usize>,
    /// The position of each entry's transpose (the pattern is structurally symmetric).
    transpose: Vec<usize>,
    /// Relative tolerance of the symmetry test (the entries' round-off).
    symmetry: f64,
    symbolic_llt: Option<SymbolicLlt<usize>>,
    symbolic_lu: Option<SymbolicLu<usize>>,
    factor: Option<Factor>,
    /// Whether the matrix can be positive definite (not with a free body's multipliers).
    may_be_definite: bool,
}

enum Factor {
    Llt(Llt<usize, f64>),
    Lu(Box<Lu<usize, f64>>),
}

impl SparseSolver {
    pub fn new(p: &BlockPattern, symmetry: f64) -> Result<Self, String> {
        let symbolic = SymbolicSparseColMat::new_checked(
            p.size(),
            p.size(),
            p.col_ptr.clone(),
            None,
            p.row_idx.clone(),
        );
        // Entry k is (row_idx[k], column j); its transpose is (j, row_idx[k]).
        let mut transpose = vec![0usize; p.row_idx.len()];
        for j in 0..p.n {
            for (k, &i) in p
                .row_idx
                .iter()
                .enumerate()
                .take(p.col_ptr[j + 1])
                .skip(p.col_ptr[j])
            {
                let col = &p.row_idx[p.col_ptr[i]..p.col_ptr[i + 1]];
                let at = col
                    .binary_search(&j)
                    .map_err(|_| "the tangent's pattern is not symmetric".to_string())?;
                transpose[k] = p.col_ptr[i] + at;
            }
        }
        Ok(SparseSolver {
            symbolic,
            transpose,
            symmetry,
            symbolic_llt: None,
            symbolic_lu: None,
            factor: None,
            may_be_definite: !p.rigid,
        })
    }

    /// Whether the values form a symmetric matrix (to round-off).
    fn symmetric(&self, values: &[f64]) -> bool {
        let scale = values.iter().fold(0.0f64, |m, v| m.max(v.abs()));
        let tol = self.symmetry * scale;
        values
            .iter()
            .zip(&self.transpose)
            .all(|(v, &t)| (v - values[t]).abs() <= tol)
    }

    /// Factor the matrix with these values (the pattern's order). Returns which
    /// factorization was used (`"cholesky"` or `"lu"`).
    pub fn factor(&mut self, values: &[f64]) -> Result<&'static str, String> {
        let mat = SparseColMatRef::new(self.symbolic.as_ref(), values);
        if self.may_be_definite && self.symmetric(values) {
            if self.symbolic_llt.is_none() {
                self.symbolic_llt = Some(
                    SymbolicLlt::try_new(self.symbolic.as_ref(), Side::Lower)
                        .map_err(|e| format!("symbolic Cholesky factorization failed: {e:?}"))?,
                );
            }
            let symbolic = self.symbolic_llt.clone().expect("computed");
            if let Ok(llt) = Llt::try_new_with_symbolic(symbolic, mat, Side::Lower) {
                self.factor = Some(Factor::Llt(llt));
                return Ok("cholesky");
            }
        }
        if self.symbolic_lu.is_none() {
            self.symbolic_lu = Some(
                SymbolicLu::try_new(self.symbolic.as_ref())
                    .map_err(|e| format!("symbolic LU factorization failed: {e:?}"))?,
            );
        }
        let symbolic = self.symbolic_lu.clone().expect("computed");
        let lu = Lu::try_new_with_symbolic(symbolic, mat).map_err(|e| format!("{e:?}"))?;
        self.factor = Some(Factor::Lu(Box::new(lu)));
        Ok("lu")
    }

    /// Solve K·y = b in place.
    pub fn solve(&self, b: &mut [f64]) {
        let n = b.len();
        let rhs = faer::MatMut::from_column_major_slice_mut(b, n, 1);
        match self.factor.as_ref().expect("factored") {
            Factor::Llt(f) => f.solve_in_place(rhs),
            Factor::Lu(f) => f.solve_in_place(rhs),
        }
    }

    /// Solve Kᵀ·y = b in place.
    pub fn solve_transpose(&self, b: &mut [f64]) {
        let n = b.len();
        let rhs = faer::MatMut::from_column_major_slice_mut(b, n, 1);
        match self.factor.as_ref().expect("factored") {
            Factor::Llt(f) => f.solve_in_place(rhs),
            Factor::Lu(f) => f.solve_transpose_in_place(rhs),
        }
    }
}
