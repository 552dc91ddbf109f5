//! The GPU's time loop (issue 28): a stretch of steps recorded at once, state checks read back
//! without waiting, and the adjoint's states kept in device memory give the bits of launching
//! kernel by kernel with states copied to the host, in a few submissions.
//!
//! Without an adapter these tests print a note and pass, except with `CI=true`, where they
//! fail: CI installs Mesa's lavapipe (`mesa-vulkan-drivers`) so they always run there.

mod common;

use softc::devices::gpu::Gpu;
use softc::devices::{Backend, HostSlice, HostSliceMut, PendingRead, Uniforms};
use softc::engine::adjoint::GradOptions;
use softc::engine::scene::Scene;
use softc::engine::{RunError, RunSummary, Simulation};
use softc_compiler::back::Precision;
use softc_compiler::back::wgsl::LaunchMode;
use softc_compiler::ir::{BufferId, Module};
use std::ops::Range;
use std::path::{Path, PathBuf};

fn root() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .parent()
        .unwrap()
        .to_path_buf()
}

fn scene(example: &str) -> Scene {
    Scene::load(&root().join("examples").join(example), &[]).unwrap()
}

/// The GPU backend, or `None` (with a note) when this machine has no adapter.
fn gpu(module: &Module, launch: LaunchMode) -> Option<Gpu> {
    match Gpu::with_launch_mode(module, Precision::F32, None, launch) {
        Ok(g) => Some(g),
        Err(e) if e.starts_with("no GPU adapter found") => {
            assert!(
                std::env::var("CI").as_deref() != Ok("true"),
                "CI=true but no GPU adapter: {e}"
            );
            eprintln!("note: GPU test skipped: {e}");
            None
        }
        Err(e) if e.contains("no immediates") => {
            eprintln!("note: {e}");
            None
        }
        Err(e) => panic!("{e}"),
    }
}

/// A backend as the engine drove the GPU before its time loop: every launch on its own
/// (no `run_steps`), every read waited for, the adjoint's states copied to the host.
struct OneByOne<B>(B);

impl<B: Backend> Backend for OneByOne<B> {
    fn name(&self) -> &'static str {
        self.0.name()
    }
    fn prepare(&mut self, scene: &Scene) -> Result<(), String> {
        self.0.prepare(scene)
    }
    fn set(&mut self, b: BufferId, data: &[f64]) {
        self.0.set(b, data)
    }
    fn get(&self, b: BufferId) -> Vec<f64> {
        self.0.get(b)
    }
    fn get_into(&self, b: BufferId, out: HostSliceMut<'_>) {
        self.0.get_into(b, out)
    }
    fn set_from(&mut self, b: BufferId, src: HostSlice<'_>) {
        self.0.set_from(b, src)
    }
    fn swap(&mut self, a: BufferId, b: BufferId) {
        self.0.swap(a, b)
    }
    fn run(&mut self, k: usize, range: Range<usize>, u: &Uniforms) -> Result<(), String> {
        self.0.run(k, range, u)
    }
    fn precision(&self) -> Precision {
        self.0.precision()
    }
    fn device_error(&self) -> Option<String> {
        self.0.device_error()
    }
    fn read_later(&mut self, bufs: &[BufferId]) -> PendingRead {
        PendingRead::Done(bufs.iter().map(|&b| self.0.get(b)).collect())
    }
}

fn same_bits(a: &[[f64; 3]], b: &[[f64; 3]]) -> bool {
    a.iter()
        .flatten()
        .zip(b.iter().flatten())
        .all(|(p, q)| p.to_bits() == q.to_bits())
}

#[test]
fn the_time_loop_gives_the_bits_of_launching_kernel_by_kernel() {
    // The benchmark (one chamber, its pressure ramped in t) and the explicit pressure study
    // (several materials and chambers).
    for example in ["benchmark-1k.soft", "pressure_optimization_explicit.soft"] {
        let scene = scene(example);
        let module = &scene.lowered.module;
        let Some(g) = gpu(module, LaunchMode::Uniform) else {
            return;
        };
        let steps = 260;
        let looped = Simulation::new(&scene, g).run(None, Some(steps)).unwrap();
        let one = gpu(module, LaunchMode::Uniform).unwrap();
        let stepped = Simulation::new(&scene, OneByOne(one))
            .run(None, Some(steps))
            .unwrap();
        assert!(
            same_bits(&looped.x, &stepped.x) && same_bits(&looped.v, &stepped.v),
            "{example}: the time loop changed the results"
        );
        assert_eq!(
            looped.loss.map(f64::to_bits),
            stepped.loss.map(f64::to_bits)
        );
        assert!(looped.x != scene.mesh.nodes, "{example}: the body moved");
        // Without fusing independent kernels into one dispatch: the same bits.
        let unfused = gpu(module, LaunchMode::Uniform).unwrap();
        unfused.set_fusion(false);
        let separate = Simulation::new(&scene, unfused)
            .run(None, Some(steps))
            .unwrap();
        assert!(
            same_bits(&looped.x, &separate.x) && same_bits(&looped.v, &separate.v),
            "{example}: fusing kernels changed the results"
        );
        // Launch blocks in a storage table indexed by an immediate: the same bits again.
        if let Some(t) = gpu(module, LaunchMode::Table) {
            let table = Simulation::new(&scene, t).run(None, Some(steps)).unwrap();
            assert!(
                same_bits(&table.x, &looped.x) && same_bits(&table.v, &looped.v),
                "{example}: the launch table changed the results"
            );
        }
    }
}

#[test]
fn a_thousand_steps_take_one_submission_per_state_check() {
    let scene = scene("benchmark-1k.soft");
    let Some(g) = gpu(&scene.lowered.module, LaunchMode::Uniform) else {
        return;
    };
    let mut sim = Simulation::new(&scene, g);
    let before = sim.backend.stats();
    let steps = 1000;
    sim.run(None, Some(steps)).unwrap();
    let after = sim.backend.stats();
    let (submissions, readbacks) = (
        after.submissions - before.submissions,
        after.readbacks - before.readbacks,
    );
    let launches = after.launches - before.launches;
    eprintln!(
        "{steps} steps: {launches} launches, {submissions} submissions, {readbacks} readbacks, \
         {:.1} µs host per step",
        (after.host_seconds - before.host_seconds) / steps as f64 * 1e6
    );
    // On a GPU the state is checked every `CHECK_EVERY_RUNNING_AHEAD` steps: each stretch,
    // its checked step and the check's readback copy are one submission; the run's reads of
    // x and v at its start and end and the loss's add one each (six).
    let every = softc::engine::CHECK_EVERY_RUNNING_AHEAD;
    assert!(
        submissions <= steps / every + 8,
        "{submissions} submissions"
    );
    assert!(readbacks <= steps / every + 8, "{readbacks} readbacks");
    // Three kernels a step (element, pressure, node) and a diagnostics launch per check;
    // the element and pressure kernels share a dispatch in the time loop.
    let dispatches = after.dispatches - before.dispatches;
    assert!(launches >= 3 * steps, "{launches} launches");
    assert!(
        dispatches <= 2 * steps + 3 * (steps / every + 1),
        "{dispatches} dispatches for {launches} launches"
    );
}

/// The step a run's report names: the number after its first "at step ".
fn step_named(report: &str) -> u64 {
    let after = report
        .split("at step ")
        .nth(1)
        .unwrap_or_else(|| panic!("{report}"));
    after
        .split(|c: char| !c.is_ascii_digit())
        .next()
        .and_then(|n| n.parse().ok())
        .unwrap_or_else(|| panic!("{report}"))
}

#[test]
fn a_blow_up_between_rare_gpu_checks_is_reported_at_its_step() {
    // dt above the stable step: the run inverts an element within the first hundred steps,
    // long before the GPU's first check after step 0 (step `CHECK_EVERY_RUNNING_AHEAD`). The
    // stretch since the last good state is run again step by step, so the report names the
    // same step as a run checked every 50 steps with the same arithmetic.
    let scene = scene("benchmark-1k.soft");
    let Some(g) = gpu(&scene.lowered.module, LaunchMode::Uniform) else {
        return;
    };
    let (dt, steps) = (Some(56e-6), Some(1500));
    let rare = Simulation::new(&scene, g).run(dt, steps).unwrap_err().0;
    let every_50 = OneByOne(gpu(&scene.lowered.module, LaunchMode::Uniform).unwrap());
    let often = Simulation::new(&scene, every_50)
        .run(dt, steps)
        .unwrap_err()
        .0;
    assert!(rare.contains("inverted at step"), "{rare}");
    let step = step_named(&rare);
    assert!(
        step > 1 && step < softc::engine::CHECK_EVERY_RUNNING_AHEAD,
        "{rare}"
    );
    assert_eq!(step, step_named(&often), "{rare}\n{often}");
}

#[test]
fn gradients_with_the_states_on_the_gpu_equal_those_kept_on_the_host() {
    let scene = scene("benchmark-1k.soft");
    let adjoint = &scene.lowered.adjoint.module;
    let Some(g) = gpu(adjoint, LaunchMode::Uniform) else {
        return;
    };
    let steps = 240;
    let options = GradOptions::default();
    let mut sim = Simulation::new(&scene, g);
    let before = sim.backend.stats();
    let on_device = sim.gradient(None, Some(steps), &options).unwrap();
    let after = sim.backend.stats();
    // Again on the same device (an optimization's next iteration): the state store and its
    // copy kernels are reused, the same bits come out.
    let again = sim.gradient(None, Some(steps), &options).unwrap();
    assert_eq!(again.schedule, on_device.schedule);
    for (name, g) in &on_device.gradients {
        assert_eq!(again.gradients[name].to_bits(), g.to_bits(), "{name}");
    }
    let submissions = after.submissions - before.submissions;
    eprintln!(
        "forward+backward of {steps} steps: {submissions} submissions, {} dispatches",
        after.dispatches - before.dispatches
    );
    // Both passes run as the time loop: a submission per state check (forward) or health
    // sample (every 50 reversed steps, backward), and
    // about twenty for the reads at the ends (the last state, the loss and its derivative,
    // the accumulated gradients), not one per step.
    assert!(
        submissions <= steps / softc::engine::CHECK_EVERY_RUNNING_AHEAD + steps / 50 + 20,
        "{submissions} submissions"
    );
    assert!(
        on_device.schedule.contains("on the device"),
        "{}",
        on_device.schedule
    );
    let host = Simulation::new(&scene, OneByOne(gpu(adjoint, LaunchMode::Uniform).unwrap()))
        .gradient(None, Some(steps), &options)
        .unwrap();
    assert_eq!(host.schedule, "auto: store_all");
    assert_eq!(
        on_device.summary.loss.map(f64::to_bits),
        host.summary.loss.map(f64::to_bits)
    );
    assert!(!on_device.gradients.is_empty());
    for (name, g) in &host.gradients {
        assert_eq!(
            on_device.gradients[name].to_bits(),
            g.to_bits(),
            "{name}: {} on the device, {g} through the host",
            on_device.gradients[name]
        );
    }
    assert_eq!(on_device.health, host.health);
    // A checkpointed schedule restores its snapshots from the device too: same gradient.
    let revolve = GradOptions {
        checkpoint: softc::engine::adjoint::Checkpointing::Revolve(5),
        ..GradOptions::default()
    };
    let g = gpu(adjoint, LaunchMode::Uniform).unwrap();
    let checkpointed = Simulation::new(&scene, g)
        .gradient(None, Some(steps), &revolve)
        .unwrap();
    assert!(checkpointed.recompute_ratio > 1.5);
    for (name, g) in &host.gradients {
        assert_eq!(
            checkpointed.gradients[name].to_bits(),
            g.to_bits(),
            "{name}"
        );
    }
}

/// The scene run on the GPU once per `p_peak` in `pressures`, each alone, then all as one batch
/// in lockstep: the single runs, the batch's results, and the batch's dispatch counts.
fn single_and_batched(
    scene: &Scene,
    pressures: &[f64],
    steps: u64,
) -> (
    Vec<RunSummary>,
    Vec<Result<RunSummary, RunError>>,
    softc::devices::gpu::DispatchStats,
) {
    let module = &scene.lowered.module;
    let single: Vec<_> = pressures
        .iter()
        .map(|&p| {
            let mut sim = Simulation::new(scene, gpu(module, LaunchMode::Uniform).unwrap());
            sim.uniforms.set_named("param.p_peak", p);
            sim.run(None, Some(steps)).unwrap()
        })
        .collect();
    let batch =
        softc::devices::gpu::GpuBatch::new(module, Precision::F32, None, pressures.len()).unwrap();
    let mut sims: Vec<_> = pressures
        .iter()
        .enumerate()
        .map(|(i, &p)| {
            let mut sim = Simulation::new(scene, batch.scene(i).unwrap());
            sim.uniforms.set_named("param.p_peak", p);
            sim
        })
        .collect();
    let before = batch.stats();
    let results = softc::engine::in_lockstep(&mut sims, |_, sim| sim.run(None, Some(steps)));
    let after = batch.stats();
    let stats = softc::devices::gpu::DispatchStats {
        launches: after.launches - before.launches,
        dispatches: after.dispatches - before.dispatches,
        submissions: after.submissions - before.submissions,
        ..Default::default()
    };
    (single, results, stats)
}

#[test]
fn a_batch_runs_its_scenes_matching_stretches_as_one() {
    let scene = scene("benchmark-1k.soft");
    let module = &scene.lowered.module;
    let Some(g) = gpu(module, LaunchMode::Uniform) else {
        return;
    };
    drop(g);
    let steps = 260;
    let (single, results, stats) = single_and_batched(&scene, &[1.0e3, 2.0e3, 3.0e3, 4.0e3], steps);
    let (launches, dispatches) = (stats.launches, stats.dispatches);
    eprintln!(
        "batch of 4, {steps} steps: {launches} launches in {dispatches} dispatches, {} submissions",
        stats.submissions
    );
    // Each stretch of the four scenes is one batched stretch: a dispatch per launch of all.
    assert!(
        dispatches * 4 <= launches + 8,
        "{launches} launches, {dispatches} dispatches"
    );
    for (i, (b, s)) in results.into_iter().zip(&single).enumerate() {
        let b = b.unwrap();
        assert!(
            same_bits(&b.x, &s.x) && same_bits(&b.v, &s.v),
            "scene {i}: the batch changed its results"
        );
    }
}

/// Quadratic (10-node) elements in a GPU batch: each scene's result is the bits of its single
/// run.
#[test]
fn a_batch_of_quadratic_scenes_gives_the_bits_of_single_runs() {
    let text = common::script_at_order("examples/benchmark-1k.soft", 2)
        // The quadratic mesh's stable step is 17 µs (the linear one's above 40 µs).
        .replace("dt = 40 us", "dt = 10 us");
    let path =
        std::env::temp_dir().join(format!("softc-gpu-quad-batch-{}.soft", std::process::id()));
    std::fs::write(&path, text).unwrap();
    let scene = Scene::load(&path, &[]).unwrap();
    std::fs::remove_file(&path).ok();
    assert_eq!(scene.order(), softc_compiler::ir::ElementOrder::Quadratic);
    let module = &scene.lowered.module;
    let Some(g) = gpu(module, LaunchMode::Uniform) else {
        return;
    };
    drop(g);
    let (single, results, _) = single_and_batched(&scene, &[2.0e3, 5.0e3], 60);
    for (i, (b, s)) in results.into_iter().zip(&single).enumerate() {
        let b = b.unwrap();
        assert!(b.x.iter().zip(&scene.mesh.nodes).any(|(x, x0)| x != x0));
        assert!(
            same_bits(&b.x, &s.x) && same_bits(&b.v, &s.v),
            "scene {i}: the batch changed its results"
        );
    }
}

/// A run's JSON with its timings left out (the lines that name seconds or speeds).
fn json_without_timings(stdout: &[u8]) -> String {
    String::from_utf8_lossy(stdout)
        .lines()
        .filter(|l| {
            !["seconds", "steps_per", "_us", "_s\""]
                .iter()
                .any(|k| l.contains(k))
        })
        .collect::<Vec<_>>()
        .join("\n")
}

/// `softc run examples/benchmark-1k.soft --backend gpu --steps N [extra]` with the GPU
/// environment variable `var` set to `value` (or unset); `None` (with a note) when this machine
/// has no adapter, which fails the test under `CI=true`.
fn run_1k_on_gpu(
    steps: &str,
    extra: &[&str],
    var: &str,
    value: Option<&str>,
) -> Option<std::process::Output> {
    let mut cmd = std::process::Command::new(env!("CARGO_BIN_EXE_softc"));
    cmd.current_dir(root())
        .args([
            "run",
            "examples/benchmark-1k.soft",
            "--backend",
            "gpu",
            "--steps",
            steps,
        ])
        .args(extra);
    match value {
        Some(v) => cmd.env(var, v),
        None => cmd.env_remove(var),
    };
    let out = cmd.output().unwrap();
    let stderr = String::from_utf8_lossy(&out.stderr);
    if !out.status.success() && stderr.contains("no GPU adapter found") {
        assert!(
            std::env::var("CI").as_deref() != Ok("true"),
            "CI=true but no GPU adapter: {stderr}"
        );
        eprintln!("note: GPU test skipped: {stderr}");
        return None;
    }
    Some(out)
}

#[test]
fn workgroup_sizes_give_the_same_bits_forward_and_backward() {
    let run = |wg: Option<&str>| run_1k_on_gpu("300", &["--grad"], "SOFTC_GPU_WG", wg);
    let Some(default) = run(None) else {
        return;
    };
    let stderr = String::from_utf8_lossy(&default.stderr);
    assert!(default.status.success(), "{stderr}");
    let expected = json_without_timings(&default.stdout);
    assert!(expected.contains("\"gradients\""), "{expected}");
    for wg in ["32", "256"] {
        let out = run(Some(wg)).unwrap();
        assert!(
            out.status.success(),
            "{}",
            String::from_utf8_lossy(&out.stderr)
        );
        assert_eq!(
            json_without_timings(&out.stdout),
            expected,
            "SOFTC_GPU_WG={wg}"
        );
    }
    let bad = run(Some("100")).unwrap();
    assert!(!bad.status.success(), "a bad size is refused");
    assert!(String::from_utf8_lossy(&bad.stderr).contains("SOFTC_GPU_WG=100: give a power of two"));
}

#[test]
fn a_profiled_run_reports_each_kernels_gpu_time() {
    let Some(out) = run_1k_on_gpu("120", &[], "SOFTC_GPU_PROFILE", Some("1")) else {
        return;
    };
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(out.status.success(), "{stderr}");
    // The same answer as an unprofiled run: only the timing changes.
    let plain = run_1k_on_gpu("120", &[], "SOFTC_GPU_PROFILE", None).unwrap();
    assert_eq!(
        json_without_timings(&out.stdout),
        json_without_timings(&plain.stdout)
    );
    let Some(report) = stderr.split("GPU time per kernel").nth(1) else {
        // An adapter without timestamp queries has nothing to report.
        eprintln!("note: no timestamp queries on this adapter");
        return;
    };
    // Every step's kernels, with their dispatch counts: the fused element and pressure
    // kernels and the node kernel run once per step.
    let dispatches = |name: &str| -> u64 {
        report
            .lines()
            .find(|l| l.trim_start().starts_with(name))
            .and_then(|l| l.split_whitespace().nth(1))
            .and_then(|n| n.parse().ok())
            .unwrap_or(0)
    };
    assert!(dispatches("integrate") >= 100, "{report}");
    assert!(
        dispatches("softc_fused_fem_rubber_pressure_cavity") + dispatches("fem_rubber") >= 100,
        "{report}"
    );
    let shares: f64 = report
        .lines()
        .filter_map(|l| l.trim_end().strip_suffix('%'))
        .filter_map(|l| l.split_whitespace().last()?.parse::<f64>().ok())
        .sum();
    assert!(
        (shares - 100.0).abs() < 1.0,
        "shares add up to {shares}: {report}"
    );
}
