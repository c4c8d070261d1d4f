//! Dead reckoning from the wheel modules' encoders.
//!
//! Each wheel i reports its steering angle φ_i, spin rate ω_i, leg extension λ_i and leg
//! rate λ̇_i. Its contact velocity in the body frame is w_i = r ω_i (cos φ_i, sin φ_i) and,
//! by the rolling model (seed 000 eq. 18; DESIGN.md),
//!
//! ```text
//! w_i = (v_x, v_y) + ω λ_i e⊥_i + λ̇_i e_i
//! ```
//!
//! With λ̇_i measured these are 2n linear equations A x = b in the 3 unknowns
//! x = (v_x, v_y, ω) (A_i = [[1, 0, −λ_i sin α_i], [0, 1, λ_i cos α_i]],
//! b_i = w_i − λ̇_i e_i), solved by least squares through the 3×3 normal equations. The
//! RMS per-wheel mismatch √(Σ|A_i x − b_i|²/n) is reported as a slip indicator: zero for
//! consistent wheels, of the order of the slip speed when one wheel slips.
//!
//! A wheel without a leg has λ_i fixed and λ̇_i = 0. An off-centred wheel (caster offset
//! d > 0, [`crate::model::kinematics`], "Off-centred steering") rolls at its contact point
//! C_i = P_i − d h_i, which moves on the body as the wheel steers: the body's velocity at
//! C_i is the rolling velocity plus the steering's sweep, v_W h_i + d φ̇_i h⊥_i, so its rows
//! are A_i = [[1, 0, −C_iy], [0, 1, C_ix]] with b_i = v_W h_i + d φ̇_i h⊥_i − λ̇_i e_i (the
//! measured steering rate enters the estimate).
//!
//! Timing. What a reading at the end of a cycle says about the cycle that just ended depends
//! on the drives, so it is a setting ([`Sampling`]):
//!
//! - [`Sampling::Continuous`] (real drives and the simulator; the runtime's default): speeds
//!   and angles change continuously and each reading is the instantaneous value at the SYNC
//!   that sampled it. The speed at the end of an interval leads the interval's mean by about
//!   half a cycle, so integrating it over the whole interval makes the heading estimate lead
//!   the truth by ω·dt/2 while turning; rotated into the world, that offset becomes a lateral
//!   drift of v·ω·dt/2 (0.155 mm/s on the seed-000 run: 3.7 mm over 25 s, measured against the
//!   simulator). The twist is therefore integrated with the trapezoidal rule: the mean of the
//!   twists solved at both ends of the interval (each from that instant's angles, legs and
//!   speeds).
//! - [`Sampling::ZeroOrderHold`] (the ideal plant, whose commands are held over each
//!   cycle): the reported speeds are the held values of the cycle that just ended, and only
//!   the angles and legs moved during it, so they are taken back to the middle of the cycle
//!   (φ_i − φ̇_i dt/2, λ_i − λ̇_i dt/2) before solving.
//!
//! Either way the twist is integrated exactly on SE(2) over dt
//! ([`crate::model::kinematics::se2_integrate`]).
//!
//! # Uncertainty
//!
//! The twist is a least-squares estimate x̂ = (AᵀA)⁻¹Aᵀb from 2n equations in 3 unknowns, so
//! its covariance is Σ_v = σ² (AᵀA)⁻¹ with σ² the variance of one equation's error. It is
//! estimated from the data: the residual sum of squares over its 2n − 3 degrees of freedom,
//! floored by what the encoders' resolution alone leaves (a uniform quantisation error of
//! one step q has variance q²/12: (r q_ω)²/12 along the wheel, (|u| q_φ)²/12 across it;
//! [`EncoderResolution`]). The pose is propagated through the SE(2) step,
//! P ← F P Fᵀ + G Σ_v Gᵀ, F = ∂ξ⁺/∂ξ (the heading error swings the displacement),
//! G = ∂ξ⁺/∂v = R(θ) dt (and dt for θ), the twist errors of successive cycles taken as
//! independent. The residual also holds the wheels' momentary disagreement while they
//! accelerate (each drive lags on its own), which does not all turn into drift, so the
//! estimate is on the safe side (over a 60 s random session in the simulator the true final
//! error was about a tenth of the reported σ; `tests/tests/e2e_drive.rs`). The covariance
//! does not know systematic errors (a wrong wheel radius, a slipping wheel the
//! residual does not see); the slip residual is reported separately.
//!
//! # Which wheel slips
//!
//! The residual says that the wheels disagree, not which one. Least squares spreads one
//! wheel's error e over every wheel: the residuals are (I − H) e, H = A(AᵀA)⁻¹Aᵀ the hat
//! matrix, so the slipping wheel keeps only part of its own error and the others take the
//! rest; on Justin's four wheels the largest residual is not always the slipping wheel's.
//! The odometry therefore also fits the twist without each wheel k in turn (leave-one-out:
//! n more 3×3 solves, 2(n − 1) ≥ 4 equations in 3 unknowns for n ≥ 3, done on request,
//! [`Odometry::slip_suspect`], which the runtime makes only while the residual is above the
//! slip threshold) and names the wheel whose removal leaves the others most consistent
//! ([`SlipSuspect`]). If only
//! wheel k is wrong, the others fit exactly (their RMS mismatch is the encoders' and the
//! drives' momentary lag), and wheel k's distance from what that fit gives it is e itself,
//! undiluted: a wheel spinning 0.1 m/s faster than the ground under it is 0.1 m/s off. If
//! several wheels are wrong, no removal leaves the rest consistent, which the supervisor
//! says instead of naming one ([`crate::supervisor::SLIP_SINGLE_WHEEL`]).

// Index loops over parallel per-wheel arrays read better than zipped iterators here.
#![allow(clippy::needless_range_loop)]

use crate::model::kinematics::{body_to_world, se2_integrate};
use crate::model::platform::Platform;
use crate::types::{Measurement, Pose, Twist, MAX_WHEELS};
use nalgebra::{Matrix3, Vector3};

/// Result of one odometry update.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct OdometryOutput {
    /// Covariance of the pose (x, y, θ) after the update (module docs, "Uncertainty").
    pub pose_covariance: [[f64; 3]; 3],
    /// Covariance of the least-squares body twist (v_x, v_y, ω).
    pub twist_covariance: [[f64; 3]; 3],
    /// Pose after the update.
    pub pose: Pose,
    /// Least-squares body twist over the cycle (m/s, m/s, rad/s).
    pub twist_body: Twist,
    /// The same twist in the world frame at the updated heading.
    pub twist_world: Twist,
    /// RMS per-wheel velocity mismatch (m/s): the slip indicator.
    pub residual: f64,
}

/// Least-squares body twist and RMS residual from wheel contact velocities `w` (body
/// frame), legs and leg rates. Returns `None` if the normal matrix is singular or the
/// input is not finite.
pub fn twist_from_wheels(
    p: &Platform,
    n: usize,
    w: &[[f64; 2]; MAX_WHEELS],
    legs: &[f64; MAX_WHEELS],
    leg_rates: &[f64; MAX_WHEELS],
) -> Option<(Twist, f64)> {
    let r = Readings {
        n,
        w: *w,
        legs: *legs,
        leg_rates: *leg_rates,
        steer: [None; MAX_WHEELS],
    };
    solve(p, &r, None).map(|s| (s.twist, s.rms))
}

/// The least-squares solution with what its covariance needs.
struct Solution {
    twist: Twist,
    /// RMS per-wheel mismatch (m/s).
    rms: f64,
    /// Sum of squared residuals (m²/s²).
    rss: f64,
    /// The normal matrix AᵀA.
    ata: Matrix3<f64>,
}

/// Where a wheel's rows of the least-squares system sit, and the extra velocity they carry:
/// for an off-centred wheel its contact point C_i = P_i − d h_i and the steering's sweep
/// d φ̇_i h⊥_i; `None` for a centred wheel (the rows at P_i, as seed 000).
fn offset_rows(
    wc: &crate::model::platform::WheelConfig,
    leg: f64,
    steer: Option<(f64, f64)>,
) -> Option<([f64; 2], [f64; 2])> {
    let d = wc.caster_offset;
    let (phi, rate) = steer?;
    if d <= 0.0 {
        return None;
    }
    let (sa, ca) = wc.alpha.sin_cos();
    let c = crate::model::kinematics::contact_point([leg * ca, leg * sa], phi, d);
    let (s, co) = phi.sin_cos();
    Some((c, [-d * rate * s, d * rate * co]))
}

/// One cycle's readings as the least-squares system takes them: per wheel its contact
/// velocity (body frame), leg, leg rate and, for an off-centred wheel, its steering angle and
/// rate.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
struct Readings {
    n: usize,
    w: [[f64; 2]; MAX_WHEELS],
    legs: [f64; MAX_WHEELS],
    leg_rates: [f64; MAX_WHEELS],
    steer: [Option<(f64, f64)>; MAX_WHEELS],
}

/// A wheel's rows of the least-squares system: (A_i as two rows, b_i).
fn rows(
    wc: &crate::model::platform::WheelConfig,
    w: [f64; 2],
    leg: f64,
    leg_rate: f64,
    steer: Option<(f64, f64)>,
) -> ([Vector3<f64>; 2], [f64; 2]) {
    let (sa, ca) = wc.alpha.sin_cos();
    let (c, sweep) = offset_rows(wc, leg, steer).unwrap_or(([leg * ca, leg * sa], [0.0, 0.0]));
    (
        [Vector3::new(1.0, 0.0, -c[1]), Vector3::new(0.0, 1.0, c[0])],
        [
            w[0] + sweep[0] - leg_rate * ca,
            w[1] + sweep[1] - leg_rate * sa,
        ],
    )
}

/// The least-squares solution over the readings' wheels but `skip`.
fn solve(p: &Platform, r: &Readings, skip: Option<usize>) -> Option<Solution> {
    // The rows of the wheels used, built once for the solve and the residual.
    let mut sys = [([Vector3::<f64>::zeros(); 2], [0.0; 2]); MAX_WHEELS];
    let mut count = 0usize;
    for (i, wc) in p.wheels.iter().enumerate().take(r.n) {
        if Some(i) != skip {
            sys[count] = rows(wc, r.w[i], r.legs[i], r.leg_rates[i], r.steer[i]);
            count += 1;
        }
    }
    let sys = &sys[..count];
    let mut ata = Matrix3::<f64>::zeros();
    let mut atb = Vector3::<f64>::zeros();
    for (a, b) in sys {
        ata += a[0] * a[0].transpose() + a[1] * a[1].transpose();
        atb += a[0] * b[0] + a[1] * b[1];
    }
    let x = ata.lu().solve(&atb)?;
    if !x.iter().all(|v| v.is_finite()) {
        return None;
    }
    let sq: f64 = sys
        .iter()
        .map(|(a, b)| (a[0].dot(&x) - b[0]).powi(2) + (a[1].dot(&x) - b[1]).powi(2))
        .sum();
    Some(Solution {
        twist: Twist {
            vx: x[0],
            vy: x[1],
            omega: x[2],
        },
        rms: (sq / count.max(1) as f64).sqrt(),
        rss: sq,
        ata,
    })
}

/// The wheel the slip residual most likely comes from (module docs, "Which wheel slips").
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct SlipSuspect {
    /// Wheel index (from 0).
    pub wheel: usize,
    /// How far (m/s) the wheel's measured contact velocity is from the one the twist fitted
    /// to the other wheels gives it.
    pub off: f64,
    /// RMS mismatch (m/s) of the other wheels about their own fit.
    pub others: f64,
}

/// Leave-one-out over the wheels (module docs, "Which wheel slips"); `None` for fewer than
/// three wheels or where no fit without a wheel is solvable.
fn slip_suspect(p: &Platform, r: &Readings) -> Option<SlipSuspect> {
    let n = r.n;
    if n < 3 {
        return None;
    }
    let mut best: Option<SlipSuspect> = None;
    for k in 0..n {
        let Some(sol) = solve(p, r, Some(k)) else {
            continue;
        };
        if best.is_some_and(|b| b.others <= sol.rms) {
            continue;
        }
        let x = Vector3::new(sol.twist.vx, sol.twist.vy, sol.twist.omega);
        let (a, b) = rows(&p.wheels[k], r.w[k], r.legs[k], r.leg_rates[k], r.steer[k]);
        best = Some(SlipSuspect {
            wheel: k,
            off: (a[0].dot(&x) - b[0]).hypot(a[1].dot(&x) - b[1]),
            others: sol.rms,
        });
    }
    best
}

/// Resolution of the encoders the odometry reads (one step of the transmitted value).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct EncoderResolution {
    /// Wheel speed step (rad/s).
    pub wheel_speed: f64,
    /// Steering angle step (rad).
    pub steer_angle: f64,
}

impl Default for EncoderResolution {
    /// The native protocol's steps: 0.001 rad/s wheel speed, 1e-4 rad steering angle.
    fn default() -> Self {
        Self {
            wheel_speed: 1e-3,
            steer_angle: 1e-4,
        }
    }
}

/// How readings relate to the motion between them (see the module docs).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum Sampling {
    /// Instantaneous samples of continuously changing speeds (real drives, the simulator).
    #[default]
    Continuous,
    /// Speeds held constant over each cycle (the ideal plant).
    ZeroOrderHold,
}

/// Dead-reckoning state.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct Odometry {
    pose: Pose,
    sampling: Sampling,
    prev: Option<Twist>,
    resolution: EncoderResolution,
    pose_cov: Matrix3<f64>,
    /// The last update's readings, when they were valid ([`Odometry::slip_suspect`]).
    last: Option<Readings>,
}

impl Odometry {
    /// Starts at `pose`, for continuously sampled drives ([`Sampling::Continuous`]).
    pub fn new(pose: Pose) -> Self {
        Self::with_sampling(pose, Sampling::Continuous)
    }

    /// Starts at `pose` with the given sampling model.
    pub fn with_sampling(pose: Pose, sampling: Sampling) -> Self {
        Self {
            pose,
            sampling,
            prev: None,
            resolution: EncoderResolution::default(),
            pose_cov: Matrix3::zeros(),
            last: None,
        }
    }

    /// Sets the encoders' resolution (the floor of the twist covariance).
    pub fn set_resolution(&mut self, r: EncoderResolution) {
        self.resolution = r;
    }

    /// The pose covariance accumulated so far.
    pub fn pose_covariance(&self) -> [[f64; 3]; 3] {
        to_array(&self.pose_cov)
    }

    /// The wheel the last update's residual most likely comes from (module docs, "Which
    /// wheel slips"): n more least-squares solves, so the runtime asks only once the
    /// residual is above the slip threshold. `None` with fewer than three wheels, or when the
    /// last readings were not valid.
    pub fn slip_suspect(&self, p: &Platform) -> Option<SlipSuspect> {
        self.last.as_ref().and_then(|r| slip_suspect(p, r))
    }

    /// Current pose estimate.
    pub fn pose(&self) -> Pose {
        self.pose
    }

    /// Resets the estimate to `pose` (known exactly: the covariance restarts at zero).
    pub fn set_pose(&mut self, pose: Pose) {
        self.pose = pose;
        self.prev = None;
        self.pose_cov = Matrix3::zeros();
    }

    /// Integrates one cycle of measurements taken `dt` seconds after the previous ones.
    /// Non-finite measurements, fewer than two wheels or a non-positive `dt` leave the
    /// pose unchanged (the output then carries a zero twist and an infinite residual).
    pub fn update(&mut self, p: &Platform, m: &Measurement, dt: f64) -> OdometryOutput {
        let n = p.n().min(m.n).min(MAX_WHEELS);
        let mut r = Readings {
            n,
            w: [[0.0; 2]; MAX_WHEELS],
            legs: [0.0; MAX_WHEELS],
            leg_rates: [0.0; MAX_WHEELS],
            steer: [None; MAX_WHEELS],
        };
        let dtc = if dt.is_finite() && dt > 0.0 { dt } else { 0.0 };
        let mut ok = n >= 2 && dtc > 0.0;
        let back = match self.sampling {
            Sampling::Continuous => 0.0,
            Sampling::ZeroOrderHold => 0.5 * dtc,
        };
        for i in 0..n {
            let wm = &m.wheels[i];
            let phi = wm.steer_angle - back * wm.steer_rate;
            let v = p.wheel_radius * wm.wheel_speed;
            r.w[i] = [v * phi.cos(), v * phi.sin()];
            r.legs[i] = wm.leg - back * wm.leg_rate;
            r.leg_rates[i] = wm.leg_rate;
            if p.wheels[i].off_centred() {
                r.steer[i] = Some((phi, wm.steer_rate));
                ok &= wm.steer_rate.is_finite();
            }
            ok &= r.w[i][0].is_finite()
                && r.w[i][1].is_finite()
                && r.legs[i].is_finite()
                && r.leg_rates[i].is_finite();
        }
        let solved = if ok { solve(p, &r, None) } else { None };
        self.last = solved.as_ref().map(|_| r);
        let Some(sol) = solved else {
            return OdometryOutput {
                pose: self.pose,
                twist_body: Twist::default(),
                twist_world: Twist::default(),
                residual: f64::INFINITY,
                pose_covariance: to_array(&self.pose_cov),
                twist_covariance: [[f64::INFINITY; 3]; 3],
            };
        };
        let (tw, residual) = (sol.twist, sol.rms);
        // Twist covariance σ² (AᵀA)⁻¹ (module docs, "Uncertainty").
        let mut umax = 0.0f64;
        for wi in r.w.iter().take(n) {
            umax = umax.max(wi[0].hypot(wi[1]));
        }
        let q = self.resolution;
        let enc =
            (p.wheel_radius * q.wheel_speed).powi(2) / 12.0 + (umax * q.steer_angle).powi(2) / 12.0;
        let dof = (2 * n).saturating_sub(3).max(1) as f64;
        let sigma2 = (sol.rss / dof).max(enc);
        let twist_cov = sol
            .ata
            .try_inverse()
            .map(|m| m * sigma2)
            .unwrap_or_else(|| Matrix3::from_diagonal_element(f64::INFINITY));
        let step = match (self.sampling, self.prev) {
            (Sampling::Continuous, Some(prev)) => Twist {
                vx: 0.5 * (prev.vx + tw.vx),
                vy: 0.5 * (prev.vy + tw.vy),
                omega: 0.5 * (prev.omega + tw.omega),
            },
            _ => tw,
        };
        self.prev = Some(tw);
        let before = self.pose;
        self.pose = se2_integrate(self.pose, &step, dtc);
        // Propagation: P ← F P Fᵀ + G Σ_v Gᵀ · (τ_c/dt), with F = ∂pose⁺/∂pose and
        // G = ∂pose⁺/∂v (module docs).
        let (dx, dy) = (self.pose.x - before.x, self.pose.y - before.y);
        let f = Matrix3::new(1.0, 0.0, -dy, 0.0, 1.0, dx, 0.0, 0.0, 1.0);
        let (s, c) = (before.theta + 0.5 * step.omega * dtc).sin_cos();
        let g = Matrix3::new(c * dtc, -s * dtc, 0.0, s * dtc, c * dtc, 0.0, 0.0, 0.0, dtc);
        self.pose_cov = f * self.pose_cov * f.transpose() + g * twist_cov * g.transpose();
        let vw = body_to_world(self.pose.theta, [tw.vx, tw.vy]);
        OdometryOutput {
            pose_covariance: to_array(&self.pose_cov),
            twist_covariance: to_array(&twist_cov),
            pose: self.pose,
            twist_body: tw,
            twist_world: Twist {
                vx: vw[0],
                vy: vw[1],
                omega: tw.omega,
            },
            residual,
        }
    }
}

fn to_array(m: &Matrix3<f64>) -> [[f64; 3]; 3] {
    let mut a = [[0.0; 3]; 3];
    for (r, row) in a.iter_mut().enumerate() {
        for (c, v) in row.iter_mut().enumerate() {
            *v = m[(r, c)];
        }
    }
    a
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::model::kinematics::wheel_velocity_body;
    use crate::types::WheelMeasurement;

    fn consistent_measurement(
        p: &Platform,
        tw_body: Twist,
        legs: [f64; 4],
        rates: [f64; 4],
    ) -> Measurement {
        let mut m = Measurement {
            n: 4,
            ..Measurement::default()
        };
        for i in 0..4 {
            // θ = 0 so world and body coincide; the encoders are read at the end of a
            // 4 ms cycle, so the wheel moved with the mid-cycle leg extension
            let mid = legs[i] - 0.002 * rates[i];
            let u = wheel_velocity_body(p, i, 0.0, mid, &tw_body, rates[i]);
            m.wheels[i] = WheelMeasurement {
                steer_angle: u[1].atan2(u[0]),
                steer_rate: 0.0,
                wheel_speed: u[0].hypot(u[1]) / p.wheel_radius,
                leg: legs[i],
                leg_rate: rates[i],
            };
        }
        m
    }

    #[test]
    fn consistent_wheels_give_zero_residual_and_the_true_twist() {
        let p = Platform::justin();
        let tw = Twist {
            vx: 0.3,
            vy: -0.2,
            omega: 0.4,
        };
        let m = consistent_measurement(&p, tw, [0.4, 0.45, 0.5, 0.55], [0.01, -0.02, 0.0, 0.03]);
        let mut o = Odometry::with_sampling(Pose::default(), Sampling::ZeroOrderHold);
        let out = o.update(&p, &m, 0.004);
        assert!(out.residual < 1e-12, "residual {}", out.residual);
        assert!((out.twist_body.vx - 0.3).abs() < 1e-12);
        assert!((out.twist_body.vy + 0.2).abs() < 1e-12);
        assert!((out.twist_body.omega - 0.4).abs() < 1e-12);
        let expect = se2_integrate(Pose::default(), &tw, 0.004);
        assert!(
            (out.pose.x - expect.x).abs() < 1e-15 && (out.pose.theta - expect.theta).abs() < 1e-15
        );
    }

    #[test]
    fn a_slipping_wheel_shows_a_clear_residual() {
        let p = Platform::justin();
        let tw = Twist {
            vx: 0.2,
            vy: 0.1,
            omega: 0.0,
        };
        let mut m = consistent_measurement(&p, tw, [0.45; 4], [0.0; 4]);
        // wheel 2 spins 0.1 m/s faster than the ground moves under it
        m.wheels[2].wheel_speed += 0.1 / p.wheel_radius;
        let out = Odometry::new(Pose::default()).update(&p, &m, 0.004);
        // one wheel off by 0.1 m/s: least squares spreads it, the RMS stays a clear fraction
        assert!(out.residual > 0.03, "residual {}", out.residual);
        assert!(out.residual < 0.1);
    }

    #[test]
    fn leave_one_out_names_the_slipping_wheel_and_its_whole_error() {
        let p = Platform::justin();
        let tw = Twist {
            vx: 0.3,
            vy: -0.1,
            omega: 0.5,
        };
        let legs = [0.42, 0.47, 0.5, 0.55];
        for k in 0..4 {
            let mut m = consistent_measurement(&p, tw, legs, [0.0; 4]);
            // wheel k spins 0.08 m/s faster than the ground moves under it
            m.wheels[k].wheel_speed += 0.08 / p.wheel_radius;
            let mut o = Odometry::new(Pose::default());
            o.update(&p, &m, 0.004);
            let s = o.slip_suspect(&p).expect("four wheels: a suspect");
            assert_eq!(s.wheel, k, "{s:?}");
            assert!((s.off - 0.08).abs() < 1e-9, "wheel {k}: off {}", s.off);
            assert!(s.others < 1e-9, "wheel {k}: others {}", s.others);
        }
    }

    #[test]
    fn two_wrong_wheels_leave_no_consistent_rest() {
        let p = Platform::justin();
        let tw = Twist {
            vx: 0.2,
            vy: 0.2,
            omega: -0.3,
        };
        let mut m = consistent_measurement(&p, tw, [0.45; 4], [0.0; 4]);
        m.wheels[0].wheel_speed += 0.1 / p.wheel_radius;
        m.wheels[2].steer_angle += 0.3;
        let mut o = Odometry::new(Pose::default());
        o.update(&p, &m, 0.004);
        let s = o.slip_suspect(&p).expect("a suspect");
        // without either wrong wheel the other one still disagrees with the remaining two
        assert!(
            s.others > crate::supervisor::SLIP_SINGLE_WHEEL * s.off,
            "{s:?} would name one wheel"
        );
    }

    #[test]
    fn garbage_leaves_the_pose_unchanged() {
        let p = Platform::justin();
        let mut m = consistent_measurement(
            &p,
            Twist {
                vx: 0.1,
                vy: 0.0,
                omega: 0.0,
            },
            [0.45; 4],
            [0.0; 4],
        );
        m.wheels[1].wheel_speed = f64::NAN;
        let mut o = Odometry::new(Pose {
            x: 1.0,
            y: 2.0,
            theta: 3.0,
        });
        let out = o.update(&p, &m, 0.004);
        assert_eq!(
            out.pose,
            Pose {
                x: 1.0,
                y: 2.0,
                theta: 3.0
            }
        );
        assert!(out.residual.is_infinite());
        // Nothing to name from a reading that was not valid, even after a valid one.
        m.wheels[1].wheel_speed = 0.1 / p.wheel_radius;
        o.update(&p, &m, 0.004);
        assert!(o.slip_suspect(&p).is_some());
        let out = o.update(&p, &Measurement::default(), 0.004);
        assert!(out.residual.is_infinite());
        assert!(o.slip_suspect(&p).is_none());
    }

    /// Heading and turn rate of the test motion: ω ramps from 0 to 0.31 rad/s over 2 s.
    fn heading(t: f64) -> (f64, f64) {
        let w = 0.31;
        if t < 2.0 {
            (w * t * t / 4.0, w * t / 2.0)
        } else {
            (w * (t - 1.0), w)
        }
    }

    /// Samples of a continuous motion: a straight world line at 0.25 m/s while the platform
    /// spins up to 0.31 rad/s (the seed-000 cruise), legs fixed. The measurement at time t.
    fn sampled_translation_while_turning(p: &Platform, t: f64) -> Measurement {
        let v = 0.25;
        let (theta, w) = heading(t);
        let (s, c) = theta.sin_cos();
        let tw_body = Twist {
            vx: c * v,
            vy: -s * v,
            omega: w,
        };
        let mut m = Measurement {
            n: 4,
            ..Measurement::default()
        };
        for i in 0..4 {
            let u = wheel_velocity_body(p, i, 0.0, 0.465, &tw_body, 0.0);
            m.wheels[i] = WheelMeasurement {
                steer_angle: u[1].atan2(u[0]),
                steer_rate: 0.0,
                wheel_speed: u[0].hypot(u[1]) / p.wheel_radius,
                leg: 0.465,
                leg_rate: 0.0,
            };
        }
        // Analytic steering rate is not needed by the continuous model; give the finite
        // difference so the zero-order-hold model gets its best input too.
        let h = 1e-6;
        let tw2 = {
            let (th2, w2) = heading(t + h);
            let (s2, c2) = th2.sin_cos();
            Twist {
                vx: c2 * v,
                vy: -s2 * v,
                omega: w2,
            }
        };
        for i in 0..4 {
            let u2 = wheel_velocity_body(p, i, 0.0, 0.465, &tw2, 0.0);
            let d = crate::angle::diff(u2[1].atan2(u2[0]), m.wheels[i].steer_angle);
            m.wheels[i].steer_rate = d / h;
        }
        m
    }

    #[test]
    fn continuous_sampling_does_not_drift_while_turning() {
        let p = Platform::justin();
        let dt = 0.004;
        let steps = 6250; // 25 s
        let run = |sampling: Sampling| {
            let mut o = Odometry::with_sampling(Pose::default(), sampling);
            o.update(&p, &sampled_translation_while_turning(&p, 0.0), dt);
            o.set_pose(Pose::default());
            o.update(&p, &sampled_translation_while_turning(&p, 0.0), dt);
            o.set_pose(Pose::default());
            // Prime the previous twist at t = 0 without moving.
            let _ = o.update(&p, &sampled_translation_while_turning(&p, 0.0), 0.0);
            let mut last = Pose::default();
            for k in 1..=steps {
                last = o
                    .update(
                        &p,
                        &sampled_translation_while_turning(&p, k as f64 * dt),
                        dt,
                    )
                    .pose;
            }
            let t = steps as f64 * dt;
            ((last.x - 0.25 * t).hypot(last.y), last.theta - heading(t).0)
        };
        let (pos_c, th_c) = run(Sampling::Continuous);
        let (pos_z, th_z) = run(Sampling::ZeroOrderHold);
        assert!(pos_c < 1e-4, "continuous model error {pos_c} m after 25 s");
        // The trapezoid's only error is second order, at the two kinks of the ω ramp
        // (≈1.2 µrad); reading the same samples as held values leads by ≈280 µrad.
        assert!(th_c.abs() < 1e-5, "heading error {th_c}");
        assert!(th_z.abs() > 1e-4, "zero-order-hold heading lead {th_z}");
        // The zero-order-hold reading of the same samples drifts (v·ω·dt/2 per second).
        assert!(
            pos_z > 5.0 * pos_c && pos_z > 5e-4,
            "zero-order-hold model error {pos_z} m"
        );
    }

    #[test]
    fn off_centred_wheels_at_any_angle_give_the_true_twist() {
        // MPO-700-like: d = 45 mm, wheels at arbitrary angles (not along their direction of
        // travel), each rolling and steering as the slip-free constraint says.
        let p = Platform::mpo700();
        let tw = Twist {
            vx: 0.3,
            vy: -0.15,
            omega: 0.5,
        };
        let mut m = Measurement {
            n: 4,
            ..Measurement::default()
        };
        let angles = [0.3, -2.0, 2.9, 1.1];
        for i in 0..4 {
            let w = &p.wheels[i];
            let u = wheel_velocity_body(&p, i, 0.0, w.lambda_nominal, &tw, 0.0);
            let (v, rate) =
                crate::model::kinematics::caster_inverse(u, angles[i], tw.omega, w.caster_offset);
            m.wheels[i] = WheelMeasurement {
                steer_angle: angles[i],
                steer_rate: rate,
                wheel_speed: v / p.wheel_radius,
                leg: w.lambda_nominal,
                leg_rate: 0.0,
            };
        }
        let out = Odometry::new(Pose::default()).update(&p, &m, 0.004);
        assert!(out.residual < 1e-12, "residual {}", out.residual);
        assert!((out.twist_body.vx - tw.vx).abs() < 1e-12);
        assert!((out.twist_body.vy - tw.vy).abs() < 1e-12);
        assert!((out.twist_body.omega - tw.omega).abs() < 1e-12);
        // Ignoring the offset (the centred model) gets it wrong.
        let mut centred = p.clone();
        for w in &mut centred.wheels {
            w.caster_offset = 0.0;
        }
        let wrong = Odometry::new(Pose::default()).update(&centred, &m, 0.004);
        assert!(wrong.residual > 0.01 && (wrong.twist_body.omega - tw.omega).abs() > 0.01);
    }
}
