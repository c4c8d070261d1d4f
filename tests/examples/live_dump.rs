//! Debug: a live run from a JSON command list on stdin, per-cycle CSV on stdout.
use rollbase_control::ports::{CommandEvent, CommandKind, LegTargets, MotionCommand};
use rollbase_control::types::Twist;
use rollbase_tests::*;
use std::io::Read;

fn main() {
    let mut text = String::new();
    std::io::stdin().read_to_string(&mut text).unwrap();
    let mut cmds = Vec::new();
    for line in text.lines() {
        let v: serde_json::Value = match serde_json::from_str(line) {
            Ok(v) => v,
            Err(_) => continue,
        };
        let t = v["t"].as_f64().unwrap();
        if v.get("end").is_some() {
            cmds.push(CommandEvent {
                t,
                kind: CommandKind::EndOfStream,
            });
            continue;
        }
        let legs = v.get("legs").map(|l| {
            LegTargets::from_slice(
                &l.as_array()
                    .unwrap()
                    .iter()
                    .map(|x| x.as_f64().unwrap())
                    .collect::<Vec<_>>(),
            )
        });
        cmds.push(CommandEvent {
            t,
            kind: CommandKind::Motion(MotionCommand {
                twist: Twist {
                    vx: v["vx"].as_f64().unwrap(),
                    vy: v["vy"].as_f64().unwrap(),
                    omega: v["omega"].as_f64().unwrap(),
                },
                legs,
            }),
        });
    }
    let out = run_live(&LiveOptions::default(), &cmds);
    eprintln!("{}", out.summary.to_json());
    if let Ok(tt) = std::env::var("AT") {
        let tt: f64 = tt.parse().unwrap();
        for r in out.records.iter().filter(|r| (r.t - tt).abs() < 0.0041) {
            eprintln!(
                "t={} mode={} cmd={:?} steer={:?} meas={:?}",
                r.t,
                r.mode,
                r.command.wheels[..4]
                    .iter()
                    .map(|w| (w.wheel_speed, w.steer_rate))
                    .collect::<Vec<_>>(),
                (
                    r.reference.steer.angle[..4].to_vec(),
                    r.reference.steer.rate[..4].to_vec()
                ),
                r.measurement.wheels[..4]
                    .iter()
                    .map(|w| w.steer_angle)
                    .collect::<Vec<_>>()
            );
        }
    }
    let w: usize = std::env::var("WHEEL")
        .ok()
        .and_then(|x| x.parse().ok())
        .unwrap_or(0);
    println!("t,state,mode,lim,vbx,vby,om,ex,ey,eth,cmdw,cmds,measw,meass,refsteer,refrate");
    for r in &out.records {
        let (p, _) = r.truth.unwrap_or_default();
        let (s, c) = r.reference.z[2].sin_cos();
        let vb = [
            c * r.reference.dz[0] + s * r.reference.dz[1],
            -s * r.reference.dz[0] + c * r.reference.dz[1],
        ];
        println!("{:.3},{},{},{:?},{:.4},{:.4},{:.4},{:.5},{:.5},{:.5},{:.4},{:.4},{:.4},{:.4},{:.4},{:.4}", r.t, r.state.name(), r.mode, r.shaping.limiting, vb[0], vb[1], r.reference.dz[2], r.reference.z[0]-p.x, r.reference.z[1]-p.y, r.reference.z[2]-p.theta, r.command.wheels[w].wheel_speed, r.command.wheels[w].steer_rate, r.measurement.wheels[w].wheel_speed, r.measurement.wheels[w].steer_angle, r.reference.steer.angle[w], r.reference.steer.rate[w]);
    }
}
#[allow(dead_code)]
fn unused() {}
