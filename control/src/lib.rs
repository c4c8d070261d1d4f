//! rollbase-control: the math and the loop.
//!
//! Pure cores (models, trajectories, controllers, odometry, avoidance, supervisor) take
//! time and measurements as arguments and return values; the runtime drivers (lockstep, real
//! time) are thin adapters around them. No file formats, middleware or plotting here: those
//! live in the application layer (the `rollbase` package), so a user can depend on this crate
//! alone without pulling IO.
#![deny(missing_docs)]

pub mod angle;
pub mod avoidance;
pub mod command;
pub mod dfl;
pub mod ideal_plant;
pub mod kinematic;
pub mod limits;
pub mod link;
pub mod model;
pub mod num;
pub mod odometry;
pub mod platform;
pub mod ports;
pub mod ramp;
pub mod record;
pub mod runtime;
pub mod scenario;
pub mod shaper;
pub mod supervisor;
pub mod timescale;
pub mod trajectory;
pub mod types;
pub mod wmr;

pub use platform::{ConfigError, Platform, Protocol};
pub use types::*;
