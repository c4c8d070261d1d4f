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
use rollbase_control::runtime::record::CycleRecord;
use rollbase_control::service::ports::{BaseState, CommandEvent, CommandKind};
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
    /// On a platform with two buses, the interface of each bus: a frame of bus b gets
    /// `bus_interfaces[b]` as its `frame_id` (`can_interface` when there is none).
    pub bus_interfaces: Vec<String>,
}

impl Default for RecordOptions {
    fn default() -> Self {
        Self {
            ros2: Ros2Options::default(),
            can_interface: "can".into(),
            bus_interfaces: Vec::new(),
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
    bus_interfaces: Vec<String>,
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
            bus_interfaces: opts.bus_interfaces.clone(),
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
        // The interface of each bus (at most two: one clone each per cycle).
        let iface_of = |b: usize| {
            self.bus_interfaces
                .get(b)
                .unwrap_or(&self.can_interface)
                .clone()
        };
        let ifaces = [iface_of(0), iface_of(1)];
        for f in &r.rx[..r.n_rx.min(r.rx.len())] {
            let iface = &ifaces[usize::from(f.bus).min(1)];
            let len = f.len.min(8);
            let frame = msg::CanFrame {
                header: Header::new(at(f.t), iface),
                id: u32::from(f.id),
                dlc: len,
                data: f.data,
                ..Default::default()
            };
            self.put(RX, at(f.t), &frame)?;
            if let Some(kind) = f.error {
                let rej = msg::FrameRejection {
                    header: Header::new(at(f.t), iface),
                    id: u32::from(f.id),
                    dlc: len,
                    data: f.data,
                    error: kind.to_string(),
                };
                self.put(REJECTED, at(f.t), &rej)?;
            }
        }
        for f in &r.tx[..r.n_tx.min(r.tx.len())] {
            let iface = &ifaces[usize::from(f.bus).min(1)];
            let frame = msg::CanFrame {
                header: Header::new(at(f.t), iface),
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
        let legs_msg = |l: &rollbase_control::service::ports::LegTargets| msg::Float64MultiArray {
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

/// A region of the input that [`recover`] could not use.
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct SkippedRegion {
    /// Byte offset in the input where the region starts.
    pub offset: u64,
    /// Its length in bytes.
    pub length: u64,
    /// Why it was skipped (a chunk whose CRC does not match, a damaged record …).
    pub reason: String,
    /// For a chunk: the first and last log time (ns) its header claims (the header is not
    /// covered by the CRC: treat these as a hint).
    pub log_times: Option<(u64, u64)>,
}

/// What [`recover`] salvaged.
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct RecoverReport {
    /// Messages written to the new file, per topic.
    pub messages: BTreeMap<String, u64>,
    /// Whether the input already had a valid footer (then nothing was missing).
    pub had_footer: bool,
    /// Why reading stopped before the end of the input, if it did (a record cut off at the end
    /// of the file: the chunk a killed writer was filling).
    pub stopped: Option<String>,
    /// Damaged regions that were skipped (at most [`MAX_SKIPPED_REPORTED`] are listed; the
    /// rest are counted in `skipped_more`). Every intact chunk after them is kept.
    pub skipped: Vec<SkippedRegion>,
    /// Skipped regions beyond those listed.
    pub skipped_more: u64,
    /// Messages of intact chunks that could not be written because their channel was defined
    /// only in a damaged region.
    pub orphaned: u64,
}

/// Most skipped regions [`RecoverReport::skipped`] lists.
pub const MAX_SKIPPED_REPORTED: usize = 1000;

impl RecoverReport {
    /// Total messages recovered.
    pub fn total(&self) -> u64 {
        self.messages.values().sum()
    }

    fn skip(&mut self, r: SkippedRegion) {
        // A region that continues the last one is the same damage.
        if let Some(last) = self.skipped.last_mut() {
            if last.offset + last.length == r.offset {
                last.length += r.length;
                return;
            }
        }
        if self.skipped.len() < MAX_SKIPPED_REPORTED {
            self.skipped.push(r);
        } else {
            self.skipped_more += 1;
        }
    }
}

/// A bounds-checked little-endian reader over one record's body: every length field is
/// checked against the bytes that are there before anything is taken, so a damaged length
/// is an error, never a huge allocation.
struct Body<'a> {
    b: &'a [u8],
    p: usize,
}

impl<'a> Body<'a> {
    fn new(b: &'a [u8]) -> Self {
        Self { b, p: 0 }
    }
    fn take(&mut self, n: usize) -> Option<&'a [u8]> {
        let end = self.p.checked_add(n)?;
        let s = self.b.get(self.p..end)?;
        self.p = end;
        Some(s)
    }
    fn u16(&mut self) -> Option<u16> {
        Some(u16::from_le_bytes(self.take(2)?.try_into().ok()?))
    }
    fn u32(&mut self) -> Option<u32> {
        Some(u32::from_le_bytes(self.take(4)?.try_into().ok()?))
    }
    fn u64(&mut self) -> Option<u64> {
        Some(u64::from_le_bytes(self.take(8)?.try_into().ok()?))
    }
    fn bytes32(&mut self) -> Option<&'a [u8]> {
        let n = self.u32()? as usize;
        self.take(n)
    }
    fn string(&mut self) -> Option<String> {
        std::str::from_utf8(self.bytes32()?)
            .ok()
            .map(str::to_string)
    }
    fn map(&mut self) -> Option<BTreeMap<String, String>> {
        let mut inner = Body::new(self.bytes32()?);
        let mut m = BTreeMap::new();
        while inner.p < inner.b.len() {
            let k = inner.string()?;
            let v = inner.string()?;
            m.insert(k, v);
        }
        Some(m)
    }
    fn rest(&mut self) -> &'a [u8] {
        let s = &self.b[self.p.min(self.b.len())..];
        self.p = self.b.len();
        s
    }
}

/// One top-level or chunked record: opcode and body, at `offset` in its buffer.
struct RawRecord<'a> {
    op: u8,
    body: &'a [u8],
    /// Offset of the record (its opcode) in the buffer it was read from.
    offset: usize,
    /// Offset just past it.
    end: usize,
}

/// The record at `at` in `b`, if its length field fits in `b`.
fn record_at(b: &[u8], at: usize) -> Option<RawRecord<'_>> {
    let op = *b.get(at)?;
    let len = u64::from_le_bytes(b.get(at + 1..at + 9)?.try_into().ok()?);
    let start = at + 9;
    let end = start.checked_add(usize::try_from(len).ok()?)?;
    Some(RawRecord {
        op,
        body: b.get(start..end)?,
        offset: at,
        end,
    })
}

/// A chunk whose records are intact: its header times and its (uncompressed) records.
struct GoodChunk<'a> {
    records: &'a [u8],
}

/// Checks a chunk record's body: the header's sizes agree with the record's length, the
/// chunk is uncompressed (rollbase writes it so; this build has no decompressor) and the
/// CRC of its records matches. `Err` says why not, with the header's times when it could be
/// read.
#[allow(clippy::type_complexity)]
fn check_chunk(body: &[u8]) -> Result<GoodChunk<'_>, (String, Option<(u64, u64)>)> {
    let mut r = Body::new(body);
    let times = (r.u64(), r.u64());
    let times = match times {
        (Some(a), Some(b)) => Some((a, b)),
        _ => return Err(("chunk header cut short".into(), None)),
    };
    let (Some(size), Some(crc), Some(compression), Some(compressed)) =
        (r.u64(), r.u32(), r.bytes32(), r.u64())
    else {
        return Err((
            "chunk header damaged (lengths beyond the record)".into(),
            times,
        ));
    };
    let records = r.rest();
    if compressed != records.len() as u64 || size != compressed {
        return Err((
            format!(
                "chunk sizes do not match its record (header: {size} bytes uncompressed, {compressed} stored; record: {} bytes)",
                records.len()
            ),
            times,
        ));
    }
    if !compression.is_empty() {
        return Err((
            format!(
                "chunk compressed with {:?}: this build reads uncompressed chunks only",
                String::from_utf8_lossy(&compression[..compression.len().min(16)])
            ),
            times,
        ));
    }
    if crc != 0 {
        let calculated = crc32fast::hash(records);
        if calculated != crc {
            return Err((
                format!("chunk CRC mismatch (stored {crc:#010x}, computed {calculated:#010x})"),
                times,
            ));
        }
    }
    Ok(GoodChunk { records })
}

/// The opcodes a record boundary in an MCAP data section can hold.
fn known_opcode(op: u8) -> bool {
    (mcap::records::op::HEADER..=mcap::records::op::DATA_END).contains(&op)
}

/// Whether a record that checks starts at `at` (or the data ends there): a chunk that
/// checks, a message index whose length is its entries', a data-end record. After a damaged
/// chunk this decides whether its length can be trusted to find the next record.
fn checked_boundary(b: &[u8], at: usize) -> bool {
    use mcap::records::op;
    if at == b.len() {
        return true;
    }
    let Some(r) = record_at(b, at) else {
        return false;
    };
    match r.op {
        op::CHUNK => check_chunk(r.body).is_ok(),
        op::MESSAGE_INDEX => {
            let mut body = Body::new(r.body);
            let (Some(_channel), Some(len)) = (body.u16(), body.u32()) else {
                return false;
            };
            len % 16 == 0 && r.body.len() == 6 + len as usize
        }
        op::DATA_END => r.body.len() == 4,
        _ => false,
    }
}

/// The next offset at or after `from` where an intact chunk with a CRC starts (a record
/// whose every length agrees and whose CRC matches), if any.
fn next_good_chunk(b: &[u8], from: usize) -> Option<usize> {
    let mut at = from;
    while at < b.len() {
        let i = at + memchr_byte(&b[at..], mcap::records::op::CHUNK)?;
        if let Some(r) = record_at(b, i) {
            // A CRC of 0 means "not computed": such a chunk cannot prove itself.
            let has_crc = r.body.get(24..28).is_some_and(|c| c != [0, 0, 0, 0]);
            if has_crc && check_chunk(r.body).is_ok() {
                return Some(i);
            }
        }
        at = i + 1;
    }
    None
}

fn memchr_byte(b: &[u8], x: u8) -> Option<usize> {
    b.iter().position(|&c| c == x)
}

/// What the scan of a file found: the intact places of the data section in order, the
/// definitions, the metadata and what was skipped.
#[derive(Default)]
struct Scan<'a> {
    /// Intact record sequences in file order: a chunk's records, or one top-level message.
    pieces: Vec<&'a [u8]>,
    schemas: BTreeMap<u16, (String, String, &'a [u8])>,
    channels: BTreeMap<u16, (u16, String, String, BTreeMap<String, String>)>,
    metadata: Vec<mcap::records::Metadata>,
    profile: Option<String>,
}

/// Takes the definitions (schemas, channels) and metadata out of a sequence of records;
/// `false` when a record is damaged (the sequence is then not used).
fn definitions<'a>(scan: &mut Scan<'a>, records: &'a [u8], top_level: bool) -> bool {
    use mcap::records::op;
    let mut at = 0;
    while at < records.len() {
        let Some(r) = record_at(records, at) else {
            return false;
        };
        let mut body = Body::new(r.body);
        let ok = match r.op {
            op::SCHEMA => (|| {
                let id = body.u16()?;
                let name = body.string()?;
                let enc = body.string()?;
                let data = body.bytes32()?;
                scan.schemas.entry(id).or_insert((name, enc, data));
                Some(())
            })()
            .is_some(),
            op::CHANNEL => (|| {
                let id = body.u16()?;
                let sid = body.u16()?;
                let topic = body.string()?;
                let enc = body.string()?;
                let meta = body.map()?;
                scan.channels.entry(id).or_insert((sid, topic, enc, meta));
                Some(())
            })()
            .is_some(),
            op::MESSAGE => r.body.len() >= 22,
            op::METADATA if top_level => (|| {
                let name = body.string()?;
                let metadata = body.map()?;
                scan.metadata
                    .push(mcap::records::Metadata { name, metadata });
                Some(())
            })()
            .is_some(),
            op::HEADER if top_level => {
                scan.profile = body.string();
                scan.profile.is_some()
            }
            o => known_opcode(o),
        };
        if !ok {
            return false;
        }
        at = r.end;
    }
    true
}

/// Walks the file's records from the magic on: intact chunks are kept, a chunk whose CRC (or
/// any length) does not check is skipped, and after a damaged record the next intact chunk is
/// searched for, so one damaged place costs only what it damaged.
fn scan<'a>(b: &'a [u8], report: &mut RecoverReport) -> Scan<'a> {
    use mcap::records::op;
    let mut s = Scan::default();
    let mut pos = mcap::MAGIC.len();
    let mut in_summary = false;
    while pos < b.len() {
        if b.len() - pos < 9 || (b.len() - pos == mcap::MAGIC.len() && b[pos..] == *mcap::MAGIC) {
            if b[pos..] != *mcap::MAGIC {
                report.stopped = Some(format!(
                    "the last {} bytes (from offset {pos}) are a cut-off record",
                    b.len() - pos
                ));
            }
            break;
        }
        let rec = record_at(b, pos).filter(|r| known_opcode(r.op));
        let Some(rec) = rec else {
            // The record's length runs past the end of the file, or its opcode is not one:
            // either the torn last record of a killed writer, or damage. Find the next intact
            // chunk; without one, this is where the data ends.
            match next_good_chunk(b, pos + 1) {
                Some(next) => {
                    report.skip(SkippedRegion {
                        offset: pos as u64,
                        length: (next - pos) as u64,
                        reason: "damaged record (its opcode or length cannot be right)".into(),
                        log_times: None,
                    });
                    pos = next;
                    continue;
                }
                None => {
                    if !in_summary {
                        report.stopped = Some(format!(
                            "the record at offset {pos} runs past the end of the file or is damaged, and no intact chunk follows ({} bytes not used)",
                            b.len() - pos
                        ));
                    }
                    break;
                }
            }
        };
        match rec.op {
            op::CHUNK if !in_summary => match check_chunk(rec.body) {
                Ok(c) => {
                    if definitions(&mut s, c.records, false) {
                        s.pieces.push(c.records);
                    } else {
                        report.skip(SkippedRegion {
                            offset: rec.offset as u64,
                            length: (rec.end - rec.offset) as u64,
                            reason: "chunk whose CRC matches holds a malformed record".into(),
                            log_times: None,
                        });
                    }
                    pos = rec.end;
                }
                Err((reason, log_times)) => {
                    // Trust the record's length only when a record that checks follows it.
                    let next = if checked_boundary(b, rec.end) {
                        rec.end
                    } else {
                        next_good_chunk(b, pos + 1).unwrap_or(b.len())
                    };
                    report.skip(SkippedRegion {
                        offset: pos as u64,
                        length: (next - pos) as u64,
                        reason,
                        log_times,
                    });
                    pos = next;
                }
            },
            op::DATA_END => {
                // The summary section follows: only its definitions are of use (they repeat
                // those of the data section, and name the channels of a damaged chunk).
                in_summary = true;
                pos = rec.end;
            }
            op::FOOTER => break,
            op::MESSAGE if in_summary => pos = rec.end,
            _ => {
                let one = &b[rec.offset..rec.end];
                if definitions(&mut s, one, !in_summary) {
                    if rec.op == op::MESSAGE {
                        s.pieces.push(one);
                    }
                    pos = rec.end;
                } else {
                    let next = next_good_chunk(b, pos + 1).unwrap_or(b.len());
                    report.skip(SkippedRegion {
                        offset: pos as u64,
                        length: (next - pos) as u64,
                        reason: format!("damaged record (opcode {:#04x})", rec.op),
                        log_times: None,
                    });
                    pos = next;
                }
            }
        }
    }
    s
}

/// [`recover`] on a file's bytes, writing the new recording to `out` (named `out_name` in
/// errors). Never panics and never allocates more than the input's size on any input.
pub fn recover_bytes<W: Write + std::io::Seek>(
    bytes: &[u8],
    out: W,
    out_name: &str,
) -> Result<(RecoverReport, W), RecordError> {
    let op = out_name;
    if !bytes.starts_with(mcap::MAGIC) {
        return Err(RecordError::Format {
            path: op.to_string(),
            message: "the input does not start with the MCAP magic: not an MCAP recording".into(),
        });
    }
    let mut report = RecoverReport {
        had_footer: mcap::read::footer(bytes).is_ok() && bytes.ends_with(mcap::MAGIC),
        ..Default::default()
    };
    let s = scan(bytes, &mut report);
    let mut writer = mcap::WriteOptions::new()
        .compression(None)
        .profile(s.profile.clone().unwrap_or_else(|| "ros2".into()))
        .library("rollbase recover")
        .chunk_size(Some(CHUNK_SIZE))
        .create(out)
        .map_err(|e| mcap_error(op, e))?;
    for m in &s.metadata {
        writer.write_metadata(m).map_err(|e| mcap_error(op, e))?;
    }
    let mut schema_ids: BTreeMap<u16, u16> = BTreeMap::new();
    let mut channel_ids: BTreeMap<u16, Option<u16>> = BTreeMap::new();
    for piece in &s.pieces {
        let mut at = 0;
        while let Some(r) = record_at(piece, at) {
            at = r.end;
            if r.op != mcap::records::op::MESSAGE {
                continue;
            }
            let mut body = Body::new(r.body);
            let (Some(cid), Some(sequence), Some(log_time), Some(publish_time)) =
                (body.u16(), body.u32(), body.u64(), body.u64())
            else {
                continue;
            };
            let data = body.rest();
            let out_cid = match channel_ids.get(&cid) {
                Some(c) => *c,
                None => {
                    let c = match s.channels.get(&cid) {
                        None => None,
                        Some((sid, topic, enc, meta)) => {
                            let out_sid = match (schema_ids.get(sid), s.schemas.get(sid)) {
                                (Some(&x), _) => x,
                                (None, Some((name, senc, sdata))) => {
                                    let x = writer
                                        .add_schema(name, senc, sdata)
                                        .map_err(|e| mcap_error(op, e))?;
                                    schema_ids.insert(*sid, x);
                                    x
                                }
                                // Schema 0 (none), or one defined only in a damaged region.
                                (None, None) => 0,
                            };
                            Some(
                                writer
                                    .add_channel(out_sid, topic, enc, meta)
                                    .map_err(|e| mcap_error(op, e))?,
                            )
                        }
                    };
                    channel_ids.insert(cid, c);
                    c
                }
            };
            let Some(out_cid) = out_cid else {
                report.orphaned += 1;
                continue;
            };
            writer
                .write_to_known_channel(
                    &mcap::records::MessageHeader {
                        channel_id: out_cid,
                        sequence,
                        log_time,
                        publish_time,
                    },
                    data,
                )
                .map_err(|e| mcap_error(op, e))?;
            let topic = &s.channels[&cid].1;
            match report.messages.get_mut(topic) {
                Some(n) => *n += 1,
                None => {
                    report.messages.insert(topic.clone(), 1);
                }
            }
        }
    }
    writer.finish().map_err(|e| mcap_error(op, e))?;
    Ok((report, writer.into_inner()))
}

/// Rewrites a recording that has no footer (the writer was killed) or damaged places into
/// `out`, with a complete index and summary: every schema, channel and metadata record and
/// every message of every intact chunk. A chunk whose CRC does not match is skipped whole
/// (none of its bytes reach the output), and so is any other damaged region; reading goes on
/// at the next intact chunk. The report lists what was skipped. `out` must not exist (the
/// input is never overwritten; neither is anything else).
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
    if !bytes.starts_with(mcap::MAGIC) {
        return Err(RecordError::Format {
            path: ip,
            message: "does not start with the MCAP magic: not an MCAP recording".into(),
        });
    }
    let file = std::fs::OpenOptions::new()
        .write(true)
        .create_new(true)
        .open(out)
        .map_err(|source| RecordError::Io {
            path: op.clone(),
            source,
        })?;
    let (report, w) = recover_bytes(&bytes, BufWriter::new(file), &op)?;
    let mut inner = w;
    inner.flush().map_err(|source| RecordError::Io {
        path: op.clone(),
        source,
    })?;
    Ok(report)
}

#[cfg(test)]
mod tests {
    use super::*;
    use rollbase_control::runtime::record::FrameRecord;

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
            kind: CommandKind::Motion(rollbase_control::service::ports::MotionCommand {
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
                kind: CommandKind::Legs(rollbase_control::service::ports::LegTargets::from_slice(
                    &[0.4, 0.41, 0.42, 0.43],
                )),
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
    /// Every message of a file as (topic, log time, bytes), read with CRC checks; and the
    /// byte ranges of its chunk records with the messages each holds.
    fn messages_of(bytes: &[u8]) -> Vec<(String, u64, Vec<u8>)> {
        let opts = mcap::read::Options::ValidateChunkCrcs.into();
        mcap::MessageStream::new_with_options(bytes, opts)
            .unwrap()
            .map(|m| {
                let m = m.unwrap();
                (m.channel.topic.clone(), m.log_time, m.data.into_owned())
            })
            .collect()
    }

    fn chunks_of(bytes: &[u8]) -> Vec<(std::ops::Range<usize>, u64)> {
        let summary = mcap::Summary::read(bytes).unwrap().expect("summary");
        let mut v: Vec<_> = summary
            .chunk_indexes
            .iter()
            .map(|c| {
                let msgs = summary
                    .read_message_indexes(bytes, c)
                    .unwrap()
                    .values()
                    .map(|x| x.len() as u64)
                    .sum();
                let start = c.chunk_start_offset as usize;
                (start..start + c.chunk_length as usize, msgs)
            })
            .collect();
        v.sort_by_key(|(r, _)| r.start);
        v
    }

    /// A finished recording of `cycles` cycles: its bytes.
    fn recording(dir: &Path, cycles: u64) -> Vec<u8> {
        let path = dir.join("run.mcap");
        let mut meta = BTreeMap::new();
        meta.insert("scenario".to_string(), "seed000".to_string());
        let mut rec = McapRecorder::create(&path, &meta).unwrap();
        for k in 0..cycles {
            rec.write_cycle(&cycle(k), &[[0.3, 0.2]; 4]).unwrap();
        }
        rec.finish().unwrap();
        std::fs::read(&path).unwrap()
    }

    #[test]
    fn recover_skips_a_damaged_chunk_and_keeps_every_intact_chunk_after_it() {
        let dir = tmp("skip");
        let bytes = recording(&dir, 6000);
        let all = messages_of(&bytes);
        let chunks = chunks_of(&bytes);
        assert!(chunks.len() >= 6, "{} chunks", chunks.len());
        // 8 bytes overwritten in the middle of the second chunk (as in issue 27); then also
        // without the footer and the summary (the file a killed writer leaves).
        let (bad, lost) = chunks[1].clone();
        let mut damaged = bytes.clone();
        let mid = (bad.start + bad.end) / 2;
        damaged[mid..mid + 8].copy_from_slice(b"DAMAGED!");
        for (name, file) in [
            ("complete", damaged.clone()),
            (
                "unfinished",
                damaged[..chunks.last().unwrap().0.end].to_vec(),
            ),
        ] {
            let input = dir.join(format!("{name}.mcap"));
            std::fs::write(&input, &file).unwrap();
            let out = dir.join(format!("{name}.recovered.mcap"));
            let rep = recover(&input, &out).unwrap();
            // Every message of every other chunk, and nothing of the damaged one.
            let got = messages_of(&std::fs::read(&out).unwrap());
            let first_bad = chunks[..1].iter().map(|c| c.1).sum::<u64>() as usize;
            let mut want = all[..first_bad].to_vec();
            want.extend_from_slice(&all[first_bad + lost as usize..]);
            assert_eq!(got.len(), want.len(), "{name}: {rep:?}");
            assert!(
                got == want,
                "{name}: the recovered messages differ from the intact ones"
            );
            assert_eq!(rep.total(), want.len() as u64);
            // What was skipped is reported: the chunk's place in the file and why.
            assert_eq!(rep.skipped.len(), 1, "{name}: {:?}", rep.skipped);
            let s = &rep.skipped[0];
            assert_eq!(s.offset, bad.start as u64, "{name}: {s:?}");
            assert_eq!(s.length, (bad.end - bad.start) as u64, "{name}: {s:?}");
            assert!(s.reason.contains("CRC"), "{name}: {s:?}");
            assert_eq!(rep.orphaned, 0);
        }
        let _ = std::fs::remove_dir_all(dir);
    }

    #[test]
    fn recover_finds_the_next_chunk_after_a_damaged_record_length() {
        let dir = tmp("resync");
        let bytes = recording(&dir, 6000);
        let all = messages_of(&bytes);
        let chunks = chunks_of(&bytes);
        // The length field of the third chunk record now claims far more than the file has
        // (or a little less than it is): the reader cannot step over it and must find the
        // next chunk by itself.
        for (name, len) in [("beyond the end", u64::MAX / 3), ("short", 1000)] {
            let mut damaged = bytes.clone();
            let at = chunks[2].0.start;
            damaged[at + 1..at + 9].copy_from_slice(&len.to_le_bytes());
            let input = dir.join(format!("in-{}.mcap", len));
            std::fs::write(&input, &damaged).unwrap();
            let out = dir.join(format!("out-{}.mcap", len));
            let rep = recover(&input, &out).unwrap();
            let before = chunks[..2].iter().map(|c| c.1).sum::<u64>() as usize;
            let lost = chunks[2].1 as usize;
            let mut want = all[..before].to_vec();
            want.extend_from_slice(&all[before + lost..]);
            let got = messages_of(&std::fs::read(&out).unwrap());
            assert!(
                got == want,
                "{name}: {} of {} messages: {rep:?}",
                got.len(),
                want.len()
            );
            assert_eq!(rep.skipped.len(), 1, "{name}: {:?}", rep.skipped);
            assert_eq!(rep.skipped[0].offset, chunks[2].0.start as u64);
            assert_eq!(
                rep.skipped[0].offset + rep.skipped[0].length,
                chunks[3].0.start as u64,
                "{name}: the skipped region ends where the next chunk starts"
            );
        }
        let _ = std::fs::remove_dir_all(dir);
    }

    #[test]
    fn recover_loses_only_the_chunks_random_bit_flips_hit() {
        let dir = tmp("flips");
        let bytes = recording(&dir, 6000);
        let all = messages_of(&bytes);
        let chunks = chunks_of(&bytes);
        let data_end = chunks.last().unwrap().0.end;
        // 20 bit flips at pseudo-random places of the data section (a fixed LCG: the test
        // is the same every run).
        let mut x: u64 = 0x2545_F491_4F6C_DD1D;
        let mut damaged = bytes.clone();
        let mut hit = std::collections::BTreeSet::new();
        for _ in 0..20 {
            x = x
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            let at = chunks[0].0.start + (x >> 20) as usize % (data_end - chunks[0].0.start);
            damaged[at] ^= 1 << ((x >> 8) % 8);
            if let Some(k) = chunks.iter().position(|c| c.0.contains(&at)) {
                hit.insert(k);
            }
        }
        let input = dir.join("in.mcap");
        std::fs::write(&input, &damaged).unwrap();
        let out = dir.join("out.mcap");
        let rep = recover(&input, &out).unwrap();
        let intact: u64 = chunks
            .iter()
            .enumerate()
            .filter(|(k, _)| !hit.contains(k))
            .map(|(_, c)| c.1)
            .sum();
        let got = messages_of(&std::fs::read(&out).unwrap());
        // Every message of a chunk no flip hit, unless its channel was declared in a damaged
        // one (then it is counted as orphaned); a flip in a chunk's header fields that the
        // CRC does not cover (its times) costs nothing, hence "at least".
        assert!(got.len() as u64 + rep.orphaned >= intact, "{rep:?}");
        assert!(
            got.len() as u64 > intact * 9 / 10,
            "{} of {intact}",
            got.len()
        );
        let set: std::collections::HashSet<_> = all.iter().collect();
        assert!(got.iter().all(|m| set.contains(m)), "only intact messages");
        assert!(
            !rep.skipped.is_empty() && rep.skipped.len() <= 20,
            "{:?}",
            rep.skipped
        );
        let _ = std::fs::remove_dir_all(dir);
    }
}
