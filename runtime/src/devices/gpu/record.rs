//! Recording: launches and writes become pending dispatches, their launch blocks go into the
//! staging area, bind groups are made once, and a submission is one compute pass.

use super::setup::launch_stride_of;
use super::*;

impl Core {
    pub(super) fn record(&mut self, scene: usize, op: Op) -> Result<(), String> {
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

    pub(super) fn record_set(&mut self, scene: usize, phys: usize, data: &[f64]) {
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
        let bytes = self.bytes_of(&self.rows[phys].pad(data));
        // A failure to submit shows at the next launch or readback.
        let _ = self.record(scene, Op::Set { phys, bytes });
    }

    /// Record kernel `k` over `range` of scene `scene`, with its buffers bound as `slot` maps
    /// them.
    pub(super) fn record_run(
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
        if !self.check_launch(k, &range)? {
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
    pub(super) fn flush(&mut self) {
        let start = (std::time::Instant::now(), self.stats.submit_seconds);
        self.drain();
        self.submit();
        self.add_host_time(start);
    }

    /// Turn every scene's recorded operations into pending dispatches, each scene's in its
    /// order. The scenes' next launches of the same kernel on the same buffers become one
    /// dispatch; a `set` waits until no scene has a launch before its own next `set`, so the
    /// writes of a batch in lockstep cost one break in the submission.
    pub(super) fn drain(&mut self) {
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
                        let offset =
                            (s * self.gpu_lens[phys] * self.module.precision.size()) as u64;
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
    pub(super) fn workgroups(&self, count: u64, scenes: usize) -> (u32, u32, u32) {
        let groups = count.div_ceil(u64::from(self.wg_size));
        let max = u64::from(self.device.limits().max_compute_workgroups_per_dimension);
        let gx = groups.clamp(1, max);
        (gx as u32, groups.div_ceil(gx) as u32, scenes as u32)
    }

    /// Bytes of launch blocks the next submission can hold.
    pub(super) fn launch_capacity(&self) -> u64 {
        self.launch_buffer.as_ref().map_or(0, |b| b.size())
    }

    /// Make room for `bytes` more bytes of launch blocks (aligned) in the next submission:
    /// submits what is pending if they do not fit, and grows the buffer (dropping the bind
    /// groups, which bind it) if one submission cannot hold them.
    pub(super) fn reserve(&mut self, bytes: u64) {
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
    pub(super) fn block_align(&self, kernel: usize) -> u64 {
        match self.module.launch {
            LaunchMode::Table => self.module.kernels[kernel].launch_stride(),
            LaunchMode::Uniform => u64::from(self.align),
        }
    }

    /// Room for `rows` dispatches' launch blocks of `kernel` (each one block per scene);
    /// returns the byte offset of the first and its dispatch argument (see [`Dispatch::arg`]).
    /// Call [`Core::reserve`] first for many rows at once.
    pub(super) fn alloc_blocks(&mut self, kernel: usize, rows: u64) -> (usize, u32) {
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
    pub(super) fn next_arg(&self, kernel: usize, arg: u32, row: u64) -> u32 {
        let stride = self.module.kernels[kernel].launch_stride();
        let span = round_up(self.scenes as u64 * stride, self.block_align(kernel));
        match self.module.launch {
            LaunchMode::Table => arg + (row * span / stride) as u32,
            LaunchMode::Uniform => arg + (row * span) as u32,
        }
    }

    /// Write scene `scene`'s launch block, the `j`-th of the blocks at `at`.
    #[allow(clippy::too_many_arguments)]
    pub(super) fn write_block(
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
    pub(super) fn bind_group(&mut self, kernel: usize, key: &[usize]) -> usize {
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
    pub(super) fn key_of(&self, k: usize, slot: &[usize]) -> Vec<usize> {
        self.entry_kernel(k)
            .bindings
            .iter()
            .filter_map(|(_, w)| match w {
                Binding::Buffer { id, .. } => Some(slot[id.0 as usize]),
                _ => None,
            })
            .collect()
    }

    /// Check a launch of kernel `k` over `range`: whether it has entities to run.
    pub(super) fn check_launch(&self, k: usize, range: &Range<usize>) -> Result<bool, String> {
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
            return Ok(false);
        }
        let groups = (range.len() as u64).div_ceil(u64::from(self.wg_size));
        let max = u64::from(self.device.limits().max_compute_workgroups_per_dimension);
        if groups.div_ceil(max) > max {
            return Err(format!(
                "kernel `{}`: {} entities exceed one launch of this adapter",
                kernel.name,
                range.len()
            ));
        }
        Ok(true)
    }

    /// Record dispatch `d` into `pass`, setting only what differs from `bound` (the pipeline
    /// and bind group bound last).
    fn encode_dispatch(
        &self,
        pass: &mut wgpu::ComputePass<'_>,
        d: &Dispatch,
        bound: &mut Option<(usize, usize)>,
    ) {
        let table = self.module.launch == LaunchMode::Table;
        if bound.is_none_or(|(k, _)| k != d.kernel) {
            pass.set_pipeline(&self.pipelines[d.kernel].pipeline);
        }
        if d.kernel >= self.module.kernels.len() {
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
        *bound = Some((d.kernel, d.group));
        pass.dispatch_workgroups(d.groups.0, d.groups.1, d.groups.2);
    }

    /// The pending dispatches, each in a compute pass of its own timed by its own pair of
    /// timestamps (profiling: passes cost more than dispatches, so wall time suffers, but
    /// each pair brackets one kernel). Dispatches beyond the free pairs go untimed.
    fn encode_profiled(&mut self, enc: &mut wgpu::CommandEncoder) {
        let pending = std::mem::take(&mut self.pending);
        for d in &pending {
            let pair = self
                .timing
                .as_mut()
                .and_then(|t| t.next_pair_of(Some(d.kernel)));
            let timestamp_writes = self.timing.as_ref().zip(pair).map(|(t, i)| t.writes(i));
            {
                let mut pass = enc.begin_compute_pass(&wgpu::ComputePassDescriptor {
                    label: Some("softc profiled dispatch"),
                    timestamp_writes,
                });
                self.encode_dispatch(&mut pass, d, &mut None);
            }
            if let (Some(t), Some(i)) = (&self.timing, pair) {
                t.resolve(enc, i);
            }
        }
        self.pending = pending;
    }

    /// The GPU time per kernel profiled so far (`SOFTC_GPU_PROFILE=1`), one line per
    /// pipeline, the most expensive first: its dispatches, µs per dispatch and share.
    pub(super) fn profile_report(&mut self) -> Option<String> {
        let t = self.timing.as_mut()?;
        t.collect(&self.device, &self.queue);
        let total: f64 = t.per_pipeline.values().map(|v| v.0).sum();
        if total <= 0.0 {
            return None;
        }
        let mut rows: Vec<(usize, (f64, u64))> =
            t.per_pipeline.iter().map(|(&p, &v)| (p, v)).collect();
        rows.sort_by(|a, b| b.1.0.total_cmp(&a.1.0));
        let mut out = format!(
            "GPU time per kernel ({}, workgroups of {}; a pass per dispatch):\n",
            self.adapter, self.wg_size
        );
        for (p, (seconds, n)) in rows {
            let name = self
                .module
                .kernels
                .get(p)
                .or_else(|| self.fused_kernels.get(&p))
                .map(|k| k.name.clone())
                .or_else(|| {
                    let st = self.states.as_ref()?;
                    (p == st.store || p == st.restore).then(|| {
                        let what = if p == st.store { "store" } else { "restore" };
                        format!("adjoint state {what} (copy)")
                    })
                })
                .unwrap_or_else(|| format!("pipeline {p}"));
            out.push_str(&format!(
                "  {name:<48} {n:>8} dispatches {:>10.2} us each {:>6.1} %\n",
                seconds / n as f64 * 1e6,
                100.0 * seconds / total
            ));
        }
        Some(out)
    }

    /// Submit the pending dispatches in one compute pass (their blocks are in the staging
    /// area), without waiting.
    pub(super) fn submit(&mut self) {
        if !self.pending.is_empty() {
            self.submit_with(|_| {});
        }
        self.staging.clear();
    }

    /// Submit the pending dispatches in one compute pass followed by `after`'s commands (a
    /// readback's copies) in the same submission; returns its index.
    pub(super) fn submit_with(
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
        let profile = self.profile && self.timing.is_some();
        let pair = if profile {
            None
        } else {
            self.timing.as_mut().and_then(Timing::next_pair)
        };
        if profile {
            self.encode_profiled(&mut enc);
        } else {
            let timestamp_writes = self.timing.as_ref().zip(pair).map(|(t, i)| t.writes(i));
            let mut pass = enc.begin_compute_pass(&wgpu::ComputePassDescriptor {
                label: Some("softc steps"),
                timestamp_writes,
            });
            let mut bound: Option<(usize, usize)> = None;
            for d in &self.pending {
                self.encode_dispatch(&mut pass, d, &mut bound);
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
}

impl Drop for Core {
    /// With `SOFTC_GPU_PROFILE=1`, the GPU time per kernel on stderr.
    fn drop(&mut self) {
        if self.profile
            && let Some(report) = self.profile_report()
        {
            eprint!("{report}");
        }
    }
}
