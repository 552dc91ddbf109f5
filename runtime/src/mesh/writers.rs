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
    Int(&'a [i32]),
}

impl Field<'_> {
    fn len(&self) -> usize {
        match self {
            Field::Scalar(v) => v.len(),
            Field::Vector(v) => v.len(),
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

/// A `.vtu` document: tets (VTK type 10) followed by the tagged triangles (type 5). Cell
/// array `tag` holds the region tag of tets and the surface tag of triangles. `positions`
/// replaces the rest positions (deformed state; metres, written in `unit`); point fields are
/// written as given (SI), cell fields are per tet (triangles get 0).
pub fn vtu_string(
    mesh: &Mesh,
    unit: LengthUnit,
    positions: Option<&[[f64; 3]]>,
    point_data: &[(&str, Field)],
    cell_data: &[(&str, Field)],
) -> String {
    let s = 1.0 / unit.to_metres();
    let pos = positions.unwrap_or(&mesh.nodes);
    let nc = mesh.tets.len() + mesh.tris.len();
    let mut o = String::with_capacity(nc * 40 + pos.len() * 60);
    o.push_str("<?xml version=\"1.0\"?>\n<VTKFile type=\"UnstructuredGrid\" version=\"1.0\" byte_order=\"LittleEndian\" header_type=\"UInt64\">\n  <UnstructuredGrid>\n");
    let _ = writeln!(
        o,
        "    <Piece NumberOfPoints=\"{}\" NumberOfCells=\"{nc}\">",
        pos.len()
    );
    let _ = writeln!(o, "      <!-- length unit: {unit} -->");
    o.push_str("      <Points>\n        <DataArray type=\"Float64\" NumberOfComponents=\"3\" format=\"ascii\">\n");
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
    for t in &mesh.tets {
        let _ = writeln!(o, "{} {} {} {}", t[0], t[1], t[2], t[3]);
    }
    for t in &mesh.tris {
        let _ = writeln!(o, "{} {} {}", t[0], t[1], t[2]);
    }
    o.push_str("        </DataArray>\n        <DataArray type=\"Int64\" Name=\"offsets\" format=\"ascii\">\n");
    let mut off = 0;
    for _ in &mesh.tets {
        off += 4;
        let _ = writeln!(o, "{off}");
    }
    for _ in &mesh.tris {
        off += 3;
        let _ = writeln!(o, "{off}");
    }
    o.push_str("        </DataArray>\n        <DataArray type=\"UInt8\" Name=\"types\" format=\"ascii\">\n");
    for _ in &mesh.tets {
        o.push_str("10\n");
    }
    for _ in &mesh.tris {
        o.push_str("5\n");
    }
    o.push_str("        </DataArray>\n      </Cells>\n");
    if !point_data.is_empty() {
        o.push_str("      <PointData>\n");
        for (n, f) in point_data {
            push_field(&mut o, n, f, pos.len().max(f.len()));
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
    push_field(&mut o, "tag", &Field::Int(&tags), nc);
    for (n, f) in cell_data {
        push_field(&mut o, n, f, nc);
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
    entries: Vec<(f64, String)>,
}

impl PvdSeries {
    pub fn new(dir: &Path, name: &str, unit: LengthUnit) -> Self {
        PvdSeries {
            dir: dir.to_path_buf(),
            name: name.to_string(),
            unit,
            entries: Vec::new(),
        }
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
        let doc = vtu_string(mesh, self.unit, Some(positions), point_data, cell_data);
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
