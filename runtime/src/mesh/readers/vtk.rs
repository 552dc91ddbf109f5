//! Legacy VTK (`.vtk`) reader: ASCII `UNSTRUCTURED_GRID`, both the classic `CELLS n size`
//! layout and the 5.1 `OFFSETS`/`CONNECTIVITY` layout. Tets (type 10) become elements,
//! triangles (type 5) tagged surfaces; the cell tag comes from an integer cell array named
//! `tag`, `gmsh:physical`, `CellEntityIds`, `region`, `cell_tags` or `MaterialIds` (else 1).

use std::path::Path;

use super::{Cursor, RawElem, RawMesh, cap, read_bytes, truncate};
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
            (1 | 2 | 3 | 4 | 9, _) => {
                *raw.ignored.entry(format!("vtk type {ty}")).or_insert(0) += 1
            }
            (10 | 5, n) => {
                return Err(
                    MeshError::parse(format!("cell {i} of type {ty} has {n} nodes"))
                        .in_file(c.path),
                );
            }
            (t, _) => {
                return Err(MeshError::unsupported(format!(
                    "cell {i} has VTK type {t}; softc simulates linear tets (type 10) only"
                ))
                .in_file(c.path)
                .with_fix("convert to linear tetrahedra"));
            }
        }
    }
    if raw.tets.is_empty() {
        return Err(
            MeshError::parse("the file contains no tetrahedra (VTK type 10)").in_file(c.path),
        );
    }
    Ok(raw)
}

/// Read a legacy `.vtk` file.
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
    if fmt.eq_ignore_ascii_case("BINARY") {
        return Err(c
            .err("binary legacy VTK is not supported")
            .with_fix("save as ASCII legacy VTK, or as .vtu"));
    }
    if !fmt.eq_ignore_ascii_case("ASCII") {
        return Err(c.err(format!("expected ASCII, found `{}`", truncate(fmt))));
    }
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
                c.need("point data type")?;
                points.reserve(cap(n, data.len()));
                for _ in 0..n {
                    let p = [c.float("x")?, c.float("y")?, c.float("z")?];
                    points.push(p);
                }
            }
            "CELLS" => {
                let n: usize = c.num("number of cells")?;
                let size: usize = c.num("cell list size")?;
                c.skip_ws();
                let save = c.pos;
                let next = c.token();
                if next.is_some_and(|t| t.eq_ignore_ascii_case("OFFSETS")) {
                    // 5.1 layout: n = number of offsets, size = connectivity length.
                    c.need("offsets type")?;
                    let mut off = Vec::with_capacity(cap(n, data.len()));
                    for _ in 0..n {
                        off.push(c.num::<usize>("offset")?);
                    }
                    if !c.need("CONNECTIVITY")?.eq_ignore_ascii_case("CONNECTIVITY") {
                        return Err(c.err("expected CONNECTIVITY"));
                    }
                    c.need("connectivity type")?;
                    let mut conn = Vec::with_capacity(cap(size, data.len()));
                    for _ in 0..size {
                        conn.push(c.num::<i64>("node index")?);
                    }
                    for w in off.windows(2) {
                        if w[0] > w[1] || w[1] > conn.len() {
                            return Err(c.err("OFFSETS are not increasing or exceed CONNECTIVITY"));
                        }
                        cells.push(conn[w[0]..w[1]].to_vec());
                    }
                } else {
                    c.pos = save;
                    let mut used = 0;
                    for i in 0..n {
                        let k: usize = c.num("cell size")?;
                        used += k + 1;
                        if k > 64 || used > size {
                            return Err(c.err(format!(
                                "cell {i} claims {k} nodes; counts do not match CELLS {n} {size}"
                            )));
                        }
                        let mut v = Vec::with_capacity(k);
                        for _ in 0..k {
                            v.push(c.num::<i64>("node index")?);
                        }
                        cells.push(v);
                    }
                }
            }
            "CELL_TYPES" => {
                let n: usize = c.num("number of cell types")?;
                for _ in 0..n {
                    types.push(c.num::<i64>("cell type")?);
                }
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
                c.need("data type")?;
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
                let vals = read_values(&mut c, count)?;
                consider(cell_data, &name, ncomp, vals, &mut tags, &mut tag_rank);
            }
            "FIELD" => {
                c.need("field name")?;
                let narr: usize = c.num("number of arrays")?;
                for _ in 0..narr {
                    let name = c.need("array name")?.to_string();
                    let ncomp: usize = c.num("number of components")?;
                    let ntup: usize = c.num("number of tuples")?;
                    c.need("data type")?;
                    let vals = read_values(&mut c, ncomp.saturating_mul(ntup))?;
                    consider(cell_data, &name, ncomp, vals, &mut tags, &mut tag_rank);
                }
            }
            "VECTORS" | "NORMALS" => {
                c.need("array name")?;
                c.need("data type")?;
                let count = if cell_data { ncells_data } else { points.len() } * 3;
                read_values(&mut c, count)?;
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
                    .with_fix("softc reads ASCII UNSTRUCTURED_GRID files"));
            }
        }
    }
    let tags = tags.map(|t| t.into_iter().collect::<Vec<_>>());
    let mut raw = assemble(&c, points, cells, types, tags)?;
    // Node ids are 0-based indices; keep them so error messages match the file.
    raw.node_lines.iter_mut().for_each(|l| *l = 0);
    raw.finish(path, unit)
}

fn read_values(c: &mut Cursor, count: usize) -> Result<Vec<f64>, MeshError> {
    if count > c.data.len() {
        return Err(c.err(format!(
            "array claims {count} values, more than the file holds"
        )));
    }
    let mut v = Vec::with_capacity(count);
    for _ in 0..count {
        v.push(c.float("array value")?);
    }
    Ok(v)
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
