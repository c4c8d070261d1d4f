//! Wheel-module firmware emulation (sans-IO): one [`ModuleFirmware`] per CAN node.
//!
//! State machine (the driver's [`ModuleState`]):
//!
//! ```text
//!  Boot ──(boot_time elapsed)──► Ready ──(valid SETPOINT, enable=1)──► Enabled
//!                                  ▲  ◄──(valid SETPOINT, enable=0)────┘   │
//!                                  │                                        │ watchdog / motor fault
//!                                  └──(valid SETPOINT, fault_reset=1)── Fault ◄┘ (also from Ready)
//! ```
//!
//! - Receive path: every frame goes through the module's own
//!   [`rollbase_driver::rx::Receiver`]s, so frames with a bad CRC, wrong DLC or a bad rolling
//!   counter are ignored and counted ([`FirmwareStats`]). SETPOINTs use the configured counter
//!   policy (default: reject a skipped counter, like the driver's default); SYNC uses
//!   `AcceptWithLoss` so a lost SYNC never makes the module skip the next one, while a repeated
//!   (duplicated) SYNC is still rejected and not answered twice.
//! - Enabling needs the explicit `enable` flag in a valid SETPOINT addressed to this node. A
//!   SETPOINT with `fault_reset` clears a latched fault and goes to Ready (not straight to
//!   Enabled: the next SETPOINT with `enable` enables), so a fault reset never starts motors
//!   by itself.
//! - Setpoint watchdog: in Enabled, when no valid SETPOINT arrived for `watchdog` (50 ms), the
//!   module latches [`FAULT_WATCHDOG`] and the motors decelerate at the torque limit to zero.
//! - `brake` in a valid SETPOINT: motors decelerate at the torque limit while it is set.
//!   A disabled module (Boot/Ready/Fault) does the same: the kinematic plant has no free
//!   (coasting) wheel, so "disable" is modelled as a torque-limited stop.
//! - Answers each accepted SYNC with FEEDBACK_A then FEEDBACK_B (not in Boot), each stream with
//!   its own rolling counter; values are clamped into the protocol's declared ranges.
//! - Sends STATUS every `status_period` (100 ms = 10 Hz) and immediately on a change of state
//!   or fault code.

use crate::plant::{MotorSetpoint, SensorReading};
use rollbase_driver::codec::{
    encode, FeedbackA, FeedbackB, Message, ModuleState, Payload, Setpoint, Status, FAULT_NONE,
    FAULT_WATCHDOG,
};
use rollbase_driver::frame::CanFrame;
use rollbase_driver::protocol::{classify, spec, MessageKind};
use rollbase_driver::rx::{CounterPolicy, Receiver, RxError};
use std::time::Duration;

/// Firmware parameters.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct FirmwareConfig {
    /// Setpoint watchdog timeout (default 50 ms).
    pub watchdog: Duration,
    /// STATUS period (default 100 ms, 10 Hz).
    pub status_period: Duration,
    /// Time from power-on (simulator time 0) to Ready (default 0: ready at the first tick).
    pub boot_time: Duration,
    /// Counter policy for SETPOINT frames (default: reject skipped counters).
    pub setpoint_policy: CounterPolicy,
    /// Reported temperature (°C).
    pub temperature: f64,
    /// Reported DC-link voltage (V).
    pub bus_voltage: f64,
}

impl Default for FirmwareConfig {
    fn default() -> Self {
        Self {
            watchdog: Duration::from_millis(50),
            status_period: Duration::from_millis(100),
            boot_time: Duration::ZERO,
            setpoint_policy: CounterPolicy::RejectSkipped,
            temperature: 35.0,
            bus_voltage: 48.0,
        }
    }
}

/// What one module's firmware did so far.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct FirmwareStats {
    /// SYNCs answered with FEEDBACK_A + FEEDBACK_B.
    pub syncs_answered: u64,
    /// SYNCs rejected (bad CRC, repeated counter …) or received in Boot.
    pub syncs_ignored: u64,
    /// Valid SETPOINTs for this node.
    pub setpoints_accepted: u64,
    /// SETPOINTs for this node rejected for a bad CRC.
    pub setpoints_bad_crc: u64,
    /// SETPOINTs for this node rejected for a repeated or skipped counter.
    pub setpoints_bad_counter: u64,
    /// SETPOINTs for this node rejected for any other decode error (DLC, range …).
    pub setpoints_other_error: u64,
    /// Frames sent (FEEDBACK_A, FEEDBACK_B, STATUS).
    pub frames_sent: u64,
    /// STATUS frames sent.
    pub status_sent: u64,
    /// Watchdog trips.
    pub watchdog_trips: u64,
    /// Frames that could not be encoded (never expected: values are clamped).
    pub encode_errors: u64,
}

/// One emulated wheel module.
#[derive(Clone, Debug)]
pub struct ModuleFirmware {
    node: u8,
    cfg: FirmwareConfig,
    state: ModuleState,
    fault_code: u8,
    sync_rx: Receiver,
    setpoint_rx: Receiver,
    setpoint: Setpoint,
    last_valid: Option<Duration>,
    counter_a: u8,
    counter_b: u8,
    counter_status: u8,
    last_status: Option<Duration>,
    status_dirty: bool,
    stop_since: Option<Duration>,
    stats: FirmwareStats,
    /// The module has a leg encoder (and answers SYNC with FEEDBACK_B).
    leg: bool,
}

/// Clamps `v` into the declared range of `kind.signal` (non-finite → 0).
fn clamp_signal(kind: MessageKind, signal: &str, v: f64) -> f64 {
    let v = if v.is_finite() { v } else { 0.0 };
    match spec(kind).signal(signal) {
        Some(s) => v.clamp(s.min, s.max),
        None => v,
    }
}

impl ModuleFirmware {
    /// A module with CAN node `node` (1..=15), powered on at simulator time 0, in Boot.
    pub fn new(node: u8, cfg: FirmwareConfig) -> Self {
        Self {
            node,
            cfg,
            state: ModuleState::Boot,
            fault_code: FAULT_NONE,
            sync_rx: Receiver::with_policy(CounterPolicy::AcceptWithLoss),
            setpoint_rx: Receiver::with_policy(cfg.setpoint_policy),
            setpoint: Setpoint::default(),
            last_valid: None,
            counter_a: 0,
            counter_b: 0,
            counter_status: 0,
            last_status: None,
            status_dirty: true,
            stop_since: None,
            stats: FirmwareStats::default(),
            leg: true,
        }
    }

    /// The same module without a leg encoder: it answers a SYNC with FEEDBACK_A only (a
    /// wheel without a leg has no leg extension to report; its motor currents go unreported).
    pub fn without_leg(mut self) -> Self {
        self.leg = false;
        self
    }

    /// The module's CAN node.
    pub fn node(&self) -> u8 {
        self.node
    }

    /// Current state.
    pub fn state(&self) -> ModuleState {
        self.state
    }

    /// Latched fault code (`FAULT_NONE` when none).
    pub fn fault_code(&self) -> u8 {
        self.fault_code
    }

    /// Counters.
    pub fn stats(&self) -> &FirmwareStats {
        &self.stats
    }

    /// The SYNC receiver's statistics.
    pub fn sync_rx_stats(&self) -> &rollbase_driver::rx::RxStats {
        self.sync_rx.stats()
    }

    /// The SETPOINT receiver's statistics.
    pub fn setpoint_rx_stats(&self) -> &rollbase_driver::rx::RxStats {
        self.setpoint_rx.stats()
    }

    /// Time of the last valid SETPOINT, if any.
    pub fn last_valid_setpoint(&self) -> Option<Duration> {
        self.last_valid
    }

    /// Since when the motors have been commanded to stop (disabled, braking, fault), if
    /// they are; `None` while enabled and following setpoints.
    pub fn stopping_since(&self) -> Option<Duration> {
        self.stop_since
    }

    fn set_state(&mut self, now: Duration, state: ModuleState, fault: u8) {
        if state != self.state || fault != self.fault_code {
            self.state = state;
            self.fault_code = fault;
            self.status_dirty = true;
        }
        self.update_stop(now);
    }

    fn update_stop(&mut self, now: Duration) {
        let running = self.state == ModuleState::Enabled && !self.setpoint.flags.brake;
        if running {
            self.stop_since = None;
        } else if self.stop_since.is_none() {
            self.stop_since = Some(now);
        }
    }

    /// Latches a fault with `code` (e.g. a motor over-current), stopping the motors.
    pub fn inject_fault(&mut self, now: Duration, code: u8) {
        self.set_state(now, ModuleState::Fault, code);
    }

    /// What the motors should do now.
    pub fn motor_setpoint(&self) -> MotorSetpoint {
        if self.state == ModuleState::Enabled && !self.setpoint.flags.brake {
            MotorSetpoint {
                wheel_speed: self.setpoint.wheel_speed,
                steer_rate: self.setpoint.steer_rate,
                drive_enabled: true,
                steer_enabled: true,
            }
        } else {
            MotorSetpoint::default()
        }
    }

    fn send(&mut self, msg: Message, out: &mut impl FnMut(CanFrame)) {
        match encode(&msg) {
            Ok(f) => {
                self.stats.frames_sent += 1;
                out(f);
            }
            Err(_) => self.stats.encode_errors += 1,
        }
    }

    fn send_status(&mut self, now: Duration, out: &mut impl FnMut(CanFrame)) {
        let msg = Message {
            node: self.node,
            counter: self.counter_status,
            payload: Payload::Status(Status {
                state: self.state,
                fault_code: self.fault_code,
                temperature: clamp_signal(MessageKind::Status, "temperature", self.cfg.temperature),
                bus_voltage: clamp_signal(MessageKind::Status, "bus_voltage", self.cfg.bus_voltage),
            }),
        };
        self.counter_status = (self.counter_status + 1) & 0x0F;
        self.send(msg, out);
        self.stats.status_sent += 1;
        self.last_status = Some(now);
        self.status_dirty = false;
    }

    /// Time-driven work at `now`: boot completion, setpoint watchdog, STATUS (periodic and on
    /// change). Call it at every plant sub-step and before handling a frame.
    pub fn tick(&mut self, now: Duration, out: &mut impl FnMut(CanFrame)) {
        if self.state == ModuleState::Boot && now >= self.cfg.boot_time {
            self.set_state(now, ModuleState::Ready, self.fault_code);
        }
        if self.state == ModuleState::Enabled {
            let last = self.last_valid.unwrap_or(Duration::ZERO);
            if now.saturating_sub(last) >= self.cfg.watchdog {
                self.stats.watchdog_trips += 1;
                self.set_state(now, ModuleState::Fault, FAULT_WATCHDOG);
            }
        }
        self.update_stop(now);
        let due = match self.last_status {
            None => true,
            Some(t) => now.saturating_sub(t) >= self.cfg.status_period,
        };
        if self.state != ModuleState::Boot && (self.status_dirty || due) {
            self.send_status(now, out);
        }
    }

    /// Handles one received frame at `now`; `sensors` is this module's current encoder
    /// reading (used to answer a SYNC). Frames for other nodes and module-to-controller
    /// frames are ignored.
    pub fn handle_frame(
        &mut self,
        now: Duration,
        frame: &CanFrame,
        sensors: &SensorReading,
        out: &mut impl FnMut(CanFrame),
    ) {
        match classify(frame.id()) {
            Some((MessageKind::Sync, _)) => self.on_sync(now, frame, sensors, out),
            Some((MessageKind::Setpoint, node)) if node == self.node => {
                self.on_setpoint(now, frame, out)
            }
            _ => {}
        }
    }

    fn on_sync(
        &mut self,
        now: Duration,
        frame: &CanFrame,
        s: &SensorReading,
        out: &mut impl FnMut(CanFrame),
    ) {
        if self.sync_rx.accept(frame).is_err() || self.state == ModuleState::Boot {
            self.stats.syncs_ignored += 1;
            return;
        }
        let _ = now;
        let a = Message {
            node: self.node,
            counter: self.counter_a,
            payload: Payload::FeedbackA(FeedbackA {
                steer_angle: clamp_signal(MessageKind::FeedbackA, "steer_angle", s.steer_angle),
                wheel_speed: clamp_signal(MessageKind::FeedbackA, "wheel_speed", s.wheel_speed),
                steer_rate: clamp_signal(MessageKind::FeedbackA, "steer_rate", s.steer_rate),
            }),
        };
        let b = Message {
            node: self.node,
            counter: self.counter_b,
            payload: Payload::FeedbackB(FeedbackB {
                leg_extension: clamp_signal(MessageKind::FeedbackB, "leg_extension", s.leg),
                leg_rate: clamp_signal(MessageKind::FeedbackB, "leg_rate", s.leg_rate),
                drive_current: clamp_signal(
                    MessageKind::FeedbackB,
                    "drive_current",
                    s.drive_current,
                ),
                steer_current: clamp_signal(
                    MessageKind::FeedbackB,
                    "steer_current",
                    s.steer_current,
                ),
            }),
        };
        self.counter_a = (self.counter_a + 1) & 0x0F;
        self.send(a, out);
        if self.leg {
            self.counter_b = (self.counter_b + 1) & 0x0F;
            self.send(b, out);
        }
        self.stats.syncs_answered += 1;
    }

    fn on_setpoint(&mut self, now: Duration, frame: &CanFrame, out: &mut impl FnMut(CanFrame)) {
        let msg = match self.setpoint_rx.accept(frame) {
            Ok(m) => m,
            Err(RxError::Decode(rollbase_driver::codec::DecodeError::BadCrc { .. })) => {
                self.stats.setpoints_bad_crc += 1;
                return;
            }
            Err(RxError::RepeatedCounter { .. } | RxError::SkippedCounter { .. }) => {
                self.stats.setpoints_bad_counter += 1;
                return;
            }
            Err(_) => {
                self.stats.setpoints_other_error += 1;
                return;
            }
        };
        let Payload::Setpoint(sp) = msg.payload else {
            self.stats.setpoints_other_error += 1;
            return;
        };
        if self.state == ModuleState::Boot {
            // Not listening yet.
            return;
        }
        self.stats.setpoints_accepted += 1;
        self.last_valid = Some(now);
        self.setpoint = sp;
        match self.state {
            ModuleState::Fault if sp.flags.fault_reset => {
                self.setpoint.flags.enable = false;
                self.set_state(now, ModuleState::Ready, FAULT_NONE);
            }
            ModuleState::Ready if sp.flags.enable => {
                self.set_state(now, ModuleState::Enabled, FAULT_NONE)
            }
            ModuleState::Enabled if !sp.flags.enable => {
                self.set_state(now, ModuleState::Ready, FAULT_NONE)
            }
            _ => self.update_stop(now),
        }
        if self.status_dirty {
            self.send_status(now, out);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rollbase_driver::codec::{decode, SetpointFlags, Sync, FAULT_OVERCURRENT};

    const NODE: u8 = 2;

    fn ms(t: u64) -> Duration {
        Duration::from_millis(t)
    }

    fn sync(counter: u8, cycle: u16) -> CanFrame {
        encode(&Message {
            node: 0,
            counter,
            payload: Payload::Sync(Sync { cycle }),
        })
        .unwrap()
    }

    fn setpoint(counter: u8, w: f64, enable: bool, fault_reset: bool) -> CanFrame {
        encode(&Message {
            node: NODE,
            counter,
            payload: Payload::Setpoint(Setpoint {
                wheel_speed: w,
                steer_rate: 0.1,
                flags: SetpointFlags {
                    enable,
                    brake: false,
                    fault_reset,
                },
            }),
        })
        .unwrap()
    }

    fn sensors() -> SensorReading {
        SensorReading {
            steer_angle: 0.5,
            steer_rate: -0.25,
            wheel_speed: 3.25,
            leg: 0.45,
            leg_rate: 0.02,
            drive_current: 2.5,
            steer_current: -1.0,
        }
    }

    /// A booted (Ready) module and the frames it sent.
    fn ready() -> (ModuleFirmware, Vec<CanFrame>) {
        let mut fw = ModuleFirmware::new(NODE, FirmwareConfig::default());
        let mut out = Vec::new();
        fw.tick(ms(0), &mut |f| out.push(f));
        assert_eq!(fw.state(), ModuleState::Ready);
        (fw, out)
    }

    fn statuses(frames: &[CanFrame]) -> Vec<Status> {
        frames
            .iter()
            .filter_map(|f| match decode(f) {
                Ok(Message {
                    payload: Payload::Status(s),
                    ..
                }) => Some(s),
                _ => None,
            })
            .collect()
    }

    #[test]
    fn answers_every_sync_with_both_feedback_frames() {
        let (mut fw, _) = ready();
        let mut rx = Receiver::new();
        let s = sensors();
        for k in 0..100u16 {
            let mut out = Vec::new();
            fw.handle_frame(
                ms(4 * u64::from(k)),
                &sync((k % 16) as u8, k),
                &s,
                &mut |f| out.push(f),
            );
            assert_eq!(out.len(), 2, "SYNC {k}");
            assert_eq!(out[0].id(), 0x180 + u16::from(NODE));
            assert_eq!(out[1].id(), 0x280 + u16::from(NODE));
            // Counters in sequence and CRCs valid: the strict receiver accepts all.
            let a = rx.accept(&out[0]).unwrap();
            let b = rx.accept(&out[1]).unwrap();
            let (Payload::FeedbackA(a), Payload::FeedbackB(b)) = (a.payload, b.payload) else {
                panic!("wrong payloads");
            };
            assert!((a.steer_angle - 0.5).abs() < 1e-4 && (a.wheel_speed - 3.25).abs() < 1e-3);
            assert!((a.steer_rate + 0.25).abs() < 1e-3);
            assert!((b.leg_extension - 0.45).abs() < 1e-5 && (b.leg_rate - 0.02).abs() < 1e-4);
            assert!((b.drive_current - 2.5).abs() < 0.125 && (b.steer_current + 1.0).abs() < 0.125);
        }
        assert_eq!(fw.stats().syncs_answered, 100);
        // A lost SYNC does not stop the module answering the next one …
        let mut out = Vec::new();
        fw.handle_frame(ms(400), &sync(6, 102), &s, &mut |f| out.push(f));
        assert_eq!(out.len(), 2);
        // … but a duplicated SYNC is answered once.
        let mut out = Vec::new();
        fw.handle_frame(ms(400), &sync(6, 102), &s, &mut |f| out.push(f));
        assert!(out.is_empty());
        assert_eq!(fw.stats().syncs_ignored, 1);
    }

    #[test]
    fn out_of_range_sensor_values_are_clamped_not_dropped() {
        let (mut fw, _) = ready();
        let s = SensorReading {
            wheel_speed: 100.0,
            leg: 0.9,
            drive_current: f64::NAN,
            ..sensors()
        };
        let mut out = Vec::new();
        fw.handle_frame(ms(0), &sync(0, 0), &s, &mut |f| out.push(f));
        assert_eq!(out.len(), 2);
        assert_eq!(fw.stats().encode_errors, 0);
    }

    #[test]
    fn enables_only_on_explicit_flag() {
        let (mut fw, _) = ready();
        let mut out = Vec::new();
        fw.handle_frame(
            ms(1),
            &setpoint(0, 2.0, false, false),
            &sensors(),
            &mut |f| out.push(f),
        );
        assert_eq!(fw.state(), ModuleState::Ready);
        assert!(!fw.motor_setpoint().drive_enabled);
        assert_eq!(fw.motor_setpoint().wheel_speed, 0.0);
        fw.handle_frame(
            ms(5),
            &setpoint(1, 2.0, true, false),
            &sensors(),
            &mut |f| out.push(f),
        );
        assert_eq!(fw.state(), ModuleState::Enabled);
        let m = fw.motor_setpoint();
        assert!(m.drive_enabled && m.steer_enabled && (m.wheel_speed - 2.0).abs() < 1e-12);
        // A setpoint addressed to another node does nothing.
        let other = encode(&Message {
            node: NODE + 1,
            counter: 2,
            payload: Payload::Setpoint(Setpoint::default()),
        })
        .unwrap();
        fw.handle_frame(ms(9), &other, &sensors(), &mut |f| out.push(f));
        assert_eq!(fw.state(), ModuleState::Enabled);
        fw.handle_frame(
            ms(9),
            &setpoint(2, 2.0, false, false),
            &sensors(),
            &mut |f| out.push(f),
        );
        assert_eq!(fw.state(), ModuleState::Ready);
        // Each change was announced at once.
        let st: Vec<ModuleState> = statuses(&out).iter().map(|s| s.state).collect();
        assert_eq!(st, vec![ModuleState::Enabled, ModuleState::Ready]);
    }

    #[test]
    fn bad_crc_and_bad_counter_are_ignored_and_counted() {
        let (mut fw, _) = ready();
        let s = sensors();
        let mut out = Vec::new();
        fw.handle_frame(ms(0), &setpoint(0, 1.0, true, false), &s, &mut |f| {
            out.push(f)
        });
        assert_eq!(fw.state(), ModuleState::Enabled);
        // Corrupted: one payload bit flipped in the wheel speed.
        let bad = setpoint(1, 5.0, true, false).with_flipped_bit(3);
        fw.handle_frame(ms(4), &bad, &s, &mut |f| out.push(f));
        assert_eq!(fw.stats().setpoints_bad_crc, 1);
        assert!((fw.motor_setpoint().wheel_speed - 1.0).abs() < 1e-12);
        assert_eq!(fw.last_valid_setpoint(), Some(ms(0)));
        // Repeated counter (stale/duplicated frame).
        fw.handle_frame(ms(8), &setpoint(0, 5.0, true, false), &s, &mut |f| {
            out.push(f)
        });
        assert_eq!(fw.stats().setpoints_bad_counter, 1);
        assert!((fw.motor_setpoint().wheel_speed - 1.0).abs() < 1e-12);
        // Skipped counter (0 → 5) rejected under the default strict policy …
        fw.handle_frame(ms(12), &setpoint(5, 5.0, true, false), &s, &mut |f| {
            out.push(f)
        });
        assert_eq!(fw.stats().setpoints_bad_counter, 2);
        assert!((fw.motor_setpoint().wheel_speed - 1.0).abs() < 1e-12);
        // … and the stream re-synchronised: 6 is accepted.
        fw.handle_frame(ms(16), &setpoint(6, 5.0, true, false), &s, &mut |f| {
            out.push(f)
        });
        assert!((fw.motor_setpoint().wheel_speed - 5.0).abs() < 1e-12);
        assert_eq!(fw.stats().setpoints_accepted, 2);
        assert_eq!(fw.last_valid_setpoint(), Some(ms(16)));
        // A bad frame on a SYNC is not answered.
        let mut out = Vec::new();
        fw.handle_frame(ms(20), &sync(0, 0).with_flipped_bit(0), &s, &mut |f| {
            out.push(f)
        });
        assert!(out.is_empty());
    }

    #[test]
    fn watchdog_stops_motors_50ms_after_last_valid_setpoint() {
        let (mut fw, _) = ready();
        let s = sensors();
        let mut out = Vec::new();
        let mut counter = 0u8;
        // Valid setpoints every 4 ms from t = 1 ms to t = 97 ms, ticks every 1 ms.
        let mut last = ms(0);
        let mut trip = None;
        for t in 0..300u64 {
            if t % 4 == 1 && t < 100 {
                fw.handle_frame(ms(t), &setpoint(counter, 3.0, true, false), &s, &mut |f| {
                    out.push(f)
                });
                counter = (counter + 1) & 0x0F;
                last = ms(t);
            }
            fw.tick(ms(t), &mut |f| out.push(f));
            if trip.is_none() && fw.state() == ModuleState::Fault {
                trip = Some(ms(t));
            }
        }
        let trip = trip.expect("watchdog tripped");
        assert_eq!(last, ms(97));
        assert_eq!(
            trip - last,
            ms(50),
            "tripped {trip:?} after last setpoint {last:?}"
        );
        assert_eq!(fw.fault_code(), FAULT_WATCHDOG);
        assert_eq!(fw.stopping_since(), Some(trip));
        assert!(!fw.motor_setpoint().drive_enabled);
        assert_eq!(fw.stats().watchdog_trips, 1);
        let st = statuses(&out);
        assert!(st
            .iter()
            .any(|s| s.state == ModuleState::Fault && s.fault_code == FAULT_WATCHDOG));
    }

    #[test]
    fn faults_latch_until_reset() {
        let (mut fw, _) = ready();
        let s = sensors();
        let mut out = Vec::new();
        fw.handle_frame(ms(0), &setpoint(0, 2.0, true, false), &s, &mut |f| {
            out.push(f)
        });
        fw.inject_fault(ms(2), FAULT_OVERCURRENT);
        assert_eq!(fw.state(), ModuleState::Fault);
        assert!(!fw.motor_setpoint().drive_enabled);
        // Enable alone does not clear it.
        for k in 1..5u8 {
            fw.handle_frame(
                ms(4 * u64::from(k)),
                &setpoint(k, 2.0, true, false),
                &s,
                &mut |f| out.push(f),
            );
            fw.tick(ms(4 * u64::from(k)), &mut |f| out.push(f));
            assert_eq!(fw.state(), ModuleState::Fault);
            assert_eq!(fw.fault_code(), FAULT_OVERCURRENT);
        }
        // Reset → Ready (motors still off), then enable → Enabled.
        fw.handle_frame(ms(20), &setpoint(5, 2.0, true, true), &s, &mut |f| {
            out.push(f)
        });
        assert_eq!(fw.state(), ModuleState::Ready);
        assert_eq!(fw.fault_code(), FAULT_NONE);
        assert!(!fw.motor_setpoint().drive_enabled);
        fw.handle_frame(ms(24), &setpoint(6, 2.0, true, false), &s, &mut |f| {
            out.push(f)
        });
        assert_eq!(fw.state(), ModuleState::Enabled);
        assert!(fw.motor_setpoint().drive_enabled);
        let seq: Vec<(ModuleState, u8)> = statuses(&out)
            .iter()
            .map(|s| (s.state, s.fault_code))
            .collect();
        assert_eq!(
            seq,
            vec![
                (ModuleState::Enabled, FAULT_NONE),
                (ModuleState::Fault, FAULT_OVERCURRENT),
                (ModuleState::Ready, FAULT_NONE),
                (ModuleState::Enabled, FAULT_NONE),
            ]
        );
    }

    #[test]
    fn status_at_10_hz_with_its_own_counter() {
        let (mut fw, mut out) = ready();
        for t in 1..=1000u64 {
            fw.tick(ms(t), &mut |f| out.push(f));
        }
        // Boot → Ready announced at t = 0, then every 100 ms: 0, 100, …, 1000.
        let st = statuses(&out);
        assert_eq!(st.len(), 11);
        assert!(st.iter().all(|s| s.state == ModuleState::Ready));
        assert!((st[0].bus_voltage - 48.0).abs() < 0.01 && (st[0].temperature - 35.0).abs() < 1.0);
        let mut rx = Receiver::new();
        for f in &out {
            rx.accept(f).unwrap();
        }
    }

    #[test]
    fn boot_ignores_sync_until_ready() {
        let cfg = FirmwareConfig {
            boot_time: ms(20),
            ..FirmwareConfig::default()
        };
        let mut fw = ModuleFirmware::new(NODE, cfg);
        let mut out = Vec::new();
        fw.tick(ms(10), &mut |f| out.push(f));
        fw.handle_frame(ms(10), &sync(0, 0), &sensors(), &mut |f| out.push(f));
        assert!(out.is_empty());
        assert_eq!(fw.state(), ModuleState::Boot);
        fw.tick(ms(20), &mut |f| out.push(f));
        assert_eq!(fw.state(), ModuleState::Ready);
        assert_eq!(statuses(&out).len(), 1);
    }
}
