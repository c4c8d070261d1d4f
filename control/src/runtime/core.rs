//! The cycle minus IO and clocks: [`CycleCore`].

// Index loops over parallel per-wheel arrays read better than zipped iterators here.
#![allow(clippy::needless_range_loop)]

use super::{ControllerKind, RuntimeConfig, RuntimeError};
use crate::estimation::odometry::{EncoderResolution, Odometry};
use crate::model::kinematics::wheel_positions;
use crate::model::platform::{Platform, MAX_BUSES};
use crate::reference::avoidance::Avoidance;
use crate::reference::limits::guard_command;
use crate::reference::shaper::Shaper;
use crate::reference::trajectory::Trajectory;
use crate::runtime::link::{Buses, Update, WheelFault};
use crate::runtime::record::{AvoidanceRecord, CycleRecord, FrameRecord, MAX_RECORDED_COMMANDS};
use crate::service::command::{check_legs, check_motion};
use crate::service::ports::Rejection;
use crate::service::ports::{
    BaseState, CommandEvent, CommandKind, CommandStats, JointState, Limiting, ModuleDiagnostics,
    OdometryState, ShapingState,
};
use crate::supervisor::FaultReason;
use crate::supervisor::{
    command_at_rest, halt_command, Mode, Supervisor, SupervisorInput, SupervisorState,
};
use crate::tracking::dfl::{alignment_command, ControlInput, DflController, TrackingController};
use crate::tracking::kinematic::KinematicController;
use crate::types::{Command, Measurement, ReferenceSample, Twist, MAX_WHEELS};
use rollbase_driver::bus::BusEvent;
use rollbase_driver::busload::frame_bits;
use rollbase_driver::canopen::config::Role;
use rollbase_driver::canopen::master::DeviceFault;
use rollbase_driver::codec::{ModuleState, Setpoint, SetpointFlags, FAULT_WATCHDOG};
use rollbase_driver::frame::{CanFrame, FrameBuf};

/// Checks, before anything starts, what no timing of the trajectory can fix
/// ([`crate::reference::timescale::check_fixable`]): a duration beyond 10 h, a leg leaving its range, a
/// moving wheel whose direction of travel jumps (a corner without a stop). The error names
/// the waypoint and the cause. Everything else runs, stretched where the limits need it
/// ([`crate::reference::timescale::ScaledTrajectory`], which [`CycleCore::new`] plans).
pub fn check_feasible(p: &Platform, traj: &dyn Trajectory) -> Result<(), RuntimeError> {
    crate::reference::timescale::check_fixable(
        p,
        traj,
        &crate::reference::timescale::TimeScaleConfig::default(),
    )?;
    Ok(())
}

/// For a trajectory run as given (time scaling off): that it stays inside the platform's
/// wheel speed and leg speed limits, sampled every control period (the wheel's rolling speed
/// |u_i| / r, seed 000 eq. 18, against `limits.wheel_speed`, |λ̇_i*| against
/// `limits.leg_speed`). Steering rates are not checked: near rest they are unbounded in the
/// reference (singularity A) and the controllers (and the avoidance) limit them.
fn check_speeds(p: &Platform, traj: &dyn Trajectory) -> Result<(), RuntimeError> {
    let n = p.n().min(MAX_WHEELS).min(traj.n_legs());
    let dt = p.dt();
    let d = traj.duration();
    if !(d.is_finite() && (0.0..=crate::reference::trajectory::MAX_WAYPOINT_TIME_S).contains(&d)) {
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
            let u = crate::model::kinematics::wheel_velocity_body(
                p,
                i,
                r.z[2],
                r.z[3 + i],
                &tw,
                r.dz[3 + i],
            );
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

/// The trajectory the core follows: with the avoidance on, the avoided path time-scaled
/// into the limits; otherwise time-scaled into the limits ([`RuntimeConfig::time_scaling`]),
/// unless it already is or scaling is off (then it must stay within the speed limits as
/// given).
fn prepare_trajectory(
    p: &Platform,
    trajectory: Box<dyn Trajectory>,
    cfg: &RuntimeConfig,
) -> Result<Box<dyn Trajectory>, RuntimeError> {
    // With the avoidance on, it acts on the path before the run, and the avoided path (a
    // path the avoidance made, not the one given) is always time-scaled within every limit,
    // with the configured margins or, when the scaling is off, the default ones
    // (`crate::reference::avoidance`, "Pre-planned trajectories"); a trajectory already time-scaled is
    // avoided and scaled again. A configuration that fails validation is off, as online.
    if let Some(a) = cfg.avoidance.filter(|a| a.enabled && a.validate(p).is_ok()) {
        let avoided = crate::reference::avoidance::AvoidedTrajectory::plan(p, trajectory, a)?;
        return Ok(Box::new(
            crate::reference::timescale::ScaledTrajectory::plan(
                p,
                Box::new(avoided),
                cfg.time_scaling.unwrap_or_default(),
            )?,
        ));
    }
    if trajectory.time_scale(0.0).is_some() {
        return Ok(trajectory);
    }
    match cfg.time_scaling {
        Some(ts) => Ok(Box::new(
            crate::reference::timescale::ScaledTrajectory::plan(p, trajectory, ts)?,
        )),
        None => {
            check_feasible(p, trajectory.as_ref())?;
            check_speeds(p, trajectory.as_ref())?;
            Ok(trajectory)
        }
    }
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

/// Where the reference comes from.
enum Source {
    /// A pre-planned trajectory, from its start when tracking begins.
    Trajectory(TrajectorySource),
    /// Live motion commands through the shaper (the base service).
    Live(Box<LiveSource>),
}

struct TrajectorySource {
    traj: Box<dyn Trajectory>,
    /// The cycle clock's period count ([`CycleCore`]'s `periods`) when tracking began: the
    /// trajectory's clock starts there.
    track_start_period: Option<u64>,
    /// The kinematic controller finishes the run after the DFL terminated early.
    terminal_active: bool,
}

struct LiveSource {
    shaper: Shaper,
    stats: CommandStats,
    /// Receive time of the last valid command (s).
    last_valid: f64,
    /// The command held now is not zero (a timeout of it counts).
    holding_motion: bool,
    /// A stop was asked for: the platform stops and holds until re-armed.
    stop_pending: bool,
    /// The run ends once the platform is at rest (shutdown, or the end of the stream).
    exit: bool,
    /// The command stream ended.
    end_of_stream: bool,
    /// The DFL (not the kinematic controller) tracks this cycle.
    dfl_active: bool,
    /// A halt's ramp has brought the commands to rest: the reference follows the measured
    /// state until the next command.
    halt_done: bool,
    last_rejection: Option<Rejection>,
}

/// Per-wheel diagnostics kept by the core.
#[derive(Clone, Copy, Debug, Default)]
struct WheelDiag {
    counters: ModuleDiagnostics,
    /// The wheel was in a communication-loss fault last cycle (edge detection).
    in_watchdog: bool,
    /// Last steering-stream sequence number seen (for loss counting).
    last_seq: Option<u8>,
}

/// The decode stage's output: the measurement and the age of what it is made of.
struct Decoded {
    meas: Measurement,
    /// Data age per wheel (cycles): its oldest stream.
    age: [u32; MAX_WHEELS],
    /// Module age per wheel (cycles): its newest stream.
    alive: [u32; MAX_WHEELS],
    /// The node of each wheel's oldest stream.
    stale_node: [u8; MAX_WHEELS],
    /// Receive time of the oldest wheel's newest sample (s; −∞ when none arrived).
    oldest_fb: f64,
}

/// What the cycle sent, for its record.
struct Sent {
    cmd: Command,
    enable: bool,
    /// The supervisor's mode as sent (`track`, `halt`, `align`, …).
    mode: &'static str,
}

/// The cycle minus IO and clocks: decode → odometry → reference (trajectory or shaper) →
/// avoidance → controller → supervisor → output guard → encode (see the `runtime` module
/// docs). Built once; allocates nothing per cycle.
pub struct CycleCore {
    fault_reset_cycles: u32,
    platform: Platform,
    cfg: RuntimeConfig,
    n: usize,
    nodes: [u8; MAX_WHEELS],
    link: Buses,
    /// An arm was asked for while the link was not ready (CiA 402 devices booting).
    arm_pending: bool,
    /// Cycle the supervisor was last armed in: the age of a stream that never delivered.
    armed_cycle: u64,
    /// Latest time passed in (s).
    now: f64,
    /// SYNC time of this cycle ([`CycleCore::start_cycle`]) and of the cycle whose readings
    /// the odometry last integrated: the interval the odometry integrates over.
    sync_t: f64,
    odom_sync_t: Option<f64>,
    /// SYNC time of the cycle run before this one (none before the first).
    prev_sync_t: Option<f64>,
    /// When this cycle's SYNC and the previous cycle's really went out (s; the SYNC time
    /// unless the runtime says otherwise: [`CycleCore::sync_sent_at`]).
    sync_sent: f64,
    prev_sync_sent: Option<f64>,
    /// Commands taken since the last finished cycle (for the record), their count, and those
    /// beyond the record's room.
    taken: [Option<CommandEvent>; MAX_RECORDED_COMMANDS],
    n_taken: usize,
    taken_omitted: u32,
    setpoints: [Setpoint; MAX_WHEELS],
    odom: Odometry,
    sup: Supervisor,
    controller: Box<dyn TrackingController + Send>,
    /// The kinematic controller: finishes trajectories after the DFL terminated early (it
    /// cannot pass through rest, seed 000 Sect. IV), and tracks live commands near rest.
    kinematic: KinematicController,
    avoidance: Option<Avoidance>,
    source: Source,
    fb: [WheelFeedback; MAX_WHEELS],
    cycle: u64,
    /// Periods of the cycle clock elapsed since the first cycle, skipped cycles included
    /// ([`elapsed_periods`]): the clock of a trajectory and of the live shaper. Equal to
    /// `cycle` while no cycle is skipped (every lockstep run).
    periods: u64,
    /// Periods this cycle's SYNC is after the previous cycle's (1 unless cycles were skipped).
    periods_this_cycle: u64,
    last_cmd: Command,
    record: CycleRecord,
    stop_requested: bool,
    bus_error: bool,
    /// The bus that went bus-off, latched until re-armed.
    bus_off: Option<u8>,
    /// A bus went bus-off since the last re-arm: the next re-arm asks the runtime to reopen
    /// the interface ([`CycleCore::take_reopen`]).
    reopen_after_rearm: bool,
    reopen: bool,
    done_cycles: u32,
    controller_moved: bool,
    sync_time: f64,
    rejected_this_cycle: u32,
    wheel_xy: [[f64; 2]; MAX_WHEELS],
    diag: [WheelDiag; MAX_WHEELS],
    wheel_angle: [f64; MAX_WHEELS],
    prev_wheel_speed: [f64; MAX_WHEELS],
    /// The last steering angle of each wheel with a steering range, inside its range (turns
    /// counted; kept across re-arms).
    steer_turns: [Option<f64>; MAX_WHEELS],
    /// Frame bits of each of the last second's cycles (ring, per bus) and their sum.
    bus_bits: [Vec<u32>; MAX_BUSES],
    bus_bits_at: usize,
    bus_bits_sum: [u64; MAX_BUSES],
    bits_this_cycle: [u32; MAX_BUSES],
    /// The bus the frames pushed now belong to (for their records and bit counts).
    cur_bus: usize,
    state: BaseState,
}

/// Contact speed (m/s) from which the DFL takes over from the kinematic controller when
/// following live commands; it hands back below [`crate::tracking::dfl::EPSILON`] (hysteresis).
pub const DFL_ENTRY_SPEED: f64 = 2.0 * crate::tracking::dfl::EPSILON;

/// A trajectory run whose reference has ended is done once the platform rests within this
/// distance (m) of the reference's end (by the estimate; the tracking controllers' last
/// millimetres converge with a time constant of about K_D/K_P = 1.5 s)…
pub const SETTLED_POSITION: f64 = 0.002;
/// …this heading (rad, 0.2°)…
pub const SETTLED_HEADING: f64 = 0.003_490_658_503_988_659;
/// …and every leg within this of its end extension (m), every wheel and steering drive
/// slower than SETTLED_SPEED.
pub const SETTLED_LEG: f64 = 0.001;
/// Speed (rad/s) below which a drive has settled at the end of a trajectory (a wheel's
/// 0.1 rad/s is 8.5 mm/s: the controllers' creep onto the goal).
pub const SETTLED_SPEED: f64 = 0.1;

/// Most shaper steps one cycle takes after skipped cycles (0.1 s at 250 Hz; twice the
/// modules' 50 ms setpoint watchdog, after which they stop on their own).
const MAX_CATCH_UP_PERIODS: u64 = 25;

/// Whole periods `dt` from the SYNC time `prev` to the SYNC time `sync`, at least one: how far
/// the cycle clock moved from one cycle run to the next. A real-time runtime that falls behind
/// skips cycles, and the base keeps moving on the setpoints it has meanwhile, so the
/// references advance by the periods elapsed, not by one per cycle run: a trajectory's clock
/// that counted cycles run fell behind the base by the skipped time (a stall of 2 of every 3
/// cycles for 2 s of seed 000 left its reference 9 cm behind the simulated base) and the
/// controller then pulled the base back to it.
fn elapsed_periods(dt: f64, prev: f64, sync: f64) -> u64 {
    let k = (sync - prev) / dt;
    if k.is_finite() && k > 1.5 {
        // A clock that jumped by days is still a finite count (saturating cast).
        k.round() as u64
    } else {
        1
    }
}

/// The time the odometry integrates a cycle's readings over: the whole number of periods
/// `dt` between the SYNC that sampled them (`sync`) and the SYNC of the readings it
/// integrated last (`prev`), at least one. A real-time runtime that falls behind skips
/// cycles ([`super::realtime`]): no SYNC goes out for them, but the base keeps moving, so
/// integrating one nominal period would lose the skipped cycles' travel (seen under load:
/// the pose fell 19 mm behind its own twists in 0.14 s). SYNCs are sent on the period's
/// grid, so the interval is a whole number of periods; rounding it keeps lockstep runs
/// (where `k·dt − (k−1)·dt` differs from `dt` in the last bit) bit-identical to integrating
/// `dt`.
fn odometry_interval(dt: f64, prev: Option<f64>, sync: f64) -> f64 {
    match prev {
        Some(p) if (sync - p).is_finite() && sync > p => ((sync - p) / dt).round().max(1.0) * dt,
        _ => dt,
    }
}

impl CycleCore {
    /// Builds the core following a pre-planned trajectory; allocates everything it will
    /// ever need.
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
        let trajectory = prepare_trajectory(&platform, trajectory, &cfg)?;
        let r0 = trajectory.sample(0.0);
        let mut legs = [0.0; MAX_WHEELS];
        legs[..n].copy_from_slice(&r0.z.as_slice()[3..3 + n]);
        let source = Source::Trajectory(TrajectorySource {
            traj: trajectory,
            track_start_period: None,
            terminal_active: false,
        });
        Ok(Self::build(platform, cfg, source, r0.pose(), &legs[..n]))
    }

    /// Builds the core of the base service: it follows live motion commands
    /// ([`CycleCore::command`]) through the shaper ([`crate::reference::shaper`]), from wherever the
    /// platform is when it is armed. Odometry starts at the origin of the odometry frame.
    pub fn new_live(platform: Platform, cfg: RuntimeConfig) -> Result<Self, RuntimeError> {
        platform.validate()?;
        cfg.validate(&platform)?;
        let n = platform.n();
        let mut legs = [0.0; MAX_WHEELS];
        for (l, w) in legs.iter_mut().zip(&platform.wheels) {
            *l = w.lambda_nominal;
        }
        let mut shaper = Shaper::new(&platform, cfg.shaper);
        // Live commands: the avoidance acts on the command, before the shaper (the shaped
        // reference then carries the avoided motion within every limit; `crate::reference::avoidance`,
        // "Live commands"). A configuration that fails validation is off, as on trajectories.
        shaper.set_avoidance(cfg.avoidance.filter(|a| a.validate(&platform).is_ok()));
        let source = Source::Live(Box::new(LiveSource {
            shaper,
            stats: CommandStats::default(),
            last_valid: 0.0,
            holding_motion: false,
            stop_pending: false,
            exit: false,
            end_of_stream: false,
            dfl_active: false,
            halt_done: false,
            last_rejection: None,
        }));
        Ok(Self::build(
            platform,
            cfg,
            source,
            crate::types::Pose::default(),
            &legs[..n],
        ))
    }

    fn build(
        platform: Platform,
        cfg: RuntimeConfig,
        source: Source,
        start: crate::types::Pose,
        legs: &[f64],
    ) -> Self {
        let n = platform.n();
        let link = Buses::new(&platform, cfg.counter_policy);
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
        let wheel_xy = wheel_positions(&platform, legs);
        let mut odom = Odometry::new(start);
        odom.set_resolution(encoder_resolution(&platform));
        let window = platform.cycle_hz.round().clamp(1.0, 10_000.0) as usize;
        let mut diag = [WheelDiag::default(); MAX_WHEELS];
        for (d, node) in diag.iter_mut().zip(nodes) {
            d.counters.node = node;
            d.counters.state = 255;
        }
        let mut kinematic = KinematicController::new(&platform);
        kinematic.set_termination(matches!(source, Source::Trajectory(_)));
        let mut state = BaseState {
            n,
            ..BaseState::default()
        };
        state.odometry.pose = start;
        Self {
            fault_reset_cycles: 0,
            n,
            nodes,
            link,
            arm_pending: false,
            armed_cycle: 0,
            now: 0.0,
            sync_t: 0.0,
            odom_sync_t: None,
            prev_sync_t: None,
            sync_sent: 0.0,
            prev_sync_sent: None,
            taken: [None; MAX_RECORDED_COMMANDS],
            n_taken: 0,
            taken_omitted: 0,
            setpoints: [Setpoint::default(); MAX_WHEELS],
            odom,
            sup,
            controller,
            kinematic,
            avoidance,
            source,
            fb: [WheelFeedback::default(); MAX_WHEELS],
            cycle: 0,
            periods: 0,
            periods_this_cycle: 1,
            last_cmd: Command::zero(n),
            record,
            stop_requested: false,
            bus_error: false,
            bus_off: None,
            reopen_after_rearm: false,
            reopen: false,
            done_cycles: 0,
            controller_moved: false,
            sync_time: 0.0,
            rejected_this_cycle: 0,
            wheel_xy,
            diag,
            wheel_angle: [0.0; MAX_WHEELS],
            prev_wheel_speed: [0.0; MAX_WHEELS],
            steer_turns: [None; MAX_WHEELS],
            bus_bits: std::array::from_fn(|_| vec![0; window]),
            bus_bits_at: 0,
            bus_bits_sum: [0; MAX_BUSES],
            bits_this_cycle: [0; MAX_BUSES],
            cur_bus: 0,
            state,
            platform,
            cfg,
        }
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
    /// [`Link::rx_stats`](crate::runtime::link::Link::rx_stats) for the CiA 402 profile's mapping).
    pub fn rx_stats(&self) -> &rollbase_driver::rx::RxStats {
        self.link.rx_stats()
    }

    /// The wire side of the cycle, one link per bus (e.g. the CiA 402 masters' devices, for
    /// reports).
    pub fn link(&self) -> &Buses {
        &self.link
    }

    /// Number of CAN buses the platform's wheels are on.
    pub fn buses(&self) -> usize {
        self.link.count()
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

    /// The state port's value of the last finished cycle (odometry, joints, supervisor,
    /// diagnostics, command counters, shaping).
    pub fn base_state(&self) -> &BaseState {
        &self.state
    }

    /// Mutable access to the state (the IO layer adds log time and deadline misses).
    pub fn base_state_mut(&mut self) -> &mut BaseState {
        &mut self.state
    }

    /// True when the core follows live commands (built with [`CycleCore::new_live`]).
    pub fn is_live(&self) -> bool {
        matches!(self.source, Source::Live(_))
    }

    /// The last command the command port rejected, and why.
    pub fn last_rejection(&self) -> Option<Rejection> {
        match &self.source {
            Source::Live(l) => l.last_rejection,
            Source::Trajectory(_) => None,
        }
    }

    /// The timing of the trajectory being followed when it is time-scaled: nominal and
    /// executed durations, the slowest scale and why (`None` for live commands or an
    /// unscaled trajectory).
    pub fn trajectory_timing(&self) -> Option<crate::reference::status::Timing> {
        match &self.source {
            Source::Trajectory(s) => s.traj.timing(),
            Source::Live(_) => None,
        }
    }

    /// The duration of the trajectory being followed (infinite for live commands).
    pub fn reference_duration(&self) -> f64 {
        match &self.source {
            Source::Trajectory(s) => s.traj.duration(),
            Source::Live(_) => f64::INFINITY,
        }
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
    /// running and clears the devices' latched faults ([`Link::rearm`](crate::runtime::link::Link::rearm)); the supervisor arms
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
        self.bus_off = None;
        if std::mem::take(&mut self.reopen_after_rearm) {
            self.reopen = true;
        }
        self.done_cycles = 0;
        match &mut self.source {
            Source::Trajectory(s) => s.track_start_period = None,
            Source::Live(l) => {
                l.stop_pending = false;
                l.shaper.halt_for(Limiting::None);
            }
        }
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
        if self.link.is_cia402() {
            // Devices may have been rebooted to get here: samples from before are not
            // evidence of anything now, and the streams' ages count from the arm.
            self.fb = [WheelFeedback::default(); MAX_WHEELS];
        }
        self.sup.arm()
    }

    /// Operator stop (Ctrl-C, SIGTERM): a controlled stop, then the run ends.
    pub fn request_stop(&mut self) {
        self.stop_requested = true;
        if let Source::Live(l) = &mut self.source {
            l.stop_pending = true;
            l.exit = true;
            l.shaper.halt_for(Limiting::Stop);
        }
    }

    /// The bus reported an error (interface down, socket error): fault and controlled stop.
    pub fn report_bus_error(&mut self) {
        self.bus_error = true;
    }

    /// The CAN controller of bus `bus` reported a change of its error state (an error
    /// frame): counted per kind in the diagnostics ([`CanBusDiagnostics`](crate::service::ports::CanBusDiagnostics)) when it
    /// changes the state (a repeated report, e.g. every failed send while bus-off, is not
    /// counted). Bus-off faults the platform ([`FaultReason::BusOff`], latched until
    /// re-armed), takes every CiA 402 device of that bus as lost ([`Link::bus_off`](crate::runtime::link::Link::bus_off): the
    /// re-arm boots them again) and commands quick stop; the next re-arm also asks the
    /// runtime to reopen the interface ([`CycleCore::take_reopen`]). The other states are
    /// only counted and shown.
    pub fn report_bus_event(&mut self, bus: usize, event: BusEvent) {
        let b = bus.min(MAX_BUSES - 1);
        let d = &mut self.state.diagnostics.can[b];
        if d.state == Some(event) && event != BusEvent::Controller {
            return;
        }
        d.state = Some(event);
        d.events[event.index()] = d.events[event.index()].saturating_add(1);
        if event == BusEvent::BusOff {
            self.bus_off.get_or_insert(b as u8);
            self.reopen_after_rearm = true;
            self.link.bus_off(b);
        }
    }

    /// True once after a re-arm that followed a bus-off: the runtime reopens the interface
    /// (a fresh socket, [`CanBus::reopen`](rollbase_driver::bus::CanBus::reopen)) before the devices are booted again.
    pub fn take_reopen(&mut self) -> bool {
        std::mem::take(&mut self.reopen)
    }

    /// True once the platform has been at rest in Stopped, Fault or Idle (after a stop
    /// request) for [`RuntimeConfig::linger_cycles`] cycles. Following live commands, only
    /// after a shutdown or the end of the command stream.
    pub fn done(&self) -> bool {
        self.done_cycles >= self.cfg.linger_cycles
    }

    /// The command port: takes one event from a command source, received at `ev.t` (s, on
    /// the run's time base). Motion commands are checked ([`crate::service::command`]) and rejected
    /// ones are counted and never reach the wheels; valid ones go to the shaper while the
    /// platform follows commands (Tracking), and are counted as ignored otherwise (stopped or
    /// in fault: re-arm first). With a trajectory source only `Shutdown` (and `Stop`) act: a
    /// controlled stop.
    pub fn command(&mut self, ev: CommandEvent) {
        if self.n_taken < MAX_RECORDED_COMMANDS {
            self.taken[self.n_taken] = Some(ev);
            self.n_taken += 1;
        } else {
            self.taken_omitted = self.taken_omitted.saturating_add(1);
        }
        let tracking = self.sup.state() == SupervisorState::Tracking;
        let rearm = {
            let Source::Live(l) = &mut self.source else {
                if matches!(ev.kind, CommandKind::Shutdown | CommandKind::Stop) {
                    self.request_stop();
                }
                return;
            };
            let p = &self.platform;
            let following = tracking && !l.stop_pending;
            let accept = |l: &mut LiveSource, r: Result<(), Rejection>| match r {
                Err(e) => {
                    l.stats.rejected += 1;
                    l.stats.last_rejection = Some(e);
                    l.last_rejection = Some(e);
                    false
                }
                Ok(()) if !following => {
                    l.stats.ignored += 1;
                    false
                }
                Ok(()) => {
                    l.stats.accepted += 1;
                    l.last_valid = ev.t;
                    true
                }
            };
            match ev.kind {
                CommandKind::Motion(m) => match check_motion(p, &m) {
                    Ok(m) => {
                        if accept(l, Ok(())) {
                            l.holding_motion = m.twist != Twist::default() || m.legs.is_some();
                            l.shaper
                                .command(m.twist, m.legs.as_ref().map(|x| x.as_slice()));
                        }
                    }
                    Err(e) => {
                        accept(l, Err(e));
                    }
                },
                CommandKind::Legs(t) => match check_legs(p, &t) {
                    Ok(t) => {
                        if accept(l, Ok(())) {
                            l.holding_motion = true;
                            l.shaper.command_legs(t.as_slice());
                        }
                    }
                    Err(e) => {
                        accept(l, Err(e));
                    }
                },
                CommandKind::Stop => {
                    l.stop_pending = true;
                    l.shaper.halt_for(Limiting::Stop);
                }
                CommandKind::Shutdown => {
                    l.stop_pending = true;
                    l.exit = true;
                    l.shaper.halt_for(Limiting::Stop);
                }
                CommandKind::EndOfStream => l.end_of_stream = true,
                CommandKind::Rearm => {}
            }
            matches!(ev.kind, CommandKind::Rearm)
        };
        if rearm {
            self.arm();
        }
        if matches!(ev.kind, CommandKind::Shutdown) {
            self.stop_requested = true;
        }
    }

    /// Starts the cycle at time `t` (s): writes the frames to send now into `out` (cleared
    /// first), SYNC first; with the CiA 402 profile NMT commands, the master's heartbeat and
    /// SDO requests follow when due. On a platform with two buses every bus's frames go into
    /// `out` (as if on one medium): use [`CycleCore::start_cycle_buses`] there.
    pub fn start_cycle(&mut self, t: f64, out: &mut FrameBuf) {
        self.start_cycle_buses(t, std::slice::from_mut(out));
    }

    /// [`CycleCore::start_cycle`] with one buffer per bus: bus `b`'s frames (its own SYNC
    /// first) into `outs[b]`, each cleared first.
    pub fn start_cycle_buses(&mut self, t: f64, outs: &mut [FrameBuf]) {
        let mut rec = CycleRecord::new(self.cycle, t, self.n);
        rec.nodes = self.nodes;
        self.record = rec;
        self.rejected_this_cycle = 0;
        self.bits_this_cycle = [0; MAX_BUSES];
        self.now = t;
        if self.cycle > 0 {
            self.prev_sync_t = Some(self.sync_t);
            self.prev_sync_sent = Some(self.sync_sent);
            self.periods_this_cycle = elapsed_periods(self.platform.dt(), self.sync_t, t);
            self.periods += self.periods_this_cycle;
        }
        self.sync_t = t;
        self.sync_sent = t;
        for o in outs.iter_mut() {
            o.clear();
        }
        self.link.start_cycle(self.cycle, t, outs);
        self.record_sent(t, outs);
    }

    /// The time (s, the cycle clock) this cycle's SYNC really went out, when it differs from
    /// the time passed to [`CycleCore::start_cycle`] (a real-time cycle that woke late sends
    /// it late). The modules sample their encoders when the SYNC reaches them, so the
    /// encoder-jump check predicts a steering reading from the previous one over the time
    /// between the two SYNCs as sent, not one period.
    pub fn sync_sent_at(&mut self, t: f64) {
        if t.is_finite() && t >= self.sync_t {
            self.sync_sent = t;
        }
    }

    /// Records every frame of `outs` (buffer b = bus b) as sent at `t`.
    fn record_sent(&mut self, t: f64, outs: &[FrameBuf]) {
        for (b, o) in outs.iter().enumerate() {
            self.cur_bus = b;
            for &f in o.as_slice() {
                self.push_tx(t, &f);
            }
        }
        self.cur_bus = 0;
    }

    /// After [`CycleCore::start_cycle`] and the frames that arrived since the last cycle's
    /// window ([`CycleCore::on_frame`], stamped before the SYNC): appends to `out` the frames
    /// those made due (CiA 402: the next SDO request of a device being configured whose
    /// answer just came; nothing natively). Returns how many were appended. Runtimes call it
    /// before they send `out`, so the SYNC still goes first.
    pub fn after_late_frames(&mut self, t: f64, out: &mut FrameBuf) -> usize {
        self.after_late_frames_buses(t, std::slice::from_mut(out))
    }

    /// [`CycleCore::after_late_frames`] with one buffer per bus (as
    /// [`CycleCore::start_cycle_buses`]): each bus's due frames go into its own buffer.
    pub fn after_late_frames_buses(&mut self, t: f64, outs: &mut [FrameBuf]) -> usize {
        let mut before = [0usize; MAX_BUSES];
        for (b, o) in outs.iter().enumerate().take(MAX_BUSES) {
            before[b] = o.len();
        }
        self.link.service(t, outs);
        let mut added = 0;
        for (b, o) in outs.iter().enumerate().take(MAX_BUSES) {
            self.cur_bus = b;
            for k in before[b]..o.len() {
                let f = o.as_slice()[k];
                self.push_tx(t, &f);
                added += 1;
            }
        }
        self.cur_bus = 0;
        added
    }

    fn push_tx(&mut self, t: f64, f: &CanFrame) {
        if f.id() == 0x080 {
            self.sync_time = t;
        }
        let b = self.cur_bus.min(MAX_BUSES - 1);
        self.bits_this_cycle[b] = self.bits_this_cycle[b].saturating_add(frame_bits(f.len()));
        let mut data = [0u8; 8];
        data[..f.len()].copy_from_slice(f.data());
        self.record.push_tx(FrameRecord {
            t,
            id: f.id(),
            len: f.len() as u8,
            data,
            error: None,
            bus: b as u8,
        });
    }

    /// The wheel whose module (native) or device (CiA 402) uses `node`.
    fn wheel_of_node(&self, node: u8) -> Option<usize> {
        if node == 0 {
            return None;
        }
        (0..self.n).find(|&i| {
            [Role::Steer, Role::Drive, Role::Leg]
                .iter()
                .any(|&r| self.link.stream_node(i, r) == node)
        })
    }

    /// Takes one received frame (its timestamp in s on the run's time base). On a platform
    /// with two buses it goes to the bus its node is on ([`CycleCore::on_frame_on`] when the
    /// bus it arrived on is known).
    pub fn on_frame(&mut self, frame: &CanFrame, t: f64) {
        self.on_frame_from(None, frame, t);
    }

    /// Takes one frame received on bus `bus`.
    pub fn on_frame_on(&mut self, bus: usize, frame: &CanFrame, t: f64) {
        self.on_frame_from(Some(bus), frame, t);
    }

    fn on_frame_from(&mut self, bus: Option<usize>, frame: &CanFrame, t: f64) {
        let mut data = [0u8; 8];
        data[..frame.len()].copy_from_slice(frame.data());
        self.record.timing.frames_in += 1;
        let node = (frame.id() & 0x7F) as u8;
        let b = bus
            .unwrap_or_else(|| self.link.bus_of_node(node))
            .min(MAX_BUSES - 1);
        self.bits_this_cycle[b] = self.bits_this_cycle[b].saturating_add(frame_bits(frame.len()));
        self.now = self.now.max(t);
        let result = self.link.on_frame(bus, frame, t);
        let error = match &result {
            Ok(_) => None,
            Err(kind) => {
                self.rejected_this_cycle += 1;
                // Standard-frame ids carry the node in their low 7 bits (native and CANopen).
                if let Some(w) = self.wheel_of_node(node) {
                    self.diag[w].counters.rejected += 1;
                }
                Some(*kind)
            }
        };
        self.record.push_rx(FrameRecord {
            t,
            id: frame.id(),
            len: frame.len() as u8,
            data,
            error,
            bus: b as u8,
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
                    let d = &mut self.diag[wheel];
                    if let Some(prev) = d.last_seq {
                        let gap = seq.wrapping_sub(prev).wrapping_sub(1) & 0x0F;
                        d.counters.lost += u64::from(gap);
                    }
                    d.last_seq = Some(seq);
                    if !on_time {
                        d.counters.late += 1;
                    }
                    let fb = &mut self.fb[wheel];
                    // Within a steering range the angle is kept inside it, turn by turn
                    // (crate::angle::SteerRange): from the reading nearest the range's
                    // centre, then by continuity.
                    let angle = match self.platform.wheels[wheel].steering_range() {
                        None => angle,
                        Some(r) => {
                            let a = match self.steer_turns[wheel] {
                                Some(prev) => prev + crate::angle::diff(angle, prev),
                                None => r.first(angle),
                            };
                            self.steer_turns[wheel] = Some(a);
                            a
                        }
                    };
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
            // A wheel without a leg has no leg stream: its steering stream stands in.
            let has_leg = self.platform.wheels[i].leg;
            let leg_at = if has_leg { &fb.leg_at } else { &fb.steer_at };
            let streams = [
                (age_of(&fb.steer_at), Role::Steer),
                (age_of(&fb.drive_at), Role::Drive),
                (
                    age_of(leg_at),
                    if has_leg { Role::Leg } else { Role::Steer },
                ),
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
            let newest = fb.steer_at.time.min(fb.drive_at.time).min(leg_at.time);
            if oldest == f64::NEG_INFINITY || newest < oldest {
                oldest = newest;
            }
        }
        (m, age, alive, stale_node, oldest)
    }

    /// Runs the control step at time `t` (s) and writes the setpoint frames into `out`
    /// (cleared first; with the CiA 402 profile SDO requests that became due follow);
    /// returns how many were written. The cycle's record is then available from
    /// [`CycleCore::record`], its state from [`CycleCore::base_state`]. On a platform with
    /// two buses every bus's frames go into `out`: use [`CycleCore::finish_cycle_buses`].
    ///
    /// The body is the loop itself, one named stage per line.
    pub fn finish_cycle(&mut self, t: f64, out: &mut FrameBuf) -> usize {
        self.finish_cycle_buses(t, std::slice::from_mut(out))
    }

    /// [`CycleCore::finish_cycle`] with one buffer per bus (bus `b`'s setpoints into
    /// `outs[b]`, each cleared first); returns how many frames were written in all.
    pub fn finish_cycle_buses(&mut self, t: f64, out: &mut [FrameBuf]) -> usize {
        let dt = self.platform.dt();
        self.now = self.now.max(t);
        self.arm_when_ready();
        let fb = self.decode();
        let odo_dt = odometry_interval(dt, self.odom_sync_t, self.sync_t);
        self.odom_sync_t = Some(self.sync_t);
        let odo = self.odom.update(&self.platform, &fb.meas, odo_dt);
        // Reference: the trajectory or the shaper (after the command timeout), then avoidance.
        self.live_tick(t);
        let nominal = self.reference(&fb.meas, &odo);
        let (reference, av) = self.avoid(&nominal, dt);
        // Controller (only while tracking) before the supervisor so it can see the result.
        let (mut sup_in, mut track_cmd) = self.supervisor_input(&fb, &odo, &nominal);
        if self.sup.state() == SupervisorState::Tracking {
            // The controllers integrate over the time elapsed since the last cycle run (one
            // period unless cycles were skipped: [`elapsed_periods`]), as the references
            // advance: integrating one period after a skip left seed 000 4.8 mm off its
            // reference (2 s with 2 of every 3 cycles skipped), now 0.2 mm. The output guard
            // still limits the change to one period's acceleration.
            let elapsed = dt * self.periods_this_cycle.min(MAX_CATCH_UP_PERIODS) as f64;
            track_cmd = self.control(&fb.meas, &odo, &reference, &mut sup_in, elapsed);
        }
        let mode = self.supervise(&sup_in, &fb.meas, &odo, &mut track_cmd);
        // Command: the supervisor's mode, then the output guard.
        let (cmd, enable, brake, mode_name) =
            self.command_for(mode, &fb.meas, &nominal, &reference, track_cmd);
        let k = self.encode(t, &cmd, enable, brake, out);
        // Bookkeeping: the command sent, the record, the state port.
        self.end_of_cycle(&cmd);
        let sent = Sent {
            cmd,
            enable,
            mode: mode_name,
        };
        self.fill_record(t, &fb, &odo, (&nominal, &reference), av, &sent);
        self.publish_state(t, &fb.meas, &odo, fb.alive, dt);
        self.cycle += 1;
        k
    }

    /// Decode: the latest measurement with the age of each wheel's streams
    /// ([`CycleCore::measurement`]), and the wheel contact points at the measured legs.
    fn decode(&mut self) -> Decoded {
        let (meas, age, alive, stale_node, oldest_fb) = self.measurement();
        for (i, w) in meas.wheels[..self.n].iter().enumerate() {
            let a = self.platform.wheels[i].alpha;
            self.wheel_xy[i] = [w.leg * a.cos(), w.leg * a.sin()];
        }
        Decoded {
            meas,
            age,
            alive,
            stale_node,
            oldest_fb,
        }
    }

    /// Supervisor: one step of the state machine on this cycle's inputs; on entering
    /// Tracking the reference and the controllers start ([`CycleCore::start_tracking`]) and
    /// `track_cmd` becomes their first command. Returns the mode to command.
    fn supervise(
        &mut self,
        sup_in: &SupervisorInput,
        meas: &Measurement,
        odo: &crate::estimation::odometry::OdometryOutput,
        track_cmd: &mut Command,
    ) -> Mode {
        let at_rest = command_at_rest(&self.last_cmd, self.sup.config().rest_speed);
        let state_before = self.sup.state();
        let mode = self.sup.step(&self.platform, sup_in, at_rest);
        // Feedback lost or the bus failing: the host cannot ramp the drives down on what they
        // do; drives that can (CiA 402) stop on their own quick-stop ramp.
        if self.sup.state() == SupervisorState::Fault
            && state_before != SupervisorState::Fault
            && matches!(
                self.sup.reason(),
                Some(
                    FaultReason::StaleFeedback { .. }
                        | FaultReason::BusError
                        | FaultReason::BusOff { .. }
                )
            )
        {
            self.link.quick_stop();
        }
        if self.sup.state() == SupervisorState::Tracking
            && state_before != SupervisorState::Tracking
        {
            *track_cmd = self.start_tracking(meas, odo);
        }
        mode
    }

    /// After the setpoints went out: the command becomes the last one sent (the next
    /// cycle's acceleration limits start from it), and the count of cycles spent at rest in
    /// a finished state (towards [`CycleCore::done`]) advances or restarts.
    fn end_of_cycle(&mut self, cmd: &Command) {
        self.last_cmd = *cmd;
        let settled = matches!(
            self.sup.state(),
            SupervisorState::Stopped | SupervisorState::Fault
        ) && command_at_rest(cmd, self.sup.config().rest_speed);
        let idle_stop = self.sup.state() == SupervisorState::Idle && self.stop_requested;
        if (settled || idle_stop) && self.may_end() {
            self.done_cycles = self.done_cycles.saturating_add(1);
        } else {
            self.done_cycles = 0;
        }
    }

    /// The cycle's record (started by [`CycleCore::start_cycle`], frames added since):
    /// measurement and feedback ages, module states, references, the command sent and its
    /// mode, odometry, avoidance, supervisor state, timing, and the commands taken since the
    /// last record.
    fn fill_record(
        &mut self,
        t: f64,
        fb: &Decoded,
        odo: &crate::estimation::odometry::OdometryOutput,
        (nominal, reference): (&ReferenceSample, &ReferenceSample),
        av: AvoidanceRecord,
        sent: &Sent,
    ) {
        let r = &mut self.record;
        r.t = r.t.min(t);
        r.measurement = fb.meas;
        r.feedback_age = fb.age;
        for i in 0..self.n {
            r.module_state[i] = self.link.wheel_state(i).map_or(255, |s| s.to_raw());
        }
        r.nominal = *nominal;
        r.reference = *reference;
        r.command = sent.cmd;
        r.mode = sent.mode;
        r.enable = sent.enable;
        r.pose = odo.pose;
        r.twist_body = odo.twist_body;
        r.slip_residual = odo.residual;
        r.avoidance = av;
        r.wheel_xy = self.wheel_xy;
        r.state = self.sup.state();
        r.reason = self.sup.reason();
        r.timing.frames_out = r.n_tx_total;
        r.timing.rejected = self.rejected_this_cycle;
        r.timing.feedback_age_us = if fb.oldest_fb.is_finite() {
            ((t - fb.oldest_fb) * 1e6).max(0.0)
        } else {
            f64::NAN
        };
        // The commands taken since the last record.
        r.commands_in = std::mem::replace(&mut self.taken, [None; MAX_RECORDED_COMMANDS]);
        r.commands_in_omitted = std::mem::take(&mut self.taken_omitted);
        self.n_taken = 0;
    }

    /// CiA 402: arm once every device runs (or fault naming the one that cannot boot).
    fn arm_when_ready(&mut self) {
        if !self.arm_pending {
            return;
        }
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

    /// Whether a settled platform may end the run: a trajectory run always; the base
    /// service only after a shutdown or the end of its command stream.
    fn may_end(&self) -> bool {
        match &self.source {
            Source::Trajectory(_) => true,
            Source::Live(l) => l.exit,
        }
    }

    /// Live commands: the command timeout, and the end of the stream.
    fn live_tick(&mut self, t: f64) {
        let tracking = self.sup.state() == SupervisorState::Tracking;
        let Source::Live(l) = &mut self.source else {
            return;
        };
        if tracking
            && !l.shaper.halted()
            && t - l.last_valid > self.platform.service.command_timeout
        {
            l.shaper.halt();
            if l.holding_motion {
                l.stats.timeouts += 1;
            }
            l.holding_motion = false;
        }
        if l.end_of_stream && (l.halt_done || !tracking) && !l.exit {
            l.exit = true;
            l.stop_pending = true;
            self.stop_requested = true;
        }
    }

    fn reference_time(&self) -> f64 {
        match &self.source {
            Source::Trajectory(TrajectorySource {
                track_start_period: Some(c),
                ..
            }) => self.periods.saturating_sub(*c) as f64 * self.platform.dt(),
            _ => 0.0,
        }
    }

    /// The nominal reference of this cycle: the trajectory at its clock (held at its start
    /// until tracking begins), or the shaper's next sample while following live commands
    /// (held at the measured state otherwise).
    fn reference(
        &mut self,
        meas: &Measurement,
        odo: &crate::estimation::odometry::OdometryOutput,
    ) -> ReferenceSample {
        let t_ref = self.reference_time();
        let tracking = self.sup.state() == SupervisorState::Tracking;
        let n = self.n;
        match &mut self.source {
            Source::Trajectory(s) => s.traj.sample(t_ref.min(s.traj.duration())),
            Source::Live(l) => {
                if !l.shaper.halted() {
                    l.halt_done = false;
                }
                if !tracking || l.halt_done {
                    let mut legs = [0.0; MAX_WHEELS];
                    let mut steer = [0.0; MAX_WHEELS];
                    for i in 0..n {
                        legs[i] = meas.wheels[i].leg;
                        steer[i] = meas.wheels[i].steer_angle;
                    }
                    l.shaper.reset(odo.pose, &legs[..n], &steer[..n]);
                    return l.shaper.hold_sample();
                }
                // The shaper's reference advances by the periods elapsed, as a trajectory's
                // clock does ([`elapsed_periods`]); after a stall longer than
                // MAX_CATCH_UP_PERIODS the modules' watchdogs have stopped the base anyway.
                for _ in 1..self.periods_this_cycle.min(MAX_CATCH_UP_PERIODS) {
                    l.shaper.step();
                }
                l.shaper.step()
            }
        }
    }

    /// Singularity avoidance of this cycle's reference (seed 001). A trajectory was avoided
    /// before the run ([`crate::reference::avoidance::AvoidedTrajectory`], built by
    /// `prepare_trajectory` whenever the avoidance is on): its sample is the avoided
    /// reference, and the record is the filter's state at the clock's path time; a
    /// trajectory without that record would go through [`Avoidance::step`] while tracking
    /// (none does when the configuration is valid). Live commands were avoided before the
    /// shaper ([`crate::reference::avoidance`], "Live commands"): the shaped reference is followed as it
    /// is, and the record says whether the command's ICR was moved out of a field.
    fn avoid(&mut self, nominal: &ReferenceSample, dt: f64) -> (ReferenceSample, AvoidanceRecord) {
        if let Source::Live(l) = &self.source {
            let mut rec = icr_record(nominal, &self.wheel_xy[..self.n]);
            if self.avoidance.is_some() {
                let a = l.shaper.avoidance();
                rec.active = a.active && self.sup.state() == SupervisorState::Tracking;
                rec.d_start = a.d_start;
            }
            return (*nominal, rec);
        }
        let tracking = self.sup.state() == SupervisorState::Tracking;
        if let Source::Trajectory(s) = &self.source {
            // A path avoided before the run: the sample is the avoided reference; the record
            // is the avoidance's at the path time the clock has reached.
            let t_ref = self.reference_time().min(s.traj.duration());
            if let Some(st) = s.traj.avoidance_at(t_ref) {
                let mut rec = icr_record(nominal, &self.wheel_xy[..self.n]);
                if tracking {
                    let mut d = [0.0; 3 + MAX_WHEELS];
                    d.copy_from_slice(st.deviation.as_slice());
                    rec = AvoidanceRecord {
                        icr_body: st.icr_body,
                        active: st.active,
                        min_distance: st.min_distance,
                        nearest_wheel: st.nearest_wheel,
                        d_start: st.d_start,
                        deviation: d,
                    };
                }
                return (*nominal, rec);
            }
        }
        match (&mut self.avoidance, self.sup.state()) {
            (Some(a), SupervisorState::Tracking) => {
                let (r, s) = a.step(&self.platform, nominal, dt);
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
            _ => (*nominal, icr_record(nominal, &self.wheel_xy[..self.n])),
        }
    }

    /// What the supervisor sees this cycle, apart from the controller's verdicts; also the
    /// (zero) tracking command of a cycle that does not track.
    fn supervisor_input(
        &mut self,
        fb: &Decoded,
        odo: &crate::estimation::odometry::OdometryOutput,
        nominal: &ReferenceSample,
    ) -> (SupervisorInput, Command) {
        let (meas, age, alive, stale_node) = (&fb.meas, fb.age, fb.alive, fb.stale_node);
        let dt = self.platform.dt();
        let (_, align_err) = alignment_command(&self.platform, meas, nominal);
        // Alignment and the start check need every module's feedback at least once.
        let reported = self.fb[..self.n]
            .iter()
            .zip(&self.platform.wheels)
            .all(|(f, w)| f.steer.is_some() && f.drive.is_some() && (f.leg.is_some() || !w.leg));
        let start_legs = if reported {
            let mut worst = (0usize, meas.wheels[0].leg, nominal.z[3]);
            let r0 = match &self.source {
                Source::Trajectory(s) => s.traj.sample(0.0),
                // Live commands start wherever the platform is.
                Source::Live(_) => *nominal,
            };
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
        // a late answer to the SYNC before). Consecutive cycles are one SYNC apart only when
        // the runtime skipped none between them (a real-time run that fell behind skips
        // cycles and sends no SYNC for them; the modules keep steering meanwhile), so their
        // SYNC times must be one period apart too. Other pairs are not checked.
        let one_period = self
            .prev_sync_t
            .is_some_and(|p| ((self.sync_t - p) / dt).round() == 1.0);
        // The time between the two SYNCs as sent (one period in lockstep; late wake-ups make
        // it shorter or longer in real time).
        let between = match self.prev_sync_sent {
            Some(p) if self.sync_sent > p && (self.sync_sent - p).is_finite() => self.sync_sent - p,
            _ => dt,
        };
        let mut steer_jump = [0.0; MAX_WHEELS];
        for (i, j) in steer_jump.iter_mut().enumerate().take(self.n) {
            let fb = &mut self.fb[i];
            if let (true, Some((a, ar)), Some(c), Some(((pa, par), pk, pc, p_on_time))) =
                (fb.steer_fresh, fb.steer, fb.steer_at.cycle, fb.prev_steer)
            {
                let k = fb.steer_seq.wrapping_sub(pk) & 0x0F;
                if k == 1 && pc + 1 == c && one_period && p_on_time && fb.steer_on_time {
                    let predicted = pa + 0.5 * (par + ar) * between;
                    *j = crate::angle::diff(a, predicted);
                }
            }
            fb.steer_fresh = false;
        }
        let stop_requested = match &self.source {
            Source::Trajectory(_) => self.stop_requested,
            // While following commands the shaper stops the platform (steering held) and the
            // supervisor goes to Stopped once it is at rest; before that, the supervisor stops.
            Source::Live(l) => l.stop_pending && self.sup.state() != SupervisorState::Tracking,
        };
        let mut sup_in = SupervisorInput {
            steer_jump,
            feedback_age: alive,
            data_age: age,
            stale_node,
            alignment_error: if reported { align_err } else { f64::INFINITY },
            start_legs,
            bus_error: self.bus_error,
            bus_off: self.bus_off,
            slip_residual: odo.residual,
            // The leave-one-out fits only once the residual is above the threshold.
            slip_suspect: if odo.residual > self.sup.config().slip_threshold {
                self.odom.slip_suspect(&self.platform)
            } else {
                None
            },
            stop_requested,
            ..Default::default()
        };
        if let (SupervisorState::Stopping, Source::Trajectory(src)) =
            (self.sup.state(), &self.source)
        {
            // Arrival check at the end of a trajectory run: the estimate against the goal.
            // (Live commands have no goal: the service stops where it is told to.)
            let goal = src.traj.sample(src.traj.duration());
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
                    sup_in.device_fault[i] = Some((node, role, fault));
                    self.sup.refine_device_fault(i, node, fault);
                }
                None => {}
            }
        }
        (sup_in, Command::zero(self.n))
    }

    /// The tracking controller's step (Tracking only); sets the controller's verdicts in
    /// `sup_in`.
    fn control(
        &mut self,
        meas: &Measurement,
        odo: &crate::estimation::odometry::OdometryOutput,
        reference: &ReferenceSample,
        sup_in: &mut SupervisorInput,
        dt: f64,
    ) -> Command {
        let t_ref = self.reference_time();
        let input = ControlInput {
            measured_twist: Some(odo.twist_world),
            t: t_ref,
            dt,
            measurement: meas,
            pose: odo.pose,
            reference,
        };
        let dfl = self.cfg.controller == ControllerKind::Dfl;
        match &mut self.source {
            Source::Trajectory(s) => {
                let duration = s.traj.duration();
                if s.terminal_active && dfl && t_ref + dt < duration {
                    // The kinematic controller tracks a reference near rest; once the
                    // reference moves again (faster than 2ε: a trajectory that starts from
                    // rest, or stops and goes on) the DFL takes over, initialised on it.
                    let mut v_ref = 0.0f64;
                    for i in 0..self.n {
                        let u = crate::reference::limits::contact_kinematics(
                            &self.platform,
                            i,
                            reference,
                        )[0];
                        v_ref = v_ref.max(u[0].hypot(u[1]));
                    }
                    if v_ref >= DFL_ENTRY_SPEED {
                        let r = dfl_entry_reference(&self.platform, reference, meas);
                        self.controller.reset(&self.platform, &r);
                        s.terminal_active = false;
                    }
                }
                let mut o = if s.terminal_active {
                    self.kinematic.step(&self.platform, &input)
                } else {
                    self.controller.step(&self.platform, &input)
                };
                if o.finished && !s.terminal_active && dfl && t_ref + dt < duration {
                    // The DFL terminated (|v_W*| < ε) before the reference's end: the
                    // kinematic controller tracks (and stops at rest) until the reference
                    // moves again.
                    s.terminal_active = true;
                    self.kinematic.reset(&self.platform, reference);
                    o = self.kinematic.step(&self.platform, &input);
                }
                // A DFL reports `singular` until the reference wheel moves faster than ε (it
                // cannot leave rest on its own, seed 000 Sect. IV); that is waiting, not a
                // fault. Singular after it has moved is singularity A: a fault.
                if !o.singular {
                    self.controller_moved = true;
                }
                sup_in.controller_singular =
                    (o.singular && self.controller_moved) || !command_finite(&o.command);
                // A controller that finished before the reference's end is at an interior
                // rest of the reference; the run ends at the end: when the controller
                // finishes, or when the platform has settled on the goal (every drive slower
                // than SETTLED_SPEED — what is left is the controller's creep onto the last
                // millimetres, which the stop then ends — and the estimate within SETTLED_*
                // of the reference's end), or at the latest 2 s after the end.
                let settled = t_ref + dt >= duration
                    && (0..self.n).all(|i| {
                        let w = &meas.wheels[i];
                        w.wheel_speed.abs() <= SETTLED_SPEED
                            && w.steer_rate.abs() <= SETTLED_SPEED
                            && (w.leg - reference.z[3 + i]).abs() <= SETTLED_LEG
                    })
                    && (reference.z[0] - odo.pose.x).hypot(reference.z[1] - odo.pose.y)
                        <= SETTLED_POSITION
                    && crate::angle::diff(reference.z[2], odo.pose.theta).abs() <= SETTLED_HEADING;
                sup_in.trajectory_done =
                    (o.finished && t_ref + dt >= duration) || settled || t_ref >= duration + 2.0;
                o.command
            }
            Source::Live(l) => {
                // The DFL tracks while the reference moves; near rest (where it is singular,
                // seed 000 Sect. IV) the kinematic controller holds and stops the platform.
                let mut v_ref = 0.0f64;
                for i in 0..self.n {
                    let u =
                        crate::reference::limits::contact_kinematics(&self.platform, i, reference)
                            [0];
                    v_ref = v_ref.max(u[0].hypot(u[1]));
                }
                let entry = if l.dfl_active {
                    crate::tracking::dfl::EPSILON
                } else {
                    DFL_ENTRY_SPEED
                };
                let want_dfl = dfl && v_ref >= entry;
                if want_dfl && !l.dfl_active {
                    self.controller.reset(&self.platform, reference);
                }
                if !want_dfl && l.dfl_active {
                    self.kinematic.reset(&self.platform, reference);
                }
                l.dfl_active = want_dfl;
                let mut o = if want_dfl {
                    self.controller.step(&self.platform, &input)
                } else {
                    self.kinematic.step(&self.platform, &input)
                };
                if want_dfl && (o.finished || o.singular) {
                    l.dfl_active = false;
                    self.kinematic.reset(&self.platform, reference);
                    o = self.kinematic.step(&self.platform, &input);
                }
                sup_in.controller_singular = !command_finite(&o.command);
                sup_in.trajectory_done = l.stop_pending && l.halt_done;
                o.command
            }
        }
    }

    /// Entering tracking: the reference clock starts now, the controller is initialised on
    /// the reference (perfect matching condition, seed 000 Sect. IV). Returns this cycle's
    /// tracking command.
    fn start_tracking(
        &mut self,
        meas: &Measurement,
        odo: &crate::estimation::odometry::OdometryOutput,
    ) -> Command {
        let dt = self.platform.dt();
        self.controller_moved = false;
        let period_now = self.periods;
        let dfl = self.cfg.controller == ControllerKind::Dfl;
        let platform = &self.platform;
        let r0 = match &mut self.source {
            Source::Trajectory(s) => {
                s.track_start_period = Some(period_now);
                let r0 = s.traj.sample(0.0);
                // A reference that starts from rest (slower than the DFL's ε, which it
                // cannot leave on its own) starts with the kinematic controller; the DFL
                // takes over once the reference moves (seed 000's persistence start, ε,
                // starts with the DFL).
                let mut v0 = 0.0f64;
                for i in 0..platform.n().min(MAX_WHEELS) {
                    let u = crate::reference::limits::contact_kinematics(platform, i, &r0)[0];
                    v0 = v0.max(u[0].hypot(u[1]));
                }
                s.terminal_active = dfl && v0 < crate::tracking::dfl::EPSILON;
                r0
            }
            Source::Live(l) => {
                l.dfl_active = false;
                l.last_valid = self.now;
                l.shaper.hold_sample()
            }
        };
        self.controller.reset(&self.platform, &r0);
        self.kinematic.reset(&self.platform, &r0);
        let input = ControlInput {
            measured_twist: Some(odo.twist_world),
            t: 0.0,
            dt,
            measurement: meas,
            pose: odo.pose,
            reference: &r0,
        };
        match &self.source {
            Source::Trajectory(s) if !s.terminal_active => {
                self.controller.step(&self.platform, &input).command
            }
            _ => self.kinematic.step(&self.platform, &input).command,
        }
    }

    /// The command of the supervisor's mode; tracking and alignment commands pass the output
    /// guard ([`crate::reference::limits::guard_command`]): every wheel within its speed and
    /// acceleration limits, the change scaled as a whole. A controlled stop of the supervisor
    /// (faults, operator stop outside tracking) ramps the wheel speeds down at the wheel
    /// acceleration limit and holds the steering at once.
    fn command_for(
        &mut self,
        mode: Mode,
        meas: &Measurement,
        nominal: &ReferenceSample,
        reference: &ReferenceSample,
        track_cmd: Command,
    ) -> (Command, bool, bool, &'static str) {
        let dt = self.platform.dt();
        let settling = matches!(
            self.sup.state(),
            SupervisorState::Stopped | SupervisorState::Fault
        ) || (self.sup.state() == SupervisorState::Idle && self.stop_requested);
        // With synchronous RPDOs (CiA 402) a controlword acts at the next SYNC: the drives are
        // told to disable for as many cycles before the end as the link needs.
        let lead = self.link.disable_lead_cycles();
        let last_cycle =
            settling && self.may_end() && self.done_cycles + lead >= self.cfg.linger_cycles;
        let guard =
            |c: Command, last: &Command| guard_command(&self.platform.limits, last, &c, dt).0;
        let (cmd, enable, brake, mode_name) = match mode {
            // Drives are disabled only once every command is at zero: a steering rate still
            // winding down (a fault at rest) ramps out within its limit first.
            Mode::Disabled if self.last_cmd != Command::zero(self.n) => (
                halt_command(&self.platform, &self.last_cmd, dt),
                true,
                false,
                "decelerate",
            ),
            Mode::Disabled => (Command::zero(self.n), false, false, "disabled"),
            Mode::Align => {
                let (align_cmd, _) = alignment_command(&self.platform, meas, nominal);
                (guard(align_cmd, &self.last_cmd), true, false, "align")
            }
            Mode::Track if self.halting() => {
                let c = halt_command(&self.platform, &self.last_cmd, dt);
                if let Source::Live(l) = &mut self.source {
                    if c == Command::zero(self.n) {
                        l.halt_done = true;
                        l.dfl_active = false;
                    }
                }
                (c, true, false, "halt")
            }
            Mode::Track => {
                if command_finite(&track_cmd) {
                    let lead = lag_compensation(&self.platform, reference, meas, track_cmd);
                    (guard(lead, &self.last_cmd), true, false, "track")
                } else {
                    (
                        halt_command(&self.platform, &self.last_cmd, dt),
                        true,
                        false,
                        "decelerate",
                    )
                }
            }
            Mode::Decelerate => (
                halt_command(&self.platform, &self.last_cmd, dt),
                true,
                false,
                "decelerate",
            ),
            // At rest: whatever steering is still in motion winds down within its limit.
            Mode::Hold => (
                halt_command(&self.platform, &self.last_cmd, dt),
                true,
                true,
                "hold",
            ),
        };
        let at_rest_now = command_at_rest(&cmd, self.sup.config().rest_speed);
        if last_cycle && at_rest_now {
            (cmd, false, brake, "disable")
        } else {
            (cmd, enable, brake, mode_name)
        }
    }

    /// True while a halt (command timeout, stop request) brings the platform to rest under
    /// live commands.
    fn halting(&self) -> bool {
        matches!(&self.source, Source::Live(l) if l.shaper.halted())
    }

    /// Setpoints of this cycle into `out`; returns how many frames.
    fn encode(
        &mut self,
        t: f64,
        cmd: &Command,
        enable: bool,
        brake: bool,
        out: &mut [FrameBuf],
    ) -> usize {
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
        self.sup.note_command(cmd, &[enable && !brake; MAX_WHEELS]);
        for o in out.iter_mut() {
            o.clear();
        }
        self.link.finish_cycle(t, &self.setpoints[..self.n], out);
        let settled = matches!(
            self.sup.state(),
            SupervisorState::Stopped | SupervisorState::Fault
        ) && command_at_rest(cmd, self.sup.config().rest_speed);
        let idle_stop = self.sup.state() == SupervisorState::Idle && self.stop_requested;
        // The very last cycle of a finished run, drives disabled: hand the devices back.
        if (settled || idle_stop)
            && self.may_end()
            && self.done_cycles + 1 >= self.cfg.linger_cycles
        {
            self.link.release(out);
        }
        self.record_sent(t, out);
        out.iter().map(FrameBuf::len).sum()
    }

    /// Fills the state port's value of this cycle.
    fn publish_state(
        &mut self,
        t: f64,
        meas: &Measurement,
        odo: &crate::estimation::odometry::OdometryOutput,
        alive: [u32; MAX_WHEELS],
        dt: f64,
    ) {
        // Bus load over the last second, per bus.
        let window = self.bus_bits[0].len();
        for b in 0..MAX_BUSES {
            let bits = self.bits_this_cycle[b];
            let slot = &mut self.bus_bits[b][self.bus_bits_at];
            self.bus_bits_sum[b] = self.bus_bits_sum[b] - u64::from(*slot) + u64::from(bits);
            *slot = bits;
        }
        self.bus_bits_at = (self.bus_bits_at + 1) % window;
        let window_s = window as f64 * dt;
        let s = &mut self.state;
        s.cycle = self.cycle;
        s.t = t;
        s.log_time_ns = self.record.log_time_ns;
        s.n = self.n;
        s.odometry = OdometryState {
            pose: odo.pose,
            twist: odo.twist_body,
            pose_covariance: odo.pose_covariance,
            twist_covariance: odo.twist_covariance,
        };
        for i in 0..self.n {
            let w = meas.wheels[i];
            let speed = if w.wheel_speed.is_finite() {
                w.wheel_speed
            } else {
                0.0
            };
            self.wheel_angle[i] += 0.5 * (self.prev_wheel_speed[i] + speed) * dt;
            self.prev_wheel_speed[i] = speed;
            s.joints[i] = JointState {
                steer_angle: w.steer_angle,
                steer_rate: w.steer_rate,
                wheel_angle: self.wheel_angle[i],
                wheel_speed: w.wheel_speed,
                leg: w.leg,
                leg_rate: w.leg_rate,
                no_leg: !self.platform.wheels[i].leg,
            };
            let d = &mut self.diag[i];
            let watchdog = match self.link.wheel_fault(i) {
                Some(WheelFault::Module { code, .. }) => code == FAULT_WATCHDOG,
                Some(WheelFault::Device { fault, .. }) => matches!(
                    fault,
                    DeviceFault::MasterSilent { .. }
                        | DeviceFault::Emcy {
                            code: 0x8100..=0x81FF | 0x8250,
                            ..
                        }
                ),
                None => false,
            };
            if watchdog && !d.in_watchdog {
                d.counters.watchdog_trips += 1;
            }
            if let Some((m, k)) = self.link.master_of_wheel(i) {
                emcy_diagnostics(m, k, &mut d.counters);
            }
            d.in_watchdog = watchdog;
            d.counters.age_cycles = alive[i];
            d.counters.state = self.record.module_state[i];
            s.diagnostics.modules[i] = d.counters;
        }
        for b in 0..MAX_BUSES {
            s.diagnostics.bus_loads[b] =
                self.bus_bits_sum[b] as f64 / (self.cfg.bitrate as f64 * window_s);
        }
        s.diagnostics.bus_load = s.diagnostics.bus_loads[0].max(s.diagnostics.bus_loads[1]);
        s.state = self.sup.state();
        s.reason = self.sup.reason();
        match &self.source {
            Source::Live(l) => {
                s.commands = l.stats;
                s.shaping = l.shaper.status();
            }
            Source::Trajectory(src) => {
                // The time scaling's clock: how fast the trajectory runs now, and why.
                let status = match (src.track_start_period, self.sup.state()) {
                    (Some(c), SupervisorState::Tracking) => src
                        .traj
                        .time_scale(self.periods.saturating_sub(c) as f64 * dt),
                    _ => None,
                };
                s.shaping = ShapingState {
                    commanded: Default::default(),
                    scale: status.map_or(1.0, |x| x.scale),
                    limiting: status.map_or(Limiting::None, |x| x.limiting),
                };
            }
        }
        // The record carries the command counters, the shaping and the whole state too.
        self.record.commands = s.commands;
        self.record.shaping = s.shaping;
        self.record.base = *s;
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

/// The reference the DFL is initialised on when it takes over from the kinematic
/// controller mid-trajectory: its steering reference gives every wheel the direction of its
/// reference contact velocity on the branch (±π) nearest the wheel's measured angle (the
/// steering reference's own angle where the reference has one), so the compensator's
/// reference-wheel speed η_W is the signed speed along the wheel as it stands (seed 000's
/// perfect matching, [`DflController::reset`]).
fn dfl_entry_reference(
    p: &Platform,
    reference: &ReferenceSample,
    meas: &Measurement,
) -> ReferenceSample {
    let mut r = *reference;
    if r.steer.valid {
        return r;
    }
    r.steer.valid = true;
    for i in 0..p.n().min(meas.n).min(MAX_WHEELS) {
        let u = crate::reference::limits::contact_kinematics(p, i, reference)[0];
        let phi = meas.wheels[i].steer_angle;
        let a = u[1].atan2(u[0]);
        r.steer.angle[i] = if u[0] == 0.0 && u[1] == 0.0 {
            phi
        } else {
            a + (crate::angle::diff(phi, a) / std::f64::consts::PI).round() * std::f64::consts::PI
        };
        r.steer.rate[i] = 0.0;
        r.steer.accel[i] = 0.0;
    }
    r
}

/// The drives' lag compensation ([`crate::model::platform::Drives`]): adds τ × the reference's
/// acceleration to each wheel's command: the rolling acceleration along the wheel's measured
/// heading, (u̇*·h)/r, and the steering acceleration φ̈* (or the steering reference's, for a
/// wheel steered by it).
///
/// An off-centred wheel is not steered by the direction of its axis' velocity but by the
/// caster law φ̇ = (u·h⊥)/d − θ̇ at its measured angle (controller 2, point 8), and it rolls
/// at u·h along its own heading h, which turns with it (ḣ = φ̇ h⊥, ḣ⊥ = −φ̇ h). So its
/// accelerations are the law's derivatives: φ̈ = (u̇·h⊥ − φ̇ (u·h))/d − θ̈ and
/// d(u·h)/dt = u̇·h + φ̇ (u·h⊥). The direction's φ̈* it had before is zero on a straight
/// start, where a caster swings hardest, and u̇·h alone misses the roll a swing builds up:
/// the MPO-700-like live session's worst moment, two casters swinging ~130° as the base
/// starts backwards, went from 4.26 to 1.80 mm (native) and from 4.53 to 2.06 mm (CiA 402)
/// (3.55 / 3.81 mm with the steering term alone). A leading caster (held near its leading
/// angle by feedback) is at the law's equilibrium there, where the two agree.
fn lag_compensation(
    p: &Platform,
    reference: &ReferenceSample,
    meas: &Measurement,
    mut cmd: Command,
) -> Command {
    let (tw, ts) = (p.drives.wheel_time_constant, p.drives.steer_time_constant);
    if tw == 0.0 && ts == 0.0 {
        return cmd;
    }
    let held = crate::tracking::dfl::held_wheels(p, reference);
    for i in 0..cmd.n.min(p.n()).min(MAX_WHEELS) {
        let phi = meas.wheels[i].steer_angle;
        let [u, du, _] = crate::reference::limits::contact_kinematics(p, i, reference);
        let (a, sa) = if p.wheels[i].off_centred() {
            // The caster law (`caster_inverse`) and its derivative: projected on (h, h⊥),
            // u̇ gives u̇·h and (u̇·h⊥)/d − θ̈; the turning of h adds the rest.
            use crate::model::kinematics::caster_inverse;
            let d = p.wheels[i].caster_offset;
            let (along, rate) = caster_inverse(u, phi, reference.dz[2], d);
            let (dalong, drate) = caster_inverse(du, phi, reference.ddz[2], d);
            let across = d * (rate + reference.dz[2]);
            // d(u·h)/dt = u̇·h + φ̇ (u·h⊥); φ̈ = (u̇·h⊥ − φ̇ (u·h))/d − θ̈.
            (
                (dalong + rate * across) / p.wheel_radius,
                drate - rate * along / d,
            )
        } else {
            let a = (du[0] * phi.cos() + du[1] * phi.sin()) / p.wheel_radius;
            let sa = if held[i] {
                reference.steer.accel[i]
            } else {
                crate::reference::limits::wheel_demand(p, i, reference).steer_accel
            };
            (a, sa)
        };
        let w = &mut cmd.wheels[i];
        if a.is_finite() {
            w.wheel_speed += tw * a;
        }
        if sa.is_finite() {
            w.steer_rate += ts * sa;
        }
    }
    cmd
}

/// CiA 402: the EMCY counters and the newest [`crate::service::ports::EMCY_KEPT`] EMCYs of wheel
/// `wheel`'s devices (no allocation).
fn emcy_diagnostics(
    m: &rollbase_driver::canopen::master::Master,
    wheel: usize,
    out: &mut crate::service::ports::ModuleDiagnostics,
) {
    use crate::service::ports::{EmcyEntry, EMCY_KEPT};
    out.emcy_informational = 0;
    out.emcy_faults = 0;
    out.emcy = [EmcyEntry::default(); EMCY_KEPT];
    for d in m.devices().iter().filter(|d| d.wheel == wheel) {
        out.emcy_informational = out.emcy_informational.saturating_add(d.emcy_informational);
        out.emcy_faults = out.emcy_faults.saturating_add(d.emcy_faults);
        for (t, e) in d.emcy_history() {
            let entry = EmcyEntry {
                node: d.node,
                code: e.code,
                register: e.register,
                at_ms: (t.max(0.0) * 1e3) as u64,
            };
            // Insert by time, newest first; the oldest falls off the end.
            if let Some(k) = out
                .emcy
                .iter()
                .position(|x| x.node == 0 || x.at_ms < entry.at_ms)
            {
                out.emcy.copy_within(k..EMCY_KEPT - 1, k + 1);
                out.emcy[k] = entry;
            }
        }
    }
}

/// The odometry's encoder resolution for the platform's wire profile: the native protocol's
/// steps, or (CiA 402) one velocity unit of the rolling drive and one increment of the
/// steering drive's position.
fn encoder_resolution(p: &Platform) -> EncoderResolution {
    match p.protocol {
        crate::model::platform::Protocol::Native => EncoderResolution::default(),
        crate::model::platform::Protocol::Cia402 => {
            let c = p.cia402();
            let ws = c.drive.velocity_resolution().abs();
            let sa = (std::f64::consts::TAU / c.steer.increments_per_joint_rev()).abs();
            EncoderResolution {
                wheel_speed: if ws.is_finite() && ws > 0.0 { ws } else { 1e-3 },
                steer_angle: if sa.is_finite() && sa > 0.0 { sa } else { 1e-4 },
            }
        }
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
    fn a_caster_is_lag_compensated_with_the_caster_laws_accelerations() {
        let p = Platform::mpo700();
        let ts = p.drives.steer_time_constant;
        let d = p.wheels[0].caster_offset;
        // A straight start along +x at 0.1 m/s, accelerating at 0.5 m/s²: the direction of
        // every axis' velocity is constant (φ̈* = 0), but a caster across its travel swings
        // at −v/d and speeds up at −a/d.
        let mut r = ReferenceSample {
            n: p.n(),
            ..ReferenceSample::default()
        };
        r.dz[0] = 0.1;
        r.ddz[0] = 0.5;
        for i in 0..p.n() {
            r.z[3 + i] = p.wheels[i].lambda_nominal;
        }
        let mut m = Measurement {
            n: p.n(),
            ..Measurement::default()
        };
        m.wheels[0].steer_angle = std::f64::consts::FRAC_PI_2; // across its travel
        m.wheels[1].steer_angle = 0.0; // trailing, along its travel
        let out = lag_compensation(&p, &r, &m, Command::zero(p.n()));
        let want = ts * (-0.5 / d);
        assert!(
            (out.wheels[0].steer_rate - want).abs() < 1e-9,
            "across: {} rad/s, want {want}",
            out.wheels[0].steer_rate
        );
        assert!(
            out.wheels[1].steer_rate.abs() < 1e-12,
            "a trailing caster along its travel does not swing: {}",
            out.wheels[1].steer_rate
        );
        // Its rolling speed u·h grows as it swings: φ̇ (u·h⊥) = (−v/d)(−v) = v²/d, although
        // u̇·h = 0 across; along its travel the rolling acceleration is the base's.
        let (tw, r) = (p.drives.wheel_time_constant, p.wheel_radius);
        let want = tw * (0.1 * 0.1 / d) / r;
        assert!(
            (out.wheels[0].wheel_speed - want).abs() < 1e-9,
            "across: {} rad/s, want {want}",
            out.wheels[0].wheel_speed
        );
        let want = tw * 0.5 / r;
        assert!(
            (out.wheels[1].wheel_speed - want).abs() < 1e-9,
            "along: {} rad/s, want {want}",
            out.wheels[1].wheel_speed
        );
    }

    #[test]
    fn an_infeasible_tiny_limit_is_printed_readably() {
        let mut p = Platform::justin();
        p.limits.leg_speed = 1e-300;
        let traj =
            crate::runtime::scenario::trajectory(crate::runtime::scenario::Scenario::Seed000, &p)
                .unwrap();
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
