//! Where a run's records go: the summary, the MCAP recording, the candump log.

use rollbase::record::McapRecorder;
use rollbase_control::record::CycleRecord;
use rollbase_control::runtime::RunSummary;
use rollbase_driver::candump::{CandumpWriter, LogEntry};
use rollbase_driver::frame::CanFrame;
use std::collections::BTreeMap;
use std::io::Write;
use std::time::Duration;

use super::{CliError, CommonRun};

/// Where the records go: summary, MCAP, candump, progress.
pub(crate) struct Sinks {
    pub(crate) summary: RunSummary,
    pub(crate) mcap: Option<McapRecorder>,
    pub(crate) candump: Option<CandumpWriter<std::io::BufWriter<std::fs::File>>>,
    pub(crate) iface: String,
    pub(crate) time_origin: f64,
    pub(crate) error: Option<CliError>,
}

impl Sinks {
    pub(crate) fn new(
        scenario: &str,
        common: &CommonRun,
        iface: &str,
        time_origin: f64,
        meta: BTreeMap<String, String>,
    ) -> Result<Self, CliError> {
        let record_path = common.record.clone().or_else(|| {
            common
                .plots
                .as_ref()
                .map(|d| d.join(format!("{scenario}.mcap")))
        });
        let mcap = match record_path {
            Some(p) => Some(McapRecorder::create(&p, &meta)?),
            None => None,
        };
        let candump = match &common.candump {
            Some(p) => {
                if let Some(d) = p.parent() {
                    if !d.as_os_str().is_empty() {
                        std::fs::create_dir_all(d).map_err(|e| CliError::File {
                            path: d.display().to_string(),
                            message: e.to_string(),
                        })?;
                    }
                }
                let f = std::fs::File::create(p).map_err(|e| CliError::File {
                    path: p.display().to_string(),
                    message: format!("cannot create candump log: {e}"),
                })?;
                Some(CandumpWriter::new(std::io::BufWriter::new(f)))
            }
            None => None,
        };
        Ok(Self {
            summary: RunSummary::new(scenario),
            mcap,
            candump,
            iface: iface.into(),
            time_origin,
            error: None,
        })
    }

    pub(crate) fn take(&mut self, r: &CycleRecord, wheel_xy: &[[f64; 2]]) {
        self.summary.update(r);
        if self.error.is_some() {
            return;
        }
        if let Some(m) = &mut self.mcap {
            if let Err(e) = m.write_cycle(r, wheel_xy) {
                self.error = Some(e.into());
                return;
            }
        }
        if let Some(w) = &mut self.candump {
            // Frames in bus order: SYNC first, then what was received, then the setpoints.
            let mut frames: Vec<(f64, &rollbase_control::record::FrameRecord)> =
                Vec::with_capacity(r.n_rx + r.n_tx);
            frames.extend(r.tx[..r.n_tx].iter().map(|f| (f.t, f)));
            frames.extend(r.rx[..r.n_rx].iter().map(|f| (f.t, f)));
            frames.sort_by(|a, b| a.0.total_cmp(&b.0));
            for (t, f) in frames {
                let Ok(frame) = CanFrame::new(f.id, &f.data[..f.len as usize]) else {
                    continue;
                };
                let entry = LogEntry {
                    timestamp: Duration::from_secs_f64((self.time_origin + t).max(0.0)),
                    interface: self.iface.clone(),
                    frame,
                };
                if let Err(e) = w.write(&entry) {
                    self.error = Some(CliError::File {
                        path: "candump log".into(),
                        message: e.to_string(),
                    });
                    return;
                }
            }
        }
    }

    /// Closes the outputs; returns the summary and, when recording, messages per topic.
    pub(crate) fn finish(
        mut self,
        common: &CommonRun,
        scenario: &str,
    ) -> Result<(RunSummary, Option<BTreeMap<String, u64>>), CliError> {
        if let Some(e) = self.error.take() {
            return Err(e);
        }
        if let Some(mut w) = self.candump.take() {
            w.flush().map_err(|e| CliError::File {
                path: "candump log".into(),
                message: e.to_string(),
            })?;
        }
        let mut recorded = None;
        if let Some(m) = self.mcap.take() {
            let s = m.finish()?;
            let total: u64 = s.messages.values().sum();
            if !common.json {
                eprintln!("recorded {total} messages on {} topics", s.messages.len());
            }
            recorded = Some(s.messages);
        }
        if let Some(dir) = &common.plots {
            let path = common
                .record
                .clone()
                .unwrap_or_else(|| dir.join(format!("{scenario}.mcap")));
            let rep = rollbase::plot::plot_recording(&path, dir)?;
            if !common.json {
                for f in &rep.files {
                    eprintln!("plot: {}", f.display());
                }
            }
        }
        Ok((self.summary, recorded))
    }
}

/// 0 when the run ended in Stopped (the controller's arrival check passed on its estimate)
/// and, where the simulator's ground truth is known (the demo), the true final position is
/// within `arrive_position` (m) of the goal too; 1 otherwise (says why when only the truth
/// disagrees: the estimate drifted).
pub(crate) fn exit_code(s: &RunSummary, arrive_position: f64) -> i32 {
    if s.final_state != "stopped" {
        return 1;
    }
    let arrived = s.final_position_error_m <= arrive_position; // NaN: not arrived
    if s.against_truth && !arrived {
        let _ = writeln!(
            std::io::stderr(),
            "did not arrive: the controller's estimate says the platform reached the goal, but the simulator's ground truth puts it {:.3} m away (more than arrive_position = {arrive_position} m): the odometry drifted; the run failed",
            s.final_position_error_m
        );
        return 1;
    }
    0
}

pub(crate) fn print_summary(
    s: &RunSummary,
    json: bool,
    reason: Option<rollbase_control::supervisor::FaultReason>,
    recorded: Option<&BTreeMap<String, u64>>,
) {
    if json {
        let mut j = s.to_json();
        if let Some(r) = recorded {
            // Messages per MCAP topic, to check a recording against its run.
            j["recorded_messages"] = serde_json::json!(r);
        }
        println!("{j}");
        return;
    }
    let j = s.to_json();
    let row = |k: &str, unit: &str, scale: f64| {
        let v = j[k]
            .as_f64()
            .map(|x| format!("{:.3}", x * scale))
            .unwrap_or_else(|| "-".into());
        println!("  {k:<28} {v:>12} {unit}");
    };
    println!(
        "summary ({} — errors against {}):",
        s.scenario,
        j["errors_against"].as_str().unwrap_or("?")
    );
    println!("  {:<28} {:>12}", "cycles", s.cycles);
    println!("  {:<28} {:>12}", "deadline_misses", s.deadline_misses);
    row("max_position_error_m", "mm", 1e3);
    row("final_position_error_m", "mm", 1e3);
    row("max_heading_error_rad", "deg", 180.0 / std::f64::consts::PI);
    row("max_leg_error_m", "mm", 1e3);
    row("max_wheel_speed_rad_s", "rad/s", 1.0);
    row("max_steer_rate_rad_s", "rad/s", 1.0);
    row("min_icr_wheel_distance_m", "m", 1.0);
    row("cycle_period_p99_us", "µs", 1.0);
    row("compute_time_p99_us", "µs", 1.0);
    println!("  {:<28} {:>12}", "rejected_frames", s.rejected_frames);
    println!("  {:<28} {:>12}", "supervisor_final_state", s.final_state);
    if let Some(r) = reason {
        println!("  fault: {r}");
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_run_fails_when_it_did_not_stop_or_the_truth_says_it_did_not_arrive() {
        let mut s = RunSummary::new("seed000");
        s.final_state = "fault".into();
        assert_eq!(exit_code(&s, 0.05), 1);
        s.final_state = "stopped".into();
        s.final_position_error_m = 0.2;
        // On hardware (no truth) the controller's own arrival check decided: stopped is 0.
        assert_eq!(exit_code(&s, 0.05), 0);
        // In simulation the truth must agree.
        s.against_truth = true;
        assert_eq!(exit_code(&s, 0.05), 1);
        s.final_position_error_m = 0.001;
        assert_eq!(exit_code(&s, 0.05), 0);
        s.final_position_error_m = f64::NAN;
        assert_eq!(exit_code(&s, 0.05), 1);
    }
}
