//! One simulated CANopen device (sans-IO): the CiA 301 communication (NMT, expedited SDO
//! server, PDOs mapped by SDO writes, SYNC, heartbeat producer and consumer, EMCY) around a
//! CiA 402 drive (state machine, cyclic synchronous velocity) or a CiA 406 linear encoder.
//!
//! Behaviour, CiA 301 unless noted:
//! - Power-on and NMT reset: initialising for `boot_time`, then pre-operational with a
//!   boot-up message. Reset communication restores 0x1000–0x1FFF and leaves the drive
//!   application alone (a drive in fault stays in fault; one in operation enabled first
//!   takes the 0x6007 reaction to leaving operational, see below); reset node restores every
//!   object and restarts the drive in switch on disabled.
//! - SDO: served in pre-operational and operational (not in stopped, not while
//!   initialising); expedited, and segmented for the string objects (0x1008 device name,
//!   0x100A software version, 0x2000 a writable label of up to 32 bytes: toggle bit checked,
//!   0x05030000); a segmented download of a numeric object is written like an expedited one
//!   once its last segment came; block transfers are aborted with 0x05040001.
//!   Aborts: object missing 0x06020000, sub-index missing 0x06090011, read-only 0x06010002,
//!   write-only 0x06010001, size 0x06070010, value 0x06090030 (modes of operation other than
//!   0 or 9: only cyclic synchronous velocity is emulated; transmission types that do not
//!   exist; an abort-connection code above 3; a 29-bit COB-ID), too many mapping entries
//!   0x06090031.
//! - PDO mapping: a mapping object can be written only while its PDO is invalid (COB-ID bit
//!   31), entries only while sub-index 0 is 0; otherwise 0x08000022 (this emulation's choice
//!   for "not in the present device state"). Writing sub-index 0 = n checks entries 1..=n:
//!   each object exists, is mappable in that direction and has exactly the entry's length
//!   (else 0x06040041), and together they fit 64 bits (else 0x06040042). Changing the COB-ID
//!   of a valid PDO is refused (0x06090030). What the device sends and receives follows its
//!   dictionary.
//! - PDOs only in operational. A synchronous TPDO (type 1..=240) is sampled and sent at every
//!   n-th SYNC (type 0: at a SYNC when a mapped value changed); an event-driven TPDO (254,
//!   255) when a mapped value changed, no sooner than its inhibit time after the previous one,
//!   and every event-timer period. A synchronous RPDO's data is applied at the next SYNC, an
//!   asynchronous one on reception; an RPDO of the wrong length is dropped with EMCY 0x8210.
//! - Heartbeat consumer (0x1016:01, drives): monitoring starts with the first heartbeat of
//!   that node; a gap longer than the consumer time sends EMCY 0x8130. RPDO deadline (RPDO
//!   event timer, drives): after the first RPDO, a gap longer than the timer sends EMCY
//!   0x8250. Either, in operation enabled only, applies the abort connection option 0x6007
//!   (1 fault, 2 disable voltage, 3 quick stop); in the other states the drive function is
//!   off anyway and only the EMCY is sent. Each is reported once until the heartbeat or
//!   RPDO comes back. Leaving NMT operational in operation enabled applies the same reaction.
//! - CiA 402: not ready to switch on → switch on disabled when the boot completes; fault
//!   reaction active → fault one tick later. The motor follows the target velocity only in
//!   operation enabled, with modes of operation 9 and the halt bit clear; otherwise its power
//!   stage is off (the plant decelerates it at the torque limit). An injected motor fault sends
//!   EMCY 0x2310 (error register 0x03) and goes to fault; a fault reset sends EMCY 0x0000.
//!   Statusword: the state's bits, voltage enabled (bit 4) from ready to switch on up, remote
//!   (bit 9) always, bit 12 while the drive follows its command.
//! - Process values: position actual of a steering drive = the plant's steering angle,
//!   unwrapped, minus the counter's zero: the angle at power-on for an incremental encoder
//!   (so 0 at power-on wherever the wheel points), the home position after a homing, the
//!   switch edge for an absolute one; of a rolling drive = the integrated wheel angle;
//!   velocities from the plant's rates; encoder position and speed from the leg. Digital
//!   inputs 0x60FD bit 2 = the home switch.
//! - Homing mode (6): methods 3–6, 19–22, 33, 34, 35, 37 on the axis of [`super::twin`],
//!   started by a rising edge of controlword bit 4 in operation enabled, at the speeds of
//!   0x6099 and the acceleration of 0x609A; statusword bit 10 target reached, 12 attained,
//!   13 error (no switch or index within two turns).
//! - The twin's habits ([`super::twin::TwinConfig`]): an informational EMCY when started,
//!   vendor statusword bits, a lagging mode display, a factory TPDO2 on the encoders.

use super::od::{Access, Dictionary, Mappable};
use super::twin::{self, HomingRun, SteerAxis, TwinConfig};
use crate::plant::SensorReading;
use rollbase_control::angle;
use rollbase_driver::canopen::cob::{self, Cob};
use rollbase_driver::canopen::config::{Cia402Config, Role};
use rollbase_driver::canopen::ds402::{self, State as State402};
use rollbase_driver::canopen::emcy::{codes, Emcy};
use rollbase_driver::canopen::nmt::{self, NmtCommand, NmtState};
use rollbase_driver::canopen::od;
use rollbase_driver::canopen::pdo::{self, MapEntry};
use rollbase_driver::canopen::sdo::{AbortCode, SdoRequest, SdoResponse};
use rollbase_driver::canopen::units::{DriveUnits, EncoderUnits};
use rollbase_driver::frame::CanFrame;
use std::time::Duration;

/// PDOs per direction.
pub const PDOS: usize = 4;
/// CiA 402 error code object (UNSIGNED16): the last error.
pub const ERROR_CODE: u16 = 0x603F;
/// Error code recorded when the drive is faulted by leaving NMT operational (CiA 301:
/// 0x8100, communication).
pub const COMMUNICATION: u16 = 0x8100;

/// NMT state of a device, including the initialisation before its boot-up.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum DeviceNmt {
    /// Initialising after power-on or a reset; no communication.
    Initialising,
    /// Pre-operational: SDO and NMT, no PDO.
    PreOperational,
    /// Operational: everything.
    Operational,
    /// Stopped: NMT (and heartbeat) only.
    Stopped,
}

impl DeviceNmt {
    fn heartbeat(self) -> Option<NmtState> {
        match self {
            DeviceNmt::Initialising => None,
            DeviceNmt::PreOperational => Some(NmtState::PreOperational),
            DeviceNmt::Operational => Some(NmtState::Operational),
            DeviceNmt::Stopped => Some(NmtState::Stopped),
        }
    }
}

/// What the device does.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum App {
    /// A CiA 402 drive.
    Drive {
        /// Units of its position and velocity objects.
        units: DriveUnits,
        /// Steering (true) or rolling (false).
        steer: bool,
        /// Steering angle at position 0 (rad).
        offset: f64,
    },
    /// A CiA 406 linear encoder.
    Encoder {
        /// Units of its position and speed objects.
        units: EncoderUnits,
    },
}

/// Counters of one device.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct DeviceStats {
    /// SDO requests answered with data or an acknowledgement.
    pub sdo_served: u64,
    /// SDO requests answered with an abort.
    pub sdo_aborted: u64,
    /// NMT commands addressed to the device.
    pub nmt_commands: u64,
    /// Boot-up messages sent.
    pub boot_ups: u64,
    /// SYNCs received in operational.
    pub syncs: u64,
    /// TPDOs sent.
    pub tpdos_sent: u64,
    /// RPDOs received (operational, right length).
    pub rpdos_received: u64,
    /// RPDOs dropped for their length.
    pub rpdo_length_errors: u64,
    /// EMCY messages sent.
    pub emcy_sent: u64,
    /// Heartbeats sent.
    pub heartbeats_sent: u64,
    /// Heartbeat consumer timeouts.
    pub heartbeat_timeouts: u64,
    /// RPDO deadline timeouts.
    pub rpdo_timeouts: u64,
}

#[derive(Clone, Copy, Debug, Default)]
struct TpdoRun {
    sync_count: u8,
    last_sent: Option<Duration>,
    last_values: [u32; 8],
}

#[derive(Clone, Copy, Debug, Default)]
struct RpdoRun {
    pending: Option<[u32; 8]>,
    last_rx: Option<Duration>,
    timed_out: bool,
}

/// One simulated device.
#[derive(Clone, Debug)]
pub struct Device {
    node: u8,
    wheel: usize,
    role: Role,
    app: App,
    od: Dictionary,
    nmt: DeviceNmt,
    boot_time: Duration,
    boot_at: Duration,
    state: State402,
    last_cw: u16,
    halt: bool,
    fault_since: Option<Duration>,
    tpdo: [TpdoRun; PDOS],
    rpdo: [RpdoRun; PDOS],
    next_hb: Option<Duration>,
    consumer_last: Option<Duration>,
    consumer_timed_out: bool,
    last_sample: Option<Duration>,
    joint_angle: f64,
    last_wrapped: Option<f64>,
    stats: DeviceStats,
    /// The steering axis (steering drives).
    axis: Option<SteerAxis>,
    /// The unwrapped steering angle at position 0 (`None` until the first sample after a
    /// power-on: an incremental counter starts at 0 wherever the wheel points).
    zero: Option<f64>,
    prev_joint: Option<f64>,
    homing: HomingRun,
    home_cmd: f64,
    mode_pending: Option<(u32, Duration)>,
    mode_lag: Duration,
    info_emcy: u16,
    info_emcy_due: bool,
    vendor_bits: u16,
    first_status_delay: Duration,
    status_hold_until: Option<Duration>,
    strings: Vec<((u16, u8), Vec<u8>, bool)>,
    seg: Option<Segmented>,
    /// −1 when the motor is mounted mirrored (its positive direction turns the joint the
    /// negative way), else 1.
    mirror: f64,
    /// The quick stop's velocity ramp (joint rate, rad/s) while in quick stop active.
    qs_cmd: Option<f64>,
    /// The joint rate at the last sample (rad/s).
    last_rate: f64,
}

/// A segmented SDO transfer in progress (CiA 301 7.2.4.3.4–7).
#[derive(Clone, Debug)]
enum Segmented {
    Upload {
        data: Vec<u8>,
        pos: usize,
        toggle: u8,
    },
    Download {
        key: (u16, u8),
        buf: Vec<u8>,
        toggle: u8,
        /// A numeric object (not one of the strings): written as an expedited write would
        /// be once the last segment came.
        numeric: bool,
    },
}

/// Largest string the writable label 0x2000 takes (bytes).
pub const LABEL_MAX: usize = 32;
/// The writable label object (VISIBLE_STRING, segmented download).
pub const LABEL: u16 = 0x2000;

fn ms(v: u32) -> Duration {
    Duration::from_millis(u64::from(v))
}

fn valid_transmission(dir: Mappable, t: u8) -> bool {
    match dir {
        Mappable::Rpdo => matches!(t, 0..=240 | 254 | 255),
        _ => matches!(t, 0..=240 | 252..=255),
    }
}

/// Adds one PDO's communication (`comm`) and mapping (`map`) records: sub 0 = 5 entries,
/// COB-ID, transmission type, inhibit time (TPDOs only), event timer, and a mapping of
/// `first` alone (or empty) with room for 8 entries.
fn add_pdo(
    d: &mut Dictionary,
    comm: u16,
    map: u16,
    cob_id: u32,
    transmission: u32,
    tpdo: bool,
    first: Option<MapEntry>,
) {
    use Access::{Const, Rw};
    use Mappable as M;
    d.add(comm, 0, 1, Const, M::No, 5);
    d.add(comm, 1, 4, Rw, M::No, cob_id);
    d.add(comm, 2, 1, Rw, M::No, transmission);
    if tpdo {
        d.add(comm, 3, 2, Rw, M::No, 0);
    }
    d.add(comm, 5, 2, Rw, M::No, 0);
    d.add(map, 0, 1, Rw, M::No, u32::from(first.is_some()));
    for s in 1..=8u8 {
        let v = if s == 1 {
            first.map_or(0, MapEntry::raw)
        } else {
            0
        };
        d.add(map, s, 4, Rw, M::No, v);
    }
}

impl Device {
    /// Device `role` of wheel `wheel` with the node, units and homing offset of `cfg`,
    /// powered on at time 0 and initialising for `boot_time`, behaving as `twin` says.
    pub fn new(
        cfg: &Cia402Config,
        wheel: usize,
        role: Role,
        boot_time: Duration,
        twin: &TwinConfig,
    ) -> Self {
        let w = cfg.wheels.get(wheel).copied().unwrap_or(cfg.wheels[0]);
        let node = w.node(role);
        // The machine's gear is the ratio's magnitude: a negative ratio is how the platform
        // file compensates a mirrored motor (`twin.mirrored`), not part of the drive.
        let machine = |u: DriveUnits| DriveUnits {
            gear_ratio: u.gear_ratio.abs(),
            ..u
        };
        let app = match role {
            Role::Drive => App::Drive {
                units: machine(cfg.drive),
                steer: false,
                offset: 0.0,
            },
            Role::Steer => App::Drive {
                units: machine(cfg.steer),
                steer: true,
                offset: w.steer_offset_rad,
            },
            Role::Leg => App::Encoder {
                units: cfg.leg_encoder,
            },
        };
        let mut d = Self {
            node,
            wheel,
            role,
            app,
            od: Dictionary::new(),
            nmt: DeviceNmt::Initialising,
            boot_time,
            boot_at: boot_time,
            state: State402::NotReadyToSwitchOn,
            last_cw: 0,
            halt: false,
            fault_since: None,
            tpdo: [TpdoRun::default(); PDOS],
            rpdo: [RpdoRun::default(); PDOS],
            next_hb: None,
            consumer_last: None,
            consumer_timed_out: false,
            last_sample: None,
            joint_angle: 0.0,
            last_wrapped: None,
            stats: DeviceStats::default(),
            axis: (role == Role::Steer).then(|| {
                twin.axes
                    .get(wheel)
                    .copied()
                    .flatten()
                    .unwrap_or(SteerAxis {
                        switch_edge_rad: w.steer_offset_rad,
                        index_rad: w.steer_offset_rad,
                        ..SteerAxis::default()
                    })
            }),
            zero: None,
            prev_joint: None,
            homing: HomingRun::Idle,
            home_cmd: 0.0,
            mode_pending: None,
            mode_lag: ms(twin.mode_lag_ms),
            info_emcy: twin.info_emcy,
            info_emcy_due: false,
            vendor_bits: twin.vendor_status_bits,
            first_status_delay: ms(twin.first_status_delay_ms),
            status_hold_until: None,
            strings: Vec::new(),
            seg: None,
            mirror: if twin.mirrored.contains(&node) {
                -1.0
            } else {
                1.0
            },
            qs_cmd: None,
            last_rate: 0.0,
        };
        d.build_dictionary(twin);
        for &(n, index, sub, v) in &twin.objects {
            if n == node {
                d.od.set_default(index, sub, v);
            }
        }
        let name = match role {
            Role::Drive => "rollbase twin CiA 402 rolling drive",
            Role::Steer => "rollbase twin CiA 402 steering drive",
            Role::Leg => "rollbase twin CiA 406 linear encoder",
        };
        d.strings
            .push(((od::DEVICE_NAME, 0), name.as_bytes().to_vec(), false));
        d.strings
            .push(((od::SOFTWARE_VERSION, 0), b"1.0".to_vec(), false));
        d.strings.push(((LABEL, 0), Vec::new(), true));
        d.update_statusword();
        d
    }

    /// The string value of a VISIBLE_STRING object (0x1008 device name, 0x2000 label).
    pub fn string(&self, index: u16, sub: u8) -> Option<&[u8]> {
        self.strings
            .iter()
            .find(|(k, _, _)| *k == (index, sub))
            .map(|(_, v, _)| v.as_slice())
    }

    /// The steering position counter's zero (unwrapped angle), once set.
    pub fn zero_angle(&self) -> Option<f64> {
        self.zero
    }

    /// True while the drive runs a homing (mode 6).
    pub fn homing_active(&self) -> bool {
        matches!(self.homing, HomingRun::Seek { .. } | HomingRun::Stop)
    }

    fn is_drive(&self) -> bool {
        matches!(self.app, App::Drive { .. })
    }

    fn build_dictionary(&mut self, twin: &TwinConfig) {
        use Access::*;
        use Mappable as M;
        let node = u32::from(self.node);
        let drive = self.is_drive();
        let d = &mut self.od;
        let device_type = if drive { 0x0002_0192 } else { 0x0008_0196 };
        d.add(od::DEVICE_TYPE, 0, 4, Const, M::No, device_type);
        d.add(od::ERROR_REGISTER, 0, 1, Ro, M::Tpdo, 0);
        d.add(od::COB_ID_SYNC, 0, 4, Rw, M::No, 0x80);
        d.add(od::COMM_CYCLE_PERIOD, 0, 4, Rw, M::No, 0);
        d.add(od::PRODUCER_HEARTBEAT, 0, 2, Rw, M::No, 0);
        d.add(od::IDENTITY, 0, 1, Const, M::No, 4);
        // Vendor-ID 0: not a registered vendor (a simulation).
        d.add(od::IDENTITY, 1, 4, Const, M::No, 0);
        d.add(
            od::IDENTITY,
            2,
            4,
            Const,
            M::No,
            if drive { 402 } else { 406 },
        );
        d.add(od::IDENTITY, 3, 4, Const, M::No, 1);
        d.add(od::IDENTITY, 4, 4, Const, M::No, node);
        // 0x1003: number of errors, newest error (code in the low word).
        d.add(od::PRE_DEFINED_ERROR_FIELD, 0, 1, Rw, M::No, 0);
        d.add(od::PRE_DEFINED_ERROR_FIELD, 1, 4, Ro, M::No, 0);
        // Encoders have TPDO1 and TPDO2 only (an optional object missing on a device type).
        let tpdos = if drive { PDOS as u16 } else { 2 };
        for n in 0..tpdos {
            let comm = od::TPDO_COMM + n;
            let map = od::TPDO_MAP + n;
            let base = u32::from(cob::TPDO[usize::from(n)]) + node;
            // TPDO1 exists by default (CiA 402: statusword; CiA 406: position value), the
            // others not.
            let cob_id = if n == 0 {
                od::PDO_COB_NO_RTR | base
            } else {
                od::PDO_COB_INVALID | od::PDO_COB_NO_RTR | base
            };
            let default_type = if drive { 255 } else { 1 };
            let first = match (n, drive) {
                (0, true) => Some(MapEntry::new(od::STATUSWORD, 0, 16)),
                (0, false) => Some(MapEntry::new(od::POSITION_VALUE, 0, 32)),
                _ => None,
            };
            let ty = if n == 0 { default_type } else { 255 };
            // A factory default left on: the encoder's TPDO2 sends the position at every SYNC.
            let (cob_id, ty, first) = if n == 1 && !drive && twin.encoder_tpdo2_on {
                (
                    od::PDO_COB_NO_RTR | base,
                    1,
                    Some(MapEntry::new(od::POSITION_VALUE, 0, 32)),
                )
            } else {
                (cob_id, ty, first)
            };
            add_pdo(d, comm, map, cob_id, ty, true, first);
        }
        if drive {
            for n in 0..tpdos {
                let comm = od::RPDO_COMM + n;
                let map = od::RPDO_MAP + n;
                let base = u32::from(cob::RPDO[usize::from(n)]) + node;
                let cob_id = if n == 0 {
                    base
                } else {
                    od::PDO_COB_INVALID | base
                };
                let first = (n == 0).then(|| MapEntry::new(od::CONTROLWORD, 0, 16));
                add_pdo(d, comm, map, cob_id, 255, false, first);
            }
            d.add(od::CONSUMER_HEARTBEAT, 0, 1, Const, M::No, 1);
            d.add(od::CONSUMER_HEARTBEAT, 1, 4, Rw, M::No, 0);
            d.add(od::ABORT_CONNECTION_OPTION, 0, 2, Rw, M::No, 1);
            d.add(ERROR_CODE, 0, 2, Ro, M::Tpdo, 0);
            d.add(od::CONTROLWORD, 0, 2, Rw, M::Rpdo, 0);
            d.add(od::STATUSWORD, 0, 2, Ro, M::Tpdo, 0);
            d.add(od::MODES_OF_OPERATION, 0, 1, Rw, M::Rpdo, 0);
            d.add(od::MODES_OF_OPERATION_DISPLAY, 0, 1, Ro, M::Tpdo, 0);
            d.add(od::POSITION_ACTUAL, 0, 4, Ro, M::Tpdo, 0);
            d.add(od::VELOCITY_ACTUAL, 0, 4, Ro, M::Tpdo, 0);
            d.add(od::INTERPOLATION_TIME_PERIOD, 0, 1, Const, M::No, 2);
            d.add(od::INTERPOLATION_TIME_PERIOD, 1, 1, Rw, M::No, 1);
            d.add(
                od::INTERPOLATION_TIME_PERIOD,
                2,
                1,
                Rw,
                M::No,
                u32::from((-3i8) as u8),
            );
            d.add(od::TARGET_VELOCITY, 0, 4, Rw, M::Rpdo, 0);
            d.add(od::DIGITAL_INPUTS, 0, 4, Ro, M::Tpdo, 0);
            d.add(od::QUICK_STOP_OPTION, 0, 2, Rw, M::No, 2);
            // Quick stop deceleration (acceleration units; the factory's: the largest).
            d.add(od::QUICK_STOP_DECELERATION, 0, 4, Rw, M::No, 0x7FFF_FFFF);
            d.add(od::POLARITY, 0, 1, Rw, M::No, 0);
            d.add(od::FAULT_REACTION_OPTION, 0, 2, Rw, M::No, 2);
            d.add(od::HOMING_METHOD, 0, 1, Rw, M::No, 0);
            d.add(od::HOMING_SPEEDS, 0, 1, Const, M::No, 2);
            d.add(od::HOMING_SPEEDS, 1, 4, Rw, M::No, 0);
            d.add(od::HOMING_SPEEDS, 2, 4, Rw, M::No, 0);
            d.add(od::HOMING_ACCELERATION, 0, 4, Rw, M::No, 0);
            d.add(od::HOME_OFFSET, 0, 4, Rw, M::No, 0);
            if let App::Drive { units, steer, .. } = self.app {
                d.add(
                    od::SI_UNIT_VELOCITY,
                    0,
                    4,
                    Rw,
                    M::No,
                    units.velocity_unit.si_unit_velocity(),
                );
                d.add(od::POSITION_ENCODER_RESOLUTION, 0, 1, Const, M::No, 2);
                d.add(
                    od::POSITION_ENCODER_RESOLUTION,
                    1,
                    4,
                    Rw,
                    M::No,
                    units.increments_per_rev,
                );
                d.add(od::POSITION_ENCODER_RESOLUTION, 2, 4, Rw, M::No, 1);
                // Rolling drives have no gear ratio object (optional, missing on a type).
                if steer {
                    d.add(od::GEAR_RATIO, 0, 1, Const, M::No, 2);
                    d.add(od::GEAR_RATIO, 1, 4, Rw, M::No, 1);
                    d.add(od::GEAR_RATIO, 2, 4, Rw, M::No, 1);
                }
            }
        } else if let App::Encoder { units } = self.app {
            d.add(od::POSITION_VALUE, 0, 4, Ro, M::Tpdo, 0);
            d.add(od::MEASURING_STEP, 0, 1, Const, M::No, 2);
            d.add(od::MEASURING_STEP, 1, 4, Ro, M::No, units.position_step_nm);
            d.add(od::MEASURING_STEP, 2, 4, Ro, M::No, units.speed_step_um_s);
            d.add(od::SPEED_VALUE, 0, 1, Const, M::No, 1);
            d.add(od::SPEED_VALUE, 1, 2, Ro, M::Tpdo, 0);
        }
    }

    /// Node-ID.
    pub fn node(&self) -> u8 {
        self.node
    }

    /// Wheel index.
    pub fn wheel(&self) -> usize {
        self.wheel
    }

    /// Role on the platform.
    pub fn role(&self) -> Role {
        self.role
    }

    /// NMT state.
    pub fn nmt(&self) -> DeviceNmt {
        self.nmt
    }

    /// CiA 402 state (drives; an encoder stays in not ready to switch on).
    pub fn state402(&self) -> State402 {
        self.state
    }

    /// The statusword (drives).
    pub fn statusword(&self) -> u16 {
        self.od.value(od::STATUSWORD, 0) as u16
    }

    /// Counters.
    pub fn stats(&self) -> &DeviceStats {
        &self.stats
    }

    /// The object dictionary (read access, for tests and reports).
    pub fn dictionary(&self) -> &Dictionary {
        &self.od
    }

    /// The joint rate the motor is told to follow (rad/s), or `None` when the drive function
    /// is off (not enabled, halt, not in cyclic synchronous velocity, or an encoder).
    pub fn motor(&self) -> Option<f64> {
        if self.homing_active() && self.state == State402::OperationEnabled {
            return Some(self.pos_sign() * self.home_cmd);
        }
        if self.state == State402::QuickStopActive && self.is_drive() {
            return self.qs_cmd;
        }
        match self.app {
            App::Drive { units, .. } if self.follows() => Some(
                self.vel_sign()
                    * units.velocity_to_si(self.od.value(od::TARGET_VELOCITY, 0) as i32),
            ),
            _ => None,
        }
    }

    /// Sign between the joint and the drive's position values: the mounting times the
    /// position polarity (0x607E bit 7).
    fn pos_sign(&self) -> f64 {
        let inverted = self.od.value(od::POLARITY, 0) & 0x80 != 0;
        self.mirror * if inverted { -1.0 } else { 1.0 }
    }

    /// Sign between the joint and the drive's velocity values: the mounting times the
    /// velocity polarity (0x607E bit 6).
    fn vel_sign(&self) -> f64 {
        let inverted = self.od.value(od::POLARITY, 0) & 0x40 != 0;
        self.mirror * if inverted { -1.0 } else { 1.0 }
    }

    /// The quick stop option code 0x605A.
    fn quick_stop_option(&self) -> i16 {
        self.od.value(od::QUICK_STOP_OPTION, 0) as u16 as i16
    }

    /// One step of a quick stop (in quick stop active): the velocity ramps to zero at the
    /// quick-stop deceleration 0x6085 (options 1, 2, 5, 6; the slow-down ramp of 1 and 5 is
    /// not emulated apart from it) or at the torque limit (3, 4, 7, 8: the power stage
    /// brakes, `qs_cmd` none until at rest); at rest, options 1–4 go on to switch on
    /// disabled, 5–8 hold.
    fn quick_stop_step(&mut self, now: Duration, dt: f64) {
        let App::Drive { units, .. } = self.app else {
            return;
        };
        let opt = self.quick_stop_option();
        let stopped = match opt {
            1 | 2 | 5 | 6 => {
                let decel = units
                    .velocity_to_si(self.od.value(od::QUICK_STOP_DECELERATION, 0) as i32)
                    .abs();
                let c = self.qs_cmd.unwrap_or(self.last_rate);
                let a = decel * dt;
                let next = if c.abs() <= a { 0.0 } else { c - a.copysign(c) };
                self.qs_cmd = Some(next);
                next == 0.0 && self.last_rate.abs() < 1e-3
            }
            _ => {
                let at_rest = self.last_rate.abs() < 1e-3;
                self.qs_cmd = at_rest.then_some(0.0);
                at_rest
            }
        };
        if stopped && (1..=4).contains(&opt) {
            self.set_state(now, State402::SwitchOnDisabled);
        }
    }

    fn follows(&self) -> bool {
        self.state == State402::OperationEnabled
            && !self.halt
            && self.od.value(od::MODES_OF_OPERATION, 0) as u8 as i8 == od::MODE_CSV
    }

    fn update_statusword(&mut self) {
        if !self.is_drive() {
            return;
        }
        let mut sw = self.state.statusword_bits() | ds402::SW_REMOTE;
        if matches!(
            self.state,
            State402::ReadyToSwitchOn
                | State402::SwitchedOn
                | State402::OperationEnabled
                | State402::QuickStopActive
        ) {
            sw |= ds402::SW_VOLTAGE_ENABLED;
        }
        let mode = self.od.value(od::MODES_OF_OPERATION_DISPLAY, 0) as u8 as i8;
        if mode == od::MODE_HOMING {
            // Homing mode: bit 10 target reached (not moving), 12 attained, 13 error.
            match self.homing {
                HomingRun::Attained => sw |= ds402::SW_TARGET_REACHED | (1 << 12),
                HomingRun::Error => sw |= ds402::SW_TARGET_REACHED | (1 << 13),
                HomingRun::Idle => sw |= ds402::SW_TARGET_REACHED,
                _ => {}
            }
        } else if self.follows() {
            sw |= ds402::SW_FOLLOWS_COMMAND;
        }
        sw |= self.vendor_bits;
        self.od.set(od::STATUSWORD, 0, u32::from(sw));
    }

    fn set_state(&mut self, now: Duration, s: State402) {
        if s != self.state {
            if s != State402::OperationEnabled && self.homing_active() {
                self.homing = HomingRun::Idle;
                self.home_cmd = 0.0;
            }
            if s == State402::QuickStopActive {
                // The ramp starts from the speed the joint has now; option 0 disables the
                // drive function at once (the motor coasts).
                self.qs_cmd = Some(self.last_rate);
                if self.quick_stop_option() == 0 && self.state == State402::OperationEnabled {
                    self.qs_cmd = None;
                    self.state = State402::SwitchOnDisabled;
                    self.fault_since = None;
                    self.update_statusword();
                    return;
                }
            } else {
                self.qs_cmd = None;
            }
            self.state = s;
            self.fault_since = (s == State402::FaultReactionActive).then_some(now);
        }
        self.update_statusword();
    }

    fn emcy(&mut self, code: u16, register: u8, out: &mut impl FnMut(CanFrame)) {
        self.od.set(od::ERROR_REGISTER, 0, u32::from(register));
        if code != codes::NO_ERROR && register != 0 {
            self.od.set(od::PRE_DEFINED_ERROR_FIELD, 1, u32::from(code));
            let n = self.od.value(od::PRE_DEFINED_ERROR_FIELD, 0);
            self.od.set(od::PRE_DEFINED_ERROR_FIELD, 0, (n + 1).min(1));
        }
        self.stats.emcy_sent += 1;
        out(Emcy::new(code, register).to_frame(self.node));
    }

    /// A fault of the drive (e.g. an over-current): EMCY with `code` and the error register
    /// 0x03 (generic, current), then fault reaction active → fault. No effect on an encoder.
    pub fn inject_fault(&mut self, now: Duration, code: u16, out: &mut impl FnMut(CanFrame)) {
        if !self.is_drive() || self.nmt == DeviceNmt::Initialising {
            return;
        }
        self.od.set(ERROR_CODE, 0, u32::from(code));
        self.emcy(code, 0x03, out);
        if !self.state.is_fault() {
            self.set_state(now, State402::FaultReactionActive);
        }
    }

    fn start_homing(&mut self) {
        let (Some(axis), App::Drive { .. }) = (self.axis, self.app) else {
            self.homing = HomingRun::Error;
            return;
        };
        let method = self.od.value(od::HOMING_METHOD, 0) as u8 as i8;
        // In the drive's coordinates (its positive direction): a mirrored motor or an
        // inverted polarity sees the switch on the other side.
        let sign = self.pos_sign();
        let angle = angle::wrap(sign * self.last_wrapped.unwrap_or(0.0));
        let axis = twin::axis_in(&axis, sign);
        self.home_cmd = 0.0;
        self.homing = match twin::start(method, &axis, angle) {
            Ok(Some(run)) => run,
            Ok(None) => {
                // Current position (35, 37): the position here is the home position.
                self.zero = Some(self.joint_angle);
                HomingRun::Attained
            }
            Err(()) => HomingRun::Error,
        };
        self.update_statusword();
    }

    /// One step of the drive's homing at the latest sample: ramp the homing speed, look
    /// for the switch edge or index pulse between the last two samples, stop there.
    fn homing_step(&mut self, dt: f64) {
        let (Some(axis), App::Drive { units, .. }) = (self.axis, self.app) else {
            return;
        };
        let speed = |sub: u8| {
            units
                .velocity_to_si(self.od.value(od::HOMING_SPEEDS, sub) as i32)
                .abs()
        };
        let accel = units
            .velocity_to_si(self.od.value(od::HOMING_ACCELERATION, 0) as i32)
            .abs();
        let a = if accel > 0.0 { accel } else { 1.0 } * dt;
        let ramp = |cmd: f64, target: f64| -> f64 {
            if (target - cmd).abs() <= a {
                target
            } else {
                cmd + a.copysign(target - cmd)
            }
        };
        // In the drive's coordinates, as the drive homes.
        let sign = self.pos_sign();
        let axis = twin::axis_in(&axis, sign);
        let (prev, now) = (
            sign * self.prev_joint.unwrap_or(self.joint_angle),
            sign * self.joint_angle,
        );
        match self.homing {
            HomingRun::Seek {
                dir,
                edge,
                then_index,
                travel,
            } => {
                let target = dir * if edge { speed(1) } else { speed(2) };
                self.home_cmd = ramp(self.home_cmd, target);
                let travel = travel + (now - prev).abs();
                let mark = if edge {
                    axis.switch_edge_rad
                } else {
                    axis.index_rad
                };
                let hit = if edge && axis.switch_width_rad <= 0.0 {
                    None
                } else {
                    twin::crossed(prev, now, mark)
                };
                self.homing = match (hit, then_index) {
                    (Some(_), Some(d)) => HomingRun::Seek {
                        dir: d,
                        edge: false,
                        then_index: None,
                        travel: 0.0,
                    },
                    (Some(at), None) => {
                        self.zero = Some(sign * at);
                        HomingRun::Stop
                    }
                    // Two turns without the switch or the index: give up (homing error).
                    (None, _) if travel > 2.0 * std::f64::consts::TAU => {
                        self.home_cmd = 0.0;
                        HomingRun::Error
                    }
                    (None, _) => HomingRun::Seek {
                        dir,
                        edge,
                        then_index,
                        travel,
                    },
                };
            }
            HomingRun::Stop => {
                self.home_cmd = ramp(self.home_cmd, 0.0);
                if self.home_cmd == 0.0 {
                    self.homing = HomingRun::Attained;
                }
            }
            _ => return,
        }
        self.update_statusword();
    }

    /// The device loses power and boots again (after its boot time): every object back to
    /// its default, the drive in switch on disabled, an incremental position counter at 0
    /// wherever the axis is.
    pub fn power_cycle(&mut self, now: Duration) {
        self.nmt = DeviceNmt::Initialising;
        self.reset(now, true);
    }

    /// An EMCY from the device: with error register 0 a notice (nothing else happens); with
    /// another register on a drive, a fault with `code` (as [`Device::inject_fault`]).
    pub fn send_emcy(
        &mut self,
        now: Duration,
        code: u16,
        register: u8,
        out: &mut impl FnMut(CanFrame),
    ) {
        if self.nmt == DeviceNmt::Initialising {
            return;
        }
        if register == 0 || !self.is_drive() {
            self.stats.emcy_sent += 1;
            out(Emcy::new(code, register).to_frame(self.node));
            return;
        }
        self.od.set(ERROR_CODE, 0, u32::from(code));
        self.emcy(code, register, out);
        if !self.state.is_fault() {
            self.set_state(now, State402::FaultReactionActive);
        }
    }

    /// The abort connection option (0x6007) reaction, in operation enabled only.
    fn connection_reaction(&mut self, now: Duration, code: u16) {
        if self.state != State402::OperationEnabled {
            return;
        }
        match self.od.value(od::ABORT_CONNECTION_OPTION, 0) as u16 as i16 {
            1 => {
                self.od.set(ERROR_CODE, 0, u32::from(code));
                self.set_state(now, State402::FaultReactionActive);
            }
            2 => self.set_state(now, State402::SwitchOnDisabled),
            3 => self.set_state(now, State402::QuickStopActive),
            _ => {}
        }
    }

    fn comm_loss(&mut self, now: Duration, code: u16, out: &mut impl FnMut(CanFrame)) {
        self.emcy(code, 0x11, out);
        self.connection_reaction(now, code);
    }

    fn process_controlword(&mut self, now: Duration, cw: u16, out: &mut impl FnMut(CanFrame)) {
        if !self.is_drive() {
            return;
        }
        let prev = self.last_cw;
        self.last_cw = cw;
        self.halt = cw & ds402::CW_HALT != 0;
        let before = self.state;
        let after = ds402::device_transition(before, ds402::decode_controlword(cw, prev));
        if before == State402::Fault && after == State402::SwitchOnDisabled {
            self.od.set(ERROR_CODE, 0, 0);
            self.emcy(codes::NO_ERROR, 0, out);
        }
        self.set_state(now, after);
        // Homing mode: a rising edge of bit 4 in operation enabled starts the homing, a
        // falling edge interrupts it.
        let mode = self.od.value(od::MODES_OF_OPERATION_DISPLAY, 0) as u8 as i8;
        let start = cw & 0x10 != 0 && prev & 0x10 == 0;
        if mode == od::MODE_HOMING && self.state == State402::OperationEnabled && start {
            self.start_homing();
        } else if cw & 0x10 == 0 && self.homing_active() {
            self.homing = HomingRun::Idle;
            self.home_cmd = 0.0;
        }
        self.update_statusword();
    }

    /// Writes an object with its side effects (controlword, heartbeat times …), no checks.
    fn apply(
        &mut self,
        now: Duration,
        index: u16,
        sub: u8,
        v: u32,
        out: &mut impl FnMut(CanFrame),
    ) {
        match (index, sub) {
            (od::MODES_OF_OPERATION, 0) => {
                let mode = v as u8 as i8;
                if matches!(mode, 0 | od::MODE_HOMING | od::MODE_CSV) {
                    self.od.set(index, 0, v);
                    if self.mode_lag.is_zero() {
                        self.od.set(od::MODES_OF_OPERATION_DISPLAY, 0, v);
                    } else {
                        // The display follows a little later, as on many drives.
                        self.mode_pending = Some((v, now + self.mode_lag));
                    }
                    if mode != od::MODE_HOMING {
                        self.homing = HomingRun::Idle;
                    }
                    self.update_statusword();
                }
            }
            (od::CONTROLWORD, 0) => {
                self.od.set(index, sub, v);
                self.process_controlword(now, v as u16, out);
            }
            (od::PRODUCER_HEARTBEAT, 0) => {
                self.od.set(index, sub, v);
                self.next_hb = (v & 0xFFFF != 0).then(|| now + ms(v & 0xFFFF));
            }
            (od::CONSUMER_HEARTBEAT, 1) => {
                self.od.set(index, sub, v);
                self.consumer_last = None;
                self.consumer_timed_out = false;
            }
            _ => self.od.set(index, sub, v),
        }
    }

    /// Which PDO an object index configures: (direction, number 0..PDOS, is mapping).
    fn pdo_object(&self, index: u16) -> Option<(Mappable, usize, bool)> {
        let n = PDOS as u16;
        let f = |base: u16| {
            (base..base + n)
                .contains(&index)
                .then(|| usize::from(index - base))
        };
        if let Some(k) = f(od::TPDO_COMM) {
            return Some((Mappable::Tpdo, k, false));
        }
        if let Some(k) = f(od::TPDO_MAP) {
            return Some((Mappable::Tpdo, k, true));
        }
        if !self.is_drive() {
            return None;
        }
        if let Some(k) = f(od::RPDO_COMM) {
            return Some((Mappable::Rpdo, k, false));
        }
        f(od::RPDO_MAP).map(|k| (Mappable::Rpdo, k, true))
    }

    fn comm_index(dir: Mappable, k: usize) -> u16 {
        match dir {
            Mappable::Rpdo => od::RPDO_COMM + k as u16,
            _ => od::TPDO_COMM + k as u16,
        }
    }

    fn map_index(dir: Mappable, k: usize) -> u16 {
        match dir {
            Mappable::Rpdo => od::RPDO_MAP + k as u16,
            _ => od::TPDO_MAP + k as u16,
        }
    }

    fn pdo_valid(&self, dir: Mappable, k: usize) -> bool {
        self.od
            .get(Self::comm_index(dir, k), 1)
            .is_some_and(|e| e.value & od::PDO_COB_INVALID == 0)
    }

    fn mapping(&self, dir: Mappable, k: usize) -> ([MapEntry; 8], usize) {
        let ix = Self::map_index(dir, k);
        let n = (self.od.value(ix, 0) as usize).min(8);
        let mut e = [MapEntry::new(0, 0, 0); 8];
        for (i, slot) in e.iter_mut().enumerate().take(n) {
            *slot = MapEntry::from_raw(self.od.value(ix, (i + 1) as u8));
        }
        (e, n)
    }

    /// The checks of an SDO download beyond existence, access and size.
    fn check_write(&self, index: u16, sub: u8, v: u32) -> Result<(), AbortCode> {
        if let Some((dir, k, is_map)) = self.pdo_object(index) {
            if !is_map {
                match sub {
                    1 => {
                        let cur = self.od.value(index, 1);
                        let cur_valid = cur & od::PDO_COB_INVALID == 0;
                        let new_valid = v & od::PDO_COB_INVALID == 0;
                        if v & (1 << 29) != 0
                            || (cur_valid && new_valid && (cur & 0x7FF) != (v & 0x7FF))
                        {
                            return Err(AbortCode::InvalidValue);
                        }
                    }
                    2 if !valid_transmission(dir, v as u8) => return Err(AbortCode::InvalidValue),
                    _ => {}
                }
                return Ok(());
            }
            if self.pdo_valid(dir, k) {
                return Err(AbortCode::DeviceState);
            }
            if sub != 0 {
                return if self.od.value(index, 0) != 0 {
                    Err(AbortCode::DeviceState)
                } else {
                    Ok(())
                };
            }
            if v > 8 {
                return Err(AbortCode::ValueTooHigh);
            }
            let mut bits = 0u32;
            for s in 1..=v as u8 {
                let e = MapEntry::from_raw(self.od.value(index, s));
                match self.od.get(e.index, e.sub) {
                    Some(o) if o.map == dir && u32::from(e.bits) == 8 * u32::from(o.size) => {}
                    _ => return Err(AbortCode::NotMappable),
                }
                bits += u32::from(e.bits);
            }
            if bits > 64 {
                return Err(AbortCode::PdoLength);
            }
            return Ok(());
        }
        match (index, sub) {
            (od::MODES_OF_OPERATION, 0) => {
                let m = v as u8 as i8;
                if !matches!(m, 0 | od::MODE_HOMING | od::MODE_CSV) {
                    return Err(AbortCode::InvalidValue);
                }
            }
            (od::HOMING_METHOD, 0)
                if twin::start(v as u8 as i8, &SteerAxis::default(), 0.0).is_err() =>
            {
                return Err(AbortCode::InvalidValue)
            }
            (od::ABORT_CONNECTION_OPTION, 0) if (v as u16 as i16) > 3 => {
                return Err(AbortCode::InvalidValue)
            }
            _ => {}
        }
        Ok(())
    }

    /// Segmented transfers and string objects (CiA 301 7.2.4.3): true when `f` was one.
    fn on_sdo_segmented(
        &mut self,
        now: Duration,
        f: &CanFrame,
        out: &mut impl FnMut(CanFrame),
    ) -> bool {
        if f.len() != 8 {
            return false;
        }
        let d = f.data();
        let (cs, index, sub) = (d[0], u16::from_le_bytes([d[1], d[2]]), d[3]);
        let id = cob::sdo_tx(self.node);
        let mut send = |bytes: [u8; 8], stats: &mut DeviceStats| {
            stats.sdo_served += 1;
            if let Ok(fr) = CanFrame::new(id, &bytes) {
                out(fr);
            }
        };
        let abort = |index: u16, sub: u8, code: AbortCode| {
            SdoResponse::Abort { index, sub, code }.to_frame(self.node)
        };
        let string = self.strings.iter().position(|(k, _, _)| *k == (index, sub));
        match cs >> 5 {
            // Initiate upload of a string.
            2 => {
                let Some(k) = string else { return false };
                let data = self.strings[k].1.clone();
                self.seg = None;
                let mut r = [0u8; 8];
                r[1..3].copy_from_slice(&index.to_le_bytes());
                r[3] = sub;
                if (1..=4).contains(&data.len()) {
                    r[0] = 0x43 | (((4 - data.len()) as u8) << 2);
                    r[4..4 + data.len()].copy_from_slice(&data);
                } else {
                    r[0] = 0x41;
                    r[4..8].copy_from_slice(&(data.len() as u32).to_le_bytes());
                    self.seg = Some(Segmented::Upload {
                        data,
                        pos: 0,
                        toggle: 0,
                    });
                }
                send(r, &mut self.stats);
                true
            }
            // Upload segment request.
            3 => {
                let toggle = (cs >> 4) & 1;
                match self.seg.take() {
                    Some(Segmented::Upload {
                        data,
                        pos,
                        toggle: t,
                    }) if t == toggle => {
                        let n = (data.len() - pos).min(7);
                        let last = pos + n >= data.len();
                        let mut r = [0u8; 8];
                        r[0] = (toggle << 4) | (((7 - n) as u8) << 1) | u8::from(last);
                        r[1..1 + n].copy_from_slice(&data[pos..pos + n]);
                        if !last {
                            self.seg = Some(Segmented::Upload {
                                data,
                                pos: pos + n,
                                toggle: toggle ^ 1,
                            });
                        }
                        send(r, &mut self.stats);
                    }
                    Some(Segmented::Upload { .. }) => {
                        self.stats.sdo_aborted += 1;
                        out(abort(0, 0, AbortCode::ToggleBit));
                    }
                    _ => {
                        self.stats.sdo_aborted += 1;
                        out(abort(0, 0, AbortCode::InvalidCommand));
                    }
                }
                true
            }
            // Initiate download: segmented (e = 0), or expedited to a string.
            1 => {
                let expedited = cs & 0x02 != 0;
                let Some(k) = string else {
                    if expedited {
                        return false;
                    }
                    // A segmented download of a numeric object: legal (CiA 301 lets the client
                    // choose), written once the last segment came.
                    let code = match self.od.get(index, sub) {
                        None if self.od.has_index(index) => Some(AbortCode::NoSubIndex),
                        None => Some(AbortCode::NoObject),
                        Some(e) if matches!(e.access, Access::Ro | Access::Const) => {
                            Some(AbortCode::ReadOnly)
                        }
                        Some(_) => None,
                    };
                    if let Some(code) = code {
                        self.stats.sdo_aborted += 1;
                        out(abort(index, sub, code));
                        return true;
                    }
                    self.seg = Some(Segmented::Download {
                        key: (index, sub),
                        buf: Vec::new(),
                        toggle: 0,
                        numeric: true,
                    });
                    let mut r = [0u8; 8];
                    r[0] = 0x60;
                    r[1..3].copy_from_slice(&index.to_le_bytes());
                    r[3] = sub;
                    send(r, &mut self.stats);
                    return true;
                };
                self.seg = None;
                if !self.strings[k].2 {
                    self.stats.sdo_aborted += 1;
                    out(abort(index, sub, AbortCode::ReadOnly));
                    return true;
                }
                if expedited {
                    let n = if cs & 0x01 != 0 {
                        4 - usize::from((cs >> 2) & 3)
                    } else {
                        4
                    };
                    self.strings[k].1 = d[4..4 + n].to_vec();
                } else {
                    let size = u32::from_le_bytes([d[4], d[5], d[6], d[7]]) as usize;
                    if cs & 0x01 != 0 && size > LABEL_MAX {
                        self.stats.sdo_aborted += 1;
                        out(abort(index, sub, AbortCode::LengthTooHigh));
                        return true;
                    }
                    self.seg = Some(Segmented::Download {
                        key: (index, sub),
                        buf: Vec::new(),
                        toggle: 0,
                        numeric: false,
                    });
                }
                let mut r = [0u8; 8];
                r[0] = 0x60;
                r[1..3].copy_from_slice(&index.to_le_bytes());
                r[3] = sub;
                send(r, &mut self.stats);
                true
            }
            // Download segment.
            0 => {
                let toggle = (cs >> 4) & 1;
                match self.seg.take() {
                    Some(Segmented::Download {
                        key,
                        mut buf,
                        toggle: t,
                        numeric,
                    }) if t == toggle => {
                        let n = 7 - usize::from((cs >> 1) & 7);
                        buf.extend_from_slice(&d[1..1 + n]);
                        let max = if numeric { 4 } else { LABEL_MAX };
                        if buf.len() > max {
                            self.stats.sdo_aborted += 1;
                            out(abort(key.0, key.1, AbortCode::LengthTooHigh));
                            return true;
                        }
                        let last = cs & 0x01 != 0;
                        if last && numeric {
                            // Written as an expedited write of the same bytes would be.
                            let mut v = [0u8; 4];
                            v[..buf.len()].copy_from_slice(&buf);
                            let data = rollbase_driver::canopen::sdo::SdoData::new(
                                u32::from_le_bytes(v),
                                buf.len() as u8,
                            );
                            let r = if buf.is_empty() {
                                Err(AbortCode::LengthTooLow)
                            } else {
                                self.od
                                    .sdo_check_write(key.0, key.1, &data)
                                    .and_then(|_| self.check_write(key.0, key.1, data.as_u32()))
                            };
                            if let Err(code) = r {
                                self.stats.sdo_aborted += 1;
                                out(SdoResponse::Abort {
                                    index: key.0,
                                    sub: key.1,
                                    code,
                                }
                                .to_frame(self.node));
                                return true;
                            }
                            self.apply(now, key.0, key.1, data.as_u32(), out);
                        } else if last {
                            if let Some(e) = self.strings.iter_mut().find(|(k, _, _)| *k == key) {
                                e.1 = buf;
                            }
                        } else {
                            self.seg = Some(Segmented::Download {
                                key,
                                buf,
                                toggle: toggle ^ 1,
                                numeric,
                            });
                        }
                        self.stats.sdo_served += 1;
                        let ack = [0x20 | (toggle << 4), 0, 0, 0, 0, 0, 0, 0];
                        if let Ok(fr) = CanFrame::new(cob::sdo_tx(self.node), &ack) {
                            out(fr);
                        }
                    }
                    Some(Segmented::Download { key, .. }) => {
                        self.stats.sdo_aborted += 1;
                        out(abort(key.0, key.1, AbortCode::ToggleBit));
                    }
                    _ => {
                        self.stats.sdo_aborted += 1;
                        out(abort(0, 0, AbortCode::InvalidCommand));
                    }
                }
                true
            }
            4 => {
                self.seg = None;
                false
            }
            _ => false,
        }
    }

    fn on_sdo(&mut self, now: Duration, f: &CanFrame, out: &mut impl FnMut(CanFrame)) {
        if self.on_sdo_segmented(now, f, out) {
            return;
        }
        let resp = match SdoRequest::parse(f) {
            Ok((_, SdoRequest::Upload { index, sub })) => match self.od.sdo_read(index, sub) {
                Ok(data) => SdoResponse::Upload { index, sub, data },
                Err(code) => SdoResponse::Abort { index, sub, code },
            },
            Ok((_, SdoRequest::Download { index, sub, data })) => {
                let r = self
                    .od
                    .sdo_check_write(index, sub, &data)
                    .and_then(|_| self.check_write(index, sub, data.as_u32()));
                match r {
                    Ok(()) => {
                        self.apply(now, index, sub, data.as_u32(), out);
                        SdoResponse::DownloadAck { index, sub }
                    }
                    Err(code) => SdoResponse::Abort { index, sub, code },
                }
            }
            // The client gave up on a transfer: nothing to answer.
            Ok((_, SdoRequest::Abort { .. })) => return,
            Err(_) if f.len() == 8 => {
                let d = f.data();
                SdoResponse::Abort {
                    index: u16::from_le_bytes([d[1], d[2]]),
                    sub: d[3],
                    code: AbortCode::InvalidCommand,
                }
            }
            Err(_) => return,
        };
        if matches!(resp, SdoResponse::Abort { .. }) {
            self.stats.sdo_aborted += 1;
        } else {
            self.stats.sdo_served += 1;
        }
        out(resp.to_frame(self.node));
    }

    fn reset(&mut self, now: Duration, node_reset: bool) {
        if node_reset {
            self.od.reset(0x0000..=0xFFFF);
            // The application restarts: an incremental position counter starts at 0 again.
            if !self.axis.is_some_and(|a| a.absolute) {
                self.zero = None;
            }
            self.homing = HomingRun::Idle;
            self.home_cmd = 0.0;
            self.last_cw = 0;
            self.halt = false;
            self.state = State402::NotReadyToSwitchOn;
            self.fault_since = None;
        } else {
            self.leave_operational(now);
            self.od.reset(0x1000..=0x1FFF);
        }
        self.nmt = DeviceNmt::Initialising;
        self.boot_at = now + self.boot_time;
        self.tpdo = [TpdoRun::default(); PDOS];
        self.rpdo = [RpdoRun::default(); PDOS];
        self.next_hb = None;
        self.consumer_last = None;
        self.consumer_timed_out = false;
        self.update_statusword();
    }

    fn leave_operational(&mut self, now: Duration) {
        if self.nmt == DeviceNmt::Operational {
            self.connection_reaction(now, COMMUNICATION);
        }
    }

    fn on_nmt(&mut self, now: Duration, f: &CanFrame) {
        let Ok((cmd, node)) = nmt::parse_command(f) else {
            return;
        };
        if node != 0 && node != self.node {
            return;
        }
        self.stats.nmt_commands += 1;
        match cmd {
            NmtCommand::Start => {
                if matches!(self.nmt, DeviceNmt::PreOperational | DeviceNmt::Stopped) {
                    self.nmt = DeviceNmt::Operational;
                    self.tpdo = [TpdoRun::default(); PDOS];
                    self.rpdo = [RpdoRun::default(); PDOS];
                    self.info_emcy_due = self.info_emcy != 0;
                    self.status_hold_until = Some(now + self.first_status_delay);
                }
            }
            NmtCommand::Stop => {
                self.leave_operational(now);
                self.nmt = DeviceNmt::Stopped;
            }
            NmtCommand::EnterPreOperational => {
                self.leave_operational(now);
                self.nmt = DeviceNmt::PreOperational;
            }
            NmtCommand::ResetNode => self.reset(now, true),
            NmtCommand::ResetCommunication => self.reset(now, false),
        }
    }

    /// Updates the process values from the plant's reading at `now`.
    fn sample(&mut self, now: Duration, s: &SensorReading) {
        let dt = self
            .last_sample
            .map_or(0.0, |t| now.saturating_sub(t).as_secs_f64());
        self.last_sample = Some(now);
        match self.app {
            App::Drive {
                units,
                steer,
                offset,
            } => {
                let (rate, pos) = if steer {
                    let a = match self.last_wrapped {
                        Some(prev) => self.joint_angle + angle::diff(s.steer_angle, prev),
                        None => s.steer_angle,
                    };
                    self.last_wrapped = Some(s.steer_angle);
                    self.prev_joint = Some(self.joint_angle);
                    self.joint_angle = a;
                    let axis = self.axis.unwrap_or_default();
                    // An incremental counter reads 0 at power-on wherever the wheel points;
                    // an absolute one the angle from its zero (the switch edge).
                    let zero = *self
                        .zero
                        .get_or_insert(if axis.absolute { offset } else { a });
                    let inputs = u32::from(twin::switch_active(&axis, s.steer_angle)) << 2;
                    self.od.set(od::DIGITAL_INPUTS, 0, inputs);
                    (s.steer_rate, a - zero)
                } else {
                    self.joint_angle += s.wheel_speed * dt;
                    (s.wheel_speed, self.joint_angle)
                };
                self.last_rate = rate;
                // What the drive reports: the joint's motion as its motor and encoder see it
                // (mounting), inverted where its polarity says so.
                let (ps, vs) = (self.pos_sign(), self.vel_sign());
                let v = vs * rate;
                let vel =
                    units
                        .velocity_from_si(v)
                        .unwrap_or(if v > 0.0 { i32::MAX } else { i32::MIN });
                self.od.set(
                    od::POSITION_ACTUAL,
                    0,
                    units.rad_to_position(ps * pos) as u32,
                );
                self.od.set(od::VELOCITY_ACTUAL, 0, vel as u32);
                if steer && self.homing_active() && dt > 0.0 {
                    self.homing_step(dt);
                    // The counter's zero may just have been set: the position follows.
                    let p = self.joint_angle - self.zero.unwrap_or(self.joint_angle);
                    self.od
                        .set(od::POSITION_ACTUAL, 0, units.rad_to_position(ps * p) as u32);
                }
                if self.state == State402::QuickStopActive && dt > 0.0 {
                    self.quick_stop_step(now, dt);
                }
            }
            App::Encoder { units } => {
                self.od.set(
                    od::POSITION_VALUE,
                    0,
                    units.m_to_position(s.leg).unwrap_or(0),
                );
                self.od.set(
                    od::SPEED_VALUE,
                    1,
                    u32::from(units.speed_from_si(s.leg_rate) as u16),
                );
            }
        }
    }

    fn tpdo_values(&self, k: usize) -> ([u32; 8], [MapEntry; 8], usize) {
        let (entries, n) = self.mapping(Mappable::Tpdo, k);
        let mut v = [0u32; 8];
        for (o, e) in v.iter_mut().zip(&entries[..n]) {
            *o = self.od.value(e.index, e.sub);
        }
        (v, entries, n)
    }

    fn send_tpdo(&mut self, now: Duration, k: usize, out: &mut impl FnMut(CanFrame)) {
        let (values, entries, n) = self.tpdo_values(k);
        let mut data = [0u8; 8];
        let len = pdo::pack_into(&entries[..n], &values[..n], &mut data);
        let id = (self.od.value(Self::comm_index(Mappable::Tpdo, k), 1) & 0x7FF) as u16;
        if let Ok(f) = CanFrame::new(id, &data[..len]) {
            self.stats.tpdos_sent += 1;
            out(f);
        }
        let t = &mut self.tpdo[k];
        t.last_sent = Some(now);
        t.last_values = values;
    }

    /// Event-driven TPDOs: sent on a change (inhibit time permitting) and every event-timer
    /// period.
    fn event_tpdos(&mut self, now: Duration, out: &mut impl FnMut(CanFrame)) {
        if self.nmt != DeviceNmt::Operational {
            return;
        }
        for k in 0..PDOS {
            if !self.pdo_valid(Mappable::Tpdo, k) {
                continue;
            }
            if self.status_hold_until.is_some_and(|t| now < t) {
                continue;
            }
            let comm = Self::comm_index(Mappable::Tpdo, k);
            let ty = self.od.value(comm, 2) as u8;
            if ty < 254 {
                continue;
            }
            let inhibit = Duration::from_micros(100 * u64::from(self.od.value(comm, 3)));
            let timer = ms(self.od.value(comm, 5));
            let (values, _, _) = self.tpdo_values(k);
            let t = self.tpdo[k];
            let due = match t.last_sent {
                None => true,
                Some(last) => {
                    (values != t.last_values && now >= last + inhibit)
                        || (!timer.is_zero() && now >= last + timer)
                }
            };
            if due {
                self.send_tpdo(now, k, out);
            }
        }
    }

    fn on_sync(&mut self, now: Duration, s: &SensorReading, out: &mut impl FnMut(CanFrame)) {
        if self.nmt != DeviceNmt::Operational {
            return;
        }
        self.stats.syncs += 1;
        self.sample(now, s);
        // Synchronous RPDOs act now, then the synchronous TPDOs sample.
        for k in 0..PDOS {
            if let Some(values) = self.rpdo[k].pending.take() {
                self.apply_rpdo(now, k, &values, out);
            }
        }
        for k in 0..PDOS {
            if !self.pdo_valid(Mappable::Tpdo, k) {
                continue;
            }
            let ty = self.od.value(Self::comm_index(Mappable::Tpdo, k), 2) as u8;
            match ty {
                0 => {
                    let (values, _, _) = self.tpdo_values(k);
                    if self.tpdo[k].last_sent.is_none() || values != self.tpdo[k].last_values {
                        self.send_tpdo(now, k, out);
                    }
                }
                1..=240 => {
                    let t = &mut self.tpdo[k];
                    t.sync_count = t.sync_count.saturating_add(1);
                    if t.sync_count >= ty {
                        t.sync_count = 0;
                        self.send_tpdo(now, k, out);
                    }
                }
                _ => {}
            }
        }
        self.event_tpdos(now, out);
    }

    fn apply_rpdo(
        &mut self,
        now: Duration,
        k: usize,
        values: &[u32; 8],
        out: &mut impl FnMut(CanFrame),
    ) {
        let (entries, n) = self.mapping(Mappable::Rpdo, k);
        for (e, v) in entries[..n].iter().zip(values) {
            if self
                .od
                .get(e.index, e.sub)
                .is_some_and(|o| o.map == Mappable::Rpdo)
            {
                self.apply(now, e.index, e.sub, *v, out);
            }
        }
    }

    fn on_rpdo(&mut self, now: Duration, k: usize, f: &CanFrame, out: &mut impl FnMut(CanFrame)) {
        let (entries, n) = self.mapping(Mappable::Rpdo, k);
        let values = match pdo::unpack(&entries[..n], f) {
            Ok(v) => v,
            Err(_) => {
                self.stats.rpdo_length_errors += 1;
                self.emcy(codes::PDO_LENGTH, 0x11, out);
                return;
            }
        };
        self.stats.rpdos_received += 1;
        let r = &mut self.rpdo[k];
        r.last_rx = Some(now);
        r.timed_out = false;
        let ty = self.od.value(Self::comm_index(Mappable::Rpdo, k), 2) as u8;
        if ty <= 240 {
            r.pending = Some(values);
        } else {
            self.apply_rpdo(now, k, &values, out);
            self.event_tpdos(now, out);
        }
    }

    /// A frame on the bus at `now`; `s` is the wheel's current encoder reading.
    pub fn handle_frame(
        &mut self,
        now: Duration,
        f: &CanFrame,
        s: &SensorReading,
        out: &mut impl FnMut(CanFrame),
    ) {
        if self.nmt == DeviceNmt::Initialising {
            // Only a reset restarts an initialisation; nothing else is heard.
            if f.id() == cob::NMT {
                self.on_nmt(now, f);
            }
            self.finish_boot(now, out);
            return;
        }
        match cob::classify(f.id()) {
            Cob::Nmt => self.on_nmt(now, f),
            Cob::Sync if nmt::is_sync(f) => self.on_sync(now, s, out),
            Cob::SdoRx(n) if n == self.node => {
                if matches!(self.nmt, DeviceNmt::PreOperational | DeviceNmt::Operational) {
                    self.on_sdo(now, f, out);
                }
            }
            Cob::Heartbeat(n) => {
                let c = self.od.value(od::CONSUMER_HEARTBEAT, 1);
                if self.is_drive() && c & 0xFFFF != 0 && ((c >> 16) & 0x7F) as u8 == n {
                    self.consumer_last = Some(now);
                    self.consumer_timed_out = false;
                }
            }
            _ if self.nmt == DeviceNmt::Operational && self.is_drive() => {
                for k in 0..PDOS {
                    let cob_id = self.od.value(Self::comm_index(Mappable::Rpdo, k), 1);
                    if cob_id & od::PDO_COB_INVALID == 0 && (cob_id & 0x7FF) as u16 == f.id() {
                        self.on_rpdo(now, k, f, out);
                        break;
                    }
                }
            }
            _ => {}
        }
        self.finish_boot(now, out);
    }

    fn finish_boot(&mut self, now: Duration, out: &mut impl FnMut(CanFrame)) {
        if self.nmt != DeviceNmt::Initialising || now < self.boot_at {
            return;
        }
        self.nmt = DeviceNmt::PreOperational;
        self.stats.boot_ups += 1;
        out(nmt::heartbeat(self.node, NmtState::BootUp));
        if self.is_drive() && self.state == State402::NotReadyToSwitchOn {
            self.set_state(now, State402::SwitchOnDisabled);
        }
        let p = self.od.value(od::PRODUCER_HEARTBEAT, 0);
        self.next_hb = (p != 0).then(|| now + ms(p));
    }

    /// Time-driven work at `now`: boot completion, fault reaction, heartbeat production and
    /// consumption, RPDO deadlines, event-driven TPDOs; `s` is the wheel's encoder reading.
    pub fn tick(&mut self, now: Duration, s: &SensorReading, out: &mut impl FnMut(CanFrame)) {
        self.sample(now, s);
        self.finish_boot(now, out);
        if self.nmt == DeviceNmt::Initialising {
            return;
        }
        if let Some(since) = self.fault_since {
            if self.state == State402::FaultReactionActive && now > since {
                self.set_state(now, State402::Fault);
            }
        }
        if let Some((v, at)) = self.mode_pending {
            if now >= at {
                self.mode_pending = None;
                self.od.set(od::MODES_OF_OPERATION_DISPLAY, 0, v);
                self.update_statusword();
            }
        }
        if self.info_emcy_due && self.nmt == DeviceNmt::Operational {
            self.info_emcy_due = false;
            let code = self.info_emcy;
            // A notice, not an error: error register 0 (and no entry in 0x1003).
            self.stats.emcy_sent += 1;
            out(Emcy::new(code, 0).to_frame(self.node));
        }

        if let (Some(next), Some(state)) = (self.next_hb, self.nmt.heartbeat()) {
            if now >= next {
                let p = ms(self.od.value(od::PRODUCER_HEARTBEAT, 0));
                self.stats.heartbeats_sent += 1;
                out(nmt::heartbeat(self.node, state));
                self.next_hb = Some(if now >= next + p { now + p } else { next + p });
            }
        }
        if self.is_drive() {
            let c = self.od.value(od::CONSUMER_HEARTBEAT, 1);
            let timeout = ms(c & 0xFFFF);
            if let Some(last) = self.consumer_last {
                if !timeout.is_zero() && !self.consumer_timed_out && now > last + timeout {
                    self.consumer_timed_out = true;
                    self.stats.heartbeat_timeouts += 1;
                    self.comm_loss(now, codes::HEARTBEAT, out);
                }
            }
            if self.nmt == DeviceNmt::Operational {
                for k in 0..PDOS {
                    let timer = ms(self.od.value(Self::comm_index(Mappable::Rpdo, k), 5));
                    let r = self.rpdo[k];
                    if let (false, Some(last), false) = (timer.is_zero(), r.last_rx, r.timed_out) {
                        if self.pdo_valid(Mappable::Rpdo, k) && now > last + timer {
                            self.rpdo[k].timed_out = true;
                            self.stats.rpdo_timeouts += 1;
                            self.comm_loss(now, codes::RPDO_TIMEOUT, out);
                        }
                    }
                }
            }
        }
        self.event_tpdos(now, out);
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rollbase_driver::canopen::config::{for_node, SdoOp};
    use rollbase_driver::canopen::sdo::SdoData;

    const BOOT: Duration = Duration::from_millis(5);

    /// One device, a clock and what it sent.
    struct Rig {
        dev: Device,
        t: Duration,
        sensors: SensorReading,
        sent: Vec<CanFrame>,
    }

    fn at_ms(v: u64) -> Duration {
        Duration::from_millis(v)
    }

    impl Rig {
        /// Device `role` of wheel 0 of the default configuration, booted (boot-up taken).
        fn booted(role: Role) -> Rig {
            let cfg = Cia402Config::default();
            let mut r = Rig {
                dev: Device::new(&cfg, 0, role, BOOT, &TwinConfig::ideal()),
                t: Duration::ZERO,
                sensors: SensorReading {
                    leg: 0.465,
                    ..SensorReading::default()
                },
                sent: Vec::new(),
            };
            r.advance(BOOT);
            let node = r.dev.node();
            assert_eq!(r.take(), vec![nmt::heartbeat(node, NmtState::BootUp)]);
            r
        }

        fn node(&self) -> u8 {
            self.dev.node()
        }

        /// Ticks every millisecond up to `t + d`.
        fn advance(&mut self, d: Duration) {
            let end = self.t + d;
            while self.t < end {
                self.t = (self.t + at_ms(1)).min(end);
                let sent = &mut self.sent;
                self.dev.tick(self.t, &self.sensors, &mut |f| sent.push(f));
            }
        }

        fn frame(&mut self, f: CanFrame) {
            let sent = &mut self.sent;
            self.dev
                .handle_frame(self.t, &f, &self.sensors, &mut |f| sent.push(f));
        }

        fn take(&mut self) -> Vec<CanFrame> {
            std::mem::take(&mut self.sent)
        }

        fn take_id(&mut self, id: u16) -> Vec<CanFrame> {
            let (hit, rest): (Vec<CanFrame>, Vec<CanFrame>) =
                self.take().into_iter().partition(|f| f.id() == id);
            self.sent = rest;
            hit
        }

        fn sdo(&mut self, req: SdoRequest) -> Option<SdoResponse> {
            let node = self.node();
            self.frame(req.to_frame(node));
            let replies = self.take_id(cob::sdo_tx(node));
            assert!(replies.len() <= 1, "{replies:?}");
            replies
                .first()
                .map(|f| SdoResponse::parse(f).expect("SDO response").1)
        }

        fn write(&mut self, index: u16, sub: u8, data: SdoData) -> Result<(), AbortCode> {
            match self.sdo(SdoRequest::Download { index, sub, data }) {
                Some(SdoResponse::DownloadAck { .. }) => Ok(()),
                Some(SdoResponse::Abort { code, .. }) => Err(code),
                other => panic!("download {index:04X}:{sub}: {other:?}"),
            }
        }

        fn read(&mut self, index: u16, sub: u8) -> Result<u32, AbortCode> {
            match self.sdo(SdoRequest::Upload { index, sub }) {
                Some(SdoResponse::Upload { data, .. }) => Ok(data.as_u32()),
                Some(SdoResponse::Abort { code, .. }) => Err(code),
                other => panic!("upload {index:04X}:{sub}: {other:?}"),
            }
        }

        /// The master's boot plan for this device, every step accepted.
        fn configure(&mut self) {
            // Cyclic synchronous velocity for both drives (the homing has its own tests).
            let mut cfg = Cia402Config::default();
            cfg.homing.kind = rollbase_driver::canopen::config::HomingKind::None;
            fn missing<T>(r: Result<T, AbortCode>) -> bool {
                matches!(r, Err(AbortCode::NoObject | AbortCode::NoSubIndex))
            }
            for op in cfg.plan(self.dev.role(), 4000) {
                match for_node(op, self.node()) {
                    SdoOp::Write {
                        index,
                        sub,
                        data,
                        optional,
                    } => {
                        let r = self.write(index, sub, data);
                        if !(optional && missing(r)) {
                            assert_eq!(r, Ok(()), "{index:04X}:{sub}")
                        }
                    }
                    SdoOp::Verify {
                        index,
                        sub,
                        mask,
                        expected,
                        what,
                        optional,
                        ..
                    } => {
                        let r = self.read(index, sub);
                        if !(optional && missing(r)) {
                            assert_eq!(r.map(|v| v & mask), Ok(expected), "{what}")
                        }
                    }
                }
            }
        }

        fn nmt(&mut self, cmd: NmtCommand) {
            self.frame(nmt::command(cmd, self.node()));
        }

        fn sync(&mut self) {
            self.frame(nmt::sync());
        }

        fn rpdo1(&mut self, cw: u16, vel: i32) {
            let mut d = [0u8; 6];
            d[..2].copy_from_slice(&cw.to_le_bytes());
            d[2..].copy_from_slice(&vel.to_le_bytes());
            let id = cob::rpdo(1, self.node());
            self.frame(CanFrame::new(id, &d).expect("frame"));
        }

        fn emcys(&mut self) -> Vec<Emcy> {
            let id = cob::emcy(self.node());
            self.take_id(id)
                .iter()
                .map(|f| Emcy::parse(f).expect("EMCY").1)
                .collect()
        }

        /// Configured, operational and in operation enabled through RPDO1 (synchronous).
        fn enabled_drive(role: Role) -> Rig {
            let mut r = Rig::booted(role);
            r.configure();
            r.nmt(NmtCommand::Start);
            for cw in [0x06, 0x07, 0x0F] {
                r.rpdo1(cw, 0);
                r.sync();
            }
            assert_eq!(r.dev.state402(), State402::OperationEnabled);
            r.take();
            r
        }
    }

    #[test]
    fn boots_after_its_boot_time_and_resets_restore_their_areas() {
        let cfg = Cia402Config::default();
        let mut d = Device::new(&cfg, 0, Role::Drive, BOOT, &TwinConfig::ideal());
        let mut out = Vec::new();
        let s = SensorReading::default();
        // Initialising: deaf to SDO, silent.
        d.handle_frame(
            at_ms(1),
            &SdoRequest::Upload {
                index: 0x1000,
                sub: 0,
            }
            .to_frame(d.node()),
            &s,
            &mut |f| out.push(f),
        );
        d.tick(at_ms(4), &s, &mut |f| out.push(f));
        assert!(out.is_empty(), "{out:?}");
        assert_eq!(d.nmt(), DeviceNmt::Initialising);
        d.tick(at_ms(5), &s, &mut |f| out.push(f));
        assert_eq!(out, vec![nmt::heartbeat(d.node(), NmtState::BootUp)]);
        assert_eq!(d.nmt(), DeviceNmt::PreOperational);
        assert_eq!(d.state402(), State402::SwitchOnDisabled);

        let mut r = Rig::booted(Role::Drive);
        r.write(od::PRODUCER_HEARTBEAT, 0, SdoData::u16(20))
            .unwrap();
        r.write(od::MODES_OF_OPERATION, 0, SdoData::i8(9)).unwrap();
        // Reset communication: 0x1000–0x1FFF back to defaults, the application area kept.
        r.nmt(NmtCommand::ResetCommunication);
        assert_eq!(r.dev.nmt(), DeviceNmt::Initialising);
        r.advance(BOOT);
        assert_eq!(
            r.take(),
            vec![nmt::heartbeat(r.node(), NmtState::BootUp)],
            "one boot-up and no heartbeat (0x1017 back to 0)"
        );
        assert_eq!(r.read(od::PRODUCER_HEARTBEAT, 0), Ok(0));
        assert_eq!(r.read(od::MODES_OF_OPERATION, 0), Ok(9));
        // Reset node: everything back.
        r.nmt(NmtCommand::ResetNode);
        r.advance(BOOT);
        r.take();
        assert_eq!(r.read(od::MODES_OF_OPERATION, 0), Ok(0));
    }

    #[test]
    fn sdo_server_aborts_with_the_cia301_codes() {
        let mut r = Rig::booted(Role::Drive);
        assert_eq!(r.read(0x1234, 0), Err(AbortCode::NoObject));
        assert_eq!(
            r.read(od::MODES_OF_OPERATION, 5),
            Err(AbortCode::NoSubIndex)
        );
        assert_eq!(
            r.write(od::STATUSWORD, 0, SdoData::u16(6)),
            Err(AbortCode::ReadOnly)
        );
        assert_eq!(
            r.write(od::PRODUCER_HEARTBEAT, 0, SdoData::u32(100)),
            Err(AbortCode::LengthMismatch)
        );
        assert_eq!(
            r.write(od::MODES_OF_OPERATION, 0, SdoData::i8(3)),
            Err(AbortCode::InvalidValue),
            "only cyclic synchronous velocity is emulated"
        );
        assert_eq!(
            r.write(od::ABORT_CONNECTION_OPTION, 0, SdoData::i16(4)),
            Err(AbortCode::InvalidValue)
        );
        // A segmented download initiate (no e bit) of a read-only object: refused at once.
        let mut seg = [0u8; 8];
        seg[0] = 0x21;
        seg[1..3].copy_from_slice(&od::STATUSWORD.to_le_bytes());
        seg[4] = 2;
        let node = r.node();
        r.frame(CanFrame::new(cob::sdo_rx(node), &seg).unwrap());
        let reply = r.take_id(cob::sdo_tx(node));
        assert_eq!(
            SdoResponse::parse(&reply[0]).unwrap().1,
            SdoResponse::Abort {
                index: od::STATUSWORD,
                sub: 0,
                code: AbortCode::ReadOnly
            }
        );
        // Other nodes' requests are not answered; the value written last is read back.
        r.frame(
            SdoRequest::Upload {
                index: 0x1000,
                sub: 0,
            }
            .to_frame(node + 1),
        );
        assert!(r.take().is_empty());
        r.write(od::PRODUCER_HEARTBEAT, 0, SdoData::u16(250))
            .unwrap();
        assert_eq!(r.read(od::PRODUCER_HEARTBEAT, 0), Ok(250));
        assert_eq!(r.dev.stats().sdo_aborted, 7);
        // An encoder has no drive objects.
        let mut e = Rig::booted(Role::Leg);
        assert_eq!(e.read(od::CONTROLWORD, 0), Err(AbortCode::NoObject));
        assert_eq!(e.read(od::MEASURING_STEP, 1), Ok(1000));
    }

    #[test]
    fn pdo_mapping_follows_the_cia301_order_and_checks_entries() {
        let mut r = Rig::booted(Role::Drive);
        let comm = od::TPDO_COMM + 1;
        let map = od::TPDO_MAP + 1;
        let entry = |ix: u16, sub: u8, bits: u8| SdoData::u32(MapEntry::new(ix, sub, bits).raw());
        // TPDO1 is valid after boot: its mapping is locked.
        assert_eq!(
            r.write(od::TPDO_MAP, 0, SdoData::u8(0)),
            Err(AbortCode::DeviceState)
        );
        // TPDO2 is invalid: entries need sub 0 = 0 first.
        r.write(map, 0, SdoData::u8(0)).unwrap();
        r.write(map, 1, entry(od::VELOCITY_ACTUAL, 0, 32)).unwrap();
        r.write(map, 2, entry(od::POSITION_ACTUAL, 0, 32)).unwrap();
        r.write(map, 3, entry(od::STATUSWORD, 0, 16)).unwrap();
        assert_eq!(r.write(map, 0, SdoData::u8(3)), Err(AbortCode::PdoLength));
        assert_eq!(
            r.write(map, 0, SdoData::u8(9)),
            Err(AbortCode::ValueTooHigh)
        );
        r.write(map, 3, entry(od::TARGET_VELOCITY, 0, 32)).unwrap();
        r.write(map, 2, entry(od::STATUSWORD, 0, 16)).unwrap();
        assert_eq!(
            r.write(map, 0, SdoData::u8(3)),
            Err(AbortCode::NotMappable),
            "target velocity is an RPDO object"
        );
        r.write(map, 2, entry(od::STATUSWORD, 0, 32)).unwrap();
        assert_eq!(
            r.write(map, 0, SdoData::u8(2)),
            Err(AbortCode::NotMappable),
            "the entry's length must be the object's"
        );
        r.write(map, 2, entry(od::STATUSWORD, 0, 16)).unwrap();
        r.write(map, 0, SdoData::u8(2)).unwrap();
        assert_eq!(
            r.write(map, 1, entry(od::STATUSWORD, 0, 16)),
            Err(AbortCode::DeviceState),
            "entries are locked while sub 0 is not 0"
        );
        let cob_id = cob::tpdo(2, r.node());
        r.write(comm, 2, SdoData::u8(1)).unwrap();
        assert_eq!(
            r.write(comm, 2, SdoData::u8(245)),
            Err(AbortCode::InvalidValue)
        );
        r.write(
            comm,
            1,
            SdoData::u32(od::PDO_COB_NO_RTR | u32::from(cob_id)),
        )
        .unwrap();
        assert_eq!(
            r.write(comm, 1, SdoData::u32(u32::from(cob_id) + 1)),
            Err(AbortCode::InvalidValue),
            "the COB-ID of a valid PDO cannot change"
        );
        // Operational: the SYNC samples exactly that layout.
        r.sensors.wheel_speed = 2.0;
        r.nmt(NmtCommand::Start);
        r.advance(at_ms(2));
        r.take();
        r.sync();
        let tpdo = r.take_id(cob_id);
        assert_eq!(tpdo.len(), 1);
        let d = tpdo[0].data();
        assert_eq!(d.len(), 6);
        let units = Cia402Config::default().drive;
        assert_eq!(
            i32::from_le_bytes([d[0], d[1], d[2], d[3]]),
            units.velocity_from_si(2.0).unwrap()
        );
        assert_eq!(u16::from_le_bytes([d[4], d[5]]), r.dev.statusword());
    }

    #[test]
    fn synchronous_tpdos_go_out_every_nth_sync_only_when_operational() {
        let mut r = Rig::booted(Role::Leg);
        r.configure();
        let id = cob::tpdo(1, r.node());
        r.write(
            od::TPDO_COMM,
            1,
            SdoData::u32(od::PDO_COB_INVALID | u32::from(id)),
        )
        .unwrap();
        r.write(od::TPDO_COMM, 2, SdoData::u8(3)).unwrap();
        r.write(od::TPDO_COMM, 1, SdoData::u32(u32::from(id)))
            .unwrap();
        r.sync();
        assert!(r.take_id(id).is_empty(), "no PDO in pre-operational");
        r.nmt(NmtCommand::Start);
        let mut per_sync = Vec::new();
        for _ in 0..9 {
            r.sync();
            per_sync.push(r.take_id(id).len());
        }
        assert_eq!(per_sync, [0, 0, 1, 0, 0, 1, 0, 0, 1]);
        // The encoder's layout: position value in 1 µm steps, speed in its step.
        r.sensors.leg = 0.4321;
        r.sensors.leg_rate = 0.01;
        r.sync();
        r.sync();
        r.sync();
        let f = r.take_id(id);
        let d = f[0].data();
        assert_eq!(u32::from_le_bytes([d[0], d[1], d[2], d[3]]), 432_100);
        let units = Cia402Config::default().leg_encoder;
        assert_eq!(i16::from_le_bytes([d[4], d[5]]), units.speed_from_si(0.01));
        r.nmt(NmtCommand::Stop);
        for _ in 0..3 {
            r.sync();
        }
        assert!(r.take_id(id).is_empty(), "no PDO when stopped");
    }

    #[test]
    fn event_driven_statusword_respects_inhibit_and_event_timer() {
        let mut r = Rig::booted(Role::Steer);
        r.configure();
        let cfg = Cia402Config::default();
        let status = cob::tpdo(2, r.node());
        r.nmt(NmtCommand::Start);
        r.advance(at_ms(1));
        assert_eq!(r.take_id(status).len(), 1, "first transmission on start");
        r.advance(at_ms(3));
        assert!(r.take_id(status).is_empty(), "no change, no transmission");
        // Two changes 0.5 ms apart: the second waits for the inhibit time (1 ms).
        r.rpdo1(0x06, 0);
        r.sync();
        assert_eq!(r.take_id(status).len(), 1);
        r.t += Duration::from_micros(500);
        r.rpdo1(0x07, 0);
        r.sync();
        assert!(r.take_id(status).is_empty(), "inhibited");
        r.advance(at_ms(1));
        let f = r.take_id(status);
        assert_eq!(f.len(), 1);
        assert_eq!(
            u16::from_le_bytes([f[0].data()[0], f[0].data()[1]]) & 0x6F,
            0x23,
            "switched on"
        );
        // Unchanged: again after the event timer, not sooner.
        let timer = u64::from(cfg.status_event_timer_ms);
        r.advance(at_ms(timer - 2));
        assert!(r.take_id(status).is_empty());
        r.advance(at_ms(2));
        assert_eq!(r.take_id(status).len(), 1);
        assert_eq!(
            cfg.status_inhibit_100us, 10,
            "the test assumes 1 ms inhibit"
        );
    }

    #[test]
    fn synchronous_rpdo_acts_at_the_next_sync_asynchronous_at_once() {
        let mut r = Rig::enabled_drive(Role::Drive);
        let units = Cia402Config::default().drive;
        let v = units.velocity_from_si(3.0).unwrap();
        r.rpdo1(0x0F, v);
        assert_eq!(r.dev.motor(), Some(0.0), "type 1: held until the SYNC");
        r.sync();
        assert!((r.dev.motor().unwrap() - 3.0).abs() < 1e-3);
        // Asynchronous (255): applied on reception.
        let comm = od::RPDO_COMM;
        let id = u32::from(cob::rpdo(1, r.node()));
        r.write(comm, 1, SdoData::u32(od::PDO_COB_INVALID | id))
            .unwrap();
        r.write(comm, 2, SdoData::u8(255)).unwrap();
        r.write(comm, 1, SdoData::u32(id)).unwrap();
        r.rpdo1(0x0F, -v);
        assert!((r.dev.motor().unwrap() + 3.0).abs() < 1e-3);
        // A wrong length is dropped with EMCY 0x8210.
        let node = r.node();
        r.frame(CanFrame::new(cob::rpdo(1, node), &[0x0F, 0, 0, 0]).unwrap());
        assert!((r.dev.motor().unwrap() + 3.0).abs() < 1e-3);
        assert_eq!(r.emcys(), vec![Emcy::new(codes::PDO_LENGTH, 0x11)]);
        assert_eq!(r.dev.stats().rpdo_length_errors, 1);
    }

    #[test]
    fn motor_follows_only_in_operation_enabled_csv_without_halt() {
        let mut r = Rig::booted(Role::Drive);
        r.configure();
        r.nmt(NmtCommand::Start);
        let v = Cia402Config::default().drive.velocity_from_si(1.0).unwrap();
        let mut seen = Vec::new();
        for cw in [0x06, 0x07, 0x0F, 0x010F, 0x0F, 0x07] {
            r.rpdo1(cw, v);
            r.sync();
            seen.push((r.dev.state402(), r.dev.motor().is_some()));
        }
        use State402::*;
        assert_eq!(
            seen,
            [
                (ReadyToSwitchOn, false),
                (SwitchedOn, false),
                (OperationEnabled, true),
                (OperationEnabled, false), // halt
                (OperationEnabled, true),
                (SwitchedOn, false),
            ]
        );
        // Modes of operation 0 (none): enabled but not following.
        r.rpdo1(0x0F, v);
        r.sync();
        r.write(od::MODES_OF_OPERATION, 0, SdoData::i8(0)).unwrap();
        assert_eq!(r.dev.state402(), OperationEnabled);
        assert_eq!(r.dev.motor(), None);
        assert_eq!(r.dev.statusword() & ds402::SW_FOLLOWS_COMMAND, 0);
    }

    #[test]
    fn heartbeat_producer_sends_the_nmt_state_at_its_period() {
        let mut r = Rig::booted(Role::Leg);
        let hb = cob::heartbeat(r.node());
        r.write(od::PRODUCER_HEARTBEAT, 0, SdoData::u16(20))
            .unwrap();
        r.advance(at_ms(100));
        let got = r.take_id(hb);
        assert_eq!(got.len(), 5);
        assert!(got.iter().all(|f| f.data() == [0x7F]), "pre-operational");
        r.nmt(NmtCommand::Start);
        r.advance(at_ms(40));
        let got = r.take_id(hb);
        assert_eq!(got.len(), 2);
        assert!(got.iter().all(|f| f.data() == [0x05]), "operational");
        r.nmt(NmtCommand::Stop);
        r.advance(at_ms(20));
        assert_eq!(r.take_id(hb)[0].data(), [0x04]);
    }

    #[test]
    fn master_heartbeat_loss_is_reported_once_and_faults_an_enabled_drive() {
        let mut r = Rig::enabled_drive(Role::Drive);
        let cfg = Cia402Config::default();
        let master_hb = nmt::heartbeat(cfg.master_node, NmtState::Operational);
        // Keep the RPDO deadline out of the way: asynchronous RPDOs, no deadline.
        let id = u32::from(cob::rpdo(1, r.node()));
        r.write(od::RPDO_COMM, 1, SdoData::u32(od::PDO_COB_INVALID | id))
            .unwrap();
        r.write(od::RPDO_COMM, 5, SdoData::u16(0)).unwrap();
        r.write(od::RPDO_COMM, 1, SdoData::u32(id)).unwrap();
        for _ in 0..5 {
            r.frame(master_hb);
            r.advance(at_ms(20));
        }
        assert!(r.emcys().is_empty());
        let timeout = u64::from(cfg.device_heartbeat_timeout_ms);
        r.advance(at_ms(timeout - 20));
        assert!(r.emcys().is_empty(), "not before the consumer time");
        r.advance(at_ms(1));
        assert_eq!(r.emcys(), vec![Emcy::new(codes::HEARTBEAT, 0x11)]);
        assert_eq!(r.dev.state402(), State402::FaultReactionActive);
        r.advance(at_ms(1));
        assert_eq!(r.dev.state402(), State402::Fault);
        assert_eq!(r.dev.motor(), None);
        assert_eq!(r.read(ERROR_CODE, 0), Ok(u32::from(codes::HEARTBEAT)));
        r.advance(at_ms(500));
        assert!(r.emcys().is_empty(), "reported once");
        assert_eq!(r.dev.stats().heartbeat_timeouts, 1);
    }

    #[test]
    fn rpdo_deadline_applies_the_abort_connection_option() {
        for (option, expected) in [
            (1i16, State402::Fault),
            (2, State402::SwitchOnDisabled),
            (3, State402::QuickStopActive),
            (0, State402::OperationEnabled),
        ] {
            let mut r = Rig::enabled_drive(Role::Steer);
            r.write(od::ABORT_CONNECTION_OPTION, 0, SdoData::i16(option))
                .unwrap();
            // Quick stop option 6: ramp down, then stay in quick stop active (with 2, the
            // factory's, a drive at rest goes on to switch on disabled at once).
            r.write(od::QUICK_STOP_OPTION, 0, SdoData::i16(6)).unwrap();
            let deadline = u64::from(Cia402Config::default().rpdo_timeout_ms);
            r.rpdo1(0x0F, 0);
            r.advance(at_ms(deadline));
            assert!(r.emcys().is_empty(), "option {option}: not yet");
            r.advance(at_ms(2));
            assert_eq!(
                r.emcys(),
                vec![Emcy::new(codes::RPDO_TIMEOUT, 0x11)],
                "option {option}"
            );
            assert_eq!(r.dev.state402(), expected, "option {option}");
            // The RPDO coming back re-arms the deadline.
            r.rpdo1(0x0F, 0);
            r.advance(at_ms(deadline + 2));
            assert_eq!(r.emcys().len(), 1, "option {option}: re-armed");
        }
    }

    #[test]
    fn injected_fault_and_fault_reset_send_their_emcys() {
        let mut r = Rig::enabled_drive(Role::Drive);
        let t = r.t;
        let sent = &mut r.sent;
        r.dev
            .inject_fault(t, codes::OVERCURRENT, &mut |f| sent.push(f));
        assert_eq!(r.emcys(), vec![Emcy::new(codes::OVERCURRENT, 0x03)]);
        assert_eq!(r.read(od::ERROR_REGISTER, 0), Ok(0x03));
        r.advance(at_ms(1));
        assert_eq!(r.dev.state402(), State402::Fault);
        assert_eq!(r.dev.statusword() & 0x4F, 0x08);
        // Fault reset is the rising edge of bit 7.
        r.rpdo1(0x80, 0);
        r.sync();
        assert_eq!(r.dev.state402(), State402::SwitchOnDisabled);
        assert_eq!(r.emcys(), vec![Emcy::new(codes::NO_ERROR, 0)]);
        assert_eq!(r.read(od::ERROR_REGISTER, 0), Ok(0));
        r.rpdo1(0x80, 0);
        r.sync();
        assert!(r.emcys().is_empty(), "held bit 7 is not another reset");
        // An encoder ignores fault injection.
        let mut e = Rig::booted(Role::Leg);
        let t = e.t;
        let sent = &mut e.sent;
        e.dev
            .inject_fault(t, codes::OVERCURRENT, &mut |f| sent.push(f));
        assert!(e.take().is_empty());
    }

    #[test]
    fn reset_communication_keeps_the_drive_state_reset_node_restarts_it() {
        let mut r = Rig::enabled_drive(Role::Drive);
        r.write(od::ABORT_CONNECTION_OPTION, 0, SdoData::i16(2))
            .unwrap();
        // Operation enabled and operational: the reset is a departure from operational.
        r.nmt(NmtCommand::ResetCommunication);
        r.advance(BOOT);
        assert_eq!(r.dev.nmt(), DeviceNmt::PreOperational);
        assert_eq!(r.dev.state402(), State402::SwitchOnDisabled, "0x6007 = 2");
        // A drive in fault stays in fault across a reset communication …
        let t = r.t;
        let sent = &mut r.sent;
        r.dev
            .inject_fault(t, codes::OVERCURRENT, &mut |f| sent.push(f));
        r.advance(at_ms(1));
        r.nmt(NmtCommand::ResetCommunication);
        r.advance(BOOT);
        assert_eq!(r.dev.state402(), State402::Fault);
        assert_eq!(r.read(ERROR_CODE, 0), Ok(u32::from(codes::OVERCURRENT)));
        // … and a reset node restarts it.
        r.nmt(NmtCommand::ResetNode);
        r.advance(BOOT);
        assert_eq!(r.dev.state402(), State402::SwitchOnDisabled);
        assert_eq!(r.read(ERROR_CODE, 0), Ok(0));
    }

    #[test]
    fn leaving_operational_while_enabled_applies_the_reaction() {
        let mut r = Rig::enabled_drive(Role::Drive);
        r.nmt(NmtCommand::EnterPreOperational);
        r.advance(at_ms(1));
        assert_eq!(r.dev.state402(), State402::Fault);
        assert_eq!(r.read(ERROR_CODE, 0), Ok(u32::from(COMMUNICATION)));
        // Broadcast NMT (node 0) reaches every device; other nodes' commands do not.
        let mut e = Rig::booted(Role::Leg);
        e.frame(nmt::command(NmtCommand::Start, e.node() + 1));
        assert_eq!(e.dev.nmt(), DeviceNmt::PreOperational);
        e.frame(nmt::command(NmtCommand::Start, 0));
        assert_eq!(e.dev.nmt(), DeviceNmt::Operational);
    }

    proptest::proptest! {
        /// Bytes from the bus never panic a simulated device, drive or encoder: ids are
        /// drawn mostly from the ones it listens to (NMT, SYNC, its RPDOs and SDO server,
        /// the master's heartbeat), with any length and payload, between timer ticks.
        #[test]
        fn arbitrary_frames_never_panic_a_device(
            frames in proptest::collection::vec(
                (
                    proptest::prop_oneof![
                        proptest::sample::select(vec![
                            0x000u16, 0x080, 0x201, 0x301, 0x401, 0x501, 0x601, 0x77F,
                        ]),
                        0u16..0x800,
                    ],
                    proptest::collection::vec(proptest::num::u8::ANY, 0..=8),
                ),
                1..300,
            ),
            drive in proptest::bool::ANY,
        ) {
            let mut r = Rig::booted(if drive { Role::Drive } else { Role::Leg });
            // Operational first, so PDOs are processed too.
            let start = nmt::command(NmtCommand::Start, r.node());
            let (t, sensors) = (r.t, r.sensors);
            r.dev.handle_frame(t, &start, &sensors, &mut |_| {});
            for (id, data) in &frames {
                let f = CanFrame::new(*id, data).expect("id < 0x800, len <= 8");
                let (t, sensors) = (r.t, r.sensors);
                let sent = &mut r.sent;
                r.dev.handle_frame(t, &f, &sensors, &mut |f| sent.push(f));
                r.advance(at_ms(1));
                r.sent.clear();
            }
        }
    }
}
