//! The tracking controllers: seed 000's dynamic feedback linearisation ([`dfl`]) and the
//! kinematic controller used near rest and as its fallback ([`kinematic`]).

pub mod dfl;
pub mod kinematic;
