//! Golden byte vectors for every message, computed by hand.
//!
//! Layout arithmetic (little-endian: bit k lives in byte k/8 at bit k%8; a signed value is
//! written as its 16/8-bit two's complement; the CRC is CRC-8 SAE J1850, poly 0x1D, init
//! 0xFF, xorout 0xFF, over [id & 0xFF, id >> 8, payload bytes before the CRC byte]; the CRC
//! values were checked with an independent bit-by-bit implementation):
//!
//! SYNC id 0x080, cycle 0x1234, counter 5
//!   bytes 0–1: 0x1234 → 34 12; byte 2: counter 5 in bits 16–19, reserved 0 → 05
//!   CRC over [80 00 34 12 05] = 0x58                     → 34 12 05 58
//!
//! SETPOINT node 1 (id 0x201), wheel 1.5 rad/s, steer −0.25 rad/s, enable + fault_reset, counter 3
//!   wheel 1.5 / 0.001 = 1500 = 0x05DC → DC 05
//!   steer −0.25 / 0.001 = −250 → 0x10000 − 250 = 0xFF06 → 06 FF
//!   byte 4: enable bit 32 → 0x01, brake bit 33 → 0, fault_reset bit 34 → 0x04,
//!           reserved bit 35 → 0, counter 3 in bits 36–39 → 0x30;  0x01|0x04|0x30 = 0x35
//!   CRC over [01 02 DC 05 06 FF 35] = 0xFF               → DC 05 06 FF 35 FF
//!
//! FEEDBACK_A node 2 (id 0x182), steer −π/2, wheel 13.9 rad/s, steer rate −10 rad/s, counter 15
//!   −π/2 / 1e-4 = −15707.96 → −15708 → 0x10000 − 15708 = 0xC2A4 → A4 C2
//!   13.9 / 0.001 = 13900 = 0x364C → 4C 36
//!   −10 / 0.001 = −10000 → 0xD8F0 → F0 D8
//!   byte 6: counter 15 in bits 48–51, reserved 0 → 0F
//!   CRC over [82 01 A4 C2 4C 36 F0 D8 0F] = 0x67         → A4 C2 4C 36 F0 D8 0F 67
//!
//! FEEDBACK_B node 4 (id 0x284), leg 0.465 m, leg rate −0.05 m/s, drive 12.5 A, steer −3.25 A, counter 0
//!   0.465 / 1e-5 = 46500 = 0xB5A4 → A4 B5
//!   −0.05 / 1e-4 = −500 → 0xFE0C → 0C FE
//!   12.5 / 0.25 = 50 = 0x32;  −3.25 / 0.25 = −13 → 0x100 − 13 = 0xF3
//!   byte 6: counter 0 → 00
//!   CRC over [84 02 A4 B5 0C FE 32 F3 00] = 0x27         → A4 B5 0C FE 32 F3 00 27
//!
//! STATUS node 3 (id 0x703), state fault (3), counter 9, fault overtemperature (2), 85 °C, 48.0 V
//!   byte 0: state 3 in bits 0–3, counter 9 in bits 4–7 → 0x93
//!   byte 1: fault code 2 → 02
//!   byte 2: (85 − (−40)) / 1 = 125 = 0x7D
//!   bytes 3–4: 48.0 / 0.01 = 4800 = 0x12C0 → C0 12
//!   CRC over [03 07 93 02 7D C0 12] = 0x6F               → 93 02 7D C0 12 6F

use rollbase_driver::codec::*;
use rollbase_driver::frame::CanFrame;
use std::f64::consts::FRAC_PI_2;

fn check(msg: Message, id: u16, bytes: &[u8]) {
    let frame = encode(&msg).expect("golden message encodes");
    assert_eq!(frame.id(), id, "{msg:?}");
    assert_eq!(frame.data(), bytes, "{msg:?}");
    let expected = CanFrame::new(id, bytes).expect("frame");
    let back = decode(&expected).expect("golden frame decodes");
    assert_eq!(back.node, msg.node);
    assert_eq!(back.counter, msg.counter);
    assert_eq!(
        encode(&back).expect("re-encode"),
        expected,
        "decode→encode is exact"
    );
}

#[test]
fn golden_sync() {
    check(
        Message {
            node: 0,
            counter: 5,
            payload: Payload::Sync(Sync { cycle: 0x1234 }),
        },
        0x080,
        &[0x34, 0x12, 0x05, 0x58],
    );
}

#[test]
fn golden_setpoint() {
    let msg = Message {
        node: 1,
        counter: 3,
        payload: Payload::Setpoint(Setpoint {
            wheel_speed: 1.5,
            steer_rate: -0.25,
            flags: SetpointFlags {
                enable: true,
                brake: false,
                fault_reset: true,
            },
        }),
    };
    check(msg, 0x201, &[0xDC, 0x05, 0x06, 0xFF, 0x35, 0xFF]);
    let back = decode(&encode(&msg).expect("encode")).expect("decode");
    assert_eq!(back, msg, "exactly representable values survive unchanged");
}

#[test]
fn golden_feedback_a() {
    let msg = Message {
        node: 2,
        counter: 15,
        payload: Payload::FeedbackA(FeedbackA {
            steer_angle: -FRAC_PI_2,
            wheel_speed: 13.9,
            steer_rate: -10.0,
        }),
    };
    check(
        msg,
        0x182,
        &[0xA4, 0xC2, 0x4C, 0x36, 0xF0, 0xD8, 0x0F, 0x67],
    );
    let Payload::FeedbackA(fa) = decode(&encode(&msg).expect("encode"))
        .expect("decode")
        .payload
    else {
        panic!("wrong payload kind");
    };
    // −15708 · 1e-4 rad: the quantized value, not π/2 itself.
    assert!((fa.steer_angle - (-15708.0 * 1e-4)).abs() < 1e-12);
    assert!((fa.wheel_speed - 13.9).abs() < 1e-12);
}

#[test]
fn golden_feedback_b() {
    check(
        Message {
            node: 4,
            counter: 0,
            payload: Payload::FeedbackB(FeedbackB {
                leg_extension: 0.465,
                leg_rate: -0.05,
                drive_current: 12.5,
                steer_current: -3.25,
            }),
        },
        0x284,
        &[0xA4, 0xB5, 0x0C, 0xFE, 0x32, 0xF3, 0x00, 0x27],
    );
}

#[test]
fn golden_status() {
    let msg = Message {
        node: 3,
        counter: 9,
        payload: Payload::Status(Status {
            state: ModuleState::Fault,
            fault_code: FAULT_OVERTEMPERATURE,
            temperature: 85.0,
            bus_voltage: 48.0,
        }),
    };
    check(msg, 0x703, &[0x93, 0x02, 0x7D, 0xC0, 0x12, 0x6F]);
    assert_eq!(decode(&encode(&msg).expect("encode")).expect("decode"), msg);
}

#[test]
fn out_of_range_encode_is_an_error_never_wrapped() {
    let sp = |w: f64, s: f64| Message {
        node: 1,
        counter: 0,
        payload: Payload::Setpoint(Setpoint {
            wheel_speed: w,
            steer_rate: s,
            flags: SetpointFlags::default(),
        }),
    };
    // 40 rad/s would wrap to a negative i16 raw if not checked (40000 > 32767).
    let e = encode(&sp(40.0, 0.0)).expect_err("40 rad/s must be rejected");
    match e {
        EncodeError::OutOfRange { signal, value, .. } => {
            assert_eq!(signal, "wheel_speed");
            assert_eq!(value, 40.0);
        }
        other => panic!("unexpected {other:?}"),
    }
    assert!(e.to_string().contains("wheel_speed"), "{e}");
    assert!(e.to_string().contains("40"), "{e}");
    assert!(matches!(
        encode(&sp(0.0, -15.5)),
        Err(EncodeError::OutOfRange {
            signal: "steer_rate",
            ..
        })
    ));
    assert!(matches!(
        encode(&sp(f64::NAN, 0.0)),
        Err(EncodeError::OutOfRange { .. })
    ));
    assert!(matches!(
        encode(&sp(f64::INFINITY, 0.0)),
        Err(EncodeError::OutOfRange { .. })
    ));
    // The declared limit itself is fine, and so is a value within half a step beyond it.
    assert!(encode(&sp(30.0, -15.0)).is_ok());
    assert!(encode(&sp(30.0004, 0.0)).is_ok());
    assert!(encode(&sp(30.0006, 0.0)).is_err());
    let leg = Message {
        node: 1,
        counter: 0,
        payload: Payload::FeedbackB(FeedbackB {
            leg_extension: -0.001,
            ..FeedbackB::default()
        }),
    };
    assert!(matches!(
        encode(&leg),
        Err(EncodeError::OutOfRange {
            signal: "leg_extension",
            ..
        })
    ));
    let hot = Message {
        node: 1,
        counter: 0,
        payload: Payload::Status(Status {
            temperature: -41.0,
            ..Status::default()
        }),
    };
    assert!(matches!(
        encode(&hot),
        Err(EncodeError::OutOfRange {
            signal: "temperature",
            ..
        })
    ));
}

#[test]
fn bad_node_and_counter_are_encode_errors() {
    let sync = |node, counter| Message {
        node,
        counter,
        payload: Payload::Sync(Sync { cycle: 1 }),
    };
    assert!(matches!(
        encode(&sync(1, 0)),
        Err(EncodeError::BadNode { node: 1, .. })
    ));
    assert!(matches!(
        encode(&sync(0, 16)),
        Err(EncodeError::BadCounter { counter: 16, .. })
    ));
    for node in [0u8, 16, 255] {
        let m = Message {
            node,
            counter: 0,
            payload: Payload::Setpoint(Setpoint::default()),
        };
        assert!(
            matches!(encode(&m), Err(EncodeError::BadNode { .. })),
            "node {node}"
        );
    }
}

#[test]
fn decode_errors_are_typed() {
    // Unknown id.
    let f = CanFrame::new(0x123, &[0; 8]).expect("frame");
    assert_eq!(decode(&f), Err(DecodeError::UnknownId { id: 0x123 }));
    // Per-node base id = node 0.
    let f = CanFrame::new(0x180, &[0; 8]).expect("frame");
    assert!(matches!(
        decode(&f),
        Err(DecodeError::BadNode { id: 0x180, .. })
    ));
    // Wrong DLC.
    let f = CanFrame::new(0x181, &[0; 7]).expect("frame");
    assert!(matches!(
        decode(&f),
        Err(DecodeError::WrongDlc {
            expected: 8,
            got: 7,
            ..
        })
    ));
    // Bad CRC: flip one bit of the golden STATUS frame.
    let good = [0x93, 0x02, 0x7D, 0xC0, 0x12, 0x6F];
    let mut bad = good;
    bad[2] ^= 0x10;
    let f = CanFrame::new(0x703, &bad).expect("frame");
    assert!(matches!(
        decode(&f),
        Err(DecodeError::BadCrc { received: 0x6F, .. })
    ));
    // Bad enum: state 5, with a correct CRC.
    let mut st = good;
    st[0] = 0x95;
    st[5] = rollbase_driver::crc::frame_crc(0x703, &st[..5]);
    let f = CanFrame::new(0x703, &st).expect("frame");
    assert!(matches!(
        decode(&f),
        Err(DecodeError::BadEnum {
            signal: "state",
            raw: 5,
            ..
        })
    ));
    // Out of range: steer angle raw 31417 (> π), with a correct CRC.
    let mut fa = [0u8; 8];
    fa[..2].copy_from_slice(&31417i16.to_le_bytes());
    fa[7] = rollbase_driver::crc::frame_crc(0x181, &fa[..7]);
    let f = CanFrame::new(0x181, &fa).expect("frame");
    assert!(matches!(
        decode(&f),
        Err(DecodeError::OutOfRange {
            signal: "steer_angle",
            raw: 31417,
            min_raw: -31416,
            max_raw: 31416,
            ..
        })
    ));
    fa[..2].copy_from_slice(&31416i16.to_le_bytes());
    fa[7] = rollbase_driver::crc::frame_crc(0x181, &fa[..7]);
    assert!(decode(&CanFrame::new(0x181, &fa).expect("frame")).is_ok());
}

#[test]
fn reserved_bits_are_zero_on_encode_and_ignored_on_decode() {
    let msg = Message {
        node: 2,
        counter: 7,
        payload: Payload::FeedbackA(FeedbackA::default()),
    };
    let f = encode(&msg).expect("encode");
    assert_eq!(f.data()[6] & 0xF0, 0, "reserved bits 52..55 are 0");
    let mut bytes = [0u8; 8];
    bytes.copy_from_slice(f.data());
    bytes[6] |= 0xA0;
    bytes[7] = rollbase_driver::crc::frame_crc(0x182, &bytes[..7]);
    let back = decode(&CanFrame::new(0x182, &bytes).expect("frame")).expect("decode");
    assert_eq!(back, msg);
}
