//! The real-time cycle thread: absolute deadlines, two wake-ups per cycle.
//!
//! One CAN bus or several: [`run_realtime_buses`] takes one [`CanBus`] per bus of the
//! platform (`buses[b]` serves the wheels with `bus = b`, [`Platform::buses`](crate::Platform::buses)) and refuses
//! ([`RealtimeError::BusCount`], before anything runs) a number of buses that differs from
//! the platform's. Each cycle keeps the one-bus order on every bus: the late frames of every
//! bus are handed over first (each with its bus, [`CycleCore::on_frame_on`]), then the cycle
//! starts with one [`FrameBuf`] per bus ([`CycleCore::start_cycle_buses`],
//! [`CycleCore::after_late_frames_buses`]) and each bus's SYNC and due frames go out on it,
//! bus 0 first; one feedback window serves all buses (their SYNCs leave together), then
//! every bus is drained, the commands are taken and each bus's setpoints go out on it
//! ([`CycleCore::finish_cycle_buses`]). A controller state change or a bus error is
//! reported with the index of the bus it came from ([`CycleCore::report_bus_event`]). After
//! a re-arm that followed a bus-off ([`CycleCore::take_reopen`]) the buses that reported
//! bus-off since the last reopen are reopened, and only those: the other buses' devices
//! were never lost (their frames go on flowing); if none did (a bus-off the core learnt of
//! otherwise), every bus is reopened.
//!
//! [`run_realtime`] and [`run_realtime_io`] are the one-bus entry points: the same loop on one
//! bus, every frame on it, as before (a platform with two buses is then served as if on one
//! medium, as [`CycleCore::start_cycle`] documents).

use super::command_channel::CommandReceiver;
use super::CycleCore;
use crate::model::platform::MAX_BUSES;
use crate::runtime::record::CycleRecord;
use crate::service::ports::BaseState;
use rollbase_driver::bus::{BusEvent, CanBus};
use rollbase_driver::frame::FrameBuf;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::mpsc::{SyncSender, TrySendError};

/// Options of the real-time cycle thread.
#[derive(Clone, Debug)]
pub struct RealtimeOptions {
    /// Try SCHED_FIFO at this priority (1..=99); `None` = normal scheduling.
    pub fifo_priority: Option<i32>,
    /// Try to lock memory (mlockall).
    pub lock_memory: bool,
    /// Stop after this many cycles (None = until done or stopped).
    pub max_cycles: Option<u64>,
}

impl Default for RealtimeOptions {
    fn default() -> Self {
        Self {
            fifo_priority: Some(80),
            lock_memory: true,
            max_cycles: None,
        }
    }
}

/// What the real-time thread reports at the end.
#[derive(Clone, Debug, Default)]
pub struct RealtimeReport {
    /// Cycles run.
    pub cycles: u64,
    /// Cycles whose control step finished after the next cycle's deadline (each such
    /// cycle's record has `timing.deadline_miss` set).
    pub deadline_misses: u64,
    /// Cycles never run because the loop fell behind by more than a period (it
    /// resynchronises instead of bursting to catch up; they have no record).
    pub skipped_cycles: u64,
    /// Records dropped because the recorder channel was full.
    pub records_dropped: u64,
    /// State-port values dropped because their channel was full.
    pub states_dropped: u64,
    /// What the thread could set up (SCHED_FIFO, mlockall), for the operator.
    pub setup: Vec<String>,
    /// Bus errors seen.
    pub bus_errors: u64,
}

/// Why [`run_realtime_buses`] refused to run.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum RealtimeError {
    /// The number of buses given differs from the number the platform's wheels are on.
    BusCount {
        /// Buses the platform's wheels are on ([`Platform::buses`](crate::Platform::buses)).
        platform: usize,
        /// Buses given.
        given: usize,
    },
}

impl std::fmt::Display for RealtimeError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Self::BusCount { platform, given } => write!(
                f,
                "the platform's wheels are on {platform} CAN bus(es) but {given} bus(es) were given: the real-time cycle needs one bus per platform bus (bus b serves the wheels with bus = b)"
            ),
        }
    }
}

impl std::error::Error for RealtimeError {}

fn monotonic_now() -> libc::timespec {
    let mut ts = libc::timespec {
        tv_sec: 0,
        tv_nsec: 0,
    };
    // SAFETY: clock_gettime writes into the provided timespec; CLOCK_MONOTONIC always exists.
    unsafe { libc::clock_gettime(libc::CLOCK_MONOTONIC, &mut ts) };
    ts
}

fn ts_ns(ts: &libc::timespec) -> i128 {
    ts.tv_sec as i128 * 1_000_000_000 + ts.tv_nsec as i128
}

fn ns_ts(ns: i128) -> libc::timespec {
    libc::timespec {
        tv_sec: (ns / 1_000_000_000) as libc::time_t,
        tv_nsec: (ns % 1_000_000_000) as libc::c_long,
    }
}

fn sleep_until(ns: i128) {
    let ts = ns_ts(ns);
    loop {
        // SAFETY: absolute sleep on CLOCK_MONOTONIC with a valid timespec; a null remainder is
        // allowed with TIMER_ABSTIME.
        let r = unsafe {
            libc::clock_nanosleep(
                libc::CLOCK_MONOTONIC,
                libc::TIMER_ABSTIME,
                &ts,
                std::ptr::null_mut(),
            )
        };
        if r != libc::EINTR {
            break;
        }
    }
}

/// Slack kept between the end of the computation and the next deadline (the setpoints'
/// send, the records, the wake-up's own jitter).
const DEADLINE_SLACK_NS: i128 = 250_000;

/// When the feedback window of a cycle with deadline `deadline` whose SYNC went out at
/// `sync_sent` closes (all ns on CLOCK_MONOTONIC): `window` after the SYNC, but no later than
/// the next deadline less twice `reserve` (the recent peak compute time: a host whose compute
/// is slow is as slow to wake, so its late cycles get less of the period) and
/// [`DEADLINE_SLACK_NS`], and never earlier than `window` after the deadline (the window of a
/// cycle on time).
fn window_end(deadline: i128, sync_sent: i128, period: i128, window: i128, reserve: i128) -> i128 {
    let latest = deadline + period - 2 * reserve - DEADLINE_SLACK_NS;
    (sync_sent + window).min(latest).max(deadline + window)
}

/// The compute-time reserve after a cycle that computed for `compute` ns: a peak detector
/// that follows a longer cycle at once and forgets it by 1/64 a cycle (a 3 ms spike decays to
/// 1 ms in about 70 cycles, 0.28 s at 250 Hz).
fn next_compute_reserve(reserve: i128, compute: i128) -> i128 {
    compute.max(reserve - reserve / 64).max(0)
}

/// Which bus a drain or send serves: its index, and whether frames are handed to the core
/// with it (several buses, [`CycleCore::on_frame_on`]) or without (one medium,
/// [`CycleCore::on_frame`]: the core finds the bus from the node).
#[derive(Clone, Copy)]
struct BusTag {
    index: usize,
    tagged: bool,
}

/// Hands every frame waiting on `bus` to the core, stamped `t`; a controller state change
/// (error frame: warning, passive, bus-off, restarted) goes to the core
/// ([`CycleCore::report_bus_event`], with the bus's index) and the drain goes on; another
/// non-retryable receive error is reported to the core (bus-error fault) and ends the drain.
/// A bus-off sets `off`.
fn drain(
    bus: &mut dyn CanBus,
    tag: BusTag,
    core: &mut CycleCore,
    t: f64,
    report: &mut RealtimeReport,
    off: &mut bool,
) {
    loop {
        match bus.try_recv() {
            Ok(Some(f)) => {
                if tag.tagged {
                    core.on_frame_on(tag.index, &f.frame, t)
                } else {
                    core.on_frame(&f.frame, t)
                }
            }
            Ok(None) => break,
            Err(e) if e.bus_event().is_some() => {
                if let Some(ev) = e.bus_event() {
                    core.report_bus_event(tag.index, ev);
                    if ev == BusEvent::BusOff {
                        report.bus_errors += 1;
                        *off = true;
                    }
                }
            }
            Err(e) if e.is_retryable() => break,
            Err(_) => {
                core.report_bus_error();
                report.bus_errors += 1;
                break;
            }
        }
    }
}

/// Sends every frame of `out`; a controller state change goes to the core with the bus's
/// index (a bus-off sets `off`), another non-retryable error is reported to the core
/// (bus-error fault), a retryable one drops that frame.
fn send_all(
    bus: &mut dyn CanBus,
    tag: BusTag,
    core: &mut CycleCore,
    out: &FrameBuf,
    report: &mut RealtimeReport,
    off: &mut bool,
) {
    for f in out.as_slice() {
        if let Err(e) = bus.send(f) {
            if let Some(ev) = e.bus_event() {
                core.report_bus_event(tag.index, ev);
                if ev == BusEvent::BusOff {
                    *off = true;
                }
            } else if !e.is_retryable() {
                core.report_bus_error();
                report.bus_errors += 1;
            }
        }
    }
}

/// Tries SCHED_FIFO and mlockall as asked; returns one line per attempt for the operator.
pub fn realtime_setup(opts: &RealtimeOptions) -> Vec<String> {
    let mut out = Vec::new();
    if let Some(prio) = opts.fifo_priority {
        let param = libc::sched_param {
            sched_priority: prio.clamp(1, 99),
        };
        // SAFETY: sets the calling thread's scheduling policy; the parameter is valid.
        let r = unsafe { libc::sched_setscheduler(0, libc::SCHED_FIFO, &param) };
        if r == 0 {
            out.push(format!(
                "cycle thread runs SCHED_FIFO priority {}",
                param.sched_priority
            ));
        } else {
            out.push(format!(
                "SCHED_FIFO not permitted ({}): running with normal scheduling; grant CAP_SYS_NICE or an rtprio limit for real-time priority",
                std::io::Error::last_os_error()
            ));
        }
    }
    if opts.lock_memory {
        // SAFETY: mlockall has no memory-safety preconditions.
        let r = unsafe { libc::mlockall(libc::MCL_CURRENT | libc::MCL_FUTURE) };
        if r == 0 {
            out.push("memory locked (mlockall)".into());
        } else {
            out.push(format!(
                "mlockall not permitted ({}): memory may be paged; raise the memlock limit or grant CAP_IPC_LOCK",
                std::io::Error::last_os_error()
            ));
        }
    }
    out
}

/// Runs the cycle on the calling thread in real time until done, stopped by `stop` (a
/// controlled stop, then exit) or `max_cycles`. Records go to `sink` with `try_send`.
///
/// `time_origin_unix_ns` is added to record log times so recordings carry Unix time.
pub fn run_realtime(
    core: &mut CycleCore,
    bus: &mut dyn CanBus,
    stop: &AtomicBool,
    sink: Option<&SyncSender<CycleRecord>>,
    opts: &RealtimeOptions,
    time_origin_unix_ns: u64,
) -> RealtimeReport {
    run_realtime_io(
        core,
        bus,
        stop,
        &RealtimeIo {
            records: sink,
            ..Default::default()
        },
        opts,
        time_origin_unix_ns,
    )
}

/// The channels of a real-time run: records out (recorder), state out (the state port: ROS 2,
/// status line), commands in (the command port). All bounded and non-blocking on the cycle
/// thread: a full output channel drops (and counts) the value; commands are taken without
/// blocking — every stop, re-arm, end of stream and shutdown first, then at most
/// [`MAX_COMMANDS_PER_CYCLE`] motion commands ([`command_channel`](mod@super::command_channel)) — and stamped with
/// the time the cycle took them.
///
/// The consumers of `records` and `states` should poll (`try_recv`) rather than block in
/// `recv`: a receiver blocked in `recv` registers with the channel's waker, and the cycle's
/// `try_send` then takes the waker's mutex to wake it — a lock shared with a normal-priority
/// thread that a busy machine may preempt while it holds it.
#[derive(Default)]
pub struct RealtimeIo<'a> {
    /// Where cycle records go.
    pub records: Option<&'a SyncSender<CycleRecord>>,
    /// Where the state port's values go.
    pub states: Option<&'a SyncSender<BaseState>>,
    /// Where commands come from.
    pub commands: Option<&'a CommandReceiver>,
}

/// Most command events the cycle takes per cycle (the rest wait for the next cycle).
pub const MAX_COMMANDS_PER_CYCLE: usize = 64;

/// [`run_realtime`] with the base service's ports ([`RealtimeIo`]).
pub fn run_realtime_io(
    core: &mut CycleCore,
    bus: &mut dyn CanBus,
    stop: &AtomicBool,
    io: &RealtimeIo<'_>,
    opts: &RealtimeOptions,
    time_origin_unix_ns: u64,
) -> RealtimeReport {
    run_loop(core, &mut [bus], false, stop, io, opts, time_origin_unix_ns)
}

/// [`run_realtime_io`] on one CAN bus per bus of the platform: `buses[b]` serves the wheels
/// with `bus = b` (module docs). Refuses, before anything runs, a number of buses that
/// differs from [`Platform::buses`](crate::Platform::buses) ([`RealtimeError::BusCount`]).
pub fn run_realtime_buses(
    core: &mut CycleCore,
    buses: &mut [&mut dyn CanBus],
    stop: &AtomicBool,
    io: &RealtimeIo<'_>,
    opts: &RealtimeOptions,
    time_origin_unix_ns: u64,
) -> Result<RealtimeReport, RealtimeError> {
    let platform = core.platform().buses();
    if buses.len() != platform || platform > MAX_BUSES {
        return Err(RealtimeError::BusCount {
            platform,
            given: buses.len(),
        });
    }
    let tagged = buses.len() > 1;
    Ok(run_loop(
        core,
        buses,
        tagged,
        stop,
        io,
        opts,
        time_origin_unix_ns,
    ))
}

/// The cycle loop on `buses` (one to [`MAX_BUSES`]); `tagged`: hand received frames to the
/// core with their bus's index.
fn run_loop(
    core: &mut CycleCore,
    buses: &mut [&mut dyn CanBus],
    tagged: bool,
    stop: &AtomicBool,
    io: &RealtimeIo<'_>,
    opts: &RealtimeOptions,
    time_origin_unix_ns: u64,
) -> RealtimeReport {
    let nb = buses.len().clamp(1, MAX_BUSES);
    let tag = |index: usize| BusTag { index, tagged };
    // Buses that reported bus-off since they were last reopened.
    let mut off = [false; MAX_BUSES];
    let sink = io.records;
    let mut report = RealtimeReport {
        setup: realtime_setup(opts),
        ..Default::default()
    };
    let period_ns = (core.platform().dt() * 1e9).round() as i128;
    let window_ns = (core.config().feedback_window * 1e9).round() as i128;
    let start = ts_ns(&monotonic_now()) + period_ns;
    let mut outs: [FrameBuf; MAX_BUSES] = std::array::from_fn(|_| FrameBuf::new());
    let mut prev_wake: Option<i128> = None;
    let mut stop_sent = false;
    core.arm();
    let mut k: u64 = 0;
    let mut deadline = start;
    // Until the first cycle measured its compute time: a quarter of the period.
    let mut compute_reserve_ns = period_ns / 4;
    loop {
        if let Some(m) = opts.max_cycles {
            if k >= m {
                break;
            }
        }
        sleep_until(deadline);
        let wake = ts_ns(&monotonic_now());
        let t = (wake - start) as f64 * 1e-9;
        let td = (deadline - start) as f64 * 1e-9;
        if !stop_sent && stop.load(Ordering::Relaxed) {
            core.request_stop();
            stop_sent = true;
        }
        // Answers that arrived after the last window belong to the previous SYNC: hand them
        // over first, stamped just before this SYNC, so they count as late (not as this
        // cycle's samples). Then SYNC (and whatever else is due at the cycle start), one sleep
        // to the window's end, one drain: two wake-ups a cycle instead of one per frame (the
        // cycle waits for the window's end anyway).
        // A re-arm after a bus-off: a fresh socket before the devices are booted again.
        // Only the buses that went bus-off (module docs); all if none is known to have.
        if core.take_reopen() {
            let any = off[..nb].iter().any(|&o| o);
            for (b, bus) in buses.iter_mut().enumerate().take(nb) {
                if (!any || off[b]) && bus.reopen().is_err() {
                    core.report_bus_error();
                    report.bus_errors += 1;
                }
                off[b] = false;
            }
        }
        core.start_cycle_buses(td, &mut outs[..nb]);
        for (b, bus) in buses.iter_mut().enumerate().take(nb) {
            drain(
                &mut **bus,
                tag(b),
                core,
                td - 1e-6,
                &mut report,
                &mut off[b],
            );
        }
        // What the late answers made due (CiA 402: a device's next SDO request) goes out
        // with the SYNC, not a cycle later.
        core.after_late_frames_buses(td, &mut outs[..nb]);
        for (b, bus) in buses.iter_mut().enumerate().take(nb) {
            send_all(&mut **bus, tag(b), core, &outs[b], &mut report, &mut off[b]);
        }
        // The modules get the whole window to answer from the moment the SYNC went out, not
        // from the deadline: a cycle that woke late (a busy host) would otherwise close its
        // window before the answers came and steer on the previous SYNC's readings, a cycle
        // old (tests/tests/realtime_late_sync.rs). But the late cycle must still finish
        // before the next deadline: the window ends no later than the next deadline less
        // twice the compute time the recent cycles took (`window_end`), and never before the
        // deadline's own window. A host too slow for both (a slow VM: compute 1 ms, wake-ups 1 ms late)
        // then keeps the 250 Hz cadence on answers a cycle old instead of overrunning every
        // period (tests/tests/realtime_slow_compute.rs).
        let sync_sent = ts_ns(&monotonic_now());
        core.sync_sent_at((sync_sent - start) as f64 * 1e-9);
        sleep_until(window_end(
            deadline,
            sync_sent,
            period_ns,
            window_ns,
            compute_reserve_ns,
        ));
        let now_rt = (ts_ns(&monotonic_now()) - start) as f64 * 1e-9;
        for (b, bus) in buses.iter_mut().enumerate().take(nb) {
            drain(&mut **bus, tag(b), core, now_rt, &mut report, &mut off[b]);
        }
        // Commands last, just before the setpoints are computed: a command that arrived
        // during the feedback window acts in this cycle's setpoints (latency ≤ one period plus
        // the compute time), not one cycle later.
        if let Some(rx) = io.commands {
            rx.take(MAX_COMMANDS_PER_CYCLE, |mut ev| {
                ev.t = td;
                core.command(ev);
            });
        }
        let collected = ts_ns(&monotonic_now());
        let tw = (collected - start) as f64 * 1e-9;
        core.finish_cycle_buses(tw, &mut outs[..nb]);
        for (b, bus) in buses.iter_mut().enumerate().take(nb) {
            send_all(&mut **bus, tag(b), core, &outs[b], &mut report, &mut off[b]);
        }
        let done_ns = ts_ns(&monotonic_now());
        let miss = done_ns > deadline + period_ns;
        if miss {
            report.deadline_misses += 1;
        }
        {
            let rec = core.record_mut();
            rec.t = td;
            rec.log_time_ns = time_origin_unix_ns.saturating_add((deadline - start).max(0) as u64);
            rec.timing.period_us =
                prev_wake.map_or(period_ns as f64 / 1e3, |p| (wake - p) as f64 / 1e3);
            rec.timing.wakeup_latency_us = (wake - deadline) as f64 / 1e3;
            // Compute time: from the end of feedback collection to the last setpoint sent
            // (the collection window itself is waiting, not computing).
            rec.timing.compute_us = (done_ns - collected) as f64 / 1e3;
            compute_reserve_ns = next_compute_reserve(compute_reserve_ns, done_ns - collected);
            rec.timing.deadline_miss = miss;
            let _ = t;
        }
        prev_wake = Some(wake);
        {
            let s = core.base_state_mut();
            s.log_time_ns = time_origin_unix_ns.saturating_add((deadline - start).max(0) as u64);
            s.t = td;
            s.diagnostics.deadline_misses = report.deadline_misses;
            if let Some(rx) = io.commands {
                s.commands.dropped = rx.dropped();
            }
        }
        {
            let st = *core.base_state();
            let rec = core.record_mut();
            rec.base = st;
            rec.commands.dropped = st.commands.dropped;
        }
        if let Some(tx) = sink {
            match tx.try_send(*core.record()) {
                Ok(()) => {}
                Err(TrySendError::Full(_)) => report.records_dropped += 1,
                Err(TrySendError::Disconnected(_)) => report.records_dropped += 1,
            }
        }
        if let Some(tx) = io.states {
            if tx.try_send(*core.base_state()).is_err() {
                report.states_dropped += 1;
            }
        }
        k += 1;
        report.cycles = k;
        if core.done() {
            break;
        }
        deadline += period_ns;
        // Fell behind by more than a period: count the skipped cycles and resynchronise
        // instead of bursting to catch up.
        let now = ts_ns(&monotonic_now());
        if now > deadline + period_ns {
            let behind = (now - deadline) / period_ns;
            report.skipped_cycles += behind as u64;
            deadline += behind * period_ns;
        }
    }
    report
}

#[cfg(test)]
mod tests {
    use super::*;

    const MS: i128 = 1_000_000;

    #[test]
    fn a_late_sync_gets_its_window_while_the_compute_still_fits() {
        // On time: the window after the deadline.
        assert_eq!(window_end(0, 0, 4 * MS, 2 * MS, MS / 5), 2 * MS);
        // 1 ms late, fast compute: the whole window after the SYNC.
        assert_eq!(window_end(0, MS, 4 * MS, 2 * MS, MS / 5), 3 * MS);
        // 1.5 ms late, 0.5 ms compute: cut where twice the compute and the slack still fit
        // (4 - 1 - 0.25 = 2.75 ms).
        assert_eq!(
            window_end(0, 3 * MS / 2, 4 * MS, 2 * MS, MS / 2),
            11 * MS / 4
        );
        // A compute too long for any extension (1 ms: 4 - 2 - 0.25 < 2): the on-time window,
        // not earlier.
        assert_eq!(window_end(0, MS, 4 * MS, 2 * MS, MS), 2 * MS);
        assert_eq!(window_end(0, MS, 4 * MS, 2 * MS, 3 * MS), 2 * MS);
    }

    #[test]
    fn the_compute_reserve_follows_a_peak_at_once_and_forgets_it_slowly() {
        let mut r = next_compute_reserve(MS / 5, 3 * MS);
        assert_eq!(r, 3 * MS);
        let mut n = 0;
        while r > MS {
            r = next_compute_reserve(r, MS / 10);
            n += 1;
        }
        assert!((60..=80).contains(&n), "{n} cycles to forget a 3 ms peak");
        for _ in 0..2000 {
            r = next_compute_reserve(r, MS / 10);
        }
        assert!((MS / 10..MS / 10 + MS / 50).contains(&r), "{r} ns");
    }
    use crate::model::platform::Platform;
    use crate::runtime::command_channel::command_channel;
    use crate::runtime::RuntimeConfig;
    use crate::service::ports::{CommandEvent, CommandKind};
    use rollbase_driver::bus::{BusError, BusEvent};
    use rollbase_driver::frame::{CanFrame, TimestampedFrame};
    use std::sync::atomic::AtomicU32;
    use std::sync::Arc;
    use std::time::Instant;

    /// A bus whose controller goes bus-off at the first receive; counts `reopen` calls.
    struct OffOnce {
        told: bool,
        reopened: Arc<AtomicU32>,
    }

    impl CanBus for OffOnce {
        fn send(&mut self, _: &CanFrame) -> Result<(), BusError> {
            Ok(())
        }
        fn try_recv(&mut self) -> Result<Option<TimestampedFrame>, BusError> {
            if !self.told {
                self.told = true;
                return Err(BusError::BusOff {
                    iface: "can9".into(),
                });
            }
            Ok(None)
        }
        fn recv_until(&mut self, _: Instant) -> Result<Option<TimestampedFrame>, BusError> {
            self.try_recv()
        }
        fn name(&self) -> &str {
            "can9"
        }
        fn reopen(&mut self) -> Result<(), BusError> {
            self.reopened.fetch_add(1, Ordering::SeqCst);
            Ok(())
        }
    }

    #[test]
    fn bus_off_faults_and_the_re_arm_reopens_the_interface_once() {
        let mut core =
            CycleCore::new_live(Platform::justin(), RuntimeConfig::default()).expect("core");
        let reopened = Arc::new(AtomicU32::new(0));
        let mut bus = OffOnce {
            told: false,
            reopened: Arc::clone(&reopened),
        };
        let (tx, rx) = command_channel(16, 16);
        let stop = AtomicBool::new(false);
        let opts = RealtimeOptions {
            fifo_priority: None,
            lock_memory: false,
            max_cycles: Some(100),
        };
        let report = std::thread::scope(|s| {
            s.spawn(|| {
                // Well after the fault (first cycle); the cycle takes it when it comes.
                std::thread::sleep(std::time::Duration::from_millis(100));
                let _ = tx.try_send(CommandEvent {
                    t: 0.0,
                    kind: CommandKind::Rearm,
                });
            });
            let io = RealtimeIo {
                commands: Some(&rx),
                ..Default::default()
            };
            run_realtime_io(&mut core, &mut bus, &stop, &io, &opts, 0)
        });
        assert_eq!(report.bus_errors, 1, "{report:?}");
        assert_eq!(
            reopened.load(Ordering::SeqCst),
            1,
            "reopened once, after the re-arm"
        );
        let d = core.base_state().diagnostics.can[0];
        assert_eq!(d.count(BusEvent::BusOff), 1, "{d:?}");
    }
}

#[cfg(test)]
mod two_bus_off_tests {
    use super::tests_support::OffOnce;
    use super::*;
    use crate::model::platform::Platform;
    use crate::runtime::command_channel::command_channel;
    use crate::runtime::RuntimeConfig;
    use crate::service::ports::{CommandEvent, CommandKind};
    use std::sync::atomic::AtomicU32;
    use std::sync::Arc;

    #[test]
    fn a_bus_off_on_bus_1_is_reported_on_bus_1_and_only_bus_1_is_reopened() {
        let mut core =
            CycleCore::new_live(Platform::six_wheel(), RuntimeConfig::default()).expect("core");
        let reopened = [Arc::new(AtomicU32::new(0)), Arc::new(AtomicU32::new(0))];
        // Bus 0 never goes bus-off (already "told"); bus 1 does at its first receive.
        let mut b0 = OffOnce {
            told: true,
            reopened: Arc::clone(&reopened[0]),
        };
        let mut b1 = OffOnce {
            told: false,
            reopened: Arc::clone(&reopened[1]),
        };
        let (tx, rx) = command_channel(16, 16);
        let stop = AtomicBool::new(false);
        let opts = RealtimeOptions {
            fifo_priority: None,
            lock_memory: false,
            max_cycles: Some(100),
        };
        let report = std::thread::scope(|s| {
            s.spawn(|| {
                std::thread::sleep(std::time::Duration::from_millis(100));
                let _ = tx.try_send(CommandEvent {
                    t: 0.0,
                    kind: CommandKind::Rearm,
                });
            });
            let io = RealtimeIo {
                commands: Some(&rx),
                ..Default::default()
            };
            run_realtime_buses(&mut core, &mut [&mut b0, &mut b1], &stop, &io, &opts, 0)
                .expect("two buses")
        });
        assert_eq!(report.bus_errors, 1, "{report:?}");
        assert_eq!(
            reopened[0].load(Ordering::SeqCst),
            0,
            "bus 0 kept its socket"
        );
        assert_eq!(reopened[1].load(Ordering::SeqCst), 1, "bus 1 reopened once");
        let d = core.base_state().diagnostics.can;
        assert_eq!(d[1].count(BusEvent::BusOff), 1, "{d:?}");
        assert_eq!(d[0].count(BusEvent::BusOff), 0, "{d:?}");
    }
}

#[cfg(test)]
mod tests_support {
    use rollbase_driver::bus::{BusError, CanBus};
    use rollbase_driver::frame::{CanFrame, TimestampedFrame};
    use std::sync::atomic::{AtomicU32, Ordering};
    use std::sync::Arc;
    use std::time::Instant;

    /// A bus whose controller goes bus-off at the first receive (unless `told`); counts
    /// `reopen` calls.
    pub(super) struct OffOnce {
        pub(super) told: bool,
        pub(super) reopened: Arc<AtomicU32>,
    }

    impl CanBus for OffOnce {
        fn send(&mut self, _: &CanFrame) -> Result<(), BusError> {
            Ok(())
        }
        fn try_recv(&mut self) -> Result<Option<TimestampedFrame>, BusError> {
            if !self.told {
                self.told = true;
                return Err(BusError::BusOff {
                    iface: "can9".into(),
                });
            }
            Ok(None)
        }
        fn recv_until(&mut self, _: Instant) -> Result<Option<TimestampedFrame>, BusError> {
            self.try_recv()
        }
        fn name(&self) -> &str {
            "can9"
        }
        fn reopen(&mut self) -> Result<(), BusError> {
            self.reopened.fetch_add(1, Ordering::SeqCst);
            Ok(())
        }
    }
}

#[cfg(test)]
mod bus_count_tests {
    use super::*;
    use crate::model::platform::Platform;
    use crate::runtime::RuntimeConfig;
    use rollbase_driver::bus::{BusError, VirtualBus, VirtualBusConfig};
    use rollbase_driver::frame::{CanFrame, TimestampedFrame};
    use std::time::Instant;

    /// A bus that must never be used: the refusal comes before anything runs.
    struct Untouched;

    impl CanBus for Untouched {
        fn send(&mut self, _: &CanFrame) -> Result<(), BusError> {
            panic!("a refused run sent a frame")
        }
        fn try_recv(&mut self) -> Result<Option<TimestampedFrame>, BusError> {
            panic!("a refused run received")
        }
        fn recv_until(&mut self, _: Instant) -> Result<Option<TimestampedFrame>, BusError> {
            panic!("a refused run received")
        }
        fn name(&self) -> &str {
            "untouched"
        }
    }

    fn refused(p: Platform, given: usize) -> RealtimeError {
        let mut core = CycleCore::new_live(p, RuntimeConfig::default()).expect("core");
        let mut a = Untouched;
        let mut b = Untouched;
        let mut c = Untouched;
        let all: [&mut dyn CanBus; 3] = [&mut a, &mut b, &mut c];
        let mut buses: Vec<&mut dyn CanBus> = all.into_iter().take(given).collect();
        let stop = AtomicBool::new(false);
        let opts = RealtimeOptions {
            fifo_priority: None,
            lock_memory: false,
            max_cycles: Some(1),
        };
        let r = run_realtime_buses(
            &mut core,
            &mut buses,
            &stop,
            &RealtimeIo::default(),
            &opts,
            0,
        );
        assert_eq!(core.cycles(), 0, "no cycle ran");
        r.expect_err("a bus count that differs from the platform's is refused")
    }

    #[test]
    fn a_bus_count_that_differs_from_the_platforms_is_refused_naming_both() {
        let six = Platform::six_wheel();
        assert_eq!(six.buses(), 2);
        for given in [0, 1, 3] {
            let e = refused(six.clone(), given);
            assert_eq!(e, RealtimeError::BusCount { platform: 2, given });
            let m = e.to_string();
            assert!(
                m.contains("on 2 CAN bus(es)") && m.contains(&format!("but {given} bus(es)")),
                "{m}"
            );
        }
        let justin = Platform::justin();
        assert_eq!(justin.buses(), 1);
        let e = refused(justin, 2);
        assert_eq!(
            e,
            RealtimeError::BusCount {
                platform: 1,
                given: 2
            }
        );
        let m = e.to_string();
        assert!(
            m.contains("on 1 CAN bus(es)") && m.contains("but 2 bus(es)"),
            "{m}"
        );
    }

    #[test]
    fn a_matching_bus_count_runs() {
        let mut core =
            CycleCore::new_live(Platform::six_wheel(), RuntimeConfig::default()).expect("core");
        let v0 = VirtualBus::new(VirtualBusConfig::default());
        let v1 = VirtualBus::new(VirtualBusConfig::default());
        let mut c0 = v0.node("controller");
        let mut c1 = v1.node("controller");
        let mut p0 = v0.node("peer");
        let mut p1 = v1.node("peer");
        let stop = AtomicBool::new(false);
        let opts = RealtimeOptions {
            fifo_priority: None,
            lock_memory: false,
            max_cycles: Some(3),
        };
        let report = run_realtime_buses(
            &mut core,
            &mut [&mut c0, &mut c1],
            &stop,
            &RealtimeIo::default(),
            &opts,
            0,
        )
        .expect("two buses for a two-bus platform");
        assert_eq!(report.cycles, 3);
        // Each bus carried its own SYNC every cycle.
        for peer in [&mut p0, &mut p1] {
            let mut syncs = 0;
            while let Ok(Some(f)) = peer.try_recv() {
                syncs += usize::from(f.frame.id() == 0x080);
            }
            assert_eq!(syncs, 3);
        }
    }
}
