//! Virtual bus: ordering, timestamps, fan-out, each fault kind, determinism from the seed.

use std::time::{Duration, Instant};

use rollbase_driver::bus::{AsyncCanBus, BusClock, CanBus, VirtualBus, VirtualBusConfig};
use rollbase_driver::codec::{decode, encode, FeedbackA, Message, Payload};
use rollbase_driver::fault::FaultModel;
use rollbase_driver::frame::{CanFrame, TimestampedFrame};
use rollbase_driver::rx::{Receiver, RxError};

fn frame(i: u16) -> CanFrame {
    CanFrame::new(0x100 + (i % 0x100), &i.to_le_bytes()).expect("frame")
}

fn drain(node: &mut rollbase_driver::bus::VirtualNode) -> Vec<TimestampedFrame> {
    let mut v = Vec::new();
    while let Some(f) = node.try_recv().expect("recv") {
        v.push(f);
    }
    v
}

fn cfg(faults: FaultModel, seed: u64) -> VirtualBusConfig {
    VirtualBusConfig {
        faults,
        seed,
        ..VirtualBusConfig::default()
    }
}

#[test]
fn fan_out_in_order_with_timestamps_and_not_to_sender() {
    let bus = VirtualBus::new(VirtualBusConfig::default());
    let mut tx = bus.node("controller");
    let mut rxs: Vec<_> = (0..8).map(|i| bus.node(&format!("module{i}"))).collect();
    for i in 0..100u16 {
        bus.set_time(Duration::from_micros(250 * u64::from(i)));
        tx.send(&frame(i)).expect("send");
    }
    assert_eq!(
        tx.try_recv().expect("recv"),
        None,
        "sender does not hear itself"
    );
    for rx in &mut rxs {
        let got = drain(rx);
        assert_eq!(got.len(), 100);
        for (i, f) in got.iter().enumerate() {
            assert_eq!(f.frame, frame(i as u16), "order");
            assert_eq!(
                f.timestamp,
                Duration::from_micros(250 * i as u64),
                "timestamp"
            );
        }
    }
    let s = bus.stats();
    assert_eq!((s.sent, s.delivered), (100, 800));
}

#[test]
fn two_senders_interleave_in_send_order() {
    let bus = VirtualBus::new(VirtualBusConfig::default());
    let mut a = bus.node("a");
    let mut b = bus.node("b");
    let mut c = bus.node("c");
    a.send(&frame(1)).expect("send");
    b.send(&frame(2)).expect("send");
    a.send(&frame(3)).expect("send");
    let got: Vec<_> = drain(&mut c).into_iter().map(|f| f.frame).collect();
    assert_eq!(got, vec![frame(1), frame(2), frame(3)]);
    assert_eq!(drain(&mut a).len(), 1, "a hears b only");
    assert_eq!(drain(&mut b).len(), 2, "b hears a twice");
}

#[test]
fn delay_holds_frames_until_virtual_time_reaches_delivery() {
    let bus = VirtualBus::new(cfg(
        FaultModel {
            delay: Duration::from_micros(300),
            ..FaultModel::none()
        },
        1,
    ));
    let mut tx = bus.node("tx");
    let mut rx = bus.node("rx");
    bus.set_time(Duration::from_millis(4));
    tx.send(&frame(7)).expect("send");
    assert_eq!(rx.try_recv().expect("recv"), None, "not yet delivered");
    // recv_until in virtual mode never blocks on wall time.
    let t0 = Instant::now();
    assert_eq!(
        rx.recv_until(Instant::now() + Duration::from_secs(5))
            .expect("recv"),
        None
    );
    assert!(t0.elapsed() < Duration::from_secs(1));
    bus.set_time(Duration::from_micros(4299));
    assert_eq!(rx.try_recv().expect("recv"), None);
    bus.set_time(Duration::from_micros(4300));
    let f = rx.try_recv().expect("recv").expect("delivered now");
    assert_eq!(f.timestamp, Duration::from_micros(4300));
    assert_eq!(f.frame, frame(7));
    assert_eq!(bus.stats().faults.delayed, 1);
}

fn run_faulty(faults: FaultModel, seed: u64, n: u16) -> Vec<TimestampedFrame> {
    let bus = VirtualBus::new(VirtualBusConfig {
        queue_capacity: 2 * usize::from(n),
        ..cfg(faults, seed)
    });
    let mut tx = bus.node("tx");
    let mut rx = bus.node("rx");
    for i in 0..n {
        bus.set_time(Duration::from_millis(u64::from(i)));
        tx.send(&frame(i)).expect("send");
    }
    bus.set_time(Duration::from_secs(3600));
    drain(&mut rx)
}

#[test]
fn drop_is_deterministic_from_seed() {
    let m = FaultModel {
        drop_prob: 0.1,
        ..FaultModel::none()
    };
    let a = run_faulty(m, 42, 2000);
    let b = run_faulty(m, 42, 2000);
    let c = run_faulty(m, 43, 2000);
    assert_eq!(a, b, "same seed, same deliveries");
    assert_ne!(a, c, "different seed, different deliveries");
    // Binomial(2000, 0.9): mean 1800, sd 13.4.
    assert!((a.len() as i64 - 1800).abs() < 70, "delivered {}", a.len());
    // Survivors keep their order.
    let ids: Vec<u16> = a
        .iter()
        .map(|f| u16::from_le_bytes([f.frame.data()[0], f.frame.data()[1]]))
        .collect();
    assert!(ids.windows(2).all(|w| w[0] < w[1]));
}

#[test]
fn duplicate_is_deterministic_and_rejected_by_the_receiver() {
    let m = FaultModel {
        duplicate_prob: 0.2,
        ..FaultModel::none()
    };
    let bus = VirtualBus::new(cfg(m, 5));
    let mut tx = bus.node("module1");
    let mut rx = bus.node("controller");
    for i in 0..500u16 {
        let f = encode(&Message {
            node: 1,
            counter: (i % 16) as u8,
            payload: Payload::FeedbackA(FeedbackA::default()),
        })
        .expect("encode");
        tx.send(&f).expect("send");
    }
    let got = drain(&mut rx);
    let dups = bus.stats().faults.duplicated;
    assert_eq!(got.len() as u64, 500 + dups);
    assert!(dups > 50 && dups < 150, "duplicated {dups}");
    let mut r = Receiver::new();
    let mut repeated = 0;
    for f in &got {
        match r.accept(&f.frame) {
            Ok(_) => {}
            Err(RxError::RepeatedCounter { .. }) => repeated += 1,
            Err(e) => panic!("unexpected {e}"),
        }
    }
    assert_eq!(repeated, dups);
    assert_eq!(r.stats().accepted, 500);
    let again = run_faulty(m, 5, 500);
    assert_eq!(again, run_faulty(m, 5, 500));
}

#[test]
fn corruption_is_caught_by_the_crc() {
    let m = FaultModel {
        corrupt_prob: 0.3,
        ..FaultModel::none()
    };
    let bus = VirtualBus::new(cfg(m, 77));
    let mut tx = bus.node("module1");
    let mut rx = bus.node("controller");
    for i in 0..1000u16 {
        let f = encode(&Message {
            node: 1,
            counter: (i % 16) as u8,
            payload: Payload::FeedbackA(FeedbackA {
                steer_angle: f64::from(i) * 1e-3,
                wheel_speed: 2.0,
                steer_rate: -1.0,
            }),
        })
        .expect("encode");
        tx.send(&f).expect("send");
    }
    let got = drain(&mut rx);
    assert_eq!(got.len(), 1000);
    let bad = got.iter().filter(|f| decode(&f.frame).is_err()).count() as u64;
    assert_eq!(
        bad,
        bus.stats().faults.corrupted,
        "every corrupted frame is rejected"
    );
    assert!(bad > 240 && bad < 360, "corrupted {bad}");
}

#[test]
fn silence_drops_one_nodes_transmissions_only() {
    let bus = VirtualBus::new(VirtualBusConfig::default());
    let mut m1 = bus.node("module1");
    let mut m2 = bus.node("module2");
    let mut ctl = bus.node("controller");
    bus.silence("module1", true);
    m1.send(&frame(1))
        .expect("silenced send still succeeds locally");
    m2.send(&frame(2)).expect("send");
    ctl.send(&frame(3)).expect("send");
    let got: Vec<_> = drain(&mut ctl).into_iter().map(|f| f.frame).collect();
    assert_eq!(got, vec![frame(2)]);
    assert_eq!(drain(&mut m1).len(), 2, "a silenced node still receives");
    bus.silence("module1", false);
    m1.send(&frame(4)).expect("send");
    assert_eq!(drain(&mut ctl).len(), 1);
    assert_eq!(bus.stats().silenced, 1);
}

#[test]
fn full_queue_drops_oldest_and_counts_overrun() {
    let bus = VirtualBus::new(VirtualBusConfig {
        queue_capacity: 4,
        ..VirtualBusConfig::default()
    });
    let mut tx = bus.node("tx");
    let mut rx = bus.node("rx");
    for i in 0..10 {
        tx.send(&frame(i)).expect("send");
    }
    let got: Vec<_> = drain(&mut rx).into_iter().map(|f| f.frame).collect();
    assert_eq!(got, (6..10).map(frame).collect::<Vec<_>>());
    assert_eq!(rx.overruns(), 6);
    assert_eq!(bus.stats().overruns, 6);
}

#[test]
fn dropped_node_stops_receiving_and_close_fails_everyone() {
    let bus = VirtualBus::new(VirtualBusConfig::default());
    let mut tx = bus.node("tx");
    let rx = bus.node("gone");
    drop(rx);
    tx.send(&frame(1)).expect("send");
    assert_eq!(bus.stats().delivered, 0);
    assert_eq!(bus.node_names(), vec!["tx".to_string()]);
    bus.close();
    let e = tx.send(&frame(2)).expect_err("closed");
    assert!(!e.is_retryable());
}

#[test]
fn wall_clock_recv_until_wakes_on_send_from_another_thread() {
    let bus = VirtualBus::new(VirtualBusConfig {
        clock: BusClock::Wall,
        ..VirtualBusConfig::default()
    });
    let mut rx = bus.node("rx");
    let mut tx = bus.node("tx");
    let h = std::thread::spawn(move || {
        std::thread::sleep(Duration::from_millis(20));
        tx.send(&frame(9)).expect("send");
        tx
    });
    let got = rx
        .recv_until(Instant::now() + Duration::from_secs(10))
        .expect("recv")
        .expect("frame arrives before the deadline");
    assert_eq!(got.frame, frame(9));
    let _tx = h.join().expect("thread");
    // Timeout path returns None.
    assert_eq!(
        rx.recv_until(Instant::now() + Duration::from_millis(5))
            .expect("recv"),
        None
    );
}

#[test]
fn wall_clock_delay_is_honoured_by_recv_until() {
    let bus = VirtualBus::new(VirtualBusConfig {
        clock: BusClock::Wall,
        faults: FaultModel {
            delay: Duration::from_millis(30),
            ..FaultModel::none()
        },
        ..VirtualBusConfig::default()
    });
    let mut rx = bus.node("rx");
    let mut tx = bus.node("tx");
    tx.send(&frame(1)).expect("send");
    assert_eq!(rx.try_recv().expect("recv"), None);
    let got = rx
        .recv_until(Instant::now() + Duration::from_secs(10))
        .expect("recv")
        .expect("delivered after the delay");
    assert!(bus.now() >= got.timestamp);
}

#[test]
fn async_recv_wakes_on_send_and_on_virtual_time() {
    let rt = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .expect("runtime");
    rt.block_on(async {
        let bus = VirtualBus::new(cfg(
            FaultModel {
                delay: Duration::from_millis(1),
                ..FaultModel::none()
            },
            0,
        ));
        let mut rx = bus.node("rx");
        let mut tx = bus.node("tx");
        let bus2 = bus.clone();
        let task = tokio::spawn(async move {
            AsyncCanBus::send(&mut tx, &frame(5)).await.expect("send");
            tokio::task::yield_now().await;
            bus2.set_time(Duration::from_millis(1));
            tx
        });
        let got = AsyncCanBus::recv(&mut rx).await.expect("recv");
        assert_eq!(got.frame, frame(5));
        assert_eq!(got.timestamp, Duration::from_millis(1));
        let _tx = task.await.expect("join");
    });
}

#[test]
fn async_recv_futures_are_send() {
    fn assert_send<T: Send>(_: &T) {}
    let bus = VirtualBus::new(VirtualBusConfig::default());
    let mut n = bus.node("n");
    let f = AsyncCanBus::recv(&mut n);
    assert_send(&f);
    drop(f);
    let f0 = frame(0);
    let g = AsyncCanBus::send(&mut n, &f0);
    assert_send(&g);
}

#[test]
fn boxed_virtual_node_is_a_can_bus() {
    let bus = VirtualBus::new(VirtualBusConfig::default());
    let mut a: Box<dyn CanBus> = Box::new(bus.node("a"));
    let mut b = bus.node("b");
    a.send(&frame(3)).expect("send");
    assert_eq!(a.name(), "a");
    assert_eq!(b.try_recv().expect("recv").map(|f| f.frame), Some(frame(3)));
}

#[test]
fn all_fault_kinds_together_are_reproducible_from_the_seed() {
    let m = FaultModel {
        drop_prob: 0.05,
        duplicate_prob: 0.05,
        corrupt_prob: 0.05,
        delay: Duration::from_micros(200),
        jitter: Duration::from_micros(500),
    };
    let a = run_faulty(m, 1234, 3000);
    assert_eq!(a, run_faulty(m, 1234, 3000), "same seed, same bus");
    assert_ne!(
        a,
        run_faulty(m, 1235, 3000),
        "different seed, different bus"
    );
    // Delivery times never go backwards and are at least send time + delay.
    assert!(a.windows(2).all(|w| w[0].timestamp <= w[1].timestamp));
    assert!(a.iter().all(|f| f.timestamp >= Duration::from_micros(200)));
}

#[test]
fn async_recv_in_wall_mode_waits_for_a_delayed_frame() {
    let rt = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .expect("runtime");
    rt.block_on(async {
        let bus = VirtualBus::new(VirtualBusConfig {
            clock: BusClock::Wall,
            faults: FaultModel {
                delay: Duration::from_millis(20),
                ..FaultModel::none()
            },
            ..VirtualBusConfig::default()
        });
        let mut rx = bus.node("rx");
        let mut tx = bus.node("tx");
        let sent_at = bus.now();
        tx.send(&frame(8)).expect("send");
        assert_eq!(rx.try_recv().expect("recv"), None, "still in flight");
        let got = tokio::time::timeout(Duration::from_secs(10), AsyncCanBus::recv(&mut rx))
            .await
            .expect("delivered well before 10 s")
            .expect("recv");
        assert_eq!(got.frame, frame(8));
        assert!(got.timestamp >= sent_at + Duration::from_millis(20));
        assert!(
            bus.now() >= got.timestamp,
            "not handed out before its delivery time"
        );
    });
}

#[test]
fn bus_off_node_reads_the_event_once_sends_fail_and_receives_nothing_until_restarted() {
    use rollbase_driver::bus::{BusError, BusEvent};
    let bus = VirtualBus::new(VirtualBusConfig::default());
    let mut ctl = bus.node("controller");
    let mut dev = bus.node("simulator");
    dev.send(&frame(1)).expect("send");
    bus.set_bus_off("controller", true);
    // The error frame comes first (once), then what was already received.
    let e = ctl.try_recv().expect_err("bus-off event");
    assert!(
        matches!(e, BusError::BusOff { .. }) && !e.is_retryable(),
        "{e:?}"
    );
    assert_eq!(e.bus_event(), Some(BusEvent::BusOff));
    assert_eq!(drain(&mut ctl).len(), 1);
    // Bus-off: nothing goes out, nothing comes in.
    let e = ctl.send(&frame(2)).expect_err("send while bus-off");
    assert!(matches!(e, BusError::BusOff { .. }), "{e:?}");
    assert!(drain(&mut dev).is_empty());
    dev.send(&frame(3)).expect("others still send");
    assert!(drain(&mut ctl).is_empty());
    // Setting the same state again reports nothing new.
    bus.set_bus_off("controller", true);
    assert!(ctl.try_recv().expect("no second event").is_none());
    // Restart: reported once, then traffic flows both ways.
    bus.set_bus_off("controller", false);
    let e = ctl.try_recv().expect_err("restart event");
    assert_eq!(e.bus_event(), Some(BusEvent::Restarted));
    assert!(e.is_retryable());
    ctl.send(&frame(4)).expect("send after restart");
    assert_eq!(drain(&mut dev).len(), 1);
    dev.send(&frame(5)).expect("send");
    assert_eq!(drain(&mut ctl).len(), 1);
    // Warning and error passive are delivered as typed, retryable events.
    bus.inject_event("controller", BusEvent::Warning);
    bus.inject_event("controller", BusEvent::ErrorPassive);
    for want in [BusEvent::Warning, BusEvent::ErrorPassive] {
        let e = ctl.try_recv().expect_err("event");
        assert!(
            matches!(e, BusError::Controller { event, .. } if event == want),
            "{e:?}"
        );
    }
    assert!(ctl.try_recv().expect("no more").is_none());
}
