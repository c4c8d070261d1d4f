//! Command-line commands: thin adapters over the library crates.
//!
//! One module per job: [`trajectory`] (`demo`, `run`: follow a trajectory), [`monitor`]
//! (decode frames), [`sinks`] (where a run's records go: summary, recording, candump).

mod monitor;
mod sinks;
mod trajectory;

use monitor::MonitorArgs;
use trajectory::{DemoArgs, RunArgs};

use clap::{Args, Parser, Subcommand};
use rollbase_control::runtime::RuntimeConfig;
use rollbase_control::scenario::{self, Scenario};
use rollbase_control::{Platform, Protocol};
use std::io::Write;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;

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
    Record(#[from] rollbase::record::RecordError),
    /// Plotting failed.
    #[error(transparent)]
    Plot(#[from] rollbase::plot::PlotError),
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
pub(crate) struct CommonRun {
    /// Platform file (TOML); default: the built-in Justin-like platform.
    #[arg(long)]
    pub(crate) config: Option<PathBuf>,
    /// Tracking controller: dfl (seed 000) or kinematic; default: the scenario's (seed000: dfl,
    /// seed001: kinematic) or dfl for a waypoint file.
    #[arg(long)]
    pub(crate) controller: Option<String>,
    /// Singularity avoidance: on, off, locked (legs locked) or the scenario's default.
    #[arg(long)]
    pub(crate) avoidance: Option<String>,
    /// Write an MCAP recording of the run.
    #[arg(long)]
    pub(crate) record: Option<PathBuf>,
    /// Write every frame on the bus to a candump -L log.
    #[arg(long)]
    pub(crate) candump: Option<PathBuf>,
    /// Write PNG plots of the run into this directory (implies a recording).
    #[arg(long)]
    pub(crate) plots: Option<PathBuf>,
    /// Print one JSON object with the run's summary instead of the table.
    #[arg(long)]
    pub(crate) json: bool,
    /// Wire profile: native (rollbase wheel modules) or cia402 (CANopen CiA 402 drives and
    /// CiA 406 leg encoders); default: the platform file's `protocol`.
    #[arg(long)]
    pub(crate) profile: Option<Protocol>,
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
        Command::Demo(a) => trajectory::demo(a),
        Command::Run(a) => trajectory::run_bus(a),
        Command::Monitor(a) => monitor::monitor(a),
        Command::Bridge(a) => Ok(crate::bridge::run(a)?),
        Command::Plot(a) => {
            let rep = rollbase::plot::plot_recording(&a.file, &a.out)?;
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

pub(crate) fn load_platform(path: Option<&Path>) -> Result<Platform, CliError> {
    Ok(match path {
        Some(p) => Platform::load(p)?,
        None => Platform::justin(),
    })
}

/// The platform file (or the default platform) with the wire profile overridden when
/// `profile` is given, validated again (the `[cia402]` section must fit the platform).
pub(crate) fn load_platform_as(
    path: Option<&Path>,
    profile: Option<Protocol>,
) -> Result<Platform, CliError> {
    let mut p = load_platform(path)?;
    if let Some(pr) = profile {
        p.protocol = pr;
        p.validate()?;
    }
    Ok(p)
}

pub(crate) fn runtime_config(
    common: &CommonRun,
    sc: Option<Scenario>,
) -> Result<RuntimeConfig, CliError> {
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

pub(crate) fn unix_now() -> f64 {
    std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map(|d| d.as_secs_f64())
        .unwrap_or(0.0)
}

/// What Ctrl-C stops: said to the operator when it arrives.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) enum StopKind {
    /// A run that drives the platform: Ctrl-C is a controlled stop (decelerate, then exit).
    Platform,
    /// A tool that only listens (the monitor): nothing moves, Ctrl-C just ends it.
    Listener,
}

/// Sets `stop` on the first Ctrl-C and tells the operator what that does (`kind`).
pub(crate) fn install_ctrl_c(stop: Arc<AtomicBool>, kind: StopKind) {
    std::thread::spawn(move || {
        let Ok(rt) = tokio::runtime::Builder::new_current_thread()
            .enable_all()
            .build()
        else {
            return;
        };
        rt.block_on(async {
            if tokio::signal::ctrl_c().await.is_ok() {
                let msg = match kind {
                    StopKind::Platform => "\nCtrl-C: controlled stop (Ctrl-C again is ignored; the platform is decelerating)",
                    StopKind::Listener => "\nCtrl-C: stopping the monitor (it only listens: nothing on the bus is driven or stopped by it)",
                };
                // A closed stderr must not stop the stop.
                let _ = writeln!(std::io::stderr(), "{msg}");
                stop.store(true, Ordering::SeqCst);
            }
        });
    });
}
