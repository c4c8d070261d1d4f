//! `monitor`: decode frames live from a bus or from a candump log.

use clap::Args;
use rollbase_control::Protocol;
use rollbase_driver::bus::{self as bus, CanBus};
use rollbase_driver::candump::{self};
use rollbase_driver::frame::CanFrame;
use std::io::Write;
use std::path::PathBuf;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::Duration;

use super::common::{install_signals, load_platform_as, CliError, SignalAction};

#[derive(Args, Debug)]
pub(crate) struct MonitorArgs {
    /// Wire profile to decode: native or cia402; default: the platform file's `protocol`.
    #[arg(long)]
    pub(crate) profile: Option<Protocol>,
    /// Platform file (the CiA 402 profile's node-IDs and units come from it).
    #[arg(long)]
    pub(crate) config: Option<PathBuf>,
    /// Live CAN interface to listen on.
    #[arg(long, conflicts_with = "candump")]
    pub(crate) bus: Option<String>,
    /// candump -L log to decode.
    #[arg(long)]
    pub(crate) candump: Option<PathBuf>,
    /// Print a summary (frames per kind, rejections, SYNC period) at the end.
    #[arg(long)]
    pub(crate) summary: bool,
    /// One JSON object per frame (id, DLC, data, decoded signals or the rejection) instead
    /// of text; with --summary, a last object {"summary": …}.
    #[arg(long)]
    pub(crate) json: bool,
}

/// Decodes frames for the monitor in the chosen profile.
pub(crate) enum Decoder {
    Native(rollbase_driver::rx::Receiver),
    Cia402(rollbase_driver::canopen::config::Cia402Config),
}

impl Decoder {
    fn text(&mut self, stats: &mut candump::MonitorStats, ts: Duration, f: &CanFrame) -> String {
        match self {
            Decoder::Native(rx) => candump::describe(rx, stats, ts, f),
            Decoder::Cia402(cfg) => {
                let r = rollbase_driver::canopen::describe::describe(f, cfg);
                crate::monitor_json::count_cia402(stats, &r);
                let mut line = format!(
                    "({}.{:06}) {:03X} [{}]",
                    ts.as_secs(),
                    ts.subsec_micros(),
                    f.id(),
                    f.len()
                );
                for b in f.data() {
                    line.push_str(&format!(" {b:02X}"));
                }
                for _ in f.len()..8 {
                    line.push_str("   ");
                }
                match r {
                    Ok(d) => line.push_str(&format!("  {d}")),
                    Err(e) => line.push_str(&format!("  REJECTED: {e}")),
                }
                line
            }
        }
    }

    fn json(
        &mut self,
        stats: &mut candump::MonitorStats,
        ts: Duration,
        f: &CanFrame,
    ) -> serde_json::Value {
        match self {
            Decoder::Native(rx) => crate::monitor_json::frame_json(rx, stats, ts, f),
            Decoder::Cia402(cfg) => crate::monitor_json::cia402_frame_json(cfg, stats, ts, f),
        }
    }

    fn summary(&self, stats: &candump::MonitorStats, json: bool) -> String {
        match (self, json) {
            (Decoder::Native(_), true) => crate::monitor_json::summary_json(stats).to_string(),
            (Decoder::Native(_), false) => stats.to_string(),
            (Decoder::Cia402(_), true) => {
                crate::monitor_json::cia402_summary_json(stats).to_string()
            }
            (Decoder::Cia402(_), false) => format!(
                "frames: {}, described: {}, rejected: {}; unparsable lines: {}",
                stats.frames,
                stats.frames - stats.rejected,
                stats.rejected,
                stats.unparsable
            ),
        }
    }
}

pub(crate) fn monitor(a: MonitorArgs) -> Result<i32, CliError> {
    let platform = load_platform_as(a.config.as_deref(), a.profile)?;
    let mut dec = match platform.protocol {
        Protocol::Native => Decoder::Native(rollbase_driver::rx::Receiver::new()),
        Protocol::Cia402 => Decoder::Cia402(platform.cia402()),
    };
    let mut stats = candump::MonitorStats::default();
    // A closed stdout (`rollbase monitor … | head`) ends the monitor quietly.
    let mut out = std::io::stdout().lock();
    macro_rules! emit {
        ($($arg:tt)*) => {
            if writeln!(out, $($arg)*).is_err() {
                return Ok(0);
            }
        };
    }
    match (&a.bus, &a.candump) {
        (Some(iface), None) => {
            let stop = Arc::new(AtomicBool::new(false));
            install_signals(stop.clone(), SignalAction::End);
            let mut canbus = bus::open(iface)?;
            while !stop.load(Ordering::Relaxed) {
                let deadline = std::time::Instant::now() + Duration::from_millis(200);
                match canbus.recv_until(deadline) {
                    Ok(Some(f)) => {
                        if a.json {
                            let v = dec.json(&mut stats, f.timestamp, &f.frame);
                            emit!("{v}");
                        } else {
                            let line = dec.text(&mut stats, f.timestamp, &f.frame);
                            emit!("{line}");
                        }
                    }
                    Ok(None) => {}
                    Err(e) if e.is_retryable() => {}
                    Err(e) => return Err(e.into()),
                }
            }
        }
        (None, Some(path)) => {
            let f = std::fs::File::open(path).map_err(|e| CliError::File {
                path: path.display().to_string(),
                message: format!("cannot open candump log: {e}"),
            })?;
            // Line numbers are the file's (blank lines count); a bad line is reported and
            // counted and decoding goes on; a line longer than the cap (not a candump log:
            // `/dev/zero`, a binary file) or a read error ends the decode with an error.
            let mut reader = candump::CandumpReader::new(std::io::BufReader::new(f));
            while let Some(item) = reader.next() {
                match item {
                    // A remote frame (RTR) asks for data and carries none: shown as such
                    // (rollbase's protocols use none, so it is counted as rejected).
                    Ok(e) if reader.last_kind() == candump::FrameKind::Remote => {
                        stats.frames += 1;
                        stats.rejected += 1;
                        let ts = e.timestamp;
                        if a.json {
                            let v = serde_json::json!({
                                "t": ts.as_secs_f64(), "id": e.frame.id(), "dlc": e.frame.len(),
                                "remote": true, "accepted": false,
                                "error": "remote frame (RTR): no data; rollbase's protocols use none",
                            });
                            emit!("{v}");
                        } else {
                            emit!(
                                "({}.{:06}) {:03X} [{}] remote request (RTR), no data  REJECTED: rollbase's protocols use no remote frames",
                                ts.as_secs(),
                                ts.subsec_micros(),
                                e.frame.id(),
                                e.frame.len(),
                            );
                        }
                    }
                    Ok(e) if a.json => {
                        let v = dec.json(&mut stats, e.timestamp, &e.frame);
                        emit!("{v}");
                    }
                    Ok(e) => {
                        let line = dec.text(&mut stats, e.timestamp, &e.frame);
                        emit!("{line}");
                    }
                    Err(
                        e @ (candump::CandumpError::LineTooLong { .. }
                        | candump::CandumpError::Io { .. }),
                    ) => {
                        if a.summary {
                            stats.unparsable += 1;
                            let line = dec.summary(&stats, a.json);
                            emit!("{line}");
                        }
                        return Err(CliError::File {
                            path: path.display().to_string(),
                            message: e.to_string(),
                        });
                    }
                    Err(e) if a.json => {
                        stats.unparsable += 1;
                        let v = serde_json::json!({"line": e.line(), "error": e.to_string()});
                        emit!("{v}");
                    }
                    Err(e) => {
                        stats.unparsable += 1;
                        emit!("{}: {e}", path.display());
                    }
                }
            }
        }
        _ => {
            return Err(CliError::Usage(
                "monitor needs exactly one of --bus IFACE or --candump FILE".into(),
            ))
        }
    }
    if a.summary {
        let line = dec.summary(&stats, a.json);
        emit!("{line}");
    }
    Ok(0)
}
