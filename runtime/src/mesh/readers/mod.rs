//! Mesh file readers. Each produces a [`RawMesh`] with the file's own ids; [`RawMesh::finish`]
//! maps ids to indices, converts units, checks every reference, and orients tets and tagged
//! faces (counting what it changed).

pub mod abaqus;
pub mod gmsh;
pub mod stl;
pub mod tetgen;
pub mod vtk;
pub mod vtu;

use std::collections::{BTreeMap, HashMap};
use std::path::Path;

use super::error::MeshError;
use super::model::{LengthUnit, Mesh, PhysicalName};

/// A mesh as read, before ids are resolved. Ids are the file's own; `line` fields are 1-based
/// source lines (0 when unknown, e.g. binary data).
#[derive(Debug, Default)]
pub(crate) struct RawMesh {
    pub node_ids: Vec<i64>,
    pub coords: Vec<[f64; 3]>,
    pub node_lines: Vec<usize>,
    pub tets: Vec<RawElem<4>>,
    pub tris: Vec<RawElem<3>>,
    pub names: Vec<PhysicalName>,
    pub node_sets: BTreeMap<String, Vec<i64>>,
    /// Element sets by element id.
    pub elem_sets: BTreeMap<String, Vec<i64>>,
    pub ignored: BTreeMap<String, usize>,
    /// gmsh point elements `(node id, tag)`: named 0-D physical groups become node sets.
    pub point_tags: Vec<(i64, i32)>,
    /// Quadratic tets: `(index in tets, mid-edge node ids in VTK order)`.
    pub tet_mids: Vec<(usize, [i64; 6])>,
    /// 6-node triangles: `(index in tris, mid-edge node ids on edges 0-1, 1-2, 2-0)`.
    pub tri_mids: Vec<(usize, [i64; 3])>,
}

#[derive(Debug, Clone)]
pub(crate) struct RawElem<const N: usize> {
    pub id: i64,
    pub nodes: [i64; N],
    pub tag: i32,
    pub line: usize,
}

impl RawMesh {
    /// A 10-node tet: corners, then mid-edge nodes in VTK order (0-1, 1-2, 0-2, 0-3, 1-3, 2-3).
    pub fn add_quad_tet(&mut self, id: i64, nodes: [i64; 10], tag: i32, line: usize) {
        self.tet_mids.push((
            self.tets.len(),
            [nodes[4], nodes[5], nodes[6], nodes[7], nodes[8], nodes[9]],
        ));
        self.tets.push(RawElem {
            id,
            nodes: [nodes[0], nodes[1], nodes[2], nodes[3]],
            tag,
            line,
        });
    }

    /// A 6-node triangle: corners, then mid-edge nodes on edges 0-1, 1-2, 2-0.
    pub fn add_quad_tri(&mut self, id: i64, nodes: [i64; 6], tag: i32, line: usize) {
        self.tri_mids
            .push((self.tris.len(), [nodes[3], nodes[4], nodes[5]]));
        self.tris.push(RawElem {
            id,
            nodes: [nodes[0], nodes[1], nodes[2]],
            tag,
            line,
        });
    }

    /// Refuse a file that mixes element orders: 4- and 10-node tets, or 3- and 6-node tagged
    /// triangles beside quadratic tets, or 6-node triangles beside linear tets.
    fn check_one_order(&self, path: &Path) -> Result<(), MeshError> {
        let at = |e: MeshError, line: usize| {
            let e = e.in_file(path);
            let e = if line > 0 { e.at_line(line) } else { e };
            e.with_fix(
                "export every element at one order (gmsh: Mesh.ElementOrder = 2, or 1), or \
                 convert a linear mesh with `softc mesh convert --order 2`",
            )
        };
        // The first element not in a sorted index list of quadratic ones.
        fn first_missing(n: usize, quad: impl Iterator<Item = usize>) -> Option<usize> {
            let mut want = 0;
            for i in quad {
                if i != want {
                    return Some(want);
                }
                want += 1;
            }
            (want < n).then_some(want)
        }
        let quad_tets = !self.tet_mids.is_empty();
        if quad_tets {
            if let Some(i) = first_missing(self.tets.len(), self.tet_mids.iter().map(|m| m.0)) {
                let (lin, quad) = (&self.tets[i], &self.tets[self.tet_mids[0].0]);
                return Err(at(
                    MeshError::unsupported(format!(
                        "element {} is a 4-node tetrahedron but element {} has 10 nodes: a \
                         mesh's tetrahedra must all be linear or all quadratic",
                        lin.id, quad.id
                    )),
                    lin.line,
                ));
            }
            if let Some(i) = first_missing(self.tris.len(), self.tri_mids.iter().map(|m| m.0)) {
                let t = &self.tris[i];
                return Err(at(
                    MeshError::unsupported(format!(
                        "surface triangle {} has 3 nodes but the tetrahedra have 10: a \
                         quadratic mesh's tagged triangles need their mid-edge nodes (6-node \
                         triangles)",
                        t.id
                    )),
                    t.line,
                ));
            }
        } else if let Some(&(i, _)) = self.tri_mids.first() {
            let t = &self.tris[i];
            return Err(at(
                MeshError::unsupported(format!(
                    "surface triangle {} has 6 nodes but the tetrahedra have 4: a linear mesh's \
                     tagged triangles have 3 nodes",
                    t.id
                )),
                t.line,
            ));
        }
        Ok(())
    }

    pub fn add_node(&mut self, id: i64, p: [f64; 3], line: usize) {
        self.node_ids.push(id);
        self.coords.push(p);
        self.node_lines.push(line);
    }

    /// Resolve ids, convert to metres, orient. Errors name the file and line.
    pub fn finish(self, path: &Path, unit: LengthUnit) -> Result<Mesh, MeshError> {
        self.check_one_order(path)?;
        let err = |msg: String, line: usize| {
            let e = MeshError::parse(msg).in_file(path);
            if line > 0 { e.at_line(line) } else { e }
        };
        let mut index: HashMap<i64, u32> = HashMap::with_capacity(self.node_ids.len());
        for (i, &id) in self.node_ids.iter().enumerate() {
            if index.insert(id, i as u32).is_some() {
                return Err(
                    err(format!("node id {id} is defined twice"), self.node_lines[i])
                        .with_fix("give every node a unique id"),
                );
            }
            let p = self.coords[i];
            if !p.iter().all(|c| c.is_finite()) {
                return Err(err(
                    format!("node {id} has a non-finite coordinate {p:?}"),
                    self.node_lines[i],
                )
                .with_fix("replace NaN/inf coordinates with real numbers"));
            }
        }
        if self.node_ids.len() > u32::MAX as usize {
            return Err(err("too many nodes".into(), 0));
        }
        let s = unit.to_metres();
        let nodes: Vec<[f64; 3]> = self
            .coords
            .iter()
            .map(|p| [p[0] * s, p[1] * s, p[2] * s])
            .collect();
        let look = |id: i64, what: &str, eid: i64, line: usize| -> Result<u32, MeshError> {
            index.get(&id).copied().ok_or_else(|| {
                err(
                    format!("{what} {eid} refers to node {id}, which is not defined"),
                    line,
                )
                .with_fix("check the node numbering / that the file is complete")
            })
        };
        let mut tets = Vec::with_capacity(self.tets.len());
        let mut tet_tags = Vec::with_capacity(self.tets.len());
        let mut elem_index: HashMap<i64, u32> = HashMap::with_capacity(self.tets.len());
        for t in &self.tets {
            let mut v = [0u32; 4];
            for (vk, &id) in v.iter_mut().zip(&t.nodes) {
                *vk = look(id, "element", t.id, t.line)?;
            }
            elem_index.insert(t.id, tets.len() as u32);
            tets.push(v);
            tet_tags.push(t.tag);
        }
        let mut tris = Vec::with_capacity(self.tris.len());
        let mut tri_tags = Vec::with_capacity(self.tris.len());
        for t in &self.tris {
            let mut v = [0u32; 3];
            for (vk, &id) in v.iter_mut().zip(&t.nodes) {
                *vk = look(id, "surface triangle", t.id, t.line)?;
            }
            tris.push(v);
            tri_tags.push(t.tag);
        }
        let mid_edges = if self.tet_mids.is_empty() {
            None
        } else {
            let mut q = super::model::MidEdges {
                tets: Vec::with_capacity(self.tet_mids.len()),
                tris: Vec::with_capacity(self.tri_mids.len()),
            };
            for (i, m) in &self.tet_mids {
                let t = &self.tets[*i];
                let mut v = [0u32; 6];
                for (vk, &id) in v.iter_mut().zip(m) {
                    *vk = look(id, "element", t.id, t.line)?;
                }
                q.tets.push(v);
            }
            for (i, m) in &self.tri_mids {
                let t = &self.tris[*i];
                let mut v = [0u32; 3];
                for (vk, &id) in v.iter_mut().zip(m) {
                    *vk = look(id, "surface triangle", t.id, t.line)?;
                }
                q.tris.push(v);
            }
            Some(q)
        };
        let mut node_sets = BTreeMap::new();
        let mut raw_sets = self.node_sets;
        for (id, tag) in &self.point_tags {
            if let Some(p) = self.names.iter().find(|p| p.dim == 0 && p.tag == *tag) {
                raw_sets.entry(p.name.clone()).or_default().push(*id);
            }
        }
        for (name, ids) in raw_sets {
            let mut v = Vec::with_capacity(ids.len());
            for id in ids {
                v.push(index.get(&id).copied().ok_or_else(|| {
                    err(
                        format!("node set `{name}` refers to node {id}, which is not defined"),
                        0,
                    )
                })?);
            }
            v.sort_unstable();
            v.dedup();
            node_sets.insert(name, v);
        }
        let mut element_sets = BTreeMap::new();
        for (name, ids) in self.elem_sets {
            let mut v: Vec<u32> = ids
                .iter()
                .filter_map(|id| elem_index.get(id).copied())
                .collect();
            v.sort_unstable();
            v.dedup();
            element_sets.insert(name, v);
        }
        let mut names = self.names;
        names.sort_by_key(|a| (a.dim, a.tag));
        names.dedup_by(|a, b| a.dim == b.dim && a.tag == b.tag);
        let ids = super::model::FileIds {
            nodes: super::model::FileIds::compact(self.node_ids.clone()),
            tets: super::model::FileIds::compact(self.tets.iter().map(|t| t.id).collect()),
            tris: super::model::FileIds::compact(self.tris.iter().map(|t| t.id).collect()),
        };
        let mut mesh = Mesh {
            nodes,
            tets,
            tet_tags,
            tris,
            tri_tags,
            names,
            node_sets,
            element_sets,
            report: Default::default(),
            ids,
            mid_edges,
        };
        mesh.report.ignored_elements = self.ignored;
        mesh.orient_tets();
        mesh.orient_surfaces();
        Ok(mesh)
    }
}

/// A cursor over a file's bytes for formats that mix text and binary (gmsh) or are text.
pub(crate) struct Cursor<'a> {
    pub data: &'a [u8],
    pub pos: usize,
    pub path: &'a Path,
    /// `(offset, line at offset)` of the last line lookup, so sequential lookups are O(1)
    /// amortized.
    line_cache: std::cell::Cell<(usize, usize)>,
}

impl<'a> Cursor<'a> {
    pub fn new(data: &'a [u8], path: &'a Path) -> Self {
        Cursor {
            data,
            pos: 0,
            path,
            line_cache: std::cell::Cell::new((0, 1)),
        }
    }

    /// 1-based line of byte offset `pos`.
    pub fn line_at(&self, pos: usize) -> usize {
        let pos = pos.min(self.data.len());
        let (mut from, mut line) = self.line_cache.get();
        if pos < from {
            from = 0;
            line = 1;
        }
        line += self.data[from..pos].iter().filter(|&&b| b == b'\n').count();
        self.line_cache.set((pos, line));
        line
    }

    pub fn err(&self, msg: impl Into<String>) -> MeshError {
        MeshError::parse(msg)
            .in_file(self.path)
            .at_line(self.line_at(self.pos))
    }

    pub fn err_bin(&self, msg: impl Into<String>) -> MeshError {
        MeshError::parse(msg).in_file(self.path).at_offset(self.pos)
    }

    pub fn at_end(&mut self) -> bool {
        self.skip_ws();
        self.pos >= self.data.len()
    }

    pub fn skip_ws(&mut self) {
        while self.pos < self.data.len() && self.data[self.pos].is_ascii_whitespace() {
            self.pos += 1;
        }
    }

    /// Next whitespace-separated token, or `None` at end of file.
    pub fn token(&mut self) -> Option<&'a str> {
        self.skip_ws();
        let start = self.pos;
        while self.pos < self.data.len() && !self.data[self.pos].is_ascii_whitespace() {
            self.pos += 1;
        }
        if start == self.pos {
            return None;
        }
        std::str::from_utf8(&self.data[start..self.pos])
            .ok()
            .or(Some("\u{FFFD}"))
    }

    /// Next token or an error saying what was expected.
    pub fn need(&mut self, what: &str) -> Result<&'a str, MeshError> {
        match self.token() {
            Some(t) => Ok(t),
            None => Err(self
                .err(format!("unexpected end of file, expected {what}"))
                .with_fix("the file is truncated; re-export it")),
        }
    }

    pub fn num<T: std::str::FromStr>(&mut self, what: &str) -> Result<T, MeshError> {
        let start = self.pos;
        let t = self.need(what)?;
        t.parse::<T>().map_err(|_| {
            let mut c = Cursor::new(self.data, self.path);
            c.pos = start;
            c.skip_ws();
            c.err(format!("expected {what}, found `{}`", truncate(t)))
        })
    }

    /// A float, accepting Fortran-style `1.0D+03`.
    pub fn float(&mut self, what: &str) -> Result<f64, MeshError> {
        let start = self.pos;
        let t = self.need(what)?;
        parse_float(t).ok_or_else(|| {
            let mut c = Cursor::new(self.data, self.path);
            c.pos = start;
            c.skip_ws();
            c.err(format!("expected {what}, found `{}`", truncate(t)))
        })
    }

    /// The rest of the current line (without the newline), advancing past it.
    pub fn rest_of_line(&mut self) -> &'a str {
        let start = self.pos;
        while self.pos < self.data.len() && self.data[self.pos] != b'\n' {
            self.pos += 1;
        }
        let s = std::str::from_utf8(&self.data[start..self.pos]).unwrap_or("");
        if self.pos < self.data.len() {
            self.pos += 1;
        }
        s.trim_end_matches('\r')
    }

    /// Skip the single newline that ends a header line before binary data.
    pub fn end_header_line(&mut self) {
        while self.pos < self.data.len()
            && (self.data[self.pos] == b' ' || self.data[self.pos] == b'\r')
        {
            self.pos += 1;
        }
        if self.pos < self.data.len() && self.data[self.pos] == b'\n' {
            self.pos += 1;
        }
    }

    pub fn bytes(&mut self, n: usize, what: &str) -> Result<&'a [u8], MeshError> {
        if self.data.len() - self.pos < n {
            return Err(self
                .err_bin(format!("unexpected end of binary data in {what}"))
                .with_fix("the file is truncated; re-export it"));
        }
        let s = &self.data[self.pos..self.pos + n];
        self.pos += n;
        Ok(s)
    }
}

pub(crate) fn truncate(s: &str) -> String {
    if s.chars().count() > 40 {
        format!("{}…", s.chars().take(40).collect::<String>())
    } else {
        s.to_string()
    }
}

pub(crate) fn parse_float(t: &str) -> Option<f64> {
    t.parse::<f64>()
        .ok()
        .or_else(|| t.replace(['D', 'd'], "e").parse::<f64>().ok())
}

/// Read a whole file, with the error naming it.
pub(crate) fn read_bytes(path: &Path) -> Result<Vec<u8>, MeshError> {
    crate::files::read_regular(path).map_err(|e| {
        MeshError::io(path, &e).with_fix(if e.kind() == std::io::ErrorKind::InvalidInput {
            "name a mesh file (.msh, .vtk, .vtu, .node/.ele, .inp), not a pipe, device or folder"
        } else {
            "check the path and that the file is readable"
        })
    })
}

/// A capacity hint that cannot be abused by a bogus count in a file.
pub(crate) fn cap(n: usize, data_len: usize) -> usize {
    n.min(data_len / 2 + 16)
}
