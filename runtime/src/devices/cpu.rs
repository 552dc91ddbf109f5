//! The CPU device: kernels compiled to native code by Cranelift (f64 or f32), multi-threaded
//! on large meshes, with whole stretches of steps run by a compiled time loop.

use super::{Backend, HostSlice, HostSliceMut, Launch, Uniforms};
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

/// How fast time loops ran on one thread and on several, per kind of step (its largest
/// launch, all its entities, the precision): kept for the process, so that every simulation
/// of a scene (an optimization's iterations, a benchmark's repeats) starts from what earlier
/// ones measured.
static LOOP_SPEEDS: std::sync::Mutex<Vec<(StepKind, LoopSpeed)>> =
    std::sync::Mutex::new(Vec::new());

/// A step's largest launch, all its entities, and the precision's bytes.
type StepKind = (usize, usize, usize);

/// The automatic thread count of the compiled time loop: measured, not guessed. Whether a
/// second thread pays depends on the mesh, the machine and what else runs on it (on a 2-core
/// machine busy with a build, threads that wait for each other after every launch run slower
/// than one), and the results are the same bits either way. So stretches of steps run on one
/// thread and on all, each stretch's time per step is kept (a moving average), the faster
/// choice runs, and every `PROBE_EVERY`-th stretch tries the other one again (the first four
/// alternate, so that neither is judged by one cold stretch).
#[derive(Default, Clone, Copy)]
struct LoopSpeed {
    /// Seconds per step on one thread, on several.
    per_step: [Option<f64>; 2],
    stretches: u64,
}

impl LoopSpeed {
    const PROBE_EVERY: u64 = 16;

    /// Whether the next stretch runs on several threads.
    fn pick(&mut self) -> bool {
        self.stretches += 1;
        if self.stretches <= 4 {
            return self.stretches % 2 == 1;
        }
        match self.per_step {
            [_, None] => true,
            [None, _] => false,
            [Some(one), Some(many)] => {
                let faster = many < one;
                if self.stretches.is_multiple_of(Self::PROBE_EVERY) {
                    !faster
                } else {
                    faster
                }
            }
        }
    }

    fn record(&mut self, many: bool, seconds_per_step: f64) {
        let s = &mut self.per_step[many as usize];
        *s = Some(s.map_or(seconds_per_step, |old| 0.7 * old + 0.3 * seconds_per_step));
    }
}

/// The threads a large launch is split over: this machine's cores, at most 8. Asked of the
/// OS once: `available_parallelism` reads the cgroup files on every call (a few system calls),
/// and a launch asked it each time — at 10k tets that cost the backward pass a third of its
/// speed (f32 forward+backward ~3,400 steps/s, ~4,300 with `--threads 2`, which did not ask).
fn launch_threads() -> usize {
    static THREADS: std::sync::OnceLock<usize> = std::sync::OnceLock::new();
    *THREADS.get_or_init(|| std::thread::available_parallelism().map_or(1, |n| n.get().min(8)))
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
        // Launches of 2,000+ entities are split over the launch pool's workers, which spin
        // between launches (`pool.rs`), so a backward pass's short launches find them awake.
        // Measured on this 2-core VM, f32 forward+backward steps/s: 10k tets 2,413 (1,843–1,971
        // with launches below 11,000 entities on one thread; 1,754 all on one), 1k tets
        // 18,381 (7,106 with its 1,032-element launches split too), 50k 550.
        self.threads.unwrap_or_else(|| {
            if entities >= 2_000 {
                // Capped at 8: on a 16-core machine 16 threads ran 2.6x slower than 8
                // (benchmark-50k: 420 vs 162 steps/s, with threads spawned per launch then).
                launch_threads()
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

    fn get_into(&self, b: BufferId, out: HostSliceMut<'_>) {
        let bufs = self.buffers.as_ref().expect("prepared");
        match (out, bufs.f32(b), bufs.f64(b)) {
            (HostSliceMut::F32(o), Some(d), _) => o.copy_from_slice(d),
            (HostSliceMut::F64(o), _, Some(d)) => o.copy_from_slice(d),
            (HostSliceMut::F32(o), None, Some(d)) => {
                for (o, &x) in o.iter_mut().zip(d) {
                    *o = x as f32;
                }
            }
            (HostSliceMut::F64(o), Some(d), None) => {
                for (o, &x) in o.iter_mut().zip(d) {
                    *o = f64::from(x);
                }
            }
            (_, None, None) => unreachable!("a buffer is f32 or f64"),
        }
    }

    fn set_from(&mut self, b: BufferId, src: HostSlice<'_>) {
        let bufs = self.buffers.as_mut().expect("prepared");
        match src {
            HostSlice::F32(s) => match bufs.f32_mut(b) {
                Some(d) => d.copy_from_slice(s),
                None => {
                    let d = bufs.f64_mut(b).expect("a buffer is f32 or f64");
                    for (d, &x) in d.iter_mut().zip(s) {
                        *d = f64::from(x);
                    }
                }
            },
            HostSlice::F64(s) => bufs.set(b, s).unwrap_or_else(|e| panic!("{e}")),
        }
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
        if !self.use_step_loop {
            return Ok(false);
        }
        let largest = launches.iter().map(|(_, r)| r.len()).max().unwrap_or(0);
        // With no thread count given, steps of 8,000+ entities measure one thread against all
        // (at most 8, see `threads_for`) and run the faster (`LoopSpeed`); smaller steps (~30 µs
        // at 1k tets) stay on one thread, where a probe's waits would cost more than it wins.
        let all = launch_threads();
        let auto = self.threads.is_none() && largest >= 8_000 && all > 1 && n >= 8;
        let key = (
            largest,
            launches.iter().map(|(_, r)| r.len()).sum::<usize>(),
            self.module.precision().size(),
        );
        let speeds = || LOOP_SPEEDS.lock().unwrap_or_else(|e| e.into_inner());
        let many = auto && {
            let mut all_speeds = speeds();
            let at = match all_speeds.iter().position(|(k, _)| *k == key) {
                Some(at) => at,
                None => {
                    all_speeds.push((key, LoopSpeed::default()));
                    all_speeds.len() - 1
                }
            };
            all_speeds[at].1.pick()
        };
        let threads = match (self.threads, many) {
            (Some(t), _) => t,
            (None, true) => all,
            (None, false) => 1,
        };
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
        let start = std::time::Instant::now();
        let (Some(bufs), Some(topo), Some(lp)) = (
            self.buffers.as_mut(),
            self.topology.as_ref(),
            self.step_loop.as_ref(),
        ) else {
            return Err("the backend is not prepared".into());
        };
        self.module.run_loop_threads(
            lp, bufs, topo, &uniforms, &ranges, swaps, first, dt, n, threads,
        )?;
        if auto {
            let per_step = start.elapsed().as_secs_f64() / n as f64;
            if let Some((_, s)) = speeds().iter_mut().find(|(k, _)| *k == key) {
                s.record(many, per_step);
            }
        }
        Ok(true)
    }
}
