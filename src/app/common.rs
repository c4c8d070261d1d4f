//! What the commands share: the command line's errors ([`CliError`]), the options of every
//! run ([`CommonRun`]), loading the platform and the run's configuration, the signal handling
//! ([`install_signals`]), the `--ros2` options of `drive` and `demo` ([`Ros2Run`]), the
//! readiness the command sources wait for ([`Ready`]) and the state port's consumers
//! ([`StateConsumer`]). Every job module depends on this one and none on the dispatcher
//! (`app/mod.rs`) or in a circle: `service` (drive and the live demos) uses `teleop` (the
//! keyboard source and status line) and `trajectory` (demo and run), which use only this
//! module, `rt` and `sinks`.

use clap::Args;
use rollbase::ros2::{Ros2Args, Ros2Options};
use rollbase_control::runtime::scenario::{self, Scenario};
use rollbase_control::runtime::{ControllerKind, RuntimeConfig};
use rollbase_control::service::ports::BaseState;
use rollbase_control::{Platform, Protocol};
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

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
    /// The lockstep run could not start.
    #[error(transparent)]
    Lockstep(#[from] rollbase_control::runtime::LockstepError),
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
    /// Experimental: shape live commands as rolling turns (the wheels turn while the base
    /// keeps rolling instead of slowing to re-steer; docs/time-scaling.md, "Rolling turns").
    /// Needs `--controller kinematic`. Trajectories are not affected.
    #[arg(long)]
    pub(crate) rolling_turns: bool,
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

/// A consumer of the state port (on the state thread).
pub(crate) type StateConsumer = Box<dyn FnMut(&BaseState) + Send>;

/// `--ros2` and the node's options, on `drive` and `demo`.
#[derive(Args, Clone, Debug, Default)]
pub(crate) struct Ros2Run {
    /// Be a ROS 2 node (over DDS; no ROS installation needed): take `cmd_vel` and leg
    /// commands, publish odom, tf, joint_states, diagnostics and the supervisor state, serve
    /// ~/stop and ~/rearm. See README "ROS 2". Honours ROS_DOMAIN_ID.
    #[arg(long)]
    pub(crate) ros2: bool,
    #[command(flatten)]
    pub(crate) node: Ros2Args,
}

impl Ros2Run {
    /// The node's options with `--ros2` (checked against the platform's `wheels`), `None`
    /// without it; `--ros2-*` options without `--ros2` are refused rather than ignored.
    pub(crate) fn options(&self, wheels: usize) -> Result<Option<Ros2Options>, CliError> {
        if !self.ros2 {
            if self.node != Ros2Args::default() {
                return Err(CliError::Usage(
                    "--ros2-* options need --ros2 (they configure the ROS 2 node)".into(),
                ));
            }
            return Ok(None);
        }
        let opts = self.node.to_options();
        opts.validate(Some(wheels))?;
        // The domain comes from ROS_DOMAIN_ID when not given: check it now, not after boot.
        opts.resolve_domain_id()?;
        Ok(Some(opts))
    }
}

/// When the driver became ready (first followed commands), shared with the sources.
#[derive(Default)]
pub(crate) struct Ready {
    at: Mutex<Option<Instant>>,
}

impl Ready {
    /// Marks the driver ready (the first time only).
    pub(crate) fn set(&self) {
        if let Ok(mut g) = self.at.lock() {
            g.get_or_insert_with(Instant::now);
        }
    }
    /// Waits until ready or `stop`; returns the instant.
    pub(crate) fn wait(&self, stop: &AtomicBool) -> Option<Instant> {
        loop {
            if stop.load(Ordering::SeqCst) {
                return None;
            }
            if let Ok(g) = self.at.lock() {
                if let Some(t) = *g {
                    return Some(t);
                }
            }
            std::thread::sleep(Duration::from_millis(5));
        }
    }
}

pub(crate) fn load_platform(path: Option<&Path>) -> Result<Platform, CliError> {
    Ok(match path {
        Some(p) => Platform::load(p)?,
        None => Platform::justin(),
    })
}

/// [`load_platform_profile`] for a command that runs the platform on the buses `buses` (the
/// `--bus` options, in order: the b-th serves the wheels with `bus = b`): refused unless
/// there is one per platform bus, each a different bus.
pub(crate) fn load_platform_on(
    path: Option<&Path>,
    profile: Option<Protocol>,
    buses: &[String],
) -> Result<Platform, CliError> {
    let p = load_platform_profile(path, profile)?;
    check_buses(&p, buses)?;
    Ok(p)
}

/// One `--bus` per bus of `p`, each a different one.
pub(crate) fn check_buses(p: &Platform, buses: &[String]) -> Result<(), CliError> {
    if buses.len() != p.buses() {
        return Err(CliError::Usage(format!(
            "platform `{}` puts its wheels on {} CAN bus(es) but {} `--bus` option(s) were given: give one `--bus` per platform bus, in order (the first `--bus` serves the wheels with `bus = 0`, the second those with `bus = 1`)",
            p.name,
            p.buses(),
            buses.len()
        )));
    }
    for (k, b) in buses.iter().enumerate() {
        if buses[..k].contains(b) {
            return Err(CliError::Usage(format!(
                "`--bus {b}` given twice: each platform bus needs its own CAN bus (two SYNCs a cycle on one bus would reach every module)"
            )));
        }
    }
    Ok(())
}

/// The platform file (or the default platform) with the wire profile overridden when
/// `profile` is given, validated again (the `[cia402]` section must fit the platform), for
/// the commands that only read the platform or decode its frames (bus-load, monitor): a
/// platform on two buses is fine there.
pub(crate) fn load_platform_profile(
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
    if common.rolling_turns {
        if cfg.controller != ControllerKind::Kinematic {
            return Err(CliError::Usage(
                "--rolling-turns needs --controller kinematic: the DFL does not track rolling \
                 turns within 5 mm (docs/time-scaling.md, \"Rolling turns\")"
                    .into(),
            ));
        }
        cfg.shaper.rolling_turns = true;
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
