//! `rollbase monitor --json`: one JSON object per frame, for tools (the interop tests compare
//! every signal with cantools' decoding of the same capture).
//!
//! ```json
//! {"t": 1700000000.123456, "id": 385, "dlc": 8, "data": "0011223344556677",
//!  "accepted": true, "message": "FEEDBACK_A", "node": 1,
//!  "signals": {"steer_angle": 0.0017, "wheel_speed": 13.346, "steer_rate": 0.0,
//!              "counter": 6, "crc": 119}}
//! ```
//!
//! Signal names are the DBC's (`rollbase dbc`), values are physical (SI) as our decoder
//! produced them, flags and enumerations as their wire integers, `crc` is the frame's CRC
//! byte (checked by the decoder when `accepted`). A rejected frame has `"accepted": false`,
//! `"error"` (the receiver's reason) and no `signals`. An unreadable log line is
//! `{"line": N, "error": "…"}`.

use rollbase_driver::candump::MonitorStats;
use rollbase_driver::codec::{Message, Payload};
use rollbase_driver::frame::CanFrame;
use rollbase_driver::protocol::{spec, MessageKind};
use rollbase_driver::rx::Receiver;
use serde_json::{json, Map, Value};
use std::time::Duration;

/// The DBC-named signals of a decoded message (physical values).
fn signals(m: &Message, frame: &CanFrame) -> Value {
    let mut s = Map::new();
    let mut put = |k: &str, v: Value| {
        s.insert(k.to_string(), v);
    };
    match &m.payload {
        Payload::Sync(p) => put("cycle", json!(p.cycle)),
        Payload::Setpoint(p) => {
            put("wheel_speed", json!(p.wheel_speed));
            put("steer_rate", json!(p.steer_rate));
            put("enable", json!(u8::from(p.flags.enable)));
            put("brake", json!(u8::from(p.flags.brake)));
            put("fault_reset", json!(u8::from(p.flags.fault_reset)));
        }
        Payload::FeedbackA(p) => {
            put("steer_angle", json!(p.steer_angle));
            put("wheel_speed", json!(p.wheel_speed));
            put("steer_rate", json!(p.steer_rate));
        }
        Payload::FeedbackB(p) => {
            put("leg_extension", json!(p.leg_extension));
            put("leg_rate", json!(p.leg_rate));
            put("drive_current", json!(p.drive_current));
            put("steer_current", json!(p.steer_current));
        }
        Payload::Status(p) => {
            put("state", json!(p.state.to_raw()));
            put("fault_code", json!(p.fault_code));
            put("temperature", json!(p.temperature));
            put("bus_voltage", json!(p.bus_voltage));
        }
    }
    put("counter", json!(m.counter));
    let crc = frame.data().get(spec(m.kind()).crc_byte()).copied();
    put("crc", json!(crc));
    Value::Object(s)
}

/// One frame as a JSON object; updates `rx` and `stats` as `candump::describe` does.
pub fn frame_json(
    rx: &mut Receiver,
    stats: &mut MonitorStats,
    timestamp: Duration,
    frame: &CanFrame,
) -> Value {
    stats.frames += 1;
    let data: String = frame.data().iter().map(|b| format!("{b:02X}")).collect();
    let mut v = json!({
        "t": timestamp.as_secs_f64(),
        "id": frame.id(),
        "dlc": frame.len(),
        "data": data,
    });
    match rx.accept(frame) {
        Ok(m) => {
            stats.accepted[m.kind().index()] += 1;
            v["accepted"] = json!(true);
            v["message"] = json!(spec(m.kind()).name);
            v["node"] = json!(m.node);
            v["signals"] = signals(&m, frame);
        }
        Err(e) => {
            stats.rejected += 1;
            v["accepted"] = json!(false);
            v["error"] = json!(e.to_string());
        }
    }
    stats.rx = *rx.stats();
    v
}

/// The `--summary` object.
pub fn summary_json(stats: &MonitorStats) -> Value {
    let accepted: Map<String, Value> = MessageKind::ALL
        .iter()
        .map(|k| (spec(*k).name.to_string(), json!(stats.accepted[k.index()])))
        .collect();
    json!({"summary": {
        "frames": stats.frames,
        "accepted": accepted,
        "rejected": stats.rejected,
        "bad_crc": stats.rx.bad_crc,
        "unparsable_lines": stats.unparsable,
    }})
}

/// Counts one CiA 402 frame in the monitor statistics (frames, rejected).
pub fn count_cia402(stats: &mut MonitorStats, r: &Result<String, String>) {
    stats.frames += 1;
    if r.is_err() {
        stats.rejected += 1;
    }
}

/// `--profile cia402 --json`: one object per frame with the frame's description
/// (`rollbase_driver::canopen::describe`), or `"accepted": false` and `"error"`.
pub fn cia402_frame_json(
    cfg: &rollbase_driver::canopen::config::Cia402Config,
    stats: &mut MonitorStats,
    ts: Duration,
    f: &CanFrame,
) -> Value {
    let r = rollbase_driver::canopen::describe::describe(f, cfg);
    count_cia402(stats, &r);
    let data: String = f.data().iter().map(|b| format!("{b:02X}")).collect();
    let mut v = json!({"t": ts.as_secs_f64(), "id": f.id(), "dlc": f.len(), "data": data});
    match r {
        Ok(d) => {
            v["accepted"] = json!(true);
            v["description"] = json!(d);
        }
        Err(e) => {
            v["accepted"] = json!(false);
            v["error"] = json!(e);
        }
    }
    v
}

/// The last object of `--profile cia402 --json --summary`.
pub fn cia402_summary_json(stats: &MonitorStats) -> Value {
    json!({"summary": {
        "frames": stats.frames,
        "rejected": stats.rejected,
        "unparsable_lines": stats.unparsable,
    }})
}

#[cfg(test)]
mod tests {
    use super::*;
    use rollbase_driver::codec::{encode, FeedbackA, Sync};

    #[test]
    fn accepted_and_rejected_frames() {
        let mut rx = Receiver::new();
        let mut st = MonitorStats::default();
        let m = Message {
            node: 2,
            counter: 5,
            payload: Payload::FeedbackA(FeedbackA {
                steer_angle: -1.2345,
                wheel_speed: 13.9,
                steer_rate: 0.25,
            }),
        };
        let f = encode(&m).expect("encode");
        let v = frame_json(&mut rx, &mut st, Duration::from_millis(1500), &f);
        assert_eq!(v["accepted"], json!(true));
        assert_eq!(v["message"], json!("FEEDBACK_A"));
        assert_eq!(v["id"], json!(0x182));
        assert_eq!(v["node"], json!(2));
        assert_eq!(v["t"], json!(1.5));
        let s = &v["signals"];
        assert!((s["steer_angle"].as_f64().expect("f64") + 1.2345).abs() < 1e-9);
        assert!((s["wheel_speed"].as_f64().expect("f64") - 13.9).abs() < 1e-9);
        assert_eq!(s["counter"], json!(5));
        assert_eq!(s["crc"], json!(f.data()[7]));
        // Same frame again: a repeated counter is rejected, with the reason.
        let v = frame_json(&mut rx, &mut st, Duration::ZERO, &f);
        assert_eq!(v["accepted"], json!(false));
        assert!(v["error"].as_str().is_some_and(|e| !e.is_empty()));
        assert!(v.get("signals").is_none());
        let s = encode(&Message {
            node: 0,
            counter: 0,
            payload: Payload::Sync(Sync { cycle: 7 }),
        })
        .expect("encode");
        let bad = s.with_flipped_bit(3);
        let v = frame_json(&mut rx, &mut st, Duration::ZERO, &bad);
        assert_eq!(v["accepted"], json!(false));
        let sum = summary_json(&st);
        assert_eq!(sum["summary"]["frames"], json!(3));
        assert_eq!(sum["summary"]["accepted"]["FEEDBACK_A"], json!(1));
        assert_eq!(sum["summary"]["rejected"], json!(2));
        assert_eq!(sum["summary"]["bad_crc"], json!(1));
    }
}
