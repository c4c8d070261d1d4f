//! Two buses (issue 25): the six-wheel example (wheels 1–3 on bus 0, 4–6 on bus 1), each
//! bus on its own virtual medium with its own SYNC, both wire profiles, seed 000 and a live
//! session with leg commands; the bus load per bus; one bus lost → a controlled stop of the
//! whole base.

use rollbase_control::runtime::scenario::Scenario;
use rollbase_control::runtime::ControllerKind;
use rollbase_control::{Platform, Protocol};
use rollbase_tests::{
    assert_commands_within_limits, assert_controlled_stop_from, assert_tracking_bounds,
    five_step_session, run_buses, run_live, LiveOptions, RunOptions, RunOutcome,
};

fn opts(profile: Protocol) -> RunOptions {
    let mut o = RunOptions::new(Scenario::Seed000).with_controller(ControllerKind::Dfl);
    if profile == Protocol::Cia402 {
        o = o.cia402();
    }
    o.platform = Some(Platform::six_wheel());
    o
}

fn check_two_buses(name: &str, out: &RunOutcome) {
    let s = &out.summary;
    println!("{name}: {}", s.to_json());
    assert_tracking_bounds(s, name);
    assert_eq!(s.rejected_frames, 0, "{name}: a clean bus rejects nothing");
    assert_commands_within_limits(out);
    // Every cycle: one SYNC per bus, each wheel's setpoints on its own bus only.
    for r in out.records.iter().filter(|r| r.cycle > 10).take(500) {
        let syncs: Vec<u8> = r.tx[..r.n_tx]
            .iter()
            .filter(|f| f.id == 0x080)
            .map(|f| f.bus)
            .collect();
        assert_eq!(syncs, vec![0, 1], "{name}: cycle {} SYNCs", r.cycle);
        for f in &r.tx[..r.n_tx] {
            if let Some(w) = wheel_of_node(&out.platform, (f.id & 0x7F) as u8) {
                let want = out.platform.wheels[w].bus;
                assert_eq!(f.bus, want, "{name}: frame {:#x} on the wrong bus", f.id);
            }
        }
    }
}

/// The wheel whose module (native) or device (CiA 402) has CAN node `node`.
fn wheel_of_node(p: &Platform, node: u8) -> Option<usize> {
    match p.protocol {
        Protocol::Native => p.wheels.iter().position(|w| w.node == node),
        Protocol::Cia402 => p.cia402().wheels.iter().position(|d| {
            node != 0 && (d.drive_node == node || d.steer_node == node || d.leg_node == node)
        }),
    }
}

fn bus_loads(profile: Protocol) -> [f64; 2] {
    let mut o = opts(profile);
    o.max_seconds = Some(3.0);
    let out = run_buses(&o, None);
    out.final_state.expect("state").diagnostics.bus_loads
}

#[test]
fn six_wheels_on_two_buses_run_seed000_native() {
    let out = run_buses(&opts(Protocol::Native), None);
    check_two_buses("six-wheel native", &out);
}

#[test]
fn six_wheels_on_two_buses_run_seed000_cia402() {
    let out = run_buses(&opts(Protocol::Cia402), None);
    check_two_buses("six-wheel cia402", &out);
}

/// The five-step live session ([`five_step_session`]) on both buses, the legs in to 0.42 m
/// at 4 s and out to 0.52 m at 10 s.
fn live_session(profile: Protocol) -> RunOutcome {
    let opts = LiveOptions {
        profile,
        max_seconds: 40.0,
        platform: Some(Platform::six_wheel()),
        ..LiveOptions::default()
    };
    let cmds = five_step_session(&[(4.0, &[0.42; 6]), (10.0, &[0.52; 6])]);
    run_live(&opts, &cmds)
}

fn check_live_session(name: &str, out: &RunOutcome) {
    check_two_buses(name, out);
    assert_eq!(
        out.summary.rejected_commands, 0,
        "{name}: every command taken"
    );
    let last = out.records.last().expect("records");
    let (pose, _) = last.truth.expect("truth");
    assert!(pose.x.hypot(pose.y) > 0.5, "{name}: ends at {pose:?}");
    for (i, w) in last.measurement.wheels[..6].iter().enumerate() {
        assert!(
            (w.leg - 0.52).abs() < 0.002,
            "{name}: leg {i} ends at {} m, commanded 0.52 m",
            w.leg
        );
    }
    // The legs went in first: every leg was below 0.43 m at some point.
    for i in 0..6 {
        let lo = out
            .records
            .iter()
            .map(|r| r.measurement.wheels[i].leg)
            .fold(f64::INFINITY, f64::min);
        assert!(lo < 0.43, "{name}: leg {i} never went in (lowest {lo} m)");
    }
}

#[test]
fn six_wheels_on_two_buses_live_session_native() {
    check_live_session("six-wheel live native", &live_session(Protocol::Native));
}

#[test]
fn six_wheels_on_two_buses_live_session_cia402() {
    check_live_session("six-wheel live cia402", &live_session(Protocol::Cia402));
}

#[test]
fn bus_load_is_measured_per_bus() {
    for profile in [Protocol::Native, Protocol::Cia402] {
        let [b0, b1] = bus_loads(profile);
        println!("{profile}: bus loads {b0:.3} {b1:.3}");
        // Three wheels each: the same traffic on both, well above nothing.
        assert!(b0 > 0.05 && b1 > 0.05, "{profile}: {b0} {b1}");
        assert!((b0 - b1).abs() < 0.1 * b0, "{profile}: {b0} {b1}");
    }
}

#[test]
fn one_bus_lost_stops_the_whole_base() {
    for profile in [Protocol::Native, Protocol::Cia402] {
        let lose_at = 20.0;
        let out = run_buses(&opts(profile), Some((1, lose_at)));
        let from = (lose_at * out.platform.cycle_hz) as u64;
        let fault = out
            .records
            .iter()
            .find(|r| {
                r.cycle >= from && r.state == rollbase_control::supervisor::SupervisorState::Fault
            })
            .unwrap_or_else(|| panic!("{profile}: no fault after bus 1 was lost"));
        println!(
            "{profile}: fault at cycle {} ({:?})",
            fault.cycle, fault.reason
        );
        assert!(
            fault.cycle < from + 50,
            "{profile}: detected at cycle {}",
            fault.cycle
        );
        assert_controlled_stop_from(&out, fault.cycle);
        // The wheels on the bus that is still there are brought to rest too.
        let last = out.records.last().unwrap();
        for i in 0..3 {
            assert_eq!(
                last.command.wheels[i].wheel_speed, 0.0,
                "{profile}: wheel {i}"
            );
        }
    }
}

/// The cycle of the last NMT start before the supervisor armed (boot and configuration
/// done; homing follows).
fn configured_cycle(out: &RunOutcome) -> usize {
    let armed = out
        .records
        .iter()
        .position(|r| r.state != rollbase_control::supervisor::SupervisorState::Idle)
        .expect("armed");
    out.records[..=armed]
        .iter()
        .rposition(|r| {
            r.tx[..r.n_tx]
                .iter()
                .any(|f| f.id == 0 && f.len == 2 && f.data[0] == 0x01)
        })
        .expect("NMT start")
}

/// Two CiA 402 buses boot as fast as one: the devices' SDO answers that arrive after the
/// feedback window are taken before the next SYNC and the next request goes out with it
/// (`CycleCore::after_late_frames_buses`), as on one bus — not one SDO request per cycle.
#[test]
fn two_cia402_buses_boot_as_fast_as_one() {
    let one = rollbase_tests::run(&{
        let mut o = RunOptions::new(Scenario::Seed000).cia402();
        o.max_seconds = Some(3.0);
        o
    });
    let mut o = opts(Protocol::Cia402);
    o.max_seconds = Some(3.0);
    let two = run_buses(&o, None);
    let (c1, c2) = (configured_cycle(&one), configured_cycle(&two));
    println!(
        "configured: one bus (12 devices) {c1} cycles, two buses (9 devices each) {c2} cycles"
    );
    assert!(
        c2 as f64 <= c1 as f64 * 1.1,
        "two buses took {c2} cycles to configure, one bus {c1}"
    );
}

/// A number of lockstep buses other than the platform's is refused before anything runs,
/// with the typed error naming both counts (it used to be an assertion, a panic).
#[test]
fn a_lockstep_run_with_the_wrong_number_of_buses_is_refused_with_a_typed_error() {
    use rollbase_control::runtime::{
        run_lockstep_buses, LockstepBus, LockstepError, VirtualLockstepBus,
    };
    for (platform, given) in [(Platform::six_wheel(), 1usize), (Platform::justin(), 2)] {
        let o = RunOptions {
            platform: Some(platform),
            ..opts(Protocol::Native)
        };
        let (mut core, mut sim, _, _) = rollbase_tests::build(&o).expect("valid setup");
        let mut media: Vec<VirtualLockstepBus> = (0..given)
            .map(|b| VirtualLockstepBus::new(Default::default(), b as u64))
            .collect();
        let mut buses: Vec<&mut dyn LockstepBus> = media
            .iter_mut()
            .map(|m| m as &mut dyn LockstepBus)
            .collect();
        let mut cycles = 0;
        let err = run_lockstep_buses(
            &mut core,
            &mut buses,
            &mut sim,
            &[],
            100,
            &mut |_| false,
            &mut |_, _| cycles += 1,
        )
        .expect_err("a wrong bus count must be refused");
        let want = core.buses();
        assert_eq!(
            err,
            LockstepError::BusCount {
                platform: want,
                given
            }
        );
        assert_eq!(cycles, 0, "nothing may run before the refusal");
        let text = err.to_string();
        assert!(
            text.contains(&format!("{want} CAN bus(es)"))
                && text.contains(&format!("{given} lockstep")),
            "{text}"
        );
    }
}
