//! `--backend` and `--precision` to a device: the one place that maps them. [`open`] gives the
//! devices of a run (one, or a batch of scenes sharing a GPU), [`Device`] any of them as one
//! type for code that runs whichever the flags name, and [`precision`] the kernels' precision.

use super::cpu::Cpu;
use super::gpu::{AdapterDesc, DispatchStats, Gpu, GpuBatch, GpuScene};
use super::interp::Interpreter;
use super::{Backend, Launch, Lockstep, PendingRead, Uniforms};
use crate::engine::scene::Scene;
use clap::ValueEnum;
use softc_compiler::back::Precision;
use softc_compiler::ir::{BufferId, Module};
use std::cell::Cell;
use std::ops::Range;

#[derive(Copy, Clone, Debug, PartialEq, Eq, ValueEnum)]
pub enum PrecisionChoice {
    F32,
    F64,
}

#[derive(Copy, Clone, Debug, PartialEq, Eq, ValueEnum)]
pub enum BackendChoice {
    /// Native code through Cranelift, multi-threaded, deterministic.
    Cpu,
    /// The kernel-IR interpreter: the reference semantics of the kernels, slow.
    Interp,
    /// The plain-Rust f64 reference simulator (the test oracle).
    Reference,
    /// WGSL kernels on a GPU through wgpu (Vulkan, Metal, DX12; lavapipe without a GPU).
    Gpu,
}

impl From<PrecisionChoice> for Precision {
    fn from(p: PrecisionChoice) -> Self {
        match p {
            PrecisionChoice::F32 => Precision::F32,
            PrecisionChoice::F64 => Precision::F64,
        }
    }
}

/// The kernels' precision: `flag` (`--precision`), else the script's `precision` `setting`,
/// else the backend's default: f32 on the GPU, f64 elsewhere.
pub fn precision(
    backend: BackendChoice,
    flag: Option<Precision>,
    setting: Option<Precision>,
) -> Precision {
    let default = match backend {
        BackendChoice::Gpu => Precision::F32,
        _ => Precision::F64,
    };
    flag.or(setting).unwrap_or(default)
}

/// The device a run asks for (`--backend`, `--precision`, `--adapter`, `--threads`).
#[derive(Clone, Debug)]
pub struct DeviceChoice<'a> {
    pub backend: BackendChoice,
    /// `--precision`; `None`: the script's setting, else the backend's default.
    pub precision: Option<Precision>,
    /// The GPU adapter: a case-insensitive part of its name (see [`Gpu::new`]).
    pub adapter: Option<&'a str>,
    /// Worker threads of the cpu backend (`None`: its own choice).
    pub threads: Option<usize>,
}

/// Open the device `choice` names for `members` scenes of `scene` that run `module` (the
/// forward kernels, or the adjoint module for gradients); [`Devices::make`] gives each scene
/// its backend. Several GPU scenes share one batch (each launch one dispatch for all of them);
/// several cpu scenes, which run on threads of their own, get one kernel thread each unless
/// `threads` says otherwise. The reference oracle is not a device: it runs on its own
/// ([`crate::reference`]).
pub fn open<'m>(
    choice: &DeviceChoice,
    scene: &Scene,
    module: &'m Module,
    members: usize,
) -> Result<Devices<'m>, String> {
    let precision = precision(
        choice.backend,
        choice.precision,
        scene.resolved.sim.precision,
    );
    let kind = match choice.backend {
        BackendChoice::Reference => {
            return Err("the reference oracle is not a device (it runs on its own)".into());
        }
        // The interpreter computes in f64 whatever the precision asked for.
        BackendChoice::Interp => {
            return Ok(Devices {
                precision: Precision::F64,
                kind: Kind::Interp(module),
                made: Cell::new(0),
            });
        }
        BackendChoice::Cpu => Kind::Cpu {
            module,
            // Scenes of a batch run on their own threads: one kernel thread each.
            threads: choice.threads.or((members > 1).then_some(1)),
        },
        BackendChoice::Gpu if members > 1 => {
            Kind::Batch(GpuBatch::new(module, precision, choice.adapter, members)?)
        }
        BackendChoice::Gpu => Kind::Gpu {
            module,
            adapter: choice.adapter.map(str::to_string),
        },
    };
    Ok(Devices {
        precision,
        kind,
        made: Cell::new(0),
    })
}

/// The devices [`open`] opened: a backend per scene from [`Devices::make`].
pub struct Devices<'m> {
    /// The kernels' precision.
    pub precision: Precision,
    kind: Kind<'m>,
    /// Backends made so far (a batch gives its scenes in turn).
    made: Cell<usize>,
}

enum Kind<'m> {
    Interp(&'m Module),
    Cpu {
        module: &'m Module,
        threads: Option<usize>,
    },
    Gpu {
        module: &'m Module,
        adapter: Option<String>,
    },
    Batch(GpuBatch),
}

impl Devices<'_> {
    /// The next scene's backend: the kernels compiled afresh for each (interp, cpu, gpu), or
    /// the batch's next scene.
    pub fn make(&self) -> Result<Device, String> {
        let n = self.made.get();
        self.made.set(n + 1);
        match &self.kind {
            Kind::Interp(module) => Ok(Device::Interp(Box::new(Interpreter::new(module)))),
            Kind::Cpu { module, threads } => Cpu::new(module, self.precision, *threads)
                .map(|cpu| Device::Cpu(Box::new(cpu)))
                .map_err(|e| format!("the kernels do not compile: {e}")),
            Kind::Gpu { module, adapter } => Gpu::new(module, self.precision, adapter.as_deref())
                .map(|gpu| Device::Gpu(Box::new(gpu))),
            Kind::Batch(batch) => batch.scene(n).map(Device::GpuScene),
        }
    }

    /// The adapter of a GPU batch (a single GPU's is [`Device::adapter`]).
    pub fn adapter(&self) -> Option<AdapterDesc> {
        match &self.kind {
            Kind::Batch(batch) => Some(batch.adapter()),
            _ => None,
        }
    }
}

/// A backend of whichever device [`open`] opened.
pub enum Device {
    Interp(Box<Interpreter>),
    Cpu(Box<Cpu>),
    Gpu(Box<Gpu>),
    /// One scene of a GPU batch.
    GpuScene(GpuScene),
}

impl Device {
    /// The adapter of a single GPU.
    pub fn adapter(&self) -> Option<AdapterDesc> {
        match self {
            Device::Gpu(gpu) => Some(gpu.adapter()),
            _ => None,
        }
    }

    /// What a GPU device did so far (launches, submissions, host and GPU time); `None` off
    /// the GPU.
    pub fn gpu_stats(&self) -> Option<DispatchStats> {
        match self {
            Device::Gpu(gpu) => Some(gpu.stats()),
            Device::GpuScene(scene) => Some(scene.stats()),
            _ => None,
        }
    }

    /// Time a GPU device's compute passes with timestamp queries (see
    /// [`Gpu::enable_timing`]); `false` off the GPU or where the adapter cannot.
    pub fn enable_gpu_timing(&self) -> bool {
        match self {
            Device::Gpu(gpu) => gpu.enable_timing(),
            Device::GpuScene(scene) => scene.enable_timing(),
            _ => false,
        }
    }

    fn inner(&self) -> &dyn Backend {
        match self {
            Device::Interp(d) => &**d,
            Device::Cpu(d) => &**d,
            Device::Gpu(d) => &**d,
            Device::GpuScene(d) => d,
        }
    }

    fn inner_mut(&mut self) -> &mut dyn Backend {
        match self {
            Device::Interp(d) => &mut **d,
            Device::Cpu(d) => &mut **d,
            Device::Gpu(d) => &mut **d,
            Device::GpuScene(d) => d,
        }
    }
}

impl Backend for Device {
    fn name(&self) -> &'static str {
        self.inner().name()
    }

    fn prepare(&mut self, scene: &Scene) -> Result<(), String> {
        self.inner_mut().prepare(scene)
    }

    fn set(&mut self, b: BufferId, data: &[f64]) {
        self.inner_mut().set(b, data)
    }

    fn get(&self, b: BufferId) -> Vec<f64> {
        self.inner().get(b)
    }

    fn swap(&mut self, a: BufferId, b: BufferId) {
        self.inner_mut().swap(a, b)
    }

    fn run(&mut self, k: usize, range: Range<usize>, uniforms: &Uniforms) -> Result<(), String> {
        self.inner_mut().run(k, range, uniforms)
    }

    fn precision(&self) -> Precision {
        self.inner().precision()
    }

    fn device_error(&self) -> Option<String> {
        self.inner().device_error()
    }

    fn lockstep(&self) -> Lockstep {
        self.inner().lockstep()
    }

    fn runs_ahead(&self) -> bool {
        self.inner().runs_ahead()
    }

    fn read_later(&mut self, bufs: &[BufferId]) -> PendingRead {
        self.inner_mut().read_later(bufs)
    }

    fn collect(&mut self, read: PendingRead) -> Vec<Vec<f64>> {
        self.inner_mut().collect(read)
    }

    fn device_states(&mut self, slots: usize, len: usize) -> Result<Option<u64>, String> {
        self.inner_mut().device_states(slots, len)
    }

    fn store_state(&mut self, slot: usize, x: BufferId, v: BufferId) -> Result<(), String> {
        self.inner_mut().store_state(slot, x, v)
    }

    fn restore_state(&mut self, slot: usize, x: BufferId, v: BufferId) -> Result<(), String> {
        self.inner_mut().restore_state(slot, x, v)
    }

    fn get_into(&self, b: BufferId, out: crate::devices::HostSliceMut<'_>) {
        self.inner().get_into(b, out)
    }

    fn set_from(&mut self, b: BufferId, src: crate::devices::HostSlice<'_>) {
        self.inner_mut().set_from(b, src)
    }

    fn run_stepped(&mut self, stepped: &crate::devices::Stepped<'_>) -> Result<bool, String> {
        self.inner_mut().run_stepped(stepped)
    }

    fn run_steps(
        &mut self,
        launches: &[Launch],
        swaps: &[(BufferId, BufferId)],
        first: u64,
        n: u64,
        dt: f64,
        uniforms: &Uniforms,
    ) -> Result<bool, String> {
        self.inner_mut()
            .run_steps(launches, swaps, first, n, dt, uniforms)
    }
}
