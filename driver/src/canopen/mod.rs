//! The CANopen profile: CiA 301 communication with CiA 402 drives and CiA 406 encoders.
//!
//! The native profile ([`crate::protocol`]) is one frame per wheel module per direction with
//! end-to-end protection. Off-the-shelf brushless drives (Maxon, Elmo, Copley, Nanotec …)
//! speak CANopen instead: every wheel is two CiA 402 drives (rolling and steering) and the
//! leg is a CiA 406 absolute linear encoder. This module is everything the master needs to
//! drive them, layered like the native profile, pure first:
//!
//! - [`cob`]: COB-IDs of the predefined connection set and their classification;
//! - [`nmt`]: NMT commands, boot-up and heartbeat, SYNC;
//! - [`sdo`]: expedited SDO requests and responses, abort codes as a typed enum;
//! - [`sdo_client`]: one SDO transfer, expedited or segmented (`rollbase sdo`);
//! - [`emcy`]: emergency frames and their error-code classes;
//! - [`pdo`]: PDO communication and mapping parameters, packing mapped objects into frames,
//!   the profile's fixed mappings;
//! - [`ds402`]: the CiA 402 state machine (statusword decode, controlword commands, the
//!   device's transitions and the master's next controlword);
//! - [`od`]: object indices both sides use;
//! - [`units`]: drive increments, rpm, gear ratio and encoder steps to SI and back;
//! - [`eds`]: EDS/DCF device description files (CiA 306) and the check of the boot plan
//!   against them;
//! - [`config`]: the profile's section of the platform file and the SDO configuration plan
//!   written to every device at boot;
//! - [`master`]: the sans-IO master (boot, configuration, cyclic exchange, supervision);
//! - [`busload`]: the profile's bus load, derived from the mappings and the timing;
//! - [`describe`]: one-line descriptions of CANopen frames for the monitor;
//! - [`doc`]: `docs/cia402.md`, generated from these tables.
//!
//! Everything here is pure (values in, values out, time passed in) and never panics on a
//! frame from the bus: malformed frames are typed [`CanOpenError`]s.
//!
//! Facts used throughout (CiA 301 v4.2, CiA 402 / IEC 61800-7-201, CiA 406 v3.1): COB-IDs of
//! the predefined connection set, the SDO command specifiers, the NMT command specifiers and
//! states, the statusword/controlword bit assignments and the 402 state transitions, the
//! device-type encoding of 0x1000 (low word = profile number, 402 or 406).

pub mod busload;
pub mod cob;
pub mod config;
pub mod describe;
pub mod doc;
pub mod ds402;
pub mod eds;
pub mod emcy;
pub mod master;
pub mod nmt;
pub mod od;
pub mod pdo;
pub mod sdo;
pub mod sdo_client;
pub mod units;

/// Largest CANopen node-ID (1..=127; 0 addresses all nodes in NMT commands only).
pub const MAX_NODE_ID: u8 = 127;

/// Why a CANopen frame or value was rejected.
#[derive(Debug, Clone, Copy, PartialEq, Eq, thiserror::Error)]
pub enum CanOpenError {
    /// The frame has the wrong number of data bytes for its object.
    #[error("{what} (id 0x{id:03X}) has {got} data bytes, expected {expected}")]
    WrongLength {
        /// The object the frame was parsed as ("SDO response", "heartbeat", …).
        what: &'static str,
        /// CAN id.
        id: u16,
        /// Data bytes received.
        got: usize,
        /// What the object needs (a minimum where noted by `what`).
        expected: usize,
    },
    /// The id does not belong to the object the frame was parsed as.
    #[error("id 0x{id:03X} is not a {what} COB-ID")]
    WrongId {
        /// The object expected.
        what: &'static str,
        /// CAN id.
        id: u16,
    },
    /// A command specifier or state byte has no meaning.
    #[error("{what}: byte 0x{value:02X} is not a valid {what} value")]
    BadValue {
        /// What the byte should have been ("NMT command", "SDO server command" …).
        what: &'static str,
        /// The byte.
        value: u8,
    },
    /// A node-ID is outside 1..=127.
    #[error("node-ID {0} is outside 1..=127")]
    BadNode(u8),
}
