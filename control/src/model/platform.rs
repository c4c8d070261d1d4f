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

use crate::num::Num;
use crate::types::MAX_WHEELS;
use rollbase_driver::busload::DEFAULT_FEEDBACK_WINDOW_S;
pub use rollbase_driver::canopen::config::Cia402Config;
use rollbase_driver::protocol::SETPOINT_WATCHDOG_S;

/// Cycles without feedback the controller tolerates before it declares stale feedback
/// (`SupervisorConfig::stale_cycles`' default): the devices' own watchdogs must tolerate as
/// many lost SETPOINTs/RPDOs plus one.
pub const TOLERATED_LOST_CYCLES: u32 = 3;

/// Lowest control rate (Hz): the wheel modules' setpoint watchdog (50 ms,
/// [`SETPOINT_WATCHDOG_S`]) must span the [`TOLERATED_LOST_CYCLES`] (3) cycles the controller
/// tolerates without feedback plus one, or a module trips on a lost SETPOINT before the
/// controller has noticed anything: 4 / 50 ms = 80 Hz.
pub const MIN_CYCLE_HZ: f64 = (TOLERATED_LOST_CYCLES + 1) as f64 / SETPOINT_WATCHDOG_S;

/// Time a cycle needs after its feedback window for the control step, the SETPOINTs' send and
/// the thread's wake-up latency (s): 1 ms, about 8 times the largest measured compute time
/// of a trajectory run's cycle (119 µs) and 6 times a live one's (161 µs, a cycle whose
/// shaper plans a transition through an intermediate twist), docs/performance.md, plus the
/// wake-up latency.
pub const CYCLE_COMPUTE_BUDGET_S: f64 = 0.001;

/// Highest control rate (Hz): a cycle waits [`DEFAULT_FEEDBACK_WINDOW_S`] (2 ms) for the
/// devices' answers to its SYNC and needs [`CYCLE_COMPUTE_BUDGET_S`] (1 ms) more, so its
/// period is at least 3 ms: 333 Hz.
pub const MAX_CYCLE_HZ: f64 = 1.0 / (DEFAULT_FEEDBACK_WINDOW_S + CYCLE_COMPUTE_BUDGET_S);
use serde::{Deserialize, Serialize};
use std::path::Path;

/// Errors from loading or validating a platform description.
#[derive(Debug, thiserror::Error)]
pub enum ConfigError {
    /// The file could not be read, is too large (`/dev/zero` …) or is not UTF-8 text.
    #[error(transparent)]
    Input(#[from] rollbase_driver::input::InputError),
    /// A device description file (`[cia402] eds`) could not be read, or the boot plan does
    /// not fit it.
    #[error(transparent)]
    Eds(#[from] Box<rollbase_driver::canopen::eds::EdsError>),
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

/// Most CAN buses a platform may spread its wheel modules over (`wheels[i].bus` = 0 or 1).
pub const MAX_BUSES: usize = 2;

/// Largest caster offset `wheels[i].caster_offset` (m).
pub const MAX_CASTER_OFFSET: f64 = 0.5;

/// Smallest steering range `wheels[i].steer_range` may span (rad): a little more than half a
/// turn, so that a wheel can always roll one of its two ways (forward at φ, backward at
/// φ + π) without leaving the range ([`crate::angle::SteerRange`]).
pub const MIN_STEER_SPAN: f64 = std::f64::consts::PI + 0.1;

/// Largest steering range `wheels[i].steer_range` may span (rad): three turns. The steering
/// encoders are absolute over one turn; the controller counts turns from the start
/// ([`crate::angle::SteerRange`]).
pub const MAX_STEER_SPAN: f64 = 6.0 * std::f64::consts::PI;

/// Largest distance of a fixed wheel's steering axis from the body origin (m).
pub const MAX_FIXED_LAMBDA: f64 = 5.0;

/// Largest steer→drive coupling `wheels[i].coupling` (wheel turns per steering turn).
pub const MAX_COUPLING: f64 = 10.0;

/// One wheel module: where its steering axis sits (on a leg, or fixed), how it steers
/// (centred or off-centred, endless or within a range), its motors' polarity and coupling,
/// its CAN node and bus.
///
/// In the platform file a wheel on a leg gives `lambda_min`, `lambda_max` and
/// `lambda_nominal`; a wheel without a leg (a fixed footprint) gives `lambda` instead, its
/// steering axis' fixed distance from the body origin along `alpha`. In memory a wheel
/// without a leg has `leg = false` and `lambda_min = lambda_max = lambda_nominal = lambda`,
/// so every use of the leg range sees a range of one point.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(try_from = "WheelFile", into = "WheelFile")]
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
    /// The wheel sits on a leg with an encoder (true), or is mounted at a fixed distance
    /// (false: no leg encoder, no leg setpoint, no leg joint).
    pub leg: bool,
    /// Caster offset d ≥ 0 (m): the wheel's contact point trails the steering axis by d
    /// along the wheel plane, P_i − d (cos φ_i, sin φ_i) (seed 003's off-centred orientable
    /// wheel; [`crate::model::kinematics`], "Off-centred steering"). 0 = centred steering.
    pub caster_offset: f64,
    /// Steering range [min, max] (rad) when the wheel cannot steer endlessly (cable stops):
    /// its steering angle never leaves it. `None`: endless (slip rings).
    pub steer_range: Option<[f64; 2]>,
    /// The CAN bus the module is on (0 or 1). The cycle core runs one link per bus
    /// ([`crate::runtime::link::Buses`]); the command line drives one bus so far, so `rollbase` refuses
    /// to run a platform with wheels on bus 1 (`config check` accepts it).
    pub bus: u8,
    /// +1, or −1 for a rolling motor mounted mirrored: its positive direction rolls the
    /// wheel backwards. Applied to setpoints and feedback on the wire side (both profiles).
    pub drive_polarity: i8,
    /// +1, or −1 for a steering motor (and encoder) whose positive direction turns the wheel
    /// clockwise seen from above.
    pub steer_polarity: i8,
    /// Steer→drive coupling (wheel turns per steering turn): modules whose rolling motor sits
    /// in the body and drives the wheel through the steering axis (bevel gears) turn the wheel
    /// by `coupling · Δφ` when only the steering turns. The wheel's spin is then
    /// ω = ω_motor + coupling · φ̇ (ω_motor the rolling motor's speed at the wheel); the link
    /// subtracts it from every rolling setpoint and adds it to every measured rolling speed.
    pub coupling: f64,
}

fn one() -> i8 {
    1
}

/// A wheel as written in the platform file (see [`WheelConfig`]).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
struct WheelFile {
    node: u8,
    alpha: f64,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    lambda: Option<f64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    lambda_min: Option<f64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    lambda_max: Option<f64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    lambda_nominal: Option<f64>,
    #[serde(default)]
    caster_offset: f64,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    steer_range: Option<[f64; 2]>,
    #[serde(default)]
    bus: u8,
    #[serde(default = "one")]
    drive_polarity: i8,
    #[serde(default = "one")]
    steer_polarity: i8,
    #[serde(default)]
    coupling: f64,
}

impl WheelFile {
    /// The wheel in memory; `at` is its place in the file (`wheels[2]`), for the errors. Only
    /// the choice between a leg and a fixed mount is checked here; the values are checked by
    /// [`Platform::validate`].
    fn into_config(self, at: &str) -> Result<WheelConfig, ConfigError> {
        let legged = [self.lambda_min, self.lambda_max, self.lambda_nominal];
        let (lambda_min, lambda_max, lambda_nominal, leg) = match (self.lambda, legged) {
            (Some(l), [None, None, None]) => (l, l, l, false),
            (None, [Some(a), Some(b), Some(c)]) => (a, b, c, true),
            (Some(l), _) => {
                let field = ["lambda_min", "lambda_max", "lambda_nominal"]
                    .iter()
                    .zip(legged)
                    .find(|(_, v)| v.is_some())
                    .map_or("lambda_min", |(f, _)| *f);
                return Err(invalid(
                    format!("{at}.{field}"),
                    legged.iter().flatten().next().map_or(0.0, |v| *v),
                    format!("a wheel with a fixed `lambda` = {l} has no leg: remove lambda_min, lambda_max and lambda_nominal, or remove `lambda` for a wheel on a leg"),
                ));
            }
            (None, _) => {
                let field = ["lambda_min", "lambda_max", "lambda_nominal"]
                    .iter()
                    .zip(legged)
                    .find(|(_, v)| v.is_none())
                    .map_or("lambda", |(f, _)| *f);
                return Err(invalid(
                    format!("{at}.{field}"),
                    "(missing)",
                    "a wheel on a leg needs lambda_min, lambda_max and lambda_nominal (m); a wheel without a leg gives only `lambda`, its steering axis' distance from the body origin (m)",
                ));
            }
        };
        Ok(WheelConfig {
            node: self.node,
            alpha: self.alpha,
            lambda_min,
            lambda_max,
            lambda_nominal,
            leg,
            caster_offset: self.caster_offset,
            steer_range: self.steer_range,
            bus: self.bus,
            drive_polarity: self.drive_polarity,
            steer_polarity: self.steer_polarity,
            coupling: self.coupling,
        })
    }
}

impl TryFrom<WheelFile> for WheelConfig {
    type Error = String;
    fn try_from(f: WheelFile) -> Result<Self, String> {
        f.into_config("wheels[]").map_err(|e| e.to_string())
    }
}

impl From<WheelConfig> for WheelFile {
    fn from(w: WheelConfig) -> Self {
        let (lambda, lambda_min, lambda_max, lambda_nominal) = if w.leg {
            (
                None,
                Some(w.lambda_min),
                Some(w.lambda_max),
                Some(w.lambda_nominal),
            )
        } else {
            (Some(w.lambda_nominal), None, None, None)
        };
        Self {
            node: w.node,
            alpha: w.alpha,
            lambda,
            lambda_min,
            lambda_max,
            lambda_nominal,
            caster_offset: w.caster_offset,
            steer_range: w.steer_range,
            bus: w.bus,
            drive_polarity: w.drive_polarity,
            steer_polarity: w.steer_polarity,
            coupling: w.coupling,
        }
    }
}

impl WheelConfig {
    /// A wheel on a leg with range [λ_min, λ_max], nominal λ_0, centred endless steering,
    /// both motors positive, no coupling, on bus 0.
    pub fn on_leg(node: u8, alpha: f64, lambda_min: f64, lambda_max: f64, nominal: f64) -> Self {
        Self {
            node,
            alpha,
            lambda_min,
            lambda_max,
            lambda_nominal: nominal,
            leg: true,
            caster_offset: 0.0,
            steer_range: None,
            bus: 0,
            drive_polarity: 1,
            steer_polarity: 1,
            coupling: 0.0,
        }
    }

    /// A wheel without a leg, its steering axis at `lambda` along `alpha` (otherwise as
    /// [`WheelConfig::on_leg`]).
    pub fn fixed(node: u8, alpha: f64, lambda: f64) -> Self {
        Self {
            leg: false,
            ..Self::on_leg(node, alpha, lambda, lambda, lambda)
        }
    }

    /// Whether the wheel sits on a leg (with a leg encoder).
    pub fn has_leg(&self) -> bool {
        self.leg
    }

    /// Whether the contact point is off the steering axis (caster offset > 0).
    pub fn off_centred(&self) -> bool {
        self.caster_offset > 0.0
    }

    /// The steering range as (min, max) (rad); `None` when endless.
    pub fn steer_limits(&self) -> Option<(f64, f64)> {
        self.steer_range.map(|[a, b]| (a, b))
    }

    /// The steering range as an [`angle::SteerRange`](crate::angle::SteerRange); `None` when
    /// endless.
    pub fn steering_range(&self) -> Option<crate::angle::SteerRange> {
        self.steer_limits()
            .map(|(min, max)| crate::angle::SteerRange { min, max })
    }
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
    /// Which protocol the wheel modules speak on the bus (default: the native profile).
    #[serde(default)]
    pub protocol: Protocol,
    /// The CiA 402 profile's nodes, units and timing (`[cia402]`); used when `protocol =
    /// "cia402"`. Absent: [`Cia402Config::for_wheels`] for the platform's wheel count.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub cia402: Option<Cia402Config>,
    /// The base service's command port (`[service]`): command timeout and sanity bounds.
    #[serde(default)]
    pub service: Service,
    /// The drives' velocity loops (`[drives]`): their lag, which the controller compensates.
    #[serde(default)]
    pub drives: Drives,
}

/// The drives' velocity loops, modelled as first-order lags ω̇ = (ω_cmd − ω)/τ (`[drives]`
/// in the platform file). The cycle adds τ × the reference's acceleration to every command
/// (a lead that cancels the lag: (1 + τs)/(1 + τs) = 1), so the wheels follow the reference
/// without the τ·a velocity shortfall that a fast reference would otherwise leave (20 mm of
/// position error per m/s² of acceleration at τ = 20 ms). Set them from the drives' tuning
/// (their velocity-loop bandwidth f: τ ≈ 1/(2πf)); 0 turns the compensation off. The
/// defaults match the simulator's drives.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct Drives {
    /// Rolling drives' velocity-loop time constant (s). Default 0.020.
    pub wheel_time_constant: f64,
    /// Steering drives' velocity-loop time constant (s). Default 0.015.
    pub steer_time_constant: f64,
}

impl Default for Drives {
    fn default() -> Self {
        Self {
            wheel_time_constant: 0.020,
            steer_time_constant: 0.015,
        }
    }
}

/// The base service's command port settings (`[service]` in the platform file; every field
/// has a default).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct Service {
    /// A live command holds for this long (s); then the platform comes to a controlled stop,
    /// steering held, until the next valid command. Default 0.5 s.
    pub command_timeout: f64,
    /// Sanity bound on |vx| and |vy| of a command (m/s): beyond it a command is refused as a
    /// sender's bug (below it, a command beyond the actuator limits is slowed down, not
    /// refused). Default 10 m/s.
    pub max_linear_command: f64,
    /// Sanity bound on |ω| of a command (rad/s). Default 10 rad/s.
    pub max_angular_command: f64,
}

impl Default for Service {
    fn default() -> Self {
        Self {
            command_timeout: 0.5,
            max_linear_command: 10.0,
            max_angular_command: 10.0,
        }
    }
}

/// The protocol profile the wheel modules speak.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Protocol {
    /// rollbase's own wheel-module protocol: one SETPOINT and two FEEDBACK frames per module
    /// and cycle, with rolling counters and CRC ([`rollbase_driver::protocol`]).
    #[default]
    Native,
    /// CANopen: two CiA 402 drives (rolling, steering) and a CiA 406 leg encoder per wheel
    /// ([`rollbase_driver::canopen`]).
    Cia402,
}

impl std::str::FromStr for Protocol {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, Self::Err> {
        match s {
            "native" => Ok(Self::Native),
            "cia402" => Ok(Self::Cia402),
            other => Err(format!(
                "unknown protocol profile `{other}`: expected `native` or `cia402`"
            )),
        }
    }
}

impl std::fmt::Display for Protocol {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            Self::Native => "native",
            Self::Cia402 => "cia402",
        })
    }
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
        let wheel = |node: u8, alpha: f64| WheelConfig::on_leg(node, alpha, 0.37, 0.56, 0.465);
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
            protocol: Protocol::Native,
            cia402: None,
            service: Service::default(),
            drives: Drives::default(),
        }
    }

    /// The CiA 402 profile's configuration: the `[cia402]` table, or the default node
    /// assignment for this platform's wheel count (a wheel without a leg has no leg encoder:
    /// `leg_node = 0`).
    pub fn cia402(&self) -> Cia402Config {
        self.cia402.clone().unwrap_or_else(|| {
            let mut c = Cia402Config::for_wheels(self.n());
            for (cw, w) in c.wheels.iter_mut().zip(&self.wheels) {
                if !w.leg {
                    cw.leg_node = 0;
                }
            }
            c
        })
    }

    /// Whether any wheel sits on a leg.
    pub fn has_legs(&self) -> bool {
        self.wheels.iter().any(|w| w.leg)
    }

    /// Number of wheels on legs.
    pub fn n_legs(&self) -> usize {
        self.wheels.iter().filter(|w| w.leg).count()
    }

    /// Whether any wheel's contact point is off its steering axis.
    pub fn has_caster_offset(&self) -> bool {
        self.wheels.iter().any(|w| w.off_centred())
    }

    /// Number of CAN buses the wheels are on (1 or 2).
    pub fn buses(&self) -> usize {
        self.wheels
            .iter()
            .map(|w| usize::from(w.bus) + 1)
            .max()
            .unwrap_or(1)
            .clamp(1, MAX_BUSES)
    }

    /// The part of the platform on bus `b`: its wheels in wheel order (and their `[cia402]`
    /// entries), everything else as it is. What one bus's link is built from.
    pub fn bus_subset(&self, b: usize) -> Self {
        let mine: Vec<usize> = self.wheels_on_bus(b).collect();
        let mut p = self.clone();
        p.wheels = mine.iter().map(|&i| self.wheels[i]).collect();
        let mut c = self.cia402();
        c.wheels = mine
            .iter()
            .filter_map(|&i| c.wheels.get(i).copied())
            .collect();
        p.cia402 = Some(c);
        p
    }

    /// The wheels on bus `b`, as indices in wheel order.
    pub fn wheels_on_bus(&self, b: usize) -> impl Iterator<Item = usize> + '_ {
        self.wheels
            .iter()
            .enumerate()
            .filter(move |(_, w)| usize::from(w.bus) == b)
            .map(|(i, _)| i)
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
        check_wheel_tables(text)?;
        let p: Platform = toml::from_str(text).map_err(|e| ConfigError::Parse(e.to_string()))?;
        p.validate()?;
        Ok(p)
    }

    /// Reads, parses and validates a platform file; with `[cia402] eds` files, reads them
    /// (paths relative to the platform file's directory), takes the DCFs' values into the
    /// boot plan and checks the plan against them ([`rollbase_driver::canopen::eds`]).
    pub fn load(path: impl AsRef<Path>) -> Result<Self, ConfigError> {
        Ok(Self::load_checked(path)?.0)
    }

    /// [`Platform::load`], with what the EDS/DCF check did (for `rollbase config check`).
    pub fn load_checked(
        path: impl AsRef<Path>,
    ) -> Result<(Self, rollbase_driver::canopen::eds::EdsReport), ConfigError> {
        let path = path.as_ref();
        let text = rollbase_driver::input::read_text(
            path,
            rollbase_driver::input::MAX_CONFIG_BYTES,
            "platform file",
        )?;
        let mut p = Self::from_toml_str(&text)?;
        let mut report = rollbase_driver::canopen::eds::EdsReport::default();
        let period_us = (p.dt() * 1e6).round() as u32;
        if let Some(c) = p.cia402.as_mut().filter(|c| !c.eds.is_empty()) {
            let base = path.parent().unwrap_or(Path::new("."));
            report = rollbase_driver::canopen::eds::apply(c, base, period_us).map_err(Box::new)?;
        }
        Ok((p, report))
    }

    /// The platform as TOML text (round-trips through [`Platform::from_toml_str`]).
    pub fn to_toml_string(&self) -> String {
        toml::to_string_pretty(self).unwrap_or_default()
    }

    /// Checks every field; the error names the first bad one.
    pub fn validate(&self) -> Result<(), ConfigError> {
        fn pos(field: &str, v: f64) -> Result<(), ConfigError> {
            if !v.is_finite() {
                return Err(invalid(field, Num(v), "must be a finite number"));
            }
            if v <= 0.0 {
                return Err(invalid(field, Num(v), "must be greater than zero"));
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
        if self.cycle_hz < MIN_CYCLE_HZ {
            return Err(invalid(
                "cycle_hz",
                Num(self.cycle_hz),
                format!(
                    "must be at least {MIN_CYCLE_HZ:.0} Hz: the wheel modules stop their motors when no valid SETPOINT arrived for {:.0} ms (setpoint watchdog), and the controller tolerates {TOLERATED_LOST_CYCLES} cycles without feedback before it stops the platform, so {} cycles must fit in {:.0} ms (250 Hz is the design rate)",
                    SETPOINT_WATCHDOG_S * 1e3,
                    TOLERATED_LOST_CYCLES + 1,
                    SETPOINT_WATCHDOG_S * 1e3
                ),
            ));
        }
        if self.cycle_hz > MAX_CYCLE_HZ {
            return Err(invalid(
                "cycle_hz",
                Num(self.cycle_hz),
                format!(
                    "must be at most {MAX_CYCLE_HZ:.0} Hz: each cycle waits {:.0} ms for the devices' feedback after its SYNC (the feedback window) and needs {:.0} ms more for the control step and the SETPOINTs, so the period must be at least {:.0} ms (250 Hz is the design rate)",
                    DEFAULT_FEEDBACK_WINDOW_S * 1e3,
                    CYCLE_COMPUTE_BUDGET_S * 1e3,
                    (DEFAULT_FEEDBACK_WINDOW_S + CYCLE_COMPUTE_BUDGET_S) * 1e3
                ),
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
            if w.leg {
                self.validate_leg(i, w)?;
            } else {
                if !(w.lambda_nominal.is_finite()
                    && w.lambda_nominal > 0.0
                    && w.lambda_nominal <= MAX_FIXED_LAMBDA)
                {
                    return Err(invalid(
                        f("lambda"),
                        Num(w.lambda_nominal),
                        format!("must be the steering axis' distance from the body origin, greater than 0 and at most {MAX_FIXED_LAMBDA} m"),
                    ));
                }
                if w.lambda_min != w.lambda_nominal || w.lambda_max != w.lambda_nominal {
                    return Err(invalid(
                        f("lambda"),
                        Num(w.lambda_nominal),
                        format!(
                            "a wheel without a leg has lambda_min = lambda_max = lambda (here [{}, {}])",
                            w.lambda_min, w.lambda_max
                        ),
                    ));
                }
            }
            self.validate_steering(i, w)?;
            for (j, o) in self.wheels.iter().enumerate().take(i) {
                if o.node == w.node {
                    return Err(invalid(
                        f("node"),
                        w.node,
                        format!("wheel {j} already uses node {}", o.node),
                    ));
                }
                let d = crate::angle::diff(w.alpha, o.alpha).abs();
                // Two legs on one direction would collide; two fixed wheels may share a
                // direction at different distances.
                let apart =
                    !(w.leg || o.leg) && (w.lambda_nominal - o.lambda_nominal).abs() >= 0.01;
                if d < 1e-3 && !apart {
                    return Err(invalid(
                        f("alpha"),
                        w.alpha,
                        format!("leg direction coincides with wheels[{j}].alpha = {}: two legs on the same direction", o.alpha),
                    ));
                }
            }
        }
        if self.buses() > 1 && self.wheels_on_bus(0).next().is_none() {
            return Err(invalid(
                "wheels[0].bus",
                self.wheels[0].bus,
                "no wheel is on bus 0 but some are on bus 1: number the buses from 0",
            ));
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
                Num(l.wheel_speed),
                "exceeds the protocol's wheel-speed range of ±32 rad/s",
            ));
        }
        if l.steer_rate > 32.0 {
            return Err(invalid(
                "limits.steer_rate",
                Num(l.steer_rate),
                "exceeds the protocol's steer-rate range of ±32 rad/s",
            ));
        }
        if self.protocol == Protocol::Cia402 || self.cia402.is_some() {
            self.validate_cia402()?;
        }
        let sv = &self.service;
        pos("service.command_timeout", sv.command_timeout)?;
        if sv.command_timeout < 2.0 / self.cycle_hz || sv.command_timeout > 60.0 {
            return Err(invalid(
                "service.command_timeout",
                sv.command_timeout,
                format!(
                    "must lie between two control cycles ({:.4} s) and 60 s",
                    2.0 / self.cycle_hz
                ),
            ));
        }
        pos("service.max_linear_command", sv.max_linear_command)?;
        pos("service.max_angular_command", sv.max_angular_command)?;
        for (field, v) in [
            (
                "drives.wheel_time_constant",
                self.drives.wheel_time_constant,
            ),
            (
                "drives.steer_time_constant",
                self.drives.steer_time_constant,
            ),
        ] {
            if !(v.is_finite() && (0.0..=0.2).contains(&v)) {
                return Err(invalid(
                    field,
                    v,
                    "must lie in [0, 0.2] s (0 turns the lag compensation off)",
                ));
            }
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

impl Platform {
    /// A wheel on a leg: its range and nominal extension.
    fn validate_leg(&self, i: usize, w: &WheelConfig) -> Result<(), ConfigError> {
        let f = |name: &str| format!("wheels[{i}].{name}");
        for (name, v) in [("lambda_min", w.lambda_min), ("lambda_max", w.lambda_max)] {
            if !v.is_finite() {
                return Err(invalid(f(name), Num(v), "must be a finite number"));
            }
            if v <= 0.0 {
                return Err(invalid(f(name), Num(v), "must be greater than zero"));
            }
        }
        if w.lambda_min >= w.lambda_max {
            return Err(invalid(
                f("lambda_min"),
                Num(w.lambda_min),
                format!(
                    "must be less than lambda_max = {} (a wheel without a leg gives `lambda` instead of the leg range)",
                    w.lambda_max
                ),
            ));
        }
        if w.lambda_max > 0.65 {
            return Err(invalid(
                f("lambda_max"),
                Num(w.lambda_max),
                "exceeds the protocol's leg-extension range of 0.65 m",
            ));
        }
        if !w.lambda_nominal.is_finite()
            || w.lambda_nominal < w.lambda_min
            || w.lambda_nominal > w.lambda_max
        {
            return Err(invalid(
                f("lambda_nominal"),
                Num(w.lambda_nominal),
                format!(
                    "must lie in [lambda_min, lambda_max] = [{}, {}]",
                    w.lambda_min, w.lambda_max
                ),
            ));
        }
        Ok(())
    }

    /// A wheel's steering and motors: caster offset, steering range, bus, polarity, coupling.
    fn validate_steering(&self, i: usize, w: &WheelConfig) -> Result<(), ConfigError> {
        let f = |name: &str| format!("wheels[{i}].{name}");
        let d = w.caster_offset;
        if !(d.is_finite() && (0.0..=MAX_CASTER_OFFSET).contains(&d)) {
            return Err(invalid(
                f("caster_offset"),
                Num(d),
                format!("must lie in [0, {MAX_CASTER_OFFSET}] m: the distance from the steering axis back to the wheel's contact point, measured along the wheel plane behind the axis (a trailing caster); 0 for a wheel whose steering axis passes through its contact point"),
            ));
        }
        if d >= w.lambda_min {
            return Err(invalid(
                f("caster_offset"),
                Num(d),
                format!(
                    "must be less than the steering axis' smallest distance from the body origin ({} m): the contact point would swing across the body origin",
                    w.lambda_min
                ),
            ));
        }
        if let Some([lo, hi]) = w.steer_range {
            let shown = format!("[{}, {}]", Num(lo), Num(hi));
            if !(lo.is_finite() && hi.is_finite()) {
                return Err(invalid(
                    f("steer_range"),
                    shown,
                    "must be two finite angles [min, max] in radians",
                ));
            }
            if hi - lo < MIN_STEER_SPAN {
                return Err(invalid(
                    f("steer_range"),
                    shown,
                    format!(
                        "must span more than half a turn, at least {MIN_STEER_SPAN:.2} rad (min < max): within it a wheel must be able to roll one of its two ways (forward at φ or backward at φ + π) in every direction; a wheel that cannot steer that far is not an omnidirectional wheel"
                    ),
                ));
            }
            if hi - lo > MAX_STEER_SPAN {
                return Err(invalid(
                    f("steer_range"),
                    shown,
                    format!("may span at most three turns ({MAX_STEER_SPAN:.2} rad); leave it out for a wheel that steers endlessly"),
                ));
            }
        }
        if usize::from(w.bus) >= MAX_BUSES {
            return Err(invalid(
                f("bus"),
                w.bus,
                format!("must be 0 or 1: a platform has at most {MAX_BUSES} buses"),
            ));
        }
        for (name, v) in [
            ("drive_polarity", w.drive_polarity),
            ("steer_polarity", w.steer_polarity),
        ] {
            if v != 1 && v != -1 {
                return Err(invalid(
                    f(name),
                    v,
                    "must be 1, or -1 for a motor mounted mirrored (its positive direction turns the wheel the other way)",
                ));
            }
        }
        if !(w.coupling.is_finite() && w.coupling.abs() <= MAX_COUPLING) {
            return Err(invalid(
                f("coupling"),
                Num(w.coupling),
                format!("must be a finite ratio within ±{MAX_COUPLING}: wheel turns per steering turn when only the steering turns (0 for modules whose motors do not couple)"),
            ));
        }
        Ok(())
    }

    /// Checks the `[cia402]` section against the platform: node assignment and timing
    /// ([`Cia402Config::validate`]), and that the units carry the platform's limits: twice
    /// the wheel-speed and steering-rate limits must fit the drives' INTEGER32 velocity
    /// objects, 1.2 times the leg-speed limit the encoders' INTEGER16 speed value, and every
    /// leg extension the encoders' UNSIGNED32 position value.
    fn validate_cia402(&self) -> Result<(), ConfigError> {
        let c = self.cia402();
        c.validate(self.n(), self.cycle_hz)
            .map_err(|e| invalid(e.field, e.value, e.reason))?;
        for (i, (cw, w)) in c.wheels.iter().zip(&self.wheels).enumerate() {
            if w.leg && cw.leg_node == 0 {
                return Err(invalid(
                    format!("cia402.wheels[{i}].leg_node"),
                    0,
                    format!("wheels[{i}] sits on a leg: give its CiA 406 leg encoder's node-ID (1..=127)"),
                ));
            }
            if !w.leg && cw.leg_node != 0 {
                return Err(invalid(
                    format!("cia402.wheels[{i}].leg_node"),
                    cw.leg_node,
                    format!("wheels[{i}] has no leg (`lambda`): it has no leg encoder; set leg_node = 0"),
                ));
            }
        }
        // The drives' RPDO deadline is their setpoint watchdog: like the native modules' it
        // must span the cycles the controller tolerates without feedback plus one.
        let need_ms = f64::from(TOLERATED_LOST_CYCLES + 1) * 1000.0 / self.cycle_hz;
        if c.rpdo_timeout_ms != 0 && f64::from(c.rpdo_timeout_ms) < need_ms {
            return Err(invalid(
                "cia402.rpdo_timeout_ms",
                c.rpdo_timeout_ms,
                format!(
                    "must be 0 (off) or at least {} control cycles ({need_ms:.1} ms at cycle_hz = {}): the controller tolerates {TOLERATED_LOST_CYCLES} cycles without feedback, the drives must tolerate as many lost RPDOs plus one",
                    TOLERATED_LOST_CYCLES + 1,
                    Num(self.cycle_hz)
                ),
            ));
        }
        let l = &self.limits;
        c.homing
            .validate("cia402.homing", l.steer_rate, l.steer_accel)
            .map_err(|e| invalid(e.field, e.value, e.reason))?;
        for (i, (w, pw)) in c.wheels.iter().zip(&self.wheels).enumerate() {
            if let Some(r) = pw.steering_range() {
                // The turn to the rest angle after homing stays inside the range only if
                // the rest angle does.
                if !(w.rest_angle_rad >= r.min && w.rest_angle_rad <= r.max) {
                    return Err(invalid(
                        format!("cia402.wheels[{i}].rest_angle_rad"),
                        w.rest_angle_rad,
                        format!(
                            "must lie inside wheels[{i}].steer_range [{}, {}] rad: the wheel turns there after homing",
                            Num(r.min),
                            Num(r.max)
                        ),
                    ));
                }
            }
        }
        for (i, w) in c.wheels.iter().enumerate() {
            if let Some(h) = w.homing {
                h.validate(
                    &format!("cia402.wheels[{i}].homing"),
                    l.steer_rate,
                    l.steer_accel,
                )
                .map_err(|e| invalid(e.field, e.value, e.reason))?;
            }
        }
        for (field, units, limit, name) in [
            ("cia402.drive", c.drive, l.wheel_speed, "limits.wheel_speed"),
            ("cia402.steer", c.steer, l.steer_rate, "limits.steer_rate"),
        ] {
            if units.velocity_from_si(2.0 * limit).is_none() {
                return Err(invalid(
                    format!("{field}.increments_per_rev"),
                    units.increments_per_rev,
                    format!(
                        "with gear_ratio {} twice `{name}` = {limit} rad/s does not fit the drive's INTEGER32 velocity; check the encoder resolution and gear",
                        units.gear_ratio
                    ),
                ));
            }
        }
        let enc = c.leg_encoder;
        if enc.max_speed() < 1.2 * l.leg_speed {
            return Err(invalid(
                "cia402.leg_encoder.speed_step_um_s",
                enc.speed_step_um_s,
                format!(
                    "the INTEGER16 speed value reaches only {:.3} m/s, less than 1.2 × limits.leg_speed = {:.3} m/s; use a larger speed step",
                    enc.max_speed(),
                    1.2 * l.leg_speed
                ),
            ));
        }
        for (i, w) in self.wheels.iter().enumerate().filter(|(_, w)| w.leg) {
            if enc.m_to_position(w.lambda_min).is_none()
                || enc.m_to_position(w.lambda_max).is_none()
            {
                return Err(invalid(
                    "cia402.leg_encoder.offset_m",
                    enc.offset_m,
                    format!(
                        "wheels[{i}]'s leg range [{}, {}] m is not representable by the encoder's position value (offset above lambda_min, or beyond UNSIGNED32 steps)",
                        w.lambda_min, w.lambda_max
                    ),
                ));
            }
        }
        Ok(())
    }
}

/// The pre-pass of [`Platform::from_toml_str`]: every `[[wheels]]` table chooses between a
/// leg and a fixed mount, checked here with the wheel's index in the error (the full parse
/// that follows would only say where in the file).
fn check_wheel_tables(text: &str) -> Result<(), ConfigError> {
    let Ok(table) = toml::from_str::<toml::Table>(text) else {
        // Not TOML at all: the full parse reports it with its position.
        return Ok(());
    };
    let Some(toml::Value::Array(wheels)) = table.get("wheels") else {
        return Ok(());
    };
    for (i, w) in wheels.iter().enumerate() {
        if let Ok(f) = WheelFile::deserialize(w.clone()) {
            f.into_config(&format!("wheels[{i}]"))?;
        }
    }
    Ok(())
}

/// The example platforms' names, for `rollbase config default --example NAME`.
pub const EXAMPLE_NAMES: [&str; 3] = ["mpo700", "three-wheel", "six-wheel"];

impl Platform {
    /// An example platform by name ([`EXAMPLE_NAMES`]; `justin` is the default platform).
    pub fn example(name: &str) -> Option<Self> {
        match name {
            "justin" => Some(Self::justin()),
            "mpo700" => Some(Self::mpo700()),
            "three-wheel" => Some(Self::three_wheel()),
            "six-wheel" => Some(Self::six_wheel()),
            _ => None,
        }
    }

    /// An MPO-700-like base (docs/examples/mpo700.toml): four wheels without legs at the
    /// corners of a 0.48 m × 0.38 m rectangle, contact points 45 mm behind their steering
    /// axes (the off-centred steering of Neobotix's omni-drive modules, modelled in ROS by
    /// cob_omni_drive_controller as `wheel_offset`), steering limited to ±1.2 turns by the
    /// modules' cables, wheel radius 0.09 m, 0.6 m/s wheels. The numbers are illustrative,
    /// not a datasheet's.
    pub fn mpo700() -> Self {
        let (x, y): (f64, f64) = (0.24, 0.19);
        let l = x.hypot(y);
        let a = y.atan2(x);
        let pi = std::f64::consts::PI;
        let turns = 1.2 * std::f64::consts::TAU;
        let wheel = |node: u8, alpha: f64| WheelConfig {
            caster_offset: 0.045,
            steer_range: Some([-turns, turns]),
            ..WheelConfig::fixed(node, alpha, l)
        };
        Self {
            name: "mpo700-like".into(),
            wheel_radius: 0.09,
            mass: 100.0,
            drive_torque: 20.0,
            steer_torque: 15.0,
            cycle_hz: 250.0,
            wheels: vec![
                wheel(1, a),
                wheel(2, pi - a),
                wheel(3, a - pi),
                wheel(4, -a),
            ],
            limits: Limits {
                wheel_speed: 12.0,
                wheel_accel: 12.0,
                steer_rate: 6.0,
                steer_accel: 40.0,
                leg_speed: 0.25,
            },
            ..Self::justin()
        }
    }

    /// A three-wheel base without legs (docs/examples/three-wheel.toml): centred wheels 0.3 m
    /// from the centre at 120° spacing, steering limited to ±170° by cable stops; the second
    /// wheel's motors are mounted mirrored (both polarities −1).
    pub fn three_wheel() -> Self {
        let pi = std::f64::consts::PI;
        let stop = 170f64.to_radians();
        let wheel = |node: u8, alpha: f64| WheelConfig {
            steer_range: Some([-stop, stop]),
            ..WheelConfig::fixed(node, alpha, 0.3)
        };
        let mut wheels = vec![
            wheel(1, 0.0),
            wheel(2, 2.0 * pi / 3.0),
            wheel(3, -2.0 * pi / 3.0),
        ];
        wheels[1].drive_polarity = -1;
        wheels[1].steer_polarity = -1;
        Self {
            name: "three-wheel".into(),
            wheel_radius: 0.075,
            mass: 60.0,
            drive_torque: 10.0,
            steer_torque: 8.0,
            cycle_hz: 250.0,
            wheels,
            limits: Limits {
                wheel_speed: 16.0,
                wheel_accel: 20.0,
                steer_rate: 5.0,
                steer_accel: 30.0,
                leg_speed: 0.25,
            },
            ..Self::justin()
        }
    }

    /// A six-wheel Justin-like base on two buses (docs/examples/six-wheel.toml): six wheels
    /// on legs at 60° spacing, λ ∈ [0.37, 0.56] m, wheels 1–3 on bus 0 and 4–6 on bus 1 (six
    /// native modules or eighteen CiA 402/406 devices are too much for one 1 Mbit/s bus at
    /// 250 Hz: `rollbase bus-load --config`).
    pub fn six_wheel() -> Self {
        let pi = std::f64::consts::PI;
        let wheels = (0..6u8)
            .map(|k| WheelConfig {
                bus: k / 3,
                ..WheelConfig::on_leg(
                    k + 1,
                    crate::angle::wrap(pi / 6.0 + f64::from(k) * pi / 3.0),
                    0.37,
                    0.56,
                    0.465,
                )
            })
            .collect();
        Self {
            name: "six-wheel".into(),
            mass: 220.0,
            wheels,
            ..Self::justin()
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn cia402_section_is_validated_against_the_platform() {
        let mut p = Platform::justin();
        p.protocol = Protocol::Cia402;
        p.validate().unwrap();
        let back = Platform::from_toml_str(&p.to_toml_string()).unwrap();
        assert_eq!(back.protocol, Protocol::Cia402);
        // The full section round-trips too.
        p.cia402 = Some(Cia402Config::for_wheels(4));
        let text = p.to_toml_string();
        assert!(
            text.contains("[cia402]") && text.contains("steer_node"),
            "{text}"
        );
        assert_eq!(Platform::from_toml_str(&text).unwrap(), p);
        let mut q = p.clone();
        q.cia402.as_mut().unwrap().wheels.pop();
        assert_eq!(err_field(&q), "cia402.wheels");
        let mut q = p.clone();
        q.cia402.as_mut().unwrap().wheels[3].leg_node = 2;
        assert_eq!(err_field(&q), "cia402.wheels[3].leg_node");
        let mut q = p.clone();
        q.cia402.as_mut().unwrap().leg_encoder.speed_step_um_s = 1;
        assert_eq!(err_field(&q), "cia402.leg_encoder.speed_step_um_s");
        let mut q = p.clone();
        q.cia402.as_mut().unwrap().leg_encoder.offset_m = 0.4;
        assert_eq!(err_field(&q), "cia402.leg_encoder.offset_m");
        let mut q = p.clone();
        q.cia402.as_mut().unwrap().drive.gear_ratio = 900_000.0;
        assert_eq!(err_field(&q), "cia402.drive.increments_per_rev");
        // An unknown profile names the choices.
        let t = Platform::justin()
            .to_toml_string()
            .replace("protocol = \"native\"", "protocol = \"canopen\"");
        assert!(t.contains("canopen"));
        match Platform::from_toml_str(&t) {
            Err(ConfigError::Parse(m)) => {
                assert!(m.contains("native") && m.contains("cia402"), "{m}")
            }
            other => panic!("{other:?}"),
        }
    }

    #[test]
    fn a_rest_angle_outside_the_steering_range_is_refused() {
        let mut p = Platform::three_wheel();
        p.protocol = Protocol::Cia402;
        let mut c = p.cia402();
        c.wheels[1].rest_angle_rad = 175f64.to_radians();
        p.cia402 = Some(c);
        assert_eq!(err_field(&p), "cia402.wheels[1].rest_angle_rad");
        let m = p.validate().unwrap_err().to_string();
        assert!(
            m.contains("steer_range") && m.contains("after homing"),
            "{m}"
        );
    }

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
    fn the_cycle_rate_is_bounded_by_the_timing_design() {
        let msg = |hz: f64| {
            let mut p = Platform::justin();
            p.cycle_hz = hz;
            match p.validate() {
                Err(ConfigError::Invalid {
                    field,
                    value,
                    reason,
                }) => {
                    format!("{field} = {value}: {reason}")
                }
                other => panic!("cycle_hz = {hz} accepted: {other:?}"),
            }
        };
        // Far too slow: the controller would not run a cycle before the modules' watchdog.
        let m = msg(0.001);
        assert!(
            m.starts_with("cycle_hz = 0.001: must be at least 80 Hz"),
            "{m}"
        );
        assert!(m.contains("50 ms") && m.contains("watchdog"), "{m}");
        // 10 Hz: one SETPOINT per 100 ms trips the 50 ms watchdog at once.
        assert!(msg(10.0).contains("at least 80 Hz"));
        assert!(msg(79.9).contains("at least 80 Hz"));
        let m = msg(1000.0);
        assert!(
            m.contains("at most 333 Hz") && m.contains("feedback window"),
            "{m}"
        );
        assert!(msg(1e300).starts_with("cycle_hz = 1e300"), "{}", msg(1e300));
        for ok in [MIN_CYCLE_HZ, 100.0, 250.0, 333.0] {
            let mut p = Platform::justin();
            p.cycle_hz = ok;
            p.validate().unwrap();
        }
        // The CiA 402 drives' RPDO deadline must span 4 cycles at the platform's rate.
        let mut p = Platform::justin();
        p.protocol = Protocol::Cia402;
        p.cycle_hz = 80.0;
        let mut c = Cia402Config::for_wheels(4);
        c.rpdo_timeout_ms = 49;
        p.cia402 = Some(c);
        assert_eq!(err_field(&p), "cia402.rpdo_timeout_ms");
        p.cia402.as_mut().unwrap().rpdo_timeout_ms = 50;
        p.validate().unwrap();
    }

    #[test]
    fn tiny_values_are_printed_readably() {
        let mut p = Platform::justin();
        p.limits.leg_speed = -1e-300;
        let m = p.validate().unwrap_err().to_string();
        assert!(m.contains("= -1e-300:"), "{m}");
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

    #[test]
    fn the_examples_are_valid_and_round_trip() {
        for name in EXAMPLE_NAMES {
            let p = Platform::example(name).unwrap();
            p.validate().unwrap();
            let text = p.to_toml_string();
            assert_eq!(Platform::from_toml_str(&text).unwrap(), p, "{name}");
            let mut c = p.clone();
            c.protocol = Protocol::Cia402;
            c.validate().unwrap();
            c.cia402 = Some(c.cia402());
            assert_eq!(Platform::from_toml_str(&c.to_toml_string()).unwrap(), c);
        }
        assert!(Platform::example("nope").is_none());
        let m = Platform::mpo700();
        assert!(!m.has_legs() && m.has_caster_offset() && m.buses() == 1);
        let s = Platform::six_wheel();
        assert_eq!((s.n(), s.buses(), s.n_legs()), (6, 2, 6));
        assert_eq!(s.wheels_on_bus(1).collect::<Vec<_>>(), vec![3, 4, 5]);
        // A fixed wheel is written with `lambda` only.
        let t = Platform::three_wheel().to_toml_string();
        assert!(
            t.contains("lambda = 0.3") && !t.contains("lambda_min"),
            "{t}"
        );
        // Without a leg the CiA 402 default has no leg encoder.
        assert!(Platform::three_wheel()
            .cia402()
            .wheels
            .iter()
            .all(|w| w.leg_node == 0));
    }

    fn err_of(text: &str) -> (String, String) {
        match Platform::from_toml_str(text) {
            Err(ConfigError::Invalid { field, reason, .. }) => (field, reason),
            other => panic!("expected Invalid, got {other:?}"),
        }
    }

    #[test]
    fn every_new_wheel_field_is_explained() {
        let base = Platform::three_wheel().to_toml_string();
        let legged = Platform::justin().to_toml_string();
        let cases: Vec<(String, &str, &str)> = vec![
            // A fixed wheel that also gives a leg range.
            (
                base.replacen("lambda = 0.3\n", "lambda = 0.3\nlambda_max = 0.5\n", 1),
                "wheels[0].lambda_max",
                "remove lambda_min",
            ),
            // A wheel on a leg missing part of its range.
            (
                legged.replacen("lambda_nominal = 0.465\n", "", 1),
                "wheels[0].lambda_nominal",
                "gives only `lambda`",
            ),
            (
                base.replacen("lambda = 0.3\n", "lambda = -0.3\n", 1),
                "wheels[0].lambda",
                "distance from the body origin",
            ),
            (
                base.replacen("caster_offset = 0.0", "caster_offset = -0.01", 1),
                "wheels[0].caster_offset",
                "trailing caster",
            ),
            (
                base.replacen("caster_offset = 0.0", "caster_offset = 0.31", 1),
                "wheels[0].caster_offset",
                "across the body origin",
            ),
            (
                base.replacen("-2.9670597283903604", "1.0", 1),
                "wheels[0].steer_range",
                "half a turn",
            ),
            (
                base.replacen("-2.9670597283903604", "-30.0", 1),
                "wheels[0].steer_range",
                "three turns",
            ),
            (
                base.replacen("bus = 0", "bus = 2", 1),
                "wheels[0].bus",
                "at most 2 buses",
            ),
            (
                base.replace("bus = 0", "bus = 1"),
                "wheels[0].bus",
                "number the buses from 0",
            ),
            (
                base.replacen("drive_polarity = 1", "drive_polarity = 0", 1),
                "wheels[0].drive_polarity",
                "mirrored",
            ),
            (
                base.replacen("steer_polarity = 1", "steer_polarity = 2", 1),
                "wheels[0].steer_polarity",
                "mirrored",
            ),
            (
                base.replacen("coupling = 0.0", "coupling = 11.0", 1),
                "wheels[0].coupling",
                "wheel turns per steering turn",
            ),
        ];
        for (text, field, hint) in cases {
            let (f, reason) = err_of(&text);
            assert_eq!(f, field, "{reason}");
            assert!(reason.contains(hint), "{field}: {reason}");
        }
        // CiA 402: a wheel without a leg has no leg encoder, a wheel on a leg has one.
        let mut p = Platform::three_wheel();
        p.protocol = Protocol::Cia402;
        let mut c = p.cia402();
        c.wheels[1].leg_node = 20;
        p.cia402 = Some(c);
        assert_eq!(err_field(&p), "cia402.wheels[1].leg_node");
        let mut p = Platform::justin();
        p.protocol = Protocol::Cia402;
        let mut c = p.cia402();
        c.wheels[2].leg_node = 0;
        p.cia402 = Some(c);
        assert_eq!(err_field(&p), "cia402.wheels[2].leg_node");
    }
}
