//! Summary figures of a run, accumulated from its records.

use crate::record::CycleRecord;
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
    /// Cycle periods (µs), for percentiles.
    pub periods_us: Vec<f64>,
    /// Compute times (µs), for percentiles.
    pub compute_us: Vec<f64>,
    /// Frames rejected by the receive path.
    pub rejected_frames: u64,
    /// Final supervisor state.
    pub final_state: String,
    /// Fault reason, if the run ended in Fault.
    pub fault_reason: Option<String>,
    /// Whether errors were measured against ground truth (simulation) or the estimate.
    pub against_truth: bool,
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
        self.periods_us.push(r.timing.period_us);
        if r.timing.compute_us > 0.0 {
            self.compute_us.push(r.timing.compute_us);
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
        let tracking = matches!(
            r.state,
            SupervisorState::Tracking | SupervisorState::Stopping | SupervisorState::Stopped
        );
        if !tracking {
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
            "cycle_period_p50_us": f(percentile(&self.periods_us, 50.0)),
            "cycle_period_p99_us": f(percentile(&self.periods_us, 99.0)),
            "compute_time_p50_us": f(percentile(&self.compute_us, 50.0)),
            "compute_time_p99_us": f(percentile(&self.compute_us, 99.0)),
            "rejected_frames": self.rejected_frames,
            "supervisor_final_state": self.final_state,
            "fault_reason": self.fault_reason,
            "errors_against": if self.against_truth { "ground_truth" } else { "estimate" },
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn percentile_by_nearest_rank() {
        let xs: Vec<f64> = (1..=100).map(|x| x as f64).collect();
        assert_eq!(percentile(&xs, 50.0), 50.0);
        assert_eq!(percentile(&xs, 99.0), 99.0);
        assert_eq!(percentile(&xs, 100.0), 100.0);
        assert!(percentile(&[], 50.0).is_nan());
    }
}
