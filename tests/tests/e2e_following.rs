//! Following-error supervision and the arrival check (issue 19, finding 2), through the
//! whole stack in lockstep on both wire profiles: motors that never respond must fault the
//! run (they used to let it end in Stopped, 6.4 m and 180° from the goal), and a run that
//! does not arrive must fail.

use rollbase_control::reference::trajectory::Waypoint;
use rollbase_control::runtime::scenario::Scenario;
use rollbase_control::supervisor::FaultReason;
use rollbase_control::ZVec;
use rollbase_tests::{assert_controlled_stop_from, run, RunOptions};

/// Motors that never respond (the plant's drive time constant 1e300 s): a following-error
/// fault naming a wheel and its rolling drive's node, a controlled stop, the run ends in
/// Fault, long before the trajectory's end.
#[test]
fn motors_that_never_respond_are_a_following_error_on_both_profiles() {
    for cia in [false, true] {
        let mut o = RunOptions::new(Scenario::Seed000);
        if cia {
            o = o.cia402();
        }
        o.plant.drive_time_constant = 1e300;
        let out = run(&o);
        let s = &out.summary;
        assert_eq!(s.final_state, "fault", "cia402 {cia}: {:?}", s.fault_reason);
        let reason = s.fault_reason.clone().unwrap_or_default();
        assert!(
            reason.starts_with("following error: wheel")
                && reason.contains("wheel speed measured")
                && reason.contains("was commanded"),
            "cia402 {cia}: {reason}"
        );
        let first = out
            .records
            .iter()
            .find(|r| r.state == rollbase_control::supervisor::SupervisorState::Fault)
            .expect("a fault record");
        match first.reason {
            Some(FaultReason::FollowingError {
                wheel,
                node,
                commanded,
                measured,
                duration,
                ..
            }) => {
                // The node is the wheel's rolling drive: the module (native) or 2i+1 (CiA 402).
                let drive = if cia {
                    2 * wheel as u8 + 1
                } else {
                    wheel as u8 + 1
                };
                assert_eq!(node, drive, "cia402 {cia}");
                assert!(measured.abs() < 0.05 && commanded.abs() > 1.0);
                assert!(duration > 0.2 && duration < 0.25, "{duration}");
            }
            r => panic!("cia402 {cia}: {r:?}"),
        }
        assert!(first.t < 3.0, "fault at {} s", first.t);
        assert_controlled_stop_from(&out, first.cycle);
    }
}

/// A short move (0.5 m in 4 s) with every motor dead and the following-error check switched
/// off: the trajectory runs out with the platform where it started, and the arrival check
/// fails the run, naming how far it is from the goal.
#[test]
fn a_run_that_does_not_arrive_ends_in_fault() {
    let wp = |t: f64, x: f64| {
        let mut z = ZVec::zeros();
        z[0] = x;
        for i in 0..4 {
            z[3 + i] = 0.45;
        }
        Waypoint { t, z }
    };
    let mut o = RunOptions::new(Scenario::Seed000);
    o.waypoints = Some(vec![wp(0.0, 0.0), wp(4.0, 0.5)]);
    o.plant.drive_time_constant = 1e300;
    o.runtime.supervisor.follow_timeout = f64::INFINITY;
    let out = run(&o);
    let s = &out.summary;
    assert_eq!(s.final_state, "fault", "{:?}", s.fault_reason);
    match out.records.last().and_then(|r| r.reason) {
        Some(FaultReason::NotArrived { distance, .. }) => {
            assert!((distance - 0.5).abs() < 0.01, "distance {distance}")
        }
        r => panic!("expected 'did not arrive', got {r:?}"),
    }
    assert!(
        s.fault_reason
            .as_deref()
            .is_some_and(|r| r.starts_with("did not arrive") && r.contains("0.500 m")),
        "{:?}",
        s.fault_reason
    );
    // The same short move with healthy motors arrives: Stopped, no fault.
    let mut o = RunOptions::new(Scenario::Seed000);
    o.waypoints = Some(vec![wp(0.0, 0.0), wp(4.0, 0.5)]);
    let out = run(&o);
    assert_eq!(
        out.summary.final_state, "stopped",
        "{:?}",
        out.summary.fault_reason
    );
}
