//! The CiA 402 profile's devices: per wheel a rolling drive and a steering drive (CiA 402)
//! and a leg encoder (CiA 406), each a complete simulated CANopen device
//! ([`device::Device`]) with its object dictionary ([`od::Dictionary`]).
//!
//! The simulator ([`crate::sim::Simulator`]) builds them when the platform's `protocol` is
//! `cia402`, from its `[cia402]` table (node-IDs, units, homing offsets), and moves the
//! plant with what the drives follow.

pub mod device;
pub mod od;
pub mod twin;

pub use device::{App, Device, DeviceNmt, DeviceStats};
pub use twin::{SteerAxis, TwinConfig};
