//! Area weights of node sets for `area_mean(n in SET) …`: the mean of a nodal field over the
//! boundary surface a node set covers, (1/A)·∫ u dA with u interpolated by the elements' shape
//! functions. Node `a` weighs ∫ Nₐ dA over the boundary triangles whose nodes all lie in the
//! set: A/3 per corner of a linear triangle; on a flat 6-node triangle 0 per corner and A/3 per
//! mid-edge node (a plain node mean would weight them alike, which is wrong for quadratic
//! elements). Curved 6-node triangles are integrated by the degree-4 rule.

use super::bind::MeshView;
use crate::lower::quadratic::{TET_EDGES, triangle_rule, triangle_shape};
use std::collections::HashMap;

/// The boundary triangles of a mesh: 3 corners, then (quadratic) the mid-edge nodes of edges
/// 0-1, 1-2, 2-0; each a face of exactly one tet.
fn boundary_triangles(mesh: &dyn MeshView) -> Vec<Vec<u32>> {
    let (tets, mids) = (mesh.tets(), mesh.tet_mids());
    let mut faces: Vec<([u32; 3], usize, usize)> = Vec::with_capacity(4 * tets.len());
    for (e, t) in tets.iter().enumerate() {
        for opposite in 0..4 {
            let mut key: Vec<u32> = (0..4).filter(|&c| c != opposite).map(|c| t[c]).collect();
            key.sort_unstable();
            faces.push(([key[0], key[1], key[2]], e, opposite));
        }
    }
    faces.sort_unstable();
    let mut out = Vec::new();
    let mut i = 0;
    while i < faces.len() {
        let mut j = i + 1;
        while j < faces.len() && faces[j].0 == faces[i].0 {
            j += 1;
        }
        if j - i == 1 {
            let (_, e, opposite) = faces[i];
            let local: Vec<usize> = (0..4).filter(|&c| c != opposite).collect();
            let mut nodes: Vec<u32> = local.iter().map(|&c| tets[e][c]).collect();
            if let Some(m) = mids.get(e) {
                for k in 0..3 {
                    let (a, b) = (local[k], local[(k + 1) % 3]);
                    let edge = TET_EDGES
                        .iter()
                        .position(|&[p, q]| (p, q) == (a.min(b), a.max(b)))
                        .expect("a tet edge");
                    nodes.push(m[edge]);
                }
            }
            out.push(nodes);
        }
        i = j;
    }
    out
}

/// ∫ Nₐ dA of each node of a boundary triangle (3 or 6 nodes).
fn triangle_weights(x: &[[f64; 3]]) -> Vec<f64> {
    let cross_norm = |u: [f64; 3], v: [f64; 3]| {
        let c = [
            u[1] * v[2] - u[2] * v[1],
            u[2] * v[0] - u[0] * v[2],
            u[0] * v[1] - u[1] * v[0],
        ];
        (c[0] * c[0] + c[1] * c[1] + c[2] * c[2]).sqrt()
    };
    if x.len() == 3 {
        let d = |a: usize| [0, 1, 2].map(|k| x[a][k] - x[0][k]);
        return vec![cross_norm(d(1), d(2)) / 6.0; 3];
    }
    let mut w = vec![0.0; 6];
    for (l, weight) in triangle_rule() {
        let (n, g) = triangle_shape(l);
        let tangent = |c: usize| [0, 1, 2].map(|k| (0..6).map(|a| x[a][k] * g[a][c]).sum::<f64>());
        let da = cross_norm(tangent(0), tangent(1));
        for (wa, na) in w.iter_mut().zip(n) {
            *wa += weight * na * da;
        }
    }
    w
}

/// Per node set (in its node order), each node's area weight; all zeros for a set that covers
/// no whole boundary triangle.
pub(super) fn area_weights(
    mesh: &dyn MeshView,
    node_sets: &[(String, Vec<u32>)],
) -> HashMap<String, Vec<f64>> {
    let triangles = boundary_triangles(mesh);
    let nodes = mesh.nodes();
    node_sets
        .iter()
        .map(|(name, set)| {
            let position: HashMap<u32, usize> =
                set.iter().enumerate().map(|(i, &n)| (n, i)).collect();
            let mut w = vec![0.0; set.len()];
            for t in &triangles {
                if !t.iter().all(|n| position.contains_key(n)) {
                    continue;
                }
                let x: Vec<[f64; 3]> = t.iter().map(|&n| nodes[n as usize]).collect();
                for (&n, wn) in t.iter().zip(triangle_weights(&x)) {
                    w[position[&n]] += wn;
                }
            }
            (name.clone(), w)
        })
        .collect()
}

/// The contact nodes of each `contact` statement (in order): the boundary nodes of its body
/// (the mesh, or a node set's nodes on the boundary surface), in node order, each with its
/// lumped boundary area — a third of the area of each boundary triangle it is a corner of
/// (linear meshes: contact needs them).
pub(super) fn contact_nodes(
    mesh: &dyn MeshView,
    contacts: &[crate::lower::contact::ContactBody],
    node_sets: &[(String, Vec<u32>)],
) -> Vec<crate::lower::contact::ContactNodes> {
    if contacts.is_empty() {
        return Vec::new();
    }
    let nodes = mesh.nodes();
    let mut area = vec![0.0; nodes.len()];
    for t in boundary_triangles(mesh) {
        let x: Vec<[f64; 3]> = t.iter().take(3).map(|&n| nodes[n as usize]).collect();
        for (&n, w) in t.iter().zip(triangle_weights(&x)) {
            area[n as usize] += w;
        }
    }
    contacts
        .iter()
        .map(|c| {
            let members: Vec<u32> = match node_sets.iter().find(|(name, _)| *name == c.body) {
                Some((_, set)) => {
                    let mut set = set.clone();
                    set.sort_unstable();
                    set.dedup();
                    set
                }
                None => (0..nodes.len() as u32).collect(),
            };
            let (nodes, areas) = members
                .into_iter()
                .filter(|&n| area[n as usize] > 0.0)
                .map(|n| (n, area[n as usize]))
                .unzip();
            crate::lower::contact::ContactNodes { nodes, areas }
        })
        .collect()
}
