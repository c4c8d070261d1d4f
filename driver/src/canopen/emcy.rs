//! Emergency (EMCY) messages: id 0x080 + node, 8 bytes
//! `[error code (UNSIGNED16, LE), error register (0x1001), 5 manufacturer-specific bytes]`.
//!
//! A device sends one EMCY when an error occurs and one with error code 0x0000 ("error
//! reset or no error") when its errors are cleared. The error-code classes are CiA 301
//! table 21; the codes in [`codes`] are those CiA 301 and CiA 402 assign and that the
//! simulated devices raise.

use super::cob;
use super::CanOpenError;
use crate::frame::CanFrame;

/// Error codes used by this profile.
pub mod codes {
    /// Error reset or no error.
    pub const NO_ERROR: u16 = 0x0000;
    /// Generic error.
    pub const GENERIC: u16 = 0x1000;
    /// CiA 402: continuous over-current (device output side).
    pub const OVERCURRENT: u16 = 0x2310;
    /// DC-link over-voltage.
    pub const DC_LINK_OVERVOLTAGE: u16 = 0x3210;
    /// Device (drive) over-temperature.
    pub const DRIVE_TEMPERATURE: u16 = 0x4310;
    /// Position sensor (encoder) fault.
    pub const SENSOR: u16 = 0x7305;
    /// CAN overrun (objects lost).
    pub const CAN_OVERRUN: u16 = 0x8110;
    /// CAN in error-passive mode.
    pub const CAN_PASSIVE: u16 = 0x8120;
    /// Life guard or heartbeat consumer error: the master's heartbeat stopped.
    pub const HEARTBEAT: u16 = 0x8130;
    /// Recovered from bus-off.
    pub const BUS_OFF_RECOVERED: u16 = 0x8140;
    /// PDO not processed due to a length error.
    pub const PDO_LENGTH: u16 = 0x8210;
    /// RPDO timeout: no RPDO within its deadline (0x1400:05).
    pub const RPDO_TIMEOUT: u16 = 0x8250;
}

/// One emergency message.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub struct Emcy {
    /// Error code.
    pub code: u16,
    /// Error register (0x1001): bit 0 generic, 1 current, 2 voltage, 3 temperature,
    /// 4 communication, 5 device profile specific, 7 manufacturer specific.
    pub register: u8,
    /// Manufacturer-specific bytes.
    pub vendor: [u8; 5],
}

impl Emcy {
    /// An EMCY with no manufacturer-specific data.
    pub fn new(code: u16, register: u8) -> Self {
        Self {
            code,
            register,
            vendor: [0; 5],
        }
    }

    /// The frame from `node`.
    pub fn to_frame(&self, node: u8) -> CanFrame {
        let c = self.code.to_le_bytes();
        let v = self.vendor;
        let d = [c[0], c[1], self.register, v[0], v[1], v[2], v[3], v[4]];
        CanFrame::new(cob::emcy(node), &d)
            .unwrap_or_else(|_| unreachable!("EMCY frames are always valid"))
    }

    /// Parses an EMCY frame: (node, message). Shorter frames than 8 bytes are accepted
    /// when they carry at least the error code and register (some devices truncate).
    pub fn parse(f: &CanFrame) -> Result<(u8, Emcy), CanOpenError> {
        let cob::Cob::Emcy(node) = cob::classify(f.id()) else {
            return Err(CanOpenError::WrongId {
                what: "EMCY",
                id: f.id(),
            });
        };
        let d = f.data();
        if d.len() < 3 {
            return Err(CanOpenError::WrongLength {
                what: "EMCY (at least)",
                id: f.id(),
                got: d.len(),
                expected: 3,
            });
        }
        let mut vendor = [0u8; 5];
        for (o, b) in vendor.iter_mut().zip(&d[3..]) {
            *o = *b;
        }
        Ok((
            node,
            Emcy {
                code: u16::from_le_bytes([d[0], d[1]]),
                register: d[2],
                vendor,
            },
        ))
    }

    /// True for the "error reset / no error" message.
    pub fn is_reset(&self) -> bool {
        self.code == codes::NO_ERROR
    }
}

/// True for an EMCY that reports no active error, so is logged and counted but is not a
/// fault: the error reset (code 0), an error register of 0 (CiA 301: bit 0, generic error,
/// is set while any error is active, so 0 means none is: a vendor's notice such as 0xFF01),
/// the CAN warnings 0x8120 (error passive) and 0x8140 (recovered from bus-off), and the
/// codes in `extra` (the platform file's `informational_emcy`).
pub fn is_informational(e: &Emcy, extra: &[u16]) -> bool {
    e.code == codes::NO_ERROR
        || e.register == 0
        || matches!(e.code, codes::CAN_PASSIVE | codes::BUS_OFF_RECOVERED)
        || extra.contains(&e.code)
}

/// The class of an error code (CiA 301 table 21), or the specific meaning for the codes in
/// [`codes`].
pub fn describe(code: u16) -> &'static str {
    match code {
        codes::NO_ERROR => "error reset or no error",
        codes::OVERCURRENT => "continuous over-current",
        codes::DC_LINK_OVERVOLTAGE => "DC-link over-voltage",
        codes::DRIVE_TEMPERATURE => "drive over-temperature",
        codes::SENSOR => "position sensor fault",
        codes::CAN_OVERRUN => "CAN overrun, objects lost",
        codes::CAN_PASSIVE => "CAN in error-passive mode",
        codes::HEARTBEAT => "heartbeat consumer timeout (master heartbeat lost)",
        codes::BUS_OFF_RECOVERED => "recovered from bus-off",
        codes::PDO_LENGTH => "PDO not processed: length error",
        codes::RPDO_TIMEOUT => "RPDO timeout (no setpoint within the deadline)",
        _ => match code >> 12 {
            0x1 => "generic error",
            0x2 => "current error",
            0x3 => "voltage error",
            0x4 => "temperature error",
            0x5 => "device hardware error",
            0x6 => "device software error",
            0x7 => "additional modules error",
            0x8 => "monitoring (communication or control) error",
            0x9 => "external error",
            0xF if code >> 8 == 0xFF => "device-specific error",
            0xF => "additional functions error",
            _ => "unknown error class",
        },
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn golden_emcy() {
        // Over-current on node 4, error register bit 1 (current): 10 23 02 00 00 00 00 00.
        let f = Emcy::new(codes::OVERCURRENT, 0x02).to_frame(4);
        assert_eq!(f.id(), 0x084);
        assert_eq!(f.data(), &[0x10, 0x23, 0x02, 0, 0, 0, 0, 0]);
        assert_eq!(
            Emcy::parse(&f),
            Ok((4, Emcy::new(codes::OVERCURRENT, 0x02)))
        );
        // Error reset: all zero.
        let f = Emcy::new(codes::NO_ERROR, 0).to_frame(4);
        assert_eq!(f.data(), &[0; 8]);
        assert!(Emcy::parse(&f).unwrap().1.is_reset());
        // Heartbeat consumer error, register bit 4 (communication).
        let f = Emcy::new(codes::HEARTBEAT, 0x11).to_frame(0x7F);
        assert_eq!(
            (f.id(), f.data()),
            (0x0FF, &[0x30, 0x81, 0x11, 0, 0, 0, 0, 0][..])
        );
        // Manufacturer bytes are kept, truncated frames accepted, too short ones refused.
        let f = CanFrame::new(0x085, &[0x00, 0x50, 0x01, 0xAA, 0xBB]).unwrap();
        let (n, e) = Emcy::parse(&f).unwrap();
        assert_eq!((n, e.code, e.vendor), (5, 0x5000, [0xAA, 0xBB, 0, 0, 0]));
        assert!(Emcy::parse(&CanFrame::new(0x085, &[0x10, 0x23]).unwrap()).is_err());
        assert!(Emcy::parse(&CanFrame::new(0x080, &[0; 8]).unwrap()).is_err());
    }

    #[test]
    fn classes() {
        assert_eq!(describe(0x2310), "continuous over-current");
        assert_eq!(describe(0x2311), "current error");
        assert_eq!(
            describe(0x8611),
            "monitoring (communication or control) error"
        );
        assert_eq!(describe(0xFF01), "device-specific error");
    }
}
