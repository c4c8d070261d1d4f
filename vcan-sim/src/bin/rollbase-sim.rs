//! `rollbase-sim`: the simulated wheel modules and platform on a CAN bus, in real time.
//!
//! ```text
//! rollbase-sim --bus vcan0 [--bus vcan1] [--config platform.toml] [--profile native|cia402]
//!              [--plant plant.toml] [--faults faults.toml] [--loss P]
//!              [--silent NODE:FROM:TO] … [--seed N] [--duration S]
//!              [--start nominal|scenario:NAME|waypoints.toml]
//! ```
//!
//! The modules answer the controller's SYNCs (the simulator follows the bus's SYNC pace; it
//! has no cycle clock of its own), obey its SETPOINTs and move the simulated platform in 1 ms
//! sub-steps. With `--profile cia402` (or `protocol = "cia402"` in the platform file) the
//! bus carries CANopen instead: per wheel a CiA 402 rolling drive, a CiA 402 steering drive
//! and a CiA 406 leg encoder, at the node-IDs of the file's `[cia402]` table, each with its
//! object dictionary, SDO server, NMT, heartbeat, EMCY and PDOs (configured by the master
//! over SDO). SIGINT (Ctrl-C), SIGTERM (`kill`, systemd, a test harness), SIGHUP (a closed
//! terminal or ssh session) and SIGQUIT stop it cleanly: it prints its summary and exits 0;
//! SIGUSR1 and SIGUSR2 are ignored. A bad option or file, or a bus that cannot be opened,
//! exits 2 before anything runs; a failure while it runs exits 1. Its output never kills it:
//! SIGPIPE is ignored and every write to stdout/stderr ignores errors (a closed terminal or a
//! `| head` that went away).
//!
//! A platform with wheels on two buses (`bus = 0|1` in its file) takes one `--bus` per
//! platform bus, in order (the first carries the devices of the wheels with `bus = 0`, the
//! second those with `bus = 1`): each device sends on its own bus and hears only its own bus's
//! frames (its SYNC among them). A number of `--bus` options that differs from the platform's
//! buses, or the same interface twice, exits 2 before anything runs.
//!
//! `--bus virtual` creates an in-process virtual bus that no other process can reach: it is
//! only useful to check a configuration. To run the controller against the simulator without
//! kernel CAN, use `rollbase demo`, which starts this simulator in-process on a shared
//! virtual bus.

use clap::Parser;
use rollbase_control::Platform;
use rollbase_driver::bus::{self, BusClock, BusError, CanBus, VirtualBus, VirtualBusConfig};
use rollbase_vcan_sim::{
    spawn_realtime_buses, FaultArgs, PlantConfig, SimConfig, SimError, Simulator,
};
use std::io::Write;
use std::path::PathBuf;
use std::process::ExitCode;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::Duration;

/// `eprintln!` that never panics: a closed or broken stderr loses the text, not the process.
macro_rules! say {
    ($($arg:tt)*) => {{
        let _ = writeln!(std::io::stderr(), $($arg)*);
    }};
}

/// Simulated rollbase wheel modules and platform, speaking the wheel-module protocol.
#[derive(Debug, Parser)]
#[command(name = "rollbase-sim", version, about, long_about = None)]
struct Cli {
    /// CAN interface (vcan0, can0, …) or `virtual` (in-process only; see `rollbase demo`). A
    /// platform on two buses takes two, in order: the first carries the wheels with
    /// `bus = 0`, the second those with `bus = 1`.
    #[arg(long, required = true)]
    bus: Vec<String>,
    /// Platform description (TOML); default: the Justin-like platform.
    #[arg(long, value_name = "FILE")]
    config: Option<PathBuf>,
    /// Wire profile: native (rollbase wheel modules) or cia402 (CANopen CiA 402 drives and
    /// CiA 406 leg encoders); default: the platform file's `protocol`.
    #[arg(long)]
    profile: Option<rollbase_control::Protocol>,
    /// Plant parameters (TOML: motor time constants, encoder noise …); default values otherwise.
    #[arg(long, value_name = "FILE")]
    plant: Option<PathBuf>,
    #[command(flatten)]
    faults: FaultArgs,
    /// Seed for encoder noise and frame faults (a `seed` in the fault file wins for the latter).
    #[arg(long, default_value_t = 1)]
    seed: u64,
    /// Stop after this many seconds (default: run until Ctrl-C).
    #[arg(long, value_name = "S")]
    duration: Option<f64>,
    /// Where the platform starts: `nominal` (legs at their nominal extension, wheels straight),
    /// `scenario:NAME` (the scenario's initial pose and legs, e.g. `scenario:seed000`, so
    /// `rollbase run --trajectory scenario:seed000` finds the platform where it starts) or a
    /// waypoint file (its first waypoint's pose and legs, for `rollbase run --trajectory
    /// FILE`).
    #[arg(
        long,
        default_value = "nominal",
        value_name = "nominal|scenario:NAME|FILE"
    )]
    start: String,
    /// Time from a SYNC to the modules' feedback frames (µs).
    #[arg(long, value_name = "US", default_value_t = 300.0)]
    response_latency_us: f64,
    /// SCHED_FIFO priority of the simulator thread (1–99; 0: normal scheduling). Default 81,
    /// one above the controller's cycle thread, as in `rollbase demo`: simulated modules, like
    /// real ones, must not wait for a busy host. Needs CAP_SYS_NICE or an rtprio limit; without
    /// it the simulator says so and runs with normal scheduling.
    #[arg(long, value_name = "PRIO", default_value_t = 81, value_parser = clap::value_parser!(i32).range(0..=99))]
    priority: i32,
}

#[derive(Debug, thiserror::Error)]
enum CliError {
    #[error(transparent)]
    Sim(#[from] SimError),
    #[error("cannot open bus {bus}: {source}{hint}")]
    Open {
        bus: String,
        source: BusError,
        hint: &'static str,
    },
    #[error("platform `{platform}` puts its wheels on {buses} CAN bus(es) but {given} `--bus` option(s) were given: give one `--bus` per platform bus, in order (the first carries the wheels with `bus = 0`, the second those with `bus = 1`)")]
    BusCount {
        platform: String,
        buses: usize,
        given: usize,
    },
    #[error("`--bus {0}` given twice: each platform bus needs its own interface")]
    BusTwice(String),
    #[error("`{option}` = {value}: {reason}")]
    Option {
        option: &'static str,
        value: String,
        reason: &'static str,
    },
    #[error("`--start` = {value}: not `nominal`, a scenario (`scenario:seed000`, `scenario:seed001`) or a usable waypoint file: {source}")]
    Start {
        value: String,
        source: rollbase_control::reference::trajectory::TrajectoryError,
    },
    #[error("cannot start the signal handler runtime: {0}")]
    Runtime(std::io::Error),
    #[error("the simulator thread panicked")]
    Panicked,
    #[error("the simulation failed: {0}")]
    Run(SimError),
}

impl CliError {
    /// The exit code: 2 for what was refused before the simulator started (a bad option or
    /// file, a bus that cannot be opened: nothing ran), 1 for a failure while it ran.
    fn exit_code(&self) -> u8 {
        match self {
            CliError::Panicked | CliError::Run(_) => 1,
            _ => 2,
        }
    }
}

fn open_bus(name: &str) -> Result<Box<dyn CanBus>, CliError> {
    if name == "virtual" {
        say!(
            "rollbase-sim: note: the virtual bus lives inside this process; no controller in \
             another process can reach it. `rollbase demo` runs the simulator in-process with \
             the controller. Use --bus vcan0 to talk to other processes."
        );
        let vbus = VirtualBus::new(VirtualBusConfig {
            clock: BusClock::Wall,
            ..VirtualBusConfig::default()
        });
        return Ok(Box::new(vbus.node("rollbase-sim")));
    }
    bus::open(name).map_err(|source| {
        let hint = match source {
            BusError::NoSuchInterface { .. } | BusError::AfCanUnsupported { .. } => {
                "\n(no kernel CAN here? `rollbase demo` runs controller and simulator in-process \
                 on the virtual bus)"
            }
            _ => "",
        };
        CliError::Open {
            bus: name.to_string(),
            source,
            hint,
        }
    })
}

fn run(cli: Cli) -> Result<(), CliError> {
    let mut platform = match &cli.config {
        Some(p) => Platform::load(p).map_err(SimError::from)?,
        None => Platform::justin(),
    };
    if let Some(profile) = cli.profile {
        platform.protocol = profile;
        platform.validate().map_err(SimError::from)?;
    }
    if cli.bus.len() != platform.buses() {
        return Err(CliError::BusCount {
            platform: platform.name.clone(),
            buses: platform.buses(),
            given: cli.bus.len(),
        });
    }
    for (k, b) in cli.bus.iter().enumerate() {
        // Each `virtual` is a bus of its own.
        if b != "virtual" && cli.bus[..k].contains(b) {
            return Err(CliError::BusTwice(b.clone()));
        }
    }
    let plant = match &cli.plant {
        Some(p) => PlantConfig::load(p)?,
        None => PlantConfig::default(),
    };
    let faults = cli.faults.to_schedule()?;
    let duration = match cli.duration {
        None => None,
        Some(s) if s.is_finite() && s > 0.0 && s < 1e9 => Some(Duration::from_secs_f64(s)),
        Some(s) => {
            return Err(CliError::Option {
                option: "--duration",
                value: s.to_string(),
                reason: "must be a positive number of seconds",
            })
        }
    };
    let lat = cli.response_latency_us;
    if !(lat.is_finite() && (0.0..=4000.0).contains(&lat)) {
        return Err(CliError::Option {
            option: "--response-latency-us",
            value: lat.to_string(),
            reason: "must be between 0 and 4000 µs",
        });
    }
    let initial = match cli.start.as_str() {
        "nominal" => None,
        other => {
            let name = other.strip_prefix("scenario:").unwrap_or(other);
            let r0 = match name.parse::<rollbase_control::runtime::scenario::Scenario>() {
                Ok(sc) => rollbase_control::runtime::scenario::trajectory(sc, &platform)
                    .map_err(|_| CliError::Option {
                        option: "--start",
                        value: other.to_string(),
                        reason: "the scenario cannot be built for this platform",
                    })?
                    .sample(0.0),
                Err(_) if other.starts_with("scenario:") => return Err(CliError::Option {
                    option: "--start",
                    value: other.to_string(),
                    reason:
                        "use `nominal`, `scenario:seed000` / `scenario:seed001` or a waypoint file",
                }),
                // A waypoint file: the platform starts at its first waypoint (the time
                // scaling never moves the start).
                Err(_) => {
                    use rollbase_control::reference::trajectory::Trajectory;
                    rollbase_control::reference::trajectory::load_waypoints(&platform, other)
                        .map_err(|source| CliError::Start {
                            value: other.to_string(),
                            source,
                        })?
                        .sample(0.0)
                }
            };
            Some(rollbase_vcan_sim::InitialState::from_reference(
                &platform, &r0,
            ))
        }
    };
    let cfg = SimConfig {
        plant,
        faults,
        initial,
        seed: cli.seed,
        response_latency: Duration::from_secs_f64(lat * 1e-6),
        ..SimConfig::default()
    };
    let sim = Simulator::with_config(&platform, cfg)?;
    let buses = cli
        .bus
        .iter()
        .map(|b| open_bus(b))
        .collect::<Result<Vec<_>, _>>()?;
    let names = buses
        .iter()
        .map(|b| b.name().to_string())
        .collect::<Vec<_>>()
        .join(" and ");
    // SIGINT and SIGTERM are both a clean stop; their handlers are in place before the
    // simulator says it runs (a signal sent right after that line must not kill it). Should
    // one not install, the simulator still runs (and says so).
    let rt = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .map_err(CliError::Runtime)?;
    let (mut term, mut int, mut hup, mut quit) = {
        use tokio::signal::unix::{signal, SignalKind};
        let _in_runtime = rt.enter();
        let term = signal(SignalKind::terminate())
            .map_err(|e| say!("rollbase-sim: cannot listen for SIGTERM ({e}); only Ctrl-C or --duration stop it cleanly"))
            .ok();
        let int = signal(SignalKind::interrupt())
            .map_err(|e| say!("rollbase-sim: cannot listen for Ctrl-C ({e})"))
            .ok();
        // A closed terminal or ssh session (SIGHUP) and Ctrl-\ (SIGQUIT) stop it cleanly too.
        let hup = signal(SignalKind::hangup())
            .map_err(|e| say!("rollbase-sim: cannot listen for SIGHUP ({e})"))
            .ok();
        let quit = signal(SignalKind::quit())
            .map_err(|e| say!("rollbase-sim: cannot listen for SIGQUIT ({e})"))
            .ok();
        (term, int, hup, quit)
    };
    match platform.protocol {
        rollbase_control::Protocol::Native => say!(
            "rollbase-sim: {} modules (nodes {:?}) of platform `{}` on {}; waiting for SYNC. Ctrl-C to stop.",
            sim.n(),
            sim.nodes(),
            platform.name,
            names
        ),
        rollbase_control::Protocol::Cia402 => say!(
            "rollbase-sim: CiA 402 profile, {} wheels = {} CANopen devices (nodes {:?}) of platform `{}` on {}; booting, then waiting for the master. Ctrl-C to stop.",
            sim.n(),
            sim.nodes().len(),
            sim.nodes(),
            platform.name,
            names
        ),
    }
    let stop = Arc::new(AtomicBool::new(false));
    let priority = (cli.priority != 0).then_some(cli.priority);
    let (handle, lines) = spawn_realtime_buses(sim, buses, stop.clone(), duration, priority);
    for l in lines.iter() {
        say!("rollbase-sim: {l}");
    }
    rt.block_on(async {
        loop {
            tokio::select! {
                Some(()) = async { term.as_mut()?.recv().await } => {
                    say!("rollbase-sim: SIGTERM: stopping");
                    break;
                }
                Some(()) = async { int.as_mut()?.recv().await } => {
                    say!("rollbase-sim: Ctrl-C: stopping");
                    break;
                }
                Some(()) = async { hup.as_mut()?.recv().await } => {
                    say!("rollbase-sim: SIGHUP: stopping");
                    break;
                }
                Some(()) = async { quit.as_mut()?.recv().await } => {
                    say!("rollbase-sim: SIGQUIT: stopping");
                    break;
                }
                _ = tokio::time::sleep(Duration::from_millis(50)) => {
                    if handle.is_finished() {
                        break;
                    }
                }
            }
        }
    });
    stop.store(true, Ordering::Relaxed);
    let (sim, result) = handle.join().map_err(|_| CliError::Panicked)?;
    let summary = result.map_err(CliError::Run)?;
    let st = sim.stats();
    let truth = sim.truth();
    say!(
        "rollbase-sim: ran {:.3} s: {} frames in, {} out ({} send errors, max send lateness {:?}); \
         {} sub-steps; injected: {} dropped, {} duplicated, {} corrupted",
        summary.elapsed.as_secs_f64(),
        summary.frames_in,
        summary.frames_out,
        summary.send_errors,
        summary.max_send_lateness,
        st.substeps,
        st.injector.dropped,
        st.injector.duplicated,
        st.injector.corrupted,
    );
    for d in sim.devices() {
        let s = d.stats();
        let state = if d.role() == rollbase_driver::canopen::config::Role::Leg {
            String::new()
        } else {
            format!(", {} (statusword 0x{:04X})", d.state402(), d.statusword())
        };
        say!(
            "  node {}: wheel {} {}, {:?}{state}, {} SDO served, {} SDO aborted, {} SYNCs, {} TPDOs, {} RPDOs, {} EMCY, {} heartbeat timeouts, {} RPDO timeouts",
            d.node(),
            d.wheel() + 1,
            d.role(),
            d.nmt(),
            s.sdo_served,
            s.sdo_aborted,
            s.syncs,
            s.tpdos_sent,
            s.rpdos_received,
            s.emcy_sent,
            s.heartbeat_timeouts,
            s.rpdo_timeouts
        );
    }
    let native_modules = if sim.devices().is_empty() { st.n } else { 0 };
    for (i, m) in st.modules[..native_modules].iter().enumerate() {
        say!(
            "  node {}: {:?}, {} SYNCs answered, {} setpoints ok, {} bad CRC, {} bad counter, {} watchdog trips",
            sim.nodes()[i],
            sim.module_states()[i],
            m.syncs_answered,
            m.setpoints_accepted,
            m.setpoints_bad_crc,
            m.setpoints_bad_counter,
            m.watchdog_trips
        );
    }
    say!(
        "  final pose x = {:.4} m, y = {:.4} m, θ = {:.4} rad",
        truth.pose.x,
        truth.pose.y,
        truth.pose.theta
    );
    Ok(())
}

fn main() -> ExitCode {
    // A write to a closed pipe must be an error the writer ignores, never a signal that kills
    // the process (the Rust runtime does this too; said here so nobody depends on it).
    // SAFETY: setting a signal's disposition to SIG_IGN before any thread is started.
    unsafe {
        libc::signal(libc::SIGPIPE, libc::SIG_IGN);
        // SIGUSR1/SIGUSR2 mean nothing here; their default action would kill it unsummarised.
        libc::signal(libc::SIGUSR1, libc::SIG_IGN);
        libc::signal(libc::SIGUSR2, libc::SIG_IGN);
    }
    let cli = Cli::parse();
    match run(cli) {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            say!("rollbase-sim: error: {e}");
            ExitCode::from(e.exit_code())
        }
    }
}
