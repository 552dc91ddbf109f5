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
