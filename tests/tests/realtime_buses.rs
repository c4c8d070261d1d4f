//! Two CAN buses in real time (issue 25): the six-wheel platform (wheels 1–3 on bus 0, 4–6
//! on bus 1) with the cycle thread on two wall-clock virtual buses
//! (`run_realtime_buses`) against the simulator serving both in its own thread
//! (`rollbase_vcan_sim::run_realtime_buses`): one SYNC per bus per cycle, each wheel's frames
//! only on its own bus in both directions (seen on the wire, at the controller's side of each
//! bus), the loop closed (fresh feedback from all six wheels, tracking), and deadline misses a
//! small fraction of the cycles.
//! This file holds a single test so no other test of this suite competes for the CPU.

use rollbase_control::runtime::scenario::{self, Scenario};
use rollbase_control::runtime::{
    percentile, run_realtime_buses, ControllerKind, CycleCore, RealtimeIo, RealtimeOptions,
};
use rollbase_control::Platform;
use rollbase_driver::bus::{BusClock, BusError, CanBus, VirtualBus, VirtualBusConfig};
use rollbase_driver::frame::{CanFrame, TimestampedFrame};
use rollbase_tests::RealtimeSim;
use rollbase_vcan_sim::{FaultSchedule, PlantConfig, Simulator};
use std::sync::atomic::AtomicBool;
use std::time::Instant;

/// SYNC's identifier in the native protocol (driver/src/protocol.rs).
const SYNC_ID: u16 = 0x080;

/// The controller's side of one bus: counts the SYNCs it sent and notes the nodes of the
/// other frames it sent and received (bit `node` set).
struct Tap<B> {
    inner: B,
    syncs: u64,
    nodes_sent: u128,
    nodes_received: u128,
}

impl<B> Tap<B> {
    fn new(inner: B) -> Self {
        Self {
            inner,
            syncs: 0,
            nodes_sent: 0,
            nodes_received: 0,
        }
    }
}

impl<B: CanBus> Tap<B> {
    fn note(&mut self, r: &Result<Option<TimestampedFrame>, BusError>) {
        if let Ok(Some(f)) = r {
            self.nodes_received |= 1u128 << (f.frame.id() & 0x7F);
        }
    }
}

impl<B: CanBus> CanBus for Tap<B> {
    fn send(&mut self, frame: &CanFrame) -> Result<(), BusError> {
        if frame.id() == SYNC_ID {
            self.syncs += 1;
        } else {
            self.nodes_sent |= 1u128 << (frame.id() & 0x7F);
        }
        self.inner.send(frame)
    }
    fn try_recv(&mut self) -> Result<Option<TimestampedFrame>, BusError> {
        let r = self.inner.try_recv();
        self.note(&r);
        r
    }
    fn recv_until(&mut self, deadline: Instant) -> Result<Option<TimestampedFrame>, BusError> {
        let r = self.inner.recv_until(deadline);
        self.note(&r);
        r
    }
    fn name(&self) -> &str {
        self.inner.name()
    }
}

#[test]
fn six_wheels_on_two_buses_in_real_time() {
    let p = Platform::six_wheel();
    assert_eq!(p.buses(), 2);
    let traj = scenario::trajectory(Scenario::Seed000, &p).unwrap();
    let r0 = traj.sample(0.0);
    let mut cfg = scenario::runtime_config(Scenario::Seed000);
    cfg.controller = ControllerKind::Dfl;
    let mut core = CycleCore::new(p.clone(), traj, cfg).unwrap();
    let sim = Simulator::new(&p, PlantConfig::default(), FaultSchedule::default(), &r0, 3).unwrap();
    let wall = || {
        VirtualBus::new(VirtualBusConfig {
            clock: BusClock::Wall,
            ..Default::default()
        })
    };
    let (bus0, bus1) = (wall(), wall());
    let mut ctrl0 = Tap::new(bus0.node("controller"));
    let mut ctrl1 = Tap::new(bus1.node("controller"));
    let sim_thread = RealtimeSim::start(sim, vec![bus0.node("simulator"), bus1.node("simulator")]);
    let (tx, rx) = std::sync::mpsc::sync_channel(4096);
    let stop = AtomicBool::new(false);
    let cycles = 500;
    let opts = RealtimeOptions {
        max_cycles: Some(cycles),
        ..Default::default()
    };
    let io = RealtimeIo {
        records: Some(&tx),
        ..Default::default()
    };
    let report = run_realtime_buses(
        &mut core,
        &mut [&mut ctrl0, &mut ctrl1],
        &stop,
        &io,
        &opts,
        0,
    )
    .expect("two buses for a two-bus platform");
    drop(tx);
    let sim_summary = sim_thread.finish();
    let records: Vec<_> = rx.iter().collect();
    let periods: Vec<f64> = records.iter().skip(1).map(|r| r.timing.period_us).collect();
    let last = records.last().expect("records");
    println!("setup: {:?}", report.setup);
    println!(
        "cycles {} misses {} skipped {} dropped {} bus errors {} | SYNCs bus 0 {} bus 1 {} | period p50 {:.0} p99 {:.0} µs | simulator in {} out {} max send lateness {:?} | final state {}",
        report.cycles,
        report.deadline_misses,
        report.skipped_cycles,
        report.records_dropped,
        report.bus_errors,
        ctrl0.syncs,
        ctrl1.syncs,
        percentile(&periods, 50.0),
        percentile(&periods, 99.0),
        sim_summary.frames_in,
        sim_summary.frames_out,
        sim_summary.max_send_lateness,
        last.state.name()
    );
    assert_eq!(
        report.cycles,
        cycles,
        "the run ended early in state {} ({:?})",
        last.state.name(),
        last.reason.map(|r| r.to_string())
    );
    assert_eq!(report.bus_errors, 0);
    // One SYNC per bus per cycle run.
    assert_eq!(ctrl0.syncs, cycles, "SYNCs on bus 0");
    assert_eq!(ctrl1.syncs, cycles, "SYNCs on bus 1");
    // Each wheel's frames on its own bus only, both ways: nodes 1–3 on bus 0, 4–6 on bus 1.
    let nodes = |b: u8| -> u128 {
        p.wheels
            .iter()
            .filter(|w| w.bus == b)
            .fold(0, |m, w| m | 1u128 << w.node)
    };
    assert_eq!(nodes(0), 0b1110);
    assert_eq!(nodes(1), 0b111_0000);
    assert_eq!(
        ctrl0.nodes_sent,
        nodes(0),
        "sent on bus 0: {:#b}",
        ctrl0.nodes_sent
    );
    assert_eq!(
        ctrl1.nodes_sent,
        nodes(1),
        "sent on bus 1: {:#b}",
        ctrl1.nodes_sent
    );
    assert_eq!(
        ctrl0.nodes_received,
        nodes(0),
        "received on bus 0: {:#b}",
        ctrl0.nodes_received
    );
    assert_eq!(
        ctrl1.nodes_received,
        nodes(1),
        "received on bus 1: {:#b}",
        ctrl1.nodes_received
    );
    // The loop is closed on both buses.
    assert_eq!(last.n, 6);
    assert!(
        last.feedback_age[..last.n].iter().all(|&a| a <= 1),
        "fresh feedback: {:?}",
        last.feedback_age
    );
    assert!(
        matches!(last.state.name(), "tracking" | "aligning"),
        "state {} ({:?})",
        last.state.name(),
        last.reason.map(|r| r.to_string())
    );
    // A tenth is room for a shared machine's stalls.
    assert!(
        report.deadline_misses * 10 < report.cycles,
        "{} deadline misses in {} cycles ({} skipped)",
        report.deadline_misses,
        report.cycles,
        report.skipped_cycles
    );
}
