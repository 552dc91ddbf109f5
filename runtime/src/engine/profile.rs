//! Where a time step's time goes: a backend wrapper that times every kernel launch and counts
//! the bytes each launch moves, and a streaming test of this machine's memory bandwidth to
//! compare them with (`softc bench --profile`).

use crate::devices::{Backend, Uniforms, domain_len};
use crate::engine::scene::Scene;
use softc_compiler::back::Precision;
use softc_compiler::ir::{ArgSource, Domain, Module};
use std::ops::Range;
use std::time::{Duration, Instant};

/// Per kernel: launches, time and logical bytes moved.
#[derive(Clone, Debug, Default)]
pub struct KernelCost {
    pub name: String,
    pub domain: String,
    pub launches: u64,
    pub time: Duration,
    pub bytes: u64,
}

/// Runs `inner` and accounts every launch to its kernel.
pub struct Profiled<B: Backend> {
    pub inner: B,
    pub costs: Vec<KernelCost>,
    /// Bytes one entity of each kernel moves (see [`entity_bytes`]).
    per_entity: Vec<f64>,
}

impl<B: Backend> Profiled<B> {
    pub fn new(inner: B, module: &Module, scene: &Scene) -> Self {
        let value = match inner.precision() {
            Precision::F32 => 4.0,
            _ => 8.0,
        };
        Profiled {
            costs: module
                .kernels
                .iter()
                .map(|k| KernelCost {
                    name: k.name.clone(),
                    domain: format!("{:?}", k.domain).to_lowercase(),
                    ..Default::default()
                })
                .collect(),
            per_entity: (0..module.kernels.len())
                .map(|k| entity_bytes(module, k, scene, value))
                .collect(),
            inner,
        }
    }

    /// Start counting afresh (after a warm-up run).
    pub fn reset_costs(&mut self) {
        for c in &mut self.costs {
            c.launches = 0;
            c.time = Duration::ZERO;
            c.bytes = 0;
        }
    }
}

/// The logical traffic of one entity of kernel `k`: every value it reads (its own, a corner's,
/// each gathered contribution) and writes, plus the connectivity indices that address them (a
/// u32 per corner of an element or triangle read through, two per CSR entry gathered). Caches
/// serve part of the corner reads (neighbouring elements share nodes), so this bounds the
/// memory traffic from above for the gathers and corners and is exact for the rest.
pub fn entity_bytes(module: &Module, k: usize, scene: &Scene, value: f64) -> f64 {
    let kernel = &module.kernels[k];
    let nodes = scene.mesh.nodes.len().max(1) as f64;
    let mut bytes = 0.0;
    let mut corners = std::collections::BTreeSet::new();
    for a in &kernel.args {
        match a {
            ArgSource::Own { .. } => bytes += value,
            ArgSource::Corner { corner, .. } => {
                bytes += value;
                corners.insert(*corner);
            }
            ArgSource::Uniform(_) => {}
            ArgSource::Gather { over, .. } => {
                let corners_per = if *over == Domain::Triangle { 3.0 } else { 4.0 };
                let mean_degree = domain_len(scene, *over) as f64 * corners_per / nodes;
                bytes += mean_degree * (value + 8.0);
            }
        }
    }
    bytes + 4.0 * corners.len() as f64 + value * kernel.stores.len() as f64
}

impl<B: Backend> Backend for Profiled<B> {
    fn name(&self) -> &'static str {
        self.inner.name()
    }
    fn prepare(&mut self, scene: &Scene) -> Result<(), String> {
        self.inner.prepare(scene)
    }
    fn set(&mut self, b: softc_compiler::ir::BufferId, data: &[f64]) {
        self.inner.set(b, data)
    }
    fn get(&self, b: softc_compiler::ir::BufferId) -> Vec<f64> {
        self.inner.get(b)
    }
    fn swap(&mut self, a: softc_compiler::ir::BufferId, b: softc_compiler::ir::BufferId) {
        self.inner.swap(a, b)
    }
    fn run(&mut self, k: usize, range: Range<usize>, u: &Uniforms) -> Result<(), String> {
        let n = range.len();
        let start = Instant::now();
        let r = self.inner.run(k, range, u);
        let cost = &mut self.costs[k];
        cost.time += start.elapsed();
        cost.launches += 1;
        cost.bytes += (self.per_entity[k] * n as f64) as u64;
        r
    }
    fn precision(&self) -> Precision {
        self.inner.precision()
    }
    fn device_error(&self) -> Option<String> {
        self.inner.device_error()
    }
}

/// This machine's sustainable memory bandwidth in bytes/s: the best of several passes of a
/// STREAM-style triad `a = b + s·c` over arrays far larger than the caches, on one thread
/// (the kernels' launches of a small scene run on one) and on all threads.
pub fn memory_bandwidth(threads: usize) -> f64 {
    const N: usize = 1 << 23; // 3 arrays × 64 MiB
    let b = vec![1.0f64; N];
    let c = vec![2.0f64; N];
    let mut a = vec![0.0f64; N];
    let mut best = f64::INFINITY;
    for pass in 0..5 {
        let s = 1.0 + pass as f64;
        let start = Instant::now();
        let chunk = N.div_ceil(threads.max(1));
        std::thread::scope(|scope| {
            for ((a, b), c) in a
                .chunks_mut(chunk)
                .zip(b.chunks(chunk))
                .zip(c.chunks(chunk))
            {
                scope.spawn(move || {
                    for ((x, y), z) in a.iter_mut().zip(b).zip(c) {
                        *x = y + s * z;
                    }
                });
            }
        });
        best = best.min(start.elapsed().as_secs_f64());
    }
    std::hint::black_box(&a);
    // Read b and c, write a (and read it first: write-allocate).
    4.0 * 8.0 * N as f64 / best
}
