//! The base service's boundary: the command and state port values ([`ports`]) and the
//! checks every incoming command passes before it reaches the shaper ([`command`]).

pub mod command;
pub mod ports;
