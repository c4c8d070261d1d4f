//! Recordings of runs as ROS 2 bags: MCAP files that rosbag2 (`ros2 bag play`, storage
//! `mcap`), Foxglove and the Python readers open.
//!
//! Format, as rosbag2's MCAP storage plugin writes it:
//!
//! - profile `ros2`; one schema per message type, encoding `ros2msg`, named `pkg/msg/Type`,
//!   holding the full `.msg` definition with every dependency appended after a line of 80 `=`
//!   and `MSG: pkg/Type` ([`crate::ros2::msg::MsgDef::full_definition`]);
//! - one channel per topic, message encoding `cdr`; each message is a serialized ROS 2 message:
//!   the 4-byte CDR encapsulation header (`00 01 00 00`, little endian) and the CDR payload;
//! - log time = publish time = the message's time (header stamp): Unix time in real-time
//!   runs, virtual time in lockstep runs (so two lockstep runs with the same seed give
//!   byte-identical payloads).
//!
//! Topics (a channel is declared when its first message is written):
//!
//! | topic | type | one message per |
//! |---|---|---|
//! | `/can/rx` | `can_msgs/msg/Frame` | received frame (accepted or not) |
//! | `/can/tx` | `can_msgs/msg/Frame` | sent frame |
//! | `/can/rejected` | `rollbase_msgs/msg/FrameRejection` | received frame the receive path refused, with the kind |
//! | `/feedback` | `rollbase_msgs/msg/Feedback` | cycle: decoded per-wheel φ, φ̇, ω, λ, λ̇, feedback age, module state |
//! | `/reference` | `rollbase_msgs/msg/Reference` | cycle: nominal z*, ż*, and the reference tracked |
//! | `/command` | `rollbase_msgs/msg/Command` | cycle: mode, enable, wheel speeds and steering rates sent |
//! | `/pose` | `rollbase_msgs/msg/Pose` | cycle: estimated pose and twist, slip residual, truth when simulated |
//! | `/icr` | `rollbase_msgs/msg/Icr` | cycle: ICR in the body frame, avoidance, wheel contact points |
//! | `/supervisor` | `rollbase_msgs/msg/Supervisor` | cycle: state and fault reason |
//! | `/timing` | `rollbase_msgs/msg/Timing` | cycle: period, latency, compute time, frames |
//! | `odom`, `tf`, `joint_states`, `diagnostics`, `supervisor_state` | as the ROS 2 node publishes them | state, at the node's rates ([`McapRecorder::write_state`]) |
//! | `cmd_vel` (`geometry_msgs/msg/Twist`), leg topic (`std_msgs/msg/Float64MultiArray`) | received commands | command ([`McapRecorder::write_command`]) |
//!
//! The ROS topics are resolved in the node's namespace (default `/`: `/odom`, …), so a
//! played-back bag republishes what the live node published.
//!
//! `rollbase_msgs` is rollbase's own package of per-cycle record types: their definitions
//! are in the file (schema text), CDR-encoded like any ROS 2 message. A ROS installation does
//! not have the package, so `ros2 bag play` skips those topics (it warns that it cannot load
//! the type) and plays the standard ones; readers that decode from the schema text (Python
//! `rosbags`, `mcap-ros2-support`, Foxglove) read all of them. NaN marks a missing value
//! (no truth, ICR at infinity).
//!
//! Chunks are 256 KiB: a process killed hard loses at most the chunk being filled (about
//! 0.4 s of a 4-wheel run: a seed-000 demo writes about 2.8 kB per cycle, 690 kB/s at
//! 250 Hz); [`recover`] rewrites such a file with its index and summary.

use crate::ros2::convert::StateSampler;
use crate::ros2::msg::{self, Header, RosMsg};
use crate::ros2::Ros2Options;
use rollbase_control::ports::{BaseState, CommandEvent, CommandKind};
use rollbase_control::record::CycleRecord;
use rollbase_control::types::MAX_WHEELS;
use serde_json::Value;
use std::collections::BTreeMap;
use std::fs::File;
use std::io::{BufWriter, Write};
use std::path::Path;

/// The per-cycle topics, in the order of the module table.
pub const TOPICS: [&str; 10] = [
    "/can/rx",
    "/can/tx",
    "/can/rejected",
    "/feedback",
    "/reference",
    "/command",
    "/pose",
    "/icr",
    "/supervisor",
    "/timing",
];

/// Largest recording read for plots or recovery (bytes); larger files are refused before
/// reading (the reader holds the file in memory).
pub const MAX_READ_BYTES: u64 = 4 << 30;

/// MCAP chunk size of recordings (bytes).
pub const CHUNK_SIZE: u64 = 256 * 1024;

/// Errors of the recorder and the readers.
#[derive(Debug, thiserror::Error)]
pub enum RecordError {
    /// The file could not be created, written or read (the OS error says why, e.g. "No space
    /// left on device").
    #[error("recording {path}: {source}")]
    Io {
        /// File path.
        path: String,
        /// Underlying error.
        source: std::io::Error,
    },
    /// The MCAP library reported an error that is not an OS error.
    #[error("recording {path}: MCAP error: {message}")]
    Mcap {
        /// File path.
        path: String,
        /// The library's message.
        message: String,
    },
    /// A message could not be encoded.
    #[error("recording {path}: {source}")]
    Encode {
        /// File path.
        path: String,
        /// The codec error.
        source: msg::MsgError,
    },
    /// A recording being read is not what this program writes, or is damaged.
    #[error("reading {path}: {message}")]
    Format {
        /// File path.
        path: String,
        /// What is wrong.
        message: String,
    },
}

fn mcap_error(path: &str, e: mcap::McapError) -> RecordError {
    match e {
        mcap::McapError::Io(source) => RecordError::Io {
            path: path.to_string(),
            source,
        },
        e => RecordError::Mcap {
            path: path.to_string(),
            message: e.to_string(),
        },
    }
}

/// Options of a recording: the ROS 2 options (frames, joint names, rates, namespace, tf) for
/// the state topics, and the CAN interface name for the frames' `frame_id`.
#[derive(Clone, Debug, PartialEq)]
pub struct RecordOptions {
    /// As for the ROS 2 node.
    pub ros2: Ros2Options,
    /// `header.frame_id` of `can_msgs/msg/Frame` messages (the CAN interface, e.g. `can0`).
    pub can_interface: String,
}

impl Default for RecordOptions {
    fn default() -> Self {
        Self {
            ros2: Ros2Options::default(),
            can_interface: "can".into(),
        }
    }
}

// Topic slots of a recorder.
const RX: usize = 0;
const TX: usize = 1;
const REJECTED: usize = 2;
const FEEDBACK: usize = 3;
const REFERENCE: usize = 4;
const COMMAND: usize = 5;
const POSE: usize = 6;
const ICR: usize = 7;
const SUPERVISOR: usize = 8;
const TIMING: usize = 9;
const ODOM: usize = 10;
const TF: usize = 11;
const JOINTS: usize = 12;
const DIAGNOSTICS: usize = 13;
const SUPERVISOR_STATE: usize = 14;
const CMD_VEL: usize = 15;
const LEGS: usize = 16;
const SLOTS: usize = 17;

/// Writes [`CycleRecord`]s, [`BaseState`]s and received commands into a ROS 2 bag (MCAP).
pub struct McapRecorder {
    path: String,
    writer: mcap::Writer<BufWriter<File>>,
    topics: Vec<(String, &'static msg::MsgDef)>,
    schemas: BTreeMap<&'static str, u16>,
    channels: [Option<u16>; SLOTS],
    sequence: [u32; SLOTS],
    counts: [u64; SLOTS],
    sampler: StateSampler,
    can_interface: String,
    failed: bool,
}

/// Message counts per topic of a finished recording.
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct RecordSummary {
    /// Topic → number of messages (topics with at least one message).
    pub messages: BTreeMap<String, u64>,
}

impl McapRecorder {
    /// Creates the file (and its directory) with default [`RecordOptions`] and writes the
    /// metadata record `rollbase.run`.
    pub fn create(
        path: impl AsRef<Path>,
        metadata: &BTreeMap<String, String>,
    ) -> Result<Self, RecordError> {
        Self::create_with(path, metadata, &RecordOptions::default())
    }

    /// Creates the file with the given options.
    pub fn create_with(
        path: impl AsRef<Path>,
        metadata: &BTreeMap<String, String>,
        opts: &RecordOptions,
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
        let mut writer = mcap::WriteOptions::new()
            .compression(None)
            .profile("ros2")
            .library("rollbase")
            .chunk_size(Some(CHUNK_SIZE))
            .create(BufWriter::new(file))
            .map_err(|e| mcap_error(&p, e))?;
        if !metadata.is_empty() {
            writer
                .write_metadata(&mcap::records::Metadata {
                    name: "rollbase.run".into(),
                    metadata: metadata.clone(),
                })
                .map_err(|e| mcap_error(&p, e))?;
        }
        let o = &opts.ros2;
        let mut topics: Vec<(String, &'static msg::MsgDef)> = vec![
            ("/can/rx".into(), &msg::CAN_FRAME),
            ("/can/tx".into(), &msg::CAN_FRAME),
            ("/can/rejected".into(), &msg::RB_FRAME_REJECTION),
            ("/feedback".into(), &msg::RB_FEEDBACK),
            ("/reference".into(), &msg::RB_REFERENCE),
            ("/command".into(), &msg::RB_COMMAND),
            ("/pose".into(), &msg::RB_POSE),
            ("/icr".into(), &msg::RB_ICR),
            ("/supervisor".into(), &msg::RB_SUPERVISOR),
            ("/timing".into(), &msg::RB_TIMING),
        ];
        topics.extend([
            (o.topic("odom"), &msg::ODOMETRY),
            (o.topic("tf"), &msg::TF_MESSAGE),
            (o.topic("joint_states"), &msg::JOINT_STATE),
            (o.topic("diagnostics"), &msg::DIAGNOSTIC_ARRAY),
            (o.topic("supervisor_state"), &msg::STRING),
            (o.topic(&o.cmd_vel_topic), &msg::TWIST),
            (o.topic(&o.leg_topic), &msg::FLOAT64_MULTI_ARRAY),
        ]);
        Ok(Self {
            path: p,
            writer,
            topics,
            schemas: BTreeMap::new(),
            channels: [None; SLOTS],
            sequence: [0; SLOTS],
            counts: [0; SLOTS],
            sampler: StateSampler::new(o),
            can_interface: opts.can_interface.clone(),
            failed: false,
        })
    }

    fn channel(&mut self, slot: usize) -> Result<u16, RecordError> {
        if let Some(c) = self.channels[slot] {
            return Ok(c);
        }
        let (topic, def) = (self.topics[slot].0.clone(), self.topics[slot].1);
        let sid = match self.schemas.get(def.name) {
            Some(&s) => s,
            None => {
                let s = self
                    .writer
                    .add_schema(def.name, "ros2msg", def.full_definition().as_bytes())
                    .map_err(|e| mcap_error(&self.path, e))?;
                self.schemas.insert(def.name, s);
                s
            }
        };
        let c = self
            .writer
            .add_channel(sid, &topic, "cdr", &BTreeMap::new())
            .map_err(|e| mcap_error(&self.path, e))?;
        self.channels[slot] = Some(c);
        Ok(c)
    }

    fn put<T: RosMsg>(&mut self, slot: usize, t_ns: u64, m: &T) -> Result<(), RecordError> {
        if self.failed {
            return Err(RecordError::Format {
                path: self.path.clone(),
                message: "an earlier write failed; the recording was not continued".into(),
            });
        }
        let data = msg::to_cdr(m).map_err(|source| RecordError::Encode {
            path: self.path.clone(),
            source,
        })?;
        let channel_id = self.channel(slot)?;
        let header = mcap::records::MessageHeader {
            channel_id,
            sequence: self.sequence[slot],
            log_time: t_ns,
            publish_time: t_ns,
        };
        self.sequence[slot] = self.sequence[slot].wrapping_add(1);
        if let Err(e) = self.writer.write_to_known_channel(&header, &data) {
            self.failed = true;
            return Err(mcap_error(&self.path, e));
        }
        self.counts[slot] += 1;
        Ok(())
    }

    /// Writes one cycle: its frames and the per-cycle records. `wheel_xy` are the wheel
    /// contact points in the body frame (for plots).
    pub fn write_cycle(
        &mut self,
        r: &CycleRecord,
        wheel_xy: &[[f64; 2]],
    ) -> Result<(), RecordError> {
        let n = r.n.min(MAX_WHEELS);
        let base = r.log_time_ns;
        let at = |t: f64| {
            let dt = t - r.t;
            if dt.is_finite() && dt > 0.0 {
                base.saturating_add((dt * 1e9) as u64)
            } else {
                base
            }
        };
        let iface = self.can_interface.clone();
        for f in &r.rx[..r.n_rx.min(r.rx.len())] {
            let len = f.len.min(8);
            let frame = msg::CanFrame {
                header: Header::new(at(f.t), &iface),
                id: u32::from(f.id),
                dlc: len,
                data: f.data,
                ..Default::default()
            };
            self.put(RX, at(f.t), &frame)?;
            if let Some(kind) = f.error {
                let rej = msg::FrameRejection {
                    header: Header::new(at(f.t), &iface),
                    id: u32::from(f.id),
                    dlc: len,
                    data: f.data,
                    error: kind.to_string(),
                };
                self.put(REJECTED, at(f.t), &rej)?;
            }
        }
        for f in &r.tx[..r.n_tx.min(r.tx.len())] {
            let frame = msg::CanFrame {
                header: Header::new(at(f.t), &iface),
                id: u32::from(f.id),
                dlc: f.len.min(8),
                data: f.data,
                ..Default::default()
            };
            self.put(TX, at(f.t), &frame)?;
        }
        let h = Header::new(base, "base_link");
        let wheels = (0..n)
            .map(|i| {
                let w = &r.measurement.wheels[i];
                msg::WheelFeedback {
                    node: r.nodes[i],
                    steer_angle: w.steer_angle,
                    steer_rate: w.steer_rate,
                    wheel_speed: w.wheel_speed,
                    leg: w.leg,
                    leg_rate: w.leg_rate,
                    age_cycles: r.feedback_age[i],
                    module_state: r.module_state[i],
                }
            })
            .collect();
        self.put(
            FEEDBACK,
            base,
            &msg::Feedback {
                header: h.clone(),
                cycle: r.cycle,
                wheels,
            },
        )?;
        let z = |v: &[f64]| v[..(3 + n).min(v.len())].to_vec();
        self.put(
            REFERENCE,
            base,
            &msg::Reference {
                header: h.clone(),
                cycle: r.cycle,
                t: r.reference.t,
                z: z(r.reference.z.as_slice()),
                dz: z(r.reference.dz.as_slice()),
                ddz: z(r.reference.ddz.as_slice()),
                nominal_z: z(r.nominal.z.as_slice()),
                nominal_dz: z(r.nominal.dz.as_slice()),
            },
        )?;
        self.put(
            COMMAND,
            base,
            &msg::CycleCommand {
                header: h.clone(),
                cycle: r.cycle,
                mode: r.mode.to_string(),
                enable: r.enable,
                wheel_speed: r.command.wheels[..n]
                    .iter()
                    .map(|w| w.wheel_speed)
                    .collect(),
                steer_rate: r.command.wheels[..n].iter().map(|w| w.steer_rate).collect(),
            },
        )?;
        let (has_truth, tp, tl) = match r.truth {
            Some((p, legs)) => (true, [p.x, p.y, p.theta], legs[..n].to_vec()),
            None => (false, [f64::NAN; 3], Vec::new()),
        };
        self.put(
            POSE,
            base,
            &msg::CyclePose {
                header: Header::new(base, "odom"),
                cycle: r.cycle,
                x: r.pose.x,
                y: r.pose.y,
                theta: r.pose.theta,
                vx: r.twist_body.vx,
                vy: r.twist_body.vy,
                omega: r.twist_body.omega,
                slip_residual: r.slip_residual,
                has_truth,
                true_x: tp[0],
                true_y: tp[1],
                true_theta: tp[2],
                true_legs: tl,
            },
        )?;
        let a = &r.avoidance;
        let [ix, iy] = a.icr_body.unwrap_or([f64::NAN; 2]);
        self.put(
            ICR,
            base,
            &msg::Icr {
                header: h.clone(),
                cycle: r.cycle,
                at_infinity: a.icr_body.is_none(),
                icr_x: ix,
                icr_y: iy,
                active: a.active,
                min_distance: a.min_distance,
                nearest_wheel: a
                    .nearest_wheel
                    .and_then(|w| i32::try_from(w).ok())
                    .unwrap_or(-1),
                d_start: a.d_start[..n].to_vec(),
                deviation: a.deviation[..3 + n].to_vec(),
                wheel_x: wheel_xy.iter().take(n).map(|w| w[0]).collect(),
                wheel_y: wheel_xy.iter().take(n).map(|w| w[1]).collect(),
            },
        )?;
        self.put(
            SUPERVISOR,
            base,
            &msg::Supervisor {
                header: h.clone(),
                cycle: r.cycle,
                state: r.state.name().to_string(),
                reason: r.reason.map(|x| x.to_string()).unwrap_or_default(),
            },
        )?;
        let tm = &r.timing;
        self.put(
            TIMING,
            base,
            &msg::Timing {
                header: h,
                cycle: r.cycle,
                period_us: tm.period_us,
                wakeup_latency_us: tm.wakeup_latency_us,
                compute_us: tm.compute_us,
                feedback_age_us: tm.feedback_age_us,
                frames_in: tm.frames_in,
                frames_out: tm.frames_out,
                rejected: tm.rejected,
                deadline_miss: tm.deadline_miss,
            },
        )?;
        Ok(())
    }

    /// Writes the ROS 2 topics of a state at the configured rates (the same messages the node
    /// publishes: odom, tf, joint_states, diagnostics, supervisor_state). Give every state
    /// (one per cycle); the recorder decimates. Returns a warning to show once, if any.
    pub fn write_state(&mut self, s: &BaseState) -> Result<Option<String>, RecordError> {
        let m = self.sampler.sample(s);
        let t = s.log_time_ns;
        if let Some(o) = &m.odom {
            self.put(ODOM, t, o)?;
        }
        if let Some(x) = &m.tf {
            self.put(TF, t, x)?;
        }
        if let Some(x) = &m.joint_states {
            self.put(JOINTS, t, x)?;
        }
        if let Some(x) = &m.diagnostics {
            self.put(DIAGNOSTICS, t, x)?;
        }
        if let Some(x) = &m.supervisor_state {
            self.put(SUPERVISOR_STATE, t, x)?;
        }
        Ok(m.warning)
    }

    /// Writes a received command at `log_time_ns`: a motion command as `geometry_msgs/Twist`
    /// on the velocity topic (with its leg targets, if any, on the leg topic), leg targets as
    /// `std_msgs/Float64MultiArray` on the leg topic. Other commands (stop, rearm, end of
    /// stream, shutdown) are not ROS topics and are not written.
    pub fn write_command(
        &mut self,
        ev: &CommandEvent,
        log_time_ns: u64,
    ) -> Result<(), RecordError> {
        let legs_msg = |l: &rollbase_control::ports::LegTargets| msg::Float64MultiArray {
            layout: msg::MultiArrayLayout {
                dim: vec![msg::MultiArrayDimension {
                    label: "legs".into(),
                    size: l.as_slice().len() as u32,
                    stride: l.as_slice().len() as u32,
                }],
                data_offset: 0,
            },
            data: l.as_slice().to_vec(),
        };
        match &ev.kind {
            CommandKind::Motion(m) => {
                let t = msg::Twist {
                    linear: msg::Vector3 {
                        x: m.twist.vx,
                        y: m.twist.vy,
                        z: 0.0,
                    },
                    angular: msg::Vector3 {
                        x: 0.0,
                        y: 0.0,
                        z: m.twist.omega,
                    },
                };
                self.put(CMD_VEL, log_time_ns, &t)?;
                if let Some(l) = &m.legs {
                    self.put(LEGS, log_time_ns, &legs_msg(l))?;
                }
            }
            CommandKind::Legs(l) => self.put(LEGS, log_time_ns, &legs_msg(l))?,
            _ => {}
        }
        Ok(())
    }

    /// Stops writing without finishing the file: no summary, no index, no footer are written
    /// (after a failed write the writer's state is not trustworthy: finishing could put an
    /// index and a valid-looking footer after a cut record). What reached the file stays, as
    /// after a killed writer, for [`recover`]. Returns the file's length in bytes (0 when it
    /// cannot be read).
    pub fn abandon(self) -> u64 {
        // `into_inner` unwraps the writer without writing anything (it also marks it
        // finished, so nothing is written when it is dropped).
        let mut inner = self.writer.into_inner();
        // What the buffer still holds is the continuation of the data: keep it if it fits.
        let _ = inner.flush();
        inner.get_ref().metadata().map(|m| m.len()).unwrap_or(0)
    }

    /// Finishes the file (summary, index) and returns the message counts per topic.
    pub fn finish(mut self) -> Result<RecordSummary, RecordError> {
        self.writer
            .finish()
            .map_err(|e| mcap_error(&self.path, e))?;
        let mut inner = self.writer.into_inner();
        inner.flush().map_err(|source| RecordError::Io {
            path: self.path.clone(),
            source,
        })?;
        inner
            .get_ref()
            .sync_all()
            .map_err(|source| RecordError::Io {
                path: self.path.clone(),
                source,
            })?;
        Ok(RecordSummary {
            messages: self
                .topics
                .iter()
                .zip(self.counts.iter())
                .filter(|(_, c)| **c > 0)
                .map(|((t, _), c)| (t.clone(), *c))
                .collect(),
        })
    }
}

// ---------------------------------------------------------------------------------------------
// Reading
// ---------------------------------------------------------------------------------------------

/// Reads a file for the readers: refuses what is not a regular file (a device like
/// `/dev/zero` would never end) and files over [`MAX_READ_BYTES`], before reading.
fn read_bounded(path: &Path) -> Result<Vec<u8>, RecordError> {
    let p = path.display().to_string();
    let meta = std::fs::metadata(path).map_err(|source| RecordError::Io {
        path: p.clone(),
        source,
    })?;
    if !meta.is_file() {
        return Err(RecordError::Format {
            path: p,
            message: "not a regular file (a device, pipe or directory); give an MCAP recording"
                .into(),
        });
    }
    if meta.len() > MAX_READ_BYTES {
        return Err(RecordError::Format {
            path: p,
            message: format!(
                "{} bytes is more than the {} bytes this reader loads into memory; split the recording (e.g. with the mcap CLI) first",
                meta.len(),
                MAX_READ_BYTES
            ),
        });
    }
    use std::io::Read;
    let f = File::open(path).map_err(|source| RecordError::Io {
        path: p.clone(),
        source,
    })?;
    let mut bytes = Vec::with_capacity(meta.len() as usize);
    // `take`: a file that grows while read still stops at the limit.
    f.take(MAX_READ_BYTES + 1)
        .read_to_end(&mut bytes)
        .map_err(|source| RecordError::Io { path: p, source })?;
    Ok(bytes)
}

/// Decodes a rollbase per-cycle message into JSON (field names as in the `.msg`; NaN and
/// infinities become `null`).
fn decode_to_json(schema: &str, data: &[u8]) -> Option<Result<Value, msg::MsgError>> {
    fn j<T: RosMsg>(data: &[u8]) -> Result<Value, msg::MsgError> {
        let v: T = msg::from_cdr(data)?;
        serde_json::to_value(&v).map_err(|e| msg::MsgError::Decode {
            ty: T::DEF.name,
            len: data.len(),
            message: e.to_string(),
        })
    }
    Some(match schema {
        "rollbase_msgs/msg/Feedback" => j::<msg::Feedback>(data),
        "rollbase_msgs/msg/Reference" => j::<msg::Reference>(data),
        "rollbase_msgs/msg/Command" => j::<msg::CycleCommand>(data),
        "rollbase_msgs/msg/Pose" => j::<msg::CyclePose>(data),
        "rollbase_msgs/msg/Icr" => j::<msg::Icr>(data),
        "rollbase_msgs/msg/Supervisor" => j::<msg::Supervisor>(data),
        "rollbase_msgs/msg/Timing" => j::<msg::Timing>(data),
        "rollbase_msgs/msg/FrameRejection" => j::<msg::FrameRejection>(data),
        "can_msgs/msg/Frame" => j::<msg::CanFrame>(data),
        _ => return None,
    })
}

/// Reads the per-cycle messages of a recording as (topic, log time ns, JSON value), for plots
/// and tests. CDR messages of the `rollbase_msgs` and `can_msgs` types are decoded (other
/// topics, e.g. `/odom`, are skipped); recordings of earlier versions (JSON messages) are read
/// as they are. Chunk CRCs are checked: a damaged chunk is an error naming its position, not
/// silently plotted data.
pub fn read_recording(path: impl AsRef<Path>) -> Result<Vec<(String, u64, Value)>, RecordError> {
    let p = path.as_ref().display().to_string();
    let bytes = read_bounded(path.as_ref())?;
    let fmt = |message: String| RecordError::Format {
        path: p.clone(),
        message,
    };
    let options = mcap::read::Options::ValidateChunkCrcs.into();
    let stream = mcap::MessageStream::new_with_options(&bytes, options)
        .map_err(|e| fmt(format!("not an MCAP file: {e}")))?;
    let mut out = Vec::new();
    for (k, m) in stream.enumerate() {
        let m = m.map_err(|e| match e {
            mcap::McapError::BadChunkCrc { saved, calculated } => fmt(format!(
                "chunk CRC mismatch after {k} good messages (stored {saved:#010x}, computed {calculated:#010x}): the file is damaged; `rollbase recover` can salvage the intact chunks"
            )),
            e => fmt(format!("corrupt MCAP data after {k} good messages: {e}")),
        })?;
        let topic = m.channel.topic.clone();
        let v = match m.channel.message_encoding.as_str() {
            "json" => serde_json::from_slice(&m.data)
                .map_err(|e| fmt(format!("message {k} on {topic} is not JSON: {e}")))?,
            "cdr" => {
                let schema = m
                    .channel
                    .schema
                    .as_ref()
                    .map(|s| s.name.as_str())
                    .unwrap_or("");
                match decode_to_json(schema, &m.data) {
                    Some(r) => r.map_err(|e| fmt(format!("message {k} on {topic}: {e}")))?,
                    None => continue,
                }
            }
            _ => continue,
        };
        out.push((topic, m.log_time, v));
    }
    Ok(out)
}

// ---------------------------------------------------------------------------------------------
// Recovery
// ---------------------------------------------------------------------------------------------

/// What [`recover`] salvaged.
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct RecoverReport {
    /// Messages written to the new file, per topic.
    pub messages: BTreeMap<String, u64>,
    /// Whether the input already had a valid footer (then nothing was missing).
    pub had_footer: bool,
    /// Why reading stopped before the end of the input, if it did (truncation, damage).
    pub stopped: Option<String>,
}

impl RecoverReport {
    /// Total messages recovered.
    pub fn total(&self) -> u64 {
        self.messages.values().sum()
    }
}

/// Rewrites a recording that has no footer (the writer was killed) or a damaged tail into
/// `out`, with a complete index and summary: every schema, channel, metadata record and every
/// message of the intact chunks up to the first damage. `out` must not exist (the input is
/// never overwritten; neither is anything else).
pub fn recover(input: &Path, out: &Path) -> Result<RecoverReport, RecordError> {
    let ip = input.display().to_string();
    let op = out.display().to_string();
    if let (Ok(a), Ok(b)) = (input.canonicalize(), out.canonicalize()) {
        if a == b {
            return Err(RecordError::Format {
                path: op,
                message: "the output is the input: give another --out path".into(),
            });
        }
    }
    let bytes = read_bounded(input)?;
    let had_footer = mcap::read::footer(&bytes).is_ok() && bytes.ends_with(mcap::MAGIC);
    if !bytes.starts_with(mcap::MAGIC) {
        return Err(RecordError::Format {
            path: ip,
            message: "does not start with the MCAP magic: not an MCAP recording".into(),
        });
    }
    // Metadata records, from a linear scan of the top-level records.
    let mut metadata = Vec::new();
    let lenient = mcap::read::Options::IgnoreEndMagic;
    if let Ok(reader) = mcap::read::LinearReader::new_with_options(&bytes, lenient.into()) {
        for r in reader {
            match r {
                Ok(mcap::records::Record::Metadata(m)) => metadata.push(m),
                Ok(_) => {}
                Err(_) => break,
            }
        }
    }
    let file = std::fs::OpenOptions::new()
        .write(true)
        .create_new(true)
        .open(out)
        .map_err(|source| RecordError::Io {
            path: op.clone(),
            source,
        })?;
    let mut header_profile = String::from("ros2");
    if let Ok(mut reader) = mcap::read::LinearReader::new_with_options(&bytes, lenient.into()) {
        if let Some(Ok(mcap::records::Record::Header(h))) = reader.next() {
            header_profile = h.profile;
        }
    }
    let mut writer = mcap::WriteOptions::new()
        .compression(None)
        .profile(header_profile)
        .library("rollbase recover")
        .chunk_size(Some(CHUNK_SIZE))
        .create(BufWriter::new(file))
        .map_err(|e| mcap_error(&op, e))?;
    for m in &metadata {
        writer.write_metadata(m).map_err(|e| mcap_error(&op, e))?;
    }
    let mut report = RecoverReport {
        had_footer,
        ..Default::default()
    };
    let options = lenient | mcap::read::Options::ValidateChunkCrcs;
    let stream = mcap::MessageStream::new_with_options(&bytes, options).map_err(|e| {
        RecordError::Format {
            path: ip.clone(),
            message: format!("not an MCAP file: {e}"),
        }
    })?;
    let mut schema_ids: BTreeMap<u16, u16> = BTreeMap::new();
    let mut channel_ids: BTreeMap<u16, u16> = BTreeMap::new();
    for m in stream {
        let m = match m {
            Ok(m) => m,
            Err(e) => {
                report.stopped = Some(e.to_string());
                break;
            }
        };
        let ch = &m.channel;
        let cid = match channel_ids.get(&ch.id) {
            Some(&c) => c,
            None => {
                let sid = match &ch.schema {
                    Some(s) => match schema_ids.get(&s.id) {
                        Some(&x) => x,
                        None => {
                            let x = writer
                                .add_schema(&s.name, &s.encoding, &s.data)
                                .map_err(|e| mcap_error(&op, e))?;
                            schema_ids.insert(s.id, x);
                            x
                        }
                    },
                    None => 0,
                };
                let c = writer
                    .add_channel(sid, &ch.topic, &ch.message_encoding, &ch.metadata)
                    .map_err(|e| mcap_error(&op, e))?;
                channel_ids.insert(ch.id, c);
                c
            }
        };
        writer
            .write_to_known_channel(
                &mcap::records::MessageHeader {
                    channel_id: cid,
                    sequence: m.sequence,
                    log_time: m.log_time,
                    publish_time: m.publish_time,
                },
                &m.data,
            )
            .map_err(|e| mcap_error(&op, e))?;
        *report.messages.entry(ch.topic.clone()).or_default() += 1;
    }
    writer.finish().map_err(|e| mcap_error(&op, e))?;
    let mut inner = writer.into_inner();
    inner.flush().map_err(|source| RecordError::Io {
        path: op.clone(),
        source,
    })?;
    Ok(report)
}

#[cfg(test)]
mod tests {
    use super::*;
    use rollbase_control::record::FrameRecord;

    fn tmp(name: &str) -> std::path::PathBuf {
        let d = std::env::temp_dir().join(format!("rollbase-rec-{name}-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&d);
        std::fs::create_dir_all(&d).unwrap();
        d
    }

    fn cycle(k: u64) -> CycleRecord {
        let mut r = CycleRecord::new(k, k as f64 * 0.004, 4);
        r.push_rx(FrameRecord {
            t: r.t + 0.001,
            id: 0x181,
            len: 8,
            data: [1, 2, 3, 4, 5, 6, 7, 8],
            error: None,
            bus: 0,
        });
        if k.is_multiple_of(5) {
            r.push_rx(FrameRecord {
                t: r.t + 0.0015,
                id: 0x182,
                len: 8,
                data: [9; 8],
                error: Some("crc"),
                bus: 0,
            });
        }
        r.push_tx(FrameRecord {
            t: r.t,
            id: 0x80,
            len: 4,
            data: [0; 8],
            error: None,
            bus: 0,
        });
        r.pose.x = k as f64;
        r
    }

    #[test]
    fn writes_and_reads_back_every_cycle_topic() {
        let dir = tmp("rt");
        let path = dir.join("t.mcap");
        let mut rec = McapRecorder::create(&path, &BTreeMap::new()).unwrap();
        for k in 0..10u64 {
            rec.write_cycle(&cycle(k), &[[0.3, 0.2]; 4]).unwrap();
        }
        let summary = rec.finish().unwrap();
        for t in TOPICS {
            let want = if t == "/can/rejected" {
                2
            } else if t == "/can/rx" {
                12
            } else {
                10
            };
            assert_eq!(summary.messages[t], want, "topic {t}");
        }
        let msgs = read_recording(&path).unwrap();
        assert_eq!(msgs.len(), 12 + 10 + 2 + 7 * 10);
        let poses: Vec<f64> = msgs
            .iter()
            .filter(|(t, _, _)| t == "/pose")
            .map(|(_, _, v)| v["x"].as_f64().unwrap())
            .collect();
        assert_eq!(poses, (0..10).map(|k| k as f64).collect::<Vec<_>>());
        let pose = &msgs.iter().find(|(t, _, _)| t == "/pose").unwrap().2;
        assert_eq!(pose["has_truth"], false);
        assert!(pose["true_x"].is_null(), "NaN reads back as null");
        let rx = msgs.iter().find(|(t, _, _)| t == "/can/rx").unwrap();
        assert_eq!(rx.2["id"], 0x181);
        assert_eq!(rx.2["data"], serde_json::json!([1, 2, 3, 4, 5, 6, 7, 8]));
        assert_eq!(rx.1, 1_000_000, "log time of the frame is its receive time");
        let rej = msgs.iter().find(|(t, _, _)| t == "/can/rejected").unwrap();
        assert_eq!(rej.2["error"], "crc");
        let icr = &msgs.iter().find(|(t, _, _)| t == "/icr").unwrap().2;
        assert_eq!(icr["at_infinity"], true);
        assert_eq!(icr["nearest_wheel"], -1);
    }

    #[test]
    fn schemas_are_ros2msg_with_full_definitions_and_messages_cdr() {
        let dir = tmp("schema");
        let path = dir.join("t.mcap");
        let mut rec = McapRecorder::create(&path, &BTreeMap::new()).unwrap();
        rec.write_cycle(&cycle(0), &[[0.3, 0.2]; 4]).unwrap();
        let mut s = BaseState {
            n: 4,
            log_time_ns: 5,
            ..Default::default()
        };
        s.odometry.pose.x = 2.0;
        rec.write_state(&s).unwrap();
        rec.finish().unwrap();
        let bytes = std::fs::read(&path).unwrap();
        let summary = mcap::Summary::read(&bytes).unwrap().unwrap();
        let mut names = Vec::new();
        for ch in summary.channels.values() {
            let schema = ch.schema.as_ref().unwrap();
            assert_eq!(schema.encoding, "ros2msg", "{}", ch.topic);
            assert_eq!(ch.message_encoding, "cdr", "{}", ch.topic);
            names.push((ch.topic.clone(), schema.name.clone()));
            if schema.name == "nav_msgs/msg/Odometry" {
                let text = std::str::from_utf8(&schema.data).unwrap();
                assert_eq!(text, msg::ODOMETRY.full_definition());
                assert!(text.contains("\nMSG: geometry_msgs/Quaternion\n"));
            }
        }
        names.sort();
        assert!(names.contains(&("/odom".into(), "nav_msgs/msg/Odometry".into())));
        assert!(names.contains(&("/can/rx".into(), "can_msgs/msg/Frame".into())));
        assert!(names.contains(&("/icr".into(), "rollbase_msgs/msg/Icr".into())));
        let header = mcap::read::LinearReader::new(&bytes)
            .unwrap()
            .next()
            .unwrap()
            .unwrap();
        match header {
            mcap::records::Record::Header(h) => assert_eq!(h.profile, "ros2"),
            r => panic!("first record {r:?}"),
        }
        // The odometry message decodes with its header.
        for m in mcap::MessageStream::new(&bytes).unwrap() {
            let m = m.unwrap();
            assert_eq!(&m.data[..4], &msg::CDR_LE_HEADER);
            if m.channel.topic == "/odom" {
                let o: msg::Odometry = msg::from_cdr(&m.data).unwrap();
                assert_eq!(o.pose.pose.position.x, 2.0);
                assert_eq!(o.header.frame_id, "odom");
                assert_eq!(m.log_time, 5);
            }
        }
    }

    #[test]
    fn a_fixed_footprint_records_no_leg_joints_and_no_leg_topic() {
        let dir = tmp("fixed");
        let path = dir.join("f.mcap");
        let mut rec = McapRecorder::create(&path, &BTreeMap::new()).unwrap();
        for k in 0..50u64 {
            let mut s = BaseState {
                cycle: k,
                t: k as f64 * 0.004,
                log_time_ns: k * 4_000_000,
                n: 3,
                ..Default::default()
            };
            for j in &mut s.joints[..3] {
                j.no_leg = true;
                j.leg = 0.3;
            }
            rec.write_state(&s).unwrap();
        }
        let s = rec.finish().unwrap();
        assert_eq!(s.messages["/joint_states"], 10);
        assert!(
            s.messages.keys().all(|t| !t.contains("leg")),
            "{:?}",
            s.messages
        );
        let bytes = std::fs::read(&path).unwrap();
        let mut seen = 0;
        for m in mcap::MessageStream::new(&bytes).unwrap() {
            let m = m.unwrap();
            if m.channel.topic == "/joint_states" {
                let j: msg::JointState = msg::from_cdr(&m.data).unwrap();
                assert_eq!(j.name.len(), 6, "{:?}", j.name);
                assert!(j.name.iter().all(|n| !n.contains("leg")), "{:?}", j.name);
                assert_eq!(j.position.len(), 6);
                seen += 1;
            }
        }
        assert_eq!(seen, 10);
        let _ = std::fs::remove_dir_all(dir);
    }

    #[test]
    fn state_topics_are_decimated_and_commands_recorded() {
        let dir = tmp("state");
        let path = dir.join("t.mcap");
        let mut rec = McapRecorder::create(&path, &BTreeMap::new()).unwrap();
        for k in 0..500u64 {
            let s = BaseState {
                cycle: k,
                t: k as f64 * 0.004,
                log_time_ns: k * 4_000_000,
                n: 4,
                ..Default::default()
            };
            rec.write_state(&s).unwrap();
        }
        let ev = CommandEvent {
            t: 0.1,
            kind: CommandKind::Motion(rollbase_control::ports::MotionCommand {
                twist: rollbase_control::types::Twist {
                    vx: 0.5,
                    vy: 0.25,
                    omega: -0.125,
                },
                legs: None,
            }),
        };
        rec.write_command(&ev, 100_000_000).unwrap();
        rec.write_command(
            &CommandEvent {
                t: 0.2,
                kind: CommandKind::Legs(rollbase_control::ports::LegTargets::from_slice(&[
                    0.4, 0.41, 0.42, 0.43,
                ])),
            },
            200_000_000,
        )
        .unwrap();
        rec.write_command(
            &CommandEvent {
                t: 0.3,
                kind: CommandKind::Stop,
            },
            300_000_000,
        )
        .unwrap();
        let s = rec.finish().unwrap();
        let m = &s.messages;
        assert_eq!(m["/odom"], 100);
        assert_eq!(m["/tf"], 100);
        assert_eq!(m["/joint_states"], 100);
        assert_eq!(m["/diagnostics"], 2);
        assert_eq!(m["/supervisor_state"], 2);
        assert_eq!(m["/cmd_vel"], 1);
        assert_eq!(m["/leg_commands"], 1);
        assert!(!m.contains_key("/pose"), "no cycle written, no cycle topic");
        let bytes = std::fs::read(&path).unwrap();
        for msg_ in mcap::MessageStream::new(&bytes).unwrap() {
            let msg_ = msg_.unwrap();
            if msg_.channel.topic == "/cmd_vel" {
                let t: msg::Twist = msg::from_cdr(&msg_.data).unwrap();
                assert_eq!((t.linear.x, t.linear.y, t.angular.z), (0.5, 0.25, -0.125));
            }
        }
    }

    #[test]
    fn write_errors_carry_the_os_cause() {
        // /dev/full accepts the open and fails every write with ENOSPC.
        if !Path::new("/dev/full").exists() {
            eprintln!("skipped: no /dev/full");
            return;
        }
        let mut rec = match McapRecorder::create("/dev/full", &BTreeMap::new()) {
            Err(e) => {
                assert!(e.to_string().contains("No space left on device"), "{e}");
                return;
            }
            Ok(r) => r,
        };
        let mut err = None;
        for k in 0..2000u64 {
            if let Err(e) = rec.write_cycle(&cycle(k), &[[0.3, 0.2]; 4]) {
                err = Some(e);
                break;
            }
        }
        let e = match err {
            Some(e) => e,
            None => rec.finish().unwrap_err(),
        };
        assert!(matches!(e, RecordError::Io { .. }), "{e:?}");
        assert!(e.to_string().contains("No space left on device"), "{e}");
    }

    #[test]
    fn reading_garbage_a_device_or_a_directory_is_a_typed_error() {
        let dir = tmp("bad");
        let path = dir.join("bad.mcap");
        std::fs::write(&path, b"this is not mcap").unwrap();
        assert!(matches!(
            read_recording(&path),
            Err(RecordError::Format { .. })
        ));
        let e = read_recording(&dir).unwrap_err().to_string();
        assert!(e.contains("not a regular file"), "{e}");
        if Path::new("/dev/zero").exists() {
            let e = read_recording("/dev/zero").unwrap_err().to_string();
            assert!(e.contains("not a regular file"), "{e}");
        }
    }

    #[test]
    fn a_flipped_byte_in_a_chunk_is_refused() {
        let dir = tmp("crc");
        let path = dir.join("t.mcap");
        let mut rec = McapRecorder::create(&path, &BTreeMap::new()).unwrap();
        for k in 0..50u64 {
            rec.write_cycle(&cycle(k), &[[0.3, 0.2]; 4]).unwrap();
        }
        rec.finish().unwrap();
        let mut bytes = std::fs::read(&path).unwrap();
        // Flip a digit of a pose value: find the f64 of x = 17.0 in the data.
        let needle = 17.0f64.to_le_bytes();
        let at = bytes
            .windows(8)
            .position(|w| w == needle)
            .expect("the value is in the file");
        bytes[at + 6] ^= 0x01;
        std::fs::write(&path, &bytes).unwrap();
        let e = read_recording(&path).unwrap_err().to_string();
        assert!(e.contains("chunk CRC mismatch"), "{e}");
    }

    #[test]
    fn an_abandoned_recording_has_no_footer_and_recover_reads_its_chunks() {
        let dir = tmp("abandon");
        let path = dir.join("run.mcap");
        let mut rec = McapRecorder::create(&path, &BTreeMap::new()).unwrap();
        for k in 0..1000u64 {
            rec.write_cycle(&cycle(k), &[[0.3, 0.2]; 4]).unwrap();
        }
        let len = rec.abandon();
        let bytes = std::fs::read(&path).unwrap();
        assert_eq!(len, bytes.len() as u64);
        assert!(len > CHUNK_SIZE, "{len} bytes: more than one chunk written");
        // Nothing finished it: no summary, no footer (not even when dropped).
        assert!(!bytes.ends_with(mcap::MAGIC) || mcap::read::footer(&bytes).is_err());
        assert!(read_recording(&path).is_err());
        let fixed = dir.join("fixed.mcap");
        let rep = recover(&path, &fixed).unwrap();
        assert!(!rep.had_footer);
        assert!(rep.total() > 0);
        assert_eq!(read_recording(&fixed).unwrap().len() as u64, rep.total());
        let _ = std::fs::remove_dir_all(dir);
    }

    #[test]
    fn recover_rewrites_a_truncated_file_and_never_overwrites() {
        let dir = tmp("recover");
        let path = dir.join("run.mcap");
        let mut meta = BTreeMap::new();
        meta.insert("scenario".to_string(), "seed000".to_string());
        let mut rec = McapRecorder::create(&path, &meta).unwrap();
        for k in 0..3000u64 {
            rec.write_cycle(&cycle(k), &[[0.3, 0.2]; 4]).unwrap();
        }
        let full = rec.finish().unwrap();
        let total: u64 = full.messages.values().sum();
        let bytes = std::fs::read(&path).unwrap();
        // Cut the file in the middle of the data: as after kill -9 (no footer, a torn chunk).
        let broken = dir.join("broken.mcap");
        std::fs::write(&broken, &bytes[..bytes.len() * 2 / 3]).unwrap();
        assert!(
            read_recording(&broken).is_err(),
            "the torn file is an error"
        );
        let fixed = dir.join("fixed.mcap");
        let rep = recover(&broken, &fixed).unwrap();
        assert!(!rep.had_footer);
        assert!(rep.stopped.is_some());
        let got = rep.total();
        assert!(got > total / 3 && got < total, "{got} of {total}");
        // The new file is complete: summary, statistics, metadata, and it reads.
        let fb = std::fs::read(&fixed).unwrap();
        let summary = mcap::Summary::read(&fb).unwrap().expect("summary");
        assert_eq!(summary.stats.unwrap().message_count, got);
        assert_eq!(read_recording(&fixed).unwrap().len() as u64, got);
        let idx = &summary.metadata_indexes;
        assert_eq!(idx.len(), 1);
        assert_eq!(
            mcap::read::metadata(&fb, &idx[0]).unwrap().metadata["scenario"],
            "seed000"
        );
        // Never overwrite: an existing output, or the input itself, is refused.
        let before = std::fs::read(&broken).unwrap();
        assert!(recover(&broken, &fixed).is_err());
        assert!(recover(&broken, &broken).is_err());
        assert_eq!(std::fs::read(&broken).unwrap(), before);
        // A complete file recovers whole.
        let again = dir.join("again.mcap");
        let rep = recover(&path, &again).unwrap();
        assert!(rep.had_footer && rep.stopped.is_none());
        assert_eq!(rep.total(), total);
    }
}
