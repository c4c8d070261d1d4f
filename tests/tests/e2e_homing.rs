//! Steering homing on the CiA 402 twin, on virtual time: the steering drives' position
//! counters start at 0 wherever the wheels point (incremental encoders), each method of the
//! platform file homes them from random power-on angles, the wheels turn to their rest
//! angles, and seed 000 then runs within its bounds against the simulator's truth. Homings
//! that cannot succeed (no switch, too slow) are refused with the wheel named, nothing
//! tracked. A steering drive that loses power mid-run is noticed, and homed again on re-arm.

use rollbase_control::angle;
use rollbase_control::runtime::record::CycleRecord;
use rollbase_control::runtime::scenario::Scenario;
use rollbase_control::service::ports::{CommandEvent, CommandKind};
use rollbase_control::supervisor::{FaultReason, SupervisorState};
use rollbase_control::{Platform, Protocol, MAX_WHEELS};
use rollbase_driver::canopen::config::{ExtraSdo, Homing, HomingKind, Role};
use rollbase_driver::canopen::master::{BootError, DeviceFault, HomingError};
use rollbase_driver::canopen::nmt::NmtState;
use rollbase_tests::{
    assert_seed000_bounds, run, run_live, twist_at, LiveOptions, RunOptions, RunOutcome,
};
use rollbase_vcan_sim::canopen::{SteerAxis, TwinConfig};
use rollbase_vcan_sim::faults::PowerCycle;

/// Where the machine's home switches are (rad): the angles the base powered on at.
const EDGES: [f64; 4] = [0.3, -0.5, 1.0, -1.4];

/// Power-on steering angles in (−π, π), from a seed (a small LCG: the test is repeatable).
fn random_angles(seed: u64) -> [f64; MAX_WHEELS] {
    let mut x = seed.wrapping_mul(6_364_136_223_846_793_005).wrapping_add(1);
    let mut a = [0.0; MAX_WHEELS];
    for v in a.iter_mut().take(4) {
        x = x
            .wrapping_mul(6_364_136_223_846_793_005)
            .wrapping_add(1_442_695_040_888_963_407);
        *v = ((x >> 11) as f64 / (1u64 << 53) as f64 - 0.5) * 2.0 * 3.1;
    }
    a
}

/// The controller's platform: CiA 402, `homing` on every steering drive, each wheel's
/// `steer_offset_rad` the angle that homing finds on this machine.
fn platform(homing: Homing, home: [f64; 4]) -> Platform {
    let mut p = Platform::justin();
    p.protocol = Protocol::Cia402;
    let mut c = p.cia402();
    c.homing = homing;
    for (w, h) in c.wheels.iter_mut().zip(home) {
        w.steer_offset_rad = h;
    }
    p.cia402 = Some(c);
    p.validate().expect("valid platform");
    p
}

fn twin(axis: impl Fn(usize) -> SteerAxis) -> TwinConfig {
    let mut t = TwinConfig::default();
    for (i, a) in t.axes.iter_mut().enumerate().take(4) {
        *a = Some(axis(i));
    }
    t
}

fn drive_method(method: i8) -> Homing {
    Homing {
        kind: HomingKind::Drive,
        method,
        ..Homing::default()
    }
}

fn armed_at(out: &RunOutcome) -> usize {
    out.records
        .iter()
        .position(|r| r.state != SupervisorState::Idle)
        .expect("armed")
}

/// At the end of the run every wheel's measured steering angle is its true angle (within
/// 0.5°): the homing gave the counters their meaning (seed 000's bounds against the truth
/// say the same for the whole run).
fn assert_angles_true(out: &RunOutcome, what: &str) {
    let armed = armed_at(out);
    let last = out.records.last().expect("records");
    let mut worst = 0.0f64;
    for i in 0..last.n {
        let e = angle::diff(
            last.measurement.wheels[i].steer_angle,
            out.final_truth_steer[i],
        )
        .abs();
        worst = worst.max(e);
    }
    println!(
        "{what}: armed after {} ms, final steering angle error {:.4}°",
        armed * 4,
        worst.to_degrees()
    );
    assert!(
        worst < 0.5f64.to_radians(),
        "{what}: measured steering {:.3}° off the truth",
        worst.to_degrees()
    );
}

fn homed_seed000(
    homing: Homing,
    home: [f64; 4],
    axis: impl Fn(usize) -> SteerAxis,
    start: [f64; MAX_WHEELS],
    what: &str,
) {
    let mut opts = RunOptions::new(Scenario::Seed000).cia402();
    opts.platform = Some(platform(homing, home));
    opts.twin = twin(axis);
    opts.initial_steer = Some(start);
    // Homing and the rest turn come before the trajectory: up to ~15 s more.
    opts.slack_s = 40.0;
    let out = run(&opts);
    println!("{what}: {}", out.summary.to_json());
    assert_seed000_bounds(&out);
    assert_angles_true(&out, what);
    // Before homing the counters said 0 wherever the wheels pointed: the angles the
    // platform would have believed without homing were wrong by the power-on angle.
    let believed_wrong = (0..4).any(|i| angle::diff(start[i], home[i]).abs() > 0.1);
    assert!(
        believed_wrong,
        "{what}: the power-on angles must differ from the home angles"
    );
}

fn switch_axis(i: usize, positive: bool, index: f64) -> SteerAxis {
    SteerAxis {
        switch_edge_rad: EDGES[i],
        switch_positive: positive,
        index_rad: EDGES[i] + index,
        ..SteerAxis::default()
    }
}

#[test]
fn method_19_positive_home_switch_from_random_power_on_angles() {
    homed_seed000(
        drive_method(19),
        EDGES,
        |i| switch_axis(i, true, 0.0),
        random_angles(19),
        "method 19",
    );
}

#[test]
fn method_21_negative_home_switch_from_random_power_on_angles() {
    homed_seed000(
        drive_method(21),
        EDGES,
        |i| switch_axis(i, false, 0.0),
        random_angles(21),
        "method 21",
    );
}

#[test]
fn method_3_positive_switch_then_index_pulse_from_random_power_on_angles() {
    // The index pulse 0.2 rad on the negative side of the edge: that is the home position.
    let home = EDGES.map(|e| e - 0.2);
    homed_seed000(
        drive_method(3),
        home,
        |i| switch_axis(i, true, -0.2),
        random_angles(3),
        "method 3",
    );
}

#[test]
fn method_5_negative_switch_then_index_pulse_from_random_power_on_angles() {
    let home = EDGES.map(|e| e + 0.2);
    homed_seed000(
        drive_method(5),
        home,
        |i| switch_axis(i, false, 0.2),
        random_angles(5),
        "method 5",
    );
}

#[test]
fn methods_33_and_34_index_pulse_only_from_random_power_on_angles() {
    // The index fires once per steering turn: searched at 0.5 rad/s (0x6099:02), at most
    // a turn (12.6 s) within the 20 s timeout.
    let home = EDGES.map(|e| e + 0.05);
    for m in [33, 34] {
        let homing = Homing {
            index_speed_rad_s: 0.5,
            ..drive_method(m)
        };
        homed_seed000(
            homing,
            home,
            |i| switch_axis(i, true, 0.05),
            random_angles(m as u64),
            &format!("method {m}"),
        );
    }
}

#[test]
fn method_37_current_position_when_the_wheels_are_set_by_hand() {
    // The method's precondition: the wheels stand at the home angle at power-on (set by
    // hand or a fixture); the counter's 0 is then that angle.
    let mut start = [0.0; MAX_WHEELS];
    start[..4].copy_from_slice(&EDGES);
    let mut opts = RunOptions::new(Scenario::Seed000).cia402();
    opts.platform = Some(platform(drive_method(37), EDGES));
    opts.twin = twin(|i| switch_axis(i, true, 0.0));
    opts.initial_steer = Some(start);
    opts.slack_s = 40.0;
    let out = run(&opts);
    assert_seed000_bounds(&out);
    assert_angles_true(&out, "method 37");
}

#[test]
fn host_side_homing_on_a_digital_input_from_random_power_on_angles() {
    let homing = Homing {
        kind: HomingKind::DigitalInput,
        input_bit: 2,
        switch_speed_rad_s: 0.5,
        ..Homing::default()
    };
    homed_seed000(
        homing,
        EDGES,
        |i| switch_axis(i, true, 0.0),
        random_angles(7),
        "digital input",
    );
}

#[test]
fn absolute_steering_encoders_are_verified_and_not_moved() {
    let homing = Homing {
        kind: HomingKind::Absolute,
        ..Homing::default()
    };
    let axis = |i: usize| SteerAxis {
        absolute: true,
        ..switch_axis(i, true, 0.0)
    };
    homed_seed000(homing, EDGES, axis, random_angles(11), "absolute");
}

fn first_fault(out: &RunOutcome) -> &CycleRecord {
    out.records
        .iter()
        .find(|r| r.state == SupervisorState::Fault)
        .expect("the supervisor faulted")
}

fn refused(
    homing: Homing,
    axis: impl Fn(usize) -> SteerAxis,
    wheel: usize,
) -> (RunOutcome, HomingError, String) {
    let mut opts = RunOptions::new(Scenario::Seed000).cia402();
    opts.platform = Some(platform(homing, EDGES));
    opts.twin = twin(axis);
    opts.initial_steer = Some(random_angles(5));
    opts.slack_s = 0.0;
    let out = run(&opts);
    let f = first_fault(&out);
    let text = f.reason.expect("reason").to_string();
    let node = 2 + 2 * wheel as u8;
    let e = match f.reason {
        Some(FaultReason::DeviceFault {
            wheel: w,
            node: n,
            role: Role::Steer,
            fault: DeviceFault::Boot(BootError::Homing { error, .. }),
        }) if w == wheel && n == node => error,
        r => panic!("unexpected reason {r:?}"),
    };
    // Refused before anything tracked; the platform never followed a reference.
    assert!(out
        .records
        .iter()
        .all(|r| r.state != SupervisorState::Tracking));
    let name = format!("wheel {} steering drive (node {node})", wheel + 1);
    assert!(text.contains(&name), "{text}");
    (out, e, text)
}

#[test]
fn a_home_switch_never_seen_is_refused_naming_the_wheel() {
    // Wheel 2's switch is not connected; its homing times out.
    let homing = Homing {
        timeout_ms: 8000,
        ..drive_method(19)
    };
    let (out, e, text) = refused(
        homing,
        |i| SteerAxis {
            switch_width_rad: if i == 1 { 0.0 } else { std::f64::consts::PI },
            ..switch_axis(i, true, 0.0)
        },
        1,
    );
    assert!(
        matches!(
            e,
            HomingError::Timeout {
                ms: 8000,
                phase: rollbase_driver::canopen::master::HomingPhase::Searching,
                ..
            }
        ),
        "{e:?}"
    );
    assert!(text.contains("never seen"), "{text}");
    let t = first_fault(&out).t;
    println!("{text} (at {t:.2} s)");
    assert!((8.0..9.0).contains(&t), "refused at {t} s");
    // A host-side homing on an input that never fires is refused after 1.25 turns.
    let homing = Homing {
        kind: HomingKind::DigitalInput,
        ..Homing::default()
    };
    let (_, e, text) = refused(
        homing,
        |i| SteerAxis {
            switch_width_rad: if i == 1 { 0.0 } else { std::f64::consts::PI },
            ..switch_axis(i, true, 0.0)
        },
        1,
    );
    assert!(
        matches!(e, HomingError::InputNeverSeen { bit: 2, .. }),
        "{e:?}"
    );
    assert!(text.contains("input bit 2"), "{text}");
}

#[test]
fn a_homing_slower_than_its_timeout_is_refused_naming_the_wheel() {
    let homing = Homing {
        switch_speed_rad_s: 0.02,
        timeout_ms: 2000,
        ..drive_method(19)
    };
    // Wheel 1's axis is the first whose homing runs out of time (they start together).
    let (_, e, text) = refused(homing, |i| switch_axis(i, true, 0.0), 0);
    assert!(matches!(e, HomingError::Timeout { ms: 2000, .. }), "{e:?}");
    println!("{text}");
}

/// A steering drive power-cycled while the base drives: its boot-up is a fault (the wheel's
/// angle is lost), the platform stops; the re-arm boots it, homes it again (its counter
/// restarted at 0 wherever the wheel stood) and the base drives on with true angles.
#[test]
fn a_power_cycled_steering_drive_is_homed_again_on_re_arm() {
    let mut start = [0.0; MAX_WHEELS];
    start[..4].copy_from_slice(&random_angles(3)[..4]);
    let mut opts = LiveOptions {
        profile: Protocol::Cia402,
        platform: Some(platform(drive_method(19), EDGES)),
        twin: twin(|i| switch_axis(i, true, 0.0)),
        initial: Some(rollbase_vcan_sim::InitialState {
            steer: start,
            ..rollbase_vcan_sim::InitialState::nominal(&Platform::justin())
        }),
        max_seconds: 90.0,
        ..LiveOptions::default()
    };
    // Wheel 2's steering drive loses power 4 s into the run (it is tracking by then).
    opts.faults
        .power_cycle
        .push(PowerCycle { node: 4, at: 12.0 });
    let mut cmds: Vec<CommandEvent> = Vec::new();
    let mut t = 0.5;
    while t < 6.0 {
        cmds.push(twist_at(t, 0.15, 0.05, 0.0));
        t += 0.25;
    }
    cmds.push(CommandEvent {
        t: 12.0,
        kind: CommandKind::Rearm,
    });
    let mut t = 25.0;
    while t < 29.0 {
        cmds.push(twist_at(t, 0.15, 0.0, 0.1));
        t += 0.25;
    }
    cmds.push(CommandEvent {
        t: 30.0,
        kind: CommandKind::EndOfStream,
    });
    let out = run_live(&opts, &cmds);
    let fault = first_fault(&out);
    match fault.reason {
        Some(FaultReason::DeviceFault {
            wheel: 1,
            node: 4,
            role: Role::Steer,
            fault: DeviceFault::NmtState {
                state: NmtState::BootUp,
            },
        }) => {}
        r => panic!("unexpected reason {r:?}"),
    }
    let fault_at = fault.cycle as usize;
    // After the fault the platform tracks again (re-armed, re-homed) and moves.
    let back = out.records[fault_at..]
        .iter()
        .position(|r| r.state == SupervisorState::Tracking)
        .map(|k| k + fault_at)
        .expect("tracking again after the re-arm");
    let pose_back = out.records[back].pose;
    let end = out.records.last().unwrap();
    let moved = (end.pose.x - pose_back.x).hypot(end.pose.y - pose_back.y);
    println!(
        "power cycle: fault at {:.2} s, tracking again at {:.2} s, moved {moved:.3} m after",
        fault.t, out.records[back].t
    );
    assert!(moved > 0.3, "moved {moved} m after the re-arm");
    // The re-homed axis reports its true angle again (its counter restarted at 0 at
    // wherever the wheel stood).
    assert_angles_true(&out, "power cycle");
    assert_eq!(
        out.summary.final_state, "stopped",
        "{:?}",
        out.summary.fault_reason
    );
    // The twin's informational EMCY after each start (0xFF01, error register 0) was counted
    // and kept in the diagnostics (state port, recording, ROS 2), never a fault: wheel 2's
    // steering drive started twice, its rolling drive and leg encoder once each.
    let d = out.final_state.expect("state").diagnostics.modules[1];
    assert_eq!(d.emcy_faults, 0, "{d:?}");
    assert_eq!(d.emcy_informational, 4, "{d:?}");
    assert!(
        d.emcy
            .iter()
            .any(|e| e.node == 4 && e.code == 0xFF01 && e.register == 0),
        "{d:?}"
    );
}

/// Mirrored motors (mounted so that the motor's positive direction turns the joint the
/// negative way; the twin models the mounting and the drives' polarity 0x607E) run seed 000
/// within its bounds, homing included, when the platform file says so: wheel 2's rolling and
/// steering drives with polarity 0x607E = 0xC0 (position and velocity inverted) written at
/// boot by [[cia402.sdo]]; or every motor mirrored and the platform's gear ratios negative.
#[test]
fn mirrored_motors_compensated_by_polarity_or_a_negative_ratio_run_seed000() {
    // 0x607E on one wheel's drives.
    let mut p = platform(drive_method(19), EDGES);
    let mut c = p.cia402.take().expect("cia402");
    for node in [3, 4] {
        c.sdo.push(ExtraSdo {
            role: None,
            node: Some(node),
            index: 0x607E,
            sub: 0,
            value: 0xC0,
            size: 1,
            optional: false,
        });
    }
    p.cia402 = Some(c);
    p.validate().expect("valid");
    let mut t = twin(|i| switch_axis(i, true, 0.0));
    t.mirrored = vec![3, 4];
    mirrored_seed000(p, t, "wheel 2 mirrored, 0x607E = 0xC0");
    // Negative ratios for every rolling and steering drive, every motor mirrored.
    let mut p = platform(drive_method(19), EDGES);
    let mut c = p.cia402.take().expect("cia402");
    c.drive.gear_ratio = -c.drive.gear_ratio;
    c.steer.gear_ratio = -c.steer.gear_ratio;
    p.cia402 = Some(c);
    p.validate().expect("a negative gear ratio is valid");
    let mut t = twin(|i| switch_axis(i, true, 0.0));
    t.mirrored = (1..=8).collect();
    mirrored_seed000(p, t, "all mirrored, negative ratios");
}

fn mirrored_seed000(p: Platform, twin: TwinConfig, what: &str) {
    let mut opts = RunOptions::new(Scenario::Seed000).cia402();
    // The simulated machine: the same drives (its units are the machine's, the sign is the
    // mounting, `twin.mirrored`).
    opts.sim_platform = Some(p.clone());
    opts.platform = Some(p);
    opts.twin = twin;
    opts.initial_steer = Some(random_angles(7));
    opts.slack_s = 40.0;
    let out = run(&opts);
    println!("{what}: {}", out.summary.to_json());
    assert_seed000_bounds(&out);
    assert_angles_true(&out, what);
}

/// A mirrored motor the platform file does not know about (wheel 2's rolling drive, or its
/// steering drive; no 0x607E, no negative ratio): the drive's own feedback agrees with its
/// command, so homing and the rest turn pass, but the wheel turns the other way; the
/// odometry's residual between the wheels (slip) catches it once the base moves, and the
/// platform stops before it got far from its path.
#[test]
fn an_uncompensated_mirrored_motor_is_caught_before_the_base_drives_off() {
    for node in [3u8, 4] {
        let p = platform(drive_method(19), EDGES);
        let mut t = twin(|i| switch_axis(i, true, 0.0));
        t.mirrored = vec![node];
        let mut opts = RunOptions::new(Scenario::Seed000).cia402();
        opts.sim_platform = Some(p.clone());
        opts.platform = Some(p);
        opts.twin = t;
        opts.initial_steer = Some(random_angles(7));
        opts.slack_s = 40.0;
        let out = run(&opts);
        let f = first_fault(&out);
        let text = f.reason.expect("reason").to_string();
        println!(
            "node {node} mirrored: fault at {:.2} s: {text}; max position error {:.3} m",
            f.t, out.summary.max_position_error_m
        );
        assert!(
            matches!(f.reason, Some(FaultReason::Slip { .. })),
            "node {node}: {text}"
        );
        // The slip points at wheel 2, whose motor is mirrored, or at no wheel; never at
        // another one. The mirrored rolling motor leaves wheel 2 alone disagreeing with the
        // others. The mirrored steering turns wheel 2 the wrong way while its encoder reads
        // what was commanded: the simulated base moves as the least-squares compromise of all
        // its wheels, so every wheel's reading disagrees a little, and no drive is outside
        // its following window.
        let lead = f.reason.and_then(|r| r.slip_lead());
        let expected = if node == 3 {
            vec![Some(1)]
        } else {
            vec![Some(1), None]
        };
        assert!(expected.contains(&lead), "node {node}: {text}");
        // Stopped within 10 cm of the path (seed 000 runs 4.5 m each way).
        assert!(
            out.summary.max_position_error_m < 0.1,
            "node {node}: {} m off the path",
            out.summary.max_position_error_m
        );
        assert_eq!(out.summary.final_state, "fault");
    }
}

/// A wheel with a steering range turns to its rest angle after homing inside the range
/// (issue 25): the three-wheel example (±170°), wheel 0 powered on at −150° on its home
/// switch and homed by the drive (method 19) at the switch's edge, −160°, with its rest
/// angle at +160°. The short way round (−40°, through ±180°) would wind
/// it past its −170° stop; it must turn the long way (+320°) inside [−170°, 170°]. Checked
/// every cycle on its encoder, followed by continuity from the first reading.
#[test]
fn a_wheel_with_a_steering_range_turns_to_its_rest_angle_inside_the_range() {
    let home = [-150f64.to_radians(), 0.0, 0.0, 0.0];
    let rest = 160f64.to_radians();
    let mut p = Platform::three_wheel();
    p.protocol = Protocol::Cia402;
    let mut c = p.cia402();
    c.homing = drive_method(19);
    for (w, h) in c.wheels.iter_mut().zip(home) {
        w.steer_offset_rad = h;
    }
    c.wheels[0].rest_angle_rad = rest;
    p.cia402 = Some(c);
    p.validate().expect("valid platform");
    let range = p.wheels[0].steering_range().expect("a range");
    let mut opts = RunOptions::new(Scenario::Seed000).cia402();
    opts.platform = Some(p);
    opts.twin = twin(|i| SteerAxis {
        switch_edge_rad: home[i],
        ..SteerAxis::default()
    });
    let mut start = [0.0; MAX_WHEELS];
    start[..4].copy_from_slice(&home.map(|h| h + 10f64.to_radians()));
    opts.initial_steer = Some(start);
    opts.max_seconds = Some(20.0);
    let out = run(&opts);
    let armed = armed_at(&out);
    let mut phi: Option<f64> = None;
    let (mut lo, mut hi) = (f64::INFINITY, f64::NEG_INFINITY);
    for r in out.records.iter().take(armed) {
        if r.feedback_age[0] != 0 && phi.is_none() {
            continue;
        }
        let m = r.measurement.wheels[0].steer_angle;
        let a = match phi {
            None => range.first(m),
            Some(p) => p + angle::diff(m, p),
        };
        phi = Some(a);
        lo = lo.min(a);
        hi = hi.max(a);
        assert!(
            a >= range.min - 1e-3 && a <= range.max + 1e-3,
            "wheel 0 at {:.1}° at t = {:.3} s, outside [{:.0}°, {:.0}°]",
            a.to_degrees(),
            r.t,
            range.min.to_degrees(),
            range.max.to_degrees()
        );
    }
    let at_arm = phi.expect("steering readings");
    println!(
        "wheel 0 swept [{:.1}°, {:.1}°], at {:.2}° when armed after {} ms",
        lo.to_degrees(),
        hi.to_degrees(),
        at_arm.to_degrees(),
        armed * 4
    );
    assert!(
        (at_arm - rest).abs() < 0.01,
        "armed with wheel 0 at {:.2}°, its rest angle is 160°",
        at_arm.to_degrees()
    );
    assert!(lo < -145f64.to_radians(), "it was homed at −150°: {lo}");
}
