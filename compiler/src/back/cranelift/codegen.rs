//! Translation of one IR kernel into a Cranelift function.
//!
//! The function is `fn(ctx: *const KernelCtx, begin: u64, end: u64)` and loops over the
//! entities `begin..end` itself:
//!
//! ```text
//! entry(ctx, begin, end):  load buffer pointers, connectivity pointers and uniforms once
//! header(i):               if i < end goto body else exit
//! body:                    [gather loops over the node's CSR list, one per incident domain]
//!                          the body's instructions in order (arguments loaded where the
//!                          body reads them), then the stores; i += 1; goto header
//! exit:                    return
//! ```
//!
//! Every floating-point operation is one IEEE operation of the precision (no fused
//! multiply-add, no reassociation), so f64 results equal the interpreter's bit for bit.

use super::KernelCtx;
use super::libm::Lib;
use super::schedule::Step;
use crate::back::Precision;
use crate::ir::valid::validate_kernel;
use crate::ir::{ArgSource, BinOp, CmpOp, Domain, Inst, Kernel, Module, UnOp, UniformId};
use cranelift_codegen::ir::condcodes::{FloatCC, IntCC};
use cranelift_codegen::ir::{
    AbiParam, ConstantData, Endianness, FuncRef, Function, InstBuilder, MemFlagsData, Type,
    UserFuncName, Value, types,
};
use cranelift_frontend::{FunctionBuilder, FunctionBuilderContext, Variable};
use cranelift_jit::JITModule;
use cranelift_module::{FuncId, Linkage, Module as _};
use std::collections::HashMap;
use std::mem::offset_of;

/// Imported helper functions, declared once per JIT module.
#[derive(Default)]
pub(super) struct Imports {
    ids: HashMap<&'static str, FuncId>,
}

/// How `min`/`max` are compiled.
#[derive(Clone, Copy, PartialEq, Eq)]
pub(super) enum MinMax {
    /// Compare and select inline (matches rustc's x86-64 lowering of `f64::min`/`max`).
    Inline,
    /// Call the std function.
    Call,
}

pub(super) struct Translator<'a> {
    pub jit: &'a mut JITModule,
    pub imports: &'a mut Imports,
    pub precision: Precision,
    pub min_max: MinMax,
}

pub(super) const PTR: Type = types::I64;

pub(super) fn trusted() -> MemFlagsData {
    MemFlagsData::trusted()
}

/// Read-only data for the whole call (the context, the connectivity, the uniforms).
pub(super) fn readonly() -> MemFlagsData {
    MemFlagsData::trusted().with_readonly()
}

/// A 32-bit immediate offset: at most 4 lanes × 2^24 components × 8 bytes (`validate_kernel`).
pub(super) fn off(bytes: usize) -> i32 {
    i32::try_from(bytes).expect("offsets inside validated buffers fit in 32 bits")
}

/// `x · k` for an index `x`: a shift where `k` is a power of two, which the x86 lowering folds
/// into an address (`base + x·4`) where an `imul` stays an instruction (Cranelift's e-graph,
/// which would make the same rewrite, does not run: see `jit_module_with`).
pub(super) fn scaled(b: &mut FunctionBuilder, x: Value, k: i64) -> Value {
    if k > 0 && (k as u64).is_power_of_two() {
        b.ins().ishl_imm_s(x, k.trailing_zeros() as i64)
    } else {
        b.ins().imul_imm_s(x, k)
    }
}

/// What the entity loops share: values loaded once in the entry block.
pub(super) struct Hoisted {
    /// Base pointer of the buffer each used argument reads.
    pub arg_buf: HashMap<usize, Value>,
    /// Base pointer of each store's buffer.
    store_ptrs: Vec<Value>,
    /// The connectivity of the kernel's domain, if corners are read.
    conn: Option<Value>,
    /// The uniforms (scalars), in the order of `uniforms`.
    uni_vals: Vec<Value>,
    uniforms: Vec<UniformId>,
    /// Imported helper functions.
    fref: HashMap<Lib, FuncRef>,
}

impl Translator<'_> {
    pub(super) fn fty(&self) -> Type {
        match self.precision {
            Precision::F32 => types::F32,
            Precision::F64 => types::F64,
        }
    }

    /// Build the Cranelift function of kernel `k`. With `simd`, entities go `lanes` at a
    /// time through vector code (one entity per lane: every lane performs exactly the scalar
    /// operation sequence, so results are the same bits), and the remainder through scalar
    /// code (a node kernel's gathers too, see `gather.rs`).
    pub fn translate(
        &mut self,
        m: &Module,
        k: &Kernel,
        index: u32,
        simd: bool,
        fctx: &mut FunctionBuilderContext,
    ) -> Result<(Function, bool), String> {
        if self.jit.target_config().pointer_type() != PTR {
            return Err("the Cranelift backend needs a 64-bit host".into());
        }
        validate_kernel(m, k)?;
        let fty = self.fty();
        let mut sig = self.jit.make_signature();
        sig.params.push(AbiParam::new(PTR));
        sig.params.push(AbiParam::new(types::I64));
        sig.params.push(AbiParam::new(types::I64));
        let mut func = Function::with_name_signature(UserFuncName::user(0, index), sig);

        // Helper imports this kernel needs, declared in the function up front.
        let mut fref = HashMap::new();
        for inst in &k.body.insts {
            let lib = match *inst {
                Inst::Un(op, _) => Lib::Un(op),
                Inst::Bin(op, _, _) => Lib::Bin(op),
                _ => continue,
            };
            if matches!(lib, Lib::Bin(BinOp::Min | BinOp::Max)) && self.min_max == MinMax::Inline {
                continue;
            }
            let Some(sym) = lib.symbol(self.precision) else {
                continue;
            };
            if fref.contains_key(&lib) {
                continue;
            }
            let id = match self.imports.ids.get(sym) {
                Some(&id) => id,
                None => {
                    let mut s = self.jit.make_signature();
                    for _ in 0..lib.arity() {
                        s.params.push(AbiParam::new(fty));
                    }
                    s.returns.push(AbiParam::new(fty));
                    let id = self
                        .jit
                        .declare_function(sym, Linkage::Import, &s)
                        .map_err(|e| format!("declaring {sym}: {e}"))?;
                    self.imports.ids.insert(sym, id);
                    id
                }
            };
            fref.insert(lib, self.jit.declare_func_in_func(id, &mut func));
        }

        let mut b = FunctionBuilder::new(&mut func, fctx);
        let entry = b.create_block();
        b.append_block_params_for_function_params(entry);
        b.switch_to_block(entry);
        let params = b.block_params(entry).to_vec();
        let (cx, begin, end) = (params[0], params[1], params[2]);

        // Which arguments the body reads at all (a hand-built body may leave some unused).
        let mut used = vec![false; k.args.len()];
        for inst in &k.body.insts {
            if let Inst::Arg(a) = *inst {
                used[a as usize] = true;
            }
        }
        let ctx_load =
            |b: &mut FunctionBuilder, field: usize| b.ins().load(PTR, readonly(), cx, off(field));

        // Hoisted loads: buffer pointers, connectivity pointers, uniforms.
        let mut bufs_arr = None;
        let mut buf_ptr: HashMap<u32, Value> = HashMap::new();
        let mut need_buf = |b: &mut FunctionBuilder, id: u32| {
            let arr = *bufs_arr.get_or_insert_with(|| ctx_load(b, offset_of!(KernelCtx, buffers)));
            *buf_ptr
                .entry(id)
                .or_insert_with(|| b.ins().load(PTR, readonly(), arr, off(8 * id as usize)))
        };
        let uniforms = k.uniforms();
        let mut uni_vals = Vec::new();
        if !uniforms.is_empty() {
            let up = ctx_load(&mut b, offset_of!(KernelCtx, uniforms));
            for j in 0..uniforms.len() {
                uni_vals.push(
                    b.ins()
                        .load(fty, readonly(), up, off(j * self.precision.size())),
                );
            }
        }
        let mut arg_buf = HashMap::new();
        for (a, src) in k.args.iter().enumerate() {
            if !used[a] {
                continue;
            }
            match src {
                ArgSource::Own { buffer, .. }
                | ArgSource::Corner { buffer, .. }
                | ArgSource::Gather { buffer, .. } => {
                    arg_buf.insert(a, need_buf(&mut b, buffer.0));
                }
                ArgSource::Uniform(_) => {}
            }
        }
        let store_ptrs: Vec<Value> = k
            .stores
            .iter()
            .map(|s| need_buf(&mut b, s.buffer.0))
            .collect();
        let conn = if k
            .args
            .iter()
            .zip(&used)
            .any(|(a, &u)| u && matches!(a, ArgSource::Corner { .. }))
        {
            let field = match k.domain {
                Domain::Element => offset_of!(KernelCtx, elem_conn),
                _ => offset_of!(KernelCtx, tri_conn),
            };
            Some(ctx_load(&mut b, field))
        } else {
            None
        };
        // Gathers grouped by incident domain: one CSR loop per domain.
        let mut gathers: Vec<(Domain, Vec<usize>)> = Vec::new();
        for (a, src) in k.args.iter().enumerate() {
            if let (true, ArgSource::Gather { over, .. }) = (used[a], src) {
                match gathers.iter_mut().find(|(d, _)| d == over) {
                    Some((_, v)) => v.push(a),
                    None => gathers.push((*over, vec![a])),
                }
            }
        }
        let csr: Vec<(Value, Value, Value)> = gathers
            .iter()
            .map(|(d, _)| {
                let (o, e, s) = match d {
                    Domain::Element => (
                        offset_of!(KernelCtx, node_elem_offsets),
                        offset_of!(KernelCtx, node_elem_entries),
                        offset_of!(KernelCtx, node_elem_slots),
                    ),
                    _ => (
                        offset_of!(KernelCtx, node_tri_offsets),
                        offset_of!(KernelCtx, node_tri_entries),
                        offset_of!(KernelCtx, node_tri_slots),
                    ),
                };
                (
                    ctx_load(&mut b, o),
                    ctx_load(&mut b, e),
                    ctx_load(&mut b, s),
                )
            })
            .collect();
        let h = Hoisted {
            arg_buf,
            store_ptrs,
            conn,
            uni_vals,
            uniforms,
            fref,
        };

        let lanes: u32 = match self.precision {
            Precision::F64 => 2,
            Precision::F32 => 4,
        };
        let simd = simd && k.domain != Domain::Single;
        let iv: Variable = b.declare_var(types::I64);
        b.def_var(iv, begin);
        let sheader = b.create_block();
        let sbody = b.create_block();
        let exit = b.create_block();
        if simd {
            // Vector loop: while i + lanes <= end.
            let vheader = b.create_block();
            let vbody = b.create_block();
            b.ins().jump(vheader, &[]);
            b.switch_to_block(vheader);
            let i = b.use_var(iv);
            let next = b.ins().iadd_imm_s(i, lanes as i64);
            let fits = b.ins().icmp(IntCC::UnsignedLessThanOrEqual, next, end);
            b.ins().brif(fits, vbody, &[], sheader, &[]);
            b.switch_to_block(vbody);
            let gathered = self.emit_gathers(&mut b, m, k, &h, &gathers, &csr, i, lanes, simd);
            self.emit_body(&mut b, m, k, &h, i, lanes, &gathered);
            b.def_var(iv, next);
            b.ins().jump(vheader, &[]);
        } else {
            b.ins().jump(sheader, &[]);
        }

        b.switch_to_block(sheader);
        let i = b.use_var(iv);
        let more = b.ins().icmp(IntCC::UnsignedLessThan, i, end);
        b.ins().brif(more, sbody, &[], exit, &[]);

        b.switch_to_block(sbody);
        let gathered = self.emit_gathers(&mut b, m, k, &h, &gathers, &csr, i, 1, simd);
        self.emit_body(&mut b, m, k, &h, i, 1, &gathered);
        let i1 = b.ins().iadd_imm_s(i, 1);
        b.def_var(iv, i1);
        b.ins().jump(sheader, &[]);

        b.switch_to_block(exit);
        b.ins().return_(&[]);
        b.seal_all_blocks();
        b.finalize(self.jit.target_config());
        Ok((func, simd))
    }

    /// Loads, body and stores for the entities `i .. i + lanes` (`lanes` = 1: scalar code).
    #[allow(clippy::too_many_arguments)]
    fn emit_body(
        &self,
        b: &mut FunctionBuilder,
        m: &Module,
        k: &Kernel,
        h: &Hoisted,
        i: Value,
        lanes: u32,
        gathered: &HashMap<usize, Value>,
    ) {
        let fty = self.fty();
        let size = self.precision.size();
        let vty = if lanes == 1 {
            fty
        } else {
            fty.by(lanes).expect("2 × f64 and 4 × f32 are vector types")
        };
        let ity = vty.as_int();
        // Scalars of all lanes into one value.
        let pack = |b: &mut FunctionBuilder, xs: &[Value]| {
            if lanes == 1 {
                return xs[0];
            }
            // A splat rather than `scalar_to_vector`: a loaded scalar becomes one broadcast
            // load instead of a load, a zeroed register and a merge; lanes 1.. are replaced.
            let mut v = b.ins().splat(vty, xs[0]);
            for (l, &x) in xs.iter().enumerate().skip(1) {
                v = b.ins().insertlane(v, x, l as u8);
            }
            v
        };
        let lane = |b: &mut FunctionBuilder, v: Value, l: u32| {
            if lanes == 1 {
                v
            } else {
                b.ins().extractlane(v, l as u8)
            }
        };
        // A comparison mask (all ones / zeros per lane) as a float value, for `bitselect`.
        let mask_f =
            |b: &mut FunctionBuilder, mask: Value| b.ins().bitcast(vty, MemFlagsData::new(), mask);
        let select = |b: &mut FunctionBuilder, c: Value, x: Value, y: Value| {
            if lanes == 1 {
                b.ins().select(c, x, y)
            } else {
                let c = mask_f(b, c);
                b.ins().bitselect(c, x, y)
            }
        };
        let constant = |b: &mut FunctionBuilder, c: f64| {
            let s = self.fconst(b, c);
            if lanes == 1 { s } else { b.ins().splat(vty, s) }
        };
        let per_lane = |b: &mut FunctionBuilder,
                        f: &dyn Fn(&mut FunctionBuilder, &[Value]) -> Value,
                        xs: &[Value]| {
            let outs: Vec<Value> = (0..lanes)
                .map(|l| {
                    let args: Vec<Value> = xs.iter().map(|&x| lane(b, x, l)).collect();
                    f(b, &args)
                })
                .collect();
            pack(b, &outs)
        };

        // Loads of buffers the kernel does not store to are pure (read only during the call,
        // in bounds): Cranelift may place them next to their first use, which shortens what is
        // live at once in the large element kernels.
        let load_flags = |buffer: u32| {
            if k.stores.iter().any(|s| s.buffer.0 == buffer) {
                trusted()
            } else {
                readonly().with_can_move()
            }
        };
        // Whole rows as vectors: flags without `aligned` (a row of an entity is aligned to its
        // values, not to 16 bytes).
        let vector_flags = |buffer: u32| {
            let f = MemFlagsData::new().with_notrap();
            if k.stores.iter().any(|s| s.buffer.0 == buffer) {
                f
            } else {
                f.with_readonly().with_can_move()
            }
        };
        let le = MemFlagsData::new().with_endianness(Endianness::Little);
        // Lanes of two vectors picked from their concatenation (`sel[j] < 2 · lanes`).
        let pick = |b: &mut FunctionBuilder, x: Value, y: Value, sel: &[u8]| {
            let xi = b.ins().bitcast(types::I8X16, le, x);
            let yi = b.ins().bitcast(types::I8X16, le, y);
            let mask: Vec<u8> = sel
                .iter()
                .flat_map(|&s| (0..size as u8).map(move |q| s * size as u8 + q))
                .collect();
            let imm = b.func.dfg.immediates.push(ConstantData::from(mask));
            let r = b.ins().shuffle(xi, yi, imm);
            b.ins().bitcast(vty, le, r)
        };
        // `lanes` vectors of `lanes` values transposed (rows of entities <-> components): only
        // moves bits.
        let transpose = |b: &mut FunctionBuilder, v: &[Value]| -> Vec<Value> {
            if lanes == 2 {
                vec![pick(b, v[0], v[1], &[0, 2]), pick(b, v[0], v[1], &[1, 3])]
            } else {
                let t0 = pick(b, v[0], v[1], &[0, 4, 1, 5]);
                let t1 = pick(b, v[0], v[1], &[2, 6, 3, 7]);
                let t2 = pick(b, v[2], v[3], &[0, 4, 1, 5]);
                let t3 = pick(b, v[2], v[3], &[2, 6, 3, 7]);
                vec![
                    pick(b, t0, t2, &[0, 1, 4, 5]),
                    pick(b, t0, t2, &[2, 3, 6, 7]),
                    pick(b, t1, t3, &[0, 1, 4, 5]),
                    pick(b, t1, t3, &[2, 3, 6, 7]),
                ]
            }
        };
        // Own components loaded `lanes` at a time: (buffer, first component) -> components.
        let mut own_groups: HashMap<(u32, usize), Vec<Value>> = HashMap::new();
        // Corner components likewise: (buffer, corner, first component) -> components.
        let mut corner_groups: HashMap<(u32, u32, usize), Vec<Value>> = HashMap::new();
        let mut rows: HashMap<(u32, Option<u32>), Value> = HashMap::new();
        let mut nodes: HashMap<(u32, u32), Value> = HashMap::new();
        // This iteration's connectivity row (first lane's entity), computed once.
        let mut conn_row: Option<Value> = None;
        let nc = m.corners(k.domain).unwrap_or(1) as usize;
        // Store units: `lanes` consecutive components of a buffer stored once each go as one
        // transpose and one vector store per lane; the others one by one, lane by lane.
        let units = store_units(m, k, lanes as usize);
        let unit_values: Vec<Vec<usize>> = units
            .iter()
            .map(|u| {
                u.stores()
                    .iter()
                    .map(|&j| k.body.outputs[k.stores[j].output].0 as usize)
                    .collect()
            })
            .collect();
        let reads_stored = k.args.iter().any(|a| match a {
            ArgSource::Own { buffer, .. }
            | ArgSource::Corner { buffer, .. }
            | ArgSource::Gather { buffer, .. } => k.stores.iter().any(|s| s.buffer == *buffer),
            ArgSource::Uniform(_) => false,
        });
        let deferred = |i: usize| {
            matches!(k.body.insts[i], Inst::Const(_))
                || matches!(k.body.insts[i], Inst::Arg(a)
                    if !matches!(k.args[a as usize], ArgSource::Gather { .. }))
        };
        // Stores keep their order where two write one component (the last one wins).
        let rewrites = k.stores.iter().enumerate().any(|(j, s)| {
            k.stores[..j]
                .iter()
                .any(|t| t.buffer == s.buffer && t.component == s.component)
        });
        let early = !reads_stored && !rewrites;
        let steps = super::schedule::order(&k.body, &deferred, &unit_values, early);
        let mut vals: Vec<Option<Value>> = vec![None; k.body.insts.len()];
        for step in steps {
            let idx = match step {
                Step::Inst(idx) => idx,
                Step::Store(u) => {
                    let xs: Vec<Value> = unit_values[u]
                        .iter()
                        .map(|&v| vals[v].expect("the schedule emits stored values first"))
                        .collect();
                    let mut row = |b: &mut FunctionBuilder, j: usize| {
                        let s = &k.stores[j];
                        let width = m.buffers[s.buffer.0 as usize].width as usize;
                        *rows.entry((s.buffer.0, None)).or_insert_with(|| {
                            let o = scaled(b, i, (width * size) as i64);
                            b.ins().iadd(h.store_ptrs[j], o)
                        })
                    };
                    match &units[u] {
                        StoreUnit::Rows(group) => {
                            let s = &k.stores[group[0]];
                            let width = m.buffers[s.buffer.0 as usize].width as usize;
                            let c0 = s.component as usize;
                            let base = row(b, group[0]);
                            let per_lane = transpose(b, &xs);
                            for (l, &v) in per_lane.iter().enumerate() {
                                let o = (l * width + c0) * size;
                                b.ins()
                                    .store(MemFlagsData::new().with_notrap(), v, base, off(o));
                            }
                        }
                        StoreUnit::Lanes(j) => {
                            let s = &k.stores[*j];
                            let width = m.buffers[s.buffer.0 as usize].width as usize;
                            let base = row(b, *j);
                            for l in 0..lanes {
                                let xl = lane(b, xs[0], l);
                                let o = (l as usize * width + s.component as usize) * size;
                                b.ins().store(trusted(), xl, base, off(o));
                            }
                        }
                    }
                    continue;
                }
            };
            let v =
                |n: crate::ir::V| vals[n.0 as usize].expect("the schedule emits operands first");
            let r = match k.body.insts[idx] {
                Inst::Const(c) => constant(b, c),
                Inst::Arg(a) => {
                    let a = a as usize;
                    match &k.args[a] {
                        ArgSource::Own { buffer, component } => {
                            let width = m.buffers[buffer.0 as usize].width as usize;
                            let base = h.arg_buf[&a];
                            let row = *rows.entry((buffer.0, None)).or_insert_with(|| {
                                let o = scaled(b, i, (width * size) as i64);
                                b.ins().iadd(base, o)
                            });
                            let nl = lanes as usize;
                            let c = *component as usize;
                            let c0 = c / nl * nl;
                            if nl > 1 && width == 1 {
                                // The lanes' values are adjacent: one vector load.
                                vals[idx] = Some(b.ins().load(vty, vector_flags(buffer.0), row, 0));
                                continue;
                            }
                            // Reading past the last lane's row is only for buffers this
                            // kernel does not store to: another thread may be writing the
                            // next entity's row of those.
                            let stored = k.stores.iter().any(|s| s.buffer == *buffer);
                            if nl > 1 && (c0 + nl <= width || (c0 < width && !stored)) {
                                // Components c0.. of each lane's row as one vector, transposed
                                // (past the row's end: the next row's values or the buffers'
                                // zeroed slack, `super::SLACK`, in lanes nothing reads).
                                let key = (buffer.0, c0);
                                let group = own_groups.entry(key).or_insert_with(|| {
                                    let rowv: Vec<Value> = (0..nl)
                                        .map(|l| {
                                            let o = (l * width + c0) * size;
                                            b.ins().load(vty, vector_flags(buffer.0), row, off(o))
                                        })
                                        .collect();
                                    transpose(b, &rowv)
                                });
                                vals[idx] = Some(group[c - c0]);
                                continue;
                            }
                            let xs: Vec<Value> = (0..lanes as usize)
                                .map(|l| {
                                    let o = (l * width + *component as usize) * size;
                                    b.ins().load(fty, load_flags(buffer.0), row, off(o))
                                })
                                .collect();
                            pack(b, &xs)
                        }
                        ArgSource::Corner {
                            buffer,
                            corner,
                            component,
                        } => {
                            let width = m.buffers[buffer.0 as usize].width as i64;
                            let base = h.arg_buf[&a];
                            let conn = h.conn.expect("corner loads load the connectivity");
                            let mut node_row = |b: &mut FunctionBuilder, l: u32| {
                                let node = *nodes.entry((*corner, l)).or_insert_with(|| {
                                    let p = *conn_row.get_or_insert_with(|| {
                                        let o = scaled(b, i, nc as i64 * 4);
                                        b.ins().iadd(conn, o)
                                    });
                                    let at = (l as usize * nc + *corner as usize) * 4;
                                    b.ins().uload32(readonly(), p, off(at))
                                });
                                *rows
                                    .entry((buffer.0, Some(*corner * lanes + l)))
                                    .or_insert_with(|| {
                                        let o = scaled(b, node, width * size as i64);
                                        b.ins().iadd(base, o)
                                    })
                            };
                            let nl = lanes as usize;
                            let c = *component as usize;
                            let c0 = c / nl * nl;
                            if nl > 1 {
                                // Each lane's node row from component c0 as one vector (past
                                // the row's end as with own rows), transposed: four loads and
                                // a few shuffles instead of a load and an insert per value.
                                let key = (buffer.0, *corner, c0);
                                let group = match corner_groups.get(&key) {
                                    Some(g) => g.clone(),
                                    None => {
                                        let rowv: Vec<Value> = (0..lanes)
                                            .map(|l| {
                                                let row = node_row(b, l);
                                                b.ins().load(
                                                    vty,
                                                    vector_flags(buffer.0),
                                                    row,
                                                    off(c0 * size),
                                                )
                                            })
                                            .collect();
                                        let g = transpose(b, &rowv);
                                        corner_groups.insert(key, g.clone());
                                        g
                                    }
                                };
                                vals[idx] = Some(group[c - c0]);
                                continue;
                            }
                            let row = node_row(b, 0);
                            b.ins().load(fty, load_flags(buffer.0), row, off(c * size))
                        }
                        ArgSource::Uniform(id) => {
                            let j = h
                                .uniforms
                                .iter()
                                .position(|n| n == id)
                                .expect("uniforms are collected from the arguments");
                            let u = h.uni_vals[j];
                            if lanes == 1 { u } else { b.ins().splat(vty, u) }
                        }
                        ArgSource::Gather { .. } => gathered[&a],
                    }
                }
                Inst::Un(op, a) => {
                    let x = v(a);
                    match op {
                        UnOp::Neg if lanes > 1 => {
                            // x XOR the sign bits, the mask a constant-pool operand of one
                            // `xorps` (Cranelift's vector `fneg` rebuilds the mask in registers
                            // at each use: three instructions). The same bits as `fneg`.
                            let mut sign = vec![0u8; size];
                            sign[size - 1] = 0x80;
                            let bits: Vec<u8> = (0..lanes).flat_map(|_| sign.clone()).collect();
                            let c = b.func.dfg.constants.insert(ConstantData::from(bits));
                            let mask = b.ins().vconst(vty, c);
                            b.ins().bxor(x, mask)
                        }
                        UnOp::Neg => b.ins().fneg(x),
                        UnOp::Abs => b.ins().fabs(x),
                        UnOp::Sqrt => b.ins().sqrt(x),
                        UnOp::Floor => per_lane(b, &|b, a| b.ins().floor(a[0]), &[x]),
                        UnOp::Ceil => per_lane(b, &|b, a| b.ins().ceil(a[0]), &[x]),
                        UnOp::Ln => super::vmath::emit_ln(b, x, self.precision, lanes),
                        UnOp::Cbrt | UnOp::Exp | UnOp::Sin | UnOp::Cos | UnOp::Tan | UnOp::Tanh => {
                            let f = h.fref[&Lib::Un(op)];
                            per_lane(
                                b,
                                &|b, a| {
                                    let call = b.ins().call(f, a);
                                    b.inst_results(call)[0]
                                },
                                &[x],
                            )
                        }
                    }
                }
                Inst::Bin(op, x, y) => {
                    let (x, y) = (v(x), v(y));
                    match op {
                        BinOp::Add => b.ins().fadd(x, y),
                        BinOp::Sub => b.ins().fsub(x, y),
                        BinOp::Mul => b.ins().fmul(x, y),
                        BinOp::Div => b.ins().fdiv(x, y),
                        BinOp::Min | BinOp::Max if self.min_max == MinMax::Inline => {
                            // Rust's min/max: a NaN `x` gives `y`; otherwise `y` only where it
                            // is strictly smaller (larger), so ties and a NaN `y` give `x`.
                            let cc = if op == BinOp::Min {
                                FloatCC::LessThan
                            } else {
                                FloatCC::GreaterThan
                            };
                            let y_wins = b.ins().fcmp(cc, y, x);
                            let r = select(b, y_wins, y, x);
                            let x_nan = b.ins().fcmp(FloatCC::Unordered, x, x);
                            select(b, x_nan, y, r)
                        }
                        BinOp::Pow | BinOp::Min | BinOp::Max => {
                            let f = h.fref[&Lib::Bin(op)];
                            per_lane(
                                b,
                                &|b, a| {
                                    let call = b.ins().call(f, a);
                                    b.inst_results(call)[0]
                                },
                                &[x, y],
                            )
                        }
                    }
                }
                Inst::Cmp(op, x, y) => {
                    let cc = match op {
                        CmpOp::Lt => FloatCC::LessThan,
                        CmpOp::Le => FloatCC::LessThanOrEqual,
                        CmpOp::Gt => FloatCC::GreaterThan,
                        CmpOp::Ge => FloatCC::GreaterThanOrEqual,
                        CmpOp::Eq => FloatCC::Equal,
                        // `!=` is true for unordered operands, as in Rust.
                        CmpOp::Ne => FloatCC::NotEqual,
                    };
                    let c = b.ins().fcmp(cc, v(x), v(y));
                    if lanes == 1 {
                        let one = constant(b, 1.0);
                        let zero = constant(b, 0.0);
                        b.ins().select(c, one, zero)
                    } else {
                        // mask & bits(1.0): 1.0 where true, +0.0 where false.
                        let one = constant(b, 1.0);
                        let one_bits = b.ins().bitcast(ity, MemFlagsData::new(), one);
                        let r = b.ins().band(c, one_bits);
                        b.ins().bitcast(vty, MemFlagsData::new(), r)
                    }
                }
                Inst::Select(c, x, y) => {
                    let zero = constant(b, 0.0);
                    // `c != 0.0`: NaN selects `x`, as in the interpreter.
                    let t = b.ins().fcmp(FloatCC::NotEqual, v(c), zero);
                    select(b, t, v(x), v(y))
                }
            };
            vals[idx] = Some(r);
        }
    }

    pub(super) fn fconst(&self, b: &mut FunctionBuilder, c: f64) -> Value {
        match self.precision {
            Precision::F64 => b.ins().f64const(c),
            Precision::F32 => b.ins().f32const(c as f32),
        }
    }
}

/// Stores that go out together.
pub(super) enum StoreUnit {
    /// `lanes` stores of consecutive components `c0..c0 + lanes` of one buffer, each the only
    /// store of its component: one transpose and one vector store per lane (stores in
    /// component order).
    Rows(Vec<usize>),
    /// One store, lane by lane.
    Lanes(usize),
}

impl StoreUnit {
    fn stores(&self) -> &[usize] {
        match self {
            StoreUnit::Rows(g) => g,
            StoreUnit::Lanes(j) => std::slice::from_ref(j),
        }
    }
}

/// The kernel's stores as units for `lanes` lanes (1: scalar code, no row units).
fn store_units(m: &Module, k: &Kernel, lanes: usize) -> Vec<StoreUnit> {
    let mut units = Vec::new();
    let mut taken = vec![false; k.stores.len()];
    if lanes > 1 {
        for (si, s) in k.stores.iter().enumerate() {
            let width = m.buffers[s.buffer.0 as usize].width as usize;
            let c0 = s.component as usize;
            if taken[si] || !c0.is_multiple_of(lanes) || c0 + lanes > width {
                continue;
            }
            let once = |c: usize| {
                let mut at = k
                    .stores
                    .iter()
                    .enumerate()
                    .filter(|(_, t)| t.buffer == s.buffer && t.component as usize == c);
                match (at.next(), at.next()) {
                    (Some((j, _)), None) => Some(j),
                    _ => None,
                }
            };
            let Some(group) = (c0..c0 + lanes).map(once).collect::<Option<Vec<usize>>>() else {
                continue;
            };
            if group.iter().any(|&j| taken[j]) {
                continue;
            }
            for &j in &group {
                taken[j] = true;
            }
            units.push(StoreUnit::Rows(group));
        }
    }
    units.extend(
        (0..k.stores.len())
            .filter(|&j| !taken[j])
            .map(StoreUnit::Lanes),
    );
    units
}
