//! From the state port to ROS 2 messages, and from ROS 2 commands to the command port: pure
//! functions, shared by the DDS node ([`super::node`]) and the recorder ([`crate::record`]) so
//! a bag holds exactly what the node publishes.
//!
//! Conventions (REP 103 units and axes, REP 105 frames):
//!
//! - `odom`: `header.frame_id` = the odometry frame, `child_frame_id` = the base frame; pose in
//!   the odometry frame, twist in the base frame. The planar 3×3 covariances of (x, y, θ) and
//!   (vx, vy, ω) go to rows/columns 0, 1 and 5 of the 6×6 (x, y, z, rot x, rot y, rot z). The
//!   odometry does not observe z, roll and pitch: their diagonal entries are [`UNOBSERVED_VARIANCE`]
//!   (1e6) and their off-diagonal entries 0, which marks them as unknown while keeping the
//!   matrix positive definite (a filter that inverts it, e.g. robot_localization, does not meet a
//!   singular matrix; in two_d_mode it ignores these entries anyway).
//! - `tf`: one transform odom → base_link with the pose and stamp of the odometry message.
//! - `joint_states`: per wheel three joints in the order steer, drive, leg (names from
//!   [`JointNames`]): steer position = steering angle (rad) and velocity = steering rate, drive
//!   position = wheel angle (rad, integrated) and velocity = wheel spin rate, leg position =
//!   extension (m) and velocity = extension rate. `effort` is empty (not measured).
//! - `diagnostics`: see [`DiagnosticsBuilder`].
//! - `supervisor_state`: `std_msgs/String`, see [`supervisor_text`].

use super::msg::{
    DiagnosticArray, DiagnosticStatus, Header, JointState, KeyValue, Odometry, Point, Pose,
    PoseWithCovariance, Quaternion, StringMsg, TFMessage, Transform, TransformStamped, Twist,
    TwistWithCovariance, Vector3,
};
use rollbase_control::service::ports::{BaseState, CommandKind, LegTargets, MotionCommand};
use rollbase_control::supervisor::SupervisorState;
use rollbase_control::types::{Twist as BodyTwist, MAX_WHEELS};

/// Variance on the diagonal of the 6×6 covariances for the unobserved z, roll and pitch.
pub const UNOBSERVED_VARIANCE: f64 = 1e6;

/// Index in the 6×6 of each planar coordinate (x, y, θ) → (x, y, rot z).
const PLANAR: [usize; 3] = [0, 1, 5];

/// Maps a planar 3×3 covariance into the row-major 6×6 of (x, y, z, rot x, rot y, rot z).
pub fn covariance_6x6(c: &[[f64; 3]; 3]) -> [f64; 36] {
    let mut out = [0.0; 36];
    for i in [2, 3, 4] {
        out[i * 6 + i] = UNOBSERVED_VARIANCE;
    }
    for (r, &rr) in PLANAR.iter().enumerate() {
        for (k, &cc) in PLANAR.iter().enumerate() {
            out[rr * 6 + cc] = c[r][k];
        }
    }
    out
}

/// The frames of the odometry messages.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Frames {
    /// Odometry frame (REP 105 `odom`).
    pub odom: String,
    /// Base frame (REP 105 `base_link`).
    pub base: String,
}

impl Default for Frames {
    fn default() -> Self {
        Self {
            odom: "odom".into(),
            base: "base_link".into(),
        }
    }
}

/// `nav_msgs/Odometry` of a state.
pub fn odometry(s: &BaseState, frames: &Frames) -> Odometry {
    let o = &s.odometry;
    Odometry {
        header: Header::new(s.log_time_ns, &frames.odom),
        child_frame_id: frames.base.clone(),
        pose: PoseWithCovariance {
            pose: Pose {
                position: Point {
                    x: o.pose.x,
                    y: o.pose.y,
                    z: 0.0,
                },
                orientation: Quaternion::from_yaw(o.pose.theta),
            },
            covariance: covariance_6x6(&o.pose_covariance),
        },
        twist: TwistWithCovariance {
            twist: Twist {
                linear: Vector3 {
                    x: o.twist.vx,
                    y: o.twist.vy,
                    z: 0.0,
                },
                angular: Vector3 {
                    x: 0.0,
                    y: 0.0,
                    z: o.twist.omega,
                },
            },
            covariance: covariance_6x6(&o.twist_covariance),
        },
    }
}

/// `tf2_msgs/TFMessage` with the transform odom → base of a state (same stamp and pose as
/// [`odometry`]).
pub fn tf(s: &BaseState, frames: &Frames) -> TFMessage {
    let p = &s.odometry.pose;
    TFMessage {
        transforms: vec![TransformStamped {
            header: Header::new(s.log_time_ns, &frames.odom),
            child_frame_id: frames.base.clone(),
            transform: Transform {
                translation: Vector3 {
                    x: p.x,
                    y: p.y,
                    z: 0.0,
                },
                rotation: Quaternion::from_yaw(p.theta),
            },
        }],
    }
}

/// Names of the joints of `sensor_msgs/JointState`: three per wheel (steer, drive, leg).
#[derive(Clone, Debug, PartialEq, Eq, Default)]
pub enum JointNames {
    /// `wheel_<i>_steer_joint`, `wheel_<i>_drive_joint`, `wheel_<i>_leg_joint` for i = 1 … n.
    #[default]
    Default,
    /// Given names, three per wheel in the order steer, drive, leg (3·n names).
    Custom(Vec<String>),
}

impl JointNames {
    /// The 3·n names for `n` wheels; custom names must be exactly 3·n.
    pub fn names(&self, n: usize) -> Result<Vec<String>, String> {
        match self {
            Self::Default => Ok((1..=n)
                .flat_map(|i| {
                    [
                        format!("wheel_{i}_steer_joint"),
                        format!("wheel_{i}_drive_joint"),
                        format!("wheel_{i}_leg_joint"),
                    ]
                })
                .collect()),
            Self::Custom(v) if v.len() == 3 * n => Ok(v.clone()),
            Self::Custom(v) => Err(format!(
                "{} joint names given for {n} wheels: give 3 per wheel (steer, drive, leg), {} in all",
                v.len(),
                3 * n
            )),
        }
    }
}

/// `sensor_msgs/JointState` of a state with the given names (3 per wheel, see [`JointNames`]).
/// A wheel without a leg ([`rollbase_control::service::ports::JointState::no_leg`]) has no leg joint:
/// its steer and drive joints only (its leg name is not used).
pub fn joint_state(s: &BaseState, names: &[String]) -> JointState {
    let n = s.n.min(MAX_WHEELS);
    let mut position = Vec::with_capacity(3 * n);
    let mut velocity = Vec::with_capacity(3 * n);
    let mut name = Vec::with_capacity(3 * n);
    for (i, j) in s.joints[..n].iter().enumerate() {
        let k = if j.no_leg { 2 } else { 3 };
        position.extend_from_slice(&[j.steer_angle, j.wheel_angle, j.leg][..k]);
        velocity.extend_from_slice(&[j.steer_rate, j.wheel_speed, j.leg_rate][..k]);
        name.extend(names.iter().skip(3 * i).take(k).cloned());
    }
    JointState {
        header: Header::new(s.log_time_ns, ""),
        name,
        position,
        velocity,
        effort: Vec::new(),
    }
}

/// The `supervisor_state` text: `<state>[: <fault reason>][ (limited by <what>, speed scale
/// <s>)][ (halting: command timeout|stop request)]`, e.g. `tracking`, `fault: stale feedback
/// …`, `tracking (limited by steering rate, speed scale 0.62)`, `tracking (halting: stop
/// request)` while a requested stop decelerates. The first word is always the state name (`idle`, `aligning`,
/// `tracking`, `stopping`, `stopped`, `fault`).
pub fn supervisor_text(s: &BaseState) -> StringMsg {
    let mut data = s.state.name().to_string();
    if let Some(r) = s.reason {
        data.push_str(&format!(": {r}"));
    }
    use rollbase_control::service::ports::Limiting;
    match s.shaping.limiting {
        Limiting::None => {}
        l @ (Limiting::Timeout | Limiting::Stop) => {
            data.push_str(&format!(" (halting: {})", l.name()));
        }
        l => data.push_str(&format!(
            " (limited by {}, speed scale {:.2})",
            l.name(),
            s.shaping.scale
        )),
    }
    StringMsg { data }
}

/// Name of a module state wire value.
fn module_state_name(raw: u8) -> &'static str {
    rollbase_driver::codec::ModuleState::from_raw(raw)
        .map(|m| m.name())
        .unwrap_or("unknown")
}

/// Feedback older than this many cycles is an ERROR (the supervisor's stale-feedback limit).
pub const STALE_CYCLES: u32 = 3;
/// Bus load above which the bus status is WARN.
pub const BUS_LOAD_WARN: f64 = 0.8;

/// Builds `diagnostic_msgs/DiagnosticArray` messages. Counters in [`BaseState`] are
/// cumulative; levels look at what changed since the previous array, so the builder keeps the
/// previous counters.
///
/// One status per module (`rollbase: wheel <i> (node <n>)`), one for the bus (`rollbase: CAN
/// bus`), one for the supervisor (`rollbase: supervisor`):
///
/// | status | ERROR | WARN | OK |
/// |---|---|---|---|
/// | module | feedback older than [`STALE_CYCLES`] cycles, or module state `fault` | frames rejected, late or lost, or watchdog trips since the last array, or state not `enabled`/`ready` | otherwise |
/// | bus | load ≥ 100 % | load > [`BUS_LOAD_WARN`], or deadline misses since the last array | otherwise |
/// | supervisor | state `fault` | commands rejected or command timeouts since the last array, or the motion limited by the command timeout | otherwise |
#[derive(Clone, Debug, Default)]
pub struct DiagnosticsBuilder {
    prev: Option<BaseState>,
    /// `hardware_id` prefix (e.g. the node name).
    pub hardware: String,
}

impl DiagnosticsBuilder {
    /// A builder whose statuses carry `hardware` in their hardware id.
    pub fn new(hardware: &str) -> Self {
        Self {
            prev: None,
            hardware: hardware.to_string(),
        }
    }

    /// The array for `s` (and remembers `s` for the next one).
    pub fn build(&mut self, s: &BaseState) -> DiagnosticArray {
        let n = s.n.min(MAX_WHEELS);
        let prev = self.prev.unwrap_or(BaseState {
            n: s.n,
            ..BaseState::default()
        });
        let kv = |k: &str, v: String| KeyValue {
            key: k.into(),
            value: v,
        };
        let mut status = Vec::with_capacity(n + 2);
        for (i, m) in s.diagnostics.modules[..n].iter().enumerate() {
            let p = &prev.diagnostics.modules[i];
            let d = |a: u64, b: u64| a.saturating_sub(b);
            let (d_rej, d_late, d_lost, d_wd) = (
                d(m.rejected, p.rejected),
                d(m.late, p.late),
                d(m.lost, p.lost),
                d(m.watchdog_trips, p.watchdog_trips),
            );
            let state = module_state_name(m.state);
            let (level, message) = if m.age_cycles > STALE_CYCLES {
                (
                    DiagnosticStatus::ERROR,
                    format!("no valid feedback for {} cycles", m.age_cycles),
                )
            } else if state == "fault" {
                (DiagnosticStatus::ERROR, "module reports a fault".into())
            } else if d_rej + d_late + d_lost + d_wd > 0 {
                (
                    DiagnosticStatus::WARN,
                    format!(
                        "since last report: {d_rej} rejected, {d_late} late, {d_lost} lost, {d_wd} watchdog trips"
                    ),
                )
            } else if state != "enabled" && state != "ready" {
                (DiagnosticStatus::WARN, format!("module state {state}"))
            } else {
                (DiagnosticStatus::OK, format!("module state {state}"))
            };
            status.push(DiagnosticStatus {
                level,
                name: format!("rollbase: wheel {} (node {})", i + 1, m.node),
                message,
                hardware_id: format!("{} node {}", self.hardware, m.node),
                values: vec![
                    kv("rejected", m.rejected.to_string()),
                    kv("late", m.late.to_string()),
                    kv("lost", m.lost.to_string()),
                    kv("watchdog_trips", m.watchdog_trips.to_string()),
                    kv("age_cycles", m.age_cycles.to_string()),
                    kv("state", state.to_string()),
                    kv("emcy_informational", m.emcy_informational.to_string()),
                    kv("emcy_faults", m.emcy_faults.to_string()),
                    kv("emcy_last", emcy_text(&m.emcy)),
                ],
            });
        }
        let g = &s.diagnostics;
        let d_miss = g
            .deadline_misses
            .saturating_sub(prev.diagnostics.deadline_misses);
        let load = g.bus_load;
        let (level, message) = if !load.is_finite() || load >= 1.0 {
            (
                DiagnosticStatus::ERROR,
                format!("bus load {:.1} %: the bus is saturated", load * 100.0),
            )
        } else if load > BUS_LOAD_WARN || d_miss > 0 {
            (
                DiagnosticStatus::WARN,
                format!(
                    "bus load {:.1} %, {d_miss} deadline misses since last report",
                    load * 100.0
                ),
            )
        } else {
            (
                DiagnosticStatus::OK,
                format!("bus load {:.1} %", load * 100.0),
            )
        };
        status.push(DiagnosticStatus {
            level,
            name: "rollbase: CAN bus".into(),
            message,
            hardware_id: format!("{} bus", self.hardware),
            values: vec![
                kv("load", format!("{load:.4}")),
                kv("deadline_misses", g.deadline_misses.to_string()),
                kv(
                    "controller_state",
                    g.can[0].state.map_or("error active", |e| e.name()).into(),
                ),
                kv(
                    "bus_off",
                    g.can[0]
                        .count(rollbase_driver::bus::BusEvent::BusOff)
                        .to_string(),
                ),
                kv(
                    "error_passive",
                    g.can[0]
                        .count(rollbase_driver::bus::BusEvent::ErrorPassive)
                        .to_string(),
                ),
                kv(
                    "error_warning",
                    g.can[0]
                        .count(rollbase_driver::bus::BusEvent::Warning)
                        .to_string(),
                ),
            ],
        });
        let c = &s.commands;
        let d_rej = c.rejected.saturating_sub(prev.commands.rejected);
        let d_to = c.timeouts.saturating_sub(prev.commands.timeouts);
        let limiting = s.shaping.limiting;
        let level = if s.state == SupervisorState::Fault {
            DiagnosticStatus::ERROR
        } else if d_rej > 0
            || d_to > 0
            || limiting == rollbase_control::service::ports::Limiting::Timeout
        {
            DiagnosticStatus::WARN
        } else {
            DiagnosticStatus::OK
        };
        status.push(DiagnosticStatus {
            level,
            name: "rollbase: supervisor".into(),
            message: supervisor_text(s).data,
            hardware_id: self.hardware.clone(),
            values: vec![
                kv("state", s.state.name().into()),
                kv(
                    "reason",
                    s.reason.map(|r| r.to_string()).unwrap_or_default(),
                ),
                kv("limiting", limiting.name().into()),
                kv("speed_scale", format!("{:.3}", s.shaping.scale)),
                kv("commanded_vx", format!("{:.4}", s.shaping.commanded.vx)),
                kv("commanded_vy", format!("{:.4}", s.shaping.commanded.vy)),
                kv(
                    "commanded_omega",
                    format!("{:.4}", s.shaping.commanded.omega),
                ),
                kv("commands_accepted", c.accepted.to_string()),
                kv("commands_rejected", c.rejected.to_string()),
                kv("command_timeouts", c.timeouts.to_string()),
            ],
        });
        self.prev = Some(*s);
        DiagnosticArray {
            header: Header::new(s.log_time_ns, ""),
            status,
        }
    }
}

/// Decimates a 250 Hz stream to a rate, on the stream's own time (cycle time, so lockstep and
/// real time decimate alike): the first sample is due, then one every `1/rate` s; a gap longer
/// than a period restarts the schedule instead of bursting.
#[derive(Clone, Copy, Debug)]
pub struct Decimator {
    period: f64,
    next: Option<f64>,
}

impl Decimator {
    /// A decimator for `rate_hz` (> 0; a rate above the stream's gives every sample).
    pub fn new(rate_hz: f64) -> Self {
        Self {
            period: 1.0 / rate_hz,
            next: None,
        }
    }

    /// Whether the sample at time `t` (s) is due; if so, schedules the next.
    pub fn due(&mut self, t: f64) -> bool {
        // Half a microsecond of slack for rounding of accumulated cycle times.
        const EPS: f64 = 5e-7;
        match self.next {
            Some(n) if t + EPS < n => false,
            Some(n) => {
                let next = n + self.period;
                self.next = Some(if next + EPS < t {
                    t + self.period
                } else {
                    next
                });
                true
            }
            None => {
                self.next = Some(t + self.period);
                true
            }
        }
    }
}

/// The ROS 2 messages one state gives at the configured rates (`None`: not due).
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Sampled {
    /// `odom`, at the odometry rate.
    pub odom: Option<super::msg::Odometry>,
    /// `tf`, with `odom` when tf is on.
    pub tf: Option<TFMessage>,
    /// `joint_states`, at its rate.
    pub joint_states: Option<JointState>,
    /// `diagnostics`, at its rate and whenever the supervisor state, fault reason or limiting
    /// cause changes (at most every [`MIN_CHANGE_INTERVAL`] for changes).
    pub diagnostics: Option<DiagnosticArray>,
    /// `supervisor_state`, with `diagnostics`.
    pub supervisor_state: Option<StringMsg>,
    /// A problem to report once (custom joint names that do not fit the wheel count).
    pub warning: Option<String>,
}

/// Turns the 250 Hz state stream into the messages of the ROS 2 topics at their rates, the
/// same way for the DDS node and for recordings.
#[derive(Clone, Debug)]
pub struct StateSampler {
    frames: Frames,
    publish_tf: bool,
    joint_names: JointNames,
    odom: Decimator,
    joints: Decimator,
    diag: Decimator,
    builder: DiagnosticsBuilder,
    names: Option<(usize, Vec<String>)>,
    last_key: Option<String>,
    pending: bool,
    last_change: Option<f64>,
}

/// Shortest time between two change-triggered publications of `diagnostics` and
/// `supervisor_state` (s): a cause that flaps every cycle must not flood the topic; the latest
/// state still goes out at most this late.
pub const MIN_CHANGE_INTERVAL: f64 = 0.1;

impl StateSampler {
    /// A sampler with the options' frames, tf switch, joint names and rates.
    pub fn new(opts: &super::Ros2Options) -> Self {
        Self {
            frames: opts.frames.clone(),
            publish_tf: opts.publish_tf,
            joint_names: opts.joint_names.clone(),
            odom: Decimator::new(opts.odom_rate_hz),
            joints: Decimator::new(opts.joint_states_rate_hz),
            diag: Decimator::new(opts.diagnostics_rate_hz),
            builder: DiagnosticsBuilder::new(&opts.node_name),
            names: None,
            last_key: None,
            pending: false,
            last_change: None,
        }
    }

    /// The messages due for state `s`.
    pub fn sample(&mut self, s: &BaseState) -> Sampled {
        let mut out = Sampled::default();
        if self.odom.due(s.t) {
            out.odom = Some(odometry(s, &self.frames));
            if self.publish_tf {
                out.tf = Some(tf(s, &self.frames));
            }
        }
        if self.joints.due(s.t) {
            if self.names.as_ref().map(|(n, _)| *n) != Some(s.n) {
                let list = self.joint_names.names(s.n).unwrap_or_else(|e| {
                    out.warning = Some(format!("{e}; using the default joint names"));
                    JointNames::Default.names(s.n).unwrap_or_default()
                });
                self.names = Some((s.n, list));
            }
            if let Some((_, list)) = &self.names {
                out.joint_states = Some(joint_state(s, list));
            }
        }
        // A change of state, fault reason or limiting cause (not of the speed scale, which
        // moves continuously) is published at once, at most every MIN_CHANGE_INTERVAL.
        let key = format!(
            "{} {:?} {}",
            s.state.name(),
            s.reason.map(|r| r.to_string()),
            s.shaping.limiting.name()
        );
        if self.last_key.as_deref() != Some(key.as_str()) {
            self.pending = true;
        }
        let due = self.diag.due(s.t);
        let may = self
            .last_change
            .is_none_or(|l| s.t - l >= MIN_CHANGE_INTERVAL - 1e-9);
        if due || (self.pending && may) {
            if !due {
                self.last_change = Some(s.t);
            }
            out.diagnostics = Some(self.builder.build(s));
            out.supervisor_state = Some(supervisor_text(s));
            self.last_key = Some(key);
            self.pending = false;
        }
        out
    }
}

/// The command a body twist asks for (vx = linear.x, vy = linear.y, ω = angular.z; the other
/// components do not apply to a planar base and are ignored).
pub fn motion_command(t: &Twist) -> CommandKind {
    CommandKind::Motion(MotionCommand {
        twist: BodyTwist {
            vx: t.linear.x,
            vy: t.linear.y,
            omega: t.angular.z,
        },
        legs: None,
    })
}

/// The command a leg command message asks for: one target extension per wheel (m). The
/// count is checked by the command port (a wrong count is rejected and counted there).
pub fn legs_command(data: &[f64]) -> CommandKind {
    CommandKind::Legs(LegTargets::from_slice(data))
}

/// The EMCY history of a wheel's devices for a diagnostic value: newest first, `code (node N,
/// register R, at T s)`; `-` when none came.
fn emcy_text(e: &[rollbase_control::service::ports::EmcyEntry]) -> String {
    let parts: Vec<String> = e
        .iter()
        .filter(|x| x.node != 0)
        .map(|x| {
            format!(
                "0x{:04X} (node {}, register 0x{:02X}, at {:.3} s)",
                x.code,
                x.node,
                x.register,
                x.at_ms as f64 * 1e-3
            )
        })
        .collect();
    if parts.is_empty() {
        "-".into()
    } else {
        parts.join("; ")
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rollbase_control::service::ports::{Limiting, ModuleDiagnostics};
    use rollbase_control::types::Pose as BodyPose;

    fn state() -> BaseState {
        let mut s = BaseState {
            cycle: 10,
            t: 0.04,
            log_time_ns: 1_000_040_000_000,
            n: 2,
            ..Default::default()
        };
        s.odometry.pose = BodyPose {
            x: 1.0,
            y: 2.0,
            theta: std::f64::consts::FRAC_PI_2,
        };
        s.odometry.twist = BodyTwist {
            vx: 0.1,
            vy: 0.2,
            omega: 0.3,
        };
        s.odometry.pose_covariance = [[1.0, 2.0, 3.0], [2.0, 4.0, 5.0], [3.0, 5.0, 6.0]];
        s.odometry.twist_covariance = [[7.0, 0.0, 0.0], [0.0, 8.0, 0.0], [0.0, 0.0, 9.0]];
        s.joints[0].steer_angle = 0.5;
        s.joints[0].wheel_speed = 3.0;
        s.joints[1].leg = 0.45;
        s
    }

    #[test]
    fn covariance_goes_to_x_y_and_yaw_with_unobserved_rest() {
        let c = covariance_6x6(&state().odometry.pose_covariance);
        // Row 0: x with x, y, yaw.
        assert_eq!(&c[0..6], &[1.0, 2.0, 0.0, 0.0, 0.0, 3.0], "row x");
        assert_eq!(&c[6..12], &[2.0, 4.0, 0.0, 0.0, 0.0, 5.0], "row y");
        assert_eq!(&c[30..36], &[3.0, 5.0, 0.0, 0.0, 0.0, 6.0], "row yaw");
        for i in [2, 3, 4] {
            for k in 0..6 {
                let want = if i == k { UNOBSERVED_VARIANCE } else { 0.0 };
                assert_eq!(c[i * 6 + k], want, "({i},{k})");
                assert_eq!(c[k * 6 + i], want, "({k},{i})");
            }
        }
    }

    #[test]
    fn odometry_and_tf_agree_and_follow_rep_105() {
        let s = state();
        let f = Frames::default();
        let o = odometry(&s, &f);
        assert_eq!(o.header.frame_id, "odom");
        assert_eq!(o.child_frame_id, "base_link");
        assert_eq!(o.header.stamp.sec, 1000);
        assert_eq!(o.header.stamp.nanosec, 40_000_000);
        assert_eq!(o.pose.pose.position.x, 1.0);
        assert!((o.pose.pose.orientation.yaw() - std::f64::consts::FRAC_PI_2).abs() < 1e-12);
        assert!((o.pose.pose.orientation.z - (0.5f64).sqrt()).abs() < 1e-12);
        assert_eq!(o.twist.twist.linear.y, 0.2);
        assert_eq!(o.twist.twist.angular.z, 0.3);
        assert_eq!(o.twist.covariance[35], 9.0);
        let t = tf(&s, &f);
        assert_eq!(t.transforms.len(), 1);
        let ts = &t.transforms[0];
        assert_eq!(ts.header, o.header);
        assert_eq!(ts.child_frame_id, o.child_frame_id);
        assert_eq!(ts.transform.translation.x, o.pose.pose.position.x);
        assert_eq!(ts.transform.translation.y, o.pose.pose.position.y);
        assert_eq!(ts.transform.rotation, o.pose.pose.orientation);
    }

    #[test]
    fn joint_states_have_three_joints_per_wheel() {
        let s = state();
        let names = JointNames::Default.names(2).unwrap();
        assert_eq!(
            names,
            [
                "wheel_1_steer_joint",
                "wheel_1_drive_joint",
                "wheel_1_leg_joint",
                "wheel_2_steer_joint",
                "wheel_2_drive_joint",
                "wheel_2_leg_joint"
            ]
        );
        let j = joint_state(&s, &names);
        assert_eq!(j.name.len(), 6);
        assert_eq!(j.position, vec![0.5, 0.0, 0.0, 0.0, 0.0, 0.45]);
        assert_eq!(j.velocity, vec![0.0, 3.0, 0.0, 0.0, 0.0, 0.0]);
        assert!(j.effort.is_empty());
        let e = JointNames::Custom(vec!["a".into(); 5])
            .names(2)
            .unwrap_err();
        assert!(e.contains("5 joint names given for 2 wheels"), "{e}");
    }

    #[test]
    fn joint_states_of_wheels_without_legs_have_no_leg_joint() {
        let mut s = state();
        s.joints[0].no_leg = true;
        let names = JointNames::Default.names(2).unwrap();
        let j = joint_state(&s, &names);
        assert_eq!(
            j.name,
            [
                "wheel_1_steer_joint",
                "wheel_1_drive_joint",
                "wheel_2_steer_joint",
                "wheel_2_drive_joint",
                "wheel_2_leg_joint"
            ]
        );
        assert_eq!(j.position, vec![0.5, 0.0, 0.0, 0.0, 0.45]);
        assert_eq!(j.velocity, vec![0.0, 3.0, 0.0, 0.0, 0.0]);
        s.joints[1].no_leg = true;
        let j = joint_state(&s, &names);
        assert!(j.name.iter().all(|n| !n.contains("leg")), "{:?}", j.name);
        assert_eq!((j.position.len(), j.velocity.len()), (4, 4));
    }

    #[test]
    fn diagnostics_levels_follow_the_changes() {
        let mut b = DiagnosticsBuilder::new("rollbase");
        let mut s = state();
        for i in 0..2 {
            s.diagnostics.modules[i] = ModuleDiagnostics {
                node: i as u8 + 1,
                state: 2,
                ..Default::default()
            };
        }
        s.diagnostics.bus_load = 0.5;
        let a = b.build(&s);
        assert_eq!(a.status.len(), 4, "2 wheels, bus, supervisor");
        assert!(
            a.status.iter().all(|x| x.level == DiagnosticStatus::OK),
            "{a:?}"
        );
        // Wheel 2 loses frames, wheel 1 goes stale, the bus fills up, the supervisor faults.
        s.diagnostics.modules[1].lost = 2;
        s.diagnostics.modules[0].age_cycles = 4;
        s.diagnostics.bus_load = 0.85;
        s.state = SupervisorState::Fault;
        let a = b.build(&s);
        assert_eq!(a.status[0].level, DiagnosticStatus::ERROR);
        assert_eq!(a.status[0].name, "rollbase: wheel 1 (node 1)");
        assert_eq!(a.status[1].level, DiagnosticStatus::WARN);
        assert!(
            a.status[1].message.contains("2 lost"),
            "{}",
            a.status[1].message
        );
        assert_eq!(a.status[2].level, DiagnosticStatus::WARN);
        assert_eq!(a.status[3].level, DiagnosticStatus::ERROR);
        // Nothing new: the lost counter no longer warns.
        s.diagnostics.modules[0].age_cycles = 0;
        let a = b.build(&s);
        assert_eq!(a.status[1].level, DiagnosticStatus::OK);
        assert_eq!(a.status[0].level, DiagnosticStatus::OK);
    }

    #[test]
    fn supervisor_text_starts_with_the_state() {
        let mut s = state();
        s.state = SupervisorState::Tracking;
        assert_eq!(supervisor_text(&s).data, "tracking");
        s.shaping.limiting = Limiting::SteerRate;
        s.shaping.scale = 0.625;
        assert_eq!(
            supervisor_text(&s).data,
            "tracking (limited by steering rate, speed scale 0.62)"
        );
    }

    #[test]
    fn decimator_keeps_the_rate_on_cycle_time() {
        let mut d = Decimator::new(50.0);
        let hits: Vec<u64> = (0..250u64).filter(|&k| d.due(k as f64 * 0.004)).collect();
        assert_eq!(hits.len(), 50, "{hits:?}");
        assert_eq!(&hits[..3], &[0, 5, 10]);
        let mut d = Decimator::new(1.0);
        assert_eq!((0..1000u64).filter(|&k| d.due(k as f64 * 0.004)).count(), 4);
        // A gap of 10 s gives one sample, not a burst.
        let mut d = Decimator::new(50.0);
        assert!(d.due(0.0));
        assert!(d.due(10.0));
        assert!(!d.due(10.004));
        // Faster than the stream: every sample.
        let mut d = Decimator::new(1000.0);
        assert_eq!((0..10u64).filter(|&k| d.due(k as f64 * 0.004)).count(), 10);
    }

    #[test]
    fn sampler_gives_each_topic_at_its_rate_and_state_changes_at_once() {
        let opts = crate::ros2::Ros2Options::default();
        let mut sm = StateSampler::new(&opts);
        let mut s = state();
        let (mut odom, mut tfs, mut joints, mut diag) = (0, 0, 0, 0);
        for k in 0..500u64 {
            s.t = k as f64 * 0.004;
            s.state = if k == 300 {
                SupervisorState::Fault
            } else {
                SupervisorState::Tracking
            };
            s.shaping.scale = k as f64 / 500.0; // moving scale: not a change
            let m = sm.sample(&s);
            odom += m.odom.is_some() as u32;
            tfs += m.tf.is_some() as u32;
            joints += m.joint_states.is_some() as u32;
            diag += m.diagnostics.is_some() as u32;
            assert_eq!(m.diagnostics.is_some(), m.supervisor_state.is_some());
            if k == 300 {
                assert_eq!(m.supervisor_state.as_ref().unwrap().data, "fault");
            }
            // Back to tracking one cycle later: held back for 0.1 s (a flapping cause must
            // not flood the topic), then published.
            if (301..325).contains(&k) {
                assert!(m.supervisor_state.is_none(), "cycle {k}");
            }
            if k == 325 {
                assert_eq!(m.supervisor_state.as_ref().unwrap().data, "tracking");
            }
        }
        // 2 s: 100 at 50 Hz; diagnostics at t = 0, 1 s plus the change to fault and back.
        assert_eq!((odom, tfs, joints, diag), (100, 100, 100, 4));
        let mut no_tf = StateSampler::new(&crate::ros2::Ros2Options {
            publish_tf: false,
            joint_names: JointNames::Custom(vec!["x".into(); 3]),
            ..Default::default()
        });
        let m = no_tf.sample(&state());
        assert!(m.odom.is_some() && m.tf.is_none());
        assert!(m
            .warning
            .unwrap()
            .contains("3 joint names given for 2 wheels"));
        assert_eq!(m.joint_states.unwrap().name[0], "wheel_1_steer_joint");
    }

    #[test]
    fn commands_map_the_planar_components() {
        let t = Twist {
            linear: Vector3 {
                x: 0.5,
                y: -0.25,
                z: 9.0,
            },
            angular: Vector3 {
                x: 9.0,
                y: 9.0,
                z: 0.125,
            },
        };
        match motion_command(&t) {
            CommandKind::Motion(m) => {
                assert_eq!((m.twist.vx, m.twist.vy, m.twist.omega), (0.5, -0.25, 0.125));
                assert!(m.legs.is_none());
            }
            k => panic!("{k:?}"),
        }
        match legs_command(&[0.4, 0.5, 0.45, 0.41]) {
            CommandKind::Legs(l) => assert_eq!(l.as_slice(), &[0.4, 0.5, 0.45, 0.41]),
            k => panic!("{k:?}"),
        }
    }
}
