//! Bus load of the CiA 402 profile, derived from the PDO layouts ([`super::pdo`]) and the
//! timing in the platform file, with the same worst-case frame length as the native profile
//! ([`crate::busload::frame_bits`]).
//!
//! Per control cycle: one SYNC (0 bytes), one RPDO1 per drive (6 bytes), one TPDO1 per drive
//! (8 bytes) and one TPDO1 per encoder (6 bytes). Besides: the drives' statusword TPDO2
//! (2 bytes) every event-timer period (and on each state change, a handful per run), every
//! device's heartbeat (1 byte) every `heartbeat_ms` and the master's every
//! `master_heartbeat_ms`. SDO and NMT traffic happens at boot only and EMCY on faults only;
//! neither is part of the steady-state load.
//!
//! The report also gives the length of the burst of feedback that follows each SYNC (every
//! TPDO1 answers the same SYNC and they go out back to back, in COB-ID order): it must fit
//! the controller's feedback window, or the last frames miss the cycle.

use super::config::Cia402Config;
use super::pdo;
use crate::busload::{frame_bits, write_table, BusLoadRow, DEFAULT_FEEDBACK_WINDOW_S};
use std::fmt;

/// The steady-state load of the profile on a bus.
#[derive(Debug, Clone, PartialEq)]
pub struct Cia402Load {
    /// Wheels (each: 2 drives, 1 encoder).
    pub wheels: usize,
    /// Control cycle rate (Hz).
    pub cycle_hz: f64,
    /// Bit rate (bit/s).
    pub bitrate: u32,
    /// One row per frame kind.
    pub rows: Vec<BusLoadRow>,
    /// Worst-case bits of the cyclic frames of one cycle (SYNC, RPDO1s, TPDO1s).
    pub cyclic_bits_per_cycle: u32,
    /// Cyclic load, %.
    pub cyclic_percent: f64,
    /// All frames, bit/s.
    pub total_bits_per_s: f64,
    /// All frames, %.
    pub total_percent: f64,
    /// Worst-case time on the wire of SYNC plus every TPDO1 answering it (s).
    pub feedback_burst_s: f64,
}

impl Cia402Load {
    /// Unused capacity, % of the bit rate.
    pub fn headroom_percent(&self) -> f64 {
        100.0 - self.total_percent
    }

    /// Why this configuration cannot run as configured (empty when it fits): the traffic
    /// exceeds the bus, or the feedback burst does not end inside the default feedback window.
    pub fn problems(&self) -> Vec<String> {
        let mut out = Vec::new();
        if self.total_percent >= 100.0 {
            out.push(format!(
                "the traffic needs {:.2}% of the bus: raise the bit rate, lower `cycle_hz` or split the wheels over two buses",
                self.total_percent
            ));
        }
        if self.feedback_burst_s > DEFAULT_FEEDBACK_WINDOW_S {
            out.push(format!(
                "the feedback burst ({:.3} ms) outlasts the {:.1} ms feedback window: the last TPDO1s of every cycle would arrive too late",
                self.feedback_burst_s * 1e3,
                DEFAULT_FEEDBACK_WINDOW_S * 1e3
            ));
        }
        out
    }
}

/// The steady-state load of `cfg` with `wheels` wheels at `cycle_hz` on a `bitrate` bus.
pub fn load(cfg: &Cia402Config, wheels: usize, cycle_hz: f64, bitrate: u32) -> Cia402Load {
    let drives = 2.0 * wheels as f64;
    let encoders = wheels as f64;
    let rate = |ms: u16| if ms == 0 { 0.0 } else { 1000.0 / f64::from(ms) };
    let kinds: [(&'static str, usize, f64, bool); 7] = [
        ("SYNC", 0, 1.0, true),
        ("RPDO1 drive", pdo::DRIVE_RPDO1.len_bytes(), drives, true),
        ("TPDO1 drive", pdo::DRIVE_TPDO1.len_bytes(), drives, true),
        ("TPDO1 enc", pdo::ENCODER_TPDO1.len_bytes(), encoders, true),
        (
            "TPDO2 sw",
            pdo::DRIVE_TPDO2.len_bytes(),
            drives * rate(cfg.status_event_timer_ms) / cycle_hz,
            false,
        ),
        (
            "heartbeat",
            1,
            (drives + encoders) * rate(cfg.heartbeat_ms) / cycle_hz,
            false,
        ),
        (
            "master hb",
            1,
            rate(cfg.master_heartbeat_ms) / cycle_hz,
            false,
        ),
    ];
    let bitrate_f = f64::from(bitrate.max(1));
    let mut rows = Vec::with_capacity(kinds.len());
    let mut cyclic_bits = 0u32;
    for (name, dlc, frames_per_cycle, cyclic) in kinds {
        let bits = frame_bits(dlc);
        if cyclic {
            cyclic_bits += bits * frames_per_cycle as u32;
        }
        let frames_per_s = frames_per_cycle * cycle_hz;
        let bits_per_s = frames_per_s * f64::from(bits);
        rows.push(BusLoadRow {
            name,
            dlc: dlc as u8,
            bits_per_frame: bits,
            frames_per_cycle,
            frames_per_s,
            bits_per_s,
            load_percent: 100.0 * bits_per_s / bitrate_f,
        });
    }
    let total_bits_per_s: f64 = rows.iter().map(|r| r.bits_per_s).sum();
    let burst_bits = frame_bits(0) as f64
        + drives * f64::from(frame_bits(pdo::DRIVE_TPDO1.len_bytes()))
        + encoders * f64::from(frame_bits(pdo::ENCODER_TPDO1.len_bytes()));
    Cia402Load {
        wheels,
        cycle_hz,
        bitrate,
        rows,
        cyclic_bits_per_cycle: cyclic_bits,
        cyclic_percent: 100.0 * f64::from(cyclic_bits) * cycle_hz / bitrate_f,
        total_bits_per_s,
        total_percent: 100.0 * total_bits_per_s / bitrate_f,
        feedback_burst_s: burst_bits / bitrate_f,
    }
}

impl fmt::Display for Cia402Load {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        writeln!(
            f,
            "Bus load, CiA 402 profile: {} wheels = {} drives + {} encoders, {} Hz cycle ({:.3} ms), {} bit/s",
            self.wheels,
            2 * self.wheels,
            self.wheels,
            self.cycle_hz,
            1000.0 / self.cycle_hz,
            self.bitrate
        )?;
        write_table(
            f,
            "frame",
            11,
            &self.rows,
            self.total_bits_per_s,
            self.total_percent,
        )?;
        writeln!(f)?;
        writeln!(
            f,
            "cyclic frames per cycle: {} bits = {:.2}% of the bus",
            self.cyclic_bits_per_cycle, self.cyclic_percent
        )?;
        writeln!(
            f,
            "total: {:.2}%, headroom {:.2}% (SDO and NMT at boot and EMCY on faults come on top)",
            self.total_percent,
            self.headroom_percent()
        )?;
        writeln!(
            f,
            "feedback burst after each SYNC (SYNC + every TPDO1): {:.3} ms worst case; it must end inside the controller's feedback window (default {:.0} ms)",
            self.feedback_burst_s * 1e3,
            DEFAULT_FEEDBACK_WINDOW_S * 1e3
        )?;
        let problems = self.problems();
        if problems.is_empty() {
            write!(f, "verdict: fits")
        } else {
            write!(f, "verdict: DOES NOT FIT: {}", problems.join("; "))
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn eight_drives_and_four_encoders_at_250_hz_on_1_mbit() {
        let cfg = Cia402Config::for_wheels(4);
        let l = load(&cfg, 4, 250.0, 1_000_000);
        // SYNC 55 + 8 RPDO1 × 115 + 8 TPDO1 × 135 + 4 encoder TPDO1 × 115 = 2515 bits.
        assert_eq!(l.cyclic_bits_per_cycle, 55 + 8 * 115 + 8 * 135 + 4 * 115);
        assert!(
            (l.cyclic_percent - 62.875).abs() < 1e-9,
            "{}",
            l.cyclic_percent
        );
        // + statusword 8 × 10 Hz × 75 + heartbeats 12 × 10 Hz × 65 + master 50 Hz × 65.
        let extra = 8.0 * 10.0 * 75.0 + 12.0 * 10.0 * 65.0 + 50.0 * 65.0;
        let total = 2515.0 * 250.0 + extra;
        assert!((l.total_bits_per_s - total).abs() < 1e-6);
        assert!(
            (l.total_percent - 64.58).abs() < 1e-9,
            "{}",
            l.total_percent
        );
        assert!((l.headroom_percent() - 35.42).abs() < 1e-9);
        // SYNC + 8 × 135 + 4 × 115 = 1595 bits = 1.595 ms of the 2 ms window.
        assert!((l.feedback_burst_s - 1.595e-3).abs() < 1e-12);
        let text = l.to_string();
        assert!(text.contains("62.88%"), "{text}");
        assert!(text.contains("headroom 35.42%"), "{text}");
        assert!(l.problems().is_empty(), "{:?}", l.problems());
        assert!(text.ends_with("verdict: fits"), "{text}");
    }

    #[test]
    fn at_500_kbit_the_same_platform_does_not_fit_and_the_report_says_why() {
        let cfg = Cia402Config::for_wheels(4);
        let l = load(&cfg, 4, 250.0, 500_000);
        assert!(
            (l.total_percent - 129.16).abs() < 1e-9,
            "{}",
            l.total_percent
        );
        // 1595 bits at 500 kbit/s = 3.19 ms > 2 ms.
        assert!((l.feedback_burst_s - 3.19e-3).abs() < 1e-12);
        let p = l.problems();
        assert_eq!(p.len(), 2, "{p:?}");
        assert!(p[0].contains("129.16% of the bus"), "{}", p[0]);
        assert!(p[1].contains("3.190 ms"), "{}", p[1]);
        assert!(l.to_string().contains("verdict: DOES NOT FIT"));
        // Three wheels at 500 kbit/s: 1900 cyclic bits per cycle = 95 % plus 2.72 % of
        // heartbeats and statuswords fits the bus, but SYNC + 6 × 135 + 3 × 115 = 1210 bits
        // = 2.42 ms of burst does not fit the window: only that is reported.
        let l3 = load(&Cia402Config::for_wheels(3), 3, 250.0, 500_000);
        assert!(
            (l3.total_percent - 97.72).abs() < 1e-9,
            "{}",
            l3.total_percent
        );
        let p3 = l3.problems();
        assert_eq!(p3.len(), 1, "{p3:?}");
        assert!(p3[0].contains("2.420 ms"), "{}", p3[0]);
    }
}
