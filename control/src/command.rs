//! The command port's checks: what a live motion command must satisfy before it can reach the
//! shaper, and the command timeout.
//!
//! A command is rejected (counted, and it never reaches the wheels) when any value is NaN or
//! infinite, when its twist is beyond the sanity bound of the platform file's `[service]`
//! table (a sender asking for 50 m/s has a bug: it is not shaped, it is refused), when it gives
//! a different number of legs than the platform has, or a leg target outside the leg's range
//! by more than [`LEG_RANGE_SLACK`] (closer targets are clamped into the range: numerical
//! noise from a sender's own computation is not an error). Commands beyond the actuator
//! limits but within the sanity bound are valid: the shaper slows them down.

use crate::platform::Platform;
use crate::ports::{LegTargets, MotionCommand};
use crate::types::{Twist, MAX_WHEELS};

/// Leg targets this far (m) outside a leg's range are clamped into it; farther ones are
/// rejected.
pub const LEG_RANGE_SLACK: f64 = 1e-3;

/// Why a command was rejected.
#[derive(Clone, Copy, Debug, PartialEq, thiserror::Error)]
pub enum Rejection {
    /// A value is NaN or infinite.
    #[error("command field `{field}` is {value}: every value must be a finite number")]
    NonFinite {
        /// The field (`vx`, `vy`, `omega`, `legs[i]`).
        field: &'static str,
        /// The value.
        value: f64,
    },
    /// A twist component is beyond the sanity bound.
    #[error("command field `{field}` = {value} is beyond the sanity bound ±{bound} (`service.{setting}` in the platform file): refused, not shaped; check the sender")]
    Beyond {
        /// The field.
        field: &'static str,
        /// The value.
        value: f64,
        /// The bound.
        bound: f64,
        /// The platform-file setting that holds the bound.
        setting: &'static str,
    },
    /// Wrong number of leg targets.
    #[error("command gives {given} leg targets but the platform has {expected} legs")]
    LegCount {
        /// Targets given.
        given: usize,
        /// Legs on the platform.
        expected: usize,
    },
    /// Leg targets for a platform whose wheels have no legs (a fixed footprint).
    #[error("command gives leg targets but the platform has no legs (every wheel is mounted at a fixed `lambda`): send motion commands without legs")]
    NoLegs,
    /// A leg target outside the leg's range.
    #[error("command leg {} target {value} m is outside the leg's range [{min}, {max}] m", leg + 1)]
    LegRange {
        /// Leg index (0-based).
        leg: usize,
        /// The target.
        value: f64,
        /// Range minimum.
        min: f64,
        /// Range maximum.
        max: f64,
    },
}

fn finite(field: &'static str, v: f64) -> Result<(), Rejection> {
    if v.is_finite() {
        Ok(())
    } else {
        Err(Rejection::NonFinite { field, value: v })
    }
}

const LEG_FIELDS: [&str; MAX_WHEELS] = [
    "legs[0]", "legs[1]", "legs[2]", "legs[3]", "legs[4]", "legs[5]", "legs[6]", "legs[7]",
];

/// Checks a twist against the sanity bounds.
pub fn check_twist(p: &Platform, t: &Twist) -> Result<(), Rejection> {
    finite("vx", t.vx)?;
    finite("vy", t.vy)?;
    finite("omega", t.omega)?;
    let s = &p.service;
    for (field, v, bound, setting) in [
        ("vx", t.vx, s.max_linear_command, "max_linear_command"),
        ("vy", t.vy, s.max_linear_command, "max_linear_command"),
        (
            "omega",
            t.omega,
            s.max_angular_command,
            "max_angular_command",
        ),
    ] {
        if v.abs() > bound {
            return Err(Rejection::Beyond {
                field,
                value: v,
                bound,
                setting,
            });
        }
    }
    Ok(())
}

/// Checks leg targets; returns them clamped into the legs' ranges.
pub fn check_legs(p: &Platform, l: &LegTargets) -> Result<LegTargets, Rejection> {
    if !p.has_legs() {
        return Err(Rejection::NoLegs);
    }
    let n = p.n().min(MAX_WHEELS);
    if l.n != n {
        return Err(Rejection::LegCount {
            given: l.n,
            expected: n,
        });
    }
    let mut out = *l;
    for (i, (field, w)) in LEG_FIELDS.iter().zip(&p.wheels).enumerate().take(n) {
        let v = l.lambda[i];
        finite(field, v)?;
        if v < w.lambda_min - LEG_RANGE_SLACK || v > w.lambda_max + LEG_RANGE_SLACK {
            return Err(Rejection::LegRange {
                leg: i,
                value: v,
                min: w.lambda_min,
                max: w.lambda_max,
            });
        }
        out.lambda[i] = v.clamp(w.lambda_min, w.lambda_max);
    }
    Ok(out)
}

/// Checks a whole motion command; returns it with the leg targets clamped.
pub fn check_motion(p: &Platform, c: &MotionCommand) -> Result<MotionCommand, Rejection> {
    check_twist(p, &c.twist)?;
    let legs = match &c.legs {
        Some(l) => Some(check_legs(p, l)?),
        None => None,
    };
    Ok(MotionCommand {
        twist: c.twist,
        legs,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn rejects_what_it_names_and_keeps_what_the_shaper_can_slow_down() {
        let p = Platform::justin();
        let ok = MotionCommand {
            twist: Twist {
                vx: 3.0,
                vy: 0.0,
                omega: 5.0,
            },
            legs: Some(LegTargets::from_slice(&[0.37, 0.5605, 0.4, 0.5])),
        };
        let c = check_motion(&p, &ok).expect("beyond the limits, within the sanity bound");
        assert_eq!(c.legs.unwrap().lambda[1], 0.56, "clamped into range");
        let mut bad = ok;
        bad.twist.vy = f64::NAN;
        assert!(matches!(
            check_motion(&p, &bad),
            Err(Rejection::NonFinite { field: "vy", .. })
        ));
        bad = ok;
        bad.twist.omega = f64::INFINITY;
        assert!(matches!(
            check_motion(&p, &bad),
            Err(Rejection::NonFinite { field: "omega", .. })
        ));
        bad = ok;
        bad.twist.vx = 1e6;
        let e = check_motion(&p, &bad).unwrap_err();
        assert!(matches!(e, Rejection::Beyond { field: "vx", .. }));
        assert!(e.to_string().contains("service.max_linear_command"), "{e}");
        bad = ok;
        bad.legs = Some(LegTargets::from_slice(&[0.4, 0.4, 0.4]));
        assert!(matches!(
            check_motion(&p, &bad),
            Err(Rejection::LegCount {
                given: 3,
                expected: 4
            })
        ));
        bad.legs = Some(LegTargets::from_slice(&[0.4, 0.9, 0.4, 0.4]));
        let e = check_motion(&p, &bad).unwrap_err();
        assert!(matches!(e, Rejection::LegRange { leg: 1, .. }));
        assert!(e.to_string().contains("leg 2"), "{e}");
        // A fixed footprint refuses leg targets whatever they are; motion without legs is fine.
        let fixed = Platform::three_wheel();
        let mut m = ok;
        m.legs = Some(LegTargets::from_slice(&[0.3, 0.3, 0.3]));
        let e = check_motion(&fixed, &m).unwrap_err();
        assert_eq!(e, Rejection::NoLegs);
        assert!(e.to_string().contains("no legs"), "{e}");
        m.legs = None;
        assert!(check_motion(&fixed, &m).is_ok());
        bad.legs = Some(LegTargets::from_slice(&[0.4, f64::NAN, 0.4, 0.4]));
        assert!(matches!(
            check_motion(&p, &bad),
            Err(Rejection::NonFinite {
                field: "legs[1]",
                ..
            })
        ));
    }
}
