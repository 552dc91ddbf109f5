//! What crosses between host and device: readbacks (waited for, or under way), the
//! adjoint's states kept in device memory, and pass times from timestamp queries.

use super::setup::workgroup_constants;
use super::*;

/// The copy kernel between a state (`x`, `v`: `len` values each) and a slot of the device's
/// state store (bound at a dynamic offset): `store` into the slot, else out of it.
/// The rows of the adjoint's states, positions and velocities: 3 per node.
const STATE_ROW: RowLayout = RowLayout::of(3);

/// Values in device memory of a state of `len` values (3 per node, as `vec4`s).
fn state_gpu_len(len: usize) -> usize {
    len / STATE_ROW.width as usize * STATE_ROW.padded() as usize
}

/// The copy kernel into (`store`) or out of a device slot of a state of `len` values in
/// device memory (x then v, each `len / 4` `vec4`s).
pub(super) fn state_copy_wgsl(real: &str, len: usize, store: bool) -> String {
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
const N: u32 = {}u;
@group(0) @binding(0) var<storage, {state}> x: array<vec4<real>>;
@group(0) @binding(1) var<storage, {state}> v: array<vec4<real>>;
@group(0) @binding(2) var<storage, {slot}> slot: array<vec4<real>>;
override softc_wg: u32 = 64u;
@compute @workgroup_size(softc_wg)
fn {name}(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {{
    let i = gid.x + gid.y * nwg.x * softc_wg;
    if (i < N) {{
        {body}
    }}
}}
",
        len / 4
    )
}

impl Timing {
    const PAIRS: u32 = 512;

    pub(super) fn new(device: &wgpu::Device, queue: &wgpu::Queue) -> Self {
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
            labels: Vec::new(),
            per_pipeline: Default::default(),
        }
    }

    /// The first query of a free pair, if any is left.
    pub(super) fn next_pair(&mut self) -> Option<u32> {
        self.next_pair_of(None)
    }

    /// As [`Timing::next_pair`] for a pass that runs one dispatch of `pipeline` (profiling).
    pub(super) fn next_pair_of(&mut self, pipeline: Option<usize>) -> Option<u32> {
        (self.used < self.pairs).then(|| {
            self.used += 1;
            self.labels.push(pipeline);
            2 * (self.used - 1)
        })
    }

    /// A pass's timestamp writes into the pair starting at query `first`.
    pub(super) fn writes(&self, first: u32) -> wgpu::ComputePassTimestampWrites<'_> {
        wgpu::ComputePassTimestampWrites {
            query_set: &self.set,
            beginning_of_pass_write_index: Some(first),
            end_of_pass_write_index: Some(first + 1),
        }
    }

    pub(super) fn resolve(&self, enc: &mut wgpu::CommandEncoder, first: u32) {
        enc.resolve_query_set(
            &self.set,
            first..first + 2,
            &self.resolve,
            u64::from(first / 2) * wgpu::QUERY_RESOLVE_BUFFER_ALIGNMENT,
        );
    }

    /// Add up the used pairs (waits for the GPU) and free them.
    pub(super) fn collect(&mut self, device: &wgpu::Device, queue: &wgpu::Queue) {
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
            for (pair, label) in view.chunks_exact(span).zip(&self.labels) {
                let (begin, end) = (tick(&pair[0..8]), tick(&pair[8..16]));
                let seconds = end.saturating_sub(begin) as f64 * self.period * 1e-9;
                self.seconds += seconds;
                if let Some(p) = label {
                    let e = self.per_pipeline.entry(*p).or_default();
                    e.0 += seconds;
                    e.1 += 1;
                }
            }
        }
        self.read.unmap();
        self.used = 0;
        self.labels.clear();
    }
}

impl Core {
    /// Time the compute passes with timestamp queries from now on, if the adapter has them
    /// (`false` if not).
    pub(super) fn enable_timing(&mut self) -> bool {
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
    pub(super) fn stats_now(&mut self) -> DispatchStats {
        let mut s = self.stats;
        if let Some(t) = self.timing.as_mut() {
            t.collect(&self.device, &self.queue);
            s.gpu_seconds = Some(t.seconds);
        }
        s
    }

    /// Start reading `(physical buffer, scene)` pairs back: submits what is recorded and a
    /// copy into a readback buffer, maps it without waiting; [`Core::collect`] waits for that
    /// submission only, so the GPU runs on with what is submitted after.
    pub(super) fn read_later(&mut self, requests: &[(usize, usize)]) -> Result<u64, String> {
        let start = (std::time::Instant::now(), self.stats.submit_seconds);
        self.drain();
        self.stats.readbacks += 1;
        let size = self.module.precision.size();
        let mut spans = Vec::new();
        let mut rows = Vec::new();
        let mut total = 0u64;
        for &(phys, scene) in requests {
            let n = *self
                .gpu_lens
                .get(phys)
                .ok_or_else(|| format!("no buffer {phys}"))?;
            let bytes = (n * size) as u64;
            spans.push((phys, (scene * n * size) as u64, total, bytes));
            rows.push(self.rows[phys]);
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
                spans: spans.iter().zip(rows).map(|(s, r)| (s.2, s.3, r)).collect(),
                index,
                mapped: rx,
            },
        );
        Ok(ticket)
    }

    /// The values of a [`Core::read_later`] (waits for its copy).
    pub(super) fn collect(&mut self, ticket: u64) -> Result<Vec<Vec<f64>>, String> {
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
                .map(|&(to, bytes, row)| {
                    row.unpad(self.values(&view[to as usize..(to + bytes) as usize]))
                })
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
    pub(super) fn values(&self, bytes: &[u8]) -> Vec<f64> {
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
    pub(super) fn device_states(
        &mut self,
        slots: usize,
        len: usize,
    ) -> Result<Option<u64>, String> {
        self.flush();
        // An optimization asks once per iteration: the store it has serves when it is large
        // enough (its buffers, copy kernels and bind groups are kept).
        if let Some(st) = &self.states
            && st.len == len
            && st.slots >= slots
            && slots > 0
        {
            return Ok(Some(st.slot_bytes * slots as u64));
        }
        // A new store: the copy kernels' bind groups name the old buffers.
        let copies = self.states.take().map(|st| (st.store, st.restore, st.len));
        if let Some((store, restore, _)) = copies {
            self.bind_groups
                .retain(|(k, _), _| *k != store && *k != restore);
        }
        let size = self.module.precision.size() as u64;
        let limits = self.device.limits();
        let align = u64::from(limits.min_storage_buffer_offset_alignment).max(256);
        let slot_bytes = round_up(2 * state_gpu_len(len) as u64 * size, align);
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
        // The copy kernels depend only on `len`: made once for it.
        let (store, restore) = match copies {
            Some((store, restore, made_for)) if made_for == len => (store, restore),
            _ => self.state_copy_pipelines(len)?,
        };
        self.states = Some(DeviceStates {
            chunks,
            per_chunk,
            slot_bytes,
            slots,
            len,
            store,
            restore,
        });
        Ok(Some(total))
    }

    /// Compile the kernels that copy a state of `len` positions and velocities into a device
    /// slot (`store`) and out of it (`restore`); their pipeline indices.
    fn state_copy_pipelines(&mut self, len: usize) -> Result<(usize, usize), String> {
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
                        state_copy_wgsl(real, state_gpu_len(len), name == "store").into(),
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
                    compilation_options: workgroup_constants(&[(
                        wgsl::WORKGROUP_OVERRIDE,
                        f64::from(self.wg_size),
                    )]),
                    cache: None,
                });
            self.pipelines.push(Pipeline { pipeline, layout });
        }
        if let Some(e) = self.take_error() {
            return Err(e);
        }
        Ok((first, first + 1))
    }

    /// Record a copy between the state buffers `x`, `v` (physical) and device slot `slot`:
    /// `store` into the slot, else out of it. A dispatch in the step's compute pass.
    pub(super) fn record_state_copy(
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
    pub(super) fn state_copy(
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
        if self.lens[x] != st.len
            || self.lens[v] != st.len
            || self.rows[x] != STATE_ROW
            || self.rows[v] != STATE_ROW
        {
            return Err("a device state copy of buffers of another size".into());
        }
        let (chunk, offset) = (
            slot / st.per_chunk,
            (slot % st.per_chunk) as u64 * st.slot_bytes,
        );
        let kernel = if store { st.store } else { st.restore };
        let (count, slot_bytes) = (state_gpu_len(st.len) as u64 / 4, st.slot_bytes);
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

    /// Read back the values of `(physical buffer, scene)` pairs: submits what is recorded
    /// with the copies, and waits for that submission.
    pub(super) fn read(&mut self, requests: &[(usize, usize)]) -> Result<Vec<Vec<f64>>, String> {
        let ticket = self.read_later(requests)?;
        self.collect(ticket)
    }

    /// values are NaN.
    pub(super) fn values_or_nan(&self, phys: usize, r: Result<Vec<f64>, String>) -> Vec<f64> {
        r.unwrap_or_else(|e| {
            if let Ok(mut errors) = self.errors.lock() {
                errors.push(e);
            }
            vec![f64::NAN; self.lens.get(phys).copied().unwrap_or(0)]
        })
    }

    /// Lockstep: when every scene of the group waits for a readback, read them all at once.
    pub(super) fn serve_if_ready(&mut self) -> bool {
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
