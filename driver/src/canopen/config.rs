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
    /// Steering angle φ (rad) at steering position 0 (the homing offset).
    #[serde(default)]
    pub steer_offset_rad: f64,
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
    },
}

impl SdoOp {
    /// The object the step is about.
    pub fn object(&self) -> (u16, u8) {
        match *self {
            SdoOp::Write { index, sub, .. } | SdoOp::Verify { index, sub, .. } => (index, sub),
        }
    }
}

fn write(index: u16, sub: u8, data: SdoData) -> SdoOp {
    SdoOp::Write { index, sub, data }
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

    /// The SDO plan of one device with role `role` (see the module docs), for a control
    /// period of `period_us` µs.
    pub fn plan(&self, role: Role, period_us: u32) -> Vec<SdoOp> {
        let mut ops = Vec::with_capacity(40);
        match role {
            Role::Drive | Role::Steer => {
                ops.push(SdoOp::Verify {
                    index: od::DEVICE_TYPE,
                    sub: 0,
                    mask: 0xFFFF,
                    expected: u32::from(od::PROFILE_DRIVE),
                    what: "device type (a CiA 402 drive)",
                });
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
                let pdos = [
                    (
                        pdo::DRIVE_RPDO1,
                        PdoComm {
                            transmission: self.rpdo_transmission,
                            inhibit_100us: 0,
                            event_timer_ms: self.rpdo_timeout_ms,
                        },
                    ),
                    (
                        pdo::DRIVE_TPDO1,
                        PdoComm {
                            transmission: 1,
                            inhibit_100us: 0,
                            event_timer_ms: 0,
                        },
                    ),
                    (
                        pdo::DRIVE_TPDO2,
                        PdoComm {
                            transmission: 255,
                            inhibit_100us: self.status_inhibit_100us,
                            event_timer_ms: self.status_event_timer_ms,
                        },
                    ),
                ];
                for (layout, comm) in pdos {
                    // The node only sets the COB-IDs; filled in by the master per device.
                    for (index, sub, data) in pdo::config_writes(&layout, 0, &comm) {
                        ops.push(write(index, sub, data));
                    }
                }
                ops.push(write(
                    od::ABORT_CONNECTION_OPTION,
                    0,
                    SdoData::i16(self.comm_loss_reaction),
                ));
                let (v, ix) = interpolation_period(period_us).unwrap_or((4, -3));
                ops.push(write(od::INTERPOLATION_TIME_PERIOD, 1, SdoData::u8(v)));
                ops.push(write(od::INTERPOLATION_TIME_PERIOD, 2, SdoData::i8(ix)));
                ops.push(write(od::MODES_OF_OPERATION, 0, SdoData::i8(od::MODE_CSV)));
                ops.push(SdoOp::Verify {
                    index: od::MODES_OF_OPERATION_DISPLAY,
                    sub: 0,
                    mask: 0xFF,
                    expected: u32::from(od::MODE_CSV as u8),
                    what: "modes of operation display (cyclic synchronous velocity, 9)",
                });
            }
            Role::Leg => {
                ops.push(SdoOp::Verify {
                    index: od::DEVICE_TYPE,
                    sub: 0,
                    mask: 0xFFFF,
                    expected: u32::from(od::PROFILE_ENCODER),
                    what: "device type (a CiA 406 encoder)",
                });
                ops.push(SdoOp::Verify {
                    index: od::MEASURING_STEP,
                    sub: 1,
                    mask: 0xFFFF_FFFF,
                    expected: self.leg_encoder.position_step_nm,
                    what: "position measuring step in nm (cia402.leg_encoder.position_step_nm)",
                });
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
            }
        }
        ops
    }
}

/// A plan step with the node's COB-IDs filled in: PDO COB-ID writes of the plan carry node
/// 0 (they are built once for every device) and get `node` added here.
pub fn for_node(op: SdoOp, node: u8) -> SdoOp {
    match op {
        SdoOp::Write { index, sub, data }
            if sub == od::PDO_COB_ID
                && ((od::RPDO_COMM..od::RPDO_COMM + 4).contains(&index)
                    || (od::TPDO_COMM..od::TPDO_COMM + 4).contains(&index)) =>
        {
            SdoOp::Write {
                index,
                sub,
                data: SdoData::u32(data.as_u32() + u32::from(node & 0x7F)),
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
                    } if *index == ix && *s == sub => Some(data.as_u32()),
                    _ => None,
                })
                .collect()
        };
        assert_eq!(write_of(0x6060, 0), vec![9]);
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
