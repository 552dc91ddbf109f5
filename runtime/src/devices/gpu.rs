//! The GPU device: a scene's kernels as WGSL ([`softc_compiler::back::wgsl`]) run by wgpu on
//! any adapter (Vulkan, Metal, DX12; Mesa's lavapipe on machines without a GPU).
//!
//! Few host round trips: [`Backend::run`] only records a launch (its uniforms go into a host
//! staging area at an aligned offset of one uniform buffer, bound with a dynamic offset);
//! [`Backend::swap`] exchanges buffer handles host-side (bind groups are cached per
//! combination of physical buffers, so double-buffered state costs two bind groups per
//! kernel); the recorded launches are submitted in one compute pass only when data has to
//! cross (`get`, `set`) or [`MAX_PENDING`] launches have accumulated. The engine reads the
//! state every 50 steps, so ~50 steps × (kernels per step) launches go in one submission.
//!
//! Results match the CPU backend up to floating-point rounding: f32 kernels on the GPU round
//! differently from Cranelift's (fused or reordered operations are the driver's choice, and
//! `exp`/`log`/`pow` are the driver's), f64 kernels use the software transcendental functions
//! of the WGSL backend.

use crate::engine::scene::{Csr, Scene};
use crate::engine::{Backend, Uniforms};
use softc_compiler::back::Precision;
use softc_compiler::back::wgsl::{self, Binding, TopoArray, WgslModule};
use softc_compiler::ir::{BufferId, Domain, Module};
use std::cell::RefCell;
use std::collections::HashMap;
use std::ops::Range;
use std::sync::{Arc, Mutex};

/// Launches recorded before a submission is forced (bounds the uniform staging area).
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

/// A recorded launch.
struct Launch {
    kernel: usize,
    /// Physical buffers of the kernel's buffer bindings (the bind group's cache key).
    key: Vec<usize>,
    offset: u32,
    groups: (u32, u32),
}

/// Buffers and recorded work (behind a `RefCell`: `Backend::get` takes `&self` and submits).
#[derive(Default)]
struct State {
    /// Physical buffers; `slot[b]` is the one buffer `b` names now (swaps permute `slot`).
    buffers: Vec<wgpu::Buffer>,
    slot: Vec<usize>,
    /// Values of each buffer (by `BufferId`).
    lens: Vec<usize>,
    topo: Vec<wgpu::Buffer>,
    /// Entities per domain of the prepared scene: element, triangle, node.
    counts: [usize; 3],
    uniform: Option<wgpu::Buffer>,
    staging: Vec<u8>,
    pending: Vec<Launch>,
    bind_groups: HashMap<(usize, Vec<usize>), wgpu::BindGroup>,
    readback: Option<wgpu::Buffer>,
}

/// Runs kernels on a GPU through wgpu.
pub struct Gpu {
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
    state: RefCell<State>,
}

fn round_up(x: u64, a: u64) -> u64 {
    x.div_ceil(a) * a
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
        let wg = wgsl::emit(module, precision)?;
        let limits = chosen.limits();
        for k in &wg.kernels {
            if k.storage_buffers > limits.max_storage_buffers_per_shader_stage {
                return Err(format!(
                    "kernel `{}` binds {} storage buffers; adapter {desc} allows {} per shader stage",
                    k.name, k.storage_buffers, limits.max_storage_buffers_per_shader_stage
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
                            min_binding_size: wgpu::BufferSize::new(round_up(k.launch_size, 16)),
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
        Ok(Gpu {
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
            state: RefCell::new(State::default()),
        })
    }

    /// The adapter in use.
    pub fn adapter(&self) -> &AdapterDesc {
        &self.adapter
    }

    pub fn precision(&self) -> Precision {
        self.module.precision
    }

    /// The WGSL source the kernels run.
    pub fn wgsl(&self) -> &str {
        &self.module.source
    }

    fn take_error(&self) -> Option<String> {
        self.errors.lock().ok().and_then(|mut v| v.drain(..).next())
    }

    /// Submit the recorded launches (without waiting for them).
    pub fn flush(&self) -> Result<(), String> {
        let mut st = self.state.borrow_mut();
        self.flush_state(&mut st);
        match self.take_error() {
            Some(e) => Err(format!("GPU ({}): {e}", self.adapter)),
            None => Ok(()),
        }
    }

    fn flush_state(&self, st: &mut State) {
        if st.pending.is_empty() {
            return;
        }
        let need = st.staging.len() as u64;
        if st.uniform.as_ref().is_none_or(|u| u.size() < need) {
            let size = need.next_power_of_two().max(4096);
            st.uniform = Some(self.device.create_buffer(&wgpu::BufferDescriptor {
                label: Some("softc launch blocks"),
                size,
                usage: wgpu::BufferUsages::UNIFORM | wgpu::BufferUsages::COPY_DST,
                mapped_at_creation: false,
            }));
            st.bind_groups.clear();
        }
        let Some(uniform) = st.uniform.clone() else {
            return;
        };
        self.queue.write_buffer(&uniform, 0, &st.staging);
        // Bind groups first (the pass borrows them).
        let pending = std::mem::take(&mut st.pending);
        for l in &pending {
            let key = (l.kernel, l.key.clone());
            if st.bind_groups.contains_key(&key) {
                continue;
            }
            let k = &self.module.kernels[l.kernel];
            let mut phys = l.key.iter();
            let entries: Vec<wgpu::BindGroupEntry> = k
                .bindings
                .iter()
                .map(|&(binding, what)| {
                    let resource = match what {
                        Binding::Buffer { .. } => {
                            let p = *phys.next().unwrap_or(&0);
                            st.buffers[p].as_entire_binding()
                        }
                        Binding::Topo(t) => st.topo[t as usize].as_entire_binding(),
                        Binding::Launch => wgpu::BindingResource::Buffer(wgpu::BufferBinding {
                            buffer: &uniform,
                            offset: 0,
                            size: wgpu::BufferSize::new(round_up(k.launch_size, 16)),
                        }),
                    };
                    wgpu::BindGroupEntry { binding, resource }
                })
                .collect();
            let bg = self.device.create_bind_group(&wgpu::BindGroupDescriptor {
                label: Some(&k.name),
                layout: &self.pipelines[l.kernel].layout,
                entries: &entries,
            });
            st.bind_groups.insert(key, bg);
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
            for l in &pending {
                let bg = &st.bind_groups[&(l.kernel, l.key.clone())];
                pass.set_pipeline(&self.pipelines[l.kernel].pipeline);
                pass.set_bind_group(0, bg, &[l.offset]);
                pass.dispatch_workgroups(l.groups.0, l.groups.1, 1);
            }
        }
        self.queue.submit([enc.finish()]);
        st.staging.clear();
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

    /// Read a buffer back (submits what is recorded and waits for it).
    fn read(&self, b: BufferId) -> Result<Vec<f64>, String> {
        let mut st = self.state.borrow_mut();
        self.flush_state(&mut st);
        let i = b.0 as usize;
        let n = *st.lens.get(i).ok_or_else(|| format!("no buffer {i}"))?;
        let bytes = (n * self.module.precision.size()) as u64;
        if bytes == 0 {
            return Ok(Vec::new());
        }
        if st.readback.as_ref().is_none_or(|r| r.size() < bytes) {
            st.readback = Some(self.device.create_buffer(&wgpu::BufferDescriptor {
                label: Some("softc readback"),
                size: round_up(bytes, 256),
                usage: wgpu::BufferUsages::MAP_READ | wgpu::BufferUsages::COPY_DST,
                mapped_at_creation: false,
            }));
        }
        let rb = st.readback.clone().ok_or("no readback buffer")?;
        let mut enc = self
            .device
            .create_command_encoder(&wgpu::CommandEncoderDescriptor {
                label: Some("softc read"),
            });
        enc.copy_buffer_to_buffer(&st.buffers[st.slot[i]], 0, &rb, 0, bytes);
        self.queue.submit([enc.finish()]);
        let (tx, rx) = std::sync::mpsc::channel();
        rb.map_async(wgpu::MapMode::Read, 0..bytes, move |r| {
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
                .get_mapped_range(0..bytes)
                .map_err(|e| format!("GPU ({}): {e}", self.adapter))?;
            match self.module.precision {
                Precision::F32 => view
                    .chunks_exact(4)
                    .map(|c| f64::from(f32::from_le_bytes([c[0], c[1], c[2], c[3]])))
                    .collect(),
                Precision::F64 => view
                    .chunks_exact(8)
                    .map(|c| {
                        let mut a = [0u8; 8];
                        a.copy_from_slice(c);
                        f64::from_le_bytes(a)
                    })
                    .collect(),
            }
        };
        rb.unmap();
        if let Some(e) = self.take_error() {
            return Err(format!("GPU ({}): {e}", self.adapter));
        }
        Ok(out)
    }

    /// Allocate zeroed buffers for a mesh of `n_nodes` nodes, these tets and chamber triangles
    /// (node CSR lists in entity order, as scenes build them), and upload the connectivity.
    /// [`Backend::prepare`] does this for a scene.
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
        self.prepare_topology(n_nodes, tets, tris, &ne, &nt)
    }

    fn prepare_topology(
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
        let mut st = State {
            counts,
            ..State::default()
        };
        for (i, b) in self.layout.iter().enumerate() {
            let n = match b.0 {
                Domain::Element => counts[0],
                Domain::Triangle => counts[1],
                Domain::Node => counts[2],
                Domain::Single => 1,
            } * b.1 as usize;
            let bytes = n as u64 * size;
            if bytes > max {
                return Err(format!(
                    "buffer `{}` needs {bytes} bytes; adapter {} binds at most {max}",
                    b.2, self.adapter
                ));
            }
            st.buffers.push(self.storage_buffer(&b.2, bytes));
            st.slot.push(i);
            st.lens.push(n);
        }
        let flat = |v: &[u32]| -> Vec<u8> { v.iter().flat_map(|x| x.to_le_bytes()).collect() };
        let elem: Vec<u32> = tets.iter().flatten().copied().collect();
        let tri: Vec<u32> = tris.iter().flatten().copied().collect();
        let pairs = |c: &Csr| -> Vec<u32> {
            c.entries
                .iter()
                .flat_map(|&(e, k)| [e, u32::from(k)])
                .collect()
        };
        for t in TopoArray::ALL {
            let data = match t {
                TopoArray::ElemConn => flat(&elem),
                TopoArray::TriConn => flat(&tri),
                TopoArray::NodeElemOffsets => flat(&node_elements.offsets),
                TopoArray::NodeElemEntries => flat(&pairs(node_elements)),
                TopoArray::NodeTriOffsets => flat(&node_tris.offsets),
                TopoArray::NodeTriEntries => flat(&pairs(node_tris)),
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
            st.topo.push(buf);
        }
        *self.state.get_mut() = st;
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
}

impl Backend for Gpu {
    fn precision(&self) -> Precision {
        self.module.precision
    }

    fn name(&self) -> &'static str {
        "gpu"
    }

    fn prepare(&mut self, scene: &Scene) -> Result<(), String> {
        // The compiled module is the scene's forward module or its adjoint (a superset whose
        // first buffers are the forward ones).
        if scene.lowered.module.buffers.len() > self.buffer_count {
            return Err(format!(
                "the scene has {} buffers, the compiled module {}",
                scene.lowered.module.buffers.len(),
                self.buffer_count
            ));
        }
        self.prepare_topology(
            scene.mesh.nodes.len(),
            &scene.mesh.tets,
            &scene.tris,
            &scene.node_elements,
            &scene.node_tris,
        )
    }

    fn set(&mut self, b: BufferId, data: &[f64]) {
        let mut st = self.state.borrow_mut();
        let i = b.0 as usize;
        assert_eq!(
            st.lens[i],
            data.len(),
            "buffer {i}: {} values given, {} expected",
            data.len(),
            st.lens[i]
        );
        // Launches recorded so far read the old contents.
        self.flush_state(&mut st);
        if !data.is_empty() {
            let bytes = self.bytes_of(data);
            self.queue.write_buffer(&st.buffers[st.slot[i]], 0, &bytes);
        }
    }

    fn get(&self, b: BufferId) -> Vec<f64> {
        // A failed readback (a lost device, a mapping error) cannot be returned from here: it
        // is recorded, reported by the next launch or state check, and the values are NaN.
        self.read(b).unwrap_or_else(|e| {
            if let Ok(mut errors) = self.errors.lock() {
                errors.push(e);
            }
            let len = self.state.borrow().lens.get(b.0 as usize).copied();
            vec![f64::NAN; len.unwrap_or(0)]
        })
    }

    fn device_error(&self) -> Option<String> {
        let errors = self.errors.lock().ok()?;
        errors
            .first()
            .map(|e| format!("GPU ({}): {e}", self.adapter))
    }

    fn swap(&mut self, a: BufferId, b: BufferId) {
        let st = self.state.get_mut();
        st.slot.swap(a.0 as usize, b.0 as usize);
        st.lens.swap(a.0 as usize, b.0 as usize);
    }

    fn run(&mut self, k: usize, range: Range<usize>, u: &Uniforms) -> Result<(), String> {
        if let Some(e) = self.take_error() {
            return Err(format!("GPU ({}): {e}", self.adapter));
        }
        let kernel = self
            .module
            .kernels
            .get(k)
            .ok_or_else(|| format!("no kernel {k}"))?;
        let st = self.state.get_mut();
        if st.topo.is_empty() {
            return Err("the backend is not prepared".into());
        }
        let n = match kernel.domain {
            Domain::Element => st.counts[0],
            Domain::Triangle => st.counts[1],
            Domain::Node => st.counts[2],
            Domain::Single => 1,
        };
        if range.start > range.end || range.end > n {
            return Err(format!(
                "entity range {range:?} outside 0..{n} of kernel `{}`",
                kernel.name
            ));
        }
        let count = range.len();
        if count == 0 {
            return Ok(());
        }
        let offset = round_up(st.staging.len() as u64, u64::from(self.align));
        st.staging.resize(offset as usize, 0);
        st.staging
            .extend_from_slice(&(range.start as u32).to_le_bytes());
        st.staging.extend_from_slice(&(count as u32).to_le_bytes());
        for name in &kernel.uniforms {
            let v = u.get(name);
            match self.module.precision {
                Precision::F32 => st.staging.extend_from_slice(&(v as f32).to_le_bytes()),
                Precision::F64 => st.staging.extend_from_slice(&v.to_le_bytes()),
            }
        }
        // The binding reads a 16-byte multiple.
        let end = offset + round_up(kernel.launch_size, 16);
        st.staging.resize(end as usize, 0);
        let groups = (count as u64).div_ceil(u64::from(wgsl::WORKGROUP_SIZE));
        let max = u64::from(self.device.limits().max_compute_workgroups_per_dimension);
        let gx = groups.min(max);
        let gy = groups.div_ceil(gx);
        if gy > max {
            return Err(format!(
                "kernel `{}`: {count} entities exceed one launch of this adapter",
                kernel.name
            ));
        }
        let key = kernel
            .bindings
            .iter()
            .filter_map(|(_, w)| match w {
                Binding::Buffer { id, .. } => Some(st.slot[id.0 as usize]),
                _ => None,
            })
            .collect();
        st.pending.push(Launch {
            kernel: k,
            key,
            offset: offset as u32,
            groups: (gx as u32, gy as u32),
        });
        if st.pending.len() >= MAX_PENDING {
            self.flush()?;
        }
        Ok(())
    }
}
