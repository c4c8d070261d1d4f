//! Issue 25's example platforms closed-loop through the full frame path on virtual time,
//! both wire profiles: seed 000's motion (without legs where the platform has none) and a
//! live command session, within 5 mm / 0.5° / 2 mm of the simulator's truth and every limit.
//! The simulator's plant has each platform's geometry: wheels without legs, the caster
//! offset (MPO-700-like, whose ±1.2-turn steering range seed 000's one turn stays inside),
//! mirrored motors (three-wheel).
//!
//! The three-wheel example's ±170° steering stops are taken off ([`endless`]) for the runs
//! that compare it with the other platforms; seed 000's full turn with the stops, where the
//! time scaling stops the platform to unwind each wheel, is the steering-range test
//! ([`unwinds_within_the_steering_range`]). The six-wheel example's two buses are run in
//! tests/tests/e2e_buses.rs.
//!
//! Live sessions: the three-wheel base (endless steering) and the MPO-700-like base, both
//! profiles. The MPO-700-like base's casters take their leading-caster angle from the
//! reference's direction of travel, not from the feedback-corrected command, whose direction
//! swings without bound as the base stops (control/src/tracking/kinematic.rs, point 8);
//! before that its session ended in a wheel-slip fault (15.9 mm native, 18.8 mm CiA 402).

use rollbase_control::runtime::scenario::Scenario;
use rollbase_control::runtime::ControllerKind;
use rollbase_control::{Platform, Protocol};
use rollbase_tests::{
    assert_commands_within_limits, assert_tracking_bounds, five_step_session, run, run_live,
    twist_at, LiveOptions, RunOptions, RunOutcome,
};

fn seed000(p: Platform, profile: Protocol, controller: ControllerKind) -> RunOutcome {
    let mut opts = RunOptions::new(Scenario::Seed000).with_controller(controller);
    if profile == Protocol::Cia402 {
        opts = opts.cia402();
    }
    opts.platform = Some(p);
    run(&opts)
}

fn check_seed000(name: &str, out: &RunOutcome) {
    let s = &out.summary;
    println!("{name}: {}", s.to_json());
    assert_tracking_bounds(s, name);
    assert_eq!(s.rejected_frames, 0, "{name}: a clean bus rejects nothing");
    assert_commands_within_limits(out);
    let last = out.records.last().expect("records");
    assert_eq!(last.mode, "disable", "{name}");
    // The platform reached seed 000's goal (4.5 m, 4.5 m, one turn).
    let (pose, _) = last.truth.expect("truth");
    assert!(
        (pose.x - 4.5).abs() < 0.005 && (pose.y - 4.5).abs() < 0.005,
        "{name}: ends at {pose:?}"
    );
}

fn endless(mut p: Platform) -> Platform {
    for w in &mut p.wheels {
        w.steer_range = None;
    }
    p
}

#[test]
fn three_wheel_fixed_footprint_runs_seed000_native() {
    let out = seed000(
        endless(Platform::three_wheel()),
        Protocol::Native,
        ControllerKind::Dfl,
    );
    check_seed000("three-wheel native", &out);
}

#[test]
fn three_wheel_fixed_footprint_runs_seed000_cia402() {
    let out = seed000(
        endless(Platform::three_wheel()),
        Protocol::Cia402,
        ControllerKind::Dfl,
    );
    check_seed000("three-wheel cia402", &out);
}

#[test]
fn mpo700_off_centred_runs_seed000_native() {
    let out = seed000(
        Platform::mpo700(),
        Protocol::Native,
        ControllerKind::Kinematic,
    );
    check_seed000("mpo700 native", &out);
}

#[test]
fn mpo700_off_centred_runs_seed000_cia402() {
    let out = seed000(
        Platform::mpo700(),
        Protocol::Cia402,
        ControllerKind::Kinematic,
    );
    check_seed000("mpo700 cia402", &out);
}

/// The five-step live session ([`five_step_session`]) with a leg command at 4 s (refused:
/// no legs).
fn live(p: Platform, profile: Protocol, controller: ControllerKind) -> RunOutcome {
    let n = p.n();
    let mut opts = LiveOptions {
        profile,
        max_seconds: 40.0,
        platform: Some(p),
        ..LiveOptions::default()
    };
    opts.runtime.controller = controller;
    let cmds = five_step_session(&[(4.0, &vec![0.3; n])]);
    run_live(&opts, &cmds)
}

fn check_live(name: &str, out: &RunOutcome) {
    let s = &out.summary;
    println!("{name}: {}", s.to_json());
    assert_tracking_bounds(s, name);
    assert_commands_within_limits(out);
    assert_eq!(s.rejected_frames, 0, "{name}: a clean bus rejects nothing");
    assert_eq!(s.rejected_commands, 1, "{name}: the leg command is refused");
    // It moved: the session's distance is several metres.
    let (pose, _) = out.records.last().and_then(|r| r.truth).expect("truth");
    assert!(pose.x.hypot(pose.y) > 0.5, "{name}: ends at {pose:?}");
}

#[test]
fn three_wheel_live_session_native() {
    let out = live(
        endless(Platform::three_wheel()),
        Protocol::Native,
        ControllerKind::Dfl,
    );
    check_live("three-wheel live native", &out);
}

#[test]
fn three_wheel_live_session_cia402() {
    let out = live(
        endless(Platform::three_wheel()),
        Protocol::Cia402,
        ControllerKind::Dfl,
    );
    check_live("three-wheel live cia402", &out);
}

/// The off-centred casters must swing as the base starts in a new direction and roll
/// backwards as leading casters after the reversal at 12 s (kinematic controller, module
/// docs point 8).
#[test]
fn mpo700_live_session_native() {
    let out = live(
        Platform::mpo700(),
        Protocol::Native,
        ControllerKind::Kinematic,
    );
    check_live("mpo700 live native", &out);
}

#[test]
fn mpo700_live_session_cia402() {
    let out = live(
        Platform::mpo700(),
        Protocol::Cia402,
        ControllerKind::Kinematic,
    );
    check_live("mpo700 live cia402", &out);
}

/// Each wheel's steering angle as its own encoder reports it (one turn), followed by
/// continuity from the first full reading (the turn nearest its range's centre), checked
/// inside its range every cycle (one encoder count of slack: the readings are quantised).
/// Returns the last angles and the smallest and largest per wheel.
fn follow_steering(
    out: &RunOutcome,
    ranges: &[rollbase_control::angle::SteerRange],
    name: &str,
) -> (Vec<f64>, Vec<f64>, Vec<f64>) {
    let n = ranges.len();
    let first = out
        .records
        .iter()
        .find(|r| r.feedback_age[..n].iter().all(|&a| a == 0))
        .expect("feedback");
    let mut angle: Vec<f64> = (0..n)
        .map(|i| ranges[i].first(first.measurement.wheels[i].steer_angle))
        .collect();
    let (mut lo, mut hi) = (angle.clone(), angle.clone());
    let slack = 1e-3;
    for r in &out.records {
        for i in 0..n {
            let m = r.measurement.wheels[i].steer_angle;
            angle[i] += rollbase_control::angle::diff(m, angle[i]);
            lo[i] = lo[i].min(angle[i]);
            hi[i] = hi[i].max(angle[i]);
            assert!(
                angle[i] >= ranges[i].min - slack && angle[i] <= ranges[i].max + slack,
                "{name}: wheel {i} steered to {:.2}° at t = {:.3} s, outside its range [{:.1}°, {:.1}°]",
                angle[i].to_degrees(),
                r.t,
                ranges[i].min.to_degrees(),
                ranges[i].max.to_degrees()
            );
        }
    }
    (angle, lo, hi)
}

/// Issue 25's steering-range test: seed 000 turns the platform a full turn while it
/// translates, so every wheel of a fixed footprint steers a full turn relative to the body,
/// past the three-wheel example's ±170° stops. The time scaling stops the platform where a
/// wheel's directions no longer fit inside its range and unwinds it there (the dwell turns it
/// back, the wheel then rolling the other way round). Every cycle, each wheel's steering
/// angle as its own encoder reports it (one turn), followed by continuity from the first
/// reading (the one nearest the range's centre), stays inside its range; the plant's angle
/// at the end agrees with where that following ended. Seed 000's bounds hold as on the
/// endless-steering platform, both profiles.
fn unwinds_within_the_steering_range(profile: Protocol) {
    let p = Platform::three_wheel();
    let ranges: Vec<_> = p
        .wheels
        .iter()
        .map(|w| w.steering_range().expect("the example has steering stops"))
        .collect();
    let n = p.n();
    let out = seed000(p, profile, ControllerKind::Dfl);
    let name = format!("three-wheel ±170° {profile:?}");
    let (angle, lo, hi) = follow_steering(&out, &ranges, &name);
    for (i, (&truth, &a)) in out.final_truth_steer.iter().zip(&angle).enumerate() {
        assert!(
            rollbase_control::angle::diff(truth, a).abs() < 0.01,
            "{profile:?}: wheel {i}: the plant ends at {truth} rad, the followed readings at {a}"
        );
    }
    let sweep: Vec<String> = (0..n)
        .map(|i| format!("[{:.0}°, {:.0}°]", lo[i].to_degrees(), hi[i].to_degrees()))
        .collect();
    let timing = out.timing.expect("time-scaled");
    println!(
        "{profile:?}: steering swept {}; executed {:.2} s (optimal {:.2} s, dwells {:.2} s)",
        sweep.join(" "),
        timing.executed_duration_s,
        timing.optimal_duration_s,
        timing.dwell_s
    );
    // The stops were reached: some wheel swept more than half a turn and the plan dwelt.
    assert!(
        (0..n).any(|i| hi[i] - lo[i] > std::f64::consts::PI) && timing.dwell_s > 0.0,
        "the test does not exercise the stops"
    );
    check_seed000(&name, &out);
}

#[test]
fn three_wheel_unwinds_within_its_steering_range_native() {
    unwinds_within_the_steering_range(Protocol::Native);
}

#[test]
fn three_wheel_unwinds_within_its_steering_range_cia402() {
    unwinds_within_the_steering_range(Protocol::Cia402);
}

/// The steering-range test for live commands: a 20 Hz stream at 0.3 m/s (no rotation) whose
/// direction of travel turns 540° in 18 s — in 45° steps every 1.5 s, or `continuous`ly at
/// 0.52 rad/s — so every wheel of the three-wheel example would have to steer 1.5 turns,
/// past its ±170° stops. The shaper stops the base before a wheel would come within
/// [`RANGE_MARGIN`] of a stop and turns it back within its range (to the other branch: it
/// then rolls backwards), then drives on. Every cycle each wheel's steering angle (its
/// encoder, followed by continuity) stays inside its range, every command pair within the
/// limits, the tracking within the bounds, and the base still travels most of the commanded
/// path. The continuous stream moves the wheels' aim while they unwind (11.4 mm when they
/// turned at 90 % of their rate limit: shaper module docs, "Steering ranges").
///
/// [`RANGE_MARGIN`]: rollbase_control::reference::shaper::RANGE_MARGIN
fn live_unwinds_within_the_steering_range(profile: Protocol, continuous: bool) {
    use rollbase_control::service::ports::{CommandEvent, CommandKind};
    let p = Platform::three_wheel();
    let ranges: Vec<_> = p
        .wheels
        .iter()
        .map(|w| w.steering_range().unwrap())
        .collect();
    let n = p.n();
    let opts = LiveOptions {
        profile,
        max_seconds: 40.0,
        platform: Some(p),
        ..LiveOptions::default()
    };
    // The direction steps on by 45° every 1.5 s, 12 steps (540°), or turns continuously at
    // the same mean rate (0.52 rad/s), so that the aim moves while the wheels unwind.
    let (speed, step, hold, steps) = (0.3, std::f64::consts::FRAC_PI_4, 1.5, 12);
    let secs = hold * steps as f64;
    let mut cmds = Vec::new();
    let mut t = 0.0;
    while t < secs {
        let b = if continuous {
            step * t / hold
        } else {
            step * (t / hold).floor()
        };
        cmds.push(twist_at(t, speed * b.cos(), speed * b.sin(), 0.0));
        t += 0.05;
    }
    for k in 0..5 {
        cmds.push(twist_at(secs + 0.3 * f64::from(k), 0.0, 0.0, 0.0));
    }
    cmds.push(CommandEvent {
        t: secs + 3.0,
        kind: CommandKind::EndOfStream,
    });
    let out = run_live(&opts, &cmds);
    let s = &out.summary;
    let name = format!(
        "three-wheel ±170° live {profile:?}{}",
        if continuous { ", continuous" } else { "" }
    );
    println!("{name}: {}", s.to_json());
    let (_, lo, hi) = follow_steering(&out, &ranges, &name);
    let mut dist = 0.0;
    for w in out.records.windows(2) {
        if let (Some((a, _)), Some((b, _))) = (w[0].truth, w[1].truth) {
            dist += (b.x - a.x).hypot(b.y - a.y);
        }
    }
    let sweep: Vec<String> = (0..n)
        .map(|i| format!("[{:.0}°, {:.0}°]", lo[i].to_degrees(), hi[i].to_degrees()))
        .collect();
    println!(
        "{name}: steering swept {}; travelled {dist:.2} m of {:.2} m commanded",
        sweep.join(" "),
        speed * secs
    );
    // The direction of travel turned 540°, more than any range spans (340°): every wheel
    // was turned back to the other branch on the way, rolling forwards (> 1 rad/s) at some
    // times and backwards at others.
    for i in 0..n {
        let speeds = out
            .records
            .iter()
            .map(|r| r.measurement.wheels[i].wheel_speed);
        let (fwd, back) = speeds.fold((false, false), |(f, b), w| (f || w > 1.0, b || w < -1.0));
        assert!(
            fwd && back,
            "{name}: wheel {i} never changed branch: the test does not exercise the stops"
        );
    }
    assert_eq!(s.final_state, "stopped", "{name}: {:?}", s.fault_reason);
    assert_tracking_bounds(s, &name);
    assert_commands_within_limits(&out);
    assert!(dist > 0.6 * speed * secs, "{name}: travelled only {dist} m");
}

#[test]
fn three_wheel_live_unwinds_within_its_steering_range_native() {
    live_unwinds_within_the_steering_range(Protocol::Native, false);
}

#[test]
fn three_wheel_live_unwinds_within_its_steering_range_cia402() {
    live_unwinds_within_the_steering_range(Protocol::Cia402, false);
}

#[test]
fn three_wheel_live_unwinds_a_continuous_turn_within_its_steering_range_native() {
    live_unwinds_within_the_steering_range(Protocol::Native, true);
}

#[test]
fn three_wheel_live_unwinds_a_continuous_turn_within_its_steering_range_cia402() {
    live_unwinds_within_the_steering_range(Protocol::Cia402, true);
}
