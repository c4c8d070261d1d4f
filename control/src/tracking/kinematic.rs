//! Controller 2: kinematic tracking with per-wheel inverse kinematics.
//!
//! Each cycle:
//! 1. Commanded platform motion = feed-forward + gain × error:
//!    (ẋ, ẏ)_c = (ẋ*, ẏ*) + k_pos (p* − p̂), θ̇_c = θ̇* + k_θ diff(θ*, θ̂),
//!    λ̇_c = λ̇* + k_λ (λ* − λ) (gains `kin_k_pos`, `kin_k_heading`, `kin_k_leg`), with p̂, θ̂
//!    from odometry and λ measured.
//! 2. Its time derivative for the analytic steering rates: z̈* + K (ż* − ż_prev), where
//!    ż_prev is the previous cycle's command (what the platform is doing now).
//! 3. Per wheel: u_i (body contact velocity), φ_i = atan2(u_i), φ̇_i analytically
//!    ([`crate::model::kinematics`]), plus `steer_kp`·(angle error).
//! 4. ±π branch chosen **for the whole platform**: a single flip flag; it toggles (with
//!    hysteresis) only when the largest steering error under the current branch exceeds
//!    π/2 + `FLIP_HYSTERESIS` and the other branch is better. No wheel flips alone. With a
//!    steering reference ([`crate::types::SteerReference`]: live commands, time-scaled
//!    trajectories) each wheel rolls on the branch of the reference's steering angle instead:
//!    the reference is continuous and already says which way each wheel rolls (after a
//!    reversal through zero on a line, a wheel rolls backwards while the others roll on).
//! 5. Wheels whose contact speed is below [`crate::tracking::dfl::REST_SPEED`] hold their angle; with a
//!    steering reference, wheels whose *reference* contact speed is below
//!    [`crate::reference::limits::HOLD_SPEED`] follow the reference's angle and rate instead
//!    ([`crate::tracking::dfl::held_wheels`]): the feedback's small corrections never turn a wheel the
//!    ICR rests on; up to three times that speed the two are blended
//!    ([`crate::tracking::dfl::steer_weights`]), so the hand-over is continuous.
//!
//!    5a. With a steering reference, a rolling centred wheel without a steering range is not
//!    steered to atan2(u_i) itself but to the reference's angle φ_i* offset towards it by
//!    at most [`REFERENCE_OFFSET`], at the reference's rate:
//!    φ̇_i = φ̇_i* + `steer_kp`·(φ_i* + clamp(atan2(u_i) − φ_i*, ±2°) − φ_i).
//!    Derivation: u_i = u_i* + δu_i, with δu_i the contact velocity of the feedback terms
//!    k (z* − ẑ). Its angle off the reference's is δφ_i ≈ (u_i* × δu_i)/|u_i*|², which grows
//!    as 1/|u_i*| when the reference slows: at 6 cm/s a 3 mm error (k_pos = 2) turns the
//!    wheel 5° off where the reference rolls it, and the analytic rate of atan2(u_i) carries
//!    that swing. Rolling turns ([`crate::reference::roll`]) turn the wheels while the base
//!    rolls slowly (a reversal with a turn, a start with the wheels still turning), and a
//!    wheel 5–9° off its direction at 0.2–0.4 m/s rolls sideways at 2–5 cm/s: 8–12 mm of
//!    position error on issue 23's joystick sticks. Clamped, the wheel stays within 2° of
//!    the reference's direction, and the correction across it is at most |u_i*| sin 2°
//!    (1.7 cm/s at 0.5 m/s, where δφ_i is a fraction of a degree for millimetre errors, so
//!    the clamp is idle); along it the rolling speed still corrects in full. With the
//!    clamp the same sticks track to 2.0–2.5 mm and 0.19–0.25° (native; 2.8–3.8 mm and
//!    0.29–0.37° CiA 402; docs/time-scaling.md, "Rolling turns").
//! 6. Rolling speed = ± |u_i| cos(e_i) for steering error |e_i| < π/2, else 0: a wheel
//!    that still points the wrong way does not roll, and rolls fully once aligned.
//! 7. Desaturation (seed 004 Sect. on actuator limits, α_s scaling; WPILib
//!    `desaturateWheelSpeeds`): if any wheel spin, steering rate or leg rate exceeds its
//!    limit, the whole command is multiplied by 1/ratio so its direction is kept.
//!
//! 8. Off-centred wheels (caster offset d > 0, [`crate::model::kinematics`], "Off-centred steering") are
//!    commanded by the slip-free caster law at their measured angle, v_W = u·h, φ̇ = (u·h⊥)/d
//!    − θ̇ ([`crate::model::kinematics::caster_inverse`]): a wheel rolling forward (trailing) turns towards
//!    its direction of travel by itself and is never steered at rest. A wheel that points
//!    backwards along its direction of travel (after a reversal) rolls backwards as a
//!    leading caster, its steering held on the leading angle ψ + π + lag by `steer_kp`
//!    feedback (the caster law would swing it round), until it is more than
//!    [`LEAD_RELEASE`] off it. The lag is asin(d (ψ̇ + θ̇)/|u|), which saturates at ±π/2
//!    when a slow contact turns fast (a twist passing near the wheel's ICR), so a wheel
//!    enters the mode only if it is within [`LEAD_ENTRY`] of *both* ψ + π + lag and ψ + π:
//!    without the second condition a wheel standing across its travel counted as leading,
//!    was held across, and the MPO-700-like live session ended in a wheel-slip fault.
//!    The leading angle is taken from the *reference's* contact velocity (and its
//!    derivative and θ̇*) whenever the reference moves the wheel's axis, not from the
//!    commanded one: the command adds k_pos·(p* − p̂), and as the reference speed goes to
//!    zero at a stop the direction of that sum swings towards the position error's, which
//!    says nothing about where the wheel rolls. A leading wheel that followed it steered at
//!    up to 6 rad/s in the last 0.3 s before the stop of the MPO-700-like live session and
//!    dragged the base 0.65° round; held on the reference's straight line it does not steer
//!    at all, and the feedback's small cross component is rolled through (a slip of the
//!    order of the feedback speed, millimetres per second). The rolling speed and the
//!    trailing caster law still use the commanded velocity: they are what corrects the
//!    error.
//! 9. A wheel with a steering range ([`crate::angle::SteerRange`]) steers to the turn of its
//!    target inside the range ([`crate::angle::steer_error`]: the long way round when the
//!    short one crosses a stop), and the branch decision compares errors within the ranges.
//!
//! `finished` is raised once the reference, after having moved, is at rest (all reference contact speeds below
//! 1e-6 m/s, and with a steering reference every centred wheel's steering rate below 1e-6
//! rad/s and its steering error below 1e-3 rad) and the pose/leg errors are below 0.1 mm /
//! 1e-4 rad. A finished controller commands zero: without the steering condition it stopped
//! the wheels at the start of a dwell, where the platform stands but the time scaling turns
//! them (a ranged wheel unwinding, a corner at a stop), and they then turned while the base
//! moved off (35 mm off on the three-wheel ±170° seed 000 run).

// Index loops over parallel per-wheel arrays read better than zipped iterators here.
#![allow(clippy::needless_range_loop)]

use crate::angle;
use crate::model::kinematics::{steer_from_velocity, wheel_acceleration_body, wheel_velocity_body};
use crate::model::platform::Platform;
use crate::tracking::dfl::{
    desaturate, limit_ratio, ControlInput, ControlOutput, TrackingController, REST_SPEED,
};
use crate::types::{Command, ReferenceSample, Twist, MAX_WHEELS};
use std::f64::consts::{FRAC_PI_2, PI};

/// Largest angle (rad) by which the feedback's correction turns a rolling wheel off the
/// steering reference's angle (module docs, point 5a). 2°.
pub const REFERENCE_OFFSET: f64 = 2.0 * std::f64::consts::PI / 180.0;

/// Extra angle (rad) beyond π/2 before the platform-wide ±π branch is switched.
pub const FLIP_HYSTERESIS: f64 = 0.3;

/// An off-centred wheel within this angle (rad) of its leading angle (pointing backwards
/// along its direction of travel) rolls backwards, held there by its steering motor.
pub const LEAD_ENTRY: f64 = 0.35;

/// A leading off-centred wheel further than this (rad) from its leading angle is released
/// to the caster law (it swings round to trailing).
pub const LEAD_RELEASE: f64 = 0.6;

/// Steering command of an off-centred wheel (module docs, point 8): (steering rate, rolling
/// speed along the wheel) for the commanded steering-axis velocity `u` (its derivative
/// `du`) and body rate `omega`, at the measured angle `phi`; `leading` is the wheel's mode
/// (updated). `reference` is the reference's (axis velocity, its derivative, θ̇*): where it
/// moves the axis (≥ [`REST_SPEED`]) the leading angle is taken from it, else from the
/// command. Near a steering stop the rate towards it fades with the distance left.
#[allow(clippy::too_many_arguments)]
pub fn caster_command(
    w: &crate::model::platform::WheelConfig,
    u: [f64; 2],
    du: [f64; 2],
    omega: f64,
    phi: f64,
    kp: f64,
    leading: &mut bool,
    reference: Option<([f64; 2], [f64; 2], f64)>,
) -> (f64, f64) {
    let d = w.caster_offset;
    let sp = u[0].hypot(u[1]);
    let (roll, mut rate) = crate::model::kinematics::caster_inverse(u, phi, omega, d);
    let (lu, ldu, lom) = match reference {
        Some((ru, rdu, rom)) if ru[0].hypot(ru[1]) >= REST_SPEED => (ru, rdu, rom),
        _ => (u, du, omega),
    };
    let lsp = lu[0].hypot(lu[1]);
    if sp >= REST_SPEED && sp.is_finite() && lsp.is_finite() {
        let psi = steer_from_velocity(lu, ldu);
        let lag = crate::model::kinematics::caster_lag(lsp, psi.steer_rate + lom, d, true);
        let e = angle::diff(psi.steer_angle + PI + lag, phi);
        // Entry also asks that the wheel point backwards along its travel: the lag saturates
        // at ±π/2 when a slow contact turns fast, and a wheel across its travel would
        // otherwise count as "near its leading angle" and be held there (module docs, 8).
        let back = angle::diff(psi.steer_angle + PI, phi);
        *leading = if *leading {
            e.abs() < LEAD_RELEASE
        } else {
            e.abs() < LEAD_ENTRY && back.abs() < LEAD_ENTRY
        };
        if *leading {
            rate = psi.steer_rate + kp * e;
        }
    } else {
        *leading = false;
    }
    if let Some(r) = w.steering_range() {
        // Never into a stop: the rate towards it is at most kp × the angle left.
        if rate > 0.0 {
            rate = rate.min(kp * (r.max - phi).max(0.0));
        } else {
            rate = rate.max(-kp * (phi - r.min).max(0.0));
        }
    }
    (rate, roll)
}

/// Controller 2 (module docs).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct KinematicController {
    flip: bool,
    leading: [bool; MAX_WHEELS],
    prev: [f64; 3 + MAX_WHEELS],
    has_prev: bool,
    started: bool,
    terminates: bool,
}

impl KinematicController {
    /// A controller for platform `p`.
    pub fn new(p: &Platform) -> Self {
        let _ = p;
        Self {
            flip: false,
            leading: [false; MAX_WHEELS],
            prev: [0.0; 3 + MAX_WHEELS],
            has_prev: false,
            started: false,
            terminates: true,
        }
    }

    /// Whether the trajectory termination rule applies (module docs; default true). Live
    /// commands never end, so the base service turns it off: a platform at rest with its
    /// wheels turning in place (align-first) must keep receiving their steering commands.
    pub fn set_termination(&mut self, on: bool) {
        self.terminates = on;
    }

    /// Resets the internal state (flip branch, previous command) for a new trajectory.
    pub fn reset(&mut self, p: &Platform, reference: &ReferenceSample) {
        let _ = (p, reference);
        self.flip = false;
        self.leading = [false; MAX_WHEELS];
        self.has_prev = false;
        self.started = false;
    }

    /// Whether the platform-wide ±π branch is currently flipped.
    pub fn flipped(&self) -> bool {
        self.flip
    }

    /// One cycle (module docs).
    pub fn step(&mut self, p: &Platform, input: &ControlInput) -> ControlOutput {
        let n = p.n().min(MAX_WHEELS).min(input.measurement.n);
        let mut out = ControlOutput {
            command: Command::zero(p.n().min(MAX_WHEELS)),
            ..ControlOutput::default()
        };
        let r = input.reference;
        let m = input.measurement;
        let g = &p.gains;
        let pose = input.pose;
        let ok = pose.x.is_finite()
            && pose.y.is_finite()
            && pose.theta.is_finite()
            && m.wheels
                .iter()
                .take(n)
                .all(|w| w.leg.is_finite() && w.steer_angle.is_finite())
            && r.z
                .iter()
                .chain(r.dz.iter())
                .chain(r.ddz.iter())
                .all(|v| v.is_finite());
        if !ok || n == 0 {
            out.singular = true;
            return out;
        }
        // 1. commanded motion
        let ex = r.z[0] - pose.x;
        let ey = r.z[1] - pose.y;
        let eth = angle::diff(r.z[2], pose.theta);
        let mut cmdv = [0.0; 3 + MAX_WHEELS];
        cmdv[0] = r.dz[0] + g.kin_k_pos * ex;
        cmdv[1] = r.dz[1] + g.kin_k_pos * ey;
        cmdv[2] = r.dz[2] + g.kin_k_heading * eth;
        let mut max_leg_err: f64 = 0.0;
        for i in 0..n {
            let e = r.z[3 + i] - m.wheels[i].leg;
            max_leg_err = max_leg_err.max(e.abs());
            cmdv[3 + i] = r.dz[3 + i] + g.kin_k_leg * e;
        }
        // 2. its derivative
        if !self.has_prev {
            self.prev[..3 + n].copy_from_slice(&r.dz.as_slice()[..3 + n]);
            self.has_prev = true;
        }
        let mut acc = [0.0; 3 + MAX_WHEELS];
        for c in 0..3 + n {
            let k = match c {
                0 | 1 => g.kin_k_pos,
                2 => g.kin_k_heading,
                _ => g.kin_k_leg,
            };
            acc[c] = r.ddz[c] + k * (r.dz[c] - self.prev[c]);
        }
        self.prev = cmdv;
        let tw = Twist {
            vx: cmdv[0],
            vy: cmdv[1],
            omega: cmdv[2],
        };
        let rtw = Twist {
            vx: r.dz[0],
            vy: r.dz[1],
            omega: r.dz[2],
        };
        // 3. per-wheel inverse kinematics
        let mut target = [0.0; MAX_WHEELS];
        let mut ff = [0.0; MAX_WHEELS];
        let mut speed = [0.0; MAX_WHEELS];
        let mut moving = [false; MAX_WHEELS];
        let mut min_speed = f64::INFINITY;
        let mut fastest = (0usize, -1.0);
        let held = crate::tracking::dfl::held_wheels(p, r);
        let weight = crate::tracking::dfl::steer_weights(p, r);
        let mut caster: [Option<(f64, f64)>; MAX_WHEELS] = [None; MAX_WHEELS];
        for i in 0..n {
            let leg = m.wheels[i].leg;
            let u = wheel_velocity_body(p, i, pose.theta, leg, &tw, cmdv[3 + i]);
            let du = wheel_acceleration_body(
                p,
                i,
                pose.theta,
                leg,
                cmdv[3 + i],
                acc[3 + i],
                [cmdv[0], cmdv[1], cmdv[2]],
                [acc[0], acc[1], acc[2]],
            );
            let sp = u[0].hypot(u[1]);
            min_speed = min_speed.min(sp);
            if sp > fastest.1 {
                fastest = (i, sp);
            }
            if p.wheels[i].off_centred() {
                caster[i] = Some(caster_command(
                    &p.wheels[i],
                    u,
                    du,
                    cmdv[2],
                    m.wheels[i].steer_angle,
                    g.steer_kp,
                    &mut self.leading[i],
                    Some((
                        wheel_velocity_body(p, i, pose.theta, leg, &rtw, r.dz[3 + i]),
                        wheel_acceleration_body(
                            p,
                            i,
                            pose.theta,
                            leg,
                            r.dz[3 + i],
                            r.ddz[3 + i],
                            [r.dz[0], r.dz[1], r.dz[2]],
                            [r.ddz[0], r.ddz[1], r.ddz[2]],
                        ),
                        r.dz[2],
                    )),
                ));
                continue;
            }
            if held[i] {
                // Steered by the reference's angle; rolls its share of the commanded motion
                // along its heading.
                target[i] = r.steer.angle[i];
                let phi = m.wheels[i].steer_angle;
                speed[i] = u[0] * phi.cos() + u[1] * phi.sin();
            } else if sp >= REST_SPEED {
                let w = steer_from_velocity(u, du);
                target[i] = w.steer_angle;
                ff[i] = w.steer_rate;
                speed[i] = sp;
                moving[i] = true;
            } else {
                target[i] = m.wheels[i].steer_angle;
                // a wheel at rest still rolls its (tiny) projected speed
                let phi = m.wheels[i].steer_angle;
                speed[i] = u[0] * phi.cos() + u[1] * phi.sin();
            }
        }
        // 4. platform-wide branch with hysteresis
        let worst = |flip: bool| -> f64 {
            let off = if flip { PI } else { 0.0 };
            (0..n)
                .filter(|&i| moving[i])
                .map(|i| {
                    angle::steer_error(
                        p.wheels[i].steering_range(),
                        target[i] + off,
                        m.wheels[i].steer_angle,
                    )
                    .abs()
                })
                .fold(0.0, f64::max)
        };
        let cur = worst(self.flip);
        if cur > FRAC_PI_2 + FLIP_HYSTERESIS && worst(!self.flip) < cur {
            self.flip = !self.flip;
        }
        let (off0, sign0) = if self.flip { (PI, -1.0) } else { (0.0, 1.0) };
        // 5.–6. steering and rolling
        for i in 0..n {
            if let Some((rate, roll)) = caster[i] {
                out.command.wheels[i].steer_rate = rate;
                out.command.wheels[i].wheel_speed = roll / p.wheel_radius;
                continue;
            }
            let phi = m.wheels[i].steer_angle;
            let range = p.wheels[i].steering_range();
            // With a steering reference each wheel rolls on the reference's branch (a wheel
            // whose velocity passed through zero on a line rolls backwards: its own branch).
            let (off, sign) = if r.steer.valid && moving[i] {
                if angle::diff(target[i], r.steer.angle[i]).abs() > FRAC_PI_2 {
                    (PI, -1.0)
                } else {
                    (0.0, 1.0)
                }
            } else {
                (off0, sign0)
            };
            let (rate, roll) = if held[i] {
                (
                    crate::tracking::dfl::held_steer_rate(p, r, i, phi),
                    speed[i],
                )
            } else if moving[i] {
                let e = angle::steer_error(range, target[i] + off, phi);
                let scale = if e.abs() < FRAC_PI_2 { e.cos() } else { 0.0 };
                let own = if r.steer.valid && range.is_none() {
                    // Point 5a: the reference's angle, offset towards the commanded velocity
                    // by at most REFERENCE_OFFSET, at the reference's rate.
                    let d = angle::diff(target[i] + off, r.steer.angle[i])
                        .clamp(-REFERENCE_OFFSET, REFERENCE_OFFSET);
                    let ec = angle::diff(r.steer.angle[i] + d, phi);
                    r.steer.rate[i] + g.steer_kp * ec
                } else {
                    ff[i] + g.steer_kp * e
                };
                // Near the hold speed, blended with the reference's angle (dfl::steer_weights).
                let w = weight[i];
                let rate = if w < 1.0 {
                    w * own + (1.0 - w) * crate::tracking::dfl::held_steer_rate(p, r, i, phi)
                } else {
                    own
                };
                (rate, sign * speed[i] * scale)
            } else {
                (0.0, speed[i])
            };
            out.command.wheels[i].steer_rate = rate;
            out.command.wheels[i].wheel_speed = roll / p.wheel_radius;
        }
        // 7. desaturation as a whole
        let ratio = limit_ratio(p, &out.command, &cmdv[3..3 + n]);
        out.limit_ratio = ratio;
        out.saturated = desaturate(&mut out.command, ratio);
        out.reference_wheel = fastest.0;
        out.min_wheel_speed = min_speed;
        // termination
        let rtw = r.twist_world();
        let ref_rest = (0..n).all(|i| {
            let u = wheel_velocity_body(p, i, r.z[2], r.z[3 + i], &rtw, r.dz[3 + i]);
            u[0].hypot(u[1]) < 1e-6
        });
        self.started |= !ref_rest;
        // The reference rests only once its steering does too: during a dwell (a stop where
        // the time scaling turns the wheels, e.g. to unwind one within its steering range)
        // the platform stands while held wheels follow the steering reference.
        let steer_rest = !r.steer.valid
            || (0..n).all(|i| {
                if p.wheels[i].off_centred() {
                    return true;
                }
                let e = angle::steer_error(
                    p.wheels[i].steering_range(),
                    r.steer.angle[i],
                    m.wheels[i].steer_angle,
                );
                r.steer.rate[i].abs() < 1e-6 && (!e.is_finite() || e.abs() < 1e-3)
            });
        out.finished = self.terminates
            && self.started
            && ref_rest
            && steer_rest
            && ex.hypot(ey) < 1e-4
            && eth.abs() < 1e-4
            && max_leg_err < 1e-4;
        if out.finished {
            out.command = Command::zero(out.command.n);
        }
        out
    }
}

impl TrackingController for KinematicController {
    fn reset(&mut self, p: &Platform, reference: &ReferenceSample) {
        KinematicController::reset(self, p, reference)
    }
    fn step(&mut self, p: &Platform, input: &ControlInput) -> ControlOutput {
        KinematicController::step(self, p, input)
    }
    fn name(&self) -> &'static str {
        "kinematic"
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::reference::trajectory::{
        seed000_experiment, ComponentTrajectory, QuasiTrapezoid, Trajectory,
    };
    use crate::tracking::dfl::harness::run;

    #[test]
    fn kinematic_tracks_the_seed000_experiment() {
        let p = Platform::justin();
        let traj = seed000_experiment(&p);
        let mut c = KinematicController::new(&p);
        let st = run(&mut c, &p, &traj, 3.0);
        eprintln!("kinematic seed-000 run: {st:#?}");
        assert!(st.max_pos < 1e-3, "max position error {} m", st.max_pos);
        assert!(
            st.max_head < 0.1f64.to_radians(),
            "max heading error {}",
            st.max_head
        );
        assert!(st.max_leg < 1e-3, "max leg error {}", st.max_leg);
        assert!(st.final_pos < 1e-3 && st.final_head < 0.1f64.to_radians() && st.final_leg < 1e-3);
        assert!(
            st.max_ratio <= 1.0 && !st.saturated,
            "limit ratio {}",
            st.max_ratio
        );
        assert!(
            st.max_steer_jump < 0.05,
            "steering-rate spike {}",
            st.max_steer_jump
        );
        assert!(
            st.max_steer_rate < 1.2,
            "steering rate {}",
            st.max_steer_rate
        );
    }

    #[test]
    fn kinematic_starts_and_stops_at_rest() {
        let p = Platform::justin();
        let q = |a: f64, b: f64, v: f64, acc: f64| QuasiTrapezoid::new(a, b, v, acc, 0.0).unwrap();
        let legs = [q(0.45, 0.50, 0.02, 0.01); 4];
        let traj = ComponentTrajectory::new(
            q(0.0, 1.0, 0.3, 0.2),
            q(0.0, -0.5, 0.2, 0.2),
            q(0.0, 0.8, 0.3, 0.3),
            &legs,
        );
        let mut c = KinematicController::new(&p);
        let st = run(&mut c, &p, &traj, 3.0);
        eprintln!("kinematic rest-to-rest run: {st:#?}");
        assert!(st.max_pos < 1e-3, "max position error {} m", st.max_pos);
        assert!(st.final_pos < 1e-3 && st.final_head < 0.1f64.to_radians() && st.final_leg < 1e-3);
        assert!(
            st.finished_at.is_some(),
            "must report finished once at rest on the goal"
        );
        assert_eq!(st.final_command_max, 0.0);
        assert!(st.max_ratio <= 1.0);
    }

    #[test]
    fn a_slow_wheel_across_its_travel_does_not_enter_leading_mode() {
        let p = Platform::mpo700();
        let w = &p.wheels[0];
        let kp = p.gains.steer_kp;
        // Contact moving along +x at 5 mm/s, its direction turning at 1 rad/s:
        // d ψ̇ / |u| = 0.045 / 0.005 = 9, so the lag saturates at π/2 and the "leading
        // angle" ψ + π + lag is across the travel, where this wheel stands.
        let (u, du) = ([0.005, 0.0], [0.0, 0.005]);
        let across = PI + FRAC_PI_2;
        let mut leading = false;
        caster_command(w, u, du, 0.0, across, kp, &mut leading, None);
        assert!(
            !leading,
            "a wheel across its travel must be left to the caster law"
        );
        // The same slow contact with the wheel pointing backwards does lead.
        let mut leading = false;
        caster_command(w, u, [0.0; 2], 0.0, PI + 0.1, kp, &mut leading, None);
        assert!(leading, "a wheel pointing backwards along its travel leads");
    }

    #[test]
    fn a_leading_wheel_holds_the_reference_line_while_the_command_swings_at_a_stop() {
        let p = Platform::mpo700();
        let w = &p.wheels[0];
        let kp = p.gains.steer_kp;
        // Backing along −x, slowing down, 6 cm/s left; the wheel points forwards (φ = 0)
        // and rolls backwards as a leading caster. Position feedback adds 1 cm/s across.
        let (ru, rdu) = ([-0.06, 0.0], [0.3, 0.0]);
        let (u, du) = ([-0.06, 0.01], [0.3, 0.0]);
        let mut leading = true;
        let (rate, roll) =
            caster_command(w, u, du, 0.0, 0.0, kp, &mut leading, Some((ru, rdu, 0.0)));
        assert!(leading, "still leading on the reference's line");
        assert!(
            rate.abs() < 1e-9,
            "no steering on a straight stop: {rate} rad/s"
        );
        assert!(
            (roll + 0.06).abs() < 1e-12,
            "rolls the commanded speed along itself: {roll}"
        );
        // Steered by the command's direction instead: (u × du)/|u|² = −0.81 rad/s, lag
        // asin(−0.045·0.81/0.061) ≈ −0.64 rad, so the leading angle is 0.8 rad away, the
        // wheel is released and the caster law starts to swing it round.
        let mut leading = true;
        let (rate, _) = caster_command(w, u, du, 0.0, 0.0, kp, &mut leading, None);
        assert!(!leading, "the command's direction releases the wheel");
        assert!(rate > 0.2, "and it turns: {rate} rad/s");
    }

    #[test]
    fn limits_scale_the_whole_command() {
        let p = Platform::justin();
        let q = |a: f64, b: f64| QuasiTrapezoid::new(a, b, 3.0, 2.0, 0.0).unwrap();
        let legs = [QuasiTrapezoid::hold(0.45); 4];
        let traj = ComponentTrajectory::new(
            q(0.0, 6.0),
            QuasiTrapezoid::hold(0.0),
            QuasiTrapezoid::hold(0.0),
            &legs,
        );
        let r = traj.sample(2.5);
        let mut m = crate::types::Measurement {
            n: 4,
            ..Default::default()
        };
        for i in 0..4 {
            m.wheels[i].leg = 0.45;
        }
        let mut c = KinematicController::new(&p);
        c.reset(&p, &r);
        let out = c.step(
            &p,
            &ControlInput {
                measured_twist: None,
                t: 2.5,
                dt: 0.004,
                measurement: &m,
                pose: r.pose(),
                reference: &r,
            },
        );
        assert!(out.saturated && out.limit_ratio > 1.0);
        let lim = p.limits.wheel_speed;
        let mx = out
            .command
            .wheels
            .iter()
            .map(|w| w.wheel_speed.abs())
            .fold(0.0, f64::max);
        assert!(
            (mx - lim).abs() < 1e-9,
            "largest wheel exactly at its limit: {mx}"
        );
        // all wheels equal (pure translation): scaled together, not clamped one by one
        for w in out.command.wheels.iter().take(4) {
            assert!((w.wheel_speed - out.command.wheels[0].wheel_speed).abs() < 1e-9);
        }
    }
}
