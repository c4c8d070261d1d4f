//! Command-line commands: thin adapters over the library crates.

use clap::{Args, Parser, Subcommand};
use rollbase_control::record::{CycleRecord, McapRecorder};
use rollbase_control::runtime::{
    run_lockstep, run_realtime, CycleCore, RealtimeOptions, RunSummary, RuntimeConfig,
    VirtualLockstepBus,
};
use rollbase_control::scenario::{self, Scenario};
use rollbase_control::{Platform, Protocol};
use rollbase_driver::bus::{self as bus, CanBus};
use rollbase_driver::candump::{self, CandumpWriter, LogEntry};
use rollbase_driver::frame::CanFrame;
use rollbase_vcan_sim::{FaultSchedule, PlantConfig, Simulator};
use std::collections::BTreeMap;
use std::io::{BufRead, IsTerminal, Write};
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::Arc;
use std::time::Duration;

/// Errors of the command line.
#[derive(Debug, thiserror::Error)]
pub enum CliError {
    /// Bad platform file.
    #[error(transparent)]
    Config(#[from] rollbase_control::ConfigError),
    /// Bad scenario or trajectory.
    #[error(transparent)]
    Scenario(#[from] scenario::ScenarioError),
    /// Runtime could not start.
    #[error(transparent)]
    Runtime(#[from] rollbase_control::runtime::RuntimeError),
    /// Bus could not be opened or failed.
    #[error(transparent)]
    Bus(#[from] rollbase_driver::bus::BusError),
    /// Simulator setup failed.
    #[error(transparent)]
    Sim(#[from] rollbase_vcan_sim::SimError),
    /// Recording failed.
    #[error(transparent)]
    Record(#[from] rollbase_control::record::RecordError),
    /// Plotting failed.
    #[error(transparent)]
    Plot(#[from] rollbase_control::plot::PlotError),
    /// A capture file could not be read.
    #[error("{path}: {message}")]
    File {
        /// File.
        path: String,
        /// What went wrong.
        message: String,
    },
    /// The socketcand bridge failed.
    #[error(transparent)]
    Bridge(#[from] crate::bridge::BridgeError),
    /// An argument value is not acceptable.
    #[error("{0}")]
    Usage(String),
}

/// rollbase: CAN driver and 250 Hz control stack for omnidirectional platforms with steered
/// wheels on movable legs.
#[derive(Parser, Debug)]
#[command(name = "rollbase", version, about, long_about = None)]
pub struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand, Debug)]
enum Command {
    /// Run the simulator and the controller together on the in-process bus (needs nothing).
    Demo(DemoArgs),
    /// Drive a platform on a CAN interface along a trajectory (vcan0 with rollbase-sim, or hardware).
    Run(RunArgs),
    /// Decode frames live from a bus or from a candump log, one line per frame.
    Monitor(MonitorArgs),
    /// Plot a recording to PNG files.
    Plot(PlotArgs),
    /// Print the protocol as a DBC file (load it in cantools, SavvyCAN, …).
    Dbc,
    /// Print docs/protocol.md, generated from the protocol table.
    ProtocolDoc,
    /// Print docs/cia402.md, generated from the CiA 402 profile's tables.
    Cia402Doc,
    /// Print the bus-load table of the protocol for a configuration.
    BusLoad(BusLoadArgs),
    /// Serve userspace CAN buses over TCP with the socketcand protocol (127.0.0.1:29536).
    Bridge(crate::bridge::BridgeArgs),
    /// Platform file commands.
    Config {
        #[command(subcommand)]
        cmd: ConfigCmd,
    },
}

#[derive(Subcommand, Debug)]
enum ConfigCmd {
    /// Validate a platform file and print it back with every field.
    Check {
        /// Platform TOML file.
        file: PathBuf,
    },
    /// Print the default (Justin-like) platform file.
    Default {
        /// Wire profile of the printed file: native, or cia402 (with the full `[cia402]`
        /// table: node-IDs, drive and encoder units, timing).
        #[arg(long, default_value = "native")]
        profile: Protocol,
    },
}

#[derive(Args, Debug, Clone)]
struct CommonRun {
    /// Platform file (TOML); default: the built-in Justin-like platform.
    #[arg(long)]
    config: Option<PathBuf>,
    /// Tracking controller: dfl (seed 000) or kinematic; default: the scenario's (seed000: dfl,
    /// seed001: kinematic) or dfl for a waypoint file.
    #[arg(long)]
    controller: Option<String>,
    /// Singularity avoidance: on, off, locked (legs locked) or the scenario's default.
    #[arg(long)]
    avoidance: Option<String>,
    /// Write an MCAP recording of the run.
    #[arg(long)]
    record: Option<PathBuf>,
    /// Write every frame on the bus to a candump -L log.
    #[arg(long)]
    candump: Option<PathBuf>,
    /// Write PNG plots of the run into this directory (implies a recording).
    #[arg(long)]
    plots: Option<PathBuf>,
    /// Print one JSON object with the run's summary instead of the table.
    #[arg(long)]
    json: bool,
    /// Wire profile: native (rollbase wheel modules) or cia402 (CANopen CiA 402 drives and
    /// CiA 406 leg encoders); default: the platform file's `protocol`.
    #[arg(long)]
    profile: Option<Protocol>,
}

#[derive(Args, Debug)]
struct DemoArgs {
    /// Scenario: seed000 (the seed-000 experiment) or seed001 (the avoidance experiment).
    #[arg(long, default_value = "seed000")]
    scenario: String,
    /// Run on virtual time as fast as the CPU allows (deterministic) instead of real time.
    #[arg(long)]
    lockstep: bool,
    /// Seed of the simulator's noise and faults.
    #[arg(long, default_value_t = 1)]
    seed: u64,
    /// Simulator fault schedule (TOML).
    #[arg(long)]
    faults: Option<PathBuf>,
    /// Simulator plant parameters (TOML).
    #[arg(long)]
    plant: Option<PathBuf>,
    #[command(flatten)]
    common: CommonRun,
}

#[derive(Args, Debug)]
struct RunArgs {
    /// CAN interface (vcan0, can0, …).
    #[arg(long)]
    bus: String,
    /// Trajectory: a waypoint file (TOML) or `scenario:NAME` (scenario:seed000, scenario:seed001).
    #[arg(long)]
    trajectory: String,
    /// Stop after this many seconds (a controlled stop), e.g. to shorten a scenario.
    #[arg(long)]
    duration: Option<f64>,
    #[command(flatten)]
    common: CommonRun,
}

#[derive(Args, Debug)]
struct MonitorArgs {
    /// Wire profile to decode: native or cia402; default: the platform file's `protocol`.
    #[arg(long)]
    profile: Option<Protocol>,
    /// Platform file (the CiA 402 profile's node-IDs and units come from it).
    #[arg(long)]
    config: Option<PathBuf>,
    /// Live CAN interface to listen on.
    #[arg(long, conflicts_with = "candump")]
    bus: Option<String>,
    /// candump -L log to decode.
    #[arg(long)]
    candump: Option<PathBuf>,
    /// Print a summary (frames per kind, rejections, SYNC period) at the end.
    #[arg(long)]
    summary: bool,
    /// One JSON object per frame (id, DLC, data, decoded signals or the rejection) instead
    /// of text; with --summary, a last object {"summary": …}.
    #[arg(long)]
    json: bool,
}

#[derive(Args, Debug)]
struct PlotArgs {
    /// MCAP recording.
    file: PathBuf,
    /// Output directory.
    #[arg(long, default_value = "plots")]
    out: PathBuf,
}

#[derive(Args, Debug)]
struct BusLoadArgs {
    /// Platform file (its wheel count and cycle rate are used, and for the CiA 402 profile
    /// its `[cia402]` timing).
    #[arg(long)]
    config: Option<PathBuf>,
    /// Wire profile: native or cia402; default: the platform file's `protocol`.
    #[arg(long)]
    profile: Option<Protocol>,
    /// Bit rate (bit/s).
    #[arg(long, default_value_t = 1_000_000)]
    bitrate: u32,
}

/// Runs a command; returns the process exit code.
pub fn run(cli: Cli) -> Result<i32, CliError> {
    match cli.command {
        Command::Demo(a) => demo(a),
        Command::Run(a) => run_bus(a),
        Command::Monitor(a) => monitor(a),
        Command::Bridge(a) => Ok(crate::bridge::run(a)?),
        Command::Plot(a) => {
            let rep = rollbase_control::plot::plot_recording(&a.file, &a.out)?;
            for f in &rep.files {
                println!("{}", f.display());
            }
            if !rep.labelled {
                eprintln!("note: no TTF font found, plots have no text; install fonts-dejavu-core or set ROLLBASE_FONT");
            }
            Ok(0)
        }
        Command::Dbc => {
            print!("{}", rollbase_driver::dbc::dbc());
            Ok(0)
        }
        Command::ProtocolDoc => {
            print!("{}", rollbase_driver::dbc::protocol_markdown());
            Ok(0)
        }
        Command::Cia402Doc => {
            print!("{}", rollbase_driver::canopen::doc::markdown());
            Ok(0)
        }
        Command::BusLoad(a) => {
            let p = load_platform_as(a.config.as_deref(), a.profile)?;
            if a.bitrate == 0 {
                return Err(CliError::Usage(
                    "--bitrate 0: give the bus bit rate in bit/s, e.g. 1000000".into(),
                ));
            }
            match p.protocol {
                Protocol::Native => {
                    let cfg = rollbase_driver::busload::BusLoadConfig {
                        modules: p.n(),
                        cycle_hz: p.cycle_hz,
                        bitrate: a.bitrate,
                        ..Default::default()
                    };
                    print!("{}", rollbase_driver::busload::report(&cfg));
                }
                Protocol::Cia402 => {
                    let l = rollbase_driver::canopen::busload::load(
                        &p.cia402(),
                        p.n(),
                        p.cycle_hz,
                        a.bitrate,
                    );
                    println!("{l}");
                }
            }
            Ok(0)
        }
        Command::Config { cmd } => match cmd {
            ConfigCmd::Check { file } => {
                let p = Platform::load(&file)?;
                println!(
                    "# {}: valid platform `{}` with {} wheels",
                    file.display(),
                    p.name,
                    p.n()
                );
                print!("{}", p.to_toml_string());
                Ok(0)
            }
            ConfigCmd::Default { profile } => {
                let mut p = Platform::justin();
                p.protocol = profile;
                if profile == Protocol::Cia402 {
                    p.cia402 = Some(p.cia402());
                }
                print!("{}", p.to_toml_string());
                Ok(0)
            }
        },
    }
}

fn load_platform(path: Option<&Path>) -> Result<Platform, CliError> {
    Ok(match path {
        Some(p) => Platform::load(p)?,
        None => Platform::justin(),
    })
}

/// The platform file (or the default platform) with the wire profile overridden when
/// `profile` is given, validated again (the `[cia402]` section must fit the platform).
fn load_platform_as(path: Option<&Path>, profile: Option<Protocol>) -> Result<Platform, CliError> {
    let mut p = load_platform(path)?;
    if let Some(pr) = profile {
        p.protocol = pr;
        p.validate()?;
    }
    Ok(p)
}

fn runtime_config(common: &CommonRun, sc: Option<Scenario>) -> Result<RuntimeConfig, CliError> {
    let mut cfg = match sc {
        Some(s) => scenario::runtime_config(s),
        None => RuntimeConfig::default(),
    };
    if let Some(c) = &common.controller {
        cfg.controller = c.parse().map_err(CliError::Usage)?;
    }
    if let Some(a) = &common.avoidance {
        cfg.avoidance = scenario::avoidance_mode(a).map_err(CliError::Usage)?;
    }
    Ok(cfg)
}

/// Where the records go: summary, MCAP, candump, progress.
struct Sinks {
    summary: RunSummary,
    mcap: Option<McapRecorder>,
    candump: Option<CandumpWriter<std::io::BufWriter<std::fs::File>>>,
    iface: String,
    time_origin: f64,
    error: Option<CliError>,
}

impl Sinks {
    fn new(
        scenario: &str,
        common: &CommonRun,
        iface: &str,
        time_origin: f64,
        meta: BTreeMap<String, String>,
    ) -> Result<Self, CliError> {
        let record_path = common.record.clone().or_else(|| {
            common
                .plots
                .as_ref()
                .map(|d| d.join(format!("{scenario}.mcap")))
        });
        let mcap = match record_path {
            Some(p) => Some(McapRecorder::create(&p, &meta)?),
            None => None,
        };
        let candump = match &common.candump {
            Some(p) => {
                if let Some(d) = p.parent() {
                    if !d.as_os_str().is_empty() {
                        std::fs::create_dir_all(d).map_err(|e| CliError::File {
                            path: d.display().to_string(),
                            message: e.to_string(),
                        })?;
                    }
                }
                let f = std::fs::File::create(p).map_err(|e| CliError::File {
                    path: p.display().to_string(),
                    message: format!("cannot create candump log: {e}"),
                })?;
                Some(CandumpWriter::new(std::io::BufWriter::new(f)))
            }
            None => None,
        };
        Ok(Self {
            summary: RunSummary::new(scenario),
            mcap,
            candump,
            iface: iface.into(),
            time_origin,
            error: None,
        })
    }

    fn take(&mut self, r: &CycleRecord, wheel_xy: &[[f64; 2]]) {
        self.summary.update(r);
        if self.error.is_some() {
            return;
        }
        if let Some(m) = &mut self.mcap {
            if let Err(e) = m.write_cycle(r, wheel_xy) {
                self.error = Some(e.into());
                return;
            }
        }
        if let Some(w) = &mut self.candump {
            // Frames in bus order: SYNC first, then what was received, then the setpoints.
            let mut frames: Vec<(f64, &rollbase_control::record::FrameRecord)> =
                Vec::with_capacity(r.n_rx + r.n_tx);
            frames.extend(r.tx[..r.n_tx].iter().map(|f| (f.t, f)));
            frames.extend(r.rx[..r.n_rx].iter().map(|f| (f.t, f)));
            frames.sort_by(|a, b| a.0.total_cmp(&b.0));
            for (t, f) in frames {
                let Ok(frame) = CanFrame::new(f.id, &f.data[..f.len as usize]) else {
                    continue;
                };
                let entry = LogEntry {
                    timestamp: Duration::from_secs_f64((self.time_origin + t).max(0.0)),
                    interface: self.iface.clone(),
                    frame,
                };
                if let Err(e) = w.write(&entry) {
                    self.error = Some(CliError::File {
                        path: "candump log".into(),
                        message: e.to_string(),
                    });
                    return;
                }
            }
        }
    }

    /// Closes the outputs; returns the summary and, when recording, messages per topic.
    fn finish(
        mut self,
        common: &CommonRun,
        scenario: &str,
    ) -> Result<(RunSummary, Option<BTreeMap<String, u64>>), CliError> {
        if let Some(e) = self.error.take() {
            return Err(e);
        }
        if let Some(mut w) = self.candump.take() {
            w.flush().map_err(|e| CliError::File {
                path: "candump log".into(),
                message: e.to_string(),
            })?;
        }
        let mut recorded = None;
        if let Some(m) = self.mcap.take() {
            let s = m.finish()?;
            let total: u64 = s.messages.values().sum();
            if !common.json {
                eprintln!("recorded {total} messages on {} topics", s.messages.len());
            }
            recorded = Some(s.messages);
        }
        if let Some(dir) = &common.plots {
            let path = common
                .record
                .clone()
                .unwrap_or_else(|| dir.join(format!("{scenario}.mcap")));
            let rep = rollbase_control::plot::plot_recording(&path, dir)?;
            if !common.json {
                for f in &rep.files {
                    eprintln!("plot: {}", f.display());
                }
            }
        }
        Ok((self.summary, recorded))
    }
}

fn unix_now() -> f64 {
    std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map(|d| d.as_secs_f64())
        .unwrap_or(0.0)
}

fn demo(a: DemoArgs) -> Result<i32, CliError> {
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
    Ok(exit_code(&summary))
}

fn cfg_controller(common: &CommonRun, sc: Scenario) -> rollbase_control::runtime::ControllerKind {
    runtime_config(common, Some(sc))
        .map(|c| c.controller)
        .unwrap_or(rollbase_control::runtime::ControllerKind::Dfl)
}

fn exit_code(s: &RunSummary) -> i32 {
    if s.final_state == "stopped" {
        0
    } else {
        1
    }
}

fn install_ctrl_c(stop: Arc<AtomicBool>) {
    std::thread::spawn(move || {
        let Ok(rt) = tokio::runtime::Builder::new_current_thread()
            .enable_all()
            .build()
        else {
            return;
        };
        rt.block_on(async {
            if tokio::signal::ctrl_c().await.is_ok() {
                eprintln!("\nCtrl-C: controlled stop (Ctrl-C again is ignored; the platform is decelerating)");
                stop.store(true, Ordering::SeqCst);
            }
        });
    });
}

fn run_demo_realtime(
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
    install_ctrl_c(stop.clone());
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

fn print_summary(
    s: &RunSummary,
    json: bool,
    reason: Option<rollbase_control::supervisor::FaultReason>,
    recorded: Option<&BTreeMap<String, u64>>,
) {
    if json {
        let mut j = s.to_json();
        if let Some(r) = recorded {
            // Messages per MCAP topic, to check a recording against its run.
            j["recorded_messages"] = serde_json::json!(r);
        }
        println!("{j}");
        return;
    }
    let j = s.to_json();
    let row = |k: &str, unit: &str, scale: f64| {
        let v = j[k]
            .as_f64()
            .map(|x| format!("{:.3}", x * scale))
            .unwrap_or_else(|| "-".into());
        println!("  {k:<28} {v:>12} {unit}");
    };
    println!(
        "summary ({} — errors against {}):",
        s.scenario,
        j["errors_against"].as_str().unwrap_or("?")
    );
    println!("  {:<28} {:>12}", "cycles", s.cycles);
    println!("  {:<28} {:>12}", "deadline_misses", s.deadline_misses);
    row("max_position_error_m", "mm", 1e3);
    row("final_position_error_m", "mm", 1e3);
    row("max_heading_error_rad", "deg", 180.0 / std::f64::consts::PI);
    row("max_leg_error_m", "mm", 1e3);
    row("max_wheel_speed_rad_s", "rad/s", 1.0);
    row("max_steer_rate_rad_s", "rad/s", 1.0);
    row("min_icr_wheel_distance_m", "m", 1.0);
    row("cycle_period_p99_us", "µs", 1.0);
    row("compute_time_p99_us", "µs", 1.0);
    println!("  {:<28} {:>12}", "rejected_frames", s.rejected_frames);
    println!("  {:<28} {:>12}", "supervisor_final_state", s.final_state);
    if let Some(r) = reason {
        println!("  fault: {r}");
    }
}

fn run_bus(a: RunArgs) -> Result<i32, CliError> {
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
    install_ctrl_c(stop.clone());
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
    Ok(exit_code(&summary))
}

/// Decodes frames for the monitor in the chosen profile.
enum Decoder {
    Native(rollbase_driver::rx::Receiver),
    Cia402(rollbase_driver::canopen::config::Cia402Config),
}

impl Decoder {
    fn text(&mut self, stats: &mut candump::MonitorStats, ts: Duration, f: &CanFrame) -> String {
        match self {
            Decoder::Native(rx) => candump::describe(rx, stats, ts, f),
            Decoder::Cia402(cfg) => {
                let r = rollbase_driver::canopen::describe::describe(f, cfg);
                crate::monitor_json::count_cia402(stats, &r);
                let mut line = format!(
                    "({}.{:06}) {:03X} [{}]",
                    ts.as_secs(),
                    ts.subsec_micros(),
                    f.id(),
                    f.len()
                );
                for b in f.data() {
                    line.push_str(&format!(" {b:02X}"));
                }
                for _ in f.len()..8 {
                    line.push_str("   ");
                }
                match r {
                    Ok(d) => line.push_str(&format!("  {d}")),
                    Err(e) => line.push_str(&format!("  REJECTED: {e}")),
                }
                line
            }
        }
    }

    fn json(
        &mut self,
        stats: &mut candump::MonitorStats,
        ts: Duration,
        f: &CanFrame,
    ) -> serde_json::Value {
        match self {
            Decoder::Native(rx) => crate::monitor_json::frame_json(rx, stats, ts, f),
            Decoder::Cia402(cfg) => crate::monitor_json::cia402_frame_json(cfg, stats, ts, f),
        }
    }

    fn summary(&self, stats: &candump::MonitorStats, json: bool) -> String {
        match (self, json) {
            (Decoder::Native(_), true) => crate::monitor_json::summary_json(stats).to_string(),
            (Decoder::Native(_), false) => stats.to_string(),
            (Decoder::Cia402(_), true) => {
                crate::monitor_json::cia402_summary_json(stats).to_string()
            }
            (Decoder::Cia402(_), false) => format!(
                "frames: {}, described: {}, rejected: {}; unparsable lines: {}",
                stats.frames,
                stats.frames - stats.rejected,
                stats.rejected,
                stats.unparsable
            ),
        }
    }
}

fn monitor(a: MonitorArgs) -> Result<i32, CliError> {
    let platform = load_platform_as(a.config.as_deref(), a.profile)?;
    let mut dec = match platform.protocol {
        Protocol::Native => Decoder::Native(rollbase_driver::rx::Receiver::new()),
        Protocol::Cia402 => Decoder::Cia402(platform.cia402()),
    };
    let mut stats = candump::MonitorStats::default();
    // A closed stdout (`rollbase monitor … | head`) ends the monitor quietly.
    let mut out = std::io::stdout().lock();
    macro_rules! emit {
        ($($arg:tt)*) => {
            if writeln!(out, $($arg)*).is_err() {
                return Ok(0);
            }
        };
    }
    match (&a.bus, &a.candump) {
        (Some(iface), None) => {
            let mut canbus = bus::open(iface)?;
            let stop = Arc::new(AtomicBool::new(false));
            install_ctrl_c(stop.clone());
            while !stop.load(Ordering::Relaxed) {
                let deadline = std::time::Instant::now() + Duration::from_millis(200);
                match canbus.recv_until(deadline) {
                    Ok(Some(f)) => {
                        if a.json {
                            let v = dec.json(&mut stats, f.timestamp, &f.frame);
                            emit!("{v}");
                        } else {
                            let line = dec.text(&mut stats, f.timestamp, &f.frame);
                            emit!("{line}");
                        }
                    }
                    Ok(None) => {}
                    Err(e) if e.is_retryable() => {}
                    Err(e) => return Err(e.into()),
                }
            }
        }
        (None, Some(path)) => {
            let f = std::fs::File::open(path).map_err(|e| CliError::File {
                path: path.display().to_string(),
                message: format!("cannot open candump log: {e}"),
            })?;
            for (lineno, line) in std::io::BufReader::new(f).lines().enumerate() {
                let line = line.map_err(|e| CliError::File {
                    path: path.display().to_string(),
                    message: e.to_string(),
                })?;
                if line.trim().is_empty() {
                    continue;
                }
                match candump::parse_line(&line) {
                    Ok(e) if a.json => {
                        let v = dec.json(&mut stats, e.timestamp, &e.frame);
                        emit!("{v}");
                    }
                    Ok(e) => {
                        let line = dec.text(&mut stats, e.timestamp, &e.frame);
                        emit!("{line}");
                    }
                    Err(e) if a.json => {
                        stats.unparsable += 1;
                        let v = serde_json::json!({"line": lineno + 1, "error": e.to_string()});
                        emit!("{v}");
                    }
                    Err(e) => {
                        stats.unparsable += 1;
                        println!("line {}: {e}", lineno + 1);
                    }
                }
            }
        }
        _ => {
            return Err(CliError::Usage(
                "monitor needs exactly one of --bus IFACE or --candump FILE".into(),
            ))
        }
    }
    if a.summary {
        let line = dec.summary(&stats, a.json);
        emit!("{line}");
    }
    Ok(0)
}

#[allow(dead_code)]
fn flush_stdout() {
    let _ = std::io::stdout().flush();
}
