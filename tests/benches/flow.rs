//! Issue 23's benchmarks ("Motion that flows"):
//!
//! - `flow/plan_60_waypoints`: planning the timing of a 60-waypoint file
//!   ([`ScaledTrajectory::plan`] with the runtime's default time scaling, on
//!   [`rollbase_tests::flow::waypoint_tour`]: 60 waypoints over about 20 m, legs moving now and
//!   then, every tenth waypoint untimed) — the work done once before a `demo --trajectory` or
//!   `drive --trajectory` run starts, with the spline's construction;
//! - `flow/shaper_joystick_every_cycle`: the live shaper per cycle with a command that changes
//!   every cycle: the noisy joystick of `rollbase_tests::flow` (σ = 0.05 m/s, 2σ rad/s on ω)
//!   sampled at 250 Hz, so every cycle brings a new goal (`Shaper::command`, then
//!   `Shaper::step`), 30 s then the release to rest;
//! - `flow/shaper_rolling_joystick_every_cycle`: the same with rolling turns
//!   (`ShaperConfig::rolling_turns`, experimental, off by default): each cycle runs the
//!   turn's braking look-ahead (up to 800 cycles of every wheel's angle, bisected up to 12
//!   times when a step fails it), so its worst step is what a real-time cycle must budget
//!   for.
//!
//! As in `live.rs`, a counting global allocator counts heap allocations over one full replay
//! of the joystick session (`ALLOCS <bench> <allocations> <steps>`: 0 expected, the shaper is
//! in the 250 Hz cycle), and more replays time every step alone, keeping each step's minimum
//! (`STEPTIME <bench> <p50 ns> <p99 ns> <max ns> <steps> <step of the max>`); `perf-report`
//! reads both lines. The planning benchmark allocates by design (it builds the plan once,
//! before the run), so its allocations are printed for the record only.

use criterion::{criterion_group, criterion_main, Criterion};
use rollbase_control::reference::shaper::{Shaper, ShaperConfig};
use rollbase_control::reference::timescale::{ScaledTrajectory, TimeScaleConfig};
use rollbase_control::reference::trajectory::{QuinticSpline, Trajectory};
use rollbase_control::service::ports::CommandKind;
use rollbase_control::types::{Pose, Twist};
use rollbase_control::Platform;
use rollbase_tests::alloc_count::{allocations, reset, set_counting, CountingAlloc};
use rollbase_tests::flow::{joystick_session_at, waypoint_tour};
use std::hint::black_box;
use std::time::Instant;

#[global_allocator]
static GLOBAL: CountingAlloc = CountingAlloc;

/// Length of the joystick session (s).
const SESSION_S: f64 = 30.0;
/// Noise of the joystick session (m/s; 2σ rad/s on ω).
const SIGMA: f64 = 0.05;
/// Replays whose per-step minimum is kept.
const TIMED_REPLAYS: usize = 5;

/// The session's twists, one per cycle.
fn twists(p: &Platform) -> Vec<Twist> {
    joystick_session_at(23, SESSION_S, SIGMA, p.cycle_hz)
        .iter()
        .filter_map(|e| match e.kind {
            CommandKind::Motion(m) => Some(m.twist),
            _ => None,
        })
        .collect()
}

/// The shaper of `cfg` at rest at the origin, legs nominal, wheels straight.
fn fresh_shaper(p: &Platform, cfg: ShaperConfig) -> Shaper {
    let mut s = Shaper::new(p, cfg);
    let legs: Vec<f64> = p.wheels.iter().map(|w| w.lambda_nominal).collect();
    s.reset(Pose::default(), &legs, &vec![0.0; p.n()]);
    s
}

/// One cycle: the new goal, then the shaped sample.
fn cycle(s: &mut Shaper, t: &Twist) -> rollbase_control::ReferenceSample {
    s.command(*t, None);
    s.step()
}

/// p50, p99 and max of per-step times (ns) as a `STEPTIME` line.
fn print_step_times(id: &str, ns: &[f64]) {
    let worst = (0..ns.len()).fold(0, |w, k| if ns[k] > ns[w] { k } else { w });
    let mut sorted = ns.to_vec();
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

fn shaper_bench(c: &mut Criterion) {
    if let Ok(l) = std::fs::read_to_string("/proc/loadavg") {
        println!("LOADAVG {}", l.trim());
    }
    let p = Platform::justin();
    let tw = twists(&p);
    let rolling = ShaperConfig {
        rolling_turns: true,
        ..ShaperConfig::default()
    };
    for (id, cfg) in [
        ("flow/shaper_joystick_every_cycle", ShaperConfig::default()),
        ("flow/shaper_rolling_joystick_every_cycle", rolling),
    ] {
        every_cycle(c, &p, &tw, id, cfg);
    }
}

/// The shaper of `cfg`, a new goal every cycle: allocations over one replay, per-step times
/// over [`TIMED_REPLAYS`] more, then criterion.
fn every_cycle(c: &mut Criterion, p: &Platform, tw: &[Twist], id: &str, cfg: ShaperConfig) {
    let mut s = fresh_shaper(p, cfg);
    reset();
    set_counting(true);
    for t in tw {
        black_box(cycle(&mut s, black_box(t)));
    }
    set_counting(false);
    println!("ALLOCS {id} {} {}", allocations(), tw.len());
    let mut best = vec![f64::INFINITY; tw.len()];
    for _ in 0..TIMED_REPLAYS {
        let mut s = fresh_shaper(p, cfg);
        for (b, t) in best.iter_mut().zip(tw) {
            let at = Instant::now();
            black_box(cycle(&mut s, black_box(t)));
            *b = b.min(at.elapsed().as_nanos() as f64);
        }
    }
    print_step_times(id, &best);
    let mut s = fresh_shaper(p, cfg);
    let mut k = 0usize;
    c.bench_function(id, |b| {
        b.iter(|| {
            if k == tw.len() {
                k = 0;
                s = fresh_shaper(p, cfg);
            }
            let r = cycle(&mut s, black_box(&tw[k]));
            k += 1;
            black_box(r)
        })
    });
}

/// Planning a 60-waypoint file (criterion samples of a few plans each: sample size 10).
fn plan_bench(c: &mut Criterion) {
    let p = Platform::justin();
    let id = "flow/plan_60_waypoints";
    let w = waypoint_tour(60, 60);
    let plan = || {
        let spline = QuinticSpline::from_specs(&p, &w).expect("a valid file");
        ScaledTrajectory::plan(&p, Box::new(spline), TimeScaleConfig::default())
    };
    reset();
    set_counting(true);
    let first = plan();
    set_counting(false);
    let planned = first.expect("a plannable file");
    println!(
        "PLAN {id}: 60 waypoints, nominal {:.2} s, executed {:.2} s, {} allocations (once, before the run)",
        planned.inner().duration(),
        planned.duration(),
        allocations()
    );
    c.bench_function(id, |b| b.iter(|| black_box(plan())));
}

criterion_group!(shaper, shaper_bench);
criterion_group! {
    name = plan;
    config = Criterion::default().sample_size(10);
    targets = plan_bench
}
criterion_main!(shaper, plan);
