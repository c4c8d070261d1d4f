//! Property test (issue 8): over random seeded feasible waypoint trajectories, both
//! controllers' commands through the whole stack are always finite and within the platform's
//! limits (plus the supervisor's 20 % margin), and no run faults.

use proptest::prelude::*;
use rollbase_control::reference::trajectory::Waypoint;
use rollbase_control::runtime::scenario::Scenario;
use rollbase_control::runtime::ControllerKind;
use rollbase_control::{Platform, ZVec, MAX_WHEELS};
use rollbase_tests::campaign::{Hooks, Rig, RigOptions};

fn waypoints(dx: f64, dy: f64, dth: f64, legs: [f64; 4], t: f64) -> Vec<Waypoint> {
    let mut a = ZVec::zeros();
    let mut b = ZVec::zeros();
    for i in 0..4 {
        a[3 + i] = 0.45;
        b[3 + i] = legs[i];
    }
    b[0] = dx;
    b[1] = dy;
    b[2] = dth;
    vec![Waypoint { t: 0.0, z: a }, Waypoint { t, z: b }]
}

proptest! {
    // Seeded (issue 8: "random (seeded) feasible trajectories"): every run draws the same
    // cases, so a failure here is reproducible and never depends on the day.
    #![proptest_config(ProptestConfig {
        cases: 12,
        rng_seed: proptest::test_runner::RngSeed::Fixed(0x5eed_0008),
        failure_persistence: None,
        ..ProptestConfig::default()
    })]
    #[test]
    fn commands_are_finite_and_within_limits(
        dx in -0.6f64..0.6,
        dy in -0.6f64..0.6,
        dth in -1.0f64..1.0,
        legs in proptest::array::uniform4(0.40f64..0.52),
        dur in 3.0f64..5.0,
        dfl in any::<bool>(),
        seed in 1u64..1000,
    ) {
        // Feasible by construction: at least 0.3 m or 0.5 rad of motion (never all wheels
        // at rest mid-way), speeds well inside the limits (checked by CycleCore::new too).
        prop_assume!(dx.hypot(dy) > 0.3 || dth.abs() > 0.5);
        let mut o = RigOptions::new(Scenario::Seed000);
        o.seed = seed;
        o.runtime.controller = if dfl { ControllerKind::Dfl } else { ControllerKind::Kinematic };
        o.waypoints = Some(waypoints(dx, dy, dth, legs, dur));
        let mut rig = Rig::new(&o).map_err(TestCaseError::fail)?;
        let p = Platform::justin();
        let ws = p.limits.wheel_speed * 1.2;
        let sr = p.limits.steer_rate * 1.2;
        let max = ((dur + 6.0) * 250.0) as u64;
        while rig.cycle() < max {
            let Some(r) = rig.step(&mut Hooks::default()) else { continue };
            for w in &r.command.wheels[..r.n.min(MAX_WHEELS)] {
                prop_assert!(w.wheel_speed.is_finite() && w.steer_rate.is_finite());
                prop_assert!(w.wheel_speed.abs() <= ws, "wheel speed {} at cycle {}", w.wheel_speed, r.cycle);
                prop_assert!(w.steer_rate.abs() <= sr, "steer rate {} at cycle {}", w.steer_rate, r.cycle);
            }
            prop_assert!(r.reason.is_none(), "fault {:?}", r.reason);
            if rig.core.done() {
                break;
            }
        }
    }
}
