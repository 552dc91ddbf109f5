//! `--vtk DIR`: the deformed mesh as a ParaView series, one `.vtu` file per written step. One
//! unit system per file, SI as every other output of a run: points and displacement in m,
//! velocity in m/s, strain-energy density in J/m³, the time in s; each array's name ends in its
//! unit (`displacement_m`), as the CSV logs' columns do. A quadratic mesh is written as
//! quadratic tetrahedra (VTK type 24, its tagged triangles type 22): the mid-edge nodes are
//! points like the corners, with their own displacement and velocity. A scene with contact adds
//! each node's contact pressure.

use crate::engine::{Frame, StateSeries};
use crate::mesh::Mesh;
use crate::mesh::writers::Field;

/// A `.pvd` series of `.vtu` files: the deformed mesh with displacement and velocity per
/// node, strain energy and volume ratio J per element.
pub struct VtkOutput {
    pub series: crate::mesh::writers::PvdSeries,
    /// Write every this many steps (and the first and last state).
    pub every: u64,
}

/// The array names, each with its SI unit.
pub const DISPLACEMENT: &str = "displacement_m";
pub const VELOCITY: &str = "velocity_m_per_s";
pub const ENERGY_DENSITY: &str = "strain_energy_density_J_per_m3";
/// The obstacles' force on a contact node over its boundary area (scenes with contact).
pub const CONTACT_PRESSURE: &str = "contact_pressure_Pa";
/// The volume ratio (dimensionless).
pub const VOLUME_RATIO: &str = "J";

impl VtkOutput {
    /// A series `DIR/NAME.pvd` written every `every` steps, in SI units.
    pub fn new(dir: &std::path::Path, name: &str, every: u64) -> VtkOutput {
        VtkOutput {
            series: crate::mesh::writers::PvdSeries::new(dir, name, crate::mesh::LengthUnit::Metre),
            every,
        }
    }

    /// Write one frame of `mesh` (whose elements' rest volumes are `rest_volume`): positions,
    /// displacement and velocity per node; strain energy density and J per element.
    pub fn write_frame(
        &mut self,
        mesh: &Mesh,
        rest_volume: &[f64],
        frame: &Frame,
    ) -> Result<(), String> {
        let Frame {
            t,
            x,
            v,
            energy,
            j,
            contact_pressure,
        } = *frame;
        let pos: Vec<[f64; 3]> = x.chunks(3).map(|c| [c[0], c[1], c[2]]).collect();
        let disp: Vec<[f64; 3]> = pos
            .iter()
            .zip(&mesh.nodes)
            .map(|(p, p0)| [p[0] - p0[0], p[1] - p0[1], p[2] - p0[2]])
            .collect();
        let vel: Vec<[f64; 3]> = v.chunks(3).map(|c| [c[0], c[1], c[2]]).collect();
        let density: Vec<f64> = energy
            .iter()
            .zip(rest_volume)
            .map(|(e, v0)| e / v0)
            .collect();
        // The spring mesh has no strain energy: its elements carry J only.
        let mut cell_fields = vec![(VOLUME_RATIO, Field::Scalar(j))];
        if !density.is_empty() {
            cell_fields.insert(0, (ENERGY_DENSITY, Field::Scalar(&density)));
        }
        let mut point_fields = vec![
            (DISPLACEMENT, Field::Vector(&disp)),
            (VELOCITY, Field::Vector(&vel)),
        ];
        if !contact_pressure.is_empty() {
            point_fields.push((CONTACT_PRESSURE, Field::Scalar(contact_pressure)));
        }
        self.series
            .write_step(mesh, t, &pos, &point_fields, &cell_fields)
            .map(|_| ())
            .map_err(|e| format!("cannot write the VTK output: {e}"))
    }
}

impl StateSeries for VtkOutput {
    fn every(&self) -> u64 {
        self.every
    }

    fn write_frame(
        &mut self,
        mesh: &Mesh,
        rest_volume: &[f64],
        frame: &Frame,
    ) -> Result<(), String> {
        VtkOutput::write_frame(self, mesh, rest_volume, frame)
    }
}
