//! The CiA 402 profile's section of the platform file (`protocol = "cia402"`, `[cia402]`),
//! its validation, and the SDO configuration plan the master runs on every device at boot.
//!
//! # Devices
//!
//! Every wheel is three CANopen devices: the rolling drive and the steering drive (CiA 402,
//! cyclic synchronous velocity) and the leg's absolute linear encoder (CiA 406). The default
//! node assignment for n wheels puts wheel i's drives at 1 + 2i and 2 + 2i and its encoder
//! at 2n + 1 + i (four wheels: drives 1..=8, encoders 9..=12); the master produces its
//! heartbeat as node 127.
//!
//! # The boot plan (per device, in order)
//!
//! Drives: check the device type (0x1000, low word 402); communication cycle period 0x1006;
//! heartbeat producer 0x1017; heartbeat consumer 0x1016:01 for the master's node; RPDO1,
//! TPDO1 and TPDO2 (see [`super::pdo`]); abort connection option 0x6007; interpolation time
//! period 0x60C2 = the cycle period; mode of operation 0x6060 = 9 (cyclic synchronous
//! velocity), then read back 0x6061 to confirm the drive took it.
//!
//! Encoders: check the device type (low word 406) and the position measuring step
//! (0x6005:01) against the platform file; 0x1006; 0x1017; TPDO1.
//!
//! A read that does not match, an SDO abort or a device that does not answer stops the boot
//! with a [`super::master::BootError`] that names the node, the object and the value.

use super::od;
use super::pdo::{self, PdoComm};
use super::sdo::SdoData;
use super::units::{DriveUnits, EncoderUnits, VelocityUnit};
use serde::{Deserialize, Serialize};

/// A configuration field with an unacceptable value.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("`{field}` = {value}: {reason}")]
pub struct Invalid {
    /// Dotted path of the field (`cia402.wheels[1].steer_node`).
    pub field: String,
    /// The value, printed.
    pub value: String,
    /// What is wrong and what is expected.
    pub reason: String,
}

impl Invalid {
    /// Builds the error.
    pub fn new(
        field: impl Into<String>,
        value: impl std::fmt::Display,
        reason: impl Into<String>,
    ) -> Self {
        Self {
            field: field.into(),
            value: value.to_string(),
            reason: reason.into(),
        }
    }
}

/// What a device does on the platform.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Role {
    /// Rolling (wheel spin) drive, CiA 402.
    Drive,
    /// Steering drive, CiA 402.
    Steer,
    /// Leg extension encoder, CiA 406.
    Leg,
}

impl Role {
    /// Lower-case name.
    pub fn name(self) -> &'static str {
        match self {
            Role::Drive => "rolling drive",
            Role::Steer => "steering drive",
            Role::Leg => "leg encoder",
        }
    }
}

impl std::fmt::Display for Role {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name())
    }
}

/// The CANopen nodes of one wheel module, in platform wheel order.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Cia402Wheel {
    /// Node-ID (1..=127) of the rolling (wheel spin) drive.
    pub drive_node: u8,
    /// Node-ID of the steering drive.
    pub steer_node: u8,
    /// Node-ID of the leg's CiA 406 linear encoder; 0 for a wheel without a leg (no
    /// encoder: the wheel has a fixed footprint).
    pub leg_node: u8,
    /// Steering angle φ (rad) at steering position 0, i.e. at the home position the homing
    /// finds (the homing offset; with `homing.kind = "absolute"`, the angle at the encoder's
    /// zero).
    #[serde(default)]
    pub steer_offset_rad: f64,
    /// Steering angle φ (rad) the wheel is turned to after homing, before the first motion
    /// command is accepted (within the platform's steering rate and acceleration limits).
    #[serde(default)]
    pub rest_angle_rad: f64,
    /// This steering drive's homing, when it differs from `[cia402.homing]`.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub homing: Option<Homing>,
}

impl Cia402Wheel {
    /// The node of a role.
    pub fn node(&self, role: Role) -> u8 {
        match role {
            Role::Drive => self.drive_node,
            Role::Steer => self.steer_node,
            Role::Leg => self.leg_node,
        }
    }
}

/// Everything the master needs to configure and run the CiA 402 profile.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct Cia402Config {
    /// Node-ID the master's heartbeat is produced under (1..=127, unused by any device).
    pub master_node: u8,
    /// The nodes of each wheel, in platform wheel order (as many as the platform has wheels).
    pub wheels: Vec<Cia402Wheel>,
    /// Rolling drives.
    pub drive: DriveUnits,
    /// Steering drives.
    pub steer: DriveUnits,
    /// Leg encoders.
    pub leg_encoder: EncoderUnits,
    /// Devices' heartbeat producer time, 0x1017 (ms).
    pub heartbeat_ms: u16,
    /// The master's heartbeat producer time (ms; sent at the first cycle at or after it is
    /// due).
    pub master_heartbeat_ms: u16,
    /// Drives' consumer time for the master's heartbeat, 0x1016:01 (ms).
    pub device_heartbeat_timeout_ms: u16,
    /// The master's consumer time for each device's heartbeat (ms).
    pub master_heartbeat_timeout_ms: u16,
    /// RPDO deadline monitoring in the drives, 0x1400:05 event timer (ms); 0 = off.
    pub rpdo_timeout_ms: u16,
    /// Abort connection option code, 0x6007 (0 no action, 1 fault, 2 disable voltage,
    /// 3 quick stop), applied by a drive in operation enabled on a heartbeat or RPDO timeout.
    pub comm_loss_reaction: i16,
    /// Transmission type of the drives' RPDO1 (1..=240 synchronous: applied at the next
    /// SYNC; 254/255: applied on reception).
    pub rpdo_transmission: u8,
    /// Inhibit time of the event-driven statusword TPDO, 0x1801:03 (100 µs units).
    pub status_inhibit_100us: u16,
    /// Event timer of the statusword TPDO, 0x1801:05 (ms): it is also sent this often
    /// without a change.
    pub status_event_timer_ms: u16,
    /// Time the master waits for one SDO response (ms).
    pub sdo_timeout_ms: u16,
    /// SDO retries after a timeout before configuration fails.
    pub sdo_retries: u8,
    /// Time from the master's NMT reset to every device's boot-up message (ms).
    pub boot_timeout_ms: u16,
    /// Time from the master's first "enable" to a drive reporting operation enabled (ms).
    pub enable_timeout_ms: u16,
    /// Time a drive's modes of operation display (0x6061) may take to follow a write of
    /// 0x6060 (ms): it is read again every cycle until it shows the mode, then the boot goes
    /// on; still another mode after this time fails the boot naming the drive.
    pub mode_switch_timeout_ms: u16,
    /// How every steering drive is homed before the platform is armed (per wheel:
    /// `wheels[i].homing`).
    pub homing: Homing,
    /// Mechanical coupling of steering into rolling: wheel turns per steering turn with the
    /// rolling motor at rest (0: none). While a wheel is homed or turned to its rest angle the
    /// rolling drive is told −coupling × the steering rate, so the wheel does not roll.
    pub coupling: f64,
    /// Error codes of EMCY messages that are informational (logged and counted, not a fault)
    /// besides those CiA 301 says are: an error register of 0 (no error active), 0x8120 CAN
    /// error passive and 0x8140 recovered from bus-off.
    pub informational_emcy: Vec<u16>,
    /// Extra objects mapped into the drives' statusword TPDO2 after the statusword, as
    /// CiA 301 mapping entries (`index << 16 | sub << 8 | bits`, e.g. 0x603F0010 error code,
    /// 0x60FD0020 digital inputs, 0x60770010 torque actual); at most 6 bytes in all. 0x60FD is
    /// added when a steering drive is homed on a digital input.
    pub status_extra: Vec<u32>,
    /// The drives' quick stop (0x605A option code, 0x6085 decelerations): what a drive does
    /// when the master sends the Quick Stop command because it cannot ramp the drives down
    /// itself (feedback lost, bus stalled, a fatal error with the drives enabled).
    pub quick_stop: QuickStop,
    /// Extra SDO writes, in order, near the end of each device's boot plan (after a DCF's
    /// values, before the unit checks and the mode of operation): current limits, fault
    /// reactions, polarity, brakes, vendor objects.
    pub sdo: Vec<ExtraSdo>,
    /// Device description files (EDS or DCF) per role or device: the boot plan is checked
    /// against them (objects present, access, value ranges, PDO capacity) before anything
    /// starts, and a DCF's values are written at boot ([`super::eds`]).
    pub eds: EdsFiles,
    /// The DCF values written at boot (after the plan's own configuration, before `sdo`),
    /// filled in from the DCFs of `eds` when the platform file is loaded
    /// ([`super::eds::apply`]); not part of the file.
    #[serde(skip)]
    pub dcf: Vec<super::eds::DcfWrite>,
}

/// The drives' quick stop (`[cia402.quick_stop]`).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct QuickStop {
    /// Quick stop option code 0x605A (CiA 402): 0 disable the drive function (the motor
    /// coasts); 1 slow down on the slow-down ramp, 2 on the quick-stop ramp (0x6085), 3 at
    /// the current limit, 4 at the voltage limit, then switch on disabled; 5–8 the same, then
    /// stay in quick stop active (holding, powered).
    pub option: i16,
    /// Quick-stop deceleration of the rolling drives (rad/s² at the wheel; 0x6085).
    pub drive_decel_rad_s2: f64,
    /// Quick-stop deceleration of the steering drives (rad/s² at the steering axis; 0x6085).
    pub steer_decel_rad_s2: f64,
}

impl Default for QuickStop {
    fn default() -> Self {
        Self {
            option: 2,
            drive_decel_rad_s2: 40.0,
            steer_decel_rad_s2: 40.0,
        }
    }
}

/// One extra SDO write of the platform file (`[[cia402.sdo]]`).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ExtraSdo {
    /// Which devices: `drive`, `steer` or `leg` (all of that role); absent with `node`.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub role: Option<Role>,
    /// One device by node-ID (instead of `role`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub node: Option<u8>,
    /// Object index.
    pub index: u16,
    /// Sub-index.
    #[serde(default)]
    pub sub: u8,
    /// Value (little-endian, `size` bytes; a negative value is written in two's complement).
    pub value: i64,
    /// Size in bytes: 1, 2 or 4.
    pub size: u8,
    /// Skipped (and reported) when the device answers "object does not exist".
    #[serde(default)]
    pub optional: bool,
}

impl ExtraSdo {
    /// True when the write is for `node` with role `role`.
    pub fn applies(&self, role: Role, node: u8) -> bool {
        self.node.is_none_or(|n| n == node) && self.role.is_none_or(|r| r == role)
    }
}

/// EDS/DCF files per role, or per device (paths relative to the platform file's directory).
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct EdsFiles {
    /// One device's file (`[[cia402.eds.devices]] node = 4 file = "steer4.dcf"`), before its
    /// role's.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub devices: Vec<EdsDevice>,
    /// Rolling drives.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub drive: Option<String>,
    /// Steering drives.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub steer: Option<String>,
    /// Leg encoders.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub leg: Option<String>,
}

/// The description file of one device.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct EdsDevice {
    /// Node-ID.
    pub node: u8,
    /// EDS or DCF path.
    pub file: String,
}

impl EdsFiles {
    /// The file of a role.
    pub fn of(&self, role: Role) -> Option<&str> {
        match role {
            Role::Drive => self.drive.as_deref(),
            Role::Steer => self.steer.as_deref(),
            Role::Leg => self.leg.as_deref(),
        }
    }

    /// The file of the device with `role` at `node`: its own, else its role's.
    pub fn for_device(&self, role: Role, node: u8) -> Option<&str> {
        self.devices
            .iter()
            .find(|d| d.node == node)
            .map(|d| d.file.as_str())
            .or_else(|| self.of(role))
    }

    /// True when no file is named.
    pub fn is_empty(&self) -> bool {
        self.devices.is_empty()
            && self.drive.is_none()
            && self.steer.is_none()
            && self.leg.is_none()
    }
}

/// How a steering drive finds its zero.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum HomingKind {
    /// CiA 402 homing mode (6) run by the drive with `method` (0x6098).
    Drive,
    /// Run by the host: the drive turns at `switch_speed_rad_s` in cyclic synchronous
    /// velocity until bit `input_bit` of the digital inputs (0x60FD) is set; the position
    /// there is the steering angle `steer_offset_rad`.
    DigitalInput,
    /// An absolute steering encoder: no motion; the angle read at boot is checked to lie
    /// within a turn of the zero.
    Absolute,
    /// No homing: the position counter is trusted as it is (only for drives that keep their
    /// position across power cycles; a counter at 0 after power-on is a wrong angle).
    None,
}

/// The homing of a steering drive (`[cia402.homing]`, `wheels[i].homing`).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct Homing {
    /// Who homes and how.
    pub kind: HomingKind,
    /// CiA 402 homing method (0x6098) with `kind = "drive"`: 3 / 4 positive home switch and
    /// index pulse, 5 / 6 negative home switch and index pulse, 19 / 20 positive home
    /// switch, 21 / 22 negative home switch, 33 / 34 index pulse in the negative / positive
    /// direction, 35 or 37 the current position.
    pub method: i8,
    /// Speed while searching for the switch (rad/s at the steering axis; 0x6099:01). With
    /// `digital_input` the signed speed the axis turns at.
    pub switch_speed_rad_s: f64,
    /// Speed while searching for the zero (index pulse) (rad/s; 0x6099:02).
    pub index_speed_rad_s: f64,
    /// Acceleration of the homing moves (rad/s²; 0x609A).
    pub accel_rad_s2: f64,
    /// Time the whole homing may take (ms) before it fails naming the wheel.
    pub timeout_ms: u32,
    /// Digital input bit of 0x60FD that marks the home position (`digital_input`; CiA 402:
    /// bit 2 is the home switch, 16–31 are the manufacturer's).
    pub input_bit: u8,
}

impl Default for Homing {
    fn default() -> Self {
        Self {
            kind: HomingKind::Drive,
            method: 19,
            switch_speed_rad_s: 0.5,
            index_speed_rad_s: 0.1,
            accel_rad_s2: 2.0,
            timeout_ms: 20_000,
            input_bit: 2,
        }
    }
}

/// The CiA 402 homing methods (0x6098) this master accepts with `kind = "drive"`.
pub const HOMING_METHODS: [i8; 12] = [3, 4, 5, 6, 19, 20, 21, 22, 33, 34, 35, 37];

impl Homing {
    /// True when the drive moves (methods other than the current position).
    pub fn moves(&self) -> bool {
        match self.kind {
            HomingKind::Drive => !matches!(self.method, 35 | 37),
            HomingKind::DigitalInput => true,
            _ => false,
        }
    }

    /// Checks the fields against the steering limits; `field` is the table's path.
    pub fn validate(&self, field: &str, steer_rate: f64, steer_accel: f64) -> Result<(), Invalid> {
        if self.kind == HomingKind::Drive && !HOMING_METHODS.contains(&self.method) {
            return Err(Invalid::new(
                format!("{field}.method"),
                self.method,
                "is not a homing method this master supports: 3, 4, 5, 6 (home switch and index pulse), 19, 20, 21, 22 (home switch), 33, 34 (index pulse), 35 or 37 (current position); check the drive manual's 0x6098 table",
            ));
        }
        let speed_ok = |v: f64| v.is_finite() && v != 0.0 && v.abs() <= steer_rate;
        if self.moves() && !speed_ok(self.switch_speed_rad_s) {
            return Err(Invalid::new(
                format!("{field}.switch_speed_rad_s"),
                self.switch_speed_rad_s,
                format!("must be a non-zero speed within limits.steer_rate = {steer_rate} rad/s (the steering axis turns at it while homing)"),
            ));
        }
        if self.kind == HomingKind::Drive
            && self.moves()
            && !(speed_ok(self.index_speed_rad_s) && self.index_speed_rad_s > 0.0)
        {
            return Err(Invalid::new(
                format!("{field}.index_speed_rad_s"),
                self.index_speed_rad_s,
                format!("must be a positive speed within limits.steer_rate = {steer_rate} rad/s"),
            ));
        }
        if self.moves()
            && !(self.accel_rad_s2.is_finite()
                && self.accel_rad_s2 > 0.0
                && self.accel_rad_s2 <= steer_accel)
        {
            return Err(Invalid::new(
                format!("{field}.accel_rad_s2"),
                self.accel_rad_s2,
                format!("must be positive and within limits.steer_accel = {steer_accel} rad/s²"),
            ));
        }
        if self.timeout_ms < 100 || self.timeout_ms > 600_000 {
            return Err(Invalid::new(
                format!("{field}.timeout_ms"),
                self.timeout_ms,
                "must lie in 100..=600000 ms (long enough for the longest homing move, at most 10 min)",
            ));
        }
        if self.kind == HomingKind::DigitalInput && self.input_bit > 31 {
            return Err(Invalid::new(
                format!("{field}.input_bit"),
                self.input_bit,
                "must be a bit of the UNSIGNED32 digital inputs 0x60FD: 0..=31",
            ));
        }
        Ok(())
    }
}

impl Default for Cia402Config {
    fn default() -> Self {
        Self::for_wheels(4)
    }
}

/// One step of a device's boot plan.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum SdoOp {
    /// Expedited download.
    Write {
        /// Object index.
        index: u16,
        /// Sub-index.
        sub: u8,
        /// Value.
        data: SdoData,
        /// Skipped (and reported) when the device answers that the object or sub-index does
        /// not exist (abort 0x06020000 / 0x06090011).
        optional: bool,
    },
    /// Upload, then check `value & mask == expected`.
    Verify {
        /// Object index.
        index: u16,
        /// Sub-index.
        sub: u8,
        /// Bits compared.
        mask: u32,
        /// Expected value of the compared bits.
        expected: u32,
        /// What the object is, for the error message.
        what: &'static str,
        /// Read again every cycle for up to this long (ms) while the value differs (a mode
        /// display that follows its mode); 0: read once.
        poll_ms: u16,
        /// Skipped (and reported) when the object does not exist.
        optional: bool,
    },
}

impl SdoOp {
    /// The object the step is about.
    pub fn object(&self) -> (u16, u8) {
        match *self {
            SdoOp::Write { index, sub, .. } | SdoOp::Verify { index, sub, .. } => (index, sub),
        }
    }

    /// True for a step that is skipped when its object does not exist.
    pub fn optional(&self) -> bool {
        match *self {
            SdoOp::Write { optional, .. } | SdoOp::Verify { optional, .. } => optional,
        }
    }
}

fn write(index: u16, sub: u8, data: SdoData) -> SdoOp {
    SdoOp::Write {
        index,
        sub,
        data,
        optional: false,
    }
}

fn write_opt(index: u16, sub: u8, data: SdoData) -> SdoOp {
    SdoOp::Write {
        index,
        sub,
        data,
        optional: true,
    }
}

fn verify(index: u16, sub: u8, mask: u32, expected: u32, what: &'static str) -> SdoOp {
    SdoOp::Verify {
        index,
        sub,
        mask,
        expected,
        what,
        poll_ms: 0,
        optional: false,
    }
}

/// The interpolation time period 0x60C2 for a period in µs: (value, index) with
/// period = value · 10^index s, the largest index that represents the period exactly with
/// value ≤ 255 (4000 µs → (4, −3)); `None` when no index from −3 to −6 does.
pub fn interpolation_period(period_us: u32) -> Option<(u8, i8)> {
    let mut div = 1000u32;
    for index in [-3i8, -4, -5, -6] {
        if period_us % div == 0 && period_us / div <= 255 && period_us / div > 0 {
            return Some(((period_us / div) as u8, index));
        }
        div /= 10;
    }
    None
}

impl Cia402Config {
    /// The default node assignment for `n` wheels (at most 8): wheel i (0-based) has its
    /// rolling drive at node 1 + 2i, its steering drive at 2 + 2i and its leg encoder at
    /// 2n + 1 + i (four wheels: drives 1..=8, encoders 9..=12). Units and timing are those of
    /// a typical 48 V brushless drive with a 14-bit motor encoder and a 1 µm leg encoder.
    pub fn for_wheels(n: usize) -> Self {
        let n8 = n.min(8) as u8;
        let wheels = (0..n8)
            .map(|i| Cia402Wheel {
                drive_node: 1 + 2 * i,
                steer_node: 2 + 2 * i,
                leg_node: 2 * n8 + 1 + i,
                steer_offset_rad: 0.0,
                rest_angle_rad: 0.0,
                homing: None,
            })
            .collect();
        Self {
            master_node: 0x7F,
            wheels,
            drive: DriveUnits {
                increments_per_rev: 16384,
                gear_ratio: 30.0,
                velocity_unit: VelocityUnit::IncrementsPerSecond,
            },
            steer: DriveUnits {
                increments_per_rev: 16384,
                gear_ratio: 50.0,
                velocity_unit: VelocityUnit::IncrementsPerSecond,
            },
            leg_encoder: EncoderUnits {
                position_step_nm: 1000,
                speed_step_um_s: 10,
                offset_m: 0.0,
            },
            heartbeat_ms: 100,
            master_heartbeat_ms: 20,
            device_heartbeat_timeout_ms: 60,
            master_heartbeat_timeout_ms: 300,
            rpdo_timeout_ms: 50,
            comm_loss_reaction: 1,
            rpdo_transmission: 1,
            status_inhibit_100us: 10,
            status_event_timer_ms: 100,
            sdo_timeout_ms: 50,
            sdo_retries: 2,
            boot_timeout_ms: 2000,
            enable_timeout_ms: 500,
            mode_switch_timeout_ms: 100,
            homing: Homing::default(),
            coupling: 0.0,
            informational_emcy: Vec::new(),
            status_extra: Vec::new(),
            quick_stop: QuickStop::default(),
            sdo: Vec::new(),
            eds: EdsFiles::default(),
            dcf: Vec::new(),
        }
    }

    /// Every device as (wheel index, role, node), wheel by wheel (a wheel without a leg,
    /// `leg_node = 0`, has no leg encoder).
    pub fn devices(&self) -> impl Iterator<Item = (usize, Role, u8)> + '_ {
        self.wheels.iter().enumerate().flat_map(|(i, w)| {
            [Role::Drive, Role::Steer, Role::Leg]
                .into_iter()
                .filter(move |&r| !(r == Role::Leg && w.leg_node == 0))
                .map(move |r| (i, r, w.node(r)))
        })
    }

    /// Checks the section for a platform of `n_wheels` wheels running at `cycle_hz`. Field
    /// paths in errors start with `cia402.`.
    pub fn validate(&self, n_wheels: usize, cycle_hz: f64) -> Result<(), Invalid> {
        if self.wheels.len() != n_wheels {
            return Err(Invalid::new(
                "cia402.wheels",
                format!("{} entries", self.wheels.len()),
                format!(
                    "the platform has {n_wheels} wheels: give one {{ drive_node, steer_node, leg_node }} per wheel, in wheel order"
                ),
            ));
        }
        let node_ok = |n: u8| (1..=super::MAX_NODE_ID).contains(&n);
        if !node_ok(self.master_node) {
            return Err(Invalid::new(
                "cia402.master_node",
                self.master_node,
                "must be a node-ID in 1..=127",
            ));
        }
        let mut seen: Vec<(u8, String)> = vec![(self.master_node, "cia402.master_node".into())];
        for (i, w) in self.wheels.iter().enumerate() {
            for (role, field) in [
                (Role::Drive, "drive_node"),
                (Role::Steer, "steer_node"),
                (Role::Leg, "leg_node"),
            ] {
                let path = format!("cia402.wheels[{i}].{field}");
                let n = w.node(role);
                if role == Role::Leg && n == 0 {
                    // No leg encoder: a wheel without a leg (the platform checks which).
                    continue;
                }
                if !node_ok(n) {
                    return Err(Invalid::new(path, n, "must be a node-ID in 1..=127"));
                }
                if let Some((_, other)) = seen.iter().find(|(m, _)| *m == n) {
                    return Err(Invalid::new(
                        path,
                        n,
                        format!("node-ID already used by `{other}`; every device needs its own"),
                    ));
                }
                seen.push((n, path));
            }
            if !(w.steer_offset_rad.is_finite() && w.steer_offset_rad.abs() <= 100.0) {
                return Err(Invalid::new(
                    format!("cia402.wheels[{i}].steer_offset_rad"),
                    w.steer_offset_rad,
                    "must be a finite angle in radians",
                ));
            }
        }
        self.drive.validate("cia402.drive")?;
        self.steer.validate("cia402.steer")?;
        for (i, w) in self.wheels.iter().enumerate() {
            if !(w.rest_angle_rad.is_finite() && w.rest_angle_rad.abs() <= std::f64::consts::PI) {
                return Err(Invalid::new(
                    format!("cia402.wheels[{i}].rest_angle_rad"),
                    w.rest_angle_rad,
                    "must be a steering angle in [-π, π] rad",
                ));
            }
        }
        self.leg_encoder.validate("cia402.leg_encoder")?;
        let period_ms = if cycle_hz.is_finite() && cycle_hz > 0.0 {
            1000.0 / cycle_hz
        } else {
            4.0
        };
        let positive = |field: &str, v: u16| {
            if v == 0 {
                Err(Invalid::new(
                    format!("cia402.{field}"),
                    v,
                    "must be at least 1 ms",
                ))
            } else {
                Ok(())
            }
        };
        positive("heartbeat_ms", self.heartbeat_ms)?;
        positive("master_heartbeat_ms", self.master_heartbeat_ms)?;
        positive("sdo_timeout_ms", self.sdo_timeout_ms)?;
        positive("boot_timeout_ms", self.boot_timeout_ms)?;
        positive("enable_timeout_ms", self.enable_timeout_ms)?;
        if f64::from(self.device_heartbeat_timeout_ms)
            < f64::from(self.master_heartbeat_ms) + 2.0 * period_ms
        {
            return Err(Invalid::new(
                "cia402.device_heartbeat_timeout_ms",
                self.device_heartbeat_timeout_ms,
                format!(
                    "must exceed master_heartbeat_ms ({}) by at least two control cycles ({:.0} ms): the master's heartbeat goes out on the cycle grid",
                    self.master_heartbeat_ms,
                    2.0 * period_ms
                ),
            ));
        }
        if self.master_heartbeat_timeout_ms <= self.heartbeat_ms {
            return Err(Invalid::new(
                "cia402.master_heartbeat_timeout_ms",
                self.master_heartbeat_timeout_ms,
                format!(
                    "must be longer than the devices' heartbeat period heartbeat_ms = {} (three periods is usual)",
                    self.heartbeat_ms
                ),
            ));
        }
        if self.rpdo_timeout_ms != 0 && f64::from(self.rpdo_timeout_ms) < 3.0 * period_ms {
            return Err(Invalid::new(
                "cia402.rpdo_timeout_ms",
                self.rpdo_timeout_ms,
                format!(
                    "must be 0 (off) or at least three control cycles ({:.0} ms), or every late cycle trips the drives",
                    3.0 * period_ms
                ),
            ));
        }
        if !(0..=3).contains(&self.comm_loss_reaction) {
            return Err(Invalid::new(
                "cia402.comm_loss_reaction",
                self.comm_loss_reaction,
                "must be 0 (no action), 1 (fault), 2 (disable voltage) or 3 (quick stop)",
            ));
        }
        if !matches!(self.rpdo_transmission, 1..=240 | 254 | 255) {
            return Err(Invalid::new(
                "cia402.rpdo_transmission",
                self.rpdo_transmission,
                "must be 1..=240 (synchronous: applied at the next SYNC) or 254/255 (applied on reception)",
            ));
        }
        if self.mode_switch_timeout_ms == 0 || self.mode_switch_timeout_ms > 10_000 {
            return Err(Invalid::new(
                "cia402.mode_switch_timeout_ms",
                self.mode_switch_timeout_ms,
                "must lie in 1..=10000 ms (how long a drive's mode display may take to follow)",
            ));
        }
        if !(self.coupling.is_finite() && self.coupling.abs() <= 100.0) {
            return Err(Invalid::new(
                "cia402.coupling",
                self.coupling,
                "must be a finite ratio (wheel turns per steering turn, 0 for none)",
            ));
        }
        let mut bytes = 2usize;
        for (i, raw) in self.status_extra.iter().enumerate() {
            let m = pdo::MapEntry::from_raw(*raw);
            if !matches!(m.bits, 8 | 16 | 32) {
                return Err(Invalid::new(
                    format!("cia402.status_extra[{i}]"),
                    format!("0x{raw:08X}"),
                    "a mapping entry is index << 16 | sub << 8 | bits with 8, 16 or 32 bits (e.g. 0x603F0010)",
                ));
            }
            bytes += m.bytes();
        }
        let needs_inputs = (0..self.wheels.len())
            .any(|w| self.homing_of(w).kind == HomingKind::DigitalInput)
            && !self
                .status_extra
                .iter()
                .any(|r| pdo::MapEntry::from_raw(*r).index == od::DIGITAL_INPUTS);
        if needs_inputs {
            bytes += 4;
        }
        if bytes > 8 {
            return Err(Invalid::new(
                "cia402.status_extra",
                format!("{} entries", self.status_extra.len()),
                "the statusword TPDO2 holds 8 bytes: the statusword (2), these entries and, for a steering drive homed on a digital input, 0x60FD (4)",
            ));
        }
        for (i, x) in self.sdo.iter().enumerate() {
            let f = format!("cia402.sdo[{i}]");
            if !matches!(x.size, 1 | 2 | 4) {
                return Err(Invalid::new(
                    format!("{f}.size"),
                    x.size,
                    "must be 1, 2 or 4 bytes (the object's data type: UNSIGNED8/INTEGER8 1, 16-bit 2, 32-bit 4)",
                ));
            }
            let bits = 8 * u32::from(x.size);
            let fits = if bits == 32 {
                x.value >= i64::from(i32::MIN) && x.value <= i64::from(u32::MAX)
            } else {
                x.value >= -(1i64 << (bits - 1)) && x.value < (1i64 << bits)
            };
            if !fits {
                return Err(Invalid::new(
                    format!("{f}.value"),
                    x.value,
                    format!("does not fit {} bytes", x.size),
                ));
            }
            if let Some(n) = x.node {
                if !self.devices().any(|(_, _, m)| m == n) {
                    return Err(Invalid::new(
                        format!("{f}.node"),
                        n,
                        "is not a node of this platform's [cia402] wheels",
                    ));
                }
            }
            if x.index < 0x1000 {
                return Err(Invalid::new(
                    format!("{f}.index"),
                    format!("0x{:04X}", x.index),
                    "is not an object of a device's dictionary (indices start at 0x1000)",
                ));
            }
        }
        if !(0..=8).contains(&self.quick_stop.option) {
            return Err(Invalid::new(
                "cia402.quick_stop.option",
                self.quick_stop.option,
                "must be a CiA 402 quick stop option code 0..=8 (2: stop on the quick-stop ramp, then switch on disabled)",
            ));
        }
        for (field, v) in [
            ("drive_decel_rad_s2", self.quick_stop.drive_decel_rad_s2),
            ("steer_decel_rad_s2", self.quick_stop.steer_decel_rad_s2),
        ] {
            if !(v.is_finite() && v > 0.0 && v <= 1e4) {
                return Err(Invalid::new(
                    format!("cia402.quick_stop.{field}"),
                    v,
                    "must be a positive deceleration in rad/s² (0x6085)",
                ));
            }
        }
        for (i, d) in self.eds.devices.iter().enumerate() {
            if !self.devices().any(|(_, _, m)| m == d.node) {
                return Err(Invalid::new(
                    format!("cia402.eds.devices[{i}].node"),
                    d.node,
                    "is not a node of this platform's [cia402] wheels",
                ));
            }
        }
        let period_us = (period_ms * 1000.0).round() as u32;
        if interpolation_period(period_us).is_none() {
            return Err(Invalid::new(
                "cycle_hz",
                cycle_hz,
                "the CiA 402 profile needs a cycle period the drives' interpolation time period (0x60C2) can represent: a whole number of µs up to 255 ms",
            ));
        }
        Ok(())
    }

    /// The homing of wheel `wheel`'s steering drive.
    pub fn homing_of(&self, wheel: usize) -> Homing {
        self.wheels
            .get(wheel)
            .and_then(|w| w.homing)
            .unwrap_or(self.homing)
    }

    /// The statusword TPDO2's entries: the statusword, `status_extra`, and the digital
    /// inputs when a steering drive is homed on one (at most 8 entries, 8 bytes).
    pub fn status_entries(&self) -> ([pdo::MapEntry; 8], usize) {
        let mut e = [pdo::MapEntry::new(0, 0, 0); 8];
        e[0] = pdo::MapEntry::new(od::STATUSWORD, 0, 16);
        let mut n = 1;
        let mut bytes = 2;
        let needs_inputs =
            (0..self.wheels.len()).any(|w| self.homing_of(w).kind == HomingKind::DigitalInput);
        let inputs = pdo::MapEntry::new(od::DIGITAL_INPUTS, 0, 32);
        let extra = self
            .status_extra
            .iter()
            .map(|r| pdo::MapEntry::from_raw(*r));
        let auto = (needs_inputs && !extra.clone().any(|x| x.index == od::DIGITAL_INPUTS))
            .then_some(inputs);
        for m in extra.chain(auto) {
            if n < 8 && bytes + m.bytes() <= 8 {
                e[n] = m;
                n += 1;
                bytes += m.bytes();
            }
        }
        (e, n)
    }

    /// The SDO plan of one device with role `role` (see the module docs), for a control
    /// period of `period_us` µs (wheel 0's: see [`Cia402Config::plan_for`]).
    pub fn plan(&self, role: Role, period_us: u32) -> Vec<SdoOp> {
        self.plan_for(0, role, period_us)
    }

    /// The SDO plan of wheel `wheel`'s device with role `role`: the communication objects,
    /// the PDOs (unused ones disabled), the unit checks, the extra writes of the platform
    /// file, then the mode of operation (homing mode 6 for a steering drive the drive homes,
    /// cyclic synchronous velocity otherwise), polled until its display follows.
    pub fn plan_for(&self, wheel: usize, role: Role, period_us: u32) -> Vec<SdoOp> {
        let mut ops = Vec::with_capacity(64);
        let node = self.wheels.get(wheel).map_or(0, |w| w.node(role));
        let poll = |index: u16, expected: i8, what: &'static str| SdoOp::Verify {
            index,
            sub: 0,
            mask: 0xFF,
            expected: u32::from(expected as u8),
            what,
            poll_ms: self.mode_switch_timeout_ms,
            optional: false,
        };
        match role {
            Role::Drive | Role::Steer => {
                let units = if role == Role::Drive {
                    self.drive
                } else {
                    self.steer
                };
                ops.push(verify(
                    od::DEVICE_TYPE,
                    0,
                    0xFFFF,
                    u32::from(od::PROFILE_DRIVE),
                    "device type (a CiA 402 drive)",
                ));
                ops.push(write(od::COMM_CYCLE_PERIOD, 0, SdoData::u32(period_us)));
                ops.push(write(
                    od::PRODUCER_HEARTBEAT,
                    0,
                    SdoData::u16(self.heartbeat_ms),
                ));
                ops.push(write(
                    od::CONSUMER_HEARTBEAT,
                    1,
                    SdoData::u32(
                        (u32::from(self.master_node) << 16)
                            | u32::from(self.device_heartbeat_timeout_ms),
                    ),
                ));
                let (status, n_status) = self.status_entries();
                let pdos: [(pdo::Direction, u8, &[pdo::MapEntry], PdoComm); 3] = [
                    (
                        pdo::Direction::Rx,
                        1,
                        pdo::DRIVE_RPDO1.entries,
                        PdoComm {
                            transmission: self.rpdo_transmission,
                            inhibit_100us: 0,
                            event_timer_ms: self.rpdo_timeout_ms,
                        },
                    ),
                    (
                        pdo::Direction::Tx,
                        1,
                        pdo::DRIVE_TPDO1.entries,
                        PdoComm {
                            transmission: 1,
                            inhibit_100us: 0,
                            event_timer_ms: 0,
                        },
                    ),
                    (
                        pdo::Direction::Tx,
                        2,
                        &status[..n_status],
                        PdoComm {
                            transmission: 255,
                            inhibit_100us: self.status_inhibit_100us,
                            event_timer_ms: self.status_event_timer_ms,
                        },
                    ),
                ];
                for (dir, num, entries, comm) in pdos {
                    // The node only sets the COB-IDs; filled in by the master per device.
                    for (index, sub, data) in
                        pdo::config_writes_entries(dir, num, entries, 0, &comm)
                    {
                        ops.push(write(index, sub, data));
                    }
                }
                // PDOs the plan does not use: disabled, so that a factory default does not
                // load the bus (a device without them is fine).
                for num in 2..=4u8 {
                    ops.push(write_opt(
                        od::RPDO_COMM + u16::from(num - 1),
                        od::PDO_COB_ID,
                        SdoData::u32(od::PDO_COB_INVALID | u32::from(super::cob::rpdo(num, 0))),
                    ));
                }
                for num in 3..=4u8 {
                    ops.push(write_opt(
                        od::TPDO_COMM + u16::from(num - 1),
                        od::PDO_COB_ID,
                        SdoData::u32(
                            od::PDO_COB_INVALID
                                | od::PDO_COB_NO_RTR
                                | u32::from(super::cob::tpdo(num, 0)),
                        ),
                    ));
                }
                ops.push(write(
                    od::ABORT_CONNECTION_OPTION,
                    0,
                    SdoData::i16(self.comm_loss_reaction),
                ));
                // What the drive does on the master's Quick Stop command.
                ops.push(write_opt(
                    od::QUICK_STOP_OPTION,
                    0,
                    SdoData::i16(self.quick_stop.option),
                ));
                let decel = if role == Role::Drive {
                    self.quick_stop.drive_decel_rad_s2
                } else {
                    self.quick_stop.steer_decel_rad_s2
                };
                ops.push(write_opt(
                    od::QUICK_STOP_DECELERATION,
                    0,
                    SdoData::u32(
                        units
                            .velocity_from_si(decel)
                            .map_or(u32::MAX >> 1, i32::unsigned_abs),
                    ),
                ));
                let (v, ix) = interpolation_period(period_us).unwrap_or((4, -3));
                ops.push(write(od::INTERPOLATION_TIME_PERIOD, 1, SdoData::u8(v)));
                ops.push(write(od::INTERPOLATION_TIME_PERIOD, 2, SdoData::i8(ix)));
                // A DCF's values and the platform file's writes, then the units are read
                // as the drive ended up with them.
                self.push_extra(&mut ops, role, node);
                // Units, where the drive has the objects: its encoder resolution is the
                // platform file's, it does not apply a gear of its own, and its velocity
                // objects are in the unit the platform file converts from.
                if units.velocity_unit == super::units::VelocityUnit::IncrementsPerSecond {
                    ops.push(SdoOp::Verify {
                        index: od::POSITION_ENCODER_RESOLUTION,
                        sub: 1,
                        mask: 0xFFFF_FFFF,
                        expected: units.increments_per_rev,
                        what: if role == Role::Drive {
                            "position encoder resolution, increments per motor revolution (cia402.drive.increments_per_rev)"
                        } else {
                            "position encoder resolution, increments per motor revolution (cia402.steer.increments_per_rev)"
                        },
                        poll_ms: 0,
                        optional: true,
                    });
                    // … per one motor revolution (the resolution is 0x608F:01 / 0x608F:02).
                    ops.push(SdoOp::Verify {
                        index: od::POSITION_ENCODER_RESOLUTION,
                        sub: 2,
                        mask: 0xFFFF_FFFF,
                        expected: 1,
                        what: "position encoder resolution, motor revolutions (must be 1: increments_per_rev counts one revolution)",
                        poll_ms: 0,
                        optional: true,
                    });
                }
                for sub in [1u8, 2] {
                    ops.push(SdoOp::Verify {
                        index: od::GEAR_RATIO,
                        sub,
                        mask: 0xFFFF_FFFF,
                        expected: 1,
                        what: "gear ratio (must be 1:1: the platform file's gear_ratio converts, the drive must not scale as well)",
                        poll_ms: 0,
                        optional: true,
                    });
                }
                ops.push(SdoOp::Verify {
                    index: od::SI_UNIT_VELOCITY,
                    sub: 0,
                    // Bits 0-7 are reserved.
                    mask: 0xFFFF_FF00,
                    expected: units.velocity_unit.si_unit_velocity(),
                    what: match (role, units.velocity_unit) {
                        (Role::Drive, super::units::VelocityUnit::IncrementsPerSecond) => "SI unit velocity (cia402.drive.velocity_unit = increments_per_second: inc/s)",
                        (Role::Drive, super::units::VelocityUnit::Rpm) => "SI unit velocity (cia402.drive.velocity_unit = rpm: rev/min)",
                        (Role::Drive, super::units::VelocityUnit::MilliRpm) => "SI unit velocity (cia402.drive.velocity_unit = milli_rpm: 0.001 rev/min)",
                        (_, super::units::VelocityUnit::IncrementsPerSecond) => "SI unit velocity (cia402.steer.velocity_unit = increments_per_second: inc/s)",
                        (_, super::units::VelocityUnit::Rpm) => "SI unit velocity (cia402.steer.velocity_unit = rpm: rev/min)",
                        (_, super::units::VelocityUnit::MilliRpm) => "SI unit velocity (cia402.steer.velocity_unit = milli_rpm: 0.001 rev/min)",
                    },
                    poll_ms: 0,
                    optional: true,
                });
                let h = self.homing_of(wheel);
                if role == Role::Steer && h.kind == HomingKind::Drive {
                    let vel = |v: f64| units.velocity_from_si(v.abs()).unwrap_or(0).unsigned_abs();
                    ops.push(write(od::HOMING_METHOD, 0, SdoData::i8(h.method)));
                    ops.push(write(
                        od::HOMING_SPEEDS,
                        1,
                        SdoData::u32(vel(h.switch_speed_rad_s)),
                    ));
                    ops.push(write(
                        od::HOMING_SPEEDS,
                        2,
                        SdoData::u32(vel(h.index_speed_rad_s)),
                    ));
                    ops.push(write(
                        od::HOMING_ACCELERATION,
                        0,
                        SdoData::u32(vel(h.accel_rad_s2)),
                    ));
                    // Position 0 at the home position: the steering angle there is the
                    // wheel's steer_offset_rad (host side, whatever the drive's convention).
                    ops.push(write_opt(od::HOME_OFFSET, 0, SdoData::u32(0)));
                    ops.push(write(
                        od::MODES_OF_OPERATION,
                        0,
                        SdoData::i8(od::MODE_HOMING),
                    ));
                    ops.push(poll(
                        od::MODES_OF_OPERATION_DISPLAY,
                        od::MODE_HOMING,
                        "modes of operation display (homing, 6)",
                    ));
                } else {
                    ops.push(write(od::MODES_OF_OPERATION, 0, SdoData::i8(od::MODE_CSV)));
                    ops.push(poll(
                        od::MODES_OF_OPERATION_DISPLAY,
                        od::MODE_CSV,
                        "modes of operation display (cyclic synchronous velocity, 9)",
                    ));
                }
            }
            Role::Leg => {
                ops.push(verify(
                    od::DEVICE_TYPE,
                    0,
                    0xFFFF,
                    u32::from(od::PROFILE_ENCODER),
                    "device type (a CiA 406 encoder)",
                ));
                ops.push(verify(
                    od::MEASURING_STEP,
                    1,
                    0xFFFF_FFFF,
                    self.leg_encoder.position_step_nm,
                    "position measuring step in nm (cia402.leg_encoder.position_step_nm)",
                ));
                ops.push(write(od::COMM_CYCLE_PERIOD, 0, SdoData::u32(period_us)));
                ops.push(write(
                    od::PRODUCER_HEARTBEAT,
                    0,
                    SdoData::u16(self.heartbeat_ms),
                ));
                let comm = PdoComm {
                    transmission: 1,
                    inhibit_100us: 0,
                    event_timer_ms: 0,
                };
                for (index, sub, data) in pdo::config_writes(&pdo::ENCODER_TPDO1, 0, &comm) {
                    ops.push(write(index, sub, data));
                }
                for num in 2..=4u8 {
                    ops.push(write_opt(
                        od::TPDO_COMM + u16::from(num - 1),
                        od::PDO_COB_ID,
                        SdoData::u32(
                            od::PDO_COB_INVALID
                                | od::PDO_COB_NO_RTR
                                | u32::from(super::cob::tpdo(num, 0)),
                        ),
                    ));
                }
                self.push_extra(&mut ops, role, node);
            }
        }
        ops
    }

    /// The steps that switch a homed steering drive back to cyclic synchronous velocity.
    pub fn after_homing_plan(&self) -> [SdoOp; 2] {
        [
            write(od::MODES_OF_OPERATION, 0, SdoData::i8(od::MODE_CSV)),
            SdoOp::Verify {
                index: od::MODES_OF_OPERATION_DISPLAY,
                sub: 0,
                mask: 0xFF,
                expected: u32::from(od::MODE_CSV as u8),
                what: "modes of operation display (cyclic synchronous velocity, 9)",
                poll_ms: self.mode_switch_timeout_ms,
                optional: false,
            },
        ]
    }

    /// The DCF's values of the device (see [`super::eds`]), then the platform file's extra
    /// writes: the platform file has the last word.
    fn push_extra(&self, ops: &mut Vec<SdoOp>, role: Role, node: u8) {
        for d in self.dcf.iter().filter(|d| d.node == node) {
            ops.push(SdoOp::Write {
                index: d.index,
                sub: d.sub,
                data: d.data,
                optional: false,
            });
        }
        for x in self.sdo.iter().filter(|x| x.applies(role, node)) {
            let data = SdoData::new(x.value as u32, x.size);
            ops.push(SdoOp::Write {
                index: x.index,
                sub: x.sub,
                data,
                optional: x.optional,
            });
        }
    }
}

/// A plan step with the node's COB-IDs filled in: PDO COB-ID writes of the plan carry node
/// 0 (they are built once for every device) and get `node` added here.
pub fn for_node(op: SdoOp, node: u8) -> SdoOp {
    match op {
        SdoOp::Write {
            index,
            sub,
            data,
            optional,
        } if sub == od::PDO_COB_ID
            && ((od::RPDO_COMM..od::RPDO_COMM + 4).contains(&index)
                || (od::TPDO_COMM..od::TPDO_COMM + 4).contains(&index)) =>
        {
            SdoOp::Write {
                index,
                sub,
                data: SdoData::u32(data.as_u32() + u32::from(node & 0x7F)),
                optional,
            }
        }
        other => other,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn default_assignment_and_validation() {
        let c = Cia402Config::for_wheels(4);
        let nodes: Vec<(usize, Role, u8)> = c.devices().collect();
        assert_eq!(nodes.len(), 12);
        assert_eq!(nodes[0], (0, Role::Drive, 1));
        assert_eq!(nodes[1], (0, Role::Steer, 2));
        assert_eq!(nodes[2], (0, Role::Leg, 9));
        assert_eq!(nodes[11], (3, Role::Leg, 12));
        c.validate(4, 250.0).unwrap();
        let e = c.validate(3, 250.0).unwrap_err();
        assert_eq!(e.field, "cia402.wheels");
        let mut d = c.clone();
        d.wheels[2].steer_node = 1;
        let e = d.validate(4, 250.0).unwrap_err();
        assert_eq!(e.field, "cia402.wheels[2].steer_node");
        assert!(e.reason.contains("cia402.wheels[0].drive_node"), "{e}");
        let mut d = c.clone();
        d.master_node = 9;
        assert_eq!(
            d.validate(4, 250.0).unwrap_err().field,
            "cia402.wheels[0].leg_node"
        );
        let mut d = c.clone();
        d.device_heartbeat_timeout_ms = 20;
        assert_eq!(
            d.validate(4, 250.0).unwrap_err().field,
            "cia402.device_heartbeat_timeout_ms"
        );
        let mut d = c.clone();
        d.rpdo_transmission = 250;
        assert_eq!(
            d.validate(4, 250.0).unwrap_err().field,
            "cia402.rpdo_transmission"
        );
        let mut d = c.clone();
        d.rpdo_timeout_ms = 5;
        assert_eq!(
            d.validate(4, 250.0).unwrap_err().field,
            "cia402.rpdo_timeout_ms"
        );
        let mut d = c;
        d.comm_loss_reaction = 7;
        assert_eq!(
            d.validate(4, 250.0).unwrap_err().field,
            "cia402.comm_loss_reaction"
        );
    }

    #[test]
    fn interpolation_periods() {
        assert_eq!(interpolation_period(4000), Some((4, -3)));
        assert_eq!(interpolation_period(2500), Some((25, -4)));
        assert_eq!(interpolation_period(1), Some((1, -6)));
        assert_eq!(interpolation_period(300_000), None);
    }

    #[test]
    fn drive_plan_ends_in_csv_and_fills_in_the_node() {
        let c = Cia402Config::for_wheels(4);
        let plan: Vec<SdoOp> = c
            .plan(Role::Steer, 4000)
            .into_iter()
            .map(|o| for_node(o, 2))
            .collect();
        assert!(matches!(plan[0], SdoOp::Verify { index: 0x1000, .. }));
        assert!(matches!(
            plan.last(),
            Some(SdoOp::Verify { index: 0x6061, .. })
        ));
        let write_of = |ix: u16, sub: u8| -> Vec<u32> {
            plan.iter()
                .filter_map(|o| match o {
                    SdoOp::Write {
                        index,
                        sub: s,
                        data,
                        ..
                    } if *index == ix && *s == sub => Some(data.as_u32()),
                    _ => None,
                })
                .collect()
        };
        // The default homing is the drive's (mode 6) on a home switch: the steering drive
        // boots into homing mode; the rolling drive into cyclic synchronous velocity.
        assert_eq!(write_of(0x6060, 0), vec![6]);
        assert_eq!(write_of(0x6098, 0), vec![19]);
        assert_eq!(write_of(0x1016, 1), vec![0x007F_003C]);
        assert_eq!(write_of(0x1017, 0), vec![100]);
        assert_eq!(write_of(0x1006, 0), vec![4000]);
        assert_eq!(write_of(0x1400, 1), vec![0x8000_0202, 0x0000_0202]);
        assert_eq!(write_of(0x1800, 1), vec![0xC000_0182, 0x4000_0182]);
        assert_eq!(write_of(0x1801, 1), vec![0xC000_0282, 0x4000_0282]);
        assert_eq!(write_of(0x60C2, 2), vec![0xFD]);
        // The encoder plan checks the measuring step.
        let plan = c.plan(Role::Leg, 4000);
        assert!(plan.iter().any(|o| matches!(
            o,
            SdoOp::Verify {
                index: 0x6005,
                sub: 1,
                expected: 1000,
                ..
            }
        )));
    }
}
