//! rollbase-vcan-sim: the other side of every frame the driver sends.
//!
//! - [`plant`]: the platform (motors, encoders, passive legs, body), pure and seeded.
//! - [`firmware`]: one emulated wheel-module firmware per CAN node (sans-IO).
//! - [`faults`]: the fault schedule (TOML or command-line options).
//! - [`sim`]: the [`Simulator`] (plant + firmwares + faults) as a sans-IO core, plus the
//!   real-time loop [`sim::run_realtime`] used by the `rollbase-sim` binary.
#![deny(missing_docs)]

pub mod canopen;
pub mod error;
pub mod faults;
pub mod firmware;
pub mod lockstep;
pub mod plant;
pub mod sim;

pub use error::SimError;
pub use faults::{FaultArgs, FaultSchedule};
pub use firmware::{FirmwareConfig, FirmwareStats, ModuleFirmware};
pub use plant::{InitialState, MotorSetpoint, Plant, PlantConfig, PlantTruth, SensorReading};
pub use sim::{
    run_realtime, run_realtime_buses, spawn_realtime, spawn_realtime_at_priority,
    spawn_realtime_buses, ClockMap, RealtimeSummary, SimConfig, SimHandle, SimStats, Simulator,
};
