//! The GPU device: a scene's kernels as WGSL ([`softc_compiler::back::wgsl`]) run by wgpu on
//! any adapter (Vulkan, Metal, DX12; Mesa's lavapipe on machines without a GPU).
//!
//! Few host round trips: [`Backend::run`] and [`Backend::set`] only record an operation;
//! [`Backend::swap`] exchanges buffer handles host-side (bind groups are cached per
//! combination of physical buffers, so double-buffered state costs two bind groups per
//! kernel). Recorded operations are submitted when data has to come back (`get`) or
//! [`MAX_PENDING`] have accumulated: launches go into one compute pass, their uniforms into a
//! host staging area at aligned offsets of one uniform buffer, bound with a dynamic offset.
//! The engine reads the state every 50 steps, so ~50 steps × (kernels per step) launches go
//! in one submission.
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
use softc_compiler::back::wgsl::{self, Binding, LaunchMode, TopoArray, WgslKernel, WgslModule};
use softc_compiler::ir::{BufferId, Domain, Module};
use std::cell::RefCell;
use std::collections::{HashMap, VecDeque};
use std::ops::Range;
use std::sync::{Arc, Condvar, Mutex, MutexGuard};

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

/// Bytes of the launch block bound at `binding` (a kernel's launch binding follows the
/// buffers and the connectivity, in kernel order).
fn launch_stride_of(wg: &WgslModule, buffers: usize, binding: u32) -> u64 {
    let k = binding as usize - buffers - TopoArray::ALL.len();
    wg.kernels.get(k).map_or(16, WgslKernel::launch_stride)
}

/// The pipeline of entry point `k` of `shader`, its bind group laid out as its bindings say
/// (launch blocks of `scenes` scenes at dynamic offsets, `stride_of` giving a launch
/// binding's block size, or the launch table with its row as an immediate).
fn pipeline_for(
    device: &wgpu::Device,
    shader: &wgpu::ShaderModule,
    k: &WgslKernel,
    scenes: u64,
    launch: LaunchMode,
    stride_of: &dyn Fn(u32) -> u64,
) -> Pipeline {
    let entries: Vec<wgpu::BindGroupLayoutEntry> = k
        .bindings
        .iter()
        .map(|&(binding, what)| {
            let ty = match what {
                Binding::Buffer { writable, .. } => wgpu::BindingType::Buffer {
                    ty: wgpu::BufferBindingType::Storage {
                        read_only: !writable,
                    },
                    has_dynamic_offset: false,
                    min_binding_size: None,
                },
                Binding::Topo(_) | Binding::LaunchTable => wgpu::BindingType::Buffer {
                    ty: wgpu::BufferBindingType::Storage { read_only: true },
                    has_dynamic_offset: false,
                    min_binding_size: None,
                },
                Binding::Launch => wgpu::BindingType::Buffer {
                    ty: wgpu::BufferBindingType::Uniform,
                    has_dynamic_offset: true,
                    min_binding_size: wgpu::BufferSize::new(scenes * stride_of(binding)),
                },
            };
            wgpu::BindGroupLayoutEntry {
                binding,
                visibility: wgpu::ShaderStages::COMPUTE,
                ty,
                count: None,
            }
        })
        .collect();
    let layout = device.create_bind_group_layout(&wgpu::BindGroupLayoutDescriptor {
        label: Some(&k.name),
        entries: &entries,
    });
    let pl = device.create_pipeline_layout(&wgpu::PipelineLayoutDescriptor {
        label: Some(&k.name),
        bind_group_layouts: &[Some(&layout)],
        immediate_size: match launch {
            LaunchMode::Table => wgsl::IMMEDIATE_BYTES,
            LaunchMode::Uniform => 0,
        },
    });
    let pipeline = device.create_compute_pipeline(&wgpu::ComputePipelineDescriptor {
        label: Some(&k.name),
        layout: Some(&pl),
        module: shader,
        entry_point: Some(&k.entry),
        compilation_options: Default::default(),
        cache: None,
    });
    Pipeline { pipeline, layout }
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

/// The copy kernel between a state (`x`, `v`: `len` values each) and a slot of the device's
/// state store (bound at a dynamic offset): `store` into the slot, else out of it.
fn state_copy_wgsl(real: &str, len: usize, store: bool) -> String {
    let (state, slot, body, name) = if store {
        (
            "read",
            "read_write",
            "slot[i] = x[i];\n        slot[N + i] = v[i];",
            "store",
        )
    } else {
        (
            "read_write",
            "read",
            "x[i] = slot[i];\n        v[i] = slot[N + i];",
            "restore",
        )
    };
    format!(
        "// softc: the adjoint's state store on the device (copies, no arithmetic).
alias real = {real};
const N: u32 = {len}u;
@group(0) @binding(0) var<storage, {state}> x: array<real>;
@group(0) @binding(1) var<storage, {state}> v: array<real>;
@group(0) @binding(2) var<storage, {slot}> slot: array<real>;
@compute @workgroup_size(64)
fn {name}(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {{
    let i = gid.x + gid.y * nwg.x * 64u;
    if (i < N) {{
        {body}
    }}
}}
"
    )
}

/// A readback under way.
struct InFlight {
    buffer: wgpu::Buffer,
    total: u64,
    /// (offset, bytes) of each buffer's values in it.
    spans: Vec<(u64, u64)>,
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
}

impl Timing {
    const PAIRS: u32 = 512;

    fn new(device: &wgpu::Device, queue: &wgpu::Queue) -> Self {
        let bytes = u64::from(Self::PAIRS) * wgpu::QUERY_RESOLVE_BUFFER_ALIGNMENT;
        Timing {
            set: device.create_query_set(&wgpu::QuerySetDescriptor {
                label: Some("softc pass times"),
                ty: wgpu::QueryType::Timestamp,
                count: 2 * Self::PAIRS,
            }),
            resolve: device.create_buffer(&wgpu::BufferDescriptor {
                label: Some("softc pass times"),
                size: bytes,
                usage: wgpu::BufferUsages::QUERY_RESOLVE | wgpu::BufferUsages::COPY_SRC,
                mapped_at_creation: false,
            }),
            read: device.create_buffer(&wgpu::BufferDescriptor {
                label: Some("softc pass times read"),
                size: bytes,
                usage: wgpu::BufferUsages::MAP_READ | wgpu::BufferUsages::COPY_DST,
                mapped_at_creation: false,
            }),
            pairs: Self::PAIRS,
            used: 0,
            period: f64::from(queue.get_timestamp_period()),
            seconds: 0.0,
        }
    }

    /// The first query of a free pair, if any is left.
    fn next_pair(&mut self) -> Option<u32> {
        (self.used < self.pairs).then(|| {
            self.used += 1;
            2 * (self.used - 1)
        })
    }

    fn resolve(&self, enc: &mut wgpu::CommandEncoder, first: u32) {
        enc.resolve_query_set(
            &self.set,
            first..first + 2,
            &self.resolve,
            u64::from(first / 2) * wgpu::QUERY_RESOLVE_BUFFER_ALIGNMENT,
        );
    }

    /// Add up the used pairs (waits for the GPU) and free them.
    fn collect(&mut self, device: &wgpu::Device, queue: &wgpu::Queue) {
        if self.used == 0 {
            return;
        }
        // Each pair's two ticks at the start of its own aligned span.
        let span = wgpu::QUERY_RESOLVE_BUFFER_ALIGNMENT as usize;
        let bytes = u64::from(self.used) * span as u64;
        let mut enc = device.create_command_encoder(&wgpu::CommandEncoderDescriptor {
            label: Some("softc pass times"),
        });
        enc.copy_buffer_to_buffer(&self.resolve, 0, &self.read, 0, bytes);
        queue.submit([enc.finish()]);
        let (tx, rx) = std::sync::mpsc::channel();
        self.read
            .map_async(wgpu::MapMode::Read, 0..bytes, move |r| {
                let _ = tx.send(r);
            });
        let _ = device.poll(wgpu::PollType::wait_indefinitely());
        if let Ok(Ok(())) = rx.recv()
            && let Ok(view) = self.read.get_mapped_range(0..bytes)
        {
            let tick =
                |c: &[u8]| u64::from_le_bytes([c[0], c[1], c[2], c[3], c[4], c[5], c[6], c[7]]);
            for pair in view.chunks_exact(span) {
                let (begin, end) = (tick(&pair[0..8]), tick(&pair[8..16]));
                self.seconds += end.saturating_sub(begin) as f64 * self.period * 1e-9;
            }
        }
        self.read.unmap();
        self.used = 0;
    }
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
    /// Physical buffers, each holding `scenes × lens[i]` values.
    buffers: Vec<wgpu::Buffer>,
    lens: Vec<usize>,
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
    readback: Option<wgpu::Buffer>,
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

impl Core {
    /// Compile `module` (batched for `batch` scenes) for an adapter: the first one whose name
    /// (or backend) contains `adapter` (case-insensitive), else the preferred one (discrete,
    /// integrated, virtual, then software; Vulkan first). f64 needs `SHADER_F64`.
    fn open(
        module: &Module,
        precision: Precision,
        adapter: Option<&str>,
        batch: Option<u32>,
        launch: Option<LaunchMode>,
    ) -> Result<Self, String> {
        let inst = instance();
        let mut all = pollster::block_on(inst.enumerate_adapters(wgpu::Backends::all()));
        if all.is_empty() {
            return Err(NO_ADAPTER_HINT.into());
        }
        all.sort_by_key(rank);
        let chosen = match adapter {
            Some(want) => {
                let w = want.to_lowercase();
                let found = all.iter().position(|a| {
                    let d = describe(a);
                    d.name.to_lowercase().contains(&w) || d.backend.to_lowercase() == w
                });
                match found {
                    Some(i) => all.swap_remove(i),
                    None => {
                        let names: Vec<String> =
                            all.iter().map(|a| format!("  {}", describe(a))).collect();
                        return Err(format!(
                            "no GPU adapter matches `{want}`; found:\n{}",
                            names.join("\n")
                        ));
                    }
                }
            }
            None => all.swap_remove(0),
        };
        let desc = describe(&chosen);
        let mut features = wgpu::Features::empty();
        if precision == Precision::F64 {
            if !desc.shader_f64 {
                return Err(format!(
                    "adapter {desc} has no SHADER_F64 (64-bit floats in shaders): use \
                     `--precision f32`, another adapter (`--adapter`), or `--backend cpu`"
                ));
            }
            features |= wgpu::Features::SHADER_F64;
        }
        let limits = chosen.limits();
        // Launch blocks as uniform blocks at dynamic offsets (any adapter). The alternative, a
        // storage table indexed by an immediate (`SOFTC_GPU_LAUNCH=table`, where the adapter
        // has immediates), gives the same bits but measured slower on an H100 (10k, 8000
        // steps: 22,495 against 29,698 steps/s): each kernel then starts with a dependent
        // load of its launch block from memory.
        let has_immediates = chosen.features().contains(wgpu::Features::IMMEDIATES)
            && limits.max_immediate_size >= wgsl::IMMEDIATE_BYTES;
        let wanted = launch.unwrap_or(
            if std::env::var("SOFTC_GPU_LAUNCH").as_deref() == Ok("table") {
                LaunchMode::Table
            } else {
                LaunchMode::Uniform
            },
        );
        let launch = match wanted {
            LaunchMode::Table if has_immediates => {
                features |= wgpu::Features::IMMEDIATES;
                LaunchMode::Table
            }
            LaunchMode::Table => {
                return Err(format!(
                    "adapter {desc} has no immediates (push constants) for launch tables"
                ));
            }
            LaunchMode::Uniform => LaunchMode::Uniform,
        };
        if chosen.features().contains(wgpu::Features::TIMESTAMP_QUERY) {
            features |= wgpu::Features::TIMESTAMP_QUERY;
        }
        let wg = wgsl::emit_for(module, precision, batch, launch)?;
        let scenes = batch.unwrap_or(1) as u64;
        for k in &wg.kernels {
            if k.storage_buffers > limits.max_storage_buffers_per_shader_stage {
                return Err(format!(
                    "kernel `{}` binds {} storage buffers; adapter {desc} allows {} per shader stage",
                    k.name, k.storage_buffers, limits.max_storage_buffers_per_shader_stage
                ));
            }
            let blocks = scenes * k.launch_stride();
            if launch == LaunchMode::Uniform && blocks > limits.max_uniform_buffer_binding_size {
                return Err(format!(
                    "kernel `{}`: {scenes} launch blocks of {} bytes exceed the {} bytes adapter \
                     {desc} binds as uniforms; run fewer scenes per batch",
                    k.name,
                    round_up(k.launch_size, 16),
                    limits.max_uniform_buffer_binding_size
                ));
            }
        }
        let (device, queue) = pollster::block_on(chosen.request_device(&wgpu::DeviceDescriptor {
            label: Some("softc"),
            required_features: features,
            required_limits: limits.clone(),
            ..Default::default()
        }))
        .map_err(|e| format!("adapter {desc}: cannot open a device: {e}"))?;
        let errors: Arc<Mutex<Vec<String>>> = Arc::default();
        let sink = errors.clone();
        device.on_uncaptured_error(Arc::new(move |e: wgpu::Error| {
            if let Ok(mut v) = sink.lock() {
                v.push(e.to_string());
            }
        }));
        let shader = device.create_shader_module(wgpu::ShaderModuleDescriptor {
            label: Some("softc kernels"),
            source: wgpu::ShaderSource::Wgsl(wg.source.as_str().into()),
        });
        let stride_of = |b: u32| launch_stride_of(&wg, module.buffers.len(), b);
        let pipelines = wg
            .kernels
            .iter()
            .map(|k| pipeline_for(&device, &shader, k, scenes, launch, &stride_of))
            .collect();
        let _ = device.poll(wgpu::PollType::wait_indefinitely());
        if let Some(e) = errors.lock().ok().and_then(|mut v| v.drain(..).next()) {
            return Err(format!("adapter {desc}: the kernels do not compile: {e}"));
        }
        let align = limits.min_uniform_buffer_offset_alignment.max(16);
        let scenes = scenes as usize;
        Ok(Core {
            device,
            queue,
            adapter: desc,
            module: wg,
            pipelines,
            align,
            buffer_count: module.buffers.len(),
            layout: module
                .buffers
                .iter()
                .map(|b| (b.domain, b.width, b.name.clone()))
                .collect(),
            errors,
            scenes,
            buffers: Vec::new(),
            lens: Vec::new(),
            topo: Vec::new(),
            counts: [0; 3],
            launch_buffer: None,
            staging: Vec::new(),
            queues: (0..scenes).map(|_| VecDeque::new()).collect(),
            recorded: 0,
            pending: Vec::new(),
            bind_groups: HashMap::new(),
            groups: Vec::new(),
            readback: None,
            timing: None,
            in_flight: HashMap::new(),
            next_ticket: 0,
            spare_readbacks: Vec::new(),
            states: None,
            ir: module.clone(),
            fuse: std::env::var("SOFTC_GPU_FUSE").as_deref() != Ok("0"),
            fused: HashMap::new(),
            fused_kernels: HashMap::new(),
            stats: DispatchStats::default(),
            active: vec![false; scenes],
            waiting: vec![None; scenes],
            served: (0..scenes).map(|_| None).collect(),
        })
    }

    /// Add the host time since `start` (an instant and the submission time then), less the
    /// time inside queue submissions, to the stats.
    fn add_host_time(&mut self, start: (std::time::Instant, f64)) {
        let submitting = self.stats.submit_seconds - start.1;
        self.stats.host_seconds += start.0.elapsed().as_secs_f64() - submitting;
    }

    /// Time the compute passes with timestamp queries from now on, if the adapter has them
    /// (`false` if not).
    fn enable_timing(&mut self) -> bool {
        if self.timing.is_none()
            && self
                .device
                .features()
                .contains(wgpu::Features::TIMESTAMP_QUERY)
        {
            self.timing = Some(Timing::new(&self.device, &self.queue));
        }
        self.timing.is_some()
    }

    /// The figures so far (reading the pass times back waits for the GPU).
    fn stats_now(&mut self) -> DispatchStats {
        let mut s = self.stats;
        if let Some(t) = self.timing.as_mut() {
            t.collect(&self.device, &self.queue);
            s.gpu_seconds = Some(t.seconds);
        }
        s
    }

    fn take_error(&self) -> Option<String> {
        self.errors
            .lock()
            .ok()
            .and_then(|mut v| v.drain(..).next())
            .map(|e| format!("GPU ({}): {e}", self.adapter))
    }

    fn device_error(&self) -> Option<String> {
        let errors = self.errors.lock().ok()?;
        errors
            .first()
            .map(|e| format!("GPU ({}): {e}", self.adapter))
    }

    /// Check a scene against the compiled module: the module is the scene's forward module or
    /// its adjoint (a superset whose first buffers are the forward ones).
    fn check_scene(&self, scene: &Scene) -> Result<(), String> {
        if scene.lowered.module.buffers.len() > self.buffer_count {
            return Err(format!(
                "the scene has {} buffers, the compiled module {}",
                scene.lowered.module.buffers.len(),
                self.buffer_count
            ));
        }
        Ok(())
    }

    /// Allocate zeroed buffers for every scene of a mesh and upload its connectivity (node CSR
    /// lists in entity order, as scenes build them). Drops recorded work.
    fn allocate(
        &mut self,
        n_nodes: usize,
        tets: &[[u32; 4]],
        tris: &[[u32; 3]],
        node_elements: &Csr,
        node_tris: &Csr,
    ) -> Result<(), String> {
        let max = self.device.limits().max_storage_buffer_binding_size;
        let size = self.module.precision.size() as u64;
        let counts = [tets.len(), tris.len(), n_nodes];
        let mut buffers = Vec::new();
        let mut lens = Vec::new();
        for b in &self.layout {
            let n = domain_count(&counts, b.0) * b.1 as usize;
            let bytes = (n * self.scenes) as u64 * size;
            if bytes > max {
                return Err(format!(
                    "buffer `{}` needs {bytes} bytes{}; adapter {} binds at most {max}",
                    b.2,
                    if self.scenes > 1 {
                        format!(" for {} scenes", self.scenes)
                    } else {
                        String::new()
                    },
                    self.adapter
                ));
            }
            buffers.push(self.storage_buffer(&b.2, bytes));
            lens.push(n);
        }
        let flat = |v: &[u32]| -> Vec<u8> { v.iter().flat_map(|x| x.to_le_bytes()).collect() };
        let elem: Vec<u32> = tets.iter().flatten().copied().collect();
        let tri: Vec<u32> = tris.iter().flatten().copied().collect();
        let mut topo = Vec::new();
        for t in TopoArray::ALL {
            let data = match t {
                TopoArray::ElemConn => flat(&elem),
                TopoArray::TriConn => flat(&tri),
                TopoArray::NodeElemOffsets => flat(&node_elements.offsets),
                TopoArray::NodeElemEntries => flat(&node_elements.flat_entries()),
                TopoArray::NodeTriOffsets => flat(&node_tris.offsets),
                TopoArray::NodeTriEntries => flat(&node_tris.flat_entries()),
            };
            if data.len() as u64 > max {
                return Err(format!(
                    "connectivity `{}` needs {} bytes; adapter {} binds at most {max}",
                    t.name(),
                    data.len(),
                    self.adapter
                ));
            }
            let buf = self.storage_buffer(t.name(), data.len() as u64);
            if !data.is_empty() {
                self.queue.write_buffer(&buf, 0, &data);
            }
            topo.push(buf);
        }
        self.counts = counts;
        self.buffers = buffers;
        self.lens = lens;
        self.topo = topo;
        self.bind_groups.clear();
        self.groups.clear();
        self.pending.clear();
        self.staging.clear();
        for q in &mut self.queues {
            q.clear();
        }
        self.recorded = 0;
        Ok(())
    }

    fn storage_buffer(&self, label: &str, bytes: u64) -> wgpu::Buffer {
        self.device.create_buffer(&wgpu::BufferDescriptor {
            label: Some(label),
            // Bindings cannot be empty: a buffer of an empty domain still has 16 bytes.
            size: round_up(bytes.max(16), 4),
            usage: wgpu::BufferUsages::STORAGE
                | wgpu::BufferUsages::COPY_SRC
                | wgpu::BufferUsages::COPY_DST,
            mapped_at_creation: false,
        })
    }

    fn bytes_of(&self, data: &[f64]) -> Vec<u8> {
        match self.module.precision {
            Precision::F32 => data
                .iter()
                .flat_map(|&v| (v as f32).to_le_bytes())
                .collect(),
            Precision::F64 => data.iter().flat_map(|&v| v.to_le_bytes()).collect(),
        }
    }

    fn record(&mut self, scene: usize, op: Op) -> Result<(), String> {
        self.queues[scene].push_back(op);
        self.recorded += 1;
        if self.recorded >= MAX_PENDING {
            self.drain();
            self.submit();
            if let Some(e) = self.take_error() {
                return Err(e);
            }
        }
        Ok(())
    }

    fn record_set(&mut self, scene: usize, phys: usize, data: &[f64]) {
        assert_eq!(
            self.lens[phys],
            data.len(),
            "buffer `{}`: {} values given, {} expected",
            self.layout[phys].2,
            data.len(),
            self.lens[phys]
        );
        if data.is_empty() {
            return;
        }
        let bytes = self.bytes_of(data);
        // A failure to submit shows at the next launch or readback.
        let _ = self.record(scene, Op::Set { phys, bytes });
    }

    /// Record kernel `k` over `range` of scene `scene`, with its buffers bound as `slot` maps
    /// them.
    fn record_run(
        &mut self,
        scene: usize,
        slot: &[usize],
        k: usize,
        range: Range<usize>,
        u: &Uniforms,
    ) -> Result<(), String> {
        if let Some(e) = self.take_error() {
            return Err(e);
        }
        let start = (std::time::Instant::now(), self.stats.submit_seconds);
        if self.check_launch(k, &range)?.is_none() {
            return Ok(());
        }
        let key = self.key_of(k, slot);
        let kernel = &self.module.kernels[k];
        let values = kernel.uniforms.iter().map(|&id| u.get(id)).collect();
        self.stats.launches += 1;
        self.record(
            scene,
            Op::Run {
                kernel: k,
                key,
                begin: range.start as u32,
                count: range.len() as u32,
                values,
            },
        )?;
        self.add_host_time(start);
        Ok(())
    }

    /// Submit every scene's recorded operations, each scene's in its order (see
    /// [`Core::drain`]).
    fn flush(&mut self) {
        let start = (std::time::Instant::now(), self.stats.submit_seconds);
        self.drain();
        self.submit();
        self.add_host_time(start);
    }

    /// Turn every scene's recorded operations into pending dispatches, each scene's in its
    /// order. The scenes' next launches of the same kernel on the same buffers become one
    /// dispatch; a `set` waits until no scene has a launch before its own next `set`, so the
    /// writes of a batch in lockstep cost one break in the submission.
    fn drain(&mut self) {
        loop {
            let heads: Vec<usize> = (0..self.scenes)
                .filter(|&s| !self.queues[s].is_empty())
                .collect();
            if heads.is_empty() {
                break;
            }
            // Stretches first: those that match run as one batched stretch.
            let mut stretches: Vec<Vec<usize>> = Vec::new();
            for &s in &heads {
                let Some(Op::Steps(op)) = self.queues[s].front() else {
                    continue;
                };
                let found = stretches
                    .iter_mut()
                    .find(|g| match self.queues[g[0]].front() {
                        Some(Op::Steps(first)) => first.matches(op),
                        _ => false,
                    });
                match found {
                    Some(g) => g.push(s),
                    None => stretches.push(vec![s]),
                }
            }
            for members in &stretches {
                let ops: Vec<StepsOp> = members
                    .iter()
                    .filter_map(|&s| match self.queues[s].pop_front() {
                        Some(Op::Steps(op)) => Some(*op),
                        _ => None,
                    })
                    .collect();
                let Some(op) = ops.first() else {
                    continue;
                };
                let mut slot = op.slot.clone();
                let stepped = Stepped {
                    launches: &op.launches,
                    swaps: &op.swaps,
                    first: op.first,
                    n: op.n,
                    dt: op.dt,
                    uniforms: &op.uniforms,
                    reverse: false,
                    states: None,
                };
                let scenes: Vec<(usize, &Uniforms)> = members
                    .iter()
                    .zip(&ops)
                    .map(|(&s, op)| (s, &op.uniforms))
                    .collect();
                if let Err(e) = self.record_steps_for(&mut slot, &stepped, &scenes)
                    && let Ok(mut errors) = self.errors.lock()
                {
                    errors.push(e);
                }
            }
            if !stretches.is_empty() {
                continue;
            }
            let runs: Vec<usize> = heads
                .iter()
                .copied()
                .filter(|&s| matches!(self.queues[s].front(), Some(Op::Run { .. })))
                .collect();
            if runs.is_empty() {
                // Only writes at the heads: what is recorded reads the old contents.
                self.submit();
                for s in heads {
                    if let Some(Op::Set { phys, bytes }) = self.queues[s].pop_front() {
                        let offset = (s * self.lens[phys] * self.module.precision.size()) as u64;
                        self.queue.write_buffer(&self.buffers[phys], offset, &bytes);
                    }
                }
                continue;
            }
            // Group the heads by kernel and bound buffers.
            let mut groups: Vec<(usize, Vec<usize>, Vec<usize>)> = Vec::new();
            for s in runs {
                let Some(Op::Run { kernel, key, .. }) = self.queues[s].front() else {
                    continue;
                };
                match groups.iter_mut().find(|g| g.0 == *kernel && g.1 == *key) {
                    Some(g) => g.2.push(s),
                    None => groups.push((*kernel, key.clone(), vec![s])),
                }
            }
            for (kernel, key, members) in groups {
                let (at, arg) = self.alloc_blocks(kernel, 1);
                let mut count = 0u64;
                for (j, &s) in members.iter().enumerate() {
                    if let Some(Op::Run {
                        begin,
                        count: c,
                        values,
                        ..
                    }) = self.queues[s].pop_front()
                    {
                        self.write_block(at, j, kernel, s, begin, c, values.iter().copied());
                        count = count.max(u64::from(c));
                    }
                }
                let group = self.bind_group(kernel, &key);
                let groups = self.workgroups(count, members.len());
                self.pending.push(Dispatch::one(kernel, group, arg, groups));
            }
        }
        self.recorded = 0;
        if self.pending.len() >= MAX_PENDING {
            self.submit();
        }
    }

    /// Workgroups of a dispatch of `count` entities for `scenes` scenes (rows beyond 65,535
    /// workgroups go to y).
    fn workgroups(&self, count: u64, scenes: usize) -> (u32, u32, u32) {
        let groups = count.div_ceil(u64::from(wgsl::WORKGROUP_SIZE));
        let max = u64::from(self.device.limits().max_compute_workgroups_per_dimension);
        let gx = groups.clamp(1, max);
        (gx as u32, groups.div_ceil(gx) as u32, scenes as u32)
    }

    /// Bytes of launch blocks the next submission can hold.
    fn launch_capacity(&self) -> u64 {
        self.launch_buffer.as_ref().map_or(0, |b| b.size())
    }

    /// Make room for `bytes` more bytes of launch blocks (aligned) in the next submission:
    /// submits what is pending if they do not fit, and grows the buffer (dropping the bind
    /// groups, which bind it) if one submission cannot hold them.
    fn reserve(&mut self, bytes: u64) {
        let used = self.staging.len() as u64;
        if used + bytes <= self.launch_capacity() {
            return;
        }
        self.submit();
        if bytes > self.launch_capacity() {
            let size = bytes.next_power_of_two().max(MIN_LAUNCH_BYTES);
            let usage = match self.module.launch {
                LaunchMode::Table => wgpu::BufferUsages::STORAGE,
                LaunchMode::Uniform => wgpu::BufferUsages::UNIFORM,
            } | wgpu::BufferUsages::COPY_DST;
            self.launch_buffer = Some(self.device.create_buffer(&wgpu::BufferDescriptor {
                label: Some("softc launch blocks"),
                size,
                usage,
                mapped_at_creation: false,
            }));
            self.bind_groups.clear();
            self.groups.clear();
        }
    }

    /// The alignment of a kernel's launch blocks in the launch buffer.
    fn block_align(&self, kernel: usize) -> u64 {
        match self.module.launch {
            LaunchMode::Table => self.module.kernels[kernel].launch_stride(),
            LaunchMode::Uniform => u64::from(self.align),
        }
    }

    /// Room for `rows` dispatches' launch blocks of `kernel` (each one block per scene);
    /// returns the byte offset of the first and its dispatch argument (see [`Dispatch::arg`]).
    /// Call [`Core::reserve`] first for many rows at once.
    fn alloc_blocks(&mut self, kernel: usize, rows: u64) -> (usize, u32) {
        let stride = self.module.kernels[kernel].launch_stride();
        let align = self.block_align(kernel);
        let span = round_up(self.scenes as u64 * stride, align);
        self.reserve(span * rows + align);
        let at = round_up(self.staging.len() as u64, align);
        self.staging.resize((at + span * rows) as usize, 0);
        let arg = match self.module.launch {
            LaunchMode::Table => at / stride,
            LaunchMode::Uniform => at,
        };
        (at as usize, arg as u32)
    }

    /// The dispatch argument of the row `row` rows after `arg` (see [`Core::alloc_blocks`]).
    fn next_arg(&self, kernel: usize, arg: u32, row: u64) -> u32 {
        let stride = self.module.kernels[kernel].launch_stride();
        let span = round_up(self.scenes as u64 * stride, self.block_align(kernel));
        match self.module.launch {
            LaunchMode::Table => arg + (row * span / stride) as u32,
            LaunchMode::Uniform => arg + (row * span) as u32,
        }
    }

    /// Write scene `scene`'s launch block, the `j`-th of the blocks at `at`.
    #[allow(clippy::too_many_arguments)]
    fn write_block(
        &mut self,
        at: usize,
        j: usize,
        kernel: usize,
        scene: usize,
        begin: u32,
        count: u32,
        values: impl Iterator<Item = f64>,
    ) {
        let k = &self.module.kernels[kernel];
        let stride = k.launch_stride() as usize;
        let start = at + j * stride;
        let block = &mut self.staging[start..start + stride];
        block[0..4].copy_from_slice(&begin.to_le_bytes());
        block[4..8].copy_from_slice(&count.to_le_bytes());
        if self.module.batch.is_some() {
            for (i, v) in [scene, self.counts[0], self.counts[1], self.counts[2]]
                .into_iter()
                .enumerate()
            {
                block[8 + 4 * i..12 + 4 * i].copy_from_slice(&(v as u32).to_le_bytes());
            }
        }
        let mut o = k.uniform_offset as usize;
        for v in values {
            match self.module.precision {
                Precision::F32 => {
                    block[o..o + 4].copy_from_slice(&(v as f32).to_le_bytes());
                    o += 4;
                }
                Precision::F64 => {
                    block[o..o + 8].copy_from_slice(&v.to_le_bytes());
                    o += 8;
                }
            }
        }
    }

    /// The bind group of `kernel` with the physical buffers `key` bound (made once).
    fn bind_group(&mut self, kernel: usize, key: &[usize]) -> usize {
        if let Some(&g) = self.bind_groups.get(&(kernel, key.to_vec())) {
            return g;
        }
        let Some(launch) = self.launch_buffer.clone() else {
            unreachable!("launch blocks are reserved before their bind group");
        };
        let k = self.entry_kernel(kernel);
        let mut phys = key.iter();
        let entries: Vec<wgpu::BindGroupEntry> = k
            .bindings
            .iter()
            .map(|&(binding, what)| {
                let resource = match what {
                    Binding::Buffer { .. } => {
                        let p = *phys.next().unwrap_or(&0);
                        self.buffers[p].as_entire_binding()
                    }
                    Binding::Topo(t) => self.topo[t as usize].as_entire_binding(),
                    Binding::Launch => wgpu::BindingResource::Buffer(wgpu::BufferBinding {
                        buffer: &launch,
                        offset: 0,
                        size: wgpu::BufferSize::new(
                            self.scenes as u64
                                * launch_stride_of(&self.module, self.buffer_count, binding),
                        ),
                    }),
                    Binding::LaunchTable => launch.as_entire_binding(),
                };
                wgpu::BindGroupEntry { binding, resource }
            })
            .collect();
        let bg = self.device.create_bind_group(&wgpu::BindGroupDescriptor {
            label: Some(&k.name),
            layout: &self.pipelines[kernel].layout,
            entries: &entries,
        });
        self.groups.push(bg);
        self.bind_groups
            .insert((kernel, key.to_vec()), self.groups.len() - 1);
        self.groups.len() - 1
    }

    /// The physical buffers kernel `k` binds when the module's buffers are mapped by `slot`.
    fn key_of(&self, k: usize, slot: &[usize]) -> Vec<usize> {
        self.entry_kernel(k)
            .bindings
            .iter()
            .filter_map(|(_, w)| match w {
                Binding::Buffer { id, .. } => Some(slot[id.0 as usize]),
                _ => None,
            })
            .collect()
    }

    /// The entry point of pipeline `p`: a module kernel or a fused one.
    fn entry_kernel(&self, p: usize) -> &WgslKernel {
        match self.module.kernels.get(p) {
            Some(k) => k,
            None => &self.fused_kernels[&p],
        }
    }

    /// The pipelines of fused entry points for `groups` (kernels of the module, mutually
    /// independent), compiled once per group: one shader module for the new ones.
    fn fused_pipelines(&mut self, groups: &[Vec<usize>]) -> Result<Vec<usize>, String> {
        let new: Vec<Vec<usize>> = groups
            .iter()
            .filter(|g| !self.fused.contains_key(*g))
            .cloned()
            .collect();
        if !new.is_empty() {
            let wg = wgsl::emit_fused(&self.ir, self.module.precision, &new)?;
            let shader = self
                .device
                .create_shader_module(wgpu::ShaderModuleDescriptor {
                    label: Some("softc fused kernels"),
                    source: wgpu::ShaderSource::Wgsl(wg.source.as_str().into()),
                });
            let stride_of = |b: u32| launch_stride_of(&self.module, self.buffer_count, b);
            for (g, k) in new.iter().zip(&wg.kernels[self.module.kernels.len()..]) {
                let p = pipeline_for(
                    &self.device,
                    &shader,
                    k,
                    self.scenes as u64,
                    LaunchMode::Uniform,
                    &stride_of,
                );
                self.pipelines.push(p);
                let at = self.pipelines.len() - 1;
                self.fused.insert(g.clone(), at);
                self.fused_kernels.insert(at, k.clone());
            }
            if let Some(e) = self.take_error() {
                return Err(e);
            }
        }
        Ok(groups.iter().map(|g| self.fused[g]).collect())
    }

    /// Check a launch of kernel `k` over `range`; `Ok(None)` for an empty one, else its
    /// kernel's entity count.
    fn check_launch(&self, k: usize, range: &Range<usize>) -> Result<Option<()>, String> {
        let kernel = self
            .module
            .kernels
            .get(k)
            .ok_or_else(|| format!("no kernel {k}"))?;
        if self.topo.is_empty() {
            return Err("the backend is not prepared".into());
        }
        let n = domain_count(&self.counts, kernel.domain);
        if range.start > range.end || range.end > n {
            return Err(format!(
                "entity range {range:?} outside 0..{n} of kernel `{}`",
                kernel.name
            ));
        }
        if range.is_empty() {
            return Ok(None);
        }
        let groups = (range.len() as u64).div_ceil(u64::from(wgsl::WORKGROUP_SIZE));
        let max = u64::from(self.device.limits().max_compute_workgroups_per_dimension);
        if groups.div_ceil(max) > max {
            return Err(format!(
                "kernel `{}`: {} entities exceed one launch of this adapter",
                kernel.name,
                range.len()
            ));
        }
        Ok(Some(()))
    }

    /// The time loop of one scene (unbatched): `n` steps from step `first`, each setting
    /// `t = step · dt` where a kernel reads it, running `launches` in order and then swapping
    /// `swaps` in `slot`. Launch blocks are written once per step only for kernels that read
    /// `t` (once per submission for the others), bind groups are resolved once per buffer
    /// parity, and up to [`STEPS_PER_SUBMISSION`] steps go in one submission, submitted
    /// without waiting. The same dispatches, blocks and order as launching one by one.
    fn record_steps(&mut self, slot: &mut [usize], stepped: &Stepped<'_>) -> Result<(), String> {
        if let Some(e) = self.take_error() {
            return Err(e);
        }
        let start = (std::time::Instant::now(), self.stats.submit_seconds);
        self.drain();
        let recorded = self.record_steps_for(slot, stepped, &[(0, stepped.uniforms)]);
        self.add_host_time(start);
        recorded?;
        match self.take_error() {
            Some(e) => Err(e),
            None => Ok(()),
        }
    }

    /// [`Core::record_steps`] for the scenes `members` of a batch (scene, its uniforms), all
    /// with the same buffer slots: each dispatch runs the kernel for every member, one launch
    /// block each.
    fn record_steps_for(
        &mut self,
        slot: &mut [usize],
        stepped: &Stepped<'_>,
        members: &[(usize, &Uniforms)],
    ) -> Result<(), String> {
        let Stepped {
            launches,
            swaps,
            first,
            n,
            dt,
            uniforms: u,
            reverse,
            states,
        } = *stepped;
        let step_of = |j: u64| if reverse { first - j } else { first + j };
        if states.is_some() && members.len() != 1 {
            return Err("device state copies are for one scene".into());
        }
        if reverse && n > first + 1 {
            return Err(format!("{n} steps down from step {first}"));
        }
        let t_id = u.id("t");
        // Per launch: kernel, range, the position of `t` among its uniforms, its values.
        struct Plan {
            kernel: usize,
            begin: u32,
            count: u32,
            t_at: Option<usize>,
            /// Each member's values.
            values: Vec<Vec<f64>>,
            groups: (u32, u32, u32),
        }
        let mut plans = Vec::new();
        for (k, range) in launches {
            if self.check_launch(*k, range)?.is_none() {
                continue;
            }
            let kernel = &self.module.kernels[*k];
            let t_at = t_id.and_then(|t| kernel.uniforms.iter().position(|&id| id == t));
            let values = members
                .iter()
                .map(|(_, u)| kernel.uniforms.iter().map(|&id| u.get(id)).collect())
                .collect();
            plans.push(Plan {
                kernel: *k,
                begin: range.start as u32,
                count: range.len() as u32,
                t_at,
                values,
                groups: self.workgroups(range.len() as u64, members.len()),
            });
        }
        // Dispatch units: runs of consecutive launches with no data between them share a
        // dispatch (a fused entry point), one launch block each.
        let mut units: Vec<(usize, Vec<usize>)> = Vec::new();
        let fuse = self.fuse && self.scenes == 1 && self.module.launch == LaunchMode::Uniform;
        for (i, p) in plans.iter().enumerate() {
            let joins = fuse
                && units.last().is_some_and(|(_, members)| {
                    members.len() < MAX_PARTS
                        && members
                            .iter()
                            .all(|&m| wgsl::independent(&self.ir, plans[m].kernel, p.kernel))
                });
            match units.last_mut() {
                Some((_, members)) if joins => members.push(i),
                _ => units.push((p.kernel, vec![i])),
            }
        }
        for unit in &mut units {
            if unit.1.len() > 1 {
                unit.1.sort_by_key(|&m| plans[m].kernel);
                let kernels: Vec<usize> = unit.1.iter().map(|&m| plans[m].kernel).collect();
                unit.0 = self.fused_pipelines(&[kernels])?[0];
            }
        }
        let unit_groups: Vec<(u32, u32, u32)> = units
            .iter()
            .map(|(_, members)| {
                let count: u64 = members.iter().map(|&m| u64::from(plans[m].count)).sum();
                if members.len() == 1 {
                    plans[members[0]].groups
                } else {
                    self.workgroups(count, 1)
                }
            })
            .collect();
        // Bind groups by parity: two steps' swaps bring pairs of distinct buffers back.
        let swap_all = |slot: &mut [usize]| {
            for (a, b) in swaps {
                slot.swap(a.0 as usize, b.0 as usize);
            }
        };
        let mut after_two = slot.to_vec();
        swap_all(&mut after_two);
        swap_all(&mut after_two);
        let periodic = after_two == slot;
        let mut done = 0u64;
        while done < n {
            let chunk = (n - done).min(STEPS_PER_SUBMISSION);
            // Room for every block of the chunk, so that nothing is submitted half-way.
            let bytes: u64 = plans
                .iter()
                .map(|p| {
                    let align = self.block_align(p.kernel);
                    let span = round_up(
                        self.scenes as u64 * self.module.kernels[p.kernel].launch_stride(),
                        align,
                    );
                    span * if p.t_at.is_some() { chunk } else { 1 } + align
                })
                .sum();
            self.reserve(bytes);
            // Blocks: one per step for kernels reading `t`, else one for the chunk.
            let mut args = Vec::with_capacity(plans.len());
            for (i, p) in plans.iter().enumerate() {
                let rows = if p.t_at.is_some() { chunk } else { 1 };
                let (at, arg) = self.alloc_blocks(p.kernel, rows);
                let span = round_up(
                    self.scenes as u64 * self.module.kernels[p.kernel].launch_stride(),
                    self.block_align(p.kernel),
                ) as usize;
                for (j, &(scene, _)) in members.iter().enumerate() {
                    let mut values = p.values[j].clone();
                    for r in 0..rows {
                        if let Some(ti) = p.t_at {
                            values[ti] = step_of(done + r) as f64 * dt;
                        }
                        self.write_block(
                            at + r as usize * span,
                            j,
                            p.kernel,
                            scene,
                            p.begin,
                            p.count,
                            values.iter().copied(),
                        );
                    }
                }
                args.push((i, arg));
            }
            let mut parity: [Option<Vec<usize>>; 2] = [None, None];
            for s in 0..chunk {
                if let Some(copy) = states {
                    let (store, x, v) = match copy {
                        StateCopy::Store { x, v } => (true, x, v),
                        StateCopy::Restore { x, v } => (false, x, v),
                    };
                    let (x, v) = (slot[x.0 as usize], slot[v.0 as usize]);
                    let d = self.state_copy(store, step_of(done + s) as usize, x, v)?;
                    self.pending.push(d);
                    self.stats.launches += 1;
                }
                let groups = match (periodic, &parity[(s % 2) as usize]) {
                    (true, Some(g)) => g.clone(),
                    _ => {
                        let g: Vec<usize> = units
                            .iter()
                            .map(|&(pipeline, _)| {
                                let key = self.key_of(pipeline, slot);
                                self.bind_group(pipeline, &key)
                            })
                            .collect();
                        parity[(s % 2) as usize] = Some(g.clone());
                        g
                    }
                };
                for (((pipeline, members), group), &workgroups) in
                    units.iter().zip(groups).zip(&unit_groups)
                {
                    let mut d = Dispatch::one(*pipeline, group, 0, workgroups);
                    for (j, &m) in members.iter().enumerate() {
                        let p = &plans[m];
                        let arg = args[m].1;
                        d.args[j] = if p.t_at.is_some() {
                            self.next_arg(p.kernel, arg, s)
                        } else {
                            arg
                        };
                    }
                    d.parts = members.len() as u8;
                    self.pending.push(d);
                }
                swap_all(slot);
            }
            self.stats.launches += chunk * (plans.len() * members.len()) as u64;
            done += chunk;
            // A full chunk goes now; the rest with what follows it (the state check's step
            // and readback copy share its submission).
            if chunk == STEPS_PER_SUBMISSION {
                self.submit();
            }
        }
        Ok(())
    }

    /// Submit the pending dispatches in one compute pass (their blocks are in the staging
    /// area), without waiting.
    fn submit(&mut self) {
        if !self.pending.is_empty() {
            self.submit_with(|_| {});
        }
        self.staging.clear();
    }

    /// Submit the pending dispatches in one compute pass followed by `after`'s commands (a
    /// readback's copies) in the same submission; returns its index.
    fn submit_with(
        &mut self,
        after: impl FnOnce(&mut wgpu::CommandEncoder),
    ) -> wgpu::SubmissionIndex {
        let mut enc = self
            .device
            .create_command_encoder(&wgpu::CommandEncoderDescriptor {
                label: Some("softc steps"),
            });
        if self.pending.is_empty() {
            after(&mut enc);
            let index = self.queue.submit([enc.finish()]);
            self.stats.submissions += 1;
            return index;
        }
        // (Only state copies pending: no launch blocks.)
        if let Some(launch) = &self.launch_buffer
            && !self.staging.is_empty()
        {
            self.queue.write_buffer(launch, 0, &self.staging);
        }
        if self.timing.as_ref().is_some_and(|t| t.used == t.pairs)
            && let Some(t) = self.timing.as_mut()
        {
            t.collect(&self.device, &self.queue);
        }
        let pair = self.timing.as_mut().and_then(Timing::next_pair);
        {
            let timestamp_writes = match (&self.timing, pair) {
                (Some(t), Some(i)) => Some(wgpu::ComputePassTimestampWrites {
                    query_set: &t.set,
                    beginning_of_pass_write_index: Some(i),
                    end_of_pass_write_index: Some(i + 1),
                }),
                _ => None,
            };
            let mut pass = enc.begin_compute_pass(&wgpu::ComputePassDescriptor {
                label: Some("softc steps"),
                timestamp_writes,
            });
            let table = self.module.launch == LaunchMode::Table;
            let kernels = self.module.kernels.len();
            let mut bound: Option<(usize, usize)> = None;
            for d in &self.pending {
                if bound.is_none_or(|(k, _)| k != d.kernel) {
                    pass.set_pipeline(&self.pipelines[d.kernel].pipeline);
                }
                if d.kernel >= kernels {
                    // Fused kernels (a launch block each) or a state copy (its slot).
                    pass.set_bind_group(0, &self.groups[d.group], &d.args[..d.parts as usize]);
                } else if table {
                    if bound.is_none_or(|(_, g)| g != d.group) {
                        pass.set_bind_group(0, &self.groups[d.group], &[]);
                    }
                    pass.set_immediates(0, &d.args[0].to_le_bytes());
                } else {
                    pass.set_bind_group(0, &self.groups[d.group], &d.args[..1]);
                }
                bound = Some((d.kernel, d.group));
                pass.dispatch_workgroups(d.groups.0, d.groups.1, d.groups.2);
            }
        }
        if let (Some(t), Some(i)) = (&self.timing, pair) {
            t.resolve(&mut enc, i);
        }
        after(&mut enc);
        let commands = enc.finish();
        let queued = std::time::Instant::now();
        let index = self.queue.submit([commands]);
        self.stats.submit_seconds += queued.elapsed().as_secs_f64();
        self.stats.dispatches += self.pending.len() as u64;
        self.stats.submissions += 1;
        self.pending.clear();
        self.staging.clear();
        index
    }

    /// Start reading `(physical buffer, scene)` pairs back: submits what is recorded and a
    /// copy into a readback buffer, maps it without waiting; [`Core::collect`] waits for that
    /// submission only, so the GPU runs on with what is submitted after.
    fn read_later(&mut self, requests: &[(usize, usize)]) -> Result<u64, String> {
        let start = (std::time::Instant::now(), self.stats.submit_seconds);
        self.drain();
        self.stats.readbacks += 1;
        let size = self.module.precision.size();
        let mut spans = Vec::new();
        let mut total = 0u64;
        for &(phys, scene) in requests {
            let n = *self
                .lens
                .get(phys)
                .ok_or_else(|| format!("no buffer {phys}"))?;
            let bytes = (n * size) as u64;
            spans.push((phys, (scene * n * size) as u64, total, bytes));
            total = round_up(total + bytes, 256);
        }
        let total = total.max(256);
        let buffer = match self.spare_readbacks.iter().position(|b| b.size() >= total) {
            Some(i) => self.spare_readbacks.swap_remove(i),
            None => self.device.create_buffer(&wgpu::BufferDescriptor {
                label: Some("softc readback"),
                size: total.next_power_of_two(),
                usage: wgpu::BufferUsages::MAP_READ | wgpu::BufferUsages::COPY_DST,
                mapped_at_creation: false,
            }),
        };
        // The copies go in the submission of the work recorded before them.
        let sources: Vec<wgpu::Buffer> = spans
            .iter()
            .map(|&(phys, ..)| self.buffers[phys].clone())
            .collect();
        let index = self.submit_with(|enc| {
            for (src, &(_, from, to, bytes)) in sources.iter().zip(&spans) {
                if bytes > 0 {
                    enc.copy_buffer_to_buffer(src, from, &buffer, to, bytes);
                }
            }
        });
        self.staging.clear();
        self.add_host_time(start);
        let (tx, rx) = std::sync::mpsc::channel();
        buffer.map_async(wgpu::MapMode::Read, 0..total, move |r| {
            let _ = tx.send(r);
        });
        self.next_ticket += 1;
        let ticket = self.next_ticket;
        self.in_flight.insert(
            ticket,
            InFlight {
                buffer,
                total,
                spans: spans.iter().map(|s| (s.2, s.3)).collect(),
                index,
                mapped: rx,
            },
        );
        Ok(ticket)
    }

    /// The values of a [`Core::read_later`] (waits for its copy).
    fn collect(&mut self, ticket: u64) -> Result<Vec<Vec<f64>>, String> {
        let f = self
            .in_flight
            .remove(&ticket)
            .ok_or_else(|| format!("no readback {ticket} under way"))?;
        self.device
            .poll(wgpu::PollType::Wait {
                submission_index: Some(f.index),
                timeout: None,
            })
            .map_err(|e| format!("GPU ({}): {e}", self.adapter))?;
        match f.mapped.recv() {
            Ok(Ok(())) => {}
            _ => {
                return Err(format!(
                    "GPU ({}): reading a buffer back failed",
                    self.adapter
                ));
            }
        }
        let out = {
            let view = f
                .buffer
                .get_mapped_range(0..f.total)
                .map_err(|e| format!("GPU ({}): {e}", self.adapter))?;
            f.spans
                .iter()
                .map(|&(to, bytes)| self.values(&view[to as usize..(to + bytes) as usize]))
                .collect()
        };
        f.buffer.unmap();
        self.spare_readbacks.push(f.buffer);
        if let Some(e) = self.take_error() {
            return Err(e);
        }
        Ok(out)
    }

    /// Values of the module's precision from their bytes.
    fn values(&self, bytes: &[u8]) -> Vec<f64> {
        match self.module.precision {
            Precision::F32 => bytes
                .chunks_exact(4)
                .map(|c| f64::from(f32::from_le_bytes([c[0], c[1], c[2], c[3]])))
                .collect(),
            Precision::F64 => bytes
                .chunks_exact(8)
                .map(|c| {
                    let mut a = [0u8; 8];
                    a.copy_from_slice(c);
                    f64::from_le_bytes(a)
                })
                .collect(),
        }
    }

    /// Reserve `slots` device slots of `len` values each (x then v) and build the copy
    /// kernels; `None` when they do not fit [`DEVICE_STATE_BYTES`] or the device's memory.
    fn device_states(&mut self, slots: usize, len: usize) -> Result<Option<u64>, String> {
        self.flush();
        self.states = None;
        let size = self.module.precision.size() as u64;
        let limits = self.device.limits();
        let align = u64::from(limits.min_storage_buffer_offset_alignment).max(256);
        let slot_bytes = round_up(2 * len as u64 * size, align);
        let total = slot_bytes.saturating_mul(slots as u64);
        let cap = device_state_limit();
        if slots == 0 || total > cap || slot_bytes > limits.max_storage_buffer_binding_size {
            return Ok(None);
        }
        let per_chunk = (limits.max_buffer_size.min(1 << 30) / slot_bytes).max(1) as usize;
        // Out of memory: keep the states on the host instead.
        let scope = self.device.push_error_scope(wgpu::ErrorFilter::OutOfMemory);
        let mut chunks = Vec::new();
        let mut left = slots;
        while left > 0 {
            let n = left.min(per_chunk);
            chunks.push(self.device.create_buffer(&wgpu::BufferDescriptor {
                label: Some("softc device states"),
                size: n as u64 * slot_bytes,
                usage: wgpu::BufferUsages::STORAGE,
                mapped_at_creation: false,
            }));
            left -= n;
        }
        if pollster::block_on(scope.pop()).is_some() {
            return Ok(None);
        }
        let real = match self.module.precision {
            Precision::F32 => "f32",
            Precision::F64 => "f64",
        };
        let entry = |binding: u32, read_only: bool, dynamic: bool| wgpu::BindGroupLayoutEntry {
            binding,
            visibility: wgpu::ShaderStages::COMPUTE,
            ty: wgpu::BindingType::Buffer {
                ty: wgpu::BufferBindingType::Storage { read_only },
                has_dynamic_offset: dynamic,
                min_binding_size: None,
            },
            count: None,
        };
        let first = self.pipelines.len();
        for (name, entries) in [
            (
                "store",
                [
                    entry(0, true, false),
                    entry(1, true, false),
                    entry(2, false, true),
                ],
            ),
            (
                "restore",
                [
                    entry(0, false, false),
                    entry(1, false, false),
                    entry(2, true, true),
                ],
            ),
        ] {
            let shader = self
                .device
                .create_shader_module(wgpu::ShaderModuleDescriptor {
                    label: Some(name),
                    source: wgpu::ShaderSource::Wgsl(
                        state_copy_wgsl(real, len, name == "store").into(),
                    ),
                });
            let layout = self
                .device
                .create_bind_group_layout(&wgpu::BindGroupLayoutDescriptor {
                    label: Some(name),
                    entries: &entries,
                });
            let pl = self
                .device
                .create_pipeline_layout(&wgpu::PipelineLayoutDescriptor {
                    label: Some(name),
                    bind_group_layouts: &[Some(&layout)],
                    immediate_size: 0,
                });
            let pipeline = self
                .device
                .create_compute_pipeline(&wgpu::ComputePipelineDescriptor {
                    label: Some(name),
                    layout: Some(&pl),
                    module: &shader,
                    entry_point: Some(name),
                    compilation_options: Default::default(),
                    cache: None,
                });
            self.pipelines.push(Pipeline { pipeline, layout });
        }
        if let Some(e) = self.take_error() {
            return Err(e);
        }
        self.states = Some(DeviceStates {
            chunks,
            per_chunk,
            slot_bytes,
            slots,
            len,
            store: first,
            restore: first + 1,
        });
        Ok(Some(total))
    }

    /// Record a copy between the state buffers `x`, `v` (physical) and device slot `slot`:
    /// `store` into the slot, else out of it. A dispatch in the step's compute pass.
    fn record_state_copy(
        &mut self,
        store: bool,
        slot: usize,
        x: usize,
        v: usize,
    ) -> Result<(), String> {
        let start = (std::time::Instant::now(), self.stats.submit_seconds);
        self.drain();
        let d = self.state_copy(store, slot, x, v)?;
        self.pending.push(d);
        self.stats.launches += 1;
        if self.pending.len() >= MAX_PENDING {
            self.submit();
        }
        self.add_host_time(start);
        Ok(())
    }

    /// The dispatch of a copy between the state buffers `x`, `v` (physical) and device slot
    /// `slot`: `store` into the slot, else out of it.
    fn state_copy(
        &mut self,
        store: bool,
        slot: usize,
        x: usize,
        v: usize,
    ) -> Result<Dispatch, String> {
        let Some(st) = &self.states else {
            return Err("no device states reserved".into());
        };
        if slot >= st.slots {
            return Err(format!("device state slot {slot} of {}", st.slots));
        }
        if self.lens[x] != st.len || self.lens[v] != st.len {
            return Err("a device state copy of buffers of another size".into());
        }
        let (chunk, offset) = (
            slot / st.per_chunk,
            (slot % st.per_chunk) as u64 * st.slot_bytes,
        );
        let kernel = if store { st.store } else { st.restore };
        let (count, slot_bytes) = (st.len as u64, st.slot_bytes);
        let key = vec![x, v, chunk];
        let group = match self.bind_groups.get(&(kernel, key.clone())) {
            Some(&g) => g,
            None => {
                let st = self.states.as_ref().ok_or("no device states")?;
                let bg = self.device.create_bind_group(&wgpu::BindGroupDescriptor {
                    label: Some("softc state copy"),
                    layout: &self.pipelines[kernel].layout,
                    entries: &[
                        wgpu::BindGroupEntry {
                            binding: 0,
                            resource: self.buffers[x].as_entire_binding(),
                        },
                        wgpu::BindGroupEntry {
                            binding: 1,
                            resource: self.buffers[v].as_entire_binding(),
                        },
                        wgpu::BindGroupEntry {
                            binding: 2,
                            resource: wgpu::BindingResource::Buffer(wgpu::BufferBinding {
                                buffer: &st.chunks[chunk],
                                offset: 0,
                                size: wgpu::BufferSize::new(slot_bytes),
                            }),
                        },
                    ],
                });
                self.groups.push(bg);
                self.bind_groups
                    .insert((kernel, key), self.groups.len() - 1);
                self.groups.len() - 1
            }
        };
        let groups = self.workgroups(count, 1);
        Ok(Dispatch::one(kernel, group, offset as u32, groups))
    }

    /// Read back the values of `(physical buffer, scene)` pairs: submits what is recorded,
    /// then one copy per request into one readback buffer, one map, one wait.
    fn read(&mut self, requests: &[(usize, usize)]) -> Result<Vec<Vec<f64>>, String> {
        self.flush();
        self.stats.readbacks += 1;
        let size = self.module.precision.size();
        let mut spans = Vec::new();
        let mut total = 0u64;
        for &(phys, scene) in requests {
            let n = *self
                .lens
                .get(phys)
                .ok_or_else(|| format!("no buffer {phys}"))?;
            let bytes = (n * size) as u64;
            spans.push((phys, (scene * n * size) as u64, total, bytes));
            total = round_up(total + bytes, 256);
        }
        if total == 0 {
            return Ok(requests.iter().map(|_| Vec::new()).collect());
        }
        if self.readback.as_ref().is_none_or(|r| r.size() < total) {
            self.readback = Some(self.device.create_buffer(&wgpu::BufferDescriptor {
                label: Some("softc readback"),
                size: total.next_power_of_two(),
                usage: wgpu::BufferUsages::MAP_READ | wgpu::BufferUsages::COPY_DST,
                mapped_at_creation: false,
            }));
        }
        let rb = self.readback.clone().ok_or("no readback buffer")?;
        let mut enc = self
            .device
            .create_command_encoder(&wgpu::CommandEncoderDescriptor {
                label: Some("softc read"),
            });
        for &(phys, from, to, bytes) in &spans {
            if bytes > 0 {
                enc.copy_buffer_to_buffer(&self.buffers[phys], from, &rb, to, bytes);
            }
        }
        self.queue.submit([enc.finish()]);
        let (tx, rx) = std::sync::mpsc::channel();
        rb.map_async(wgpu::MapMode::Read, 0..total, move |r| {
            let _ = tx.send(r);
        });
        self.device
            .poll(wgpu::PollType::wait_indefinitely())
            .map_err(|e| format!("GPU ({}): {e}", self.adapter))?;
        match rx.recv() {
            Ok(Ok(())) => {}
            _ => {
                return Err(format!(
                    "GPU ({}): reading a buffer back failed",
                    self.adapter
                ));
            }
        }
        let out = {
            let view = rb
                .get_mapped_range(0..total)
                .map_err(|e| format!("GPU ({}): {e}", self.adapter))?;
            spans
                .iter()
                .map(|&(_, _, to, bytes)| {
                    let bytes = &view[to as usize..(to + bytes) as usize];
                    match self.module.precision {
                        Precision::F32 => bytes
                            .chunks_exact(4)
                            .map(|c| f64::from(f32::from_le_bytes([c[0], c[1], c[2], c[3]])))
                            .collect(),
                        Precision::F64 => bytes
                            .chunks_exact(8)
                            .map(|c| {
                                let mut a = [0u8; 8];
                                a.copy_from_slice(c);
                                f64::from_le_bytes(a)
                            })
                            .collect(),
                    }
                })
                .collect()
        };
        rb.unmap();
        if let Some(e) = self.take_error() {
            return Err(e);
        }
        Ok(out)
    }

    /// A failed readback (a lost device, a mapping error) cannot be returned from
    /// [`Backend::get`]: it is recorded, reported by the next launch or state check, and the
    /// values are NaN.
    fn values_or_nan(&self, phys: usize, r: Result<Vec<f64>, String>) -> Vec<f64> {
        r.unwrap_or_else(|e| {
            if let Ok(mut errors) = self.errors.lock() {
                errors.push(e);
            }
            vec![f64::NAN; self.lens.get(phys).copied().unwrap_or(0)]
        })
    }

    /// Lockstep: when every scene of the group waits for a readback, read them all at once.
    fn serve_if_ready(&mut self) -> bool {
        let ready = (0..self.scenes).any(|s| self.waiting[s].is_some())
            && (0..self.scenes).all(|s| !self.active[s] || self.waiting[s].is_some());
        if !ready {
            return false;
        }
        let requests: Vec<(usize, usize)> = (0..self.scenes)
            .filter_map(|s| self.waiting[s].map(|p| (p, s)))
            .collect();
        match self.read(&requests) {
            Ok(values) => {
                for (&(_, s), v) in requests.iter().zip(values) {
                    self.served[s] = Some(Ok(v));
                }
            }
            Err(e) => {
                for &(_, s) in &requests {
                    self.served[s] = Some(Err(e.clone()));
                }
            }
        }
        for w in &mut self.waiting {
            *w = None;
        }
        true
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
        core.allocate(n_nodes, tets, tris, &ne, &nt)?;
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
            &scene.mesh.tets,
            &scene.tris,
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
                &scene.mesh.tets,
                &scene.tris,
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
