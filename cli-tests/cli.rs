//! The `rollbase` binary as an operator uses it: Ctrl-C, bad input, exit codes.

use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

/// The tests of this file run one at a time: the real-time one must not share the two cores
/// with a lockstep run of another test.
static SERIAL: std::sync::Mutex<()> = std::sync::Mutex::new(());

fn serial() -> std::sync::MutexGuard<'static, ()> {
    SERIAL.lock().unwrap_or_else(|e| e.into_inner())
}

fn rollbase() -> Command {
    Command::new(env!("CARGO_BIN_EXE_rollbase"))
}

#[test]
fn ctrl_c_during_a_real_time_demo_is_a_controlled_stop_then_exit() {
    let _serial = serial();
    let child = rollbase()
        .args(["demo", "--json"])
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .expect("start rollbase demo");
    // Let it arm, align and start tracking.
    std::thread::sleep(Duration::from_millis(3000));
    // SAFETY: sending SIGINT to our own child process.
    let r = unsafe { libc::kill(child.id() as libc::pid_t, libc::SIGINT) };
    assert_eq!(r, 0);
    let sent = Instant::now();
    let out = child.wait_with_output().expect("wait");
    let took = sent.elapsed();
    let stdout = String::from_utf8_lossy(&out.stdout);
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(
        out.status.success(),
        "exit {:?}\n{stdout}\n{stderr}",
        out.status
    );
    let v: serde_json::Value = serde_json::from_str(stdout.trim()).expect("one JSON object");
    assert_eq!(v["supervisor_final_state"], "stopped", "{v}");
    assert!(v["fault_reason"].is_null());
    // Stopped long before the 27.6 s trajectory would have ended.
    assert!(took < Duration::from_secs(10), "took {took:?} to stop");
    assert!(v["cycles"].as_u64().unwrap() < 250 * 10);
}

#[test]
fn bad_platform_file_names_the_field_and_fails() {
    let _serial = serial();
    let dir = std::env::temp_dir().join(format!("rollbase-cli-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let good = rollbase().args(["config", "default"]).output().unwrap();
    assert!(good.status.success());
    let text = String::from_utf8(good.stdout).unwrap();
    let bad = text.replacen("lambda_max = 0.56", "lambda_max = 0.2", 1);
    let path = dir.join("bad.toml");
    std::fs::write(&path, bad).unwrap();
    let out = rollbase()
        .args(["config", "check"])
        .arg(&path)
        .output()
        .unwrap();
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("wheels[0].lambda_min"), "{err}");
    // The demo refuses it too, before starting anything.
    let out = rollbase()
        .args(["demo", "--lockstep", "--config"])
        .arg(&path)
        .output()
        .unwrap();
    assert!(!out.status.success());
    assert!(String::from_utf8_lossy(&out.stderr).contains("wheels[0]"));
    let _ = std::fs::remove_dir_all(dir);
}

#[test]
fn unknown_scenario_and_bus_are_clear_errors() {
    let _serial = serial();
    let out = rollbase()
        .args(["demo", "--scenario", "nope"])
        .output()
        .unwrap();
    assert!(!out.status.success());
    assert!(String::from_utf8_lossy(&out.stderr).contains("unknown scenario `nope`"));
    let out = rollbase()
        .args([
            "run",
            "--bus",
            "nosuchcan7",
            "--trajectory",
            "scenario:seed000",
        ])
        .output()
        .unwrap();
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("nosuchcan7"), "{err}");
}

#[test]
fn lockstep_demo_json_has_the_documented_fields() {
    let _serial = serial();
    let out = rollbase()
        .args(["demo", "--lockstep", "--json"])
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let v: serde_json::Value = serde_json::from_slice(&out.stdout).expect("JSON");
    for k in [
        "scenario",
        "cycles",
        "deadline_misses",
        "max_position_error_m",
        "max_heading_error_rad",
        "max_leg_error_m",
        "final_position_error_m",
        "max_steer_rate_rad_s",
        "max_wheel_speed_rad_s",
        "min_icr_wheel_distance_m",
        "cycle_period_p99_us",
        "compute_time_p99_us",
        "rejected_frames",
        "supervisor_final_state",
    ] {
        assert!(v.get(k).is_some(), "missing {k} in {v}");
    }
    assert_eq!(v["supervisor_final_state"], "stopped");
    assert!(v["max_position_error_m"].as_f64().unwrap() < 0.005);
}
