//! In-process virtual CAN bus: many nodes share one broadcast medium.
//!
//! - Every frame a node sends is seen by every *other* attached node (not by the sender,
//!   like a SocketCAN socket without `CAN_RAW_RECV_OWN_MSGS`), in send order, stamped with
//!   the bus time at which it is delivered.
//! - A [`FaultModel`] (through one bus-wide [`FaultInjector`] seeded from
//!   [`VirtualBusConfig::seed`]) drops, delays, duplicates or corrupts frames on the medium,
//!   so all receivers see the same fate of a frame (it is one wire). [`VirtualBus::silence`]
//!   drops everything one node sends (a dead transceiver). Same seed and same sequence of
//!   sends → same deliveries.
//! - Clock: [`BusClock::Virtual`] — time only moves with [`VirtualBus::set_time`]; a frame
//!   delayed to `t` becomes visible when `now ≥ t`; nothing ever blocks, and
//!   [`CanBus::recv_until`] behaves like [`CanBus::try_recv`] (waiting on a wall-clock deadline
//!   would make lockstep runs timing-dependent). [`BusClock::Wall`] — bus time is the time
//!   since the bus was created; `recv_until` blocks on a condition variable, the async
//!   `recv` on a `tokio::sync::Notify` (and a tokio timer for delayed frames, so the runtime
//!   needs its time driver enabled).
//! - Each receiver has a bounded queue (`queue_capacity`). When it is full the **oldest**
//!   frame is dropped and counted as an overrun ([`VirtualNode::overruns`],
//!   [`BusStats::overruns`]), as a real CAN controller's receive FIFO does; `send` never fails
//!   because a receiver is slow.
//! - Controller error states: [`VirtualBus::set_bus_off`] puts every node of a name in
//!   bus-off (its sends fail with [`BusError::BusOff`], nothing reaches it) and back
//!   (restarted); [`VirtualBus::inject_event`] reports a warning or error-passive state.
//!   Each change reaches the node once, before its next frame, as the error frame a
//!   SocketCAN socket reads ([`BusError::bus_event`]).

use std::collections::VecDeque;
use std::sync::{Arc, Condvar, Mutex, MutexGuard};
use std::time::{Duration, Instant};

use super::{AsyncCanBus, BusError, BusEvent, CanBus};
use crate::fault::{FaultInjector, FaultModel, FaultStats};
use crate::frame::{CanFrame, TimestampedFrame};

/// Which clock stamps and releases frames.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub enum BusClock {
    /// Virtual time set by [`VirtualBus::set_time`] (lockstep, deterministic).
    #[default]
    Virtual,
    /// Wall time since the bus was created (real-time runs).
    Wall,
}

/// Configuration of a [`VirtualBus`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct VirtualBusConfig {
    /// Clock mode.
    pub clock: BusClock,
    /// Faults injected on the medium.
    pub faults: FaultModel,
    /// Seed of the fault injector.
    pub seed: u64,
    /// Receive queue capacity per node, frames (at least 1 is used).
    pub queue_capacity: usize,
}

impl Default for VirtualBusConfig {
    fn default() -> Self {
        VirtualBusConfig {
            clock: BusClock::Virtual,
            faults: FaultModel::none(),
            seed: 0,
            queue_capacity: 1024,
        }
    }
}

/// Bus-wide counters.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct BusStats {
    /// Frames passed to `send` by attached nodes (including silenced ones).
    pub sent: u64,
    /// Frames dropped because their sender was silenced.
    pub silenced: u64,
    /// Frame copies put into receive queues.
    pub delivered: u64,
    /// Frames dropped from full receive queues (oldest first).
    pub overruns: u64,
    /// What the fault injector did.
    pub faults: FaultStats,
}

#[derive(Debug)]
struct NodeSlot {
    name: String,
    attached: bool,
    queue: VecDeque<TimestampedFrame>,
    overruns: u64,
    /// The node's controller is bus-off: it sends and receives nothing.
    bus_off: bool,
    /// Controller state changes not yet read (the oldest are dropped beyond
    /// [`MAX_PENDING_EVENTS`]).
    events: VecDeque<BusEvent>,
}

/// Controller state changes kept per node until read.
const MAX_PENDING_EVENTS: usize = 16;

impl NodeSlot {
    fn push_event(&mut self, e: BusEvent) {
        if self.events.len() >= MAX_PENDING_EVENTS {
            self.events.pop_front();
        }
        self.events.push_back(e);
    }
}

#[derive(Debug)]
struct State {
    now: Duration,
    nodes: Vec<NodeSlot>,
    silenced: Vec<String>,
    injector: FaultInjector,
    stats: BusStats,
    closed: bool,
    capacity: usize,
}

#[derive(Debug)]
struct Shared {
    state: Mutex<State>,
    cond: Condvar,
    notify: tokio::sync::Notify,
    epoch: Instant,
    clock: BusClock,
}

impl Shared {
    fn lock(&self) -> MutexGuard<'_, State> {
        // No code panics while holding the lock; recover the data if it ever was poisoned.
        self.state.lock().unwrap_or_else(|e| e.into_inner())
    }

    /// Bus time now (virtual: the set time; wall: time since creation).
    fn now(&self, st: &State) -> Duration {
        match self.clock {
            BusClock::Virtual => st.now,
            BusClock::Wall => self.epoch.elapsed(),
        }
    }

    fn wake_all(&self) {
        // Only wall-clock receivers block on the condition variable (a virtual-clock
        // `recv_until` never waits), and `notify_all` costs a futex syscall even with no
        // waiter: skip it on the virtual clock, where lockstep runs send ~13 frames a cycle.
        if self.clock == BusClock::Wall {
            self.cond.notify_all();
        }
        self.notify.notify_waiters();
    }
}

/// The shared medium. Cheap to clone (all clones are the same bus).
#[derive(Debug, Clone)]
pub struct VirtualBus {
    shared: Arc<Shared>,
}

impl VirtualBus {
    /// A new bus with no nodes.
    pub fn new(config: VirtualBusConfig) -> VirtualBus {
        VirtualBus {
            shared: Arc::new(Shared {
                state: Mutex::new(State {
                    now: Duration::ZERO,
                    nodes: Vec::new(),
                    silenced: Vec::new(),
                    injector: FaultInjector::new(config.faults, config.seed),
                    stats: BusStats::default(),
                    closed: false,
                    capacity: config.queue_capacity.max(1),
                }),
                cond: Condvar::new(),
                notify: tokio::sync::Notify::new(),
                epoch: Instant::now(),
                clock: config.clock,
            }),
        }
    }

    /// Attaches a new node called `name` (names need not be unique; [`silence`](Self::silence)
    /// applies to every node of that name). It receives frames sent from now on.
    pub fn node(&self, name: &str) -> VirtualNode {
        let mut st = self.shared.lock();
        st.nodes.push(NodeSlot {
            name: name.to_string(),
            attached: true,
            queue: VecDeque::new(),
            overruns: 0,
            bus_off: false,
            events: VecDeque::new(),
        });
        VirtualNode {
            shared: Arc::clone(&self.shared),
            index: st.nodes.len() - 1,
            name: name.to_string(),
        }
    }

    /// Names of the attached nodes, in attachment order.
    pub fn node_names(&self) -> Vec<String> {
        let st = self.shared.lock();
        st.nodes
            .iter()
            .filter(|n| n.attached)
            .map(|n| n.name.clone())
            .collect()
    }

    /// The clock mode.
    pub fn clock(&self) -> BusClock {
        self.shared.clock
    }

    /// Current bus time.
    pub fn now(&self) -> Duration {
        let st = self.shared.lock();
        self.shared.now(&st)
    }

    /// Sets the virtual time (frames delivered at or before `t` become visible). Time never
    /// goes backwards: an earlier `t` is ignored. No effect with [`BusClock::Wall`].
    pub fn set_time(&self, t: Duration) {
        if self.shared.clock != BusClock::Virtual {
            return;
        }
        {
            let mut st = self.shared.lock();
            if t > st.now {
                st.now = t;
            }
        }
        self.shared.wake_all();
    }

    /// Advances the virtual time by `dt` (see [`set_time`](Self::set_time)).
    pub fn advance(&self, dt: Duration) {
        let t = self.now().saturating_add(dt);
        self.set_time(t);
    }

    /// Replaces the fault model (the injector's random stream continues).
    pub fn set_faults(&self, faults: FaultModel) {
        self.shared.lock().injector.set_model(faults);
    }

    /// Silences (`true`) or un-silences every node called `node_name`, including nodes
    /// attached later: their transmissions are dropped.
    pub fn silence(&self, node_name: &str, silent: bool) {
        let mut st = self.shared.lock();
        st.silenced.retain(|n| n != node_name);
        if silent {
            st.silenced.push(node_name.to_string());
        }
    }

    /// Puts the controller of every node called `node_name` in bus-off (`true`: its sends
    /// fail with [`BusError::BusOff`] and put nothing on the medium, frames sent by others
    /// do not reach it, and it reads the bus-off error once) or restarts it (`false`: it
    /// reads [`BusEvent::Restarted`] once, then sends and receives again). Setting the state
    /// it already has does nothing.
    pub fn set_bus_off(&self, node_name: &str, off: bool) {
        {
            let mut st = self.shared.lock();
            for slot in st.nodes.iter_mut() {
                if slot.attached && slot.name == node_name && slot.bus_off != off {
                    slot.bus_off = off;
                    slot.push_event(if off {
                        BusEvent::BusOff
                    } else {
                        BusEvent::Restarted
                    });
                }
            }
        }
        self.shared.wake_all();
    }

    /// Reports a controller state change (warning, error passive, active) to every node
    /// called `node_name`: it reads it once, before its next frame. Bus-off and restart go
    /// through [`set_bus_off`](Self::set_bus_off).
    pub fn inject_event(&self, node_name: &str, event: BusEvent) {
        if matches!(event, BusEvent::BusOff | BusEvent::Restarted) {
            self.set_bus_off(node_name, event == BusEvent::BusOff);
            return;
        }
        {
            let mut st = self.shared.lock();
            for slot in st.nodes.iter_mut() {
                if slot.attached && slot.name == node_name {
                    slot.push_event(event);
                }
            }
        }
        self.shared.wake_all();
    }

    /// Counters.
    pub fn stats(&self) -> BusStats {
        let st = self.shared.lock();
        let mut s = st.stats;
        s.faults = *st.injector.stats();
        s
    }

    /// Closes the bus: every node's operations fail with [`BusError::Closed`] and waiting
    /// receivers wake up.
    pub fn close(&self) {
        self.shared.lock().closed = true;
        self.shared.wake_all();
    }
}

/// One node attached to a [`VirtualBus`]. Dropping it detaches it.
#[derive(Debug)]
pub struct VirtualNode {
    shared: Arc<Shared>,
    index: usize,
    name: String,
}

impl VirtualNode {
    fn closed(&self) -> BusError {
        BusError::Closed {
            iface: self.name.clone(),
        }
    }

    /// Sends a frame (never blocks). Same as [`CanBus::send`]; an inherent method so that
    /// `node.send(&f)` is unambiguous when both bus traits are in scope.
    pub fn send(&mut self, frame: &CanFrame) -> Result<(), BusError> {
        self.send_frame(frame)
    }

    /// Same as [`CanBus::try_recv`].
    pub fn try_recv(&mut self) -> Result<Option<TimestampedFrame>, BusError> {
        let mut st = self.shared.lock();
        self.pop_visible(&mut st)
    }

    /// Same as [`CanBus::recv_until`].
    pub fn recv_until(&mut self, deadline: Instant) -> Result<Option<TimestampedFrame>, BusError> {
        let mut st = self.shared.lock();
        loop {
            if let Some(f) = self.pop_visible(&mut st)? {
                return Ok(Some(f));
            }
            if self.shared.clock == BusClock::Virtual {
                return Ok(None);
            }
            let wall_now = Instant::now();
            if wall_now >= deadline {
                return Ok(None);
            }
            let mut wait = deadline - wall_now;
            if let Some(next) = st.nodes[self.index].queue.front() {
                let bus_now = self.shared.now(&st);
                wait = wait.min(next.timestamp.saturating_sub(bus_now));
            }
            st = match self.shared.cond.wait_timeout(st, wait) {
                Ok((g, _)) => g,
                Err(poisoned) => poisoned.into_inner().0,
            };
        }
    }

    /// Frames waiting in this node's queue (visible or not yet delivered).
    pub fn pending(&self) -> usize {
        self.shared.lock().nodes[self.index].queue.len()
    }

    /// Frames this node lost because its queue was full.
    pub fn overruns(&self) -> u64 {
        self.shared.lock().nodes[self.index].overruns
    }

    /// The node's name.
    pub fn name(&self) -> &str {
        &self.name
    }

    fn send_frame(&self, frame: &CanFrame) -> Result<(), BusError> {
        {
            let mut st = self.shared.lock();
            if st.closed {
                return Err(self.closed());
            }
            if st.nodes[self.index].bus_off {
                return Err(BusError::BusOff {
                    iface: self.name.clone(),
                });
            }
            st.stats.sent += 1;
            if st.silenced.contains(&self.name) {
                st.stats.silenced += 1;
                return Ok(());
            }
            let now = self.shared.now(&st);
            let State {
                nodes,
                injector,
                stats,
                capacity,
                ..
            } = &mut *st;
            let me = self.index;
            let cap = *capacity;
            injector.apply(now, frame, &mut |at, f| {
                for (i, slot) in nodes.iter_mut().enumerate() {
                    if i == me || !slot.attached || slot.bus_off {
                        continue;
                    }
                    if slot.queue.len() >= cap {
                        slot.queue.pop_front();
                        slot.overruns += 1;
                        stats.overruns += 1;
                    }
                    slot.queue.push_back(TimestampedFrame {
                        timestamp: at,
                        frame: f,
                    });
                    stats.delivered += 1;
                }
            });
        }
        self.shared.wake_all();
        Ok(())
    }

    fn pop_visible(&self, st: &mut State) -> Result<Option<TimestampedFrame>, BusError> {
        if st.closed {
            return Err(self.closed());
        }
        if let Some(event) = st.nodes[self.index].events.pop_front() {
            let iface = self.name.clone();
            return Err(match event {
                BusEvent::BusOff => BusError::BusOff { iface },
                event => BusError::Controller { iface, event },
            });
        }
        let now = self.shared.now(st);
        let q = &mut st.nodes[self.index].queue;
        match q.front() {
            Some(f) if f.timestamp <= now => Ok(q.pop_front()),
            _ => Ok(None),
        }
    }

    /// Time until the head of the queue becomes visible, if it exists and is in the future.
    fn head_wait(&self, st: &State) -> Option<Duration> {
        let now = self.shared.now(st);
        st.nodes[self.index]
            .queue
            .front()
            .map(|f| f.timestamp.saturating_sub(now))
    }

    async fn recv_async(&self) -> Result<TimestampedFrame, BusError> {
        loop {
            let notified = self.shared.notify.notified();
            tokio::pin!(notified);
            // Register interest before checking, so a send between the check and the await
            // is not missed.
            notified.as_mut().enable();
            let wait = {
                let mut st = self.shared.lock();
                if let Some(f) = self.pop_visible(&mut st)? {
                    return Ok(f);
                }
                match self.shared.clock {
                    BusClock::Wall => self.head_wait(&st),
                    BusClock::Virtual => None,
                }
            };
            match wait {
                Some(d) => {
                    tokio::select! {
                        _ = &mut notified => {}
                        _ = tokio::time::sleep(d) => {}
                    }
                }
                None => notified.await,
            }
        }
    }
}

impl Drop for VirtualNode {
    fn drop(&mut self) {
        let mut st = self.shared.lock();
        if let Some(slot) = st.nodes.get_mut(self.index) {
            slot.attached = false;
            slot.queue.clear();
            slot.queue.shrink_to_fit();
        }
    }
}

impl CanBus for VirtualNode {
    fn send(&mut self, frame: &CanFrame) -> Result<(), BusError> {
        self.send_frame(frame)
    }
    fn try_recv(&mut self) -> Result<Option<TimestampedFrame>, BusError> {
        VirtualNode::try_recv(self)
    }
    fn recv_until(&mut self, deadline: Instant) -> Result<Option<TimestampedFrame>, BusError> {
        VirtualNode::recv_until(self, deadline)
    }
    fn name(&self) -> &str {
        &self.name
    }
}

impl AsyncCanBus for VirtualNode {
    fn send(
        &mut self,
        frame: &CanFrame,
    ) -> impl std::future::Future<Output = Result<(), BusError>> + Send {
        std::future::ready(self.send_frame(frame))
    }
    fn recv(
        &mut self,
    ) -> impl std::future::Future<Output = Result<TimestampedFrame, BusError>> + Send {
        self.recv_async()
    }
}
