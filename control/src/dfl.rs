//! Controller 1: dynamic feedback linearization (seed 000, Sect. IV), plus the pieces
//! both tracking controllers share ([`ControlInput`], [`ControlOutput`],
//! [`TrackingController`], [`alignment_command`]).
//!
//! # Model and derivation of H and M (seed 000 eq. 23, "omitted for lack of space")
//!
//! Reduced model (seed 000 eq. 20) written with a *reference wheel* k (the paper uses
//! k = 1): with c = cos(θ + φ_k), s = sin(θ + φ_k), c_α = cos(θ + α_k), s_α = sin(θ + α_k),
//!
//! ```text
//! ẋ = c v_Wk + λ_k s_α ω − c_α v_λk
//! ẏ = s v_Wk − λ_k c_α ω − s_α v_λk
//! θ̇ = ω,   λ̇_i = v_λi,   φ̇_k = v_φk
//! ```
//!
//! (solve u_k = v_Wk (cos φ_k, sin φ_k) = Rᵀ(ẋ, ẏ) + ω λ_k e⊥_k + v_λk e_k for (ẋ, ẏ)).
//! Output z = (x, y, θ, λ_1 … λ_n). The inputs v_Wk, ω, v_λ appear already in ż, so
//! integrators η = (v_Wk, ω, v_λ1 … v_λn) are added with η̇ = (u_W, u_ω, u_λ), and φ̇_k =
//! v_φk stays a direct input. Differentiating ż once more (using θ̇ = ω, λ̇_k = v_λk,
//! d/dt c = −s (ω + v_φk), d/dt s = c (ω + v_φk), d/dt c_α = −s_α ω, d/dt s_α = c_α ω):
//!
//! ```text
//! ẍ = c u_W − s v_Wk v_φk + λ_k s_α u_ω − c_α u_λk + M_x
//! ÿ = s u_W + c v_Wk v_φk − λ_k c_α u_ω − s_α u_λk + M_y
//! θ̈ = u_ω,   λ̈_i = u_λi
//! M_x = −s v_Wk ω + 2 s_α ω v_λk + λ_k c_α ω²
//! M_y =  c v_Wk ω − 2 c_α ω v_λk + λ_k s_α ω²
//! ```
//!
//! So z̈ = H(q_e) u + M(q_e) with u = (u_W, u_ω, u_λ1 … u_λn, v_φk) and (rows x, y, θ, λ_i)
//!
//! ```text
//!       u_W   u_ω       u_λk        v_φk
//! H = [ c     λ_k s_α   −c_α   …   −s v_Wk ]
//!     [ s    −λ_k c_α   −s_α   …    c v_Wk ]
//!     [ 0     1          0     …    0      ]
//!     [ 0     0          I_n        0      ]
//! ```
//!
//! M = (M_x, M_y, 0, 0 … 0). The θ and λ rows fix u_ω and u_λ; what remains is the 2×2
//! block [[c, −s v_Wk], [s, c v_Wk]] in (u_W, v_φk), of determinant v_Wk. Moving the v_φk
//! column from the last place to the second takes m − 2 transpositions (m = 3 + n), so
//! **det H = (−1)^(m−2) v_Wk = (−1)^(n+1) v_Wk**: independent of λ, θ and the angles,
//! singular exactly at v_Wk = 0 (test `det_h_is_signed_wheel_speed`). The inverse in
//! closed form: u_ω = v_θ, u_λ = v_λ, and with
//! b = (v_x − M_x − λ_k s_α u_ω + c_α u_λk, v_y − M_y + λ_k c_α u_ω + s_α u_λk):
//! u_W = c b_x + s b_y, v_φk = (−s b_x + c b_y)/v_Wk.
//!
//! The outer loop is seed 000 eq. 25: v = z̈* + K_D (ż* − ż) + K_P (z* − z), with ż from
//! the model (eq. 20 evaluated on η: "ż is obtained through (20)"), ξ from odometry,
//! λ and φ_k measured. Gains K_D = `gains.dfl_kd`·I, K_P = `gains.dfl_kp`·I (3 and 2).
//!
//! # Wheels other than k (seed 000 eq. 22)
//!
//! Each other wheel is steered to φ_j = atan2(u_j) with u_j its model contact velocity
//! (from η), the feed-forward rate φ̇_j = (u_x u̇_y − u_y u̇_x)/|u|² with u̇_j from the model
//! accelerations z̈ = v, plus `gains.steer_kp`·diff(φ_j*, φ_j). A wheel rolls at the
//! projection of u_j on its actual heading (so a steering lag never pushes it sideways).
//! The sign of v_Wj is chosen per wheel so that φ_j* is the branch nearest the measured
//! angle: when u_j passes through zero along a line (the wheel stops and reverses), the
//! wheel keeps its angle and v_Wj changes sign. Below `REST_SPEED` a wheel holds its angle.
//!
//! # Practical rules (seed 000 Sect. IV–V) and beyond
//!
//! * Open-loop alignment first ([`alignment_command`]); perfect matching: [`DflController::reset`]
//!   sets η = η*(t₀) from the reference.
//! * Termination: once motion has started, `finished` is raised (and zero is commanded)
//!   when the reference wheel speed |v_Wk*| < ε = 0.01 m/s. With k the fastest wheel this is
//!   max_i |v_Wi*| < ε, i.e. the whole platform is about to stop.
//! * Beyond the paper: k is chosen per cycle as the fastest wheel of the model, switching
//!   only when another wheel is 25 % faster (hysteresis). At a switch η is handed over:
//!   ω and v_λ are platform quantities and stay, v_Wj := u_j · (cos φ_j, sin φ_j), the new
//!   wheel's model velocity projected on its measured heading, so ż is continuous.
//!   Thus a wheel passing through rest does not stop the controller (test
//!   `dfl_survives_wheel_one_stopping`).
//! * Limits: the controller *reports* `limit_ratio` (largest |command|/limit over wheel
//!   spin, steering rate and leg rate). If it exceeds 1 the whole command is scaled by
//!   1/ratio (never one wheel clamped) and `saturated` is set, so a supervisor can stop;
//!   the linearization is then no longer exact.

// Index loops over parallel per-wheel arrays read better than zipped iterators here.
#![allow(clippy::needless_range_loop)]

use crate::angle;
use crate::model::{steer_from_velocity, wheel_acceleration_body, wheel_velocity_body};
use crate::platform::Platform;
use crate::types::{Command, Measurement, Pose, ReferenceSample, Twist, ZVec, MAX_WHEELS, Z_MAX};
use nalgebra::SMatrix;

/// Contact speed (m/s) below which a coordinated wheel holds its steering angle.
pub const REST_SPEED: f64 = 1e-3;
/// Seed 000's persistence / termination threshold ε (m/s).
pub const EPSILON: f64 = 0.01;
/// Reference-wheel switching hysteresis: switch when another wheel is this much faster.
pub const SWITCH_RATIO: f64 = 1.25;

/// What a tracking controller gets each cycle.
#[derive(Clone, Copy, Debug)]
pub struct ControlInput<'a> {
    /// Time (s) on the trajectory's clock.
    pub t: f64,
    /// Cycle period (s).
    pub dt: f64,
    /// This cycle's wheel measurements.
    pub measurement: &'a Measurement,
    /// Estimated pose (odometry).
    pub pose: Pose,
    /// Reference sample at `t`.
    pub reference: &'a ReferenceSample,
    /// Measured world-frame platform twist (odometry), when the controller should use it.
    ///
    /// `None` reproduces seed 000, where ż in the outer loop is computed from the model (20)
    /// with the compensator states η. `Some` makes the DFL form ė from the measured twist and
    /// the measured leg rates instead. Why: with η-derived ż, any velocity the drives fail to
    /// deliver (motor lag, setpoint latency, slip) is invisible to K_D, and a constant
    /// shortfall δ settles at a position error e = (K_D/K_P)·δ (1.6 mm on the legs in the
    /// simulator at 0.02 m/s). With measured ż the integrators η act as integral action on
    /// the velocity error and the steady-state error to a constant shortfall is zero.
    pub measured_twist: Option<crate::types::Twist>,
}

/// What a tracking controller returns each cycle.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct ControlOutput {
    /// Wheel commands (already within limits: scaled as a whole if needed).
    pub command: Command,
    /// Termination rule hit: the controller commands zero and the motion is over.
    pub finished: bool,
    /// Index of the reference wheel used this cycle (DFL: wheel k; kinematic: the fastest).
    pub reference_wheel: usize,
    /// The controller met a singularity (DFL: reference-wheel speed ≈ 0) this cycle.
    pub singular: bool,
    /// Smallest model contact speed over all wheels (m/s): distance to singularity A.
    pub min_wheel_speed: f64,
    /// Largest |command|/limit before scaling (wheel spin, steering rate, leg rate).
    pub limit_ratio: f64,
    /// `limit_ratio` > 1: the command was scaled down as a whole.
    pub saturated: bool,
}

/// Shared interface of the tracking controllers.
pub trait TrackingController {
    /// Initialises the internal state from the reference at t₀ (perfect matching).
    fn reset(&mut self, p: &Platform, reference: &ReferenceSample);
    /// One control cycle.
    fn step(&mut self, p: &Platform, input: &ControlInput) -> ControlOutput;
    /// Short name for logs.
    fn name(&self) -> &'static str;
}

/// Largest |command|/limit over wheel spin, steering rate and the given leg rates.
pub fn limit_ratio(p: &Platform, cmd: &Command, leg_rates: &[f64]) -> f64 {
    let l = &p.limits;
    let mut r: f64 = 0.0;
    for w in cmd.wheels.iter().take(cmd.n) {
        r = r.max(w.wheel_speed.abs() / l.wheel_speed);
        r = r.max(w.steer_rate.abs() / l.steer_rate);
    }
    for v in leg_rates {
        r = r.max(v.abs() / l.leg_speed);
    }
    if r.is_finite() {
        r
    } else {
        f64::INFINITY
    }
}

/// Scales the whole command by 1/ratio when ratio > 1 (seed 004's α_s scaling applied to
/// the full command: the direction in actuator space is kept). Non-finite commands are
/// replaced by zero. Returns whether scaling happened.
pub fn desaturate(cmd: &mut Command, ratio: f64) -> bool {
    if !ratio.is_finite() {
        *cmd = Command::zero(cmd.n);
        return true;
    }
    if ratio > 1.0 {
        for w in cmd.wheels.iter_mut().take(cmd.n) {
            w.wheel_speed /= ratio;
            w.steer_rate /= ratio;
        }
        return true;
    }
    false
}

/// Wheels that follow the reference's steering angle instead of their direction of travel:
/// with a steering reference, those whose reference contact speed is below
/// [`crate::limits::HOLD_SPEED`] (a wheel the ICR rests on, a platform at rest or aligning).
/// Without one, none (the controllers' own rules apply).
pub fn held_wheels(p: &Platform, r: &ReferenceSample) -> [bool; MAX_WHEELS] {
    let mut held = [false; MAX_WHEELS];
    if !r.steer.valid {
        return held;
    }
    let tw = r.twist_world();
    for (i, h) in held
        .iter_mut()
        .enumerate()
        .take(p.n().min(r.n).min(MAX_WHEELS))
    {
        let u = wheel_velocity_body(p, i, r.z[2], r.z[3 + i], &tw, r.dz[3 + i]);
        let sp = u[0].hypot(u[1]);
        // NaN (a broken reference) holds too.
        *h = sp.is_nan() || sp < crate::limits::HOLD_SPEED;
    }
    held
}

/// How far above [`crate::limits::HOLD_SPEED`] (as a multiple of it) a wheel's steering
/// blends from the reference's angle to its own direction of travel.
pub const HOLD_BLEND: f64 = 2.0;

/// Per wheel, how much of its steering comes from its own direction of travel (1) rather
/// than the reference's steering angle (0), with a steering reference: 0 below
/// [`crate::limits::HOLD_SPEED`] ([`held_wheels`]), rising linearly to 1 at (1 +
/// [`HOLD_BLEND`]) × that speed of the reference's contact speed. Near rest the direction of
/// the commanded velocity is mostly the feedback's correction, which swings without bound as
/// the reference's speed goes to zero; the reference says where the wheel rolls. The blend
/// makes the hand-over between the two continuous. Without a steering reference, 1.
pub fn steer_weights(p: &Platform, r: &ReferenceSample) -> [f64; MAX_WHEELS] {
    let mut w = [1.0; MAX_WHEELS];
    if !r.steer.valid {
        return w;
    }
    let tw = r.twist_world();
    let hold = crate::limits::HOLD_SPEED;
    for (i, wi) in w
        .iter_mut()
        .enumerate()
        .take(p.n().min(r.n).min(MAX_WHEELS))
    {
        let u = wheel_velocity_body(p, i, r.z[2], r.z[3 + i], &tw, r.dz[3 + i]);
        let sp = u[0].hypot(u[1]);
        *wi = if sp.is_nan() {
            0.0
        } else {
            ((sp - hold) / (HOLD_BLEND * hold)).clamp(0.0, 1.0)
        };
    }
    w
}

/// Steering-rate command of a held wheel ([`held_wheels`]): the reference's steering rate
/// plus `steer_kp` × the angle error.
pub fn held_steer_rate(p: &Platform, r: &ReferenceSample, i: usize, phi_meas: f64) -> f64 {
    let range = p.wheels.get(i).and_then(angle::SteerRange::of);
    let e = angle::steer_error(range, r.steer.angle[i], phi_meas);
    let v = r.steer.rate[i] + p.gains.steer_kp * if e.is_finite() { e } else { 0.0 };
    if v.is_finite() {
        v
    } else {
        0.0
    }
}

/// Direction of wheel `i`'s reference contact velocity: atan2(u_i*) when |u_i*| ≥
/// `REST_SPEED`, otherwise the direction it will take as the reference starts moving
/// (u_i evaluated on the Taylor expansion of z* with ż*, z̈*, z⃛* at increasing look-ahead
/// times). `None` if the wheel stays at rest.
pub fn reference_direction(p: &Platform, r: &ReferenceSample, i: usize) -> Option<f64> {
    for &h in &[0.0, 0.05, 0.2, 0.5, 1.0] {
        let mut z = ZVec::zeros();
        let mut dz = ZVec::zeros();
        for k in 0..3 + r.n.min(MAX_WHEELS) {
            z[k] = r.z[k] + r.dz[k] * h + 0.5 * r.ddz[k] * h * h + r.dddz[k] * h * h * h / 6.0;
            dz[k] = r.dz[k] + r.ddz[k] * h + 0.5 * r.dddz[k] * h * h;
        }
        let tw = Twist {
            vx: dz[0],
            vy: dz[1],
            omega: dz[2],
        };
        let u = wheel_velocity_body(p, i, z[2], z[3 + i], &tw, dz[3 + i]);
        let sp = u[0].hypot(u[1]);
        let threshold = if h == 0.0 { REST_SPEED } else { 1e-6 };
        if sp.is_finite() && sp >= threshold {
            return Some(u[1].atan2(u[0]));
        }
    }
    None
}

/// Steering-only command turning every wheel toward the reference's initial angles (the
/// open-loop alignment phase of seed 000 Sect. IV, point 2); wheels do not roll. The rate
/// is `gains.steer_kp` × error, limited to `limits.steer_rate`. Returns the command and the
/// largest remaining angle error (rad). Wheels whose reference direction is undefined
/// (at rest for the whole look-ahead) keep their angle. A reference with a steering
/// reference ([`crate::types::SteerReference`]) gives the target angles itself.
pub fn alignment_command(
    p: &Platform,
    m: &Measurement,
    reference: &ReferenceSample,
) -> (Command, f64) {
    let n = p.n().min(m.n).min(MAX_WHEELS);
    let mut cmd = Command::zero(p.n().min(MAX_WHEELS));
    let mut worst: f64 = 0.0;
    for i in 0..n {
        // A source with a steering reference says where each wheel should point.
        let target = if reference.steer.valid {
            Some(reference.steer.angle[i])
        } else {
            reference_direction(p, reference, i)
        };
        let Some(target) = target else {
            continue;
        };
        let w = &p.wheels[i];
        if w.off_centred() {
            // An off-centred wheel is never steered at rest: it would scrub its contact
            // point sideways (crate::model, "Off-centred steering"); it turns as it rolls.
            continue;
        }
        let phi = m.wheels[i].steer_angle;
        let range = angle::SteerRange::of(w);
        let err = match range {
            None => angle::diff(target, phi),
            // Within a range: the turn of the target (or, with no steering reference, of the
            // opposite direction, rolling backwards) reachable within it, the nearer one.
            Some(_) if reference.steer.valid => angle::steer_error(range, target, phi),
            Some(_) => {
                let fwd = angle::steer_error(range, target, phi);
                let back = angle::steer_error(range, target + std::f64::consts::PI, phi);
                if back.abs() < fwd.abs() {
                    back
                } else {
                    fwd
                }
            }
        };
        if !err.is_finite() {
            continue;
        }
        worst = worst.max(err.abs());
        let lim = p.limits.steer_rate;
        cmd.wheels[i].steer_rate = (p.gains.steer_kp * err).clamp(-lim, lim);
    }
    (cmd, worst)
}

/// Decoupling matrix H and drift M of seed 000 eq. 23 (see the module docs), for
/// reference wheel `k`, posture angle `theta`, legs `legs`, reference-wheel angle `phi_k`
/// and compensator state η = (`v_w`, `omega`, `leg_rates`). Rows (x, y, θ, λ_1 … λ_n),
/// columns (u_W, u_ω, u_λ1 … u_λn, v_φk); the matrix is m × m with m = 3 + n, padded with
/// identity up to [`Z_MAX`].
#[allow(clippy::too_many_arguments)]
pub fn decoupling(
    p: &Platform,
    k: usize,
    theta: f64,
    legs: &[f64; MAX_WHEELS],
    phi_k: f64,
    v_w: f64,
    omega: f64,
    leg_rates: &[f64; MAX_WHEELS],
) -> (SMatrix<f64, Z_MAX, Z_MAX>, ZVec) {
    let n = p.n().min(MAX_WHEELS);
    let m = 3 + n;
    let mut h = SMatrix::<f64, Z_MAX, Z_MAX>::zeros();
    let mut mv = ZVec::zeros();
    let alpha = p.wheels.get(k).map(|w| w.alpha).unwrap_or(0.0);
    let (s, c) = (theta + phi_k).sin_cos();
    let (sa, ca) = (theta + alpha).sin_cos();
    let lk = legs[k];
    let vl = leg_rates[k];
    h[(0, 0)] = c;
    h[(0, 1)] = lk * sa;
    h[(0, 2 + k)] = -ca;
    h[(0, m - 1)] = -s * v_w;
    h[(1, 0)] = s;
    h[(1, 1)] = -lk * ca;
    h[(1, 2 + k)] = -sa;
    h[(1, m - 1)] = c * v_w;
    h[(2, 1)] = 1.0;
    // λ_i row: column of u_λi is 2 + i (u_W, u_ω, then legs), i = 0 … n−1
    for i in 0..n {
        h[(3 + i, 2 + i)] = 1.0;
    }
    for d in m..Z_MAX {
        h[(d, d)] = 1.0;
    }
    mv[0] = -s * v_w * omega + 2.0 * sa * omega * vl + lk * ca * omega * omega;
    mv[1] = c * v_w * omega - 2.0 * ca * omega * vl + lk * sa * omega * omega;
    (h, mv)
}

/// World-frame platform velocity (ẋ, ẏ) from eq. 20 with reference wheel k.
#[allow(clippy::too_many_arguments)]
fn model_velocity(
    p: &Platform,
    k: usize,
    theta: f64,
    lk: f64,
    phi_k: f64,
    v_w: f64,
    omega: f64,
    vl: f64,
) -> [f64; 2] {
    let alpha = p.wheels.get(k).map(|w| w.alpha).unwrap_or(0.0);
    let (s, c) = (theta + phi_k).sin_cos();
    let (sa, ca) = (theta + alpha).sin_cos();
    [
        c * v_w + lk * sa * omega - ca * vl,
        s * v_w - lk * ca * omega - sa * vl,
    ]
}

/// Controller 1: dynamic feedback linearization (seed 000 Sect. IV; module docs).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct DflController {
    k: usize,
    eta_w: f64,
    eta_omega: f64,
    eta_leg: [f64; MAX_WHEELS],
    started: bool,
    finished: bool,
}

impl DflController {
    /// A controller for platform `p`, at rest, reference wheel 0.
    pub fn new(p: &Platform) -> Self {
        let _ = p;
        Self {
            k: 0,
            eta_w: 0.0,
            eta_omega: 0.0,
            eta_leg: [0.0; MAX_WHEELS],
            started: false,
            finished: false,
        }
    }

    /// Initialise η from the reference at t0 (perfect matching condition, seed 000 Sect. IV):
    /// k = the fastest reference wheel, v_Wk = |u_k*| (wheel aligned with atan2(u_k*)),
    /// ω = θ̇*, v_λ = λ̇*. With a steering reference, v_Wk is the projection of u_k* on the
    /// reference's steering angle of wheel k (negative on the flipped branch).
    pub fn reset(&mut self, p: &Platform, reference: &ReferenceSample) {
        let n = p.n().min(MAX_WHEELS);
        let tw = reference.twist_world();
        let mut best = (0usize, -1.0);
        for i in 0..n {
            let u = wheel_velocity_body(
                p,
                i,
                reference.z[2],
                reference.z[3 + i],
                &tw,
                reference.dz[3 + i],
            );
            let sp = u[0].hypot(u[1]);
            if sp > best.1 {
                best = (i, sp);
            }
        }
        self.k = best.0;
        self.eta_w = if !best.1.is_finite() {
            0.0
        } else if reference.steer.valid {
            // The wheel's heading is the steering reference's angle, which may be the flipped
            // branch (after a reversal the wheel rolls backwards): η is the signed speed
            // along it.
            let u = wheel_velocity_body(
                p,
                best.0,
                reference.z[2],
                reference.z[3 + best.0],
                &tw,
                reference.dz[3 + best.0],
            );
            let a = reference.steer.angle[best.0];
            u[0] * a.cos() + u[1] * a.sin()
        } else {
            best.1.max(0.0)
        };
        self.eta_omega = if tw.omega.is_finite() { tw.omega } else { 0.0 };
        for i in 0..MAX_WHEELS {
            let v = if i < n { reference.dz[3 + i] } else { 0.0 };
            self.eta_leg[i] = if v.is_finite() { v } else { 0.0 };
        }
        self.started = false;
        self.finished = false;
    }

    /// Current compensator state η = (v_Wk, ω, v_λ) and the reference wheel k.
    pub fn eta(&self) -> (usize, f64, f64, [f64; MAX_WHEELS]) {
        (self.k, self.eta_w, self.eta_omega, self.eta_leg)
    }

    /// One cycle of seed 000 eqs. 24–25 (module docs).
    pub fn step(&mut self, p: &Platform, input: &ControlInput) -> ControlOutput {
        let n = p.n().min(MAX_WHEELS).min(input.measurement.n);
        let mut out = ControlOutput {
            command: Command::zero(p.n().min(MAX_WHEELS)),
            reference_wheel: self.k,
            ..ControlOutput::default()
        };
        let r = input.reference;
        let m = input.measurement;
        let dt = if input.dt.is_finite() && input.dt > 0.0 {
            input.dt
        } else {
            0.0
        };
        let g = &p.gains;
        let theta = input.pose.theta;
        let mut legs = [0.0; MAX_WHEELS];
        let mut phis = [0.0; MAX_WHEELS];
        for i in 0..n {
            legs[i] = m.wheels[i].leg;
            phis[i] = m.wheels[i].steer_angle;
        }
        let finite_in = theta.is_finite()
            && input.pose.x.is_finite()
            && input.pose.y.is_finite()
            && legs.iter().chain(phis.iter()).all(|v| v.is_finite())
            && r.z
                .iter()
                .chain(r.dz.iter())
                .chain(r.ddz.iter())
                .all(|v| v.is_finite());
        if !finite_in || n == 0 {
            out.singular = true;
            return out;
        }
        // Termination rule on the reference wheel speeds.
        let rtw = r.twist_world();
        let mut ref_max: f64 = 0.0;
        for i in 0..n {
            let u = wheel_velocity_body(p, i, r.z[2], r.z[3 + i], &rtw, r.dz[3 + i]);
            ref_max = ref_max.max(u[0].hypot(u[1]));
        }
        if ref_max >= EPSILON {
            self.started = true;
        } else if self.started {
            self.finished = true;
        }
        if self.finished || !self.started {
            out.finished = self.finished;
            out.singular = !self.started;
            return out;
        }

        // Model velocity and wheel speeds; reference-wheel handover.
        let tw_model = |k: usize, vw: f64, om: f64, el: &[f64; MAX_WHEELS]| {
            let v = model_velocity(p, k, theta, legs[k], phis[k], vw, om, el[k]);
            Twist {
                vx: v[0],
                vy: v[1],
                omega: om,
            }
        };
        let tw = tw_model(self.k, self.eta_w, self.eta_omega, &self.eta_leg);
        let mut speeds = [0.0; MAX_WHEELS];
        let mut best = self.k;
        for i in 0..n {
            let u = wheel_velocity_body(p, i, theta, legs[i], &tw, self.eta_leg[i]);
            speeds[i] = u[0].hypot(u[1]);
            if speeds[i] > speeds[best] {
                best = i;
            }
        }
        if best != self.k && speeds[best] > SWITCH_RATIO * speeds[self.k] {
            let u = wheel_velocity_body(p, best, theta, legs[best], &tw, self.eta_leg[best]);
            self.eta_w = u[0] * phis[best].cos() + u[1] * phis[best].sin();
            self.k = best;
        }
        let k = self.k;
        out.reference_wheel = k;
        let tw = tw_model(k, self.eta_w, self.eta_omega, &self.eta_leg);

        // Outer loop v = z̈* + K_D ė + K_P e.
        let mut e = ZVec::zeros();
        let mut de = ZVec::zeros();
        e[0] = r.z[0] - input.pose.x;
        e[1] = r.z[1] - input.pose.y;
        e[2] = angle::diff(r.z[2], theta);
        match input.measured_twist {
            Some(mt) if mt.vx.is_finite() && mt.vy.is_finite() && mt.omega.is_finite() => {
                de[0] = r.dz[0] - mt.vx;
                de[1] = r.dz[1] - mt.vy;
                de[2] = r.dz[2] - mt.omega;
                for i in 0..n {
                    e[3 + i] = r.z[3 + i] - legs[i];
                    de[3 + i] = r.dz[3 + i] - m.wheels[i].leg_rate;
                }
            }
            _ => {
                de[0] = r.dz[0] - tw.vx;
                de[1] = r.dz[1] - tw.vy;
                de[2] = r.dz[2] - tw.omega;
                for i in 0..n {
                    e[3 + i] = r.z[3 + i] - legs[i];
                    de[3 + i] = r.dz[3 + i] - self.eta_leg[i];
                }
            }
        }
        let v: ZVec = r.ddz + de * g.dfl_kd + e * g.dfl_kp;

        // u = H⁻¹ (v − M) in closed form.
        let alpha = p.wheels[k].alpha;
        let (s, c) = (theta + phis[k]).sin_cos();
        let (sa, ca) = (theta + alpha).sin_cos();
        let (lk, vl, om, vw) = (legs[k], self.eta_leg[k], self.eta_omega, self.eta_w);
        let mx = -s * vw * om + 2.0 * sa * om * vl + lk * ca * om * om;
        let my = c * vw * om - 2.0 * ca * om * vl + lk * sa * om * om;
        let u_om = v[2];
        let mut u_leg = [0.0; MAX_WHEELS];
        for i in 0..n {
            u_leg[i] = v[3 + i];
        }
        let bx = v[0] - mx - lk * sa * u_om + ca * u_leg[k];
        let by = v[1] - my + lk * ca * u_om + sa * u_leg[k];
        let u_w = c * bx + s * by;
        let singular = vw.abs() < 1e-4;
        if singular && ref_max < 5.0 * EPSILON {
            // The compensator's reference wheel reached rest while the reference itself is
            // within 5ε of rest: the final approach of a rest-to-rest move (with measured
            // velocity feedback η may settle a few cycles before the reference does). This is
            // the termination of seed 000, not singularity A: report it as finished so the
            // runtime hands the last millimetres to a controller that can stop at rest.
            self.finished = true;
            out.finished = true;
            return out;
        }
        let v_phi_k = if singular {
            0.0
        } else {
            (-s * bx + c * by) / vw
        };
        out.singular = singular;

        // Integrate η (midpoint value commanded over the cycle).
        let h = 0.5 * dt;
        let eta_leg_old = self.eta_leg;
        let eta_w_mid = vw + u_w * h;
        let om_mid = om + u_om * h;
        let mut leg_mid = [0.0; MAX_WHEELS];
        for i in 0..n {
            leg_mid[i] = eta_leg_old[i] + u_leg[i] * h;
        }
        self.eta_w += u_w * dt;
        self.eta_omega += u_om * dt;
        for i in 0..n {
            self.eta_leg[i] += u_leg[i] * dt;
        }

        // Commands: wheel k from η, the others by eq. 22 with steering feedback.
        let r_w = p.wheel_radius;
        out.command.wheels[k].wheel_speed = eta_w_mid / r_w;
        out.command.wheels[k].steer_rate = v_phi_k;
        let phi_k_mid = phis[k] + v_phi_k * h;
        let vmid = model_velocity(
            p,
            k,
            theta + om * h,
            lk + vl * h,
            phi_k_mid,
            eta_w_mid,
            om_mid,
            leg_mid[k],
        );
        let tw_mid = Twist {
            vx: vmid[0],
            vy: vmid[1],
            omega: om_mid,
        };
        let acc = [v[0], v[1], v[2]];
        let vel = [tw.vx, tw.vy, tw.omega];
        let held = held_wheels(p, r);
        let weight = steer_weights(p, r);
        let mut min_speed = f64::INFINITY;
        for j in 0..n {
            let u0 = wheel_velocity_body(p, j, theta, legs[j], &tw, eta_leg_old[j]);
            min_speed = min_speed.min(u0[0].hypot(u0[1]));
            if j == k {
                continue;
            }
            let du =
                wheel_acceleration_body(p, j, theta, legs[j], eta_leg_old[j], u_leg[j], vel, acc);
            let rate = if held[j] {
                held_steer_rate(p, r, j, phis[j])
            } else {
                let range = angle::SteerRange::of(&p.wheels[j]);
                let own = coordinated_steer_in(range, u0, du, phis[j], g.steer_kp).0;
                let wj = weight[j];
                if wj < 1.0 {
                    wj * own + (1.0 - wj) * held_steer_rate(p, r, j, phis[j])
                } else {
                    own
                }
            };
            let phi_mid = phis[j] + rate * h;
            let um = wheel_velocity_body(
                p,
                j,
                theta + om * h,
                legs[j] + eta_leg_old[j] * h,
                &tw_mid,
                leg_mid[j],
            );
            let roll = um[0] * phi_mid.cos() + um[1] * phi_mid.sin();
            out.command.wheels[j].wheel_speed = roll / r_w;
            out.command.wheels[j].steer_rate = rate;
        }
        out.min_wheel_speed = min_speed;
        let ratio = limit_ratio(p, &out.command, &leg_mid[..n]);
        out.limit_ratio = ratio;
        out.saturated = desaturate(&mut out.command, ratio);
        out
    }
}

/// Steering of a coordinated wheel from its model contact velocity `u` and acceleration
/// `du` and its measured angle: returns (steering-rate command, signed rolling speed
/// along the chosen branch). The branch atan2(u) or atan2(u) + π nearest the measured angle
/// is taken; below [`REST_SPEED`] the wheel holds its angle.
pub fn coordinated_steer(u: [f64; 2], du: [f64; 2], phi_meas: f64, kp: f64) -> (f64, f64) {
    let sp = u[0].hypot(u[1]);
    if sp.is_nan() || sp < REST_SPEED {
        return (0.0, 0.0);
    }
    let w = steer_from_velocity(u, du);
    let mut target = w.steer_angle;
    let mut speed = w.rolling_speed;
    if angle::diff(target, phi_meas).abs() > std::f64::consts::FRAC_PI_2 {
        target = angle::wrap(target + std::f64::consts::PI);
        speed = -speed;
    }
    (w.steer_rate + kp * angle::diff(target, phi_meas), speed)
}

/// [`coordinated_steer`] for a wheel with a steering range: of the two branches the one
/// whose turn inside the range is nearer the measured angle (an endless wheel: exactly
/// [`coordinated_steer`]).
pub fn coordinated_steer_in(
    range: Option<angle::SteerRange>,
    u: [f64; 2],
    du: [f64; 2],
    phi_meas: f64,
    kp: f64,
) -> (f64, f64) {
    let Some(rg) = range else {
        return coordinated_steer(u, du, phi_meas, kp);
    };
    let sp = u[0].hypot(u[1]);
    if sp.is_nan() || sp < REST_SPEED {
        return (0.0, 0.0);
    }
    let w = steer_from_velocity(u, du);
    let fwd = angle::steer_error(Some(rg), w.steer_angle, phi_meas);
    let back = angle::steer_error(Some(rg), w.steer_angle + std::f64::consts::PI, phi_meas);
    let (e, speed) = if back.abs() < fwd.abs() {
        (back, -w.rolling_speed)
    } else {
        (fwd, w.rolling_speed)
    };
    (w.steer_rate + kp * e, speed)
}

impl TrackingController for DflController {
    fn reset(&mut self, p: &Platform, reference: &ReferenceSample) {
        DflController::reset(self, p, reference)
    }
    fn step(&mut self, p: &Platform, input: &ControlInput) -> ControlOutput {
        DflController::step(self, p, input)
    }
    fn name(&self) -> &'static str {
        "dfl"
    }
}

/// Lockstep closed-loop harness shared by the controller tests.
#[cfg(test)]
pub(crate) mod harness {
    use super::*;
    use crate::ideal_plant::IdealPlant;
    use crate::odometry::Odometry;
    use crate::trajectory::Trajectory;

    /// Measured numbers of one closed-loop run.
    #[derive(Clone, Copy, Debug, Default)]
    pub(crate) struct RunStats {
        pub max_pos: f64,
        pub max_head: f64,
        pub max_leg: f64,
        pub final_pos: f64,
        pub final_head: f64,
        pub final_leg: f64,
        pub max_ratio: f64,
        pub saturated: bool,
        pub max_steer_rate: f64,
        pub max_steer_jump: f64,
        pub max_wheel_speed: f64,
        pub finished_at: Option<f64>,
        pub align_time: f64,
        pub switches: usize,
        pub singular_cycles: usize,
        pub final_command_max: f64,
    }

    /// Aligns (open loop), resets `ctrl`, then tracks `traj` against an [`IdealPlant`] at
    /// the platform's cycle rate with odometry in the loop, for the trajectory duration
    /// plus `extra` seconds or until the controller finishes.
    pub(crate) fn run(
        ctrl: &mut dyn TrackingController,
        p: &Platform,
        traj: &dyn Trajectory,
        extra: f64,
    ) -> RunStats {
        let dt = p.dt();
        let n = p.n();
        let r0 = traj.sample(0.0);
        let legs: Vec<f64> = (0..n).map(|i| r0.z[3 + i]).collect();
        let mut plant = IdealPlant::new(p, r0.pose(), &legs, &vec![0.0; n]);
        let mut st = RunStats::default();
        // alignment phase
        for k in 0..2500 {
            let (cmd, err) = alignment_command(p, &plant.measurement(), &r0);
            if err < 1e-6 {
                st.align_time = k as f64 * dt;
                break;
            }
            plant.step(p, &cmd, dt);
        }
        let mut odo =
            Odometry::with_sampling(plant.pose(), crate::odometry::Sampling::ZeroOrderHold);
        ctrl.reset(p, &r0);
        let steps = ((traj.duration() + extra) / dt).ceil() as usize;
        let mut prev_rates = [0.0; MAX_WHEELS];
        let mut prev_k = usize::MAX;
        let mut last = ControlOutput::default();
        for s in 0..=steps {
            let t = s as f64 * dt;
            let r = traj.sample(t);
            let m = plant.measurement();
            let q = plant.pose();
            let tl = plant.legs();
            st.max_pos = st.max_pos.max((r.z[0] - q.x).hypot(r.z[1] - q.y));
            st.max_head = st.max_head.max(angle::diff(r.z[2], q.theta).abs());
            for i in 0..n {
                st.max_leg = st.max_leg.max((r.z[3 + i] - tl[i]).abs());
            }
            let out = ctrl.step(
                p,
                &ControlInput {
                    measured_twist: None,
                    t,
                    dt,
                    measurement: &m,
                    pose: odo.pose(),
                    reference: &r,
                },
            );
            last = out;
            if out.finished {
                st.finished_at = Some(t);
                break;
            }
            if prev_k != usize::MAX && out.reference_wheel != prev_k {
                st.switches += 1;
            }
            prev_k = out.reference_wheel;
            st.singular_cycles += usize::from(out.singular);
            st.max_ratio = st.max_ratio.max(out.limit_ratio);
            st.saturated |= out.saturated;
            for i in 0..n {
                let w = out.command.wheels[i];
                st.max_steer_rate = st.max_steer_rate.max(w.steer_rate.abs());
                st.max_wheel_speed = st.max_wheel_speed.max(w.wheel_speed.abs());
                if s > 0 {
                    st.max_steer_jump = st.max_steer_jump.max((w.steer_rate - prev_rates[i]).abs());
                }
                prev_rates[i] = w.steer_rate;
            }
            plant.step(p, &out.command, dt);
            odo.update(p, &plant.measurement(), dt);
        }
        st.final_command_max = last
            .command
            .wheels
            .iter()
            .map(|w| w.wheel_speed.abs())
            .fold(0.0, f64::max);
        let goal = traj.sample(traj.duration());
        let q = plant.pose();
        st.final_pos = (goal.z[0] - q.x).hypot(goal.z[1] - q.y);
        st.final_head = angle::diff(goal.z[2], q.theta).abs();
        let tl = plant.legs();
        for i in 0..n {
            st.final_leg = st.final_leg.max((goal.z[3 + i] - tl[i]).abs());
        }
        st
    }
}

#[cfg(test)]
mod tests {
    use super::harness::run;
    use super::*;
    use crate::model::wheel_setpoints;
    use crate::trajectory::{seed000_experiment, Trajectory};

    fn sample_state() -> (Platform, [f64; MAX_WHEELS], [f64; MAX_WHEELS]) {
        let p = Platform::justin();
        let mut legs = [0.0; MAX_WHEELS];
        let mut rates = [0.0; MAX_WHEELS];
        for i in 0..4 {
            legs[i] = 0.4 + 0.03 * i as f64;
            rates[i] = 0.02 - 0.015 * i as f64;
        }
        (p, legs, rates)
    }

    #[test]
    fn det_h_is_signed_wheel_speed() {
        let (p, legs, rates) = sample_state();
        for &(k, th, phi, vw, om) in &[
            (0usize, 0.3, 1.1, 0.25, 0.4),
            (2, -2.0, -0.4, -0.7, -0.2),
            (3, 5.0, 3.0, 1e-3, 1.3),
            (1, 0.0, 0.0, 0.0, 0.5),
        ] {
            let (h, _) = decoupling(&p, k, th, &legs, phi, vw, om, &rates);
            let det = h.determinant();
            // n = 4: det H = (−1)^(n+1) v_Wk = −v_Wk
            assert!((det + vw).abs() < 1e-12, "k={k} det {det} vs −{vw}");
        }
        let mut p3 = Platform::justin();
        p3.wheels.truncate(3);
        let (h, _) = decoupling(&p3, 1, 0.2, &legs, 0.5, 0.3, 0.1, &rates);
        assert!(
            (h.determinant() - 0.3).abs() < 1e-12,
            "n = 3: det H = +v_Wk"
        );
    }

    /// Integrates the extended system q_e' = f(q_e, u) (eq. 20 with η̇ = u, φ̇_k = v_φk) with
    /// RK4 for constant u and compares the finite-difference z̈ with H u + M.
    #[test]
    fn z_ddot_equals_h_u_plus_m_against_simulated_motion() {
        let (p, legs0, rates0) = sample_state();
        let k = 1;
        let u_in = [0.07, -0.2, 0.01, -0.02, 0.03, 0.005, 0.4]; // u_W, u_ω, u_λ1..4, v_φk
                                                                // state: x, y, θ, λ1..4, φ_k, v_W, ω, v_λ1..4
        type S = [f64; 15];
        let f = |s: &S| -> S {
            let mut legs = [0.0; MAX_WHEELS];
            legs[..4].copy_from_slice(&s[3..7]);
            let v = model_velocity(&p, k, s[2], legs[k], s[7], s[8], s[9], s[10 + k]);
            let mut d = [0.0; 15];
            d[0] = v[0];
            d[1] = v[1];
            d[2] = s[9];
            d[3..7].copy_from_slice(&s[10..14]);
            d[7] = u_in[6];
            d[8] = u_in[0];
            d[9] = u_in[1];
            d[10..14].copy_from_slice(&u_in[2..6]);
            d
        };
        let mut s: S = [0.0; 15];
        s[0] = 0.5;
        s[1] = -0.3;
        s[2] = 0.7;
        s[3..7].copy_from_slice(&legs0[..4]);
        s[7] = 0.9;
        s[8] = 0.3;
        s[9] = 0.25;
        s[10..14].copy_from_slice(&rates0[..4]);
        let rk4 = |s: &S, h: f64| -> S {
            let add = |a: &S, b: &S, c: f64| {
                let mut o = *a;
                for i in 0..15 {
                    o[i] += c * b[i];
                }
                o
            };
            let k1 = f(s);
            let k2 = f(&add(s, &k1, h / 2.0));
            let k3 = f(&add(s, &k2, h / 2.0));
            let k4 = f(&add(s, &k3, h));
            let mut o = *s;
            for i in 0..15 {
                o[i] += h / 6.0 * (k1[i] + 2.0 * k2[i] + 2.0 * k3[i] + k4[i]);
            }
            o
        };
        let h = 1e-3;
        let sp = rk4(&s, h);
        let sm = rk4(&s, -h);
        let mut legs = [0.0; MAX_WHEELS];
        legs[..4].copy_from_slice(&s[3..7]);
        let mut rates = [0.0; MAX_WHEELS];
        rates[..4].copy_from_slice(&s[10..14]);
        let (hm, m) = decoupling(&p, k, s[2], &legs, s[7], s[8], s[9], &rates);
        let mut u = ZVec::zeros();
        u[0] = u_in[0];
        u[1] = u_in[1];
        for i in 0..4 {
            u[2 + i] = u_in[2 + i];
        }
        u[6] = u_in[6];
        let zdd = hm * u + m;
        for (c, idx) in [(0usize, 0usize), (1, 1), (2, 2), (3, 3), (6, 6)] {
            let fd = (sp[idx] - 2.0 * s[idx] + sm[idx]) / (h * h);
            assert!(
                (fd - zdd[c]).abs() < 1e-5,
                "component {c}: fd {fd} vs model {}",
                zdd[c]
            );
        }
        // and the closed-form inverse used by the controller equals H⁻¹ (v − M)
        let lu = hm.lu();
        let back = lu.solve(&(zdd - m)).unwrap();
        for i in 0..7 {
            assert!((back[i] - u[i]).abs() < 1e-10);
        }
    }

    /// Eq. 20 against the ideal plant: wheels commanded consistently with (v_Wk, ω, v_λ)
    /// move the platform with the model's ż.
    #[test]
    fn eq20_matches_the_plant() {
        use crate::ideal_plant::IdealPlant;
        let (p, legs, rates) = sample_state();
        let k = 0;
        let theta = 0.4;
        let phi_k = 0.8;
        let (vw, om) = (0.2, 0.3);
        let v = model_velocity(&p, k, theta, legs[k], phi_k, vw, om, rates[k]);
        let tw = Twist {
            vx: v[0],
            vy: v[1],
            omega: om,
        };
        let mut steer = [0.0; 4];
        let mut cmd = Command::zero(4);
        for i in 0..4 {
            let u = wheel_velocity_body(&p, i, theta, legs[i], &tw, rates[i]);
            steer[i] = u[1].atan2(u[0]);
            cmd.wheels[i].wheel_speed = u[0].hypot(u[1]) / p.wheel_radius;
        }
        assert!((steer[0] - phi_k).abs() < 1e-12, "wheel k rolls along φ_k");
        let pose = Pose {
            x: 0.0,
            y: 0.0,
            theta,
        };
        let mut plant = IdealPlant::new(&p, pose, &legs[..4], &steer);
        let h = 1e-4;
        plant.step(&p, &cmd, h);
        let q = plant.pose();
        assert!(((q.x - 0.0) / h - v[0]).abs() < 1e-4);
        assert!(((q.y - 0.0) / h - v[1]).abs() < 1e-4);
        assert!(((q.theta - theta) / h - om).abs() < 1e-4);
        for i in 0..4 {
            assert!(((plant.legs()[i] - legs[i]) / h - rates[i]).abs() < 1e-6);
        }
    }

    /// Largest |φ̇*| of the reference's own inverse kinematics (analytic steering rates).
    pub(crate) fn reference_max_steer_rate(p: &Platform, traj: &dyn Trajectory) -> f64 {
        let mut mx: f64 = 0.0;
        let steps = (traj.duration() / p.dt()) as usize;
        for s in 0..steps {
            let r = traj.sample(s as f64 * p.dt());
            if let Ok(w) = wheel_setpoints(p, &r.z, &r.dz, &r.ddz, 1e-3) {
                for x in w.iter().take(p.n()) {
                    mx = mx.max(x.steer_rate.abs());
                }
            }
        }
        mx
    }

    #[test]
    fn dfl_tracks_the_seed000_experiment() {
        let p = Platform::justin();
        let traj = seed000_experiment(&p);
        let mut c = DflController::new(&p);
        let st = run(&mut c, &p, &traj, 1.0);
        let ref_rate = reference_max_steer_rate(&p, &traj);
        eprintln!("DFL seed-000 run: {st:#?}\nreference max steering rate {ref_rate} rad/s");
        let t_end = st
            .finished_at
            .expect("termination rule must fire near the end");
        assert!(t_end > traj.duration() - 0.5 && t_end < traj.duration());
        assert!(st.max_pos < 1e-3, "max position error {} m", st.max_pos);
        assert!(
            st.max_head < 0.1f64.to_radians(),
            "max heading error {} rad",
            st.max_head
        );
        assert!(st.max_leg < 1e-3, "max leg error {} m", st.max_leg);
        // Final error w.r.t. the goal: the paper's termination rule (stop once
        // |v_W*| < ε) leaves the reference's remaining distance untravelled.
        let stop = traj.sample(t_end);
        let goal = traj.sample(traj.duration());
        let remaining = (goal.z[0] - stop.z[0]).hypot(goal.z[1] - stop.z[1]);
        eprintln!("reference distance left at termination: {remaining} m");
        assert!(
            st.final_pos < remaining + 1e-3,
            "final position error {} m",
            st.final_pos
        );
        assert!(st.final_head < 0.1f64.to_radians());
        assert!(st.final_leg < 1e-3);
        assert!(
            st.max_ratio <= 1.0 && !st.saturated,
            "limit ratio {}",
            st.max_ratio
        );
        assert!(
            st.max_steer_rate < 1.1 * ref_rate,
            "steering rate {} vs reference {ref_rate}",
            st.max_steer_rate
        );
        assert!(
            st.max_steer_jump < 0.05,
            "steering-rate spike {}",
            st.max_steer_jump
        );
        assert_eq!(st.singular_cycles, 0);
        assert_eq!(st.final_command_max, 0.0);
    }

    /// Translation along leg 1's direction while leg 1 retracts faster than the platform
    /// moves: wheel 1's contact velocity (V + λ̇_1) e_1 passes through zero twice while the
    /// platform keeps moving (seed 000 Sect. V's example of a wheel at rest).
    struct WheelOneStops {
        p: Platform,
    }

    const V: f64 = 0.1;
    const A: f64 = 0.15;
    const T: f64 = 2.0;

    impl Trajectory for WheelOneStops {
        fn sample(&self, t: f64) -> ReferenceSample {
            let a1 = self.p.wheels[0].alpha;
            let mut r = ReferenceSample {
                t,
                n: 4,
                ..Default::default()
            };
            r.z[0] = V * a1.cos() * t;
            r.z[1] = V * a1.sin() * t;
            r.dz[0] = V * a1.cos();
            r.dz[1] = V * a1.sin();
            let w = std::f64::consts::PI / T;
            let tc = t.clamp(0.0, T);
            r.z[3] = 0.55 - A * (tc / 2.0 - (2.0 * w * tc).sin() / (4.0 * w));
            if t < T {
                r.dz[3] = -A * (w * t).sin().powi(2);
                r.ddz[3] = -A * w * (2.0 * w * t).sin();
                r.dddz[3] = -2.0 * A * w * w * (2.0 * w * t).cos();
            }
            for i in 1..4 {
                r.z[3 + i] = 0.45;
            }
            r
        }
        fn duration(&self) -> f64 {
            T
        }
        fn n_legs(&self) -> usize {
            4
        }
    }

    #[test]
    fn dfl_survives_wheel_one_stopping() {
        let p = Platform::justin();
        let traj = WheelOneStops { p: p.clone() };
        // the reference really stops wheel 1 (twice) while the others keep rolling
        let mut min1 = f64::INFINITY;
        let mut min_other = f64::INFINITY;
        for s in 0..=500 {
            let r = traj.sample(s as f64 * T / 500.0);
            let tw = r.twist_world();
            for i in 0..4 {
                let u = wheel_velocity_body(&p, i, r.z[2], r.z[3 + i], &tw, r.dz[3 + i]);
                if i == 0 {
                    min1 = min1.min(u[0].hypot(u[1]));
                } else {
                    min_other = min_other.min(u[0].hypot(u[1]));
                }
            }
        }
        assert!(
            min1 < 1e-3 && min_other > 0.05,
            "wheel 1 min {min1}, others {min_other}"
        );
        let mut c = DflController::new(&p);
        let st = run(&mut c, &p, &traj, 0.0);
        eprintln!("DFL wheel-1-stops run: {st:#?}");
        assert!(
            st.finished_at.is_none(),
            "must not stop while the platform moves"
        );
        assert!(st.switches >= 1, "the reference wheel must leave wheel 1");
        assert_eq!(st.singular_cycles, 0);
        assert!(st.max_pos < 1e-3, "max position error {}", st.max_pos);
        assert!(
            st.max_head < 0.1f64.to_radians(),
            "max heading error {}",
            st.max_head
        );
        assert!(st.max_leg < 1e-3, "max leg error {}", st.max_leg);
        assert!(st.max_ratio <= 1.0, "limit ratio {}", st.max_ratio);
        assert!(
            st.max_steer_rate < 0.5,
            "steering rate {}",
            st.max_steer_rate
        );
    }
}
