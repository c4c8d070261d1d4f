//! rollbase's application layer: the adapters from the control stack's ports to the world.
//!
//! `rollbase-control` is a pure library (models, shaping, controllers, the sans-IO cycle core
//! and its drivers); everything that touches a file format or a middleware lives here, so a
//! user can depend on `rollbase-control` alone without pulling IO:
//!
//! - [`commands`]: motion commands as JSON Lines (command files, stdin);
//! - [`record`]: recordings of runs as ROS 2 bags (MCAP, CDR), and their recovery;
//! - [`plot`]: PNG plots of a recording;
//! - [`ros2`]: rollbase as a ROS 2 node over DDS (no ROS installation needed), and the ROS 2
//!   message types the recordings share.
#![deny(missing_docs)]

pub mod commands;
pub mod plot;
pub mod record;
pub mod ros2;
