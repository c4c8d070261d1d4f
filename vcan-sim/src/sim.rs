//! The simulator: plant + one firmware per wheel module + fault schedule, as a sans-IO core.
//!
//! Drive it with three calls (all times are simulator time, from 0 at construction):
//! - [`Simulator::on_frame`]`(now, frame)`: a frame arrived at `now` (the plant is first
//!   advanced to `now`, then every module sees the frame);
//! - [`Simulator::advance_to`]`(now)`: step the plant in fixed sub-steps (default 1 ms) on the
//!   grid `k · substep` up to `now`; at each grid point the scheduled faults fire and the
//!   firmwares run their timers (boot, setpoint watchdog, STATUS); the motor setpoints in force
//!   at a grid point drive the plant for the following sub-step;
//! - [`Simulator::drain_tx`] / [`Simulator::drain_due`]: hand out the frames the modules
//!   transmit, each with the time it should appear on the bus.
//!
//! One cycle: SYNC at `t` → `on_frame(t, sync)` → FEEDBACK_A/B of every module with send time
//! `t + response_latency` (default 0.3 ms, plus the fault schedule's delay/jitter) → the
//! controller's SETPOINTs → `on_frame(t_sp, setpoint)` → applied from the next grid point
//! on (from `t_sp` itself when `t_sp` is a grid point).
//! The encoder readings in the feedback are those of the last grid point ≤ `t` (delayed by
//! the plant's `latency_samples`).
//!
//! Everything the modules transmit passes through, in order: the module's `silent` windows,
//! the `bus_off` windows (which also swallow received frames), and one
//! [`rollbase_driver::fault::FaultInjector`] (loss, delay, jitter, duplication, corruption),
//! seeded from the schedule's seed or the simulator's seed, so a run is reproducible frame by
//! frame.
//!
//! [`run_realtime`] drives the same core from a real bus in wall-clock time;
//! [`Simulator::pump`] is the lockstep equivalent for one time instant.

use crate::canopen::Device;
use crate::error::{invalid, SimError};
use crate::faults::FaultSchedule;
use crate::firmware::{FirmwareConfig, FirmwareStats, ModuleFirmware};
use crate::plant::{InitialState, MotorSetpoint, Plant, PlantConfig, PlantTruth};
use rollbase_control::{Platform, Protocol, ReferenceSample, MAX_WHEELS};
use rollbase_driver::bus::CanBus;
use rollbase_driver::canopen::config::Role;
use rollbase_driver::canopen::emcy::codes as emcy_codes;
use rollbase_driver::codec::{ModuleState, FAULT_OVERCURRENT};
use rollbase_driver::fault::{FaultInjector, FaultModel, FaultStats};
use rollbase_driver::frame::CanFrame;
use rollbase_driver::rng::splitmix64;
use std::collections::VecDeque;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};

/// Capacity of the transmit queue; beyond it the oldest frame is dropped and counted.
pub const TX_QUEUE_CAPACITY: usize = 1024;

/// Everything the simulator needs besides the platform.
#[derive(Clone, Debug, PartialEq)]
pub struct SimConfig {
    /// Plant parameters.
    pub plant: PlantConfig,
    /// Fault schedule.
    pub faults: FaultSchedule,
    /// Firmware parameters (same for every module).
    pub firmware: FirmwareConfig,
    /// Initial state; `None` = [`InitialState::nominal`].
    pub initial: Option<InitialState>,
    /// Plant sub-step (default 1 ms; at most 10 ms).
    pub substep: Duration,
    /// Time from a SYNC to the modules' feedback frames (default 0.3 ms).
    pub response_latency: Duration,
    /// Master seed: plant noise and (unless the schedule has its own) frame faults.
    pub seed: u64,
    /// Serialize the frames the simulator sends on a bus of this bit rate (`None`: every
    /// frame goes out at its send time). Frames produced at the same instant go out one after
    /// the other in CAN-id order (the lowest id wins arbitration), each taking its worst-case
    /// length in bits ([`rollbase_driver::busload::frame_bits`]); the controller's own frames
    /// are not modelled.
    pub bitrate: Option<u32>,
    /// How the CiA 402 profile's devices behave where real drives differ from an ideal
    /// device (incremental steering counters, home switches, informational EMCYs …).
    pub twin: crate::canopen::TwinConfig,
}

impl Default for SimConfig {
    fn default() -> Self {
        Self {
            plant: PlantConfig::default(),
            faults: FaultSchedule::default(),
            firmware: FirmwareConfig::default(),
            initial: None,
            substep: Duration::from_millis(1),
            response_latency: Duration::from_micros(300),
            seed: 1,
            bitrate: None,
            twin: crate::canopen::TwinConfig::default(),
        }
    }
}

/// Simulator counters.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct SimStats {
    /// Frames passed to [`Simulator::on_frame`].
    pub frames_received: u64,
    /// Received frames swallowed because the bus was off.
    pub frames_lost_bus_off_rx: u64,
    /// Frames the firmwares produced.
    pub frames_generated: u64,
    /// Produced frames dropped because their module was silent.
    pub frames_dropped_silent: u64,
    /// Produced frames dropped because the bus was off.
    pub frames_dropped_bus_off: u64,
    /// Frames put into the transmit queue (after loss and duplication).
    pub frames_queued: u64,
    /// Frames dropped because the transmit queue was full (nobody drained it).
    pub tx_overflow: u64,
    /// Plant sub-steps taken.
    pub substeps: u64,
    /// Scheduled fault events fired so far.
    pub events_fired: u64,
    /// The frame fault injector's counters.
    pub injector: FaultStats,
    /// Number of modules (entries of `modules`).
    pub n: usize,
    /// Per-module firmware counters, in platform wheel order (native profile).
    pub modules: [FirmwareStats; MAX_WHEELS],
}

/// The devices on the bus: the native wheel-module firmwares or the CiA 402 profile's
/// CANopen devices (three per wheel).
#[derive(Clone, Debug)]
enum Modules {
    Native(Vec<ModuleFirmware>),
    CanOpen(Vec<Device>),
}

#[derive(Clone, Copy, Debug, PartialEq)]
enum EventKind {
    MotorFault,
    PowerCycle,
    Emcy(u16, u8),
    EncoderStuck,
    EncoderJump(f64),
    DriveGain(f64),
}

#[derive(Clone, Copy, Debug, PartialEq)]
struct Event {
    at: f64,
    wheel: usize,
    node: u8,
    kind: EventKind,
}

/// Plant + firmwares + faults; see the module docs.
#[derive(Clone, Debug)]
pub struct Simulator {
    plant: Plant,
    modules: Modules,
    n_wheels: usize,
    nodes: Vec<u8>,
    outbox: Vec<(u8, CanFrame)>,
    bitrate: Option<u32>,
    /// Per bus (`wheels[i].bus`), when its wire is free again.
    bus_free: [Duration; 2],
    /// Per wheel, its bus; per CAN node, the bus of its device.
    wheel_bus: [u8; MAX_WHEELS],
    node_bus: [u8; 128],
    schedule: FaultSchedule,
    events: Vec<Event>,
    next_event: usize,
    injector: FaultInjector,
    substep: Duration,
    response_latency: Duration,
    now: Duration,
    plant_time: Duration,
    tx: VecDeque<(Duration, CanFrame)>,
    latched: Option<[MotorSetpoint; MAX_WHEELS]>,
    started: bool,
    stats: SimStats,
}

fn secs(d: Duration) -> f64 {
    d.as_secs_f64()
}

impl Simulator {
    /// The usual set-up: default firmware, sub-step and response latency; the plant starts at
    /// the reference's initial pose and legs ([`InitialState::from_reference`]); `seed` drives
    /// encoder noise and (unless the schedule has its own seed) the frame faults.
    pub fn new(
        platform: &Platform,
        plant: PlantConfig,
        faults: FaultSchedule,
        r0: &ReferenceSample,
        seed: u64,
    ) -> Result<Self, SimError> {
        let initial = InitialState::from_reference(platform, r0);
        Self::with_config(
            platform,
            SimConfig {
                plant,
                faults,
                initial: Some(initial),
                seed,
                ..SimConfig::default()
            },
        )
    }

    /// Builds the simulator from a full [`SimConfig`]. Fails (naming the field) on an invalid platform, plant
    /// configuration, fault schedule (including events for nodes the platform does not have),
    /// initial state, sub-step or latency.
    pub fn with_config(platform: &Platform, cfg: SimConfig) -> Result<Self, SimError> {
        platform.validate()?;
        cfg.faults.validate()?;
        let cia402 = platform.cia402();
        let nodes_vec: Vec<u8> = match platform.protocol {
            Protocol::Native => platform.wheels.iter().map(|w| w.node).collect(),
            Protocol::Cia402 => cia402.devices().map(|(_, _, n)| n).collect(),
        };
        cfg.faults.check_nodes(&nodes_vec)?;
        if cfg.bitrate == Some(0) {
            return Err(invalid(
                "bitrate",
                0,
                "must be a bit rate in bit/s (e.g. 1000000), or absent",
            ));
        }
        if cfg.substep.is_zero() || cfg.substep > Duration::from_millis(10) {
            return Err(invalid(
                "substep",
                format!("{:?}", cfg.substep),
                "must be greater than 0 and at most 10 ms",
            ));
        }
        if cfg.response_latency > Duration::from_millis(4) {
            return Err(invalid(
                "response_latency",
                format!("{:?}", cfg.response_latency),
                "must be at most 4 ms (one control cycle)",
            ));
        }
        let mut seed_state = cfg.seed;
        let plant_seed = splitmix64(&mut seed_state);
        let fault_seed = cfg
            .faults
            .seed
            .unwrap_or_else(|| splitmix64(&mut seed_state));
        let initial = cfg
            .initial
            .unwrap_or_else(|| InitialState::nominal(platform));
        let plant = Plant::new(platform, cfg.plant.clone(), initial, plant_seed)?;
        let modules = match platform.protocol {
            Protocol::Native => Modules::Native(
                nodes_vec
                    .iter()
                    .zip(&platform.wheels)
                    .map(|(&n, w)| {
                        let f = ModuleFirmware::new(n, cfg.firmware);
                        if w.leg {
                            f
                        } else {
                            f.without_leg()
                        }
                    })
                    .collect(),
            ),
            Protocol::Cia402 => Modules::CanOpen(
                cia402
                    .devices()
                    .map(|(w, r, _)| Device::new(&cia402, w, r, cfg.firmware.boot_time, &cfg.twin))
                    .collect(),
            ),
        };
        let wheel_of = |node: u8| match platform.protocol {
            Protocol::Native => nodes_vec.iter().position(|&n| n == node).unwrap_or(0),
            Protocol::Cia402 => cia402
                .devices()
                .find(|(_, _, n)| *n == node)
                .map_or(0, |(w, _, _)| w),
        };
        let f = &cfg.faults;
        let mut events: Vec<Event> = Vec::new();
        events.extend(f.motor_fault.iter().map(|m| Event {
            at: m.at,
            wheel: wheel_of(m.node),
            node: m.node,
            kind: EventKind::MotorFault,
        }));
        events.extend(f.power_cycle.iter().map(|m| Event {
            at: m.at,
            wheel: wheel_of(m.node),
            node: m.node,
            kind: EventKind::PowerCycle,
        }));
        events.extend(f.emcy.iter().map(|m| Event {
            at: m.at,
            wheel: wheel_of(m.node),
            node: m.node,
            kind: EventKind::Emcy(m.code, m.register),
        }));
        events.extend(f.encoder_stuck.iter().map(|m| Event {
            at: m.at,
            wheel: wheel_of(m.node),
            node: m.node,
            kind: EventKind::EncoderStuck,
        }));
        events.extend(f.encoder_jump.iter().map(|m| Event {
            at: m.at,
            wheel: wheel_of(m.node),
            node: m.node,
            kind: EventKind::EncoderJump(m.amount),
        }));
        events.extend(f.drive_gain.iter().map(|g| Event {
            at: g.at,
            wheel: wheel_of(g.node),
            node: g.node,
            kind: EventKind::DriveGain(g.gain),
        }));
        events.sort_by(|a, b| a.at.total_cmp(&b.at));
        let model = FaultModel {
            drop_prob: f.loss,
            duplicate_prob: f.duplicate,
            corrupt_prob: f.corrupt,
            delay: Duration::from_secs_f64(f.delay),
            jitter: Duration::from_secs_f64(f.jitter),
        };
        let n = platform.n();
        let mut wheel_bus = [0u8; MAX_WHEELS];
        for (b, w) in wheel_bus.iter_mut().zip(&platform.wheels) {
            *b = w.bus.min(1);
        }
        let mut node_bus = [0u8; 128];
        match &modules {
            Modules::Native(fw) => {
                for (i, f) in fw.iter().enumerate() {
                    node_bus[usize::from(f.node() & 0x7F)] = wheel_bus[i.min(MAX_WHEELS - 1)];
                }
            }
            Modules::CanOpen(devs) => {
                for d in devs {
                    node_bus[usize::from(d.node() & 0x7F)] =
                        wheel_bus[d.wheel().min(MAX_WHEELS - 1)];
                }
            }
        }
        Ok(Self {
            plant,
            modules,
            n_wheels: n,
            nodes: nodes_vec,
            outbox: Vec::with_capacity(32),
            bitrate: cfg.bitrate,
            bus_free: [Duration::ZERO; 2],
            wheel_bus,
            node_bus,
            schedule: cfg.faults,
            events,
            next_event: 0,
            injector: FaultInjector::new(model, fault_seed),
            substep: cfg.substep,
            response_latency: cfg.response_latency,
            now: Duration::ZERO,
            plant_time: Duration::ZERO,
            tx: VecDeque::with_capacity(TX_QUEUE_CAPACITY),
            latched: None,
            started: false,
            stats: SimStats {
                n,
                ..SimStats::default()
            },
        })
    }

    /// Number of wheels.
    pub fn n(&self) -> usize {
        self.n_wheels
    }

    /// The devices' CAN nodes: one per wheel module in wheel order (native), or every
    /// CANopen device wheel by wheel: rolling drive, steering drive, leg encoder (CiA 402).
    pub fn nodes(&self) -> &[u8] {
        &self.nodes
    }

    /// The CiA 402 profile's devices (empty for the native profile).
    pub fn devices(&self) -> &[Device] {
        match &self.modules {
            Modules::CanOpen(d) => d,
            Modules::Native(_) => &[],
        }
    }

    /// Latest time seen by `on_frame`/`advance_to`.
    pub fn now(&self) -> Duration {
        self.now
    }

    /// The plant's own time (the last sub-step grid point reached).
    pub fn plant_time(&self) -> Duration {
        self.plant_time
    }

    /// The plant's true state.
    pub fn truth(&self) -> PlantTruth {
        self.plant.truth()
    }

    /// The plant.
    pub fn plant(&self) -> &Plant {
        &self.plant
    }

    /// Module `i`'s firmware (platform wheel order; native profile only).
    pub fn firmware(&self, i: usize) -> Option<&ModuleFirmware> {
        match &self.modules {
            Modules::Native(f) => f.get(i),
            Modules::CanOpen(_) => None,
        }
    }

    /// State of every wheel module. CiA 402: Boot until the wheel's devices are
    /// operational, Fault when a drive is in fault, Enabled when both drives are in operation
    /// enabled, Ready otherwise.
    pub fn module_states(&self) -> [ModuleState; MAX_WHEELS] {
        let mut s = [ModuleState::Boot; MAX_WHEELS];
        match &self.modules {
            Modules::Native(f) => {
                for (o, f) in s.iter_mut().zip(f) {
                    *o = f.state();
                }
            }
            Modules::CanOpen(devs) => {
                use crate::canopen::DeviceNmt;
                use rollbase_driver::canopen::ds402::State as S;
                for (w, o) in s.iter_mut().enumerate().take(self.n_wheels) {
                    let mine = || devs.iter().filter(move |d| d.wheel() == w);
                    *o = if mine().any(|d| d.role() != Role::Leg && d.state402().is_fault()) {
                        ModuleState::Fault
                    } else if mine().any(|d| d.nmt() != DeviceNmt::Operational) {
                        ModuleState::Boot
                    } else if mine()
                        .filter(|d| d.role() != Role::Leg)
                        .all(|d| d.state402() == S::OperationEnabled)
                    {
                        ModuleState::Enabled
                    } else {
                        ModuleState::Ready
                    };
                }
            }
        }
        s
    }

    /// Whether the simulated bus connection is off at `t`.
    pub fn is_bus_off(&self, t: Duration) -> bool {
        self.schedule.is_bus_off(secs(t))
    }

    /// Whether the schedule holds the controller's interface bus-off at `t`
    /// (`[[controller_bus_off]]`).
    pub fn is_controller_bus_off(&self, t: Duration) -> bool {
        self.schedule.is_controller_bus_off(secs(t))
    }

    /// Counters.
    pub fn stats(&self) -> SimStats {
        let mut s = self.stats;
        s.injector = *self.injector.stats();
        if let Modules::Native(fw) = &self.modules {
            for (o, f) in s.modules.iter_mut().zip(fw) {
                *o = *f.stats();
            }
        }
        s
    }

    /// Time of the next sub-step grid point after the plant's time.
    pub fn next_step_time(&self) -> Duration {
        self.plant_time + self.substep
    }

    /// Send time of the earliest queued frame.
    pub fn next_tx_time(&self) -> Option<Duration> {
        self.tx.front().map(|(t, _)| *t)
    }

    /// Frames waiting to be sent.
    pub fn tx_pending(&self) -> usize {
        self.tx.len()
    }

    /// Sends what the devices produced at `send_at` (the outbox) through the schedule: in
    /// production order, or, with a bit rate, serialized on the wire in CAN-id order.
    fn flush_outbox(&mut self, send_at: Duration) {
        let mut out = std::mem::take(&mut self.outbox);
        if let Some(rate) = self.bitrate {
            // The lowest id wins arbitration; equal ids keep their production order.
            // Each bus is its own wire (a platform on one bus uses only bus 0's).
            out.sort_by_key(|(_, f)| f.id());
            let mut t = [send_at.max(self.bus_free[0]), send_at.max(self.bus_free[1])];
            for &(node, f) in &out {
                let b = self.bus_of_node(node);
                let bits = rollbase_driver::busload::frame_bits(f.len());
                t[b] += Duration::from_nanos(u64::from(bits) * 1_000_000_000 / u64::from(rate));
                self.transmit(t[b], node, f);
            }
            self.bus_free = t;
        } else {
            for &(node, f) in &out {
                self.transmit(send_at, node, f);
            }
        }
        out.clear();
        self.outbox = out;
    }

    /// Puts one frame produced by the device `node` at `send_at` through the schedule.
    fn transmit(&mut self, send_at: Duration, node: u8, frame: CanFrame) {
        self.stats.frames_generated += 1;
        let t = secs(send_at);
        if self.schedule.is_silent(node, t) {
            self.stats.frames_dropped_silent += 1;
            return;
        }
        if self.schedule.is_bus_off(t) {
            self.stats.frames_dropped_bus_off += 1;
            return;
        }
        let tx = &mut self.tx;
        let stats = &mut self.stats;
        self.injector.apply(send_at, &frame, &mut |at, f| {
            if tx.len() >= TX_QUEUE_CAPACITY {
                tx.pop_front();
                stats.tx_overflow += 1;
            }
            // Keep the queue ordered by send time (the injector already never reorders, so
            // this is normally a push at the back).
            let mut pos = tx.len();
            while pos > 0 && tx[pos - 1].0 > at {
                pos -= 1;
            }
            tx.insert(pos, (at, f));
            stats.frames_queued += 1;
        });
    }

    /// Runs every device's timers at `t`, transmitting what they produce at `t`.
    fn tick_all(&mut self, t: Duration) {
        match &mut self.modules {
            Modules::Native(fw) => {
                for f in fw.iter_mut() {
                    let node = f.node();
                    let outbox = &mut self.outbox;
                    f.tick(t, &mut |fr| outbox.push((node, fr)));
                }
            }
            Modules::CanOpen(devs) => {
                let sensors = self.plant.sensors();
                for d in devs.iter_mut() {
                    let node = d.node();
                    let s = sensors[d.wheel().min(MAX_WHEELS - 1)];
                    let outbox = &mut self.outbox;
                    d.tick(t, &s, &mut |fr| outbox.push((node, fr)));
                }
            }
        }
        self.flush_outbox(t);
    }

    fn fire_events(&mut self, t: Duration) {
        let ts = secs(t);
        while let Some(ev) = self.events.get(self.next_event).copied() {
            if ev.at > ts {
                break;
            }
            self.next_event += 1;
            self.stats.events_fired += 1;
            match ev.kind {
                EventKind::MotorFault => match &mut self.modules {
                    Modules::Native(fw) => {
                        if let Some(fw) = fw.get_mut(ev.wheel) {
                            fw.inject_fault(t, FAULT_OVERCURRENT);
                        }
                    }
                    Modules::CanOpen(devs) => {
                        if let Some(d) = devs.iter_mut().find(|d| d.node() == ev.node) {
                            let outbox = &mut self.outbox;
                            d.inject_fault(t, emcy_codes::OVERCURRENT, &mut |fr| {
                                outbox.push((ev.node, fr))
                            });
                        }
                        self.flush_outbox(t);
                    }
                },
                EventKind::PowerCycle | EventKind::Emcy(..) => {
                    if let Modules::CanOpen(devs) = &mut self.modules {
                        if let Some(d) = devs.iter_mut().find(|d| d.node() == ev.node) {
                            match ev.kind {
                                EventKind::PowerCycle => d.power_cycle(t),
                                EventKind::Emcy(code, register) => {
                                    let outbox = &mut self.outbox;
                                    d.send_emcy(t, code, register, &mut |fr| {
                                        outbox.push((ev.node, fr))
                                    });
                                }
                                _ => {}
                            }
                        }
                        self.flush_outbox(t);
                    }
                }
                EventKind::EncoderStuck => self.plant.set_encoder_stuck(ev.wheel, true),
                EventKind::EncoderJump(a) => self.plant.add_steer_encoder_offset(ev.wheel, a),
                EventKind::DriveGain(g) => self.plant.set_drive_gain(ev.wheel, g),
            }
        }
    }

    /// Advances the plant on the sub-step grid up to `now` (see the module docs). Times
    /// earlier than the latest time seen are ignored.
    ///
    /// Causality: the motor setpoints used for the sub-step `[t_k, t_k + h)` are those in
    /// force at `t_k`. Anything that happens strictly inside a sub-step (a SETPOINT frame, a
    /// fault event, a watchdog trip at a non-grid time) takes effect from the next grid point.
    pub fn advance_to(&mut self, now: Duration) {
        if now < self.now {
            return;
        }
        self.now = now;
        if !self.started {
            self.started = true;
            self.fire_events(Duration::ZERO);
            self.tick_all(Duration::ZERO);
        }
        let dt = secs(self.substep);
        while self.plant_time + self.substep <= now {
            let sp = match self.latched.take() {
                Some(sp) => sp,
                None => self.motor_setpoints(),
            };
            self.plant.step(dt, &sp);
            self.plant_time += self.substep;
            self.stats.substeps += 1;
            let t = self.plant_time;
            self.fire_events(t);
            self.tick_all(t);
        }
        if now > self.plant_time {
            // Freeze the setpoints for the sub-step in progress before anything at `now`
            // can change them.
            if self.latched.is_none() {
                self.latched = Some(self.motor_setpoints());
            }
            self.fire_events(now);
            self.tick_all(now);
        }
    }

    fn motor_setpoints(&self) -> [MotorSetpoint; MAX_WHEELS] {
        let mut sp = [MotorSetpoint::default(); MAX_WHEELS];
        match &self.modules {
            Modules::Native(fw) => {
                for (o, f) in sp.iter_mut().zip(fw) {
                    *o = f.motor_setpoint();
                }
            }
            Modules::CanOpen(devs) => {
                for d in devs {
                    let Some(o) = sp.get_mut(d.wheel()) else {
                        continue;
                    };
                    match (d.role(), d.motor()) {
                        (Role::Drive, Some(w)) => {
                            o.wheel_speed = w;
                            o.drive_enabled = true;
                        }
                        (Role::Steer, Some(w)) => {
                            o.steer_rate = w;
                            o.steer_enabled = true;
                        }
                        _ => {}
                    }
                }
            }
        }
        sp
    }

    /// A frame arrived at `now`: advance to `now`, then let every module handle it. Replies
    /// (FEEDBACK_A/B to a SYNC, STATUS on a state change) are queued with send time
    /// `now + response_latency`.
    pub fn on_frame(&mut self, now: Duration, frame: &CanFrame) {
        self.receive(None, now, frame);
    }

    /// [`Simulator::on_frame`] for a frame on bus `bus` (`wheels[i].bus`): only the devices
    /// of the wheels on that bus see it (each bus has its own SYNC).
    pub fn on_frame_on(&mut self, bus: usize, now: Duration, frame: &CanFrame) {
        self.receive(Some(bus), now, frame);
    }

    /// The bus the device with CAN node `node` is on (its frames carry the node in the low
    /// 7 bits of their id, in both profiles).
    pub fn bus_of_node(&self, node: u8) -> usize {
        usize::from(self.node_bus[usize::from(node & 0x7F)])
    }

    fn receive(&mut self, bus: Option<usize>, now: Duration, frame: &CanFrame) {
        self.advance_to(now);
        let now = self.now;
        self.stats.frames_received += 1;
        if self.schedule.is_bus_off(secs(now)) {
            self.stats.frames_lost_bus_off_rx += 1;
            return;
        }
        let sensors = self.plant.sensors();
        let send_at = now + self.response_latency;
        match &mut self.modules {
            Modules::Native(fw) => {
                for (i, (f, reading)) in fw.iter_mut().zip(sensors.iter()).enumerate() {
                    if bus.is_some_and(|b| usize::from(self.wheel_bus[i.min(MAX_WHEELS - 1)]) != b)
                    {
                        continue;
                    }
                    let node = f.node();
                    let outbox = &mut self.outbox;
                    f.handle_frame(now, frame, reading, &mut |fr| outbox.push((node, fr)));
                }
            }
            Modules::CanOpen(devs) => {
                for d in devs.iter_mut() {
                    let w = d.wheel().min(MAX_WHEELS - 1);
                    if bus.is_some_and(|b| usize::from(self.wheel_bus[w]) != b) {
                        continue;
                    }
                    let node = d.node();
                    let s = sensors[w];
                    let outbox = &mut self.outbox;
                    d.handle_frame(now, frame, &s, &mut |fr| outbox.push((node, fr)));
                }
            }
        }
        self.flush_outbox(send_at);
    }

    /// Hands out every queued frame, in send-time order, with its send time.
    pub fn drain_tx(&mut self, out: &mut impl FnMut(Duration, CanFrame)) {
        while let Some((t, f)) = self.tx.pop_front() {
            out(t, f);
        }
    }

    /// Hands out the queued frames whose send time is ≤ `now`, in order.
    pub fn drain_due(&mut self, now: Duration, out: &mut impl FnMut(Duration, CanFrame)) {
        while let Some(&(t, f)) = self.tx.front() {
            if t > now {
                break;
            }
            self.tx.pop_front();
            out(t, f);
        }
    }

    /// Runs this simulator against `bus` in real time until `stop` is set (see
    /// [`run_realtime`]).
    pub fn run_realtime(
        &mut self,
        bus: &mut dyn CanBus,
        stop: &AtomicBool,
    ) -> Result<RealtimeSummary, SimError> {
        run_realtime(self, bus, stop, None)
    }

    /// Lockstep helper for one instant: feed every frame `bus` has now (`try_recv`, using the
    /// bus timestamps, which must be simulator time, e.g. a virtual-clock `VirtualBus` whose
    /// time is the simulator's), advance to `now`, and send the frames due by `now`.
    /// Returns the number of frames sent; retryable send errors drop the frame (counted by
    /// the caller through the bus), others are returned.
    pub fn pump(&mut self, now: Duration, bus: &mut dyn CanBus) -> Result<usize, SimError> {
        loop {
            match bus.try_recv() {
                Ok(Some(tf)) => self.on_frame(tf.timestamp.max(self.now), &tf.frame),
                Ok(None) => break,
                Err(e) if e.is_retryable() => break,
                Err(e) => return Err(e.into()),
            }
        }
        self.advance_to(now);
        let mut sent = 0;
        let mut err = None;
        self.drain_due(now, &mut |_, f| match bus.send(&f) {
            Ok(()) => sent += 1,
            Err(e) if e.is_retryable() => {}
            Err(e) => err = Some(e),
        });
        match err {
            Some(e) => Err(e.into()),
            None => Ok(sent),
        }
    }
}

/// What a real-time run did.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct RealtimeSummary {
    /// Wall time run.
    pub elapsed: Duration,
    /// Frames received from the bus.
    pub frames_in: u64,
    /// Frames sent on the bus.
    pub frames_out: u64,
    /// Sends that failed with a retryable error (frame dropped).
    pub send_errors: u64,
    /// Receives that failed with a retryable error (error frames …).
    pub recv_errors: u64,
    /// Largest delay between a frame's due time and its actual send.
    pub max_send_lateness: Duration,
    /// Largest delay between a received frame's arrival (its bus timestamp on the
    /// simulator's time base) and the moment the simulator read it: how far the simulator
    /// thread fell behind (a stall shows here). The frame itself was applied at its arrival.
    pub max_receive_lag: Duration,
}

/// Maps the bus's receive timestamps onto the simulator's time base (module docs of
/// [`run_realtime`]).
///
/// Each backend stamps a frame when it arrives, on its own clock: the wall-clock
/// `VirtualBus` with the time since the bus was created, SocketCAN with the kernel's receive
/// time (`SO_TIMESTAMP`, `CLOCK_REALTIME` since the Unix epoch), the socketcand client with
/// the time the server (the bridge, or a socketcand daemon, possibly on another machine)
/// stamped it. Whatever the clock, `arrival (simulator time) = timestamp + offset`, with an
/// offset that is constant up to the clock's drift. A frame read at simulator time `r` arrived
/// no later than `r`, so `r − timestamp` bounds the offset from above; the estimate is the
/// smallest bound seen, allowed to grow by [`ClockMap::DRIFT`] (1000 ppm, twice the largest slew
/// NTP applies) so a slowly drifting clock is followed. Two more facts bound each arrival
/// from below: a frame the previous empty poll did not return arrived after that poll, and a
/// frame arrived no earlier than the one read before it (one queue, in order). The mapped time
/// is the estimate clamped into these bounds, so a frame is never applied before it can have
/// arrived nor after it was read, whatever the backend's clock does (a stepped clock moves the
/// estimate to the bound).
#[derive(Clone, Copy, Debug, Default)]
pub struct ClockMap {
    /// Offset estimate (ns): simulator time − bus timestamp.
    offset: Option<i128>,
    /// Simulator time of the last offset update (ns).
    updated: i128,
    /// Lower bound of the next arrival (ns, simulator time).
    floor: i128,
}

impl ClockMap {
    /// Largest drift rate of a bus clock against the simulator's the estimate follows
    /// (s per s).
    pub const DRIFT: f64 = 1e-3;

    /// A map with no frame seen yet.
    pub fn new() -> Self {
        Self::default()
    }

    /// The queue was found empty at simulator time `at`: later frames arrived after it.
    pub fn empty_at(&mut self, at: Duration) {
        self.floor = self.floor.max(at.as_nanos() as i128);
    }

    /// The simulator time at which a frame with bus timestamp `stamp`, read at simulator time
    /// `read`, arrived.
    pub fn arrival(&mut self, stamp: Duration, read: Duration) -> Duration {
        let ts = stamp.as_nanos() as i128;
        let r = read.as_nanos() as i128;
        let bound = r - ts;
        let est = match self.offset {
            None => bound,
            Some(o) => {
                let grown = o + ((r - self.updated).max(0) as f64 * Self::DRIFT) as i128;
                grown.min(bound)
            }
        };
        let floor = self.floor.min(r);
        let est = est.max(floor - ts);
        self.offset = Some(est);
        self.updated = r;
        let t = (ts + est).clamp(floor, r);
        self.floor = t;
        Duration::from_nanos(t.max(0) as u64)
    }
}

/// Most frames handled per wake-up before the loop sends what is due (the rest stay queued and
/// the simulator does not advance past them).
const MAX_FRAMES_PER_WAKEUP: usize = 256;

/// Runs `sim` against a real (or wall-clock virtual) bus in real time until `stop` is set or
/// `duration` has elapsed.
///
/// Each wake-up (the next sub-step, the next due frame, or a frame's arrival) reads every
/// frame waiting on the bus, and applies each at its own arrival time — its bus timestamp on
/// the simulator's time base ([`ClockMap`]) — advancing the plant and the modules' timers
/// (setpoint watchdog, STATUS) to that time first: frames and plant steps interleave in time
/// order. Only when the queue is empty does the simulator advance to the present and send
/// what is due. So when the simulator thread is held up (a page fault, a busy machine, a
/// debugger), the SETPOINTs that arrived meanwhile are applied when they arrived, before the
/// watchdog is evaluated at any later time: the simulated modules, like real ones, do not
/// pause when the host does, and the simulator never trips a watchdog the controller did not
/// cause. Non-retryable bus errors end the run with [`SimError::Bus`].
pub fn run_realtime(
    sim: &mut Simulator,
    bus: &mut dyn CanBus,
    stop: &AtomicBool,
    duration: Option<Duration>,
) -> Result<RealtimeSummary, SimError> {
    run_realtime_buses(sim, &mut [bus], stop, duration)
}

/// How long [`run_realtime_buses`] waits on bus 0 before it looks at the other buses (a
/// thread cannot block on two buses at once): a frame on another bus is read at most this late
/// (it is still applied at its arrival, [`ClockMap`]; only the answers it causes may leave up to
/// this late, counted in [`RealtimeSummary::max_send_lateness`]).
pub const MULTI_BUS_POLL: Duration = Duration::from_micros(200);

/// [`run_realtime`] on one bus per bus of the platform: `buses[b]` carries the devices of the
/// wheels with `bus = b` (their frames go out on it, and a frame received on it reaches only
/// them, [`Simulator::on_frame_on`]). With one bus (what [`run_realtime`] runs), a wake-up
/// waits on it until the next step or due frame, and every device sees every frame. With
/// several, each wake-up waits on bus 0 at most [`MULTI_BUS_POLL`], then reads every bus (each
/// with its own [`ClockMap`]), applies the frames in arrival order and advances to the
/// earliest moment a bus was seen empty. A device whose bus index is beyond `buses` sends on
/// the last bus.
pub fn run_realtime_buses(
    sim: &mut Simulator,
    buses: &mut [&mut dyn CanBus],
    stop: &AtomicBool,
    duration: Option<Duration>,
) -> Result<RealtimeSummary, SimError> {
    if buses.is_empty() {
        return Err(invalid("buses", 0, "the simulator needs at least one bus"));
    }
    let nb = buses.len();
    let epoch = Instant::now() - sim.now();
    let start = sim.now();
    let mut summary = RealtimeSummary::default();
    let mut clocks = vec![ClockMap::new(); nb];
    for c in clocks.iter_mut() {
        c.empty_at(start);
    }
    // (arrival, bus, frame) of one wake-up, applied in arrival order.
    let mut got: Vec<(Duration, usize, CanFrame)> = Vec::with_capacity(MAX_FRAMES_PER_WAKEUP);
    let mut due: Vec<(Duration, CanFrame)> = Vec::new();
    loop {
        let now = epoch.elapsed();
        summary.elapsed = now - start;
        if stop.load(Ordering::Relaxed) || duration.is_some_and(|d| now - start >= d) {
            break;
        }
        let mut next = sim.next_step_time();
        if let Some(t) = sim.next_tx_time() {
            next = next.min(t);
        }
        if let Some(d) = duration {
            next = next.min(start + d);
        }
        if nb > 1 {
            next = next.min(now + MULTI_BUS_POLL);
        }
        got.clear();
        // The moment every bus had been seen empty (nothing unseen arrived before it), or
        // None when a bus still holds frames (then advance only to the last frame applied).
        let mut seen_empty: Option<Duration> = None;
        let mut full = false;
        for (b, bus) in buses.iter_mut().enumerate() {
            let mut r = if b == 0 {
                bus.recv_until(epoch + next)
            } else {
                bus.try_recv()
            };
            let mut taken = 0usize;
            loop {
                match r {
                    Ok(Some(tf)) => {
                        let read = epoch.elapsed();
                        let at = clocks[b].arrival(tf.timestamp, read);
                        summary.frames_in += 1;
                        summary.max_receive_lag =
                            summary.max_receive_lag.max(read.saturating_sub(at));
                        got.push((at, b, tf.frame));
                        taken += 1;
                        if taken >= MAX_FRAMES_PER_WAKEUP / nb {
                            full = true;
                            break;
                        }
                    }
                    Ok(None) => {
                        let empty = epoch.elapsed();
                        clocks[b].empty_at(empty);
                        seen_empty = Some(seen_empty.map_or(empty, |e| e.min(empty)));
                        break;
                    }
                    Err(e) if e.is_retryable() => {
                        summary.recv_errors += 1;
                        let empty = epoch.elapsed();
                        seen_empty = Some(seen_empty.map_or(empty, |e| e.min(empty)));
                        break;
                    }
                    Err(e) => return Err(e.into()),
                }
                r = bus.try_recv();
            }
        }
        got.sort_by_key(|(at, _, _)| *at);
        let mut last = sim.now();
        for &(at, b, f) in &got {
            let at = at.max(sim.now());
            if nb > 1 {
                sim.on_frame_on(b, at, &f);
            } else {
                sim.on_frame(at, &f);
            }
            last = at;
        }
        let now = if full {
            last
        } else {
            seen_empty.unwrap_or(last)
        }
        .max(sim.now());
        sim.advance_to(now);
        let mut err = None;
        due.clear();
        sim.drain_due(now, &mut |at, f| due.push((at, f)));
        for &(at, f) in &due {
            summary.max_send_lateness = summary.max_send_lateness.max(now.saturating_sub(at));
            let b = sim.bus_of_node((f.id() & 0x7F) as u8).min(nb - 1);
            match buses[b].send(&f) {
                Ok(()) => summary.frames_out += 1,
                Err(e) if e.is_retryable() => summary.send_errors += 1,
                Err(e) => err = Some(e),
            }
        }
        if let Some(e) = err {
            return Err(e.into());
        }
    }
    Ok(summary)
}

/// The thread of [`spawn_realtime`]: it returns the simulator and the run's result.
pub type SimHandle = std::thread::JoinHandle<(Simulator, Result<RealtimeSummary, SimError>)>;

/// Runs [`run_realtime`] on its own thread (for in-process use, e.g. `rollbase demo` with a
/// wall-clock `VirtualBus` node). Set `stop` to end it; the thread returns the simulator
/// (for its truth and statistics) and the run's result.
pub fn spawn_realtime(
    mut sim: Simulator,
    mut bus: Box<dyn CanBus>,
    stop: Arc<AtomicBool>,
    duration: Option<Duration>,
) -> SimHandle {
    std::thread::spawn(move || {
        let r = run_realtime(&mut sim, bus.as_mut(), &stop, duration);
        (sim, r)
    })
}

/// [`run_realtime_buses`] on its own thread (`buses[b]` carries the devices of the wheels with
/// `bus = b`), first asking for SCHED_FIFO `priority` when given (as
/// [`spawn_realtime_at_priority`], whose lines the receiver gets; none without a priority).
/// One bus runs exactly as [`spawn_realtime`] / [`spawn_realtime_at_priority`].
pub fn spawn_realtime_buses(
    mut sim: Simulator,
    mut buses: Vec<Box<dyn CanBus>>,
    stop: Arc<AtomicBool>,
    duration: Option<Duration>,
    priority: Option<i32>,
) -> (SimHandle, std::sync::mpsc::Receiver<String>) {
    let (tx, rx) = std::sync::mpsc::channel();
    let h = std::thread::spawn(move || {
        if let Some(priority) = priority {
            let lines = rollbase_control::runtime::realtime_setup(
                &rollbase_control::runtime::RealtimeOptions {
                    fifo_priority: Some(priority),
                    lock_memory: true,
                    max_cycles: None,
                },
            );
            for l in lines {
                let _ = tx.send(l.replace("cycle thread", "simulator thread"));
            }
        }
        drop(tx);
        let mut refs: Vec<&mut dyn CanBus> = buses
            .iter_mut()
            .map(|b| &mut **b as &mut dyn CanBus)
            .collect();
        let r = run_realtime_buses(&mut sim, &mut refs, &stop, duration);
        drop(refs);
        (sim, r)
    });
    (h, rx)
}

/// [`spawn_realtime`] on a thread that first asks for SCHED_FIFO `priority` (the simulated
/// modules stand in for hardware, which never waits for a busy host). The returned receiver
/// gets one line saying whether the priority was granted (without CAP_SYS_NICE or an rtprio
/// limit the thread runs with normal scheduling).
pub fn spawn_realtime_at_priority(
    mut sim: Simulator,
    mut bus: Box<dyn CanBus>,
    stop: Arc<AtomicBool>,
    duration: Option<Duration>,
    priority: i32,
) -> (SimHandle, std::sync::mpsc::Receiver<String>) {
    let (tx, rx) = std::sync::mpsc::channel();
    let h = std::thread::spawn(move || {
        let lines = rollbase_control::runtime::realtime_setup(
            // Memory locked too (the modules it stands in for never wait for a page of
            // their code to be read back from disk under memory pressure).
            &rollbase_control::runtime::RealtimeOptions {
                fifo_priority: Some(priority),
                lock_memory: true,
                max_cycles: None,
            },
        );
        for l in lines {
            let _ = tx.send(l.replace("cycle thread", "simulator thread"));
        }
        drop(tx);
        let r = run_realtime(&mut sim, bus.as_mut(), &stop, duration);
        (sim, r)
    });
    (h, rx)
}
