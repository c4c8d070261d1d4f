//! Platform description: geometry, limits and gains, loaded from a TOML file and validated.
//!
//! The default is a Justin-like platform (seed 000, Sect. II; seed 001, Sect. V):
//! four centred steerable wheels on legs along the diagonals of the footprint, whose
//! extension λ ranges over [0.37, 0.56] m; the legs point along the diagonals of the
//! 685 mm × 515 mm minimum footprint (α = ±atan2(515, 685) ≈ ±36.9° front, 180° ∓ 36.9°
//! rear); wheel radius 0.085 m, so that the paper's 2.1 rad/s platform rotation at full
//! leg extension needs the stated 13.9 rad/s wheel spin (2.1 · 0.56 / 0.085 ≈ 13.8).
//! Torque limits 30 Nm (rolling) and 28 Nm (steering) and the ~150 kg mass are from
//! seed 000, Sect. II/III-B.
//!
//! Every field is validated on load and errors name the field (`wheels[2].alpha`,
//! `limits.wheel_speed` …) and say what is wrong with its value.

use crate::types::MAX_WHEELS;
use serde::{Deserialize, Serialize};
use std::path::Path;

/// Errors from loading or validating a platform description.
#[derive(Debug, thiserror::Error)]
pub enum ConfigError {
    /// The file could not be read.
    #[error("cannot read platform file {path}: {source}")]
    Io {
        /// File path.
        path: String,
        /// Underlying IO error.
        source: std::io::Error,
    },
    /// The TOML is malformed or has unknown/missing fields.
    #[error("platform file is not valid TOML for a platform description: {0}")]
    Parse(String),
    /// A field has a value that is not acceptable.
    #[error("platform field `{field}` = {value}: {reason}")]
    Invalid {
        /// Dotted path of the field, e.g. `wheels[1].lambda_min`.
        field: String,
        /// The offending value, printed.
        value: String,
        /// What is wrong and what is expected.
        reason: String,
    },
}

fn invalid(
    field: impl Into<String>,
    value: impl std::fmt::Display,
    reason: impl Into<String>,
) -> ConfigError {
    ConfigError::Invalid {
        field: field.into(),
        value: value.to_string(),
        reason: reason.into(),
    }
}

/// One wheel module: its leg and its CAN node.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct WheelConfig {
    /// CAN node number of the module (1..=15).
    pub node: u8,
    /// Fixed leg direction α_i in the body frame (rad).
    pub alpha: f64,
    /// Minimum leg extension λ_min (m).
    pub lambda_min: f64,
    /// Maximum leg extension λ_max (m).
    pub lambda_max: f64,
    /// Nominal (equilibrium) leg extension λ_i,0 used by the leg repulsion (m).
    pub lambda_nominal: f64,
}

/// Actuator limits, per wheel module.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Limits {
    /// Maximum wheel spin rate |ω| (rad/s).
    pub wheel_speed: f64,
    /// Maximum wheel spin acceleration |ω̇| (rad/s²).
    pub wheel_accel: f64,
    /// Maximum steering rate |φ̇| (rad/s).
    pub steer_rate: f64,
    /// Maximum steering acceleration |φ̈| (rad/s²).
    pub steer_accel: f64,
    /// Maximum leg extension rate |λ̇| (m/s).
    pub leg_speed: f64,
}

/// Controller gains.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Gains {
    /// DFL proportional gain K_P (scalar times identity; seed 000 uses 2).
    pub dfl_kp: f64,
    /// DFL derivative gain K_D (scalar times identity; seed 000 uses 3).
    pub dfl_kd: f64,
    /// Steering-angle feedback gain for the coordinated wheels (1/s).
    pub steer_kp: f64,
    /// Kinematic controller: position error gain (1/s).
    pub kin_k_pos: f64,
    /// Kinematic controller: heading error gain (1/s).
    pub kin_k_heading: f64,
    /// Kinematic controller: leg error gain (1/s).
    pub kin_k_leg: f64,
}

/// The complete platform description.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Platform {
    /// Human-readable name.
    pub name: String,
    /// Wheel radius r (m).
    pub wheel_radius: f64,
    /// Platform mass (kg), used by the simulator and for torque-derived limits.
    pub mass: f64,
    /// Rolling motor torque limit (N·m).
    pub drive_torque: f64,
    /// Steering motor torque limit (N·m).
    pub steer_torque: f64,
    /// Control cycle rate (Hz); 250 Hz on Justin.
    pub cycle_hz: f64,
    /// The wheel modules, in controller order (wheel 1 first).
    pub wheels: Vec<WheelConfig>,
    /// Actuator limits.
    pub limits: Limits,
    /// Controller gains.
    pub gains: Gains,
}

impl Default for Platform {
    fn default() -> Self {
        Self::justin()
    }
}

impl Platform {
    /// The Justin-like default platform (see the module docs for the sources of each number).
    pub fn justin() -> Self {
        let a = (515.0f64).atan2(685.0);
        let pi = std::f64::consts::PI;
        let wheel = |node: u8, alpha: f64| WheelConfig {
            node,
            alpha,
            lambda_min: 0.37,
            lambda_max: 0.56,
            lambda_nominal: 0.465,
        };
        Self {
            name: "justin-like".into(),
            wheel_radius: 0.085,
            mass: 150.0,
            drive_torque: 30.0,
            steer_torque: 28.0,
            cycle_hz: 250.0,
            wheels: vec![
                wheel(1, a),
                wheel(2, pi - a),
                wheel(3, a - pi),
                wheel(4, -a),
            ],
            limits: Limits {
                wheel_speed: 13.9,
                wheel_accel: 40.0,
                steer_rate: 6.0,
                steer_accel: 40.0,
                leg_speed: 0.25,
            },
            gains: Gains {
                dfl_kp: 2.0,
                dfl_kd: 3.0,
                steer_kp: 10.0,
                kin_k_pos: 2.0,
                kin_k_heading: 2.0,
                kin_k_leg: 2.0,
            },
        }
    }

    /// Number of wheels n.
    pub fn n(&self) -> usize {
        self.wheels.len()
    }

    /// Control period (s).
    pub fn dt(&self) -> f64 {
        1.0 / self.cycle_hz
    }

    /// Parses and validates a platform from TOML text.
    pub fn from_toml_str(text: &str) -> Result<Self, ConfigError> {
        let p: Platform = toml::from_str(text).map_err(|e| ConfigError::Parse(e.to_string()))?;
        p.validate()?;
        Ok(p)
    }

    /// Reads, parses and validates a platform file.
    pub fn load(path: impl AsRef<Path>) -> Result<Self, ConfigError> {
        let path = path.as_ref();
        let text = std::fs::read_to_string(path).map_err(|source| ConfigError::Io {
            path: path.display().to_string(),
            source,
        })?;
        Self::from_toml_str(&text)
    }

    /// The platform as TOML text (round-trips through [`Platform::from_toml_str`]).
    pub fn to_toml_string(&self) -> String {
        toml::to_string_pretty(self).unwrap_or_default()
    }

    /// Checks every field; the error names the first bad one.
    pub fn validate(&self) -> Result<(), ConfigError> {
        fn pos(field: &str, v: f64) -> Result<(), ConfigError> {
            if !v.is_finite() {
                return Err(invalid(field, v, "must be a finite number"));
            }
            if v <= 0.0 {
                return Err(invalid(field, v, "must be greater than zero"));
            }
            Ok(())
        }
        if self.name.trim().is_empty() {
            return Err(invalid("name", "\"\"", "must not be empty"));
        }
        pos("wheel_radius", self.wheel_radius)?;
        pos("mass", self.mass)?;
        pos("drive_torque", self.drive_torque)?;
        pos("steer_torque", self.steer_torque)?;
        pos("cycle_hz", self.cycle_hz)?;
        if self.cycle_hz > 2000.0 {
            return Err(invalid(
                "cycle_hz",
                self.cycle_hz,
                "must be at most 2000 Hz",
            ));
        }
        let n = self.wheels.len();
        if !(2..=MAX_WHEELS).contains(&n) {
            return Err(invalid(
                "wheels",
                n,
                format!("a platform needs between 2 and {MAX_WHEELS} wheels"),
            ));
        }
        for (i, w) in self.wheels.iter().enumerate() {
            let f = |name: &str| format!("wheels[{i}].{name}");
            if !(1..=15).contains(&w.node) {
                return Err(invalid(f("node"), w.node, "CAN node numbers are 1..=15"));
            }
            if !w.alpha.is_finite() {
                return Err(invalid(
                    f("alpha"),
                    w.alpha,
                    "must be a finite angle in radians",
                ));
            }
            pos(&f("lambda_min"), w.lambda_min)?;
            pos(&f("lambda_max"), w.lambda_max)?;
            if w.lambda_min >= w.lambda_max {
                return Err(invalid(
                    f("lambda_min"),
                    w.lambda_min,
                    format!("must be less than lambda_max = {}", w.lambda_max),
                ));
            }
            if w.lambda_max > 0.65 {
                return Err(invalid(
                    f("lambda_max"),
                    w.lambda_max,
                    "exceeds the protocol's leg-extension range of 0.65 m",
                ));
            }
            if !w.lambda_nominal.is_finite()
                || w.lambda_nominal < w.lambda_min
                || w.lambda_nominal > w.lambda_max
            {
                return Err(invalid(
                    f("lambda_nominal"),
                    w.lambda_nominal,
                    format!(
                        "must lie in [lambda_min, lambda_max] = [{}, {}]",
                        w.lambda_min, w.lambda_max
                    ),
                ));
            }
            for (j, o) in self.wheels.iter().enumerate().take(i) {
                if o.node == w.node {
                    return Err(invalid(
                        f("node"),
                        w.node,
                        format!("wheel {j} already uses node {}", o.node),
                    ));
                }
                let d = crate::angle::diff(w.alpha, o.alpha).abs();
                if d < 1e-3 {
                    return Err(invalid(
                        f("alpha"),
                        w.alpha,
                        format!("leg direction coincides with wheels[{j}].alpha = {}: two legs on the same direction", o.alpha),
                    ));
                }
            }
        }
        let l = &self.limits;
        pos("limits.wheel_speed", l.wheel_speed)?;
        pos("limits.wheel_accel", l.wheel_accel)?;
        pos("limits.steer_rate", l.steer_rate)?;
        pos("limits.steer_accel", l.steer_accel)?;
        pos("limits.leg_speed", l.leg_speed)?;
        if l.wheel_speed > 32.0 {
            return Err(invalid(
                "limits.wheel_speed",
                l.wheel_speed,
                "exceeds the protocol's wheel-speed range of ±32 rad/s",
            ));
        }
        if l.steer_rate > 32.0 {
            return Err(invalid(
                "limits.steer_rate",
                l.steer_rate,
                "exceeds the protocol's steer-rate range of ±32 rad/s",
            ));
        }
        let g = &self.gains;
        pos("gains.dfl_kp", g.dfl_kp)?;
        pos("gains.dfl_kd", g.dfl_kd)?;
        pos("gains.steer_kp", g.steer_kp)?;
        pos("gains.kin_k_pos", g.kin_k_pos)?;
        pos("gains.kin_k_heading", g.kin_k_heading)?;
        pos("gains.kin_k_leg", g.kin_k_leg)?;
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn default_round_trips_through_toml() {
        let p = Platform::justin();
        p.validate().unwrap();
        let back = Platform::from_toml_str(&p.to_toml_string()).unwrap();
        assert_eq!(p, back);
    }

    fn err_field(p: &Platform) -> String {
        match p.validate() {
            Err(ConfigError::Invalid { field, .. }) => field,
            other => panic!("expected Invalid, got {other:?}"),
        }
    }

    #[test]
    fn names_the_bad_field() {
        let mut p = Platform::justin();
        p.wheel_radius = -0.1;
        assert_eq!(err_field(&p), "wheel_radius");
        let mut p = Platform::justin();
        p.wheels[2].lambda_min = 0.6;
        assert_eq!(err_field(&p), "wheels[2].lambda_min");
        let mut p = Platform::justin();
        p.limits.steer_rate = f64::NAN;
        assert_eq!(err_field(&p), "limits.steer_rate");
        let mut p = Platform::justin();
        p.wheels[3].alpha = p.wheels[0].alpha + 2.0 * std::f64::consts::PI;
        assert_eq!(err_field(&p), "wheels[3].alpha");
        let mut p = Platform::justin();
        p.wheels[1].node = 1;
        assert_eq!(err_field(&p), "wheels[1].node");
    }

    #[test]
    fn malformed_toml_is_a_parse_error() {
        assert!(matches!(
            Platform::from_toml_str("wheel_radius = ["),
            Err(ConfigError::Parse(_))
        ));
        let mut t = Platform::justin().to_toml_string();
        t.push_str("\nbogus = 1\n");
        assert!(matches!(
            Platform::from_toml_str(&t),
            Err(ConfigError::Parse(_))
        ));
    }
}
