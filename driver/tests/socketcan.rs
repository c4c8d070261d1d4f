//! SocketCAN tests: run against vcan0 when it exists, print that they were skipped when not.
//!
//! To run them for real: `sudo modprobe vcan && sudo ip link add dev vcan0 type vcan &&
//! sudo ip link set up vcan0` (or inside the VM described in DESIGN.md).

use std::time::{Duration, Instant, SystemTime, UNIX_EPOCH};

use rollbase_driver::bus::socketcan::{protocol_filters, AsyncSocketCanBus, SocketCanBus};
use rollbase_driver::bus::{self, AsyncCanBus, BusError, CanBus};
use rollbase_driver::frame::CanFrame;

const IFACE: &str = "vcan0";

fn open_or_skip(test: &str) -> Option<SocketCanBus> {
    match SocketCanBus::open(IFACE) {
        Ok(b) => Some(b),
        Err(e) => {
            println!("skipped: {IFACE} not available ({e}) [{test}]");
            None
        }
    }
}

#[test]
fn open_errors_say_what_to_do() {
    // Works with or without kernel CAN: a missing interface is either "does not exist" with
    // the commands to create it, or "kernel has no CAN support" pointing at --bus virtual.
    let e = SocketCanBus::open("rbnosuch9").expect_err("no such interface");
    match &e {
        BusError::NoSuchInterface { hint, .. } => assert!(hint.contains("ip link"), "{e}"),
        BusError::AfCanUnsupported { .. } => {
            assert!(e.to_string().contains("--bus virtual"), "{e}")
        }
        other => panic!("unexpected error {other:?}"),
    }
    assert!(!e.is_retryable());
    let e = SocketCanBus::open("vcan_this_name_is_too_long").expect_err("too long");
    assert!(matches!(e, BusError::InvalidName { .. }), "{e:?}");
    let e = bus::open("virtual")
        .err()
        .expect("virtual is in-process only");
    assert!(e.to_string().contains("VirtualBus::new"), "{e}");
    let e = bus::open("").err().expect("empty name");
    assert!(matches!(e, BusError::InvalidName { .. }));
}

#[test]
fn vcan_missing_interface_hint_names_the_commands() {
    match SocketCanBus::open("vcan9") {
        Ok(_) => println!("skipped: vcan9 exists on this machine"),
        Err(BusError::NoSuchInterface { hint, .. }) => {
            assert!(hint.contains("sudo modprobe vcan && sudo ip link add dev vcan9 type vcan && sudo ip link set up vcan9"), "{hint}");
        }
        Err(e @ BusError::AfCanUnsupported { .. }) => {
            assert!(e.to_string().contains("no CAN support"), "{e}");
            println!("kernel without AF_CAN: {e}");
        }
        Err(e) => panic!("unexpected {e:?}"),
    }
}

#[test]
fn vcan0_send_receive_timestamps_and_filters() {
    let Some(mut a) = open_or_skip("send_receive") else {
        return;
    };
    let Some(mut b) = open_or_skip("send_receive") else {
        return;
    };
    // Drain anything already queued.
    while b.try_recv().expect("recv").is_some() {}
    let f = CanFrame::new(0x181, &[1, 2, 3, 4, 5, 6, 7, 8]).expect("frame");
    let before = SystemTime::now().duration_since(UNIX_EPOCH).expect("clock");
    a.send(&f).expect("send");
    let got = b
        .recv_until(Instant::now() + Duration::from_secs(1))
        .expect("recv")
        .expect("frame within 1 s");
    assert_eq!(got.frame, f);
    assert!(
        got.timestamp + Duration::from_millis(100) >= before,
        "timestamp is epoch-based"
    );
    assert_eq!(
        a.try_recv().expect("recv"),
        None,
        "own frames are not received"
    );

    b.set_filters(&protocol_filters()).expect("filters");
    a.send(&CanFrame::new(0x123, &[9]).expect("frame"))
        .expect("send");
    a.send(&CanFrame::new(0x702, &[0; 6]).expect("frame"))
        .expect("send");
    let got = b
        .recv_until(Instant::now() + Duration::from_secs(1))
        .expect("recv")
        .expect("STATUS passes the filter");
    assert_eq!(got.frame.id(), 0x702, "0x123 was filtered out");
    let t0 = Instant::now();
    assert_eq!(
        b.recv_until(t0 + Duration::from_millis(20)).expect("recv"),
        None
    );
}

#[test]
fn vcan0_async_round_trip() {
    if open_or_skip("async_round_trip").is_none() {
        return;
    }
    let rt = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .expect("runtime");
    rt.block_on(async {
        let mut a = AsyncSocketCanBus::open(IFACE).expect("open");
        let mut b = AsyncSocketCanBus::open(IFACE).expect("open");
        let f = CanFrame::new(0x080, &[0x34, 0x12, 0x05, 0x58]).expect("frame");
        AsyncCanBus::send(&mut a, &f).await.expect("send");
        let got = tokio::time::timeout(Duration::from_secs(1), AsyncCanBus::recv(&mut b))
            .await
            .expect("within 1 s")
            .expect("recv");
        assert_eq!(got.frame, f);
    });
}
