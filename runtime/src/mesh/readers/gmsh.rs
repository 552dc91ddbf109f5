//! gmsh `.msh` reader (format 2.2 ASCII and binary, 4.1 ASCII and binary) and 4.1 ASCII
//! writer.
//!
//! Written by hand rather than with `mshio`: mshio 0.4 reads only format 4.1, and softc needs
//! 2.2 (still the default of many pipelines) and error messages with line numbers.

use std::collections::BTreeMap;
use std::fmt::Write as _;
use std::path::Path;

use super::{Cursor, RawElem, RawMesh, cap, read_bytes, truncate};
use crate::mesh::error::MeshError;
use crate::mesh::model::{LengthUnit, Mesh, PhysicalName};

/// Number of nodes of gmsh element type `t`, with a name for messages.
fn elem_info(t: i64) -> Option<(usize, &'static str)> {
    Some(match t {
        1 => (2, "2-node line"),
        2 => (3, "3-node triangle"),
        3 => (4, "4-node quadrangle"),
        4 => (4, "4-node tetrahedron"),
        5 => (8, "8-node hexahedron"),
        6 => (6, "6-node prism"),
        7 => (5, "5-node pyramid"),
        8 => (3, "3-node line"),
        9 => (6, "6-node triangle"),
        10 => (9, "9-node quadrangle"),
        11 => (10, "10-node tetrahedron"),
        12 => (27, "27-node hexahedron"),
        13 => (18, "18-node prism"),
        14 => (14, "14-node pyramid"),
        15 => (1, "point"),
        16 => (8, "8-node quadrangle"),
        17 => (20, "20-node hexahedron"),
        18 => (15, "15-node prism"),
        19 => (13, "13-node pyramid"),
        _ => return None,
    })
}

/// Add one element (type `t`, file id, node ids, tag) to the raw mesh.
fn add_elem(
    raw: &mut RawMesh,
    c: &Cursor,
    t: i64,
    id: i64,
    nodes: &[i64],
    tag: i32,
    line: usize,
) -> Result<(), MeshError> {
    match t {
        4 => raw.tets.push(RawElem {
            id,
            nodes: [nodes[0], nodes[1], nodes[2], nodes[3]],
            tag,
            line,
        }),
        2 => raw.tris.push(RawElem {
            id,
            nodes: [nodes[0], nodes[1], nodes[2]],
            tag,
            line,
        }),
        // gmsh's 10-node tet lists edge 2-3 before edge 1-3; VTK's order (softc's) the other
        // way round.
        11 => {
            let mut v = [0i64; 10];
            v.copy_from_slice(&nodes[..10]);
            v.swap(8, 9);
            raw.add_quad_tet(id, v, tag, line);
        }
        9 => {
            let mut v = [0i64; 6];
            v.copy_from_slice(&nodes[..6]);
            raw.add_quad_tri(id, v, tag, line);
        }
        15 => {
            // Point elements: members of a 0-D physical group become a node set.
            raw.point_tags.push((nodes[0], tag));
            *raw.ignored.entry("point".to_string()).or_insert(0) += 1;
        }
        1 | 8 | 3 | 10 | 16 => {
            *raw.ignored
                .entry(elem_info(t).map(|x| x.1).unwrap_or("?").to_string())
                .or_insert(0) += 1;
        }
        _ => {
            let name = elem_info(t).map(|x| x.1).unwrap_or("unknown");
            let e = MeshError::unsupported(format!(
                "element {id} is a {name} (gmsh type {t}); softc simulates 4- and 10-node \
                 tetrahedra only"
            ))
            .in_file(c.path);
            let e = if line > 0 { e.at_line(line) } else { e };
            return Err(e.with_fix(
                "mesh the volume with tets (gmsh: Mesh.ElementOrder = 1 or 2, no recombine)",
            ));
        }
    }
    Ok(())
}

/// Read a gmsh file.
pub fn read(path: &Path, unit: LengthUnit) -> Result<Mesh, MeshError> {
    let data = read_bytes(path)?;
    parse(&data, path)?.finish(path, unit)
}

pub(crate) fn parse(data: &[u8], path: &Path) -> Result<RawMesh, MeshError> {
    let mut c = Cursor::new(data, path);
    let mut raw = RawMesh::default();
    let first = c.token();
    if first != Some("$MeshFormat") {
        return Err(c
            .err("not a gmsh .msh file: it does not start with $MeshFormat")
            .with_fix("export the mesh from gmsh in format 2.2 or 4.1"));
    }
    let version_tok = c.need("format version")?;
    let version: f64 = version_tok
        .parse()
        .map_err(|_| c.err(format!("bad format version `{}`", truncate(version_tok))))?;
    let file_type: i32 = c.num("file type (0 ascii, 1 binary)")?;
    let data_size: usize = c.num("data size")?;
    let binary = file_type == 1;
    let v4 = if (2.0..3.0).contains(&version) {
        false
    } else if (4.1..4.2).contains(&version) {
        true
    } else {
        return Err(c
            .err(format!("gmsh format {version} is not supported"))
            .with_fix("save as format 2.2 or 4.1 (gmsh -format msh22 / msh41)"));
    };
    let mut little = true;
    if binary {
        if v4 && data_size != 8 {
            return Err(c.err(format!(
                "binary data size {data_size} is not supported (need 8)"
            )));
        }
        c.end_header_line();
        let one = c.bytes(4, "endianness marker")?;
        let le = i32::from_le_bytes([one[0], one[1], one[2], one[3]]);
        let be = i32::from_be_bytes([one[0], one[1], one[2], one[3]]);
        little = if le == 1 {
            true
        } else if be == 1 {
            false
        } else {
            return Err(c.err_bin("bad endianness marker in binary $MeshFormat"));
        };
    }
    expect(&mut c, "$EndMeshFormat")?;
    let mut b = Bin { little };
    // entity (dim, tag) -> first physical tag (v4)
    let mut entity_phys: BTreeMap<(i32, i32), i32> = BTreeMap::new();
    let mut saw_nodes = false;
    while let Some(sec) = c.token() {
        match sec {
            "$PhysicalNames" => {
                let n: usize = c.num("number of physical names")?;
                for _ in 0..n {
                    let dim: u8 = c.num("physical dimension")?;
                    let tag: i32 = c.num("physical tag")?;
                    let rest = c.rest_of_line().trim();
                    let name = rest.trim_matches('"').to_string();
                    raw.names.push(PhysicalName { dim, tag, name });
                }
                expect(&mut c, "$EndPhysicalNames")?;
            }
            "$Entities" if v4 => {
                entity_phys = if binary {
                    entities_bin(&mut c, &mut b)?
                } else {
                    entities_ascii(&mut c)?
                };
                expect(&mut c, "$EndEntities")?;
            }
            "$Nodes" => {
                saw_nodes = true;
                match (v4, binary) {
                    (false, false) => nodes_v2_ascii(&mut c, &mut raw)?,
                    (false, true) => nodes_v2_bin(&mut c, &mut b, &mut raw, data_size)?,
                    (true, false) => nodes_v4_ascii(&mut c, &mut raw)?,
                    (true, true) => nodes_v4_bin(&mut c, &mut b, &mut raw)?,
                }
                expect(&mut c, "$EndNodes")?;
            }
            "$Elements" => {
                match (v4, binary) {
                    (false, false) => elems_v2_ascii(&mut c, &mut raw)?,
                    (false, true) => elems_v2_bin(&mut c, &mut b, &mut raw)?,
                    (true, false) => elems_v4_ascii(&mut c, &mut raw, &entity_phys)?,
                    (true, true) => elems_v4_bin(&mut c, &mut b, &mut raw, &entity_phys)?,
                }
                expect(&mut c, "$EndElements")?;
            }
            s if s.starts_with('$') && !s.starts_with("$End") => {
                // Unknown section ($NodeData, $Periodic, ...): skip to its end marker.
                let end = format!("$End{}", &s[1..]);
                let hay = &c.data[c.pos..];
                match find(hay, end.as_bytes()) {
                    Some(k) => c.pos += k + end.len(),
                    None => return Err(c.err(format!("section {s} has no {end}"))),
                }
            }
            other => {
                return Err(c
                    .err(format!("unexpected `{}` between sections", truncate(other)))
                    .with_fix("the file is corrupt; re-export it"));
            }
        }
    }
    if !saw_nodes {
        return Err(MeshError::parse("no $Nodes section").in_file(path));
    }
    if raw.tets.is_empty() {
        return Err(MeshError::parse("the file contains no tetrahedra")
            .in_file(path)
            .with_fix("mesh the volume (gmsh: Mesh 3) before saving, or save all elements"));
    }
    Ok(raw)
}

fn find(hay: &[u8], needle: &[u8]) -> Option<usize> {
    hay.windows(needle.len()).position(|w| w == needle)
}

fn expect(c: &mut Cursor, end: &str) -> Result<(), MeshError> {
    match c.token() {
        Some(t) if t == end => Ok(()),
        Some(t) => Err(c
            .err(format!("expected {end}, found `{}`", truncate(t)))
            .with_fix("a count in this section does not match its contents")),
        None => Err(c
            .err(format!("unexpected end of file, expected {end}"))
            .with_fix("the file is truncated; re-export it")),
    }
}

struct Bin {
    little: bool,
}

impl Bin {
    fn i32(&mut self, c: &mut Cursor, what: &str) -> Result<i32, MeshError> {
        let s = c.bytes(4, what)?;
        let a = [s[0], s[1], s[2], s[3]];
        Ok(if self.little {
            i32::from_le_bytes(a)
        } else {
            i32::from_be_bytes(a)
        })
    }
    fn u64(&mut self, c: &mut Cursor, what: &str) -> Result<u64, MeshError> {
        let s = c.bytes(8, what)?;
        let a = [s[0], s[1], s[2], s[3], s[4], s[5], s[6], s[7]];
        Ok(if self.little {
            u64::from_le_bytes(a)
        } else {
            u64::from_be_bytes(a)
        })
    }
    fn f64(&mut self, c: &mut Cursor, what: &str) -> Result<f64, MeshError> {
        Ok(f64::from_bits(self.u64(c, what)?))
    }
    fn count(&mut self, c: &mut Cursor, what: &str) -> Result<usize, MeshError> {
        let v = self.u64(c, what)?;
        if v > c.data.len() as u64 {
            return Err(c.err_bin(format!("{what} {v} exceeds the file size")));
        }
        Ok(v as usize)
    }
}

fn nodes_v2_ascii(c: &mut Cursor, raw: &mut RawMesh) -> Result<(), MeshError> {
    let n: usize = c.num("number of nodes")?;
    raw.coords.reserve(cap(n, c.data.len()));
    for _ in 0..n {
        c.skip_ws();
        let line = c.line_at(c.pos);
        let id: i64 = c.num("node id")?;
        let x = c.float("x coordinate")?;
        let y = c.float("y coordinate")?;
        let z = c.float("z coordinate")?;
        raw.add_node(id, [x, y, z], line);
    }
    Ok(())
}

fn nodes_v2_bin(
    c: &mut Cursor,
    b: &mut Bin,
    raw: &mut RawMesh,
    data_size: usize,
) -> Result<(), MeshError> {
    if data_size != 8 {
        return Err(c.err(format!(
            "binary data size {data_size} is not supported (need 8)"
        )));
    }
    let n: usize = c.num("number of nodes")?;
    if n.saturating_mul(28) > c.data.len() {
        return Err(c.err(format!("node count {n} exceeds the file size")));
    }
    c.end_header_line();
    for _ in 0..n {
        let id = b.i32(c, "node id")? as i64;
        let x = b.f64(c, "node coordinates")?;
        let y = b.f64(c, "node coordinates")?;
        let z = b.f64(c, "node coordinates")?;
        raw.add_node(id, [x, y, z], 0);
    }
    Ok(())
}

fn elems_v2_ascii(c: &mut Cursor, raw: &mut RawMesh) -> Result<(), MeshError> {
    let n: usize = c.num("number of elements")?;
    for _ in 0..n {
        c.skip_ws();
        let line = c.line_at(c.pos);
        let id: i64 = c.num("element id")?;
        let t: i64 = c.num("element type")?;
        let ntags: usize = c.num("number of tags")?;
        if ntags > 64 {
            return Err(c.err(format!("element {id} claims {ntags} tags")));
        }
        let mut tags = Vec::with_capacity(ntags);
        for _ in 0..ntags {
            tags.push(c.num::<i32>("element tag")?);
        }
        let Some((nn, _)) = elem_info(t) else {
            return Err(c.err(format!("element {id} has unknown gmsh type {t}")));
        };
        let mut nodes = Vec::with_capacity(nn);
        for _ in 0..nn {
            nodes.push(c.num::<i64>("element node id")?);
        }
        let tag = v2_tag(&tags);
        add_elem(raw, c, t, id, &nodes, tag, line)?;
    }
    Ok(())
}

fn v2_tag(tags: &[i32]) -> i32 {
    match tags {
        [phys, ..] if *phys != 0 => *phys,
        [_, elem, ..] => *elem,
        _ => 0,
    }
}

fn elems_v2_bin(c: &mut Cursor, b: &mut Bin, raw: &mut RawMesh) -> Result<(), MeshError> {
    let n: usize = c.num("number of elements")?;
    if n > c.data.len() {
        return Err(c.err(format!("element count {n} exceeds the file size")));
    }
    c.end_header_line();
    let mut done = 0;
    while done < n {
        let t = b.i32(c, "element block header")? as i64;
        let follow = b.i32(c, "element block header")?;
        let ntags = b.i32(c, "element block header")?;
        if follow <= 0 || !(0..=64).contains(&ntags) || follow as usize > n - done {
            return Err(c.err_bin(format!(
                "bad binary element block header (type {t}, {follow} elements, {ntags} tags)"
            )));
        }
        let Some((nn, _)) = elem_info(t) else {
            return Err(c.err_bin(format!("unknown gmsh element type {t}")));
        };
        for _ in 0..follow {
            let id = b.i32(c, "element id")? as i64;
            let mut tags = Vec::with_capacity(ntags as usize);
            for _ in 0..ntags {
                tags.push(b.i32(c, "element tags")?);
            }
            let mut nodes = Vec::with_capacity(nn);
            for _ in 0..nn {
                nodes.push(b.i32(c, "element nodes")? as i64);
            }
            add_elem(raw, c, t, id, &nodes, v2_tag(&tags), 0)?;
        }
        done += follow as usize;
    }
    Ok(())
}

fn entities_ascii(c: &mut Cursor) -> Result<BTreeMap<(i32, i32), i32>, MeshError> {
    let mut map = BTreeMap::new();
    let mut counts = [0usize; 4];
    for cnt in &mut counts {
        *cnt = c.num("number of entities")?;
    }
    for (dim, &cnt) in counts.iter().enumerate() {
        for _ in 0..cnt {
            let tag: i32 = c.num("entity tag")?;
            let nco = if dim == 0 { 3 } else { 6 };
            for _ in 0..nco {
                c.float("entity bounding box")?;
            }
            let np: usize = c.num("number of physical tags")?;
            let mut first = None;
            for _ in 0..np {
                let p: i32 = c.num("physical tag")?;
                first.get_or_insert(p);
            }
            if let Some(p) = first {
                map.insert((dim as i32, tag), p);
            }
            if dim > 0 {
                let nb: usize = c.num("number of bounding entities")?;
                for _ in 0..nb {
                    c.num::<i64>("bounding entity tag")?;
                }
            }
        }
    }
    Ok(map)
}

fn entities_bin(c: &mut Cursor, b: &mut Bin) -> Result<BTreeMap<(i32, i32), i32>, MeshError> {
    c.end_header_line();
    let mut map = BTreeMap::new();
    let mut counts = [0usize; 4];
    for cnt in &mut counts {
        *cnt = b.count(c, "number of entities")?;
    }
    for (dim, &cnt) in counts.iter().enumerate() {
        for _ in 0..cnt {
            let tag = b.i32(c, "entity tag")?;
            let nco = if dim == 0 { 3 } else { 6 };
            for _ in 0..nco {
                b.f64(c, "entity bounding box")?;
            }
            let np = b.count(c, "number of physical tags")?;
            let mut first = None;
            for _ in 0..np {
                let p = b.i32(c, "physical tag")?;
                first.get_or_insert(p);
            }
            if let Some(p) = first {
                map.insert((dim as i32, tag), p);
            }
            if dim > 0 {
                let nb = b.count(c, "number of bounding entities")?;
                for _ in 0..nb {
                    b.i32(c, "bounding entity tag")?;
                }
            }
        }
    }
    Ok(map)
}

fn nodes_v4_ascii(c: &mut Cursor, raw: &mut RawMesh) -> Result<(), MeshError> {
    let nblocks: usize = c.num("number of node blocks")?;
    let total: usize = c.num("number of nodes")?;
    c.num::<i64>("min node tag")?;
    c.num::<i64>("max node tag")?;
    raw.coords.reserve(cap(total, c.data.len()));
    let mut read = 0usize;
    for _ in 0..nblocks {
        let _dim: i32 = c.num("entity dimension")?;
        let _tag: i32 = c.num("entity tag")?;
        let param: i32 = c.num("parametric flag")?;
        let n: usize = c.num("number of nodes in block")?;
        if n > c.data.len() {
            return Err(c.err(format!(
                "node block claims {n} nodes, more than the file holds"
            )));
        }
        let mut ids = Vec::with_capacity(n);
        for _ in 0..n {
            ids.push(c.num::<i64>("node tag")?);
        }
        let extra = if param != 0 {
            _dim.clamp(0, 3) as usize
        } else {
            0
        };
        for id in ids {
            c.skip_ws();
            let line = c.line_at(c.pos);
            let x = c.float("x coordinate")?;
            let y = c.float("y coordinate")?;
            let z = c.float("z coordinate")?;
            for _ in 0..extra {
                c.float("parametric coordinate")?;
            }
            raw.add_node(id, [x, y, z], line);
        }
        read += n;
    }
    if read != total {
        return Err(c.err(format!(
            "$Nodes header says {total} nodes but its blocks hold {read}"
        )));
    }
    Ok(())
}

fn nodes_v4_bin(c: &mut Cursor, b: &mut Bin, raw: &mut RawMesh) -> Result<(), MeshError> {
    c.end_header_line();
    let nblocks = b.count(c, "number of node blocks")?;
    let total = b.count(c, "number of nodes")?;
    b.u64(c, "min node tag")?;
    b.u64(c, "max node tag")?;
    let mut read = 0usize;
    for _ in 0..nblocks {
        let dim = b.i32(c, "entity dimension")?;
        let _tag = b.i32(c, "entity tag")?;
        let param = b.i32(c, "parametric flag")?;
        let n = b.count(c, "number of nodes in block")?;
        let mut ids = Vec::with_capacity(n);
        for _ in 0..n {
            ids.push(b.u64(c, "node tag")? as i64);
        }
        let extra = if param != 0 {
            dim.clamp(0, 3) as usize
        } else {
            0
        };
        for id in ids {
            let x = b.f64(c, "node coordinates")?;
            let y = b.f64(c, "node coordinates")?;
            let z = b.f64(c, "node coordinates")?;
            for _ in 0..extra {
                b.f64(c, "parametric coordinates")?;
            }
            raw.add_node(id, [x, y, z], 0);
        }
        read += n;
    }
    if read != total {
        return Err(c.err_bin(format!(
            "$Nodes header says {total} nodes but its blocks hold {read}"
        )));
    }
    Ok(())
}

fn v4_tag(map: &BTreeMap<(i32, i32), i32>, dim: i32, etag: i32) -> i32 {
    if map.is_empty() {
        etag
    } else {
        map.get(&(dim, etag)).copied().unwrap_or(etag)
    }
}

fn elems_v4_ascii(
    c: &mut Cursor,
    raw: &mut RawMesh,
    map: &BTreeMap<(i32, i32), i32>,
) -> Result<(), MeshError> {
    let nblocks: usize = c.num("number of element blocks")?;
    let total: usize = c.num("number of elements")?;
    c.num::<i64>("min element tag")?;
    c.num::<i64>("max element tag")?;
    let mut read = 0;
    for _ in 0..nblocks {
        let dim: i32 = c.num("entity dimension")?;
        let etag: i32 = c.num("entity tag")?;
        let t: i64 = c.num("element type")?;
        let n: usize = c.num("number of elements in block")?;
        let Some((nn, _)) = elem_info(t) else {
            return Err(c.err(format!("unknown gmsh element type {t}")));
        };
        let tag = v4_tag(map, dim, etag);
        let mut nodes = vec![0i64; nn];
        for _ in 0..n {
            c.skip_ws();
            let line = c.line_at(c.pos);
            let id: i64 = c.num("element tag")?;
            for v in nodes.iter_mut() {
                *v = c.num("element node tag")?;
            }
            add_elem(raw, c, t, id, &nodes, tag, line)?;
        }
        read += n;
    }
    if read != total {
        return Err(c.err(format!(
            "$Elements header says {total} elements but its blocks hold {read}"
        )));
    }
    Ok(())
}

fn elems_v4_bin(
    c: &mut Cursor,
    b: &mut Bin,
    raw: &mut RawMesh,
    map: &BTreeMap<(i32, i32), i32>,
) -> Result<(), MeshError> {
    c.end_header_line();
    let nblocks = b.count(c, "number of element blocks")?;
    let total = b.count(c, "number of elements")?;
    b.u64(c, "min element tag")?;
    b.u64(c, "max element tag")?;
    let mut read = 0;
    for _ in 0..nblocks {
        let dim = b.i32(c, "entity dimension")?;
        let etag = b.i32(c, "entity tag")?;
        let t = b.i32(c, "element type")? as i64;
        let n = b.count(c, "number of elements in block")?;
        let Some((nn, _)) = elem_info(t) else {
            return Err(c.err_bin(format!("unknown gmsh element type {t}")));
        };
        let tag = v4_tag(map, dim, etag);
        let mut nodes = vec![0i64; nn];
        for _ in 0..n {
            let id = b.u64(c, "element tag")? as i64;
            for v in nodes.iter_mut() {
                *v = b.u64(c, "element node tag")? as i64;
            }
            add_elem(raw, c, t, id, &nodes, tag, 0)?;
        }
        read += n;
    }
    if read != total {
        return Err(c.err_bin(format!(
            "$Elements header says {total} elements but its blocks hold {read}"
        )));
    }
    Ok(())
}

/// Shortest decimal that round-trips the value rounded to 15 significant digits (keeps files
/// free of `2.4999999999999996` after unit conversion).
pub(crate) fn fmt_coord(x: f64) -> String {
    let r: f64 = format!("{x:.14e}").parse().unwrap_or(x);
    format!("{r}")
}

/// Serialize as gmsh 4.1 ASCII, coordinates in `unit`. Tags must be positive (gmsh rule).
/// One volume entity per region tag and one surface entity per surface tag, each carrying
/// the physical group of the same number; all nodes are listed in the first volume entity.
pub fn to_string(mesh: &Mesh, unit: LengthUnit) -> Result<String, MeshError> {
    let regions = mesh.region_tags();
    let surfaces = mesh.surface_tags();
    if let Some(t) = regions.iter().chain(&surfaces).find(|t| **t <= 0) {
        return Err(MeshError::unsupported(format!(
            "tag {t} is not positive; gmsh physical tags must be ≥ 1"
        ))
        .with_fix("renumber the tags"));
    }
    if let Some(q) = &mesh.mid_edges
        && (q.tets.len() != mesh.tets.len() || q.tris.len() != mesh.tris.len())
    {
        return Err(MeshError::spec(format!(
            "the quadratic mesh has mid-edge nodes for {} of {} tets and {} of {} triangles",
            q.tets.len(),
            mesh.tets.len(),
            q.tris.len(),
            mesh.tris.len()
        )));
    }
    let s = 1.0 / unit.to_metres();
    let mut o = String::with_capacity(mesh.tets.len() * 40 + mesh.nodes.len() * 60);
    o.push_str("$MeshFormat\n4.1 0 8\n$EndMeshFormat\n");
    let mut names: Vec<&PhysicalName> = mesh
        .names
        .iter()
        .filter(|p| {
            (p.dim == 3 && regions.contains(&p.tag)) || (p.dim == 2 && surfaces.contains(&p.tag))
        })
        .collect();
    names.sort_by_key(|p| (p.dim, p.tag));
    if !names.is_empty() {
        let _ = writeln!(o, "$PhysicalNames\n{}", names.len());
        for p in &names {
            let _ = writeln!(o, "{} {} \"{}\"", p.dim, p.tag, p.name.replace('"', "'"));
        }
        o.push_str("$EndPhysicalNames\n");
    }
    // Entity bounding boxes.
    let bbox = |nodes: &mut dyn Iterator<Item = u32>| {
        let mut lo = [f64::INFINITY; 3];
        let mut hi = [f64::NEG_INFINITY; 3];
        for n in nodes {
            let p = mesh.nodes[n as usize];
            for k in 0..3 {
                lo[k] = lo[k].min(p[k] * s);
                hi[k] = hi[k].max(p[k] * s);
            }
        }
        format!(
            "{} {} {} {} {} {}",
            fmt_coord(lo[0]),
            fmt_coord(lo[1]),
            fmt_coord(lo[2]),
            fmt_coord(hi[0]),
            fmt_coord(hi[1]),
            fmt_coord(hi[2])
        )
    };
    let _ = writeln!(o, "$Entities\n0 0 {} {}", surfaces.len(), regions.len());
    let quad = mesh.mid_edges.as_ref();
    for &t in &surfaces {
        let mut it = (0..mesh.tris.len())
            .filter(|&f| mesh.tri_tags[f] == t)
            .flat_map(|f| tri_nodes(mesh, f));
        let _ = writeln!(o, "{t} {} 1 {t} 0", bbox(&mut it));
    }
    for &t in &regions {
        let mut it = (0..mesh.tets.len())
            .filter(|&e| mesh.tet_tags[e] == t)
            .flat_map(|e| tet_nodes(mesh, e));
        let _ = writeln!(o, "{t} {} 1 {t} 0", bbox(&mut it));
    }
    o.push_str("$EndEntities\n");
    let nn = mesh.nodes.len();
    let host = regions.first().copied().unwrap_or(1);
    let _ = writeln!(o, "$Nodes\n1 {nn} 1 {nn}\n3 {host} 0 {nn}");
    for i in 1..=nn {
        let _ = writeln!(o, "{i}");
    }
    for p in &mesh.nodes {
        let _ = writeln!(
            o,
            "{} {} {}",
            fmt_coord(p[0] * s),
            fmt_coord(p[1] * s),
            fmt_coord(p[2] * s)
        );
    }
    o.push_str("$EndNodes\n");
    // One block per run of equal tags, so element order survives a round trip.
    fn runs(tags: &[i32]) -> Vec<(i32, usize, usize)> {
        let mut out: Vec<(i32, usize, usize)> = Vec::new();
        for (i, &t) in tags.iter().enumerate() {
            match out.last_mut() {
                Some(r) if r.0 == t => r.2 = i + 1,
                _ => out.push((t, i, i + 1)),
            }
        }
        out
    }
    let tri_runs = runs(&mesh.tri_tags);
    let tet_runs = runs(&mesh.tet_tags);
    let ne = mesh.tets.len() + mesh.tris.len();
    let _ = writeln!(
        o,
        "$Elements\n{} {ne} 1 {ne}",
        tri_runs.len() + tet_runs.len()
    );
    let (tri_type, tet_type) = if quad.is_some() { (9, 11) } else { (2, 4) };
    let mut id = 1usize;
    let line = |o: &mut String, id: usize, nodes: &mut dyn Iterator<Item = u32>| {
        let _ = write!(o, "{id}");
        for v in nodes {
            let _ = write!(o, " {}", v + 1);
        }
        o.push('\n');
    };
    for (t, a, b) in tri_runs {
        let _ = writeln!(o, "2 {t} {tri_type} {}", b - a);
        for f in a..b {
            line(&mut o, id, &mut tri_nodes(mesh, f));
            id += 1;
        }
    }
    for (t, a, b) in tet_runs {
        let _ = writeln!(o, "3 {t} {tet_type} {}", b - a);
        for e in a..b {
            line(&mut o, id, &mut tet_nodes(mesh, e));
            id += 1;
        }
    }
    o.push_str("$EndElements\n");
    Ok(o)
}

/// Tet `e`'s nodes in gmsh's order: the corners, then (quadratic meshes) the mid-edge nodes
/// of edges 0-1, 1-2, 0-2, 0-3, 2-3, 1-3 (gmsh type 11 swaps VTK's last two).
fn tet_nodes(mesh: &Mesh, e: usize) -> impl Iterator<Item = u32> + '_ {
    let mids = mesh
        .mid_edges
        .as_ref()
        .map(|q| {
            let m = q.tets[e];
            [m[0], m[1], m[2], m[3], m[5], m[4]]
        })
        .into_iter()
        .flatten();
    mesh.tets[e].into_iter().chain(mids)
}

/// Tagged triangle `f`'s nodes: the corners, then (quadratic meshes) the mid-edge nodes of
/// edges 0-1, 1-2, 2-0 (gmsh type 9).
fn tri_nodes(mesh: &Mesh, f: usize) -> impl Iterator<Item = u32> + '_ {
    let mids = mesh
        .mid_edges
        .as_ref()
        .map(|q| q.tris[f])
        .into_iter()
        .flatten();
    mesh.tris[f].into_iter().chain(mids)
}
