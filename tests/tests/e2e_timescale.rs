//! Time scaling of pre-planned trajectories (issue 18) through the full frame path in
//! lockstep: encode → virtual bus → simulated modules and plant with the simulator's
//! defaults (noise, motor lag, encoder latency) → decode. Errors are the simulator's truth
//! against the executed (scaled) reference; every command sent is within its speed and
//! acceleration limits ([`rollbase_control::reference::limits::check_command`]) on every cycle.

use rollbase_control::reference::status::Timing;
use rollbase_control::reference::trajectory::{QuinticSpline, Trajectory, WaypointSpec};
use rollbase_control::runtime::record::CycleRecord;
use rollbase_control::runtime::scenario::Scenario;
use rollbase_control::runtime::{
    run_lockstep, CycleCore, RunSummary, RuntimeConfig, VirtualLockstepBus,
};
use rollbase_control::Platform;
use rollbase_driver::fault::FaultModel;
use rollbase_tests::flow::{icr_sweep, pivot, wp, z};
use rollbase_tests::{assert_tracking_bounds, steering_chatter, steering_turn_while_slow};
use rollbase_vcan_sim::{InitialState, SimConfig, Simulator};

/// What one run produced.
struct Outcome {
    records: Vec<CycleRecord>,
    summary: RunSummary,
    platform: Platform,
    timing: Timing,
}

/// Runs `waypoints` (a quintic spline, time-scaled by the runtime) through the full frame
/// path with the simulator's defaults, the simulated platform starting at the first waypoint.
fn run(waypoints: &[WaypointSpec], seed: u64) -> Outcome {
    let platform = Platform::justin();
    let traj = QuinticSpline::from_specs(&platform, waypoints).expect("valid waypoints");
    let r0 = traj.sample(0.0);
    let mut core = CycleCore::new(platform.clone(), Box::new(traj), RuntimeConfig::default())
        .expect("a trajectory every timing can fix");
    let timing = core.trajectory_timing().expect("time-scaled");
    let mut sim = Simulator::with_config(
        &platform,
        SimConfig {
            initial: Some(InitialState::from_reference(&platform, &r0)),
            seed,
            ..SimConfig::default()
        },
    )
    .expect("simulator");
    let mut bus = VirtualLockstepBus::new(FaultModel::none(), seed ^ 0x5EED);
    let max_cycles = ((core.reference_duration() + 15.0) * platform.cycle_hz) as u64;
    let mut records = Vec::with_capacity(max_cycles as usize);
    let mut summary = RunSummary::new("waypoints");
    summary.timing = Some(timing);
    run_lockstep(
        &mut core,
        &mut bus,
        &mut sim,
        max_cycles,
        None,
        &mut |r, _| {
            summary.update(r);
            records.push(*r);
        },
    )
    .expect("one-bus platform, one lockstep bus");
    Outcome {
        records,
        summary,
        platform,
        timing,
    }
}

/// Prints the run's figures (for the record of what was measured) and asserts the issue's
/// bounds: the run ends in Stopped; errors against the truth below 5 mm, 0.5° and 2 mm
/// (legs); every command within its speed and acceleration limits on every cycle; and the
/// reference within the time scaling's shares (its own verification).
fn assert_bounds(name: &str, o: &Outcome) {
    let s = &o.summary;
    let t = &o.timing;
    println!(
        "{name}: pos {:.2} mm, heading {:.3}°, legs {:.2} mm, {}, nominal {:.2} s, executed {:.2} s, scale min {:.3} at {:.2} s ({}), shares used {:.3}",
        s.max_position_error_m * 1e3,
        s.max_heading_error_rad.to_degrees(),
        s.max_leg_error_m * 1e3,
        s.final_state,
        t.nominal_duration_s,
        t.executed_duration_s,
        t.min_scale,
        t.min_scale_at_s,
        s.to_json()["time_scale_limit"],
        t.max_ratio
    );
    assert_tracking_bounds(s, name);
    let p = &o.platform;
    for w in o.records.windows(2) {
        if let Some(v) = rollbase_control::reference::limits::check_command(
            &p.limits,
            &w[0].command,
            &w[1].command,
            p.dt(),
        ) {
            panic!("{name}: cycle {} ({}): {v}", w[1].cycle, w[1].mode);
        }
    }
    assert!(
        t.max_ratio <= 1.0 + rollbase_control::reference::timescale::VERIFY_TOLERANCE,
        "{name}: the reference uses {} of its shares",
        t.max_ratio
    );
}

/// Steering chatter of a wheel ([`steering_chatter`], the measure of e2e_drive.rs).
fn chatter(o: &Outcome, wheel: usize) -> usize {
    steering_chatter(&o.records, o.platform.wheel_radius, wheel)
}

/// Largest change of a wheel's measured steering angle while it is commanded to roll slower
/// than 1 cm/s during tracking ([`steering_turn_while_slow`]; a flip would be about π).
fn turn_while_slow(o: &Outcome, wheel: usize) -> f64 {
    steering_turn_while_slow(&o.records, o.platform.wheel_radius, wheel)
}

#[test]
fn seed000_sends_the_same_frames_time_scaled_and_as_given() {
    // Nothing saturates in the seed-000 experiment: the scaled trajectory passes its samples
    // through, and every frame on the bus is the same, bit for bit.
    let scaled = same_frames_scaled_and_raw(Scenario::Seed000);
    rollbase_tests::assert_seed000_bounds(&scaled);
}

#[test]
fn seed001_with_its_avoidance_is_time_scaled_whether_the_scaling_is_on_or_off() {
    // The avoidance experiment (its default controller and avoidance): the avoidance acts on
    // the path before the run and the avoided path is always time-scaled
    // (`rollbase_control::reference::avoidance`, "Pre-planned trajectories"), with the default margins
    // when the scaling is off. So the same frames, bit for bit, and the run is slowed: the
    // nominal asks 5× the steering acceleration limit.
    let scaled = same_frames_scaled_and_raw(Scenario::Seed001);
    let timing = scaled.timing.expect("a time-scaled trajectory");
    assert!(
        timing.executed_duration_s > timing.nominal_duration_s
            && timing.max_ratio <= 1.0 + rollbase_control::reference::timescale::VERIFY_TOLERANCE,
        "{timing:?}"
    );
}

/// Runs the scenario with the time scaling (the default) and without it, asserts that every
/// frame sent, every command and every reference are the same bit for bit, and returns the
/// scaled run.
fn same_frames_scaled_and_raw(sc: Scenario) -> rollbase_tests::RunOutcome {
    let mut scaled_opts = rollbase_tests::RunOptions::new(sc);
    scaled_opts.runtime.time_scaling =
        Some(rollbase_control::reference::timescale::TimeScaleConfig::default());
    let scaled = rollbase_tests::run(&scaled_opts);
    let mut raw_opts = rollbase_tests::RunOptions::new(sc);
    raw_opts.runtime.time_scaling = None;
    let raw = rollbase_tests::run(&raw_opts);
    assert_eq!(scaled.records.len(), raw.records.len(), "{sc:?}");
    let mut frames = 0;
    for (a, b) in scaled.records.iter().zip(&raw.records) {
        assert_eq!(a.n_tx, b.n_tx, "{sc:?} cycle {}", a.cycle);
        for (fa, fb) in a.tx[..a.n_tx].iter().zip(&b.tx[..b.n_tx]) {
            assert_eq!(
                (fa.id, fa.len, fa.data),
                (fb.id, fb.len, fb.data),
                "{sc:?} cycle {}",
                a.cycle
            );
            frames += 1;
        }
        assert_eq!(a.command, b.command, "{sc:?} cycle {}", a.cycle);
        assert_eq!(a.reference, b.reference, "{sc:?} cycle {}", a.cycle);
    }
    // At least a SYNC per cycle: the comparison saw the whole run's traffic.
    assert!(
        frames >= scaled.records.len(),
        "{sc:?}: {frames} frames compared in {} cycles",
        scaled.records.len()
    );
    assert_eq!(
        scaled.summary.max_position_error_m,
        raw.summary.max_position_error_m
    );
    scaled
}

#[test]
fn a_pivot_about_a_wheel_holds_that_wheel_without_chatter() {
    let o = run(&pivot(1, 1.5, 2.5), 1);
    assert_bounds("pivot about wheel 2", &o);
    assert!(o.timing.steer_reference);
    let (c, turn) = (chatter(&o, 1), turn_while_slow(&o, 1));
    println!(
        "pivot wheel: {c} reversals, largest turn while slow {:.3}°",
        turn.to_degrees()
    );
    assert_eq!(c, 0, "wheel 2 chatters: {c} steering reversals while still");
    assert!(
        turn < 2f64.to_radians(),
        "wheel 2 turned {:.2}° while still",
        turn.to_degrees()
    );
    // The platform did turn about it.
    let (last, _) = o.records.last().and_then(|r| r.truth).expect("truth");
    assert!((last.theta - 1.5).abs() < 0.01, "turned {}", last.theta);
}

#[test]
fn an_icr_sweeping_across_a_wheel_reverses_its_roll_without_a_flip() {
    let o = run(&icr_sweep(0, 0.8, 0.4, 4.0), 2);
    assert_bounds("ICR sweeping across wheel 1", &o);
    assert!(o.timing.steer_reference);
    assert!(
        o.timing.executed_duration_s > o.timing.nominal_duration_s,
        "slowed to turn the wheels near the ICR"
    );
    let (c, turn) = (chatter(&o, 0), turn_while_slow(&o, 0));
    println!(
        "swept wheel: {c} reversals, largest turn while slow {:.3}°",
        turn.to_degrees()
    );
    // No flip: while slow the wheel never turns by more than a fraction of the half turn
    // its direction of travel makes. (The spline passes the ICR a few millimetres beside
    // the wheel: the wheel follows its direction a little way before and after the stretch
    // it holds, one back-and-forth of about 25° while slower than 1.3 cm/s.)
    assert!(c <= 1, "wheel 1 chatters: {c} reversals");
    assert!(
        turn < 45f64.to_radians(),
        "wheel 1 turned {:.2}° while slow",
        turn.to_degrees()
    );
    // The wheel rolled both ways: its roll reversed as the ICR crossed it.
    let speeds: Vec<f64> = o
        .records
        .iter()
        .map(|r| r.command.wheels[0].wheel_speed)
        .collect();
    let (lo, hi) = speeds
        .iter()
        .fold((0.0f64, 0.0f64), |(a, b), &v| (a.min(v), b.max(v)));
    assert!(lo < -0.5 && hi > 0.5, "wheel 1 rolled {lo}..{hi} rad/s");
}

#[test]
fn a_reversal_runs_out_and_back_within_bounds() {
    let l = [0.465; 4];
    let w = [
        wp(0.0, z(0.0, 0.0, 0.0, l)),
        wp(1.5, z(1.0, 0.3, 0.6, l)),
        wp(3.0, z(0.0, 0.0, 0.0, l)),
    ];
    let o = run(&w, 3);
    assert_bounds("reversal", &o);
    let (end, _) = o.records.last().and_then(|r| r.truth).expect("truth");
    assert!(end.x.hypot(end.y) < 0.005 && end.theta.abs() < 0.5f64.to_radians());
}

#[test]
fn sideways_with_the_legs_from_limit_to_limit() {
    // Waypoints exactly at the leg limits (accepted: the spline is kept in range), the legs
    // faster than their speed limit allows: the run is stretched.
    let (lo, hi) = ([0.37; 4], [0.56; 4]);
    let w = [
        wp(0.0, z(0.0, 0.0, 0.0, lo)),
        wp(1.2, z(0.0, 0.8, 0.0, hi)),
        wp(2.4, z(0.0, 1.6, 0.0, lo)),
    ];
    let o = run(&w, 4);
    assert_bounds("sideways, legs limit to limit", &o);
    assert!(o.timing.min_scale < 1.0, "{:?}", o.timing);
    let legs = |r: &CycleRecord| r.truth.expect("truth").1[0];
    let max = o.records.iter().map(legs).fold(0.0, f64::max);
    let min = o.records.iter().map(legs).fold(1.0, f64::min);
    assert!(
        max > 0.558 && min < 0.372 && max <= 0.5605 && min >= 0.3695,
        "legs {min}..{max}"
    );
}

/// A random waypoint trajectory (seeded): 3–5 waypoints mixing translation (0.2–1.2 m per
/// segment), rotation (up to ±1.5 rad) and leg motion (a quarter of the legs set exactly at
/// a limit), timed for 0.25–1.0 m/s (at the top, beyond what the wheels allow), with the
/// times of every waypoint left out in a fifth of the trajectories and of every other
/// waypoint in another fifth.
fn random_waypoints(seed: u64) -> Vec<WaypointSpec> {
    let mut rng = rollbase_driver::rng::Rng::new(seed);
    let mut u = |lo: f64, hi: f64| lo + (hi - lo) * rng.next_f64();
    let (lmin, lmax) = (0.37, 0.56);
    let leg = |u: &mut dyn FnMut(f64, f64) -> f64, prev: f64| {
        let c = u(0.0, 1.0);
        if c < 0.12 {
            lmin
        } else if c < 0.25 {
            lmax
        } else if c < 0.5 {
            prev
        } else {
            u(lmin, lmax)
        }
    };
    let m = 3 + (u(0.0, 3.0) as usize).min(2);
    let untimed = u(0.0, 1.0);
    let mut legs = [0.0; 4];
    for l in legs.iter_mut() {
        *l = leg(&mut u, 0.465);
    }
    let mut zs = vec![z(0.0, 0.0, 0.0, legs)];
    let mut ts = vec![0.0];
    for _ in 1..m {
        let prev = *zs.last().expect("a waypoint");
        let (d, a, th) = (
            u(0.2, 1.2),
            u(-std::f64::consts::PI, std::f64::consts::PI),
            u(-1.5, 1.5),
        );
        for (i, l) in legs.iter_mut().enumerate() {
            *l = leg(&mut u, prev[3 + i]);
        }
        let next = z(
            prev[0] + d * a.cos(),
            prev[1] + d * a.sin(),
            prev[2] + th,
            legs,
        );
        let v = u(0.25, 1.0);
        let dl = (0..4)
            .map(|i| (next[3 + i] - prev[3 + i]).abs())
            .fold(0.0, f64::max);
        let h = (d / v)
            .max(th.abs() * 0.5 / v)
            .max(dl / u(0.1, 0.3))
            .max(0.5);
        ts.push(ts.last().expect("a time") + h);
        zs.push(next);
    }
    zs.iter()
        .zip(&ts)
        .enumerate()
        .map(|(k, (z, t))| WaypointSpec {
            t: if untimed < 0.2 || (untimed < 0.4 && k % 2 == 1) {
                None
            } else {
                Some(*t)
            },
            z: *z,
        })
        .collect()
}

/// Ten of the 50 seeded random trajectories (five tests, so the default test run spreads
/// them over the cores).
fn random_batch(first: u64) {
    for seed in first..first + 10 {
        let w = random_waypoints(seed);
        assert_bounds(&format!("random {seed}"), &run(&w, seed));
    }
}

#[test]
fn random_trajectories_0_to_9() {
    random_batch(0);
}

#[test]
fn random_trajectories_10_to_19() {
    random_batch(10);
}

#[test]
fn random_trajectories_20_to_29() {
    random_batch(20);
}

#[test]
fn random_trajectories_30_to_39() {
    random_batch(30);
}

#[test]
fn random_trajectories_40_to_49() {
    random_batch(40);
}

#[test]
fn the_random_trajectories_mix_what_the_issue_asks_for() {
    // The generator covers every kind: untimed waypoints, legs at their limits, and speeds
    // beyond the limits (the runs above are stretched).
    let all: Vec<_> = (0..50).map(random_waypoints).collect();
    let untimed = all
        .iter()
        .filter(|w| w.iter().any(|x| x.t.is_none()))
        .count();
    let all_untimed = all
        .iter()
        .filter(|w| w.iter().all(|x| x.t.is_none()))
        .count();
    let at_limit = all
        .iter()
        .filter(|w| {
            w.iter()
                .any(|x| (3..7).any(|i| x.z[i] == 0.37 || x.z[i] == 0.56))
        })
        .count();
    let p = Platform::justin();
    let beyond = all
        .iter()
        .filter(|w| w.iter().all(|x| x.t.is_some()))
        .filter(|w| {
            let s = QuinticSpline::from_specs(&p, w).expect("valid");
            (0..=400).any(|k| {
                let r = s.sample(s.duration() * k as f64 / 400.0);
                rollbase_control::reference::limits::reference_ratio(&p, &r).0 > 1.0
            })
        })
        .count();
    println!("{untimed} with untimed waypoints ({all_untimed} fully), {at_limit} with a leg at a limit, {beyond} timed beyond the limits");
    assert!(untimed >= 10 && all_untimed >= 5 && at_limit >= 25 && beyond >= 15);
}
