//! Opening the device: the adapter, the kernels' pipelines, the buffers of a mesh.

use super::*;

/// Bytes of the launch block bound at `binding` (a kernel's launch binding follows the
/// buffers and the connectivity, in kernel order).
/// Runs of consecutive kernels of `module` (in its order, as a step launches them) that are
/// pairwise independent: what a time loop fuses into one dispatch.
fn fusable_runs(module: &Module) -> Vec<Vec<usize>> {
    let mut runs: Vec<Vec<usize>> = Vec::new();
    let mut run: Vec<usize> = Vec::new();
    for k in 0..module.kernels.len() {
        let joins = run.len() < MAX_PARTS && run.iter().all(|&m| wgsl::independent(module, m, k));
        if !joins {
            if run.len() > 1 {
                runs.push(std::mem::take(&mut run));
            }
            run.clear();
        }
        run.push(k);
    }
    if run.len() > 1 {
        runs.push(run);
    }
    runs
}

/// Storage buffers an entry point fusing `kernels` binds.
pub(super) fn fused_storage_buffers(wg: &WgslModule, kernels: &[usize]) -> u32 {
    let mut bindings: Vec<u32> = kernels
        .iter()
        .flat_map(|&k| wg.kernels[k].bindings.iter())
        .filter(|b| !matches!(b.1, Binding::Launch))
        .map(|b| b.0)
        .collect();
    bindings.sort_unstable();
    bindings.dedup();
    bindings.len() as u32
}

pub(super) fn launch_stride_of(wg: &WgslModule, buffers: usize, binding: u32) -> u64 {
    let k = binding as usize - buffers - TopoArray::ALL.len();
    wg.kernels.get(k).map_or(16, WgslKernel::launch_stride)
}

/// The pipeline of entry point `k` of `shader`, its bind group laid out as its bindings say
/// (launch blocks of `scenes` scenes at dynamic offsets, `stride_of` giving a launch
/// binding's block size, or the launch table with its row as an immediate).
pub(super) fn pipeline_for(
    device: &wgpu::Device,
    shader: &wgpu::ShaderModule,
    k: &WgslKernel,
    scenes: u64,
    launch: LaunchMode,
    stride_of: &dyn Fn(u32) -> u64,
    wg_size: u32,
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
        compilation_options: workgroup_constants(&[(wgsl::WORKGROUP_OVERRIDE, f64::from(wg_size))]),
        cache: None,
    });
    Pipeline { pipeline, layout }
}

impl Core {
    /// Compile `module` (batched for `batch` scenes) for an adapter: the first one whose name
    /// (or backend) contains `adapter` (case-insensitive), else the preferred one (discrete,
    /// integrated, virtual, then software; Vulkan first). f64 needs `SHADER_F64`.
    pub(super) fn open(
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
        let mut wg = wgsl::emit_for(module, precision, batch, launch)?;
        // The fused entry points a time loop will want, compiled with the others (a
        // pipeline made in the middle of a run costs it milliseconds): runs of consecutive
        // independent kernels, as a step launches them in module order.
        let fuse = std::env::var("SOFTC_GPU_FUSE").as_deref() != Ok("0");
        let groups: Vec<Vec<usize>> = if fuse && batch.is_none() && launch == LaunchMode::Uniform {
            fusable_runs(module)
                .into_iter()
                .filter(|g| {
                    fused_storage_buffers(&wg, g) <= limits.max_storage_buffers_per_shader_stage
                })
                .collect()
        } else {
            Vec::new()
        };
        if !groups.is_empty() {
            wg = wgsl::emit_fused(module, precision, &groups)?;
        }
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
        let wg_size = workgroup_size(&limits)?;
        let shader = kernels_module(&device, &wg.source);
        let stride_of = |b: u32| launch_stride_of(&wg, module.buffers.len(), b);
        let pipelines = wg
            .kernels
            .iter()
            .map(|k| pipeline_for(&device, &shader, k, scenes, launch, &stride_of, wg_size))
            .collect();
        let _ = device.poll(wgpu::PollType::wait_indefinitely());
        if let Some(e) = errors.lock().ok().and_then(|mut v| v.drain(..).next()) {
            return Err(format!("adapter {desc}: the kernels do not compile: {e}"));
        }
        // The fused entry points follow the module's kernels.
        let fused_kernels: HashMap<usize, WgslKernel> = wg
            .kernels
            .drain(module.kernels.len()..)
            .enumerate()
            .map(|(i, k)| (module.kernels.len() + i, k))
            .collect();
        let fused = fused_kernels
            .iter()
            .map(|(&at, k)| (k.parts.clone(), at))
            .collect();
        let align = limits.min_uniform_buffer_offset_alignment.max(16);
        let scenes = scenes as usize;
        let mut core = Core {
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
            gpu_lens: Vec::new(),
            rows: Vec::new(),
            topo: Vec::new(),
            counts: [0; 3],
            launch_buffer: None,
            staging: Vec::new(),
            queues: (0..scenes).map(|_| VecDeque::new()).collect(),
            recorded: 0,
            pending: Vec::new(),
            bind_groups: HashMap::new(),
            groups: Vec::new(),
            timing: None,
            in_flight: HashMap::new(),
            next_ticket: 0,
            spare_readbacks: Vec::new(),
            states: None,
            ir: module.clone(),
            fuse,
            wg_size,
            profile: std::env::var("SOFTC_GPU_PROFILE").as_deref() == Ok("1"),
            fused,
            fused_kernels,
            stats: DispatchStats::default(),
            active: vec![false; scenes],
            waiting: vec![None; scenes],
            served: (0..scenes).map(|_| None).collect(),
        };
        if core.profile {
            core.enable_timing();
        }
        Ok(core)
    }

    /// Add the host time since `start` (an instant and the submission time then), less the
    /// time inside queue submissions, to the stats.
    pub(super) fn add_host_time(&mut self, start: (std::time::Instant, f64)) {
        let submitting = self.stats.submit_seconds - start.1;
        self.stats.host_seconds += start.0.elapsed().as_secs_f64() - submitting;
    }

    pub(super) fn take_error(&self) -> Option<String> {
        self.errors
            .lock()
            .ok()
            .and_then(|mut v| v.drain(..).next())
            .map(|e| format!("GPU ({}): {e}", self.adapter))
    }

    pub(super) fn device_error(&self) -> Option<String> {
        let errors = self.errors.lock().ok()?;
        errors
            .first()
            .map(|e| format!("GPU ({}): {e}", self.adapter))
    }

    /// Check a scene against the compiled module: the module is the scene's forward module or
    /// its adjoint (a superset whose first buffers are the forward ones).
    pub(super) fn check_scene(&self, scene: &Scene) -> Result<(), String> {
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
    pub(super) fn allocate(
        &mut self,
        n_nodes: usize,
        (elem, n_elems): (&[u32], usize),
        (tri, n_tris): (&[u32], usize),
        node_elements: &Csr,
        node_tris: &Csr,
    ) -> Result<(), String> {
        let max = self.device.limits().max_storage_buffer_binding_size;
        let size = self.module.precision.size() as u64;
        let counts = [n_elems, n_tris, n_nodes];
        let mut buffers = Vec::new();
        let (mut lens, mut gpu_lens, mut rows) = (Vec::new(), Vec::new(), Vec::new());
        let batched = self.module.batch.is_some();
        for (i, b) in self.layout.iter().enumerate() {
            let row = RowLayout::of_buffer(&self.ir, BufferId(i as u32), batched);
            let n = domain_count(&counts, b.0) * b.1 as usize;
            let gpu_n = domain_count(&counts, b.0) * row.padded() as usize;
            let bytes = (gpu_n * self.scenes) as u64 * size;
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
            gpu_lens.push(gpu_n);
            rows.push(row);
        }
        let flat = |v: &[u32]| -> Vec<u8> { v.iter().flat_map(|x| x.to_le_bytes()).collect() };
        let mut topo = Vec::new();
        for t in TopoArray::ALL {
            let data = match t {
                TopoArray::ElemConn => flat(elem),
                TopoArray::TriConn => flat(tri),
                TopoArray::NodeElemOffsets => flat(&node_elements.offsets),
                TopoArray::NodeElemSlots => {
                    flat(&node_elements.slots(self.ir.order.element_nodes()))
                }
                TopoArray::NodeTriOffsets => flat(&node_tris.offsets),
                TopoArray::NodeTriSlots => flat(&node_tris.slots(self.ir.order.triangle_nodes())),
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
        self.gpu_lens = gpu_lens;
        self.rows = rows;
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

    pub(super) fn storage_buffer(&self, label: &str, bytes: u64) -> wgpu::Buffer {
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

    pub(super) fn bytes_of(&self, data: &[f64]) -> Vec<u8> {
        match self.module.precision {
            Precision::F32 => data
                .iter()
                .flat_map(|&v| (v as f32).to_le_bytes())
                .collect(),
            Precision::F64 => data.iter().flat_map(|&v| v.to_le_bytes()).collect(),
        }
    }
}

/// The generated kernels as a shader module without wgpu's loop bounding and integer-division
/// guards. Both are for untrusted shaders: a loop bound (a counter and a test in every gather
/// loop, which also keeps the driver from unrolling it) guards against infinite loops, and
/// ours run over a node's CSR range, `offsets[e]..offsets[e + 1]`, so they end; our integer
/// divisions are by constant corner counts. Buffer bounds checks stay: on an H200 the benchmark
/// step's kernels ran as fast with them as without (45.8 against 45.7 µs a step at 420k tets,
/// 2026-11-27). `SOFTC_GPU_LOOP_BOUND=1` puts the guards
/// back, to measure what they cost.
pub(super) fn kernels_module(device: &wgpu::Device, source: &str) -> wgpu::ShaderModule {
    let desc = wgpu::ShaderModuleDescriptor {
        label: Some("softc kernels"),
        source: wgpu::ShaderSource::Wgsl(source.into()),
    };
    if std::env::var("SOFTC_GPU_LOOP_BOUND").as_deref() == Ok("1") {
        return device.create_shader_module(desc);
    }
    let checks = wgpu::ShaderRuntimeChecks {
        force_loop_bounding: false,
        int_div_checks: false,
        ..wgpu::ShaderRuntimeChecks::checked()
    };
    // SAFETY: the module is softc's generated code: every loop runs over a CSR range of
    // validated connectivity (it ends), every integer division is by a nonzero constant, and
    // bounds checks are kept.
    unsafe { device.create_shader_module_trusted(desc, checks) }
}

/// Pipeline options setting the overrides `constants`.
pub(super) fn workgroup_constants<'a>(
    constants: &'a [(&'a str, f64)],
) -> wgpu::PipelineCompilationOptions<'a> {
    wgpu::PipelineCompilationOptions {
        constants,
        ..Default::default()
    }
}

/// Invocations per workgroup: [`wgsl::WORKGROUP_SIZE`], or `SOFTC_GPU_WG` (a power of two from
/// 32 to the adapter's limit) to measure another size; the same bits either way, since each
/// entity is one invocation whatever the grouping. 128 by measurement on an H200 (2026-11-27,
/// forward steps/s at 64 / 128 / 256 invocations: 10k 58,527 / 59,064 / 56,576; 50k 45,938 /
/// 45,787 / 45,188; 420k 5,918 / 7,149 / 5,182).
fn workgroup_size(limits: &wgpu::Limits) -> Result<u32, String> {
    let Ok(v) = std::env::var("SOFTC_GPU_WG") else {
        return Ok(wgsl::WORKGROUP_SIZE);
    };
    let max = limits
        .max_compute_invocations_per_workgroup
        .min(limits.max_compute_workgroup_size_x);
    match v.trim().parse::<u32>() {
        Ok(n) if n.is_power_of_two() && (32..=max).contains(&n) => Ok(n),
        _ => Err(format!(
            "SOFTC_GPU_WG={v}: give a power of two from 32 to {max} (invocations per workgroup)"
        )),
    }
}
