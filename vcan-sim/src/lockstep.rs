//! The simulator as the controller's lockstep peer
//! (`rollbase_control::runtime::run_lockstep`).

use crate::sim::Simulator;
use rollbase_control::runtime::LockstepPeer;
use rollbase_control::{Pose, MAX_WHEELS};
use rollbase_driver::frame::CanFrame;
use std::time::Duration;

/// The simulator is the controller's peer in `rollbase_control::runtime::run_lockstep`.
impl LockstepPeer for Simulator {
    fn on_frame(&mut self, now: Duration, frame: &CanFrame) {
        Simulator::on_frame(self, now, frame);
    }
    fn advance_to(&mut self, now: Duration) {
        Simulator::advance_to(self, now);
    }
    fn drain_tx(&mut self, out: &mut dyn FnMut(Duration, CanFrame)) {
        Simulator::drain_tx(self, &mut |t, f| out(t, f));
    }
    fn truth(&self) -> Option<(Pose, [f64; MAX_WHEELS])> {
        let t = self.truth();
        Some((t.pose, t.legs))
    }
    fn controller_bus_off(&self, now: Duration) -> bool {
        self.is_controller_bus_off(now)
    }
    fn bus_of(&self, frame: &CanFrame) -> usize {
        self.bus_of_node((frame.id() & 0x7F) as u8)
    }
    fn on_frame_on(&mut self, bus: usize, now: Duration, frame: &CanFrame) {
        Simulator::on_frame_on(self, bus, now, frame);
    }
}
