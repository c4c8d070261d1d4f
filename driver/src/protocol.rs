//! The wheel-module protocol, declared once, as data.
//!
//! [`MESSAGES`] is the single source of truth: the codec ([`crate::codec`]) packs and unpacks
//! signals by walking it, the DBC export ([`crate::dbc`]), `docs/protocol.md`
//! ([`crate::dbc::protocol_markdown`]) and the bus-load calculator ([`crate::busload`]) are
//! generated from it.
//!
//! Conventions (classic CAN 2.0A, 11-bit ids, 1 Mbit/s, little-endian / Intel byte order):
//! - Node `n` (1..=[`MAX_NODE`]) is one wheel module; per-node ids are `base_id + n`.
//! - A signal's `start_bit` is the position of its least significant bit when the payload is
//!   read as one little-endian unsigned integer (bit 0 = LSB of byte 0, bit 8 = LSB of byte 1,
//!   ...). This is exactly DBC's `start|length@1` notation.
//! - Physical value = raw · scale + offset. The declared `[min, max]` is the accepted physical
//!   range in both directions: encoding a value outside it is an error, decoding a raw value
//!   outside `[round((min−offset)/scale), round((max−offset)/scale)]` is an error.
//! - Every frame carries a 4-bit rolling counter and ends with a CRC-8 SAE J1850 byte computed
//!   over `[id & 0xFF, id >> 8, all payload bytes before the CRC]` ([`crate::crc::frame_crc`]).
//! - Reserved bits are sent as 0 and ignored on receipt (they are covered by the CRC, so a
//!   future protocol revision can use them without breaking old receivers).

use std::f64::consts::PI;

/// Highest wheel-module node number (node ids are 4 bits; node 0 is not a module).
pub const MAX_NODE: u8 = 15;

/// Default node numbers of a 4-wheel platform.
pub const DEFAULT_NODES: [u8; 4] = [1, 2, 3, 4];

/// The wheel modules' setpoint watchdog (s): a module that received no valid SETPOINT for
/// this long stops its motors and latches `FAULT_WATCHDOG` (the protocol's safety rule; the
/// simulated firmware's default). The control rate must leave room for lost SETPOINTs inside
/// it (`rollbase_control::model::platform::MIN_CYCLE_HZ`).
pub const SETPOINT_WATCHDOG_S: f64 = 0.050;

/// Nominal bit rate of the bus, bit/s.
pub const BITRATE: u32 = 1_000_000;

/// Which message a frame is.
#[derive(Copy, Clone, Debug, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub enum MessageKind {
    /// Cycle start / controller heartbeat.
    Sync,
    /// Wheel speed and steer rate setpoint for one module.
    Setpoint,
    /// Steer angle, wheel speed, steer rate feedback.
    FeedbackA,
    /// Leg extension, leg rate, motor currents feedback.
    FeedbackB,
    /// Module state, fault code, temperature, bus voltage.
    Status,
}

impl MessageKind {
    /// All kinds, in table order.
    pub const ALL: [MessageKind; 5] = [
        MessageKind::Sync,
        MessageKind::Setpoint,
        MessageKind::FeedbackA,
        MessageKind::FeedbackB,
        MessageKind::Status,
    ];

    /// Index of this kind in [`MESSAGES`] and [`MessageKind::ALL`].
    pub const fn index(self) -> usize {
        match self {
            MessageKind::Sync => 0,
            MessageKind::Setpoint => 1,
            MessageKind::FeedbackA => 2,
            MessageKind::FeedbackB => 3,
            MessageKind::Status => 4,
        }
    }
}

impl std::fmt::Display for MessageKind {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(spec(*self).name)
    }
}

/// Who sends a message to whom.
#[derive(Copy, Clone, Debug, PartialEq, Eq, Hash)]
pub enum Direction {
    /// From the controller to one wheel module.
    ControllerToModule,
    /// From a wheel module to the controller.
    ModuleToController,
    /// From the controller to every module (broadcast).
    ControllerToAll,
}

/// What a signal means to the codec.
#[derive(Copy, Clone, Debug, PartialEq, Eq, Hash)]
pub enum SignalRole {
    /// A scaled physical value.
    Value,
    /// A single-bit boolean flag.
    Flag,
    /// An enumeration; raw values outside `[min, max]` are a bad enum value.
    Enum,
    /// The 4-bit rolling counter.
    Counter,
    /// The CRC-8 byte (always the last payload byte).
    Crc,
}

/// One signal of a message.
#[derive(Copy, Clone, Debug, PartialEq)]
pub struct SignalSpec {
    /// Signal name (snake_case, also used in the DBC).
    pub name: &'static str,
    /// Position of the least significant bit (little-endian numbering).
    pub start_bit: u8,
    /// Width in bits (1..=16).
    pub length: u8,
    /// Two's complement signed raw value.
    pub signed: bool,
    /// Physical = raw · scale + offset.
    pub scale: f64,
    /// Physical = raw · scale + offset.
    pub offset: f64,
    /// SI unit of the physical value ("" for dimensionless).
    pub unit: &'static str,
    /// Lowest accepted physical value.
    pub min: f64,
    /// Highest accepted physical value.
    pub max: f64,
    /// How the codec treats the signal.
    pub role: SignalRole,
    /// One-line description.
    pub doc: &'static str,
}

impl SignalSpec {
    /// Lowest raw value the bit field can hold.
    pub fn wire_raw_min(&self) -> i64 {
        if self.signed {
            -(1i64 << (self.length - 1))
        } else {
            0
        }
    }

    /// Highest raw value the bit field can hold.
    pub fn wire_raw_max(&self) -> i64 {
        if self.signed {
            (1i64 << (self.length - 1)) - 1
        } else {
            (1i64 << self.length) - 1
        }
    }

    /// Lowest accepted raw value: `round((min − offset) / scale)`.
    pub fn raw_min(&self) -> i64 {
        ((self.min - self.offset) / self.scale).round() as i64
    }

    /// Highest accepted raw value: `round((max − offset) / scale)`.
    pub fn raw_max(&self) -> i64 {
        ((self.max - self.offset) / self.scale).round() as i64
    }

    /// Physical value of a raw value.
    pub fn to_physical(&self, raw: i64) -> f64 {
        raw as f64 * self.scale + self.offset
    }

    /// Raw value (rounded to nearest, ties away from zero) of a physical value, or `None`
    /// when the value is not finite or its raw value lies outside
    /// [`raw_min`](Self::raw_min)..=[`raw_max`](Self::raw_max).
    pub fn to_raw(&self, physical: f64) -> Option<i64> {
        if !physical.is_finite() {
            return None;
        }
        let raw = ((physical - self.offset) / self.scale).round();
        // Compare as f64 first so that huge values cannot saturate into range.
        if raw < self.raw_min() as f64 || raw > self.raw_max() as f64 {
            return None;
        }
        Some(raw as i64)
    }

    /// Half a quantization step: the worst-case rounding error of encode→decode.
    pub fn half_step(&self) -> f64 {
        self.scale.abs() / 2.0
    }
}

/// One message of the protocol.
#[derive(Copy, Clone, Debug, PartialEq)]
pub struct MessageSpec {
    /// Which message.
    pub kind: MessageKind,
    /// Upper-case name (as in the DBC).
    pub name: &'static str,
    /// Identifier (SYNC) or identifier base (per-node messages: id = base + node).
    pub base_id: u16,
    /// True when the id is `base_id + node`.
    pub per_node: bool,
    /// Data length code (payload bytes).
    pub dlc: u8,
    /// Sender and receiver.
    pub direction: Direction,
    /// Nominal period in milliseconds (`None` for event-only messages).
    pub period_ms: Option<f64>,
    /// Signals, ordered by start bit.
    pub signals: &'static [SignalSpec],
    /// Description.
    pub doc: &'static str,
}

impl MessageSpec {
    /// The signal called `name`.
    pub fn signal(&self, name: &str) -> Option<&'static SignalSpec> {
        self.signals.iter().find(|s| s.name == name)
    }

    /// Identifier of this message for `node` (ignored for SYNC); see [`id_of`].
    pub fn id(&self, node: u8) -> u16 {
        id_of(self.kind, node)
    }

    /// Index of the CRC byte (the last payload byte).
    pub fn crc_byte(&self) -> usize {
        usize::from(self.dlc) - 1
    }
}

#[expect(
    clippy::too_many_arguments,
    reason = "one argument per column of the signal table, read like a DBC SG_ line"
)]
const fn value(
    name: &'static str,
    start_bit: u8,
    length: u8,
    signed: bool,
    scale: f64,
    offset: f64,
    unit: &'static str,
    min: f64,
    max: f64,
    doc: &'static str,
) -> SignalSpec {
    SignalSpec {
        name,
        start_bit,
        length,
        signed,
        scale,
        offset,
        unit,
        min,
        max,
        role: SignalRole::Value,
        doc,
    }
}

const fn flag(name: &'static str, start_bit: u8, doc: &'static str) -> SignalSpec {
    SignalSpec {
        name,
        start_bit,
        length: 1,
        signed: false,
        scale: 1.0,
        offset: 0.0,
        unit: "",
        min: 0.0,
        max: 1.0,
        role: SignalRole::Flag,
        doc,
    }
}

const fn counter(start_bit: u8) -> SignalSpec {
    SignalSpec {
        name: "counter",
        start_bit,
        length: 4,
        signed: false,
        scale: 1.0,
        offset: 0.0,
        unit: "",
        min: 0.0,
        max: 15.0,
        role: SignalRole::Counter,
        doc: "rolling counter, +1 mod 16 per frame of this id",
    }
}

const fn crc(start_bit: u8) -> SignalSpec {
    SignalSpec {
        name: "crc",
        start_bit,
        length: 8,
        signed: false,
        scale: 1.0,
        offset: 0.0,
        unit: "",
        min: 0.0,
        max: 255.0,
        role: SignalRole::Crc,
        doc: "CRC-8 SAE J1850 over [id & 0xFF, id >> 8, preceding payload bytes]",
    }
}

/// Declared wheel speed range, rad/s (wire range ±32.767 rad/s). Covers the ±20 rad/s the
/// platform needs (seed 001: 13.9 rad/s maximum wheel spin for a 2.1 rad/s platform turn).
pub const WHEEL_SPEED_MAX: f64 = 30.0;
/// Declared steer rate range, rad/s (wire range ±32.767 rad/s).
pub const STEER_RATE_MAX: f64 = 15.0;
/// Declared leg extension upper limit, m.
pub const LEG_EXTENSION_MAX: f64 = 0.65;
/// Declared leg rate range, m/s (wire range ±3.2767 m/s).
pub const LEG_RATE_MAX: f64 = 3.0;
/// Declared motor current range, A (wire range −32..31.75 A).
pub const CURRENT_MAX: f64 = 30.0;

static SYNC_SIGNALS: [SignalSpec; 3] = [
    value(
        "cycle",
        0,
        16,
        false,
        1.0,
        0.0,
        "",
        0.0,
        65535.0,
        "controller cycle number, wraps at 65536",
    ),
    counter(16),
    crc(24),
];

static SETPOINT_SIGNALS: [SignalSpec; 7] = [
    value(
        "wheel_speed",
        0,
        16,
        true,
        0.001,
        0.0,
        "rad/s",
        -WHEEL_SPEED_MAX,
        WHEEL_SPEED_MAX,
        "commanded wheel spin rate",
    ),
    value(
        "steer_rate",
        16,
        16,
        true,
        0.001,
        0.0,
        "rad/s",
        -STEER_RATE_MAX,
        STEER_RATE_MAX,
        "commanded steering rate",
    ),
    flag(
        "enable",
        32,
        "1 = motors enabled; 0 = disable (coast to stop)",
    ),
    flag(
        "brake",
        33,
        "1 = brake: decelerate both motors to zero at the torque limit",
    ),
    flag("fault_reset", 34, "1 = clear a latched fault"),
    counter(36),
    crc(40),
];

static FEEDBACK_A_SIGNALS: [SignalSpec; 5] = [
    value(
        "steer_angle",
        0,
        16,
        true,
        1e-4,
        0.0,
        "rad",
        -PI,
        PI,
        "absolute steering angle, wrapped to [-pi, pi]",
    ),
    value(
        "wheel_speed",
        16,
        16,
        true,
        0.001,
        0.0,
        "rad/s",
        -WHEEL_SPEED_MAX,
        WHEEL_SPEED_MAX,
        "measured wheel spin rate",
    ),
    value(
        "steer_rate",
        32,
        16,
        true,
        0.001,
        0.0,
        "rad/s",
        -STEER_RATE_MAX,
        STEER_RATE_MAX,
        "measured steering rate",
    ),
    counter(48),
    crc(56),
];

static FEEDBACK_B_SIGNALS: [SignalSpec; 6] = [
    value(
        "leg_extension",
        0,
        16,
        false,
        1e-5,
        0.0,
        "m",
        0.0,
        LEG_EXTENSION_MAX,
        "leg extension lambda along the leg direction",
    ),
    value(
        "leg_rate",
        16,
        16,
        true,
        1e-4,
        0.0,
        "m/s",
        -LEG_RATE_MAX,
        LEG_RATE_MAX,
        "leg extension rate",
    ),
    value(
        "drive_current",
        32,
        8,
        true,
        0.25,
        0.0,
        "A",
        -CURRENT_MAX,
        CURRENT_MAX,
        "drive motor current",
    ),
    value(
        "steer_current",
        40,
        8,
        true,
        0.25,
        0.0,
        "A",
        -CURRENT_MAX,
        CURRENT_MAX,
        "steering motor current",
    ),
    counter(48),
    crc(56),
];

static STATUS_SIGNALS: [SignalSpec; 6] = [
    SignalSpec {
        name: "state",
        start_bit: 0,
        length: 4,
        signed: false,
        scale: 1.0,
        offset: 0.0,
        unit: "",
        min: 0.0,
        max: 3.0,
        role: SignalRole::Enum,
        doc: "module state: 0 boot, 1 ready, 2 enabled, 3 fault",
    },
    counter(4),
    value(
        "fault_code",
        8,
        8,
        false,
        1.0,
        0.0,
        "",
        0.0,
        255.0,
        "latched fault code (codec::FAULT_*), 0 = none",
    ),
    value(
        "temperature",
        16,
        8,
        false,
        1.0,
        -40.0,
        "degC",
        -40.0,
        215.0,
        "hottest motor/driver temperature",
    ),
    value(
        "bus_voltage",
        24,
        16,
        false,
        0.01,
        0.0,
        "V",
        0.0,
        100.0,
        "DC link voltage",
    ),
    crc(40),
];

/// Every message of the protocol, indexed by [`MessageKind::index`].
pub static MESSAGES: [MessageSpec; 5] = [
    MessageSpec {
        kind: MessageKind::Sync,
        name: "SYNC",
        base_id: 0x080,
        per_node: false,
        dlc: 4,
        direction: Direction::ControllerToAll,
        period_ms: Some(4.0),
        signals: &SYNC_SIGNALS,
        doc: "Starts a control cycle; every module answers with FEEDBACK_A and FEEDBACK_B. \
              Doubles as the controller heartbeat.",
    },
    MessageSpec {
        kind: MessageKind::Setpoint,
        name: "SETPOINT",
        base_id: 0x200,
        per_node: true,
        dlc: 6,
        direction: Direction::ControllerToModule,
        period_ms: Some(4.0),
        signals: &SETPOINT_SIGNALS,
        doc: "Velocity setpoints for one wheel module. A module stops its motors when no valid \
              SETPOINT arrived for 50 ms (setpoint watchdog).",
    },
    MessageSpec {
        kind: MessageKind::FeedbackA,
        name: "FEEDBACK_A",
        base_id: 0x180,
        per_node: true,
        dlc: 8,
        direction: Direction::ModuleToController,
        period_ms: Some(4.0),
        signals: &FEEDBACK_A_SIGNALS,
        doc: "Steering and wheel encoder feedback, sent in answer to each SYNC.",
    },
    MessageSpec {
        kind: MessageKind::FeedbackB,
        name: "FEEDBACK_B",
        base_id: 0x280,
        per_node: true,
        dlc: 8,
        direction: Direction::ModuleToController,
        period_ms: Some(4.0),
        signals: &FEEDBACK_B_SIGNALS,
        doc: "Leg and motor-current feedback, sent in answer to each SYNC.",
    },
    MessageSpec {
        kind: MessageKind::Status,
        name: "STATUS",
        base_id: 0x700,
        per_node: true,
        dlc: 6,
        direction: Direction::ModuleToController,
        period_ms: Some(100.0),
        signals: &STATUS_SIGNALS,
        doc: "Module state, sent at 10 Hz and immediately when the state or fault code changes.",
    },
];

/// The table entry of `kind`.
pub fn spec(kind: MessageKind) -> &'static MessageSpec {
    &MESSAGES[kind.index()]
}

/// Which message and node an identifier belongs to.
///
/// Returns `(kind, node)` with `node` in 1..=[`MAX_NODE`] for per-node messages and 0 for
/// SYNC; `None` for every other id (including the per-node base ids, whose node 0 is not a
/// module).
pub fn classify(id: u16) -> Option<(MessageKind, u8)> {
    match classify_any_node(id) {
        Some((kind, node)) if !spec(kind).per_node || node != 0 => Some((kind, node)),
        _ => None,
    }
}

/// Like [`classify`] but also maps the per-node base ids (node 0).
pub(crate) fn classify_any_node(id: u16) -> Option<(MessageKind, u8)> {
    for m in MESSAGES.iter() {
        if m.per_node {
            if id >= m.base_id && id <= m.base_id + u16::from(MAX_NODE) {
                // id - base <= 15 fits u8.
                return Some((m.kind, (id - m.base_id) as u8));
            }
        } else if id == m.base_id {
            return Some((m.kind, 0));
        }
    }
    None
}

/// Identifier of `kind` for `node`.
///
/// SYNC ignores `node`. For per-node messages `node` must be 1..=[`MAX_NODE`]; any other
/// value yields the block's base id (node 0), which no module accepts and
/// [`crate::codec::decode`] rejects as a bad node, so a wrong node can never address another
/// module. Use [`try_id_of`] to detect invalid nodes; [`crate::codec::encode`] validates them.
pub fn id_of(kind: MessageKind, node: u8) -> u16 {
    let m = spec(kind);
    if m.per_node && (1..=MAX_NODE).contains(&node) {
        m.base_id + u16::from(node)
    } else {
        m.base_id
    }
}

/// Identifier of `kind` for `node`, or `None` when `node` is not valid for `kind`
/// (per-node messages need 1..=[`MAX_NODE`], SYNC needs 0).
pub fn try_id_of(kind: MessageKind, node: u8) -> Option<u16> {
    let m = spec(kind);
    let ok = if m.per_node {
        (1..=MAX_NODE).contains(&node)
    } else {
        node == 0
    };
    ok.then(|| id_of(kind, node))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn table_is_indexed_by_kind() {
        for k in MessageKind::ALL {
            assert_eq!(spec(k).kind, k);
        }
    }

    #[test]
    fn signals_fit_dlc_do_not_overlap_and_crc_is_last_byte() {
        for m in MESSAGES.iter() {
            let mut used = 0u64;
            let mut counters = 0;
            let mut crcs = 0;
            for s in m.signals {
                assert!(s.length >= 1 && s.length <= 16, "{}.{}", m.name, s.name);
                let end = u32::from(s.start_bit) + u32::from(s.length);
                assert!(
                    end <= u32::from(m.dlc) * 8,
                    "{}.{} beyond DLC",
                    m.name,
                    s.name
                );
                let mask = ((1u64 << s.length) - 1) << s.start_bit;
                assert_eq!(used & mask, 0, "{}.{} overlaps", m.name, s.name);
                used |= mask;
                match s.role {
                    SignalRole::Counter => counters += 1,
                    SignalRole::Crc => {
                        crcs += 1;
                        assert_eq!(usize::from(s.start_bit), m.crc_byte() * 8);
                        assert_eq!(s.length, 8);
                    }
                    _ => {}
                }
            }
            assert_eq!((counters, crcs), (1, 1), "{} counter/crc", m.name);
        }
    }

    #[test]
    fn declared_ranges_fit_wire_and_cover_platform() {
        for m in MESSAGES.iter() {
            for s in m.signals {
                assert!(s.raw_min() >= s.wire_raw_min(), "{}.{}", m.name, s.name);
                assert!(s.raw_max() <= s.wire_raw_max(), "{}.{}", m.name, s.name);
                assert!(s.min < s.max);
            }
        }
        let sp = spec(MessageKind::Setpoint);
        let ws = sp.signal("wheel_speed").expect("wheel_speed");
        assert!(ws.min <= -20.0 && ws.max >= 20.0);
        let sr = sp.signal("steer_rate").expect("steer_rate");
        assert!(sr.min <= -10.0 && sr.max >= 10.0);
        let fa = spec(MessageKind::FeedbackA);
        let sa = fa.signal("steer_angle").expect("steer_angle");
        assert_eq!((sa.raw_min(), sa.raw_max()), (-31416, 31416));
        let fb = spec(MessageKind::FeedbackB);
        let le = fb.signal("leg_extension").expect("leg_extension");
        assert_eq!((le.raw_min(), le.raw_max()), (0, 65000));
    }

    #[test]
    fn classify_and_id_of_agree() {
        assert_eq!(classify(0x080), Some((MessageKind::Sync, 0)));
        assert_eq!(classify(0x181), Some((MessageKind::FeedbackA, 1)));
        assert_eq!(classify(0x20F), Some((MessageKind::Setpoint, 15)));
        assert_eq!(classify(0x284), Some((MessageKind::FeedbackB, 4)));
        assert_eq!(classify(0x703), Some((MessageKind::Status, 3)));
        for id in [
            0x000, 0x081, 0x180, 0x190, 0x200, 0x210, 0x280, 0x700, 0x710, 0x7FF,
        ] {
            assert_eq!(classify(id), None, "id 0x{id:X}");
        }
        for k in MessageKind::ALL {
            let nodes: &[u8] = if spec(k).per_node { &[1, 7, 15] } else { &[0] };
            for &n in nodes {
                assert_eq!(classify(id_of(k, n)), Some((k, n)));
                assert_eq!(try_id_of(k, n), Some(id_of(k, n)));
            }
        }
        assert_eq!(
            id_of(MessageKind::Setpoint, 17),
            0x200,
            "never another module's id"
        );
        assert_eq!(id_of(MessageKind::Status, 0), 0x700);
        assert_eq!(try_id_of(MessageKind::Setpoint, 0), None);
        assert_eq!(try_id_of(MessageKind::Setpoint, 16), None);
        assert_eq!(try_id_of(MessageKind::Sync, 1), None);
    }

    #[test]
    fn id_blocks_do_not_overlap() {
        let mut seen = std::collections::HashSet::new();
        for k in MessageKind::ALL {
            for n in 0..=MAX_NODE {
                if let Some(id) = try_id_of(k, n) {
                    assert!(seen.insert(id), "duplicate id 0x{id:X}");
                }
            }
        }
    }
}
