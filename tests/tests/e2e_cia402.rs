//! The CiA 402 profile end to end, on virtual time: the controller's CANopen master boots,
//! configures and drives the simulated CiA 402 drives and CiA 406 leg encoders through the
//! full frame path (SDO, NMT, SYNC, PDOs, heartbeats, EMCY), with the simulator's frames
//! serialized on a 1 Mbit/s bus.

use rollbase_control::reference::trajectory::Waypoint;
use rollbase_control::runtime::record::CycleRecord;
use rollbase_control::runtime::scenario::Scenario;
use rollbase_control::runtime::{lockstep_cycle, LockstepState, StepHooks};
use rollbase_control::supervisor::{FaultReason, SupervisorState};
use rollbase_control::{Platform, ZVec};
use rollbase_driver::canopen::config::Role;
use rollbase_driver::canopen::master::{BootError, DeviceFault};
use rollbase_driver::canopen::{ds402, pdo};
use rollbase_driver::frame::CanFrame;
use rollbase_tests::{
    assert_controlled_stop_from, assert_seed000_bounds, build, run, RunOptions, RunOutcome,
    AFTER_END,
};
use rollbase_vcan_sim::faults::{MotorFault, Silent};

fn first_fault(out: &RunOutcome) -> &CycleRecord {
    out.records
        .iter()
        .find(|r| r.state == SupervisorState::Fault)
        .expect("the supervisor faulted")
}

fn frame(f: &rollbase_control::runtime::record::FrameRecord) -> CanFrame {
    CanFrame::new(f.id, &f.data[..usize::from(f.len)]).expect("recorded frames are valid")
}

#[test]
fn seed000_dfl_tracks_through_the_cia402_profile_within_the_native_bounds() {
    let out = run(&RunOptions::new(Scenario::Seed000).cia402());
    println!("cia402 dfl: {}", out.summary.to_json());
    assert_seed000_bounds(&out);

    // Boot: every device reset, configured and started by the cycle the supervisor armed in
    // (the last NMT start goes out at that cycle's start).
    let armed = out
        .records
        .iter()
        .position(|r| r.state != SupervisorState::Idle)
        .expect("armed");
    let boot: Vec<&CycleRecord> = out.records[..=armed].iter().collect();
    let tx = |pred: &dyn Fn(&CanFrame) -> bool| -> Vec<CanFrame> {
        boot.iter()
            .flat_map(|r| r.tx[..r.n_tx].iter().map(frame))
            .filter(|f| pred(f))
            .collect()
    };
    let mut reset: Vec<u8> = tx(&|f| f.id() == 0 && f.data()[0] == 0x82)
        .iter()
        .map(|f| f.data()[1])
        .collect();
    reset.sort();
    assert_eq!(reset, (1..=12).collect::<Vec<u8>>(), "reset communication");
    let mut started: Vec<u8> = tx(&|f| f.id() == 0 && f.data()[0] == 0x01)
        .iter()
        .map(|f| f.data()[1])
        .collect();
    started.sort();
    assert_eq!(started, (1..=12).collect::<Vec<u8>>(), "NMT start");
    // Each drive was put into cyclic synchronous velocity mode by SDO (2F 60 60 00 09).
    let csv =
        tx(&|f| (0x601..=0x608).contains(&f.id()) && f.data()[..5] == [0x2F, 0x60, 0x60, 0, 9]);
    assert_eq!(csv.len(), 8);
    // The only SDO aborts are "object does not exist" for the optional steps the devices
    // lack (the encoders' TPDO3/4, the rolling drives' gear ratio 0x6091), each skipped and
    // reported by the master.
    let aborts: Vec<(u16, u16, u8, u32)> = boot
        .iter()
        .flat_map(|r| r.rx[..r.n_rx].iter())
        .filter(|f| (0x581..=0x58C).contains(&f.id) && f.data[0] == 0x80)
        .map(|f| {
            let d = f.data;
            (
                f.id - 0x580,
                u16::from_le_bytes([d[1], d[2]]),
                d[3],
                u32::from_le_bytes([d[4], d[5], d[6], d[7]]),
            )
        })
        .collect();
    assert_eq!(aborts.len(), 16, "{aborts:?}");
    assert!(aborts.iter().all(|a| a.3 == 0x0602_0000), "{aborts:?}");
    for a in &aborts {
        let skipped = out
            .final_skipped
            .iter()
            .any(|(n, ix, sub)| *n == a.0 as u8 && *ix == a.1 && *sub == a.2);
        assert!(skipped, "{a:?} not reported as skipped");
    }
    // Boot and configuration end with the last NMT start; the arm follows once every
    // steering drive is homed and turned to its rest angle.
    let configured = boot
        .iter()
        .rposition(|r| {
            r.tx[..r.n_tx]
                .iter()
                .any(|f| f.id == 0 && f.len == 2 && f.data[0] == 0x01)
        })
        .expect("NMT start");
    println!(
        "boot: configured in {configured} cycles ({} ms), armed after {armed} cycles ({} ms, homing included)",
        configured * 4,
        armed * 4
    );
    assert!(
        configured < 50,
        "boot and configuration took {configured} cycles"
    );

    // Steady state while tracking: per cycle one SYNC and one RPDO1 per drive out, one
    // TPDO1 per device in.
    for r in out
        .records
        .iter()
        .filter(|r| r.state == SupervisorState::Tracking)
    {
        let txs: Vec<CanFrame> = r.tx[..r.n_tx].iter().map(frame).collect();
        assert_eq!(txs[0].id(), 0x080, "SYNC first");
        let rpdos = txs
            .iter()
            .filter(|f| (0x201..=0x208).contains(&f.id()))
            .count();
        assert_eq!(rpdos, 8, "cycle {}", r.cycle);
        let tpdo1 = r.rx[..r.n_rx]
            .iter()
            .filter(|f| (0x181..=0x18C).contains(&f.id) && f.t >= r.t)
            .count();
        assert_eq!(tpdo1, 12, "cycle {}", r.cycle);
    }

    // The run ends with the drives told to shut down (two cycles: a synchronous RPDO acts at
    // the next SYNC), with zero targets, and the simulated drives end disabled (not in a
    // communication-loss fault when the controller goes away).
    let n = out.records.len();
    for r in &out.records[n - 2..] {
        for f in r.tx[..r.n_tx].iter().map(frame) {
            if (0x201..=0x208).contains(&f.id()) {
                let v = pdo::DRIVE_RPDO1.unpack(&f).unwrap();
                assert_eq!(v[0], u32::from(ds402::CW_SHUTDOWN), "cycle {}", r.cycle);
                assert_eq!(v[1], 0);
            }
        }
    }
    // The last cycle hands every device back (NMT reset communication): they boot again,
    // stop monitoring the master, and no communication-loss EMCY follows once it is gone.
    let last: Vec<CanFrame> = out.records[n - 1].tx[..out.records[n - 1].n_tx]
        .iter()
        .map(frame)
        .collect();
    let mut released: Vec<u8> = last
        .iter()
        .filter(|f| f.id() == 0 && f.data()[0] == 0x82)
        .map(|f| f.data()[1])
        .collect();
    released.sort();
    assert_eq!(released, (1..=12).collect::<Vec<u8>>(), "released");
    let mut boot_ups: Vec<u16> = out
        .after_end
        .iter()
        .filter(|f| (0x701..=0x70C).contains(&f.id()) && f.data() == [0])
        .map(|f| f.id() - 0x700)
        .collect();
    boot_ups.sort();
    assert_eq!(boot_ups, (1..=12).collect::<Vec<u16>>());
    let emcy: Vec<&CanFrame> = out
        .after_end
        .iter()
        .filter(|f| (0x081..=0x0FF).contains(&f.id()))
        .collect();
    assert!(emcy.is_empty(), "EMCY after the end: {emcy:?}");
    let drives = &out.final_drive_states;
    assert_eq!(drives.len(), 8);
    for (node, state) in drives {
        // Told to shut down, and a reset communication leaves that state alone.
        assert_eq!(
            *state,
            ds402::State::ReadyToSwitchOn,
            "drive {node} {AFTER_END:?} after the end"
        );
    }
}

/// 1 % of the frames lost, both ways: no drive is taken as lost. With heartbeats every
/// 100 ms and a 300 ms consumer time, two heartbeats of one device lost in a row happened at
/// 4.3 s here, and the master judged the silence at the start of the cycle in which the
/// third was read: a heartbeat fault and a controlled stop on healthy drives (fault-campaign
/// case 32 on main before bd6249b).
#[test]
fn seed000_at_one_percent_frame_loss_completes_without_a_fault() {
    let mut opts = RunOptions::new(Scenario::Seed000).cia402();
    opts.bus_faults.drop_prob = 0.01;
    let out = run(&opts);
    println!("cia402 at 1 % loss: {}", out.summary.to_json());
    assert_seed000_bounds(&out);
}

#[test]
fn seed000_kinematic_tracks_through_the_cia402_profile() {
    let opts = RunOptions::new(Scenario::Seed000)
        .with_controller(rollbase_control::runtime::ControllerKind::Kinematic)
        .cia402();
    let out = run(&opts);
    println!("cia402 kinematic: {}", out.summary.to_json());
    assert_seed000_bounds(&out);
}

#[test]
fn a_drive_fault_is_reported_by_emcy_naming_the_device_and_stops_the_platform() {
    let mut opts = RunOptions::new(Scenario::Seed000).cia402();
    // Wheel 2's steering drive (node 4) over-currents mid-trajectory.
    opts.faults
        .motor_fault
        .push(MotorFault { node: 4, at: 10.0 });
    let out = run(&opts);
    let fault = first_fault(&out);
    assert!(
        fault.t >= 10.0 && fault.t < 10.02,
        "faulted at {} s",
        fault.t
    );
    match fault.reason {
        Some(FaultReason::DeviceFault {
            wheel: 1,
            node: 4,
            role: Role::Steer,
            fault: DeviceFault::Emcy { code: 0x2310, .. },
        }) => {}
        r => panic!("unexpected reason {r:?}"),
    }
    let text = fault.reason.unwrap().to_string();
    assert!(text.contains("wheel 2 steering drive (node 4)"), "{text}");
    assert!(text.contains("0x2310"), "{text}");
    // The master read the drive's error code (0x603F) back into the fault a few cycles later.
    let end = out
        .records
        .last()
        .expect("records")
        .reason
        .expect("reason")
        .to_string();
    assert!(end.contains("error code 0x603F reads 0x2310"), "{end}");
    // Controlled stop within the wheel acceleration limit, the steering winding down within
    // its own, latched.
    assert_controlled_stop_from(&out, fault.cycle);
    assert_eq!(out.summary.final_state, "fault");
}

#[test]
fn a_silent_leg_encoder_is_stale_feedback_naming_its_node() {
    let mut opts = RunOptions::new(Scenario::Seed000).cia402();
    opts.faults.silent.push(Silent {
        node: 10,
        from: 10.0,
        to: 30.0,
    });
    let out = run(&opts);
    let fault = first_fault(&out);
    match fault.reason {
        Some(FaultReason::StaleFeedback {
            wheel: 1, node: 10, ..
        }) => {}
        r => panic!("unexpected reason {r:?}"),
    }
    // The leg stream is the wheel's oldest value: the data-age bound (8 cycles) trips.
    assert!(
        fault.t > 10.0 && fault.t < 10.0 + 10.0 * 0.004,
        "faulted at {} s",
        fault.t
    );
}

#[test]
fn a_device_that_never_boots_fails_the_boot_naming_it_and_nothing_moves() {
    let mut opts = RunOptions::new(Scenario::Seed000).cia402();
    opts.faults.silent.push(Silent {
        node: 7,
        from: 0.0,
        to: 1000.0,
    });
    opts.slack_s = 0.0;
    let out = run(&opts);
    let fault = first_fault(&out);
    match fault.reason {
        Some(FaultReason::DeviceFault {
            wheel: 3,
            node: 7,
            role: Role::Drive,
            fault: DeviceFault::Boot(BootError::NoBootUp { ms: 2000, .. }),
        }) => {}
        r => panic!("unexpected reason {r:?}"),
    }
    // The boot timeout is 2 s from the NMT reset.
    assert!((fault.t - 2.0).abs() < 0.01, "faulted at {} s", fault.t);
    assert!(out.records.iter().all(|r| r.command.wheels[..r.n]
        .iter()
        .all(|w| w.wheel_speed == 0.0 && w.steer_rate == 0.0)));
    assert!(out.records.iter().all(|r| !r.enable));
}

#[test]
fn an_encoder_configured_differently_from_the_platform_file_is_refused_at_boot() {
    let mut opts = RunOptions::new(Scenario::Seed000).cia402();
    // The machine's encoders count 500 nm steps; the controller's platform file says 1000.
    let mut machine = Platform::justin();
    let mut c = machine.cia402();
    c.leg_encoder.position_step_nm = 500;
    machine.cia402 = Some(c);
    opts.sim_platform = Some(machine);
    opts.slack_s = 0.0;
    let out = run(&opts);
    let fault = first_fault(&out);
    match fault.reason {
        Some(FaultReason::DeviceFault {
            node,
            role: Role::Leg,
            fault:
                DeviceFault::Boot(BootError::Mismatch {
                    index: 0x6005,
                    sub: 1,
                    got: 500,
                    expected: 1000,
                    ..
                }),
            ..
        }) => assert!((9..=12).contains(&node)),
        r => panic!("unexpected reason {r:?}"),
    }
    assert!(fault.t < 0.2, "refused at {} s", fault.t);
    assert!(out.records.iter().all(|r| !r.enable));
}

/// The controller dies mid-trajectory (no SYNC, no RPDO, no heartbeat): the drives' own
/// supervision (RPDO deadline 50 ms, heartbeat consumer 60 ms) must stop the wheels, and the
/// controller that comes back must see why and not move.
#[test]
fn drives_stop_on_their_own_when_the_master_dies_and_report_it() {
    let opts = RunOptions::new(Scenario::Seed000).cia402();
    let (mut core, mut sim, mut bus, _) = build(&opts).expect("setup");
    let mut st = LockstepState::new(&core);
    core.arm();
    let dead_from = 2500u64; // 10 s: tracking at speed
    let dead_cycles = 50u64; // 200 ms
    let mut max_speed_at_death = 0.0f64;
    let mut speed_after = Vec::new();
    let mut records = Vec::new();
    for k in 0..dead_from + dead_cycles + 500 {
        let dead = (dead_from..dead_from + dead_cycles).contains(&k);
        let mut hooks = StepHooks {
            controller_silent: dead,
            ..Default::default()
        };
        if lockstep_cycle(&mut st, &mut core, &mut bus, &mut sim, &mut hooks) {
            records.push(*core.record());
        }
        let truth = sim.truth();
        let w = truth.wheel_speed[..truth.n]
            .iter()
            .fold(0.0f64, |a, b| a.max(b.abs()));
        if k + 1 == dead_from {
            max_speed_at_death = w;
        }
        if dead {
            speed_after.push((k - dead_from, w));
        }
    }
    assert!(
        max_speed_at_death > 1.0,
        "wheels turning at the death: {max_speed_at_death}"
    );
    // Within 50 ms (RPDO deadline) + 2 cycles of the last RPDO the drives fault, and with
    // their power stage off the wheels decelerate at the torque limit: well below their speed
    // at the death 100 ms later, at rest within the 200 ms.
    let at = |ms: u64| speed_after[(ms / 4) as usize].1;
    assert!(
        at(40) > 0.5 * max_speed_at_death,
        "still driven before the deadline"
    );
    assert!(
        at(120) < 0.5 * max_speed_at_death,
        "{} rad/s at 120 ms",
        at(120)
    );
    assert!(at(196) < 1e-6, "{} rad/s at 196 ms", at(196));
    // Every drive noticed on its own: an RPDO deadline or heartbeat-consumer timeout, EMCY
    // sent, and the 0x6007 reaction (fault) taken.
    for d in sim.devices().iter().filter(|d| d.role() != Role::Leg) {
        let st = d.stats();
        assert!(
            st.rpdo_timeouts + st.heartbeat_timeouts >= 1 && st.emcy_sent >= 1,
            "drive {}: {st:?}",
            d.node()
        );
        assert!(
            d.state402().is_fault(),
            "drive {}: {}",
            d.node(),
            d.state402()
        );
    }
    // The controller back: its receive queue was lost while it was dead (so were the EMCYs),
    // but it faults at once and never commands motion again.
    let back: Vec<&CycleRecord> = records.iter().filter(|r| r.cycle >= dead_from).collect();
    let fault = back
        .iter()
        .find(|r| r.state == SupervisorState::Fault)
        .expect("faulted after the master came back");
    // The core's cycle counter does not run while it is dead: it resumes at `dead_from`.
    // It knows its own heartbeat stopped for longer than the drives' consumer time: faulted
    // in the first cycle back.
    assert_eq!(fault.cycle, dead_from, "faulted at cycle {}", fault.cycle);
    match fault.reason {
        Some(FaultReason::DeviceFault {
            fault: DeviceFault::MasterSilent { ms, timeout_ms: 60 },
            ..
        }) => assert!((200..=208).contains(&ms), "silent {ms} ms"),
        r => panic!("unexpected reason {r:?}"),
    }
    // From the fault on: a controlled stop, every wheel's command only decreasing.
    let after: Vec<&&CycleRecord> = back.iter().filter(|r| r.cycle >= fault.cycle).collect();
    for pair in after.windows(2) {
        for i in 0..pair[1].n {
            assert!(
                pair[1].command.wheels[i].wheel_speed.abs()
                    <= pair[0].command.wheels[i].wheel_speed.abs() + 1e-12
            );
        }
    }
    assert_eq!(records.last().unwrap().state, SupervisorState::Fault);
}

/// After a crash (the drives faulted on their own, as above) a new controller process takes
/// over the same bus: it resets and configures every device again, clears the drives'
/// communication-loss faults with the fault reset of arming, homes every steering drive
/// again (a new master cannot know where their counters stand), and drives the platform
/// again.
#[test]
fn a_restarted_controller_clears_the_communication_loss_faults_and_drives_again() {
    let opts = RunOptions::new(Scenario::Seed000).cia402();
    let (mut core, mut sim, mut bus, _) = build(&opts).expect("setup");
    let mut st = LockstepState::new(&core);
    core.arm();
    let crash = 1500u64; // 6 s: tracking
    for k in 0..crash + 50 {
        let mut hooks = StepHooks {
            controller_silent: k >= crash,
            ..Default::default()
        };
        lockstep_cycle(&mut st, &mut core, &mut bus, &mut sim, &mut hooks);
    }
    let drives = |sim: &rollbase_vcan_sim::Simulator| -> Vec<ds402::State> {
        sim.devices()
            .iter()
            .filter(|d| d.role() != Role::Leg)
            .map(|d| d.state402())
            .collect()
    };
    assert!(
        drives(&sim).iter().all(|s| s.is_fault()),
        "{:?}",
        drives(&sim)
    );

    // The new process: a fresh core (new master, odometry from its own origin) on the same
    // bus and clock, with a trajectory from where the platform stopped: 0.5 m ahead in 4 s,
    // legs where they are.
    let legs = sim.truth().legs;
    let mut a = ZVec::zeros();
    for i in 0..4 {
        a[3 + i] = legs[i];
    }
    let mut b = a;
    b[0] = 0.5;
    let mut opts2 = opts.clone();
    opts2.waypoints = Some(vec![Waypoint { t: 0.0, z: a }, Waypoint { t: 4.0, z: b }]);
    let (mut core, _, _, _) = build(&opts2).expect("setup");
    core.arm();
    let mut records = Vec::new();
    let mut tracking_since = None;
    for k in 0..4000 {
        lockstep_cycle(
            &mut st,
            &mut core,
            &mut bus,
            &mut sim,
            &mut StepHooks::default(),
        );
        records.push(*core.record());
        if core.state() == SupervisorState::Tracking {
            tracking_since.get_or_insert(k);
        }
        if tracking_since.is_some_and(|s| k > s + 500) {
            break;
        }
    }
    let states: Vec<SupervisorState> = records.iter().map(|r| r.state).collect();
    assert!(
        !states.contains(&SupervisorState::Fault),
        "{:?}",
        records.iter().find_map(|r| r.reason)
    );
    let tracking = records
        .iter()
        .position(|r| r.state == SupervisorState::Tracking)
        .expect("tracking again");
    println!("restart: tracking {tracking} cycles after the new process armed");
    // Boot, fault reset, homing (each steering axis turns to its switch at 0.5 rad/s, at
    // most half a turn: 6.3 s) and the turn to the rest angles.
    assert!(tracking < 2000, "tracking after {tracking} cycles");
    assert!(drives(&sim)
        .iter()
        .all(|s| *s == ds402::State::OperationEnabled));
    // Each drive acknowledged its fault reset with EMCY 0x0000 after the restart.
    let resets = records
        .iter()
        .flat_map(|r| r.rx[..r.n_rx].iter())
        .filter(|f| (0x081..=0x088).contains(&f.id) && f.len == 8 && f.data[..2] == [0, 0])
        .count();
    assert_eq!(resets, 8);
    let truth = sim.truth();
    let moving = truth.wheel_speed[..truth.n]
        .iter()
        .fold(0.0f64, |a, b| a.max(b.abs()));
    assert!(moving > 0.1, "wheels at {moving} rad/s");
}

/// Feedback cut mid-run (a leg encoder falls silent): the host cannot close its ramp on what
/// the drives do, so the master sends every enabled drive the Quick Stop command (controlword
/// 0x0002) and keeps sending it; each drive enters quick stop active and stops on its own
/// quick-stop ramp (0x6085, written at boot), then (option 2) switches on disabled; none is
/// enabled again.
#[test]
fn lost_feedback_quick_stops_every_drive_on_its_own_ramp() {
    let mut opts = RunOptions::new(Scenario::Seed000).cia402();
    opts.faults.silent.push(Silent {
        node: 10,
        from: 10.0,
        to: 30.0,
    });
    let out = run(&opts);
    let k = out
        .records
        .iter()
        .position(|r| r.state == SupervisorState::Fault)
        .expect("faulted");
    assert!(matches!(
        out.records[k].reason,
        Some(FaultReason::StaleFeedback { node: 10, .. })
    ));
    let rpdo = |r: &CycleRecord, node: u16| -> Option<(u16, i32)> {
        r.tx[..r.n_tx]
            .iter()
            .map(frame)
            .find(|f| f.id() == 0x200 + node)
            .map(|f| {
                let v = pdo::DRIVE_RPDO1.unpack(&f).unwrap();
                (v[0] as u16, v[1] as i32)
            })
    };
    // Before the fault every drive was enabled and driven.
    for node in 1..=8 {
        assert_eq!(rpdo(&out.records[k - 1], node).map(|x| x.0), Some(0x0F));
    }
    // The cycle after the fault: Quick Stop with a zero target to every drive.
    for node in 1..=8 {
        assert_eq!(
            rpdo(&out.records[k + 1], node),
            Some((ds402::CW_QUICK_STOP_CMD, 0)),
            "node {node}"
        );
    }
    // Every drive reported quick stop active (its statusword, TPDO2), and none was told to
    // enable operation again for the rest of the run.
    let mut qsa = [false; 9];
    for r in &out.records[k..] {
        for f in r.rx[..r.n_rx].iter() {
            let node = f.id.wrapping_sub(0x280);
            if (1..=8).contains(&node) {
                let sw = u16::from_le_bytes([f.data[0], f.data[1]]);
                if ds402::State::from_statusword(sw) == Some(ds402::State::QuickStopActive) {
                    qsa[usize::from(node)] = true;
                }
            }
        }
        for node in 1..=8 {
            if let Some((cw, target)) = rpdo(r, node) {
                assert_ne!(cw, ds402::CW_ENABLE_OPERATION_CMD, "cycle {}", r.cycle);
                assert_eq!(target, 0);
            }
        }
    }
    assert!(
        qsa[1..].iter().all(|&q| q),
        "quick stop active seen: {qsa:?}"
    );
    // The drives decelerate on their ramp (the default 40 rad/s² at the wheel): the wheels
    // that were rolling are at rest within their speed / 40 s (plus the statusword's and the
    // measurement's delays, 0.1 s).
    let n = out.records[k].n;
    let w0 = out.records[k].measurement.wheels[..n]
        .iter()
        .map(|w| w.wheel_speed.abs())
        .fold(0.0, f64::max);
    assert!(w0 > 0.5, "the base was moving ({w0} rad/s)");
    let at = out.records[k..]
        .iter()
        .find(|r| {
            r.measurement.wheels[..n]
                .iter()
                .all(|w| w.wheel_speed.abs() < 0.05)
        })
        .expect("every wheel at rest before the run ended");
    assert!(
        at.t - out.records[k].t <= w0 / 40.0 + 0.1,
        "at rest only {:.3} s after the quick stop ({w0} rad/s)",
        at.t - out.records[k].t
    );
    // … on a ramp, not a coast or a step: half-way through the ramp time the fastest
    // wheel still turns at more than a quarter of its speed.
    let half = w0 / 40.0 / 2.0;
    let mid = out
        .records
        .iter()
        .find(|r| r.t >= out.records[k].t + half)
        .expect("records");
    let w_mid = mid.measurement.wheels[..n]
        .iter()
        .map(|w| w.wheel_speed.abs())
        .fold(0.0, f64::max);
    println!(
        "quick stop: {w0:.2} rad/s at the fault, {w_mid:.2} rad/s {half:.3} s later, below 0.05 rad/s after {:.3} s",
        at.t - out.records[k].t
    );
    assert!(w_mid > 0.25 * w0, "{w_mid} rad/s half-way: not a ramp");
}

/// A drive whose units are not the ones the platform file converts with is refused at boot,
/// naming the object, the value read and what the file expects: velocity unit 0x60A9
/// (rev/min where the file says increments per second), and an encoder resolution 0x608F
/// counted over two motor revolutions.
#[test]
fn a_drive_whose_units_are_not_the_platform_files_is_refused_at_boot() {
    for (node, index, sub, value, expected, words) in [
        (
            3u8,
            0x60A9u16,
            0u8,
            0x00B4_4700u32,
            0x00B5_0300u32,
            "rev/min",
        ),
        (4, 0x608F, 2, 2, 1, "motor revolutions"),
    ] {
        let mut opts = RunOptions::new(Scenario::Seed000).cia402();
        opts.twin.objects.push((node, index, sub, value));
        opts.slack_s = 0.0;
        let out = run(&opts);
        let fault = first_fault(&out);
        let text = fault.reason.expect("reason").to_string();
        match fault.reason {
            Some(FaultReason::DeviceFault {
                node: n,
                fault:
                    DeviceFault::Boot(BootError::Mismatch {
                        index: i,
                        sub: s,
                        got,
                        expected: e,
                        ..
                    }),
                ..
            }) if n == node && i == index && s == sub => {
                assert_eq!((got, e), (value, expected), "{text}");
            }
            r => panic!("unexpected reason {r:?}"),
        }
        let object = format!("0x{index:04X}:{sub:02X}");
        assert!(
            text.contains(&object)
                && text.contains(words)
                && text.contains(&format!("node {node}")),
            "{text}"
        );
        println!("{text}");
        assert!(fault.t < 0.3, "refused at {} s", fault.t);
        assert!(out.records.iter().all(|r| !r.enable));
    }
}
