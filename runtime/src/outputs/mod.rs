//! What a run writes: ParaView series ([`vtk`]), node-set logs ([`csv`]), the JSON summary
//! ([`json`]), each file replaced atomically ([`atomic`]). The formats live here and depend on
//! the engine, never the reverse: the engine hands states to its sink traits
//! (`engine::sinks`), which the VTK and CSV outputs and the [`progress`] line implement;
//! `softc run`, its optimization and `softc bench` format the engine's results as JSON. An output folder is held by one run at a time ([`lock`]); a long run shows
//! its [`progress`].

pub mod atomic;
pub mod csv;
pub mod json;
pub mod lock;
pub mod progress;
pub mod vtk;

/// Mean, min and max displacement of a node set per axis (m): what `softc run` reports per set
/// and `output csv(SET)` logs. `position(n)` is node n's current position.
pub fn set_displacement(
    nodes: &[u32],
    rest: &[[f64; 3]],
    position: impl Fn(usize) -> [f64; 3],
) -> [[f64; 3]; 3] {
    let mut mean = [0.0; 3];
    let mut min = [f64::INFINITY; 3];
    let mut max = [f64::NEG_INFINITY; 3];
    for &n in nodes {
        let (x, x0) = (position(n as usize), rest[n as usize]);
        for d in 0..3 {
            let u = x[d] - x0[d];
            mean[d] += u / nodes.len().max(1) as f64;
            min[d] = min[d].min(u);
            max[d] = max[d].max(u);
        }
    }
    [mean, min, max]
}
