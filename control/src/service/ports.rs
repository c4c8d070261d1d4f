//! The base service's ports: what goes into the cycle (motion commands and operator
//! requests) and what comes out of it (the platform's state), as plain `Copy` values.
//!
//! ```text
//!  sources (JSON lines, keyboard, ROS 2)              cycle core (250 Hz)
//!  ───────────────────────────────────── CommandEvent ──► CommandPort ──► shaper ─► …
//!                                                                         │
//!  consumers (ROS 2, recorder, status line) ◄── BaseState (bounded) ◄─────┘
//! ```
//!
//! Both directions cross threads over bounded channels owned by the IO layer: the cycle takes
//! whatever commands are waiting without blocking and hands its state over with `try_send`,
//! so neither a slow consumer nor a silent source can delay a cycle. Everything here is
//! fixed-size: building, sending and receiving these values never allocates.
//!
//! Frames and units follow ROS REP 103: the body twist is in the base frame (x forward, y
//! left, z up; m/s and rad/s), the pose in the odometry frame (m, rad).

use crate::supervisor::{FaultReason, SupervisorState};
use crate::types::{Pose, Twist, MAX_WHEELS};

/// Leg extension targets, one per wheel (m), in controller order.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct LegTargets {
    /// Number of legs given (must equal the platform's wheel count).
    pub n: usize,
    /// Target extension λ_i (m); entries past `n` are unused.
    pub lambda: [f64; MAX_WHEELS],
}

impl LegTargets {
    /// Targets from a slice (at most [`MAX_WHEELS`] are kept; `n` records how many were given).
    pub fn from_slice(legs: &[f64]) -> Self {
        let mut lambda = [0.0; MAX_WHEELS];
        for (d, s) in lambda.iter_mut().zip(legs) {
            *d = *s;
        }
        Self {
            n: legs.len(),
            lambda,
        }
    }

    /// The given targets.
    pub fn as_slice(&self) -> &[f64] {
        &self.lambda[..self.n.min(MAX_WHEELS)]
    }
}

/// A live motion command: a body twist to hold until the next command, and optionally where
/// the legs should go.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct MotionCommand {
    /// Body twist in the base frame: vx, vy (m/s), omega (rad/s).
    pub twist: Twist,
    /// Leg extension targets; `None` keeps the legs' current targets.
    pub legs: Option<LegTargets>,
}

/// What a command source can ask of the cycle.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum CommandKind {
    /// Follow this motion command (until the next one or the command timeout).
    Motion(MotionCommand),
    /// Only move the legs (the twist keeps its last command and timeout).
    Legs(LegTargets),
    /// Controlled stop; the platform holds until re-armed.
    Stop,
    /// Clear latched faults whose cause is gone and follow commands again.
    Rearm,
    /// The source has no more commands (end of a command file, EOF on stdin): the command
    /// timeout stops the platform and the run ends once it is at rest.
    EndOfStream,
    /// Controlled stop, then the run ends (SIGINT, SIGTERM, a ROS 2 shutdown).
    Shutdown,
}

/// A command with the time it was received (s, on the run's time base: seconds since the
/// driver was ready).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct CommandEvent {
    /// Receive time (s).
    pub t: f64,
    /// What is asked.
    pub kind: CommandKind,
}

/// Odometry: pose in the odometry frame, body twist, and their covariances.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct OdometryState {
    /// Pose (x, y, θ) of the base in the odometry frame (m, m, rad; θ not wrapped).
    pub pose: Pose,
    /// Body twist (vx, vy, ω) in the base frame.
    pub twist: Twist,
    /// Covariance of (x, y, θ), row-major (m², m·rad, rad²).
    pub pose_covariance: [[f64; 3]; 3],
    /// Covariance of (vx, vy, ω), row-major.
    pub twist_covariance: [[f64; 3]; 3],
}

/// One wheel module's joints.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct JointState {
    /// Steering angle φ (rad, wrapped to (−π, π]).
    pub steer_angle: f64,
    /// Steering rate φ̇ (rad/s).
    pub steer_rate: f64,
    /// Wheel rotation angle (rad), integrated from the measured wheel speed since start.
    pub wheel_angle: f64,
    /// Wheel spin rate (rad/s).
    pub wheel_speed: f64,
    /// Leg extension λ (m).
    pub leg: f64,
    /// Leg extension rate λ̇ (m/s).
    pub leg_rate: f64,
    /// The wheel has no leg (a fixed footprint, `wheels[i].leg = false`): `leg` is its fixed
    /// distance, `leg_rate` 0, and it has no leg joint (ROS 2 `joint_states` leaves it out).
    pub no_leg: bool,
}

/// EMCY messages kept per wheel in its diagnostics (CiA 402).
pub const EMCY_KEPT: usize = 4;

/// One EMCY from a device of a wheel (CiA 402), as kept in the diagnostics.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct EmcyEntry {
    /// Node-ID of the device.
    pub node: u8,
    /// Error code (0: none, or the error reset).
    pub code: u16,
    /// Error register (0: informational).
    pub register: u8,
    /// Receive time (ms on the run's time base).
    pub at_ms: u64,
}

/// Receive-path and safety counters of one wheel module (or, with CiA 402, of the devices of
/// one wheel), cumulative since start.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct ModuleDiagnostics {
    /// The wheel's CAN node (native) or its rolling drive's node-ID (CiA 402).
    pub node: u8,
    /// Frames from the module rejected by the receive path (CRC, counter, DLC, range …).
    pub rejected: u64,
    /// Cycles in which the module's feedback arrived after the feedback window.
    pub late: u64,
    /// Frames known lost (gaps in the rolling counter).
    pub lost: u64,
    /// Times the module reported its setpoint watchdog tripped.
    pub watchdog_trips: u64,
    /// Cycles since the module's last valid feedback.
    pub age_cycles: u32,
    /// Module state from STATUS (wire value; 255 = unknown).
    pub state: u8,
    /// CiA 402: informational EMCYs of the wheel's devices (logged and counted, not faults).
    pub emcy_informational: u32,
    /// CiA 402: EMCYs of the wheel's devices that were faults.
    pub emcy_faults: u32,
    /// CiA 402: the last EMCYs of the wheel's devices, newest first (code 0 = empty slot
    /// unless `at_ms` is set: an error reset).
    pub emcy: [EmcyEntry; EMCY_KEPT],
}

/// The CAN controller of one bus, as its error frames report it (SocketCAN, socketcand, the
/// virtual bus): the current error state and how often each state change was seen.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct CanBusDiagnostics {
    /// The last error state reported (`None`: error active, nothing reported yet; after a
    /// restart `Some(Restarted)`).
    pub state: Option<rollbase_driver::bus::BusEvent>,
    /// State changes seen, per kind ([`rollbase_driver::bus::BusEvent::index`]: warning,
    /// error passive, active, bus-off, restarted, controller problem). A repeated report of
    /// the state the controller is already in is not counted.
    pub events: [u32; 6],
}

impl CanBusDiagnostics {
    /// Times the given kind of state change was seen.
    pub fn count(&self, e: rollbase_driver::bus::BusEvent) -> u32 {
        self.events[e.index()]
    }
}

/// Diagnostics of the bus and the modules.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct Diagnostics {
    /// Per wheel, in controller order (first `n` valid).
    pub modules: [ModuleDiagnostics; MAX_WHEELS],
    /// Measured bus load over the last second: frame bits (worst-case stuffing) seen on the
    /// bus per second over the bit rate (0..1+); with two buses, the busier one's.
    pub bus_load: f64,
    /// The same per bus (`wheels[i].bus`; entries past the platform's buses are 0).
    pub bus_loads: [f64; crate::model::platform::MAX_BUSES],
    /// Cycles whose control step finished after the next cycle's deadline (real time).
    pub deadline_misses: u64,
    /// Per bus (`wheels[i].bus`), its CAN controller's error state and state changes.
    pub can: [CanBusDiagnostics; crate::model::platform::MAX_BUSES],
}

/// Why the shaper is moving slower than commanded, if it is.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum Limiting {
    /// Nothing: the command is executed as given.
    #[default]
    None,
    /// A wheel's spin rate limit (`limits.wheel_speed`).
    WheelSpeed,
    /// A wheel's spin acceleration limit (`limits.wheel_accel`).
    WheelAccel,
    /// A steering rate limit (`limits.steer_rate`).
    SteerRate,
    /// A steering acceleration limit (`limits.steer_accel`).
    SteerAccel,
    /// A leg speed limit (`limits.leg_speed`).
    LegSpeed,
    /// The wheels are steering to a new direction before rolling (align-first).
    Aligning,
    /// No valid command for longer than the command timeout: stopping.
    Timeout,
    /// A stop was requested (SIGINT/SIGTERM, `~/stop`, the end of the command stream):
    /// stopping, then holding until re-armed.
    Stop,
}

impl Limiting {
    /// Short lower-case name, for status lines and diagnostics.
    pub fn name(self) -> &'static str {
        match self {
            Self::None => "none",
            Self::WheelSpeed => "wheel speed",
            Self::WheelAccel => "wheel acceleration",
            Self::SteerRate => "steering rate",
            Self::SteerAccel => "steering acceleration",
            Self::LegSpeed => "leg speed",
            Self::Aligning => "aligning",
            Self::Timeout => "command timeout",
            Self::Stop => "stop request",
        }
    }
}

/// Command-port counters, cumulative since start.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct CommandStats {
    /// Commands accepted.
    pub accepted: u64,
    /// Commands rejected (NaN, inf, beyond the sanity bound, wrong leg count, leg target out
    /// of range).
    pub rejected: u64,
    /// Times the command timeout expired while a non-zero command was held.
    pub timeouts: u64,
    /// Valid commands not followed because the platform was not following commands
    /// (stopped, in fault or not yet armed: re-arm first).
    pub ignored: u64,
    /// Why the last rejected command was rejected.
    pub last_rejection: Option<Rejection>,
    /// Motion commands dropped before the cycle saw them because the command queue was
    /// full (a source sending faster than the cycle takes them); set by the real-time
    /// driver from its command channel ([`crate::runtime::command_channel`](mod@crate::runtime::command_channel)).
    pub dropped: u64,
}

/// What the shaper is doing with the live command.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct ShapingState {
    /// The twist last commanded (base frame), after validation.
    pub commanded: Twist,
    /// Speed scale applied to the commanded twist (1 = as commanded, 0 = stopped).
    pub scale: f64,
    /// What limits the motion now.
    pub limiting: Limiting,
}

/// The platform's state as the cycle leaves it: one value per cycle on the state port.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct BaseState {
    /// Cycle index from 0.
    pub cycle: u64,
    /// Cycle time (s since the driver was ready).
    pub t: f64,
    /// Log time (ns; Unix time in real time, virtual in lockstep).
    pub log_time_ns: u64,
    /// Number of wheels.
    pub n: usize,
    /// Odometry.
    pub odometry: OdometryState,
    /// Joints per wheel (first `n` valid).
    pub joints: [JointState; MAX_WHEELS],
    /// Supervisor state.
    pub state: SupervisorState,
    /// Why the supervisor is in Fault (or stopped), if it is.
    pub reason: Option<FaultReason>,
    /// Bus and module diagnostics.
    pub diagnostics: Diagnostics,
    /// Command-port counters.
    pub commands: CommandStats,
    /// What the shaper does with the live command.
    pub shaping: ShapingState,
}

impl Default for BaseState {
    fn default() -> Self {
        Self {
            cycle: 0,
            t: 0.0,
            log_time_ns: 0,
            n: 0,
            odometry: OdometryState::default(),
            joints: [JointState::default(); MAX_WHEELS],
            state: SupervisorState::Idle,
            reason: None,
            diagnostics: Diagnostics::default(),
            commands: CommandStats::default(),
            shaping: ShapingState::default(),
        }
    }
}

/// Why a command was rejected (the checks are in [`crate::service::command`]).
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
