//! Process data objects: mapping entries, the profile's fixed PDO layouts, packing mapped
//! values into frames and back, and the SDO writes that configure a PDO.
//!
//! A mapping entry is the UNSIGNED32 `index << 16 | sub << 8 | bit length`; mapped objects
//! are packed little-endian one after the other (CiA 301 7.5.2.36). This profile maps whole
//! bytes only (8, 16, 32 bits).
//!
//! # The profile's PDOs
//!
//! | PDO | COB-ID | content | bytes | transmission |
//! |---|---|---|---|---|
//! | drive RPDO1 | 0x200 + node | controlword 0x6040, target velocity 0x60FF | 6 | `rpdo_transmission` (default 1: applied at the next SYNC) |
//! | drive TPDO1 | 0x180 + node | position actual 0x6064, velocity actual 0x606C | 8 | 1: every SYNC |
//! | drive TPDO2 | 0x280 + node | statusword 0x6041 | 2 | 255: on change (inhibit time) and every event-timer period |
//! | encoder TPDO1 | 0x180 + node | position value 0x6004, speed value 0x6030:01 | 6 | 1: every SYNC |
//!
//! The statusword is event-driven rather than in TPDO1 because it changes a handful of times
//! per run while TPDO1 goes out 250 times a second: keeping it out of the cyclic frame keeps
//! the drive's cyclic TPDO at 8 bytes (see [`super::busload`]).

use super::od;
use super::sdo::SdoData;
use super::CanOpenError;
use crate::frame::CanFrame;

/// One mapped object: index, sub-index, length in bits.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub struct MapEntry {
    /// Object index.
    pub index: u16,
    /// Sub-index.
    pub sub: u8,
    /// Length in bits (8, 16 or 32 in this profile).
    pub bits: u8,
}

impl MapEntry {
    /// A mapping entry.
    pub const fn new(index: u16, sub: u8, bits: u8) -> Self {
        Self { index, sub, bits }
    }

    /// The UNSIGNED32 written to the mapping object.
    pub fn raw(self) -> u32 {
        (u32::from(self.index) << 16) | (u32::from(self.sub) << 8) | u32::from(self.bits)
    }

    /// The entry a mapping object's UNSIGNED32 describes.
    pub fn from_raw(raw: u32) -> Self {
        Self {
            index: (raw >> 16) as u16,
            sub: (raw >> 8) as u8,
            bits: raw as u8,
        }
    }

    /// Length in whole bytes (bits rounded up).
    pub fn bytes(self) -> usize {
        usize::from(self.bits).div_ceil(8)
    }
}

/// Receive (master → device) or transmit (device → master) PDO.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum Direction {
    /// RPDO: received by the device.
    Rx,
    /// TPDO: transmitted by the device.
    Tx,
}

/// A PDO of the profile: direction, number and mapped objects.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct PdoLayout {
    /// RPDO or TPDO.
    pub dir: Direction,
    /// PDO number 1..=4.
    pub num: u8,
    /// Mapped objects, in frame order.
    pub entries: &'static [MapEntry],
}

impl PdoLayout {
    /// Data bytes of the frame.
    pub fn len_bytes(&self) -> usize {
        self.entries.iter().map(|e| e.bytes()).sum()
    }

    /// COB-ID on `node` (predefined connection set).
    pub fn cob_id(&self, node: u8) -> u16 {
        match self.dir {
            Direction::Rx => super::cob::rpdo(self.num, node),
            Direction::Tx => super::cob::tpdo(self.num, node),
        }
    }

    /// Index of the communication parameter object.
    pub fn comm_index(&self) -> u16 {
        let base = match self.dir {
            Direction::Rx => od::RPDO_COMM,
            Direction::Tx => od::TPDO_COMM,
        };
        base + u16::from(self.num.clamp(1, 4) - 1)
    }

    /// Index of the mapping parameter object.
    pub fn map_index(&self) -> u16 {
        let base = match self.dir {
            Direction::Rx => od::RPDO_MAP,
            Direction::Tx => od::TPDO_MAP,
        };
        base + u16::from(self.num.clamp(1, 4) - 1)
    }

    /// Packs one raw value per entry (truncated to the entry's length) into a frame on
    /// `node`'s COB-ID.
    pub fn pack(&self, node: u8, values: &[u32]) -> CanFrame {
        let mut data = [0u8; 8];
        let n = pack_into(self.entries, values, &mut data);
        CanFrame::new(self.cob_id(node), &data[..n])
            .unwrap_or_else(|_| unreachable!("profile PDOs are at most 8 bytes"))
    }

    /// Unpacks a frame into one raw value per entry; the frame must be exactly as long as
    /// the mapping.
    pub fn unpack(&self, f: &CanFrame) -> Result<[u32; 8], CanOpenError> {
        unpack(self.entries, f)
    }
}

const CW_16: MapEntry = MapEntry::new(od::CONTROLWORD, 0, 16);
const TV_32: MapEntry = MapEntry::new(od::TARGET_VELOCITY, 0, 32);
const POS_32: MapEntry = MapEntry::new(od::POSITION_ACTUAL, 0, 32);
const VEL_32: MapEntry = MapEntry::new(od::VELOCITY_ACTUAL, 0, 32);
const SW_16: MapEntry = MapEntry::new(od::STATUSWORD, 0, 16);
const ENC_POS_32: MapEntry = MapEntry::new(od::POSITION_VALUE, 0, 32);
const ENC_SPEED_16: MapEntry = MapEntry::new(od::SPEED_VALUE, 1, 16);

/// Drive RPDO1: controlword, target velocity.
pub const DRIVE_RPDO1: PdoLayout = PdoLayout {
    dir: Direction::Rx,
    num: 1,
    entries: &[CW_16, TV_32],
};
/// Drive TPDO1: position actual value, velocity actual value.
pub const DRIVE_TPDO1: PdoLayout = PdoLayout {
    dir: Direction::Tx,
    num: 1,
    entries: &[POS_32, VEL_32],
};
/// Drive TPDO2: statusword.
pub const DRIVE_TPDO2: PdoLayout = PdoLayout {
    dir: Direction::Tx,
    num: 2,
    entries: &[SW_16],
};
/// Encoder TPDO1: position value, speed value (channel 1).
pub const ENCODER_TPDO1: PdoLayout = PdoLayout {
    dir: Direction::Tx,
    num: 1,
    entries: &[ENC_POS_32, ENC_SPEED_16],
};

/// Packs values into `out` (little-endian, byte-aligned entries); returns the bytes used.
/// Entries beyond 8 bytes, or without a value, are left out.
pub fn pack_into(entries: &[MapEntry], values: &[u32], out: &mut [u8; 8]) -> usize {
    let mut pos = 0;
    for (e, v) in entries.iter().zip(values) {
        let n = e.bytes().min(4);
        if pos + n > 8 {
            break;
        }
        out[pos..pos + n].copy_from_slice(&v.to_le_bytes()[..n]);
        pos += n;
    }
    pos
}

/// Unpacks a frame by a mapping into one raw value per entry (zero-extended).
pub fn unpack(entries: &[MapEntry], f: &CanFrame) -> Result<[u32; 8], CanOpenError> {
    let expected: usize = entries.iter().map(|e| e.bytes().min(4)).sum();
    if f.len() != expected {
        return Err(CanOpenError::WrongLength {
            what: "PDO",
            id: f.id(),
            got: f.len(),
            expected,
        });
    }
    let mut out = [0u32; 8];
    let d = f.data();
    let mut pos = 0;
    for (o, e) in out.iter_mut().zip(entries) {
        let n = e.bytes().min(4);
        let mut b = [0u8; 4];
        b[..n].copy_from_slice(&d[pos..pos + n]);
        *o = u32::from_le_bytes(b);
        pos += n;
    }
    Ok(out)
}

/// Communication parameters of one PDO.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct PdoComm {
    /// Transmission type: 1..=240 synchronous (every n-th SYNC; for an RPDO: applied at the
    /// next SYNC), 254/255 event-driven (for an RPDO: applied on reception).
    pub transmission: u8,
    /// Inhibit time (100 µs); TPDOs only.
    pub inhibit_100us: u16,
    /// Event timer (ms): a TPDO is also sent this often; on an RPDO it is the deadline
    /// monitoring time (0 = off).
    pub event_timer_ms: u16,
}

/// One SDO write of a configuration plan.
pub type Write = (u16, u8, SdoData);

/// The SDO writes that configure `layout` on `node` with `comm`, in the order CiA 301
/// requires: make the PDO invalid (COB-ID bit 31), set the transmission parameters,
/// clear the mapping (sub 0 = 0), write the entries, set the number of entries, make the
/// PDO valid again with its COB-ID.
pub fn config_writes(layout: &PdoLayout, node: u8, comm: &PdoComm) -> Vec<Write> {
    config_writes_entries(layout.dir, layout.num, layout.entries, node, comm)
}

/// [`config_writes`] for a mapping given as entries (PDO `num` 1..=4 in direction `dir`).
pub fn config_writes_entries(
    dir: Direction,
    num: u8,
    entries: &[MapEntry],
    node: u8,
    comm: &PdoComm,
) -> Vec<Write> {
    let layout = PdoLayout {
        dir,
        num,
        entries: &[],
    };
    let comm_ix = layout.comm_index();
    let map_ix = layout.map_index();
    let cob = u32::from(layout.cob_id(node))
        | match dir {
            Direction::Tx => od::PDO_COB_NO_RTR,
            Direction::Rx => 0,
        };
    let mut w = vec![
        (
            comm_ix,
            od::PDO_COB_ID,
            SdoData::u32(cob | od::PDO_COB_INVALID),
        ),
        (
            comm_ix,
            od::PDO_TRANSMISSION,
            SdoData::u8(comm.transmission),
        ),
    ];
    if dir == Direction::Tx {
        w.push((comm_ix, od::PDO_INHIBIT, SdoData::u16(comm.inhibit_100us)));
    }
    w.push((
        comm_ix,
        od::PDO_EVENT_TIMER,
        SdoData::u16(comm.event_timer_ms),
    ));
    w.push((map_ix, 0, SdoData::u8(0)));
    for (i, e) in entries.iter().enumerate() {
        w.push((map_ix, (i + 1) as u8, SdoData::u32(e.raw())));
    }
    w.push((map_ix, 0, SdoData::u8(entries.len() as u8)));
    w.push((comm_ix, od::PDO_COB_ID, SdoData::u32(cob)));
    w
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn layouts_have_the_documented_lengths() {
        assert_eq!(DRIVE_RPDO1.len_bytes(), 6);
        assert_eq!(DRIVE_TPDO1.len_bytes(), 8);
        assert_eq!(DRIVE_TPDO2.len_bytes(), 2);
        assert_eq!(ENCODER_TPDO1.len_bytes(), 6);
        assert_eq!(DRIVE_RPDO1.cob_id(3), 0x203);
        assert_eq!(DRIVE_TPDO2.cob_id(3), 0x283);
        assert_eq!(DRIVE_TPDO2.comm_index(), 0x1801);
        assert_eq!(DRIVE_TPDO2.map_index(), 0x1A01);
        assert_eq!(DRIVE_RPDO1.map_index(), 0x1600);
        assert_eq!(MapEntry::new(0x60FF, 0, 32).raw(), 0x60FF_0020);
        assert_eq!(MapEntry::from_raw(0x6030_0110), ENC_SPEED_16);
    }

    #[test]
    fn golden_pdo_frames() {
        // RPDO1 of node 1: controlword 0x000F, target velocity −1000 inc/s.
        let f = DRIVE_RPDO1.pack(1, &[0x000F, (-1000i32) as u32]);
        assert_eq!(f.id(), 0x201);
        assert_eq!(f.data(), &[0x0F, 0x00, 0x18, 0xFC, 0xFF, 0xFF]);
        // TPDO1 of node 2: position 0x00012345, velocity 100.
        let f = DRIVE_TPDO1.pack(2, &[0x0001_2345, 100]);
        assert_eq!(f.id(), 0x182);
        assert_eq!(f.data(), &[0x45, 0x23, 0x01, 0x00, 0x64, 0x00, 0x00, 0x00]);
        let v = DRIVE_TPDO1.unpack(&f).unwrap();
        assert_eq!((v[0], v[1]), (0x0001_2345, 100));
        // TPDO2: statusword 0x0637 (operation enabled, remote, voltage enabled).
        let f = DRIVE_TPDO2.pack(2, &[0x0637]);
        assert_eq!((f.id(), f.data()), (0x282, &[0x37, 0x06][..]));
        // Encoder TPDO1 of node 9: 370 000 µm steps, speed −12.
        let f = ENCODER_TPDO1.pack(9, &[370_000, (-12i16) as u16 as u32]);
        assert_eq!(f.id(), 0x189);
        assert_eq!(f.data(), &[0x50, 0xA5, 0x05, 0x00, 0xF4, 0xFF]);
        // A frame of the wrong length is refused, not misread.
        let short = CanFrame::new(0x189, &[0x50, 0xA5, 0x05, 0x00, 0xF4]).unwrap();
        assert!(matches!(
            ENCODER_TPDO1.unpack(&short),
            Err(CanOpenError::WrongLength {
                got: 5,
                expected: 6,
                ..
            })
        ));
    }

    #[test]
    fn configuration_follows_the_cia301_order() {
        let comm = PdoComm {
            transmission: 255,
            inhibit_100us: 10,
            event_timer_ms: 100,
        };
        let w = config_writes(&DRIVE_TPDO2, 5, &comm);
        let expect: Vec<(u16, u8, u32)> = vec![
            (0x1801, 1, 0xC000_0285),
            (0x1801, 2, 255),
            (0x1801, 3, 10),
            (0x1801, 5, 100),
            (0x1A01, 0, 0),
            (0x1A01, 1, 0x6041_0010),
            (0x1A01, 0, 1),
            (0x1801, 1, 0x4000_0285),
        ];
        let got: Vec<(u16, u8, u32)> = w.iter().map(|(i, s, d)| (*i, *s, d.as_u32())).collect();
        assert_eq!(got, expect);
        // An RPDO has no inhibit time and no RTR bit; its event timer is the deadline.
        let w = config_writes(
            &DRIVE_RPDO1,
            5,
            &PdoComm {
                transmission: 1,
                inhibit_100us: 0,
                event_timer_ms: 50,
            },
        );
        let got: Vec<(u16, u8, u32)> = w.iter().map(|(i, s, d)| (*i, *s, d.as_u32())).collect();
        assert_eq!(
            got,
            vec![
                (0x1400, 1, 0x8000_0205),
                (0x1400, 2, 1),
                (0x1400, 5, 50),
                (0x1600, 0, 0),
                (0x1600, 1, 0x6040_0010),
                (0x1600, 2, 0x60FF_0020),
                (0x1600, 0, 2),
                (0x1400, 1, 0x0000_0205),
            ]
        );
        // Sizes: COB-IDs and entries are UNSIGNED32, sub 0 UNSIGNED8, times UNSIGNED16.
        assert_eq!(w[0].2.len(), 4);
        assert_eq!(w[1].2.len(), 1);
        assert_eq!(w[2].2.len(), 2);
        assert_eq!(w[3].2.len(), 1);
    }
}
