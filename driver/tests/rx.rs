//! Receiver: every RxError kind, both counter policies, statistics.

use rollbase_driver::codec::*;
use rollbase_driver::frame::CanFrame;
use rollbase_driver::protocol::MessageKind;
use rollbase_driver::rx::{CounterPolicy, Receiver, RxError};

fn fa(node: u8, counter: u8) -> CanFrame {
    encode(&Message {
        node,
        counter,
        payload: Payload::FeedbackA(FeedbackA {
            steer_angle: 0.1,
            wheel_speed: 1.0,
            steer_rate: 0.0,
        }),
    })
    .expect("encode")
}

#[test]
fn first_frame_any_counter_then_in_sequence_wrapping() {
    let mut rx = Receiver::new();
    for c in [13u8, 14, 15, 0, 1, 2] {
        let m = rx.accept(&fa(1, c)).expect("in sequence");
        assert_eq!(m.counter, c);
    }
    assert_eq!(rx.stats().accepted, 6);
    assert_eq!(rx.stats().rejected(), 0);
}

#[test]
fn repeated_counter_is_rejected_and_state_kept() {
    let mut rx = Receiver::new();
    rx.accept(&fa(1, 4)).expect("first");
    assert_eq!(
        rx.accept(&fa(1, 4)),
        Err(RxError::RepeatedCounter {
            kind: MessageKind::FeedbackA,
            node: 1,
            counter: 4
        })
    );
    rx.accept(&fa(1, 5))
        .expect("next in sequence still accepted");
    assert_eq!(rx.stats().repeated, 1);
    assert_eq!(rx.stats().accepted, 2);
}

#[test]
fn skipped_counter_reports_loss_and_resyncs() {
    let mut rx = Receiver::new();
    rx.accept(&fa(2, 14)).expect("first");
    // 15, 0, 1 lost: got 2 after 14 → lost = (2 − 14 − 1) mod 16 = 3.
    assert_eq!(
        rx.accept(&fa(2, 2)),
        Err(RxError::SkippedCounter {
            kind: MessageKind::FeedbackA,
            node: 2,
            expected: 15,
            got: 2,
            lost: 3
        })
    );
    rx.accept(&fa(2, 3))
        .expect("re-synchronised to 2, so 3 is accepted");
    let s = rx.stats();
    assert_eq!((s.skipped, s.lost, s.accepted), (1, 3, 2));
    let e = RxError::SkippedCounter {
        kind: MessageKind::FeedbackA,
        node: 2,
        expected: 15,
        got: 2,
        lost: 3,
    };
    assert!(e.to_string().contains("3 frame(s) lost"), "{e}");
}

#[test]
fn accept_with_loss_policy_returns_ok_but_counts() {
    let mut rx = Receiver::with_policy(CounterPolicy::AcceptWithLoss);
    rx.accept(&fa(1, 0)).expect("first");
    let m = rx.accept(&fa(1, 5)).expect("accepted with loss");
    assert_eq!(m.counter, 5);
    assert!(matches!(
        rx.accept(&fa(1, 5)),
        Err(RxError::RepeatedCounter { .. })
    ));
    let s = rx.stats();
    assert_eq!((s.accepted, s.skipped, s.lost, s.repeated), (2, 1, 4, 1));
}

#[test]
fn streams_are_independent_per_kind_and_node() {
    let mut rx = Receiver::new();
    rx.accept(&fa(1, 3)).expect("node 1");
    rx.accept(&fa(2, 9)).expect("node 2 has its own counter");
    let status = encode(&Message {
        node: 1,
        counter: 0,
        payload: Payload::Status(Status::default()),
    })
    .expect("encode");
    rx.accept(&status).expect("STATUS node 1 is its own stream");
    rx.accept(&fa(1, 4)).expect("node 1 continues");
    rx.accept(&fa(2, 10)).expect("node 2 continues");
    assert_eq!(rx.stats().accepted, 5);
}

#[test]
fn reset_stream_accepts_any_next_counter() {
    let mut rx = Receiver::new();
    rx.accept(&fa(1, 3)).expect("first");
    rx.reset_stream(MessageKind::FeedbackA, 1);
    rx.accept(&fa(1, 3))
        .expect("after reset, a repeat is a first frame");
    assert!(rx.accept(&fa(1, 3)).is_err());
}

#[test]
fn decode_errors_are_counted_by_kind_and_do_not_touch_streams() {
    let mut rx = Receiver::new();
    rx.accept(&fa(1, 0)).expect("first");
    let good = fa(1, 1);
    let corrupt = good.with_flipped_bit(3);
    assert!(matches!(
        rx.accept(&corrupt),
        Err(RxError::Decode(DecodeError::BadCrc { .. }))
    ));
    let short = CanFrame::new(0x181, &good.data()[..6]).expect("frame");
    assert!(matches!(
        rx.accept(&short),
        Err(RxError::Decode(DecodeError::WrongDlc { .. }))
    ));
    let unknown = CanFrame::new(0x555, &[1]).expect("frame");
    assert!(matches!(
        rx.accept(&unknown),
        Err(RxError::Decode(DecodeError::UnknownId { .. }))
    ));
    let mut oor = [0u8; 8];
    oor[..2].copy_from_slice(&(-32000i16).to_le_bytes());
    oor[6] = 1;
    oor[7] = rollbase_driver::crc::frame_crc(0x181, &oor[..7]);
    assert!(matches!(
        rx.accept(&CanFrame::new(0x181, &oor).expect("frame")),
        Err(RxError::Decode(DecodeError::OutOfRange { .. }))
    ));
    let node0 = CanFrame::new(0x200, &[0; 6]).expect("frame");
    assert!(matches!(
        rx.accept(&node0),
        Err(RxError::Decode(DecodeError::BadNode { .. }))
    ));
    // The stream is untouched by all of the above: counter 1 is still next.
    rx.accept(&good).expect("in sequence");
    let s = *rx.stats();
    assert_eq!(
        (
            s.bad_crc,
            s.wrong_dlc,
            s.unknown_id,
            s.out_of_range,
            s.other,
            s.accepted
        ),
        (1, 1, 1, 1, 1, 2)
    );
    assert_eq!(s.rejected(), 5);
    rx.reset_stats();
    assert_eq!(rx.stats().accepted, 0);
}
