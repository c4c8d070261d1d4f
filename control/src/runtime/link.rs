//! The wire side of the cycle, one value per protocol profile: what goes out at the start
//! and at the end of a cycle, and how a received frame becomes feedback.
//!
//! The cycle core ([`crate::runtime::CycleCore`]) is profile-neutral: it keeps three
//! feedback streams per wheel (steering: angle and rate; rolling: wheel speed; leg:
//! extension and rate) with their arrival cycle and time, and hands every wheel's
//! [`Setpoint`] (SI, enable / brake / fault-reset flags) to the link. The link does the rest:
//!
//! | | native ([`rollbase_driver::protocol`]) | CiA 402 ([`rollbase_driver::canopen`]) |
//! |---|---|---|
//! | start of cycle | SYNC (cycle counter, rolling counter, CRC) | SYNC, then NMT / heartbeat / SDO requests that are due |
//! | feedback | FEEDBACK_A → steering + rolling, FEEDBACK_B → leg | steering drive TPDO1, rolling drive TPDO1, encoder TPDO1 |
//! | sequence of steering samples | the module's rolling counter | the count of the drive's TPDO1s |
//! | module state | STATUS frames | statusword, EMCY, heartbeat, boot (the master's latched device faults) |
//! | end of cycle | one SETPOINT per module | one RPDO1 per drive (controlword + target velocity) |
//! | ready to arm | always | when every device is booted, configured and started |
//!
//! The native link is exactly the code the cycle core had before the second profile: the
//! same frames, in the same order.
//!
//! Both profiles apply each wheel's motor polarity and steer→drive coupling here, between
//! the joints the controller speaks of and the motors on the wire ([`Wiring`]): a mirrored
//! motor's setpoints and readings change sign, and a coupled module's rolling motor is told
//! ω − c·φ̇ (the steering turns the wheel by c·φ̇ on its own) and its reading gets c·φ̇ back.
//! A platform whose motors are all positive and uncoupled passes every value untouched.

use crate::angle;
use crate::model::platform::{Limits, Platform, Protocol};
use crate::reference::limits::guard_command;
use crate::types::{Command, MAX_WHEELS};
use rollbase_driver::canopen::config::Role;
use rollbase_driver::canopen::master::{
    BootError, BootState, DeviceFault, Event, HomingError, HomingPhase, Master, Reject,
};
use rollbase_driver::codec::{
    encode, Message, ModuleState, Payload, Setpoint, SetpointFlags, Sync,
};
use rollbase_driver::frame::{CanFrame, FrameBuf};
use rollbase_driver::rx::{CounterPolicy, Receiver, RxError, RxStats};
use rollbase_driver::DecodeError;

/// One feedback sample from a received frame, in SI units.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Update {
    /// Steering angle (wrapped to (−π, π]) and rate; `seq` counts the wheel's steering
    /// samples modulo 16.
    Steer {
        /// Wheel index.
        wheel: usize,
        /// φ (rad).
        angle: f64,
        /// φ̇ (rad/s).
        rate: f64,
        /// Sample sequence number (mod 16).
        seq: u8,
    },
    /// Wheel spin rate ω (rad/s).
    Drive {
        /// Wheel index.
        wheel: usize,
        /// ω (rad/s).
        speed: f64,
    },
    /// Leg extension λ (m) and rate (m/s).
    Leg {
        /// Wheel index.
        wheel: usize,
        /// λ (m).
        leg: f64,
        /// λ̇ (m/s).
        rate: f64,
    },
}

/// The samples one frame carries (FEEDBACK_A carries two).
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct Updates {
    items: [Option<Update>; 2],
}

impl Updates {
    fn one(u: Update) -> Self {
        Self {
            items: [Some(u), None],
        }
    }

    /// The samples.
    pub fn iter(&self) -> impl Iterator<Item = Update> + '_ {
        self.items.iter().flatten().copied()
    }
}

/// A wheel's fault as the link reports it.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum WheelFault {
    /// Native: the module's STATUS reports a fault code.
    Module {
        /// Module node.
        node: u8,
        /// Fault code.
        code: u8,
    },
    /// CiA 402: a device of the wheel has a latched fault.
    Device {
        /// Node-ID.
        node: u8,
        /// Which device.
        role: Role,
        /// What happened.
        fault: DeviceFault,
    },
}

/// Each wheel's motor polarity and steer→drive coupling, applied on the wire side
/// (module docs).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Wiring {
    drive: [f64; MAX_WHEELS],
    steer: [f64; MAX_WHEELS],
    coupling: [f64; MAX_WHEELS],
    /// Latest steering rate per wheel (joint side), for the coupling of rolling readings.
    last_steer_rate: [f64; MAX_WHEELS],
    /// Some wheel is mirrored or coupled.
    active: bool,
}

impl Wiring {
    /// The platform's wiring.
    pub fn new(p: &Platform) -> Self {
        let mut w = Self {
            drive: [1.0; MAX_WHEELS],
            steer: [1.0; MAX_WHEELS],
            coupling: [0.0; MAX_WHEELS],
            last_steer_rate: [0.0; MAX_WHEELS],
            active: false,
        };
        for (i, c) in p.wheels.iter().enumerate().take(MAX_WHEELS) {
            w.drive[i] = f64::from(c.drive_polarity);
            w.steer[i] = f64::from(c.steer_polarity);
            w.coupling[i] = c.coupling;
            w.active |= c.drive_polarity != 1 || c.steer_polarity != 1 || c.coupling != 0.0;
        }
        w
    }

    /// A joint setpoint as the motors must be told it.
    pub fn to_motors(&self, i: usize, sp: &Setpoint) -> Setpoint {
        if !self.active || i >= MAX_WHEELS {
            return *sp;
        }
        Setpoint {
            wheel_speed: self.drive[i] * (sp.wheel_speed - self.coupling[i] * sp.steer_rate),
            steer_rate: self.steer[i] * sp.steer_rate,
            flags: sp.flags,
        }
    }

    /// The sign that turns wheel `wheel`'s steering motor reading into the joint's.
    pub fn steer_sign(&self, wheel: usize) -> f64 {
        if self.active {
            self.steer.get(wheel).copied().unwrap_or(1.0)
        } else {
            1.0
        }
    }

    /// A motor reading as the joint's.
    pub fn to_joints(&mut self, u: Update) -> Update {
        if !self.active {
            return u;
        }
        match u {
            Update::Steer {
                wheel,
                angle: a,
                rate,
                seq,
            } if wheel < MAX_WHEELS => {
                let rate = self.steer[wheel] * rate;
                self.last_steer_rate[wheel] = rate;
                Update::Steer {
                    wheel,
                    angle: angle::wrap(self.steer[wheel] * a),
                    rate,
                    seq,
                }
            }
            Update::Drive { wheel, speed } if wheel < MAX_WHEELS => Update::Drive {
                wheel,
                speed: self.drive[wheel] * speed
                    + self.coupling[wheel] * self.last_steer_rate[wheel],
            },
            other => other,
        }
    }
}

/// The native profile's link: the code the cycle core always had.
pub struct NativeLink {
    nodes: [u8; MAX_WHEELS],
    node_to_wheel: [Option<usize>; 16],
    n: usize,
    rx: Receiver,
    sync_counter: u8,
    setpoint_counter: [u8; MAX_WHEELS],
    state: [Option<ModuleState>; MAX_WHEELS],
    fault_code: [u8; MAX_WHEELS],
    cycle: u64,
    wiring: Wiring,
}

/// The CiA 402 profile's link: the driver's sans-IO master, plus the receive statistics
/// in the native receiver's terms (see [`Link::rx_stats`]), and the turn of every steering
/// axis to its rest angle after homing.
pub struct Cia402Link {
    master: Master,
    stats: RxStats,
    n: usize,
    rest: RestAlignment,
    wiring: Wiring,
    motors: [Setpoint; MAX_WHEELS],
}

/// Steering to the rest angles after homing (before the first motion command): each axis
/// from the angle it was homed at to `cia402.wheels[i].rest_angle_rad`, on a braking-distance
/// profile within the steering rate and acceleration limits, every command through the
/// output guard ([`crate::reference::limits::guard_command`], the project's one limit check); the
/// rolling drives hold against the steer→drive coupling. The link is ready once every axis
/// is there and at rest.
struct RestAlignment {
    limits: Limits,
    dt: f64,
    rest: [f64; MAX_WHEELS],
    coupling: f64,
    /// Homings seen at the end of the last alignment ([`Master::homed_moves`]).
    done_moves: u32,
    since: Option<f64>,
    last: Command,
    angle: [Option<f64>; MAX_WHEELS],
    /// The joint angle as the drive counts it since homing (not wrapped), for wheels with a
    /// steering range: their turn to the rest angle is the plain difference, which stays
    /// inside the range (module docs of [`crate::angle::SteerRange`]); the wrapped angle's
    /// short way round could cross a stop.
    turns: [Option<f64>; MAX_WHEELS],
    ranges: [Option<angle::SteerRange>; MAX_WHEELS],
    rate: [f64; MAX_WHEELS],
    failure: Option<(usize, u8, Role, DeviceFault)>,
}

/// Steering angle error (rad) and rate (rad/s) under which a wheel is at its rest angle.
pub const REST_TOLERANCE: (f64, f64) = (3e-3, 0.02);
/// Gain of the turn to the rest angle near it (1/s).
pub const REST_GAIN: f64 = 6.0;
/// Time the turn to the rest angles may take (s).
pub const REST_TIMEOUT_S: f64 = 15.0;

impl RestAlignment {
    fn needed(&self, m: &Master) -> bool {
        m.homed_moves() != self.done_moves
    }

    /// This cycle's steering setpoints toward the rest angles (None when done or not due).
    fn step(
        &mut self,
        m: &Master,
        n: usize,
        t: f64,
        setpoints: &mut [Setpoint; MAX_WHEELS],
    ) -> bool {
        if !m.ready() || !self.needed(m) || self.failure.is_some() {
            self.since = None;
            self.last = Command::zero(n);
            return false;
        }
        let since = *self.since.get_or_insert(t);
        let mut desired = Command::zero(n);
        let mut there = true;
        let a = self.limits.steer_accel;
        let vmax = self.limits.steer_rate;
        for i in 0..n {
            let Some(phi) = self.angle[i] else {
                there = false;
                continue;
            };
            // A wheel with a range turns the plain difference (inside the range, however
            // long); an endless one the short way round.
            let e = match (self.ranges[i], self.turns[i]) {
                (Some(_), Some(turns)) => self.rest[i] - turns,
                _ => angle::diff(self.rest[i], phi),
            };
            // The speed from which the axis stops at the rest angle at 80 % of the
            // acceleration limit, capped at 80 % of the rate limit, and proportional near
            // the angle (REST_GAIN: a settling time well above the drives' lag and the
            // synchronous RPDO's cycle of delay, so the axis does not hunt).
            let v = (2.0 * 0.8 * a * e.abs())
                .sqrt()
                .min(0.8 * vmax)
                .min(REST_GAIN * e.abs())
                .copysign(e);
            desired.wheels[i].steer_rate = if e.abs() < REST_TOLERANCE.0 { 0.0 } else { v };
            if e.abs() >= REST_TOLERANCE.0 || self.rate[i].abs() >= REST_TOLERANCE.1 {
                there = false;
            }
        }
        let (mut cmd, _) = guard_command(&self.limits, &self.last, &desired, self.dt);
        for (sp, w) in setpoints.iter_mut().zip(cmd.wheels.iter_mut()).take(n) {
            w.wheel_speed = 0.0;
            *sp = Setpoint {
                wheel_speed: -self.coupling * w.steer_rate,
                steer_rate: w.steer_rate,
                flags: SetpointFlags {
                    enable: true,
                    brake: false,
                    fault_reset: false,
                },
            };
        }
        self.last = cmd;
        let at_rest = (0..n).all(|i| cmd.wheels[i].steer_rate == 0.0);
        if there && at_rest {
            self.done_moves = m.homed_moves();
            self.since = None;
        } else if t - since > REST_TIMEOUT_S {
            let worst = (0..n)
                .max_by(|&x, &y| {
                    let e = |k: usize| {
                        self.angle[k].map_or(f64::INFINITY, |p| angle::diff(self.rest[k], p).abs())
                    };
                    e(x).total_cmp(&e(y))
                })
                .unwrap_or(0);
            let node = m.node(worst, Role::Steer).unwrap_or(0);
            self.failure = Some((
                worst,
                node,
                Role::Steer,
                DeviceFault::Boot(BootError::Homing {
                    node,
                    role: Role::Steer,
                    error: HomingError::Timeout {
                        ms: (REST_TIMEOUT_S * 1e3) as u32,
                        phase: HomingPhase::RestAngle,
                        statusword: None,
                    },
                }),
            ));
        }
        true
    }
}

/// The link of a cycle core.
#[allow(clippy::large_enum_variant)] // one per core, never moved in the hot path
pub enum Link {
    /// Native wheel-module protocol.
    Native(NativeLink),
    /// CANopen CiA 402 / 406.
    Cia402(Cia402Link),
}

fn rx_error_kind(e: &RxError) -> &'static str {
    match e {
        RxError::RepeatedCounter { .. } => "repeated_counter",
        RxError::SkippedCounter { .. } => "skipped_counter",
        RxError::Decode(d) => match d {
            DecodeError::UnknownId { .. } => "unknown_id",
            DecodeError::BadCrc { .. } => "bad_crc",
            DecodeError::WrongDlc { .. } => "wrong_dlc",
            DecodeError::OutOfRange { .. } => "out_of_range",
            _ => "invalid",
        },
    }
}

impl Link {
    /// The link for the platform's profile. The platform must be valid.
    pub fn new(p: &Platform, counter_policy: CounterPolicy) -> Self {
        let n = p.n().min(MAX_WHEELS);
        match p.protocol {
            Protocol::Native => {
                let mut nodes = [0u8; MAX_WHEELS];
                let mut node_to_wheel = [None; 16];
                for (i, w) in p.wheels.iter().enumerate().take(MAX_WHEELS) {
                    nodes[i] = w.node;
                    node_to_wheel[usize::from(w.node & 15)] = Some(i);
                }
                Link::Native(NativeLink {
                    nodes,
                    node_to_wheel,
                    n,
                    rx: Receiver::with_policy(counter_policy),
                    sync_counter: 0,
                    setpoint_counter: [0; MAX_WHEELS],
                    state: [None; MAX_WHEELS],
                    fault_code: [0; MAX_WHEELS],
                    cycle: 0,
                    wiring: Wiring::new(p),
                })
            }
            Protocol::Cia402 => {
                let c = p.cia402();
                let mut rest = [0.0; MAX_WHEELS];
                for (r, w) in rest.iter_mut().zip(&c.wheels) {
                    *r = w.rest_angle_rad;
                }
                let mut ranges = [None; MAX_WHEELS];
                for (r, w) in ranges.iter_mut().zip(&p.wheels) {
                    *r = w.steering_range();
                }
                Link::Cia402(Cia402Link {
                    master: Master::new(&c, p.dt()),
                    stats: RxStats::default(),
                    n,
                    wiring: Wiring::new(p),
                    motors: [Setpoint::default(); MAX_WHEELS],
                    rest: RestAlignment {
                        limits: p.limits,
                        dt: p.dt(),
                        rest,
                        coupling: c.coupling,
                        done_moves: 0,
                        since: None,
                        last: Command::zero(n),
                        angle: [None; MAX_WHEELS],
                        turns: [None; MAX_WHEELS],
                        ranges,
                        rate: [0.0; MAX_WHEELS],
                        failure: None,
                    },
                })
            }
        }
    }

    /// The node that names wheel `i` in messages: the module (native) or the steering
    /// drive (CiA 402, whose samples the encoder-jump check uses).
    pub fn wheel_node(&self, i: usize) -> u8 {
        match self {
            Link::Native(l) => l.nodes.get(i).copied().unwrap_or(0),
            Link::Cia402(l) => l.master.node(i, Role::Steer).unwrap_or(0),
        }
    }

    /// The node of wheel `i`'s stream: `steer` (steering angle), `drive` (wheel speed) or
    /// `leg`; the module's node for every stream of the native profile.
    pub fn stream_node(&self, i: usize, role: Role) -> u8 {
        match self {
            Link::Native(l) => l.nodes.get(i).copied().unwrap_or(0),
            Link::Cia402(l) => l.master.node(i, role).unwrap_or(0),
        }
    }

    /// Frames of the start of a cycle at `t`, SYNC first.
    pub fn start_cycle(&mut self, cycle: u64, t: f64, out: &mut FrameBuf) {
        match self {
            Link::Native(l) => {
                l.cycle = cycle;
                let msg = Message {
                    node: 0,
                    counter: l.sync_counter,
                    payload: Payload::Sync(Sync {
                        cycle: (cycle & 0xFFFF) as u16,
                    }),
                };
                l.sync_counter = (l.sync_counter + 1) & 0x0F;
                // SYNC always encodes (node 0, counter < 16, raw cycle).
                if let Ok(f) = encode(&msg) {
                    out.push(f);
                }
            }
            Link::Cia402(l) => l.master.start_cycle(t, out),
        }
    }

    /// Frames made due by the late frames of the last cycle (taken after
    /// [`Link::start_cycle`]): CiA 402 SDO requests ([`Master::service`]); none natively.
    pub fn service(&mut self, t: f64, out: &mut FrameBuf) {
        if let Link::Cia402(l) = self {
            l.master.service(t, out);
        }
    }

    /// Takes one received frame; `Err` names the rejection kind (as recorded).
    pub fn on_frame(&mut self, frame: &CanFrame, t: f64) -> Result<Updates, &'static str> {
        match self {
            Link::Native(l) => {
                let msg = l.rx.accept(frame).map_err(|e| rx_error_kind(&e))?;
                let Some(w) = l
                    .node_to_wheel
                    .get(usize::from(msg.node))
                    .copied()
                    .flatten()
                    .filter(|w| *w < l.n)
                else {
                    return Ok(Updates::default());
                };
                Ok(match msg.payload {
                    Payload::FeedbackA(a) => Updates {
                        items: [
                            Some(l.wiring.to_joints(Update::Steer {
                                wheel: w,
                                angle: a.steer_angle,
                                rate: a.steer_rate,
                                seq: msg.counter,
                            })),
                            Some(l.wiring.to_joints(Update::Drive {
                                wheel: w,
                                speed: a.wheel_speed,
                            })),
                        ],
                    },
                    Payload::FeedbackB(b) => Updates::one(Update::Leg {
                        wheel: w,
                        leg: b.leg_extension,
                        rate: b.leg_rate,
                    }),
                    Payload::Status(s) => {
                        l.state[w] = Some(s.state);
                        l.fault_code[w] = s.fault_code;
                        Updates::default()
                    }
                    _ => Updates::default(),
                })
            }
            Link::Cia402(l) => {
                let r = l.master.on_frame(frame, t);
                let s = &mut l.stats;
                match r {
                    Ok(e) => {
                        s.accepted += 1;
                        Ok(match e {
                            Event::None => Updates::default(),
                            Event::Steer {
                                wheel,
                                angle: a,
                                rate,
                                seq,
                            } => {
                                // The rest alignment works on the joints, as the controller.
                                if let Some(x) = l.rest.turns.get_mut(wheel) {
                                    *x = Some(l.wiring.steer_sign(wheel) * a);
                                }
                                let u = l.wiring.to_joints(Update::Steer {
                                    wheel,
                                    angle: angle::wrap(a),
                                    rate,
                                    seq,
                                });
                                if let Update::Steer { angle, rate, .. } = u {
                                    if let Some(x) = l.rest.angle.get_mut(wheel) {
                                        *x = Some(angle);
                                        l.rest.rate[wheel] = rate;
                                    }
                                }
                                Updates::one(u)
                            }
                            Event::Drive { wheel, speed, .. } => {
                                Updates::one(l.wiring.to_joints(Update::Drive { wheel, speed }))
                            }
                            Event::Leg { wheel, leg, rate } => {
                                Updates::one(Update::Leg { wheel, leg, rate })
                            }
                        })
                    }
                    Err(e) => {
                        match e {
                            Reject::Malformed => s.wrong_dlc += 1,
                            Reject::UnknownId | Reject::UnknownNode => s.unknown_id += 1,
                            Reject::ForeignMaster | Reject::Unexpected => s.other += 1,
                        }
                        Err(e.kind())
                    }
                }
            }
        }
    }

    /// The setpoint frames at the end of a cycle at `t` (one per wheel natively, one per
    /// drive on CiA 402, then SDO requests that became due).
    pub fn finish_cycle(&mut self, t: f64, setpoints: &[Setpoint], out: &mut FrameBuf) {
        match self {
            Link::Native(l) => {
                for (i, sp) in setpoints.iter().enumerate().take(l.n) {
                    let sp = &l.wiring.to_motors(i, sp);
                    let msg = Message {
                        node: l.nodes[i],
                        counter: l.setpoint_counter[i],
                        payload: Payload::Setpoint(*sp),
                    };
                    let frame = match encode(&msg) {
                        Ok(f) => f,
                        Err(_) => {
                            // Not representable on the wire (beyond the protocol range): never
                            // clamp one wheel silently; send a braking zero setpoint for this
                            // wheel and let the supervisor's limit check stop the platform.
                            let safe = Message {
                                payload: Payload::Setpoint(Setpoint {
                                    wheel_speed: 0.0,
                                    steer_rate: 0.0,
                                    flags: SetpointFlags {
                                        enable: sp.flags.enable,
                                        brake: true,
                                        fault_reset: false,
                                    },
                                }),
                                ..msg
                            };
                            match encode(&safe) {
                                Ok(f) => f,
                                Err(_) => continue,
                            }
                        }
                    };
                    l.setpoint_counter[i] = (l.setpoint_counter[i] + 1) & 0x0F;
                    out.push(frame);
                }
            }
            Link::Cia402(l) => {
                let mut own = [Setpoint::default(); MAX_WHEELS];
                let n = l.n.min(setpoints.len());
                own[..n].copy_from_slice(&setpoints[..n]);
                let rest = l.rest.step(&l.master, l.n, t, &mut own);
                if l.wiring.active {
                    // Joints to motors: the controller's (or the rest alignment's) setpoints.
                    let src: &[Setpoint] = if rest { &own[..l.n] } else { setpoints };
                    let k = src.len().min(MAX_WHEELS);
                    for (i, sp) in src.iter().enumerate().take(k) {
                        l.motors[i] = l.wiring.to_motors(i, sp);
                    }
                    l.master.finish_cycle(t, &l.motors[..k], out)
                } else if rest {
                    l.master.finish_cycle(t, &own[..l.n], out)
                } else {
                    l.master.finish_cycle(t, setpoints, out)
                }
            }
        }
    }

    /// True when the devices are ready for the supervisor to arm (CiA 402: every device
    /// runs, every steering axis is homed and at its rest angle).
    pub fn ready(&self) -> bool {
        match self {
            Link::Native(_) => true,
            Link::Cia402(l) => l.master.ready() && !l.rest.needed(&l.master),
        }
    }

    /// The host cannot ramp the drives down itself (feedback lost, bus failing): CiA 402
    /// drives get the Quick Stop command until re-armed ([`Master::quick_stop`]); natively
    /// nothing more (the modules' own watchdogs stop them).
    pub fn quick_stop(&mut self) {
        if let Link::Cia402(l) = self {
            l.master.quick_stop();
        }
    }

    /// The controller's CAN interface went bus-off and was restarted: CiA 402 devices are
    /// taken as lost and latch the fault until re-armed (then booted again); natively the
    /// modules' watchdogs have tripped and the re-arm's fault reset clears them.
    pub fn bus_off(&mut self) {
        if let Link::Cia402(l) = self {
            l.master.bus_off();
        }
    }

    /// A boot failure (CiA 402): (wheel, node, role, fault): the first failed boot, homing or
    /// rest turn, or, while not every device is ready, the first device fault latched.
    pub fn boot_failure(&self) -> Option<(usize, u8, Role, DeviceFault)> {
        match self {
            Link::Native(_) => None,
            Link::Cia402(l) if l.rest.failure.is_some() => l.rest.failure,
            // A device that faulted while the arm waits (lost, left operational, a fault EMCY
            // during homing): the arm fails naming it, rather than waiting for ever.
            Link::Cia402(l) if l.master.boot_failure().is_none() && !l.master.ready() => l
                .master
                .devices()
                .iter()
                .find_map(|d| d.fault.map(|f| (d.wheel, d.node, d.role, f))),
            Link::Cia402(l) => l.master.boot_failure().map(|(w, e)| {
                let (node, role) = l
                    .master
                    .devices()
                    .iter()
                    .find(|d| matches!(d.fault, Some(DeviceFault::Boot(b)) if b == e))
                    .map_or((0, Role::Drive), |d| (d.node, d.role));
                (w, node, role, DeviceFault::Boot(e))
            }),
        }
    }

    /// The wheel's fault, if its module (native STATUS) or one of its devices (CiA 402,
    /// latched until re-armed) reports one.
    pub fn wheel_fault(&self, i: usize) -> Option<WheelFault> {
        match self {
            Link::Native(l) => (l.state.get(i).copied().flatten() == Some(ModuleState::Fault))
                .then(|| WheelFault::Module {
                    node: l.nodes[i],
                    code: l.fault_code[i],
                }),
            Link::Cia402(l) => l
                .master
                .wheel_fault(i)
                .map(|(node, role, fault)| WheelFault::Device { node, role, fault }),
        }
    }

    /// The wheel's state for the record (`None` = not known yet).
    pub fn wheel_state(&self, i: usize) -> Option<ModuleState> {
        match self {
            Link::Native(l) => l.state.get(i).copied().flatten(),
            Link::Cia402(l) => (i < l.n).then(|| l.master.wheel_state(i)),
        }
    }

    /// The operator re-armed at `t`: forget cached module states (native: only a STATUS
    /// sent after the re-arm can fault the platform again) or clear the devices' latched
    /// faults and boot again every device that is not running (CiA 402).
    pub fn rearm(&mut self, t: f64) {
        match self {
            Link::Native(l) => {
                l.state = [None; MAX_WHEELS];
                l.fault_code = [0; MAX_WHEELS];
            }
            Link::Cia402(l) => {
                l.rest.failure = None;
                l.master.rearm(t)
            }
        }
    }

    /// Frames that hand the devices back at the clean end of a run, after the drives were
    /// disabled. Native: none (a module without setpoints goes to Ready by itself). CiA 402:
    /// NMT reset communication to every device ([`Master::release`]).
    pub fn release(&mut self, out: &mut FrameBuf) {
        if let Link::Cia402(l) = self {
            l.master.release(out);
        }
    }

    /// Cycles before the end of a run in which the drives are told to disable: one natively
    /// (a SETPOINT acts on reception); with synchronous RPDOs (CiA 402, transmission type
    /// 1..=240) the controlword acts at the next SYNC, so one more cycle is needed.
    pub fn disable_lead_cycles(&self) -> u32 {
        match self {
            Link::Native(_) => 1,
            Link::Cia402(l) => {
                if (1..=240).contains(&l.master.config().rpdo_transmission) {
                    2
                } else {
                    1
                }
            }
        }
    }

    /// Receive statistics. Native: the receiver's. CiA 402: accepted frames, malformed ones
    /// (wrong length, invalid values) as `wrong_dlc`, unknown ids and nodes as `unknown_id`,
    /// frames of another master or unexpected responses as `other`.
    pub fn rx_stats(&self) -> &RxStats {
        match self {
            Link::Native(l) => l.rx.stats(),
            Link::Cia402(l) => &l.stats,
        }
    }

    /// The CiA 402 master, when that is the profile.
    pub fn master(&self) -> Option<&Master> {
        match self {
            Link::Native(_) => None,
            Link::Cia402(l) => Some(&l.master),
        }
    }

    /// True while CiA 402 devices are being booted or configured.
    pub fn booting(&self) -> bool {
        match self {
            Link::Native(_) => false,
            Link::Cia402(l) => {
                l.master.booting()
                    && l.master
                        .devices()
                        .iter()
                        .any(|d| d.boot != BootState::Started)
            }
        }
    }
}

/// Most buses: [`crate::model::platform::MAX_BUSES`].
const NB: usize = crate::model::platform::MAX_BUSES;

/// The links of a platform, one per bus (`wheels[i].bus`), presented with the platform's
/// wheel indices: each bus has its own SYNC, its own setpoints and (CiA 402) its own master,
/// all on the one cycle clock. A platform on one bus has one link, used exactly as before.
pub struct Buses {
    links: Vec<Link>,
    /// Per bus, the platform's index of each of its wheels (bus order).
    global: [[usize; MAX_WHEELS]; NB],
    /// Per platform wheel, its bus and its index there.
    local: [(usize, usize); MAX_WHEELS],
    /// Per CAN node (0..=127), the bus its device is on.
    node_bus: [u8; 128],
    n: usize,
    sum: RxStats,
    scratch: [Setpoint; MAX_WHEELS],
}

impl Buses {
    /// The links of the platform (which must be valid).
    pub fn new(p: &Platform, counter_policy: CounterPolicy) -> Self {
        let nb = p.buses();
        let mut global = [[0usize; MAX_WHEELS]; NB];
        let mut local = [(0usize, 0usize); MAX_WHEELS];
        let mut node_bus = [0u8; 128];
        let mut links = Vec::with_capacity(nb);
        for (b, g) in global.iter_mut().enumerate().take(nb) {
            let sub = if nb == 1 { p.clone() } else { p.bus_subset(b) };
            for (k, i) in p.wheels_on_bus(b).enumerate().take(MAX_WHEELS) {
                g[k] = i;
                if i < MAX_WHEELS {
                    local[i] = (b, k);
                }
            }
            let link = Link::new(&sub, counter_policy);
            for k in 0..sub.n().min(MAX_WHEELS) {
                for r in [Role::Drive, Role::Steer, Role::Leg] {
                    let node = link.stream_node(k, r);
                    if node != 0 {
                        node_bus[usize::from(node & 0x7F)] = b as u8;
                    }
                }
            }
            links.push(link);
        }
        Self {
            links,
            global,
            local,
            node_bus,
            n: p.n().min(MAX_WHEELS),
            sum: RxStats::default(),
            scratch: [Setpoint::default(); MAX_WHEELS],
        }
    }

    /// Number of buses.
    pub fn count(&self) -> usize {
        self.links.len()
    }

    /// Bus `b`'s link.
    pub fn link(&self, b: usize) -> Option<&Link> {
        self.links.get(b)
    }

    /// The bus a device's node is on (0 for nodes no wheel uses).
    pub fn bus_of_node(&self, node: u8) -> usize {
        usize::from(self.node_bus[usize::from(node & 0x7F)])
    }

    /// The bus of wheel `i`.
    pub fn bus_of_wheel(&self, i: usize) -> usize {
        self.local.get(i).map_or(0, |l| l.0)
    }

    fn at(&self, i: usize) -> Option<(&Link, usize)> {
        if i >= self.n {
            return None;
        }
        let (b, k) = self.local[i];
        self.links.get(b).map(|l| (l, k))
    }

    /// [`Link::wheel_node`] of platform wheel `i`.
    pub fn wheel_node(&self, i: usize) -> u8 {
        self.at(i).map_or(0, |(l, k)| l.wheel_node(k))
    }

    /// [`Link::stream_node`] of platform wheel `i`.
    pub fn stream_node(&self, i: usize, role: Role) -> u8 {
        self.at(i).map_or(0, |(l, k)| l.stream_node(k, role))
    }

    /// Frames of the start of a cycle, bus `b`'s into `outs[b]` (the last buffer when fewer
    /// are given: every bus on one medium).
    pub fn start_cycle(&mut self, cycle: u64, t: f64, outs: &mut [FrameBuf]) {
        let last = outs.len().saturating_sub(1);
        for (b, l) in self.links.iter_mut().enumerate() {
            if let Some(out) = outs.get_mut(b.min(last)) {
                l.start_cycle(cycle, t, out);
            }
        }
    }

    /// [`Link::on_frame`] for a frame that arrived on bus `bus`, its wheels as the
    /// platform's. `None` for `bus`: the bus the frame's node is on.
    pub fn on_frame(
        &mut self,
        bus: Option<usize>,
        frame: &CanFrame,
        t: f64,
    ) -> Result<Updates, &'static str> {
        let b = bus.unwrap_or_else(|| self.bus_of_node((frame.id() & 0x7F) as u8));
        let Some(l) = self.links.get_mut(b) else {
            return Err("unknown_bus");
        };
        let r = l.on_frame(frame, t);
        if self.links.len() > 1 {
            self.sum = RxStats::default();
            for l in &self.links {
                let s = l.rx_stats();
                self.sum.accepted += s.accepted;
                self.sum.bad_crc += s.bad_crc;
                self.sum.wrong_dlc += s.wrong_dlc;
                self.sum.unknown_id += s.unknown_id;
                self.sum.out_of_range += s.out_of_range;
                self.sum.repeated += s.repeated;
                self.sum.skipped += s.skipped;
                self.sum.lost += s.lost;
                self.sum.other += s.other;
            }
        }
        let mut u = r?;
        let g = &self.global[b];
        for it in u.items.iter_mut().flatten() {
            match it {
                Update::Steer { wheel, .. }
                | Update::Drive { wheel, .. }
                | Update::Leg { wheel, .. } => {
                    *wheel = g.get(*wheel).copied().unwrap_or(usize::MAX);
                }
            }
        }
        Ok(u)
    }

    /// The setpoint frames at the end of a cycle (`setpoints` in platform wheel order),
    /// bus `b`'s into `outs[b]` (as [`Buses::start_cycle`]).
    pub fn finish_cycle(&mut self, t: f64, setpoints: &[Setpoint], outs: &mut [FrameBuf]) {
        let last = outs.len().saturating_sub(1);
        if self.links.len() == 1 {
            if let (Some(l), Some(out)) = (self.links.first_mut(), outs.get_mut(0)) {
                l.finish_cycle(t, setpoints, out);
            }
            return;
        }
        for (b, l) in self.links.iter_mut().enumerate() {
            let mut k = 0;
            for (i, sp) in setpoints.iter().enumerate().take(self.n) {
                if self.local[i].0 == b && k < MAX_WHEELS {
                    self.scratch[k] = *sp;
                    k += 1;
                }
            }
            if let Some(out) = outs.get_mut(b.min(last)) {
                l.finish_cycle(t, &self.scratch[..k], out);
            }
        }
    }

    /// [`Link::service`] on every bus, bus `b`'s frames into `outs[b]` (as
    /// [`Buses::start_cycle`]).
    pub fn service(&mut self, t: f64, outs: &mut [FrameBuf]) {
        let last = outs.len().saturating_sub(1);
        for (b, l) in self.links.iter_mut().enumerate() {
            if let Some(out) = outs.get_mut(b.min(last)) {
                l.service(t, out);
            }
        }
    }

    /// [`Link::quick_stop`] on every bus.
    pub fn quick_stop(&mut self) {
        for l in &mut self.links {
            l.quick_stop();
        }
    }

    /// [`Link::bus_off`] on bus `b` (the interface that went bus-off).
    pub fn bus_off(&mut self, b: usize) {
        if let Some(l) = self.links.get_mut(b) {
            l.bus_off();
        }
    }

    /// The CiA 402 master of wheel `i`'s bus, and the wheel's index on that bus.
    pub fn master_of_wheel(&self, i: usize) -> Option<(&Master, usize)> {
        let (b, k) = *self.local.get(i)?;
        self.links.get(b)?.master().map(|m| (m, k))
    }

    /// Every bus's devices are ready.
    pub fn ready(&self) -> bool {
        self.links.iter().all(Link::ready)
    }

    /// The first bus's boot failure, its wheel as the platform's.
    pub fn boot_failure(&self) -> Option<(usize, u8, Role, DeviceFault)> {
        self.links.iter().enumerate().find_map(|(b, l)| {
            l.boot_failure().map(|(w, node, role, f)| {
                (self.global[b].get(w).copied().unwrap_or(w), node, role, f)
            })
        })
    }

    /// [`Link::wheel_fault`] of platform wheel `i`.
    pub fn wheel_fault(&self, i: usize) -> Option<WheelFault> {
        self.at(i).and_then(|(l, k)| l.wheel_fault(k))
    }

    /// [`Link::wheel_state`] of platform wheel `i`.
    pub fn wheel_state(&self, i: usize) -> Option<ModuleState> {
        self.at(i).and_then(|(l, k)| l.wheel_state(k))
    }

    /// [`Link::rearm`] on every bus.
    pub fn rearm(&mut self, t: f64) {
        for l in &mut self.links {
            l.rearm(t);
        }
    }

    /// [`Link::release`] on every bus (as [`Buses::start_cycle`]).
    pub fn release(&mut self, outs: &mut [FrameBuf]) {
        let last = outs.len().saturating_sub(1);
        for (b, l) in self.links.iter_mut().enumerate() {
            if let Some(out) = outs.get_mut(b.min(last)) {
                l.release(out);
            }
        }
    }

    /// The most cycles any bus needs to disable its drives.
    pub fn disable_lead_cycles(&self) -> u32 {
        self.links
            .iter()
            .map(Link::disable_lead_cycles)
            .max()
            .unwrap_or(1)
    }

    /// Receive statistics of every bus together.
    pub fn rx_stats(&self) -> &RxStats {
        match self.links.as_slice() {
            [one] => one.rx_stats(),
            _ => &self.sum,
        }
    }

    /// Whether bus 0's link is the CiA 402 profile's.
    pub fn is_cia402(&self) -> bool {
        matches!(self.links.first(), Some(Link::Cia402(_)))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rollbase_driver::codec::{decode, FeedbackA};

    #[test]
    fn wiring_undoes_polarity_and_coupling_both_ways() {
        let mut p = Platform::three_wheel();
        p.wheels[2].coupling = 0.5;
        let mut w = Wiring::new(&p);
        let sp = Setpoint {
            wheel_speed: 4.0,
            steer_rate: 2.0,
            flags: SetpointFlags::default(),
        };
        // Wheel 0: plain; wheel 1: both motors mirrored; wheel 2: coupled.
        assert_eq!(w.to_motors(0, &sp), sp);
        let m1 = w.to_motors(1, &sp);
        assert_eq!((m1.wheel_speed, m1.steer_rate), (-4.0, -2.0));
        let m2 = w.to_motors(2, &sp);
        assert_eq!((m2.wheel_speed, m2.steer_rate), (3.0, 2.0));
        // The readings of those motors are the joints' again.
        for (i, m) in [(1, m1), (2, m2)] {
            let Update::Steer { angle, rate, .. } = w.to_joints(Update::Steer {
                wheel: i,
                angle: if i == 1 { -0.3 } else { 0.3 },
                rate: m.steer_rate,
                seq: 0,
            }) else {
                unreachable!()
            };
            assert!((angle - 0.3).abs() < 1e-12 && (rate - 2.0).abs() < 1e-12);
            let Update::Drive { speed, .. } = w.to_joints(Update::Drive {
                wheel: i,
                speed: m.wheel_speed,
            }) else {
                unreachable!()
            };
            assert!((speed - 4.0).abs() < 1e-12, "wheel {i}: {speed}");
        }
        // Justin's wiring passes everything untouched.
        let j = Wiring::new(&Platform::justin());
        assert!(!j.active);
        assert_eq!(j.to_motors(1, &sp), sp);
    }

    #[test]
    fn two_buses_each_get_their_sync_and_their_wheels() {
        let p = Platform::six_wheel();
        let mut b = Buses::new(&p, CounterPolicy::default());
        assert_eq!(b.count(), 2);
        let mut outs = [FrameBuf::new(), FrameBuf::new()];
        b.start_cycle(0, 0.0, &mut outs);
        for o in &outs {
            assert_eq!(o.as_slice()[0].id(), 0x080, "each bus starts with its SYNC");
        }
        let sps: Vec<Setpoint> = (0..6)
            .map(|i| Setpoint {
                wheel_speed: f64::from(i as u8),
                ..Setpoint::default()
            })
            .collect();
        for o in &mut outs {
            o.clear();
        }
        b.finish_cycle(0.001, &sps, &mut outs);
        for (bus, o) in outs.iter().enumerate() {
            let nodes: Vec<u8> = o
                .as_slice()
                .iter()
                .map(|f| decode(f).expect("a setpoint").node)
                .collect();
            let want: Vec<u8> = (1..=6u8).filter(|n| (n - 1) / 3 == bus as u8).collect();
            assert_eq!(nodes, want, "bus {bus}");
            for f in o.as_slice() {
                let m = decode(f).unwrap();
                let Payload::Setpoint(s) = m.payload else {
                    panic!("{m:?}")
                };
                assert!((s.wheel_speed - f64::from(m.node - 1)).abs() < 1e-3);
            }
        }
        // Feedback from node 5 (bus 1's second wheel) is platform wheel 4's.
        for (counter, bus) in [(0, Some(1)), (1, None)] {
            let fb = encode(&Message {
                node: 5,
                counter,
                payload: Payload::FeedbackA(FeedbackA {
                    steer_angle: 0.25,
                    ..FeedbackA::default()
                }),
            })
            .unwrap();
            let u = b.on_frame(bus, &fb, 0.002).unwrap();
            let wheels: Vec<usize> = u
                .items
                .iter()
                .flatten()
                .map(|it| match it {
                    Update::Steer { wheel, .. }
                    | Update::Drive { wheel, .. }
                    | Update::Leg { wheel, .. } => *wheel,
                })
                .collect();
            assert_eq!(wheels, vec![4, 4]);
        }
        assert_eq!(
            (b.bus_of_wheel(4), b.bus_of_node(5), b.wheel_node(4)),
            (1, 1, 5)
        );
    }
}
