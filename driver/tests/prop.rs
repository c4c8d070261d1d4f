//! Property tests: codec round trips, no panics on arbitrary input, candump round trips.

use std::time::Duration;

use proptest::prelude::*;
use rollbase_driver::candump::{
    format_line_with_kind, parse_line, parse_line_with_kind, FrameKind, LogEntry,
};
use rollbase_driver::codec::*;
use rollbase_driver::fault::{FaultInjector, FaultModel};
use rollbase_driver::frame::CanFrame;
use rollbase_driver::protocol::{spec, MessageKind};
use rollbase_driver::rx::Receiver;

/// Uniform physical value within the declared range of `kind.signal`.
fn in_range(kind: MessageKind, signal: &'static str) -> impl Strategy<Value = f64> {
    let s = spec(kind).signal(signal).expect("signal exists");
    s.min..=s.max
}

/// |a − b| within half a quantization step of `kind.signal`; 1e-9 of a step is allowed for
/// the floating-point error of the `raw · scale` product itself.
fn close(kind: MessageKind, signal: &'static str, a: f64, b: f64) -> Result<(), TestCaseError> {
    let s = spec(kind).signal(signal).expect("signal exists");
    let err = (a - b).abs();
    prop_assert!(
        err <= s.half_step() * (1.0 + 1e-9),
        "{kind}.{signal}: {a} → {b}, error {err} > half step {}",
        s.half_step()
    );
    Ok(())
}

fn node() -> impl Strategy<Value = u8> {
    1u8..=15
}

fn counter() -> impl Strategy<Value = u8> {
    0u8..=15
}

proptest! {
    #[test]
    fn sync_round_trip(cycle in any::<u16>(), c in counter()) {
        let m = Message { node: 0, counter: c, payload: Payload::Sync(Sync { cycle }) };
        prop_assert_eq!(decode(&encode(&m).expect("encode")).expect("decode"), m);
    }

    #[test]
    fn setpoint_round_trip(
        n in node(), c in counter(),
        w in in_range(MessageKind::Setpoint, "wheel_speed"),
        s in in_range(MessageKind::Setpoint, "steer_rate"),
        enable in any::<bool>(), brake in any::<bool>(), fault_reset in any::<bool>(),
    ) {
        let flags = SetpointFlags { enable, brake, fault_reset };
        let m = Message { node: n, counter: c, payload: Payload::Setpoint(Setpoint { wheel_speed: w, steer_rate: s, flags }) };
        let back = decode(&encode(&m).expect("encode")).expect("decode");
        prop_assert_eq!((back.node, back.counter), (n, c));
        let Payload::Setpoint(p) = back.payload else { return Err(TestCaseError::fail("kind")) };
        close(MessageKind::Setpoint, "wheel_speed", w, p.wheel_speed)?;
        close(MessageKind::Setpoint, "steer_rate", s, p.steer_rate)?;
        prop_assert_eq!(p.flags, flags);
    }

    #[test]
    fn feedback_a_round_trip(
        n in node(), c in counter(),
        a in in_range(MessageKind::FeedbackA, "steer_angle"),
        w in in_range(MessageKind::FeedbackA, "wheel_speed"),
        s in in_range(MessageKind::FeedbackA, "steer_rate"),
    ) {
        let m = Message { node: n, counter: c, payload: Payload::FeedbackA(FeedbackA { steer_angle: a, wheel_speed: w, steer_rate: s }) };
        let back = decode(&encode(&m).expect("encode")).expect("decode");
        prop_assert_eq!((back.node, back.counter), (n, c));
        let Payload::FeedbackA(p) = back.payload else { return Err(TestCaseError::fail("kind")) };
        close(MessageKind::FeedbackA, "steer_angle", a, p.steer_angle)?;
        close(MessageKind::FeedbackA, "wheel_speed", w, p.wheel_speed)?;
        close(MessageKind::FeedbackA, "steer_rate", s, p.steer_rate)?;
    }

    #[test]
    fn feedback_b_round_trip(
        n in node(), c in counter(),
        l in in_range(MessageKind::FeedbackB, "leg_extension"),
        r in in_range(MessageKind::FeedbackB, "leg_rate"),
        d in in_range(MessageKind::FeedbackB, "drive_current"),
        s in in_range(MessageKind::FeedbackB, "steer_current"),
    ) {
        let m = Message { node: n, counter: c, payload: Payload::FeedbackB(FeedbackB { leg_extension: l, leg_rate: r, drive_current: d, steer_current: s }) };
        let back = decode(&encode(&m).expect("encode")).expect("decode");
        prop_assert_eq!((back.node, back.counter), (n, c));
        let Payload::FeedbackB(p) = back.payload else { return Err(TestCaseError::fail("kind")) };
        close(MessageKind::FeedbackB, "leg_extension", l, p.leg_extension)?;
        close(MessageKind::FeedbackB, "leg_rate", r, p.leg_rate)?;
        close(MessageKind::FeedbackB, "drive_current", d, p.drive_current)?;
        close(MessageKind::FeedbackB, "steer_current", s, p.steer_current)?;
    }

    #[test]
    fn status_round_trip(
        n in node(), c in counter(), state in 0u8..=3, fault_code in any::<u8>(),
        t in in_range(MessageKind::Status, "temperature"),
        v in in_range(MessageKind::Status, "bus_voltage"),
    ) {
        let state = ModuleState::from_raw(state).expect("0..=3");
        let m = Message { node: n, counter: c, payload: Payload::Status(Status { state, fault_code, temperature: t, bus_voltage: v }) };
        let back = decode(&encode(&m).expect("encode")).expect("decode");
        prop_assert_eq!((back.node, back.counter), (n, c));
        let Payload::Status(p) = back.payload else { return Err(TestCaseError::fail("kind")) };
        prop_assert_eq!((p.state, p.fault_code), (state, fault_code));
        close(MessageKind::Status, "temperature", t, p.temperature)?;
        close(MessageKind::Status, "bus_voltage", v, p.bus_voltage)?;
    }

    #[test]
    fn out_of_range_never_encodes(w in prop_oneof![-1e12..-30.0005f64, 30.0005..1e12f64]) {
        let m = Message { node: 1, counter: 0, payload: Payload::Setpoint(Setpoint { wheel_speed: w, ..Setpoint::default() }) };
        let is_out_of_range = matches!(encode(&m), Err(EncodeError::OutOfRange { signal: "wheel_speed", .. }));
        prop_assert!(is_out_of_range);
    }

    #[test]
    fn decode_of_arbitrary_frames_never_panics_and_is_a_fixed_point(
        id in 0u16..=0x7FF, data in proptest::collection::vec(any::<u8>(), 0..=8),
    ) {
        let f = CanFrame::new(id, &data).expect("valid frame");
        if let Ok(m) = decode(&f) {
            // Whatever decodes re-encodes, and decodes to the same message again.
            let again = encode(&m).expect("a decoded message is in range");
            prop_assert_eq!(again.id(), id);
            prop_assert_eq!(decode(&again).expect("decode"), m);
        }
    }

    #[test]
    fn decode_of_valid_ids_with_random_payloads(
        kind in 0usize..5, n in node(), data in proptest::collection::vec(any::<u8>(), 0..=8),
    ) {
        // Bias towards protocol ids so the CRC/range paths are reached, not just UnknownId.
        let kind = MessageKind::ALL[kind];
        let id = rollbase_driver::protocol::id_of(kind, n);
        let mut bytes = data.clone();
        if bytes.len() == usize::from(spec(kind).dlc) {
            let last = bytes.len() - 1;
            bytes[last] = rollbase_driver::crc::frame_crc(id, &bytes[..last]);
        }
        let _ = decode(&CanFrame::new(id, &bytes).expect("valid frame"));
    }

    #[test]
    fn receiver_never_panics_and_accounts_for_every_frame(
        frames in proptest::collection::vec((0u16..=0x7FF, proptest::collection::vec(any::<u8>(), 0..=8)), 0..64),
    ) {
        let mut rx = Receiver::new();
        for (id, data) in &frames {
            let _ = rx.accept(&CanFrame::new(*id, data).expect("valid frame"));
        }
        let s = rx.stats();
        prop_assert_eq!(s.accepted + s.rejected(), frames.len() as u64);
    }

    #[test]
    fn candump_parse_of_arbitrary_strings_never_panics(s in "\\PC*") {
        let _ = parse_line(&s);
    }

    #[test]
    fn candump_parse_of_near_miss_lines_never_panics(
        s in "\\(([0-9]{0,12})\\.?[0-9]{0,10}\\)? ?[a-z0-9]{0,16} ?[0-9A-Fa-f]{0,9}#{0,2}[0-9A-Fa-fR_.]{0,20}",
    ) {
        let _ = parse_line(&s);
    }

    #[test]
    fn candump_format_parse_round_trip(
        secs in 0u64..=4_000_000_000, micros in 0u32..1_000_000,
        iface in "[a-z][a-z0-9]{0,14}", id in 0u16..=0x7FF,
        data in proptest::collection::vec(any::<u8>(), 0..=8), remote in any::<bool>(),
    ) {
        let frame = if remote {
            CanFrame::new(id, &vec![0; data.len()]).expect("frame")
        } else {
            CanFrame::new(id, &data).expect("frame")
        };
        let kind = if remote { FrameKind::Remote } else { FrameKind::Data };
        let e = LogEntry { timestamp: Duration::new(secs, micros * 1000), interface: iface, frame };
        let line = format_line_with_kind(&e, kind);
        prop_assert_eq!(parse_line_with_kind(&line).expect("parse"), (e, kind));
    }

    #[test]
    fn fault_injector_never_panics_and_emits_at_most_two(
        drop in -1.0f64..2.0, dup in -1.0f64..2.0, corrupt in -1.0f64..2.0,
        delay_us in 0u64..100_000, jitter_us in 0u64..100_000, seed in any::<u64>(),
        data in proptest::collection::vec(any::<u8>(), 0..=8),
    ) {
        let model = FaultModel { drop_prob: drop, duplicate_prob: dup, corrupt_prob: corrupt, delay: Duration::from_micros(delay_us), jitter: Duration::from_micros(jitter_us) };
        let mut inj = FaultInjector::new(model, seed);
        let f = CanFrame::new(0x181, &data).expect("frame");
        for k in 0..8u64 {
            let mut n = 0;
            let now = Duration::from_millis(k);
            inj.apply(now, &f, &mut |t, g| { n += 1; assert!(t >= now); assert_eq!(g.len(), f.len()); });
            prop_assert!(n <= 2);
        }
    }
}
