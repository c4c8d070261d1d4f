//! CRC-8 SAE J1850 (the AUTOSAR E2E profile 1/2 CRC): polynomial 0x1D, initial value 0xFF,
//! final XOR 0xFF, no reflection. Check value over ASCII `"123456789"` is 0x4B.
//!
//! The protocol computes it over `[id & 0xFF, id >> 8, payload bytes except the CRC byte]`,
//! see [`frame_crc`].

const POLY: u8 = 0x1D;

const fn make_table() -> [u8; 256] {
    let mut table = [0u8; 256];
    let mut i = 0;
    while i < 256 {
        let mut c = i as u8;
        let mut b = 0;
        while b < 8 {
            c = if c & 0x80 != 0 {
                (c << 1) ^ POLY
            } else {
                c << 1
            };
            b += 1;
        }
        table[i] = c;
        i += 1;
    }
    table
}

static TABLE: [u8; 256] = make_table();

/// Feeds `bytes` into a running (non-finalised) CRC register.
fn update(mut crc: u8, bytes: &[u8]) -> u8 {
    for &b in bytes {
        crc = TABLE[usize::from(crc ^ b)];
    }
    crc
}

/// CRC-8 SAE J1850 of `bytes` (init 0xFF, xorout 0xFF).
pub fn crc8_sae_j1850(bytes: &[u8]) -> u8 {
    update(0xFF, bytes) ^ 0xFF
}

/// The protocol CRC of a frame: CRC-8 SAE J1850 over the id (low byte, then high byte)
/// followed by `payload_without_crc`.
///
/// Covering the id protects against a frame being delivered under a wrong id (for
/// example a corrupted node number that the CAN CRC happened not to catch, or a
/// misconfigured module answering under another node's id).
pub fn frame_crc(id: u16, payload_without_crc: &[u8]) -> u8 {
    let [lo, hi] = id.to_le_bytes();
    update(update(0xFF, &[lo, hi]), payload_without_crc) ^ 0xFF
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn check_value_of_123456789_is_0x4b() {
        assert_eq!(crc8_sae_j1850(b"123456789"), 0x4B);
    }

    #[test]
    fn table_matches_bitwise_definition() {
        fn bitwise(bytes: &[u8]) -> u8 {
            let mut crc = 0xFFu8;
            for &b in bytes {
                crc ^= b;
                for _ in 0..8 {
                    crc = if crc & 0x80 != 0 {
                        (crc << 1) ^ POLY
                    } else {
                        crc << 1
                    };
                }
            }
            crc ^ 0xFF
        }
        for len in 0..6u8 {
            let v: Vec<u8> = (0..len)
                .map(|i| i.wrapping_mul(37).wrapping_add(11))
                .collect();
            assert_eq!(crc8_sae_j1850(&v), bitwise(&v), "len {len}");
        }
        assert_eq!(frame_crc(0x181, &[1, 2]), bitwise(&[0x81, 0x01, 1, 2]));
    }

    #[test]
    fn empty_input_is_zero() {
        // 0xFF register, no data, xorout 0xFF.
        assert_eq!(crc8_sae_j1850(&[]), 0x00);
    }
}
