//! The one place where angles are wrapped.

use std::f64::consts::{PI, TAU};

/// Wraps an angle to (−π, π].
pub fn wrap(a: f64) -> f64 {
    if !a.is_finite() {
        return a;
    }
    let mut w = a.rem_euclid(TAU); // [0, 2π)
    if w > PI {
        w -= TAU;
    }
    w
}

/// Shortest signed difference `a − b`, wrapped to (−π, π].
pub fn diff(a: f64, b: f64) -> f64 {
    wrap(a - b)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn wraps_into_half_open_interval() {
        assert_eq!(wrap(PI), PI);
        assert!((wrap(-PI) - PI).abs() < 1e-15);
        assert!((wrap(3.0 * PI) - PI).abs() < 1e-12);
        assert!((wrap(0.5 + TAU) - 0.5).abs() < 1e-12);
        assert!((wrap(-0.5 - 2.0 * TAU) + 0.5).abs() < 1e-12);
    }

    #[test]
    fn diff_takes_the_short_way_round() {
        assert!((diff(PI - 0.1, -PI + 0.1) + 0.2).abs() < 1e-12);
        assert!((diff(0.1, -0.1) - 0.2).abs() < 1e-12);
    }
}
