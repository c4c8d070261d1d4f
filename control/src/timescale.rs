//! Time scaling of pre-planned trajectories (seed 004's remedy for references the actuators
//! cannot follow: keep the path, slow its execution), and the time-optimal timing of
//! waypoints given without times.
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
//! The path is unchanged; only its timing stretches. ṡ is continuous, s̈ continuous and s⃛
//! bounded, so z is C² with bounded jerk wherever z* is, as the DFL of seed 000 needs
//! (its feed-forward is z̈*, seed 000 eq. 25).
//!
//! # What a timing asks of the actuators
//!
//! Wheel i's contact velocity is linear in ż for a given z ([`crate::limits`], seed 000 eq.
//! 18), so along the scaled reference u_i = w_i ṡ with w_i(τ) the contact velocity of the
//! nominal path at ṡ = 1 (and w_i', w_i'' its τ-derivatives, [`contact_kinematics`] of the
//! nominal sample). Its direction φ_i = atan2(w_i) does not depend on the timing. With
//! φ' = dφ/dτ and φ'' from [`direction_rates`] (the same formulas as the steering rate and
//! acceleration, in τ), every actuator's demand is linear in ṡ, or in (x, s̈) with x = ṡ²:
//!
//! ```text
//! wheel speed          |w| ṡ / r                          ≤ f_v ω_max
//! steering rate        |φ'| ṡ                             ≤ f_v φ̇_max
//! leg speed            |λ'| ṡ                             ≤ f_v λ̇_max
//! wheel acceleration   |(w·w'/|w|) x + |w| s̈| / r         ≤ f_a ω̇_max
//! steering accel.      |φ'' x + φ' s̈|                     ≤ f_a φ̈_max
//! ```
//!
//! f_v and f_a are the margins ([`TimeScaleConfig`]): the live-command shaper's
//! `speed_fraction` (0.9) and `accel_fraction` (0.6) by default, for the same reasons
//! ([`crate::shaper::ShaperConfig`]): the controller's corrections need room, and the drives'
//! lag compensation adds τ_drive × the reference's jerk to the commanded acceleration.
//!
//! # Planning (TOPP on a grid)
//!
//! 1. **Grid.** τ_j = j Δτ (Δτ ≈ 2 ms, at most [`MAX_GRID`] points); at each point the
//!    speed constraints and a cap give an upper bound x̄_j on x (the *maximum velocity
//!    curve*); a pair of acceleration constraints k, l whose admissible s̈ intervals
//!    [L_k(x), U_k(x)] and [L_l(x), U_l(x)] no longer overlap bounds x too (a path
//!    curvature that needs steering acceleration at any speed). The cap is 1 where the
//!    trajectory's timing is given (the scaling only slows down) and
//!    [`TimeScaleConfig::free_scale_cap`] where it is free (waypoints without a time).
//! 2. **Backward pass.** With constant s̈ on [τ_j, τ_{j+1}], x_{j+1} = x_j + 2 Δτ s̈. The
//!    largest x_j from which the next point can still be reached below its bound K_{j+1}
//!    decelerating as hard as allowed: K_N = x̄_N and
//!    `K_j = max { x ≤ x̄_j : x + 2 Δτ L_j(x) ≤ K_{j+1} }`, where L_j(x) = max_k (p_k + q_k x)
//!    is affine per constraint, so each constraint gives the closed form
//!    x ≤ (K_{j+1} − 2 Δτ p_k)/(1 + 2 Δτ q_k) (when the denominator is positive; otherwise
//!    the constraint never binds, as L_k(0) ≤ 0).
//! 3. **Forward pass.** From x_0 = K_0, accelerate as hard as allowed without leaving the
//!    controllable bounds: x_{j+1} = min(K_{j+1}, x_j + 2 Δτ U_j(x_j)). This is the
//!    time-optimal x(τ) on the grid (the classic numerical-integration TOPP; with one
//!    path parameter and constraints affine in (x, s̈) the reachability sets of TOPP-RA
//!    reduce to these two passes).
//! 4. **Smoothing (jerk limit).** y = √x has a continuous slope only where x does; its
//!    kinks would make s̈ jump. y is first *eroded* (the minimum over a window of width W
//!    in τ) and then averaged over the same window: every averaged value is a mean of
//!    minima over windows that contain the point itself, so the smooth profile never
//!    exceeds the time-optimal one (all speed constraints hold exactly at the grid
//!    points), its slope is continuous and its curvature bounded (s̈ continuous, s⃛
//!    bounded). W = `jerk_time` × the largest ṡ, so accelerations build up over at least
//!    `jerk_time` (40 ms, the shaper's). The acceleration constraints hold up to the
//!    variation of their coefficients within a window.
//! 5. **Clock.** t_j from dt = dτ/ṡ (exact for ṡ linear in τ between grid points); the
//!    clock is the quintic Hermite interpolant of (τ_j, ṡ_j, s̈_j) at the t_j: τ(t) is C²
//!    with bounded s⃛ and meets every knot exactly.
//! 6. **Verification and repair.** The scaled reference is evaluated (with the limits.rs
//!    formulas, [`wheel_demand`]) at every knot and three points between each two; where a
//!    demand exceeds its share f·limit by more than [`VERIFY_TOLERANCE`], x̄ is lowered
//!    around that point (by the ratio, squared for speed-type limits) and steps 2–6 run
//!    again (at most [`MAX_REPAIRS`] times).
//!
//! **Bit-identical when nothing saturates.** If the smooth profile is ṡ ≡ 1 exactly, the
//! scaled trajectory passes every sample of the inner one through unchanged (τ = t, no
//! re-accumulation): the seed-000 experiment sends the same commands, bit for bit.
//!
//! # Steering the wheels the ICR rests on
//!
//! Where a wheel barely moves compared with the fastest wheel (|w_i| < `hold_ratio` · max_k
//! |w_k|: the ICR on or next to it, a pivot about it) its direction of travel is not worth
//! steering by. Over such a stretch the wheel's steering angle is the quintic Hermite blend
//! (in τ, matching angle, dφ/dτ and d²φ/dτ²) from the direction it had before to the one it
//! will have after, taken on the branch (±π) nearest the first: a wheel the ICR sweeps
//! across keeps its angle and reverses its roll direction, and a wheel the platform pivots
//! about holds its angle. Elsewhere the angle is the direction of travel, continued across
//! the branches (a wheel whose contact velocity passes through zero along a line keeps its
//! angle and rolls backwards after). When a trajectory has such a stretch while the platform
//! moves, the samples carry this angle and its rate and acceleration as the
//! [`SteerReference`], which the controllers follow for wheels slower than
//! [`crate::limits::HOLD_SPEED`] ([`crate::dfl::held_wheels`]): the wheel neither chatters
//! nor flips. The blend's rate and acceleration are limited like any other steering demand.
//!
//! # What no timing can fix
//!
//! [`ScaledTrajectory::plan`] refuses, naming the waypoint (when the trajectory has
//! waypoints) and the cause: a leg outside its range, and a kink in the direction of travel
//! of a moving wheel (the direction jumps while the wheel rolls: an infinite steering rate
//! at any speed). The quintic splines of [`crate::trajectory`] are C², so their wheels'
//! directions only jump where the wheel's contact velocity passes through zero, which is a
//! roll reversal, not a kink; other trajectories are checked. A timing that would take
//! longer than [`MAX_EXECUTED_S`] is refused too.

// Index loops over parallel per-wheel arrays read better than zipped iterators here.
#![allow(clippy::needless_range_loop)]

use crate::limits::{contact_kinematics, direction_rates};
use crate::platform::Platform;
use crate::ports::Limiting;
use crate::trajectory::{eval_quintic, quintic, Trajectory};
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
/// ([`crate::trajectory::MAX_WAYPOINT_TIME_S`]).
pub const MAX_EXECUTED_S: f64 = crate::trajectory::MAX_WAYPOINT_TIME_S;
/// A platform whose fastest wheel moves slower than this along the path (m/s at ṡ = 1) is at
/// rest there (its wheels' directions are taken from the neighbouring points).
const REST_W: f64 = 1e-9;
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
    /// reference may use. Default: the shaper's `speed_fraction` (0.9).
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
    /// about [`crate::limits::HOLD_SPEED`]).
    pub hold_ratio: f64,
    /// Largest ṡ where the timing is free (waypoints without a time): their nominal
    /// parametrisation runs at the platform's top speeds, so the limits bind well below this
    /// everywhere except near rest, where it keeps the start and stop gentle. Default 4.
    pub free_scale_cap: f64,
    /// Largest lateral acceleration |u| |φ̇| of a wheel's contact point (m/s²): the rate at
    /// which its direction of travel turns times its speed. The steering drives follow the
    /// reference with a few milliseconds of residual lag, and a wheel a small angle δ off its
    /// direction rolls δ |u| sideways; that drift is |u| φ̇ × the lag. Default 0.5 m/s² (the
    /// shaper's `direction_rate` of 1 rad/s at half the platform's top speed).
    pub lateral_accel: f64,
}

impl Default for TimeScaleConfig {
    fn default() -> Self {
        Self::from_shaper(&crate::shaper::ShaperConfig::default())
    }
}

impl TimeScaleConfig {
    /// The margins shared with the live-command shaper (its speed fraction and jerk time:
    /// one description of how much of each speed limit a reference may use and how fast its
    /// accelerations may build up), with the scaling's own defaults for the rest.
    pub fn from_shaper(s: &crate::shaper::ShaperConfig) -> Self {
        Self {
            speed_fraction: s.speed_fraction,
            accel_fraction: 0.5,
            jerk_time: s.jerk_time,
            hold_ratio: 0.02,
            free_scale_cap: 4.0,
            lateral_accel: 0.5,
        }
    }

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
    /// Duration of the scaled trajectory (s).
    pub executed_duration_s: f64,
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
    /// The base grid, refined where a wheel's direction turns by more than
    /// [`REFINE_ANGLE`] between two points or its contact velocity passes close to zero
    /// between them (the linearised closest approach, as the shaper refines its grid).
    fn build(
        p: &Platform,
        inner: &dyn Trajectory,
        cfg: &TimeScaleConfig,
        n: usize,
        nominal: f64,
    ) -> Result<Self, TimeScaleError> {
        let base = if nominal > 0.0 {
            ((nominal / GRID_STEP).ceil() as usize).clamp(1, MAX_GRID / 2)
        } else {
            0
        };
        let tau_base = |j: usize| {
            if j >= base {
                nominal
            } else {
                nominal * j as f64 / base as f64
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

/// The steering geometry of the path: per wheel, the angle along τ (module docs).
#[derive(Clone, Debug, Default)]
struct SteerGeometry {
    taus: Vec<f64>,
    /// Per grid point and wheel (index j·n + i): the angle.
    angle: Vec<f64>,
    /// Per wheel: the blends, sorted.
    blends: Vec<Vec<Blend>>,
}

/// A trajectory run on a clock chosen so that every actuator stays within its share of its
/// speed and acceleration limits (module docs).
pub struct ScaledTrajectory {
    inner: Box<dyn Trajectory>,
    platform: Platform,
    n: usize,
    nominal: f64,
    executed: f64,
    /// ṡ ≡ 1: samples are the inner trajectory's.
    pass: bool,
    /// Clock knots: time, τ, ṡ, s̈ (empty when `pass`).
    kt: Vec<f64>,
    ktau: Vec<f64>,
    kv: Vec<f64>,
    ka: Vec<f64>,
    /// Per grid point: the binding limit and its wheel, and whether the clock runs below
    /// its cap there.
    reason: Vec<(Limiting, u8, bool)>,
    geo: SteerGeometry,
    steer: bool,
    timing: Timing,
}

impl std::fmt::Debug for ScaledTrajectory {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("ScaledTrajectory")
            .field("timing", &self.timing)
            .field("pass_through", &self.pass)
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

impl Point {
    fn upper(&self, x: f64) -> f64 {
        self.acc
            .iter()
            .map(|k| {
                let (_, (r, s)) = k.bounds();
                r + s * x
            })
            .fold(f64::INFINITY, f64::min)
    }
}

/// The steering rate (rad/s) a scaled reference may have at its start and end: the change
/// the steering acceleration share allows in one control cycle (the wheels stand still
/// before and after, their steering at rest).
fn start_steer_rate(p: &Platform, cfg: &TimeScaleConfig) -> f64 {
    cfg.accel_fraction * p.limits.steer_accel * p.dt()
}

/// Smallest x kept anywhere (the clock never stops).
const X_FLOOR: f64 = 1e-300;

/// Share of the acceleration shares the passes plan with: the smoothing averages s̈ over
/// its window, which can add a few per cent where the constraints change within it.
const SMOOTHING_MARGIN: f64 = 0.9;

/// The constraints of every grid point (module docs, "What a timing asks").
fn constraints(p: &Platform, cfg: &TimeScaleConfig, n: usize, g: &Grid) -> Vec<Point> {
    let l = &p.limits;
    let rw = p.wheel_radius;
    let (fv, fa) = (cfg.speed_fraction, cfg.accel_fraction * SMOOTHING_MARGIN);
    let points = g.points();
    (0..points)
        .map(|j| {
            let mut xbar = g.caps[j] * g.caps[j];
            if j == 0 || j + 1 == points {
                // The wheels start from rest and end at rest without steering: the steering
                // rate may start and end with at most one cycle's change.
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
    let mut grid = Grid::build(p, traj, cfg, n, nominal)?;
    steering_geometry(p, traj, cfg, n, &mut grid)?;
    Ok(())
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
        let mut grid = Grid::build(p, inner.as_ref(), &cfg, n, nominal)?;
        let (sgeo, steer) = steering_geometry(p, inner.as_ref(), &cfg, n, &mut grid)?;
        let base = constraints(p, &cfg, n, &grid);
        let points = grid.points();
        let taus = &grid.taus;
        let mut fix = vec![1.0f64; points];
        let mut inner = inner;
        let mut round = 0;
        loop {
            let x = topp(&base, &fix, taus);
            let est: f64 = (0..points.saturating_sub(1))
                .map(|j| segment_time(taus[j + 1] - taus[j], x[j].sqrt(), x[j + 1].sqrt()))
                .sum();
            if !(est <= MAX_EXECUTED_S) {
                let j = (0..points)
                    .min_by(|&a, &b| x[a].total_cmp(&x[b]))
                    .unwrap_or(0);
                return Err(too_slow(p, &cfg, inner.as_ref(), &grid, n, j, est));
            }
            let ys = smooth_in_time(taus, &x, cfg.jerk_time);
            let pass = ys.iter().all(|&v| v == 1.0);
            // The steering reference goes with every scaled trajectory, and with one that
            // passes through unchanged where a wheel is held while the platform moves or the
            // platform stops between two motions (the controllers' own rules near rest steer
            // by the feedback's corrections).
            let steer = steer || !pass || interior_stop(&grid.wmax);
            let mut st = ScaledTrajectory {
                inner,
                platform: p.clone(),
                n,
                nominal,
                executed: nominal,
                pass,
                kt: Vec::new(),
                ktau: Vec::new(),
                kv: Vec::new(),
                ka: Vec::new(),
                reason: Vec::new(),
                geo: sgeo.clone(),
                steer,
                timing: Timing {
                    nominal_duration_s: nominal,
                    executed_duration_s: nominal,
                    min_scale: 1.0,
                    min_scale_at_s: 0.0,
                    limiting: Limiting::None,
                    wheel: 0,
                    max_ratio: 0.0,
                    steer_reference: steer,
                },
            };
            if !pass {
                st.set_clock(taus, ys);
            }
            let violations = st.verify(&cfg, taus, &grid.caps);
            if violations.is_empty() || round == MAX_REPAIRS {
                return Ok(st);
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
                let (a, b) = (st.clock(t0).0, st.clock(t1).0);
                let lo = taus.partition_point(|&x| x < a).saturating_sub(1);
                let hi = taus.partition_point(|&x| x <= b).min(points - 1);
                for v in &mut factor[lo..=hi] {
                    *v = v.min(f);
                }
            }
            for (v, f) in fix.iter_mut().zip(&factor) {
                *v *= f;
            }
            inner = st.inner;
            round += 1;
        }
    }

    /// The clock knots from ṡ per grid point: executed times by dt = dτ/ṡ, s̈ = ṡ dṡ/dτ.
    fn set_clock(&mut self, taus: &[f64], ys: Vec<f64>) {
        let points = taus.len();
        let mut kt = Vec::with_capacity(points);
        let mut t = 0.0;
        for j in 0..points {
            if j > 0 {
                t += segment_time(taus[j] - taus[j - 1], ys[j - 1], ys[j]);
            }
            kt.push(t);
        }
        let ka: Vec<f64> = (0..points)
            .map(|j| {
                let (a, b) = (j.saturating_sub(1), (j + 1).min(points - 1));
                let slope = if b > a {
                    (ys[b] - ys[a]) / (taus[b] - taus[a])
                } else {
                    0.0
                };
                ys[j] * slope
            })
            .collect();
        self.executed = t;
        self.kt = kt;
        self.ktau = taus.to_vec();
        self.kv = ys;
        self.ka = ka;
    }

    /// The trajectory being scaled.
    pub fn inner(&self) -> &dyn Trajectory {
        self.inner.as_ref()
    }

    /// True when ṡ ≡ 1: the samples are the inner trajectory's.
    pub fn is_pass_through(&self) -> bool {
        self.pass
    }

    /// The clock: (τ, ṡ, s̈, s⃛) at executed time `t` (before the start: the start; after
    /// the end: the end, at rest).
    pub fn clock(&self, t: f64) -> (f64, f64, f64, f64) {
        let t = if t.is_finite() { t } else { 0.0 };
        if self.pass {
            return (t.clamp(0.0, self.nominal), 1.0, 0.0, 0.0);
        }
        let last = self.kt.len() - 1;
        if t <= 0.0 || last == 0 {
            return (self.ktau[0], self.kv[0], self.ka[0], 0.0);
        }
        if t >= self.kt[last] {
            return (self.nominal, 0.0, 0.0, 0.0);
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
        (tau.clamp(0.0, self.nominal), v, a, j)
    }

    /// Wheel `i`'s steering geometry at path time `tau`, with the inner sample `r` there:
    /// (φ, dφ/dτ, d²φ/dτ²).
    fn steer_at(&self, i: usize, tau: f64, r: &ReferenceSample) -> (f64, f64, f64) {
        let g = &self.geo;
        if let Some(b) = self.blend(i, tau) {
            let (phi, d1, d2, _) = eval_quintic(&b.coef, tau - b.a);
            return (phi, d1, d2);
        }
        let m = g.taus.len();
        let grid = if m < 2 {
            g.angle[i]
        } else {
            let j = g.taus.partition_point(|&x| x <= tau).clamp(1, m - 1) - 1;
            let f = ((tau - g.taus[j]) / (g.taus[j + 1] - g.taus[j])).clamp(0.0, 1.0);
            g.angle[j * self.n + i] * (1.0 - f) + g.angle[(j + 1) * self.n + i] * f
        };
        let [u, du, ddu] = contact_kinematics(&self.platform, i, r);
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
            for i in 0..self.n {
                let (phi, d1, d2) = self.steer_at(i, tau, &r);
                sr.angle[i] = phi;
                sr.rate[i] = d1 * v;
                sr.accel[i] = d2 * v * v + d1 * a;
            }
            s.steer = sr;
        }
        (s, r, clk)
    }

    /// Largest demand over its share at one instant, from the inner sample `r` at the
    /// clock's τ and the clock (the chain rule of the module docs; the same as
    /// [`wheel_demand`] of the scaled sample, test `demands_match_the_scaled_samples`):
    /// (ratio, limit, wheel, speed-type).
    fn ratio(
        &self,
        cfg: &TimeScaleConfig,
        r: &ReferenceSample,
        clk: (f64, f64, f64, f64),
    ) -> (f64, Limiting, usize, bool) {
        let p = &self.platform;
        let l = &p.limits;
        let (fv, fa) = (cfg.speed_fraction, cfg.accel_fraction);
        let (tau, v, a, _) = clk;
        let mut worst = (0.0f64, Limiting::None, 0usize, true);
        for i in 0..self.n {
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

    /// Executed times of the grid points.
    fn grid_times(&self, taus: &[f64]) -> Vec<f64> {
        if self.pass {
            taus.to_vec()
        } else {
            self.kt.clone()
        }
    }

    /// Checks the demands at the grid points and midway between them: returns the largest
    /// demand over its share and the violations (executed time, ratio, speed-type) beyond the
    /// tolerance, and records the timing and the binding limit at every grid point.
    fn verify(
        &mut self,
        cfg: &TimeScaleConfig,
        taus: &[f64],
        caps: &[f64],
    ) -> Vec<(f64, f64, bool)> {
        let kt = self.grid_times(taus);
        let mut worst = 0.0f64;
        let mut out = Vec::new();
        let mut reason = Vec::with_capacity(kt.len());
        let mut min = (f64::INFINITY, 0.0, Limiting::None, 0usize);
        let r0 = start_steer_rate(&self.platform, cfg);
        let ends = (kt.first().copied(), kt.last().copied());
        let mut check = |t: f64| {
            let clk = self.clock(t);
            let r = self.inner.sample(if self.pass { t } else { clk.0 });
            let mut q = self.ratio(cfg, &r, clk);
            if Some(t) == ends.0 || Some(t) == ends.1 {
                for i in 0..self.n {
                    let [w, dw, ddw] = contact_kinematics(&self.platform, i, &r);
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
            let (_, what, wheel, _) = check(t);
            if let Some(&t1) = kt.get(j + 1) {
                check(0.5 * (t + t1));
            }
            let v = if self.pass { 1.0 } else { self.kv[j] };
            reason.push((what, wheel as u8, v < caps[j] * (1.0 - 1e-9)));
            if v < min.0 {
                min = (v, t, what, wheel);
            }
        }
        self.reason = reason;
        self.timing = Timing {
            nominal_duration_s: self.nominal,
            executed_duration_s: self.executed,
            min_scale: if min.0.is_finite() { min.0 } else { 1.0 },
            min_scale_at_s: min.1,
            limiting: if min.0 < 1.0 - 1e-9 {
                min.2
            } else {
                Limiting::None
            },
            wheel: min.3,
            max_ratio: worst,
            steer_reference: self.steer,
        };
        out
    }
}

/// Whether the platform comes (nearly) to rest between two motions: its fastest wheel drops
/// below 2 % of the path's fastest after having moved faster than 10 %, and moves that fast
/// again later.
fn interior_stop(wmax: &[f64]) -> bool {
    let top = wmax.iter().copied().fold(0.0, f64::max);
    if !(top > 0.0) {
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
            let den = 1.0 + 2.0 * h * ql;
            if den > 0.0 {
                kj = kj.min((k[j + 1] - 2.0 * h * pl) / den);
            }
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
        let next = x[j] + 2.0 * h * pts[j].upper(x[j]);
        x[j + 1] = if next.is_nan() {
            k[j + 1]
        } else {
            next.min(k[j + 1]).max(X_FLOOR)
        };
    }
    x
}

/// The smoothing of the time-optimal profile (module docs): ṡ as a function of its own time
/// (linear within each grid interval, s̈ constant there), eroded over a window of
/// `jerk_time` plus one sample and averaged over `jerk_time`, read back at the grid points.
/// Never above the time-optimal ṡ at a grid point; exactly 1 where that is 1 throughout.
fn smooth_in_time(taus: &[f64], x: &[f64], jerk_time: f64) -> Vec<f64> {
    let points = taus.len();
    let y: Vec<f64> = x.iter().map(|v| v.sqrt()).collect();
    if points < 2 {
        return y;
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
    if !(total > 0.0) {
        return y;
    }
    let h = (jerk_time / 8.0).max(total / (4 * MAX_GRID) as f64);
    let half = ((0.5 * jerk_time / h).round() as usize).max(1);
    let samples = (total / h).ceil() as usize + 1;
    // ṡ of the time-optimal profile at time t (linear within each interval).
    let sdot = |t: f64, j: usize| -> f64 {
        if j + 1 >= points {
            return y[points - 1];
        }
        let dt = tt[j + 1] - tt[j];
        if dt <= 0.0 {
            return y[j];
        }
        let f = ((t - tt[j]) / dt).clamp(0.0, 1.0);
        if y[j] == y[j + 1] {
            y[j]
        } else {
            y[j] + (y[j + 1] - y[j]) * f
        }
    };
    let seg = |t: f64| tt.partition_point(|&x| x <= t).clamp(1, points) - 1;
    let ts: Vec<f64> = (0..samples).map(|m| (m as f64 * h).min(total)).collect();
    // Erosion: the minimum of the piecewise-linear ṡ over [t − w, t + w] is at the window's
    // ends or at a grid point inside.
    let w = (half + 1) as f64 * h;
    let eroded: Vec<f64> = ts
        .iter()
        .map(|&t| {
            let (a, b) = ((t - w).max(0.0), (t + w).min(total));
            let (ja, jb) = (seg(a), seg(b));
            let mut m = sdot(a, ja).min(sdot(b, jb));
            for j in ja + 1..=jb.min(points - 1) {
                m = m.min(y[j]);
            }
            m
        })
        .collect();
    let smooth: Vec<f64> = (0..samples)
        .map(|m| {
            let lo = m.saturating_sub(half);
            let hi = (m + half).min(samples - 1);
            let win = &eroded[lo..=hi];
            let mn = win.iter().copied().fold(f64::INFINITY, f64::min);
            let mx = win.iter().copied().fold(0.0, f64::max);
            if mn == mx {
                mn
            } else {
                // Windows cut by the ends count their end value again (the profile held).
                let extra = (2 * half + 1) - win.len();
                let pad = if m < half {
                    eroded[0]
                } else {
                    eroded[samples - 1]
                };
                let sum: f64 = win.iter().sum::<f64>() + pad * extra as f64;
                (sum / (2 * half + 1) as f64).clamp(mn.min(pad), mx.max(pad))
            }
        })
        .collect();
    (0..points)
        .map(|j| {
            let t = tt[j];
            let m = ((t / h).floor() as usize).min(samples - 1);
            let v = if m + 1 >= samples || smooth[m] == smooth[m + 1] {
                smooth[m]
            } else {
                let f = ((t - ts[m]) / (ts[m + 1] - ts[m])).clamp(0.0, 1.0);
                smooth[m] + (smooth[m + 1] - smooth[m]) * f
            };
            v.min(y[j])
        })
        .collect()
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
    for i in 0..n {
        for j in 0..points {
            let wmax = g.wmax[j];
            let q = &mut g.geo[j * n + i];
            q.defined = wmax > REST_W && q.speed >= cfg.hold_ratio * wmax && q.speed > 0.0;
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
                a: 0.0,
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
            if (start..end).any(|k| g.wmax[k] > REST_W) {
                steer_needed = true;
            }
            // Where the whole platform is at rest at the path's start or end, the direction
            // there is the limit of the directions next to it: continued (to second order)
            // from the nearest steered point, so the steering rate has no step. A wheel held
            // while the platform moves holds its angle.
            let at_rest = (start..end).all(|k| g.wmax[k] <= REST_W);
            let blend = if start == 0 {
                let q = g.geo[first * n + i];
                let h = taus[first];
                let coef = if at_rest {
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
                Blend { a: 0.0, b: h, coef }
            } else if end == points {
                let q = g.geo[(start - 1) * n + i];
                let coef = if at_rest {
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
        let taus = &self.geo.taus;
        let m = self.reason.len().min(taus.len());
        let (what, wheel, slowed) = if m == 0 {
            (Limiting::None, 0, false)
        } else {
            let k = taus.partition_point(|&x| x <= tau).clamp(1, m) - 1;
            self.reason[k]
        };
        let running = t < self.executed;
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
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::trajectory::{QuinticSpline, Waypoint, WaypointSpec};
    use crate::types::ZVec;

    fn wp(t: f64, x: f64, y: f64, th: f64, legs: [f64; 4]) -> Waypoint {
        let mut z = ZVec::zeros();
        z[0] = x;
        z[1] = y;
        z[2] = th;
        for i in 0..4 {
            z[3 + i] = legs[i];
        }
        Waypoint { t, z }
    }

    #[test]
    fn explore() {
        let p = Platform::justin();
        let seed = crate::trajectory::seed000_experiment(&p);
        let t0 = std::time::Instant::now();
        let s = ScaledTrajectory::plan(&p, Box::new(seed), TimeScaleConfig::default()).unwrap();
        println!("seed000 {:?} {:?}", s.timing, t0.elapsed());
        let l = [0.45; 4];
        let w = vec![
            wp(0.0, 0.0, 0.0, 0.0, l),
            wp(2.0, 1.0, 0.5, 1.5, [0.5, 0.4, 0.5, 0.4]),
            wp(3.5, 1.5, 1.5, 0.0, l),
            wp(5.0, 0.5, 1.0, -1.0, [0.56, 0.37, 0.56, 0.37]),
        ];
        let sp = QuinticSpline::new(&p, &w).unwrap();
        let t0 = std::time::Instant::now();
        let s = ScaledTrajectory::plan(&p, Box::new(sp), TimeScaleConfig::default()).unwrap();
        println!("fast {:?} {:?}", s.timing, t0.elapsed());
        {
            let sp = QuinticSpline::new(&p, &w).unwrap();
            let cfg = TimeScaleConfig::default();
            let mut g = Grid::build(&p, &sp, &cfg, 4, sp.duration()).unwrap();
            let (sg, _) = steering_geometry(&p, &sp, &cfg, 4, &mut g).unwrap();
            for j in 0..g.points() {
                let tau = g.taus[j];
                if tau > 3.36 && tau < 3.54 {
                    let q0 = g.geo[j * 4];
                    let q2 = g.geo[j * 4 + 2];
                    println!("  tau {tau:.4} W {:.3} | w0 {:.4} d{} a{:7.3} r{:9.2} | w2 {:.4} d{} a{:7.3} r{:9.2}", g.wmax[j], q0.speed, q0.defined as u8, q0.angle, q0.rate, q2.speed, q2.defined as u8, q2.angle, q2.rate);
                }
            }
            println!("blends0 {:?}", sg.blends[0]);
            println!("blends2 {:?}", sg.blends[2]);
        }
        let mut t = 0.0;
        while t < s.duration() {
            let (tau, v, a, _) = s.clock(t);
            let st = s.time_scale(t).unwrap();
            println!(
                "  t {t:6.2} tau {tau:6.3} sdot {v:7.4} sddot {a:8.3} {:?} w{}",
                st.limiting, st.wheel
            );
            t += 0.25;
        }
        let specs: Vec<WaypointSpec> = w.iter().map(|w| WaypointSpec { t: None, z: w.z }).collect();
        let sp = QuinticSpline::from_specs(&p, &specs).unwrap();
        println!("times {:?}", sp.times());
        let t0 = std::time::Instant::now();
        let s = ScaledTrajectory::plan(&p, Box::new(sp), TimeScaleConfig::default()).unwrap();
        println!("free {:?} {:?}", s.timing, t0.elapsed());
    }
}
