//! Random live-command sessions in lockstep (the base service through the full frame path):
//! `cargo run --release -p rollbase-tests --example random_session -- SEED0 SEED1 VMAX WMAX P_LEGS`
//! prints each seed's tracking figures; `WIN=t0,t1` dumps every wheel between two times and `CSV=1`
//! writes a per-cycle CSV to stderr. Used to look for weak spots of the shaper.
use rollbase_control::service::ports::{CommandEvent, CommandKind, LegTargets, MotionCommand};
use rollbase_control::types::Twist;
use rollbase_tests::*;

fn session(seed: u64, vmax: f64, wmax: f64, legs_p: f64) -> Vec<CommandEvent> {
    let mut rng = rollbase_driver::rng::Rng::new(seed);
    let mut u = |lo: f64, hi: f64| lo + (hi - lo) * rng.next_f64();
    let mut cmds = Vec::new();
    let mut t = 0.0;
    let m = |t: f64, vx: f64, vy: f64, om: f64, legs: Option<[f64; 4]>| CommandEvent {
        t,
        kind: CommandKind::Motion(MotionCommand {
            twist: Twist { vx, vy, omega: om },
            legs: legs.map(|l| LegTargets::from_slice(&l)),
        }),
    };
    while t < 60.0 {
        let hold = u(1.5, 3.0);
        let (vx, vy, om) = (u(-vmax, vmax), u(-vmax, vmax), u(-wmax, wmax));
        let legs = (u(0.0, 1.0) < legs_p)
            .then(|| [u(0.37, 0.56), u(0.37, 0.56), u(0.37, 0.56), u(0.37, 0.56)]);
        let mut k = 0.0;
        while k < hold {
            cmds.push(m(t + k, vx, vy, om, if k == 0.0 { legs } else { None }));
            k += 0.4;
        }
        t += hold;
    }
    for k in 0..5 {
        cmds.push(m(t + 0.4 * k as f64, 0.0, 0.0, 0.0, None));
    }
    cmds.push(CommandEvent {
        t: t + 2.0,
        kind: CommandKind::EndOfStream,
    });
    cmds
}

fn main() {
    let args: Vec<f64> = std::env::args()
        .skip(1)
        .map(|a| a.parse().unwrap())
        .collect();
    let (s0, s1, vmax, wmax, lp) = (args[0] as u64, args[1] as u64, args[2], args[3], args[4]);
    for seed in s0..s1 {
        let out = run_live(&LiveOptions::default(), &session(seed, vmax, wmax, lp));
        let s = &out.summary;
        println!(
            "seed {seed}: pos {:.2} mm head {:.3}° leg {:.2} mm dir {:.2}° state {} {:?}",
            s.max_position_error_m * 1e3,
            s.max_heading_error_rad.to_degrees(),
            s.max_leg_error_m * 1e3,
            s.max_direction_error_rad.to_degrees(),
            s.final_state,
            s.fault_reason
        );
        if let Ok(w) = std::env::var("WIN") {
            let v: Vec<f64> = w.split(",").map(|x| x.parse().unwrap()).collect();
            dump_at(&out, v[0], v[1]);
        }
        if std::env::var("CSV").is_ok() {
            for r in &out.records {
                let (p, l) = r.truth.unwrap_or_default();
                let (sn, c) = r.reference.z[2].sin_cos();
                let vb = [
                    c * r.reference.dz[0] + sn * r.reference.dz[1],
                    -sn * r.reference.dz[0] + c * r.reference.dz[1],
                ];
                eprintln!(
                    "{:.3},{},{:?},{:.4},{:.4},{:.4},{:.5},{:.5},{:.5},{:.5},{:.5},{:.4},{:.4}",
                    r.t,
                    r.mode,
                    r.shaping.limiting,
                    vb[0],
                    vb[1],
                    r.reference.dz[2],
                    r.reference.z[0] - p.x,
                    r.reference.z[1] - p.y,
                    r.reference.z[2] - p.theta,
                    r.reference.z[3],
                    l[0],
                    r.command.wheels[0].wheel_speed,
                    r.command.wheels[0].steer_rate
                );
            }
        }
    }
}
#[allow(dead_code)]
pub fn dump_at(out: &RunOutcome, t0: f64, t1: f64) {
    for r in out.records.iter().filter(|r| r.t >= t0 && r.t <= t1) {
        let p = &out.platform;
        let mut s = format!("{:.3} {}", r.t, r.mode);
        for i in 0..4 {
            let d = rollbase_control::reference::limits::wheel_demand(p, i, &r.reference);
            s += &format!(
                " | w{i} L={:.4}/{:.4} u={:.3} st={:.3}/{:.3} cmd=({:.2},{:.2}) meas=({:.2},{:.3})",
                r.reference.z[3 + i],
                r.truth.unwrap().1[i],
                d.speed * p.wheel_radius,
                r.reference.steer.angle[i],
                r.reference.steer.rate[i],
                r.command.wheels[i].wheel_speed,
                r.command.wheels[i].steer_rate,
                r.measurement.wheels[i].wheel_speed,
                r.measurement.wheels[i].steer_angle
            );
        }
        println!("{s}");
    }
}
