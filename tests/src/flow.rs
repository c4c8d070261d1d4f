//! Issue 23 ("Motion that flows"): what a user sends a base that should move when asked —
//! joystick and Nav2-like live command sessions and classes of waypoint files — the measures
//! that say whether it did, over the records of a lockstep run, and the runners of
//! `tests/e2e_flow.rs`.
//!
//! Everything here is deterministic: generators take a seed and use
//! [`rollbase_driver::rng::Rng`], runs are lockstep (virtual time, seeded simulator).
//!
//! # Sessions
//!
//! **Joystick** ([`joystick_session`]). A person on a gamepad, as a 50 Hz `cmd_vel` stream
//! (teleop nodes publish at the joystick driver's rate; 50 Hz is common):
//!
//! - the *stick* jumps to a new target at random times, a Poisson process of
//!   [`STICK_MOVES_PER_S`] = 1.5 moves a second (exponential gaps, mean 0.67 s): with
//!   probability [`STICK_LET_GO`] = 0.2 the user lets go (target 0, 0, 0), otherwise
//!   (vx, vy) uniform in the disc of radius [`STICK_MAX_LINEAR`] = 0.8 m/s and ω uniform in
//!   ±[`STICK_MAX_ANGULAR`] = ±1.5 rad/s;
//! - the thumb and the stick's spring do not jump: the output follows the target through a
//!   first-order lag of time constant [`STICK_TAU_S`] = 0.17 s (exact discretisation at
//!   50 Hz, y ← y + (1 − e^(−Δt/τ)) (target − y));
//! - the stick's electrical and mechanical noise is added to every message: Gaussian, σ on vx
//!   and vy, 2σ on ω (σ in m/s, 2σ in rad/s), independent per message;
//! - at the end of the session the user lets go: [`RELEASE_S`] = 1 s of exact zero twists (a
//!   teleop node with a deadzone), then the end of the stream.
//!
//! The stick and the noise come from two generators seeded from the same seed, so the
//! noise-free stick is the same for every σ: the sessions σ = 0, 0.02, 0.05 of one seed are
//! the same intention with more or less noise.
//!
//! **Nav2-like** ([`Nav2Stream`], [`run_nav2`], [`nav2_open_loop`]). A 20 Hz controller
//! server ([`NAV2_HZ`]) running a pure-pursuit follower in the manner of Nav2's Regulated
//! Pure Pursuit (parameter names and meanings from its configuration guide,
//! <https://docs.nav2.org/configuration/packages/configuring-regulated-pp.html>), on a random
//! smooth path ([`curvy_path`]: a Catmull-Rom spline through 4–6 points within ±3 m of the
//! start), through a velocity smoother's acceleration limits (Nav2's `velocity_smoother`
//! defaults, 2.5 m/s² and 3.2 rad/s²). Two styles ([`FollowerStyle`]):
//!
//! - *diff-drive* (what RPP sends): vy = 0, ω = v κ with κ = 2 y_L / d_L² the curvature to
//!   the lookahead point L (body frame), rotate in place first where L is more than 45° off
//!   the heading (`use_rotate_to_heading`);
//! - *holonomic* (what an omnidirectional base's controller may send, e.g. MPPI's omni model):
//!   the velocity points at L, ω turns the heading toward the path's tangent at L.
//!
//! Speed: [`NAV2_MAX_SPEED`] = 0.5 m/s (`desired_linear_vel`), reduced on tight curves
//! (`regulated_linear_scaling_min_radius` 0.9 m) and over the last 0.6 m of the path
//! (`approach_velocity_scaling_dist`) down to 0.05 m/s (`min_approach_linear_velocity`); the
//! lookahead distance is 1.2 s × speed, within [0.4, 0.6] m. Within [`GOAL_TOLERANCE`] of the
//! path's end the follower is done: zero twists for [`RELEASE_S`], then the end of the
//! stream.
//!
//! The follower is simulated two ways: in closed loop on the run's own odometry
//! ([`run_nav2`]: each 20 Hz tick reads the state port's odometry pose, as Nav2 reads TF —
//! what the tests run), and in open loop on the ideal integration of its own commands
//! ([`nav2_open_loop`]: the base does exactly what it is told — the reference path length).
//!
//! # Waypoint classes
//!
//! [`WaypointClass`] and [`waypoint_class`]: random instances (from a seed) of the files the
//! issue lists: stop-and-go corners, circles at constant heading and facing the centre, spin
//! in place with the legs moving, pivots about a wheel ([`pivot`]), ICR sweeps across a
//! wheel ([`icr_sweep`]), dense waypoints at speed, untimed and mixed files. Each class's
//! docs say what varies.
//!
//! # Measures
//!
//! Each is defined in its doc comment and proven on small synthetic record sequences in this
//! module's unit tests: [`truth_path_length`], [`steering_reversals`],
//! [`aligning_standing_fraction`], [`executed_duration`], [`clock_samples`] and
//! [`slow_clock`], [`limit_violations`]; and on command streams [`ideal_path_length`].

use crate::{build_live, LiveOptions, RunOptions, RunOutcome};
use rollbase_control::reference::limits::Violation;
use rollbase_control::reference::shaper::Shaper;
use rollbase_control::reference::timescale::{ScaledTrajectory, TimeScaleConfig};
use rollbase_control::reference::trajectory::{QuinticSpline, Trajectory, WaypointSpec};
use rollbase_control::runtime::record::CycleRecord;
use rollbase_control::runtime::scenario::Scenario;
use rollbase_control::runtime::{lockstep_cycle, LockstepState, RunSummary, StepHooks};
use rollbase_control::service::ports::{CommandEvent, CommandKind, Limiting, MotionCommand};
use rollbase_control::supervisor::SupervisorState;
use rollbase_control::types::{Pose, Twist};
use rollbase_control::{Platform, Protocol, ZVec};
use rollbase_driver::rng::Rng;
use std::f64::consts::{FRAC_PI_2, FRAC_PI_4, PI, TAU};
use std::fmt;

// ---------------------------------------------------------------------------------------
// Joystick
// ---------------------------------------------------------------------------------------

/// Message rate of the joystick stream (Hz).
pub const JOYSTICK_HZ: f64 = 50.0;
/// Mean rate at which the stick's target moves (moves per second, Poisson).
pub const STICK_MOVES_PER_S: f64 = 1.5;
/// Time constant of the stick's first-order smoothing (s).
pub const STICK_TAU_S: f64 = 0.17;
/// Radius of the disc the stick's (vx, vy) target is drawn from (m/s).
pub const STICK_MAX_LINEAR: f64 = 0.8;
/// Largest |ω| of the stick's target (rad/s).
pub const STICK_MAX_ANGULAR: f64 = 1.5;
/// Probability that a move of the stick is a let-go (target 0, 0, 0).
pub const STICK_LET_GO: f64 = 0.2;
/// Zero twists sent at the end of a session, before the end of the stream (s).
pub const RELEASE_S: f64 = 1.0;

/// Salt of the noise generator's seed (the stick's generator uses the seed itself).
const NOISE_SALT: u64 = 0x4E01_5E00_0000_0023;

fn uniform(rng: &mut Rng, lo: f64, hi: f64) -> f64 {
    lo + (hi - lo) * rng.next_f64()
}

/// The noise-free stick of a joystick session: one `(t, twist)` every 1/[`JOYSTICK_HZ`] s
/// for `t` in [0, `session_s`) (module docs, "Joystick"). Starts centred.
pub fn joystick_stick(seed: u64, session_s: f64) -> Vec<(f64, Twist)> {
    joystick_stick_at(seed, session_s, JOYSTICK_HZ)
}

/// [`joystick_stick`] sampled at `hz` instead of 50 Hz: the same stick (its moves are drawn
/// in continuous time, its lag discretised exactly at the rate).
pub fn joystick_stick_at(seed: u64, session_s: f64, hz: f64) -> Vec<(f64, Twist)> {
    let mut rng = Rng::new(seed);
    let dt = 1.0 / hz;
    let alpha = 1.0 - (-dt / STICK_TAU_S).exp();
    let gap = |rng: &mut Rng| -(1.0 - rng.next_f64()).ln() / STICK_MOVES_PER_S;
    let mut next_move = gap(&mut rng);
    let mut target = Twist::default();
    let mut y = Twist::default();
    let n = (session_s * hz).round().max(0.0) as usize;
    let mut out = Vec::with_capacity(n);
    for k in 0..n {
        let t = k as f64 * dt;
        while t >= next_move {
            target = if rng.chance(STICK_LET_GO) {
                Twist::default()
            } else {
                let (vx, vy) = loop {
                    let vx = uniform(&mut rng, -STICK_MAX_LINEAR, STICK_MAX_LINEAR);
                    let vy = uniform(&mut rng, -STICK_MAX_LINEAR, STICK_MAX_LINEAR);
                    if vx.hypot(vy) <= STICK_MAX_LINEAR {
                        break (vx, vy);
                    }
                };
                Twist {
                    vx,
                    vy,
                    omega: uniform(&mut rng, -STICK_MAX_ANGULAR, STICK_MAX_ANGULAR),
                }
            };
            next_move += gap(&mut rng);
        }
        if k > 0 {
            y.vx += alpha * (target.vx - y.vx);
            y.vy += alpha * (target.vy - y.vy);
            y.omega += alpha * (target.omega - y.omega);
        }
        out.push((t, y));
    }
    out
}

fn motion(t: f64, twist: Twist) -> CommandEvent {
    CommandEvent {
        t,
        kind: CommandKind::Motion(MotionCommand { twist, legs: None }),
    }
}

/// A joystick session of `session_s` seconds at noise level `sigma` (m/s on vx and vy,
/// 2σ rad/s on ω): the stick of [`joystick_stick`] plus the noise, then [`RELEASE_S`] of
/// zero twists at 50 Hz and the end of the stream (module docs, "Joystick").
pub fn joystick_session(seed: u64, session_s: f64, sigma: f64) -> Vec<CommandEvent> {
    joystick_session_at(seed, session_s, sigma, JOYSTICK_HZ)
}

/// [`joystick_session`] at `hz` messages a second (the stick of [`joystick_stick_at`], fresh
/// noise on every message; the release at the same rate).
pub fn joystick_session_at(seed: u64, session_s: f64, sigma: f64, hz: f64) -> Vec<CommandEvent> {
    let mut noise = Rng::new(seed ^ NOISE_SALT);
    let mut out: Vec<CommandEvent> = joystick_stick_at(seed, session_s, hz)
        .into_iter()
        .map(|(t, s)| {
            // Three draws per message whatever σ is: the noise is the same sequence scaled.
            let (nx, ny, nw) = (noise.gaussian(), noise.gaussian(), noise.gaussian());
            motion(
                t,
                Twist {
                    vx: s.vx + sigma * nx,
                    vy: s.vy + sigma * ny,
                    omega: s.omega + 2.0 * sigma * nw,
                },
            )
        })
        .collect();
    let end = (session_s * hz).round() / hz;
    let release = (RELEASE_S * hz).round() as usize;
    for k in 0..release {
        out.push(motion(end + k as f64 / hz, Twist::default()));
    }
    out.push(CommandEvent {
        t: end + RELEASE_S,
        kind: CommandKind::EndOfStream,
    });
    out
}

/// Path length (m) of the ideal execution of a command stream: each motion command's body
/// twist held exactly from its time until the next event's (at most `timeout` s, the
/// command timeout after which the base stops), integrated as rigid-body motion. The speed of
/// the base's origin is constant while a twist is held (|v| = √(vx² + vy²) in any frame), so
/// the length is exactly Σ |v_k| · hold_k. Events must be sorted by time; a motion command
/// with nothing after it is held for `timeout`.
pub fn ideal_path_length(cmds: &[CommandEvent], timeout: f64) -> f64 {
    let mut len = 0.0;
    for (k, ev) in cmds.iter().enumerate() {
        if let CommandKind::Motion(m) = ev.kind {
            let next = cmds.get(k + 1).map_or(ev.t + timeout, |n| n.t);
            let hold = (next - ev.t).clamp(0.0, timeout);
            len += m.twist.vx.hypot(m.twist.vy) * hold;
        }
    }
    len
}

/// [`ideal_path_length`] of the stream as `p` could execute it at most: each twist scaled by
/// one factor (direction kept, seed 004) so that no wheel (legs at their nominal extension)
/// turns faster than its speed limit. The part of the ideal path a platform cannot travel
/// whatever it steers: a stick pushed to 0.8 m/s while turning at 1.5 rad/s asks Justin's
/// outer wheels for more than their 1.18 m/s.
pub fn feasible_path_length(cmds: &[CommandEvent], timeout: f64, p: &Platform) -> f64 {
    let vmax = p.limits.wheel_speed * p.wheel_radius;
    let scaled: Vec<CommandEvent> = cmds
        .iter()
        .map(|ev| match ev.kind {
            CommandKind::Motion(m) => {
                let t = m.twist;
                let worst = fastest_contact(p, [t.vx, t.vy, t.omega]);
                let k = if worst > vmax { vmax / worst } else { 1.0 };
                motion(
                    ev.t,
                    Twist {
                        vx: k * t.vx,
                        vy: k * t.vy,
                        omega: k * t.omega,
                    },
                )
            }
            _ => *ev,
        })
        .collect();
    ideal_path_length(&scaled, timeout)
}

/// Largest contact speed (m/s) of `p`'s wheels, legs at their nominal extension, for the
/// body twist `q` = (vx, vy, ω) (seed 000 eq. 18 with the legs at rest; also the largest
/// change of a contact velocity for a change `q` of the twist, the map being linear).
pub fn fastest_contact(p: &Platform, q: [f64; 3]) -> f64 {
    p.wheels
        .iter()
        .map(|w| {
            let (sa, ca) = w.alpha.sin_cos();
            let l = w.lambda_nominal;
            (q[0] - q[2] * l * sa).hypot(q[1] + q[2] * l * ca)
        })
        .fold(0.0, f64::max)
}

/// Path length (m) of the stream executed by a base whose wheels steer instantly: the twist
/// moves each cycle of `p.dt()` straight towards the command in force (zero after a stop, the
/// end of the stream or `timeout` s without a command), capped as a whole to
/// `speed_fraction` of the wheel speed limit, with no wheel's contact velocity changing by
/// more than `accel_fraction` of the wheel acceleration limit (at the contact point) per
/// second, until it rests after the last event.
///
/// What the shaper's shares of the drives' speed and acceleration leave of
/// [`ideal_path_length`] before any steering is asked for: a stick reversed at 0.8 m/s must
/// brake through rest at the acceleration share whatever the wheels do. It is the path of a
/// line transition (the shaper's default) without its steering constraints and jerk limit,
/// not a bound on every shaper: a twist that swings round instead of passing through rest
/// (a U-turn for a reversal) can travel more.
pub fn unsteered_path_length(
    cmds: &[CommandEvent],
    timeout: f64,
    p: &Platform,
    speed_fraction: f64,
    accel_fraction: f64,
) -> f64 {
    let dt = p.dt();
    let vmax = speed_fraction * p.limits.wheel_speed * p.wheel_radius;
    let step = accel_fraction * p.limits.wheel_accel * p.wheel_radius * dt;
    let last = cmds.last().map_or(0.0, |e| e.t);
    let (mut k, mut t, mut len) = (0usize, 0.0f64, 0.0f64);
    let (mut goal, mut since) = ([0.0f64; 3], 0.0f64);
    let mut q = [0.0f64; 3];
    while t <= last + timeout || q.iter().any(|v| *v != 0.0) {
        while k < cmds.len() && cmds[k].t <= t + 1e-9 {
            goal = match cmds[k].kind {
                CommandKind::Motion(m) => {
                    let g = [m.twist.vx, m.twist.vy, m.twist.omega];
                    let worst = fastest_contact(p, g);
                    let c = if worst > vmax { vmax / worst } else { 1.0 };
                    [c * g[0], c * g[1], c * g[2]]
                }
                _ => [0.0; 3],
            };
            since = cmds[k].t;
            k += 1;
        }
        if t - since > timeout {
            goal = [0.0; 3];
        }
        let d = [goal[0] - q[0], goal[1] - q[1], goal[2] - q[2]];
        let worst = fastest_contact(p, d);
        let f = if worst > step { step / worst } else { 1.0 };
        let prev = q;
        for c in 0..3 {
            q[c] += f * d[c];
        }
        len += 0.5 * (prev[0].hypot(prev[1]) + q[0].hypot(q[1])) * dt;
        t += dt;
    }
    len
}

/// Feeds a command stream to the live shaper alone (no bus, no plant), one step per cycle
/// of `dt` for `until` seconds: each motion command as it falls due, anything else as a
/// stop ([`Shaper::halt_for`]). After every step, `each(t, shaper, asked)` sees the shaper
/// and the twist last asked for (zero after a stop).
pub fn drive_shaper(
    shaper: &mut Shaper,
    cmds: &[CommandEvent],
    dt: f64,
    until: f64,
    mut each: impl FnMut(f64, &Shaper, Twist),
) {
    let (mut k, mut t) = (0usize, 0.0f64);
    let mut asked = Twist::default();
    while t < until {
        while k < cmds.len() && cmds[k].t <= t + 1e-9 {
            match cmds[k].kind {
                CommandKind::Motion(m) => {
                    shaper.command(m.twist, None);
                    asked = m.twist;
                }
                _ => {
                    shaper.halt_for(Limiting::Stop);
                    asked = Twist::default();
                }
            }
            k += 1;
        }
        shaper.step();
        each(t, shaper, asked);
        t += dt;
    }
}

// ---------------------------------------------------------------------------------------
// Nav2-like follower
// ---------------------------------------------------------------------------------------

/// Rate of the follower's commands (Hz; Nav2's `controller_frequency` default).
pub const NAV2_HZ: f64 = 20.0;
/// Desired (largest) linear speed (m/s; RPP's `desired_linear_vel` default).
pub const NAV2_MAX_SPEED: f64 = 0.5;
/// Lookahead time (s): the lookahead distance is this times the speed, within
/// [`LOOKAHEAD_MIN`, `LOOKAHEAD_MAX`].
pub const LOOKAHEAD_TIME: f64 = 1.2;
/// Shortest lookahead distance (m).
pub const LOOKAHEAD_MIN: f64 = 0.4;
/// Longest lookahead distance (m).
pub const LOOKAHEAD_MAX: f64 = 0.6;
/// Path left (m) from which the speed is scaled down toward the goal
/// (`approach_velocity_scaling_dist`).
pub const APPROACH_DIST: f64 = 0.6;
/// Smallest speed while approaching the goal (m/s; `min_approach_linear_velocity`).
pub const MIN_APPROACH_SPEED: f64 = 0.05;
/// Distance to the path's end (m) at which the follower is done.
pub const GOAL_TOLERANCE: f64 = 0.03;
/// Radius (m) below which the speed is scaled by radius / this
/// (`regulated_linear_scaling_min_radius`).
pub const MIN_RADIUS: f64 = 0.9;
/// Smallest curvature-regulated speed (m/s; `regulated_linear_scaling_min_speed`).
pub const MIN_REGULATED_SPEED: f64 = 0.25;
/// Angle to the lookahead point (rad) beyond which a diff-drive follower rotates in place
/// (`rotate_to_heading_min_angle`).
pub const ROTATE_MIN_ANGLE: f64 = FRAC_PI_4;
/// Angular speed of a rotation in place (rad/s).
pub const ROTATE_SPEED: f64 = 1.0;
/// Largest |ω| the follower sends (rad/s).
pub const NAV2_MAX_ANGULAR: f64 = 1.0;
/// Heading gain of the holonomic style (1/s).
pub const HEADING_GAIN: f64 = 1.5;
/// Velocity smoother: linear acceleration limit (m/s²).
pub const SMOOTHER_ACCEL: f64 = 2.5;
/// Velocity smoother: angular acceleration limit (rad/s²).
pub const SMOOTHER_ANGULAR_ACCEL: f64 = 3.2;

/// What twists the follower sends.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum FollowerStyle {
    /// vy = 0: forward speed and turn rate, rotating in place first when the path is far
    /// off the heading (Regulated Pure Pursuit).
    DiffDrive,
    /// vx, vy toward the lookahead point, ω toward the path's heading.
    Holonomic,
}

/// A path: a polyline with its cumulative arc length.
#[derive(Clone, Debug, PartialEq)]
pub struct Path {
    /// Points (m), at most a few cm apart.
    pub points: Vec<[f64; 2]>,
    /// Arc length at each point (m), from 0.
    pub s: Vec<f64>,
}

impl Path {
    /// The polyline through `points` (at least one).
    pub fn new(points: Vec<[f64; 2]>) -> Self {
        let mut s = Vec::with_capacity(points.len());
        let mut acc = 0.0;
        for (k, p) in points.iter().enumerate() {
            if k > 0 {
                acc += (p[0] - points[k - 1][0]).hypot(p[1] - points[k - 1][1]);
            }
            s.push(acc);
        }
        Self { points, s }
    }

    /// Total length (m).
    pub fn length(&self) -> f64 {
        self.s.last().copied().unwrap_or(0.0)
    }

    /// Direction of travel (rad) at point `j`.
    pub fn heading(&self, j: usize) -> f64 {
        let m = self.points.len();
        let (a, b) = if j + 1 < m {
            (j, j + 1)
        } else {
            (j.saturating_sub(1), j)
        };
        let (p, q) = (self.points[a], self.points[b]);
        (q[1] - p[1]).atan2(q[0] - p[0])
    }
}

/// A random smooth curvy path from the origin (seeded): a uniform Catmull-Rom spline
/// through 4–6 control points, the first at the origin, each next one 1.0–1.8 m from the
/// last in a direction that turns by up to ±95° from the previous leg, all within ±3 m of
/// the origin; sampled every ~2 cm.
pub fn curvy_path(seed: u64) -> Path {
    let mut rng = Rng::new(seed);
    let m = 4 + rng.below(3) as usize;
    let mut ctrl = vec![[0.0, 0.0]];
    let mut psi = uniform(&mut rng, -PI, PI);
    while ctrl.len() < m {
        let last = *ctrl.last().expect("a point");
        let mut placed = None;
        for _ in 0..50 {
            let turn = if ctrl.len() == 1 {
                0.0
            } else {
                uniform(&mut rng, -1.66, 1.66)
            };
            let step = uniform(&mut rng, 1.0, 1.8);
            let dir = psi + turn;
            let p = [last[0] + step * dir.cos(), last[1] + step * dir.sin()];
            if p[0].abs() <= 3.0 && p[1].abs() <= 3.0 {
                placed = Some((p, dir));
                break;
            }
        }
        // Boxed in (rare): head back toward the origin.
        let (p, dir) = placed.unwrap_or_else(|| {
            let dir = (-last[1]).atan2(-last[0]);
            ([last[0] + dir.cos(), last[1] + dir.sin()], dir)
        });
        ctrl.push(p);
        psi = dir;
    }
    // Uniform Catmull-Rom, the end points doubled.
    let at = |k: isize| ctrl[k.clamp(0, m as isize - 1) as usize];
    let mut pts = vec![ctrl[0]];
    for k in 0..m as isize - 1 {
        let (p0, p1, p2, p3) = (at(k - 1), at(k), at(k + 1), at(k + 2));
        let chord = (p2[0] - p1[0]).hypot(p2[1] - p1[1]);
        let steps = (chord / 0.02).ceil().max(1.0) as usize;
        for q in 1..=steps {
            let u = q as f64 / steps as f64;
            let (u2, u3) = (u * u, u * u * u);
            let c = |i: usize| {
                0.5 * (2.0 * p1[i]
                    + (-p0[i] + p2[i]) * u
                    + (2.0 * p0[i] - 5.0 * p1[i] + 4.0 * p2[i] - p3[i]) * u2
                    + (-p0[i] + 3.0 * p1[i] - 3.0 * p2[i] + p3[i]) * u3)
            };
            pts.push([c(0), c(1)]);
        }
    }
    Path::new(pts)
}

/// A pure-pursuit follower (module docs, "Nav2-like"): one [`PurePursuit::step`] per
/// 20 Hz tick with the robot's pose.
#[derive(Clone, Debug)]
pub struct PurePursuit {
    path: Path,
    style: FollowerStyle,
    idx: usize,
    last: Twist,
    done: bool,
}

impl PurePursuit {
    /// A follower of `path` at its start.
    pub fn new(path: Path, style: FollowerStyle) -> Self {
        Self {
            path,
            style,
            idx: 0,
            last: Twist::default(),
            done: false,
        }
    }

    /// True once the robot came within [`GOAL_TOLERANCE`] of the path's end.
    pub fn done(&self) -> bool {
        self.done
    }

    /// The twist for the robot at `pose` (path frame = odometry frame, starting at the
    /// origin): zero once done.
    pub fn step(&mut self, pose: Pose) -> Twist {
        let pts = &self.path.points;
        let end = *pts.last().expect("a path");
        let p = [pose.x, pose.y];
        let dist = |q: [f64; 2]| (q[0] - p[0]).hypot(q[1] - p[1]);
        // Progress: the nearest point within 1 m of path ahead of the last one.
        let (mut best, mut best_d) = (self.idx, dist(pts[self.idx]));
        for (j, &q) in pts.iter().enumerate().skip(self.idx) {
            if self.path.s[j] > self.path.s[self.idx] + 1.0 {
                break;
            }
            let d = dist(q);
            if d < best_d {
                best = j;
                best_d = d;
            }
        }
        self.idx = best;
        let remaining = self.path.length() - self.path.s[self.idx];
        if self.done || (dist(end) < GOAL_TOLERANCE && remaining < 0.2) {
            self.done = true;
            self.last = Twist::default();
            return self.last;
        }
        let speed = self.last.vx.hypot(self.last.vy);
        let ld = (LOOKAHEAD_TIME * speed).clamp(LOOKAHEAD_MIN, LOOKAHEAD_MAX);
        let j = (self.idx..pts.len())
            .find(|&j| dist(pts[j]) >= ld)
            .unwrap_or(pts.len() - 1);
        let target = pts[j];
        let (s, c) = pose.theta.sin_cos();
        let (dx, dy) = (target[0] - p[0], target[1] - p[1]);
        let (xl, yl) = (c * dx + s * dy, -s * dx + c * dy);
        let dl = xl.hypot(yl).max(1e-9);
        let mut v = NAV2_MAX_SPEED;
        if remaining < APPROACH_DIST {
            v = (NAV2_MAX_SPEED * remaining.max(dist(end)) / APPROACH_DIST).max(MIN_APPROACH_SPEED);
        }
        let want = match self.style {
            FollowerStyle::DiffDrive => {
                let angle = yl.atan2(xl);
                if angle.abs() > ROTATE_MIN_ANGLE {
                    Twist {
                        vx: 0.0,
                        vy: 0.0,
                        omega: ROTATE_SPEED.copysign(angle),
                    }
                } else {
                    let kappa = 2.0 * yl / (dl * dl);
                    let radius = 1.0 / kappa.abs().max(1e-9);
                    if radius < MIN_RADIUS && v > MIN_REGULATED_SPEED {
                        v = (v * radius / MIN_RADIUS).max(MIN_REGULATED_SPEED);
                    }
                    let mut omega = v * kappa;
                    if omega.abs() > NAV2_MAX_ANGULAR {
                        omega = NAV2_MAX_ANGULAR.copysign(omega);
                        v = omega / kappa;
                    }
                    Twist {
                        vx: v,
                        vy: 0.0,
                        omega,
                    }
                }
            }
            FollowerStyle::Holonomic => {
                let e = rollbase_control::angle::diff(self.path.heading(j), pose.theta);
                Twist {
                    vx: v * xl / dl,
                    vy: v * yl / dl,
                    omega: (HEADING_GAIN * e).clamp(-NAV2_MAX_ANGULAR, NAV2_MAX_ANGULAR),
                }
            }
        };
        // The velocity smoother: per-component acceleration limits.
        let dt = 1.0 / NAV2_HZ;
        let lim = |now: f64, want: f64, a: f64| now + (want - now).clamp(-a * dt, a * dt);
        let mut next = Twist {
            vx: lim(self.last.vx, want.vx, SMOOTHER_ACCEL),
            vy: lim(self.last.vy, want.vy, SMOOTHER_ACCEL),
            omega: lim(self.last.omega, want.omega, SMOOTHER_ANGULAR_ACCEL),
        };
        // Per-component limits can leave the speed above the largest one while the
        // direction turns: scaled back to it (the smoother's velocity limit).
        let speed = next.vx.hypot(next.vy);
        if speed > NAV2_MAX_SPEED {
            next.vx *= NAV2_MAX_SPEED / speed;
            next.vy *= NAV2_MAX_SPEED / speed;
        }
        self.last = next;
        self.last
    }
}

/// The follower's command stream as a state machine: [`Nav2Stream::next`] once per 20 Hz
/// tick gives the command of that tick (`None` after the end of the stream).
#[derive(Clone, Debug)]
pub struct Nav2Stream {
    follower: PurePursuit,
    tick: u64,
    deadline_s: f64,
    release_from: Option<u64>,
    /// Time (s from the first tick) at which the follower was done (`None`: not, or the
    /// deadline came first).
    pub reached_at: Option<f64>,
    ended: bool,
}

impl Nav2Stream {
    /// A stream following `path`; after `deadline_s` without reaching the goal it releases
    /// (zero twists for [`RELEASE_S`]) and ends anyway.
    pub fn new(path: Path, style: FollowerStyle, deadline_s: f64) -> Self {
        Self {
            follower: PurePursuit::new(path, style),
            tick: 0,
            deadline_s,
            release_from: None,
            reached_at: None,
            ended: false,
        }
    }

    /// Time (s from the first tick) of the next tick.
    pub fn next_time(&self) -> f64 {
        self.tick as f64 / NAV2_HZ
    }

    /// True after the end of the stream.
    pub fn ended(&self) -> bool {
        self.ended
    }

    /// The command of the next tick, for the robot at `pose`.
    pub fn next(&mut self, pose: Pose) -> Option<CommandKind> {
        if self.ended {
            return None;
        }
        let t = self.next_time();
        let release_ticks = (RELEASE_S * NAV2_HZ).round() as u64;
        let kind = match self.release_from {
            Some(k) if self.tick >= k + release_ticks => {
                self.ended = true;
                CommandKind::EndOfStream
            }
            Some(_) => CommandKind::Motion(MotionCommand {
                twist: Twist::default(),
                legs: None,
            }),
            None => {
                let twist = self.follower.step(pose);
                if self.follower.done() || t >= self.deadline_s {
                    if self.follower.done() {
                        self.reached_at = Some(t);
                    }
                    self.release_from = Some(self.tick);
                }
                CommandKind::Motion(MotionCommand {
                    twist: if self.release_from.is_some() {
                        Twist::default()
                    } else {
                        twist
                    },
                    legs: None,
                })
            }
        };
        self.tick += 1;
        Some(kind)
    }
}

/// What a Nav2-like session did.
#[derive(Clone, Debug)]
pub struct Nav2Session {
    /// The commands sent (times from the first tick).
    pub commands: Vec<CommandEvent>,
    /// When the follower reached the goal (s from the first tick), if it did.
    pub reached_at: Option<f64>,
    /// Length of the session: from the first command to the end of the stream (s).
    pub session_s: f64,
}

/// Deadline of a follower on `path` (s): twice the time at full speed, plus 10 s.
pub fn nav2_deadline(path: &Path) -> f64 {
    2.0 * path.length() / NAV2_MAX_SPEED + 10.0
}

/// The follower in open loop: the robot is the ideal integration of the commanded twists
/// (each held for one tick), from the origin. Its [`ideal_path_length`] is the reference
/// path length of the Nav2-like sessions.
pub fn nav2_open_loop(path: &Path, style: FollowerStyle) -> Nav2Session {
    let mut stream = Nav2Stream::new(path.clone(), style, nav2_deadline(path));
    let mut pose = Pose::default();
    let mut commands = Vec::new();
    while let Some(kind) = stream.next(pose) {
        let t = (stream.tick - 1) as f64 / NAV2_HZ;
        if let CommandKind::Motion(m) = kind {
            pose =
                rollbase_control::model::kinematics::se2_integrate(pose, &m.twist, 1.0 / NAV2_HZ);
        }
        commands.push(CommandEvent { t, kind });
    }
    Nav2Session {
        session_s: commands.last().map_or(0.0, |c| c.t),
        commands,
        reached_at: stream.reached_at,
    }
}

/// Runs a Nav2-like session in closed loop through the full frame path in lockstep: at each
/// 20 Hz tick (counted from the moment the core first tracks, as command times are) the
/// follower reads the state port's odometry pose of the last cycle and its command is
/// delivered to the core in that cycle. Ends when the core is done or after
/// `opts.max_seconds`.
pub fn run_nav2(
    opts: &LiveOptions,
    path: &Path,
    style: FollowerStyle,
) -> (RunOutcome, Nav2Session) {
    let (mut core, mut sim, mut bus) = build_live(opts);
    let platform = core.platform().clone();
    let max_cycles = (opts.max_seconds * platform.cycle_hz) as u64;
    let mut records = Vec::with_capacity(max_cycles.min(1 << 14) as usize);
    let mut summary = RunSummary::new("nav2");
    let mut stream = Nav2Stream::new(path.clone(), style, nav2_deadline(path));
    let mut commands = Vec::new();
    let mut st = LockstepState::new(&core);
    core.arm();
    let mut ready_at: Option<f64> = None;
    let mut report = rollbase_control::runtime::LockstepReport::default();
    for k in 0..max_cycles {
        let t = st.time();
        if ready_at.is_none() && core.state() == SupervisorState::Tracking {
            ready_at = Some(t);
        }
        if let Some(t0) = ready_at {
            if !stream.ended() && stream.next_time() <= t - t0 + 1e-9 {
                let ts = stream.next_time();
                let pose = core.base_state().odometry.pose;
                if let Some(kind) = stream.next(pose) {
                    commands.push(CommandEvent { t: ts, kind });
                    core.command(CommandEvent { t, kind });
                }
            }
        }
        lockstep_cycle(
            &mut st,
            &mut core,
            &mut bus,
            &mut sim,
            &mut StepHooks::default(),
        );
        let r = core.record();
        summary.update(r);
        records.push(*r);
        report.cycles = k + 1;
        if core.done() {
            break;
        }
    }
    let session = Nav2Session {
        session_s: commands.last().map_or(0.0, |c| c.t),
        commands,
        reached_at: stream.reached_at,
    };
    let out = RunOutcome {
        records,
        summary,
        report,
        platform,
        final_drive_states: Vec::new(),
        after_end: Vec::new(),
        final_state: Some(*core.base_state()),
        final_skipped: crate::skipped_of(&core),
        final_truth_steer: sim.truth().steer,
        timing: None,
    };
    (out, session)
}

// ---------------------------------------------------------------------------------------
// Waypoint classes
// ---------------------------------------------------------------------------------------

/// z = (x, y, θ, λ_1..λ_4).
pub fn z(x: f64, y: f64, th: f64, legs: [f64; 4]) -> ZVec {
    let mut z = ZVec::zeros();
    z[0] = x;
    z[1] = y;
    z[2] = th;
    for i in 0..4 {
        z[3 + i] = legs[i];
    }
    z
}

/// A waypoint at time `t`.
pub fn wp(t: f64, z: ZVec) -> WaypointSpec {
    WaypointSpec { t: Some(t), z }
}

/// A waypoint without a time.
pub fn wp_untimed(z: ZVec) -> WaypointSpec {
    WaypointSpec { t: None, z }
}

/// The platform turns by `turn` rad about wheel `k`'s contact point in `secs` (waypoints
/// every `turn`/8, which the spline interpolates to within about 2 cm/s of contact speed).
pub fn pivot(k: usize, turn: f64, secs: f64) -> Vec<WaypointSpec> {
    let p = Platform::justin();
    let (l, a) = (p.wheels[k].lambda_nominal, p.wheels[k].alpha);
    (0..=8)
        .map(|q| {
            let th = turn * q as f64 / 8.0;
            // P = (x, y) + R(θ) λ e_α stays where it starts.
            let (px, py) = (l * a.cos(), l * a.sin());
            let (wx, wy) = (l * (th + a).cos(), l * (th + a).sin());
            wp(secs * q as f64 / 8.0, z(px - wx, py - wy, th, [l; 4]))
        })
        .collect()
}

/// The body turns at `omega` while its ICR moves in the body frame along the normal of
/// wheel `k`'s leg, through the wheel's contact point (from `span` m before it to `span` m
/// after it) in `secs`; sampled into waypoints every 0.25 s.
pub fn icr_sweep(k: usize, omega: f64, span: f64, secs: f64) -> Vec<WaypointSpec> {
    let p = Platform::justin();
    let (l, a) = (p.wheels[k].lambda_nominal, p.wheels[k].alpha);
    let wheel = [l * a.cos(), l * a.sin()];
    let d = [-a.sin(), a.cos()];
    let dt = 0.001;
    let steps = (secs / dt).round() as usize;
    let mut pose = Pose::default();
    let mut out = vec![wp(0.0, z(0.0, 0.0, 0.0, [l; 4]))];
    for q in 0..steps {
        let s = span * (2.0 * (q as f64 + 0.5) / steps as f64 - 1.0);
        let icr = [wheel[0] + d[0] * s, wheel[1] + d[1] * s];
        // v = −ω × p: the ICR's own velocity is zero.
        let tw = Twist {
            vx: omega * icr[1],
            vy: -omega * icr[0],
            omega,
        };
        pose = rollbase_control::model::kinematics::se2_integrate(pose, &tw, dt);
        if (q + 1) % 250 == 0 || q + 1 == steps {
            out.push(wp(
                (q + 1) as f64 * dt,
                z(pose.x, pose.y, pose.theta, [l; 4]),
            ));
        }
    }
    out
}

/// The classes of waypoint files of issue 23's "Must show".
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum WaypointClass {
    /// a → b, b again 0.5–1.5 s later (a stop), then c: legs 0.6–1.2 m at 0.3–0.5 m/s, a
    /// constant random heading; the turn at b is +90° or −90° (seed ≡ 0 mod 3), 180° (a
    /// reversal, seed ≡ 1) or uniform in ±180° (seed ≡ 2).
    StopAndGoCorner,
    /// A circle from rest to rest, either sense, a waypoint every 15°: 1 loop of radius
    /// 0.5–1.5 m for even seeds, 2 loops of 0.5–1.0 m for odd ones (keeping the runs short),
    /// timed at the speed of a centripetal acceleration of 0.3–0.45 m/s² (0.39–0.82 m/s);
    /// the heading constant (random).
    CircleConstantHeading,
    /// The same circles with the base facing the centre (it turns once per loop).
    CircleFacingCentre,
    /// Spin in place from rest: 2–3 segments turning ±(1.5–3.2) rad then back by 0.5–2 rad
    /// at 0.5–0.9 rad/s, the legs moving to a new random extension (a quarter of them at a
    /// limit) on every segment at 0.08–0.2 m/s.
    SpinWithLegs,
    /// [`pivot`] about wheel (seed mod 4), turning ±(1.0–2.5) rad at 0.4–0.8 rad/s.
    Pivot,
    /// [`icr_sweep`] across wheel (seed mod 4) at ±(0.5–0.9) rad/s, span 0.3–0.5 m,
    /// over 3–5 s (a multiple of 0.25 s).
    IcrSweep,
    /// A fast wavy curve sampled every 0.1–0.2 s: 3–4.5 m at a top speed of 0.6–0.9 m/s
    /// (ramps of 0.8 s from and to rest), the direction of travel swinging ±(0.4–0.9) rad
    /// with a wavelength of 1.5–3 m, the heading turning up to 0.3 rad/m.
    DenseAtSpeed,
    /// Files with waypoints without a time, the last one always untimed: seed ≡ 0 mod 3 is
    /// the issue's file ((0, 0) then (1, 0), neither timed); ≡ 1: 4 waypoints, the first
    /// three timed; ≡ 2: 3–5 waypoints, every third one untimed (timed, timed, untimed, …). Random segments move
    /// 0.4–1.2 m, turn up to ±1.2 rad, and set a leg to a new value now and then.
    UntimedMixed,
}

impl WaypointClass {
    /// Every class.
    pub const ALL: [WaypointClass; 8] = [
        Self::StopAndGoCorner,
        Self::CircleConstantHeading,
        Self::CircleFacingCentre,
        Self::SpinWithLegs,
        Self::Pivot,
        Self::IcrSweep,
        Self::DenseAtSpeed,
        Self::UntimedMixed,
    ];

    /// Short name, for messages.
    pub fn name(self) -> &'static str {
        match self {
            Self::StopAndGoCorner => "stop-and-go corner",
            Self::CircleConstantHeading => "circle, constant heading",
            Self::CircleFacingCentre => "circle, facing the centre",
            Self::SpinWithLegs => "spin in place, legs moving",
            Self::Pivot => "pivot about a wheel",
            Self::IcrSweep => "ICR sweep across a wheel",
            Self::DenseAtSpeed => "dense waypoints at speed",
            Self::UntimedMixed => "untimed and mixed",
        }
    }
}

/// The nominal leg extension of the default platform (m).
fn nominal_legs() -> [f64; 4] {
    let p = Platform::justin();
    [
        p.wheels[0].lambda_nominal,
        p.wheels[1].lambda_nominal,
        p.wheels[2].lambda_nominal,
        p.wheels[3].lambda_nominal,
    ]
}

/// A random instance of `class` (seeded; the class's docs say what varies).
pub fn waypoint_class(class: WaypointClass, seed: u64) -> Vec<WaypointSpec> {
    let mut rng = Rng::new(seed ^ 0xF10A_0000 ^ ((class as u64) << 40));
    let l = nominal_legs();
    match class {
        WaypointClass::StopAndGoCorner => {
            let psi = uniform(&mut rng, -PI, PI);
            let th = uniform(&mut rng, -PI, PI);
            let (d1, d2) = (uniform(&mut rng, 0.6, 1.2), uniform(&mut rng, 0.6, 1.2));
            let v = uniform(&mut rng, 0.3, 0.5);
            let stop = uniform(&mut rng, 0.5, 1.5);
            let turn = match seed % 3 {
                0 => FRAC_PI_2.copysign(uniform(&mut rng, -1.0, 1.0)),
                1 => PI,
                _ => uniform(&mut rng, -PI, PI),
            };
            let b = [d1 * psi.cos(), d1 * psi.sin()];
            let c = [
                b[0] + d2 * (psi + turn).cos(),
                b[1] + d2 * (psi + turn).sin(),
            ];
            let t1 = d1 / v;
            vec![
                wp(0.0, z(0.0, 0.0, th, l)),
                wp(t1, z(b[0], b[1], th, l)),
                wp(t1 + stop, z(b[0], b[1], th, l)),
                wp(t1 + stop + d2 / v, z(c[0], c[1], th, l)),
            ]
        }
        WaypointClass::CircleConstantHeading | WaypointClass::CircleFacingCentre => {
            let facing = class == WaypointClass::CircleFacingCentre;
            let loops = 1 + (seed % 2) as usize;
            let r = uniform(&mut rng, 0.5, if loops == 1 { 1.5 } else { 1.0 });
            let sense = if rng.chance(0.5) { 1.0 } else { -1.0 };
            // The speed of a centripetal acceleration of 0.3–0.45 m/s².
            let v = (uniform(&mut rng, 0.3, 0.45) * r).sqrt();
            let a0 = uniform(&mut rng, -PI, PI);
            let th0 = uniform(&mut rng, -PI, PI);
            let step = 15f64.to_radians();
            let n = 24 * loops;
            // Centre chosen so that the circle starts at the origin.
            let c = [-r * a0.cos(), -r * a0.sin()];
            (0..=n)
                .map(|k| {
                    let a = a0 + sense * step * k as f64;
                    let th = if facing {
                        // The body's X axis points from the base to the centre.
                        a + PI
                    } else {
                        th0
                    };
                    wp(
                        k as f64 * r * step / v,
                        z(c[0] + r * a.cos(), c[1] + r * a.sin(), th, l),
                    )
                })
                .collect()
        }
        WaypointClass::SpinWithLegs => {
            let p = Platform::justin();
            let segments = 2 + (seed % 2) as usize;
            let mut legs = l;
            let mut th = 0.0f64;
            let mut t = 0.0;
            let mut out = vec![wp(0.0, z(0.0, 0.0, 0.0, legs))];
            for s in 0..segments {
                let dth = if s == 0 {
                    uniform(&mut rng, 1.5, 3.2).copysign(uniform(&mut rng, -1.0, 1.0))
                } else {
                    -th.signum() * uniform(&mut rng, 0.5, 2.0)
                };
                let prev = legs;
                for (i, leg) in legs.iter_mut().enumerate() {
                    let (lo, hi) = (p.wheels[i].lambda_min, p.wheels[i].lambda_max);
                    let c = rng.next_f64();
                    *leg = if c < 0.125 {
                        lo
                    } else if c < 0.25 {
                        hi
                    } else {
                        uniform(&mut rng, lo, hi)
                    };
                }
                let dl = (0..4)
                    .map(|i| (legs[i] - prev[i]).abs())
                    .fold(0.0, f64::max);
                let h = (dth.abs() / uniform(&mut rng, 0.5, 0.9))
                    .max(dl / uniform(&mut rng, 0.08, 0.2))
                    .max(1.0);
                th += dth;
                t += h;
                out.push(wp(t, z(0.0, 0.0, th, legs)));
            }
            out
        }
        WaypointClass::Pivot => {
            let turn = uniform(&mut rng, 1.0, 2.5).copysign(uniform(&mut rng, -1.0, 1.0));
            let secs = turn.abs() / uniform(&mut rng, 0.4, 0.8);
            pivot((seed % 4) as usize, turn, secs)
        }
        WaypointClass::IcrSweep => {
            let omega = uniform(&mut rng, 0.5, 0.9).copysign(uniform(&mut rng, -1.0, 1.0));
            let span = uniform(&mut rng, 0.3, 0.5);
            // A whole number of the builder's 0.25 s waypoint spacing.
            let secs = (uniform(&mut rng, 3.0, 5.0) * 4.0).round() / 4.0;
            icr_sweep((seed % 4) as usize, omega, span, secs)
        }
        WaypointClass::DenseAtSpeed => {
            let length = uniform(&mut rng, 3.0, 4.5);
            let vmax = uniform(&mut rng, 0.6, 0.9);
            let ramp = 0.8;
            let amp = uniform(&mut rng, 0.4, 0.9);
            let wave = uniform(&mut rng, 1.5, 3.0);
            let psi0 = uniform(&mut rng, -PI, PI);
            let th0 = uniform(&mut rng, -PI, PI);
            let rot = uniform(&mut rng, -0.3, 0.3);
            let h = uniform(&mut rng, 0.1, 0.2);
            // Speed profile: smoothstep ramps of `ramp` s from and to rest around a cruise at
            // vmax; the cruise lasts what the length needs (the ramps cover vmax·ramp).
            let cruise = (length - vmax * ramp) / vmax;
            let total = cruise + 2.0 * ramp;
            let smooth = |u: f64| {
                let u = u.clamp(0.0, 1.0);
                u * u * (3.0 - 2.0 * u)
            };
            let speed = |t: f64| vmax * smooth(t / ramp).min(smooth((total - t) / ramp));
            let dt = 0.001;
            let (mut x, mut y, mut s) = (0.0, 0.0, 0.0);
            let mut out = vec![wp(0.0, z(0.0, 0.0, th0, l))];
            let mut next = h;
            let steps = (total / dt).round() as usize;
            for q in 1..=steps {
                let t = q as f64 * dt;
                let v = speed(t - 0.5 * dt);
                let psi = psi0 + amp * (TAU * s / wave).sin();
                x += v * psi.cos() * dt;
                y += v * psi.sin() * dt;
                s += v * dt;
                if t >= next - 1e-9 || q == steps {
                    out.push(wp(t, z(x, y, th0 + rot * s, l)));
                    next += h;
                }
            }
            out
        }
        WaypointClass::UntimedMixed => {
            let p = Platform::justin();
            let variant = seed % 3;
            if variant == 0 {
                return vec![
                    wp_untimed(z(0.0, 0.0, 0.0, l)),
                    wp_untimed(z(1.0, 0.0, 0.0, l)),
                ];
            }
            let m = if variant == 1 {
                4
            } else {
                3 + rng.below(3) as usize
            };
            let mut out = vec![wp(0.0, z(0.0, 0.0, 0.0, l))];
            let mut legs = l;
            let mut t = 0.0;
            for k in 1..m {
                let prev = out[k - 1].z;
                let d = uniform(&mut rng, 0.4, 1.2);
                let dir = uniform(&mut rng, -PI, PI);
                let dth = uniform(&mut rng, -1.2, 1.2);
                if rng.chance(0.3) {
                    let i = rng.below(4) as usize;
                    legs[i] = uniform(&mut rng, p.wheels[i].lambda_min, p.wheels[i].lambda_max);
                }
                let next = z(
                    prev[0] + d * dir.cos(),
                    prev[1] + d * dir.sin(),
                    prev[2] + dth,
                    legs,
                );
                t += (d / uniform(&mut rng, 0.25, 0.5))
                    .max(dth.abs() / 0.5)
                    .max(1.0);
                let timed = k + 1 < m && (variant == 1 || k % 3 != 2);
                out.push(WaypointSpec {
                    t: timed.then_some(t),
                    z: next,
                });
            }
            out
        }
    }
}

/// A long waypoint file (seeded), for the planning benchmark: `m` waypoints from the origin,
/// each segment 0.2–0.5 m in a direction turning by up to ±0.6 rad from the last one, the
/// heading turning by up to ±0.3 rad, one leg set to a new extension on one segment in
/// eight; timed at 0.3–0.6 m/s (at least 0.3 s a segment), every tenth waypoint without a
/// time (the last one timed).
pub fn waypoint_tour(seed: u64, m: usize) -> Vec<WaypointSpec> {
    let p = Platform::justin();
    let mut rng = Rng::new(seed ^ 0x7007);
    let mut legs = nominal_legs();
    let mut out = vec![wp(0.0, z(0.0, 0.0, 0.0, legs))];
    let mut dir = uniform(&mut rng, -PI, PI);
    let mut t = 0.0;
    for k in 1..m {
        let prev = out[k - 1].z;
        dir += uniform(&mut rng, -0.6, 0.6);
        let d = uniform(&mut rng, 0.2, 0.5);
        if rng.chance(0.125) {
            let i = rng.below(4) as usize;
            legs[i] = uniform(&mut rng, p.wheels[i].lambda_min, p.wheels[i].lambda_max);
        }
        let next = z(
            prev[0] + d * dir.cos(),
            prev[1] + d * dir.sin(),
            prev[2] + uniform(&mut rng, -0.3, 0.3),
            legs,
        );
        t += (d / uniform(&mut rng, 0.3, 0.6)).max(0.3);
        out.push(WaypointSpec {
            t: (k % 10 != 0 || k + 1 == m).then_some(t),
            z: next,
        });
    }
    out
}

// ---------------------------------------------------------------------------------------
// Planned timing (the lead's additions to timescale.rs, through one adapter)
// ---------------------------------------------------------------------------------------

/// What a plan says about its own timing beyond [`rollbase_control::reference::status::Timing`].
#[derive(Clone, Debug, PartialEq)]
pub struct PlanTiming {
    /// The plan's executed duration (s).
    pub planned_s: f64,
    /// The time-optimal timing of the path (s; no jerk smoothing).
    pub optimal_s: f64,
    /// Sum of the planned dwells (s).
    pub dwell_s: f64,
    /// The planned dwells: intervals of executed time (s) in which the clock holds while
    /// wheels re-steer.
    pub dwells: Vec<(f64, f64)>,
}

/// The plan's timing: its executed duration, the time-optimal timing of the path's motions
/// ([`rollbase_control::reference::status::Timing::optimal_duration_s`]: the passes' timing before the
/// jerk smoothing), the dwells in all and each dwell's executed-time interval
/// ([`ScaledTrajectory::dwells`]).
pub fn plan_timing(plan: &ScaledTrajectory) -> PlanTiming {
    let t = plan.timing().expect("a scaled trajectory has a timing");
    PlanTiming {
        planned_s: plan.duration(),
        optimal_s: t.optimal_duration_s,
        dwell_s: t.dwell_s,
        dwells: plan.dwells().to_vec(),
    }
}

// ---------------------------------------------------------------------------------------
// Measures
// ---------------------------------------------------------------------------------------

/// Path length travelled by the simulator's truth (m): Σ √(Δx² + Δy²) of the true pose of
/// the base's origin between consecutive records that both carry a truth (translation only:
/// a spin in place travels 0). At 250 Hz the chord sum equals the arc length to far below a
/// millimetre per metre. It counts every back-and-forth, so a base that jitters on a noisy
/// command adds its jitter.
pub fn truth_path_length(records: &[CycleRecord]) -> f64 {
    records
        .windows(2)
        .filter_map(|w| match (w[0].truth, w[1].truth) {
            (Some((a, _)), Some((b, _))) => Some((b.x - a.x).hypot(b.y - a.y)),
            _ => None,
        })
        .sum()
}

/// Steering rate (rad/s) a reversal must exceed on both sides.
pub const REVERSAL_RATE: f64 = 0.2;

/// Steering reversals of wheel `wheel` over the records: sign changes of its **measured**
/// steering rate (`record.measurement.wheels[wheel].steer_rate`, what the wheel does) counted
/// with a hysteresis of ±[`REVERSAL_RATE`]: a reversal is the rate above +0.2 rad/s and later
/// below −0.2 rad/s, or the other way round (rates in between do not reset the last sign).
///
/// The measured rate, not the commanded one ([`setpoint_reversals`]): the steering setpoint
/// carries the drives' lag compensation, φ̇* + τ φ̈* (τ = 15 ms; `lag_compensation` in
/// control/src/runtime/core.rs), which dips below zero at the end of every turn braked faster
/// than 0.2 rad/s / τ ≈ 13 rad/s² although the drive, a first-order lag, only comes to rest
/// and the wheel never turns back. On the σ = 0.02 m/s joystick session the setpoints
/// changed sign 16–23 times per wheel, the wheels 13–19 times, the reference 11–19 times.
/// The encoders' noise and quantisation (about 1e-3 rad/s) are far below the hysteresis.
pub fn steering_reversals(records: &[CycleRecord], wheel: usize) -> usize {
    sign_changes(
        records
            .iter()
            .map(|r| r.measurement.wheels[wheel].steer_rate),
    )
}

/// [`steering_reversals`]'s count on the commanded steering rate (the setpoint sent, lag
/// compensation included): reported beside it.
pub fn setpoint_reversals(records: &[CycleRecord], wheel: usize) -> usize {
    sign_changes(records.iter().map(|r| r.command.wheels[wheel].steer_rate))
}

/// Sign changes of a rate beyond ±[`REVERSAL_RATE`] (see [`steering_reversals`]).
fn sign_changes(rates: impl Iterator<Item = f64>) -> usize {
    let mut last = 0.0f64;
    let mut count = 0;
    for rate in rates {
        let sign = if rate > REVERSAL_RATE {
            1.0
        } else if rate < -REVERSAL_RATE {
            -1.0
        } else {
            continue;
        };
        if last != 0.0 && sign != last {
            count += 1;
        }
        last = sign;
    }
    count
}

/// The steering reversals a command stream asks for by itself: [`steering_reversals`]'s rule
/// (sign changes of a steering rate beyond ±[`REVERSAL_RATE`]) applied to the wheels of an
/// ideal follower of `cmds` on `p` — each wheel pointing along its contact velocity for each
/// motion command's twist (legs at their nominal extension, on the branch nearest its last
/// angle), its rate the change between two consecutive commands over their interval; wheels
/// slower than [`rollbase_control::reference::limits::HOLD_SPEED`] in either command are skipped (their
/// direction means nothing). A session's stick that moves to a new random twist about 1.5
/// times a second asks for about one reversal per wheel per 2 s by itself; what a run does
/// beyond that is the shaper's (or the noise's) own.
pub fn command_reversals(cmds: &[CommandEvent], p: &Platform) -> [usize; 4] {
    let hold = rollbase_control::reference::limits::HOLD_SPEED;
    let dir = |t: &Twist, i: usize| -> Option<f64> {
        let w = p.wheels.get(i)?;
        let (sa, ca) = w.alpha.sin_cos();
        let l = w.lambda_nominal;
        let u = [t.vx - t.omega * l * sa, t.vy + t.omega * l * ca];
        (u[0].hypot(u[1]) >= hold).then(|| u[1].atan2(u[0]))
    };
    let mut last: Option<(f64, Twist)> = None;
    let mut sign = [0.0f64; 4];
    let mut count = [0usize; 4];
    for ev in cmds {
        let CommandKind::Motion(m) = ev.kind else {
            continue;
        };
        if let Some((t0, tw0)) = last {
            let h = ev.t - t0;
            if h > 0.0 {
                for i in 0..4 {
                    let (Some(a), Some(b)) = (dir(&tw0, i), dir(&m.twist, i)) else {
                        continue;
                    };
                    // The change modulo π (either roll direction), nearest branch.
                    let mut d = rollbase_control::angle::diff(b, a);
                    if d > FRAC_PI_2 {
                        d -= PI;
                    } else if d < -FRAC_PI_2 {
                        d += PI;
                    }
                    let rate = d / h;
                    let sg = if rate > REVERSAL_RATE {
                        1.0
                    } else if rate < -REVERSAL_RATE {
                        -1.0
                    } else {
                        continue;
                    };
                    if sign[i] != 0.0 && sg != sign[i] {
                        count[i] += 1;
                    }
                    sign[i] = sg;
                }
            }
        }
        last = Some((ev.t, m.twist));
    }
    count
}

/// Speed (m/s) below which the base stands.
pub const STANDING_SPEED: f64 = 0.01;
/// Radius (m) of the part of the base whose points must be that slow (the wheels sit within
/// about 0.56 m of the centre).
pub const STANDING_RADIUS: f64 = 0.5;

/// Whether a record is aligning: the supervisor aligns (state Aligning, mode `align`) or the
/// shaper steers its wheels before rolling (`shaping.limiting == Aligning`).
pub fn is_aligning(r: &CycleRecord) -> bool {
    r.state == SupervisorState::Aligning
        || r.mode == "align"
        || r.shaping.limiting == Limiting::Aligning
}

/// Fraction of all records (cycles of the run) spent aligning ([`is_aligning`]) with the
/// base standing: by its truth, every point within [`STANDING_RADIUS`] of the origin moves
/// slower than [`STANDING_SPEED`], i.e. |v| + [`STANDING_RADIUS`]·|ω| < 1 cm/s, with v and ω
/// the truth's backward difference to the previous record (the first record uses the
/// difference to the second). Records without a truth count as not standing.
pub fn aligning_standing_fraction(records: &[CycleRecord]) -> f64 {
    if records.is_empty() {
        return 0.0;
    }
    let standing = |a: &CycleRecord, b: &CycleRecord| match (a.truth, b.truth) {
        (Some((p, _)), Some((q, _))) if b.t > a.t => {
            let dt = b.t - a.t;
            let v = (q.x - p.x).hypot(q.y - p.y) / dt;
            let w = (q.theta - p.theta).abs() / dt;
            v + STANDING_RADIUS * w < STANDING_SPEED
        }
        _ => false,
    };
    let count = (0..records.len())
        .filter(|&k| {
            let (a, b) = if k == 0 {
                (0, 1.min(records.len() - 1))
            } else {
                (k - 1, k)
            };
            is_aligning(&records[k]) && standing(&records[a], &records[b])
        })
        .count();
    count as f64 / records.len() as f64
}

/// Executed duration of a trajectory run (s): from the start of the first Tracking cycle to
/// the start of the first Stopped cycle after it (`None` if it never tracked or never
/// stopped). It includes the controlled stop after the trajectory's end.
pub fn executed_duration(records: &[CycleRecord]) -> Option<f64> {
    let k0 = records
        .iter()
        .position(|r| r.state == SupervisorState::Tracking)?;
    let k1 = records[k0..]
        .iter()
        .position(|r| r.state == SupervisorState::Stopped)?;
    Some(records[k0 + k1].t - records[k0].t)
}

/// The clock of a plan as the run executed it: for every Tracking record whose executed time
/// t_e (cycles since the first Tracking cycle × `dt`: the core starts the reference clock at
/// 0 in that cycle) is before the plan's end, `(t_e, ṡ(t_e))` from
/// [`ScaledTrajectory::clock`].
pub fn clock_samples(records: &[CycleRecord], plan: &ScaledTrajectory, dt: f64) -> Vec<(f64, f64)> {
    let Some(k0) = records
        .iter()
        .position(|r| r.state == SupervisorState::Tracking)
    else {
        return Vec::new();
    };
    let c0 = records[k0].cycle;
    let end = plan.duration();
    records[k0..]
        .iter()
        .filter(|r| r.state == SupervisorState::Tracking)
        .map(|r| (r.cycle - c0) as f64 * dt)
        .filter(|&te| te < end)
        .map(|te| (te, plan.clock(te).1))
        .collect()
}

/// Clock speed below which the plan counts as crawling.
pub const SLOW_CLOCK: f64 = 0.05;
/// How far (s) a dwell is widened on either side for [`slow_clock`]: the clock's ramp into
/// and out of a hold (the time scaling's jerk time is 40 ms; this leaves room for the ramp
/// between ṡ = 0.05 and the hold).
pub const DWELL_EDGE_S: f64 = 0.1;

/// Where a clock crawls outside the planned dwells.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct SlowClock {
    /// Time (s) with ṡ < [`SLOW_CLOCK`] outside every dwell widened by [`DWELL_EDGE_S`]
    /// (samples × their spacing).
    pub outside_s: f64,
    /// Longest stretch of consecutive such samples (s).
    pub longest_s: f64,
    /// Where that stretch starts (executed time, s).
    pub longest_at_s: f64,
    /// Smallest ṡ outside the widened dwells (1 if there is no sample there).
    pub min_outside: f64,
    /// Smallest ṡ of all samples (1 if there is none).
    pub min_all: f64,
    /// Time (s) with ṡ < [`SLOW_CLOCK`] inside the widened dwells.
    pub inside_s: f64,
}

/// [`SlowClock`] of clock samples (`(t, ṡ)`, evenly spaced by `dt`, as [`clock_samples`]
/// gives them) against planned dwells (executed-time intervals).
pub fn slow_clock(samples: &[(f64, f64)], dwells: &[(f64, f64)], dt: f64) -> SlowClock {
    let in_dwell = |t: f64| {
        dwells
            .iter()
            .any(|&(a, b)| t >= a - DWELL_EDGE_S && t <= b + DWELL_EDGE_S)
    };
    let mut s = SlowClock {
        min_outside: 1.0,
        min_all: 1.0,
        ..Default::default()
    };
    let mut run = 0.0;
    let mut run_at = 0.0;
    for &(t, v) in samples {
        s.min_all = s.min_all.min(v);
        let inside = in_dwell(t);
        if !inside {
            s.min_outside = s.min_outside.min(v);
        }
        if v < SLOW_CLOCK && !inside {
            if run == 0.0 {
                run_at = t;
            }
            run += dt;
            s.outside_s += dt;
            if run > s.longest_s {
                s.longest_s = run;
                s.longest_at_s = run_at;
            }
        } else {
            run = 0.0;
            if v < SLOW_CLOCK {
                s.inside_s += dt;
            }
        }
    }
    s
}

/// Limit violations of one kind at one hand-over: every consecutive pair of commands whose
/// check ([`rollbase_control::reference::limits::check_command`]) fails, grouped by (mode of the earlier
/// command, mode of the later one, what was exceeded).
#[derive(Clone, Debug, PartialEq)]
pub struct ModeViolations {
    /// Mode of the earlier command of the pair.
    pub from: &'static str,
    /// Mode of the later command.
    pub to: &'static str,
    /// The limit exceeded (the first the check reports for the pair).
    pub what: Limiting,
    /// How many pairs.
    pub count: usize,
    /// The worst of them (largest value / limit) and its cycle.
    pub worst: (Violation, u64),
}

impl fmt::Display for ModeViolations {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let (v, cycle) = &self.worst;
        write!(
            f,
            "{} → {}: {} × {} (worst cycle {cycle}: {v})",
            self.from,
            self.to,
            self.count,
            self.what.name()
        )
    }
}

/// Every failing consecutive pair of commands of a run, grouped ([`ModeViolations`]), in
/// order of first appearance.
pub fn limit_violations(records: &[CycleRecord], p: &Platform) -> Vec<ModeViolations> {
    let mut out: Vec<ModeViolations> = Vec::new();
    for w in records.windows(2) {
        let Some(v) = rollbase_control::reference::limits::check_command(
            &p.limits,
            &w[0].command,
            &w[1].command,
            p.dt(),
        ) else {
            continue;
        };
        let key = (w[0].mode, w[1].mode, v.what);
        match out.iter_mut().find(|m| (m.from, m.to, m.what) == key) {
            Some(m) => {
                m.count += 1;
                if (v.value / v.limit).abs() > (m.worst.0.value / m.worst.0.limit).abs() {
                    m.worst = (v, w[1].cycle);
                }
            }
            None => out.push(ModeViolations {
                from: key.0,
                to: key.1,
                what: key.2,
                count: 1,
                worst: (v, w[1].cycle),
            }),
        }
    }
    out
}

// ---------------------------------------------------------------------------------------
// Figures of a run, and the checks of e2e_flow
// ---------------------------------------------------------------------------------------

/// The measures of a live session.
#[derive(Clone, Debug)]
pub struct LiveFigures {
    /// Length of the session the bounds scale with (s).
    pub session_s: f64,
    /// [`truth_path_length`] (m).
    pub truth_path_m: f64,
    /// The reference path length (m): the noise-free command's (see the tests).
    pub reference_path_m: f64,
    /// [`steering_reversals`] per wheel.
    pub reversals: [usize; 4],
    /// [`setpoint_reversals`] per wheel (reported, not bounded).
    pub setpoint_reversals: [usize; 4],
    /// [`command_reversals`] of the session's noise-free commands per wheel: what the command
    /// asks for by itself.
    pub command_reversals: [usize; 4],
    /// [`aligning_standing_fraction`].
    pub aligning_standing: f64,
    /// The run's limit violations ([`limit_violations`]).
    pub violations: Vec<ModeViolations>,
    /// Final state, errors against the truth (mm, °, mm).
    pub final_state: String,
    /// Largest position error (m).
    pub max_position_error_m: f64,
    /// Largest heading error (rad).
    pub max_heading_error_rad: f64,
    /// Largest leg error (m).
    pub max_leg_error_m: f64,
}

impl LiveFigures {
    /// The figures of `out` for a session of `session_s` seconds whose reference path is
    /// `reference_path_m` long.
    pub fn of(
        out: &RunOutcome,
        session_s: f64,
        reference_path_m: f64,
        command_reversals: [usize; 4],
    ) -> Self {
        let mut reversals = [0; 4];
        let mut setpoint = [0; 4];
        for i in 0..4 {
            reversals[i] = steering_reversals(&out.records, i);
            setpoint[i] = setpoint_reversals(&out.records, i);
        }
        let s = &out.summary;
        Self {
            session_s,
            truth_path_m: truth_path_length(&out.records),
            reference_path_m,
            reversals,
            setpoint_reversals: setpoint,
            command_reversals,
            aligning_standing: aligning_standing_fraction(&out.records),
            violations: limit_violations(&out.records, &out.platform),
            final_state: s.final_state.clone(),
            max_position_error_m: s.max_position_error_m,
            max_heading_error_rad: s.max_heading_error_rad,
            max_leg_error_m: s.max_leg_error_m,
        }
    }

    /// Truth path length over the reference's.
    pub fn path_ratio(&self) -> f64 {
        self.truth_path_m / self.reference_path_m
    }

    /// The bounds in `b` on these measures that are missed (empty when all hold).
    pub fn misses(&self, b: &LiveBounds) -> Vec<String> {
        let mut m = Vec::new();
        // NaN (no reference) misses too.
        let enough = self.path_ratio() >= b.path_share;
        if !enough {
            m.push(format!(
                "the truth travelled {:.2} m, {:.1} % of the reference's {:.2} m (≥ {:.0} %)",
                self.truth_path_m,
                100.0 * self.path_ratio(),
                self.reference_path_m,
                100.0 * b.path_share
            ));
        }
        let allowed = b.allowed_reversals(self.session_s);
        for (i, &r) in self.reversals.iter().enumerate() {
            let own = self.command_reversals[i];
            if r > own + allowed {
                m.push(format!(
                    "wheel {} reversed its steering {r} times in {:.0} s, {} beyond the {own} its command asks for (≤ {allowed})",
                    i + 1,
                    self.session_s,
                    r - own
                ));
            }
        }
        let few = self.aligning_standing <= b.aligning_standing;
        if !few {
            m.push(format!(
                "{:.1} % of the cycles aligning with the base standing (≤ {:.0} %)",
                100.0 * self.aligning_standing,
                100.0 * b.aligning_standing
            ));
        }
        m
    }
}

/// Bounds on a live session's [`LiveFigures`].
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct LiveBounds {
    /// Least share of the reference path the truth must travel.
    pub path_share: f64,
    /// Most steering reversals per wheel per 2 s of session beyond the command's own.
    pub reversals_per_2s: f64,
    /// Largest share of cycles aligning with the base standing.
    pub aligning_standing: f64,
}

impl LiveBounds {
    /// Issue 23's bounds: path ≥ 90 %, at most one reversal per wheel per 2 s of session
    /// (counted beyond the reversals the command asks for by itself,
    /// [`command_reversals`]), aligning with the base standing ≤ 10 % of the cycles.
    pub const ISSUE: LiveBounds = LiveBounds {
        path_share: 0.9,
        reversals_per_2s: 1.0,
        aligning_standing: 0.10,
    };

    /// Reversals allowed beyond the command's own in a session of `session_s` seconds.
    pub fn allowed_reversals(&self, session_s: f64) -> usize {
        (self.reversals_per_2s * session_s / 2.0).floor() as usize
    }
}

impl fmt::Display for LiveFigures {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(
            f,
            "session {:.1} s: path {:.2} m of {:.2} m ({:.1} %), reversals {:?} (setpoints {:?}; the command's own {:?}; issue 23 allows {} beyond), aligning standing {:.1} %, {}, errors {:.2} mm {:.3}° legs {:.2} mm, limit violations: {}",
            self.session_s,
            self.truth_path_m,
            self.reference_path_m,
            100.0 * self.path_ratio(),
            self.reversals,
            self.setpoint_reversals,
            self.command_reversals,
            LiveBounds::ISSUE.allowed_reversals(self.session_s),
            100.0 * self.aligning_standing,
            self.final_state,
            self.max_position_error_m * 1e3,
            self.max_heading_error_rad.to_degrees(),
            self.max_leg_error_m * 1e3,
            violations_text(&self.violations)
        )
    }
}

/// The violations, `;`-separated ("none" when there is none).
pub fn violations_text(v: &[ModeViolations]) -> String {
    if v.is_empty() {
        "none".into()
    } else {
        v.iter()
            .map(|m| m.to_string())
            .collect::<Vec<_>>()
            .join("; ")
    }
}

/// Longest a waypoint run may take (s of platform time) whatever its plan says: every
/// instance of [`waypoint_class`] plans well below this (a plan that does not end is cut
/// here and fails as not Stopped).
pub const MAX_WAYPOINT_RUN_S: f64 = 40.0;
/// Platform time (s) a waypoint run gets beyond its bound on the executed duration: the
/// alignment before tracking and the controlled stop after the trajectory's end.
pub const WAYPOINT_RUN_SLACK_S: f64 = 10.0;
/// The issue's bound: executed ≤ this × (time-optimal timing + planned dwells).
pub const DURATION_RATIO: f64 = 1.25;

/// One waypoint run and its plan.
pub struct WaypointRun {
    /// The run.
    pub out: RunOutcome,
    /// The plan, planned again here as the core planned it (same inputs, deterministic;
    /// the core's timing is checked to be the same in [`WaypointFigures::misses`]).
    pub plan: ScaledTrajectory,
    /// The plan's timing through [`plan_timing`].
    pub plan_timing: PlanTiming,
    /// Nominal duration of the spline (s).
    pub nominal_s: f64,
}

/// Options of a waypoint run.
#[derive(Clone, Debug)]
pub struct WaypointRunOptions {
    /// Wire profile.
    pub profile: Protocol,
    /// `--avoidance` (`None`: off).
    pub avoidance: Option<rollbase_control::reference::avoidance::AvoidanceConfig>,
    /// Simulator seed.
    pub seed: u64,
}

/// Plans `specs` as the runtime does (the default time scaling) and runs them through the
/// full frame path in lockstep, the simulated platform starting at the first waypoint; the
/// run is cut after min(planned, 1.25 × (optimal + dwells)) + [`WAYPOINT_RUN_SLACK_S`], at
/// most [`MAX_WAYPOINT_RUN_S`]. `Err` when the spline or the plan is refused.
pub fn run_waypoints(
    specs: &[WaypointSpec],
    o: &WaypointRunOptions,
) -> Result<WaypointRun, String> {
    let mut platform = Platform::justin();
    platform.protocol = o.profile;
    let mut opts = RunOptions::new(Scenario::Seed000);
    opts.runtime = rollbase_control::runtime::RuntimeConfig {
        avoidance: o.avoidance,
        ..Default::default()
    };
    let cfg: TimeScaleConfig = opts
        .runtime
        .time_scaling
        .ok_or("the default runtime has no time scaling")?;
    let spline = QuinticSpline::from_specs(&platform, specs).map_err(|e| e.to_string())?;
    let nominal_s = spline.duration();
    // With the avoidance on, the runtime scales the path the avoidance made before the run.
    let path: Box<dyn Trajectory> = match o.avoidance.filter(|a| a.enabled) {
        Some(a) => Box::new(
            rollbase_control::reference::avoidance::AvoidedTrajectory::plan(
                &platform,
                Box::new(spline),
                a,
            )
            .map_err(|e| e.to_string())?,
        ),
        None => Box::new(spline),
    };
    let plan = ScaledTrajectory::plan(&platform, path, cfg).map_err(|e| e.to_string())?;
    let pt = plan_timing(&plan);
    let bound = DURATION_RATIO * (pt.optimal_s + pt.dwell_s);
    let budget = (pt.planned_s.min(bound) + WAYPOINT_RUN_SLACK_S).min(MAX_WAYPOINT_RUN_S);
    opts.seed = o.seed;
    opts.waypoint_specs = Some(specs.to_vec());
    opts.max_seconds = Some(budget);
    if o.profile == Protocol::Cia402 {
        opts = opts.cia402();
    }
    let out = crate::run(&opts);
    Ok(WaypointRun {
        out,
        plan,
        plan_timing: pt,
        nominal_s,
    })
}

/// The measures of a waypoint run.
#[derive(Clone, Debug)]
pub struct WaypointFigures {
    /// Nominal duration of the spline (s).
    pub nominal_s: f64,
    /// The plan's timing ([`plan_timing`]).
    pub timing: PlanTiming,
    /// [`executed_duration`] of the run (s).
    pub executed_s: Option<f64>,
    /// [`slow_clock`] of the run's [`clock_samples`] against the planned dwells.
    pub clock: SlowClock,
    /// The core planned the same timing as [`WaypointRun::plan`].
    pub same_plan: bool,
    /// The run's limit violations.
    pub violations: Vec<ModeViolations>,
    /// Final state.
    pub final_state: String,
    /// Largest position error (m).
    pub max_position_error_m: f64,
    /// Largest heading error (rad).
    pub max_heading_error_rad: f64,
    /// Largest leg error (m).
    pub max_leg_error_m: f64,
}

impl WaypointFigures {
    /// The figures of a run.
    pub fn of(run: &WaypointRun) -> Self {
        let out = &run.out;
        let samples = clock_samples(&out.records, &run.plan, out.platform.dt());
        let s = &out.summary;
        Self {
            nominal_s: run.nominal_s,
            timing: run.plan_timing.clone(),
            executed_s: executed_duration(&out.records),
            clock: slow_clock(&samples, &run.plan_timing.dwells, out.platform.dt()),
            same_plan: out.timing == run.plan.timing(),
            violations: limit_violations(&out.records, &out.platform),
            final_state: s.final_state.clone(),
            max_position_error_m: s.max_position_error_m,
            max_heading_error_rad: s.max_heading_error_rad,
            max_leg_error_m: s.max_leg_error_m,
        }
    }

    /// The bound on the executed duration: 1.25 × (optimal + dwells) (s).
    pub fn duration_bound(&self) -> f64 {
        DURATION_RATIO * (self.timing.optimal_s + self.timing.dwell_s)
    }

    /// The issue's timing bounds on this run: the run ended Stopped; the plan and the run
    /// take at most 1.25 × (optimal + dwells), the run from its first Tracking cycle to its
    /// first Stopped cycle (its controlled stop included); ṡ < 0.05 only inside the planned
    /// dwells (widened by [`DWELL_EDGE_S`]). And the measure's own premise: the core
    /// planned what was measured.
    pub fn misses(&self) -> Vec<String> {
        let mut m = Vec::new();
        if !self.same_plan {
            m.push("the core's timing differs from the plan measured here".into());
        }
        if self.final_state != "stopped" {
            m.push(format!("the run ended {} (not stopped)", self.final_state));
        }
        let bound = self.duration_bound();
        let t = &self.timing;
        let why = format!(
            "1.25 × (optimal {} + dwells {})",
            secs(t.optimal_s),
            secs(t.dwell_s)
        );
        let within = t.planned_s <= bound;
        if !within {
            m.push(format!(
                "planned {} > {} = {why}",
                secs(t.planned_s),
                secs(bound)
            ));
        }
        match self.executed_s {
            Some(e) if e <= bound => {}
            Some(e) => m.push(format!(
                "executed {} (of which {} after the plan's end) > {} = {why}",
                secs(e),
                secs(e - t.planned_s),
                secs(bound)
            )),
            None => m.push("no executed duration (never tracked, or never stopped)".into()),
        }
        if self.clock.outside_s > 0.0 {
            m.push(format!(
                "ṡ < {SLOW_CLOCK} for {} outside the planned dwells (longest {} from {}, min ṡ {:.3e})",
                secs(self.clock.outside_s),
                secs(self.clock.longest_s),
                secs(self.clock.longest_at_s),
                self.clock.min_outside
            ));
        }
        m
    }
}

impl fmt::Display for WaypointFigures {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let t = &self.timing;
        write!(
            f,
            "nominal {}, planned {}, executed {} (stop after the plan's end {}), optimal {} + dwells {} ({} dwells) → bound {}, min ṡ {:.3e} (outside dwells {:.3e}), ṡ < 0.05 outside dwells {} (longest {} from {}), {}, errors {:.2} mm {:.3}° legs {:.2} mm, limit violations: {}",
            secs(self.nominal_s),
            secs(t.planned_s),
            self.executed_s.map_or("never (not stopped)".into(), secs),
            self.executed_s
                .map_or("-".into(), |e| secs(e - t.planned_s)),
            secs(t.optimal_s),
            secs(t.dwell_s),
            t.dwells.len(),
            secs(self.duration_bound()),
            self.clock.min_all,
            self.clock.min_outside,
            secs(self.clock.outside_s),
            secs(self.clock.longest_s),
            secs(self.clock.longest_at_s),
            self.final_state,
            self.max_position_error_m * 1e3,
            self.max_heading_error_rad.to_degrees(),
            self.max_leg_error_m * 1e3,
            violations_text(&self.violations)
        )
    }
}

/// A duration for messages: `1.23 s`, or `1.234e147 s` for a plan that does not end.
pub fn secs(x: f64) -> String {
    if x.abs() < 5e-3 {
        // Rounding about zero, not "-0.00 s".
        "0.00 s".into()
    } else if x.abs() < 1e5 {
        format!("{x:.2} s")
    } else {
        format!("{x:.3e} s")
    }
}

/// Runs `f` (an assertion) and returns its panic message, if it panicked.
pub fn failure_of(f: impl FnOnce()) -> Option<String> {
    std::panic::catch_unwind(std::panic::AssertUnwindSafe(f))
        .err()
        .map(|e| {
            e.downcast_ref::<String>()
                .cloned()
                .or_else(|| e.downcast_ref::<&str>().map(|s| s.to_string()))
                .unwrap_or_else(|| "(panicked)".into())
        })
}

#[cfg(test)]
mod tests {
    use super::*;
    use rollbase_control::types::Command;

    const DT: f64 = 0.004;

    fn rec(k: u64) -> CycleRecord {
        let mut r = CycleRecord::new(k, k as f64 * DT, 4);
        r.state = SupervisorState::Tracking;
        r.mode = "track";
        r
    }

    fn with_truth(mut r: CycleRecord, x: f64, y: f64, th: f64) -> CycleRecord {
        r.truth = Some((
            Pose { x, y, theta: th },
            [0.465; rollbase_control::types::MAX_WHEELS],
        ));
        r
    }

    #[test]
    fn truth_path_length_sums_the_translation_and_ignores_rotation() {
        // An L: 3 records along x (0.3 m), then along y (0.4 m), then a spin in place.
        let pts = [
            (0.0, 0.0, 0.0),
            (0.1, 0.0, 0.0),
            (0.3, 0.0, 0.0),
            (0.3, 0.4, 0.0),
            (0.3, 0.4, 1.0),
            (0.3, 0.4, 2.0),
        ];
        let recs: Vec<_> = pts
            .iter()
            .enumerate()
            .map(|(k, &(x, y, th))| with_truth(rec(k as u64), x, y, th))
            .collect();
        assert!((truth_path_length(&recs) - 0.7).abs() < 1e-12);
        // A back-and-forth counts both ways; a record without truth breaks no pair it is not in.
        let mut recs2 = recs.clone();
        recs2.push(with_truth(rec(6), 0.3, 0.0, 2.0));
        assert!((truth_path_length(&recs2) - 1.1).abs() < 1e-12);
        recs2.push(rec(7));
        recs2.push(with_truth(rec(8), 5.0, 0.0, 2.0));
        assert!((truth_path_length(&recs2) - 1.1).abs() < 1e-12);
        assert_eq!(truth_path_length(&[]), 0.0);
    }

    fn with_steer(k: u64, wheel: usize, rate: f64) -> CycleRecord {
        let mut r = rec(k);
        r.command = Command::zero(4);
        r.measurement.wheels[wheel].steer_rate = rate;
        r
    }

    #[test]
    fn reversals_are_the_wheels_measured_ones_and_the_setpoints_are_counted_apart() {
        // The setpoint dips below −0.2 rad/s at the end of each turn (the lag compensation's
        // φ̈ term) while the measured rate only comes to rest: the wheel never turned back.
        let turn = [0.0, 0.5, 1.0, 0.5, -0.3, 0.0];
        let wheel = [0.0, 0.3, 0.8, 0.7, 0.1, 0.0];
        let recs: Vec<_> = (0..3 * turn.len())
            .map(|k| {
                let mut r = with_steer(k as u64, 1, wheel[k % turn.len()]);
                r.command.wheels[1].steer_rate = turn[k % turn.len()];
                r
            })
            .collect();
        assert_eq!(steering_reversals(&recs, 1), 0);
        assert_eq!(setpoint_reversals(&recs, 1), 5);
    }

    #[test]
    fn steering_reversals_count_sign_changes_beyond_the_threshold_only() {
        let rates = [
            0.0, 0.5, 0.3, 0.1, -0.1, 0.15, // small wiggles around 0 after +: nothing
            -0.3, // reversal 1 (+ → −)
            -0.19, 0.19,    // inside the band: nothing
            -0.25,   // still −: nothing
            0.21,    // reversal 2
            0.2,     // exactly the threshold: not beyond
            -0.2,    // idem
            -0.2001, // reversal 3
        ];
        let recs: Vec<_> = rates
            .iter()
            .enumerate()
            .map(|(k, &r)| with_steer(k as u64, 2, r))
            .collect();
        assert_eq!(steering_reversals(&recs, 2), 3);
        // Other wheels saw nothing.
        assert_eq!(steering_reversals(&recs, 0), 0);
        // Noise below the threshold never counts, however often it changes sign.
        let noise: Vec<_> = (0..100)
            .map(|k| with_steer(k, 1, if k % 2 == 0 { 0.19 } else { -0.19 }))
            .collect();
        assert_eq!(steering_reversals(&noise, 1), 0);
        // A rate that chatters beyond it counts every change.
        let chatter: Vec<_> = (0..10)
            .map(|k| with_steer(k, 1, if k % 2 == 0 { 1.0 } else { -1.0 }))
            .collect();
        assert_eq!(steering_reversals(&chatter, 1), 9);
    }

    #[test]
    fn aligning_standing_counts_cycles_that_align_while_the_truth_stands() {
        // 10 records; x moves 1 mm per 4 ms cycle (0.25 m/s) from record 5 on.
        let mut recs: Vec<_> = (0..10u64)
            .map(|k| {
                let x = if k >= 5 { (k - 4) as f64 * 0.001 } else { 0.0 };
                with_truth(rec(k), x, 0.0, 0.0)
            })
            .collect();
        // Aligning by the supervisor (records 0, 1), by the shaper (2, 6, 7); 3–5 track.
        recs[0].state = SupervisorState::Aligning;
        recs[0].mode = "align";
        recs[1].mode = "align";
        recs[2].shaping.limiting = Limiting::Aligning;
        recs[6].shaping.limiting = Limiting::Aligning;
        recs[7].shaping.limiting = Limiting::Aligning;
        // Standing: 0–4 (record 5 moved since 4). Aligning and standing: 0, 1, 2.
        assert!((aligning_standing_fraction(&recs) - 0.3).abs() < 1e-12);
        // A slow rotation in place counts as moving once |ω|·0.5 m reaches 1 cm/s.
        for (k, r) in recs.iter_mut().enumerate() {
            r.truth = Some((
                Pose {
                    x: 0.0,
                    y: 0.0,
                    theta: k as f64 * 0.021 * DT,
                },
                [0.465; rollbase_control::types::MAX_WHEELS],
            ));
        }
        assert_eq!(aligning_standing_fraction(&recs), 0.0);
        for (k, r) in recs.iter_mut().enumerate() {
            r.truth = Some((
                Pose {
                    x: 0.0,
                    y: 0.0,
                    theta: k as f64 * 0.019 * DT,
                },
                [0.465; rollbase_control::types::MAX_WHEELS],
            ));
        }
        // Aligning: 0, 1, 2, 6, 7 — all standing now.
        assert!((aligning_standing_fraction(&recs) - 0.5).abs() < 1e-12);
        assert_eq!(aligning_standing_fraction(&[]), 0.0);
    }

    #[test]
    fn executed_duration_runs_from_the_first_tracking_to_the_first_stopped_cycle() {
        let states = [
            SupervisorState::Idle,
            SupervisorState::Aligning,
            SupervisorState::Tracking,
            SupervisorState::Tracking,
            SupervisorState::Stopping,
            SupervisorState::Stopping,
            SupervisorState::Stopped,
            SupervisorState::Stopped,
        ];
        let mut recs: Vec<_> = (0..states.len() as u64).map(rec).collect();
        for (r, s) in recs.iter_mut().zip(states) {
            r.state = s;
        }
        let d = executed_duration(&recs).expect("tracked and stopped");
        assert!((d - 4.0 * DT).abs() < 1e-12, "{d}");
        // Never stopped (a plan that does not end), never tracked.
        assert_eq!(executed_duration(&recs[..6]), None);
        assert_eq!(executed_duration(&recs[..2]), None);
        // A Stopped before tracking does not count.
        recs[0].state = SupervisorState::Stopped;
        assert!((executed_duration(&recs).expect("stopped") - 4.0 * DT).abs() < 1e-12);
    }

    #[test]
    fn slow_clock_finds_crawls_outside_the_dwells_only() {
        // 1 s at 4 ms: ṡ = 1, except 0.20–0.30 s (a dwell, ṡ = 0), 0.30–0.35 s (its ramp,
        // ṡ 0.01, inside the widened dwell) and 0.60–0.72 s (a crawl, ṡ 0.02).
        let samples: Vec<(f64, f64)> = (0..250)
            .map(|k| {
                let t = k as f64 * DT;
                let v = if (0.2..0.3).contains(&t) {
                    0.0
                } else if (0.3..0.35).contains(&t) {
                    0.01
                } else if (0.6..0.72).contains(&t) {
                    0.02
                } else {
                    1.0
                };
                (t, v)
            })
            .collect();
        let s = slow_clock(&samples, &[(0.2, 0.3)], DT);
        assert!((s.outside_s - 0.12).abs() < 1.5 * DT, "{s:?}");
        assert!((s.longest_s - 0.12).abs() < 1.5 * DT, "{s:?}");
        assert!((s.longest_at_s - 0.6).abs() < 1.5 * DT, "{s:?}");
        assert_eq!(s.min_outside, 0.02);
        assert_eq!(s.min_all, 0.0);
        assert!((s.inside_s - 0.15).abs() < 1.5 * DT, "{s:?}");
        // Without the dwell, the hold and its ramp crawl too, and make the longest stretch.
        let s = slow_clock(&samples, &[], DT);
        assert!((s.outside_s - 0.27).abs() < 1.5 * DT, "{s:?}");
        assert!((s.longest_s - 0.15).abs() < 1.5 * DT, "{s:?}");
        assert!((s.longest_at_s - 0.2).abs() < 1.5 * DT, "{s:?}");
        // A dwell that covers everything leaves nothing outside.
        let s = slow_clock(&samples, &[(0.0, 1.0)], DT);
        assert_eq!((s.outside_s, s.min_outside), (0.0, 1.0));
    }

    #[test]
    fn clock_samples_follow_the_plan_from_the_first_tracking_cycle() {
        let p = Platform::justin();
        let l = nominal_legs();
        // A fast move: the plan slows it (ṡ < 1 somewhere).
        let specs = [wp(0.0, z(0.0, 0.0, 0.0, l)), wp(0.6, z(1.0, 0.0, 1.0, l))];
        let spline = QuinticSpline::from_specs(&p, &specs).expect("valid");
        let plan = ScaledTrajectory::plan(&p, Box::new(spline), TimeScaleConfig::default())
            .expect("plannable");
        let end = plan.duration();
        assert!(end > 0.6);
        // 3 aligning cycles, tracking to beyond the plan's end, then stopped.
        let n = 3 + (end / DT) as u64 + 10;
        let recs: Vec<_> = (0..n)
            .map(|k| {
                let mut r = rec(k);
                r.state = if k < 3 {
                    SupervisorState::Aligning
                } else {
                    SupervisorState::Tracking
                };
                r
            })
            .collect();
        let s = clock_samples(&recs, &plan, DT);
        assert_eq!(s.len(), (end / DT).ceil() as usize);
        assert_eq!(s[0], (0.0, plan.clock(0.0).1));
        assert_eq!(s[10], (10.0 * DT, plan.clock(10.0 * DT).1));
        assert!(s.iter().all(|&(t, _)| t < end));
        assert!(s.iter().any(|&(_, v)| v < 1.0));
    }

    #[test]
    fn limit_violations_group_failing_pairs_by_hand_over() {
        let p = Platform::justin();
        let l = p.limits;
        let mut recs: Vec<_> = (0..6u64).map(rec).collect();
        // Record 1 jumps from 0 to 6 rad/s of steering (track → track, 1500 rad/s² > 40);
        // record 2 eases it within the limit; track → hold cuts it to 0 in one cycle;
        // hold → decelerate and decelerate → decelerate step a wheel speed by 1 rad/s
        // (250 rad/s² > 40).
        recs[1].command.wheels[0].steer_rate = 6.0;
        recs[2].command.wheels[0].steer_rate = 6.0 - l.steer_accel * DT * 0.5;
        recs[3].mode = "hold";
        recs[4].mode = "decelerate";
        recs[4].command.wheels[1].wheel_speed = 1.0;
        recs[5].mode = "decelerate";
        recs[5].command.wheels[1].wheel_speed = 2.0;
        let v = limit_violations(&recs, &p);
        let kinds: Vec<_> = v.iter().map(|m| (m.from, m.to, m.what, m.count)).collect();
        assert_eq!(
            kinds,
            vec![
                ("track", "track", Limiting::SteerAccel, 1),
                ("track", "hold", Limiting::SteerAccel, 1),
                ("hold", "decelerate", Limiting::WheelAccel, 1),
                ("decelerate", "decelerate", Limiting::WheelAccel, 1),
            ]
        );
        assert_eq!(v[1].worst.1, 3);
        assert!((v[1].worst.0.value.abs() - (6.0 - l.steer_accel * DT * 0.5) / DT).abs() < 1e-9);
        assert!(limit_violations(&recs[2..3], &p).is_empty());
    }

    #[test]
    fn unsteered_path_length_brakes_and_starts_at_the_acceleration_share() {
        let p = Platform::justin();
        let a = 0.6 * p.limits.wheel_accel * p.wheel_radius;
        let v = 0.5;
        let go = motion(
            0.0,
            Twist {
                vx: v,
                ..Twist::default()
            },
        );
        let end = CommandEvent {
            t: 2.0,
            kind: CommandKind::EndOfStream,
        };
        // Straight ahead for 2 s from rest, then a stop: the start loses v²/(2a) against the
        // ideal and the stop adds as much (the trapezoid's two ramps), to within a cycle.
        let got = unsteered_path_length(&[go, end], 5.0, &p, 0.9, 0.6);
        let ideal = ideal_path_length(&[go, end], 5.0);
        assert!((ideal - 2.0 * v).abs() < 1e-12);
        assert!((got - ideal).abs() < v * p.dt(), "{got} against {ideal}");
        // A reversal at t = 1 s: through rest at the acceleration share, so the base loses
        // v²/a (braking and starting again) against the ideal, whose twist jumps.
        let back = motion(
            1.0,
            Twist {
                vx: -v,
                ..Twist::default()
            },
        );
        let got = unsteered_path_length(&[go, back, end], 5.0, &p, 0.9, 0.6);
        let want = 2.0 * v - v * v / a;
        assert!((got - want).abs() < v * p.dt(), "{got} against {want}");
        // A wheel speed beyond the share is capped as a whole.
        let fast = motion(
            0.0,
            Twist {
                vx: 2.0,
                ..Twist::default()
            },
        );
        let vmax = 0.9 * p.limits.wheel_speed * p.wheel_radius;
        let got = unsteered_path_length(&[fast, end], 5.0, &p, 0.9, 0.6);
        let want = 2.0 * vmax;
        assert!((got - want).abs() < vmax * p.dt(), "{got} against {want}");
    }

    #[test]
    fn feasible_path_length_scales_a_twist_beyond_the_wheel_speed_limit_as_a_whole() {
        let p = Platform::justin();
        let vmax = p.limits.wheel_speed * p.wheel_radius;
        let slow = motion(
            0.0,
            Twist {
                vx: 0.5,
                ..Twist::default()
            },
        );
        // Straight ahead at twice the limit: every wheel at 2·vmax, scaled to vmax.
        let fast = motion(
            0.0,
            Twist {
                vx: 2.0 * vmax,
                ..Twist::default()
            },
        );
        let end = CommandEvent {
            t: 1.0,
            kind: CommandKind::EndOfStream,
        };
        assert!((feasible_path_length(&[slow, end], 0.5, &p) - 0.25).abs() < 1e-12);
        assert!((feasible_path_length(&[fast, end], 0.5, &p) - 0.5 * vmax).abs() < 1e-12);
        // A spin with translation: the scale comes from the fastest wheel, and the base's
        // path shrinks by the same factor.
        let spin = motion(
            0.0,
            Twist {
                vx: 0.8,
                vy: 0.0,
                omega: 3.0,
            },
        );
        let ideal = ideal_path_length(&[spin, end], 0.5);
        let feasible = feasible_path_length(&[spin, end], 0.5, &p);
        assert!(feasible < ideal && feasible > 0.0, "{feasible} of {ideal}");
    }

    #[test]
    fn ideal_path_length_holds_each_twist_until_the_next_event_or_the_timeout() {
        let cmds = [
            motion(
                0.0,
                Twist {
                    vx: 0.3,
                    vy: 0.4,
                    omega: 1.0,
                },
            ), // 0.5 m/s
            motion(
                1.0,
                Twist {
                    vx: 0.0,
                    vy: 0.0,
                    omega: 2.0,
                },
            ), // spin: 0 m
            motion(
                2.0,
                Twist {
                    vx: -1.0,
                    vy: 0.0,
                    omega: 0.0,
                },
            ), // 1 m/s until the timeout
            motion(
                4.0,
                Twist {
                    vx: 0.2,
                    vy: 0.0,
                    omega: 0.0,
                },
            ), // held 0.25 s
            CommandEvent {
                t: 4.25,
                kind: CommandKind::EndOfStream,
            },
        ];
        // Timeout 1 s: 0.5 m/s × 1 s, the spin 0 m, 1 m/s × 1 s (not 2 s), 0.2 m/s × 0.25 s.
        assert!((ideal_path_length(&cmds, 1.0) - (0.5 + 1.0 + 0.05)).abs() < 1e-12);
        // Timeout 0.5 s: the first and third are cut to 0.5 s.
        assert!((ideal_path_length(&cmds, 0.5) - (0.25 + 0.5 + 0.05)).abs() < 1e-12);
        // The last motion with nothing after it: held for the timeout.
        assert!((ideal_path_length(&cmds[..4], 1.0) - (0.5 + 1.0 + 0.2)).abs() < 1e-12);
    }

    #[test]
    fn the_joystick_model_is_deterministic_bounded_and_the_same_stick_for_every_sigma() {
        let a = joystick_session(3, 20.0, 0.02);
        assert_eq!(a, joystick_session(3, 20.0, 0.02));
        assert_ne!(a, joystick_session(4, 20.0, 0.02));
        let stick = joystick_stick(3, 20.0);
        assert_eq!(stick.len(), 1000);
        // 50 Hz, the stick inside its disc and its ω range (a lag never overshoots).
        for (k, (t, s)) in stick.iter().enumerate() {
            assert!((t - k as f64 * 0.02).abs() < 1e-12);
            assert!(s.vx.hypot(s.vy) <= STICK_MAX_LINEAR + 1e-12);
            assert!(s.omega.abs() <= STICK_MAX_ANGULAR + 1e-12);
        }
        // Over 20 s the stick reaches beyond half its range in vx, vy and ω.
        let far =
            |f: &dyn Fn(&Twist) -> f64, lim: f64| stick.iter().any(|(_, s)| f(s).abs() > 0.5 * lim);
        assert!(far(&|s| s.vx, STICK_MAX_LINEAR));
        assert!(far(&|s| s.vy, STICK_MAX_LINEAR));
        assert!(far(&|s| s.omega, STICK_MAX_ANGULAR));
        // Its smoothing: no step between messages larger than α × the largest jump.
        let alpha = 1.0 - (-0.02 / STICK_TAU_S).exp();
        for w in stick.windows(2) {
            let dv = (w[1].1.vx - w[0].1.vx).hypot(w[1].1.vy - w[0].1.vy);
            assert!(dv <= alpha * 2.0 * STICK_MAX_LINEAR + 1e-12);
        }
        // σ = 0 is the stick itself; σ > 0 adds noise of about σ (and 2σ on ω).
        let zero = joystick_session(3, 20.0, 0.0);
        let noisy = joystick_session(3, 20.0, 0.05);
        let (mut sx, mut sw) = (0.0, 0.0);
        for ((z, n), (_, s)) in zero.iter().zip(&noisy).zip(&stick) {
            let (CommandKind::Motion(zm), CommandKind::Motion(nm)) = (z.kind, n.kind) else {
                panic!("motion expected");
            };
            assert_eq!(zm.twist, *s);
            sx += (nm.twist.vx - s.vx).powi(2);
            sw += (nm.twist.omega - s.omega).powi(2);
        }
        let (sx, sw) = ((sx / 1000.0).sqrt(), (sw / 1000.0).sqrt());
        assert!((0.045..0.055).contains(&sx), "σ_vx {sx}");
        assert!((0.09..0.11).contains(&sw), "σ_ω {sw}");
        // Then 1 s of exact zeros at 50 Hz and the end of the stream.
        let tail = &noisy[1000..];
        assert_eq!(tail.len(), 51);
        for ev in &tail[..50] {
            assert!(matches!(ev.kind, CommandKind::Motion(m) if m.twist == Twist::default()));
        }
        assert!(matches!(tail[50].kind, CommandKind::EndOfStream));
        assert!((tail[50].t - 21.0).abs() < 1e-9);
        // Let-go periods: the noise-free stick rests near 0 at some time.
        assert!(stick
            .iter()
            .skip(50)
            .any(|(_, s)| s.vx.hypot(s.vy) < 0.05 && s.omega.abs() < 0.1));
    }

    #[test]
    fn curvy_paths_stay_within_3_m_and_the_follower_reaches_their_end() {
        for seed in 0..6 {
            let path = curvy_path(seed);
            assert_eq!(path, curvy_path(seed));
            assert_eq!(path.points[0], [0.0, 0.0]);
            assert!(path.length() > 2.5, "seed {seed}: {} m", path.length());
            // Catmull-Rom stays near its control points' box.
            for p in &path.points {
                assert!(p[0].abs() <= 3.5 && p[1].abs() <= 3.5, "seed {seed}: {p:?}");
            }
            for w in path.points.windows(2) {
                assert!((w[1][0] - w[0][0]).hypot(w[1][1] - w[0][1]) <= 0.03);
            }
            for style in [FollowerStyle::DiffDrive, FollowerStyle::Holonomic] {
                let s = nav2_open_loop(&path, style);
                let reached = s.reached_at.unwrap_or_else(|| {
                    panic!("seed {seed} {style:?}: the ideal follower never reached the goal")
                });
                // 20 Hz, at most 0.5 m/s (and the rotation limit), vy = 0 for diff-drive.
                for (k, c) in s.commands.iter().enumerate() {
                    assert!((c.t - k as f64 / NAV2_HZ).abs() < 1e-9);
                    if let CommandKind::Motion(m) = c.kind {
                        assert!(m.twist.vx.hypot(m.twist.vy) <= NAV2_MAX_SPEED + 1e-9);
                        assert!(m.twist.omega.abs() <= NAV2_MAX_ANGULAR + 1e-9);
                        if style == FollowerStyle::DiffDrive {
                            assert_eq!(m.twist.vy, 0.0);
                        }
                    }
                }
                // Zero twists for ≥ 1 s at the end, then the end of the stream.
                let n = s.commands.len();
                assert!(matches!(s.commands[n - 1].kind, CommandKind::EndOfStream));
                for c in &s.commands[n - 21..n - 1] {
                    assert!(
                        matches!(c.kind, CommandKind::Motion(m) if m.twist == Twist::default())
                    );
                    assert!(c.t >= reached);
                }
                // Slowing to 0 at the goal: the last moving command is slow.
                let last_moving = s.commands[..n - 1]
                    .iter()
                    .rev()
                    .find_map(|c| match c.kind {
                        CommandKind::Motion(m) if m.twist != Twist::default() => Some(m.twist),
                        _ => None,
                    })
                    .expect("it moved");
                assert!(
                    last_moving.vx.hypot(last_moving.vy) <= 0.1 + 1e-9,
                    "{last_moving:?}"
                );
                // The ideal path follows the path: about its length (pure pursuit cuts the
                // corners by up to a lookahead distance, the holonomic style straighter than
                // the diff-drive one; a rotation in place adds nothing).
                let ideal = ideal_path_length(&s.commands, 0.5);
                assert!(
                    ideal > 0.75 * path.length() && ideal < 1.1 * path.length(),
                    "seed {seed} {style:?}: {ideal} m along a {} m path",
                    path.length()
                );
            }
        }
    }

    #[test]
    fn waypoint_classes_are_deterministic_plannable_splines_of_their_kind() {
        let p = Platform::justin();
        for class in WaypointClass::ALL {
            for seed in 0..4 {
                let w = waypoint_class(class, seed);
                assert_eq!(w, waypoint_class(class, seed), "{class:?}");
                QuinticSpline::from_specs(&p, &w)
                    .unwrap_or_else(|e| panic!("{class:?} {seed}: {e}"));
                let last = w.last().expect("waypoints");
                match class {
                    WaypointClass::StopAndGoCorner => {
                        // A stop: b repeated later.
                        assert_eq!(w.len(), 4);
                        assert_eq!(w[1].z, w[2].z);
                        assert!(w[2].t > w[1].t);
                        let turn = |a: &ZVec, b: &ZVec, c: &ZVec| {
                            let d1 = (b[1] - a[1]).atan2(b[0] - a[0]);
                            let d2 = (c[1] - b[1]).atan2(c[0] - b[0]);
                            rollbase_control::angle::diff(d2, d1).abs()
                        };
                        let t = turn(&w[0].z, &w[1].z, &w[3].z);
                        match seed % 3 {
                            0 => assert!((t - FRAC_PI_2).abs() < 1e-9),
                            1 => assert!((t - PI).abs() < 1e-9),
                            _ => {}
                        }
                    }
                    WaypointClass::CircleConstantHeading | WaypointClass::CircleFacingCentre => {
                        let loops = 1 + (seed % 2) as usize;
                        assert_eq!(w.len(), 24 * loops + 1);
                        // Back where it started, all on one circle.
                        assert!((last.z[0]).hypot(last.z[1]) < 1e-9);
                        let facing = class == WaypointClass::CircleFacingCentre;
                        let dth = last.z[2] - w[0].z[2];
                        if facing {
                            assert!((dth.abs() - TAU * loops as f64).abs() < 1e-9);
                        } else {
                            assert_eq!(dth, 0.0);
                        }
                    }
                    WaypointClass::SpinWithLegs => {
                        assert!(w.iter().all(|x| x.z[0] == 0.0 && x.z[1] == 0.0));
                        assert!(w[1].z[2].abs() >= 1.5);
                        assert!((3..7).any(|i| w[1].z[i] != w[0].z[i]));
                    }
                    WaypointClass::Pivot => {
                        // Wheel (seed mod 4)'s contact point stays put.
                        let k = (seed % 4) as usize;
                        let (l, a) = (p.wheels[k].lambda_nominal, p.wheels[k].alpha);
                        for x in &w {
                            let th = x.z[2];
                            let cx = x.z[0] + l * (th + a).cos();
                            let cy = x.z[1] + l * (th + a).sin();
                            assert!((cx - l * a.cos()).abs() < 1e-9);
                            assert!((cy - l * a.sin()).abs() < 1e-9);
                        }
                    }
                    WaypointClass::IcrSweep => {
                        assert!(w.len() >= 13 && last.z[2].abs() > 1.0);
                    }
                    WaypointClass::DenseAtSpeed => {
                        // Every 0.1–0.2 s, at up to 0.9 m/s.
                        for pair in w[..w.len() - 1].windows(2) {
                            let h = pair[1].t.unwrap() - pair[0].t.unwrap();
                            assert!((0.099..=0.201).contains(&h), "{h}");
                        }
                        let fastest = w
                            .windows(2)
                            .map(|q| {
                                (q[1].z[0] - q[0].z[0]).hypot(q[1].z[1] - q[0].z[1])
                                    / (q[1].t.unwrap() - q[0].t.unwrap())
                            })
                            .fold(0.0, f64::max);
                        assert!((0.55..=0.9).contains(&fastest), "{fastest}");
                    }
                    WaypointClass::UntimedMixed => {
                        assert!(last.t.is_none(), "the last waypoint is untimed");
                        if seed % 3 == 0 {
                            assert_eq!(w.len(), 2);
                            assert!(w[0].t.is_none());
                        }
                        if seed % 3 == 1 {
                            assert!(w[..3].iter().all(|x| x.t.is_some()));
                        }
                    }
                }
            }
        }
    }

    #[test]
    fn the_benchmark_tour_has_60_waypoints_some_untimed_and_plans() {
        let p = Platform::justin();
        let w = waypoint_tour(60, 60);
        assert_eq!(w, waypoint_tour(60, 60));
        assert_eq!(w.len(), 60);
        let untimed: Vec<usize> = (0..60).filter(|&k| w[k].t.is_none()).collect();
        assert_eq!(untimed, vec![10, 20, 30, 40, 50]);
        assert!(w[59].t.is_some());
        let len: f64 = w
            .windows(2)
            .map(|q| (q[1].z[0] - q[0].z[0]).hypot(q[1].z[1] - q[0].z[1]))
            .sum();
        assert!((59.0 * 0.2..=59.0 * 0.5).contains(&len), "{len} m");
        assert!(
            w.iter().any(|x| (3..7).any(|i| x.z[i] != w[0].z[i])),
            "legs move"
        );
        QuinticSpline::from_specs(&p, &w).expect("a valid file");
    }

    #[test]
    fn failure_of_returns_the_panic_message() {
        assert_eq!(failure_of(|| {}), None);
        assert_eq!(failure_of(|| panic!("bad {}", 1)).as_deref(), Some("bad 1"));
        assert_eq!(failure_of(|| panic!("static")).as_deref(), Some("static"));
    }
}
