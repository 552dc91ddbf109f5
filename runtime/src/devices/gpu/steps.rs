//! The time loop: stretches of steps (forward, or the adjoint's backward with its states
//! restored) recorded at once, independent kernels fused into one dispatch, a batch's
//! matching stretches merged.

use super::setup::{fused_storage_buffers, kernels_module, launch_stride_of, pipeline_for};
use super::*;

impl Core {
    /// The entry point of pipeline `p`: a module kernel or a fused one.
    pub(super) fn entry_kernel(&self, p: usize) -> &WgslKernel {
        match self.module.kernels.get(p) {
            Some(k) => k,
            None => &self.fused_kernels[&p],
        }
    }

    /// The pipelines of fused entry points for `groups` (kernels of the module, mutually
    /// independent), compiled once per group: one shader module for the new ones.
    pub(super) fn fused_pipelines(&mut self, groups: &[Vec<usize>]) -> Result<Vec<usize>, String> {
        let new: Vec<Vec<usize>> = groups
            .iter()
            .filter(|g| !self.fused.contains_key(*g))
            .cloned()
            .collect();
        if !new.is_empty() {
            let wg = wgsl::emit_fused(&self.ir, self.module.precision, &new)?;
            let shader = kernels_module(&self.device, &wg.source);
            let stride_of = |b: u32| launch_stride_of(&self.module, self.buffer_count, b);
            for (g, k) in new.iter().zip(&wg.kernels[self.module.kernels.len()..]) {
                let p = pipeline_for(
                    &self.device,
                    &shader,
                    k,
                    self.scenes as u64,
                    LaunchMode::Uniform,
                    &stride_of,
                    self.wg_size,
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

    /// The time loop of one scene (unbatched): `n` steps from step `first`, each setting
    /// `t = step · dt` where a kernel reads it, running `launches` in order and then swapping
    /// `swaps` in `slot`. Launch blocks are written once per step only for kernels that read
    /// `t` (once per submission for the others), bind groups are resolved once per buffer
    /// parity, and up to [`STEPS_PER_SUBMISSION`] steps go in one submission, submitted
    /// without waiting. The same dispatches, blocks and order as launching one by one.
    pub(super) fn record_steps(
        &mut self,
        slot: &mut [usize],
        stepped: &Stepped<'_>,
    ) -> Result<(), String> {
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
    pub(super) fn record_steps_for(
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
            if !self.check_launch(*k, range)? {
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
            let limit = self.device.limits().max_storage_buffers_per_shader_stage;
            let joins = fuse
                && units.last().is_some_and(|(_, members)| {
                    let mut kernels: Vec<usize> =
                        members.iter().map(|&m| plans[m].kernel).collect();
                    kernels.push(p.kernel);
                    members.len() < MAX_PARTS
                        && members
                            .iter()
                            .all(|&m| wgsl::independent(&self.ir, plans[m].kernel, p.kernel))
                        && fused_storage_buffers(&self.module, &kernels) <= limit
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
            // Each plan's first launch block (its dispatch argument).
            let mut args = Vec::with_capacity(plans.len());
            for p in &plans {
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
                args.push(arg);
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
                        let arg = args[m];
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
}
