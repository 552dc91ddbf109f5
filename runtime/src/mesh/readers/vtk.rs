//! Legacy VTK (`.vtk`) reader: ASCII or BINARY (big-endian) `UNSTRUCTURED_GRID`, both the classic `CELLS n size`
//! layout and the 5.1 `OFFSETS`/`CONNECTIVITY` layout. Tets (type 10, or 24 for 10-node tets)
//! become elements, triangles (type 5, or 22 for 6-node ones) tagged surfaces; the cell tag comes from an integer cell array named
//! `tag`, `gmsh:physical`, `CellEntityIds`, `region`, `cell_tags` or `MaterialIds` (else 1).

use std::path::Path;

use super::{Cursor, RawElem, RawMesh, read_bytes, truncate};
use crate::mesh::error::MeshError;
use crate::mesh::model::{LengthUnit, Mesh};

pub(crate) const TAG_NAMES: [&str; 6] = [
    "tag",
    "gmsh:physical",
    "CellEntityIds",
    "region",
    "cell_tags",
    "MaterialIds",
];

/// Build a raw mesh from points, cells (connectivity lists), VTK cell types and optional tags.
pub(crate) fn assemble(
    c: &Cursor,
    points: Vec<[f64; 3]>,
    cells: Vec<Vec<i64>>,
    types: Vec<i64>,
    tags: Option<Vec<i64>>,
) -> Result<RawMesh, MeshError> {
    let mut raw = RawMesh::default();
    for (i, p) in points.into_iter().enumerate() {
        raw.add_node(i as i64, p, 0);
    }
    if cells.len() != types.len() {
        return Err(MeshError::parse(format!(
            "{} cells but {} cell types",
            cells.len(),
            types.len()
        ))
        .in_file(c.path));
    }
    if let Some(t) = &tags
        && t.len() != cells.len()
    {
        return Err(MeshError::parse(format!(
            "cell tag array has {} values for {} cells",
            t.len(),
            cells.len()
        ))
        .in_file(c.path));
    }
    for (i, (conn, ty)) in cells.iter().zip(&types).enumerate() {
        let tag = tags.as_ref().map(|t| t[i] as i32).unwrap_or(1);
        match (*ty, conn.len()) {
            (10, 4) => raw.tets.push(RawElem {
                id: i as i64,
                nodes: [conn[0], conn[1], conn[2], conn[3]],
                tag,
                line: 0,
            }),
            (5, 3) => raw.tris.push(RawElem {
                id: i as i64,
                nodes: [conn[0], conn[1], conn[2]],
                tag,
                line: 0,
            }),
            (24, 10) => {
                let mut v = [0i64; 10];
                v.copy_from_slice(conn);
                raw.add_quad_tet(i as i64, v, tag, 0);
            }
            (22, 6) => {
                let mut v = [0i64; 6];
                v.copy_from_slice(conn);
                raw.add_quad_tri(i as i64, v, tag, 0);
            }
            (1 | 2 | 3 | 4 | 9 | 21, _) => {
                *raw.ignored.entry(format!("vtk type {ty}")).or_insert(0) += 1
            }
            (10 | 5 | 24 | 22, n) => {
                return Err(
                    MeshError::parse(format!("cell {i} of type {ty} has {n} nodes"))
                        .in_file(c.path),
                );
            }
            (t, _) => {
                return Err(MeshError::unsupported(format!(
                    "cell {i} has VTK type {t}; softc simulates tetrahedra: linear (type 10) \
                     or quadratic (type 24)"
                ))
                .in_file(c.path)
                .with_fix("convert to tetrahedra"));
            }
        }
    }
    if raw.tets.is_empty() {
        return Err(
            MeshError::parse("the file contains no tetrahedra (VTK type 10 or 24)").in_file(c.path),
        );
    }
    Ok(raw)
}

/// Read a legacy `.vtk` file (ASCII or BINARY, i.e. big-endian raw arrays).
pub fn read(path: &Path, unit: LengthUnit) -> Result<Mesh, MeshError> {
    let data = read_bytes(path)?;
    let mut c = Cursor::new(&data, path);
    let first = c.rest_of_line();
    if !first.starts_with("# vtk DataFile") {
        return Err(c
            .err("not a legacy VTK file (first line must be `# vtk DataFile Version ...`)")
            .with_fix("for XML VTK use the .vtu extension"));
    }
    c.rest_of_line(); // title
    let fmt = c.need("ASCII or BINARY")?;
    let binary = if fmt.eq_ignore_ascii_case("BINARY") {
        true
    } else if fmt.eq_ignore_ascii_case("ASCII") {
        false
    } else {
        return Err(c.err(format!(
            "expected ASCII or BINARY, found `{}`",
            truncate(fmt)
        )));
    };
    let mut points: Vec<[f64; 3]> = Vec::new();
    let mut cells: Vec<Vec<i64>> = Vec::new();
    let mut types: Vec<i64> = Vec::new();
    let mut tags: Option<Vec<i64>> = None;
    let mut tag_rank = usize::MAX;
    let mut cell_data = false;
    let mut ncells_data = 0usize;
    while let Some(kw) = c.token() {
        match kw.to_ascii_uppercase().as_str() {
            "DATASET" => {
                let t = c.need("dataset type")?;
                if !t.eq_ignore_ascii_case("UNSTRUCTURED_GRID") {
                    return Err(c.err(format!(
                        "dataset {t} is not supported (need UNSTRUCTURED_GRID)"
                    )));
                }
            }
            "POINTS" => {
                let n: usize = c.num("number of points")?;
                let ty = c.need("point data type")?;
                let v = values(&mut c, n.saturating_mul(3), ty, binary)?;
                points = v.chunks_exact(3).map(|p| [p[0], p[1], p[2]]).collect();
            }
            "CELLS" => {
                let n: usize = c.num("number of cells")?;
                let size: usize = c.num("cell list size")?;
                c.skip_ws();
                let save = c.pos;
                let next = c.token();
                if next.is_some_and(|t| t.eq_ignore_ascii_case("OFFSETS")) {
                    // 5.1 layout: n = number of offsets, size = connectivity length.
                    let ty = c.need("offsets type")?;
                    let off = values(&mut c, n, ty, binary)?;
                    if !c.need("CONNECTIVITY")?.eq_ignore_ascii_case("CONNECTIVITY") {
                        return Err(c.err("expected CONNECTIVITY"));
                    }
                    let ty = c.need("connectivity type")?;
                    let conn = values(&mut c, size, ty, binary)?;
                    for w in off.windows(2) {
                        let (a, b) = (w[0] as usize, w[1] as usize);
                        if a > b || b > conn.len() {
                            return Err(c.err("OFFSETS are not increasing or exceed CONNECTIVITY"));
                        }
                        cells.push(conn[a..b].iter().map(|x| *x as i64).collect());
                    }
                } else {
                    c.pos = save;
                    let list = values(&mut c, size, "int", binary)?;
                    let mut i = 0;
                    for k in 0..n {
                        let len = list.get(i).copied().unwrap_or(-1.0);
                        if !(0.0..=64.0).contains(&len) || i + 1 + len as usize > list.len() {
                            return Err(c.err(format!(
                                "cell {k}: bad node count {len}; counts do not match CELLS {n} {size}"
                            )));
                        }
                        let len = len as usize;
                        cells.push(list[i + 1..i + 1 + len].iter().map(|x| *x as i64).collect());
                        i += len + 1;
                    }
                }
            }
            "CELL_TYPES" => {
                let n: usize = c.num("number of cell types")?;
                types = values(&mut c, n, "int", binary)?
                    .iter()
                    .map(|x| *x as i64)
                    .collect();
            }
            "CELL_DATA" => {
                cell_data = true;
                ncells_data = c.num("number of cell values")?;
            }
            "POINT_DATA" => {
                cell_data = false;
                c.num::<usize>("number of point values")?;
            }
            "SCALARS" => {
                let name = c.need("array name")?.to_string();
                let ty = c.need("data type")?;
                let rest = c.rest_of_line();
                let ncomp: usize = rest.trim().parse().unwrap_or(1);
                c.skip_ws();
                let save = c.pos;
                if c.token()
                    .is_some_and(|t| t.eq_ignore_ascii_case("LOOKUP_TABLE"))
                {
                    c.need("lookup table name")?;
                } else {
                    c.pos = save;
                }
                let count = if cell_data { ncells_data } else { points.len() } * ncomp.max(1);
                let vals = values(&mut c, count, ty, binary)?;
                consider(cell_data, &name, ncomp, vals, &mut tags, &mut tag_rank);
            }
            "FIELD" => {
                c.need("field name")?;
                let narr: usize = c.num("number of arrays")?;
                for _ in 0..narr {
                    let name = c.need("array name")?.to_string();
                    let ncomp: usize = c.num("number of components")?;
                    let ntup: usize = c.num("number of tuples")?;
                    let ty = c.need("data type")?;
                    let vals = values(&mut c, ncomp.saturating_mul(ntup), ty, binary)?;
                    consider(cell_data, &name, ncomp, vals, &mut tags, &mut tag_rank);
                }
            }
            "VECTORS" | "NORMALS" => {
                c.need("array name")?;
                let ty = c.need("data type")?;
                let count = if cell_data { ncells_data } else { points.len() } * 3;
                values(&mut c, count, ty, binary)?;
            }
            "METADATA" => {
                // Skip to the blank line that ends a metadata block.
                while !c.at_end() {
                    let l = c.rest_of_line();
                    if l.trim().is_empty() {
                        break;
                    }
                }
            }
            other => {
                return Err(c
                    .err(format!("unexpected `{}` in legacy VTK", truncate(other)))
                    .with_fix("softc reads UNSTRUCTURED_GRID files"));
            }
        }
    }
    let raw = assemble(&c, points, cells, types, tags)?;
    raw.finish(path, unit)
}

/// `count` numbers of VTK type `ty`: whitespace-separated text, or big-endian raw data
/// starting on the line after the header.
fn values(c: &mut Cursor, count: usize, ty: &str, binary: bool) -> Result<Vec<f64>, MeshError> {
    if count > c.data.len() {
        return Err(c.err(format!(
            "array claims {count} values, more than the file holds"
        )));
    }
    if !binary {
        let mut v = Vec::with_capacity(count);
        for _ in 0..count {
            v.push(c.float("array value")?);
        }
        return Ok(v);
    }
    let t = ty.to_ascii_lowercase();
    let size = match t.as_str() {
        "bit" => {
            return Err(c.err("binary arrays of type bit are not supported"));
        }
        "char" | "unsigned_char" | "int8" | "uint8" | "vtktypeint8" | "vtktypeuint8" => 1,
        "short" | "unsigned_short" | "vtktypeint16" | "vtktypeuint16" => 2,
        "int" | "unsigned_int" | "float" | "vtktypeint32" | "vtktypeuint32" | "vtktypefloat32" => 4,
        "long" | "unsigned_long" | "double" | "vtktypeint64" | "vtktypeuint64"
        | "vtktypefloat64" | "vtkidtype" => 8,
        _ => return Err(c.err(format!("unknown VTK data type `{}`", truncate(ty)))),
    };
    c.end_header_line();
    let bytes = c.bytes(count * size, "binary VTK array")?;
    let signed = !t.starts_with("unsigned") && !t.contains("uint");
    let float = t == "float" || t == "double" || t.contains("float");
    Ok(bytes
        .chunks_exact(size)
        .map(|ch| {
            let mut b = [0u8; 8];
            b[8 - size..].copy_from_slice(ch);
            let u = u64::from_be_bytes(b);
            match (size, float, signed) {
                (4, true, _) => f32::from_bits(u as u32) as f64,
                (8, true, _) => f64::from_bits(u),
                (1, _, true) => u as u8 as i8 as f64,
                (2, _, true) => u as u16 as i16 as f64,
                (4, _, true) => u as u32 as i32 as f64,
                (8, _, true) => u as i64 as f64,
                _ => u as f64,
            }
        })
        .collect())
}

fn consider(
    cell_data: bool,
    name: &str,
    ncomp: usize,
    vals: Vec<f64>,
    tags: &mut Option<Vec<i64>>,
    rank: &mut usize,
) {
    if !cell_data || ncomp != 1 {
        return;
    }
    if let Some(r) = TAG_NAMES.iter().position(|n| n.eq_ignore_ascii_case(name))
        && r < *rank
    {
        *rank = r;
        *tags = Some(vals.iter().map(|x| *x as i64).collect());
    }
}
