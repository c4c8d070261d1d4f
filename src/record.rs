//! Recording of runs as MCAP files with JSON-encoded messages and JSON schemas.
//!
//! The cycle builds one fixed-size, `Copy` [`CycleRecord`] per cycle (no allocation) and hands
//! it over a bounded channel; this module turns records into MCAP messages on the recorder
//! thread. One topic per stream, log time = the cycle's time, schemas in JSON Schema so
//! Foxglove Studio and the Python `mcap` reader can interpret them:
//!
//! | topic | one message per | content |
//! |---|---|---|
//! | `/can/rx` | received frame | time, id, dlc, data (hex), accepted, error kind |
//! | `/can/tx` | sent frame | time, id, dlc, data (hex) |
//! | `/feedback` | cycle | decoded per-wheel φ, φ̇, ω, λ, λ̇, feedback age, module state |
//! | `/reference` | cycle | nominal z*, ż*, z̈* and the reference actually tracked |
//! | `/command` | cycle | mode, enable flag, per-wheel wheel speed and steering rate |
//! | `/pose` | cycle | estimated pose, body twist, slip residual, true pose when simulated |
//! | `/icr` | cycle | ICR in the body frame, avoidance state, min ICR–wheel distance |
//! | `/supervisor` | cycle | state and fault reason |
//! | `/timing` | cycle | period, wake-up latency, compute time, feedback age, frames in/out, rejections |
//!
//! In lockstep runs every time in a record is virtual (and compute time is recorded as 0), so
//! two runs with the same seed give byte-identical message payloads.

use rollbase_control::record::CycleRecord;
use rollbase_control::types::MAX_WHEELS;
use serde_json::{json, Value};
use std::collections::BTreeMap;
use std::fs::File;
use std::io::{BufWriter, Write};
use std::path::Path;

/// Every topic a recording has, in order.
pub const TOPICS: [&str; 9] = [
    "/can/rx",
    "/can/tx",
    "/feedback",
    "/reference",
    "/command",
    "/pose",
    "/icr",
    "/supervisor",
    "/timing",
];

/// Errors of the recorder.
#[derive(Debug, thiserror::Error)]
pub enum RecordError {
    /// The file could not be created or written.
    #[error("recording {path}: {source}")]
    Io {
        /// File path.
        path: String,
        /// Underlying error.
        source: std::io::Error,
    },
    /// The MCAP library reported an error.
    #[error("recording {path}: MCAP error: {message}")]
    Mcap {
        /// File path.
        path: String,
        /// The library's message.
        message: String,
    },
    /// A recording being read is not what this program writes.
    #[error("reading {path}: {message}")]
    Format {
        /// File path.
        path: String,
        /// What is wrong.
        message: String,
    },
}

fn hex(data: &[u8]) -> String {
    let mut s = String::with_capacity(data.len() * 2);
    for b in data {
        s.push_str(&format!("{b:02X}"));
    }
    s
}

fn finite(x: f64) -> Value {
    if x.is_finite() {
        json!(x)
    } else {
        Value::Null
    }
}

fn arr(xs: &[f64]) -> Value {
    Value::Array(xs.iter().map(|&x| finite(x)).collect())
}

fn schema(topic: &str) -> Value {
    let num = json!({"type": ["number", "null"]});
    let nums = json!({"type": "array", "items": {"type": ["number", "null"]}});
    let int = json!({"type": "integer"});
    let (title, props): (&str, Value) = match topic {
        "/can/rx" | "/can/tx" => (
            "rollbase.CanFrame",
            json!({"t": num, "id": int, "dlc": int, "data": {"type": "string", "description": "payload, uppercase hex"},
                   "accepted": {"type": "boolean"}, "error": {"type": ["string", "null"]}}),
        ),
        "/feedback" => (
            "rollbase.Feedback",
            json!({"cycle": int, "wheels": {"type": "array", "items": {"type": "object", "properties": {
                "node": int, "steer_angle": num, "steer_rate": num, "wheel_speed": num, "leg": num,
                "leg_rate": num, "age_cycles": int, "module_state": int}}}}),
        ),
        "/reference" => (
            "rollbase.Reference",
            json!({"cycle": int, "t": num, "z": nums, "dz": nums, "ddz": nums, "nominal_z": nums,
                   "nominal_dz": nums}),
        ),
        "/command" => (
            "rollbase.Command",
            json!({"cycle": int, "mode": {"type": "string"}, "enable": {"type": "boolean"},
                   "wheel_speed": nums, "steer_rate": nums}),
        ),
        "/pose" => (
            "rollbase.Pose",
            json!({"cycle": int, "x": num, "y": num, "theta": num, "vx": num, "vy": num, "omega": num,
                   "slip_residual": num, "true_x": num, "true_y": num, "true_theta": num, "true_legs": nums}),
        ),
        "/icr" => (
            "rollbase.Icr",
            json!({"cycle": int, "icr_x": num, "icr_y": num, "at_infinity": {"type": "boolean"},
                   "active": {"type": "boolean"}, "min_distance": num, "nearest_wheel": {"type": ["integer", "null"]},
                   "d_start": nums, "deviation": nums, "wheel_x": nums, "wheel_y": nums}),
        ),
        "/supervisor" => (
            "rollbase.Supervisor",
            json!({"cycle": int, "state": {"type": "string"}, "reason": {"type": ["string", "null"]}}),
        ),
        _ => (
            "rollbase.Timing",
            json!({"cycle": int, "period_us": num, "wakeup_latency_us": num, "compute_us": num,
                   "feedback_age_us": num, "frames_in": int, "frames_out": int, "rejected": int,
                   "deadline_miss": {"type": "boolean"}}),
        ),
    };
    json!({"title": title, "type": "object", "properties": props})
}

/// The JSON messages of one cycle record, as (topic index into [`TOPICS`], log time ns, payload).
/// Pure: used by the writer and by tests.
pub fn record_messages(
    r: &CycleRecord,
    wheel_xy: &[[f64; 2]],
    out: &mut Vec<(usize, u64, Vec<u8>)>,
) {
    let n = r.n.min(MAX_WHEELS);
    let ns = |t: f64| (t.max(0.0) * 1e9) as u64;
    let base = r.log_time_ns;
    let offset = |t: f64| base.saturating_add(ns(t - r.t));
    for f in &r.rx[..r.n_rx] {
        let v = json!({"t": finite(f.t), "id": f.id, "dlc": f.len, "data": hex(&f.data[..f.len as usize]),
                       "accepted": f.error.is_none(), "error": f.error});
        out.push((0, offset(f.t), v.to_string().into_bytes()));
    }
    for f in &r.tx[..r.n_tx] {
        let v = json!({"t": finite(f.t), "id": f.id, "dlc": f.len, "data": hex(&f.data[..f.len as usize]),
                       "accepted": true, "error": Value::Null});
        out.push((1, offset(f.t), v.to_string().into_bytes()));
    }
    let wheels: Vec<Value> = (0..n)
        .map(|i| {
            let w = &r.measurement.wheels[i];
            json!({"node": r.nodes[i], "steer_angle": finite(w.steer_angle), "steer_rate": finite(w.steer_rate),
                   "wheel_speed": finite(w.wheel_speed), "leg": finite(w.leg), "leg_rate": finite(w.leg_rate),
                   "age_cycles": r.feedback_age[i], "module_state": r.module_state[i]})
        })
        .collect();
    let msgs = [
        json!({"cycle": r.cycle, "wheels": wheels}),
        json!({"cycle": r.cycle, "t": finite(r.reference.t), "z": arr(&r.reference.z.as_slice()[..3 + n]),
               "dz": arr(&r.reference.dz.as_slice()[..3 + n]), "ddz": arr(&r.reference.ddz.as_slice()[..3 + n]),
               "nominal_z": arr(&r.nominal.z.as_slice()[..3 + n]), "nominal_dz": arr(&r.nominal.dz.as_slice()[..3 + n])}),
        json!({"cycle": r.cycle, "mode": r.mode, "enable": r.enable,
               "wheel_speed": arr(&r.command.wheels[..n].iter().map(|w| w.wheel_speed).collect::<Vec<_>>()),
               "steer_rate": arr(&r.command.wheels[..n].iter().map(|w| w.steer_rate).collect::<Vec<_>>())}),
        {
            let (tx, ty, tt, tl) = match r.truth {
                Some((p, legs)) => (finite(p.x), finite(p.y), finite(p.theta), arr(&legs[..n])),
                None => (Value::Null, Value::Null, Value::Null, Value::Null),
            };
            json!({"cycle": r.cycle, "x": finite(r.pose.x), "y": finite(r.pose.y), "theta": finite(r.pose.theta),
                   "vx": finite(r.twist_body.vx), "vy": finite(r.twist_body.vy), "omega": finite(r.twist_body.omega),
                   "slip_residual": finite(r.slip_residual), "true_x": tx, "true_y": ty, "true_theta": tt, "true_legs": tl})
        },
        {
            let a = &r.avoidance;
            let (ix, iy) = match a.icr_body {
                Some([x, y]) => (finite(x), finite(y)),
                None => (Value::Null, Value::Null),
            };
            json!({"cycle": r.cycle, "icr_x": ix, "icr_y": iy, "at_infinity": a.icr_body.is_none(),
                   "active": a.active, "min_distance": finite(a.min_distance), "nearest_wheel": a.nearest_wheel,
                   "d_start": arr(&a.d_start[..n]), "deviation": arr(&a.deviation[..3 + n]),
                   "wheel_x": arr(&wheel_xy.iter().take(n).map(|w| w[0]).collect::<Vec<_>>()),
                   "wheel_y": arr(&wheel_xy.iter().take(n).map(|w| w[1]).collect::<Vec<_>>())})
        },
        json!({"cycle": r.cycle, "state": r.state.name(), "reason": r.reason.map(|x| x.to_string())}),
        json!({"cycle": r.cycle, "period_us": finite(r.timing.period_us), "wakeup_latency_us": finite(r.timing.wakeup_latency_us),
               "compute_us": finite(r.timing.compute_us), "feedback_age_us": finite(r.timing.feedback_age_us),
               "frames_in": r.timing.frames_in, "frames_out": r.timing.frames_out, "rejected": r.timing.rejected,
               "deadline_miss": r.timing.deadline_miss}),
    ];
    for (k, v) in msgs.into_iter().enumerate() {
        out.push((2 + k, base, v.to_string().into_bytes()));
    }
}

/// Writes [`CycleRecord`]s to an MCAP file.
pub struct McapRecorder {
    path: String,
    writer: mcap::Writer<BufWriter<File>>,
    channels: [u16; TOPICS.len()],
    sequence: [u32; TOPICS.len()],
    counts: [u64; TOPICS.len()],
    scratch: Vec<(usize, u64, Vec<u8>)>,
}

/// Message counts per topic of a finished recording.
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct RecordSummary {
    /// Topic → number of messages.
    pub messages: BTreeMap<String, u64>,
}

impl McapRecorder {
    /// Creates the file and declares every topic and schema.
    pub fn create(
        path: impl AsRef<Path>,
        metadata: &BTreeMap<String, String>,
    ) -> Result<Self, RecordError> {
        let p = path.as_ref().display().to_string();
        if let Some(dir) = path.as_ref().parent() {
            if !dir.as_os_str().is_empty() {
                std::fs::create_dir_all(dir).map_err(|source| RecordError::Io {
                    path: p.clone(),
                    source,
                })?;
            }
        }
        let file = File::create(path.as_ref()).map_err(|source| RecordError::Io {
            path: p.clone(),
            source,
        })?;
        let mcap_err = |e: mcap::McapError| RecordError::Mcap {
            path: p.clone(),
            message: e.to_string(),
        };
        let mut writer = mcap::WriteOptions::new()
            .compression(None)
            .profile("")
            .library("rollbase")
            .create(BufWriter::new(file))
            .map_err(mcap_err)?;
        let mut channels = [0u16; TOPICS.len()];
        for (i, topic) in TOPICS.iter().enumerate() {
            let s = schema(topic);
            let name = s["title"]
                .as_str()
                .unwrap_or("rollbase.Unknown")
                .to_string();
            let sid = writer
                .add_schema(&name, "jsonschema", s.to_string().as_bytes())
                .map_err(mcap_err)?;
            channels[i] = writer
                .add_channel(sid, topic, "json", &BTreeMap::new())
                .map_err(mcap_err)?;
        }
        if !metadata.is_empty() {
            writer
                .write_metadata(&mcap::records::Metadata {
                    name: "rollbase.run".into(),
                    metadata: metadata.clone(),
                })
                .map_err(mcap_err)?;
        }
        Ok(Self {
            path: p,
            writer,
            channels,
            sequence: [0; TOPICS.len()],
            counts: [0; TOPICS.len()],
            scratch: Vec::with_capacity(64),
        })
    }

    /// Writes one cycle. `wheel_xy` are the wheel contact points in the body frame (for plots).
    pub fn write_cycle(
        &mut self,
        r: &CycleRecord,
        wheel_xy: &[[f64; 2]],
    ) -> Result<(), RecordError> {
        self.scratch.clear();
        let mut scratch = std::mem::take(&mut self.scratch);
        record_messages(r, wheel_xy, &mut scratch);
        for (topic, t, data) in scratch.drain(..) {
            let header = mcap::records::MessageHeader {
                channel_id: self.channels[topic],
                sequence: self.sequence[topic],
                log_time: t,
                publish_time: t,
            };
            self.sequence[topic] = self.sequence[topic].wrapping_add(1);
            self.counts[topic] += 1;
            self.writer
                .write_to_known_channel(&header, &data)
                .map_err(|e| RecordError::Mcap {
                    path: self.path.clone(),
                    message: e.to_string(),
                })?;
        }
        self.scratch = scratch;
        Ok(())
    }

    /// Finishes the file (summary, index) and returns the message counts.
    pub fn finish(mut self) -> Result<RecordSummary, RecordError> {
        self.writer.finish().map_err(|e| RecordError::Mcap {
            path: self.path.clone(),
            message: e.to_string(),
        })?;
        let mut inner = self.writer.into_inner();
        inner.flush().map_err(|source| RecordError::Io {
            path: self.path.clone(),
            source,
        })?;
        Ok(RecordSummary {
            messages: TOPICS
                .iter()
                .zip(self.counts.iter())
                .map(|(t, c)| (t.to_string(), *c))
                .collect(),
        })
    }
}

/// Reads every message of a recording: (topic, log time ns, JSON value). For plots and tests.
pub fn read_recording(path: impl AsRef<Path>) -> Result<Vec<(String, u64, Value)>, RecordError> {
    let p = path.as_ref().display().to_string();
    let bytes = std::fs::read(path.as_ref()).map_err(|source| RecordError::Io {
        path: p.clone(),
        source,
    })?;
    let stream = mcap::MessageStream::new(&bytes).map_err(|e| RecordError::Format {
        path: p.clone(),
        message: format!("not an MCAP file: {e}"),
    })?;
    let mut out = Vec::new();
    for m in stream {
        let m = m.map_err(|e| RecordError::Format {
            path: p.clone(),
            message: format!("corrupt MCAP message: {e}"),
        })?;
        let v: Value = serde_json::from_slice(&m.data).map_err(|e| RecordError::Format {
            path: p.clone(),
            message: format!("message on {} is not JSON: {e}", m.channel.topic),
        })?;
        out.push((m.channel.topic.clone(), m.log_time, v));
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;
    use rollbase_control::record::FrameRecord;

    #[test]
    fn writes_and_reads_back_every_topic() {
        let dir = std::env::temp_dir().join(format!("rollbase-rec-{}", std::process::id()));
        let path = dir.join("t.mcap");
        let mut rec = McapRecorder::create(&path, &BTreeMap::new()).unwrap();
        for k in 0..10u64 {
            let mut r = CycleRecord::new(k, k as f64 * 0.004, 4);
            r.push_rx(FrameRecord {
                t: r.t + 0.001,
                id: 0x181,
                len: 8,
                data: [1, 2, 3, 4, 5, 6, 7, 8],
                error: None,
            });
            r.push_tx(FrameRecord {
                t: r.t,
                id: 0x80,
                len: 4,
                data: [0; 8],
                error: None,
            });
            r.pose.x = k as f64;
            rec.write_cycle(&r, &[[0.3, 0.2]; 4]).unwrap();
        }
        let summary = rec.finish().unwrap();
        for t in TOPICS {
            assert_eq!(summary.messages[t], 10, "topic {t}");
        }
        let msgs = read_recording(&path).unwrap();
        assert_eq!(msgs.len(), 90);
        let poses: Vec<f64> = msgs
            .iter()
            .filter(|(t, _, _)| t == "/pose")
            .map(|(_, _, v)| v["x"].as_f64().unwrap())
            .collect();
        assert_eq!(poses, (0..10).map(|k| k as f64).collect::<Vec<_>>());
        let rx = msgs.iter().find(|(t, _, _)| t == "/can/rx").unwrap();
        assert_eq!(rx.2["data"], "0102030405060708");
        assert_eq!(rx.1, 1_000_000, "log time of the frame is its receive time");
        let _ = std::fs::remove_dir_all(dir);
    }

    #[test]
    fn reading_garbage_is_a_typed_error() {
        let dir = std::env::temp_dir().join(format!("rollbase-rec-bad-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let path = dir.join("bad.mcap");
        std::fs::write(&path, b"this is not mcap").unwrap();
        assert!(matches!(
            read_recording(&path),
            Err(RecordError::Format { .. })
        ));
        let _ = std::fs::remove_dir_all(dir);
    }
}
