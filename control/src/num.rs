//! Numbers in messages: readable whatever their magnitude.
//!
//! `f64`'s `Display` never switches to an exponent, so `1e-300` prints as a 0 followed by 300
//! decimals and `{:.3}` prints it as `0.000`: an error saying "needs 0.000 but the limit is
//! 0.000" explains nothing. These wrappers print ordinary magnitudes as before and tiny or
//! huge ones in scientific notation.

use std::fmt;

/// The value as written in a file: shortest round-trip decimal for magnitudes in
/// [1e-4, 1e9) (and 0), scientific (`1e-300`) outside; NaN and ±inf as themselves.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Num(pub f64);

impl fmt::Display for Num {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let x = self.0;
        if !x.is_finite() || x == 0.0 || (1e-4..1e9).contains(&x.abs()) {
            write!(f, "{x}")
        } else {
            write!(f, "{x:e}")
        }
    }
}

/// Three decimals (`{:.3}`) for magnitudes in [1e-3, 1e6) (and 0), three decimals of a
/// mantissa (`{:.3e}`, e.g. `1.000e-300`) outside; NaN and ±inf as themselves.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Fixed3(pub f64);

impl fmt::Display for Fixed3 {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let x = self.0;
        if !x.is_finite() {
            write!(f, "{x}")
        } else if x == 0.0 || (1e-3..1e6).contains(&x.abs()) {
            write!(f, "{x:.3}")
        } else {
            write!(f, "{x:.3e}")
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn tiny_and_huge_values_stay_readable() {
        assert_eq!(Num(0.085).to_string(), "0.085");
        assert_eq!(Num(250.0).to_string(), "250");
        assert_eq!(Num(1e-300).to_string(), "1e-300");
        assert_eq!(Num(-1e300).to_string(), "-1e300");
        assert_eq!(Num(f64::NAN).to_string(), "NaN");
        assert_eq!(Fixed3(1.0024).to_string(), "1.002");
        assert_eq!(Fixed3(0.0).to_string(), "0.000");
        assert_eq!(Fixed3(1e-300).to_string(), "1.000e-300");
        assert_eq!(Fixed3(2.5e12).to_string(), "2.500e12");
    }
}
