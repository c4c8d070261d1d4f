//! Waypoint files (issue 27, finding 7): a number that cannot be executed within the limits is
//! refused naming its field, and a spacing of exactly 10 ms, as written in decimal, is not.
//!
//! The bound on coordinates and headings (`trajectory::coordinate_limits`) comes from what
//! f64 can hold at a magnitude against the motion the encoders measure in one cycle; the
//! trajectory at the largest accepted values is run through the full frame path in lockstep
//! and held to the tracking bounds of every closed-loop test.

use rollbase_control::reference::trajectory::{coordinate_limits, QuinticSpline, Trajectory};
use rollbase_control::runtime::{run_lockstep, CycleCore, RunSummary, RuntimeConfig};
use rollbase_control::Platform;
use rollbase_driver::fault::FaultModel;
use rollbase_tests::assert_tracking_bounds;
use rollbase_vcan_sim::{InitialState, SimConfig, Simulator};

/// A waypoint file: one `[[waypoints]]` per row (t, x, y, theta), legs at 0.45 m.
fn file(rows: &[(Option<&str>, &str, &str, &str)]) -> String {
    rows.iter()
        .map(|(t, x, y, th)| {
            let t = t.map(|t| format!("t = {t}\n")).unwrap_or_default();
            format!(
                "[[waypoints]]\n{t}x = {x}\ny = {y}\ntheta = {th}\nlegs = [0.45, 0.45, 0.45, 0.45]\n\n"
            )
        })
        .collect()
}

#[test]
fn waypoints_exactly_10_ms_apart_as_written_in_decimal_are_accepted() {
    let p = Platform::justin();
    // t = 0.00, 0.01, …, 1.00: in binary floating point several neighbours are less than
    // 0.01 apart (0.03 − 0.02 = 0.009999999999999998).
    let times: Vec<String> = (0..=100)
        .map(|k| format!("{:.2}", k as f64 / 100.0))
        .collect();
    let rows: Vec<_> = times
        .iter()
        .enumerate()
        .map(|(k, t)| {
            (
                Some(t.as_str()),
                if k % 2 == 0 { "0.0" } else { "0.0001" },
                "0.0",
                "0.0",
            )
        })
        .collect();
    if let Err(e) = QuinticSpline::from_toml_str(&p, &file(&rows)) {
        panic!("10 ms apart must be accepted: {e}");
    }
    // Clearly closer than 10 ms is still refused, naming the waypoint.
    let close = file(&[
        (Some("0.0"), "0.0", "0.0", "0.0"),
        (Some("0.0099"), "0.0", "0.0", "0.0"),
    ]);
    let e = QuinticSpline::from_toml_str(&p, &close)
        .unwrap_err()
        .to_string();
    assert!(
        e.contains("waypoints[1].t") && e.contains("0.01 s apart"),
        "{e}"
    );
}

#[test]
fn coordinates_and_headings_too_large_to_execute_are_refused_naming_the_field() {
    let p = Platform::justin();
    let (xy, th) = coordinate_limits(&p);
    // The derivation's figures for the default platform (the docs quote them).
    assert_eq!(xy, 2f64.powi(25));
    assert_eq!(th, 2f64.powi(26));
    let at = |x: f64, y: f64, t: f64| {
        file(&[
            (
                Some("0.0"),
                &format!("{x:e}"),
                &format!("{y:e}"),
                &format!("{t:e}"),
            ),
            (
                Some("10.0"),
                &format!("{:e}", x + 1.0),
                &format!("{y:e}"),
                &format!("{t:e}"),
            ),
        ])
    };
    // The values of the issue (accepted before, then a wheel-slip fault and 721.9 rad/s²
    // of steering acceleration) and the first values beyond the bounds.
    for (text, field) in [
        (at(1e15, 0.0, 0.0), "waypoints[0].x"),
        (at(0.0, 0.0, 1e17), "waypoints[0].theta"),
        (at(xy * 1.001, 0.0, 0.0), "waypoints[0].x"),
        (at(0.0, -xy * 1.001, 0.0), "waypoints[0].y"),
        (at(0.0, 0.0, -th * 1.001), "waypoints[0].theta"),
    ] {
        let e = QuinticSpline::from_toml_str(&p, &text)
            .expect_err("refused")
            .to_string();
        assert!(
            e.starts_with(&format!("`{field}` = ")) && e.contains("beyond ±"),
            "{field}: {e}"
        );
    }
    assert!(QuinticSpline::from_toml_str(&p, &at(xy - 2.0, -(xy - 2.0), th - 2.0)).is_ok());
}

#[test]
fn a_trajectory_at_the_largest_accepted_coordinates_is_tracked_within_the_bounds() {
    let p = Platform::justin();
    let (xy, th) = coordinate_limits(&p);
    let (x0, y0, t0) = (xy - 4.0, -(xy - 4.0), th - 4.0);
    let text = format!(
        "[[waypoints]]\nt = 0.0\nx = {x0:?}\ny = {y0:?}\ntheta = {t0:?}\nlegs = [0.45, 0.45, 0.45, 0.45]\n\n\
         [[waypoints]]\nx = {:?}\ny = {:?}\ntheta = {:?}\nlegs = [0.5, 0.5, 0.5, 0.5]\n",
        x0 + 1.5,
        y0 + 1.0,
        t0 + 1.0
    );
    let traj = QuinticSpline::from_toml_str(&p, &text).expect("within the bounds");
    let r0 = traj.sample(0.0);
    let mut core =
        CycleCore::new(p.clone(), Box::new(traj), RuntimeConfig::default()).expect("feasible");
    let mut sim = Simulator::with_config(
        &p,
        SimConfig {
            initial: Some(InitialState::from_reference(&p, &r0)),
            ..SimConfig::default()
        },
    )
    .expect("simulator");
    let mut bus = rollbase_control::runtime::VirtualLockstepBus::new(FaultModel::none(), 0x5EED);
    let max_cycles = ((core.reference_duration() + 15.0) * p.cycle_hz) as u64;
    let mut summary = RunSummary::new("far from the origin");
    let mut prev: Option<rollbase_control::types::Command> = None;
    let mut breach = None;
    run_lockstep(
        &mut core,
        &mut bus,
        &mut sim,
        max_cycles,
        None,
        &mut |r, _| {
            summary.update(r);
            if let Some(c) = prev {
                if let Some(v) = rollbase_control::reference::limits::check_command(
                    &p.limits,
                    &c,
                    &r.command,
                    p.dt(),
                ) {
                    breach.get_or_insert(format!("cycle {}: {v}", r.cycle));
                }
            }
            prev = Some(r.command);
        },
    )
    .expect("one-bus platform, one lockstep bus");
    println!(
        "x0 = {x0} m, θ0 = {t0} rad: pos {:.3} mm, heading {:.4}°, legs {:.3} mm, {}",
        summary.max_position_error_m * 1e3,
        summary.max_heading_error_rad.to_degrees(),
        summary.max_leg_error_m * 1e3,
        summary.final_state
    );
    assert_eq!(breach, None, "every command within its limits");
    assert_tracking_bounds(&summary, "at the coordinate limits");
}
