//! Named scenarios (the demo's and `rollbase run --trajectory scenario:NAME`) and the runtime
//! settings that go with them.

use crate::avoidance::AvoidanceConfig;
use crate::platform::Platform;
use crate::runtime::RuntimeConfig;
use crate::trajectory::{load_waypoints, seed000_experiment, Trajectory, TrajectoryError};

/// The built-in scenarios.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Scenario {
    /// Seed 000, Sect. V: ξ (0, 0, 0) → (4.5 m, 4.5 m, 2π) with the legs 0.37 → 0.56 m.
    Seed000,
    /// Seed 001, Sect. V: a fast rotation whose nominal ICR passes close to the wheels.
    Seed001,
}

/// Every scenario name, for help texts and errors.
pub const SCENARIO_NAMES: [&str; 2] = ["seed000", "seed001"];

impl Scenario {
    /// The scenario's name.
    pub fn name(self) -> &'static str {
        match self {
            Self::Seed000 => "seed000",
            Self::Seed001 => "seed001",
        }
    }
}

/// Errors choosing or loading a trajectory.
#[derive(Debug, thiserror::Error)]
pub enum ScenarioError {
    /// Unknown scenario name.
    #[error("unknown scenario `{0}`: use one of seed000, seed001")]
    Unknown(String),
    /// The trajectory file is invalid.
    #[error(transparent)]
    Trajectory(#[from] TrajectoryError),
}

impl std::str::FromStr for Scenario {
    type Err = ScenarioError;
    fn from_str(s: &str) -> Result<Self, ScenarioError> {
        match s {
            "seed000" | "seed-000" | "000" => Ok(Self::Seed000),
            "seed001" | "seed-001" | "001" => Ok(Self::Seed001),
            other => Err(ScenarioError::Unknown(other.into())),
        }
    }
}

/// The scenario's reference trajectory for a platform.
pub fn trajectory(s: Scenario, p: &Platform) -> Result<Box<dyn Trajectory>, ScenarioError> {
    Ok(match s {
        Scenario::Seed000 => Box::new(seed000_experiment(p)),
        Scenario::Seed001 => Box::new(crate::avoidance::Seed001Scenario::new(p)),
    })
}

/// `scenario:NAME` or a waypoint file path.
pub fn trajectory_arg(
    arg: &str,
    p: &Platform,
) -> Result<(Box<dyn Trajectory>, Option<Scenario>), ScenarioError> {
    if let Some(name) = arg.strip_prefix("scenario:") {
        let s: Scenario = name.parse()?;
        return Ok((trajectory(s, p)?, Some(s)));
    }
    Ok((Box::new(load_waypoints(p, arg)?), None))
}

/// Runtime settings for a scenario. Seed 000 uses the DFL controller (the paper's). Seed 001
/// runs with avoidance (legs free) and the kinematic controller: its trajectory starts a
/// pure rotation from rest, where the DFL is singular (det H ∝ v_W) and its start-up
/// transient saturates the wheel spin (limit ratio ≈ 58 at t ≈ 0.16 s on the ideal plant,
/// leaving 4.4 cm of tracking error), while the kinematic controller tracks it within
/// 0.7–1.4 cm (docs/avoidance.md). Seed 001's nominal is not time-scaled (time scaling off):
/// its nominal ICR passes 2.5 cm from the wheels on purpose, asking 2.9× the steering rate
/// and 5.3× the steering acceleration limit, and the experiment is the avoidance that
/// reshapes it; slowed down first it would no longer be that experiment
/// (docs/time-scaling.md). The avoidance acts on the nominal at its own timing, and the
/// path it makes is then time-scaled within every limit, whatever this option says
/// ([`crate::avoidance`], "Pre-planned trajectories"); with `--avoidance off` the nominal
/// runs as given.
pub fn runtime_config(s: Scenario) -> RuntimeConfig {
    let mut cfg = RuntimeConfig::default();
    if s == Scenario::Seed001 {
        cfg.avoidance = Some(AvoidanceConfig::default());
        cfg.controller = crate::runtime::ControllerKind::Kinematic;
        cfg.time_scaling = None;
    }
    cfg
}

/// The default controller's command-line name for a scenario.
pub fn default_controller(s: Scenario) -> &'static str {
    match s {
        Scenario::Seed000 => "dfl",
        Scenario::Seed001 => "kinematic",
    }
}

/// Parses `--avoidance on|off|locked|free`.
pub fn avoidance_mode(arg: &str) -> Result<Option<AvoidanceConfig>, String> {
    match arg {
        "off" => Ok(None),
        "on" | "free" => Ok(Some(AvoidanceConfig {
            legs_free: true,
            ..AvoidanceConfig::default()
        })),
        "locked" => Ok(Some(AvoidanceConfig {
            legs_free: false,
            ..AvoidanceConfig::default()
        })),
        other => Err(format!(
            "--avoidance {other}: use on (legs free), locked (legs locked) or off"
        )),
    }
}
