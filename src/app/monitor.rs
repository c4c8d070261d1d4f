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

use super::common::{install_signals, load_platform_profile, CliError, SignalAction};

#[derive(Args, Debug)]
pub(crate) struct MonitorArgs {
    /// Wire profile to decode: native or cia402; default: the platform file's `protocol`.
    #[arg(long)]
    pub(crate) profile: Option<Protocol>,
    /// Platform file (the CiA 402 profile's node-IDs and units come from it).
    #[arg(long)]
    pub(crate) config: Option<PathBuf>,
    /// Live CAN interface to listen on; repeat for several (a platform on two buses: one
    /// `--bus` per bus). With more than one, each frame is labelled with its interface and
    /// the summary is one per interface.
    #[arg(long, conflicts_with = "candump")]
    pub(crate) bus: Vec<String>,
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

/// One interface's decoder and counts (frames of a platform on two buses are decoded and
/// counted per bus, as they were sent).
struct Slot {
    name: String,
    dec: Decoder,
    stats: candump::MonitorStats,
}

/// The slot of interface `name`, made on its first frame.
fn slot<'a>(
    slots: &'a mut Vec<Slot>,
    name: &str,
    platform: &rollbase_control::Platform,
) -> &'a mut Slot {
    let k = match slots.iter().position(|s| s.name == name) {
        Some(k) => k,
        None => {
            slots.push(Slot {
                name: name.to_string(),
                dec: match platform.protocol {
                    Protocol::Native => Decoder::Native(rollbase_driver::rx::Receiver::new()),
                    Protocol::Cia402 => Decoder::Cia402(platform.cia402()),
                },
                stats: candump::MonitorStats::default(),
            });
            slots.len() - 1
        }
    };
    &mut slots[k]
}

/// A decoded frame as text or JSON, labelled with its interface when `label`.
fn frame_line(s: &mut Slot, ts: Duration, f: &CanFrame, json: bool, label: bool) -> String {
    if json {
        let mut v = s.dec.json(&mut s.stats, ts, f);
        if label {
            if let Some(o) = v.as_object_mut() {
                o.insert("bus".into(), serde_json::Value::String(s.name.clone()));
            }
        }
        v.to_string()
    } else {
        let line = s.dec.text(&mut s.stats, ts, f);
        if label {
            format!("{} {line}", s.name)
        } else {
            line
        }
    }
}

/// The summary of one interface, labelled when `label`.
fn summary_line(s: &Slot, json: bool, label: bool) -> String {
    let text = s.dec.summary(&s.stats, json);
    match (label, json) {
        (false, _) => text,
        (true, false) => format!("{}: {text}", s.name),
        (true, true) => {
            let mut v: serde_json::Value = serde_json::from_str(&text).unwrap_or_default();
            if let Some(o) = v.as_object_mut() {
                o.insert("bus".into(), serde_json::Value::String(s.name.clone()));
            }
            v.to_string()
        }
    }
}

pub(crate) fn monitor(a: MonitorArgs) -> Result<i32, CliError> {
    // Any platform: decoding needs no bus of its own (a two-bus platform's frames are told
    // apart by their interface).
    let platform = load_platform_profile(a.config.as_deref(), a.profile)?;
    let mut slots: Vec<Slot> = Vec::new();
    let mut unparsable = 0u64;
    // Frames and summaries carry their interface when there may be more than one.
    let label = a.bus.len() > 1 || (a.bus.is_empty() && platform.buses() > 1);
    // A closed stdout (`rollbase monitor … | head`) ends the monitor quietly.
    let mut out = std::io::stdout().lock();
    macro_rules! emit {
        ($($arg:tt)*) => {
            if writeln!(out, $($arg)*).is_err() {
                return Ok(0);
            }
        };
    }
    match (a.bus.as_slice(), &a.candump) {
        ([_, ..], None) => {
            let mut seen = std::collections::HashSet::new();
            if let Some(dup) = a.bus.iter().find(|b| !seen.insert(b.as_str())) {
                return Err(CliError::Usage(format!(
                    "--bus {dup} is given twice: give each interface once"
                )));
            }
            let stop = Arc::new(AtomicBool::new(false));
            install_signals(stop.clone(), SignalAction::End);
            let mut buses = Vec::with_capacity(a.bus.len());
            for iface in &a.bus {
                buses.push(bus::open(iface)?);
            }
            // Frames are labelled with the interface's name (`vcan0` for
            // socketcand://host/vcan0, as candump logs name them), or with the `--bus` as
            // given where two names would be the same.
            let names: Vec<&str> = buses.iter().map(|b| b.name()).collect();
            let unique = (0..names.len()).all(|i| !names[..i].contains(&names[i]));
            for (k, iface) in a.bus.iter().enumerate() {
                let name = if unique { names[k] } else { iface.as_str() };
                slot(&mut slots, name, &platform);
            }
            // Each interface in turn, for a share of 200 ms (frames wait in the socket's
            // queue meanwhile; each keeps its own receive timestamp).
            let share = Duration::from_millis(200) / buses.len() as u32;
            while !stop.load(Ordering::Relaxed) {
                for (k, canbus) in buses.iter_mut().enumerate() {
                    let deadline = std::time::Instant::now() + share;
                    loop {
                        match canbus.recv_until(deadline) {
                            Ok(Some(f)) => {
                                let line =
                                    frame_line(&mut slots[k], f.timestamp, &f.frame, a.json, label);
                                emit!("{line}");
                            }
                            Ok(None) => break,
                            Err(e) if e.is_retryable() => break,
                            Err(e) => return Err(e.into()),
                        }
                    }
                }
            }
        }
        ([], Some(path)) => {
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
                        let s = slot(&mut slots, &e.interface, &platform);
                        s.stats.frames += 1;
                        s.stats.rejected += 1;
                        let ts = e.timestamp;
                        let bus = if label {
                            format!("{} ", e.interface)
                        } else {
                            String::new()
                        };
                        if a.json {
                            let mut v = serde_json::json!({
                                "t": ts.as_secs_f64(), "id": e.frame.id(), "dlc": e.frame.len(),
                                "remote": true, "accepted": false,
                                "error": "remote frame (RTR): no data; rollbase's protocols use none",
                            });
                            if label {
                                v["bus"] = serde_json::Value::String(e.interface.clone());
                            }
                            emit!("{v}");
                        } else {
                            emit!(
                                "{bus}({}.{:06}) {:03X} [{}] remote request (RTR), no data  REJECTED: rollbase's protocols use no remote frames",
                                ts.as_secs(),
                                ts.subsec_micros(),
                                e.frame.id(),
                                e.frame.len(),
                            );
                        }
                    }
                    Ok(e) => {
                        let s = slot(&mut slots, &e.interface, &platform);
                        let line = frame_line(s, e.timestamp, &e.frame, a.json, label);
                        emit!("{line}");
                    }
                    Err(
                        e @ (candump::CandumpError::LineTooLong { .. }
                        | candump::CandumpError::Io { .. }),
                    ) => {
                        if a.summary {
                            unparsable += 1;
                            for line in summaries(&mut slots, &platform, unparsable, a.json, label)
                            {
                                emit!("{line}");
                            }
                        }
                        return Err(CliError::File {
                            path: path.display().to_string(),
                            message: e.to_string(),
                        });
                    }
                    Err(e) if a.json => {
                        unparsable += 1;
                        let v = serde_json::json!({"line": e.line(), "error": e.to_string()});
                        emit!("{v}");
                    }
                    Err(e) => {
                        unparsable += 1;
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
        for line in summaries(&mut slots, &platform, unparsable, a.json, label) {
            emit!("{line}");
        }
    }
    Ok(0)
}

/// The summary lines: one per interface (lines of a log that name no interface, the
/// unparsable ones, are counted in the first interface's).
fn summaries(
    slots: &mut Vec<Slot>,
    platform: &rollbase_control::Platform,
    unparsable: u64,
    json: bool,
    label: bool,
) -> Vec<String> {
    if slots.is_empty() {
        slot(slots, "(no frames)", platform);
    }
    slots[0].stats.unparsable += unparsable;
    let lines = slots.iter().map(|s| summary_line(s, json, label)).collect();
    slots[0].stats.unparsable -= unparsable;
    lines
}
