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
    /// One thread or all for the large launches run one by one (no thread count given).
    launch_speed: LaunchSpeed,
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
/// A probe of the slower choice costs time when it confirms the faster one, so probes that
/// confirm it come ever more rarely (every 16th stretch, then 32nd, … up to every 512th), and
/// a probe that changes the choice brings them back to every 16th: on a machine shared with
/// another run the many-thread probes cost little, and the choice still follows the load.
#[derive(Default, Clone, Copy)]
struct LoopSpeed {
    /// Seconds per step on one thread, on several.
    per_step: [Option<f64>; 2],
    stretches: u64,
    /// Stretches between probes, and the stretch of the next probe.
    interval: u64,
    next_probe: u64,
    /// The choice a probe running now questions (`Some(faster was many)`).
    probing: Option<bool>,
}

impl LoopSpeed {
    const PROBE_EVERY: u64 = 16;
    const PROBE_AT_MOST_EVERY: u64 = 512;

    /// Whether the next stretch runs on several threads.
    fn pick(&mut self) -> bool {
        self.stretches += 1;
        if self.stretches <= 4 {
            return self.stretches % 2 == 1;
        }
        let Some(faster) = self.faster() else {
            return self.per_step[1].is_none();
        };
        if self.interval == 0 {
            self.interval = Self::PROBE_EVERY;
            self.next_probe = self.stretches + self.interval;
        }
        if self.stretches >= self.next_probe {
            self.probing = Some(faster);
            self.next_probe = self.stretches + self.interval;
            return !faster;
        }
        faster
    }

    /// Whether several threads are faster, once both have been measured.
    fn faster(&self) -> Option<bool> {
        match self.per_step {
            [Some(one), Some(many)] => Some(many < one),
            _ => None,
        }
    }

    fn record(&mut self, many: bool, seconds_per_step: f64) {
        let s = &mut self.per_step[many as usize];
        // A probe's time replaces the probed choice's: what it had is as old as the probes
        // are rare, and the load may have changed since.
        *s = Some(match (*s, self.probing) {
            (Some(old), None) => 0.7 * old + 0.3 * seconds_per_step,
            _ => seconds_per_step,
        });
        if let Some(before) = self.probing.take() {
            self.interval = if self.faster() == Some(before) {
                (2 * self.interval).min(Self::PROBE_AT_MOST_EVERY)
            } else {
                Self::PROBE_EVERY
            };
            self.next_probe = self.stretches + self.interval;
        }
    }
}

/// The same choice for the launches that go one by one through the host (a backward pass's
/// kernels, on a 10k mesh five launches of 50–500 µs per step): split over the launch pool's
/// workers, or run on the calling thread. Judged by stretches of [`LaunchSpeed::STRETCH`]
/// launches (their seconds per entity), so that a many-thread stretch is not judged by the
/// wake-up of workers that slept through a single-thread one. Alone on a 2-core machine the
/// split wins; beside another run, whose threads take the cores the workers wait on, one
/// thread does (issue 31 item 18: two such runs at once took 3.0 s each against 1.85 s with
/// one thread each).
#[derive(Default)]
struct LaunchSpeed {
    speed: LoopSpeed,
    many: bool,
    launches: u32,
    entities: usize,
    seconds: f64,
}

impl LaunchSpeed {
    const STRETCH: u32 = 64;

    /// Whether this launch runs on several threads.
    fn pick(&mut self) -> bool {
        if self.launches == 0 {
            self.many = self.speed.pick();
        }
        self.many
    }

    fn record(&mut self, entities: usize, seconds: f64) {
        self.launches += 1;
        self.entities += entities;
        self.seconds += seconds;
        if self.launches == Self::STRETCH {
            let per_entity = self.seconds / self.entities.max(1) as f64;
            self.speed.record(self.many, per_entity);
            (self.launches, self.entities, self.seconds) = (0, 0, 0.0);
        }
    }
}

/// The threads a large launch is split over: this machine's cores, at most 8. Asked of the
/// OS once: `available_parallelism` reads the cgroup files on every call (a few system calls),
/// and a launch asked it each time — at 10k tets that cost the backward pass a third of its
/// speed (f32 forward+backward ~3,400 steps/s, ~4,300 with `--threads 2`, which did not ask).
/// `SOFTC_THREADS=N` sets it for every run of the process that gives no thread count (a sweep
/// running one softc per core sets 1).
fn launch_threads() -> usize {
    static THREADS: std::sync::OnceLock<usize> = std::sync::OnceLock::new();
    *THREADS.get_or_init(|| {
        let cores = std::thread::available_parallelism().map_or(1, |n| n.get().min(8));
        match std::env::var("SOFTC_THREADS") {
            Err(_) => cores,
            Ok(text) => threads_from_env(&text).unwrap_or_else(|| {
                eprintln!(
                    "softc: warning: SOFTC_THREADS={text} is not a positive whole number; \
                     using {cores} threads"
                );
                cores
            }),
        }
    })
}

/// A thread count from `SOFTC_THREADS`: a positive whole number.
fn threads_from_env(text: &str) -> Option<usize> {
    text.trim().parse::<usize>().ok().filter(|&n| n >= 1)
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
            launch_speed: LaunchSpeed::default(),
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
        let elem = scene.elem_conn();
        let tri = scene.tri_conn();
        // The scene's own incidence lists, laid out for the generated code (not rebuilt).
        let flat = |c: &crate::engine::scene::Csr| (c.offsets.clone(), c.flat_entries());
        let topology = Topology::with_csr(
            scene.order(),
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
        let entities = range.len();
        let mut threads = self.threads_for(entities);
        // Measured, as the time loop's thread count is, where no count was given.
        let auto = self.threads.is_none() && threads > 1;
        if auto && !self.launch_speed.pick() {
            threads = 1;
        }
        let (Some(bufs), Some(topo)) = (self.buffers.as_mut(), self.topology.as_ref()) else {
            return Err("the backend is not prepared".into());
        };
        let start = std::time::Instant::now();
        self.module
            .run_parallel(k, bufs, topo, &self.scratch, range, threads)?;
        if auto {
            self.launch_speed
                .record(entities, start.elapsed().as_secs_f64());
        }
        Ok(())
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

#[cfg(test)]
mod tests {
    use super::*;

    /// Feed `speed` stretches whose seconds per step are `one` on one thread and `many` on
    /// several; returns how many of `n` stretches ran on several.
    fn run_stretches(speed: &mut LoopSpeed, n: usize, one: f64, many: f64) -> usize {
        let mut on_many = 0;
        for _ in 0..n {
            let m = speed.pick();
            speed.record(m, if m { many } else { one });
            on_many += m as usize;
        }
        on_many
    }

    #[test]
    fn the_faster_thread_count_runs_and_probes_of_the_slower_grow_rare() {
        let mut speed = LoopSpeed::default();
        // Alone: several threads are faster, and run (probes of one thread aside).
        let many = run_stretches(&mut speed, 1000, 2.0, 1.0);
        assert!(many > 980, "{many} of 1000 on several threads");
        // Beside another run: several threads are slower; after a few stretches to see it,
        // one thread runs, and probes of several come at most every 512th stretch.
        run_stretches(&mut speed, 100, 2.0, 5.0);
        let many = run_stretches(&mut speed, 2048, 2.0, 5.0);
        assert!(many <= 6, "{many} of 2048 probes on several threads");
        // Alone again: a probe finds several threads faster, and they run again.
        run_stretches(&mut speed, 600, 2.0, 1.0);
        let many = run_stretches(&mut speed, 100, 2.0, 1.0);
        assert!(many > 90, "{many} of 100 on several threads");
    }

    #[test]
    fn a_launch_stretch_keeps_one_choice_for_all_its_launches() {
        let mut launches = LaunchSpeed::default();
        let mut choices = Vec::new();
        for _ in 0..4 * LaunchSpeed::STRETCH {
            let m = launches.pick();
            choices.push(m);
            launches.record(1000, if m { 1e-4 } else { 2e-4 });
        }
        for stretch in choices.chunks(LaunchSpeed::STRETCH as usize) {
            assert!(stretch.iter().all(|&m| m == stretch[0]), "{stretch:?}");
        }
        // The first stretches alternate: both choices are measured.
        assert_eq!(choices[0], !choices[LaunchSpeed::STRETCH as usize]);
    }

    #[test]
    fn softc_threads_takes_a_positive_whole_number() {
        assert_eq!(threads_from_env("1"), Some(1));
        assert_eq!(threads_from_env(" 4 "), Some(4));
        for bad in ["0", "-2", "two", "1.5", ""] {
            assert_eq!(threads_from_env(bad), None, "{bad}");
        }
    }
}
