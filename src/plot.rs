//! PNG plots from recordings.
//!
//! [`plot_recording`] reads an MCAP file written by [`crate::record::McapRecorder`] and draws
//! the figures the papers use to judge a run:
//!
//! | file | content | model |
//! |---|---|---|
//! | `xy_path.png` | reference, estimated and true path; footprint snapshots; ICR in the world | seed 000 Fig. 7 |
//! | `tracking_errors.png` | e_ξ = ξ* − ξ (top) and e_λ = λ* − λ (bottom) over time | seed 000 Fig. 8 |
//! | `commands.png` | commanded wheel spin rates ω_i (top) and steering rates v_φi (bottom) | seed 000 Fig. 9 |
//! | `icr_body.png` | ICR trajectory in the body frame, wheel contact points, potential fields | seed 001 |
//! | `timing.png` | histograms of cycle period and compute time | — |
//!
//! Which data each figure uses:
//!
//! * Time axes are the messages' log times relative to the earliest cycle message, in s.
//! * Messages of one cycle are joined by their `cycle` field, not by time.
//! * Tracking errors compare the reference actually tracked (`/reference` `z`, i.e. nominal
//!   plus avoidance deviation) with the true pose and legs when the run was simulated
//!   (`/pose` `true_*`), else with the estimated pose and the measured legs (`/feedback`).
//!   The heading error is wrapped with [`rollbase_control::angle::diff`].
//! * Footprints are the wheel contact points of `/icr` (`wheel_x`, `wheel_y`, body frame)
//!   mapped to the world by the pose of the same cycle (true pose when present):
//!   `p_world = (x, y) + R(θ)·p_body`. The ICR is mapped the same way when it is finite.
//! * The potential fields of seed 001 are circles of radius `d_start` around each contact
//!   point; they are drawn at the cycle where the ICR came closest to a wheel.
//!
//! Labels need a TrueType font (the `ab_glyph` text backend of `plotters` has none built in).
//! One is looked up at run time ([`font_path`]): `$ROLLBASE_FONT`, then the usual
//! DejaVu/Liberation/Noto locations of Debian, Fedora and Arch. Without one the figures are
//! still drawn, with no text at all, and [`PlotReport::labelled`] is `false` (print
//! [`FONT_HINT`]).
//!
//! Non-finite and missing values are tolerated everywhere: lines are broken at them, ranges
//! ignore them. Values beyond ±[`ABSURD`] are left out the same way and named in
//! [`PlotReport::ignored`] (a damaged or meaningless value must neither stretch a figure to
//! nothing nor crash the plotting library). The recording is read with its chunk CRCs checked
//! ([`crate::record::read_recording`]): a damaged file is an error, not a plot of wrong data;
//! devices, pipes and files too large to load are refused before reading.

use crate::record::{read_recording, RecordError};
use plotters::coord::types::RangedCoordf64;
use plotters::coord::Shift;
use plotters::prelude::*;
use serde_json::Value;
use std::collections::HashMap;
use std::fmt::Display;
use std::path::{Path, PathBuf};
use std::sync::OnceLock;

/// Width of every figure (pixels).
pub const WIDTH: u32 = 1200;
/// Height of every figure (pixels).
pub const HEIGHT: u32 = 800;

/// Hint to print when [`PlotReport::labelled`] is `false`.
pub const FONT_HINT: &str =
    "plots have no text: install fonts-dejavu-core or set ROLLBASE_FONT=/path/to/font.ttf for labelled plots";

/// Font family name the TTF is registered under. Deliberately not `"sans-serif"` (the
/// default of `plotters` text styles), so any text drawn without going through [`Style`] fails
/// loudly in the unlabelled tests instead of silently using the font.
const FAMILY: &str = "rollbase-sans";

/// Standard locations of a sans TrueType font on Debian/Ubuntu, Fedora and Arch.
const FONT_CANDIDATES: [&str; 11] = [
    "/usr/share/fonts/truetype/dejavu/DejaVuSans.ttf",
    "/usr/share/fonts/dejavu-sans-fonts/DejaVuSans.ttf",
    "/usr/share/fonts/dejavu/DejaVuSans.ttf",
    "/usr/share/fonts/TTF/DejaVuSans.ttf",
    "/usr/share/fonts/truetype/liberation/LiberationSans-Regular.ttf",
    "/usr/share/fonts/liberation-sans/LiberationSans-Regular.ttf",
    "/usr/share/fonts/liberation/LiberationSans-Regular.ttf",
    "/usr/share/fonts/truetype/noto/NotoSans-Regular.ttf",
    "/usr/share/fonts/noto/NotoSans-Regular.ttf",
    "/usr/share/fonts/google-noto/NotoSans-Regular.ttf",
    "/usr/share/fonts/truetype/freefont/FreeSans.ttf",
];

/// Errors of [`plot_recording`].
#[derive(Debug, thiserror::Error)]
pub enum PlotError {
    /// The recording could not be read (missing file, not MCAP, corrupt, not JSON).
    #[error(transparent)]
    Record(#[from] RecordError),
    /// A topic every plot needs has no messages.
    #[error(
        "plotting {path}: recording has no {topic} messages; pass an MCAP file recorded by rollbase"
    )]
    MissingTopic {
        /// The recording.
        path: String,
        /// The topic without messages.
        topic: &'static str,
    },
    /// The output directory could not be created.
    #[error("plotting {path}: cannot create output directory {dir}: {source}; pick a writable --out directory")]
    OutputDir {
        /// The recording.
        path: String,
        /// The output directory.
        dir: String,
        /// Underlying error.
        source: std::io::Error,
    },
    /// Drawing or writing one figure failed.
    #[error("plotting {path}: drawing {file} failed: {message}")]
    Draw {
        /// The recording.
        path: String,
        /// The PNG being drawn.
        file: String,
        /// What the plotting library reported.
        message: String,
    },
}

/// What [`plot_recording`] produced.
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct PlotReport {
    /// The PNG files written, in the order of the module table.
    pub files: Vec<PathBuf>,
    /// Whether a font was found and the figures have titles, axis labels and legends.
    pub labelled: bool,
    /// Figures not drawn because the recording lacks their data, as "file: reason".
    pub skipped: Vec<String>,
    /// Values left out because they are absurd (beyond ±[`ABSURD`]), one line per topic and
    /// field naming the first such value and its cycle.
    pub ignored: Vec<String>,
}

/// Largest magnitude a plotted value may have (m, rad, s, rad/s, µs): beyond it a value is
/// damaged or meaningless, is left out of the figures and reported in
/// [`PlotReport::ignored`].
pub const ABSURD: f64 = 1e9;

/// The TrueType font registered for labels, if one was found (looked up once per process:
/// `$ROLLBASE_FONT`, then standard Debian/Fedora/Arch paths). A file that exists but is not a
/// valid font is passed over.
pub fn font_path() -> Option<&'static Path> {
    static FONT: OnceLock<Option<PathBuf>> = OnceLock::new();
    FONT.get_or_init(|| {
        let env = std::env::var_os("ROLLBASE_FONT").map(PathBuf::from);
        let candidates = env
            .into_iter()
            .chain(FONT_CANDIDATES.iter().map(PathBuf::from));
        for p in candidates {
            let Ok(bytes) = std::fs::read(&p) else {
                continue;
            };
            // `register_font` needs `'static` bytes; this leaks one font file once per process.
            let bytes: &'static [u8] = Box::leak(bytes.into_boxed_slice());
            if plotters::style::register_font(FAMILY, FontStyle::Normal, bytes).is_ok() {
                return Some(p);
            }
        }
        None
    })
    .as_deref()
}

/// Draws the figures of the module table from the recording `mcap` into `out_dir` (created
/// if missing). Needs `/pose` messages; other figures are skipped (and listed in
/// [`PlotReport::skipped`]) when their topic is empty.
pub fn plot_recording(mcap: &Path, out_dir: &Path) -> Result<PlotReport, PlotError> {
    let style = Style {
        family: font_path().map(|_| FAMILY),
    };
    plot_with_style(mcap, out_dir, style)
}

fn plot_with_style(mcap: &Path, out_dir: &Path, style: Style) -> Result<PlotReport, PlotError> {
    let src = mcap.display().to_string();
    let msgs = read_recording(mcap)?;
    let (data, ignored) = Data::parse(&msgs);
    if data.pose.is_empty() {
        return Err(PlotError::MissingTopic {
            path: src,
            topic: "/pose",
        });
    }
    std::fs::create_dir_all(out_dir).map_err(|source| PlotError::OutputDir {
        path: src.clone(),
        dir: out_dir.display().to_string(),
        source,
    })?;
    let mut report = PlotReport {
        files: Vec::new(),
        labelled: style.family.is_some(),
        skipped: Vec::new(),
        ignored,
    };
    type Figure = fn(&Data, &Style, &Ctx) -> Result<(), PlotError>;
    let figures: [(&str, Option<&str>, Figure); 5] = [
        ("xy_path.png", None, xy_path),
        ("tracking_errors.png", Some("/reference"), tracking_errors),
        ("commands.png", Some("/command"), commands),
        ("icr_body.png", Some("/icr"), icr_body),
        ("timing.png", Some("/timing"), timing),
    ];
    for (name, needs, draw) in figures {
        let empty = match needs {
            Some("/reference") => data.reference.is_empty(),
            Some("/command") => data.command.is_empty(),
            Some("/icr") => data.icr.is_empty(),
            Some("/timing") => data.timing.is_empty(),
            _ => false,
        };
        if let (true, Some(topic)) = (empty, needs) {
            report
                .skipped
                .push(format!("{name}: recording has no {topic} messages"));
            continue;
        }
        let file = out_dir.join(name);
        let ctx = Ctx {
            src: src.clone(),
            file: file.clone(),
        };
        // The data are validated before drawing; should the plotting library still panic on
        // some input, the figure fails with an error instead of the process.
        let drawn =
            std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| draw(&data, &style, &ctx)));
        match drawn {
            Ok(r) => r?,
            Err(p) => {
                let what = p
                    .downcast_ref::<&str>()
                    .map(|s| s.to_string())
                    .or_else(|| p.downcast_ref::<String>().cloned())
                    .unwrap_or_else(|| "unknown panic".into());
                return Err(ctx.err(format!("the plotting library failed: {what}")));
            }
        }
        report.files.push(file);
    }
    Ok(report)
}

// ---------------------------------------------------------------------------------------------
// Data extraction
// ---------------------------------------------------------------------------------------------

/// Collects absurd values per (topic, field): count, first cycle, first value.
#[derive(Default)]
struct Problems(std::collections::BTreeMap<(String, String), (u64, Option<u64>, f64)>);

impl Problems {
    /// `x` if it is missing (NaN), infinite (as recorded for "none") or plausible, else NaN
    /// and the value is noted.
    fn check(&mut self, topic: &str, key: &str, cycle: Option<u64>, x: f64) -> f64 {
        if x.is_finite() && x.abs() > ABSURD {
            let e = self
                .0
                .entry((topic.to_string(), key.to_string()))
                .or_insert((0, cycle, x));
            e.0 += 1;
            f64::NAN
        } else {
            x
        }
    }

    fn lines(self) -> Vec<String> {
        self.0
            .into_iter()
            .map(|((topic, key), (n, cycle, x))| {
                let at = cycle
                    .map(|c| format!("cycle {c}"))
                    .unwrap_or("a message".into());
                format!(
                    "{topic} {key}: {n} value(s) beyond ±{ABSURD:e} left out (first at {at}: {x:e})"
                )
            })
            .collect()
    }
}

/// A field's number, checked; JSON null and a missing field are NaN.
struct Fields<'a> {
    topic: &'a str,
    v: &'a Value,
    cycle: Option<u64>,
}

impl Fields<'_> {
    fn num(&self, p: &mut Problems, key: &str) -> f64 {
        let x = self.v.get(key).and_then(Value::as_f64).unwrap_or(f64::NAN);
        p.check(self.topic, key, self.cycle, x)
    }

    fn nums(&self, p: &mut Problems, key: &str) -> Vec<f64> {
        self.v
            .get(key)
            .and_then(Value::as_array)
            .map(|a| {
                a.iter()
                    .map(|x| {
                        let x = x.as_f64().unwrap_or(f64::NAN);
                        p.check(self.topic, key, self.cycle, x)
                    })
                    .collect()
            })
            .unwrap_or_default()
    }
}

fn cycle_of(v: &Value) -> Option<u64> {
    v.get("cycle").and_then(Value::as_u64)
}

fn at(xs: &[f64], i: usize) -> f64 {
    xs.get(i).copied().unwrap_or(f64::NAN)
}

struct PoseRow {
    t: f64,
    cycle: Option<u64>,
    est: [f64; 3],
    truth: [f64; 3],
    true_legs: Vec<f64>,
}

struct RefRow {
    z: Vec<f64>,
}

struct CmdRow {
    t: f64,
    mode: String,
    wheel_speed: Vec<f64>,
    steer_rate: Vec<f64>,
}

struct IcrRow {
    t: f64,
    icr: [f64; 2],
    active: bool,
    min_distance: f64,
    d_start: Vec<f64>,
    wheel_x: Vec<f64>,
    wheel_y: Vec<f64>,
}

struct TimingRow {
    period_us: f64,
    compute_us: f64,
    deadline_miss: bool,
}

/// The cycle topics of one recording, as rows sorted by time.
struct Data {
    pose: Vec<PoseRow>,
    reference: Vec<RefRow>,
    reference_by_cycle: HashMap<u64, usize>,
    feedback_legs: HashMap<u64, Vec<f64>>,
    command: Vec<CmdRow>,
    icr: Vec<IcrRow>,
    icr_by_cycle: HashMap<u64, usize>,
    timing: Vec<TimingRow>,
    /// Whether any `/pose` message carries a finite true pose.
    has_truth: bool,
}

const CYCLE_TOPICS: [&str; 6] = [
    "/feedback",
    "/reference",
    "/command",
    "/pose",
    "/icr",
    "/timing",
];

impl Data {
    fn parse(msgs: &[(String, u64, Value)]) -> (Self, Vec<String>) {
        let t0 = msgs
            .iter()
            .filter(|(topic, _, _)| CYCLE_TOPICS.contains(&topic.as_str()))
            .map(|(_, t, _)| *t)
            .min()
            .unwrap_or(0);
        let mut d = Data {
            pose: Vec::new(),
            reference: Vec::new(),
            reference_by_cycle: HashMap::new(),
            feedback_legs: HashMap::new(),
            command: Vec::new(),
            icr: Vec::new(),
            icr_by_cycle: HashMap::new(),
            timing: Vec::new(),
            has_truth: false,
        };
        let mut p = Problems::default();
        for (topic, log_ns, v) in msgs {
            let t = log_ns.saturating_sub(t0) as f64 * 1e-9;
            let f = Fields {
                topic,
                v,
                cycle: cycle_of(v),
            };
            match topic.as_str() {
                "/pose" => {
                    let truth = [
                        f.num(&mut p, "true_x"),
                        f.num(&mut p, "true_y"),
                        f.num(&mut p, "true_theta"),
                    ];
                    d.has_truth |= truth[0].is_finite() && truth[1].is_finite();
                    d.pose.push(PoseRow {
                        t,
                        cycle: f.cycle,
                        est: [
                            f.num(&mut p, "x"),
                            f.num(&mut p, "y"),
                            f.num(&mut p, "theta"),
                        ],
                        truth,
                        true_legs: f.nums(&mut p, "true_legs"),
                    });
                }
                "/reference" => {
                    if let Some(c) = f.cycle {
                        d.reference_by_cycle.insert(c, d.reference.len());
                    }
                    d.reference.push(RefRow {
                        z: f.nums(&mut p, "z"),
                    });
                }
                "/feedback" => {
                    if let (Some(c), Some(ws)) =
                        (f.cycle, v.get("wheels").and_then(Value::as_array))
                    {
                        let legs = ws
                            .iter()
                            .map(|w| {
                                Fields {
                                    topic,
                                    v: w,
                                    cycle: Some(c),
                                }
                                .num(&mut p, "leg")
                            })
                            .collect();
                        d.feedback_legs.insert(c, legs);
                    }
                }
                "/command" => d.command.push(CmdRow {
                    t,
                    mode: v
                        .get("mode")
                        .and_then(Value::as_str)
                        .unwrap_or("?")
                        .to_string(),
                    wheel_speed: f.nums(&mut p, "wheel_speed"),
                    steer_rate: f.nums(&mut p, "steer_rate"),
                }),
                "/icr" => {
                    if let Some(c) = f.cycle {
                        d.icr_by_cycle.insert(c, d.icr.len());
                    }
                    let at_inf = v
                        .get("at_infinity")
                        .and_then(Value::as_bool)
                        .unwrap_or(false);
                    let icr = if at_inf {
                        [f64::NAN; 2]
                    } else {
                        [f.num(&mut p, "icr_x"), f.num(&mut p, "icr_y")]
                    };
                    d.icr.push(IcrRow {
                        t,
                        icr,
                        active: v.get("active").and_then(Value::as_bool).unwrap_or(false),
                        min_distance: f.num(&mut p, "min_distance"),
                        d_start: f.nums(&mut p, "d_start"),
                        wheel_x: f.nums(&mut p, "wheel_x"),
                        wheel_y: f.nums(&mut p, "wheel_y"),
                    });
                }
                "/timing" => d.timing.push(TimingRow {
                    period_us: f.num(&mut p, "period_us"),
                    compute_us: f.num(&mut p, "compute_us"),
                    deadline_miss: v
                        .get("deadline_miss")
                        .and_then(Value::as_bool)
                        .unwrap_or(false),
                }),
                _ => {}
            }
        }
        // MCAP stream order is the file order; one writer writes in time order, but be safe.
        d.pose.sort_by(|a, b| a.t.total_cmp(&b.t));
        d.command.sort_by(|a, b| a.t.total_cmp(&b.t));
        (d, p.lines())
    }

    /// The pose a figure should show for a row: true when the run has truth, else estimated.
    fn shown_pose(&self, p: &PoseRow) -> [f64; 3] {
        if self.has_truth {
            p.truth
        } else {
            p.est
        }
    }

    fn icr_row(&self, cycle: Option<u64>) -> Option<&IcrRow> {
        cycle
            .and_then(|c| self.icr_by_cycle.get(&c))
            .and_then(|&i| self.icr.get(i))
    }
}

// ---------------------------------------------------------------------------------------------
// Geometry and ranges
// ---------------------------------------------------------------------------------------------

/// Body → world: `(x, y) + R(θ)·p`.
fn to_world(pose: [f64; 3], p: [f64; 2]) -> (f64, f64) {
    let (s, c) = pose[2].sin_cos();
    (pose[0] + c * p[0] - s * p[1], pose[1] + s * p[0] + c * p[1])
}

/// Finite wheel contact points of an `/icr` row, ordered by angle around their centroid so
/// they form a simple polygon whatever the wheel numbering.
fn footprint(row: &IcrRow) -> Vec<[f64; 2]> {
    let mut pts: Vec<[f64; 2]> = row
        .wheel_x
        .iter()
        .zip(row.wheel_y.iter())
        .filter(|(x, y)| x.is_finite() && y.is_finite())
        .map(|(&x, &y)| [x, y])
        .collect();
    if pts.is_empty() {
        return pts;
    }
    let k = pts.len() as f64;
    let cx = pts.iter().map(|p| p[0]).sum::<f64>() / k;
    let cy = pts.iter().map(|p| p[1]).sum::<f64>() / k;
    pts.sort_by(|a, b| {
        (a[1] - cy)
            .atan2(a[0] - cx)
            .total_cmp(&(b[1] - cy).atan2(b[0] - cx))
    });
    pts
}

/// Values beyond this magnitude are treated as non-finite: no plotted quantity (m, rad, s,
/// rad/s, µs) is legitimately that large, and they would overflow the range arithmetic.
const HUGE: f64 = 1e12;

/// Range of the finite values, padded by 5 % (a zero-width range is widened).
fn range(values: impl IntoIterator<Item = f64>) -> (f64, f64) {
    let (mut lo, mut hi) = (f64::INFINITY, f64::NEG_INFINITY);
    for v in values.into_iter().filter(|v| v.abs() < HUGE) {
        lo = lo.min(v);
        hi = hi.max(v);
    }
    if lo > hi {
        return (-1.0, 1.0);
    }
    let span = hi - lo;
    let pad = if span > 1e-12 * lo.abs().max(hi.abs()).max(1e-300) {
        0.05 * span
    } else {
        (0.05 * lo.abs()).max(1e-3)
    };
    (lo - pad, hi + pad)
}

/// Widens one of two ranges so one data unit has the same length in pixels on both axes.
fn equal_aspect(x: (f64, f64), y: (f64, f64), px: (u32, u32)) -> ((f64, f64), (f64, f64)) {
    let (w, h) = (px.0.max(1) as f64, px.1.max(1) as f64);
    let (sx, sy) = ((x.1 - x.0) / w, (y.1 - y.0) / h);
    if sx > sy {
        let c = 0.5 * (y.0 + y.1);
        let half = 0.5 * sx * h;
        (x, (c - half, c + half))
    } else {
        let c = 0.5 * (x.0 + x.1);
        let half = 0.5 * sy * w;
        ((c - half, c + half), y)
    }
}

fn inside(p: (f64, f64), x: (f64, f64), y: (f64, f64)) -> bool {
    p.0 >= x.0 && p.0 <= x.1 && p.1 >= y.0 && p.1 <= y.1
}

/// Splits a polyline into runs of points that are finite and inside the ranges.
fn segments(
    pts: impl IntoIterator<Item = (f64, f64)>,
    x: (f64, f64),
    y: (f64, f64),
) -> Vec<Vec<(f64, f64)>> {
    let mut out: Vec<Vec<(f64, f64)>> = Vec::new();
    let mut cur = Vec::new();
    for p in pts {
        if p.0.is_finite() && p.1.is_finite() && inside(p, x, y) {
            cur.push(p);
        } else if !cur.is_empty() {
            out.push(std::mem::take(&mut cur));
        }
    }
    if !cur.is_empty() {
        out.push(cur);
    }
    out
}

/// Points of a circle (for data-space circles, which `plotters` only has in pixels).
fn circle(c: (f64, f64), r: f64) -> Vec<(f64, f64)> {
    (0..=72)
        .map(|k| {
            let a = k as f64 * std::f64::consts::TAU / 72.0;
            (c.0 + r * a.cos(), c.1 + r * a.sin())
        })
        .collect()
}

/// A "nice" snapshot interval giving at most `max` snapshots over `duration` seconds.
fn snapshot_interval(duration: f64, max: f64) -> f64 {
    const STEPS: [f64; 12] = [
        0.1, 0.2, 0.5, 1.0, 2.0, 5.0, 10.0, 20.0, 30.0, 60.0, 120.0, 300.0,
    ];
    if !duration.is_finite() || duration <= 0.0 {
        return 1.0;
    }
    STEPS
        .iter()
        .copied()
        .find(|s| duration / s <= max)
        .unwrap_or((duration / max).ceil())
}

// ---------------------------------------------------------------------------------------------
// Drawing helpers
// ---------------------------------------------------------------------------------------------

/// Text settings: `family` is `None` when no font is available, then no text is drawn.
#[derive(Clone, Copy)]
struct Style {
    family: Option<&'static str>,
}

impl Style {
    fn text(&self, size: f64) -> Option<TextStyle<'static>> {
        self.family
            .map(|f| TextStyle::from((f, size).into_font()).color(&BLACK))
    }
}

/// Where a figure comes from and goes to, for error messages.
struct Ctx {
    src: String,
    file: PathBuf,
}

impl Ctx {
    fn err<E: Display>(&self, e: E) -> PlotError {
        PlotError::Draw {
            path: self.src.clone(),
            file: self.file.display().to_string(),
            message: e.to_string(),
        }
    }
}

const COLORS: [RGBColor; 8] = [
    RGBColor(31, 119, 180),
    RGBColor(214, 39, 40),
    RGBColor(44, 160, 44),
    RGBColor(255, 127, 14),
    RGBColor(148, 103, 189),
    RGBColor(140, 86, 75),
    RGBColor(227, 119, 194),
    RGBColor(23, 190, 207),
];

fn color(i: usize) -> RGBColor {
    COLORS[i % COLORS.len()]
}

type Chart<'a, DB> = ChartContext<'a, DB, Cartesian2d<RangedCoordf64, RangedCoordf64>>;

/// Label area sizes (x axis, y axis) in pixels: zero when there is no text.
fn label_areas(style: &Style) -> (u32, u32) {
    if style.family.is_some() {
        (45, 75)
    } else {
        (0, 0)
    }
}

const MARGIN: u32 = 15;

/// The drawing area below the figure title (the whole area when unlabelled).
fn titled<DB: DrawingBackend>(
    root: &DrawingArea<DB, Shift>,
    style: &Style,
    title: &str,
    ctx: &Ctx,
) -> Result<DrawingArea<DB, Shift>, PlotError> {
    match style.text(26.0) {
        Some(t) => root.titled(title, t).map_err(|e| ctx.err(e)),
        None => Ok(root.clone()),
    }
}

/// Pixel size of the plotting area a [`chart`] on `area` will have.
fn plot_pixels<DB: DrawingBackend>(area: &DrawingArea<DB, Shift>, style: &Style) -> (u32, u32) {
    let (w, h) = area.dim_in_pixel();
    let (xl, yl) = label_areas(style);
    (
        w.saturating_sub(2 * MARGIN + yl),
        h.saturating_sub(2 * MARGIN + xl),
    )
}

/// Tick label format for an axis range: enough decimals for about ten ticks, and values
/// that are zero up to rounding shown as "0" (not "-0.0").
fn tick_format(r: (f64, f64)) -> impl Fn(&f64) -> String {
    let span = (r.1 - r.0).abs();
    let step = span / 10.0;
    let decimals = if step.is_finite() && step > 0.0 {
        (-step.log10().floor()).clamp(0.0, 12.0) as usize
    } else {
        1
    };
    move |v: &f64| {
        let v = if v.abs() <= 1e-9 * span { 0.0 } else { *v };
        let s = format!("{v:.decimals$}");
        if s.starts_with('-') && s[1..].chars().all(|c| c == '0' || c == '.') {
            s[1..].to_string()
        } else {
            s
        }
    }
}

/// A cartesian chart with mesh and (when labelled) axis descriptions.
/// Ranges and descriptions of a chart's axes.
struct Axes<'s> {
    x: (f64, f64),
    y: (f64, f64),
    x_desc: &'s str,
    y_desc: &'s str,
    /// Counts on the y axis: integer tick labels.
    integer_y: bool,
}

fn axes<'s>(x: (f64, f64), y: (f64, f64), x_desc: &'s str, y_desc: &'s str) -> Axes<'s> {
    Axes {
        x,
        y,
        x_desc,
        y_desc,
        integer_y: false,
    }
}

fn chart<'a, DB: DrawingBackend>(
    area: &'a DrawingArea<DB, Shift>,
    style: &Style,
    ax: Axes<'_>,
    ctx: &Ctx,
) -> Result<Chart<'a, DB>, PlotError> {
    let (xl, yl) = label_areas(style);
    let mut c = ChartBuilder::on(area)
        .margin(MARGIN)
        .x_label_area_size(xl)
        .y_label_area_size(yl)
        .build_cartesian_2d(ax.x.0..ax.x.1, ax.y.0..ax.y.1)
        .map_err(|e| ctx.err(e))?;
    let mut mesh = c.configure_mesh();
    mesh.light_line_style(RGBColor(245, 245, 245))
        .bold_line_style(RGBColor(205, 205, 205));
    let (fx, fy) = (tick_format(ax.x), tick_format(ax.y));
    let integer = |v: &f64| format!("{v:.0}");
    mesh.x_label_formatter(&fx);
    if ax.integer_y {
        mesh.y_label_formatter(&integer);
    } else {
        mesh.y_label_formatter(&fy);
    }
    if let (Some(label), Some(desc)) = (style.text(15.0), style.text(17.0)) {
        mesh.label_style(label)
            .axis_desc_style(desc)
            .x_desc(ax.x_desc)
            .y_desc(ax.y_desc);
    }
    mesh.draw().map_err(|e| ctx.err(e))?;
    Ok(c)
}

/// Draws a polyline broken at non-finite points; labels the first segment for the legend.
fn line<'a, DB: DrawingBackend + 'a>(
    c: &mut Chart<'a, DB>,
    pts: impl IntoIterator<Item = (f64, f64)>,
    st: ShapeStyle,
    label: Option<&str>,
    ctx: &Ctx,
) -> Result<(), PlotError> {
    let (xr, yr) = (c.x_range(), c.y_range());
    let segs = segments(pts, (xr.start, xr.end), (yr.start, yr.end));
    for (k, seg) in segs.into_iter().enumerate() {
        let ann = c
            .draw_series(LineSeries::new(seg, st))
            .map_err(|e| ctx.err(e))?;
        if let (0, Some(l)) = (k, label) {
            ann.label(l)
                .legend(move |(x, y)| PathElement::new(vec![(x, y), (x + 24, y)], st));
        }
    }
    Ok(())
}

/// Draws the legend when labelled and some series has a label.
fn legend<'a, DB: DrawingBackend + 'a>(
    c: &mut Chart<'a, DB>,
    style: &Style,
    pos: SeriesLabelPosition,
    ctx: &Ctx,
) -> Result<(), PlotError> {
    if let Some(t) = style.text(15.0) {
        c.configure_series_labels()
            .label_font(t)
            .position(pos)
            .background_style(WHITE.mix(0.85))
            .border_style(BLACK)
            .draw()
            .map_err(|e| ctx.err(e))?;
    }
    Ok(())
}

fn finish<DB: DrawingBackend>(root: &DrawingArea<DB, Shift>, ctx: &Ctx) -> Result<(), PlotError> {
    root.present().map_err(|e| ctx.err(e))
}

// ---------------------------------------------------------------------------------------------
// Figures
// ---------------------------------------------------------------------------------------------

/// One footprint snapshot in the world: contact point polygon and the ICR when finite.
struct Snapshot {
    poly: Vec<(f64, f64)>,
    icr: Option<(f64, f64)>,
}

/// Seed 000 Fig. 7: stroboscopic view of the motion with the ICR.
fn xy_path(d: &Data, style: &Style, ctx: &Ctx) -> Result<(), PlotError> {
    let root = BitMapBackend::new(&ctx.file, (WIDTH, HEIGHT)).into_drawing_area();
    root.fill(&WHITE).map_err(|e| ctx.err(e))?;
    let which = if d.has_truth { "true" } else { "estimated" };
    let area = titled(
        &root,
        style,
        &format!("XY path with footprints ({which} pose) and ICR"),
        ctx,
    )?;

    // Snapshots: footprint polygons in the world, and the ICR when finite.
    let t_end = d.pose.last().map(|p| p.t).unwrap_or(0.0);
    let t_start = d.pose.first().map(|p| p.t).unwrap_or(0.0);
    let dt = snapshot_interval(t_end - t_start, 12.0);
    let mut shots: Vec<Snapshot> = Vec::new();
    let mut next = t_start;
    for (k, p) in d.pose.iter().enumerate() {
        let last = k + 1 == d.pose.len();
        if p.t < next && !last {
            continue;
        }
        next = p.t + dt;
        let pose = d.shown_pose(p);
        let Some(row) = d.icr_row(p.cycle) else {
            continue;
        };
        if !pose.iter().all(|v| v.is_finite()) {
            continue;
        }
        let poly: Vec<(f64, f64)> = footprint(row)
            .into_iter()
            .map(|b| to_world(pose, b))
            .collect();
        let icr = row
            .icr
            .iter()
            .all(|v| v.is_finite())
            .then(|| to_world(pose, row.icr));
        shots.push(Snapshot { poly, icr });
    }

    let refs: Vec<(f64, f64)> = d
        .reference
        .iter()
        .map(|r| (at(&r.z, 0), at(&r.z, 1)))
        .collect();
    let est: Vec<(f64, f64)> = d.pose.iter().map(|p| (p.est[0], p.est[1])).collect();
    let tru: Vec<(f64, f64)> = if d.has_truth {
        d.pose.iter().map(|p| (p.truth[0], p.truth[1])).collect()
    } else {
        Vec::new()
    };
    let all_pts = || {
        refs.iter()
            .chain(est.iter())
            .chain(tru.iter())
            .chain(shots.iter().flat_map(|s| s.poly.iter()))
            .copied()
    };
    let (xr, yr) = equal_aspect(
        range(all_pts().map(|p| p.0)),
        range(all_pts().map(|p| p.1)),
        plot_pixels(&area, style),
    );
    let mut c = chart(&area, style, axes(xr, yr, "x (m)", "y (m)"), ctx)?;

    let gray = RGBColor(120, 120, 120);
    for (k, Snapshot { poly, .. }) in shots.iter().enumerate() {
        let mut closed = poly.clone();
        if let Some(&first) = poly.first() {
            closed.push(first);
        }
        line(
            &mut c,
            closed,
            gray.stroke_width(1),
            (k == 0).then_some("footprint (wheel contact points)"),
            ctx,
        )?;
        let dots: Vec<(f64, f64)> = poly
            .iter()
            .copied()
            .filter(|&p| inside(p, xr, yr))
            .collect();
        c.draw_series(dots.into_iter().map(|p| Circle::new(p, 3, gray.filled())))
            .map_err(|e| ctx.err(e))?;
    }
    if d.has_truth {
        line(
            &mut c,
            tru.iter().copied(),
            color(1).stroke_width(3),
            Some("true"),
            ctx,
        )?;
    }
    line(
        &mut c,
        est.iter().copied(),
        color(0).stroke_width(2),
        Some("estimated"),
        ctx,
    )?;
    line(
        &mut c,
        refs.iter().copied(),
        BLACK.stroke_width(1),
        Some("reference z*"),
        ctx,
    )?;
    let icrs: Vec<(f64, f64)> = shots
        .iter()
        .filter_map(|s| s.icr)
        .filter(|&p| inside(p, xr, yr))
        .collect();
    let any_icr = !icrs.is_empty();
    let ann = c
        .draw_series(icrs.into_iter().map(|p| Circle::new(p, 5, BLACK.filled())))
        .map_err(|e| ctx.err(e))?;
    if any_icr {
        ann.label("ICR at snapshot")
            .legend(|(x, y)| Circle::new((x + 12, y), 5, BLACK.filled()));
    }
    legend(&mut c, style, SeriesLabelPosition::UpperLeft, ctx)?;
    if let Some(t) = style.text(15.0) {
        let note = format!("snapshots every {dt} s");
        root.draw_text(
            &note,
            &t,
            (WIDTH as i32 - 220, HEIGHT as i32 - 2 * MARGIN as i32 - 50),
        )
        .map_err(|e| ctx.err(e))?;
    }
    finish(&root, ctx)
}

/// Seed 000 Fig. 8: e_ξ(t) (top) and e_λ(t) (bottom).
fn tracking_errors(d: &Data, style: &Style, ctx: &Ctx) -> Result<(), PlotError> {
    let root = BitMapBackend::new(&ctx.file, (WIDTH, HEIGHT)).into_drawing_area();
    root.fill(&WHITE).map_err(|e| ctx.err(e))?;
    let vs = if d.has_truth {
        "true pose and legs"
    } else {
        "estimated pose, measured legs"
    };
    let area = titled(
        &root,
        style,
        &format!("Tracking errors e = z* − z (z from {vs})"),
        ctx,
    )?;
    let panels = area.split_evenly((2, 1));

    let legs = d
        .reference
        .iter()
        .map(|r| r.z.len().saturating_sub(3))
        .max()
        .unwrap_or(0);
    let mut exi: [Vec<(f64, f64)>; 3] = Default::default();
    let mut elam: Vec<Vec<(f64, f64)>> = vec![Vec::new(); legs];
    for p in &d.pose {
        let Some(r) = p
            .cycle
            .and_then(|c| d.reference_by_cycle.get(&c))
            .and_then(|&i| d.reference.get(i))
        else {
            continue;
        };
        let q = d.shown_pose(p);
        exi[0].push((p.t, at(&r.z, 0) - q[0]));
        exi[1].push((p.t, at(&r.z, 1) - q[1]));
        exi[2].push((p.t, rollbase_control::angle::diff(at(&r.z, 2), q[2])));
        let fb = p.cycle.and_then(|c| d.feedback_legs.get(&c));
        for (i, e) in elam.iter_mut().enumerate() {
            let truth = at(&p.true_legs, i);
            // One source per figure: truth when the run has it (gaps where a cycle lacks it).
            let leg = if d.has_truth {
                truth
            } else {
                fb.map(|f| at(f, i)).unwrap_or(f64::NAN)
            };
            e.push((p.t, at(&r.z, 3 + i) - leg));
        }
    }
    let tr = range(d.pose.iter().map(|p| p.t));
    let tr = (
        tr.0.max(d.pose.first().map(|p| p.t).unwrap_or(0.0) - 1e-9),
        tr.1,
    );

    let yr = range(exi.iter().flatten().map(|p| p.1));
    let mut c = chart(
        &panels[0],
        style,
        axes(tr, yr, "t (s)", "e_ξ (m, rad)"),
        ctx,
    )?;
    for (k, (pts, name)) in exi
        .iter()
        .zip(["e_x (m)", "e_y (m)", "e_θ (rad)"])
        .enumerate()
    {
        line(
            &mut c,
            pts.iter().copied(),
            color(k).stroke_width(2),
            Some(name),
            ctx,
        )?;
    }
    legend(&mut c, style, SeriesLabelPosition::UpperRight, ctx)?;

    let yr = range(elam.iter().flatten().map(|p| p.1));
    let mut c = chart(&panels[1], style, axes(tr, yr, "t (s)", "e_λ (m)"), ctx)?;
    for (i, pts) in elam.iter().enumerate() {
        let name = format!("e_λ{}", i + 1);
        line(
            &mut c,
            pts.iter().copied(),
            color(i).stroke_width(2),
            Some(&name),
            ctx,
        )?;
    }
    legend(&mut c, style, SeriesLabelPosition::UpperRight, ctx)?;
    finish(&root, ctx)
}

/// Seed 000 Fig. 9: commanded wheel spin rates and steering rates, with mode changes.
fn commands(d: &Data, style: &Style, ctx: &Ctx) -> Result<(), PlotError> {
    let root = BitMapBackend::new(&ctx.file, (WIDTH, HEIGHT)).into_drawing_area();
    root.fill(&WHITE).map_err(|e| ctx.err(e))?;
    let area = titled(
        &root,
        style,
        "Commanded wheel speeds and steering rates",
        ctx,
    )?;
    let panels = area.split_evenly((2, 1));
    let n = d
        .command
        .iter()
        .map(|r| r.wheel_speed.len().max(r.steer_rate.len()))
        .max()
        .unwrap_or(0);
    let changes: Vec<(f64, &str)> = d
        .command
        .windows(2)
        .filter(|w| w[0].mode != w[1].mode)
        .map(|w| (w[1].t, w[1].mode.as_str()))
        .collect();
    let tr = range(d.command.iter().map(|r| r.t));
    type Field = fn(&CmdRow) -> &Vec<f64>;
    let fields: [(Field, &str, &str); 2] = [
        (|r| &r.wheel_speed, "ω (rad/s)", "ω"),
        (|r| &r.steer_rate, "v_φ (rad/s)", "v_φ"),
    ];
    for (panel, (field, desc, sym)) in panels.iter().zip(fields) {
        let yr = range(d.command.iter().flat_map(|r| field(r).iter().copied()));
        let mut c = chart(panel, style, axes(tr, yr, "t (s)", desc), ctx)?;
        for (k, (t, mode)) in changes.iter().enumerate() {
            line(
                &mut c,
                [(*t, yr.0), (*t, yr.1)],
                RGBColor(150, 150, 150).stroke_width(1),
                (k == 0).then_some("mode change"),
                ctx,
            )?;
            if let Some(ts) = style.text(13.0) {
                c.draw_series(std::iter::once(Text::new(mode.to_string(), (*t, yr.1), ts)))
                    .map_err(|e| ctx.err(e))?;
            }
        }
        for i in 0..n {
            let pts = d.command.iter().map(|r| (r.t, at(field(r), i)));
            let name = format!("{sym}{}", i + 1);
            line(&mut c, pts, color(i).stroke_width(2), Some(&name), ctx)?;
        }
        legend(&mut c, style, SeriesLabelPosition::LowerRight, ctx)?;
    }
    finish(&root, ctx)
}

/// Seed 001: the ICR in the body frame against the wheels' potential fields.
fn icr_body(d: &Data, style: &Style, ctx: &Ctx) -> Result<(), PlotError> {
    let root = BitMapBackend::new(&ctx.file, (WIDTH, HEIGHT)).into_drawing_area();
    root.fill(&WHITE).map_err(|e| ctx.err(e))?;

    // The cycle where the ICR came closest to a wheel (else the last with wheel points).
    let key = d
        .icr
        .iter()
        .enumerate()
        .filter(|(_, r)| r.min_distance.is_finite() && !footprint(r).is_empty())
        .min_by(|a, b| a.1.min_distance.total_cmp(&b.1.min_distance))
        .map(|(i, _)| i)
        .or_else(|| d.icr.iter().rposition(|r| !footprint(r).is_empty()));
    let title = match key.and_then(|i| d.icr.get(i)) {
        Some(r) if r.min_distance.is_finite() => format!(
            "ICR in the body frame; fields at t = {:.2} s (closest approach {:.3} m)",
            r.t, r.min_distance
        ),
        _ => "ICR in the body frame and potential fields".to_string(),
    };
    let area = titled(&root, style, &title, ctx)?;

    // Window: the platform with its fields, widened so the ICR near the platform is visible.
    let reach = d
        .icr
        .iter()
        .flat_map(|r| {
            r.wheel_x
                .iter()
                .zip(r.wheel_y.iter())
                .enumerate()
                .map(move |(i, (x, y))| x.hypot(*y) + at(&r.d_start, i).max(0.0))
        })
        .filter(|v| v.is_finite())
        .fold(0.0f64, f64::max);
    let half = if reach > 0.0 {
        (2.5 * reach).max(0.5)
    } else {
        2.0
    };
    let (xr, yr) = equal_aspect((-half, half), (-half, half), plot_pixels(&area, style));
    let mut c = chart(&area, style, axes(xr, yr, "x_B (m)", "y_B (m)"), ctx)?;

    // Wheel contact point traces (legs move).
    let n = d.icr.iter().map(|r| r.wheel_x.len()).max().unwrap_or(0);
    for i in 0..n {
        let pts = d.icr.iter().map(|r| (at(&r.wheel_x, i), at(&r.wheel_y, i)));
        line(&mut c, pts, color(i).mix(0.5).stroke_width(1), None, ctx)?;
    }
    // Platform outline, wheels and fields at the key cycle.
    if let Some(r) = key.and_then(|i| d.icr.get(i)) {
        let mut poly: Vec<(f64, f64)> = footprint(r).into_iter().map(|p| (p[0], p[1])).collect();
        if let Some(&first) = poly.first() {
            poly.push(first);
        }
        line(
            &mut c,
            poly,
            BLACK.stroke_width(1),
            Some("wheel contact points"),
            ctx,
        )?;
        let draw_fields = r.d_start.iter().any(|&v| v.is_finite() && v > 0.0);
        for i in 0..r.wheel_x.len() {
            let w = (at(&r.wheel_x, i), at(&r.wheel_y, i));
            if !(w.0.is_finite() && w.1.is_finite()) {
                continue;
            }
            if inside(w, xr, yr) {
                c.draw_series(std::iter::once(Circle::new(w, 6, color(i).filled())))
                    .map_err(|e| ctx.err(e))?;
            }
            let ds = at(&r.d_start, i);
            if draw_fields && ds.is_finite() && ds > 0.0 {
                let label = (i == 0).then_some("potential field (radius d_start)");
                line(&mut c, circle(w, ds), color(i).stroke_width(2), label, ctx)?;
            }
        }
        if r.icr.iter().all(|v| v.is_finite()) && inside((r.icr[0], r.icr[1]), xr, yr) {
            c.draw_series(std::iter::once(Cross::new(
                (r.icr[0], r.icr[1]),
                8,
                BLACK.stroke_width(2),
            )))
            .map_err(|e| ctx.err(e))?
            .label("ICR at that cycle")
            .legend(|(x, y)| Cross::new((x + 12, y), 6, BLACK.stroke_width(2)));
        }
    }
    // Body origin.
    c.draw_series(std::iter::once(Circle::new((0.0, 0.0), 3, BLACK.filled())))
        .map_err(|e| ctx.err(e))?;
    // ICR trajectory (broken where the ICR is at infinity or outside the window).
    line(
        &mut c,
        d.icr.iter().map(|r| (r.icr[0], r.icr[1])),
        RGBColor(60, 60, 60).stroke_width(2),
        Some("ICR trajectory"),
        ctx,
    )?;
    // Dots show where the ICR dwells (and isolated samples a line cannot show).
    let stride = d.icr.len() / 3000 + 1;
    let dots: Vec<(f64, f64)> = d
        .icr
        .iter()
        .step_by(stride)
        .map(|r| (r.icr[0], r.icr[1]))
        .filter(|&p| p.0.is_finite() && p.1.is_finite() && inside(p, xr, yr))
        .collect();
    c.draw_series(
        dots.into_iter()
            .map(|p| Circle::new(p, 2, RGBColor(60, 60, 60).filled())),
    )
    .map_err(|e| ctx.err(e))?;
    let active: Vec<(f64, f64)> = d
        .icr
        .iter()
        .filter(|r| r.active)
        .map(|r| (r.icr[0], r.icr[1]))
        .filter(|&p| p.0.is_finite() && p.1.is_finite() && inside(p, xr, yr))
        .collect();
    if !active.is_empty() {
        c.draw_series(active.into_iter().map(|p| Circle::new(p, 3, RED.filled())))
            .map_err(|e| ctx.err(e))?
            .label("ICR while avoidance active")
            .legend(|(x, y)| Circle::new((x + 12, y), 3, RED.filled()));
    }
    legend(&mut c, style, SeriesLabelPosition::UpperLeft, ctx)?;
    finish(&root, ctx)
}

fn median_and_max(v: &[f64]) -> (f64, f64) {
    let mut s: Vec<f64> = v.iter().copied().filter(|x| x.is_finite()).collect();
    if s.is_empty() {
        return (f64::NAN, f64::NAN);
    }
    s.sort_by(f64::total_cmp);
    (s[s.len() / 2], s[s.len() - 1])
}

/// Histograms of cycle period and compute time.
fn timing(d: &Data, style: &Style, ctx: &Ctx) -> Result<(), PlotError> {
    let root = BitMapBackend::new(&ctx.file, (WIDTH, HEIGHT)).into_drawing_area();
    root.fill(&WHITE).map_err(|e| ctx.err(e))?;
    let misses = d.timing.iter().filter(|r| r.deadline_miss).count();
    let area = titled(
        &root,
        style,
        &format!(
            "Cycle timing ({} cycles, {misses} deadline misses)",
            d.timing.len()
        ),
        ctx,
    )?;
    let panels = area.split_evenly((1, 2));
    let series: [(Vec<f64>, &str); 2] = [
        (
            d.timing.iter().map(|r| r.period_us).collect(),
            "cycle period",
        ),
        (
            d.timing.iter().map(|r| r.compute_us).collect(),
            "compute time",
        ),
    ];
    for (k, (panel, (vals, name))) in panels.iter().zip(series.iter()).enumerate() {
        const BINS: usize = 60;
        let (lo, hi) = range(vals.iter().copied());
        let width = (hi - lo) / BINS as f64;
        let mut counts = [0u64; BINS];
        for &v in vals.iter().filter(|v| v.is_finite()) {
            let b = ((v - lo) / width).floor();
            let b = if b.is_finite() && b > 0.0 {
                b as usize
            } else {
                0
            };
            counts[b.min(BINS - 1)] += 1;
        }
        let top = counts.iter().copied().max().unwrap_or(0).max(1) as f64 * 1.08;
        let desc = format!("{name} (µs)");
        let mut c = chart(
            panel,
            style,
            Axes {
                integer_y: true,
                ..axes((lo, hi), (0.0, top), &desc, "cycles")
            },
            ctx,
        )?;
        let col = color(k);
        let (median, max) = median_and_max(vals);
        c.draw_series(
            counts
                .iter()
                .enumerate()
                .filter(|(_, &n)| n > 0)
                .map(|(b, &n)| {
                    let x0 = lo + b as f64 * width;
                    Rectangle::new([(x0, 0.0), (x0 + width, n as f64)], col.mix(0.8).filled())
                }),
        )
        .map_err(|e| ctx.err(e))?
        .label(if max == 0.0 {
            format!("{name}: all 0 (not measured in lockstep runs)")
        } else {
            format!("{name}: median {median:.0} µs, max {max:.0} µs")
        })
        .legend(move |(x, y)| Rectangle::new([(x, y - 5), (x + 20, y + 5)], col.filled()));
        legend(&mut c, style, SeriesLabelPosition::UpperRight, ctx)?;
    }
    finish(&root, ctx)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::record::McapRecorder;
    use rollbase_control::runtime::record::CycleRecord;
    use rollbase_control::types::{Pose, MAX_WHEELS};
    use std::collections::BTreeMap;

    fn tmp(name: &str) -> PathBuf {
        let d = std::env::temp_dir().join(format!("rollbase-plot-{name}-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&d);
        d
    }

    const WHEELS: [[f64; 2]; 4] = [[0.35, 0.35], [-0.35, 0.35], [-0.35, -0.35], [0.35, -0.35]];

    /// A circle of radius 1.5 m at 0.3 m/s with the heading following the tangent, 4 wheels,
    /// legs ramping, a small estimation offset and truth. `odd` sprinkles NaN/∞ in.
    fn write_circle(path: &Path, cycles: u64, odd: bool) {
        write_circle_with(path, cycles, odd, &|_, _, _| {});
    }

    type Tweak = dyn Fn(u64, &mut CycleRecord, &mut [[f64; 2]; 4]);

    /// [`write_circle`] with `tweak` applied to each cycle before it is written.
    fn write_circle_with(path: &Path, cycles: u64, odd: bool, tweak: &Tweak) {
        let mut rec = McapRecorder::create(path, &BTreeMap::new()).unwrap();
        let (rad, v) = (1.5, 0.3);
        for k in 0..cycles {
            let t = k as f64 * 0.02;
            let mut r = CycleRecord::new(k, t, 4);
            let a = v * t / rad;
            let truth = Pose {
                x: rad * a.sin(),
                y: rad * (1.0 - a.cos()),
                theta: a,
            };
            let mut legs = [0.0; MAX_WHEELS];
            for (i, l) in legs.iter_mut().take(4).enumerate() {
                *l = 0.4 + 0.001 * t + 0.002 * i as f64;
            }
            r.truth = Some((truth, legs));
            r.pose = Pose {
                x: truth.x + 0.01 * (3.0 * t).sin(),
                y: truth.y - 0.005,
                theta: truth.theta + 0.002,
            };
            r.reference.n = 4;
            r.reference.z[0] = truth.x + 0.003;
            r.reference.z[1] = truth.y;
            r.reference.z[2] = truth.theta + 0.001;
            for (i, &leg) in legs.iter().take(4).enumerate() {
                r.reference.z[3 + i] = leg + 0.0005;
                r.measurement.wheels[i].leg = leg;
                r.command.wheels[i].wheel_speed = 3.0 + 0.5 * i as f64;
                r.command.wheels[i].steer_rate = 0.1 * (t + i as f64).sin();
                r.avoidance.d_start[i] = 0.25;
            }
            r.mode = if t < 0.5 { "align" } else { "track" };
            // ICR of the circular motion in the body frame: (0, R), with a detour close to
            // wheel 1 half-way through.
            let near = (k as f64 - cycles as f64 / 2.0).abs() < 20.0;
            r.avoidance.icr_body = Some(if near { [-0.1, 0.55] } else { [0.0, rad] });
            r.avoidance.active = near;
            r.avoidance.min_distance = if near { 0.3 } else { 1.2 };
            r.timing.period_us = 4000.0 + 30.0 * ((k * 7919) % 13) as f64;
            r.timing.compute_us = 150.0 + 10.0 * ((k * 104_729) % 7) as f64;
            if odd && k % 17 == 3 {
                r.pose.x = f64::NAN;
                r.truth = None;
                r.reference.z[2] = f64::INFINITY;
                r.command.wheels[2].wheel_speed = f64::NAN;
                r.avoidance.icr_body = None;
                r.avoidance.min_distance = f64::INFINITY;
                r.timing.period_us = f64::NAN;
            }
            let mut wheels = WHEELS;
            if odd && k % 29 == 5 {
                wheels[1] = [f64::NAN, 0.2];
            }
            tweak(k, &mut r, &mut wheels);
            rec.write_cycle(&r, &wheels).unwrap();
        }
        rec.finish().unwrap();
    }

    /// Checks the PNG signature and the IHDR size, returning (width, height).
    fn png_size(path: &Path) -> (u32, u32) {
        let b = std::fs::read(path).unwrap();
        assert!(b.len() > 33, "{} is too short for a PNG", path.display());
        assert_eq!(
            &b[..8],
            b"\x89PNG\r\n\x1a\n",
            "{} signature",
            path.display()
        );
        assert_eq!(&b[12..16], b"IHDR", "{} first chunk", path.display());
        let w = u32::from_be_bytes([b[16], b[17], b[18], b[19]]);
        let h = u32::from_be_bytes([b[20], b[21], b[22], b[23]]);
        (w, h)
    }

    const NAMES: [&str; 5] = [
        "xy_path.png",
        "tracking_errors.png",
        "commands.png",
        "icr_body.png",
        "timing.png",
    ];

    fn assert_five_pngs(report: &PlotReport, out: &Path) {
        let expected: Vec<PathBuf> = NAMES.iter().map(|n| out.join(n)).collect();
        assert_eq!(report.files, expected);
        assert!(report.skipped.is_empty(), "{:?}", report.skipped);
        for f in &report.files {
            assert_eq!(png_size(f), (WIDTH, HEIGHT), "{}", f.display());
        }
    }

    #[test]
    fn circular_run_gives_five_pngs_of_the_figure_size() {
        let dir = tmp("circle");
        let mcap = dir.join("run.mcap");
        write_circle(&mcap, 400, false);
        let out = dir.join("plots");
        let report = plot_recording(&mcap, &out).unwrap();
        assert_five_pngs(&report, &out);
        assert_eq!(report.labelled, font_path().is_some());
        let _ = std::fs::remove_dir_all(dir);
    }

    #[test]
    fn unlabelled_plots_draw_no_text_and_still_succeed() {
        // With `family: None` no text style exists; any text drawn by mistake would fall
        // back to the unregistered "sans-serif" family and fail the drawing.
        let dir = tmp("nofont");
        let mcap = dir.join("run.mcap");
        write_circle(&mcap, 200, false);
        let out = dir.join("plots");
        let report = plot_with_style(&mcap, &out, Style { family: None }).unwrap();
        assert!(!report.labelled);
        assert_five_pngs(&report, &out);
        let _ = std::fs::remove_dir_all(dir);
    }

    #[test]
    fn nan_and_null_fields_do_not_panic() {
        let dir = tmp("odd");
        let mcap = dir.join("run.mcap");
        write_circle(&mcap, 300, true);
        let out = dir.join("plots");
        let report = plot_recording(&mcap, &out).unwrap();
        assert_five_pngs(&report, &out);
        let _ = std::fs::remove_dir_all(dir);
    }

    /// Issue 19: `/icr` holding 1e308 (wheel points, field radii) made plotters panic in
    /// `icr_body.png` (exit 101, 4 of 5 figures). Now the values are left out and named.
    #[test]
    fn absurd_icr_values_are_left_out_and_named_instead_of_a_panic() {
        let dir = tmp("absurd");
        let mcap = dir.join("run.mcap");
        write_circle_with(&mcap, 300, false, &|k, r, wheels| {
            if k == 150 {
                r.avoidance.d_start[0] = 1e308;
                wheels[2] = [1e308, -1e308];
                r.avoidance.icr_body = Some([1e308, 1e308]);
            }
        });
        let out = dir.join("plots");
        let report = plot_recording(&mcap, &out).unwrap();
        assert_five_pngs(&report, &out);
        let all = report.ignored.join("\n");
        for field in ["d_start", "wheel_x", "wheel_y", "icr_x", "icr_y"] {
            assert!(
                report
                    .ignored
                    .iter()
                    .any(|l| l.starts_with(&format!("/icr {field}: 1 value(s)"))
                        && l.contains("cycle 150")),
                "{field} not reported in:\n{all}"
            );
        }
        let _ = std::fs::remove_dir_all(dir);
    }

    /// Issue 19: a flipped digit inside a chunk was plotted (the chunk CRC was not checked).
    #[test]
    fn a_damaged_chunk_is_an_error_naming_the_crc() {
        let dir = tmp("crc");
        let mcap = dir.join("run.mcap");
        write_circle(&mcap, 200, false);
        let mut bytes = std::fs::read(&mcap).unwrap();
        // A timing value of the file (4000 + 30·((k·7919) mod 13) µs): change one bit of it.
        let needle = 4000.0f64.to_le_bytes();
        let at = bytes
            .windows(8)
            .position(|w| w == needle)
            .expect("value in file");
        bytes[at + 5] ^= 0x10;
        std::fs::write(&mcap, &bytes).unwrap();
        let err = plot_recording(&mcap, &dir.join("plots")).unwrap_err();
        assert!(
            matches!(err, PlotError::Record(RecordError::Format { .. })),
            "{err:?}"
        );
        let msg = err.to_string();
        assert!(
            msg.contains("chunk CRC mismatch") && msg.contains("run.mcap"),
            "{msg}"
        );
        assert!(
            !dir.join("plots").exists(),
            "nothing drawn from a damaged file"
        );
        let _ = std::fs::remove_dir_all(dir);
    }

    /// Issue 19: `plot /dev/zero` read forever and ate memory.
    #[test]
    fn a_device_is_refused_before_reading() {
        for dev in ["/dev/zero", "/dev/urandom"] {
            if !Path::new(dev).exists() {
                eprintln!("skipped: no {dev}");
                continue;
            }
            let dir = tmp("dev");
            let err = plot_recording(Path::new(dev), &dir.join("plots")).unwrap_err();
            let msg = err.to_string();
            assert!(
                msg.contains("not a regular file") && msg.contains(dev),
                "{msg}"
            );
        }
    }

    #[test]
    fn single_cycle_recording_gives_five_pngs() {
        let dir = tmp("one");
        let mcap = dir.join("run.mcap");
        write_circle(&mcap, 1, false);
        let out = dir.join("plots");
        let report = plot_recording(&mcap, &out).unwrap();
        assert_five_pngs(&report, &out);
        let _ = std::fs::remove_dir_all(dir);
    }

    #[test]
    fn pose_only_recording_with_null_fields_draws_the_path_and_skips_the_rest() {
        let dir = tmp("poseonly");
        std::fs::create_dir_all(&dir).unwrap();
        let mcap = dir.join("pose.mcap");
        let file = std::io::BufWriter::new(std::fs::File::create(&mcap).unwrap());
        let mut w = mcap::WriteOptions::new()
            .compression(None)
            .create(file)
            .unwrap();
        let ch = w.add_channel(0, "/pose", "json", &BTreeMap::new()).unwrap();
        for k in 0..5u32 {
            let v = if k == 2 {
                serde_json::json!({"cycle": k, "x": null, "y": null, "theta": null})
            } else {
                serde_json::json!({"cycle": k, "x": k, "y": 0.5 * k as f64, "theta": null,
                                   "true_x": null, "true_legs": null})
            };
            let header = mcap::records::MessageHeader {
                channel_id: ch,
                sequence: k,
                log_time: u64::from(k) * 4_000_000,
                publish_time: 0,
            };
            w.write_to_known_channel(&header, v.to_string().as_bytes())
                .unwrap();
        }
        w.finish().unwrap();
        drop(w);
        let out = dir.join("plots");
        let report = plot_recording(&mcap, &out).unwrap();
        assert_eq!(report.files, vec![out.join("xy_path.png")]);
        assert_eq!(png_size(&report.files[0]), (WIDTH, HEIGHT));
        assert_eq!(report.skipped.len(), 4, "{:?}", report.skipped);
        assert!(report.skipped[0].starts_with("tracking_errors.png: recording has no /reference"));
        let _ = std::fs::remove_dir_all(dir);
    }

    #[test]
    fn recording_without_pose_is_a_typed_error() {
        let dir = tmp("nopose");
        let mcap = dir.join("empty.mcap");
        McapRecorder::create(&mcap, &BTreeMap::new())
            .unwrap()
            .finish()
            .unwrap();
        let err = plot_recording(&mcap, &dir.join("plots")).unwrap_err();
        assert!(
            matches!(err, PlotError::MissingTopic { topic: "/pose", .. }),
            "{err}"
        );
        let msg = err.to_string();
        assert!(
            msg.contains("no /pose messages") && msg.contains("empty.mcap"),
            "{msg}"
        );
        assert!(!dir.join("plots").exists(), "nothing written on error");
        let _ = std::fs::remove_dir_all(dir);
    }

    #[test]
    fn non_mcap_file_is_a_typed_error() {
        let dir = tmp("garbage");
        std::fs::create_dir_all(&dir).unwrap();
        let path = dir.join("notes.mcap");
        std::fs::write(&path, b"definitely not an MCAP file").unwrap();
        let err = plot_recording(&path, &dir.join("plots")).unwrap_err();
        assert!(
            matches!(err, PlotError::Record(RecordError::Format { .. })),
            "{err}"
        );
        assert!(err.to_string().contains("notes.mcap"), "{err}");
        let _ = std::fs::remove_dir_all(dir);
    }

    #[test]
    fn segments_break_at_non_finite_and_outside_points() {
        let pts = [
            (0.0, 0.0),
            (1.0, 1.0),
            (f64::NAN, 1.0),
            (2.0, 2.0),
            (50.0, 2.0),
            (3.0, 3.0),
            (4.0, f64::INFINITY),
        ];
        let s = segments(pts, (-10.0, 10.0), (-10.0, 10.0));
        assert_eq!(
            s,
            vec![
                vec![(0.0, 0.0), (1.0, 1.0)],
                vec![(2.0, 2.0)],
                vec![(3.0, 3.0)]
            ]
        );
    }

    #[test]
    fn range_ignores_non_finite_and_widens_degenerate() {
        let (lo, hi) = range([1.0, f64::NAN, 3.0, f64::INFINITY]);
        assert!(
            (lo - 0.9).abs() < 1e-12 && (hi - 3.1).abs() < 1e-12,
            "{lo} {hi}"
        );
        let (lo, hi) = range([2.0, 2.0]);
        assert!(lo < 2.0 && hi > 2.0);
        assert_eq!(range([f64::NAN]), (-1.0, 1.0));
        let (lo, hi) = range([-1e308, 1.0, 2.0, 1e308]);
        assert!(
            (lo - 0.95).abs() < 1e-12 && (hi - 2.05).abs() < 1e-12,
            "{lo} {hi}"
        );
        let (lo, hi) = range([0.0]);
        assert!(lo < 0.0 && hi > 0.0);
    }

    #[test]
    fn equal_aspect_gives_equal_scale_and_keeps_the_data() {
        let ((x0, x1), (y0, y1)) = equal_aspect((0.0, 4.0), (0.0, 1.0), (1000, 500));
        assert!(((x1 - x0) / 1000.0 - (y1 - y0) / 500.0).abs() < 1e-12);
        assert!(x0 <= 0.0 && x1 >= 4.0 && y0 <= 0.0 && y1 >= 1.0);
    }

    #[test]
    fn footprint_is_ordered_around_the_centroid_and_skips_nan() {
        let row = IcrRow {
            t: 0.0,
            icr: [f64::NAN; 2],
            active: false,
            min_distance: f64::NAN,
            d_start: vec![],
            // Crossed numbering: 0 and 1 are diagonal.
            wheel_x: vec![1.0, -1.0, -1.0, 1.0, f64::NAN],
            wheel_y: vec![1.0, -1.0, 1.0, -1.0, 0.0],
        };
        let p = footprint(&row);
        assert_eq!(p, vec![[-1.0, -1.0], [1.0, -1.0], [1.0, 1.0], [-1.0, 1.0]]);
        let w = to_world([1.0, 2.0, std::f64::consts::FRAC_PI_2], [1.0, 0.0]);
        assert!((w.0 - 1.0).abs() < 1e-12 && (w.1 - 3.0).abs() < 1e-12);
    }

    #[test]
    fn tick_labels_have_sensible_precision_and_no_negative_zero() {
        let f = tick_format((-0.0005, 0.0015));
        assert_eq!(f(&0.0012), "0.0012");
        assert_eq!(f(&-1e-19), "0.0000");
        assert_eq!(f(&-0.00001), "0.0000");
        let f = tick_format((3900.0, 4400.0));
        assert_eq!(f(&4000.0), "4000");
    }

    #[test]
    fn snapshot_interval_bounds_the_count() {
        assert_eq!(snapshot_interval(8.0, 12.0), 1.0);
        assert_eq!(snapshot_interval(31.0, 12.0), 5.0);
        assert_eq!(snapshot_interval(0.0, 12.0), 1.0);
        assert!(5000.0 / snapshot_interval(5000.0, 12.0) <= 12.0);
    }
}
