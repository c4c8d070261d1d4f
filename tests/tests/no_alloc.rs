//! The cycle core allocates nothing per cycle: a counting global allocator around
//! `start_cycle`, `on_frame` and `finish_cycle` (the simulator and the bus are outside the
//! counted region), over the seed-000 scenario with avoidance on, in lockstep.
//! A single test in this binary, so no other test allocates on the counted thread's behalf.

use rollbase_control::avoidance::AvoidanceConfig;
use rollbase_control::runtime::{
    lockstep_cycle, CycleCore, LockstepState, StepHooks, VirtualLockstepBus,
};
use rollbase_control::scenario::{self, Scenario};
use rollbase_control::Platform;
use rollbase_driver::fault::FaultModel;
use rollbase_tests::alloc_count::{allocations, set_counting, CountingAlloc};
use rollbase_vcan_sim::{FaultSchedule, PlantConfig, Simulator};

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
    let mut st = LockstepState::new(&core);
    core.arm();
    let mut counted_cycles = 0;
    let mut count = |on: bool| set_counting(on);
    for _ in 0..7000u64 {
        let mut hooks = StepHooks {
            around_core: Some(&mut count),
            ..Default::default()
        };
        lockstep_cycle(&mut st, &mut core, &mut bus, &mut sim, &mut hooks);
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
