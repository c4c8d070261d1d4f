//! Bus-off of the controller's CAN interface, on virtual time, both wire profiles (issue 24):
//! the simulator's fault schedule holds the controller's interface bus-off for half a second
//! while the base drives at speed (`[[controller_bus_off]]`: the virtual bus hands the
//! controller the bus-off error frame, its sends fail, nothing reaches it, then it is
//! restarted as the kernel's `restart-ms` would). The supervisor faults naming the bus-off
//! within a cycle or two; the wheels stop on the modules' and drives' own watchdogs (RPDO and
//! heartbeat timeouts on the CiA 402 twin); nothing moves after the bus is back until the
//! operator re-arms; the re-arm boots the CiA 402 devices again (NMT reset communication,
//! the boot plan's SDOs) and the base tracks again.

use rollbase_control::runtime::record::CycleRecord;
use rollbase_control::service::ports::{CommandEvent, CommandKind};
use rollbase_control::supervisor::{FaultReason, SupervisorState};
use rollbase_control::Protocol;
use rollbase_driver::bus::BusEvent;
use rollbase_tests::{run_live, twist_at, LiveOptions, RunOutcome};
use rollbase_vcan_sim::faults::BusOff;

/// The controller's interface is bus-off in [OFF_AT, OFF_UNTIL) (simulator time, s).
const OFF_AT: f64 = 15.0;
const OFF_UNTIL: f64 = 15.5;
/// The operator re-arms this long after the driver was ready (s): after the bus is back.
const REARM_AFTER_READY: f64 = 20.0;

fn truth_xy(r: &CycleRecord) -> (f64, f64) {
    let (p, _) = r.truth.expect("in-process simulation has truth");
    (p.x, p.y)
}

fn run(profile: Protocol) -> RunOutcome {
    let mut opts = LiveOptions {
        profile,
        max_seconds: 70.0,
        ..LiveOptions::default()
    };
    opts.faults.controller_bus_off.push(BusOff {
        at: OFF_AT,
        until: OFF_UNTIL,
    });
    let mut cmds: Vec<CommandEvent> = Vec::new();
    // A steady drive at 0.3 m/s from the start (the command stream goes on through the
    // fault: ignored until the re-arm).
    let mut t = 0.25;
    while t < REARM_AFTER_READY + 12.0 {
        cmds.push(twist_at(t, 0.3, 0.0, 0.0));
        t += 0.25;
    }
    cmds.push(CommandEvent {
        t: REARM_AFTER_READY,
        kind: CommandKind::Rearm,
    });
    cmds.sort_by(|a, b| a.t.total_cmp(&b.t));
    cmds.push(CommandEvent {
        t: REARM_AFTER_READY + 13.0,
        kind: CommandKind::EndOfStream,
    });
    run_live(&opts, &cmds)
}

fn at(out: &RunOutcome, t: f64) -> usize {
    out.records
        .iter()
        .position(|r| r.t >= t - 1e-9)
        .expect("the run reaches that time")
}

/// What both profiles must show; returns (fault cycle, re-arm cycle).
fn check(out: &RunOutcome, name: &str) -> (usize, usize) {
    let off = at(out, OFF_AT);
    assert_eq!(
        out.records[off - 1].state,
        SupervisorState::Tracking,
        "{name}: tracking when the bus goes off"
    );
    // Fault within two cycles, naming the bus-off.
    let fault = out.records[off..]
        .iter()
        .position(|r| r.state == SupervisorState::Fault)
        .map(|k| k + off)
        .expect("faulted");
    assert!(
        fault - off <= 2,
        "{name}: fault {} cycles after the bus-off",
        fault - off
    );
    let reason = out.records[fault].reason;
    assert_eq!(reason, Some(FaultReason::BusOff { bus: 0 }), "{name}");
    let text = reason.map(|r| r.to_string()).unwrap_or_default();
    for what in ["bus-off", "termination", "bit rate", "babbles", "re-arm"] {
        assert!(text.contains(what), "{name}: {text:?} lacks {what:?}");
    }
    // The fault stays latched until the re-arm (the cycle that took the operator's
    // command), after the bus came back.
    let rearm = out
        .records
        .iter()
        .position(|r| {
            r.commands_in
                .iter()
                .flatten()
                .any(|c| c.kind == CommandKind::Rearm)
        })
        .expect("re-arm taken");
    assert!(out.records[rearm].t > OFF_UNTIL + 1.0);
    assert!(
        out.records[fault..rearm]
            .iter()
            .all(|r| r.state == SupervisorState::Fault),
        "{name}: left Fault before the operator re-armed"
    );
    // The wheels stopped on the devices' own watchdogs while the controller could not speak:
    // the platform is at rest 0.4 s into the bus-off and does not move until the re-arm.
    let rest = at(out, OFF_AT + 0.4);
    let (x0, y0) = truth_xy(&out.records[rest]);
    for r in &out.records[rest..rearm] {
        let (x, y) = truth_xy(r);
        let d = (x - x0).hypot(y - y0);
        assert!(
            d < 1e-3,
            "{name}: the base moved {:.4} m at {:.3} s (bus-off {OFF_AT}–{OFF_UNTIL} s, re-arm at {:.3} s)",
            d,
            r.t,
            out.records[rearm].t
        );
    }
    let (xs, ys) = truth_xy(&out.records[off]);
    println!(
        "{name}: bus-off at {OFF_AT} s, fault after {} cycles, coasted {:.3} m, re-armed at {:.2} s",
        fault - off,
        (x0 - xs).hypot(y0 - ys),
        out.records[rearm].t
    );
    // Tracking again after the re-arm, and the base moves as commanded.
    let back = out.records[rearm..]
        .iter()
        .position(|r| r.state == SupervisorState::Tracking)
        .map(|k| k + rearm)
        .expect("tracking again after the re-arm");
    let end = out.records.len() - 1;
    let (xb, yb) = truth_xy(&out.records[back]);
    let (xe, ye) = truth_xy(&out.records[end]);
    let moved = (xe - xb).hypot(ye - yb);
    assert!(moved > 1.0, "{name}: moved {moved:.3} m after the re-arm");
    // Odometry follows the truth after the re-arm (within 2 % of the travel).
    let (pb, pe) = (out.records[back].pose, out.records[end].pose);
    let odo = (pe.x - pb.x).hypot(pe.y - pb.y);
    assert!(
        (odo - moved).abs() < 0.02 * moved,
        "{name}: odometry {odo:.3} m, truth {moved:.3} m after the re-arm"
    );
    println!(
        "{name}: tracking again at {:.2} s ({:.2} s after the re-arm), moved {moved:.2} m",
        out.records[back].t,
        out.records[back].t - out.records[rearm].t
    );
    // Counted: one bus-off, one restart; shown in the state port's diagnostics.
    let d = out.final_state.expect("state").diagnostics.can[0];
    assert_eq!(d.count(BusEvent::BusOff), 1, "{name}: {d:?}");
    assert_eq!(d.count(BusEvent::Restarted), 1, "{name}: {d:?}");
    assert_eq!(
        out.summary.can[0], d,
        "{name}: the run summary has the same counts"
    );
    let j = out.summary.to_json();
    assert_eq!(j["can_bus"][0]["bus_off"], 1, "{name}: {}", j["can_bus"]);
    assert_eq!(out.summary.final_state, "stopped", "{name}");
    (fault, rearm)
}

#[test]
fn native_bus_off_faults_stops_and_resumes_only_after_re_arm() {
    let out = run(Protocol::Native);
    check(&out, "native");
}

#[test]
fn cia402_bus_off_faults_stops_and_re_boots_every_device_on_re_arm() {
    let out = run(Protocol::Cia402);
    let (fault, rearm) = check(&out, "cia402");
    // Nothing of the boot is sent between the fault and the re-arm (the devices are taken
    // as lost, not booted behind the operator's back); the re-arm resets and boots all 12.
    let nmt_resets = |rs: &[CycleRecord]| -> Vec<u8> {
        let mut v: Vec<u8> = rs
            .iter()
            .flat_map(|r| r.tx[..r.n_tx].iter())
            .filter(|f| f.id == 0 && f.len == 2 && f.data[0] == 0x82)
            .map(|f| f.data[1])
            .collect();
        v.sort();
        v
    };
    let sdo_requests = |rs: &[CycleRecord]| -> usize {
        rs.iter()
            .flat_map(|r| r.tx[..r.n_tx].iter())
            .filter(|f| (0x601..=0x67F).contains(&f.id))
            .count()
    };
    assert!(nmt_resets(&out.records[fault..rearm]).is_empty());
    assert_eq!(sdo_requests(&out.records[fault..rearm]), 0);
    // (Up to tracking again: the clean end of the run resets them all once more.)
    let back = out.records[rearm..]
        .iter()
        .position(|r| r.state == SupervisorState::Tracking)
        .map(|k| k + rearm)
        .expect("tracking again");
    let after = &out.records[rearm..back];
    assert_eq!(
        nmt_resets(after),
        (1..=12).collect::<Vec<u8>>(),
        "NMT reset communication to every device after the re-arm"
    );
    let sdos = sdo_requests(after);
    assert!(sdos >= 12 * 10, "{sdos} SDO requests after the re-arm");
    println!("cia402: re-arm booted 12 devices again ({sdos} SDO requests)");
}

/// Warning and error-passive reports are counted and shown, once per change of state, and
/// never fault the platform: the bus still carries every frame.
#[test]
fn warning_and_error_passive_are_counted_not_faults() {
    use rollbase_control::runtime::{lockstep_cycle, LockstepState, StepHooks};
    let (mut core, mut sim, mut bus) = rollbase_tests::build_live(&LiveOptions::default());
    core.arm();
    let mut st = LockstepState::new(&core);
    let mut step = |core: &mut rollbase_control::runtime::CycleCore,
                    bus: &mut rollbase_control::runtime::VirtualLockstepBus,
                    n: usize| {
        for _ in 0..n {
            lockstep_cycle(&mut st, core, bus, &mut sim, &mut StepHooks::default());
        }
    };
    step(&mut core, &mut bus, 250);
    assert_eq!(core.state(), SupervisorState::Tracking);
    for e in [
        BusEvent::Warning,
        BusEvent::Warning,
        BusEvent::ErrorPassive,
        BusEvent::Warning,
        BusEvent::Active,
    ] {
        bus.bus.inject_event("controller", e);
        step(&mut core, &mut bus, 5);
    }
    step(&mut core, &mut bus, 50);
    let d = core.base_state().diagnostics.can[0];
    // The repeated warning is one state, not two changes.
    assert_eq!(d.count(BusEvent::Warning), 2, "{d:?}");
    assert_eq!(d.count(BusEvent::ErrorPassive), 1, "{d:?}");
    assert_eq!(d.count(BusEvent::Active), 1, "{d:?}");
    assert_eq!(d.count(BusEvent::BusOff), 0, "{d:?}");
    assert_eq!(d.state, Some(BusEvent::Active));
    assert_eq!(
        core.state(),
        SupervisorState::Tracking,
        "{:?}",
        core.supervisor().reason()
    );
}
