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

use super::{Backend, Lockstep, Uniforms};
use crate::engine::scene::{Csr, Scene};
use softc_compiler::back::Precision;
use softc_compiler::back::wgsl::{self, Binding, TopoArray, WgslModule};
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
}

/// A dispatch of one submission: a kernel over one or more scenes.
struct Dispatch {
    kernel: usize,
    key: Vec<usize>,
    offset: u32,
    groups: (u32, u32, u32),
}

/// Launches recorded and dispatches submitted: how well a batch merges.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct DispatchStats {
    /// Kernel launches the scenes recorded.
    pub launches: u64,
    /// Dispatches submitted for them (one per launch unbatched; as few as launches / scenes
    /// when a batch runs in lockstep).
    pub dispatches: u64,
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
    uniform: Option<wgpu::Buffer>,
    staging: Vec<u8>,
    /// Each scene's recorded operations.
    queues: Vec<VecDeque<Op>>,
    recorded: usize,
    bind_groups: HashMap<(usize, Vec<usize>), wgpu::BindGroup>,
    readback: Option<wgpu::Buffer>,
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
        let wg = match batch {
            Some(n) => wgsl::emit_batched(module, precision, n)?,
            None => wgsl::emit(module, precision)?,
        };
        let scenes = batch.unwrap_or(1) as u64;
        let limits = chosen.limits();
        for k in &wg.kernels {
            if k.storage_buffers > limits.max_storage_buffers_per_shader_stage {
                return Err(format!(
                    "kernel `{}` binds {} storage buffers; adapter {desc} allows {} per shader stage",
                    k.name, k.storage_buffers, limits.max_storage_buffers_per_shader_stage
                ));
            }
            let blocks = scenes * round_up(k.launch_size, 16);
            if blocks > limits.max_uniform_buffer_binding_size {
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
        let mut pipelines = Vec::new();
        for k in &wg.kernels {
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
                        Binding::Topo(_) => wgpu::BindingType::Buffer {
                            ty: wgpu::BufferBindingType::Storage { read_only: true },
                            has_dynamic_offset: false,
                            min_binding_size: None,
                        },
                        Binding::Launch => wgpu::BindingType::Buffer {
                            ty: wgpu::BufferBindingType::Uniform,
                            has_dynamic_offset: true,
                            min_binding_size: wgpu::BufferSize::new(
                                scenes * round_up(k.launch_size, 16),
                            ),
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
                immediate_size: 0,
            });
            let pipeline = device.create_compute_pipeline(&wgpu::ComputePipelineDescriptor {
                label: Some(&k.name),
                layout: Some(&pl),
                module: &shader,
                entry_point: Some(&k.entry),
                compilation_options: Default::default(),
                cache: None,
            });
            pipelines.push(Pipeline { pipeline, layout });
        }
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
            uniform: None,
            staging: Vec::new(),
            queues: (0..scenes).map(|_| VecDeque::new()).collect(),
            recorded: 0,
            bind_groups: HashMap::new(),
            readback: None,
            stats: DispatchStats::default(),
            active: vec![false; scenes],
            waiting: vec![None; scenes],
            served: (0..scenes).map(|_| None).collect(),
        })
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
            self.flush();
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
            return Ok(());
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
        let key = kernel
            .bindings
            .iter()
            .filter_map(|(_, w)| match w {
                Binding::Buffer { id, .. } => Some(slot[id.0 as usize]),
                _ => None,
            })
            .collect();
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
        )
    }

    /// Submit every scene's recorded operations, each scene's in its order. The scenes' next
    /// launches of the same kernel on the same buffers become one dispatch; a `set` waits
    /// until no scene has a launch before its own next `set`, so the writes of a batch in
    /// lockstep cost one break in the submission.
    fn flush(&mut self) {
        let mut dispatches: Vec<Dispatch> = Vec::new();
        loop {
            let heads: Vec<usize> = (0..self.scenes)
                .filter(|&s| !self.queues[s].is_empty())
                .collect();
            if heads.is_empty() {
                break;
            }
            let runs: Vec<usize> = heads
                .iter()
                .copied()
                .filter(|&s| matches!(self.queues[s].front(), Some(Op::Run { .. })))
                .collect();
            if runs.is_empty() {
                // Only writes at the heads: what is recorded reads the old contents.
                self.submit(&mut dispatches);
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
                let offset = self.write_blocks(kernel, &members);
                let count = members
                    .iter()
                    .filter_map(|&s| match self.queues[s].front() {
                        Some(Op::Run { count, .. }) => Some(u64::from(*count)),
                        _ => None,
                    })
                    .max()
                    .unwrap_or(0);
                for &s in &members {
                    self.queues[s].pop_front();
                }
                let groups = count.div_ceil(u64::from(wgsl::WORKGROUP_SIZE));
                let max = u64::from(self.device.limits().max_compute_workgroups_per_dimension);
                let gx = groups.min(max);
                dispatches.push(Dispatch {
                    kernel,
                    key,
                    offset,
                    groups: (gx as u32, groups.div_ceil(gx) as u32, members.len() as u32),
                });
            }
        }
        self.submit(&mut dispatches);
        self.recorded = 0;
    }

    /// Write the launch blocks of the head launches of `members` (one per scene, consecutive)
    /// into the staging area; returns their offset.
    fn write_blocks(&mut self, kernel: usize, members: &[usize]) -> u32 {
        let k = &self.module.kernels[kernel];
        let stride = round_up(k.launch_size, 16) as usize;
        let offset = round_up(self.staging.len() as u64, u64::from(self.align)) as usize;
        // The binding covers every scene's block, used or not.
        self.staging.resize(offset + self.scenes * stride, 0);
        for (j, &s) in members.iter().enumerate() {
            let Some(Op::Run {
                begin,
                count,
                values,
                ..
            }) = self.queues[s].front()
            else {
                continue;
            };
            let mut block: Vec<u8> = Vec::with_capacity(stride);
            block.extend_from_slice(&begin.to_le_bytes());
            block.extend_from_slice(&count.to_le_bytes());
            if self.module.batch.is_some() {
                for v in [s, self.counts[0], self.counts[1], self.counts[2]] {
                    block.extend_from_slice(&(v as u32).to_le_bytes());
                }
            }
            block.resize(k.uniform_offset as usize, 0);
            for &v in values {
                match self.module.precision {
                    Precision::F32 => block.extend_from_slice(&(v as f32).to_le_bytes()),
                    Precision::F64 => block.extend_from_slice(&v.to_le_bytes()),
                }
            }
            let at = offset + j * stride;
            self.staging[at..at + block.len()].copy_from_slice(&block);
        }
        offset as u32
    }

    /// Submit `dispatches` in one compute pass (their blocks are in the staging area).
    fn submit(&mut self, dispatches: &mut Vec<Dispatch>) {
        if dispatches.is_empty() {
            self.staging.clear();
            return;
        }
        let need = self.staging.len() as u64;
        if self.uniform.as_ref().is_none_or(|u| u.size() < need) {
            let size = need.next_power_of_two().max(4096);
            self.uniform = Some(self.device.create_buffer(&wgpu::BufferDescriptor {
                label: Some("softc launch blocks"),
                size,
                usage: wgpu::BufferUsages::UNIFORM | wgpu::BufferUsages::COPY_DST,
                mapped_at_creation: false,
            }));
            self.bind_groups.clear();
        }
        let Some(uniform) = self.uniform.clone() else {
            return;
        };
        self.queue.write_buffer(&uniform, 0, &self.staging);
        // Bind groups first (the pass borrows them).
        for d in dispatches.iter() {
            let cache_key = (d.kernel, d.key.clone());
            if self.bind_groups.contains_key(&cache_key) {
                continue;
            }
            let k = &self.module.kernels[d.kernel];
            let mut phys = d.key.iter();
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
                            buffer: &uniform,
                            offset: 0,
                            size: wgpu::BufferSize::new(
                                self.scenes as u64 * round_up(k.launch_size, 16),
                            ),
                        }),
                    };
                    wgpu::BindGroupEntry { binding, resource }
                })
                .collect();
            let bg = self.device.create_bind_group(&wgpu::BindGroupDescriptor {
                label: Some(&k.name),
                layout: &self.pipelines[d.kernel].layout,
                entries: &entries,
            });
            self.bind_groups.insert(cache_key, bg);
        }
        let mut enc = self
            .device
            .create_command_encoder(&wgpu::CommandEncoderDescriptor {
                label: Some("softc steps"),
            });
        {
            let mut pass = enc.begin_compute_pass(&wgpu::ComputePassDescriptor {
                label: Some("softc steps"),
                timestamp_writes: None,
            });
            for d in dispatches.iter() {
                let bg = &self.bind_groups[&(d.kernel, d.key.clone())];
                pass.set_pipeline(&self.pipelines[d.kernel].pipeline);
                pass.set_bind_group(0, bg, &[d.offset]);
                pass.dispatch_workgroups(d.groups.0, d.groups.1, d.groups.2);
            }
        }
        self.queue.submit([enc.finish()]);
        self.stats.dispatches += dispatches.len() as u64;
        dispatches.clear();
        self.staging.clear();
    }

    /// Read back the values of `(physical buffer, scene)` pairs: submits what is recorded,
    /// then one copy per request into one readback buffer, one map, one wait.
    fn read(&mut self, requests: &[(usize, usize)]) -> Result<Vec<Vec<f64>>, String> {
        self.flush();
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
            core: RefCell::new(Core::open(module, precision, adapter, None)?),
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
                core: Mutex::new(Core::open(module, precision, adapter, Some(n))?),
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

    /// Launches recorded and dispatches submitted so far.
    pub fn stats(&self) -> DispatchStats {
        self.shared.lock().stats
    }
}

/// One scene of a [`GpuBatch`].
pub struct GpuScene {
    shared: Arc<Shared>,
    scene: usize,
    slot: Vec<usize>,
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
