//! The Cranelift CPU backend: a module's kernels compiled to native code with cranelift-jit.
//!
//! Each kernel becomes one function `extern "C" fn(ctx: *const KernelCtx, begin: u64, end: u64)`
//! that runs the kernel for every entity in `begin..end` (the entity loop, and a node kernel's
//! gather loops over its CSR list, are inside the generated code). [`KernelCtx`] holds the
//! buffers (indexed by [`BufferId`]), the connectivity and the kernel's uniforms.
//!
//! - In [`Precision::F64`] every operation is the single IEEE operation the interpreter
//!   ([`crate::ir::interp`]) performs, in the same order: results are bit-identical to it.
//!   Transcendental functions (`pow`, `exp`, `ln`, `sin`, `cos`, `tan`, `tanh`) call `extern
//!   "C"` wrappers of the same std functions; `sqrt`, `abs`, `floor`, `ceil`, `neg`, `min`,
//!   `max`, comparisons and selects are inline, with Rust's semantics (`min`/`max` return the
//!   non-NaN operand). Nothing is fused or reassociated.
//! - In [`Precision::F32`] every value and buffer is `f32`, constants and uniforms are
//!   rounded to `f32`, and the wrappers call the `f32` functions.
//!
//! [`CpuModule`] is the safe interface: it checks buffers, connectivity ([`Topology`]) and
//! entity ranges before it calls generated code, and runs a kernel on any number of threads
//! ([`CpuModule::run_parallel`]) over contiguous chunks of the range. Entities write only
//! their own outputs, so results do not depend on the thread count.
//!
//! Element, triangle and node kernels run 2 (f64) or 4 (f32) entities per iteration in
//! 128-bit vector code, one entity per lane (each lane performs exactly the scalar operation
//! sequence; transcendental calls go lane by lane; a node kernel's gathers walk the lanes' CSR
//! lists side by side, each lane adding its own incidences in list order, see `gather.rs`),
//! and the rest of the range in scalar code; [`Options::simd`] turns this off.
//!
//! ```
//! use softc_compiler::back::{Precision, cranelift::{Buffers, CpuModule, Topology}};
//! use softc_compiler::ir::{ArgSource, Domain, KernelBuilder, Module};
//!
//! // y[e] = scale * (x at corner 0 + x at corner 3) of every tet.
//! let mut m = Module::default();
//! let x = m.buffer("x", Domain::Node, 1, "");
//! let y = m.buffer("y", Domain::Element, 1, "");
//! let mut k = KernelBuilder::new("demo", Domain::Element, "doc");
//! let a = k.load(ArgSource::Corner { buffer: x, corner: 0, component: 0 });
//! let b = k.load(ArgSource::Corner { buffer: x, corner: 3, component: 0 });
//! let s = k.uniform("scale");
//! let sum = k.b.add(a, b);
//! let v = k.b.mul(s, sum);
//! k.store(y, 0, v);
//! m.push_kernel(k.finish());
//!
//! let cpu = CpuModule::compile(&m, Precision::F64).unwrap();
//! let topo = Topology::new(5, vec![0, 1, 2, 3, 1, 2, 3, 4], vec![]).unwrap();
//! let mut bufs = Buffers::new(&m, &topo, Precision::F64);
//! bufs.set(x, &[1.0, 2.0, 3.0, 4.0, 5.0]).unwrap();
//! assert_eq!(cpu.kernel(0).uniforms, [m.uniform_named("scale").unwrap()]);
//! cpu.run_parallel(0, &mut bufs, &topo, &[0.5], 0..2, 2).unwrap();
//! assert_eq!(bufs.get(y), [2.5, 3.5]);
//! assert!(cpu.clif(0).contains("fmul"));
//! ```

mod codegen;
mod gather;
mod libm;
mod pool;
mod schedule;
mod step_loop;
mod vmath;

pub use step_loop::StepLoop;

pub use crate::back::{Precision, Topology, node_csr};
use crate::ir::{ArgSource, BufferId, Domain, Module, UniformId};
/// The layout checks of a kernel against its module (shared with the WGSL backend).
use codegen::{Imports, MinMax, Translator};
use cranelift_codegen::{Context, settings, settings::Configurable};
use cranelift_frontend::FunctionBuilderContext;
use cranelift_jit::{JITBuilder, JITModule};
use cranelift_module::{Linkage, Module as _};
use std::ops::Range;
use std::time::{Duration, Instant};

/// What a compiled kernel reads: the layout the generated code expects (`repr(C)`).
///
/// Connectivity is `u32`: `elem_conn` has 4 node indices per element, `tri_conn` 3 per
/// triangle; the node→element CSR has `n_nodes + 1` offsets and, for each incidence, a pair
/// `(element, corner)` in `node_elem_entries` (likewise for triangles). Pointers a kernel
/// does not use may be null.
#[repr(C)]
#[derive(Clone, Copy, Debug)]
pub struct KernelCtx {
    /// One pointer per buffer of the module, indexed by [`BufferId`], to `f64` or `f32` data.
    pub buffers: *const *mut u8,
    /// The kernel's uniforms (`f64` or `f32`), in the order of [`CompiledKernel::uniforms`].
    pub uniforms: *const u8,
    pub elem_conn: *const u32,
    pub tri_conn: *const u32,
    pub node_elem_offsets: *const u32,
    pub node_elem_entries: *const u32,
    pub node_tri_offsets: *const u32,
    pub node_tri_entries: *const u32,
    pub node_elem_slots: *const u32,
    pub node_tri_slots: *const u32,
}

impl KernelCtx {
    /// A context for these buffer pointers and uniforms over `topology`'s connectivity.
    pub fn new(buffers: *const *mut u8, uniforms: *const u8, topology: &Topology) -> Self {
        KernelCtx {
            buffers,
            uniforms,
            elem_conn: topology.elem_conn.as_ptr(),
            tri_conn: topology.tri_conn.as_ptr(),
            node_elem_offsets: topology.node_elem_offsets.as_ptr(),
            node_elem_entries: topology.node_elem_entries.as_ptr(),
            node_tri_offsets: topology.node_tri_offsets.as_ptr(),
            node_tri_entries: topology.node_tri_entries.as_ptr(),
            node_elem_slots: topology.node_elem_slots().as_ptr(),
            node_tri_slots: topology.node_tri_slots().as_ptr(),
        }
    }
}

/// The signature of a generated kernel.
pub type KernelFn = unsafe extern "C" fn(ctx: *const KernelCtx, begin: u64, end: u64);

/// One compiled kernel.
#[derive(Debug)]
pub struct CompiledKernel {
    pub name: String,
    pub domain: Domain,
    /// The uniforms the kernel reads, in the order its uniforms array holds them.
    pub uniforms: Vec<UniformId>,
    /// The Cranelift IR of the kernel, as generated (before Cranelift's optimizations).
    pub clif: String,
    /// Wall time spent translating, verifying and compiling this kernel.
    pub compile_time: Duration,
    /// Entities per iteration of the main loop: 2 (f64) or 4 (f32) in vector code, 1 in
    /// scalar code (single kernels, or `Options::simd` off).
    pub lanes: u32,
    func: KernelFn,
    /// Buffers the kernel reads or writes (for the length checks).
    touched: Vec<BufferId>,
}

/// The JIT memory; only freed, never used after finalization.
struct Code(Option<JITModule>);

// SAFETY: after `finalize_definitions` the JIT module is never accessed except to free its
// memory on drop (which needs `&mut`, so exclusive access); the finalized code is immutable.
unsafe impl Send for Code {}
// SAFETY: as above: a shared reference gives no access to the module at all.
unsafe impl Sync for Code {}

impl Drop for Code {
    fn drop(&mut self) {
        if let Some(m) = self.0.take() {
            // SAFETY: the function pointers into this memory live in the `CpuModule` that owns
            // this `Code` and are dropped with it; no call can be running (calls borrow it).
            unsafe { m.free_memory() };
        }
    }
}

/// How to compile.
#[derive(Clone, Debug)]
pub struct Options {
    /// Run entities through 128-bit vector code (2 × f64 or 4 × f32 per iteration; one entity
    /// per lane, so results are the same bits as scalar code). Default on.
    pub simd: bool,
}

impl Default for Options {
    fn default() -> Self {
        Options { simd: true }
    }
}

/// A module's kernels compiled to native code.
pub struct CpuModule {
    precision: Precision,
    /// The order of the elements the kernels were generated for.
    order: crate::ir::ElementOrder,
    kernels: Vec<CompiledKernel>,
    /// `(domain, width)` of each buffer.
    layout: Vec<(Domain, u32)>,
    names: Vec<String>,
    /// The module's uniform names (messages and listings).
    uniform_names: Vec<String>,
    _code: Code,
}

impl std::fmt::Debug for CpuModule {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("CpuModule")
            .field("precision", &self.precision)
            .field("kernels", &self.kernels)
            .finish_non_exhaustive()
    }
}

fn jit_module() -> Result<JITModule, String> {
    jit_module_with(&[])
}

/// A JIT module that links the libm helpers and `extra` (symbol, address) pairs.
fn jit_module_with(extra: &[(String, *const u8)]) -> Result<JITModule, String> {
    let mut flags = settings::builder();
    let set = |f: &mut settings::Builder, k: &str, v: &str| {
        f.set(k, v)
            .map_err(|e| format!("Cranelift flag {k}={v}: {e}"))
    };
    // No e-graph pass: the kernels arrive simplified and value-numbered by the IR passes, in an
    // order chosen for register pressure (`schedule.rs`). Cranelift's e-graph would re-place
    // every pure instruction at its first use, which keeps a transposed group's loaded rows
    // (and each corner's node index) live until its last lane is read: in the benchmark's f32
    // element kernel that was 164 spill moves in 511 instructions per 4 elements, against 60
    // in 428 without it.
    set(&mut flags, "opt_level", "none")?;
    set(&mut flags, "is_pic", "false")?;
    set(&mut flags, "use_colocated_libcalls", "false")?;
    set(&mut flags, "enable_verifier", "true")?;
    let isa = cranelift_native::builder()
        .map_err(|e| format!("this host is not supported by Cranelift: {e}"))?
        .finish(settings::Flags::new(flags))
        .map_err(|e| format!("Cranelift target: {e}"))?;
    let mut jb = JITBuilder::with_isa(isa, cranelift_module::default_libcall_names());
    jb.symbols(libm::symbols());
    for (name, ptr) in extra {
        jb.symbol(name.clone(), *ptr);
    }
    Ok(JITModule::new(jb))
}

impl CpuModule {
    /// Compile every kernel of `module` (with [`Options::default`]). Errors describe a kernel
    /// that does not fit its module (an access outside a buffer's declared layout) or a
    /// Cranelift failure.
    pub fn compile(module: &Module, precision: Precision) -> Result<CpuModule, String> {
        Self::compile_with(module, precision, &Options::default())
    }

    pub fn compile_with(
        module: &Module,
        precision: Precision,
        options: &Options,
    ) -> Result<CpuModule, String> {
        let mut jit = jit_module()?;
        let mut imports = Imports::default();
        let min_max = if libm::inline_min_max_matches_std() {
            MinMax::Inline
        } else {
            MinMax::Call
        };
        let mut fctx = FunctionBuilderContext::new();
        let mut ctx = Context::new();
        let mut pending = Vec::new();
        for (index, k) in module.kernels.iter().enumerate() {
            let t0 = Instant::now();
            let name = format!("softc_kernel_{index}");
            let mut id = None;
            let mut result = Err(String::new());
            // Vector code first where asked for; scalar code if the target cannot take it.
            let tries: &[bool] = if options.simd {
                &[true, false]
            } else {
                &[false]
            };
            for &simd in tries {
                result = (|| {
                    let mut tr = Translator {
                        jit: &mut jit,
                        imports: &mut imports,
                        precision,
                        min_max,
                    };
                    let (func, simd) = tr.translate(module, k, index as u32, simd, &mut fctx)?;
                    let clif = func.display().to_string();
                    cranelift_codegen::verify_function(&func, jit.isa()).map_err(|e| {
                        format!(
                            "kernel `{}`: invalid Cranelift IR: {}",
                            k.name,
                            cranelift_codegen::print_errors::pretty_verifier_error(&func, None, e)
                        )
                    })?;
                    let fid = match id {
                        Some(fid) => fid,
                        None => {
                            let fid = jit
                                .declare_function(&name, Linkage::Local, &func.signature)
                                .map_err(|e| format!("kernel `{}`: {e}", k.name))?;
                            id = Some(fid);
                            fid
                        }
                    };
                    ctx.clear();
                    ctx.func = func;
                    // `SOFTC_DUMP_ASM=1`: each kernel's machine code (Cranelift's VCode, after
                    // register allocation) on stderr, to count spills when tuning the backend.
                    let disasm = std::env::var_os("SOFTC_DUMP_ASM").is_some();
                    ctx.set_disasm(disasm);
                    jit.define_function(fid, &mut ctx)
                        .map_err(|e| format!("kernel `{}`: Cranelift: {e:?}", k.name))?;
                    if disasm
                        && let Some(cc) = ctx.compiled_code()
                        && let Some(v) = &cc.vcode
                    {
                        eprintln!("=== kernel {} simd={simd}\n{v}", k.name);
                    }
                    Ok((fid, clif, simd))
                })();
                if result.is_ok() {
                    break;
                }
            }
            let (id, clif, simd) = result?;
            let mut touched: Vec<BufferId> = k
                .args
                .iter()
                .filter_map(|a| match a {
                    ArgSource::Own { buffer, .. }
                    | ArgSource::Corner { buffer, .. }
                    | ArgSource::Gather { buffer, .. } => Some(*buffer),
                    ArgSource::Uniform(_) => None,
                })
                .collect();
            touched.extend(k.stores.iter().map(|s| s.buffer));
            touched.sort_by_key(|b| b.0);
            touched.dedup();
            pending.push((id, k, clif, t0.elapsed(), touched, simd));
        }
        let t0 = Instant::now();
        jit.finalize_definitions()
            .map_err(|e| format!("Cranelift: {e}"))?;
        let link = t0.elapsed() / pending.len().max(1) as u32;
        let kernels = pending
            .into_iter()
            .map(|(id, k, clif, t, touched, simd)| {
                let ptr = jit.get_finalized_function(id);
                // SAFETY: the function was defined with the signature of `KernelFn` (pointer,
                // u64, u64, no result) in the host's default calling convention, which is the
                // C calling convention of this platform.
                let func = unsafe { std::mem::transmute::<*const u8, KernelFn>(ptr) };
                CompiledKernel {
                    name: k.name.clone(),
                    domain: k.domain,
                    uniforms: k.uniforms(),
                    clif,
                    compile_time: t + link,
                    lanes: if simd {
                        16 / precision.size() as u32
                    } else {
                        1
                    },
                    func,
                    touched,
                }
            })
            .collect();
        Ok(CpuModule {
            precision,
            order: module.order,
            kernels,
            layout: module.buffers.iter().map(|b| (b.domain, b.width)).collect(),
            names: module.buffers.iter().map(|b| b.name.clone()).collect(),
            uniform_names: module.uniforms.clone(),
            _code: Code(Some(jit)),
        })
    }

    pub fn precision(&self) -> Precision {
        self.precision
    }

    pub fn kernels(&self) -> &[CompiledKernel] {
        &self.kernels
    }

    pub fn kernel(&self, index: usize) -> &CompiledKernel {
        &self.kernels[index]
    }

    pub fn kernel_index(&self, name: &str) -> Option<usize> {
        self.kernels.iter().position(|k| k.name == name)
    }

    /// The Cranelift IR of a kernel (`softc compile --emit clif`).
    pub fn clif(&self, kernel: usize) -> String {
        self.kernels[kernel].clif.clone()
    }

    /// The Cranelift IR of every kernel, each under a comment naming it.
    pub fn clif_all(&self) -> String {
        let mut s = String::new();
        for k in &self.kernels {
            s.push_str(&format!("; kernel {} over {:?}\n", k.name, k.domain));
            if !k.uniforms.is_empty() {
                s.push_str(&format!("; uniforms: {}\n", self.uniform_list(k)));
            }
            s.push_str(&k.clif);
            s.push('\n');
        }
        s
    }

    /// The names of a kernel's uniforms, comma-separated.
    fn uniform_list(&self, k: &CompiledKernel) -> String {
        let names: Vec<&str> = k
            .uniforms
            .iter()
            .map(|u| self.uniform_names[u.0 as usize].as_str())
            .collect();
        names.join(", ")
    }

    /// Run kernel `kernel` over the entities `range` on the calling thread. `uniforms` holds
    /// the values of [`CompiledKernel::uniforms`] in order (rounded to f32 in f32 modules).
    pub fn run(
        &self,
        kernel: usize,
        buffers: &mut Buffers,
        topology: &Topology,
        uniforms: &[f64],
        range: Range<usize>,
    ) -> Result<(), String> {
        self.run_parallel(kernel, buffers, topology, uniforms, range, 1)
    }

    /// Run kernel `kernel` over `range` split into `threads` contiguous chunks, one per
    /// thread (`std::thread::scope`). Results are bit-identical for any thread count.
    pub fn run_parallel(
        &self,
        kernel: usize,
        buffers: &mut Buffers,
        topology: &Topology,
        uniforms: &[f64],
        range: Range<usize>,
        threads: usize,
    ) -> Result<(), String> {
        let k = self.check_launch(kernel, buffers, topology, uniforms, &range)?;
        let uni64: Vec<f64>;
        let uni32: Vec<f32>;
        let uniforms_ptr = match self.precision {
            Precision::F64 => {
                uni64 = uniforms.to_vec();
                uni64.as_ptr() as *const u8
            }
            Precision::F32 => {
                uni32 = uniforms.iter().map(|&u| u as f32).collect();
                uni32.as_ptr() as *const u8
            }
        };
        buffers.ensure_slack();
        let ptrs: Vec<*mut u8> = buffers.data.iter_mut().map(Storage::as_mut_ptr).collect();
        let ctx = KernelCtx::new(ptrs.as_ptr(), uniforms_ptr, topology);
        let len = range.end - range.start;
        let threads = threads.clamp(1, len.max(1));
        let bounds: Vec<usize> = (0..=threads)
            .map(|t| range.start + len * t / threads)
            .collect();
        /// One launch split into the chunks `bounds[c]..bounds[c + 1]`.
        struct Split<'a> {
            f: KernelFn,
            ctx: &'a KernelCtx,
            bounds: &'a [usize],
        }
        /// Chunk `c` of the `Split` at `data`.
        unsafe fn chunk(data: *const (), c: usize) {
            // SAFETY: `data` is the `Split` below, alive while `run_chunks` runs.
            let s = unsafe { &*(data as *const Split) };
            // SAFETY: the buffers the kernel touches have the lengths its layout needs for the
            // topology's entity counts (and their slack), the topology's indices were validated
            // against those counts, the chunk lies inside the kernel's domain, and the kernel
            // was validated to access only inside that layout. Chunks are disjoint; an entity
            // stores only to its own row of buffers of the kernel's domain, while other
            // entities' rows are read only from buffers of other domains (corners read node
            // buffers in element and triangle kernels, gathers read element or triangle
            // buffers in node kernels), so concurrent chunks never touch a location another
            // one writes.
            unsafe { (s.f)(s.ctx, s.bounds[c] as u64, s.bounds[c + 1] as u64) }
        }
        let split = Split {
            f: k.func,
            ctx: &ctx,
            bounds: &bounds,
        };
        // The chunks are fixed by the thread count alone, so which thread runs which chunk
        // changes nothing in the result.
        // SAFETY: see `chunk`; `split` outlives the call.
        unsafe { pool::run_chunks(chunk, &split as *const Split as *const (), threads) };
        Ok(())
    }

    /// Everything a launch of `kernel` needs to be safe: buffers of the module's precision and
    /// of the lengths the topology implies, the right number of uniforms, a range inside the
    /// kernel's domain.
    fn check_launch(
        &self,
        kernel: usize,
        buffers: &Buffers,
        topology: &Topology,
        uniforms: &[f64],
        range: &Range<usize>,
    ) -> Result<&CompiledKernel, String> {
        let k = self
            .kernels
            .get(kernel)
            .ok_or_else(|| format!("no kernel {kernel}"))?;
        if buffers.precision != self.precision {
            return Err(format!(
                "buffers are {} but the module was compiled for {}",
                buffers.precision, self.precision
            ));
        }
        if topology.order() != self.order {
            return Err(format!(
                "the connectivity has {:?} elements but the module was compiled for {:?}",
                topology.order(),
                self.order
            ));
        }
        if buffers.data.len() != self.layout.len() {
            return Err(format!(
                "{} buffers given, the module has {}",
                buffers.data.len(),
                self.layout.len()
            ));
        }
        for b in &k.touched {
            let (domain, width) = self.layout[b.0 as usize];
            let want = topology.count(domain) * width as usize;
            let data = &buffers.data[b.0 as usize];
            if data.precision() != self.precision {
                return Err(format!(
                    "buffer `{}` holds {} values, the module was compiled for {}",
                    self.names[b.0 as usize],
                    data.precision(),
                    self.precision
                ));
            }
            let have = data.len();
            if have != want {
                return Err(format!(
                    "buffer `{}` has {have} values, {want} expected ({domain:?} × {width})",
                    self.names[b.0 as usize]
                ));
            }
        }
        if uniforms.len() != k.uniforms.len() {
            return Err(format!(
                "kernel `{}` takes {} uniforms ({}), {} given",
                k.name,
                k.uniforms.len(),
                self.uniform_list(k),
                uniforms.len()
            ));
        }
        let n = topology.count(k.domain);
        if range.start > range.end || range.end > n {
            return Err(format!(
                "entity range {range:?} outside 0..{n} of kernel `{}`",
                k.name
            ));
        }
        Ok(k)
    }

    /// Compile a time loop whose every step launches `kernels` in this order (see
    /// [`StepLoop`] and [`CpuModule::run_loop`]). The loop calls this module's code: keep the
    /// module alive as long as the loop.
    pub fn compile_loop(&self, kernels: &[usize]) -> Result<StepLoop, String> {
        let t = self
            .uniform_names
            .iter()
            .position(|u| u == "t")
            .map(|i| UniformId(i as u32));
        let launches = kernels
            .iter()
            .map(|&k| {
                let ck = self
                    .kernels
                    .get(k)
                    .ok_or_else(|| format!("no kernel {k}"))?;
                Ok(step_loop::LoopLaunch {
                    func: ck.func as *const u8,
                    t_index: t.and_then(|t| ck.uniforms.iter().position(|&u| u == t)),
                })
            })
            .collect::<Result<Vec<_>, String>>()?;
        step_loop::compile(&launches, kernels.to_vec(), self.precision)
    }

    /// Run `n` steps of a compiled time loop on the calling thread, the first being step
    /// `first`: each step sets `t = step · dt` in every launch that reads it, runs launch `l`
    /// of `lp.kernels` over `ranges[l]` with `uniforms[l]` (the other uniforms, as
    /// [`CpuModule::run`] takes them), then swaps the buffer pairs `swaps`. Bit-identical to
    /// the same launches and swaps made one by one.
    #[allow(clippy::too_many_arguments)]
    pub fn run_loop(
        &self,
        lp: &StepLoop,
        buffers: &mut Buffers,
        topology: &Topology,
        uniforms: &[Vec<f64>],
        ranges: &[Range<usize>],
        swaps: &[(BufferId, BufferId)],
        first: u64,
        dt: f64,
        n: u64,
    ) -> Result<(), String> {
        self.run_loop_threads(
            lp, buffers, topology, uniforms, ranges, swaps, first, dt, n, 1,
        )
    }

    /// [`CpuModule::run_loop`] on `threads` threads: each launch's entities are split into
    /// `threads` contiguous chunks as [`CpuModule::run_parallel`] splits them, every thread
    /// runs its chunk of every launch of every step, and all wait for each other after each
    /// launch (a spinning barrier, see [`step_loop::run_threads`]). Bit-identical to one
    /// thread.
    #[allow(clippy::too_many_arguments)]
    pub fn run_loop_threads(
        &self,
        lp: &StepLoop,
        buffers: &mut Buffers,
        topology: &Topology,
        uniforms: &[Vec<f64>],
        ranges: &[Range<usize>],
        swaps: &[(BufferId, BufferId)],
        first: u64,
        dt: f64,
        n: u64,
        threads: usize,
    ) -> Result<(), String> {
        // The loop's threads need the cores the launch pool's workers may be spinning on.
        pool::park();
        let l = lp.kernels.len();
        if uniforms.len() != l || ranges.len() != l {
            return Err(format!(
                "a step of {l} launches: {} uniform lists and {} ranges given",
                uniforms.len(),
                ranges.len()
            ));
        }
        for ((&k, u), r) in lp.kernels.iter().zip(uniforms).zip(ranges) {
            self.check_launch(k, buffers, topology, u, r)?;
        }
        for &(a, b) in swaps {
            let (a, b) = (a.0 as usize, b.0 as usize);
            if a == b || a >= self.layout.len() || b >= self.layout.len() {
                return Err(format!("cannot swap buffers {a} and {b}"));
            }
            if self.layout[a] != self.layout[b] || buffers.data[a].len() != buffers.data[b].len() {
                return Err(format!(
                    "cannot swap `{}` and `{}`: different layouts",
                    self.names[a], self.names[b]
                ));
            }
        }
        if n == 0 {
            return Ok(());
        }
        // Each launch's uniforms in the module's precision; the loop writes `t` into them.
        let mut uni64: Vec<Vec<f64>> = Vec::new();
        let mut uni32: Vec<Vec<f32>> = Vec::new();
        let uniform_ptrs: Vec<*const u8> = match self.precision {
            Precision::F64 => {
                uni64 = uniforms.to_vec();
                uni64
                    .iter_mut()
                    .map(|u| u.as_mut_ptr() as *const u8)
                    .collect()
            }
            Precision::F32 => {
                uni32 = uniforms
                    .iter()
                    .map(|u| u.iter().map(|&v| v as f32).collect())
                    .collect();
                uni32
                    .iter_mut()
                    .map(|u| u.as_mut_ptr() as *const u8)
                    .collect()
            }
        };
        // Buffer pointers before an even and an odd number of swaps.
        buffers.ensure_slack();
        let even: Vec<*mut u8> = buffers.data.iter_mut().map(Storage::as_mut_ptr).collect();
        let mut odd = even.clone();
        for &(a, b) in swaps {
            odd.swap(a.0 as usize, b.0 as usize);
        }
        let ctx = |ptrs: &Vec<*mut u8>, u: *const u8| KernelCtx::new(ptrs.as_ptr(), u, topology);
        let ctxs: Vec<KernelCtx> = [&even, &odd]
            .iter()
            .flat_map(|ptrs| uniform_ptrs.iter().map(|&u| ctx(ptrs, u)))
            .collect();
        let bounds: Vec<u64> = ranges
            .iter()
            .flat_map(|r| [r.start as u64, r.end as u64])
            .collect();
        let largest = ranges.iter().map(|r| r.end - r.start).max().unwrap_or(0);
        let threads = threads.clamp(1, largest.max(1));
        if threads > 1 {
            let t = self
                .uniform_names
                .iter()
                .position(|u| u == "t")
                .map(|i| UniformId(i as u32));
            let launches: Vec<step_loop::ThreadLaunch> = lp
                .kernels
                .iter()
                .zip(ranges)
                .map(|(&k, r)| {
                    let ck = &self.kernels[k];
                    step_loop::ThreadLaunch {
                        func: ck.func,
                        t_index: t.and_then(|t| ck.uniforms.iter().position(|&u| u == t)),
                        range: r.clone(),
                    }
                })
                .collect();
            // SAFETY: as for the single-threaded loop below; in addition the threads run
            // disjoint chunks of each launch (which `run_parallel` shows safe to run at once)
            // and wait for each other between launches, and each thread writes `t` into a
            // copy of the uniforms of its own.
            unsafe {
                step_loop::run_threads(
                    &launches,
                    &ctxs,
                    uniforms,
                    self.precision,
                    first,
                    dt,
                    n,
                    threads,
                )
            };
            drop((uni64, uni32));
            if n % 2 == 1 {
                for &(a, b) in swaps {
                    buffers.swap(a, b);
                }
            }
            return Ok(());
        }
        // SAFETY: every launch passed the checks of `run_parallel` (buffer lengths for the
        // topology, uniforms, ranges inside the domains) for the buffers as they are; the
        // swapped pairs have equal layouts, so the same holds after any number of swaps. The
        // launches run one after another on this thread, and the uniform arrays, pointer
        // arrays and contexts outlive the call. `t` is written between launches, never while
        // a kernel reads it.
        unsafe { (lp.func)(ctxs.as_ptr(), bounds.as_ptr(), first, dt, n) };
        drop((uni64, uni32));
        if n % 2 == 1 {
            for &(a, b) in swaps {
                buffers.swap(a, b);
            }
        }
        Ok(())
    }

    /// Call a kernel's native code directly.
    ///
    /// # Safety
    /// `ctx` must satisfy everything [`CpuModule::run_parallel`] checks: every buffer the
    /// kernel touches holds `count(domain) × width` values of the module's precision
    /// followed by [`SLACK`] readable values (vector code may load past a row's end),
    /// connectivity and CSR indices are in range, `begin..end` lies inside the kernel's domain,
    /// and no other thread writes what this call reads or writes.
    pub unsafe fn run_raw(&self, kernel: usize, ctx: &KernelCtx, begin: u64, end: u64) {
        // SAFETY: forwarded to the caller.
        unsafe { (self.kernels[kernel].func)(ctx, begin, end) }
    }
}

/// The data of one buffer.
#[derive(Clone, Debug, PartialEq)]
pub enum Storage {
    F64(Vec<f64>),
    F32(Vec<f32>),
}

/// Values past a buffer's end that vector code may read (and ignore): a row loaded as a whole
/// vector (a node's x, y, z as 4 × f32) reads up to 3 values past the last row. Every launch
/// first makes sure each buffer has this much zeroed capacity beyond its length
/// ([`Buffers::ensure_slack`]), so the ignored lanes are zeros, never NaN or subnormal.
pub const SLACK: usize = 4;

impl Storage {
    /// Reserve [`SLACK`] values of capacity past the end and zero them.
    fn ensure_slack(&mut self) {
        fn pad<T: Copy + Default>(v: &mut Vec<T>) {
            if v.capacity() - v.len() < SLACK {
                v.reserve_exact(SLACK);
            }
            for x in &mut v.spare_capacity_mut()[..SLACK] {
                x.write(T::default());
            }
        }
        match self {
            Storage::F64(v) => pad(v),
            Storage::F32(v) => pad(v),
        }
    }

    pub fn precision(&self) -> Precision {
        match self {
            Storage::F64(_) => Precision::F64,
            Storage::F32(_) => Precision::F32,
        }
    }

    pub fn len(&self) -> usize {
        match self {
            Storage::F64(v) => v.len(),
            Storage::F32(v) => v.len(),
        }
    }

    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    fn as_mut_ptr(&mut self) -> *mut u8 {
        match self {
            Storage::F64(v) => v.as_mut_ptr() as *mut u8,
            Storage::F32(v) => v.as_mut_ptr() as *mut u8,
        }
    }
}

/// The buffers of a module at one precision, sized for a topology.
#[derive(Clone, Debug)]
pub struct Buffers {
    precision: Precision,
    data: Vec<Storage>,
}

impl Buffers {
    /// Zero-filled buffers of `module` for the entity counts of `topology`.
    pub fn new(module: &Module, topology: &Topology, precision: Precision) -> Buffers {
        let data = module
            .buffers
            .iter()
            .map(|b| {
                let n = topology.count(b.domain) * b.width as usize;
                // Allocated with their zeroed slack, so the first launch moves nothing.
                fn zeros<T: Copy + Default>(n: usize) -> Vec<T> {
                    let mut v = vec![T::default(); n + SLACK];
                    v.truncate(n);
                    v
                }
                match precision {
                    Precision::F64 => Storage::F64(zeros(n)),
                    Precision::F32 => Storage::F32(zeros(n)),
                }
            })
            .collect();
        Buffers { precision, data }
    }

    /// Buffers made by the caller, one per buffer of the module in [`BufferId`] order (their
    /// lengths are checked when a kernel runs).
    pub fn from_storage(precision: Precision, data: Vec<Storage>) -> Result<Buffers, String> {
        if let Some(i) = data.iter().position(|d| d.precision() != precision) {
            return Err(format!("buffer {i} is not {precision}"));
        }
        Ok(Buffers { precision, data })
    }

    pub fn into_storage(self) -> Vec<Storage> {
        self.data
    }

    /// Give every buffer its zeroed [`SLACK`] (before pointers to them go to native code).
    fn ensure_slack(&mut self) {
        for d in &mut self.data {
            d.ensure_slack();
        }
    }

    /// The data of every buffer, in [`BufferId`] order (lengths and precisions are checked
    /// again when a kernel runs).
    pub fn storage_mut(&mut self) -> &mut [Storage] {
        &mut self.data
    }

    pub fn precision(&self) -> Precision {
        self.precision
    }

    /// Exchange the data of two buffers (double-buffered state: the new state becomes the
    /// current one without a copy).
    pub fn swap(&mut self, a: BufferId, b: BufferId) {
        self.data.swap(a.0 as usize, b.0 as usize);
    }

    /// Overwrite a buffer with `values` (rounded to f32 in f32 buffers); the length must match.
    pub fn set(&mut self, id: BufferId, values: &[f64]) -> Result<(), String> {
        let d = self
            .data
            .get_mut(id.0 as usize)
            .ok_or_else(|| format!("no buffer {}", id.0))?;
        if d.len() != values.len() {
            return Err(format!(
                "buffer {} holds {} values, {} given",
                id.0,
                d.len(),
                values.len()
            ));
        }
        match d {
            Storage::F64(v) => v.copy_from_slice(values),
            Storage::F32(v) => v.iter_mut().zip(values).for_each(|(a, &b)| *a = b as f32),
        }
        Ok(())
    }

    /// A buffer's values as f64.
    pub fn get(&self, id: BufferId) -> Vec<f64> {
        match &self.data[id.0 as usize] {
            Storage::F64(v) => v.clone(),
            Storage::F32(v) => v.iter().map(|&x| f64::from(x)).collect(),
        }
    }

    /// The data of an f64 buffer (`None` in f32 buffers).
    pub fn f64(&self, id: BufferId) -> Option<&[f64]> {
        match &self.data[id.0 as usize] {
            Storage::F64(v) => Some(v),
            Storage::F32(_) => None,
        }
    }

    pub fn f64_mut(&mut self, id: BufferId) -> Option<&mut [f64]> {
        match &mut self.data[id.0 as usize] {
            Storage::F64(v) => Some(v),
            Storage::F32(_) => None,
        }
    }

    pub fn f32(&self, id: BufferId) -> Option<&[f32]> {
        match &self.data[id.0 as usize] {
            Storage::F32(v) => Some(v),
            Storage::F64(_) => None,
        }
    }

    pub fn f32_mut(&mut self, id: BufferId) -> Option<&mut [f32]> {
        match &mut self.data[id.0 as usize] {
            Storage::F32(v) => Some(v),
            Storage::F64(_) => None,
        }
    }
}
