//! Summary figures of a run, accumulated from its records.

use crate::runtime::record::CycleRecord;
use crate::supervisor::SupervisorState;
use crate::types::MAX_WHEELS;

/// Summary figures of a run, accumulated from its records (the `--json` output of the demo).
#[derive(Clone, Debug, Default)]
pub struct RunSummary {
    /// Scenario name.
    pub scenario: String,
    /// Cycles run.
    pub cycles: u64,
    /// Deadline misses (real time) — 0 in lockstep.
    pub deadline_misses: u64,
    /// Largest position error |(x*, y*) − (x, y)| while tracking and after (m).
    pub max_position_error_m: f64,
    /// Largest heading error (rad).
    pub max_heading_error_rad: f64,
    /// Largest leg error (m).
    pub max_leg_error_m: f64,
    /// Position error at the end of the run (m).
    pub final_position_error_m: f64,
    /// Largest commanded steering rate (rad/s).
    pub max_steer_rate_rad_s: f64,
    /// Largest commanded wheel speed (rad/s).
    pub max_wheel_speed_rad_s: f64,
    /// Smallest ICR–wheel distance seen while tracking (m).
    pub min_icr_wheel_distance_m: f64,
    /// Cycle periods, for percentiles (fixed size: a run of any length uses the same memory).
    pub periods: TimeHistogram,
    /// Compute times, for percentiles.
    pub compute: TimeHistogram,
    /// Frames rejected by the receive path.
    pub rejected_frames: u64,
    /// Final supervisor state.
    pub final_state: String,
    /// Fault reason, if the run ended in Fault.
    pub fault_reason: Option<String>,
    /// Whether errors were measured against ground truth (simulation) or the estimate.
    pub against_truth: bool,
    /// Largest commanded wheel acceleration, from the commands sent cycle to cycle (rad/s²).
    pub max_wheel_accel_rad_s2: f64,
    /// Largest commanded steering acceleration, cycle to cycle (rad/s²).
    pub max_steer_accel_rad_s2: f64,
    /// Command timeouts (live commands).
    pub command_timeouts: u64,
    /// Commands rejected by the command port.
    pub rejected_commands: u64,
    /// Valid commands ignored because the platform was not following commands.
    pub ignored_commands: u64,
    /// Motion commands dropped because the command queue was full (real time).
    pub dropped_commands: u64,
    /// Largest angle between the reference's and the executed direction of travel (base
    /// frame) while both moved faster than `DIRECTION_MIN_SPEED` (0.05 m/s) and the platform tracked
    /// (rad).
    pub max_direction_error_rad: f64,
    /// Longest time from a command timeout or stop request to the commanded wheels at rest
    /// (s); `None` when the run had none.
    pub stop_time_s: Option<f64>,
    /// The trajectory's time scaling ([`crate::reference::timescale`]): nominal and executed durations,
    /// the slowest scale and what limits it there (`None`: live commands or an unscaled
    /// trajectory). Set by the caller from [`super::CycleCore::trajectory_timing`].
    pub timing: Option<crate::reference::status::Timing>,
    /// The pose estimate (odometry) of the last cycle: where the platform ended up, as the
    /// driver knows it (`None` before the first cycle).
    pub final_pose: Option<crate::types::Pose>,
    /// Per bus, the CAN controller's error state changes seen (warning, error passive,
    /// bus-off, restarts) and its last state.
    pub can: [crate::service::ports::CanBusDiagnostics; crate::model::platform::MAX_BUSES],
    prev: Option<PrevCycle>,
    stop_started: Option<f64>,
}

/// Speed (m/s) above which the direction of travel is compared ([`RunSummary`]).
pub const DIRECTION_MIN_SPEED: f64 = 0.05;

#[derive(Clone, Copy, Debug)]
struct PrevCycle {
    t: f64,
    command: crate::types::Command,
    truth: Option<crate::types::Pose>,
    halted: bool,
}

/// Commanded wheel speed (rad/s) at or below which a stop has ended ([`RunSummary`]).
pub const STOP_REST_SPEED: f64 = 0.02;

/// A histogram of durations for percentiles: fixed size (about 230 kB, allocated once, never
/// resized), 3 significant digits (a reported percentile is within 0.1 % of the recorded
/// value), from 1 ns to 100 s (longer durations count as 100 s). Recording allocates nothing.
/// An `hdrhistogram` (HdrHistogram, Gil Tene's design) underneath.
#[derive(Clone, Debug)]
pub struct TimeHistogram {
    h: hdrhistogram::Histogram<u64>,
}

impl TimeHistogram {
    /// Longest duration held (ns).
    pub const MAX_NS: u64 = 100_000_000_000;

    /// An empty histogram.
    pub fn new() -> Self {
        // The bounds are constants within hdrhistogram's domain: this cannot fail.
        let h = hdrhistogram::Histogram::new_with_bounds(1, Self::MAX_NS, 3)
            .unwrap_or_else(|_| unreachable!("valid constant bounds"));
        Self { h }
    }

    /// Records one duration (µs); a value that is not finite or negative is not recorded.
    pub fn record_us(&mut self, us: f64) {
        if us.is_finite() && us >= 0.0 {
            self.h.saturating_record((us * 1e3).round().max(1.0) as u64);
        }
    }

    /// Number of durations recorded.
    pub fn len(&self) -> u64 {
        self.h.len()
    }

    /// True when nothing was recorded.
    pub fn is_empty(&self) -> bool {
        self.h.is_empty()
    }

    /// The p-th percentile (0..=100) in µs, as the nearest rank: the smallest recorded value
    /// (to 3 significant digits) that at least p % of the values do not exceed; NaN when
    /// empty.
    pub fn percentile_us(&self, p: f64) -> f64 {
        if self.h.is_empty() {
            return f64::NAN;
        }
        let v = self.h.value_at_quantile((p / 100.0).clamp(0.0, 1.0));
        // The middle of the value's bucket: within half a unit of the 3rd digit either way.
        self.h.median_equivalent(v) as f64 * 1e-3
    }
}

impl Default for TimeHistogram {
    fn default() -> Self {
        Self::new()
    }
}

/// p-th percentile (0..=100) of `xs` by nearest rank; NaN when empty.
pub fn percentile(xs: &[f64], p: f64) -> f64 {
    let mut v: Vec<f64> = xs.iter().copied().filter(|x| x.is_finite()).collect();
    if v.is_empty() {
        return f64::NAN;
    }
    v.sort_by(|a, b| a.total_cmp(b));
    let rank = ((p / 100.0) * v.len() as f64).ceil().max(1.0) as usize;
    v[rank.min(v.len()) - 1]
}

impl RunSummary {
    /// An empty summary.
    pub fn new(scenario: &str) -> Self {
        Self {
            scenario: scenario.into(),
            min_icr_wheel_distance_m: f64::INFINITY,
            ..Default::default()
        }
    }

    /// Adds one cycle.
    pub fn update(&mut self, r: &CycleRecord) {
        self.cycles = r.cycle + 1;
        let n = r.n.min(MAX_WHEELS);
        self.command_timeouts = r.commands.timeouts;
        self.rejected_commands = r.commands.rejected;
        self.ignored_commands = r.commands.ignored;
        self.dropped_commands = r.commands.dropped;
        self.can = r.base.diagnostics.can;
        let halted = matches!(
            r.shaping.limiting,
            crate::service::ports::Limiting::Timeout | crate::service::ports::Limiting::Stop
        );
        let at_rest = r.command.wheels[..n]
            .iter()
            .all(|w| w.wheel_speed.abs() <= STOP_REST_SPEED);
        if let Some(p) = self.prev {
            let dt = r.t - p.t;
            if dt > 0.0 {
                for i in 0..n {
                    let dw =
                        (r.command.wheels[i].wheel_speed - p.command.wheels[i].wheel_speed) / dt;
                    let ds = (r.command.wheels[i].steer_rate - p.command.wheels[i].steer_rate) / dt;
                    if dw.is_finite() {
                        self.max_wheel_accel_rad_s2 = self.max_wheel_accel_rad_s2.max(dw.abs());
                    }
                    if ds.is_finite() {
                        self.max_steer_accel_rad_s2 = self.max_steer_accel_rad_s2.max(ds.abs());
                    }
                }
                if r.state == SupervisorState::Tracking && r.mode == "track" {
                    self.direction_error(r, p.truth, dt);
                }
            }
            let stopping_now = (halted && !p.halted)
                || (r.state == SupervisorState::Stopping && self.stop_started.is_none());
            if stopping_now && self.stop_started.is_none() {
                self.stop_started = Some(p.t);
            }
        }
        if let Some(t0) = self.stop_started {
            if at_rest {
                let d = r.t - t0;
                self.stop_time_s = Some(self.stop_time_s.map_or(d, |x: f64| x.max(d)));
                self.stop_started = None;
            }
        }
        self.prev = Some(PrevCycle {
            t: r.t,
            command: r.command,
            truth: r.truth.map(|(p, _)| p),
            halted,
        });
        self.periods.record_us(r.timing.period_us);
        if r.timing.compute_us > 0.0 {
            self.compute.record_us(r.timing.compute_us);
        }
        if r.timing.deadline_miss {
            self.deadline_misses += 1;
        }
        self.rejected_frames += r.timing.rejected as u64;
        for w in &r.command.wheels[..n] {
            self.max_steer_rate_rad_s = self.max_steer_rate_rad_s.max(w.steer_rate.abs());
            self.max_wheel_speed_rad_s = self.max_wheel_speed_rad_s.max(w.wheel_speed.abs());
        }
        self.final_state = r.state.name().into();
        self.fault_reason = r.reason.map(|x| x.to_string());
        self.final_pose = Some(r.pose);
        let tracking = matches!(
            r.state,
            SupervisorState::Tracking | SupervisorState::Stopping | SupervisorState::Stopped
        );
        // A halt (command timeout, stop) is a controlled stop, not tracking: the platform
        // leaves the reference by its drives' lag and the reference then restarts from it.
        if !tracking || r.mode == "halt" || halted {
            return;
        }
        if r.avoidance.min_distance.is_finite() {
            self.min_icr_wheel_distance_m =
                self.min_icr_wheel_distance_m.min(r.avoidance.min_distance);
        }
        let (pose, legs) = match r.truth {
            Some((p, l)) => {
                self.against_truth = true;
                (p, l)
            }
            None => {
                let mut l = [0.0; MAX_WHEELS];
                for (i, x) in l.iter_mut().enumerate().take(n) {
                    *x = r.measurement.wheels[i].leg;
                }
                (r.pose, l)
            }
        };
        let z = &r.reference.z;
        let ep = ((z[0] - pose.x).powi(2) + (z[1] - pose.y).powi(2)).sqrt();
        let eh = crate::angle::diff(z[2], pose.theta).abs();
        self.max_position_error_m = self.max_position_error_m.max(ep);
        self.max_heading_error_rad = self.max_heading_error_rad.max(eh);
        for (i, l) in legs.iter().enumerate().take(n) {
            self.max_leg_error_m = self.max_leg_error_m.max((z[3 + i] - l).abs());
        }
        self.final_position_error_m = ep;
    }

    /// Direction of travel: the reference's body velocity against the executed one (the
    /// simulator's truth, differentiated over the cycle, or the odometry's twist).
    fn direction_error(
        &mut self,
        r: &CycleRecord,
        prev_truth: Option<crate::types::Pose>,
        dt: f64,
    ) {
        let (s, c) = r.reference.z[2].sin_cos();
        let (vx, vy) = (r.reference.dz[0], r.reference.dz[1]);
        let rb = [c * vx + s * vy, -s * vx + c * vy];
        let eb = match (r.truth, prev_truth) {
            (Some((p, _)), Some(q)) => {
                let (wx, wy) = ((p.x - q.x) / dt, (p.y - q.y) / dt);
                let (s, c) = (0.5 * (p.theta + q.theta)).sin_cos();
                [c * wx + s * wy, -s * wx + c * wy]
            }
            _ => [r.twist_body.vx, r.twist_body.vy],
        };
        let speed = eb[0].hypot(eb[1]);
        if speed > DIRECTION_MIN_SPEED && rb[0].hypot(rb[1]) > DIRECTION_MIN_SPEED {
            let e = (rb[0] * eb[1] - rb[1] * eb[0]).atan2(rb[0] * eb[0] + rb[1] * eb[1]);
            if e.is_finite() {
                self.max_direction_error_rad = self.max_direction_error_rad.max(e.abs());
            }
        }
    }

    /// The one-object JSON of `rollbase demo --json`.
    pub fn to_json(&self) -> serde_json::Value {
        let f = |x: f64| {
            if x.is_finite() {
                serde_json::json!(x)
            } else {
                serde_json::Value::Null
            }
        };
        serde_json::json!({
            "scenario": self.scenario,
            "cycles": self.cycles,
            "deadline_misses": self.deadline_misses,
            "max_position_error_m": f(self.max_position_error_m),
            "max_heading_error_rad": f(self.max_heading_error_rad),
            "max_leg_error_m": f(self.max_leg_error_m),
            "final_position_error_m": f(self.final_position_error_m),
            "max_steer_rate_rad_s": f(self.max_steer_rate_rad_s),
            "max_wheel_speed_rad_s": f(self.max_wheel_speed_rad_s),
            "min_icr_wheel_distance_m": f(self.min_icr_wheel_distance_m),
            "cycle_period_p50_us": f(self.periods.percentile_us(50.0)),
            "cycle_period_p99_us": f(self.periods.percentile_us(99.0)),
            "compute_time_p50_us": f(self.compute.percentile_us(50.0)),
            "compute_time_p99_us": f(self.compute.percentile_us(99.0)),
            "rejected_frames": self.rejected_frames,
            "supervisor_final_state": self.final_state,
            "fault_reason": self.fault_reason,
            "errors_against": if self.against_truth { "ground_truth" } else { "estimate" },
            "max_wheel_accel_rad_s2": f(self.max_wheel_accel_rad_s2),
            "max_steer_accel_rad_s2": f(self.max_steer_accel_rad_s2),
            "command_timeouts": self.command_timeouts,
            "rejected_commands": self.rejected_commands,
            "ignored_commands": self.ignored_commands,
            "dropped_commands": self.dropped_commands,
            "max_direction_error_deg": f(self.max_direction_error_rad.to_degrees()),
            "stop_time_s": self.stop_time_s.map(f),
            "duration_nominal_s": self.timing.map(|t| f(t.nominal_duration_s)),
            "duration_executed_s": self.timing.map(|t| f(t.executed_duration_s)),
            "time_scale_min": self.timing.map(|t| f(t.min_scale)),
            "time_scale_min_at_s": self.timing.map(|t| f(t.min_scale_at_s)),
            "final_pose": self.final_pose.map(|p| serde_json::json!({
                "x": f(p.x), "y": f(p.y), "theta": f(p.theta),
            })),
            "can_bus": self.can.iter().map(|d| {
                let mut m = serde_json::Map::new();
                for e in rollbase_driver::bus::BusEvent::ALL {
                    m.insert(e.name().replace([' ', '-'], "_"), serde_json::json!(d.count(e)));
                }
                m.insert("state".into(), serde_json::json!(d.state.map_or("error active", |e| e.name())));
                serde_json::Value::Object(m)
            }).collect::<Vec<_>>(),
            "time_scale_limit": self.timing.and_then(|t| {
                (t.limiting != crate::service::ports::Limiting::None)
                    .then(|| format!("wheel {} {}", t.wheel + 1, t.limiting.name()))
            }),
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_histogram_gives_the_nearest_rank_to_three_digits_and_never_grows() {
        let mut h = TimeHistogram::new();
        assert!(h.percentile_us(50.0).is_nan());
        for x in 1..=1000 {
            h.record_us(x as f64 * 4.0);
        }
        let near = |got: f64, want: f64| (got - want).abs() <= want * 1e-3;
        assert!(
            near(h.percentile_us(50.0), 2000.0),
            "{}",
            h.percentile_us(50.0)
        );
        assert!(
            near(h.percentile_us(99.0), 3960.0),
            "{}",
            h.percentile_us(99.0)
        );
        assert!(near(h.percentile_us(100.0), 4000.0));
        assert_eq!(h.len(), 1000);
        // Out of range, not finite or negative: clamped or left out, never a panic.
        h.record_us(1e12);
        h.record_us(f64::NAN);
        h.record_us(-1.0);
        assert_eq!(h.len(), 1001);
        assert!(near(h.percentile_us(100.0), 1e8));
        // A million more values: the histogram is the same size (nothing allocated).
        let before = h.h.distinct_values();
        for k in 0..1_000_000u64 {
            h.record_us((k % 5000) as f64);
        }
        assert_eq!(h.h.distinct_values(), before);
        assert_eq!(h.len(), 1_001_001);
    }

    #[test]
    fn percentile_by_nearest_rank() {
        let xs: Vec<f64> = (1..=100).map(|x| x as f64).collect();
        assert_eq!(percentile(&xs, 50.0), 50.0);
        assert_eq!(percentile(&xs, 99.0), 99.0);
        assert_eq!(percentile(&xs, 100.0), 100.0);
        assert!(percentile(&[], 50.0).is_nan());
    }
}
