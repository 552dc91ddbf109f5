//! Tetrahedral meshes (issue 3): the model, precomputed kernel data, readers and writers,
//! a built-in isosurface-stuffing mesher, the structured Kuhn benchmark grid, validation and
//! quality reports.
//!
//! Units: coordinates are SI metres inside softc. Mesh files are read and written in
//! millimetres unless a [`LengthUnit`] says otherwise.
//!
//! Conventions: tets are positively oriented (`det[b−a, c−a, d−a] > 0`); tagged surface
//! triangles are wound so that `(b−a) × (c−a)` points **into the solid**, i.e. the direction
//! in which a positive chamber pressure pushes the wall.
//!
//! ```
//! use softc::mesh::kuhn::{KuhnSpec, kuhn_grid};
//! use softc::mesh::{LengthUnit, Precomputed, check_selection, has_errors};
//!
//! // The 1k benchmark scene (or `softc::mesh::load(path, LengthUnit::Millimetre)?`).
//! let mesh = kuhn_grid(&KuhnSpec::benchmark(12, 4, 4), LengthUnit::Millimetre)?;
//! assert!(!has_errors(&mesh.validate()));
//! let cavity = mesh.resolve_surface("cavity").map_err(|e| e.to_string()).unwrap();
//! let clamp = mesh.nodes_in_box([-1e-3, -1.0, -1.0], [1e-6, 1.0, 1.0]);
//! assert!(check_selection("clamp", &clamp).is_none());
//! let pre = Precomputed::with_uniform_density(&mesh, 1070.0)?;
//! let chamber = pre.surface(cavity).unwrap();
//! assert!(chamber.chamber && !chamber.tris.is_empty());
//! assert_eq!(pre.node_elements.of(0)[0], (0, 0)); // node 0 is corner 0 of tet 0
//! # Ok::<(), softc::mesh::MeshError>(())
//! ```

pub mod commands;
pub mod error;
pub mod kuhn;
pub mod mesher;
pub mod model;
pub mod precompute;
pub mod probe;
pub mod quadratic;
pub mod quality;
pub mod readers;
pub mod renumber;
pub mod validate;
pub mod writers;

use std::path::Path;

pub use error::{MeshError, MeshErrorKind};
pub use model::{
    BoundaryFace, LengthUnit, LoadReport, Mesh, MidEdges, PhysicalName, QUAD_TET_EDGES,
    signed_volume,
};
pub use precompute::{Edge, NodeElementCsr, Precomputed, SurfaceTris};
pub use quality::QualityReport;
pub use validate::{IssueKind, MeshIssue, Severity, check_selection, has_errors};

/// File formats softc reads or writes.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Format {
    Gmsh,
    VtkLegacy,
    Vtu,
    Tetgen,
    Abaqus,
    Stl,
}

impl Format {
    /// Format from a file extension.
    pub fn from_path(path: &Path) -> Result<Format, MeshError> {
        let ext = path
            .extension()
            .and_then(|e| e.to_str())
            .map(|e| e.to_ascii_lowercase())
            .unwrap_or_default();
        Ok(match ext.as_str() {
            "msh" => Format::Gmsh,
            "vtk" => Format::VtkLegacy,
            "vtu" => Format::Vtu,
            "node" | "ele" | "face" => Format::Tetgen,
            "inp" => Format::Abaqus,
            "stl" => Format::Stl,
            _ => {
                return Err(MeshError::unsupported(format!(
                    "unknown mesh file extension `.{ext}`"
                ))
                .in_file(path)
                .with_fix(
                    "use .msh (gmsh), .vtk/.vtu (VTK), .node/.ele (tetgen), .inp (Abaqus); \
                     mesh .stl surfaces with `softc mesh generate`",
                ));
            }
        })
    }
}

/// Read a tet mesh, choosing the reader by extension, without semantic validation (tets are
/// oriented and every reference checked). Use [`load`] to also refuse invalid meshes.
pub fn read(path: &Path, unit: LengthUnit) -> Result<Mesh, MeshError> {
    match Format::from_path(path)? {
        Format::Gmsh => readers::gmsh::read(path, unit),
        Format::VtkLegacy => readers::vtk::read(path, unit),
        Format::Vtu => readers::vtu::read(path, unit),
        Format::Tetgen => readers::tetgen::read(path, unit),
        Format::Abaqus => readers::abaqus::read(path, unit),
        Format::Stl => Err(MeshError::unsupported(
            "an STL file is a surface, not a tetrahedral mesh",
        )
        .in_file(path)
        .with_fix(
            "mesh it with `softc mesh generate SPEC -o OUT.msh` (a TOML spec naming this STL as \
             the body or a cavity), then load OUT.msh",
        )),
    }
}

/// Read a tet mesh and validate it: errors (inverted or degenerate tets, open chambers,
/// chamber faces off the boundary, disconnected pieces, ...) refuse the mesh, with every
/// issue listed in the error. Warnings are returned by [`Mesh::validate`] for the caller.
pub fn load(path: &Path, unit: LengthUnit) -> Result<Mesh, MeshError> {
    refuse_invalid(read(path, unit)?, path)
}

/// [`load`] for a file whose coordinates are in units of `metres_per_unit` metres (a script's
/// `load(path, unit: …)`, 1e-3 for millimetres): the mesh is scaled to metres before it is
/// validated, so the volumes quoted in its messages are SI.
pub fn load_scaled(path: &Path, metres_per_unit: f64) -> Result<Mesh, MeshError> {
    let mut mesh = read(path, LengthUnit::Metre)?;
    mesh.scale(metres_per_unit);
    refuse_invalid(mesh, path)
}

fn refuse_invalid(mesh: Mesh, path: &Path) -> Result<Mesh, MeshError> {
    let issues = mesh.validate();
    if has_errors(&issues) {
        let n = issues
            .iter()
            .filter(|i| i.severity == Severity::Error)
            .count();
        let mut e = MeshError::new(
            MeshErrorKind::Invalid,
            format!("the mesh is invalid ({n} error(s))"),
        )
        .in_file(path)
        .with_fix("fix the listed elements/faces/nodes in the source and re-export");
        e.issues = issues
            .into_iter()
            .filter(|i| i.severity == Severity::Error)
            .collect();
        return Err(e);
    }
    Ok(mesh)
}

/// Write a mesh as `.msh` (gmsh 4.1 ASCII) or `.vtu`, by extension, coordinates in `unit`.
/// The file is written atomically (temporary file in the same directory, then renamed).
pub fn save(mesh: &Mesh, path: &Path, unit: LengthUnit) -> Result<(), MeshError> {
    let text = match Format::from_path(path)? {
        Format::Gmsh => readers::gmsh::to_string(mesh, unit)?,
        Format::Vtu => writers::vtu_string(mesh, unit, None, &[], &[]),
        _ => {
            return Err(MeshError::unsupported("softc writes .msh and .vtu meshes")
                .in_file(path)
                .with_fix("give the output a .msh or .vtu extension"));
        }
    };
    writers::write_atomic(path, text.as_bytes())
}
