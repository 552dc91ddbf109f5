//! Rust twins of the WGSL software math of `math.rs`, step for step, evaluated the ways a
//! Vulkan driver may evaluate that WGSL: each `a*b + c` rounded twice or fused into one
//! rounding (contraction: naga emits no `NoContraction`), f32 subnormal results kept or
//! flushed to zero, and the native f32 `exp` that `softc_cbrt` starts from off by up to
//! ±40 ulps (NVIDIA's is 37 ulps off at 76). Explicit `fma` calls are fused in every variant.
//! The tests check every variant against the GPU tests' tolerances at the arguments where an
//! NVIDIA H200 failed and over the GPU tests' ranges, and that the H200's errors before the
//! explicit `fma`s are those of a reduction by the rounded sum of the constant's parts.
//!
//! Keep each twin in step with the WGSL it mirrors (same operations, same order).

use super::{
    CBRT_F32, INV_LN2, LN2_HI, LN2_LO, PIO2, TWO_OVER_PI, inv_factorials, ln_f32_consts,
    sin_cos_coeffs,
};

/// How a device evaluates the WGSL.
#[derive(Clone, Copy, Debug)]
struct Dev {
    /// `a*b + c` as one rounding.
    fused: bool,
    /// f32 subnormal results are flushed to zero.
    ftz: bool,
    /// The native f32 `exp`'s error, in ulps.
    exp_ulps: f64,
}

fn devices() -> Vec<Dev> {
    let mut v = Vec::new();
    for fused in [false, true] {
        for ftz in [false, true] {
            for exp_ulps in [-40.0, 0.0, 40.0] {
                v.push(Dev {
                    fused,
                    ftz,
                    exp_ulps,
                });
            }
        }
    }
    v
}

impl Dev {
    /// f64 `a*b + c`.
    fn mad(self, a: f64, b: f64, c: f64) -> f64 {
        if self.fused {
            a.mul_add(b, c)
        } else {
            a * b + c
        }
    }
    /// An f32 result as the device keeps it.
    fn f(self, v: f32) -> f32 {
        if self.ftz && v != 0.0 && v.abs() < f32::MIN_POSITIVE {
            0.0f32.copysign(v)
        } else {
            v
        }
    }
    fn mad32(self, a: f32, b: f32, c: f32) -> f32 {
        if self.fused {
            self.f(a.mul_add(b, c))
        } else {
            self.f(self.f(a * b) + c)
        }
    }
    fn mul32(self, a: f32, b: f32) -> f32 {
        self.f(a * b)
    }
    fn add32(self, a: f32, b: f32) -> f32 {
        self.f(a + b)
    }
    fn sub32(self, a: f32, b: f32) -> f32 {
        self.f(a - b)
    }
    fn div32(self, a: f32, b: f32) -> f32 {
        self.f(a / b)
    }
    fn exp32(self, x: f32) -> f32 {
        let e = f64::from(x).exp();
        self.f((e * (1.0 + self.exp_ulps * 2f64.powi(-24))) as f32)
    }
}

/// `c0 + z * (c1 + z * (...))`, as `horner` writes it.
fn horner(d: Dev, coeffs: &[f64], z: f64) -> f64 {
    let mut s = *coeffs.last().unwrap();
    for &c in coeffs.iter().rev().skip(1) {
        s = d.mad(z, s, c);
    }
    s
}

/// `v·2^k` exact (WGSL's `ldexp`), also where `2^k` alone would overflow.
fn ldexp(v: f64, k: i32) -> f64 {
    v * 2f64.powi(k / 2) * 2f64.powi(k - k / 2)
}

/// `softc_exp` (f64).
fn exp64(d: Dev, x: f64) -> f64 {
    if x.is_nan() {
        return x;
    }
    if x > 709.782712893384 {
        return f64::INFINITY;
    }
    if x < -745.2 {
        return 0.0;
    }
    let k = (x * INV_LN2).round_ties_even();
    let r = (-k).mul_add(LN2_LO, (-k).mul_add(LN2_HI, x));
    let p = horner(d, &inv_factorials(13), r);
    ldexp(p, k as i32)
}

/// `softc_sincos` (f64).
fn sincos64(d: Dev, x: f64) -> (f64, f64) {
    let q = (x * TWO_OVER_PI).round_ties_even();
    let r = (-q).mul_add(PIO2[2], (-q).mul_add(PIO2[1], (-q).mul_add(PIO2[0], x)));
    quadrant(d, q, r)
}

/// The polynomials and the quadrant of `softc_sincos`, given `q` and `r`.
fn quadrant(d: Dev, q: f64, r: f64) -> (f64, f64) {
    let (sc, cc) = sin_cos_coeffs();
    let z = r * r;
    let s = r * horner(d, &sc, z);
    let c = horner(d, &cc, z);
    match (q - 4.0 * (q * 0.25).floor()) as i32 {
        0 => (s, c),
        1 => (c, -s),
        2 => (-s, -c),
        _ => (-c, s),
    }
}

/// f32 `softc_ln` (musl's `logf`, subnormals normalized on their bits).
fn ln32(d: Dev, x: f32) -> f32 {
    let (hi, lo, [lg1, lg2, lg3, lg4]) = ln_f32_consts();
    let mut ix = x.to_bits();
    let mut k = 0i32;
    if ix >= 0x7f80_0000 {
        if ix == 0x7f80_0000 {
            return x;
        }
        return if ix == 0x8000_0000 {
            f32::NEG_INFINITY
        } else {
            f32::NAN
        };
    }
    if ix < 0x0080_0000 {
        if ix == 0 {
            return f32::NEG_INFINITY;
        }
        let sh = ix.leading_zeros() - 8;
        ix <<= sh;
        k = -(sh as i32);
    }
    ix += 0x3f80_0000 - 0x3f35_04f3;
    k += (ix >> 23) as i32 - 127;
    let f = d.sub32(f32::from_bits((ix & 0x007f_ffff) + 0x3f35_04f3), 1.0);
    let s = d.div32(f, d.add32(2.0, f));
    let z = d.mul32(s, s);
    let w = d.mul32(z, z);
    // z * (lg1 + w * lg3) + w * (lg2 + w * lg4)
    let r = d.mad32(z, d.mad32(w, lg3, lg1), d.mul32(w, d.mad32(w, lg4, lg2)));
    let hfsq = d.mul32(d.mul32(0.5, f), f);
    let dk = k as f32;
    // s * (hfsq + r) + dk * ln2_lo - hfsq + f + dk * ln2_hi
    let t = d.mad32(s, d.add32(hfsq, r), d.mul32(dk, lo));
    let t = d.add32(d.sub32(t, hfsq), f);
    d.mad32(dk, hi, t)
}

/// `v·2^k` in f32 for the exact scalings of `softc_cbrt`.
fn ldexp32(v: f32, k: i32) -> f32 {
    (f64::from(v) * 2f64.powi(k)) as f32
}

/// f32 `softc_cbrt`.
fn cbrt32(d: Dev, x: f32) -> f32 {
    let (big, small, j) = CBRT_F32;
    let mut m = x.abs();
    if m == 0.0 || x.is_nan() || m == f32::INFINITY {
        return x;
    }
    let mut scale = 0;
    if m > big {
        m = ldexp32(m, -3 * j);
        scale = j;
    }
    if m < small {
        m = ldexp32(m, 3 * j);
        scale = -j;
    }
    let mut r = d.exp32(d.mul32(0.333_333_34, ln32(d, m)));
    // r - (r * r * r - m) / (real(3) * r * r)
    let res = d.mad32(d.mul32(r, r), r, -m);
    r = d.sub32(r, d.div32(res, d.mul32(d.mul32(3.0, r), r)));
    r = ldexp32(r, scale);
    if x < 0.0 { -r } else { r }
}

/// An f32 ulp at `v` (as the GPU test's `ulp32`).
fn ulp32(v: f64) -> f64 {
    let v = v.abs();
    if v < f64::from(f32::MIN_POSITIVE) {
        return 2f64.powi(-149);
    }
    2f64.powi(v.log2().floor() as i32 - 23)
}

/// The f64 GPU test's arguments, the H200's worst ones, and `n·π/2 + δ` up to `|x| ≈ 2^20`
/// (where the reduction cancels most).
fn f64_arguments() -> Vec<f64> {
    let mut xs = vec![660.69, 709.7, -745.0, 14199.99999999999, -92600.0, -99400.0];
    for i in 0..2000 {
        let t = f64::from(i) / 2000.0;
        xs.push(match i % 4 {
            0 => (t - 0.5) * 60.0,
            1 => (t - 0.5) * 1400.0,
            2 => (t - 0.5) * 2e5,
            _ => -(1.0 + 10.0 * t),
        });
    }
    for n in (1..600_000).step_by(997) {
        let x = f64::from(n) * std::f64::consts::FRAC_PI_2;
        xs.extend([x, -x, x * (1.0 + 1e-15), x + 1e-9]);
    }
    xs
}

#[test]
fn f64_exp_and_trig_twins_are_accurate_with_and_without_contraction() {
    for d in devices()
        .into_iter()
        .filter(|d| !d.ftz && d.exp_ulps == 0.0)
    {
        let (mut exp_worst, mut trig_worst) = ((0.0f64, 0.0), (0.0f64, 0.0));
        for x in f64_arguments() {
            if x.abs() < 709.0 {
                let (got, want) = (exp64(d, x), x.exp());
                let e = (got - want).abs() / want;
                if e > exp_worst.0 {
                    exp_worst = (e, x);
                }
            }
            if x.abs() < 1e6 {
                let (s, c) = sincos64(d, x);
                // tan next to a pole: π/2's three parts miss it by 8.5e-32, an error of
                // q·8.5e-32 relative to cos x in the quotient (the GPU test's grid keeps away).
                let tan = if x.cos().abs() > 1e-6 {
                    (s / c, x.tan())
                } else {
                    (0.0, 0.0)
                };
                for (got, want) in [(s, x.sin()), (c, x.cos()), tan] {
                    let e = (got - want).abs() / want.abs().max(1e-3);
                    if e > trig_worst.0 || e.is_nan() {
                        trig_worst = (e, x);
                    }
                }
            }
        }
        assert!(exp_worst.0 < 1e-14, "{d:?}: exp {exp_worst:?}");
        assert!(trig_worst.0 < 1e-14, "{d:?}: sin/cos/tan {trig_worst:?}");
    }
}

/// The H200's errors before the explicit `fma`s (from `f64_software_functions_are_accurate_on
/// _the_gpu`) are those of `fma(−k, C, x)` with `C` the rounded sum of the constant's parts:
/// the driver had reassociated `(x − k·C1) − k·C2` and contracted it.
#[test]
fn the_h200s_f64_errors_were_a_reassociated_reduction() {
    let d = devices()[0];
    let x = 660.69f64;
    let k = (x * INV_LN2).round_ties_even();
    let r = (-k).mul_add(LN2_HI + LN2_LO, x);
    let e = (ldexp(horner(d, &inv_factorials(13), r), k as i32) - x.exp()).abs() / x.exp();
    assert!((e / 2.216e-14 - 1.0).abs() < 0.01, "exp {e:e}");
    for (x, which, h200) in [
        (14199.99999999999f64, 0, 4.591e-10),
        (-92600.0, 1, 2.531e-10),
        (-99400.0, 2, 4.591e-10),
    ] {
        let q = (x * TWO_OVER_PI).round_ties_even();
        let r = (-q).mul_add(PIO2[0] + PIO2[1] + PIO2[2], x);
        let (s, c) = quadrant(d, q, r);
        let (got, want) = [(s, x.sin()), (c, x.cos()), (s / c, x.tan())][which];
        let e = (got - want).abs() / want.abs().max(1e-3);
        assert!((e / h200 - 1.0).abs() < 0.01, "{x}: {e:e}, H200 {h200:e}");
    }
}

/// The f32 GPU test's ordinary arguments (every binade at several mantissas, pseudo-random
/// ones over 1e-30..1e30), the H200's worst cbrt argument, and subnormals.
fn f32_arguments() -> Vec<f32> {
    let mut xs = vec![3.310_192_163_662_043e-36_f64 as f32];
    for e in -126..=127 {
        for m in [
            1.0,
            1.0 + f64::from(f32::EPSILON),
            1.1,
            1.25,
            std::f64::consts::SQRT_2 - 1e-7,
            std::f64::consts::SQRT_2,
            std::f64::consts::SQRT_2 + 1e-7,
            1.5,
            1.75,
            2.0 - f64::from(f32::EPSILON),
        ] {
            xs.push((m * 2f64.powi(e)) as f32);
        }
    }
    let mut state = 0x2545_f491_4f6c_dd1du64;
    for _ in 0..3000 {
        state = state
            .wrapping_mul(6_364_136_223_846_793_005)
            .wrapping_add(1_442_695_040_888_963_407);
        let t = (state >> 11) as f64 / (1u64 << 53) as f64;
        xs.push(10f64.powf((t - 0.5) * 76.0) as f32);
    }
    for k in 1..=64u32 {
        xs.push(f32::from_bits(1.0f32.to_bits() + k));
        xs.push(f32::from_bits(1.0f32.to_bits() - k));
    }
    xs.extend([f32::MAX, f32::MIN_POSITIVE]);
    xs
}

#[test]
fn f32_ln_and_cbrt_twins_are_accurate_with_contraction_and_flushed_subnormals() {
    let subnormals = [
        1e-40f32,
        1e-45,
        2f32.powi(-130),
        f32::from_bits(0x007f_ffff),
    ];
    for d in devices() {
        let (mut ln_worst, mut cbrt_worst) = ((0.0f64, 0.0f32), (0.0f64, 0.0f32));
        for x in f32_arguments().into_iter().chain(subnormals) {
            let a = f64::from(x);
            let want = a.ln();
            let e = (f64::from(ln32(d, x)) - want).abs() / ulp32(want);
            if e > ln_worst.0 {
                ln_worst = (e, x);
            }
            if x >= f32::MIN_POSITIVE {
                let want = a.cbrt();
                let e = (f64::from(cbrt32(d, x)) - want).abs() / ulp32(want);
                if e > cbrt_worst.0 {
                    cbrt_worst = (e, x);
                }
            }
        }
        assert!(ln_worst.0 < 2.0, "{d:?}: ln {ln_worst:?}");
        assert!(cbrt_worst.0 < 2.0, "{d:?}: cbrt {cbrt_worst:?}");
    }
}

/// Without the scaling of small arguments, a device that flushes f32 subnormals drops the
/// Newton step of `softc_cbrt` below ~1e-29 (the H200 was 34 ulps off at 3.3e-36).
#[test]
fn f32_cbrt_of_a_tiny_argument_needed_the_scaling() {
    let d = Dev {
        fused: false,
        ftz: true,
        exp_ulps: 40.0,
    };
    let x = 3.310_192_163_662_043e-36_f64 as f32;
    let r = d.exp32(d.mul32(0.333_333_34, ln32(d, x)));
    let res = d.mad32(d.mul32(r, r), r, -x);
    assert_eq!(res, 0.0, "the residual r³ − m is flushed");
    let want = f64::from(x).cbrt();
    assert!((f64::from(cbrt32(d, x)) - want).abs() < ulp32(want));
}
