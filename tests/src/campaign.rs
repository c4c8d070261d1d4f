//! The fault campaign (issue 8): every fault of the issue through the whole stack in lockstep
//! (controller [`CycleCore`] → virtual bus → simulated modules → virtual bus → controller),
//! with the outcome of each asserted and summarised as a table row.
//!
//! [`Rig`] is the lockstep loop of `rollbase_control::runtime::run_lockstep`, one cycle per
//! call, with hooks the campaign needs and `run_lockstep` does not offer: re-arming between
//! cycles, a dead controller (no SYNC/SETPOINT at all), the controller's interface going down
//! and coming back, and a hook on every frame the controller receives (to corrupt, duplicate,
//! forge or alter feedback). The per-cycle order (peer catches up, SYNC, feedback window,
//! control step, SETPOINTs) is exactly that of `run_lockstep`.
//!
//! Each case is a function returning a [`CaseResult`]; `quick = true` shortens the runs so the
//! debug-mode tests stay fast (the assertions are the same).

use rollbase_control::runtime::record::CycleRecord;
use rollbase_control::runtime::scenario::{self, Scenario};
use rollbase_control::runtime::{
    lockstep_cycle, CycleCore, LockstepState, RuntimeConfig, VirtualLockstepBus,
};
use rollbase_control::supervisor::{FaultReason, SupervisorState};
use rollbase_control::{Platform, MAX_WHEELS};
use rollbase_driver::codec::{decode, encode, Payload};
use rollbase_driver::crc::frame_crc;
use rollbase_driver::frame::CanFrame;
use rollbase_driver::protocol::{classify, spec, MessageKind};
use rollbase_driver::rx::CounterPolicy;
use rollbase_vcan_sim::{FaultSchedule, Simulator};
use std::time::Duration;

/// The nominal position-error bound of the seed-000 run (m); the issue allows 2× under loss.
pub const NOMINAL_BOUND_M: f64 = 0.005;

/// What to build a [`Rig`] from: the harness's options.
pub type RigOptions = crate::RunOptions;

/// A hook on the controller's receive path: sees one received frame, emits what the
/// controller gets instead.
pub type RxHook<'a> = &'a mut dyn FnMut(&CanFrame, &mut dyn FnMut(CanFrame));

/// Per-cycle hooks: those of the runtime's lockstep driver.
pub type Hooks<'a> = rollbase_control::runtime::StepHooks<'a>;

/// The whole stack in lockstep, one cycle per [`Rig::step`].
pub struct Rig {
    /// The controller's cycle core.
    pub core: CycleCore,
    /// The simulated modules and plant.
    pub sim: Simulator,
    /// The in-process bus on virtual time.
    pub bus: VirtualLockstepBus,
    /// The lockstep driver's state (time, queued frames, frames lost to a down interface).
    pub st: LockstepState,
}

impl Rig {
    /// Builds the stack and arms the controller (as `run_lockstep` does).
    pub fn new(o: &RigOptions) -> Result<Self, String> {
        let (mut core, sim, bus, _) = crate::build(o)?;
        core.arm();
        let st = LockstepState::new(&core);
        Ok(Self { core, sim, bus, st })
    }

    /// Cycles run so far.
    pub fn cycle(&self) -> u64 {
        self.st.cycle()
    }

    /// Start time of the next cycle (s).
    pub fn time(&self) -> f64 {
        self.st.time()
    }

    /// Runs one cycle; returns the controller's record (`None` when the controller is
    /// silent this cycle).
    pub fn step(&mut self, hooks: &mut Hooks<'_>) -> Option<&CycleRecord> {
        if lockstep_cycle(
            &mut self.st,
            &mut self.core,
            &mut self.bus,
            &mut self.sim,
            hooks,
        ) {
            Some(self.core.record())
        } else {
            None
        }
    }
}

/// Running figures of a case.
#[derive(Clone, Debug, Default)]
pub struct Track {
    /// Largest position error against the plant's truth while tracking (m).
    pub max_err: f64,
    /// Cycle of the first Tracking record.
    pub tracking_from: Option<u64>,
    /// First Fault record: (cycle, time, reason).
    pub fault: Option<(u64, f64, Option<FaultReason>)>,
    /// Last supervisor state.
    pub last_state: Option<SupervisorState>,
    /// Largest feedback age (cycles) seen in a Tracking record.
    pub max_age_tracking: u32,
    /// Cycles whose newest feedback was older than the feedback window (late frames).
    pub late_cycles: u64,
    /// Largest per-cycle wheel-speed change after the fault (rad/s).
    pub max_dv_after_fault: f64,
    /// Largest growth of a commanded steering rate's magnitude from one cycle to the next
    /// after the fault (rad/s; 0 when the steering only winds down or holds).
    pub max_steer_growth_after_fault: f64,
    /// Largest per-cycle steering-rate change after the fault (rad/s).
    pub max_dsteer_after_fault: f64,
    /// Last command's largest wheel speed (rad/s).
    pub last_speed: f64,
    prev_speeds: [f64; MAX_WHEELS],
    prev_steer: [f64; MAX_WHEELS],
    /// Records seen.
    pub cycles: u64,
}

impl Track {
    /// Takes one record.
    pub fn update(&mut self, r: &CycleRecord, window_s: f64) {
        let n = r.n.min(MAX_WHEELS);
        self.cycles += 1;
        if r.state == SupervisorState::Tracking {
            self.tracking_from.get_or_insert(r.cycle);
            let age = r.feedback_age[..n].iter().copied().max().unwrap_or(0);
            self.max_age_tracking = self.max_age_tracking.max(age);
            if let Some((pose, _)) = r.truth {
                let z = &r.reference.z;
                let e = ((z[0] - pose.x).powi(2) + (z[1] - pose.y).powi(2)).sqrt();
                self.max_err = self.max_err.max(e);
            }
        }
        if r.timing.feedback_age_us.is_finite() && r.timing.feedback_age_us > window_s * 1e6 {
            self.late_cycles += 1;
        }
        if r.state == SupervisorState::Fault && self.fault.is_none() {
            self.fault = Some((r.cycle, r.t, r.reason));
        }
        let mut peak = 0.0f64;
        for i in 0..n {
            let w = r.command.wheels[i];
            if self.fault.is_some() {
                self.max_dv_after_fault = self
                    .max_dv_after_fault
                    .max((w.wheel_speed - self.prev_speeds[i]).abs());
                let prev = self.prev_steer[i];
                self.max_steer_growth_after_fault = self
                    .max_steer_growth_after_fault
                    .max(w.steer_rate.abs() - prev.abs());
                self.max_dsteer_after_fault =
                    self.max_dsteer_after_fault.max((w.steer_rate - prev).abs());
            }
            self.prev_speeds[i] = w.wheel_speed;
            self.prev_steer[i] = w.steer_rate;
            peak = peak.max(w.wheel_speed.abs());
        }
        self.last_speed = peak;
        self.last_state = Some(r.state);
    }

    /// The fault was a controlled stop: speed steps within `accel·dt` (plus rounding), the
    /// steering winding down within its acceleration limit and then held (never turning
    /// faster than when the fault came), wheels at rest at the end.
    pub fn controlled_stop(&self, p: &Platform) -> bool {
        self.fault.is_some()
            && self.max_dv_after_fault <= p.limits.wheel_accel * p.dt() + 1e-9
            && self.max_steer_growth_after_fault <= 1e-12
            && self.max_dsteer_after_fault <= p.limits.steer_accel * p.dt() + 1e-9
            && self.last_speed == 0.0
    }
}

/// One row of the table.
#[derive(Clone, Debug)]
pub struct CaseResult {
    /// Fault name.
    pub fault: String,
    /// The policy for it.
    pub policy: String,
    /// Detection time (text, e.g. "16 ms (4 cycles)").
    pub detection: String,
    /// What the platform did.
    pub outcome: String,
    /// Data lost / rejected.
    pub data_lost: String,
    /// The assertions held.
    pub pass: bool,
    /// Failed assertions, if any.
    pub failures: Vec<String>,
    /// Largest position error against the truth while tracking (m), where measured.
    pub max_err: f64,
}

impl CaseResult {
    fn new(fault: &str, policy: &str) -> Self {
        Self {
            fault: fault.into(),
            policy: policy.into(),
            detection: "—".into(),
            outcome: String::new(),
            data_lost: "none".into(),
            pass: true,
            failures: Vec::new(),
            max_err: 0.0,
        }
    }

    fn check(&mut self, ok: bool, what: impl Into<String>) {
        if !ok {
            self.pass = false;
            self.failures.push(what.into());
        }
    }
}

fn ms(cycles: u64, p: &Platform) -> String {
    format!("{:.0} ms ({cycles} cycles)", cycles as f64 * p.dt() * 1e3)
}

fn fmt_reason(r: &Option<FaultReason>) -> String {
    r.map_or_else(|| "none".into(), |r| r.to_string())
}

/// Runs the rig until the core is done or `max_cycles`, feeding `track`.
fn run_to_end(rig: &mut Rig, track: &mut Track, max_cycles: u64, hooks: &mut Hooks<'_>) {
    let window = rig.st.window();
    while rig.cycle() < max_cycles {
        if let Some(r) = rig.step(hooks) {
            track.update(r, window);
        }
        if rig.core.done() {
            break;
        }
    }
}

fn max_cycles(quick: bool, full_s: f64, quick_s: f64) -> u64 {
    ((if quick { quick_s } else { full_s }) * 250.0) as u64
}

/// Random frame loss on the bus medium (both directions) at probability `p`.
pub fn frame_loss(p: f64, seed: u64, quick: bool) -> CaseResult {
    let mut c = CaseResult::new(
        &format!("random frame loss {:.0} %", p * 100.0),
        "keep tracking on the last values; a module with neither feedback frame for > 3 cycles, or either stream > 8 cycles old → stale-feedback fault, controlled stop (data age recorded every cycle)",
    );
    let mut o = RigOptions::new(Scenario::Seed000);
    o.bus_faults.drop_prob = p;
    o.seed = seed;
    let mut rig = match Rig::new(&o) {
        Ok(r) => r,
        Err(e) => {
            c.check(false, e);
            return c;
        }
    };
    let mut t = Track::default();
    run_to_end(
        &mut rig,
        &mut t,
        max_cycles(quick, 60.0, 16.0),
        &mut Hooks::default(),
    );
    let p_ = Platform::justin();
    let stats = *rig.core.rx_stats();
    let completed = t.last_state == Some(SupervisorState::Stopped);
    c.outcome = match &t.fault {
        None if completed => format!("trajectory completed, max error {:.2} mm", t.max_err * 1e3),
        None => format!(
            "tracking ({} cycles run), max error {:.2} mm",
            t.cycles,
            t.max_err * 1e3
        ),
        Some((_, time, r)) => format!(
            "controlled stop at {time:.2} s: {}; max error before {:.2} mm",
            fmt_reason(r),
            t.max_err * 1e3
        ),
    };
    if let Some((cy, _, _)) = t.fault {
        c.detection = format!("fault at cycle {cy}");
    }
    c.max_err = t.max_err;
    c.data_lost = format!(
        "{} frames lost (counter gaps), bus dropped {}; max age while tracking {} cycles",
        stats.lost,
        rig.bus.bus.stats().faults.dropped,
        t.max_age_tracking
    );
    c.check(
        t.max_age_tracking <= o.runtime.supervisor.stale_data_cycles,
        format!("tracked on data {} cycles old", t.max_age_tracking),
    );
    {
        let ok_track =
            t.fault.is_none() && t.max_err <= 2.0 * NOMINAL_BOUND_M && (quick || completed);
        let ok_stop = t.fault.is_some() && t.controlled_stop(&p_);
        c.check(
            ok_track || ok_stop,
            format!(
                "neither tracking within 10 mm ({:.2} mm) nor a controlled stop ({:?})",
                t.max_err * 1e3,
                t.fault
            ),
        );
    }
    c
}

/// Frame loss over several seeds: returns one row with the completion rate.
pub fn frame_loss_seeds(p: f64, seeds: u64, quick: bool) -> CaseResult {
    let mut rows: Vec<CaseResult> = (1..=seeds).map(|s| frame_loss(p, s, quick)).collect();
    let completed = rows.iter().filter(|r| r.pass && r.detection == "—").count();
    let stopped = rows.iter().filter(|r| r.pass && r.detection != "—").count();
    let worst = rows.iter().map(|r| r.max_err).fold(0.0, f64::max);
    let mut c = rows.remove(0);
    c.outcome = format!(
        "{completed}/{seeds} seeds completed without a fault; seed 1: {}",
        c.outcome
    );
    for r in &rows {
        c.failures.extend(r.failures.iter().cloned());
    }
    c.outcome.push_str(&format!(
        "; {stopped}/{seeds} controlled stops; max error over all seeds while tracking {:.2} mm",
        worst * 1e3
    ));
    c.pass = c.failures.is_empty();
    // 1 %: every seed completes. 5 %: a rare controlled stop (a module missing both frames,
    // or the SYNC lost, 4 cycles in a row) is allowed for at most 1 seed in 10. 20 %: any
    // mix of tracking within 10 mm and controlled stops.
    if p > 0.0 && p <= 0.01 {
        c.check(
            completed as u64 == seeds,
            format!("only {completed}/{seeds} completed"),
        );
    }
    if p > 0.01 && p <= 0.05 {
        let need = (seeds * 9).div_ceil(10) as usize;
        c.check(
            completed >= need,
            format!("only {completed}/{seeds} seeds completed at 5 % loss"),
        );
    }
    c
}

/// A scheduled simulator fault at `at` (s): runs until the core is done and fills the
/// detection time, outcome and frame counts.
fn scheduled(
    name: &str,
    policy: &str,
    o: &RigOptions,
    at: f64,
    max_s: f64,
) -> (CaseResult, Track, Option<Rig>) {
    let mut c = CaseResult::new(name, policy);
    let mut rig = match Rig::new(o) {
        Ok(r) => r,
        Err(e) => {
            c.check(false, e);
            return (c, Track::default(), None);
        }
    };
    let mut t = Track::default();
    run_to_end(
        &mut rig,
        &mut t,
        (max_s * 250.0) as u64,
        &mut Hooks::default(),
    );
    let p = Platform::justin();
    match t.fault {
        Some((cy, time, r)) => {
            let d = ((time - at) / p.dt()).round().max(0.0) as u64;
            c.detection = ms(d, &p);
            c.outcome = format!(
                "{}: {}",
                if t.controlled_stop(&p) {
                    "controlled stop, latched"
                } else {
                    "FAULT WITHOUT CONTROLLED STOP"
                },
                fmt_reason(&r)
            );
            let _ = cy;
        }
        None => {
            c.outcome = format!(
                "no fault; final state {:?}, max error {:.2} mm",
                t.last_state,
                t.max_err * 1e3
            )
        }
    }
    let s = *rig.core.rx_stats();
    c.data_lost = format!(
        "rx rejected {}, lost {}; rest of trajectory not run",
        s.rejected(),
        s.lost
    );
    (c, t, Some(rig))
}

/// One module silent for 2 s mid-trajectory, then back; re-armed 1 s after it returned.
pub fn silent_module_rearm(quick: bool) -> CaseResult {
    let _ = quick;
    let mut c = CaseResult::new(
        "one module silent (node 3, 2 s), back, re-armed",
        "neither FEEDBACK_A nor _B for > 3 cycles → stale-feedback fault naming the module, controlled stop; latched when it returns; re-arm = CycleCore::arm() (operator request), then the start check decides",
    );
    let mut o = RigOptions::new(Scenario::Seed000);
    o.faults.silent.push(rollbase_vcan_sim::faults::Silent {
        node: 3,
        from: 10.0,
        to: 12.0,
    });
    let Ok(mut rig) = Rig::new(&o) else {
        c.check(false, "rig");
        return c;
    };
    let p = Platform::justin();
    let mut t = Track::default();
    let mut latched_after_return = true;
    while rig.time() < 13.0 {
        if let Some(r) = rig.step(&mut Hooks::default()) {
            t.update(r, 0.002);
            if r.t > 12.1 && r.state != SupervisorState::Fault {
                latched_after_return = false;
            }
        }
    }
    match t.fault {
        Some((_, time, Some(FaultReason::StaleFeedback { node: 3, .. }))) => {
            c.detection = ms(((time - 10.0) / p.dt()).round() as u64, &p);
        }
        f => c.check(
            false,
            format!("expected stale feedback of node 3, got {f:?}"),
        ),
    }
    c.check(t.controlled_stop(&p), "not a controlled stop");
    c.check(latched_after_return, "left Fault without re-arm");
    let armed = rig.core.arm();
    c.check(armed, "arm refused");
    let mut after = Track::default();
    for _ in 0..250 {
        if let Some(r) = rig.step(&mut Hooks::default()) {
            after.update(r, 0.002);
        }
    }
    let reason = after.fault.and_then(|f| f.2);
    c.check(
        matches!(reason, Some(FaultReason::StartMismatch { .. })),
        format!("after re-arm mid-trajectory expected a start mismatch, got {reason:?}"),
    );
    c.check(
        after.tracking_from.is_none(),
        "tracked after re-arm from the wrong place",
    );
    c.outcome = format!(
        "controlled stop, latched while the module was back; re-arm: communication fresh, tracking refused ({})",
        fmt_reason(&reason)
    );
    c.data_lost = format!(
        "{} cycles of node-3 feedback; the rest of the trajectory",
        (2.0 / p.dt()) as u64
    );
    c
}

/// The controller dies at 10 s: no SYNC, no SETPOINT. Every module's watchdog must stop its
/// motors within 50 ms of the last SETPOINT.
pub fn controller_silent() -> CaseResult {
    let mut c = CaseResult::new(
        "controller silent (no SYNC/SETPOINT from 10 s)",
        "module firmware: setpoint watchdog 50 ms → motors decelerate at the torque limit, disabled; stays so until enabled again",
    );
    let o = RigOptions::new(Scenario::Seed000);
    let Ok(mut rig) = Rig::new(&o) else {
        c.check(false, "rig");
        return c;
    };
    while rig.time() < 10.0 {
        rig.step(&mut Hooks::default());
    }
    let n = rig.sim.n();
    let last_sp = rig.time() - 0.004 + o.runtime.feedback_window;
    let speed0 = rig.sim.truth().wheel_speed;
    let trips0: Vec<u64> = (0..n)
        .map(|i| rig.sim.stats().modules[i].watchdog_trips)
        .collect();
    let mut trip_at = vec![None; n];
    let mut rest_at = None;
    let mut tt = rig.time();
    while tt < rig.time() + 1.0 {
        tt += 0.0005;
        rig.sim.advance_to(Duration::from_secs_f64(tt));
        rig.sim.drain_tx(&mut |_, _| {});
        let st = rig.sim.stats();
        for i in 0..n {
            if trip_at[i].is_none() && st.modules[i].watchdog_trips > trips0[i] {
                trip_at[i] = Some(tt);
            }
        }
        let tr = rig.sim.truth();
        if rest_at.is_none() && tr.wheel_speed[..n].iter().all(|w| w.abs() < 0.02) {
            rest_at = Some(tt);
        }
    }
    let worst = trip_at
        .iter()
        .map(|t| t.map_or(f64::INFINITY, |t| t - last_sp))
        .fold(0.0, f64::max);
    c.detection = format!("watchdog after {:.1} ms (worst module)", worst * 1e3);
    c.check(
        worst <= 0.050 + 0.001,
        format!("watchdog after {:.1} ms", worst * 1e3),
    );
    let v0 = speed0[..n].iter().fold(0.0f64, |a, w| a.max(w.abs()));
    c.outcome = match rest_at {
        Some(r) => format!(
            "all {n} modules tripped; wheels at rest {:.0} ms after the last SETPOINT (from {v0:.1} rad/s at the torque limit)",
            (r - last_sp) * 1e3
        ),
        None => "wheels still turning 1 s later".into(),
    };
    c.check(rest_at.is_some(), "wheels never stopped");
    c.data_lost = "controller output from 10 s".into();
    c
}

/// Commands of a run of `cycles` cycles with an optional receive hook.
fn commands(
    o: &RigOptions,
    cycles: u64,
    on_rx: Option<RxHook<'_>>,
) -> Result<(Vec<[f64; 2 * MAX_WHEELS]>, Rig, Track), String> {
    let mut rig = Rig::new(o)?;
    let mut hooks = Hooks {
        on_rx,
        ..Hooks::default()
    };
    let mut out = Vec::with_capacity(cycles as usize);
    let mut t = Track::default();
    for _ in 0..cycles {
        if let Some(r) = rig.step(&mut hooks) {
            t.update(r, 0.002);
            let mut c = [0.0; 2 * MAX_WHEELS];
            for i in 0..r.n.min(MAX_WHEELS) {
                c[2 * i] = r.command.wheels[i].wheel_speed;
                c[2 * i + 1] = r.command.wheels[i].steer_rate;
            }
            out.push(c);
        }
    }
    Ok((out, rig, t))
}

fn refresh_crc(data: &mut [u8], id: u16, kind: MessageKind) {
    let at = spec(kind).crc_byte();
    if at < data.len() {
        data[at] = frame_crc(id, &data[..at]);
    }
}

/// Forged and damaged frames next to the real ones: bad CRC, wrong DLC, unknown id,
/// out-of-range value, repeated counter (and, with `strict`, skipped counter). All must be
/// rejected, counted per kind, and never acted on: the commands equal those of a clean run
/// bit for bit.
pub fn bad_frames(strict: bool, quick: bool) -> CaseResult {
    let mut c = CaseResult::new(
        if strict {
            "skipped counters (strict counter policy)"
        } else {
            "bad CRC, wrong DLC, unknown id, out-of-range value, repeated counter"
        },
        if strict {
            "strict policy: a counter jump is rejected and counted; default policy (AcceptWithLoss) accepts a CRC-valid frame after a jump and counts the loss — counters detect loss, they do not authenticate"
        } else {
            "rejected by the receive path (decode / counter check), counted per kind, the cycle goes on with the last valid data"
        },
    );
    let mut o = RigOptions::new(Scenario::Seed000);
    if strict {
        o.runtime.counter_policy = CounterPolicy::RejectSkipped;
    }
    let cycles = if quick { 1500 } else { 9000 };
    let clean = match commands(&o, cycles, None) {
        Ok(x) => x.0,
        Err(e) => {
            c.check(false, e);
            return c;
        }
    };
    let mut counts = [0u64; 6];
    let mut k = 0u64;
    let unknown_id: u16 = (0x100..0x7FF)
        .find(|id| {
            CanFrame::new(*id, &[0; 8]).is_ok_and(|f| {
                matches!(
                    decode(&f),
                    Err(rollbase_driver::DecodeError::UnknownId { .. })
                )
            })
        })
        .unwrap_or(0x7FF);
    let mut hook = |f: &CanFrame, emit: &mut dyn FnMut(CanFrame)| {
        emit(*f);
        let Some((kind, _)) = classify(f.id()) else {
            return;
        };
        if kind != MessageKind::FeedbackA {
            return;
        }
        k += 1;
        if k % 3 != 0 {
            return;
        }
        let mut d = [0u8; 8];
        d[..f.len()].copy_from_slice(f.data());
        let len = f.len();
        let which = if strict { 5 } else { ((k / 3) % 5) as usize };
        let forged = match which {
            0 => {
                d[len - 1] ^= 0x01;
                CanFrame::new(f.id(), &d[..len])
            }
            1 => CanFrame::new(f.id(), &d[..len - 1]),
            2 => CanFrame::new(unknown_id, &d[..len]),
            3 => {
                // steer_angle raw 32767 > 31416 (π), CRC valid.
                d[0] = 0xFF;
                d[1] = 0x7F;
                refresh_crc(&mut d[..len], f.id(), kind);
                CanFrame::new(f.id(), &d[..len])
            }
            4 => Ok(*f),
            _ => {
                // Same frame with the counter advanced by 2, CRC valid.
                let ctr = d[6] & 0x0F;
                d[6] = (d[6] & 0xF0) | ((ctr + 2) & 0x0F);
                refresh_crc(&mut d[..len], f.id(), kind);
                CanFrame::new(f.id(), &d[..len])
            }
        };
        if let Ok(g) = forged {
            counts[which] += 1;
            emit(g);
        }
    };
    let (cmds, rig, t) = match commands(&o, cycles, Some(&mut hook)) {
        Ok(x) => x,
        Err(e) => {
            c.check(false, e);
            return c;
        }
    };
    let s = *rig.core.rx_stats();
    let same = cmds == clean;
    if strict {
        // Reject and re-synchronise: the forged frame and the genuine one after it.
        c.check(
            s.skipped >= 2 * counts[5] - 2 && s.skipped <= 2 * counts[5],
            format!("skipped {} ≠ 2 × injected {}", s.skipped, counts[5]),
        );
        c.check(
            t.max_err <= 2.0 * NOMINAL_BOUND_M,
            format!("error {:.2} mm", t.max_err * 1e3),
        );
    } else {
        c.check(
            s.bad_crc == counts[0],
            format!("bad_crc {} ≠ {}", s.bad_crc, counts[0]),
        );
        c.check(
            s.wrong_dlc == counts[1],
            format!("wrong_dlc {} ≠ {}", s.wrong_dlc, counts[1]),
        );
        c.check(
            s.unknown_id == counts[2],
            format!("unknown_id {} ≠ {}", s.unknown_id, counts[2]),
        );
        c.check(
            s.out_of_range == counts[3],
            format!("out_of_range {} ≠ {}", s.out_of_range, counts[3]),
        );
        c.check(
            s.repeated == counts[4],
            format!("repeated {} ≠ {}", s.repeated, counts[4]),
        );
    }
    if !strict {
        c.check(
            same,
            "commands differ from the clean run: a bad frame was acted on",
        );
    }
    c.check(t.fault.is_none(), format!("fault {:?}", t.fault));
    c.detection = "same cycle (on receipt)".into();
    c.outcome = format!(
        "{} cycles, commands identical to the clean run: {same}; no fault",
        cmds.len()
    );
    c.data_lost = if strict {
        format!(
            "{} forged frames rejected as skipped, and the genuine frame after each ({} in all): 1 genuine frame lost per forged one",
            counts[5], s.skipped
        )
    } else {
        format!(
            "rejected: bad CRC {}, wrong DLC {}, unknown id {}, out of range {}, repeated {} (= injected)",
            s.bad_crc, s.wrong_dlc, s.unknown_id, s.out_of_range, s.repeated
        )
    };
    c
}

/// Random bit flips on the medium (1 % of frames, both directions).
pub fn corrupted_medium(quick: bool) -> CaseResult {
    let mut c = CaseResult::new(
        "corrupted frames on the medium (1 %)",
        "CRC-8 rejects them (both directions: modules reject bad SETPOINTs and keep the last for ≤ 50 ms); the cycle uses the last valid data",
    );
    let mut o = RigOptions::new(Scenario::Seed000);
    o.bus_faults.corrupt_prob = 0.01;
    let Ok(mut rig) = Rig::new(&o) else {
        c.check(false, "rig");
        return c;
    };
    let mut t = Track::default();
    run_to_end(
        &mut rig,
        &mut t,
        max_cycles(quick, 60.0, 12.0),
        &mut Hooks::default(),
    );
    let s = *rig.core.rx_stats();
    let corrupted = rig.bus.bus.stats().faults.corrupted;
    c.check(t.fault.is_none(), format!("fault {:?}", t.fault));
    c.check(s.bad_crc > 0, "no bad CRC counted");
    c.check(
        t.max_err <= 2.0 * NOMINAL_BOUND_M,
        format!("error {:.2} mm", t.max_err * 1e3),
    );
    c.detection = "on receipt".into();
    c.outcome = format!("tracking continues, max error {:.2} mm", t.max_err * 1e3);
    c.data_lost = format!(
        "{corrupted} frames corrupted on the bus; controller rejected {} (bad CRC {}, other {})",
        s.rejected(),
        s.bad_crc,
        s.rejected() - s.bad_crc
    );
    c
}

/// Delayed module transmissions (`delay`, `jitter` in s).
pub fn delayed(delay: f64, jitter: f64, quick: bool) -> CaseResult {
    let mut c = CaseResult::new(
        &format!(
            "feedback delayed {:.1} ms{}",
            delay * 1e3,
            if jitter > 0.0 {
                format!(" + jitter ≤ {:.1} ms", jitter * 1e3)
            } else {
                String::new()
            }
        ),
        "the cycle collects feedback until 2 ms after SYNC; later frames are used in the next cycle (a one-cycle-older sample) and counted as late cycles (newest feedback older than the window); more than 3 cycles without any → stale fault",
    );
    let mut o = RigOptions::new(Scenario::Seed000);
    o.faults.delay = delay;
    o.faults.jitter = jitter;
    let Ok(mut rig) = Rig::new(&o) else {
        c.check(false, "rig");
        return c;
    };
    let mut t = Track::default();
    run_to_end(
        &mut rig,
        &mut t,
        max_cycles(quick, 60.0, 12.0),
        &mut Hooks::default(),
    );
    c.check(t.fault.is_none(), format!("fault {:?}", t.fault));
    c.check(
        t.max_err <= 2.0 * NOMINAL_BOUND_M,
        format!("error {:.2} mm", t.max_err * 1e3),
    );
    c.detection = format!("{} late cycles counted", t.late_cycles);
    c.outcome = format!(
        "tracking continues ({:?}), max error {:.2} mm",
        t.last_state.map(|s| s.name()),
        t.max_err * 1e3
    );
    c.data_lost = "none".into();
    c
}

/// A simulator fault from the schedule at `at`; `expect` says which reasons are a pass.
pub fn sim_fault(
    name: &str,
    policy: &str,
    faults: FaultSchedule,
    at: f64,
    expect: fn(&FaultReason) -> bool,
) -> CaseResult {
    let mut o = RigOptions::new(Scenario::Seed000);
    o.faults = faults;
    let (mut c, t, _) = scheduled(name, policy, &o, at, 25.0);
    let p = Platform::justin();
    match t.fault {
        Some((_, time, Some(r))) => {
            c.check(expect(&r), format!("unexpected reason {r}"));
            c.check(
                time >= at,
                format!("fault at {time} before the injection at {at}"),
            );
            c.check(t.controlled_stop(&p), "not a controlled stop");
        }
        f => c.check(false, format!("not detected ({f:?})")),
    }
    c
}

/// The leg's mechanical end stop is short of the platform file's `lambda_max`: the plant
/// stops wheel 1's leg at 0.50 m while seed 000 extends the legs to 0.56 m.
pub fn leg_end_stop() -> CaseResult {
    let mut o = RigOptions::new(Scenario::Seed000);
    let mut sp = Platform::justin();
    sp.wheels[0].lambda_max = 0.50;
    o.sim_platform = Some(sp);
    let (mut c, t, _) = scheduled(
        "leg at its end stop (node 1 blocked at 0.50 m, file says 0.56 m)",
        "a blocked leg makes the wheels fight: the odometry residual rises; residual > 0.05 m/s for 25 cycles → slip fault naming wheel 1, controlled stop",
        &o,
        0.0,
        40.0,
    );
    let p = Platform::justin();
    c.check(t.fault.is_some(), "not detected");
    if let Some((_, _, r)) = t.fault {
        c.check(
            r.and_then(|r| r.slip_wheel()) == Some(0),
            format!("expected a slip fault naming wheel 1, got {r:?}"),
        );
    }
    c.check(
        t.fault.is_none() || t.controlled_stop(&p),
        "not a controlled stop",
    );
    if let Some((_, time, _)) = t.fault {
        c.detection = format!("fault at {time:.2} s (leg reaches 0.50 m during the run)");
    }
    c
}

/// Wheel 2 slips: its encoder reports a spin 2× faster than the ground moves from 8 s
/// (FEEDBACK_A altered in flight, CRC and counter valid).
pub fn wheel_slip() -> CaseResult {
    let mut c = CaseResult::new(
        "wheel slipping (node 2 spins 2× faster than the ground, from 8 s)",
        "odometry least-squares residual > 0.05 m/s for 25 consecutive cycles → slip fault naming wheel 2, controlled stop",
    );
    let o = RigOptions::new(Scenario::Seed000);
    let Ok(mut rig) = Rig::new(&o) else {
        c.check(false, "rig");
        return c;
    };
    let now = std::cell::Cell::new(0.0f64);
    let mut hook = |f: &CanFrame, emit: &mut dyn FnMut(CanFrame)| {
        if now.get() >= 8.0 {
            if let Ok(mut m) = decode(f) {
                if let (2, Payload::FeedbackA(ref mut a)) = (m.node, &mut m.payload) {
                    a.wheel_speed *= 2.0;
                    if let Ok(g) = encode(&m) {
                        emit(g);
                        return;
                    }
                }
            }
        }
        emit(*f);
    };
    let mut t = Track::default();
    while rig.cycle() < 25 * 250 {
        now.set(rig.time());
        let mut h = Hooks {
            on_rx: Some(&mut hook),
            ..Hooks::default()
        };
        if let Some(r) = rig.step(&mut h) {
            t.update(r, 0.002);
        }
        if rig.core.done() {
            break;
        }
    }
    let p = Platform::justin();
    match t.fault {
        Some((_, time, Some(r @ FaultReason::Slip { .. }))) if r.slip_wheel() == Some(1) => {
            c.detection = ms(((time - 8.0) / p.dt()).round() as u64, &p);
            c.outcome = format!("controlled stop, latched: {r}");
        }
        f => c.check(
            false,
            format!("expected a slip fault naming wheel 2, got {f:?}"),
        ),
    }
    c.check(t.controlled_stop(&p), "not a controlled stop");
    c.data_lost = "rest of trajectory".into();
    c
}

/// The controller's interface goes down in `[from, to)` (send and receive fail), comes back,
/// and the operator re-arms at `rearm`. Returns the row and whether the trajectory completed.
pub fn iface_down(from: f64, to: f64, rearm: f64, quick: bool) -> CaseResult {
    let _ = quick;
    let mut c = CaseResult::new(
        &format!("controller interface down {from:.1}–{to:.1} s, back, re-armed at {rearm:.1} s"),
        "a send/receive error → bus-error fault (controlled stop commanded; if the frames cannot leave, the modules' 50 ms watchdog stops the motors); latched; re-arm on request (CycleCore::arm) once the bus is back",
    );
    let o = RigOptions::new(Scenario::Seed000);
    let Ok(mut rig) = Rig::new(&o) else {
        c.check(false, "rig");
        return c;
    };
    let p = Platform::justin();
    let mut t = Track::default();
    let mut after = Track::default();
    let mut armed = false;
    let mut watchdog_stop = true;
    while rig.cycle() < 90 * 250 {
        let now = rig.time();
        if !armed && now >= rearm {
            armed = true;
            c.check(rig.core.arm(), "arm refused");
        }
        let mut h = Hooks {
            iface_down: now >= from && now < to,
            ..Hooks::default()
        };
        if let Some(r) = rig.step(&mut h) {
            if armed {
                after.update(r, 0.002);
            } else {
                t.update(r, 0.002);
            }
        }
        if now >= to - 0.004 && now < to && !armed {
            let tr = rig.sim.truth();
            watchdog_stop = tr.wheel_speed[..tr.n].iter().all(|w| w.abs() < 0.02);
        }
        if armed && rig.core.done() {
            break;
        }
    }
    match t.fault {
        Some((_, time, Some(FaultReason::BusError))) => {
            c.detection = ms(((time - from) / p.dt()).round() as u64, &p);
        }
        f => c.check(false, format!("expected a bus error, got {f:?}")),
    }
    c.check(watchdog_stop, "wheels still turning when the bus came back");
    let completed = after.last_state == Some(SupervisorState::Stopped);
    let refused = matches!(
        after.fault,
        Some((_, _, Some(FaultReason::StartMismatch { .. })))
    );
    c.check(
        completed || (refused && after.tracking_from.is_none()),
        format!("after re-arm: {:?} {:?}", after.last_state, after.fault),
    );
    c.outcome = format!(
        "fault latched, wheels at rest while down; after re-arm: {}",
        if completed {
            format!(
                "aligned and completed the trajectory (max error {:.2} mm)",
                after.max_err * 1e3
            )
        } else {
            format!(
                "tracking refused: {}",
                fmt_reason(&after.fault.and_then(|f| f.2))
            )
        }
    );
    c.data_lost = format!(
        "{} frames dropped at the controller while down",
        rig.st.lost_iface_down
    );
    c
}

/// The simulator's side of the bus is gone in `[at, until)` (bus-off at the modules).
pub fn modules_bus_off() -> CaseResult {
    let mut f = FaultSchedule::default();
    f.bus_off.push(rollbase_vcan_sim::faults::BusOff {
        at: 10.0,
        until: 10.5,
    });
    sim_fault(
        "modules bus-off 10.0–10.5 s",
        "all modules stale > 3 cycles → stale-feedback fault (first wheel named), controlled stop; the modules' watchdog stops them too; latched until re-armed",
        f,
        10.0,
        |r| matches!(r, FaultReason::StaleFeedback { .. }),
    )
}

/// Bad input from files: every error names the field or value; nothing is started.
pub fn bad_input() -> CaseResult {
    use rollbase_control::reference::trajectory::QuinticSpline;
    let mut c = CaseResult::new(
        "bad input: malformed platform TOML, NaN waypoint, unreachable leg, infeasible limits",
        "validated before anything starts; the error names the field and value; the CLI exits non-zero (cli-tests: bad_platform_file_names_the_field_and_fails, unknown_scenario_and_bus_are_clear_errors)",
    );
    let p = Platform::justin();
    let mut msgs = Vec::new();
    let bad_platform =
        p.to_toml_string()
            .replacen("wheel_radius = 0.085", "wheel_radius = -1.0", 1);
    match Platform::from_toml_str(&bad_platform) {
        Err(e) => {
            c.check(
                e.to_string().contains("wheel_radius"),
                format!("platform: {e}"),
            );
            msgs.push(e.to_string());
        }
        Ok(_) => c.check(false, "negative wheel radius accepted"),
    }
    match Platform::from_toml_str("wheel_radius = \"big\"") {
        Err(e) => msgs.push(e.to_string()),
        Ok(_) => c.check(false, "malformed platform accepted"),
    }
    let wp = |x: &str, leg: &str| {
        format!(
            "[[waypoints]]\nt = 0.0\nx = 0.0\ny = 0.0\ntheta = 0.0\nlegs = [0.45, 0.45, 0.45, 0.45]\n\n[[waypoints]]\nt = 5.0\nx = {x}\ny = 0.0\ntheta = 0.0\nlegs = [{leg}, 0.45, 0.45, 0.45]\n"
        )
    };
    match QuinticSpline::from_toml_str(&p, &wp("nan", "0.45")) {
        Err(e) => {
            c.check(
                e.to_string().contains("waypoints[1].x"),
                format!("NaN: {e}"),
            );
            msgs.push(e.to_string());
        }
        Ok(_) => c.check(false, "NaN waypoint accepted"),
    }
    match QuinticSpline::from_toml_str(&p, &wp("1.0", "0.9")) {
        Err(e) => {
            c.check(e.to_string().contains("0.9"), format!("leg: {e}"));
            msgs.push(e.to_string());
        }
        Ok(_) => c.check(false, "unreachable leg accepted"),
    }
    // Limits below what seed 000 asks at its given timing are no longer a refusal: the time
    // scaling (issue 18) stretches the run into them. A wheel speed limit of 1 rad/s runs,
    // slower.
    let mut slow = Platform::justin();
    slow.limits.wheel_speed = 1.0;
    let traj = scenario::trajectory(Scenario::Seed000, &slow);
    match traj.map_err(|e| e.to_string()).and_then(|t| {
        CycleCore::new(slow.clone(), t, RuntimeConfig::default()).map_err(|e| e.to_string())
    }) {
        Ok(core) => {
            let stretched = core.trajectory_timing().map(|t| t.min_scale);
            c.check(
                stretched.is_some_and(|s| s < 1.0),
                format!("wheel_speed 1 rad/s runs, but not slowed: {stretched:?}"),
            );
        }
        Err(e) => c.check(false, format!("a stretchable trajectory refused: {e}")),
    }
    // Limits no timing can meet within a run's 10 h: refused before start, naming the limit.
    let mut hopeless = Platform::justin();
    hopeless.limits.wheel_speed = 1e-4;
    let traj = scenario::trajectory(Scenario::Seed000, &hopeless);
    match traj.map_err(|e| e.to_string()).and_then(|t| {
        CycleCore::new(hopeless.clone(), t, RuntimeConfig::default()).map_err(|e| e.to_string())
    }) {
        Err(e) => {
            c.check(e.contains("wheel_speed"), format!("infeasible: {e}"));
            msgs.push(e);
        }
        Ok(_) => c.check(false, "infeasible limits accepted: the run would start"),
    }
    c.detection = "before start".into();
    c.outcome = format!("refused: {}", msgs.join(" | "));
    c.data_lost = "nothing started".into();
    c
}

/// Peak and current resident memory of this process (kB), from `/proc/self/status`
/// (`VmHWM`, `VmRSS`); `None` where that file does not exist.
pub fn memory_kb() -> Option<(u64, u64)> {
    let text = std::fs::read_to_string("/proc/self/status").ok()?;
    let field = |name: &str| {
        text.lines()
            .find(|l| l.starts_with(name))
            .and_then(|l| l.split_whitespace().nth(1))
            .and_then(|v| v.parse::<u64>().ok())
    };
    Some((field("VmHWM:")?, field("VmRSS:")?))
}

/// A looping waypoint trajectory of `segments` 10-s segments: the platform visits the
/// corners of a 1 m square while turning 1 rad per segment (never at rest in between, so the
/// DFL never meets singularity A) and alternately extends and retracts its legs.
pub fn soak_waypoints(segments: usize) -> Vec<rollbase_control::reference::trajectory::Waypoint> {
    let corners = [(0.0, 0.0), (1.0, 0.0), (1.0, 1.0), (0.0, 1.0)];
    (0..=segments)
        .map(|k| {
            let mut z = rollbase_control::ZVec::zeros();
            let (x, y) = corners[k % 4];
            z[0] = x;
            z[1] = y;
            z[2] = k as f64;
            for i in 0..4 {
                z[3 + i] = if k % 2 == 0 { 0.45 } else { 0.50 };
            }
            rollbase_control::reference::trajectory::Waypoint {
                t: 10.0 * k as f64,
                z,
            }
        })
        .collect()
}

/// What the soak measured.
#[derive(Clone, Debug, Default)]
pub struct SoakReport {
    /// Cycles run.
    pub cycles: u64,
    /// The core's own cycle counter at the end.
    pub core_cycles: u64,
    /// Records whose cycle number differed from the loop's count.
    pub bookkeeping_errors: u64,
    /// Simulator time minus cycles × period at the end (s).
    pub time_drift_s: f64,
    /// VmRSS samples (kB) along the run.
    pub rss_kb: Vec<u64>,
    /// VmHWM at the end (kB).
    pub peak_kb: u64,
    /// Wall time (s).
    pub wall_s: f64,
    /// Largest position error while tracking (m).
    pub max_err: f64,
    /// Final supervisor state and reason.
    pub final_state: String,
    /// Frames the receive path counted as lost.
    pub lost: u64,
    /// The platform faulted (a soak on healthy drives must not).
    pub faulted: bool,
}

/// Runs `cycles` lockstep cycles of the looping trajectory with random frame loss `loss`, on
/// the native profile or (`cia402`) the CiA 402 one.
pub fn soak(cycles: u64, loss: f64, cia402: bool) -> Result<SoakReport, String> {
    let wall = std::time::Instant::now();
    let mut o = RigOptions::new(Scenario::Seed000);
    if cia402 {
        o = o.cia402();
    }
    o.bus_faults.drop_prob = loss;
    let seconds = cycles as f64 / 250.0;
    o.waypoints = Some(soak_waypoints((seconds / 10.0).ceil() as usize + 2));
    let mut rig = Rig::new(&o)?;
    let mut t = Track::default();
    let mut rep = SoakReport::default();
    let sample_every = (cycles / 20).max(1);
    for k in 0..cycles {
        let Some(r) = rig.step(&mut Hooks::default()) else {
            continue;
        };
        if r.cycle != k {
            rep.bookkeeping_errors += 1;
        }
        t.update(r, 0.002);
        if k % sample_every == 0 {
            if let Some((_, rss)) = memory_kb() {
                rep.rss_kb.push(rss);
            }
        }
    }
    rep.cycles = rig.cycle();
    rep.core_cycles = rig.core.cycles();
    rig.sim
        .advance_to(Duration::from_secs_f64(rep.cycles as f64 / 250.0));
    rep.time_drift_s = rig.sim.now().as_secs_f64() - rep.cycles as f64 / 250.0;
    rep.peak_kb = memory_kb().map_or(0, |m| m.0);
    rep.wall_s = wall.elapsed().as_secs_f64();
    rep.max_err = t.max_err;
    rep.final_state = format!(
        "{} {}",
        t.last_state.map_or("none", |s| s.name()),
        t.fault.map_or(String::new(), |f| fmt_reason(&f.2))
    );
    rep.lost = rig.core.rx_stats().lost;
    rep.faulted = t.fault.is_some();
    Ok(rep)
}

/// A case of the following-error supervision (issue 19): rolling drives that do not respond
/// or respond at a fraction of their setpoint, on the native or the CiA 402 profile. `o`
/// carries the plant and fault schedule; `at` is the injection time (`None`: the plant is
/// like that from the start, and detection is timed from the start of tracking); `expect`
/// says which reasons pass. Checks a controlled stop, reports the time to fault.
pub fn following_case(
    name: &str,
    policy: &str,
    o: &RigOptions,
    at: Option<f64>,
    expect: fn(&FaultReason) -> bool,
) -> CaseResult {
    let mut c = CaseResult::new(name, policy);
    let mut rig = match Rig::new(o) {
        Ok(r) => r,
        Err(e) => {
            c.check(false, e);
            return c;
        }
    };
    let mut t = Track::default();
    run_to_end(&mut rig, &mut t, 40 * 250, &mut Hooks::default());
    let p = Platform::justin();
    let from = match at {
        Some(a) => a,
        None => t.tracking_from.map_or(0.0, |k| k as f64 * p.dt()),
    };
    match t.fault {
        Some((_, time, Some(r))) => {
            c.check(expect(&r), format!("unexpected reason {r}"));
            c.check(
                time >= from,
                format!("fault at {time} s before the injection at {from} s"),
            );
            c.check(t.controlled_stop(&p), "not a controlled stop");
            let d = ((time - from) / p.dt()).round().max(0.0) as u64;
            c.detection = format!(
                "{} after {}",
                ms(d, &p),
                if at.is_some() {
                    "the injection"
                } else {
                    "tracking started"
                }
            );
            c.outcome = format!("controlled stop, latched: {r}");
        }
        f => c.check(false, format!("not detected ({f:?})")),
    }
    let pk = rig.core.supervisor().follow_peak();
    c.data_lost = format!(
        "rest of trajectory; max position error before the fault {:.2} mm; peak following error {:.2} × window",
        t.max_err * 1e3,
        pk.ratio
    );
    c
}

/// The following error's margin on healthy runs: seed 000 and seed 001 on both profiles,
/// seed 000 with 3 ms feedback delay and 1 % frame loss: none may fault, and the largest
/// following error stays below its window (ratio < 1) with no cycle outside.
pub fn following_margin() -> CaseResult {
    let mut c = CaseResult::new(
        "healthy drives: following-error margin (seed 000, seed 001, both profiles; 3 ms delay; 1 % loss)",
        "the measured wheel speed and steering rate stay within the range of the last 0.1 s of commands widened by 0.5 / 0.3 rad/s + 25 % (CiA 402 0x6065 window); outside for more than 0.2 s (0x6066 time out) → following-error fault",
    );
    let mut worst: f64 = 0.0;
    let mut parts = Vec::new();
    for cia in [false, true] {
        for (label, sc, delay, loss) in [
            ("seed 000", Scenario::Seed000, 0.0, 0.0),
            ("seed 001", Scenario::Seed001, 0.0, 0.0),
            ("seed 000 + 3 ms delay", Scenario::Seed000, 0.003, 0.0),
            ("seed 000 + 1 % loss", Scenario::Seed000, 0.0, 0.01),
        ] {
            let mut o = RigOptions::new(sc);
            if cia {
                o = o.cia402();
            }
            o.faults.delay = delay;
            o.bus_faults.drop_prob = loss;
            let Ok(mut rig) = Rig::new(&o) else {
                c.check(false, format!("{label}: rig"));
                continue;
            };
            let mut t = Track::default();
            run_to_end(&mut rig, &mut t, 60 * 250, &mut Hooks::default());
            let pk = rig.core.supervisor().follow_peak();
            let prof = if cia { "CiA 402" } else { "native" };
            c.check(
                t.last_state == Some(SupervisorState::Stopped) && t.fault.is_none(),
                format!("{prof} {label}: {:?} {:?}", t.last_state, t.fault),
            );
            c.check(
                pk.ratio < 1.0 && pk.outside_s == 0.0,
                format!("{prof} {label}: peak {pk:?}"),
            );
            worst = worst.max(pk.ratio);
            parts.push(format!("{prof} {label} {:.2}", pk.ratio));
        }
    }
    c.detection = "—".into();
    c.outcome = format!(
        "no fault, every run completed; largest following error / window: {} (worst {worst:.2}: a margin of {:.1}×)",
        parts.join(", "),
        1.0 / worst.max(1e-9)
    );
    c.data_lost = "none".into();
    c
}

/// The arrival check's safety net: the following-error check switched off (infinite time
/// out), every rolling drive dead from 8 s: the platform stops short, the trajectory runs out
/// and the run must end in Fault (did not arrive), not in Stopped.
pub fn not_arrived() -> CaseResult {
    let mut c = CaseResult::new(
        "run that does not arrive (following-error check off, all rolling drives dead from 8 s)",
        "at the end of a trajectory run, the estimated pose and legs are compared with the goal: more than 0.05 m, 5° or 20 mm away → fault 'did not arrive' (the run fails, exit 1)",
    );
    let mut o = RigOptions::new(Scenario::Seed000);
    o.runtime.supervisor.follow_timeout = f64::INFINITY;
    for node in 1..=4 {
        o.faults
            .drive_gain
            .push(rollbase_vcan_sim::faults::DriveGain {
                node,
                at: 8.0,
                gain: 0.0,
            });
    }
    let Ok(mut rig) = Rig::new(&o) else {
        c.check(false, "rig");
        return c;
    };
    let mut t = Track::default();
    run_to_end(&mut rig, &mut t, 60 * 250, &mut Hooks::default());
    match t.fault {
        Some((_, time, Some(r @ FaultReason::NotArrived { distance, .. }))) => {
            c.check(distance > 0.05, format!("distance {distance}"));
            c.detection = format!("at the end of the run ({time:.2} s)");
            c.outcome = format!("{r}");
        }
        f => c.check(false, format!("expected 'did not arrive', got {f:?}")),
    }
    c.check(
        t.last_state == Some(SupervisorState::Fault),
        format!("final state {:?}", t.last_state),
    );
    c.data_lost = "the rest of the trajectory (the platform stood still from 8 s)".into();
    c
}

/// An encoded SETPOINT for the stall case (1 rad/s when enabling, 0 when disabling).
fn stall_setpoint(
    node: u8,
    k: u16,
    enable: bool,
) -> Result<CanFrame, rollbase_driver::codec::EncodeError> {
    use rollbase_driver::codec::{Message, Setpoint, SetpointFlags};
    encode(&Message {
        node,
        counter: (k % 16) as u8,
        payload: Payload::Setpoint(Setpoint {
            wheel_speed: if enable { 1.0 } else { 0.0 },
            steer_rate: 0.0,
            flags: SetpointFlags {
                enable,
                brake: false,
                fault_reset: false,
            },
        }),
    })
}

/// The simulator bus wrapper that holds the simulator thread up once (a page fault, a
/// preemption), in the first receive call after `at`, for `stall`.
struct StallingBus<B: rollbase_driver::bus::CanBus> {
    inner: B,
    at: std::time::Instant,
    stall: Duration,
    done: bool,
}

impl<B: rollbase_driver::bus::CanBus> StallingBus<B> {
    fn maybe_stall(&mut self) {
        if !self.done && std::time::Instant::now() >= self.at {
            self.done = true;
            std::thread::sleep(self.stall);
        }
    }
}

impl<B: rollbase_driver::bus::CanBus> rollbase_driver::bus::CanBus for StallingBus<B> {
    fn send(&mut self, frame: &CanFrame) -> Result<(), rollbase_driver::bus::BusError> {
        self.inner.send(frame)
    }
    fn try_recv(
        &mut self,
    ) -> Result<Option<rollbase_driver::frame::TimestampedFrame>, rollbase_driver::bus::BusError>
    {
        self.maybe_stall();
        self.inner.try_recv()
    }
    fn recv_until(
        &mut self,
        deadline: std::time::Instant,
    ) -> Result<Option<rollbase_driver::frame::TimestampedFrame>, rollbase_driver::bus::BusError>
    {
        self.maybe_stall();
        self.inner.recv_until(deadline)
    }
    fn name(&self) -> &str {
        self.inner.name()
    }
}

/// Wall-clock case (not lockstep: a thread stall exists only in real time): the simulator
/// thread is held up for `stall` while a 250 Hz sender keeps sending SYNC + 4 SETPOINTs every
/// 4 ms on a wall-clock virtual bus. Every SETPOINT must be applied at its bus timestamp: no
/// module may trip its 50 ms watchdog. Attempts whose sender itself stalled > 30 ms are
/// repeated (3 at most).
pub fn simulator_stall(stall: Duration) -> CaseResult {
    use rollbase_driver::bus::{BusClock, VirtualBus, VirtualBusConfig};
    use rollbase_driver::codec::{Message, Sync};
    use std::sync::atomic::{AtomicBool, Ordering};
    use std::sync::Arc;
    use std::time::Instant;
    let mut c = CaseResult::new(
        &format!(
            "simulator thread stalled {:.0} ms (wall clock, real time; SETPOINTs every 4 ms)",
            stall.as_secs_f64() * 1e3
        ),
        "the simulator reads everything queued and applies each frame at its bus timestamp, plant and timers advanced in time order, before advancing to the present: the modules never pause when the host does, their 50 ms watchdog sees the SETPOINTs when they arrived",
    );
    let cycles = 150u16;
    for _ in 0..3 {
        let vbus = VirtualBus::new(VirtualBusConfig {
            clock: BusClock::Wall,
            ..VirtualBusConfig::default()
        });
        let mut ctrl = vbus.node("controller");
        let t0 = Instant::now();
        let bus = StallingBus {
            inner: vbus.node("simulator"),
            at: t0 + Duration::from_millis(200),
            stall,
            done: false,
        };
        let Ok(sim) = Simulator::with_config(&Platform::justin(), Default::default()) else {
            c.check(false, "simulator");
            return c;
        };
        let stop = Arc::new(AtomicBool::new(false));
        let handle = rollbase_vcan_sim::spawn_realtime(sim, Box::new(bus), stop.clone(), None);
        let mut worst_gap = Duration::ZERO;
        let mut last: Option<Instant> = None;
        for k in 0..cycles {
            let deadline = t0 + Duration::from_millis(4) * u32::from(k);
            if let Some(d) = deadline.checked_duration_since(Instant::now()) {
                std::thread::sleep(d);
            }
            let now = Instant::now();
            if let Some(l) = last {
                worst_gap = worst_gap.max(now - l);
            }
            last = Some(now);
            let sync = encode(&Message {
                node: 0,
                counter: (k % 16) as u8,
                payload: Payload::Sync(Sync { cycle: k }),
            });
            if let Ok(f) = sync {
                let _ = ctrl.send(&f);
            }
            for n in 1..=4u8 {
                if let Ok(f) = stall_setpoint(n, k, true) {
                    let _ = ctrl.send(&f);
                }
            }
            while let Ok(Some(_)) = ctrl.try_recv() {}
        }
        // A last SETPOINT disables the modules (no watchdog after it); then the simulator has
        // all the time it needs to read everything.
        for n in 1..=4u8 {
            if let Ok(f) = stall_setpoint(n, cycles, false) {
                let _ = ctrl.send(&f);
            }
        }
        std::thread::sleep(Duration::from_millis(150));
        stop.store(true, Ordering::Relaxed);
        let Ok((sim, result)) = handle.join() else {
            c.check(false, "simulator thread panicked");
            return c;
        };
        if worst_gap > Duration::from_millis(30) {
            continue;
        }
        let Ok(summary) = result else {
            c.check(false, format!("simulator run: {result:?}"));
            return c;
        };
        let st = sim.stats();
        let trips: u64 = st.modules[..4].iter().map(|m| m.watchdog_trips).sum();
        let accepted: Vec<u64> = st.modules[..4]
            .iter()
            .map(|m| m.setpoints_accepted)
            .collect();
        c.check(trips == 0, format!("{trips} watchdog trips"));
        c.check(
            accepted.iter().all(|&a| a == u64::from(cycles) + 1),
            format!("SETPOINTs accepted {accepted:?} of {}", cycles + 1),
        );
        c.check(
            summary.max_receive_lag >= stall.mul_f64(0.5),
            format!("the stall did not show: lag {:?}", summary.max_receive_lag),
        );
        c.detection = "— (nothing to detect: no false trip)".into();
        c.outcome = format!(
            "{trips} watchdog trips; SETPOINTs accepted per module {accepted:?} of {}; the simulator read frames up to {:.1} ms late (max receive lag) and applied each at its arrival; sender's largest gap {:.1} ms. Before the fix (c4a8cb9) the modules tripped their watchdog: the first frame read after the stall was stamped with the wake-up time (vcan-sim/tests/stall.rs)",
            cycles + 1,
            summary.max_receive_lag.as_secs_f64() * 1e3,
            worst_gap.as_secs_f64() * 1e3
        );
        c.data_lost = "none".into();
        return c;
    }
    c.check(
        false,
        "the sender itself stalled > 30 ms in 3 attempts: machine too loaded to measure",
    );
    c
}
