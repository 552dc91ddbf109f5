//! A fill-reducing ordering of the tangent for its sparse factorization: nested dissection of
//! the mesh's node graph by coordinate bisection, with the leaves ordered by approximate
//! minimum degree.
//!
//! Approximate minimum degree alone (faer's default) is a local, greedy choice; nested
//! dissection (George, 1973), what PARDISO and MUMPS use through METIS, bounds a 3-D mesh's
//! fill by n^(4/3) by numbering separators last. A mesh carries its own geometry, so the
//! separators come from planes: each of the three axes is cut at a few places near the median
//! of the part's nodes, the cut meeting the fewest edges wins, its separator is the smaller of
//! the two rows of nodes along it, and both halves are dissected in turn before the separator
//! is numbered. Measured on the verification cuboid (Cholesky, one core): at 45.7k dofs
//! 26M nonzeros in L against AMD's 27M (a factorization 1.4× faster); at 146k dofs 132M
//! against 213M (12 s against 30 s, 3.0 GB peak against 4.3 GB); on the 15.6k-dof hollow
//! sphere the same as AMD. Everything is deterministic (ties broken by index): the ordering,
//! and with it the factorization's round-off, depends only on the mesh.

use faer::dyn_stack::{MemBuffer, MemStack};
use faer::sparse::SymbolicSparseColMatRef;
use faer::sparse::linalg::amd;

/// Parts with at most this many nodes are not dissected further but ordered by approximate
/// minimum degree (whose fill inside a part this small is close to optimal).
const LEAF_NODES: usize = 96;

/// Where along each axis a cut is tried (the fraction of the part's nodes below it): the
/// smallest separator among them wins. Off-median cuts that meet fewer edges (a thinner
/// cross-section) saved 2–6 % of the factor's nonzeros on the cuboid and the sphere.
const SPLIT_FRACTIONS: [f64; 5] = [0.4, 0.45, 0.5, 0.55, 0.6];

/// The order in which to eliminate the nodes of a graph (`adjacency[i]`: node i's
/// neighbours, itself allowed) whose nodes sit at `coords`: `order[k]` is the node eliminated
/// k-th.
pub fn nested_dissection(adjacency: &[Vec<u32>], coords: &[[f64; 3]]) -> Vec<u32> {
    let n = adjacency.len();
    let mut d = Dissection {
        adjacency,
        coords,
        side: vec![0; n],
        order: Vec::with_capacity(n),
    };
    d.dissect((0..n as u32).collect());
    debug_assert_eq!(d.order.len(), n);
    d.order
}

/// A fill-reducing elimination order of a tangent's dofs, three per node in node order, from
/// its sparsity pattern (CSC, rows of each node's three columns alike) and the nodes' positions:
/// the nodes' [`nested_dissection`], each node's three dofs together; and its inverse.
pub fn dof_order(
    (col_ptr, row_idx): (&[usize], &[usize]),
    coords: &[[f64; 3]],
) -> (Vec<usize>, Vec<usize>) {
    let adjacency: Vec<Vec<u32>> = (0..coords.len())
        .map(|k| {
            let rows = &row_idx[col_ptr[3 * k]..col_ptr[3 * k + 1]];
            rows.iter().step_by(3).map(|&r| (r / 3) as u32).collect()
        })
        .collect();
    let nodes = nested_dissection(&adjacency, coords);
    let forward: Vec<usize> = nodes
        .iter()
        .flat_map(|&k| (0..3).map(move |d| 3 * k as usize + d))
        .collect();
    let mut inverse = vec![0; forward.len()];
    for (new, &old) in forward.iter().enumerate() {
        inverse[old] = new;
    }
    (forward, inverse)
}

struct Dissection<'a> {
    adjacency: &'a [Vec<u32>],
    coords: &'a [[f64; 3]],
    /// Scratch: 1 or 2 for the nodes of the part being split (its two sides), else 0.
    side: Vec<u8>,
    order: Vec<u32>,
}

impl Dissection<'_> {
    fn dissect(&mut self, mut part: Vec<u32>) {
        if part.len() <= LEAF_NODES {
            self.minimum_degree(&part);
            return;
        }
        // (separator, one side, the other side)
        let mut best: Option<[Vec<u32>; 3]> = None;
        for axis in 0..3 {
            let coords = self.coords;
            let key = |&i: &u32| (coords[i as usize][axis], i);
            part.sort_unstable_by(|a, b| key(a).partial_cmp(&key(b)).expect("finite coordinates"));
            for f in SPLIT_FRACTIONS {
                let half = (part.len() as f64 * f) as usize;
                let (low, high) = part.split_at(half);
                let cut = self.separate(low, high);
                if best
                    .as_ref()
                    .is_none_or(|best| cut[0].len() < best[0].len())
                {
                    best = Some(cut);
                }
            }
        }
        let [separator, a, b] = best.expect("three axes tried");
        // A separator as large as its part would not dissect it (a clique-like part).
        if a.is_empty() || b.is_empty() {
            let mut all = a;
            all.extend(b);
            all.extend(separator);
            self.minimum_degree(&all);
            return;
        }
        self.dissect(a);
        self.dissect(b);
        self.order.extend(separator);
    }

    /// The vertex separator along the cut between `low` and `high`: the nodes of one side
    /// with a neighbour on the other (the smaller set); and the two sides without it.
    fn separate(&mut self, low: &[u32], high: &[u32]) -> [Vec<u32>; 3] {
        for &i in low {
            self.side[i as usize] = 1;
        }
        for &i in high {
            self.side[i as usize] = 2;
        }
        let touching = |nodes: &[u32], other: u8| -> Vec<bool> {
            nodes
                .iter()
                .map(|&i| {
                    self.adjacency[i as usize]
                        .iter()
                        .any(|&j| self.side[j as usize] == other)
                })
                .collect()
        };
        let low_cut = touching(low, 2);
        let high_cut = touching(high, 1);
        for &i in low.iter().chain(high) {
            self.side[i as usize] = 0;
        }
        let count = |cut: &[bool]| cut.iter().filter(|&&c| c).count();
        let split = |nodes: &[u32], cut: &[bool]| -> (Vec<u32>, Vec<u32>) {
            let (sep, rest): (Vec<_>, Vec<_>) = nodes.iter().zip(cut).partition(|(_, c)| **c);
            (
                sep.into_iter().map(|(&i, _)| i).collect(),
                rest.into_iter().map(|(&i, _)| i).collect(),
            )
        };
        if count(&low_cut) <= count(&high_cut) {
            let (sep, a) = split(low, &low_cut);
            [sep, a, high.to_vec()]
        } else {
            let (sep, b) = split(high, &high_cut);
            [sep, low.to_vec(), b]
        }
    }

    /// Append the nodes of a small part in approximate-minimum-degree order of the graph they
    /// induce (faer's AMD); in their given order should it fail.
    fn minimum_degree(&mut self, part: &[u32]) {
        if part.len() <= 2 {
            self.order.extend_from_slice(part);
            return;
        }
        let ordered = self.amd_order(part);
        self.order.extend(ordered);
    }

    fn amd_order(&self, part: &[u32]) -> Vec<u32> {
        let m = part.len();
        // Local indices by binary search in a sorted copy: no scratch the size of the graph.
        let mut sorted: Vec<(u32, u32)> = part
            .iter()
            .enumerate()
            .map(|(k, &i)| (i, k as u32))
            .collect();
        sorted.sort_unstable();
        let local = |i: u32| {
            sorted
                .binary_search_by_key(&i, |&(g, _)| g)
                .ok()
                .map(|p| sorted[p].1)
        };
        let mut col_ptr = Vec::with_capacity(m + 1);
        let mut row_idx = Vec::new();
        col_ptr.push(0usize);
        for &i in part {
            let mut rows: Vec<usize> = self.adjacency[i as usize]
                .iter()
                .filter_map(|&j| local(j))
                .map(|k| k as usize)
                .collect();
            rows.sort_unstable();
            rows.dedup();
            row_idx.extend(rows);
            col_ptr.push(row_idx.len());
        }
        let pattern = SymbolicSparseColMatRef::new_checked(m, m, &col_ptr, None, &row_idx);
        let mut perm = vec![0usize; m];
        let mut perm_inv = vec![0usize; m];
        let ordered = MemBuffer::try_new(amd::order_scratch::<usize>(m, row_idx.len()))
            .ok()
            .and_then(|mut buffer| {
                amd::order(
                    &mut perm,
                    &mut perm_inv,
                    pattern,
                    amd::Control::default(),
                    MemStack::new(&mut buffer),
                )
                .ok()
            });
        match ordered {
            Some(_) => perm.iter().map(|&k| part[k]).collect(),
            None => part.to_vec(),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The nodes of an n×n×n grid with their 27-point neighbourhoods (a hexahedral mesh's
    /// node graph).
    fn grid(n: usize) -> (Vec<Vec<u32>>, Vec<[f64; 3]>) {
        let id = |x: usize, y: usize, z: usize| (x + n * (y + n * z)) as u32;
        let mut adjacency = Vec::new();
        let mut coords = Vec::new();
        for z in 0..n {
            for y in 0..n {
                for x in 0..n {
                    let mut nbrs = Vec::new();
                    for (dx, dy, dz) in (0..27).map(|k| (k % 3, (k / 3) % 3, k / 9)) {
                        let (a, b, c) = (x + dx, y + dy, z + dz);
                        if (1..=n).contains(&a) && (1..=n).contains(&b) && (1..=n).contains(&c) {
                            nbrs.push(id(a - 1, b - 1, c - 1));
                        }
                    }
                    adjacency.push(nbrs);
                    coords.push([x as f64, y as f64, z as f64]);
                }
            }
        }
        (adjacency, coords)
    }

    #[test]
    fn the_order_is_a_permutation_with_the_top_separator_last() {
        let (adjacency, coords) = grid(12);
        let order = nested_dissection(&adjacency, &coords);
        let mut seen = vec![false; order.len()];
        for &i in &order {
            assert!(!seen[i as usize], "node {i} ordered twice");
            seen[i as usize] = true;
        }
        assert!(seen.iter().all(|&s| s));
        // The last nodes are a plane of the grid (12 × 12 nodes): the first separator.
        let last = &order[order.len() - 144..];
        let planes: Vec<_> = (0..3)
            .map(|axis| {
                let mut values: Vec<i64> = last
                    .iter()
                    .map(|&i| coords[i as usize][axis] as i64)
                    .collect();
                values.sort_unstable();
                values.dedup();
                values.len()
            })
            .collect();
        assert!(
            planes.contains(&1),
            "the last 144 nodes are not one plane: {planes:?}"
        );
    }

    /// The factor's nonzeros under an ordering of the grid's scalar matrix.
    fn factor_nonzeros(adjacency: &[Vec<u32>], ordering: Option<&[u32]>) -> usize {
        use faer::Side;
        use faer::sparse::linalg::cholesky::{SymmetricOrdering, factorize_symbolic_cholesky};
        let n = adjacency.len();
        let mut col_ptr = vec![0usize];
        let mut row_idx = Vec::new();
        for nbrs in adjacency {
            let mut rows: Vec<usize> = nbrs.iter().map(|&j| j as usize).collect();
            rows.sort_unstable();
            row_idx.extend(rows);
            col_ptr.push(row_idx.len());
        }
        let pattern = SymbolicSparseColMatRef::new_checked(n, n, &col_ptr, None, &row_idx);
        let forward: Vec<usize> = ordering
            .unwrap_or(&[])
            .iter()
            .map(|&i| i as usize)
            .collect();
        let mut inverse = vec![0; forward.len()];
        for (k, &i) in forward.iter().enumerate() {
            inverse[i] = k;
        }
        let ordering = match ordering {
            Some(_) => {
                SymmetricOrdering::Custom(faer::perm::PermRef::new_checked(&forward, &inverse, n))
            }
            None => SymmetricOrdering::Amd,
        };
        factorize_symbolic_cholesky(pattern, Side::Lower, ordering, Default::default())
            .expect("symbolic factorization")
            .len_val()
    }

    #[test]
    fn nested_dissection_fills_a_3d_grid_less_than_minimum_degree() {
        let (adjacency, coords) = grid(24);
        let order = nested_dissection(&adjacency, &coords);
        let dissected = factor_nonzeros(&adjacency, Some(&order));
        let minimum_degree = factor_nonzeros(&adjacency, None);
        assert!(
            (dissected as f64) < 0.9 * minimum_degree as f64,
            "nested dissection {dissected} nonzeros, AMD {minimum_degree}"
        );
    }
}
