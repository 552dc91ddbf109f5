//! The time loop as native code: `n` steps of a fixed sequence of kernel launches in one call.
//!
//! Between two host events (a state check, an output, a loss term) a step is always the same
//! launches over the same entity ranges with the same uniforms, except the time `t` and which
//! of two double-buffered states is current. The generated loop takes both: for step `first +
//! i` it stores `t = (first + i) · dt` into the uniform `t` of every launch that reads it (the
//! same value the host computes, rounded to f32 in f32 modules), calls the kernels in order
//! with the contexts of parity `i mod 2` (the buffer pointers with the state pairs as they are
//! before an even or an odd number of swaps), and loops. Nothing is recomputed from the host,
//! so the result is bit-identical to launching the kernels one by one.
//!
//! ```text
//! fn loop(ctxs: *const KernelCtx /* [2][L] */, ranges: *const u64 /* [L][2] */,
//!         first: u64, dt: f64, n: u64)
//! ```

use super::{Code, KernelCtx, jit_module_with};
use crate::back::Precision;
use cranelift_codegen::Context;
use cranelift_codegen::ir::condcodes::IntCC;
use cranelift_codegen::ir::{AbiParam, Function, InstBuilder, MemFlagsData, UserFuncName, types};
use cranelift_frontend::{FunctionBuilder, FunctionBuilderContext};
use cranelift_module::{Linkage, Module as _};
use std::mem::{offset_of, size_of};
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::{Condvar, Mutex};

/// The signature of a generated time loop.
pub(super) type LoopFn =
    unsafe extern "C" fn(ctxs: *const KernelCtx, ranges: *const u64, first: u64, dt: f64, n: u64);

/// One launch of a step as the loop is compiled for it.
pub(super) struct LoopLaunch {
    /// The kernel's native code.
    pub func: *const u8,
    /// Index of `t` in the kernel's uniforms, if it reads it.
    pub t_index: Option<usize>,
}

/// A compiled time loop for one sequence of kernels (see [`super::CpuModule::compile_loop`]).
pub struct StepLoop {
    pub(super) func: LoopFn,
    /// The kernels of one step, in launch order.
    pub kernels: Vec<usize>,
    /// The loop's Cranelift IR, as generated.
    pub clif: String,
    pub(super) _code: Code,
}

impl std::fmt::Debug for StepLoop {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("StepLoop")
            .field("kernels", &self.kernels)
            .finish_non_exhaustive()
    }
}

pub(super) fn compile(
    launches: &[LoopLaunch],
    kernels: Vec<usize>,
    precision: Precision,
) -> Result<StepLoop, String> {
    // The kernels are linked by name (`softc_kernel_K` at their addresses), so the loop calls
    // them directly and its printed IR names them instead of showing addresses.
    let symbols: Vec<(String, *const u8)> = launches
        .iter()
        .zip(&kernels)
        .map(|(l, k)| (format!("softc_kernel_{k}"), l.func))
        .collect();
    let mut jit = jit_module_with(&symbols)?;
    let ptr = types::I64;
    let mut kernel_sig = jit.make_signature();
    kernel_sig.params.push(AbiParam::new(ptr));
    kernel_sig.params.push(AbiParam::new(types::I64));
    kernel_sig.params.push(AbiParam::new(types::I64));
    let mut kernel_ids = Vec::new();
    for (name, _) in &symbols {
        let id = jit
            .declare_function(name, Linkage::Import, &kernel_sig)
            .map_err(|e| format!("time loop: {e}"))?;
        kernel_ids.push(id);
    }
    let mut sig = jit.make_signature();
    sig.params.push(AbiParam::new(ptr));
    sig.params.push(AbiParam::new(ptr));
    sig.params.push(AbiParam::new(types::I64));
    sig.params.push(AbiParam::new(types::F64));
    sig.params.push(AbiParam::new(types::I64));
    let mut func = Function::with_name_signature(UserFuncName::user(1, 0), sig);
    let callees: Vec<_> = kernel_ids
        .iter()
        .map(|&id| jit.declare_func_in_func(id, &mut func))
        .collect();
    let mut fctx = FunctionBuilderContext::new();
    {
        let mut b = FunctionBuilder::new(&mut func, &mut fctx);
        let entry = b.create_block();
        let header = b.create_block();
        let body = b.create_block();
        let exit = b.create_block();
        b.append_block_params_for_function_params(entry);
        b.append_block_param(header, types::I64);
        b.switch_to_block(entry);
        let p = b.block_params(entry).to_vec();
        let (ctxs, ranges, first, dt, n) = (p[0], p[1], p[2], p[3], p[4]);
        let zero = b.ins().iconst(types::I64, 0);
        b.ins().jump(header, &[zero.into()]);

        b.switch_to_block(header);
        let i = b.block_params(header)[0];
        let done = b.ins().icmp(IntCC::UnsignedGreaterThanOrEqual, i, n);
        b.ins().brif(done, exit, &[], body, &[]);

        b.switch_to_block(body);
        let step = b.ins().iadd(first, i);
        let step_f = b.ins().fcvt_from_uint(types::F64, step);
        let t64 = b.ins().fmul(step_f, dt);
        let t = match precision {
            Precision::F64 => t64,
            Precision::F32 => b.ins().fdemote(types::F32, t64),
        };
        let parity = b.ins().band_imm_u(i, 1);
        let stride = (launches.len() * size_of::<KernelCtx>()) as i64;
        let parity_offset = b.ins().imul_imm_s(parity, stride);
        let ctx_base = b.ins().iadd(ctxs, parity_offset);
        let flags = MemFlagsData::trusted();
        for (l, launch) in launches.iter().enumerate() {
            let ctx = b
                .ins()
                .iadd_imm_s(ctx_base, (l * size_of::<KernelCtx>()) as i64);
            if let Some(k) = launch.t_index {
                let uniforms =
                    b.ins()
                        .load(ptr, flags, ctx, offset_of!(KernelCtx, uniforms) as i32);
                b.ins()
                    .store(flags, t, uniforms, (k * precision.size()) as i32);
            }
            let begin = b.ins().load(types::I64, flags, ranges, (16 * l) as i32);
            let end = b.ins().load(types::I64, flags, ranges, (16 * l + 8) as i32);
            b.ins().call(callees[l], &[ctx, begin, end]);
        }
        let next = b.ins().iadd_imm_s(i, 1);
        b.ins().jump(header, &[next.into()]);

        b.switch_to_block(exit);
        b.ins().return_(&[]);
        b.seal_all_blocks();
        b.finalize(jit.target_config());
    }
    let clif = func.display().to_string();
    cranelift_codegen::verify_function(&func, jit.isa()).map_err(|e| {
        format!(
            "time loop: invalid Cranelift IR: {}",
            cranelift_codegen::print_errors::pretty_verifier_error(&func, None, e)
        )
    })?;
    let id = jit
        .declare_function("softc_step_loop", Linkage::Local, &func.signature)
        .map_err(|e| format!("time loop: {e}"))?;
    let mut ctx = Context::new();
    ctx.func = func;
    jit.define_function(id, &mut ctx)
        .map_err(|e| format!("time loop: Cranelift: {e:?}"))?;
    jit.finalize_definitions()
        .map_err(|e| format!("Cranelift: {e}"))?;
    let ptr = jit.get_finalized_function(id);
    // SAFETY: defined above with the signature of `LoopFn` (pointer, pointer, u64, f64, u64,
    // no result) in the host's default calling convention, the platform's C convention.
    let func = unsafe { std::mem::transmute::<*const u8, LoopFn>(ptr) };
    Ok(StepLoop {
        func,
        kernels,
        clif,
        _code: Code(Some(jit)),
    })
}

/// One launch of a step as the threads of [`run_threads`] run it.
pub(super) struct ThreadLaunch {
    pub func: super::KernelFn,
    /// Index of `t` in the kernel's uniforms, if it reads it.
    pub t_index: Option<usize>,
    /// All the launch's entities (each thread runs its chunk).
    pub range: std::ops::Range<usize>,
}

/// The shared progress of a [`run_threads`] call: chunks are claimed in order from one
/// counter, and a chunk starts only when every chunk of the launches before it is done.
///
/// Not a barrier that every thread must reach: a thread that lost its core to another process
/// (a build on a 2-core machine) holds up the others only while it holds a claimed chunk; the
/// others claim the rest of the launch's chunks. Waiting spins first (a chunk takes ~10-100
/// µs, waking a sleeping thread about as long), then sleeps, so that a waiting thread gives
/// its core to the thread it waits for.
struct Progress {
    next: AtomicUsize,
    done: AtomicUsize,
    /// Threads asleep waiting for `done`.
    sleepers: Mutex<usize>,
    wake: Condvar,
}

impl Progress {
    /// Wait until at least `target` chunks are done.
    fn wait_for(&self, target: usize) {
        for _ in 0..4000 {
            if self.done.load(Ordering::Acquire) >= target {
                return;
            }
            std::hint::spin_loop();
        }
        let mut sleepers = self.sleepers.lock().unwrap_or_else(|e| e.into_inner());
        while self.done.load(Ordering::Acquire) < target {
            *sleepers += 1;
            sleepers = self.wake.wait(sleepers).unwrap_or_else(|e| e.into_inner());
            *sleepers -= 1;
        }
    }

    /// One more chunk done (its writes released to the threads that see the count).
    fn finish(&self) {
        self.done.fetch_add(1, Ordering::AcqRel);
        // Under the lock, so that a thread going to sleep either sees the new count or is
        // asleep (counted) before it is woken.
        let sleepers = self.sleepers.lock().unwrap_or_else(|e| e.into_inner());
        if *sleepers > 0 {
            self.wake.notify_all();
        }
    }
}

/// Raw contexts shared by the threads of one call (read only).
struct Shared<'a>(&'a [KernelCtx]);
// SAFETY: the contexts are only read; what their pointers reach is partitioned between the
// threads by entity and ordered by the chunk counts (see `run_threads`).
unsafe impl Sync for Shared<'_> {}

/// `n` steps of `launches` on `threads` threads (see `CpuModule::run_loop_threads`). Each
/// launch is cut into a fixed number of contiguous chunks (up to 4 per thread, at least 256
/// entities each); the chunks of all steps are claimed in order from one counter by whichever
/// thread is free, and a chunk of launch `k` starts when all chunks before it (of the earlier
/// launches and steps) are done. The thread writes `t = (first + i)·dt` (rounded to f32 in f32
/// modules, as the compiled loop and the host compute it) into a copy of the launch's uniforms
/// of its own and runs the chunk with the contexts of parity `i mod 2`. An entity's result
/// does not depend on which chunk or thread computes it, so this is bit-identical to one
/// thread.
///
/// # Safety
/// `ctxs` holds `2 × launches.len()` contexts (even, then odd parity) that satisfy what
/// `CpuModule::run_raw` requires for every launch's range, except that their uniform pointers
/// are replaced; `uniforms[l]` are launch `l`'s uniforms; the kernels of a launch write only
/// their own entities' rows (as `run_parallel` relies on).
#[allow(clippy::too_many_arguments)]
pub(super) unsafe fn run_threads(
    launches: &[ThreadLaunch],
    ctxs: &[KernelCtx],
    uniforms: &[Vec<f64>],
    precision: Precision,
    first: u64,
    dt: f64,
    n: u64,
    threads: usize,
) {
    let l = launches.len();
    assert_eq!(ctxs.len(), 2 * l, "two parities of contexts per launch");
    // Chunks of each launch, and the chunks of a step before each launch.
    let chunks: Vec<usize> = launches
        .iter()
        .map(|la| ((la.range.end - la.range.start) / 256).clamp(1, 4 * threads))
        .collect();
    let before: Vec<usize> = chunks
        .iter()
        .scan(0, |acc, &c| {
            let b = *acc;
            *acc += c;
            Some(b)
        })
        .collect();
    let per_step: usize = chunks.iter().sum();
    let total = per_step * n as usize;
    let progress = Progress {
        next: AtomicUsize::new(0),
        done: AtomicUsize::new(0),
        sleepers: Mutex::new(0),
        wake: Condvar::new(),
    };
    let shared = Shared(ctxs);
    let work = || {
        let shared = &shared;
        // This thread's uniforms, in the module's precision (`t` is written into them).
        let mut u64s: Vec<Vec<f64>> = uniforms.to_vec();
        let mut u32s: Vec<Vec<f32>> = uniforms
            .iter()
            .map(|u| u.iter().map(|&v| v as f32).collect())
            .collect();
        let ptrs: Vec<*mut u8> = match precision {
            Precision::F64 => u64s.iter_mut().map(|u| u.as_mut_ptr() as *mut u8).collect(),
            Precision::F32 => u32s.iter_mut().map(|u| u.as_mut_ptr() as *mut u8).collect(),
        };
        let own: Vec<KernelCtx> = shared
            .0
            .iter()
            .enumerate()
            .map(|(c, ctx)| KernelCtx {
                uniforms: ptrs[c % l],
                ..*ctx
            })
            .collect();
        loop {
            let g = progress.next.fetch_add(1, Ordering::Relaxed);
            if g >= total {
                break;
            }
            let (i, within) = (g / per_step, g % per_step);
            let k = before.iter().rposition(|&b| b <= within).unwrap_or(0);
            let c = within - before[k];
            // Every chunk of the earlier launches and steps done.
            progress.wait_for(i * per_step + before[k]);
            let la = &launches[k];
            if let Some(ti) = la.t_index {
                let t = (first + i as u64) as f64 * dt;
                // SAFETY: `ptrs[k]` points to this thread's uniforms of launch `k`, which hold
                // the kernel's uniforms (`ti` is one of them); no kernel runs on this thread
                // while it is written, and no other thread reads it.
                unsafe {
                    match precision {
                        Precision::F64 => *(ptrs[k] as *mut f64).add(ti) = t,
                        Precision::F32 => *(ptrs[k] as *mut f32).add(ti) = t as f32,
                    }
                }
            }
            let len = la.range.end - la.range.start;
            let lo = la.range.start + len * c / chunks[k];
            let hi = la.range.start + len * (c + 1) / chunks[k];
            // SAFETY: forwarded from the caller; the chunk lies inside the launch's range, the
            // chunks are disjoint, and a chunk starts only after every chunk of the launches
            // before it is done (the acquire of `done` sees their writes).
            unsafe { (la.func)(&own[(i & 1) * l + k], lo as u64, hi as u64) };
            progress.finish();
        }
        drop((u64s, u32s));
    };
    std::thread::scope(|s| {
        for _ in 1..threads {
            let work = &work;
            s.spawn(work);
        }
        work();
    });
}
