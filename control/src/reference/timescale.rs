//! Time scaling of pre-planned trajectories (seed 004's remedy for references the actuators
//! cannot follow: keep the path, slow its execution), and the time-optimal timing of
//! waypoints given without times. The derivation in full, with a figure:
//! docs/time-scaling.md.
//!
//! # The scaled reference
//!
//! A trajectory z*(τ) is a path with a nominal clock τ ∈ [0, T]. [`ScaledTrajectory`] runs it
//! on a clock τ(t) that advances at the rate ṡ = dτ/dt > 0 chosen offline, before the run:
//! the executed reference is z(t) = z*(τ(t)) and, by the chain rule (primes are d/dτ),
//!
//! ```text
//! ż = z*' ṡ
//! z̈ = z*'' ṡ² + z*' s̈
//! z⃛ = z*''' ṡ³ + 3 z*'' ṡ s̈ + z*' s⃛
//! ```
//!
//! The path is unchanged; only its timing stretches. ṡ and s̈ are continuous and s⃛ bounded,
//! so z is C² with bounded jerk wherever z* is, as the DFL of seed 000 needs (its
//! feed-forward is z̈*, seed 000 eq. 25).
//!
//! # What a timing asks of the actuators
//!
//! Wheel i's contact velocity is linear in ż for a given z ([`crate::reference::limits`], seed 000 eq.
//! 18), so along the scaled reference u_i = w_i ṡ with w_i(τ) the contact velocity of the
//! nominal path at ṡ = 1 (w_i', w_i'' its τ-derivatives: [`contact_kinematics`] of the
//! nominal sample). Its direction φ_i = atan2(w_i) does not depend on the timing. With
//! φ' = dφ/dτ and φ'' from [`direction_rates`] (the limits module's steering rate and
//! acceleration formulas, in τ), every demand is linear in ṡ, in x = ṡ², or in (x, s̈):
//!
//! ```text
//! wheel speed           |w| ṡ / r                     ≤ f_v ω_max
//! steering rate         |φ'| ṡ                        ≤ f_v φ̇_max
//! leg speed             |λ'| ṡ                        ≤ f_v λ̇_max
//! lateral acceleration  |w| |φ'| x                    ≤ a_lat
//! wheel acceleration    |(w·w'/|w|) x + |w| s̈| / r    ≤ f_a ω̇_max
//! steering accel.       |φ'' x + φ' s̈|                ≤ f_a φ̈_max
//! ```
//!
//! The margins ([`TimeScaleConfig`]): f_v = 0.9, the live-command shaper's `speed_fraction`
//! (the controller's corrections and the drives' lag compensation need room); f_a = 0.5 and
//! a_lat = 0.5 m/s², measured: the residual lag of the steering and rolling drives turns
//! sustained acceleration and turning into tracking error, and with these the lockstep runs
//! stay within the issue's bounds with room to spare (docs/time-scaling.md, "Margins").
//!
//! At its start and end the platform stands still with its steering at rest, so there the
//! steering rate |φ'| ṡ may be at most one control cycle's change at the acceleration share
//! (f_a φ̈_max Δt): a path whose wheels turn as they leave rest starts with ṡ near 0 and
//! speeds up within the steering acceleration.
//!
//! # Planning (TOPP on a grid)
//!
//! 1. **Grid.** τ_j every 2 ms ([`GRID_STEP`]; at most [`MAX_GRID`] points), refined where a
//!    wheel's direction turns by more than 0.1 rad between two points or its contact
//!    velocity passes close to zero between them (the linearised closest approach, as the
//!    shaper refines its transitions). At each point the speed-type constraints and a cap
//!    bound x (the *maximum velocity curve* x̄_j); so do two acceleration constraints whose
//!    admissible s̈ intervals [L(x), U(x)] stop overlapping (a path whose curvature needs
//!    steering acceleration at any speed). The cap is 1 where the trajectory's timing is
//!    given (the scaling only slows down) and [`TimeScaleConfig::free_scale_cap`] where it
//!    is free (waypoints without a time).
//! 2. **Backward pass.** With constant s̈ on [τ_j, τ_{j+1}], x_{j+1} = x_j + 2 Δτ s̈. The
//!    largest x_j from which the next point can still be reached below its bound K_{j+1},
//!    decelerating as hard as allowed: K_N = x̄_N and
//!    `K_j = max { x ≤ x̄_j : x + 2 Δτ L_j(x) ≤ K_{j+1} }`. L_j(x) = max_k (p_k + q_k x) is a
//!    maximum of affine functions, so each constraint gives the closed form
//!    x ≤ (K_{j+1} − 2 Δτ p_k)/(1 + 2 Δτ q_k) (when the denominator is positive; otherwise
//!    the constraint cannot bind, as L_k(0) ≤ 0).
//! 3. **Forward pass.** From x_0 = K_0, accelerate as hard as allowed within the
//!    controllable bounds: x_{j+1} = min(K_{j+1}, x_j + 2 Δτ U_j(x_j)). This is the
//!    time-optimal x(τ) on the grid (the numerical-integration form of TOPP; with one path
//!    parameter and constraints affine in (x, s̈) the reachable and controllable sets of
//!    TOPP-RA are these intervals). The passes plan with 90 % of the acceleration shares,
//!    room for the smoothing.
//! 4. **Smoothing (jerk limit).** The time-optimal ṡ is piecewise linear in its own time t'
//!    (s̈ constant per interval), so s̈ jumps. It is *eroded* (the minimum over a window of
//!    `jerk_time` plus one sample in t', exact for the piecewise-linear profile) and then
//!    averaged over `jerk_time`: every averaged value is a mean of minima over windows that
//!    contain the point, so the result never exceeds the time-optimal ṡ (every speed-type
//!    constraint holds exactly at the grid points), and s̈ becomes continuous, building up
//!    over at least `jerk_time` (40 ms, the shaper's). The result is read back as ṡ_j at
//!    the grid points (a profile in τ: the speed bounds are bounds in τ).
//! 5. **Clock.** Executed times t_j from dt = dτ/ṡ (ṡ² linear in τ between grid points),
//!    s̈_j = ṡ_j dṡ/dτ; the clock is the quintic Hermite interpolant of (τ_j, ṡ_j, s̈_j) at
//!    the t_j: τ(t) is C² with bounded s⃛ and meets every knot exactly.
//! 6. **Verification and repair.** Every demand is evaluated at every grid point and at three
//!    points between each two (from the inner sample and the clock by the chain rule, the same numbers as
//!    [`crate::reference::limits::wheel_demand`] of the scaled sample). Where one exceeds its share by more than
//!    [`VERIFY_TOLERANCE`], x̄ is lowered over the path within twice the jerk time of it (by
//!    the ratio, squared for speed-type limits) and steps 2–6 run again, at most
//!    [`MAX_REPAIRS`] times. [`Timing::max_ratio`] reports what remains.
//!
//! **Bit-identical when nothing saturates.** If the smooth profile is ṡ ≡ 1 exactly, the
//! scaled trajectory passes every sample of the inner one through unchanged (τ = t, no
//! re-accumulation): the seed-000 experiment sends the same commands, bit for bit.
//!
//! # Steering: the wheels the ICR rests on, stops, branches
//!
//! Where a wheel barely moves compared with the fastest wheel (|w_i| < `hold_ratio` · max_k
//! |w_k|: the ICR on or next to it, a pivot about it) its direction of travel is not worth
//! steering by. Over such a stretch the wheel's steering angle is the quintic Hermite blend
//! (in τ, matching angle, dφ/dτ and d²φ/dτ²) from the direction it had before to the one it
//! will have after, taken on the branch (±π) nearest the first: a wheel the ICR sweeps
//! across keeps its angle and reverses its roll direction, and a wheel the platform pivots
//! about holds its angle. Elsewhere the angle is the direction of travel, continued across
//! the branches (a wheel whose contact velocity passes through zero along a line keeps its
//! angle and rolls backwards after); where the whole platform is at rest at the path's start
//! or end it is the limit of the directions next to it. The samples carry this angle, its
//! rate and its acceleration as the [`SteerReference`] (whenever the clock is not ṡ ≡ 1,
//! and whenever a wheel is held while the platform moves or the platform stops between two
//! motions). The controllers follow it for wheels slower than [`crate::reference::limits::HOLD_SPEED`]
//! ([`crate::tracking::dfl::held_wheels`]), so such a wheel neither chatters nor flips, nor turns
//! after the feedback's corrections near rest. The blends' rates and accelerations are
//! limited like any other steering demand.
//!
//! # Stops and dwells
//!
//! Seed 004 keeps the direction of the operational motion and changes only the speed of
//! its execution (Sect. 4.1). At a point where the path itself stops (ż = 0: a repeated
//! waypoint, a reversal, the start and the end) there is no direction to keep: a wheel's
//! direction of travel u_i/|u_i| is 0/0 there, and along the path next to it the direction
//! turns at dφ/dτ = (u × u')/|u|², which grows like 1/|u| as the speed goes to zero. A
//! clock that kept every wheel's steering rate within its share would have to crawl,
//! ṡ → 0, into the stop and out of it — an unbounded duration (the 1e147 s plans).
//!
//! Instead the path is cut at its exact stops ([`Trajectory::stops`] and the rests at its
//! ends): each piece between two stops is timed on its own, from rest to rest, and at each
//! stop the clock holds for a **dwell** while every wheel steers from the direction it
//! arrived in to the direction it leaves in. Both are limits, well defined where the first
//! derivative vanishes: with u(τ₀) = 0 and u'(τ₀) ≠ 0, u(τ) ≈ u'(τ₀)(τ − τ₀), so the
//! direction tends to ±u'(τ₀)/|u'(τ₀)| (the sign of τ − τ₀ picks the side); where u' also
//! vanishes, the first non-zero derivative gives it (taken in practice from the points next
//! to the stop). The dwell's steering is the quintic in executed time matching the steering
//! angle, rate and acceleration of the pieces on either side, on the branch nearest the
//! arrival angle; its duration is the shortest for which the quintic's
//! rate and acceleration stay within the steering shares (`dwell_duration`). A stop, a
//! corner at a stop, a reversal, a start from rest thus cost a bounded dwell.
//!
//! A path that only nearly stops — the fastest wheel slower than [`NEAR_REST`] at the
//! clock's cap over less than [`NEAR_REST_TRAVEL`] of travel, inside a piece (a corner whose
//! waypoints are a few millimetres apart) — has the same problem without an exact stop to
//! cut at: its wheels' steering there is blended from the direction before to the one after
//! (the Hermite blend of the previous section for every wheel), and the clock slows so that
//! the blend stays within the steering shares. The run by which a piece leaves or reaches
//! its exact stop is blended the same way only where some wheel's direction turns by more
//! than 2° along it (a path that starts straight from rest, like seed 000, is followed as
//! it is). These stretches are reported with the dwells
//! ([`ScaledTrajectory::dwells`], [`Timing::dwell_s`] counts only the true dwells).
//!
//! # Steering ranges
//!
//! A wheel with a steering range ([`crate::angle::SteerRange`], cable stops) cannot follow
//! a direction that keeps turning: seed 000 turns a fixed-footprint platform a full turn
//! while it translates, so each wheel's direction relative to the body turns a full turn
//! too, past ±170° stops. Each direction has two branches, φ and φ + π (rolling backwards);
//! a piece of the path whose angles span [lo, hi] fits inside [min, max] on a branch
//! φ + mπ exactly when some integer m satisfies min − lo ≤ mπ ≤ max − hi (`branches_inside`).
//! A range wider than π always leaves room for a span up to (max − min) − π; beyond that
//! the wheel must turn back while it does not roll — at a stop of the platform, since on a
//! rigid body no wheel stops rolling on its own unless the ICR sits on it.
//!
//! So the planner adds stops (`range_stops`): walking each motion's grid from its start,
//! it cuts at the last point up to which every ranged wheel's angles still fit on some
//! branch, then repeats on the rest (at most `MAX_RANGE_STOPS` = 256 cuts). A cut lies where
//! the path moves, so the clock is brought to ṡ = 0 there (the piece ends at rest in
//! executed time: its last grid point's ṡ bound is 0) and restarts from ṡ = 0 after it. Each
//! piece is then put on the branch inside the range nearest where the wheel was (the first
//! piece: nearest the range's centre, where homing leaves it), and the dwell at the cut
//! turns the wheel from its arrival angle to its departure angle — about half a turn, the
//! other branch — with the dwell's quintic, which is monotonic between two rests and so
//! never leaves the range. A path that fits adds no stop: the plan of a platform without
//! ranges, or of a path within them, is unchanged bit for bit.
//!
//! A dwell's steering is followed by the controllers as any held wheel's: the kinematic
//! controller does not report an interior rest finished while the steering reference still
//! moves or a wheel is off it ([`crate::tracking::kinematic`]).
//!
//! # What no timing can fix
//!
//! [`ScaledTrajectory::plan`] (and [`check_fixable`]) refuses, naming the waypoint when the
//! trajectory has waypoints, and the cause: a leg outside its range, and a kink in the
//! direction of travel of a moving wheel (the direction jumps while the wheel rolls: an
//! infinite steering rate at any speed). The quintic splines of [`crate::reference::trajectory`] are
//! C², so their wheels' directions only jump where the wheel's contact velocity passes
//! through zero, which is a roll reversal, not a kink; other trajectories are checked
//! (bisection of a suspicious interval: a jump that does not shrink with it is a kink). A
//! timing that would take longer than [`MAX_EXECUTED_S`] is refused too, naming the limit.

// Index loops over parallel per-wheel arrays read better than zipped iterators here.
#![allow(clippy::needless_range_loop)]

use crate::model::platform::Platform;
use crate::reference::limits::{
    contact_kinematics, direction_rates, DEFAULT_JERK_TIME, DEFAULT_SPEED_FRACTION, HOLD_SPEED,
};
use crate::reference::status::{ScaleStatus, Timing};
use crate::reference::trajectory::{eval_quintic, quintic, Trajectory};
use crate::service::ports::Limiting;
use crate::types::{ReferenceSample, SteerReference, MAX_WHEELS};
use std::f64::consts::{FRAC_PI_2, PI};

/// Base grid step in path time τ (s); the grid is refined where a wheel's direction turns
/// quickly.
pub const GRID_STEP: f64 = 0.002;
/// Largest number of grid points (longer trajectories get a coarser base grid).
pub const MAX_GRID: usize = 1 << 17;
/// Relative excess of a demand over its share f·limit that the verification accepts.
pub const VERIFY_TOLERANCE: f64 = 0.01;
/// Largest number of verification-and-repair rounds.
pub const MAX_REPAIRS: usize = 16;
/// Longest executed duration (s): 10 h, as for a trajectory's waypoint times
/// ([`crate::reference::trajectory::MAX_WAYPOINT_TIME_S`]).
pub const MAX_EXECUTED_S: f64 = crate::reference::trajectory::MAX_WAYPOINT_TIME_S;
/// A platform whose fastest wheel moves slower than this along the path (m/s at ṡ = 1) is at
/// rest there (its wheels' directions are taken from the neighbouring points).
const REST_W: f64 = 1e-9;
/// Speed (m/s) of the fastest wheel at the clock's cap below which the platform is near a
/// stop: its wheels' directions of travel are not steered by, they blend from the one before
/// to the one after (the clock slows to let them turn within their limits: a planned dwell
/// at a near stop, [`ScaledTrajectory::dwells`]).
pub const NEAR_REST: f64 = 0.5 * HOLD_SPEED;
/// Turn (rad) of a wheel's direction of travel along a near stop at a piece's end beyond
/// which the run is blended like a near stop inside the piece (module docs, "Stops and
/// dwells").
const END_RUN_TURN: f64 = 0.035;
/// Longest travel (m) of the platform along a near stop.
pub const NEAR_REST_TRAVEL: f64 = 0.005;
/// Direction change (rad) between two grid points beyond what the steering rate explains
/// that is examined as a possible kink.
const KINK_SUSPECT: f64 = 0.05;
/// Largest direction change (rad) of a wheel between two grid points after refinement.
const REFINE_ANGLE: f64 = 0.1;
/// Most points inserted into one base interval.
const REFINE_MAX: usize = 64;

/// Margins and options of the time scaling (defaults documented per field).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct TimeScaleConfig {
    /// Fraction of the speed-type limits (wheel speed, steering rate, leg speed) the scaled
    /// reference may use. Default: the shaper's `speed_fraction` (0.9): the controller's
    /// corrections and the drives' lag compensation need the rest.
    pub speed_fraction: f64,
    /// Fraction of the acceleration limits (wheel, steering) it may use. Default 0.5, below
    /// the shaper's 0.6: a live command's transitions are straight lines in velocity space
    /// that end at rest in acceleration, while a path's curvature can hold a wheel at its
    /// acceleration share for long stretches, and the residual drive lag turns sustained
    /// acceleration into tracking error (docs/time-scaling.md, "Margins").
    pub accel_fraction: f64,
    /// Time (s) over which s̈ may build up at ṡ = 1 (bounds the jerk). Default: the shaper's
    /// `jerk_time` (40 ms).
    pub jerk_time: f64,
    /// A wheel slower than this fraction of the fastest wheel holds its steering angle (the
    /// ICR rests on it). Default 0.02 (at the platform's top rolling speed, 2.4 cm/s:
    /// about [`crate::reference::limits::HOLD_SPEED`]).
    pub hold_ratio: f64,
    /// Largest ṡ where the timing is free (waypoints without a time): their nominal
    /// parametrisation runs at the platform's top speeds, so the limits bind well below this
    /// everywhere except near rest, where it keeps the start and stop gentle. Default 4.
    pub free_scale_cap: f64,
    /// Largest lateral acceleration |u| |φ̇| of a wheel's contact point (m/s²): the rate at
    /// which its direction of travel turns times its speed. The steering drives follow the
    /// reference with a few milliseconds of residual lag, and a wheel a small angle δ off its
    /// direction rolls δ |u| sideways; that drift is |u| φ̇ × the lag. Default 0.5 m/s²: a
    /// pre-planned path is held to it over its whole length (the live shaper allows
    /// 2 m/s² for the short turns of a command stream, `ShaperConfig::lateral_accel`).
    pub lateral_accel: f64,
}

impl Default for TimeScaleConfig {
    /// The margins shared with the live-command shaper (its speed fraction and jerk time,
    /// [`DEFAULT_SPEED_FRACTION`] and [`DEFAULT_JERK_TIME`]: one description of how much of
    /// each speed limit a reference may use and how fast its accelerations may build up), with
    /// the scaling's own defaults for the rest.
    fn default() -> Self {
        Self {
            speed_fraction: DEFAULT_SPEED_FRACTION,
            accel_fraction: 0.5,
            jerk_time: DEFAULT_JERK_TIME,
            hold_ratio: 0.02,
            free_scale_cap: 4.0,
            lateral_accel: 0.5,
        }
    }
}

impl TimeScaleConfig {
    fn validate(&self) -> Result<(), TimeScaleError> {
        let check = |field: &'static str, v: f64, lo: f64, hi: f64| {
            if v.is_finite() && v > lo && v <= hi {
                Ok(())
            } else {
                Err(TimeScaleError::Option {
                    field,
                    value: v,
                    reason: format!("must be in ({lo}, {hi}]"),
                })
            }
        };
        check("speed_fraction", self.speed_fraction, 0.0, 1.0)?;
        check("accel_fraction", self.accel_fraction, 0.0, 1.0)?;
        check("jerk_time", self.jerk_time, 0.0, 10.0)?;
        check("hold_ratio", self.hold_ratio, 0.0, 0.5)?;
        check("free_scale_cap", self.free_scale_cap, 0.0, 100.0)?;
        check("lateral_accel", self.lateral_accel, 0.0, 1000.0)
    }
}

/// What no timing can fix, or an option out of range.
#[derive(Debug, thiserror::Error)]
pub enum TimeScaleError {
    /// The trajectory's duration is not a finite time in [0, 10 h].
    #[error("the trajectory lasts {} s: it must be a finite time of at most {} s (10 h); split longer runs", crate::num::Num(*duration), MAX_EXECUTED_S)]
    Duration {
        /// The duration (s).
        duration: f64,
    },
    /// A leg leaves its range (no timing moves a leg back into its range).
    #[error("{} leg {} goes to {} m, outside the platform's leg range [{min}, {max}] m: no timing can fix this; move the waypoint into the range", at(*waypoint, *t), leg + 1, crate::num::Num(*value))]
    LegOutOfRange {
        /// The waypoint nearest to it, when the trajectory has waypoints.
        waypoint: Option<usize>,
        /// Nominal time (s).
        t: f64,
        /// Leg index (0-based).
        leg: usize,
        /// The value (m).
        value: f64,
        /// λ_min (m).
        min: f64,
        /// λ_max (m).
        max: f64,
    },
    /// The direction of travel of a moving wheel jumps (a corner without a stop): it would
    /// need an infinite steering rate at any speed.
    #[error("{} wheel {}'s direction of travel jumps by {:.1}° while it rolls (a corner without a stop): that needs an infinite steering rate at any speed, no timing can fix it; stop the platform at that point (repeat the waypoint) or round the corner", at(*waypoint, *t), wheel + 1, angle.to_degrees())]
    SteeringKink {
        /// The waypoint nearest to it, when the trajectory has waypoints.
        waypoint: Option<usize>,
        /// Nominal time (s).
        t: f64,
        /// Wheel index (0-based).
        wheel: usize,
        /// The jump (rad).
        angle: f64,
    },
    /// Slowed into the limits, the trajectory would last longer than a run may.
    #[error("{} wheel {} needs {} but `limits.{field}` = {}; slowed into the limits the trajectory would last {} s, beyond the {} s (10 h) a run may take: raise the limit in the platform file or split the trajectory", at(*waypoint, *t), wheel + 1, crate::num::Fixed3(*value), crate::num::Fixed3(*limit), crate::num::Fixed3(*duration), MAX_EXECUTED_S)]
    TooSlow {
        /// The platform file's name of the limit.
        field: &'static str,
        /// The waypoint nearest to the slowest point.
        waypoint: Option<usize>,
        /// Nominal time of the slowest point (s).
        t: f64,
        /// Wheel (0-based).
        wheel: usize,
        /// What the trajectory asks there at its nominal timing.
        value: f64,
        /// The limit.
        limit: f64,
        /// The executed duration it would take (s).
        duration: f64,
    },
    /// An option of the scaling is out of its range.
    #[error("time scaling option `{field}` = {value}: {reason}")]
    Option {
        /// The option.
        field: &'static str,
        /// Its value.
        value: f64,
        /// The range.
        reason: String,
    },
}

/// "at waypoints[k] (t = …)" or "at t = … s".
fn at(waypoint: Option<usize>, t: f64) -> String {
    match waypoint {
        Some(k) => format!("near waypoints[{k}] (t = {} s):", crate::num::Fixed3(t)),
        None => format!("at t = {} s:", crate::num::Fixed3(t)),
    }
}

/// One wheel at one grid point: what the path asks of it at ṡ = 1.
#[derive(Clone, Copy, Debug, Default)]
struct Geo {
    /// w, the contact velocity at ṡ = 1 (m/s, body frame).
    w: [f64; 2],
    /// w' (m/s²).
    dw: [f64; 2],
    /// |w| (m/s).
    speed: f64,
    /// w·w'/|w| (m/s²): d|w|/dτ.
    speed_d: f64,
    /// Steering angle of the steering geometry (rad, continued across branches).
    angle: f64,
    /// dφ/dτ of the steering geometry (rad/s).
    rate: f64,
    /// d²φ/dτ² (rad/s²).
    accel: f64,
    /// dφ/dτ, d²φ/dτ² of the direction of travel (where |w| > 0).
    raw_rate: f64,
    raw_accel: f64,
    /// |λ'| (m/s).
    leg_rate: f64,
    /// The wheel is steered by its direction of travel here (not held).
    defined: bool,
}

/// The path sampled on the grid.
struct Grid {
    taus: Vec<f64>,
    caps: Vec<f64>,
    /// Fastest wheel per point (m/s at ṡ = 1).
    wmax: Vec<f64>,
    /// Per point and wheel (index j·n + i).
    geo: Vec<Geo>,
}

fn sample_point(
    p: &Platform,
    inner: &dyn Trajectory,
    cfg: &TimeScaleConfig,
    n: usize,
    tau: f64,
    out: &mut Vec<Geo>,
) -> Result<(f64, f64), TimeScaleError> {
    let r = inner.sample(tau);
    let cap = if inner.timed_at(tau) {
        1.0
    } else {
        cfg.free_scale_cap
    };
    let mut wmax = 0.0f64;
    for (i, wc) in p.wheels.iter().enumerate().take(n) {
        let l = r.z[3 + i];
        if !(l >= wc.lambda_min - 1e-9 && l <= wc.lambda_max + 1e-9) {
            return Err(TimeScaleError::LegOutOfRange {
                waypoint: inner.waypoint_near(tau),
                t: tau,
                leg: i,
                value: l,
                min: wc.lambda_min,
                max: wc.lambda_max,
            });
        }
        let [u, du, ddu] = contact_kinematics(p, i, &r);
        let sp = u[0].hypot(u[1]);
        let (raw_rate, raw_accel) = if sp > 0.0 {
            direction_rates(u, du, ddu)
        } else {
            (0.0, 0.0)
        };
        out.push(Geo {
            w: u,
            dw: du,
            speed: sp,
            speed_d: if sp > 0.0 {
                (u[0] * du[0] + u[1] * du[1]) / sp
            } else {
                0.0
            },
            raw_rate,
            raw_accel,
            leg_rate: r.dz[3 + i].abs(),
            ..Geo::default()
        });
        wmax = wmax.max(sp);
    }
    Ok((cap, wmax))
}

/// Direction difference of two vectors modulo π, in [0, π/2].
fn angle_mod_pi(a: [f64; 2], b: [f64; 2]) -> f64 {
    let d = (a[0] * b[1] - a[1] * b[0])
        .atan2(a[0] * b[0] + a[1] * b[1])
        .abs();
    d.min(PI - d)
}

impl Grid {
    /// The base grid of the path from τ `a` to `b`, refined where a wheel's direction turns by more than
    /// [`REFINE_ANGLE`] between two points or its contact velocity passes close to zero
    /// between them (the linearised closest approach, as the shaper refines its grid).
    fn build(
        p: &Platform,
        inner: &dyn Trajectory,
        cfg: &TimeScaleConfig,
        n: usize,
        a: f64,
        b: f64,
    ) -> Result<Self, TimeScaleError> {
        let len = b - a;
        let base = if len > 0.0 {
            ((len / GRID_STEP).ceil() as usize).clamp(1, MAX_GRID / 2)
        } else {
            0
        };
        let tau_base = |j: usize| {
            if j >= base {
                b
            } else {
                a + len * j as f64 / base as f64
            }
        };
        let mut g = Grid {
            taus: Vec::with_capacity(base + 1),
            caps: Vec::with_capacity(base + 1),
            wmax: Vec::with_capacity(base + 1),
            geo: Vec::with_capacity((base + 1) * n),
        };
        for j in 0..=base {
            let tau = tau_base(j);
            let (cap, wmax) = sample_point(p, inner, cfg, n, tau, &mut g.geo)?;
            g.taus.push(tau);
            g.caps.push(cap);
            g.wmax.push(wmax);
        }
        if base == 0 {
            return Ok(g);
        }
        // Refinement: how many points each interval needs.
        let mut extra = vec![0usize; base];
        let mut total = base + 1;
        for j in 0..base {
            let h = g.taus[j + 1] - g.taus[j];
            let mut k = 1usize;
            for i in 0..n {
                let (a, b) = (g.geo[j * n + i], g.geo[(j + 1) * n + i]);
                if a.speed <= 0.0 || b.speed <= 0.0 {
                    continue;
                }
                let turn = angle_mod_pi(a.w, b.w)
                    .max(a.raw_rate.abs() * h)
                    .max(b.raw_rate.abs() * h);
                k = k.max((turn / REFINE_ANGLE).ceil() as usize);
                // Closest approach of the linearised contact velocity inside the interval.
                for (g0, sign) in [(a, 1.0), (b, -1.0)] {
                    let d2 = g0.dw[0] * g0.dw[0] + g0.dw[1] * g0.dw[1];
                    if d2 <= 0.0 {
                        continue;
                    }
                    let s = -(g0.w[0] * g0.dw[0] + g0.w[1] * g0.dw[1]) / d2;
                    if s * sign > 0.0 && (s * sign) < h {
                        let m = [g0.w[0] + g0.dw[0] * s, g0.w[1] + g0.dw[1] * s];
                        let closest = m[0].hypot(m[1]);
                        let floor = cfg.hold_ratio * g.wmax[j].min(g.wmax[j + 1]);
                        if closest < 0.5 * a.speed.min(b.speed) {
                            // The direction turns within about |w|/|w'| of the closest point.
                            let width = closest.max(floor) / d2.sqrt();
                            if width > 0.0 {
                                k = k.max((4.0 * h / width).ceil() as usize);
                            }
                        }
                    }
                }
            }
            let k = k.min(REFINE_MAX);
            if total + k - 1 > MAX_GRID {
                break;
            }
            extra[j] = k - 1;
            total += k - 1;
        }
        if extra.iter().all(|&e| e == 0) {
            return Ok(g);
        }
        let mut r = Grid {
            taus: Vec::with_capacity(total),
            caps: Vec::with_capacity(total),
            wmax: Vec::with_capacity(total),
            geo: Vec::with_capacity(total * n),
        };
        for j in 0..=base {
            r.taus.push(g.taus[j]);
            r.caps.push(g.caps[j]);
            r.wmax.push(g.wmax[j]);
            r.geo.extend_from_slice(&g.geo[j * n..(j + 1) * n]);
            if j < base && extra[j] > 0 {
                let k = extra[j] + 1;
                for q in 1..k {
                    let tau = g.taus[j] + (g.taus[j + 1] - g.taus[j]) * q as f64 / k as f64;
                    let (cap, wmax) = sample_point(p, inner, cfg, n, tau, &mut r.geo)?;
                    r.taus.push(tau);
                    r.caps.push(cap);
                    r.wmax.push(wmax);
                }
            }
        }
        Ok(r)
    }

    fn points(&self) -> usize {
        self.taus.len()
    }
}

/// A stretch over which a wheel's steering angle is a blend, not its direction of travel.
#[derive(Clone, Copy, Debug, PartialEq)]
struct Blend {
    /// Start and end in path time (s).
    a: f64,
    b: f64,
    /// Quintic in (τ − a) (a constant when the other coefficients are zero).
    coef: [f64; 6],
}

/// The steering geometry of a piece of the path: per wheel, the angle along τ (module docs).
#[derive(Clone, Debug, Default)]
struct SteerGeometry {
    taus: Vec<f64>,
    /// Per grid point and wheel (index j·n + i): the angle.
    angle: Vec<f64>,
    /// Per wheel: the blends, sorted.
    blends: Vec<Vec<Blend>>,
}

impl SteerGeometry {
    /// The smallest and largest angle wheel `i` takes on the grid (its blends between grid
    /// points are quintics between their end states, within a grid step of them).
    fn extent(&self, n: usize, i: usize) -> (f64, f64) {
        let mut e = (f64::INFINITY, f64::NEG_INFINITY);
        for j in 0..self.taus.len() {
            let a = self.angle[j * n + i];
            e = (e.0.min(a), e.1.max(a));
        }
        e
    }

    /// Moves wheel `i`'s angles by `d` (a multiple of π: the other branch of the same
    /// directions).
    fn shift(&mut self, n: usize, i: usize, d: f64) {
        for j in 0..self.taus.len() {
            self.angle[j * n + i] += d;
        }
        for b in &mut self.blends[i] {
            b.coef[0] += d;
        }
    }
}

/// One motion of the path between two of its stops (or its ends): its grid, steering
/// geometry and clock (module docs, "Stops and dwells").
#[derive(Clone, Debug)]
struct Piece {
    /// Path times of its start and end (s).
    tau0: f64,
    tau1: f64,
    /// Executed time of its start (s).
    t0: f64,
    /// Executed duration (s).
    duration: f64,
    /// ṡ ≡ 1 on the whole piece: τ = tau0 + (t − t0).
    pass: bool,
    /// Clock knots (empty when `pass`): time from `t0`, τ, ṡ, s̈.
    kt: Vec<f64>,
    ktau: Vec<f64>,
    kv: Vec<f64>,
    ka: Vec<f64>,
    /// Per grid point: the binding limit and its wheel, and whether the clock runs below
    /// its cap there.
    reason: Vec<(Limiting, u8, bool)>,
    geo: SteerGeometry,
    /// Whether the piece needs a steering reference (a wheel held while the platform moves).
    steer: bool,
    /// Duration of the time-optimal timing on the grid (s), before the jerk smoothing.
    optimal: f64,
    /// Smallest ṡ where something moves: (ṡ, executed time from `t0`, limit, wheel).
    min: (f64, f64, Limiting, usize),
    /// Largest demand over its share found by the verification.
    max_ratio: f64,
    /// The near stops (times from `t0`, s): where the platform passes a near stop and the
    /// clock slows to let the wheels re-steer (reported with the dwells).
    near: Vec<(f64, f64)>,
}

/// A planned dwell (module docs, "Stops and dwells"): the clock holds at a stop of the path
/// while the wheels steer from the direction they stopped in to the one they start in.
#[derive(Clone, Debug)]
struct Dwell {
    /// Executed start (s) and duration (s).
    t0: f64,
    duration: f64,
    /// The stop's path times (equal for a stop at a point; a stand otherwise).
    tau0: f64,
    tau1: f64,
    /// Per wheel, the steering angle as a quintic in (t − t0).
    steer: [[f64; 6]; MAX_WHEELS],
}

/// What runs at an executed time.
#[derive(Clone, Copy, Debug, PartialEq)]
enum Span {
    Piece(usize),
    Dwell(usize),
}

/// A trajectory run on a clock chosen so that every actuator stays within its share of its
/// speed and acceleration limits (module docs).
pub struct ScaledTrajectory {
    inner: Box<dyn Trajectory>,
    platform: Platform,
    n: usize,
    nominal: f64,
    executed: f64,
    /// One piece with ṡ ≡ 1 and no dwell: samples are the inner trajectory's.
    pass: bool,
    pieces: Vec<Piece>,
    dwells: Vec<Dwell>,
    /// Executed start of every piece and dwell, in order.
    spans: Vec<(f64, Span)>,
    /// The dwells as executed-time intervals (s).
    dwell_spans: Vec<(f64, f64)>,
    steer: bool,
    timing: Timing,
}

impl std::fmt::Debug for ScaledTrajectory {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("ScaledTrajectory")
            .field("timing", &self.timing)
            .field("pass_through", &self.pass)
            .field("dwells", &self.dwell_spans)
            .finish_non_exhaustive()
    }
}

/// One acceleration constraint |a x + b s̈| ≤ c.
#[derive(Clone, Copy, Debug)]
struct Acc {
    a: f64,
    b: f64,
    c: f64,
}

impl Acc {
    /// (p, q) of the lower bound p + q x on s̈, and (r, s) of the upper bound r + s x.
    fn bounds(&self) -> ((f64, f64), (f64, f64)) {
        let (a, b, c) = (self.a, self.b, self.c);
        if b > 0.0 {
            ((-c / b, -a / b), (c / b, -a / b))
        } else {
            ((c / b, -a / b), (-c / b, -a / b))
        }
    }
}

/// Constraints of one grid point.
#[derive(Clone, Debug, Default)]
struct Point {
    xbar: f64,
    acc: Vec<Acc>,
}

/// The steering rate (rad/s) a scaled reference may have where it starts or ends without a
/// stop of the path (the platform already moving: the change the steering acceleration share
/// allows in one control cycle).
fn start_steer_rate(p: &Platform, cfg: &TimeScaleConfig) -> f64 {
    cfg.accel_fraction * p.limits.steer_accel * p.dt()
}

/// Smallest x kept anywhere (the clock never stops).
const X_FLOOR: f64 = 1e-300;

/// Share of the acceleration shares the passes plan with: the smoothing averages s̈ over
/// its window, which can add a few per cent where the constraints change within it.
const SMOOTHING_MARGIN: f64 = 0.9;

/// The constraints of every grid point of a piece (module docs, "What a timing asks");
/// `open` says which of its ends (start, end) is not a stop of the path (the steering rate
/// there is bounded by one cycle's change: nothing re-steers the wheels there).
fn constraints(
    p: &Platform,
    cfg: &TimeScaleConfig,
    n: usize,
    g: &Grid,
    open: (bool, bool),
    halt: (bool, bool),
) -> Vec<Point> {
    let l = &p.limits;
    let rw = p.wheel_radius;
    let (fv, fa) = (cfg.speed_fraction, cfg.accel_fraction * SMOOTHING_MARGIN);
    let points = g.points();
    (0..points)
        .map(|j| {
            let mut xbar = g.caps[j] * g.caps[j];
            // An end where the steering range stops a moving platform: the clock stops there.
            if (j == 0 && halt.0) || (j + 1 == points && halt.1) {
                xbar = 0.0;
            }
            if (j == 0 && open.0) || (j + 1 == points && open.1) {
                let r0 = start_steer_rate(p, cfg);
                for i in 0..n {
                    let rate = g.geo[j * n + i].rate.abs();
                    if rate > 0.0 {
                        xbar = xbar.min((r0 / rate).powi(2));
                    }
                }
            }
            let mut acc = Vec::with_capacity(2 * n);
            for i in 0..n {
                let q = &g.geo[j * n + i];
                if q.speed > 0.0 {
                    xbar = xbar.min((fv * l.wheel_speed * rw / q.speed).powi(2));
                    acc.push(Acc {
                        a: q.speed_d,
                        b: q.speed,
                        c: fa * l.wheel_accel * rw,
                    });
                }
                if q.leg_rate > 0.0 {
                    xbar = xbar.min((fv * l.leg_speed / q.leg_rate).powi(2));
                }
                if q.rate != 0.0 {
                    xbar = xbar.min((fv * l.steer_rate / q.rate).powi(2));
                    if q.speed > 0.0 {
                        xbar = xbar.min(cfg.lateral_accel / (q.speed * q.rate.abs()));
                    }
                }
                if q.rate != 0.0 || q.accel != 0.0 {
                    acc.push(Acc {
                        a: q.accel,
                        b: q.rate,
                        c: fa * l.steer_accel,
                    });
                }
            }
            // Constraints without s̈ bound x alone; pairs whose s̈ intervals stop overlapping
            // bound it too.
            acc.retain(|k| {
                if k.b.abs() <= 1e-12 * (k.a.abs() + 1.0) {
                    if k.a != 0.0 {
                        xbar = xbar.min(k.c / k.a.abs());
                    }
                    false
                } else {
                    true
                }
            });
            for k in &acc {
                let ((p0, q0), _) = k.bounds();
                for m in &acc {
                    let (_, (r1, s1)) = m.bounds();
                    // p0 + q0 x ≤ r1 + s1 x
                    let dq = q0 - s1;
                    if dq > 0.0 {
                        xbar = xbar.min((r1 - p0) / dq);
                    }
                }
            }
            if xbar.is_nan() {
                xbar = X_FLOOR;
            }
            Point {
                xbar: xbar.max(X_FLOOR),
                acc,
            }
        })
        .collect()
}

/// The exact stops of a path (module docs, "Stops and dwells"): the trajectory's own
/// ([`Trajectory::stops`]) and its ends where the platform rests there, sorted and merged,
/// within [0, `nominal`].
fn stops_of(p: &Platform, inner: &dyn Trajectory, n: usize, nominal: f64) -> Vec<(f64, f64)> {
    let at_rest = |tau: f64| {
        let r = inner.sample(tau);
        (0..n).all(|i| {
            let u = contact_kinematics(p, i, &r)[0];
            u[0].hypot(u[1]) <= REST_W
        }) && (0..3 + n).all(|c| r.dz[c].abs() <= REST_W)
    };
    let mut v: Vec<(f64, f64)> = inner
        .stops()
        .into_iter()
        .filter(|(a, b)| a.is_finite() && b.is_finite() && a <= b)
        .map(|(a, b)| (a.clamp(0.0, nominal), b.clamp(0.0, nominal)))
        .collect();
    if at_rest(0.0) {
        v.push((0.0, 0.0));
    }
    if nominal > 0.0 && at_rest(nominal) {
        v.push((nominal, nominal));
    }
    v.sort_by(|a, b| a.0.total_cmp(&b.0));
    let mut out: Vec<(f64, f64)> = Vec::with_capacity(v.len());
    for (a, b) in v {
        match out.last_mut() {
            Some(last) if a <= last.1 => last.1 = last.1.max(b),
            _ => out.push((a, b)),
        }
    }
    out
}

/// Checks what no timing can fix (module docs, "What no timing can fix"): a duration beyond
/// [`MAX_EXECUTED_S`], a leg out of its range, a moving wheel whose direction jumps.
pub fn check_fixable(
    p: &Platform,
    traj: &dyn Trajectory,
    cfg: &TimeScaleConfig,
) -> Result<(), TimeScaleError> {
    cfg.validate()?;
    let nominal = traj.duration();
    if !(nominal.is_finite() && (0.0..=MAX_EXECUTED_S).contains(&nominal)) {
        return Err(TimeScaleError::Duration { duration: nominal });
    }
    let n = p.n().min(traj.n_legs()).min(MAX_WHEELS);
    for part in layout(&stops_of(p, traj, n, nominal), nominal) {
        if let Part::Motion { a, b, .. } = part {
            let mut grid = Grid::build(p, traj, cfg, n, a, b)?;
            steering_geometry(p, traj, cfg, n, &mut grid)?;
        }
    }
    Ok(())
}

/// The branches (multiples m of π) that put angles spanning `extent` inside range `r`:
/// `Some((lo, hi))` with every m in lo..=hi fitting, `None` when none does.
fn branches_inside(r: crate::angle::SteerRange, extent: (f64, f64)) -> Option<(f64, f64)> {
    let (lo, hi) = extent;
    if !(lo.is_finite() && hi.is_finite()) {
        return None;
    }
    let m_lo = ((r.min - lo) / PI - 1e-9).ceil();
    let m_hi = ((r.max - hi) / PI + 1e-9).floor();
    (m_lo <= m_hi).then_some((m_lo, m_hi))
}

/// Most stops the steering ranges may add to a path ([`range_stops`]).
const MAX_RANGE_STOPS: usize = 256;

/// Adds to `stops` where a wheel with a steering range must stop to unwind (module docs,
/// "Steering ranges"): along each motion, the first grid point beyond which the wheel's
/// directions since the motion's start no longer fit inside its range on any branch
/// (turned by a multiple of π, the wheel rolling backwards on the odd ones). The motion
/// is cut at the last point that fits; the dwell there turns the wheel back within its
/// range while the platform stands. Repeated on what follows the cut until every motion
/// fits. Returns the cuts (the path moves there: its clock must stop).
fn range_stops(
    p: &Platform,
    inner: &dyn Trajectory,
    cfg: &TimeScaleConfig,
    n: usize,
    nominal: f64,
    stops: &mut Vec<(f64, f64)>,
) -> Result<Vec<f64>, TimeScaleError> {
    let mut cuts = Vec::new();
    if !p
        .wheels
        .iter()
        .take(n)
        .any(|w| w.steering_range().is_some())
    {
        return Ok(cuts);
    }
    for _ in 0..MAX_RANGE_STOPS {
        let mut cut = None;
        for part in layout(stops, nominal) {
            let Part::Motion { a, b, .. } = part else {
                continue;
            };
            let mut grid = Grid::build(p, inner, cfg, n, a, b)?;
            let (geo, _) = steering_geometry(p, inner, cfg, n, &mut grid)?;
            let points = geo.taus.len();
            for (i, w) in p.wheels.iter().enumerate().take(n) {
                let Some(r) = w.steering_range() else {
                    continue;
                };
                let (mut lo, mut hi) = (f64::INFINITY, f64::NEG_INFINITY);
                for j in 0..points {
                    let x = geo.angle[j * n + i];
                    let (l, h) = (lo.min(x), hi.max(x));
                    if branches_inside(r, (l, h)).is_none() {
                        // Cut at the last point that fits (at least one grid step in: the
                        // motion always advances).
                        let at = geo.taus[j.saturating_sub(1).max(1).min(points - 1)];
                        if at > a && at < b {
                            cut = Some(cut.map_or(at, |c: f64| c.min(at)));
                        }
                        break;
                    }
                    (lo, hi) = (l, h);
                }
            }
            if cut.is_some() {
                break;
            }
        }
        let Some(at) = cut else {
            return Ok(cuts);
        };
        cuts.push(at);
        stops.push((at, at));
        stops.sort_by(|x, y| x.0.total_cmp(&y.0));
    }
    Ok(cuts)
}

/// A part of the path in the order it runs: a motion between stops, or a stop.
#[derive(Clone, Copy, Debug, PartialEq)]
enum Part {
    /// A motion from τ `a` to `b`; whether it starts and ends at a stop.
    Motion {
        a: f64,
        b: f64,
        from_stop: bool,
        to_stop: bool,
    },
    /// A stop from τ `a` to `b` (equal: a stop at a point).
    Stop { a: f64, b: f64 },
}

/// The path's parts in order: motions between the stops. A path that never moves is one
/// motion (of no consequence: nothing moves on it).
fn layout(stops: &[(f64, f64)], nominal: f64) -> Vec<Part> {
    let mut out = Vec::with_capacity(2 * stops.len() + 1);
    let (mut cur, mut rest) = (0.0, false);
    for &(a, b) in stops {
        if a > cur {
            out.push(Part::Motion {
                a: cur,
                b: a,
                from_stop: rest,
                to_stop: true,
            });
        }
        out.push(Part::Stop { a, b });
        cur = b;
        rest = true;
    }
    if cur < nominal {
        out.push(Part::Motion {
            a: cur,
            b: nominal,
            from_stop: rest,
            to_stop: false,
        });
    }
    if !out.iter().any(|p| matches!(p, Part::Motion { .. })) {
        return vec![Part::Motion {
            a: 0.0,
            b: nominal,
            from_stop: false,
            to_stop: false,
        }];
    }
    out
}

/// Steering state (angle, rate, acceleration) in executed time.
type SteerState = (f64, f64, f64);

/// The shortest duration (s) of a dwell from steering state `from` to the state `to(d)`
/// (which may depend on the duration) whose quintic keeps the steering rate within
/// `rate` and its acceleration within `accel` (0 when the states already agree).
fn dwell_duration(
    from: SteerState,
    to: &dyn Fn(f64) -> SteerState,
    rate: f64,
    accel: f64,
    dt: f64,
) -> f64 {
    let fits = |d: f64| {
        let e = to(d);
        let c = quintic(from.0, from.1, from.2, e.0, e.1, e.2, d);
        (0..=64).all(|k| {
            let (_, v, a, _) = eval_quintic(&c, d * k as f64 / 64.0);
            v.abs() <= rate && a.abs() <= accel
        })
    };
    let e = to(0.0);
    let tol = 1e-9;
    if (e.0 - from.0).abs() <= tol && (e.1 - from.1).abs() <= tol && (e.2 - from.2).abs() <= tol {
        return 0.0;
    }
    let mut hi = 2.0 * dt;
    let mut tries = 0;
    while !fits(hi) {
        hi *= 2.0;
        tries += 1;
        if tries > 40 {
            return hi;
        }
    }
    let mut lo = if hi > 2.0 * dt { 0.5 * hi } else { return hi };
    for _ in 0..40 {
        let m = 0.5 * (lo + hi);
        if fits(m) {
            hi = m;
        } else {
            lo = m;
        }
        if hi - lo <= 1e-4 * hi {
            break;
        }
    }
    // A whole number of microseconds above the shortest: the quintic is checked at 65
    // points, which the bisection's last step may straddle.
    hi * 1.001
}

impl ScaledTrajectory {
    /// Plans the timing of `inner` for platform `p` (module docs). Refuses what no timing
    /// can fix ([`TimeScaleError`]).
    pub fn plan(
        p: &Platform,
        inner: Box<dyn Trajectory>,
        cfg: TimeScaleConfig,
    ) -> Result<Self, TimeScaleError> {
        cfg.validate()?;
        let nominal = inner.duration();
        if !(nominal.is_finite() && (0.0..=MAX_EXECUTED_S).contains(&nominal)) {
            return Err(TimeScaleError::Duration { duration: nominal });
        }
        let n = p.n().min(inner.n_legs()).min(MAX_WHEELS);
        let mut stops = stops_of(p, inner.as_ref(), n, nominal);
        let cuts = range_stops(p, inner.as_ref(), &cfg, n, nominal, &mut stops)?;
        let parts = layout(&stops, nominal);
        let mut pieces: Vec<Piece> = Vec::with_capacity(parts.len());
        let mut optimal = 0.0;
        for part in &parts {
            if let Part::Motion {
                a,
                b,
                from_stop,
                to_stop,
            } = *part
            {
                let halt = (cuts.contains(&a), cuts.contains(&b));
                let piece = Piece::plan(
                    p,
                    inner.as_ref(),
                    &cfg,
                    n,
                    a,
                    b,
                    (!from_stop, !to_stop),
                    halt,
                )?;
                optimal += piece.optimal;
                if optimal.is_nan() || optimal > MAX_EXECUTED_S {
                    return Err(piece_too_slow(p, &cfg, inner.as_ref(), n, &piece, optimal));
                }
                pieces.push(piece);
            }
        }
        // Every piece on the branch of its wheels' directions nearest the one before it; a
        // wheel with a steering range on the branch nearest that among those inside its range
        // (the first piece: nearest the range's centre, where homing leaves the wheel), so
        // the dwell between two pieces unwinds it (module docs, "Steering ranges").
        for k in 0..pieces.len() {
            for i in 0..n {
                let range = p.wheels[i].steering_range();
                if k == 0 && range.is_none() {
                    continue;
                }
                let start = pieces[k].start_angle(i);
                let from = match (k, range) {
                    (0, Some(r)) => r.centre(),
                    _ => pieces[k - 1].end_angle(n, i),
                };
                let mut m = ((from - start) / PI).round();
                if let Some(r) = range {
                    if let Some((lo, hi)) = branches_inside(r, pieces[k].geo.extent(n, i)) {
                        m = m.clamp(lo, hi);
                    }
                }
                let d = m * PI;
                if d != 0.0 && d.is_finite() {
                    pieces[k].geo.shift(n, i, d);
                }
            }
        }
        // The parts in order: pieces on their clocks, dwells at the stops.
        let rate = cfg.speed_fraction * p.limits.steer_rate;
        let accel = cfg.accel_fraction * p.limits.steer_accel;
        let mut dwells = Vec::new();
        let mut spans = Vec::with_capacity(parts.len());
        let mut t = 0.0;
        let mut index = Vec::with_capacity(parts.len());
        let mut k = 0;
        for part in &parts {
            index.push(match part {
                Part::Motion { .. } => {
                    k += 1;
                    Some(k - 1)
                }
                Part::Stop { .. } => None,
            });
        }
        for (m, part) in parts.iter().enumerate() {
            match *part {
                Part::Motion { .. } => {
                    let q = index[m].unwrap_or(0);
                    pieces[q].t0 = t;
                    spans.push((t, Span::Piece(q)));
                    t += pieces[q].duration;
                }
                Part::Stop { a, b } => {
                    let before = m.checked_sub(1).and_then(|j| index[j]);
                    let after = index.get(m + 1).copied().flatten();
                    // A stand whose duration is given lasts at least that long.
                    let stand = if b > a && inner.timed_at(0.5 * (a + b)) {
                        b - a
                    } else {
                        0.0
                    };
                    let mut ends = [((0.0, 0.0, 0.0), None); MAX_WHEELS];
                    let mut longest = stand;
                    for i in 0..n {
                        let from = before.map(|q| pieces[q].steer_end(p, inner.as_ref(), n, i));
                        let to = after.map(|q| pieces[q].steer_start(p, inner.as_ref(), n, i));
                        // The path's start: from rest at the angle it starts with; its end:
                        // the steering comes to rest, its rate falling evenly.
                        let f = match (from, to) {
                            (Some(f), _) => f,
                            (None, Some(e)) => (e.0, 0.0, 0.0),
                            (None, None) => (0.0, 0.0, 0.0),
                        };
                        let target = |d: f64| to.unwrap_or((f.0 + 0.5 * f.1 * d, 0.0, 0.0));
                        longest = longest.max(dwell_duration(f, &target, rate, accel, p.dt()));
                        ends[i] = (f, to);
                    }
                    if longest > 0.0 {
                        let mut steer = [[0.0; 6]; MAX_WHEELS];
                        for i in 0..n {
                            let (f, to) = ends[i];
                            let e = to.unwrap_or((f.0 + 0.5 * f.1 * longest, 0.0, 0.0));
                            steer[i] = quintic(f.0, f.1, f.2, e.0, e.1, e.2, longest);
                        }
                        spans.push((t, Span::Dwell(dwells.len())));
                        dwells.push(Dwell {
                            t0: t,
                            duration: longest,
                            tau0: a,
                            tau1: b,
                            steer,
                        });
                        t += longest;
                    }
                }
            }
        }
        let executed = t;
        let dwell_s: f64 = dwells.iter().map(|d| d.duration).sum();
        if executed.is_nan() || executed > MAX_EXECUTED_S {
            let slowest = (0..pieces.len())
                .min_by(|&a, &b| pieces[a].min.0.total_cmp(&pieces[b].min.0))
                .unwrap_or(0);
            return Err(piece_too_slow(
                p,
                &cfg,
                inner.as_ref(),
                n,
                &pieces[slowest],
                executed,
            ));
        }
        let pass = pieces.len() == 1 && pieces[0].pass && dwells.is_empty();
        let steer = !pass || pieces.iter().any(|q| q.steer);
        let mut min = (f64::INFINITY, 0.0, Limiting::None, 0usize);
        let mut max_ratio = 0.0f64;
        for q in &pieces {
            if q.min.0 < min.0 {
                min = (q.min.0, q.t0 + q.min.1, q.min.2, q.min.3);
            }
            max_ratio = max_ratio.max(q.max_ratio);
        }
        // The dwells and the near stops, in order (overlapping ones merged).
        let mut all: Vec<(f64, f64)> = dwells.iter().map(|d| (d.t0, d.t0 + d.duration)).collect();
        for q in &pieces {
            all.extend(q.near.iter().map(|&(a, b)| (q.t0 + a, q.t0 + b)));
        }
        all.sort_by(|a, b| a.0.total_cmp(&b.0));
        let mut dwell_spans: Vec<(f64, f64)> = Vec::with_capacity(all.len());
        for (a, b) in all {
            match dwell_spans.last_mut() {
                Some(last) if a <= last.1 => last.1 = last.1.max(b),
                _ => dwell_spans.push((a, b)),
            }
        }
        Ok(ScaledTrajectory {
            inner,
            platform: p.clone(),
            n,
            nominal,
            executed,
            pass,
            pieces,
            dwells,
            spans,
            dwell_spans,
            steer,
            timing: Timing {
                nominal_duration_s: nominal,
                executed_duration_s: executed,
                optimal_duration_s: optimal,
                dwell_s,
                min_scale: if min.0.is_finite() { min.0 } else { 1.0 },
                min_scale_at_s: min.1,
                limiting: if min.0 < 1.0 - 1e-9 {
                    min.2
                } else {
                    Limiting::None
                },
                wheel: min.3,
                max_ratio,
                steer_reference: steer,
            },
        })
    }

    /// The trajectory being scaled.
    pub fn inner(&self) -> &dyn Trajectory {
        self.inner.as_ref()
    }

    /// True when ṡ ≡ 1: the samples are the inner trajectory's.
    pub fn is_pass_through(&self) -> bool {
        self.pass
    }

    /// The planned dwells (module docs, "Stops and dwells"): executed-time intervals (s) in
    /// which the clock holds at a stop of the path while the wheels re-steer, and those in
    /// which it passes a near stop slowly for the same reason.
    pub fn dwells(&self) -> &[(f64, f64)] {
        &self.dwell_spans
    }

    /// Largest demand over its share at one instant ([`Piece::ratio`] of the piece whose path
    /// times hold the clock's τ; a dwell asks nothing of the rolling drives).
    #[cfg(test)]
    fn ratio(
        &self,
        cfg: &TimeScaleConfig,
        r: &ReferenceSample,
        clk: (f64, f64, f64, f64),
    ) -> (f64, Limiting, usize, bool) {
        self.pieces
            .iter()
            .find(|q| q.tau0 <= clk.0 && clk.0 <= q.tau1)
            .map_or((0.0, Limiting::None, 0, true), |q| {
                q.ratio(&self.platform, self.n, cfg, r, clk)
            })
    }

    /// What runs at executed time `t` (clamped into the run) and the time into it.
    fn locate(&self, t: f64) -> (Span, f64) {
        let k = self.spans.partition_point(|s| s.0 <= t).max(1) - 1;
        match self.spans.get(k) {
            Some(&(t0, s)) => (s, (t - t0).max(0.0)),
            None => (Span::Piece(0), t.max(0.0)),
        }
    }

    /// The clock: (τ, ṡ, s̈, s⃛) at executed time `t` (before the start: the start; after
    /// the end: the end, at rest; in a dwell: held at the stop).
    pub fn clock(&self, t: f64) -> (f64, f64, f64, f64) {
        let t = if t.is_finite() { t } else { 0.0 };
        if self.pass {
            return (t.clamp(0.0, self.nominal), 1.0, 0.0, 0.0);
        }
        if t >= self.executed {
            return (self.nominal, 0.0, 0.0, 0.0);
        }
        match self.locate(t) {
            (Span::Dwell(k), dt) => {
                let d = &self.dwells[k];
                let v = if d.duration > 0.0 {
                    (d.tau1 - d.tau0) / d.duration
                } else {
                    0.0
                };
                ((d.tau0 + v * dt).min(d.tau1), v, 0.0, 0.0)
            }
            (Span::Piece(k), dt) => self.pieces[k].clock(dt),
        }
    }

    /// The scaled sample at `t` and the inner sample at its path time, with the clock.
    fn sample_full(&self, t: f64) -> (ReferenceSample, ReferenceSample, (f64, f64, f64, f64)) {
        let clk = self.clock(t);
        let (tau, v, a, j) = clk;
        let r = self.inner.sample(if self.pass { t } else { tau });
        let mut s = r;
        if !self.pass {
            s.t = t;
            for c in 0..3 + self.n {
                s.dz[c] = r.dz[c] * v;
                s.ddz[c] = r.ddz[c] * v * v + r.dz[c] * a;
                s.dddz[c] = r.dddz[c] * v * v * v + 3.0 * r.ddz[c] * v * a + r.dz[c] * j;
            }
        }
        if self.steer {
            let mut sr = SteerReference {
                valid: true,
                ..SteerReference::default()
            };
            let t = if t.is_finite() { t } else { 0.0 };
            // After the end: where the last span left the steering, at rest.
            let end = t >= self.executed;
            let (span, dt) = if end {
                match self.spans.last() {
                    Some(&(t0, s)) => (s, t - t0),
                    None => (Span::Piece(0), t),
                }
            } else {
                self.locate(t)
            };
            match span {
                Span::Dwell(k) => {
                    let d = &self.dwells[k];
                    for i in 0..self.n {
                        let (phi, d1, d2, _) = eval_quintic(&d.steer[i], dt.min(d.duration));
                        sr.angle[i] = phi;
                        sr.rate[i] = if end { 0.0 } else { d1 };
                        sr.accel[i] = if end { 0.0 } else { d2 };
                    }
                }
                Span::Piece(k) => {
                    let q = &self.pieces[k];
                    for i in 0..self.n {
                        let (phi, d1, d2) = q.steer_at(&self.platform, self.n, i, tau, &r);
                        sr.angle[i] = phi;
                        sr.rate[i] = d1 * v;
                        sr.accel[i] = d2 * v * v + d1 * a;
                    }
                }
            }
            s.steer = sr;
        }
        (s, r, clk)
    }
}

impl Piece {
    /// Plans the clock of the path from τ `a` to `b` (module docs, "Planning"); `open` as
    /// for [`constraints`]; `halt`: the clock stops at that end (a cut the steering ranges
    /// made where the path moves, [`range_stops`]).
    #[allow(clippy::too_many_arguments)]
    fn plan(
        p: &Platform,
        inner: &dyn Trajectory,
        cfg: &TimeScaleConfig,
        n: usize,
        a: f64,
        b: f64,
        open: (bool, bool),
        halt: (bool, bool),
    ) -> Result<Self, TimeScaleError> {
        let mut grid = Grid::build(p, inner, cfg, n, a, b)?;
        let (geo, steer_needed) = steering_geometry(p, inner, cfg, n, &mut grid)?;
        let base = constraints(p, cfg, n, &grid, open, halt);
        let points = grid.points();
        let taus = &grid.taus;
        let mut fix = vec![1.0f64; points];
        let mut round = 0;
        loop {
            let x = topp(&base, &fix, taus);
            let est: f64 = (0..points.saturating_sub(1))
                .map(|j| segment_time(taus[j + 1] - taus[j], x[j].sqrt(), x[j + 1].sqrt()))
                .sum();
            if est.is_nan() || est > MAX_EXECUTED_S {
                let j = (0..points)
                    .min_by(|&a, &b| x[a].total_cmp(&x[b]))
                    .unwrap_or(0);
                return Err(too_slow(p, cfg, inner, &grid, n, j, est));
            }
            let (ys, ka) = smooth_in_time(taus, &x, cfg.jerk_time);
            let pass = ys.iter().all(|&v| v == 1.0);
            // The steering reference goes with every scaled piece, and with one that passes
            // through unchanged where a wheel is held while the platform moves or the
            // platform comes near rest between two motions (the controllers' own rules near
            // rest steer by the feedback's corrections).
            let steer = steer_needed || !pass || interior_stop(&grid.wmax);
            let mut piece = Piece {
                tau0: a,
                tau1: b,
                t0: 0.0,
                duration: b - a,
                pass,
                kt: Vec::new(),
                ktau: Vec::new(),
                kv: Vec::new(),
                ka: Vec::new(),
                reason: Vec::new(),
                geo: geo.clone(),
                steer,
                optimal: est,
                min: (f64::INFINITY, 0.0, Limiting::None, 0),
                max_ratio: 0.0,
                near: Vec::new(),
            };
            if !pass {
                piece.set_clock(taus, ys, ka);
            }
            let violations = piece.verify(p, inner, cfg, n, taus, &grid.caps, open);
            if violations.is_empty() || round == MAX_REPAIRS {
                piece.near = piece.near_spans(taus, &near_stops(&grid));
                return Ok(piece);
            }
            // Lower the bounds around each violation: over the path the smoothing window
            // mixes into it (twice the jerk time either side), and its own interval.
            let mut factor = vec![1.0f64; points];
            for (t, ratio, speed_type) in violations {
                let f = if speed_type {
                    (1.0 / ratio).powi(2)
                } else {
                    1.0 / ratio
                } * 0.95;
                let (t0, t1) = (t - 2.0 * cfg.jerk_time, t + 2.0 * cfg.jerk_time);
                let (ta, tb) = (piece.clock(t0).0, piece.clock(t1).0);
                let lo = taus.partition_point(|&x| x < ta).saturating_sub(1);
                let hi = taus.partition_point(|&x| x <= tb).min(points - 1);
                for v in &mut factor[lo..=hi] {
                    *v = v.min(f);
                }
            }
            for (v, f) in fix.iter_mut().zip(&factor) {
                *v *= f;
            }
            round += 1;
        }
    }

    /// The clock knots from ṡ and s̈ per grid point: executed times by dt = dτ/ṡ.
    fn set_clock(&mut self, taus: &[f64], ys: Vec<f64>, ka: Vec<f64>) {
        let points = taus.len();
        let mut kt = Vec::with_capacity(points);
        let mut t = 0.0;
        for j in 0..points {
            if j > 0 {
                t += knot_time(taus[j] - taus[j - 1], ys[j - 1], ys[j], ka[j - 1], ka[j]);
            }
            kt.push(t);
        }
        self.duration = t;
        self.kt = kt;
        self.ktau = taus.to_vec();
        self.kv = ys;
        self.ka = ka;
    }

    /// The piece's clock: (τ, ṡ, s̈, s⃛) at time `t` from its start (clamped into it).
    fn clock(&self, t: f64) -> (f64, f64, f64, f64) {
        let t = if t.is_finite() { t } else { 0.0 };
        if self.pass {
            return ((self.tau0 + t).clamp(self.tau0, self.tau1), 1.0, 0.0, 0.0);
        }
        let last = self.kt.len().saturating_sub(1);
        if t <= 0.0 || last == 0 {
            return (self.ktau[0], self.kv[0], self.ka[0], 0.0);
        }
        if t >= self.kt[last] {
            return (self.tau1, self.kv[last], self.ka[last], 0.0);
        }
        let k = (self.kt.partition_point(|&x| x <= t) - 1).min(last - 1);
        let c = quintic(
            self.ktau[k],
            self.kv[k],
            self.ka[k],
            self.ktau[k + 1],
            self.kv[k + 1],
            self.ka[k + 1],
            self.kt[k + 1] - self.kt[k],
        );
        let (tau, v, a, j) = eval_quintic(&c, t - self.kt[k]);
        (tau.clamp(self.tau0, self.tau1), v, a, j)
    }

    /// Wheel `i`'s steering geometry at path time `tau`, with the inner sample `r` there:
    /// (φ, dφ/dτ, d²φ/dτ²).
    fn steer_at(
        &self,
        p: &Platform,
        n: usize,
        i: usize,
        tau: f64,
        r: &ReferenceSample,
    ) -> (f64, f64, f64) {
        let g = &self.geo;
        if let Some(b) = self.blend(i, tau) {
            let (phi, d1, d2, _) = eval_quintic(&b.coef, tau - b.a);
            return (phi, d1, d2);
        }
        let m = g.taus.len();
        let grid = if m < 2 {
            g.angle.get(i).copied().unwrap_or(0.0)
        } else {
            let j = g.taus.partition_point(|&x| x <= tau).clamp(1, m - 1) - 1;
            let f = ((tau - g.taus[j]) / (g.taus[j + 1] - g.taus[j])).clamp(0.0, 1.0);
            g.angle[j * n + i] * (1.0 - f) + g.angle[(j + 1) * n + i] * f
        };
        let [u, du, ddu] = contact_kinematics(p, i, r);
        if u[0] == 0.0 && u[1] == 0.0 {
            return (grid, 0.0, 0.0);
        }
        let a = u[1].atan2(u[0]);
        let phi = a + ((grid - a) / PI).round() * PI;
        let (d1, d2) = direction_rates(u, du, ddu);
        (phi, d1, d2)
    }

    /// The blend wheel `i` follows at path time `tau`, if any.
    fn blend(&self, i: usize, tau: f64) -> Option<&Blend> {
        let bl = &self.geo.blends[i];
        let k = bl.partition_point(|b| b.a <= tau);
        (k > 0 && tau <= bl[k - 1].b).then(|| &bl[k - 1])
    }

    /// dφ/dτ and d²φ/dτ² of wheel `i`'s steering geometry at `tau`, given its contact
    /// velocity w and derivatives there.
    fn steer_rates(
        &self,
        i: usize,
        tau: f64,
        w: [f64; 2],
        dw: [f64; 2],
        ddw: [f64; 2],
    ) -> (f64, f64) {
        if let Some(b) = self.blend(i, tau) {
            let (_, d1, d2, _) = eval_quintic(&b.coef, tau - b.a);
            return (d1, d2);
        }
        if w[0] == 0.0 && w[1] == 0.0 {
            return (0.0, 0.0);
        }
        direction_rates(w, dw, ddw)
    }

    /// Wheel `i`'s steering angle at the piece's first and last grid point.
    fn start_angle(&self, i: usize) -> f64 {
        self.geo.angle.get(i).copied().unwrap_or(0.0)
    }
    fn end_angle(&self, n: usize, i: usize) -> f64 {
        let m = self.geo.taus.len();
        self.geo
            .angle
            .get((m.max(1) - 1) * n + i)
            .copied()
            .unwrap_or(0.0)
    }

    /// Wheel `i`'s steering state (angle, rate, acceleration in executed time) where the
    /// piece starts and ends.
    fn steer_start(&self, p: &Platform, inner: &dyn Trajectory, n: usize, i: usize) -> SteerState {
        self.steer_state(p, inner, n, i, 0.0)
    }
    fn steer_end(&self, p: &Platform, inner: &dyn Trajectory, n: usize, i: usize) -> SteerState {
        self.steer_state(p, inner, n, i, self.duration)
    }
    fn steer_state(
        &self,
        p: &Platform,
        inner: &dyn Trajectory,
        n: usize,
        i: usize,
        t: f64,
    ) -> SteerState {
        let (tau, v, a, _) = self.clock(t);
        let r = inner.sample(tau);
        let (phi, d1, d2) = self.steer_at(p, n, i, tau, &r);
        (phi, d1 * v, d2 * v * v + d1 * a)
    }

    /// Largest demand over its share at one instant, from the inner sample `r` at the
    /// clock's τ and the clock (the chain rule of the module docs; the same as
    /// [`crate::reference::limits::wheel_demand`] of the scaled sample, test `demands_match_the_scaled_samples`):
    /// (ratio, limit, wheel, speed-type).
    fn ratio(
        &self,
        p: &Platform,
        n: usize,
        cfg: &TimeScaleConfig,
        r: &ReferenceSample,
        clk: (f64, f64, f64, f64),
    ) -> (f64, Limiting, usize, bool) {
        let l = &p.limits;
        let (fv, fa) = (cfg.speed_fraction, cfg.accel_fraction);
        let (tau, v, a, _) = clk;
        let mut worst = (0.0f64, Limiting::None, 0usize, true);
        for i in 0..n {
            let [w, dw, ddw] = contact_kinematics(p, i, r);
            let sp = w[0].hypot(w[1]);
            let speed_d = if sp > 0.0 {
                (w[0] * dw[0] + w[1] * dw[1]) / sp
            } else {
                0.0
            };
            let (d1, d2) = self.steer_rates(i, tau, w, dw, ddw);
            for (val, lim, what, speed) in [
                (
                    sp * v / p.wheel_radius,
                    fv * l.wheel_speed,
                    Limiting::WheelSpeed,
                    true,
                ),
                (
                    (speed_d * v * v + sp * a) / p.wheel_radius,
                    fa * l.wheel_accel,
                    Limiting::WheelAccel,
                    false,
                ),
                (d1 * v, fv * l.steer_rate, Limiting::SteerRate, true),
                (
                    d2 * v * v + d1 * a,
                    fa * l.steer_accel,
                    Limiting::SteerAccel,
                    false,
                ),
                (r.dz[3 + i] * v, fv * l.leg_speed, Limiting::LegSpeed, true),
                (
                    sp * d1 * v * v,
                    cfg.lateral_accel,
                    Limiting::SteerRate,
                    true,
                ),
            ] {
                let q = if val.is_finite() {
                    val.abs() / lim
                } else {
                    f64::INFINITY
                };
                if q > worst.0 {
                    worst = (q, what, i, speed);
                }
            }
        }
        worst
    }

    /// Checks the demands at the grid points and between them: returns the violations
    /// (time from the piece's start, ratio, speed-type) beyond the tolerance, and records the
    /// largest demand, the slowest point and the binding limit at every grid point.
    #[allow(clippy::too_many_arguments)]
    fn verify(
        &mut self,
        p: &Platform,
        inner: &dyn Trajectory,
        cfg: &TimeScaleConfig,
        n: usize,
        taus: &[f64],
        caps: &[f64],
        open: (bool, bool),
    ) -> Vec<(f64, f64, bool)> {
        let kt: Vec<f64> = if self.pass {
            taus.iter().map(|t| t - self.tau0).collect()
        } else {
            self.kt.clone()
        };
        let mut worst = 0.0f64;
        let mut out = Vec::new();
        let mut reason = Vec::with_capacity(kt.len());
        let mut min = (f64::INFINITY, 0.0, Limiting::None, 0usize);
        let r0 = start_steer_rate(p, cfg);
        let ends = (
            kt.first().copied().filter(|_| open.0),
            kt.last().copied().filter(|_| open.1),
        );
        let mut check = |t: f64| {
            let clk = self.clock(t);
            let r = inner.sample(clk.0);
            let mut q = self.ratio(p, n, cfg, &r, clk);
            if Some(t) == ends.0 || Some(t) == ends.1 {
                for i in 0..n {
                    let [w, dw, ddw] = contact_kinematics(p, i, &r);
                    let rate = self.steer_rates(i, clk.0, w, dw, ddw).0 * clk.1;
                    let e = rate.abs() / r0;
                    if e > q.0 {
                        q = (e, Limiting::SteerAccel, i, false);
                    }
                }
            }
            worst = worst.max(q.0);
            if q.0 > 1.0 + VERIFY_TOLERANCE {
                out.push((t, q.0, q.3));
            }
            q
        };
        for (j, &t) in kt.iter().enumerate() {
            let (ratio, what, wheel, _) = check(t);
            if let Some(&t1) = kt.get(j + 1) {
                for q in 1..4 {
                    check(t + (t1 - t) * q as f64 / 4.0);
                }
            }
            let v = if self.pass { 1.0 } else { self.kv[j] };
            reason.push((what, wheel as u8, v < caps[j] * (1.0 - 1e-9)));
            // Where the path asks nothing of any actuator (the platform at rest) the clock's
            // rate means nothing: the slowest scale is taken where something moves.
            if v < min.0 && ratio > 0.0 {
                min = (v, t, what, wheel);
            }
        }
        self.reason = reason;
        self.min = min;
        self.max_ratio = worst;
        out
    }

    /// The executed-time spans (from the piece's start) of the runs of near-stop grid points.
    fn near_spans(&self, taus: &[f64], near: &[bool]) -> Vec<(f64, f64)> {
        let time = |j: usize| {
            if self.pass {
                taus[j] - self.tau0
            } else {
                self.kt.get(j).copied().unwrap_or(self.duration)
            }
        };
        let mut out = Vec::new();
        let mut j = 0;
        while j < near.len() {
            if !near[j] {
                j += 1;
                continue;
            }
            let start = j;
            while j < near.len() && near[j] {
                j += 1;
            }
            out.push((time(start), time(j - 1)));
        }
        out
    }

    /// The binding limit at path time `tau` and whether the clock runs below its cap there.
    fn reason_at(&self, tau: f64) -> (Limiting, u8, bool) {
        let taus = &self.geo.taus;
        let m = self.reason.len().min(taus.len());
        if m == 0 {
            (Limiting::None, 0, false)
        } else {
            let k = taus.partition_point(|&x| x <= tau).clamp(1, m) - 1;
            self.reason[k]
        }
    }
}

/// The refusal for a timing that would last too long ([`too_slow`]) at the slowest point of
/// `piece`.
fn piece_too_slow(
    p: &Platform,
    cfg: &TimeScaleConfig,
    inner: &dyn Trajectory,
    n: usize,
    piece: &Piece,
    duration: f64,
) -> TimeScaleError {
    let tau = piece.clock(piece.min.1).0;
    match Grid::build(p, inner, cfg, n, tau, tau) {
        Ok(g) => too_slow(p, cfg, inner, &g, n, 0, duration),
        Err(e) => e,
    }
}

/// Whether the platform comes (nearly) to rest between two motions: its fastest wheel drops
/// below 2 % of the path's fastest after having moved faster than 10 %, and moves that fast
/// again later.
fn interior_stop(wmax: &[f64]) -> bool {
    let top = wmax.iter().copied().fold(0.0, f64::max);
    if top.is_nan() || top <= 0.0 {
        return false;
    }
    let mut moved = false;
    let mut stopped = false;
    for &w in wmax {
        if w >= 0.1 * top {
            if stopped {
                return true;
            }
            moved = true;
        } else if moved && w < 0.02 * top {
            stopped = true;
        }
    }
    false
}

/// The time (s) between two clock knots Δτ apart with (ṡ, s̈) = (v0, a0) and (v1, a1): the
/// one for which ṡ is the cubic Hermite between them, Δτ = Δt (v0 + v1)/2 + Δt² (a0 − a1)/12
/// (so the quintic clock through the knots does not wiggle to make up a different Δτ);
/// [`segment_time`] where that has no positive root.
fn knot_time(dtau: f64, v0: f64, v1: f64, a0: f64, a1: f64) -> f64 {
    let guess = segment_time(dtau, v0, v1);
    let (qa, qb, qc) = ((a0 - a1) / 12.0, 0.5 * (v0 + v1), -dtau);
    if qa.abs() * guess <= 1e-12 * qb {
        return guess;
    }
    let disc = qb * qb - 4.0 * qa * qc;
    if disc.is_nan() || disc < 0.0 {
        return guess;
    }
    // The root near the trapezoid's, in the form that stays accurate for small qa.
    let root = 2.0 * dtau / (qb + disc.sqrt());
    if root.is_finite() && root > 0.0 && (root - guess).abs() < 0.5 * guess {
        root
    } else {
        guess
    }
}

/// Time (s) to advance `dtau` with ṡ going from `y0` to `y1`, ṡ² linear in τ (constant s̈).
fn segment_time(dtau: f64, y0: f64, y1: f64) -> f64 {
    let (a, b) = (y0.max(1e-150), y1.max(1e-150));
    2.0 * dtau / (a + b)
}

/// The backward and forward passes (module docs); returns x = ṡ² per grid point.
fn topp(pts: &[Point], fix: &[f64], taus: &[f64]) -> Vec<f64> {
    let points = taus.len();
    let xbar = |j: usize| (pts[j].xbar * fix[j]).max(X_FLOOR);
    let mut x = vec![0.0; points];
    if points == 1 {
        x[0] = xbar(0);
        return x;
    }
    let mut k = vec![0.0; points];
    k[points - 1] = xbar(points - 1);
    for j in (0..points - 1).rev() {
        let h = taus[j + 1] - taus[j];
        let mut kj = xbar(j);
        for c in &pts[j].acc {
            let ((pl, ql), _) = c.bounds();
            kj = kj.min(step_back(h, pl, ql, k[j + 1]));
        }
        k[j] = if kj.is_nan() {
            X_FLOOR
        } else {
            kj.max(X_FLOOR)
        };
    }
    x[0] = k[0];
    for j in 0..points - 1 {
        let h = taus[j + 1] - taus[j];
        let next = pts[j]
            .acc
            .iter()
            .map(|c| {
                let (_, (r, s)) = c.bounds();
                step(h, r, s, x[j])
            })
            .fold(f64::INFINITY, f64::min);
        x[j + 1] = if next.is_nan() {
            k[j + 1]
        } else {
            next.min(k[j + 1]).max(X_FLOOR)
        };
    }
    x
}

/// x at the end of an interval of length `h` in τ from `x` at its start, with s̈ on the bound
/// r + s x of one constraint (dx/dτ = 2 s̈). Where the bound falls with x (s < 0: a wheel whose
/// speed grows along the path, so its acceleration |w'| ṡ² grows with x) the step is
/// semi-implicit — the bound taken at the interval's end, x' = (x + 2hr)/(1 − 2hs) — because the
/// explicit step x + 2h(r + s x) overshoots the bound's equilibrium x = −r/s when 2h|s| > 1
/// (near rest, where |w| is small, |s| = |w'|/|w| is large: the explicit step then stopped the
/// clock at a grid point and the run never ended). Otherwise the explicit step.
fn step(h: f64, r: f64, s: f64, x: f64) -> f64 {
    if s < 0.0 {
        (x + 2.0 * h * r) / (1.0 - 2.0 * h * s)
    } else {
        x + 2.0 * h * (r + s * x)
    }
}

/// The largest x at an interval's start from which the lower bound p + q x of one constraint
/// (decelerating as hard as it allows, the step of [`step`]) reaches at most `next` at its
/// end.
fn step_back(h: f64, p: f64, q: f64, next: f64) -> f64 {
    if q < 0.0 {
        next * (1.0 - 2.0 * h * q) - 2.0 * h * p
    } else {
        // x (1 + 2hq) + 2hp ≤ next, 1 + 2hq > 0.
        (next - 2.0 * h * p) / (1.0 + 2.0 * h * q)
    }
}

/// A function sampled every `h` from 0, linear between the samples and held beyond the ends.
struct Sampled {
    vals: Vec<f64>,
    h: f64,
    /// ∫₀^{t_m} (trapezoids, exact for the linear pieces).
    cum: Vec<f64>,
}

impl Sampled {
    fn new(vals: Vec<f64>, h: f64) -> Self {
        let mut cum = Vec::with_capacity(vals.len());
        cum.push(0.0);
        for m in 1..vals.len() {
            cum.push(cum[m - 1] + 0.5 * (vals[m - 1] + vals[m]) * h);
        }
        Self { vals, h, cum }
    }

    fn at(&self, t: f64) -> f64 {
        let n = self.vals.len();
        if t <= 0.0 {
            return self.vals[0];
        }
        let m = ((t / self.h).floor() as usize).min(n - 1);
        if m + 1 >= n {
            return self.vals[n - 1];
        }
        let f = (t - m as f64 * self.h) / self.h;
        self.vals[m] + (self.vals[m + 1] - self.vals[m]) * f
    }

    fn integral(&self, t: f64) -> f64 {
        let n = self.vals.len();
        if t <= 0.0 {
            return self.vals[0] * t;
        }
        let m = ((t / self.h).floor() as usize).min(n - 1);
        let d = t - m as f64 * self.h;
        if m + 1 >= n {
            return self.cum[n - 1] + self.vals[n - 1] * d;
        }
        self.cum[m] + d * 0.5 * (self.vals[m] + self.at(t))
    }

    /// The average over [t − w/2, t + w/2] and its derivative in t; exactly the value where
    /// every sample the window touches is the same.
    fn box_avg(&self, t: f64, w: f64) -> (f64, f64) {
        let (a, b) = (t - 0.5 * w, t + 0.5 * w);
        let n = self.vals.len();
        let ma = ((a / self.h).floor().max(0.0) as usize).min(n - 1);
        let mb = ((b / self.h).ceil().max(0.0) as usize).min(n - 1);
        let win = &self.vals[ma..=mb];
        let lo = win.iter().copied().fold(f64::INFINITY, f64::min);
        let hi = win.iter().copied().fold(f64::NEG_INFINITY, f64::max);
        if lo == hi {
            return (lo, 0.0);
        }
        (
            ((self.integral(b) - self.integral(a)) / w).clamp(lo, hi),
            (self.at(b) - self.at(a)) / w,
        )
    }
}

/// The smoothing of the time-optimal profile (module docs): ṡ as a function of its own time
/// t' (linear within each grid interval, s̈ constant there) is eroded over a window of
/// `jerk_time` plus two samples either side, then averaged twice over `jerk_time` (a
/// triangular kernel: s̈ continuous and building up over at least `jerk_time`), and read back
/// at the grid points with its exact slope. Returns (ṡ_j, s̈_j) per grid point, s̈ in the
/// executed time: s̈ = dṡ/dτ ṡ = (dṡ/dt') ṡ / ṡ_topp. Never above the time-optimal ṡ at a
/// grid point (every value averaged for time t comes from an erosion window containing t);
/// exactly 1 (and s̈ = 0) where that is 1 throughout the window.
fn smooth_in_time(taus: &[f64], x: &[f64], jerk_time: f64) -> (Vec<f64>, Vec<f64>) {
    let points = taus.len();
    let y: Vec<f64> = x.iter().map(|v| v.sqrt()).collect();
    let flat = (y.clone(), vec![0.0; points]);
    if points < 2 {
        return flat;
    }
    let mut tt = Vec::with_capacity(points);
    let mut t = 0.0;
    for j in 0..points {
        if j > 0 {
            t += segment_time(taus[j] - taus[j - 1], y[j - 1], y[j]);
        }
        tt.push(t);
    }
    let total = t;
    if total.is_nan() || total <= 0.0 {
        return flat;
    }
    let h = (jerk_time / 8.0).max(total / (4 * MAX_GRID) as f64);
    let half = ((0.5 * jerk_time / h).round() as usize).max(1);
    let width = 2.0 * half as f64 * h;
    let samples = (total / h).ceil() as usize + 1;
    // ṡ of the time-optimal profile at time t' in interval j (linear within it).
    let sdot = |t: f64, j: usize| -> f64 {
        if j + 1 >= points {
            return y[points - 1];
        }
        let dt = tt[j + 1] - tt[j];
        if dt <= 0.0 || y[j] == y[j + 1] {
            return y[j];
        }
        let f = ((t - tt[j]) / dt).clamp(0.0, 1.0);
        y[j] + (y[j + 1] - y[j]) * f
    };
    let seg = |t: f64| tt.partition_point(|&x| x <= t).clamp(1, points) - 1;
    // Erosion at the samples: the minimum of the piecewise-linear ṡ over [t − w, t + w] is at
    // the window's ends or at a grid point inside.
    let w = width + 2.0 * h;
    let eroded: Vec<f64> = (0..samples)
        .map(|m| {
            let t = m as f64 * h;
            let (a, b) = ((t - w).max(0.0), (t + w).min(total));
            let (ja, jb) = (seg(a), seg(b));
            let mut v = sdot(a, ja).min(sdot(b, jb));
            for j in ja + 1..=jb.min(points - 1) {
                v = v.min(y[j]);
            }
            v
        })
        .collect();
    let e = Sampled::new(eroded, h);
    let first = Sampled::new(
        (0..samples)
            .map(|m| e.box_avg(m as f64 * h, width).0)
            .collect(),
        h,
    );
    let mut ys = Vec::with_capacity(points);
    let mut accel = Vec::with_capacity(points);
    for j in 0..points {
        let (v, slope) = first.box_avg(tt[j], width);
        let v = v.min(y[j]);
        ys.push(v);
        accel.push(if y[j] > 0.0 { slope * v / y[j] } else { 0.0 });
    }
    (ys, accel)
}

/// The refusal for a timing that would last too long, naming the binding speed limit at the
/// slowest point.
fn too_slow(
    p: &Platform,
    cfg: &TimeScaleConfig,
    inner: &dyn Trajectory,
    g: &Grid,
    n: usize,
    j: usize,
    duration: f64,
) -> TimeScaleError {
    let l = &p.limits;
    let fv = cfg.speed_fraction;
    let mut worst = (0.0f64, "wheel_speed", 0usize, 0.0, l.wheel_speed);
    for i in 0..n {
        let q = &g.geo[j * n + i];
        for (need, lim, field) in [
            (q.speed / p.wheel_radius, l.wheel_speed, "wheel_speed"),
            (q.rate.abs(), l.steer_rate, "steer_rate"),
            (q.leg_rate, l.leg_speed, "leg_speed"),
        ] {
            let r = need / (fv * lim);
            if r > worst.0 {
                worst = (r, field, i, need, lim);
            }
        }
    }
    let tau = g.taus[j];
    TimeScaleError::TooSlow {
        field: worst.1,
        waypoint: inner.waypoint_near(tau),
        t: tau,
        wheel: worst.2,
        value: worst.3,
        limit: worst.4,
        duration,
    }
}

/// Classifies every wheel's direction along the grid (steered by, or held and blended),
/// continues the angles across branches, fills the steering geometry into the grid, and
/// finds kinks. Returns the geometry and whether a wheel is held while the platform moves.
fn steering_geometry(
    p: &Platform,
    inner: &dyn Trajectory,
    cfg: &TimeScaleConfig,
    n: usize,
    g: &mut Grid,
) -> Result<(SteerGeometry, bool), TimeScaleError> {
    let points = g.points();
    let taus = g.taus.clone();
    let mut sg = SteerGeometry {
        taus: taus.clone(),
        angle: vec![0.0; points * n],
        blends: vec![Vec::new(); n],
    };
    let mut steer_needed = false;
    let near = near_stops(g);
    for i in 0..n {
        // Points held only because the wheel never reaches HOLD_SPEED there (the controllers
        // hold it by themselves; they need no steering reference for it).
        let mut slow_hold = vec![false; points];
        // Held until the wheel moves faster than twice `hold_ratio` of the fastest wheel,
        // steered until it is slower than `hold_ratio` (hysteresis: a wheel whose speed
        // hovers about the threshold, like the pivot wheel of a pivot through waypoints,
        // whose contact point moves by the spline's interpolation error, neither toggles).
        let mut steered = false;
        for j in 0..points {
            let wmax = g.wmax[j];
            let q = &mut g.geo[j * n + i];
            // The whole platform slower than NEAR_REST even at the clock's cap: a near stop,
            // where no wheel's direction of travel means anything (module docs, "Stops and
            // dwells").
            if wmax <= REST_W || q.speed <= 0.0 || near[j] {
                q.defined = false;
                continue;
            }
            let ratio = q.speed / wmax;
            steered = if steered {
                ratio >= cfg.hold_ratio
            } else {
                ratio >= 2.0 * cfg.hold_ratio
            };
            // A wheel is steered by its direction of travel unless it barely moves compared
            // with the platform (above), or never moves faster than HOLD_SPEED here while the
            // platform moves clearly (the controllers hold such a wheel anyway: it follows the
            // steering reference).
            let cap = g.caps[j];
            let slow = q.speed * cap < HOLD_SPEED && wmax * cap >= 2.0 * HOLD_SPEED;
            slow_hold[j] = slow && steered;
            q.defined = steered && !slow;
        }
        // Continue the direction of travel across branches over the defined points.
        let mut prev: Option<(usize, f64, f64)> = None; // (j, angle, rate)
        for j in 0..points {
            let q = g.geo[j * n + i];
            if !q.defined {
                continue;
            }
            let a = q.w[1].atan2(q.w[0]);
            let angle = match prev {
                None => a,
                Some((pj, pa, pr)) => {
                    // Right after a held stretch: the branch nearest the angle before it.
                    let adjacent = pj + 1 == j;
                    let predicted = if adjacent {
                        pa + 0.5 * (pr + q.raw_rate) * (taus[j] - taus[pj])
                    } else {
                        pa
                    };
                    let phi = a + ((predicted - a) / PI).round() * PI;
                    if adjacent && (phi - predicted).abs() > KINK_SUSPECT {
                        if let Some(angle) = kink(p, inner, i, taus[pj], taus[j]) {
                            let t = 0.5 * (taus[pj] + taus[j]);
                            return Err(TimeScaleError::SteeringKink {
                                waypoint: inner.waypoint_near(t),
                                t,
                                wheel: i,
                                angle,
                            });
                        }
                    }
                    phi
                }
            };
            let q = &mut g.geo[j * n + i];
            q.angle = angle;
            q.rate = q.raw_rate;
            q.accel = q.raw_accel;
            prev = Some((j, angle, q.raw_rate));
        }
        let Some(first) = (0..points).find(|&j| g.geo[j * n + i].defined) else {
            // Never steered by its direction: hold the direction it has where it moves most
            // (relative to the platform), on the branch nearest 0, or 0.
            let best = (0..points)
                .filter(|&j| g.wmax[j] > REST_W)
                .max_by(|&a, &b| {
                    (g.geo[a * n + i].speed / g.wmax[a])
                        .total_cmp(&(g.geo[b * n + i].speed / g.wmax[b]))
                });
            let angle = best
                .map(|j| {
                    let w = g.geo[j * n + i].w;
                    let a = w[1].atan2(w[0]);
                    if a.abs() > FRAC_PI_2 {
                        a - a.signum() * PI
                    } else {
                        a
                    }
                })
                .filter(|a| a.is_finite())
                .unwrap_or(0.0);
            if best.is_some() {
                steer_needed = true;
            }
            for j in 0..points {
                let q = &mut g.geo[j * n + i];
                q.angle = angle;
                q.rate = 0.0;
                q.accel = 0.0;
                sg.angle[j * n + i] = angle;
            }
            sg.blends[i].push(Blend {
                a: taus[0],
                b: taus[points - 1],
                coef: [angle, 0.0, 0.0, 0.0, 0.0, 0.0],
            });
            continue;
        };
        // Held stretches: blends (constants before the first and after the last defined
        // point).
        let mut j = 0;
        while j < points {
            if g.geo[j * n + i].defined {
                j += 1;
                continue;
            }
            let start = j;
            while j < points && !g.geo[j * n + i].defined {
                j += 1;
            }
            let end = j;
            if (start..end).any(|k| g.wmax[k] > REST_W && !slow_hold[k]) {
                steer_needed = true;
            }
            // Where the whole platform is at rest at the path's start or end, the direction
            // there is the limit of the directions next to it: continued (to second order)
            // from the nearest steered point, so the steering rate has no step. A wheel held
            // while the platform moves holds its angle.
            let at_rest = (start..end).all(|k| g.wmax[k] <= REST_W);
            let near_rest = !at_rest && (start..end).all(|k| near[k]);
            let blend = if start == 0 {
                let q = g.geo[first * n + i];
                let h = taus[first] - taus[0];
                let coef = if near_rest {
                    // From rest, the rate building up over the stretch to the first steered
                    // point's.
                    quintic(
                        q.angle - 0.5 * q.rate * h,
                        0.0,
                        0.0,
                        q.angle,
                        q.rate,
                        q.accel,
                        h,
                    )
                } else if at_rest {
                    [
                        q.angle - q.rate * h + 0.5 * q.accel * h * h,
                        q.rate - q.accel * h,
                        0.5 * q.accel,
                        0.0,
                        0.0,
                        0.0,
                    ]
                } else {
                    [q.angle, 0.0, 0.0, 0.0, 0.0, 0.0]
                };
                Blend {
                    a: taus[0],
                    b: taus[first],
                    coef,
                }
            } else if end == points {
                let q = g.geo[(start - 1) * n + i];
                let h = taus[points - 1] - taus[start - 1];
                let coef = if near_rest {
                    // To rest over the stretch.
                    quintic(
                        q.angle,
                        q.rate,
                        q.accel,
                        q.angle + 0.5 * q.rate * h,
                        0.0,
                        0.0,
                        h,
                    )
                } else if at_rest {
                    [q.angle, q.rate, 0.5 * q.accel, 0.0, 0.0, 0.0]
                } else {
                    [q.angle, 0.0, 0.0, 0.0, 0.0, 0.0]
                };
                Blend {
                    a: taus[start - 1],
                    b: taus[points - 1],
                    coef,
                }
            } else {
                let (q0, q1) = (g.geo[(start - 1) * n + i], g.geo[end * n + i]);
                let (a, b) = (taus[start - 1], taus[end]);
                let coef = quintic(
                    q0.angle,
                    q0.rate,
                    q0.accel,
                    q1.angle,
                    q1.rate,
                    q1.accel,
                    b - a,
                );
                Blend { a, b, coef }
            };
            for k in start..end {
                let (phi, d1, d2, _) = eval_quintic(&blend.coef, (taus[k] - blend.a).max(0.0));
                let q = &mut g.geo[k * n + i];
                q.angle = phi;
                q.rate = d1;
                q.accel = d2;
            }
            sg.blends[i].push(blend);
        }
        for j in 0..points {
            sg.angle[j * n + i] = g.geo[j * n + i].angle;
        }
    }
    Ok((sg, steer_needed))
}

/// The grid points of the path's near stops (module docs, "Stops and dwells"): maximal runs
/// of points inside a piece where the fastest wheel is slower than [`NEAR_REST`] at the
/// clock's cap, along which the platform travels less than [`NEAR_REST_TRAVEL`] (a
/// deliberately slow motion over a longer distance is steered by its directions as any
/// other).
fn near_stops(g: &Grid) -> Vec<bool> {
    let points = g.points();
    let mut near = vec![false; points];
    let mut j = 0;
    while j < points {
        if g.wmax[j] * g.caps[j] >= NEAR_REST {
            j += 1;
            continue;
        }
        let start = j;
        let mut travel = 0.0;
        while j < points && g.wmax[j] * g.caps[j] < NEAR_REST {
            if j > start {
                travel += 0.5 * (g.wmax[j] + g.wmax[j - 1]) * (g.taus[j] - g.taus[j - 1]);
            }
            j += 1;
        }
        // A run that starts or ends the piece leaves (or reaches) the exact stop there, whose
        // dwell steers the wheels to the path's limit direction: where no wheel's direction
        // of travel turns by more than END_RUN_TURN along the run, the wheels roll on along
        // it without a blend (a path that starts straight from rest is followed as it is).
        let at_end = start == 0 || j == points;
        if travel <= NEAR_REST_TRAVEL && (!at_end || run_turns(g, start, j) > END_RUN_TURN) {
            for v in &mut near[start..j] {
                *v = true;
            }
        }
    }
    near
}

/// Largest turn (rad, modulo π) of a wheel's direction of travel over the grid points
/// `a..b` (points where it rests are skipped).
fn run_turns(g: &Grid, a: usize, b: usize) -> f64 {
    let n = g.geo.len() / g.points().max(1);
    let mut worst = 0.0f64;
    for i in 0..n {
        let (mut lo, mut hi, mut first): (f64, f64, Option<f64>) = (0.0, 0.0, None);
        for j in a..b {
            let q = &g.geo[j * n + i];
            if q.speed <= REST_W {
                continue;
            }
            let d = q.w[1].atan2(q.w[0]);
            let f = *first.get_or_insert(d);
            let mut e = d - f;
            e -= (e / PI).round() * PI;
            lo = lo.min(e);
            hi = hi.max(e);
        }
        worst = worst.max(hi - lo);
    }
    worst
}

/// Whether wheel `i`'s direction of travel jumps between path times `a` and `b`: bisects
/// towards the larger change beyond what the steering rate explains; a change that does not
/// shrink with the interval is a jump. Returns its size.
fn kink(p: &Platform, inner: &dyn Trajectory, i: usize, mut a: f64, mut b: f64) -> Option<f64> {
    let dir = |t: f64| {
        let r = inner.sample(t);
        let [u, du, ddu] = contact_kinematics(p, i, &r);
        let (d1, _) = direction_rates(u, du, ddu);
        (u[1].atan2(u[0]), d1, u[0].hypot(u[1]))
    };
    // Change of the direction over an interval beyond the rate's trapezoid, modulo π.
    let excess = |s: (f64, f64, f64), e: (f64, f64, f64), h: f64| {
        let d = e.0 - (s.0 + 0.5 * (s.1 + e.1) * h);
        (d - (d / PI).round() * PI).abs()
    };
    let (mut da, mut db) = (dir(a), dir(b));
    for _ in 0..60 {
        let m = 0.5 * (a + b);
        let dm = dir(m);
        if excess(da, dm, m - a) >= excess(dm, db, b - m) {
            b = m;
            db = dm;
        } else {
            a = m;
            da = dm;
        }
        if b - a <= 1e-9 * (1.0 + a.abs()) {
            break;
        }
    }
    let e = excess(da, db, b - a);
    // A wheel passing through rest reverses (a held stretch), it does not kink.
    let moving = da.2.min(db.2) > 1e-6;
    (moving && e > KINK_SUSPECT / 2.0).then_some(e)
}

impl Trajectory for ScaledTrajectory {
    fn sample(&self, t: f64) -> ReferenceSample {
        self.sample_full(t).0
    }
    fn duration(&self) -> f64 {
        self.executed
    }
    fn n_legs(&self) -> usize {
        self.inner.n_legs()
    }
    fn waypoint_near(&self, t: f64) -> Option<usize> {
        self.inner.waypoint_near(self.clock(t).0)
    }
    fn time_scale(&self, t: f64) -> Option<ScaleStatus> {
        let (tau, v, _, _) = self.clock(t);
        let running = t < self.executed;
        let (what, wheel, slowed) = match self.locate(t) {
            _ if self.pass => self.pieces[0].reason_at(tau),
            (Span::Piece(k), _) => self.pieces[k].reason_at(tau),
            // A dwell: the clock holds while the wheels re-steer.
            (Span::Dwell(_), _) => (Limiting::Aligning, 0, true),
        };
        Some(ScaleStatus {
            scale: if running { v } else { 1.0 },
            limiting: if slowed && running {
                what
            } else {
                Limiting::None
            },
            wheel: wheel as usize,
        })
    }
    fn timing(&self) -> Option<Timing> {
        Some(self.timing)
    }
    fn avoidance_at(&self, t: f64) -> Option<crate::reference::status::AvoidanceState> {
        // The avoided path's record at the path time the clock has reached.
        self.inner.avoidance_at(self.clock(t).0)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::reference::limits::wheel_demand;
    use crate::reference::trajectory::{QuinticSpline, Waypoint, WaypointSpec};
    use crate::types::ZVec;

    fn z(x: f64, y: f64, th: f64, legs: [f64; 4]) -> ZVec {
        let mut z = ZVec::zeros();
        z[0] = x;
        z[1] = y;
        z[2] = th;
        for i in 0..4 {
            z[3 + i] = legs[i];
        }
        z
    }

    /// Far beyond the limits: 1.1 m, 1.5 rad and legs limit to limit in 2 s, then on.
    fn fast() -> Vec<Waypoint> {
        let l = [0.45; 4];
        vec![
            Waypoint {
                t: 0.0,
                z: z(0.0, 0.0, 0.0, l),
            },
            Waypoint {
                t: 2.0,
                z: z(1.0, 0.5, 1.5, [0.56, 0.37, 0.56, 0.37]),
            },
            Waypoint {
                t: 3.5,
                z: z(1.5, 1.5, 0.0, l),
            },
            Waypoint {
                t: 5.0,
                z: z(0.5, 1.0, -1.0, [0.56, 0.37, 0.56, 0.37]),
            },
        ]
    }

    fn plan(w: &[Waypoint]) -> ScaledTrajectory {
        let p = Platform::justin();
        let s = QuinticSpline::new(&p, w).expect("valid waypoints");
        ScaledTrajectory::plan(&p, Box::new(s), TimeScaleConfig::default()).expect("plannable")
    }

    #[test]
    fn seed000_passes_through_bit_for_bit() {
        let p = Platform::justin();
        let inner = crate::reference::trajectory::seed000_experiment(&p);
        let s = ScaledTrajectory::plan(&p, Box::new(inner), TimeScaleConfig::default()).unwrap();
        assert!(s.is_pass_through());
        let t = s.timing().unwrap();
        assert_eq!(t.executed_duration_s, inner.duration());
        assert_eq!((t.min_scale, t.limiting), (1.0, Limiting::None));
        assert!(!t.steer_reference);
        assert!(
            t.max_ratio < 0.5,
            "seed 000 uses {} of its shares",
            t.max_ratio
        );
        for k in 0..=3000 {
            let tt = k as f64 * 0.0097 - 0.5;
            assert_eq!(s.sample(tt), inner.sample(tt), "t = {tt}");
        }
        assert_eq!(s.time_scale(3.0).unwrap().scale, 1.0);
    }

    #[test]
    fn a_trajectory_beyond_the_limits_is_stretched_into_its_shares() {
        let p = Platform::justin();
        let l = p.limits;
        let cfg = TimeScaleConfig::default();
        let w = fast();
        let inner = QuinticSpline::new(&p, &w).unwrap();
        // Unscaled it asks far more than the limits allow.
        let worst = (0..=500)
            .map(|k| {
                crate::reference::limits::reference_ratio(&p, &inner.sample(k as f64 * 0.01)).0
            })
            .fold(0.0, f64::max);
        assert!(worst > 3.0, "{worst}");
        let s = plan(&w);
        let t = s.timing().unwrap();
        assert!(!s.is_pass_through());
        assert!(t.executed_duration_s > 5.5, "{t:?}");
        assert!(t.min_scale < 0.5 && t.limiting != Limiting::None, "{t:?}");
        assert!(t.steer_reference);
        // Every actuator within its share (and the tolerance), checked with the limits
        // module's own function on the scaled samples every 2 ms; the path is unchanged.
        let tol = 1.0 + VERIFY_TOLERANCE + 1e-6;
        let mut prev_tau = -1.0;
        let steps = (t.executed_duration_s / 0.002).ceil() as usize;
        for k in 0..=steps {
            let tt = k as f64 * 0.002;
            let r = s.sample(tt);
            let (tau, v, _, _) = s.clock(tt);
            assert!(tau >= prev_tau, "the clock runs forwards");
            assert!(v <= 1.0 + 1e-9, "a timed trajectory is only slowed down");
            prev_tau = tau;
            assert_eq!(
                r.z,
                inner.sample(tau).z,
                "the path is the inner trajectory's"
            );
            for i in 0..4 {
                let d = wheel_demand(&p, i, &r);
                assert!(
                    d.speed <= cfg.speed_fraction * l.wheel_speed * tol,
                    "t {tt} wheel {i} speed {}",
                    d.speed
                );
                assert!(
                    d.accel.abs() <= cfg.accel_fraction * l.wheel_accel * tol,
                    "t {tt} wheel {i} accel {}",
                    d.accel
                );
                assert!(d.leg_speed <= cfg.speed_fraction * l.leg_speed * tol);
                // The steering reference's rate and acceleration: the direction of travel's
                // where the wheel moves (the same numbers), the blends' where it is held.
                if d.moving && (r.steer.angle[i] - d.steer_angle).sin().abs() < 1e-6 {
                    assert!(
                        (r.steer.rate[i] - d.steer_rate).abs() < 1e-6 * (1.0 + d.steer_rate.abs())
                    );
                }
                assert!(
                    r.steer.rate[i].abs() <= cfg.speed_fraction * l.steer_rate * tol,
                    "t {tt} wheel {i} steer rate {}",
                    r.steer.rate[i]
                );
                assert!(
                    r.steer.accel[i].abs() <= cfg.accel_fraction * l.steer_accel * tol,
                    "t {tt} wheel {i} steer accel {}",
                    r.steer.accel[i]
                );
                assert!(
                    d.speed * p.wheel_radius * r.steer.rate[i].abs() <= cfg.lateral_accel * tol
                );
            }
        }
        let end = s.sample(t.executed_duration_s + 1.0);
        assert_eq!(end.z, inner.sample(inner.duration()).z);
        assert!(end.dz.iter().chain(end.ddz.iter()).all(|v| *v == 0.0));
    }

    #[test]
    fn the_scaled_reference_is_c2_with_bounded_jerk() {
        let s = plan(&fast());
        let d = s.duration();
        let h = 1e-4;
        let (mut max_jump_a, mut max_jerk) = (0.0f64, 0.0f64);
        let mut prev = s.sample(0.0);
        let mut prev_clock = s.clock(0.0);
        for k in 1..=(d / h) as usize {
            let tt = k as f64 * h;
            let r = s.sample(tt);
            let c = s.clock(tt);
            for c_ in 0..7 {
                // ż is the derivative of z and z̈ of ż (trapezoid over one step).
                let fd = (r.z[c_] - prev.z[c_]) / h;
                assert!(
                    (fd - 0.5 * (r.dz[c_] + prev.dz[c_])).abs() < 2e-4,
                    "t {tt} dz[{c_}]"
                );
                let fd2 = (r.dz[c_] - prev.dz[c_]) / h;
                assert!(
                    (fd2 - 0.5 * (r.ddz[c_] + prev.ddz[c_])).abs() < 2e-2,
                    "t {tt} ddz[{c_}]"
                );
                max_jump_a = max_jump_a.max((r.ddz[c_] - prev.ddz[c_]).abs());
            }
            // ṡ and s̈ continuous, s⃛ bounded — except where a dwell starts or ends: the path
            // rests there (ż* = z̈* = 0, checked below), so the clock may start and stop
            // at once while z stays C².
            let at_dwell = s
                .dwells()
                .iter()
                .any(|&(a, b)| (tt - a).abs() <= h || (tt - b).abs() <= h);
            if at_dwell {
                for &(a, b) in s.dwells() {
                    for e in [a, b] {
                        let r = s.inner.sample(s.clock(e).0);
                        assert!(
                            r.dz.iter().chain(r.ddz.iter()).all(|v| v.abs() < 1e-9),
                            "the path rests where a dwell starts or ends ({e})"
                        );
                    }
                }
                prev = s.sample(tt);
                prev_clock = c;
                continue;
            }
            assert!((c.1 - prev_clock.1).abs() < 1e-3, "ṡ jumps at {tt}");
            assert!(
                (c.2 - prev_clock.2).abs() < 2e-2,
                "s̈ jumps at {tt}: {} → {}",
                prev_clock.2,
                c.2
            );
            max_jerk = max_jerk.max(c.3.abs());
            prev = r;
            prev_clock = c;
        }
        assert!(max_jump_a < 0.05, "z̈ continuous: largest step {max_jump_a}");
        assert!(
            max_jerk.is_finite() && max_jerk < 500.0,
            "s⃛ bounded: {max_jerk}"
        );
    }

    #[test]
    fn demands_match_the_scaled_samples() {
        let s = plan(&fast());
        let cfg = TimeScaleConfig::default();
        let p = Platform::justin();
        for k in 0..400 {
            let tt = s.duration() * k as f64 / 400.0;
            let clk = s.clock(tt);
            let r = s.inner.sample(clk.0);
            let scaled = s.sample(tt);
            let (ratio, what, wheel, _) = s.ratio(&cfg, &r, clk);
            let d = wheel_demand(&p, wheel, &scaled);
            let direct = match what {
                Limiting::WheelSpeed => d.speed / (cfg.speed_fraction * p.limits.wheel_speed),
                Limiting::WheelAccel => d.accel.abs() / (cfg.accel_fraction * p.limits.wheel_accel),
                Limiting::LegSpeed => d.leg_speed / (cfg.speed_fraction * p.limits.leg_speed),
                _ => continue,
            };
            assert!(
                (ratio - direct).abs() < 1e-9 * (1.0 + ratio),
                "{tt}: {ratio} vs {direct}"
            );
        }
    }

    #[test]
    fn waypoints_without_times_run_as_fast_as_the_limits_allow() {
        let p = Platform::justin();
        let w = fast();
        let free: Vec<WaypointSpec> = w.iter().map(|x| WaypointSpec { t: None, z: x.z }).collect();
        let inner = QuinticSpline::from_specs(&p, &free).unwrap();
        assert!(!inner.timed_at(0.5));
        let s = ScaledTrajectory::plan(&p, Box::new(inner), TimeScaleConfig::default()).unwrap();
        let t = s.timing().unwrap();
        assert!(t.max_ratio <= 1.0 + VERIFY_TOLERANCE + 1e-9, "{t:?}");
        // Time-optimal within the shares: most of the time some actuator is near its share
        // (the rest is the jerk-limited build-up of accelerations and the start and stop).
        let n = 1000;
        let busy = (0..n)
            .filter(|k| {
                let tt = t.executed_duration_s * (*k as f64 + 0.5) / n as f64;
                let clk = s.clock(tt);
                s.ratio(&TimeScaleConfig::default(), &s.inner.sample(clk.0), clk)
                    .0
                    > 0.8
            })
            .count();
        assert!(busy * 10 > n * 7, "near a share {busy} of {n} samples");
        // The same path with generous times runs as given (ṡ ≡ 1) and takes longer.
        let slow: Vec<WaypointSpec> = free
            .iter()
            .enumerate()
            .map(|(k, x)| WaypointSpec {
                t: Some(k as f64 * t.executed_duration_s * 2.0),
                z: x.z,
            })
            .collect();
        let s2 = ScaledTrajectory::plan(
            &p,
            Box::new(QuinticSpline::from_specs(&p, &slow).unwrap()),
            TimeScaleConfig::default(),
        )
        .unwrap();
        assert!(s2.timing().unwrap().executed_duration_s > 2.0 * t.executed_duration_s);
    }

    /// Straight segments at constant speed with a corner at t = 1 (no stop): an infinite
    /// steering rate at any speed.
    struct Corner;
    impl Trajectory for Corner {
        fn sample(&self, t: f64) -> ReferenceSample {
            let mut r = ReferenceSample {
                t,
                n: 4,
                ..Default::default()
            };
            let tc = t.clamp(0.0, 2.0);
            let (x, y, vx, vy) = if tc < 1.0 {
                (0.3 * tc, 0.0, 0.3, 0.0)
            } else {
                (0.3, 0.3 * (tc - 1.0), 0.0, 0.3)
            };
            r.z = z(x, y, 0.0, [0.45; 4]);
            r.dz[0] = vx;
            r.dz[1] = vy;
            r
        }
        fn duration(&self) -> f64 {
            2.0
        }
        fn n_legs(&self) -> usize {
            4
        }
        fn waypoint_near(&self, t: f64) -> Option<usize> {
            Some(t.round().clamp(0.0, 2.0) as usize)
        }
    }

    #[test]
    fn a_corner_without_a_stop_is_refused_naming_the_waypoint() {
        let p = Platform::justin();
        let e =
            ScaledTrajectory::plan(&p, Box::new(Corner), TimeScaleConfig::default()).unwrap_err();
        match &e {
            TimeScaleError::SteeringKink {
                waypoint: Some(1),
                angle,
                t,
                ..
            } => {
                assert!(
                    (angle - std::f64::consts::FRAC_PI_2).abs() < 0.05,
                    "{angle}"
                );
                assert!((t - 1.0).abs() < 0.01, "{t}");
            }
            other => panic!("{other:?}"),
        }
        let m = e.to_string();
        assert!(
            m.contains("waypoints[1]")
                && m.contains("corner without a stop")
                && m.contains("90.0°"),
            "{m}"
        );
        assert!(check_fixable(&p, &Corner, &TimeScaleConfig::default()).is_err());
    }

    /// A leg that runs past its range half-way.
    struct LegOut;
    impl Trajectory for LegOut {
        fn sample(&self, t: f64) -> ReferenceSample {
            let mut r = ReferenceSample {
                t,
                n: 4,
                ..Default::default()
            };
            let l = 0.45 + 0.2 * (t.clamp(0.0, 2.0) * std::f64::consts::FRAC_PI_2).sin();
            r.z = z(0.0, 0.0, 0.0, [0.45, 0.45, l, 0.45]);
            r
        }
        fn duration(&self) -> f64 {
            2.0
        }
        fn n_legs(&self) -> usize {
            4
        }
        fn waypoint_near(&self, t: f64) -> Option<usize> {
            Some(t.round() as usize)
        }
    }

    #[test]
    fn a_leg_beyond_its_range_is_refused_naming_the_waypoint_and_leg() {
        let p = Platform::justin();
        let e =
            ScaledTrajectory::plan(&p, Box::new(LegOut), TimeScaleConfig::default()).unwrap_err();
        assert!(
            matches!(e, TimeScaleError::LegOutOfRange { leg: 2, .. }),
            "{e:?}"
        );
        let m = e.to_string();
        assert!(
            m.contains("leg 3") && m.contains("[0.37, 0.56]") && m.contains("no timing can fix"),
            "{m}"
        );
    }

    #[test]
    fn a_timing_beyond_ten_hours_is_refused_naming_the_limit() {
        let mut p = Platform::justin();
        p.limits.leg_speed = 1e-7;
        let s = QuinticSpline::new(&p, &fast()).unwrap();
        let e = ScaledTrajectory::plan(&p, Box::new(s), TimeScaleConfig::default()).unwrap_err();
        let m = e.to_string();
        assert!(
            matches!(
                e,
                TimeScaleError::TooSlow {
                    field: "leg_speed",
                    ..
                }
            ),
            "{m}"
        );
        assert!(
            m.contains("`limits.leg_speed` = 1.000e-7") && m.contains("36000 s"),
            "{m}"
        );
    }

    /// Waypoints of a pivot about wheel `k`'s contact point by `turn` rad in `secs`.
    pub(crate) fn pivot(k: usize, turn: f64, secs: f64) -> Vec<Waypoint> {
        let p = Platform::justin();
        let (l, a) = (p.wheels[k].lambda_nominal, p.wheels[k].alpha);
        (0..=8)
            .map(|q| {
                let th = turn * q as f64 / 8.0;
                let (px, py) = (l * a.cos(), l * a.sin());
                let (wx, wy) = (l * (th + a).cos(), l * (th + a).sin());
                Waypoint {
                    t: secs * q as f64 / 8.0,
                    z: z(px - wx, py - wy, th, [l; 4]),
                }
            })
            .collect()
    }

    #[test]
    fn the_wheel_a_pivot_turns_about_holds_its_steering_angle() {
        let s = plan(&pivot(1, 1.5, 3.0));
        assert!(s.timing().unwrap().steer_reference);
        let first = s.sample(0.0).steer.angle[1];
        let p = Platform::justin();
        for k in 0..=200 {
            let r = s.sample(s.duration() * k as f64 / 200.0);
            assert!(r.steer.valid);
            assert!(
                (r.steer.angle[1] - first).abs() < 1e-9,
                "held: {} vs {first}",
                r.steer.angle[1]
            );
            assert!(r.steer.rate[1] == 0.0);
            // The pivot wheel barely moves; the others roll.
            assert!(wheel_demand(&p, 1, &r).speed * p.wheel_radius < HOLD_SPEED);
        }
    }

    #[test]
    fn a_wheel_the_icr_sweeps_across_reverses_its_roll_and_keeps_its_angle() {
        // The platform turns at 0.8 rad/s while its ICR moves through wheel 0's contact
        // point along the leg's normal (sampled into waypoints every 0.25 s).
        let p = Platform::justin();
        let (l, a) = (p.wheels[0].lambda_nominal, p.wheels[0].alpha);
        let wheel = [l * a.cos(), l * a.sin()];
        let d = [-a.sin(), a.cos()];
        let mut pose = crate::types::Pose::default();
        let mut w = vec![Waypoint {
            t: 0.0,
            z: z(0.0, 0.0, 0.0, [l; 4]),
        }];
        let dt = 0.001;
        for q in 0..4000 {
            let s = 0.4 * (2.0 * (q as f64 + 0.5) / 4000.0 - 1.0);
            let icr = [wheel[0] + d[0] * s, wheel[1] + d[1] * s];
            let tw = crate::types::Twist {
                vx: 0.8 * icr[1],
                vy: -0.8 * icr[0],
                omega: 0.8,
            };
            pose = crate::model::kinematics::se2_integrate(pose, &tw, dt);
            if (q + 1) % 250 == 0 {
                w.push(Waypoint {
                    t: (q + 1) as f64 * dt,
                    z: z(pose.x, pose.y, pose.theta, [l; 4]),
                });
            }
        }
        let s = plan(&w);
        assert!(s.timing().unwrap().steer_reference);
        // Across the sweep the wheel's direction of travel turns by about π while its
        // steering angle moves by far less: it rolls backwards afterwards.
        let at = |tau: f64| {
            let t = (0..=20000)
                .map(|k| s.duration() * k as f64 / 20000.0)
                .find(|&t| s.clock(t).0 >= tau)
                .unwrap();
            let r = s.sample(t);
            (wheel_demand(&p, 0, &r).steer_angle, r.steer.angle[0])
        };
        let (dir0, steer0) = at(1.2);
        let (dir1, steer1) = at(2.8);
        let turned = crate::angle::diff(dir1, dir0).abs();
        assert!(turned > 2.5, "direction of travel turned {turned}");
        assert!(
            (steer1 - steer0).abs() < 0.8,
            "steering moved {} rad",
            steer1 - steer0
        );
        // The roll reversed: the steering angle is on the other branch of the direction.
        assert!(crate::angle::diff(steer1, dir1).abs() > 2.5);
        assert!(crate::angle::diff(steer0, dir0).abs() < 0.2);
    }

    #[test]
    fn the_time_scale_says_what_limits_it() {
        let s = plan(&fast());
        let t = s.timing().unwrap();
        let st = s.time_scale(t.min_scale_at_s).unwrap();
        assert!((st.scale - t.min_scale).abs() < 1e-9);
        assert_eq!((st.limiting, st.wheel), (t.limiting, t.wheel));
        let after = s.time_scale(t.executed_duration_s + 1.0).unwrap();
        assert_eq!((after.scale, after.limiting), (1.0, Limiting::None));
        // From rest and back to rest the steering rate starts and ends within one cycle's
        // change at the acceleration share.
        let p = Platform::justin();
        let r0 = start_steer_rate(&p, &TimeScaleConfig::default());
        for tt in [0.0, t.executed_duration_s] {
            let r = s.sample(tt);
            for i in 0..4 {
                assert!(
                    r.steer.rate[i].abs() <= r0 * (1.0 + VERIFY_TOLERANCE),
                    "{tt}: {:?}",
                    r.steer.rate
                );
            }
        }
    }

    #[test]
    fn seed001s_nominal_needs_more_than_the_steering_limits() {
        // Why the seed-001 nominal is not scaled (its avoidance, which acts on it at its own
        // timing, is the experiment; the avoided path is then scaled).
        let p = Platform::justin();
        let inner = crate::reference::avoidance::Seed001Scenario::new(&p);
        let worst = (0..=2000)
            .map(|k| {
                crate::reference::limits::reference_ratio(
                    &p,
                    &inner.sample(inner.duration() * k as f64 / 2000.0),
                )
            })
            .fold((0.0, Limiting::None), |a, b| if b.0 > a.0 { b } else { a });
        assert!(
            worst.0 > 5.0 && worst.1 == Limiting::SteerAccel,
            "{worst:?}"
        );
        let cfg =
            crate::runtime::scenario::runtime_config(crate::runtime::scenario::Scenario::Seed001);
        assert!(cfg.time_scaling.is_none());
        assert!(crate::runtime::scenario::runtime_config(
            crate::runtime::scenario::Scenario::Seed000
        )
        .time_scaling
        .is_some());
    }
}
