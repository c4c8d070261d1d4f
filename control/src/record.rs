//! The per-cycle record: everything one cycle saw and did, in one fixed-size `Copy` value.
//!
//! The cycle builds one [`CycleRecord`] per cycle (no allocation) and hands it over a bounded
//! channel; the application layer (the `rollbase` package's `record` module) turns records
//! into recordings, summaries and plots. This crate has no file-format dependency.

use crate::supervisor::{FaultReason, SupervisorState};
use crate::types::{Command, Measurement, Pose, ReferenceSample, Twist, MAX_WHEELS};

/// Largest number of received frames kept per cycle record.
pub const MAX_RX_FRAMES: usize = 48;
/// Largest number of sent frames kept per cycle record (the native profile sends SYNC and
/// one SETPOINT per wheel; the CiA 402 profile up to SYNC, heartbeat, NMT and SDO requests
/// for 24 devices and one RPDO per drive while booting).
pub const MAX_TX_FRAMES: usize = 48;

/// Commands recorded per cycle (a velocity source publishes at 10–50 Hz: one a cycle at most,
/// normally; a burst beyond this is counted in [`CycleRecord::commands_in_omitted`]).
pub const MAX_RECORDED_COMMANDS: usize = 8;

/// One raw CAN frame as recorded.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct FrameRecord {
    /// Time the frame was received or sent (s since the run's time origin).
    pub t: f64,
    /// 11-bit identifier.
    pub id: u16,
    /// Data length.
    pub len: u8,
    /// Payload bytes (first `len` valid).
    pub data: [u8; 8],
    /// For received frames: `None` if accepted, else the rejection kind.
    pub error: Option<&'static str>,
    /// The bus it was sent on or received from (`wheels[i].bus`; 0 on a one-bus platform).
    pub bus: u8,
}

/// Avoidance part of a cycle record.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct AvoidanceRecord {
    /// ICR in the body frame, `None` when at infinity (pure translation) or undefined.
    pub icr_body: Option<[f64; 2]>,
    /// Whether the avoidance is pushing (the ICR is inside a field).
    pub active: bool,
    /// Smallest ICR–wheel contact point distance (m); infinite when the ICR is at infinity.
    pub min_distance: f64,
    /// Index of the wheel nearest the ICR.
    pub nearest_wheel: Option<usize>,
    /// Field radii d_start per wheel (m).
    pub d_start: [f64; MAX_WHEELS],
    /// Deviation from the nominal reference (z units).
    pub deviation: [f64; 3 + MAX_WHEELS],
}

/// Timing of one cycle.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct TimingRecord {
    /// Time since the previous cycle's start (µs).
    pub period_us: f64,
    /// Lateness of the wake-up against the absolute deadline (µs).
    pub wakeup_latency_us: f64,
    /// Time from the end of feedback collection to setpoints sent (µs); 0 in lockstep.
    pub compute_us: f64,
    /// Age of the oldest wheel's newest feedback at the controller step (µs).
    pub feedback_age_us: f64,
    /// Frames received this cycle.
    pub frames_in: u32,
    /// Frames sent this cycle.
    pub frames_out: u32,
    /// Frames rejected this cycle.
    pub rejected: u32,
    /// Whether this cycle missed its deadline.
    pub deadline_miss: bool,
}

/// Everything recorded about one cycle. `Copy` and fixed-size: built without allocation.
#[derive(Clone, Copy, Debug)]
pub struct CycleRecord {
    /// Cycle index from 0.
    pub cycle: u64,
    /// Cycle start time (s since the run's time origin).
    pub t: f64,
    /// Log time in ns (virtual in lockstep, Unix time in real time).
    pub log_time_ns: u64,
    /// Number of wheels.
    pub n: usize,
    /// CAN nodes per wheel.
    pub nodes: [u8; MAX_WHEELS],
    /// Received frames.
    pub rx: [FrameRecord; MAX_RX_FRAMES],
    /// Number of valid entries in `rx`.
    pub n_rx: usize,
    /// Sent frames.
    pub tx: [FrameRecord; MAX_TX_FRAMES],
    /// Number of valid entries in `tx`.
    pub n_tx: usize,
    /// Frames sent this cycle, including any beyond `MAX_TX_FRAMES` that were not kept.
    pub n_tx_total: u32,
    /// Latest decoded feedback per wheel.
    pub measurement: Measurement,
    /// Cycles since each wheel's last valid feedback.
    pub feedback_age: [u32; MAX_WHEELS],
    /// Module state per wheel from STATUS (wire value; 255 = unknown).
    pub module_state: [u8; MAX_WHEELS],
    /// Nominal reference.
    pub nominal: ReferenceSample,
    /// Reference fed to the controller (nominal + avoidance deviation).
    pub reference: ReferenceSample,
    /// The command sent.
    pub command: Command,
    /// Supervisor mode name.
    pub mode: &'static str,
    /// Enable flag sent.
    pub enable: bool,
    /// Estimated pose.
    pub pose: Pose,
    /// Estimated body twist.
    pub twist_body: Twist,
    /// Odometry slip residual (m/s).
    pub slip_residual: f64,
    /// True pose and legs when the run is simulated in-process.
    pub truth: Option<(Pose, [f64; MAX_WHEELS])>,
    /// Avoidance state.
    pub avoidance: AvoidanceRecord,
    /// Wheel contact points in the body frame at the measured leg extensions (m).
    pub wheel_xy: [[f64; 2]; MAX_WHEELS],
    /// Supervisor state.
    pub state: SupervisorState,
    /// Fault reason, if any.
    pub reason: Option<FaultReason>,
    /// Timing.
    pub timing: TimingRecord,
    /// Command-port counters (live commands; zero for trajectories).
    pub commands: crate::ports::CommandStats,
    /// What the shaper (or the time scaling) does with the reference.
    pub shaping: crate::ports::ShapingState,
    /// The state port's value of this cycle (what the ROS 2 node publishes; recorded as the
    /// ROS 2 topics of a bag).
    pub base: crate::ports::BaseState,
    /// The commands the cycle took since the last record, in order (the first
    /// [`MAX_RECORDED_COMMANDS`]; see `commands_in_omitted`).
    pub commands_in: [Option<crate::ports::CommandEvent>; MAX_RECORDED_COMMANDS],
    /// Commands taken in this cycle beyond [`MAX_RECORDED_COMMANDS`] (counted, not recorded).
    pub commands_in_omitted: u32,
}

impl CycleRecord {
    /// An empty record for cycle `cycle` at time `t`.
    pub fn new(cycle: u64, t: f64, n: usize) -> Self {
        Self {
            cycle,
            t,
            log_time_ns: (t.max(0.0) * 1e9) as u64,
            n,
            nodes: [0; MAX_WHEELS],
            rx: [FrameRecord::default(); MAX_RX_FRAMES],
            n_rx: 0,
            tx: [FrameRecord::default(); MAX_TX_FRAMES],
            n_tx: 0,
            n_tx_total: 0,
            measurement: Measurement::default(),
            feedback_age: [0; MAX_WHEELS],
            module_state: [255; MAX_WHEELS],
            nominal: ReferenceSample::default(),
            reference: ReferenceSample::default(),
            command: Command::zero(n),
            mode: "disabled",
            enable: false,
            pose: Pose::default(),
            twist_body: Twist::default(),
            slip_residual: 0.0,
            truth: None,
            avoidance: AvoidanceRecord::default(),
            wheel_xy: [[0.0; 2]; MAX_WHEELS],
            state: SupervisorState::Idle,
            reason: None,
            timing: TimingRecord::default(),
            commands: Default::default(),
            shaping: Default::default(),
            base: Default::default(),
            commands_in: [None; MAX_RECORDED_COMMANDS],
            commands_in_omitted: 0,
        }
    }

    /// Appends a received frame (dropped silently when the record is full; counted in timing).
    pub fn push_rx(&mut self, f: FrameRecord) {
        if self.n_rx < MAX_RX_FRAMES {
            self.rx[self.n_rx] = f;
            self.n_rx += 1;
        }
    }

    /// Appends a sent frame.
    pub fn push_tx(&mut self, f: FrameRecord) {
        self.n_tx_total = self.n_tx_total.saturating_add(1);
        if self.n_tx < MAX_TX_FRAMES {
            self.tx[self.n_tx] = f;
            self.n_tx += 1;
        }
    }
}
