//! The sans-IO CANopen master for the CiA 402 profile: boot, configuration, homing, cyclic
//! exchange and supervision of every device of the platform.
//!
//! Three calls per control cycle, like the native profile's cycle (time in seconds, passed
//! in; nothing here reads a clock, opens a socket or allocates after [`Master::new`]):
//!
//! - [`Master::start_cycle`]: SYNC first, then whatever is due: NMT commands, the master's
//!   heartbeat, the next SDO request of every device being configured (or read after a
//!   fault);
//! - [`Master::on_frame`]: every received frame; feedback TPDOs come back as [`Event`]s in SI
//!   units, everything else updates the devices' state;
//! - [`Master::finish_cycle`]: one RPDO1 per drive (controlword + target velocity) from the
//!   wheels' setpoints (or, while a wheel is homed, from the homing), then SDO requests whose
//!   previous response came in this cycle.
//!
//! # Boot (per device, all devices in parallel)
//!
//! ```text
//!  NeedsReset ──NMT reset communication──► ResetSent ──boot-up──► Configuring
//!      ▲                                      │ boot_timeout           │ SDO plan (one request
//!      │ re-arm                               ▼                        │ in flight per device)
//!  Lost / Rebooted ◄── heartbeat timeout ── Failed ◄── abort, timeout, │
//!      ▲               or boot-up              ▲        mismatch        ▼
//!      └───────────────────────────────── Started ◄──NMT start── Configured
//! ```
//!
//! Optional plan steps (PDOs the plan disables, unit checks, extra writes marked optional)
//! are skipped when the device answers "object does not exist" (0x06020000) or "sub-index
//! does not exist" (0x06090011); [`Device::skipped`] lists them. A mode display (0x6061) that
//! does not show the mode yet is read again every cycle for `mode_switch_timeout_ms`.
//!
//! # Homing (steering drives, once the operator asked to arm)
//!
//! Every steering drive that booted (power-on or reboot: its position counter means
//! nothing yet) is homed before the platform is armed, each wheel on its own as soon as its
//! drives run: `kind = "drive"` walks the drive to operation enabled in homing mode (6),
//! sets controlword bit 4 and waits for statusword bit 12 (homing attained) with bit 10
//! (target reached), fails on bit 13 (homing error) or the timeout, then shuts the drive
//! down and switches it to cyclic synchronous velocity (polled). `digital_input` turns the
//! axis in cyclic synchronous velocity (ramped within `accel_rad_s2`) until the input bit of
//! 0x60FD is set, takes the position there as the home position, and ramps down.
//! `absolute` checks the first angle read. While a wheel is homed its rolling drive is
//! enabled and told −coupling × the steering rate (0: it holds). [`Master::ready`] is true
//! when every device runs and every steering drive is homed.
//!
//! # Supervision (latched per device until [`Master::rearm`])
//!
//! EMCY that is not informational ([`emcy::is_informational`]: error register 0, CAN
//! warnings, the platform file's list; those are counted and kept in the device's
//! [`Device::emcy_history`]); a statusword showing Fault (outside the grace period after a
//! re-arm, in which the drive gets the fault-reset edge); a heartbeat older than
//! `master_heartbeat_timeout_ms`; a heartbeat or boot-up showing the device left
//! operational; a drive that does not reach operation enabled within `enable_timeout_ms` of
//! being asked. On a drive's fault the master reads its error code (0x603F) and the newest
//! entry of its error history (0x1003:01) and adds them to the fault. [`Master::wheel_fault`]
//! reports the first fault of a wheel's devices.
//!
//! # The controlword
//!
//! Each cycle every drive gets the controlword [`ds402::master_controlword`] chooses for its
//! last reported state and the wheel's setpoint flags (enable, brake → halt bit, fault reset),
//! and a target velocity that is zero unless the drive reported operation enabled and the
//! wheel is enabled and not braking (a drive is never handed a speed before it confirmed it
//! is enabled). A target the velocity object cannot carry is replaced by zero with the halt
//! bit; the supervisor's limit check stops the platform.

use super::cob::{self, Cob};
use super::config::{Cia402Config, HomingKind, Role, SdoOp};
use super::ds402::{self, State as State402};
use super::emcy::{self, Emcy};
use super::nmt::{self, NmtCommand, NmtState};
use super::od;
use super::pdo::{self, MapEntry};
use super::sdo::{AbortCode, SdoRequest, SdoResponse};
use crate::codec::{ModuleState, Setpoint};
use crate::frame::{CanFrame, FrameBuf};

/// Where a homing stood when it failed, for the message.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum HomingPhase {
    /// Walking the drive to operation enabled.
    Enabling,
    /// The homing move (searching for the switch, index pulse or input).
    Searching,
    /// Stopping after the home position was found.
    Stopping,
    /// Switching the drive back to cyclic synchronous velocity.
    SwitchingMode,
    /// Turning the homed axis to its rest angle (the controller's link does that).
    RestAngle,
}

impl HomingPhase {
    fn name(self) -> &'static str {
        match self {
            Self::Enabling => "enabling the drive",
            Self::Searching => "searching for the home position",
            Self::Stopping => "stopping at the home position",
            Self::SwitchingMode => "switching back to cyclic synchronous velocity",
            Self::RestAngle => "turning to the rest angle (cia402.wheels[i].rest_angle_rad)",
        }
    }
}

/// Why the homing of a steering drive failed.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum HomingError {
    /// Not done within `timeout_ms`.
    Timeout {
        /// The timeout (ms).
        ms: u32,
        /// What it was doing.
        phase: HomingPhase,
        /// The last statusword.
        statusword: Option<u16>,
    },
    /// The drive reported a homing error (statusword bit 13).
    DriveError {
        /// The statusword.
        statusword: u16,
    },
    /// The digital input never fired while the axis turned this far (turns).
    InputNeverSeen {
        /// The input bit of 0x60FD.
        bit: u8,
        /// Steering turns made.
        turns: f64,
    },
    /// The drive went to Fault and stayed there despite fault resets.
    Faulted {
        /// The statusword.
        statusword: u16,
    },
    /// An absolute steering encoder read an angle further than a turn from its zero.
    AbsoluteOutOfRange {
        /// The angle read (rad, before `steer_offset_rad`).
        angle: f64,
    },
}

impl std::fmt::Display for HomingError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Self::Timeout { ms, phase, statusword } => {
                write!(f, "homing not done within {ms} ms (timeout_ms) while {}", phase.name())?;
                if let Some(sw) = statusword {
                    write!(f, ", statusword 0x{sw:04X}")?;
                }
                if *phase == HomingPhase::Searching {
                    write!(f, "; the home switch or index pulse was never seen: check the switch, its wiring and the method (0x6098), and that the axis turns (speeds 0x6099)")?;
                }
                Ok(())
            }
            Self::DriveError { statusword } => write!(
                f,
                "the drive reported a homing error (statusword 0x{statusword:04X}, bit 13): check the home switch, the method (0x6098) and the direction of the search"
            ),
            Self::InputNeverSeen { bit, turns } => write!(
                f,
                "digital input bit {bit} (0x60FD) never set in {turns:.2} steering turns: check the home switch wiring and cia402.homing.input_bit"
            ),
            Self::Faulted { statusword } => write!(
                f,
                "the drive went to fault while homing and a fault reset did not clear it (statusword 0x{statusword:04X}); read its error code (rollbase sdo … read 0x603F:00)"
            ),
            Self::AbsoluteOutOfRange { angle } => write!(
                f,
                "the absolute steering encoder reads {angle:.3} rad from its zero, more than a turn: is the encoder absolute (single-turn at the steering axis), and its zero set? (homing kind \"absolute\")"
            ),
        }
    }
}

/// Why the boot of a device failed.
#[derive(Clone, Copy, Debug, PartialEq, thiserror::Error)]
pub enum BootError {
    /// The device sent no boot-up message after the NMT reset.
    #[error("node {node} ({role}): no boot-up message within {ms} ms of the NMT reset; check its power, wiring, bit rate and node-ID")]
    NoBootUp {
        /// Node-ID.
        node: u8,
        /// Role on the platform.
        role: Role,
        /// The boot timeout (ms).
        ms: u16,
    },
    /// The device aborted an SDO transfer of the configuration.
    #[error("node {node} ({role}): SDO {} of 0x{index:04X}:{sub:02X} aborted: {code}; check that the device supports this object and value (platform file [cia402], the device's EDS)", if *write { "write" } else { "read" })]
    Aborted {
        /// Node-ID.
        node: u8,
        /// Role.
        role: Role,
        /// Object index.
        index: u16,
        /// Sub-index.
        sub: u8,
        /// Write (download) or read (upload).
        write: bool,
        /// The device's abort code.
        code: AbortCode,
    },
    /// The device did not answer an SDO request.
    #[error("node {node} ({role}): no SDO response for 0x{index:04X}:{sub:02X} after {tries} tries of {timeout_ms} ms each")]
    SdoTimeout {
        /// Node-ID.
        node: u8,
        /// Role.
        role: Role,
        /// Object index.
        index: u16,
        /// Sub-index.
        sub: u8,
        /// Requests sent.
        tries: u8,
        /// Timeout per request (ms).
        timeout_ms: u16,
    },
    /// A value read back is not what the platform file expects.
    #[error("node {node} ({role}): 0x{index:04X}:{sub:02X} {what} reads 0x{got:X}, expected 0x{expected:X}; {}", mismatch_hint(*index, *got, *expected))]
    Mismatch {
        /// Node-ID.
        node: u8,
        /// Role.
        role: Role,
        /// Object index.
        index: u16,
        /// Sub-index.
        sub: u8,
        /// What the object is.
        what: &'static str,
        /// The compared bits read.
        got: u32,
        /// The expected bits.
        expected: u32,
    },
    /// A mode display did not follow the mode written within the time allowed.
    #[error("node {node} ({role}): 0x{index:04X}:{sub:02X} {what} still reads {got} {ms} ms after the mode (0x6060) was written {expected}: the drive did not switch modes; check that it supports the mode, is not held in another by its own tool or inputs, or raise cia402.mode_switch_timeout_ms")]
    ModeNotFollowed {
        /// Node-ID.
        node: u8,
        /// Role.
        role: Role,
        /// Object index.
        index: u16,
        /// Sub-index.
        sub: u8,
        /// What the object is.
        what: &'static str,
        /// The value read last.
        got: i8,
        /// The mode written.
        expected: i8,
        /// The time allowed (ms).
        ms: u16,
    },
    /// The device answered an upload with a segmented transfer.
    #[error("node {node} ({role}): answered the read of 0x{index:04X}:{sub:02X} with a segmented transfer, but the object is at most 4 bytes; check the object's data type in the device's EDS")]
    Segmented {
        /// Node-ID.
        node: u8,
        /// Role.
        role: Role,
        /// Object index.
        index: u16,
        /// Sub-index.
        sub: u8,
    },
    /// The homing of a steering drive failed.
    #[error("node {node} ({role}): {error}")]
    Homing {
        /// Node-ID.
        node: u8,
        /// Role (steering drive).
        role: Role,
        /// What went wrong.
        error: HomingError,
    },
}

fn mismatch_hint(index: u16, got: u32, expected: u32) -> String {
    match index {
        od::DEVICE_TYPE | od::MEASURING_STEP => "is this the right device at this node-ID?".into(),
        od::POSITION_ENCODER_RESOLUTION => "set the platform file's increments_per_rev to the drive's encoder resolution (or the drive's 0x608F to the platform file's)".into(),
        od::GEAR_RATIO => "set the drive's gear ratio (0x6091) to 1:1; the platform file's gear_ratio converts".into(),
        od::SI_UNIT_VELOCITY => format!(
            "the drive's velocity objects (0x60FF, 0x606C) are in {} but the platform file converts from {}: set velocity_unit to the drive's unit, or the drive's 0x60A9 to 0x{expected:08X} (a [[cia402.sdo]] entry, where the drive allows it)",
            super::units::describe_si_velocity(got),
            super::units::describe_si_velocity(expected)
        ),
        _ => "check the platform file against the drive's configuration".into(),
    }
}

/// A fault of one device, latched until [`Master::rearm`].
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum DeviceFault {
    /// The device could not be booted, configured or homed.
    Boot(BootError),
    /// The device sent an emergency message that is not informational.
    Emcy {
        /// Error code.
        code: u16,
        /// Error register.
        register: u8,
        /// The drive's error code (0x603F) read back after the fault, once read.
        read_back: Option<u16>,
    },
    /// The drive's statusword shows Fault or Fault reaction active.
    DriveFault {
        /// The statusword.
        statusword: u16,
        /// The drive's error code (0x603F) read back after the fault, once read.
        read_back: Option<u16>,
    },
    /// No heartbeat within the consumer time.
    HeartbeatLost {
        /// The consumer time (ms).
        ms: u16,
    },
    /// A boot-up or heartbeat shows the device left operational (a boot-up: it rebooted).
    NmtState {
        /// The state reported.
        state: NmtState,
    },
    /// The master itself was silent (no cycle, so no heartbeat and no RPDO) for longer than
    /// the drives' heartbeat consumer time: every drive has taken its communication-loss
    /// reaction (0x6007) meanwhile.
    MasterSilent {
        /// How long the master was silent (ms).
        ms: u32,
        /// The drives' consumer time (ms).
        timeout_ms: u16,
    },
    /// The drive did not reach operation enabled in time.
    EnableTimeout {
        /// The last state it reported.
        state: Option<State402>,
        /// The timeout (ms).
        ms: u16,
    },
    /// The bus went bus-off (the controller's own CAN interface): every device is booted
    /// again on re-arm.
    BusOff,
}

impl std::fmt::Display for DeviceFault {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Self::Boot(e) => write!(f, "boot failed: {e}"),
            Self::Emcy {
                code,
                register,
                read_back,
            } => {
                write!(
                    f,
                    "EMCY 0x{code:04X} ({}), error register 0x{register:02X}",
                    emcy::describe(*code)
                )?;
                if let Some(c) = read_back {
                    write!(f, "; error code 0x603F reads 0x{c:04X} ({})", emcy::describe(*c))?;
                }
                Ok(())
            }
            Self::DriveFault {
                statusword,
                read_back,
            } => match read_back {
                Some(c) => write!(
                    f,
                    "drive in fault (statusword 0x{statusword:04X}), error code 0x603F reads 0x{c:04X} ({})",
                    emcy::describe(*c)
                ),
                None => write!(
                    f,
                    "drive in fault (statusword 0x{statusword:04X}); its error code (0x603F) could not be read: read it and its EMCY history (0x1003) with rollbase sdo"
                ),
            },
            Self::HeartbeatLost { ms } => write!(
                f,
                "no heartbeat for {ms} ms: device off the bus or powered down"
            ),
            Self::NmtState { state: NmtState::BootUp } => {
                write!(f, "device rebooted (boot-up message while running)")
            }
            Self::NmtState { state } => write!(f, "device left operational: now {state}"),
            Self::MasterSilent { ms, timeout_ms } => write!(
                f,
                "the controller was silent for {ms} ms, longer than the drives' heartbeat consumer time of {timeout_ms} ms: the drive has taken its communication-loss reaction"
            ),
            Self::EnableTimeout { state, ms } => match state {
                Some(s) => write!(f, "drive did not reach operation enabled within {ms} ms (stuck in {s})"),
                None => write!(f, "drive did not reach operation enabled within {ms} ms (no statusword received)"),
            },
            Self::BusOff => write!(
                f,
                "the CAN interface went bus-off (wiring, termination, bit rate or a babbling node); the socket was restarted and every device is booted again on re-arm"
            ),
        }
    }
}

/// Feedback decoded from a TPDO, in SI units at the joint.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Event {
    /// Nothing for the controller (NMT, SDO, EMCY, statusword …).
    None,
    /// Steering drive TPDO1.
    Steer {
        /// Wheel index.
        wheel: usize,
        /// Steering angle φ (rad), position + homing offset, not wrapped.
        angle: f64,
        /// Steering rate (rad/s).
        rate: f64,
        /// Count of this drive's TPDO1s, modulo 16 (the sequence of its samples).
        seq: u8,
    },
    /// Rolling drive TPDO1.
    Drive {
        /// Wheel index.
        wheel: usize,
        /// Wheel spin rate ω (rad/s).
        speed: f64,
        /// Wheel angle (rad), from the position counter, not wrapped.
        angle: f64,
    },
    /// Leg encoder TPDO1.
    Leg {
        /// Wheel index.
        wheel: usize,
        /// Leg extension λ (m).
        leg: f64,
        /// Leg rate (m/s).
        rate: f64,
    },
}

/// Why a received frame was not used.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Reject {
    /// A frame of a node this platform does not have.
    UnknownNode,
    /// Not a COB-ID of the predefined connection set.
    UnknownId,
    /// A frame of the right kind with the wrong length or an invalid value.
    Malformed,
    /// A frame only a master sends (SYNC, NMT, RPDO, SDO request): another master on the bus.
    ForeignMaster,
    /// An SDO response that matches no request in flight, or PDO data from a device that is
    /// not started.
    Unexpected,
}

impl Reject {
    /// Short name, as recorded.
    pub fn kind(self) -> &'static str {
        match self {
            Self::UnknownNode => "unknown_node",
            Self::UnknownId => "unknown_id",
            Self::Malformed => "malformed",
            Self::ForeignMaster => "foreign_master",
            Self::Unexpected => "unexpected",
        }
    }
}

/// Where a device is in its boot.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum BootState {
    /// An NMT reset is due.
    NeedsReset,
    /// Reset sent at this time; waiting for the boot-up.
    ResetSent(f64),
    /// Running the SDO plan.
    Configuring,
    /// Plan done; NMT start due.
    Configured,
    /// Operational.
    Started,
    /// The boot failed (see the device's fault).
    Failed,
    /// Was started, then left operational (rebooted, heartbeat lost, other NMT state).
    Lost,
}

/// Where a steering drive is in its homing.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum HomingState {
    /// Booted, not homed: its steering angle means nothing yet.
    NotHomed,
    /// Homing, in this phase.
    Running(HomingPhase),
    /// Homed (or nothing to do: rolling drives, encoders, `none`).
    Done,
    /// Homing failed (see the device's fault).
    Failed,
}

/// What an SDO request in flight is for.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Purpose {
    /// A step of the boot plan (or of the switch back after homing).
    Plan,
    /// A read after a fault (0x603F, 0x1003:01): its value goes into the fault.
    Diagnosis,
}

/// Number of EMCY messages kept per device.
pub const EMCY_HISTORY: usize = 8;
/// Optional plan steps remembered per device as skipped.
pub const MAX_SKIPPED: usize = 12;
/// Fault-reset edges the master sends to a drive in fault during the grace period.
const MAX_RESET_EDGES: u8 = 8;

/// What the master knows about one device.
#[derive(Clone, Copy, Debug)]
pub struct Device {
    /// Wheel index.
    pub wheel: usize,
    /// Role.
    pub role: Role,
    /// Node-ID.
    pub node: u8,
    /// Boot progress.
    pub boot: BootState,
    /// Homing progress (steering drives; `Done` for the others).
    pub homing: HomingState,
    /// Last NMT state seen in a boot-up or heartbeat.
    pub nmt: Option<NmtState>,
    /// Time of the last boot-up or heartbeat (or of the NMT start).
    pub last_heartbeat: Option<f64>,
    /// Last statusword (drives).
    pub statusword: Option<u16>,
    /// Last digital inputs 0x60FD (drives that map them into TPDO2).
    pub inputs: Option<u32>,
    /// Last controlword sent (drives).
    pub controlword: u16,
    /// Latched fault.
    pub fault: Option<DeviceFault>,
    /// Last EMCY received (also after a reset message).
    pub last_emcy: Option<Emcy>,
    /// EMCYs received: informational ones (not faults).
    pub emcy_informational: u32,
    /// EMCYs received: faults.
    pub emcy_faults: u32,
    /// Error code 0x603F read after the last fault.
    pub error_code: Option<u16>,
    /// Newest entry of the pre-defined error field 0x1003:01, read after the last fault.
    pub error_history: Option<u32>,
    /// Boots (boot-ups after a reset or power-on) seen.
    pub boots: u32,
    emcy_hist: [Option<(f64, Emcy)>; EMCY_HISTORY],
    emcy_next: usize,
    skipped: [(u16, u8); MAX_SKIPPED],
    n_skipped: usize,
    plan: usize,
    after_homing: bool,
    plan_pos: usize,
    inflight: Option<(SdoOp, f64, u8, Purpose)>,
    poll_since: Option<f64>,
    diag: [Option<(u16, u8)>; 2],
    enable_since: Option<f64>,
    reset_grace_until: f64,
    reset_edges: u8,
    tpdo_seq: u8,
    hb_lost_reported: bool,
    homing_since: f64,
    home_cmd: f64,
    home_travel: f64,
    pos_zero: i64,
    last_pos: Option<(i32, f64, f64)>,
    last_rate: f64,
    stopped_cycles: u32,
    home_armed: bool,
    input_edge_at: f64,
    started_at: f64,
    confirmed: bool,
}

impl Device {
    fn new(wheel: usize, role: Role, node: u8, plan: usize) -> Self {
        Self {
            wheel,
            role,
            node,
            boot: BootState::NeedsReset,
            homing: HomingState::Done,
            nmt: None,
            last_heartbeat: None,
            statusword: None,
            inputs: None,
            controlword: 0,
            fault: None,
            last_emcy: None,
            emcy_informational: 0,
            emcy_faults: 0,
            error_code: None,
            error_history: None,
            boots: 0,
            emcy_hist: [None; EMCY_HISTORY],
            emcy_next: 0,
            skipped: [(0, 0); MAX_SKIPPED],
            n_skipped: 0,
            plan,
            after_homing: false,
            plan_pos: 0,
            inflight: None,
            poll_since: None,
            diag: [None; 2],
            enable_since: None,
            reset_grace_until: f64::NEG_INFINITY,
            reset_edges: 0,
            tpdo_seq: 0,
            hb_lost_reported: false,
            homing_since: 0.0,
            home_cmd: 0.0,
            home_travel: 0.0,
            pos_zero: 0,
            last_pos: None,
            last_rate: 0.0,
            stopped_cycles: 0,
            home_armed: false,
            input_edge_at: 0.0,
            started_at: 0.0,
            confirmed: false,
        }
    }

    /// The 402 state from the last statusword (drives).
    pub fn state402(&self) -> Option<State402> {
        self.statusword.and_then(State402::from_statusword)
    }

    /// Optional plan steps the device did not have (skipped), in plan order.
    pub fn skipped(&self) -> &[(u16, u8)] {
        &self.skipped[..self.n_skipped]
    }

    /// The last EMCYs (at most [`EMCY_HISTORY`]) with their receive times, oldest first.
    pub fn emcy_history(&self) -> impl Iterator<Item = (f64, Emcy)> + '_ {
        (0..EMCY_HISTORY).filter_map(move |k| self.emcy_hist[(self.emcy_next + k) % EMCY_HISTORY])
    }

    fn latch(&mut self, f: DeviceFault) {
        if self.fault.is_none() {
            self.fault = Some(f);
        }
    }

    /// Queues the reads that go into a drive's fault (error code, newest error history).
    fn diagnose(&mut self) {
        if self.role != Role::Leg && self.diag == [None; 2] && self.error_code.is_none() {
            self.diag = [
                Some((od::ERROR_CODE, 0)),
                Some((od::PRE_DEFINED_ERROR_FIELD, 1)),
            ];
        }
    }
}

const NO_DEVICE: u8 = 0xFF;

/// The master; see the module docs.
#[derive(Clone, Debug)]
pub struct Master {
    cfg: Cia402Config,
    period_us: u32,
    devices: Vec<Device>,
    by_node: [u8; 128],
    plans: Vec<Vec<SdoOp>>,
    after_homing: [SdoOp; 2],
    status: ([MapEntry; 8], usize),
    next_master_hb: f64,
    now: f64,
    last_start: Option<f64>,
    failure: Option<(usize, BootError)>,
    tx_overflow: u32,
    homing_allowed: bool,
    homed_moves: u32,
    bus_off: u32,
    /// Quick stop commanded ([`Master::quick_stop`]), until the next re-arm.
    quick_stop: bool,
    quick_stops: u32,
}

impl Master {
    /// A master for `cfg` on a platform of `wheels` wheels with control period `period_s`.
    /// The configuration must have been validated ([`Cia402Config::validate`]); every device
    /// starts in [`BootState::NeedsReset`].
    pub fn new(cfg: &Cia402Config, period_s: f64) -> Self {
        let period_us = (period_s * 1e6).round().clamp(1.0, 255_000.0) as u32;
        let mut plans = Vec::new();
        let devices: Vec<Device> = cfg
            .devices()
            .map(|(w, r, n)| {
                plans.push(cfg.plan_for(w, r, period_us));
                Device::new(w, r, n, plans.len() - 1)
            })
            .collect();
        let mut by_node = [NO_DEVICE; 128];
        for (i, d) in devices.iter().enumerate() {
            by_node[usize::from(d.node & 0x7F)] = i as u8;
        }
        Self {
            cfg: cfg.clone(),
            period_us,
            devices,
            by_node,
            plans,
            after_homing: cfg.after_homing_plan(),
            status: cfg.status_entries(),
            next_master_hb: 0.0,
            now: 0.0,
            last_start: None,
            failure: None,
            tx_overflow: 0,
            homing_allowed: false,
            homed_moves: 0,
            bus_off: 0,
            quick_stop: false,
            quick_stops: 0,
        }
    }

    /// The configuration.
    pub fn config(&self) -> &Cia402Config {
        &self.cfg
    }

    /// Every device, wheel by wheel (drive, steer, leg).
    pub fn devices(&self) -> &[Device] {
        &self.devices
    }

    /// Frames the caller's buffer refused (never expected with [`FrameBuf`]'s capacity).
    pub fn tx_overflow(&self) -> u32 {
        self.tx_overflow
    }

    /// True when every device is started (configured and operational).
    pub fn started(&self) -> bool {
        self.devices.iter().all(|d| d.boot == BootState::Started)
    }

    /// True when every device is started and every steering drive is homed.
    pub fn ready(&self) -> bool {
        self.devices
            .iter()
            .all(|d| d.boot == BootState::Started && d.homing == HomingState::Done)
    }

    /// True while some device is still being reset, configured or homed (and none failed).
    pub fn booting(&self) -> bool {
        self.failure.is_none() && !self.ready()
    }

    /// Homings that moved an axis since the master was made (the rest alignment after
    /// homing runs when this changes).
    pub fn homed_moves(&self) -> u32 {
        self.homed_moves
    }

    /// The homing of wheel `wheel`'s steering drive.
    pub fn homing(&self, wheel: usize) -> HomingState {
        self.devices
            .iter()
            .find(|d| d.wheel == wheel && d.role == Role::Steer)
            .map_or(HomingState::Done, |d| d.homing)
    }

    /// Times the bus went bus-off ([`Master::bus_off`]).
    pub fn bus_offs(&self) -> u32 {
        self.bus_off
    }

    /// The first boot failure since the last re-arm, as (wheel, error).
    pub fn boot_failure(&self) -> Option<(usize, BootError)> {
        self.failure
    }

    /// The first latched fault among wheel `wheel`'s devices, as (node, role, fault).
    pub fn wheel_fault(&self, wheel: usize) -> Option<(u8, Role, DeviceFault)> {
        self.devices
            .iter()
            .filter(|d| d.wheel == wheel)
            .find_map(|d| d.fault.map(|f| (d.node, d.role, f)))
    }

    /// A summary of wheel `wheel` in the native profile's terms (for records): Fault when a
    /// device has a latched fault or a drive is in fault, Enabled when both drives are in
    /// operation enabled, Ready when every device is started, Boot otherwise.
    pub fn wheel_state(&self, wheel: usize) -> ModuleState {
        let devs = || self.devices.iter().filter(move |d| d.wheel == wheel);
        if devs().any(|d| d.fault.is_some() || d.state402().is_some_and(|s| s.is_fault())) {
            return ModuleState::Fault;
        }
        if devs().any(|d| d.boot != BootState::Started) {
            return ModuleState::Boot;
        }
        if devs()
            .filter(|d| d.role != Role::Leg)
            .all(|d| d.state402() == Some(State402::OperationEnabled))
        {
            ModuleState::Enabled
        } else {
            ModuleState::Ready
        }
    }

    /// The node of a wheel's device.
    pub fn node(&self, wheel: usize, role: Role) -> Option<u8> {
        self.cfg.wheels.get(wheel).map(|w| w.node(role))
    }

    /// Clears every latched fault and boot failure; devices that are not started (never
    /// booted, failed, rebooted, lost) are reset and configured again, and steering drives
    /// that booted since they were homed are homed again. Call it when the operator arms or
    /// re-arms, with the platform at rest: homing moves only after the first call. `t` starts
    /// the grace period in which a drive still in fault (its statusword) is not latched: the
    /// master sends it the fault-reset edge (whatever the setpoints say), however late its
    /// statusword comes.
    ///
    /// Devices that boot again get their grace period from the cycle in which every device
    /// runs (the controller arms only then): a drive that faulted on its own while no master
    /// was there (communication loss after a crash) is cleared by the next master instead of
    /// failing its arming; one whose fault persists is reported when the grace period ends.
    pub fn rearm(&mut self, t: f64) {
        self.failure = None;
        self.quick_stop = false;
        self.homing_allowed = true;
        let grace = t + f64::from(self.cfg.enable_timeout_ms) * 1e-3;
        for d in &mut self.devices {
            d.fault = None;
            d.enable_since = None;
            d.hb_lost_reported = false;
            d.reset_edges = 0;
            d.error_code = None;
            d.error_history = None;
            d.diag = [None; 2];
            if d.homing == HomingState::Failed {
                d.homing = HomingState::NotHomed;
            }
            if d.boot == BootState::Started && d.homing == HomingState::Done {
                d.reset_grace_until = grace;
            } else {
                if d.boot != BootState::Started {
                    d.boot = BootState::NeedsReset;
                }
                d.reset_grace_until = f64::INFINITY;
            }
        }
    }

    /// The host cannot ramp the drives down itself (feedback lost, bus stalled beyond the
    /// stale limit, a fatal error with the drives enabled): from the next
    /// [`Master::finish_cycle`] on, every drive in operation enabled gets the Quick Stop
    /// command (controlword 0x0002, CiA 402 transition 11) and keeps getting it while in
    /// quick stop active, so that it stops on its own quick-stop ramp (0x605A option, 0x6085
    /// deceleration, both written at boot from `[cia402.quick_stop]`); drives in other
    /// states are not enabled again. Homings in progress end. Until the next re-arm.
    pub fn quick_stop(&mut self) {
        if !self.quick_stop {
            self.quick_stops = self.quick_stops.saturating_add(1);
        }
        self.quick_stop = true;
    }

    /// True while a quick stop is commanded ([`Master::quick_stop`]).
    pub fn quick_stopping(&self) -> bool {
        self.quick_stop
    }

    /// Quick stops commanded since start-up.
    pub fn quick_stops(&self) -> u32 {
        self.quick_stops
    }

    /// The controller's CAN interface went bus-off (and was restarted by the caller): every
    /// device is taken as lost (it may have missed anything meanwhile), the fault is latched
    /// on every device until the operator re-arms, which boots them all again.
    pub fn bus_off(&mut self) {
        self.bus_off = self.bus_off.saturating_add(1);
        for d in &mut self.devices {
            d.latch(DeviceFault::BusOff);
            d.boot = BootState::Lost;
            d.inflight = None;
        }
    }

    /// Hands the devices back at the clean end of a run, after the drives were told to
    /// disable: NMT reset communication to every device. Their communication objects return
    /// to the power-on values, so they stop expecting our heartbeat and RPDOs (no
    /// communication-loss EMCY or reaction once we are gone) and wait, pre-operational and
    /// disabled, for the next master. A process that dies instead leaves them monitoring:
    /// that is the fail-safe path. A later [`Master::start_cycle`] boots them again.
    pub fn release(&mut self, out: &mut FrameBuf) {
        for i in 0..self.devices.len() {
            let node = self.devices[i].node;
            self.push(out, nmt::command(NmtCommand::ResetCommunication, node));
            let d = &mut self.devices[i];
            d.boot = BootState::NeedsReset;
            d.inflight = None;
            d.nmt = None;
            d.statusword = None;
        }
    }

    fn push(&mut self, out: &mut FrameBuf, f: CanFrame) {
        if !out.push(f) {
            self.tx_overflow = self.tx_overflow.saturating_add(1);
        }
    }

    fn fail(&mut self, i: usize, e: BootError) {
        let d = &mut self.devices[i];
        d.boot = BootState::Failed;
        d.inflight = None;
        d.latch(DeviceFault::Boot(e));
        if self.failure.is_none() {
            self.failure = Some((d.wheel, e));
        }
    }

    fn fail_homing(&mut self, i: usize, error: HomingError) {
        let d = &mut self.devices[i];
        d.homing = HomingState::Failed;
        let e = BootError::Homing {
            node: d.node,
            role: d.role,
            error,
        };
        d.latch(DeviceFault::Boot(e));
        if self.failure.is_none() {
            self.failure = Some((d.wheel, e));
        }
    }

    /// Start of a cycle at `t` (s): SYNC, then NMT commands, the master's heartbeat and SDO
    /// requests that are due; boot, homing and heartbeat timeouts are checked.
    pub fn start_cycle(&mut self, t: f64, out: &mut FrameBuf) {
        self.now = t;
        // A gap in our own cycles longer than the drives' consumer time: they have reacted to
        // the missing heartbeat (and RPDOs) while we were away; say so now rather than when
        // their statuswords or our heartbeat timeout tell.
        if let Some(prev) = self.last_start {
            let gap_ms = (t - prev) * 1e3;
            if gap_ms > f64::from(self.cfg.device_heartbeat_timeout_ms) {
                for d in &mut self.devices {
                    if d.role != Role::Leg && d.boot == BootState::Started {
                        d.latch(DeviceFault::MasterSilent {
                            ms: gap_ms.round().min(f64::from(u32::MAX)) as u32,
                            timeout_ms: self.cfg.device_heartbeat_timeout_ms,
                        });
                    }
                }
            }
        }
        // Frames are read after the cycle starts: the heartbeats seen so far are those read
        // up to the previous cycle, so a device's silence is judged as of then. Judged as of
        // `t`, a device that lost two heartbeats in a row faulted in the very cycle its third
        // arrived, exactly one consumer time after the last (100 ms producer, 300 ms consumer:
        // CiA 402 seed 000 at 1 % frame loss faulted at 4.3 s, `fault-campaign` case 32).
        let seen_until = self.last_start.unwrap_or(t);
        self.last_start = Some(t);
        self.push(out, nmt::sync());
        if t >= self.next_master_hb {
            self.push(
                out,
                nmt::heartbeat(self.cfg.master_node, NmtState::Operational),
            );
            let p = f64::from(self.cfg.master_heartbeat_ms) * 1e-3;
            // Stay on the grid of the first heartbeat unless we fell behind by a period.
            self.next_master_hb = if t - self.next_master_hb > p {
                t + p
            } else {
                self.next_master_hb + p
            };
        }
        let boot_timeout = f64::from(self.cfg.boot_timeout_ms) * 1e-3;
        let hb_timeout = f64::from(self.cfg.master_heartbeat_timeout_ms) * 1e-3;
        for i in 0..self.devices.len() {
            let d = self.devices[i];
            match d.boot {
                BootState::NeedsReset => {
                    self.push(out, nmt::command(NmtCommand::ResetCommunication, d.node));
                    let dev = &mut self.devices[i];
                    dev.boot = BootState::ResetSent(t);
                    dev.nmt = None;
                    dev.statusword = None;
                    dev.inflight = None;
                    dev.plan_pos = 0;
                    dev.after_homing = false;
                }
                BootState::ResetSent(at) if t - at > boot_timeout => self.fail(
                    i,
                    BootError::NoBootUp {
                        node: d.node,
                        role: d.role,
                        ms: self.cfg.boot_timeout_ms,
                    },
                ),
                BootState::Configured => {
                    self.push(out, nmt::command(NmtCommand::Start, d.node));
                    let dev = &mut self.devices[i];
                    dev.boot = BootState::Started;
                    dev.nmt = Some(NmtState::Operational);
                    dev.last_heartbeat = Some(t);
                    dev.started_at = t;
                    dev.confirmed = false;
                }
                BootState::Started => {
                    let last = d.last_heartbeat.unwrap_or(seen_until);
                    if seen_until - last > hb_timeout && !d.hb_lost_reported {
                        let dev = &mut self.devices[i];
                        dev.hb_lost_reported = true;
                        dev.boot = BootState::Lost;
                        dev.latch(DeviceFault::HeartbeatLost {
                            ms: self.cfg.master_heartbeat_timeout_ms,
                        });
                    }
                }
                _ => {}
            }
        }
        self.homing_timeouts(t);
        // Everything runs: the grace periods of a re-arm start now (see `rearm`).
        if self.ready() {
            let grace = t + f64::from(self.cfg.enable_timeout_ms) * 1e-3;
            for d in &mut self.devices {
                if d.reset_grace_until == f64::INFINITY {
                    d.reset_grace_until = grace;
                    d.reset_edges = 0;
                }
            }
        }
        self.service_sdo(t, out);
    }

    /// After the frames that came in between the last cycle's window and this cycle's
    /// start were taken ([`Master::on_frame`], stamped before this cycle's SYNC): the SDO
    /// requests they made due (the next step of a device whose answer to the request sent
    /// at the end of the last cycle just came), sent right after the SYNC. Without this
    /// call a device gets one SDO request per cycle (the answer to the end-of-cycle request
    /// comes after the window and is only read after the next start); with it, two.
    pub fn service(&mut self, t: f64, out: &mut FrameBuf) {
        self.now = self.now.max(t);
        self.service_sdo(t, out);
    }

    fn homing_timeouts(&mut self, t: f64) {
        for i in 0..self.devices.len() {
            let d = self.devices[i];
            if let HomingState::Running(phase) = d.homing {
                let h = self.cfg.homing_of(d.wheel);
                if (t - d.homing_since) * 1e3 > f64::from(h.timeout_ms) {
                    self.fail_homing(
                        i,
                        HomingError::Timeout {
                            ms: h.timeout_ms,
                            phase,
                            statusword: d.statusword,
                        },
                    );
                }
            }
        }
    }

    fn current_op(&self, d: &Device) -> Option<SdoOp> {
        if d.after_homing {
            self.after_homing.get(d.plan_pos).copied()
        } else {
            self.plans[d.plan].get(d.plan_pos).copied()
        }
    }

    /// Sends the next SDO request of every configuring device (or one switching back after
    /// homing, or one with a fault to diagnose) without one in flight, and repeats (or
    /// fails) requests that timed out.
    fn service_sdo(&mut self, t: f64, out: &mut FrameBuf) {
        let timeout = f64::from(self.cfg.sdo_timeout_ms) * 1e-3;
        for i in 0..self.devices.len() {
            let d = self.devices[i];
            let configuring = d.boot == BootState::Configuring
                || (d.boot == BootState::Started && d.after_homing);
            let diagnosing = d.boot == BootState::Started && d.diag.iter().any(Option::is_some);
            if !configuring && !diagnosing && d.inflight.is_none() {
                continue;
            }
            match d.inflight {
                Some((op, sent, tries, purpose)) => {
                    if t - sent <= timeout {
                        continue;
                    }
                    if tries > self.cfg.sdo_retries || purpose == Purpose::Diagnosis {
                        let (index, sub) = op.object();
                        // Tell the device the transfer is over before giving up on it.
                        self.push(
                            out,
                            SdoRequest::Abort {
                                index,
                                sub,
                                code: AbortCode::Timeout,
                            }
                            .to_frame(d.node),
                        );
                        if purpose == Purpose::Diagnosis {
                            self.devices[i].inflight = None;
                            continue;
                        }
                        self.fail(
                            i,
                            BootError::SdoTimeout {
                                node: d.node,
                                role: d.role,
                                index,
                                sub,
                                tries,
                                timeout_ms: self.cfg.sdo_timeout_ms,
                            },
                        );
                        continue;
                    }
                    self.push(out, request_frame(&op, d.node));
                    self.devices[i].inflight = Some((op, t, tries + 1, purpose));
                }
                None if configuring => match self.current_op(&d) {
                    Some(op) => {
                        let op = super::config::for_node(op, d.node);
                        self.push(out, request_frame(&op, d.node));
                        self.devices[i].inflight = Some((op, t, 1, Purpose::Plan));
                    }
                    None => {
                        let dev = &mut self.devices[i];
                        if dev.after_homing {
                            dev.after_homing = false;
                            dev.homing = HomingState::Done;
                        } else {
                            dev.boot = BootState::Configured;
                        }
                    }
                },
                None => {
                    let dev = &mut self.devices[i];
                    if let Some(k) = dev.diag.iter().position(Option::is_some) {
                        let (index, sub) = dev.diag[k].take().unwrap_or((0, 0));
                        let op = SdoOp::Verify {
                            index,
                            sub,
                            mask: 0,
                            expected: 0,
                            what: "diagnosis",
                            poll_ms: 0,
                            optional: true,
                        };
                        dev.inflight = Some((op, t, 1, Purpose::Diagnosis));
                        self.push(out, SdoRequest::Upload { index, sub }.to_frame(d.node));
                    }
                }
            }
        }
    }

    /// End of the cycle at `t`: one RPDO1 per drive of every started wheel from
    /// `setpoints[wheel]` (SI, the native profile's setpoint type) — or from the homing for a
    /// wheel being homed —, then the SDO requests that became due during the cycle. Drives
    /// of wheels without a setpoint get a disabled zero.
    pub fn finish_cycle(&mut self, t: f64, setpoints: &[Setpoint], out: &mut FrameBuf) {
        self.now = t;
        self.start_homings(t);
        let enable_timeout = f64::from(self.cfg.enable_timeout_ms) * 1e-3;
        for i in 0..self.devices.len() {
            let d = self.devices[i];
            if d.role == Role::Leg || d.boot != BootState::Started {
                continue;
            }
            let quick_stop = self.quick_stop.then(|| {
                let state = d.state402();
                let cw = match state {
                    Some(State402::OperationEnabled | State402::QuickStopActive) => {
                        ds402::CW_QUICK_STOP_CMD
                    }
                    _ => ds402::master_controlword(state, false, false, false, d.controlword),
                };
                (cw, 0)
            });
            let (cw, target) = match quick_stop.or_else(|| self.homing_command(i)) {
                Some(c) => c,
                None => {
                    let sp = setpoints.get(d.wheel).copied().unwrap_or_default();
                    let units = match d.role {
                        Role::Drive => self.cfg.drive,
                        _ => self.cfg.steer,
                    };
                    let rate = match d.role {
                        Role::Drive => sp.wheel_speed,
                        _ => sp.steer_rate,
                    };
                    let state = d.state402();
                    let enable = sp.flags.enable;
                    let mut halt = sp.flags.brake;
                    let enabled = state == Some(State402::OperationEnabled);
                    let target = if enabled && enable && !halt {
                        match units.velocity_from_si(rate) {
                            Some(v) => v,
                            None => {
                                halt = true;
                                0
                            }
                        }
                    } else {
                        0
                    };
                    let reset = sp.flags.fault_reset || self.grace_reset(i, t);
                    let cw = ds402::master_controlword(state, enable, halt, reset, d.controlword);
                    let dev = &mut self.devices[i];
                    // Enable supervision: asked to enable and not there yet.
                    if enable && !enabled && !state.is_some_and(|s| s.is_fault()) {
                        let since = *dev.enable_since.get_or_insert(t);
                        if t - since > enable_timeout {
                            dev.latch(DeviceFault::EnableTimeout {
                                state,
                                ms: self.cfg.enable_timeout_ms,
                            });
                        }
                    } else {
                        dev.enable_since = None;
                    }
                    (cw, target)
                }
            };
            let dev = &mut self.devices[i];
            if cw & ds402::CW_FAULT_RESET != 0 && dev.controlword & ds402::CW_FAULT_RESET == 0 {
                dev.reset_edges = dev.reset_edges.saturating_add(1);
            }
            dev.controlword = cw;
            self.push(
                out,
                pdo::DRIVE_RPDO1.pack(d.node, &[u32::from(cw), target as u32]),
            );
        }
        self.service_sdo(t, out);
    }

    /// True while drive `i` in fault should get the fault-reset edge on the master's own
    /// account: inside its grace period after a (re-)arm or boot, a bounded number of times.
    fn grace_reset(&self, i: usize, t: f64) -> bool {
        let d = &self.devices[i];
        d.state402().is_some_and(|s| s == State402::Fault)
            && t < d.reset_grace_until
            && d.reset_edges < MAX_RESET_EDGES
    }

    /// Starts the homing of every steering drive whose wheel's drives all run, once the
    /// operator asked to arm.
    fn start_homings(&mut self, t: f64) {
        if !self.homing_allowed || self.failure.is_some() {
            return;
        }
        for i in 0..self.devices.len() {
            let d = self.devices[i];
            if d.role != Role::Steer || d.homing != HomingState::NotHomed {
                continue;
            }
            let wheel_runs = self
                .devices
                .iter()
                .filter(|o| o.wheel == d.wheel && o.role != Role::Leg)
                .all(|o| o.boot == BootState::Started);
            if !wheel_runs || d.boot != BootState::Started {
                continue;
            }
            let h = self.cfg.homing_of(d.wheel);
            let dev = &mut self.devices[i];
            match h.kind {
                HomingKind::None => dev.homing = HomingState::Done,
                HomingKind::Absolute => {
                    // Checked on the first position that arrives (`on_tpdo`).
                    dev.homing = HomingState::Running(HomingPhase::Searching);
                    dev.homing_since = t;
                }
                HomingKind::Drive | HomingKind::DigitalInput => {
                    dev.homing = HomingState::Running(HomingPhase::Enabling);
                    dev.homing_since = t;
                    dev.home_cmd = 0.0;
                    dev.home_travel = 0.0;
                    dev.stopped_cycles = 0;
                    dev.home_armed = false;
                    dev.enable_since = None;
                }
            }
        }
    }

    /// The controlword and target velocity of drive `i` while its wheel is homed (`None`
    /// when the wheel is not being homed).
    fn homing_command(&mut self, i: usize) -> Option<(u16, i32)> {
        let d = self.devices[i];
        let steer_i = self
            .devices
            .iter()
            .position(|o| o.wheel == d.wheel && o.role == Role::Steer)?;
        let steer = self.devices[steer_i];
        let HomingState::Running(phase) = steer.homing else {
            return None;
        };
        let h = self.cfg.homing_of(d.wheel);
        if h.kind == HomingKind::Absolute {
            return None;
        }
        let dt = f64::from(self.period_us) * 1e-6;
        let state = d.state402();
        let reset = state == Some(State402::Fault) && d.reset_edges < MAX_RESET_EDGES;
        if state == Some(State402::Fault) && d.reset_edges >= MAX_RESET_EDGES {
            self.fail_homing(
                steer_i,
                HomingError::Faulted {
                    statusword: d.statusword.unwrap_or(0),
                },
            );
            return Some((ds402::CW_DISABLE_VOLTAGE, 0));
        }
        if d.role == Role::Drive {
            // The rolling drive holds the wheel: enabled, and counter-turned against the
            // steer→drive coupling.
            let rate = -self.cfg.coupling * steer.last_rate;
            let enabled = state == Some(State402::OperationEnabled);
            let target = if enabled {
                self.cfg.drive.velocity_from_si(rate).unwrap_or(0)
            } else {
                0
            };
            let cw = ds402::master_controlword(state, true, false, reset, d.controlword);
            return Some((cw, target));
        }
        let enabled = state == Some(State402::OperationEnabled);
        let set = |m: &mut Master, p: HomingPhase| {
            m.devices[i].homing = HomingState::Running(p);
        };
        match (h.kind, phase) {
            (_, HomingPhase::Enabling) => {
                let cw = ds402::master_controlword(state, true, false, reset, d.controlword);
                if enabled {
                    set(self, HomingPhase::Searching);
                    if h.kind == HomingKind::Drive {
                        return Some((ds402::CW_ENABLE_OPERATION_CMD | CW_HOMING_START, 0));
                    }
                }
                Some((cw, 0))
            }
            (HomingKind::Drive, HomingPhase::Searching) => {
                let sw = d.statusword.unwrap_or(0);
                if sw & SW_HOMING_ERROR != 0 {
                    self.fail_homing(i, HomingError::DriveError { statusword: sw });
                    return Some((ds402::CW_SHUTDOWN, 0));
                }
                // Attained only counts once the start bit was seen (the statusword after it).
                if d.controlword & CW_HOMING_START != 0
                    && sw & SW_HOMING_ATTAINED != 0
                    && sw & ds402::SW_TARGET_REACHED != 0
                {
                    set(self, HomingPhase::Stopping);
                    return Some((ds402::CW_SHUTDOWN, 0));
                }
                if !enabled {
                    let cw = ds402::master_controlword(state, true, false, reset, d.controlword);
                    return Some((cw, 0));
                }
                Some((ds402::CW_ENABLE_OPERATION_CMD | CW_HOMING_START, 0))
            }
            (HomingKind::Drive, HomingPhase::Stopping) => {
                if state.is_some_and(|s| s != State402::OperationEnabled) {
                    // Switch back to cyclic synchronous velocity by SDO, drive disabled.
                    let dev = &mut self.devices[i];
                    dev.after_homing = true;
                    dev.plan_pos = 0;
                    dev.poll_since = None;
                    dev.pos_zero = 0;
                    set(self, HomingPhase::SwitchingMode);
                    if h.moves() {
                        self.homed_moves += 1;
                    }
                }
                Some((ds402::CW_SHUTDOWN, 0))
            }
            (_, HomingPhase::SwitchingMode) => Some((ds402::CW_SHUTDOWN, 0)),
            (HomingKind::DigitalInput, HomingPhase::Searching) => {
                if !enabled {
                    let cw = ds402::master_controlword(state, true, false, reset, d.controlword);
                    return Some((cw, 0));
                }
                let dir = h.switch_speed_rad_s;
                let a = h.accel_rad_s2 * dt;
                let dev = &mut self.devices[i];
                dev.home_travel += dev.last_rate.abs() * dt;
                let input = dev
                    .inputs
                    .is_some_and(|v| v & (1u32 << (h.input_bit & 31)) != 0);
                // The input must rise while turning at `dir`: an axis that starts with it set
                // first turns the other way until it clears.
                if !input {
                    dev.home_armed = true;
                }
                if input && dev.home_armed {
                    // The home position: where the axis was when the input rose (the last
                    // position sample carried forward at its rate to the input's frame).
                    if let Some((pos, at, rate)) = dev.last_pos {
                        let units = self.cfg.steer;
                        let carried = rate
                            * (dev.input_edge_at - at).clamp(-0.02, 0.02)
                            * units.increments_per_joint_rev()
                            / std::f64::consts::TAU;
                        dev.pos_zero = i64::from(pos) + carried.round() as i64;
                    }
                    set(self, HomingPhase::Stopping);
                    return self.homing_command(i);
                }
                if dev.home_travel > 1.25 * std::f64::consts::TAU {
                    let turns = dev.home_travel / std::f64::consts::TAU;
                    self.fail_homing(
                        i,
                        HomingError::InputNeverSeen {
                            bit: h.input_bit,
                            turns,
                        },
                    );
                    return Some((ds402::CW_SHUTDOWN, 0));
                }
                let dev = &mut self.devices[i];
                let want = if dev.home_armed { dir } else { -dir };
                let c = dev.home_cmd;
                dev.home_cmd = if (want - c).abs() <= a {
                    want
                } else {
                    c + a.copysign(want - c)
                };
                let v = self.cfg.steer.velocity_from_si(dev.home_cmd).unwrap_or(0);
                Some((ds402::CW_ENABLE_OPERATION_CMD, v))
            }
            (HomingKind::DigitalInput, HomingPhase::Stopping) => {
                let a = h.accel_rad_s2 * dt;
                let dev = &mut self.devices[i];
                let c = dev.home_cmd;
                dev.home_cmd = if c.abs() <= a { 0.0 } else { c - a.copysign(c) };
                if dev.home_cmd == 0.0 && dev.last_rate.abs() < 0.01 {
                    dev.stopped_cycles += 1;
                } else {
                    dev.stopped_cycles = 0;
                }
                if dev.stopped_cycles >= 3 {
                    dev.homing = HomingState::Done;
                    self.homed_moves += 1;
                    return Some((ds402::CW_SHUTDOWN, 0));
                }
                let v = self.cfg.steer.velocity_from_si(dev.home_cmd).unwrap_or(0);
                Some((ds402::CW_ENABLE_OPERATION_CMD, v))
            }
            _ => None,
        }
    }

    /// Takes one received frame at `t`.
    pub fn on_frame(&mut self, f: &CanFrame, t: f64) -> Result<Event, Reject> {
        self.now = self.now.max(t);
        let node = match cob::classify(f.id()) {
            Cob::Sync | Cob::Nmt | Cob::Rpdo(..) | Cob::SdoRx(_) => {
                return Err(Reject::ForeignMaster)
            }
            Cob::Other => return Err(Reject::UnknownId),
            Cob::Emcy(n) | Cob::Tpdo(_, n) | Cob::SdoTx(n) | Cob::Heartbeat(n) => n,
        };
        let ix = self.by_node[usize::from(node & 0x7F)];
        if ix == NO_DEVICE {
            // The master's own heartbeat looped back, or a device we do not know.
            return Err(Reject::UnknownNode);
        }
        let i = usize::from(ix);
        match cob::classify(f.id()) {
            Cob::Heartbeat(_) => self.on_heartbeat(i, f, t),
            Cob::SdoTx(_) => self.on_sdo(i, f, t),
            Cob::Emcy(_) => {
                let (_, e) = Emcy::parse(f).map_err(|_| Reject::Malformed)?;
                let info = emcy::is_informational(&e, &self.cfg.informational_emcy);
                let d = &mut self.devices[i];
                d.last_emcy = Some(e);
                d.emcy_hist[d.emcy_next] = Some((t, e));
                d.emcy_next = (d.emcy_next + 1) % EMCY_HISTORY;
                if e.is_reset() {
                } else if info {
                    d.emcy_informational = d.emcy_informational.saturating_add(1);
                } else {
                    d.emcy_faults = d.emcy_faults.saturating_add(1);
                    d.latch(DeviceFault::Emcy {
                        code: e.code,
                        register: e.register,
                        read_back: None,
                    });
                    d.diagnose();
                }
                Ok(Event::None)
            }
            Cob::Tpdo(n, _) => self.on_tpdo(i, n, f, t),
            _ => Err(Reject::UnknownId),
        }
    }

    fn on_heartbeat(&mut self, i: usize, f: &CanFrame, t: f64) -> Result<Event, Reject> {
        let (_, state) = nmt::parse_heartbeat(f).map_err(|_| Reject::Malformed)?;
        let hb_timeout = f64::from(self.cfg.master_heartbeat_timeout_ms) * 1e-3;
        let steer_moves = self.cfg.homing_of(self.devices[i].wheel).kind != HomingKind::None;
        let d = &mut self.devices[i];
        d.nmt = Some(state);
        d.last_heartbeat = Some(t);
        if state == NmtState::BootUp {
            d.boots = d.boots.saturating_add(1);
            // Its position counter restarted: a steering drive is homed again.
            if d.role == Role::Steer && steer_moves {
                d.homing = HomingState::NotHomed;
            }
            d.pos_zero = 0;
            d.last_pos = None;
        }
        match (d.boot, state) {
            (BootState::ResetSent(_), NmtState::BootUp) => {
                d.boot = BootState::Configuring;
                d.plan_pos = 0;
                d.inflight = None;
                d.poll_since = None;
                d.n_skipped = 0;
            }
            // Rebooted in the middle of its configuration: start over.
            (BootState::Configuring, NmtState::BootUp) => {
                d.plan_pos = 0;
                d.inflight = None;
                d.poll_since = None;
                d.n_skipped = 0;
            }
            (BootState::Started, NmtState::Operational) => d.confirmed = true,
            // A heartbeat the device sent before it took our NMT start (in flight when we
            // sent it): not a departure from operational until the device has shown it runs.
            (BootState::Started, NmtState::PreOperational)
                if !d.confirmed && t - d.started_at <= hb_timeout => {}
            (BootState::Started, s) if s != NmtState::Operational => {
                d.boot = BootState::Lost;
                d.latch(DeviceFault::NmtState { state: s });
            }
            (BootState::Configured, NmtState::BootUp) => {
                d.boot = BootState::Configuring;
                d.plan_pos = 0;
            }
            _ => {}
        }
        Ok(Event::None)
    }

    fn on_sdo(&mut self, i: usize, f: &CanFrame, t: f64) -> Result<Event, Reject> {
        let (_, resp) = SdoResponse::parse(f).map_err(|_| Reject::Malformed)?;
        let d = self.devices[i];
        let Some((op, _, _, purpose)) = d.inflight else {
            return Err(Reject::Unexpected);
        };
        if op.object() != resp.object() {
            return Err(Reject::Unexpected);
        }
        let (index, sub) = op.object();
        let (node, role) = (d.node, d.role);
        if purpose == Purpose::Diagnosis {
            let dev = &mut self.devices[i];
            dev.inflight = None;
            if let SdoResponse::Upload { data, .. } = resp {
                if index == od::ERROR_CODE {
                    let c = data.as_u32() as u16;
                    dev.error_code = Some(c);
                    match &mut dev.fault {
                        Some(DeviceFault::Emcy { read_back, .. })
                        | Some(DeviceFault::DriveFault { read_back, .. }) => *read_back = Some(c),
                        _ => {}
                    }
                } else {
                    dev.error_history = Some(data.as_u32());
                }
            }
            return Ok(Event::None);
        }
        let advance = |m: &mut Master| {
            let d = &mut m.devices[i];
            d.inflight = None;
            d.poll_since = None;
            d.plan_pos += 1;
        };
        match (op, resp) {
            (SdoOp::Write { .. }, SdoResponse::DownloadAck { .. }) => advance(self),
            (
                SdoOp::Verify {
                    mask,
                    expected,
                    what,
                    poll_ms,
                    ..
                },
                SdoResponse::Upload { data, .. },
            ) => {
                let got = data.as_u32() & mask;
                if got == expected {
                    advance(self);
                } else if poll_ms > 0 {
                    let dev = &mut self.devices[i];
                    let since = *dev.poll_since.get_or_insert(t);
                    if (t - since) * 1e3 < f64::from(poll_ms) {
                        // Not there yet: the same read goes out again next cycle.
                        dev.inflight = None;
                    } else {
                        self.fail(
                            i,
                            BootError::ModeNotFollowed {
                                node,
                                role,
                                index,
                                sub,
                                what,
                                got: got as u8 as i8,
                                expected: expected as u8 as i8,
                                ms: poll_ms,
                            },
                        );
                    }
                } else {
                    self.fail(
                        i,
                        BootError::Mismatch {
                            node,
                            role,
                            index,
                            sub,
                            what,
                            got,
                            expected,
                        },
                    );
                }
            }
            (op, SdoResponse::Abort { code, .. })
                if op.optional() && matches!(code, AbortCode::NoObject | AbortCode::NoSubIndex) =>
            {
                let dev = &mut self.devices[i];
                if dev.n_skipped < MAX_SKIPPED {
                    dev.skipped[dev.n_skipped] = (index, sub);
                    dev.n_skipped += 1;
                }
                advance(self);
            }
            (op, SdoResponse::Abort { code, .. }) => self.fail(
                i,
                BootError::Aborted {
                    node,
                    role,
                    index,
                    sub,
                    write: matches!(op, SdoOp::Write { .. }),
                    code,
                },
            ),
            (_, SdoResponse::UploadSegmented { .. }) => self.fail(
                i,
                BootError::Segmented {
                    node,
                    role,
                    index,
                    sub,
                },
            ),
            // A download acknowledged as an upload or the reverse.
            _ => return Err(Reject::Unexpected),
        }
        Ok(Event::None)
    }

    fn on_tpdo(&mut self, i: usize, n: u8, f: &CanFrame, t: f64) -> Result<Event, Reject> {
        let d = self.devices[i];
        if d.boot != BootState::Started {
            return Err(Reject::Unexpected);
        }
        self.devices[i].confirmed = true;
        match (d.role, n) {
            (Role::Drive | Role::Steer, 1) => {
                let v = pdo::DRIVE_TPDO1.unpack(f).map_err(|_| Reject::Malformed)?;
                let units = if d.role == Role::Drive {
                    self.cfg.drive
                } else {
                    self.cfg.steer
                };
                let raw = v[0] as i32;
                // Position relative to the home position latched by the host (0 otherwise),
                // on the 32-bit counter's circle.
                let rel = (i64::from(raw) - d.pos_zero) as i32;
                let pos = units.position_to_rad(rel);
                let rate = units.velocity_to_si(v[1] as i32);
                let dev = &mut self.devices[i];
                let seq = dev.tpdo_seq;
                dev.tpdo_seq = (seq + 1) & 0x0F;
                dev.last_pos = Some((raw, t, rate));
                dev.last_rate = rate;
                if d.role == Role::Steer {
                    if let HomingState::Running(_) = d.homing {
                        if self.cfg.homing_of(d.wheel).kind == HomingKind::Absolute {
                            if pos.abs() > std::f64::consts::TAU {
                                self.fail_homing(i, HomingError::AbsoluteOutOfRange { angle: pos });
                            } else {
                                self.devices[i].homing = HomingState::Done;
                            }
                        }
                    }
                }
                Ok(match d.role {
                    Role::Drive => Event::Drive {
                        wheel: d.wheel,
                        speed: rate,
                        angle: pos,
                    },
                    _ => Event::Steer {
                        wheel: d.wheel,
                        angle: pos + self.cfg.wheels[d.wheel].steer_offset_rad,
                        rate,
                        seq,
                    },
                })
            }
            (Role::Drive | Role::Steer, 2) => {
                let (entries, k) = self.status;
                let v = pdo::unpack(&entries[..k], f).map_err(|_| Reject::Malformed)?;
                let sw = v[0] as u16;
                let dev = &mut self.devices[i];
                dev.statusword = Some(sw);
                for (e, val) in entries[..k].iter().zip(v) {
                    match e.index {
                        od::DIGITAL_INPUTS => {
                            if dev.inputs != Some(val) {
                                dev.input_edge_at = t;
                            }
                            dev.inputs = Some(val);
                        }
                        od::ERROR_CODE if val != 0 => dev.error_code = Some(val as u16),
                        _ => {}
                    }
                }
                if let Some(s) = State402::from_statusword(sw) {
                    if s.is_fault() && t >= dev.reset_grace_until {
                        let read_back = dev.error_code;
                        dev.latch(DeviceFault::DriveFault {
                            statusword: sw,
                            read_back,
                        });
                        if read_back.is_none() {
                            dev.diagnose();
                        }
                    }
                }
                Ok(Event::None)
            }
            (Role::Leg, 1) => {
                let v = pdo::ENCODER_TPDO1
                    .unpack(f)
                    .map_err(|_| Reject::Malformed)?;
                let enc = self.cfg.leg_encoder;
                Ok(Event::Leg {
                    wheel: d.wheel,
                    leg: enc.position_to_m(v[0]),
                    rate: enc.speed_to_si(v[1] as u16 as i16),
                })
            }
            _ => Err(Reject::Unexpected),
        }
    }

    /// The period (µs) written to 0x1006 and 0x60C2.
    pub fn period_us(&self) -> u32 {
        self.period_us
    }
}

/// Controlword bit 4 in homing mode: homing operation start.
pub const CW_HOMING_START: u16 = 1 << 4;
/// Statusword bit 12 in homing mode: homing attained.
pub const SW_HOMING_ATTAINED: u16 = 1 << 12;
/// Statusword bit 13 in homing mode: homing error.
pub const SW_HOMING_ERROR: u16 = 1 << 13;

fn request_frame(op: &SdoOp, node: u8) -> CanFrame {
    match *op {
        SdoOp::Write {
            index, sub, data, ..
        } => SdoRequest::Download { index, sub, data },
        SdoOp::Verify { index, sub, .. } => SdoRequest::Upload { index, sub },
    }
    .to_frame(node)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::canopen::od;
    use crate::canopen::sdo::SdoData;
    use crate::codec::SetpointFlags;

    /// A minimal scripted device side: answers every SDO request with an acknowledgement
    /// or the expected read value, boots when reset, reports a statusword on request.
    struct Devices {
        cfg: Cia402Config,
        reset: Vec<u8>,
        started: Vec<u8>,
        abort: Option<(u8, u16)>,
        mode: std::collections::HashMap<u8, u32>,
        /// Reads of 0x6061 after a write of 0x6060 that still show the old mode.
        mode_lag_reads: u32,
        lag_left: std::collections::HashMap<u8, u32>,
        /// Objects the devices do not have (answered with 0x06020000).
        missing: Vec<u16>,
        /// Value of 0x603F.
        error_code: u16,
    }

    /// The default configuration for `n` wheels without homing (the scripted devices here
    /// do not home; the homing has its own tests).
    fn no_homing(n: usize) -> Cia402Config {
        let mut c = Cia402Config::for_wheels(n);
        c.homing.kind = crate::canopen::config::HomingKind::None;
        c
    }

    impl Devices {
        fn answer(&mut self, f: &CanFrame, out: &mut Vec<CanFrame>) {
            match cob::classify(f.id()) {
                Cob::Nmt => {
                    let (cmd, node) = nmt::parse_command(f).unwrap();
                    match cmd {
                        NmtCommand::ResetCommunication => {
                            self.reset.push(node);
                            out.push(nmt::heartbeat(node, NmtState::BootUp));
                        }
                        NmtCommand::Start => self.started.push(node),
                        _ => {}
                    }
                }
                Cob::SdoRx(node) => {
                    let (_, req) = SdoRequest::parse(f).unwrap();
                    let (index, sub) = req.object();
                    if self.missing.contains(&index) {
                        out.push(
                            SdoResponse::Abort {
                                index,
                                sub,
                                code: AbortCode::NoObject,
                            }
                            .to_frame(node),
                        );
                        return;
                    }
                    if self.abort == Some((node, index)) {
                        out.push(
                            SdoResponse::Abort {
                                index,
                                sub,
                                code: AbortCode::InvalidValue,
                            }
                            .to_frame(node),
                        );
                        return;
                    }
                    let resp = match req {
                        SdoRequest::Download { data, .. } => {
                            if index == od::MODES_OF_OPERATION {
                                self.mode.insert(node, data.as_u32());
                                self.lag_left.insert(node, self.mode_lag_reads);
                            }
                            SdoResponse::DownloadAck { index, sub }
                        }
                        SdoRequest::Upload { .. } => {
                            let is_leg = self.cfg.wheels.iter().any(|w| w.leg_node == node);
                            let v = match (index, sub) {
                                (od::DEVICE_TYPE, 0) if is_leg => 0x0008_0196,
                                (od::DEVICE_TYPE, 0) => 0x0002_0192,
                                (od::MODES_OF_OPERATION_DISPLAY, 0) => {
                                    let left = self.lag_left.entry(node).or_insert(0);
                                    if *left > 0 {
                                        *left -= 1;
                                        0
                                    } else {
                                        self.mode.get(&node).copied().unwrap_or(0)
                                    }
                                }
                                (od::ERROR_CODE, 0) => u32::from(self.error_code),
                                (od::POSITION_ENCODER_RESOLUTION, 1) => 16384,
                                (od::POSITION_ENCODER_RESOLUTION, 2) => 1,
                                (od::GEAR_RATIO, _) => 1,
                                (od::SI_UNIT_VELOCITY, 0) => 0x00B5_0300,
                                (od::MEASURING_STEP, 1) => 1000,
                                _ => 0,
                            };
                            SdoResponse::Upload {
                                index,
                                sub,
                                data: SdoData::u32(v),
                            }
                        }
                        SdoRequest::Abort { .. } => return,
                    };
                    out.push(resp.to_frame(node));
                }
                _ => {}
            }
        }
    }

    fn run_boot(m: &mut Master, dev: &mut Devices, cycles: usize) -> usize {
        let mut buf = FrameBuf::new();
        for k in 0..cycles {
            let t = k as f64 * 0.004;
            buf.clear();
            m.start_cycle(t, &mut buf);
            let mut replies = Vec::new();
            for f in buf.as_slice() {
                dev.answer(f, &mut replies);
            }
            for r in &replies {
                m.on_frame(r, t + 0.0005).unwrap();
            }
            buf.clear();
            m.finish_cycle(t + 0.002, &[Setpoint::default(); 4], &mut buf);
            let mut replies = Vec::new();
            for f in buf.as_slice() {
                dev.answer(f, &mut replies);
            }
            for r in &replies {
                m.on_frame(r, t + 0.0025).unwrap();
            }
            if m.ready() || m.boot_failure().is_some() {
                return k;
            }
        }
        cycles
    }

    fn devices(cfg: &Cia402Config) -> Devices {
        Devices {
            cfg: cfg.clone(),
            reset: vec![],
            started: vec![],
            abort: None,
            mode: Default::default(),
            mode_lag_reads: 0,
            lag_left: Default::default(),
            missing: vec![],
            error_code: 0,
        }
    }

    #[test]
    fn boots_every_device_with_one_request_in_flight_each() {
        let cfg = no_homing(4);
        let mut m = Master::new(&cfg, 0.004);
        let mut dev = devices(&cfg);
        let k = run_boot(&mut m, &mut dev, 200);
        assert!(
            m.ready(),
            "not ready after {k} cycles: {:?}",
            m.boot_failure()
        );
        // Drive plans are 33 steps, two per cycle: ready in about 20 cycles (80 ms).
        assert!(k < 25, "boot took {k} cycles");
        let mut reset = dev.reset.clone();
        reset.sort();
        assert_eq!(reset, (1..=12).collect::<Vec<u8>>());
        assert_eq!(dev.started.len(), 12);
        assert_eq!(m.tx_overflow(), 0);
        assert!(m.devices().iter().all(|d| d.fault.is_none()));
    }

    #[test]
    fn an_abort_fails_the_boot_naming_node_object_and_code() {
        let cfg = no_homing(4);
        let mut m = Master::new(&cfg, 0.004);
        let mut dev = devices(&cfg);
        dev.abort = Some((6, od::MODES_OF_OPERATION));
        run_boot(&mut m, &mut dev, 200);
        let (wheel, e) = m.boot_failure().expect("failed");
        assert_eq!(wheel, 2);
        assert_eq!(
            e,
            BootError::Aborted {
                node: 6,
                role: Role::Steer,
                index: 0x6060,
                sub: 0,
                write: true,
                code: AbortCode::InvalidValue
            }
        );
        let text = e.to_string();
        assert!(text.contains("node 6 (steering drive)"), "{text}");
        assert!(text.contains("0x6060:00"), "{text}");
        assert!(text.contains("0x06090030"), "{text}");
        assert!(!m.ready());
        assert!(matches!(
            m.wheel_fault(2),
            Some((6, Role::Steer, DeviceFault::Boot(_)))
        ));
    }

    #[test]
    fn a_silent_device_times_out_its_boot() {
        let cfg = no_homing(1);
        let mut m = Master::new(&cfg, 0.004);
        let mut buf = FrameBuf::new();
        let mut t = 0.0;
        while m.boot_failure().is_none() && t < 5.0 {
            buf.clear();
            m.start_cycle(t, &mut buf);
            t += 0.004;
        }
        let (_, e) = m.boot_failure().unwrap();
        assert!(matches!(
            e,
            BootError::NoBootUp {
                node: 1,
                ms: 2000,
                ..
            }
        ));
        assert!((t - 2.0).abs() < 0.01, "{t}");
    }

    #[test]
    fn sdo_timeouts_are_retried_then_fail() {
        let cfg = no_homing(1);
        let mut m = Master::new(&cfg, 0.004);
        let mut buf = FrameBuf::new();
        m.start_cycle(0.0, &mut buf);
        m.on_frame(&nmt::heartbeat(1, NmtState::BootUp), 0.001)
            .unwrap();
        let mut requests = 0;
        let mut t = 0.004;
        while m.boot_failure().is_none() && t < 1.0 {
            buf.clear();
            m.start_cycle(t, &mut buf);
            requests += buf
                .as_slice()
                .iter()
                .filter(|f| f.id() == 0x601 && f.data()[0] == 0x40)
                .count();
            t += 0.004;
        }
        // One request and two retries, then the abort and the failure.
        assert_eq!(requests, 3);
        assert!(matches!(
            m.boot_failure(),
            Some((
                0,
                BootError::SdoTimeout {
                    node: 1,
                    index: 0x1000,
                    tries: 3,
                    ..
                }
            ))
        ));
    }

    #[test]
    fn controlwords_walk_the_drive_to_operation_enabled_and_targets_wait_for_it() {
        let cfg = no_homing(1);
        let mut m = Master::new(&cfg, 0.004);
        let mut dev = devices(&cfg);
        run_boot(&mut m, &mut dev, 100);
        assert!(m.ready());
        let sp = Setpoint {
            wheel_speed: 1.0,
            steer_rate: 0.5,
            flags: SetpointFlags {
                enable: true,
                brake: false,
                fault_reset: false,
            },
        };
        let mut state = State402::SwitchOnDisabled;
        let mut prev = 0u16;
        let mut t = 1.0;
        let mut seen = Vec::new();
        for _ in 0..6 {
            // The drive reports its state, the master answers with the next controlword.
            let sw = pdo::DRIVE_TPDO2.pack(1, &[u32::from(state.statusword_bits())]);
            m.on_frame(&sw, t).unwrap();
            let mut buf = FrameBuf::new();
            m.finish_cycle(t, &[sp], &mut buf);
            let rpdo = buf.as_slice().iter().find(|f| f.id() == 0x201).unwrap();
            let v = pdo::DRIVE_RPDO1.unpack(rpdo).unwrap();
            let (cw, target) = (v[0] as u16, v[1] as i32);
            seen.push((state, cw, target));
            state = ds402::device_transition(state, ds402::decode_controlword(cw, prev));
            prev = cw;
            t += 0.004;
        }
        assert_eq!(seen[0], (State402::SwitchOnDisabled, 0x06, 0));
        assert_eq!(seen[1], (State402::ReadyToSwitchOn, 0x07, 0));
        assert_eq!(seen[2], (State402::SwitchedOn, 0x0F, 0));
        // Only once the drive reported operation enabled does it get a speed:
        // 1 rad/s · 16384 · 30 / 2π = 78 228.2 → 78 228 increments/s.
        assert_eq!(seen[3], (State402::OperationEnabled, 0x0F, 78_228));
        assert!(m.wheel_fault(0).is_none());
        assert_eq!(
            m.wheel_state(0),
            ModuleState::Ready,
            "steer drive not enabled yet"
        );
    }

    #[test]
    fn quick_stop_commands_enabled_drives_until_re_armed_and_enables_none() {
        let cfg = no_homing(1);
        let mut m = Master::new(&cfg, 0.004);
        let mut dev = devices(&cfg);
        run_boot(&mut m, &mut dev, 100);
        let sp = Setpoint {
            wheel_speed: 1.0,
            steer_rate: 0.0,
            flags: SetpointFlags {
                enable: true,
                brake: false,
                fault_reset: false,
            },
        };
        // One cycle: the rolling drive reports `state`; the master's controlword and target.
        let step = |m: &mut Master, state: State402, t: f64| -> (u16, i32) {
            let sw = pdo::DRIVE_TPDO2.pack(1, &[u32::from(state.statusword_bits())]);
            m.on_frame(&sw, t).unwrap();
            let mut buf = FrameBuf::new();
            m.finish_cycle(t, &[sp], &mut buf);
            let rpdo = buf.as_slice().iter().find(|f| f.id() == 0x201).unwrap();
            let v = pdo::DRIVE_RPDO1.unpack(rpdo).unwrap();
            (v[0] as u16, v[1] as i32)
        };
        assert_eq!(
            step(&mut m, State402::OperationEnabled, 1.0),
            (0x0F, 78_228)
        );
        assert!(!m.quick_stopping());
        m.quick_stop();
        m.quick_stop();
        assert_eq!(m.quick_stops(), 1, "one quick stop, however often asked");
        // Enabled: Quick Stop (0x0002) and a zero target, which the drive decodes as the
        // quick stop command (transition 11), and keeps getting while it ramps down.
        let (cw, target) = step(&mut m, State402::OperationEnabled, 1.004);
        assert_eq!((cw, target), (ds402::CW_QUICK_STOP_CMD, 0));
        assert_eq!(
            ds402::device_transition(
                State402::OperationEnabled,
                ds402::decode_controlword(cw, 0x0F)
            ),
            State402::QuickStopActive
        );
        assert_eq!(
            step(&mut m, State402::QuickStopActive, 1.008),
            (ds402::CW_QUICK_STOP_CMD, 0)
        );
        // At rest the drive went on to switch on disabled (option 2): it is not enabled
        // again, whatever the setpoints say.
        for (k, state) in [State402::SwitchOnDisabled, State402::ReadyToSwitchOn]
            .into_iter()
            .enumerate()
        {
            let (cw, target) = step(&mut m, state, 1.012 + 0.004 * k as f64);
            assert_eq!(target, 0);
            assert_eq!(cw, ds402::CW_SHUTDOWN, "{state:?}");
        }
        // The re-arm lifts it: a drive held in quick stop active (options 5-8) is disabled
        // (transition 12), then walked up again.
        m.rearm(2.0);
        assert!(!m.quick_stopping());
        assert_eq!(
            step(&mut m, State402::QuickStopActive, 2.0).0,
            ds402::CW_DISABLE_VOLTAGE
        );
        assert_eq!(step(&mut m, State402::SwitchOnDisabled, 2.004).0, 0x06);
    }

    #[test]
    fn faults_latch_until_rearm_and_name_the_device() {
        let cfg = no_homing(2);
        let mut m = Master::new(&cfg, 0.004);
        let mut dev = devices(&cfg);
        let k = run_boot(&mut m, &mut dev, 100);
        // The clock runs on from the boot (a jump would be a silent master, see below).
        let t = (k + 1) as f64 * 0.004;
        m.on_frame(&Emcy::new(emcy::codes::OVERCURRENT, 0x02).to_frame(3), t)
            .unwrap();
        // The fault's own statusword does not replace the more specific EMCY.
        m.on_frame(&pdo::DRIVE_TPDO2.pack(3, &[0x0218]), t).unwrap();
        assert_eq!(
            m.wheel_fault(1),
            Some((
                3,
                Role::Drive,
                DeviceFault::Emcy {
                    code: 0x2310,
                    register: 0x02,
                    read_back: None,
                }
            ))
        );
        assert_eq!(m.wheel_state(1), ModuleState::Fault);
        assert!(m.wheel_fault(0).is_none());
        // A device that stops sending heartbeats is lost after the consumer time.
        let mut buf = FrameBuf::new();
        for k in 0..100 {
            let tk = t + 0.004 * f64::from(k);
            for node in [1u8, 2, 4, 5, 6] {
                m.on_frame(&nmt::heartbeat(node, NmtState::Operational), tk)
                    .unwrap();
            }
            buf.clear();
            m.start_cycle(tk, &mut buf);
        }
        assert!(m.wheel_fault(0).is_none());
        let lost: Vec<u8> = m
            .devices()
            .iter()
            .filter(|d| d.boot == BootState::Lost)
            .map(|d| d.node)
            .collect();
        assert_eq!(lost, vec![3]);
        // Its first fault (the EMCY) stays the one reported.
        assert!(matches!(
            m.wheel_fault(1),
            Some((3, Role::Drive, DeviceFault::Emcy { .. }))
        ));
        // Re-arming clears the latches and resets the lost device only.
        let t = t + 0.4;
        m.rearm(t);
        assert!(m.wheel_fault(1).is_none());
        assert!(!m.ready());
        buf.clear();
        m.start_cycle(t, &mut buf);
        let resets: Vec<u8> = buf
            .as_slice()
            .iter()
            .filter(|f| f.id() == 0 && f.data()[0] == 0x82)
            .map(|f| f.data()[1])
            .collect();
        assert_eq!(resets, vec![3]);
    }

    #[test]
    fn a_gap_in_the_masters_own_cycles_longer_than_the_drives_consumer_time_is_a_fault() {
        let cfg = no_homing(1);
        let mut m = Master::new(&cfg, 0.004);
        let mut dev = devices(&cfg);
        let k = run_boot(&mut m, &mut dev, 100);
        let mut buf = FrameBuf::new();
        let mut t = (k + 1) as f64 * 0.004;
        // Late cycles up to the consumer time (60 ms) are not a fault …
        for gap in [0.004, 0.030, 0.060] {
            t += gap;
            m.start_cycle(t, &mut buf);
            assert!(m.wheel_fault(0).is_none(), "gap {gap}");
        }
        // … 64 ms is: both drives (not the encoder) have reacted meanwhile.
        t += 0.064;
        m.start_cycle(t, &mut buf);
        let faulted: Vec<(u8, Option<DeviceFault>)> =
            m.devices().iter().map(|d| (d.node, d.fault)).collect();
        let silent = DeviceFault::MasterSilent {
            ms: 64,
            timeout_ms: 60,
        };
        assert_eq!(
            faulted,
            vec![(1, Some(silent)), (2, Some(silent)), (3, None)]
        );
        assert!(silent.to_string().contains("silent for 64 ms"));
    }

    #[test]
    fn feedback_in_si_and_foreign_frames_rejected() {
        let cfg = no_homing(1);
        let mut m = Master::new(&cfg, 0.004);
        let mut dev = devices(&cfg);
        run_boot(&mut m, &mut dev, 100);
        // Steering drive at half a turn, −1 rad/s.
        let steer = cfg.steer;
        let f = pdo::DRIVE_TPDO1.pack(
            2,
            &[
                steer.rad_to_position(std::f64::consts::PI) as u32,
                steer.velocity_from_si(-1.0).unwrap() as u32,
            ],
        );
        match m.on_frame(&f, 1.0).unwrap() {
            Event::Steer {
                wheel, angle, rate, ..
            } => {
                assert_eq!(wheel, 0);
                assert!((angle - std::f64::consts::PI).abs() < 1e-5);
                assert!((rate + 1.0).abs() < 1e-4);
            }
            e => panic!("{e:?}"),
        }
        let f = pdo::ENCODER_TPDO1.pack(3, &[450_000, 25]);
        assert_eq!(
            m.on_frame(&f, 1.0).unwrap(),
            Event::Leg {
                wheel: 0,
                leg: 0.45,
                rate: 250e-6
            }
        );
        assert_eq!(m.on_frame(&nmt::sync(), 1.0), Err(Reject::ForeignMaster));
        let f = CanFrame::new(0x188, &[0; 8]).unwrap();
        assert_eq!(m.on_frame(&f, 1.0), Err(Reject::UnknownNode));
        let f = CanFrame::new(0x182, &[0; 7]).unwrap();
        assert_eq!(m.on_frame(&f, 1.0), Err(Reject::Malformed));
        let f = CanFrame::new(0x7E5, &[0; 7]).unwrap();
        assert_eq!(m.on_frame(&f, 1.0), Err(Reject::UnknownId));
        // An SDO response nobody asked for.
        let f = SdoResponse::DownloadAck {
            index: 0x6040,
            sub: 0,
        }
        .to_frame(1);
        assert_eq!(m.on_frame(&f, 1.0), Err(Reject::Unexpected));
    }

    /// A drive whose mode display follows 0x6060 a few reads (cycles) late boots: the master
    /// reads 0x6061 again until it shows the mode. (Before, it read once and failed the
    /// boot with "is this the right device at this node-ID?".)
    #[test]
    fn a_mode_display_that_lags_is_polled_until_it_follows() {
        let cfg = no_homing(1);
        let mut m = Master::new(&cfg, 0.004);
        let mut dev = devices(&cfg);
        dev.mode_lag_reads = 3; // about 12 ms at 4 ms a cycle
        run_boot(&mut m, &mut dev, 200);
        assert!(m.ready(), "{:?}", m.boot_failure());
        // One that never follows fails after mode_switch_timeout_ms, naming drive and object.
        let mut m = Master::new(&cfg, 0.004);
        let mut dev = devices(&cfg);
        dev.mode_lag_reads = 1000;
        run_boot(&mut m, &mut dev, 200);
        let (wheel, e) = m.boot_failure().expect("failed");
        assert_eq!(wheel, 0);
        assert!(
            matches!(
                e,
                BootError::ModeNotFollowed {
                    index: 0x6061,
                    got: 0,
                    expected: 9,
                    ms: 100,
                    ..
                }
            ),
            "{e:?}"
        );
        let text = e.to_string();
        assert!(
            text.contains("node 1 (rolling drive)") && text.contains("0x6061:00"),
            "{text}"
        );
        assert!(!text.contains("right device"), "{text}");
    }

    /// Optional steps (unused PDOs, unit checks) are skipped when the device does not have
    /// the object, and reported; the PDOs the plan does not use are disabled.
    #[test]
    fn optional_steps_are_skipped_on_missing_objects_and_unused_pdos_disabled() {
        let cfg = no_homing(1);
        let mut m = Master::new(&cfg, 0.004);
        let mut dev = devices(&cfg);
        dev.missing = vec![0x1803, 0x608F, 0x6091];
        run_boot(&mut m, &mut dev, 200);
        assert!(m.ready(), "{:?}", m.boot_failure());
        let drive = &m.devices()[0];
        assert_eq!(
            drive.skipped(),
            &[
                (0x1803, 1),
                (0x608F, 1),
                (0x608F, 2),
                (0x6091, 1),
                (0x6091, 2)
            ]
        );
        // A mandatory object missing still fails the boot.
        let mut m = Master::new(&cfg, 0.004);
        let mut dev = devices(&cfg);
        dev.missing = vec![0x60C2];
        run_boot(&mut m, &mut dev, 200);
        assert!(matches!(
            m.boot_failure(),
            Some((
                0,
                BootError::Aborted {
                    index: 0x60C2,
                    code: AbortCode::NoObject,
                    ..
                }
            ))
        ));
        // The plans disable RPDO2–4 and TPDO3–4 of a drive, TPDO2–4 of an encoder.
        let cob_writes = |role: Role| -> Vec<(u16, u32)> {
            cfg.plan(role, 4000)
                .iter()
                .filter_map(|op| match *op {
                    SdoOp::Write {
                        index,
                        sub: 1,
                        data,
                        optional: true,
                    } if (0x1400..0x1404).contains(&index) || (0x1800..0x1804).contains(&index) => {
                        Some((index, data.as_u32()))
                    }
                    _ => None,
                })
                .collect()
        };
        assert_eq!(
            cob_writes(Role::Drive),
            vec![
                (0x1401, 0x8000_0300),
                (0x1402, 0x8000_0400),
                (0x1403, 0x8000_0500),
                (0x1802, 0xC000_0380),
                (0x1803, 0xC000_0480),
            ]
        );
        assert_eq!(
            cob_writes(Role::Leg),
            vec![
                (0x1801, 0xC000_0280),
                (0x1802, 0xC000_0380),
                (0x1803, 0xC000_0480)
            ]
        );
    }

    /// After a crash the drives are in fault; the new master sends the fault reset whenever
    /// a drive's statusword shows Fault inside the grace period after the arm, however late
    /// that statusword comes (the event timer allows it 100 ms late). Before, the reset rode
    /// on the few cycles of `fault_reset` after the arm only, and a statusword 10 ms late was
    /// never answered: "drive in fault (statusword 0x8218)".
    #[test]
    fn a_late_fault_statusword_still_gets_the_fault_reset() {
        let cfg = no_homing(1);
        let mut m = Master::new(&cfg, 0.004);
        m.rearm(0.0);
        let mut dev = devices(&cfg);
        let k = run_boot(&mut m, &mut dev, 100);
        assert!(m.ready());
        let mut buf = FrameBuf::new();
        let mut t = (k + 1) as f64 * 0.004;
        buf.clear();
        m.start_cycle(t, &mut buf);
        // The arm's own fault_reset cycles pass with no statusword yet.
        let enable = Setpoint {
            flags: SetpointFlags {
                enable: true,
                brake: false,
                fault_reset: false,
            },
            ..Setpoint::default()
        };
        let mut state = State402::Fault;
        let mut prev = 0u16;
        let mut resets = 0;
        for c in 0..40 {
            if c >= 5 {
                // The statusword arrives 20 ms late, and keeps coming on change.
                let sw = pdo::DRIVE_TPDO2.pack(1, &[u32::from(state.statusword_bits() | 0x8200)]);
                m.on_frame(&sw, t).unwrap();
            }
            buf.clear();
            m.finish_cycle(t, &[enable], &mut buf);
            let rpdo = buf.as_slice().iter().find(|f| f.id() == 0x201).unwrap();
            let cw = pdo::DRIVE_RPDO1.unpack(rpdo).unwrap()[0] as u16;
            if c >= 5 {
                let cmd = ds402::decode_controlword(cw, prev);
                if cmd == ds402::Command::FaultReset {
                    resets += 1;
                }
                state = ds402::device_transition(state, cmd);
            }
            prev = cw;
            t += 0.004;
            buf.clear();
            m.start_cycle(t, &mut buf);
        }
        assert_eq!(resets, 1, "one reset edge cleared it");
        assert_eq!(state, State402::OperationEnabled);
        assert!(m.wheel_fault(0).is_none(), "{:?}", m.wheel_fault(0));
    }

    /// EMCYs as drives send them: an informational one (error register 0, a vendor notice)
    /// is counted and kept, not a fault; a fault EMCY latches and the master reads the
    /// drive's error code back into the fault.
    #[test]
    fn informational_emcy_is_counted_fault_emcy_latches_with_the_code_read_back() {
        let cfg = no_homing(1);
        let mut m = Master::new(&cfg, 0.004);
        let mut dev = devices(&cfg);
        dev.error_code = 0x2310;
        let k = run_boot(&mut m, &mut dev, 100);
        let t = (k + 1) as f64 * 0.004;
        let info = Emcy::new(0xFF01, 0);
        m.on_frame(&info.to_frame(1), t).unwrap();
        m.on_frame(&Emcy::new(emcy::codes::CAN_PASSIVE, 0x11).to_frame(2), t)
            .unwrap();
        assert!(m.wheel_fault(0).is_none());
        assert_eq!(m.devices()[0].emcy_informational, 1);
        assert_eq!(m.devices()[1].emcy_informational, 1);
        m.on_frame(
            &Emcy::new(emcy::codes::OVERCURRENT, 0x03).to_frame(1),
            t + 0.001,
        )
        .unwrap();
        assert_eq!(
            m.wheel_fault(0),
            Some((
                1,
                Role::Drive,
                DeviceFault::Emcy {
                    code: 0x2310,
                    register: 0x03,
                    read_back: None
                }
            ))
        );
        let hist: Vec<(f64, u16)> = m.devices()[0]
            .emcy_history()
            .map(|(at, e)| (at, e.code))
            .collect();
        assert_eq!(hist, vec![(t, 0xFF01), (t + 0.001, 0x2310)]);
        // The next cycle reads 0x603F (then 0x1003:01) and puts the code in the fault.
        let mut buf = FrameBuf::new();
        for c in 0..4 {
            let tc = t + 0.004 * f64::from(c + 1);
            buf.clear();
            m.start_cycle(tc, &mut buf);
            let mut replies = Vec::new();
            for f in buf.as_slice() {
                dev.answer(f, &mut replies);
            }
            for r in &replies {
                m.on_frame(r, tc + 0.0005).unwrap();
            }
        }
        let f = m.wheel_fault(0).unwrap().2;
        assert_eq!(
            f,
            DeviceFault::Emcy {
                code: 0x2310,
                register: 0x03,
                read_back: Some(0x2310)
            }
        );
        assert!(
            f.to_string().contains("error code 0x603F reads 0x2310"),
            "{f}"
        );
    }

    /// A heartbeat a device sent just before it took the NMT start (in flight when the master
    /// sent it) shows pre-operational after the master marked it started: not a departure
    /// from operational. (Found against the independent python-canopen devices: the boot hung
    /// with the device latched as "left operational".) Once it showed it runs, it is one.
    #[test]
    fn a_pre_operational_heartbeat_in_flight_at_the_start_is_not_a_fault() {
        let cfg = no_homing(1);
        let mut m = Master::new(&cfg, 0.004);
        let mut dev = devices(&cfg);
        let k = run_boot(&mut m, &mut dev, 100);
        assert!(m.ready());
        let t = (k + 1) as f64 * 0.004;
        m.on_frame(&nmt::heartbeat(1, NmtState::PreOperational), t)
            .unwrap();
        assert!(m.wheel_fault(0).is_none(), "{:?}", m.wheel_fault(0));
        m.on_frame(&nmt::heartbeat(1, NmtState::Operational), t + 0.1)
            .unwrap();
        m.on_frame(&nmt::heartbeat(1, NmtState::PreOperational), t + 0.2)
            .unwrap();
        assert!(matches!(
            m.wheel_fault(0),
            Some((
                1,
                Role::Drive,
                DeviceFault::NmtState {
                    state: NmtState::PreOperational
                }
            ))
        ));
    }

    /// Heartbeats every 100 ms (the default producer time), 300 ms consumer time: two lost in
    /// a row are tolerated (the third arrives one consumer time after the last, just before
    /// a cycle starts, and is read in that cycle: judged at the cycle's start, the silence
    /// was 300.5 ms and the device faulted); three lost are a fault, at most two cycles after
    /// the consumer time ran out.
    #[test]
    fn two_lost_heartbeats_are_tolerated_three_are_a_fault() {
        for lost in [2usize, 3] {
            let cfg = no_homing(1);
            let mut m = Master::new(&cfg, 0.004);
            let mut dev = devices(&cfg);
            let k0 = run_boot(&mut m, &mut dev, 100) + 1;
            assert!(m.ready());
            let nodes: Vec<u8> = m.devices.iter().map(|d| d.node).collect();
            let hb_every = 25; // cycles: 100 ms
            let mut buf = FrameBuf::new();
            let mut faulted_at = None;
            let mut last_hb = k0;
            for k in k0..k0 + 6 * hb_every {
                let t = k as f64 * 0.004;
                buf.clear();
                m.start_cycle(t, &mut buf);
                let n = (k - k0) / hb_every;
                if (k - k0) % hb_every == 0 {
                    for &node in &nodes {
                        // Node 1's heartbeats 1..=lost are lost; every other one arrives.
                        // Sent on the device's own clock, 0.5 ms before this cycle started,
                        // so read in this cycle, after its start.
                        if node != 1 || n == 0 || n > lost {
                            m.on_frame(&nmt::heartbeat(node, NmtState::Operational), t - 0.0005)
                                .unwrap();
                        }
                    }
                    if n == 0 {
                        last_hb = k;
                    }
                }
                if faulted_at.is_none() && m.wheel_fault(0).is_some() {
                    faulted_at = Some(k);
                }
            }
            match lost {
                2 => assert_eq!(faulted_at, None, "{:?}", m.wheel_fault(0)),
                _ => {
                    let k = faulted_at.expect("three heartbeats lost: a fault");
                    assert!(matches!(
                        m.wheel_fault(0),
                        Some((1, _, DeviceFault::HeartbeatLost { ms: 300 }))
                    ));
                    // 300 ms is 75 cycles; seen as of the previous cycle start: 76 or 77.
                    assert!((76..=77).contains(&(k - last_hb)), "{} cycles", k - last_hb);
                }
            }
        }
    }

    proptest::proptest! {
        /// Bytes from the bus never panic the master, while booting or running: ids drawn
        /// mostly from what its devices send, any length, any payload are either used,
        /// ignored or rejected.
        #[test]
        fn arbitrary_frames_never_panic_the_master(
            frames in proptest::collection::vec(
                (
                    proptest::prop_oneof![
                        // What devices 1 (drive), 2 (steering) and 9 (encoder) send.
                        proptest::sample::select(vec![
                            0x081u16, 0x082, 0x181, 0x182, 0x189, 0x281, 0x282, 0x581, 0x589,
                            0x701, 0x709,
                        ]),
                        0u16..0x800,
                    ],
                    proptest::collection::vec(proptest::num::u8::ANY, 0..=8),
                ),
                1..200,
            ),
            boot_first in proptest::bool::ANY,
        ) {
            let cfg = no_homing(4);
            let mut m = Master::new(&cfg, 0.004);
            if boot_first {
                let mut dev = devices(&cfg);
                run_boot(&mut m, &mut dev, 200);
            }
            let mut buf = FrameBuf::new();
            let sp = [Setpoint::default(); 4];
            for (k, (id, data)) in frames.iter().enumerate() {
                let t = 1.0 + k as f64 * 0.001;
                let f = CanFrame::new(*id, data).expect("id < 0x800, len <= 8");
                let _ = m.on_frame(&f, t);
                if k % 4 == 0 {
                    buf.clear();
                    m.start_cycle(t, &mut buf);
                    buf.clear();
                    m.finish_cycle(t, &sp, &mut buf);
                }
            }
        }
    }
}
