//! Backends: code generated from the kernel IR ([`crate::ir`]).
//!
//! - [`cranelift`]: native CPU code through the Cranelift JIT, f64 or f32, bit-identical to
//!   the IR interpreter in f64, run on any number of threads with identical results.
//! - [`wgsl`]: WGSL compute shaders for wgpu (any GPU, or lavapipe), f32 or f64.
//!
//! What both share lives here: the [`Precision`] and the mesh connectivity as the generated code
//! reads it, [`Topology`].

pub mod cranelift;
pub mod wgsl;

use crate::ir::{Domain, ElementOrder};

/// The floating-point type of every value and buffer of a compiled module.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum Precision {
    F32,
    F64,
}

impl Precision {
    /// Bytes per value.
    pub fn size(self) -> usize {
        match self {
            Precision::F32 => 4,
            Precision::F64 => 8,
        }
    }
}

impl std::fmt::Display for Precision {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            Precision::F32 => "f32",
            Precision::F64 => "f64",
        })
    }
}

/// Mesh connectivity as the generated code reads it, validated on construction.
#[derive(Clone, Debug, PartialEq)]
pub struct Topology {
    order: ElementOrder,
    n_nodes: usize,
    elem_conn: Vec<u32>,
    tri_conn: Vec<u32>,
    node_elem_offsets: Vec<u32>,
    node_elem_entries: Vec<u32>,
    node_tri_offsets: Vec<u32>,
    node_tri_entries: Vec<u32>,
    /// Each entry of `node_elem_entries` as one index `element · nc + corner` (nc = 4, or 10
    /// for quadratic tets): the row of a per-corner buffer (element × nc·stride) the incidence reads, one load for the CPU's
    /// gather loops instead of two and a multiply.
    node_elem_slots: Vec<u32>,
    /// Likewise `triangle · nc + corner` for `node_tri_entries` (nc = 3 or 6).
    node_tri_slots: Vec<u32>,
}

/// `(entity, corner)` pairs as `entity · nc + corner` (below `u32::MAX`: the connectivity's
/// length is, see `check_conn`).
fn slots(entries: &[u32], nc: u32) -> Vec<u32> {
    entries.chunks_exact(2).map(|p| p[0] * nc + p[1]).collect()
}

/// Node → entity incidences in CSR form, softc's one connectivity list: the incidences of node
/// `n` are `entries[offsets[n]..offsets[n + 1]]`, each `(entity, corner)`, in increasing entity
/// then corner order, the order every gather sums in (deterministic, no atomics). The runtime
/// keeps one per scene for elements and one for chamber triangles; [`Topology`] lays them out
/// for the generated code.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct NodeCsr {
    pub offsets: Vec<u32>,
    pub entries: Vec<(u32, u8)>,
}

impl NodeCsr {
    /// The incidences of `n_nodes` nodes in `entities` (each its nodes in corner order).
    ///
    /// # Panics
    /// If a node index is `n_nodes` or more.
    pub fn build(n_nodes: usize, entities: impl IntoIterator<Item = impl AsRef<[u32]>>) -> Self {
        let entities: Vec<_> = entities.into_iter().collect();
        let mut counts = vec![0u32; n_nodes + 1];
        for e in &entities {
            for &n in e.as_ref() {
                counts[n as usize + 1] += 1;
            }
        }
        for i in 0..n_nodes {
            counts[i + 1] += counts[i];
        }
        let offsets = counts.clone();
        let mut fill = counts;
        let mut entries = vec![(0u32, 0u8); offsets[n_nodes] as usize];
        // Entities in increasing order, corners in increasing order: each node's list ends up
        // sorted by (entity, corner) without a sort.
        for (e, nodes) in entities.iter().enumerate() {
            for (c, &n) in nodes.as_ref().iter().enumerate() {
                let slot = &mut fill[n as usize];
                entries[*slot as usize] = (e as u32, c as u8);
                *slot += 1;
            }
        }
        NodeCsr { offsets, entries }
    }

    /// The `(entity, corner)` incidences of node `node`.
    pub fn of(&self, node: usize) -> &[(u32, u8)] {
        &self.entries[self.offsets[node] as usize..self.offsets[node + 1] as usize]
    }

    /// The incidences as flat `entity, corner` pairs, the layout generated code reads.
    pub fn flat_entries(&self) -> Vec<u32> {
        self.entries
            .iter()
            .flat_map(|&(e, c)| [e, u32::from(c)])
            .collect()
    }

    /// Each incidence as one index `entity · nc + corner` for entities of `nc` nodes: the row
    /// of a per-corner buffer it reads, the layout of the GPU's gathers and the CPU's
    /// ([`Topology::node_elem_slots`]).
    pub fn slots(&self, nc: u32) -> Vec<u32> {
        self.entries
            .iter()
            .map(|&(e, c)| e * nc + u32::from(c))
            .collect()
    }
}

/// The node→entity CSR of a connectivity with `nc` nodes per entity, flattened
/// ([`NodeCsr::flat_entries`]).
///
/// # Panics
/// If an index of `conn` is `n_nodes` or more ([`Topology::new`] checks that first).
pub fn node_csr(n_nodes: usize, conn: &[u32], nc: usize) -> (Vec<u32>, Vec<u32>) {
    let csr = NodeCsr::build(n_nodes, conn.chunks(nc));
    let entries = csr.flat_entries();
    (csr.offsets, entries)
}

impl Topology {
    /// Connectivity of `n_nodes` nodes, linear tets (`elem_conn`, 4 per element) and chamber
    /// triangles (`tri_conn`, 3 per triangle); builds both node CSR lists.
    pub fn new(n_nodes: usize, elem_conn: Vec<u32>, tri_conn: Vec<u32>) -> Result<Self, String> {
        Topology::of_order(ElementOrder::Linear, n_nodes, elem_conn, tri_conn)
    }

    /// As [`Topology::new`] for elements of `order` (quadratic: 10 nodes per element, 6 per
    /// triangle).
    pub fn of_order(
        order: ElementOrder,
        n_nodes: usize,
        elem_conn: Vec<u32>,
        tri_conn: Vec<u32>,
    ) -> Result<Self, String> {
        let (ne, nt) = (
            order.element_nodes() as usize,
            order.triangle_nodes() as usize,
        );
        check_conn(n_nodes, &elem_conn, ne, "element")?;
        check_conn(n_nodes, &tri_conn, nt, "triangle")?;
        let (node_elem_offsets, node_elem_entries) = node_csr(n_nodes, &elem_conn, ne);
        let (node_tri_offsets, node_tri_entries) = node_csr(n_nodes, &tri_conn, nt);
        Ok(Topology {
            order,
            n_nodes,
            elem_conn,
            tri_conn,
            node_elem_slots: slots(&node_elem_entries, ne as u32),
            node_tri_slots: slots(&node_tri_entries, nt as u32),
            node_elem_offsets,
            node_elem_entries,
            node_tri_offsets,
            node_tri_entries,
        })
    }

    /// Connectivity with CSR lists given by the caller (any order of incidences per node;
    /// gathers sum in that order). Each entry must name an incidence of its node.
    pub fn with_csr(
        order: ElementOrder,
        n_nodes: usize,
        elem_conn: Vec<u32>,
        tri_conn: Vec<u32>,
        node_elem: (Vec<u32>, Vec<u32>),
        node_tri: (Vec<u32>, Vec<u32>),
    ) -> Result<Self, String> {
        let (ne, nt) = (
            order.element_nodes() as usize,
            order.triangle_nodes() as usize,
        );
        check_conn(n_nodes, &elem_conn, ne, "element")?;
        check_conn(n_nodes, &tri_conn, nt, "triangle")?;
        check_csr(
            n_nodes,
            &elem_conn,
            ne,
            &node_elem.0,
            &node_elem.1,
            "element",
        )?;
        check_csr(n_nodes, &tri_conn, nt, &node_tri.0, &node_tri.1, "triangle")?;
        Ok(Topology {
            order,
            n_nodes,
            elem_conn,
            tri_conn,
            node_elem_slots: slots(&node_elem.1, ne as u32),
            node_tri_slots: slots(&node_tri.1, nt as u32),
            node_elem_offsets: node_elem.0,
            node_elem_entries: node_elem.1,
            node_tri_offsets: node_tri.0,
            node_tri_entries: node_tri.1,
        })
    }

    /// How many entities a domain has.
    pub fn count(&self, d: Domain) -> usize {
        match d {
            Domain::Element => self.elem_conn.len() / self.order.element_nodes() as usize,
            Domain::Triangle => self.tri_conn.len() / self.order.triangle_nodes() as usize,
            Domain::Node => self.n_nodes,
            Domain::Single => 1,
        }
    }

    /// The elements' order (the corners per element and per triangle).
    pub fn order(&self) -> ElementOrder {
        self.order
    }

    pub fn elem_conn(&self) -> &[u32] {
        &self.elem_conn
    }

    pub fn tri_conn(&self) -> &[u32] {
        &self.tri_conn
    }

    /// The node→element CSR: `(offsets, entries)`, entries as `(element, corner)` pairs.
    pub fn node_elem(&self) -> (&[u32], &[u32]) {
        (&self.node_elem_offsets, &self.node_elem_entries)
    }

    /// The node→triangle CSR: `(offsets, entries)`, entries as `(triangle, corner)` pairs.
    pub fn node_tri(&self) -> (&[u32], &[u32]) {
        (&self.node_tri_offsets, &self.node_tri_entries)
    }

    /// The node→element entries as `element · nc + corner`.
    pub fn node_elem_slots(&self) -> &[u32] {
        &self.node_elem_slots
    }

    /// The node→triangle entries as `triangle · nc + corner`.
    pub fn node_tri_slots(&self) -> &[u32] {
        &self.node_tri_slots
    }
}

fn check_conn(n_nodes: usize, conn: &[u32], nc: usize, what: &str) -> Result<(), String> {
    if n_nodes >= u32::MAX as usize || conn.len() >= u32::MAX as usize {
        return Err("meshes are limited to 2^32 - 1 nodes and incidences".into());
    }
    if !conn.len().is_multiple_of(nc) {
        return Err(format!(
            "{what} connectivity has {} indices, not a multiple of {nc}",
            conn.len()
        ));
    }
    if let Some(p) = conn.iter().position(|&n| n as usize >= n_nodes) {
        return Err(format!(
            "{what} {} names node {} of {n_nodes}",
            p / nc,
            conn[p]
        ));
    }
    Ok(())
}

fn check_csr(
    n_nodes: usize,
    conn: &[u32],
    nc: usize,
    offsets: &[u32],
    entries: &[u32],
    what: &str,
) -> Result<(), String> {
    if offsets.len() != n_nodes + 1 || offsets[0] != 0 {
        return Err(format!(
            "node→{what} offsets: {} values starting at {:?}, expected {} starting at 0",
            offsets.len(),
            offsets.first(),
            n_nodes + 1
        ));
    }
    if offsets.windows(2).any(|w| w[0] > w[1]) {
        return Err(format!("node→{what} offsets decrease"));
    }
    if offsets[n_nodes] as usize * 2 != entries.len() {
        return Err(format!(
            "node→{what} offsets end at {} but there are {} entries",
            offsets[n_nodes],
            entries.len() / 2
        ));
    }
    for node in 0..n_nodes {
        for j in offsets[node] as usize..offsets[node + 1] as usize {
            let (e, c) = (entries[2 * j] as usize, entries[2 * j + 1] as usize);
            if c >= nc || e >= conn.len() / nc || conn[e * nc + c] as usize != node {
                return Err(format!(
                    "node→{what} entry {j} ({e}, {c}) is not an incidence of node {node}"
                ));
            }
        }
    }
    Ok(())
}
