//! What a run writes: ParaView series ([`vtk`]), node-set logs ([`csv`]), the JSON summary
//! ([`json`]), each file replaced atomically ([`atomic`]). Below the command line: the engine
//! writes the VTK and CSV outputs while it runs; `softc run`, its optimization and `softc bench`
//! write the JSON. An output folder is held by one run at a time ([`lock`]); a long run shows
//! its [`progress`].

pub mod atomic;
pub mod csv;
pub mod json;
pub mod lock;
pub mod progress;
pub mod vtk;

/// A number for a message: seven significant digits in exponent form, trailing zeros dropped
/// (`4e-5`, not `3.9999999999999996e-5`; `4.975053e-5`). Files keep full precision.
#[derive(Debug, Clone, Copy)]
pub struct Sig(pub f64);

impl std::fmt::Display for Sig {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        if !self.0.is_finite() {
            return write!(f, "{}", self.0);
        }
        let text = format!("{:.6e}", self.0);
        let (mantissa, exponent) = text.split_once('e').unwrap_or((&text, "0"));
        let mantissa = if mantissa.contains('.') {
            mantissa.trim_end_matches('0').trim_end_matches('.')
        } else {
            mantissa
        };
        write!(f, "{mantissa}e{exponent}")
    }
}

/// `{:e}` too: the same short form.
impl std::fmt::LowerExp for Sig {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        std::fmt::Display::fmt(self, f)
    }
}

/// Mean, min and max displacement of a node set per axis (m): what `softc run` reports per set
/// and `output csv(SET)` logs. `position(n)` is node n's current position.
pub fn set_displacement(
    nodes: &[u32],
    rest: &[[f64; 3]],
    position: impl Fn(usize) -> [f64; 3],
) -> [[f64; 3]; 3] {
    let mut mean = [0.0; 3];
    let mut min = [f64::INFINITY; 3];
    let mut max = [f64::NEG_INFINITY; 3];
    for &n in nodes {
        let (x, x0) = (position(n as usize), rest[n as usize]);
        for d in 0..3 {
            let u = x[d] - x0[d];
            mean[d] += u / nodes.len().max(1) as f64;
            min[d] = min[d].min(u);
            max[d] = max[d].max(u);
        }
    }
    [mean, min, max]
}

#[cfg(test)]
mod tests {
    use super::Sig;

    #[test]
    fn message_numbers_are_short() {
        assert_eq!(Sig(3.9999999999999996e-5).to_string(), "4e-5");
        assert_eq!(Sig(4.9750530147027545e-5).to_string(), "4.975053e-5");
        assert_eq!(Sig(-0.7422814904570816).to_string(), "-7.422815e-1");
        assert_eq!(Sig(1000.0).to_string(), "1e3");
        assert_eq!(Sig(0.0).to_string(), "0e0");
        assert_eq!(Sig(f64::NAN).to_string(), "NaN");
    }
}
