//! Process-level reliability checks, measured on the real release binaries (issue 19): prints
//! each result as a Markdown table row and writes the table to `docs/reliability-live.md`,
//! which `fault-campaign` appends to `docs/reliability.md`.
//!
//! ```sh
//! cargo build --release -p rollbase -p rollbase-vcan-sim
//! cargo run --release -p rollbase-tests --bin reliability-live
//! # the same checks on other builds too (e.g. an older commit's), as extra rows:
//! cargo run --release -p rollbase-tests --bin reliability-live -- --compare DIR=LABEL
//! # one check only, without writing the file:
//! cargo run --release -p rollbase-tests --bin reliability-live -- --only bridge-memory --no-write
//! # the real-time runs under load (issue 27; 10 minutes each by default, the ROS 2 run in a
//! # private network namespace), rewriting only their section of the file:
//! unshare -n sh -c 'ip link set lo up; target/release/reliability-live --load --compare DIR=LABEL'
//! ```
//!
//! `--load` (`--load-secs S` to shorten): a SCHED_FIFO timer loop without rollbase under the
//! load (what the machine does to any real-time thread), then for each build the live demo,
//! the live demo as a ROS 2 node and `drive` with `rollbase-sim` over the bridge, each for S
//! seconds while 2 × the cores busy loops run at normal priority; faults are counted and
//! re-armed, deadline misses come from the summary.
//!
//! Every check is a function `fn(&Build) -> Result<Row, String>` listed in [`CHECKS`]: add a
//! check by writing one and adding it there. Each spawns what it needs on loopback only,
//! bounds its load in count and time, and stops every process it started (SIGTERM, then
//! SIGKILL after 5 s). Exit code 1 when a check of the current build fails.

use rollbase_driver::bus::socketcand::SocketcandBus;
use rollbase_driver::bus::CanBus;
use rollbase_driver::frame::CanFrame;
use std::fmt::Write as _;
use std::io::{Read, Write};
use std::net::{Shutdown, TcpStream};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};

/// One row of the table.
struct Row {
    check: &'static str,
    setup: String,
    measured: String,
    pass: bool,
}

/// The binaries a check runs.
struct Build {
    dir: PathBuf,
    label: String,
    /// The current build (its failures fail the run); compared builds only add rows.
    current: bool,
    /// Run the bridge at SCHED_FIFO 60 and the simulator at SCHED_FIFO 81 (the controller
    /// runs at 80), as `chrt -f` would: the real-time figures then show the bridge's own
    /// scheduling, not the machine's other load.
    fifo: bool,
}

impl Build {
    fn label(&self) -> String {
        if self.fifo {
            format!("{}, bridge and simulator at SCHED_FIFO 60/81", self.label)
        } else {
            format!("{}, normal priority", self.label)
        }
    }
}

/// Starts the command at SCHED_FIFO `prio` (set in the child before exec, so every thread
/// it creates inherits it).
fn with_fifo(cmd: &mut Command, prio: Option<i32>) -> &mut Command {
    use std::os::unix::process::CommandExt;
    if let Some(p) = prio {
        // SAFETY: the closure only makes one async-signal-safe system call.
        unsafe {
            cmd.pre_exec(move || {
                let sp = libc::sched_param { sched_priority: p };
                if libc::sched_setscheduler(0, libc::SCHED_FIFO, &sp) == 0 {
                    Ok(())
                } else {
                    Err(std::io::Error::last_os_error())
                }
            });
        }
    }
    cmd
}

impl Build {
    fn bin(&self, name: &str) -> PathBuf {
        self.dir.join(name)
    }
}

type Check = fn(&Build) -> Result<Row, String>;

/// Every check, by name (`--only NAME`), and whether it also runs with real-time priorities.
const CHECKS: &[(&str, Check, bool)] = &[
    ("flood-baseline", flood_baseline, true),
    ("flood-isolation", flood_isolation, true),
    ("flood-latency", flood_latency, true),
    ("bridge-memory", bridge_memory, false),
];

fn root() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .parent()
        .map(Path::to_path_buf)
        .unwrap_or_else(|| PathBuf::from(".."))
}

/// A child process stopped with SIGTERM (then SIGKILL) when dropped.
struct Proc {
    child: Child,
    name: String,
}

impl Proc {
    fn spawn(cmd: &mut Command, name: &str) -> Result<Proc, String> {
        let child = cmd
            .spawn()
            .map_err(|e| format!("cannot start {name} ({:?}): {e}", cmd.get_program()))?;
        Ok(Proc {
            child,
            name: name.to_string(),
        })
    }

    fn pid(&self) -> i32 {
        self.child.id() as i32
    }

    /// SIGTERM, then wait up to 5 s (SIGKILL after); the exit code (None: killed).
    fn stop(&mut self) -> Option<i32> {
        if let Ok(Some(s)) = self.child.try_wait() {
            return s.code();
        }
        // SAFETY: signalling our own child.
        unsafe {
            libc::kill(self.pid(), libc::SIGTERM);
        }
        let until = Instant::now() + Duration::from_secs(5);
        while Instant::now() < until {
            if let Ok(Some(s)) = self.child.try_wait() {
                return s.code();
            }
            std::thread::sleep(Duration::from_millis(20));
        }
        eprintln!("{} did not stop on SIGTERM: killed", self.name);
        let _ = self.child.kill();
        let _ = self.child.wait();
        None
    }
}

impl Drop for Proc {
    fn drop(&mut self) {
        self.stop();
    }
}

fn log_path(name: &str) -> PathBuf {
    std::env::temp_dir().join(format!(
        "reliability-live-{}-{name}.log",
        std::process::id()
    ))
}

/// `rollbase bridge --listen 127.0.0.1:0`, its stderr in a file; returns it and its port.
fn start_bridge(b: &Build, log: &Path) -> Result<(Proc, u16), String> {
    let file = std::fs::File::create(log).map_err(|e| format!("{}: {e}", log.display()))?;
    let bridge = Proc::spawn(
        with_fifo(&mut Command::new(b.bin("rollbase")), b.fifo.then_some(60))
            .args(["bridge", "--listen", "127.0.0.1:0"])
            .stdout(Stdio::null())
            .stderr(file),
        "rollbase bridge",
    )?;
    let until = Instant::now() + Duration::from_secs(10);
    while Instant::now() < until {
        let text = std::fs::read_to_string(log).unwrap_or_default();
        if let Some(rest) = text.split("listening on 127.0.0.1:").nth(1) {
            let port = rest
                .split(|c: char| !c.is_ascii_digit())
                .next()
                .and_then(|p| p.parse().ok())
                .ok_or_else(|| format!("no port in the bridge's line: {rest:.80}"))?;
            return Ok((bridge, port));
        }
        std::thread::sleep(Duration::from_millis(20));
    }
    Err(format!(
        "the bridge never said where it listens ({})",
        log.display()
    ))
}

/// Reads until `needle` has arrived (true), EOF or `within` (false).
fn read_until(s: &mut TcpStream, got: &mut String, needle: &str, within: Duration) -> bool {
    let until = Instant::now() + within;
    let mut buf = [0u8; 4096];
    while !got.contains(needle) && Instant::now() < until {
        match s.read(&mut buf) {
            Ok(0) => return got.contains(needle),
            Ok(n) => got.push_str(&String::from_utf8_lossy(&buf[..n])),
            Err(e)
                if matches!(
                    e.kind(),
                    std::io::ErrorKind::WouldBlock | std::io::ErrorKind::TimedOut
                ) => {}
            Err(_) => return false,
        }
    }
    got.contains(needle)
}

/// A raw-mode client on `ch`: `< hi >`, open, raw mode, `< echo >` answered.
fn join(port: u16, ch: &str) -> Result<TcpStream, String> {
    let mut s = TcpStream::connect(("127.0.0.1", port)).map_err(|e| format!("connect: {e}"))?;
    s.set_read_timeout(Some(Duration::from_millis(100)))
        .map_err(|e| e.to_string())?;
    let mut got = String::new();
    let t = Duration::from_secs(5);
    let mut step = |send: &str, want: &str| -> Result<(), String> {
        if !send.is_empty() {
            s.write_all(send.as_bytes())
                .map_err(|e| format!("write: {e}"))?;
        }
        if read_until(&mut s, &mut got, want, t) {
            Ok(())
        } else {
            Err(format!("channel {ch}: no {want:?} (got {got:.200})"))
        }
    };
    step("", "< hi >")?;
    step(&format!("< open {ch} >"), "< hi >< ok >")?;
    step("< rawmode >", "< ok >< ok >")?;
    step("< echo >", "< echo >")?;
    Ok(s)
}

/// 50 listeners that read everything on channel `flood` (one thread polls them all, so the
/// harness adds two busy threads to the machine, not 51) and one client that sends as fast
/// as the bridge takes it, until `stop` or `limit` (bounded in time and count: 50 million
/// frames). Returns the two threads; the flooder's returns the frames it wrote.
fn start_flood(
    port: u16,
    stop: &Arc<AtomicBool>,
    limit: Duration,
) -> Result<(std::thread::JoinHandle<u64>, std::thread::JoinHandle<u64>), String> {
    let mut socks = Vec::new();
    for _ in 0..50 {
        let s = join(port, "flood")?;
        s.set_nonblocking(true).map_err(|e| e.to_string())?;
        socks.push(s);
    }
    let listeners = {
        let stop = stop.clone();
        std::thread::spawn(move || {
            use std::os::fd::AsRawFd;
            let mut fds: Vec<libc::pollfd> = socks
                .iter()
                .map(|s| libc::pollfd {
                    fd: s.as_raw_fd(),
                    events: libc::POLLIN,
                    revents: 0,
                })
                .collect();
            let mut buf = vec![0u8; 65536];
            let mut bytes = 0u64;
            let t0 = Instant::now();
            while !stop.load(Ordering::Relaxed) && t0.elapsed() < limit + Duration::from_secs(5) {
                // SAFETY: fds is a valid array of fds.len() pollfd structures.
                let n = unsafe { libc::poll(fds.as_mut_ptr(), fds.len() as libc::nfds_t, 100) };
                if n <= 0 {
                    continue;
                }
                for (pfd, s) in fds.iter_mut().zip(socks.iter_mut()) {
                    if pfd.revents != 0 {
                        while let Ok(n) = s.read(&mut buf) {
                            if n == 0 {
                                pfd.fd = -1; // closed: poll ignores negative fds
                                break;
                            }
                            bytes += n as u64;
                        }
                    }
                }
            }
            bytes
        })
    };
    let mut s = join(port, "flood")?;
    s.set_write_timeout(Some(Duration::from_millis(50)))
        .map_err(|e| e.to_string())?;
    let stop = stop.clone();
    let flooder = std::thread::spawn(move || {
        let chunk = "< send 123 8 00 11 22 33 44 55 66 77 >".repeat(200);
        let t0 = Instant::now();
        let mut frames = 0u64;
        while !stop.load(Ordering::Relaxed) && t0.elapsed() < limit && frames < 50_000_000 {
            let mut off = 0;
            while off < chunk.len() && !stop.load(Ordering::Relaxed) && t0.elapsed() < limit {
                // A write timeout (the bridge holding the flooder back) just retries.
                if let Ok(n) = s.write(&chunk.as_bytes()[off..]) {
                    off += n;
                }
            }
            frames += 200;
        }
        frames
    });
    Ok((listeners, flooder))
}

/// CPU seconds (user + system) a process has used so far.
fn cpu_seconds(pid: i32) -> Option<f64> {
    let stat = std::fs::read_to_string(format!("/proc/{pid}/stat")).ok()?;
    // Fields after the command name in parentheses; utime and stime are fields 14 and 15.
    let after = stat.rsplit_once(')')?.1;
    let f: Vec<&str> = after.split_whitespace().collect();
    let ticks: f64 = f.get(11)?.parse::<f64>().ok()? + f.get(12)?.parse::<f64>().ok()?;
    // SAFETY: sysconf has no preconditions.
    let hz = unsafe { libc::sysconf(libc::_SC_CLK_TCK) } as f64;
    Some(ticks / hz.max(1.0))
}

fn rss_kb(pid: i32) -> Option<u64> {
    let status = std::fs::read_to_string(format!("/proc/{pid}/status")).ok()?;
    status
        .lines()
        .find(|l| l.starts_with("VmRSS:"))?
        .split_whitespace()
        .nth(1)?
        .parse()
        .ok()
}

/// The 1-minute load average (other processes on the machine disturb real-time figures).
fn loadavg() -> String {
    std::fs::read_to_string("/proc/loadavg")
        .ok()
        .and_then(|s| s.split_whitespace().next().map(str::to_string))
        .unwrap_or_else(|| "?".into())
}

/// SCHED_FIFO for the calling thread (as the controller has), if permitted.
fn fifo(prio: i32) -> bool {
    let p = libc::sched_param {
        sched_priority: prio,
    };
    // SAFETY: sets the calling thread's policy; the parameter is valid.
    unsafe { libc::sched_setscheduler(0, libc::SCHED_FIFO, &p) == 0 }
}

/// Request/answer round trips on channel `probe` (one request every 4 ms for 10 s, answered
/// at once by another client; both at SCHED_FIFO 70 when permitted, so that the figure is
/// the bridge's) while channel `flood` floods: what one channel's flood adds to another's
/// latency. 16 ms (4 cycles) without feedback is a stale-feedback fault.
fn flood_latency(b: &Build) -> Result<Row, String> {
    let load = loadavg();
    let blog = log_path("bridge-latency");
    let (mut bridge, port) = start_bridge(b, &blog)?;
    let url = format!("socketcand://127.0.0.1:{port}/probe");
    let open = |what: &str| SocketcandBus::open(&url).map_err(|e| format!("{what}: {e}"));
    let mut req = open("requester")?;
    let mut resp = open("responder")?;
    // Until the bridge forwards between them.
    let hello = CanFrame::new(0x7FF, &[0xEE]).map_err(|e| e.to_string())?;
    let until = Instant::now() + Duration::from_secs(5);
    loop {
        req.send(&hello).map_err(|e| e.to_string())?;
        if let Ok(Some(f)) = resp.recv_until(Instant::now() + Duration::from_millis(10)) {
            if f.frame == hello {
                break;
            }
        }
        if Instant::now() > until {
            return Err("the probe clients never saw each other".into());
        }
    }
    while let Ok(Some(_)) = resp.recv_until(Instant::now() + Duration::from_millis(20)) {}
    let stop = Arc::new(AtomicBool::new(false));
    let (listeners, flooder) = start_flood(port, &stop, Duration::from_secs(20))?;
    std::thread::sleep(Duration::from_millis(500));
    let responder = {
        let stop = stop.clone();
        std::thread::spawn(move || {
            fifo(70);
            while !stop.load(Ordering::Relaxed) {
                if let Ok(Some(f)) = resp.recv_until(Instant::now() + Duration::from_millis(20)) {
                    if f.frame.id() == 0x200 {
                        if let Ok(a) = CanFrame::new(0x201, f.frame.data()) {
                            let _ = resp.send(&a);
                        }
                    }
                }
            }
        })
    };
    let rt = fifo(70);
    let mut rtt_us: Vec<u64> = Vec::new();
    let mut sent = 0u32;
    let t0 = Instant::now();
    while t0.elapsed() < Duration::from_secs(10) {
        sent += 1;
        let q = CanFrame::new(0x200, &sent.to_le_bytes()).map_err(|e| e.to_string())?;
        let at = Instant::now();
        if req.send(&q).is_ok() {
            while let Ok(Some(f)) = req.recv_until(at + Duration::from_secs(1)) {
                if f.frame.id() == 0x201 && f.frame.data() == sent.to_le_bytes() {
                    rtt_us.push(at.elapsed().as_micros() as u64);
                    break;
                }
            }
        }
        if let Some(d) = (at + Duration::from_millis(4)).checked_duration_since(Instant::now()) {
            std::thread::sleep(d);
        }
    }
    if rt {
        let p = libc::sched_param { sched_priority: 0 };
        // SAFETY: back to normal scheduling for this thread.
        unsafe {
            libc::sched_setscheduler(0, libc::SCHED_OTHER, &p);
        }
    }
    stop.store(true, Ordering::Relaxed);
    let flood_frames = flooder.join().unwrap_or(0);
    let _ = listeners.join();
    let _ = responder.join();
    bridge.stop();
    let _ = std::fs::remove_file(&blog);
    let answered = rtt_us.len();
    rtt_us.sort_unstable();
    let pct = |q: f64| -> f64 {
        if rtt_us.is_empty() {
            return f64::NAN;
        }
        let i = ((rtt_us.len() - 1) as f64 * q).round() as usize;
        rtt_us[i.min(rtt_us.len() - 1)] as f64 / 1000.0
    };
    let over16 = rtt_us.iter().filter(|&&u| u > 16_000).count();
    let max = rtt_us.last().copied().unwrap_or(0) as f64 / 1000.0;
    Ok(Row {
        check: "channel flood: round trips on another channel",
        setup: format!(
            "{}: one request every 4 ms for 10 s on channel `probe`, answered at once by a second client ({}), while channel `flood` carries one client sending as fast as the bridge takes it ({flood_frames} frames written) to 50 listeners; load average before {load}",
            b.label(),
            if rt { "both at SCHED_FIFO 70" } else { "normal priority: SCHED_FIFO not permitted" },
        ),
        measured: format!(
            "{answered}/{sent} answered; round trip p50 {:.2} ms, p99 {:.2} ms, max {max:.2} ms; {over16} over 16 ms (4 cycles: a stale-feedback fault for a controller)",
            pct(0.5),
            pct(0.99),
        ),
        pass: answered == sent as usize && over16 == 0,
    })
}

/// The outcome of one real-time run over the bridge.
struct RtRun {
    cycles: u64,
    deadline_misses: u64,
    final_state: String,
    fault: Option<String>,
    bridge_cpu_pct: f64,
    flood_frames: u64,
    bridge_totals: String,
}

const RUN_S: u64 = 10;

/// `rollbase-sim` and a 10 s real-time `rollbase run` of scenario seed000 on channel vcan0,
/// with or without a flood on channel `flood`.
fn realtime_run(b: &Build, flood: bool) -> Result<RtRun, String> {
    let tag = if flood { "flood" } else { "quiet" };
    let blog = log_path(&format!("bridge-{tag}"));
    let (mut bridge, port) = start_bridge(b, &blog)?;
    let url = format!("socketcand://127.0.0.1:{port}/vcan0");
    let slog = log_path(&format!("sim-{tag}"));
    let sim_log = std::fs::File::create(&slog).map_err(|e| e.to_string())?;
    let mut sim = Proc::spawn(
        with_fifo(
            &mut Command::new(b.bin("rollbase-sim")),
            b.fifo.then_some(81),
        )
        .args(["--bus", &url, "--start", "scenario:seed000"])
        .stdout(Stdio::null())
        .stderr(sim_log),
        "rollbase-sim",
    )?;
    std::thread::sleep(Duration::from_millis(500));
    let stop = Arc::new(AtomicBool::new(false));
    let limit = Duration::from_secs(RUN_S + 10);
    let flood_threads = if flood {
        Some(start_flood(port, &stop, limit)?)
    } else {
        None
    };
    std::thread::sleep(Duration::from_millis(500));
    let cpu0 = cpu_seconds(bridge.pid()).unwrap_or(0.0);
    let t0 = Instant::now();
    let out = Command::new(b.bin("rollbase"))
        .args([
            "run",
            "--bus",
            &url,
            "--trajectory",
            "scenario:seed000",
            "--duration",
            &RUN_S.to_string(),
            "--json",
        ])
        .stdin(Stdio::null())
        .output()
        .map_err(|e| format!("cannot start rollbase run: {e}"))?;
    let wall = t0.elapsed().as_secs_f64();
    let cpu = cpu_seconds(bridge.pid()).unwrap_or(cpu0) - cpu0;
    stop.store(true, Ordering::Relaxed);
    let mut flood_frames = 0;
    if let Some((listeners, flooder)) = flood_threads {
        flood_frames = flooder.join().unwrap_or(0);
        let _ = listeners.join();
    }
    sim.stop();
    let code = bridge.stop();
    let log = std::fs::read_to_string(&blog).unwrap_or_default();
    let bridge_totals = log
        .lines()
        .rev()
        .find_map(|l| l.split("stopped: ").nth(1))
        .map(|s| s.to_string())
        .unwrap_or_else(|| format!("no totals (exit {code:?})"));
    let _ = std::fs::remove_file(&blog);
    let _ = std::fs::remove_file(&slog);
    let stdout = String::from_utf8_lossy(&out.stdout);
    let v: serde_json::Value = serde_json::from_str(stdout.trim()).map_err(|e| {
        format!(
            "rollbase run printed no JSON summary ({e}): {}",
            String::from_utf8_lossy(&out.stderr)
        )
    })?;
    Ok(RtRun {
        cycles: v["cycles"].as_u64().unwrap_or(0),
        deadline_misses: v["deadline_misses"].as_u64().unwrap_or(0),
        final_state: v["supervisor_final_state"]
            .as_str()
            .unwrap_or("?")
            .to_string(),
        fault: v["fault_reason"].as_str().map(str::to_string),
        bridge_cpu_pct: 100.0 * cpu / wall.max(1e-9),
        flood_frames,
        bridge_totals,
    })
}

/// Real-time runs per row: a fault in any of them fails the row.
const RUNS: usize = 3;

fn rt_row(check: &'static str, b: &Build, flood: bool) -> Result<Row, String> {
    let load = loadavg();
    let mut runs = Vec::new();
    for _ in 0..RUNS {
        runs.push(realtime_run(b, flood)?);
    }
    let stale = |r: &RtRun| r.fault.as_deref().is_some_and(|f| f.contains("stale"));
    // 250 Hz for 10 s, less the start-up the runtime needs.
    let clean = |r: &RtRun| r.fault.is_none() && r.final_state == "stopped" && r.cycles >= 2400;
    let n_clean = runs.iter().filter(|r| clean(r)).count();
    let setup = format!(
        "{}: {RUNS} × `rollbase run --bus socketcand://127.0.0.1:PORT/vcan0 --trajectory scenario:seed000 --duration {RUN_S}` with `rollbase-sim --start scenario:seed000` on channel vcan0{}",
        b.label(),
        if flood {
            "; meanwhile channel `flood` carries one client sending as fast as the bridge takes it to 50 listeners that read everything"
        } else {
            "; nothing else on the bridge"
        }
    ) + &format!("; load average before {load}");
    let mut measured = format!("{n_clean}/{RUNS} runs clean");
    for (i, r) in runs.iter().enumerate() {
        let _ = write!(
            measured,
            "; run {}: {} cycles, {} deadline misses, {} stale-feedback fault{}, final state {}{}, bridge CPU {:.0} %{}",
            i + 1,
            r.cycles,
            r.deadline_misses,
            u8::from(stale(r)),
            if stale(r) { "" } else { "s" },
            r.final_state,
            r.fault.as_deref().map(|f| format!(" ({f})")).unwrap_or_default(),
            r.bridge_cpu_pct,
            if flood {
                format!(", {} flood frames written", r.flood_frames)
            } else {
                String::new()
            },
        );
    }
    if let Some(last) = runs.last() {
        let _ = write!(
            measured,
            "; bridge totals of run {RUNS}: {}",
            last.bridge_totals
        );
    }
    Ok(Row {
        check,
        setup,
        measured,
        pass: n_clean == RUNS,
    })
}

fn flood_baseline(b: &Build) -> Result<Row, String> {
    rt_row("real-time run over the bridge, no flood", b, false)
}

fn flood_isolation(b: &Build) -> Result<Row, String> {
    rt_row("channel flood isolation", b, true)
}

/// 10 000 short connections, each opening a channel of its own name (at most 50 open at
/// once), then all closed: the bridge's RSS before, with the last 50 still open, and after.
fn bridge_memory(b: &Build) -> Result<Row, String> {
    const OPENS: usize = 10_000;
    const WINDOW: usize = 50;
    let blog = log_path("bridge-memory");
    let (mut bridge, port) = start_bridge(b, &blog)?;
    let pid = bridge.pid();
    std::thread::sleep(Duration::from_millis(200));
    let before = rss_kb(pid).ok_or("no VmRSS for the bridge")?;
    let t0 = Instant::now();
    let mut open: std::collections::VecDeque<TcpStream> = std::collections::VecDeque::new();
    let mut refused = 0usize;
    let close = |mut s: TcpStream| {
        // Half-close and wait for the bridge's close: it has processed the leave.
        let _ = s.shutdown(Shutdown::Write);
        let mut got = String::new();
        let _ = read_until(&mut s, &mut got, "\u{0}never", Duration::from_secs(5));
    };
    for i in 0..OPENS {
        if t0.elapsed() > Duration::from_secs(300) {
            return Err(format!("10 000 opens took over 300 s (stopped at {i})"));
        }
        match join(port, &format!("mem{i}")) {
            Ok(s) => open.push_back(s),
            Err(_) => refused += 1,
        }
        if open.len() >= WINDOW {
            if let Some(s) = open.pop_front() {
                close(s);
            }
        }
    }
    let with_clients = rss_kb(pid).unwrap_or(0);
    let took = t0.elapsed().as_secs_f64();
    for s in open.drain(..) {
        close(s);
    }
    std::thread::sleep(Duration::from_millis(500));
    let after = rss_kb(pid).unwrap_or(0);
    let code = bridge.stop();
    let _ = std::fs::remove_file(&blog);
    let grew = after.saturating_sub(before);
    let pass = refused == 0 && grew < 16 * 1024 && code == Some(0);
    Ok(Row {
        check: "bridge memory over 10 000 channel opens",
        setup: format!(
            "{}: {OPENS} short connections, each opening a new channel name (at most {WINDOW} open at once), in {took:.1} s; RSS (VmRSS) of `rollbase bridge`",
            b.label
        ),
        measured: format!(
            "before {:.1} MB, with the last {WINDOW} clients connected {:.1} MB, after every client left {:.1} MB (+{:.1} MB); {refused} opens failed; exit code after SIGTERM {}",
            before as f64 / 1024.0,
            with_clients as f64 / 1024.0,
            after as f64 / 1024.0,
            grew as f64 / 1024.0,
            code.map(|c| c.to_string()).unwrap_or_else(|| "none (killed by a signal)".into()),
        ),
        pass,
    })
}

// ---------------------------------------------------------------------------------------------
// Real-time runs under load (issue 27): `--load [--load-secs S]`
// ---------------------------------------------------------------------------------------------

/// What the long runs do to the machine: 2 × the cores busy loops at normal priority.
fn hogs(stop: &Arc<AtomicBool>) -> Vec<std::thread::JoinHandle<()>> {
    let n = 2 * std::thread::available_parallelism().map_or(2, |n| n.get());
    (0..n)
        .map(|_| {
            let stop = stop.clone();
            std::thread::spawn(move || {
                let mut x = 0u64;
                while !stop.load(Ordering::Relaxed) {
                    for _ in 0..100_000 {
                        x = std::hint::black_box(
                            x.wrapping_mul(6364136223846793005).wrapping_add(1),
                        );
                    }
                }
            })
        })
        .collect()
}

/// Whether this process's network namespace has only loopback (the DDS rule).
fn only_loopback() -> bool {
    std::fs::read_to_string("/proc/net/dev").is_ok_and(|t| {
        t.lines()
            .skip(2)
            .filter_map(|l| l.split(':').next())
            .all(|n| n.trim() == "lo")
    })
}

/// The three long runs: the live demo, the live demo as a ROS 2 node, `drive` with
/// `rollbase-sim` over the bridge.
#[derive(Clone, Copy, PartialEq)]
enum LoadKind {
    Demo,
    Ros2,
    Drive,
}

/// The DDS domain of the ROS 2 run (in its own network namespace anyway).
const LOAD_DOMAIN: u16 = 57;

/// A live run of `secs` under the load: commands 3 s on (20 Hz, 0.3 m/s forward then back,
/// 0.2 rad/s), 2 s off (the command timeout stops the platform every 5 s), re-armed on stdin
/// after each fault; then SIGTERM. Counts the faults (the service's `fault:` log lines) and
/// reads the summary.
fn load_run(b: &Build, kind: LoadKind, secs: u64) -> Result<Row, String> {
    if kind == LoadKind::Ros2 && !only_loopback() {
        return Err("the ROS 2 run needs a private network namespace with only loopback: unshare -n sh -c 'ip link set lo up; …'".into());
    }
    let tag = match kind {
        LoadKind::Demo => "demo",
        LoadKind::Ros2 => "ros2",
        LoadKind::Drive => "drive",
    };
    let stop = Arc::new(AtomicBool::new(false));
    let load_threads = hogs(&stop);
    std::thread::sleep(Duration::from_secs(2));
    let load = loadavg();
    let mut extra: Vec<Proc> = Vec::new();
    let mut cmd = Command::new(b.bin("rollbase"));
    let what = match kind {
        LoadKind::Demo => {
            cmd.args(["demo", "--commands", "-", "--json"]);
            "`rollbase demo --commands -` (simulator in-process)".to_string()
        }
        LoadKind::Ros2 => {
            cmd.args(["demo", "--ros2", "--commands", "-", "--json"])
                .env("ROS_DOMAIN_ID", LOAD_DOMAIN.to_string());
            "`rollbase demo --ros2 --commands -` (cmd_vel from a ROS 2 peer, re-arm on stdin)"
                .to_string()
        }
        LoadKind::Drive => {
            let blog = log_path("load-bridge");
            let (bridge, port) = start_bridge(
                &Build {
                    dir: b.dir.clone(),
                    label: b.label.clone(),
                    current: b.current,
                    fifo: false,
                },
                &blog,
            )?;
            extra.push(bridge);
            let url = format!("socketcand://127.0.0.1:{port}/vcan0");
            let slog = std::fs::File::create(log_path("load-sim")).map_err(|e| e.to_string())?;
            extra.push(Proc::spawn(
                Command::new(b.bin("rollbase-sim"))
                    .args(["--bus", &url])
                    .stdout(Stdio::null())
                    .stderr(slog),
                "rollbase-sim",
            )?);
            std::thread::sleep(Duration::from_millis(500));
            cmd.args(["drive", "--bus", &url, "--commands", "-", "--json"]);
            "`rollbase drive --commands -` with `rollbase bridge` and `rollbase-sim` (each at its own default priority)".to_string()
        }
    };
    let elog = log_path(&format!("load-{tag}"));
    let olog = log_path(&format!("load-{tag}-out"));
    let mut p = Proc::spawn(
        cmd.env("RUST_LOG", "info")
            .stdin(Stdio::piped())
            .stdout(std::fs::File::create(&olog).map_err(|e| e.to_string())?)
            .stderr(std::fs::File::create(&elog).map_err(|e| e.to_string())?),
        tag,
    )?;
    let mut stdin = p.child.stdin.take().ok_or("no stdin")?;
    let until = Instant::now() + Duration::from_secs(30);
    while !std::fs::read_to_string(&elog)
        .unwrap_or_default()
        .contains("state: tracking")
    {
        if Instant::now() > until {
            return Err(format!(
                "{tag} never tracked: {}",
                std::fs::read_to_string(&elog).unwrap_or_default()
            ));
        }
        std::thread::sleep(Duration::from_millis(50));
    }
    let ros = if kind == LoadKind::Ros2 {
        use rollbase::ros2::dds::{qos, Dds};
        use rollbase::ros2::msg::Twist;
        let peer = Dds::new(LOAD_DOMAIN, &[]).map_err(|e| format!("DDS participant: {e}"))?;
        let pb = peer
            .writer::<Twist>("/cmd_vel", qos::ros_default())
            .map_err(|e| e.to_string())?;
        Some((peer, pb))
    } else {
        None
    };
    let t0 = Instant::now();
    let mut faults_seen = 0usize;
    let mut k = 0u64;
    while t0.elapsed() < Duration::from_secs(secs) {
        let t = t0.elapsed().as_secs_f64();
        if t % 5.0 < 3.0 {
            let vx = if (t / 5.0) as u64 % 2 == 0 { 0.3 } else { -0.3 };
            match &ros {
                Some((_, pb)) => {
                    let mut tw = rollbase::ros2::msg::Twist::default();
                    tw.linear.x = vx;
                    tw.angular.z = 0.2;
                    let _ = pb.write(tw, None);
                }
                None => {
                    let _ = writeln!(stdin, "{{\"vx\": {vx}, \"vy\": 0.0, \"omega\": 0.2}}");
                }
            }
        }
        k += 1;
        if k % 10 == 0 {
            let faults = std::fs::read_to_string(&elog)
                .unwrap_or_default()
                .matches(" fault: ")
                .count();
            if faults > faults_seen {
                faults_seen = faults;
                let _ = writeln!(stdin, "{{\"rearm\": true}}");
            }
        }
        std::thread::sleep(Duration::from_millis(50));
    }
    drop(stdin);
    let code = p.stop();
    for mut e in extra.drain(..).rev() {
        e.stop();
    }
    drop(ros);
    stop.store(true, Ordering::Relaxed);
    for h in load_threads {
        let _ = h.join();
    }
    let err = std::fs::read_to_string(&elog).unwrap_or_default();
    let out = std::fs::read_to_string(&olog).unwrap_or_default();
    let _ = std::fs::remove_file(&elog);
    let _ = std::fs::remove_file(&olog);
    let _ = std::fs::remove_file(log_path("load-bridge"));
    let _ = std::fs::remove_file(log_path("load-sim"));
    let v: serde_json::Value = out
        .lines()
        .rev()
        .find_map(|l| serde_json::from_str(l).ok())
        .ok_or_else(|| {
            format!(
                "no JSON summary (exit {code:?}): {}",
                err.lines().rev().take(5).collect::<Vec<_>>().join(" / ")
            )
        })?;
    let faults: Vec<&str> = err
        .lines()
        .filter_map(|l| l.split(" fault: ").nth(1))
        .map(|r| r.split("; controlled stop").next().unwrap_or(r))
        .collect();
    let mut reasons: Vec<String> = Vec::new();
    for f in &faults {
        let short: String = f.split(':').next().unwrap_or(f).to_string();
        if !reasons.contains(&short) {
            reasons.push(short);
        }
    }
    Ok(Row {
        check: "real-time run under a CPU load of 2× the cores",
        setup: format!(
            "{}: {what} for {secs} s, as root, while {} busy loops run at normal priority; commands 3 s on (20 Hz), 2 s off (a command-timeout stop every 5 s), re-armed after a fault; load average at the start {load}",
            b.label,
            2 * std::thread::available_parallelism().map_or(2, |n| n.get()),
        ),
        measured: format!(
            "{} cycles, {} deadline misses, {} fault(s){}, {} command timeouts; final state {}; exit code after SIGTERM {}",
            v["cycles"],
            v["deadline_misses"],
            faults.len(),
            if reasons.is_empty() { String::new() } else { format!(" ({})", reasons.join(", ")) },
            v["command_timeouts"],
            v["supervisor_final_state"].as_str().unwrap_or("?"),
            code.map(|c| c.to_string()).unwrap_or_else(|| "none (killed)".into()),
        ),
        pass: faults.is_empty() && code == Some(0),
    })
}

/// What the machine does to any SCHED_FIFO thread under the same load, without rollbase: a
/// timer loop at priority 80 with locked memory, woken at the cycle's two instants (every
/// 4 ms and 2 ms after), measuring how late each wake-up is.
fn load_timer(secs: u64) -> Row {
    let stop = Arc::new(AtomicBool::new(false));
    let load_threads = hogs(&stop);
    std::thread::sleep(Duration::from_secs(2));
    let load = loadavg();
    let lateness = std::thread::spawn(move || {
        let rt = fifo(80);
        // SAFETY: mlockall has no memory-safety preconditions.
        unsafe {
            libc::mlockall(libc::MCL_CURRENT | libc::MCL_FUTURE);
        }
        let now = || {
            let mut ts = libc::timespec {
                tv_sec: 0,
                tv_nsec: 0,
            };
            // SAFETY: clock_gettime writes into the timespec.
            unsafe { libc::clock_gettime(libc::CLOCK_MONOTONIC, &mut ts) };
            ts.tv_sec as i128 * 1_000_000_000 + ts.tv_nsec as i128
        };
        let sleep_until = |ns: i128| {
            let ts = libc::timespec {
                tv_sec: (ns / 1_000_000_000) as libc::time_t,
                tv_nsec: (ns % 1_000_000_000) as libc::c_long,
            };
            // SAFETY: an absolute sleep with a valid timespec.
            while unsafe {
                libc::clock_nanosleep(
                    libc::CLOCK_MONOTONIC,
                    libc::TIMER_ABSTIME,
                    &ts,
                    std::ptr::null_mut(),
                )
            } == libc::EINTR
            {}
        };
        let period = 4_000_000i128;
        let mut d = now() + period;
        let end = d + secs as i128 * 1_000_000_000;
        let mut late: Vec<i64> = Vec::with_capacity((secs as usize + 1) * 500);
        while d < end {
            for off in [0, 2_000_000] {
                sleep_until(d + off);
                late.push(((now() - d - off) / 1000) as i64);
            }
            d += period;
            let n = now();
            if n > d + period {
                d += ((n - d) / period) * period;
            }
        }
        (rt, late)
    });
    let (rt, mut late) = lateness.join().unwrap_or((false, Vec::new()));
    stop.store(true, Ordering::Relaxed);
    for h in load_threads {
        let _ = h.join();
    }
    late.sort_unstable();
    let q = |p: f64| {
        late.get(((late.len().max(1) - 1) as f64 * p) as usize)
            .copied()
            .unwrap_or(0)
    };
    let over = |ms: i64| late.iter().filter(|&&x| x > ms * 1000).count();
    Row {
        check: "SCHED_FIFO timer loop under the same load, without rollbase (the machine's share)",
        setup: format!(
            "a thread at {} with locked memory sleeping to absolute deadlines at the cycle's two instants (every 4 ms, and 2 ms after) for {secs} s while {} busy loops run at normal priority; load average at the start {load}",
            if rt { "SCHED_FIFO 80" } else { "normal priority (SCHED_FIFO not permitted)" },
            2 * std::thread::available_parallelism().map_or(2, |n| n.get()),
        ),
        measured: format!(
            "{} wake-ups; lateness p50 {} µs, p99 {} µs, p99.9 {} µs, max {:.1} ms; later than 1 ms: {}, 4 ms: {}, 16 ms: {}",
            late.len(),
            q(0.5),
            q(0.99),
            q(0.999),
            late.last().copied().unwrap_or(0) as f64 / 1000.0,
            over(1),
            over(4),
            over(16),
        ),
        pass: true,
    }
}

/// Markers of the load section in docs/reliability-live.md (rewritten by `--load` alone).
const LOAD_BEGIN: &str =
    "<!-- load-runs: generated by `reliability-live --load`; edit nothing between the markers -->";
const LOAD_END: &str = "<!-- /load-runs -->";

/// `--load`: the timer baseline, then each build's three long runs; replaces the section
/// between the markers (or appends it) and keeps the rest of the file.
fn run_load(builds: &[Build], secs: u64, write: bool) -> usize {
    let mut md =
        format!("{LOAD_BEGIN}\n\n| check | setup | measured | result |\n|---|---|---|---|\n");
    let mut failed = 0;
    let mut emit = |row: Row, current: bool, md: &mut String| {
        if !row.pass && current {
            failed += 1;
        }
        let line = format!(
            "| {} | {} | {} | {} |",
            cell(row.check),
            cell(&row.setup),
            cell(&row.measured),
            if row.pass { "pass" } else { "**FAIL**" }
        );
        println!("{line}");
        let _ = writeln!(md, "{line}");
    };
    eprintln!("running the timer baseline ({} s)…", secs.min(120));
    emit(load_timer(secs.min(120)), false, &mut md);
    for b in builds.iter().filter(|b| !b.fifo) {
        for kind in [LoadKind::Demo, LoadKind::Ros2, LoadKind::Drive] {
            eprintln!("running a {secs} s load run ({})…", b.label);
            let row = load_run(b, kind, secs).unwrap_or_else(|e| Row {
                check: "real-time run under a CPU load of 2× the cores",
                setup: b.label.clone(),
                measured: format!("could not run: {e}"),
                pass: false,
            });
            emit(row, b.current, &mut md);
        }
    }
    md.push('\n');
    md.push_str(LOAD_END);
    if write {
        let path = root().join("docs/reliability-live.md");
        let old = std::fs::read_to_string(&path).unwrap_or_default();
        let new = match (old.find(LOAD_BEGIN), old.find(LOAD_END)) {
            (Some(a), Some(z)) if z > a => {
                format!("{}{md}{}", &old[..a], &old[z + LOAD_END.len()..])
            }
            _ => format!(
                "{}\n## Real-time runs under load (issue 27)\n\n{md}\n",
                old.trim_end()
            ),
        };
        if let Err(e) = std::fs::write(&path, new) {
            eprintln!("cannot write {}: {e}", path.display());
            return failed + 1;
        }
        eprintln!("wrote the load section of {}", path.display());
    }
    failed
}

fn cell(s: &str) -> String {
    s.replace('|', "\\|").replace('\n', " ")
}

fn main() {
    let mut builds = vec![Build {
        dir: root().join("target/release"),
        label: "this build".into(),
        current: true,
        fifo: false,
    }];
    let mut only: Option<String> = None;
    let mut write = true;
    let mut load: Option<u64> = None;
    let mut args = std::env::args().skip(1);
    while let Some(a) = args.next() {
        match a.as_str() {
            "--no-write" => write = false,
            "--load" => {
                load.get_or_insert(600);
            }
            "--load-secs" => match args.next().and_then(|v| v.parse().ok()) {
                Some(v) if v > 0 => load = Some(v),
                _ => {
                    eprintln!(
                        "--load-secs S: the length of each load run in seconds (default 600)"
                    );
                    std::process::exit(2);
                }
            },
            "--only" => only = args.next(),
            "--compare" => match args.next().as_deref().and_then(|v| v.split_once('=')) {
                Some((dir, label)) => builds.push(Build {
                    dir: PathBuf::from(dir),
                    label: label.to_string(),
                    current: false,
                    fifo: false,
                }),
                None => {
                    eprintln!("--compare DIR=LABEL: a directory with rollbase and rollbase-sim, and a label for its rows");
                    std::process::exit(2);
                }
            },
            "--bins" => match args.next() {
                Some(d) => builds[0].dir = PathBuf::from(d),
                None => {
                    eprintln!("--bins DIR: the directory with rollbase and rollbase-sim");
                    std::process::exit(2);
                }
            },
            other => {
                eprintln!("unknown argument `{other}`: use --only NAME, --compare DIR=LABEL, --bins DIR, --no-write; checks: {}",
                    CHECKS.iter().map(|c| c.0).collect::<Vec<_>>().join(", "));
                std::process::exit(2);
            }
        }
    }
    if let Some(o) = &only {
        if !CHECKS.iter().any(|c| c.0 == o) {
            eprintln!(
                "--only {o}: no such check; checks: {}",
                CHECKS.iter().map(|c| c.0).collect::<Vec<_>>().join(", ")
            );
            std::process::exit(2);
        }
    }
    // Every build also with real-time priorities (for the checks that take them), right
    // after its normal-priority rows.
    let builds: Vec<Build> = builds
        .into_iter()
        .flat_map(|b| {
            let rt = Build {
                dir: b.dir.clone(),
                label: b.label.clone(),
                current: b.current,
                fifo: true,
            };
            [b, rt]
        })
        .collect();
    for b in &builds {
        for bin in ["rollbase", "rollbase-sim"] {
            if !b.bin(bin).is_file() {
                eprintln!(
                    "{} not found: build it first (cargo build --release -p rollbase -p rollbase-vcan-sim)",
                    b.bin(bin).display()
                );
                std::process::exit(2);
            }
        }
    }
    if let Some(secs) = load {
        let failed = run_load(&builds, secs, write);
        if failed > 0 {
            eprintln!("{failed} load run(s) of this build failed");
            std::process::exit(1);
        }
        return;
    }
    let mut md = String::from(
        "# rollbase reliability: process-level checks\n\n\
         Generated by `cargo run --release -p rollbase-tests --bin reliability-live` after\n\
         `cargo build --release -p rollbase -p rollbase-vcan-sim` (do not edit by hand; rows of\n\
         other builds come from `--compare DIR=LABEL`). The real binaries run as separate\n\
         processes on loopback, on the machine that generated this file (2 cores, shared with\n\
         other work: the 1-minute load average before each check is given). The real-time checks\n\
         run each build twice: at normal priority, as started by hand, and with the bridge and\n\
         the simulator at SCHED_FIFO 60 and 81 (what `chrt -f` does; the controller runs at\n\
         SCHED_FIFO 80 by itself), which separates what the bridge does from what the machine's\n\
         other load does to processes at normal priority.\n\n\
         | check | setup | measured | result |\n|---|---|---|---|\n",
    );
    let mut failed = 0;
    for (name, check, rt) in CHECKS {
        if only.as_deref().is_some_and(|o| o != *name) {
            continue;
        }
        for b in builds.iter().filter(|b| *rt || !b.fifo) {
            eprintln!("running {name} ({})…", b.label);
            let row = check(b).unwrap_or_else(|e| Row {
                check: name,
                setup: b.label.clone(),
                measured: format!("could not run: {e}"),
                pass: false,
            });
            if !row.pass && b.current {
                failed += 1;
            }
            let line = format!(
                "| {} | {} | {} | {} |",
                cell(row.check),
                cell(&row.setup),
                cell(&row.measured),
                if row.pass { "pass" } else { "**FAIL**" }
            );
            println!("{line}");
            let _ = writeln!(md, "{line}");
        }
    }
    if write {
        let path = root().join("docs/reliability-live.md");
        if let Err(e) = std::fs::write(&path, &md) {
            eprintln!("cannot write {}: {e}", path.display());
            std::process::exit(1);
        }
        eprintln!("wrote {}", path.display());
    }
    if failed > 0 {
        eprintln!("{failed} check(s) of this build failed");
        std::process::exit(1);
    }
}
