//! Math helpers emitted into WGSL modules, only those a module uses.
//!
//! f32: WGSL's built-ins for `exp`, `sqrt` and the trigonometric functions (Vulkan bounds
//! their errors relative to the result), except:
//! - `ln` is software (`softc_ln`): Vulkan lets `log`/`log2` have an *absolute* error of
//!   2^-21 on `[0.5, 2]`, so a native `log(J)` at `J = 1 + 1e-6` may be off by 50 % (NVIDIA);
//!   the stress of a hyperelastic material near rest is made of such logarithms. It is musl's
//!   (fdlibm's) `logf`: the exponent and mantissa from the bits (subnormals normalized by
//!   integer shifts, not scaled by a product that a device flushing subnormals makes 0), `m`
//!   in `[√½, √2)`, `f = m − 1` exact, `s = f/(2+f)` and
//!   `ln(1+f) = f − f²/2 + s (f²/2 + R(s²))` with a degree-4 minimax `R`: within 1 ulp, and
//!   relative to `f` near 1. The quotient only enters the correction term, so Vulkan's 2.5-ulp
//!   division costs nothing, and no step relies on an exact product or sum, so a driver's
//!   fused multiply-adds cannot break it (`twin` checks it). Special cases are decided on the bits (a driver may
//!   assume floats are never NaN or infinite, and fold comparisons with them).
//! - `pow` is `exp(b · softc_ln|a|)` (native `pow` is `exp2(b · log2 a)` with the same
//!   absolute error), following Rust's `powf` for negative bases with integral exponents and
//!   zero bases (WGSL leaves them undefined); `cbrt` starts from `exp(softc_ln|x| / 3)` and
//!   takes one Newton step, on an argument scaled by `2^±120` out of the ends of the range
//!   (below 1e-18 the residual `r³ − x` would be subnormal, and NVIDIA flushes it: 34 ulps).
//! - `tanh` is exactly ±1 for large arguments: some drivers compute it as a quotient of
//!   exponentials that overflows to NaN.
//!
//! f64: SPIR-V's GLSL.std.450 transcendental functions take only 16/32-bit floats, so these
//! are software implementations: `exp` by reduction to `r = x − k ln 2` (ln 2 in two parts,
//! `|r| ≤ ln2/2`) and a degree-13 Taylor polynomial, then `ldexp`; `ln` from the
//! mantissa moved into `[√½, √2)` (by exact `ldexp` scaling and an f32 `log2` estimate of the
//! exponent, corrected by one step either way, so the estimate's error does not matter:
//! naga's f64 `frexp` needs 64-bit integers) and the `atanh` series of `s = (m−1)/(m+1)`
//! (`|s| ≤ 0.172`, to `s^23`); `sin`/`cos`/`tan` by Cody–Waite reduction modulo π/2 (three
//! parts of π/2, exact products for `|x| < 2^20`) and Taylor polynomials to degree 17/18 on
//! `|r| ≤ π/4`; `tanh` from `expm1` (series below 0.5, so small arguments keep their relative
//! accuracy). Truncation errors of the polynomials are below 1e-17 relative; rounding adds a
//! few ulps. None of them relies on an error-free transformation (no TwoSum or Dekker
//! product), but a reduction `(x − k·C1) − k·C2` relies on its order: without SPIR-V's
//! `NoContraction` (naga emits none) a driver may reassociate as well as contract, and
//! NVIDIA's (580, H200) computes `fma(−k, C1 + C2, x)` with the constant sum rounded, which
//! throws the split away (its exp and sin/cos/tan errors at k = 953 and q ≈ 9040..63300
//! matched that model to 4 digits: 2.2e-14 and 4.6e-10). So the reductions are chains of
//! explicit `fma` calls, whose products `k·Ci` are exact anyway (a driver that evaluates an
//! `fma` as a product and a sum gets the same result). They do rely on f64 `/` (ln, tan,
//! tanh) and `sqrt` being accurate to a few ulps, which Vulkan does not promise for doubles
//! (only single-precision accuracy).

use super::Precision;
use std::collections::BTreeSet;
use std::fmt::Write as _;

#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord)]
pub(super) enum Fun {
    Exp,
    Ln,
    Sin,
    Cos,
    Tan,
    Tanh,
    Pow,
    Cbrt,
}

#[derive(Default)]
pub(super) struct Helpers {
    used: BTreeSet<Fun>,
}

/// ln 2 in two parts (fdlibm's): `LN2_HI` has 32 significant bits, so `k·LN2_HI` is exact
/// for any exponent `k`.
pub(super) const LN2_HI: f64 = 6.931_471_803_691_238e-1;
pub(super) const LN2_LO: f64 = 1.908_214_929_270_587_7e-10;
/// π/2 in three parts of 33 bits (fdlibm's): `q·PIO2[i]` is exact for `|q| < 2^20`.
pub(super) const PIO2: [f64; 3] = [
    1.570_796_326_734_125_6,
    6.077_100_506_303_966e-11,
    2.022_266_248_711_166_5e-21,
];
/// f32 `softc_ln`'s constants: ln 2 in two parts (the first times any exponent is exact),
/// and the minimax coefficients of R(z) = Lg1 z + Lg2 z² + Lg3 z³ + Lg4 z⁴
/// (|error| < 2^-34.24).
pub(super) fn ln_f32_consts() -> (f32, f32, [f32; 4]) {
    (
        f32::from_bits(0x3f31_7180),
        f32::from_bits(0x3717_f7d1),
        [
            0xaaaaaa as f32 * 2f32.powi(-24),
            0xccce13 as f32 * 2f32.powi(-25),
            0x91e9ee as f32 * 2f32.powi(-25),
            0xf89e26 as f32 * 2f32.powi(-26),
        ],
    )
}
/// `softc_cbrt`'s scaling (f32): above `BIG` the cube root of `m·2^-3J` times `2^J`, below
/// `SMALL` that of `m·2^3J` times `2^-J`.
pub(super) const CBRT_F32: (f32, f32, i32) = (1e36, 1e-18, 40);
pub(super) const CBRT_F64: (f64, f64, i32) = (1e300, 1e-280, 330);

/// `1/ln 2` and `2/π`, the reductions' quotient factors.
pub(super) const INV_LN2: f64 = std::f64::consts::LOG2_E;
pub(super) const TWO_OVER_PI: f64 = std::f64::consts::FRAC_2_PI;

/// Taylor coefficients of `sin r / r` and `cos r` in `z = r²` (to r^17 and r^18).
pub(super) fn sin_cos_coeffs() -> (Vec<f64>, Vec<f64>) {
    let f = inv_factorials(18);
    let sign = |i: usize| if i.is_multiple_of(2) { 1.0 } else { -1.0 };
    (
        (0..9).map(|i| sign(i) * f[2 * i + 1]).collect(),
        (0..10).map(|i| sign(i) * f[2 * i]).collect(),
    )
}

/// `1/n!` for `n = 0..=max`.
fn inv_factorials(max: u32) -> Vec<f64> {
    let mut f = 1.0f64;
    let mut out = vec![1.0];
    for n in 1..=max {
        f *= f64::from(n);
        out.push(1.0 / f);
    }
    out
}

fn lit(c: f64) -> String {
    format!("{c:?}lf")
}

/// Horner evaluation of `sum coeffs[i] * z^i` as a WGSL expression in `z`.
fn horner(coeffs: &[f64], z: &str) -> String {
    let mut s = lit(*coeffs.last().unwrap_or(&0.0));
    for c in coeffs.iter().rev().skip(1) {
        s = format!("{} + {z} * ({s})", lit(*c));
    }
    s
}

/// An f32 constant given by its bits, as a WGSL literal that rounds back to it.
fn lit32(bits: u32) -> String {
    format!("{:?}f", f32::from_bits(bits))
}

#[cfg(test)]
#[path = "math_twin.rs"]
mod twin;

/// f32 `softc_ln`: musl's `logf` (see the module's comment).
fn ln_f32(w: &mut String) {
    let (hi, lo, lg) = ln_f32_consts();
    let [ln2_hi, ln2_lo] = [hi, lo].map(|c| lit32(c.to_bits()));
    let [lg1, lg2, lg3, lg4] = lg.map(|c| lit32(c.to_bits()));
    let _ = writeln!(
        w,
        "// ln x: x = m 2^k, m in [sqrt(1/2), sqrt(2)), f = m - 1;\n\
         // ln(1+f) = f - f^2/2 + s (f^2/2 + R(s^2)), s = f/(2+f) (musl's logf, within 1 ulp)."
    );
    let _ = writeln!(w, "fn softc_ln(x: real) -> real {{");
    let _ = writeln!(w, "    var ix = bitcast<u32>(x);");
    let _ = writeln!(w, "    var k = 0;");
    // The sign bit, infinities and NaN, decided on the bits.
    let _ = writeln!(w, "    if (ix >= 0x7f800000u) {{");
    let _ = writeln!(w, "        if (ix == 0x7f800000u) {{ return x; }}");
    let _ = writeln!(
        w,
        "        return select(softc_nan(), -softc_inf(), ix == 0x80000000u);"
    );
    let _ = writeln!(w, "    }}");
    let _ = writeln!(w, "    if (ix < 0x00800000u) {{");
    let _ = writeln!(w, "        if (ix == 0u) {{ return -softc_inf(); }}");
    // musl scales a subnormal by 2^25; a device that flushes subnormals would find 0, so
    // the bits are normalized instead (exponent field 1, k lowered by the shift).
    let _ = writeln!(
        w,
        "        // A subnormal, normalized on its bits (no float operation to flush it)."
    );
    let _ = writeln!(w, "        let sh = countLeadingZeros(ix) - 8u;");
    let _ = writeln!(w, "        ix = ix << sh;");
    let _ = writeln!(w, "        k = -i32(sh);");
    let _ = writeln!(w, "    }}");
    let _ = writeln!(w, "    ix += 0x3f800000u - 0x3f3504f3u;");
    let _ = writeln!(w, "    k += i32(ix >> 23u) - 127;");
    let _ = writeln!(
        w,
        "    let f = bitcast<f32>((ix & 0x007fffffu) + 0x3f3504f3u) - 1.0f;"
    );
    let _ = writeln!(w, "    let s = f / (2.0f + f);");
    let _ = writeln!(w, "    let z = s * s;");
    let _ = writeln!(w, "    let w = z * z;");
    let _ = writeln!(
        w,
        "    let r = z * ({lg1} + w * {lg3}) + w * ({lg2} + w * {lg4});"
    );
    let _ = writeln!(w, "    let hfsq = 0.5f * f * f;");
    let _ = writeln!(w, "    let dk = f32(k);");
    let _ = writeln!(
        w,
        "    return s * (hfsq + r) + dk * {ln2_lo} - hfsq + f + dk * {ln2_hi};"
    );
    let _ = writeln!(w, "}}");
}

impl Helpers {
    /// The name of the function computing `f`, recorded as used.
    pub(super) fn use_fn(&mut self, f: Fun, p: Precision) -> &'static str {
        match (f, p) {
            (Fun::Exp, Precision::F32) => "exp",
            (Fun::Sin, Precision::F32) => "sin",
            (Fun::Cos, Precision::F32) => "cos",
            (Fun::Tan, Precision::F32) => "tan",
            _ => {
                self.used.insert(f);
                match f {
                    Fun::Exp => "softc_exp",
                    Fun::Ln => "softc_ln",
                    Fun::Sin => "softc_sin",
                    Fun::Cos => "softc_cos",
                    Fun::Tan => "softc_tan",
                    Fun::Tanh => "softc_tanh",
                    Fun::Pow => "softc_pow",
                    Fun::Cbrt => "softc_cbrt",
                }
            }
        }
    }

    /// The helpers' source (empty when none is used). Infinity and NaN helpers are always
    /// there: literals of non-finite constants call them.
    pub(super) fn source(&self, p: Precision) -> String {
        let mut s = String::new();
        let w = &mut s;
        let _ = writeln!(
            w,
            "// Non-finite values, computed at run time (WGSL has no literal for them)."
        );
        let _ = writeln!(w, "fn softc_inf() -> real {{");
        let _ = writeln!(w, "    var zero = real(0);");
        let _ = writeln!(w, "    return real(1) / zero;");
        let _ = writeln!(w, "}}");
        let _ = writeln!(w, "fn softc_nan() -> real {{");
        let _ = writeln!(w, "    var zero = real(0);");
        let _ = writeln!(w, "    return zero / zero;");
        let _ = writeln!(w, "}}");
        let u = |f: Fun| self.used.contains(&f);
        let f64_mode = p == Precision::F64;
        let need_exp = f64_mode && (u(Fun::Exp) || u(Fun::Pow) || u(Fun::Tanh) || u(Fun::Cbrt));
        let need_ln = u(Fun::Ln) || u(Fun::Pow) || u(Fun::Cbrt);
        let need_trig = f64_mode && (u(Fun::Sin) || u(Fun::Cos) || u(Fun::Tan));
        if need_exp {
            let c = inv_factorials(13);
            let _ = writeln!(
                w,
                "// e^x: x = k ln2 + r, |r| <= ln2/2; degree-13 Taylor of e^r."
            );
            let _ = writeln!(w, "fn softc_exp(x: real) -> real {{");
            let _ = writeln!(w, "    if (x != x) {{ return x; }}");
            let _ = writeln!(
                w,
                "    if (x > 709.782712893384lf) {{ return softc_inf(); }}"
            );
            let _ = writeln!(w, "    if (x < -745.2lf) {{ return 0.0lf; }}");
            let _ = writeln!(w, "    let k = round(x * {});", lit(INV_LN2));
            let _ = writeln!(
                w,
                "    let r = fma(-k, {}, fma(-k, {}, x));",
                lit(LN2_LO),
                lit(LN2_HI)
            );
            let _ = writeln!(w, "    let p = {};", horner(&c, "r"));
            let _ = writeln!(w, "    return ldexp(p, i32(k));");
            let _ = writeln!(w, "}}");
        }
        if need_ln && !f64_mode {
            ln_f32(w);
        }
        if need_ln && f64_mode {
            let c: Vec<f64> = (0..12).map(|i| 1.0 / f64::from(2 * i + 1)).collect();
            let _ = writeln!(
                w,
                "// ln x: x = m 2^e, m in [sqrt(1/2), sqrt(2)); ln m = 2 atanh((m-1)/(m+1))."
            );
            let _ = writeln!(w, "fn softc_ln(x: real) -> real {{");
            let _ = writeln!(w, "    if (!(x > 0.0lf)) {{");
            let _ = writeln!(
                w,
                "        return select(softc_nan(), -softc_inf(), x == 0.0lf);"
            );
            let _ = writeln!(w, "    }}");
            let _ = writeln!(w, "    if (x == softc_inf()) {{ return x; }}");
            // No frexp: naga's f64 frexp result has an i64 exponent (SHADER_INT64). Scale by
            // exact powers of two into f32's range, take the exponent from an f32 log2, correct.
            // The scaling loops are bounded (10 steps span f64's range): a driver may fold the
            // `x == inf` test above away (Vulkan lets it assume no infinities), and an
            // unbounded loop would then hang the GPU on an infinite argument.
            let _ = writeln!(w, "    var y = x;");
            let _ = writeln!(w, "    var ex = 0.0lf;");
            let _ = writeln!(
                w,
                "    for (var i = 0; i < 11 && y > 1e30lf; i++) {{ y = ldexp(y, -100); ex += 100.0lf; }}"
            );
            let _ = writeln!(
                w,
                "    for (var i = 0; i < 11 && y < 1e-30lf; i++) {{ y = ldexp(y, 100); ex -= 100.0lf; }}"
            );
            let _ = writeln!(w, "    let k = floor(log2(f32(y)));");
            let _ = writeln!(w, "    var m = ldexp(y, -i32(k));");
            let _ = writeln!(w, "    ex += real(k);");
            let _ = writeln!(w, "    if (m >= 2.0lf) {{ m *= 0.5lf; ex += 1.0lf; }}");
            let _ = writeln!(w, "    if (m < 1.0lf) {{ m *= 2.0lf; ex -= 1.0lf; }}");
            let _ = writeln!(
                w,
                "    if (m > 1.4142135623730951lf) {{ m *= 0.5lf; ex += 1.0lf; }}"
            );
            let _ = writeln!(w, "    let s = (m - 1.0lf) / (m + 1.0lf);");
            let _ = writeln!(w, "    let z = s * s;");
            let _ = writeln!(w, "    let lm = 2.0lf * s * ({});", horner(&c, "z"));
            let _ = writeln!(
                w,
                "    return ex * {} + (ex * {} + lm);",
                lit(LN2_HI),
                lit(LN2_LO)
            );
            let _ = writeln!(w, "}}");
        }
        if need_trig {
            // sin r = r (1 - r²/3! + r⁴/5! ...), cos r = 1 - r²/2! + ...
            let (sc, cc) = sin_cos_coeffs();
            let _ = writeln!(
                w,
                "// sin and cos of x: x = q pi/2 + r (Cody-Waite, 3 parts), |r| <= pi/4, Taylor in r."
            );
            let _ = writeln!(w, "fn softc_sincos(x: real) -> vec2<real> {{");
            let _ = writeln!(w, "    let q = round(x * {});", lit(TWO_OVER_PI));
            let _ = writeln!(
                w,
                "    let r = fma(-q, {}, fma(-q, {}, fma(-q, {}, x)));",
                lit(PIO2[2]),
                lit(PIO2[1]),
                lit(PIO2[0])
            );
            let _ = writeln!(w, "    let z = r * r;");
            let _ = writeln!(w, "    let s = r * ({});", horner(&sc, "z"));
            let _ = writeln!(w, "    let c = {};", horner(&cc, "z"));
            let _ = writeln!(w, "    let quadrant = i32(q - 4.0lf * floor(q * 0.25lf));");
            let _ = writeln!(w, "    switch quadrant {{");
            let _ = writeln!(w, "        case 0: {{ return vec2<real>(s, c); }}");
            let _ = writeln!(w, "        case 1: {{ return vec2<real>(c, -s); }}");
            let _ = writeln!(w, "        case 2: {{ return vec2<real>(-s, -c); }}");
            let _ = writeln!(w, "        default: {{ return vec2<real>(-c, s); }}");
            let _ = writeln!(w, "    }}");
            let _ = writeln!(w, "}}");
            if u(Fun::Sin) {
                let _ = writeln!(w, "fn softc_sin(x: real) -> real {{");
                let _ = writeln!(w, "    return softc_sincos(x).x;");
                let _ = writeln!(w, "}}");
            }
            if u(Fun::Cos) {
                let _ = writeln!(w, "fn softc_cos(x: real) -> real {{");
                let _ = writeln!(w, "    return softc_sincos(x).y;");
                let _ = writeln!(w, "}}");
            }
            if u(Fun::Tan) {
                let _ = writeln!(w, "fn softc_tan(x: real) -> real {{");
                let _ = writeln!(w, "    let sc = softc_sincos(x);");
                let _ = writeln!(w, "    return sc.x / sc.y;");
                let _ = writeln!(w, "}}");
            }
        }
        if u(Fun::Tanh) {
            if f64_mode {
                let c: Vec<f64> = inv_factorials(18).into_iter().skip(1).collect();
                let _ = writeln!(
                    w,
                    "// tanh x = sign(x) em1 / (em1 + 2), em1 = e^(2|x|) - 1 (series below 0.5)."
                );
                let _ = writeln!(w, "fn softc_tanh(x: real) -> real {{");
                let _ = writeln!(w, "    let a = abs(x);");
                let _ = writeln!(w, "    if (a > 22.0lf) {{ return sign(x); }}");
                let _ = writeln!(w, "    let y = 2.0lf * a;");
                let _ = writeln!(w, "    var em1 = softc_exp(y) - 1.0lf;");
                let _ = writeln!(w, "    if (y < 0.5lf) {{");
                let _ = writeln!(w, "        em1 = y * ({});", horner(&c, "y"));
                let _ = writeln!(w, "    }}");
                let _ = writeln!(w, "    let t = em1 / (em1 + 2.0lf);");
                let _ = writeln!(w, "    return select(t, -t, x < 0.0lf);");
                let _ = writeln!(w, "}}");
            } else {
                let _ = writeln!(w, "// tanh, exactly +-1 where it rounds to it.");
                let _ = writeln!(w, "fn softc_tanh(x: real) -> real {{");
                let _ = writeln!(w, "    return select(tanh(x), sign(x), abs(x) > 10.0f);");
                let _ = writeln!(w, "}}");
            }
        }
        if u(Fun::Pow) {
            let one = if f64_mode { "1.0lf" } else { "1.0f" };
            let zero = if f64_mode { "0.0lf" } else { "0.0f" };
            let half = if f64_mode { "0.5lf" } else { "0.5f" };
            let _ = writeln!(
                w,
                "// a^b as Rust's powf: negative bases with integral exponents, zero bases."
            );
            let _ = writeln!(w, "fn softc_pow(a: real, b: real) -> real {{");
            let _ = writeln!(w, "    if (b == {zero} || a == {one}) {{ return {one}; }}");
            let _ = writeln!(w, "    let m = abs(a);");
            let _ = writeln!(w, "    if (m == {zero}) {{");
            let _ = writeln!(w, "        return select({zero}, softc_inf(), b < {zero});");
            let _ = writeln!(w, "    }}");
            let exp = if f64_mode { "softc_exp" } else { "exp" };
            let _ = writeln!(w, "    var r = {exp}(b * softc_ln(m));");
            let _ = writeln!(w, "    if (a < {zero}) {{");
            let _ = writeln!(w, "        if (b != floor(b)) {{ return softc_nan(); }}");
            let _ = writeln!(w, "        if (fract(b * {half}) != {zero}) {{ r = -r; }}");
            let _ = writeln!(w, "    }}");
            let _ = writeln!(w, "    return r;");
            let _ = writeln!(w, "}}");
        }
        if u(Fun::Cbrt) {
            // Above `big`, r³ in the Newton step would overflow: the cube root of m·2^-3j,
            // times 2^j (exact scalings). Below `small`, the residual r³ − m (~m·2^-24 in
            // f32) would be subnormal, and a device that flushes subnormals (NVIDIA's f32)
            // drops the Newton step: the cube root of m·2^3j, times 2^-j.
            let (zero, third, big, small, j) = if f64_mode {
                let (big, small, j) = CBRT_F64;
                ("0.0lf", "0.3333333333333333lf", lit(big), lit(small), j)
            } else {
                let (big, small, j) = CBRT_F32;
                (
                    "0.0f",
                    "0.33333334f",
                    format!("{big:e}f"),
                    format!("{small:e}f"),
                    j,
                )
            };
            let exp = if f64_mode { "softc_exp" } else { "exp" };
            let _ = writeln!(
                w,
                "// The real cube root: |x|^(1/3) with x's sign, refined by one Newton step."
            );
            let _ = writeln!(w, "fn softc_cbrt(x: real) -> real {{");
            let _ = writeln!(w, "    var m = abs(x);");
            let _ = writeln!(
                w,
                "    if (m == {zero} || x != x || m == softc_inf()) {{ return x; }}"
            );
            let _ = writeln!(w, "    var scale = 0;");
            let _ = writeln!(
                w,
                "    if (m > {big}) {{ m = ldexp(m, {}); scale = {j}; }}",
                -3 * j
            );
            let _ = writeln!(
                w,
                "    if (m < {small}) {{ m = ldexp(m, {}); scale = -{j}; }}",
                3 * j
            );
            let _ = writeln!(w, "    var r = {exp}({third} * softc_ln(m));");
            let _ = writeln!(w, "    r = r - (r * r * r - m) / (real(3) * r * r);");
            let _ = writeln!(w, "    r = ldexp(r, scale);");
            let _ = writeln!(w, "    return select(r, -r, x < {zero});");
            let _ = writeln!(w, "}}");
        }
        s
    }
}
