//! The lockstep driver: the cycle core and a simulated peer on virtual time.

use super::CycleCore;
use crate::model::platform::MAX_BUSES;
use crate::runtime::record::CycleRecord;
use crate::service::ports::CommandEvent;
use crate::supervisor::SupervisorState;
use crate::types::{Pose, MAX_WHEELS};
use rollbase_driver::bus::BusError;
use rollbase_driver::frame::{CanFrame, FrameBuf, TimestampedFrame};
use std::time::Duration;

/// A simulated peer on the bus for lockstep runs (the simulator implements it).
pub trait LockstepPeer {
    /// A frame reached the peer at `now`.
    fn on_frame(&mut self, now: Duration, frame: &CanFrame);
    /// Advance the peer's own time (plant, watchdogs) to `now`.
    fn advance_to(&mut self, now: Duration);
    /// Frames the peer wants to send, with their send times.
    fn drain_tx(&mut self, out: &mut dyn FnMut(Duration, CanFrame));
    /// True pose and legs, when the peer knows them.
    fn truth(&self) -> Option<(Pose, [f64; MAX_WHEELS])> {
        None
    }
    /// True while the peer's fault schedule holds the controller's CAN interface bus-off
    /// at `now` ([`LockstepBus::set_controller_bus_off`]).
    fn controller_bus_off(&self, now: Duration) -> bool {
        let _ = now;
        false
    }
    /// The bus (index into the platform's buses) a frame the peer sent goes out on, for
    /// [`run_lockstep_buses`]. Default: bus 0.
    fn bus_of(&self, frame: &CanFrame) -> usize {
        let _ = frame;
        0
    }
    /// A frame the controller sent on bus `bus`, for [`run_lockstep_buses`]. Default:
    /// [`LockstepPeer::on_frame`].
    fn on_frame_on(&mut self, bus: usize, now: Duration, frame: &CanFrame) {
        let _ = bus;
        self.on_frame(now, frame);
    }
}

/// The lockstep bus: what [`run_lockstep`] needs from the in-process virtual bus.
pub trait LockstepBus {
    /// Sets the bus's virtual time.
    fn set_time(&mut self, t: Duration);
    /// Sends from the controller's node.
    fn controller_send(&mut self, f: &CanFrame) -> Result<(), BusError>;
    /// Receives at the controller's node (non-blocking).
    fn controller_recv(&mut self) -> Result<Option<TimestampedFrame>, BusError>;
    /// Sends from the simulator's node.
    fn peer_send(&mut self, f: &CanFrame) -> Result<(), BusError>;
    /// Receives at the simulator's node (non-blocking).
    fn peer_recv(&mut self) -> Result<Option<TimestampedFrame>, BusError>;
    /// Puts the controller's CAN interface in bus-off (`true`) or restarts it (`false`);
    /// each change reaches the controller once, as an error frame. A bus without this
    /// ability ignores it.
    fn set_controller_bus_off(&mut self, off: bool) {
        let _ = off;
    }
}

/// The in-process virtual bus on a virtual clock with a controller node and a simulator node.
pub struct VirtualLockstepBus {
    /// The bus (virtual clock).
    pub bus: rollbase_driver::bus::virtual_bus::VirtualBus,
    /// The controller's node.
    pub controller: rollbase_driver::bus::virtual_bus::VirtualNode,
    /// The simulator's node.
    pub peer: rollbase_driver::bus::virtual_bus::VirtualNode,
}

impl VirtualLockstepBus {
    /// A virtual-clock bus with the given fault model and seed.
    pub fn new(faults: rollbase_driver::fault::FaultModel, seed: u64) -> Self {
        use rollbase_driver::bus::virtual_bus::{BusClock, VirtualBus, VirtualBusConfig};
        let bus = VirtualBus::new(VirtualBusConfig {
            clock: BusClock::Virtual,
            faults,
            seed,
            queue_capacity: 1024,
        });
        let controller = bus.node("controller");
        let peer = bus.node("simulator");
        Self {
            bus,
            controller,
            peer,
        }
    }
}

impl LockstepBus for VirtualLockstepBus {
    fn set_time(&mut self, t: Duration) {
        self.bus.set_time(t);
    }
    fn controller_send(&mut self, f: &CanFrame) -> Result<(), BusError> {
        self.controller.send(f)
    }
    fn controller_recv(&mut self) -> Result<Option<TimestampedFrame>, BusError> {
        self.controller.try_recv()
    }
    fn peer_send(&mut self, f: &CanFrame) -> Result<(), BusError> {
        self.peer.send(f)
    }
    fn peer_recv(&mut self) -> Result<Option<TimestampedFrame>, BusError> {
        self.peer.try_recv()
    }
    fn set_controller_bus_off(&mut self, off: bool) {
        self.bus.set_bus_off(self.controller.name(), off);
    }
}

/// Timing and outcome of a lockstep run.
#[derive(Clone, Debug, Default)]
pub struct LockstepReport {
    /// Cycles run.
    pub cycles: u64,
    /// Wall-clock compute times of the cycles' control steps, for reports only (a fixed-size
    /// histogram: a run of any length uses the same memory).
    pub compute: super::TimeHistogram,
    /// Their sum (s).
    pub compute_total_s: f64,
    /// Wall time of the whole run (s).
    pub wall_s: f64,
}

/// Why a lockstep run refused to start.
#[derive(Clone, Debug, PartialEq, Eq, thiserror::Error)]
pub enum LockstepError {
    /// The number of lockstep buses given differs from the number the platform's wheels are
    /// on (the one-bus runners give one).
    #[error(
        "the platform's wheels are on {platform} CAN bus(es) but {given} lockstep bus(es) were \
         given: give one bus per platform bus (run_lockstep_buses; bus b carries the wheels \
         with bus = b)"
    )]
    BusCount {
        /// Buses the platform's wheels are on ([`Platform::buses`](crate::Platform::buses),
        /// at least one).
        platform: usize,
        /// Buses given.
        given: usize,
    },
}

/// What one lockstep cycle may do differently (fault campaigns, measurements). The default
/// is a normal cycle.
#[derive(Default)]
pub struct StepHooks<'a> {
    /// The controller is dead this cycle: no SYNC, no control step, no SETPOINT; its receive
    /// queue is drained so it cannot overflow.
    pub controller_silent: bool,
    /// The controller's interface is down this cycle: its sends and receives fail (the core
    /// sees a bus error) and what reached it is lost.
    pub iface_down: bool,
    /// Sees every frame the controller receives and emits what the controller gets instead
    /// (the frame itself, a changed frame, extra frames, or nothing).
    #[allow(clippy::type_complexity)]
    pub on_rx: Option<&'a mut dyn FnMut(&CanFrame, &mut dyn FnMut(CanFrame))>,
    /// Called with `true` right before and `false` right after each group of calls into the
    /// cycle core (`start_cycle`; `on_frame` … `finish_cycle`): to count allocations or time
    /// the core alone.
    pub around_core: Option<&'a mut dyn FnMut(bool)>,
    /// The cycle woke this long (s) after its start: the SYNC goes out late (the core is
    /// told, [`CycleCore::sync_sent_at`]) and the feedback window counts from it, as in the
    /// real-time runtime. 0 (the default): on time.
    pub sync_delay: f64,
}

/// The lockstep driver's own state between cycles (time, the peer's queued frames, buffers).
pub struct LockstepState {
    k: u64,
    period: f64,
    window: f64,
    pending: Vec<(Duration, CanFrame)>,
    /// The controller's frames per bus.
    outs: [FrameBuf; MAX_BUSES],
    /// What the controller received, as (bus, time, frame).
    rx_buf: Vec<(usize, f64, CanFrame)>,
    /// Frames the controller lost because its interface was down.
    pub lost_iface_down: u64,
}

impl LockstepState {
    /// State for `core`'s platform and feedback window, at cycle 0.
    pub fn new(core: &CycleCore) -> Self {
        let period = core.platform().dt();
        Self {
            k: 0,
            period,
            window: core.config().feedback_window.clamp(0.0, period),
            pending: Vec::with_capacity(64),
            outs: [FrameBuf::new(), FrameBuf::new()],
            rx_buf: Vec::with_capacity(64),
            lost_iface_down: 0,
        }
    }

    /// Cycles run so far.
    pub fn cycle(&self) -> u64 {
        self.k
    }

    /// Start time of the next cycle (s).
    pub fn time(&self) -> f64 {
        self.k as f64 * self.period
    }

    /// The feedback window inside the cycle (s after SYNC).
    pub fn window(&self) -> f64 {
        self.window
    }

    /// The peer's frames sent up to `until` onto their buses ([`LockstepPeer::bus_of`]), in
    /// time order (a stable sort keeps the peer's order among equal send times).
    fn flush_peer(
        &mut self,
        buses: &mut [&mut dyn LockstepBus],
        peer: &mut dyn LockstepPeer,
        until: Duration,
    ) {
        let pending = &mut self.pending;
        peer.drain_tx(&mut |t, f| pending.push((t, f)));
        pending.sort_by_key(|(t, _)| *t);
        let mut sent = 0;
        for (t, f) in pending.iter() {
            if *t > until {
                break;
            }
            let b = peer.bus_of(f).min(buses.len() - 1);
            buses[b].set_time(*t);
            // A failed send from the simulated peer is the same as a lost frame.
            let _ = buses[b].peer_send(f);
            sent += 1;
        }
        pending.drain(..sent);
    }
}

/// What the controller sent reaches the peer (on one bus as [`LockstepPeer::on_frame`], on
/// several with the bus named).
fn deliver_to_peer(buses: &mut [&mut dyn LockstepBus], peer: &mut dyn LockstepPeer) {
    let one = buses.len() == 1;
    for (b, bus) in buses.iter_mut().enumerate() {
        while let Ok(Some(f)) = bus.peer_recv() {
            if one {
                peer.on_frame(f.timestamp, &f.frame);
            } else {
                peer.on_frame_on(b, f.timestamp, &f.frame);
            }
        }
    }
}

/// Everything the controller's nodes hold now into `st.rx_buf` (cleared first; several
/// buses' frames in time order), through the hooks (lost while the interface is down,
/// transformed by `on_rx`).
fn receive(
    st: &mut LockstepState,
    core: &mut CycleCore,
    buses: &mut [&mut dyn LockstepBus],
    hooks: &mut StepHooks<'_>,
) {
    st.rx_buf.clear();
    for (b, bus) in buses.iter_mut().enumerate() {
        loop {
            match bus.controller_recv() {
                Ok(Some(_)) if hooks.iface_down => st.lost_iface_down += 1,
                Ok(Some(f)) => {
                    let t = f.timestamp.as_secs_f64();
                    let buf = &mut st.rx_buf;
                    match hooks.on_rx.as_mut() {
                        Some(h) => h(&f.frame, &mut |g| buf.push((b, t, g))),
                        None => buf.push((b, t, f.frame)),
                    }
                }
                Ok(None) => break,
                // A controller state change (error frame): counted, and on bus-off a fault;
                // the frames behind it are still read.
                Err(e) if e.bus_event().is_some() => {
                    if let Some(ev) = e.bus_event() {
                        core.report_bus_event(b, ev);
                    }
                }
                Err(_) => {
                    core.report_bus_error();
                    break;
                }
            }
        }
    }
    // Several buses' frames in time order (one bus keeps the order it delivered them in).
    if buses.len() > 1 {
        st.rx_buf.sort_by(|a, b| a.1.total_cmp(&b.1));
    }
}

/// The received frames into the core (with their bus when there are several).
fn take_frames(st: &LockstepState, core: &mut CycleCore, buses: usize) {
    for (b, t, f) in &st.rx_buf {
        if buses == 1 {
            core.on_frame(f, *t);
        } else {
            core.on_frame_on(*b, f, *t);
        }
    }
}

/// Sends each bus's frames from the controller: a bus-off send failure is the bus-off state
/// (already reported by its error frame; reported again, not counted twice), any other
/// failure a bus error.
fn send_out(
    st: &LockstepState,
    core: &mut CycleCore,
    buses: &mut [&mut dyn LockstepBus],
    down: bool,
) {
    for (b, bus) in buses.iter_mut().enumerate() {
        for f in st.outs[b].as_slice() {
            if down {
                core.report_bus_error();
                continue;
            }
            match bus.controller_send(f) {
                Ok(()) => {}
                Err(e) => match e.bus_event() {
                    Some(ev) => core.report_bus_event(b, ev),
                    None => core.report_bus_error(),
                },
            }
        }
    }
}

/// One lockstep cycle on one bus: [`lockstep_cycle_buses`] with `bus` as the only one.
pub fn lockstep_cycle(
    st: &mut LockstepState,
    core: &mut CycleCore,
    bus: &mut dyn LockstepBus,
    peer: &mut dyn LockstepPeer,
    hooks: &mut StepHooks<'_>,
) -> bool {
    lockstep_cycle_buses(st, core, &mut [bus], peer, hooks)
}

/// One lockstep cycle: the peer catches up to the cycle start (its frames go out in time
/// order, each on its bus), SYNC on every bus, the peer answers, frames up to the end of the
/// feedback window reach the controller, the control step, the setpoints reach the peer.
/// `buses[b]` carries the platform's bus `b` (the caller gives one per platform bus; the
/// runners check it). The hooks act on every bus. The record carries the ground truth at the
/// SYNC (when the modules sample their encoders) and virtual timing. Returns `false` when the
/// controller was silent this cycle (no record was made).
pub fn lockstep_cycle_buses(
    st: &mut LockstepState,
    core: &mut CycleCore,
    buses: &mut [&mut dyn LockstepBus],
    peer: &mut dyn LockstepPeer,
    hooks: &mut StepHooks<'_>,
) -> bool {
    let nb = buses.len().clamp(1, MAX_BUSES);
    let buses = &mut buses[..nb];
    let k = st.k;
    st.k += 1;
    let t0 = Duration::from_secs_f64(k as f64 * st.period);
    let delay = if hooks.sync_delay.is_finite() {
        // At most until the window still closes before the next cycle starts.
        hooks
            .sync_delay
            .clamp(0.0, 0.99 * (st.period - st.window).max(0.0))
    } else {
        0.0
    };
    // The SYNC's send time; exactly t0 when on time (the common case keeps its bits).
    let t_sync = if delay > 0.0 {
        Duration::from_secs_f64(k as f64 * st.period + delay)
    } else {
        t0
    };
    let t_win = Duration::from_secs_f64(k as f64 * st.period + delay + st.window);
    peer.advance_to(t_sync);
    let off = peer.controller_bus_off(t_sync);
    for bus in buses.iter_mut() {
        bus.set_controller_bus_off(off);
    }
    let truth_at_sync = peer.truth();
    st.flush_peer(buses, peer, t_sync);
    for bus in buses.iter_mut() {
        bus.set_time(t_sync);
    }
    if !hooks.controller_silent {
        around(hooks, true);
        core.start_cycle_buses(t0.as_secs_f64(), &mut st.outs[..nb]);
        if delay > 0.0 {
            core.sync_sent_at(t_sync.as_secs_f64());
        }
        around(hooks, false);
        // What came in after the last window (late answers, the devices' answers to the
        // requests sent at the end of the last cycle) is taken now, before the SYNC goes
        // out, as the real-time runtime does; what it made due goes out with the SYNC.
        receive(st, core, buses, hooks);
        around(hooks, true);
        take_frames(st, core, nb);
        core.after_late_frames_buses(t0.as_secs_f64(), &mut st.outs[..nb]);
        around(hooks, false);
        send_out(st, core, buses, hooks.iface_down);
    }
    deliver_to_peer(buses, peer);
    peer.advance_to(t_win);
    st.flush_peer(buses, peer, t_win);
    for bus in buses.iter_mut() {
        bus.set_time(t_win);
    }
    if hooks.controller_silent {
        for bus in buses.iter_mut() {
            while let Ok(Some(_)) = bus.controller_recv() {}
        }
        return false;
    }
    receive(st, core, buses, hooks);
    if hooks.iface_down {
        core.report_bus_error();
    }
    around(hooks, true);
    take_frames(st, core, nb);
    core.finish_cycle_buses(t_win.as_secs_f64(), &mut st.outs[..nb]);
    around(hooks, false);
    send_out(st, core, buses, hooks.iface_down);
    deliver_to_peer(buses, peer);
    let rec = core.record_mut();
    rec.truth = truth_at_sync;
    rec.timing.period_us = st.period * 1e6;
    rec.timing.wakeup_latency_us = 0.0;
    rec.timing.compute_us = 0.0;
    true
}

/// Calls the `around_core` hook, if any.
fn around(hooks: &mut StepHooks<'_>, on: bool) {
    if let Some(h) = hooks.around_core.as_mut() {
        h(on)
    }
}

/// Runs the core and a peer on virtual time until the core is done, `max_cycles` elapse,
/// or `stop_at_cycle` requests an operator stop. Each record is passed to `sink`.
pub fn run_lockstep(
    core: &mut CycleCore,
    bus: &mut dyn LockstepBus,
    peer: &mut dyn LockstepPeer,
    max_cycles: u64,
    stop_at_cycle: Option<u64>,
    sink: &mut dyn FnMut(&CycleRecord, &[[f64; 2]]),
) -> Result<LockstepReport, LockstepError> {
    run_lockstep_with(
        core,
        bus,
        peer,
        &[],
        max_cycles,
        &mut |k| Some(k) == stop_at_cycle,
        sink,
    )
}

/// Runs the base service on virtual time: the core follows `commands` (sorted by time; each
/// event's `t` counts from the first cycle in which the core follows commands, i.e. from the
/// moment the driver is ready, as in a command file) until the core is done (a `Shutdown`
/// event, or the end of the stream and the platform at rest) or `max_cycles` elapse. An event
/// is delivered in the first cycle that starts at or after its time, stamped with that
/// cycle's time. Each record is passed to `sink`. Allocates nothing per cycle.
pub fn run_lockstep_live(
    core: &mut CycleCore,
    bus: &mut dyn LockstepBus,
    peer: &mut dyn LockstepPeer,
    commands: &[CommandEvent],
    max_cycles: u64,
    sink: &mut dyn FnMut(&CycleRecord, &[[f64; 2]]),
) -> Result<LockstepReport, LockstepError> {
    run_lockstep_with(core, bus, peer, commands, max_cycles, &mut |_| false, sink)
}

/// The lockstep driver behind [`run_lockstep`] and [`run_lockstep_live`]: `commands` as in
/// [`run_lockstep_live`] (empty for a trajectory), and `stop(cycle)` asked before every cycle
/// (true once: an operator stop, as from a signal).
pub fn run_lockstep_with(
    core: &mut CycleCore,
    bus: &mut dyn LockstepBus,
    peer: &mut dyn LockstepPeer,
    commands: &[CommandEvent],
    max_cycles: u64,
    stop: &mut dyn FnMut(u64) -> bool,
    sink: &mut dyn FnMut(&CycleRecord, &[[f64; 2]]),
) -> Result<LockstepReport, LockstepError> {
    run_lockstep_buses(core, &mut [bus], peer, commands, max_cycles, stop, sink)
}

/// [`run_lockstep_with`] on every bus of the platform: `buses[b]` carries the frames of the
/// platform's bus `b` (the core's SYNC and setpoints for it, [`CycleCore::start_cycle_buses`];
/// the peer's frames on the bus [`LockstepPeer::bus_of`] names, delivered to the peer with
/// [`LockstepPeer::on_frame_on`]). The cycle is [`lockstep_cycle`]'s without hooks, bus by
/// bus: late frames taken before the SYNC, the feedback window, the setpoints. With one bus it
/// gives [`run_lockstep_with`]'s records. A number of buses other than the platform's is
/// refused before anything runs ([`LockstepError::BusCount`]); so is a two-bus platform given
/// to the one-bus runners.
#[allow(clippy::too_many_arguments)]
pub fn run_lockstep_buses(
    core: &mut CycleCore,
    buses: &mut [&mut dyn LockstepBus],
    peer: &mut dyn LockstepPeer,
    commands: &[CommandEvent],
    max_cycles: u64,
    stop: &mut dyn FnMut(u64) -> bool,
    sink: &mut dyn FnMut(&CycleRecord, &[[f64; 2]]),
) -> Result<LockstepReport, LockstepError> {
    let platform = core.buses().max(1);
    if buses.len() != platform {
        return Err(LockstepError::BusCount {
            platform,
            given: buses.len(),
        });
    }
    let mut report = LockstepReport::default();
    let wall = std::time::Instant::now();
    let period = core.platform().dt();
    let mut st = LockstepState::new(core);
    core.arm();
    let mut ready_at: Option<f64> = None;
    let mut next = 0usize;
    let mut stopped = false;
    for k in 0..max_cycles {
        if !stopped && stop(k) {
            stopped = true;
            core.request_stop();
        }
        let t = k as f64 * period;
        if ready_at.is_none() && core.state() == SupervisorState::Tracking {
            ready_at = Some(t);
        }
        if let Some(t0) = ready_at {
            while next < commands.len() && commands[next].t <= t - t0 + 1e-9 {
                let mut ev = commands[next];
                ev.t = t;
                core.command(ev);
                next += 1;
            }
        }
        // Wall-clock time spent inside the core, for reports only (never recorded).
        let mut spent = Duration::ZERO;
        let mut entered = std::time::Instant::now();
        let mut timer = |on: bool| {
            if on {
                entered = std::time::Instant::now();
            } else {
                spent += entered.elapsed();
            }
        };
        let mut hooks = StepHooks {
            around_core: Some(&mut timer),
            ..StepHooks::default()
        };
        lockstep_cycle_buses(&mut st, core, buses, peer, &mut hooks);
        report.compute.record_us(spent.as_secs_f64() * 1e6);
        report.compute_total_s += spent.as_secs_f64();
        sink(core.record(), core.wheel_xy());
        report.cycles = k + 1;
        if core.done() {
            break;
        }
    }
    report.wall_s = wall.elapsed().as_secs_f64();
    Ok(report)
}
