//! The tracking controllers: seed 000's dynamic feedback linearisation ([`dfl`]) and the
//! kinematic controller used near rest and as its fallback ([`kinematic`]); seed 001's
//! closed-loop experiment on the ideal plant ([`avoidance_experiment`]).

pub mod avoidance_experiment;
pub mod dfl;
pub mod kinematic;
