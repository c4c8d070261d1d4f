//! The figure of docs/time-scaling.md: the clock rate ṡ = dτ/dt of a waypoint trajectory
//! over executed time, as the runtime plans it (default platform, default
//! [`TimeScaleConfig`]), with the limit that binds where the clock runs below its cap and the
//! waypoints marked. Writes a plain SVG (no plotting dependency) and prints the timing.
//!
//! ```sh
//! cargo run --release -p rollbase-tests --bin timescale-figure
//! cargo run --release -p rollbase-tests --bin timescale-figure -- WAYPOINTS.toml OUT.svg
//! ```
//!
//! Defaults: docs/examples/time-scaling.toml → docs/img/time-scale.svg.

use rollbase_control::reference::timescale::{ScaledTrajectory, TimeScaleConfig};
use rollbase_control::reference::trajectory::{load_waypoints, Trajectory};
use rollbase_control::service::ports::Limiting;
use rollbase_control::Platform;
use std::fmt::Write as _;
use std::path::{Path, PathBuf};
use std::process::ExitCode;

/// Sampling step of the plotted clock (s): one control cycle at 250 Hz.
const STEP: f64 = 0.004;

/// Plot geometry (SVG user units).
const W: f64 = 840.0;
const H: f64 = 384.0;
const LEFT: f64 = 60.0;
const RIGHT: f64 = 20.0;
const TOP: f64 = 44.0;
const BOTTOM: f64 = 300.0;

/// The limit categories shown in the strip above the plot, with their colours.
const KINDS: [(Limiting, &str); 5] = [
    (Limiting::WheelSpeed, "#1f77b4"),
    (Limiting::WheelAccel, "#2ca02c"),
    (Limiting::SteerRate, "#d62728"),
    (Limiting::SteerAccel, "#ff7f0e"),
    (Limiting::LegSpeed, "#9467bd"),
];

/// One sample of the clock.
struct Sample {
    t: f64,
    tau: f64,
    scale: f64,
    limiting: Limiting,
    /// The timing is free here (a segment next to a waypoint without a time).
    free: bool,
}

fn root() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("..")
}

/// A "nice" tick step (1, 2 or 5 × 10^k) giving about `target` ticks over `span`.
fn tick_step(span: f64, target: f64) -> f64 {
    let raw = (span / target).max(1e-9);
    let mag = 10f64.powf(raw.log10().floor());
    [1.0, 2.0, 5.0, 10.0]
        .into_iter()
        .map(|m| m * mag)
        .find(|s| *s >= raw)
        .unwrap_or(10.0 * mag)
}

fn svg(samples: &[Sample], waypoints: &[f64], title: &str) -> String {
    let t_end = samples.last().map_or(1.0, |s| s.t).max(STEP);
    let s_max = samples.iter().map(|s| s.scale).fold(1.0, f64::max);
    let y_max = (s_max * 1.1 * 4.0).ceil() / 4.0;
    let x = |t: f64| LEFT + (W - LEFT - RIGHT) * t / t_end;
    let y = |s: f64| BOTTOM - (BOTTOM - TOP) * s / y_max;
    let mut o = String::new();
    let _ = writeln!(
        o,
        r##"<svg xmlns="http://www.w3.org/2000/svg" width="{W}" height="{H}" viewBox="0 0 {W} {H}" font-family="sans-serif" font-size="12">"##
    );
    let _ = writeln!(o, r##"<rect width="{W}" height="{H}" fill="white"/>"##);
    let _ = writeln!(
        o,
        r##"<text x="{}" y="16" text-anchor="middle" font-size="13">{title}</text>"##,
        W / 2.0
    );
    // Where the timing is free (next to a waypoint without a time): shaded.
    let mut k = 0;
    while k < samples.len() {
        if !samples[k].free {
            k += 1;
            continue;
        }
        let a = k;
        while k < samples.len() && samples[k].free {
            k += 1;
        }
        let (t0, t1) = (samples[a].t, samples[k - 1].t);
        let _ = writeln!(
            o,
            r##"<rect x="{:.1}" y="{TOP}" width="{:.1}" height="{:.1}" fill="#eeeeee"/>"##,
            x(t0),
            x(t1) - x(t0),
            BOTTOM - TOP
        );
    }
    // Grid and ticks.
    let ys = tick_step(y_max, 8.0);
    let mut v = 0.0;
    while v <= y_max + 1e-9 {
        let _ = writeln!(
            o,
            r##"<line x1="{LEFT}" y1="{0:.1}" x2="{1}" y2="{0:.1}" stroke="#dddddd"/><text x="{2}" y="{3:.1}" text-anchor="end">{v}</text>"##,
            y(v),
            W - RIGHT,
            LEFT - 6.0,
            y(v) + 4.0
        );
        v = ((v + ys) * 1e6).round() / 1e6;
    }
    let xs = tick_step(t_end, 10.0);
    let mut t = 0.0;
    while t <= t_end + 1e-9 {
        let _ = writeln!(
            o,
            r##"<line x1="{0:.1}" y1="{BOTTOM}" x2="{0:.1}" y2="{1}" stroke="black"/><text x="{0:.1}" y="{2}" text-anchor="middle">{t}</text>"##,
            x(t),
            BOTTOM + 5.0,
            BOTTOM + 18.0
        );
        t = ((t + xs) * 1e6).round() / 1e6;
    }
    // ṡ = 1: the timing as given.
    let _ = writeln!(
        o,
        r##"<line x1="{LEFT}" y1="{0:.1}" x2="{1}" y2="{0:.1}" stroke="#555555" stroke-dasharray="6 4"/><text x="{2}" y="{3:.1}" text-anchor="end" fill="#555555">as given</text>"##,
        y(1.0),
        W - RIGHT,
        W - RIGHT - 4.0,
        y(1.0) - 4.0
    );
    // Waypoints.
    for (i, &t) in waypoints.iter().enumerate() {
        let label = format!("waypoints[{i}]");
        let _ = writeln!(
            o,
            r##"<line x1="{0:.1}" y1="{TOP}" x2="{0:.1}" y2="{BOTTOM}" stroke="#888888" stroke-dasharray="2 3"/><text x="{1:.1}" y="{2}" font-size="10" fill="#555555" text-anchor="end" transform="rotate(-90 {1:.1} {2})">{label}</text>"##,
            x(t),
            x(t) + 11.0,
            TOP + 4.0
        );
    }
    // The binding limit where the clock runs below its cap: a strip above the plot.
    let mut k = 0;
    while k + 1 < samples.len() {
        let l = samples[k].limiting;
        let a = k;
        while k + 1 < samples.len() && samples[k].limiting == l {
            k += 1;
        }
        if let Some((_, c)) = KINDS.iter().find(|(x, _)| *x == l) {
            let _ = writeln!(
                o,
                r##"<rect x="{:.2}" y="{}" width="{:.2}" height="8" fill="{c}"/>"##,
                x(samples[a].t),
                TOP - 12.0,
                (x(samples[k].t) - x(samples[a].t)).max(0.5)
            );
        }
    }
    // ṡ(t).
    let mut pts = String::new();
    for s in samples {
        let _ = write!(pts, "{:.2},{:.2} ", x(s.t), y(s.scale));
    }
    let _ = writeln!(
        o,
        r##"<polyline points="{}" fill="none" stroke="black" stroke-width="1.6"/>"##,
        pts.trim_end()
    );
    // Axes and labels.
    let _ = writeln!(
        o,
        r##"<line x1="{LEFT}" y1="{TOP}" x2="{LEFT}" y2="{BOTTOM}" stroke="black"/><line x1="{LEFT}" y1="{BOTTOM}" x2="{0}" y2="{BOTTOM}" stroke="black"/>"##,
        W - RIGHT
    );
    let _ = writeln!(
        o,
        r##"<text x="{0}" y="{1}" text-anchor="middle">executed time t (s)</text><text x="16" y="{2}" text-anchor="middle" transform="rotate(-90 16 {2})">ṡ = dτ/dt</text>"##,
        (LEFT + W - RIGHT) / 2.0,
        BOTTOM + 32.0,
        (TOP + BOTTOM) / 2.0
    );
    // Legend: the shading, then the limit colours.
    let (ly1, ly2) = (H - 30.0, H - 10.0);
    let _ = writeln!(
        o,
        r##"<rect x="{LEFT}" y="{}" width="14" height="10" fill="#eeeeee" stroke="#cccccc"/><text x="{}" y="{ly1}">timing free (next to a waypoint without t; ṡ relative to the nominal parametrisation)</text>"##,
        ly1 - 9.0,
        LEFT + 18.0
    );
    let _ = write!(
        o,
        r##"<text x="{LEFT}" y="{ly2}">binding limit (top strip):</text>"##
    );
    let mut lx = LEFT + 150.0;
    for (l, c) in KINDS {
        let _ = writeln!(
            o,
            r##"<rect x="{lx}" y="{}" width="14" height="10" fill="{c}"/><text x="{}" y="{ly2}">{}</text>"##,
            ly2 - 9.0,
            lx + 18.0,
            l.name()
        );
        lx += 18.0 + 6.9 * l.name().len() as f64 + 6.0;
    }
    o.push_str("</svg>\n");
    o
}

fn run(input: &Path, out: &Path) -> Result<(), String> {
    let p = Platform::justin();
    let spline = load_waypoints(&p, input).map_err(|e| format!("{}: {e}", input.display()))?;
    let knots = spline.times().to_vec();
    let traj = ScaledTrajectory::plan(&p, Box::new(spline), TimeScaleConfig::default())
        .map_err(|e| format!("{}: {e}", input.display()))?;
    let timing = traj.timing().ok_or("no timing")?;
    let end = timing.executed_duration_s;
    let n = (end / STEP).ceil() as usize;
    let samples: Vec<Sample> = (0..=n)
        .map(|k| {
            // The clock reads ṡ = 0 from the end on (at rest): the last sample is taken
            // just before it.
            let t = (k as f64 * STEP).min(end * (1.0 - 1e-12));
            let (tau, scale, _, _) = traj.clock(t);
            let st = traj.time_scale(t).ok_or("not time-scaled");
            let limiting = st.map_or(Limiting::None, |s| s.limiting);
            Sample {
                t,
                tau,
                scale,
                limiting,
                free: !traj.inner().timed_at(tau),
            }
        })
        .collect();
    // The executed time of each waypoint: where the clock passes its nominal knot time.
    let waypoints: Vec<f64> = knots
        .iter()
        .map(|&k| {
            samples
                .iter()
                .find(|s| s.tau >= k - 1e-9)
                .map_or(end, |s| s.t)
        })
        .collect();
    let name = input
        .file_name()
        .map_or_else(String::new, |s| s.to_string_lossy().into_owned());
    let title = format!(
        "Clock rate ṡ of {name}: nominal {:.2} s, executed {:.2} s, smallest ṡ {:.3} at t = {:.2} s",
        timing.nominal_duration_s, end, timing.min_scale, timing.min_scale_at_s
    );
    let doc = svg(&samples, &waypoints, &title);
    if let Some(dir) = out.parent() {
        std::fs::create_dir_all(dir).map_err(|e| format!("{}: {e}", dir.display()))?;
    }
    std::fs::write(out, doc).map_err(|e| format!("{}: {e}", out.display()))?;
    println!(
        "{name}: nominal {:.3} s, executed {:.3} s, min ṡ {:.3} at t = {:.3} s ({} of wheel {}), max ṡ {:.3}, shares used {:.3}",
        timing.nominal_duration_s,
        end,
        timing.min_scale,
        timing.min_scale_at_s,
        timing.limiting.name(),
        timing.wheel + 1,
        samples.iter().map(|s| s.scale).fold(0.0, f64::max),
        timing.max_ratio
    );
    for (i, (k, t)) in knots.iter().zip(&waypoints).enumerate() {
        println!("  waypoints[{i}]: nominal {k:.3} s, executed {t:.3} s");
    }
    println!("wrote {}", out.display());
    Ok(())
}

fn main() -> ExitCode {
    let args: Vec<String> = std::env::args().skip(1).collect();
    if args.len() > 2 || args.iter().any(|a| a.starts_with('-')) {
        eprintln!("usage: timescale-figure [WAYPOINTS.toml [OUT.svg]] (defaults: docs/examples/time-scaling.toml, docs/img/time-scale.svg)");
        return ExitCode::from(2);
    }
    let input = args.first().map_or_else(
        || root().join("docs/examples/time-scaling.toml"),
        PathBuf::from,
    );
    let out = args
        .get(1)
        .map_or_else(|| root().join("docs/img/time-scale.svg"), PathBuf::from);
    match run(&input, &out) {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("timescale-figure: {e}");
            ExitCode::FAILURE
        }
    }
}
