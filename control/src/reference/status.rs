//! What a reference reports beside its samples: the time scaling's clock
//! ([`ScaleStatus`], [`Timing`]: [`crate::reference::timescale`]) and the singularity
//! avoidance's per-cycle record ([`AvoidanceState`]: [`crate::reference::avoidance`]).
//!
//! Plain values, kept apart from the modules that compute them so that the
//! [`Trajectory`](crate::reference::trajectory::Trajectory) trait can report them without
//! depending on the time scaling or the avoidance (both build on trajectories).

use crate::service::ports::Limiting;
use crate::types::{ZVec, MAX_WHEELS};

/// How fast the clock of a scaled trajectory runs at one instant, and why.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ScaleStatus {
    /// ṡ = dτ/dt (1 = as planned; below 1 slowed down; above 1 only where the timing is free).
    pub scale: f64,
    /// The limit closest to its share there, when the clock runs slower than its cap
    /// (`Limiting::None` otherwise).
    pub limiting: Limiting,
    /// The wheel (0-based) of `limiting`.
    pub wheel: usize,
}

/// The timing of a scaled trajectory, for summaries.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Timing {
    /// Duration of the trajectory as given (s).
    pub nominal_duration_s: f64,
    /// Duration of the scaled trajectory (s), its dwells included.
    pub executed_duration_s: f64,
    /// Duration of the time-optimal timing of the path's motions (s): the passes' timing
    /// before the jerk smoothing, without the dwells ([`Timing::dwell_s`]).
    pub optimal_duration_s: f64,
    /// Planned dwells in all (s): the clock held at the path's stops while the wheels
    /// re-steer ([`crate::reference::timescale::ScaledTrajectory::dwells`]).
    pub dwell_s: f64,
    /// Smallest ṡ.
    pub min_scale: f64,
    /// Executed time (s) of the smallest ṡ.
    pub min_scale_at_s: f64,
    /// What limits the motion there.
    pub limiting: Limiting,
    /// Its wheel (0-based).
    pub wheel: usize,
    /// Largest demand over its share f·limit found by the verification (≤ 1 + the
    /// tolerance unless the repairs ran out).
    pub max_ratio: f64,
    /// The samples carry a steering reference (a wheel the ICR rests on while moving).
    pub steer_reference: bool,
}

/// Per-cycle record of the avoidance (Copy; the runtime records it every cycle).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct AvoidanceState {
    /// The ICR lies inside a wheel's field this cycle (repulsion acting).
    pub active: bool,
    /// The deviation is non-zero (returning to nominal, or being pushed).
    pub deviating: bool,
    /// ICR of the modified reference twist in the body frame (m); `None` at infinity.
    pub icr_body: Option<[f64; 2]>,
    /// Wheel whose singular point is nearest to the ICR (relative to its field radius).
    pub nearest_wheel: Option<usize>,
    /// Smallest ICR–singular-point distance d_i = |u_i|/|θ̇| (m); infinite when θ̇ = 0.
    pub min_distance: f64,
    /// Field radius per wheel this cycle (m), after the no-overlap cap.
    pub d_start: [f64; MAX_WHEELS],
    /// Repulsive force F_rep (m/s) acting this cycle (0 when inactive).
    pub force: f64,
    /// Deviation δ added to z* (m, m, rad, m …), world frame for x, y.
    pub deviation: ZVec,
    /// Deviation rate δ̇ added to ż*.
    pub deviation_rate: ZVec,
    /// Deviation acceleration δ̈ added to z̈* (avoidance output or return loop).
    pub deviation_accel: ZVec,
}

impl Default for AvoidanceState {
    fn default() -> Self {
        Self {
            active: false,
            deviating: false,
            icr_body: None,
            nearest_wheel: None,
            min_distance: f64::INFINITY,
            d_start: [0.0; MAX_WHEELS],
            force: 0.0,
            deviation: ZVec::zeros(),
            deviation_rate: ZVec::zeros(),
            deviation_accel: ZVec::zeros(),
        }
    }
}
