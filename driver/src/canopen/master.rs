//! The sans-IO CANopen master for the CiA 402 profile: boot, configuration, cyclic
//! exchange and supervision of every device of the platform.
//!
//! Three calls per control cycle, like the native profile's cycle (time in seconds, passed
//! in; nothing here reads a clock, opens a socket or allocates after [`Master::new`]):
//!
//! - [`Master::start_cycle`]: SYNC first, then whatever is due: NMT commands, the master's
//!   heartbeat, the next SDO request of every device being configured;
//! - [`Master::on_frame`]: every received frame; feedback TPDOs come back as [`Event`]s in SI
//!   units, everything else updates the devices' state;
//! - [`Master::finish_cycle`]: one RPDO1 per drive (controlword + target velocity) from the
//!   wheels' setpoints, then SDO requests whose previous response came in this cycle.
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
//! [`Master::ready`] is true when every device is started; the controller arms only then.
//! A boot failure ([`Master::boot_failure`]) names the node, the object and the abort code.
//!
//! # Supervision (latched per device until [`Master::rearm`])
//!
//! EMCY with a non-zero error code; a statusword showing Fault; a heartbeat older than
//! `master_heartbeat_timeout_ms`; a heartbeat or boot-up showing the device left
//! operational; a drive that does not reach operation enabled within `enable_timeout_ms` of
//! being asked. [`Master::wheel_fault`] reports the first fault of a wheel's devices.
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
use super::config::{for_node, Cia402Config, Role, SdoOp};
use super::ds402::{self, State as State402};
use super::emcy::{self, Emcy};
use super::nmt::{self, NmtCommand, NmtState};
use super::pdo;
use super::sdo::{AbortCode, SdoRequest, SdoResponse};
use crate::codec::{ModuleState, Setpoint};
use crate::frame::{CanFrame, FrameBuf};

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
    #[error("node {node} ({role}): SDO {} of 0x{index:04X}:{sub:02X} aborted: {code}; check that the device supports this object and value (platform file [cia402])", if *write { "write" } else { "read" })]
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
    #[error("node {node} ({role}): 0x{index:04X}:{sub:02X} {what} reads 0x{got:X}, expected 0x{expected:X}; is this the right device at this node-ID?")]
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
    /// The device answered an upload with a segmented transfer.
    #[error("node {node} ({role}): answered the read of 0x{index:04X}:{sub:02X} with a segmented transfer; this master supports expedited transfers only")]
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
}

/// A fault of one device, latched until [`Master::rearm`].
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum DeviceFault {
    /// The device could not be booted and configured.
    Boot(BootError),
    /// The device sent an emergency message.
    Emcy {
        /// Error code.
        code: u16,
        /// Error register.
        register: u8,
    },
    /// The drive's statusword shows Fault or Fault reaction active.
    DriveFault {
        /// The statusword.
        statusword: u16,
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
}

impl std::fmt::Display for DeviceFault {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Self::Boot(e) => write!(f, "boot failed: {e}"),
            Self::Emcy { code, register } => write!(
                f,
                "EMCY 0x{code:04X} ({}), error register 0x{register:02X}",
                emcy::describe(*code)
            ),
            Self::DriveFault { statusword } => write!(
                f,
                "drive in fault (statusword 0x{statusword:04X}); read its error code (0x603F) or EMCY history (0x1003)"
            ),
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
    /// Last NMT state seen in a boot-up or heartbeat.
    pub nmt: Option<NmtState>,
    /// Time of the last boot-up or heartbeat (or of the NMT start).
    pub last_heartbeat: Option<f64>,
    /// Last statusword (drives).
    pub statusword: Option<u16>,
    /// Last controlword sent (drives).
    pub controlword: u16,
    /// Latched fault.
    pub fault: Option<DeviceFault>,
    /// Last EMCY received (also after a reset message).
    pub last_emcy: Option<Emcy>,
    plan_pos: usize,
    inflight: Option<(SdoOp, f64, u8)>,
    enable_since: Option<f64>,
    reset_grace_until: f64,
    tpdo_seq: u8,
    hb_lost_reported: bool,
}

impl Device {
    fn new(wheel: usize, role: Role, node: u8) -> Self {
        Self {
            wheel,
            role,
            node,
            boot: BootState::NeedsReset,
            nmt: None,
            last_heartbeat: None,
            statusword: None,
            controlword: 0,
            fault: None,
            last_emcy: None,
            plan_pos: 0,
            inflight: None,
            enable_since: None,
            reset_grace_until: f64::NEG_INFINITY,
            tpdo_seq: 0,
            hb_lost_reported: false,
        }
    }

    /// The 402 state from the last statusword (drives).
    pub fn state402(&self) -> Option<State402> {
        self.statusword.and_then(State402::from_statusword)
    }

    fn latch(&mut self, f: DeviceFault) {
        if self.fault.is_none() {
            self.fault = Some(f);
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
    plans: [Vec<SdoOp>; 3],
    next_master_hb: f64,
    now: f64,
    last_start: Option<f64>,
    failure: Option<(usize, BootError)>,
    tx_overflow: u32,
}

fn role_index(r: Role) -> usize {
    match r {
        Role::Drive => 0,
        Role::Steer => 1,
        Role::Leg => 2,
    }
}

impl Master {
    /// A master for `cfg` on a platform of `wheels` wheels with control period `period_s`.
    /// The configuration must have been validated ([`Cia402Config::validate`]); every device
    /// starts in [`BootState::NeedsReset`].
    pub fn new(cfg: &Cia402Config, period_s: f64) -> Self {
        let period_us = (period_s * 1e6).round().clamp(1.0, 255_000.0) as u32;
        let devices: Vec<Device> = cfg
            .devices()
            .map(|(w, r, n)| Device::new(w, r, n))
            .collect();
        let mut by_node = [NO_DEVICE; 128];
        for (i, d) in devices.iter().enumerate() {
            by_node[usize::from(d.node & 0x7F)] = i as u8;
        }
        let plans = [
            cfg.plan(Role::Drive, period_us),
            cfg.plan(Role::Steer, period_us),
            cfg.plan(Role::Leg, period_us),
        ];
        Self {
            cfg: cfg.clone(),
            period_us,
            devices,
            by_node,
            plans,
            next_master_hb: 0.0,
            now: 0.0,
            last_start: None,
            failure: None,
            tx_overflow: 0,
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
    pub fn ready(&self) -> bool {
        self.devices.iter().all(|d| d.boot == BootState::Started)
    }

    /// True while some device is still being reset or configured (and none failed).
    pub fn booting(&self) -> bool {
        self.failure.is_none() && !self.ready()
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
    /// booted, failed, rebooted, lost) are reset and configured again. Call it when the
    /// operator re-arms, with the platform at rest. `t` starts the grace period in which a
    /// drive still in fault (its statusword) is not re-latched: the controller is sending it
    /// a fault reset.
    ///
    /// Devices that boot again get their grace period from the cycle in which every device
    /// runs (the controller arms, and starts the fault reset, only then): a drive that
    /// faulted on its own while no master was there (communication loss after a crash) is
    /// cleared by the next master instead of failing its arming; one whose fault persists is
    /// reported when the grace period ends.
    pub fn rearm(&mut self, t: f64) {
        self.failure = None;
        let grace = t + f64::from(self.cfg.enable_timeout_ms) * 1e-3;
        for d in &mut self.devices {
            d.fault = None;
            d.enable_since = None;
            d.hb_lost_reported = false;
            if d.boot == BootState::Started {
                d.reset_grace_until = grace;
            } else {
                d.boot = BootState::NeedsReset;
                d.reset_grace_until = f64::INFINITY;
            }
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

    /// Start of a cycle at `t` (s): SYNC, then NMT commands, the master's heartbeat and SDO
    /// requests that are due; boot and heartbeat timeouts are checked.
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
                }
                BootState::Started => {
                    let last = d.last_heartbeat.unwrap_or(t);
                    if t - last > hb_timeout && !d.hb_lost_reported {
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
        // Everything runs: the grace periods of a re-arm start now (see `rearm`).
        if self.ready() {
            let grace = t + f64::from(self.cfg.enable_timeout_ms) * 1e-3;
            for d in &mut self.devices {
                if d.reset_grace_until == f64::INFINITY {
                    d.reset_grace_until = grace;
                }
            }
        }
        self.service_sdo(t, out);
    }

    /// Sends the next SDO request of every configuring device without one in flight, and
    /// repeats (or fails) requests that timed out.
    fn service_sdo(&mut self, t: f64, out: &mut FrameBuf) {
        let timeout = f64::from(self.cfg.sdo_timeout_ms) * 1e-3;
        for i in 0..self.devices.len() {
            let d = self.devices[i];
            if d.boot != BootState::Configuring {
                continue;
            }
            match d.inflight {
                Some((op, sent, tries)) => {
                    if t - sent <= timeout {
                        continue;
                    }
                    if tries > self.cfg.sdo_retries {
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
                    self.devices[i].inflight = Some((op, t, tries + 1));
                }
                None => {
                    let plan = &self.plans[role_index(d.role)];
                    match plan.get(d.plan_pos) {
                        Some(op) => {
                            let op = for_node(*op, d.node);
                            self.push(out, request_frame(&op, d.node));
                            self.devices[i].inflight = Some((op, t, 1));
                        }
                        None => self.devices[i].boot = BootState::Configured,
                    }
                }
            }
        }
    }

    /// End of the cycle at `t`: one RPDO1 per drive of every started wheel from
    /// `setpoints[wheel]` (SI, the native profile's setpoint type), then the SDO requests
    /// that became due during the cycle. Drives of wheels without a setpoint get a disabled
    /// zero.
    pub fn finish_cycle(&mut self, t: f64, setpoints: &[Setpoint], out: &mut FrameBuf) {
        self.now = t;
        let enable_timeout = f64::from(self.cfg.enable_timeout_ms) * 1e-3;
        for i in 0..self.devices.len() {
            let d = self.devices[i];
            if d.role == Role::Leg || d.boot != BootState::Started {
                continue;
            }
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
            let cw =
                ds402::master_controlword(state, enable, halt, sp.flags.fault_reset, d.controlword);
            let dev = &mut self.devices[i];
            dev.controlword = cw;
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
            self.push(
                out,
                pdo::DRIVE_RPDO1.pack(d.node, &[u32::from(cw), target as u32]),
            );
        }
        self.service_sdo(t, out);
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
                let d = &mut self.devices[i];
                d.last_emcy = Some(e);
                if !e.is_reset() {
                    d.latch(DeviceFault::Emcy {
                        code: e.code,
                        register: e.register,
                    });
                }
                Ok(Event::None)
            }
            Cob::Tpdo(n, _) => self.on_tpdo(i, n, f, t),
            _ => Err(Reject::UnknownId),
        }
    }

    fn on_heartbeat(&mut self, i: usize, f: &CanFrame, t: f64) -> Result<Event, Reject> {
        let (_, state) = nmt::parse_heartbeat(f).map_err(|_| Reject::Malformed)?;
        let d = &mut self.devices[i];
        d.nmt = Some(state);
        d.last_heartbeat = Some(t);
        match (d.boot, state) {
            (BootState::ResetSent(_), NmtState::BootUp) => {
                d.boot = BootState::Configuring;
                d.plan_pos = 0;
                d.inflight = None;
            }
            // Rebooted in the middle of its configuration: start over.
            (BootState::Configuring, NmtState::BootUp) => {
                d.plan_pos = 0;
                d.inflight = None;
            }
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

    fn on_sdo(&mut self, i: usize, f: &CanFrame, _t: f64) -> Result<Event, Reject> {
        let (_, resp) = SdoResponse::parse(f).map_err(|_| Reject::Malformed)?;
        let d = self.devices[i];
        let Some((op, _, _)) = d.inflight else {
            return Err(Reject::Unexpected);
        };
        if op.object() != resp.object() {
            return Err(Reject::Unexpected);
        }
        let (index, sub) = op.object();
        let (node, role) = (d.node, d.role);
        let advance = |m: &mut Master| {
            let d = &mut m.devices[i];
            d.inflight = None;
            d.plan_pos += 1;
        };
        match (op, resp) {
            (SdoOp::Write { .. }, SdoResponse::DownloadAck { .. }) => advance(self),
            (
                SdoOp::Verify {
                    mask,
                    expected,
                    what,
                    ..
                },
                SdoResponse::Upload { data, .. },
            ) => {
                let got = data.as_u32() & mask;
                if got == expected {
                    advance(self);
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
        match (d.role, n) {
            (Role::Drive | Role::Steer, 1) => {
                let v = pdo::DRIVE_TPDO1.unpack(f).map_err(|_| Reject::Malformed)?;
                let units = if d.role == Role::Drive {
                    self.cfg.drive
                } else {
                    self.cfg.steer
                };
                let pos = units.position_to_rad(v[0] as i32);
                let rate = units.velocity_to_si(v[1] as i32);
                let dev = &mut self.devices[i];
                let seq = dev.tpdo_seq;
                dev.tpdo_seq = (seq + 1) & 0x0F;
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
                let v = pdo::DRIVE_TPDO2.unpack(f).map_err(|_| Reject::Malformed)?;
                let sw = v[0] as u16;
                let dev = &mut self.devices[i];
                dev.statusword = Some(sw);
                if let Some(s) = State402::from_statusword(sw) {
                    if s.is_fault() && t >= dev.reset_grace_until {
                        dev.latch(DeviceFault::DriveFault { statusword: sw });
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

fn request_frame(op: &SdoOp, node: u8) -> CanFrame {
    match *op {
        SdoOp::Write { index, sub, data } => SdoRequest::Download { index, sub, data },
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
                        SdoRequest::Download { .. } => SdoResponse::DownloadAck { index, sub },
                        SdoRequest::Upload { .. } => {
                            let is_leg = self.cfg.wheels.iter().any(|w| w.leg_node == node);
                            let v = match (index, sub) {
                                (od::DEVICE_TYPE, 0) if is_leg => 0x0008_0196,
                                (od::DEVICE_TYPE, 0) => 0x0002_0192,
                                (od::MODES_OF_OPERATION_DISPLAY, 0) => 9,
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
        }
    }

    #[test]
    fn boots_every_device_with_one_request_in_flight_each() {
        let cfg = Cia402Config::for_wheels(4);
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
        let cfg = Cia402Config::for_wheels(4);
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
        let cfg = Cia402Config::for_wheels(1);
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
        let cfg = Cia402Config::for_wheels(1);
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
        let cfg = Cia402Config::for_wheels(1);
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
    fn faults_latch_until_rearm_and_name_the_device() {
        let cfg = Cia402Config::for_wheels(2);
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
                    register: 0x02
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
        let cfg = Cia402Config::for_wheels(1);
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
        let cfg = Cia402Config::for_wheels(1);
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
            let cfg = Cia402Config::for_wheels(4);
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
