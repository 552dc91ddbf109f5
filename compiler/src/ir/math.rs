//! The IR's natural logarithm, written out as a fixed sequence of IEEE operations so that every
//! CPU path computes the same bits: the interpreter and constant folding call these functions,
//! and the Cranelift backend emits the very same sequence inline for scalars and for vectors of
//! 4 × f32 / 2 × f64 (`back/cranelift/vmath.rs`), so the element kernels take `ln` in vector
//! registers instead of one library call per lane.
//!
//! The method is the classic one of 4.3BSD/fdlibm: x = 2^k·m with m in [√½, √2), f = m − 1,
//! s = f / (2 + f), ln(1 + f) = 2s + 2s³/3 + … = f − f²/2 + s·(f²/2 + R(s²)) with R a minimax
//! polynomial (degree 7 in s² for f64, 4 for f32, the published fdlibm/FreeBSD coefficients),
//! and k·ln 2 split into a high part exact in the precision and a low part. The result is
//! within 1 ulp of the exact logarithm (f64, f32; the tests in this module check it against
//! the std/libm `ln` at millions of points, including arguments within a few ulps of 1, where
//! ln(1 + d) must stay accurate relative to d — a stress at small strain depends on it).
//!
//! Special values as C's `log`: ln(±0) = −∞, ln(x < 0) = NaN, ln(+∞) = +∞, ln(NaN) = NaN;
//! subnormal arguments are scaled into the normal range first.
//!
//! Every step is one IEEE operation in the written order (no fused multiply-add); the integer
//! steps move the exponent through the bit pattern, and the exponent reaches floating point
//! through the 2^52 (2^23) bias trick instead of an int-to-float conversion, which x86 SSE has
//! no 2 × i64 form of.

/// The f64 constants of the method (the published decimal forms, which parse to the exact
/// doubles).
#[allow(clippy::excessive_precision)]
pub mod f64c {
    pub const LG: [f64; 7] = [
        6.666666666666735130e-01,
        3.999999999940941908e-01,
        2.857142874366239149e-01,
        2.222219843214978396e-01,
        1.818357216161805012e-01,
        1.531383769920937332e-01,
        1.479819860511658591e-01,
    ];
    pub const LN2_HI: f64 = 6.93147180369123816490e-01;
    pub const LN2_LO: f64 = 1.90821492927058770002e-10;
    /// Added to the bit pattern so that the exponent field rounds at √½ instead of 1.
    pub const SHIFT: u64 = (0x3ff0_0000 - 0x3fe6_a09e) << 32;
    /// The bit pattern of √½'s exponent and leading mantissa bits, added back to the mantissa.
    pub const SQRT_HALF_BITS: u64 = 0x3fe6_a09e << 32;
    pub const MANTISSA: u64 = (1 << 52) - 1;
    pub const MANTISSA_BITS: u32 = 52;
    /// 2^52: its bit pattern OR a small integer is 2^52 + that integer.
    pub const TWO52_BITS: u64 = 0x4330_0000_0000_0000;
    pub const TWO52: f64 = 4_503_599_627_370_496.0;
    pub const BIAS: f64 = 1023.0;
    /// Subnormals are multiplied by 2^54 first.
    pub const SUBNORMAL_SCALE: f64 = 18_014_398_509_481_984.0;
    pub const SUBNORMAL_K: f64 = -54.0;
}

/// The f32 constants of the method.
pub mod f32c {
    pub const LG: [f32; 4] = [
        f32::from_bits(0x3f2a_aaaa), // 0xaaaaaa × 2^-24 ≈ 0.666 666 63
        f32::from_bits(0x3ecc_ce13), // 0xccce13 × 2^-25 ≈ 0.400 009 72
        f32::from_bits(0x3e91_e9ee), // 0x91e9ee × 2^-25 ≈ 0.284 987 87
        f32::from_bits(0x3e78_9e26), // 0xf89e26 × 2^-26 ≈ 0.242 790 79
    ];
    /// ln 2 to 16 bits (k · LN2_HI is exact) and the rest.
    pub const LN2_HI: f32 = f32::from_bits(0x3f31_7180);
    pub const LN2_LO: f32 = f32::from_bits(0x3717_f7d1);
    pub const SHIFT: u32 = 0x3f80_0000 - 0x3f35_04f3;
    pub const SQRT_HALF_BITS: u32 = 0x3f35_04f3;
    pub const MANTISSA: u32 = (1 << 23) - 1;
    pub const MANTISSA_BITS: u32 = 23;
    pub const TWO23_BITS: u32 = 0x4b00_0000;
    pub const TWO23: f32 = 8_388_608.0;
    pub const BIAS: f32 = 127.0;
    pub const SUBNORMAL_SCALE: f32 = 33_554_432.0;
    pub const SUBNORMAL_K: f32 = -25.0;
}

/// ln(x) in f64, as the IR defines it (within 1 ulp of the exact value).
pub fn ln_f64(x: f64) -> f64 {
    use f64c::*;
    let tiny = x < f64::MIN_POSITIVE;
    let xs = if tiny { x * SUBNORMAL_SCALE } else { x };
    let k_extra = if tiny { SUBNORMAL_K } else { 0.0 };
    let ix = xs.to_bits().wrapping_add(SHIFT);
    let kb = f64::from_bits((ix >> MANTISSA_BITS) | TWO52_BITS) - TWO52;
    let k = (kb - BIAS) + k_extra;
    let m = f64::from_bits((ix & MANTISSA).wrapping_add(SQRT_HALF_BITS));
    let f = m - 1.0;
    let hfsq = 0.5 * f * f;
    let s = f / (2.0 + f);
    let z = s * s;
    let w = z * z;
    let t1 = w * (LG[1] + w * (LG[3] + w * LG[5]));
    let t2 = z * (LG[0] + w * (LG[2] + w * (LG[4] + w * LG[6])));
    let r = t2 + t1;
    let y = s * (hfsq + r) + k * LN2_LO - hfsq + f + k * LN2_HI;
    special(x, y, f64::INFINITY, f64::NEG_INFINITY, f64::NAN)
}

/// ln(x) in f32, as the IR defines it at f32 (within 1 ulp of the exact value).
pub fn ln_f32(x: f32) -> f32 {
    use f32c::*;
    let tiny = x < f32::MIN_POSITIVE;
    let xs = if tiny { x * SUBNORMAL_SCALE } else { x };
    let k_extra = if tiny { SUBNORMAL_K } else { 0.0 };
    let ix = xs.to_bits().wrapping_add(SHIFT);
    let kb = f32::from_bits((ix >> MANTISSA_BITS) | TWO23_BITS) - TWO23;
    let k = (kb - BIAS) + k_extra;
    let m = f32::from_bits((ix & MANTISSA).wrapping_add(SQRT_HALF_BITS));
    let f = m - 1.0;
    let hfsq = 0.5 * f * f;
    let s = f / (2.0 + f);
    let z = s * s;
    let w = z * z;
    let t1 = w * (LG[1] + w * LG[3]);
    let t2 = z * (LG[0] + w * LG[2]);
    let r = t2 + t1;
    let y = s * (hfsq + r) + k * LN2_LO - hfsq + f + k * LN2_HI;
    special(x, y, f32::INFINITY, f32::NEG_INFINITY, f32::NAN)
}

/// The special values, in the order the backend selects them.
fn special<T: PartialOrd + Default + Copy>(x: T, y: T, inf: T, neg_inf: T, nan: T) -> T {
    let y = if x == inf { inf } else { y };
    let y = if x == T::default() { neg_inf } else { y };
    // Negative or NaN (unordered): NaN.
    if x >= T::default() { y } else { nan }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Distance in ulps between two finite values of the same sign.
    fn ulps64(a: f64, b: f64) -> u64 {
        (a.to_bits() as i64 - b.to_bits() as i64).unsigned_abs()
    }

    /// The correctly rounded f64 logarithm is not at hand; std's `ln` (glibc, < 1 ulp) is the
    /// yardstick, so "within 1 ulp of the exact value" is checked as "within 2 ulps of std's"
    /// with the share of exact agreements reported.
    #[test]
    fn ln_f64_is_within_an_ulp_everywhere_and_exact_at_the_special_values() {
        let mut worst = 0;
        let mut same = 0usize;
        let mut n = 0usize;
        let mut check = |x: f64| {
            let (got, want) = (ln_f64(x), x.ln());
            let d = if want == 0.0 {
                assert_eq!(got, 0.0, "ln({x:e})");
                0
            } else {
                assert_eq!(got.is_sign_negative(), want.is_sign_negative(), "ln({x:e})");
                ulps64(got, want)
            };
            assert!(d <= 1, "ln({x:e}) = {got:e}, std {want:e}: {d} ulps");
            worst = worst.max(d);
            same += usize::from(d == 0);
            n += 1;
        };
        // Every binade from the subnormals to the largest finite values, 200 points each.
        let mut state = 0x9e37_79b9_7f4a_7c15u64;
        for e in -1074..1024 {
            for _ in 0..200 {
                state ^= state << 13;
                state ^= state >> 7;
                state ^= state << 17;
                let m = 1.0 + (state >> 11) as f64 / (1u64 << 53) as f64;
                let x = m * 2f64.powi(e);
                if x.is_finite() && x > 0.0 {
                    check(x);
                }
            }
        }
        // Near 1, where ln(1 + d) ≈ d must keep d's relative accuracy.
        for k in 1..20_000u64 {
            check(1.0 + k as f64 * f64::EPSILON);
            check(1.0 - k as f64 * f64::EPSILON / 2.0);
            check(1.0 + k as f64 * 1e-9);
            check(1.0 - k as f64 * 1e-9);
        }
        check(f64::MIN_POSITIVE);
        check(f64::from_bits(1));
        check(f64::MAX);
        eprintln!("ln_f64: worst {worst} ulp, {same} of {n} equal to std's");
        assert_eq!(ln_f64(1.0), 0.0);
        assert_eq!(ln_f64(0.0), f64::NEG_INFINITY);
        assert_eq!(ln_f64(-0.0), f64::NEG_INFINITY);
        assert_eq!(ln_f64(f64::INFINITY), f64::INFINITY);
        assert!(ln_f64(-1.0).is_nan() && ln_f64(f64::NEG_INFINITY).is_nan());
        assert!(ln_f64(f64::NAN).is_nan() && ln_f64(-f64::MIN_POSITIVE).is_nan());
    }

    #[test]
    fn ln_f32_is_within_an_ulp_of_the_exact_value_across_all_binades_and_near_1() {
        // Positive finite f32s (every 97th bit pattern) against the f64 logarithm:
        // the stride keeps the test fast while visiting every binade and many mantissas.
        let mut worst = 0.0f64;
        let mut bits = 1u32;
        while bits < 0x7f80_0000 {
            let x = f32::from_bits(bits);
            let exact = f64::from(x).ln();
            let got = f64::from(ln_f32(x));
            // One ulp of f32 at the exact value.
            let ulp = if exact == 0.0 {
                f64::from(f32::from_bits(1))
            } else {
                let e = (exact.abs() as f32).to_bits() & 0x7f80_0000;
                f64::from(f32::from_bits(e.max(0x0080_0000))) * f64::from(f32::EPSILON)
            };
            let err = (got - exact).abs() / ulp;
            assert!(
                err <= 1.0,
                "ln({x:e}) = {got:e}, exact {exact:e}: {err} ulp"
            );
            worst = worst.max(err);
            bits += 97;
        }
        // Within a few ulps of 1, where ln(1 + d) ≈ d.
        for k in 1..100_000u32 {
            for x in [
                f32::from_bits(0x3f80_0000 + k),
                f32::from_bits(0x3f80_0000 - k),
            ] {
                let exact = f64::from(x).ln();
                let got = f64::from(ln_f32(x));
                let ulp = f64::from(f32::from_bits(
                    ((exact.abs() as f32).to_bits() & 0x7f80_0000).max(0x0080_0000),
                )) * f64::from(f32::EPSILON);
                assert!(
                    (got - exact).abs() <= ulp,
                    "ln({x:e}) = {got:e}, exact {exact:e}"
                );
            }
        }
        eprintln!("ln_f32: worst {worst:.3} ulp of the exact value");
        assert_eq!(ln_f32(1.0), 0.0);
        assert_eq!(ln_f32(0.0), f32::NEG_INFINITY);
        assert_eq!(ln_f32(f32::INFINITY), f32::INFINITY);
        assert!(ln_f32(-1.0).is_nan() && ln_f32(f32::NAN).is_nan());
    }
}
