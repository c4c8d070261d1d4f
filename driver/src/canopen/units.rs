//! Drive and encoder units: what the devices put on the wire, converted to SI and back.
//!
//! A drive counts motor encoder increments; between the motor and the joint (wheel axle or
//! steering axis) sits a gear of ratio g (motor revolutions per joint revolution). With
//! N increments per motor revolution:
//!
//! - joint angle (rad) = position (increments) · 2π / (N · g)
//! - joint rate (rad/s) = velocity / s_v, with s_v the velocity units per rad/s at the joint:
//!   increments/s: s_v = N · g / 2π; motor rpm: s_v = 60 · g / 2π; 0.001 motor rpm:
//!   s_v = 60 000 · g / 2π.
//!
//! A CiA 406 linear encoder reports its position in measuring steps (0x6005:01, nm per
//! step) and its speed as an INTEGER16 in speed steps (here µm/s per step); the leg
//! extension is λ = offset + position · step.
//!
//! The types are the platform file's `[cia402.drive]`, `[cia402.steer]` and
//! `[cia402.leg_encoder]` tables.

use super::config::Invalid;
use serde::{Deserialize, Serialize};
use std::f64::consts::TAU;

/// Unit of a drive's velocity objects (0x60FF target velocity, 0x606C velocity actual value),
/// as configured in the drive (CiA 402 0x60A9 SI unit velocity, or the vendor's default).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum VelocityUnit {
    /// Motor encoder increments per second.
    IncrementsPerSecond,
    /// Motor revolutions per minute.
    Rpm,
    /// 0.001 motor revolutions per minute.
    MilliRpm,
}

impl VelocityUnit {
    /// The value of CiA 402's SI unit velocity object 0x60A9 for this unit: prefix (a power of
    /// ten, bits 24–31), numerator unit (bits 16–23), denominator (time) unit (bits 8–15),
    /// bits 0–7 reserved (0). Unit codes as CiA 303-2 lists them and drives use them: 0xB5
    /// increments, 0xB4 revolutions; 0x03 second, 0x47 minute; prefix 0xFD = 10⁻³. So
    /// increments/s = 0x00B50300, rpm = 0x00B44700, 0.001 rpm = 0xFDB44700 (Nanotec's and
    /// Synapticon's manuals for 0x60A9; ecmc's Nanotec N6 configuration for inc/s).
    pub fn si_unit_velocity(self) -> u32 {
        match self {
            Self::IncrementsPerSecond => 0x00B5_0300,
            Self::Rpm => 0x00B4_4700,
            Self::MilliRpm => 0xFDB4_4700,
        }
    }
}

/// A value of 0x60A9 in words (`0.001 rev/min`, `inc/s`, or the codes when unknown).
pub fn describe_si_velocity(v: u32) -> String {
    let prefix = (v >> 24) as u8 as i8;
    let unit = match (v >> 16) as u8 {
        0xB5 => "inc".to_string(),
        0xB4 => "rev".to_string(),
        0x01 => "m".to_string(),
        0x10 => "rad".to_string(),
        0x41 => "°".to_string(),
        u => format!("unit 0x{u:02X}"),
    };
    let time = match (v >> 8) as u8 {
        0x03 => "s".to_string(),
        0x47 => "min".to_string(),
        0x48 => "h".to_string(),
        t => format!("time unit 0x{t:02X}"),
    };
    let scale = match prefix {
        0 => String::new(),
        -3 => "0.001 ".to_string(),
        -2 => "0.01 ".to_string(),
        -1 => "0.1 ".to_string(),
        p => format!("10^{p} "),
    };
    format!("{scale}{unit}/{time}")
}

/// One kind of drive (rolling or steering): motor encoder, gear, velocity unit.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct DriveUnits {
    /// Motor encoder increments per motor revolution (after quadrature: 4 × lines).
    pub increments_per_rev: u32,
    /// Gear ratio, motor revolutions per joint (wheel or steering axis) revolution; negative
    /// for a motor mounted mirrored (its positive direction turns the joint the negative way:
    /// the host converts with the sign; the drive's polarity 0x607E is the drive-side
    /// alternative, never both).
    pub gear_ratio: f64,
    /// Unit of 0x60FF and 0x606C.
    pub velocity_unit: VelocityUnit,
}

impl DriveUnits {
    /// Checks the fields; `field` is the table's path for messages (`cia402.drive`).
    pub fn validate(&self, field: &str) -> Result<(), Invalid> {
        if self.increments_per_rev == 0 {
            return Err(Invalid::new(
                format!("{field}.increments_per_rev"),
                0,
                "must be at least 1 (increments per motor revolution, after quadrature)",
            ));
        }
        if !(self.gear_ratio.is_finite()
            && self.gear_ratio.abs() >= 1e-6
            && self.gear_ratio.abs() < 1e6)
        {
            return Err(Invalid::new(
                format!("{field}.gear_ratio"),
                self.gear_ratio,
                "must be a non-zero number (motor revolutions per joint revolution; negative for a motor mounted mirrored)",
            ));
        }
        Ok(())
    }

    /// Position increments per joint revolution, N · g.
    pub fn increments_per_joint_rev(&self) -> f64 {
        f64::from(self.increments_per_rev) * self.gear_ratio
    }

    /// Velocity units per rad/s at the joint.
    pub fn velocity_scale(&self) -> f64 {
        match self.velocity_unit {
            VelocityUnit::IncrementsPerSecond => self.increments_per_joint_rev() / TAU,
            VelocityUnit::Rpm => 60.0 * self.gear_ratio / TAU,
            VelocityUnit::MilliRpm => 60_000.0 * self.gear_ratio / TAU,
        }
    }

    /// Joint rate (rad/s) of one velocity unit: the resolution of the velocity objects
    /// (positive, whatever the sign of the gear).
    pub fn velocity_resolution(&self) -> f64 {
        (1.0 / self.velocity_scale()).abs()
    }

    /// Joint rate (rad/s) of a velocity value.
    pub fn velocity_to_si(&self, raw: i32) -> f64 {
        f64::from(raw) / self.velocity_scale()
    }

    /// The velocity value of a joint rate (rad/s), rounded; `None` when it is not finite or
    /// does not fit INTEGER32.
    pub fn velocity_from_si(&self, rate: f64) -> Option<i32> {
        let v = (rate * self.velocity_scale()).round();
        (v.is_finite() && v >= f64::from(i32::MIN) && v <= f64::from(i32::MAX)).then_some(v as i32)
    }

    /// Joint angle (rad, not wrapped) of a position value.
    pub fn position_to_rad(&self, raw: i32) -> f64 {
        f64::from(raw) * TAU / self.increments_per_joint_rev()
    }

    /// The position value of a joint angle (rad), wrapping around the INTEGER32 range like
    /// a drive's position counter does.
    pub fn rad_to_position(&self, angle: f64) -> i32 {
        let v = (angle / TAU * self.increments_per_joint_rev()).round();
        if !v.is_finite() {
            return 0;
        }
        v.rem_euclid(4_294_967_296.0) as u64 as u32 as i32
    }
}

/// A CiA 406 absolute linear encoder on a leg.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct EncoderUnits {
    /// Position measuring step (0x6005:01), nm per step of 0x6004.
    pub position_step_nm: u32,
    /// Speed step, µm/s per step of 0x6030:01 (INTEGER16).
    pub speed_step_um_s: u32,
    /// Leg extension λ (m) at position value 0.
    pub offset_m: f64,
}

impl EncoderUnits {
    /// Checks the fields; `field` is the table's path for messages.
    pub fn validate(&self, field: &str) -> Result<(), Invalid> {
        if self.position_step_nm == 0 {
            return Err(Invalid::new(
                format!("{field}.position_step_nm"),
                0,
                "must be at least 1 nm per step",
            ));
        }
        if self.speed_step_um_s == 0 {
            return Err(Invalid::new(
                format!("{field}.speed_step_um_s"),
                0,
                "must be at least 1 µm/s per step",
            ));
        }
        if !(self.offset_m.is_finite() && self.offset_m.abs() < 100.0) {
            return Err(Invalid::new(
                format!("{field}.offset_m"),
                self.offset_m,
                "must be a finite length in metres",
            ));
        }
        Ok(())
    }

    /// Leg extension (m) of a position value.
    pub fn position_to_m(&self, raw: u32) -> f64 {
        self.offset_m + f64::from(raw) * f64::from(self.position_step_nm) * 1e-9
    }

    /// Position value of a leg extension (m), rounded; `None` when below the offset or
    /// beyond UNSIGNED32.
    pub fn m_to_position(&self, m: f64) -> Option<u32> {
        let v = ((m - self.offset_m) / (f64::from(self.position_step_nm) * 1e-9)).round();
        (v.is_finite() && v >= 0.0 && v <= f64::from(u32::MAX)).then_some(v as u32)
    }

    /// Leg rate (m/s) of a speed value.
    pub fn speed_to_si(&self, raw: i16) -> f64 {
        f64::from(raw) * f64::from(self.speed_step_um_s) * 1e-6
    }

    /// Speed value of a leg rate (m/s), rounded and saturated to INTEGER16 (a non-finite
    /// rate gives 0).
    pub fn speed_from_si(&self, v: f64) -> i16 {
        let s = (v / (f64::from(self.speed_step_um_s) * 1e-6)).round();
        if s.is_finite() {
            s.clamp(f64::from(i16::MIN), f64::from(i16::MAX)) as i16
        } else {
            0
        }
    }

    /// The largest leg rate (m/s) the speed value can carry.
    pub fn max_speed(&self) -> f64 {
        f64::from(i16::MAX) * f64::from(self.speed_step_um_s) * 1e-6
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    fn wheel() -> DriveUnits {
        DriveUnits {
            increments_per_rev: 16384,
            gear_ratio: 30.0,
            velocity_unit: VelocityUnit::IncrementsPerSecond,
        }
    }

    #[test]
    fn drive_conversions_by_hand() {
        let d = wheel();
        // One wheel revolution per second = 2π rad/s = 16384 · 30 increments/s.
        assert_eq!(d.velocity_from_si(TAU), Some(491_520));
        assert!((d.velocity_to_si(491_520) - TAU).abs() < 1e-12);
        assert!((d.position_to_rad(491_520) - TAU).abs() < 1e-12);
        assert_eq!(d.rad_to_position(-TAU), -491_520);
        // rpm: 1 wheel rev/s = 60 wheel rpm = 1800 motor rpm.
        let rpm = DriveUnits {
            velocity_unit: VelocityUnit::Rpm,
            ..d
        };
        assert_eq!(rpm.velocity_from_si(TAU), Some(1800));
        let mrpm = DriveUnits {
            velocity_unit: VelocityUnit::MilliRpm,
            ..d
        };
        assert_eq!(mrpm.velocity_from_si(TAU), Some(1_800_000));
        // Out of range and non-finite rates are refused, never wrapped.
        assert_eq!(d.velocity_from_si(1e9), None);
        assert_eq!(d.velocity_from_si(f64::NAN), None);
        // The position counter wraps like a drive's.
        let big = d.rad_to_position(5000.0 * TAU);
        assert_eq!(big, (5000i64 * 491_520).rem_euclid(1 << 32) as u32 as i32);
        assert!(d.validate("cia402.drive").is_ok());
        let bad = DriveUnits {
            gear_ratio: 0.0,
            ..d
        };
        let e = bad.validate("cia402.drive").unwrap_err();
        assert_eq!(e.field, "cia402.drive.gear_ratio");
        // A mirrored motor: a negative ratio turns every conversion's sign, both ways.
        let mirrored = DriveUnits {
            gear_ratio: -30.0,
            ..d
        };
        assert!(mirrored.validate("cia402.drive").is_ok());
        assert_eq!(mirrored.velocity_from_si(TAU), Some(-491_520));
        assert!((mirrored.velocity_to_si(-491_520) - TAU).abs() < 1e-12);
        assert!((mirrored.position_to_rad(-491_520) - TAU).abs() < 1e-12);
        assert_eq!(mirrored.rad_to_position(TAU), -491_520);
        assert!(mirrored.velocity_resolution() > 0.0);
    }

    #[test]
    fn si_unit_velocity_codes() {
        assert_eq!(
            VelocityUnit::IncrementsPerSecond.si_unit_velocity(),
            0x00B5_0300
        );
        assert_eq!(VelocityUnit::Rpm.si_unit_velocity(), 0x00B4_4700);
        assert_eq!(VelocityUnit::MilliRpm.si_unit_velocity(), 0xFDB4_4700);
        assert_eq!(describe_si_velocity(0x00B5_0300), "inc/s");
        assert_eq!(describe_si_velocity(0xFDB4_4700), "0.001 rev/min");
        assert_eq!(describe_si_velocity(0x0001_0300), "m/s");
    }

    #[test]
    fn encoder_conversions_by_hand() {
        let e = EncoderUnits {
            position_step_nm: 1000,
            speed_step_um_s: 10,
            offset_m: 0.0,
        };
        assert_eq!(e.m_to_position(0.37), Some(370_000));
        assert!((e.position_to_m(560_000) - 0.56).abs() < 1e-12);
        assert_eq!(e.speed_from_si(0.25), 25_000);
        assert!((e.speed_to_si(-12) + 120e-6).abs() < 1e-15);
        assert_eq!(e.speed_from_si(1.0), i16::MAX);
        assert_eq!(e.m_to_position(-0.1), None);
        assert!((e.max_speed() - 0.32767).abs() < 1e-9);
    }

    proptest! {
        #[test]
        fn velocity_round_trips_within_half_a_unit(rate in -50.0f64..50.0, incr in 1u32..100_000, gear in 0.5f64..200.0) {
            let d = DriveUnits { increments_per_rev: incr, gear_ratio: gear, velocity_unit: VelocityUnit::IncrementsPerSecond };
            if let Some(raw) = d.velocity_from_si(rate) {
                prop_assert!((d.velocity_to_si(raw) - rate).abs() <= 0.5 * d.velocity_resolution() + 1e-12);
            }
        }
    }
}
