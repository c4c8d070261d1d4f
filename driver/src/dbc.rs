//! Artefacts generated from the message table: a DBC file and `docs/protocol.md`.
//!
//! Both are pure functions of [`crate::protocol::MESSAGES`] (and of the codec for the example
//! frames), so they cannot drift from the code; a test compares the committed
//! `docs/protocol.md` with [`protocol_markdown`].

use std::fmt::Write as _;

use crate::busload::{bus_load, frame_bits, BusLoadConfig};
use crate::codec::{
    encode, FeedbackA, FeedbackB, Message, ModuleState, Payload, Setpoint, SetpointFlags, Status,
    Sync, FAULT_OVERTEMPERATURE,
};
use crate::protocol::{
    Direction, MessageSpec, SignalRole, SignalSpec, DEFAULT_NODES, MAX_NODE, MESSAGES,
};

const CONTROLLER: &str = "Controller";

fn module_name(node: u8) -> String {
    format!("Module{node}")
}

fn dbc_name(m: &MessageSpec, node: u8) -> String {
    if m.per_node {
        format!("{}_{node}", m.name)
    } else {
        m.name.to_string()
    }
}

/// Escapes a DBC string literal (double quotes are not allowed inside).
fn dbc_str(s: &str) -> String {
    s.replace('"', "'")
}

/// DBC for the default nodes 1..=4 (see [`dbc_for_nodes`]).
pub fn dbc() -> String {
    dbc_for_nodes(&DEFAULT_NODES)
}

/// DBC with one `BO_` per per-node message per node in `nodes` (values outside 1..=15 and
/// duplicates are skipped), plus SYNC. Signals are little-endian (`@1+` / `@1-`) with factor,
/// offset, `[min|max]` and unit from the table, including the counter and CRC signals;
/// message and signal comments, `GenMsgCycleTime` attributes and `VAL_` names for the
/// module state.
pub fn dbc_for_nodes(nodes: &[u8]) -> String {
    let mut ns: Vec<u8> = nodes
        .iter()
        .copied()
        .filter(|n| (1..=MAX_NODE).contains(n))
        .collect();
    ns.sort_unstable();
    ns.dedup();
    let modules: Vec<String> = ns.iter().map(|&n| module_name(n)).collect();
    let all_modules = if modules.is_empty() {
        "Vector__XXX".to_string()
    } else {
        modules.join(",")
    };

    let mut s = String::new();
    let _ = writeln!(s, "VERSION \"rollbase native wheel-module protocol\"");
    s.push_str("\n\nNS_ :\n\tCM_\n\tBA_DEF_\n\tBA_\n\tVAL_\n\tBA_DEF_DEF_\n\nBS_:\n\n");
    let _ = writeln!(s, "BU_: {CONTROLLER} {}", modules.join(" "));
    s.push('\n');

    // (id, message spec, node) for every frame in the file.
    let mut frames: Vec<(u16, &MessageSpec, u8)> = Vec::new();
    for m in MESSAGES.iter() {
        if m.per_node {
            for &n in &ns {
                frames.push((m.id(n), m, n));
            }
        } else {
            frames.push((m.base_id, m, 0));
        }
    }

    for &(id, m, n) in &frames {
        let (tx, rx) = match m.direction {
            Direction::ControllerToAll => (CONTROLLER.to_string(), all_modules.clone()),
            Direction::ControllerToModule => (CONTROLLER.to_string(), module_name(n)),
            Direction::ModuleToController => (module_name(n), CONTROLLER.to_string()),
        };
        let _ = writeln!(s, "BO_ {id} {}: {} {tx}", dbc_name(m, n), m.dlc);
        for sig in m.signals {
            let _ = writeln!(
                s,
                " SG_ {} : {}|{}@1{} ({},{}) [{}|{}] \"{}\" {rx}",
                sig.name,
                sig.start_bit,
                sig.length,
                if sig.signed { '-' } else { '+' },
                sig.scale,
                sig.offset,
                sig.min,
                sig.max,
                sig.unit
            );
        }
        s.push('\n');
    }

    for &(id, m, _) in &frames {
        let _ = writeln!(s, "CM_ BO_ {id} \"{}\";", dbc_str(m.doc));
        for sig in m.signals {
            let _ = writeln!(s, "CM_ SG_ {id} {} \"{}\";", sig.name, dbc_str(sig.doc));
        }
    }
    s.push_str("BA_DEF_ BO_ \"GenMsgCycleTime\" INT 0 65535;\n");
    s.push_str("BA_DEF_DEF_ \"GenMsgCycleTime\" 0;\n");
    for &(id, m, _) in &frames {
        if let Some(p) = m.period_ms {
            let _ = writeln!(s, "BA_ \"GenMsgCycleTime\" BO_ {id} {};", p.round() as i64);
        }
    }
    for &(id, m, _) in &frames {
        for sig in m.signals.iter().filter(|g| g.role == SignalRole::Enum) {
            let _ = write!(s, "VAL_ {id} {}", sig.name);
            for raw in sig.raw_min()..=sig.raw_max() {
                if let Some(st) = u8::try_from(raw).ok().and_then(ModuleState::from_raw) {
                    let _ = write!(s, " {raw} \"{}\"", st.name());
                }
            }
            s.push_str(" ;\n");
        }
    }
    s
}

fn direction_text(d: Direction) -> &'static str {
    match d {
        Direction::ControllerToModule => "controller → module",
        Direction::ModuleToController => "module → controller",
        Direction::ControllerToAll => "controller → all",
    }
}

fn type_text(sig: &SignalSpec) -> String {
    match sig.role {
        SignalRole::Flag => "bit".to_string(),
        _ => format!("{}{}", if sig.signed { 'i' } else { 'u' }, sig.length),
    }
}

/// Bit map of a message: for each byte, which signal owns bits 7..0.
fn layout_rows(m: &MessageSpec) -> Vec<String> {
    let owner = |bit: u8| -> &'static str {
        m.signals
            .iter()
            .find(|s| bit >= s.start_bit && bit < s.start_bit + s.length)
            .map_or("reserved", |s| s.name)
    };
    let mut rows = Vec::new();
    for byte in 0..m.dlc {
        // Group consecutive bits (MSB first) with the same owner.
        let mut parts: Vec<String> = Vec::new();
        let mut bit = 8 * byte + 7;
        loop {
            let name = owner(bit);
            let hi = bit;
            while bit > 8 * byte && owner(bit - 1) == name {
                bit -= 1;
            }
            let lo = bit;
            let sig = m.signals.iter().find(|s| s.name == name);
            let label = match sig {
                Some(s)
                    if s.length > 8 || s.start_bit != lo || s.start_bit + s.length - 1 != hi =>
                {
                    format!("{name}[{}..{}]", hi - s.start_bit, lo - s.start_bit)
                }
                _ => name.to_string(),
            };
            parts.push(if hi == lo {
                format!("b{}: {label}", hi % 8)
            } else {
                format!("b{}–{}: {label}", hi % 8, lo % 8)
            });
            if bit == 8 * byte {
                break;
            }
            bit -= 1;
        }
        rows.push(format!("| {byte} | {} |", parts.join(", ")));
    }
    rows
}

fn hex_bytes(data: &[u8]) -> String {
    data.iter()
        .map(|b| format!("{b:02X}"))
        .collect::<Vec<_>>()
        .join(" ")
}

/// Example messages shown in the document (the same as the golden-vector tests).
fn examples() -> [(&'static str, Message); 5] {
    [
        (
            "cycle 0x1234, counter 5",
            Message {
                node: 0,
                counter: 5,
                payload: Payload::Sync(Sync { cycle: 0x1234 }),
            },
        ),
        (
            "node 1, wheel 1.5 rad/s, steer −0.25 rad/s, enable + fault_reset, counter 3",
            Message {
                node: 1,
                counter: 3,
                payload: Payload::Setpoint(Setpoint {
                    wheel_speed: 1.5,
                    steer_rate: -0.25,
                    flags: SetpointFlags {
                        enable: true,
                        brake: false,
                        fault_reset: true,
                    },
                }),
            },
        ),
        (
            "node 2, steer −π/2 rad, wheel 13.9 rad/s, steer rate −10 rad/s, counter 15",
            Message {
                node: 2,
                counter: 15,
                payload: Payload::FeedbackA(FeedbackA {
                    steer_angle: -std::f64::consts::FRAC_PI_2,
                    wheel_speed: 13.9,
                    steer_rate: -10.0,
                }),
            },
        ),
        (
            "node 4, leg 0.465 m, leg rate −0.05 m/s, drive 12.5 A, steer −3.25 A, counter 0",
            Message {
                node: 4,
                counter: 0,
                payload: Payload::FeedbackB(FeedbackB {
                    leg_extension: 0.465,
                    leg_rate: -0.05,
                    drive_current: 12.5,
                    steer_current: -3.25,
                }),
            },
        ),
        (
            "node 3, state fault, fault code 2 (overtemperature), 85 °C, 48 V, counter 9",
            Message {
                node: 3,
                counter: 9,
                payload: Payload::Status(Status {
                    state: ModuleState::Fault,
                    fault_code: FAULT_OVERTEMPERATURE,
                    temperature: 85.0,
                    bus_voltage: 48.0,
                }),
            },
        ),
    ]
}

/// `docs/protocol.md`, generated from the table.
pub fn protocol_markdown() -> String {
    let mut s = String::new();
    s.push_str("# rollbase wheel-module CAN protocol (native profile)\n\n");
    s.push_str(
        "<!-- Generated from driver/src/protocol.rs by rollbase_driver::dbc::protocol_markdown(). \
         Do not edit: regenerate with `cargo run -- protocol-doc > docs/protocol.md` or \
         `UPDATE_DOCS=1 cargo test -p rollbase-driver --test protocol_doc`. -->\n\n",
    );
    s.push_str(
        "Classic CAN 2.0A (11-bit ids), 1 Mbit/s, little-endian (Intel) signals. Node `n` = 1..15 \
         is one wheel module; per-node ids are `base + n`.\n\n\
         - **Bit numbering**: a signal's start bit is the position of its least significant bit \
         when the payload is read as one little-endian integer (bit 0 = LSB of byte 0, bit 8 = \
         LSB of byte 1, …), as in DBC `start|length@1`.\n\
         - **Scaling**: physical = raw · scale + offset, SI units. Encoding rounds to the nearest \
         step (ties away from zero); a value outside `[min, max]` is an encode error (never \
         wrapped or clamped). A received raw value outside `[round((min−offset)/scale), \
         round((max−offset)/scale)]` is a decode error.\n\
         - **Rolling counter**: every frame carries a 4-bit counter, +1 mod 16 per frame of the \
         same id. The receiver accepts the first frame of a stream, rejects a repeated counter, \
         and reports a jump with `lost = (got − last − 1) mod 16` and re-synchronises.\n\
         - **CRC**: the last byte is CRC-8 SAE J1850 (poly 0x1D, init 0xFF, xorout 0xFF, not \
         reflected; check value of \"123456789\" = 0x4B) over `[id & 0xFF, id >> 8, payload \
         bytes before the CRC]`.\n\
         - **Reserved bits** are sent as 0 and ignored on receipt.\n\
         - **Watchdogs**: a module stops its motors when no valid SETPOINT arrived for 50 ms; \
         the controller stops the platform when feedback is stale.\n\n",
    );

    s.push_str("## Messages\n\n");
    s.push_str("| message | id | DLC | direction | period | description |\n");
    s.push_str("|---|---|---|---|---|---|\n");
    for m in MESSAGES.iter() {
        let id = if m.per_node {
            format!("0x{:03X} + n", m.base_id)
        } else {
            format!("0x{:03X}", m.base_id)
        };
        let period = m
            .period_ms
            .map_or_else(|| "event".to_string(), |p| format!("{p} ms"));
        let _ = writeln!(
            s,
            "| {} | {id} | {} | {} | {period} | {} |",
            m.name,
            m.dlc,
            direction_text(m.direction),
            m.doc
        );
    }
    s.push('\n');

    for m in MESSAGES.iter() {
        let _ = writeln!(s, "### {}\n", m.name);
        let _ = writeln!(s, "{}\n", m.doc);
        s.push_str("| signal | start bit | type | scale | offset | unit | min | max | raw range | description |\n");
        s.push_str("|---|---|---|---|---|---|---|---|---|---|\n");
        for sig in m.signals {
            let _ = writeln!(
                s,
                "| {} | {} | {} | {} | {} | {} | {} | {} | {}..{} | {} |",
                sig.name,
                sig.start_bit,
                type_text(sig),
                sig.scale,
                sig.offset,
                if sig.unit.is_empty() { "–" } else { sig.unit },
                sig.min,
                sig.max,
                sig.raw_min(),
                sig.raw_max(),
                sig.doc
            );
        }
        s.push_str("\n| byte | bits (MSB first) |\n|---|---|\n");
        for row in layout_rows(m) {
            s.push_str(&row);
            s.push('\n');
        }
        s.push('\n');
    }

    s.push_str("## Module states and fault codes\n\n");
    s.push_str("| state | value |\n|---|---|\n");
    for raw in 0..=3u8 {
        if let Some(st) = ModuleState::from_raw(raw) {
            let _ = writeln!(s, "| {} | {raw} |", st.name());
        }
    }
    s.push_str("\n| fault code | meaning |\n|---|---|\n");
    for code in [0u8, 1, 2, 3, 4, 5, 6, 7, 8, 0xFF] {
        let _ = writeln!(s, "| {code} | {} |", crate::codec::fault_name(code));
    }
    s.push('\n');

    s.push_str("## Example frames\n\n");
    s.push_str("Produced by `codec::encode`; the same vectors are hand-checked in `driver/tests/golden.rs`.\n\n");
    s.push_str("| message | values | id | bytes |\n|---|---|---|---|\n");
    for (text, msg) in examples() {
        match encode(&msg) {
            Ok(f) => {
                let _ = writeln!(
                    s,
                    "| {} | {text} | 0x{:03X} | `{}` |",
                    crate::protocol::spec(msg.kind()).name,
                    f.id(),
                    hex_bytes(f.data())
                );
            }
            Err(e) => {
                let _ = writeln!(s, "| {} | {text} | – | encode error: {e} |", msg.kind());
            }
        }
    }
    s.push('\n');

    s.push_str("## Bus load (worst-case bit stuffing)\n\n");
    let _ = writeln!(
        s,
        "Frame bits = 8n + 47 + ⌊(33 + 8n)/4⌋ for n data bytes: DLC 4 → {}, DLC 6 → {}, DLC 8 → {} bits.\n",
        frame_bits(4),
        frame_bits(6),
        frame_bits(8)
    );
    match bus_load(&BusLoadConfig::default()) {
        Ok(r) => {
            s.push_str("```text\n");
            s.push_str(&r.to_string());
            s.push_str("\n```\n");
        }
        Err(e) => {
            let _ = writeln!(s, "bus-load error: {e}");
        }
    }
    s
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn dbc_has_every_frame_and_signal() {
        let d = dbc();
        assert!(d.contains("BU_: Controller Module1 Module2 Module3 Module4"));
        assert!(d.contains("BO_ 128 SYNC: 4 Controller"));
        assert!(d.contains("BO_ 513 SETPOINT_1: 6 Controller"));
        assert!(d.contains("BO_ 388 FEEDBACK_A_4: 8 Module4"));
        assert!(d.contains(" SG_ wheel_speed : 0|16@1- (0.001,0) [-30|30] \"rad/s\" Module1"));
        assert!(d.contains(" SG_ temperature : 16|8@1+ (1,-40) [-40|215] \"degC\" Controller"));
        assert!(d.contains(" SG_ crc : 56|8@1+ (1,0) [0|255] \"\" Controller"));
        assert!(d.contains("VAL_ 1793 state 0 \"boot\" 1 \"ready\" 2 \"enabled\" 3 \"fault\" ;"));
        assert!(d.contains("BA_ \"GenMsgCycleTime\" BO_ 1793 100;"));
        let frames = d.lines().filter(|l| l.starts_with("BO_ ")).count();
        assert_eq!(frames, 1 + 4 * 4, "SYNC + 4 per-node messages x 4 nodes");
    }

    #[test]
    fn dbc_for_nodes_filters_invalid_nodes() {
        let d = dbc_for_nodes(&[2, 2, 0, 16]);
        assert!(d.contains("BU_: Controller Module2\n"));
        assert!(d.contains("SETPOINT_2"));
        assert!(!d.contains("SETPOINT_1"));
        assert!(!d.contains("Module16"));
    }

    #[test]
    fn markdown_mentions_every_message_and_the_example_bytes() {
        let md = protocol_markdown();
        for m in MESSAGES.iter() {
            assert!(md.contains(&format!("### {}", m.name)));
        }
        assert!(md.contains("`34 12 05 58`"), "SYNC golden vector");
        assert!(md.contains("`93 02 7D C0 12 6F`"), "STATUS golden vector");
        assert!(
            md.contains(
                "| 4 | b7–4: counter, b3: reserved, b2: fault_reset, b1: brake, b0: enable |"
            ),
            "{md}"
        );
    }
}
