//! Online shaping of live motion commands: the reference the tracking controller follows is
//! made from whatever a joystick, a navigation stack or a file commands, and keeps every
//! actuator within its limits on every cycle.
//!
//! # State and output
//!
//! The shaper integrates its own reference: pose ξ = (x, y, θ) and legs λ, driven by the
//! generalised velocity q̇ = (v_x, v_y, ω, λ̇_1 … λ̇_n) in the base frame, with q̈ and q⃛. Each
//! cycle it emits z = (ξ, λ) with ż, z̈, z⃛ in the world frame (v_b, a_b, j_b the body-frame
//! translational parts of q̇, q̈, q⃛; J the rotation by +90°):
//!
//! ```text
//! ẋẏ = R(θ) v_b,   ẍÿ = R(θ)(a_b + ω J v_b),   x⃛y⃛ = R(θ)(j_b + 2 ω J a_b + ω̇ J v_b − ω² v_b)
//! ```
//!
//! and a steering reference per wheel (angle, rate: [`SteerReference`]) that the controllers
//! follow for wheels too slow to steer by their direction of travel.
//!
//! Wheel i's contact velocity is linear in q̇: u_i = G_i q̇ with
//! G_i q̇ = (v_x − ω λ_i sin α_i + λ̇_i cos α_i, v_y + ω λ_i cos α_i + λ̇_i sin α_i)
//! (seed 000 eq. 18 in the base frame).
//!
//! # The goal: keep the direction, reduce the speed (seed 004)
//!
//! The command q̇_c = (v_x, v_y, ω, legs toward their targets) becomes the goal
//! q̇_g = κ q̇_c with one factor κ ∈ (0, 1] for the whole command, the largest for which every
//! wheel speed |G_i q̇_g|/r and every leg speed is within `speed_fraction` of its limit. So a
//! command the platform cannot execute keeps its direction in actuator space and only its
//! speed is reduced (seed 004, Sect. 4.1: "The direction of the operational movement is kept
//! identical, only the speed of execution is reduced"); no wheel is ever clamped alone.
//!
//! # Transitions: straight lines in q̇, timed within every limit
//!
//! From the current q̇_0 to a new goal q̇_1 the shaper moves along the segment
//! q̇(β) = q̇_0 + β Δ, Δ = q̇_1 − q̇_0, with β going from rest at 0 to rest at 1 ([`Ramp`]).
//! Then q̈ = β̇ Δ and q⃛ = β̈ Δ: q̈ is continuous (β̇ is) and zero at both ends, q⃛ is bounded
//! (β̈ is): the reference is C² with bounded jerk, which the DFL of seed 000 needs (its
//! feed-forward is z̈*, seed 000 eq. 25). What is limited where:
//!
//! * **Wheel and leg speeds** are convex functions of q̇ (norms of linear maps), so every point
//!   of a segment between two admissible velocities is admissible: no constraint on β.
//! * **Wheel acceleration**: |u̇_i| = |G_i Δ| β̇ ≤ `accel_fraction`·r·ω̇_max bounds β̇ (|u̇| ≥
//!   d|u|/dt, so this is conservative; for a stop, Δ = −q̇_0, it is exact).
//! * **Steering rate and acceleration**: with u = G_i q̇(β), g = G_i Δ, φ = atan2(u),
//!   φ' = dφ/dβ = (u × g)/|u|², φ'' = −2 (u × g)(u · g)/|u|⁴ (since d(u × g)/dβ = g × g = 0);
//!   φ̇ = φ' β̇ and φ̈ = φ'' β̇² + φ' β̈. The plan keeps |φ'| β̇ ≤ φ̇_max·f, |φ''| β̇² ≤ ½ φ̈_max·f
//!   and |φ'| |β̈| ≤ ½ φ̈_max·f at every grid point (f = `speed_fraction` / `accel_fraction`).
//!   Where a segment passes close to a wheel's zero velocity (the ICR sweeping across the
//!   wheel at distance δ: |u| passes a minimum δ), φ' grows like 1/δ; the grid is refined
//!   around the closest approach β* = −(u_0·g)/|g|², so the transition slows exactly there and
//!   the wheel turns through its half-turn within its steering limits, whatever δ (the time
//!   it takes is about π/φ̇_max). A segment through the wheel's zero (δ = 0: stops, starts,
//!   reversals) does not turn the wheel at all: its velocity changes sign along a line, and
//!   the wheel's roll direction flips while its steering angle stays.
//! * **Direction of travel**: the base origin's velocity v = (v_x, v_y) is treated like a
//!   wheel with the rate limit `direction_rate` while faster than 4 cm/s, so the direction
//!   the base travels in turns slowly enough for the drives (first-order lag τ ≈ 20 ms) to
//!   follow it: the executed direction lags the reference by about τ·`direction_rate`.
//! * **Jerk**: |β̈| ≤ β̇_max / `jerk_time`: accelerations build up over at least that time
//!   (20 ms; a stop uses `stop_jerk_time`, one cycle, so that it ends within one cycle of
//!   what the deceleration limit allows).
//!
//! A new goal while a segment is under way brakes β to rest first ([`Ramp::brake`], within the
//! same caps), so q̈ stays continuous; the next segment starts from there.
//!
//! # Align-first and the platform-wide flip
//!
//! A wheel at rest (|u| ≈ 0) holds its steering angle. Before a segment on which such a wheel
//! starts rolling, it is turned in place to the direction it will roll in (q̇ held meanwhile):
//! from rest, every wheel steers first and rolls once aligned. Steering in place follows a
//! rest-to-rest [`Ramp`] within `steer_rate` and `steer_accel`, all aligning wheels finishing
//! together. When the whole platform is at rest the branch (roll forward at φ, or backward at
//! φ + π) is chosen for all wheels together: the one whose largest steering move is smaller,
//! switching from the branch used last only if it saves more than `flip_hysteresis`. No wheel
//! flips alone while moving (a module flipping while the others roll would have to stop and
//! reverse, turning the platform).
//!
//! A segment that would turn a rolling wheel by more than `far_angle` (a new direction far
//! from the current one) is not driven through: the platform stops along its current
//! direction (steering held), aligns, then rolls in the new direction. A reversal needs no
//! steering at all: its segment passes through rest on a line and every wheel flips its roll
//! direction at the same instant.
//!
//! # Legs
//!
//! Leg targets are positions. The legs move with a common speed toward their targets (all
//! arriving together) as part of q̇, so their motion is shaped and scaled with the twist; a
//! braking segment is started when the remaining distance of the farthest leg reaches the
//! distance that segment needs (computed from its plan), so a leg never overshoots its
//! target (nor its range); the last millimetres are crept at a lower speed until within
//! `leg_tolerance`.
//!
//! # Singularity avoidance (when the runtime runs with it)
//!
//! With [`Shaper::set_avoidance`] the command is first passed through seed 001's avoidance at
//! the velocity level ([`crate::avoidance::avoid_twist`]; derivation in [`crate::avoidance`],
//! "Live commands"): a command whose ICR lies in a wheel's field becomes the twist with the
//! same base speed whose ICR is on the field's edge. That twist is then the command for
//! everything above (scale, transitions, align-first, flip), so what the avoidance changes is
//! shaped within the limits like anything else. The fields are taken at the leg targets.
//!
//! # Halt
//!
//! [`Shaper::halt`] (command timeout, stop request) sets the goal to rest: the current segment
//! brakes, then a segment to q̇ = 0 runs. Along it every wheel keeps its direction (u_i scales
//! by 1 − β), so the steering is held, and the fastest wheel decelerates at exactly the wheel
//! acceleration limit (`stop_accel_fraction` = 1 by default): the platform is at rest after
//! max_i |ω_i| / ω̇_max plus the jerk ramp.
//!
//! Pure and allocation-free: fixed arrays, time advanced by the caller's cycle.

// Index loops over parallel per-wheel arrays read better than zipped iterators here.
#![allow(clippy::needless_range_loop)]

use crate::angle;
use crate::avoidance::{avoid_twist, AvoidanceConfig, TwistAvoidance};
use crate::limits::HOLD_SPEED;
use crate::platform::{Limits, Platform};
use crate::ports::{Limiting, ShapingState};
use crate::ramp::{Ramp, GRID};
use crate::types::{Pose, ReferenceSample, SteerReference, Twist, ZVec, MAX_WHEELS};
use std::f64::consts::{FRAC_PI_2, PI};

const NQ: usize = 3 + MAX_WHEELS;
type Q = [f64; NQ];

/// Contact speed (m/s) at and below which a wheel is at rest for the shaper (its direction is
/// not defined): it holds its steering angle.
pub const REST_EPS: f64 = 1e-7;
/// A segment passing a wheel's zero velocity closer than this (m/s) passes through it.
const CROSS_EPS: f64 = 1e-9;
/// Base speed (m/s) above which the direction-of-travel rate limit applies.
const DIRECTION_MIN_SPEED: f64 = 0.04;

/// Tunables of the shaper (defaults documented per field).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ShaperConfig {
    /// Fraction of the speed-type limits (wheel speed, steering rate, leg speed) the
    /// reference may use; the rest is the tracking controller's headroom. Default 0.9.
    pub speed_fraction: f64,
    /// Fraction of the acceleration limits (wheel, steering) transitions may use. Default
    /// 0.6: the drives' lag compensation adds τ × jerk to the commanded acceleration
    /// ([`crate::platform::Drives`]), and the controller's corrections need room too.
    pub accel_fraction: f64,
    /// Fraction of the wheel acceleration limit a stop (halt) uses. Default 1.0: a timeout or
    /// stop request brings the platform to rest as fast as its limit allows.
    pub stop_accel_fraction: f64,
    /// Largest steering change (rad) of a rolling wheel driven through; beyond it the
    /// platform stops, aligns and rolls again. Default 60°.
    pub far_angle: f64,
    /// Steering errors (rad) below this need no alignment before rolling. Default 0.5°.
    pub align_tolerance: f64,
    /// Platform-wide flip hysteresis (rad). Default 0.3 rad.
    pub flip_hysteresis: f64,
    /// Rate limit (rad/s) of the base's direction of travel. Default 1.0 rad/s.
    pub direction_rate: f64,
    /// Time (s) over which an acceleration may build up (bounds the jerk). Default 40 ms
    /// (≥ τ·f/(1 − f) for the default drive lag τ = 20 ms and accel fraction f = 0.6, so the
    /// lag compensation fits within the acceleration limit).
    pub jerk_time: f64,
    /// The same for a stop (halt), which favours stopping distance. Default 4 ms.
    pub stop_jerk_time: f64,
    /// Legs within this distance (m) of their targets have arrived. Default 0.1 mm.
    pub leg_tolerance: f64,
}

impl Default for ShaperConfig {
    fn default() -> Self {
        Self {
            speed_fraction: 0.9,
            accel_fraction: 0.6,
            stop_accel_fraction: 1.0,
            far_angle: 60f64.to_radians(),
            align_tolerance: 0.5f64.to_radians(),
            flip_hysteresis: 0.3,
            direction_rate: 1.0,
            jerk_time: 0.04,
            stop_jerk_time: 0.004,
            leg_tolerance: 1e-4,
        }
    }
}

#[derive(Clone, Copy, Debug)]
enum Phase {
    Cruise,
    Line {
        from: Q,
        delta: Q,
        target: Q,
        /// A stop on the way to an alignment: runs to rest whatever the goal does.
        interim: bool,
        ramp: Ramp,
        limit: Limiting,
    },
    Align {
        from: [f64; MAX_WHEELS],
        delta: [f64; MAX_WHEELS],
        ramp: Ramp,
    },
}

/// The live-command shaper (module docs).
#[derive(Clone, Debug)]
pub struct Shaper {
    cfg: ShaperConfig,
    n: usize,
    dt: f64,
    sa: [f64; MAX_WHEELS],
    ca: [f64; MAX_WHEELS],
    rw: f64,
    limits: Limits,
    lam_min: [f64; MAX_WHEELS],
    lam_max: [f64; MAX_WHEELS],
    t: f64,
    pose: Pose,
    legs: [f64; MAX_WHEELS],
    qd: Q,
    qdd: Q,
    qddd: Q,
    steer: [f64; MAX_WHEELS],
    steer_rate: [f64; MAX_WHEELS],
    steer_accel: [f64; MAX_WHEELS],
    sign: [f64; MAX_WHEELS],
    flipped: bool,
    phase: Phase,
    twist_cmd: Twist,
    halted: bool,
    /// Why it is halted (reported as the limiting cause while halted): the command timeout,
    /// a stop request, or nothing (never commanded yet, or reset).
    halt_reason: Limiting,
    leg_target: [f64; MAX_WHEELS],
    legs_move: LegMove,
    goal: Q,
    scale: f64,
    limiting: Limiting,
    twist_limit: Limiting,
    /// Singularity avoidance of the command (seed 001 at the velocity level), if on.
    avoid: Option<AvoidanceConfig>,
    /// What it did with the command this cycle.
    avoided: TwistAvoidance,
    /// Per wheel, the side its field's edge was taken on last (unit vector; zero: none).
    avoid_side: [[f64; 2]; MAX_WHEELS],
}

/// A leg move: from rest (in the legs) to rest, the legs' velocities c·d_i (d_i their share
/// of the remaining distance, so all arrive together), with the twist held meanwhile.
#[derive(Clone, Copy, Debug, PartialEq)]
enum LegMove {
    /// The legs are at rest (at their targets, or waiting to start).
    Idle,
    /// Accelerating the legs to their cruise velocities, toward `target`.
    Accel {
        vel: [f64; MAX_WHEELS],
        twist: [f64; 3],
        target: [f64; MAX_WHEELS],
    },
    /// Cruising; braking starts when the farthest leg's remaining distance to `target`
    /// reaches `brake`.
    Cruise {
        vel: [f64; MAX_WHEELS],
        twist: [f64; 3],
        target: [f64; MAX_WHEELS],
        brake: f64,
    },
    /// Braking the legs to rest.
    Decel { twist: [f64; 3] },
}

fn dot(a: [f64; 2], b: [f64; 2]) -> f64 {
    a[0] * b[0] + a[1] * b[1]
}
fn cross(a: [f64; 2], b: [f64; 2]) -> f64 {
    a[0] * b[1] - a[1] * b[0]
}
fn norm(a: [f64; 2]) -> f64 {
    a[0].hypot(a[1])
}

impl Shaper {
    /// A shaper for platform `p`, at rest at the origin with the legs at their nominal
    /// extension and the wheels at angle 0 (call [`Shaper::reset`] with the measured state).
    pub fn new(p: &Platform, cfg: ShaperConfig) -> Self {
        let n = p.n().min(MAX_WHEELS);
        let mut sa = [0.0; MAX_WHEELS];
        let mut ca = [0.0; MAX_WHEELS];
        let mut lam_min = [0.0; MAX_WHEELS];
        let mut lam_max = [0.0; MAX_WHEELS];
        let mut legs = [0.0; MAX_WHEELS];
        for i in 0..n {
            let w = &p.wheels[i];
            (sa[i], ca[i]) = w.alpha.sin_cos();
            lam_min[i] = w.lambda_min;
            lam_max[i] = w.lambda_max;
            legs[i] = w.lambda_nominal;
        }
        Self {
            cfg,
            n,
            dt: p.dt(),
            sa,
            ca,
            rw: p.wheel_radius,
            limits: p.limits,
            lam_min,
            lam_max,
            t: 0.0,
            pose: Pose::default(),
            legs,
            qd: [0.0; NQ],
            qdd: [0.0; NQ],
            qddd: [0.0; NQ],
            steer: [0.0; MAX_WHEELS],
            steer_rate: [0.0; MAX_WHEELS],
            steer_accel: [0.0; MAX_WHEELS],
            sign: [1.0; MAX_WHEELS],
            flipped: false,
            phase: Phase::Cruise,
            twist_cmd: Twist::default(),
            halted: true,
            halt_reason: Limiting::None,
            leg_target: legs,
            legs_move: LegMove::Idle,
            goal: [0.0; NQ],
            scale: 1.0,
            limiting: Limiting::None,
            twist_limit: Limiting::None,
            avoid: None,
            avoided: TwistAvoidance::default(),
            avoid_side: [[0.0; 2]; MAX_WHEELS],
        }
    }

    /// Switches the singularity avoidance of the command on (`Some`, a configuration the
    /// caller validated with [`AvoidanceConfig::validate`]) or off (module docs, "Singularity
    /// avoidance").
    pub fn set_avoidance(&mut self, cfg: Option<AvoidanceConfig>) {
        self.avoid = cfg.filter(|c| c.enabled);
        self.avoided = TwistAvoidance::default();
        self.avoid_side = [[0.0; 2]; MAX_WHEELS];
    }

    /// What the singularity avoidance did with the command this cycle (inactive when off).
    pub fn avoidance(&self) -> &TwistAvoidance {
        &self.avoided
    }

    /// The configuration.
    pub fn config(&self) -> &ShaperConfig {
        &self.cfg
    }

    /// Restarts at rest from a measured state: pose, legs and steering angles (first n).
    /// The goal is rest, the leg targets are the legs.
    pub fn reset(&mut self, pose: Pose, legs: &[f64], steer: &[f64]) {
        self.t = 0.0;
        self.pose = pose;
        for i in 0..self.n {
            let l = legs.get(i).copied().unwrap_or(self.legs[i]);
            self.legs[i] = if l.is_finite() {
                l.clamp(self.lam_min[i], self.lam_max[i])
            } else {
                0.5 * (self.lam_min[i] + self.lam_max[i])
            };
            let s = steer.get(i).copied().unwrap_or(0.0);
            self.steer[i] = if s.is_finite() { angle::wrap(s) } else { 0.0 };
        }
        self.qd = [0.0; NQ];
        self.qdd = [0.0; NQ];
        self.qddd = [0.0; NQ];
        self.steer_rate = [0.0; MAX_WHEELS];
        self.steer_accel = [0.0; MAX_WHEELS];
        self.sign = [1.0; MAX_WHEELS];
        self.flipped = false;
        self.phase = Phase::Cruise;
        self.twist_cmd = Twist::default();
        self.halted = true;
        self.halt_reason = Limiting::None;
        self.leg_target = self.legs;
        self.legs_move = LegMove::Idle;
        self.goal = [0.0; NQ];
        self.scale = 1.0;
        self.limiting = Limiting::None;
        self.twist_limit = Limiting::None;
        self.avoided = TwistAvoidance::default();
        self.avoid_side = [[0.0; 2]; MAX_WHEELS];
    }

    /// Follow this body twist (base frame) and, when given, move the legs to these targets
    /// (clamped into each leg's range). The caller validates the values (finite, sane); a
    /// non-finite value here is treated as zero.
    pub fn command(&mut self, twist: Twist, legs: Option<&[f64]>) {
        let f = |x: f64| if x.is_finite() { x } else { 0.0 };
        self.twist_cmd = Twist {
            vx: f(twist.vx),
            vy: f(twist.vy),
            omega: f(twist.omega),
        };
        if let Some(l) = legs {
            self.set_leg_targets(l);
        }
        self.halted = false;
    }

    /// Move the legs to these targets (clamped into range); the twist keeps its command.
    pub fn command_legs(&mut self, legs: &[f64]) {
        self.set_leg_targets(legs);
        self.halted = false;
    }

    fn set_leg_targets(&mut self, legs: &[f64]) {
        let mut changed = false;
        for i in 0..self.n {
            if let Some(&l) = legs.get(i) {
                if l.is_finite() {
                    let c = l.clamp(self.lam_min[i], self.lam_max[i]);
                    changed |= c != self.leg_target[i];
                    self.leg_target[i] = c;
                }
            }
        }
        // A running leg move brakes for the new target when it safely can (see `leg_goal`).
        let _ = changed;
    }

    /// Bring everything to rest (command timeout, stop request): steering held, legs stop
    /// where they are (their targets are kept for the next command).
    pub fn halt(&mut self) {
        self.halt_for(Limiting::Timeout);
    }

    /// [`Shaper::halt`] for a stated reason, reported as the limiting cause while halted
    /// ([`Limiting::Timeout`] for the command timeout, [`Limiting::Stop`] for a stop request).
    pub fn halt_for(&mut self, why: Limiting) {
        self.halted = true;
        self.halt_reason = why;
    }

    /// True while halted (no command is followed).
    pub fn halted(&self) -> bool {
        self.halted
    }

    /// True when the reference is at rest (no motion, no steering in progress).
    pub fn at_rest(&self) -> bool {
        matches!(self.phase, Phase::Cruise) && self.qd.iter().all(|v| *v == 0.0)
    }

    /// The shaped generalised velocity q̇ = (v_x, v_y, ω, λ̇…) in the base frame.
    pub fn velocity(&self) -> &[f64] {
        &self.qd[..3 + self.n]
    }

    /// The reference pose.
    pub fn pose(&self) -> Pose {
        self.pose
    }

    /// The reference legs (first n).
    pub fn legs(&self) -> &[f64] {
        &self.legs[..self.n]
    }

    /// The leg targets (first n).
    pub fn leg_targets(&self) -> &[f64] {
        &self.leg_target[..self.n]
    }

    /// What the shaper does with the command: the commanded twist, the scale and what limits.
    pub fn status(&self) -> ShapingState {
        ShapingState {
            commanded: if self.halted {
                Twist::default()
            } else {
                self.twist_cmd
            },
            scale: self.scale,
            limiting: self.limiting,
        }
    }

    /// u_i = G_i q (module docs), with the legs at their reference extension.
    fn contact(&self, i: usize, q: &Q) -> [f64; 2] {
        let l = self.legs[i];
        let (sa, ca) = (self.sa[i], self.ca[i]);
        [
            q[0] - q[2] * l * sa + q[3 + i] * ca,
            q[1] + q[2] * l * ca + q[3 + i] * sa,
        ]
    }

    /// The twist part of the goal: κ·(command) with κ the largest scale ≤ 1 for which every
    /// wheel stays within `speed_fraction` of its speed limit at any leg extension in range
    /// (so moving legs never push a wheel beyond it) — less the room the legs need while they
    /// have somewhere to go — and what binds κ.
    fn twist_goal(&self) -> ([f64; 3], f64, Limiting, TwistAvoidance) {
        let cmd = [self.twist_cmd.vx, self.twist_cmd.vy, self.twist_cmd.omega];
        if self.halted {
            return ([0.0; 3], 1.0, self.halt_reason, TwistAvoidance::default());
        }
        let avoided = match &self.avoid {
            Some(cfg) => {
                let mut dirs = [[0.0; 2]; MAX_WHEELS];
                for i in 0..self.n {
                    dirs[i] = [self.ca[i], self.sa[i]];
                }
                avoid_twist(
                    cfg,
                    &dirs[..self.n],
                    &self.leg_target[..self.n],
                    cmd,
                    &self.avoid_side[..self.n],
                )
            }
            None => TwistAvoidance {
                twist: cmd,
                ..TwistAvoidance::default()
            },
        };
        let q = avoided.twist;
        let mut vmax = self.cfg.speed_fraction * self.limits.wheel_speed * self.rw;
        // Legs to move: leave the wheels room to roll them at half their speed limit
        // (|u + c e| ≤ |u| + c).
        let (maxr, _) = self.leg_remaining();
        if maxr > self.cfg.leg_tolerance {
            vmax -= 0.5 * self.cfg.speed_fraction * self.limits.leg_speed;
        }
        let mut worst = 0.0f64;
        for i in 0..self.n {
            for l in [self.lam_min[i], self.lam_max[i]] {
                let u = [q[0] - q[2] * l * self.sa[i], q[1] + q[2] * l * self.ca[i]];
                worst = worst.max(norm(u));
            }
        }
        if worst > vmax {
            let k = vmax / worst;
            (
                [q[0] * k, q[1] * k, q[2] * k],
                k,
                Limiting::WheelSpeed,
                avoided,
            )
        } else {
            (q, 1.0, Limiting::None, avoided)
        }
    }

    /// The largest leg cruise speed c ≤ `speed_fraction`·leg_speed (for the farthest leg; the
    /// others scale with their share `d`) for which every wheel, with the twist `tw`, stays
    /// within `speed_fraction` of its speed limit at any leg extension in range.
    fn leg_speed_cap(&self, tw: &[f64; 3], d: &[f64; MAX_WHEELS]) -> f64 {
        let f = self.cfg.speed_fraction;
        let vmax = f * self.limits.wheel_speed * self.rw;
        let mut c = f * self.limits.leg_speed;
        for i in 0..self.n {
            for l in [self.lam_min[i], self.lam_max[i]] {
                let a = [
                    tw[0] - tw[2] * l * self.sa[i],
                    tw[1] + tw[2] * l * self.ca[i],
                ];
                let e = [self.ca[i] * d[i], self.sa[i] * d[i]];
                // |a + c e| ≤ vmax: the largest c ≥ 0 (a quadratic in c).
                let (aa, ae, ee) = (dot(a, a), dot(a, e), dot(e, e));
                if ee <= 0.0 {
                    continue;
                }
                let disc = ae * ae - ee * (aa - vmax * vmax);
                let root = if disc >= 0.0 {
                    (-ae + disc.sqrt()) / ee
                } else {
                    0.0
                };
                c = c.min(root.max(0.0));
            }
        }
        c
    }

    /// Largest remaining leg distance and the leg it belongs to.
    fn leg_remaining(&self) -> (f64, usize) {
        let mut best = (0.0, 0);
        for i in 0..self.n {
            let r = (self.leg_target[i] - self.legs[i]).abs();
            if r > best.0 {
                best = (r, i);
            }
        }
        best
    }

    /// Contact acceleration bound (m/s²) of transitions.
    fn contact_accel(&self, stop: bool) -> f64 {
        let f = if stop {
            self.cfg.stop_accel_fraction
        } else {
            self.cfg.accel_fraction
        };
        f * self.limits.wheel_accel * self.rw
    }

    /// Plans the segment from `from` to `to` (module docs) and names its binding limit.
    fn plan_line(&self, from: &Q, to: &Q) -> (Ramp, Limiting) {
        let mut delta = [0.0; NQ];
        for j in 0..NQ {
            delta[j] = to[j] - from[j];
        }
        let stop = self.halted && to.iter().all(|v| *v == 0.0);
        let a_c = self.contact_accel(stop);
        let fs = self.cfg.speed_fraction;
        let fa = self.cfg.accel_fraction;
        let sr = fs * self.limits.steer_rate;
        let sa = fa * self.limits.steer_accel;
        // Grid: uniform, refined around each wheel's closest approach to its zero velocity.
        let mut grid = [0.0; GRID];
        let mut k = 0;
        const UNIFORM: usize = 49;
        for j in 0..UNIFORM {
            grid[k] = j as f64 / (UNIFORM - 1) as f64;
            k += 1;
        }
        // Geometric points near both ends resolve the short jerk ramps there.
        let mut e = 0.02;
        while e > 2e-5 {
            grid[k] = e;
            grid[k + 1] = 1.0 - e;
            k += 2;
            e *= 0.5;
        }
        // Virtual wheel n = the base origin (direction of travel).
        let mut us = [[0.0; 2]; MAX_WHEELS + 1];
        let mut gs = [[0.0; 2]; MAX_WHEELS + 1];
        for i in 0..self.n {
            us[i] = self.contact(i, from);
            gs[i] = self.contact(i, &delta);
        }
        us[self.n] = [from[0], from[1]];
        gs[self.n] = [delta[0], delta[1]];
        let mut crosses = [false; MAX_WHEELS + 1];
        for i in 0..=self.n {
            let (u0, g) = (us[i], gs[i]);
            let gn = norm(g);
            if gn <= 0.0 {
                continue;
            }
            let bstar = -dot(u0, g) / (gn * gn);
            let d = cross(u0, g).abs() / gn;
            if d <= CROSS_EPS {
                crosses[i] = true;
                continue;
            }
            if bstar > 0.0 && bstar < 1.0 && d < 0.3 {
                for m in [-8.0, -4.0, -2.0, -1.0, -0.5, 0.0, 0.5, 1.0, 2.0, 4.0, 8.0] {
                    let b = bstar + m * d / gn;
                    if b > 0.0 && b < 1.0 && k < GRID {
                        grid[k] = b;
                        k += 1;
                    }
                }
            }
        }
        let grid = &mut grid[..k];
        grid.sort_by(|a, b| a.total_cmp(b));
        let mut m = 0;
        let mut s = [0.0; GRID];
        for &b in grid.iter() {
            if m == 0 || b - s[m - 1] > 1e-12 {
                s[m] = b;
                m += 1;
            }
        }
        s[m - 1] = 1.0;
        // Caps.
        let mut gmax = 0.0f64;
        for i in 0..self.n {
            gmax = gmax.max(norm(gs[i]));
        }
        let base = if gmax > 0.0 { a_c / gmax } else { 1e6 };
        let mut vcap = [base; GRID];
        let jt = if stop {
            self.cfg.stop_jerk_time
        } else {
            self.cfg.jerk_time
        };
        let jerk_cap = base / jt.max(1e-6);
        let mut acap = [jerk_cap; GRID];
        let mut limit = Limiting::WheelAccel;
        let mut tightest = base;
        for j in 0..m {
            let b = s[j];
            for i in 0..=self.n {
                if crosses[i] {
                    continue;
                }
                let g = gs[i];
                let u = [us[i][0] + b * g[0], us[i][1] + b * g[1]];
                let un = norm(u);
                let (rate, accel, what) = if i == self.n {
                    if un < DIRECTION_MIN_SPEED {
                        continue;
                    }
                    (self.cfg.direction_rate, f64::INFINITY, Limiting::SteerRate)
                } else {
                    if un <= REST_EPS {
                        continue;
                    }
                    (sr, sa, Limiting::SteerRate)
                };
                let c = cross(u, g).abs();
                if c == 0.0 {
                    continue;
                }
                let c1 = c / (un * un);
                let c2 = 2.0 * c * dot(u, g).abs() / (un * un * un * un);
                let v1 = rate / c1;
                if v1 < vcap[j] {
                    vcap[j] = v1;
                }
                if v1 < tightest {
                    tightest = v1;
                    limit = what;
                }
                if accel.is_finite() {
                    if c2 > 0.0 {
                        let v2 = (0.5 * accel / c2).sqrt();
                        if v2 < vcap[j] {
                            vcap[j] = v2;
                        }
                        if v2 < tightest {
                            tightest = v2;
                            limit = Limiting::SteerAccel;
                        }
                    }
                    let a1 = 0.5 * accel / c1;
                    acap[j] = acap[j].min(a1);
                    if j > 0 {
                        acap[j - 1] = acap[j - 1].min(a1);
                    }
                }
            }
        }
        (Ramp::plan(&s[..m], &vcap[..m], &acap[..m]), limit)
    }

    /// Decides the next phase from rest-in-β (`Cruise`) toward `goal`.
    fn plan_next(&mut self, goal: &Q) {
        let n = self.n;
        let from = self.qd;
        let mut delta = [0.0; NQ];
        for j in 0..NQ {
            delta[j] = goal[j] - from[j];
        }
        // Rolling wheels: how far does the segment turn them?
        let mut far = false;
        let mut all_rest = true;
        let mut psi = [f64::NAN; MAX_WHEELS];
        for i in 0..n {
            let u0 = self.contact(i, &from);
            let g = self.contact(i, &delta);
            let u1 = [u0[0] + g[0], u0[1] + g[1]];
            if norm(u0) > REST_EPS {
                all_rest = false;
                let gn = norm(g);
                let through = gn > 0.0 && cross(u0, g).abs() / gn <= CROSS_EPS && {
                    let b = -dot(u0, g) / (gn * gn);
                    b > 0.0 && b < 1.0
                };
                let sweep = if norm(u1) <= REST_EPS {
                    0.0
                } else if through {
                    let m1 = [-u1[0], -u1[1]];
                    cross(u0, m1).atan2(dot(u0, m1)).abs()
                } else {
                    cross(u0, u1).atan2(dot(u0, u1)).abs()
                };
                if sweep > self.cfg.far_angle {
                    far = true;
                }
            } else if norm(g) > REST_EPS {
                // At rest now, rolling along g once the segment starts.
                psi[i] = g[1].atan2(g[0]);
            }
        }
        // Only a new twist takes the stop-align-go path: a leg move's segments (the twist
        // unchanged) run as planned, their steering within the caps; a leg braking segment in
        // particular must be the one whose distance was planned.
        let twist_changes = goal[..3] != from[..3];
        if far && twist_changes {
            // Stop along the current direction first; the next plan aligns from rest.
            let zero = [0.0; NQ];
            let (ramp, _) = self.plan_line(&from, &zero);
            self.phase = Phase::Line {
                from,
                delta: {
                    let mut d = [0.0; NQ];
                    for j in 0..NQ {
                        d[j] = -from[j];
                    }
                    d
                },
                target: zero,
                interim: true,
                ramp,
                limit: Limiting::Aligning,
            };
            return;
        }
        // Wheels at rest that will roll: turn them first.
        let mut targets = self.steer;
        let mut need = false;
        if all_rest {
            let cost = |b: f64, st: &[f64; MAX_WHEELS]| {
                let mut c = 0.0f64;
                for i in 0..n {
                    if psi[i].is_finite() {
                        c = c.max(angle::diff(psi[i] + b, st[i]).abs());
                    }
                }
                c
            };
            let (cur, other) = if self.flipped { (PI, 0.0) } else { (0.0, PI) };
            if cost(other, &self.steer) < cost(cur, &self.steer) - self.cfg.flip_hysteresis {
                self.flipped = !self.flipped;
            }
            let b = if self.flipped { PI } else { 0.0 };
            for i in 0..n {
                if psi[i].is_finite() {
                    let d = angle::diff(psi[i] + b, self.steer[i]);
                    targets[i] = self.steer[i] + d;
                    self.sign[i] = if self.flipped { -1.0 } else { 1.0 };
                    need |= d.abs() > self.cfg.align_tolerance;
                }
            }
        } else {
            for i in 0..n {
                if psi[i].is_finite() {
                    let mut d = angle::diff(psi[i], self.steer[i]);
                    let mut sgn = 1.0;
                    if d.abs() > FRAC_PI_2 {
                        d = angle::diff(psi[i] + PI, self.steer[i]);
                        sgn = -1.0;
                    }
                    targets[i] = self.steer[i] + d;
                    self.sign[i] = sgn;
                    need |= d.abs() > self.cfg.align_tolerance;
                }
            }
        }
        if need {
            let mut dmax = 0.0f64;
            let mut delta_s = [0.0; MAX_WHEELS];
            for i in 0..n {
                delta_s[i] = targets[i] - self.steer[i];
                dmax = dmax.max(delta_s[i].abs());
            }
            let sr = self.cfg.speed_fraction * self.limits.steer_rate / dmax;
            let sa = self.cfg.accel_fraction * self.limits.steer_accel / dmax;
            let jerk = sr / self.cfg.jerk_time.max(1e-6);
            const K: usize = 33;
            let mut s = [0.0; K];
            for (j, x) in s.iter_mut().enumerate() {
                *x = j as f64 / (K - 1) as f64;
            }
            let ramp = Ramp::plan(&s, &[sr; K], &[sa.min(jerk); K]);
            self.phase = Phase::Align {
                from: self.steer,
                delta: delta_s,
                ramp,
            };
            return;
        }
        let (ramp, limit) = self.plan_line(&from, goal);
        self.phase = Phase::Line {
            from,
            delta,
            target: *goal,
            interim: false,
            ramp,
            limit,
        };
    }

    /// The legs' part of the goal, advancing the leg move (module docs, "Legs"): a move
    /// starts from rest with a cruise speed for which its acceleration and braking segments
    /// fit the remaining distance; braking starts the cycle before the farthest leg's
    /// remaining distance would fall below what the braking segment needs (computed from
    /// its plan), so a leg never passes its target; what is left (less than one cycle of
    /// travel) is crept at a lower speed.
    fn leg_goal(&mut self, tw: [f64; 3]) -> ([f64; MAX_WHEELS], [f64; 3]) {
        let legs = self.leg_velocity_goal(tw);
        let twist = match self.legs_move {
            LegMove::Idle => tw,
            LegMove::Accel { twist, .. }
            | LegMove::Cruise { twist, .. }
            | LegMove::Decel { twist } => twist,
        };
        (legs, twist)
    }

    fn leg_velocity_goal(&mut self, tw: [f64; 3]) -> [f64; MAX_WHEELS] {
        let n = self.n;
        let zero = [0.0; MAX_WHEELS];
        let (maxr, _) = self.leg_remaining();
        let legs_at_rest = (0..n).all(|i| self.qd[3 + i] == 0.0);
        let settled = matches!(self.phase, Phase::Cruise);
        // A halt stops the legs with everything else. A new twist waits until the legs are at
        // rest: they brake now, with the twist they moved with, unless braking is already
        // closer than the planned braking segment (then the plan runs on; it brakes in time).
        if self.halted {
            self.legs_move = LegMove::Idle;
            return zero;
        }
        // New leg targets likewise: the move brakes now when that stops short of the target
        // it was planned for (which lies in range), else it finishes as planned first.
        let targets = self.leg_target;
        let remaining_to = |t: &[f64; MAX_WHEELS]| {
            let mut m = (0.0f64, 0usize);
            for i in 0..n {
                let r = (t[i] - self.legs[i]).abs();
                if r > m.0 {
                    m = (r, i);
                }
            }
            m
        };
        match self.legs_move {
            LegMove::Accel { twist, target, .. } if twist != tw || target != targets => {
                self.legs_move = LegMove::Decel { twist };
                return zero;
            }
            LegMove::Cruise {
                vel,
                twist,
                target,
                brake,
            } if twist != tw || target != targets => {
                let (r, f) = remaining_to(&target);
                if r - vel[f].abs() * self.dt > brake {
                    self.legs_move = LegMove::Decel { twist };
                    return zero;
                }
            }
            _ => {}
        }
        match self.legs_move {
            LegMove::Idle => {
                // A move starts from rest in the legs with the twist already at its goal, so
                // its acceleration segment is the one planned here.
                let twist_settled = self.qd[..3] == tw[..];
                if maxr <= self.cfg.leg_tolerance || !legs_at_rest || !settled || !twist_settled {
                    return zero;
                }
                let mut d = [0.0; MAX_WHEELS];
                for i in 0..n {
                    d[i] = (self.leg_target[i] - self.legs[i]) / maxr;
                }
                let mut c = self.leg_speed_cap(&tw, &d);
                let mut from = self.qd;
                from[..3].copy_from_slice(&tw);
                for i in 0..n {
                    from[3 + i] = 0.0;
                }
                // Largest c whose acceleration and braking fit (halving from the cap).
                let mut vel = [0.0; MAX_WHEELS];
                for _ in 0..40 {
                    let mut cruise = from;
                    for i in 0..n {
                        cruise[3 + i] = c * d[i];
                    }
                    let (up, _) = self.plan_line(&from, &cruise);
                    let (down, _) = self.plan_line(&cruise, &from);
                    let need = c * (up.integral_of_s() + down.duration() - down.integral_of_s())
                        + c * self.dt;
                    if need <= maxr || c < 1e-6 {
                        break;
                    }
                    c *= 0.5;
                }
                if c < 1e-6 {
                    return zero;
                }
                for i in 0..n {
                    vel[i] = c * d[i];
                }
                self.legs_move = LegMove::Accel {
                    vel,
                    twist: tw,
                    target: targets,
                };
                vel
            }
            LegMove::Accel { vel, twist, target } => {
                let reached = (0..n).all(|i| self.qd[3 + i] == vel[i]);
                if reached && settled {
                    let mut cruise = self.qd;
                    let mut stop = self.qd;
                    for i in 0..n {
                        stop[3 + i] = 0.0;
                    }
                    cruise[..3].copy_from_slice(&twist);
                    let (down, _) = self.plan_line(&cruise, &stop);
                    let (_, f) = remaining_to(&target);
                    let v = vel[f].abs();
                    let brake = v * (down.duration() - down.integral_of_s());
                    self.legs_move = LegMove::Cruise {
                        vel,
                        twist,
                        target,
                        brake,
                    };
                }
                vel
            }
            LegMove::Cruise {
                vel, twist, target, ..
            } => {
                // The braking segment's plan depends on the legs (through the wheels' contact
                // points), so its distance is planned again every cycle.
                let mut stop = self.qd;
                for i in 0..n {
                    stop[3 + i] = 0.0;
                }
                let (down, _) = self.plan_line(&self.qd, &stop);
                let (r, f) = remaining_to(&target);
                let v = vel[f].abs();
                let brake = v * (down.duration() - down.integral_of_s());
                self.legs_move = LegMove::Cruise {
                    vel,
                    twist,
                    target,
                    brake,
                };
                // Legs shorten on the way: one more cycle of travel as a margin.
                if r - 2.0 * v * self.dt <= brake {
                    self.legs_move = LegMove::Decel { twist };
                    return zero;
                }
                vel
            }
            LegMove::Decel { .. } => {
                if legs_at_rest && settled {
                    self.legs_move = LegMove::Idle;
                }
                zero
            }
        }
    }

    /// Advances one cycle and returns the reference sample (module docs).
    pub fn step(&mut self) -> ReferenceSample {
        let dt = self.dt;
        let prev = self.qd;
        let (tw, k, why, avoided) = self.twist_goal();
        // The side each field's edge was taken on is kept while the command's ICR stays in
        // that field (an ICR resting on the wheel keeps it), forgotten once it leaves.
        for i in 0..self.n {
            if !(avoided.active && avoided.wheel == Some(i)) {
                self.avoid_side[i] = [0.0; 2];
            }
        }
        if let (true, Some(w)) = (avoided.active, avoided.wheel) {
            self.avoid_side[w] = avoided.push;
        }
        self.avoided = avoided;
        let (legs, tw) = self.leg_goal(tw);
        let mut goal = [0.0; NQ];
        goal[..3].copy_from_slice(&tw);
        goal[3..3 + self.n].copy_from_slice(&legs[..self.n]);
        self.goal = goal;
        self.scale = k;
        self.twist_limit = why;

        if matches!(self.phase, Phase::Cruise) && goal != self.qd {
            self.plan_next(&goal);
        }
        let mut aligning = false;
        self.limiting = self.twist_limit;
        match &mut self.phase {
            Phase::Cruise => {
                self.qdd = [0.0; NQ];
                self.qddd = [0.0; NQ];
            }
            Phase::Line {
                from,
                delta,
                target,
                interim,
                ramp,
                limit,
            } => {
                if *target != goal && !*interim && !ramp.braking() {
                    ramp.brake();
                }
                let (b, bd, bdd) = ramp.advance(dt);
                for j in 0..NQ {
                    self.qd[j] = from[j] + b * delta[j];
                    self.qdd[j] = bd * delta[j];
                    self.qddd[j] = bdd * delta[j];
                }
                if why == Limiting::None {
                    self.limiting = *limit;
                }
                if ramp.done() {
                    if b == 1.0 {
                        // Arrived: exactly the target (from + 1·Δ may differ in the last bit).
                        self.qd = *target;
                    }
                    self.phase = Phase::Cruise;
                    self.qdd = [0.0; NQ];
                }
            }
            Phase::Align { from, delta, ramp } => {
                if self.halted && !ramp.braking() {
                    ramp.brake();
                }
                let (g, gd, gdd) = ramp.advance(dt);
                for i in 0..self.n {
                    self.steer[i] = angle::wrap(from[i] + g * delta[i]);
                    self.steer_rate[i] = gd * delta[i];
                    self.steer_accel[i] = gdd * delta[i];
                }
                aligning = true;
                self.limiting = Limiting::Aligning;
                if ramp.done() {
                    self.phase = Phase::Cruise;
                    self.steer_rate = [0.0; MAX_WHEELS];
                    self.steer_accel = [0.0; MAX_WHEELS];
                }
            }
        }
        if self.halted {
            self.limiting = self.halt_reason;
        }
        // Integrate the reference (trapezoid over the cycle).
        let avg = Twist {
            vx: 0.5 * (prev[0] + self.qd[0]),
            vy: 0.5 * (prev[1] + self.qd[1]),
            omega: 0.5 * (prev[2] + self.qd[2]),
        };
        self.pose = crate::model::se2_integrate(self.pose, &avg, dt);
        for i in 0..self.n {
            let l = self.legs[i] + 0.5 * (prev[3 + i] + self.qd[3 + i]) * dt;
            self.legs[i] = l.clamp(self.lam_min[i], self.lam_max[i]);
        }
        self.t += dt;
        if !aligning {
            self.update_steering();
        }
        self.sample()
    }

    /// Steering reference of rolling wheels: their direction of travel on their branch
    /// (a wheel whose velocity passed through zero flips its branch, not its angle).
    fn update_steering(&mut self) {
        for i in 0..self.n {
            let u = self.contact(i, &self.qd);
            let un = norm(u);
            self.steer_accel[i] = 0.0;
            if un <= REST_EPS {
                self.steer_rate[i] = 0.0;
                continue;
            }
            let mut du = self.contact(i, &self.qdd);
            // d/dt of the ω λ e⊥ term through λ̇.
            du[0] += -self.qd[2] * self.qd[3 + i] * self.sa[i];
            du[1] += self.qd[2] * self.qd[3 + i] * self.ca[i];
            let s = self.sign[i];
            let mut cand = (s * u[1]).atan2(s * u[0]);
            if angle::diff(cand, self.steer[i]).abs() > FRAC_PI_2 {
                self.sign[i] = -s;
                cand = angle::wrap(cand + PI);
            }
            self.steer[i] = cand;
            self.steer_rate[i] = cross(u, du) / (un * un);
        }
    }

    /// The current reference sample without advancing (the state held at rest after
    /// [`Shaper::reset`]).
    pub fn hold_sample(&self) -> ReferenceSample {
        self.sample()
    }

    fn sample(&self) -> ReferenceSample {
        let n = self.n;
        let (s, c) = self.pose.theta.sin_cos();
        let rot = |v: [f64; 2]| [c * v[0] - s * v[1], s * v[0] + c * v[1]];
        let jp = |v: [f64; 2]| [-v[1], v[0]];
        let vb = [self.qd[0], self.qd[1]];
        let ab = [self.qdd[0], self.qdd[1]];
        let jb = [self.qddd[0], self.qddd[1]];
        let (om, dom) = (self.qd[2], self.qdd[2]);
        let v_w = rot(vb);
        let jv = jp(vb);
        let ja = jp(ab);
        let a_w = rot([ab[0] + om * jv[0], ab[1] + om * jv[1]]);
        let j_w = rot([
            jb[0] + 2.0 * om * ja[0] + dom * jv[0] - om * om * vb[0],
            jb[1] + 2.0 * om * ja[1] + dom * jv[1] - om * om * vb[1],
        ]);
        let mut z = ZVec::zeros();
        let mut dz = ZVec::zeros();
        let mut ddz = ZVec::zeros();
        let mut dddz = ZVec::zeros();
        z[0] = self.pose.x;
        z[1] = self.pose.y;
        z[2] = self.pose.theta;
        dz[0] = v_w[0];
        dz[1] = v_w[1];
        dz[2] = om;
        ddz[0] = a_w[0];
        ddz[1] = a_w[1];
        ddz[2] = dom;
        dddz[0] = j_w[0];
        dddz[1] = j_w[1];
        dddz[2] = self.qddd[2];
        for i in 0..n {
            z[3 + i] = self.legs[i];
            dz[3 + i] = self.qd[3 + i];
            ddz[3 + i] = self.qdd[3 + i];
            dddz[3 + i] = self.qddd[3 + i];
        }
        let mut steer = SteerReference {
            valid: true,
            ..Default::default()
        };
        steer.angle[..n].copy_from_slice(&self.steer[..n]);
        steer.rate[..n].copy_from_slice(&self.steer_rate[..n]);
        steer.accel[..n].copy_from_slice(&self.steer_accel[..n]);
        ReferenceSample {
            t: self.t,
            n,
            z,
            dz,
            ddz,
            dddz,
            steer,
        }
    }
}

/// The contact speed (m/s) below which the controllers steer a wheel by the reference's
/// steering angle instead of its direction of travel (re-exported for convenience).
pub const CONTROLLER_HOLD_SPEED: f64 = HOLD_SPEED;

#[cfg(test)]
mod tests {
    use super::*;
    use crate::limits::wheel_demand;

    fn shaper() -> (Platform, Shaper) {
        let p = Platform::justin();
        let mut s = Shaper::new(&p, ShaperConfig::default());
        let legs = [0.465; 4];
        s.reset(Pose::default(), &legs, &[0.0; 4]);
        (p, s)
    }

    /// Runs `cycles` steps and checks every sample against the limits (demands from the
    /// reference itself) and continuity of z̈; returns the samples.
    fn run(p: &Platform, s: &mut Shaper, cycles: usize) -> Vec<ReferenceSample> {
        let mut out: Vec<ReferenceSample> = Vec::new();
        for _ in 0..cycles {
            let r = s.step();
            for i in 0..4 {
                let d = wheel_demand(p, i, &r);
                let l = &p.limits;
                assert!(
                    d.speed <= l.wheel_speed * 0.9 + 1e-9,
                    "t {} wheel {i} speed {}",
                    r.t,
                    d.speed
                );
                assert!(d.leg_speed <= l.leg_speed * 0.9 + 1e-9);
                assert!(
                    d.accel.abs() <= l.wheel_accel + 1e-6,
                    "t {} wheel {i} accel {}",
                    r.t,
                    d.accel
                );
                assert!(
                    d.steer_rate.abs() <= l.steer_rate + 1e-6,
                    "t {} wheel {i} steer rate {}",
                    r.t,
                    d.steer_rate
                );
                assert!(r.steer.rate[i].abs() <= l.steer_rate + 1e-6);
                assert!(
                    d.steer_accel.abs() <= l.steer_accel * 1.05 + 1e-6,
                    "t {} wheel {i} steer accel {}",
                    r.t,
                    d.steer_accel
                );
                assert!(
                    r.z[3 + i] >= p.wheels[i].lambda_min - 1e-12
                        && r.z[3 + i] <= p.wheels[i].lambda_max + 1e-12
                );
            }
            if let Some(prev) = out.last() {
                for j in 0..7 {
                    // z̈ continuous: changes by at most the jerk bound × dt.
                    assert!(
                        (r.ddz[j] - prev.ddz[j]).abs() < 1.0,
                        "t {} z̈[{j}] jump {} → {}",
                        r.t,
                        prev.ddz[j],
                        r.ddz[j]
                    );
                }
            }
            out.push(r);
        }
        out
    }

    #[test]
    fn steady_state_keeps_the_command_direction_with_one_factor() {
        let (p, mut s) = shaper();
        let cmd = Twist {
            vx: 3.0,
            vy: 1.0,
            omega: 5.0,
        };
        s.command(cmd, None);
        let samples = run(&p, &mut s, 1500);
        let v = s.velocity();
        let k = v[0] / cmd.vx;
        assert!(k > 0.0 && k < 1.0, "scaled down: {k}");
        assert!((v[1] - k * cmd.vy).abs() < 1e-12 && (v[2] - k * cmd.omega).abs() < 1e-12);
        assert!(!s.at_rest(), "moving");
        assert_eq!(s.status().limiting, Limiting::WheelSpeed);
        assert!((s.status().scale - k).abs() < 1e-12);
        // The fastest wheel is within 90 % of its limit, and would be at exactly 90 % with
        // the legs fully out (the scale holds for any leg extension).
        let last = samples.last().unwrap();
        let fastest = (0..4)
            .map(|i| wheel_demand(&p, i, last).speed)
            .fold(0.0, f64::max);
        assert!(fastest <= 0.9 * p.limits.wheel_speed + 1e-9, "{fastest}");
        let at_max = (0..4)
            .map(|i| {
                let a = p.wheels[i].alpha;
                let l = p.wheels[i].lambda_max;
                (v[0] - v[2] * l * a.sin()).hypot(v[1] + v[2] * l * a.cos()) / p.wheel_radius
            })
            .fold(0.0, f64::max);
        assert!(
            (at_max - 0.9 * p.limits.wheel_speed).abs() < 1e-9,
            "{at_max}"
        );
    }

    #[test]
    fn from_rest_the_wheels_align_before_rolling() {
        let (p, mut s) = shaper();
        s.command(
            Twist {
                vx: 0.0,
                vy: 0.5,
                omega: 0.0,
            },
            None,
        );
        let samples = run(&p, &mut s, 400);
        // While any wheel still turns, the platform does not move.
        let mut aligned_at = None;
        for r in &samples {
            let turning = (0..4).any(|i| r.steer.rate[i] != 0.0);
            let moving = r.dz[0] != 0.0 || r.dz[1] != 0.0;
            if turning {
                assert!(!moving, "rolling while aligning at t {}", r.t);
            }
            if moving && aligned_at.is_none() {
                aligned_at = Some(r.t);
                for i in 0..4 {
                    let e = angle::diff(r.steer.angle[i], FRAC_PI_2).abs();
                    let e2 = angle::diff(r.steer.angle[i], -FRAC_PI_2).abs();
                    assert!(e.min(e2) < 1e-6, "wheel {i} at {}", r.steer.angle[i]);
                }
            }
        }
        assert!(aligned_at.is_some());
        // 90° at 0.9 × 6 rad/s and 0.8 × 40 rad/s²: about 0.6 s.
        assert!(aligned_at.unwrap() > 0.3 && aligned_at.unwrap() < 1.0);
    }

    #[test]
    fn a_reversal_flips_every_wheel_at_once_without_steering() {
        let (p, mut s) = shaper();
        s.command(
            Twist {
                vx: 0.8,
                vy: 0.0,
                omega: 0.0,
            },
            None,
        );
        run(&p, &mut s, 300);
        let before = s.steer;
        s.command(
            Twist {
                vx: -0.8,
                vy: 0.0,
                omega: 0.0,
            },
            None,
        );
        let samples = run(&p, &mut s, 300);
        for r in &samples {
            for i in 0..4 {
                assert!(r.steer.rate[i].abs() < 1e-9, "steering during a reversal");
                assert!(angle::diff(r.steer.angle[i], before[i]).abs() < 1e-9);
            }
        }
        assert!((s.velocity()[0] + 0.8).abs() < 1e-12);
    }

    #[test]
    fn halt_stops_within_the_deceleration_limit_with_steering_held() {
        let (p, mut s) = shaper();
        s.command(
            Twist {
                vx: 0.6,
                vy: 0.3,
                omega: 0.4,
            },
            None,
        );
        let samples = run(&p, &mut s, 600);
        let r0 = *samples.last().unwrap();
        let wmax = (0..4)
            .map(|i| wheel_demand(&p, i, &r0).speed)
            .fold(0.0, f64::max);
        s.halt();
        let mut n = 0;
        while !s.at_rest() {
            let r = s.step();
            for i in 0..4 {
                assert!(angle::diff(r.steer.angle[i], r0.steer.angle[i]).abs() < 1e-9);
            }
            n += 1;
            assert!(n < 10_000);
        }
        let t = n as f64 * p.dt();
        let bound = wmax / p.limits.wheel_accel + 2.0 * p.dt();
        assert!(t <= bound, "stopped after {t} s, bound {bound} s");
    }

    #[test]
    fn a_direction_far_away_stops_aligns_and_goes() {
        let (p, mut s) = shaper();
        s.command(
            Twist {
                vx: 0.8,
                vy: 0.0,
                omega: 0.0,
            },
            None,
        );
        run(&p, &mut s, 300);
        s.command(
            Twist {
                vx: 0.0,
                vy: 0.8,
                omega: 0.0,
            },
            None,
        );
        let samples = run(&p, &mut s, 800);
        // Somewhere in between the platform is at rest.
        assert!(samples.iter().any(|r| r.dz[0] == 0.0 && r.dz[1] == 0.0));
        assert!((s.velocity()[1] - 0.8).abs() < 1e-12);
    }

    #[test]
    fn legs_reach_their_targets_without_overshoot_while_driving() {
        let (p, mut s) = shaper();
        s.command(
            Twist {
                vx: 0.3,
                vy: 0.1,
                omega: 0.2,
            },
            Some(&[0.56, 0.37, 0.56, 0.37]),
        );
        let samples = run(&p, &mut s, 3000);
        for r in &samples {
            assert!(r.z[3] <= 0.56 + 1e-12 && r.z[4] >= 0.37 - 1e-12);
        }
        for (i, t) in [0.56, 0.37, 0.56, 0.37].iter().enumerate() {
            assert!(
                (s.legs()[i] - t).abs() <= 1e-4 + 1e-12,
                "leg {i}: {}",
                s.legs()[i]
            );
        }
    }

    #[test]
    fn the_icr_sweeping_across_a_wheel_turns_it_within_its_limits() {
        let (p, mut s) = shaper();
        // Rotation with a translation that moves the ICR across wheel 0's contact point
        // (passing it 2 mm off): ICR = (−v_y/ω, v_x/ω).
        let a = p.wheels[0].alpha;
        let (px, py) = (0.465 * a.cos(), 0.465 * a.sin());
        let om = 0.4;
        let at = |x: f64, y: f64| Twist {
            vx: om * y,
            vy: -om * x,
            omega: om,
        };
        s.command(at(px - 0.3, py + 0.002), None);
        run(&p, &mut s, 800);
        s.command(at(px + 0.3, py + 0.002), None);
        let samples = run(&p, &mut s, 1500);
        // Wheel 0 turned through (about) half a turn on the way, within its limits (run()).
        let turned: f64 = samples
            .windows(2)
            .map(|w| angle::diff(w[1].steer.angle[0], w[0].steer.angle[0]).abs())
            .sum();
        assert!(turned > 2.5, "wheel 0 turned {turned} rad");
        let v = s.velocity();
        let want = at(px + 0.3, py + 0.002);
        assert!((v[0] - want.vx).abs() < 1e-12 && (v[1] - want.vy).abs() < 1e-12);
    }

    #[test]
    fn a_pivot_about_a_wheel_holds_that_wheel() {
        let (p, mut s) = shaper();
        let a = p.wheels[1].alpha;
        let (px, py) = (0.465 * a.cos(), 0.465 * a.sin());
        let om = 0.5;
        s.command(
            Twist {
                vx: om * py,
                vy: -om * px,
                omega: om,
            },
            None,
        );
        let samples = run(&p, &mut s, 1000);
        let held = samples[0].steer.angle[1];
        for r in &samples {
            assert_eq!(r.steer.angle[1], held, "wheel 2 turned at t {}", r.t);
            assert_eq!(r.steer.rate[1], 0.0);
        }
        assert!(samples.last().unwrap().dz[2] > 0.49);
    }

    #[test]
    fn with_avoidance_a_pivot_turns_about_the_field_edge_and_that_wheel_rolls() {
        let (p, mut s) = shaper();
        let cfg = AvoidanceConfig::default();
        s.set_avoidance(Some(cfg));
        let a = p.wheels[1].alpha;
        let l = 0.465;
        let (px, py) = (l * a.cos(), l * a.sin());
        let om = 0.5;
        let cmd = Twist {
            vx: om * py,
            vy: -om * px,
            omega: om,
        };
        s.command(cmd, None);
        let samples = run(&p, &mut s, 1000);
        assert!(s.avoidance().active && s.avoidance().wheel == Some(1));
        // Steady: the ICR on the field's edge outward along the leg, the base at the
        // commanded speed, wheel 2 rolling at |θ̇| d_start.
        let v = s.velocity();
        let ds = crate::avoidance::field_radius(&cfg, l);
        let z = crate::avoidance::icr_from_twist(v[0], v[1], v[2]).unwrap();
        let want = [(l + ds) * a.cos(), (l + ds) * a.sin()];
        assert!((z[0] - want[0]).abs() < 1e-12 && (z[1] - want[1]).abs() < 1e-12);
        assert!((v[0].hypot(v[1]) - cmd.vx.hypot(cmd.vy)).abs() < 1e-12);
        let last = samples.last().unwrap();
        let d = wheel_demand(&p, 1, last);
        assert!((d.speed * p.wheel_radius - v[2].abs() * ds).abs() < 1e-9);
        // A held command is one goal: the shaper cruises.
        let before = *s.velocity().first().unwrap();
        run(&p, &mut s, 100);
        assert_eq!(before, s.velocity()[0]);
        assert!(matches!(s.phase, Phase::Cruise));
    }

    #[test]
    fn with_avoidance_an_icr_crossing_a_wheel_reverses_its_roll_without_steering() {
        let (p, mut s) = shaper();
        s.set_avoidance(Some(AvoidanceConfig::default()));
        let a = p.wheels[0].alpha;
        // The leg is 30 µm off its nominal extension (as when reset from a measurement).
        let l = 0.465;
        s.reset(Pose::default(), &[l + 3e-5, l, l, l], &[0.0; 4]);
        let (px, py) = (l * a.cos(), l * a.sin());
        let om = 0.4;
        let at = |x: f64| Twist {
            vx: om * py,
            vy: -om * x,
            omega: om,
        };
        // Commands every 40 ms moving the ICR along x through wheel 1's contact point.
        s.command(at(px - 0.3), None);
        run(&p, &mut s, 800);
        let mut samples = Vec::new();
        for k in 0..=150 {
            s.command(at(px - 0.3 + 0.004 * k as f64), None);
            samples.extend(run(&p, &mut s, 10));
        }
        samples.extend(run(&p, &mut s, 1500));
        // Wheel 1 did not turn while slow: its velocity passed through zero on a line (a
        // flip would be π; what is left, 0.1 mrad, is the approach direction settling onto
        // the field's side, tilted by the leg's offset).
        let mut turned = 0.0f64;
        for w in samples.windows(2) {
            let slow = wheel_demand(&p, 0, &w[1]).speed * p.wheel_radius < HOLD_SPEED;
            if slow {
                turned += angle::diff(w[1].steer.angle[0], w[0].steer.angle[0]).abs();
            }
        }
        assert!(turned < 1e-3, "wheel 1 turned {turned} rad while slow");
        // It did pass through zero, and rolls the other way now.
        assert!(samples
            .iter()
            .any(|r| wheel_demand(&p, 0, r).speed * p.wheel_radius < 1e-3));
        let v = s.velocity();
        let want = at(px + 0.3);
        assert!((v[0] - want.vx).abs() < 1e-12 && (v[1] - want.vy).abs() < 1e-12);
    }
}
