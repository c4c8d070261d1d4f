//! Kinematic model of a platform with centred steering wheels on movable legs (seed 000,
//! Sect. III-B, eqs. 17–22) and the instantaneous centre of rotation (seed 001, eqs. 1–3).
//!
//! Notation (DESIGN.md, seed 000): posture ξ = (x, y, θ); wheel i sits at
//! P_i = λ_i e_i in the body frame with e_i = (cos α_i, sin α_i) and e⊥_i = (−sin α_i, cos α_i).
//! Its contact-point velocity in the body frame is
//!
//! ```text
//! u_i = Rᵀ(θ) (ẋ, ẏ) + θ̇ λ_i e⊥_i + λ̇_i e_i
//! ```
//!
//! (numerator and denominator of seed 000 eq. 18). The steering angle is
//! φ_i = atan2(u_iy, u_ix) (eq. 18) and the rolling speed v_Wi = ±|u_i|.
//!
//! **Steering rate, analytically.** Differentiating u_i once more with
//! d/dt Rᵀ(θ) = −θ̇ J Rᵀ(θ), J = [[0, −1], [1, 0]] (rotation by +90°):
//!
//! ```text
//! u̇_i = Rᵀ(θ)(ẍ, ÿ) − θ̇ J Rᵀ(θ)(ẋ, ẏ) + (θ̈ λ_i + θ̇ λ̇_i) e⊥_i + λ̈_i e_i
//! ```
//!
//! and, from φ = atan2(u_y, u_x), φ̇ = (u_x u̇_y − u_y u̇_x) / |u|². This is exact and
//! needs no finite differences; it is undefined only where |u_i| = 0 (singularity A,
//! seed 000 Sect. III-A: the ICR lies on the wheel), which [`wheel_setpoints`] reports
//! as [`KinematicsError::Singular`] instead of returning NaN.
//!
//! # Off-centred steering (caster offset d > 0)
//!
//! Seed 003's off-centred orientable wheel: the wheel's contact point trails its steering
//! axis by d along the wheel plane (`wheels[i].caster_offset`; MPO-700-like modules,
//! d = 45 mm). With h = (cos φ, sin φ) and h⊥ = J h = (−sin φ, cos φ), the contact point is
//!
//! ```text
//! C_i = P_i − d h
//! ```
//!
//! and u_i above is now the velocity of the steering axis. Differentiating the contact
//! point's world position p + R(θ) C_i (d/dt R(θ)x = R(θ)(θ̇ J x + ẋ), ḣ = φ̇ h⊥), its body
//! velocity is u_i − d (θ̇ + φ̇) h⊥. Rolling without slip it is v_W h, so
//!
//! ```text
//! u_i = v_W h + d (θ̇ + φ̇) h⊥          (seed 003's caster constraint, C₂c = d)
//! v_W = u_i · h,   φ̇ = (u_i · h⊥)/d − θ̇   ([`caster_inverse`])
//! ```
//!
//! The 2 × 2 map (v_W, φ̇ + θ̇) ↦ u_i is [h, d h⊥], of determinant d: for d > 0 the steering
//! axis can move in any direction whatever the wheel's angle, there is no singularity A,
//! and no wheel ever needs to be steered before it rolls. The price is that the steering is
//! no longer free: at rest (u_i = 0, θ̇ = 0) the only slip-free steering rate is 0. Steering
//! a wheel at rest drags its contact point sideways along a circle of radius d (a 90° turn
//! scrubs the tyre 71 mm at d = 45 mm) and pushes the body. So off-centred wheels are never
//! steered at rest: they turn as the platform moves, as a caster does (trailing, φ → ψ =
//! atan2(u_i), with the time constant d/|u_i|), and the steering rate this takes is
//! |u_i| sin|φ − ψ| / d (at most |u_i|/d, 13 rad/s at 0.6 m/s and d = 45 mm), which bounds
//! how fast the platform may move while a wheel is far from its direction of travel.
//!
//! Following a direction of travel ψ(t) that turns, the slip-free angle lags it: with
//! φ = ψ + ε (trailing, rolling forward) the constraint gives ψ̇ + ε̇ = −|u| sin ε / d − θ̇,
//! so at a steady lag sin ε = −d (ψ̇ + θ̇)/|u| ([`caster_lag`]); rolling backwards (φ = ψ +
//! π + ε, a leading caster) sin ε = +d (ψ̇ + θ̇)/|u|. A trailing caster settles on its lag by
//! itself (stable); a leading one would swing round, so a wheel rolls backwards only while
//! its steering motor holds it on the leading angle (after a reversal, where it already
//! points that way).

// Index loops over parallel per-wheel arrays read better than zipped iterators here.
#![allow(clippy::needless_range_loop)]

use crate::platform::Platform;
use crate::types::{Pose, Twist, ZVec, MAX_WHEELS};

/// Per-wheel setpoint derived from the output trajectory.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct WheelSetpoint {
    /// Steering angle φ_i (rad), wrapped to (−π, π], rolling speed positive along it.
    pub steer_angle: f64,
    /// Rolling speed v_Wi (m/s, signed; ≥ 0 as returned by [`wheel_setpoints`]).
    pub rolling_speed: f64,
    /// Steering rate φ̇_i (rad/s), computed analytically from the accelerations.
    pub steer_rate: f64,
}

/// Errors of the inverse kinematics.
#[derive(Clone, Copy, Debug, PartialEq, thiserror::Error)]
pub enum KinematicsError {
    /// Singularity A: the contact velocity of wheel `wheel` is (nearly) zero, so its
    /// steering angle is undefined. Plan the trajectory so that the ICR stays off the
    /// wheels, or hold the wheel's angle while it is at rest.
    #[error("singularity A at wheel {wheel}: contact speed {speed} m/s is below the threshold; its steering angle is undefined (keep the ICR off the wheel or hold its angle)")]
    Singular {
        /// Index of the wheel (0-based).
        wheel: usize,
        /// Its contact speed |u_i| (m/s).
        speed: f64,
    },
    /// An input was NaN or infinite.
    #[error("non-finite input `{what}`: every state and reference value must be a finite number")]
    NonFinite {
        /// Which input.
        what: &'static str,
    },
}

/// Instantaneous centre of rotation in the body frame (seed 001, eqs. 1–3).
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Icr {
    /// Pure translation: the ICR is at infinity. `direction` is the direction of motion
    /// atan2(v_y, v_x) in the body frame (rad); the ICR lies perpendicular to it.
    AtInfinity {
        /// Direction of motion in the body frame (rad).
        direction: f64,
    },
    /// Finite ICR at (x, y) in the body frame (m).
    Point {
        /// Body x (m).
        x: f64,
        /// Body y (m).
        y: f64,
    },
    /// Zero twist: the platform is at rest and the ICR is undefined.
    Undefined,
}

/// Below this angular rate (rad/s) the ICR is treated as at infinity.
const ICR_OMEGA_EPS: f64 = 1e-9;
/// Below this speed (m/s, rad/s) the twist is treated as zero.
const ICR_REST_EPS: f64 = 1e-12;

/// ICR of a body-frame twist, by seed 001 eqs. 1–3:
/// z = v/|θ̇| (cos γ, sin γ), v = √(ẋ² + ẏ²), γ = atan2(sgn(θ̇) ẋ, −sgn(θ̇) ẏ).
/// This equals (−v_y/ω, v_x/ω), the point of zero velocity.
pub fn icr_body(twist_body: &Twist) -> Icr {
    let (vx, vy, w) = (twist_body.vx, twist_body.vy, twist_body.omega);
    if !(vx.is_finite() && vy.is_finite() && w.is_finite()) {
        return Icr::Undefined;
    }
    let v = vx.hypot(vy);
    if w.abs() < ICR_OMEGA_EPS {
        if v < ICR_REST_EPS {
            return Icr::Undefined;
        }
        return Icr::AtInfinity {
            direction: vy.atan2(vx),
        };
    }
    let s = w.signum();
    let gamma = (s * vx).atan2(-s * vy);
    let rho = v / w.abs();
    Icr::Point {
        x: rho * gamma.cos(),
        y: rho * gamma.sin(),
    }
}

/// Wheel contact positions P_i = λ_i (cos α_i, sin α_i) in the body frame (m).
/// Legs missing from `legs` are taken at their nominal extension; entries past n are zero.
pub fn wheel_positions(p: &Platform, legs: &[f64]) -> [[f64; 2]; MAX_WHEELS] {
    let mut out = [[0.0; 2]; MAX_WHEELS];
    for (i, w) in p.wheels.iter().enumerate().take(MAX_WHEELS) {
        let l = legs.get(i).copied().unwrap_or(w.lambda_nominal);
        out[i] = [l * w.alpha.cos(), l * w.alpha.sin()];
    }
    out
}

/// Rotates a world vector into the body frame: Rᵀ(θ) v.
#[inline]
pub fn world_to_body(theta: f64, v: [f64; 2]) -> [f64; 2] {
    let (s, c) = theta.sin_cos();
    [c * v[0] + s * v[1], -s * v[0] + c * v[1]]
}

/// Rotates a body vector into the world frame: R(θ) v.
#[inline]
pub fn body_to_world(theta: f64, v: [f64; 2]) -> [f64; 2] {
    let (s, c) = theta.sin_cos();
    [c * v[0] - s * v[1], s * v[0] + c * v[1]]
}

/// Body-frame contact velocity u_i of wheel `i` (seed 000 eq. 18 numerator/denominator):
/// u_i = Rᵀ(θ)(ẋ, ẏ) + θ̇ λ_i e⊥_i + λ̇_i e_i, with `twist_world` = (ẋ, ẏ, θ̇).
/// Returns zero for an index past the platform's wheels.
pub fn wheel_velocity_body(
    p: &Platform,
    i: usize,
    theta: f64,
    lambda: f64,
    twist_world: &Twist,
    leg_rate: f64,
) -> [f64; 2] {
    let Some(w) = p.wheels.get(i) else {
        return [0.0; 2];
    };
    let (sa, ca) = w.alpha.sin_cos();
    let vb = world_to_body(theta, [twist_world.vx, twist_world.vy]);
    let om = twist_world.omega;
    [
        vb[0] - om * lambda * sa + leg_rate * ca,
        vb[1] + om * lambda * ca + leg_rate * sa,
    ]
}

/// Body-frame contact acceleration u̇_i (see the module docs for the derivation):
/// u̇_i = Rᵀ(θ)(ẍ, ÿ) − θ̇ J Rᵀ(θ)(ẋ, ẏ) + (θ̈ λ_i + θ̇ λ̇_i) e⊥_i + λ̈_i e_i.
/// `dz`/`ddz` hold (ẋ, ẏ, θ̇) and (ẍ, ÿ, θ̈) in their first three entries.
#[allow(clippy::too_many_arguments)]
pub fn wheel_acceleration_body(
    p: &Platform,
    i: usize,
    theta: f64,
    lambda: f64,
    leg_rate: f64,
    leg_accel: f64,
    vel_world: [f64; 3],
    acc_world: [f64; 3],
) -> [f64; 2] {
    let Some(w) = p.wheels.get(i) else {
        return [0.0; 2];
    };
    let (sa, ca) = w.alpha.sin_cos();
    let ab = world_to_body(theta, [acc_world[0], acc_world[1]]);
    let vb = world_to_body(theta, [vel_world[0], vel_world[1]]);
    let om = vel_world[2];
    // −θ̇ J v_b = −θ̇ (−v_by, v_bx) = (θ̇ v_by, −θ̇ v_bx)
    let k = acc_world[2] * lambda + om * leg_rate;
    [
        ab[0] + om * vb[1] - k * sa + leg_accel * ca,
        ab[1] - om * vb[0] + k * ca + leg_accel * sa,
    ]
}

/// Steering angle, speed and analytic steering rate from u and u̇:
/// φ = atan2(u_y, u_x), v = |u|, φ̇ = (u_x u̇_y − u_y u̇_x)/|u|². The caller checks |u| > 0.
#[inline]
pub fn steer_from_velocity(u: [f64; 2], du: [f64; 2]) -> WheelSetpoint {
    let n2 = u[0] * u[0] + u[1] * u[1];
    WheelSetpoint {
        steer_angle: u[1].atan2(u[0]),
        rolling_speed: n2.sqrt(),
        steer_rate: if n2 > 0.0 {
            (u[0] * du[1] - u[1] * du[0]) / n2
        } else {
            0.0
        },
    }
}

/// Off-centred steering ([module docs](self)): the rolling speed v_W = u·h and steering rate
/// φ̇ = (u·h⊥)/d − ω that move the steering axis of a wheel at angle `phi` with velocity `u`
/// (body frame) while the body turns at `omega`, without slip. `d` must be > 0.
#[inline]
pub fn caster_inverse(u: [f64; 2], phi: f64, omega: f64, d: f64) -> (f64, f64) {
    let (s, c) = phi.sin_cos();
    let along = u[0] * c + u[1] * s;
    let across = -u[0] * s + u[1] * c;
    (along, across / d - omega)
}

/// Off-centred steering, forward: the steering axis' body velocity u = v_W h + d (ω + φ̇) h⊥
/// of a wheel rolling at `v` (m/s) at angle `phi` turning at `phi_rate`, the body turning at
/// `omega`.
#[inline]
pub fn caster_axis_velocity(v: f64, phi: f64, phi_rate: f64, omega: f64, d: f64) -> [f64; 2] {
    let (s, c) = phi.sin_cos();
    let k = d * (omega + phi_rate);
    [v * c - k * s, v * s + k * c]
}

/// The contact point C = P − d h of a wheel whose steering axis is at `axis` (body frame).
#[inline]
pub fn contact_point(axis: [f64; 2], phi: f64, d: f64) -> [f64; 2] {
    let (s, c) = phi.sin_cos();
    [axis[0] - d * c, axis[1] - d * s]
}

/// The steady lag ε of an off-centred wheel behind its direction of travel ψ ([module
/// docs](self)): φ = ψ + ε rolling forward (`backward = false`), φ = ψ + π + ε backward, for a
/// steering axis moving at `speed` = |u| whose direction turns at `turn` = ψ̇ + θ̇ (its
/// direction's rate in the world). When the direction turns faster than |u|/d the wheel
/// cannot keep up; the lag is then ±π/2 (the wheel is across its direction of travel).
pub fn caster_lag(speed: f64, turn: f64, d: f64, backward: bool) -> f64 {
    if d <= 0.0 || !(speed.is_finite() && turn.is_finite()) || speed <= 0.0 {
        return 0.0;
    }
    let s = (d * turn / speed).clamp(-1.0, 1.0);
    if backward {
        s.asin()
    } else {
        -s.asin()
    }
}

/// Exact SE(2) integration: the pose reached after moving for `dt` seconds with the
/// constant body-frame twist `twist_body` (a circular arc, or a straight line when ω = 0).
///
/// With Δθ = ω dt the body-frame displacement is
/// (v_x sin Δθ − v_y (1 − cos Δθ), v_x (1 − cos Δθ) + v_y sin Δθ)/ω,
/// evaluated with series for small Δθ so it stays exact (to rounding) as ω → 0.
pub fn se2_integrate(pose: Pose, twist_body: &Twist, dt: f64) -> Pose {
    let dth = twist_body.omega * dt;
    // s = sin(Δθ)/Δθ, c = (1 − cos Δθ)/Δθ
    let (s, c) = if dth.abs() < 1e-4 {
        let d2 = dth * dth;
        (1.0 - d2 / 6.0, dth * (0.5 - d2 / 24.0))
    } else {
        (dth.sin() / dth, (1.0 - dth.cos()) / dth)
    };
    let (vx, vy) = (twist_body.vx * dt, twist_body.vy * dt);
    let d = [vx * s - vy * c, vx * c + vy * s];
    let w = body_to_world(pose.theta, d);
    Pose {
        x: pose.x + w[0],
        y: pose.y + w[1],
        theta: pose.theta + dth,
    }
}

fn check_finite(v: &ZVec, n: usize, what: &'static str) -> Result<(), KinematicsError> {
    if v.iter().take(3 + n).all(|x| x.is_finite()) {
        Ok(())
    } else {
        Err(KinematicsError::NonFinite { what })
    }
}

/// Inverse kinematics from the output trajectory (seed 000 eqs. 18 and 22 with the
/// analytic steering rate): z = (x, y, θ, λ), ż, z̈ (x, y in the world frame) → per-wheel
/// steering angle, rolling speed (≥ 0) and steering rate.
///
/// Returns [`KinematicsError::Singular`] for the first wheel whose contact speed |u_i| is
/// below `eps` (m/s) and [`KinematicsError::NonFinite`] for NaN/∞ input.
pub fn wheel_setpoints(
    p: &Platform,
    z: &ZVec,
    dz: &ZVec,
    ddz: &ZVec,
    eps: f64,
) -> Result<[WheelSetpoint; MAX_WHEELS], KinematicsError> {
    let n = p.n().min(MAX_WHEELS);
    check_finite(z, n, "z")?;
    check_finite(dz, n, "dz")?;
    check_finite(ddz, n, "ddz")?;
    let mut out = [WheelSetpoint::default(); MAX_WHEELS];
    let theta = z[2];
    let vel = [dz[0], dz[1], dz[2]];
    let acc = [ddz[0], ddz[1], ddz[2]];
    let tw = Twist {
        vx: dz[0],
        vy: dz[1],
        omega: dz[2],
    };
    for (i, o) in out.iter_mut().enumerate().take(n) {
        let (l, dl, ddl) = (z[3 + i], dz[3 + i], ddz[3 + i]);
        let u = wheel_velocity_body(p, i, theta, l, &tw, dl);
        let speed = u[0].hypot(u[1]);
        if speed < eps || speed == 0.0 {
            return Err(KinematicsError::Singular { wheel: i, speed });
        }
        let du = wheel_acceleration_body(p, i, theta, l, dl, ddl, vel, acc);
        *o = steer_from_velocity(u, du);
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::angle;

    fn state(t: f64) -> (ZVec, ZVec, ZVec) {
        // A smooth, non-trivial motion: a circle-ish path with rotation and legs moving.
        let mut z = ZVec::zeros();
        let mut dz = ZVec::zeros();
        let mut ddz = ZVec::zeros();
        z[0] = 0.3 * t + 0.2 * (0.7 * t).sin();
        dz[0] = 0.3 + 0.14 * (0.7 * t).cos();
        ddz[0] = -0.098 * (0.7 * t).sin();
        z[1] = 0.1 * t * t;
        dz[1] = 0.2 * t;
        ddz[1] = 0.2;
        z[2] = 0.4 * (0.5 * t).sin();
        dz[2] = 0.2 * (0.5 * t).cos();
        ddz[2] = -0.1 * (0.5 * t).sin();
        for i in 0..4 {
            let f = 0.3 + 0.1 * i as f64;
            z[3 + i] = 0.45 + 0.05 * (f * t).sin();
            dz[3 + i] = 0.05 * f * (f * t).cos();
            ddz[3 + i] = -0.05 * f * f * (f * t).sin();
        }
        (z, dz, ddz)
    }

    #[test]
    fn steering_rate_matches_finite_difference_of_angle() {
        let p = Platform::justin();
        let h = 1e-6;
        for &t in &[0.3, 1.1, 2.7, 4.0] {
            let (z, dz, ddz) = state(t);
            let sp = wheel_setpoints(&p, &z, &dz, &ddz, 1e-6).unwrap();
            let (z1, dz1, ddz1) = state(t + h);
            let (z0, dz0, ddz0) = state(t - h);
            let s1 = wheel_setpoints(&p, &z1, &dz1, &ddz1, 1e-6).unwrap();
            let s0 = wheel_setpoints(&p, &z0, &dz0, &ddz0, 1e-6).unwrap();
            for i in 0..4 {
                let fd = angle::diff(s1[i].steer_angle, s0[i].steer_angle) / (2.0 * h);
                assert!(
                    (fd - sp[i].steer_rate).abs() < 1e-6,
                    "t={t} wheel {i}: analytic {} vs fd {fd}",
                    sp[i].steer_rate
                );
            }
        }
    }

    #[test]
    fn contact_velocity_matches_finite_difference_of_world_position() {
        // u_i must be Rᵀ(θ) d/dt [ (x,y) + R(θ) λ_i e_i ].
        let p = Platform::justin();
        let h = 1e-6;
        let t = 1.7;
        let (z, dz, _) = state(t);
        let (z1, _, _) = state(t + h);
        let (z0, _, _) = state(t - h);
        let pos = |z: &ZVec, i: usize| {
            let a = p.wheels[i].alpha;
            let pb = [z[3 + i] * a.cos(), z[3 + i] * a.sin()];
            let pw = body_to_world(z[2], pb);
            [z[0] + pw[0], z[1] + pw[1]]
        };
        let tw = Twist {
            vx: dz[0],
            vy: dz[1],
            omega: dz[2],
        };
        for i in 0..4 {
            let (a, b) = (pos(&z1, i), pos(&z0, i));
            let vw = [(a[0] - b[0]) / (2.0 * h), (a[1] - b[1]) / (2.0 * h)];
            let fd = world_to_body(z[2], vw);
            let u = wheel_velocity_body(&p, i, z[2], z[3 + i], &tw, dz[3 + i]);
            assert!((fd[0] - u[0]).abs() < 1e-7 && (fd[1] - u[1]).abs() < 1e-7);
        }
    }

    #[test]
    fn singular_wheel_is_reported_not_nan() {
        let p = Platform::justin();
        // Pure rotation about wheel 0: ICR on the wheel.
        let mut z = ZVec::zeros();
        let mut dz = ZVec::zeros();
        for i in 0..4 {
            z[3 + i] = 0.45;
        }
        let a = p.wheels[0].alpha;
        let w = 0.3;
        // body origin velocity so that wheel 0 is at rest: v = −ω × P_0
        dz[0] = w * 0.45 * a.sin();
        dz[1] = -w * 0.45 * a.cos();
        dz[2] = w;
        let r = wheel_setpoints(&p, &z, &dz, &ZVec::zeros(), 1e-3);
        match r {
            Err(KinematicsError::Singular { wheel: 0, speed }) => assert!(speed < 1e-12),
            other => panic!("expected singular wheel 0, got {other:?}"),
        }
        let mut bad = dz;
        bad[1] = f64::NAN;
        assert!(matches!(
            wheel_setpoints(&p, &z, &bad, &ZVec::zeros(), 1e-3),
            Err(KinematicsError::NonFinite { what: "dz" })
        ));
    }

    #[test]
    fn icr_follows_seed001_and_is_the_zero_velocity_point() {
        let tw = Twist {
            vx: 0.3,
            vy: -0.1,
            omega: 0.5,
        };
        match icr_body(&tw) {
            Icr::Point { x, y } => {
                // velocity of the body point (x, y): v + ω × (x, y) = 0
                assert!((tw.vx - tw.omega * y).abs() < 1e-12);
                assert!((tw.vy + tw.omega * x).abs() < 1e-12);
            }
            other => panic!("{other:?}"),
        }
        let neg = Twist { omega: -0.5, ..tw };
        match icr_body(&neg) {
            Icr::Point { x, y } => {
                assert!((neg.vx - neg.omega * y).abs() < 1e-12);
                assert!((neg.vy + neg.omega * x).abs() < 1e-12);
            }
            other => panic!("{other:?}"),
        }
        match icr_body(&Twist {
            vx: 0.0,
            vy: 0.2,
            omega: 0.0,
        }) {
            Icr::AtInfinity { direction } => {
                assert!((direction - std::f64::consts::FRAC_PI_2).abs() < 1e-12)
            }
            other => panic!("{other:?}"),
        }
        assert_eq!(icr_body(&Twist::default()), Icr::Undefined);
    }

    #[test]
    fn se2_integration_is_exact_on_arcs_and_lines() {
        let p0 = Pose {
            x: 1.0,
            y: -2.0,
            theta: 0.3,
        };
        let tw = Twist {
            vx: 0.4,
            vy: 0.1,
            omega: 0.8,
        };
        // many tiny Euler steps converge to the exact result
        let mut q = p0;
        let n = 200_000;
        for _ in 0..n {
            let v = body_to_world(q.theta, [tw.vx, tw.vy]);
            q.x += v[0] * 2.0 / n as f64;
            q.y += v[1] * 2.0 / n as f64;
            q.theta += tw.omega * 2.0 / n as f64;
        }
        let e = se2_integrate(p0, &tw, 2.0);
        assert!((e.x - q.x).abs() < 1e-5 && (e.y - q.y).abs() < 1e-5);
        // composition: two half steps equal one full step
        let h = se2_integrate(se2_integrate(p0, &tw, 1.0), &tw, 1.0);
        assert!((h.x - e.x).abs() < 1e-12 && (h.y - e.y).abs() < 1e-12);
        let small = Twist { omega: 1e-9, ..tw };
        let line = se2_integrate(p0, &small, 2.0);
        let v = body_to_world(0.3, [0.8, 0.2]);
        assert!((line.x - 1.0 - v[0]).abs() < 1e-8 && (line.y + 2.0 - v[1]).abs() < 1e-8);
    }

    #[test]
    fn wheel_positions_follow_leg_directions() {
        let p = Platform::justin();
        let pos = wheel_positions(&p, &[0.4, 0.5, 0.37, 0.56]);
        for (i, l) in [0.4, 0.5, 0.37, 0.56].iter().enumerate() {
            assert!((pos[i][0].hypot(pos[i][1]) - l).abs() < 1e-12);
            assert!(angle::diff(pos[i][1].atan2(pos[i][0]), p.wheels[i].alpha).abs() < 1e-12);
        }
        assert_eq!(pos[5], [0.0, 0.0]);
    }

    #[test]
    fn caster_inverse_and_forward_agree_and_slip_free_motion_moves_the_contact_along_the_wheel() {
        let d = 0.045;
        for &(u, phi, om) in &[
            ([0.3, 0.1], 0.2, 0.4),
            ([-0.2, 0.5], -2.0, -0.3),
            ([0.0, 0.0], 1.0, 0.0),
        ] {
            let (v, rate) = caster_inverse(u, phi, om, d);
            let back = caster_axis_velocity(v, phi, rate, om, d);
            assert!((back[0] - u[0]).abs() < 1e-12 && (back[1] - u[1]).abs() < 1e-12);
            // The contact point's velocity u − d(ω + φ̇) h⊥ lies along the wheel: v h.
            let (s, c) = phi.sin_cos();
            let k = d * (om + rate);
            let cv = [u[0] + k * s, u[1] - k * c];
            assert!((cv[0] - v * c).abs() < 1e-12 && (cv[1] - v * s).abs() < 1e-12);
        }
        // At rest no steering is slip-free.
        assert_eq!(caster_inverse([0.0, 0.0], 0.7, 0.0, d), (0.0, 0.0));
        // The contact point trails the axis.
        let c = contact_point([1.0, 0.0], 0.0, d);
        assert!((c[0] - (1.0 - d)).abs() < 1e-15 && c[1] == 0.0);
    }

    #[test]
    fn a_trailing_caster_settles_on_its_lag_along_a_circle() {
        // Steering axis on a circle of radius R at speed v (world frame, body not turning):
        // integrate the slip-free steering rate; the angle settles at ψ + caster_lag.
        let (d, r, v) = (0.045, 0.5, 0.4);
        let w = v / r;
        let mut phi = 1.2; // start far off
        let dt = 1e-4;
        let mut t = 0.0;
        while t < 3.0 {
            let psi = std::f64::consts::FRAC_PI_2 + w * t;
            let u = [v * psi.cos(), v * psi.sin()];
            let (_, rate) = caster_inverse(u, phi, 0.0, d);
            phi += rate * dt;
            t += dt;
        }
        let psi = std::f64::consts::FRAC_PI_2 + w * t;
        let lag = caster_lag(v, w, d, false);
        assert!(lag < 0.0, "trails behind the turn");
        assert!(
            angle::diff(phi, psi + lag).abs() < 1e-4,
            "{phi} vs {}",
            psi + lag
        );
    }
}
