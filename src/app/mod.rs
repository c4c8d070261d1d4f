//! Command-line commands: thin adapters over the library crates.
//!
//! One module per job: [`trajectory`] (`demo`, `run`: follow a trajectory), [`service`]
//! (`drive` and the live-command demo: the base service), [`teleop`] (the keyboard as a
//! command source), [`monitor`] (decode frames), [`sinks`] (where a run's records go:
//! summary, recording, candump), [`common`] (what they share: errors, the run options,
//! loading the platform, signals, readiness). This file only parses and dispatches; the job
//! modules depend on `common`, never on this file, and on each other without a circle.
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

mod common;
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

pub use common::CliError;
use common::{load_platform, load_platform_profile};

use clap::{Args, Parser, Subcommand};
use rollbase_control::{Platform, Protocol};
use std::path::PathBuf;

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
    /// Platform file (its wheels, per bus, and cycle rate are used, and for the CiA 402
    /// profile its `[cia402]` timing); a platform on two buses gets one table per bus.
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
        Command::Demo(a) if a.is_live() => service::demo_live(a),
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
            // One table per bus: each bus carries only its own wheels' frames, with its own
            // SYNC (and, CiA 402, the master's heartbeat) every cycle.
            let nb = p.buses();
            for b in 0..nb {
                let wheels: Vec<usize> = p.wheels_on_bus(b).collect();
                if nb > 1 {
                    let names: Vec<String> = wheels.iter().map(|w| (w + 1).to_string()).collect();
                    outln!(
                        "## bus {b} of {nb} (`bus = {b}`, the {} `--bus`): wheels {}",
                        if b == 0 { "first" } else { "second" },
                        names.join(", ")
                    );
                    outln!();
                }
                match p.protocol {
                    Protocol::Native => {
                        let cfg = rollbase_driver::busload::BusLoadConfig {
                            modules: wheels.len(),
                            cycle_hz: p.cycle_hz,
                            bitrate: a.bitrate,
                            ..Default::default()
                        };
                        out!("{}", rollbase_driver::busload::report(&cfg));
                    }
                    Protocol::Cia402 => {
                        let l = rollbase_driver::canopen::busload::load(
                            &p.cia402(),
                            wheels.len(),
                            p.cycle_hz,
                            a.bitrate,
                        );
                        outln!("{l}");
                    }
                }
                if nb > 1 && b + 1 < nb {
                    outln!();
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
