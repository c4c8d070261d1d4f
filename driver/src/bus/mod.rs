//! The bus: one small synchronous trait for the 250 Hz cycle ([`CanBus`]), one async face
//! for tools ([`AsyncCanBus`]), and the backends: SocketCAN ([`socketcan`]), socketcand over
//! TCP ([`socketcand`]) and the in-process virtual bus ([`virtual_bus`]).
//!
//! Errors say whether retrying makes sense ([`BusError::is_retryable`]), in the spirit of
//! socketcan-rs' `ShouldRetry`.

use std::future::Future;
use std::time::Instant;

use crate::frame::{CanFrame, TimestampedFrame};

pub mod socketcan;
pub mod socketcand;
pub mod virtual_bus;

pub use virtual_bus::{BusClock, BusStats, VirtualBus, VirtualBusConfig, VirtualNode};

/// Why a bus operation failed.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum BusError {
    /// The transmit queue is momentarily full (EAGAIN / ENOBUFS); retry later.
    #[error("{iface}: transmit queue full, frame not sent (retry in the next cycle; if it persists the bus is overloaded or no other node acknowledges frames)")]
    WouldBlock {
        /// Interface name.
        iface: String,
    },
    /// A bounded software queue is full; retry later.
    #[error("{iface}: queue full ({capacity} frames); retry later or drain the receiver faster")]
    QueueFull {
        /// Interface name.
        iface: String,
        /// Queue capacity.
        capacity: usize,
    },
    /// The interface does not exist.
    #[error("interface {iface} does not exist: {hint}")]
    NoSuchInterface {
        /// Interface name.
        iface: String,
        /// What to run to create it.
        hint: String,
    },
    /// The interface exists but is down (ENETDOWN).
    #[error("interface {iface} is down: bring it up with `sudo ip link set up {iface}` (real CAN: `sudo ip link set {iface} type can bitrate 1000000 && sudo ip link set up {iface}`)")]
    InterfaceDown {
        /// Interface name.
        iface: String,
    },
    /// The kernel has no SocketCAN support (EAFNOSUPPORT, errno 97).
    #[error("cannot open {iface}: this kernel has no CAN support (AF_CAN sockets fail with EAFNOSUPPORT); load the modules (`sudo modprobe can can-raw vcan`), use a kernel with CONFIG_CAN, or use `--bus virtual`")]
    AfCanUnsupported {
        /// Interface name.
        iface: String,
    },
    /// The CAN controller went bus-off (too many transmit errors).
    #[error("{iface}: CAN controller is bus-off; check wiring, termination and bit rate, then restart the interface (`sudo ip link set {iface} type can restart-ms 100`)")]
    BusOff {
        /// Interface name.
        iface: String,
    },
    /// The controller reported a problem that does not stop the bus (error frame:
    /// warning/passive level, lost arbitration, protocol violation, missing ACK, ...).
    #[error("{iface}: CAN error frame: {detail}")]
    ErrorFrame {
        /// Interface name.
        iface: String,
        /// Decoded error class.
        detail: String,
    },
    /// The interface name is not usable.
    #[error("invalid bus name {name:?}: {reason}")]
    InvalidName {
        /// The name.
        name: String,
        /// Why.
        reason: String,
    },
    /// The bus or socket was closed.
    #[error("{iface}: bus closed")]
    Closed {
        /// Interface name.
        iface: String,
    },
    /// Any other operating-system error.
    #[error("{iface}: {op} failed: {message} (errno {errno:?})")]
    Io {
        /// Interface name.
        iface: String,
        /// Operation that failed.
        op: &'static str,
        /// OS error number, when there is one.
        errno: Option<i32>,
        /// OS error text.
        message: String,
    },
}

impl BusError {
    /// True when the same operation may succeed if simply tried again later (full queues,
    /// transient controller errors, interrupted system calls); false when something must be
    /// fixed first (missing or down interface, bus-off, closed bus, no kernel support).
    pub fn is_retryable(&self) -> bool {
        match self {
            BusError::WouldBlock { .. }
            | BusError::QueueFull { .. }
            | BusError::ErrorFrame { .. } => true,
            BusError::Io { errno, .. } => matches!(
                *errno,
                Some(libc::EINTR) | Some(libc::EAGAIN) | Some(libc::ENOBUFS)
            ),
            BusError::NoSuchInterface { .. }
            | BusError::InterfaceDown { .. }
            | BusError::AfCanUnsupported { .. }
            | BusError::BusOff { .. }
            | BusError::InvalidName { .. }
            | BusError::Closed { .. } => false,
        }
    }
}

/// The synchronous bus used by the 250 Hz cycle thread and by lockstep runs.
///
/// `send` and `try_recv` never block; `recv_until` blocks at most until `deadline`
/// (backends document how they treat it; the virtual bus in virtual-clock mode never blocks).
pub trait CanBus: Send {
    /// Queues `frame` for transmission without blocking.
    fn send(&mut self, frame: &CanFrame) -> Result<(), BusError>;
    /// The next received frame, or `None` when none is available now.
    fn try_recv(&mut self) -> Result<Option<TimestampedFrame>, BusError>;
    /// The next received frame, waiting until `deadline` at most (`None` on timeout).
    fn recv_until(&mut self, deadline: Instant) -> Result<Option<TimestampedFrame>, BusError>;
    /// Interface or node name.
    fn name(&self) -> &str;
}

impl<B: CanBus + ?Sized> CanBus for Box<B> {
    fn send(&mut self, frame: &CanFrame) -> Result<(), BusError> {
        (**self).send(frame)
    }
    fn try_recv(&mut self) -> Result<Option<TimestampedFrame>, BusError> {
        (**self).try_recv()
    }
    fn recv_until(&mut self, deadline: Instant) -> Result<Option<TimestampedFrame>, BusError> {
        (**self).recv_until(deadline)
    }
    fn name(&self) -> &str {
        (**self).name()
    }
}

/// The async (tokio) face of a bus, for tools (monitors, the simulator binary, the CLI).
///
/// Uses native `async fn`-style methods in traits; the returned futures are `Send`. A type
/// that implements both this and [`CanBus`] has two `send` methods: call them as
/// `AsyncCanBus::send(&mut bus, &frame).await` / `CanBus::send(&mut bus, &frame)` when both
/// traits are in scope.
pub trait AsyncCanBus {
    /// Sends a frame (waits while the transmit queue is full, where the backend can).
    fn send(&mut self, frame: &CanFrame) -> impl Future<Output = Result<(), BusError>> + Send;
    /// Waits for the next frame.
    fn recv(&mut self) -> impl Future<Output = Result<TimestampedFrame, BusError>> + Send;
}

/// Opens a SocketCAN interface by name ("vcan0", "can0", ...), or a socketcand server's bus
/// by URL (`socketcand://HOST:PORT/CHANNEL`, see [`socketcand`]).
///
/// Errors say what to run: a missing interface names the `ip link add` commands, a kernel
/// without CAN support (errno 97) says so and suggests `--bus virtual`. The name "virtual" is
/// rejected with an explanation: the virtual bus exists only inside one process and is
/// created with [`VirtualBus::new`].
pub fn open(name: &str) -> Result<Box<dyn CanBus>, BusError> {
    if name == "virtual" {
        return Err(BusError::InvalidName {
            name: name.to_string(),
            reason: "the virtual bus exists only inside one process: create it with \
                     VirtualBus::new and attach nodes with VirtualBus::node (the `rollbase demo` \
                     command runs the simulator in-process this way)"
                .to_string(),
        });
    }
    if name.starts_with(socketcand::SCHEME) {
        return Ok(Box::new(socketcand::SocketcandBus::open(name)?));
    }
    Ok(Box::new(socketcan::SocketCanBus::open(name)?))
}
