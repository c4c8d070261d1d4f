//! `ros2-perf`: the ROS 2 node's command latency and the cost of `rollbase drive --ros2`,
//! written into the ROS 2 section of `docs/performance.md`.
//!
//! DDS discovery multicasts, so this program refuses to run outside a network namespace
//! whose only interface is loopback:
//!
//! ```text
//! cargo build --release -p rollbase -p rollbase-vcan-sim -p rollbase-tests --bins
//! unshare -n sh -c 'ip link set lo up && target/release/ros2-perf [--out docs/performance.md]
//!     [--commands 600] [--seconds 30]'
//! ```
//!
//! **Latency** (in this process, the real node and the real cycle): a second DDS participant
//! publishes `geometry_msgs/Twist` on `/cmd_vel` (each with a distinct `linear.x`, at a period
//! that is not a multiple of the cycle's, so arrivals fall at every phase of the cycle); the
//! node hands each one to the command port; the cycle runs in real time on the wall-clock
//! in-process bus with the simulator on its own thread. Measured per command:
//! - *arrival*: when the node passed it to the command port (a forwarding thread between the
//!   node and the cycle's queue stamps it; it adds one channel hop, microseconds);
//! - *first SETPOINT*: when the first SETPOINT of the cycle that took the command (the
//!   cycle's records list the commands it took) was handed to the bus (a wrapper around the
//!   controller's bus stamps every send; the cycle is found by counting SYNC frames). The
//!   shaper acts on a command in the cycle that takes it, so these setpoints are the first
//!   that reflect it;
//! - *publish → arrival*: the DDS path on loopback, for scale.
//!
//! **Cost**: `rollbase bridge`, `rollbase-sim` on it, and `rollbase drive --bus
//! socketcand://…` as three processes, once with `--ros2` (this program publishing cmd_vel at
//! 20 Hz) and once with the same commands as JSON Lines on stdin; CPU time of the drive
//! process from /proc/PID/stat over the measured interval (after a warm-up), its peak resident
//! memory (VmHWM) and threads.

use rollbase::ros2::dds::{qos, Dds};
use rollbase::ros2::msg::{JointState, Odometry, Twist};
use rollbase::ros2::{spawn_node, Ros2Options};
use rollbase_control::runtime::record::CycleRecord;
use rollbase_control::runtime::{
    command_channel, percentile, realtime_setup, run_realtime_io, CycleCore, RealtimeIo,
    RealtimeOptions, RuntimeConfig,
};
use rollbase_control::service::ports::{BaseState, CommandEvent, CommandKind};
use rollbase_control::Platform;
use rollbase_driver::bus::{BusClock, BusError, CanBus, VirtualBus, VirtualBusConfig};
use rollbase_driver::frame::{CanFrame, TimestampedFrame};
use rollbase_driver::protocol::{classify, MessageKind};
use rollbase_vcan_sim::{SimConfig, Simulator};
use std::io::{BufRead, BufReader, Write};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

const BEGIN: &str = "<!-- ros2-perf:begin -->";
const END: &str = "<!-- ros2-perf:end -->";

fn main() {
    if let Err(e) = real_main() {
        eprintln!("ros2-perf: {e}");
        std::process::exit(1);
    }
}

struct Opts {
    out: PathBuf,
    commands: usize,
    seconds: f64,
}

fn parse_args() -> Result<Opts, String> {
    let mut o = Opts {
        out: PathBuf::from("docs/performance.md"),
        commands: 600,
        seconds: 30.0,
    };
    let mut args = std::env::args().skip(1);
    while let Some(a) = args.next() {
        let mut val = |name: &str| args.next().ok_or(format!("{name} needs a value"));
        match a.as_str() {
            "--out" => o.out = PathBuf::from(val("--out")?),
            "--commands" => {
                let v = val("--commands")?;
                o.commands = v
                    .parse()
                    .ok()
                    .filter(|n| (10..=100_000).contains(n))
                    .ok_or(format!("--commands {v}: give 10..=100000"))?;
            }
            "--seconds" => {
                let v = val("--seconds")?;
                o.seconds = v
                    .parse()
                    .ok()
                    .filter(|s: &f64| (5.0..=3600.0).contains(s))
                    .ok_or(format!("--seconds {v}: give 5..=3600"))?;
            }
            "-h" | "--help" => {
                println!("usage: ros2-perf [--out docs/performance.md] [--commands 600] [--seconds 30]  (inside unshare -n)");
                std::process::exit(0);
            }
            other => return Err(format!("unknown argument {other:?} (see --help)")),
        }
    }
    Ok(o)
}

/// Whether this network namespace has no interface but loopback.
fn only_loopback() -> bool {
    let Ok(text) = std::fs::read_to_string("/proc/net/dev") else {
        return false;
    };
    let ifaces: Vec<&str> = text
        .lines()
        .skip(2)
        .filter_map(|l| l.split(':').next())
        .map(str::trim)
        .collect();
    ifaces == ["lo"]
}

fn real_main() -> Result<(), String> {
    let o = parse_args()?;
    if !only_loopback() {
        return Err("DDS discovery multicasts: run me in a private network namespace with only loopback: unshare -n sh -c 'ip link set lo up && …/ros2-perf'".into());
    }
    eprintln!(
        "latency: {} commands through the node and the cycle …",
        o.commands
    );
    let lat = latency(o.commands)?;
    eprintln!(
        "cost: drive --ros2 and drive --commands -, {} s each …",
        o.seconds
    );
    let bins = bin_dir()?;
    let with = cost(&bins, true, o.seconds)?;
    let without = cost(&bins, false, o.seconds)?;
    let section = render(&lat, &with, &without, o.commands);
    write_section(&o.out, &section)?;
    eprintln!("wrote the ROS 2 section of {}", o.out.display());
    print!("{section}");
    Ok(())
}

// ---------------------------------------------------------------------------------------
// Latency

/// The controller's bus, stamping when each frame is handed over: the instant of the first
/// SETPOINT of each cycle (cycles counted by SYNC frames).
struct StampingBus<B: CanBus> {
    inner: B,
    cycle: Option<usize>,
    first_setpoint: Arc<Mutex<Vec<Option<Instant>>>>,
}

impl<B: CanBus> CanBus for StampingBus<B> {
    fn send(&mut self, frame: &CanFrame) -> Result<(), BusError> {
        let r = self.inner.send(frame);
        let now = Instant::now();
        match classify(frame.id()).map(|(k, _)| k) {
            Some(MessageKind::Sync) => self.cycle = Some(self.cycle.map_or(0, |c| c + 1)),
            Some(MessageKind::Setpoint) => {
                if let (Some(c), Ok(mut v)) = (self.cycle, self.first_setpoint.lock()) {
                    if v.len() <= c {
                        v.resize(c + 1, None);
                    }
                    v[c].get_or_insert(now);
                }
            }
            _ => {}
        }
        r
    }
    fn try_recv(&mut self) -> Result<Option<TimestampedFrame>, BusError> {
        self.inner.try_recv()
    }
    fn recv_until(&mut self, deadline: Instant) -> Result<Option<TimestampedFrame>, BusError> {
        self.inner.recv_until(deadline)
    }
    fn name(&self) -> &str {
        self.inner.name()
    }
}

struct Latency {
    /// arrival → first SETPOINT (µs), one per command.
    to_setpoint: Vec<f64>,
    /// publish → arrival (µs).
    dds: Vec<f64>,
    /// publish → first SETPOINT (µs).
    total: Vec<f64>,
    cycles: u64,
    deadline_misses: u64,
    period_ms: f64,
    lost: usize,
}

/// The command's tag: `linear.x` = 0.1 + k · 1e-4 m/s (k < 1000: ≤ 0.2 m/s, a walking pace
/// well inside the limits; the shaper passes every change on).
fn tag_speed(k: usize) -> f64 {
    0.1 + (k % 1000) as f64 * 1e-4
}

fn tag_of(vx: f64) -> usize {
    ((vx - 0.1) / 1e-4).round() as usize
}

fn latency(n: usize) -> Result<Latency, String> {
    let p = Platform::justin();
    let cfg = RuntimeConfig::default();
    let mut core = CycleCore::new_live(p.clone(), cfg).map_err(|e| e.to_string())?;
    let mut sim = Simulator::with_config(&p, SimConfig::default()).map_err(|e| e.to_string())?;
    let vbus = VirtualBus::new(VirtualBusConfig {
        clock: BusClock::Wall,
        ..Default::default()
    });
    let first_setpoint = Arc::new(Mutex::new(Vec::<Option<Instant>>::new()));
    let mut ctrl = StampingBus {
        inner: vbus.node("controller"),
        cycle: None,
        first_setpoint: first_setpoint.clone(),
    };
    let mut simnode = vbus.node("simulator");
    let sim_stop = Arc::new(AtomicBool::new(false));
    let ss = sim_stop.clone();
    let sim_thread = std::thread::spawn(move || {
        let _ = realtime_setup(&RealtimeOptions {
            fifo_priority: Some(81),
            lock_memory: false,
            max_cycles: None,
        });
        sim.run_realtime(&mut simnode, &ss)
    });

    // node → forwarder (stamps arrivals) → the cycle's command queue.
    // The command channel has no blocking receive (the cycle never waits): the forwarder
    // polls it every 50 µs, which the latency figures include.
    let (node_tx, node_rx) = command_channel(256, 64);
    let (cmd_tx, cmd_rx) = command_channel(256, 64);
    let arrivals = Arc::new(Mutex::new(Vec::<(usize, Instant)>::new()));
    let arr = arrivals.clone();
    let fwd_stop = Arc::new(AtomicBool::new(false));
    let fs = fwd_stop.clone();
    let forwarder = std::thread::spawn(move || {
        while !fs.load(Ordering::SeqCst) {
            let mut any = false;
            node_rx.take(usize::MAX, |ev: CommandEvent| {
                any = true;
                let now = Instant::now();
                if let CommandKind::Motion(m) = ev.kind {
                    if let Ok(mut a) = arr.lock() {
                        a.push((tag_of(m.twist.vx), now));
                    }
                }
                let _ = cmd_tx.try_send(ev);
            });
            if !any {
                std::thread::sleep(Duration::from_micros(50));
            }
        }
    });
    let (state_tx, state_rx) = std::sync::mpsc::sync_channel::<BaseState>(64);
    let (node_state_tx, node_state_rx) = std::sync::mpsc::sync_channel::<BaseState>(16);
    let node = spawn_node(
        Ros2Options::default(),
        node_tx,
        node_state_rx,
        Instant::now(),
    )
    .map_err(|e| e.to_string())?;
    let state_fwd = std::thread::spawn(move || {
        while let Ok(s) = state_rx.recv() {
            let _ = node_state_tx.try_send(s);
        }
    });

    // The cycle.
    let stop = Arc::new(AtomicBool::new(false));
    let (rec_tx, rec_rx) = std::sync::mpsc::sync_channel::<CycleRecord>(8192);
    let stop_c = stop.clone();
    let cycle = std::thread::spawn(move || {
        let io = RealtimeIo {
            records: Some(&rec_tx),
            states: Some(&state_tx),
            commands: Some(&cmd_rx),
        };
        let opts = RealtimeOptions::default();
        run_realtime_io(&mut core, &mut ctrl, &stop_c, &io, &opts, 0)
    });
    // Collect which cycle took which command.
    let taken = Arc::new(Mutex::new(Vec::<(usize, usize)>::new()));
    let tk = taken.clone();
    let collector = std::thread::spawn(move || {
        let mut k = 0u64;
        while let Ok(r) = rec_rx.recv() {
            k += 1;
            for ev in r.commands_in.iter().flatten() {
                if let CommandKind::Motion(m) = ev.kind {
                    if let Ok(mut t) = tk.lock() {
                        t.push((tag_of(m.twist.vx), r.cycle as usize));
                    }
                }
            }
        }
        k
    });

    // The publisher: another participant in this process.
    let peer = Dds::new(0, &[]).map_err(|e| format!("DDS participant: {e}"))?;
    let twist_pub = peer
        .writer::<Twist>("/cmd_vel", qos::ros_default())
        .map_err(|e| e.to_string())?;
    // Wait for the platform to track and for the subscription to match: publish a tag-0
    // command until one arrives.
    let t0 = Instant::now();
    loop {
        if t0.elapsed() > Duration::from_secs(30) {
            stop.store(true, Ordering::SeqCst);
            return Err("no command reached the node within 30 s (discovery failed?)".into());
        }
        let mut t = Twist::default();
        t.linear.x = tag_speed(0);
        let _ = twist_pub.write(t, None);
        std::thread::sleep(Duration::from_millis(50));
        if arrivals.lock().map(|a| !a.is_empty()).unwrap_or(false) {
            break;
        }
    }
    std::thread::sleep(Duration::from_millis(500));
    let mut published = Vec::with_capacity(n);
    // Period 37.3 ms: not a multiple of the 4 ms cycle, so the arrival phase sweeps it.
    let period = Duration::from_micros(37_300);
    let mut next = Instant::now();
    for k in 1..=n {
        let mut t = Twist::default();
        t.linear.x = tag_speed(k);
        let at = Instant::now();
        if twist_pub.write(t, None).is_ok() {
            published.push((k % 1000, at));
        }
        next += period;
        let now = Instant::now();
        if next > now {
            std::thread::sleep(next - now);
        }
    }
    std::thread::sleep(Duration::from_millis(300));
    stop.store(true, Ordering::SeqCst);
    let report = cycle.join().map_err(|_| "the cycle thread panicked")?;
    let cycles = collector.join().map_err(|_| "the collector panicked")?;
    node.shutdown();
    fwd_stop.store(true, Ordering::SeqCst);
    let _ = forwarder.join();
    let _ = state_fwd.join();
    sim_stop.store(true, Ordering::SeqCst);
    let _ = sim_thread.join();

    let arrivals = arrivals.lock().map_err(|_| "poisoned")?.clone();
    let taken = taken.lock().map_err(|_| "poisoned")?.clone();
    let first = first_setpoint.lock().map_err(|_| "poisoned")?.clone();
    let mut out = Latency {
        to_setpoint: Vec::new(),
        dds: Vec::new(),
        total: Vec::new(),
        cycles,
        deadline_misses: report.deadline_misses,
        period_ms: period.as_secs_f64() * 1e3,
        lost: 0,
    };
    // Tags repeat every 1000 commands: match each publication with the next arrival and the
    // next take of its tag, in order.
    let mut arr_i = 0usize;
    let mut take_i = 0usize;
    for &(tag, pub_at) in &published {
        let Some(ai) = arrivals[arr_i..]
            .iter()
            .position(|&(t, at)| t == tag && at >= pub_at)
        else {
            out.lost += 1;
            continue;
        };
        let arrival = arrivals[arr_i + ai].1;
        arr_i += ai + 1;
        let Some(ti) = taken[take_i..].iter().position(|&(t, _)| t == tag) else {
            out.lost += 1;
            continue;
        };
        let cycle = taken[take_i + ti].1;
        take_i += ti + 1;
        let Some(Some(sp)) = first.get(cycle) else {
            out.lost += 1;
            continue;
        };
        let us = |a: Instant, b: Instant| b.saturating_duration_since(a).as_secs_f64() * 1e6;
        out.to_setpoint.push(us(arrival, *sp));
        out.dds.push(us(pub_at, arrival));
        out.total.push(us(pub_at, *sp));
    }
    if out.to_setpoint.len() < n / 2 {
        return Err(format!(
            "only {} of {n} commands could be followed to a setpoint",
            out.to_setpoint.len()
        ));
    }
    Ok(out)
}

// ---------------------------------------------------------------------------------------
// Cost

/// Where rollbase and rollbase-sim are: next to this program (cargo puts every binary of the
/// workspace in the same target directory), or ROLLBASE_BIN_DIR.
fn bin_dir() -> Result<PathBuf, String> {
    let dir = match std::env::var_os("ROLLBASE_BIN_DIR") {
        Some(d) => PathBuf::from(d),
        None => std::env::current_exe()
            .map_err(|e| e.to_string())?
            .parent()
            .ok_or("no directory for this program")?
            .to_path_buf(),
    };
    for b in ["rollbase", "rollbase-sim"] {
        if !dir.join(b).exists() {
            return Err(format!(
                "{} is missing: cargo build --release -p rollbase -p rollbase-vcan-sim (or set ROLLBASE_BIN_DIR)",
                dir.join(b).display()
            ));
        }
    }
    Ok(dir)
}

struct Cost {
    cpu_percent: f64,
    hwm_kib: u64,
    rss_kib: u64,
    threads: u64,
    seconds: f64,
    exit: Option<i32>,
    /// odom and joint_states messages the peer received during the measurement.
    received: (u64, u64),
    cycles: Option<u64>,
    deadline_misses: Option<u64>,
}

struct Killer(Vec<Child>);

impl Drop for Killer {
    fn drop(&mut self) {
        for c in &mut self.0 {
            let _ = c.kill();
            let _ = c.wait();
        }
    }
}

fn proc_cpu_s(pid: u32) -> Option<f64> {
    let text = std::fs::read_to_string(format!("/proc/{pid}/stat")).ok()?;
    // Fields after the command name (which may hold spaces) start after the last ')'.
    let rest = &text[text.rfind(')')? + 2..];
    let f: Vec<&str> = rest.split_whitespace().collect();
    let utime: f64 = f.get(11)?.parse().ok()?;
    let stime: f64 = f.get(12)?.parse().ok()?;
    // SAFETY: sysconf has no preconditions.
    let hz = unsafe { libc::sysconf(libc::_SC_CLK_TCK) } as f64;
    Some((utime + stime) / hz)
}

fn proc_status(pid: u32, key: &str) -> Option<u64> {
    let text = std::fs::read_to_string(format!("/proc/{pid}/status")).ok()?;
    text.lines()
        .find(|l| l.starts_with(key))?
        .split_whitespace()
        .nth(1)?
        .parse()
        .ok()
}

fn cost(bins: &Path, ros2: bool, seconds: f64) -> Result<Cost, String> {
    let mut kids = Killer(Vec::new());
    let mut bridge = Command::new(bins.join("rollbase"))
        .args(["bridge", "--listen", "127.0.0.1:0"])
        .stdout(Stdio::null())
        .stderr(Stdio::piped())
        .spawn()
        .map_err(|e| format!("rollbase bridge: {e}"))?;
    let stderr = bridge.stderr.take().ok_or("bridge stderr")?;
    kids.0.push(bridge);
    let (port_tx, port_rx) = std::sync::mpsc::channel();
    std::thread::spawn(move || {
        let mut sent = false;
        for line in BufReader::new(stderr).lines().map_while(Result::ok) {
            if !sent {
                if let Some(p) = line
                    .split("127.0.0.1:")
                    .nth(1)
                    .and_then(|s| s.split(|c: char| !c.is_ascii_digit()).next())
                    .and_then(|s| s.parse::<u16>().ok())
                {
                    let _ = port_tx.send(p);
                    sent = true;
                }
            }
        }
    });
    let port = port_rx
        .recv_timeout(Duration::from_secs(10))
        .map_err(|_| "the bridge did not print its port")?;
    let bus = format!("socketcand://127.0.0.1:{port}/vcan0");
    let sim = Command::new(bins.join("rollbase-sim"))
        .args(["--bus", &bus])
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .spawn()
        .map_err(|e| format!("rollbase-sim: {e}"))?;
    kids.0.push(sim);
    std::thread::sleep(Duration::from_millis(500));
    let mut args = vec!["drive".to_string(), "--bus".into(), bus, "--json".into()];
    if ros2 {
        args.push("--ros2".into());
    } else {
        args.extend(["--commands".into(), "-".into()]);
    }
    let mut drive = Command::new(bins.join("rollbase"))
        .args(&args)
        .stdin(Stdio::piped())
        .stdout(Stdio::piped())
        .stderr(Stdio::null())
        .spawn()
        .map_err(|e| format!("rollbase drive: {e}"))?;
    let pid = drive.id();
    let mut stdin = drive.stdin.take();
    let stdout = drive.stdout.take();
    kids.0.push(drive);

    // Commands at 20 Hz: a slow circle (0.2 m/s, 0.1 rad/s), from ROS 2 or stdin.
    let mut ros = None;
    if ros2 {
        let peer = Dds::new(0, &[]).map_err(|e| format!("DDS participant: {e}"))?;
        let p = peer
            .writer::<Twist>("/cmd_vel", qos::ros_default())
            .map_err(|e| e.to_string())?;
        let odom = peer
            .reader::<Odometry>("/odom", qos::ros_default())
            .map_err(|e| e.to_string())?;
        let joints = peer
            .reader::<JointState>("/joint_states", qos::ros_default())
            .map_err(|e| e.to_string())?;
        ros = Some((peer, p, odom, joints));
    }
    let warmup = Duration::from_secs(5);
    let begin = Instant::now();
    let mut t0: Option<(Instant, f64)> = None;
    let mut k = 0u64;
    let mut received = (0u64, 0u64);
    while begin.elapsed() < warmup + Duration::from_secs_f64(seconds) {
        let mut tw = Twist::default();
        tw.linear.x = 0.2;
        tw.angular.z = 0.1;
        if let Some((_, p, odom, joints)) = &ros {
            let _ = p.write(tw, None);
            while let Ok(Some(_)) = odom.take() {
                if t0.is_some() {
                    received.0 += 1;
                }
            }
            while let Ok(Some(_)) = joints.take() {
                if t0.is_some() {
                    received.1 += 1;
                }
            }
        } else if let Some(s) = stdin.as_mut() {
            let _ = writeln!(s, "{{\"vx\": 0.2, \"vy\": 0.0, \"omega\": 0.1}}");
        }
        k += 1;
        if t0.is_none() && begin.elapsed() >= warmup {
            t0 = Some((Instant::now(), proc_cpu_s(pid).ok_or("drive exited early")?));
        }
        std::thread::sleep(Duration::from_millis(50));
    }
    let (start, cpu0) = t0.ok_or("no warm-up")?;
    let cpu1 = proc_cpu_s(pid).ok_or("drive exited early")?;
    let wall = start.elapsed().as_secs_f64();
    let hwm = proc_status(pid, "VmHWM:").unwrap_or(0);
    let rss = proc_status(pid, "VmRSS:").unwrap_or(0);
    let threads = proc_status(pid, "Threads:").unwrap_or(0);
    let _ = k;
    // SIGTERM: a controlled stop, then the summary.
    // SAFETY: sending a signal to our own child.
    unsafe { libc::kill(pid as i32, libc::SIGTERM) };
    drop(stdin);
    let mut summary = String::new();
    if let Some(mut o) = stdout {
        let _ = std::io::Read::read_to_string(&mut o, &mut summary);
    }
    let exit = kids
        .0
        .last_mut()
        .and_then(|c| c.wait().ok())
        .and_then(|s| s.code());
    drop(ros);
    let j: serde_json::Value = serde_json::from_str(summary.trim()).unwrap_or_default();
    Ok(Cost {
        cpu_percent: (cpu1 - cpu0) / wall * 100.0,
        hwm_kib: hwm,
        rss_kib: rss,
        threads,
        seconds: wall,
        exit,
        received,
        cycles: j["cycles"].as_u64(),
        deadline_misses: j["deadline_misses"].as_u64(),
    })
}

// ---------------------------------------------------------------------------------------
// Report

fn render(l: &Latency, with: &Cost, without: &Cost, n: usize) -> String {
    let p = |v: &[f64], q: f64| percentile(v, q) / 1e3;
    let cpu = |c: &Cost| {
        format!(
            "{:.1} % of one core | {:.1} MiB | {:.1} MiB | {} | {} / {} | {}",
            c.cpu_percent,
            c.hwm_kib as f64 / 1024.0,
            c.rss_kib as f64 / 1024.0,
            c.threads,
            c.cycles.map_or("?".into(), |v| v.to_string()),
            c.deadline_misses.map_or("?".into(), |v| v.to_string()),
            c.exit.map_or("signal".into(), |v| v.to_string()),
        )
    };
    let machine = std::fs::read_to_string("/proc/cpuinfo")
        .ok()
        .and_then(|t| {
            t.lines()
                .find(|l| l.starts_with("model name"))
                .and_then(|l| l.split(':').nth(1))
                .map(|s| s.trim().to_string())
        })
        .unwrap_or_else(|| "unknown CPU".into());
    let cores = std::thread::available_parallelism().map_or(0, |n| n.get());
    format!(
        "{BEGIN}\n## ROS 2: command latency and the cost of `drive --ros2`\n\n\
Generated by `tests/src/bin/ros2-perf.rs` (run it in a loopback-only network namespace: see its \
doc) on {machine}, {cores} cores, shared; release build.\n\n\
### cmd_vel → first SETPOINT\n\n\
{m} of {n} `geometry_msgs/Twist` published on `/cmd_vel` by a second DDS participant in the same \
process (one every {per:.1} ms, a period prime to the 4 ms cycle so arrivals sweep its phase), \
followed through the real node and the real-time cycle ({c} cycles, {dm} deadline misses) on the \
wall-clock in-process bus with the simulator; {lost} could not be followed. *Arrival* is when \
the node hands the command to the command port; *first SETPOINT* is when the first SETPOINT of \
the cycle that took it is handed to the bus (the shaper acts on a command in the cycle that \
takes it).\n\n\
| | p50 | p99 | max | bound |\n|---|---|---|---|---|\n\
| arrival → first SETPOINT | {a50:.2} ms | {a99:.2} ms | {amax:.2} ms | one cycle + 1 ms = 5 ms |\n\
| publish → arrival (DDS on loopback) | {d50:.2} ms | {d99:.2} ms | {dmax:.2} ms | |\n\
| publish → first SETPOINT | {t50:.2} ms | {t99:.2} ms | {tmax:.2} ms | |\n\n\
The cycle takes waiting commands just before it computes the setpoints (after the feedback \
window), so a command waits at most one period for its cycle: arrival → SETPOINT is spread \
over [compute, period + compute].\n\n\
### Cost of `rollbase drive --ros2`\n\n\
`rollbase bridge`, `rollbase-sim` on it and `rollbase drive --bus socketcand://127.0.0.1:PORT/vcan0` \
at 250 Hz, commands at 20 Hz (0.2 m/s, 0.1 rad/s), measured over {s:.0} s (with ROS 2) and {s2:.0} s (without) after a 5 s warm-up; \
ROS 2 at the default rates (odom and tf 50 Hz, joint_states 50 Hz, diagnostics 1 Hz), one peer \
subscribed to odom and joint_states (it received {ro} odom and {rj} joint_states messages in \
the measured interval: {ror:.1} and {rjr:.1} per second). CPU from /proc/PID/stat (user + system) of the drive process only; \
the bridge and the simulator are not counted.\n\n\
| drive | CPU | peak RSS (VmHWM) | RSS at the end | threads | cycles / deadline misses | exit after SIGTERM |\n|---|---|---|---|---|---|---|\n\
| `--ros2` (cmd_vel) | {w} |\n\
| `--commands -` (stdin, same commands) | {wo} |\n\n{END}\n",
        m = l.to_setpoint.len(),
        per = l.period_ms,
        c = l.cycles,
        dm = l.deadline_misses,
        lost = l.lost,
        a50 = p(&l.to_setpoint, 50.0),
        a99 = p(&l.to_setpoint, 99.0),
        amax = p(&l.to_setpoint, 100.0),
        d50 = p(&l.dds, 50.0),
        d99 = p(&l.dds, 99.0),
        dmax = p(&l.dds, 100.0),
        t50 = p(&l.total, 50.0),
        t99 = p(&l.total, 99.0),
        tmax = p(&l.total, 100.0),
        s = with.seconds,
        s2 = without.seconds,
        ro = with.received.0,
        rj = with.received.1,
        ror = with.received.0 as f64 / with.seconds,
        rjr = with.received.1 as f64 / with.seconds,
        w = cpu(with),
        wo = cpu(without),
    )
}

/// Replaces the section between the markers in `path` (or appends it).
fn write_section(path: &Path, section: &str) -> Result<(), String> {
    let old = std::fs::read_to_string(path).unwrap_or_default();
    let new = match (old.find(BEGIN), old.find(END)) {
        (Some(b), Some(e)) if e > b => {
            let mut s = String::new();
            s.push_str(&old[..b]);
            s.push_str(section.trim_end());
            s.push_str(old[e + END.len()..].trim_end_matches('\n'));
            s.push('\n');
            s
        }
        _ => {
            let mut s = old.trim_end().to_string();
            if !s.is_empty() {
                s.push_str("\n\n");
            }
            s.push_str(section);
            s
        }
    };
    let tmp = path.with_extension("md.tmp");
    std::fs::write(&tmp, new).map_err(|e| format!("{}: {e}", tmp.display()))?;
    std::fs::rename(&tmp, path).map_err(|e| format!("{}: {e}", path.display()))
}
