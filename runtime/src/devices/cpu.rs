//! The CPU device: kernels compiled to native code by Cranelift (f64 or f32), multi-threaded
//! on large meshes, with whole stretches of steps run by a compiled time loop.

use super::{Backend, Launch, Uniforms};
use crate::engine::scene::Scene;
use softc_compiler::back::Precision;
use softc_compiler::back::cranelift::{Buffers, CpuModule, Topology};
use softc_compiler::ir::{BufferId, Module};
use std::ops::Range;

/// Runs kernels compiled to native code by Cranelift (f64 or f32), on several threads when
/// the mesh is large enough to pay for them; results are bit-identical whatever the thread
/// count, and in f64 bit-identical to the interpreter.
pub struct Cpu {
    module: CpuModule,
    /// The IR module it was compiled from (buffer layout).
    ir: Module,
    buffers: Option<Buffers>,
    topology: Option<Topology>,
    threads: Option<usize>,
    scratch: Vec<f64>,
    /// The time loop compiled for the launches of a step (single-threaded steps only).
    step_loop: Option<softc_compiler::back::cranelift::StepLoop>,
    use_step_loop: bool,
}

impl Cpu {
    pub fn new(
        module: &Module,
        precision: Precision,
        threads: Option<usize>,
    ) -> Result<Self, String> {
        Ok(Cpu {
            module: CpuModule::compile(module, precision)?,
            ir: module.clone(),
            buffers: None,
            topology: None,
            threads,
            scratch: Vec::new(),
            step_loop: None,
            use_step_loop: true,
        })
    }

    /// Whether whole stretches of steps run through the compiled time loop (default on; off,
    /// every launch goes through the host, with bit-identical results).
    pub fn set_step_loop(&mut self, on: bool) {
        self.use_step_loop = on;
    }

    /// The Cranelift IR of every kernel (`softc compile --emit clif`).
    pub fn clif(&self) -> String {
        self.module.clif_all()
    }

    fn threads_for(&self, entities: usize) -> usize {
        // Spawning threads costs ~0.2 ms a launch: only worth it for large launches (measured:
        // 10k tets 695 -> 918 steps/s with 2 threads; 1k tets are faster on one).
        self.threads.unwrap_or_else(|| {
            if entities >= 8_000 {
                // Capped at 8: each launch spawns its threads, and on a 16-core machine
                // 16 threads ran 2.6x slower than 8 (benchmark-50k: 420 vs 162 steps/s).
                std::thread::available_parallelism().map_or(1, |n| n.get().min(8))
            } else {
                1
            }
        })
    }
}

impl Backend for Cpu {
    fn name(&self) -> &'static str {
        "cpu"
    }

    fn precision(&self) -> Precision {
        self.module.precision()
    }

    fn prepare(&mut self, scene: &Scene) -> Result<(), String> {
        let elem: Vec<u32> = scene.mesh.tets.iter().flatten().copied().collect();
        let tri: Vec<u32> = scene.tris.iter().flatten().copied().collect();
        // The scene's own incidence lists, laid out for the generated code (not rebuilt).
        let flat = |c: &crate::engine::scene::Csr| (c.offsets.clone(), c.flat_entries());
        let topology = Topology::with_csr(
            scene.mesh.nodes.len(),
            elem,
            tri,
            flat(&scene.node_elements),
            flat(&scene.node_tris),
        )?;
        self.buffers = Some(Buffers::new(&self.ir, &topology, self.module.precision()));
        self.topology = Some(topology);
        Ok(())
    }

    fn set(&mut self, b: BufferId, data: &[f64]) {
        let bufs = self.buffers.as_mut().expect("prepared");
        bufs.set(b, data).unwrap_or_else(|e| panic!("{e}"));
    }

    fn get(&self, b: BufferId) -> Vec<f64> {
        self.buffers.as_ref().expect("prepared").get(b)
    }

    fn swap(&mut self, a: BufferId, b: BufferId) {
        self.buffers.as_mut().expect("prepared").swap(a, b);
    }

    fn run(&mut self, k: usize, range: Range<usize>, u: &Uniforms) -> Result<(), String> {
        self.scratch.clear();
        for &id in &self.module.kernel(k).uniforms {
            self.scratch.push(u.get(id));
        }
        let threads = self.threads_for(range.len());
        let (Some(bufs), Some(topo)) = (self.buffers.as_mut(), self.topology.as_ref()) else {
            return Err("the backend is not prepared".into());
        };
        self.module
            .run_parallel(k, bufs, topo, &self.scratch, range, threads)
    }

    /// Steps whose launches all run on one thread go through the compiled time loop: one call
    /// for the whole stretch instead of one host round per launch.
    fn run_steps(
        &mut self,
        launches: &[Launch],
        swaps: &[(BufferId, BufferId)],
        first: u64,
        n: u64,
        dt: f64,
        u: &Uniforms,
    ) -> Result<bool, String> {
        if !self.use_step_loop || launches.iter().any(|(_, r)| self.threads_for(r.len()) > 1) {
            return Ok(false);
        }
        let kernels: Vec<usize> = launches.iter().map(|(k, _)| *k).collect();
        if self
            .step_loop
            .as_ref()
            .is_none_or(|lp| lp.kernels != kernels)
        {
            self.step_loop = Some(self.module.compile_loop(&kernels)?);
        }
        let uniforms: Vec<Vec<f64>> = kernels
            .iter()
            .map(|&k| {
                let ids = &self.module.kernel(k).uniforms;
                ids.iter().map(|&id| u.get(id)).collect()
            })
            .collect();
        let ranges: Vec<Range<usize>> = launches.iter().map(|(_, r)| r.clone()).collect();
        let (Some(bufs), Some(topo), Some(lp)) = (
            self.buffers.as_mut(),
            self.topology.as_ref(),
            self.step_loop.as_ref(),
        ) else {
            return Err("the backend is not prepared".into());
        };
        self.module
            .run_loop(lp, bufs, topo, &uniforms, &ranges, swaps, first, dt, n)?;
        Ok(true)
    }
}
