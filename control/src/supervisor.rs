//! Supervisor: the state machine that decides what the platform is allowed to do each cycle.
//!
//! ```text
//!            arm               aligned               trajectory done
//!   Idle ──────────► Aligning ─────────► Tracking ─────────────────► Stopping ──► Stopped
//!     │                 │                   │          stop request     ▲   (all wheels at rest)
//!     │                 └───────────────────┴───────────────────────────┘
//!     └──── any fault (from any state) ──► Fault  (controlled stop, latched until re-armed)
//! ```
//!
//! Faults: feedback from a module stale for more than [`SupervisorConfig::stale_cycles`]
//! cycles, a module reporting a fault in STATUS, a limit breach (a measured wheel speed or
//! steering rate beyond the configured limit by more than the margin, or a non-finite value),
//! a bus error, a slip residual above threshold for several cycles, a following error (a drive
//! that does not do what it is told, below), an alignment timeout, or a trajectory run that
//! ends away from its goal ([`FaultReason::NotArrived`]).
//!
//! # Following error
//!
//! Modelled on the CiA 402 following-error supervision (CiA 402 / IEC 61800-7-201 objects
//! 0x6065 *following error window*: "the configured range of tolerated position values
//! symmetrically to the position demand value … A following error may occur when a drive is
//! blocked, unreachable profile velocity occurs, or at wrong closed-loop coefficients", and
//! 0x6066 *following error time out*: "the configured time for a following error condition",
//! in ms; e.g. <https://infosys.beckhoff.com/content/1033/ax8xxx_object/11604836363.html> and
//! <https://infosys.beckhoff.com/content/1033/amp8000_object/18779988235.html>), applied to the
//! quantities this controller commands: each wheel's spin rate and steering rate, for every
//! wire profile (the check sees commands and measurements, not frames).
//!
//! A velocity-controlled drive does not reproduce its command at once: the command takes a
//! cycle (two with CiA 402's synchronous RPDOs) to reach it, its velocity loop lags with a
//! time constant T (20 ms drive, 15 ms steering in `rollbase-vcan-sim`'s plant) and its torque
//! limits its acceleration (≈ 110 rad/s² rolling, 56 rad/s² steering). All three only delay
//! the response, so the measured value of a healthy drive stays within the range of what was
//! commanded over the last [`SupervisorConfig::follow_lag`] (0.1 s: the transport delay, 3 T
//! for the lag to settle to 5 %, and the ramp of a command step at the torque limit). The
//! "demand" of 0x6065 is therefore that range, widened by a window that scales with the
//! command: `window = follow_*_window + follow_window_rel · |command|` (0.5 rad/s / 0.3 rad/s
//! plus 25 %: noise, quantization and the lag's residue stay far inside, a drive realising
//! half its command or nothing at all does not). A measurement outside the widened range for
//! longer than [`SupervisorConfig::follow_timeout`] (0x6066; 0.2 s) is a
//! [`FaultReason::FollowingError`] naming the wheel, the drive's node, the quantity, commanded
//! and measured values and how long. It is checked only once the wheel has reported its drives
//! enabled (STATUS Enabled, or both CiA 402 drives in Operation enabled) for longer than the
//! lag (a drive just enabled is still on its way to its command); a cycle whose command
//! disabled or braked the wheel enters the range as 0 (its drives are going to rest). An
//! infinite timeout switches the check off (as 0xFFFFFFFF does for 0x6065).
//!
//! A controlled stop ([`stop_command`]) decelerates every wheel from its last commanded speed
//! toward zero at the wheel acceleration limit, all wheels scaled together so the platform keeps
//! its direction of travel while slowing, with steering held (zero steering rate). In Fault the
//! same ramp is used; once all wheels are at rest the command is zero with the drives disabled.
//!
//! The supervisor is pure: inputs in, decision out; time is the cycle index.

use crate::estimation::odometry::SlipSuspect;
use crate::model::platform::Platform;
use crate::num::{Fixed3, Num};
use crate::types::{Command, MAX_WHEELS};
use rollbase_driver::canopen::config::Role;
use rollbase_driver::canopen::master::DeviceFault;

/// Supervisor states (DESIGN.md "The 250 Hz cycle").
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum SupervisorState {
    /// Not armed: drives disabled, zero setpoints.
    Idle,
    /// Open-loop phase: steer the wheels to the reference's initial angles, no rolling.
    Aligning,
    /// Closed-loop tracking of the reference.
    Tracking,
    /// Controlled stop in progress (end of trajectory or operator request).
    Stopping,
    /// At rest after a normal stop.
    Stopped,
    /// A fault was detected: controlled stop, then held until re-armed.
    Fault,
}

impl SupervisorState {
    /// Lower-case name, as recorded and printed.
    pub fn name(self) -> &'static str {
        match self {
            Self::Idle => "idle",
            Self::Aligning => "aligning",
            Self::Tracking => "tracking",
            Self::Stopping => "stopping",
            Self::Stopped => "stopped",
            Self::Fault => "fault",
        }
    }
}

/// Why the supervisor entered [`SupervisorState::Fault`] (or stopped).
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum FaultReason {
    /// No valid feedback from a module for `cycles` cycles.
    StaleFeedback {
        /// Wheel index (0-based, controller order).
        wheel: usize,
        /// CAN node of that wheel.
        node: u8,
        /// Cycles since its last valid feedback.
        cycles: u32,
    },
    /// A module reported a fault in its STATUS frame.
    ModuleFault {
        /// Wheel index.
        wheel: usize,
        /// CAN node.
        node: u8,
        /// Fault code from STATUS.
        code: u8,
    },
    /// A CANopen device of a wheel (CiA 402 profile) reported a fault, stopped answering,
    /// left operational or could not be booted.
    DeviceFault {
        /// Wheel index.
        wheel: usize,
        /// Node-ID of the device.
        node: u8,
        /// Which device of the wheel.
        role: Role,
        /// What happened.
        fault: DeviceFault,
    },
    /// A measured or commanded quantity exceeded its limit.
    LimitBreach {
        /// Wheel index.
        wheel: usize,
        /// What was breached.
        what: LimitKind,
        /// The value seen.
        value: f64,
        /// The limit (including margin).
        limit: f64,
    },
    /// The bus reported an error (interface down, socket error).
    BusError,
    /// The controller's CAN interface on this bus (`wheels[i].bus`) went bus-off.
    BusOff {
        /// The bus index.
        bus: u8,
    },
    /// The odometry slip residual stayed above threshold.
    Slip {
        /// Residual (m/s).
        residual: f64,
        /// The wheel the residual most likely comes from, that cycle (leave-one-out fit,
        /// [`crate::estimation::odometry`], "Which wheel slips").
        suspect: Option<SlipSuspect>,
        /// The drive that has been outside its following window longest as the fault is
        /// raised, if any, as (wheel, quantity, seconds): a held wheel drags the others
        /// along, so every wheel slips and no single one explains the residual, but its
        /// drive is the one not following (the following error itself needs its timeout).
        behind: Option<(usize, FollowQuantity, f64)>,
    },
    /// The wheels did not reach their initial angles in time.
    AlignmentTimeout {
        /// Largest remaining angle error (rad).
        error: f64,
    },
    /// The controller hit singularity A or produced non-finite output.
    ControllerSingular,
    /// A steering encoder's angle changed by more than its own measured steering rate can
    /// explain between two consecutive readings (a jump: slipped encoder, bad reading).
    EncoderJump {
        /// Wheel index.
        wheel: usize,
        /// CAN node.
        node: u8,
        /// Unexplained angle change (rad).
        jump: f64,
    },
    /// A drive does not follow its command: the measured value stayed outside the window
    /// around what was commanded for longer than the timeout (module docs).
    FollowingError {
        /// Wheel index.
        wheel: usize,
        /// CAN node of the drive (native: the wheel module; CiA 402: the rolling or steering
        /// drive).
        node: u8,
        /// Which quantity.
        quantity: FollowQuantity,
        /// The latest command (rad/s).
        commanded: f64,
        /// The measured value (rad/s).
        measured: f64,
        /// The window around the recent commands it is outside of (rad/s).
        window: f64,
        /// How long it has been outside (s).
        duration: f64,
    },
    /// A trajectory run ended (the trajectory done, the platform at rest) with the estimated
    /// pose or a leg farther from the trajectory's goal than the arrival tolerances.
    NotArrived {
        /// Distance of the estimated position from the goal (m).
        distance: f64,
        /// Heading difference to the goal (rad).
        heading: f64,
        /// The wheel whose leg is farthest from its goal extension.
        leg_wheel: usize,
        /// That leg's difference (m).
        leg_error: f64,
    },
    /// The platform is not where the trajectory starts: a leg differs from the trajectory's
    /// initial extension by more than the tolerance, so tracking is refused.
    StartMismatch {
        /// Wheel index.
        wheel: usize,
        /// CAN node.
        node: u8,
        /// Measured leg extension (m).
        measured: f64,
        /// The trajectory's initial leg extension (m).
        expected: f64,
    },
}

/// Which commanded quantity a [`FaultReason::FollowingError`] is about.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum FollowQuantity {
    /// The wheel's spin rate (the rolling drive).
    WheelSpeed,
    /// The steering rate (the steering drive).
    SteerRate,
}

impl std::fmt::Display for FollowQuantity {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            Self::WheelSpeed => "wheel speed",
            Self::SteerRate => "steering rate",
        })
    }
}

impl FaultReason {
    /// The one wheel a slip fault names: its leave-one-out suspect, where the other wheels
    /// agree among themselves ([`SLIP_SINGLE_WHEEL`]). `None` for any other fault, and for a
    /// slip no single wheel explains.
    pub fn slip_wheel(&self) -> Option<usize> {
        match *self {
            Self::Slip {
                suspect: Some(s), ..
            } if s.others <= SLIP_SINGLE_WHEEL * s.off => Some(s.wheel),
            _ => None,
        }
    }

    /// The wheel a slip fault tells the operator to check first: the one it names
    /// ([`FaultReason::slip_wheel`]), else the one whose drive has been outside its following
    /// window longest. `None` for any other fault, and for a slip that points at no wheel.
    pub fn slip_lead(&self) -> Option<usize> {
        match *self {
            Self::Slip { behind, .. } => self.slip_wheel().or(behind.map(|b| b.0)),
            _ => None,
        }
    }
}

/// Which limit a [`FaultReason::LimitBreach`] refers to.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum LimitKind {
    /// Wheel spin rate (rad/s).
    WheelSpeed,
    /// Steering rate (rad/s).
    SteerRate,
    /// A non-finite measurement.
    NonFinite,
}

impl std::fmt::Display for FaultReason {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match *self {
            Self::StaleFeedback {
                wheel,
                node,
                cycles,
            } => write!(
                f,
                "stale feedback: wheel {} (node {node}) sent no valid feedback for {cycles} cycles",
                wheel + 1
            ),
            Self::ModuleFault { wheel, node, code } => write!(
                f,
                "module fault: wheel {} (node {node}) reports fault code {code}",
                wheel + 1
            ),
            Self::DeviceFault {
                wheel,
                node,
                role,
                fault,
            } => write!(
                f,
                "device fault: wheel {} {role} (node {node}): {fault}",
                wheel + 1
            ),
            Self::LimitBreach {
                wheel,
                what,
                value,
                limit,
            } => write!(
                f,
                "limit breach: wheel {} {what:?} = {value:.4} beyond {limit:.4}",
                wheel + 1
            ),
            Self::BusError => write!(f, "bus error: the CAN interface reported an error"),
            Self::BusOff { bus } => write!(
                f,
                "bus-off: the controller's CAN interface on bus {bus} went bus-off (too many \
                 transmit errors); check the wiring and connectors, the termination (120 ohm \
                 at both ends only), the bit rate of every node, and for a node that babbles \
                 (a device sending error frames or flooding the bus); the drives stopped on \
                 their communication-loss reaction; re-arm once the bus is back (the devices \
                 are booted again)"
            ),
            Self::Slip {
                residual,
                suspect,
                behind,
            } => {
                write!(
                    f,
                    "wheel slip: odometry residual {residual:.4} m/s above threshold (the \
                     wheels' measured velocities disagree)"
                )?;
                match suspect {
                    Some(s) if self.slip_wheel().is_some() => write!(
                        f,
                        "; wheel {w} moves {off:.3} m/s off what the other wheels give it \
                         (they agree to {others:.3} m/s among themselves): wheel {w} slipping \
                         or held, its leg against an end stop, or its drives not following \
                         their commands; check wheel {w}'s tyre and the floor under it, its \
                         leg and its drives, then re-arm",
                        w = s.wheel + 1,
                        off = s.off,
                        others = s.others
                    ),
                    _ => {
                        match suspect {
                            Some(s) => write!(
                                f,
                                "; no single wheel explains it (without any one of them the \
                                 others still disagree by {others:.3} m/s or more): several \
                                 wheels slipping, a drive not following its command while the \
                                 others drag its wheel, or a leg against its end stop",
                                others = s.others
                            )?,
                            None => write!(
                                f,
                                ": a wheel slipping or held, a leg against its end stop, or a \
                                 drive not following its command"
                            )?,
                        }
                        if let Some((w, q, t)) = behind {
                            write!(
                                f,
                                "; wheel {w}'s {q} has been outside its following window for \
                                 {ms:.0} ms: check wheel {w}'s drive first",
                                w = w + 1,
                                ms = t * 1e3
                            )?;
                        }
                        write!(
                            f,
                            "; check the wheels, the floor, the legs and the drives, then re-arm"
                        )
                    }
                }
            }
            Self::AlignmentTimeout { error } => write!(
                f,
                "alignment timeout: steering error still {:.2}°",
                error.to_degrees()
            ),
            Self::EncoderJump { wheel, node, jump } => write!(
                f,
                "encoder jump: wheel {} (node {node}) steering angle changed {:.2}° more than its measured steering rate explains; check the steering encoder",
                wheel + 1,
                jump.to_degrees()
            ),
            Self::FollowingError {
                wheel,
                node,
                quantity,
                commanded,
                measured,
                window,
                duration,
            } => write!(
                f,
                "following error: wheel {} (node {node}) {quantity} measured {} rad/s while {} rad/s was commanded, outside the window (±{} rad/s around the last commands) for {:.3} s; the drive does not follow its command: check the motor, its power stage, brake and velocity scaling",
                wheel + 1,
                Fixed3(measured),
                Fixed3(commanded),
                Fixed3(window),
                duration
            ),
            Self::NotArrived {
                distance,
                heading,
                leg_wheel,
                leg_error,
            } => write!(
                f,
                "did not arrive: the trajectory ended with the estimated pose {} m and {:.2}° from its goal and the leg of wheel {} {} mm from its goal extension (arrival tolerances in SupervisorConfig: arrive_position, arrive_heading, arrive_leg); the run failed",
                Fixed3(distance),
                heading.to_degrees(),
                leg_wheel + 1,
                Fixed3(leg_error * 1e3)
            ),
            Self::StartMismatch {
                wheel,
                node,
                measured,
                expected,
            } => write!(
                f,
                "start mismatch: wheel {} (node {node}) leg at {measured:.4} m but the trajectory starts at {expected:.4} m; move the legs or start the trajectory from the current configuration",
                wheel + 1
            ),
            Self::ControllerSingular => {
                write!(
                    f,
                    "controller singular: a wheel at rest (singularity A) or non-finite output"
                )
            }
        }
    }
}

/// Thresholds of the supervisor.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SupervisorConfig {
    /// A module that sent neither FEEDBACK_A nor FEEDBACK_B for more than this many cycles
    /// is silent: a fault (the issue: "more than 3 cycles").
    pub stale_cycles: u32,
    /// Either feedback stream of a module older than this many cycles is a fault even while
    /// the other stream still arrives: bounds the age of any value the controller uses
    /// (8 cycles = 32 ms at 250 Hz). Random loss of single frames (issue 8: 5 % loss) must
    /// not stop the platform, a module whose data is this old must.
    pub stale_data_cycles: u32,
    /// Alignment is complete when every wheel is within this angle of its target (rad).
    pub align_tolerance: f64,
    /// Alignment must complete within this many cycles.
    pub align_timeout_cycles: u32,
    /// Relative margin on measured speeds before a limit breach is declared (0.2 = 20 %).
    pub limit_margin: f64,
    /// Slip residual threshold (m/s).
    pub slip_threshold: f64,
    /// Cycles the slip residual must stay above threshold before it is a fault.
    pub slip_cycles: u32,
    /// Wheel speeds below this (rad/s) count as at rest.
    pub rest_speed: f64,
    /// Largest accepted difference between a measured leg and the trajectory's initial leg
    /// extension before tracking starts (m).
    pub start_leg_tolerance: f64,
    /// Largest steering-angle change between consecutive readings that the measured steering
    /// rates do not explain (rad). The trapezoid of the two rates predicts the change to within
    /// ½·φ̈·dt² (0.45 mrad at the 56 rad/s² torque limit) plus quantization and noise (≈0.5
    /// mrad); 0.02 rad leaves a margin of 20 and catches any real encoder jump.
    pub steer_jump_threshold: f64,
    /// Following error (module docs): the time a healthy drive may take to follow a command
    /// change (s). The measured value is compared with the range of the commands of this
    /// long. Default 0.1 s: one or two cycles of transport delay, 3 T = 60 ms for a 20 ms
    /// velocity loop to settle to 5 %, and a command step ramped at the torque limit. At most
    /// [`FOLLOW_HISTORY`] − 1 cycles.
    pub follow_lag: f64,
    /// Following-error window of the wheel spin rate, absolute part (rad/s). Default 0.5
    /// rad/s (0.04 m/s at the ground; encoder noise is 0.002 rad/s).
    pub follow_wheel_window: f64,
    /// Following-error window of the steering rate, absolute part (rad/s). Default 0.3 rad/s.
    pub follow_steer_window: f64,
    /// Following-error window, part proportional to the largest recent command (0.25 =
    /// 25 %): a drive realising half its command is outside it.
    pub follow_window_rel: f64,
    /// Following-error time out (s; the role of CiA 402's 0x6066): how long the measured
    /// value may stay outside the window before it is a fault. Default 0.2 s; infinite
    /// switches the check off.
    pub follow_timeout: f64,
    /// Arrival check at the end of a trajectory run: largest distance of the estimated
    /// position from the goal (m). Default 0.05 m, 10 × the seed-000 acceptance bound (5 mm);
    /// infinite switches the check off.
    pub arrive_position: f64,
    /// Arrival check: largest heading difference to the goal (rad). Default 5° (10 × 0.5°).
    pub arrive_heading: f64,
    /// Arrival check: largest difference of a leg from its goal extension (m). Default 0.02 m
    /// (10 × the 2 mm leg bound).
    pub arrive_leg: f64,
}

/// A slip fault names one wheel when the others, fitted without it, agree among themselves to
/// within this share of how far that wheel is off their fit: one wheel slipping leaves the
/// others consistent (their mismatch is the encoders' and the drives' lag, millimetres a
/// second), so the share is near zero; several wheels disagreeing leave it near one.
pub const SLIP_SINGLE_WHEEL: f64 = 0.25;

/// Commands remembered per wheel for the following-error check (cycles).
pub const FOLLOW_HISTORY: usize = 64;

impl Default for SupervisorConfig {
    fn default() -> Self {
        Self {
            stale_cycles: crate::model::platform::TOLERATED_LOST_CYCLES,
            stale_data_cycles: 8,
            align_tolerance: 0.5f64.to_radians(),
            align_timeout_cycles: 2500,
            limit_margin: 0.2,
            slip_threshold: 0.05,
            slip_cycles: 25,
            rest_speed: 0.02,
            start_leg_tolerance: 0.005,
            steer_jump_threshold: 0.02,
            follow_lag: 0.1,
            follow_wheel_window: 0.5,
            follow_steer_window: 0.3,
            follow_window_rel: 0.25,
            follow_timeout: 0.2,
            arrive_position: 0.05,
            arrive_heading: 5f64.to_radians(),
            arrive_leg: 0.02,
        }
    }
}

impl SupervisorConfig {
    /// Checks the thresholds that have a range, for a control period `dt` (s); the error
    /// names the field (`supervisor.follow_lag` …), the value and the range.
    pub fn validate(&self, dt: f64) -> Result<(), (&'static str, String, String)> {
        let bad = |field, v: f64, why: String| Err((field, Num(v).to_string(), why));
        let max_lag = (FOLLOW_HISTORY - 1) as f64 * dt;
        if !(self.follow_lag.is_finite()
            && self.follow_lag >= 2.0 * dt
            && self.follow_lag <= max_lag)
        {
            return bad(
                "supervisor.follow_lag",
                self.follow_lag,
                format!(
                    "must be between 2 control cycles ({} s) and {} cycles ({} s)",
                    Num(2.0 * dt),
                    FOLLOW_HISTORY - 1,
                    Num(max_lag)
                ),
            );
        }
        for (field, v) in [
            ("supervisor.follow_wheel_window", self.follow_wheel_window),
            ("supervisor.follow_steer_window", self.follow_steer_window),
        ] {
            if !(v.is_finite() && v > 0.0) {
                return bad(field, v, "must be a finite speed > 0 rad/s".into());
            }
        }
        if !(self.follow_window_rel.is_finite() && (0.0..1.0).contains(&self.follow_window_rel)) {
            return bad(
                "supervisor.follow_window_rel",
                self.follow_window_rel,
                "must be in [0, 1): a drive realising nothing must be outside the window".into(),
            );
        }
        if self.follow_timeout.is_nan() || self.follow_timeout < dt {
            return bad(
                "supervisor.follow_timeout",
                self.follow_timeout,
                format!(
                    "must be at least one control cycle ({} s), or infinite to switch the check off",
                    Num(dt)
                ),
            );
        }
        for (field, v) in [
            ("supervisor.arrive_position", self.arrive_position),
            ("supervisor.arrive_heading", self.arrive_heading),
            ("supervisor.arrive_leg", self.arrive_leg),
        ] {
            if v.is_nan() || v <= 0.0 {
                return bad(
                    field,
                    v,
                    "must be > 0, or infinite to switch the arrival check off".into(),
                );
            }
        }
        Ok(())
    }
}

/// The commands of the last [`FOLLOW_HISTORY`] cycles per wheel and quantity, and how long
/// each measurement has been outside its window (module docs, following error).
#[derive(Clone, Debug)]
struct FollowMonitor {
    /// Ring of commands: `[cycle][wheel][quantity]`, 0 for a cycle whose command disabled or
    /// braked the wheel's drives.
    cmd: [[[f64; 2]; MAX_WHEELS]; FOLLOW_HISTORY],
    /// Next slot to write.
    head: usize,
    /// Valid entries (up to FOLLOW_HISTORY).
    len: usize,
    /// Consecutive checked cycles outside the window, per wheel and quantity.
    outside: [[u32; 2]; MAX_WHEELS],
    /// Consecutive cycles each wheel has reported its drives enabled.
    enabled_for: [u32; MAX_WHEELS],
    /// Largest error / window and longest run outside seen since the arm (for reports).
    peak: FollowPeak,
}

/// The closest a run came to a following error, since the last arm: for reports and for the
/// margin of healthy runs.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct FollowPeak {
    /// Largest ratio of the following error to its window (a fault needs > 1 for longer
    /// than the timeout).
    pub ratio: f64,
    /// Longest time outside the window (s).
    pub outside_s: f64,
}

impl FollowMonitor {
    fn new() -> Self {
        Self {
            cmd: [[[0.0; 2]; MAX_WHEELS]; FOLLOW_HISTORY],
            head: 0,
            len: 0,
            outside: [[0; 2]; MAX_WHEELS],
            enabled_for: [0; MAX_WHEELS],
            peak: FollowPeak::default(),
        }
    }

    fn push(&mut self, cmd: &Command, enabled: &[bool; MAX_WHEELS]) {
        let slot = &mut self.cmd[self.head];
        for i in 0..MAX_WHEELS {
            let w = cmd.wheels[i];
            let on = i < cmd.n && enabled[i];
            let finite = |x: f64| if x.is_finite() { x } else { 0.0 };
            slot[i] = if on {
                [finite(w.wheel_speed), finite(w.steer_rate)]
            } else {
                [0.0; 2]
            };
        }
        self.head = (self.head + 1) % FOLLOW_HISTORY;
        self.len = (self.len + 1).min(FOLLOW_HISTORY);
    }

    /// The drive outside its following window for the most cycles in a row, among the first
    /// `n` wheels, as (wheel, quantity, seconds); `None` when every drive follows.
    fn behind(&self, n: usize, dt: f64) -> Option<(usize, FollowQuantity, f64)> {
        let mut best: Option<(usize, FollowQuantity, u32)> = None;
        for (i, out) in self.outside.iter().enumerate().take(n) {
            for (q, quantity) in [
                (0, FollowQuantity::WheelSpeed),
                (1, FollowQuantity::SteerRate),
            ] {
                if out[q] > 0 && best.is_none_or(|b| out[q] > b.2) {
                    best = Some((i, quantity, out[q]));
                }
            }
        }
        best.map(|(i, q, c)| (i, q, f64::from(c) * dt))
    }

    /// Range (min, max) of the last `k` commands of wheel `i`, quantity `q`, and the newest.
    fn range(&self, i: usize, q: usize, k: usize) -> (f64, f64, f64) {
        let k = k.min(self.len).max(1);
        let mut lo = f64::INFINITY;
        let mut hi = f64::NEG_INFINITY;
        for j in 1..=k {
            let v = self.cmd[(self.head + FOLLOW_HISTORY - j) % FOLLOW_HISTORY][i][q];
            lo = lo.min(v);
            hi = hi.max(v);
        }
        let newest = self.cmd[(self.head + FOLLOW_HISTORY - 1) % FOLLOW_HISTORY][i][q];
        (lo, hi, newest)
    }
}

/// What the supervisor sees each cycle.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct SupervisorInput {
    /// Cycles since each wheel's last valid feedback of any kind (0 = this cycle).
    pub feedback_age: [u32; MAX_WHEELS],
    /// Cycles since each wheel's older feedback stream was last received (the age of the
    /// oldest value the controller uses for that wheel).
    pub data_age: [u32; MAX_WHEELS],
    /// Fault code per wheel from its latest STATUS (`None` = no fault).
    pub module_fault: [Option<u8>; MAX_WHEELS],
    /// Per wheel, a latched fault of one of its CANopen devices as (node, role, fault).
    pub device_fault: [Option<(u8, Role, DeviceFault)>; MAX_WHEELS],
    /// Per wheel, the node of its oldest feedback stream (named by a stale-feedback fault);
    /// 0 = the wheel's node.
    pub stale_node: [u8; MAX_WHEELS],
    /// Measured wheel spin rates (rad/s).
    pub wheel_speed: [f64; MAX_WHEELS],
    /// Measured steering rates (rad/s).
    pub steer_rate: [f64; MAX_WHEELS],
    /// Largest steering error to the alignment targets (rad), meaningful while aligning;
    /// infinite until every module has reported.
    pub alignment_error: f64,
    /// Per wheel, the steering-angle change since the previous reading that the measured
    /// steering rates do not explain (rad); 0 when not checkable (no consecutive readings).
    pub steer_jump: [f64; MAX_WHEELS],
    /// The wheel whose leg differs most from the trajectory's initial extension, as
    /// (wheel, measured, expected); `None` until every module has reported.
    pub start_legs: Option<(usize, f64, f64)>,
    /// The reference trajectory is complete and the controller reports it has finished.
    pub trajectory_done: bool,
    /// The controller reported singularity A or non-finite output this cycle.
    pub controller_singular: bool,
    /// The bus reported an error this cycle.
    pub bus_error: bool,
    /// The controller's interface on this bus went bus-off (latched until re-armed).
    pub bus_off: Option<u8>,
    /// Odometry slip residual (m/s).
    pub slip_residual: f64,
    /// The wheel the residual most likely comes from
    /// ([`crate::estimation::odometry::Odometry::slip_suspect`]); the runtime fills it in
    /// only while the residual is above `slip_threshold`.
    pub slip_suspect: Option<SlipSuspect>,
    /// An operator stop was requested (Ctrl-C): controlled stop, not a fault.
    pub stop_requested: bool,
    /// Per wheel, whether its drives report enabled (native STATUS Enabled; CiA 402 both
    /// drives in Operation enabled): the following error is checked only then.
    pub enabled: [bool; MAX_WHEELS],
    /// While stopping at the end of a trajectory: the estimated pose's distance (m) and
    /// heading difference (rad) to the goal, and the leg farthest from its goal as (wheel,
    /// difference in m). `None` when not known.
    pub goal_error: Option<(f64, f64, usize, f64)>,
}

/// What the cycle should do this cycle.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Mode {
    /// Zero setpoints, drives disabled.
    Disabled,
    /// Steering-only alignment command.
    Align,
    /// Controller output.
    Track,
    /// Controlled deceleration from the last command.
    Decelerate,
    /// Zero setpoints with drives enabled and braking (at rest after a stop).
    Hold,
}

/// The supervisor state machine.
#[derive(Clone, Debug)]
pub struct Supervisor {
    cfg: SupervisorConfig,
    n: usize,
    nodes: [u8; MAX_WHEELS],
    steer_nodes: [u8; MAX_WHEELS],
    leg_nodes: [u8; MAX_WHEELS],
    state: SupervisorState,
    reason: Option<FaultReason>,
    cycles_in_state: u32,
    slip_count: u32,
    transitions: u32,
    drive_nodes: [u8; MAX_WHEELS],
    dt: f64,
    follow: FollowMonitor,
    /// The current stop was asked for by the end of the trajectory (arrival is checked).
    stopping_at_goal: bool,
}

impl Supervisor {
    /// A supervisor in Idle for the platform's wheels.
    pub fn new(p: &Platform, cfg: SupervisorConfig) -> Self {
        let mut nodes = [0u8; MAX_WHEELS];
        for (i, w) in p.wheels.iter().enumerate().take(MAX_WHEELS) {
            nodes[i] = w.node;
        }
        Self {
            cfg,
            n: p.n().min(MAX_WHEELS),
            nodes,
            steer_nodes: nodes,
            leg_nodes: nodes,
            state: SupervisorState::Idle,
            reason: None,
            cycles_in_state: 0,
            slip_count: 0,
            transitions: 0,
            drive_nodes: nodes,
            dt: p.dt(),
            follow: FollowMonitor::new(),
            stopping_at_goal: false,
        }
    }

    /// The nodes that deliver each wheel's steering angle and leg extension, when they are
    /// not the wheel's module (CiA 402: the steering drive and the leg encoder): encoder-jump
    /// and start-mismatch faults name them.
    pub fn set_stream_nodes(&mut self, steer: [u8; MAX_WHEELS], leg: [u8; MAX_WHEELS]) {
        self.steer_nodes = steer;
        self.leg_nodes = leg;
    }

    /// The nodes of each wheel's rolling drive, when it is not the wheel's module (CiA 402):
    /// following errors of the wheel speed name them.
    pub fn set_drive_nodes(&mut self, drive: [u8; MAX_WHEELS]) {
        self.drive_nodes = drive;
    }

    /// The closest the run came to a following error since the last arm.
    pub fn follow_peak(&self) -> FollowPeak {
        self.follow.peak
    }

    /// The command sent this cycle and which wheels it told to follow it (enabled, not
    /// braking; the others are going to rest): the history the following-error check compares
    /// the next measurements with. Call once per cycle after [`Supervisor::step`].
    pub fn note_command(&mut self, cmd: &Command, enabled: &[bool; MAX_WHEELS]) {
        self.follow.push(cmd, enabled);
    }

    /// Enters Fault for a reason found outside the cycle's checks (a device that cannot be
    /// booted), from any state; the first reason is kept until re-armed.
    pub fn fail(&mut self, reason: FaultReason) {
        self.fault(reason);
    }

    /// Replaces the latched device fault's details with newer ones of the same device and
    /// kind (CiA 402: the drive's error code, read back by SDO after the fault); the fault,
    /// its time and its cause stay.
    pub fn refine_device_fault(&mut self, wheel: usize, node: u8, fault: DeviceFault) {
        if let Some(FaultReason::DeviceFault {
            wheel: w,
            node: n,
            fault: f,
            ..
        }) = &mut self.reason
        {
            if *w == wheel
                && *n == node
                && std::mem::discriminant(f) == std::mem::discriminant(&fault)
            {
                *f = fault;
            }
        }
    }

    /// Current state.
    pub fn state(&self) -> SupervisorState {
        self.state
    }

    /// Why the last fault happened, if any.
    pub fn reason(&self) -> Option<FaultReason> {
        self.reason
    }

    /// Cycles spent in the current state.
    pub fn cycles_in_state(&self) -> u32 {
        self.cycles_in_state
    }

    /// The configuration.
    pub fn config(&self) -> &SupervisorConfig {
        &self.cfg
    }

    /// Arms the platform: from Idle, Stopped or Fault to Aligning (clears a latched fault).
    /// Returns false (and does nothing) in any other state.
    pub fn arm(&mut self) -> bool {
        match self.state {
            SupervisorState::Idle | SupervisorState::Stopped | SupervisorState::Fault => {
                self.reason = None;
                self.slip_count = 0;
                self.follow = FollowMonitor::new();
                self.stopping_at_goal = false;
                self.enter(SupervisorState::Aligning);
                true
            }
            _ => false,
        }
    }

    fn enter(&mut self, s: SupervisorState) {
        if s != self.state {
            self.state = s;
            self.cycles_in_state = 0;
            self.transitions += 1;
        }
    }

    fn fault(&mut self, reason: FaultReason) {
        if self.state != SupervisorState::Fault {
            self.reason = Some(reason);
            self.enter(SupervisorState::Fault);
        }
    }

    /// Checks the faults that apply in every active state; returns the first one found.
    fn detect_fault(&mut self, input: &SupervisorInput, p: &Platform) -> Option<FaultReason> {
        if let Some(bus) = input.bus_off {
            return Some(FaultReason::BusOff { bus });
        }
        if input.bus_error {
            return Some(FaultReason::BusError);
        }
        for i in 0..self.n {
            let node = match input.stale_node[i] {
                0 => self.nodes[i],
                n => n,
            };
            if input.feedback_age[i] > self.cfg.stale_cycles {
                return Some(FaultReason::StaleFeedback {
                    wheel: i,
                    node,
                    cycles: input.feedback_age[i],
                });
            }
            if input.data_age[i] > self.cfg.stale_data_cycles {
                return Some(FaultReason::StaleFeedback {
                    wheel: i,
                    node,
                    cycles: input.data_age[i],
                });
            }
        }
        for i in 0..self.n {
            if let Some(code) = input.module_fault[i] {
                return Some(FaultReason::ModuleFault {
                    wheel: i,
                    node: self.nodes[i],
                    code,
                });
            }
            if let Some((node, role, fault)) = input.device_fault[i] {
                return Some(FaultReason::DeviceFault {
                    wheel: i,
                    node,
                    role,
                    fault,
                });
            }
        }
        for i in 0..self.n {
            let j = input.steer_jump[i];
            if j.abs() > self.cfg.steer_jump_threshold {
                return Some(FaultReason::EncoderJump {
                    wheel: i,
                    node: self.steer_nodes[i],
                    jump: j,
                });
            }
        }
        let ws = p.limits.wheel_speed * (1.0 + self.cfg.limit_margin);
        let sr = p.limits.steer_rate * (1.0 + self.cfg.limit_margin);
        for i in 0..self.n {
            let (w, s) = (input.wheel_speed[i], input.steer_rate[i]);
            if !w.is_finite() || !s.is_finite() {
                return Some(FaultReason::LimitBreach {
                    wheel: i,
                    what: LimitKind::NonFinite,
                    value: if w.is_finite() { s } else { w },
                    limit: 0.0,
                });
            }
            if w.abs() > ws {
                return Some(FaultReason::LimitBreach {
                    wheel: i,
                    what: LimitKind::WheelSpeed,
                    value: w,
                    limit: ws,
                });
            }
            if s.abs() > sr {
                return Some(FaultReason::LimitBreach {
                    wheel: i,
                    what: LimitKind::SteerRate,
                    value: s,
                    limit: sr,
                });
            }
        }
        if input.slip_residual > self.cfg.slip_threshold {
            self.slip_count += 1;
            if self.slip_count >= self.cfg.slip_cycles {
                return Some(FaultReason::Slip {
                    residual: input.slip_residual,
                    suspect: input.slip_suspect,
                    behind: self.follow.behind(self.n, self.dt),
                });
            }
        } else {
            self.slip_count = 0;
        }
        self.check_following(input)
    }

    /// The following-error check (module docs): updates every counter, returns the first
    /// wheel and quantity outside its window for longer than the timeout.
    fn check_following(&mut self, input: &SupervisorInput) -> Option<FaultReason> {
        let c = &self.cfg;
        if c.follow_timeout.is_infinite() {
            return None;
        }
        let k = ((c.follow_lag / self.dt).ceil() as usize).clamp(1, FOLLOW_HISTORY);
        // Cycles outside before the timeout has passed (strictly more than the timeout).
        let limit = (c.follow_timeout / self.dt).round().max(1.0) as u32;
        let mut found = None;
        for i in 0..self.n {
            let on = &mut self.follow.enabled_for[i];
            *on = if input.enabled[i] {
                on.saturating_add(1)
            } else {
                0
            };
            // A drive enabled less than the lag ago may still be on its way to the command.
            let checked = *on as usize > k;
            for (q, measured, abs, quantity, node) in [
                (
                    0,
                    input.wheel_speed[i],
                    c.follow_wheel_window,
                    FollowQuantity::WheelSpeed,
                    self.drive_nodes[i],
                ),
                (
                    1,
                    input.steer_rate[i],
                    c.follow_steer_window,
                    FollowQuantity::SteerRate,
                    self.steer_nodes[i],
                ),
            ] {
                if !checked {
                    self.follow.outside[i][q] = 0;
                    continue;
                }
                let (lo, hi, newest) = self.follow.range(i, q, k);
                let window = abs + c.follow_window_rel * lo.abs().max(hi.abs());
                let error = (lo - measured).max(measured - hi).max(0.0);
                let n = &mut self.follow.outside[i][q];
                if error > window || !measured.is_finite() {
                    *n = n.saturating_add(1);
                } else {
                    *n = 0;
                }
                let peak = &mut self.follow.peak;
                peak.ratio = peak.ratio.max(error / window);
                peak.outside_s = peak.outside_s.max(f64::from(*n) * self.dt);
                if *n > limit && found.is_none() {
                    found = Some(FaultReason::FollowingError {
                        wheel: i,
                        node,
                        quantity,
                        commanded: newest,
                        measured,
                        window,
                        duration: f64::from(*n) * self.dt,
                    });
                }
            }
        }
        found
    }

    /// Advances one cycle. `at_rest` says whether the last command had every wheel stopped.
    pub fn step(&mut self, p: &Platform, input: &SupervisorInput, at_rest: bool) -> Mode {
        self.cycles_in_state = self.cycles_in_state.saturating_add(1);
        let active = matches!(
            self.state,
            SupervisorState::Aligning | SupervisorState::Tracking | SupervisorState::Stopping
        );
        if active {
            if let Some(r) = self.detect_fault(input, p) {
                self.fault(r);
            }
        }
        match self.state {
            SupervisorState::Idle => Mode::Disabled,
            SupervisorState::Aligning => {
                if input.stop_requested {
                    self.enter(SupervisorState::Stopping);
                    return Mode::Decelerate;
                }
                if let Some((wheel, measured, expected)) = input.start_legs {
                    let dev = (measured - expected).abs();
                    if dev.is_nan() || dev > self.cfg.start_leg_tolerance {
                        self.fault(FaultReason::StartMismatch {
                            wheel,
                            node: self.leg_nodes[wheel.min(MAX_WHEELS - 1)],
                            measured,
                            expected,
                        });
                        return Mode::Decelerate;
                    }
                }
                if input.alignment_error <= self.cfg.align_tolerance && input.start_legs.is_some() {
                    self.enter(SupervisorState::Tracking);
                    Mode::Track
                } else if self.cycles_in_state > self.cfg.align_timeout_cycles {
                    self.fault(FaultReason::AlignmentTimeout {
                        error: input.alignment_error,
                    });
                    Mode::Decelerate
                } else {
                    Mode::Align
                }
            }
            SupervisorState::Tracking => {
                if input.controller_singular {
                    self.fault(FaultReason::ControllerSingular);
                    return Mode::Decelerate;
                }
                if input.stop_requested || input.trajectory_done {
                    self.stopping_at_goal = !input.stop_requested;
                    self.enter(SupervisorState::Stopping);
                    return if at_rest {
                        Mode::Hold
                    } else {
                        Mode::Decelerate
                    };
                }
                Mode::Track
            }
            SupervisorState::Stopping => {
                if !at_rest {
                    return Mode::Decelerate;
                }
                if let (true, Some((distance, heading, leg_wheel, leg_error))) =
                    (self.stopping_at_goal, input.goal_error)
                {
                    let c = &self.cfg;
                    // NaN compares false: a non-finite estimate did not arrive either.
                    let arrived = distance <= c.arrive_position
                        && heading.abs() <= c.arrive_heading
                        && leg_error.abs() <= c.arrive_leg;
                    if !arrived {
                        self.fault(FaultReason::NotArrived {
                            distance,
                            heading,
                            leg_wheel,
                            leg_error,
                        });
                        return Mode::Hold;
                    }
                }
                self.enter(SupervisorState::Stopped);
                Mode::Hold
            }
            SupervisorState::Stopped => Mode::Hold,
            SupervisorState::Fault => {
                if at_rest {
                    Mode::Disabled
                } else {
                    Mode::Decelerate
                }
            }
        }
    }

    /// Number of state transitions so far.
    pub fn transitions(&self) -> u32 {
        self.transitions
    }
}

/// One cycle of a controlled stop: every wheel's speed moves toward zero by at most
/// `wheel_accel · dt`, all wheels scaled by the same factor so their ratios (and so the
/// platform's direction of motion and its ICR) are kept; steering rates are zero (held).
pub fn stop_command(p: &Platform, last: &Command, dt: f64) -> Command {
    let n = last.n.min(MAX_WHEELS);
    let mut peak = 0.0f64;
    for w in &last.wheels[..n] {
        if w.wheel_speed.is_finite() {
            peak = peak.max(w.wheel_speed.abs());
        }
    }
    let mut out = Command::zero(n);
    let step = p.limits.wheel_accel * dt;
    if peak <= step || !peak.is_finite() {
        return out;
    }
    let scale = (peak - step) / peak;
    for i in 0..n {
        let w = last.wheels[i].wheel_speed;
        out.wheels[i].wheel_speed = if w.is_finite() { w * scale } else { 0.0 };
    }
    out
}

/// One cycle of the base service's halt (command timeout, stop request while following
/// commands): the wheel speeds ramp down together like [`stop_command`] (the platform keeps
/// its direction of motion), and the steering rates ramp to zero within the steering
/// acceleration limit, after which the steering is held. Every value stays within its speed
/// and acceleration limits.
pub fn halt_command(p: &Platform, last: &Command, dt: f64) -> Command {
    let mut out = stop_command(p, last, dt);
    let step = p.limits.steer_accel * dt;
    for i in 0..last.n.min(MAX_WHEELS) {
        let s = last.wheels[i].steer_rate;
        out.wheels[i].steer_rate = if s.is_finite() {
            s - s.clamp(-step, step)
        } else {
            0.0
        };
    }
    out
}

/// True when every wheel of the command is at rest (below `rest` rad/s).
pub fn command_at_rest(cmd: &Command, rest: f64) -> bool {
    cmd.wheels[..cmd.n.min(MAX_WHEELS)]
        .iter()
        .all(|w| w.wheel_speed.abs() <= rest)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn healthy() -> SupervisorInput {
        SupervisorInput {
            start_legs: Some((0, 0.37, 0.37)),
            ..SupervisorInput::default()
        }
    }

    #[test]
    fn refuses_to_track_from_the_wrong_start_and_waits_for_every_module() {
        let p = Platform::justin();
        let mut s = Supervisor::new(&p, SupervisorConfig::default());
        s.arm();
        let mut inp = healthy();
        inp.start_legs = None; // a module has not reported yet
        assert_eq!(s.step(&p, &inp, true), Mode::Align);
        assert_eq!(s.state(), SupervisorState::Aligning);
        inp.start_legs = Some((2, 0.465, 0.37));
        assert_eq!(s.step(&p, &inp, true), Mode::Decelerate);
        match s.reason() {
            Some(FaultReason::StartMismatch { wheel, node, .. }) => {
                assert_eq!((wheel, node), (2, 3))
            }
            r => panic!("unexpected {r:?}"),
        }
        assert!(s.reason().unwrap().to_string().contains("0.4650 m"));
    }

    #[test]
    fn normal_sequence_idle_to_stopped() {
        let p = Platform::justin();
        let mut s = Supervisor::new(&p, SupervisorConfig::default());
        assert_eq!(s.step(&p, &healthy(), true), Mode::Disabled);
        assert!(s.arm());
        let mut inp = healthy();
        inp.alignment_error = 0.3;
        assert_eq!(s.step(&p, &inp, true), Mode::Align);
        inp.alignment_error = 0.001;
        assert_eq!(s.step(&p, &inp, true), Mode::Track);
        assert_eq!(s.state(), SupervisorState::Tracking);
        inp.trajectory_done = true;
        assert_eq!(s.step(&p, &inp, false), Mode::Decelerate);
        assert_eq!(s.state(), SupervisorState::Stopping);
        assert_eq!(s.step(&p, &inp, true), Mode::Hold);
        assert_eq!(s.state(), SupervisorState::Stopped);
        assert!(s.reason().is_none());
    }

    fn tracking() -> (Platform, Supervisor) {
        let p = Platform::justin();
        let mut s = Supervisor::new(&p, SupervisorConfig::default());
        s.arm();
        s.step(&p, &healthy(), true);
        assert_eq!(s.state(), SupervisorState::Tracking);
        (p, s)
    }

    #[test]
    fn one_stale_stream_is_tolerated_up_to_the_data_age_bound() {
        let (p, mut s) = tracking();
        let mut inp = healthy();
        // FEEDBACK_B of wheel 2 lost for 8 cycles while FEEDBACK_A keeps arriving.
        inp.data_age[2] = 8;
        assert_eq!(s.step(&p, &inp, false), Mode::Track);
        inp.data_age[2] = 9;
        assert_eq!(s.step(&p, &inp, false), Mode::Decelerate);
        match s.reason() {
            Some(FaultReason::StaleFeedback { wheel, cycles, .. }) => {
                assert_eq!((wheel, cycles), (2, 9));
            }
            r => panic!("unexpected reason {r:?}"),
        }
    }

    #[test]
    fn stale_feedback_after_more_than_three_cycles_names_the_module() {
        let (p, mut s) = tracking();
        let mut inp = healthy();
        inp.feedback_age[2] = 3;
        assert_eq!(
            s.step(&p, &inp, false),
            Mode::Track,
            "3 cycles is still tolerated"
        );
        inp.feedback_age[2] = 4;
        assert_eq!(s.step(&p, &inp, false), Mode::Decelerate);
        assert_eq!(s.state(), SupervisorState::Fault);
        match s.reason() {
            Some(FaultReason::StaleFeedback {
                wheel,
                node,
                cycles,
            }) => {
                assert_eq!((wheel, node, cycles), (2, 3, 4));
            }
            r => panic!("unexpected reason {r:?}"),
        }
        assert!(s.reason().unwrap().to_string().contains("node 3"));
    }

    #[test]
    fn fault_is_latched_until_rearmed() {
        let (p, mut s) = tracking();
        let mut inp = healthy();
        inp.module_fault[1] = Some(7);
        s.step(&p, &inp, false);
        assert_eq!(s.state(), SupervisorState::Fault);
        // The module recovers: the platform stays stopped.
        for _ in 0..100 {
            assert_eq!(s.step(&p, &healthy(), true), Mode::Disabled);
        }
        assert_eq!(s.state(), SupervisorState::Fault);
        assert!(s.arm());
        assert_eq!(s.state(), SupervisorState::Aligning);
    }

    #[test]
    fn limit_breach_and_non_finite_are_faults() {
        let (p, mut s) = tracking();
        let mut inp = healthy();
        inp.wheel_speed[0] = p.limits.wheel_speed * 1.5;
        s.step(&p, &inp, false);
        assert!(matches!(
            s.reason(),
            Some(FaultReason::LimitBreach {
                what: LimitKind::WheelSpeed,
                ..
            })
        ));
        let (p, mut s) = tracking();
        let mut inp = healthy();
        inp.steer_rate[3] = f64::NAN;
        s.step(&p, &inp, false);
        assert!(matches!(
            s.reason(),
            Some(FaultReason::LimitBreach {
                what: LimitKind::NonFinite,
                wheel: 3,
                ..
            })
        ));
    }

    #[test]
    fn an_unexplained_steering_angle_step_is_an_encoder_fault() {
        let (p, mut s) = tracking();
        let mut inp = healthy();
        inp.steer_jump[3] = 0.015;
        assert_eq!(s.step(&p, &inp, false), Mode::Track, "below the threshold");
        inp.steer_jump[3] = -0.3;
        assert_eq!(s.step(&p, &inp, false), Mode::Decelerate);
        match s.reason() {
            Some(FaultReason::EncoderJump { wheel, node, jump }) => {
                assert_eq!((wheel, node), (3, 4));
                assert!((jump + 0.3).abs() < 1e-12);
            }
            r => panic!("unexpected {r:?}"),
        }
    }

    #[test]
    fn slip_needs_persistence() {
        let (p, mut s) = tracking();
        let mut inp = healthy();
        inp.slip_residual = 0.5;
        for _ in 0..SupervisorConfig::default().slip_cycles - 1 {
            s.step(&p, &inp, false);
        }
        assert_eq!(s.state(), SupervisorState::Tracking);
        s.step(&p, &inp, false);
        assert!(matches!(s.reason(), Some(FaultReason::Slip { .. })));
    }

    #[test]
    fn the_slip_fault_names_the_wheel_only_when_the_others_agree() {
        let slip = |others: f64, behind| FaultReason::Slip {
            residual: 0.12,
            suspect: Some(SlipSuspect {
                wheel: 1,
                off: 0.24,
                others,
            }),
            behind,
        };
        let one = slip(0.004, None);
        assert_eq!(one.slip_wheel(), Some(1));
        let text = one.to_string();
        assert!(text.contains("wheel 2 moves 0.240 m/s off"), "{text}");
        assert!(text.contains("check wheel 2's tyre"), "{text}");

        let several = slip(0.1, None);
        assert_eq!(several.slip_wheel(), None);
        let text = several.to_string();
        assert!(text.contains("no single wheel explains it"), "{text}");
        assert!(!text.contains("wheel 2"), "{text}");

        // A held wheel: no single wheel explains the residual, but its drive is behind.
        let held = slip(0.1, Some((2, FollowQuantity::WheelSpeed, 0.128)));
        assert_eq!(held.slip_wheel(), None);
        assert_eq!(held.slip_lead(), Some(2));
        assert_eq!(
            slip(0.004, Some((2, FollowQuantity::WheelSpeed, 0.1))).slip_lead(),
            Some(1)
        );
        let text = held.to_string();
        assert!(
            text.contains("wheel 3's wheel speed has been outside its following window for 128 ms"),
            "{text}"
        );

        let unknown = FaultReason::Slip {
            residual: 0.12,
            suspect: None,
            behind: None,
        };
        assert_eq!(unknown.slip_wheel(), None);
        assert!(
            unknown.to_string().contains("check the wheels"),
            "{unknown}"
        );
        // Without a suspect (a two-wheel base), the drive behind is still named.
        let two = FaultReason::Slip {
            residual: 0.12,
            suspect: None,
            behind: Some((1, FollowQuantity::SteerRate, 0.06)),
        };
        assert_eq!(two.slip_lead(), Some(1));
        let text = two.to_string();
        assert!(
            text.contains(
                "wheel 2's steering rate has been outside its following window for 60 ms"
            ),
            "{text}"
        );
    }

    #[test]
    fn the_slip_fault_reports_the_drive_longest_outside_its_window() {
        let (p, mut s) = tracking();
        let mut inp = healthy();
        inp.enabled = [true; MAX_WHEELS];
        let mut c = Command::zero(4);
        for w in c.wheels.iter_mut().take(4) {
            w.wheel_speed = 5.0;
        }
        // Every rolling drive follows 5 rad/s for 0.4 s (longer than the following check's
        // lag) …
        for i in 0..4 {
            inp.wheel_speed[i] = 5.0;
        }
        for _ in 0..100 {
            s.step(&p, &inp, false);
            s.note_command(&c, &[true; MAX_WHEELS]);
        }
        assert_eq!(s.state(), SupervisorState::Tracking);
        // … then wheel 3's measures 0, and the wheels disagree beyond the slip threshold: the
        // slip fault comes first (25 cycles, before the following error's 0.2 s).
        inp.wheel_speed[2] = 0.0;
        inp.slip_residual = 0.5;
        let mut reason = None;
        for _ in 0..SupervisorConfig::default().slip_cycles {
            s.step(&p, &inp, false);
            reason = s.reason();
            s.note_command(&c, &[true; MAX_WHEELS]);
        }
        match reason {
            Some(FaultReason::Slip {
                behind: Some((2, FollowQuantity::WheelSpeed, t)),
                ..
            }) => assert!(t > 0.0 && t < 0.2, "{t}"),
            r => panic!("expected a slip fault with wheel 3's drive behind, got {r:?}"),
        }
    }

    #[test]
    fn stop_request_is_a_controlled_stop_not_a_fault() {
        let (p, mut s) = tracking();
        let mut inp = healthy();
        inp.stop_requested = true;
        assert_eq!(s.step(&p, &inp, false), Mode::Decelerate);
        assert_eq!(s.state(), SupervisorState::Stopping);
        assert!(s.reason().is_none());
    }

    /// Runs the supervisor in Tracking for `cycles` cycles: every wheel is commanded
    /// `cmd(k)` (wheel speed, steering rate) and measures `meas(k, &drive)` where `drive`
    /// models a healthy velocity-controlled drive (one cycle of transport delay, first-order
    /// lag T = 20 ms, acceleration limit 110 rad/s², as in the simulator's plant) of the
    /// command. Returns the first fault and its cycle.
    fn follow_run(
        cycles: u32,
        cmd: impl Fn(u32) -> f64,
        meas: impl Fn(u32, f64) -> f64,
    ) -> (Option<(u32, FaultReason)>, FollowPeak) {
        let (p, mut s) = tracking();
        let dt = p.dt();
        let (mut x, mut prev) = (0.0f64, 0.0f64);
        for k in 0..cycles {
            // The drive: 4 sub-steps of 1 ms towards the command of the previous cycle.
            for _ in 0..4 {
                let dv = (prev - x) * (1.0 - (-0.001f64 / 0.020).exp());
                x += dv.clamp(-110.0 * 0.001, 110.0 * 0.001);
            }
            let mut inp = healthy();
            inp.enabled = [true; MAX_WHEELS];
            for i in 0..4 {
                inp.wheel_speed[i] = meas(k, x);
                inp.steer_rate[i] = 0.0;
            }
            s.step(&p, &inp, false);
            if let Some(r) = s.reason() {
                return (Some((k, r)), s.follow_peak());
            }
            let mut c = Command::zero(4);
            for w in c.wheels.iter_mut().take(4) {
                w.wheel_speed = cmd(k);
            }
            s.note_command(&c, &[true; MAX_WHEELS]);
            prev = cmd(k);
        }
        let _ = dt;
        (None, s.follow_peak())
    }

    #[test]
    fn a_healthy_lagging_drive_stays_inside_the_following_window() {
        // A step to 10 rad/s (at the acceleration limit), held, then a controlled-stop ramp
        // at 40 rad/s²: lag and acceleration limit only delay the response.
        let cmd = |k: u32| match k {
            0..=29 => 0.0,
            30..=299 => 10.0,
            _ => (10.0 - 40.0 * 0.004 * f64::from(k - 299)).max(0.0),
        };
        let (fault, peak) = follow_run(500, cmd, |_, x| x);
        assert!(fault.is_none(), "{fault:?}");
        assert!(peak.ratio < 1.0, "{peak:?}");
        // The same drive realising half its command is a following error …
        let (fault, _) = follow_run(500, cmd, |_, x| 0.5 * x);
        let (k, r) = fault.expect("a drive at 50 % is a following error");
        match r {
            FaultReason::FollowingError {
                wheel: 0,
                node: 1,
                quantity: FollowQuantity::WheelSpeed,
                commanded,
                measured,
                window,
                duration,
            } => {
                assert_eq!(commanded, 10.0);
                assert!((measured - 5.0).abs() < 0.1, "{measured}");
                assert!((window - 3.0).abs() < 1e-9, "0.5 + 25 % of 10: {window}");
                assert!(duration > 0.2, "{duration}");
            }
            r => panic!("{r:?}"),
        }
        // … detected the time out (0.2 s = 50 cycles) after it left the window.
        assert!((80..=110).contains(&k), "fault at cycle {k}");
        let msg = r.to_string();
        assert!(
            msg.starts_with("following error: wheel 1 (node 1) wheel speed measured 5.")
                && msg.contains("10.000 rad/s was commanded"),
            "{msg}"
        );
        // A drive within 20 % of its command (inside the 25 % window) is not.
        let (fault, _) = follow_run(500, cmd, |_, x| 0.8 * x);
        assert!(fault.is_none(), "{fault:?}");
    }

    #[test]
    fn a_motor_that_does_not_respond_faults_after_lag_and_timeout_and_only_when_enabled() {
        let (fault, _) = follow_run(200, |_| 5.0, |_, _| 0.0);
        let (k, r) = fault.expect("a dead motor is a following error");
        assert!(matches!(r, FaultReason::FollowingError { measured, .. } if measured == 0.0));
        // Checked once enabled longer than the lag (25 cycles: from index 25 on), then more
        // than 0.2 s = 50 cycles outside: index 75, the 76th cycle.
        assert_eq!(k, 75);
        // Not enabled (or not known to be): never checked.
        let (p, mut s) = tracking();
        let mut c = Command::zero(4);
        c.wheels[2].wheel_speed = 5.0;
        for _ in 0..500 {
            s.step(&p, &healthy(), false);
            s.note_command(&c, &[true; MAX_WHEELS]);
        }
        assert_eq!(s.state(), SupervisorState::Tracking);
        // Switched off with an infinite time out (like 0xFFFFFFFF in 0x6065).
        let p = Platform::justin();
        let cfg = SupervisorConfig {
            follow_timeout: f64::INFINITY,
            ..SupervisorConfig::default()
        };
        let mut s = Supervisor::new(&p, cfg);
        s.arm();
        s.step(&p, &healthy(), true);
        let mut inp = healthy();
        inp.enabled = [true; MAX_WHEELS];
        for _ in 0..500 {
            s.step(&p, &inp, false);
            s.note_command(&c, &[true; MAX_WHEELS]);
        }
        assert_eq!(s.state(), SupervisorState::Tracking);
    }

    #[test]
    fn following_thresholds_are_validated() {
        let dt = 0.004;
        SupervisorConfig::default().validate(dt).unwrap();
        for (cfg, field) in [
            (
                SupervisorConfig {
                    follow_lag: 0.3,
                    ..Default::default()
                },
                "supervisor.follow_lag",
            ),
            (
                SupervisorConfig {
                    follow_window_rel: 1.0,
                    ..Default::default()
                },
                "supervisor.follow_window_rel",
            ),
            (
                SupervisorConfig {
                    follow_timeout: 0.0,
                    ..Default::default()
                },
                "supervisor.follow_timeout",
            ),
            (
                SupervisorConfig {
                    follow_wheel_window: f64::NAN,
                    ..Default::default()
                },
                "supervisor.follow_wheel_window",
            ),
            (
                SupervisorConfig {
                    arrive_position: 0.0,
                    ..Default::default()
                },
                "supervisor.arrive_position",
            ),
        ] {
            assert_eq!(cfg.validate(dt).unwrap_err().0, field);
        }
    }

    #[test]
    fn a_trajectory_that_ends_away_from_its_goal_fails_but_an_operator_stop_does_not() {
        let (p, mut s) = tracking();
        let mut inp = healthy();
        inp.trajectory_done = true;
        assert_eq!(s.step(&p, &inp, false), Mode::Decelerate);
        assert_eq!(s.state(), SupervisorState::Stopping);
        inp.goal_error = Some((6.4, 3.1, 2, 0.0));
        assert_eq!(s.step(&p, &inp, false), Mode::Decelerate, "still moving");
        assert_eq!(s.step(&p, &inp, true), Mode::Hold);
        assert_eq!(s.state(), SupervisorState::Fault);
        let r = s.reason().expect("a reason");
        assert!(matches!(r, FaultReason::NotArrived { leg_wheel: 2, .. }));
        assert!(
            r.to_string().starts_with("did not arrive: the trajectory ended with the estimated pose 6.400 m and 177.62° from its goal"),
            "{r}"
        );
        // Within the tolerances (0.05 m, 5°, 20 mm): Stopped.
        let (p, mut s) = tracking();
        inp.goal_error = Some((0.01, 0.01, 0, 0.005));
        s.step(&p, &inp, true);
        s.step(&p, &inp, true);
        assert_eq!(s.state(), SupervisorState::Stopped);
        // A NaN estimate did not arrive either.
        let (p, mut s) = tracking();
        inp.goal_error = Some((f64::NAN, 0.0, 0, 0.0));
        s.step(&p, &inp, true);
        s.step(&p, &inp, true);
        assert_eq!(s.state(), SupervisorState::Fault);
        // An operator stop (Ctrl-C) ends where it ends: no arrival check.
        let (p, mut s) = tracking();
        let mut stop = healthy();
        stop.stop_requested = true;
        stop.goal_error = Some((6.4, 3.1, 2, 0.0));
        s.step(&p, &stop, true);
        s.step(&p, &stop, true);
        assert_eq!(s.state(), SupervisorState::Stopped);
        assert!(s.reason().is_none());
    }

    #[test]
    fn stop_ramp_respects_acceleration_and_keeps_ratios() {
        let p = Platform::justin();
        let mut c = Command::zero(4);
        let speeds = [10.0, -5.0, 2.5, 0.0];
        for (i, v) in speeds.iter().enumerate() {
            c.wheels[i].wheel_speed = *v;
            c.wheels[i].steer_rate = 1.0;
        }
        let dt = p.dt();
        let mut cycles = 0;
        while !command_at_rest(&c, 0.0) {
            let next = stop_command(&p, &c, dt);
            for i in 0..4 {
                let dv = (next.wheels[i].wheel_speed - c.wheels[i].wheel_speed).abs();
                assert!(dv <= p.limits.wheel_accel * dt + 1e-12);
                assert_eq!(next.wheels[i].steer_rate, 0.0, "steering held");
                if c.wheels[0].wheel_speed.abs() > 0.0 && next.wheels[0].wheel_speed != 0.0 {
                    let r0 = next.wheels[i].wheel_speed / next.wheels[0].wheel_speed;
                    assert!((r0 - speeds[i] / speeds[0]).abs() < 1e-9);
                }
            }
            c = next;
            cycles += 1;
            assert!(cycles < 1000);
        }
        // 10 rad/s at 40 rad/s² → 0.25 s → 63 cycles of 4 ms.
        assert_eq!(cycles, (10.0 / (p.limits.wheel_accel * dt)).ceil() as usize);
    }
}
