//! The cycle core allocates nothing per cycle: a counting global allocator around
//! `start_cycle`, `on_frame` and `finish_cycle` (the simulator and the bus are outside the
//! counted region), over the seed-000 scenario with avoidance on, in lockstep.
//! A single test in this binary, so no other test allocates on the counted thread's behalf.

use rollbase_control::avoidance::AvoidanceConfig;
use rollbase_control::runtime::{CycleCore, LockstepBus, LockstepPeer, VirtualLockstepBus};
use rollbase_control::scenario::{self, Scenario};
use rollbase_control::{Platform, MAX_WHEELS};
use rollbase_driver::fault::FaultModel;
use rollbase_driver::frame::CanFrame;
use rollbase_tests::alloc_count::{allocations, counted, CountingAlloc};
use rollbase_vcan_sim::{FaultSchedule, PlantConfig, Simulator};
use std::time::Duration;

#[global_allocator]
static GLOBAL: CountingAlloc = CountingAlloc;

#[test]
fn the_cycle_core_does_not_allocate() {
    let p = Platform::justin();
    let traj = scenario::trajectory(Scenario::Seed000, &p).unwrap();
    let r0 = traj.sample(0.0);
    let mut cfg = scenario::runtime_config(Scenario::Seed000);
    cfg.avoidance = Some(AvoidanceConfig::default());
    let mut core = CycleCore::new(p.clone(), traj, cfg).unwrap();
    let mut sim =
        Simulator::new(&p, PlantConfig::default(), FaultSchedule::default(), &r0, 5).unwrap();
    let mut bus = VirtualLockstepBus::new(FaultModel::none(), 5);
    let dt = p.dt();
    let mut out = [CanFrame::new(0, &[]).unwrap(); MAX_WHEELS];
    let mut pending: Vec<(Duration, CanFrame)> = Vec::with_capacity(256);
    let mut rx: Vec<(f64, CanFrame)> = Vec::with_capacity(256);
    core.arm();
    let mut counted_cycles = 0;
    for k in 0..7000u64 {
        let t0 = Duration::from_secs_f64(k as f64 * dt);
        let tw = Duration::from_secs_f64(k as f64 * dt + 0.002);
        sim.advance_to(t0);
        bus.set_time(t0);
        let sync = counted(|| core.start_cycle(t0.as_secs_f64()));
        bus.controller_send(&sync).unwrap();
        while let Ok(Some(f)) = bus.peer_recv() {
            LockstepPeer::on_frame(&mut sim, f.timestamp, &f.frame);
        }
        sim.advance_to(tw);
        sim.drain_tx(&mut |t, f| pending.push((t, f)));
        pending.sort_by_key(|x| x.0);
        for (t, f) in pending.drain(..) {
            bus.set_time(t.min(tw));
            bus.peer_send(&f).unwrap();
        }
        bus.set_time(tw);
        rx.clear();
        while let Ok(Some(f)) = bus.controller_recv() {
            rx.push((f.timestamp.as_secs_f64(), f.frame));
        }
        let m = counted(|| {
            for (t, f) in &rx {
                core.on_frame(f, *t);
            }
            core.finish_cycle(tw.as_secs_f64(), &mut out)
        });
        for f in out.iter().take(m) {
            bus.controller_send(f).unwrap();
        }
        while let Ok(Some(f)) = bus.peer_recv() {
            LockstepPeer::on_frame(&mut sim, f.timestamp, &f.frame);
        }
        if core.state().name() == "tracking" {
            counted_cycles += 1;
        }
        if core.done() {
            break;
        }
    }
    assert!(counted_cycles > 5000, "tracked {counted_cycles} cycles");
    assert_eq!(allocations(), 0, "allocations inside the cycle core");
}
