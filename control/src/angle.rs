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

/// A wheel's steering range [min, max] (rad, `wheels[i].steer_range`): cable stops the
/// steering angle must never pass. Angles inside it are not wrapped: a range of ±1.2 turns
/// holds angles from −2.4π to 2.4π, and a wheel at +170° of a ±170° range reaches −170° by
/// turning back through 0, never across ±180°.
///
/// The steering encoders report an angle within one turn; the cycle core keeps each ranged
/// wheel's angle inside its range by continuity (turn counting), starting from the
/// representative of the first reading nearest the range's centre ([`SteerRange::first`]):
/// a wheel must start within half a turn of its range's centre (homing puts it there).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SteerRange {
    /// Lower stop (rad).
    pub min: f64,
    /// Upper stop (rad).
    pub max: f64,
}

impl SteerRange {
    /// The range of a wheel (`None` when it steers endlessly).
    pub fn of(w: &crate::platform::WheelConfig) -> Option<Self> {
        w.steer_limits().map(|(min, max)| Self { min, max })
    }

    /// The range's centre.
    pub fn centre(&self) -> f64 {
        0.5 * (self.min + self.max)
    }

    /// Whether `a` lies inside (stops included).
    pub fn contains(&self, a: f64) -> bool {
        a >= self.min && a <= self.max
    }

    /// The representative of the first reading `raw` (any turn) nearest the range's centre.
    pub fn first(&self, raw: f64) -> f64 {
        let c = self.centre();
        c + diff(raw, c)
    }

    /// The representative of angle `a` (any turn: a + 2πk) inside the range nearest to
    /// `from`; `None` when no turn of `a` lies inside (`a` points into the gap between the
    /// stops).
    pub fn nearest(&self, a: f64, from: f64) -> Option<f64> {
        if !(a.is_finite() && from.is_finite()) {
            return None;
        }
        let k_lo = ((self.min - a) / TAU).ceil();
        let k_hi = ((self.max - a) / TAU).floor();
        if k_lo > k_hi {
            return None;
        }
        let k = ((from - a) / TAU).round().clamp(k_lo, k_hi);
        Some(a + k * TAU)
    }
}

/// The steering error from `from` to the direction `a`: the shortest way round for a wheel
/// that steers endlessly ([`diff`]); within a range, the way to the representative of `a`
/// inside the range nearest `from`, which may be longer than half a turn (unwinding). For
/// a direction in the gap between the stops, the way to the nearer stop.
pub fn steer_error(range: Option<SteerRange>, a: f64, from: f64) -> f64 {
    match range {
        None => diff(a, from),
        Some(r) => match r.nearest(a, from) {
            Some(t) => t - from,
            None => {
                // Pointing into the gap: the nearer stop (by angle, either way round).
                let to_min = diff(r.min, a).abs();
                let to_max = diff(r.max, a).abs();
                (if to_min < to_max { r.min } else { r.max }) - from
            }
        },
    }
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

    #[test]
    fn ranges_pick_the_turn_inside_and_unwind() {
        let stop = 170f64.to_radians();
        let r = SteerRange {
            min: -stop,
            max: stop,
        };
        // From +160° to −160°: not across ±180° (20° the short way), but back through 0.
        let e = steer_error(Some(r), (-160f64).to_radians(), 160f64.to_radians());
        assert!((e + 320f64.to_radians()).abs() < 1e-12, "{e}");
        assert!(
            (steer_error(None, (-160f64).to_radians(), 160f64.to_radians()) - 40f64.to_radians())
                .abs()
                < 1e-12
        );
        // Into the gap: the nearer stop.
        let e = steer_error(Some(r), PI, 0.0);
        assert!((e.abs() - stop).abs() < 1e-12);
        assert!(r.nearest(PI, 0.0).is_none());
        // A range of more than a turn: the representative nearest where the wheel is.
        let wide = SteerRange {
            min: -1.2 * TAU,
            max: 1.2 * TAU,
        };
        assert!((wide.nearest(0.5, TAU + 0.4).unwrap() - (TAU + 0.5)).abs() < 1e-12);
        assert!((wide.nearest(0.5, 2.3 * TAU).unwrap() - (TAU + 0.5)).abs() < 1e-12);
        assert!((wide.first(0.5 + 3.0 * TAU) - 0.5).abs() < 1e-9);
        assert!(wide.contains(1.1 * TAU) && !wide.contains(1.3 * TAU));
    }
}
