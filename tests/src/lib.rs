//! Shared harness for rollbase's end-to-end tests: runs a scenario through the full frame
//! path (encode → virtual bus → simulated modules → virtual bus → decode) on virtual time.
#![deny(missing_docs)]

pub mod alloc_count;
pub mod campaign;
pub mod flow;

use rollbase_control::runtime::record::CycleRecord;
use rollbase_control::runtime::scenario::{self, Scenario};
use rollbase_control::runtime::{
    run_lockstep, ControllerKind, CycleCore, LockstepReport, RunSummary, RuntimeConfig,
    VirtualLockstepBus,
};
use rollbase_control::{Platform, Protocol};
use rollbase_driver::fault::FaultModel;
use rollbase_vcan_sim::{FaultSchedule, PlantConfig, SimConfig, Simulator};

/// What to run.
#[derive(Clone, Debug)]
pub struct RunOptions {
    /// Scenario.
    pub scenario: Scenario,
    /// Runtime configuration (controller, avoidance, supervisor).
    pub runtime: RuntimeConfig,
    /// Simulator seed (noise, faults).
    pub seed: u64,
    /// Simulator plant parameters.
    pub plant: PlantConfig,
    /// Simulator fault schedule.
    pub faults: FaultSchedule,
    /// Faults of the virtual bus medium itself.
    pub bus_faults: FaultModel,
    /// Operator stop (Ctrl-C) at this cycle.
    pub stop_at_cycle: Option<u64>,
    /// Extra cycles beyond the trajectory's duration before giving up.
    pub slack_s: f64,
    /// Start the simulated platform at the trajectory's initial pose and legs (true) or at
    /// the simulator's nominal configuration (false: legs at their nominal extension).
    pub start_at_reference: bool,
    /// The platform the simulator builds (`None` = the controller's). A different one models
    /// a mismatch between the description and the machine (e.g. an end stop short of
    /// `lambda_max`).
    pub sim_platform: Option<Platform>,
    /// Waypoints of a quintic-spline trajectory used instead of the scenario's.
    pub waypoints: Option<Vec<rollbase_control::reference::trajectory::Waypoint>>,
    /// Waypoints whose times may be left open (time-scaled by the runtime), used instead of
    /// the scenario's and of `waypoints`.
    pub waypoint_specs: Option<Vec<rollbase_control::reference::trajectory::WaypointSpec>>,
    /// Give up after this many seconds of platform time (`None`: the trajectory's duration
    /// plus `slack_s`, which never ends for a plan that does not).
    pub max_seconds: Option<f64>,
    /// Wire profile of the controller and the simulated devices.
    pub profile: Protocol,
    /// Serialize the simulator's frames on a bus of this bit rate (`None`: every frame
    /// arrives at its send time, as the native tests always ran).
    pub sim_bitrate: Option<u32>,
    /// The controller's platform (`None` = [`Platform::justin`] with `profile`): e.g. a
    /// `[cia402]` table with a homing method.
    pub platform: Option<Platform>,
    /// How the simulated CiA 402 devices behave (the real drives' twin by default).
    pub twin: rollbase_vcan_sim::canopen::TwinConfig,
    /// Steering angles of the simulated platform at power-on (`None`: the simulator's).
    pub initial_steer: Option<[f64; rollbase_control::MAX_WHEELS]>,
}

impl RunOptions {
    /// The scenario with its default runtime settings, the simulator's defaults and seed 1.
    pub fn new(scenario: Scenario) -> Self {
        Self {
            scenario,
            runtime: scenario::runtime_config(scenario),
            seed: 1,
            plant: PlantConfig::default(),
            faults: FaultSchedule::default(),
            bus_faults: FaultModel::none(),
            stop_at_cycle: None,
            slack_s: 15.0,
            start_at_reference: true,
            sim_platform: None,
            waypoints: None,
            waypoint_specs: None,
            max_seconds: None,
            profile: Protocol::Native,
            sim_bitrate: None,
            platform: None,
            twin: Default::default(),
            initial_steer: None,
        }
    }

    /// Same, on the CiA 402 profile (CANopen drives and encoders, default `[cia402]`), with
    /// the simulator's frames serialized on a 1 Mbit/s bus.
    pub fn cia402(mut self) -> Self {
        self.profile = Protocol::Cia402;
        self.sim_bitrate = Some(1_000_000);
        self
    }

    /// Same, with the given controller.
    pub fn with_controller(mut self, c: ControllerKind) -> Self {
        self.runtime.controller = c;
        self
    }
}

/// What a run produced.
pub struct RunOutcome {
    /// Every cycle's record.
    pub records: Vec<CycleRecord>,
    /// Summary figures.
    pub summary: RunSummary,
    /// Lockstep report.
    pub report: LockstepReport,
    /// The platform.
    pub platform: Platform,
    /// CiA 402 profile: every simulated drive's node and its state [`AFTER_END`] after the
    /// controller's last cycle (empty for the native profile).
    pub final_drive_states: Vec<(u8, rollbase_driver::canopen::ds402::State)>,
    /// The frames the simulated devices sent in the [`AFTER_END`] after the controller's
    /// last cycle (nobody listening): what a controller that exits leaves on the bus.
    pub after_end: Vec<rollbase_driver::frame::CanFrame>,
    /// The state port's value after the last cycle (live runs).
    pub final_state: Option<rollbase_control::service::ports::BaseState>,
    /// CiA 402: the optional plan steps each device did not have, as (node, index, sub),
    /// as the master reported them at the end.
    pub final_skipped: Vec<(u8, u16, u8)>,
    /// The simulator's true steering angles after the last cycle (rad).
    pub final_truth_steer: [f64; rollbase_control::MAX_WHEELS],
    /// The timing of a time-scaled trajectory as the core planned it (`None` for live
    /// commands or an unscaled trajectory).
    pub timing: Option<rollbase_control::reference::status::Timing>,
}

/// Simulated time the devices run on after the controller's last cycle.
pub const AFTER_END: std::time::Duration = std::time::Duration::from_millis(500);

/// Builds the controller core, the simulator and the virtual bus for `opts` (the core is not
/// armed yet); also returns the trajectory's duration (s).
pub fn build(opts: &RunOptions) -> Result<(CycleCore, Simulator, VirtualLockstepBus, f64), String> {
    let mut platform = opts.platform.clone().unwrap_or_else(Platform::justin);
    platform.protocol = opts.profile;
    let traj: Box<dyn rollbase_control::reference::trajectory::Trajectory> =
        match (&opts.waypoint_specs, &opts.waypoints) {
            (Some(w), _) => Box::new(
                rollbase_control::reference::trajectory::QuinticSpline::from_specs(&platform, w)
                    .map_err(|e| e.to_string())?,
            ),
            (None, Some(w)) => Box::new(
                rollbase_control::reference::trajectory::QuinticSpline::new(&platform, w)
                    .map_err(|e| e.to_string())?,
            ),
            (None, None) => {
                scenario::trajectory(opts.scenario, &platform).map_err(|e| e.to_string())?
            }
        };
    let duration = traj.duration();
    let r0 = traj.sample(0.0);
    let core =
        CycleCore::new(platform.clone(), traj, opts.runtime.clone()).map_err(|e| e.to_string())?;
    let mut sim_p = opts.sim_platform.clone().unwrap_or(platform);
    sim_p.protocol = opts.profile;
    let mut initial = opts
        .start_at_reference
        .then(|| rollbase_vcan_sim::InitialState::from_reference(&sim_p, &r0));
    if let Some(steer) = opts.initial_steer {
        let s = initial.get_or_insert_with(|| rollbase_vcan_sim::InitialState::nominal(&sim_p));
        s.steer = steer;
    }
    let sim = Simulator::with_config(
        &sim_p,
        SimConfig {
            plant: opts.plant.clone(),
            faults: opts.faults.clone(),
            initial,
            seed: opts.seed,
            bitrate: opts.sim_bitrate,
            twin: opts.twin.clone(),
            ..SimConfig::default()
        },
    )
    .map_err(|e| e.to_string())?;
    let bus = VirtualLockstepBus::new(opts.bus_faults, opts.seed ^ 0x5EED);
    Ok((core, sim, bus, duration))
}

/// Runs the options in lockstep; `sink` sees every record too (e.g. to write MCAP).
pub fn run_with(opts: &RunOptions, sink: &mut dyn FnMut(&CycleRecord, &[[f64; 2]])) -> RunOutcome {
    let (mut core, mut sim, mut bus, duration) = build(opts).expect("valid setup");
    let platform = core.platform().clone();
    let timing = core.trajectory_timing();
    let seconds = opts.max_seconds.unwrap_or(duration + opts.slack_s);
    let max_cycles = (seconds * platform.cycle_hz) as u64;
    let mut records = Vec::with_capacity(max_cycles.min(1 << 14) as usize);
    let mut summary = RunSummary::new(opts.scenario.name());
    let report = run_lockstep(
        &mut core,
        &mut bus,
        &mut sim,
        max_cycles,
        opts.stop_at_cycle,
        &mut |r, w| {
            summary.update(r);
            records.push(*r);
            sink(r, w);
        },
    )
    .expect("the test platform's buses, one lockstep bus each");
    let truth_steer = sim.truth().steer;
    let end = sim.now();
    sim.advance_to(end + AFTER_END);
    let mut after_end = Vec::new();
    sim.drain_tx(&mut |t, f| {
        if t > end {
            after_end.push(f)
        }
    });
    let final_drive_states = sim
        .devices()
        .iter()
        .filter(|d| d.role() != rollbase_driver::canopen::config::Role::Leg)
        .map(|d| (d.node(), d.state402()))
        .collect();
    RunOutcome {
        records,
        summary,
        report,
        platform,
        final_drive_states,
        after_end,
        final_state: None,
        final_skipped: skipped_of(&core),
        final_truth_steer: truth_steer,
        timing,
    }
}

/// The optional plan steps the CiA 402 master skipped, per device (node, index, sub).
pub fn skipped_of(core: &CycleCore) -> Vec<(u8, u16, u8)> {
    let buses = core.link();
    (0..buses.count())
        .filter_map(|b| buses.link(b).and_then(|l| l.master()))
        .flat_map(|m| {
            m.devices()
                .iter()
                .flat_map(|d| d.skipped().iter().map(move |(i, s)| (d.node, *i, *s)))
        })
        .collect()
}

/// Runs the options in lockstep.
pub fn run(opts: &RunOptions) -> RunOutcome {
    run_with(opts, &mut |_, _| {})
}

/// The tracking bounds every closed-loop acceptance test holds a run to (seed 000, live
/// commands, time-scaled trajectories): it ends in Stopped, and its errors against the
/// simulator's ground truth, relative to the reference the controller followed, stay below
/// 5 mm (position), 0.5° (heading) and 2 mm (legs). `what` names the run in the messages.
pub fn assert_tracking_bounds(s: &RunSummary, what: &str) {
    assert_eq!(
        s.final_state, "stopped",
        "{what}: the run must end in Stopped: {:?}",
        s.fault_reason
    );
    assert!(
        s.against_truth,
        "{what}: errors are measured against the simulator's ground truth"
    );
    assert!(
        s.max_position_error_m < 0.005,
        "{what}: max position error {} mm",
        s.max_position_error_m * 1e3
    );
    assert!(
        s.max_heading_error_rad < 0.5f64.to_radians(),
        "{what}: max heading error {}°",
        s.max_heading_error_rad.to_degrees()
    );
    assert!(
        s.max_leg_error_m < 0.002,
        "{what}: max leg error {} mm",
        s.max_leg_error_m * 1e3
    );
}

/// The seed-000 acceptance bounds, one definition for every wire profile: the run ends in
/// Stopped, errors against the simulator's ground truth stay below 5 mm (position), 0.5°
/// (heading) and 2 mm (legs), no frame is rejected on a clean bus, the measured wheel speeds
/// and steering rates stay within the platform's limits, and the true final pose is within
/// 5 mm and 0.5° of the goal (4.5 m, 4.5 m, 2π).
pub fn assert_seed000_bounds(out: &RunOutcome) {
    let s = &out.summary;
    assert_tracking_bounds(s, "seed 000");
    assert_eq!(s.rejected_frames, 0, "a clean bus rejects nothing");
    let p = &out.platform;
    assert!(s.max_wheel_speed_rad_s <= p.limits.wheel_speed + 1e-9);
    assert!(s.max_steer_rate_rad_s <= p.limits.steer_rate + 1e-9);
    let last = out.records.last().expect("records");
    let (pose, _) = last.truth.expect("simulated truth");
    let to_goal = (pose.x - 4.5).hypot(pose.y - 4.5);
    assert!(to_goal < 0.005, "final distance to the goal {to_goal} m");
    assert!((pose.theta - std::f64::consts::TAU).abs() < 0.5f64.to_radians());
}

/// Asserts the supervisor's controlled stop from the record of cycle `from` on: every
/// commanded wheel speed changes by at most the wheel acceleration limit per cycle, every
/// steering rate winds down to zero within the steering acceleration limit (it never grows:
/// the steering is held once it is at rest), and the state stays Fault (latched).
pub fn assert_controlled_stop_from(out: &RunOutcome, from: u64) {
    let p = &out.platform;
    let after: Vec<_> = out.records.iter().filter(|r| r.cycle >= from).collect();
    assert!(after.len() > 1, "no records after cycle {from}");
    for pair in after.windows(2) {
        for i in 0..pair[1].n {
            let dv = (pair[1].command.wheels[i].wheel_speed
                - pair[0].command.wheels[i].wheel_speed)
                .abs();
            assert!(
                dv <= p.limits.wheel_accel * p.dt() + 1e-9,
                "cycle {}: wheel {i} speed step {dv} rad/s",
                pair[1].cycle
            );
            let (s0, s1) = (
                pair[0].command.wheels[i].steer_rate,
                pair[1].command.wheels[i].steer_rate,
            );
            assert!(
                s1.abs() <= s0.abs()
                    && (s1 - s0).abs() <= p.limits.steer_accel * p.dt() * (1.0 + 1e-9),
                "cycle {}: wheel {i} steering rate {s0} → {s1}: not winding down within its limit",
                pair[1].cycle
            );
        }
        assert_eq!(
            pair[1].state,
            rollbase_control::supervisor::SupervisorState::Fault,
            "cycle {}: fault not latched",
            pair[1].cycle
        );
    }
}

/// A live-command (base service) run in lockstep.
#[derive(Clone, Debug)]
pub struct LiveOptions {
    /// Runtime configuration (controller, avoidance, supervisor, shaper).
    pub runtime: RuntimeConfig,
    /// Simulator seed.
    pub seed: u64,
    /// Simulator plant parameters (the defaults: noise, motor lag, encoder latency).
    pub plant: PlantConfig,
    /// Wire profile.
    pub profile: Protocol,
    /// Where the simulated platform starts (`None`: at the origin, legs nominal, wheels at 0).
    pub initial: Option<rollbase_vcan_sim::InitialState>,
    /// Give up after this many seconds of platform time.
    pub max_seconds: f64,
    /// The platform (`None`: [`Platform::justin`] with `profile`).
    pub platform: Option<Platform>,
    /// Faults of the simulated devices.
    pub faults: FaultSchedule,
    /// How the simulated CiA 402 devices behave.
    pub twin: rollbase_vcan_sim::canopen::TwinConfig,
}

impl Default for LiveOptions {
    fn default() -> Self {
        Self {
            runtime: RuntimeConfig::default(),
            seed: 1,
            plant: PlantConfig::default(),
            profile: Protocol::Native,
            initial: None,
            max_seconds: 120.0,
            platform: None,
            faults: FaultSchedule::default(),
            twin: Default::default(),
        }
    }
}

/// The live core (not armed yet), the simulator and the virtual bus of `opts`.
pub fn build_live(opts: &LiveOptions) -> (CycleCore, Simulator, VirtualLockstepBus) {
    let mut platform = opts.platform.clone().unwrap_or_else(Platform::justin);
    platform.protocol = opts.profile;
    let rt = opts.runtime.clone();
    let core = CycleCore::new_live(platform.clone(), rt).expect("valid");
    let sim = Simulator::with_config(
        &platform,
        SimConfig {
            plant: opts.plant.clone(),
            initial: opts.initial,
            seed: opts.seed,
            bitrate: (opts.profile == Protocol::Cia402).then_some(1_000_000),
            faults: opts.faults.clone(),
            twin: opts.twin.clone(),
            ..SimConfig::default()
        },
    )
    .expect("valid simulator");
    let bus = VirtualLockstepBus::new(FaultModel::none(), opts.seed ^ 0x5EED);
    (core, sim, bus)
}

/// Runs the base service in lockstep through the full frame path with the given command
/// events (times from the moment the driver is ready), on as many virtual buses as the
/// platform has; the summary's errors are against the simulator's truth, relative to the
/// shaped reference.
pub fn run_live(
    opts: &LiveOptions,
    commands: &[rollbase_control::service::ports::CommandEvent],
) -> RunOutcome {
    use rollbase_control::runtime::LockstepBus;
    let (mut core, mut sim, bus) = build_live(opts);
    let platform = core.platform().clone();
    // One medium per platform bus (the first as `build_live` made it).
    let mut media: Vec<VirtualLockstepBus> =
        std::iter::once(bus)
            .chain((1..core.buses().max(1) as u64).map(|b| {
                VirtualLockstepBus::new(FaultModel::none(), opts.seed ^ 0x5EED ^ (b << 32))
            }))
            .collect();
    let mut buses: Vec<&mut dyn LockstepBus> = media
        .iter_mut()
        .map(|m| m as &mut dyn LockstepBus)
        .collect();
    let max_cycles = (opts.max_seconds * platform.cycle_hz) as u64;
    let mut records = Vec::with_capacity(max_cycles as usize);
    let mut summary = RunSummary::new("live");
    let report = rollbase_control::runtime::run_lockstep_buses(
        &mut core,
        &mut buses,
        &mut sim,
        commands,
        max_cycles,
        &mut |_| false,
        &mut |r, _| {
            summary.update(r);
            records.push(*r);
        },
    )
    .expect("the test platform's buses, one lockstep bus each");
    RunOutcome {
        records,
        summary,
        report,
        platform,
        final_drive_states: Vec::new(),
        after_end: Vec::new(),
        final_state: Some(*core.base_state()),
        final_skipped: skipped_of(&core),
        final_truth_steer: sim.truth().steer,
        timing: None,
    }
}

/// A twist command event at `t` (s after the driver is ready).
pub fn twist_at(
    t: f64,
    vx: f64,
    vy: f64,
    omega: f64,
) -> rollbase_control::service::ports::CommandEvent {
    use rollbase_control::service::ports::{CommandEvent, CommandKind, MotionCommand};
    CommandEvent {
        t,
        kind: CommandKind::Motion(MotionCommand {
            twist: rollbase_control::types::Twist { vx, vy, omega },
            legs: None,
        }),
    }
}

/// The live session of the example-platform tests: forwards (0.3 m/s), sideways (0.25 m/s),
/// a turn on the spot (0.6 rad/s), an arc (0.2 m/s, 0.1 m/s, 0.3 rad/s), backwards (0.2 m/s),
/// 3 s each with the twist repeated every 0.3 s; the leg commands `legs` ((time, targets))
/// sorted in; then five zero twists 0.3 s apart and the end of the stream 3 s after the last
/// step.
pub fn five_step_session(
    legs: &[(f64, &[f64])],
) -> Vec<rollbase_control::service::ports::CommandEvent> {
    use rollbase_control::service::ports::{CommandEvent, CommandKind, LegTargets};
    let steps = [
        (0.3, 0.0, 0.0),
        (0.0, 0.25, 0.0),
        (0.0, 0.0, 0.6),
        (0.2, 0.1, 0.3),
        (-0.2, 0.0, 0.0),
    ];
    let mut cmds = Vec::new();
    let mut t = 0.0;
    for &(vx, vy, om) in &steps {
        for k in 0..10 {
            cmds.push(twist_at(t + 0.3 * f64::from(k), vx, vy, om));
        }
        t += 3.0;
    }
    for &(at, targets) in legs {
        cmds.push(CommandEvent {
            t: at,
            kind: CommandKind::Legs(LegTargets::from_slice(targets)),
        });
    }
    cmds.sort_by(|a, b| a.t.total_cmp(&b.t));
    for k in 0..5 {
        cmds.push(twist_at(t + 0.3 * f64::from(k), 0.0, 0.0, 0.0));
    }
    cmds.push(CommandEvent {
        t: t + 3.0,
        kind: CommandKind::EndOfStream,
    });
    cmds
}

/// Asserts that every command sent on every cycle keeps every actuator within its speed and
/// acceleration limit ([`rollbase_control::reference::limits::check_command`]): every consecutive pair
/// of commands, in every mode and across every hand-over between modes (align, track, halt,
/// hold, decelerate, disable), fault stops included; no mode is exempt (issue 23).
pub fn assert_commands_within_limits(out: &RunOutcome) {
    let p = &out.platform;
    for w in out.records.windows(2) {
        if let Some(v) = rollbase_control::reference::limits::check_command(
            &p.limits,
            &w[0].command,
            &w[1].command,
            p.dt(),
        ) {
            panic!(
                "cycle {} ({} after {}): {v}",
                w[1].cycle, w[1].mode, w[0].mode
            );
        }
    }
}

/// Smallest back-and-forth of a steering angle that counts as chatter (1°).
pub const CHATTER_AMPLITUDE: f64 = 0.017_453_292_519_943_295;

/// Steering chatter of a wheel: reversals of its measured steering angle's direction of
/// motion, of at least [`CHATTER_AMPLITUDE`] each, while its commanded rolling speed is below
/// 1 cm/s (`wheel_radius` in m). A turning point counts once the angle has come back by the
/// amplitude from the last extreme: the drive's small settling at the end of a turn does not
/// count, a wheel that flips or oscillates does. The measure of the live (e2e_drive) and the
/// time-scaled (e2e_timescale) tests.
pub fn steering_chatter(records: &[CycleRecord], wheel_radius: f64, wheel: usize) -> usize {
    use rollbase_control::angle::diff;
    let mut reversals = 0;
    // (extreme angle, direction of motion: +1, −1 or 0 unknown)
    let mut state: Option<(f64, f64)> = None;
    let mut base = 0.0;
    for rec in records {
        if (rec.command.wheels[wheel].wheel_speed * wheel_radius).abs() >= 0.01 {
            state = None;
            continue;
        }
        let a = rec.measurement.wheels[wheel].steer_angle;
        let Some((ext, dir)) = state else {
            state = Some((a, 0.0));
            base = a;
            continue;
        };
        let d = diff(a, ext);
        if dir == 0.0 {
            if diff(a, base).abs() >= CHATTER_AMPLITUDE {
                state = Some((a, diff(a, base).signum()));
            }
        } else if d * dir > 0.0 {
            state = Some((a, dir));
        } else if d.abs() >= CHATTER_AMPLITUDE {
            reversals += 1;
            state = Some((a, -dir));
        }
    }
    reversals
}

/// Largest change of a wheel's measured steering angle while it is commanded to roll slower
/// than 1 cm/s during tracking (a flip would be about π).
pub fn steering_turn_while_slow(records: &[CycleRecord], wheel_radius: f64, wheel: usize) -> f64 {
    let mut worst = 0.0f64;
    let mut anchor: Option<f64> = None;
    for rec in records {
        let slow = (rec.command.wheels[wheel].wheel_speed * wheel_radius).abs() < 0.01
            && rec.state == rollbase_control::supervisor::SupervisorState::Tracking;
        let a = rec.measurement.wheels[wheel].steer_angle;
        match (slow, anchor) {
            (true, None) => anchor = Some(a),
            (true, Some(a0)) => {
                worst = worst.max(rollbase_control::angle::diff(a, a0).abs());
            }
            (false, _) => anchor = None,
        }
    }
    worst
}

/// A lockstep medium that, from `at` (s) on when `lost`, carries nothing either way and
/// reports no error (a cable cut behind the controller's transceiver): what is sent from
/// then on (by time of the medium's clock) is dropped without a word.
struct Losable {
    bus: VirtualLockstepBus,
    lost_at: Option<f64>,
    now: f64,
}

impl Losable {
    fn lost(&self) -> bool {
        self.lost_at.is_some_and(|at| self.now >= at)
    }
}

impl rollbase_control::runtime::LockstepBus for Losable {
    fn set_time(&mut self, t: std::time::Duration) {
        self.now = t.as_secs_f64();
        self.bus.set_time(t);
    }
    fn controller_send(
        &mut self,
        f: &rollbase_driver::frame::CanFrame,
    ) -> Result<(), rollbase_driver::bus::BusError> {
        if self.lost() {
            return Ok(());
        }
        self.bus.controller_send(f)
    }
    fn controller_recv(
        &mut self,
    ) -> Result<Option<rollbase_driver::frame::TimestampedFrame>, rollbase_driver::bus::BusError>
    {
        self.bus.controller_recv()
    }
    fn peer_send(
        &mut self,
        f: &rollbase_driver::frame::CanFrame,
    ) -> Result<(), rollbase_driver::bus::BusError> {
        if self.lost() {
            return Ok(());
        }
        self.bus.peer_send(f)
    }
    fn peer_recv(
        &mut self,
    ) -> Result<Option<rollbase_driver::frame::TimestampedFrame>, rollbase_driver::bus::BusError>
    {
        self.bus.peer_recv()
    }
    fn set_controller_bus_off(&mut self, off: bool) {
        self.bus.set_controller_bus_off(off);
    }
}

/// Runs `opts` in lockstep with every CAN bus of the platform (`wheels[i].bus`) on its own
/// virtual medium ([`rollbase_control::runtime::run_lockstep_buses`]): each bus gets its own
/// SYNC and setpoints from the core, the simulator's devices see only their bus's frames
/// ([`Simulator::on_frame_on`]) and answer on it. `lose` = (bus, t): from `t` (s) on, that
/// bus's medium carries nothing either way and reports no error (a cable cut behind the
/// controller's transceiver).
pub fn run_buses(opts: &RunOptions, lose: Option<(usize, f64)>) -> RunOutcome {
    use rollbase_control::runtime::LockstepBus;
    let (mut core, mut sim, _, duration) = build(opts).expect("valid setup");
    let platform = core.platform().clone();
    let nb = core.buses();
    let mut media: Vec<Losable> = (0..nb as u64)
        .map(|b| Losable {
            bus: VirtualLockstepBus::new(opts.bus_faults, opts.seed ^ 0x5EED ^ (b << 32)),
            lost_at: lose.and_then(|(lb, at)| (lb as u64 == b).then_some(at)),
            now: 0.0,
        })
        .collect();
    let mut buses: Vec<&mut dyn LockstepBus> = media
        .iter_mut()
        .map(|m| m as &mut dyn LockstepBus)
        .collect();
    let seconds = opts.max_seconds.unwrap_or(duration + opts.slack_s);
    let max_cycles = (seconds * platform.cycle_hz) as u64;
    let mut records = Vec::new();
    let mut summary = RunSummary::new(opts.scenario.name());
    let report = rollbase_control::runtime::run_lockstep_buses(
        &mut core,
        &mut buses,
        &mut sim,
        &[],
        max_cycles,
        &mut |k| Some(k) == opts.stop_at_cycle,
        &mut |r, _| {
            summary.update(r);
            records.push(*r);
        },
    )
    .expect("the test platform's buses, one lockstep bus each");
    RunOutcome {
        records,
        summary,
        report,
        platform,
        final_drive_states: Vec::new(),
        after_end: Vec::new(),
        final_state: Some(*core.base_state()),
        final_skipped: skipped_of(&core),
        final_truth_steer: sim.truth().steer,
        timing: None,
    }
}

/// The simulated modules of a real-time test on their own thread, as the demo runs them: at
/// SCHED_FIFO 81 (they stand in for hardware, which never waits for a busy host; without the
/// privilege they run at normal priority), serving one bus per platform bus
/// ([`rollbase_vcan_sim::run_realtime_buses`]) until [`RealtimeSim::finish`].
pub struct RealtimeSim {
    stop: std::sync::Arc<std::sync::atomic::AtomicBool>,
    handle: std::thread::JoinHandle<
        Result<rollbase_vcan_sim::RealtimeSummary, rollbase_vcan_sim::SimError>,
    >,
}

impl RealtimeSim {
    /// Starts `sim` on `buses` (`buses[b]` for the wheels with `bus = b`).
    pub fn start(
        mut sim: Simulator,
        mut buses: Vec<rollbase_driver::bus::virtual_bus::VirtualNode>,
    ) -> Self {
        use rollbase_driver::bus::CanBus;
        let stop = std::sync::Arc::new(std::sync::atomic::AtomicBool::new(false));
        let s2 = stop.clone();
        let handle = std::thread::spawn(move || {
            let _ = rollbase_control::runtime::realtime_setup(
                &rollbase_control::runtime::RealtimeOptions {
                    fifo_priority: Some(81),
                    lock_memory: false,
                    max_cycles: None,
                },
            );
            let mut refs: Vec<&mut dyn CanBus> =
                buses.iter_mut().map(|b| b as &mut dyn CanBus).collect();
            rollbase_vcan_sim::run_realtime_buses(&mut sim, &mut refs, &s2, None)
        });
        Self { stop, handle }
    }

    /// Stops the simulator and returns its summary; panics (the test fails) when its thread
    /// panicked or its run failed.
    pub fn finish(self) -> rollbase_vcan_sim::RealtimeSummary {
        self.stop.store(true, std::sync::atomic::Ordering::SeqCst);
        self.handle
            .join()
            .expect("simulator thread")
            .expect("simulator run")
    }
}
