//! What the controller follows: pre-planned trajectories ([`trajectory`]), their time
//! scaling ([`timescale`]), seed 001's singularity avoidance ([`avoidance`]), the
//! live-command shaper ([`shaper`]) with its rest-to-rest ramp ([`ramp`]) and its rolling
//! turns ([`roll`]), and the actuator
//! limits both the references and the output guard are held to ([`limits`]); the values a
//! reference reports beside its samples (clock, avoidance record) are in [`status`].

pub mod avoidance;
pub mod limits;
pub mod ramp;
pub mod roll;
pub mod shaper;
pub mod status;
pub mod timescale;
pub mod trajectory;
