//! The GPU device: a scene's kernels as WGSL ([`softc_compiler::back::wgsl`]) run by wgpu on
//! any adapter (Vulkan, Metal, DX12; Mesa's lavapipe on machines without a GPU).
//!
//! On a real GPU a step's kernels take a few microseconds each while a queue submission and
//! a wait cost ~140 µs (an H100), so the host must stay out of the step (issue 28):
//! - The time loop ([`Backend::run_steps`], [`Backend::run_stepped`]): a stretch of steps
//!   is recorded at once (`steps.rs`) — bind groups resolved once per buffer parity, a launch
//!   block per step only for kernels that read `t`, a step's independent kernels fused into
//!   one dispatch ([`wgsl::emit_fused`]), up to 2,048 steps per submission.
//! - Launches outside a stretch ([`Backend::run`], [`Backend::set`]) are recorded
//!   operations, turned into dispatches at the next submission (`record.rs`); launch blocks
//!   are uniform blocks at dynamic offsets of one buffer.
//! - Readbacks need not wait ([`Backend::read_later`], `transfer.rs`): the copy goes into
//!   the submission of the work before it, and the host collects it later, waiting only for
//!   that submission while the device runs on. The engine's state checks and the adjoint's
//!   health samples read this way, so each 50-step stretch is one submission.
//! - The adjoint's states stay in device memory ([`Backend::device_states`]): a copy kernel
//!   in the step's compute pass stores or restores a state.
//!
//! [`Gpu::stats`] counts launches, dispatches, submissions and readbacks, and the host and
//! (with timestamp queries) GPU time they took; `softc bench` reports them per step.
//!
//! Batches: [`GpuBatch`] holds several scenes of one mesh in the same buffers (scene after
//! scene) and runs the kernels of the batched WGSL ([`wgsl::emit_batched`]). Each scene is
//! driven by its own [`GpuScene`] (one simulation each, usually on its own thread); the scenes'
//! recorded operations are merged at submission: the next launches of the scenes that run the
//! same kernel on the same buffers become one dispatch, one workgroup row per scene. Scenes in
//! lockstep ([`Backend::lockstep`]) wait for each other at every readback, so the whole batch
//! shares each submission and each readback; a scene that runs ahead or alone is still
//! correct (each scene's operations stay in its own order), only less merged.
//!
//! Results match the CPU backend up to floating-point rounding: f32 kernels on the GPU round
//! differently from Cranelift's (fused or reordered operations are the driver's choice, and
//! `exp`/`log`/`pow` are the driver's), f64 kernels use the software transcendental functions
//! of the WGSL backend.

use super::{Backend, Launch, Lockstep, PendingRead, StateCopy, Stepped, Uniforms};
use crate::engine::scene::{Csr, Scene};
use softc_compiler::back::Precision;
use softc_compiler::back::wgsl::{
    self, Binding, LaunchMode, RowLayout, TopoArray, WgslKernel, WgslModule,
};
use softc_compiler::ir::{BufferId, Domain, Module};
use std::cell::RefCell;
use std::collections::{HashMap, VecDeque};
use std::ops::Range;
use std::sync::{Arc, Condvar, Mutex, MutexGuard};

mod record;
mod setup;
mod steps;
mod transfer;

/// Operations recorded before a submission is forced (bounds the uniform staging area).
pub const MAX_PENDING: usize = 2048;

/// What to install when no adapter is found.
pub const NO_ADAPTER_HINT: &str = "no GPU adapter found: install a Vulkan driver for your GPU, or Mesa's software \
     Vulkan driver for a CPU-only machine (Debian/Ubuntu: `apt-get install mesa-vulkan-drivers \
     libvulkan1`), or use `--backend cpu`";

/// An adapter as `softc` shows it.
#[derive(Clone, Debug)]
pub struct AdapterDesc {
    pub name: String,
    pub backend: String,
    pub device_type: String,
    pub shader_f64: bool,
}

impl std::fmt::Display for AdapterDesc {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "{} ({}, {}{})",
            self.name,
            self.backend,
            self.device_type,
            if self.shader_f64 { ", f64" } else { "" }
        )
    }
}

fn describe(a: &wgpu::Adapter) -> AdapterDesc {
    let info = a.get_info();
    AdapterDesc {
        name: info.name.clone(),
        backend: format!("{:?}", info.backend),
        device_type: format!("{:?}", info.device_type),
        shader_f64: a.features().contains(wgpu::Features::SHADER_F64),
    }
}

fn instance() -> wgpu::Instance {
    wgpu::Instance::new(wgpu::InstanceDescriptor::new_without_display_handle())
}

/// Every adapter wgpu finds on this machine.
pub fn adapters() -> Vec<AdapterDesc> {
    let inst = instance();
    pollster::block_on(inst.enumerate_adapters(wgpu::Backends::all()))
        .iter()
        .map(describe)
        .collect()
}

/// Preference among adapters when none is named: real GPUs first, then Vulkan.
fn rank(a: &wgpu::Adapter) -> (u8, u8) {
    let info = a.get_info();
    let t = match info.device_type {
        wgpu::DeviceType::DiscreteGpu => 0,
        wgpu::DeviceType::IntegratedGpu => 1,
        wgpu::DeviceType::VirtualGpu => 2,
        wgpu::DeviceType::Cpu => 3,
        wgpu::DeviceType::Other => 4,
    };
    let b = match info.backend {
        wgpu::Backend::Vulkan => 0,
        wgpu::Backend::Metal => 1,
        wgpu::Backend::Dx12 => 2,
        _ => 3,
    };
    (t, b)
}

/// One kernel's pipeline.
struct Pipeline {
    pipeline: wgpu::ComputePipeline,
    layout: wgpu::BindGroupLayout,
}

/// An operation one scene recorded, executed in its order at the next submission.
enum Op {
    Run {
        kernel: usize,
        /// Physical buffers of the kernel's buffer bindings (the bind group's cache key).
        key: Vec<usize>,
        begin: u32,
        count: u32,
        /// The launch block's uniforms, in [`wgsl::WgslKernel::uniforms`] order.
        values: Vec<f64>,
    },
    Set {
        phys: usize,
        bytes: Vec<u8>,
    },
    /// A stretch of the time loop ([`Backend::run_steps`]); the scenes' stretches that
    /// match become one batched stretch.
    Steps(Box<StepsOp>),
}

/// A scene's recorded stretch of steps: its plan, its buffer slots at the start and its
/// uniforms.
#[derive(Clone)]
struct StepsOp {
    launches: Vec<Launch>,
    swaps: Vec<(BufferId, BufferId)>,
    slot: Vec<usize>,
    first: u64,
    n: u64,
    dt: f64,
    uniforms: Uniforms,
}

impl StepsOp {
    /// Stretches that run as one batched stretch: the same launches, slots and steps.
    fn matches(&self, other: &StepsOp) -> bool {
        self.launches == other.launches
            && self.swaps == other.swaps
            && self.slot == other.slot
            && (self.first, self.n, self.dt.to_bits()) == (other.first, other.n, other.dt.to_bits())
    }
}

/// Kernels one dispatch runs at most ([`wgsl::emit_fused`]).
const MAX_PARTS: usize = 4;

/// A dispatch of one submission: a kernel (or fused kernels, or a state copy) over one or
/// more scenes.
#[derive(Clone, Copy)]
struct Dispatch {
    /// Its pipeline in [`Core::pipelines`].
    kernel: usize,
    /// Its bind group in [`Core::groups`].
    group: usize,
    /// Where its launch blocks are: the row of the launch table ([`LaunchMode::Table`], set as
    /// the immediate) or byte offsets in the uniform buffer (one per part of a fused
    /// dispatch), or a state copy's slot offset.
    args: [u32; MAX_PARTS],
    parts: u8,
    groups: (u32, u32, u32),
}

impl Dispatch {
    fn one(kernel: usize, group: usize, arg: u32, groups: (u32, u32, u32)) -> Self {
        Dispatch {
            kernel,
            group,
            args: [arg, 0, 0, 0],
            parts: 1,
            groups,
        }
    }
}

/// What the device did: how well a batch merges, how many times the host submitted and
/// waited, and the host time recording and submitting took.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct DispatchStats {
    /// Kernel launches the scenes recorded.
    pub launches: u64,
    /// Dispatches submitted for them (one per launch unbatched; as few as launches / scenes
    /// when a batch runs in lockstep).
    pub dispatches: u64,
    /// Queue submissions.
    pub submissions: u64,
    /// Readbacks (each waits for the GPU to finish what was submitted).
    pub readbacks: u64,
    /// Host seconds spent recording launches and steps into command buffers (readbacks'
    /// waits and the queue submissions themselves excluded).
    pub host_seconds: f64,
    /// Host seconds inside the driver's queue submissions (a software driver such as
    /// lavapipe may run the kernels there).
    pub submit_seconds: f64,
    /// GPU seconds of the submitted compute passes, from timestamp queries, when
    /// [`Gpu::enable_timing`] asked for them and the adapter has them.
    pub gpu_seconds: Option<f64>,
}

/// Steps of a time loop recorded into one submission at most (thousands: a submission costs
/// ~140 µs on an H100, a dispatch ~3.5 µs).
const STEPS_PER_SUBMISSION: u64 = 2048;

/// Launch-block bytes held at least (grows as needed).
const MIN_LAUNCH_BYTES: u64 = 256 << 10;

/// States of the adjoint's checkpoint store kept in the device's memory at most, by default
/// (`SOFTC_GPU_STATE_BYTES` sets another limit): 8 GiB fits the GPUs this is for with room
/// to spare; a device that cannot allocate them keeps the states on the host.
pub const DEVICE_STATE_BYTES: u64 = 8 << 30;

/// The bytes of states the device may keep ([`DEVICE_STATE_BYTES`] or
/// `SOFTC_GPU_STATE_BYTES`).
pub fn device_state_limit() -> u64 {
    std::env::var("SOFTC_GPU_STATE_BYTES")
        .ok()
        .and_then(|v| v.parse::<u64>().ok())
        .unwrap_or(DEVICE_STATE_BYTES)
}

/// The adjoint's states in device memory: `slots` slots of `slot_bytes` (x then v, padded
/// to the storage offset alignment) in chunks of `per_chunk` slots, and the copy kernels'
/// pipelines.
struct DeviceStates {
    chunks: Vec<wgpu::Buffer>,
    per_chunk: usize,
    slot_bytes: u64,
    slots: usize,
    /// Values of x (and of v) of one scene.
    len: usize,
    /// Pipelines of the copies into and out of a slot.
    store: usize,
    restore: usize,
}

/// A readback under way.
struct InFlight {
    buffer: wgpu::Buffer,
    total: u64,
    /// (offset, bytes) of each buffer's values in it.
    spans: Vec<(u64, u64, RowLayout)>,
    index: wgpu::SubmissionIndex,
    mapped: std::sync::mpsc::Receiver<Result<(), wgpu::BufferAsyncError>>,
}

/// GPU time of the submitted compute passes from timestamp queries: a pair of queries per
/// submission, resolved in its command buffer, read back when the pairs run out or the
/// figures are asked for.
struct Timing {
    set: wgpu::QuerySet,
    resolve: wgpu::Buffer,
    read: wgpu::Buffer,
    pairs: u32,
    used: u32,
    /// Nanoseconds per tick.
    period: f64,
    seconds: f64,
    /// With `SOFTC_GPU_PROFILE=1`: the pipeline each used pair timed (one dispatch per pass),
    /// and per pipeline its GPU seconds and dispatches so far.
    labels: Vec<Option<usize>>,
    per_pipeline: std::collections::BTreeMap<usize, (f64, u64)>,
}

/// The device, the compiled kernels, the buffers of every scene and the recorded work.
struct Core {
    device: wgpu::Device,
    queue: wgpu::Queue,
    adapter: AdapterDesc,
    module: WgslModule,
    pipelines: Vec<Pipeline>,
    /// Bytes between launch blocks in the uniform buffer.
    align: u32,
    buffer_count: usize,
    /// `(domain, width, name)` of each buffer of the module.
    layout: Vec<(Domain, u32, String)>,
    errors: Arc<Mutex<Vec<String>>>,
    /// Scenes the buffers hold (1 for an unbatched module).
    scenes: usize,
    /// Physical buffers, each holding `scenes × gpu_lens[i]` values: `lens[i]` values per
    /// scene, laid out by `rows[i]` (3-vectors as `vec4`s).
    buffers: Vec<wgpu::Buffer>,
    lens: Vec<usize>,
    gpu_lens: Vec<usize>,
    rows: Vec<RowLayout>,
    topo: Vec<wgpu::Buffer>,
    /// Entities per domain of the prepared mesh: element, triangle, node.
    counts: [usize; 3],
    /// The launch blocks of the recorded dispatches: a uniform buffer bound at dynamic offsets
    /// ([`LaunchMode::Uniform`]) or the storage launch table ([`LaunchMode::Table`]).
    launch_buffer: Option<wgpu::Buffer>,
    /// Its contents for the next submission.
    staging: Vec<u8>,
    /// Each scene's recorded operations.
    queues: Vec<VecDeque<Op>>,
    recorded: usize,
    /// Dispatches made from recorded operations and steps, not yet submitted (in order).
    pending: Vec<Dispatch>,
    /// Bind groups by (kernel, physical buffers bound), as indices into `groups`.
    bind_groups: HashMap<(usize, Vec<usize>), usize>,
    groups: Vec<wgpu::BindGroup>,
    timing: Option<Timing>,
    /// Readbacks under way, by ticket, and mapped buffers free for the next.
    in_flight: HashMap<u64, InFlight>,
    next_ticket: u64,
    spare_readbacks: Vec<wgpu::Buffer>,
    /// The adjoint's states kept on the device.
    states: Option<DeviceStates>,
    /// The kernel IR (fused entry points are emitted from it on demand).
    ir: Module,
    /// Fuse independent kernels of a step into one dispatch (`SOFTC_GPU_FUSE=0`: never).
    fuse: bool,
    /// Invocations per workgroup of every pipeline (the kernels' `softc_wg` override).
    wg_size: u32,
    /// `SOFTC_GPU_PROFILE=1`: with timing on, each dispatch in a pass of its own with its own
    /// timestamps, and the GPU time per kernel printed when the device closes.
    profile: bool,
    /// Fused entry points' pipelines by their (sorted) kernels, and their entry points.
    fused: HashMap<Vec<usize>, usize>,
    fused_kernels: HashMap<usize, WgslKernel>,
    stats: DispatchStats,
    /// Lockstep: scenes in the group, the buffer each waiting scene wants, served readbacks.
    active: Vec<bool>,
    waiting: Vec<Option<usize>>,
    served: Vec<Option<Result<Vec<f64>, String>>>,
}

fn round_up(x: u64, a: u64) -> u64 {
    x.div_ceil(a) * a
}

fn domain_count(counts: &[usize; 3], d: Domain) -> usize {
    match d {
        Domain::Element => counts[0],
        Domain::Triangle => counts[1],
        Domain::Node => counts[2],
        Domain::Single => 1,
    }
}

/// Runs a scene's kernels on a GPU through wgpu.
pub struct Gpu {
    core: RefCell<Core>,
    /// `slot[b]` is the physical buffer buffer `b` names now (swaps permute it).
    slot: Vec<usize>,
}

impl Gpu {
    /// Compile `module` for an adapter: the first one whose name (or backend) contains
    /// `adapter` (case-insensitive), else the preferred one (discrete, integrated, virtual,
    /// then software; Vulkan first). f64 needs an adapter with `SHADER_F64`.
    pub fn new(
        module: &Module,
        precision: Precision,
        adapter: Option<&str>,
    ) -> Result<Self, String> {
        Ok(Gpu {
            core: RefCell::new(Core::open(module, precision, adapter, None, None)?),
            slot: Vec::new(),
        })
    }

    /// As [`Gpu::new`], with the launch blocks where `launch` says ([`LaunchMode::Table`]
    /// needs an adapter with immediates).
    pub fn with_launch_mode(
        module: &Module,
        precision: Precision,
        adapter: Option<&str>,
        launch: LaunchMode,
    ) -> Result<Self, String> {
        Ok(Gpu {
            core: RefCell::new(Core::open(module, precision, adapter, None, Some(launch))?),
            slot: Vec::new(),
        })
    }

    /// The adapter in use.
    pub fn adapter(&self) -> AdapterDesc {
        self.core.borrow().adapter.clone()
    }

    pub fn precision(&self) -> Precision {
        self.core.borrow().module.precision
    }

    /// Launches, dispatches, submissions, readbacks and host (and GPU) time so far.
    pub fn stats(&self) -> DispatchStats {
        self.core.borrow_mut().stats_now()
    }

    /// Time the compute passes on the GPU from now on ([`DispatchStats::gpu_seconds`]), if
    /// the adapter has timestamp queries; `false` if not.
    pub fn enable_timing(&self) -> bool {
        self.core.borrow_mut().enable_timing()
    }

    /// Fuse a step's independent kernels into one dispatch (on by default; off with
    /// `SOFTC_GPU_FUSE=0`): the same bits either way, a dispatch fewer per fused kernel.
    pub fn set_fusion(&self, on: bool) {
        self.core.borrow_mut().fuse = on;
    }

    /// Where the kernels find their launch blocks on this adapter.
    pub fn launch_mode(&self) -> LaunchMode {
        self.core.borrow().module.launch
    }

    /// The WGSL source the kernels run.
    pub fn wgsl(&self) -> String {
        self.core.borrow().module.source.clone()
    }

    /// Submit the recorded work (without waiting for it).
    pub fn flush(&self) -> Result<(), String> {
        let mut core = self.core.borrow_mut();
        core.flush();
        match core.take_error() {
            Some(e) => Err(e),
            None => Ok(()),
        }
    }

    /// Allocate zeroed buffers for a mesh of `n_nodes` nodes, these tets and chamber triangles,
    /// and upload the connectivity. [`Backend::prepare`] does this for a scene.
    pub fn prepare_mesh(
        &mut self,
        n_nodes: usize,
        tets: &[[u32; 4]],
        tris: &[[u32; 3]],
    ) -> Result<(), String> {
        if let Some(&n) = tets
            .iter()
            .flatten()
            .chain(tris.iter().flatten())
            .find(|&&n| n as usize >= n_nodes)
        {
            return Err(format!("connectivity names node {n} of {n_nodes}"));
        }
        let ne = Csr::build(n_nodes, tets.iter());
        let nt = Csr::build(n_nodes, tris.iter());
        let core = self.core.get_mut();
        let elem: Vec<u32> = tets.iter().flatten().copied().collect();
        let tri: Vec<u32> = tris.iter().flatten().copied().collect();
        core.allocate(n_nodes, (&elem, tets.len()), (&tri, tris.len()), &ne, &nt)?;
        self.slot = (0..core.buffer_count).collect();
        Ok(())
    }
}

impl Backend for Gpu {
    fn precision(&self) -> Precision {
        self.core.borrow().module.precision
    }

    fn name(&self) -> &'static str {
        "gpu"
    }

    fn prepare(&mut self, scene: &Scene) -> Result<(), String> {
        let core = self.core.get_mut();
        core.check_scene(scene)?;
        core.allocate(
            scene.mesh.nodes.len(),
            (&scene.elem_conn(), scene.mesh.tets.len()),
            (&scene.tri_conn(), scene.tris.len()),
            &scene.node_elements,
            &scene.node_tris,
        )?;
        self.slot = (0..core.buffer_count).collect();
        Ok(())
    }

    fn set(&mut self, b: BufferId, data: &[f64]) {
        let phys = self.slot[b.0 as usize];
        self.core.get_mut().record_set(0, phys, data);
    }

    fn get(&self, b: BufferId) -> Vec<f64> {
        // An unknown buffer fails in the readback, like any other failed readback.
        let phys = self.slot.get(b.0 as usize).copied().unwrap_or(b.0 as usize);
        let mut core = self.core.borrow_mut();
        let r = core.read(&[(phys, 0)]).map(|mut v| v.remove(0));
        core.values_or_nan(phys, r)
    }

    fn device_error(&self) -> Option<String> {
        self.core.borrow().device_error()
    }

    fn swap(&mut self, a: BufferId, b: BufferId) {
        self.slot.swap(a.0 as usize, b.0 as usize);
    }

    fn run(&mut self, k: usize, range: Range<usize>, u: &Uniforms) -> Result<(), String> {
        self.core.get_mut().record_run(0, &self.slot, k, range, u)
    }

    fn runs_ahead(&self) -> bool {
        true
    }

    fn read_later(&mut self, bufs: &[BufferId]) -> PendingRead {
        let requests: Vec<(usize, usize)> = bufs
            .iter()
            .map(|b| {
                (
                    self.slot.get(b.0 as usize).copied().unwrap_or(b.0 as usize),
                    0,
                )
            })
            .collect();
        let core = self.core.get_mut();
        let lens = requests
            .iter()
            .map(|&(p, _)| core.lens.get(p).copied().unwrap_or(0))
            .collect();
        match core.read_later(&requests) {
            Ok(ticket) => PendingRead::Ticket(ticket, lens),
            Err(e) => {
                if let Ok(mut errors) = core.errors.lock() {
                    errors.push(e);
                }
                PendingRead::Done(lens.iter().map(|&n| vec![f64::NAN; n]).collect())
            }
        }
    }

    fn collect(&mut self, read: PendingRead) -> Vec<Vec<f64>> {
        match read {
            PendingRead::Done(v) => v,
            PendingRead::Ticket(ticket, lens) => {
                let core = self.core.get_mut();
                core.collect(ticket).unwrap_or_else(|e| {
                    if let Ok(mut errors) = core.errors.lock() {
                        errors.push(e);
                    }
                    lens.iter().map(|&n| vec![f64::NAN; n]).collect()
                })
            }
        }
    }

    fn device_states(&mut self, slots: usize, len: usize) -> Result<Option<u64>, String> {
        self.core.get_mut().device_states(slots, len)
    }

    fn store_state(&mut self, slot: usize, x: BufferId, v: BufferId) -> Result<(), String> {
        let (x, v) = (self.slot[x.0 as usize], self.slot[v.0 as usize]);
        self.core.get_mut().record_state_copy(true, slot, x, v)
    }

    fn restore_state(&mut self, slot: usize, x: BufferId, v: BufferId) -> Result<(), String> {
        let (x, v) = (self.slot[x.0 as usize], self.slot[v.0 as usize]);
        self.core.get_mut().record_state_copy(false, slot, x, v)
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
        let stepped = Stepped {
            launches,
            swaps,
            first,
            n,
            dt,
            uniforms,
            reverse: false,
            states: None,
        };
        self.core.get_mut().record_steps(&mut self.slot, &stepped)?;
        Ok(true)
    }

    fn run_stepped(&mut self, stepped: &Stepped<'_>) -> Result<bool, String> {
        self.core.get_mut().record_steps(&mut self.slot, stepped)?;
        Ok(true)
    }
}

/// The device and buffers of a batch, shared by its scenes.
struct Shared {
    core: Mutex<Core>,
    /// Signalled when waiting scenes' readbacks are served.
    served: Condvar,
}

impl Shared {
    fn lock(&self) -> MutexGuard<'_, Core> {
        // A scene's thread that panicked leaves the data consistent (each operation completes
        // under the lock), so a poisoned lock is still usable.
        self.core.lock().unwrap_or_else(|e| e.into_inner())
    }
}

/// Several scenes of one mesh on one GPU: each kernel launch of the batch is one dispatch
/// over all its scenes (see the module documentation). Each scene is a [`GpuScene`] backend.
#[derive(Clone)]
pub struct GpuBatch {
    shared: Arc<Shared>,
}

impl GpuBatch {
    /// Compile `module` batched for `scenes` scenes (see [`Gpu::new`] for `adapter`).
    pub fn new(
        module: &Module,
        precision: Precision,
        adapter: Option<&str>,
        scenes: usize,
    ) -> Result<Self, String> {
        let n = u32::try_from(scenes)
            .ok()
            .filter(|&n| n > 0)
            .ok_or_else(|| format!("a batch of {scenes} scenes"))?;
        Ok(GpuBatch {
            shared: Arc::new(Shared {
                core: Mutex::new(Core::open(module, precision, adapter, Some(n), None)?),
                served: Condvar::new(),
            }),
        })
    }

    /// The backend of scene `index` (< the batch's scenes).
    pub fn scene(&self, index: usize) -> Result<GpuScene, String> {
        let scenes = self.shared.lock().scenes;
        if index >= scenes {
            return Err(format!("scene {index} of a batch of {scenes}"));
        }
        Ok(GpuScene {
            shared: self.shared.clone(),
            scene: index,
            slot: Vec::new(),
        })
    }

    pub fn adapter(&self) -> AdapterDesc {
        self.shared.lock().adapter.clone()
    }

    /// Launches, dispatches, submissions, readbacks and host (and GPU) time so far.
    pub fn stats(&self) -> DispatchStats {
        self.shared.lock().stats_now()
    }

    /// Time the compute passes on the GPU from now on (see [`Gpu::enable_timing`]).
    pub fn enable_timing(&self) -> bool {
        self.shared.lock().enable_timing()
    }
}

/// One scene of a [`GpuBatch`].
pub struct GpuScene {
    shared: Arc<Shared>,
    scene: usize,
    slot: Vec<usize>,
}

impl GpuScene {
    /// What the batch's device did so far (all its scenes).
    pub fn stats(&self) -> DispatchStats {
        self.shared.lock().stats_now()
    }

    /// Time the batch's compute passes (see [`Gpu::enable_timing`]).
    pub fn enable_timing(&self) -> bool {
        self.shared.lock().enable_timing()
    }
}

impl Backend for GpuScene {
    fn precision(&self) -> Precision {
        self.shared.lock().module.precision
    }

    fn name(&self) -> &'static str {
        "gpu"
    }

    /// The first scene allocates the batch's buffers; the others must have the same mesh.
    fn prepare(&mut self, scene: &Scene) -> Result<(), String> {
        let mut core = self.shared.lock();
        core.check_scene(scene)?;
        let counts = [
            scene.mesh.tets.len(),
            scene.tris.len(),
            scene.mesh.nodes.len(),
        ];
        if core.topo.is_empty() {
            core.allocate(
                scene.mesh.nodes.len(),
                (&scene.elem_conn(), scene.mesh.tets.len()),
                (&scene.tri_conn(), scene.tris.len()),
                &scene.node_elements,
                &scene.node_tris,
            )?;
        } else if core.counts != counts {
            return Err(format!(
                "the scenes of a batch share one mesh: scene {} has {} elements, {} chamber \
                 triangles and {} nodes, the batch {}, {} and {}",
                self.scene,
                counts[0],
                counts[1],
                counts[2],
                core.counts[0],
                core.counts[1],
                core.counts[2]
            ));
        }
        self.slot = (0..core.buffer_count).collect();
        Ok(())
    }

    fn set(&mut self, b: BufferId, data: &[f64]) {
        let phys = self.slot[b.0 as usize];
        self.shared.lock().record_set(self.scene, phys, data);
    }

    fn get(&self, b: BufferId) -> Vec<f64> {
        // An unknown buffer fails in the readback, like any other failed readback.
        let phys = self.slot.get(b.0 as usize).copied().unwrap_or(b.0 as usize);
        let s = self.scene;
        let mut core = self.shared.lock();
        let r = if core.active[s] {
            core.waiting[s] = Some(phys);
            if core.serve_if_ready() {
                self.shared.served.notify_all();
            }
            loop {
                if let Some(r) = core.served[s].take() {
                    break r;
                }
                core = self
                    .shared
                    .served
                    .wait(core)
                    .unwrap_or_else(|e| e.into_inner());
            }
        } else {
            core.read(&[(phys, s)]).map(|mut v| v.remove(0))
        };
        core.values_or_nan(phys, r)
    }

    fn device_error(&self) -> Option<String> {
        self.shared.lock().device_error()
    }

    fn swap(&mut self, a: BufferId, b: BufferId) {
        self.slot.swap(a.0 as usize, b.0 as usize);
    }

    fn run(&mut self, k: usize, range: Range<usize>, u: &Uniforms) -> Result<(), String> {
        self.shared
            .lock()
            .record_run(self.scene, &self.slot, k, range, u)
    }

    /// Records the stretch; the batch's scenes that record the same stretch (in lockstep,
    /// all of them) run it as one batched stretch at the next submission.
    fn run_steps(
        &mut self,
        launches: &[Launch],
        swaps: &[(BufferId, BufferId)],
        first: u64,
        n: u64,
        dt: f64,
        uniforms: &Uniforms,
    ) -> Result<bool, String> {
        let mut core = self.shared.lock();
        if let Some(e) = core.take_error() {
            return Err(e);
        }
        for (k, range) in launches {
            core.check_launch(*k, range)?;
        }
        let op = StepsOp {
            launches: launches.to_vec(),
            swaps: swaps.to_vec(),
            slot: self.slot.clone(),
            first,
            n,
            dt,
            uniforms: uniforms.clone(),
        };
        core.record(self.scene, Op::Steps(Box::new(op)))?;
        drop(core);
        for _ in 0..n {
            for (a, b) in swaps {
                self.slot.swap(a.0 as usize, b.0 as usize);
            }
        }
        Ok(true)
    }

    /// Joins the batch's lockstep group until the token is dropped: each readback then waits
    /// until every scene of the group asks for one (or leaves), and all are served together.
    fn runs_ahead(&self) -> bool {
        true
    }

    fn lockstep(&self) -> Lockstep {
        self.shared.lock().active[self.scene] = true;
        let shared = self.shared.clone();
        let s = self.scene;
        Lockstep::new(move || {
            let mut core = shared.lock();
            core.active[s] = false;
            if core.serve_if_ready() {
                shared.served.notify_all();
            }
        })
    }
}
