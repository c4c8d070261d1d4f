//! `rollbase drive` and the live-command demo: the base service.
//!
//! ```text
//!  command sources ──► bounded channel ──► cycle thread (250 Hz) ──► records ──► recorder
//!  (file, stdin, keyboard, ROS 2)            │                                  (this thread)
//!                                            └──► state port (bounded) ──► status, ROS 2
//! ```
//!
//! The cycle thread takes what commands are waiting without blocking — stop and re-arm first,
//! through their own lane ([`rollbase_control::runtime::command_channel`]) — and hands its
//! state over with `try_send`; sources and consumers run on their own threads. SIGINT,
//! SIGTERM, SIGHUP and SIGQUIT are a controlled stop and a clean exit (recording finished);
//! the end of a command file (or EOF on stdin) lets the command timeout stop the platform,
//! and the run ends once it is at rest.

use clap::Args;
use rollbase::commands::{self, TimedCommand};
use rollbase::ros2::{spawn_node, Ros2Options};
use rollbase_control::runtime::command_channel::{command_channel, MOTION_QUEUE, PRIORITY_LANE};
use rollbase_control::runtime::record::CycleRecord;
use rollbase_control::runtime::{CommandSender, CycleCore, RuntimeConfig};
use rollbase_control::service::ports::{BaseState, CommandEvent, CommandKind};
use rollbase_control::supervisor::SupervisorState;
use rollbase_control::Platform;
use rollbase_driver::bus::{self as bus, CanBus};
use rollbase_vcan_sim::{FaultSchedule, PlantConfig, SimConfig, Simulator};
use std::collections::BTreeMap;
use std::io::{BufRead, Read};
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::mpsc::TrySendError;
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use super::common::{
    install_signals, load_platform_on, load_platform_profile, runtime_config, unix_now, CliError,
    CommonRun, SignalAction,
};
use super::common::{Ready, Ros2Run, StateConsumer};
use super::rt::{
    as_buses, boxed_buses, bus_names, poll_recv, print_report, run_cycle, wall_buses, Ports,
    SimThread,
};
use super::sinks::{OutputPlan, Sinks};
use super::trajectory::{finish, run_demo_lockstep, DemoArgs};

/// State-port values queued toward the consumers (at 250 Hz: a quarter of a second).
const STATE_QUEUE: usize = 64;
/// States queued toward the ROS 2 node (it publishes at ≤ 50 Hz and keeps only the latest).
const NODE_STATE_QUEUE: usize = 16;

#[derive(Args, Debug)]
pub(crate) struct DriveArgs {
    /// CAN bus: an interface (vcan0, can0) or socketcand://HOST:PORT/CHANNEL. A platform on
    /// two buses takes two, in order: the first `--bus` serves the wheels with `bus = 0`, the
    /// second those with `bus = 1`.
    #[arg(long, required = true)]
    pub(crate) bus: Vec<String>,
    /// Motion commands as JSON Lines from this file, or `-` for stdin (see README "Driving
    /// the platform live"). Without it the platform holds at rest until stopped.
    #[arg(long, value_name = "FILE|-")]
    pub(crate) commands: Option<PathBuf>,
    #[command(flatten)]
    pub(crate) ros2: Ros2Run,
    #[command(flatten)]
    pub(crate) common: CommonRun,
}

/// Where a run's commands come from.
pub(crate) enum Source {
    /// None: the platform holds (commands may come from elsewhere, e.g. ROS 2).
    None,
    /// A command file, read whole and checked before the run starts.
    File(Vec<TimedCommand>),
    /// Lines on stdin, as they come.
    Stdin,
    /// The keyboard (teleop).
    Keyboard,
}

impl Source {
    /// `--commands FILE|-` (files are read and checked now).
    pub(crate) fn from_arg(arg: Option<&Path>) -> Result<Source, CliError> {
        Ok(match arg {
            None => Source::None,
            Some(p) if p.as_os_str() == "-" => Source::Stdin,
            Some(p) => Source::File(commands::load_file(p)?),
        })
    }
}

/// Sends `kind` at `at` (sleeping until then, or giving up on `stop`); false once the cycle is
/// gone. A motion command that finds the queue full is dropped and counted by the channel
/// (the status log reports drops, at most once a second); stop and re-arm take the priority
/// lane and are never dropped.
fn send_at(tx: &CommandSender, stop: &AtomicBool, at: Instant, kind: CommandKind) -> bool {
    loop {
        if stop.load(Ordering::SeqCst) {
            return false;
        }
        let now = Instant::now();
        if now >= at {
            break;
        }
        std::thread::sleep((at - now).min(Duration::from_millis(20)));
    }
    // The cycle stamps the event with the time it takes it.
    !matches!(
        tx.try_send(CommandEvent { t: 0.0, kind }),
        Err(TrySendError::Disconnected(_))
    )
}

/// Reads the rest of an overlong line and forgets it: at most one buffer of the reader is held
/// at a time, however long the line (`/dev/zero`, a line of a gigabyte). Returns the bytes
/// skipped; stops at the newline (consumed), at the end of the input or on `stop`.
fn skip_rest_of_line(r: &mut impl BufRead, stop: &AtomicBool) -> std::io::Result<u64> {
    let mut skipped = 0u64;
    loop {
        if stop.load(Ordering::Relaxed) {
            return Ok(skipped);
        }
        let buf = match r.fill_buf() {
            Ok(b) => b,
            Err(e) if e.kind() == std::io::ErrorKind::Interrupted => continue,
            Err(e) => return Err(e),
        };
        if buf.is_empty() {
            return Ok(skipped);
        }
        match buf.iter().position(|&b| b == b'\n') {
            Some(i) => {
                r.consume(i + 1);
                return Ok(skipped + i as u64 + 1);
            }
            None => {
                let n = buf.len();
                r.consume(n);
                skipped += n as u64;
            }
        }
    }
}

/// Timed stdin lines (with `t`) that may wait for their time at once; more are dropped
/// (counted, with a warning).
const STDIN_SCHEDULE: usize = 1024;

/// The stdin rule for `t`: a line without `t` acts when it is read; a line with `t` acts at
/// that time (seconds after the driver was ready; at once when that has passed), and never
/// holds back the lines read after it: they are read as they come, so a stop (without `t`)
/// always acts at once. The timed lines wait here, in time order, for the scheduler thread.
struct StdinSchedule {
    state: Mutex<Pending>,
    wake: std::sync::Condvar,
}

#[derive(Default)]
struct Pending {
    lines: Vec<(Instant, u64, CommandKind)>,
    next_seq: u64,
    eof: bool,
}

impl StdinSchedule {
    fn new() -> Self {
        Self {
            state: Mutex::new(Pending {
                lines: Vec::with_capacity(STDIN_SCHEDULE),
                ..Default::default()
            }),
            wake: std::sync::Condvar::new(),
        }
    }

    fn lock(&self) -> std::sync::MutexGuard<'_, Pending> {
        self.state.lock().unwrap_or_else(|e| e.into_inner())
    }

    /// Queues a timed line; false when the schedule is full.
    fn push(&self, due: Instant, kind: CommandKind) -> bool {
        let mut g = self.lock();
        if g.lines.len() >= STDIN_SCHEDULE {
            return false;
        }
        let seq = g.next_seq;
        g.next_seq += 1;
        g.lines.push((due, seq, kind));
        drop(g);
        self.wake.notify_one();
        true
    }

    /// Whether nothing waits (a due line may then be sent directly, in reading order).
    fn is_empty(&self) -> bool {
        self.lock().lines.is_empty()
    }

    fn end(&self) {
        self.lock().eof = true;
        self.wake.notify_one();
    }

    /// Sends each waiting line at its time, earliest first (equal times in reading order);
    /// after the end of stdin, once nothing waits, the end of the stream.
    fn run(&self, tx: &CommandSender, stop: &AtomicBool, end: impl Fn(&CommandSender, &str)) {
        let mut g = self.lock();
        loop {
            if stop.load(Ordering::SeqCst) {
                return;
            }
            let next = g
                .lines
                .iter()
                .enumerate()
                .min_by_key(|(_, (due, seq, _))| (*due, *seq))
                .map(|(i, (due, _, _))| (i, *due));
            let now = Instant::now();
            let wait = match next {
                None if g.eof => {
                    drop(g);
                    end(tx, "stdin");
                    return;
                }
                None => Duration::from_millis(100),
                Some((i, due)) if due <= now => {
                    let (_, _, kind) = g.lines.swap_remove(i);
                    drop(g);
                    if !send_at(tx, stop, now, kind) {
                        return;
                    }
                    g = self.lock();
                    continue;
                }
                Some((_, due)) => (due - now).min(Duration::from_millis(100)),
            };
            g = match self.wake.wait_timeout(g, wait) {
                Ok((g, _)) => g,
                Err(e) => e.into_inner().0,
            };
        }
    }
}

/// Warnings about timed stdin lines: the first that waits more than a second is named, later
/// ones (and lines dropped because the schedule is full) are counted at most every 10 s.
struct TimedLog {
    waiting: u64,
    dropped: u64,
    last: Option<Instant>,
}

impl TimedLog {
    fn new() -> Self {
        Self {
            waiting: 0,
            dropped: 0,
            last: None,
        }
    }

    fn quiet(&self) -> bool {
        self.last
            .is_some_and(|at| at.elapsed() < Duration::from_secs(10))
    }

    fn ahead(&mut self, line: usize, t: f64, ahead: Duration) {
        self.waiting += 1;
        if self.last.is_none() {
            tracing::warn!(
                "stdin line {line}: `t` = {t} is {:.1} s ahead: the line waits until then; lines read meanwhile act as they come (without `t`: at once, a stop too)",
                ahead.as_secs_f64()
            );
        } else if !self.quiet() {
            tracing::warn!(
                "stdin: {} lines with `t` ahead waited for their time so far",
                self.waiting
            );
        } else {
            return;
        }
        self.last = Some(Instant::now());
    }

    fn full(&mut self, line: usize) {
        self.dropped += 1;
        if !self.quiet() {
            tracing::warn!(
                "stdin line {line}: {STDIN_SCHEDULE} lines already wait for their `t`: dropped ({} in all)",
                self.dropped
            );
            self.last = Some(Instant::now());
        }
    }
}

/// Starts the thread of a command source (none for [`Source::None`]). With `ends_run`, the
/// end of a file or of stdin ends the stream (the run ends once at rest); without it (another
/// source such as ROS 2 goes on) it only lets the command timeout stop the platform.
pub(crate) fn start_source(
    source: Source,
    tx: CommandSender,
    ready: Arc<Ready>,
    stop: Arc<AtomicBool>,
    platform: &Platform,
    ends_run: bool,
) -> Result<(), CliError> {
    let end = move |tx: &CommandSender, what: &str| {
        if ends_run {
            tracing::info!(
                "end of {what}: the command timeout stops the platform, then the run ends"
            );
            let _ = tx.try_send(CommandEvent {
                t: 0.0,
                kind: CommandKind::EndOfStream,
            });
        } else {
            tracing::info!(
                "end of {what}: the command timeout stops the platform; other sources go on"
            );
        }
    };
    let p = platform.clone();
    let spawn = |name: &str, f: Box<dyn FnOnce() + Send>| {
        std::thread::Builder::new()
            .name(name.into())
            .spawn(f)
            .map(|_| ())
            .map_err(|e| CliError::Usage(format!("cannot start the command source: {e}")))
    };
    match source {
        Source::None => Ok(()),
        Source::File(cmds) => spawn(
            "rollbase-commands",
            Box::new(move || {
                let Some(t0) = ready.wait(&stop) else { return };
                for c in cmds {
                    let at = t0 + Duration::from_secs_f64(c.t.unwrap_or(0.0));
                    if !send_at(&tx, &stop, at, c.kind) {
                        return;
                    }
                }
                end(&tx, "the command file");
            }),
        ),
        Source::Stdin => spawn(
            "rollbase-stdin",
            Box::new(move || {
                let Some(t0) = ready.wait(&stop) else { return };
                let schedule = Arc::new(StdinSchedule::new());
                {
                    let (schedule, tx, stop) = (schedule.clone(), tx.clone(), stop.clone());
                    let started = std::thread::Builder::new()
                        .name("rollbase-stdin-t".into())
                        .spawn(move || schedule.run(&tx, &stop, end));
                    if let Err(e) = started {
                        tracing::error!("stdin: cannot start the thread of timed lines: {e}");
                        return;
                    }
                }
                let stdin = std::io::stdin();
                let mut lock = stdin.lock();
                let mut buf = Vec::new();
                let mut line = 0usize;
                let mut log = TimedLog::new();
                loop {
                    buf.clear();
                    let r = (&mut lock)
                        .take(commands::MAX_LINE_BYTES as u64 + 2)
                        .read_until(b'\n', &mut buf);
                    match r {
                        Ok(0) => break,
                        Ok(_) => {}
                        Err(e) => {
                            tracing::error!("stdin: {e}; treating it as the end of the stream");
                            break;
                        }
                    }
                    line += 1;
                    if buf.len() > commands::MAX_LINE_BYTES + 1 && !buf.ends_with(b"\n") {
                        // Skip the rest of the overlong line, holding none of it.
                        let rest = skip_rest_of_line(&mut lock, &stop);
                        tracing::warn!(
                            "stdin line {line}: longer than {} bytes ({}); skipped",
                            commands::MAX_LINE_BYTES,
                            match &rest {
                                Ok(k) => format!("{} bytes", buf.len() as u64 + k),
                                Err(e) => format!("reading it failed: {e}"),
                            }
                        );
                        if rest.is_err() {
                            break;
                        }
                        continue;
                    }
                    let Ok(text) = std::str::from_utf8(&buf) else {
                        tracing::warn!("stdin line {line}: not UTF-8 text; skipped");
                        continue;
                    };
                    match commands::parse_line(text, "stdin", line) {
                        Ok(Some(c)) => {
                            let now = Instant::now();
                            let due = c.t.map(|t| t0 + Duration::from_secs_f64(t));
                            match (c.t, due) {
                                (Some(t), Some(due)) if due > now || !schedule.is_empty() => {
                                    if due > now + Duration::from_secs(1) {
                                        log.ahead(line, t, due - now);
                                    }
                                    if !schedule.push(due, c.kind) {
                                        log.full(line);
                                        tx.note_dropped();
                                    }
                                }
                                _ => {
                                    if !send_at(&tx, &stop, now, c.kind) {
                                        schedule.end();
                                        return;
                                    }
                                }
                            }
                        }
                        Ok(None) => {}
                        Err(e) => tracing::warn!("{e}; skipped"),
                    }
                }
                // The schedule sends the end of the stream once every timed line went out.
                schedule.end();
            }),
        ),
        Source::Keyboard => super::teleop::start(tx, ready, stop, &p),
    }
}

/// Logs what a service operator needs to know, from the records: state changes with their
/// reasons, command timeouts and rejections, what limits the motion.
pub(crate) struct StatusLog {
    state: Option<SupervisorState>,
    timeouts: u64,
    rejected: u64,
    limiting: rollbase_control::service::ports::Limiting,
    last_limit_log: Option<Instant>,
    /// Dropped commands reported so far, and when.
    dropped: u64,
    last_drop_log: Option<Instant>,
}

impl StatusLog {
    pub(crate) fn new() -> Self {
        Self {
            state: None,
            timeouts: 0,
            rejected: 0,
            limiting: Default::default(),
            last_limit_log: None,
            dropped: 0,
            last_drop_log: None,
        }
    }

    pub(crate) fn take(&mut self, r: &CycleRecord) {
        if self.state != Some(r.state) {
            match (r.state, r.reason) {
                (SupervisorState::Fault, Some(reason)) => {
                    tracing::error!("fault: {reason}; controlled stop, latched until re-armed")
                }
                (s, _) => tracing::info!("state: {}", s.name()),
            }
            self.state = Some(r.state);
        }
        let c = &r.commands;
        if c.timeouts > self.timeouts {
            tracing::warn!("no valid command for the command timeout: stopping (steering held); the next command resumes");
            self.timeouts = c.timeouts;
        }
        // A source that floods the queue drops commands every cycle: one line a second at
        // most, with the count since the last line and in all.
        if c.dropped > self.dropped
            && self
                .last_drop_log
                .is_none_or(|t| t.elapsed() >= Duration::from_secs(1))
        {
            tracing::warn!(
                "command queue full ({MOTION_QUEUE} motion commands waiting): {} commands dropped since the last report, {} in all (stop and re-arm are never dropped)",
                c.dropped - self.dropped,
                c.dropped
            );
            self.dropped = c.dropped;
            self.last_drop_log = Some(Instant::now());
        }
        if c.rejected > self.rejected {
            match c.last_rejection {
                Some(e) => tracing::warn!("command rejected: {e}"),
                None => tracing::warn!("command rejected"),
            }
            self.rejected = c.rejected;
        }
        use rollbase_control::service::ports::Limiting;
        let l = r.shaping.limiting;
        if l != self.limiting {
            let quiet_for = self
                .last_limit_log
                .is_none_or(|t| t.elapsed() > Duration::from_secs(2));
            if !matches!(l, Limiting::None | Limiting::Timeout | Limiting::Stop) && quiet_for {
                tracing::debug!(
                    "slowing: {} (command scaled by {:.2})",
                    l.name(),
                    r.shaping.scale
                );
                self.last_limit_log = Some(Instant::now());
            }
            self.limiting = l;
        }
    }
}

/// Everything the real-time base service needs besides its bus.
struct Service {
    core: CycleCore,
    sinks: Sinks,
    stop: Arc<AtomicBool>,
    signalled: Arc<AtomicBool>,
    origin: f64,
}

/// The real-time base service on `buses` (one per platform bus): sources → cycle → records
/// and state.
fn serve(
    s: &mut Service,
    buses: &mut [&mut dyn CanBus],
    source: Source,
    common: &CommonRun,
    on_state: Option<StateConsumer>,
    ros2: Option<Ros2Options>,
    cpu: Option<usize>,
) -> Result<(), CliError> {
    let (cmd_tx, cmd_rx) = command_channel(MOTION_QUEUE, PRIORITY_LANE);
    let (state_tx, state_rx) = std::sync::mpsc::sync_channel::<BaseState>(STATE_QUEUE);
    let ready = Arc::new(Ready::default());
    let platform = s.core.platform().clone();
    // The ROS 2 node: a second command source on the same port, and a state consumer. It
    // starts before the cycle so that a DDS failure refuses the run before the platform moves.
    let node = match ros2 {
        Some(mut opts) => {
            // The robot model on robot_description, with the joint names of joint_states.
            opts.robot_description = Some(
                rollbase::ros2::urdf::generate(&platform, &opts.joint_names)
                    .map_err(|e| CliError::Usage(format!("--ros2-joint-names: {e}")))?,
            );
            let (node_tx, node_rx) = std::sync::mpsc::sync_channel::<BaseState>(NODE_STATE_QUEUE);
            let handle = spawn_node(opts.clone(), cmd_tx.clone(), node_rx, Instant::now())?;
            tracing::info!(
                "ROS 2 node {} on DDS domain {}: commands on {} and {}, state on {}, {}, {}, {}{}, robot_description; services {}/stop and {}/rearm",
                opts.node_fqn(),
                handle.domain_id(),
                opts.topic(&opts.cmd_vel_topic),
                opts.topic(&opts.leg_topic),
                opts.topic("odom"),
                opts.topic("joint_states"),
                opts.topic("diagnostics"),
                opts.topic("supervisor_state"),
                if opts.publish_tf { ", tf" } else { "" },
                opts.node_fqn(),
                opts.node_fqn(),
            );
            Some((handle, node_tx))
        }
        None => None,
    };
    let (node, node_tx) = match node {
        Some((h, tx)) => (Some(h), Some(tx)),
        None => (None, None),
    };
    start_source(
        source,
        cmd_tx.clone(),
        ready.clone(),
        s.stop.clone(),
        &platform,
        node.is_none(),
    )?;
    // The state port's consumer: readiness for the sources, then whoever listens.
    let consumer = {
        let ready = ready.clone();
        let mut on_state = on_state;
        std::thread::Builder::new()
            .name("rollbase-state".into())
            .spawn(move || {
                // Polled, never blocked on: see `rt::poll_recv` (the cycle sends on it).
                loop {
                    let st = match poll_recv(&state_rx, Duration::from_secs(1)) {
                        Ok(st) => st,
                        Err(std::sync::mpsc::RecvTimeoutError::Timeout) => continue,
                        Err(std::sync::mpsc::RecvTimeoutError::Disconnected) => break,
                    };
                    // Ready: tracking, or faulted before it could (a device that did not boot
                    // or home): the sources run from then on, so a `rearm` clears a boot-time
                    // fault and the end of the stream ends the run whatever its state.
                    if matches!(st.state, SupervisorState::Tracking | SupervisorState::Fault) {
                        ready.set();
                    }
                    if let Some(tx) = &node_tx {
                        // The node decimates to its rates; when it lags, it misses a state
                        // rather than delaying this thread.
                        let _ = tx.try_send(st);
                    }
                    if let Some(f) = on_state.as_mut() {
                        f(&st);
                    }
                }
            })
            .map_err(|e| CliError::Usage(format!("cannot start the state consumer: {e}")))?
    };
    let mut status = StatusLog::new();
    tracing::info!(
        "driving on {} ({} wheels, {} profile, {} Hz): following commands once armed; SIGINT, SIGTERM, SIGHUP or SIGQUIT stops",
        bus_names(buses),
        platform.n(),
        platform.protocol,
        platform.cycle_hz
    );
    let report = run_cycle(
        &mut s.core,
        buses,
        &mut s.sinks,
        &s.stop,
        Ports {
            commands: Some(cmd_rx),
            states: Some(&state_tx),
            cpu,
        },
        s.origin,
        &mut |r, _| status.take(r),
    )?;
    drop(state_tx);
    drop(cmd_tx);
    let _ = consumer.join();
    if let Some(n) = node {
        let st = n.stats();
        tracing::info!(
            "ROS 2 node: {} commands passed on ({} dropped, {} refused), {} messages published ({} failed), {} service calls ({} cyclone, {} enhanced mapping), undecodable samples {:?}, oversized samples dropped {:?}, {} incompatible-QoS events, announced with {}",
            st.commands_sent.load(Ordering::Relaxed),
            st.commands_dropped.load(Ordering::Relaxed),
            st.commands_refused.load(Ordering::Relaxed),
            st.published.load(Ordering::Relaxed),
            st.publish_errors.load(Ordering::Relaxed),
            st.services_answered.load(Ordering::Relaxed),
            st.services_cyclone.load(Ordering::Relaxed),
            st.services_enhanced.load(Ordering::Relaxed),
            st.undecodable_by_endpoint(),
            st.oversized_by_endpoint(),
            st.qos_incompatible.load(Ordering::Relaxed),
            st.announced_layout()
                .map_or("no discovery layout (no ROS 2 peer seen)".to_string(), |l| format!("the {l}")),
        );
        n.shutdown();
    }
    print_report(&report, common.json);
    Ok(())
}

/// `rollbase drive`.
pub(crate) fn drive(a: DriveArgs) -> Result<i32, CliError> {
    // Everything is validated before the bus is opened or a file created.
    let platform = load_platform_on(a.common.config.as_deref(), a.common.profile, &a.bus)?;
    let cfg = runtime_config(&a.common, None)?;
    let source = Source::from_arg(a.commands.as_deref())?;
    let ros2 = a.ros2.options(platform.n())?;
    let mut plan = OutputPlan::of(&a.common, "drive");
    if let Some(o) = &ros2 {
        plan.ros2 = o.clone();
    }
    plan.check()?;
    let core = CycleCore::new_live(platform, cfg)?;
    let mut canbuses: Vec<Box<dyn CanBus>> = a
        .bus
        .iter()
        .map(|b| bus::open(b))
        .collect::<Result<_, _>>()?;
    let mut buses = boxed_buses(&mut canbuses);
    let origin = unix_now();
    let stop = Arc::new(AtomicBool::new(false));
    let signalled = install_signals(stop.clone(), SignalAction::ControlledStop);
    let mut meta = BTreeMap::new();
    meta.insert("bus".into(), a.bus.join(","));
    meta.insert("mode".into(), "drive".into());
    let names: Vec<&str> = buses.iter().map(|b| b.name()).collect();
    let sinks = Sinks::new("drive", &plan, &names, origin, meta)?;
    let mut s = Service {
        core,
        sinks,
        stop,
        signalled,
        origin,
    };
    serve(&mut s, &mut buses, source, &a.common, None, ros2, None)?;
    finish(
        s.sinks,
        &s.core,
        &a.common,
        s.signalled.load(Ordering::SeqCst),
    )
}

/// `rollbase demo --commands FILE|-` and `rollbase demo --teleop`: the base service with the
/// simulated platform in-process, starting at rest (legs nominal).
pub(crate) fn demo_live(a: DemoArgs) -> Result<i32, CliError> {
    // A platform on two buses runs on two in-process buses (real time) or two virtual buses
    // (--lockstep).
    let platform = load_platform_profile(a.common.config.as_deref(), a.common.profile)?;
    let cfg: RuntimeConfig = runtime_config(&a.common, None)?;
    let source = if a.teleop {
        Source::Keyboard
    } else {
        Source::from_arg(a.commands.as_deref())?
    };
    if a.lockstep && !matches!(source, Source::File(_)) {
        return Err(CliError::Usage(
            "--lockstep needs --commands FILE (virtual time cannot wait for stdin or a keyboard)"
                .into(),
        ));
    }
    let faults = match &a.faults {
        Some(p) => FaultSchedule::load(p)?,
        None => FaultSchedule::default(),
    };
    let plant = match &a.plant {
        Some(p) => PlantConfig::load(p)?,
        None => PlantConfig::default(),
    };
    let ros2 = a.ros2.options(platform.n())?;
    if a.lockstep && ros2.is_some() {
        return Err(CliError::Usage(
            "--ros2 runs in real time: drop --lockstep (virtual time cannot wait for ROS 2 commands)"
                .into(),
        ));
    }
    let name = if a.teleop {
        "teleop"
    } else if a.commands.is_none() && ros2.is_some() {
        "ros2"
    } else {
        "commands"
    };
    let mut plan = OutputPlan::of(&a.common, name);
    if let Some(o) = &ros2 {
        plan.ros2 = o.clone();
    }
    plan.check()?;
    let core = CycleCore::new_live(platform.clone(), cfg)?;
    let sim = Simulator::with_config(
        &platform,
        SimConfig {
            plant,
            faults,
            seed: a.seed,
            ..SimConfig::default()
        },
    )?;
    let origin = if a.lockstep { 0.0 } else { unix_now() };
    let stop = Arc::new(AtomicBool::new(false));
    let signalled = install_signals(stop.clone(), SignalAction::ControlledStop);
    let mut meta = BTreeMap::new();
    meta.insert("scenario".into(), name.into());
    meta.insert(
        "mode".into(),
        if a.lockstep { "lockstep" } else { "realtime" }.into(),
    );
    meta.insert("seed".into(), a.seed.to_string());
    let sinks = Sinks::new(
        name,
        &plan,
        super::trajectory::demo_interfaces(platform.buses()),
        origin,
        meta,
    )?;
    let mut s = Service {
        core,
        sinks,
        stop,
        signalled,
        origin,
    };
    match (a.lockstep, source) {
        (true, Source::File(cmds)) => {
            let events: Vec<CommandEvent> = cmds
                .iter()
                .map(|c| CommandEvent {
                    t: c.t.unwrap_or(0.0),
                    kind: c.kind,
                })
                .chain(std::iter::once(CommandEvent {
                    t: cmds.last().and_then(|c| c.t).unwrap_or(0.0),
                    kind: CommandKind::EndOfStream,
                }))
                .collect();
            let last = events.last().map_or(0.0, |e| e.t);
            let max_cycles = ((last + 60.0) * platform.cycle_hz) as u64;
            run_demo_lockstep(
                &mut s.core,
                sim,
                &mut s.sinks,
                &s.stop,
                &events,
                max_cycles,
                a.seed,
                a.common.json,
            )?;
        }
        (true, _) => return Err(CliError::Usage(
            "--lockstep needs --commands FILE (virtual time cannot wait for stdin or a keyboard)"
                .into(),
        )),
        (false, source) => {
            let (mut ctrl, sim_nodes) = wall_buses(platform.buses());
            let sim = SimThread::start(sim, sim_nodes)?;
            let on_state: Option<StateConsumer> = if a.teleop {
                Some(super::teleop::status_line())
            } else {
                None
            };
            serve(
                &mut s,
                &mut as_buses(&mut ctrl),
                source,
                &a.common,
                on_state,
                ros2,
                sim.cpu(),
            )?;
            drop(sim);
        }
    }
    finish(
        s.sinks,
        &s.core,
        &a.common,
        s.signalled.load(Ordering::SeqCst),
    )
}
