//! Where a run's results go while it runs. The engine knows no file format: it hands states to
//! these traits, and `outputs` implements them (ParaView series, CSV logs, the progress line).
//! The dependency goes one way, outputs → engine (ARCHITECTURE.md; `tests/architecture.rs`
//! checks that the engine names nothing of `outputs`).

use crate::mesh::Mesh;

/// One frame of a run: the state at time `t`, as flat buffers of the kernels.
pub struct Frame<'a> {
    pub t: f64,
    /// Positions and velocities, 3 values per node.
    pub x: &'a [f64],
    pub v: &'a [f64],
    /// Strain energy per element (empty for the spring mesh, which has none).
    pub energy: &'a [f64],
    /// Volume ratio J per element.
    pub j: &'a [f64],
    /// Contact pressure per node (Pa): the obstacles' force on it over its boundary area;
    /// empty without contact.
    pub contact_pressure: &'a [f64],
}

/// A series of whole states (`output vtk every N steps`): written every `every()` steps and at
/// the end, with the element fields the engine computes for it.
pub trait StateSeries: Send {
    fn every(&self) -> u64;
    /// Write one frame of `mesh`, whose elements' rest volumes are `rest_volume`.
    fn write_frame(
        &mut self,
        mesh: &Mesh,
        rest_volume: &[f64],
        frame: &Frame,
    ) -> Result<(), String>;
}

/// A log of a node set (`output csv(SET) every …`): recorded every `every()` steps and at the
/// end, kept until [`NodeSetLog::finish`] (also called when a run fails, so a blow-up keeps its
/// history).
pub trait NodeSetLog: Send {
    fn every(&self) -> u64;
    /// Record the state of step `step` at time `t`: positions `x` (3 per node) against `rest`.
    fn record(&mut self, step: u64, t: f64, rest: &[[f64; 3]], x: &[f64]);
    /// Write what was recorded so far.
    fn finish(&self) -> Result<(), String>;
}

/// What a long run says while it works: steps done of a phase, and a solver's state.
pub trait ProgressReport: Send {
    fn update(&mut self, phase: &str, done: u64, total: u64);
    fn note(&mut self, detail: &str);
}
