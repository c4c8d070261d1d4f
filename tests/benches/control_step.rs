//! One control step, measured: odometry → singularity avoidance → tracking controller for the
//! four wheels of the default platform, the order `runtime::CycleCore::finish_cycle` runs them.
//!
//! Inputs are recorded first from a closed loop against the ideal kinematic plant (seed-000
//! and seed-001 scenarios) and then replayed step by step, so every timed step sees the
//! measurements and reference of a real run and the controller states evolve exactly as they
//! did in that run. A counting global allocator counts heap allocations over one full replay
//! of each recording (lines `ALLOCS <bench> <allocations> <steps>` on stdout, read by
//! `benches/report.sh`).

use criterion::{criterion_group, criterion_main, Criterion};
use rollbase_control::estimation::odometry::{Odometry, OdometryOutput};
use rollbase_control::model::ideal_plant::IdealPlant;
use rollbase_control::reference::avoidance::{Avoidance, AvoidanceConfig};
use rollbase_control::reference::trajectory::Trajectory;
use rollbase_control::runtime::scenario::{self, Scenario};
use rollbase_control::tracking::dfl::{
    alignment_command, ControlInput, ControlOutput, DflController, TrackingController,
};
use rollbase_control::tracking::kinematic::KinematicController;
use rollbase_control::{Measurement, Platform, ReferenceSample};
use rollbase_tests::alloc_count::{allocations, reset, set_counting, CountingAlloc};
use std::hint::black_box;

#[global_allocator]
static GLOBAL: CountingAlloc = CountingAlloc;

/// Which parts of the step run.
#[derive(Clone, Copy)]
struct Parts {
    odometry: bool,
    avoidance: bool,
    controller: Option<Kind>,
}

#[derive(Clone, Copy, PartialEq)]
enum Kind {
    Dfl,
    Kinematic,
}

/// One recorded cycle: what the step gets, and what the full stack computed on the way
/// (used when a part is left out, so the remaining parts see the recorded values).
#[derive(Clone, Copy)]
struct Step {
    t: f64,
    measurement: Measurement,
    nominal: ReferenceSample,
    odo: OdometryOutput,
    reference: ReferenceSample,
}

/// What one step produced (kept alive with `black_box`).
type StepOut = (OdometryOutput, ReferenceSample, Option<ControlOutput>);

/// The per-cycle control stack of the runtime, without IO.
struct Stack {
    parts: Parts,
    odo: Odometry,
    avoid: Avoidance,
    ctrl: Box<dyn TrackingController>,
    r0: ReferenceSample,
}

impl Stack {
    fn new(p: &Platform, r0: ReferenceSample, parts: Parts) -> Self {
        let ctrl: Box<dyn TrackingController> = match parts.controller.unwrap_or(Kind::Dfl) {
            Kind::Dfl => Box::new(DflController::new(p)),
            Kind::Kinematic => Box::new(KinematicController::new(p)),
        };
        let mut s = Self {
            parts,
            odo: Odometry::new(r0.pose()),
            avoid: Avoidance::new(p, AvoidanceConfig::default()),
            ctrl,
            r0,
        };
        s.reset(p);
        s
    }

    fn reset(&mut self, p: &Platform) {
        self.odo = Odometry::new(self.r0.pose());
        self.avoid.reset();
        self.ctrl.reset(p, &self.r0);
    }

    /// Odometry → avoidance → controller, as `CycleCore::finish_cycle` orders them.
    fn step(&mut self, p: &Platform, s: &Step) -> StepOut {
        let dt = p.dt();
        let odo = if self.parts.odometry {
            self.odo.update(p, &s.measurement, dt)
        } else {
            s.odo
        };
        let reference = if self.parts.avoidance {
            self.avoid.step(p, &s.nominal, dt).0
        } else {
            s.reference
        };
        let out = self.parts.controller.map(|_| {
            self.ctrl.step(
                p,
                &ControlInput {
                    measured_twist: Some(odo.twist_world),
                    t: s.t,
                    dt,
                    measurement: &s.measurement,
                    pose: odo.pose,
                    reference: &reference,
                },
            )
        });
        (odo, reference, out)
    }
}

/// Closed loop against the ideal plant: align open loop, then track with the full stack;
/// returns every tracking cycle's inputs.
fn record(p: &Platform, sc: Scenario, kind: Kind) -> Vec<Step> {
    let traj: Box<dyn Trajectory> = match scenario::trajectory(sc, p) {
        Ok(t) => t,
        Err(e) => panic!("built-in scenario {}: {e}", sc.name()),
    };
    let dt = p.dt();
    let n = p.n();
    let r0 = traj.sample(0.0);
    let legs: Vec<f64> = (0..n).map(|i| r0.z[3 + i]).collect();
    let mut plant = IdealPlant::new(p, r0.pose(), &legs, &vec![0.0; n]);
    for _ in 0..2500 {
        let (cmd, err) = alignment_command(p, &plant.measurement(), &r0);
        if err < 1e-6 {
            break;
        }
        plant.step(p, &cmd, dt);
    }
    let parts = Parts {
        odometry: true,
        avoidance: true,
        controller: Some(kind),
    };
    let mut stack = Stack::new(p, r0, parts);
    let steps = (traj.duration() / dt).ceil() as usize;
    let mut out = Vec::with_capacity(steps + 1);
    for k in 0..=steps {
        let t = k as f64 * dt;
        let mut s = Step {
            t,
            measurement: plant.measurement(),
            nominal: traj.sample(t),
            odo: OdometryOutput::default(),
            reference: traj.sample(t),
        };
        let (odo, reference, o) = stack.step(p, &s);
        let Some(o) = o else {
            unreachable!("the recording stack has a controller")
        };
        s.odo = odo;
        s.reference = reference;
        out.push(s);
        if o.finished {
            break;
        }
        plant.step(p, &o.command, dt);
    }
    out
}

/// Replays `steps` once with allocation counting on; prints the count.
fn count_allocations(name: &str, p: &Platform, steps: &[Step], parts: Parts) {
    let mut stack = Stack::new(p, steps[0].nominal, parts);
    reset();
    set_counting(true);
    for s in steps {
        black_box(stack.step(p, black_box(s)));
    }
    set_counting(false);
    println!(
        "ALLOCS control_step/{name} {} {}",
        allocations(),
        steps.len()
    );
}

fn bench_case(c: &mut Criterion, name: &str, p: &Platform, steps: &[Step], parts: Parts) {
    count_allocations(name, p, steps, parts);
    let mut stack = Stack::new(p, steps[0].nominal, parts);
    let mut k = 0usize;
    c.bench_function(&format!("control_step/{name}"), |b| {
        b.iter(|| {
            if k == steps.len() {
                k = 0;
                stack.reset(p);
            }
            let o = stack.step(p, black_box(&steps[k]));
            k += 1;
            black_box(o)
        })
    });
}

fn benches(c: &mut Criterion) {
    let p = Platform::justin();
    let dfl000 = record(&p, Scenario::Seed000, Kind::Dfl);
    let kin000 = record(&p, Scenario::Seed000, Kind::Kinematic);
    let kin001 = record(&p, Scenario::Seed001, Kind::Kinematic);
    let all = |k| Parts {
        odometry: true,
        avoidance: true,
        controller: Some(k),
    };
    let only = |odometry, avoidance, controller| Parts {
        odometry,
        avoidance,
        controller,
    };
    bench_case(c, "dfl_avoid_odom_seed000", &p, &dfl000, all(Kind::Dfl));
    bench_case(
        c,
        "kinematic_avoid_odom_seed000",
        &p,
        &kin000,
        all(Kind::Kinematic),
    );
    bench_case(
        c,
        "kinematic_avoid_odom_seed001",
        &p,
        &kin001,
        all(Kind::Kinematic),
    );
    bench_case(
        c,
        "dfl_only_seed000",
        &p,
        &dfl000,
        only(false, false, Some(Kind::Dfl)),
    );
    bench_case(
        c,
        "kinematic_only_seed000",
        &p,
        &kin000,
        only(false, false, Some(Kind::Kinematic)),
    );
    bench_case(
        c,
        "odometry_only_seed000",
        &p,
        &dfl000,
        only(true, false, None),
    );
    bench_case(
        c,
        "avoidance_only_seed001",
        &p,
        &kin001,
        only(false, true, None),
    );
}

criterion_group!(control_step, benches);
criterion_main!(control_step);
