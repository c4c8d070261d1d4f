//! The base service's (`rollbase drive`'s) per-cycle control work on a live command session:
//! singularity avoidance on the command and the shaper (live command → reference within
//! every actuator limit; `CycleCore` runs the avoidance before the shaper for live commands,
//! [`rollbase_control::avoidance`], "Live commands"), and the tracking controller (DFL while the reference moves, the
//! kinematic controller near rest, switched with hysteresis as `CycleCore` does for live
//! commands).
//!
//! The session: 30 s of random commands (a new twist every 1–2.5 s, up to 2 m/s and
//! 3 rad/s, so most are beyond the limits and shaped; leg targets with some of them), each
//! repeated every 0.2 s like a live sender. The inputs are recorded first from a closed loop
//! against the ideal kinematic plant, then replayed: the shaper is fed the same commands at
//! the same cycles (it is deterministic, so it evolves as in the recording) and the
//! controllers see the recorded measurements and odometry. Odometry is not timed (it is in
//! `control_step`).
//!
//! `live/cycle_core_whole_cycle` times the whole controller side of a live cycle on the full
//! frame path (`CycleCore::new_live` against the simulated wheel modules through the lockstep
//! virtual bus): the command port, `start_cycle`, `on_frame` for the 8 feedback frames and
//! `finish_cycle` (decode, odometry, shaper, controller, supervisor, output guard, encode,
//! record, state port); the simulator and the bus run outside the timed regions.
//!
//! A counting global allocator counts heap allocations over one full replay of each case
//! (lines `ALLOCS <bench> <allocations> <steps>` on stdout, read by `perf-report`). The
//! shaper's work is uneven (a new goal plans a transition; most cycles only sample the plan),
//! so more replays time every step alone, keeping each step's minimum over the replays (what
//! the machine's other work added to one replay is gone): `STEPTIME <bench> <p50 ns> <p99 ns>
//! <max ns> <steps>` (each step between two `Instant` readings, which add a few tens of ns).

use criterion::{criterion_group, criterion_main, Criterion};
use rollbase_control::avoidance::AvoidanceConfig;
use rollbase_control::dfl::{ControlInput, ControlOutput, DflController};
use rollbase_control::ideal_plant::IdealPlant;
use rollbase_control::kinematic::KinematicController;
use rollbase_control::odometry::{Odometry, OdometryOutput};
use rollbase_control::ports::{CommandEvent, CommandKind, LegTargets, MotionCommand};
use rollbase_control::runtime::{
    lockstep_cycle, CycleCore, LockstepState, RuntimeConfig, StepHooks, VirtualLockstepBus,
    DFL_ENTRY_SPEED,
};
use rollbase_control::shaper::Shaper;
use rollbase_control::supervisor::SupervisorState;
use rollbase_control::types::{Pose, Twist};
use rollbase_control::{Measurement, Platform, ReferenceSample};
use rollbase_driver::fault::FaultModel;
use rollbase_tests::alloc_count::{allocations, reset, set_counting, CountingAlloc};
use rollbase_vcan_sim::{SimConfig, Simulator};
use std::hint::black_box;
use std::time::{Duration, Instant};

#[global_allocator]
static GLOBAL: CountingAlloc = CountingAlloc;

/// Length of the session (s).
const SESSION_S: f64 = 30.0;

/// The session's commands (times from the start), sorted.
fn session(seed: u64) -> Vec<CommandEvent> {
    let mut rng = rollbase_driver::rng::Rng::new(seed);
    let mut u = |lo: f64, hi: f64| lo + (hi - lo) * rng.next_f64();
    let mut cmds = Vec::new();
    let mut t = 0.0;
    while t < SESSION_S {
        let hold = u(1.0, 2.5);
        let twist = Twist {
            vx: u(-2.0, 2.0),
            vy: u(-2.0, 2.0),
            omega: u(-3.0, 3.0),
        };
        let legs = (u(0.0, 1.0) < 0.3).then(|| LegTargets::from_slice(&[u(0.37, 0.56); 4]));
        let mut k = 0.0;
        while k < hold && t + k < SESSION_S {
            cmds.push(CommandEvent {
                t: t + k,
                kind: CommandKind::Motion(MotionCommand {
                    twist,
                    legs: if k == 0.0 { legs } else { None },
                }),
            });
            k += 0.2;
        }
        t += hold;
    }
    cmds
}

/// The commands as (cycle, kind), for replay.
fn schedule(p: &Platform, cmds: &[CommandEvent]) -> Vec<(usize, CommandKind)> {
    cmds.iter()
        .map(|c| ((c.t / p.dt()).round() as usize, c.kind))
        .collect()
}

/// One recorded cycle: what the controllers get.
#[derive(Clone, Copy)]
struct Step {
    measurement: Measurement,
    odo: OdometryOutput,
}

/// (Avoidance →) shaper → controller, as `CycleCore::finish_cycle` runs them for live
/// commands.
struct LiveStack {
    shaper: Shaper,
    dfl: DflController,
    kin: KinematicController,
    dfl_active: bool,
    control: bool,
    next: usize,
}

impl LiveStack {
    fn new(p: &Platform, avoid: bool, control: bool) -> Self {
        let mut kin = KinematicController::new(p);
        kin.set_termination(false);
        let mut shaper = Shaper::new(p, Default::default());
        shaper.set_avoidance(avoid.then(AvoidanceConfig::default));
        let mut s = Self {
            shaper,
            dfl: DflController::new(p),
            kin,
            dfl_active: false,
            control,
            next: 0,
        };
        s.reset(p);
        s
    }

    /// At rest at the origin, legs nominal, wheels straight (as the recording starts).
    fn reset(&mut self, p: &Platform) {
        let legs: Vec<f64> = p.wheels.iter().map(|w| w.lambda_nominal).collect();
        self.shaper.reset(Pose::default(), &legs, &vec![0.0; p.n()]);
        let r0 = self.shaper.hold_sample();
        self.dfl.reset(p, &r0);
        self.kin.reset(p, &r0);
        self.dfl_active = false;
        self.next = 0;
    }

    /// The commands of cycle `k`, then one step.
    fn step(
        &mut self,
        p: &Platform,
        k: usize,
        cmds: &[(usize, CommandKind)],
        s: &Step,
    ) -> (ReferenceSample, Option<ControlOutput>) {
        while self.next < cmds.len() && cmds[self.next].0 <= k {
            match &cmds[self.next].1 {
                CommandKind::Motion(m) => self
                    .shaper
                    .command(m.twist, m.legs.as_ref().map(|l| l.as_slice())),
                CommandKind::Legs(l) => self.shaper.command_legs(l.as_slice()),
                _ => {}
            }
            self.next += 1;
        }
        let dt = p.dt();
        let reference = self.shaper.step();
        if !self.control {
            return (reference, None);
        }
        let input = ControlInput {
            measured_twist: Some(s.odo.twist_world),
            t: 0.0,
            dt,
            measurement: &s.measurement,
            pose: s.odo.pose,
            reference: &reference,
        };
        // The DFL tracks while the reference moves, the kinematic controller near rest.
        let mut v_ref = 0.0f64;
        for i in 0..p.n() {
            let u = rollbase_control::limits::contact_kinematics(p, i, &reference)[0];
            v_ref = v_ref.max(u[0].hypot(u[1]));
        }
        let entry = if self.dfl_active {
            rollbase_control::dfl::EPSILON
        } else {
            DFL_ENTRY_SPEED
        };
        let want = v_ref >= entry;
        if want && !self.dfl_active {
            self.dfl.reset(p, &reference);
        }
        if !want && self.dfl_active {
            self.kin.reset(p, &reference);
        }
        self.dfl_active = want;
        let mut o = if want {
            self.dfl.step(p, &input)
        } else {
            self.kin.step(p, &input)
        };
        if want && (o.finished || o.singular) {
            self.dfl_active = false;
            self.kin.reset(p, &reference);
            o = self.kin.step(p, &input);
        }
        (reference, Some(o))
    }
}

/// Closed loop against the ideal plant with the full stack (avoidance on); returns every
/// cycle's controller inputs.
fn record(p: &Platform, cmds: &[(usize, CommandKind)]) -> Vec<Step> {
    let dt = p.dt();
    let legs: Vec<f64> = p.wheels.iter().map(|w| w.lambda_nominal).collect();
    let mut plant = IdealPlant::new(p, Pose::default(), &legs, &vec![0.0; p.n()]);
    let mut odom = Odometry::new(Pose::default());
    let mut stack = LiveStack::new(p, true, true);
    let steps = (SESSION_S / dt) as usize + 500;
    let mut out = Vec::with_capacity(steps);
    let mut worst = 0.0f64;
    for k in 0..steps {
        let measurement = plant.measurement();
        let odo = odom.update(p, &measurement, dt);
        let s = Step { measurement, odo };
        let (reference, o) = stack.step(p, k, cmds, &s);
        let Some(o) = o else {
            unreachable!("the recording stack controls")
        };
        worst = worst.max((reference.z[0] - odo.pose.x).hypot(reference.z[1] - odo.pose.y));
        out.push(s);
        plant.step(p, &o.command, dt);
    }
    // Sanity: the recording tracked its reference (a diverged loop would time garbage).
    println!(
        "live session: {} cycles, largest position error against the reference {:.2} mm",
        out.len(),
        worst * 1e3
    );
    assert!(worst < 0.05, "the recording loop did not track: {worst} m");
    out
}

/// Replays the whole recording once with allocation counting on; prints the count.
fn count_allocations(name: &str, p: &Platform, steps: &[Step], cmds: &[(usize, CommandKind)]) {
    let (avoid, control) = case(name);
    let mut stack = LiveStack::new(p, avoid, control);
    reset();
    set_counting(true);
    for (k, s) in steps.iter().enumerate() {
        black_box(stack.step(p, k, cmds, black_box(s)));
    }
    set_counting(false);
    println!("ALLOCS live/{name} {} {}", allocations(), steps.len());
}

/// (avoidance, controller) of a case.
fn case(name: &str) -> (bool, bool) {
    match name {
        "shaper_avoid_control" => (true, true),
        "shaper_control" => (false, true),
        "shaper_only" => (false, false),
        other => unreachable!("no case {other}"),
    }
}

/// p50, p99 and max of per-step times (ns), and the step of the max, printed as a
/// `STEPTIME <id> <p50> <p99> <max> <steps> <step of the max>` line.
fn print_step_times(id: &str, ns: Vec<f64>) {
    let worst = (0..ns.len()).fold(0, |w, k| if ns[k] > ns[w] { k } else { w });
    let mut sorted = ns.clone();
    sorted.sort_by(|a, b| a.total_cmp(b));
    let at = |q: f64| sorted[((q * ns.len() as f64).ceil() as usize).clamp(1, ns.len()) - 1];
    println!(
        "STEPTIME {id} {:.0} {:.0} {:.0} {} {worst}",
        at(0.50),
        at(0.99),
        sorted[ns.len() - 1],
        ns.len()
    );
}

/// Replays of the session whose per-step times are combined (each step's minimum): a step
/// the machine preempted in one replay is not preempted in all of them, so what remains is
/// the step's own cost.
const TIMED_REPLAYS: usize = 5;

/// Replays the whole recording [`TIMED_REPLAYS`] times, timing every step alone.
fn step_times(name: &str, p: &Platform, steps: &[Step], cmds: &[(usize, CommandKind)]) {
    let (avoid, control) = case(name);
    let mut best = vec![f64::INFINITY; steps.len()];
    for _ in 0..TIMED_REPLAYS {
        let mut stack = LiveStack::new(p, avoid, control);
        for (k, s) in steps.iter().enumerate() {
            let at = Instant::now();
            black_box(stack.step(p, k, cmds, black_box(s)));
            best[k] = best[k].min(at.elapsed().as_nanos() as f64);
        }
    }
    print_step_times(&format!("live/{name}"), best);
}

fn bench_case(
    c: &mut Criterion,
    name: &str,
    p: &Platform,
    steps: &[Step],
    cmds: &[(usize, CommandKind)],
) {
    count_allocations(name, p, steps, cmds);
    step_times(name, p, steps, cmds);
    let (avoid, control) = case(name);
    let mut stack = LiveStack::new(p, avoid, control);
    let mut k = 0usize;
    c.bench_function(&format!("live/{name}"), |b| {
        b.iter(|| {
            if k == steps.len() {
                k = 0;
                stack.reset(p);
            }
            let o = stack.step(p, k, cmds, black_box(&steps[k]));
            k += 1;
            black_box(o)
        })
    });
}

/// The live cycle core, the simulator and the virtual bus, advanced one cycle at a time
/// with the session's commands (times from the moment the core follows commands).
struct CoreHarness {
    core: CycleCore,
    sim: Simulator,
    bus: VirtualLockstepBus,
    st: LockstepState,
    cmds: Vec<CommandEvent>,
    next: usize,
    ready_at: Option<f64>,
}

impl CoreHarness {
    fn new(p: &Platform, cmds: &[CommandEvent]) -> Self {
        let mut core = match CycleCore::new_live(p.clone(), RuntimeConfig::default()) {
            Ok(c) => c,
            Err(e) => panic!("cycle core: {e}"),
        };
        let sim = match Simulator::with_config(
            p,
            SimConfig {
                seed: 5,
                ..SimConfig::default()
            },
        ) {
            Ok(s) => s,
            Err(e) => panic!("simulator: {e}"),
        };
        core.arm();
        let st = LockstepState::new(&core);
        Self {
            core,
            sim,
            bus: VirtualLockstepBus::new(FaultModel::none(), 5),
            st,
            cmds: cmds.to_vec(),
            next: 0,
            ready_at: None,
        }
    }

    fn finished(&self) -> bool {
        self.next == self.cmds.len() || self.core.done()
    }

    /// One cycle; returns the time spent in the core (command port included) and, with
    /// `count`, counts its allocations.
    fn cycle(&mut self, count: bool) -> Duration {
        let mut spent = Duration::ZERO;
        let t = self.st.time();
        if self.ready_at.is_none() && self.core.state() == SupervisorState::Tracking {
            self.ready_at = Some(t);
        }
        if let Some(t0) = self.ready_at {
            while self.next < self.cmds.len() && self.cmds[self.next].t <= t - t0 + 1e-9 {
                let mut ev = self.cmds[self.next];
                ev.t = t;
                set_counting(count);
                let at = Instant::now();
                self.core.command(ev);
                spent += at.elapsed();
                set_counting(false);
                self.next += 1;
            }
        }
        let mut entered = Instant::now();
        let mut hook = |on: bool| {
            if on {
                set_counting(count);
                entered = Instant::now();
            } else {
                spent += entered.elapsed();
                set_counting(false);
            }
        };
        let mut hooks = StepHooks {
            around_core: Some(&mut hook),
            ..Default::default()
        };
        lockstep_cycle(
            &mut self.st,
            &mut self.core,
            &mut self.bus,
            &mut self.sim,
            &mut hooks,
        );
        black_box(self.core.base_state());
        spent
    }
}

fn benches(c: &mut Criterion) {
    // What else the machine was doing (perf-report prints it beside the figures).
    if let Ok(l) = std::fs::read_to_string("/proc/loadavg") {
        println!("LOADAVG {}", l.trim());
    }
    let p = Platform::justin();
    let events = session(11);
    let cmds = schedule(&p, &events);
    let steps = record(&p, &cmds);
    for name in ["shaper_avoid_control", "shaper_control", "shaper_only"] {
        bench_case(c, name, &p, &steps, &cmds);
    }

    // The whole live cycle: allocations over one session, then timing.
    let mut h = CoreHarness::new(&p, &events);
    reset();
    let mut cycles = 0u64;
    while !h.finished() && cycles < 20_000 {
        h.cycle(true);
        cycles += 1;
    }
    assert_eq!(h.next, events.len(), "the session ran to its end");
    println!(
        "ALLOCS live/cycle_core_whole_cycle {} {cycles}",
        allocations()
    );
    // The session is deterministic (seeded simulator, virtual time): cycle k is the same
    // work in every replay.
    let mut best = vec![f64::INFINITY; cycles as usize];
    for _ in 0..TIMED_REPLAYS {
        let mut h = CoreHarness::new(&p, &events);
        for b in best.iter_mut() {
            *b = b.min(h.cycle(false).as_nanos() as f64);
        }
    }
    print_step_times("live/cycle_core_whole_cycle", best);
    let mut h = CoreHarness::new(&p, &events);
    c.bench_function("live/cycle_core_whole_cycle", |b| {
        b.iter_custom(|iters| {
            let mut total = Duration::ZERO;
            for _ in 0..iters {
                if h.finished() {
                    h = CoreHarness::new(&p, &events);
                }
                total += h.cycle(false);
            }
            total
        })
    });
}

criterion_group!(live, benches);
criterion_main!(live);
