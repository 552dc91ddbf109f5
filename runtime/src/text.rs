//! How numbers appear in messages (a leaf module: the engine, the solvers, the outputs and the
//! command line all write messages).

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
