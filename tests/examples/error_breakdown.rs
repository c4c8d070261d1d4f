//! Where does the seed-000 tracking error come from? Runs the scenario through the full frame
//! path in lockstep and splits the error against ground truth into tracking error (reference
//! vs the controller's own estimate) and odometry error (estimate vs truth), every 2 s.
//!
//! `cargo run --release -p rollbase-tests --example error_breakdown [-- kinematic] [ideal]`
//! (`ideal`: simulator without noise, quantization or encoder latency).

use rollbase_control::angle;
use rollbase_control::runtime::scenario::Scenario;
use rollbase_control::runtime::ControllerKind;
use rollbase_tests::{run, RunOptions};

fn main() {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let mut opts = RunOptions::new(Scenario::Seed000);
    if args.iter().any(|a| a == "kinematic") {
        opts = opts.with_controller(ControllerKind::Kinematic);
    }
    if args.iter().any(|a| a == "ideal") {
        opts.plant = rollbase_vcan_sim::PlantConfig::ideal();
    }
    let out = run(&opts);
    let (mut worst_track, mut worst_odo, mut worst_leg) = (0.0f64, 0.0f64, 0.0f64);
    println!("  cycle  state      track(mm)  odo(mm)  odo-heading(mrad)  leg(mm)");
    for r in &out.records {
        let Some((truth, legs)) = r.truth else {
            continue;
        };
        let z = &r.reference.z;
        let track = (z[0] - r.pose.x).hypot(z[1] - r.pose.y);
        let odo = (truth.x - r.pose.x).hypot(truth.y - r.pose.y);
        let leg = (0..r.n)
            .map(|i| (z[3 + i] - legs[i]).abs())
            .fold(0.0, f64::max);
        worst_track = worst_track.max(track);
        worst_odo = worst_odo.max(odo);
        worst_leg = worst_leg.max(leg);
        if r.cycle % 500 == 0 {
            println!(
                "{:7}  {:9} {:10.3} {:8.3} {:18.4} {:8.3}",
                r.cycle,
                r.state.name(),
                track * 1e3,
                odo * 1e3,
                angle::diff(r.pose.theta, truth.theta) * 1e3,
                leg * 1e3
            );
        }
    }
    println!(
        "worst: tracking {:.3} mm, odometry {:.3} mm, legs {:.3} mm",
        worst_track * 1e3,
        worst_odo * 1e3,
        worst_leg * 1e3
    );
    println!("{}", out.summary.to_json());
}
