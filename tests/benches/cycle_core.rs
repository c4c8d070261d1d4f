//! `runtime::CycleCore` on the full frame path: the seed-000 scenario (DFL, avoidance on)
//! through the lockstep virtual bus against the simulated wheel modules, timing only the
//! controller's side of each cycle: `start_cycle` (SYNC), `on_frame` for the 8 feedback
//! frames and `finish_cycle` (decode, odometry, avoidance, supervisor, DFL, encode of the 4
//! SETPOINTs, record). The simulator and the bus run between the timed regions.
//!
//! A counting global allocator counts heap allocations inside the timed regions over one
//! whole scenario (line `ALLOCS cycle_core/... <allocations> <cycles>` on stdout).

use criterion::{criterion_group, criterion_main, Criterion};
use rollbase_control::avoidance::AvoidanceConfig;
use rollbase_control::runtime::{CycleCore, LockstepBus, LockstepPeer, VirtualLockstepBus};
use rollbase_control::scenario::{self, Scenario};
use rollbase_control::{Platform, MAX_WHEELS};
use rollbase_driver::fault::FaultModel;
use rollbase_driver::frame::CanFrame;
use rollbase_tests::alloc_count::{allocations, reset, set_counting, CountingAlloc};
use rollbase_vcan_sim::{FaultSchedule, PlantConfig, Simulator};
use std::hint::black_box;
use std::time::{Duration, Instant};

#[global_allocator]
static GLOBAL: CountingAlloc = CountingAlloc;

/// The controller core, the simulator and the virtual bus, advanced one cycle at a time.
struct Harness {
    p: Platform,
    core: CycleCore,
    sim: Simulator,
    bus: VirtualLockstepBus,
    k: u64,
    out: [CanFrame; MAX_WHEELS],
    pending: Vec<(Duration, CanFrame)>,
    rx: Vec<(f64, CanFrame)>,
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
        let blank = match CanFrame::new(0, &[]) {
            Ok(f) => f,
            Err(e) => panic!("empty frame: {e}"),
        };
        Self {
            p,
            core,
            sim,
            bus: VirtualLockstepBus::new(FaultModel::none(), 5),
            k: 0,
            out: [blank; MAX_WHEELS],
            pending: Vec::with_capacity(256),
            rx: Vec::with_capacity(256),
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
        let dt = self.p.dt();
        let k = self.k;
        self.k += 1;
        let t0 = Duration::from_secs_f64(k as f64 * dt);
        let tw = Duration::from_secs_f64(k as f64 * dt + 0.002);
        self.sim.advance_to(t0);
        self.bus.set_time(t0);
        set_counting(count);
        let a = Instant::now();
        let sync = self.core.start_cycle(t0.as_secs_f64());
        let start = a.elapsed();
        set_counting(false);
        let _ = self.bus.controller_send(&sync);
        while let Ok(Some(f)) = self.bus.peer_recv() {
            LockstepPeer::on_frame(&mut self.sim, f.timestamp, &f.frame);
        }
        self.sim.advance_to(tw);
        let pending = &mut self.pending;
        self.sim.drain_tx(&mut |t, f| pending.push((t, f)));
        self.pending.sort_by_key(|x| x.0);
        for (t, f) in self.pending.drain(..) {
            self.bus.set_time(t.min(tw));
            let _ = self.bus.peer_send(&f);
        }
        self.bus.set_time(tw);
        self.rx.clear();
        while let Ok(Some(f)) = self.bus.controller_recv() {
            self.rx.push((f.timestamp.as_secs_f64(), f.frame));
        }
        set_counting(count);
        let b = Instant::now();
        for (t, f) in &self.rx {
            self.core.on_frame(f, *t);
        }
        let m = self.core.finish_cycle(tw.as_secs_f64(), &mut self.out);
        black_box(self.core.record());
        let finish = b.elapsed();
        set_counting(false);
        for f in self.out.iter().take(m) {
            let _ = self.bus.controller_send(f);
        }
        while let Ok(Some(f)) = self.bus.peer_recv() {
            LockstepPeer::on_frame(&mut self.sim, f.timestamp, &f.frame);
        }
        CoreTime { start, finish }
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
