//! What every real-time run does around the cycle thread: the thread itself, the recorder on
//! the calling thread (a failed write stops the run in a controlled way), the in-process
//! simulator of the demos, and the report.

use rollbase_control::runtime::record::CycleRecord;
use rollbase_control::runtime::{
    run_realtime_io, CommandReceiver, CycleCore, RealtimeIo, RealtimeOptions, RealtimeReport,
};
use rollbase_control::service::ports::BaseState;
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

/// Runs `core` on `bus` in real time on its own thread until it is done; the calling thread
/// takes the records into `sinks` and calls `each` with every record (status lines). `stop`
/// (signals, `--duration`) asks for a controlled stop; so does a failed recording, whose
/// error the caller finds in the sinks.
pub(crate) fn run_cycle(
    core: &mut CycleCore,
    bus: &mut dyn CanBus,
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
                let mut r = run_realtime_io(core, bus, stop, &io, &opts, origin_ns);
                r.setup.extend(pinned);
                drop(tx);
                r
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
        loop {
            match poll_recv(&rx, Duration::from_millis(100)) {
                Ok(r) => {
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
            .map_err(|_| CliError::Usage("the cycle thread panicked".into()))
    })?;
    sinks.summary.deadline_misses = sinks.summary.deadline_misses.max(report.deadline_misses);
    Ok(report)
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
/// in-process bus).
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
    /// Starts `sim` on `node`, on the CPU the caller runs on.
    pub(crate) fn start(
        mut sim: Simulator,
        mut node: rollbase_driver::bus::virtual_bus::VirtualNode,
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
                if let Err(e) = sim.run_realtime(&mut node, &s2) {
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

/// An in-process wall-clock bus with the controller's node and the simulator's node.
pub(crate) fn wall_bus() -> (
    rollbase_driver::bus::virtual_bus::VirtualNode,
    rollbase_driver::bus::virtual_bus::VirtualNode,
) {
    use rollbase_driver::bus::{BusClock, VirtualBus, VirtualBusConfig};
    let vbus = VirtualBus::new(VirtualBusConfig {
        clock: BusClock::Wall,
        ..Default::default()
    });
    (vbus.node("controller"), vbus.node("simulator"))
}
