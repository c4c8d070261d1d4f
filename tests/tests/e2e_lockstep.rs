//! Closed-loop end-to-end tests through the full frame path, on virtual time.

use rollbase_control::runtime::ControllerKind;
use rollbase_control::scenario::Scenario;
use rollbase_control::supervisor::SupervisorState;
use rollbase_tests::{assert_seed000_bounds, run, RunOptions};

fn assert_tracks_seed000(controller: ControllerKind) {
    let out = run(&RunOptions::new(Scenario::Seed000).with_controller(controller));
    println!("{controller:?}: {}", out.summary.to_json());
    assert_seed000_bounds(&out);
    let last = out.records.last().expect("records");
    // The run ends by disabling the drives, so no module trips its watchdog afterwards.
    assert_eq!(last.mode, "disable");
    let setpoints: Vec<_> = last.tx[..last.n_tx]
        .iter()
        .filter(|f| (0x201..=0x20F).contains(&f.id))
        .collect();
    assert_eq!(setpoints.len(), 4);
    for f in setpoints {
        let frame = rollbase_driver::frame::CanFrame::new(f.id, &f.data[..f.len as usize]).unwrap();
        match rollbase_driver::decode(&frame).unwrap().payload {
            rollbase_driver::Payload::Setpoint(sp) => {
                assert!(!sp.flags.enable, "drives disabled at the end");
                assert_eq!(sp.wheel_speed, 0.0);
            }
            p => panic!("unexpected {p:?}"),
        }
    }
}

#[test]
fn a_platform_away_from_the_trajectory_start_is_refused_before_it_moves() {
    let mut opts = RunOptions::new(Scenario::Seed000);
    // The simulated legs sit at their nominal 0.465 m; seed 000 starts at 0.37 m.
    opts.start_at_reference = false;
    let out = run(&opts);
    assert_eq!(out.summary.final_state, "fault");
    let fault = out
        .records
        .iter()
        .find(|r| r.state == SupervisorState::Fault)
        .expect("faulted");
    match fault.reason {
        Some(rollbase_control::supervisor::FaultReason::StartMismatch {
            measured,
            expected,
            ..
        }) => {
            assert!((measured - 0.465).abs() < 1e-3 && (expected - 0.37).abs() < 1e-9);
        }
        r => panic!("unexpected {r:?}"),
    }
    // Refused within the first cycles, and no wheel ever rolled.
    assert!(fault.cycle < 10, "refused at cycle {}", fault.cycle);
    assert!(out
        .records
        .iter()
        .all(|r| r.command.wheels[..r.n].iter().all(|w| w.wheel_speed == 0.0)));
}

#[test]
fn seed000_dfl_tracks_through_the_full_frame_path() {
    assert_tracks_seed000(ControllerKind::Dfl);
}

#[test]
fn seed000_kinematic_tracks_through_the_full_frame_path() {
    assert_tracks_seed000(ControllerKind::Kinematic);
}

#[test]
fn seed001_avoidance_keeps_steering_rates_within_limits() {
    let out = run(&RunOptions::new(Scenario::Seed001));
    let s = &out.summary;
    println!("seed001: {}", s.to_json());
    assert_eq!(s.final_state, "stopped", "{:?}", s.fault_reason);
    let lim = out.platform.limits.steer_rate;
    for r in &out.records {
        for w in &r.command.wheels[..r.n] {
            assert!(
                w.steer_rate.abs() <= lim + 1e-9,
                "cycle {}: steer rate {}",
                r.cycle,
                w.steer_rate
            );
        }
    }
    assert!(s.max_steer_rate_rad_s > 0.0);
}

#[test]
fn operator_stop_is_a_controlled_stop() {
    let mut opts = RunOptions::new(Scenario::Seed000);
    // Mid-trajectory, at speed (alignment takes well under 2 s).
    let stop_cycle = 250 * 12;
    opts.stop_at_cycle = Some(stop_cycle);
    let out = run(&opts);
    assert_eq!(out.summary.final_state, "stopped");
    assert!(out.summary.fault_reason.is_none());
    let p = &out.platform;
    let dt = p.dt();
    let mut stopping_seen = false;
    for pair in out.records.windows(2) {
        let (a, b) = (&pair[0], &pair[1]);
        if b.state == SupervisorState::Stopping {
            stopping_seen = true;
            for i in 0..b.n {
                let dv = (b.command.wheels[i].wheel_speed - a.command.wheels[i].wheel_speed).abs();
                assert!(
                    dv <= p.limits.wheel_accel * dt + 1e-9,
                    "deceleration within the limit"
                );
                // The steering winds down within its acceleration limit, then holds.
                let (s0, s1) = (
                    a.command.wheels[i].steer_rate,
                    b.command.wheels[i].steer_rate,
                );
                assert!(
                    s1.abs() <= s0.abs() && (s1 - s0).abs() <= p.limits.steer_accel * dt + 1e-9,
                    "steering winds down while stopping: {s0} → {s1}"
                );
            }
        }
    }
    assert!(stopping_seen);
    let first_stop = out
        .records
        .iter()
        .find(|r| r.cycle >= stop_cycle)
        .expect("cycle");
    assert_eq!(first_stop.state, SupervisorState::Stopping);
    // Stopped well before the trajectory's end (31 s).
    let stopped_at = out
        .records
        .iter()
        .find(|r| r.state == SupervisorState::Stopped)
        .expect("stopped")
        .cycle;
    assert!(
        stopped_at < stop_cycle + 250,
        "stopped within 1 s of the request"
    );
}
