//! Rolling turns: a live twist shaped as a direction and a speed, so that the wheels change
//! direction while the platform rolls instead of stopping to align.
//!
//! # Why
//!
//! The line-based transitions of [`crate::reference::shaper`] move the twist q̇ on straight
//! lines. A line between two twists of different direction passes close to rest, where a
//! small change of the twist is a large change of every wheel's direction, so a change of
//! direction either crawls through near rest within the steering limits or stops, turns the
//! wheels and starts again. On issue 23's noise-free joystick (eight 20 s sticks of
//! `tests/tests/shaper_streams.rs`) that leaves the base standing while its wheels turn for
//! 16 points of the ideal path (`tests/examples/joystick_limits.rs`).
//!
//! # Direction and speed
//!
//! Write the twist as q̇ = μ η̂ with η̂ a unit vector in the metric (v_x, v_y, L ω) (L the
//! legs' mean extension) and μ a signed speed. Wheel i's contact velocity is
//! u_i = G_i q̇ = μ G_i η̂ (seed 000 eq. 18, legs at rest), so its steering angle
//!
//! ```text
//! φ_i = atan2(G_i η̂)   (mod π: a wheel rolling backwards is the same steering)
//! ```
//!
//! depends on η̂ alone. Turning η̂ at a rate w (a tangent vector at η̂) turns wheel i at
//!
//! ```text
//! φ̇_i = (G_i η̂ × G_i w) / |G_i η̂|²
//! ```
//!
//! whatever μ is, and a reversal (μ through zero, η̂ kept) needs no steering at all. So a
//! change of direction is a turn of η̂ on the unit sphere within every wheel's steering
//! rate and acceleration, and the speed μ is free to stay up meanwhile, within the wheel
//! acceleration the turn leaves: u̇_i = μ̇ G_i η̂ + μ G_i w, whose second term (μ |G_i w|,
//! the lateral acceleration of the contact point) is taken first, within `lateral_accel`.
//! This is seed 004's rule (Sect. 4.1, the direction of the operational motion is kept and
//! only the speed of execution changes) applied to the turn itself: the direction moves
//! as fast as the steering allows, the speed as fast as the wheels allow.
//!
//! # Where the sphere is singular
//!
//! G_i η̂ = 0 at two antipodal points n_i (the ICR at wheel i). Near them φ̇_i grows as the
//! distance to n_i shrinks, and a turn that passes close to n_i swings wheel i by nearly π.
//! Two rules keep every wheel within its limits there:
//!
//! * **A check before each step.** The turn rate w moves towards the geodesic to the goal's
//!   direction (rate within the steering rate, braking to the goal within the steering
//!   acceleration) only as far as a braking test allows: from the state the step leads to,
//!   braking w along its geodesic (every steered wheel's rate falling in proportion, the
//!   fastest at `BRAKE_SHARE` of the acceleration share) must keep every steered wheel's
//!   rate and acceleration within their shares until w is at rest. A step that fails is
//!   bisected towards the present w; if even that fails, the turn brakes by the same law.
//!   The test looks ahead as far as braking takes (at most `CHECK_STEPS` cycles), so a turn
//!   slows before a singular point rather than at it. The look-ahead holds μ, so a wheel
//!   steered now counts as steered all along: a wheel it would release at today's μ stays
//!   steered if μ grows meanwhile, and one that did so (a start from rest towards the
//!   wheel's singular point) was turned at 9–13 rad/s against a 5.4 rad/s share.
//! * **Slow wheels near n_i turn on their own.** A wheel whose direction is less than
//!   `FREE_NORM` from singular (|G_i η̂| below it) and that rolls slower than the shaper's
//!   `slip_speed` (3 mm/s) is released from η̂: it steers towards its direction in η̂ within
//!   the steering shares (η̂'s rate as feed-forward, braking onto what is left). It is
//!   steered by η̂ again once it is within `SNAP_ANGLE` of its direction with its rate within
//!   one cycle's acceleration of η̂'s. A released wheel, and a wheel steered for less than
//!   the averaging window (not yet aligned in the window's mean), holds μ so that it rolls
//!   no faster than [`TURN_SPEED`] (the shaper's rule for turning wheels), and a released
//!   one also no faster across its own angle than `slip_speed`; μ brakes there within
//!   `STOP_SHARE` of the stop deceleration. Released at [`TURN_SPEED`] (1.5 cm/s) with
//!   `FREE_NORM` 0.05, a wheel let go while μ was 0.6 grew to 1.4 cm/s across its angle
//!   (86° off) before μ could brake, for 0.3 s: the leg it sits on moved 3 mm in closed
//!   loop. Released at `slip_speed` the turn brakes earlier instead, and the path grew
//!   (fewer releases, each one cheaper: 86.4 % → 88.9 % of the ideal on the eight sticks).
//!
//! At rest every wheel that is not aligned with η̂ is released, so a start from rest with
//! the wheels anywhere turns them first (aligning with the base standing); with the wheels
//! already along a common direction η̂ the start rolls along them while they turn.
//!
//! # Following a noisy goal
//!
//! Braking onto the goal's direction as late as the steering acceleration allows is the
//! fastest turn, and the worst filter: a goal that wobbles by a few degrees with the noise
//! of a stick (σ = 0.02–0.05 m/s per message) makes every wobble a turn at the full braking
//! law, and the wheels near their singular direction reverse their steering with each one
//! (three runs of sixteen, closed loop, reversed a wheel 13–17 times beyond the command's
//! own in 20 s). So on a noisy goal the turn rate is also held to θ / `FOLLOW_TIME` (θ the
//! angle left to the goal's direction, `FOLLOW_TIME` = 0.2 s): a large change of direction
//! is still turned at the steering limits until its last 0.2 s, which become a first-order
//! approach, and the noise is averaged over 0.2 s rather than chased. How noisy the goal is
//! comes from the shaper's estimate of the command's noise (the one that sets its
//! smoothing, [`Roll::follow_noise`]); a clean stream keeps the fastest turn, whose end a
//! first-order approach would only stretch (a quarter turn at 0.5 m/s would arrive within
//! 1e-3 after 1.6 s instead of under 0.8 s). The speed does not wait for it (μ follows the goal's
//! speed as before). On the eight sticks at σ = 0.02 and 0.05 m/s no run in closed loop
//! reverses a wheel more than 10 times beyond the command's own, on either profile.
//!
//! # The speed while turning
//!
//! The turn's lateral acceleration μ |G_i w| (and the base origin's) stays within
//! `lateral_accel`: a fast turn holds the speed down, since the drives follow a turn with a
//! lag and a wheel that far behind rolls sideways by that lag times μ |G_i w|.
//!
//! # Jerk
//!
//! The raw speed, direction and steering angles change their accelerations step-wise. The
//! output is their mean over the last `window` cycles (the shaper's `jerk_time`; the
//! speed's mean then goes through the drives' lag, below), as the shaper's steering
//! generator does: the mean of values within a bound is within it, and
//! the mean's acceleration changes by at most twice the bound over the window, so the jerk
//! is within 2 a / `jerk_time`. The derivatives are exact for the averaged signals: a
//! mean's rate is the difference of the window's ends over its length. μ and η̂ are
//! averaged apart and the twist is their product μ̄ η̄, so its direction is η̄'s whatever
//! μ̄ does (a reversal turns no wheel); each wheel's steering reference is the mean of its
//! raw angles, which agrees with the direction of G_i η̄ to second order in the window's
//! turn (0.11° at most on the test stick of this module).
//!
//! # The speed and the drives' lag
//!
//! The runtime sends each drive its reference plus the drive's lag compensation,
//! u + τ u̇ (a first-order drive of time constant τ, `lag_compensation` in
//! `runtime/core.rs`). With the window mean b as the reference speed, the command's
//! acceleration is ḃ + τ b̈, and the window's jerk (up to 2a/T) adds up to 2aτ/T = a on top
//! (T = 40 ms, τ = 20 ms): 1.5 to 2 times the share at a start or a reversal. That is why
//! the speed used 0.6 of the acceleration limit, and the output guard still scaled 6–35
//! cycles of each 20 s closed-loop stick. So the speed is shaped at the command instead:
//!
//! ```text
//! b     = window mean of the raw μ       (|ḃ| ≤ speed_accel / max|G_i η̂|, |b̈| ≤ 2|ḃ|/T)
//! μ̄' = (b − μ̄) / τ                       (the reference: b through the drive's lag)
//! ⇒  μ̄ + τ μ̄' = b
//! ```
//!
//! The lag compensation of μ̄ gives back b, whose acceleration is within `speed_accel` (0.75
//! of the limit by default; the rest for the feedback and the turn): the reference is what
//! the drive does with a command within the limits. The step is the exact solution over a
//! cycle h for b linear in between its samples, a = (b₁ − b₀)/h:
//! μ̄(h) = b₁ − aτ + (μ̄(0) − b₀ + aτ) e^(−h/τ), μ̄' = (b₁ − μ̄)/τ, μ̄'' = (a − μ̄')/τ;
//! once b rests, what the exponential leaves below 1 µm/s is rest. The reference now trails
//! the raw μ by T/2 + τ, so what caps μ for a wheel not yet aligned is taken that far ahead:
//! the wheel's angle error as it grows at the present rates, and a falling cap where it
//! will be. With the window mean as the reference and the share 0.6, the eight sticks
//! travelled 88.9 % of the ideal (shaper alone), 89.1 % (native) and 89.4 % (CiA 402) in
//! closed loop; shaped through the lag at 0.75, 90.7 %, 90.9 % and 90.8 %, and the guard
//! scales the wheel speeds in 0–9 cycles of a session. Only the speed: the direction η̂
//! and the steering angles keep the window mean (and the steering's own lag compensation on
//! top of the steering share, as before).
//!
//! # What it achieves, and what not yet
//!
//! On issue 23's eight noise-free joystick sticks the shaper with rolling turns travels
//! 90.7 % of the ideal path (72.5 % with the line transitions; 92–100 % of what wheels
//! that steer instantly would travel at the same shares), every wheel's reference within
//! 3.3 mm/s of its steering direction (`tests/tests/shaper_streams.rs`). In closed loop the
//! DFL does not track it within 5 mm (its reference wheel is steered by the compensator,
//! not by the steering reference); controller 2 does, with its leg gain raised, on noisy
//! sticks too and within issue 23's reversal bound (`docs/time-scaling.md`, "Rolling
//! turns"). The path is not 90 % of the ideal on every stick (85.3 % on the worst), so
//! [`crate::reference::shaper::ShaperConfig`] leaves it off by default.

// Index loops over parallel per-wheel arrays read better than zipped iterators here.
#![allow(clippy::needless_range_loop)]

use crate::reference::limits::HOLD_SPEED;
use crate::service::ports::Limiting;
use crate::types::MAX_WHEELS;
use std::f64::consts::PI;

/// Contact speed (m/s) below which a wheel near its singular direction turns on its own
/// (the shaper's `TURN_SPEED`).
pub const TURN_SPEED: f64 = 0.75 * HOLD_SPEED;
/// |G_i η̂| (m/s per unit of μ) below which a slow wheel is released from η̂.
const FREE_NORM: f64 = 0.03;
/// Share of the steering acceleration share the braking test brakes at.
const BRAKE_SHARE: f64 = 0.5;
/// Longest look-ahead of the braking test (cycles).
const CHECK_STEPS: usize = 800;
/// Bisections of a step that fails the braking test.
const BISECTIONS: usize = 12;
/// Angle (rad) within which a released wheel, turning at η̂'s rate, is steered by η̂ again
/// (what is left is taken up in one cycle: at most 1e-4 rad in 4 ms).
const SNAP_ANGLE: f64 = 1e-4;
/// Share of the stop deceleration a halt brakes μ at, and μ is braked at when a released
/// wheel or the turn caps it (the window mean of μ η̂ adds the product's cross terms).
const STOP_SHARE: f64 = 0.95;
/// Time constant (s) of the direction's approach to a fully noisy goal over the last part
/// of a turn (module docs, "Following a noisy goal").
const FOLLOW_TIME: f64 = 0.2;
/// Noise share ([`Roll::follow_noise`]) from which a goal's direction is followed with the
/// whole [`FOLLOW_TIME`]: a noise-free stick's stays below 0.15 (its own curvature), a
/// stick with σ = 0.02 m/s is above 0.77 nine tenths of the time.
const FOLLOW_FULL_SHARE: f64 = 0.5;
/// Reference speed (m/s) below which a speed whose command is at rest is snapped to rest.
const REST_SPEED: f64 = 1e-6;
/// History kept for the window mean (cycles, at least the window plus two).
const HIST: usize = 34;

/// What the turn may use: the reference's shares of the platform's limits, at the contact
/// points (m/s, m/s²) and of the steering (rad/s, rad/s²).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct RollLimits {
    /// Contact speed of the fastest wheel (m/s).
    pub wheel_speed: f64,
    /// Contact acceleration of any wheel (m/s²) in the reference: the bound of the turn's
    /// lateral acceleration.
    pub wheel_accel: f64,
    /// Contact acceleration (m/s²) of the speed in the command the drives get (module docs,
    /// "The speed and the drives' lag").
    pub speed_accel: f64,
    /// The drives' wheel-speed time constant (s) the speed is shaped through; 0 for none.
    pub drive_lag: f64,
    /// Deceleration of a halt (stop request, timeout), and the braking of μ when a
    /// released wheel caps it.
    pub stop_accel: f64,
    /// Steering rate (rad/s).
    pub steer_rate: f64,
    /// Steering acceleration (rad/s²).
    pub steer_accel: f64,
    /// Largest lateral acceleration μ |G_i w| of a contact point and of the base origin.
    pub lateral_accel: f64,
    /// Angle (rad) within which a wheel at rest counts as aligned with the direction the
    /// turn starts from ([`Roll::new`]).
    pub align_tolerance: f64,
    /// Sideways speed (m/s) a released wheel that is not yet aligned may roll with (the
    /// shaper's `slip_speed`).
    pub slip_speed: f64,
}

/// The raw and averaged state of a rolling turn.
#[derive(Clone, Copy, Debug)]
pub struct Roll {
    n: usize,
    dt: f64,
    window: usize,
    /// Contact points (m) in the base frame.
    pos: [[f64; 2]; MAX_WHEELS],
    /// The length scaling ω in η̂ (m).
    scale: f64,
    lim: RollLimits,
    eta: [f64; 3],
    w: [f64; 3],
    mu: f64,
    ang: [f64; MAX_WHEELS],
    rate: [f64; MAX_WHEELS],
    steered: [bool; MAX_WHEELS],
    /// Per wheel, for how many cycles it has been steered by η̂ (saturating).
    steered_for: [usize; MAX_WHEELS],
    /// Raw (μ, η̂) and angles of the last cycles (ring buffers; `k` the newest).
    hm: [[f64; 4]; HIST],
    ha: [[f64; MAX_WHEELS]; HIST],
    k: usize,
    limiting: Limiting,
    /// The reference speed μ̄ and its first two derivatives: the window mean of the raw μ
    /// through the drives' lag (module docs, "The speed and the drives' lag"); `None`
    /// without a lag (μ̄ is the window mean).
    spd: Option<[f64; 3]>,
    /// Last cycle's cap on μ for the wheels not yet aligned, and for the wheel speed.
    cap_prev: f64,
    speed_cap_prev: f64,
    /// Time constant (s) of the last approach to a noisy goal's direction; 0 for a clean
    /// goal ([`Roll::follow_noise`]).
    follow: f64,
}

/// One cycle of a rolling turn, averaged over the window: the twist q̇ = (v_x, v_y, ω), its
/// first two derivatives, and every wheel's steering angle, rate and acceleration.
#[derive(Clone, Copy, Debug, Default)]
pub struct RollSample {
    /// Twist (m/s, m/s, rad/s), base frame.
    pub q: [f64; 3],
    /// Its rate of change.
    pub qd: [f64; 3],
    /// Its second rate of change.
    pub qdd: [f64; 3],
    /// Steering angle per wheel (rad; unwrapped).
    pub steer: [f64; MAX_WHEELS],
    /// Steering rate per wheel (rad/s).
    pub steer_rate: [f64; MAX_WHEELS],
    /// Steering acceleration per wheel (rad/s²).
    pub steer_accel: [f64; MAX_WHEELS],
}

fn dot3(a: [f64; 3], b: [f64; 3]) -> f64 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}

fn unit3(a: [f64; 3]) -> [f64; 3] {
    let n = dot3(a, a).sqrt();
    if n > 0.0 {
        [a[0] / n, a[1] / n, a[2] / n]
    } else {
        a
    }
}

fn norm2(a: [f64; 2]) -> f64 {
    a[0].hypot(a[1])
}

/// `d` wrapped into [−π/2, π/2] (angles mod π).
fn wrap_half(d: f64) -> f64 {
    d - PI * (d / PI).round()
}

impl Roll {
    /// At rest with the wheels at `steer` (first `pos.len()` used). `dir`, a twist the wheels
    /// are all aligned with (if any), is where η̂ starts, every wheel steered by it; without
    /// one every wheel is released and aligns before the platform rolls.
    pub fn new(
        pos: &[[f64; 2]],
        lim: RollLimits,
        dt: f64,
        window: usize,
        steer: &[f64],
        dir: Option<[f64; 3]>,
    ) -> Self {
        let n = pos.len().min(MAX_WHEELS);
        let mut p = [[0.0; 2]; MAX_WHEELS];
        p[..n].copy_from_slice(&pos[..n]);
        let scale = (p[..n]
            .iter()
            .map(|c| c[0] * c[0] + c[1] * c[1])
            .sum::<f64>()
            / n.max(1) as f64)
            .sqrt()
            .max(1e-3);
        let mut ang = [0.0; MAX_WHEELS];
        for i in 0..n {
            ang[i] = steer
                .get(i)
                .copied()
                .filter(|a| a.is_finite())
                .unwrap_or(0.0);
        }
        let mut r = Self {
            n,
            dt,
            window: window.clamp(1, HIST - 2),
            pos: p,
            scale,
            lim,
            eta: [1.0, 0.0, 0.0],
            w: [0.0; 3],
            mu: 0.0,
            ang,
            rate: [0.0; MAX_WHEELS],
            steered: [false; MAX_WHEELS],
            steered_for: [0; MAX_WHEELS],
            hm: [[0.0, 1.0, 0.0, 0.0]; HIST],
            ha: [ang; HIST],
            k: 0,
            limiting: Limiting::None,
            spd: (lim.drive_lag > 0.0).then_some([0.0; 3]),
            cap_prev: f64::INFINITY,
            speed_cap_prev: f64::INFINITY,
            follow: 0.0,
        };
        if let Some(d) = dir {
            let e = unit3([d[0], d[1], d[2] * scale]);
            if dot3(e, e) > 0.5 {
                r.eta = e;
                for i in 0..n {
                    if r.norm_at(e, i) > 1e-6 {
                        r.steered[i] =
                            wrap_half(r.angle(e, i) - r.ang[i]).abs() <= lim.align_tolerance;
                        if r.steered[i] {
                            r.ang[i] += wrap_half(r.angle(e, i) - r.ang[i]);
                            r.steered_for[i] = HIST;
                        }
                    }
                }
                r.ha = [r.ang; HIST];
                r.hm = [[0.0, e[0], e[1], e[2]]; HIST];
            }
        }
        r
    }

    /// G_i e for a direction (or tangent) e in the scaled metric.
    fn contact(&self, e: [f64; 3], i: usize) -> [f64; 2] {
        let om = e[2] / self.scale;
        [e[0] - om * self.pos[i][1], e[1] + om * self.pos[i][0]]
    }

    fn norm_at(&self, e: [f64; 3], i: usize) -> f64 {
        norm2(self.contact(e, i))
    }

    fn angle(&self, e: [f64; 3], i: usize) -> f64 {
        let a = self.contact(e, i);
        a[1].atan2(a[0])
    }

    /// φ̇_i for a turn at rate v from e.
    fn rate_of(&self, e: [f64; 3], v: [f64; 3], i: usize) -> f64 {
        let a = self.contact(e, i);
        let b = self.contact(v, i);
        (a[0] * b[1] - a[1] * b[0]) / (a[0] * a[0] + a[1] * a[1]).max(1e-12)
    }

    /// Whether wheel i is steered by η̂ = e at speed mu (module docs, "Where the sphere is
    /// singular").
    fn held_by(&self, e: [f64; 3], mu: f64, i: usize) -> bool {
        let a = self.norm_at(e, i);
        a >= FREE_NORM || mu.abs() * a >= self.lim.slip_speed
    }

    /// e advanced by the turn v over h, and v carried along (its length kept).
    fn advance(e: [f64; 3], v: [f64; 3], h: f64) -> ([f64; 3], [f64; 3]) {
        let e1 = unit3([e[0] + v[0] * h, e[1] + v[1] * h, e[2] + v[2] * h]);
        let r = dot3(v, e1);
        let t = [v[0] - r * e1[0], v[1] - r * e1[1], v[2] - r * e1[2]];
        let (nt, nv) = (dot3(t, t).sqrt(), dot3(v, v).sqrt());
        (
            e1,
            if nt > 0.0 {
                [t[0] * nv / nt, t[1] * nv / nt, t[2] * nv / nt]
            } else {
                t
            },
        )
    }

    /// The factor the braking law scales the turn v at e by over h.
    fn brake_factor(&self, e: [f64; 3], v: [f64; 3], mu: f64, h: f64) -> f64 {
        let mut fastest = 0.0f64;
        for i in 0..self.n {
            if self.held_by(e, mu, i) {
                fastest = fastest.max(self.rate_of(e, v, i).abs());
            }
        }
        if fastest > 0.0 {
            (1.0 - BRAKE_SHARE * self.lim.steer_accel * h / fastest).max(0.0)
        } else {
            0.0
        }
    }

    /// The worst excess over the steering shares (≤ 0: within) of one cycle turning at v
    /// from the present state and braking to rest after it.
    fn check(&self, v: [f64; 3]) -> f64 {
        let (dt, mu) = (self.dt, self.mu);
        let mut worst = f64::NEG_INFINITY;
        let mut prev = [None; MAX_WHEELS];
        for i in 0..self.n {
            if self.steered[i] {
                prev[i] = Some(self.rate[i]);
            }
        }
        let (mut e, mut vv) = (self.eta, v);
        // Each wheel's angle at e, carried from one step to the next (one atan2 a step).
        let mut ang = [0.0; MAX_WHEELS];
        for (i, a) in ang.iter_mut().enumerate().take(self.n) {
            *a = self.angle(e, i);
        }
        for _ in 0..CHECK_STEPS {
            let (e1, v1) = Self::advance(e, vv, dt);
            for (i, pr) in prev.iter_mut().enumerate().take(self.n) {
                let a1 = self.angle(e1, i);
                let a0 = std::mem::replace(&mut ang[i], a1);
                // A wheel steered now counts as steered all along: the look-ahead holds μ,
                // and a wheel it would release at this μ stays steered if μ grows.
                if self.steered[i] || (self.held_by(e, mu, i) && self.held_by(e1, mu, i)) {
                    let r = wrap_half(a1 - a0) / dt;
                    worst = worst.max(r.abs() - self.lim.steer_rate);
                    if let Some(r0) = *pr {
                        worst = worst.max(((r - r0) / dt).abs() - self.lim.steer_accel);
                    }
                    *pr = Some(r);
                } else {
                    *pr = None;
                }
            }
            e = e1;
            if dot3(v1, v1) <= 1e-18 {
                break;
            }
            let f = self.brake_factor(e, v1, mu, dt);
            vv = [v1[0] * f, v1[1] * f, v1[2] * f];
        }
        worst
    }

    /// How noisy the goal is: the command's noise as a share of the noise the shaper smooths
    /// fully, from 0 (a clean stream: the turn brakes onto the goal's direction as late as it
    /// can) to [`FOLLOW_FULL_SHARE`] and above (the last [`FOLLOW_TIME`] of the turn is a
    /// first-order approach); module docs, "Following a noisy goal".
    pub fn follow_noise(&mut self, share: f64) {
        self.follow = FOLLOW_TIME * (share / FOLLOW_FULL_SHARE).clamp(0.0, 1.0);
    }

    /// One cycle towards the goal twist `goal` (base frame, within the wheel-speed share
    /// already); `halt` brakes at the stop deceleration. Returns the averaged sample.
    pub fn step(&mut self, goal: [f64; 3], halt: bool) -> RollSample {
        let dt = self.dt;
        let lim = self.lim;
        let gs = [goal[0], goal[1], goal[2] * self.scale];
        let gn = dot3(gs, gs).sqrt();
        let (eta_t, mu_t) = if gn < 1e-9 {
            (self.eta, 0.0)
        } else {
            let e = [gs[0] / gn, gs[1] / gn, gs[2] / gn];
            if dot3(e, self.eta) >= 0.0 {
                (e, gn)
            } else {
                ([-e[0], -e[1], -e[2]], -gn)
            }
        };
        let eta = self.eta;
        let cth = dot3(eta, eta_t).clamp(-1.0, 1.0);
        let theta = cth.acos();
        let tang = unit3([
            eta_t[0] - cth * eta[0],
            eta_t[1] - cth * eta[1],
            eta_t[2] - cth * eta[2],
        ]);
        // The turn rate wanted along the geodesic.
        let (mut rho_rate, mut rho_acc) = (f64::INFINITY, f64::INFINITY);
        let lateral = lim.lateral_accel.min(lim.wheel_accel);
        for i in 0..self.n {
            if !self.steered[i] {
                continue;
            }
            let k = self.rate_of(eta, tang, i).abs();
            if k > 0.0 {
                rho_rate = rho_rate.min(lim.steer_rate / k);
                rho_acc = rho_acc.min(lim.steer_accel / k);
            }
            let bl = norm2(self.contact(tang, i)) * self.mu.abs();
            if bl > 0.0 {
                rho_rate = rho_rate.min(lateral / bl);
            }
        }
        let bo = tang[0].hypot(tang[1]) * self.mu.abs();
        if bo > 0.0 {
            rho_rate = rho_rate.min(lateral / bo);
        }
        let rho_des = if theta <= 1e-12 {
            0.0
        } else if rho_acc.is_finite() {
            // Discrete braking onto the goal's direction: ρ dt + ρ²/(2a) ≤ θ.
            let a = rho_acc * BRAKE_SHARE;
            rho_rate.min(a * (-dt + (dt * dt + 2.0 * theta / a).sqrt()))
        } else {
            rho_rate.min(theta / dt)
        };
        // A noisy goal's direction is approached at most as θ / follow over the turn's last
        // `follow` seconds (module docs, "Following a noisy goal").
        let rho_des = if self.follow > 0.0 {
            rho_des.min(theta / self.follow)
        } else {
            rho_des
        };
        let w = self.w;
        let dw = [
            tang[0] * rho_des - w[0],
            tang[1] * rho_des - w[1],
            tang[2] * rho_des - w[2],
        ];
        let at = |f: f64| [w[0] + f * dw[0], w[1] + f * dw[1], w[2] + f * dw[2]];
        let mut turn_limited = false;
        let next = if self.check(at(1.0)) <= 0.0 {
            at(1.0)
        } else {
            turn_limited = true;
            if self.check(w) <= 0.0 {
                let (mut lo, mut hi) = (0.0, 1.0);
                for _ in 0..BISECTIONS {
                    let m = 0.5 * (lo + hi);
                    if self.check(at(m)) <= 0.0 {
                        lo = m;
                    } else {
                        hi = m;
                    }
                }
                at(lo)
            } else {
                let f = self.brake_factor(eta, w, self.mu, dt);
                [w[0] * f, w[1] * f, w[2] * f]
            }
        };
        let (eta1, w1) = Self::advance(eta, next, dt);
        self.eta = eta1;
        self.w = w1;
        // The speed: what the turn's lateral part leaves of the wheel acceleration; no
        // released wheel that is not yet aligned rolls faster than TURN_SPEED.
        let acc = if halt {
            STOP_SHARE * lim.stop_accel
        } else {
            lim.speed_accel
        };
        let (mut lat, mut amax) = (0.0f64, 0.0f64);
        // The reference trails the raw speed by T/2 + τ (the window mean, then the drives'
        // lag: module docs, "The speed and the drives' lag"), and what caps the speed for a
        // wheel not yet aligned is for the reference: it is taken that far ahead.
        let lead = 0.5 * self.window as f64 * dt + lim.drive_lag;
        let mut cap = f64::INFINITY;
        let mut aligning = false;
        for i in 0..self.n {
            let a = self.norm_at(eta1, i);
            lat = lat.max(self.mu.abs() * norm2(self.contact(w1, i)));
            amax = amax.max(a);
            // (A wheel steered for less than the window is not yet aligned in the window
            // mean either: it stays slow until it is.)
            let unaligned = !self.steered[i];
            let settling = self.steered_for[i] <= self.window + 1
                && self.mu.abs() * a <= TURN_SPEED * (1.0 + 1e-9);
            if unaligned || settling {
                // A wheel not yet along its direction rolls sideways by the sine of what is
                // left: at most `slip_speed` of it.
                let side = if unaligned {
                    // What is left, or what it grows to over the lead at today's rates if
                    // it grows.
                    let err = wrap_half(self.angle(eta1, i) - self.ang[i]);
                    let grow = (self.rate_of(eta1, w1, i) - self.rate[i]) * lead;
                    err.abs().max((err + grow).abs()).min(0.5 * PI).sin()
                } else {
                    0.0
                };
                let allowed = if side * TURN_SPEED > lim.slip_speed {
                    lim.slip_speed / side
                } else {
                    TURN_SPEED
                };
                let c = 0.999 * allowed / a.max(1e-12);
                if c < cap {
                    cap = c;
                    aligning = true;
                }
            }
        }
        // A falling cap is met where it will be when the reference gets there.
        let falling = if cap.is_finite() && self.cap_prev.is_finite() {
            (cap - self.cap_prev).min(0.0) / dt
        } else {
            0.0
        };
        self.cap_prev = cap;
        let mut cap = (cap + falling * lead).max(0.0);
        let amax = amax.max(1e-9);
        // The turn's lateral acceleration μ |G_i w| within its share: a fast turn holds the
        // speed down (the drives follow a turn with a lag, and a wheel that far behind rolls
        // sideways by that lag times μ |G_i w|).
        let mut lat_rate = w1[0].hypot(w1[1]);
        for i in 0..self.n {
            if self.steered[i] {
                lat_rate = lat_rate.max(norm2(self.contact(w1, i)));
            }
        }
        if lat_rate > 0.0 && lateral / lat_rate < cap {
            cap = lateral / lat_rate;
            aligning = false;
        }
        // The wheel-speed cap falls as the turn moves the fastest wheel's share up: it too is
        // met where it will be when the reference gets there.
        let speed_cap = lim.wheel_speed / amax;
        let falling = if self.speed_cap_prev.is_finite() {
            (speed_cap - self.speed_cap_prev).min(0.0) / dt
        } else {
            0.0
        };
        self.speed_cap_prev = speed_cap;
        let speed_cap = (speed_cap + falling * lead).max(0.0);
        let (cap, by_speed) = if speed_cap < cap {
            (speed_cap, true)
        } else {
            (cap, false)
        };
        let left = (acc * acc - lat * lat).max(0.0).sqrt() / amax;
        let m1 = self.mu + (mu_t - self.mu).clamp(-left * dt, left * dt);
        self.mu = if m1.abs() > cap {
            let stop = STOP_SHARE * lim.stop_accel;
            let full = (stop * stop - lat * lat).max(0.0).sqrt() / amax;
            m1.signum() * cap.max(self.mu.abs() - full * dt)
        } else {
            m1
        };
        // The wheels: steered ones along G_i η̂, released ones by their generator.
        for i in 0..self.n {
            let r_eta = self.rate_of(eta, next, i);
            let target = self.ang[i] + wrap_half(self.angle(eta1, i) - self.ang[i]);
            let steer_now = self.held_by(eta1, self.mu, i)
                && (self.steered[i]
                    || ((target - self.ang[i] - r_eta * dt).abs() <= SNAP_ANGLE
                        && (r_eta - self.rate[i]).abs() <= lim.steer_accel * dt));
            let r = if steer_now {
                if !self.steered[i] {
                    // What is left within the tolerance is taken up at once.
                    self.ang[i] = target - r_eta * dt;
                }
                self.steered[i] = true;
                (target - self.ang[i]) / dt
            } else {
                self.steered[i] = false;
                // What is left if it turns at η̂'s rate this cycle, braked onto.
                let d = target - self.ang[i] - r_eta * dt;
                let a = lim.steer_accel;
                let vb = a * (-dt + (dt * dt + 2.0 * d.abs() / a).sqrt());
                let want = (r_eta + d.signum() * vb.min(lim.steer_rate))
                    .clamp(-lim.steer_rate, lim.steer_rate);
                self.rate[i] + (want - self.rate[i]).clamp(-a * dt, a * dt)
            };
            self.ang[i] += r * dt;
            self.rate[i] = r;
            self.steered_for[i] = if self.steered[i] {
                (self.steered_for[i] + 1).min(HIST)
            } else {
                0
            };
        }
        self.limiting = if halt {
            Limiting::Stop
        } else if aligning && !by_speed && self.mu.abs() >= cap * 0.999 {
            Limiting::Aligning
        } else if by_speed && self.mu.abs() >= cap * 0.999 && mu_t.abs() > cap {
            Limiting::WheelSpeed
        } else if turn_limited || (theta > 1e-3 && rho_des < theta / dt) {
            Limiting::SteerRate
        } else if (mu_t - self.mu).abs() > 1e-9 {
            Limiting::WheelAccel
        } else {
            Limiting::None
        };
        // Raw state into the history, the window mean out.
        self.k = (self.k + 1) % HIST;
        self.hm[self.k] = [self.mu, self.eta[0], self.eta[1], self.eta[2]];
        self.ha[self.k] = self.ang;
        self.lag_speed();
        self.sample()
    }

    /// The reference speed: the window mean b of the raw μ (the speed part of the command)
    /// through the drives' first-order lag τ, r' = (b − r)/τ, solved exactly over the cycle
    /// for b linear in between its samples (module docs, "The speed and the drives' lag").
    fn lag_speed(&mut self) {
        let (dt, wn) = (self.dt, self.window);
        // The window mean now (b₁) and one cycle ago (b₀), from the history (HIST ≥ wn + 2).
        let mean = |from: usize| {
            (from..from + wn)
                .map(|j| self.hm[(self.k + HIST - j) % HIST][0])
                .sum::<f64>()
                / wn as f64
        };
        let (b1, b0) = (mean(0), mean(1));
        let tau = self.lim.drive_lag;
        let Some([r0, _, _]) = self.spd else {
            return;
        };
        let a = (b1 - b0) / dt;
        let r = b1 - a * tau + (r0 - b0 + a * tau) * (-dt / tau).exp();
        let dr = (b1 - r) / tau;
        self.spd = Some([r, dr, (a - dr) / tau]);
        // What the exponential leaves of a speed come to rest is rest (a µm/s step).
        if b1 == 0.0 && b0 == 0.0 && r.abs() < REST_SPEED && dr.abs() < REST_SPEED / tau {
            self.spd = Some([0.0; 3]);
        }
    }

    /// The averaged sample of the present window. μ and η̂ are averaged apart, and the twist
    /// is their product q̇ = μ̄ η̄ (module docs, "Jerk"): its direction is η̄'s whatever μ̄
    /// does, so a reversal of μ̄ turns no wheel's direction of travel. The window mean's
    /// derivatives are exact: the rate is the difference of the window's ends over its
    /// length, the acceleration that of the raw rates at its ends.
    pub fn sample(&self) -> RollSample {
        let wn = self.window;
        let at = |j: usize| (self.k + HIST - j) % HIST;
        let (dt, wf) = (self.dt, self.window as f64);
        // Mean, rate and acceleration of each of μ, η̂.
        let mut m = [[0.0f64; 4]; 3];
        for d in 0..4 {
            let h = |j: usize| self.hm[at(j)][d];
            m[0][d] = (0..wn).map(h).sum::<f64>() / wf;
            m[1][d] = (h(0) - h(wn)) / (wf * dt);
            m[2][d] = ((h(0) - h(1)) - (h(wn) - h(wn + 1))) / (wf * dt * dt);
        }
        let [mu, dmu, ddmu] = self.spd.unwrap_or([m[0][0], m[1][0], m[2][0]]);
        let e = [m[0][1], m[0][2], m[0][3]];
        let de = [m[1][1], m[1][2], m[1][3]];
        let dde = [m[2][1], m[2][2], m[2][3]];
        let mut s = RollSample::default();
        for d in 0..3 {
            let sc = if d == 2 { 1.0 / self.scale } else { 1.0 };
            s.q[d] = sc * mu * e[d];
            s.qd[d] = sc * (dmu * e[d] + mu * de[d]);
            s.qdd[d] = sc * (ddmu * e[d] + 2.0 * dmu * de[d] + mu * dde[d]);
        }
        for i in 0..self.n {
            // Each wheel's raw angles averaged the same way: within the raw rates' and
            // accelerations' bounds, and along G_i η̄ to second order in the window's turn.
            let h = |j: usize| self.ha[at(j)][i];
            s.steer[i] = (0..wn).map(h).sum::<f64>() / wf;
            s.steer_rate[i] = (h(0) - h(wn)) / (wf * dt);
            s.steer_accel[i] = ((h(0) - h(1)) - (h(wn) - h(wn + 1))) / (wf * dt * dt);
        }
        s
    }

    /// Why the turn is slower than the goal, this cycle.
    pub fn limiting(&self) -> Limiting {
        self.limiting
    }

    /// True when the raw state and the whole window are at rest (no speed, no turn, no
    /// steering).
    pub fn at_rest(&self) -> bool {
        self.mu == 0.0
            && self.spd.is_none_or(|s| s == [0.0; 3])
            && dot3(self.w, self.w) < 1e-24
            && (0..self.n).all(|i| self.rate[i].abs() < 1e-12)
            && (0..self.window + 2).all(|j| {
                let h = self.hm[(self.k + HIST - j) % HIST];
                h[0] == 0.0
                    && (1..4).all(|d| (h[d] - self.eta[d - 1]).abs() < 1e-12)
                    && (0..self.n).all(|i| {
                        (self.ha[(self.k + HIST - j) % HIST][i] - self.ang[i]).abs() < 1e-12
                    })
            })
    }

    /// The raw steering angles (rad), first n.
    pub fn angles(&self) -> &[f64] {
        &self.ang[..self.n]
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::model::platform::Platform;

    const DT: f64 = 0.004;
    const WINDOW: usize = 10;

    /// Justin's contact points (legs nominal) and the shaper's default shares.
    fn setup() -> ([[f64; 2]; 4], RollLimits) {
        let p = Platform::justin();
        let mut pos = [[0.0; 2]; 4];
        for (i, c) in pos.iter_mut().enumerate() {
            let w = &p.wheels[i];
            *c = [
                w.lambda_nominal * w.alpha.cos(),
                w.lambda_nominal * w.alpha.sin(),
            ];
        }
        let (fs, fa) = (0.9, 0.6);
        let lim = RollLimits {
            wheel_speed: fs * p.limits.wheel_speed * p.wheel_radius,
            wheel_accel: fa * p.limits.wheel_accel * p.wheel_radius,
            speed_accel: 0.75 * p.limits.wheel_accel * p.wheel_radius,
            drive_lag: p.drives.wheel_time_constant,
            stop_accel: p.limits.wheel_accel * p.wheel_radius,
            steer_rate: fs * p.limits.steer_rate,
            steer_accel: fa * p.limits.steer_accel,
            lateral_accel: 2.0,
            align_tolerance: 1.5f64.to_radians(),
            slip_speed: 0.003,
        };
        (pos, lim)
    }

    fn contact(pos: &[[f64; 2]; 4], i: usize, q: [f64; 3]) -> [f64; 2] {
        [q[0] - q[2] * pos[i][1], q[1] + q[2] * pos[i][0]]
    }

    /// Worst use of each limit over a run, as a share of it.
    #[derive(Default, Debug)]
    struct Worst {
        steer_rate: f64,
        steer_accel: f64,
        speed: f64,
        accel: f64,
        /// Largest angle (rad, mod π) between a wheel faster than HOLD_SPEED and its
        /// direction of travel.
        off: f64,
        /// Largest steering angle change beyond rate × dt between two samples (rad).
        jump: f64,
    }

    fn observe(
        pos: &[[f64; 2]; 4],
        lim: &RollLimits,
        s: &RollSample,
        prev: Option<&RollSample>,
        w: &mut Worst,
    ) {
        for i in 0..4 {
            w.steer_rate = w.steer_rate.max(s.steer_rate[i].abs() / lim.steer_rate);
            w.steer_accel = w.steer_accel.max(s.steer_accel[i].abs() / lim.steer_accel);
            let u = contact(pos, i, s.q);
            let du = contact(pos, i, s.qd);
            w.speed = w.speed.max(norm2(u) / lim.wheel_speed);
            w.accel = w.accel.max(norm2(du) / lim.stop_accel);
            if norm2(u) > HOLD_SPEED {
                w.off = w.off.max(wrap_half(u[1].atan2(u[0]) - s.steer[i]).abs());
            }
            if let Some(p) = prev {
                let d = s.steer[i] - p.steer[i] - 0.5 * (s.steer_rate[i] + p.steer_rate[i]) * DT;
                w.jump = w.jump.max(d.abs());
            }
        }
    }

    fn run(r: &mut Roll, goal: [f64; 3], cycles: usize, halt: bool, out: &mut Vec<RollSample>) {
        for _ in 0..cycles {
            let s = r.step(goal, halt);
            out.push(s);
        }
    }

    fn worst(pos: &[[f64; 2]; 4], lim: &RollLimits, samples: &[RollSample]) -> Worst {
        let mut w = Worst::default();
        for (k, s) in samples.iter().enumerate() {
            observe(pos, lim, s, k.checked_sub(1).map(|j| &samples[j]), &mut w);
        }
        w
    }

    fn assert_within(w: &Worst) {
        assert!(w.steer_rate <= 1.0 + 1e-9, "{w:?}");
        assert!(w.steer_accel <= 1.0 + 1e-6, "{w:?}");
        assert!(w.speed <= 1.0 + 1e-9, "{w:?}");
        assert!(w.accel <= 1.0 + 1e-9, "{w:?}");
        assert!(w.jump < 3e-3, "{w:?}");
    }

    #[test]
    fn a_stick_that_moves_every_message_keeps_every_wheel_within_its_shares() {
        let (pos, lim) = setup();
        let mut rng = rollbase_driver::rng::Rng::new(23);
        let mut r = Roll::new(&pos, lim, DT, WINDOW, &[0.0; 4], None);
        let mut out = Vec::new();
        let mut to = [0.0; 3];
        // 20 s: a new target every 0.5 s (up to 0.8 m/s, 1.5 rad/s, capped to the wheel
        // speed share with the direction kept), the goal moving linearly towards it every
        // 20 ms message.
        for seg in 0..40 {
            let from = to;
            to = [
                0.8 * (2.0 * rng.next_f64() - 1.0),
                0.8 * (2.0 * rng.next_f64() - 1.0),
                1.5 * (2.0 * rng.next_f64() - 1.0),
            ];
            if seg % 7 == 6 {
                to = [0.0; 3];
            }
            let fastest = (0..4)
                .map(|i| norm2(contact(&pos, i, to)))
                .fold(0.0, f64::max);
            if fastest > lim.wheel_speed {
                to = to.map(|x| x * lim.wheel_speed / fastest);
            }
            for m in 0..25 {
                let f = (m + 1) as f64 / 25.0;
                let g = [0, 1, 2].map(|d| from[d] + f * (to[d] - from[d]));
                run(&mut r, g, 5, false, &mut out);
            }
        }
        let w = worst(&pos, &lim, &out);
        assert_within(&w);
        // Rolling wheels point along their direction of travel (to what the window mean
        // leaves between the mean angle and the mean direction: 0.11° here).
        assert!(w.off <= 0.2f64.to_radians(), "{w:?}");
        // It moved.
        let path: f64 = out.iter().map(|s| s.q[0].hypot(s.q[1]) * DT).sum();
        assert!(path > 5.0, "travelled {path} m");
    }

    #[test]
    fn a_reversal_turns_no_wheel() {
        let (pos, lim) = setup();
        let mut r = Roll::new(&pos, lim, DT, WINDOW, &[0.0; 4], Some([1.0, 0.0, 0.0]));
        let mut out = Vec::new();
        run(&mut r, [0.5, 0.0, 0.0], 250, false, &mut out);
        run(&mut r, [-0.5, 0.0, 0.0], 250, false, &mut out);
        for s in &out {
            for i in 0..4 {
                assert!(s.steer_rate[i].abs() < 1e-9 && s.steer[i].abs() < 1e-9);
            }
        }
        let last = out.last().unwrap().q;
        assert!(
            (last[0] + 0.5).abs() < 1e-9 && last[1].abs() < 1e-9,
            "{last:?}"
        );
        assert_within(&worst(&pos, &lim, &out));
    }

    #[test]
    fn a_quarter_turn_at_speed_keeps_rolling() {
        let (pos, lim) = setup();
        let mut r = Roll::new(&pos, lim, DT, WINDOW, &[0.0; 4], Some([1.0, 0.0, 0.0]));
        let mut out = Vec::new();
        run(&mut r, [0.5, 0.0, 0.0], 250, false, &mut out);
        let start = out.len();
        run(&mut r, [0.0, 0.5, 0.0], 500, false, &mut out);
        let turn = &out[start..];
        let slowest = turn
            .iter()
            .map(|s| s.q[0].hypot(s.q[1]))
            .fold(f64::INFINITY, f64::min);
        // A straight line between the two twists would pass 0.35 m/s; the turn keeps the
        // speed within the lateral acceleration (2 m/s² at 0.5 m/s: 4 rad/s).
        assert!(slowest > 0.45, "slowest {slowest} m/s");
        let arrived = turn
            .iter()
            .position(|s| s.q[0].abs() < 0.5 * 1e-3 && (s.q[1] - 0.5).abs() < 1e-3)
            .expect("the turn arrives");
        assert!(
            (arrived as f64) * DT < 0.8,
            "arrived after {} s",
            arrived as f64 * DT
        );
        assert_within(&worst(&pos, &lim, &out));
    }

    #[test]
    fn from_rest_with_the_wheels_apart_no_wheel_rolls_before_it_is_aligned() {
        let (pos, lim) = setup();
        let steer = [0.0, 1.0, 2.0, -1.0];
        let mut r = Roll::new(&pos, lim, DT, WINDOW, &steer, None);
        let mut out = Vec::new();
        let goal = [0.3, 0.1, 0.2];
        run(&mut r, goal, 500, false, &mut out);
        for s in &out {
            for i in 0..4 {
                let u = contact(&pos, i, s.q);
                let off = wrap_half(u[1].atan2(u[0]) - s.steer[i]).abs();
                // A wheel rolls faster than TURN_SPEED only once it is aligned.
                assert!(
                    norm2(u) <= TURN_SPEED + 1e-9 || off <= lim.align_tolerance + 1e-3,
                    "wheel {i} rolls at {} m/s {off} rad off its direction",
                    norm2(u)
                );
            }
        }
        let last = out.last().unwrap().q;
        for d in 0..3 {
            assert!((last[d] - goal[d]).abs() < 1e-6, "{last:?}");
        }
        assert_within(&worst(&pos, &lim, &out));
    }

    #[test]
    fn a_halt_comes_to_rest_within_the_stop_deceleration() {
        let (pos, lim) = setup();
        let mut r = Roll::new(&pos, lim, DT, WINDOW, &[0.0; 4], Some([1.0, 0.0, 0.0]));
        let mut out = Vec::new();
        run(&mut r, [0.6, 0.0, 0.0], 250, false, &mut out);
        let start = out.len();
        let mut k = 0;
        while !r.at_rest() {
            out.push(r.step([0.0; 3], true));
            k += 1;
            assert!(k < 1000, "no rest after 4 s");
        }
        // 0.6 m/s at 95 % of 3.4 m/s², plus the window the mean lags by, plus the drives'
        // lag settling from its offset (the deceleration times τ) to REST_SPEED.
        let a = STOP_SHARE * lim.stop_accel;
        let tau = lim.drive_lag;
        let bound = 0.6 / a + (WINDOW + 2) as f64 * DT + tau * (a * tau / REST_SPEED).ln() + DT;
        assert!(
            k as f64 * DT <= bound,
            "rest after {} s, bound {bound} s",
            k as f64 * DT
        );
        assert_eq!(r.limiting(), Limiting::Stop);
        assert_within(&worst(&pos, &lim, &out[start..]));
    }

    /// The speed part of the command the drives get, u + τ u̇ (the runtime's lag
    /// compensation of the reference speed u), changes within `speed_accel` while the speed
    /// runs up and within the stop deceleration while it brakes: the reference is that command
    /// through the lag. With the window mean alone as the reference (no lag), the same start
    /// asks the drives for 1.5 times the share.
    #[test]
    fn the_speed_command_stays_within_its_share_through_the_drives_lag() {
        let (pos, lim) = setup();
        let tau = lim.drive_lag;
        let worst_command_accel = |lim: RollLimits| {
            let mut r = Roll::new(&pos, lim, DT, WINDOW, &[0.0; 4], Some([1.0, 0.0, 0.0]));
            let (mut up, mut down) = (0.0f64, 0.0f64);
            let mut prev: Option<f64> = None;
            for k in 0..600 {
                let halt = k >= 300;
                let s = r.step([0.8, 0.0, 0.0], halt);
                // Straight ahead every wheel rolls at v_x: the command is v_x + τ v̇_x.
                let c = s.q[0] + tau * s.qd[0];
                if let Some(p) = prev {
                    let a = ((c - p) / DT).abs();
                    if halt {
                        down = down.max(a);
                    } else {
                        up = up.max(a);
                    }
                }
                prev = Some(c);
            }
            (up, down)
        };
        let (up, down) = worst_command_accel(lim);
        assert!(
            up <= lim.speed_accel * (1.0 + 1e-9),
            "{up} m/s² running up, share {}",
            lim.speed_accel
        );
        let stop = STOP_SHARE * lim.stop_accel;
        assert!(down <= stop * (1.0 + 1e-9), "{down} m/s² braking, {stop}");
        let (up, _) = worst_command_accel(RollLimits {
            drive_lag: 0.0,
            ..lim
        });
        assert!(up > 1.4 * lim.speed_accel, "{up} m/s² without the lag");
    }
}
