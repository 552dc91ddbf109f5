//! Bounded parameters (SPEC §5.6): the optimizer updates an unconstrained value u; the param is
//! p(u), a smooth bijection onto the open interval, as Stan does for constrained parameters.
//! The transforms never reach a bound, so no iteration can leave the declared range.

/// The declared range of a param entry.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Bounds {
    Free,
    /// `[lo, hi]`: p = lo + (hi − lo)·σ(u).
    Both(f64, f64),
    /// `[lo, ..]`: p = lo + exp(u).
    Lower(f64),
    /// `[.., hi]`: p = hi − exp(u).
    Upper(f64),
}

/// As the script writes bounds, in SI units: `[0, 50000]`, `[0, ..]`, `[.., 1]`.
impl std::fmt::Display for Bounds {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Bounds::Free => f.write_str("(none)"),
            Bounds::Both(lo, hi) => write!(f, "[{lo}, {hi}]"),
            Bounds::Lower(lo) => write!(f, "[{lo}, ..]"),
            Bounds::Upper(hi) => write!(f, "[.., {hi}]"),
        }
    }
}

fn sigmoid(u: f64) -> f64 {
    // Split by sign so neither branch overflows exp.
    if u >= 0.0 {
        1.0 / (1.0 + (-u).exp())
    } else {
        let e = u.exp();
        e / (1.0 + e)
    }
}

impl Bounds {
    pub fn new(lower: Option<f64>, upper: Option<f64>) -> Bounds {
        match (lower, upper) {
            (Some(lo), Some(hi)) => Bounds::Both(lo, hi),
            (Some(lo), None) => Bounds::Lower(lo),
            (None, Some(hi)) => Bounds::Upper(hi),
            (None, None) => Bounds::Free,
        }
    }

    /// The param value of an unconstrained value.
    pub fn to_param(self, u: f64) -> f64 {
        match self {
            Bounds::Free => u,
            Bounds::Both(lo, hi) => {
                // σ(u) rounds to exactly 0 or 1 for |u| > ~37; keep the result strictly inside.
                let p = lo + (hi - lo) * sigmoid(u);
                p.clamp(lo.next_up(), hi.next_down())
            }
            Bounds::Lower(lo) => (lo + u.exp()).max(lo.next_up()),
            Bounds::Upper(hi) => (hi - u.exp()).min(hi.next_down()),
        }
    }

    /// dp/du at u (the chain rule from d loss/dp to d loss/du).
    pub fn dp_du(self, u: f64) -> f64 {
        match self {
            Bounds::Free => 1.0,
            Bounds::Both(lo, hi) => {
                let s = sigmoid(u);
                (hi - lo) * s * (1.0 - s)
            }
            Bounds::Lower(_) => u.exp(),
            Bounds::Upper(_) => -u.exp(),
        }
    }

    /// The unconstrained value of a param value strictly inside the bounds.
    pub fn to_unconstrained(self, p: f64) -> Result<f64, String> {
        let inside = match self {
            Bounds::Free => true,
            Bounds::Both(lo, hi) => p > lo && p < hi,
            Bounds::Lower(lo) => p > lo,
            Bounds::Upper(hi) => p < hi,
        };
        if !inside {
            return Err(format!(
                "the value {p} is not strictly inside the bounds {self}"
            ));
        }
        Ok(match self {
            Bounds::Free => p,
            Bounds::Both(lo, hi) => {
                let s = (p - lo) / (hi - lo);
                (s / (1.0 - s)).ln()
            }
            Bounds::Lower(lo) => (p - lo).ln(),
            Bounds::Upper(hi) => (hi - p).ln(),
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn transforms_round_trip_and_differentiate() {
        let cases = [
            (Bounds::Free, 3.5),
            (Bounds::Both(0.0, 50e3), 1e3),
            (Bounds::Both(-0.01, 0.01), 0.0),
            (Bounds::Lower(1e3), 1e4),
            (Bounds::Upper(200.0), 20.0),
        ];
        for (b, p) in cases {
            let u = b.to_unconstrained(p).unwrap();
            let back = b.to_param(u);
            assert!(
                (back - p).abs() <= 1e-12 * p.abs().max(1.0),
                "{b:?}: {back} vs {p}"
            );
            let h = 1e-6;
            let fd = (b.to_param(u + h) - b.to_param(u - h)) / (2.0 * h);
            let d = b.dp_du(u);
            assert!(
                (fd - d).abs() <= 1e-6 * d.abs().max(1e-12),
                "{b:?}: {fd} vs {d}"
            );
        }
    }

    #[test]
    fn bounds_are_never_reached_or_crossed() {
        let b = Bounds::Both(0.0, 50e3);
        for u in [-1e6, -800.0, -40.0, 0.0, 40.0, 800.0, 1e6] {
            let p = b.to_param(u);
            assert!(p > 0.0 && p < 50e3, "u = {u}: p = {p}");
        }
        assert!(Bounds::Lower(2.0).to_param(-1e6) > 2.0);
        assert!(Bounds::Upper(2.0).to_param(-1e6) < 2.0);
        assert!(Bounds::Both(0.0, 1.0).to_unconstrained(0.0).is_err());
        // Issue 20 item 19: the message showed Rust's debug text, `Both(0.0, 50000.0)`.
        let e = Bounds::Both(0.0, 50e3).to_unconstrained(0.0).unwrap_err();
        assert_eq!(
            e,
            "the value 0 is not strictly inside the bounds [0, 50000]"
        );
        assert_eq!(Bounds::Lower(0.5).to_string(), "[0.5, ..]");
        assert!(Bounds::Lower(0.0).to_unconstrained(-1.0).is_err());
    }
}
