//! The fault campaign of issue 8: runs every fault through the whole stack in lockstep,
//! checks each outcome, prints the table and writes `docs/reliability.md`.
//!
//! ```sh
//! cargo run --release -p rollbase-tests --bin fault-campaign            # campaign + docs
//! cargo run --release -p rollbase-tests --bin fault-campaign -- --soak  # + 1 h soak
//! ```
//!
//! Exit code 1 when any case fails its assertions.
use rollbase_control::runtime::scenario::Scenario;
use rollbase_control::supervisor::FaultReason;
use rollbase_tests::campaign::*;
use rollbase_vcan_sim::faults::{DriveGain, EncoderJump, EncoderStuck, MotorFault};
use rollbase_vcan_sim::FaultSchedule;
use std::fmt::Write as _;

/// The rows of `docs/reliability-live.md` (written by `reliability-live`) as a second table,
/// if that file exists.
fn live_table() -> Option<String> {
    let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../docs/reliability-live.md");
    let text = std::fs::read_to_string(path).ok()?;
    let mut rows: Vec<&str> = Vec::new();
    for l in text.lines().filter(|l| l.starts_with('|')) {
        // One table: the header and separator rows of later tables (the load runs) go.
        let header = l.starts_with("| check |") || l.starts_with("|---");
        if !header || rows.len() < 2 {
            rows.push(l);
        }
    }
    if rows.is_empty() {
        return None;
    }
    Some(format!(
        "\n## Process-level checks (measured by reliability-live)\n\n\
         The real release binaries as separate processes on loopback, copied from\n\
         `docs/reliability-live.md` (which says how it was generated). Rows at normal priority\n\
         depend on the machine's other load (its load average is given); the rows with the\n\
         bridge and simulator at SCHED_FIFO show what the bridge itself does.\n\n{}\n",
        rows.join("\n")
    ))
}

fn cell(s: &str) -> String {
    s.replace('|', "\\|").replace('\n', " ")
}

fn main() {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let soak_run = args.iter().any(|a| a == "--soak");
    let no_write = args.iter().any(|a| a == "--no-write");
    if let Some(bad) = args
        .iter()
        .find(|a| !matches!(a.as_str(), "--soak" | "--no-write"))
    {
        eprintln!("unknown argument `{bad}`: use --soak and/or --no-write");
        std::process::exit(2);
    }
    let mut rows = vec![
        frame_loss_seeds(0.0, 1, false),
        frame_loss_seeds(0.01, 12, false),
        frame_loss_seeds(0.05, 12, false),
        frame_loss_seeds(0.2, 12, false),
        silent_module_rearm(false),
        controller_silent(),
        bad_frames(false, false),
        bad_frames(true, false),
        corrupted_medium(false),
        delayed(0.001, 0.0, false),
        delayed(0.003, 0.0, false),
        delayed(0.0005, 0.0015, false),
    ];
    let mut f = FaultSchedule::default();
    f.motor_fault.push(MotorFault { node: 2, at: 8.0 });
    rows.push(sim_fault(
        "motor fault in STATUS (node 2, 8 s)",
        "STATUS fault code → module fault naming the node, controlled stop, latched; re-arm sends fault_reset",
        f,
        8.0,
        |r| matches!(r, FaultReason::ModuleFault { node: 2, .. }),
    ));
    let mut f = FaultSchedule::default();
    f.encoder_stuck.push(EncoderStuck { node: 1, at: 8.0 });
    rows.push(sim_fault(
        "encoder stuck (node 1, all encoders, 8 s)",
        "no dedicated check: the frozen readings stop following the commands → following error naming the module (before issue 19: the odometry residual, slip fault after 768 ms), controlled stop",
        f,
        8.0,
        |r| matches!(r, FaultReason::FollowingError { wheel: 0, node: 1, .. }),
    ));
    let mut f = FaultSchedule::default();
    f.encoder_jump.push(EncoderJump {
        node: 4,
        at: 8.0,
        amount: 0.3,
    });
    rows.push(sim_fault(
        "steering encoder jump (node 4, +0.3 rad, 8 s)",
        "two readings one SYNC apart must differ by what the trapezoid of their measured steering rates predicts; more than 0.02 rad unexplained → encoder-jump fault naming the module, controlled stop, latched",
        f,
        8.0,
        |r| matches!(r, FaultReason::EncoderJump { wheel: 3, node: 4, .. }),
    ));
    rows.push(leg_end_stop());
    rows.push(wheel_slip());
    rows.push(modules_bus_off());
    rows.push(iface_down(0.5, 1.0, 1.5, false));
    rows.push(iface_down(10.0, 10.2, 11.0, false));
    rows.push(bad_input());
    // Following error (issue 19): drives that do not respond or respond at 50 %, both profiles.
    let following = "measured wheel speed outside the range of the last 0.1 s of commands ± (0.5 rad/s + 25 %) for more than 0.2 s (CiA 402 0x6065/0x6066) → following-error fault naming the wheel, the drive's node, commanded and measured, controlled stop";
    for cia in [false, true] {
        let prof = if cia { "CiA 402" } else { "native" };
        let base = || {
            let o = rollbase_tests::RunOptions::new(Scenario::Seed000);
            if cia {
                o.cia402()
            } else {
                o
            }
        };
        // The rolling drive of wheel i: node i+1 (native) or 2i+1 (CiA 402 defaults).
        let drive = |i: u8| if cia { 2 * i + 1 } else { i + 1 };
        let mut o = base();
        o.plant.drive_time_constant = 1e300;
        rows.push(following_case(
            &format!("{prof}: motors that never respond (plant drive_time_constant = 1e300, from the start)"),
            following,
            &o,
            None,
            |r| matches!(r, FaultReason::FollowingError { .. }),
        ));
        for (gain, what) in [(0.0, "do not respond"), (0.5, "respond at 50 %")] {
            let mut o = base();
            for i in 0..4 {
                o.faults.drive_gain.push(DriveGain {
                    node: drive(i),
                    at: 8.0,
                    gain,
                });
            }
            rows.push(following_case(
                &format!("{prof}: all 4 rolling drives {what} from 8 s"),
                following,
                &o,
                Some(8.0),
                |r| matches!(r, FaultReason::FollowingError { .. }),
            ));
        }
        let mut o = base();
        o.faults.drive_gain.push(DriveGain {
            node: drive(1),
            at: 8.0,
            gain: 0.5,
        });
        rows.push(following_case(
            &format!("{prof}: wheel 2's rolling drive responds at 50 % from 8 s"),
            following,
            &o,
            Some(8.0),
            |r| matches!(r, FaultReason::FollowingError { wheel: 1, .. }),
        ));
        let mut o = base();
        o.faults.drive_gain.push(DriveGain {
            node: drive(1),
            at: 8.0,
            gain: 0.0,
        });
        rows.push(following_case(
            &format!("{prof}: wheel 2's rolling drive does not respond from 8 s"),
            "one wheel standing still while the others roll makes the wheels fight: odometry residual > 0.05 m/s for 25 cycles → slip fault pointing at wheel 2's drive (outside its following window), usually before the following error's 0.2 s time out; either is a controlled stop",
            &o,
            Some(8.0),
            |r| {
                // The others drag the held wheel, so every wheel slips a little and no
                // single wheel explains the residual: the slip points at wheel 2 by its
                // drive, outside its following window.
                r.slip_lead() == Some(1) || matches!(r, FaultReason::FollowingError { wheel: 1, .. })
            },
        ));
    }
    rows.push(following_margin());
    rows.push(not_arrived());
    rows.push(simulator_stall(std::time::Duration::from_millis(80)));

    let mut md = String::new();
    let _ = writeln!(
        md,
        "# rollbase reliability: fault campaign\n\n\
         Generated by `cargo run --release -p rollbase-tests --bin fault-campaign` (do not edit by hand).\n\
         Every case runs the whole stack in lockstep — `CycleCore` → in-process virtual bus → simulated\n\
         wheel modules and plant → virtual bus → `CycleCore` — on virtual time with the simulator's fault\n\
         schedule, the bus medium's fault model, or a hook on the controller's receive path\n\
         (`rollbase_tests::campaign`). Scenario: seed 000 (DFL), seed 1, native profile unless stated;\n\
         the simulator-stall row is the one wall-clock (real-time) case. Detection time is\n\
         from the injection to the first cycle in Fault. \"Controlled stop\" is checked: every wheel's\n\
         speed step ≤ wheel_accel·dt, steering rate 0, wheels at rest at the end.\n\n\
         | # | fault | policy | detection | platform outcome | data lost | result |\n|---|---|---|---|---|---|---|"
    );
    let mut failed = 0;
    for (i, c) in rows.iter().enumerate() {
        if !c.pass {
            failed += 1;
        }
        let _ = writeln!(
            md,
            "| {} | {} | {} | {} | {} | {} | {} |",
            i + 1,
            cell(&c.fault),
            cell(&c.policy),
            cell(&c.detection),
            cell(&c.outcome),
            cell(&c.data_lost),
            if c.pass {
                "pass".to_string()
            } else {
                format!("**FAIL**: {}", cell(&c.failures.join("; ")))
            }
        );
        println!(
            "{:>2} {} {} — {} — {}",
            i + 1,
            if c.pass { "pass" } else { "FAIL" },
            c.fault,
            c.detection,
            c.outcome
        );
        for f in &c.failures {
            println!("      failed: {f}");
        }
    }
    if let Some(live) = live_table() {
        md.push_str(&live);
    }
    md.push_str(include_str!("reliability_tail.md"));
    let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../docs/reliability.md");
    if soak_run {
        let mut text = "\n## Soak (last run)\n\n`fault-campaign --soak`: 900 000 cycles (one simulated hour at 250 Hz) per wire profile, 1 % random frame loss on the bus, looping waypoint trajectory (`campaign::soak_waypoints`), lockstep, release build; a run passes when every cycle ran with its bookkeeping right, memory did not grow and the platform never faulted.\n".to_string();
        for (profile, cia402) in [("native", false), ("CiA 402", true)] {
            match soak(900_000, 0.01, cia402) {
                Ok(r) => {
                    let grow = r.rss_kb.last().copied().unwrap_or(0) as i64
                        - r.rss_kb.get(1).copied().unwrap_or(0) as i64;
                    let ok = r.cycles == 900_000
                        && r.core_cycles == 900_000
                        && r.bookkeeping_errors == 0
                        && r.time_drift_s.abs() < 1e-6
                        && grow <= 1024
                        && !r.faulted;
                    if !ok {
                        failed += 1;
                    }
                    let part = format!(
                        "\n### {profile}\n\n\
                         - result: {}\n- wall time: {:.1} s\n- cycles: loop {}, core counter {}, records with a wrong cycle number {}, simulator clock − cycles·period = {:.3e} s\n- peak RSS (VmHWM): {} kB; VmRSS samples (kB, every 45 000 cycles): {:?}; growth after the first sample: {} kB\n- max position error while tracking: {:.2} mm; frames lost (counter gaps): {}; final state: {}\n",
                        if ok { "pass" } else { "**FAIL**" },
                        r.wall_s,
                        r.cycles,
                        r.core_cycles,
                        r.bookkeeping_errors,
                        r.time_drift_s,
                        r.peak_kb,
                        r.rss_kb,
                        grow,
                        r.max_err * 1e3,
                        r.lost,
                        r.final_state
                    );
                    println!("{part}");
                    text.push_str(&part);
                }
                Err(e) => {
                    eprintln!("{profile} soak could not start: {e}");
                    failed += 1;
                }
            }
        }
        md.push_str(&text);
    } else if let Ok(old) = std::fs::read_to_string(&path) {
        // Keep the last soak section when only the campaign is rerun.
        if let Some(at) = old.find("\n## Soak (last run)") {
            md.push_str(&old[at..]);
        }
    }
    if !no_write {
        if let Err(e) = std::fs::write(&path, &md) {
            eprintln!("cannot write {}: {e}", path.display());
            std::process::exit(1);
        }
        println!("wrote {}", path.display());
    }
    if failed > 0 {
        eprintln!("{failed} case(s) failed");
        std::process::exit(1);
    }
}
