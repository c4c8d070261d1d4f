//! Issue 23's joystick sessions on eight sticks instead of one: `e2e_flow.rs` runs one stick
//! (seed 23) per noise level on both wire profiles; this runs the sticks of
//! `shaper_streams.rs` (seeds 23, 1–7) through the same closed loop (native profile: frame
//! path, simulated modules and plant, controller) at σ = 0, 0.02 and 0.05 m/s, so that a
//! change of the shaper is judged on more than one session in closed loop too.
//!
//! Asserted, for every run: the tracking bounds of every closed-loop acceptance test (ends
//! Stopped, 5 mm, 0.5°, 2 mm) and no limit violation on any pair of commands. Over the runs,
//! at the level the live shaper achieves now (measured figures with the constants), so that
//! it cannot get worse unnoticed:
//! - the noise-free sessions' mean path, as a share of the ideal execution's
//!   ([`ideal_path_length`]; issue 23 asks 90 % of each);
//! - how many of the sixteen noisy runs meet every bound of issue 23 ([`LiveBounds::ISSUE`]:
//!   path ≥ 90 % of the same stick's noise-free run, reversals, aligning standing).
//!
//! Every run prints a `SESSIONS` line (`cargo test -p rollbase-tests --test flow_sessions
//! -- --nocapture | grep SESSIONS`).

use rollbase_control::Protocol;
use rollbase_tests::flow::*;
use rollbase_tests::{
    assert_commands_within_limits, assert_tracking_bounds, run_live, LiveOptions,
};

/// The sticks (as `shaper_streams.rs`).
const SEEDS: [u64; 8] = [23, 1, 2, 3, 4, 5, 6, 7];
/// Length of each session (s).
const SESSION_S: f64 = 20.0;
/// Mean path of the noise-free sessions (share of the ideal execution's) achieved now: 72.4 %
/// (64.3 % before the start's speed took what the turn leaves of the acceleration share,
/// transitions went through intermediate twists, noisy goals kept their direction and goals
/// capped to a crawl became rest).
const MEAN_PATH_ACHIEVED: f64 = 0.72;
/// Noisy runs (of 16) that meet every bound of issue 23, achieved now: 11 (7 before the
/// same changes, when seed 3 at σ = 0.02 m/s also left its legs 2.6 mm off their reference,
/// beyond the 2 mm tracking bound).
const NOISY_RUNS_MEETING_ACHIEVED: usize = 11;

#[test]
fn eight_joystick_sessions_per_noise_level_in_closed_loop() {
    let p = rollbase_control::Platform::justin();
    let timeout = p.service.command_timeout;
    let opts = LiveOptions {
        profile: Protocol::Native,
        max_seconds: SESSION_S + RELEASE_S + 15.0,
        ..LiveOptions::default()
    };
    let mut failures: Vec<String> = Vec::new();
    let (mut mean_path, mut meeting) = (0.0, 0usize);
    for seed in SEEDS {
        let clean = joystick_session(seed, SESSION_S, 0.0);
        let ideal = ideal_path_length(&clean, timeout);
        let own = command_reversals(&clean, &p);
        let mut noise_free_path = 0.0;
        for sigma in [0.0, 0.02, 0.05] {
            let name = format!("seed {seed}, σ = {sigma} m/s");
            let out = run_live(&opts, &joystick_session(seed, SESSION_S, sigma));
            // The path's reference as in `e2e_flow.rs`: the ideal execution for the
            // noise-free stick, the noise-free run for the noisy ones.
            let reference = if sigma == 0.0 { ideal } else { noise_free_path };
            let fig = LiveFigures::of(&out, SESSION_S, reference, own);
            if sigma == 0.0 {
                noise_free_path = fig.truth_path_m;
                mean_path += fig.truth_path_m / ideal / SEEDS.len() as f64;
            }
            let missed = fig.misses(&LiveBounds::ISSUE);
            if sigma > 0.0 && missed.is_empty() {
                meeting += 1;
            }
            println!(
                "SESSIONS {name}: {fig}; issue 23 bounds: {}",
                if missed.is_empty() {
                    "met".to_string()
                } else {
                    format!("missed ({})", missed.join("; "))
                }
            );
            failures.extend(
                failure_of(|| assert_tracking_bounds(&out.summary, &name))
                    .into_iter()
                    .chain(failure_of(|| assert_commands_within_limits(&out)))
                    .map(|f| format!("{name}: {f}")),
            );
        }
    }
    println!(
        "SESSIONS noise-free mean path {:.1} % of the ideal; {meeting} of 16 noisy runs meet \
         every bound of issue 23",
        100.0 * mean_path
    );
    if mean_path < MEAN_PATH_ACHIEVED {
        failures.push(format!(
            "noise-free mean path {:.1} % (achieved: ≥ {:.0} %)",
            100.0 * mean_path,
            100.0 * MEAN_PATH_ACHIEVED
        ));
    }
    if meeting < NOISY_RUNS_MEETING_ACHIEVED {
        failures.push(format!(
            "{meeting} of 16 noisy runs meet issue 23's bounds (achieved: \
             ≥ {NOISY_RUNS_MEETING_ACHIEVED})"
        ));
    }
    assert!(failures.is_empty(), "{}", failures.join("\n"));
}
