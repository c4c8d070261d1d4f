//! COB-IDs of the CiA 301 predefined connection set, and what a received id is.
//!
//! | object | COB-ID | direction |
//! |---|---|---|
//! | NMT command | 0x000 | master → devices |
//! | SYNC | 0x080 | master → devices |
//! | EMCY | 0x080 + node | device → all |
//! | TPDO1..4 | 0x180 / 0x280 / 0x380 / 0x480 + node | device → master |
//! | RPDO1..4 | 0x200 / 0x300 / 0x400 / 0x500 + node | master → device |
//! | SDO response (server → client) | 0x580 + node | device → master |
//! | SDO request (client → server) | 0x600 + node | master → device |
//! | NMT error control (boot-up, heartbeat) | 0x700 + node | device → all |
//!
//! The native wheel-module protocol reuses several of these ranges (its SYNC is 0x080, its
//! FEEDBACK_A 0x180 + n …), so one bus carries one profile at a time.

/// NMT command COB-ID.
pub const NMT: u16 = 0x000;
/// SYNC COB-ID.
pub const SYNC: u16 = 0x080;
/// EMCY base (plus node-ID).
pub const EMCY: u16 = 0x080;
/// TPDO1..4 bases (plus node-ID).
pub const TPDO: [u16; 4] = [0x180, 0x280, 0x380, 0x480];
/// RPDO1..4 bases (plus node-ID).
pub const RPDO: [u16; 4] = [0x200, 0x300, 0x400, 0x500];
/// SDO server → client base (plus node-ID).
pub const SDO_TX: u16 = 0x580;
/// SDO client → server base (plus node-ID).
pub const SDO_RX: u16 = 0x600;
/// NMT error control (boot-up, heartbeat) base (plus node-ID).
pub const HEARTBEAT: u16 = 0x700;

/// What a CAN id is in the predefined connection set.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum Cob {
    /// NMT command (0x000).
    Nmt,
    /// SYNC (0x080).
    Sync,
    /// Emergency of a node.
    Emcy(u8),
    /// Transmit PDO `pdo` (1..=4) of a node.
    Tpdo(u8, u8),
    /// Receive PDO `pdo` (1..=4) of a node.
    Rpdo(u8, u8),
    /// SDO response from a node's server.
    SdoTx(u8),
    /// SDO request to a node's server.
    SdoRx(u8),
    /// Boot-up or heartbeat of a node.
    Heartbeat(u8),
    /// Not in the predefined connection set (or node-ID 0 where a node is required).
    Other,
}

/// Classifies an 11-bit id.
pub fn classify(id: u16) -> Cob {
    if id == NMT {
        return Cob::Nmt;
    }
    if id == SYNC {
        return Cob::Sync;
    }
    let node = (id & 0x7F) as u8;
    if node == 0 {
        return Cob::Other;
    }
    match id & 0x780 {
        0x080 => Cob::Emcy(node),
        0x180 => Cob::Tpdo(1, node),
        0x200 => Cob::Rpdo(1, node),
        0x280 => Cob::Tpdo(2, node),
        0x300 => Cob::Rpdo(2, node),
        0x380 => Cob::Tpdo(3, node),
        0x400 => Cob::Rpdo(3, node),
        0x480 => Cob::Tpdo(4, node),
        0x500 => Cob::Rpdo(4, node),
        0x580 => Cob::SdoTx(node),
        0x600 => Cob::SdoRx(node),
        0x700 => Cob::Heartbeat(node),
        _ => Cob::Other,
    }
}

/// COB-ID of TPDO `pdo` (1..=4, clamped) of `node`.
pub fn tpdo(pdo: u8, node: u8) -> u16 {
    TPDO[usize::from(pdo.clamp(1, 4) - 1)] + u16::from(node & 0x7F)
}

/// COB-ID of RPDO `pdo` (1..=4, clamped) of `node`.
pub fn rpdo(pdo: u8, node: u8) -> u16 {
    RPDO[usize::from(pdo.clamp(1, 4) - 1)] + u16::from(node & 0x7F)
}

/// COB-ID of `node`'s SDO responses.
pub fn sdo_tx(node: u8) -> u16 {
    SDO_TX + u16::from(node & 0x7F)
}

/// COB-ID of SDO requests to `node`.
pub fn sdo_rx(node: u8) -> u16 {
    SDO_RX + u16::from(node & 0x7F)
}

/// COB-ID of `node`'s boot-up and heartbeat.
pub fn heartbeat(node: u8) -> u16 {
    HEARTBEAT + u16::from(node & 0x7F)
}

/// COB-ID of `node`'s emergency messages.
pub fn emcy(node: u8) -> u16 {
    EMCY + u16::from(node & 0x7F)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn classifies_the_predefined_connection_set() {
        assert_eq!(classify(0x000), Cob::Nmt);
        assert_eq!(classify(0x080), Cob::Sync);
        assert_eq!(classify(0x081), Cob::Emcy(1));
        assert_eq!(classify(0x0FF), Cob::Emcy(127));
        assert_eq!(classify(0x185), Cob::Tpdo(1, 5));
        assert_eq!(classify(0x285), Cob::Tpdo(2, 5));
        assert_eq!(classify(0x4FF), Cob::Tpdo(4, 127));
        assert_eq!(classify(0x20C), Cob::Rpdo(1, 12));
        assert_eq!(classify(0x50C), Cob::Rpdo(4, 12));
        assert_eq!(classify(0x58C), Cob::SdoTx(12));
        assert_eq!(classify(0x60C), Cob::SdoRx(12));
        assert_eq!(classify(0x77F), Cob::Heartbeat(127));
        // Node-ID 0 outside NMT/SYNC, and the unused ranges.
        assert_eq!(classify(0x180), Cob::Other);
        assert_eq!(classify(0x680), Cob::Other);
        assert_eq!(classify(0x7E5), Cob::Other);
        for id in 0..=0x7FFu16 {
            let c = classify(id);
            let back = match c {
                Cob::Nmt => Some(NMT),
                Cob::Sync => Some(SYNC),
                Cob::Emcy(n) => Some(emcy(n)),
                Cob::Tpdo(p, n) => Some(tpdo(p, n)),
                Cob::Rpdo(p, n) => Some(rpdo(p, n)),
                Cob::SdoTx(n) => Some(sdo_tx(n)),
                Cob::SdoRx(n) => Some(sdo_rx(n)),
                Cob::Heartbeat(n) => Some(heartbeat(n)),
                Cob::Other => None,
            };
            if let Some(b) = back {
                assert_eq!(b, id, "{c:?}");
            }
        }
    }
}
