//! Where a run's records go: the summary, the MCAP recording, the candump log.
//!
//! Recordings are never lost or overwritten by a run that fails:
//! - every path is checked before anything starts (the same file given twice, a path under a
//!   regular file, a directory, a device or FIFO given to `--record`), and nothing is created
//!   before the run's inputs are validated and its bus is open ([`OutputPlan::check`], called
//!   by each command);
//! - the MCAP and the candump log are written under a temporary name next to the target
//!   (`.NAME.partial-PID`) and renamed onto it only when finished, so an earlier file of the
//!   same name stays until a new one is complete (a candump log given as an existing device,
//!   FIFO or socket, e.g. `/dev/stdout`, is written to it directly: there is no earlier
//!   recording to protect, and a rename would replace the device node);
//! - a write error (a full disk, a file-size limit) stops the run in a controlled way
//!   ([`Sinks::failed`] tells the caller; the cycle keeps its own rhythm, the summary is still
//!   printed) and its cause is reported. The output that failed is *not* finished and *not*
//!   renamed: its target name is left as it was (absent, or the earlier file), and what was
//!   written up to the failure stays in the temporary file, which the error names with the
//!   `rollbase recover` command that salvages it (an MCAP written after a failed write could
//!   hold a cut record under a valid-looking index). An output that did not fail is finished
//!   and renamed as usual; it ends where the recording stopped. The same holds when finishing
//!   itself fails (the disk fills while the index is written): the temporary file is kept.

use rollbase::record::{McapRecorder, RecordOptions};
use rollbase_control::runtime::record::CycleRecord;
use rollbase_control::runtime::RunSummary;
use rollbase_driver::candump::{CandumpWriter, LogEntry};
use rollbase_driver::frame::CanFrame;
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::time::Duration;

use super::common::{CliError, CommonRun};

/// The output files of a run, checked before anything starts.
#[derive(Clone, Debug, Default)]
pub(crate) struct OutputPlan {
    /// The MCAP recording (given, or implied by `--plots DIR`).
    pub(crate) record: Option<PathBuf>,
    /// The candump log.
    pub(crate) candump: Option<PathBuf>,
    /// The plots directory.
    pub(crate) plots: Option<PathBuf>,
    /// Topic names, frames and rates of the ROS 2 topics in the recording (those of the
    /// node, with `--ros2`; the defaults otherwise).
    pub(crate) ros2: rollbase::ros2::Ros2Options,
    /// The option that named the recording, for messages (`--record`, or `--plots` when the
    /// recording is implied by it).
    pub(crate) record_option: &'static str,
}

impl OutputPlan {
    /// The outputs `common` asks for (`scenario` names the implied recording of `--plots`).
    pub(crate) fn of(common: &CommonRun, scenario: &str) -> Self {
        let record = common.record.clone().or_else(|| {
            common
                .plots
                .as_ref()
                .map(|d| d.join(format!("{scenario}.mcap")))
        });
        Self {
            record,
            candump: common.candump.clone(),
            plots: common.plots.clone(),
            ros2: Default::default(),
            record_option: if common.record.is_none() && common.plots.is_some() {
                "--plots"
            } else {
                "--record"
            },
        }
    }

    fn record_option(&self) -> &'static str {
        if self.record_option.is_empty() {
            "--record"
        } else {
            self.record_option
        }
    }

    /// Refuses what cannot work, before anything is created: the same file for two outputs,
    /// a path whose directory part is a regular file, an output that is a directory, a
    /// recording that is not a regular file (a device, FIFO or socket).
    pub(crate) fn check(&self) -> Result<(), CliError> {
        if let Some(d) = &self.plots {
            if d.exists() && !d.is_dir() {
                return Err(CliError::Usage(format!(
                    "--plots {}: not a directory",
                    d.display()
                )));
            }
            check_ancestors("--plots", d)?;
        }
        if let Some(p) = &self.record {
            check_output_path(self.record_option(), p, false)?;
        }
        if let Some(p) = &self.candump {
            check_output_path("--candump", p, true)?;
        }
        if let (Some(a), Some(b)) = (&self.record, &self.candump) {
            if same_file(a, b) {
                return Err(CliError::Usage(format!(
                    "{} and --candump both name {}: give two different files",
                    self.record_option(),
                    a.display()
                )));
            }
        }
        Ok(())
    }
}

/// A path's absolute form, as far as it can be resolved (for comparing outputs).
fn absolute(p: &Path) -> PathBuf {
    let abs = if p.is_absolute() {
        p.to_path_buf()
    } else {
        std::env::current_dir().unwrap_or_default().join(p)
    };
    match (abs.parent(), abs.file_name()) {
        (Some(d), Some(f)) => d.canonicalize().map(|d| d.join(f)).unwrap_or(abs),
        _ => abs,
    }
}

fn same_file(a: &Path, b: &Path) -> bool {
    if absolute(a) == absolute(b) {
        return true;
    }
    // Two names of one existing file (a symbolic or hard link).
    use std::os::unix::fs::MetadataExt;
    match (std::fs::metadata(a), std::fs::metadata(b)) {
        (Ok(x), Ok(y)) => x.dev() == y.dev() && x.ino() == y.ino(),
        _ => false,
    }
}

/// True when `p` exists and is not a regular file or a directory (a device such as
/// `/dev/null` or `/dev/stdout`, a FIFO, a socket), following symbolic links.
fn is_special(p: &Path) -> bool {
    std::fs::metadata(p).is_ok_and(|m| !m.is_file() && !m.is_dir())
}

/// No regular file among the directories of `p` (which are created when missing).
fn check_ancestors(option: &str, p: &Path) -> Result<(), CliError> {
    let mut dir = p.parent();
    while let Some(d) = dir {
        if d.as_os_str().is_empty() {
            break;
        }
        if d.exists() {
            if !d.is_dir() {
                return Err(CliError::Usage(format!(
                    "{option} {}: {} is a file, not a directory; give a path under a directory",
                    p.display(),
                    d.display()
                )));
            }
            break;
        }
        dir = d.parent();
    }
    Ok(())
}

/// An output file's path must be creatable: no regular file among its directories, and not a
/// directory itself. A device, FIFO or socket is refused unless `special_ok` (then it is
/// written directly, see [`Sinks::new`]).
fn check_output_path(option: &str, p: &Path, special_ok: bool) -> Result<(), CliError> {
    if p.is_dir() {
        return Err(CliError::Usage(format!(
            "{option} {}: is a directory; give a file name",
            p.display()
        )));
    }
    if !special_ok && is_special(p) {
        return Err(CliError::Usage(format!(
            "{option} {}: not a regular file (a device, FIFO or socket); an MCAP recording needs a regular file: give a file path, or leave the option out to record nothing",
            p.display()
        )));
    }
    check_ancestors(option, p)
}

/// Reserves the temporary name a file is written under until it is complete:
/// `.NAME.partial-PID` next to the target, created empty here so that a leftover of an
/// earlier run (a killed one whose process id was the same, as in a container) is never
/// truncated: then `-2`, `-3`, … is appended.
fn reserve_partial(option: &str, p: &Path) -> Result<PathBuf, CliError> {
    let name = p
        .file_name()
        .map(|n| n.to_string_lossy().into_owned())
        .unwrap_or_else(|| "output".into());
    let base = format!(".{name}.partial-{}", std::process::id());
    let mut last = None;
    for k in 1..=100u32 {
        let tmp = p.with_file_name(if k == 1 {
            base.clone()
        } else {
            format!("{base}-{k}")
        });
        match std::fs::OpenOptions::new()
            .write(true)
            .create_new(true)
            .open(&tmp)
        {
            Ok(_) => return Ok(tmp),
            Err(e) if e.kind() == std::io::ErrorKind::AlreadyExists => last = Some(e),
            Err(e) => {
                return Err(CliError::File {
                    path: tmp.display().to_string(),
                    message: format!("{option}: cannot create the temporary file: {e}"),
                })
            }
        }
    }
    Err(CliError::File {
        path: p.with_file_name(base).display().to_string(),
        message: format!(
            "{option}: 100 temporary files of this name exist already ({}); move them away",
            last.map(|e| e.to_string()).unwrap_or_default()
        ),
    })
}

fn make_parent(p: &Path) -> Result<(), CliError> {
    if let Some(d) = p.parent() {
        if !d.as_os_str().is_empty() {
            std::fs::create_dir_all(d).map_err(|e| CliError::File {
                path: d.display().to_string(),
                message: format!("cannot create the directory: {e}"),
            })?;
        }
    }
    Ok(())
}

/// An output being written: under `tmp`, renamed onto `target` when finished (`tmp ==
/// target`: a candump log written directly to a device or FIFO).
struct Out<W> {
    w: W,
    tmp: PathBuf,
    target: PathBuf,
}

/// Which output failed during the run.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Failed {
    Mcap,
    Candump,
}

/// Where the records go: summary, MCAP, candump.
pub(crate) struct Sinks {
    pub(crate) summary: RunSummary,
    mcap: Option<Out<McapRecorder>>,
    candump: Option<Out<CandumpWriter<std::io::BufWriter<std::fs::File>>>>,
    plan: OutputPlan,
    /// The interface of each bus (bus b's frames are logged on `ifaces[b]`).
    ifaces: Vec<String>,
    pub(crate) time_origin: f64,
    error: Option<(Failed, CliError)>,
    /// The recorder's warning about the state was logged.
    state_warned: bool,
}

impl Sinks {
    /// Opens the outputs of `plan` (checked again here) under their temporary names; `ifaces`
    /// names the interface of each bus (at least one), for the frames' logs.
    pub(crate) fn new(
        scenario: &str,
        plan: &OutputPlan,
        ifaces: &[&str],
        time_origin: f64,
        meta: BTreeMap<String, String>,
    ) -> Result<Self, CliError> {
        plan.check()?;
        let ifaces: Vec<String> = if ifaces.is_empty() {
            vec!["can".to_string()]
        } else {
            ifaces.iter().map(|s| s.to_string()).collect()
        };
        let mcap = match &plan.record {
            Some(p) => {
                make_parent(p)?;
                let tmp = reserve_partial(plan.record_option(), p)?;
                let rec = McapRecorder::create_with(
                    &tmp,
                    &meta,
                    &RecordOptions {
                        can_interface: ifaces[0].clone(),
                        bus_interfaces: ifaces.clone(),
                        ros2: plan.ros2.clone(),
                    },
                );
                match rec {
                    Ok(w) => Some(Out {
                        w,
                        tmp,
                        target: p.clone(),
                    }),
                    Err(e) => {
                        // Nothing was recorded yet: leave nothing behind.
                        let _ = std::fs::remove_file(&tmp);
                        return Err(CliError::File {
                            path: p.display().to_string(),
                            message: format!(
                                "cannot start the recording (temporary file {}): {}",
                                tmp.display(),
                                root_cause(&e)
                            ),
                        });
                    }
                }
            }
            None => None,
        };
        let candump = match &plan.candump {
            Some(p) => {
                // A device, FIFO or socket (`/dev/stdout`, a pipe to another tool) is written
                // directly: a temporary file renamed onto it would replace the node.
                let (tmp, f) = if is_special(p) {
                    let f = std::fs::OpenOptions::new().write(true).open(p);
                    (p.clone(), f)
                } else {
                    make_parent(p)?;
                    let tmp = reserve_partial("--candump", p)?;
                    let f = std::fs::File::create(&tmp);
                    (tmp, f)
                };
                let f = f.map_err(|e| CliError::File {
                    path: p.display().to_string(),
                    message: format!("cannot create candump log: {e}"),
                })?;
                Some(Out {
                    w: CandumpWriter::new(std::io::BufWriter::new(f)),
                    tmp,
                    target: p.clone(),
                })
            }
            None => None,
        };
        Ok(Self {
            summary: RunSummary::new(scenario),
            mcap,
            candump,
            plan: plan.clone(),
            ifaces,
            time_origin,
            error: None,
            state_warned: false,
        })
    }

    /// True once writing an output failed (the caller stops the run).
    pub(crate) fn failed(&self) -> bool {
        self.error.is_some()
    }

    /// The write error, if any (for the operator while the run stops).
    pub(crate) fn error(&self) -> Option<&CliError> {
        self.error.as_ref().map(|(_, e)| e)
    }

    pub(crate) fn take(&mut self, r: &CycleRecord, wheel_xy: &[[f64; 2]]) {
        self.summary.update(r);
        if self.error.is_some() {
            return;
        }
        if let Some(o) = &mut self.mcap {
            // The cycle, then the ROS 2 topics: the state (decimated to the node's rates by
            // the recorder) and the commands the cycle took.
            let mut st = r.base;
            st.log_time_ns = r.log_time_ns;
            st.t = r.t;
            let m = &mut o.w;
            let written = m.write_cycle(r, wheel_xy).and_then(|()| {
                if let Some(w) = m.write_state(&st)? {
                    if !self.state_warned {
                        tracing::warn!("recording: {w}");
                        self.state_warned = true;
                    }
                }
                for ev in r.commands_in.iter().flatten() {
                    m.write_command(ev, r.log_time_ns)?;
                }
                Ok(())
            });
            if let Err(e) = written {
                self.error = Some((
                    Failed::Mcap,
                    CliError::Recording {
                        path: o.target.display().to_string(),
                        source: Box::new(e.into()),
                    },
                ));
                return;
            }
        }
        if let Some(o) = &mut self.candump {
            // Frames in bus order: SYNC first, then what was received, then the setpoints.
            let mut frames: Vec<(f64, &rollbase_control::runtime::record::FrameRecord)> =
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
                    interface: self
                        .ifaces
                        .get(usize::from(f.bus))
                        .unwrap_or(&self.ifaces[0])
                        .clone(),
                    frame,
                };
                if let Err(e) = o.w.write(&entry) {
                    self.error = Some((
                        Failed::Candump,
                        CliError::Recording {
                            path: o.target.display().to_string(),
                            source: Box::new(CliError::File {
                                path: o.tmp.display().to_string(),
                                message: e.to_string(),
                            }),
                        },
                    ));
                    return;
                }
            }
        }
    }

    /// Closes the outputs (renaming each finished one onto its target) and makes the plots;
    /// returns the summary, the messages per recorded topic, and the error that stopped the
    /// recording. An output that failed is neither finished nor renamed: its temporary file
    /// is kept and named in the error, with how to salvage it (module docs).
    pub(crate) fn finish(
        mut self,
        quiet: bool,
    ) -> (RunSummary, Option<BTreeMap<String, u64>>, Option<CliError>) {
        let (failed, mut err) = match self.error.take() {
            Some((f, e)) => (Some(f), Some(e)),
            None => (None, None),
        };
        if let Some(Out { mut w, tmp, target }) = self.candump.take() {
            if failed == Some(Failed::Candump) {
                let _ = w.flush();
                if tmp == target {
                    // Written directly (a device or FIFO): nothing kept elsewhere.
                } else {
                    err = with_kept(
                        err.take(),
                        &tmp,
                        &target,
                        "the log up to the failure is kept in it (its last line may be cut); rename it to use it",
                    );
                }
            } else {
                match w.flush() {
                    Ok(()) if tmp == target => {}
                    Ok(()) => {
                        if let Err(e) = rename(&tmp, &target) {
                            report(&mut err, e);
                        }
                    }
                    Err(e) => report(
                        &mut err,
                        CliError::File {
                            path: target.display().to_string(),
                            message: if tmp == target {
                                format!("the candump log could not be finished: {e}")
                            } else {
                                format!(
                                    "the candump log could not be finished ({e}): not written; the log up to the failure is kept in {} (its last line may be cut)",
                                    tmp.display()
                                )
                            },
                        },
                    ),
                }
            }
        }
        let mut recorded = None;
        if let Some(o) = self.mcap.take() {
            let Out { w, tmp, target } = o;
            if failed == Some(Failed::Mcap) {
                let bytes = w.abandon();
                err = with_kept(
                    err.take(),
                    &tmp,
                    &target,
                    &format!(
                        "the {bytes} bytes written up to the failure are kept in it, without index or summary; {}",
                        recover_hint(&tmp, &target)
                    ),
                );
            } else {
                match w.finish() {
                    Ok(s) => {
                        let total: u64 = s.messages.values().sum();
                        match rename(&tmp, &target) {
                            Ok(()) => {
                                if !quiet {
                                    errln!(
                                        "recorded {total} messages on {} topics to {}",
                                        s.messages.len(),
                                        target.display()
                                    );
                                }
                                recorded = Some(s.messages);
                            }
                            Err(e) => report(&mut err, e),
                        }
                    }
                    Err(e) => {
                        // Finishing failed (the disk filled while the index was written):
                        // the data written so far stays for `recover`.
                        let bytes = std::fs::metadata(&tmp).map(|m| m.len()).unwrap_or(0);
                        report(&mut err, CliError::File {
                            path: target.display().to_string(),
                            message: format!(
                                "the recording could not be finished ({}): not written; the {bytes} bytes recorded are kept in {}, without index or summary; {}",
                                root_cause(&e),
                                tmp.display(),
                                recover_hint(&tmp, &target)
                            ),
                        });
                    }
                }
            }
        }
        if let (Some(dir), Some(path), None) = (&self.plan.plots, &self.plan.record, &err) {
            match rollbase::plot::plot_recording(path, dir) {
                Ok(rep) => {
                    if !quiet {
                        for f in &rep.files {
                            errln!("plot: {}", f.display());
                        }
                        for w in &rep.ignored {
                            errln!("plot warning: {w}");
                        }
                    }
                }
                Err(e) => {
                    err.get_or_insert(e.into());
                }
            }
        }
        (self.summary, recorded, err)
    }
}

/// Keeps the first error of a run's outputs for its exit code and its last lines; a further
/// one (a second output that failed too) is printed at once, so that no kept file goes
/// unmentioned.
fn report(err: &mut Option<CliError>, e: CliError) {
    if err.is_none() {
        *err = Some(e);
    } else {
        errln!("error: {e}");
    }
}

/// The innermost cause of an error (the OS error of an I/O failure, e.g. "No space left on
/// device (os error 28)").
fn root_cause(e: &dyn std::error::Error) -> String {
    let mut e = e;
    while let Some(s) = e.source() {
        e = s;
    }
    e.to_string()
}

/// The recording error of a failed output, its cause completed with where the data was kept
/// (any other error passes unchanged).
fn with_kept(err: Option<CliError>, tmp: &Path, target: &Path, what: &str) -> Option<CliError> {
    match err {
        Some(CliError::Recording { path, source }) => Some(CliError::Recording {
            path,
            source: Box::new(kept(&source, tmp, target, what)),
        }),
        other => other,
    }
}

/// The cause of a failed output, with where its data was kept and what to do.
fn kept(cause: &CliError, tmp: &Path, target: &Path, what: &str) -> CliError {
    CliError::File {
        path: tmp.display().to_string(),
        message: format!(
            "{}; {what} ({} was not written{})",
            root_cause(cause),
            target.display(),
            if target.exists() {
                ": the earlier file of that name is unchanged"
            } else {
                ""
            }
        ),
    }
}

/// How to salvage a recording kept under `tmp` (an unused output name near `target`).
fn recover_hint(tmp: &Path, target: &Path) -> String {
    let out = if target.exists() {
        let stem = target
            .file_stem()
            .map(|s| s.to_string_lossy().into_owned())
            .unwrap_or_else(|| "recording".into());
        target.with_file_name(format!("{stem}.recovered.mcap"))
    } else {
        target.to_path_buf()
    };
    format!(
        "once there is space, `rollbase recover {} --out {}` rewrites its complete chunks with an index",
        tmp.display(),
        out.display()
    )
}

fn rename(tmp: &Path, target: &Path) -> Result<(), CliError> {
    std::fs::rename(tmp, target).map_err(|e| CliError::File {
        path: target.display().to_string(),
        message: format!(
            "finished, but could not be renamed from {}: {e}",
            tmp.display()
        ),
    })
}

/// What a run's end means for its exit code (README "Exit codes").
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) enum Ending {
    /// Ran to its end: the trajectory completed, or the service stopped on request.
    Completed,
    /// A trajectory run stopped early on SIGINT or SIGTERM (controlled stop).
    Interrupted,
}

/// Exit codes (README "Exit codes").
pub(crate) mod exit {
    /// Completed: trajectory done and stopped, or the service stopped on request.
    pub const OK: i32 = 0;
    /// The run ended in a fault (latched), or did not arrive.
    pub const FAULT: i32 = 1;
    /// Refused before starting, or failed to run (bad input, file, bus).
    pub const REFUSED: i32 = 2;
    /// A trajectory run was interrupted by SIGINT or SIGTERM (controlled stop, outputs kept).
    pub const INTERRUPTED: i32 = 3;
    /// The recording or candump log failed during the run (controlled stop, cause printed).
    pub const RECORDING: i32 = 4;
}

/// The exit code of a run (README "Exit codes"). `arrive_position` (m): for a trajectory run
/// whose errors were measured against the simulator's ground truth (the demo), the true final
/// position must be within it of the goal too — the controller's own arrival check only sees
/// its estimate, and an odometry that drifted would otherwise pass.
pub(crate) fn exit_code(
    s: &RunSummary,
    ending: Ending,
    record_error: bool,
    arrive_position: Option<f64>,
) -> i32 {
    if record_error {
        return exit::RECORDING;
    }
    if s.final_state == "fault" {
        return exit::FAULT;
    }
    if ending == Ending::Interrupted {
        return exit::INTERRUPTED;
    }
    if s.final_state != "stopped" && s.final_state != "idle" {
        return exit::FAULT;
    }
    if let Some(tol) = arrive_position {
        let arrived = s.final_position_error_m <= tol; // NaN: not arrived
        if s.against_truth && !arrived {
            errln!(
                "did not arrive: the controller's estimate says the platform reached the goal, but the simulator's ground truth puts it {:.3} m away (more than arrive_position = {tol} m): the odometry drifted; the run failed",
                s.final_position_error_m
            );
            return exit::FAULT;
        }
    }
    exit::OK
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
        outln!("{j}");
        return;
    }
    let j = s.to_json();
    let row = |k: &str, unit: &str, scale: f64| {
        let v = j[k]
            .as_f64()
            .map(|x| format!("{:.3}", x * scale))
            .unwrap_or_else(|| "-".into());
        outln!("  {k:<28} {v:>12} {unit}");
    };
    outln!(
        "summary ({} — errors against {}):",
        s.scenario,
        j["errors_against"].as_str().unwrap_or("?")
    );
    outln!("  {:<28} {:>12}", "cycles", s.cycles);
    outln!("  {:<28} {:>12}", "deadline_misses", s.deadline_misses);
    row("max_position_error_m", "mm", 1e3);
    row("final_position_error_m", "mm", 1e3);
    // The JSON's key is in rad; the table shows degrees under a unit-free name.
    {
        let v = j["max_heading_error_rad"]
            .as_f64()
            .map(|x| format!("{:.3}", x.to_degrees()))
            .unwrap_or_else(|| "-".into());
        outln!("  {:<28} {v:>12} deg", "max_heading_error");
    }
    row("max_leg_error_m", "mm", 1e3);
    row("max_direction_error_deg", "deg", 1.0);
    row("max_wheel_speed_rad_s", "rad/s", 1.0);
    row("max_wheel_accel_rad_s2", "rad/s²", 1.0);
    row("max_steer_rate_rad_s", "rad/s", 1.0);
    row("max_steer_accel_rad_s2", "rad/s²", 1.0);
    row("min_icr_wheel_distance_m", "m", 1.0);
    row("stop_time_s", "s", 1.0);
    row("cycle_period_p99_us", "µs", 1.0);
    row("compute_time_p99_us", "µs", 1.0);
    outln!("  {:<28} {:>12}", "rejected_frames", s.rejected_frames);
    outln!("  {:<28} {:>12}", "command_timeouts", s.command_timeouts);
    outln!("  {:<28} {:>12}", "rejected_commands", s.rejected_commands);
    if s.dropped_commands > 0 {
        outln!("  {:<28} {:>12}", "dropped_commands", s.dropped_commands);
    }
    outln!("  {:<28} {:>12}", "supervisor_final_state", s.final_state);
    if let Some(p) = s.final_pose {
        outln!(
            "  {:<28} x {:.3} m, y {:.3} m, θ {:.2}°",
            "final_pose (estimate)",
            p.x,
            p.y,
            p.theta.to_degrees()
        );
    }
    if let Some(r) = reason {
        outln!("  fault: {r}");
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_leftover_temporary_file_is_never_reused_or_truncated() {
        let dir = std::env::temp_dir().join(format!("rollbase-sinks-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        std::fs::create_dir_all(&dir).unwrap();
        let target = dir.join("run.mcap");
        // What a killed run with the same process id left (a container restarted).
        let leftover = dir.join(format!(".run.mcap.partial-{}", std::process::id()));
        std::fs::write(&leftover, b"earlier data").unwrap();
        let tmp = reserve_partial("--record", &target).unwrap();
        assert_ne!(tmp, leftover);
        assert!(tmp.to_string_lossy().ends_with("-2"), "{}", tmp.display());
        assert_eq!(std::fs::read(&leftover).unwrap(), b"earlier data");
        assert_eq!(std::fs::read(&tmp).unwrap(), b"");
        let _ = std::fs::remove_dir_all(dir);
    }

    #[test]
    fn devices_are_refused_as_recordings_and_written_directly_as_candump_logs() {
        let plan = OutputPlan {
            record: Some("/dev/null".into()),
            ..Default::default()
        };
        let e = plan.check().unwrap_err().to_string();
        assert!(e.contains("--record /dev/null: not a regular file"), "{e}");
        let plan = OutputPlan {
            candump: Some("/dev/null".into()),
            ..Default::default()
        };
        plan.check().unwrap();
        assert!(is_special(Path::new("/dev/null")));
        assert!(!is_special(Path::new("/nonexistent/x.log")));
    }

    #[test]
    fn a_run_fails_when_it_did_not_stop_or_the_truth_says_it_did_not_arrive() {
        let mut s = RunSummary::new("seed000");
        s.final_state = "fault".into();
        assert_eq!(exit_code(&s, Ending::Completed, false, Some(0.05)), 1);
        s.final_state = "stopped".into();
        s.final_position_error_m = 0.2;
        // On hardware (no truth) the controller's own arrival check decided: stopped is 0.
        assert_eq!(exit_code(&s, Ending::Completed, false, Some(0.05)), 0);
        // In simulation the truth must agree.
        s.against_truth = true;
        assert_eq!(exit_code(&s, Ending::Completed, false, Some(0.05)), 1);
        s.final_position_error_m = 0.001;
        assert_eq!(exit_code(&s, Ending::Completed, false, Some(0.05)), 0);
        s.final_position_error_m = f64::NAN;
        assert_eq!(exit_code(&s, Ending::Completed, false, Some(0.05)), 1);
        // An interrupted run is 3, a failed recording 4 (it wins over everything), the
        // service (no goal) 0 once stopped.
        s.final_position_error_m = 0.001;
        assert_eq!(exit_code(&s, Ending::Interrupted, false, Some(0.05)), 3);
        assert_eq!(exit_code(&s, Ending::Completed, true, Some(0.05)), 4);
        s.final_position_error_m = 3.0;
        assert_eq!(exit_code(&s, Ending::Completed, false, None), 0);
        s.final_state = "fault".into();
        assert_eq!(exit_code(&s, Ending::Interrupted, false, None), 1);
    }
}
