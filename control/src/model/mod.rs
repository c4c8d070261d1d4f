//! The platform and its kinematics: the platform file ([`platform`]), seed 000's kinematic
//! model with seed 003's off-centred wheels ([`kinematics`]), the general WMR models
//! ([`wmr`]) and the ideal kinematic plant used by the pure experiments ([`ideal_plant`]).
//! Everything else in the crate builds on these.

pub mod ideal_plant;
pub mod kinematics;
pub mod platform;
pub mod wmr;
