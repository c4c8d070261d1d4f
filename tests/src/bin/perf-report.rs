//! `perf-report`: measures rollbase against its references and writes `docs/performance.md`.
//!
//! Run it through `benches/report.sh` (which first runs the criterion benchmarks); by hand:
//!
//! ```text
//! perf-report [--out docs/performance.md] [--criterion target/criterion]
//!             [--bench-log FILE]... [--cycles 10000]
//! ```
//!
//! In one run it measures, each beside its reference:
//! - the criterion medians of the codec and control-step benchmarks (read from
//!   `<criterion>/<id>/new/estimates.json`) and the allocation counts the benchmarks print
//!   (`ALLOCS <id> <allocations> <steps>` lines in the bench logs);
//! - the lockstep speed of the whole seed-000 scenario through the virtual bus and the
//!   simulator (`rollbase_tests::run`), as a real-time factor;
//! - the real-time cycle (`runtime::run_realtime` on the wall-clock virtual bus, simulator in
//!   its own thread) over `--cycles` cycles in a child process: period jitter, wake-up
//!   latency, CPU time of each thread per second of run (getrusage), peak memory (VmHWM);
//! - the baseline: `cyclictest -t1 -i 4000 -l N -v` (rt-tests), or a minimal
//!   clock_nanosleep loop in a child process when cyclictest is missing or fails;
//! - the protocol's bus load from `rollbase_driver::busload` beside the least any protocol
//!   carrying the same signals needs;
//! - the base service's per-cycle work on a live command session (`tests/benches/live.rs`:
//!   criterion medians, per-step percentiles from its `STEPTIME` lines, allocations) and issue
//!   23's benchmarks (`tests/benches/flow.rs`: the shaper with a new goal every cycle, the
//!   planning of a 60-waypoint file), in a section between `<!-- live:begin -->` and
//!   `<!-- live:end -->`.
//!
//! `perf-report --section live [--out …] [--criterion …] [--bench-log …]` rewrites only that
//! section of an existing report (from the live benchmark's results), leaving every other
//! figure as it was measured.

use rollbase_control::runtime::record::CycleRecord;
use rollbase_control::runtime::scenario::{self, Scenario};
use rollbase_control::runtime::{
    percentile, realtime_setup, run_realtime, CycleCore, RealtimeOptions,
};
use rollbase_control::Platform;
use rollbase_driver::bus::{BusClock, VirtualBus, VirtualBusConfig};
use rollbase_driver::busload::{bus_load, frame_bits, BusLoadConfig};
use rollbase_driver::protocol::{MessageKind, SignalRole, MESSAGES};
use rollbase_tests::{run, RunOptions};
use rollbase_vcan_sim::{FaultSchedule, PlantConfig, Simulator};
use serde_json::{json, Value};
use std::fmt::Write as _;
use std::path::{Path, PathBuf};
use std::process::Command;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::Instant;

const PERIOD_US: f64 = 4000.0;

fn main() {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let r = match args.first().map(String::as_str) {
        Some("realtime-child") => {
            child_cycles(&args).and_then(|n| realtime_child(n).map(|v| println!("{v}")))
        }
        Some("nanosleep-child") => {
            child_cycles(&args).and_then(|n| nanosleep_child(n).map(|v| println!("{v}")))
        }
        _ => Options::parse(&args).and_then(|o| match o.section.as_deref() {
            None => report(&o),
            Some("live") => update_live_section(&o),
            Some(other) => Err(format!(
                "--section `{other}`: the only section written alone is `live`"
            )),
        }),
    };
    if let Err(e) = r {
        eprintln!("perf-report: {e}");
        std::process::exit(1);
    }
}

fn child_cycles(args: &[String]) -> Result<u64, String> {
    let a = args
        .get(1)
        .ok_or("the child mode needs a cycle count, e.g. `realtime-child 10000`")?;
    a.parse()
        .map_err(|_| format!("cycle count `{a}` is not a positive integer"))
}

/// Command-line options of the report.
struct Options {
    out: PathBuf,
    criterion: PathBuf,
    bench_logs: Vec<PathBuf>,
    cycles: u64,
    /// Rewrite only this section of `out` (`live`).
    section: Option<String>,
}

impl Options {
    fn parse(args: &[String]) -> Result<Self, String> {
        let mut o = Options {
            out: PathBuf::from("docs/performance.md"),
            criterion: PathBuf::from("target/criterion"),
            bench_logs: Vec::new(),
            cycles: 10_000,
            section: None,
        };
        let mut it = args.iter();
        while let Some(a) = it.next() {
            let mut val = |name: &str| {
                it.next()
                    .cloned()
                    .ok_or_else(|| format!("{name} needs a value"))
            };
            match a.as_str() {
                "--out" => o.out = val("--out")?.into(),
                "--criterion" => o.criterion = val("--criterion")?.into(),
                "--bench-log" => o.bench_logs.push(val("--bench-log")?.into()),
                "--section" => o.section = Some(val("--section")?),
                "--cycles" => {
                    let v = val("--cycles")?;
                    o.cycles = v
                        .parse()
                        .ok()
                        .filter(|&n| n >= 100)
                        .ok_or(format!("--cycles `{v}`: give an integer ≥ 100"))?;
                }
                "-h" | "--help" => {
                    println!(
                        "perf-report [--out docs/performance.md] [--criterion target/criterion] [--bench-log FILE]... [--cycles 10000] [--section live]"
                    );
                    std::process::exit(0);
                }
                other => {
                    return Err(format!(
                        "unknown argument `{other}` (see --help; run benches/report.sh for the full report)"
                    ))
                }
            }
        }
        Ok(o)
    }
}

// ---------------------------------------------------------------- process statistics

/// user + sys CPU seconds of `who` (RUSAGE_SELF or RUSAGE_THREAD).
fn cpu_seconds(who: libc::c_int) -> f64 {
    // SAFETY: rusage is plain data; all-zero is a valid value.
    let mut ru: libc::rusage = unsafe { std::mem::zeroed() };
    // SAFETY: getrusage writes into the provided struct; `who` is a valid selector.
    if unsafe { libc::getrusage(who, &mut ru) } != 0 {
        return f64::NAN;
    }
    let tv = |t: libc::timeval| t.tv_sec as f64 + t.tv_usec as f64 * 1e-6;
    tv(ru.ru_utime) + tv(ru.ru_stime)
}

/// A `kB` field of /proc/self/status (e.g. VmHWM), in kB.
fn proc_status_kb(field: &str) -> Option<u64> {
    let s = std::fs::read_to_string("/proc/self/status").ok()?;
    s.lines()
        .find(|l| l.starts_with(field) && l[field.len()..].starts_with(':'))
        .and_then(|l| l.split_whitespace().nth(1))
        .and_then(|v| v.parse().ok())
}

fn stats(xs: &[f64]) -> Value {
    json!({
        "raw": xs,
        "n": xs.len(),
        "p50": percentile(xs, 50.0),
        "p99": percentile(xs, 99.0),
        "max": percentile(xs, 100.0),
    })
}

// ---------------------------------------------------------------- real-time child

/// The runtime's real-time cycle over `cycles` cycles (seed-000 sessions back to back: a
/// session that finishes its trajectory early is followed by a fresh one). Prints one JSON
/// object.
fn realtime_child(cycles: u64) -> Result<Value, String> {
    let cpu0 = cpu_seconds(libc::RUSAGE_SELF);
    let wall0 = Instant::now();
    let (tx, rx) = std::sync::mpsc::sync_channel::<CycleRecord>(1024);
    // The recorder: keeps only the timing of each record.
    let collector = std::thread::Builder::new()
        .name("recorder".into())
        .spawn(move || {
            let c0 = cpu_seconds(libc::RUSAGE_THREAD);
            let mut v: Vec<(u64, f64, f64, f64, bool)> = Vec::with_capacity(cycles as usize);
            for r in rx {
                let t = r.timing;
                v.push((
                    r.cycle,
                    t.period_us,
                    t.wakeup_latency_us,
                    t.compute_us,
                    t.deadline_miss,
                ));
            }
            (v, cpu_seconds(libc::RUSAGE_THREAD) - c0)
        })
        .map_err(|e| format!("cannot start the recorder thread: {e}"))?;
    let cycle_thread = std::thread::Builder::new()
        .name("rollbase-cycle".into())
        .spawn(move || -> Result<Value, String> {
            let p = Platform::justin();
            let mut done = 0u64;
            let (mut misses, mut dropped, mut sessions) = (0u64, 0u64, 0u32);
            let (mut thread_cpu, mut sim_cpu, mut wall) = (0.0, 0.0, 0.0);
            let mut setup = Vec::new();
            while done < cycles {
                let traj = scenario::trajectory(Scenario::Seed000, &p)
                    .map_err(|e| format!("seed000 scenario: {e}"))?;
                let r0 = traj.sample(0.0);
                let mut core =
                    CycleCore::new(p.clone(), traj, scenario::runtime_config(Scenario::Seed000))
                        .map_err(|e| format!("cycle core: {e}"))?;
                let mut sim =
                    Simulator::new(&p, PlantConfig::default(), FaultSchedule::default(), &r0, 3)
                        .map_err(|e| format!("simulator: {e}"))?;
                let bus = VirtualBus::new(VirtualBusConfig {
                    clock: BusClock::Wall,
                    ..Default::default()
                });
                let mut ctrl = bus.node("controller");
                let mut simnode = bus.node("simulator");
                let sim_stop = Arc::new(AtomicBool::new(false));
                let ss = sim_stop.clone();
                let sim_thread = std::thread::Builder::new()
                    .name("simulator".into())
                    .spawn(move || {
                        let c0 = cpu_seconds(libc::RUSAGE_THREAD);
                        let r = sim.run_realtime(&mut simnode, &ss).map(|_| ());
                        (r, cpu_seconds(libc::RUSAGE_THREAD) - c0)
                    })
                    .map_err(|e| format!("cannot start the simulator thread: {e}"))?;
                let stop = AtomicBool::new(false);
                let opts = RealtimeOptions {
                    max_cycles: Some(cycles - done),
                    ..Default::default()
                };
                let c0 = cpu_seconds(libc::RUSAGE_THREAD);
                let w0 = Instant::now();
                let rep = run_realtime(&mut core, &mut ctrl, &stop, Some(&tx), &opts, 0);
                wall += w0.elapsed().as_secs_f64();
                thread_cpu += cpu_seconds(libc::RUSAGE_THREAD) - c0;
                sim_stop.store(true, Ordering::SeqCst);
                let (sr, sc) = sim_thread
                    .join()
                    .map_err(|_| "the simulator thread panicked".to_string())?;
                sr.map_err(|e| format!("simulator: {e}"))?;
                sim_cpu += sc;
                done += rep.cycles;
                misses += rep.deadline_misses;
                dropped += rep.records_dropped;
                sessions += 1;
                if setup.is_empty() {
                    setup = rep.setup.clone();
                }
                if rep.cycles == 0 {
                    return Err("a real-time session ran no cycle".into());
                }
            }
            drop(tx);
            Ok(json!({
                "cycles": done, "sessions": sessions, "deadline_misses": misses,
                "records_dropped": dropped, "setup": setup,
                "cycle_thread_cpu_s": thread_cpu, "simulator_cpu_s": sim_cpu, "wall_s": wall,
            }))
        })
        .map_err(|e| format!("cannot start the cycle thread: {e}"))?;
    let mut out = cycle_thread
        .join()
        .map_err(|_| "the cycle thread panicked".to_string())??;
    let (records, recorder_cpu) = collector
        .join()
        .map_err(|_| "the recorder thread panicked".to_string())?;
    let periods: Vec<f64> = records
        .iter()
        .filter(|r| r.0 > 0)
        .map(|r| (r.1 - PERIOD_US).abs())
        .collect();
    let latency: Vec<f64> = records.iter().map(|r| r.2).collect();
    let compute: Vec<f64> = records.iter().map(|r| r.3).collect();
    out["records"] = json!(records.len());
    out["recorded_misses"] = json!(records.iter().filter(|r| r.4).count());
    out["jitter_us"] = stats(&periods);
    out["latency_us"] = stats(&latency);
    out["compute_us"] = stats(&compute);
    out["recorder_cpu_s"] = json!(recorder_cpu);
    out["process_cpu_s"] = json!(cpu_seconds(libc::RUSAGE_SELF) - cpu0);
    out["process_wall_s"] = json!(wall0.elapsed().as_secs_f64());
    out["vm_hwm_kb"] = json!(proc_status_kb("VmHWM"));
    out["vm_rss_kb"] = json!(proc_status_kb("VmRSS"));
    Ok(out)
}

// ---------------------------------------------------------------- nanosleep baseline

/// A minimal absolute-deadline clock_nanosleep loop at 4 ms with the runtime's scheduling
/// setup: no work at all. Prints one JSON object.
fn nanosleep_child(cycles: u64) -> Result<Value, String> {
    let setup = realtime_setup(&RealtimeOptions::default());
    let now = || {
        let mut ts = libc::timespec {
            tv_sec: 0,
            tv_nsec: 0,
        };
        // SAFETY: clock_gettime writes into the provided timespec.
        unsafe { libc::clock_gettime(libc::CLOCK_MONOTONIC, &mut ts) };
        ts.tv_sec as i128 * 1_000_000_000 + ts.tv_nsec as i128
    };
    let period = 4_000_000i128;
    let mut deadline = now() + period;
    let mut lat = Vec::with_capacity(cycles as usize);
    let mut per = Vec::with_capacity(cycles as usize);
    let mut prev: Option<i128> = None;
    for _ in 0..cycles {
        let ts = libc::timespec {
            tv_sec: (deadline / 1_000_000_000) as libc::time_t,
            tv_nsec: (deadline % 1_000_000_000) as libc::c_long,
        };
        // SAFETY: absolute sleep on CLOCK_MONOTONIC with a valid timespec and no remainder.
        while unsafe {
            libc::clock_nanosleep(
                libc::CLOCK_MONOTONIC,
                libc::TIMER_ABSTIME,
                &ts,
                std::ptr::null_mut(),
            )
        } == libc::EINTR
        {}
        let w = now();
        lat.push((w - deadline) as f64 / 1e3);
        if let Some(p) = prev {
            per.push(((w - p) as f64 / 1e3 - PERIOD_US).abs());
        }
        prev = Some(w);
        deadline += period;
    }
    Ok(json!({
        "tool": "clock_nanosleep loop (perf-report nanosleep-child)",
        "setup": setup,
        "jitter_us": stats(&per),
        "latency_us": stats(&lat),
    }))
}

/// `cyclictest -t1 -i 4000 -l N -v [-p 80 -m]`: per-loop latencies; the period jitter of
/// loop k is |lat_k − lat_{k−1}| (each wake-up is due exactly 4 ms after the previous
/// deadline).
fn cyclictest(cycles: u64, fifo: bool) -> Result<Value, String> {
    let mut cmd = Command::new("cyclictest");
    let mut args = vec![
        "-t1".to_string(),
        "-i".into(),
        "4000".into(),
        "-l".into(),
        cycles.to_string(),
        "-v".into(),
    ];
    if fifo {
        args.extend(["-p".into(), "80".into(), "-m".into()]);
    }
    cmd.args(&args);
    let out = cmd
        .output()
        .map_err(|e| format!("cyclictest not runnable ({e}); apt-get install rt-tests"))?;
    if !out.status.success() {
        return Err(format!(
            "cyclictest failed ({}): {}",
            out.status,
            String::from_utf8_lossy(&out.stderr).trim()
        ));
    }
    let text = String::from_utf8_lossy(&out.stdout);
    let mut lat = Vec::with_capacity(cycles as usize);
    for l in text.lines() {
        let f: Vec<&str> = l.split(':').map(str::trim).collect();
        if f.len() == 3 && f[0] == "0" {
            if let Ok(v) = f[2].parse::<f64>() {
                lat.push(v);
            }
        }
    }
    if (lat.len() as u64) < cycles / 2 {
        return Err(format!(
            "cyclictest printed {} samples for {cycles} loops",
            lat.len()
        ));
    }
    let per: Vec<f64> = lat.windows(2).map(|w| (w[1] - w[0]).abs()).collect();
    Ok(json!({
        "tool": format!("cyclictest {}", args.join(" ")),
        "setup": [if fifo { "SCHED_FIFO 80, mlockall (as the runtime got)" } else { "normal scheduling (as the runtime got)" }],
        "jitter_us": stats(&per),
        "latency_us": stats(&lat),
    }))
}

// ---------------------------------------------------------------- criterion results

struct Estimate {
    median_ns: f64,
    lo_ns: f64,
    hi_ns: f64,
}

fn criterion_median(dir: &Path, id: &str) -> Option<Estimate> {
    let p = dir.join(id.replace('/', "_")).join("new/estimates.json");
    let v: Value = serde_json::from_str(&std::fs::read_to_string(p).ok()?).ok()?;
    let m = &v["median"];
    Some(Estimate {
        median_ns: m["point_estimate"].as_f64()?,
        lo_ns: m["confidence_interval"]["lower_bound"].as_f64()?,
        hi_ns: m["confidence_interval"]["upper_bound"].as_f64()?,
    })
}

/// `ALLOCS <id> <allocations> <steps>` lines of the bench logs.
fn alloc_counts(logs: &[PathBuf]) -> Vec<(String, u64, u64)> {
    let mut v = Vec::new();
    for l in logs {
        let Ok(text) = std::fs::read_to_string(l) else {
            continue;
        };
        for line in text.lines() {
            let f: Vec<&str> = line.split_whitespace().collect();
            if f.len() >= 4 && f[0] == "ALLOCS" {
                if let (Ok(a), Ok(s)) = (f[2].parse(), f[3].parse()) {
                    v.push((f[1].to_string(), a, s));
                }
            }
        }
    }
    v
}

// ---------------------------------------------------------------- bus load minimum

/// Signal bits (values, flags, enums; not counters and CRCs) of a message kind.
fn signal_bits(kind: MessageKind) -> u32 {
    MESSAGES
        .iter()
        .filter(|m| m.kind == kind)
        .flat_map(|m| m.signals.iter())
        .filter(|s| !matches!(s.role, SignalRole::Counter | SignalRole::Crc))
        .map(|s| u32::from(s.length))
        .sum()
}

/// Worst-case bits of the fewest classic frames that carry `bits` data bits.
fn min_frames_bits(bits: u32) -> (u32, u32) {
    let mut bytes = bits.div_ceil(8);
    let (mut frames, mut total) = (0, 0);
    loop {
        let b = bytes.min(8);
        total += frame_bits(b as usize);
        frames += 1;
        bytes -= b;
        if bytes == 0 {
            return (frames, total);
        }
    }
}

/// Alternating blocks of the real-time measurement.
const BLOCKS: u64 = 5;

/// Merges the children's JSON objects: raw samples concatenated (statistics recomputed),
/// numbers summed, VmHWM/VmRSS the largest, everything else from the first block.
fn merge(parts: &[Value]) -> Value {
    let mut out = parts.first().cloned().unwrap_or_else(|| json!({}));
    let Some(obj) = out.as_object_mut() else {
        return out;
    };
    for (k, v) in obj.iter_mut() {
        if v.get("raw").is_some() {
            let all: Vec<f64> = parts
                .iter()
                .filter_map(|p| p[k.as_str()]["raw"].as_array())
                .flatten()
                .filter_map(Value::as_f64)
                .collect();
            *v = stats(&all);
        } else if v.is_number() {
            let xs = parts.iter().filter_map(|p| p[k.as_str()].as_f64());
            *v = if k.starts_with("vm_") {
                json!(xs.fold(0.0, f64::max))
            } else {
                json!(xs.sum::<f64>())
            };
        }
    }
    obj.insert("blocks".into(), json!(parts.len()));
    out
}

// ---------------------------------------------------------------- lockstep breakdown

/// Where lockstep wall time goes: the seed-000 scenario in a lockstep loop of the same
/// shape as `run_lockstep` (no records kept), timing the simulator (advance, drain, frame
/// delivery), the virtual bus (time, send, receive) and the controller core separately.
/// Returns (simulator, bus, core, total) seconds and the cycle count.
fn lockstep_breakdown(p: &Platform) -> Result<([f64; 4], u64), String> {
    use rollbase_control::runtime::{LockstepBus, LockstepPeer, VirtualLockstepBus};
    use rollbase_driver::fault::FaultModel;
    use rollbase_driver::frame::CanFrame;
    use std::time::Duration;
    let traj = scenario::trajectory(Scenario::Seed000, p).map_err(|e| e.to_string())?;
    let r0 = traj.sample(0.0);
    let max = ((traj.duration() + 15.0) / p.dt()) as u64;
    let mut core = CycleCore::new(p.clone(), traj, scenario::runtime_config(Scenario::Seed000))
        .map_err(|e| e.to_string())?;
    let mut sim = Simulator::new(p, PlantConfig::default(), FaultSchedule::default(), &r0, 1)
        .map_err(|e| e.to_string())?;
    let mut bus = VirtualLockstepBus::new(FaultModel::none(), 1);
    let mut out = rollbase_driver::frame::FrameBuf::new();
    let mut pending: Vec<(Duration, CanFrame)> = Vec::with_capacity(64);
    let mut rx: Vec<(f64, CanFrame)> = Vec::with_capacity(64);
    let mut got = Vec::with_capacity(64);
    let (mut t_sim, mut t_bus, mut t_core) = (0.0, 0.0, 0.0);
    let total = Instant::now();
    core.arm();
    let mut k = 0;
    while k < max && !core.done() {
        let t0 = Duration::from_secs_f64(k as f64 * p.dt());
        let tw = Duration::from_secs_f64(k as f64 * p.dt() + 0.002);
        let a = Instant::now();
        sim.advance_to(t0);
        t_sim += a.elapsed().as_secs_f64();
        let a = Instant::now();
        bus.set_time(t0);
        t_bus += a.elapsed().as_secs_f64();
        let a = Instant::now();
        core.start_cycle(t0.as_secs_f64(), &mut out);
        t_core += a.elapsed().as_secs_f64();
        let a = Instant::now();
        for f in out.as_slice() {
            let _ = bus.controller_send(f);
        }
        got.clear();
        while let Ok(Some(f)) = bus.peer_recv() {
            got.push(f);
        }
        t_bus += a.elapsed().as_secs_f64();
        let a = Instant::now();
        for f in &got {
            LockstepPeer::on_frame(&mut sim, f.timestamp, &f.frame);
        }
        sim.advance_to(tw);
        sim.drain_tx(&mut |t, f| pending.push((t, f)));
        t_sim += a.elapsed().as_secs_f64();
        let a = Instant::now();
        pending.sort_by_key(|x| x.0);
        for (t, f) in pending.drain(..) {
            bus.set_time(t.min(tw));
            let _ = bus.peer_send(&f);
        }
        bus.set_time(tw);
        rx.clear();
        while let Ok(Some(f)) = bus.controller_recv() {
            rx.push((f.timestamp.as_secs_f64(), f.frame));
        }
        t_bus += a.elapsed().as_secs_f64();
        let a = Instant::now();
        for (t, f) in &rx {
            core.on_frame(f, *t);
        }
        core.finish_cycle(tw.as_secs_f64(), &mut out);
        t_core += a.elapsed().as_secs_f64();
        let a = Instant::now();
        for f in out.as_slice() {
            let _ = bus.controller_send(f);
        }
        got.clear();
        while let Ok(Some(f)) = bus.peer_recv() {
            got.push(f);
        }
        t_bus += a.elapsed().as_secs_f64();
        let a = Instant::now();
        for f in &got {
            LockstepPeer::on_frame(&mut sim, f.timestamp, &f.frame);
        }
        t_sim += a.elapsed().as_secs_f64();
        k += 1;
    }
    Ok(([t_sim, t_bus, t_core, total.elapsed().as_secs_f64()], k))
}

// ---------------------------------------------------------------- the report

fn sh(cmd: &str, args: &[&str]) -> String {
    Command::new(cmd)
        .args(args)
        .output()
        .ok()
        .filter(|o| o.status.success())
        .map(|o| String::from_utf8_lossy(&o.stdout).trim().to_string())
        .unwrap_or_else(|| format!("({cmd} unavailable)"))
}

fn child(mode: &str, cycles: u64) -> Result<Value, String> {
    let exe = std::env::current_exe().map_err(|e| format!("own executable: {e}"))?;
    let out = Command::new(exe)
        .args([mode, &cycles.to_string()])
        .output()
        .map_err(|e| format!("cannot run the {mode}: {e}"))?;
    if !out.status.success() {
        return Err(format!(
            "{mode} failed: {}",
            String::from_utf8_lossy(&out.stderr).trim()
        ));
    }
    serde_json::from_slice(&out.stdout).map_err(|e| format!("{mode} output: {e}"))
}

fn met(ok: bool) -> &'static str {
    if ok {
        "**met**"
    } else {
        "**not met**"
    }
}

fn f(v: &Value) -> f64 {
    v.as_f64().unwrap_or(f64::NAN)
}

fn report(o: &Options) -> Result<(), String> {
    let started = Instant::now();
    let load_start = sh("cat", &["/proc/loadavg"]);
    let mut md = String::new();
    let w = &mut md;
    let p = Platform::justin();

    // Real time first, on a quiet process: our cycle, then the baseline.
    eprintln!(
        "perf-report: real-time run, {} cycles ({:.0} s)…",
        o.cycles,
        o.cycles as f64 * 0.004
    );
    // Ours and the baseline alternate in blocks so both see the same background load on a
    // shared machine (the baseline's scheduling follows what the runtime got).
    let blocks = BLOCKS.min(o.cycles / 100).max(1);
    let per_block = o.cycles.div_ceil(blocks);
    let mut rt_parts = Vec::new();
    let mut base_parts = Vec::new();
    let mut base_note = String::new();
    let mut use_cyclictest = true;
    for b in 0..blocks {
        eprintln!(
            "perf-report: block {}/{blocks}: runtime, {per_block} cycles…",
            b + 1
        );
        let rt = child("realtime-child", per_block)?;
        let fifo = rt["setup"].as_array().is_some_and(|s| {
            s.iter()
                .any(|l| l.as_str().is_some_and(|l| l.contains("runs SCHED_FIFO")))
        });
        rt_parts.push(rt);
        eprintln!("perf-report: block {}/{blocks}: baseline…", b + 1);
        let base = if use_cyclictest {
            match cyclictest(per_block, fifo) {
                Ok(v) => v,
                Err(e) => {
                    eprintln!("perf-report: {e}; using the clock_nanosleep loop");
                    base_note = format!("cyclictest could not run ({e}), ");
                    use_cyclictest = false;
                    child("nanosleep-child", per_block)?
                }
            }
        } else {
            child("nanosleep-child", per_block)?
        };
        base_parts.push(base);
    }
    let rt = merge(&rt_parts);
    let base = merge(&base_parts);

    // Lockstep speed.
    eprintln!("perf-report: lockstep runs…");
    let mut rtf = Vec::new();
    let mut step_share = Vec::new();
    let mut last = None;
    for _ in 0..5 {
        let r = run(&RunOptions::new(Scenario::Seed000));
        let platform_s = r.report.cycles as f64 * p.dt();
        rtf.push(platform_s / r.report.wall_s);
        step_share.push(r.report.compute_total_s / r.report.wall_s);
        last = Some((
            r.report.cycles,
            platform_s,
            r.report.wall_s,
            r.summary.to_json(),
        ));
    }
    let (ls_cycles, ls_platform_s, ls_wall_s, ls_summary) = last.ok_or("no lockstep run")?;
    let rtf_med = percentile(&rtf, 50.0);
    let (bd, bd_cycles) = lockstep_breakdown(&p)?;

    // Criterion figures.
    let crit = |id: &str| criterion_median(&o.criterion, id);
    let allocs = alloc_counts(&o.bench_logs);

    // ---- write
    writeln!(w, "# rollbase performance report").ok();
    writeln!(w).ok();
    writeln!(
        w,
        "Generated by `benches/report.sh` (criterion benchmarks, then `perf-report`); every figure \
         below comes from that one run, each beside its reference. Do not edit by hand: rerun \
         `benches/report.sh`."
    )
    .ok();
    writeln!(w).ok();

    // Targets.
    let dfl = crit("control_step/dfl_avoid_odom_seed000");
    let dfl_allocs = allocs
        .iter()
        .find(|a| a.0 == "control_step/dfl_avoid_odom_seed000");
    let core_allocs = allocs.iter().find(|a| a.0 == "cycle_core/whole_cycle");
    let jit_ours = f(&rt["jitter_us"]["p99"]);
    let jit_base = f(&base["jitter_us"]["p99"]);
    let ratio = jit_ours / jit_base;
    let rt_wall = f(&rt["wall_s"]);
    let ctl_cpu = (f(&rt["cycle_thread_cpu_s"]) + f(&rt["recorder_cpu_s"])) / rt_wall * 100.0;
    let cyc_cpu = f(&rt["cycle_thread_cpu_s"]) / rt_wall * 100.0;
    let proc_cpu = f(&rt["process_cpu_s"]) / f(&rt["process_wall_s"]) * 100.0;
    let sim_cpu = f(&rt["simulator_cpu_s"]) / rt_wall * 100.0;
    writeln!(w, "## Targets").ok();
    writeln!(w).ok();
    writeln!(w, "| target | measured | reference | result |").ok();
    writeln!(w, "|---|---|---|---|").ok();
    match dfl {
        Some(e) => writeln!(
            w,
            "| control step (DFL + avoidance + odometry, 4 wheels), median | {:.2} µs | ≤ 10 µs | {} |",
            e.median_ns / 1e3,
            met(e.median_ns <= 10_000.0)
        ),
        None => writeln!(
            w,
            "| control step (DFL + avoidance + odometry, 4 wheels), median | not measured (criterion results missing) | ≤ 10 µs | **not met** |"
        ),
    }
    .ok();
    let alloc_text = |a: Option<&(String, u64, u64)>| match a {
        Some((_, n, s)) => (format!("{n} in {s} steps"), *n == 0),
        None => ("not measured (bench log missing)".into(), false),
    };
    let (t1, ok1) = alloc_text(dfl_allocs);
    let (t2, ok2) = alloc_text(core_allocs);
    writeln!(
        w,
        "| allocations per control step / per whole cycle (CycleCore) | {t1} / {t2} | 0 | {} |",
        met(ok1 && ok2)
    )
    .ok();
    writeln!(
        w,
        "| lockstep, seed-000 scenario, full frame path | {:.0}× real time (median of 5) | ≥ 500× | {} |",
        rtf_med,
        met(rtf_med >= 500.0)
    )
    .ok();
    writeln!(
        w,
        "| period jitter p99, ours / baseline | {:.0} µs / {:.0} µs = {:.2} | ≤ 1.5 | {} |",
        jit_ours,
        jit_base,
        ratio,
        met(ratio <= 1.5)
    )
    .ok();
    writeln!(
        w,
        "| CPU at 250 Hz, controller (cycle thread + recorder) | {:.2} % of one core | ≤ 3 % | {} |",
        ctl_cpu,
        met(ctl_cpu <= 3.0)
    )
    .ok();
    writeln!(w).ok();

    // Codec.
    writeln!(w, "## Codec").ok();
    writeln!(w).ok();
    writeln!(
        w,
        "One control cycle's frames: SYNC + 4 SETPOINT + 8 feedback (FEEDBACK_A/B per module), \
         `driver/benches/codec.rs`. Criterion median with its 95 % confidence interval; the \
         reference is the 4 ms cycle."
    )
    .ok();
    writeln!(w).ok();
    writeln!(
        w,
        "| benchmark | median | 95 % CI | share of the 4 ms cycle |"
    )
    .ok();
    writeln!(w, "|---|---|---|---|").ok();
    let row = |w: &mut String, id: &str, what: &str| {
        match crit(id) {
            Some(e) => writeln!(
                w,
                "| {what} (`{id}`) | {:.0} ns | {:.0}–{:.0} ns | {:.4} % |",
                e.median_ns,
                e.lo_ns,
                e.hi_ns,
                e.median_ns / 4e6 * 100.0
            ),
            None => writeln!(w, "| {what} (`{id}`) | not measured | | |"),
        }
        .ok();
    };
    row(w, "codec/cycle_encode_decode", "encode 13 + decode 13");
    row(w, "codec/cycle_encode", "encode 13");
    row(w, "codec/cycle_decode", "decode 13");
    row(
        w,
        "codec/cycle_receiver",
        "receive path on the 8 feedback frames (decode, CRC, counters)",
    );
    writeln!(w).ok();

    // Control step.
    writeln!(w, "## Control step").ok();
    writeln!(w).ok();
    writeln!(
        w,
        "`tests/benches/control_step.rs`: inputs recorded from a closed loop against the ideal \
         plant, replayed step by step (controller states evolve as in the run). Odometry → \
         avoidance → controller in the order `CycleCore::finish_cycle` runs them. \
         `tests/benches/cycle_core.rs` times the whole controller side of a cycle on the full \
         frame path (simulator and virtual bus outside the timed region). Reference: 10 µs \
         target, 4 ms cycle."
    )
    .ok();
    writeln!(w).ok();
    writeln!(
        w,
        "| benchmark | median | 95 % CI | share of the 4 ms cycle |"
    )
    .ok();
    writeln!(w, "|---|---|---|---|").ok();
    for (id, what) in [
        (
            "control_step/dfl_avoid_odom_seed000",
            "DFL + avoidance + odometry, seed 000",
        ),
        (
            "control_step/kinematic_avoid_odom_seed000",
            "kinematic + avoidance + odometry, seed 000",
        ),
        (
            "control_step/kinematic_avoid_odom_seed001",
            "kinematic + avoidance + odometry, seed 001 (avoidance acting)",
        ),
        ("control_step/dfl_only_seed000", "DFL controller alone"),
        (
            "control_step/kinematic_only_seed000",
            "kinematic controller alone",
        ),
        ("control_step/odometry_only_seed000", "odometry alone"),
        (
            "control_step/avoidance_only_seed001",
            "avoidance alone, seed 001",
        ),
        (
            "cycle_core/whole_cycle",
            "CycleCore: start_cycle + 8 × on_frame + finish_cycle",
        ),
        (
            "cycle_core/feedback_and_finish",
            "CycleCore: 8 × on_frame + finish_cycle",
        ),
    ] {
        row(w, id, what);
    }
    writeln!(w).ok();
    writeln!(
        w,
        "Heap allocations counted by a counting global allocator inside the timed code (one full \
         replay of each recording; the whole seed-000 scenario for the cycle core):"
    )
    .ok();
    writeln!(w).ok();
    writeln!(w, "| benchmark | allocations | steps |").ok();
    writeln!(w, "|---|---|---|").ok();
    if allocs.is_empty() {
        writeln!(w, "| (no bench log given) | | |").ok();
    }
    for (id, n, s) in &allocs {
        writeln!(w, "| `{id}` | {n} | {s} |").ok();
    }
    writeln!(w).ok();

    // Live commands (base service).
    w.push_str(&live_section(o));
    writeln!(w).ok();

    // Lockstep.
    writeln!(w, "## Lockstep speed").ok();
    writeln!(w).ok();
    writeln!(
        w,
        "`rollbase_tests::run(RunOptions::new(Scenario::Seed000))`: the whole seed-000 scenario \
         (alignment, ≈31 s trajectory, stop) through encode → virtual bus → simulated modules \
         and plant → virtual bus → decode, on virtual time, every record kept. Five runs."
    )
    .ok();
    writeln!(w).ok();
    writeln!(
        w,
        "| figure | value | reference |\n|---|---|---|\n\
         | cycles per run | {ls_cycles} ({ls_platform_s:.2} s of platform time) | |\n\
         | wall time per run (last) | {:.3} s | |\n\
         | real-time factor, median (min–max) | {:.0}× ({:.0}–{:.0}) | ≥ 500× |\n\
         | share of wall time in `finish_cycle` (median) | {:.1} % | the rest is simulator, bus, decode, records |\n\
         | max position error of the run (sanity) | {:.4} m | |",
        ls_wall_s,
        rtf_med,
        percentile(&rtf, 0.0),
        percentile(&rtf, 100.0),
        percentile(&step_share, 50.0) * 100.0,
        f(&ls_summary["max_position_error_m"])
    )
    .ok();
    writeln!(w).ok();
    writeln!(
        w,
        "Where the time goes (one more run, {bd_cycles} cycles, same loop shape as \
         `run_lockstep`, no records kept; `Instant` around each part, so the parts include \
         some timer overhead): simulator (plant, firmware emulation) {:.1} %, virtual bus \
         (clock, queues, fault injector, wake-up notifications) {:.1} %, controller core {:.1} \
         %, rest {:.1} %; {:.0}× real time without records and per-cycle timing. The \
         controller core alone would run the scenario at {:.0}× real time.",
        100.0 * bd[0] / bd[3],
        100.0 * bd[1] / bd[3],
        100.0 * bd[2] / bd[3],
        100.0 * (bd[3] - bd[0] - bd[1] - bd[2]) / bd[3],
        bd_cycles as f64 * p.dt() / bd[3],
        bd_cycles as f64 * p.dt() / bd[2]
    )
    .ok();
    writeln!(w).ok();

    // Real time.
    writeln!(w, "## Cycle timing in real time").ok();
    writeln!(w).ok();
    writeln!(
        w,
        "`runtime::run_realtime` with the seed-000 scenario on the wall-clock `VirtualBus`, the \
         simulator in its own thread (`Simulator::run_realtime`), records to a recorder thread \
         over the bounded channel; {} cycles in {} blocks, each a child process ({} seed-000 \
         session(s) in all: a finished scenario is followed by a fresh one). Jitter = |period − \
         4 ms| between consecutive wake-ups; latency = wake-up − absolute deadline. The \
         baseline alternates with ours block by block in the same run, so both see the same \
         background load: {}`{}` per block.",
        f(&rt["cycles"]),
        f(&rt["blocks"]),
        f(&rt["sessions"]),
        base_note,
        base["tool"].as_str().unwrap_or("?")
    )
    .ok();
    writeln!(w).ok();
    let setup = |v: &Value| {
        v["setup"]
            .as_array()
            .map(|a| {
                a.iter()
                    .filter_map(|s| s.as_str())
                    .collect::<Vec<_>>()
                    .join("; ")
            })
            .unwrap_or_default()
    };
    writeln!(w, "Runtime setup: {}.  ", setup(&rt)).ok();
    writeln!(w, "Baseline setup: {}.", setup(&base)).ok();
    writeln!(w).ok();
    writeln!(w, "| µs | ours p50 | ours p99 | ours max | baseline p50 | baseline p99 | baseline max | p99 ratio |").ok();
    writeln!(w, "|---|---|---|---|---|---|---|---|").ok();
    for (k, name) in [
        ("jitter_us", "period jitter"),
        ("latency_us", "wake-up latency"),
    ] {
        writeln!(
            w,
            "| {name} | {:.0} | {:.0} | {:.0} | {:.0} | {:.0} | {:.0} | {:.2} |",
            f(&rt[k]["p50"]),
            f(&rt[k]["p99"]),
            f(&rt[k]["max"]),
            f(&base[k]["p50"]),
            f(&base[k]["p99"]),
            f(&base[k]["max"]),
            f(&rt[k]["p99"]) / f(&base[k]["p99"])
        )
        .ok();
    }
    writeln!(
        w,
        "| compute (feedback collected → setpoints sent) | {:.0} | {:.0} | {:.0} | | | | |",
        f(&rt["compute_us"]["p50"]),
        f(&rt["compute_us"]["p99"]),
        f(&rt["compute_us"]["max"])
    )
    .ok();
    writeln!(w).ok();
    writeln!(
        w,
        "Deadline misses counted by the runtime: {}; records dropped: {}.",
        f(&rt["deadline_misses"]),
        f(&rt["records_dropped"])
    )
    .ok();
    writeln!(w).ok();

    // CPU and memory.
    writeln!(w, "## CPU and memory at 250 Hz").ok();
    writeln!(w).ok();
    writeln!(
        w,
        "getrusage (user + sys) per thread over the real-time run above ({:.1} s of run), per \
         second of run; the simulator stands in for the wheel modules and is not part of the \
         controller's cost.",
        rt_wall
    )
    .ok();
    writeln!(w).ok();
    writeln!(
        w,
        "| figure | value | reference |\n|---|---|---|\n\
         | cycle thread | {cyc_cpu:.2} % of one core | |\n\
         | controller (cycle thread + recorder thread) | {ctl_cpu:.2} % of one core | ≤ 3 % |\n\
         | simulator thread | {sim_cpu:.2} % of one core | (test peer) |\n\
         | whole child process (controller + simulator + setup) | {proc_cpu:.2} % of one core | |\n\
         | peak resident memory (VmHWM) of the child process | {:.0} kB | |",
        f(&rt["vm_hwm_kb"])
    )
    .ok();
    writeln!(w).ok();

    // Bus load.
    bus_section(w)?;

    // Machine.
    writeln!(w, "## Machine").ok();
    writeln!(w).ok();
    let lscpu = sh("lscpu", &[]);
    let keep = [
        "Architecture",
        "CPU(s)",
        "Model name",
        "Thread(s) per core",
        "Core(s) per socket",
        "CPU max MHz",
        "BogoMIPS",
        "Hypervisor vendor",
        "Virtualization type",
        "L2 cache",
        "L3 cache",
    ];
    writeln!(w, "```text").ok();
    for l in lscpu.lines() {
        if keep
            .iter()
            .any(|k| l.trim_start().starts_with(&format!("{k}:")))
        {
            writeln!(w, "{}", l.trim()).ok();
        }
    }
    writeln!(w, "kernel: {}", sh("uname", &["-srvm"])).ok();
    writeln!(w, "{}", sh("rustc", &["-V"])).ok();
    writeln!(w, "{}", sh("cargo", &["-V"])).ok();
    let gov = std::fs::read_to_string("/sys/devices/system/cpu/cpu0/cpufreq/scaling_governor")
        .map(|s| s.trim().to_string())
        .unwrap_or_else(|_| "not exposed".into());
    writeln!(w, "cpufreq governor: {gov}").ok();
    writeln!(w, "load average at the start of perf-report: {load_start}").ok();
    writeln!(
        w,
        "load average at the end: {}",
        sh("cat", &["/proc/loadavg"])
    )
    .ok();
    writeln!(w, "```").ok();
    writeln!(w).ok();
    writeln!(
        w,
        "Report generation took {:.0} s (plus the benchmarks).",
        started.elapsed().as_secs_f64()
    )
    .ok();

    if let Some(dir) = o.out.parent().filter(|d| !d.as_os_str().is_empty()) {
        std::fs::create_dir_all(dir).map_err(|e| format!("{}: {e}", dir.display()))?;
    }
    // The ROS 2 sections are written by `ros2-perf` and from interop/test_ros2_fleet.py (they
    // need network namespaces): keep them.
    if let Ok(old) = std::fs::read_to_string(&o.out) {
        for (begin, end) in [
            ("<!-- ros2-perf:begin -->", "<!-- ros2-perf:end -->"),
            ("<!-- ros2-fleet:begin -->", "<!-- ros2-fleet:end -->"),
        ] {
            if let (Some(b), Some(e)) = (old.find(begin), old.find(end)) {
                if e > b {
                    md.push('\n');
                    md.push_str(&old[b..e + end.len()]);
                    md.push('\n');
                }
            }
        }
    }
    std::fs::write(&o.out, &md).map_err(|e| format!("{}: {e}", o.out.display()))?;
    print!("{md}");
    eprintln!("perf-report: wrote {}", o.out.display());
    Ok(())
}

const LIVE_BEGIN: &str = "<!-- live:begin -->";
const LIVE_END: &str = "<!-- live:end -->";

/// `STEPTIME <id> <p50 ns> <p99 ns> <max ns> <steps> [<step of the max>]` lines of the bench
/// logs.
fn step_times(logs: &[PathBuf]) -> Vec<(String, [f64; 3], u64, Option<u64>)> {
    let mut v = Vec::new();
    for l in logs {
        let Ok(text) = std::fs::read_to_string(l) else {
            continue;
        };
        for line in text.lines() {
            let f: Vec<&str> = line.split_whitespace().collect();
            if f.len() >= 6 && f[0] == "STEPTIME" {
                if let (Ok(a), Ok(b), Ok(c), Ok(n)) =
                    (f[2].parse(), f[3].parse(), f[4].parse(), f[5].parse())
                {
                    v.push((
                        f[1].to_string(),
                        [a, b, c],
                        n,
                        f.get(6).and_then(|k| k.parse().ok()),
                    ));
                }
            }
        }
    }
    v
}

/// The base service's section (between its markers): the live benchmark's medians, per-step
/// percentiles and allocations, with the machine and load it ran on.
fn live_section(o: &Options) -> String {
    let mut md = String::new();
    let w = &mut md;
    let allocs = alloc_counts(&o.bench_logs);
    let times = step_times(&o.bench_logs);
    writeln!(w, "{LIVE_BEGIN}").ok();
    writeln!(w, "## Live commands (base service)").ok();
    writeln!(w).ok();
    writeln!(
        w,
        "`tests/benches/live.rs`: what `rollbase drive` computes per cycle while following live \
         commands. A 30 s session of random commands (a new twist every 1–2.5 s, up to 2 m/s \
         and 3 rad/s, so most are beyond the limits and shaped; leg targets with some; each \
         repeated every 0.2 s like a live sender) is recorded from a closed loop against the \
         ideal plant and replayed: the shaper gets the same commands at the same cycles, \
         avoidance runs on the shaped reference, the controller (DFL while the reference \
         moves, the kinematic controller near rest, as `CycleCore` switches them) sees the \
         recorded measurements. The last row is the whole controller side of a live cycle on \
         the full frame path against the simulated modules (`CycleCore::new_live`, `drive`'s \
         default: avoidance off): command port, SYNC, 8 feedback frames, `finish_cycle` \
         (decode, odometry, shaper, controller, supervisor, output guard, encode, record, \
         state port). Criterion median with its 95 % confidence interval; each criterion \
         sample runs many consecutive cycles of the session, so this is the mean cost of a \
         cycle over the session (the few expensive planning steps spread over the rest); \
         reference: the 4 ms cycle."
    )
    .ok();
    writeln!(w).ok();
    writeln!(
        w,
        "| benchmark | median | 95 % CI | share of the 4 ms cycle |\n|---|---|---|---|"
    )
    .ok();
    for (id, what) in [
        (
            "live/shaper_avoid_control",
            "shaper + avoidance + controller (`drive --avoidance on`)",
        ),
        (
            "live/shaper_control",
            "shaper + controller (`drive`'s default)",
        ),
        ("live/shaper_only", "shaper alone"),
        (
            "live/cycle_core_whole_cycle",
            "CycleCore (live): command port + start_cycle + 8 × on_frame + finish_cycle",
        ),
    ] {
        match criterion_median(&o.criterion, id) {
            Some(e) => writeln!(
                w,
                "| {what} (`{id}`) | {:.2} µs | {:.2}–{:.2} µs | {:.3} % |",
                e.median_ns / 1e3,
                e.lo_ns / 1e3,
                e.hi_ns / 1e3,
                e.median_ns / 4e6 * 100.0
            ),
            None => writeln!(w, "| {what} (`{id}`) | not measured | | |"),
        }
        .ok();
    }
    writeln!(w).ok();
    flow_rows(w, o);
    writeln!(w).ok();
    writeln!(
        w,
        "The work is uneven: a new goal plans a transition (its grid is refined where a \
         wheel's steering turns fastest), the cycles after it only sample the plan. Every \
         step timed alone (two `Instant` readings around it) in 5 replays of the session, \
         each step's minimum over them kept (a preemption by other work on the machine seldom \
         hits the same step in all five), so the maximum is the most expensive step's own \
         cost, plus what preemption is left on a busy machine (see the load average below; \
         the step it was found at is the same across the rows when it is the plan's cost):"
    )
    .ok();
    writeln!(w).ok();
    writeln!(
        w,
        "| benchmark | p50 | p99 | max (at step) | steps | allocations |\n|---|---|---|---|---|---|"
    )
    .ok();
    if times.is_empty() {
        writeln!(w, "| (no live bench log given) | | | | | |").ok();
    }
    for (id, [p50, p99, max], n, at) in &times {
        let a = allocs
            .iter()
            .find(|a| &a.0 == id)
            .map_or("not counted".to_string(), |a| {
                format!("{} in {} steps", a.1, a.2)
            });
        let at = at.map(|k| format!(" ({k})")).unwrap_or_default();
        writeln!(
            w,
            "| `{id}` | {:.2} µs | {:.2} µs | {:.2} µs{at} | {n} | {a} |",
            p50 / 1e3,
            p99 / 1e3,
            max / 1e3
        )
        .ok();
    }
    writeln!(w).ok();
    let model = sh("lscpu", &[])
        .lines()
        .find_map(|l| {
            l.trim()
                .strip_prefix("Model name:")
                .map(|m| m.trim().to_string())
        })
        .unwrap_or_else(|| "unknown CPU".into());
    // The load when the benchmark started (its `LOADAVG` line), else now.
    let load = o
        .bench_logs
        .iter()
        .filter_map(|l| std::fs::read_to_string(l).ok())
        .find_map(|t| {
            t.lines()
                .find_map(|l| l.strip_prefix("LOADAVG ").map(|x| x.trim().to_string()))
        })
        .map(|l| format!("load average when the benchmark started: {l}"))
        .unwrap_or_else(|| {
            format!(
                "load average when this section was written: {}",
                sh("cat", &["/proc/loadavg"])
            )
        });
    writeln!(
        w,
        "Machine: {model}, {} CPU(s), {}; {load}.",
        sh("nproc", &[]),
        sh("rustc", &["-V"])
    )
    .ok();
    writeln!(w, "{LIVE_END}").ok();
    md
}

/// Issue 23's benchmarks (`tests/benches/flow.rs`): the shaper with a new goal every cycle
/// and the planning of a 60-waypoint file, criterion medians and allocations.
fn flow_rows(w: &mut String, o: &Options) {
    let allocs = alloc_counts(&o.bench_logs);
    writeln!(
        w,
        "`tests/benches/flow.rs` (issue 23): the shaper alone with a command that changes every \
         cycle — a noisy joystick (the stick model of `rollbase_tests::flow`, σ = 0.05 m/s, 2σ \
         rad/s on ω) sampled at 250 Hz, 30 s then the release to rest, one `Shaper::command` \
         and one `Shaper::step` per cycle — and the planning of a 60-waypoint file \
         (`flow::waypoint_tour`: about 20 m, legs moving now and then, every tenth waypoint \
         untimed; spline and `ScaledTrajectory::plan` with the default time scaling), done \
         once before a trajectory run starts (it allocates; the cycle does not)."
    )
    .ok();
    writeln!(w).ok();
    writeln!(
        w,
        "| benchmark | median | 95 % CI | allocations |\n|---|---|---|---|"
    )
    .ok();
    for (id, what, unit) in [
        (
            "flow/shaper_joystick_every_cycle",
            "shaper, a new goal every cycle (per cycle)",
            1e3,
        ),
        (
            "flow/shaper_rolling_joystick_every_cycle",
            "the same with rolling turns (experimental; per cycle)",
            1e3,
        ),
        (
            "flow/plan_60_waypoints",
            "planning a 60-waypoint file (once per run)",
            1e6,
        ),
    ] {
        // The plan is built once before a run and allocates by design: not counted.
        let a = allocs
            .iter()
            .find(|a| a.0 == id)
            .map_or("— (built once, before the run)".to_string(), |a| {
                format!("{} in {} steps", a.1, a.2)
            });
        let u = if unit == 1e3 { "µs" } else { "ms" };
        match criterion_median(&o.criterion, id) {
            Some(e) => writeln!(
                w,
                "| {what} (`{id}`) | {:.2} {u} | {:.2}–{:.2} {u} | {a} |",
                e.median_ns / unit,
                e.lo_ns / unit,
                e.hi_ns / unit,
            ),
            None => writeln!(w, "| {what} (`{id}`) | not measured | | {a} |"),
        }
        .ok();
    }
}

/// `--section live`: the live section of the existing report replaced (or inserted before
/// "## Lockstep speed"), the rest of the file unchanged.
fn update_live_section(o: &Options) -> Result<(), String> {
    let old = std::fs::read_to_string(&o.out).map_err(|e| {
        format!(
            "{}: {e} (--section rewrites a section of an existing report)",
            o.out.display()
        )
    })?;
    let section = live_section(o);
    let new = match (old.find(LIVE_BEGIN), old.find(LIVE_END)) {
        (Some(b), Some(e)) if e > b => {
            format!(
                "{}{}{}",
                &old[..b],
                section.trim_end(),
                &old[e + LIVE_END.len()..]
            )
        }
        _ => match old.find("## Lockstep speed") {
            Some(at) => format!("{}{section}\n{}", &old[..at], &old[at..]),
            None => format!("{}\n{section}", old.trim_end()),
        },
    };
    std::fs::write(&o.out, &new).map_err(|e| format!("{}: {e}", o.out.display()))?;
    print!("{section}");
    eprintln!(
        "perf-report: rewrote the live section of {}",
        o.out.display()
    );
    Ok(())
}

fn bus_section(w: &mut String) -> Result<(), String> {
    let cfg = BusLoadConfig::default();
    let r = bus_load(&cfg).map_err(|e| format!("bus load: {e}"))?;
    let n = cfg.modules as u32;
    let per_cycle_s = 1.0 / cfg.cycle_hz;
    let sync = signal_bits(MessageKind::Sync);
    let sp = signal_bits(MessageKind::Setpoint);
    let fb = signal_bits(MessageKind::FeedbackA) + signal_bits(MessageKind::FeedbackB);
    let st = signal_bits(MessageKind::Status);
    let (sync_f, sync_b) = min_frames_bits(sync);
    let (sp_f, sp_b) = min_frames_bits(sp);
    let (fb_f, fb_b) = min_frames_bits(fb);
    let (_, st_b) = min_frames_bits(st);
    let min_cycle = sync_b + n * (sp_b + fb_b);
    let bitrate = f64::from(cfg.bitrate);
    let avail = bitrate * per_cycle_s;
    let info_cycle = sync + n * (sp + fb);
    let status_per_s = f64::from(n) * cfg.status_hz;
    let ours_status = r
        .rows
        .iter()
        .find(|x| x.name == "STATUS")
        .map_or(0.0, |x| x.bits_per_s);
    let min_total = f64::from(min_cycle) * cfg.cycle_hz + status_per_s * f64::from(st_b);
    writeln!(w, "## Bus load").ok();
    writeln!(w).ok();
    writeln!(
        w,
        "From `rollbase_driver::busload` ({} modules, {} Hz, {} bit/s, STATUS {} Hz per module; \
         worst-case bit stuffing, `frame_bits(n) = 8n + 47 + ⌊(33 + 8n)/4⌋`).",
        cfg.modules, cfg.cycle_hz, cfg.bitrate, cfg.status_hz
    )
    .ok();
    writeln!(w).ok();
    writeln!(w, "{r}").ok();
    writeln!(w).ok();
    writeln!(
        w,
        "**The least any protocol carrying the same signals needs.** Signals are the values, \
         flags and enums of the protocol table at their declared widths (ranges and \
         resolutions unchanged); rolling counters and CRCs are integrity overhead and are left \
         out. Per cycle: SYNC's cycle number ({sync} bit), per module the setpoint ({sp} bit: two \
         16-bit rates and three flags) and the feedback ({fb} bit: FEEDBACK_A's three 16-bit \
         values, FEEDBACK_B's two 16-bit and two 8-bit values). Packed with no gaps, each \
         direction of each module in as few classic frames as the bits allow (a frame carries \
         at most 64 bit): SYNC {sync_f} frame of {} byte(s), setpoint {sp_f} frame of {} bytes, \
         feedback {} bit = {} bytes > 8, so {fb_f} frames (8 + {} bytes) — one frame per module \
         per direction is impossible on classic CAN for the feedback; a CAN FD frame of 12 \
         bytes would do it. Every frame costs the same worst-case `frame_bits` as ours. STATUS: \
         {st} bit in one frame at the same rate.",
        sync.div_ceil(8),
        sp.div_ceil(8),
        fb,
        fb.div_ceil(8),
        fb.div_ceil(8) - 8,
    )
    .ok();
    writeln!(w).ok();
    writeln!(
        w,
        "| per 4 ms cycle | ours | minimum, framed | signal bits alone (no framing) |\n|---|---|---|---|\n\
         | cyclic bits | {} | {} | {} |\n\
         | cyclic load | {:.2} % | {:.2} % | {:.2} % |\n\
         | total load incl. STATUS | {:.2} % | {:.2} % | |\n\
         | ours / minimum framed (cyclic) | {:.3} | | |",
        r.cyclic_bits_per_cycle,
        min_cycle,
        info_cycle,
        r.cyclic_percent,
        100.0 * f64::from(min_cycle) / avail,
        100.0 * f64::from(info_cycle) / avail,
        r.total_percent,
        100.0 * min_total / bitrate,
        f64::from(r.cyclic_bits_per_cycle) / f64::from(min_cycle)
    )
    .ok();
    writeln!(w).ok();
    writeln!(
        w,
        "Where ours spends the difference: SYNC's 4-bit counter + CRC-8 (one more byte), the \
         SETPOINT's counter + CRC (one more byte), and the feedback split as 8 + 8 bytes instead \
         of 8 + 4 (counter + CRC in both frames, and FEEDBACK_B's spare bits). STATUS costs \
         {:.0} bit/s of ours.",
        ours_status
    )
    .ok();
    writeln!(w).ok();
    Ok(())
}
