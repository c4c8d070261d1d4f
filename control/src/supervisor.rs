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
//! a bus error, a slip residual above threshold for several cycles, or an alignment timeout.
//!
//! A controlled stop ([`stop_command`]) decelerates every wheel from its last commanded speed
//! toward zero at the wheel acceleration limit, all wheels scaled together so the platform keeps
//! its direction of travel while slowing, with steering held (zero steering rate). In Fault the
//! same ramp is used; once all wheels are at rest the command is zero with the drives disabled.
//!
//! The supervisor is pure: inputs in, decision out; time is the cycle index.

use crate::platform::Platform;
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
    /// The bus reported an error (interface down, bus-off, socket error).
    BusError,
    /// The odometry slip residual stayed above threshold.
    Slip {
        /// Residual (m/s).
        residual: f64,
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
            Self::Slip { residual } => {
                write!(
                    f,
                    "wheel slip: odometry residual {residual:.4} m/s above threshold"
                )
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
}

impl Default for SupervisorConfig {
    fn default() -> Self {
        Self {
            stale_cycles: crate::platform::TOLERATED_LOST_CYCLES,
            stale_data_cycles: 8,
            align_tolerance: 0.5f64.to_radians(),
            align_timeout_cycles: 2500,
            limit_margin: 0.2,
            slip_threshold: 0.05,
            slip_cycles: 25,
            rest_speed: 0.02,
            start_leg_tolerance: 0.005,
            steer_jump_threshold: 0.02,
        }
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
    /// Odometry slip residual (m/s).
    pub slip_residual: f64,
    /// An operator stop was requested (Ctrl-C): controlled stop, not a fault.
    pub stop_requested: bool,
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
        }
    }

    /// The nodes that deliver each wheel's steering angle and leg extension, when they are
    /// not the wheel's module (CiA 402: the steering drive and the leg encoder): encoder-jump
    /// and start-mismatch faults name them.
    pub fn set_stream_nodes(&mut self, steer: [u8; MAX_WHEELS], leg: [u8; MAX_WHEELS]) {
        self.steer_nodes = steer;
        self.leg_nodes = leg;
    }

    /// Enters Fault for a reason found outside the cycle's checks (a device that cannot be
    /// booted), from any state; the first reason is kept until re-armed.
    pub fn fail(&mut self, reason: FaultReason) {
        self.fault(reason);
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
                });
            }
        } else {
            self.slip_count = 0;
        }
        None
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
                if at_rest {
                    self.enter(SupervisorState::Stopped);
                    Mode::Hold
                } else {
                    Mode::Decelerate
                }
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
    fn stop_request_is_a_controlled_stop_not_a_fault() {
        let (p, mut s) = tracking();
        let mut inp = healthy();
        inp.stop_requested = true;
        assert_eq!(s.step(&p, &inp, false), Mode::Decelerate);
        assert_eq!(s.state(), SupervisorState::Stopping);
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
