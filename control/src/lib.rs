//! rollbase-control: the math and the loop.
//!
//! Pure cores (models, trajectories, controllers, odometry, avoidance, supervisor) take
//! time and measurements as arguments and return values; the runtime drivers (lockstep, real
//! time) are thin adapters around them. No file formats, middleware or plotting here: those
//! live in the application layer (the `rollbase` package), so a user can depend on this crate
//! alone without pulling IO.
#![deny(missing_docs)]

pub mod angle;
pub mod estimation;
pub mod model;
pub mod num;
pub mod reference;
pub mod runtime;
pub mod service;
pub mod supervisor;
pub mod tracking;
pub mod types;

pub use model::platform::{ConfigError, Platform, Protocol};
pub use types::*;
