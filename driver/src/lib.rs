//! rollbase-driver: the wheel-module CAN protocol and everything that moves its frames.
//!
//! Layers, from pure to IO:
//! - [`frame`]: the checked classic CAN 2.0A frame newtype ([`CanFrame`]).
//! - [`protocol`]: THE message table, as data ([`protocol::MESSAGES`]). The codec, the DBC
//!   export, `docs/protocol.md` and the bus-load calculator are all derived from it.
//! - [`crc`]: CRC-8 SAE J1850 used by the end-to-end protection.
//! - [`codec`]: pure, stateless `encode`/`decode` between SI values and frames.
//! - [`rx`]: the stateful receive path (rolling counters, statistics).
//! - [`rng`], [`fault`]: a small deterministic PRNG and a pure fault injector (drop, delay,
//!   duplicate, corrupt) reused by the simulator.
//! - [`bus`]: the bus traits ([`bus::CanBus`], [`bus::AsyncCanBus`]) and backends
//!   (SocketCAN, in-process virtual bus).
//! - [`candump`]: `candump -L` log reader/writer.
//! - [`input`]: bounded reading of input files (size and line-length caps), for every crate.
//! - [`dbc`], [`busload`]: artefacts generated from the table.
//! - [`canopen`]: the second protocol profile, CANopen (CiA 301) with the CiA 402 drive and
//!   CiA 406 encoder profiles: frames, SDO, PDO mapping, the 402 state machine, units, the
//!   boot configuration and the sans-IO master.
#![deny(missing_docs)]

pub mod bus;
pub mod busload;
pub mod candump;
pub mod canopen;
pub mod codec;
pub mod crc;
pub mod dbc;
pub mod fault;
pub mod frame;
pub mod input;
pub mod protocol;
pub mod rng;
pub mod rx;

pub use bus::{AsyncCanBus, BusError, CanBus};
pub use busload::{bus_load, BusLoadConfig, BusLoadReport};
pub use codec::{decode, encode, DecodeError, EncodeError, Message, Payload};
pub use dbc::{dbc, dbc_for_nodes, protocol_markdown};
pub use frame::{CanFrame, FrameError, TimestampedFrame};
pub use rx::{Receiver, RxError, RxStats};

/// Any error of this crate, for callers that just propagate (`?`) and report. Each variant
/// wraps the specific error type, whose message names the bad field or value.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum Error {
    /// Building a frame failed.
    #[error(transparent)]
    Frame(#[from] FrameError),
    /// Encoding a message failed.
    #[error(transparent)]
    Encode(#[from] EncodeError),
    /// Decoding a frame failed.
    #[error(transparent)]
    Decode(#[from] DecodeError),
    /// The receive path rejected a frame.
    #[error(transparent)]
    Rx(#[from] RxError),
    /// A bus operation failed.
    #[error(transparent)]
    Bus(#[from] BusError),
    /// A candump log line is invalid.
    #[error(transparent)]
    Candump(#[from] candump::CandumpError),
    /// A bus-load configuration is invalid.
    #[error(transparent)]
    BusLoad(#[from] busload::BusLoadError),
    /// A fault model is invalid.
    #[error(transparent)]
    FaultModel(#[from] fault::FaultModelError),
}

impl Error {
    /// True when retrying the failed operation may succeed (see [`BusError::is_retryable`]);
    /// false for every non-bus error.
    pub fn is_retryable(&self) -> bool {
        matches!(self, Error::Bus(e) if e.is_retryable())
    }
}
