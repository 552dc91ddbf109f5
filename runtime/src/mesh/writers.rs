//! Writers: `.vtu` (VTK XML unstructured grid, ASCII) and `.pvd` time series for ParaView,
//! plus atomic file writing. gmsh output lives in [`super::readers::gmsh::to_string`].

use std::fmt::Write as _;
use std::path::{Path, PathBuf};

use super::error::MeshError;
use super::model::{LengthUnit, Mesh};
use super::readers::gmsh::fmt_coord;

/// A data array attached to points or cells.
#[derive(Debug, Clone, Copy)]
pub enum Field<'a> {
    Scalar(&'a [f64]),
    Vector(&'a [[f64; 3]]),
    /// A 3×3 tensor per entry, row-major (e.g. Cauchy or first Piola stress per tet).
    Tensor(&'a [[f64; 9]]),
    Int(&'a [i32]),
}

impl Field<'_> {
    fn len(&self) -> usize {
        match self {
            Field::Scalar(v) => v.len(),
            Field::Vector(v) => v.len(),
            Field::Tensor(v) => v.len(),
            Field::Int(v) => v.len(),
        }
    }
}

/// Write `bytes` to `path` atomically: a temporary file in the same directory, then rename.
pub fn write_atomic(path: &Path, bytes: &[u8]) -> Result<(), MeshError> {
    let dir = match path.parent() {
        Some(d) if !d.as_os_str().is_empty() => d.to_path_buf(),
        _ => PathBuf::from("."),
    };
    let name = path
        .file_name()
        .map(|n| n.to_string_lossy().into_owned())
        .unwrap_or_else(|| "out".into());
    let tmp = dir.join(format!(".{name}.tmp{}", std::process::id()));
    let res = std::fs::write(&tmp, bytes).and_then(|_| std::fs::rename(&tmp, path));
    if let Err(e) = res {
        let _ = std::fs::remove_file(&tmp);
        return Err(
            MeshError::io(path, &e).with_fix("check that the directory exists and is writable")
        );
    }
    Ok(())
}

/// How `.vtu` data arrays are stored.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum VtuEncoding {
    /// Text: readable, about 3× larger and slower to write.
    Ascii,
    /// Inline base64 of little-endian binary with a UInt64 byte-count header (ParaView's
    /// default "binary" mode, uncompressed).
    #[default]
    Binary,
}

fn b64_encode(data: &[u8], out: &mut String) {
    const T: &[u8; 64] = b"ABCDEFGHIJKLMNOPQRSTUVWXYZabcdefghijklmnopqrstuvwxyz0123456789+/";
    for ch in data.chunks(3) {
        let b = [ch[0], *ch.get(1).unwrap_or(&0), *ch.get(2).unwrap_or(&0)];
        let n = ((b[0] as u32) << 16) | ((b[1] as u32) << 8) | b[2] as u32;
        for k in 0..4 {
            if k <= ch.len() {
                out.push(T[((n >> (18 - 6 * k)) & 63) as usize] as char);
            } else {
                out.push('=');
            }
        }
    }
}

/// One binary DataArray: `type` name, values as little-endian bytes.
fn push_binary(o: &mut String, ty: &str, name: &str, ncomp: usize, bytes: &[u8]) {
    let nc = if ncomp > 1 {
        format!(" NumberOfComponents=\"{ncomp}\"")
    } else {
        String::new()
    };
    let nm = if name.is_empty() {
        String::new()
    } else {
        format!(" Name=\"{name}\"")
    };
    let _ = write!(
        o,
        "        <DataArray type=\"{ty}\"{nm}{nc} format=\"binary\">"
    );
    let mut buf = (bytes.len() as u64).to_le_bytes().to_vec();
    buf.extend_from_slice(bytes);
    b64_encode(&buf, o);
    o.push_str("</DataArray>\n");
}

fn push_field_bin(o: &mut String, name: &str, f: &Field, pad_to: usize) {
    let name = name.replace(['"', '<', '>', '&'], "_");
    match f {
        Field::Scalar(v) => {
            let mut b: Vec<u8> = v.iter().flat_map(|x| x.to_le_bytes()).collect();
            b.resize(8 * pad_to.max(v.len()), 0);
            push_binary(o, "Float64", &name, 1, &b);
        }
        Field::Vector(v) => {
            let mut b: Vec<u8> = v.iter().flatten().flat_map(|x| x.to_le_bytes()).collect();
            b.resize(24 * pad_to.max(v.len()), 0);
            push_binary(o, "Float64", &name, 3, &b);
        }
        Field::Tensor(v) => {
            let mut b: Vec<u8> = v.iter().flatten().flat_map(|x| x.to_le_bytes()).collect();
            b.resize(72 * pad_to.max(v.len()), 0);
            push_binary(o, "Float64", &name, 9, &b);
        }
        Field::Int(v) => {
            let mut b: Vec<u8> = v.iter().flat_map(|x| x.to_le_bytes()).collect();
            b.resize(4 * pad_to.max(v.len()), 0);
            push_binary(o, "Int32", &name, 1, &b);
        }
    }
}

fn push_field(o: &mut String, name: &str, f: &Field, pad_to: usize) {
    let name = name.replace(['"', '<', '>', '&'], "_");
    match f {
        Field::Scalar(v) => {
            let _ = writeln!(
                o,
                "        <DataArray type=\"Float64\" Name=\"{name}\" format=\"ascii\">"
            );
            for x in v.iter() {
                let _ = writeln!(o, "{x:e}");
            }
            for _ in v.len()..pad_to {
                o.push_str("0\n");
            }
        }
        Field::Vector(v) => {
            let _ = writeln!(
                o,
                "        <DataArray type=\"Float64\" Name=\"{name}\" NumberOfComponents=\"3\" format=\"ascii\">"
            );
            for x in v.iter() {
                let _ = writeln!(o, "{:e} {:e} {:e}", x[0], x[1], x[2]);
            }
            for _ in v.len()..pad_to {
                o.push_str("0 0 0\n");
            }
        }
        Field::Tensor(v) => {
            let _ = writeln!(
                o,
                "        <DataArray type=\"Float64\" Name=\"{name}\" NumberOfComponents=\"9\" format=\"ascii\">"
            );
            for x in v.iter() {
                let row: Vec<String> = x.iter().map(|c| format!("{c:e}")).collect();
                let _ = writeln!(o, "{}", row.join(" "));
            }
            for _ in v.len()..pad_to {
                o.push_str("0 0 0 0 0 0 0 0 0\n");
            }
        }
        Field::Int(v) => {
            let _ = writeln!(
                o,
                "        <DataArray type=\"Int32\" Name=\"{name}\" format=\"ascii\">"
            );
            for x in v.iter() {
                let _ = writeln!(o, "{x}");
            }
            for _ in v.len()..pad_to {
                o.push_str("0\n");
            }
        }
    }
    o.push_str("        </DataArray>\n");
}

/// A `.vtu` document with ASCII arrays (see [`vtu_document`]).
pub fn vtu_string(
    mesh: &Mesh,
    unit: LengthUnit,
    positions: Option<&[[f64; 3]]>,
    point_data: &[(&str, Field)],
    cell_data: &[(&str, Field)],
) -> String {
    vtu_document(
        mesh,
        unit,
        positions,
        point_data,
        cell_data,
        VtuEncoding::Ascii,
    )
}

/// The cells of a `.vtu` file: the tets, then the tagged triangles.
struct Cells {
    conn: Vec<i64>,
    offsets: Vec<i64>,
    types: Vec<u8>,
}

impl Cells {
    /// Linear tets are VTK type 10 and triangles type 5; a quadratic mesh's tets are type 24
    /// (`VTK_QUADRATIC_TETRA`: corners, then the mid-edge nodes in softc's order, which is
    /// VTK's) and its triangles type 22 (`VTK_QUADRATIC_TRIANGLE`).
    fn of(mesh: &Mesh) -> Cells {
        let nc = mesh.tets.len() + mesh.tris.len();
        let mut c = Cells {
            conn: Vec::with_capacity(nc * 10),
            offsets: Vec::with_capacity(nc),
            types: Vec::with_capacity(nc),
        };
        let q = mesh.mid_edges.as_ref();
        for (e, t) in mesh.tets.iter().enumerate() {
            c.conn.extend(t.iter().map(|&v| v as i64));
            if let Some(m) = q.and_then(|q| q.tets.get(e)) {
                c.conn.extend(m.iter().map(|&v| v as i64));
                c.types.push(24);
            } else {
                c.types.push(10);
            }
            c.offsets.push(c.conn.len() as i64);
        }
        for (f, t) in mesh.tris.iter().enumerate() {
            c.conn.extend(t.iter().map(|&v| v as i64));
            if let Some(m) = q.and_then(|q| q.tris.get(f)) {
                c.conn.extend(m.iter().map(|&v| v as i64));
                c.types.push(22);
            } else {
                c.types.push(5);
            }
            c.offsets.push(c.conn.len() as i64);
        }
        c
    }
}

/// A `.vtu` document: tets (VTK type 10, or 24 for a quadratic mesh) followed by the tagged
/// triangles (type 5, or 22). Cell
/// array `tag` holds the region tag of tets and the surface tag of triangles. `positions`
/// replaces the rest positions (deformed state; metres, written in `unit`); point fields are
/// written as given (SI), cell fields are per tet (triangles get 0).
pub fn vtu_document(
    mesh: &Mesh,
    unit: LengthUnit,
    positions: Option<&[[f64; 3]]>,
    point_data: &[(&str, Field)],
    cell_data: &[(&str, Field)],
    encoding: VtuEncoding,
) -> String {
    let s = 1.0 / unit.to_metres();
    let pos = positions.unwrap_or(&mesh.nodes);
    let nc = mesh.tets.len() + mesh.tris.len();
    let bin = encoding == VtuEncoding::Binary;
    let mut o = String::with_capacity(nc * 40 + pos.len() * 60);
    o.push_str("<?xml version=\"1.0\"?>\n<VTKFile type=\"UnstructuredGrid\" version=\"1.0\" byte_order=\"LittleEndian\" header_type=\"UInt64\">\n  <UnstructuredGrid>\n");
    let _ = writeln!(
        o,
        "    <Piece NumberOfPoints=\"{}\" NumberOfCells=\"{nc}\">",
        pos.len()
    );
    let _ = writeln!(o, "      <!-- length unit: {unit} -->");
    o.push_str("      <Points>\n");
    let cells = Cells::of(mesh);
    let (conn, offs, types) = (&cells.conn, &cells.offsets, &cells.types);
    if bin {
        let b: Vec<u8> = pos
            .iter()
            .flat_map(|p| [p[0] * s, p[1] * s, p[2] * s])
            .flat_map(|x| x.to_le_bytes())
            .collect();
        push_binary(&mut o, "Float64", "", 3, &b);
        o.push_str("      </Points>\n      <Cells>\n");
        let b: Vec<u8> = conn.iter().flat_map(|x| x.to_le_bytes()).collect();
        push_binary(&mut o, "Int64", "connectivity", 1, &b);
        let b: Vec<u8> = offs.iter().flat_map(|x| x.to_le_bytes()).collect();
        push_binary(&mut o, "Int64", "offsets", 1, &b);
        push_binary(&mut o, "UInt8", "types", 1, types);
    } else {
        o.push_str(
            "        <DataArray type=\"Float64\" NumberOfComponents=\"3\" format=\"ascii\">\n",
        );
        for p in pos {
            let _ = writeln!(
                o,
                "{} {} {}",
                fmt_coord(p[0] * s),
                fmt_coord(p[1] * s),
                fmt_coord(p[2] * s)
            );
        }
        o.push_str("        </DataArray>\n      </Points>\n      <Cells>\n");
        o.push_str("        <DataArray type=\"Int64\" Name=\"connectivity\" format=\"ascii\">\n");
        let mut from = 0;
        for &to in offs {
            for (k, v) in conn[from as usize..to as usize].iter().enumerate() {
                let sep = if k == 0 { "" } else { " " };
                let _ = write!(o, "{sep}{v}");
            }
            o.push('\n');
            from = to;
        }
        o.push_str("        </DataArray>\n        <DataArray type=\"Int64\" Name=\"offsets\" format=\"ascii\">\n");
        for x in offs {
            let _ = writeln!(o, "{x}");
        }
        o.push_str("        </DataArray>\n        <DataArray type=\"UInt8\" Name=\"types\" format=\"ascii\">\n");
        for x in types {
            let _ = writeln!(o, "{x}");
        }
        o.push_str("        </DataArray>\n");
    }
    o.push_str("      </Cells>\n");
    let field = |o: &mut String, n: &str, f: &Field, pad: usize| {
        if bin {
            push_field_bin(o, n, f, pad)
        } else {
            push_field(o, n, f, pad)
        }
    };
    if !point_data.is_empty() {
        o.push_str("      <PointData>\n");
        for (n, f) in point_data {
            field(&mut o, n, f, pos.len().max(f.len()));
        }
        o.push_str("      </PointData>\n");
    }
    o.push_str("      <CellData>\n");
    let tags: Vec<i32> = mesh
        .tet_tags
        .iter()
        .chain(&mesh.tri_tags)
        .copied()
        .collect();
    field(&mut o, "tag", &Field::Int(&tags), nc);
    for (n, f) in cell_data {
        field(&mut o, n, f, nc);
    }
    o.push_str("      </CellData>\n    </Piece>\n  </UnstructuredGrid>\n</VTKFile>\n");
    o
}

/// A `.pvd` collection listing `(time, file)` pairs (files relative to the `.pvd`).
pub fn pvd_string(entries: &[(f64, String)]) -> String {
    let mut o = String::from(
        "<?xml version=\"1.0\"?>\n<VTKFile type=\"Collection\" version=\"1.0\">\n  <Collection>\n",
    );
    for (t, f) in entries {
        let _ = writeln!(
            o,
            "    <DataSet timestep=\"{t:e}\" part=\"0\" file=\"{}\"/>",
            f.replace('"', "_")
        );
    }
    o.push_str("  </Collection>\n</VTKFile>\n");
    o
}

/// A ParaView time series: `DIR/NAME.pvd` listing `DIR/NAME_000000.vtu`, ... Each
/// [`PvdSeries::write_step`] writes one `.vtu` and rewrites the `.pvd` (atomically), so the
/// series can be opened while a run is still going.
#[derive(Debug, Clone)]
pub struct PvdSeries {
    dir: PathBuf,
    name: String,
    unit: LengthUnit,
    encoding: VtuEncoding,
    entries: Vec<(f64, String)>,
}

impl PvdSeries {
    pub fn new(dir: &Path, name: &str, unit: LengthUnit) -> Self {
        PvdSeries {
            dir: dir.to_path_buf(),
            name: name.to_string(),
            unit,
            encoding: VtuEncoding::Binary,
            entries: Vec::new(),
        }
    }

    /// Choose how the `.vtu` steps store their arrays (binary by default).
    pub fn with_encoding(mut self, encoding: VtuEncoding) -> Self {
        self.encoding = encoding;
        self
    }

    /// Path of the `.pvd` file.
    pub fn pvd_path(&self) -> PathBuf {
        self.dir.join(format!("{}.pvd", self.name))
    }

    /// Write one time step: deformed positions (m) and fields (e.g. `displacement`,
    /// `velocity` per node; `strain_energy`, `stress` per tet). Returns the `.vtu` path.
    pub fn write_step(
        &mut self,
        mesh: &Mesh,
        time: f64,
        positions: &[[f64; 3]],
        point_data: &[(&str, Field)],
        cell_data: &[(&str, Field)],
    ) -> Result<PathBuf, MeshError> {
        let file = format!("{}_{:06}.vtu", self.name, self.entries.len());
        let path = self.dir.join(&file);
        let doc = vtu_document(
            mesh,
            self.unit,
            Some(positions),
            point_data,
            cell_data,
            self.encoding,
        );
        write_atomic(&path, doc.as_bytes())?;
        self.entries.push((time, file));
        write_atomic(&self.pvd_path(), pvd_string(&self.entries).as_bytes())?;
        Ok(path)
    }

    pub fn len(&self) -> usize {
        self.entries.len()
    }
    pub fn is_empty(&self) -> bool {
        self.entries.is_empty()
    }
}
