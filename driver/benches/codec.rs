//! The codec on one full control cycle's frames: SYNC, four SETPOINTs and eight feedback
//! frames (FEEDBACK_A + FEEDBACK_B per module), with realistic mid-range values.
//!
//! - `codec/cycle_encode_decode`: encode all 13 messages, then decode all 13 frames.
//! - `codec/cycle_encode` and `codec/cycle_decode`: the two halves.
//! - `codec/cycle_receiver`: the controller's receive path on the 8 feedback frames
//!   (`rx::Receiver::accept`: decode + CRC + rolling-counter check).
//!
//! Counters advance every cycle as on the bus, so the receiver sees a valid stream.

use criterion::{criterion_group, criterion_main, Criterion};
use rollbase_driver::codec::{
    decode, encode, FeedbackA, FeedbackB, Message, Payload, Setpoint, SetpointFlags, Sync,
};
use rollbase_driver::frame::CanFrame;
use rollbase_driver::protocol::DEFAULT_NODES;
use rollbase_driver::rx::Receiver;
use std::hint::black_box;

/// The 13 messages of cycle `k` (counters `k mod 16`).
fn cycle_messages(k: u32) -> [Message; 13] {
    let c = (k & 0x0F) as u8;
    let x = f64::from(k % 100) * 1e-3;
    let mut m = [Message {
        node: 0,
        counter: c,
        payload: Payload::Sync(Sync {
            cycle: (k & 0xFFFF) as u16,
        }),
    }; 13];
    for (i, &node) in DEFAULT_NODES.iter().enumerate() {
        let s = i as f64;
        m[1 + i] = Message {
            node,
            counter: c,
            payload: Payload::Setpoint(Setpoint {
                wheel_speed: 12.5 - s - x,
                steer_rate: -0.75 + 0.1 * s + x,
                flags: SetpointFlags {
                    enable: true,
                    brake: false,
                    fault_reset: false,
                },
            }),
        };
        m[5 + 2 * i] = Message {
            node,
            counter: c,
            payload: Payload::FeedbackA(FeedbackA {
                steer_angle: 1.2345 - 0.5 * s + x,
                wheel_speed: 12.5 - s,
                steer_rate: -0.75 + 0.1 * s,
            }),
        };
        m[6 + 2 * i] = Message {
            node,
            counter: c,
            payload: Payload::FeedbackB(FeedbackB {
                leg_extension: 0.45 + 0.01 * s + 0.1 * x,
                leg_rate: 0.0123,
                drive_current: 3.25 + s,
                steer_current: -1.5,
            }),
        };
    }
    m
}

fn encode_all(msgs: &[Message; 13], out: &mut [CanFrame; 13]) -> usize {
    let mut ok = 0;
    for (m, f) in msgs.iter().zip(out.iter_mut()) {
        if let Ok(e) = encode(m) {
            *f = e;
            ok += 1;
        }
    }
    ok
}

fn decode_all(frames: &[CanFrame; 13]) -> usize {
    frames
        .iter()
        .filter(|f| decode(f).map(black_box).is_ok())
        .count()
}

fn benches(c: &mut Criterion) {
    let msgs: Vec<[Message; 13]> = (0..16).map(cycle_messages).collect();
    let blank = match CanFrame::new(0, &[]) {
        Ok(f) => f,
        Err(e) => panic!("empty frame: {e}"),
    };
    let mut frames = vec![[blank; 13]; 16];
    for (m, f) in msgs.iter().zip(frames.iter_mut()) {
        assert_eq!(encode_all(m, f), 13, "every message of the cycle encodes");
        assert_eq!(decode_all(f), 13, "every frame of the cycle decodes");
    }

    let mut k = 0usize;
    let mut buf = [blank; 13];
    c.bench_function("codec/cycle_encode_decode", |b| {
        b.iter(|| {
            k = (k + 1) & 15;
            let n = encode_all(black_box(&msgs[k]), &mut buf);
            n + decode_all(black_box(&buf))
        })
    });
    c.bench_function("codec/cycle_encode", |b| {
        b.iter(|| {
            k = (k + 1) & 15;
            let n = encode_all(black_box(&msgs[k]), &mut buf);
            black_box(&buf);
            n
        })
    });
    c.bench_function("codec/cycle_decode", |b| {
        b.iter(|| {
            k = (k + 1) & 15;
            decode_all(black_box(&frames[k]))
        })
    });
    let mut rx = Receiver::new();
    let mut cycle = 0usize;
    c.bench_function("codec/cycle_receiver", |b| {
        b.iter(|| {
            cycle = (cycle + 1) & 15;
            let mut ok = 0;
            for f in &frames[cycle][5..] {
                ok += usize::from(rx.accept(black_box(f)).is_ok());
            }
            ok
        })
    });
    assert_eq!(
        rx.stats().rejected(),
        0,
        "the replayed feedback stream is valid (counters in order)"
    );
}

criterion_group!(codec, benches);
criterion_main!(codec);
