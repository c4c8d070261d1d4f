//! The cycle minus IO and clocks: [`CycleCore`].

use super::{ControllerKind, RuntimeConfig, RuntimeError};
use crate::avoidance::Avoidance;
use crate::dfl::{alignment_command, ControlInput, DflController, TrackingController};
use crate::kinematic::KinematicController;
use crate::link::{Link, Update, WheelFault};
use crate::model::wheel_positions;
use crate::odometry::Odometry;
use crate::platform::Platform;
use crate::record::{AvoidanceRecord, CycleRecord, FrameRecord};
use crate::supervisor::FaultReason;
use crate::supervisor::{
    command_at_rest, stop_command, Mode, Supervisor, SupervisorInput, SupervisorState,
};
use crate::trajectory::Trajectory;
use crate::types::{Command, Measurement, ReferenceSample, MAX_WHEELS};
use rollbase_driver::canopen::config::Role;
use rollbase_driver::codec::{ModuleState, Setpoint, SetpointFlags};
use rollbase_driver::frame::{CanFrame, FrameBuf};

/// Checks, before anything starts, that the reference stays inside the platform's wheel
/// speed and leg speed limits (sampled every control period over the whole trajectory):
/// the wheel's rolling speed |u_i| / r (seed 000 eq. 18, [`crate::model::wheel_velocity_body`])
/// against `limits.wheel_speed` and |λ̇_i*| against `limits.leg_speed`. Steering rates are
/// not checked here: near rest they are unbounded in the reference (singularity A) and the
/// controllers limit them.
pub fn check_feasible(p: &Platform, traj: &dyn Trajectory) -> Result<(), RuntimeError> {
    let n = p.n().min(MAX_WHEELS).min(traj.n_legs());
    let dt = p.dt();
    let d = traj.duration();
    if !(d.is_finite() && (0.0..=crate::trajectory::MAX_WAYPOINT_TIME_S).contains(&d)) {
        return Err(RuntimeError::Duration { duration: d });
    }
    // At most 10 h × 333 Hz = 12 million samples: every sample of every valid trajectory.
    let steps = (d / dt).ceil() as u64;
    for k in 0..=steps {
        let t = (k as f64 * dt).min(d.max(0.0));
        let r = traj.sample(t);
        let tw = crate::types::Twist {
            vx: r.dz[0],
            vy: r.dz[1],
            omega: r.dz[2],
        };
        for i in 0..n {
            let u = crate::model::wheel_velocity_body(p, i, r.z[2], r.z[3 + i], &tw, r.dz[3 + i]);
            let w = u[0].hypot(u[1]) / p.wheel_radius;
            if w.is_nan() || w > p.limits.wheel_speed {
                return Err(RuntimeError::Infeasible {
                    field: "wheel_speed",
                    wheel: i,
                    t,
                    value: w,
                    limit: p.limits.wheel_speed,
                });
            }
            let l = r.dz[3 + i].abs();
            if l.is_nan() || l > p.limits.leg_speed {
                return Err(RuntimeError::Infeasible {
                    field: "leg_speed",
                    wheel: i,
                    t,
                    value: l,
                    limit: p.limits.leg_speed,
                });
            }
        }
    }
    Ok(())
}

/// When a feedback stream last delivered a sample.
#[derive(Clone, Copy, Debug, Default)]
struct Arrival {
    /// Cycle it arrived in (`None`: never since the streams were last cleared).
    cycle: Option<u64>,
    /// Its receive time (s).
    time: f64,
}

impl Arrival {
    fn set(&mut self, cycle: u64, t: f64) {
        self.cycle = Some(cycle);
        self.time = t;
    }
}

/// One wheel's feedback, as three streams: steering (angle, rate), rolling (wheel speed) and
/// leg (extension, rate). The native profile fills steering and rolling from one frame
/// (FEEDBACK_A), the CiA 402 profile from two drives.
#[derive(Clone, Copy, Debug, Default)]
struct WheelFeedback {
    steer: Option<(f64, f64)>,
    steer_at: Arrival,
    /// Sequence number of `steer`: one step per SYNC the device answered.
    steer_seq: u8,
    /// Whether `steer` arrived after the SYNC of the cycle it arrived in (not a late answer).
    steer_on_time: bool,
    /// The steering sample before `steer`, with its sequence number, arrival cycle and
    /// punctuality: for the encoder-jump check.
    prev_steer: Option<((f64, f64), u8, u64, bool)>,
    /// `steer` arrived since the last encoder-jump check.
    steer_fresh: bool,
    drive: Option<f64>,
    drive_at: Arrival,
    leg: Option<(f64, f64)>,
    leg_at: Arrival,
}

/// Cycles after [`CycleCore::arm`] whose SETPOINTs carry `fault_reset`.
pub const FAULT_RESET_CYCLES: u32 = 3;

/// The cycle minus IO and clocks.
pub struct CycleCore {
    fault_reset_cycles: u32,
    platform: Platform,
    cfg: RuntimeConfig,
    n: usize,
    nodes: [u8; MAX_WHEELS],
    link: Link,
    /// An arm was asked for while the link was not ready (CiA 402 devices booting).
    arm_pending: bool,
    /// Cycle the supervisor was last armed in: the age of a stream that never delivered.
    armed_cycle: u64,
    /// Latest time passed in (s).
    now: f64,
    setpoints: [Setpoint; MAX_WHEELS],
    odom: Odometry,
    sup: Supervisor,
    controller: Box<dyn TrackingController + Send>,
    /// Takes over from the DFL when it terminates before the trajectory's end (it cannot
    /// pass through rest, seed 000 Sect. IV): the kinematic controller stops at rest.
    terminal: KinematicController,
    terminal_active: bool,
    avoidance: Option<Avoidance>,
    trajectory: Box<dyn Trajectory>,
    fb: [WheelFeedback; MAX_WHEELS],
    cycle: u64,
    last_cmd: Command,
    track_start_cycle: Option<u64>,
    record: CycleRecord,
    stop_requested: bool,
    bus_error: bool,
    done_cycles: u32,
    controller_moved: bool,
    sync_time: f64,
    rejected_this_cycle: u32,
    wheel_xy: [[f64; 2]; MAX_WHEELS],
}

impl CycleCore {
    /// Builds the core; allocates everything it will ever need.
    pub fn new(
        platform: Platform,
        trajectory: Box<dyn Trajectory>,
        cfg: RuntimeConfig,
    ) -> Result<Self, RuntimeError> {
        platform.validate()?;
        cfg.validate(&platform)?;
        let n = platform.n();
        if trajectory.n_legs() != n {
            return Err(RuntimeError::LegCount {
                traj: trajectory.n_legs(),
                platform: n,
            });
        }
        check_feasible(&platform, trajectory.as_ref())?;
        let link = Link::new(&platform, cfg.counter_policy);
        let mut nodes = [0u8; MAX_WHEELS];
        let mut steer_nodes = [0u8; MAX_WHEELS];
        let mut leg_nodes = [0u8; MAX_WHEELS];
        let mut drive_nodes = [0u8; MAX_WHEELS];
        for i in 0..n.min(MAX_WHEELS) {
            nodes[i] = link.wheel_node(i);
            steer_nodes[i] = link.stream_node(i, Role::Steer);
            leg_nodes[i] = link.stream_node(i, Role::Leg);
            drive_nodes[i] = link.stream_node(i, Role::Drive);
        }
        let r0 = trajectory.sample(0.0);
        let start = r0.pose();
        let controller: Box<dyn TrackingController + Send> = match cfg.controller {
            ControllerKind::Dfl => Box::new(DflController::new(&platform)),
            ControllerKind::Kinematic => Box::new(KinematicController::new(&platform)),
        };
        let avoidance = cfg.avoidance.map(|a| Avoidance::new(&platform, a));
        let mut sup = Supervisor::new(&platform, cfg.supervisor);
        sup.set_stream_nodes(steer_nodes, leg_nodes);
        sup.set_drive_nodes(drive_nodes);
        let mut record = CycleRecord::new(0, 0.0, n);
        record.nodes = nodes;
        let mut legs = [0.0; MAX_WHEELS];
        legs[..n].copy_from_slice(&r0.z.as_slice()[3..3 + n]);
        let wheel_xy = wheel_positions(&platform, &legs[..n]);
        Ok(Self {
            fault_reset_cycles: 0,
            n,
            nodes,
            link,
            arm_pending: false,
            armed_cycle: 0,
            now: 0.0,
            setpoints: [Setpoint::default(); MAX_WHEELS],
            odom: Odometry::new(start),
            sup,
            controller,
            terminal: KinematicController::new(&platform),
            terminal_active: false,
            avoidance,
            trajectory,
            fb: [WheelFeedback::default(); MAX_WHEELS],
            cycle: 0,
            last_cmd: Command::zero(n),
            track_start_cycle: None,
            record,
            stop_requested: false,
            bus_error: false,
            done_cycles: 0,
            controller_moved: false,
            sync_time: 0.0,
            rejected_this_cycle: 0,
            wheel_xy,
            platform,
            cfg,
        })
    }

    /// The runtime options the core was built with.
    pub fn config(&self) -> &RuntimeConfig {
        &self.cfg
    }

    /// The platform.
    pub fn platform(&self) -> &Platform {
        &self.platform
    }

    /// Supervisor state.
    pub fn state(&self) -> SupervisorState {
        self.sup.state()
    }

    /// The supervisor (state, reason).
    pub fn supervisor(&self) -> &Supervisor {
        &self.sup
    }

    /// Receive statistics (accepted and rejected frames by kind; see
    /// [`Link::rx_stats`] for the CiA 402 profile's mapping).
    pub fn rx_stats(&self) -> &rollbase_driver::rx::RxStats {
        self.link.rx_stats()
    }

    /// The wire side of the cycle (e.g. the CiA 402 master's devices, for reports).
    pub fn link(&self) -> &Link {
        &self.link
    }

    /// True while an arm waits for the link (CiA 402 devices still booting).
    pub fn arm_pending(&self) -> bool {
        self.arm_pending
    }

    /// Cycles run so far.
    pub fn cycles(&self) -> u64 {
        self.cycle
    }

    /// Wheel contact points in the body frame at the latest measured leg extensions.
    pub fn wheel_xy(&self) -> &[[f64; 2]] {
        &self.wheel_xy[..self.n]
    }

    /// Arms the platform (Idle/Stopped/Fault → Aligning). Re-arming after a fault clears it.
    ///
    /// Re-arming is the operator's "reconnect": the SETPOINTs of the next
    /// [`FAULT_RESET_CYCLES`] cycles carry `fault_reset`, so modules whose setpoint watchdog
    /// latched while the bus was gone (or that latched any other fault) go back to Ready,
    /// and the module states cached from earlier STATUS frames are forgotten: only a STATUS
    /// sent after the re-arm can fault the platform again. A fault that persists is reported
    /// again by the module and faults the platform again.
    ///
    /// With the CiA 402 profile the master first boots (again) every device that is not
    /// running and clears the devices' latched faults ([`Link::rearm`]); the supervisor arms
    /// when all devices run ([`CycleCore::arm_pending`] until then), or faults naming the
    /// device when one cannot be booted. Returns false when the state does not allow arming.
    pub fn arm(&mut self) -> bool {
        if !matches!(
            self.sup.state(),
            SupervisorState::Idle | SupervisorState::Stopped | SupervisorState::Fault
        ) {
            return false;
        }
        self.link.rearm(self.now);
        self.stop_requested = false;
        self.bus_error = false;
        self.done_cycles = 0;
        self.track_start_cycle = None;
        if self.link.ready() {
            self.arm_now()
        } else {
            self.arm_pending = true;
            true
        }
    }

    fn arm_now(&mut self) -> bool {
        self.arm_pending = false;
        self.fault_reset_cycles = FAULT_RESET_CYCLES + 1;
        self.armed_cycle = self.cycle;
        if matches!(self.link, Link::Cia402(_)) {
            // Devices may have been rebooted to get here: samples from before are not
            // evidence of anything now, and the streams' ages count from the arm.
            self.fb = [WheelFeedback::default(); MAX_WHEELS];
        }
        self.sup.arm()
    }

    /// Operator stop (Ctrl-C): a controlled stop, then the run ends.
    pub fn request_stop(&mut self) {
        self.stop_requested = true;
    }

    /// The bus reported an error (interface down, bus-off): fault and controlled stop.
    pub fn report_bus_error(&mut self) {
        self.bus_error = true;
    }

    /// True once the platform has been at rest in Stopped, Fault or Idle (after a stop
    /// request) for [`RuntimeConfig::linger_cycles`] cycles.
    pub fn done(&self) -> bool {
        self.done_cycles >= self.cfg.linger_cycles
    }

    /// Starts the cycle at time `t` (s): writes the frames to send now into `out` (cleared
    /// first), SYNC first; with the CiA 402 profile NMT commands, the master's heartbeat and
    /// SDO requests follow when due.
    pub fn start_cycle(&mut self, t: f64, out: &mut FrameBuf) {
        let mut rec = CycleRecord::new(self.cycle, t, self.n);
        rec.nodes = self.nodes;
        self.record = rec;
        self.rejected_this_cycle = 0;
        self.now = t;
        out.clear();
        self.link.start_cycle(self.cycle, t, out);
        for &f in out.as_slice() {
            self.push_tx(t, &f);
        }
    }

    fn push_tx(&mut self, t: f64, f: &CanFrame) {
        if f.id() == 0x080 {
            self.sync_time = t;
        }
        let mut data = [0u8; 8];
        data[..f.len()].copy_from_slice(f.data());
        self.record.push_tx(FrameRecord {
            t,
            id: f.id(),
            len: f.len() as u8,
            data,
            error: None,
        });
    }

    /// Takes one received frame (its timestamp in s on the run's time base).
    pub fn on_frame(&mut self, frame: &CanFrame, t: f64) {
        let mut data = [0u8; 8];
        data[..frame.len()].copy_from_slice(frame.data());
        self.record.timing.frames_in += 1;
        self.now = self.now.max(t);
        let result = self.link.on_frame(frame, t);
        let error = match &result {
            Ok(_) => None,
            Err(kind) => {
                self.rejected_this_cycle += 1;
                Some(*kind)
            }
        };
        self.record.push_rx(FrameRecord {
            t,
            id: frame.id(),
            len: frame.len() as u8,
            data,
            error,
        });
        let Ok(updates) = result else { return };
        let cycle = self.cycle;
        let on_time = t >= self.sync_time;
        for u in updates.iter() {
            match u {
                Update::Steer {
                    wheel,
                    angle,
                    rate,
                    seq,
                } if wheel < self.n => {
                    let fb = &mut self.fb[wheel];
                    if let (Some(old), Some(c)) = (fb.steer, fb.steer_at.cycle) {
                        fb.prev_steer = Some((old, fb.steer_seq, c, fb.steer_on_time));
                    }
                    fb.steer_seq = seq;
                    fb.steer_on_time = on_time;
                    fb.steer_fresh = true;
                    fb.steer = Some((angle, rate));
                    fb.steer_at.set(cycle, t);
                }
                Update::Drive { wheel, speed } if wheel < self.n => {
                    let fb = &mut self.fb[wheel];
                    fb.drive = Some(speed);
                    fb.drive_at.set(cycle, t);
                }
                Update::Leg { wheel, leg, rate } if wheel < self.n => {
                    let fb = &mut self.fb[wheel];
                    fb.leg = Some((leg, rate));
                    fb.leg_at.set(cycle, t);
                }
                _ => {}
            }
        }
    }

    /// The latest measurement, the data age and module age of every wheel (cycles), the
    /// node of each wheel's oldest stream, and the receive time of the oldest wheel's
    /// newest sample.
    #[allow(clippy::type_complexity)]
    fn measurement(
        &self,
    ) -> (
        Measurement,
        [u32; MAX_WHEELS],
        [u32; MAX_WHEELS],
        [u8; MAX_WHEELS],
        f64,
    ) {
        let mut m = Measurement {
            n: self.n,
            ..Default::default()
        };
        let mut age = [0u32; MAX_WHEELS];
        let mut alive = [0u32; MAX_WHEELS];
        let mut stale_node = [0u8; MAX_WHEELS];
        let mut oldest = f64::NEG_INFINITY;
        // A stream that never delivered since the arm is as old as the arm.
        let never = self.cycle - self.armed_cycle.min(self.cycle) + 1;
        #[allow(clippy::needless_range_loop)] // parallel per-wheel arrays
        for i in 0..self.n {
            let fb = &self.fb[i];
            if let Some((angle, rate)) = fb.steer {
                m.wheels[i].steer_angle = angle;
                m.wheels[i].steer_rate = rate;
            }
            if let Some(w) = fb.drive {
                m.wheels[i].wheel_speed = w;
            }
            if let Some((leg, rate)) = fb.leg {
                m.wheels[i].leg = leg;
                m.wheels[i].leg_rate = rate;
            } else {
                m.wheels[i].leg = self.platform.wheels[i].lambda_nominal;
            }
            let age_of = |a: &Arrival| a.cycle.map_or(never, |c| self.cycle - c);
            let streams = [
                (age_of(&fb.steer_at), Role::Steer),
                (age_of(&fb.drive_at), Role::Drive),
                (age_of(&fb.leg_at), Role::Leg),
            ];
            let (oldest_age, oldest_role) =
                streams.iter().copied().fold((0u64, Role::Steer), |acc, s| {
                    if s.0 > acc.0 {
                        s
                    } else {
                        acc
                    }
                });
            // Data age: the oldest stream (what the controller uses).
            age[i] = oldest_age.min(u64::from(u32::MAX)) as u32;
            stale_node[i] = self.link.stream_node(i, oldest_role);
            // Module age: the newest stream; a wheel is silent only when none of its streams
            // delivered (random loss of one frame is not silence).
            let newest_age = streams.iter().map(|s| s.0).min().unwrap_or(never);
            alive[i] = newest_age.min(u64::from(u32::MAX)) as u32;
            let newest = fb.steer_at.time.min(fb.drive_at.time).min(fb.leg_at.time);
            if oldest == f64::NEG_INFINITY || newest < oldest {
                oldest = newest;
            }
        }
        (m, age, alive, stale_node, oldest)
    }

    fn reference_time(&self) -> f64 {
        match self.track_start_cycle {
            Some(c) => (self.cycle - c) as f64 * self.platform.dt(),
            None => 0.0,
        }
    }

    /// Runs the control step at time `t` (s) and writes the setpoint frames into `out`
    /// (cleared first; with the CiA 402 profile SDO requests that became due follow);
    /// returns how many were written. The cycle's record is then available from
    /// [`CycleCore::record`].
    pub fn finish_cycle(&mut self, t: f64, out: &mut FrameBuf) -> usize {
        let dt = self.platform.dt();
        self.now = self.now.max(t);
        if self.arm_pending {
            if let Some((wheel, node, role, fault)) = self.link.boot_failure() {
                self.arm_pending = false;
                self.sup.fail(FaultReason::DeviceFault {
                    wheel,
                    node,
                    role,
                    fault,
                });
            } else if self.link.ready() {
                self.arm_now();
            }
        }
        let (meas, age, alive, stale_node, oldest_fb) = self.measurement();
        for (i, w) in meas.wheels[..self.n].iter().enumerate() {
            self.wheel_xy[i] = {
                let a = self.platform.wheels[i].alpha;
                [w.leg * a.cos(), w.leg * a.sin()]
            };
        }
        let odo = self.odom.update(&self.platform, &meas, dt);

        // Reference: held at the start until tracking begins, then runs from 0.
        let t_ref = self.reference_time();
        let nominal = self
            .trajectory
            .sample(t_ref.min(self.trajectory.duration()));
        let (reference, av) = match (&mut self.avoidance, self.sup.state()) {
            (Some(a), SupervisorState::Tracking) => {
                let (r, s) = a.step(&self.platform, &nominal, dt);
                let mut d = [0.0; 3 + MAX_WHEELS];
                d.copy_from_slice(s.deviation.as_slice());
                (
                    r,
                    AvoidanceRecord {
                        icr_body: s.icr_body,
                        active: s.active,
                        min_distance: s.min_distance,
                        nearest_wheel: s.nearest_wheel,
                        d_start: s.d_start,
                        deviation: d,
                    },
                )
            }
            _ => (nominal, icr_record(&nominal, &self.wheel_xy[..self.n])),
        };

        let (align_cmd, align_err) = alignment_command(&self.platform, &meas, &nominal);
        // Alignment and the start check need every module's feedback at least once.
        let reported = self.fb[..self.n]
            .iter()
            .all(|f| f.steer.is_some() && f.drive.is_some() && f.leg.is_some());
        let start_legs = if reported {
            let r0 = self.trajectory.sample(0.0);
            let mut worst = (0usize, meas.wheels[0].leg, r0.z[3]);
            for i in 0..self.n {
                let (m, e) = (meas.wheels[i].leg, r0.z[3 + i]);
                if (m - e).abs() > (worst.1 - worst.2).abs() || !(m - e).is_finite() {
                    worst = (i, m, e);
                }
            }
            Some(worst)
        } else {
            None
        };
        // Encoder jump: two readings sampled one SYNC apart must differ in steering angle by
        // what the trapezoid of their measured steering rates predicts. The spacing is only
        // certain when the sample sequence advanced by one (native: the module's rolling
        // counter, no lost answer; CiA 402: the count of the drive's TPDOs), the two arrived
        // in consecutive cycles (no lost SYNC, which the counter cannot show: a device that
        // saw no SYNC sends nothing) and both arrived after their own cycle's SYNC (neither is
        // a late answer to the SYNC before). Other pairs are not checked.
        let mut steer_jump = [0.0; MAX_WHEELS];
        for (i, j) in steer_jump.iter_mut().enumerate().take(self.n) {
            let fb = &mut self.fb[i];
            if let (true, Some((a, ar)), Some(c), Some(((pa, par), pk, pc, p_on_time))) =
                (fb.steer_fresh, fb.steer, fb.steer_at.cycle, fb.prev_steer)
            {
                let k = fb.steer_seq.wrapping_sub(pk) & 0x0F;
                if k == 1 && pc + 1 == c && p_on_time && fb.steer_on_time {
                    let predicted = pa + 0.5 * (par + ar) * dt;
                    *j = crate::angle::diff(a, predicted);
                }
            }
            fb.steer_fresh = false;
        }
        let mut sup_in = SupervisorInput {
            steer_jump,
            feedback_age: alive,
            data_age: age,
            stale_node,
            alignment_error: if reported { align_err } else { f64::INFINITY },
            start_legs,
            bus_error: self.bus_error,
            slip_residual: odo.residual,
            stop_requested: self.stop_requested,
            ..Default::default()
        };
        if self.sup.state() == SupervisorState::Stopping {
            // Arrival check at the end of a trajectory run: the estimate against the goal.
            let goal = self.trajectory.sample(self.trajectory.duration());
            let distance = (goal.z[0] - odo.pose.x).hypot(goal.z[1] - odo.pose.y);
            let heading = crate::angle::diff(goal.z[2], odo.pose.theta);
            let mut worst = (0usize, 0.0f64);
            for i in 0..self.n {
                let e = meas.wheels[i].leg - goal.z[3 + i];
                if e.abs() > worst.1.abs() || !e.is_finite() {
                    worst = (i, e);
                }
            }
            sup_in.goal_error = Some((distance, heading, worst.0, worst.1));
        }
        for i in 0..self.n {
            sup_in.enabled[i] = self.link.wheel_state(i) == Some(ModuleState::Enabled);
            sup_in.wheel_speed[i] = meas.wheels[i].wheel_speed;
            sup_in.steer_rate[i] = meas.wheels[i].steer_rate;
            match self.link.wheel_fault(i) {
                Some(WheelFault::Module { code, .. }) => sup_in.module_fault[i] = Some(code),
                Some(WheelFault::Device { node, role, fault }) => {
                    sup_in.device_fault[i] = Some((node, role, fault))
                }
                None => {}
            }
        }

        // Controller step (only while tracking) before the supervisor so it can see the result.
        let tracking_before = self.sup.state() == SupervisorState::Tracking;
        let mut track_cmd = Command::zero(self.n);
        if tracking_before {
            let input = ControlInput {
                measured_twist: Some(odo.twist_world),
                t: t_ref,
                dt,
                measurement: &meas,
                pose: odo.pose,
                reference: &reference,
            };
            let mut o = if self.terminal_active {
                self.terminal.step(&self.platform, &input)
            } else {
                self.controller.step(&self.platform, &input)
            };
            if o.finished
                && !self.terminal_active
                && self.cfg.controller == ControllerKind::Dfl
                && t_ref + dt < self.trajectory.duration()
            {
                // The DFL terminated (|v_W*| < ε) before the reference's end: the kinematic
                // controller tracks the rest of the way and stops at rest.
                self.terminal_active = true;
                self.terminal.reset(&self.platform, &reference);
                o = self.terminal.step(&self.platform, &input);
            }
            track_cmd = o.command;
            // A DFL reports `singular` until the reference wheel moves faster than ε (it
            // cannot leave rest on its own, seed 000 Sect. IV); that is waiting, not a fault.
            // Singular after it has moved is singularity A: a fault.
            if !o.singular {
                self.controller_moved = true;
            }
            sup_in.controller_singular =
                (o.singular && self.controller_moved) || !command_finite(&track_cmd);
            sup_in.trajectory_done = (o.finished
                && (self.terminal_active
                    || self.cfg.controller != ControllerKind::Dfl
                    || t_ref + dt >= self.trajectory.duration()))
                || t_ref >= self.trajectory.duration() + 2.0;
        }
        let at_rest = command_at_rest(&self.last_cmd, self.sup.config().rest_speed);
        let state_before = self.sup.state();
        let mode = self.sup.step(&self.platform, &sup_in, at_rest);
        if self.sup.state() == SupervisorState::Tracking
            && state_before != SupervisorState::Tracking
        {
            // Entering tracking: the reference clock starts now, the controller is initialised
            // on the reference (perfect matching condition, seed 000 Sect. IV).
            self.track_start_cycle = Some(self.cycle);
            self.controller_moved = false;
            self.terminal_active = false;
            let r0 = self.trajectory.sample(0.0);
            self.controller.reset(&self.platform, &r0);
            let input = ControlInput {
                measured_twist: Some(odo.twist_world),
                t: 0.0,
                dt,
                measurement: &meas,
                pose: odo.pose,
                reference: &r0,
            };
            track_cmd = self.controller.step(&self.platform, &input).command;
        }
        // The last cycle of a finished run disables the drives (enable = 0), so the modules go
        // back to Ready instead of tripping their setpoint watchdog when the controller exits.
        let settling = matches!(
            self.sup.state(),
            SupervisorState::Stopped | SupervisorState::Fault
        ) || (self.sup.state() == SupervisorState::Idle && self.stop_requested);
        // With synchronous RPDOs (CiA 402) a controlword acts at the next SYNC: the drives are
        // told to disable for as many cycles before the end as the link needs.
        let lead = self.link.disable_lead_cycles();
        let last_cycle = settling && self.done_cycles + lead >= self.cfg.linger_cycles;
        let (cmd, enable, brake, mode_name) = match mode {
            Mode::Disabled => (Command::zero(self.n), false, false, "disabled"),
            Mode::Align => (align_cmd, true, false, "align"),
            Mode::Track => {
                if command_finite(&track_cmd) {
                    (track_cmd, true, false, "track")
                } else {
                    (
                        stop_command(&self.platform, &self.last_cmd, dt),
                        true,
                        false,
                        "decelerate",
                    )
                }
            }
            Mode::Decelerate => (
                stop_command(&self.platform, &self.last_cmd, dt),
                true,
                false,
                "decelerate",
            ),
            Mode::Hold => (Command::zero(self.n), true, true, "hold"),
        };
        let at_rest_now = command_at_rest(&cmd, self.sup.config().rest_speed);
        let (enable, mode_name) = if last_cycle && at_rest_now {
            (false, "disable")
        } else {
            (enable, mode_name)
        };

        // A re-arm asks the modules to clear latched faults (e.g. their setpoint watchdog
        // after the bus was gone) in the setpoints of the next few cycles.
        self.fault_reset_cycles = self.fault_reset_cycles.saturating_sub(1);
        for i in 0..self.n {
            let c = cmd.wheels[i];
            self.setpoints[i] = Setpoint {
                wheel_speed: c.wheel_speed,
                steer_rate: c.steer_rate,
                flags: SetpointFlags {
                    enable,
                    brake,
                    fault_reset: self.fault_reset_cycles > 0,
                },
            };
        }
        // What the drives are being told, for the following-error check of the next cycles:
        // a wheel told to disable or brake is going to rest.
        self.sup.note_command(&cmd, &[enable && !brake; MAX_WHEELS]);
        out.clear();
        self.link.finish_cycle(t, &self.setpoints[..self.n], out);
        let settled = matches!(
            self.sup.state(),
            SupervisorState::Stopped | SupervisorState::Fault
        ) && at_rest_now;
        let idle_stop = self.sup.state() == SupervisorState::Idle && self.stop_requested;
        // The very last cycle of a finished run, drives disabled: hand the devices back.
        if (settled || idle_stop) && self.done_cycles + 1 >= self.cfg.linger_cycles {
            self.link.release(out);
        }
        let k = out.len();
        for &f in out.as_slice() {
            self.push_tx(t, &f);
        }
        self.last_cmd = cmd;

        if settled || idle_stop {
            self.done_cycles = self.done_cycles.saturating_add(1);
        } else {
            self.done_cycles = 0;
        }

        let r = &mut self.record;
        r.t = r.t.min(t);
        r.measurement = meas;
        r.feedback_age = age;
        for i in 0..self.n {
            r.module_state[i] = self.link.wheel_state(i).map_or(255, |s| s.to_raw());
        }
        r.nominal = nominal;
        r.reference = reference;
        r.command = cmd;
        r.mode = mode_name;
        r.enable = enable;
        r.pose = odo.pose;
        r.twist_body = odo.twist_body;
        r.slip_residual = odo.residual;
        r.avoidance = av;
        r.wheel_xy = self.wheel_xy;
        r.state = self.sup.state();
        r.reason = self.sup.reason();
        r.timing.frames_out = r.n_tx_total;
        r.timing.rejected = self.rejected_this_cycle;
        r.timing.feedback_age_us = if oldest_fb.is_finite() {
            ((t - oldest_fb) * 1e6).max(0.0)
        } else {
            f64::NAN
        };
        self.cycle += 1;
        k
    }

    /// The record of the last finished cycle.
    pub fn record(&self) -> &CycleRecord {
        &self.record
    }

    /// Mutable access to the record (the IO layer adds timing and ground truth).
    pub fn record_mut(&mut self) -> &mut CycleRecord {
        &mut self.record
    }
}

fn command_finite(c: &Command) -> bool {
    c.wheels[..c.n.min(MAX_WHEELS)]
        .iter()
        .all(|w| w.wheel_speed.is_finite() && w.steer_rate.is_finite())
}

/// ICR of the reference's body twist, for the record when avoidance is off.
fn icr_record(r: &ReferenceSample, wheels: &[[f64; 2]]) -> AvoidanceRecord {
    let (s, c) = r.z[2].sin_cos();
    let (vx, vy, w) = (r.dz[0], r.dz[1], r.dz[2]);
    let bx = c * vx + s * vy;
    let by = -s * vx + c * vy;
    let mut rec = AvoidanceRecord {
        min_distance: f64::INFINITY,
        ..Default::default()
    };
    if w.abs() > 1e-9 {
        // ICR = point with zero velocity: v + ω × p = 0 → p = (−v_y/ω, v_x/ω).
        let p = [-by / w, bx / w];
        rec.icr_body = Some(p);
        for (i, q) in wheels.iter().enumerate() {
            let d = ((p[0] - q[0]).powi(2) + (p[1] - q[1]).powi(2)).sqrt();
            if d < rec.min_distance {
                rec.min_distance = d;
                rec.nearest_wheel = Some(i);
            }
        }
    }
    rec
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn an_infeasible_tiny_limit_is_printed_readably() {
        let mut p = Platform::justin();
        p.limits.leg_speed = 1e-300;
        let traj = crate::scenario::trajectory(crate::scenario::Scenario::Seed000, &p).unwrap();
        let e = CycleCore::new(p, traj, super::super::RuntimeConfig::default())
            .err()
            .expect("infeasible");
        let m = e.to_string();
        assert!(m.contains("but `limits.leg_speed` = 1.000e-300;"), "{m}");
        assert!(!m.contains("needs 0.000 "), "{m}");
    }

    #[test]
    fn icr_of_a_pure_rotation_is_the_origin_and_translation_is_at_infinity() {
        let mut r = ReferenceSample::default();
        r.dz[2] = 1.0;
        let rec = icr_record(&r, &[[0.3, 0.2]]);
        let p = rec.icr_body.unwrap();
        assert!(p[0].abs() < 1e-12 && p[1].abs() < 1e-12);
        r.dz[0] = 1.0;
        r.dz[2] = 0.0;
        assert!(icr_record(&r, &[[0.3, 0.2]]).icr_body.is_none());
        // Moving +x while turning left (ω > 0): the ICR is on the left, at +y = v/ω.
        r.dz[2] = 0.5;
        let p = icr_record(&r, &[[0.3, 0.2]]).icr_body.unwrap();
        assert!((p[0]).abs() < 1e-12 && (p[1] - 2.0).abs() < 1e-12);
    }
}
