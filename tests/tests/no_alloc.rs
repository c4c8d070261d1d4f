//! The cycle core allocates nothing per cycle: a counting global allocator around the calls
//! into the core (the simulator and the bus are outside the counted region), in lockstep.
//!
//! - Trajectory following: `start_cycle`, `on_frame` and `finish_cycle` over the seed-000
//!   scenario with avoidance on.
//! - The base service (`rollbase drive`'s cycle): a live core fed commands through the command
//!   port (`command`), its state port value (`base_state`) taken every cycle, over a session
//!   that exercises the shaper (commands far beyond the limits, reversals, align-first), the
//!   avoidance, leg moves, rejected commands, a command timeout, a stop and a re-arm, on both
//!   wire profiles.
//!
//! Each test counts only its own thread's allocations, so the two may run in parallel.

use rollbase_control::reference::avoidance::AvoidanceConfig;
use rollbase_control::runtime::scenario::{self, Scenario};
use rollbase_control::runtime::{
    lockstep_cycle, CycleCore, LockstepState, RuntimeConfig, StepHooks, VirtualLockstepBus,
};
use rollbase_control::service::ports::{
    CommandEvent, CommandKind, LegTargets, Limiting, MotionCommand,
};
use rollbase_control::supervisor::SupervisorState;
use rollbase_control::types::Twist;
use rollbase_control::{Platform, Protocol};
use rollbase_driver::fault::FaultModel;
use rollbase_tests::alloc_count::{counted, set_counting, thread_allocations, CountingAlloc};
use rollbase_vcan_sim::{FaultSchedule, PlantConfig, SimConfig, Simulator};

#[global_allocator]
static GLOBAL: CountingAlloc = CountingAlloc;

#[test]
fn the_cycle_core_does_not_allocate() {
    let p = Platform::justin();
    let traj = scenario::trajectory(Scenario::Seed000, &p).unwrap();
    let r0 = traj.sample(0.0);
    let mut cfg = scenario::runtime_config(Scenario::Seed000);
    cfg.avoidance = Some(AvoidanceConfig::default());
    let mut core = CycleCore::new(p.clone(), traj, cfg).unwrap();
    let mut sim =
        Simulator::new(&p, PlantConfig::default(), FaultSchedule::default(), &r0, 5).unwrap();
    let mut bus = VirtualLockstepBus::new(FaultModel::none(), 5);
    let mut st = LockstepState::new(&core);
    core.arm();
    let mut counted_cycles = 0;
    let mut count = |on: bool| set_counting(on);
    for _ in 0..7000u64 {
        let mut hooks = StepHooks {
            around_core: Some(&mut count),
            ..Default::default()
        };
        lockstep_cycle(&mut st, &mut core, &mut bus, &mut sim, &mut hooks);
        if core.state().name() == "tracking" {
            counted_cycles += 1;
        }
        if core.done() {
            break;
        }
    }
    assert!(counted_cycles > 5000, "tracked {counted_cycles} cycles");
    assert_eq!(thread_allocations(), 0, "allocations inside the cycle core");
}

fn motion(t: f64, vx: f64, vy: f64, omega: f64, legs: Option<[f64; 4]>) -> CommandEvent {
    CommandEvent {
        t,
        kind: CommandKind::Motion(MotionCommand {
            twist: Twist { vx, vy, omega },
            legs: legs.map(|l| LegTargets::from_slice(&l)),
        }),
    }
}

/// `(vx, vy, ω)` every 0.2 s over `[from, to)`.
fn hold(cmds: &mut Vec<CommandEvent>, from: f64, to: f64, twist: (f64, f64, f64)) {
    let mut t = from;
    while t < to - 1e-9 {
        cmds.push(motion(t, twist.0, twist.1, twist.2, None));
        t += 0.2;
    }
}

/// A session of every kind of command the port takes (times from the moment the core first
/// follows commands).
fn session() -> Vec<CommandEvent> {
    let ev = |t: f64, kind: CommandKind| CommandEvent { t, kind };
    let legs = |t: f64, l: &[f64]| ev(t, CommandKind::Legs(LegTargets::from_slice(l)));
    let mut c = Vec::new();
    // Far beyond the limits (shaped), then an instant reversal with a fast rotation.
    hold(&mut c, 0.0, 2.0, (3.0, 0.0, 0.0));
    hold(&mut c, 2.0, 4.0, (-3.0, 1.0, 5.0));
    // Legs in at rest (once the reversal has come to rest), then out while driving.
    c.push(motion(4.0, 0.0, 0.0, 0.0, Some([0.37; 4])));
    hold(&mut c, 4.2, 6.0, (0.0, 0.0, 0.0));
    hold(&mut c, 6.0, 6.6, (0.5, 0.0, 0.0));
    c.push(legs(6.6, &[0.56; 4]));
    hold(&mut c, 6.8, 8.0, (0.5, 0.0, 0.0));
    // Rejected: NaN, inf, beyond the sanity bound, a leg far out of range, wrong leg count.
    c.push(motion(8.0, f64::NAN, 0.0, 0.0, None));
    c.push(motion(8.1, 0.0, f64::INFINITY, 0.0, None));
    c.push(motion(8.2, 50.0, 0.0, 0.0, None));
    c.push(motion(8.3, 0.2, 0.0, 0.0, Some([0.9; 4])));
    c.push(legs(8.4, &[0.4; 2]));
    // Then silence: the command timeout stops the platform; the next command resumes.
    hold(&mut c, 10.0, 12.0, (0.0, 0.8, -2.0));
    // Pivot about wheel 1's contact point (about (0.4, 0.4) m with the legs out: v = −ω × p).
    hold(&mut c, 12.0, 14.0, (0.4, -0.4, 1.0));
    // A stop, then a re-arm and one more motion, then the end of the stream.
    c.push(ev(14.0, CommandKind::Stop));
    c.push(ev(15.5, CommandKind::Rearm));
    hold(&mut c, 16.5, 17.5, (0.4, 0.4, 0.0));
    c.push(ev(17.5, CommandKind::EndOfStream));
    c
}

/// What the session exercised (so the test fails if it stops covering these).
#[derive(Debug, Default)]
struct Seen {
    tracking_cycles: u64,
    shaped_cycles: u64,
    aligning_cycles: u64,
    leg_range: (f64, f64),
    /// Tracking again after Stopped or Fault (a re-arm).
    rearmed: bool,
    avoidance_active: u64,
}

#[test]
fn the_live_service_cycle_does_not_allocate() {
    // `rollbase drive`'s default (avoidance off) on both profiles, and with `--avoidance on`.
    for (profile, avoid) in [
        (Protocol::Native, false),
        (Protocol::Cia402, false),
        (Protocol::Native, true),
    ] {
        let mut p = Platform::justin();
        p.protocol = profile;
        let cfg = RuntimeConfig {
            avoidance: avoid.then(AvoidanceConfig::default),
            ..RuntimeConfig::default()
        };
        let mut core = CycleCore::new_live(p.clone(), cfg).unwrap();
        let mut sim = Simulator::with_config(
            &p,
            SimConfig {
                seed: 5,
                bitrate: (profile == Protocol::Cia402).then_some(1_000_000),
                ..SimConfig::default()
            },
        )
        .unwrap();
        let mut bus = VirtualLockstepBus::new(FaultModel::none(), 5);
        let mut st = LockstepState::new(&core);
        let cmds = session();
        let mut next = 0;
        let mut ready_at: Option<f64> = None;
        let mut seen = Seen {
            leg_range: (f64::INFINITY, 0.0),
            ..Seen::default()
        };
        let mut was_stopped = false;
        let before = thread_allocations();
        counted(|| core.arm());
        let mut allocating_cycles = Vec::new();
        for k in 0..40 * 250u64 {
            let at_start = thread_allocations();
            let t = st.time();
            if ready_at.is_none() && core.state() == SupervisorState::Tracking {
                ready_at = Some(t);
            }
            if let Some(t0) = ready_at {
                while next < cmds.len() && cmds[next].t <= t - t0 + 1e-9 {
                    let mut ev = cmds[next];
                    ev.t = t;
                    counted(|| core.command(ev));
                    next += 1;
                }
            }
            let mut count = |on: bool| set_counting(on);
            let mut hooks = StepHooks {
                around_core: Some(&mut count),
                ..Default::default()
            };
            lockstep_cycle(&mut st, &mut core, &mut bus, &mut sim, &mut hooks);
            // The state port's value, as the real-time cycle hands it over.
            let state = counted(|| *core.base_state());
            if thread_allocations() != at_start {
                allocating_cycles.push((k, thread_allocations() - at_start));
            }
            match state.state {
                SupervisorState::Tracking => {
                    seen.tracking_cycles += 1;
                    seen.rearmed |= was_stopped;
                }
                SupervisorState::Stopped | SupervisorState::Fault => was_stopped = true,
                _ => {}
            }
            match state.shaping.limiting {
                Limiting::None | Limiting::Timeout => {}
                Limiting::Aligning => seen.aligning_cycles += 1,
                _ => seen.shaped_cycles += 1,
            }
            let leg = state.joints[0].leg;
            seen.leg_range = (seen.leg_range.0.min(leg), seen.leg_range.1.max(leg));
            if core.record().avoidance.active {
                seen.avoidance_active += 1;
            }
            if core.done() {
                break;
            }
        }
        let state = *core.base_state();
        eprintln!(
            "{profile:?}, avoidance {avoid}: {seen:?}, commands {:?}",
            state.commands
        );
        assert_eq!(
            state.state,
            SupervisorState::Stopped,
            "{profile:?}: {:?}",
            state.reason
        );
        assert!(next == cmds.len(), "{profile:?}: every command delivered");
        assert!(core.done(), "{profile:?}: the run ended at rest");
        // The session covered what it claims.
        assert!(seen.tracking_cycles > 3000, "{profile:?}: {seen:?}");
        assert!(seen.shaped_cycles > 250, "{profile:?}: {seen:?}");
        assert!(seen.aligning_cycles > 10, "{profile:?}: {seen:?}");
        assert!(
            seen.leg_range.0 < 0.375 && seen.leg_range.1 > 0.555,
            "{profile:?}: legs {:?}",
            seen.leg_range
        );
        assert!(seen.rearmed, "{profile:?}: stop, re-arm");
        assert_eq!(seen.avoidance_active > 0, avoid, "{profile:?}: {seen:?}");
        assert_eq!(
            state.commands.rejected, 5,
            "{profile:?}: {:?}",
            state.commands
        );
        assert!(
            state.commands.timeouts >= 1,
            "{profile:?}: {:?}",
            state.commands
        );
        // And none of it allocated.
        assert_eq!(
            thread_allocations() - before,
            0,
            "{profile:?}: allocations in the live cycle (cycle, count): {allocating_cycles:?}"
        );
    }
}
