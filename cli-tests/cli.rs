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
