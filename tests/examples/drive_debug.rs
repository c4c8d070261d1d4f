//! Debug: dumps a live run's per-cycle figures as CSV (stdout).
use rollbase_control::ports::{CommandEvent, CommandKind};
use rollbase_tests::*;

fn main() {
    use rollbase_control::ports::{LegTargets, MotionCommand};
    use rollbase_control::types::Twist;
    let lo = [0.37; 4];
    let hi = [0.56; 4];
    let steps: [(f64, f64, f64, Option<[f64; 4]>); 4] = [
        (3.0, 0.0, 0.0, Some(hi)),
        (-3.0, 0.0, 0.0, None),
        (0.0, 3.0, 5.0, Some(lo)),
        (0.0, -3.0, -5.0, None),
    ];
    let mut cmds = Vec::new();
    let mut t = 0.0;
    for &(vx, vy, om, legs) in &steps {
        let mut k = 0.0;
        while k < 2.0 - 1e-9 {
            cmds.push(CommandEvent {
                t: t + k,
                kind: CommandKind::Motion(MotionCommand {
                    twist: Twist { vx, vy, omega: om },
                    legs: legs.map(|l| LegTargets::from_slice(&l)),
                }),
            });
            k += 0.4;
        }
        t += 2.0;
    }
    cmds.push(CommandEvent {
        t,
        kind: CommandKind::EndOfStream,
    });
    let out = run_live(&LiveOptions::default(), &cmds);
    eprintln!("{}", out.summary.to_json());
    println!("t,state,mode,lim,leg0,refvx,refvy,refw,ex,ey,eth,cmdw0,cmds0,ddw0,odex,odey,mw0,ms0,direrr");
    let mut prev: Option<&rollbase_control::record::CycleRecord> = None;
    for r in &out.records {
        let (p, _) = r.truth.unwrap_or_default();
        let (s, c) = r.reference.z[2].sin_cos();
        let vb = [
            c * r.reference.dz[0] + s * r.reference.dz[1],
            -s * r.reference.dz[0] + c * r.reference.dz[1],
        ];
        let dir = prev
            .and_then(|q| {
                let (p1, _) = r.truth?;
                let (p0, _) = q.truth?;
                let (wx, wy) = ((p1.x - p0.x) / 0.004, (p1.y - p0.y) / 0.004);
                let (s, c) = (0.5 * (p1.theta + p0.theta)).sin_cos();
                let eb = [c * wx + s * wy, -s * wx + c * wy];
                if eb[0].hypot(eb[1]) < 0.05 {
                    return None;
                }
                Some(
                    (vb[0] * eb[1] - vb[1] * eb[0])
                        .atan2(vb[0] * eb[0] + vb[1] * eb[1])
                        .to_degrees(),
                )
            })
            .unwrap_or(0.0);
        let ds = prev.map_or(0.0, |q| {
            (r.command.wheels[0].steer_rate - q.command.wheels[0].steer_rate) / 0.004
        });
        println!("{:.3},{},{},{:?},{:.4},{:.4},{:.4},{:.4},{:.5},{:.5},{:.5},{:.4},{:.4},{:.1},{:.5},{:.5},{:.4},{:.4},{:.3}", r.t, r.state.name(), r.mode, r.shaping.limiting, r.reference.z[3], vb[0], vb[1], r.reference.dz[2], r.reference.z[0]-p.x, r.reference.z[1]-p.y, r.reference.z[2]-p.theta, r.command.wheels[0].wheel_speed, r.command.wheels[0].steer_rate, ds, r.pose.x-p.x, r.pose.y-p.y, r.measurement.wheels[0].wheel_speed, r.measurement.wheels[0].steer_angle, dir);
        prev = Some(r);
    }
}
