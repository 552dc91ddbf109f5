//! The gather loops of node kernels: each gathered argument is the sum, over the node's CSR
//! list of incident entities (in list order), of one value of the incident entity's row.
//!
//! Scalar code (one node) keeps one accumulator per argument, starting at `+0.0`, and adds the
//! incidences in list order:
//!
//! ```text
//! acc = 0.0; for j in offsets[i]..offsets[i+1] { acc = acc + x[entries[j]] }
//! ```
//!
//! A buffer of per-corner rows (element × 4·stride, triangle × 3·stride: the force buffers)
//! is addressed through the topology's slot list, `entity · corners + corner` per incidence,
//! so the loop loads one index and forms the row with one multiply, instead of loading the
//! `(entity, corner)` pair and combining two products.
//!
//! Vector code (2 × f64 or 4 × f32 nodes per iteration) runs that same scalar loop for each
//! lane's node in turn, stores each lane's sums into a stack slot and loads them as vectors for
//! the vectorized rest of the body. Every node's sums are therefore exactly the scalar code's,
//! whatever lanes or threads the nodes fall in.
//!
//! Walking the lanes' lists side by side instead (one vector add per step, each lane loading
//! its own incidence, lanes whose list has ended masked out up to the largest count) was
//! measured slower: without a hardware gather each lane still needs its own address
//! arithmetic and loads, the scalar loop's `addss mem` becomes a load and an `insertps` per
//! lane, and the masked steps waste lanes wherever neighbouring nodes' incidence counts differ
//! (surface nodes): 3.46 M against 3.25 M instructions per 10k f32 forward step.

use super::codegen::{Hoisted, PTR, Translator, off, readonly, scaled, trusted};
use crate::ir::{ArgSource, Domain, Kernel, Module};
use cranelift_codegen::ir::condcodes::IntCC;
use cranelift_codegen::ir::{
    InstBuilder, MemFlagsData, StackSlotData, StackSlotKind, Value, types,
};
use cranelift_frontend::{FunctionBuilder, Variable};
use std::collections::HashMap;

/// Where a gather loop reads its incidences.
#[derive(Clone, Copy)]
pub(super) enum Incidences {
    /// `(entity, corner)` pairs (two `u32` per incidence).
    Pairs(Value),
    /// `entity · corners + corner` (one `u32` per incidence).
    Slots(Value),
    /// As `Slots`, and the values of a row summed as vectors (in vector code): one load and
    /// add per 4 × f32 (2 × f64) components, each lane summing its component in list order,
    /// so the sums are the scalar loop's bits. A row's last vector may read past the row into
    /// the next one or the buffer's slack (`super::SLACK`), in lanes no argument takes.
    SlotRows(Value),
}

impl Translator<'_> {
    /// The gathered arguments of the nodes `i .. i + lanes` (scalars for `lanes` = 1, else
    /// vectors with one node per lane), one CSR walk per incident domain of `gathers` (whose
    /// offsets and entries pointers are `csr`).
    #[allow(clippy::too_many_arguments)]
    pub(super) fn emit_gathers(
        &self,
        b: &mut FunctionBuilder,
        m: &Module,
        k: &Kernel,
        h: &Hoisted,
        gathers: &[(Domain, Vec<usize>)],
        csr: &[(Value, Value, Value)],
        i: Value,
        lanes: u32,
        simd: bool,
    ) -> HashMap<usize, Value> {
        let mut gathered = HashMap::new();
        for ((over, args), &(offsets, entries, slots)) in gathers.iter().zip(csr) {
            // Per-corner rows (width = corners × stride, every gather of the domain's
            // buffers): the incidence's slot `entity · corners + corner` times the stride is
            // the row, one load per incidence. Otherwise the `(entity, corner)` pair.
            let corners = m.corners(*over).unwrap_or(1);
            let per_corner = args.iter().all(|&a| match &k.args[a] {
                ArgSource::Gather { buffer, stride, .. } => {
                    m.buffers[buffer.0 as usize].width == corners * stride
                }
                _ => false,
            });
            let list = match (per_corner, simd) {
                (true, true) => Incidences::SlotRows(slots),
                (true, false) => Incidences::Slots(slots),
                _ => Incidences::Pairs(entries),
            };
            let sums = if lanes == 1 {
                self.scalar_gather(b, m, k, h, args, offsets, list, i)
            } else {
                self.lane_by_lane_gather(b, m, k, h, args, offsets, list, i, lanes)
            };
            gathered.extend(args.iter().copied().zip(sums));
        }
        gathered
    }

    /// The value of each argument of `args` at incidence `j` of `list`.
    #[allow(clippy::too_many_arguments)]
    fn incidence_loads(
        &self,
        b: &mut FunctionBuilder,
        m: &Module,
        k: &Kernel,
        h: &Hoisted,
        args: &[usize],
        list: Incidences,
        j: Value,
    ) -> Vec<Value> {
        let fty = self.fty();
        let size = self.precision.size();
        let (ent, cor) = match list {
            Incidences::Pairs(entries) => {
                let eo = scaled(b, j, 8);
                let at = b.ins().iadd(entries, eo);
                (
                    b.ins().uload32(readonly(), at, 0),
                    Some(b.ins().uload32(readonly(), at, 4)),
                )
            }
            Incidences::Slots(slots) | Incidences::SlotRows(slots) => {
                let so = scaled(b, j, 4);
                let at = b.ins().iadd(slots, so);
                (b.ins().uload32(readonly(), at, 0), None)
            }
        };
        args.iter()
            .map(|&a| {
                let ArgSource::Gather {
                    buffer,
                    stride,
                    component,
                    ..
                } = &k.args[a]
                else {
                    unreachable!("grouped gathers are gathers")
                };
                let p = match cor {
                    Some(cor) => {
                        let width = m.buffers[buffer.0 as usize].width as i64;
                        let row = scaled(b, ent, width * size as i64);
                        let col = scaled(b, cor, *stride as i64 * size as i64);
                        let p = b.ins().iadd(h.arg_buf[&a], row);
                        b.ins().iadd(p, col)
                    }
                    None => {
                        let row = scaled(b, ent, *stride as i64 * size as i64);
                        b.ins().iadd(h.arg_buf[&a], row)
                    }
                };
                b.ins()
                    .load(fty, trusted(), p, off(*component as usize * size))
            })
            .collect()
    }

    #[allow(clippy::too_many_arguments)]
    fn scalar_gather(
        &self,
        b: &mut FunctionBuilder,
        m: &Module,
        k: &Kernel,
        h: &Hoisted,
        args: &[usize],
        offsets: Value,
        list: Incidences,
        i: Value,
    ) -> Vec<Value> {
        if let Incidences::SlotRows(slots) = list {
            return self.row_gather(b, k, h, args, offsets, slots, i);
        }
        let fty = self.fty();
        let zero = self.fconst(b, 0.0);
        let accs: Vec<Variable> = args
            .iter()
            .map(|_| {
                let v = b.declare_var(fty);
                b.def_var(v, zero);
                v
            })
            .collect();
        csr_loop(b, offsets, i, &mut |b, j| {
            let xs = self.incidence_loads(b, m, k, h, args, list, j);
            for (&x, &acc) in xs.iter().zip(&accs) {
                let s = b.use_var(acc);
                let s = b.ins().fadd(s, x);
                b.def_var(acc, s);
            }
        });
        accs.iter().map(|&acc| b.use_var(acc)).collect()
    }

    /// The scalar loop with each row's components summed as vectors ([`Incidences::SlotRows`]):
    /// one accumulator per (buffer, stride, group of 4 × f32 / 2 × f64 components), the
    /// arguments' sums taken from its lanes.
    #[allow(clippy::too_many_arguments)]
    fn row_gather(
        &self,
        b: &mut FunctionBuilder,
        k: &Kernel,
        h: &Hoisted,
        args: &[usize],
        offsets: Value,
        slots: Value,
        i: Value,
    ) -> Vec<Value> {
        let size = self.precision.size();
        let nl = 16 / size;
        let vty = self
            .fty()
            .by(nl as u32)
            .expect("2 × f64 and 4 × f32 are vector types");
        // (buffer, stride, first component) of each accumulator; per argument, its
        // accumulator and lane.
        let mut groups: Vec<(u32, u32, usize, usize)> = Vec::new();
        let mut place: Vec<(usize, u8)> = Vec::new();
        for &a in args {
            let ArgSource::Gather {
                buffer,
                stride,
                component,
                ..
            } = &k.args[a]
            else {
                unreachable!("grouped gathers are gathers")
            };
            let c = *component as usize;
            let c0 = c / nl * nl;
            let g = match groups
                .iter()
                .position(|&(bu, st, g0, _)| bu == buffer.0 && st == *stride && g0 == c0)
            {
                Some(g) => g,
                None => {
                    groups.push((buffer.0, *stride, c0, a));
                    groups.len() - 1
                }
            };
            place.push((g, (c - c0) as u8));
        }
        let zero = self.fconst(b, 0.0);
        let zero = b.ins().splat(vty, zero);
        let accs: Vec<Variable> = groups
            .iter()
            .map(|_| {
                let v = b.declare_var(vty);
                b.def_var(v, zero);
                v
            })
            .collect();
        csr_loop(b, offsets, i, &mut |b, j| {
            let so = scaled(b, j, 4);
            let at = b.ins().iadd(slots, so);
            let slot = b.ins().uload32(readonly(), at, 0);
            let flags = MemFlagsData::new().with_notrap().with_readonly();
            for (&(_, stride, c0, a), &acc) in groups.iter().zip(&accs) {
                let row = scaled(b, slot, stride as i64 * size as i64);
                let p = b.ins().iadd(h.arg_buf[&a], row);
                let x = b.ins().load(vty, flags, p, off(c0 * size));
                let s = b.use_var(acc);
                let s = b.ins().fadd(s, x);
                b.def_var(acc, s);
            }
        });
        let sums: Vec<Value> = accs.iter().map(|&acc| b.use_var(acc)).collect();
        place
            .iter()
            .map(|&(g, l)| b.ins().extractlane(sums[g], l))
            .collect()
    }

    /// Each lane's sums by the scalar loop, one lane after the other, packed into vectors.
    #[allow(clippy::too_many_arguments)]
    fn lane_by_lane_gather(
        &self,
        b: &mut FunctionBuilder,
        m: &Module,
        k: &Kernel,
        h: &Hoisted,
        args: &[usize],
        offsets: Value,
        list: Incidences,
        i: Value,
        lanes: u32,
    ) -> Vec<Value> {
        let vty = self
            .fty()
            .by(lanes)
            .expect("2 × f64 and 4 × f32 are vector types");
        // Each lane's sums are stored to a stack slot right after its loop and the vectors
        // loaded from it after the last lane's: values that stayed in registers would all be
        // live across the later lanes' loops (Cranelift places pure instructions such as
        // `insertlane` at their first use) and be spilled and reloaded in those loops.
        let size = self.precision.size();
        let slot = b.create_sized_stack_slot(StackSlotData::new(
            StackSlotKind::ExplicitSlot,
            (args.len() * 16) as u32,
            4, // 16-byte aligned, as the aligned vector loads need
        ));
        let base = b.ins().stack_addr(PTR, slot, 0);
        for l in 0..lanes as usize {
            let il = b.ins().iadd_imm_s(i, l as i64);
            let xs = self.scalar_gather(b, m, k, h, args, offsets, list, il);
            for (a, &x) in xs.iter().enumerate() {
                b.ins().store(trusted(), x, base, off(a * 16 + l * size));
            }
        }
        (0..args.len())
            .map(|a| b.ins().load(vty, trusted(), base, off(a * 16)))
            .collect()
    }
}

/// `for j in offsets[i]..offsets[i + 1] { body(j) }`: node `i`'s CSR list, in order; the
/// builder continues after the loop. Unrolled by two (`body(j); body(j + 1)` per round, then
/// the odd one out), which halves the loop's own compare, branch and increment per incidence;
/// the bodies still run in list order, so sums come out the same.
fn csr_loop(
    b: &mut FunctionBuilder,
    offsets: Value,
    i: Value,
    body: &mut dyn FnMut(&mut FunctionBuilder, Value),
) {
    let o = scaled(b, i, 4);
    let oa = b.ins().iadd(offsets, o);
    let start = b.ins().uload32(readonly(), oa, 0);
    let stop = b.ins().uload32(readonly(), oa, 4);
    let jv = b.declare_var(types::I64);
    b.def_var(jv, start);
    let pair_head = b.create_block();
    let pair = b.create_block();
    let last_head = b.create_block();
    let last = b.create_block();
    let done = b.create_block();
    b.ins().jump(pair_head, &[]);
    b.switch_to_block(pair_head);
    let j = b.use_var(jv);
    let j2 = b.ins().iadd_imm_s(j, 2);
    let two_more = b.ins().icmp(IntCC::UnsignedLessThanOrEqual, j2, stop);
    b.ins().brif(two_more, pair, &[], last_head, &[]);
    b.switch_to_block(pair);
    body(b, j);
    let j1 = b.ins().iadd_imm_s(j, 1);
    body(b, j1);
    let j2 = b.ins().iadd_imm_s(j, 2);
    b.def_var(jv, j2);
    b.ins().jump(pair_head, &[]);
    b.switch_to_block(last_head);
    let j = b.use_var(jv);
    let one_more = b.ins().icmp(IntCC::UnsignedLessThan, j, stop);
    b.ins().brif(one_more, last, &[], done, &[]);
    b.switch_to_block(last);
    body(b, j);
    b.ins().jump(done, &[]);
    b.switch_to_block(done);
}
