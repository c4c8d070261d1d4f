//! `runtime::CycleCore` on the full frame path: the seed-000 scenario (DFL, avoidance on)
//! through the lockstep virtual bus against the simulated wheel modules, timing only the
//! controller's side of each cycle: `start_cycle` (SYNC), `on_frame` for the 8 feedback
//! frames and `finish_cycle` (decode, odometry, avoidance, supervisor, DFL, encode of the 4
//! SETPOINTs, record). The simulator and the bus run between the timed regions.
//!
//! A counting global allocator counts heap allocations inside the timed regions over one
//! whole scenario (line `ALLOCS cycle_core/... <allocations> <cycles>` on stdout).

use criterion::{criterion_group, criterion_main, Criterion};
use rollbase_control::reference::avoidance::AvoidanceConfig;
use rollbase_control::runtime::scenario::{self, Scenario};
use rollbase_control::runtime::{
    lockstep_cycle, CycleCore, LockstepState, StepHooks, VirtualLockstepBus,
};
use rollbase_control::Platform;
use rollbase_driver::fault::FaultModel;
use rollbase_tests::alloc_count::{allocations, reset, set_counting, CountingAlloc};
use rollbase_vcan_sim::{FaultSchedule, PlantConfig, Simulator};
use std::hint::black_box;
use std::time::{Duration, Instant};

#[global_allocator]
static GLOBAL: CountingAlloc = CountingAlloc;

/// The controller core, the simulator and the virtual bus, advanced one cycle at a time.
struct Harness {
    core: CycleCore,
    sim: Simulator,
    bus: VirtualLockstepBus,
    st: LockstepState,
}

/// Wall time spent in the core during one cycle, split by phase.
#[derive(Default, Clone, Copy)]
struct CoreTime {
    start: Duration,
    finish: Duration,
}

impl Harness {
    fn new() -> Self {
        let p = Platform::justin();
        let traj = match scenario::trajectory(Scenario::Seed000, &p) {
            Ok(t) => t,
            Err(e) => panic!("seed000 scenario: {e}"),
        };
        let r0 = traj.sample(0.0);
        let mut cfg = scenario::runtime_config(Scenario::Seed000);
        cfg.avoidance = Some(AvoidanceConfig::default());
        let mut core = match CycleCore::new(p.clone(), traj, cfg) {
            Ok(c) => c,
            Err(e) => panic!("cycle core: {e}"),
        };
        let sim = match Simulator::new(&p, PlantConfig::default(), FaultSchedule::default(), &r0, 5)
        {
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
        }
    }

    fn done(&self) -> bool {
        self.core.done()
    }

    fn tracking(&self) -> bool {
        self.core.state().name() == "tracking"
    }

    /// One cycle; the calls into the core are timed and, with `count`, allocation-counted.
    fn cycle(&mut self, count: bool) -> CoreTime {
        // The driver calls the hook around `start_cycle` (first pair) and around
        // `on_frame` … `finish_cycle` (second pair).
        let mut phase = 0usize;
        let mut spans = [Duration::ZERO; 2];
        let mut entered = Instant::now();
        let mut hook = |on: bool| {
            if on {
                set_counting(count);
                entered = Instant::now();
            } else {
                spans[phase.min(1)] += entered.elapsed();
                set_counting(false);
                phase += 1;
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
        black_box(self.core.record());
        CoreTime {
            start: spans[0],
            finish: spans[1],
        }
    }
}

fn benches(c: &mut Criterion) {
    // Allocation count over one whole scenario.
    let mut h = Harness::new();
    reset();
    let mut cycles = 0u64;
    let mut tracking = 0u64;
    while !h.done() && cycles < 20_000 {
        h.cycle(true);
        cycles += 1;
        tracking += u64::from(h.tracking());
    }
    println!(
        "ALLOCS cycle_core/whole_cycle {} {cycles} (tracking cycles {tracking})",
        allocations()
    );

    // Timing over the whole scenario, restarted when it ends (rebuilt outside the timing).
    let mut h = Harness::new();
    c.bench_function("cycle_core/whole_cycle", |b| {
        b.iter_custom(|iters| {
            let mut total = Duration::ZERO;
            for _ in 0..iters {
                if h.done() {
                    h = Harness::new();
                }
                let t = h.cycle(false);
                total += t.start + t.finish;
            }
            total
        })
    });
    let mut h = Harness::new();
    c.bench_function("cycle_core/feedback_and_finish", |b| {
        b.iter_custom(|iters| {
            let mut total = Duration::ZERO;
            for _ in 0..iters {
                if h.done() {
                    h = Harness::new();
                }
                total += h.cycle(false).finish;
            }
            total
        })
    });
}

criterion_group!(cycle_core, benches);
criterion_main!(cycle_core);
