//! Fault handling end to end: a silent module and a module fault, on virtual time.

use rollbase_control::scenario::Scenario;
use rollbase_control::supervisor::{FaultReason, SupervisorState};
use rollbase_tests::{assert_controlled_stop_from, run, RunOptions};
use rollbase_vcan_sim::faults::{MotorFault, Silent};

#[test]
fn silent_module_faults_within_three_cycles_of_staleness_and_stays_stopped() {
    let mut opts = RunOptions::new(Scenario::Seed000);
    // Node 3 goes silent at 10 s of simulated time (mid-trajectory) for 2 s, then returns.
    opts.faults.silent.push(Silent {
        node: 3,
        from: 10.0,
        to: 12.0,
    });
    let out = run(&opts);
    let wheel = 2; // node 3 is the third wheel
    let first_stale = out
        .records
        .iter()
        .find(|r| r.t >= 10.0 && r.feedback_age[wheel] > 0)
        .expect("the module went silent");
    let fault = out
        .records
        .iter()
        .find(|r| r.state == SupervisorState::Fault)
        .expect("the supervisor faulted");
    // Stale means more than 3 cycles without feedback: the fault comes on the 4th stale cycle.
    let stale_cycles = fault.cycle - first_stale.cycle + 1;
    assert_eq!(stale_cycles, 4, "fault after {stale_cycles} stale cycles");
    match fault.reason {
        Some(FaultReason::StaleFeedback { node, wheel: w, .. }) => {
            assert_eq!((node, w), (3, wheel));
        }
        r => panic!("unexpected reason {r:?}"),
    }
    // Controlled stop: decelerating within the limit, the steering winding down within its
    // own, then latched.
    assert_controlled_stop_from(&out, fault.cycle);
    // The module came back (feedback fresh again) but the platform stays stopped.
    let last = out.records.last().expect("records");
    assert_eq!(last.state, SupervisorState::Fault);
    assert!(last.command.wheels[..last.n]
        .iter()
        .all(|w| w.wheel_speed == 0.0));
    assert_eq!(out.summary.final_state, "fault");
}

#[test]
fn module_fault_in_status_stops_the_platform_and_names_the_module() {
    let mut opts = RunOptions::new(Scenario::Seed000);
    opts.faults
        .motor_fault
        .push(MotorFault { node: 2, at: 8.0 });
    let out = run(&opts);
    let fault = out
        .records
        .iter()
        .find(|r| r.state == SupervisorState::Fault)
        .expect("the supervisor faulted");
    assert!(
        fault.t >= 8.0 && fault.t < 8.0 + 0.2,
        "detected at {} s",
        fault.t
    );
    match fault.reason {
        Some(FaultReason::ModuleFault { node, .. }) => assert_eq!(node, 2),
        r => panic!("unexpected reason {r:?}"),
    }
    assert_eq!(out.summary.final_state, "fault");
}
