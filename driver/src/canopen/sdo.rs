//! Expedited SDO transfers (CiA 301 7.2.4.3): requests, responses and abort codes.
//!
//! Every SDO frame has 8 data bytes: byte 0 is the command specifier, bytes 1–2 the object
//! index (little-endian), byte 3 the sub-index, bytes 4–7 data or an abort code.
//!
//! | frame | byte 0 | bytes 4–7 |
//! |---|---|---|
//! | download request, n = 1..4 bytes | `0x23`/`0x27`/`0x2B`/`0x2F` (ccs 1, e = s = 1, 4 − n in bits 2–3) | data, zero padded |
//! | download response | `0x60` (scs 3) | 0 |
//! | upload request | `0x40` (ccs 2) | 0 |
//! | upload response, expedited | `0x43`/`0x47`/`0x4B`/`0x4F` (scs 2, e = s = 1), or `0x42` (size not indicated: 4 bytes) | data |
//! | upload response, segmented | `0x41` (e = 0, s = 1) | object size |
//! | abort | `0x80` | abort code (UNSIGNED32) |
//!
//! Every object this profile reads or writes is at most 4 bytes, so only expedited
//! transfers are implemented; a device that answers an upload with a segmented transfer is
//! reported as such ([`SdoResponse::UploadSegmented`]), never misread.

use super::cob;
use super::CanOpenError;
use crate::frame::CanFrame;

/// An SDO abort code (CiA 301 table 22), as a typed enum; unknown codes are kept.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum AbortCode {
    /// 0x05030000 toggle bit not alternated.
    ToggleBit,
    /// 0x05040000 SDO protocol timed out.
    Timeout,
    /// 0x05040001 client/server command specifier not valid or unknown.
    InvalidCommand,
    /// 0x05040005 out of memory.
    OutOfMemory,
    /// 0x06010000 unsupported access to an object.
    UnsupportedAccess,
    /// 0x06010001 attempt to read a write-only object.
    WriteOnly,
    /// 0x06010002 attempt to write a read-only object.
    ReadOnly,
    /// 0x06020000 object does not exist in the object dictionary.
    NoObject,
    /// 0x06040041 object cannot be mapped to the PDO.
    NotMappable,
    /// 0x06040042 the number and length of the objects to be mapped would exceed the PDO
    /// length.
    PdoLength,
    /// 0x06040043 general parameter incompatibility.
    ParameterIncompatible,
    /// 0x06040047 general internal incompatibility in the device.
    InternalIncompatible,
    /// 0x06060000 access failed due to a hardware error.
    Hardware,
    /// 0x06070010 data type does not match, length of service parameter does not match.
    LengthMismatch,
    /// 0x06070012 data type does not match, length of service parameter too high.
    LengthTooHigh,
    /// 0x06070013 data type does not match, length of service parameter too low.
    LengthTooLow,
    /// 0x06090011 sub-index does not exist.
    NoSubIndex,
    /// 0x06090030 invalid value for parameter (download only).
    InvalidValue,
    /// 0x06090031 value of parameter written too high.
    ValueTooHigh,
    /// 0x06090032 value of parameter written too low.
    ValueTooLow,
    /// 0x08000000 general error.
    General,
    /// 0x08000020 data cannot be transferred or stored to the application.
    CannotStore,
    /// 0x08000021 … because of local control.
    LocalControl,
    /// 0x08000022 … because of the present device state.
    DeviceState,
    /// Any other code.
    Other(u32),
}

impl AbortCode {
    const TABLE: [(AbortCode, u32, &'static str); 24] = [
        (Self::ToggleBit, 0x0503_0000, "toggle bit not alternated"),
        (Self::Timeout, 0x0504_0000, "SDO protocol timed out"),
        (
            Self::InvalidCommand,
            0x0504_0001,
            "command specifier not valid or unknown",
        ),
        (Self::OutOfMemory, 0x0504_0005, "out of memory"),
        (
            Self::UnsupportedAccess,
            0x0601_0000,
            "unsupported access to an object",
        ),
        (
            Self::WriteOnly,
            0x0601_0001,
            "attempt to read a write-only object",
        ),
        (
            Self::ReadOnly,
            0x0601_0002,
            "attempt to write a read-only object",
        ),
        (Self::NoObject, 0x0602_0000, "object does not exist"),
        (
            Self::NotMappable,
            0x0604_0041,
            "object cannot be mapped to the PDO",
        ),
        (
            Self::PdoLength,
            0x0604_0042,
            "mapped objects would exceed the PDO length",
        ),
        (
            Self::ParameterIncompatible,
            0x0604_0043,
            "general parameter incompatibility",
        ),
        (
            Self::InternalIncompatible,
            0x0604_0047,
            "general internal incompatibility in the device",
        ),
        (
            Self::Hardware,
            0x0606_0000,
            "access failed due to a hardware error",
        ),
        (
            Self::LengthMismatch,
            0x0607_0010,
            "data type or length does not match",
        ),
        (Self::LengthTooHigh, 0x0607_0012, "data length too high"),
        (Self::LengthTooLow, 0x0607_0013, "data length too low"),
        (Self::NoSubIndex, 0x0609_0011, "sub-index does not exist"),
        (
            Self::InvalidValue,
            0x0609_0030,
            "invalid value for parameter",
        ),
        (Self::ValueTooHigh, 0x0609_0031, "value written too high"),
        (Self::ValueTooLow, 0x0609_0032, "value written too low"),
        (Self::General, 0x0800_0000, "general error"),
        (
            Self::CannotStore,
            0x0800_0020,
            "data cannot be transferred or stored to the application",
        ),
        (
            Self::LocalControl,
            0x0800_0021,
            "data cannot be transferred or stored because of local control",
        ),
        (
            Self::DeviceState,
            0x0800_0022,
            "data cannot be transferred or stored in the present device state",
        ),
    ];

    /// The wire value.
    pub fn code(self) -> u32 {
        if let Self::Other(c) = self {
            return c;
        }
        Self::TABLE
            .iter()
            .find(|(a, _, _)| *a == self)
            .map_or(0, |(_, c, _)| *c)
    }

    /// The enum value of a wire code.
    pub fn from_code(code: u32) -> Self {
        Self::TABLE
            .iter()
            .find(|(_, c, _)| *c == code)
            .map_or(Self::Other(code), |(a, _, _)| *a)
    }

    /// What the code means (CiA 301's wording, shortened).
    pub fn description(self) -> &'static str {
        Self::TABLE
            .iter()
            .find(|(a, _, _)| *a == self)
            .map_or("unknown abort code", |(_, _, d)| d)
    }
}

impl std::fmt::Display for AbortCode {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "0x{:08X} ({})", self.code(), self.description())
    }
}

/// Up to 4 data bytes of an expedited transfer.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub struct SdoData {
    bytes: [u8; 4],
    len: u8,
}

impl SdoData {
    /// `len` (1..=4, clamped) little-endian bytes of `value`.
    pub fn new(value: u32, len: u8) -> Self {
        Self {
            bytes: value.to_le_bytes(),
            len: len.clamp(1, 4),
        }
        .masked()
    }

    fn masked(mut self) -> Self {
        for b in &mut self.bytes[usize::from(self.len)..] {
            *b = 0;
        }
        self
    }

    /// An UNSIGNED8 / INTEGER8 value.
    pub fn u8(v: u8) -> Self {
        Self::new(u32::from(v), 1)
    }
    /// An UNSIGNED16 value.
    pub fn u16(v: u16) -> Self {
        Self::new(u32::from(v), 2)
    }
    /// An INTEGER16 value.
    pub fn i16(v: i16) -> Self {
        Self::new(u32::from(v as u16), 2)
    }
    /// An UNSIGNED32 value.
    pub fn u32(v: u32) -> Self {
        Self::new(v, 4)
    }
    /// An INTEGER8 value.
    pub fn i8(v: i8) -> Self {
        Self::new(u32::from(v as u8), 1)
    }

    /// The meaningful bytes.
    pub fn bytes(&self) -> &[u8] {
        &self.bytes[..usize::from(self.len)]
    }

    /// Number of bytes (1..=4).
    pub fn len(&self) -> usize {
        usize::from(self.len)
    }

    /// Always false: an expedited transfer carries at least one byte.
    pub fn is_empty(&self) -> bool {
        false
    }

    /// The bytes as an unsigned little-endian value.
    pub fn as_u32(&self) -> u32 {
        u32::from_le_bytes(self.bytes)
    }

    /// The bytes as a sign-extended little-endian value.
    pub fn as_i32(&self) -> i32 {
        let shift = 32 - 8 * u32::from(self.len);
        ((self.as_u32() << shift) as i32) >> shift
    }
}

/// A request from the client (master) to a device's SDO server.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum SdoRequest {
    /// Expedited download (write) of `data` to `index:sub`.
    Download {
        /// Object index.
        index: u16,
        /// Sub-index.
        sub: u8,
        /// 1..=4 bytes.
        data: SdoData,
    },
    /// Upload (read) of `index:sub`.
    Upload {
        /// Object index.
        index: u16,
        /// Sub-index.
        sub: u8,
    },
    /// The client aborts the transfer.
    Abort {
        /// Object index.
        index: u16,
        /// Sub-index.
        sub: u8,
        /// Why.
        code: AbortCode,
    },
}

/// A response of a device's SDO server.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum SdoResponse {
    /// The download to `index:sub` was accepted.
    DownloadAck {
        /// Object index.
        index: u16,
        /// Sub-index.
        sub: u8,
    },
    /// An expedited upload of `index:sub`.
    Upload {
        /// Object index.
        index: u16,
        /// Sub-index.
        sub: u8,
        /// The value (4 bytes when the server did not indicate the size).
        data: SdoData,
    },
    /// The server started a segmented upload (the object is longer than 4 bytes or the
    /// server always segments); not supported by this client.
    UploadSegmented {
        /// Object index.
        index: u16,
        /// Sub-index.
        sub: u8,
        /// Size in bytes, when indicated.
        size: Option<u32>,
    },
    /// The server aborted the transfer.
    Abort {
        /// Object index.
        index: u16,
        /// Sub-index.
        sub: u8,
        /// Why.
        code: AbortCode,
    },
}

impl SdoResponse {
    /// The object the response is about.
    pub fn object(&self) -> (u16, u8) {
        match *self {
            Self::DownloadAck { index, sub }
            | Self::Upload { index, sub, .. }
            | Self::UploadSegmented { index, sub, .. }
            | Self::Abort { index, sub, .. } => (index, sub),
        }
    }
}

impl SdoRequest {
    /// The object the request is about.
    pub fn object(&self) -> (u16, u8) {
        match *self {
            Self::Download { index, sub, .. }
            | Self::Upload { index, sub }
            | Self::Abort { index, sub, .. } => (index, sub),
        }
    }
}

fn sdo_frame(id: u16, cs: u8, index: u16, sub: u8, tail: [u8; 4]) -> CanFrame {
    let i = index.to_le_bytes();
    let d = [cs, i[0], i[1], sub, tail[0], tail[1], tail[2], tail[3]];
    // SDO ids are ≤ 0x67F and the payload is 8 bytes.
    CanFrame::new(id, &d).unwrap_or_else(|_| unreachable!("SDO frames are always valid"))
}

fn expedited_cs(base: u8, len: usize) -> u8 {
    // n = number of bytes in 4..7 that do not contain data, in bits 2..3; e = s = 1.
    base | (((4 - len.clamp(1, 4)) as u8) << 2) | 0x03
}

fn header(f: &CanFrame, what: &'static str) -> Result<(u8, u16, u8, [u8; 4]), CanOpenError> {
    if f.len() != 8 {
        return Err(CanOpenError::WrongLength {
            what,
            id: f.id(),
            got: f.len(),
            expected: 8,
        });
    }
    let d = f.data();
    Ok((
        d[0],
        u16::from_le_bytes([d[1], d[2]]),
        d[3],
        [d[4], d[5], d[6], d[7]],
    ))
}

impl SdoRequest {
    /// The request frame to `node`'s server (id 0x600 + node).
    pub fn to_frame(&self, node: u8) -> CanFrame {
        let id = cob::sdo_rx(node);
        match *self {
            Self::Download { index, sub, data } => {
                sdo_frame(id, expedited_cs(0x20, data.len()), index, sub, data.bytes)
            }
            Self::Upload { index, sub } => sdo_frame(id, 0x40, index, sub, [0; 4]),
            Self::Abort { index, sub, code } => {
                sdo_frame(id, 0x80, index, sub, code.code().to_le_bytes())
            }
        }
    }

    /// Parses a request frame (id 0x600 + node): (node, request). Segmented and block
    /// transfers are reported as [`CanOpenError::BadValue`] of the command byte.
    pub fn parse(f: &CanFrame) -> Result<(u8, SdoRequest), CanOpenError> {
        let cob::Cob::SdoRx(node) = cob::classify(f.id()) else {
            return Err(CanOpenError::WrongId {
                what: "SDO request",
                id: f.id(),
            });
        };
        let (cs, index, sub, tail) = header(f, "SDO request")?;
        let req = match cs >> 5 {
            1 if cs & 0x02 != 0 => {
                // Expedited download; without the size bit all 4 bytes count.
                let len = if cs & 0x01 != 0 {
                    4 - usize::from((cs >> 2) & 0x03)
                } else {
                    4
                };
                SdoRequest::Download {
                    index,
                    sub,
                    data: SdoData {
                        bytes: tail,
                        len: len as u8,
                    }
                    .masked(),
                }
            }
            2 => SdoRequest::Upload { index, sub },
            4 => SdoRequest::Abort {
                index,
                sub,
                code: AbortCode::from_code(u32::from_le_bytes(tail)),
            },
            _ => {
                return Err(CanOpenError::BadValue {
                    what: "SDO client command specifier (only expedited transfers are served)",
                    value: cs,
                })
            }
        };
        Ok((node, req))
    }
}

impl SdoResponse {
    /// The response frame from `node`'s server (id 0x580 + node).
    pub fn to_frame(&self, node: u8) -> CanFrame {
        let id = cob::sdo_tx(node);
        match *self {
            Self::DownloadAck { index, sub } => sdo_frame(id, 0x60, index, sub, [0; 4]),
            Self::Upload { index, sub, data } => {
                sdo_frame(id, expedited_cs(0x40, data.len()), index, sub, data.bytes)
            }
            Self::UploadSegmented { index, sub, size } => match size {
                Some(s) => sdo_frame(id, 0x41, index, sub, s.to_le_bytes()),
                None => sdo_frame(id, 0x40, index, sub, [0; 4]),
            },
            Self::Abort { index, sub, code } => {
                sdo_frame(id, 0x80, index, sub, code.code().to_le_bytes())
            }
        }
    }

    /// Parses a response frame (id 0x580 + node): (node, response).
    pub fn parse(f: &CanFrame) -> Result<(u8, SdoResponse), CanOpenError> {
        let cob::Cob::SdoTx(node) = cob::classify(f.id()) else {
            return Err(CanOpenError::WrongId {
                what: "SDO response",
                id: f.id(),
            });
        };
        let (cs, index, sub, tail) = header(f, "SDO response")?;
        let resp = match cs >> 5 {
            3 => SdoResponse::DownloadAck { index, sub },
            2 if cs & 0x02 != 0 => {
                let len = if cs & 0x01 != 0 {
                    4 - usize::from((cs >> 2) & 0x03)
                } else {
                    4
                };
                SdoResponse::Upload {
                    index,
                    sub,
                    data: SdoData {
                        bytes: tail,
                        len: len as u8,
                    }
                    .masked(),
                }
            }
            2 => SdoResponse::UploadSegmented {
                index,
                sub,
                size: (cs & 0x01 != 0).then(|| u32::from_le_bytes(tail)),
            },
            4 => SdoResponse::Abort {
                index,
                sub,
                code: AbortCode::from_code(u32::from_le_bytes(tail)),
            },
            _ => {
                return Err(CanOpenError::BadValue {
                    what: "SDO server command specifier",
                    value: cs,
                })
            }
        };
        Ok((node, resp))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    #[test]
    fn golden_expedited_download() {
        // Write 0x6060:00 = 9 (INTEGER8) to node 3: 2F 60 60 00 09 00 00 00 on 0x603.
        let f = SdoRequest::Download {
            index: 0x6060,
            sub: 0,
            data: SdoData::i8(9),
        }
        .to_frame(3);
        assert_eq!(f.id(), 0x603);
        assert_eq!(f.data(), &[0x2F, 0x60, 0x60, 0x00, 0x09, 0, 0, 0]);
        // 0x1017:00 = 100 ms (UNSIGNED16): 2B 17 10 00 64 00 00 00.
        let f = SdoRequest::Download {
            index: 0x1017,
            sub: 0,
            data: SdoData::u16(100),
        }
        .to_frame(3);
        assert_eq!(f.data(), &[0x2B, 0x17, 0x10, 0x00, 0x64, 0x00, 0, 0]);
        // 0x1800:01 = 0x80000183 (UNSIGNED32): 23 00 18 01 83 01 00 80.
        let f = SdoRequest::Download {
            index: 0x1800,
            sub: 1,
            data: SdoData::u32(0x8000_0183),
        }
        .to_frame(3);
        assert_eq!(f.data(), &[0x23, 0x00, 0x18, 0x01, 0x83, 0x01, 0x00, 0x80]);
        // 3-byte download: 27.
        let f = SdoRequest::Download {
            index: 0x2000,
            sub: 1,
            data: SdoData::new(0x00AB_CDEF, 3),
        }
        .to_frame(3);
        assert_eq!(f.data(), &[0x27, 0x00, 0x20, 0x01, 0xEF, 0xCD, 0xAB, 0x00]);
        // The server's confirmation: 60 60 60 00 00 00 00 00 on 0x583.
        let ack = SdoResponse::DownloadAck {
            index: 0x6060,
            sub: 0,
        }
        .to_frame(3);
        assert_eq!(ack.id(), 0x583);
        assert_eq!(ack.data(), &[0x60, 0x60, 0x60, 0x00, 0, 0, 0, 0]);
        assert_eq!(
            SdoResponse::parse(&ack),
            Ok((
                3,
                SdoResponse::DownloadAck {
                    index: 0x6060,
                    sub: 0
                }
            ))
        );
    }

    #[test]
    fn golden_expedited_upload() {
        // Read 0x1000:00 of node 9: 40 00 10 00 00 00 00 00 on 0x609.
        let f = SdoRequest::Upload {
            index: 0x1000,
            sub: 0,
        }
        .to_frame(9);
        assert_eq!(
            (f.id(), f.data()),
            (0x609, &[0x40, 0, 0x10, 0, 0, 0, 0, 0][..])
        );
        // Answer 0x00080196 (CiA 406 absolute linear encoder): 43 00 10 00 96 01 08 00.
        let r = SdoResponse::Upload {
            index: 0x1000,
            sub: 0,
            data: SdoData::u32(0x0008_0196),
        }
        .to_frame(9);
        assert_eq!(r.id(), 0x589);
        assert_eq!(r.data(), &[0x43, 0x00, 0x10, 0x00, 0x96, 0x01, 0x08, 0x00]);
        // 2-byte upload (statusword 0x0637): 4B 41 60 00 37 06 00 00.
        let r = SdoResponse::Upload {
            index: 0x6041,
            sub: 0,
            data: SdoData::u16(0x0637),
        }
        .to_frame(1);
        assert_eq!(r.data(), &[0x4B, 0x41, 0x60, 0x00, 0x37, 0x06, 0, 0]);
        // 1-byte signed upload (0x6061 = 9): 4F.
        let r = SdoResponse::Upload {
            index: 0x6061,
            sub: 0,
            data: SdoData::i8(9),
        }
        .to_frame(1);
        assert_eq!(r.data()[0], 0x4F);
        // Parsing an expedited upload without the size bit (0x42): 4 bytes.
        let f = CanFrame::new(0x581, &[0x42, 0x64, 0x60, 0, 1, 2, 3, 4]).unwrap();
        let (_, r) = SdoResponse::parse(&f).unwrap();
        match r {
            SdoResponse::Upload { data, .. } => {
                assert_eq!(data.bytes(), &[1, 2, 3, 4]);
                assert_eq!(data.as_u32(), 0x0403_0201);
            }
            other => panic!("{other:?}"),
        }
        // A segmented upload start is recognised, not misread as data.
        let f = CanFrame::new(0x581, &[0x41, 0x08, 0x10, 0, 12, 0, 0, 0]).unwrap();
        assert_eq!(
            SdoResponse::parse(&f).unwrap().1,
            SdoResponse::UploadSegmented {
                index: 0x1008,
                sub: 0,
                size: Some(12)
            }
        );
    }

    #[test]
    fn golden_abort() {
        // Object does not exist: 80 34 12 00 00 00 02 06.
        let r = SdoResponse::Abort {
            index: 0x1234,
            sub: 0,
            code: AbortCode::NoObject,
        }
        .to_frame(5);
        assert_eq!(r.data(), &[0x80, 0x34, 0x12, 0x00, 0x00, 0x00, 0x02, 0x06]);
        let (node, parsed) = SdoResponse::parse(&r).unwrap();
        assert_eq!(node, 5);
        assert_eq!(
            parsed,
            SdoResponse::Abort {
                index: 0x1234,
                sub: 0,
                code: AbortCode::NoObject
            }
        );
        // The client's abort (SDO timeout): 80 .. 00 00 04 05 on 0x605.
        let a = SdoRequest::Abort {
            index: 0x6041,
            sub: 0,
            code: AbortCode::Timeout,
        }
        .to_frame(5);
        assert_eq!(a.id(), 0x605);
        assert_eq!(a.data(), &[0x80, 0x41, 0x60, 0x00, 0x00, 0x00, 0x04, 0x05]);
        // Codes round-trip; unknown codes are kept.
        for (a, c, _) in AbortCode::TABLE {
            assert_eq!(AbortCode::from_code(c), a);
            assert_eq!(a.code(), c);
        }
        assert_eq!(
            AbortCode::from_code(0x0609_0099),
            AbortCode::Other(0x0609_0099)
        );
        assert_eq!(
            AbortCode::ReadOnly.to_string(),
            "0x06010002 (attempt to write a read-only object)"
        );
    }

    #[test]
    fn sign_extension_of_short_values() {
        assert_eq!(SdoData::i8(-3).as_i32(), -3);
        assert_eq!(SdoData::i16(-300).as_i32(), -300);
        assert_eq!(SdoData::u16(0xFFFF).as_u32(), 0xFFFF);
        assert_eq!(SdoData::u32(0xFFFF_FFFF).as_i32(), -1);
        // Bytes beyond the length are zero whatever the value was.
        assert_eq!(SdoData::new(0x1234_5678, 2).as_u32(), 0x5678);
    }

    proptest! {
        #[test]
        fn requests_and_responses_round_trip(
            index in any::<u16>(), sub in any::<u8>(), v in any::<u32>(), len in 1u8..=4, node in 1u8..=127
        ) {
            let data = SdoData::new(v, len);
            for req in [
                SdoRequest::Download { index, sub, data },
                SdoRequest::Upload { index, sub },
                SdoRequest::Abort { index, sub, code: AbortCode::from_code(v) },
            ] {
                prop_assert_eq!(SdoRequest::parse(&req.to_frame(node)), Ok((node, req)));
            }
            for resp in [
                SdoResponse::DownloadAck { index, sub },
                SdoResponse::Upload { index, sub, data },
                SdoResponse::Abort { index, sub, code: AbortCode::from_code(v) },
            ] {
                prop_assert_eq!(SdoResponse::parse(&resp.to_frame(node)), Ok((node, resp)));
            }
        }

        #[test]
        fn any_frame_parses_without_panicking(id in 0u16..=0x7FF, data in proptest::collection::vec(any::<u8>(), 0..=8)) {
            let f = CanFrame::new(id, &data).unwrap();
            let _ = SdoRequest::parse(&f);
            let _ = SdoResponse::parse(&f);
        }
    }
}
