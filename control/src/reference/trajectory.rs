//! Reference trajectories z*(t) = (x, y, θ, λ_1 … λ_n) with ż*, z̈* and z⃛*.
//!
//! * [`QuasiTrapezoid`]: seed 000 Sect. V's "quasi trapezoidal velocity profile" for one
//!   component. The constant-acceleration phases of a trapezoid are replaced by smooth
//!   parabolic arcs of acceleration so that z̈* is continuous (required by the DFL
//!   feedback, seed 000 eqs. 24–25 and Fig. 6).
//! * [`ComponentTrajectory`]: one profile per component of z, and [`seed000_experiment`].
//! * [`QuinticSpline`]: C² quintic segments through timed waypoints (seed 001 uses
//!   quintic Bézier segments), loadable from a small TOML file ([`load_waypoints`]).
//!
//! # Blend rule and resulting durations
//!
//! Each velocity change Δv (from v₀ to the cruise speed, and from the cruise speed to 0)
//! follows a cubic "smoothstep" v(s) = v₀ + Δv (3s² − 2s³), s = t/T_b, whose acceleration
//! a(s) = 6 Δv s(1 − s)/T_b is a parabolic arc starting and ending at zero and peaking at
//! 1.5 Δv/T_b in the middle. The peak is set to the acceleration limit, so
//! T_b = 1.5 Δv / a_max: each blend lasts 1.5× the constant-acceleration ramp it replaces
//! and covers the same distance per unit time as the mean speed. A profile that reaches
//! its cruise speed from rest therefore lasts T = d/v_max + 1.5 v_max/a_max (a plain
//! trapezoid lasts d/v + v/a). With the paper's limits this gives (test
//! `seed000_durations_are_close_to_the_paper`):
//!
//! | component | d | limits | this rule | paper |
//! |---|---|---|---|---|
//! | x, y | 4.5 m | 0.18 m/s, 0.1 m/s², v₀ = ε = 0.01 | 27.55 s | 30.8 s |
//! | θ | 2π | 0.31 rad/s, 0.17 rad/s², v₀ = ε/0.82 | 22.90 s | 23 s |
//! | λ | 0.19 m | 0.02 m/s, 0.01 m/s² | 12.5 s | 15 s |
//!
//! The rotation matches; translation and legs come out 10–17 % shorter than the paper
//! reports. No single blend rule reproduces all three of the paper's numbers (they need
//! extra times of 3.2, 1.5 and 2.75 × v/a respectively), so the paper's interpolator must
//! have had details it does not state; this rule is the natural reading of "smooth
//! parabolic arcs replace the constant acceleration phases".
//!
//! Jerk is piecewise linear and jumps at the ends of each blend (z⃛ is not continuous; the
//! controllers here need only z̈* continuous).

// Index loops over parallel per-wheel arrays read better than zipped iterators here.
#![allow(clippy::needless_range_loop)]

use crate::model::platform::Platform;
use crate::types::{ReferenceSample, ZVec, MAX_WHEELS, Z_MAX};
use serde::Deserialize;
use std::path::Path;

/// A reference trajectory for z = (x, y, θ, λ_1 … λ_n).
pub trait Trajectory: Send + Sync {
    /// z*, ż*, z̈*, z⃛* at time `t` (s from the trajectory start); clamped outside
    /// [0, duration]: before 0 the start sample, after the end the goal at rest.
    fn sample(&self, t: f64) -> ReferenceSample;
    /// Time at which the last component reaches its goal (s).
    fn duration(&self) -> f64;
    /// Number of legs n in the samples.
    fn n_legs(&self) -> usize;
    /// Whether the timing at `t` is given (the time scaling may only slow it down, ṡ ≤ 1)
    /// or free (next to a waypoint without a time: as fast as the limits allow,
    /// [`crate::reference::timescale`]). Default: given.
    fn timed_at(&self, t: f64) -> bool {
        let _ = t;
        true
    }
    /// The waypoint nearest to time `t`, for messages (`None`: not a waypoint trajectory).
    fn waypoint_near(&self, t: f64) -> Option<usize> {
        let _ = t;
        None
    }
    /// How fast the trajectory's clock runs at `t` and why: `Some` for a time-scaled
    /// trajectory ([`crate::reference::timescale::ScaledTrajectory`]).
    fn time_scale(&self, t: f64) -> Option<crate::reference::status::ScaleStatus> {
        let _ = t;
        None
    }
    /// The nominal and executed durations and the slowest scale of a time-scaled trajectory.
    fn timing(&self) -> Option<crate::reference::status::Timing> {
        None
    }
    /// The path's exact stops: intervals of its time (s; equal ends for a stop at an
    /// instant) over which every component is at rest, with zero velocity and acceleration
    /// at their ends. The time scaling holds its clock there while the wheels re-steer
    /// ([`crate::reference::timescale`], "Stops and dwells"). Default: none known (the time scaling
    /// still finds a start and an end at rest by itself).
    fn stops(&self) -> Vec<(f64, f64)> {
        Vec::new()
    }
    /// The singularity avoidance's record at `t` when the trajectory is a path the avoidance
    /// was applied to before the run ([`crate::reference::avoidance::AvoidedTrajectory`]), `None`
    /// otherwise.
    fn avoidance_at(&self, t: f64) -> Option<crate::reference::status::AvoidanceState> {
        let _ = t;
        None
    }
}

/// Errors from building or loading a trajectory.
#[derive(Debug, thiserror::Error)]
pub enum TrajectoryError {
    /// The waypoint file could not be read, is too large (`/dev/zero` …) or is not UTF-8.
    #[error(transparent)]
    Input(#[from] rollbase_driver::input::InputError),
    /// The waypoint TOML is malformed.
    #[error("waypoint file is not valid TOML for a waypoint list: {0}")]
    Parse(String),
    /// A value is NaN or infinite.
    #[error("`{field}` = {value} is not a finite number")]
    NonFinite {
        /// Dotted path of the field.
        field: String,
        /// The value.
        value: f64,
    },
    /// A limit (velocity, acceleration) is not positive, a start speed is out of range, or a
    /// waypoint time is absurd.
    #[error("`{field}` = {}: {reason}", crate::num::Num(*value))]
    BadParameter {
        /// Parameter name.
        field: String,
        /// The value.
        value: f64,
        /// What is expected.
        reason: String,
    },
    /// Waypoint times must strictly increase.
    #[error("waypoints[{waypoint}].t = {t} is not after the previous waypoint's t = {previous}: times must strictly increase")]
    NonIncreasingTime {
        /// Waypoint index.
        waypoint: usize,
        /// Its time (s).
        t: f64,
        /// Previous time (s).
        previous: f64,
    },
    /// A waypoint has a leg extension outside the platform's range.
    #[error("waypoints[{waypoint}].legs[{leg}] = {value} m is outside the platform's leg range [{min}, {max}] m")]
    LegOutOfRange {
        /// Waypoint index (or segment index for an overshooting segment).
        waypoint: usize,
        /// Leg index.
        leg: usize,
        /// The value (m).
        value: f64,
        /// λ_min (m).
        min: f64,
        /// λ_max (m).
        max: f64,
    },
    /// A waypoint lists the wrong number of legs.
    #[error("waypoints[{waypoint}].legs has {got} entries but the platform has {expected} wheels")]
    LegCount {
        /// Waypoint index.
        waypoint: usize,
        /// Entries given.
        got: usize,
        /// Wheels on the platform.
        expected: usize,
    },
    /// Fewer than two waypoints.
    #[error("a spline needs at least 2 waypoints, got {got}")]
    TooFewWaypoints {
        /// Number given.
        got: usize,
    },
}

fn finite(field: &str, v: f64) -> Result<(), TrajectoryError> {
    if v.is_finite() {
        Ok(())
    } else {
        Err(TrajectoryError::NonFinite {
            field: field.to_string(),
            value: v,
        })
    }
}

/// One sample of a 1-D profile.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct ProfileSample {
    /// Position.
    pub pos: f64,
    /// Velocity.
    pub vel: f64,
    /// Acceleration.
    pub acc: f64,
    /// Jerk.
    pub jerk: f64,
}

/// Seed 000's quasi-trapezoidal 1-D profile with parabolic-acceleration blends (see the
/// module docs for the blend rule).
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct QuasiTrapezoid {
    start: f64,
    /// +1 or −1: direction of travel.
    dir: f64,
    v0: f64,
    vp: f64,
    ta: f64,
    tc: f64,
    td: f64,
    dist_a: f64,
    dist: f64,
}

impl QuasiTrapezoid {
    /// A profile that stays at `pos` forever (duration 0).
    pub fn hold(pos: f64) -> Self {
        Self {
            start: pos,
            dir: 1.0,
            ..Self::default()
        }
    }

    /// Profile from `start` to `goal` with speed limit `v_max` and acceleration limit
    /// `a_max` (peak of the parabolic blends), starting at speed `v_start` ≥ 0 in the
    /// direction of travel (seed 000's persistence initialisation ε) and ending at rest.
    /// If `start == goal` the profile holds `start` and `v_start` is ignored.
    pub fn new(
        start: f64,
        goal: f64,
        v_max: f64,
        a_max: f64,
        v_start: f64,
    ) -> Result<Self, TrajectoryError> {
        finite("start", start)?;
        finite("goal", goal)?;
        finite("v_max", v_max)?;
        finite("a_max", a_max)?;
        finite("v_start", v_start)?;
        let bad = |field: &str, value: f64, reason: &str| TrajectoryError::BadParameter {
            field: field.into(),
            value,
            reason: reason.into(),
        };
        if v_max <= 0.0 {
            return Err(bad("v_max", v_max, "must be greater than zero"));
        }
        if a_max <= 0.0 {
            return Err(bad("a_max", a_max, "must be greater than zero"));
        }
        if !(0.0..=v_max).contains(&v_start) {
            return Err(bad(
                "v_start",
                v_start,
                "must lie in [0, v_max] (it is a speed along the direction of travel)",
            ));
        }
        let d = (goal - start).abs();
        if d == 0.0 {
            return Ok(Self::hold(start));
        }
        let dir = (goal - start).signum();
        let v0 = v_start;
        // distance to stop from v0 alone
        let stop0 = 0.75 * v0 * v0 / a_max;
        if d < stop0 {
            return Err(bad(
                "v_start",
                v_start,
                "is too fast to stop within the distance to the goal; lower it or move the goal further",
            ));
        }
        let full = 0.75 * (2.0 * v_max * v_max - v0 * v0) / a_max;
        let vp = if full <= d {
            v_max
        } else {
            ((d * a_max / 0.75 + v0 * v0) / 2.0).sqrt()
        };
        let ta = 1.5 * (vp - v0) / a_max;
        let td = 1.5 * vp / a_max;
        let dist_a = 0.5 * ta * (v0 + vp);
        let dist_d = 0.5 * td * vp;
        let tc = ((d - dist_a - dist_d) / vp).max(0.0);
        Ok(Self {
            start,
            dir,
            v0,
            vp,
            ta,
            tc,
            td,
            dist_a,
            dist: d,
        })
    }

    /// Total duration (s).
    pub fn duration(&self) -> f64 {
        self.ta + self.tc + self.td
    }

    /// Goal position.
    pub fn goal(&self) -> f64 {
        self.start + self.dir * self.dist
    }

    /// Position, velocity, acceleration and jerk at `t` (clamped to [0, duration]; the
    /// start speed applies at t ≤ 0, rest after the end).
    pub fn sample(&self, t: f64) -> ProfileSample {
        let t = if t.is_finite() { t.max(0.0) } else { 0.0 };
        let (p, v, a, j) = if self.duration() <= 0.0 {
            (0.0, 0.0, 0.0, 0.0)
        } else if t < self.ta {
            let dv = self.vp - self.v0;
            let s = t / self.ta;
            (
                self.v0 * t + dv * self.ta * (s * s * s - 0.5 * s * s * s * s),
                self.v0 + dv * (3.0 * s * s - 2.0 * s * s * s),
                dv / self.ta * 6.0 * s * (1.0 - s),
                dv / (self.ta * self.ta) * 6.0 * (1.0 - 2.0 * s),
            )
        } else if t < self.ta + self.tc {
            (self.dist_a + self.vp * (t - self.ta), self.vp, 0.0, 0.0)
        } else if t < self.duration() {
            let s = (t - self.ta - self.tc) / self.td;
            let base = self.dist_a + self.vp * self.tc;
            (
                base + self.vp * self.td * (s - s * s * s + 0.5 * s * s * s * s),
                self.vp * (1.0 - 3.0 * s * s + 2.0 * s * s * s),
                -self.vp / self.td * 6.0 * s * (1.0 - s),
                -self.vp / (self.td * self.td) * 6.0 * (1.0 - 2.0 * s),
            )
        } else {
            (self.dist, 0.0, 0.0, 0.0)
        };
        ProfileSample {
            pos: self.start + self.dir * p,
            vel: self.dir * v,
            acc: self.dir * a,
            jerk: self.dir * j,
        }
    }
}

/// One [`QuasiTrapezoid`] per component of z = (x, y, θ, λ_1 … λ_n). Sampling does not
/// allocate.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ComponentTrajectory {
    profiles: [QuasiTrapezoid; Z_MAX],
    n: usize,
}

impl ComponentTrajectory {
    /// Builds the trajectory from profiles for x, y, θ and the legs (at most
    /// [`MAX_WHEELS`] legs are used).
    pub fn new(
        x: QuasiTrapezoid,
        y: QuasiTrapezoid,
        theta: QuasiTrapezoid,
        legs: &[QuasiTrapezoid],
    ) -> Self {
        let mut profiles = [QuasiTrapezoid::hold(0.0); Z_MAX];
        profiles[0] = x;
        profiles[1] = y;
        profiles[2] = theta;
        let n = legs.len().min(MAX_WHEELS);
        profiles[3..3 + n].copy_from_slice(&legs[..n]);
        Self { profiles, n }
    }

    /// The profile of component `k` (0 = x, 1 = y, 2 = θ, 3 + i = λ_i).
    pub fn component(&self, k: usize) -> Option<&QuasiTrapezoid> {
        if k < 3 + self.n {
            self.profiles.get(k)
        } else {
            None
        }
    }
}

impl Trajectory for ComponentTrajectory {
    fn sample(&self, t: f64) -> ReferenceSample {
        let mut s = ReferenceSample {
            t,
            n: self.n,
            ..ReferenceSample::default()
        };
        for k in 0..3 + self.n {
            let p = self.profiles[k].sample(t);
            s.z[k] = p.pos;
            s.dz[k] = p.vel;
            s.ddz[k] = p.acc;
            s.dddz[k] = p.jerk;
        }
        s
    }
    fn duration(&self) -> f64 {
        self.profiles[..3 + self.n]
            .iter()
            .map(|p| p.duration())
            .fold(0.0, f64::max)
    }
    fn n_legs(&self) -> usize {
        self.n
    }
}

/// Seed 000's persistence threshold ε (m/s), Sect. V.
pub const SEED000_EPSILON: f64 = 0.01;
/// Seed 000's minimum radius of curvature R_min (m), eq. 26.
pub const SEED000_R_MIN: f64 = 0.82;

/// The experiment of seed 000 Sect. V: ξ from (0, 0, 0) to (4.5, 4.5, 2π), every leg from
/// λ_min to λ_max of the platform (0.37 → 0.56 m on Justin); limits (0.18 m/s, 0.1 m/s²)
/// for x and y, (0.31 rad/s, 0.17 rad/s²) for θ, (0.02 m/s, 0.01 m/s²) for the legs; the
/// interpolator starts with |ẋ*| = |ẏ*| = ε and |θ̇*| = ε/R_min (persistence, ε = 0.01 m/s).
pub fn seed000_experiment(p: &Platform) -> ComponentTrajectory {
    let eps = SEED000_EPSILON;
    let prof = |a: f64, b: f64, v: f64, acc: f64, v0: f64| {
        QuasiTrapezoid::new(a, b, v, acc, v0).unwrap_or_else(|_| QuasiTrapezoid::hold(a))
    };
    let x = prof(0.0, 4.5, 0.18, 0.1, eps);
    let y = prof(0.0, 4.5, 0.18, 0.1, eps);
    let th = prof(
        0.0,
        2.0 * std::f64::consts::PI,
        0.31,
        0.17,
        eps / SEED000_R_MIN,
    );
    let mut legs = [QuasiTrapezoid::hold(0.0); MAX_WHEELS];
    let n = p.n().min(MAX_WHEELS);
    for (l, w) in legs.iter_mut().zip(&p.wheels) {
        *l = prof(w.lambda_min, w.lambda_max, 0.02, 0.01, 0.0);
    }
    ComponentTrajectory::new(x, y, th, &legs[..n])
}

/// One timed waypoint: pose and leg extensions.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct Waypoint {
    /// Time (s from the trajectory start).
    pub t: f64,
    /// z at the waypoint (x, y, θ, λ_1 … λ_n); θ is not wrapped (give 2π for a full turn).
    pub z: ZVec,
}

/// A waypoint whose time may be left open (`t = None`): the segments next to it get no
/// given duration, and the time scaling runs them as fast as the actuator limits allow
/// ([`crate::reference::timescale`]).
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct WaypointSpec {
    /// Time (s from the trajectory start), or `None`.
    pub t: Option<f64>,
    /// z at the waypoint (x, y, θ, λ_1 … λ_n); θ is not wrapped.
    pub z: ZVec,
}

impl From<Waypoint> for WaypointSpec {
    fn from(w: Waypoint) -> Self {
        Self {
            t: Some(w.t),
            z: w.z,
        }
    }
}

/// C² piecewise-quintic trajectory through waypoints.
///
/// Each component on each segment is the quintic Hermite polynomial matching position,
/// velocity and acceleration at both ends, so position, velocity and acceleration are
/// continuous. Knot velocities: 0 at the first and last waypoint (start and stop at rest)
/// and at interior waypoints where the component changes direction; otherwise the
/// three-point derivative (h_k m_{k−1} + h_{k−1} m_k)/(h_{k−1} + h_k) of the chord slopes
/// m. Knot accelerations: 0 at the ends, 2 (m_k − m_{k−1})/(h_{k−1} + h_k) inside.
///
/// **Stops.** Where every component's knot velocity is 0 (every component changes direction
/// or holds there: a corner, a reversal, a waypoint repeated to stop), the platform stops
/// exactly: the knot accelerations are 0 too, so the segment between two equal waypoints
/// stands still (a *stand*) instead of swinging out and back, and the direction in which
/// each wheel leaves and arrives is that of the segment's first non-zero derivative (its
/// jerk). [`Trajectory::stops`] lists them; the time scaling re-steers the wheels there
/// while its clock holds (a dwell), so a corner at a stop costs the time the steering
/// needs, not a crawl.
///
/// **Legs stay in their range.** A leg segment that these knot values would take beyond
/// the leg's range (a waypoint at or near a limit reached fast) gets zero velocity and
/// acceleration for that leg at both its knots, repeated until no segment leaves the range:
/// a quintic with zero end velocities and accelerations (smoothstep) is monotone and never
/// leaves [p₀, p₁]. Feasible trajectories keep their knot values (and their samples, bit for
/// bit); waypoints exactly at a limit are accepted, and evaluated legs are clamped into the
/// range so rounding can never put one 1e-12 m outside it.
///
/// **Segments without a given time.** A segment is *timed* when both its waypoints have a
/// time (its duration is their difference); otherwise it is *free*: its duration here is the
/// nominal [`nominal_segment_time`], which only parametrises the path, and
/// [`Trajectory::timed_at`] tells the time scaling to pick the fastest timing the limits
/// allow there.
#[derive(Clone, Debug, PartialEq)]
pub struct QuinticSpline {
    times: Vec<f64>,
    /// Per segment, per component, the coefficients c0..c5 in τ = t − t_k.
    coeffs: Vec<[[f64; 6]; Z_MAX]>,
    /// Per segment: its duration was given (true) or is nominal (free).
    timed: Vec<bool>,
    /// (λ_min, λ_max) per leg.
    leg_range: [(f64, f64); MAX_WHEELS],
    n: usize,
}

pub(crate) fn quintic(p0: f64, v0: f64, a0: f64, p1: f64, v1: f64, a1: f64, h: f64) -> [f64; 6] {
    let dp = p1 - p0;
    let h2 = h * h;
    let h3 = h2 * h;
    [
        p0,
        v0,
        0.5 * a0,
        (20.0 * dp - (8.0 * v1 + 12.0 * v0) * h - (3.0 * a0 - a1) * h2) / (2.0 * h3),
        (-30.0 * dp + (14.0 * v1 + 16.0 * v0) * h + (3.0 * a0 - 2.0 * a1) * h2) / (2.0 * h3 * h),
        (12.0 * dp - 6.0 * (v1 + v0) * h + (a1 - a0) * h2) / (2.0 * h3 * h2),
    ]
}

pub(crate) fn eval_quintic(c: &[f64; 6], tau: f64) -> (f64, f64, f64, f64) {
    let p = c[0] + tau * (c[1] + tau * (c[2] + tau * (c[3] + tau * (c[4] + tau * c[5]))));
    let v = c[1] + tau * (2.0 * c[2] + tau * (3.0 * c[3] + tau * (4.0 * c[4] + tau * 5.0 * c[5])));
    let a = 2.0 * c[2] + tau * (6.0 * c[3] + tau * (12.0 * c[4] + tau * 20.0 * c[5]));
    let j = 6.0 * c[3] + tau * (24.0 * c[4] + tau * 60.0 * c[5]);
    (p, v, a, j)
}

/// Latest waypoint time (s): 10 h. Longer runs are split into several trajectories; the
/// runtime plans and checks every control period of a trajectory before it starts
/// ([`crate::reference::timescale`]), which stays within seconds up to this length.
pub const MAX_WAYPOINT_TIME_S: f64 = 36_000.0;

/// Shortest time between two waypoints (s): 10 ms, shorter than any segment the platform can
/// follow (a control cycle is 3–12.5 ms), long enough that the spline's coefficients (which
/// divide by up to the fifth power of the segment time) stay finite.
pub const MIN_SEGMENT_S: f64 = 0.01;

/// Slack of the [`MIN_SEGMENT_S`] check (s): waypoints written 10 ms apart in decimal
/// (`t = 0.02`, `t = 0.03`) differ by 0.009999999999999998 s in binary floating point. 1 ns is
/// far above that rounding (10⁻¹¹ s at the 10 h limit) and far below a control cycle.
pub const MIN_SEGMENT_SLACK_S: f64 = 1e-9;

/// Largest magnitudes a waypoint's coordinates (m) and heading (rad) may have on platform `p`,
/// so that a coordinate can hold what the controller measures. The odometry adds one cycle's
/// motion to the pose every cycle; the smallest motion the encoders report in a cycle is one
/// wheel-speed step (the native protocol's 0.001 rad/s) times the wheel radius times the
/// period (3.4·10⁻⁷ m on the default platform), and for the heading that distance over the
/// longest lever (λ_max). Where an f64 of the coordinate's magnitude is coarser than 1/64 of
/// that, the pose cannot follow the motion (at x = 10¹⁵ m a step of f64 is 0.125 m): the bound
/// is the largest power of two below which the spacing of f64 is at most that fine —
/// 2²⁵ m ≈ 3.4·10⁷ m (more than UTM's northings) and 2²⁶ rad on the default platform.
pub fn coordinate_limits(p: &Platform) -> (f64, f64) {
    let step = crate::estimation::odometry::EncoderResolution::default().wheel_speed
        * p.wheel_radius
        * p.dt();
    let lever = p.wheels.iter().map(|w| w.lambda_max).fold(0.0, f64::max);
    // f64 spacing in [2^e, 2^(e+1)) is 2^(e-52): at most `fine` for every e < log2(fine) + 52.
    let limit = |fine: f64| 2f64.powi(fine.log2().floor() as i32 + 53);
    (limit(step / 64.0), limit(step / lever / 64.0))
}

/// Nominal duration (s) of a segment from `a` to `b` without a given time: the longest of
/// its translation at the wheels' top rolling speed r·ω_max, its rotation at that speed on the
/// longest lever (the largest λ_max), and its largest leg move at the leg speed limit; at least
/// [`MIN_SEGMENT_S`]. It only parametrises the path (the shape of the spline through the
/// waypoints, like a chord-length parametrisation); the time scaling finds the timing.
pub fn nominal_segment_time(p: &Platform, a: &ZVec, b: &ZVec) -> f64 {
    let v = p.limits.wheel_speed * p.wheel_radius;
    let lever = p.wheels.iter().map(|w| w.lambda_max).fold(0.0, f64::max);
    let mut h = (b[0] - a[0]).hypot(b[1] - a[1]) / v;
    h = h.max((b[2] - a[2]).abs() * lever / v);
    for i in 0..p.n().min(MAX_WHEELS) {
        h = h.max((b[3 + i] - a[3 + i]).abs() / p.limits.leg_speed);
    }
    if h.is_finite() {
        h.max(MIN_SEGMENT_S)
    } else {
        MIN_SEGMENT_S
    }
}

impl QuinticSpline {
    /// Builds the spline through `waypoints` (at least 2, strictly increasing times ≥ 0),
    /// checked against the platform: leg count, leg range at the waypoints (the segments are
    /// kept inside it, see the type's docs).
    pub fn new(p: &Platform, waypoints: &[Waypoint]) -> Result<Self, TrajectoryError> {
        let specs: Vec<WaypointSpec> = waypoints.iter().map(|w| (*w).into()).collect();
        Self::from_specs(p, &specs)
    }

    /// Builds the spline through waypoints whose times may be left open (see the type's docs
    /// for timed and free segments). A given time must be ≥ 0 and at most
    /// [`MAX_WAYPOINT_TIME_S`]; between two consecutive waypoints that both have one it must
    /// increase by at least [`MIN_SEGMENT_S`]. A first waypoint without a time is at 0.
    pub fn from_specs(p: &Platform, waypoints: &[WaypointSpec]) -> Result<Self, TrajectoryError> {
        let n = p.n().min(MAX_WHEELS);
        if waypoints.len() < 2 {
            return Err(TrajectoryError::TooFewWaypoints {
                got: waypoints.len(),
            });
        }
        for (k, w) in waypoints.iter().enumerate() {
            if let Some(t) = w.t {
                finite(&format!("waypoints[{k}].t"), t)?;
            }
            for c in 0..3 + n {
                let name = match c {
                    0 => format!("waypoints[{k}].x"),
                    1 => format!("waypoints[{k}].y"),
                    2 => format!("waypoints[{k}].theta"),
                    _ => format!("waypoints[{k}].legs[{}]", c - 3),
                };
                finite(&name, w.z[c])?;
                let limit = match c {
                    0 | 1 => Some(coordinate_limits(p).0),
                    2 => Some(coordinate_limits(p).1),
                    _ => None,
                };
                if let Some(limit) = limit.filter(|l| w.z[c].abs() > *l) {
                    return Err(TrajectoryError::BadParameter {
                        field: name,
                        value: w.z[c],
                        reason: format!(
                            "beyond ±{limit} {}: at that magnitude f64 cannot hold the motion the encoders measure in a cycle (see `trajectory::coordinate_limits`); give the waypoints in a frame whose origin is nearer",
                            if c == 2 { "rad" } else { "m" }
                        ),
                    });
                }
            }
            if let Some(t) = w.t {
                if k == 0 && t < 0.0 {
                    return Err(TrajectoryError::BadParameter {
                        field: "waypoints[0].t".into(),
                        value: t,
                        reason: "must be ≥ 0 (time from the trajectory start)".into(),
                    });
                }
                if t > MAX_WAYPOINT_TIME_S {
                    return Err(TrajectoryError::BadParameter {
                        field: format!("waypoints[{k}].t"),
                        value: t,
                        reason: format!(
                            "must be at most {MAX_WAYPOINT_TIME_S} s (10 h) from the trajectory start: a longer run is split into several trajectories"
                        ),
                    });
                }
            }
            let prev = if k > 0 { waypoints[k - 1].t } else { None };
            if let (Some(t), Some(prev)) = (w.t, prev) {
                if t <= prev {
                    return Err(TrajectoryError::NonIncreasingTime {
                        waypoint: k,
                        t,
                        previous: prev,
                    });
                }
                if t - prev < MIN_SEGMENT_S - MIN_SEGMENT_SLACK_S {
                    return Err(TrajectoryError::BadParameter {
                        field: format!("waypoints[{k}].t"),
                        value: t,
                        reason: format!(
                            "is only {} s after waypoints[{}].t = {}: waypoints must be at least {MIN_SEGMENT_S} s apart (a segment shorter than a control cycle cannot be followed)",
                            crate::num::Num(t - prev),
                            k - 1,
                            crate::num::Num(prev)
                        ),
                    });
                }
            }
            for (i, wc) in p.wheels.iter().enumerate().take(n) {
                let l = w.z[3 + i];
                if l < wc.lambda_min || l > wc.lambda_max {
                    return Err(TrajectoryError::LegOutOfRange {
                        waypoint: k,
                        leg: i,
                        value: l,
                        min: wc.lambda_min,
                        max: wc.lambda_max,
                    });
                }
            }
        }
        // Knot times: given times where both ends of a segment have one (exactly as given
        // while no free segment came before), nominal durations elsewhere.
        let m = waypoints.len();
        let mut times = Vec::with_capacity(m);
        let mut timed = Vec::with_capacity(m - 1);
        times.push(waypoints[0].t.unwrap_or(0.0));
        for k in 1..m {
            let prev = times[k - 1];
            let t = match (waypoints[k - 1].t, waypoints[k].t) {
                (Some(a), Some(b)) => {
                    timed.push(true);
                    if prev == a {
                        b
                    } else {
                        prev + (b - a)
                    }
                }
                _ => {
                    timed.push(false);
                    prev + nominal_segment_time(p, &waypoints[k - 1].z, &waypoints[k].z)
                }
            };
            if t > MAX_WAYPOINT_TIME_S {
                return Err(TrajectoryError::BadParameter {
                    field: format!("waypoints[{k}].t"),
                    value: t,
                    reason: format!(
                        "the trajectory reaches this waypoint only after {} s, beyond the {MAX_WAYPOINT_TIME_S} s (10 h) a run may take: split it into several trajectories",
                        crate::num::Num(t)
                    ),
                });
            }
            times.push(t);
        }
        let mut vel = vec![ZVec::zeros(); m];
        let mut acc = vec![ZVec::zeros(); m];
        for k in 1..m - 1 {
            let h0 = times[k] - times[k - 1];
            let h1 = times[k + 1] - times[k];
            for c in 0..3 + n {
                let m0 = (waypoints[k].z[c] - waypoints[k - 1].z[c]) / h0;
                let m1 = (waypoints[k + 1].z[c] - waypoints[k].z[c]) / h1;
                vel[k][c] = if m0 * m1 <= 0.0 {
                    0.0
                } else {
                    (h1 * m0 + h0 * m1) / (h0 + h1)
                };
                acc[k][c] = 2.0 * (m1 - m0) / (h0 + h1);
            }
            // A full stop (type docs, "Stops").
            if (0..3 + n).all(|c| vel[k][c] == 0.0) {
                for c in 0..3 + n {
                    acc[k][c] = 0.0;
                }
            }
        }
        let mut leg_range = [(0.0, 0.0); MAX_WHEELS];
        for (i, wc) in p.wheels.iter().enumerate().take(n) {
            leg_range[i] = (wc.lambda_min, wc.lambda_max);
        }
        let build = |k: usize, c: usize, vel: &[ZVec], acc: &[ZVec]| {
            quintic(
                waypoints[k].z[c],
                vel[k][c],
                acc[k][c],
                waypoints[k + 1].z[c],
                vel[k + 1][c],
                acc[k + 1][c],
                times[k + 1] - times[k],
            )
        };
        // Legs: knots whose values would take a segment out of the range get zero velocity
        // and acceleration (type docs); each pass zeroes at least one more knot value, so this
        // ends within 2m passes per leg.
        for i in 0..n {
            let c = 3 + i;
            let (lo, hi) = leg_range[i];
            for _ in 0..=2 * m {
                let mut changed = false;
                for k in 0..m - 1 {
                    let seg = build(k, c, &vel, &acc);
                    let h = times[k + 1] - times[k];
                    let out = (0..=200).any(|j| {
                        let (l, ..) = eval_quintic(&seg, h * j as f64 / 200.0);
                        l < lo - 1e-9 || l > hi + 1e-9
                    });
                    if out {
                        for kk in [k, k + 1] {
                            if vel[kk][c] != 0.0 || acc[kk][c] != 0.0 {
                                vel[kk][c] = 0.0;
                                acc[kk][c] = 0.0;
                                changed = true;
                            }
                        }
                    }
                }
                if !changed {
                    break;
                }
            }
        }
        // Knots the leg pass left with every velocity 0 are full stops too.
        for k in 1..m - 1 {
            if (0..3 + n).all(|c| vel[k][c] == 0.0) {
                for c in 0..3 + n {
                    acc[k][c] = 0.0;
                }
            }
        }
        let mut coeffs = Vec::with_capacity(m - 1);
        for k in 0..m - 1 {
            let mut seg = [[0.0; 6]; Z_MAX];
            for (c, s) in seg.iter_mut().enumerate().take(3 + n) {
                *s = build(k, c, &vel, &acc);
            }
            coeffs.push(seg);
        }
        Ok(Self {
            times,
            coeffs,
            timed,
            leg_range,
            n,
        })
    }

    /// The knot times (s): the waypoints' times, with nominal durations for free segments.
    pub fn times(&self) -> &[f64] {
        &self.times
    }

    /// Parses a waypoint list from TOML text and builds the spline for platform `p`.
    ///
    /// Format: one `[[waypoints]]` table per waypoint with `t` (s, optional), `x`, `y` (m),
    /// `theta` (rad, not wrapped) and `legs` (m, one per wheel):
    ///
    /// ```toml
    /// [[waypoints]]
    /// t = 0.0
    /// x = 0.0
    /// y = 0.0
    /// theta = 0.0
    /// legs = [0.45, 0.45, 0.45, 0.45]
    /// ```
    ///
    /// A waypoint without `t` leaves the timing of the segments next to it to the time
    /// scaling: they run as fast as the actuator limits allow. Given times only fix the
    /// durations of segments between two waypoints that both have one.
    pub fn from_toml_str(p: &Platform, text: &str) -> Result<Self, TrajectoryError> {
        #[derive(Deserialize)]
        #[serde(deny_unknown_fields)]
        struct WpFile {
            waypoints: Vec<WpEntry>,
        }
        #[derive(Deserialize)]
        #[serde(deny_unknown_fields)]
        struct WpEntry {
            t: Option<f64>,
            x: f64,
            y: f64,
            theta: f64,
            legs: Vec<f64>,
        }
        let f: WpFile = toml::from_str(text).map_err(|e| TrajectoryError::Parse(e.to_string()))?;
        let n = p.n().min(MAX_WHEELS);
        let mut wps = Vec::with_capacity(f.waypoints.len());
        for (k, e) in f.waypoints.iter().enumerate() {
            if e.legs.len() != n {
                return Err(TrajectoryError::LegCount {
                    waypoint: k,
                    got: e.legs.len(),
                    expected: n,
                });
            }
            let mut z = ZVec::zeros();
            z[0] = e.x;
            z[1] = e.y;
            z[2] = e.theta;
            for (i, l) in e.legs.iter().enumerate() {
                z[3 + i] = *l;
            }
            wps.push(WaypointSpec { t: e.t, z });
        }
        Self::from_specs(p, &wps)
    }

    fn segment_of(&self, t: f64) -> usize {
        let last = self.times.len() - 1;
        if t <= self.times[0] {
            0
        } else if t >= self.times[last] {
            last - 1
        } else {
            (self.times.partition_point(|&x| x <= t) - 1).min(last - 1)
        }
    }
}

/// Reads a TOML waypoint file (format in [`QuinticSpline::from_toml_str`]) and builds the
/// spline, validated against platform `p`.
pub fn load_waypoints(
    p: &Platform,
    path: impl AsRef<Path>,
) -> Result<QuinticSpline, TrajectoryError> {
    let path = path.as_ref();
    let text = rollbase_driver::input::read_text(
        path,
        rollbase_driver::input::MAX_TRAJECTORY_BYTES,
        "waypoint file",
    )?;
    QuinticSpline::from_toml_str(p, &text)
}

impl Trajectory for QuinticSpline {
    fn sample(&self, t: f64) -> ReferenceSample {
        let mut s = ReferenceSample {
            t,
            n: self.n,
            ..ReferenceSample::default()
        };
        let last = self.times.len() - 1;
        let tc = if t.is_finite() { t } else { 0.0 };
        let seg = self.segment_of(tc);
        let (tau, at_end) = if tc <= self.times[0] {
            (0.0, false)
        } else if tc >= self.times[last] {
            (self.times[last] - self.times[last - 1], true)
        } else {
            (tc - self.times[seg], false)
        };
        for c in 0..3 + self.n {
            let (p, v, a, j) = eval_quintic(&self.coeffs[seg][c], tau);
            s.z[c] = p;
            if !at_end {
                s.dz[c] = v;
                s.ddz[c] = a;
                s.dddz[c] = j;
            }
        }
        for i in 0..self.n {
            let (lo, hi) = self.leg_range[i];
            s.z[3 + i] = s.z[3 + i].clamp(lo, hi);
        }
        s
    }
    fn duration(&self) -> f64 {
        self.times.last().copied().unwrap_or(0.0)
    }
    fn n_legs(&self) -> usize {
        self.n
    }
    fn timed_at(&self, t: f64) -> bool {
        let t = if t.is_finite() { t } else { 0.0 };
        self.timed[self.segment_of(t)]
    }
    fn stops(&self) -> Vec<(f64, f64)> {
        // Knots where every component rests (velocity and acceleration 0), merged with the
        // stands between two of them whose waypoints are equal.
        let rests = |k: usize| {
            let seg = if k + 1 < self.times.len() { k } else { k - 1 };
            let tau = self.times[k] - self.times[seg];
            (0..3 + self.n).all(|c| {
                let (_, v, a, _) = eval_quintic(&self.coeffs[seg][c], tau);
                v == 0.0 && a == 0.0
            })
        };
        let mut out: Vec<(f64, f64)> = Vec::new();
        for k in 0..self.times.len() {
            if !rests(k) {
                continue;
            }
            let t = self.times[k];
            let stand = k > 0
                && out.last().is_some_and(|l| l.1 == self.times[k - 1])
                && (0..3 + self.n).all(|c| self.coeffs[k - 1][c][1..].iter().all(|&x| x == 0.0));
            match out.last_mut() {
                Some(last) if stand => last.1 = t,
                _ => out.push((t, t)),
            }
        }
        out
    }
    fn waypoint_near(&self, t: f64) -> Option<usize> {
        let t = if t.is_finite() { t } else { 0.0 };
        let k = self.segment_of(t);
        Some(if t - self.times[k] <= self.times[k + 1] - t {
            k
        } else {
            k + 1
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::f64::consts::PI;

    fn check_continuity(tr: &dyn Trajectory, k: usize) -> (f64, f64) {
        // max jumps of z̈ between consecutive 1 ms samples, and max |dz − fd(z)|
        let dt = 1e-3;
        let mut max_jump: f64 = 0.0;
        let mut max_fd: f64 = 0.0;
        let mut prev = tr.sample(0.0);
        let steps = (tr.duration() / dt).ceil() as usize + 10;
        for i in 1..steps {
            let s = tr.sample(i as f64 * dt);
            max_jump = max_jump.max((s.ddz[k] - prev.ddz[k]).abs());
            let fd = (s.z[k] - prev.z[k]) / dt;
            let mid = 0.5 * (s.dz[k] + prev.dz[k]);
            max_fd = max_fd.max((fd - mid).abs());
            prev = s;
        }
        (max_jump, max_fd)
    }

    #[test]
    fn seed000_durations_are_close_to_the_paper() {
        let p = Platform::justin();
        let tr = seed000_experiment(&p);
        let tt = tr.component(0).unwrap().duration();
        let ty = tr.component(1).unwrap().duration();
        let tr_ = tr.component(2).unwrap().duration();
        let tl = tr.component(3).unwrap().duration();
        // Closed-form values of the blend rule (module docs).
        let eps = 0.01;
        let expect_t = 1.5 * (0.18 - eps) / 0.1
            + 1.5 * 0.18 / 0.1
            + (4.5 - 0.75 * (0.18f64.powi(2) - eps * eps) / 0.1 - 0.75 * 0.18f64.powi(2) / 0.1)
                / 0.18;
        assert!((tt - expect_t).abs() < 1e-12 && (ty - tt).abs() < 1e-12);
        assert!((tl - (0.19 / 0.02 + 1.5 * 0.02 / 0.01)).abs() < 1e-9);
        // Against the paper: rotation 23 s, translation 30.8 s, legs 15 s.
        let w0 = eps / 0.82;
        let expect_r = 1.5 * (0.31 - w0) / 0.17
            + 1.5 * 0.31 / 0.17
            + (2.0 * PI
                - 0.75 * (0.31f64.powi(2) - w0 * w0) / 0.17
                - 0.75 * 0.31f64.powi(2) / 0.17)
                / 0.31;
        assert!((tr_ - expect_r).abs() < 1e-12);
        assert!((tr_ - 22.90).abs() < 0.005, "rotation {tr_}");
        assert!((tt - 27.55).abs() < 0.01, "translation {tt}");
        assert!((tl - 12.5).abs() < 1e-9, "legs {tl}");
        assert!((tr.duration() - tt).abs() < 1e-12);
        // Goals and persistence start.
        let end = tr.sample(tr.duration() + 1.0);
        assert!((end.z[0] - 4.5).abs() < 1e-12 && (end.z[2] - 2.0 * PI).abs() < 1e-12);
        assert!((end.z[3] - 0.56).abs() < 1e-12);
        let s0 = tr.sample(0.0);
        assert!((s0.dz[0] - eps).abs() < 1e-15 && (s0.dz[2] - eps / 0.82).abs() < 1e-15);
        assert_eq!(s0.dz[3], 0.0);
    }

    #[test]
    fn quasi_trapezoid_respects_limits_and_is_c2() {
        let q = QuasiTrapezoid::new(1.0, -2.0, 0.5, 0.3, 0.1).unwrap();
        let mut vmax: f64 = 0.0;
        let mut amax: f64 = 0.0;
        for i in 0..=20000 {
            let s = q.sample(q.duration() * i as f64 / 20000.0);
            vmax = vmax.max(s.vel.abs());
            amax = amax.max(s.acc.abs());
        }
        assert!(vmax <= 0.5 + 1e-12 && vmax > 0.499);
        assert!(amax <= 0.3 + 1e-9 && amax > 0.299);
        assert!((q.sample(0.0).vel + 0.1).abs() < 1e-15);
        assert!((q.sample(q.duration()).pos + 2.0).abs() < 1e-12);
        let tr = ComponentTrajectory::new(q, q, q, &[]);
        let (jump, fd) = check_continuity(&tr, 0);
        // largest jerk of a blend is 6 Δv / T_b² = 6 a² / (2.25 Δv); smallest Δv here is 0.4
        let jerk_max = 6.0 * 0.3 * 0.3 / (2.25 * 0.4);
        assert!(jump <= jerk_max * 1e-3 * 1.001, "ddz jump {jump}");
        assert!(
            fd < 1e-6,
            "velocity is not the derivative of position: {fd}"
        );
    }

    #[test]
    fn short_move_uses_a_lower_peak_speed() {
        let q = QuasiTrapezoid::new(0.0, 0.01, 1.0, 0.1, 0.0).unwrap();
        let peak = (0..=1000)
            .map(|i| q.sample(q.duration() * i as f64 / 1000.0).vel)
            .fold(0.0, f64::max);
        assert!(peak < 1.0 && (q.sample(q.duration()).pos - 0.01).abs() < 1e-12);
        assert!((peak - (0.01 * 0.1 / 1.5f64).sqrt()).abs() < 1e-4);
    }

    #[test]
    fn bad_profile_parameters_are_rejected() {
        assert!(matches!(
            QuasiTrapezoid::new(0.0, 1.0, -1.0, 1.0, 0.0),
            Err(TrajectoryError::BadParameter { ref field, .. }) if field == "v_max"
        ));
        assert!(matches!(
            QuasiTrapezoid::new(0.0, f64::NAN, 1.0, 1.0, 0.0),
            Err(TrajectoryError::NonFinite { ref field, .. }) if field == "goal"
        ));
        assert!(QuasiTrapezoid::new(0.0, 1e-6, 1.0, 0.1, 0.5).is_err());
        assert!(QuasiTrapezoid::new(0.0, 1.0, 1.0, 0.1, 2.0).is_err());
    }

    const WP: &str = r#"
[[waypoints]]
t = 0.0
x = 0.0
y = 0.0
theta = 0.0
legs = [0.45, 0.45, 0.45, 0.45]

[[waypoints]]
t = 4.0
x = 1.0
y = 0.5
theta = 0.5
legs = [0.50, 0.45, 0.40, 0.45]

[[waypoints]]
t = 7.0
x = 2.0
y = 0.5
theta = 1.0
legs = [0.45, 0.45, 0.45, 0.50]
"#;

    #[test]
    fn quintic_spline_interpolates_and_is_c2() {
        let p = Platform::justin();
        let s = QuinticSpline::from_toml_str(&p, WP).unwrap();
        assert_eq!(s.n_legs(), 4);
        assert!((s.duration() - 7.0).abs() < 1e-12);
        let a = s.sample(4.0);
        assert!((a.z[0] - 1.0).abs() < 1e-12 && (a.z[3] - 0.5).abs() < 1e-12);
        let e = s.sample(7.0);
        assert!((e.z[0] - 2.0).abs() < 1e-12 && e.dz[0] == 0.0);
        let st = s.sample(0.0);
        assert!(st.dz.iter().all(|v| *v == 0.0) && st.ddz.iter().all(|v| *v == 0.0));
        for k in 0..7 {
            let (jump, fd) = check_continuity(&s, k);
            assert!(jump < 2e-3, "component {k}: acceleration jump {jump}");
            assert!(fd < 1e-5, "component {k}: {fd}");
        }
        // across the knot at t = 4 exactly: left and right limits agree
        let l = s.sample(4.0 - 1e-9);
        let r = s.sample(4.0 + 1e-9);
        for k in 0..7 {
            assert!((l.ddz[k] - r.ddz[k]).abs() < 1e-6);
            assert!((l.dz[k] - r.dz[k]).abs() < 1e-8);
        }
    }

    #[test]
    fn waypoint_errors_name_the_field() {
        let p = Platform::justin();
        let bad_leg = WP.replace(
            "legs = [0.50, 0.45, 0.40, 0.45]",
            "legs = [0.50, 0.45, 0.30, 0.45]",
        );
        match QuinticSpline::from_toml_str(&p, &bad_leg) {
            Err(
                e @ TrajectoryError::LegOutOfRange {
                    waypoint: 1,
                    leg: 2,
                    ..
                },
            ) => {
                assert!(e.to_string().contains("waypoints[1].legs[2]"))
            }
            other => panic!("{other:?}"),
        }
        let bad_t = WP.replace("t = 7.0", "t = 3.0");
        assert!(matches!(
            QuinticSpline::from_toml_str(&p, &bad_t),
            Err(TrajectoryError::NonIncreasingTime { waypoint: 2, .. })
        ));
        let nan = WP.replace("x = 1.0", "x = nan");
        match QuinticSpline::from_toml_str(&p, &nan) {
            Err(TrajectoryError::NonFinite { field, .. }) => assert_eq!(field, "waypoints[1].x"),
            other => panic!("{other:?}"),
        }
        let count = WP.replace("legs = [0.45, 0.45, 0.45, 0.50]", "legs = [0.45]");
        assert!(matches!(
            QuinticSpline::from_toml_str(&p, &count),
            Err(TrajectoryError::LegCount {
                waypoint: 2,
                got: 1,
                expected: 4
            })
        ));
        assert!(matches!(
            QuinticSpline::from_toml_str(&p, "waypoints = 3"),
            Err(TrajectoryError::Parse(_))
        ));
        assert!(matches!(
            load_waypoints(&p, "/nonexistent/rollbase.toml"),
            Err(TrajectoryError::Input(_))
        ));
    }

    #[test]
    fn absurd_waypoint_times_are_refused_naming_the_waypoint() {
        let p = Platform::justin();
        let file = |t1: &str| {
            format!(
                "[[waypoints]]\nt = 0.0\nx = 0.0\ny = 0.0\ntheta = 0.0\nlegs = [0.45, 0.45, 0.45, 0.45]\n\n[[waypoints]]\nt = {t1}\nx = 1.0\ny = 0.0\ntheta = 0.0\nlegs = [0.45, 0.45, 0.45, 0.45]\n"
            )
        };
        let e = QuinticSpline::from_toml_str(&p, &file("1e300")).unwrap_err();
        let m = e.to_string();
        assert!(
            m.starts_with("`waypoints[1].t` = 1e300: must be at most 36000 s"),
            "{m}"
        );
        let e = QuinticSpline::from_toml_str(&p, &file("1e-300")).unwrap_err();
        let m = e.to_string();
        assert!(
            m.contains("waypoints[1].t") && m.contains("1e-300 s after waypoints[0].t"),
            "{m}"
        );
        assert!(QuinticSpline::from_toml_str(&p, &file("36000.0")).is_ok());
    }

    fn legs_file(rows: &[(Option<f64>, f64, [f64; 4])]) -> String {
        rows.iter()
            .map(|(t, x, l)| {
                let t = t.map(|t| format!("t = {t}\n")).unwrap_or_default();
                format!(
                    "[[waypoints]]\n{t}x = {x}\ny = 0.0\ntheta = 0.0\nlegs = [{}, {}, {}, {}]\n\n",
                    l[0], l[1], l[2], l[3]
                )
            })
            .collect()
    }

    #[test]
    fn waypoints_at_a_leg_limit_are_accepted_and_the_legs_never_leave_their_range() {
        let p = Platform::justin();
        let cases: [(&[f64], &[f64]); 4] = [
            (&[0.37, 0.56], &[0.0, 2.0]),
            (&[0.40, 0.56, 0.56, 0.40], &[0.0, 1.0, 2.5, 3.0]),
            // Fast up to a waypoint just below the limit, then on to it: the three-point knot
            // velocity would carry the leg 0.2 mm past λ_max.
            (&[0.37, 0.50, 0.56, 0.50], &[0.0, 0.3, 2.0, 2.1]),
            (&[0.37, 0.56, 0.37, 0.56], &[0.0, 1.0, 1.7, 3.0]),
        ];
        for (legs, ts) in cases {
            let rows: Vec<_> = legs
                .iter()
                .zip(ts)
                .enumerate()
                .map(|(k, (l, t))| (Some(*t), k as f64 * 0.3, [*l; 4]))
                .collect();
            let s = QuinticSpline::from_toml_str(&p, &legs_file(&rows)).expect("accepted");
            for k in 0..=4000 {
                let r = s.sample(s.duration() * k as f64 / 4000.0);
                for i in 0..4 {
                    assert!(
                        (0.37..=0.56).contains(&r.z[3 + i]),
                        "{legs:?}: {}",
                        r.z[3 + i]
                    );
                }
            }
            for (l, t) in legs.iter().zip(ts) {
                assert!((s.sample(*t).z[3] - l).abs() < 1e-12);
            }
        }
        // Outside the range is still refused, naming the waypoint and leg.
        let e = QuinticSpline::from_toml_str(
            &p,
            &legs_file(&[
                (Some(0.0), 0.0, [0.45; 4]),
                (Some(1.0), 1.0, [0.45, 0.5601, 0.45, 0.45]),
            ]),
        )
        .unwrap_err();
        assert!(
            e.to_string().contains("waypoints[1].legs[1] = 0.5601"),
            "{e}"
        );
    }

    #[test]
    fn waypoints_without_times_get_nominal_durations_and_free_segments() {
        let p = Platform::justin();
        let l = [0.45; 4];
        // No times at all: knot times from the nominal durations, every segment free.
        let free = legs_file(&[
            (None, 0.0, l),
            (None, 1.0, l),
            (None, 1.5, [0.56, 0.45, 0.45, 0.45]),
        ]);
        let s = QuinticSpline::from_toml_str(&p, &free).unwrap();
        let v = p.limits.wheel_speed * p.wheel_radius;
        assert!((s.times()[1] - 1.0 / v).abs() < 1e-12, "{:?}", s.times());
        // 0.11 m of leg at 0.25 m/s takes longer than 0.5 m of travel at 1.18 m/s.
        assert!((s.times()[2] - s.times()[1] - 0.11 / p.limits.leg_speed).abs() < 1e-12);
        assert!(!s.timed_at(0.1) && !s.timed_at(s.duration()));
        assert_eq!(s.waypoint_near(s.times()[1] + 0.01), Some(1));
        // Mixed: a segment between two timed waypoints keeps its duration, the others are
        // free; absolute times are not kept across a free segment.
        let mixed = legs_file(&[
            (Some(0.0), 0.0, l),
            (None, 1.0, l),
            (Some(7.0), 2.0, l),
            (Some(9.0), 3.0, l),
        ]);
        let s = QuinticSpline::from_toml_str(&p, &mixed).unwrap();
        let t = s.times();
        assert!(
            (t[3] - t[2] - 2.0).abs() < 1e-12 && (t[1] - 1.0 / v).abs() < 1e-12,
            "{t:?}"
        );
        assert!(!s.timed_at(0.5 * (t[0] + t[1])) && !s.timed_at(0.5 * (t[1] + t[2])));
        assert!(s.timed_at(0.5 * (t[2] + t[3])));
        // All timed: the times as given, bit for bit.
        let timed = QuinticSpline::from_toml_str(&p, WP).unwrap();
        assert_eq!(timed.times(), &[0.0, 4.0, 7.0]);
        assert!(timed.timed_at(5.0));
        // Consecutive given times must still increase.
        let bad = legs_file(&[
            (Some(0.0), 0.0, l),
            (Some(2.0), 1.0, l),
            (Some(1.0), 2.0, l),
            (None, 3.0, l),
        ]);
        assert!(matches!(
            QuinticSpline::from_toml_str(&p, &bad),
            Err(TrajectoryError::NonIncreasingTime { waypoint: 2, .. })
        ));
        assert!(nominal_segment_time(&p, &ZVec::zeros(), &ZVec::zeros()) == MIN_SEGMENT_S);
    }
}
