//! `ln` compiled inline, for scalars and for vectors (4 × f32, 2 × f64): the operation sequence
//! of [`crate::ir::math`], one Cranelift instruction per step, so every lane, the scalar tail
//! and the interpreter compute the same bits. Inline vector code replaces one library call
//! per lane (with every live vector register spilled around each call) in the element kernels
//! of logarithmic strain energies.

use crate::back::Precision;
use crate::ir::math::{f32c, f64c};
use cranelift_codegen::ir::condcodes::FloatCC;
use cranelift_codegen::ir::{InstBuilder, MemFlagsData, Type, Value, types};
use cranelift_frontend::FunctionBuilder;

/// Emits the IR's `ln` of `x` (a scalar, or a vector of `lanes` values) at `precision`.
pub(super) fn emit_ln(
    b: &mut FunctionBuilder,
    x: Value,
    precision: Precision,
    lanes: u32,
) -> Value {
    let f64p = precision == Precision::F64;
    let fty = if f64p { types::F64 } else { types::F32 };
    let vty = if lanes == 1 {
        fty
    } else {
        fty.by(lanes).expect("2 × f64 and 4 × f32 are vector types")
    };
    let ity = vty.as_int();
    let e = Emit { vty, ity, lanes };

    // The method's constants at this precision (f32 ones widened exactly).
    let c = |v32: f32, v64: f64| if f64p { v64 } else { f64::from(v32) };
    let i = |v32: u32, v64: u64| if f64p { v64 } else { u64::from(v32) };
    let lg: Vec<f64> = if f64p {
        f64c::LG.to_vec()
    } else {
        f32c::LG.iter().map(|&v| f64::from(v)).collect()
    };

    let min_positive = c(f32::MIN_POSITIVE, f64::MIN_POSITIVE);
    let min_positive = e.f(b, min_positive);
    let tiny = b.ins().fcmp(FloatCC::LessThan, x, min_positive);
    let scaled = {
        let s = e.f(b, c(f32c::SUBNORMAL_SCALE, f64c::SUBNORMAL_SCALE));
        b.ins().fmul(x, s)
    };
    let xs = e.select(b, tiny, scaled, x);
    let k_extra = {
        let sk = e.f(b, c(f32c::SUBNORMAL_K, f64c::SUBNORMAL_K));
        let zero = e.f(b, 0.0);
        e.select(b, tiny, sk, zero)
    };
    let bits = e.to_int(b, xs);
    let shift = e.i(b, i(f32c::SHIFT, f64c::SHIFT));
    let ix = b.ins().iadd(bits, shift);
    let mantissa_bits = if f64p {
        f64c::MANTISSA_BITS
    } else {
        f32c::MANTISSA_BITS
    };
    let amount = b.ins().iconst(types::I32, i64::from(mantissa_bits));
    let exponent = b.ins().ushr(ix, amount);
    let two52_bits = e.i(b, i(f32c::TWO23_BITS, f64c::TWO52_BITS));
    let biased = b.ins().bor(exponent, two52_bits);
    let biased = e.to_float(b, biased);
    let two52 = e.f(b, c(f32c::TWO23, f64c::TWO52));
    let kb = b.ins().fsub(biased, two52);
    let bias = e.f(b, c(f32c::BIAS, f64c::BIAS));
    let k = b.ins().fsub(kb, bias);
    let k = b.ins().fadd(k, k_extra);
    let mantissa = e.i(b, i(f32c::MANTISSA, f64c::MANTISSA));
    let mbits = b.ins().band(ix, mantissa);
    let sqrt_half = e.i(b, i(f32c::SQRT_HALF_BITS, f64c::SQRT_HALF_BITS));
    let mbits = b.ins().iadd(mbits, sqrt_half);
    let m = e.to_float(b, mbits);

    let one = e.f(b, 1.0);
    let f = b.ins().fsub(m, one);
    let half = e.f(b, 0.5);
    let hf = b.ins().fmul(half, f);
    let hfsq = b.ins().fmul(hf, f);
    let two = e.f(b, 2.0);
    let den = b.ins().fadd(two, f);
    let s = b.ins().fdiv(f, den);
    let z = b.ins().fmul(s, s);
    let w = b.ins().fmul(z, z);
    // Horner in w: t1 over the odd-numbered coefficients (times w), t2 over the even (times z).
    let horner = |b: &mut FunctionBuilder, coeffs: &[f64]| {
        let (&last, rest) = coeffs.split_last().expect("at least one coefficient");
        let mut acc = e.f(b, last);
        for &cf in rest.iter().rev() {
            let t = b.ins().fmul(w, acc);
            let cv = e.f(b, cf);
            acc = b.ins().fadd(cv, t);
        }
        acc
    };
    let odd: Vec<f64> = lg.iter().skip(1).step_by(2).copied().collect();
    let even: Vec<f64> = lg.iter().step_by(2).copied().collect();
    let p1 = horner(b, &odd);
    let t1 = b.ins().fmul(w, p1);
    let p2 = horner(b, &even);
    let t2 = b.ins().fmul(z, p2);
    let r = b.ins().fadd(t2, t1);
    // s·(hfsq + r) + k·ln2_lo − hfsq + f + k·ln2_hi, left to right.
    let a = b.ins().fadd(hfsq, r);
    let a = b.ins().fmul(s, a);
    let lo = e.f(b, c(f32c::LN2_LO, f64c::LN2_LO));
    let klo = b.ins().fmul(k, lo);
    let y = b.ins().fadd(a, klo);
    let y = b.ins().fsub(y, hfsq);
    let y = b.ins().fadd(y, f);
    let hi = e.f(b, c(f32c::LN2_HI, f64c::LN2_HI));
    let khi = b.ins().fmul(k, hi);
    let y = b.ins().fadd(y, khi);

    // Special values, in the order of `math::special`.
    let inf = e.f(b, f64::INFINITY);
    let is_inf = b.ins().fcmp(FloatCC::Equal, x, inf);
    let y = e.select(b, is_inf, inf, y);
    let zero = e.f(b, 0.0);
    let is_zero = b.ins().fcmp(FloatCC::Equal, x, zero);
    let neg_inf = e.f(b, f64::NEG_INFINITY);
    let y = e.select(b, is_zero, neg_inf, y);
    let below = b.ins().fcmp(FloatCC::UnorderedOrLessThan, x, zero);
    let nan = e.f(b, f64::NAN);
    e.select(b, below, nan, y)
}

/// Scalar-or-vector helpers of one `emit_ln`.
struct Emit {
    vty: Type,
    ity: Type,
    lanes: u32,
}

impl Emit {
    /// A float constant (splat across the lanes).
    fn f(&self, b: &mut FunctionBuilder, c: f64) -> Value {
        let s = match self.vty.lane_type() {
            types::F64 => b.ins().f64const(c),
            _ => b.ins().f32const(c as f32),
        };
        if self.lanes == 1 {
            s
        } else {
            b.ins().splat(self.vty, s)
        }
    }

    /// An integer constant of the lane width (splat across the lanes).
    fn i(&self, b: &mut FunctionBuilder, c: u64) -> Value {
        let lane = self.ity.lane_type();
        let s = b.ins().iconst(lane, c as i64);
        if self.lanes == 1 {
            s
        } else {
            b.ins().splat(self.ity, s)
        }
    }

    fn to_int(&self, b: &mut FunctionBuilder, x: Value) -> Value {
        b.ins().bitcast(self.ity, MemFlagsData::new(), x)
    }

    fn to_float(&self, b: &mut FunctionBuilder, x: Value) -> Value {
        b.ins().bitcast(self.vty, MemFlagsData::new(), x)
    }

    /// `c ? x : y` per lane.
    fn select(&self, b: &mut FunctionBuilder, c: Value, x: Value, y: Value) -> Value {
        if self.lanes == 1 {
            b.ins().select(c, x, y)
        } else {
            let mask = b.ins().bitcast(self.vty, MemFlagsData::new(), c);
            b.ins().bitselect(mask, x, y)
        }
    }
}
