//! The base service through the full frame path in lockstep (encode → virtual bus →
//! simulated wheel modules and plant → bus → decode): live commands, the shaper, the command
//! port and the state port. Errors are the simulator's truth against the shaped reference.

use rollbase_control::runtime::record::CycleRecord;
use rollbase_control::service::ports::{CommandEvent, CommandKind, LegTargets, MotionCommand};
use rollbase_control::supervisor::SupervisorState;
use rollbase_control::types::Twist;
use rollbase_tests::*;

fn ev(t: f64, kind: CommandKind) -> CommandEvent {
    CommandEvent { t, kind }
}

fn motion(t: f64, vx: f64, vy: f64, omega: f64, legs: Option<[f64; 4]>) -> CommandEvent {
    ev(
        t,
        CommandKind::Motion(MotionCommand {
            twist: Twist { vx, vy, omega },
            legs: legs.map(|l| LegTargets::from_slice(&l)),
        }),
    )
}

/// Holds each command for `hold` seconds, repeated every 0.4 s (within the 0.5 s timeout),
/// then a zero twist until the platform rests, then the end of the stream.
fn schedule(steps: &[(f64, f64, f64, Option<[f64; 4]>)], hold: f64) -> Vec<CommandEvent> {
    let mut cmds = Vec::new();
    let mut t = 0.0;
    for &(vx, vy, om, legs) in steps {
        let mut k = 0.0;
        while k < hold - 1e-9 {
            cmds.push(motion(t + k, vx, vy, om, legs));
            k += 0.4;
        }
        t += hold;
    }
    for k in 0..5 {
        cmds.push(motion(t + 0.4 * k as f64, 0.0, 0.0, 0.0, None));
    }
    cmds.push(ev(t + 2.0, CommandKind::EndOfStream));
    cmds
}

/// The tracking bounds, against the shaped reference.
fn assert_tracking_bounds(out: &RunOutcome) {
    rollbase_tests::assert_tracking_bounds(&out.summary, &out.summary.scenario);
}

#[test]
fn commands_far_beyond_every_limit_are_shaped_within_them() {
    far_beyond_every_limit(&LiveOptions::default());
}

/// 3 m/s, 5 rad/s, instant reversals, legs end to end: every command within its limits,
/// the errors within the bounds, the executed direction within 2°.
fn far_beyond_every_limit(o: &LiveOptions) {
    // 3 m/s, 5 rad/s, instant reversals, legs from one end of their range to the other.
    let lo = [0.37; 4];
    let hi = [0.56; 4];
    let steps = [
        (3.0, 0.0, 0.0, Some(hi)),
        (-3.0, 0.0, 0.0, None),
        (0.0, 3.0, 5.0, Some(lo)),
        (0.0, -3.0, -5.0, None),
        (2.0, 2.0, -5.0, Some(hi)),
        (-2.0, 1.0, 0.0, Some(lo)),
        (3.0, -3.0, 5.0, None),
        (-3.0, 3.0, -5.0, Some([0.56, 0.37, 0.56, 0.37])),
    ];
    let out = run_live(o, &schedule(&steps, 3.0));
    let s = &out.summary;
    eprintln!("{}", s.to_json());
    assert_commands_within_limits(&out);
    let p = &out.platform;
    assert!(s.max_wheel_speed_rad_s <= p.limits.wheel_speed + 1e-9);
    assert!(s.max_wheel_accel_rad_s2 <= p.limits.wheel_accel * (1.0 + 1e-9));
    assert!(s.max_steer_accel_rad_s2 <= p.limits.steer_accel * (1.0 + 1e-9));
    assert_tracking_bounds(&out);
    assert!(
        s.max_direction_error_rad < 2f64.to_radians(),
        "direction error {}°",
        s.max_direction_error_rad.to_degrees()
    );
    // Legs went from one end to the other (and back) and never beyond.
    let legs = |r: &CycleRecord| r.truth.expect("truth").1;
    let max = out.records.iter().map(|r| legs(r)[0]).fold(0.0, f64::max);
    let min = out.records.iter().map(|r| legs(r)[0]).fold(1.0, f64::min);
    assert!(max > 0.555 && min < 0.375, "legs travelled {min}..{max}");
    // It really was slowed down: the fastest wheel ran at its limit's shaped share.
    assert!(s.max_wheel_speed_rad_s > 0.85 * p.limits.wheel_speed);
}

/// Steering chatter of a wheel ([`steering_chatter`]).
fn chatter(out: &RunOutcome, wheel: usize) -> usize {
    steering_chatter(&out.records, out.platform.wheel_radius, wheel)
}

/// Largest change of a wheel's measured steering angle while its commanded rolling speed is
/// below 1 cm/s ([`steering_turn_while_slow`]; a flip would be about π).
fn turn_while_slow(out: &RunOutcome, wheel: usize) -> f64 {
    steering_turn_while_slow(&out.records, out.platform.wheel_radius, wheel)
}

/// [`turn_while_slow`] from the first cycle the wheel's commanded rolling speed exceeds
/// 2 cm/s on: the alignment before the first roll (align-first, from rest) does not count,
/// a flip or a turn at a later stop or reversal does.
fn turn_while_slow_once_rolling(out: &RunOutcome, wheel: usize) -> f64 {
    let r = out.platform.wheel_radius;
    let first = out
        .records
        .iter()
        .position(|rec| (rec.command.wheels[wheel].wheel_speed * r).abs() > 0.02)
        .unwrap_or(out.records.len());
    steering_turn_while_slow(&out.records[first..], r, wheel)
}

/// A run that ends stopped within the tracking bounds and the limits, in which `wheel`
/// neither chatters nor turns by 2° or more while slow once it has rolled (`what` names it).
fn assert_held_wheel(out: &RunOutcome, wheel: usize, what: &str) {
    eprintln!("{what}: {}", out.summary.to_json());
    assert_commands_within_limits(out);
    assert_tracking_bounds(out);
    assert_eq!(chatter(out, wheel), 0, "{what} chatters");
    let turn = turn_while_slow_once_rolling(out, wheel);
    assert!(
        turn < 2f64.to_radians(),
        "{what} turned {:.2}° while slow",
        turn.to_degrees()
    );
}

fn pivot_about(wheel: usize, omega: f64) -> (f64, f64, f64) {
    let p = rollbase_control::Platform::justin();
    let a = p.wheels[wheel].alpha;
    let l = p.wheels[wheel].lambda_nominal;
    let (px, py) = (l * a.cos(), l * a.sin());
    // v + ω × P = 0: the contact point of `wheel` stays still.
    (omega * py, -omega * px, omega)
}

#[test]
fn a_pivot_about_a_wheel_holds_that_wheel_without_chatter() {
    let (vx, vy, om) = pivot_about(1, 0.6);
    let steps = [
        (vx, vy, om, None),
        (-vx, -vy, -om, None),
        (vx, vy, om, None),
    ];
    let out = run_live(&LiveOptions::default(), &schedule(&steps, 4.0));
    eprintln!("{}", out.summary.to_json());
    assert_commands_within_limits(&out);
    assert_tracking_bounds(&out);
    let c = chatter(&out, 1);
    let turn = turn_while_slow(&out, 1);
    eprintln!(
        "pivot wheel: {c} reversals, largest turn while slow {:.3}°",
        turn.to_degrees()
    );
    assert_eq!(c, 0, "wheel 2 chatters: {c} steering reversals while still");
    assert!(
        turn < 2f64.to_radians(),
        "wheel 2 turned {:.2}° while still",
        turn.to_degrees()
    );
    // The platform did rotate about it.
    let rot = out
        .records
        .iter()
        .map(|r| r.reference.dz[2].abs())
        .fold(0.0, f64::max);
    assert!(rot > 0.5);
}

/// The ICR moves along a line through wheel 0's contact point, from 30 cm before it to 30 cm
/// beyond, over 6 s; commands every 40 ms (a joystick moved slowly); then a stop.
fn sweep_commands() -> Vec<CommandEvent> {
    sweep_commands_beside(0.0)
}

/// [`sweep_commands`] along a line `offset` metres beside wheel 0's contact point (positive:
/// toward +y of the base frame; 0: through it).
fn sweep_commands_beside(offset: f64) -> Vec<CommandEvent> {
    let p = rollbase_control::Platform::justin();
    let a = p.wheels[0].alpha;
    let l = p.wheels[0].lambda_nominal;
    let (px, py) = (l * a.cos(), l * a.sin());
    let om = 0.4;
    let mut cmds = Vec::new();
    let n = 150;
    for k in 0..=n {
        let f = k as f64 / n as f64;
        // ICR c = P + (f − 0.5)·0.6·(1, 0); twist with that ICR: v = −ω × c = (ω c_y, −ω c_x).
        let (cx, cy) = (px + (f - 0.5) * 0.6, py + offset);
        cmds.push(motion(0.04 * k as f64, om * cy, -om * cx, om, None));
    }
    let t = 0.04 * n as f64;
    for k in 1..=5 {
        cmds.push(motion(t + 0.4 * k as f64, 0.0, 0.0, 0.0, None));
    }
    cmds.push(ev(t + 2.4, CommandKind::EndOfStream));
    cmds
}

#[test]
fn an_icr_sweeping_across_a_wheel_does_not_make_it_chatter() {
    // The ICR moves along a line through wheel 0's contact point, from 30 cm before it to 30
    // cm beyond, over 6 s; commands every 40 ms (a joystick moved slowly).
    let out = run_live(&LiveOptions::default(), &sweep_commands());
    eprintln!("{}", out.summary.to_json());
    assert_commands_within_limits(&out);
    assert_tracking_bounds(&out);
    let c = chatter(&out, 0);
    eprintln!("swept wheel: {c} reversals");
    assert_eq!(c, 0, "wheel 1 chatters: {c} steering reversals while slow");
    // The ICR came close and went across: wheel 1's direction of travel turned around.
    assert!(
        out.summary.min_icr_wheel_distance_m < 0.1,
        "the ICR came close to the wheel"
    );
    // From the end of the start from rest on (a start rolls along the wheels while they turn,
    // so its own turn is not the sweep's).
    let aligning = |r: &CycleRecord| {
        r.shaping.limiting == rollbase_control::service::ports::Limiting::Aligning
            || r.mode == "align"
    };
    let first = out.records.iter().position(aligning).unwrap_or(0);
    let after = out.records[first..]
        .iter()
        .position(|r| !aligning(r))
        .map_or(out.records.len(), |k| first + k);
    let moving: Vec<_> = out.records[after..]
        .iter()
        .filter(|r| (r.command.wheels[0].wheel_speed * out.platform.wheel_radius).abs() > 0.02)
        .collect();
    // Its direction of travel in the reference turned around (π: the same line through the
    // wheel). The wheel itself need not turn: its roll reverses where its velocity passes
    // through zero on a line.
    let dir = |r: &CycleRecord| {
        rollbase_control::reference::limits::wheel_demand(&out.platform, 0, &r.reference)
            .steer_angle
    };
    let turned = rollbase_control::angle::diff(
        dir(moving.last().expect("moving")),
        dir(moving.first().expect("moving")),
    )
    .abs();
    assert!(
        turned > 2.5,
        "wheel 1's direction of travel turned only {turned} rad: the ICR did not cross it"
    );
}

/// [`chatter`] from the first cycle the wheel's commanded rolling speed exceeds 2 cm/s on (as
/// [`turn_while_slow_once_rolling`]): the alignment from rest before the first roll does not
/// count, a reversal at a later slow passage does.
fn chatter_once_rolling(out: &RunOutcome, wheel: usize) -> usize {
    let r = out.platform.wheel_radius;
    let first = out
        .records
        .iter()
        .position(|rec| (rec.command.wheels[wheel].wheel_speed * r).abs() > 0.02)
        .unwrap_or(out.records.len());
    // The stretches where the shaper stopped the platform to re-align its wheels (align-first
    // in the middle of the run, module docs of rollbase_control::reference::shaper, "Transitions") are a
    // deliberate re-steer at rest, like the alignment from rest at the start: counted apart.
    let mut count = 0;
    for part in out.records[first..]
        .split(|rec| rec.shaping.limiting == rollbase_control::service::ports::Limiting::Aligning)
    {
        count += steering_chatter(part, r, wheel);
    }
    count
}

/// The ICR sweeps along lines passing 1, 3 and 8 cm beside wheel 0 on either side (and
/// through it), 30 cm before to 30 cm beyond, over 6 s. Beside the wheel, its direction of
/// travel turns by nearly a half-turn in one sense, fastest as the ICR passes, while it rolls
/// slowly (|ω|·distance): the shaper slows the transitions there, stops and re-aligns where
/// a new command would turn the wheel too far (or where stopping and re-aligning is quicker
/// than crawling round). Once rolling, the wheel turns without reversal while slow (apart
/// from such a re-alignment at rest, which is counted apart); every command is within its limits, the errors within the issue's
/// bounds, the run ends stopped, and the wheel did turn around.
///
/// Not asserted: the alignment from rest at the start, with the ICR still 30 cm from the
/// wheel. The command's direction already turns (against the alignment's sense for offsets
/// on the +y side) while the wheels align to it, so the reference aligns back by 0.5° to
/// 3.5° before the first roll and the measure counts one reversal there (printed as "from
/// rest").
#[test]
fn an_icr_sweeping_beside_a_wheel_turns_it_without_reversal_once_rolling() {
    let mut failures = Vec::new();
    for offset in [0.0, 0.01, -0.01, 0.03, -0.03, 0.08, -0.08] {
        let out = run_live(&LiveOptions::default(), &sweep_commands_beside(offset));
        let s = &out.summary;
        let c = chatter_once_rolling(&out, 0);
        eprintln!(
            "offset {:+.0} mm: {c} reversals once rolling ({} from rest), turn while slow \
             once rolling {:.1}°, errors {:.3} mm {:.4}°, min ICR distance {:.4} m",
            offset * 1e3,
            chatter(&out, 0),
            turn_while_slow_once_rolling(&out, 0).to_degrees(),
            s.max_position_error_m * 1e3,
            s.max_heading_error_rad.to_degrees(),
            s.min_icr_wheel_distance_m
        );
        assert_commands_within_limits(&out);
        assert_tracking_bounds(&out);
        assert!(
            s.min_icr_wheel_distance_m < offset.abs() + 0.1,
            "offset {offset}: the ICR came within {} m of the wheel",
            s.min_icr_wheel_distance_m
        );
        let moving: Vec<_> = out
            .records
            .iter()
            .filter(|r| (r.command.wheels[0].wheel_speed * out.platform.wheel_radius).abs() > 0.02)
            .collect();
        // The ICR went past: the wheel's direction of travel in the reference turned.
        let dir = |r: &CycleRecord| {
            rollbase_control::reference::limits::wheel_demand(&out.platform, 0, &r.reference)
                .steer_angle
        };
        let turned = rollbase_control::angle::diff(
            dir(moving.last().expect("moving")),
            dir(moving.first().expect("moving")),
        )
        .abs();
        assert!(
            turned > 0.5,
            "offset {offset}: the wheel's direction of travel turned only {turned} rad"
        );
        if c != 0 {
            failures.push((offset, c));
        }
    }
    assert!(
        failures.is_empty(),
        "the swept wheel reverses its steering while slow (offset m, reversals): {failures:?}"
    );
}

#[test]
fn the_timeout_stops_within_the_deceleration_limit_and_the_next_command_resumes() {
    let mut cmds = Vec::new();
    for k in 0..10 {
        cmds.push(motion(0.4 * k as f64, 0.8, 0.3, 0.5, None));
    }
    // Last command at 3.6 s; the timeout (0.5 s) expires at 4.1 s. Resume at 8 s.
    for k in 0..5 {
        cmds.push(motion(8.0 + 0.4 * k as f64, -0.5, 0.0, 0.0, None));
    }
    for k in 0..5 {
        cmds.push(motion(10.0 + 0.4 * k as f64, 0.0, 0.0, 0.0, None));
    }
    cmds.push(ev(12.0, CommandKind::EndOfStream));
    let out = run_live(&LiveOptions::default(), &cmds);
    let s = &out.summary;
    eprintln!("{}", s.to_json());
    assert_commands_within_limits(&out);
    assert_eq!(s.command_timeouts, 1);
    assert_eq!(s.final_state, "stopped");
    // Find the timeout: the first cycle whose shaping says Timeout.
    let recs = &out.records;
    let k0 = recs
        .iter()
        .position(|r| r.shaping.limiting == rollbase_control::service::ports::Limiting::Timeout)
        .expect("a timeout");
    let before = &recs[k0 - 1];
    let p = &out.platform;
    let wmax = before.command.wheels[..4]
        .iter()
        .map(|w| w.wheel_speed.abs())
        .fold(0.0, f64::max);
    let allowed = wmax / p.limits.wheel_accel + 2.0 * p.dt();
    let k1 = recs[k0..]
        .iter()
        .position(|r| {
            r.command.wheels[..4]
                .iter()
                .all(|w| w.wheel_speed.abs() <= 0.02)
        })
        .expect("at rest")
        + k0;
    let took = (recs[k1].t - before.t).max(0.0);
    eprintln!("stop from {wmax:.2} rad/s took {took:.3} s, allowed {allowed:.3} s");
    assert!(
        took <= allowed + 1e-9,
        "stop took {took} s, allowed {allowed} s"
    );
    // Steering held from the timeout to rest: the reference's angles do not move and the
    // commanded steering rates are the feedback's small corrections only.
    for r in &recs[k0..=k1] {
        for i in 0..4 {
            assert!(
                rollbase_control::angle::diff(
                    r.reference.steer.angle[i],
                    before.reference.steer.angle[i]
                )
                .abs()
                    < 1e-9,
                "steering reference moved during the stop"
            );
            assert!(
                r.command.wheels[i].steer_rate.abs() < 0.1,
                "wheel {i} steering {}",
                r.command.wheels[i].steer_rate
            );
        }
    }
    // It stays at rest until the next command, then moves again without re-arming.
    let body_vx = |r: &CycleRecord| {
        let (s, c) = r.reference.z[2].sin_cos();
        c * r.reference.dz[0] + s * r.reference.dz[1]
    };
    let t_resume = recs
        .iter()
        .position(|r| body_vx(r) < -0.1)
        .expect("resumed");
    assert!(recs[t_resume].t > 7.9);
    assert!(recs[k1..t_resume]
        .iter()
        .all(|r| r.state == SupervisorState::Tracking));
}

#[test]
fn nan_inf_and_absurd_commands_are_rejected_counted_and_change_nothing() {
    let good: Vec<CommandEvent> = {
        let mut c = Vec::new();
        for k in 0..10 {
            c.push(motion(
                0.4 * k as f64,
                0.5,
                -0.2,
                0.3,
                Some([0.4, 0.45, 0.5, 0.55]),
            ));
        }
        for k in 10..15 {
            c.push(motion(0.4 * k as f64, 0.0, 0.0, 0.0, None));
        }
        c.push(ev(6.4, CommandKind::EndOfStream));
        c
    };
    let bad_kinds = [
        motion(0.0, f64::NAN, 0.0, 0.0, None),
        motion(0.0, 0.0, f64::INFINITY, 0.0, None),
        motion(0.0, 0.0, 0.0, f64::NEG_INFINITY, None),
        motion(0.0, 1e3, 0.0, 0.0, None),
        motion(0.0, 0.0, 0.0, -250.0, None),
        motion(0.0, 0.1, 0.0, 0.0, Some([0.4, 0.4, 0.4, f64::NAN])),
        motion(0.0, 0.1, 0.0, 0.0, Some([0.4, 0.9, 0.4, 0.4])),
        ev(0.0, CommandKind::Legs(LegTargets::from_slice(&[0.4, 0.4]))),
    ];
    let mut mixed = Vec::new();
    for (j, c) in good.iter().enumerate() {
        mixed.push(*c);
        if j < 12 {
            let mut b = bad_kinds[j % bad_kinds.len()];
            b.t = c.t + 0.1;
            mixed.push(b);
        }
    }
    mixed.sort_by(|a, b| a.t.total_cmp(&b.t));
    let clean = run_live(&LiveOptions::default(), &good);
    let dirty = run_live(&LiveOptions::default(), &mixed);
    assert_eq!(dirty.summary.rejected_commands, 12);
    assert_eq!(clean.summary.rejected_commands, 0);
    assert_eq!(clean.records.len(), dirty.records.len());
    for (a, b) in clean.records.iter().zip(&dirty.records) {
        assert_eq!(
            a.command, b.command,
            "cycle {}: a rejected command reached the wheels",
            a.cycle
        );
        assert_eq!(a.reference, b.reference);
    }
    assert_eq!(dirty.summary.final_state, "stopped");
}

#[test]
fn odometry_over_a_random_60_s_session_stays_within_its_reported_uncertainty() {
    // Random commands (seeded): a new twist every 1.5–3 s, repeated every 0.4 s, now and then
    // new leg targets; 60 s in all, then a stop.
    let mut rng = rollbase_driver::rng::Rng::new(7);
    let mut u = |lo: f64, hi: f64| lo + (hi - lo) * rng.next_f64();
    let mut cmds = Vec::new();
    let mut t = 0.0;
    while t < 60.0 {
        let hold = u(1.5, 3.0);
        let (vx, vy, om) = (u(-0.9, 0.9), u(-0.9, 0.9), u(-1.0, 1.0));
        let legs = (u(0.0, 1.0) < 0.3)
            .then(|| [u(0.37, 0.56), u(0.37, 0.56), u(0.37, 0.56), u(0.37, 0.56)]);
        let mut k = 0.0;
        while k < hold {
            cmds.push(motion(
                t + k,
                vx,
                vy,
                om,
                if k == 0.0 { legs } else { None },
            ));
            k += 0.4;
        }
        t += hold;
    }
    for k in 0..5 {
        cmds.push(motion(t + 0.4 * k as f64, 0.0, 0.0, 0.0, None));
    }
    cmds.push(ev(t + 2.0, CommandKind::EndOfStream));
    let out = run_live(&LiveOptions::default(), &cmds);
    eprintln!("{}", out.summary.to_json());
    assert_eq!(
        out.summary.final_state, "stopped",
        "{:?}",
        out.summary.fault_reason
    );
    let mut dist = 0.0;
    for w in out.records.windows(2) {
        let (a, _) = w[0].truth.unwrap();
        let (b, _) = w[1].truth.unwrap();
        dist += (b.x - a.x).hypot(b.y - a.y);
    }
    let last = out.records.last().unwrap();
    let (truth, _) = last.truth.unwrap();
    let est = out.final_state.expect("state").odometry;
    let (ex, ey) = (est.pose.x - truth.x, est.pose.y - truth.y);
    let eth = est.pose.theta - truth.theta;
    let cov = est.pose_covariance;
    let (sx, sy, sth) = (cov[0][0].sqrt(), cov[1][1].sqrt(), cov[2][2].sqrt());
    eprintln!(
        "distance {dist:.2} m; final error ({:.2}, {:.2}) mm, {:.4}°; 3σ ({:.2}, {:.2}) mm, {:.4}°",
        ex * 1e3,
        ey * 1e3,
        eth.to_degrees(),
        3e3 * sx,
        3e3 * sy,
        3.0 * sth.to_degrees()
    );
    assert!(dist > 20.0, "the session drove {dist} m");
    assert!(
        ex.hypot(ey) < 0.005 * dist,
        "final position error {} m over {dist} m",
        ex.hypot(ey)
    );
    assert!(
        eth.abs() < 0.5f64.to_radians(),
        "final heading error {}°",
        eth.to_degrees()
    );
    assert!(
        ex.abs() <= 3.0 * sx && ey.abs() <= 3.0 * sy && eth.abs() <= 3.0 * sth,
        "true error outside the reported 3σ"
    );
    // The covariance is a covariance: symmetric, positive diagonal.
    for i in 0..3 {
        assert!(cov[i][i] > 0.0);
        for j in 0..3 {
            assert!((cov[i][j] - cov[j][i]).abs() <= 1e-12 * cov[i][i].max(cov[j][j]));
        }
    }
}

/// Seed 001's avoidance on live commands (legs locked, as with live leg commands, and legs
/// free), for the pivot and the sweep above and the commands far beyond every limit. The
/// avoidance acts on the command before the shaper (`rollbase_control::reference::avoidance`, "Live
/// commands"), so the reference the controller follows is shaped as any other: every command
/// sent within its limits, the errors against that reference within the bounds, the
/// wheel the ICR rests on or crosses neither chatters nor flips, the run ends stopped.
///
/// What it does not keep, and why `drive` runs with avoidance off by default: a deliberate
/// pivot about a wheel is not executed as commanded. The avoidance wins: the platform turns
/// about a point on the field's edge, d_start = 0.3 λ = 0.14 m beyond the wheel, at the
/// commanded speed of the base (so more slowly), and that wheel rolls.
#[test]
fn with_avoidance_on_the_pivot_and_the_sweep_do_not_chatter_and_stay_within_the_limits() {
    let p = rollbase_control::Platform::justin();
    let cfg = rollbase_control::reference::avoidance::AvoidanceConfig::default();
    let d_start =
        rollbase_control::reference::avoidance::field_radius(&cfg, p.wheels[1].lambda_nominal);
    for mode in ["locked", "on"] {
        let mut o = LiveOptions::default();
        o.runtime.avoidance = rollbase_control::runtime::scenario::avoidance_mode(mode).unwrap();
        let (vx, vy, om) = pivot_about(1, 0.6);
        let steps = [
            (vx, vy, om, None),
            (-vx, -vy, -om, None),
            (vx, vy, om, None),
        ];
        let out = run_live(&o, &schedule(&steps, 4.0));
        assert_held_wheel(&out, 1, &format!("avoidance {mode}, the pivot wheel"));
        assert!(
            out.records.iter().any(|r| r.avoidance.active),
            "avoidance {mode}: the field of the pivot wheel was entered"
        );
        // The command's ICR rests on wheel 2; the reference's never came closer to any wheel
        // than the field's edge, and the platform turned (about that point).
        let dmin = out.summary.min_icr_wheel_distance_m;
        assert!(
            dmin > 0.99 * d_start && dmin < 1.01 * d_start,
            "avoidance {mode}: ICR {dmin} m from a wheel, field radius {d_start} m"
        );
        let rot = out
            .records
            .iter()
            .map(|r| r.reference.dz[2].abs())
            .fold(0.0, f64::max);
        assert!(rot > 0.4, "avoidance {mode}: turned at {rot} rad/s");

        let out = run_live(&o, &sweep_commands());
        assert_held_wheel(&out, 0, &format!("avoidance {mode}, the swept wheel"));
        assert!(out.records.iter().any(|r| r.avoidance.active));

        far_beyond_every_limit(&o);
    }
}
