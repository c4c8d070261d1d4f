//! `rollbase-sim` as a service manager or a test harness runs it: SIGTERM, SIGINT, SIGHUP (a
//! closed terminal) and SIGQUIT are a clean stop (summary, exit 0), SIGUSR1/2 are ignored, a
//! closed stdout/stderr never kills it, and what it refuses before it starts exits 2.

use std::io::{BufRead, BufReader};
use std::process::{Child, Command, ExitStatus, Stdio};
use std::sync::mpsc;
use std::time::{Duration, Instant};

fn sim() -> Command {
    Command::new(env!("CARGO_BIN_EXE_rollbase-sim"))
}

/// Waits for the child's exit for at most `limit`; kills it (and fails) after that.
fn wait_bounded(child: &mut Child, limit: Duration) -> ExitStatus {
    let start = Instant::now();
    loop {
        if let Some(s) = child.try_wait().expect("try_wait") {
            return s;
        }
        if start.elapsed() > limit {
            let _ = child.kill();
            let _ = child.wait();
            panic!("rollbase-sim did not exit within {limit:?}");
        }
        std::thread::sleep(Duration::from_millis(20));
    }
}

#[test]
fn sigterm_and_sigint_stop_it_cleanly_with_its_summary() {
    for (sig, name) in [
        (libc::SIGTERM, "SIGTERM"),
        (libc::SIGINT, "SIGINT"),
        (libc::SIGHUP, "SIGHUP"),
        (libc::SIGQUIT, "SIGQUIT"),
    ] {
        let mut child = sim()
            .args(["--bus", "virtual"])
            .stdout(Stdio::null())
            .stderr(Stdio::piped())
            .spawn()
            .expect("start rollbase-sim");
        let stderr = child.stderr.take().expect("stderr");
        let (tx, rx) = mpsc::channel::<String>();
        let reader = std::thread::spawn(move || {
            for line in BufReader::new(stderr).lines().map_while(Result::ok) {
                if tx.send(line).is_err() {
                    break;
                }
            }
        });
        // Running: it has said it waits for SYNC.
        let deadline = Instant::now() + Duration::from_secs(20);
        let mut seen = Vec::new();
        while !seen.iter().any(|l: &String| l.contains("waiting for SYNC")) {
            let left = deadline.saturating_duration_since(Instant::now());
            match rx.recv_timeout(left) {
                Ok(l) => seen.push(l),
                Err(_) => {
                    let _ = child.kill();
                    panic!("no start line within 20 s: {seen:?}");
                }
            }
        }
        // SIGUSR1 and SIGUSR2 are ignored (their default would kill it, unsummarised).
        for usr in [libc::SIGUSR1, libc::SIGUSR2] {
            // SAFETY: sending a signal to our own child process.
            assert_eq!(unsafe { libc::kill(child.id() as libc::pid_t, usr) }, 0);
        }
        std::thread::sleep(Duration::from_millis(200));
        assert!(
            child.try_wait().expect("try_wait").is_none(),
            "{name}: SIGUSR1/SIGUSR2 ended it"
        );
        // SAFETY: sending a signal to our own child process.
        assert_eq!(unsafe { libc::kill(child.id() as libc::pid_t, sig) }, 0);
        let status = wait_bounded(&mut child, Duration::from_secs(20));
        let _ = reader.join();
        seen.extend(rx.try_iter());
        assert_eq!(
            status.code(),
            Some(0),
            "{name}: exit {status:?} (a clean stop exits 0)\n{}",
            seen.join("\n")
        );
        let text = seen.join("\n");
        assert!(
            text.contains("rollbase-sim: ran") && text.contains("final pose"),
            "{name}: no summary:\n{text}"
        );
    }
}

#[test]
fn a_closed_stdout_and_stderr_never_kill_it() {
    let mut child = sim()
        .args(["--bus", "virtual", "--duration", "0.3"])
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .expect("start rollbase-sim");
    // Nobody reads its output: both pipes are closed before it writes its first line.
    drop(child.stdout.take());
    drop(child.stderr.take());
    let status = wait_bounded(&mut child, Duration::from_secs(20));
    assert_eq!(
        status.code(),
        Some(0),
        "exit {status:?}: writing to a closed pipe must not end it"
    );
}

#[test]
fn what_it_refuses_before_starting_exits_2_naming_the_input() {
    let dir = std::env::temp_dir().join(format!("rollbase-sim-exit-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let bad = dir.join("bad.toml");
    std::fs::write(&bad, "[[waypoints]]\nx = \"far\"\n").unwrap();
    let missing = dir.join("missing.toml");
    let six = concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/../docs/examples/six-wheel.toml"
    );
    for (args, needle) in [
        // A platform on two buses with one `--bus`, one bus with two, the same bus twice.
        (
            vec!["--config", six, "--bus", "nosuchcan7"],
            "on 2 CAN bus(es) but 1 `--bus`",
        ),
        (
            vec!["--bus", "nosuchcan7", "--bus", "nosuchcan8"],
            "on 1 CAN bus(es) but 2 `--bus`",
        ),
        (
            vec![
                "--config",
                six,
                "--bus",
                "nosuchcan7",
                "--bus",
                "nosuchcan7",
            ],
            "`--bus nosuchcan7` given twice",
        ),
        (
            vec!["--bus", "virtual", "--start", bad.to_str().unwrap()],
            "bad.toml",
        ),
        (
            vec!["--bus", "virtual", "--start", missing.to_str().unwrap()],
            "missing.toml",
        ),
        (vec!["--bus", "virtual", "--duration=-1"], "--duration"),
        (vec!["--bus", "nosuchcan7"], "nosuchcan7"),
    ] {
        let out = sim().args(&args).output().expect("run rollbase-sim");
        let err = String::from_utf8_lossy(&out.stderr);
        assert_eq!(out.status.code(), Some(2), "{args:?}: {err}");
        assert!(err.contains(needle), "{args:?}: {err}");
    }
    let _ = std::fs::remove_dir_all(dir);
}

#[test]
fn a_platform_on_two_buses_runs_on_two() {
    let six = concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/../docs/examples/six-wheel.toml"
    );
    let out = sim()
        .args(["--config", six, "--bus", "virtual", "--bus", "virtual"])
        .args(["--duration", "0.3", "--priority", "0"])
        .output()
        .expect("run rollbase-sim");
    let err = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(0), "{err}");
    assert!(
        err.contains("6 modules (nodes [1, 2, 3, 4, 5, 6]) of platform `six-wheel` on rollbase-sim and rollbase-sim"),
        "{err}"
    );
}
