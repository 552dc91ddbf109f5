//! Mesh validation: every problem is reported with the element, face or node it concerns.

use std::collections::BTreeMap;
use std::fmt;

use super::model::{Mesh, UnionFind, norm, sub};

/// How bad an issue is. `Error`s make [`super::load`] refuse the mesh.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord)]
pub enum Severity {
    Warning,
    Error,
}

/// What an issue is about. Indices here are 0-based (element = tet index, node = node index);
/// the messages name nodes, elements and triangles by the file's own numbers
/// ([`Mesh::node_id`], [`Mesh::tet_id`], [`Mesh::tri_id`]).
#[derive(Debug, Clone, PartialEq)]
pub enum IssueKind {
    /// A tet with negative volume while the rest of the mesh is positive: its corners are out
    /// of order in the file, or the mesh is tangled (only a whole mesh wound the other way is
    /// reordered on load).
    InvertedTet { element: usize, volume: f64 },
    /// Two positively oriented tets on the same side of the face they share: they overlap (the
    /// mesh is tangled, e.g. a node moved past its neighbours).
    OverlappingTets {
        elements: [usize; 2],
        face: [u32; 3],
    },
    /// A tet with (near) zero volume or repeated corners.
    DegenerateTet { element: usize, volume: f64 },
    /// A node index that does not exist.
    NodeOutOfRange { element: usize, node: u32 },
    /// A non-finite coordinate.
    NonFiniteNode { node: usize },
    /// A face shared by more than two tets.
    NonManifoldFace { nodes: [u32; 3], tets: usize },
    /// A boundary edge shared by more than two boundary faces: the solid is pinched there
    /// (two parts touch along an edge, e.g. a wall thinner than the mesh size).
    NonManifoldBoundaryEdge { edge: [u32; 2], faces: usize },
    /// A boundary node where separate sheets of the boundary meet (two parts of the solid
    /// touch at a single point).
    NonManifoldBoundaryNode { node: u32, sheets: usize },
    /// A chamber surface with an edge used by one triangle only (a hole).
    OpenChamber { tag: i32, edge: [u32; 2] },
    /// A chamber surface with an edge used by more than two triangles.
    NonManifoldChamber {
        tag: i32,
        edge: [u32; 2],
        uses: usize,
    },
    /// A chamber triangle that is not a boundary face of the tet mesh.
    ChamberFaceNotOnBoundary {
        tag: i32,
        face: usize,
        nodes: [u32; 3],
    },
    /// A tagged triangle (not a chamber) that is not a boundary face.
    InteriorTaggedFace {
        tag: i32,
        face: usize,
        nodes: [u32; 3],
    },
    /// A triangle with repeated or out-of-range nodes.
    BadTriangle { face: usize, nodes: [u32; 3] },
    /// Two nodes at the same position.
    DuplicateNodes { first: usize, second: usize },
    /// Nodes used by no tet.
    UnusedNodes { count: usize, first: usize },
    /// The tets form several pieces not connected through shared nodes.
    DisconnectedPieces {
        pieces: usize,
        sizes: Vec<usize>,
        example_element: usize,
    },
    /// A tag used by elements that has no physical name while other tags have one.
    UnnamedTag { dim: u8, tag: i32 },
    /// A physical name whose tag no element or triangle carries.
    UnusedName { dim: u8, tag: i32, name: String },
    /// A named selection (fixed region, node set) that selects no node.
    EmptySelection { name: String },
    /// A cavity in the solid whose wall carries no surface tag.
    UntaggedCavity {
        faces: usize,
        example_nodes: [u32; 3],
    },
    /// A chamber with non-positive enclosed volume (triangles wound the wrong way).
    ChamberWrongOrientation { tag: i32, volume: f64 },
    /// A quadratic mesh whose mid-edge node lists do not match its tets and triangles.
    MidEdgeCount {
        tets: usize,
        tet_mids: usize,
        tris: usize,
        tri_mids: usize,
    },
    /// A mid-edge node out of range, a corner of its element, or on two of its edges.
    BadMidEdgeNode { element: usize, node: u32 },
    /// An edge whose elements give it different mid-edge nodes.
    NonConformingMidEdge { edge: [u32; 2], mids: [u32; 2] },
    /// A quadratic element whose Jacobian determinant is not positive at a quadrature point or
    /// corner; `ratio` is its smallest value over the straight-sided tet's (6V).
    NonPositiveJacobian { element: usize, ratio: f64 },
}

/// One validation finding with a human-readable message.
#[derive(Debug, Clone, PartialEq)]
pub struct MeshIssue {
    pub severity: Severity,
    pub kind: IssueKind,
    pub message: String,
}

impl fmt::Display for MeshIssue {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let s = match self.severity {
            Severity::Error => "error",
            Severity::Warning => "warning",
        };
        write!(f, "{s}: {}", self.message)
    }
}

fn issue(severity: Severity, kind: IssueKind, message: String) -> MeshIssue {
    MeshIssue {
        severity,
        kind,
        message,
    }
}

/// The issue to report when a named selection (fixed region, node set) selects no node, or
/// `None` when it selects some.
pub fn check_selection(name: &str, nodes: &[u32]) -> Option<MeshIssue> {
    if nodes.is_empty() {
        Some(issue(
            Severity::Error,
            IssueKind::EmptySelection {
                name: name.to_string(),
            },
            format!(
                "selection `{name}` selects no node; check its box/plane against the mesh's \
                 bounding box and units (mesh files are read in mm unless told otherwise)"
            ),
        ))
    } else {
        None
    }
}

/// True when any issue is an error.
pub fn has_errors(issues: &[MeshIssue]) -> bool {
    issues.iter().any(|i| i.severity == Severity::Error)
}

pub(crate) const MAX_PER_KIND: usize = 50;

impl Mesh {
    /// Check the mesh; returns every issue found (empty for a clean mesh). Messages name
    /// nodes, elements and triangles by the file's numbers (issue 20 item 17).
    pub fn validate(&self) -> Vec<MeshIssue> {
        let mut out = Vec::new();
        let nn = self.nodes.len();
        // Coordinates.
        for (i, p) in self.nodes.iter().enumerate() {
            if !p.iter().all(|c| c.is_finite()) {
                out.push(issue(
                    Severity::Error,
                    IssueKind::NonFiniteNode { node: i },
                    format!("node {} has a non-finite coordinate {p:?}", self.node_id(i)),
                ));
            }
        }
        // Index ranges; stop here if broken, the rest would index out of bounds.
        let mut range_ok = true;
        for (e, t) in self.tets.iter().enumerate() {
            for &n in t {
                if n as usize >= nn {
                    range_ok = false;
                    out.push(issue(
                        Severity::Error,
                        IssueKind::NodeOutOfRange {
                            element: e,
                            node: n,
                        },
                        format!(
                            "element {} uses node index {n}, but the mesh has {nn} nodes",
                            self.tet_id(e)
                        ),
                    ));
                }
            }
        }
        for (i, f) in self.tris.iter().enumerate() {
            let bad_idx = f.iter().any(|&n| n as usize >= nn);
            if bad_idx || f[0] == f[1] || f[1] == f[2] || f[0] == f[2] {
                if bad_idx {
                    range_ok = false;
                }
                out.push(issue(
                    Severity::Error,
                    IssueKind::BadTriangle { face: i, nodes: *f },
                    format!(
                        "surface triangle {} (tag {}) has nodes {}: repeated or out of range \
                         ({nn} nodes)",
                        self.tri_id(i),
                        self.tri_tags.get(i).copied().unwrap_or(0),
                        self.node_list(f)
                    ),
                ));
            }
        }
        let finite = !out
            .iter()
            .any(|i| matches!(i.kind, IssueKind::NonFiniteNode { .. }));
        // Mid-edge nodes (quadratic meshes), once the corners can be indexed.
        let quad_ok = if range_ok && finite {
            let (quad, ok) = self.quadratic_issues();
            out.extend(quad);
            ok
        } else {
            true
        };
        if !range_ok || !quad_ok || !finite {
            return out;
        }
        // Orientation and degeneracy.
        let tol = self.degenerate_volume_tolerance();
        let mut n_inv = 0;
        for e in 0..self.tets.len() {
            let t = self.tets[e];
            let repeated = (0..4).any(|i| (i + 1..4).any(|j| t[i] == t[j]));
            let v = self.tet_volume(e);
            if repeated || v.abs() <= tol {
                n_inv += 1;
                if n_inv <= MAX_PER_KIND {
                    out.push(issue(
                        Severity::Error,
                        IssueKind::DegenerateTet {
                            element: e,
                            volume: v,
                        },
                        format!(
                            "element {} (nodes {}) is degenerate: volume {v:.3e} m³; remove it \
                             or re-mesh",
                            self.tet_id(e),
                            self.node_list(&t)
                        ),
                    ));
                }
            } else if v < 0.0 {
                n_inv += 1;
                if n_inv <= MAX_PER_KIND {
                    out.push(issue(
                        Severity::Error,
                        IssueKind::InvertedTet {
                            element: e,
                            volume: v,
                        },
                        format!(
                            "element {} (nodes {}) is inverted: volume {v:.3e} m³ while the \
                             rest of the mesh is positive — its corners are listed in the wrong \
                             order, or the mesh is tangled (a node moved past its neighbours); \
                             softc only reorders a whole mesh written with the other \
                             orientation: re-mesh, or move the node back",
                            self.tet_id(e),
                            self.node_list(&t)
                        ),
                    ));
                }
            }
        }
        // Face manifoldness.
        let table = self.face_table();
        out.extend(self.overlapping_tets(&table, tol));
        let mut i = 0;
        let mut n_nm = 0;
        while i < table.len() {
            let mut j = i + 1;
            while j < table.len() && table[j].0 == table[i].0 {
                j += 1;
            }
            if j - i > 2 {
                n_nm += 1;
                if n_nm <= MAX_PER_KIND {
                    out.push(issue(
                        Severity::Error,
                        IssueKind::NonManifoldFace {
                            nodes: table[i].0,
                            tets: j - i,
                        },
                        format!(
                            "the face with nodes {} is shared by {} tets (elements {:?}); a face \
                             may belong to at most two tets — the mesh overlaps itself",
                            self.node_list(&table[i].0),
                            j - i,
                            table[i..j]
                                .iter()
                                .map(|x| self.tet_id(x.1 as usize))
                                .collect::<Vec<_>>()
                        ),
                    ));
                }
            }
            i = j;
        }
        // Boundary edges: a closed 2-manifold boundary uses each edge in exactly two faces.
        {
            let mut be: Vec<[u32; 2]> = Vec::new();
            for f in self.boundary_faces() {
                for k in 0..3 {
                    let (a, b) = (f.nodes[k], f.nodes[(k + 1) % 3]);
                    be.push([a.min(b), a.max(b)]);
                }
            }
            be.sort_unstable();
            let mut i = 0;
            let mut n_bad = 0;
            while i < be.len() {
                let mut j = i + 1;
                while j < be.len() && be[j] == be[i] {
                    j += 1;
                }
                if j - i > 2 {
                    n_bad += 1;
                    if n_bad <= MAX_PER_KIND {
                        out.push(issue(
                            Severity::Error,
                            IssueKind::NonManifoldBoundaryEdge {
                                edge: be[i],
                                faces: j - i,
                            },
                            format!(
                                "the boundary is pinched at the edge between nodes {} and {} ({} \
                                 boundary faces meet there): two parts of the solid touch along \
                                 an edge — a wall thinner than the mesh size?",
                                self.node_id(be[i][0] as usize),
                                self.node_id(be[i][1] as usize),
                                j - i
                            ),
                        ));
                    }
                }
                i = j;
            }
        }
        out.extend(self.pinched_nodes());
        // Tagged surfaces.
        let bmap = self.boundary_face_map();
        let chambers = self.chamber_tags();
        for (fi, (f, t)) in self.tris.iter().zip(&self.tri_tags).enumerate() {
            let mut key = *f;
            key.sort_unstable();
            if !bmap.contains_key(&key) {
                let is_chamber = chambers.contains(t);
                let kind = if is_chamber {
                    IssueKind::ChamberFaceNotOnBoundary {
                        tag: *t,
                        face: fi,
                        nodes: *f,
                    }
                } else {
                    IssueKind::InteriorTaggedFace {
                        tag: *t,
                        face: fi,
                        nodes: *f,
                    }
                };
                let sev = if is_chamber {
                    Severity::Error
                } else {
                    Severity::Warning
                };
                out.push(issue(
                    sev,
                    kind,
                    format!(
                        "surface triangle {} (tag {t}{}, nodes {}) is not a boundary face of \
                         the tet mesh{}",
                        self.tri_id(fi),
                        self.name_suffix(2, *t),
                        self.node_list(f),
                        if is_chamber {
                            "; chamber faces must be faces of the tets around the cavity — \
                             generate them from the tet mesh, not from a separate surface mesh"
                        } else {
                            " (an interface between regions?)"
                        }
                    ),
                ));
            }
        }
        for &tag in &chambers {
            out.extend(self.validate_chamber(tag));
        }
        // Untagged cavities: boundary components other than the outer one with no tagged face.
        out.extend(self.untagged_cavities());
        // Duplicate nodes.
        out.extend(self.duplicate_nodes());
        // Unused nodes.
        let mut used = vec![false; nn];
        for t in &self.tets {
            for &n in t {
                used[n as usize] = true;
            }
        }
        if let Some(q) = &self.mid_edges {
            for &n in q.tets.iter().flatten() {
                used[n as usize] = true;
            }
        }
        let unused: Vec<usize> = (0..nn).filter(|&i| !used[i]).collect();
        if let Some(&first) = unused.first() {
            out.push(issue(
                Severity::Warning,
                IssueKind::UnusedNodes {
                    count: unused.len(),
                    first,
                },
                format!(
                    "{} node(s) are used by no tet (first: node {}); they get no mass and \
                     are ignored by the simulation",
                    unused.len(),
                    self.node_id(first)
                ),
            ));
        }
        // Connectivity.
        if !self.tets.is_empty() {
            let mut uf = UnionFind::new(nn);
            for t in &self.tets {
                uf.union(t[0] as usize, t[1] as usize);
                uf.union(t[0] as usize, t[2] as usize);
                uf.union(t[0] as usize, t[3] as usize);
            }
            let mut sizes: BTreeMap<usize, (usize, usize)> = BTreeMap::new();
            for (e, t) in self.tets.iter().enumerate() {
                let r = uf.find(t[0] as usize);
                let s = sizes.entry(r).or_insert((0, e));
                s.0 += 1;
            }
            if sizes.len() > 1 {
                let mut v: Vec<(usize, usize)> = sizes.values().copied().collect();
                v.sort_by(|a, b| b.0.cmp(&a.0).then(a.1.cmp(&b.1)));
                let example = v[1].1;
                out.push(issue(
                    Severity::Error,
                    IssueKind::DisconnectedPieces {
                        pieces: v.len(),
                        sizes: v.iter().map(|x| x.0).collect(),
                        example_element: example,
                    },
                    format!(
                        "the mesh has {} disconnected pieces (tets per piece: {:?}); element \
                         {} is in a smaller piece — merge duplicate nodes or remove the \
                         stray piece",
                        v.len(),
                        v.iter().map(|x| x.0).collect::<Vec<_>>(),
                        self.tet_id(example)
                    ),
                ));
            }
        }
        // Tags and names.
        out.extend(self.tag_issues());
        out
    }

    /// Interior faces whose two (positively oriented, non-degenerate) tets lie on the same side
    /// of the face: the tets overlap. Independent of the files' corner order, this catches a
    /// tangled mesh whose inverted tets were listed with their corners reordered.
    fn overlapping_tets(&self, table: &[([u32; 3], u32, u8)], tol: f64) -> Vec<MeshIssue> {
        let mut out = Vec::new();
        let mut count = 0;
        for w in table.windows(2) {
            let ((ka, ea, la), (kb, eb, lb)) = (w[0], w[1]);
            if ka != kb || ea == eb {
                continue;
            }
            let (ea, eb) = (ea as usize, eb as usize);
            if self.tet_volume(ea) <= tol || self.tet_volume(eb) <= tol {
                continue; // reported as inverted or degenerate
            }
            // The face as `ea` winds it (outward), and `eb`'s corner opposite the face: a
            // valid neighbour lies outside `ea`, on the positive side.
            let ta = self.tets[ea];
            let f = super::model::TET_FACES[la as usize];
            let opp = self.tets[eb][lb as usize];
            let p = |n: u32| self.nodes[n as usize];
            let side = super::model::signed_volume([p(ta[f[0]]), p(ta[f[1]]), p(ta[f[2]]), p(opp)]);
            if side < 0.0 {
                count += 1;
                if count <= MAX_PER_KIND {
                    out.push(issue(
                        Severity::Error,
                        IssueKind::OverlappingTets {
                            elements: [ea, eb],
                            face: ka,
                        },
                        format!(
                            "elements {} and {} overlap: both lie on the same side of the face \
                             they share (nodes {}), so the mesh is tangled (a node moved past \
                             its neighbours?); re-mesh, or move the node back",
                            self.tet_id(ea),
                            self.tet_id(eb),
                            self.node_list(&ka)
                        ),
                    ));
                }
            }
        }
        out
    }

    /// Boundary nodes whose incident boundary faces form more than one fan.
    fn pinched_nodes(&self) -> Vec<MeshIssue> {
        let bfs = self.boundary_faces();
        // (node, face) incidences sorted by node.
        let mut inc: Vec<(u32, usize)> = Vec::with_capacity(bfs.len() * 3);
        for (i, f) in bfs.iter().enumerate() {
            for &n in &f.nodes {
                inc.push((n, i));
            }
        }
        inc.sort_unstable();
        let mut out = Vec::new();
        let mut i = 0;
        while i < inc.len() {
            let mut j = i + 1;
            while j < inc.len() && inc[j].0 == inc[i].0 {
                j += 1;
            }
            let v = inc[i].0;
            let faces: Vec<usize> = inc[i..j].iter().map(|x| x.1).collect();
            // Faces around v are connected when they share an edge (v, w).
            let mut uf = UnionFind::new(faces.len());
            let mut by_other: Vec<(u32, usize)> = Vec::new();
            for (k, &f) in faces.iter().enumerate() {
                for &w in &bfs[f].nodes {
                    if w != v {
                        by_other.push((w, k));
                    }
                }
            }
            by_other.sort_unstable();
            for w in by_other.windows(2) {
                if w[0].0 == w[1].0 {
                    uf.union(w[0].1, w[1].1);
                }
            }
            let mut roots: Vec<usize> = (0..faces.len()).map(|k| uf.find(k)).collect();
            roots.sort_unstable();
            roots.dedup();
            if roots.len() > 1 && out.len() < MAX_PER_KIND {
                out.push(issue(
                    Severity::Error,
                    IssueKind::NonManifoldBoundaryNode {
                        node: v,
                        sheets: roots.len(),
                    },
                    format!(
                        "the boundary is pinched at node {} ({} separate surface sheets meet \
                         there): two parts of the solid touch at a point — a wall thinner than \
                         the mesh size?",
                        self.node_id(v as usize),
                        roots.len()
                    ),
                ));
            }
            i = j;
        }
        out
    }

    fn name_suffix(&self, dim: u8, tag: i32) -> String {
        match self.tag_name(dim, tag) {
            Some(n) => format!(" \"{n}\""),
            None => String::new(),
        }
    }

    /// Check one chamber surface: closed, manifold, wound with normals into the solid.
    pub fn validate_chamber(&self, tag: i32) -> Vec<MeshIssue> {
        let mut out = Vec::new();
        let mut edges: Vec<([u32; 2], i32)> = Vec::new();
        for f in self.surface(tag) {
            for k in 0..3 {
                let a = f[k];
                let b = f[(k + 1) % 3];
                // +1 for a→b with a<b, -1 otherwise: a consistently wound closed surface sums
                // to zero per edge.
                if a < b {
                    edges.push(([a, b], 1));
                } else {
                    edges.push(([b, a], -1));
                }
            }
        }
        edges.sort_unstable();
        let mut i = 0;
        let mut n_open = 0;
        while i < edges.len() {
            let mut j = i + 1;
            while j < edges.len() && edges[j].0 == edges[i].0 {
                j += 1;
            }
            let uses = j - i;
            let e = edges[i].0;
            if uses == 1 {
                n_open += 1;
                if n_open <= MAX_PER_KIND {
                    out.push(issue(
                        Severity::Error,
                        IssueKind::OpenChamber { tag, edge: e },
                        format!(
                            "chamber surface {tag}{} is open: edge between nodes {} and {} \
                             belongs to one triangle only; close the cavity surface",
                            self.name_suffix(2, tag),
                            self.node_id(e[0] as usize),
                            self.node_id(e[1] as usize)
                        ),
                    ));
                }
            } else if uses > 2 {
                out.push(issue(
                    Severity::Error,
                    IssueKind::NonManifoldChamber { tag, edge: e, uses },
                    format!(
                        "chamber surface {tag}{} is non-manifold: edge between nodes {} and {} \
                         belongs to {uses} triangles",
                        self.name_suffix(2, tag),
                        self.node_id(e[0] as usize),
                        self.node_id(e[1] as usize)
                    ),
                ));
            }
            i = j;
        }
        if out.is_empty() {
            let v = self.enclosed_volume(tag);
            if v <= 0.0 {
                out.push(issue(
                    Severity::Error,
                    IssueKind::ChamberWrongOrientation { tag, volume: v },
                    format!(
                        "chamber surface {tag}{} encloses volume {v:.3e} m³ ≤ 0: its triangles \
                         point out of the solid; reverse their winding",
                        self.name_suffix(2, tag)
                    ),
                ));
            }
        }
        out
    }

    fn untagged_cavities(&self) -> Vec<MeshIssue> {
        let bfs = self.boundary_faces();
        if bfs.is_empty() {
            return Vec::new();
        }
        let comps = super::model::boundary_components(&bfs);
        let outer = self.outer_boundary_keys();
        let mut tagged = std::collections::BTreeSet::new();
        for f in &self.tris {
            let mut k = *f;
            k.sort_unstable();
            tagged.insert(k);
        }
        let mut per_comp: BTreeMap<usize, (usize, bool, [u32; 3])> = BTreeMap::new();
        for (i, f) in bfs.iter().enumerate() {
            let mut k = f.nodes;
            k.sort_unstable();
            if outer.contains(&k) {
                continue;
            }
            let e = per_comp.entry(comps[i]).or_insert((0, false, f.nodes));
            e.0 += 1;
            e.1 |= tagged.contains(&k);
        }
        per_comp
            .values()
            .filter(|(_, t, _)| !t)
            .map(|&(n, _, ex)| {
                issue(
                    Severity::Warning,
                    IssueKind::UntaggedCavity {
                        faces: n,
                        example_nodes: ex,
                    },
                    format!(
                        "the solid has an internal cavity ({n} boundary faces, e.g. nodes {}) \
                         whose wall carries no surface tag, so no pressure can act on it",
                        self.node_list(&ex)
                    ),
                )
            })
            .collect()
    }

    fn duplicate_nodes(&self) -> Vec<MeshIssue> {
        let (lo, hi) = self.bounding_box();
        let tol = 1e-9 * norm(sub(hi, lo)).max(f64::MIN_POSITIVE);
        let mut idx: Vec<usize> = (0..self.nodes.len()).collect();
        idx.sort_by(|&a, &b| {
            self.nodes[a][0]
                .total_cmp(&self.nodes[b][0])
                .then(a.cmp(&b))
        });
        let mut out = Vec::new();
        let mut count = 0;
        for i in 0..idx.len() {
            let p = self.nodes[idx[i]];
            for &jn in &idx[i + 1..] {
                let q = self.nodes[jn];
                if q[0] - p[0] > tol {
                    break;
                }
                if norm(sub(p, q)) <= tol {
                    count += 1;
                    if count <= MAX_PER_KIND {
                        let (a, b) = (idx[i].min(jn), idx[i].max(jn));
                        out.push(issue(
                            Severity::Warning,
                            IssueKind::DuplicateNodes {
                                first: a,
                                second: b,
                            },
                            format!(
                                "nodes {} and {} are at the same position {p:?}; the mesh is \
                                 cut there — merge them (e.g. gmsh Coherence)",
                                self.node_id(a),
                                self.node_id(b)
                            ),
                        ));
                    }
                }
            }
        }
        out
    }

    fn tag_issues(&self) -> Vec<MeshIssue> {
        let mut out = Vec::new();
        for (dim, tags) in [(3u8, self.region_tags()), (2u8, self.surface_tags())] {
            let named = self.names.iter().any(|p| p.dim == dim);
            if named {
                for t in &tags {
                    if self.tag_name(dim, *t).is_none() {
                        out.push(issue(
                            Severity::Warning,
                            IssueKind::UnnamedTag { dim, tag: *t },
                            format!(
                                "{} tag {t} has no physical name while other tags do",
                                if dim == 3 { "region" } else { "surface" }
                            ),
                        ));
                    }
                }
            }
            for p in self.names.iter().filter(|p| p.dim == dim) {
                if !tags.contains(&p.tag) {
                    out.push(issue(
                        Severity::Warning,
                        IssueKind::UnusedName {
                            dim,
                            tag: p.tag,
                            name: p.name.clone(),
                        },
                        format!(
                            "physical name \"{}\" ({}D tag {}) is carried by no element",
                            p.name, dim, p.tag
                        ),
                    ));
                }
            }
        }
        out
    }
}
