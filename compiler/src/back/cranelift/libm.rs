//! The functions JIT code calls for transcendental operations: thin `extern "C"` wrappers
//! around the very std functions the interpreter ([`crate::ir::eval_un`], [`crate::ir::eval_bin`])
//! uses, so CPU results are bit-identical to it in f64. `ln` is not among them: it is compiled
//! inline (`vmath.rs`), as the interpreter's [`crate::ir::math`] computes it.

use crate::back::Precision;
use crate::ir::{BinOp, UnOp};
use std::hint::black_box;

macro_rules! unary {
    ($($name:ident: $t:ty => $f:ident;)*) => {$(
        extern "C" fn $name(x: $t) -> $t {
            x.$f()
        }
    )*};
}

macro_rules! binary {
    ($($name:ident: $t:ty => $f:ident;)*) => {$(
        extern "C" fn $name(x: $t, y: $t) -> $t {
            x.$f(y)
        }
    )*};
}

unary! {
    softc_cbrt_f64: f64 => cbrt;
    softc_exp_f64: f64 => exp;
    softc_sin_f64: f64 => sin;
    softc_cos_f64: f64 => cos;
    softc_tan_f64: f64 => tan;
    softc_tanh_f64: f64 => tanh;
    softc_cbrt_f32: f32 => cbrt;
    softc_exp_f32: f32 => exp;
    softc_sin_f32: f32 => sin;
    softc_cos_f32: f32 => cos;
    softc_tan_f32: f32 => tan;
    softc_tanh_f32: f32 => tanh;
}

binary! {
    softc_pow_f64: f64 => powf;
    softc_min_f64: f64 => min;
    softc_max_f64: f64 => max;
    softc_pow_f32: f32 => powf;
    softc_min_f32: f32 => min;
    softc_max_f32: f32 => max;
}

/// A function JIT code may call.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub(super) enum Lib {
    Un(UnOp),
    Bin(BinOp),
}

impl Lib {
    /// The symbol of this function at a precision; `None` for operations compiled inline.
    pub(super) fn symbol(self, p: Precision) -> Option<&'static str> {
        let f64 = p == Precision::F64;
        Some(match (self, f64) {
            (Lib::Un(UnOp::Cbrt), true) => "softc_cbrt_f64",
            (Lib::Un(UnOp::Exp), true) => "softc_exp_f64",
            (Lib::Un(UnOp::Sin), true) => "softc_sin_f64",
            (Lib::Un(UnOp::Cos), true) => "softc_cos_f64",
            (Lib::Un(UnOp::Tan), true) => "softc_tan_f64",
            (Lib::Un(UnOp::Tanh), true) => "softc_tanh_f64",
            (Lib::Bin(BinOp::Pow), true) => "softc_pow_f64",
            (Lib::Bin(BinOp::Min), true) => "softc_min_f64",
            (Lib::Bin(BinOp::Max), true) => "softc_max_f64",
            (Lib::Un(UnOp::Cbrt), false) => "softc_cbrt_f32",
            (Lib::Un(UnOp::Exp), false) => "softc_exp_f32",
            (Lib::Un(UnOp::Sin), false) => "softc_sin_f32",
            (Lib::Un(UnOp::Cos), false) => "softc_cos_f32",
            (Lib::Un(UnOp::Tan), false) => "softc_tan_f32",
            (Lib::Un(UnOp::Tanh), false) => "softc_tanh_f32",
            (Lib::Bin(BinOp::Pow), false) => "softc_pow_f32",
            (Lib::Bin(BinOp::Min), false) => "softc_min_f32",
            (Lib::Bin(BinOp::Max), false) => "softc_max_f32",
            _ => return None,
        })
    }

    pub(super) fn arity(self) -> usize {
        match self {
            Lib::Un(_) => 1,
            Lib::Bin(_) => 2,
        }
    }
}

/// Every wrapper, for `JITBuilder::symbols`.
pub(super) fn symbols() -> Vec<(&'static str, *const u8)> {
    vec![
        ("softc_cbrt_f64", softc_cbrt_f64 as *const u8),
        ("softc_exp_f64", softc_exp_f64 as *const u8),
        ("softc_sin_f64", softc_sin_f64 as *const u8),
        ("softc_cos_f64", softc_cos_f64 as *const u8),
        ("softc_tan_f64", softc_tan_f64 as *const u8),
        ("softc_tanh_f64", softc_tanh_f64 as *const u8),
        ("softc_pow_f64", softc_pow_f64 as *const u8),
        ("softc_min_f64", softc_min_f64 as *const u8),
        ("softc_max_f64", softc_max_f64 as *const u8),
        ("softc_cbrt_f32", softc_cbrt_f32 as *const u8),
        ("softc_exp_f32", softc_exp_f32 as *const u8),
        ("softc_sin_f32", softc_sin_f32 as *const u8),
        ("softc_cos_f32", softc_cos_f32 as *const u8),
        ("softc_tan_f32", softc_tan_f32 as *const u8),
        ("softc_tanh_f32", softc_tanh_f32 as *const u8),
        ("softc_pow_f32", softc_pow_f32 as *const u8),
        ("softc_min_f32", softc_min_f32 as *const u8),
        ("softc_max_f32", softc_max_f32 as *const u8),
    ]
}

/// Whether Rust's `min`/`max` on this host behave as the inline sequence the backend emits:
/// a NaN first operand gives the second operand, otherwise the second operand only when it is
/// strictly smaller (larger), so ties (`0.0` against `-0.0`) and a NaN second operand give the
/// first. That is how rustc lowers `f64::min` on x86-64; where a probe finds otherwise, the
/// backend calls the std function instead, so results match the interpreter on every host.
pub(super) fn inline_min_max_matches_std() -> bool {
    let (z, nz) = (black_box(0.0f64), black_box(-0.0f64));
    let n1 = black_box(f64::from_bits(0x7ff8_0000_0000_0001));
    let n2 = black_box(f64::from_bits(0xfff8_0000_0000_0002));
    let one = black_box(1.0f64);
    let ok64 = z.min(nz).to_bits() == z.to_bits()
        && nz.min(z).to_bits() == nz.to_bits()
        && z.max(nz).to_bits() == z.to_bits()
        && nz.max(z).to_bits() == nz.to_bits()
        && n1.min(n2).to_bits() == n2.to_bits()
        && n1.max(n2).to_bits() == n2.to_bits()
        && n1.min(one) == one
        && one.min(n1) == one
        && n1.max(one) == one
        && one.max(n1) == one;
    let (z, nz) = (black_box(0.0f32), black_box(-0.0f32));
    let n1 = black_box(f32::from_bits(0x7fc0_0001));
    let n2 = black_box(f32::from_bits(0xffc0_0002));
    let ok32 = z.min(nz).to_bits() == z.to_bits()
        && nz.min(z).to_bits() == nz.to_bits()
        && z.max(nz).to_bits() == z.to_bits()
        && nz.max(z).to_bits() == nz.to_bits()
        && n1.min(n2).to_bits() == n2.to_bits()
        && n1.max(n2).to_bits() == n2.to_bits();
    ok64 && ok32
}
