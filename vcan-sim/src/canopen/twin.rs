//! What makes the emulated devices a real drive's twin rather than the master's mirror: the
//! things real drives do at power-on that the master must cope with.
//!
//! - **Incremental steering encoders**: the steering drive's position counter is 0 at
//!   power-on (and after a reset node) wherever the wheel points; only a homing gives it a
//!   meaning. `absolute` steering drives report the angle from power-on instead.
//! - **A home switch and an index pulse** on every steering axis, at configurable angles:
//!   the switch is active over `switch_width_rad` on the positive side of its edge (a
//!   "positive home switch") or on the negative side; the index pulse fires once per
//!   steering turn (an output-side index). The drive homes in CiA 402 homing mode (6) with
//!   methods 3–6, 19–22, 33, 34, 35, 37, and shows the switch as bit 2 of its digital
//!   inputs (0x60FD) for a host-side homing.
//! - **Informational EMCY after boot**: a vendor notice with error register 0 when the
//!   device starts (operational).
//! - **Vendor statusword bits** (bits 14 and 15, manufacturer-specific) on every drive.
//! - **A mode display that lags**: 0x6061 follows a write of 0x6060 after `mode_lag_ms`.
//! - **Factory PDOs left on**: the encoders' TPDO2 is enabled at power-on (position value
//!   at every SYNC), until the master disables it.
//! - **Optional objects missing on some types**: encoders have TPDO1 and TPDO2 only;
//!   rolling drives have no gear ratio object 0x6091.
//! - **Long strings**: the device name 0x1008 is longer than 4 bytes (a segmented upload),
//!   and 0x2000:00 is a writable label of up to 32 bytes (a segmented download).
//! - **Motors mounted mirrored** (`mirrored`): the motor's positive direction turns the
//!   joint the negative way; the drive's polarity 0x607E (bit 7 position, bit 6 velocity)
//!   inverts what it reports and takes, as CiA 402 says. The platform file compensates with
//!   a negative `gear_ratio` or 0x607E = 0xC0; the twin's own conversions use the ratio's
//!   magnitude (the machine's gear) and this flag.
//! - **Objects set otherwise at the factory** (`objects`): e.g. a drive whose velocity unit
//!   0x60A9 is rev/min.

use rollbase_control::types::MAX_WHEELS;

/// The steering axis of one wheel, as the machine is built.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SteerAxis {
    /// Angle of the home switch's edge (rad).
    pub switch_edge_rad: f64,
    /// Angular width of the switch's active region (rad); 0: no switch at all.
    pub switch_width_rad: f64,
    /// The active region lies on the positive side of the edge (a positive home switch);
    /// false: on the negative side.
    pub switch_positive: bool,
    /// Angle of the index pulse (once per steering turn; rad).
    pub index_rad: f64,
    /// The steering encoder is absolute: its position is the angle minus `switch_edge_rad`
    /// from power-on (no homing needed).
    pub absolute: bool,
}

impl Default for SteerAxis {
    fn default() -> Self {
        Self {
            switch_edge_rad: 0.0,
            switch_width_rad: std::f64::consts::PI,
            switch_positive: true,
            index_rad: 0.0,
            absolute: false,
        }
    }
}

/// The twin's behaviour (see the module docs); the default is a typical off-the-shelf set.
#[derive(Clone, Debug, PartialEq)]
pub struct TwinConfig {
    /// Steering axes per wheel; `None`: a switch edge and index pulse at the wheel's
    /// `steer_offset_rad` (the angle the platform file gives the home position).
    pub axes: [Option<SteerAxis>; MAX_WHEELS],
    /// EMCY error code sent with error register 0 when a device starts (0: none).
    pub info_emcy: u16,
    /// Manufacturer-specific statusword bits set on every drive.
    pub vendor_status_bits: u16,
    /// Time the mode display 0x6061 takes to follow 0x6060 (ms).
    pub mode_lag_ms: u32,
    /// The encoders' TPDO2 is enabled at power-on (a factory default).
    pub encoder_tpdo2_on: bool,
    /// Delay of a drive's first statusword after the NMT start (ms; the event timer allows
    /// up to its period).
    pub first_status_delay_ms: u32,
    /// Nodes whose motor is mounted mirrored.
    pub mirrored: Vec<u8>,
    /// Object defaults that differ from the twin's: (node, index, sub, value).
    pub objects: Vec<(u8, u16, u8, u32)>,
}

impl Default for TwinConfig {
    fn default() -> Self {
        Self {
            axes: [None; MAX_WHEELS],
            info_emcy: 0xFF01,
            vendor_status_bits: 0xC000,
            mode_lag_ms: 6,
            encoder_tpdo2_on: true,
            first_status_delay_ms: 0,
            mirrored: Vec::new(),
            objects: Vec::new(),
        }
    }
}

impl TwinConfig {
    /// The mirror of the master, as the emulator was before it became a twin: absolute
    /// steering positions, no informational EMCY, no vendor bits, no lag, no factory PDOs.
    pub fn ideal() -> Self {
        let axis = SteerAxis {
            absolute: true,
            ..SteerAxis::default()
        };
        Self {
            axes: [Some(axis); MAX_WHEELS],
            info_emcy: 0,
            vendor_status_bits: 0,
            mode_lag_ms: 0,
            encoder_tpdo2_on: false,
            first_status_delay_ms: 0,
            mirrored: Vec::new(),
            objects: Vec::new(),
        }
    }
}

/// The steering drive's homing in mode 6, as the drive runs it.
#[derive(Clone, Copy, Debug, PartialEq)]
pub(crate) enum HomingRun {
    /// Not homing.
    Idle,
    /// Moving in `dir` until the switch's state changes (`edge`) or the index fires.
    Seek {
        /// Direction (+1 / −1).
        dir: f64,
        /// Looking for the switch edge (else the index pulse).
        edge: bool,
        /// Then look for the index pulse in this direction (methods with index).
        then_index: Option<f64>,
        /// Steering travel so far (rad).
        travel: f64,
    },
    /// Found the home position at this angle (unwrapped); decelerating.
    Stop,
    /// Done: attained.
    Attained,
    /// Failed: homing error.
    Error,
}

/// The switch state at `angle` (wrapped difference to the edge).
pub(crate) fn switch_active(axis: &SteerAxis, angle: f64) -> bool {
    if axis.switch_width_rad <= 0.0 {
        return false;
    }
    let d = rollbase_control::angle::diff(angle, axis.switch_edge_rad);
    if axis.switch_positive {
        d >= 0.0 && d < axis.switch_width_rad
    } else {
        d <= 0.0 && d > -axis.switch_width_rad
    }
}

/// Where a homing method starts: the first seek, or `None` for the current position, or
/// `Err(())` for a method the twin does not emulate.
pub(crate) fn start(method: i8, axis: &SteerAxis, angle: f64) -> Result<Option<HomingRun>, ()> {
    let active = switch_active(axis, angle);
    // Positive home switch (3, 4, 19, 20): inactive → move positive into it; active → move
    // negative out of it. Negative (5, 6, 21, 22): the mirror image.
    let seek_switch = |positive: bool| -> f64 {
        match (positive, active) {
            (true, false) | (false, true) => 1.0,
            _ => -1.0,
        }
    };
    let run = |dir: f64, edge: bool, then_index: Option<f64>| HomingRun::Seek {
        dir,
        edge,
        then_index,
        travel: 0.0,
    };
    Ok(Some(match method {
        19 | 20 => run(seek_switch(true), true, None),
        21 | 22 => run(seek_switch(false), true, None),
        // Index pulse on the negative (3) / positive (4) side of a positive switch's edge.
        3 => run(seek_switch(true), true, Some(-1.0)),
        4 => run(seek_switch(true), true, Some(1.0)),
        // Index on the positive (5) / negative (6) side of a negative switch's edge.
        5 => run(seek_switch(false), true, Some(1.0)),
        6 => run(seek_switch(false), true, Some(-1.0)),
        33 => run(-1.0, false, None),
        34 => run(1.0, false, None),
        35 | 37 => return Ok(None),
        _ => return Err(()),
    }))
}

/// The axis as a drive whose positive direction is `sign` × the joint's sees it (sign −1:
/// a mirrored motor, or an inverted polarity).
pub(crate) fn axis_in(axis: &SteerAxis, sign: f64) -> SteerAxis {
    if sign >= 0.0 {
        return *axis;
    }
    SteerAxis {
        switch_edge_rad: -axis.switch_edge_rad,
        switch_positive: !axis.switch_positive,
        index_rad: -axis.index_rad,
        ..*axis
    }
}

/// True when moving from `a` to `b` (unwrapped, one tick apart) passed angle `x` (wrapped).
pub(crate) fn crossed(a: f64, b: f64, x: f64) -> Option<f64> {
    let da = rollbase_control::angle::diff(a, x);
    let db = da + (b - a);
    if (da < 0.0 && db >= 0.0) || (da > 0.0 && db <= 0.0) || (da == 0.0 && db != 0.0) {
        // The crossing's unwrapped angle.
        Some(a - da)
    } else {
        None
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn switches_and_crossings() {
        let axis = SteerAxis {
            switch_edge_rad: 0.3,
            ..SteerAxis::default()
        };
        assert!(switch_active(&axis, 0.31));
        assert!(!switch_active(&axis, 0.29));
        assert!(!switch_active(&axis, 0.3 + 3.2));
        let neg = SteerAxis {
            switch_positive: false,
            ..axis
        };
        assert!(switch_active(&neg, 0.29));
        assert!(!switch_active(&neg, 0.31));
        assert!((crossed(0.29, 0.31, 0.3).unwrap() - 0.3).abs() < 1e-12);
        assert!((crossed(6.25, 6.35, 0.0).unwrap() - std::f64::consts::TAU).abs() < 1e-12);
        assert_eq!(crossed(0.31, 0.32, 0.3), None);
        // From inside a positive switch the search goes negative, from outside positive.
        assert!(
            matches!(start(19, &axis, 1.0), Ok(Some(HomingRun::Seek { dir, .. })) if dir < 0.0)
        );
        assert!(
            matches!(start(19, &axis, -1.0), Ok(Some(HomingRun::Seek { dir, .. })) if dir > 0.0)
        );
        assert_eq!(start(37, &axis, 1.0), Ok(None));
        assert_eq!(start(1, &axis, 1.0), Err(()));
    }
}
