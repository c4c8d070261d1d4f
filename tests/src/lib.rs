//! Shared harness for rollbase's end-to-end tests: runs a scenario through the full frame
//! path (encode → virtual bus → simulated modules → virtual bus → decode) on virtual time.
#![deny(missing_docs)]

pub mod alloc_count;
pub mod campaign;

use rollbase_control::record::CycleRecord;
use rollbase_control::runtime::{
    run_lockstep, ControllerKind, CycleCore, LockstepReport, RunSummary, RuntimeConfig,
    VirtualLockstepBus,
};
use rollbase_control::scenario::{self, Scenario};
use rollbase_control::Platform;
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
    pub waypoints: Option<Vec<rollbase_control::trajectory::Waypoint>>,
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
        }
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
}

/// Builds the controller core, the simulator and the virtual bus for `opts` (the core is not
/// armed yet); also returns the trajectory's duration (s).
pub fn build(opts: &RunOptions) -> Result<(CycleCore, Simulator, VirtualLockstepBus, f64), String> {
    let platform = Platform::justin();
    let traj: Box<dyn rollbase_control::trajectory::Trajectory> = match &opts.waypoints {
        Some(w) => Box::new(
            rollbase_control::trajectory::QuinticSpline::new(&platform, w)
                .map_err(|e| e.to_string())?,
        ),
        None => scenario::trajectory(opts.scenario, &platform).map_err(|e| e.to_string())?,
    };
    let duration = traj.duration();
    let r0 = traj.sample(0.0);
    let core =
        CycleCore::new(platform.clone(), traj, opts.runtime.clone()).map_err(|e| e.to_string())?;
    let sim_p = opts.sim_platform.clone().unwrap_or(platform);
    let sim = if opts.start_at_reference {
        Simulator::new(
            &sim_p,
            opts.plant.clone(),
            opts.faults.clone(),
            &r0,
            opts.seed,
        )
    } else {
        Simulator::with_config(
            &sim_p,
            SimConfig {
                plant: opts.plant.clone(),
                faults: opts.faults.clone(),
                seed: opts.seed,
                ..SimConfig::default()
            },
        )
    }
    .map_err(|e| e.to_string())?;
    let bus = VirtualLockstepBus::new(opts.bus_faults, opts.seed ^ 0x5EED);
    Ok((core, sim, bus, duration))
}

/// Runs the options in lockstep; `sink` sees every record too (e.g. to write MCAP).
pub fn run_with(opts: &RunOptions, sink: &mut dyn FnMut(&CycleRecord, &[[f64; 2]])) -> RunOutcome {
    let (mut core, mut sim, mut bus, duration) = build(opts).expect("valid setup");
    let platform = core.platform().clone();
    let max_cycles = ((duration + opts.slack_s) * platform.cycle_hz) as u64;
    let mut records = Vec::with_capacity(max_cycles as usize);
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
    );
    RunOutcome {
        records,
        summary,
        report,
        platform,
    }
}

/// Runs the options in lockstep.
pub fn run(opts: &RunOptions) -> RunOutcome {
    run_with(opts, &mut |_, _| {})
}
