//! Forward-mode dual numbers with three derivative slots (∂/∂Ī1, ∂/∂Ī2, ∂/∂J).
//!
//! The reference simulator differentiates a material's strain energy with these, a different
//! method from the kernel IR's reverse mode, so the two stresses check each other.

use std::ops::{Add, Div, Mul, Neg, Sub};

/// A value and its gradient with respect to the three invariants.
#[derive(Clone, Copy, Debug, PartialEq, Default)]
pub struct Dual {
    pub v: f64,
    pub d: [f64; 3],
}

impl Dual {
    pub const fn constant(v: f64) -> Dual {
        Dual { v, d: [0.0; 3] }
    }

    /// The independent variable of slot `slot`.
    pub fn var(v: f64, slot: usize) -> Dual {
        let mut d = [0.0; 3];
        d[slot] = 1.0;
        Dual { v, d }
    }

    pub fn has_derivative(&self) -> bool {
        self.d.iter().any(|&x| x != 0.0)
    }

    /// Apply a function with value `f` and derivative `df` at `self.v` (chain rule).
    fn chain(self, f: f64, df: f64) -> Dual {
        Dual {
            v: f,
            d: self.d.map(|x| df * x),
        }
    }

    pub fn abs(self) -> Dual {
        let s = if self.v < 0.0 { -1.0 } else { 1.0 };
        self.chain(self.v.abs(), s)
    }
    pub fn sqrt(self) -> Dual {
        let r = self.v.sqrt();
        self.chain(r, 0.5 / r)
    }
    pub fn exp(self) -> Dual {
        let e = self.v.exp();
        self.chain(e, e)
    }
    pub fn ln(self) -> Dual {
        self.chain(self.v.ln(), 1.0 / self.v)
    }
    pub fn sin(self) -> Dual {
        self.chain(self.v.sin(), self.v.cos())
    }
    pub fn cos(self) -> Dual {
        self.chain(self.v.cos(), -self.v.sin())
    }
    pub fn tan(self) -> Dual {
        let c = self.v.cos();
        self.chain(self.v.tan(), 1.0 / (c * c))
    }
    pub fn tanh(self) -> Dual {
        let t = self.v.tanh();
        self.chain(t, 1.0 - t * t)
    }
    pub fn floor(self) -> Dual {
        Dual::constant(self.v.floor())
    }
    pub fn ceil(self) -> Dual {
        Dual::constant(self.v.ceil())
    }
    /// The logistic function 1 / (1 + e^(−x)).
    pub fn sigmoid(self) -> Dual {
        let s = 1.0 / (1.0 + (-self.v).exp());
        self.chain(s, s * (1.0 - s))
    }

    /// `self^e`. A constant exponent uses e·x^(e−1) (valid for a negative base and an integral
    /// exponent); a varying one adds x^e·ln(x)·de.
    pub fn pow(self, e: Dual) -> Dual {
        let v = self.v.powf(e.v);
        let dx = if self.has_derivative() {
            e.v * self.v.powf(e.v - 1.0)
        } else {
            0.0
        };
        let mut d = self.d.map(|x| dx * x);
        if e.has_derivative() {
            let de = v * self.v.ln();
            for (di, ei) in d.iter_mut().zip(e.d) {
                *di += de * ei;
            }
        }
        Dual { v, d }
    }

    /// The smaller of the two (the first on a tie or when `o` is NaN, as `f64::min`).
    pub fn min(self, o: Dual) -> Dual {
        if o.v < self.v || self.v.is_nan() {
            o
        } else {
            self
        }
    }
    pub fn max(self, o: Dual) -> Dual {
        if o.v > self.v || self.v.is_nan() {
            o
        } else {
            self
        }
    }
}

impl Add for Dual {
    type Output = Dual;
    fn add(self, o: Dual) -> Dual {
        Dual {
            v: self.v + o.v,
            d: [0, 1, 2].map(|i| self.d[i] + o.d[i]),
        }
    }
}

impl Sub for Dual {
    type Output = Dual;
    fn sub(self, o: Dual) -> Dual {
        Dual {
            v: self.v - o.v,
            d: [0, 1, 2].map(|i| self.d[i] - o.d[i]),
        }
    }
}

// The product and quotient rules mix operators by nature.
#[allow(clippy::suspicious_arithmetic_impl)]
impl Mul for Dual {
    type Output = Dual;
    fn mul(self, o: Dual) -> Dual {
        Dual {
            v: self.v * o.v,
            d: [0, 1, 2].map(|i| self.d[i] * o.v + self.v * o.d[i]),
        }
    }
}

#[allow(clippy::suspicious_arithmetic_impl)]
impl Div for Dual {
    type Output = Dual;
    fn div(self, o: Dual) -> Dual {
        let q = self.v / o.v;
        Dual {
            v: q,
            d: [0, 1, 2].map(|i| (self.d[i] - q * o.d[i]) / o.v),
        }
    }
}

impl Neg for Dual {
    type Output = Dual;
    fn neg(self) -> Dual {
        Dual {
            v: -self.v,
            d: self.d.map(|x| -x),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn derivatives_match_finite_differences() {
        let f = |a: Dual, b: Dual, c: Dual| {
            (a * b - c).pow(Dual::constant(3.0)) / c.sqrt() + (a / c).ln() * b.tanh()
                - c.pow(Dual::constant(2.0 / 3.0)) * a.sigmoid()
                + a.pow(b)
        };
        let x = [3.1, 0.7, 1.3];
        let d = f(Dual::var(x[0], 0), Dual::var(x[1], 1), Dual::var(x[2], 2));
        for s in 0..3 {
            let h = 1e-6;
            let mut p = x;
            let mut m = x;
            p[s] += h;
            m[s] -= h;
            let c = |v: [f64; 3]| {
                f(
                    Dual::constant(v[0]),
                    Dual::constant(v[1]),
                    Dual::constant(v[2]),
                )
                .v
            };
            let fd = (c(p) - c(m)) / (2.0 * h);
            assert!(
                (fd - d.d[s]).abs() < 1e-6 * (1.0 + fd.abs()),
                "{s}: {fd} {}",
                d.d[s]
            );
        }
    }
}
