//! Command-line commands: thin adapters over the library crates.
//!
//! One module per job: [`trajectory`] (`demo`, `run`: follow a trajectory), [`service`]
//! (`drive` and the live-command demo: the base service), [`teleop`] (the keyboard as a
//! command source), [`monitor`] (decode frames), [`sinks`] (where a run's records go:
//! summary, recording, candump).
//!
//! Output never kills a run: SIGPIPE is ignored (`main`), and every write to stdout or stderr
//! goes through [`outln!`] / [`errln!`], which drop what a closed pipe cannot take.

/// `println!` that ignores a closed stdout (a run must not die of its output).
macro_rules! outln {
    ($($arg:tt)*) => {{
        use std::io::Write as _;
        let _ = writeln!(std::io::stdout(), $($arg)*);
    }};
}
/// `print!` that ignores a closed stdout.
macro_rules! out {
    ($($arg:tt)*) => {{
        use std::io::Write as _;
        let _ = write!(std::io::stdout(), $($arg)*);
    }};
}
/// `eprintln!` that ignores a closed stderr.
macro_rules! errln {
    ($($arg:tt)*) => {{
        use std::io::Write as _;
        let _ = writeln!(std::io::stderr(), $($arg)*);
    }};
}
/// `eprint!` that ignores a closed stderr.
macro_rules! err {
    ($($arg:tt)*) => {{
        use std::io::Write as _;
        let _ = write!(std::io::stderr(), $($arg)*);
    }};
}

mod monitor;
mod ros2cmd;
mod rt;
mod sdo;
mod service;
mod sinks;
mod teleop;
pub(crate) use teleop::log_writer;
mod trajectory;

use monitor::MonitorArgs;
use service::DriveArgs;
pub(crate) use sinks::exit;
use trajectory::{DemoArgs, RunArgs};

use clap::{Args, Parser, Subcommand};
use rollbase_control::runtime::scenario::{self, Scenario};
use rollbase_control::runtime::RuntimeConfig;
use rollbase_control::{Platform, Protocol};
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
    /// The ROS 2 node could not start.
    #[error(transparent)]
    Ros2(#[from] rollbase::ros2::Ros2Error),
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
    /// A command file or line is not acceptable.
    #[error(transparent)]
    Commands(#[from] rollbase::commands::CommandFileError),
    /// Writing the recording or the candump log failed during the run.
    #[error("recording {path} failed during the run (the run was stopped; what was recorded up to then is kept)")]
    Recording {
        /// The output.
        path: String,
        /// Why.
        #[source]
        source: Box<CliError>,
    },
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
    /// The base driver: follow live motion commands on a CAN bus until SIGINT or SIGTERM.
    Drive(DriveArgs),
    /// Decode frames live from a bus or from a candump log, one line per frame.
    Monitor(MonitorArgs),
    /// Read or write one object of a CANopen device (expedited or segmented SDO), for
    /// bring-up and diagnosis; refused while a master runs on the bus.
    Sdo(sdo::SdoArgs),
    /// Plot a recording to PNG files.
    Plot(PlotArgs),
    /// Rewrite a recording left without index and summary (killed writer) into a new file.
    Recover(ros2cmd::RecoverArgs),
    /// The ROS 2 node fed with a synthetic state (for the interop tests; needs a network).
    #[command(hide = true)]
    Ros2Selftest(ros2cmd::SelftestArgs),
    /// Print every ROS 2 message definition rollbase uses, as JSON {name: full definition}.
    #[command(hide = true)]
    Ros2MsgDefinitions,
    /// Print the robot model (URDF) generated from the platform file: what `--ros2` publishes
    /// on robot_description (for RViz, Foxglove, robot_state_publisher).
    Urdf(UrdfArgs),
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
        /// Print an example platform instead (docs/examples): mpo700 (4 fixed wheels, 45 mm
        /// caster offset, limited steering), three-wheel (fixed, ±170° steering, mirrored
        /// motors), six-wheel (Justin-like legs, two buses).
        #[arg(long, value_name = "mpo700|three-wheel|six-wheel")]
        example: Option<String>,
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
struct UrdfArgs {
    /// Platform file (TOML); default: the built-in Justin-like platform.
    #[arg(long)]
    config: Option<PathBuf>,
    /// Joint names, 3 per wheel (steer,drive,leg), as given to `--ros2-joint-names`.
    #[arg(long = "ros2-joint-names", value_name = "NAMES", value_parser = rollbase::ros2::parse_joint_names)]
    joint_names: Option<rollbase::ros2::JointNames>,
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
        Command::Drive(a) => service::drive(a),
        Command::Monitor(a) => monitor::monitor(a),
        Command::Sdo(a) => sdo::sdo(a),
        Command::Bridge(a) => Ok(crate::bridge::run(a)?),
        Command::Recover(a) => ros2cmd::recover(a),
        Command::Ros2Selftest(a) => ros2cmd::selftest(a),
        Command::Ros2MsgDefinitions => {
            let defs: serde_json::Map<String, serde_json::Value> = rollbase::ros2::msg::ALL
                .iter()
                .map(|d| (d.name.to_string(), d.full_definition().into()))
                .collect();
            outln!("{}", serde_json::Value::Object(defs));
            Ok(0)
        }
        Command::Plot(a) => {
            let rep = rollbase::plot::plot_recording(&a.file, &a.out)?;
            for f in &rep.files {
                outln!("{}", f.display());
            }
            for s in &rep.skipped {
                errln!("skipped {s}");
            }
            for w in &rep.ignored {
                errln!("warning: {w}");
            }
            if !rep.labelled {
                errln!("note: no TTF font found, plots have no text; install fonts-dejavu-core or set ROLLBASE_FONT");
            }
            Ok(0)
        }
        Command::Urdf(a) => {
            let p = load_platform(a.config.as_deref())?;
            let names = a.joint_names.unwrap_or_default();
            let u = rollbase::ros2::urdf::generate(&p, &names)
                .map_err(|e| CliError::Usage(format!("--ros2-joint-names: {e}")))?;
            out!("{u}");
            Ok(0)
        }
        Command::Dbc => {
            out!("{}", rollbase_driver::dbc::dbc());
            Ok(0)
        }
        Command::ProtocolDoc => {
            out!("{}", rollbase_driver::dbc::protocol_markdown());
            Ok(0)
        }
        Command::Cia402Doc => {
            out!("{}", rollbase_driver::canopen::doc::markdown());
            Ok(0)
        }
        Command::BusLoad(a) => {
            let p = load_platform_profile(a.config.as_deref(), a.profile)?;
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
                    out!("{}", rollbase_driver::busload::report(&cfg));
                }
                Protocol::Cia402 => {
                    let l = rollbase_driver::canopen::busload::load(
                        &p.cia402(),
                        p.n(),
                        p.cycle_hz,
                        a.bitrate,
                    );
                    outln!("{l}");
                }
            }
            Ok(0)
        }
        Command::Config { cmd } => match cmd {
            ConfigCmd::Check { file } => {
                let (p, eds) = Platform::load_checked(&file)?;
                outln!(
                    "# {}: valid platform `{}` with {} wheels",
                    file.display(),
                    p.name,
                    p.n()
                );
                for (node, role, path, product, dcf) in &eds.devices {
                    outln!(
                        "# node {node} ({role}): boot plan checked against {path} ({product}){}",
                        if *dcf > 0 {
                            format!(", {dcf} DCF values written at boot")
                        } else {
                            String::new()
                        }
                    );
                }
                for (node, index, sub, why) in &eds.skipped {
                    outln!(
                        "# node {node}: DCF value of 0x{index:04X}:{sub:02X} not written ({})",
                        why.reason()
                    );
                }
                out!("{}", p.to_toml_string());
                Ok(0)
            }
            ConfigCmd::Default { profile, example } => {
                let mut p = match example.as_deref() {
                    None => Platform::justin(),
                    Some(name) => Platform::example(name).ok_or_else(|| {
                        CliError::Usage(format!(
                            "--example {name:?}: give mpo700, three-wheel or six-wheel"
                        ))
                    })?,
                };
                p.protocol = profile;
                if profile == Protocol::Cia402 {
                    p.cia402 = Some(p.cia402());
                }
                out!("{}", p.to_toml_string());
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
    let p = load_platform_profile(path, profile)?;
    if p.buses() > 1 {
        // Two buses would share the one `--bus` medium (two SYNCs a cycle): refused.
        return Err(CliError::Usage(format!(
            "platform `{}` puts wheels on bus 1: running two buses (one `--bus` each) is not implemented yet; put every wheel on `bus = 0` (`rollbase bus-load --config` tells whether they fit)",
            p.name
        )));
    }
    Ok(p)
}

/// [`load_platform_as`] for the commands that only read the platform (bus-load): a platform
/// on two buses is fine there.
fn load_platform_profile(
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

/// What a signal asks of the process.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) enum SignalAction {
    /// Move something: a controlled stop of the platform, then exit.
    ControlledStop,
    /// Move nothing (monitor, tools): just end.
    End,
}

/// Every signal a terminal or a service manager sends to end a process — SIGINT (Ctrl-C),
/// SIGTERM (systemd, `kill`), SIGHUP (the terminal or the ssh session closed) and SIGQUIT
/// (`Ctrl-\`) — sets `stop`, once; the run then stops in a controlled way and finishes its
/// outputs. A second signal is reported and otherwise ignored (a stop in progress is not cut
/// short). SIGUSR1 and SIGUSR2 are ignored from the start (`main`). Returns a flag that tells
/// whether a signal came.
pub(crate) fn install_signals(stop: Arc<AtomicBool>, action: SignalAction) -> Arc<AtomicBool> {
    let came = Arc::new(AtomicBool::new(false));
    let came2 = came.clone();
    // The handlers are installed here, before this returns (a signal that comes right after
    // must find them); a thread then waits for them.
    let Ok(rt) = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
    else {
        tracing::error!(
            "cannot start the signal handler; Ctrl-C, SIGTERM, SIGHUP and SIGQUIT end the process at once"
        );
        return came;
    };
    let signals = {
        use tokio::signal::unix::{signal, SignalKind};
        let _in_runtime = rt.enter();
        (
            signal(SignalKind::interrupt()),
            signal(SignalKind::terminate()),
            signal(SignalKind::hangup()),
            signal(SignalKind::quit()),
        )
    };
    let (Ok(mut int), Ok(mut term), Ok(mut hup), Ok(mut quit)) = signals else {
        tracing::error!("cannot listen for SIGINT/SIGTERM/SIGHUP/SIGQUIT");
        return came;
    };
    std::thread::spawn(move || {
        rt.block_on(async {
            let mut first = true;
            loop {
                let name = tokio::select! {
                    _ = int.recv() => "SIGINT",
                    _ = term.recv() => "SIGTERM",
                    _ = hup.recv() => "SIGHUP",
                    _ = quit.recv() => "SIGQUIT",
                };
                if first {
                    match action {
                        SignalAction::ControlledStop => tracing::warn!(
                            "{name}: controlled stop (the platform decelerates within its limits, steering held), then exit"
                        ),
                        SignalAction::End => tracing::info!(
                            "{name}: ending (this command only listens: nothing on the bus is driven or stopped by it)"
                        ),
                    }
                    came2.store(true, Ordering::SeqCst);
                    stop.store(true, Ordering::SeqCst);
                    first = false;
                } else if action == SignalAction::ControlledStop {
                    tracing::warn!("{name} again: the controlled stop is already under way");
                }
            }
        });
    });
    came
}
