//! rollbase-control: the math and the loop.
//!
//! Pure cores (models, trajectories, controllers, odometry, avoidance, supervisor) take
//! time and measurements as arguments and return values; the runtime and the recorder are
//! thin adapters around them.
#![deny(missing_docs)]

pub mod angle;
pub mod avoidance;
pub mod dfl;
pub mod ideal_plant;
pub mod kinematic;
pub mod link;
pub mod model;
pub mod odometry;
pub mod platform;
pub mod plot;
pub mod record;
pub mod runtime;
pub mod scenario;
pub mod supervisor;
pub mod trajectory;
pub mod types;
pub mod wmr;

pub use platform::{ConfigError, Platform, Protocol};
pub use types::*;
