//! `recover` (rewrite a recording whose writer was killed) and the hidden `ros2-selftest`
//! (the ROS 2 node fed with a synthetic state, for the interop tests).

use clap::Args;
use rollbase::record::{McapRecorder, RecordOptions};
use rollbase::ros2::{spawn_node, Ros2Args};
use rollbase_control::service::ports::{BaseState, CommandEvent, CommandKind, ModuleDiagnostics};
use rollbase_control::supervisor::SupervisorState;
use rollbase_control::types::MAX_WHEELS;
use serde_json::json;
use std::collections::BTreeMap;
use std::path::PathBuf;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};

use super::common::{unix_now, CliError};

#[derive(Args, Debug)]
pub(crate) struct RecoverArgs {
    /// The damaged recording (e.g. left without footer by a killed process); never modified.
    file: PathBuf,
    /// Where to write the recovered recording (must not exist); default FILE.recovered.mcap.
    #[arg(long)]
    out: Option<PathBuf>,
}

/// Where `recover FILE` writes without `--out`: `run.mcap` → `run.recovered.mcap`, and the
/// temporary file of an unfinished recording, `.run.mcap.partial-PID`, → `run.recovered.mcap`.
fn default_recovered(file: &std::path::Path) -> PathBuf {
    let name = file
        .file_name()
        .map(|s| s.to_string_lossy().into_owned())
        .unwrap_or_default();
    let target = match (name.strip_prefix('.'), name.rfind(".partial-")) {
        (Some(_), Some(i)) if i > 1 => name[1..i].to_string(),
        _ => name,
    };
    let stem = std::path::Path::new(&target)
        .file_stem()
        .map(|s| s.to_string_lossy().into_owned())
        .filter(|s| !s.is_empty())
        .unwrap_or_else(|| "recording".into());
    file.with_file_name(format!("{stem}.recovered.mcap"))
}

pub(crate) fn recover(a: RecoverArgs) -> Result<i32, CliError> {
    let out = a.out.clone().unwrap_or_else(|| default_recovered(&a.file));
    let rep = rollbase::record::recover(&a.file, &out)?;
    if rep.had_footer && rep.stopped.is_none() && rep.skipped.is_empty() && rep.orphaned == 0 {
        errln!(
            "{}: the recording was complete; copied {} messages",
            a.file.display(),
            rep.total()
        );
    } else {
        errln!(
            "{}: recovered {} messages on {} topics (reading stopped: {})",
            a.file.display(),
            rep.total(),
            rep.messages.len(),
            rep.stopped.as_deref().unwrap_or("at the end of the data")
        );
    }
    for (t, n) in &rep.messages {
        errln!("  {t:<24} {n}");
    }
    if !rep.skipped.is_empty() {
        errln!(
            "{}: skipped {} damaged region(s) of the input (nothing of them is in the output; every intact chunk after them is):",
            a.file.display(),
            rep.skipped.len() as u64 + rep.skipped_more
        );
        for s in &rep.skipped {
            let times = match s.log_times {
                Some((a, b)) if a <= b => format!(
                    "; its header gives messages logged from {:.3} s to {:.3} s",
                    a as f64 * 1e-9,
                    b as f64 * 1e-9
                ),
                _ => String::new(),
            };
            errln!(
                "  bytes {}..{} ({} bytes): {}{times}",
                s.offset,
                s.offset + s.length,
                s.length,
                s.reason
            );
        }
        if rep.skipped_more > 0 {
            errln!("  … and {} more", rep.skipped_more);
        }
    }
    if rep.orphaned > 0 {
        errln!(
            "{}: {} messages of intact chunks were dropped: their channel was defined only in a damaged region",
            a.file.display(),
            rep.orphaned
        );
    }
    outln!("{}", out.display());
    Ok(0)
}

#[derive(Args, Debug)]
pub(crate) struct SelftestArgs {
    /// Run this long (s).
    #[arg(long, default_value_t = 60.0)]
    duration: f64,
    /// Number of wheels of the synthetic platform.
    #[arg(long, default_value_t = 4)]
    wheels: usize,
    /// Stop when standard input closes (for a test harness holding a pipe).
    #[arg(long)]
    stdin_stop: bool,
    /// Also record the published topics and the received commands into this bag.
    #[arg(long)]
    record: Option<PathBuf>,
    #[command(flatten)]
    ros2: Ros2Args,
}

/// Pose and twist covariances of the synthetic state (distinct values, so a wrong mapping
/// shows).
const POSE_COV: [[f64; 3]; 3] = [
    [0.01, 0.002, 0.003],
    [0.002, 0.02, 0.004],
    [0.003, 0.004, 0.05],
];
const TWIST_COV: [[f64; 3]; 3] = [
    [0.001, 0.0001, 0.0],
    [0.0001, 0.002, 0.0],
    [0.0, 0.0, 0.003],
];

/// The synthetic state of cycle `k`: every value a simple function of the cycle time.
fn synthetic(k: u64, n: usize, state: SupervisorState, log_time_ns: u64) -> BaseState {
    let t = k as f64 * 0.004;
    let mut s = BaseState {
        cycle: k,
        t,
        log_time_ns,
        n,
        state,
        ..Default::default()
    };
    s.odometry.pose.x = 0.1 * t;
    s.odometry.pose.y = 0.05 * t;
    s.odometry.pose.theta = 0.2 * t;
    s.odometry.twist.vx = 0.1;
    s.odometry.twist.vy = 0.05;
    s.odometry.twist.omega = 0.2;
    s.odometry.pose_covariance = POSE_COV;
    s.odometry.twist_covariance = TWIST_COV;
    for i in 0..n {
        let f = i as f64;
        let j = &mut s.joints[i];
        j.steer_angle = 0.1 * f;
        j.steer_rate = 0.01 * f;
        j.wheel_speed = 1.0 + f;
        j.wheel_angle = (1.0 + f) * t;
        j.leg = 0.4 + 0.01 * f;
        j.leg_rate = 0.001 * f;
        s.diagnostics.modules[i] = ModuleDiagnostics {
            node: i as u8 + 1,
            state: 2,
            ..Default::default()
        };
    }
    s.diagnostics.bus_load = 0.3;
    s.shaping.scale = 1.0;
    s
}

fn command_json(ev: &CommandEvent) -> serde_json::Value {
    match ev.kind {
        CommandKind::Motion(m) => json!({"cmd": "motion", "t": ev.t, "vx": m.twist.vx,
            "vy": m.twist.vy, "omega": m.twist.omega,
            "legs": m.legs.map(|l| l.as_slice().to_vec())}),
        CommandKind::Legs(l) => json!({"cmd": "legs", "t": ev.t, "legs": l.as_slice(), "n": l.n}),
        CommandKind::Stop => json!({"cmd": "stop", "t": ev.t}),
        CommandKind::Rearm => json!({"cmd": "rearm", "t": ev.t}),
        CommandKind::EndOfStream => json!({"cmd": "end_of_stream", "t": ev.t}),
        CommandKind::Shutdown => json!({"cmd": "shutdown", "t": ev.t}),
    }
}

/// Runs the node against a synthetic 250 Hz state; prints one JSON line when ready, one per
/// command received, and one with the node's counters at the end. `stop` turns the state to
/// `stopped`, `rearm` back to `tracking`, so the services' effect is visible.
pub(crate) fn selftest(a: SelftestArgs) -> Result<i32, CliError> {
    let n = a.wheels;
    if n == 0 || n > MAX_WHEELS {
        return Err(CliError::Usage(format!(
            "--wheels {n}: give 1..={MAX_WHEELS}"
        )));
    }
    if !(a.duration.is_finite() && a.duration > 0.0) {
        return Err(CliError::Usage(format!(
            "--duration {}: give a positive number of seconds",
            a.duration
        )));
    }
    let mut opts = a.ros2.to_options();
    opts.validate(Some(n))?;
    // The robot model of the default platform when the synthetic one has as many wheels.
    let platform = rollbase_control::Platform::default();
    if platform.wheels.len() == n {
        opts.robot_description = Some(
            rollbase::ros2::urdf::generate(&platform, &opts.joint_names)
                .map_err(|e| CliError::Usage(format!("--ros2-joint-names: {e}")))?,
        );
    }
    let mut rec = match &a.record {
        Some(p) => Some(McapRecorder::create_with(
            p,
            &BTreeMap::from([("mode".to_string(), "ros2-selftest".to_string())]),
            &RecordOptions {
                ros2: opts.clone(),
                ..Default::default()
            },
        )?),
        None => None,
    };
    let (cmd_tx, cmd_rx) = rollbase_control::runtime::command_channel(64, 16);
    let (state_tx, state_rx) = std::sync::mpsc::sync_channel::<BaseState>(16);
    let origin = Instant::now();
    let node = spawn_node(opts.clone(), cmd_tx, state_rx, origin)?;
    let stop = Arc::new(AtomicBool::new(false));
    if a.stdin_stop {
        let stop = stop.clone();
        std::thread::spawn(move || {
            let mut sink = Vec::new();
            let _ = std::io::Read::read_to_end(&mut std::io::stdin(), &mut sink);
            stop.store(true, Ordering::SeqCst);
        });
    }
    let node_fqn = opts.node_fqn();
    outln!(
        "{}",
        json!({"ready": true, "domain_id": node.domain_id(), "node": node_fqn, "wheels": n,
               "pose_covariance": POSE_COV, "twist_covariance": TWIST_COV,
               "topics": {"odom": opts.topic("odom"), "tf": opts.topic("tf"),
                          "joint_states": opts.topic("joint_states"),
                          "diagnostics": opts.topic("diagnostics"),
                          "supervisor_state": opts.topic("supervisor_state"),
                          "cmd_vel": opts.topic(&opts.cmd_vel_topic),
                          "legs": opts.topic(&opts.leg_topic)}})
    );
    let mut state = SupervisorState::Tracking;
    let (mut dropped_states, mut k) = (0u64, 0u64);
    let period = Duration::from_millis(4);
    let mut next = Instant::now();
    let mut warned = false;
    while !stop.load(Ordering::SeqCst) && origin.elapsed().as_secs_f64() < a.duration {
        let mut taken = Vec::new();
        cmd_rx.take(usize::MAX, |ev| taken.push(ev));
        for ev in taken {
            outln!("{}", command_json(&ev));
            match ev.kind {
                CommandKind::Stop => state = SupervisorState::Stopped,
                CommandKind::Rearm => state = SupervisorState::Tracking,
                _ => {}
            }
            if let Some(r) = &mut rec {
                let ns = (unix_now() * 1e9) as u64;
                r.write_command(&ev, ns)?;
            }
        }
        let s = synthetic(k, n, state, (unix_now() * 1e9) as u64);
        if state_tx.try_send(s).is_err() {
            dropped_states += 1;
        }
        if let Some(r) = &mut rec {
            if let Some(w) = r.write_state(&s)? {
                if !warned {
                    errln!("record: {w}");
                    warned = true;
                }
            }
        }
        k += 1;
        next += period;
        let now = Instant::now();
        if next > now {
            std::thread::sleep(next - now);
        } else {
            next = now;
        }
    }
    drop(state_tx);
    let st = node.stats();
    let counters = json!({
        "commands_sent": st.commands_sent.load(Ordering::Relaxed),
        "commands_dropped": st.commands_dropped.load(Ordering::Relaxed),
        "commands_refused": st.commands_refused.load(Ordering::Relaxed),
        "receive_errors": st.receive_errors.load(Ordering::Relaxed),
        "states": st.states.load(Ordering::Relaxed),
        "published": st.published.load(Ordering::Relaxed),
        "publish_errors": st.publish_errors.load(Ordering::Relaxed),
        "services_answered": st.services_answered.load(Ordering::Relaxed),
        "services_cyclone": st.services_cyclone.load(Ordering::Relaxed),
        "services_enhanced": st.services_enhanced.load(Ordering::Relaxed),
        "qos_incompatible": st.qos_incompatible.load(Ordering::Relaxed),
        "undecodable": st.undecodable_by_endpoint(),
        "oversized": st.oversized_by_endpoint(),
        "discovery_layout": st.announced_layout().map(|l| l.bytes()),
        "states_dropped_before_the_node": dropped_states,
        "cycles": k,
    });
    node.shutdown();
    let recorded = match rec {
        Some(r) => Some(r.finish()?.messages),
        None => None,
    };
    outln!(
        "{}",
        json!({"done": true, "stats": counters, "recorded_messages": recorded})
    );
    Ok(0)
}

#[cfg(test)]
mod tests {
    use super::default_recovered;
    use std::path::Path;

    #[test]
    fn recovered_names_come_from_the_recording_not_its_temporary_name() {
        let r = |p: &str| default_recovered(Path::new(p)).display().to_string();
        assert_eq!(r("runs/run.mcap"), "runs/run.recovered.mcap");
        assert_eq!(r("runs/.run.mcap.partial-4242"), "runs/run.recovered.mcap");
        assert_eq!(r(".run.mcap.partial-4242-2"), "run.recovered.mcap");
        assert_eq!(r("plain"), "plain.recovered.mcap");
    }
}
