//! The 250 Hz cycle: a sans-IO cycle core, a lockstep driver on virtual time, and the
//! real-time cycle thread. All three share the same step code.
//!
//! One cycle (DESIGN.md "The 250 Hz cycle"):
//!
//! ```text
//!  t_k            t_k + window                                  t_k + period
//!   │ SYNC ──►     │ decode → odometry → reference → avoidance → │
//!   │ feedback ◄── │ controller → supervisor → guard → encode    │
//!   │              │ SETPOINT ──► (one per module)               │
//! ```
//!
//! [`CycleCore`] is the whole cycle minus IO and clocks: [`CycleCore::start_cycle`] returns the
//! SYNC frame, [`CycleCore::on_frame`] takes every received frame, and
//! [`CycleCore::finish_cycle`] runs the control step and returns the setpoint frames and the
//! cycle's [`CycleRecord`](record::CycleRecord). It never allocates after construction.
//!
//! [`run_lockstep`] drives the core and a simulated bus peer (the simulator) on virtual time:
//! deterministic and as fast as the CPU allows. [`run_realtime`] drives it from a cycle thread
//! with absolute deadlines (`clock_nanosleep(CLOCK_MONOTONIC, TIMER_ABSTIME)`), optionally
//! SCHED_FIFO and locked memory, and hands records to a recorder over a bounded channel with
//! `try_send` (a full channel drops the record and counts it: the cycle never blocks on IO).
//!
//! The module is split by job: `core` (the cycle without IO), [`link`] (the cycle's wire
//! side, native or CiA 402), `lockstep` (virtual time), `realtime` (the cycle thread),
//! [`command_channel`](mod@command_channel) (commands into the cycle thread, with a priority lane for stop and
//! re-arm), [`record`] (the per-cycle record), `summary` (the figures of a run) and
//! [`scenario`] (the named runs: trajectory and configuration together); the items of the
//! private modules are re-exported here.

pub mod command_channel;
mod core;
pub mod link;
mod lockstep;
mod realtime;
pub mod record;
pub mod scenario;
mod summary;

pub use self::command_channel::{command_channel, CommandReceiver, CommandSender};
pub use self::core::{check_feasible, CycleCore, DFL_ENTRY_SPEED, FAULT_RESET_CYCLES};
pub use self::lockstep::{
    lockstep_cycle, lockstep_cycle_buses, run_lockstep, run_lockstep_buses, run_lockstep_live,
    run_lockstep_with, LockstepBus, LockstepError, LockstepPeer, LockstepReport, LockstepState,
    StepHooks, VirtualLockstepBus,
};
pub use self::realtime::{
    realtime_setup, run_realtime, run_realtime_buses, run_realtime_io, RealtimeError, RealtimeIo,
    RealtimeOptions, RealtimeReport, MAX_COMMANDS_PER_CYCLE,
};
pub use self::summary::{percentile, RunSummary, TimeHistogram};

use crate::num::{Fixed3, Num};
use crate::reference::avoidance::AvoidanceConfig;
use crate::supervisor::SupervisorConfig;
use rollbase_driver::bus::BusError;
use rollbase_driver::rx::CounterPolicy;

/// Which tracking controller the runtime uses.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum ControllerKind {
    /// Dynamic feedback linearization (seed 000).
    Dfl,
    /// Kinematic tracking with inverse kinematics.
    Kinematic,
}

impl std::str::FromStr for ControllerKind {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        match s {
            "dfl" => Ok(Self::Dfl),
            "kinematic" | "kin" => Ok(Self::Kinematic),
            other => Err(format!(
                "unknown controller `{other}`: use `dfl` or `kinematic`"
            )),
        }
    }
}

/// Runtime options shared by lockstep and real time.
#[derive(Clone, Debug)]
pub struct RuntimeConfig {
    /// Tracking controller.
    pub controller: ControllerKind,
    /// Singularity avoidance (`None` = off).
    pub avoidance: Option<AvoidanceConfig>,
    /// Supervisor thresholds.
    pub supervisor: SupervisorConfig,
    /// Feedback collection window inside the cycle (s after SYNC).
    pub feedback_window: f64,
    /// Counter policy of the receive path. The default accepts a frame after a counter jump
    /// (and counts the loss) so one lost frame costs one frame, not two.
    pub counter_policy: CounterPolicy,
    /// Cycles to stay in Stopped/Fault at rest before the run reports itself done.
    pub linger_cycles: u32,
    /// The live-command shaper's tunables (base service).
    pub shaper: crate::reference::shaper::ShaperConfig,
    /// Bus bit rate (bit/s), for the measured bus load on the state port.
    pub bitrate: u32,
    /// Time scaling of pre-planned trajectories ([`crate::reference::timescale`]): every trajectory is
    /// run on a clock that keeps each actuator within its share of its limits (`None`: as
    /// given, and refused if it exceeds a speed limit). Default on, with the shaper's margins.
    pub time_scaling: Option<crate::reference::timescale::TimeScaleConfig>,
}

impl Default for RuntimeConfig {
    fn default() -> Self {
        Self {
            controller: ControllerKind::Dfl,
            avoidance: None,
            supervisor: SupervisorConfig::default(),
            feedback_window: rollbase_driver::busload::DEFAULT_FEEDBACK_WINDOW_S,
            counter_policy: CounterPolicy::AcceptWithLoss,
            linger_cycles: 25,
            shaper: crate::reference::shaper::ShaperConfig::default(),
            bitrate: 1_000_000,
            time_scaling: Some(crate::reference::timescale::TimeScaleConfig::default()),
        }
    }
}

impl RuntimeConfig {
    /// Checks the options against the platform's control period: the feedback window must
    /// leave the cycle its compute budget, the supervisor's thresholds their ranges. Errors
    /// name the option, the value and the bound.
    pub fn validate(&self, p: &crate::model::platform::Platform) -> Result<(), RuntimeError> {
        let dt = p.dt();
        let max_window = dt - crate::model::platform::CYCLE_COMPUTE_BUDGET_S;
        if !(self.feedback_window.is_finite()
            && self.feedback_window > 0.0
            && self.feedback_window <= max_window)
        {
            return Err(RuntimeError::Option {
                field: "feedback_window",
                value: Num(self.feedback_window).to_string(),
                reason: format!(
                    "must be > 0 and at most the period minus the compute budget ({} s at cycle_hz = {})",
                    Num(max_window),
                    Num(p.cycle_hz)
                ),
            });
        }
        if let (ControllerKind::Dfl, Some((i, w))) = (
            self.controller,
            p.wheels.iter().enumerate().find(|(_, w)| w.off_centred()),
        ) {
            // The DFL's decoupling (seed 000 eq. 23, crate::tracking::dfl) is derived for centred
            // steering, where each wheel's angle is a function of ż. With an offset the angles
            // are states of their own (crate::model::kinematics, "Off-centred steering").
            return Err(RuntimeError::Option {
                field: "controller",
                value: "dfl".into(),
                reason: format!(
                    "the DFL is derived for centred steering, but wheels[{i}].caster_offset = {} m: use the kinematic controller (`--controller kinematic`), which commands off-centred wheels by the exact caster law",
                    Num(w.caster_offset)
                ),
            });
        }
        self.supervisor
            .validate(dt)
            .map_err(|(field, value, reason)| RuntimeError::Option {
                field,
                value,
                reason,
            })
    }

    /// The default controller for a platform: the DFL (seed 000's), or the kinematic
    /// controller on a platform with off-centred wheels (which the DFL does not cover).
    pub fn for_platform(mut self, p: &crate::model::platform::Platform) -> Self {
        if p.has_caster_offset() {
            self.controller = ControllerKind::Kinematic;
        }
        self
    }
}

/// Errors that stop a run before or while it starts.
#[derive(Debug, thiserror::Error)]
pub enum RuntimeError {
    /// The trajectory and the platform disagree.
    #[error("trajectory has {traj} legs but the platform has {platform} wheels")]
    LegCount {
        /// Legs in the trajectory.
        traj: usize,
        /// Wheels on the platform.
        platform: usize,
    },
    /// The platform description is invalid.
    #[error(transparent)]
    Config(#[from] crate::model::platform::ConfigError),
    /// The bus failed in a way the run cannot continue from.
    #[error("bus error: {0}")]
    Bus(#[from] BusError),
    /// The trajectory needs more than a limit of the platform allows.
    #[error("infeasible trajectory: at t = {} s wheel {} needs {} but `limits.{field}` = {}; slow the trajectory down or raise the limit in the platform file", Fixed3(*t), wheel + 1, Fixed3(*value), Fixed3(*limit))]
    Infeasible {
        /// The limit's field name in the platform file.
        field: &'static str,
        /// Wheel index (0-based).
        wheel: usize,
        /// Time of the first violating sample (s).
        t: f64,
        /// The value the trajectory needs.
        value: f64,
        /// The limit.
        limit: f64,
    },
    /// The trajectory needs what no timing can fix (a leg out of range, a corner without a
    /// stop), or would last too long slowed into the limits.
    #[error(transparent)]
    TimeScale(#[from] crate::reference::timescale::TimeScaleError),
    /// The avoidance applied to the trajectory before the run did not return to it
    /// ([`crate::reference::avoidance::AvoidedTrajectory`]).
    #[error(transparent)]
    Avoidance(#[from] crate::reference::avoidance::AvoidanceError),
    /// The trajectory's duration is not a finite time the runtime can check and run.
    #[error("the trajectory lasts {} s: it must be a finite time of at most {} s (10 h); split longer runs", Num(*duration), crate::reference::trajectory::MAX_WAYPOINT_TIME_S)]
    Duration {
        /// The duration (s).
        duration: f64,
    },
    /// A runtime option is out of its range.
    #[error("runtime option `{field}` = {value}: {reason}")]
    Option {
        /// The option's name (e.g. `feedback_window`, `supervisor.follow_timeout`).
        field: &'static str,
        /// The value, printed.
        value: String,
        /// What is wrong and what is expected.
        reason: String,
    },
}
