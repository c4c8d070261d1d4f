//! Simulator-level tests: a full SYNC → feedback → setpoint cycle, the watchdog acting on the
//! plant, and every fault kind appearing on the bus as specified, reproducibly for a seed.

use rollbase_control::Platform;
use rollbase_driver::codec::{
    decode, encode, FeedbackA, Message, ModuleState, Payload, Setpoint, SetpointFlags, Status,
    Sync, FAULT_OVERCURRENT, FAULT_WATCHDOG,
};
use rollbase_driver::frame::CanFrame;
use rollbase_driver::protocol::{classify, MessageKind};
use rollbase_vcan_sim::faults::{BusOff, EncoderJump, EncoderStuck, MotorFault, Silent};
use rollbase_vcan_sim::{FaultSchedule, PlantConfig, SimConfig, Simulator};
use std::time::Duration;

fn us(t: u64) -> Duration {
    Duration::from_micros(t)
}

fn ms(t: u64) -> Duration {
    Duration::from_millis(t)
}

fn sync_frame(cycle: u16) -> CanFrame {
    encode(&Message {
        node: 0,
        counter: (cycle % 16) as u8,
        payload: Payload::Sync(Sync { cycle }),
    })
    .unwrap()
}

fn setpoint_frame(node: u8, counter: u8, w: f64, steer: f64, enable: bool) -> CanFrame {
    encode(&Message {
        node,
        counter,
        payload: Payload::Setpoint(Setpoint {
            wheel_speed: w,
            steer_rate: steer,
            flags: SetpointFlags {
                enable,
                brake: false,
                fault_reset: false,
            },
        }),
    })
    .unwrap()
}

/// A minimal 250 Hz controller: SYNC at 4k ms, setpoints for every node at 4k + 1 ms
/// (until `setpoints_until`), collecting everything the simulator transmits.
struct Run {
    sim: Simulator,
    frames: Vec<(Duration, CanFrame)>,
}

fn run(schedule: FaultSchedule, seed: u64, cycles: u16, setpoints_until: Duration, w: f64) -> Run {
    let cfg = SimConfig {
        faults: schedule,
        seed,
        ..SimConfig::default()
    };
    let mut sim = Simulator::with_config(&Platform::justin(), cfg).unwrap();
    let mut frames = Vec::new();
    let nodes: Vec<u8> = sim.nodes().to_vec();
    for k in 0..cycles {
        let t = ms(4 * u64::from(k));
        sim.on_frame(t, &sync_frame(k));
        let tsp = t + ms(1);
        if tsp < setpoints_until {
            for &n in &nodes {
                sim.on_frame(tsp, &setpoint_frame(n, (k % 16) as u8, w, 0.2, true));
            }
        } else {
            sim.advance_to(tsp);
        }
        sim.drain_tx(&mut |at, f| frames.push((at, f)));
    }
    sim.advance_to(ms(4 * u64::from(cycles)));
    sim.drain_tx(&mut |at, f| frames.push((at, f)));
    Run { sim, frames }
}

fn kind_node(f: &CanFrame) -> (MessageKind, u8) {
    classify(f.id()).expect("protocol id")
}

#[test]
fn full_cycle_sync_feedback_setpoint_applied_next_substep() {
    let cfg = SimConfig {
        plant: PlantConfig::ideal(),
        ..SimConfig::default()
    };
    let mut sim = Simulator::with_config(&Platform::justin(), cfg).unwrap();
    sim.on_frame(ms(0), &sync_frame(0));
    let mut out = Vec::new();
    sim.drain_tx(&mut |at, f| out.push((at, f)));
    // Four STATUS (Boot → Ready) at t = 0 and eight feedback frames at t + 0.3 ms.
    let fb: Vec<_> = out
        .iter()
        .filter(|(_, f)| {
            matches!(
                kind_node(f).0,
                MessageKind::FeedbackA | MessageKind::FeedbackB
            )
        })
        .collect();
    assert_eq!(fb.len(), 8);
    assert!(fb.iter().all(|(at, _)| *at == us(300)));
    for node in 1..=4u8 {
        assert!(fb.iter().any(|(_, f)| f.id() == 0x180 + u16::from(node)));
        assert!(fb.iter().any(|(_, f)| f.id() == 0x280 + u16::from(node)));
    }
    let st: Vec<Status> = out
        .iter()
        .filter_map(|(_, f)| match decode(f).unwrap().payload {
            Payload::Status(s) => Some(s),
            _ => None,
        })
        .collect();
    assert_eq!(st.len(), 4);
    assert!(st.iter().all(|s| s.state == ModuleState::Ready));
    // The plant steps on a 1 ms grid: a setpoint received at 1.5 ms acts from the sub-step
    // starting at 2 ms (never on the sub-step already in progress).
    for n in 1..=4u8 {
        sim.on_frame(us(1500), &setpoint_frame(n, 0, 5.0, 0.0, true));
    }
    assert_eq!(sim.module_states()[0], ModuleState::Enabled);
    sim.advance_to(ms(2));
    assert_eq!(sim.truth().wheel_speed[0], 0.0, "applied too early");
    sim.advance_to(ms(3));
    assert!(
        sim.truth().wheel_speed[0] > 0.0,
        "not applied at the next sub-step"
    );
    // Next SYNC reports the motion (latency 0 with the ideal plant).
    sim.on_frame(ms(4), &sync_frame(1));
    let mut out = Vec::new();
    sim.drain_tx(&mut |at, f| out.push((at, f)));
    let a: Vec<FeedbackA> = out
        .iter()
        .filter_map(|(_, f)| match decode(f).unwrap().payload {
            Payload::FeedbackA(a) => Some(a),
            _ => None,
        })
        .collect();
    assert_eq!(a.len(), 4);
    let truth = sim.truth().wheel_speed[0];
    assert!(
        (a[0].wheel_speed - truth).abs() <= 5e-4,
        "{} vs {truth}",
        a[0].wheel_speed
    );
}

#[test]
fn watchdog_stops_the_wheels_after_setpoints_stop() {
    // Setpoints (5 rad/s) until t = 300 ms; SYNC continues.
    let r = run(FaultSchedule::default(), 1, 150, ms(300), 5.0);
    let last_sp = ms(297);
    let mut trip = None;
    for (at, f) in &r.frames {
        if let Ok(Message {
            node: 1,
            payload: Payload::Status(s),
            ..
        }) = decode(f)
        {
            if s.state == ModuleState::Fault && trip.is_none() {
                assert_eq!(s.fault_code, FAULT_WATCHDOG);
                trip = Some(*at);
            }
        }
    }
    let trip = trip.expect("watchdog STATUS on the bus");
    println!(
        "watchdog: STATUS(fault) {:?} after the last valid setpoint",
        trip - last_sp
    );
    assert!(
        trip - last_sp <= ms(50),
        "tripped {:?} after",
        trip - last_sp
    );
    assert_eq!(r.sim.stats().modules[0].watchdog_trips, 1);
    // Re-run stepwise to find when the wheel is at rest.
    let cfg = SimConfig {
        plant: PlantConfig::ideal(),
        ..SimConfig::default()
    };
    let mut sim = Simulator::with_config(&Platform::justin(), cfg).unwrap();
    for k in 0..75u16 {
        let t = ms(4 * u64::from(k));
        sim.on_frame(t, &sync_frame(k));
        for n in 1..=4u8 {
            sim.on_frame(
                t + ms(1),
                &setpoint_frame(n, (k % 16) as u8, 5.0, 0.0, true),
            );
        }
    }
    let speed_at_last = sim.truth().wheel_speed[0];
    let mut stop = None;
    let mut t = last_sp;
    while t < ms(600) {
        t += ms(1);
        sim.advance_to(t);
        if stop.is_none() && sim.truth().wheel_speed[0] == 0.0 {
            stop = Some(t);
        }
    }
    let stop = stop.expect("wheel stopped");
    let a_max = sim.plant().limits().drive_accel;
    println!(
        "watchdog: wheel at {speed_at_last:.3} rad/s stopped {:?} after the last setpoint (decel {a_max:.1} rad/s²)",
        stop - last_sp
    );
    // 50 ms watchdog + ω/a_max of torque-limited deceleration (+1 ms sub-step rounding).
    let bound = 0.050 + speed_at_last / a_max + 0.0015;
    assert!((stop - last_sp).as_secs_f64() <= bound);
    assert!((stop - last_sp).as_secs_f64() >= 0.050);
}

/// Feedback frames per (node, kind) in a run.
fn count(frames: &[(Duration, CanFrame)], kind: MessageKind) -> usize {
    frames
        .iter()
        .filter(|(_, f)| classify(f.id()).map(|k| k.0) == Some(kind))
        .count()
}

#[test]
fn no_fault_run_is_deterministic_and_complete() {
    let a = run(FaultSchedule::default(), 3, 100, ms(10_000), 3.0);
    let b = run(FaultSchedule::default(), 3, 100, ms(10_000), 3.0);
    assert_eq!(a.frames, b.frames);
    assert_eq!(count(&a.frames, MessageKind::FeedbackA), 400);
    assert_eq!(count(&a.frames, MessageKind::FeedbackB), 400);
    // Different seed: same frame times, different encoder noise.
    let c = run(FaultSchedule::default(), 4, 100, ms(10_000), 3.0);
    assert_ne!(a.frames, c.frames);
    assert!(a.sim.truth().slip < 1e-9);
}

fn random_kind(schedule: FaultSchedule) -> (Run, Run, Run) {
    let a = run(schedule.clone(), 11, 100, ms(10_000), 3.0);
    let b = run(schedule.clone(), 11, 100, ms(10_000), 3.0);
    let c = run(schedule, 12, 100, ms(10_000), 3.0);
    assert_eq!(a.frames, b.frames, "same seed, different frames");
    assert_ne!(a.frames, c.frames, "different seed, same frames");
    (a, b, c)
}

#[test]
fn loss_is_reproducible() {
    let s = FaultSchedule {
        loss: 0.1,
        ..FaultSchedule::default()
    };
    let (a, _, _) = random_kind(s);
    let n = count(&a.frames, MessageKind::FeedbackA) + count(&a.frames, MessageKind::FeedbackB);
    // 800 feedback frames, 10 % lost: binomial sd ≈ 8.5.
    println!("loss 0.1: {} of 800 feedback frames delivered", n);
    assert!((680..=760).contains(&n), "{n}");
    assert_eq!(
        a.sim.stats().injector.dropped as usize,
        a.sim.stats().frames_generated as usize - a.frames.len()
    );
}

#[test]
fn delay_and_jitter_are_reproducible() {
    let s = FaultSchedule {
        delay: 0.0005,
        ..FaultSchedule::default()
    };
    let a = run(s, 1, 50, ms(10_000), 3.0);
    for (at, f) in &a.frames {
        if classify(f.id()).unwrap().0 == MessageKind::FeedbackA {
            // Response 0.3 ms + delay 0.5 ms after the SYNC at 4k ms.
            assert_eq!(at.as_micros() % 4000, 800, "{at:?}");
        }
    }
    let s = FaultSchedule {
        jitter: 0.001,
        ..FaultSchedule::default()
    };
    let (a, _, _) = random_kind(s);
    let mut offsets: Vec<u128> = a
        .frames
        .iter()
        .filter(|(_, f)| classify(f.id()).unwrap().0 == MessageKind::FeedbackA)
        .map(|(at, _)| at.as_micros() % 4000)
        .collect();
    assert!(
        offsets.iter().all(|&o| (300..=1300).contains(&o)),
        "{offsets:?}"
    );
    offsets.sort_unstable();
    offsets.dedup();
    assert!(offsets.len() > 20, "jitter too regular: {offsets:?}");
    // Never reordered.
    assert!(a.frames.windows(2).all(|w| w[0].0 <= w[1].0));
}

#[test]
fn duplicates_are_reproducible() {
    let s = FaultSchedule {
        duplicate: 0.1,
        ..FaultSchedule::default()
    };
    let (a, _, _) = random_kind(s);
    let dups = a.frames.windows(2).filter(|w| w[0] == w[1]).count();
    println!("duplicate 0.1: {dups} back-to-back duplicates");
    assert!(dups > 40, "{dups}");
    assert_eq!(dups as u64, a.sim.stats().injector.duplicated);
}

#[test]
fn corruption_is_reproducible_and_caught_by_crc() {
    let s = FaultSchedule {
        corrupt: 0.05,
        ..FaultSchedule::default()
    };
    let (a, _, _) = random_kind(s);
    let bad = a.frames.iter().filter(|(_, f)| decode(f).is_err()).count();
    println!("corrupt 0.05: {bad} frames fail decode");
    assert!(bad > 20, "{bad}");
    assert_eq!(bad as u64, a.sim.stats().injector.corrupted);
}

fn silent_run(seed: u64) -> Run {
    let s = FaultSchedule {
        silent: vec![Silent {
            node: 2,
            from: 0.1,
            to: 0.2,
        }],
        ..FaultSchedule::default()
    };
    run(s, seed, 100, ms(10_000), 3.0)
}

#[test]
fn silent_module_sends_nothing_in_its_window() {
    let a = silent_run(5);
    assert_eq!(a.frames, silent_run(5).frames);
    let node2: Vec<Duration> = a
        .frames
        .iter()
        .filter(|(_, f)| kind_node(f).1 == 2)
        .map(|(t, _)| *t)
        .collect();
    assert!(node2.iter().all(|t| *t < ms(100) || *t >= ms(200)));
    assert!(node2.iter().any(|t| *t < ms(100)) && node2.iter().any(|t| *t >= ms(200)));
    // Other modules keep talking.
    assert!(a
        .frames
        .iter()
        .any(|(t, f)| kind_node(f).1 == 1 && *t >= ms(100) && *t < ms(200)));
    // 25 SYNCs in the window: 50 feedback frames of node 2 missing (+ a STATUS).
    assert!(a.sim.stats().frames_dropped_silent >= 50);
}

#[test]
fn motor_fault_latches_and_stops_the_wheel() {
    let s = FaultSchedule {
        motor_fault: vec![MotorFault { node: 3, at: 0.15 }],
        ..FaultSchedule::default()
    };
    let a = run(s.clone(), 1, 100, ms(10_000), 3.0);
    assert_eq!(a.frames, run(s, 1, 100, ms(10_000), 3.0).frames);
    let fault: Vec<(Duration, Status)> = a
        .frames
        .iter()
        .filter_map(|(t, f)| match decode(f) {
            Ok(Message {
                node: 3,
                payload: Payload::Status(st),
                ..
            }) if st.state == ModuleState::Fault => Some((*t, st)),
            _ => None,
        })
        .collect();
    assert!(!fault.is_empty());
    assert_eq!(fault[0].0, ms(150));
    assert_eq!(fault[0].1.fault_code, FAULT_OVERCURRENT);
    // Latched: still fault at the end although enable setpoints keep coming.
    assert_eq!(a.sim.module_states()[2], ModuleState::Fault);
    assert_eq!(a.sim.truth().wheel_speed[2], 0.0);
    assert!(a.sim.truth().wheel_speed[0] > 2.9);
}

fn feedback_a(frames: &[(Duration, CanFrame)], node: u8) -> Vec<(Duration, FeedbackA)> {
    frames
        .iter()
        .filter_map(|(t, f)| match decode(f) {
            Ok(Message {
                node: n,
                payload: Payload::FeedbackA(a),
                ..
            }) if n == node => Some((*t, a)),
            _ => None,
        })
        .collect()
}

#[test]
fn encoder_stuck_freezes_the_feedback() {
    let s = FaultSchedule {
        encoder_stuck: vec![EncoderStuck { node: 1, at: 0.2 }],
        ..FaultSchedule::default()
    };
    let a = run(s.clone(), 1, 100, ms(10_000), 3.0);
    assert_eq!(a.frames, run(s, 1, 100, ms(10_000), 3.0).frames);
    let fa = feedback_a(&a.frames, 1);
    let after: Vec<_> = fa.iter().filter(|(t, _)| *t > ms(210)).collect();
    assert!(after.len() > 40);
    assert!(after.iter().all(|(_, x)| *x == after[0].1), "not frozen");
    // Before: the steering is turning, so the readings change.
    let before: Vec<_> = fa.iter().filter(|(t, _)| *t < ms(190)).collect();
    assert!(before.windows(2).any(|w| w[0].1 != w[1].1));
    // Module 2 is unaffected.
    let fa2 = feedback_a(&a.frames, 2);
    let after2: Vec<_> = fa2.iter().filter(|(t, _)| *t > ms(210)).collect();
    assert!(after2.windows(2).any(|w| w[0].1 != w[1].1));
}

#[test]
fn encoder_jump_offsets_the_steering_feedback() {
    let jump = EncoderJump {
        node: 4,
        at: 0.2,
        amount: 0.3,
    };
    let s = FaultSchedule {
        encoder_jump: vec![jump],
        ..FaultSchedule::default()
    };
    let a = run(s, 1, 100, ms(10_000), 3.0);
    let clean = run(FaultSchedule::default(), 1, 100, ms(10_000), 3.0);
    let fa = feedback_a(&a.frames, 4);
    let fc = feedback_a(&clean.frames, 4);
    assert_eq!(fa.len(), fc.len());
    for ((t, x), (_, y)) in fa.iter().zip(&fc) {
        let d = x.steer_angle - y.steer_angle;
        if *t < ms(200) {
            assert_eq!(d, 0.0, "{t:?}");
        } else if *t > ms(203) {
            assert!((d - 0.3).abs() < 2e-4, "{t:?}: jump {d}");
        }
    }
}

#[test]
fn bus_off_silences_everything_in_its_window() {
    let s = FaultSchedule {
        bus_off: vec![BusOff {
            at: 0.1,
            until: 0.13,
        }],
        ..FaultSchedule::default()
    };
    let a = run(s.clone(), 1, 100, ms(10_000), 3.0);
    assert_eq!(a.frames, run(s, 1, 100, ms(10_000), 3.0).frames);
    assert!(a.frames.iter().all(|(t, _)| *t < ms(100) || *t >= ms(130)));
    assert!(a.frames.iter().any(|(t, _)| *t >= ms(130)));
    let st = a.sim.stats();
    // SYNC + 4 setpoints per cycle are swallowed while off (8 cycles in [100, 130) ms).
    assert_eq!(st.frames_lost_bus_off_rx, 8 * 5, "{st:?}");
    // No SYNC, no feedback: 8 cycles × 4 modules missing per feedback kind.
    assert_eq!(count(&a.frames, MessageKind::FeedbackA), 4 * 92);
    assert_eq!(count(&a.frames, MessageKind::FeedbackB), 4 * 92);
    // The periodic STATUS due at 100 ms fell into the window.
    assert!(st.frames_dropped_bus_off >= 4, "{st:?}");
    // 30 ms without setpoints is below the 50 ms watchdog: the modules stay enabled.
    assert!(a.sim.module_states()[..4]
        .iter()
        .all(|s| *s == ModuleState::Enabled));
}

#[test]
fn bad_schedules_are_rejected_by_the_simulator() {
    let s = FaultSchedule {
        motor_fault: vec![MotorFault { node: 9, at: 1.0 }],
        ..FaultSchedule::default()
    };
    let cfg = SimConfig {
        faults: s,
        ..SimConfig::default()
    };
    let e = Simulator::with_config(&Platform::justin(), cfg).unwrap_err();
    assert!(e.to_string().contains("motor_fault[0].node"), "{e}");
    let cfg = SimConfig {
        substep: Duration::ZERO,
        ..SimConfig::default()
    };
    assert!(Simulator::with_config(&Platform::justin(), cfg).is_err());
}

#[test]
fn realtime_loop_answers_syncs_on_a_wall_clock_virtual_bus() {
    use rollbase_driver::bus::{BusClock, VirtualBus, VirtualBusConfig};
    use std::sync::atomic::{AtomicBool, Ordering};
    use std::sync::Arc;
    use std::time::Instant;

    let vbus = VirtualBus::new(VirtualBusConfig {
        clock: BusClock::Wall,
        ..VirtualBusConfig::default()
    });
    let mut ctrl = vbus.node("controller");
    let sim_node = vbus.node("sim");
    let sim = Simulator::with_config(&Platform::justin(), SimConfig::default()).unwrap();
    let stop = Arc::new(AtomicBool::new(false));
    let handle = rollbase_vcan_sim::spawn_realtime(sim, Box::new(sim_node), stop.clone(), None);
    let mut feedback = 0;
    let syncs = 25u16;
    for k in 0..syncs {
        ctrl.send(&sync_frame(k)).unwrap();
        for n in 1..=4u8 {
            ctrl.send(&setpoint_frame(n, (k % 16) as u8, 2.0, 0.0, true))
                .unwrap();
        }
        std::thread::sleep(Duration::from_millis(4));
        while let Some(tf) = ctrl.try_recv().unwrap() {
            if matches!(
                kind_node(&tf.frame).0,
                MessageKind::FeedbackA | MessageKind::FeedbackB
            ) {
                feedback += 1;
            }
        }
    }
    // Collect the stragglers (generous deadline; this is not a timing assertion).
    let deadline = Instant::now() + Duration::from_secs(2);
    while feedback < 8 * usize::from(syncs) {
        match ctrl.recv_until(deadline).unwrap() {
            Some(tf) => {
                if matches!(
                    kind_node(&tf.frame).0,
                    MessageKind::FeedbackA | MessageKind::FeedbackB
                ) {
                    feedback += 1;
                }
            }
            None => break,
        }
    }
    stop.store(true, Ordering::Relaxed);
    let (sim, result) = handle.join().unwrap();
    let summary = result.unwrap();
    assert_eq!(feedback, 8 * usize::from(syncs));
    assert_eq!(summary.frames_in, 5 * u64::from(syncs));
    assert_eq!(sim.stats().modules[0].syncs_answered, u64::from(syncs));
    for m in &sim.stats().modules[..4] {
        assert_eq!(m.setpoints_accepted, u64::from(syncs));
    }
    assert!(
        sim.truth().pose.x > 0.0,
        "the enabled wheels moved the platform"
    );
}

#[test]
fn pump_drives_the_simulator_from_a_virtual_clock_bus() {
    use rollbase_driver::bus::{BusClock, VirtualBus, VirtualBusConfig};
    let vbus = VirtualBus::new(VirtualBusConfig {
        clock: BusClock::Virtual,
        ..VirtualBusConfig::default()
    });
    let mut ctrl = vbus.node("controller");
    let mut node = vbus.node("sim");
    let mut sim = Simulator::with_config(&Platform::justin(), SimConfig::default()).unwrap();
    let mut feedback = 0;
    for k in 0..50u16 {
        let t = ms(4 * u64::from(k));
        vbus.set_time(t);
        ctrl.send(&sync_frame(k)).unwrap();
        sim.pump(t, &mut node).unwrap();
        // Feedback is due 0.3 ms later.
        let t_fb = t + us(300);
        vbus.set_time(t_fb);
        sim.pump(t_fb, &mut node).unwrap();
        let t_sp = t + ms(2);
        vbus.set_time(t_sp);
        while let Some(tf) = ctrl.try_recv().unwrap() {
            if matches!(
                kind_node(&tf.frame).0,
                MessageKind::FeedbackA | MessageKind::FeedbackB
            ) {
                assert_eq!(tf.timestamp, t_fb);
                feedback += 1;
            }
        }
        for n in 1..=4u8 {
            ctrl.send(&setpoint_frame(n, (k % 16) as u8, 2.0, 0.0, true))
                .unwrap();
        }
        sim.pump(t_sp, &mut node).unwrap();
    }
    assert_eq!(feedback, 8 * 50);
    assert_eq!(sim.stats().modules[3].setpoints_accepted, 50);
    // 2 rad/s · 0.085 m for ~0.2 s, minus the start-up lag.
    let x = sim.truth().pose.x;
    assert!(x > 0.025 && x < 0.034, "x = {x}");
}

#[test]
fn shipped_example_files_load() {
    let dir = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("config");
    let f = FaultSchedule::load(dir.join("faults.example.toml")).unwrap();
    assert_eq!(f.silent.len(), 1);
    assert_eq!(f.bus_off.len(), 1);
    let p = PlantConfig::load(dir.join("plant.toml")).unwrap();
    assert_eq!(
        p,
        PlantConfig::default(),
        "config/plant.toml should list the defaults"
    );
}
