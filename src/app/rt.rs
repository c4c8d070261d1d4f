//! What every real-time run does around the cycle thread: the thread itself, the recorder on
//! the calling thread (a failed write stops the run in a controlled way), the in-process
//! simulator of the demos, and the report.

use rollbase_control::ports::BaseState;
use rollbase_control::record::CycleRecord;
use rollbase_control::runtime::{
    run_realtime_io, CommandReceiver, CycleCore, RealtimeIo, RealtimeOptions, RealtimeReport,
};
use rollbase_driver::bus::CanBus;
use rollbase_vcan_sim::Simulator;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::mpsc::SyncSender;
use std::sync::Arc;
use std::time::Duration;

use super::sinks::Sinks;
use super::CliError;

/// Records queued between the cycle thread and the recorder (about 8 s at 250 Hz).
pub(crate) const RECORD_QUEUE: usize = 2048;

/// The channels a real-time run connects to the cycle (besides its records).
#[derive(Default)]
pub(crate) struct Ports<'a> {
    /// Commands in (the base service).
    pub(crate) commands: Option<CommandReceiver>,
    /// State out (the base service's consumers).
    pub(crate) states: Option<&'a SyncSender<BaseState>>,
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
                let io = RealtimeIo {
                    records: Some(&tx),
                    states: ports.states,
                    commands: ports.commands.as_ref(),
                };
                let r = run_realtime_io(core, bus, stop, &io, &opts, origin_ns);
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
            match rx.recv_timeout(Duration::from_millis(100)) {
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
                Err(std::sync::mpsc::RecvTimeoutError::Timeout) => {}
                Err(std::sync::mpsc::RecvTimeoutError::Disconnected) => break,
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
        "runtime: {} cycles, {} deadline misses, {} records dropped, {} bus errors",
        report.cycles,
        report.deadline_misses,
        report.records_dropped,
        report.bus_errors
    );
}

/// The simulated wheel modules of a demo, in real time on their own thread (wall-clock
/// in-process bus).
pub(crate) struct SimThread {
    stop: Arc<AtomicBool>,
    handle: Option<std::thread::JoinHandle<()>>,
}

impl SimThread {
    /// Starts `sim` on `node`.
    pub(crate) fn start(
        mut sim: Simulator,
        mut node: rollbase_driver::bus::virtual_bus::VirtualNode,
    ) -> Result<Self, CliError> {
        let stop = Arc::new(AtomicBool::new(false));
        let s2 = stop.clone();
        let handle = std::thread::Builder::new()
            .name("rollbase-sim".into())
            .spawn(move || {
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
        })
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
