//! What every real-time run does around the cycle thread: the thread itself, the recorder on
//! the calling thread (a failed write stops the run in a controlled way), the in-process
//! simulator of the demos, and the report.

use rollbase_control::model::platform::MAX_BUSES;
use rollbase_control::runtime::record::CycleRecord;
use rollbase_control::runtime::{
    run_realtime_buses, CommandReceiver, CycleCore, RealtimeIo, RealtimeOptions, RealtimeReport,
};
use rollbase_control::service::ports::{BaseState, CanBusDiagnostics};
use rollbase_driver::bus::BusEvent;
use rollbase_driver::bus::CanBus;
use rollbase_vcan_sim::Simulator;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::mpsc::{Receiver, RecvTimeoutError, SyncSender, TryRecvError};
use std::sync::Arc;
use std::time::{Duration, Instant};

use super::common::CliError;
use super::sinks::Sinks;

/// Records queued between the cycle thread and the recorder (about 8 s at 250 Hz).
pub(crate) const RECORD_QUEUE: usize = 2048;

/// How often a consumer of the cycle's channels looks for a value ([`poll_recv`]).
const POLL: Duration = Duration::from_millis(1);

/// The next value of a channel the cycle thread sends on, waiting at most `within`, without
/// ever blocking in the channel itself: a receiver blocked in `recv` registers with the
/// channel's waker, and the sender's `try_send` then takes that waker's mutex to wake it. The
/// cycle thread (SCHED_FIFO) would share a lock with this normal-priority thread and wait
/// whenever a busy machine preempts it while it holds the lock. Polling (every [`POLL`])
/// leaves the waker empty, so the cycle's `try_send` never takes a lock.
pub(crate) fn poll_recv<T>(rx: &Receiver<T>, within: Duration) -> Result<T, RecvTimeoutError> {
    let until = Instant::now() + within;
    loop {
        match rx.try_recv() {
            Ok(v) => return Ok(v),
            Err(TryRecvError::Disconnected) => return Err(RecvTimeoutError::Disconnected),
            Err(TryRecvError::Empty) => {
                let now = Instant::now();
                if now >= until {
                    return Err(RecvTimeoutError::Timeout);
                }
                std::thread::sleep(POLL.min(until - now));
            }
        }
    }
}

/// The channels a real-time run connects to the cycle (besides its records).
#[derive(Default)]
pub(crate) struct Ports<'a> {
    /// Commands in (the base service).
    pub(crate) commands: Option<CommandReceiver>,
    /// State out (the base service's consumers).
    pub(crate) states: Option<&'a SyncSender<BaseState>>,
    /// Run the cycle thread on this CPU only (the in-process simulator's, [`SimThread`]).
    pub(crate) cpu: Option<usize>,
}

/// Restricts the calling thread to `cpu`; a line for the operator either way.
fn pin_to(cpu: usize, who: &str) -> String {
    // SAFETY: a zeroed cpu_set_t is a valid empty set; CPU_SET writes within it for any
    // cpu < CPU_SETSIZE (checked); sched_setaffinity reads it.
    let r = unsafe {
        let mut set: libc::cpu_set_t = std::mem::zeroed();
        if cpu >= libc::CPU_SETSIZE as usize {
            return format!("{who}: CPU {cpu} is beyond the CPU set; not pinned");
        }
        libc::CPU_SET(cpu, &mut set);
        libc::sched_setaffinity(0, std::mem::size_of::<libc::cpu_set_t>(), &set)
    };
    if r == 0 {
        format!("{who} runs on CPU {cpu} only (with the in-process simulator)")
    } else {
        format!(
            "{who}: cannot keep it on CPU {cpu} ({}); it may run on any",
            std::io::Error::last_os_error()
        )
    }
}

/// Runs `core` on `buses` (one per platform bus, `buses[b]` for the wheels with `bus = b`) in
/// real time on its own thread until it is done; the calling thread takes the records into
/// `sinks` and calls `each` with every record (status lines). `stop` (signals, `--duration`)
/// asks for a controlled stop; so does a failed recording, whose error the caller finds in
/// the sinks. A number of buses that differs from the platform's is refused before anything
/// runs.
pub(crate) fn run_cycle(
    core: &mut CycleCore,
    buses: &mut [&mut dyn CanBus],
    sinks: &mut Sinks,
    stop: &Arc<AtomicBool>,
    ports: Ports<'_>,
    origin_unix_s: f64,
    each: &mut dyn FnMut(&CycleRecord, &Sinks),
) -> Result<RealtimeReport, CliError> {
    let (tx, rx) = std::sync::mpsc::sync_channel::<CycleRecord>(RECORD_QUEUE);
    let opts = RealtimeOptions::default();
    let origin_ns = (origin_unix_s.max(0.0) * 1e9) as u64;
    let report = std::thread::scope(|s| {
        let cycle = std::thread::Builder::new()
            .name("rollbase-cycle".into())
            .spawn_scoped(s, move || {
                let pinned = ports.cpu.map(|c| pin_to(c, "cycle thread"));
                let io = RealtimeIo {
                    records: Some(&tx),
                    states: ports.states,
                    commands: ports.commands.as_ref(),
                };
                let r = run_realtime_buses(core, buses, stop, &io, &opts, origin_ns);
                drop(tx);
                r.map(|mut r| {
                    r.setup.extend(pinned);
                    r
                })
            });
        let cycle = match cycle {
            Ok(c) => c,
            Err(e) => {
                return Err(CliError::Usage(format!(
                    "cannot start the cycle thread: {e}"
                )))
            }
        };
        let mut reported = false;
        let mut bus_log = BusEventLog::default();
        loop {
            match poll_recv(&rx, Duration::from_millis(100)) {
                Ok(r) => {
                    for line in bus_log.update(r.t, &r.base.diagnostics.can) {
                        tracing::warn!("{line}");
                    }
                    sinks.take(&r, &r.wheel_xy[..r.n]);
                    if sinks.failed() && !reported {
                        reported = true;
                        if let Some(e) = sinks.error() {
                            tracing::error!("{e}: {}; stopping the platform", error_chain(e));
                        }
                        stop.store(true, Ordering::SeqCst);
                    }
                    each(&r, sinks);
                }
                Err(RecvTimeoutError::Timeout) => {}
                Err(RecvTimeoutError::Disconnected) => break,
            }
        }
        cycle
            .join()
            .map_err(|_| CliError::Usage("the cycle thread panicked".into()))?
            .map_err(|e| CliError::Usage(e.to_string()))
    })?;
    sinks.summary.deadline_misses = sinks.summary.deadline_misses.max(report.deadline_misses);
    Ok(report)
}

/// Logs the CAN controllers' error state changes (warning, error passive, bus-off,
/// restarted) from the records' diagnostics: one line per change, at most one line per bus
/// a second; changes in between are summed up in the next line.
#[derive(Default)]
pub(crate) struct BusEventLog {
    seen: [CanBusDiagnostics; MAX_BUSES],
    last_line: [Option<f64>; MAX_BUSES],
    held: [u32; MAX_BUSES],
}

/// Shortest time between two bus-state log lines of one bus (s).
const BUS_LOG_INTERVAL: f64 = 1.0;

impl BusEventLog {
    /// The lines to log for the diagnostics of a record at `t` (s).
    pub(crate) fn update(&mut self, t: f64, can: &[CanBusDiagnostics]) -> Vec<String> {
        let mut lines = Vec::new();
        for (b, d) in can.iter().enumerate().take(MAX_BUSES) {
            let total = |x: &CanBusDiagnostics| x.events.iter().map(|&n| u64::from(n)).sum::<u64>();
            let new = total(d).saturating_sub(total(&self.seen[b]));
            if new == 0 && self.held[b] == 0 {
                continue;
            }
            self.held[b] = self.held[b].saturating_add(new.min(u64::from(u32::MAX)) as u32);
            if self.last_line[b].is_some_and(|l| t - l < BUS_LOG_INTERVAL) {
                continue;
            }
            let state = d.state.map_or("error active", |e| e.name());
            let more = self.held[b].saturating_sub(1);
            let mut line = format!(
                "CAN bus {b}: controller {state} (bus-off {}, error passive {}, warning {}, restarted {} so far)",
                d.count(BusEvent::BusOff),
                d.count(BusEvent::ErrorPassive),
                d.count(BusEvent::Warning),
                d.count(BusEvent::Restarted),
            );
            if more > 0 {
                line.push_str(&format!("; {more} earlier change(s) not logged separately"));
            }
            if d.state == Some(BusEvent::BusOff) {
                line.push_str(
                    ": check wiring, termination, bit rate and for a babbling node; the kernel restarts the interface with `ip link set IFACE type can restart-ms 100`; re-arm after it is back",
                );
            }
            lines.push(line);
            self.seen[b] = *d;
            self.held[b] = 0;
            self.last_line[b] = Some(t);
        }
        lines
    }
}

/// The causes of an error, joined (for one log line).
pub(crate) fn error_chain(e: &dyn std::error::Error) -> String {
    let mut parts = Vec::new();
    let mut src = e.source();
    while let Some(s) = src {
        parts.push(s.to_string());
        src = s.source();
    }
    parts.join(": ")
}

/// Prints what the cycle thread could set up and how the run went (stderr).
pub(crate) fn print_report(report: &RealtimeReport, quiet: bool) {
    if quiet {
        return;
    }
    for line in &report.setup {
        errln!("runtime: {line}");
    }
    errln!(
        "runtime: {} cycles, {} deadline misses, {} cycles skipped, {} records dropped, {} bus errors",
        report.cycles,
        report.deadline_misses,
        report.skipped_cycles,
        report.records_dropped,
        report.bus_errors
    );
}

/// The simulated wheel modules of a demo, in real time on their own thread (wall-clock
/// in-process buses, one per platform bus: [`rollbase_vcan_sim::run_realtime_buses`]).
///
/// The thread runs at SCHED_FIFO 81 on one CPU, and the cycle thread is kept on the same CPU
/// ([`Ports::cpu`]). Real modules never stall with the host; a simulator thread does: on a
/// kernel without full preemption (PREEMPT_NONE, the default of many distribution and VM
/// kernels) a task in a long system call keeps its CPU up to the next preemption point, and
/// a runnable real-time thread waits — measured here: a linker held the simulator's CPU for
/// 28.8 ms while the cycle thread ran on the other CPU, sending SYNCs nobody answered (a
/// stale-feedback fault that no real module would have caused). On one CPU both wait
/// together: the cycle sees a late cycle (a deadline miss), not silent modules.
pub(crate) struct SimThread {
    stop: Arc<AtomicBool>,
    handle: Option<std::thread::JoinHandle<()>>,
    cpu: Option<usize>,
}

impl SimThread {
    /// Starts `sim` on `nodes` (node b on platform bus b), on the CPU the caller runs on.
    pub(crate) fn start(
        mut sim: Simulator,
        mut nodes: Vec<rollbase_driver::bus::virtual_bus::VirtualNode>,
    ) -> Result<Self, CliError> {
        let stop = Arc::new(AtomicBool::new(false));
        let s2 = stop.clone();
        // SAFETY: sched_getcpu has no preconditions.
        let cpu = usize::try_from(unsafe { libc::sched_getcpu() }).ok();
        let handle = std::thread::Builder::new()
            .name("rollbase-sim".into())
            .spawn(move || {
                if let Some(c) = cpu {
                    let line = pin_to(c, "simulator thread");
                    tracing::debug!("{line}");
                }
                // The simulated modules stand in for hardware, which never waits for the
                // controller's process: give them real-time priority too (one above the cycle
                // thread's), so a loaded machine delays neither side.
                let _ = rollbase_control::runtime::realtime_setup(&RealtimeOptions {
                    fifo_priority: Some(81),
                    lock_memory: false,
                    max_cycles: None,
                });
                let mut buses: Vec<&mut dyn CanBus> =
                    nodes.iter_mut().map(|n| n as &mut dyn CanBus).collect();
                if let Err(e) =
                    rollbase_vcan_sim::run_realtime_buses(&mut sim, &mut buses, &s2, None)
                {
                    tracing::error!("simulator: {e}");
                }
            })
            .map_err(|e| CliError::Usage(format!("cannot start the simulator thread: {e}")))?;
        Ok(Self {
            stop,
            handle: Some(handle),
            cpu,
        })
    }

    /// The CPU the simulator runs on (for [`Ports::cpu`]).
    pub(crate) fn cpu(&self) -> Option<usize> {
        self.cpu
    }
}

impl Drop for SimThread {
    fn drop(&mut self) {
        self.stop.store(true, Ordering::SeqCst);
        if let Some(h) = self.handle.take() {
            let _ = h.join();
        }
    }
}

/// `n` in-process wall-clock buses (one per platform bus): the controller's nodes and the
/// simulator's nodes.
pub(crate) fn wall_buses(
    n: usize,
) -> (
    Vec<rollbase_driver::bus::virtual_bus::VirtualNode>,
    Vec<rollbase_driver::bus::virtual_bus::VirtualNode>,
) {
    use rollbase_driver::bus::{BusClock, VirtualBus, VirtualBusConfig};
    (0..n.max(1))
        .map(|_| {
            let vbus = VirtualBus::new(VirtualBusConfig {
                clock: BusClock::Wall,
                ..Default::default()
            });
            (vbus.node("controller"), vbus.node("simulator"))
        })
        .unzip()
}

/// The nodes as the cycle's buses.
pub(crate) fn as_buses(
    nodes: &mut [rollbase_driver::bus::virtual_bus::VirtualNode],
) -> Vec<&mut dyn CanBus> {
    nodes.iter_mut().map(|n| n as &mut dyn CanBus).collect()
}

/// The opened buses as the cycle's buses.
pub(crate) fn boxed_buses(buses: &mut [Box<dyn CanBus>]) -> Vec<&mut dyn CanBus> {
    buses
        .iter_mut()
        .map(|b| &mut **b as &mut dyn CanBus)
        .collect()
}

/// The interface names of `buses`, joined for a log line ("vcan0 and vcan1").
pub(crate) fn bus_names(buses: &[&mut dyn CanBus]) -> String {
    let names: Vec<&str> = buses.iter().map(|b| b.name()).collect();
    names.join(" and ")
}

#[cfg(test)]
mod tests {
    use super::*;

    fn diag(state: BusEvent, counts: &[(BusEvent, u32)]) -> [CanBusDiagnostics; MAX_BUSES] {
        let mut d = [CanBusDiagnostics::default(); MAX_BUSES];
        d[0].state = Some(state);
        for &(e, n) in counts {
            d[0].events[e.index()] = n;
        }
        d
    }

    #[test]
    fn bus_state_changes_are_logged_once_and_at_most_once_a_second() {
        let mut log = BusEventLog::default();
        assert!(log
            .update(0.0, &[CanBusDiagnostics::default(); MAX_BUSES])
            .is_empty());
        let w = diag(BusEvent::Warning, &[(BusEvent::Warning, 1)]);
        let lines = log.update(1.0, &w);
        assert_eq!(lines.len(), 1, "{lines:?}");
        assert!(lines[0].contains("error warning"), "{lines:?}");
        // The same state in every later record: nothing more.
        for k in 1..500 {
            assert!(log.update(1.0 + k as f64 * 0.004, &w).is_empty());
        }
        // A flapping bus: changes within the second are held and summed up.
        let mut n = 1;
        let mut lines = Vec::new();
        for k in 0..250 {
            n += 1;
            let e = if k % 2 == 0 {
                BusEvent::ErrorPassive
            } else {
                BusEvent::Warning
            };
            let d = diag(
                e,
                &[
                    (BusEvent::Warning, n / 2),
                    (BusEvent::ErrorPassive, n - n / 2),
                ],
            );
            lines.extend(log.update(3.0 + k as f64 * 0.004, &d));
        }
        assert_eq!(lines.len(), 1, "one line a second at most: {lines:?}");
        let d = diag(
            BusEvent::BusOff,
            &[
                (BusEvent::BusOff, 1),
                (BusEvent::Warning, n / 2),
                (BusEvent::ErrorPassive, n - n / 2),
            ],
        );
        let lines = log.update(4.5, &d);
        assert_eq!(lines.len(), 1, "{lines:?}");
        assert!(
            lines[0].contains("bus-off 1") && lines[0].contains("restart-ms"),
            "{lines:?}"
        );
        assert!(lines[0].contains("not logged separately"), "{lines:?}");
    }
}
