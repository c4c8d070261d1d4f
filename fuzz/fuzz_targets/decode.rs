//! Fuzz target: `codec::decode` and `rx::Receiver` on arbitrary frames.
//!
//! The input is split into records of 11 bytes: id (2 bytes, little-endian, masked to
//! 11 bits), length (1 byte, mod 9), 8 data bytes of which `length` are used. Every record
//! goes through `decode` (must not panic; whatever decodes must re-encode to a frame that
//! decodes to the same message) and through one `Receiver` per policy (must not panic; the
//! statistics must account for every frame).
//!
//! Run: `cargo +nightly fuzz run decode` from the repository root.
#![no_main]

use libfuzzer_sys::fuzz_target;
use rollbase_driver::codec::{decode, encode};
use rollbase_driver::frame::CanFrame;
use rollbase_driver::rx::{CounterPolicy, Receiver};

fuzz_target!(|input: &[u8]| {
    let mut strict = Receiver::new();
    let mut lenient = Receiver::with_policy(CounterPolicy::AcceptWithLoss);
    let mut n = 0u64;
    for rec in input.chunks(11) {
        if rec.len() < 3 {
            break;
        }
        let id = u16::from_le_bytes([rec[0], rec[1]]) & 0x7FF;
        let len = usize::from(rec[2] % 9).min(rec.len() - 3);
        let Ok(frame) = CanFrame::new(id, &rec[3..3 + len]) else {
            panic!("id ≤ 0x7FF and len ≤ 8 must always build a frame");
        };
        if let Ok(m) = decode(&frame) {
            let again = encode(&m).expect("a decoded message must re-encode");
            assert_eq!(decode(&again).expect("re-encoded frame decodes"), m);
        }
        let _ = strict.accept(&frame);
        let _ = lenient.accept(&frame);
        n += 1;
    }
    let s = strict.stats();
    assert_eq!(s.accepted + s.rejected(), n);
});
