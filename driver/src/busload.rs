//! Bus-load calculator with worst-case bit stuffing, derived from the message table.
//!
//! A classic base-format (11-bit id) data frame with `n` data bytes has
//! 1 (SOF) + 11 (id) + 1 (RTR) + 1 (IDE) + 1 (r0) + 4 (DLC) + 8n (data) + 15 (CRC) = 34 + 8n
//! bits that are subject to bit stuffing, then 1 (CRC delimiter) + 2 (ACK) + 7 (EOF) + 3
//! (intermission) = 13 fixed bits: 47 + 8n bits without stuffing. In the worst case a stuff
//! bit follows the first 5 equal bits and then every 4 bits (the stuff bit itself starts the
//! next run), giving ⌊(34 + 8n − 1)/4⌋ stuff bits, so
//!
//! `frame_bits(n) = 8n + 47 + ⌊(33 + 8n)/4⌋`  (n = 0..8: 55 … 135 bits).
//!
//! The cyclic load per control cycle is one SYNC, one SETPOINT per module and one
//! FEEDBACK_A + FEEDBACK_B per module; STATUS adds `modules × status_hz` frames per second.

use std::fmt;

/// The controller's default feedback window after SYNC (s): the time the devices' answers
/// have to arrive before the control step. `rollbase_control`'s runtime takes its default
/// from here, so the bus-load reports compare against the value the controller uses.
pub const DEFAULT_FEEDBACK_WINDOW_S: f64 = 0.002;

use crate::protocol::{spec, MessageKind, BITRATE, MAX_NODE};

/// Worst-case bits on the wire (including stuffing and intermission) of a classic
/// base-format data frame with `n_data_bytes` bytes.
pub fn frame_bits(n_data_bytes: usize) -> u32 {
    let n = n_data_bytes.min(8) as u32;
    8 * n + 47 + (33 + 8 * n) / 4
}

/// A bus configuration to evaluate.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct BusLoadConfig {
    /// Number of wheel modules (1..=15).
    pub modules: usize,
    /// Control cycle rate, Hz.
    pub cycle_hz: f64,
    /// Bit rate, bit/s.
    pub bitrate: u32,
    /// STATUS rate per module, Hz.
    pub status_hz: f64,
}

impl Default for BusLoadConfig {
    /// 4 modules, 250 Hz, 1 Mbit/s, STATUS at the table's period (10 Hz).
    fn default() -> Self {
        let status_hz = spec(MessageKind::Status)
            .period_ms
            .map_or(10.0, |p| 1000.0 / p);
        BusLoadConfig {
            modules: 4,
            cycle_hz: 250.0,
            bitrate: BITRATE,
            status_hz,
        }
    }
}

/// A [`BusLoadConfig`] field is invalid.
#[derive(Debug, Clone, Copy, PartialEq, thiserror::Error)]
pub enum BusLoadError {
    /// Module count outside 1..=15.
    #[error("modules = {0} is outside 1..=15 (node ids are 4 bits)")]
    Modules(usize),
    /// A rate is not a positive finite number.
    #[error("{field} = {value} must be a positive finite number")]
    Rate {
        /// Field name.
        field: &'static str,
        /// Rejected value.
        value: f64,
    },
}

/// One row of the report: one message kind.
#[derive(Debug, Clone, PartialEq)]
pub struct BusLoadRow {
    /// Message name.
    pub name: &'static str,
    /// Data bytes.
    pub dlc: u8,
    /// Worst-case bits per frame.
    pub bits_per_frame: u32,
    /// Frames per control cycle (fractional for STATUS).
    pub frames_per_cycle: f64,
    /// Frames per second.
    pub frames_per_s: f64,
    /// Bits per second.
    pub bits_per_s: f64,
    /// Share of the bit rate, %.
    pub load_percent: f64,
}

/// Bus-load report for a configuration.
#[derive(Debug, Clone, PartialEq)]
pub struct BusLoadReport {
    /// The evaluated configuration.
    pub config: BusLoadConfig,
    /// One row per message kind.
    pub rows: Vec<BusLoadRow>,
    /// Worst-case bits of the cyclic frames of one control cycle (SYNC, SETPOINTs, FEEDBACKs).
    pub cyclic_bits_per_cycle: u32,
    /// Bits the bus can carry in one control cycle.
    pub bits_available_per_cycle: f64,
    /// Cyclic load, % (cyclic bits / available bits per cycle).
    pub cyclic_percent: f64,
    /// Total bits per second, all messages.
    pub total_bits_per_s: f64,
    /// Total load, %.
    pub total_percent: f64,
}

/// Computes the worst-case bus load of `config`.
pub fn bus_load(config: &BusLoadConfig) -> Result<BusLoadReport, BusLoadError> {
    if config.modules == 0 || config.modules > usize::from(MAX_NODE) {
        return Err(BusLoadError::Modules(config.modules));
    }
    let bitrate = f64::from(config.bitrate);
    for (field, value) in [
        ("cycle_hz", config.cycle_hz),
        ("bitrate", bitrate),
        ("status_hz", config.status_hz),
    ] {
        if !(value.is_finite() && value > 0.0) {
            return Err(BusLoadError::Rate { field, value });
        }
    }
    // modules ≤ 15 was checked above.
    let n = config.modules as f64;
    let mut rows = Vec::with_capacity(MessageKind::ALL.len());
    let mut cyclic_bits = 0u32;
    for kind in MessageKind::ALL {
        let m = spec(kind);
        let bits = frame_bits(usize::from(m.dlc));
        let frames_per_cycle = match kind {
            MessageKind::Sync => 1.0,
            MessageKind::Setpoint | MessageKind::FeedbackA | MessageKind::FeedbackB => n,
            MessageKind::Status => n * config.status_hz / config.cycle_hz,
        };
        if kind != MessageKind::Status {
            // Integral frame counts for the cyclic messages.
            cyclic_bits += bits * frames_per_cycle as u32;
        }
        let frames_per_s = frames_per_cycle * config.cycle_hz;
        let bits_per_s = frames_per_s * f64::from(bits);
        rows.push(BusLoadRow {
            name: m.name,
            dlc: m.dlc,
            bits_per_frame: bits,
            frames_per_cycle,
            frames_per_s,
            bits_per_s,
            load_percent: 100.0 * bits_per_s / bitrate,
        });
    }
    let total_bits_per_s: f64 = rows.iter().map(|r| r.bits_per_s).sum();
    let available = bitrate / config.cycle_hz;
    Ok(BusLoadReport {
        config: *config,
        rows,
        cyclic_bits_per_cycle: cyclic_bits,
        bits_available_per_cycle: available,
        cyclic_percent: 100.0 * f64::from(cyclic_bits) / available,
        total_bits_per_s,
        total_percent: 100.0 * total_bits_per_s / bitrate,
    })
}

/// The printable report of `config`: the table of [`BusLoadReport`]'s `Display`, or one line
/// naming the invalid field. Use [`bus_load`] when the caller must act on an invalid config.
pub fn report(config: &BusLoadConfig) -> String {
    match bus_load(config) {
        Ok(r) => format!("{r}\n"),
        Err(e) => format!("invalid bus-load configuration: {e}\n"),
    }
}

impl fmt::Display for BusLoadReport {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let c = &self.config;
        writeln!(
            f,
            "Bus load: {} modules, {} Hz cycle ({:.3} ms), {} bit/s, STATUS {} Hz per module",
            c.modules,
            c.cycle_hz,
            1000.0 / c.cycle_hz,
            c.bitrate,
            c.status_hz
        )?;
        write_table(
            f,
            "message",
            10,
            &self.rows,
            self.total_bits_per_s,
            self.total_percent,
        )?;
        writeln!(f)?;
        writeln!(
            f,
            "cyclic frames per cycle: {} bits of {:.0} available = {:.2}% (budget 50%)",
            self.cyclic_bits_per_cycle, self.bits_available_per_cycle, self.cyclic_percent
        )?;
        write!(f, "total with STATUS: {:.2}%", self.total_percent)
    }
}

/// Writes the frame-length formula and the per-frame load table (one row per frame kind and
/// a total row) shared by every profile's report; `label` heads the first column, `width`
/// is its width.
pub(crate) fn write_table(
    f: &mut fmt::Formatter<'_>,
    label: &str,
    width: usize,
    rows: &[BusLoadRow],
    total_bits_per_s: f64,
    total_percent: f64,
) -> fmt::Result {
    writeln!(
        f,
        "worst-case frame bits = 8n + 47 + floor((33 + 8n)/4) (classic 11-bit id, full bit stuffing)"
    )?;
    writeln!(f)?;
    writeln!(
        f,
        "| {label:<width$} | DLC | bits/frame | frames/cycle | frames/s | bit/s    | load %  |"
    )?;
    writeln!(
        f,
        "|-{}-|-----|------------|--------------|----------|----------|---------|",
        "-".repeat(width)
    )?;
    for r in rows {
        writeln!(
            f,
            "| {:<width$} | {:>3} | {:>10} | {:>12.3} | {:>8.1} | {:>8.0} | {:>6.2}% |",
            r.name,
            r.dlc,
            r.bits_per_frame,
            r.frames_per_cycle,
            r.frames_per_s,
            r.bits_per_s,
            r.load_percent
        )?;
    }
    writeln!(
        f,
        "| {:<width$} |     |            | {:>12.3} | {:>8.1} | {:>8.0} | {:>6.2}% |",
        "total",
        rows.iter().map(|r| r.frames_per_cycle).sum::<f64>(),
        rows.iter().map(|r| r.frames_per_s).sum::<f64>(),
        total_bits_per_s,
        total_percent
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn frame_bits_formula() {
        // n = 0: 0 + 47 + 8 = 55; n = 8: 64 + 47 + 24 = 135 (standard textbook values).
        assert_eq!(frame_bits(0), 55);
        assert_eq!(frame_bits(4), 95);
        assert_eq!(frame_bits(6), 115);
        assert_eq!(frame_bits(8), 135);
    }

    #[test]
    fn default_four_wheels_at_250_hz_is_below_half_of_1_mbit() {
        let r = bus_load(&BusLoadConfig::default()).expect("valid config");
        // SYNC 95 + 4 × SETPOINT 115 + 8 × FEEDBACK 135 = 1635 bits per 4000-bit cycle.
        assert_eq!(r.cyclic_bits_per_cycle, 1635);
        assert!(
            (r.cyclic_percent - 40.875).abs() < 1e-9,
            "{}",
            r.cyclic_percent
        );
        // + STATUS 4 × 10 Hz × 115 bits = 4600 bit/s = 0.46 %.
        assert!(
            (r.total_percent - 41.335).abs() < 1e-9,
            "{}",
            r.total_percent
        );
        assert!(r.total_percent < 50.0);
        let table = r.to_string();
        assert!(table.contains("FEEDBACK_A"));
        assert!(table.contains("41.34%"), "{table}");
    }

    #[test]
    fn invalid_configs_name_the_field() {
        let bad = BusLoadConfig {
            modules: 16,
            ..BusLoadConfig::default()
        };
        assert_eq!(bus_load(&bad), Err(BusLoadError::Modules(16)));
        let bad = BusLoadConfig {
            cycle_hz: 0.0,
            ..BusLoadConfig::default()
        };
        let e = bus_load(&bad).expect_err("zero rate");
        assert!(e.to_string().contains("cycle_hz"));
        assert!(report(&bad).contains("cycle_hz"));
        assert!(report(&BusLoadConfig::default()).contains("total with STATUS: 41.34%"));
    }

    #[test]
    fn six_wheels_at_250_hz_exceed_the_budget() {
        // 95 + 6·115 + 12·135 = 2405 bits of 4000 = 60 %: shows the budget is binding.
        let r = bus_load(&BusLoadConfig {
            modules: 6,
            ..BusLoadConfig::default()
        })
        .expect("valid");
        assert_eq!(r.cyclic_bits_per_cycle, 2405);
        assert!(r.cyclic_percent > 50.0);
    }
}
