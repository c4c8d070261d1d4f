//! `demo` and `run`: follow a trajectory (a scenario or a waypoint file) to its end.

use clap::Args;
use rollbase_control::record::CycleRecord;
use rollbase_control::runtime::{
    run_lockstep, run_realtime, CycleCore, RealtimeOptions, VirtualLockstepBus,
};
use rollbase_control::scenario::{self, Scenario};
use rollbase_driver::bus::{self as bus, CanBus};
use rollbase_vcan_sim::{FaultSchedule, PlantConfig, Simulator};
use std::collections::BTreeMap;
use std::io::IsTerminal;
use std::path::PathBuf;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::Arc;
use std::time::Duration;

use super::sinks::{exit_code, print_summary, Sinks};
use super::{
    install_ctrl_c, load_platform_as, runtime_config, unix_now, CliError, CommonRun, StopKind,
};

#[derive(Args, Debug)]
pub(crate) struct DemoArgs {
    /// Scenario: seed000 (the seed-000 experiment) or seed001 (the avoidance experiment).
    #[arg(long, default_value = "seed000")]
    pub(crate) scenario: String,
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
    #[command(flatten)]
    pub(crate) common: CommonRun,
}

#[derive(Args, Debug)]
pub(crate) struct RunArgs {
    /// CAN interface (vcan0, can0, …).
    #[arg(long)]
    pub(crate) bus: String,
    /// Trajectory: a waypoint file (TOML) or `scenario:NAME` (scenario:seed000, scenario:seed001).
    #[arg(long)]
    pub(crate) trajectory: String,
    /// Stop after this many seconds (a controlled stop), e.g. to shorten a scenario.
    #[arg(long)]
    pub(crate) duration: Option<f64>,
    #[command(flatten)]
    pub(crate) common: CommonRun,
}

pub(crate) fn demo(a: DemoArgs) -> Result<i32, CliError> {
    let platform = load_platform_as(a.common.config.as_deref(), a.common.profile)?;
    let sc: Scenario = a.scenario.parse()?;
    let traj = scenario::trajectory(sc, &platform)?;
    let duration = traj.duration();
    let cfg = runtime_config(&a.common, Some(sc))?;
    let faults = match &a.faults {
        Some(p) => FaultSchedule::load(p)?,
        None => FaultSchedule::default(),
    };
    let plant_cfg = match &a.plant {
        Some(p) => PlantConfig::load(p)?,
        None => PlantConfig::default(),
    };
    let r0 = traj.sample(0.0);
    let mut core = CycleCore::new(platform.clone(), traj, cfg)?;
    let mut meta = BTreeMap::new();
    meta.insert("scenario".into(), sc.name().to_string());
    meta.insert(
        "mode".into(),
        if a.lockstep { "lockstep" } else { "realtime" }.to_string(),
    );
    meta.insert("seed".into(), a.seed.to_string());
    meta.insert(
        "controller".into(),
        format!("{:?}", cfg_controller(&a.common, sc)),
    );
    let origin = if a.lockstep { 0.0 } else { unix_now() };
    let mut sinks = Sinks::new(sc.name(), &a.common, "vcan0", origin, meta)?;
    let mut sim = Simulator::new(&platform, plant_cfg, faults, &r0, a.seed)?;
    let max_cycles = ((duration + 20.0) * platform.cycle_hz) as u64;
    if !a.common.json {
        eprintln!(
            "demo: scenario {} ({:.1} s), controller {}, {} on the in-process bus",
            sc.name(),
            duration,
            format!("{:?}", cfg_controller(&a.common, sc)).to_lowercase(),
            if a.lockstep { "lockstep" } else { "real time" }
        );
    }
    if a.lockstep {
        let mut vbus = VirtualLockstepBus::new(Default::default(), a.seed);
        let rep = run_lockstep(
            &mut core,
            &mut vbus,
            &mut sim,
            max_cycles,
            None,
            &mut |r, w| sinks.take(r, w),
        );
        sinks.summary.compute_us = rep.compute_us.clone();
        if !a.common.json {
            eprintln!(
                "lockstep: {} cycles ({:.1} s of platform time) in {:.2} s wall, {:.0}× real time",
                rep.cycles,
                rep.cycles as f64 * platform.dt(),
                rep.wall_s,
                rep.cycles as f64 * platform.dt() / rep.wall_s.max(1e-9)
            );
        }
    } else {
        run_demo_realtime(&mut core, sim, &mut sinks, duration, a.common.json)?;
    }
    let (summary, recorded) = sinks.finish(&a.common, sc.name())?;
    print_summary(
        &summary,
        a.common.json,
        core.supervisor().reason(),
        recorded.as_ref(),
    );
    Ok(exit_code(
        &summary,
        core.config().supervisor.arrive_position,
    ))
}

pub(crate) fn cfg_controller(
    common: &CommonRun,
    sc: Scenario,
) -> rollbase_control::runtime::ControllerKind {
    runtime_config(common, Some(sc))
        .map(|c| c.controller)
        .unwrap_or(rollbase_control::runtime::ControllerKind::Dfl)
}

pub(crate) fn run_demo_realtime(
    core: &mut CycleCore,
    mut sim: Simulator,
    sinks: &mut Sinks,
    duration: f64,
    json: bool,
) -> Result<(), CliError> {
    use rollbase_driver::bus::{BusClock, VirtualBus, VirtualBusConfig};
    let vbus = VirtualBus::new(VirtualBusConfig {
        clock: BusClock::Wall,
        ..Default::default()
    });
    let mut ctrl_node = vbus.node("controller");
    let mut sim_node = vbus.node("simulator");
    let stop = Arc::new(AtomicBool::new(false));
    let sim_stop = Arc::new(AtomicBool::new(false));
    install_ctrl_c(stop.clone(), StopKind::Platform);
    let sim_thread = {
        let sim_stop = sim_stop.clone();
        std::thread::Builder::new()
            .name("rollbase-sim".into())
            .spawn(move || {
                // The simulated modules stand in for hardware, which never waits for the
                // controller's process: give them real-time priority too (one above the cycle
                // thread's), so a loaded machine delays neither side.
                let _ = rollbase_control::runtime::realtime_setup(&RealtimeOptions {
                    fifo_priority: Some(81),
                    lock_memory: false,
                    max_cycles: None,
                });
                sim.run_realtime(&mut sim_node, &sim_stop)
            })
            .map_err(|e| CliError::Usage(format!("cannot start the simulator thread: {e}")))?
    };
    let (tx, rx) = std::sync::mpsc::sync_channel::<CycleRecord>(2048);
    let progress = Arc::new(AtomicU64::new(0));
    let opts = RealtimeOptions::default();
    let origin_ns = (sinks.time_origin * 1e9) as u64;
    let report = std::thread::scope(|s| {
        let prog = progress.clone();
        let cycle = s.spawn(|| {
            let r = run_realtime(core, &mut ctrl_node, &stop, Some(&tx), &opts, origin_ns);
            drop(tx);
            r
        });
        let show = !json && std::io::stderr().is_terminal();
        let mut last_print = std::time::Instant::now();
        loop {
            match rx.recv_timeout(Duration::from_millis(100)) {
                Ok(r) => {
                    prog.store(r.cycle, Ordering::Relaxed);
                    sinks.take(&r, &r.wheel_xy[..r.n]);
                    if show && last_print.elapsed() > Duration::from_millis(200) {
                        last_print = std::time::Instant::now();
                        let t = r.reference.t;
                        let frac = (t / duration.max(1e-9)).clamp(0.0, 1.0);
                        let bars = (frac * 30.0) as usize;
                        eprint!(
                            "\r[{}{}] {:5.1}/{:.1} s  {:<9} pos err {:6.2} mm   ",
                            "#".repeat(bars),
                            ".".repeat(30 - bars),
                            t,
                            duration,
                            r.state.name(),
                            sinks.summary.max_position_error_m * 1e3
                        );
                    }
                }
                Err(std::sync::mpsc::RecvTimeoutError::Timeout) => {}
                Err(std::sync::mpsc::RecvTimeoutError::Disconnected) => break,
            }
        }
        if show {
            eprintln!();
        }
        cycle.join()
    });
    sim_stop.store(true, Ordering::SeqCst);
    let _ = sim_thread.join();
    let report = report.map_err(|_| CliError::Usage("the cycle thread panicked".into()))?;
    if !json {
        for line in &report.setup {
            eprintln!("runtime: {line}");
        }
        eprintln!(
            "runtime: {} cycles, {} deadline misses, {} records dropped",
            report.cycles, report.deadline_misses, report.records_dropped
        );
    }
    sinks.summary.deadline_misses = sinks.summary.deadline_misses.max(report.deadline_misses);
    Ok(())
}

pub(crate) fn run_bus(a: RunArgs) -> Result<i32, CliError> {
    let platform = load_platform_as(a.common.config.as_deref(), a.common.profile)?;
    let (traj, sc) = scenario::trajectory_arg(&a.trajectory, &platform)?;
    let duration = traj.duration();
    let cfg = runtime_config(&a.common, sc)?;
    let mut core = CycleCore::new(platform.clone(), traj, cfg)?;
    // Open the bus only after everything else validated: nothing starts on bad input.
    let mut canbus = bus::open(&a.bus)?;
    let name = sc
        .map(|s| s.name().to_string())
        .unwrap_or_else(|| "trajectory".into());
    let origin = unix_now();
    let mut meta = BTreeMap::new();
    meta.insert("bus".into(), a.bus.clone());
    meta.insert("trajectory".into(), a.trajectory.clone());
    // The interface name as candump logs it ("vcan0", also for socketcand://HOST:PORT/vcan0).
    let mut sinks = Sinks::new(&name, &a.common, canbus.name(), origin, meta)?;
    let stop = Arc::new(AtomicBool::new(false));
    install_ctrl_c(stop.clone(), StopKind::Platform);
    if let Some(d) = a.duration {
        if !(d.is_finite() && d > 0.0) {
            return Err(CliError::Usage(format!(
                "--duration {d}: must be a positive number of seconds"
            )));
        }
        let stop = stop.clone();
        std::thread::spawn(move || {
            std::thread::sleep(Duration::from_secs_f64(d));
            stop.store(true, Ordering::SeqCst);
        });
    }
    let (tx, rx) = std::sync::mpsc::sync_channel::<CycleRecord>(2048);
    let opts = RealtimeOptions::default();
    if !a.common.json {
        eprintln!("run: {} on {} ({:.1} s)", name, a.bus, duration);
    }
    let report = std::thread::scope(|s| {
        let cycle = s.spawn(|| {
            let r = run_realtime(
                &mut core,
                canbus.as_mut(),
                &stop,
                Some(&tx),
                &opts,
                (origin * 1e9) as u64,
            );
            drop(tx);
            r
        });
        while let Ok(r) = rx.recv() {
            sinks.take(&r, &r.wheel_xy[..r.n]);
        }
        cycle.join()
    });
    let report = report.map_err(|_| CliError::Usage("the cycle thread panicked".into()))?;
    if !a.common.json {
        for line in &report.setup {
            eprintln!("runtime: {line}");
        }
        eprintln!(
            "runtime: {} cycles, {} deadline misses, {} records dropped, {} bus errors",
            report.cycles, report.deadline_misses, report.records_dropped, report.bus_errors
        );
    }
    sinks.summary.deadline_misses = sinks.summary.deadline_misses.max(report.deadline_misses);
    let (summary, recorded) = sinks.finish(&a.common, &name)?;
    print_summary(
        &summary,
        a.common.json,
        core.supervisor().reason(),
        recorded.as_ref(),
    );
    Ok(exit_code(
        &summary,
        core.config().supervisor.arrive_position,
    ))
}
