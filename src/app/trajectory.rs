//! `demo` and `run`: follow a trajectory (a scenario or a waypoint file) to its end.

use clap::Args;
use rollbase_control::runtime::record::CycleRecord;
use rollbase_control::runtime::scenario::{self, Scenario};
use rollbase_control::runtime::{run_lockstep_buses, CycleCore, LockstepBus, VirtualLockstepBus};
use rollbase_driver::bus::{self as bus, CanBus};
use rollbase_vcan_sim::{FaultSchedule, PlantConfig, Simulator};
use std::collections::BTreeMap;
use std::io::IsTerminal;
use std::path::PathBuf;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::Duration;

use super::common::{
    install_signals, load_platform_on, load_platform_profile, runtime_config, unix_now, CliError,
    CommonRun, SignalAction,
};
use super::rt::{as_buses, print_report, run_cycle, wall_buses, Ports, SimThread};
use super::sinks::{exit_code, print_summary, Ending, OutputPlan, Sinks};

#[derive(Args, Debug)]
pub(crate) struct DemoArgs {
    /// Scenario: seed000 (the seed-000 experiment) or seed001 (the avoidance experiment).
    #[arg(long, default_value = "seed000")]
    pub(crate) scenario: String,
    /// Follow your own waypoint file (TOML; `t` optional per waypoint) instead of a scenario:
    /// the simulator starts at its first waypoint, the run is time-scaled into the limits.
    #[arg(long, value_name = "FILE", conflicts_with_all = ["scenario", "commands", "teleop"])]
    pub(crate) trajectory: Option<PathBuf>,
    /// Run on virtual time as fast as the CPU allows (deterministic) instead of real time.
    #[arg(long)]
    pub(crate) lockstep: bool,
    /// Seed of the simulator's noise and faults.
    #[arg(long, default_value_t = 1)]
    pub(crate) seed: u64,
    /// Simulator fault schedule (TOML).
    #[arg(long)]
    pub(crate) faults: Option<PathBuf>,
    /// Simulator plant parameters (TOML).
    #[arg(long)]
    pub(crate) plant: Option<PathBuf>,
    /// Follow live motion commands from this JSON Lines file (`-`: stdin) instead of a
    /// scenario: the base service with the simulator in-process (see `rollbase drive`).
    #[arg(long, value_name = "FILE", conflicts_with = "teleop")]
    pub(crate) commands: Option<PathBuf>,
    /// Drive the simulated platform from the keyboard in real time (arrows/WASD translate,
    /// Q/E rotate, +/- legs out/in, space stops, R re-arms, Esc or Ctrl-C quits).
    #[arg(long, conflicts_with = "lockstep")]
    pub(crate) teleop: bool,
    /// ROS 2: with `--ros2` the simulated platform runs in real time, starting at rest, and
    /// takes its motion commands from `cmd_vel` until Ctrl-C or SIGTERM.
    #[command(flatten)]
    pub(crate) ros2: super::common::Ros2Run,
    #[command(flatten)]
    pub(crate) common: CommonRun,
}

#[derive(Args, Debug)]
pub(crate) struct RunArgs {
    /// CAN interface (vcan0, can0, …). A platform on two buses takes two, in order: the first
    /// `--bus` serves the wheels with `bus = 0`, the second those with `bus = 1`.
    #[arg(long, required = true)]
    pub(crate) bus: Vec<String>,
    /// Trajectory: a waypoint file (TOML) or `scenario:NAME` (scenario:seed000, scenario:seed001).
    #[arg(long)]
    pub(crate) trajectory: String,
    /// Stop after this many seconds (a controlled stop), e.g. to shorten a scenario
    /// (0 < S ≤ 1e6).
    #[arg(long, value_name = "S")]
    pub(crate) duration: Option<f64>,
    #[command(flatten)]
    pub(crate) common: CommonRun,
}

impl DemoArgs {
    /// Live commands (a file, the keyboard or ROS 2) rather than a trajectory: the base
    /// service runs it (`service::demo_live`).
    pub(crate) fn is_live(&self) -> bool {
        self.commands.is_some() || self.teleop || self.ros2.ros2
    }
}

/// A demo that follows a trajectory (the live ones are `service::demo_live`).
pub(crate) fn demo(a: DemoArgs) -> Result<i32, CliError> {
    // Everything is validated before anything is created or started. The in-process
    // simulator serves a platform on two buses on two in-process buses (real time) or two
    // virtual buses (--lockstep).
    let platform = load_platform_profile(a.common.config.as_deref(), a.common.profile)?;
    a.ros2.options(platform.n())?; // refuses --ros2-* options without --ros2
    let (traj, sc, name) = match &a.trajectory {
        Some(file) => {
            let t = rollbase_control::reference::trajectory::load_waypoints(&platform, file)
                .map_err(scenario::ScenarioError::from)?;
            let t: Box<dyn rollbase_control::reference::trajectory::Trajectory> = Box::new(t);
            (t, None, "trajectory".to_string())
        }
        None => {
            let sc: Scenario = a.scenario.parse()?;
            (
                scenario::trajectory(sc, &platform)?,
                Some(sc),
                sc.name().to_string(),
            )
        }
    };
    let cfg = runtime_config(&a.common, sc)?;
    let faults = match &a.faults {
        Some(p) => FaultSchedule::load(p)?,
        None => FaultSchedule::default(),
    };
    let plant_cfg = match &a.plant {
        Some(p) => PlantConfig::load(p)?,
        None => PlantConfig::default(),
    };
    let plan = OutputPlan::of(&a.common, &name);
    plan.check()?;
    let r0 = traj.sample(0.0);
    let controller = cfg.controller;
    let mut core = CycleCore::new(platform.clone(), traj, cfg)?;
    // The executed duration: the time scaling may have stretched the trajectory.
    let duration = core.reference_duration();
    let sim = Simulator::new(&platform, plant_cfg, faults, &r0, a.seed)?;
    let mut meta = BTreeMap::new();
    meta.insert("scenario".into(), name.clone());
    if let Some(file) = &a.trajectory {
        meta.insert("trajectory".into(), file.display().to_string());
    }
    meta.insert(
        "mode".into(),
        if a.lockstep { "lockstep" } else { "realtime" }.to_string(),
    );
    meta.insert("seed".into(), a.seed.to_string());
    meta.insert("controller".into(), format!("{controller:?}"));
    let origin = if a.lockstep { 0.0 } else { unix_now() };
    let quiet = a.common.json;
    let stop = Arc::new(AtomicBool::new(false));
    let signalled = install_signals(stop.clone(), SignalAction::ControlledStop);
    let mut sinks = Sinks::new(
        &name,
        &plan,
        demo_interfaces(platform.buses()),
        origin,
        meta,
    )?;
    sinks.summary.timing = core.trajectory_timing();
    let max_cycles = ((duration + 20.0) * platform.cycle_hz) as u64;
    if !quiet {
        let what = match &a.trajectory {
            Some(file) => format!("trajectory {}", file.display()),
            None => format!("scenario {name}"),
        };
        errln!(
            "demo: {what} ({}), controller {}, {} on the in-process bus{}",
            timing_text(&core, duration),
            format!("{controller:?}").to_lowercase(),
            if a.lockstep { "lockstep" } else { "real time" },
            if platform.buses() > 1 {
                format!("es ({}, one per platform bus)", platform.buses())
            } else {
                String::new()
            }
        );
    }
    if a.lockstep {
        run_demo_lockstep(
            &mut core,
            sim,
            &mut sinks,
            &stop,
            &[],
            max_cycles,
            a.seed,
            quiet,
        )?;
    } else {
        run_demo_realtime(&mut core, sim, &mut sinks, &stop, duration, quiet)?;
    }
    finish(sinks, &core, &a.common, signalled.load(Ordering::SeqCst))
}

/// The interface names the demos log their buses' frames on: vcan0 (and vcan1 for a
/// platform on two buses).
pub(crate) fn demo_interfaces(buses: usize) -> &'static [&'static str] {
    const NAMES: [&str; 2] = ["vcan0", "vcan1"];
    &NAMES[..buses.clamp(1, NAMES.len())]
}

/// The trajectory's durations for the start line: "12.3 s" when it runs as given, "12.3 s
/// nominal, 15.1 s executed, slowest 43 % (wheel 2 steering rate)" when the time scaling
/// stretched it.
fn timing_text(core: &CycleCore, duration: f64) -> String {
    match core.trajectory_timing() {
        Some(t) if t.executed_duration_s != t.nominal_duration_s => {
            let why = if t.limiting == rollbase_control::service::ports::Limiting::None {
                String::new()
            } else {
                format!(" (wheel {} {})", t.wheel + 1, t.limiting.name())
            };
            format!(
                "{:.1} s nominal, {:.1} s executed, slowest {:.0} %{why}",
                t.nominal_duration_s,
                t.executed_duration_s,
                t.min_scale * 100.0
            )
        }
        _ => format!("{duration:.1} s"),
    }
}

/// Finishes a run's outputs, prints its summary (and the recording's failure, if any), and
/// returns the exit code (README "Exit codes").
pub(crate) fn finish(
    sinks: Sinks,
    core: &CycleCore,
    common: &CommonRun,
    interrupted: bool,
) -> Result<i32, CliError> {
    let (summary, recorded, err) = sinks.finish(common.json);
    print_summary(
        &summary,
        common.json,
        core.supervisor().reason(),
        recorded.as_ref(),
    );
    if let Some(e) = &err {
        errln!("error: {e}");
        let mut src = std::error::Error::source(e);
        while let Some(s) = src {
            errln!("  caused by: {s}");
            src = s.source();
        }
    }
    let ending = if interrupted && !core.is_live() {
        Ending::Interrupted
    } else {
        Ending::Completed
    };
    let arrive = (!core.is_live()).then_some(core.config().supervisor.arrive_position);
    Ok(exit_code(&summary, ending, err.is_some(), arrive))
}

/// The demo on virtual time: stops (in a controlled way) on a signal or a failed recording.
#[allow(clippy::too_many_arguments)]
pub(crate) fn run_demo_lockstep(
    core: &mut CycleCore,
    mut sim: Simulator,
    sinks: &mut Sinks,
    stop: &AtomicBool,
    commands: &[rollbase_control::service::ports::CommandEvent],
    max_cycles: u64,
    seed: u64,
    quiet: bool,
) -> Result<(), CliError> {
    let dt = core.platform().dt();
    // One virtual bus per platform bus (bus 0's seed as the one-bus demo's).
    let mut vbuses: Vec<VirtualLockstepBus> = (0..core.buses().max(1) as u64)
        .map(|b| VirtualLockstepBus::new(Default::default(), seed ^ (b << 32)))
        .collect();
    let mut buses: Vec<&mut dyn LockstepBus> = vbuses
        .iter_mut()
        .map(|b| b as &mut dyn LockstepBus)
        .collect();
    let failed = std::cell::Cell::new(false);
    let rep = run_lockstep_buses(
        core,
        &mut buses,
        &mut sim,
        commands,
        max_cycles,
        // A signal or a failed recording: controlled stop.
        &mut |_| stop.load(Ordering::SeqCst) || failed.get(),
        &mut |r: &CycleRecord, w: &[[f64; 2]]| {
            sinks.take(r, w);
            if sinks.failed() {
                failed.set(true);
            }
        },
    )?;
    if let Some(e) = sinks.error() {
        tracing::error!("{e}: {}", super::rt::error_chain(e));
    }
    sinks.summary.compute = rep.compute.clone();
    if !quiet {
        errln!(
            "lockstep: {} cycles ({:.1} s of platform time) in {:.2} s wall, {:.0}× real time",
            rep.cycles,
            rep.cycles as f64 * dt,
            rep.wall_s,
            rep.cycles as f64 * dt / rep.wall_s.max(1e-9)
        );
    }
    Ok(())
}

pub(crate) fn run_demo_realtime(
    core: &mut CycleCore,
    sim: Simulator,
    sinks: &mut Sinks,
    stop: &Arc<AtomicBool>,
    duration: f64,
    quiet: bool,
) -> Result<(), CliError> {
    let (mut ctrl_nodes, sim_nodes) = wall_buses(core.platform().buses());
    let _sim = SimThread::start(sim, sim_nodes)?;
    let show = !quiet && std::io::stderr().is_terminal();
    let mut last_print = std::time::Instant::now();
    let origin = sinks.time_origin;
    let report = run_cycle(
        core,
        &mut as_buses(&mut ctrl_nodes),
        sinks,
        stop,
        Ports {
            cpu: _sim.cpu(),
            ..Ports::default()
        },
        origin,
        &mut |r, sinks| {
            if show && last_print.elapsed() > Duration::from_millis(200) {
                last_print = std::time::Instant::now();
                let t = r.reference.t;
                let frac = (t / duration.max(1e-9)).clamp(0.0, 1.0);
                let bars = (frac * 30.0) as usize;
                // The time scaling slows the trajectory where an actuator needs it: say so.
                let slowing = if r.shaping.limiting
                    != rollbase_control::service::ports::Limiting::None
                    && r.shaping.scale < 0.995
                {
                    format!(
                        "slowing to {:3.0} % ({})",
                        r.shaping.scale * 100.0,
                        r.shaping.limiting.name()
                    )
                } else {
                    String::new()
                };
                err!(
                    "\r[{}{}] {:5.1}/{:.1} s  {:<9} pos err {:6.2} mm  {:<40}",
                    "#".repeat(bars),
                    ".".repeat(30 - bars),
                    t,
                    duration,
                    r.state.name(),
                    sinks.summary.max_position_error_m * 1e3,
                    slowing
                );
            }
        },
    )?;
    if show {
        errln!();
    }
    print_report(&report, quiet);
    Ok(())
}

/// Largest `--duration` (s).
const MAX_DURATION_S: f64 = 1e6;

pub(crate) fn run_bus(a: RunArgs) -> Result<i32, CliError> {
    // Everything is validated before the bus is opened or a file created.
    if let Some(d) = a.duration {
        if !(d.is_finite() && d > 0.0 && d <= MAX_DURATION_S) {
            return Err(CliError::Usage(format!(
                "--duration {d}: must be a number of seconds in (0, {MAX_DURATION_S}]"
            )));
        }
    }
    let platform = load_platform_on(a.common.config.as_deref(), a.common.profile, &a.bus)?;
    let (traj, sc) = scenario::trajectory_arg(&a.trajectory, &platform)?;
    let cfg = runtime_config(&a.common, sc)?;
    let name = sc
        .map(|s| s.name().to_string())
        .unwrap_or_else(|| "trajectory".into());
    let plan = OutputPlan::of(&a.common, &name);
    plan.check()?;
    let mut core = CycleCore::new(platform.clone(), traj, cfg)?;
    let duration = core.reference_duration();
    let mut canbuses: Vec<Box<dyn CanBus>> = a
        .bus
        .iter()
        .map(|b| bus::open(b))
        .collect::<Result<_, _>>()?;
    let mut buses = super::rt::boxed_buses(&mut canbuses);
    let origin = unix_now();
    let mut meta = BTreeMap::new();
    meta.insert("bus".into(), a.bus.join(","));
    meta.insert("trajectory".into(), a.trajectory.clone());
    let stop = Arc::new(AtomicBool::new(false));
    let signalled = install_signals(stop.clone(), SignalAction::ControlledStop);
    // The interface name as candump logs it ("vcan0", also for socketcand://HOST:PORT/vcan0).
    let names: Vec<&str> = buses.iter().map(|b| b.name()).collect();
    let mut sinks = Sinks::new(&name, &plan, &names, origin, meta)?;
    sinks.summary.timing = core.trajectory_timing();
    if let Some(d) = a.duration {
        let stop = stop.clone();
        std::thread::spawn(move || {
            std::thread::sleep(Duration::from_secs_f64(d));
            stop.store(true, Ordering::SeqCst);
        });
    }
    if !a.common.json {
        errln!(
            "run: {} on {} ({})",
            name,
            a.bus.join(" and "),
            timing_text(&core, duration)
        );
    }
    let report = run_cycle(
        &mut core,
        &mut buses,
        &mut sinks,
        &stop,
        Ports::default(),
        origin,
        &mut |_, _| {},
    )?;
    print_report(&report, a.common.json);
    finish(sinks, &core, &a.common, signalled.load(Ordering::SeqCst))
}
