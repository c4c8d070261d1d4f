//! The actuator limits: one description ([`Limits`], from the platform file) and one place
//! that evaluates and checks them, shared by the live-command shaper ([`crate::reference::shaper`]), the
//! time scaling of pre-planned trajectories ([`crate::reference::timescale`]), the output guard of the
//! cycle and the tests.
//!
//! # What a motion asks of a wheel module
//!
//! For a reference z = (x, y, θ, λ) with derivatives ż, z̈, z⃛ (world frame), wheel i's contact
//! velocity in the body frame is (seed 000 eq. 18; [`crate::model::kinematics::wheel_velocity_body`])
//!
//! ```text
//! u  = Rᵀ(θ) v + θ̇ λ e⊥ + λ̇ e                    (v = (ẋ, ẏ), e = (cos α, sin α), e⊥ = J e)
//! u̇  = Rᵀa − θ̇ J Rᵀv + (θ̈ λ + θ̇ λ̇) e⊥ + λ̈ e                       (a = (ẍ, ÿ))
//! ü  = Rᵀj − 2 θ̇ J Rᵀa − θ̈ J Rᵀv − θ̇² Rᵀv + (θ⃛ λ + 2 θ̈ λ̇ + θ̇ λ̈) e⊥ + λ⃛ e    (j = (x⃛, y⃛))
//! ```
//!
//! (d/dt Rᵀ = −θ̇ J Rᵀ with J the rotation by +90°, and J² = −I). From u, u̇, ü:
//!
//! ```text
//! wheel speed          ω   = |u| / r
//! wheel acceleration   ω̇   = (u · u̇) / (|u| r)
//! steering angle       φ   = atan2(u_y, u_x)
//! steering rate        φ̇   = (u × u̇) / |u|²
//! steering accel.      φ̈   = (u × ü) / |u|² − 2 (u × u̇)(u · u̇) / |u|⁴
//! leg speed            |λ̇|
//! ```
//!
//! The steering terms divide by |u|²: at the instantaneous centre of rotation (singularity A,
//! the ICR on the wheel's contact point) the angle is undefined. Below [`HOLD_SPEED`] a wheel
//! holds its steering angle (rate and acceleration 0 in the demand): the controllers do the
//! same, so a wheel the ICR rests on neither chatters nor flips.
//!
//! # The output guard
//!
//! Whatever the controller asks, the command sent keeps every wheel within its speed and
//! acceleration limits ([`guard_command`]): a request beyond the speed limits is first scaled
//! as a whole into them, then the change from the last command sent is scaled by one factor
//! κ ∈ [0, 1] for all wheels (so the direction of the change in actuator space is kept, never
//! one wheel clamped), the largest κ for which every wheel acceleration and steering
//! acceleration is within its limit.

use crate::model::platform::{Limits, Platform};
use crate::service::ports::Limiting;
use crate::types::{Command, ReferenceSample, MAX_WHEELS};

/// Fraction of the speed-type limits (wheel speed, steering rate, leg speed) a reference may
/// use by default, the rest being the tracking controller's headroom: one margin for the
/// live-command shaper (`ShaperConfig::speed_fraction`) and the time scaling of a
/// pre-planned path (`TimeScaleConfig::speed_fraction`).
pub const DEFAULT_SPEED_FRACTION: f64 = 0.9;

/// Time (s) over which a reference's acceleration may build up by default (bounds the jerk),
/// shared by the shaper and the time scaling like [`DEFAULT_SPEED_FRACTION`].
pub const DEFAULT_JERK_TIME: f64 = 0.04;

/// Contact speed (m/s) below which a wheel holds its steering angle: its direction of travel
/// is not defined well enough to steer by (2 cm/s: twenty steps of the native protocol's
/// wheel speed at r = 0.085 m).
pub const HOLD_SPEED: f64 = 0.02;

/// What a motion asks of one wheel module (SI units, signed along the wheel's heading φ).
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct WheelDemand {
    /// Contact velocity u in the body frame (m/s).
    pub contact: [f64; 2],
    /// Wheel spin rate |u|/r (rad/s), ≥ 0.
    pub speed: f64,
    /// Wheel spin acceleration (u·u̇)/(|u| r) (rad/s²).
    pub accel: f64,
    /// Steering angle atan2(u) (rad); meaningful only when `moving`.
    pub steer_angle: f64,
    /// Steering rate (rad/s); 0 when not `moving`.
    pub steer_rate: f64,
    /// Steering acceleration (rad/s²); 0 when not `moving`.
    pub steer_accel: f64,
    /// Leg extension rate |λ̇| (m/s).
    pub leg_speed: f64,
    /// |u| ≥ [`HOLD_SPEED`]: the wheel steers by its direction of travel.
    pub moving: bool,
}

/// J v: v rotated by +90°.
#[inline]
fn perp(v: [f64; 2]) -> [f64; 2] {
    [-v[1], v[0]]
}

/// Contact velocity, acceleration and jerk (u, u̇, ü) of wheel `i` in the body frame for the
/// reference sample `r` (module docs).
pub fn contact_kinematics(p: &Platform, i: usize, r: &ReferenceSample) -> [[f64; 2]; 3] {
    let Some(w) = p.wheels.get(i) else {
        return [[0.0; 2]; 3];
    };
    let (sa, ca) = w.alpha.sin_cos();
    let e = [ca, sa];
    let ep = [-sa, ca];
    let th = r.z[2];
    let (s, c) = th.sin_cos();
    let rt = |x: f64, y: f64| [c * x + s * y, -s * x + c * y];
    let vb = rt(r.dz[0], r.dz[1]);
    let ab = rt(r.ddz[0], r.ddz[1]);
    let jb = rt(r.dddz[0], r.dddz[1]);
    let (om, dom, ddom) = (r.dz[2], r.ddz[2], r.dddz[2]);
    let (l, dl, ddl, dddl) = (r.z[3 + i], r.dz[3 + i], r.ddz[3 + i], r.dddz[3 + i]);
    let jv = perp(vb);
    let ja = perp(ab);
    let k1 = om * l;
    let k2 = dom * l + om * dl;
    let k3 = ddom * l + 2.0 * dom * dl + om * ddl;
    let mut u = [0.0; 2];
    let mut du = [0.0; 2];
    let mut ddu = [0.0; 2];
    for d in 0..2 {
        u[d] = vb[d] + k1 * ep[d] + dl * e[d];
        du[d] = ab[d] - om * jv[d] + k2 * ep[d] + ddl * e[d];
        ddu[d] =
            jb[d] - 2.0 * om * ja[d] - dom * jv[d] - om * om * vb[d] + k3 * ep[d] + dddl * e[d];
    }
    [u, du, ddu]
}

/// The demand on wheel `i` of the reference sample `r` (module docs).
pub fn wheel_demand(p: &Platform, i: usize, r: &ReferenceSample) -> WheelDemand {
    let [u, du, ddu] = contact_kinematics(p, i, r);
    let n2 = u[0] * u[0] + u[1] * u[1];
    let sp = n2.sqrt();
    let rw = p.wheel_radius;
    let dot = u[0] * du[0] + u[1] * du[1];
    let mut d = WheelDemand {
        contact: u,
        speed: sp / rw,
        accel: if sp > 0.0 { dot / (sp * rw) } else { 0.0 },
        steer_angle: u[1].atan2(u[0]),
        leg_speed: r.dz.get(3 + i).map_or(0.0, |v| v.abs()),
        ..WheelDemand::default()
    };
    if sp >= HOLD_SPEED {
        let (rate, accel) = direction_rates(u, du, ddu);
        d.moving = true;
        d.steer_rate = rate;
        d.steer_accel = accel;
    }
    d
}

/// First and second derivative of the direction φ = atan2(u) of a vector u(s) with
/// derivatives u', u'' along any parameter s (time: the steering rate and acceleration of the
/// module docs; path time: dφ/dτ and d²φ/dτ² for the time scaling):
/// φ' = (u × u')/|u|², φ'' = (u × u'')/|u|² − 2 (u × u')(u · u')/|u|⁴. Non-finite for u = 0.
pub fn direction_rates(u: [f64; 2], du: [f64; 2], ddu: [f64; 2]) -> (f64, f64) {
    let n2 = u[0] * u[0] + u[1] * u[1];
    let dot = u[0] * du[0] + u[1] * du[1];
    let cross = u[0] * du[1] - u[1] * du[0];
    let cross2 = u[0] * ddu[1] - u[1] * ddu[0];
    (cross / n2, cross2 / n2 - 2.0 * cross * dot / (n2 * n2))
}

/// The largest ratio demand/limit over every wheel of the reference sample (wheel speed and
/// acceleration, steering rate and acceleration, leg speed), and which limit it is. A ratio
/// above 1 means the reference asks more than the platform allows.
pub fn reference_ratio(p: &Platform, r: &ReferenceSample) -> (f64, Limiting) {
    let l = &p.limits;
    let mut worst = (0.0f64, Limiting::None);
    let mut take = |v: f64, lim: f64, k: Limiting| {
        let q = if v.is_nan() {
            f64::INFINITY
        } else {
            v.abs() / lim
        };
        if q > worst.0 {
            worst = (q, k);
        }
    };
    for i in 0..p.n().min(MAX_WHEELS) {
        let d = wheel_demand(p, i, r);
        take(d.speed, l.wheel_speed, Limiting::WheelSpeed);
        take(d.accel, l.wheel_accel, Limiting::WheelAccel);
        take(d.steer_rate, l.steer_rate, Limiting::SteerRate);
        take(d.steer_accel, l.steer_accel, Limiting::SteerAccel);
        take(d.leg_speed, l.leg_speed, Limiting::LegSpeed);
    }
    worst
}

/// A commanded actuator value beyond its limit.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Violation {
    /// Wheel index (0-based).
    pub wheel: usize,
    /// Which limit.
    pub what: Limiting,
    /// The value commanded (rad/s or rad/s²).
    pub value: f64,
    /// The limit.
    pub limit: f64,
}

impl std::fmt::Display for Violation {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "wheel {} {} {:.6} beyond its limit {:.6}",
            self.wheel + 1,
            self.what.name(),
            self.value,
            self.limit
        )
    }
}

/// Relative tolerance of [`check_command`] (floating-point rounding of the guard's scaling).
pub const CHECK_TOLERANCE: f64 = 1e-9;

/// Checks a command against the limits, and its change from `prev` (the command sent one
/// cycle of `dt` seconds earlier) against the acceleration limits. Returns the first
/// violation, if any. This is the check the tests apply to every cycle.
pub fn check_command(l: &Limits, prev: &Command, cmd: &Command, dt: f64) -> Option<Violation> {
    let n = cmd.n.min(MAX_WHEELS);
    let tol = 1.0 + CHECK_TOLERANCE;
    for i in 0..n {
        let (w, s) = (cmd.wheels[i].wheel_speed, cmd.wheels[i].steer_rate);
        let dw = (w - prev.wheels[i].wheel_speed) / dt;
        let ds = (s - prev.wheels[i].steer_rate) / dt;
        for (v, lim, what) in [
            (w, l.wheel_speed, Limiting::WheelSpeed),
            (s, l.steer_rate, Limiting::SteerRate),
            (dw, l.wheel_accel, Limiting::WheelAccel),
            (ds, l.steer_accel, Limiting::SteerAccel),
        ] {
            if v.is_nan() || v.abs() > lim * tol {
                return Some(Violation {
                    wheel: i,
                    what,
                    value: v,
                    limit: lim,
                });
            }
        }
    }
    None
}

/// The output guard (module docs): the command closest to `desired` on the segment from
/// `prev` (the command sent one cycle of `dt` seconds earlier) that keeps every wheel within
/// its speed and acceleration limits, as `prev + κ (desired − prev)` with one κ ∈ [0, 1] for
/// all wheels. Returns the command and κ (1 = unchanged). Non-finite values in `desired` are
/// treated as a request to stop (zero). `prev` is expected within the speed limits (the guard
/// keeps it so); if it is not, its values are first clamped.
pub fn guard_command(l: &Limits, prev: &Command, desired: &Command, dt: f64) -> (Command, f64) {
    let n = desired.n.min(MAX_WHEELS);
    let mut p = Command::zero(n);
    let mut d = Command::zero(n);
    for i in 0..n {
        let pw = prev.wheels[i];
        p.wheels[i].wheel_speed = clamp_finite(pw.wheel_speed, l.wheel_speed);
        p.wheels[i].steer_rate = clamp_finite(pw.steer_rate, l.steer_rate);
        let dw = desired.wheels[i];
        d.wheels[i].wheel_speed = if dw.wheel_speed.is_finite() {
            dw.wheel_speed
        } else {
            0.0
        };
        d.wheels[i].steer_rate = if dw.steer_rate.is_finite() {
            dw.steer_rate
        } else {
            0.0
        };
    }
    // A desired command beyond the speed limits is first scaled as a whole into them (its
    // direction kept): then the segment from `prev` to it lies inside the limits (both ends
    // do, and the box is convex), and only the accelerations bound κ.
    let mut ratio = 1.0f64;
    for i in 0..n {
        ratio = ratio
            .max(d.wheels[i].wheel_speed.abs() / l.wheel_speed)
            .max(d.wheels[i].steer_rate.abs() / l.steer_rate);
    }
    if ratio > 1.0 {
        for i in 0..n {
            d.wheels[i].wheel_speed /= ratio;
            d.wheels[i].steer_rate /= ratio;
        }
    }
    let mut k: f64 = 1.0;
    let dt = if dt.is_finite() && dt > 0.0 { dt } else { 0.0 };
    for i in 0..n {
        for (from, to, vmax, amax) in [
            (
                p.wheels[i].wheel_speed,
                d.wheels[i].wheel_speed,
                l.wheel_speed,
                l.wheel_accel,
            ),
            (
                p.wheels[i].steer_rate,
                d.wheels[i].steer_rate,
                l.steer_rate,
                l.steer_accel,
            ),
        ] {
            let delta = to - from;
            if delta == 0.0 {
                continue;
            }
            // Acceleration: |κ Δ| ≤ a dt.
            k = k.min(amax * dt / delta.abs());
            // Speed: |from + κ Δ| ≤ v, with |from| ≤ v.
            let bound = vmax * delta.signum();
            let room = (bound - from) / delta;
            if room.is_finite() {
                k = k.min(room.max(0.0));
            }
        }
    }
    let k = k.clamp(0.0, 1.0);
    if k >= 1.0 {
        return (d, 1.0);
    }
    let mut out = Command::zero(n);
    for i in 0..n {
        out.wheels[i].wheel_speed =
            p.wheels[i].wheel_speed + k * (d.wheels[i].wheel_speed - p.wheels[i].wheel_speed);
        out.wheels[i].steer_rate =
            p.wheels[i].steer_rate + k * (d.wheels[i].steer_rate - p.wheels[i].steer_rate);
    }
    (out, k)
}

fn clamp_finite(v: f64, lim: f64) -> f64 {
    if v.is_finite() {
        v.clamp(-lim, lim)
    } else {
        0.0
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::types::{Twist, ZVec};

    fn sample_at(t: f64, h: f64) -> ReferenceSample {
        // A smooth motion with rotation and leg motion, and its derivatives.
        let f = |t: f64| -> ZVec {
            let mut z = ZVec::zeros();
            z[0] = 0.3 * t + 0.2 * (0.7 * t).sin();
            z[1] = 0.1 * t * t;
            z[2] = 0.4 * (0.5 * t).sin();
            for i in 0..4 {
                z[3 + i] = 0.45 + 0.05 * (0.3 * t + i as f64).sin();
            }
            z
        };
        let z = f(t);
        let d1 = (f(t + h) - f(t - h)) / (2.0 * h);
        let d2 = (f(t + h) - 2.0 * f(t) + f(t - h)) / (h * h);
        let d3 =
            (f(t + 2.0 * h) - 2.0 * f(t + h) + 2.0 * f(t - h) - f(t - 2.0 * h)) / (2.0 * h * h * h);
        ReferenceSample {
            t,
            n: 4,
            z,
            dz: d1,
            ddz: d2,
            dddz: d3,
            steer: Default::default(),
        }
    }

    #[test]
    fn contact_derivatives_match_finite_differences() {
        let p = Platform::justin();
        let h = 1e-3;
        for &t in &[0.3, 1.7, 4.2] {
            for i in 0..4 {
                let [u, du, ddu] = contact_kinematics(&p, i, &sample_at(t, 1e-4));
                let um = contact_kinematics(&p, i, &sample_at(t - h, 1e-4))[0];
                let up = contact_kinematics(&p, i, &sample_at(t + h, 1e-4))[0];
                // u agrees with the model's own function.
                let r = sample_at(t, 1e-4);
                let tw = Twist {
                    vx: r.dz[0],
                    vy: r.dz[1],
                    omega: r.dz[2],
                };
                let u0 = crate::model::kinematics::wheel_velocity_body(
                    &p,
                    i,
                    r.z[2],
                    r.z[3 + i],
                    &tw,
                    r.dz[3 + i],
                );
                for d in 0..2 {
                    assert!((u[d] - u0[d]).abs() < 1e-12);
                    let fd1 = (up[d] - um[d]) / (2.0 * h);
                    let fd2 = (up[d] - 2.0 * u[d] + um[d]) / (h * h);
                    assert!((du[d] - fd1).abs() < 1e-5, "u̇ {} vs {fd1}", du[d]);
                    assert!((ddu[d] - fd2).abs() < 1e-3, "ü {} vs {fd2}", ddu[d]);
                }
            }
        }
    }

    #[test]
    fn steering_acceleration_matches_the_derivative_of_the_steering_rate() {
        let p = Platform::justin();
        let h = 1e-3;
        for i in 0..4 {
            let d0 = wheel_demand(&p, i, &sample_at(2.0, 1e-4));
            let dm = wheel_demand(&p, i, &sample_at(2.0 - h, 1e-4));
            let dp = wheel_demand(&p, i, &sample_at(2.0 + h, 1e-4));
            assert!(d0.moving);
            let fd = (dp.steer_rate - dm.steer_rate) / (2.0 * h);
            assert!(
                (d0.steer_accel - fd).abs() < 1e-3 * (1.0 + fd.abs()),
                "wheel {i}: {} vs {fd}",
                d0.steer_accel
            );
            let fa = (dp.speed - dm.speed) / (2.0 * h);
            assert!((d0.accel - fa).abs() < 1e-4 * (1.0 + fa.abs()));
        }
    }

    #[test]
    fn a_wheel_at_the_icr_holds_its_angle_in_the_demand() {
        let p = Platform::justin();
        // Pivot about wheel 0: body twist with the ICR at its contact point.
        let l = 0.465;
        let a = p.wheels[0].alpha;
        let (px, py) = (l * a.cos(), l * a.sin());
        let om = 0.5;
        let mut r = ReferenceSample {
            n: 4,
            ..Default::default()
        };
        // v = −ω × P (so that the contact point of wheel 0 has zero velocity)
        r.dz[0] = om * py;
        r.dz[1] = -om * px;
        r.dz[2] = om;
        for i in 0..4 {
            r.z[3 + i] = l;
        }
        let d = wheel_demand(&p, 0, &r);
        assert!(d.speed < 1e-12 && !d.moving);
        assert_eq!((d.steer_rate, d.steer_accel), (0.0, 0.0));
        assert!(wheel_demand(&p, 2, &r).moving);
    }

    fn cmd(ws: [f64; 4], ss: [f64; 4]) -> Command {
        let mut c = Command::zero(4);
        for i in 0..4 {
            c.wheels[i].wheel_speed = ws[i];
            c.wheels[i].steer_rate = ss[i];
        }
        c
    }

    #[test]
    fn the_guard_scales_the_change_as_a_whole_and_respects_every_limit() {
        let p = Platform::justin();
        let l = p.limits;
        let dt = 0.004;
        let prev = cmd([1.0, 1.0, -1.0, 0.5], [0.0, 0.1, 0.0, 0.0]);
        // A jump far beyond the acceleration limits.
        let want = cmd([5.0, 3.0, -1.0, 0.5], [2.0, 0.1, -1.0, 0.0]);
        let (got, k) = guard_command(&l, &prev, &want, dt);
        assert!(k > 0.0 && k < 1.0);
        assert!(check_command(&l, &prev, &got, dt).is_none());
        // The change keeps its direction: every component moved by the same fraction.
        for i in 0..4 {
            let dw = want.wheels[i].wheel_speed - prev.wheels[i].wheel_speed;
            let gw = got.wheels[i].wheel_speed - prev.wheels[i].wheel_speed;
            assert!((gw - k * dw).abs() < 1e-12);
        }
        // The binding limit is met exactly: wheel 0 accelerates at wheel_accel.
        let a0 = (got.wheels[0].wheel_speed - 1.0) / dt;
        let s0 = got.wheels[0].steer_rate / dt;
        assert!(
            (a0 - l.wheel_accel).abs() < 1e-9 || (s0 - l.steer_accel).abs() < 1e-9,
            "{a0} {s0}"
        );
        // Within the limits nothing changes.
        let small = cmd([1.01, 1.0, -1.0, 0.5], [0.0, 0.1, 0.0, 0.0]);
        assert_eq!(guard_command(&l, &prev, &small, dt), (small, 1.0));
        // Speeds beyond the limit are never reached, however many cycles.
        let mut c = prev;
        let far = cmd([100.0, -100.0, 50.0, 0.0], [40.0, -40.0, 0.0, 9.0]);
        for _ in 0..500 {
            let (g, _) = guard_command(&l, &c, &far, dt);
            assert!(check_command(&l, &c, &g, dt).is_none());
            c = g;
        }
        assert!((c.wheels[0].wheel_speed - l.wheel_speed).abs() < 1e-9);
        // Non-finite requests are a stop, reached within the limits.
        let nan = cmd([f64::NAN, 0.0, 0.0, 0.0], [f64::INFINITY, 0.0, 0.0, 0.0]);
        let (g, _) = guard_command(&l, &c, &nan, dt);
        assert!(check_command(&l, &c, &g, dt).is_none());
        assert!(g.wheels[0].wheel_speed.is_finite() && g.wheels[0].steer_rate.is_finite());
    }

    #[test]
    fn check_command_names_the_wheel_and_the_limit() {
        let p = Platform::justin();
        let dt = 0.004;
        let prev = cmd([0.0; 4], [0.0; 4]);
        let v = check_command(&p.limits, &prev, &cmd([0.0, 0.0, 1.0, 0.0], [0.0; 4]), dt)
            .expect("1 rad/s in 4 ms is 250 rad/s²");
        assert_eq!((v.wheel, v.what), (2, Limiting::WheelAccel));
        assert!(v.to_string().contains("wheel 3 wheel acceleration"));
        let v = check_command(
            &p.limits,
            &prev,
            &cmd([0.0, f64::NAN, 0.0, 0.0], [0.0; 4]),
            dt,
        )
        .expect("NaN is a violation");
        assert_eq!(v.wheel, 1);
    }
}
