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

/// Starts a real-time demo, sends `signal` after 3 s, and returns its output.
fn signal_a_demo(signal: libc::c_int) -> (std::process::Output, Duration) {
    let child = rollbase()
        .args(["demo", "--json"])
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .expect("start rollbase demo");
    // Let it arm, align and start tracking.
    std::thread::sleep(Duration::from_millis(3000));
    // SAFETY: sending a signal to our own child process.
    let r = unsafe { libc::kill(child.id() as libc::pid_t, signal) };
    assert_eq!(r, 0);
    let sent = Instant::now();
    let out = child.wait_with_output().expect("wait");
    (out, sent.elapsed())
}

#[test]
fn ctrl_c_and_sigterm_during_a_real_time_demo_are_a_controlled_stop_then_exit_3() {
    let _serial = serial();
    for (signal, name) in [(libc::SIGINT, "SIGINT"), (libc::SIGTERM, "SIGTERM")] {
        let (out, took) = signal_a_demo(signal);
        let stdout = String::from_utf8_lossy(&out.stdout);
        let stderr = String::from_utf8_lossy(&out.stderr);
        // Interrupted, not killed: exit code 3 (README "Exit codes"), summary printed.
        assert_eq!(
            out.status.code(),
            Some(3),
            "{name}: exit {:?}\n{stdout}\n{stderr}",
            out.status
        );
        assert!(
            stderr.contains(&format!("{name}: controlled stop")),
            "{stderr}"
        );
        let v: serde_json::Value = serde_json::from_str(stdout.trim()).expect("one JSON object");
        assert_eq!(v["supervisor_final_state"], "stopped", "{v}");
        assert!(v["fault_reason"].is_null());
        // Stopped long before the 27.6 s trajectory would have ended.
        assert!(took < Duration::from_secs(10), "took {took:?} to stop");
        assert!(v["cycles"].as_u64().unwrap() < 250 * 10);
    }
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
    // Where the platform ended, as the driver estimates it: seed 000's goal (4.5 m, 4.5 m).
    let (x, y) = (
        v["final_pose"]["x"].as_f64().expect("final_pose.x"),
        v["final_pose"]["y"].as_f64().expect("final_pose.y"),
    );
    assert!((x - 4.5).abs() < 0.01 && (y - 4.5).abs() < 0.01, "{v}");
}

/// Parses `| label | … | load % |` rows of the bus-load table into (label, frames/cycle, load %).
fn bus_load_rows(text: &str) -> Vec<(String, f64, f64)> {
    text.lines()
        .filter(|l| l.starts_with('|') && l.trim_end().ends_with("% |"))
        .map(|l| {
            let cells: Vec<&str> = l.split('|').map(str::trim).collect();
            let frames: f64 = cells[4].parse().expect("frames/cycle");
            let load: f64 = cells[7].trim_end_matches('%').parse().expect("load %");
            (cells[1].to_string(), frames, load)
        })
        .collect()
}

#[test]
fn cia402_bus_load_counts_8_drives_and_4_encoders_and_states_the_headroom() {
    let _serial = serial();
    let out = rollbase()
        .args(["bus-load", "--profile", "cia402"])
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let text = String::from_utf8(out.stdout).unwrap();
    assert!(text.contains("8 drives + 4 encoders"), "{text}");
    let rows = bus_load_rows(&text);
    let row = |name: &str| {
        rows.iter()
            .find(|r| r.0 == name)
            .unwrap_or_else(|| panic!("no `{name}` row in\n{text}"))
            .clone()
    };
    assert_eq!(row("SYNC").1, 1.0);
    assert_eq!(row("RPDO1 drive").1, 8.0);
    assert_eq!(row("TPDO1 drive").1, 8.0);
    assert_eq!(row("TPDO1 enc").1, 4.0);
    let total = row("total").2;
    let sum: f64 = rows.iter().filter(|r| r.0 != "total").map(|r| r.2).sum();
    assert!(
        (sum - total).abs() < 0.05,
        "rows sum to {sum}, total {total}"
    );
    assert!(total < 100.0, "{text}");
    let headroom = format!("headroom {:.2}%", 100.0 - total);
    assert!(text.contains(&headroom), "expected `{headroom}` in\n{text}");
    assert!(text.contains("verdict: fits"), "{text}");
    // At half the bit rate the same traffic does not fit: the command must say so, not print
    // a plausible table.
    let out = rollbase()
        .args(["bus-load", "--profile", "cia402", "--bitrate", "500000"])
        .output()
        .unwrap();
    let text = String::from_utf8(out.stdout).unwrap();
    let total_500k = bus_load_rows(&text)
        .into_iter()
        .find(|r| r.0 == "total")
        .map(|r| r.2)
        .unwrap_or(f64::NAN);
    assert!((total_500k - 2.0 * total).abs() < 0.05, "{text}");
    assert!(text.contains("verdict: DOES NOT FIT"), "{text}");
}

/// The bus-load text of `rollbase bus-load ARGS…`, split into its per-bus tables (one table
/// when the platform has one bus).
fn bus_load_tables(args: &[&str]) -> Vec<Vec<(String, f64, f64)>> {
    let out = rollbase().arg("bus-load").args(args).output().unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let text = String::from_utf8(out.stdout).unwrap();
    let parts: Vec<&str> = text.split("## bus ").collect();
    if parts.len() == 1 {
        return vec![bus_load_rows(&text)];
    }
    assert!(
        parts[0].trim().is_empty(),
        "text before the first table:\n{text}"
    );
    parts[1..].iter().map(|t| bus_load_rows(t)).collect()
}

#[test]
fn bus_load_of_a_two_bus_platform_is_one_table_per_bus_with_its_own_wheels_and_sync() {
    let _serial = serial();
    let six = concat!(env!("CARGO_MANIFEST_DIR"), "/docs/examples/six-wheel.toml");
    for profile in ["native", "cia402"] {
        let tables = bus_load_tables(&["--config", six, "--profile", profile]);
        assert_eq!(tables.len(), 2, "{profile}: one table per bus");
        let row = |t: &[(String, f64, f64)], name: &str| {
            t.iter()
                .find(|r| r.0 == name)
                .unwrap_or_else(|| panic!("{profile}: no `{name}` row in {t:?}"))
                .clone()
        };
        // Three wheels on each bus (docs/examples/six-wheel.toml), each bus its own SYNC.
        let (setpoints, feedback) = if profile == "native" {
            ("SETPOINT", "FEEDBACK_A")
        } else {
            ("RPDO1 drive", "TPDO1 enc")
        };
        for t in &tables {
            assert_eq!(row(t, "SYNC").1, 1.0, "{profile}: {t:?}");
            let per_wheel = if profile == "native" { 1.0 } else { 2.0 };
            assert_eq!(row(t, setpoints).1, 3.0 * per_wheel, "{profile}: {t:?}");
            assert_eq!(row(t, feedback).1, 3.0, "{profile}: {t:?}");
        }
        // The same six wheels all on bus 0: one table; the two buses together carry exactly
        // that plus one more SYNC (and, CiA 402, one more master heartbeat) per cycle.
        let one_bus = std::env::temp_dir().join(format!(
            "rollbase-cli-six-one-bus-{}-{profile}.toml",
            std::process::id()
        ));
        let text = std::fs::read_to_string(six).unwrap();
        std::fs::write(&one_bus, text.replace("bus = 1", "bus = 0")).unwrap();
        let all = bus_load_tables(&["--config", one_bus.to_str().unwrap(), "--profile", profile]);
        std::fs::remove_file(&one_bus).unwrap();
        assert_eq!(all.len(), 1, "{profile}: all wheels on bus 0 is one table");
        let per_bus = row(&tables[0], "total").2;
        let extra = row(&all[0], "SYNC").2
            + if profile == "cia402" {
                row(&all[0], "master hb").2
            } else {
                0.0
            };
        let together = per_bus + row(&tables[1], "total").2;
        assert!(
            (together - (row(&all[0], "total").2 + extra)).abs() < 0.03,
            "{profile}: {together}% on two buses against {}% on one plus {extra}%",
            row(&all[0], "total").2
        );
        assert_eq!(
            per_bus,
            row(&tables[1], "total").2,
            "{profile}: both buses alike"
        );
    }
}

#[test]
fn cia402_platform_file_round_trips_and_bad_fields_are_named() {
    let _serial = serial();
    let dir = std::env::temp_dir().join(format!("rollbase-cli-cia-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let out = rollbase()
        .args(["config", "default", "--profile", "cia402"])
        .output()
        .unwrap();
    assert!(out.status.success());
    let text = String::from_utf8(out.stdout).unwrap();
    assert!(text.contains("protocol = \"cia402\""), "{text}");
    let good = dir.join("cia.toml");
    std::fs::write(&good, &text).unwrap();
    let out = rollbase()
        .args(["config", "check"])
        .arg(&good)
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    for (from, to, field) in [
        (
            "rpdo_timeout_ms = 50",
            "rpdo_timeout_ms = 2",
            "cia402.rpdo_timeout_ms",
        ),
        ("leg_node = 12", "leg_node = 1", "cia402.wheels[3].leg_node"),
    ] {
        assert!(text.contains(from), "default file lacks `{from}`");
        let bad = dir.join("bad.toml");
        std::fs::write(&bad, text.replacen(from, to, 1)).unwrap();
        let out = rollbase()
            .args(["config", "check"])
            .arg(&bad)
            .output()
            .unwrap();
        assert!(!out.status.success(), "`{to}` accepted");
        let err = String::from_utf8_lossy(&out.stderr);
        assert!(err.contains(field), "`{to}`: {err}");
    }
    let out = rollbase()
        .args(["bus-load", "--profile", "cia403"])
        .output()
        .unwrap();
    assert!(!out.status.success());
    assert!(String::from_utf8_lossy(&out.stderr).contains("cia403"));
    let _ = std::fs::remove_dir_all(dir);
}

/// `rollbase config check` with `[cia402.eds]`: the boot plan is checked against the drives'
/// and encoders' description files (driver/tests/eds/, written by interop/cia402_eds.py),
/// relative to the platform file; a file whose drive lacks an object the plan writes is
/// refused naming the node, the object and the file.
#[test]
fn config_check_checks_the_boot_plan_against_eds_files() {
    let _serial = serial();
    let dir = scratch("eds");
    let fixtures = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("driver/tests/eds");
    for f in ["drive.eds", "encoder.eds", "missing-6060.eds", "drive.dcf"] {
        std::fs::copy(fixtures.join(f), dir.join(f)).unwrap();
    }
    let out = rollbase()
        .args(["config", "default", "--profile", "cia402"])
        .output()
        .unwrap();
    let text = String::from_utf8(out.stdout).unwrap();
    assert!(text.contains("[cia402.eds]\n\n"), "{text}");
    let with = |drive: &str| {
        text.replacen(
            "[cia402.eds]\n\n",
            &format!(
                "[cia402.eds]\ndrive = \"{drive}\"\nsteer = \"drive.eds\"\nleg = \"encoder.eds\"\n\n[[cia402.eds.devices]]\nnode = 4\nfile = \"drive.dcf\"\n\n"
            ),
            1,
        )
    };
    let good = dir.join("good.toml");
    std::fs::write(&good, with("drive.eds")).unwrap();
    let out = rollbase()
        .args(["config", "check"])
        .arg(&good)
        .output()
        .unwrap();
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    assert_eq!(
        stdout.matches("boot plan checked against").count(),
        12,
        "{stdout}"
    );
    assert!(
        stdout.contains("node 4 (steering drive): boot plan checked against")
            && stdout.contains("drive.dcf")
            && stdout.contains("2 DCF values written at boot"),
        "{stdout}"
    );
    assert!(
        stdout.contains("DCF value of 0x6041:00 not written (read-only)"),
        "{stdout}"
    );
    let bad = dir.join("bad.toml");
    std::fs::write(&bad, with("missing-6060.eds")).unwrap();
    let out = rollbase()
        .args(["config", "check"])
        .arg(&bad)
        .output()
        .unwrap();
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(
        err.contains("node 1") && err.contains("0x6060:00") && err.contains("missing-6060.eds"),
        "{err}"
    );
    let _ = std::fs::remove_dir_all(dir);
}

/// `rollbase bridge --listen 127.0.0.1:0` with its stderr piped; returns it, its port and a
/// receiver of its further stderr lines (a thread reads them until EOF, or until `keep_stderr`
/// is false: then the thread closes the pipe right after the port line).
fn start_bridge(
    keep_stderr: bool,
) -> (std::process::Child, u16, std::sync::mpsc::Receiver<String>) {
    use std::io::BufRead;
    let mut child = rollbase()
        .args(["bridge", "--listen", "127.0.0.1:0"])
        .env("RUST_LOG", "info")
        .stdout(Stdio::null())
        .stderr(Stdio::piped())
        .spawn()
        .expect("start rollbase bridge");
    let stderr = child.stderr.take().expect("stderr");
    let (port_tx, port_rx) = std::sync::mpsc::channel();
    let (line_tx, line_rx) = std::sync::mpsc::channel();
    std::thread::spawn(move || {
        let mut lines = std::io::BufReader::new(stderr).lines();
        for line in lines.by_ref() {
            let Ok(line) = line else { return };
            if let Some(rest) = line.split("listening on 127.0.0.1:").nth(1) {
                let port: u16 = rest
                    .split(|c: char| !c.is_ascii_digit())
                    .next()
                    .and_then(|p| p.parse().ok())
                    .expect("port in the listening line");
                let _ = port_tx.send(port);
                break;
            }
        }
        if !keep_stderr {
            return; // drops the pipe's read end: the bridge's stderr is now closed
        }
        for line in lines.map_while(Result::ok) {
            let _ = line_tx.send(line);
        }
    });
    let port = port_rx
        .recv_timeout(Duration::from_secs(10))
        .expect("the bridge printed its port");
    (child, port, line_rx)
}

/// Two clients on channel vcan0 exchange a frame through the bridge.
fn exchange_a_frame(port: u16) {
    use rollbase_driver::bus::socketcand::SocketcandBus;
    use rollbase_driver::bus::CanBus;
    use rollbase_driver::frame::CanFrame;
    let url = format!("socketcand://127.0.0.1:{port}/vcan0");
    let mut a = SocketcandBus::open(&url).expect("client a");
    let mut b = SocketcandBus::open(&url).expect("client b");
    let f = CanFrame::new(0x181, &[1, 2, 3]).expect("frame");
    let until = Instant::now() + Duration::from_secs(5);
    loop {
        CanBus::send(&mut a, &f).expect("send");
        if let Ok(Some(g)) = b.recv_until(Instant::now() + Duration::from_millis(20)) {
            if g.frame == f {
                break;
            }
        }
        assert!(Instant::now() < until, "the frame never arrived");
    }
}

fn sigterm_and_wait(child: &mut std::process::Child) -> std::process::ExitStatus {
    // SAFETY: sending SIGTERM to our own child process.
    let r = unsafe { libc::kill(child.id() as libc::pid_t, libc::SIGTERM) };
    assert_eq!(r, 0);
    let until = Instant::now() + Duration::from_secs(10);
    loop {
        if let Some(s) = child.try_wait().expect("wait") {
            return s;
        }
        if Instant::now() > until {
            let _ = child.kill();
            panic!("the bridge did not stop within 10 s of SIGTERM");
        }
        std::thread::sleep(Duration::from_millis(20));
    }
}

#[test]
fn bridge_keeps_serving_with_its_stderr_closed_and_exits_0_on_sigterm() {
    let _serial = serial();
    let (mut child, port, _lines) = start_bridge(false);
    // Give the reader thread time to close the pipe, then make the bridge log (every client
    // that leaves is a line on the closed stderr).
    std::thread::sleep(Duration::from_millis(200));
    exchange_a_frame(port);
    exchange_a_frame(port);
    assert!(
        child.try_wait().expect("wait").is_none(),
        "the bridge died with its stderr closed"
    );
    let status = sigterm_and_wait(&mut child);
    assert_eq!(status.code(), Some(0), "{status:?}");
}

#[test]
fn bridge_stops_on_sigterm_like_ctrl_c_with_its_totals() {
    let _serial = serial();
    let (mut child, port, lines) = start_bridge(true);
    exchange_a_frame(port);
    let status = sigterm_and_wait(&mut child);
    assert_eq!(status.code(), Some(0), "{status:?}");
    // The reader thread ends at EOF, which the bridge's exit gives.
    let log: Vec<String> = lines.iter().collect();
    let log = log.join("\n");
    assert!(log.contains("SIGTERM: stopping"), "{log}");
    assert!(
        log.contains("stopped: 2 clients served, ") && log.contains(" lost by slow clients"),
        "{log}"
    );
}

/// A SIGTERM sent the moment the bridge says it is listening is a controlled stop, not a
/// kill: the stop signals are registered before that line (they were registered at the
/// shutdown future's first poll, a few µs later, and a SIGTERM in between killed the bridge
/// without its totals). The signal goes out from the thread that reads the line, as soon as
/// it is read; 100 starts, every one must exit 0. (The race is narrow: the code before the
/// fix, cf5e960^, was killed in 4 and 5 of 100 starts in two of three runs of this test and
/// survived the third, so a regression is caught most of the time, not every time.)
#[test]
fn bridge_stops_cleanly_on_a_sigterm_the_moment_it_listens() {
    use std::io::BufRead;
    let _serial = serial();
    let mut killed = Vec::new();
    for attempt in 0..100 {
        let mut child = rollbase()
            .args(["bridge", "--listen", "127.0.0.1:0"])
            .env("RUST_LOG", "info")
            .stdout(Stdio::null())
            .stderr(Stdio::piped())
            .spawn()
            .expect("start rollbase bridge");
        let pid = child.id() as libc::pid_t;
        let stderr = child.stderr.take().expect("stderr");
        let mut lines = std::io::BufReader::new(stderr).lines();
        let mut seen = false;
        for line in lines.by_ref() {
            let Ok(line) = line else { break };
            if line.contains("listening on 127.0.0.1:") {
                // SAFETY: sending SIGTERM to our own child process.
                assert_eq!(unsafe { libc::kill(pid, libc::SIGTERM) }, 0);
                seen = true;
                break;
            }
        }
        assert!(seen, "attempt {attempt}: the bridge never said it listens");
        // Drain the rest so the bridge never blocks on a full pipe, then wait.
        let rest: Vec<String> = lines.map_while(Result::ok).collect();
        let status = child.wait().expect("wait");
        if status.code() != Some(0) {
            killed.push(format!(
                "attempt {attempt}: {status:?}; {}",
                rest.join(" | ")
            ));
        }
    }
    assert!(
        killed.is_empty(),
        "SIGTERM right after the listening line did not stop the bridge cleanly:\n{}",
        killed.join("\n")
    );
}

/// `rollbase` with a 2 GiB address-space limit: a command that would read an endless input
/// into memory fails fast instead of eating the machine (the pre-fix behaviour this guards).
fn rollbase_limited() -> Command {
    use std::os::unix::process::CommandExt;
    let mut c = rollbase();
    // SAFETY: setrlimit is async-signal-safe and only affects the child.
    unsafe {
        c.pre_exec(|| {
            let lim = libc::rlimit {
                rlim_cur: 2 << 30,
                rlim_max: 2 << 30,
            };
            libc::setrlimit(libc::RLIMIT_AS, &lim);
            Ok(())
        });
    }
    c
}

/// Runs `cmd` to its end within `limit` (killed and failed after that).
fn output_within(mut cmd: Command, limit: Duration) -> std::process::Output {
    let mut child = cmd
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .expect("start rollbase");
    let start = Instant::now();
    loop {
        if child.try_wait().expect("try_wait").is_some() {
            return child.wait_with_output().expect("output");
        }
        if start.elapsed() > limit {
            let _ = child.kill();
            let out = child.wait_with_output().expect("output");
            panic!(
                "{cmd:?} still running after {limit:?}\n{}",
                String::from_utf8_lossy(&out.stderr)
            );
        }
        std::thread::sleep(Duration::from_millis(20));
    }
}

#[test]
fn endless_input_files_are_refused_at_their_size_cap() {
    let _serial = serial();
    let cases: [(&[&str], &str); 6] = [
        (&["config", "check", "/dev/zero"], "1 MiB"),
        (&["demo", "--lockstep", "--config", "/dev/zero"], "1 MiB"),
        (&["demo", "--lockstep", "--plant", "/dev/zero"], "1 MiB"),
        (&["demo", "--lockstep", "--faults", "/dev/zero"], "1 MiB"),
        (
            &["run", "--bus", "vcan0", "--trajectory", "/dev/zero"],
            "8 MiB",
        ),
        (&["monitor", "--candump", "/dev/zero"], "4096 bytes"),
    ];
    for (args, cap) in cases {
        let mut c = rollbase_limited();
        c.args(args);
        let out = output_within(c, Duration::from_secs(20));
        let err = String::from_utf8_lossy(&out.stderr);
        assert!(
            out.status.code().is_some_and(|c| c != 0),
            "{args:?}: exit {:?}\n{err}",
            out.status
        );
        assert!(
            err.contains("/dev/zero") && err.contains(cap),
            "{args:?}: the error must name the file and the cap ({cap}):\n{err}"
        );
    }
}

#[test]
fn cycle_rates_outside_the_timing_design_are_refused() {
    let _serial = serial();
    let dir = std::env::temp_dir().join(format!("rollbase-cli-hz-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let text = String::from_utf8(
        rollbase()
            .args(["config", "default"])
            .output()
            .unwrap()
            .stdout,
    )
    .unwrap();
    assert!(text.contains("cycle_hz = 250.0"), "{text}");
    for (hz, bound) in [
        ("0.001", "at least 80 Hz"),
        ("10.0", "at least 80 Hz"),
        ("1000.0", "at most 333 Hz"),
    ] {
        let path = dir.join(format!("hz-{hz}.toml"));
        std::fs::write(
            &path,
            text.replacen("cycle_hz = 250.0", &format!("cycle_hz = {hz}"), 1),
        )
        .unwrap();
        for args in [
            vec!["config", "check"],
            vec!["demo", "--lockstep", "--config"],
        ] {
            let out = output_within(
                {
                    let mut c = rollbase();
                    c.args(&args).arg(&path);
                    c
                },
                Duration::from_secs(20),
            );
            let err = String::from_utf8_lossy(&out.stderr);
            assert!(
                !out.status.success(),
                "cycle_hz = {hz} accepted by {args:?}"
            );
            assert!(
                err.contains("cycle_hz") && err.contains(bound),
                "cycle_hz = {hz}, {args:?}:\n{err}"
            );
        }
    }
    let _ = std::fs::remove_dir_all(dir);
}

#[test]
fn monitor_reports_file_line_numbers_and_goes_on_after_bad_lines() {
    let _serial = serial();
    let dir = std::env::temp_dir().join(format!("rollbase-cli-mon-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let path = dir.join("bad.log");
    let mut log = b"(1.000000) vcan0 080#00000033\n\n(1.000100) vcan0 zz#\n".to_vec();
    log.extend_from_slice(b"(1.000200) vcan0 \xff\xfe#00\n");
    log.extend_from_slice(b"(1.000300) vcan0 181#0011223344556677\n");
    std::fs::write(&path, &log).unwrap();
    let out = rollbase()
        .args(["monitor", "--summary", "--candump"])
        .arg(&path)
        .output()
        .unwrap();
    let text = String::from_utf8_lossy(&out.stdout);
    assert!(
        out.status.success(),
        "{text}\n{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let lines: Vec<&str> = text.lines().collect();
    assert_eq!(
        lines.len(),
        5,
        "2 frames, 2 bad lines, the summary:\n{text}"
    );
    assert!(
        lines[1].contains("candump log line 3,") && !lines[1].contains("line 1"),
        "{text}"
    );
    assert!(
        lines[2].contains("candump log line 4,") && lines[2].contains("UTF-8"),
        "{text}"
    );
    assert!(
        lines[3].contains(" 181 "),
        "decoding went on after the bad lines:\n{text}"
    );
    assert!(lines[4].contains("unparsable lines: 2"), "{text}");
    let out = rollbase()
        .args(["monitor", "--json", "--candump"])
        .arg(&path)
        .output()
        .unwrap();
    assert!(out.status.success());
    let v: Vec<serde_json::Value> = String::from_utf8_lossy(&out.stdout)
        .lines()
        .map(|l| serde_json::from_str(l).expect("JSON line"))
        .collect();
    assert_eq!(v.len(), 4);
    assert_eq!(v[1]["line"], 3);
    assert!(
        v[1]["error"].as_str().unwrap().contains("line 3,"),
        "{}",
        v[1]
    );
    assert_eq!(v[2]["line"], 4);
    let _ = std::fs::remove_dir_all(dir);
}

#[test]
fn ctrl_c_in_the_monitor_does_not_claim_to_stop_the_platform() {
    let _serial = serial();
    let mut bridge = rollbase()
        .args(["bridge", "--listen", "127.0.0.1:0"])
        .stderr(Stdio::piped())
        .stdout(Stdio::null())
        .spawn()
        .expect("start the bridge");
    let mut err = std::io::BufReader::new(bridge.stderr.take().unwrap());
    let mut line = String::new();
    let addr = loop {
        line.clear();
        let n = std::io::BufRead::read_line(&mut err, &mut line).unwrap();
        assert!(n > 0, "the bridge ended without saying where it listens");
        if let Some(rest) = line.split("listening on ").nth(1) {
            break rest.split_whitespace().next().unwrap().to_string();
        }
    };
    let monitor = rollbase()
        .args(["monitor", "--bus"])
        .arg(format!("socketcand://{addr}/vcan0"))
        .stdout(Stdio::null())
        .stderr(Stdio::piped())
        .spawn()
        .expect("start the monitor");
    std::thread::sleep(Duration::from_millis(1000));
    // SAFETY: sending SIGINT to our own child process.
    assert_eq!(
        unsafe { libc::kill(monitor.id() as libc::pid_t, libc::SIGINT) },
        0
    );
    let out = monitor.wait_with_output().unwrap();
    let _ = bridge.kill();
    let _ = bridge.wait();
    let text = String::from_utf8_lossy(&out.stderr);
    assert!(out.status.success(), "exit {:?}: {text}", out.status);
    assert!(
        !text.contains("decelerat"),
        "the monitor moves nothing:\n{text}"
    );
    assert!(text.contains("only listens"), "{text}");
}

#[test]
fn a_demo_whose_motors_do_not_respond_fails_with_a_following_error() {
    let _serial = serial();
    let dir = std::env::temp_dir().join(format!("rollbase-cli-follow-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let plant = dir.join("dead.toml");
    std::fs::write(&plant, "drive_time_constant = 1e300\n").unwrap();
    let text = String::from_utf8(
        rollbase()
            .args(["config", "default"])
            .output()
            .unwrap()
            .stdout,
    )
    .unwrap();
    let heavy = dir.join("heavy.toml");
    assert!(text.contains("mass = 150.0"), "{text}");
    std::fs::write(&heavy, text.replacen("mass = 150.0", "mass = 1e308", 1)).unwrap();
    for (opt, file) in [("--plant", &plant), ("--config", &heavy)] {
        for profile in ["native", "cia402"] {
            let out = output_within(
                {
                    let mut c = rollbase();
                    c.args(["demo", "--lockstep", "--profile", profile, opt])
                        .arg(file);
                    c
                },
                Duration::from_secs(60),
            );
            let stdout = String::from_utf8_lossy(&out.stdout);
            assert_eq!(
                out.status.code(),
                Some(1),
                "{opt} {profile}: a platform that does not move must fail the run\n{stdout}\n{}",
                String::from_utf8_lossy(&out.stderr)
            );
            assert!(
                stdout.contains("fault: following error: wheel")
                    && stdout.contains("supervisor_final_state")
                    && stdout.contains("fault"),
                "{opt} {profile}:\n{stdout}"
            );
        }
    }
    let _ = std::fs::remove_dir_all(dir);
}

// ---------------------------------------------------------------------------------------------
// Issue 19, findings 5 and 6: recordings are never lost, outputs and inputs are checked first.
// (One block; see src/app/sinks.rs for the rules these tests hold the CLI to.)
// ---------------------------------------------------------------------------------------------

/// A fresh scratch directory for one test.
fn scratch(name: &str) -> std::path::PathBuf {
    let d = std::env::temp_dir().join(format!("rollbase-cli-{name}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&d);
    std::fs::create_dir_all(&d).unwrap();
    d
}

/// The temporary files (`.NAME.partial-PID…`) in `dir`.
fn partials(dir: &std::path::Path) -> Vec<std::path::PathBuf> {
    let mut v: Vec<_> = std::fs::read_dir(dir)
        .unwrap()
        .filter_map(|e| e.ok())
        .map(|e| e.path())
        .filter(|p| {
            p.file_name()
                .is_some_and(|n| n.to_string_lossy().contains(".partial-"))
        })
        .collect();
    v.sort();
    v
}

/// Bytes that are not an MCAP file, to stand for an earlier recording.
fn known_bytes() -> Vec<u8> {
    (0..70_000u32).map(|i| (i * 31 % 251) as u8).collect()
}

/// A recording as a reader sees it: the MCAP summary (index) is present and counts more than
/// zero messages, and every message reads back with its chunk CRCs checked.
fn assert_readable_recording(path: &std::path::Path) -> u64 {
    let bytes = std::fs::read(path).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
    let summary = mcap::Summary::read(&bytes)
        .unwrap_or_else(|e| panic!("{}: summary unreadable: {e}", path.display()))
        .unwrap_or_else(|| panic!("{}: no summary section", path.display()));
    let stats = summary.stats.expect("statistics record");
    assert!(stats.message_count > 0, "{}: empty", path.display());
    let read = rollbase::record::read_recording(path)
        .unwrap_or_else(|e| panic!("{}: {e}", path.display()));
    assert!(
        !read.is_empty(),
        "{}: no per-cycle messages",
        path.display()
    );
    stats.message_count
}

#[test]
fn refused_runs_leave_an_existing_recording_byte_identical() {
    let _serial = serial();
    let dir = scratch("refused");
    let old = known_bytes();
    std::fs::write(dir.join("old.mcap"), &old).unwrap();
    std::fs::write(dir.join("old.log"), &old[..1000]).unwrap();
    std::fs::write(
        dir.join("node99.toml"),
        "[[motor_fault]]\nnode = 99\nat = 1.0\n",
    )
    .unwrap();
    let cases: [(&[&str], &str); 3] = [
        // Refused by validation before the bus is opened.
        (
            &[
                "run",
                "--bus",
                "nosuchcan7",
                "--trajectory",
                "scenario:seed000",
                "--duration=-5",
            ],
            "--duration -5",
        ),
        // Valid arguments, but the bus cannot be opened: still nothing written.
        (
            &[
                "run",
                "--bus",
                "nosuchcan7",
                "--trajectory",
                "scenario:seed000",
                "--duration=5",
            ],
            "nosuchcan7",
        ),
        (
            &["demo", "--lockstep", "--faults", "node99.toml"],
            "motor_fault[0].node` = 99",
        ),
    ];
    for (args, says) in cases {
        let out = rollbase()
            .current_dir(&dir)
            .args(args)
            .args(["--record", "old.mcap", "--candump", "old.log"])
            .output()
            .unwrap();
        let err = String::from_utf8_lossy(&out.stderr);
        assert_eq!(out.status.code(), Some(2), "{args:?}: {err}");
        assert!(err.contains(says), "{args:?}: expected `{says}` in {err}");
        assert!(
            std::fs::read(dir.join("old.mcap")).unwrap() == old,
            "{args:?}: the earlier recording was changed"
        );
        assert!(
            std::fs::read(dir.join("old.log")).unwrap() == old[..1000],
            "{args:?}: the earlier candump log was changed"
        );
        assert_eq!(partials(&dir), Vec::<std::path::PathBuf>::new(), "{args:?}");
    }
    let _ = std::fs::remove_dir_all(dir);
}

#[test]
fn the_same_file_for_record_and_candump_is_refused_before_anything_is_written() {
    let _serial = serial();
    let dir = scratch("same");
    let abs = dir.join("same.out").display().to_string();
    for (record, candump) in [
        ("same.out", "same.out"),
        ("./same.out", abs.as_str()),
        ("sub/../same.out", "same.out"),
    ] {
        std::fs::create_dir_all(dir.join("sub")).unwrap();
        let out = rollbase()
            .current_dir(&dir)
            .args([
                "demo",
                "--lockstep",
                "--record",
                record,
                "--candump",
                candump,
            ])
            .output()
            .unwrap();
        let err = String::from_utf8_lossy(&out.stderr);
        assert_eq!(out.status.code(), Some(2), "{record} {candump}: {err}");
        assert!(
            err.contains("--record and --candump both name") && err.contains("same.out"),
            "{err}"
        );
        let left: Vec<_> = std::fs::read_dir(&dir)
            .unwrap()
            .filter_map(|e| e.ok())
            .map(|e| e.file_name().to_string_lossy().into_owned())
            .filter(|n| n != "sub")
            .collect();
        assert!(left.is_empty(), "{record} {candump}: wrote {left:?}");
    }
    let _ = std::fs::remove_dir_all(dir);
}

#[test]
fn a_demo_whose_stdout_and_stderr_go_away_still_finishes_its_recording() {
    use std::io::BufRead;
    use std::os::unix::process::CommandExt;
    let _serial = serial();
    let dir = scratch("sigpipe");
    // `rollbase demo --lockstep --record x.mcap 2>&1 | head -1`: one pipe for both, its
    // reader gone after the first line.
    let (reader, writer) = std::io::pipe().expect("pipe");
    let mut child = rollbase()
        .current_dir(&dir)
        .args(["demo", "--lockstep", "--record", "x.mcap"])
        .stdout(writer.try_clone().unwrap())
        .stderr(writer)
        .spawn()
        .expect("start rollbase demo");
    let mut first = String::new();
    let mut lines = std::io::BufReader::new(reader);
    lines.read_line(&mut first).unwrap();
    assert!(first.starts_with("demo: "), "{first}");
    drop(lines); // the reader goes away: every later write gets EPIPE
    let status = child.wait().unwrap();
    // Completed run: exit 0 (not killed by SIGPIPE, not 141).
    assert_eq!(status.code(), Some(0), "{status:?}");
    assert_readable_recording(&dir.join("x.mcap"));
    assert!(partials(&dir).is_empty(), "{:?}", partials(&dir));

    // Both closed: the process starts without fds 1 and 2.
    let mut c = rollbase();
    c.current_dir(&dir)
        .args(["demo", "--lockstep", "--json", "--record", "y.mcap"]);
    // SAFETY: close() is async-signal-safe; the child closes its own stdout and stderr.
    unsafe {
        c.pre_exec(|| {
            libc::close(1);
            libc::close(2);
            Ok(())
        });
    }
    let status = c.status().unwrap();
    assert_eq!(status.code(), Some(0), "{status:?}");
    let n = assert_readable_recording(&dir.join("y.mcap"));
    // A summary written to a reused fd 1 would have gone into the recording; it reads back
    // whole, with as many messages as the first run (same seed, lockstep).
    assert_eq!(n, assert_readable_recording(&dir.join("x.mcap")));
    let _ = std::fs::remove_dir_all(dir);
}

/// `rollbase` with a file-size limit (`ulimit -f`): a write past `bytes` fails (EFBIG), as
/// on a full disk.
fn rollbase_fsize_limited(bytes: u64) -> Command {
    use std::os::unix::process::CommandExt;
    let mut c = rollbase();
    // SAFETY: setrlimit is async-signal-safe and only affects the child.
    unsafe {
        c.pre_exec(move || {
            let lim = libc::rlimit {
                rlim_cur: bytes as libc::rlim_t,
                rlim_max: bytes as libc::rlim_t,
            };
            if libc::setrlimit(libc::RLIMIT_FSIZE, &lim) != 0 {
                return Err(std::io::Error::last_os_error());
            }
            Ok(())
        });
    }
    c
}

#[test]
fn a_full_disk_stops_the_run_reports_the_cause_and_keeps_the_data_for_recover() {
    let _serial = serial();
    let dir = scratch("full");
    let old = known_bytes();
    std::fs::write(dir.join("x.mcap"), &old).unwrap();
    // 768 KiB: the recording (256 KiB chunks, ~2.8 kB per cycle) fails after ~1 s of run.
    let limit = 768 * 1024;
    let out = output_within(
        {
            let mut c = rollbase_fsize_limited(limit);
            c.current_dir(&dir)
                .args(["demo", "--lockstep", "--json", "--record", "x.mcap"]);
            c
        },
        Duration::from_secs(60),
    );
    let stderr = String::from_utf8_lossy(&out.stderr);
    // Exit 4: the recording failed; not killed by SIGXFSZ.
    assert_eq!(out.status.code(), Some(4), "{:?}\n{stderr}", out.status);
    assert!(
        stderr.contains("recording x.mcap failed during the run")
            && stderr.contains("File too large"),
        "the cause must be named:\n{stderr}"
    );
    // The summary is still printed: a controlled stop long before the 27.6 s trajectory's end.
    let v: serde_json::Value = serde_json::from_slice(&out.stdout).expect("one JSON summary");
    assert_eq!(v["supervisor_final_state"], "stopped", "{v}");
    let cycles = v["cycles"].as_u64().unwrap();
    assert!(cycles > 0 && (cycles as f64) < 27.6 * 250.0, "{v}");
    // Nothing pretends to be a finished recording: the earlier x.mcap is untouched, and the
    // data written up to the failure is in the temporary file the error names, without
    // summary or footer.
    assert!(std::fs::read(dir.join("x.mcap")).unwrap() == old);
    let kept = partials(&dir);
    assert_eq!(kept.len(), 1, "{kept:?}");
    let kept = &kept[0];
    let kept_name = kept.file_name().unwrap().to_string_lossy().into_owned();
    assert!(kept_name.starts_with(".x.mcap.partial-"), "{kept_name}");
    assert!(
        stderr.contains(&kept_name) && stderr.contains("rollbase recover"),
        "{stderr}"
    );
    let bytes = std::fs::read(kept).unwrap();
    assert!(bytes.len() as u64 <= limit && bytes.len() > 256 * 1024);
    assert!(mcap::read::footer(&bytes).is_err() || !bytes.ends_with(mcap::MAGIC));
    // What the error says to do works.
    let out = rollbase()
        .current_dir(&dir)
        .arg("recover")
        .arg(kept)
        .args(["--out", "x.recovered.mcap"])
        .output()
        .unwrap();
    assert_eq!(
        out.status.code(),
        Some(0),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    assert_readable_recording(&dir.join("x.recovered.mcap"));

    // The candump log alone: same rules.
    let out = output_within(
        {
            let mut c = rollbase_fsize_limited(64 * 1024);
            c.current_dir(&dir)
                .args(["demo", "--lockstep", "--json", "--candump", "x.log"]);
            c
        },
        Duration::from_secs(60),
    );
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(4), "{stderr}");
    assert!(stderr.contains("File too large"), "{stderr}");
    assert!(serde_json::from_slice::<serde_json::Value>(&out.stdout).is_ok());
    assert!(!dir.join("x.log").exists());
    let log = partials(&dir)
        .into_iter()
        .find(|p| p.to_string_lossy().contains(".x.log.partial-"))
        .expect("the log up to the failure is kept");
    assert!(stderr.contains(&*log.file_name().unwrap().to_string_lossy()));
    let text = String::from_utf8(std::fs::read(&log).unwrap()).unwrap();
    assert!(
        text.starts_with('(') && text.lines().count() > 100,
        "{text}"
    );
    let _ = std::fs::remove_dir_all(dir);
}

#[test]
fn an_output_under_a_regular_file_is_refused_with_a_clear_message() {
    let _serial = serial();
    let dir = scratch("underfile");
    std::fs::write(dir.join("file"), b"not a directory").unwrap();
    for (opt, path) in [
        ("--record", "file/x.mcap"),
        ("--candump", "file/sub/x.log"),
        ("--plots", "file/p"),
    ] {
        let out = rollbase()
            .current_dir(&dir)
            .args(["demo", "--lockstep", opt, path])
            .output()
            .unwrap();
        let err = String::from_utf8_lossy(&out.stderr);
        assert_eq!(out.status.code(), Some(2), "{opt} {path}: {err}");
        assert!(
            err.contains(&format!("{opt} {path}"))
                && err.contains("file is a file, not a directory"),
            "{opt} {path}: {err}"
        );
        assert!(!err.contains("File exists"), "{err}");
    }
    assert_eq!(std::fs::read(dir.join("file")).unwrap(), b"not a directory");
    let _ = std::fs::remove_dir_all(dir);
}

#[test]
fn a_fifo_given_as_an_output_is_written_or_refused_never_replaced() {
    use std::io::BufRead;
    use std::os::unix::fs::FileTypeExt;
    let _serial = serial();
    let dir = scratch("fifo");
    let fifo = dir.join("pipe");
    let c = std::ffi::CString::new(fifo.display().to_string()).unwrap();
    // SAFETY: mkfifo with a valid NUL-terminated path.
    assert_eq!(unsafe { libc::mkfifo(c.as_ptr(), 0o600) }, 0);
    // A recording needs a regular file: refused up front (before the FIFO is opened).
    let out = output_within(
        {
            let mut c = rollbase();
            c.current_dir(&dir)
                .args(["demo", "--lockstep", "--record", "pipe"]);
            c
        },
        Duration::from_secs(20),
    );
    let err = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(2), "{err}");
    assert!(err.contains("--record pipe: not a regular file"), "{err}");
    // A candump log is written into it (like `--candump /dev/stdout`), not renamed over it.
    let path = fifo.clone();
    let reader = std::thread::spawn(move || {
        let f = std::fs::File::open(path).unwrap();
        std::io::BufReader::new(f)
            .lines()
            .map_while(Result::ok)
            .filter(|l| l.starts_with('(') && l.contains(" vcan0 "))
            .count()
    });
    let out = output_within(
        {
            let mut c = rollbase();
            c.current_dir(&dir)
                .args(["demo", "--lockstep", "--json", "--candump", "pipe"]);
            c
        },
        Duration::from_secs(60),
    );
    assert_eq!(
        out.status.code(),
        Some(0),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let frames = reader.join().unwrap();
    assert!(frames > 1000, "{frames} candump lines through the FIFO");
    let ft = std::fs::symlink_metadata(&fifo).unwrap().file_type();
    assert!(ft.is_fifo(), "the FIFO was replaced: {ft:?}");
    assert!(partials(&dir).is_empty());
    let _ = std::fs::remove_dir_all(dir);
}

#[test]
fn bad_durations_are_refused_before_the_bus_is_opened() {
    let _serial = serial();
    // The bus: a socketcand URL on a local listener that records whether anyone connected.
    let listener = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
    listener.set_nonblocking(true).unwrap();
    let url = format!(
        "socketcand://127.0.0.1:{}/vcan0",
        listener.local_addr().unwrap().port()
    );
    for d in ["1e300", "nan", "-5", "inf", "0"] {
        let out = output_within(
            {
                let mut c = rollbase();
                c.args(["run", "--bus", &url, "--trajectory", "scenario:seed000"])
                    .arg(format!("--duration={d}"));
                c
            },
            Duration::from_secs(20),
        );
        let err = String::from_utf8_lossy(&out.stderr);
        assert_eq!(out.status.code(), Some(2), "--duration {d}: {err}");
        assert!(
            err.contains("--duration")
                && err.contains("must be a number of seconds in (0, 1000000]"),
            "--duration {d}: {err}"
        );
        assert!(!err.contains("panicked"), "{err}");
        match listener.accept() {
            Err(e) if e.kind() == std::io::ErrorKind::WouldBlock => {}
            other => panic!("--duration {d}: the bus was opened: {other:?}"),
        }
    }
    // The listener does see a run that gets as far as opening its bus.
    let mut child = rollbase()
        .args(["run", "--bus", &url, "--trajectory", "scenario:seed000"])
        .arg("--duration=1")
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .spawn()
        .unwrap();
    let until = Instant::now() + Duration::from_secs(20);
    let connected = loop {
        match listener.accept() {
            Ok(_) => break true,
            Err(_) if Instant::now() < until => std::thread::sleep(Duration::from_millis(20)),
            Err(_) => break false,
        }
    };
    let _ = child.kill();
    let _ = child.wait();
    assert!(
        connected,
        "a valid run never connected: the check above proves nothing"
    );
}

#[test]
fn a_recording_left_by_kill_9_is_recovered_with_index_and_summary() {
    let _serial = serial();
    let dir = scratch("kill9");
    let mut child = rollbase()
        .current_dir(&dir)
        .args(["demo", "--json", "--record", "x.mcap"])
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .spawn()
        .expect("start rollbase demo");
    // Wait until more than two 256 KiB chunks are on disk (about 1 s of a real-time run).
    let until = Instant::now() + Duration::from_secs(30);
    let partial = loop {
        let p = partials(&dir).into_iter().next();
        if let Some(p) = p.filter(|p| std::fs::metadata(p).is_ok_and(|m| m.len() > 600_000)) {
            break p;
        }
        if Instant::now() > until {
            let _ = child.kill();
            panic!("no growing recording after 30 s: {:?}", partials(&dir));
        }
        std::thread::sleep(Duration::from_millis(50));
    };
    child.kill().unwrap(); // SIGKILL
    let status = child.wait().unwrap();
    assert_eq!(
        std::os::unix::process::ExitStatusExt::signal(&status),
        Some(libc::SIGKILL)
    );
    // The target was never written; the temporary file has no footer.
    assert!(!dir.join("x.mcap").exists());
    let bytes = std::fs::read(&partial).unwrap();
    assert!(!bytes.ends_with(mcap::MAGIC) || mcap::read::footer(&bytes).is_err());
    assert!(matches!(mcap::Summary::read(&bytes), Ok(None) | Err(_)));
    let out = rollbase()
        .current_dir(&dir)
        .arg("recover")
        .arg(&partial)
        .args(["--out", "x.mcap"])
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(0), "{err}");
    assert!(err.contains("recovered "), "{err}");
    let n = assert_readable_recording(&dir.join("x.mcap"));
    assert!(n > 1000, "{n} messages recovered");
    // The input is never modified.
    assert_eq!(std::fs::read(&partial).unwrap(), bytes);
    let _ = std::fs::remove_dir_all(dir);
}

#[test]
fn endless_inputs_to_plot_recover_and_commands_are_refused() {
    let _serial = serial();
    let dir = scratch("endless");
    let cases: [(&[&str], &str); 3] = [
        (
            &["plot", "/dev/zero", "--out", "plots"],
            "not a regular file",
        ),
        (
            &["recover", "/dev/zero", "--out", "r.mcap"],
            "not a regular file",
        ),
        (
            &["demo", "--lockstep", "--commands", "/dev/zero"],
            "longer than the 4096 bytes a line may have",
        ),
    ];
    for (args, says) in cases {
        let mut c = rollbase_limited();
        c.current_dir(&dir).args(args);
        let out = output_within(c, Duration::from_secs(20));
        let err = String::from_utf8_lossy(&out.stderr);
        assert_eq!(out.status.code(), Some(2), "{args:?}: {err}");
        assert!(
            err.contains("/dev/zero") && err.contains(says),
            "{args:?}: {err}"
        );
    }
    assert!(!dir.join("r.mcap").exists());
    let _ = std::fs::remove_dir_all(dir);
}

/// `rollbase demo --trajectory FILE` (issue 18): a waypoint file with times left out and legs
/// at their limits runs time-scaled in lockstep, the JSON summary gives the nominal and
/// executed durations and the slowest scale; a file no timing can fix is refused naming the
/// waypoint.
#[test]
fn a_waypoint_file_runs_time_scaled_in_the_demo() {
    let _serial = serial();
    let dir = std::env::temp_dir().join(format!("rollbase-cli-traj-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let wp = |t: Option<f64>, x: f64, th: f64, legs: f64| {
        let t = t.map(|t| format!("t = {t}\n")).unwrap_or_default();
        format!(
            "[[waypoints]]\n{t}x = {x}\ny = 0.2\ntheta = {th}\nlegs = [{legs}, {legs}, {legs}, {legs}]\n\n"
        )
    };
    let file = dir.join("waypoints.toml");
    let text = [
        wp(Some(0.0), 0.0, 0.0, 0.45),
        wp(None, 0.8, 1.0, 0.56),
        wp(Some(4.0), 1.2, 0.0, 0.37),
        wp(Some(5.0), 0.6, -0.5, 0.45),
    ]
    .concat();
    std::fs::write(&file, text).unwrap();
    let out = output_within(
        {
            let mut c = rollbase();
            c.args(["demo", "--lockstep", "--json", "--trajectory"])
                .arg(&file);
            c
        },
        Duration::from_secs(120),
    );
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let v: serde_json::Value = serde_json::from_slice(&out.stdout).expect("JSON");
    assert_eq!(v["supervisor_final_state"], "stopped", "{v}");
    assert_eq!(v["scenario"], "trajectory");
    let nominal = v["duration_nominal_s"].as_f64().expect("nominal duration");
    let executed = v["duration_executed_s"]
        .as_f64()
        .expect("executed duration");
    let scale = v["time_scale_min"].as_f64().expect("slowest scale");
    assert!(executed > nominal && scale > 0.0 && scale < 1.0, "{v}");
    assert!(
        v["time_scale_limit"]
            .as_str()
            .is_some_and(|s| s.starts_with("wheel ")),
        "{v}"
    );
    assert!(v["max_position_error_m"].as_f64().unwrap() < 0.005, "{v}");
    // A leg beyond its range: refused before anything moves, naming the waypoint.
    let bad = dir.join("bad.toml");
    std::fs::write(
        &bad,
        [wp(Some(0.0), 0.0, 0.0, 0.45), wp(Some(2.0), 0.5, 0.0, 0.6)].concat(),
    )
    .unwrap();
    let out = rollbase()
        .args(["demo", "--lockstep", "--trajectory"])
        .arg(&bad)
        .output()
        .unwrap();
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("waypoints[1].legs[0] = 0.6"), "{err}");
    let _ = std::fs::remove_dir_all(dir);
}

#[test]
fn example_platforms_print_check_and_their_new_fields_are_explained() {
    let _serial = serial();
    let dir = std::env::temp_dir().join(format!("rollbase-cli-ex-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let mut files = Vec::new();
    for name in ["mpo700", "three-wheel", "six-wheel"] {
        let out = rollbase()
            .args(["config", "default", "--example", name])
            .output()
            .unwrap();
        assert!(out.status.success(), "{name}");
        let text = String::from_utf8(out.stdout).unwrap();
        // The printed example is the one in docs/examples.
        let doc = std::fs::read_to_string(
            std::path::Path::new(env!("CARGO_MANIFEST_DIR"))
                .join(format!("docs/examples/{name}.toml")),
        )
        .unwrap();
        assert_eq!(text, doc, "docs/examples/{name}.toml is stale");
        let path = dir.join(format!("{name}.toml"));
        std::fs::write(&path, &text).unwrap();
        let out = rollbase()
            .args(["config", "check"])
            .arg(&path)
            .output()
            .unwrap();
        assert!(
            out.status.success(),
            "{}",
            String::from_utf8_lossy(&out.stderr)
        );
        files.push(text);
    }
    let out = rollbase()
        .args(["config", "default", "--example", "mpo500"])
        .output()
        .unwrap();
    assert!(!out.status.success());
    assert!(String::from_utf8_lossy(&out.stderr).contains("mpo700, three-wheel or six-wheel"));
    // Each new field's error names the field and says what to give.
    let mpo = &files[0];
    for (from, to, field, hint) in [
        (
            "caster_offset = 0.045",
            "caster_offset = -0.01",
            "wheels[0].caster_offset",
            "trailing caster",
        ),
        ("bus = 0", "bus = 2", "wheels[0].bus", "must be 0 or 1"),
        (
            "drive_polarity = 1",
            "drive_polarity = 0",
            "wheels[0].drive_polarity",
            "mirrored",
        ),
        (
            "steer_polarity = 1",
            "steer_polarity = 2",
            "wheels[0].steer_polarity",
            "mirrored",
        ),
        (
            "coupling = 0.0",
            "coupling = 50.0",
            "wheels[0].coupling",
            "within ±10",
        ),
        (
            "    -7.5398223686155035,",
            "    7.6,",
            "wheels[0].steer_range",
            "half a turn",
        ),
        (
            "lambda = 0.30610455730027936",
            "lambda = -1.0",
            "wheels[0].lambda",
            "greater than 0",
        ),
    ] {
        assert!(mpo.contains(from), "the example lacks `{from}`");
        let bad = dir.join("bad.toml");
        std::fs::write(&bad, mpo.replacen(from, to, 1)).unwrap();
        let out = rollbase()
            .args(["config", "check"])
            .arg(&bad)
            .output()
            .unwrap();
        assert!(!out.status.success(), "`{to}` accepted");
        let err = String::from_utf8_lossy(&out.stderr);
        assert!(err.contains(field) && err.contains(hint), "`{to}`: {err}");
    }
    // A wheel with both a fixed `lambda` and a leg range is refused, naming what to remove.
    let six = files[2].replacen("lambda_min = 0.37", "lambda = 0.4", 1);
    let bad = dir.join("bad.toml");
    std::fs::write(&bad, six).unwrap();
    let out = rollbase()
        .args(["config", "check"])
        .arg(&bad)
        .output()
        .unwrap();
    assert!(!out.status.success());
    assert!(String::from_utf8_lossy(&out.stderr).contains("has no leg"));
    // (That it runs on two buses, in real time and on virtual time, is
    // `a_two_bus_platform_runs_on_two_buses_and_one_bus_is_refused` and
    // `lockstep_demo_runs_a_two_bus_platform`.)
    let _ = std::fs::remove_dir_all(dir);
}

/// Two CAN buses (issue 25): the real-time demo runs the six-wheel example (wheels 1–3 on
/// bus 0, 4–6 on bus 1) on two in-process buses, each wheel's frames on its own bus (the
/// candump log names them vcan0 and vcan1) with one SYNC per bus per cycle; `run` and
/// `drive` refuse a number of `--bus` options that differs from the platform's buses, and
/// the same bus twice.
#[test]
fn a_two_bus_platform_runs_on_two_buses_and_one_bus_is_refused() {
    let _serial = serial();
    let root = env!("CARGO_MANIFEST_DIR");
    let six = format!("{root}/docs/examples/six-wheel.toml");
    let dir = std::env::temp_dir().join(format!("rollbase-cli-buses-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let wp = |t: f64, x: f64| {
        format!("[[waypoints]]\nt = {t}\nx = {x}\ny = 0.0\ntheta = 0.0\nlegs = [0.465, 0.465, 0.465, 0.465, 0.465, 0.465]\n\n")
    };
    std::fs::write(dir.join("wp.toml"), wp(0.0, 0.0) + &wp(2.0, 0.3)).unwrap();
    let out = rollbase()
        .current_dir(&dir)
        .args([
            "demo",
            "--json",
            "--config",
            &six,
            "--trajectory",
            "wp.toml",
        ])
        .args(["--candump", "two.log"])
        .output()
        .unwrap();
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(0), "{stderr}");
    let v: serde_json::Value = serde_json::from_slice(&out.stdout).expect("JSON");
    let cycles = v["cycles"].as_u64().unwrap();
    let misses = v["deadline_misses"].as_u64().unwrap();
    println!(
        "two-bus demo: {cycles} cycles, {misses} deadline misses, max position error {} m, final state {}",
        v["max_position_error_m"], v["supervisor_final_state"]
    );
    assert!(v["fault_reason"].is_null(), "{v}");
    assert_eq!(v["supervisor_final_state"], "stopped", "{v}");
    // The 2 s trajectory is 500 cycles (a busy machine may skip a few: they are not counted).
    assert!(cycles > 250, "{cycles} cycles for a 2 s trajectory");
    assert!(misses * 10 < cycles, "{misses} deadline misses in {cycles}");
    assert_eq!(v["can_bus"].as_array().map(|a| a.len()), Some(2), "{v}");
    let log = std::fs::read_to_string(dir.join("two.log")).unwrap();
    check_two_bus_log(&log, cycles);
    // One `--bus` for two platform buses: refused before any bus is opened, naming both counts.
    for cmd in [
        vec!["run", "--trajectory", "scenario:seed000"],
        vec!["drive"],
    ] {
        let out = rollbase()
            .args(&cmd)
            .args(["--config", &six, "--bus", "nosuchcan7"])
            .output()
            .unwrap();
        let err = String::from_utf8_lossy(&out.stderr);
        assert_eq!(out.status.code(), Some(2), "{cmd:?}: {err}");
        assert!(
            err.contains("on 2 CAN bus(es) but 1 `--bus`") && !err.contains("nosuchcan7"),
            "{cmd:?}: {err}"
        );
        let out = rollbase()
            .args(&cmd)
            .args([
                "--config",
                &six,
                "--bus",
                "nosuchcan7",
                "--bus",
                "nosuchcan7",
            ])
            .output()
            .unwrap();
        let err = String::from_utf8_lossy(&out.stderr);
        assert_eq!(out.status.code(), Some(2), "{cmd:?}: {err}");
        assert!(
            err.contains("`--bus nosuchcan7` given twice"),
            "{cmd:?}: {err}"
        );
    }
    // Two `--bus` for a one-bus platform: refused too.
    let out = rollbase()
        .args(["run", "--trajectory", "scenario:seed000"])
        .args(["--bus", "nosuchcan7", "--bus", "nosuchcan8"])
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(2), "{err}");
    assert!(err.contains("on 1 CAN bus(es) but 2 `--bus`"), "{err}");
    let _ = std::fs::remove_dir_all(dir);
}

/// The six-wheel example's candump log (wheels 1–3 on bus 0 as vcan0, 4–6 on bus 1 as
/// vcan1): one SYNC per bus per cycle, every wheel's frames on its bus.
fn check_two_bus_log(log: &str, cycles: u64) {
    let mut syncs = [0u64; 2];
    let mut wrong = Vec::new();
    for l in log.lines() {
        let mut f = l.split_whitespace();
        let (_, iface, frame) = (f.next(), f.next().unwrap(), f.next().unwrap());
        let id = u16::from_str_radix(frame.split('#').next().unwrap(), 16).unwrap();
        let bus = match iface {
            "vcan0" => 0,
            "vcan1" => 1,
            other => panic!("frame on {other}: {l}"),
        };
        let node = id & 0x7F;
        if id == 0x080 {
            syncs[bus] += 1;
        } else if !(1..=6).contains(&node) || usize::from((node - 1) / 3) != bus {
            wrong.push(l.to_string());
        }
    }
    assert_eq!(syncs, [cycles, cycles], "one SYNC per bus per cycle");
    assert!(
        wrong.is_empty(),
        "frames on the wrong bus: {:?}",
        &wrong[..wrong.len().min(5)]
    );
}

/// Two CAN buses on virtual time (issue 25): `demo --lockstep` runs the six-wheel example
/// (seed 000) on two virtual buses and ends stopped on the goal (4.5 m, 4.5 m) within 5 mm,
/// 0.5° and 2 mm of leg; its candump log has one SYNC per bus per cycle and each wheel's
/// frames on its bus.
#[test]
fn lockstep_demo_runs_a_two_bus_platform() {
    let _serial = serial();
    let root = env!("CARGO_MANIFEST_DIR");
    let six = format!("{root}/docs/examples/six-wheel.toml");
    let dir = std::env::temp_dir().join(format!("rollbase-cli-lock2-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let out = rollbase()
        .current_dir(&dir)
        .args(["demo", "--lockstep", "--json", "--config", &six])
        .args(["--candump", "two.log"])
        .output()
        .unwrap();
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(0), "{stderr}");
    let v: serde_json::Value = serde_json::from_slice(&out.stdout).expect("JSON");
    let cycles = v["cycles"].as_u64().unwrap();
    let pos = v["max_position_error_m"].as_f64().unwrap();
    let fin = v["final_position_error_m"].as_f64().unwrap();
    let head = v["max_heading_error_rad"].as_f64().unwrap();
    let leg = v["max_leg_error_m"].as_f64().unwrap();
    println!(
        "two-bus lockstep demo: {cycles} cycles, max position error {pos} m, final {fin} m, max heading error {head} rad, max leg error {leg} m"
    );
    assert!(v["fault_reason"].is_null(), "{v}");
    assert_eq!(v["supervisor_final_state"], "stopped", "{v}");
    assert_eq!(v["can_bus"].as_array().map(|a| a.len()), Some(2), "{v}");
    assert!(pos < 0.005 && fin < 0.005, "{v}");
    assert!(head < 0.5f64.to_radians(), "{v}");
    assert!(leg < 0.002, "{v}");
    let (x, y) = (
        v["final_pose"]["x"].as_f64().expect("final_pose.x"),
        v["final_pose"]["y"].as_f64().expect("final_pose.y"),
    );
    assert!((x - 4.5).abs() < 0.005 && (y - 4.5).abs() < 0.005, "{v}");
    let log = std::fs::read_to_string(dir.join("two.log")).unwrap();
    check_two_bus_log(&log, cycles);
    // `monitor` decodes the log per interface: every frame line names its bus, one summary
    // per bus, nothing rejected, and the two summaries count every frame of the log.
    let mon = rollbase()
        .current_dir(&dir)
        .args([
            "monitor",
            "--summary",
            "--config",
            &six,
            "--candump",
            "two.log",
        ])
        .output()
        .unwrap();
    let text = String::from_utf8_lossy(&mon.stdout);
    assert_eq!(
        mon.status.code(),
        Some(0),
        "{}",
        String::from_utf8_lossy(&mon.stderr)
    );
    let lines: Vec<&str> = text.lines().collect();
    let (frames, summaries) = lines.split_at(lines.len() - 2);
    assert_eq!(
        frames.len(),
        log.lines().count(),
        "one line per logged frame"
    );
    assert!(
        frames
            .iter()
            .all(|l| l.starts_with("vcan0 (") || l.starts_with("vcan1 (")),
        "every frame line names its bus"
    );
    assert!(
        frames.iter().all(|l| !l.contains("REJECTED")),
        "nothing rejected"
    );
    let count = |bus: &str| -> usize {
        let s = summaries
            .iter()
            .find(|l| l.starts_with(&format!("{bus}: frames: ")))
            .unwrap_or_else(|| panic!("no summary for {bus}: {summaries:?}"));
        assert!(s.contains("rejected: 0 "), "{s}");
        s[bus.len() + 10..]
            .split(',')
            .next()
            .and_then(|n| n.trim().parse().ok())
            .unwrap_or_else(|| panic!("frame count in {s}"))
    };
    let (n0, n1) = (count("vcan0"), count("vcan1"));
    println!("monitor of the two-bus log: {n0} frames on vcan0, {n1} on vcan1");
    assert!(n0 > 0 && n1 > 0);
    assert_eq!(n0 + n1, frames.len());
    let _ = std::fs::remove_dir_all(dir);
}

/// `--rolling-turns` reaches the shaper of a live run, and is refused with the DFL (which does
/// not track rolling turns within 5 mm) with an error that says what to pass instead.
#[test]
fn rolling_turns_need_the_kinematic_controller_and_change_how_a_turn_is_driven() {
    let _serial = serial();
    let dir = scratch("rolling");
    let file = dir.join("turn.jsonl");
    // At 10 Hz: forward at 0.5 m/s, then sideways at 0.5 m/s (a 90° change of direction),
    // then let go.
    let mut lines = String::new();
    for k in 0..=30 {
        let t = 0.1 * k as f64;
        let (vx, vy) = match k {
            0..=14 => (0.5, 0.0),
            15..=29 => (0.0, 0.5),
            _ => (0.0, 0.0),
        };
        lines += &format!("{{\"t\": {t:.1}, \"vx\": {vx}, \"vy\": {vy}, \"omega\": 0.0}}\n");
    }
    std::fs::write(&file, lines).unwrap();
    // A lockstep run of a 3 s file takes well under a second; 60 s is a hang.
    let run = |extra: &[&str]| {
        let mut c = rollbase();
        c.args(["demo", "--lockstep", "--json", "--commands"])
            .arg(&file)
            .args(extra);
        output_within(c, Duration::from_secs(60))
    };
    let refused = run(&["--rolling-turns"]);
    let err = String::from_utf8_lossy(&refused.stderr);
    assert_eq!(refused.status.code(), Some(2), "{err}");
    assert!(
        err.contains("--rolling-turns needs --controller kinematic"),
        "{err}"
    );
    let mut end = Vec::new();
    for extra in [
        &["--controller", "kinematic"][..],
        &["--controller", "kinematic", "--rolling-turns"][..],
    ] {
        let out = run(extra);
        assert!(
            out.status.success(),
            "{extra:?}: {}",
            String::from_utf8_lossy(&out.stderr)
        );
        let v: serde_json::Value = serde_json::from_slice(&out.stdout).expect("JSON");
        assert_eq!(v["supervisor_final_state"], "stopped", "{extra:?}: {v}");
        assert!(
            v["max_position_error_m"].as_f64().unwrap() < 0.005,
            "{extra:?}: {v}"
        );
        end.push((
            v["final_pose"]["x"].as_f64().unwrap(),
            v["final_pose"]["y"].as_f64().unwrap(),
        ));
    }
    let _ = std::fs::remove_dir_all(dir);
    // The commands ask for 0.75 m forward then 0.75 m sideways. The line transition slows
    // through the corner to re-steer, the rolling turn keeps rolling while its wheels turn: it
    // ends nearer the commanded displacement (0.14 m from it against 0.29 m when this was
    // written).
    let off = |e: (f64, f64)| (e.0 - 0.75).hypot(e.1 - 0.75);
    assert!(
        off(end[1]) < off(end[0]),
        "rolling turn {:.3} m from the commanded end, line transition {:.3} m: {end:?}",
        off(end[1]),
        off(end[0])
    );
}
