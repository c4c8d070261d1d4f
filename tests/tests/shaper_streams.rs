//! The live shaper alone (no bus, no plant) on many joystick sessions: the flow tests
//! (`e2e_flow.rs`) run one stick per noise level through the full frame path; this runs
//! eight sticks per noise level through `Shaper` itself, which takes milliseconds, so that a
//! change of the shaper is judged on more than one session.
//!
//! Two measures, each asserted:
//! - **no creeping**: while the stick asks for at least 0.2 m/s, the reference is never
//!   slower than 3 cm/s for more than [`LONGEST_CREEP_S`] at a stretch. A start from rest
//!   with the wheels turning by up to 90° takes about 0.9 s; a twist left rolling a turning
//!   wheel inside the noise band held that wheel off its aim and crept at 1–2 cm/s for
//!   12 s (seed 2, σ = 0.02 m/s) before the capped goal was followed as a limit;
//! - **path**: the reference's mean path over the sessions, as a share of the ideal
//!   execution's ([`ideal_path_length`]), at least what the shaper achieves now
//!   ([`MEAN_PATH_ACHIEVED`]), so that it cannot get worse unnoticed. Issue 23 asks 90 % of
//!   the closed loop on one session; the shaper alone is its upper bound.

use rollbase_control::reference::shaper::{Shaper, ShaperConfig};
use rollbase_control::Platform;
use rollbase_tests::flow::{
    drive_shaper, ideal_path_length, joystick_session, unsteered_path_length, RELEASE_S,
};

/// The sessions' sticks.
const SEEDS: [u64; 8] = [23, 1, 2, 3, 4, 5, 6, 7];
/// Length of each session (s).
const SESSION_S: f64 = 20.0;
/// Longest stretch (s) the reference may creep while the stick asks to move.
const LONGEST_CREEP_S: f64 = 2.0;
/// Stick speed (m/s) from which a creep counts.
const ASKED: f64 = 0.2;
/// Reference speed (m/s) below which it creeps.
const CREEP: f64 = 0.03;
/// Mean path share per noise level (σ = 0, 0.02, 0.05 m/s) measured when this was last set:
/// 72.5 %, 65.7 %, 64.2 % since the start's speed takes what the turn leaves of the
/// acceleration share, transitions may go through an intermediate twist, a noisy goal's
/// direction is kept while only its speed changes, and a goal capped to a crawl is rest
/// (64.3 %, 61.8 %, 57.5 % since a start from rest rolls along the wheels while they turn
/// (64.2 %, 60.6 %, 56.6 % before; 63.4 %, 60.3 %, 56.0 % while the wheel-speed cap assumed
/// legs anywhere in their range; 56.2 %, 53.6 %, 44.9 % before the shaper chose sweeping or
/// stopping by what each leaves behind and let transitions finish)).
const MEAN_PATH_ACHIEVED: [(f64, f64); 3] = [(0.0, 0.72), (0.02, 0.65), (0.05, 0.64)];

/// (path share, longest creep in s) of one session through the shaper alone.
fn session(p: &Platform, seed: u64, sigma: f64) -> (f64, f64) {
    let cmds = joystick_session(seed, SESSION_S, sigma);
    let ideal = ideal_path_length(&cmds, p.service.command_timeout);
    let mut s = Shaper::new(p, ShaperConfig::default());
    let dt = p.dt();
    let mut path = 0.0f64;
    let (mut creep, mut longest) = (0.0f64, 0.0f64);
    let until = SESSION_S + RELEASE_S + 0.5;
    drive_shaper(&mut s, &cmds, dt, until, |_, s, asked| {
        let q = s.velocity();
        let v = q[0].hypot(q[1]);
        path += v * dt;
        if asked.vx.hypot(asked.vy) >= ASKED && v < CREEP {
            creep += dt;
            longest = longest.max(creep);
        } else {
            creep = 0.0;
        }
    });
    (path / ideal, longest)
}

#[test]
fn the_shaper_never_creeps_while_a_joystick_asks_to_move_and_keeps_its_path() {
    let p = Platform::justin();
    let mut failures = Vec::new();
    for (sigma, floor) in MEAN_PATH_ACHIEVED {
        let mut mean = 0.0;
        for seed in SEEDS {
            let (share, longest) = session(&p, seed, sigma);
            println!(
                "SHAPER joystick seed {seed} σ = {sigma}: path {:.1} % of the ideal, longest creep \
                 {longest:.2} s",
                100.0 * share
            );
            mean += share / SEEDS.len() as f64;
            if longest > LONGEST_CREEP_S {
                failures.push(format!(
                    "seed {seed}, σ = {sigma}: the reference crept below {CREEP} m/s for \
                     {longest:.2} s while the stick asked for {ASKED} m/s or more (≤ \
                     {LONGEST_CREEP_S} s)"
                ));
            }
        }
        println!("SHAPER σ = {sigma}: mean path {:.1} %", 100.0 * mean);
        if mean < floor {
            failures.push(format!(
                "σ = {sigma}: mean path {:.1} % of the ideal (≥ {:.0} %)",
                100.0 * mean,
                100.0 * floor
            ));
        }
    }
    assert!(failures.is_empty(), "{}", failures.join("\n"));
}

/// Largest sideways speed (m/s) of a wheel's reference contact velocity across its steering
/// reference with rolling turns: the shaper's `slip_speed` (3 mm/s), which caps a released
/// wheel that is not yet aligned, plus 10 % for the window mean (the output is the product
/// of the window means of μ and η̂ against the mean of the raw angles, which agree only to
/// second order in the window's turn; 3.1 mm/s on seed 2 when this was set).
const ROLL_SIDEWAYS: f64 = 1.1 * 0.003;
/// Mean path share of the rolling turns at σ = 0 when this was last set: 90.7 % (88.9 %
/// before the speed was shaped through the drives' lag, 86.7 % while a released wheel could
/// roll at 1.5 cm/s across its direction).
const ROLL_MEAN_PATH_ACHIEVED: f64 = 0.905;
/// Least share of [`unsteered_path_length`] (the same stick with wheels that steer
/// instantly, at the same shares of the drives' speed and acceleration) the rolling turns
/// travel on any noise-free stick: the path the steering costs. 92.3 % (stick 4) when this
/// was set; the unsteered path itself is 92.7–97.4 % of the ideal at the rolling turns'
/// acceleration share (0.75), 89.9–95.8 % at the line transitions' (0.6).
const ROLL_OF_UNSTEERED_ACHIEVED: f64 = 0.92;

/// Rolling turns ([`rollbase_control::reference::roll`], off by default) on the eight
/// sticks at every noise level: every wheel's reference contact velocity runs along its
/// steering reference within [`ROLL_SIDEWAYS`] (what the plant turns into slip and leg
/// motion: a released wheel crossing 86° off its direction at 1.4 cm/s moved a leg 3 mm in
/// closed loop), every steering rate within the reference's share of the limit, and the
/// noise-free mean path at least [`ROLL_MEAN_PATH_ACHIEVED`], and on every noise-free stick
/// at least [`ROLL_OF_UNSTEERED_ACHIEVED`] of what wheels that steer instantly would travel.
#[test]
fn rolling_turns_roll_every_wheel_along_its_steering_reference() {
    use rollbase_control::reference::limits::contact_kinematics;
    use rollbase_control::service::ports::CommandKind;
    let p = Platform::justin();
    let cfg = ShaperConfig {
        rolling_turns: true,
        ..ShaperConfig::default()
    };
    let rate_share = cfg.speed_fraction * p.limits.steer_rate;
    let dt = p.dt();
    let mut failures = Vec::new();
    for sigma in [0.0, 0.02, 0.05] {
        let mut mean = 0.0;
        for seed in SEEDS {
            let cmds = joystick_session(seed, SESSION_S, sigma);
            let ideal = ideal_path_length(&cmds, p.service.command_timeout);
            let mut s = Shaper::new(&p, cfg);
            let (mut k, mut t, mut path) = (0usize, 0.0f64, 0.0f64);
            let (mut side, mut rate) = ((0.0f64, 0.0f64), (0.0f64, 0.0f64));
            while t < SESSION_S + RELEASE_S + 0.5 {
                while k < cmds.len() && cmds[k].t <= t + 1e-9 {
                    match cmds[k].kind {
                        CommandKind::Motion(m) => s.command(m.twist, None),
                        _ => s.halt(),
                    }
                    k += 1;
                }
                let r = s.step();
                path += r.dz[0].hypot(r.dz[1]) * dt;
                for i in 0..p.n() {
                    let [u, _, _] = contact_kinematics(&p, i, &r);
                    let a = r.steer.angle[i];
                    let across = (-u[0] * a.sin() + u[1] * a.cos()).abs();
                    if across > side.0 {
                        side = (across, t);
                    }
                    if r.steer.rate[i].abs() > rate.0 {
                        rate = (r.steer.rate[i].abs(), t);
                    }
                }
                t += dt;
            }
            let share = path / ideal;
            mean += share / SEEDS.len() as f64;
            // At the acceleration share of the rolling turns' speed in the command (the
            // unsteered twist has no lag to shape through).
            let unsteered = unsteered_path_length(
                &cmds,
                p.service.command_timeout,
                &p,
                cfg.speed_fraction,
                cfg.roll_speed_accel_fraction,
            );
            println!(
                "ROLLING seed {seed} σ = {sigma}: path {:.1} % (unsteered {:.1} %), largest \
                 sideways speed {:.2} mm/s (t = {:.2} s), largest steering rate {:.3} rad/s",
                100.0 * share,
                100.0 * unsteered / ideal,
                1e3 * side.0,
                side.1,
                rate.0
            );
            if sigma == 0.0 && path < ROLL_OF_UNSTEERED_ACHIEVED * unsteered {
                failures.push(format!(
                    "seed {seed}, σ = 0: path {:.1} % of the unsteered path (≥ {:.1} %)",
                    100.0 * path / unsteered,
                    100.0 * ROLL_OF_UNSTEERED_ACHIEVED
                ));
            }
            if side.0 > ROLL_SIDEWAYS {
                failures.push(format!(
                    "seed {seed}, σ = {sigma}: a wheel's reference rolls {:.2} mm/s across its \
                     steering reference at t = {:.2} s (≤ {:.2} mm/s)",
                    1e3 * side.0,
                    side.1,
                    1e3 * ROLL_SIDEWAYS
                ));
            }
            if rate.0 > rate_share * (1.0 + 1e-9) {
                failures.push(format!(
                    "seed {seed}, σ = {sigma}: steering rate {:.4} rad/s at t = {:.2} s (≤ \
                     {rate_share} rad/s)",
                    rate.0, rate.1
                ));
            }
        }
        println!("ROLLING σ = {sigma}: mean path {:.1} %", 100.0 * mean);
        if sigma == 0.0 && mean < ROLL_MEAN_PATH_ACHIEVED {
            failures.push(format!(
                "σ = 0: mean path {:.1} % of the ideal (≥ {:.1} %)",
                100.0 * mean,
                100.0 * ROLL_MEAN_PATH_ACHIEVED
            ));
        }
    }
    assert!(failures.is_empty(), "{}", failures.join("\n"));
}
