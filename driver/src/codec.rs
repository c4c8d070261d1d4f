//! Pure, stateless encoding and decoding between SI values and frames.
//!
//! Both directions walk the signal table in [`crate::protocol::MESSAGES`]; nothing about a
//! layout is written twice. [`encode`] rounds each physical value to the nearest wire step
//! (ties away from zero) and refuses values outside the declared range (never wraps or
//! clamps). [`decode`] checks, in this order: known id and valid node, DLC, CRC, then every
//! signal's raw range and enum values. Rolling counters are checked by the stateful
//! [`crate::rx::Receiver`], not here.

use crate::crc::frame_crc;
use crate::frame::CanFrame;
use crate::protocol::{classify_any_node, spec, try_id_of, MessageKind, SignalRole, SignalSpec};

/// STATUS fault code: no fault.
pub const FAULT_NONE: u8 = 0;
/// STATUS fault code: a motor phase current exceeded the driver's limit.
pub const FAULT_OVERCURRENT: u8 = 1;
/// STATUS fault code: motor or power stage over its temperature limit.
pub const FAULT_OVERTEMPERATURE: u8 = 2;
/// STATUS fault code: an encoder reading is implausible (stuck, jump, signal loss).
pub const FAULT_ENCODER: u8 = 3;
/// STATUS fault code: no valid SETPOINT for 50 ms; the module stopped its motors.
pub const FAULT_WATCHDOG: u8 = 4;
/// STATUS fault code: DC link voltage below the operating range.
pub const FAULT_UNDERVOLTAGE: u8 = 5;
/// STATUS fault code: DC link voltage above the operating range (e.g. regenerative braking).
pub const FAULT_OVERVOLTAGE: u8 = 6;
/// STATUS fault code: the leg reached a hard end stop or a joint limit was violated.
pub const FAULT_LIMIT: u8 = 7;
/// STATUS fault code: motor driver hardware fault (gate driver, short circuit).
pub const FAULT_DRIVER: u8 = 8;
/// STATUS fault code: module-internal error not covered above.
pub const FAULT_INTERNAL: u8 = 0xFF;

/// Human-readable name of a STATUS fault code (unknown codes give `"unknown"`).
pub fn fault_name(code: u8) -> &'static str {
    match code {
        FAULT_NONE => "none",
        FAULT_OVERCURRENT => "overcurrent",
        FAULT_OVERTEMPERATURE => "overtemperature",
        FAULT_ENCODER => "encoder",
        FAULT_WATCHDOG => "setpoint watchdog",
        FAULT_UNDERVOLTAGE => "undervoltage",
        FAULT_OVERVOLTAGE => "overvoltage",
        FAULT_LIMIT => "limit",
        FAULT_DRIVER => "driver",
        FAULT_INTERNAL => "internal",
        _ => "unknown",
    }
}

/// SETPOINT flag bits.
#[derive(Copy, Clone, Debug, Default, PartialEq, Eq, Hash)]
pub struct SetpointFlags {
    /// Motors enabled (0 = disabled: the module coasts to a stop).
    pub enable: bool,
    /// Decelerate both motors to zero at the torque limit.
    pub brake: bool,
    /// Clear a latched fault.
    pub fault_reset: bool,
}

/// SYNC payload.
#[derive(Copy, Clone, Debug, Default, PartialEq, Eq, Hash)]
pub struct Sync {
    /// Controller cycle number (wraps at 65536).
    pub cycle: u16,
}

/// SETPOINT payload.
#[derive(Copy, Clone, Debug, Default, PartialEq)]
pub struct Setpoint {
    /// Wheel spin rate, rad/s.
    pub wheel_speed: f64,
    /// Steering rate, rad/s.
    pub steer_rate: f64,
    /// Flags.
    pub flags: SetpointFlags,
}

/// FEEDBACK_A payload.
#[derive(Copy, Clone, Debug, Default, PartialEq)]
pub struct FeedbackA {
    /// Steering angle, rad, in [−π, π].
    pub steer_angle: f64,
    /// Wheel spin rate, rad/s.
    pub wheel_speed: f64,
    /// Steering rate, rad/s.
    pub steer_rate: f64,
}

/// FEEDBACK_B payload.
#[derive(Copy, Clone, Debug, Default, PartialEq)]
pub struct FeedbackB {
    /// Leg extension, m.
    pub leg_extension: f64,
    /// Leg extension rate, m/s.
    pub leg_rate: f64,
    /// Drive motor current, A.
    pub drive_current: f64,
    /// Steering motor current, A.
    pub steer_current: f64,
}

/// Wheel-module state (STATUS `state`, wire values 0..=3).
#[derive(Copy, Clone, Debug, Default, PartialEq, Eq, Hash)]
pub enum ModuleState {
    /// Booting; not yet accepting setpoints.
    #[default]
    Boot = 0,
    /// Ready; motors disabled.
    Ready = 1,
    /// Motors enabled and following setpoints.
    Enabled = 2,
    /// Fault latched; motors stopped until a SETPOINT with `fault_reset`.
    Fault = 3,
}

impl ModuleState {
    /// Wire value.
    pub fn to_raw(self) -> u8 {
        self as u8
    }

    /// State of a wire value, `None` for 4..=15.
    pub fn from_raw(raw: u8) -> Option<ModuleState> {
        match raw {
            0 => Some(ModuleState::Boot),
            1 => Some(ModuleState::Ready),
            2 => Some(ModuleState::Enabled),
            3 => Some(ModuleState::Fault),
            _ => None,
        }
    }

    /// Lower-case name.
    pub fn name(self) -> &'static str {
        match self {
            ModuleState::Boot => "boot",
            ModuleState::Ready => "ready",
            ModuleState::Enabled => "enabled",
            ModuleState::Fault => "fault",
        }
    }
}

/// STATUS payload.
#[derive(Copy, Clone, Debug, Default, PartialEq)]
pub struct Status {
    /// Module state.
    pub state: ModuleState,
    /// Latched fault code (`FAULT_*`), [`FAULT_NONE`] when none.
    pub fault_code: u8,
    /// Hottest motor/driver temperature, °C (1 °C steps, −40..=215 on the wire).
    pub temperature: f64,
    /// DC link voltage, V.
    pub bus_voltage: f64,
}

/// The payload of any protocol message.
#[derive(Copy, Clone, Debug, PartialEq)]
pub enum Payload {
    /// SYNC.
    Sync(Sync),
    /// SETPOINT.
    Setpoint(Setpoint),
    /// FEEDBACK_A.
    FeedbackA(FeedbackA),
    /// FEEDBACK_B.
    FeedbackB(FeedbackB),
    /// STATUS.
    Status(Status),
}

impl Payload {
    /// The message kind of this payload.
    pub fn kind(&self) -> MessageKind {
        match self {
            Payload::Sync(_) => MessageKind::Sync,
            Payload::Setpoint(_) => MessageKind::Setpoint,
            Payload::FeedbackA(_) => MessageKind::FeedbackA,
            Payload::FeedbackB(_) => MessageKind::FeedbackB,
            Payload::Status(_) => MessageKind::Status,
        }
    }
}

/// A decoded (or to-be-encoded) protocol message.
#[derive(Copy, Clone, Debug, PartialEq)]
pub struct Message {
    /// Wheel-module node 1..=15; 0 for SYNC.
    pub node: u8,
    /// Rolling counter 0..=15.
    pub counter: u8,
    /// The values.
    pub payload: Payload,
}

impl Message {
    /// The message kind.
    pub fn kind(&self) -> MessageKind {
        self.payload.kind()
    }
}

impl std::fmt::Display for Message {
    /// One line, e.g. `FEEDBACK_A node 2 #15 steer_angle=-1.5708 rad wheel_speed=13.900 rad/s
    /// steer_rate=-10.000 rad/s`.
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "{}", self.kind())?;
        if self.node != 0 {
            write!(f, " node {}", self.node)?;
        }
        write!(f, " #{}", self.counter)?;
        match &self.payload {
            Payload::Sync(s) => write!(f, " cycle={}", s.cycle),
            Payload::Setpoint(s) => write!(
                f,
                " wheel_speed={:.3} rad/s steer_rate={:.3} rad/s enable={} brake={} fault_reset={}",
                s.wheel_speed,
                s.steer_rate,
                u8::from(s.flags.enable),
                u8::from(s.flags.brake),
                u8::from(s.flags.fault_reset)
            ),
            Payload::FeedbackA(a) => write!(
                f,
                " steer_angle={:.4} rad wheel_speed={:.3} rad/s steer_rate={:.3} rad/s",
                a.steer_angle, a.wheel_speed, a.steer_rate
            ),
            Payload::FeedbackB(b) => write!(
                f,
                " leg_extension={:.5} m leg_rate={:.4} m/s drive_current={:.2} A steer_current={:.2} A",
                b.leg_extension, b.leg_rate, b.drive_current, b.steer_current
            ),
            Payload::Status(s) => write!(
                f,
                " state={} fault={} ({}) temperature={:.0} degC bus_voltage={:.2} V",
                s.state.name(),
                s.fault_code,
                fault_name(s.fault_code),
                s.temperature,
                s.bus_voltage
            ),
        }
    }
}

/// Why a message could not be encoded.
#[derive(Debug, Clone, Copy, PartialEq, thiserror::Error)]
pub enum EncodeError {
    /// Node number not valid for the message kind.
    #[error("{kind} cannot be sent to node {node}: per-node messages need node 1..=15, SYNC needs node 0")]
    BadNode {
        /// Message kind.
        kind: MessageKind,
        /// Rejected node.
        node: u8,
    },
    /// Rolling counter above 15.
    #[error(
        "{kind} rolling counter {counter} does not fit 4 bits (0..=15); increment it modulo 16"
    )]
    BadCounter {
        /// Message kind.
        kind: MessageKind,
        /// Rejected counter.
        counter: u8,
    },
    /// A value is outside the signal's declared range (or not finite).
    #[error("{kind}.{signal} = {value} {unit} is outside the declared range [{min}, {max}] {unit}; limit the value before encoding (it is never wrapped or clamped)")]
    OutOfRange {
        /// Message kind.
        kind: MessageKind,
        /// Signal name.
        signal: &'static str,
        /// Rejected physical value.
        value: f64,
        /// Lowest accepted value.
        min: f64,
        /// Highest accepted value.
        max: f64,
        /// Unit of the value.
        unit: &'static str,
    },
}

/// Why a frame could not be decoded.
#[derive(Debug, Clone, Copy, PartialEq, Eq, thiserror::Error)]
pub enum DecodeError {
    /// The id is not part of the protocol.
    #[error("CAN id 0x{id:03X} is not a rollbase protocol message (check the bus for foreign nodes or set a receive filter)")]
    UnknownId {
        /// The id.
        id: u16,
    },
    /// A per-node message with node 0.
    #[error("CAN id 0x{id:03X} is {kind} for node 0, which is not a valid module node (1..=15)")]
    BadNode {
        /// Message kind of the id block.
        kind: MessageKind,
        /// The id.
        id: u16,
    },
    /// The DLC does not match the table.
    #[error("{kind} (id 0x{id:03X}) has DLC {got}, expected {expected}; the sender uses a different protocol revision or the frame is damaged")]
    WrongDlc {
        /// Message kind.
        kind: MessageKind,
        /// The id.
        id: u16,
        /// DLC from the table.
        expected: u8,
        /// DLC received.
        got: u8,
    },
    /// The CRC byte does not match the computed CRC.
    #[error("{kind} (id 0x{id:03X}) CRC mismatch: computed 0x{computed:02X}, received 0x{received:02X}; the frame was corrupted or sent under a wrong id")]
    BadCrc {
        /// Message kind.
        kind: MessageKind,
        /// The id.
        id: u16,
        /// CRC computed over the received bytes.
        computed: u8,
        /// CRC byte received.
        received: u8,
    },
    /// A signal's raw value is outside its declared range.
    #[error("{kind} (id 0x{id:03X}) signal {signal} raw value {raw} is outside the declared raw range [{min_raw}, {max_raw}]")]
    OutOfRange {
        /// Message kind.
        kind: MessageKind,
        /// The id.
        id: u16,
        /// Signal name.
        signal: &'static str,
        /// Raw value received.
        raw: i64,
        /// Lowest accepted raw value.
        min_raw: i64,
        /// Highest accepted raw value.
        max_raw: i64,
    },
    /// An enumeration signal has an undefined value.
    #[error("{kind} (id 0x{id:03X}) signal {signal} has undefined enum value {raw}")]
    BadEnum {
        /// Message kind.
        kind: MessageKind,
        /// The id.
        id: u16,
        /// Signal name.
        signal: &'static str,
        /// Raw value received.
        raw: i64,
    },
}

/// Most signals in one message (table invariant, checked by a test).
const MAX_SIGNALS: usize = 8;

fn field_mask(length: u8) -> u64 {
    if length >= 64 {
        u64::MAX
    } else {
        (1u64 << length) - 1
    }
}

/// Extracts a signal's raw value (sign-extended when signed) from the little-endian word.
fn get_raw(word: u64, s: &SignalSpec) -> i64 {
    let bits = (word >> s.start_bit) & field_mask(s.length);
    if s.signed && s.length > 0 && (bits >> (s.length - 1)) & 1 == 1 {
        bits as i64 - (1i64 << s.length)
    } else {
        bits as i64
    }
}

/// Inserts a raw value (two's complement, truncated to the field) into the word.
fn put_raw(word: &mut u64, s: &SignalSpec, raw: i64) {
    *word |= ((raw as u64) & field_mask(s.length)) << s.start_bit;
}

fn b(x: bool) -> f64 {
    if x {
        1.0
    } else {
        0.0
    }
}

/// Physical values in table signal order; counter and CRC slots are placeholders.
fn values_of(p: &Payload) -> [f64; MAX_SIGNALS] {
    let mut v = [0.0; MAX_SIGNALS];
    match p {
        // cycle, counter, crc
        Payload::Sync(s) => v[0] = f64::from(s.cycle),
        // wheel_speed, steer_rate, enable, brake, fault_reset, counter, crc
        Payload::Setpoint(s) => {
            v[..5].copy_from_slice(&[
                s.wheel_speed,
                s.steer_rate,
                b(s.flags.enable),
                b(s.flags.brake),
                b(s.flags.fault_reset),
            ]);
        }
        // steer_angle, wheel_speed, steer_rate, counter, crc
        Payload::FeedbackA(f) => {
            v[..3].copy_from_slice(&[f.steer_angle, f.wheel_speed, f.steer_rate])
        }
        // leg_extension, leg_rate, drive_current, steer_current, counter, crc
        Payload::FeedbackB(f) => v[..4].copy_from_slice(&[
            f.leg_extension,
            f.leg_rate,
            f.drive_current,
            f.steer_current,
        ]),
        // state, counter, fault_code, temperature, bus_voltage, crc
        Payload::Status(s) => {
            v[0] = f64::from(s.state.to_raw());
            v[2] = f64::from(s.fault_code);
            v[3] = s.temperature;
            v[4] = s.bus_voltage;
        }
    }
    v
}

/// Builds the payload of `kind` from raw values (table order) already range-checked.
fn payload_from(kind: MessageKind, raw: &[i64; MAX_SIGNALS], phys: &[f64; MAX_SIGNALS]) -> Payload {
    match kind {
        MessageKind::Sync => Payload::Sync(Sync {
            // 16-bit unsigned field.
            cycle: raw[0] as u16,
        }),
        MessageKind::Setpoint => Payload::Setpoint(Setpoint {
            wheel_speed: phys[0],
            steer_rate: phys[1],
            flags: SetpointFlags {
                enable: raw[2] != 0,
                brake: raw[3] != 0,
                fault_reset: raw[4] != 0,
            },
        }),
        MessageKind::FeedbackA => Payload::FeedbackA(FeedbackA {
            steer_angle: phys[0],
            wheel_speed: phys[1],
            steer_rate: phys[2],
        }),
        MessageKind::FeedbackB => Payload::FeedbackB(FeedbackB {
            leg_extension: phys[0],
            leg_rate: phys[1],
            drive_current: phys[2],
            steer_current: phys[3],
        }),
        MessageKind::Status => Payload::Status(Status {
            // Enum range 0..=3 was checked by decode.
            state: ModuleState::from_raw(raw[0] as u8).unwrap_or(ModuleState::Fault),
            // 8-bit unsigned field.
            fault_code: raw[2] as u8,
            temperature: phys[3],
            bus_voltage: phys[4],
        }),
    }
}

/// Encodes a message into its frame.
///
/// Every value is rounded to the nearest wire step; a value outside its declared
/// `[min, max]` (or NaN/infinite) is [`EncodeError::OutOfRange`]. The node must be valid
/// for the kind (1..=15, or 0 for SYNC) and the counter ≤ 15. Reserved bits are 0.
pub fn encode(msg: &Message) -> Result<CanFrame, EncodeError> {
    let kind = msg.kind();
    let m = spec(kind);
    let id = try_id_of(kind, msg.node).ok_or(EncodeError::BadNode {
        kind,
        node: msg.node,
    })?;
    if msg.counter > 15 {
        return Err(EncodeError::BadCounter {
            kind,
            counter: msg.counter,
        });
    }
    let values = values_of(&msg.payload);
    let mut word = 0u64;
    for (s, &v) in m.signals.iter().zip(values.iter()) {
        let raw = match s.role {
            SignalRole::Counter => i64::from(msg.counter),
            SignalRole::Crc => continue,
            SignalRole::Value | SignalRole::Flag | SignalRole::Enum => {
                s.to_raw(v).ok_or(EncodeError::OutOfRange {
                    kind,
                    signal: s.name,
                    value: v,
                    min: s.min,
                    max: s.max,
                    unit: s.unit,
                })?
            }
        };
        put_raw(&mut word, s, raw);
    }
    let mut bytes = word.to_le_bytes();
    let crc_at = m.crc_byte();
    bytes[crc_at] = frame_crc(id, &bytes[..crc_at]);
    // id ≤ 0x7FF and dlc ≤ 8 are table invariants (tested), so this cannot fail; map the
    // impossible error to a range error instead of panicking.
    CanFrame::new(id, &bytes[..usize::from(m.dlc)]).map_err(|_| EncodeError::BadNode {
        kind,
        node: msg.node,
    })
}

/// Decodes a frame (stateless: counters are not checked here, see [`crate::rx::Receiver`]).
///
/// Checks in order: the id belongs to the protocol ([`DecodeError::UnknownId`]) with a valid
/// node ([`DecodeError::BadNode`]), the DLC ([`DecodeError::WrongDlc`]), the CRC
/// ([`DecodeError::BadCrc`]), each value's declared range ([`DecodeError::OutOfRange`]) and
/// enum values ([`DecodeError::BadEnum`]). Never panics, whatever the bytes.
pub fn decode(frame: &CanFrame) -> Result<Message, DecodeError> {
    let id = frame.id();
    let (kind, node) = classify_any_node(id).ok_or(DecodeError::UnknownId { id })?;
    let m = spec(kind);
    if m.per_node && node == 0 {
        return Err(DecodeError::BadNode { kind, id });
    }
    let data = frame.data();
    if data.len() != usize::from(m.dlc) {
        return Err(DecodeError::WrongDlc {
            kind,
            id,
            expected: m.dlc,
            // len ≤ 8 by construction.
            got: data.len() as u8,
        });
    }
    let crc_at = m.crc_byte();
    let computed = frame_crc(id, &data[..crc_at]);
    if computed != data[crc_at] {
        return Err(DecodeError::BadCrc {
            kind,
            id,
            computed,
            received: data[crc_at],
        });
    }
    let mut buf = [0u8; 8];
    buf[..data.len()].copy_from_slice(data);
    let word = u64::from_le_bytes(buf);
    let mut raws = [0i64; MAX_SIGNALS];
    let mut phys = [0.0f64; MAX_SIGNALS];
    let mut counter = 0u8;
    for (i, s) in m.signals.iter().enumerate().take(MAX_SIGNALS) {
        let raw = get_raw(word, s);
        match s.role {
            SignalRole::Counter => counter = (raw & 0x0F) as u8,
            SignalRole::Crc | SignalRole::Flag => {}
            SignalRole::Enum => {
                if raw < s.raw_min() || raw > s.raw_max() {
                    return Err(DecodeError::BadEnum {
                        kind,
                        id,
                        signal: s.name,
                        raw,
                    });
                }
            }
            SignalRole::Value => {
                if raw < s.raw_min() || raw > s.raw_max() {
                    return Err(DecodeError::OutOfRange {
                        kind,
                        id,
                        signal: s.name,
                        raw,
                        min_raw: s.raw_min(),
                        max_raw: s.raw_max(),
                    });
                }
            }
        }
        raws[i] = raw;
        phys[i] = s.to_physical(raw);
    }
    Ok(Message {
        node,
        counter,
        payload: payload_from(kind, &raws, &phys),
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::protocol::MESSAGES;

    #[test]
    fn max_signals_bound_holds() {
        for m in MESSAGES.iter() {
            assert!(m.signals.len() <= MAX_SIGNALS, "{}", m.name);
        }
    }

    #[test]
    fn raw_field_helpers_sign_extend() {
        let s = crate::protocol::spec(MessageKind::FeedbackB)
            .signal("drive_current")
            .expect("signal");
        let mut w = 0u64;
        put_raw(&mut w, s, -3);
        assert_eq!(w, 0xFD << 32);
        assert_eq!(get_raw(w, s), -3);
    }

    #[test]
    fn fault_names_are_distinct() {
        let codes = [
            FAULT_NONE,
            FAULT_OVERCURRENT,
            FAULT_OVERTEMPERATURE,
            FAULT_ENCODER,
            FAULT_WATCHDOG,
            FAULT_UNDERVOLTAGE,
            FAULT_OVERVOLTAGE,
            FAULT_LIMIT,
            FAULT_DRIVER,
            FAULT_INTERNAL,
        ];
        let names: std::collections::HashSet<_> = codes.iter().map(|&c| fault_name(c)).collect();
        assert_eq!(names.len(), codes.len());
        assert!(!names.contains("unknown"));
        assert_eq!(fault_name(0x42), "unknown");
    }
}
