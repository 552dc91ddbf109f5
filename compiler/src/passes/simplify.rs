//! Algebraic simplification and strength reduction of kernel bodies, run on every kernel of a
//! scene (forward, adjoint, force Jacobians) after they are all built and before a backend sees
//! them.
//!
//! Each body is rebuilt through [`Builder`] (constant folding, the identities it applies,
//! sharing of equal subexpressions across the whole body with commutative operands in a
//! canonical order — global value numbering), with these rewrites:
//!
//! 1. **Products of powers.** A product or quotient whose factors include constant powers of the
//!    same value is regrouped by base with the exponents added (as exact rationals in sixths):
//!    `(I1·J^(−2/3))·J^(2/3)` is `I1` (the coupled neo-Hookean's tr(FᵀF) rebuilt through
//!    Ī1 = J^(−2/3)·I1), `(c·J^(2/3))·(J^(−2/3)·d)` is `c·d`, `Ī1·J^(−1/3)` is `I1/J`. Only
//!    products where a fractional power meets another power of its base are touched.
//! 2. **Powers with constant exponents** (`x^e`, `e` a multiple of ⅙ up to ±8): integer `e` by
//!    multiplications (square and multiply), halves through `sqrt`, thirds through `cbrt`
//!    (one root per base, shared: J^(2/3) = r·r, J^(−2/3) = 1/(r·r), J^(−1/3) = 1/r with
//!    r = ∛J), negative `e` as `1/x^|e|`. A base that may be negative keeps `pow`'s NaN for
//!    fractional exponents: the cube root of a negative value is NaN here (`select`).
//! 3. **`ln`/`exp` pairs:** `ln(exp(x)) = x`, `exp(ln(x)) = x` for `x ≥ 0` (NaN below, as
//!    before).
//! 4. **Shared reciprocals:** a divisor used by two or more divisions is inverted once and
//!    the divisions become multiplications (F⁻ᵀ = cof/J: one division instead of nine).
//! 5. **Negations** move into sums and out of products: `x + (−y)` is `x − y`, `x − (−y)` is
//!    `x + y`, `(−x)·y` is `−(x·y)` (and `/` alike), so the sum a product feeds absorbs its sign.
//! 6. **Dead stores and dead code:** of two stores to the same buffer component the last one
//!    wins; instructions no store reads are removed, then arguments nothing reads.
//!
//! Bit-exactness (f64; f32 alike): sharing subexpressions, folding constants, dead-code and
//! dead-store removal, the negation rewrites (IEEE defines `x − y` as `x + (−y)`, and
//! a product's or quotient's sign is its operands', zeros included), integer powers 2 and 3 (already products before this pass), `x^1` and
//! the NaN guards are bit-exact. Not bit-exact, each within a few ulps of the original value:
//! regrouping products of powers and of constants (reassociation), powers through
//! `sqrt`/`cbrt` and products instead of `pow` (`pow` is within an ulp of the exact power,
//! `cbrt(x)²` within two), higher integer powers by multiplication, `1/x` for `x^−1`, shared
//! reciprocals (two roundings instead of one), and `ln`/`exp` pairs (exact in real
//! arithmetic, so the new value is the more accurate one). A power cancelled to 1 also drops
//! the NaN a non-positive base gave (`J^a·J^−a` at J = 0 was NaN, is 1 now); states where
//! that matters are already reported by the runtime's inversion check on J.
//!
//! End to end (f64, against the unsimplified kernels): the benchmark-10k run's tip mean z after
//! 4000 steps moves by 5e-13 relative and its loss by 2e-15; the static verification scenes'
//! tip z by 1e-14. Ill-conditioned outputs move more: components ten times smaller than the
//! displacement by 1–3e-12, the largest node speed by 5e-9 — the stress at these small strains
//! is a difference of O(μ) terms, so any change of rounding shows there, and the unsimplified
//! kernels differ from the independent reference oracle by the same order (7e-10 on that speed).

use crate::ir::{BinOp, Builder, CmpOp, Func, Inst, Kernel, Module, UnOp, V};
use std::collections::HashMap;

/// Simplify every kernel of `m`.
pub fn simplify_module(m: &mut Module) {
    for k in &mut m.kernels {
        simplify_kernel(k);
    }
}

/// Simplify one kernel: its body, its stores (the last store to a component wins) and its
/// arguments (those nothing reads any more are dropped).
pub fn simplify_kernel(k: &mut Kernel) {
    // Dead stores: a later store to the same buffer component overwrites an earlier one.
    let mut last: HashMap<(u32, u32), usize> = HashMap::new();
    for (i, s) in k.stores.iter().enumerate() {
        last.insert((s.buffer.0, s.component), i);
    }
    let mut i = 0;
    k.stores.retain(|s| {
        let keep = last[&(s.buffer.0, s.component)] == i;
        i += 1;
        keep
    });
    // Stores name outputs by index: keep only the outputs stored, in store order.
    let outputs: Vec<V> = k.stores.iter().map(|s| k.body.outputs[s.output]).collect();
    for (i, s) in k.stores.iter_mut().enumerate() {
        s.output = i;
    }
    k.body.outputs = outputs;
    k.body = simplify(&k.body);
    k.drop_unused_args();
}

/// The simplified equivalent of a body (same arguments, same outputs in the same order).
pub fn simplify(func: &Func) -> Func {
    let first = Rewriter::run(func, &HashMap::new());
    // Divisors used by two or more divisions get one shared reciprocal.
    let mut uses: HashMap<V, usize> = HashMap::new();
    for inst in &first.insts {
        if let Inst::Bin(BinOp::Div, a, d) = *inst
            && first.constant(a) != Some(1.0)
            && first.constant(d).is_none()
        {
            *uses.entry(d).or_default() += 1;
        }
    }
    uses.retain(|_, n| *n >= 2);
    if uses.is_empty() {
        return first;
    }
    Rewriter::run(&first, &uses)
}

/// Powers are tracked as integer multiples of ⅙ (every rational exponent with denominator
/// 1, 2, 3 or 6).
const SIXTHS: i64 = 6;
/// The largest |exponent| strength-reduced (in sixths).
const MAX_SIXTHS: i64 = 8 * SIXTHS;
/// A product is expanded into at most this many factors.
const MAX_FACTORS: usize = 24;

/// One factor of a product: `base^(sixths/6)`.
#[derive(Clone, Copy, Debug)]
struct Factor {
    base: V,
    sixths: i64,
}

struct Rewriter {
    b: Builder,
}

impl Rewriter {
    /// Rebuild `func`; divisions by a value in `shared_recip` (of `func`) become
    /// multiplications by its reciprocal.
    fn run(func: &Func, shared_recip: &HashMap<V, usize>) -> Func {
        let mut r = Rewriter {
            b: Builder::new(func.n_args),
        };
        let mut uses = vec![0u32; func.insts.len()];
        for inst in &func.insts {
            for u in crate::ir::operands(inst) {
                uses[u.0 as usize] += 1;
            }
        }
        for o in &func.outputs {
            uses[o.0 as usize] += 1;
        }
        let mut map: Vec<V> = Vec::with_capacity(func.insts.len());
        for (i, inst) in func.insts.iter().enumerate() {
            let m = |v: V| map[v.0 as usize];
            let v = match *inst {
                Inst::Const(c) => r.b.constant(c),
                Inst::Arg(a) => r.b.arg(a),
                Inst::Un(op, a) => r.un(op, m(a)),
                Inst::Bin(BinOp::Div, a, d) if shared_recip.contains_key(&d) => {
                    let one = r.b.constant(1.0);
                    let inv = r.b.div(one, m(d));
                    r.mul(m(a), inv)
                }
                Inst::Bin(op, a, c) => {
                    let single = [uses[a.0 as usize] == 1, uses[c.0 as usize] == 1];
                    r.bin_moving_negations(op, m(a), m(c), single)
                }
                Inst::Cmp(op, a, c) => r.b.cmp(op, m(a), m(c)),
                Inst::Select(c, a, e) => r.b.select(m(c), m(a), m(e)),
            };
            debug_assert_eq!(map.len(), i);
            map.push(v);
        }
        let mut out = r.b.finish();
        out.outputs = func.outputs.iter().map(|o| map[o.0 as usize]).collect();
        out.prune();
        out
    }

    fn un(&mut self, op: UnOp, a: V) -> V {
        match (op, self.b.func.inst(a)) {
            (UnOp::Ln, Inst::Un(UnOp::Exp, x)) => x,
            (UnOp::Exp, Inst::Un(UnOp::Ln, x)) => {
                let zero = self.b.constant(0.0);
                let neg = self.b.cmp(CmpOp::Lt, x, zero);
                let nan = self.b.constant(f64::NAN);
                self.b.select(neg, nan, x)
            }
            _ => self.b.un(op, a),
        }
    }

    /// `Some(x)` where `v` is `neg x`.
    fn negated(&self, v: V) -> Option<V> {
        match self.b.func.inst(v) {
            Inst::Un(UnOp::Neg, x) => Some(x),
            _ => None,
        }
    }

    /// `op(a, c)` with negations moved: `x + (−y)` is `x − y` and `x − (−y)` is `x + y`
    /// always; a negated factor or dividend comes out of a product or quotient (`(−x)·y` is
    /// `−(x·y)`) when the negation has no other use (`single`: the operands' use counts are
    /// one), so that the sum the product feeds absorbs the sign — reverse-mode adjoints are
    /// full of `(−y)·x` terms added up — and no negation is duplicated.
    fn bin_moving_negations(&mut self, op: BinOp, a: V, c: V, single: [bool; 2]) -> V {
        let (na, nc) = (self.negated(a), self.negated(c));
        match (op, na, nc) {
            (BinOp::Add, _, Some(y)) => self.b.sub(a, y),
            (BinOp::Add, Some(x), None) => self.b.sub(c, x),
            (BinOp::Sub, _, Some(y)) => self.b.add(a, y),
            (BinOp::Mul | BinOp::Div, _, _)
                if (na.is_some() && single[0]) || (nc.is_some() && single[1]) =>
            {
                let pa = na.filter(|_| single[0]);
                let pc = nc.filter(|_| single[1]);
                let r = self.bin(op, pa.unwrap_or(a), pc.unwrap_or(c));
                if pa.is_some() == pc.is_some() {
                    r
                } else {
                    self.b.neg(r)
                }
            }
            _ => self.bin(op, a, c),
        }
    }

    fn bin(&mut self, op: BinOp, a: V, c: V) -> V {
        match op {
            BinOp::Mul => self.mul(a, c),
            BinOp::Div => {
                if let Some(v) = self.regroup(a, c, true) {
                    return v;
                }
                self.b.div(a, c)
            }
            BinOp::Pow => match self.b.func.constant(c).and_then(sixths) {
                Some(s) if s.abs() <= MAX_SIXTHS => self.power(a, s),
                _ => self.b.bin(op, a, c),
            },
            _ => self.b.bin(op, a, c),
        }
    }

    fn mul(&mut self, a: V, c: V) -> V {
        if let Some(v) = self.regroup(a, c, false) {
            return v;
        }
        self.b.mul(a, c)
    }

    /// `a·c` (or `a/c`) regrouped by base when a fractional power meets another power of its
    /// base among the factors; `None` when nothing cancels or combines.
    fn regroup(&mut self, a: V, c: V, divide: bool) -> Option<V> {
        let mut coef = 1.0;
        let mut fs = Vec::new();
        self.factors(a, 1, &mut coef, &mut fs, 0)?;
        self.factors(c, if divide { -1 } else { 1 }, &mut coef, &mut fs, 0)?;
        // Combine by base, in order of first appearance.
        // Per base: the summed exponent, and whether a fractional power contributed.
        let mut combined: Vec<Factor> = Vec::new();
        let mut fractional: Vec<bool> = Vec::new();
        for f in &fs {
            match combined.iter().position(|g| g.base == f.base) {
                Some(i) => combined[i].sixths += f.sixths,
                None => {
                    combined.push(*f);
                    fractional.push(false);
                }
            }
            let i = combined
                .iter()
                .position(|g| g.base == f.base)
                .expect("pushed");
            fractional[i] |= f.sixths % SIXTHS != 0;
        }
        // Worth it only where a root disappears: a base with a fractional power ends whole.
        let removes_root = combined
            .iter()
            .zip(&fractional)
            .any(|(f, &frac)| frac && f.sixths % SIXTHS == 0);
        if !removes_root
            || combined
                .iter()
                .any(|f| f.sixths.abs() > MAX_SIXTHS && f.sixths % SIXTHS != 0)
        {
            return None;
        }
        let mut num: Option<V> = None;
        let mut den: Option<V> = None;
        for f in combined.iter().filter(|f| f.sixths != 0) {
            let p = self.power(f.base, f.sixths.abs());
            let slot = if f.sixths > 0 { &mut num } else { &mut den };
            *slot = Some(match *slot {
                Some(acc) => self.b.mul(acc, p),
                None => p,
            });
        }
        let mut v = match num {
            Some(n) if coef == 1.0 => n,
            Some(n) => {
                let k = self.b.constant(coef);
                self.b.mul(k, n)
            }
            None => self.b.constant(coef),
        };
        if let Some(d) = den {
            v = self.b.div(v, d);
        }
        Some(v)
    }

    /// Expand `v` (a value of the function being built) into constant and power factors,
    /// each exponent times `sign`. `None` when it grows too large.
    fn factors(
        &self,
        v: V,
        sign: i64,
        coef: &mut f64,
        out: &mut Vec<Factor>,
        depth: u32,
    ) -> Option<()> {
        if out.len() > MAX_FACTORS {
            return None;
        }
        let leaf = |out: &mut Vec<Factor>| {
            out.push(Factor {
                base: v,
                sixths: sign * SIXTHS,
            })
        };
        if depth > 8 {
            leaf(out);
            return Some(());
        }
        match self.b.func.inst(v) {
            // A zero factor is left alone, as the Builder leaves `x * 0` (NaN for infinite x).
            Inst::Const(c) if c == 0.0 || !c.is_finite() => return None,
            Inst::Const(c) if sign > 0 => *coef *= c,
            Inst::Const(c) => *coef /= c,
            Inst::Un(UnOp::Neg, x) => {
                *coef = -*coef;
                self.factors(x, sign, coef, out, depth + 1)?;
            }
            Inst::Bin(BinOp::Mul, x, y) => {
                self.factors(x, sign, coef, out, depth + 1)?;
                self.factors(y, sign, coef, out, depth + 1)?;
            }
            Inst::Bin(BinOp::Div, x, y) => {
                self.factors(x, sign, coef, out, depth + 1)?;
                self.factors(y, -sign, coef, out, depth + 1)?;
            }
            Inst::Bin(BinOp::Pow, x, e) => match self.b.func.constant(e).and_then(sixths) {
                Some(s) => out.push(Factor {
                    base: x,
                    sixths: sign * s,
                }),
                None => leaf(out),
            },
            _ => {
                // A power already reduced to a root: r = ∛x (or √x) is x^(1/3) (x^(1/2)).
                match self.root_of(v) {
                    Some((x, s)) => out.push(Factor {
                        base: x,
                        sixths: sign * s,
                    }),
                    None => leaf(out),
                }
            }
        }
        Some(())
    }

    /// `v` as a root of another value: `sqrt(x)` is `x^(3/6)`, the guarded cube root of `x`
    /// is `x^(2/6)`.
    fn root_of(&self, v: V) -> Option<(V, i64)> {
        match self.b.func.inst(v) {
            Inst::Un(UnOp::Sqrt, x) => Some((x, 3)),
            Inst::Select(_, nan, r) if self.b.func.constant(nan).is_some_and(f64::is_nan) => {
                match self.b.func.inst(r) {
                    Inst::Un(UnOp::Cbrt, x) => Some((x, 2)),
                    _ => None,
                }
            }
            _ => None,
        }
    }

    /// `x^(s/6)` by multiplications, `sqrt` and `cbrt`, or `pow` where neither serves.
    fn power(&mut self, x: V, s: i64) -> V {
        if s == 0 {
            return self.b.constant(1.0);
        }
        if s < 0 {
            let p = self.power(x, -s);
            let one = self.b.constant(1.0);
            return self.b.div(one, p);
        }
        if s == SIXTHS {
            return x;
        }
        let (whole, rest) = (s / SIXTHS, s % SIXTHS);
        let root = match rest {
            0 => None,
            3 => Some(self.b.un(UnOp::Sqrt, x)),
            2 | 4 => {
                let r = self.cube_root(x);
                Some(if rest == 4 { self.b.mul(r, r) } else { r })
            }
            _ => {
                let e = self.b.constant(s as f64 / SIXTHS as f64);
                return self.b.bin(BinOp::Pow, x, e);
            }
        };
        let int = (whole > 0).then(|| self.int_power(x, whole));
        match (int, root) {
            (Some(i), Some(r)) => self.b.mul(i, r),
            (Some(i), None) => i,
            (None, Some(r)) => r,
            (None, None) => unreachable!("s > 0"),
        }
    }

    /// `x^n`, n ≥ 1, by squaring and multiplying.
    fn int_power(&mut self, x: V, n: i64) -> V {
        if n == 1 {
            return x;
        }
        let half = self.int_power(x, n / 2);
        let sq = self.b.mul(half, half);
        if n % 2 == 1 { self.b.mul(sq, x) } else { sq }
    }

    /// ∛x with `pow`'s NaN for a negative base.
    fn cube_root(&mut self, x: V) -> V {
        let r = self.b.un(UnOp::Cbrt, x);
        if self.b.func.constant(r).is_some() {
            return r;
        }
        let zero = self.b.constant(0.0);
        let neg = self.b.cmp(CmpOp::Lt, x, zero);
        let nan = self.b.constant(f64::NAN);
        self.b.select(neg, nan, r)
    }
}

/// `e` as a whole number of sixths, when it is one to within a few ulps: `fl(2/3)` is 4 sixths,
/// and so is the exponent AD derives from it, `fl(2/3) − 1 = −0.33333333333333337` (not
/// `fl(−1/3)`), which is −2 sixths.
fn sixths(e: f64) -> Option<i64> {
    if !e.is_finite() || e.abs() > 1e6 {
        return None;
    }
    let s = (e * SIXTHS as f64).round();
    ((s / SIXTHS as f64 - e).abs() <= 4.0 * f64::EPSILON * e.abs().max(1.0)).then_some(s as i64)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::ir::interp::eval;

    fn count(f: &Func, pred: impl Fn(&Inst) -> bool) -> usize {
        f.insts.iter().filter(|i| pred(i)).count()
    }

    fn close(a: f64, b: f64, tol: f64) -> bool {
        (a - b).abs() <= tol * a.abs().max(b.abs()) || (a.is_nan() && b.is_nan())
    }

    /// The coupled neo-Hookean's J^(2/3)·(J^(−2/3)·I1) is I1, and its three powers one cube
    /// root.
    #[test]
    fn powers_of_one_base_cancel_and_share_a_cube_root() {
        let mut b = Builder::new(2);
        let (j, i1) = (b.arg(0), b.arg(1));
        let m23 = b.powf(j, -2.0 / 3.0);
        let i1b = b.mul(i1, m23);
        let p23 = b.powf(j, 2.0 / 3.0);
        let back = b.mul(i1b, p23);
        let m13 = b.powf(j, -1.0 / 3.0);
        let t = b.mul(i1b, m13);
        let u = b.mul(p23, m23);
        b.func.outputs = vec![back, t, i1b, u, m13, p23];
        let f = b.finish();
        let s = simplify(&f);
        assert_eq!(s.outputs[0], V(1), "I1 itself: {s:?}");
        assert_eq!(count(&s, |i| matches!(i, Inst::Bin(BinOp::Pow, ..))), 0);
        assert_eq!(count(&s, |i| matches!(i, Inst::Un(UnOp::Cbrt, _))), 1);
        for (j, i1) in [(1.3, 3.1), (0.7, 2.9), (1.0, 3.0), (5e-3, 1e-2)] {
            let want = eval(&f, &[j, i1]);
            let got = eval(&s, &[j, i1]);
            // A few ulps: the unsimplified (I1·J^(−2/3))·J^(2/3) is itself 2 ulps off I1.
            for (w, g) in want.iter().zip(&got) {
                assert!(close(*w, *g, 2e-15), "{w} vs {g}");
            }
        }
        // pow's NaN for a negative base stays.
        let got = eval(&s, &[-1.0, 3.0]);
        assert!(got[4].is_nan() && got[5].is_nan(), "{got:?}");
    }

    #[test]
    fn integer_and_half_powers_are_products_and_roots() {
        let mut b = Builder::new(1);
        let x = b.arg(0);
        let outs: Vec<V> = [5.0, -2.0, 1.5, -0.5, 7.0 / 3.0, 1.0 / 6.0, 0.3]
            .iter()
            .map(|&e| b.powf(x, e))
            .collect();
        b.func.outputs = outs;
        let f = b.finish();
        let s = simplify(&f);
        // x^(1/6) and x^0.3 stay pow.
        assert_eq!(count(&s, |i| matches!(i, Inst::Bin(BinOp::Pow, ..))), 2);
        for x in [0.3, 1.0, 2.7, 1e3] {
            for (w, g) in eval(&f, &[x]).iter().zip(&eval(&s, &[x])) {
                assert!(close(*w, *g, 1e-15), "x = {x}: {w} vs {g}");
            }
        }
    }

    #[test]
    fn negations_fold_into_sums_bit_for_bit() {
        // c + (−a)·b, c − (−b) and b/(−d) + c, the shapes reverse-mode adjoints produce; −c
        // has two uses and stays (moving it out of both products would add a negation).
        let mut b = Builder::new(4);
        let (a, bb, c, d) = (b.arg(0), b.arg(1), b.arg(2), b.arg(3));
        let na = b.neg(a);
        let p = b.mul(na, bb);
        let s1 = b.add(c, p);
        let nb = b.neg(bb);
        let s2 = b.sub(c, nb);
        let nd = b.neg(d);
        let q = b.div(bb, nd);
        let s3 = b.add(q, c);
        let shared = b.neg(c);
        let m1 = b.mul(shared, a);
        let m2 = b.mul(shared, bb);
        b.func.outputs = vec![s1, s2, s3, m1, m2];
        let f = b.finish();
        let s = simplify(&f);
        assert_eq!(
            count(&s, |i| matches!(i, Inst::Un(UnOp::Neg, _))),
            1,
            "{s:?}"
        );
        let cases = [
            [0.3, 2.0, 7.0, -1.25],
            [0.0, -0.0, 0.0, 1.0],
            [-0.0, 1.0, -0.0, -0.0],
            [1.5, 3.0, 4.5, 2.0],
            [f64::INFINITY, 2.0, 1.0, 0.0],
        ];
        for xs in cases {
            for (w, g) in eval(&f, &xs).iter().zip(&eval(&s, &xs)) {
                assert!(
                    w.to_bits() == g.to_bits() || (w.is_nan() && g.is_nan()),
                    "{xs:?}: {w} vs {g}"
                );
            }
        }
    }

    #[test]
    fn ln_exp_pairs_and_shared_reciprocals() {
        let mut b = Builder::new(3);
        let (x, y, d) = (b.arg(0), b.arg(1), b.arg(2));
        let e = b.un(UnOp::Exp, x);
        let l = b.un(UnOp::Ln, e);
        let q1 = b.div(x, d);
        let q2 = b.div(y, d);
        b.func.outputs = vec![l, q1, q2];
        let f = b.finish();
        let s = simplify(&f);
        assert_eq!(s.outputs[0], V(0));
        assert_eq!(count(&s, |i| matches!(i, Inst::Bin(BinOp::Div, ..))), 1);
        for (w, g) in eval(&f, &[0.3, 2.0, 7.0])
            .iter()
            .zip(&eval(&s, &[0.3, 2.0, 7.0]))
        {
            assert!(close(*w, *g, 4e-16), "{w} vs {g}");
        }
    }

    #[test]
    fn the_last_store_to_a_component_wins() {
        use crate::ir::{ArgSource, BufferId, Domain, Store};
        let mut b = Builder::new(1);
        let x = b.arg(0);
        let y = b.mul(x, x);
        b.func.outputs = vec![y, x];
        let mut k = Kernel {
            name: "k".into(),
            domain: Domain::Node,
            origin: "test".into(),
            args: vec![ArgSource::Own {
                buffer: BufferId(0),
                component: 0,
            }],
            body: b.finish(),
            stores: vec![
                Store {
                    buffer: BufferId(1),
                    component: 0,
                    output: 0,
                },
                Store {
                    buffer: BufferId(1),
                    component: 0,
                    output: 1,
                },
            ],
        };
        simplify_kernel(&mut k);
        assert_eq!(k.stores.len(), 1);
        assert_eq!(k.body.insts.len(), 1, "{:?}", k.body);
    }
}
