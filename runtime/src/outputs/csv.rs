//! `output csv(SET) every …`: a node set's displacement over time, one row per logged step.

use super::atomic::write_atomically;
use super::set_displacement;

/// `output csv(SET) every …`: the mean, min and max displacement of a node set over time,
/// collected while running and written atomically when the run ends (also when it fails, so a
/// blow-up leaves its history).
pub struct CsvOutput {
    pub path: std::path::PathBuf,
    /// Nodes of the set.
    pub nodes: Vec<u32>,
    /// Write every this many steps (and the first and last state).
    pub every: u64,
    rows: String,
}

impl CsvOutput {
    pub fn new(path: std::path::PathBuf, nodes: Vec<u32>, every: u64) -> Self {
        CsvOutput {
            path,
            nodes,
            every: every.max(1),
            rows: "step,t_s,mean_ux_m,mean_uy_m,mean_uz_m,min_ux_m,min_uy_m,min_uz_m,max_ux_m,max_uy_m,max_uz_m\n"
                .into(),
        }
    }

    /// Log the state of step `step` at time `t`: positions `x` (3 per node) against `rest`.
    pub(crate) fn record(&mut self, step: u64, t: f64, rest: &[[f64; 3]], x: &[f64]) {
        use std::fmt::Write;
        let [mean, min, max] = set_displacement(&self.nodes, rest, |n| {
            [x[3 * n], x[3 * n + 1], x[3 * n + 2]]
        });
        let _ = write!(self.rows, "{step},{t:e}");
        for v in mean.iter().chain(&min).chain(&max) {
            let _ = write!(self.rows, ",{v:e}");
        }
        self.rows.push('\n');
    }

    /// Write the rows logged so far.
    pub(crate) fn finish(&self) -> Result<(), String> {
        write_atomically(&self.path, self.rows.as_bytes())
            .map_err(|e| format!("cannot write the CSV output `{}`: {e}", self.path.display()))
    }
}

impl crate::engine::NodeSetLog for CsvOutput {
    fn every(&self) -> u64 {
        self.every
    }

    fn record(&mut self, step: u64, t: f64, rest: &[[f64; 3]], x: &[f64]) {
        CsvOutput::record(self, step, t, rest, x)
    }

    fn finish(&self) -> Result<(), String> {
        CsvOutput::finish(self)
    }
}
