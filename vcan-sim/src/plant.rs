//! The platform plant: wheel-module motors, encoders, passive legs and the body they move.
//!
//! Pure and deterministic: the state changes only in [`Plant::step`], time is the sum of the
//! `dt`s passed in, and all randomness (encoder noise) comes from a
//! [`rollbase_driver::rng::Rng`] seeded in [`Plant::new`]. No IO, no clock, no allocation after
//! construction (all per-wheel data lives in `[_; MAX_WHEELS]` arrays).
//!
//! This model is deliberately written independently of `rollbase_control::model` and
//! `rollbase_control::odometry`, so that it can check them.
//!
//! # Motors
//!
//! Each wheel module has a drive (rolling) and a steer motor, both velocity-controlled
//! brushless drives (seed 000, Sect. II: "low-level onboard controllers are able to realize a
//! given rolling and steering velocity"). Each is a first-order lag towards its (speed-limited)
//! setpoint, `ẋ = (x* − x)/T`, discretised exactly over a step (`Δx = (x* − x)(1 − e^{−dt/T})`),
//! with the change per step clamped to `a_max·dt` (the acceleration the torque limit allows).
//! A disabled motor (module not enabled, watchdog, fault) decelerates to zero at `a_max`.
//!
//! ## Torque-limited wheel acceleration (derivation)
//!
//! The legs are passive and the platform is heavy compared with the wheels (seed 000,
//! Sect. III-B: ~150 kg, very low leg friction), so each wheel accelerates "its share" of the
//! platform mass, `m/n`. A rolling torque `τ_d` at the wheel gives a ground force `F = τ_d / r`,
//! hence a linear acceleration `a = F / (m/n) = n τ_d / (m r)` and a wheel spin acceleration
//! `ω̇_max = a / r = n τ_d / (m r²)`. Equivalently the wheel sees the reflected inertia
//! `J_d = (m/n) r²`. Justin-like numbers: `4 · 30 / (150 · 0.085²) ≈ 110.7 rad/s²`
//! (`≈ 9.4 m/s²` at the ground, about 1 g, i.e. roughly where the tyres would slip anyway).
//! The wheel's and rotor's own inertia are neglected next to the platform share.
//!
//! ## Steering acceleration
//!
//! `φ̈_max = τ_s / J_s` with a configurable effective steering inertia `J_s` (default
//! 0.5 kg·m², i.e. 28 / 0.5 = 56 rad/s²).
//!
//! ## Motor currents
//!
//! Reported currents are `τ / k_t` with `τ = J a + τ_rr sign(ω)` (drive, `τ_rr = c_rr (m/n) g r`
//! rolling resistance) and `τ = J_s φ̈` (steer), each clamped to the torque limit.
//!
//! # Platform motion (least squares over the wheel contacts)
//!
//! Wheel i sits at `P_i = λ_i (cos α_i, sin α_i)` in the body frame (seed 000, eq. 2 with the
//! polar leg parameterisation of Sect. III-B). A centred steering wheel rolling at `v_i = r ω_i`
//! with plane angle `φ_i` imposes the velocity of its contact point, in the body frame:
//!
//! ```text
//! u_i = (vx − ω λ_i sin α_i + λ̇_i cos α_i,  vy + ω λ_i cos α_i + λ̇_i sin α_i) = v_i (cos φ_i, sin φ_i)
//! ```
//!
//! (the perfect-rolling constraint (1)/(17) of seed 000 plus the rolling speed). Over all
//! wheels that is 2n equations in the 3 + n unknowns `(vx, vy, ω, λ̇_1 … λ̇_n)`; it is solved in
//! least squares and the residual is the slip.
//!
//! ## Eliminating the leg rates (derivation)
//!
//! Write `e_r,i = (cos α_i, sin α_i)` (leg direction) and `e_t,i = (−sin α_i, cos α_i)`. The body
//! part of `u_i` is `(vx, vy) + ω λ_i e_t,i`; `λ̇_i` enters only wheel i's two equations and only
//! along `e_r,i`. Projecting wheel i's equations on the orthonormal pair `(e_r,i, e_t,i)`:
//!
//! ```text
//! radial:      cos α_i vx + sin α_i vy + λ̇_i               = e_r,i · c_i
//! tangential: −sin α_i vx + cos α_i vy + λ_i ω              = e_t,i · c_i
//! ```
//!
//! with `c_i = v_i (cos φ_i, sin φ_i)`. Projection on an orthonormal basis preserves the
//! squared residual, and for any twist the radial equation is met exactly by
//! `λ̇_i = e_r,i · c_i − (cos α_i vx + sin α_i vy)`. So the least-squares twist minimises the sum
//! of the squared *tangential* residuals only: a 3-unknown problem with normal matrix
//! `N = Σ g_i g_iᵀ`, `g_i = (−sin α_i, cos α_i, λ_i)`, right-hand side `Σ g_i (e_t,i · c_i)`.
//! (For a free leg this is exactly seed 000's statement that "each leg is an independent linear
//! joint actuated by its own wheel": the radial rolling component only moves the leg.)
//!
//! A leg held at an end stop has `λ̇_i = 0`, so both of its equations constrain the twist: rows
//! `(1, 0, −λ_i sin α_i)` and `(0, 1, λ_i cos α_i)` with right-hand sides `c_i`. The 3 × 3 normal
//! system is solved with a symmetric eigen-decomposition (pseudo-inverse, so a 2-wheel platform
//! with free legs, whose twist is under-determined, gets the minimum-norm twist).
//!
//! ## End stops (active set)
//!
//! Each step starts with all legs free. A leg at `λ_max` whose solved `λ̇` points outwards (or at
//! `λ_min` pointing inwards) is blocked and the system re-solved; a blocked leg stays blocked for
//! the rest of that solve, so this terminates in at most n re-solves. A free leg that reaches a
//! stop inside a step splits the step: integrate up to the contact time, set λ exactly to the
//! stop, re-solve for the remainder.
//!
//! ## Integration
//!
//! Within a segment the body twist is constant, so the pose is integrated exactly on SE(2):
//! `Δp_body = [[sin a, −(1 − cos a)], [1 − cos a, sin a]] (vx, vy) / ω`, `a = ω Δt`, rotated by θ
//! into the world, `Δθ = a` (series expansion for |a| < 1e-6). Motor speeds and steering angles
//! use the average over the step (trapezoid), legs move linearly.
//!
//! # Wheels without legs, off-centred wheels, steering stops, polarity, coupling
//!
//! A wheel without a leg is a leg held at both stops at once (λ_min = λ_max): both of its
//! equations constrain the twist, always.
//!
//! An off-centred wheel (caster offset d > 0) touches the ground at C_i = P_i − d h_i
//! (h = (cos φ, sin φ)), and what it imposes is the body's velocity at C_i: its rolling
//! velocity plus the sweep of its steering, c_i = v_i h_i + d φ̇_i h⊥_i (the contact point
//! itself, moving on the body, must not slip). The equations above then hold at C_i instead
//! of P_i: the tangential row is g_i = (−sin α_i, cos α_i, e_r,i · C_i), the radial equation
//! carries ω (sin α_i C_ix − cos α_i C_iy), a blocked leg's rows are (1, 0, −C_iy) and
//! (0, 1, C_ix). A wheel steered at rest thus pushes the body (and slips): the model of the
//! scrub the controller avoids. This model is independent of `rollbase_control::model`'s.
//!
//! A wheel with a steering range has mechanical stops: the steering angle stops at them
//! (and the steering motor with it); every step that presses a stop is counted
//! ([`PlantTruth::steer_stop_hits`]).
//!
//! Motors mounted mirrored (`drive_polarity`, `steer_polarity` = −1) turn the wheel the other
//! way round than their own positive direction; a coupled module (`coupling` c) turns the
//! wheel by c·Δφ when only the steering turns: the wheel spins at ω = p_d ω_motor + c φ̇.
//! Setpoints are the motors' and so are the encoders (the steering encoder sits on the
//! steering motor's side: it reads p_s φ); [`PlantTruth`] holds the joints' true values.
//!
//! # Encoders
//!
//! Per module: absolute steering angle (wrapped to (−π, π] by `rollbase_control::angle::wrap`),
//! steer rate, wheel speed, leg extension and leg rate, each with configurable quantization and
//! Gaussian noise, sampled after every step and delivered `latency_samples` steps late.

use crate::error::{invalid, read_file, SimError};
use nalgebra::{Matrix3, SymmetricEigen, Vector3};
use rollbase_control::{angle, Platform, Pose, ReferenceSample, Twist, MAX_WHEELS};
use rollbase_driver::rng::Rng;
use serde::{Deserialize, Serialize};
use std::path::Path;

/// Largest encoder latency (in plant steps) a [`PlantConfig`] may ask for.
pub const MAX_LATENCY_SAMPLES: usize = 8;

/// Largest drive gain a [`PlantConfig`] or a fault may ask for.
pub const MAX_DRIVE_GAIN: f64 = 2.0;

/// Standard gravity (m/s²), for the rolling resistance.
const GRAVITY: f64 = 9.81;

/// Tolerance (m) within which a leg counts as touching an end stop.
const STOP_EPS: f64 = 1e-9;

/// Plant parameters that are not part of the platform description: motor dynamics, encoder
/// resolution, noise and latency. Loadable from TOML; every field has a default, so a file
/// needs to list only what it changes. Unknown keys are rejected.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct PlantConfig {
    /// Drive (rolling) motor velocity-loop time constant (s). Default 0.020.
    pub drive_time_constant: f64,
    /// Steer motor velocity-loop time constant (s). Default 0.015.
    pub steer_time_constant: f64,
    /// Effective steering inertia about the steering axis (kg·m²). Default 0.5.
    pub steer_inertia: f64,
    /// Wheel spin acceleration limit (rad/s²); absent = derived from the rolling torque,
    /// `n τ_d / (m r²)` (see the module docs).
    pub drive_accel_limit: Option<f64>,
    /// Steering acceleration limit (rad/s²); absent = `steer_torque / steer_inertia`.
    pub steer_accel_limit: Option<f64>,
    /// Wheel spin speed limit (rad/s); absent = the platform's `limits.wheel_speed`.
    pub drive_speed_limit: Option<f64>,
    /// Steering rate limit (rad/s); absent = the platform's `limits.steer_rate`.
    pub steer_rate_limit: Option<f64>,
    /// Rolling-resistance coefficient c_rr (dimensionless), only used for the drive current.
    /// Default 0.01.
    pub rolling_resistance: f64,
    /// Drive torque constant at the wheel (N·m/A), for the reported current. Default 1.2.
    pub drive_torque_constant: f64,
    /// Steer torque constant at the steering axis (N·m/A). Default 1.2.
    pub steer_torque_constant: f64,
    /// Steering-angle encoder resolution (rad); 0 = none. Default 2π/2¹⁷ (17-bit absolute
    /// encoder, finer than the 1e-4 rad wire scale).
    pub steer_quantum: f64,
    /// Steer-rate resolution (rad/s); 0 = none. Default 1e-4.
    pub steer_rate_quantum: f64,
    /// Wheel-speed resolution (rad/s); 0 = none. Default 1e-3 (the wire scale).
    pub wheel_quantum: f64,
    /// Leg-extension resolution (m); 0 = none. Default 1e-6.
    pub leg_quantum: f64,
    /// Leg-rate resolution (m/s); 0 = none. Default 1e-5.
    pub leg_rate_quantum: f64,
    /// Steering-angle noise standard deviation (rad). Default 2e-4.
    pub steer_noise: f64,
    /// Steer-rate noise standard deviation (rad/s). Default 2e-3.
    pub steer_rate_noise: f64,
    /// Wheel-speed noise standard deviation (rad/s). Default 2e-3.
    pub wheel_noise: f64,
    /// Leg-extension noise standard deviation (m). Default 1e-5.
    pub leg_noise: f64,
    /// Leg-rate noise standard deviation (m/s). Default 1e-4.
    pub leg_rate_noise: f64,
    /// Encoder latency in plant steps (0 = the reading after the latest step). Default 1.
    pub latency_samples: usize,
    /// Fraction of its speed setpoint every rolling drive realises (default 1): 0.5 models a
    /// motor that responds at 50 % (a weak power stage, a wrong velocity scaling or gear
    /// ratio), 0 one that does not respond at all. Per module and from a given time:
    /// the fault schedule's `drive_gain` events.
    pub drive_gain: f64,
}

impl Default for PlantConfig {
    fn default() -> Self {
        Self {
            drive_time_constant: 0.020,
            steer_time_constant: 0.015,
            steer_inertia: 0.5,
            drive_accel_limit: None,
            steer_accel_limit: None,
            drive_speed_limit: None,
            steer_rate_limit: None,
            rolling_resistance: 0.01,
            drive_torque_constant: 1.2,
            steer_torque_constant: 1.2,
            steer_quantum: std::f64::consts::TAU / 131_072.0,
            steer_rate_quantum: 1e-4,
            wheel_quantum: 1e-3,
            leg_quantum: 1e-6,
            leg_rate_quantum: 1e-5,
            steer_noise: 2e-4,
            steer_rate_noise: 2e-3,
            wheel_noise: 2e-3,
            leg_noise: 1e-5,
            leg_rate_noise: 1e-4,
            latency_samples: 1,
            drive_gain: 1.0,
        }
    }
}

impl PlantConfig {
    /// An ideal plant: no noise, no quantization, no latency (motor dynamics unchanged).
    pub fn ideal() -> Self {
        Self {
            steer_quantum: 0.0,
            steer_rate_quantum: 0.0,
            wheel_quantum: 0.0,
            leg_quantum: 0.0,
            leg_rate_quantum: 0.0,
            steer_noise: 0.0,
            steer_rate_noise: 0.0,
            wheel_noise: 0.0,
            leg_noise: 0.0,
            leg_rate_noise: 0.0,
            latency_samples: 0,
            ..Self::default()
        }
    }

    /// Parses and validates a plant configuration from TOML text.
    pub fn from_toml_str(text: &str) -> Result<Self, SimError> {
        let c: PlantConfig = toml::from_str(text).map_err(|e| SimError::Parse {
            what: "plant configuration".into(),
            message: e.to_string(),
        })?;
        c.validate()?;
        Ok(c)
    }

    /// Reads, parses and validates a plant configuration file.
    pub fn load(path: impl AsRef<Path>) -> Result<Self, SimError> {
        let path = path.as_ref();
        let text = read_file(path, "plant file")?;
        Self::from_toml_str(&text).map_err(|e| match e {
            SimError::Parse { message, .. } => SimError::Parse {
                what: format!("plant file {}", path.display()),
                message,
            },
            other => other,
        })
    }

    /// The configuration as TOML text (round-trips through [`PlantConfig::from_toml_str`]).
    pub fn to_toml_string(&self) -> String {
        toml::to_string_pretty(self).unwrap_or_default()
    }

    /// Checks every field; the error names the first bad one.
    pub fn validate(&self) -> Result<(), SimError> {
        fn pos(field: &str, v: f64) -> Result<(), SimError> {
            if !v.is_finite() || v <= 0.0 {
                return Err(invalid(
                    format!("plant.{field}"),
                    v,
                    "must be a finite number greater than zero",
                ));
            }
            Ok(())
        }
        fn non_neg(field: &str, v: f64) -> Result<(), SimError> {
            if !v.is_finite() || v < 0.0 {
                return Err(invalid(
                    format!("plant.{field}"),
                    v,
                    "must be a finite number ≥ 0 (0 switches it off)",
                ));
            }
            Ok(())
        }
        pos("drive_time_constant", self.drive_time_constant)?;
        pos("steer_time_constant", self.steer_time_constant)?;
        pos("steer_inertia", self.steer_inertia)?;
        for (name, v) in [
            ("drive_accel_limit", self.drive_accel_limit),
            ("steer_accel_limit", self.steer_accel_limit),
            ("drive_speed_limit", self.drive_speed_limit),
            ("steer_rate_limit", self.steer_rate_limit),
        ] {
            if let Some(v) = v {
                pos(name, v)?;
            }
        }
        non_neg("rolling_resistance", self.rolling_resistance)?;
        pos("drive_torque_constant", self.drive_torque_constant)?;
        pos("steer_torque_constant", self.steer_torque_constant)?;
        non_neg("steer_quantum", self.steer_quantum)?;
        non_neg("steer_rate_quantum", self.steer_rate_quantum)?;
        non_neg("wheel_quantum", self.wheel_quantum)?;
        non_neg("leg_quantum", self.leg_quantum)?;
        non_neg("leg_rate_quantum", self.leg_rate_quantum)?;
        non_neg("steer_noise", self.steer_noise)?;
        non_neg("steer_rate_noise", self.steer_rate_noise)?;
        non_neg("wheel_noise", self.wheel_noise)?;
        non_neg("leg_noise", self.leg_noise)?;
        non_neg("leg_rate_noise", self.leg_rate_noise)?;
        if !(self.drive_gain.is_finite() && (0.0..=MAX_DRIVE_GAIN).contains(&self.drive_gain)) {
            return Err(invalid(
                "plant.drive_gain",
                self.drive_gain,
                format!("must be in [0, {MAX_DRIVE_GAIN}] (1 = a healthy drive, 0.5 = one that realises half its setpoint, 0 = none)"),
            ));
        }
        if self.latency_samples >= MAX_LATENCY_SAMPLES {
            return Err(invalid(
                "plant.latency_samples",
                self.latency_samples,
                format!("must be less than {MAX_LATENCY_SAMPLES} plant steps"),
            ));
        }
        Ok(())
    }
}

/// The plant's initial state.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct InitialState {
    /// Initial posture in the world frame.
    pub pose: Pose,
    /// Initial leg extensions λ_i (m); entries past n are ignored.
    pub legs: [f64; MAX_WHEELS],
    /// Initial steering angles φ_i (rad); entries past n are ignored.
    pub steer: [f64; MAX_WHEELS],
}

impl InitialState {
    /// Pose and legs of the reference sample `r0` (z = (x, y, θ, λ_1 … λ_n)), wheels steered
    /// to 0: the wheels are not pre-aligned with the trajectory, the supervisor's Aligning
    /// phase has to steer them, as on the real platform.
    pub fn from_reference(platform: &Platform, r0: &ReferenceSample) -> Self {
        let mut s = Self::nominal(platform);
        s.pose = r0.pose();
        for i in 0..platform.n().min(MAX_WHEELS) {
            s.legs[i] = r0.z[3 + i];
        }
        s
    }

    /// Pose at the origin, legs at their nominal extension, wheels steered to 0.
    pub fn nominal(platform: &Platform) -> Self {
        let mut legs = [0.0; MAX_WHEELS];
        for (l, w) in legs.iter_mut().zip(&platform.wheels) {
            *l = w.lambda_nominal;
        }
        Self {
            pose: Pose::default(),
            legs,
            steer: [0.0; MAX_WHEELS],
        }
    }
}

/// What the firmware asks of one module's motors for the next step.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct MotorSetpoint {
    /// Wheel spin rate setpoint (rad/s).
    pub wheel_speed: f64,
    /// Steering rate setpoint (rad/s).
    pub steer_rate: f64,
    /// Rolling motor's power stage enabled; when false it decelerates to zero at the torque
    /// limit.
    pub drive_enabled: bool,
    /// Steering motor's power stage enabled; when false it decelerates to zero at the torque
    /// limit.
    pub steer_enabled: bool,
}

/// One module's encoder readings (quantized, noisy, delayed), in SI units.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct SensorReading {
    /// Absolute steering angle (rad), wrapped to (−π, π].
    pub steer_angle: f64,
    /// Steering rate (rad/s).
    pub steer_rate: f64,
    /// Wheel spin rate (rad/s).
    pub wheel_speed: f64,
    /// Leg extension (m).
    pub leg: f64,
    /// Leg extension rate (m/s).
    pub leg_rate: f64,
    /// Drive motor current (A).
    pub drive_current: f64,
    /// Steer motor current (A).
    pub steer_current: f64,
}

/// The plant's true state (for tests, plots and checking odometry).
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct PlantTruth {
    /// Plant time (s): the sum of all step sizes.
    pub time: f64,
    /// Number of wheels.
    pub n: usize,
    /// Posture in the world frame.
    pub pose: Pose,
    /// Body twist in the body frame (m/s, m/s, rad/s) over the last step.
    pub twist_body: Twist,
    /// Leg extensions λ_i (m).
    pub legs: [f64; MAX_WHEELS],
    /// Leg rates λ̇_i (m/s) over the last step.
    pub leg_rates: [f64; MAX_WHEELS],
    /// Whether leg i was held by an end stop at the end of the last step.
    pub leg_blocked: [bool; MAX_WHEELS],
    /// Steering angles φ_i (rad), wrapped to (−π, π].
    pub steer: [f64; MAX_WHEELS],
    /// Steering rates φ̇_i (rad/s).
    pub steer_rate: [f64; MAX_WHEELS],
    /// Wheel spin rates ω_i (rad/s).
    pub wheel_speed: [f64; MAX_WHEELS],
    /// Least-squares residual norm of the contact equations over the last step (m/s):
    /// zero when the wheels agree on one motion, large when they fight.
    pub slip: f64,
    /// Per-wheel slip speed (m/s): norm of wheel i's contact-velocity residual.
    pub wheel_slip: [f64; MAX_WHEELS],
    /// Drive torque at each wheel (N·m).
    pub drive_torque: [f64; MAX_WHEELS],
    /// Steer torque at each steering axis (N·m).
    pub steer_torque: [f64; MAX_WHEELS],
    /// Steering angles φ_i (rad), not wrapped: how far each wheel has turned from its start
    /// (the angle a steering range bounds).
    pub steer_unwrapped: [f64; MAX_WHEELS],
    /// Plant steps in which a steering motor pressed a wheel against its stop.
    pub steer_stop_hits: [u64; MAX_WHEELS],
}

/// Effective motor limits of the plant (after applying defaults and derivations).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct MotorLimits {
    /// Wheel spin acceleration limit (rad/s²).
    pub drive_accel: f64,
    /// Steering acceleration limit (rad/s²).
    pub steer_accel: f64,
    /// Wheel spin speed limit (rad/s).
    pub drive_speed: f64,
    /// Steering rate limit (rad/s).
    pub steer_rate: f64,
    /// Reflected drive inertia at the wheel, (m/n) r² (kg·m²).
    pub drive_inertia: f64,
}

impl MotorLimits {
    /// Derives the limits from the platform and the plant configuration (module docs).
    pub fn derive(platform: &Platform, cfg: &PlantConfig) -> Self {
        let n = platform.n().max(1) as f64;
        let r = platform.wheel_radius;
        let drive_inertia = platform.mass / n * r * r;
        Self {
            drive_accel: cfg
                .drive_accel_limit
                .unwrap_or(platform.drive_torque / drive_inertia),
            steer_accel: cfg
                .steer_accel_limit
                .unwrap_or(platform.steer_torque / cfg.steer_inertia),
            drive_speed: cfg.drive_speed_limit.unwrap_or(platform.limits.wheel_speed),
            steer_rate: cfg.steer_rate_limit.unwrap_or(platform.limits.steer_rate),
            drive_inertia,
        }
    }
}

/// Result of one least-squares solve of the contact equations.
#[derive(Clone, Copy, Debug, Default)]
struct Solution {
    twist: Twist,
    leg_rates: [f64; MAX_WHEELS],
    blocked: [bool; MAX_WHEELS],
    wheel_slip: [f64; MAX_WHEELS],
}

/// The simulated platform: motors, encoders, legs, body.
#[derive(Clone, Debug)]
pub struct Plant {
    n: usize,
    r: f64,
    mass: f64,
    drive_torque_limit: f64,
    steer_torque_limit: f64,
    cos_a: [f64; MAX_WHEELS],
    sin_a: [f64; MAX_WHEELS],
    lmin: [f64; MAX_WHEELS],
    lmax: [f64; MAX_WHEELS],
    cfg: PlantConfig,
    limits: MotorLimits,
    rng: Rng,
    time: f64,
    pose: Pose,
    legs: [f64; MAX_WHEELS],
    leg_rates: [f64; MAX_WHEELS],
    leg_blocked: [bool; MAX_WHEELS],
    steer: [f64; MAX_WHEELS],
    steer_rate: [f64; MAX_WHEELS],
    wheel_speed: [f64; MAX_WHEELS],
    drive_torque: [f64; MAX_WHEELS],
    steer_torque: [f64; MAX_WHEELS],
    twist: Twist,
    slip: f64,
    wheel_slip: [f64; MAX_WHEELS],
    /// Ring buffer of encoder samples, newest at `head`.
    history: [[SensorReading; MAX_WHEELS]; MAX_LATENCY_SAMPLES],
    head: usize,
    encoder_stuck: [bool; MAX_WHEELS],
    steer_offset: [f64; MAX_WHEELS],
    drive_gain: [f64; MAX_WHEELS],
    /// Some wheel is not a centred, endless, uncoupled, positively mounted wheel on a leg:
    /// the general model (module docs) runs; otherwise the original one, unchanged.
    general: bool,
    caster: [f64; MAX_WHEELS],
    steer_lo: [f64; MAX_WHEELS],
    steer_hi: [f64; MAX_WHEELS],
    drive_pol: [f64; MAX_WHEELS],
    steer_pol: [f64; MAX_WHEELS],
    coupling: [f64; MAX_WHEELS],
    fixed: [bool; MAX_WHEELS],
    /// Each wheel's contact point offset d·h_i over the current step (general model).
    sweep_at: [[f64; 2]; MAX_WHEELS],
    joint_steer_rate: [f64; MAX_WHEELS],
    joint_wheel_speed: [f64; MAX_WHEELS],
    steer_stop_hits: [u64; MAX_WHEELS],
}

fn quantize(x: f64, q: f64) -> f64 {
    if q > 0.0 {
        (x / q).round() * q
    } else {
        x
    }
}

fn finite_or_zero(x: f64) -> f64 {
    if x.is_finite() {
        x
    } else {
        0.0
    }
}

/// One velocity-controlled motor step; returns the new speed.
fn motor_step(v: f64, setpoint: f64, tau: f64, a_max: f64, v_max: f64, dt: f64, on: bool) -> f64 {
    let max_dv = a_max * dt;
    let dv = if on {
        let sp = finite_or_zero(setpoint).clamp(-v_max, v_max);
        (sp - v) * (1.0 - (-dt / tau).exp())
    } else {
        -v
    };
    v + dv.clamp(-max_dv, max_dv)
}

/// Pose after moving with a constant body-frame twist for `t` seconds (exact on SE(2)).
pub fn integrate_se2(pose: Pose, tw: Twist, t: f64) -> Pose {
    let a = tw.omega * t;
    let (f1, f2) = if a.abs() < 1e-6 {
        (t * (1.0 - a * a / 6.0), t * (a / 2.0 - a * a * a / 24.0))
    } else {
        (a.sin() / tw.omega, (1.0 - a.cos()) / tw.omega)
    };
    let dxb = f1 * tw.vx - f2 * tw.vy;
    let dyb = f2 * tw.vx + f1 * tw.vy;
    let (s, c) = pose.theta.sin_cos();
    Pose {
        x: pose.x + c * dxb - s * dyb,
        y: pose.y + s * dxb + c * dyb,
        theta: pose.theta + a,
    }
}

/// Minimum-norm solution of the symmetric positive semi-definite 3 × 3 system `N x = b`.
fn solve_psd3(nm: Matrix3<f64>, b: Vector3<f64>) -> Vector3<f64> {
    // Fast path: a well-conditioned (full-rank) system has a unique solution, which Cholesky
    // finds at a fraction of the eigen-decomposition's cost (4 solves per control cycle).
    // Rank-deficient or nearly so (two wheels with free legs): fall through to the
    // minimum-norm pseudo-inverse below.
    let trace = nm.trace();
    if let Some(ch) = nm.cholesky() {
        let l = ch.l_dirty();
        let min_pivot = (0..3)
            .map(|k| l[(k, k)] * l[(k, k)])
            .fold(f64::INFINITY, f64::min);
        if trace.is_finite() && min_pivot > 1e-8 * trace {
            return ch.solve(&b);
        }
    }
    let eig = SymmetricEigen::new(nm);
    let top = eig.eigenvalues.iter().fold(0.0f64, |m, &e| m.max(e.abs()));
    let tol = top * 1e-10 + 1e-300;
    let mut x = Vector3::zeros();
    for k in 0..3 {
        let e = eig.eigenvalues[k];
        if e > tol {
            let v = eig.eigenvectors.column(k);
            x += v * (v.dot(&b) / e);
        }
    }
    x
}

impl Plant {
    /// Builds a plant for `platform` with the given configuration, initial state and noise
    /// seed. Fails (naming the field) when the platform or configuration is invalid or an
    /// initial leg extension lies outside its leg's range.
    pub fn new(
        platform: &Platform,
        cfg: PlantConfig,
        initial: InitialState,
        seed: u64,
    ) -> Result<Self, SimError> {
        platform.validate()?;
        cfg.validate()?;
        let n = platform.n();
        let mut cos_a = [1.0; MAX_WHEELS];
        let mut sin_a = [0.0; MAX_WHEELS];
        let mut lmin = [0.0; MAX_WHEELS];
        let mut lmax = [0.0; MAX_WHEELS];
        let mut legs = [0.0; MAX_WHEELS];
        let mut steer = [0.0; MAX_WHEELS];
        let mut caster = [0.0; MAX_WHEELS];
        let mut steer_lo = [f64::NEG_INFINITY; MAX_WHEELS];
        let mut steer_hi = [f64::INFINITY; MAX_WHEELS];
        let mut drive_pol = [1.0; MAX_WHEELS];
        let mut steer_pol = [1.0; MAX_WHEELS];
        let mut coupling = [0.0; MAX_WHEELS];
        let mut fixed = [false; MAX_WHEELS];
        let mut general = false;
        for (i, w) in platform.wheels.iter().enumerate() {
            caster[i] = w.caster_offset;
            if let Some((lo, hi)) = w.steer_limits() {
                (steer_lo[i], steer_hi[i]) = (lo, hi);
            }
            drive_pol[i] = f64::from(w.drive_polarity);
            steer_pol[i] = f64::from(w.steer_polarity);
            coupling[i] = w.coupling;
            fixed[i] = !w.leg;
            general |= !w.leg
                || w.caster_offset != 0.0
                || w.steer_range.is_some()
                || w.drive_polarity != 1
                || w.steer_polarity != 1
                || w.coupling != 0.0;
            (sin_a[i], cos_a[i]) = w.alpha.sin_cos();
            lmin[i] = w.lambda_min;
            lmax[i] = w.lambda_max;
            let l = initial.legs[i];
            if !l.is_finite() || l < w.lambda_min || l > w.lambda_max {
                return Err(invalid(
                    format!("initial.legs[{i}]"),
                    l,
                    format!(
                        "must lie in the leg's range [{}, {}] m",
                        w.lambda_min, w.lambda_max
                    ),
                ));
            }
            legs[i] = l;
            let s = initial.steer[i];
            if !s.is_finite() {
                return Err(invalid(
                    format!("initial.steer[{i}]"),
                    s,
                    "must be a finite angle in radians",
                ));
            }
            if s < steer_lo[i] || s > steer_hi[i] {
                return Err(invalid(
                    format!("initial.steer[{i}]"),
                    s,
                    format!(
                        "must lie in the wheel's steering range [{}, {}] rad",
                        steer_lo[i], steer_hi[i]
                    ),
                ));
            }
            steer[i] = s;
        }
        let p = initial.pose;
        if !(p.x.is_finite() && p.y.is_finite() && p.theta.is_finite()) {
            return Err(invalid(
                "initial.pose",
                format!("({}, {}, {})", p.x, p.y, p.theta),
                "must be finite",
            ));
        }
        let limits = MotorLimits::derive(platform, &cfg);
        let mut plant = Self {
            n,
            r: platform.wheel_radius,
            mass: platform.mass,
            drive_torque_limit: platform.drive_torque,
            steer_torque_limit: platform.steer_torque,
            cos_a,
            sin_a,
            lmin,
            lmax,
            limits,
            rng: Rng::new(seed),
            time: 0.0,
            pose: p,
            legs,
            leg_rates: [0.0; MAX_WHEELS],
            leg_blocked: [false; MAX_WHEELS],
            steer,
            steer_rate: [0.0; MAX_WHEELS],
            wheel_speed: [0.0; MAX_WHEELS],
            drive_torque: [0.0; MAX_WHEELS],
            steer_torque: [0.0; MAX_WHEELS],
            twist: Twist::default(),
            slip: 0.0,
            wheel_slip: [0.0; MAX_WHEELS],
            history: [[SensorReading::default(); MAX_WHEELS]; MAX_LATENCY_SAMPLES],
            head: 0,
            encoder_stuck: [false; MAX_WHEELS],
            steer_offset: [0.0; MAX_WHEELS],
            drive_gain: [cfg.drive_gain; MAX_WHEELS],
            cfg,
            general,
            caster,
            steer_lo,
            steer_hi,
            drive_pol,
            steer_pol,
            coupling,
            fixed,
            sweep_at: [[0.0; 2]; MAX_WHEELS],
            joint_steer_rate: [0.0; MAX_WHEELS],
            joint_wheel_speed: [0.0; MAX_WHEELS],
            steer_stop_hits: [0; MAX_WHEELS],
        };
        // Fill the whole latency buffer with the initial reading so that early reads are sane.
        let first = plant.sample();
        plant.history = [first; MAX_LATENCY_SAMPLES];
        Ok(plant)
    }

    /// Number of wheels.
    pub fn n(&self) -> usize {
        self.n
    }

    /// The effective motor limits.
    pub fn limits(&self) -> MotorLimits {
        self.limits
    }

    /// The configuration in use.
    pub fn config(&self) -> &PlantConfig {
        &self.cfg
    }

    /// Freezes (or releases) all encoders of wheel `i` at their current reading.
    /// Out-of-range `i` is ignored.
    pub fn set_encoder_stuck(&mut self, i: usize, stuck: bool) {
        if i < self.n {
            self.encoder_stuck[i] = stuck;
        }
    }

    /// Wheel `i`'s rolling drive realises `gain` × its setpoint from now on (a weakened or dead
    /// motor). Out-of-range `i` and gains outside [0, [`MAX_DRIVE_GAIN`]] are ignored.
    pub fn set_drive_gain(&mut self, i: usize, gain: f64) {
        if i < self.n && gain.is_finite() && (0.0..=MAX_DRIVE_GAIN).contains(&gain) {
            self.drive_gain[i] = gain;
        }
    }

    /// Adds `amount` (rad) to wheel `i`'s steering-encoder reading from now on (an encoder
    /// jump, e.g. a lost absolute-track bit). Out-of-range `i` or non-finite amounts are ignored.
    pub fn add_steer_encoder_offset(&mut self, i: usize, amount: f64) {
        if i < self.n && amount.is_finite() {
            self.steer_offset[i] += amount;
        }
    }

    /// Advances the plant by `dt` seconds with the given motor setpoints (entries past n are
    /// ignored). Non-positive or non-finite `dt` leaves the plant unchanged; non-finite
    /// setpoints count as zero.
    pub fn step(&mut self, dt: f64, setpoints: &[MotorSetpoint; MAX_WHEELS]) {
        if !(dt.is_finite() && dt > 0.0) {
            return;
        }
        let lim = self.limits;
        let mut contact = [[0.0f64; 2]; MAX_WHEELS];
        for (i, sp) in setpoints.iter().enumerate().take(self.n) {
            let w0 = self.wheel_speed[i];
            let w1 = motor_step(
                w0,
                finite_or_zero(sp.wheel_speed) * self.drive_gain[i],
                self.cfg.drive_time_constant,
                lim.drive_accel,
                lim.drive_speed,
                dt,
                sp.drive_enabled,
            );
            let s0 = self.steer_rate[i];
            let s1 = motor_step(
                s0,
                sp.steer_rate,
                self.cfg.steer_time_constant,
                lim.steer_accel,
                lim.steer_rate,
                dt,
                sp.steer_enabled,
            );
            let phi0 = self.steer[i];
            let mut s1 = s1;
            let phi1 = if self.general {
                // The steering joint turns at p_s × the motor's rate; a stop holds it (and the
                // motor pressing against it).
                let mut phi1 = phi0 + self.steer_pol[i] * 0.5 * (s0 + s1) * dt;
                let (lo, hi) = (self.steer_lo[i], self.steer_hi[i]);
                if phi1 > hi || phi1 < lo {
                    phi1 = phi1.clamp(lo, hi);
                    self.steer_stop_hits[i] += 1;
                    s1 = 0.0;
                }
                let rate = (phi1 - phi0) / dt;
                let spin = self.drive_pol[i] * 0.5 * (w0 + w1) + self.coupling[i] * rate;
                let v = self.r * spin;
                let d = self.caster[i];
                let (sm, cm) = (0.5 * (phi0 + phi1)).sin_cos();
                // What the wheel imposes on the body at its contact point: rolling plus the
                // steering's sweep (module docs).
                contact[i] = [v * cm - d * rate * sm, v * sm + d * rate * cm];
                self.sweep_at[i] = [d * cm, d * sm];
                self.joint_steer_rate[i] = self.steer_pol[i] * s1;
                self.joint_wheel_speed[i] =
                    self.drive_pol[i] * w1 + self.coupling[i] * self.joint_steer_rate[i];
                phi1
            } else {
                let phi1 = phi0 + 0.5 * (s0 + s1) * dt;
                let v = self.r * 0.5 * (w0 + w1);
                let (sp_, cp) = (0.5 * (phi0 + phi1)).sin_cos();
                contact[i] = [v * cp, v * sp_];
                phi1
            };
            // Torques (for the reported currents).
            let wacc = (w1 - w0) / dt;
            let rr = self.cfg.rolling_resistance * self.mass / self.n as f64 * GRAVITY * self.r;
            let rr = if w1.abs() > 1e-6 {
                rr * w1.signum()
            } else {
                0.0
            };
            self.drive_torque[i] = (lim.drive_inertia * wacc + rr)
                .clamp(-self.drive_torque_limit, self.drive_torque_limit);
            self.steer_torque[i] = (self.cfg.steer_inertia * (s1 - s0) / dt)
                .clamp(-self.steer_torque_limit, self.steer_torque_limit);
            self.wheel_speed[i] = w1;
            self.steer_rate[i] = s1;
            self.steer[i] = phi1;
        }

        // Kinematics in segments split at end-stop contacts.
        let mut remaining = dt;
        let mut last = Solution::default();
        let mut slip_sq_time = 0.0;
        let mut wheel_slip_sq_time = [0.0; MAX_WHEELS];
        for _ in 0..(2 * self.n + 2) {
            if remaining <= 0.0 {
                break;
            }
            let sol = if self.general {
                self.solve_general(&contact)
            } else {
                self.solve(&contact)
            };
            let mut t_seg = remaining;
            let mut hit: Option<(usize, f64)> = None;
            for i in 0..self.n {
                if sol.blocked[i] {
                    continue;
                }
                let lr = sol.leg_rates[i];
                let t_hit = if lr > 0.0 {
                    (self.lmax[i] - self.legs[i]) / lr
                } else if lr < 0.0 {
                    (self.lmin[i] - self.legs[i]) / lr
                } else {
                    f64::INFINITY
                };
                if t_hit < t_seg {
                    t_seg = t_hit.max(0.0);
                    hit = Some((i, if lr > 0.0 { self.lmax[i] } else { self.lmin[i] }));
                }
            }
            self.pose = integrate_se2(self.pose, sol.twist, t_seg);
            for (i, acc) in wheel_slip_sq_time.iter_mut().enumerate().take(self.n) {
                self.legs[i] =
                    (self.legs[i] + sol.leg_rates[i] * t_seg).clamp(self.lmin[i], self.lmax[i]);
                let s2 = sol.wheel_slip[i] * sol.wheel_slip[i] * t_seg;
                *acc += s2;
                slip_sq_time += s2;
            }
            if let Some((i, stop)) = hit {
                self.legs[i] = stop;
            }
            // Snap legs that ended within rounding distance of a stop onto it.
            for i in 0..self.n {
                if self.legs[i] >= self.lmax[i] - STOP_EPS {
                    self.legs[i] = self.lmax[i];
                } else if self.legs[i] <= self.lmin[i] + STOP_EPS {
                    self.legs[i] = self.lmin[i];
                }
            }
            remaining -= t_seg;
            last = sol;
            if hit.is_none() {
                break;
            }
        }
        self.twist = last.twist;
        self.leg_rates = last.leg_rates;
        self.leg_blocked = last.blocked;
        // Blocked status reported for legs sitting at a stop after the step, too.
        for i in 0..self.n {
            let at_stop =
                self.legs[i] >= self.lmax[i] - STOP_EPS || self.legs[i] <= self.lmin[i] + STOP_EPS;
            self.leg_blocked[i] = at_stop && self.leg_rates[i] == 0.0;
        }
        // Time-averaged (RMS over the step) slip.
        self.slip = (slip_sq_time / dt).sqrt();
        for (o, acc) in self.wheel_slip.iter_mut().zip(&wheel_slip_sq_time) {
            *o = (acc / dt).sqrt();
        }
        self.time += dt;

        // Encoders.
        let reading = self.sample();
        self.head = (self.head + 1) % MAX_LATENCY_SAMPLES;
        let prev = self.history[(self.head + MAX_LATENCY_SAMPLES - 1) % MAX_LATENCY_SAMPLES];
        let mut next = reading;
        for i in 0..self.n {
            if self.encoder_stuck[i] {
                next[i] = prev[i];
            }
        }
        self.history[self.head] = next;
    }

    /// Least-squares solve of the contact equations with the end-stop active set.
    fn solve(&self, contact: &[[f64; 2]; MAX_WHEELS]) -> Solution {
        let mut blocked = [false; MAX_WHEELS];
        let mut x = Vector3::zeros();
        let mut leg_rates = [0.0; MAX_WHEELS];
        for _ in 0..=self.n {
            let mut nm = Matrix3::zeros();
            let mut b = Vector3::zeros();
            for i in 0..self.n {
                let (c, s, l) = (self.cos_a[i], self.sin_a[i], self.legs[i]);
                let [cx, cy] = contact[i];
                if blocked[i] {
                    let g1 = Vector3::new(1.0, 0.0, -l * s);
                    let g2 = Vector3::new(0.0, 1.0, l * c);
                    nm += g1 * g1.transpose() + g2 * g2.transpose();
                    b += g1 * cx + g2 * cy;
                } else {
                    let g = Vector3::new(-s, c, l);
                    nm += g * g.transpose();
                    b += g * (-s * cx + c * cy);
                }
            }
            x = solve_psd3(nm, b);
            let mut changed = false;
            for i in 0..self.n {
                if blocked[i] {
                    leg_rates[i] = 0.0;
                    continue;
                }
                let (c, s) = (self.cos_a[i], self.sin_a[i]);
                let [cx, cy] = contact[i];
                let lr = c * cx + s * cy - (c * x[0] + s * x[1]);
                leg_rates[i] = lr;
                let out = lr > 0.0 && self.legs[i] >= self.lmax[i] - STOP_EPS;
                let inw = lr < 0.0 && self.legs[i] <= self.lmin[i] + STOP_EPS;
                if out || inw {
                    blocked[i] = true;
                    leg_rates[i] = 0.0;
                    changed = true;
                }
            }
            if !changed {
                break;
            }
        }
        let twist = Twist {
            vx: x[0],
            vy: x[1],
            omega: x[2],
        };
        let mut wheel_slip = [0.0; MAX_WHEELS];
        for i in 0..self.n {
            let (c, s, l) = (self.cos_a[i], self.sin_a[i], self.legs[i]);
            let ux = twist.vx - twist.omega * l * s + leg_rates[i] * c;
            let uy = twist.vy + twist.omega * l * c + leg_rates[i] * s;
            wheel_slip[i] = (ux - contact[i][0]).hypot(uy - contact[i][1]);
        }
        Solution {
            twist,
            leg_rates,
            blocked,
            wheel_slip,
        }
    }

    /// One noisy, quantized encoder sample of the current state (advances the RNG).
    fn sample(&mut self) -> [SensorReading; MAX_WHEELS] {
        let c = &self.cfg;
        let mut out = [SensorReading::default(); MAX_WHEELS];
        for (i, o) in out.iter_mut().enumerate().take(self.n) {
            let joint = if self.general {
                self.steer_pol[i] * self.steer[i]
            } else {
                self.steer[i]
            };
            let steer = joint + self.steer_offset[i] + c.steer_noise * self.rng.gaussian();
            o.steer_angle = angle::wrap(quantize(angle::wrap(steer), c.steer_quantum));
            o.steer_rate = quantize(
                self.steer_rate[i] + c.steer_rate_noise * self.rng.gaussian(),
                c.steer_rate_quantum,
            );
            o.wheel_speed = quantize(
                self.wheel_speed[i] + c.wheel_noise * self.rng.gaussian(),
                c.wheel_quantum,
            );
            o.leg = quantize(
                self.legs[i] + c.leg_noise * self.rng.gaussian(),
                c.leg_quantum,
            );
            o.leg_rate = quantize(
                self.leg_rates[i] + c.leg_rate_noise * self.rng.gaussian(),
                c.leg_rate_quantum,
            );
            o.drive_current = self.drive_torque[i] / c.drive_torque_constant;
            o.steer_current = self.steer_torque[i] / c.steer_torque_constant;
        }
        out
    }

    /// The encoder readings as the firmware sees them now (`latency_samples` steps old).
    pub fn sensors(&self) -> [SensorReading; MAX_WHEELS] {
        let k = self.cfg.latency_samples.min(MAX_LATENCY_SAMPLES - 1);
        self.history[(self.head + MAX_LATENCY_SAMPLES - k) % MAX_LATENCY_SAMPLES]
    }

    /// The true state.
    pub fn truth(&self) -> PlantTruth {
        let mut steer = [0.0; MAX_WHEELS];
        for (o, s) in steer.iter_mut().zip(&self.steer).take(self.n) {
            *o = angle::wrap(*s);
        }
        PlantTruth {
            time: self.time,
            n: self.n,
            pose: self.pose,
            twist_body: self.twist,
            legs: self.legs,
            leg_rates: self.leg_rates,
            leg_blocked: self.leg_blocked,
            steer,
            steer_rate: if self.general {
                self.joint_steer_rate
            } else {
                self.steer_rate
            },
            wheel_speed: if self.general {
                self.joint_wheel_speed
            } else {
                self.wheel_speed
            },
            slip: self.slip,
            wheel_slip: self.wheel_slip,
            drive_torque: self.drive_torque,
            steer_torque: self.steer_torque,
            steer_unwrapped: self.steer,
            steer_stop_hits: self.steer_stop_hits,
        }
    }

    /// [`Plant::solve`] for the general model (module docs): rows at the contact points
    /// C_i = P_i − d h_i, wheels without legs always blocked.
    fn solve_general(&self, contact: &[[f64; 2]; MAX_WHEELS]) -> Solution {
        let mut blocked = self.fixed;
        let mut x = Vector3::zeros();
        let mut leg_rates = [0.0; MAX_WHEELS];
        // Contact point of wheel i (body frame).
        let at = |i: usize| {
            let l = self.legs[i];
            [
                l * self.cos_a[i] - self.sweep_at[i][0],
                l * self.sin_a[i] - self.sweep_at[i][1],
            ]
        };
        for _ in 0..=self.n {
            let mut nm = Matrix3::zeros();
            let mut b = Vector3::zeros();
            for i in 0..self.n {
                let (c, s) = (self.cos_a[i], self.sin_a[i]);
                let p = at(i);
                let [cx, cy] = contact[i];
                if blocked[i] {
                    let g1 = Vector3::new(1.0, 0.0, -p[1]);
                    let g2 = Vector3::new(0.0, 1.0, p[0]);
                    nm += g1 * g1.transpose() + g2 * g2.transpose();
                    b += g1 * cx + g2 * cy;
                } else {
                    let g = Vector3::new(-s, c, c * p[0] + s * p[1]);
                    nm += g * g.transpose();
                    b += g * (-s * cx + c * cy);
                }
            }
            x = solve_psd3(nm, b);
            let mut changed = false;
            for i in 0..self.n {
                if blocked[i] {
                    leg_rates[i] = 0.0;
                    continue;
                }
                let (c, s) = (self.cos_a[i], self.sin_a[i]);
                let p = at(i);
                let [cx, cy] = contact[i];
                let lr = c * cx + s * cy - (c * x[0] + s * x[1] + x[2] * (s * p[0] - c * p[1]));
                leg_rates[i] = lr;
                let out = lr > 0.0 && self.legs[i] >= self.lmax[i] - STOP_EPS;
                let inw = lr < 0.0 && self.legs[i] <= self.lmin[i] + STOP_EPS;
                if out || inw {
                    blocked[i] = true;
                    leg_rates[i] = 0.0;
                    changed = true;
                }
            }
            if !changed {
                break;
            }
        }
        let twist = Twist {
            vx: x[0],
            vy: x[1],
            omega: x[2],
        };
        let mut wheel_slip = [0.0; MAX_WHEELS];
        for i in 0..self.n {
            let (c, s) = (self.cos_a[i], self.sin_a[i]);
            let p = at(i);
            let ux = twist.vx - twist.omega * p[1] + leg_rates[i] * c;
            let uy = twist.vy + twist.omega * p[0] + leg_rates[i] * s;
            wheel_slip[i] = (ux - contact[i][0]).hypot(uy - contact[i][1]);
        }
        Solution {
            twist,
            leg_rates,
            blocked,
            wheel_slip,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::f64::consts::PI;

    const DT: f64 = 0.001;

    fn justin() -> Platform {
        Platform::justin()
    }

    /// Wheel contact velocity for a body twist and leg rates (the brief's equation, written
    /// out independently of the plant's solver).
    fn contact(p: &Platform, legs: &[f64; MAX_WHEELS], tw: Twist, lr: &[f64]) -> Vec<(f64, f64)> {
        p.wheels
            .iter()
            .enumerate()
            .map(|(i, w)| {
                let (s, c) = w.alpha.sin_cos();
                (
                    tw.vx - tw.omega * legs[i] * s + lr[i] * c,
                    tw.vy + tw.omega * legs[i] * c + lr[i] * s,
                )
            })
            .collect()
    }

    /// Plant (ideal encoders) whose wheels are pre-steered to realise `tw` and `lr`, plus the
    /// matching wheel-speed setpoints.
    fn consistent(
        tw: Twist,
        lr: &[f64],
        legs: [f64; MAX_WHEELS],
    ) -> (Plant, [MotorSetpoint; MAX_WHEELS]) {
        let p = justin();
        let u = contact(&p, &legs, tw, lr);
        let mut init = InitialState::nominal(&p);
        init.legs = legs;
        let mut sp = [MotorSetpoint::default(); MAX_WHEELS];
        for (i, (ux, uy)) in u.iter().enumerate() {
            init.steer[i] = uy.atan2(*ux);
            sp[i] = MotorSetpoint {
                wheel_speed: ux.hypot(*uy) / p.wheel_radius,
                steer_rate: 0.0,
                drive_enabled: true,
                steer_enabled: true,
            };
        }
        // No torque limit: the first-order ramp then scales all wheels alike, so the
        // commands stay consistent during the start-up transient too.
        let cfg = PlantConfig {
            drive_accel_limit: Some(1e9),
            ..PlantConfig::ideal()
        };
        (Plant::new(&p, cfg, init, 1).unwrap(), sp)
    }

    fn legs4(a: f64, b: f64, c: f64, d: f64) -> [f64; MAX_WHEELS] {
        let mut l = [0.0; MAX_WHEELS];
        l[..4].copy_from_slice(&[a, b, c, d]);
        l
    }

    #[test]
    fn consistent_translation_with_leg_motion_has_expected_rates_and_no_slip() {
        let tw = Twist {
            vx: 0.3,
            vy: -0.1,
            omega: 0.0,
        };
        let lr = [0.02, -0.01, 0.0, 0.015];
        let (mut plant, sp) = consistent(tw, &lr, legs4(0.45, 0.45, 0.45, 0.45));
        for _ in 0..500 {
            plant.step(DT, &sp);
            assert!(plant.truth().slip < 1e-9, "slip {}", plant.truth().slip);
        }
        let t = plant.truth();
        assert!((t.twist_body.vx - 0.3).abs() < 1e-9, "{:?}", t.twist_body);
        assert!((t.twist_body.vy + 0.1).abs() < 1e-9, "{:?}", t.twist_body);
        assert!(t.twist_body.omega.abs() < 1e-9, "{:?}", t.twist_body);
        for (i, r) in lr.iter().enumerate() {
            assert!(
                (t.leg_rates[i] - r).abs() < 1e-9,
                "leg {i}: {}",
                t.leg_rates[i]
            );
        }
        // Constant twist over the next second: pose moves by exactly that twist.
        let before = plant.truth();
        for _ in 0..1000 {
            plant.step(DT, &sp);
        }
        let after = plant.truth();
        assert!((after.pose.x - before.pose.x - 0.3).abs() < 1e-9);
        assert!((after.pose.y - before.pose.y + 0.1).abs() < 1e-9);
        for (i, r) in lr.iter().enumerate() {
            let dl = after.legs[i] - before.legs[i];
            assert!((dl - r).abs() < 1e-9, "leg {i} moved {dl}");
        }
    }

    #[test]
    fn consistent_rotation_matches_exact_se2_motion() {
        let tw = Twist {
            vx: 0.2,
            vy: 0.15,
            omega: 0.5,
        };
        let lr = [0.0; 4];
        let (mut plant, sp) = consistent(tw, &lr, legs4(0.40, 0.50, 0.56, 0.37));
        for _ in 0..500 {
            plant.step(DT, &sp);
        }
        let t0 = plant.truth();
        assert!(t0.slip < 1e-9, "slip {}", t0.slip);
        assert!((t0.twist_body.omega - 0.5).abs() < 1e-9);
        for _ in 0..2000 {
            plant.step(DT, &sp);
            assert!(plant.truth().slip < 1e-9);
        }
        let t1 = plant.truth();
        let expect = integrate_se2(t0.pose, tw, 2.0);
        assert!(
            (t1.pose.x - expect.x).abs() < 1e-9,
            "{:?} vs {expect:?}",
            t1.pose
        );
        assert!((t1.pose.y - expect.y).abs() < 1e-9);
        assert!((t1.pose.theta - expect.theta).abs() < 1e-9);
        assert_eq!(t1.legs, t0.legs);
    }

    #[test]
    fn rotation_with_leg_motion_stays_nearly_consistent() {
        // Fixed wheel commands become slightly inconsistent as λ changes (ω λ term), so the
        // slip is small but not zero: bounded by |ω| · |Δλ|.
        let tw = Twist {
            vx: 0.1,
            vy: 0.0,
            omega: 0.3,
        };
        let lr = [0.02, 0.02, -0.02, -0.02];
        let (mut plant, sp) = consistent(tw, &lr, legs4(0.45, 0.45, 0.45, 0.45));
        for _ in 0..150 {
            plant.step(DT, &sp);
        }
        let t = plant.truth();
        // |Δλ| ≤ 0.02 · 0.15 = 3 mm → slip ≲ 0.3 · 0.003 · 2 (four wheels) ≈ 2e-3 m/s.
        assert!(t.slip < 2e-3, "slip {}", t.slip);
        assert!(
            (t.twist_body.omega - 0.3).abs() < 5e-3,
            "{:?}",
            t.twist_body
        );
        for (i, r) in lr.iter().enumerate() {
            assert!(
                (t.leg_rates[i] - r).abs() < 2e-3,
                "leg {i}: {}",
                t.leg_rates[i]
            );
        }
    }

    #[test]
    fn inconsistent_steering_produces_slip() {
        let p = justin();
        let mut init = InitialState::nominal(&p);
        // Wheels 1, 3, 4 forward; wheel 2 sideways: they fight.
        init.steer[1] = PI / 2.0;
        let mut plant = Plant::new(&p, PlantConfig::ideal(), init, 1).unwrap();
        let v = 0.5;
        let sp = [MotorSetpoint {
            wheel_speed: v / p.wheel_radius,
            steer_rate: 0.0,
            drive_enabled: true,
            steer_enabled: true,
        }; MAX_WHEELS];
        for _ in 0..300 {
            plant.step(DT, &sp);
        }
        let t = plant.truth();
        assert!(t.slip > 0.1 * v, "slip {} too small", t.slip);
        assert!(t.wheel_slip[1] > 0.05, "{:?}", t.wheel_slip);
        // Same commands with all wheels forward: no slip.
        let mut plant = Plant::new(&p, PlantConfig::ideal(), InitialState::nominal(&p), 1).unwrap();
        for _ in 0..300 {
            plant.step(DT, &sp);
        }
        assert!(plant.truth().slip < 1e-9);
        assert!((plant.truth().twist_body.vx - v).abs() < 1e-6);
    }

    #[test]
    fn legs_stop_at_end_stops() {
        let tw = Twist {
            vx: 0.1,
            vy: 0.0,
            omega: 0.0,
        };
        // Leg 1 extends and leg 3 retracts at 5 cm/s, both 1 cm from their stops.
        let lr = [0.05, 0.0, -0.05, 0.0];
        let (mut plant, sp) = consistent(tw, &lr, legs4(0.55, 0.45, 0.38, 0.45));
        let mut reached = None;
        for k in 0..400 {
            plant.step(DT, &sp);
            let t = plant.truth();
            assert!(
                t.legs[0] <= 0.56 && t.legs[2] >= 0.37,
                "step {k}: {:?}",
                t.legs
            );
            if reached.is_none() && t.legs[0] == 0.56 {
                reached = Some(k);
            }
        }
        let t = plant.truth();
        assert_eq!(t.legs[0], 0.56);
        assert_eq!(t.legs[2], 0.37);
        assert!(t.leg_blocked[0] && t.leg_blocked[2], "{:?}", t.leg_blocked);
        assert_eq!(t.leg_rates[0], 0.0);
        // The blocked wheels' radial rolling now has nowhere to go: slip.
        assert!(t.slip > 0.01, "slip {}", t.slip);
        // ~0.2 s plus the motor lag (20 ms time constant).
        let k = reached.unwrap();
        assert!((200..260).contains(&k), "reached the stop at step {k}");
        // Reversing the legs' wheels frees them again.
        let mut back = sp;
        back[0].wheel_speed = 0.0;
        back[2].wheel_speed = 0.0;
        back[1].wheel_speed = 0.0;
        back[3].wheel_speed = 0.0;
        for _ in 0..300 {
            plant.step(DT, &back);
        }
        assert!(plant.truth().twist_body.vx.abs() < 1e-6);
    }

    #[test]
    fn motor_first_order_response() {
        let p = justin();
        let mut plant = Plant::new(&p, PlantConfig::ideal(), InitialState::nominal(&p), 1).unwrap();
        let mut sp = [MotorSetpoint::default(); MAX_WHEELS];
        sp[0] = MotorSetpoint {
            wheel_speed: 1.0,
            steer_rate: 0.5,
            drive_enabled: true,
            steer_enabled: true,
        };
        for _ in 0..20 {
            plant.step(DT, &sp);
        }
        // Small steps are not torque limited: exact first-order lag.
        let t = plant.truth();
        let expect_w = 1.0 - (-0.020f64 / 0.020).exp();
        let expect_s = 0.5 * (1.0 - (-0.020f64 / 0.015).exp());
        assert!(
            (t.wheel_speed[0] - expect_w).abs() < 1e-12,
            "{}",
            t.wheel_speed[0]
        );
        assert!(
            (t.steer_rate[0] - expect_s).abs() < 1e-12,
            "{}",
            t.steer_rate[0]
        );
    }

    #[test]
    fn motor_torque_and_speed_limits() {
        let p = justin();
        let plant0 = Plant::new(&p, PlantConfig::ideal(), InitialState::nominal(&p), 1).unwrap();
        let lim = plant0.limits();
        // Derived from the torque, wheel radius and mass share (module docs).
        let expect = 4.0 * 30.0 / (150.0 * 0.085 * 0.085);
        assert!((lim.drive_accel - expect).abs() < 1e-9);
        assert!((lim.steer_accel - 56.0).abs() < 1e-12);
        let mut plant = plant0;
        let mut sp = [MotorSetpoint::default(); MAX_WHEELS];
        sp[0] = MotorSetpoint {
            wheel_speed: 13.0,
            steer_rate: 5.0,
            drive_enabled: true,
            steer_enabled: true,
        };
        for k in 1..=10 {
            plant.step(DT, &sp);
            let t = plant.truth();
            assert!((t.wheel_speed[0] - lim.drive_accel * DT * k as f64).abs() < 1e-9);
            assert!((t.steer_rate[0] - 56.0 * DT * k as f64).abs() < 1e-9);
            assert!(
                (t.drive_torque[0].abs() - 30.0).abs() < 1e-6,
                "{}",
                t.drive_torque[0]
            );
            assert!(
                (t.steer_torque[0] - 28.0).abs() < 1e-6,
                "{}",
                t.steer_torque[0]
            );
        }
        // Speed limits.
        sp[0] = MotorSetpoint {
            wheel_speed: 50.0,
            steer_rate: -50.0,
            drive_enabled: true,
            steer_enabled: true,
        };
        for _ in 0..1000 {
            plant.step(DT, &sp);
        }
        let t = plant.truth();
        assert!(
            (t.wheel_speed[0] - 13.9).abs() < 1e-6,
            "{}",
            t.wheel_speed[0]
        );
        assert!((t.steer_rate[0] + 6.0).abs() < 1e-6, "{}", t.steer_rate[0]);
        // Disabled: decelerate at the torque limit, reach zero in ω/a_max.
        sp[0].drive_enabled = false;
        sp[0].steer_enabled = false;
        let mut steps = 0;
        while plant.truth().wheel_speed[0] != 0.0 && steps < 1000 {
            plant.step(DT, &sp);
            steps += 1;
        }
        let expect_steps = (13.9 / lim.drive_accel / DT).ceil() as usize;
        assert_eq!(steps, expect_steps);
        assert_eq!(plant.truth().steer_rate[0], 0.0);
    }

    #[test]
    fn se2_integration_matches_fine_euler() {
        let start = Pose {
            x: 1.0,
            y: -2.0,
            theta: 0.7,
        };
        let tw = Twist {
            vx: 0.4,
            vy: -0.3,
            omega: 1.3,
        };
        let exact = integrate_se2(start, tw, 1.5);
        let mut p = start;
        let n = 200_000;
        let h = 1.5 / n as f64;
        for _ in 0..n {
            let (s, c) = p.theta.sin_cos();
            p.x += (c * tw.vx - s * tw.vy) * h;
            p.y += (s * tw.vx + c * tw.vy) * h;
            p.theta += tw.omega * h;
        }
        assert!((exact.x - p.x).abs() < 1e-5 && (exact.y - p.y).abs() < 1e-5);
        // 2e5 Euler additions accumulate ~1e-11 of rounding in θ.
        assert!((exact.theta - p.theta).abs() < 1e-9);
        // Small-angle branch agrees with the closed form near its threshold.
        let tw2 = Twist { omega: 1e-7, ..tw };
        let a = integrate_se2(start, tw2, 1.0);
        let b = integrate_se2(start, Twist { omega: 0.0, ..tw }, 1.0);
        assert!((a.x - b.x).abs() < 1e-6 && (a.y - b.y).abs() < 1e-6);
    }

    #[test]
    fn encoders_are_seeded_noisy_quantized_and_delayed() {
        let p = justin();
        let run = |seed: u64| {
            let mut plant =
                Plant::new(&p, PlantConfig::default(), InitialState::nominal(&p), seed).unwrap();
            let sp = [MotorSetpoint {
                wheel_speed: 2.0,
                steer_rate: 0.1,
                drive_enabled: true,
                steer_enabled: true,
            }; MAX_WHEELS];
            let mut out = Vec::new();
            for _ in 0..50 {
                plant.step(DT, &sp);
                out.push(plant.sensors()[0]);
            }
            out
        };
        assert_eq!(run(5), run(5));
        assert_ne!(run(5), run(6));
        let r = run(5);
        for s in &r {
            let q = s.wheel_speed / 1e-3;
            assert!(
                (q - q.round()).abs() < 1e-6,
                "wheel speed {} not quantized",
                s.wheel_speed
            );
        }
        // Latency: with 3 samples, the reading equals the truth three steps earlier.
        let cfg = PlantConfig {
            latency_samples: 3,
            ..PlantConfig::ideal()
        };
        let mut plant = Plant::new(&p, cfg, InitialState::nominal(&p), 1).unwrap();
        let sp = [MotorSetpoint {
            wheel_speed: 5.0,
            steer_rate: 1.0,
            drive_enabled: true,
            steer_enabled: true,
        }; MAX_WHEELS];
        let mut truths = Vec::new();
        for _ in 0..20 {
            plant.step(DT, &sp);
            truths.push(plant.truth());
            if truths.len() > 3 {
                let old = truths[truths.len() - 4];
                let s = plant.sensors()[2];
                assert_eq!(s.wheel_speed, old.wheel_speed[2]);
                assert_eq!(s.steer_angle, old.steer[2]);
            }
        }
    }

    #[test]
    fn encoder_stuck_and_jump() {
        let p = justin();
        let mut plant = Plant::new(&p, PlantConfig::ideal(), InitialState::nominal(&p), 1).unwrap();
        let sp = [MotorSetpoint {
            wheel_speed: 3.0,
            steer_rate: 0.2,
            drive_enabled: true,
            steer_enabled: true,
        }; MAX_WHEELS];
        for _ in 0..10 {
            plant.step(DT, &sp);
        }
        plant.set_encoder_stuck(1, true);
        plant.add_steer_encoder_offset(2, 0.3);
        let frozen = plant.sensors()[1];
        for _ in 0..10 {
            plant.step(DT, &sp);
        }
        let s = plant.sensors();
        let t = plant.truth();
        assert_eq!(s[1], frozen);
        assert_ne!(t.wheel_speed[1], frozen.wheel_speed);
        assert!((s[2].steer_angle - (t.steer[2] + 0.3)).abs() < 1e-12);
        assert!((s[3].steer_angle - t.steer[3]).abs() < 1e-12);
    }

    #[test]
    fn config_loads_and_rejects_bad_fields() {
        let c =
            PlantConfig::from_toml_str("drive_time_constant = 0.03\nlatency_samples = 0").unwrap();
        assert_eq!(c.drive_time_constant, 0.03);
        assert_eq!(
            c.steer_time_constant,
            PlantConfig::default().steer_time_constant
        );
        let d = PlantConfig::default();
        assert_eq!(PlantConfig::from_toml_str(&d.to_toml_string()).unwrap(), d);
        let e = PlantConfig::from_toml_str("drive_tau = 0.03").unwrap_err();
        assert!(e.to_string().contains("drive_tau"), "{e}");
        for (text, field) in [
            ("steer_inertia = -1.0", "plant.steer_inertia"),
            ("wheel_noise = -0.1", "plant.wheel_noise"),
            ("latency_samples = 9", "plant.latency_samples"),
            ("drive_accel_limit = 0.0", "plant.drive_accel_limit"),
        ] {
            match PlantConfig::from_toml_str(text) {
                Err(SimError::Invalid { field: f, .. }) => assert_eq!(f, field),
                other => panic!("{text}: expected Invalid, got {other:?}"),
            }
        }
        let p = justin();
        let mut init = InitialState::nominal(&p);
        init.legs[2] = 0.6;
        match Plant::new(&p, PlantConfig::default(), init, 1) {
            Err(SimError::Invalid { field, .. }) => assert_eq!(field, "initial.legs[2]"),
            other => panic!("expected Invalid, got {other:?}"),
        }
    }

    #[test]
    fn bad_inputs_do_not_corrupt_the_state() {
        let p = justin();
        let mut plant = Plant::new(&p, PlantConfig::ideal(), InitialState::nominal(&p), 1).unwrap();
        let before = plant.truth();
        plant.step(f64::NAN, &[MotorSetpoint::default(); MAX_WHEELS]);
        plant.step(-1.0, &[MotorSetpoint::default(); MAX_WHEELS]);
        assert_eq!(plant.truth(), before);
        let sp = [MotorSetpoint {
            wheel_speed: f64::NAN,
            steer_rate: f64::INFINITY,
            drive_enabled: true,
            steer_enabled: true,
        }; MAX_WHEELS];
        plant.step(DT, &sp);
        let t = plant.truth();
        assert!(t.pose.x.is_finite() && t.wheel_speed[0] == 0.0 && t.steer_rate[0] == 0.0);
    }

    /// Drives `p`'s wheels for `seconds` with the motor setpoints that realise the body twist
    /// `tw` (legs still) at the wheels' true angles: off-centred wheels by the caster law
    /// (written out here, independently of the controller's), centred ones steered to their
    /// direction of travel; polarity and coupling undone as the link does. Returns the plant.
    fn drive_twist(p: &Platform, tw: Twist, seconds: f64, steer0: [f64; MAX_WHEELS]) -> Plant {
        let mut init = InitialState::nominal(p);
        init.steer = steer0;
        let mut plant = Plant::new(p, PlantConfig::ideal(), init, 7).unwrap();
        let dt = 0.001;
        for _ in 0..(seconds / dt) as usize {
            let t = plant.truth();
            let mut sp = [MotorSetpoint::default(); MAX_WHEELS];
            for (i, w) in p.wheels.iter().enumerate() {
                let (sa, ca) = w.alpha.sin_cos();
                let l = t.legs[i];
                let u = [tw.vx - tw.omega * l * sa, tw.vy + tw.omega * l * ca];
                let phi = t.steer_unwrapped[i];
                let (sphi, cphi) = phi.sin_cos();
                let along = u[0] * cphi + u[1] * sphi;
                let across = -u[0] * sphi + u[1] * cphi;
                let rate = if w.caster_offset > 0.0 {
                    across / w.caster_offset - tw.omega
                } else {
                    10.0 * across.atan2(along.abs()) * along.signum()
                };
                let spin = along / p.wheel_radius - w.coupling * rate;
                sp[i] = MotorSetpoint {
                    wheel_speed: f64::from(w.drive_polarity) * spin,
                    steer_rate: f64::from(w.steer_polarity) * rate,
                    drive_enabled: true,
                    steer_enabled: true,
                };
            }
            plant.step(dt, &sp);
        }
        plant
    }

    #[test]
    fn off_centred_wheels_move_the_body_by_the_caster_law_without_slip() {
        let p = Platform::mpo700();
        let tw = Twist {
            vx: 0.2,
            vy: 0.1,
            omega: 0.3,
        };
        // Wheels start across their directions of travel: the caster law turns them as the
        // platform moves, without slip once the motors have caught up.
        let plant = drive_twist(&p, tw, 2.0, [1.5, -2.0, 0.4, 3.0, 0.0, 0.0, 0.0, 0.0]);
        let t = plant.truth();
        assert!((t.twist_body.vx - tw.vx).abs() < 2e-3, "{:?}", t.twist_body);
        assert!((t.twist_body.vy - tw.vy).abs() < 2e-3, "{:?}", t.twist_body);
        assert!(
            (t.twist_body.omega - tw.omega).abs() < 5e-3,
            "{:?}",
            t.twist_body
        );
        assert!(t.slip < 2e-3, "slip {}", t.slip);
        // Steering one wheel at rest scrubs: the body moves although no wheel rolls.
        let mut plant = Plant::new(&p, PlantConfig::ideal(), InitialState::nominal(&p), 7).unwrap();
        let mut sp = [MotorSetpoint::default(); MAX_WHEELS];
        sp[0] = MotorSetpoint {
            steer_rate: 3.0,
            steer_enabled: true,
            drive_enabled: true,
            ..MotorSetpoint::default()
        };
        for _ in 0..300 {
            plant.step(0.001, &sp);
        }
        let t = plant.truth();
        assert!(t.pose.x.hypot(t.pose.y) > 1e-3 && t.slip > 0.01, "{t:?}");
        // Without the offset the same steering at rest moves nothing.
        let mut centred = p.clone();
        for w in &mut centred.wheels {
            w.caster_offset = 0.0;
        }
        let mut plant = Plant::new(
            &centred,
            PlantConfig::ideal(),
            InitialState::nominal(&centred),
            7,
        )
        .unwrap();
        for _ in 0..300 {
            plant.step(0.001, &sp);
        }
        assert!(plant.truth().pose.x.hypot(plant.truth().pose.y) < 1e-12);
    }

    #[test]
    fn wheels_without_legs_keep_their_footprint_and_mirrored_coupled_motors_are_undone() {
        let mut p = Platform::three_wheel();
        p.wheels[2].coupling = 0.5;
        let tw = Twist {
            vx: -0.1,
            vy: 0.25,
            omega: -0.4,
        };
        let plant = drive_twist(&p, tw, 3.0, [0.0; MAX_WHEELS]);
        let t = plant.truth();
        assert!((t.twist_body.vx - tw.vx).abs() < 2e-3, "{:?}", t.twist_body);
        assert!((t.twist_body.vy - tw.vy).abs() < 2e-3, "{:?}", t.twist_body);
        assert!(
            (t.twist_body.omega - tw.omega).abs() < 5e-3,
            "{:?}",
            t.twist_body
        );
        assert!(t.slip < 2e-3, "slip {}", t.slip);
        for i in 0..3 {
            assert_eq!(t.legs[i], 0.3);
            assert!(t.leg_blocked[i]);
        }
        // The mirrored module's encoders read its motors: the opposite of the joints.
        let s = plant.sensors();
        assert!((s[1].steer_angle + t.steer[1]).abs() < 1e-9);
        assert!((s[1].steer_rate + t.steer_rate[1]).abs() < 1e-9);
        // The coupled module's rolling motor turns less than the wheel by 0.5 × φ̇.
        let motor = s[2].wheel_speed;
        assert!((t.wheel_speed[2] - (motor + 0.5 * t.steer_rate[2])).abs() < 1e-9);
    }

    #[test]
    fn a_steering_stop_holds_the_wheel_and_counts() {
        let p = Platform::three_wheel();
        let mut plant = Plant::new(&p, PlantConfig::ideal(), InitialState::nominal(&p), 7).unwrap();
        let mut sp = [MotorSetpoint::default(); MAX_WHEELS];
        sp[0] = MotorSetpoint {
            steer_rate: 4.0,
            steer_enabled: true,
            drive_enabled: true,
            ..MotorSetpoint::default()
        };
        for _ in 0..2000 {
            plant.step(0.001, &sp);
        }
        let t = plant.truth();
        let stop = 170f64.to_radians();
        assert!(
            (t.steer_unwrapped[0] - stop).abs() < 1e-12,
            "{}",
            t.steer_unwrapped[0]
        );
        assert!(t.steer_stop_hits[0] > 100 && t.steer_stop_hits[1] == 0);
        assert_eq!(t.steer_rate[0], 0.0);
        // Justin's wheels have no stops.
        let j = Platform::justin();
        let mut plant = Plant::new(&j, PlantConfig::ideal(), InitialState::nominal(&j), 7).unwrap();
        for _ in 0..2000 {
            plant.step(0.001, &sp);
        }
        assert!(plant.truth().steer_unwrapped[0] > 7.0);
    }
}
