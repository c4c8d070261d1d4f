//! How far can the live shaper get on issue 23's noise-free joystick, and what holds it back?
//! Runs the eight noise-free sticks of `tests/tests/shaper_streams.rs` (20 s each) through the
//! shaper alone and prints the mean path as a share of the ideal execution's
//! ([`ideal_path_length`]: every message's twist held exactly), against:
//!
//! - **steering-free bounds**: the twist moves straight towards the command (capped to the
//!   wheel speed, one factor, direction kept), each cycle as far as the wheels' acceleration
//!   allows, and nothing else: no steering limit, no alignment ([`unsteered_path_length`]).
//!   What a shaper that moves the twist along straight lines within those two limits can
//!   travel at most while following the stick (it never moves faster than the stick asks);
//! - **the shaper with Justin's steering limits scaled** (rate and acceleration together,
//!   ×1 to ×10), with its margins as configured and with them removed (acceleration share
//!   1.0, speed share 0.97, lateral acceleration 20 m/s²);
//! - **where the default shaper's shortfall goes**: each cycle's (asked speed − reference
//!   speed) booked under the limit the shaper reports as binding;
//! - **the shaper with rolling turns** ([`rollbase_control::reference::roll`], off by default:
//!   the direction turned within the steering limits while the speed stays up), its
//!   shortfall booked the same way.
//!
//! `cargo run --release -p rollbase-tests --example joystick_limits` (about 4.5 s, most of it the rolling turns).

use rollbase_control::reference::shaper::{Shaper, ShaperConfig};
use rollbase_control::service::ports::CommandEvent;
use rollbase_control::Platform;
use rollbase_tests::flow::{
    drive_shaper, ideal_path_length, joystick_session, unsteered_path_length, RELEASE_S,
};
use std::collections::BTreeMap;

/// The sticks of `tests/tests/shaper_streams.rs`.
const SEEDS: [u64; 8] = [23, 1, 2, 3, 4, 5, 6, 7];
/// Length of each session (s).
const SESSION_S: f64 = 20.0;

fn sessions() -> Vec<Vec<CommandEvent>> {
    SEEDS
        .iter()
        .map(|&s| joystick_session(s, SESSION_S, 0.0))
        .collect()
}

fn until() -> f64 {
    SESSION_S + RELEASE_S + 0.5
}

/// Mean path share of the steering-free follower (module docs;
/// [`unsteered_path_length`]) with the given shares of the wheel acceleration and speed
/// limits.
fn steering_free(p: &Platform, cmds: &[Vec<CommandEvent>], accel: f64, speed: f64) -> f64 {
    let timeout = p.service.command_timeout;
    cmds.iter()
        .map(|c| unsteered_path_length(c, timeout, p, speed, accel) / ideal_path_length(c, timeout))
        .sum::<f64>()
        / cmds.len() as f64
}

/// Mean path share of the shaper, and the shortfall (share of the ideal path, summed over
/// the sessions' means) and time (s, summed) per binding limit.
fn shaper(
    p: &Platform,
    cfg: ShaperConfig,
    cmds: &[Vec<CommandEvent>],
) -> (f64, BTreeMap<&'static str, (f64, f64)>) {
    let dt = p.dt();
    let mut mean = 0.0;
    let mut by: BTreeMap<&'static str, (f64, f64)> = BTreeMap::new();
    for c in cmds {
        let ideal = ideal_path_length(c, p.service.command_timeout);
        let n = cmds.len() as f64;
        let mut path = 0.0;
        let mut s = Shaper::new(p, cfg);
        drive_shaper(&mut s, c, dt, until(), |_, s, asked| {
            let q = s.velocity();
            let v = q[0].hypot(q[1]);
            path += v * dt;
            let e = by.entry(s.status().limiting.name()).or_default();
            e.0 += (asked.vx.hypot(asked.vy) - v) * dt / ideal / n;
            e.1 += dt;
        });
        mean += path / ideal / n;
    }
    (mean, by)
}

/// One line per binding limit: its shortfall (points of the ideal path) and time.
fn shortfall_lines(out: &mut String, by: &BTreeMap<&'static str, (f64, f64)>) {
    use std::fmt::Write as _;
    for (limit, (loss, time)) in by {
        writeln!(
            out,
            "  {limit:22} {:5.1} points  {time:6.1} s",
            100.0 * loss
        )
        .ok();
    }
}

fn main() {
    use std::fmt::Write as _;
    use std::io::Write as _;
    let mut out = String::new();
    let cmds = sessions();
    let justin = Platform::justin();
    writeln!(
        out,
        "Issue 23's noise-free joystick, {} sticks of {SESSION_S} s: mean path, % of the ideal \
         execution's",
        SEEDS.len()
    )
    .ok();
    writeln!(out).ok();
    writeln!(
        out,
        "steering-free bound (wheel acceleration and speed only):"
    )
    .ok();
    for (a, v) in [(0.6, 0.9), (1.0, 0.9), (1.0, 1.0)] {
        writeln!(
            out,
            "  acceleration share {a:.1}, speed share {v:.2}: {:5.1} %",
            100.0 * steering_free(&justin, &cmds, a, v)
        )
        .ok();
    }
    writeln!(out).ok();
    let default = ShaperConfig::default();
    let bare = ShaperConfig {
        accel_fraction: 1.0,
        speed_fraction: 0.97,
        lateral_accel: 20.0,
        ..default
    };
    writeln!(
        out,
        "the shaper, Justin's steering limits ({} rad/s, {} rad/s²) scaled:",
        justin.limits.steer_rate, justin.limits.steer_accel
    )
    .ok();
    writeln!(out, "  scale   margins as configured   margins removed").ok();
    for scale in [1.0, 2.0, 4.0, 10.0] {
        let mut p = justin.clone();
        p.limits.steer_rate *= scale;
        p.limits.steer_accel *= scale;
        writeln!(
            out,
            "  ×{scale:<4}  {:21.1} %  {:14.1} %",
            100.0 * shaper(&p, default, &cmds).0,
            100.0 * shaper(&p, bare, &cmds).0
        )
        .ok();
    }
    writeln!(out).ok();
    let rolling = ShaperConfig {
        rolling_turns: true,
        ..default
    };
    let (m, by) = shaper(&justin, rolling, &cmds);
    writeln!(
        out,
        "the shaper with rolling turns (`rolling_turns`, off by default; {:.1} % travelled; \
         points of the ideal path, time summed over the sessions):",
        100.0 * m
    )
    .ok();
    shortfall_lines(&mut out, &by);
    writeln!(out).ok();
    let (mean, by) = shaper(&justin, default, &cmds);
    writeln!(
        out,
        "where the shaper's shortfall goes ({:.1} % travelled; points of the ideal path, time \
         summed over the sessions):",
        100.0 * mean
    )
    .ok();
    shortfall_lines(&mut out, &by);
    // A closed pipe (`| head`) is not an error here.
    let _ = std::io::stdout().write_all(out.as_bytes());
}
