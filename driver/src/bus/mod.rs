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

/// A change of the controller's CAN error state, as the interface reports it in an error
/// frame (Linux `include/uapi/linux/can/error.h`: the error class `CAN_ERR_CRTL` with
/// `data[1]` = `CAN_ERR_CRTL_{RX,TX}_{WARNING,PASSIVE}` or `CAN_ERR_CRTL_ACTIVE`,
/// `CAN_ERR_BUSOFF`, `CAN_ERR_RESTARTED`). The error counters of ISO 11898-1 decide the
/// state: warning at 96, error-passive at 128, bus-off above 255 transmit errors.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum BusEvent {
    /// An error counter reached the warning level (96): the bus is noisy, frames still flow.
    Warning,
    /// An error counter reached the error-passive level (128): the controller no longer
    /// signals errors it sees; the bus is close to failing.
    ErrorPassive,
    /// The controller is back to error active (counters below 128 again).
    Active,
    /// The controller went bus-off (transmit error counter above 255): it neither sends nor
    /// receives until it is restarted.
    BusOff,
    /// The controller was restarted after a bus-off (the kernel's `restart-ms`, or
    /// `ip link set … type can restart`).
    Restarted,
    /// A controller problem whose level the report does not say (a socketcand
    /// `< error 004 … >` carries only the error class, not `data[1]`).
    Controller,
}

impl BusEvent {
    /// Every kind, in the order of [`BusEvent::index`].
    pub const ALL: [BusEvent; 6] = [
        BusEvent::Warning,
        BusEvent::ErrorPassive,
        BusEvent::Active,
        BusEvent::BusOff,
        BusEvent::Restarted,
        BusEvent::Controller,
    ];

    /// Position in [`BusEvent::ALL`] (for per-kind counters).
    pub fn index(self) -> usize {
        match self {
            BusEvent::Warning => 0,
            BusEvent::ErrorPassive => 1,
            BusEvent::Active => 2,
            BusEvent::BusOff => 3,
            BusEvent::Restarted => 4,
            BusEvent::Controller => 5,
        }
    }

    /// Short name for logs and diagnostics.
    pub fn name(self) -> &'static str {
        match self {
            BusEvent::Warning => "error warning",
            BusEvent::ErrorPassive => "error passive",
            BusEvent::Active => "error active",
            BusEvent::BusOff => "bus-off",
            BusEvent::Restarted => "restarted",
            BusEvent::Controller => "controller problem",
        }
    }

    /// Decodes a CAN error frame: `class` is its identifier without the error flag (the
    /// error class bits), `data` its payload (may be empty when only the class is known).
    /// `None` for error frames that are not a controller state change (lost arbitration,
    /// protocol violations, missing ACK, transceiver errors, TX timeout).
    ///
    /// Bit values from Linux `include/uapi/linux/can/error.h`: `CAN_ERR_CRTL` 0x004,
    /// `CAN_ERR_BUSOFF` 0x040, `CAN_ERR_RESTARTED` 0x100; `data[1]` of a controller
    /// problem: `RX_WARNING` 0x04, `TX_WARNING` 0x08, `RX_PASSIVE` 0x10, `TX_PASSIVE` 0x20,
    /// `ACTIVE` 0x40. Bus-off wins over the others in one frame (it is the worst state).
    pub fn from_error_frame(class: u32, data: &[u8]) -> Option<BusEvent> {
        const ERR_CRTL: u32 = 0x004;
        const ERR_BUSOFF: u32 = 0x040;
        const ERR_RESTARTED: u32 = 0x100;
        const CRTL_WARNING: u8 = 0x04 | 0x08;
        const CRTL_PASSIVE: u8 = 0x10 | 0x20;
        const CRTL_ACTIVE: u8 = 0x40;
        if class & ERR_BUSOFF != 0 {
            return Some(BusEvent::BusOff);
        }
        if class & ERR_RESTARTED != 0 {
            return Some(BusEvent::Restarted);
        }
        if class & ERR_CRTL != 0 {
            return Some(match data.get(1).copied() {
                Some(d) if d & CRTL_PASSIVE != 0 => BusEvent::ErrorPassive,
                Some(d) if d & CRTL_WARNING != 0 => BusEvent::Warning,
                Some(d) if d & CRTL_ACTIVE != 0 => BusEvent::Active,
                Some(_) => return None,
                None => BusEvent::Controller,
            });
        }
        None
    }
}

impl std::fmt::Display for BusEvent {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name())
    }
}

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
    #[error("{iface}: CAN controller is bus-off; check wiring, termination (120 ohm at both ends), the bit rate of every node and for a node that babbles; let the kernel restart the interface (`sudo ip link set {iface} type can restart-ms 100`), then re-arm")]
    BusOff {
        /// Interface name.
        iface: String,
    },
    /// The controller's error state changed without stopping the bus (warning, error
    /// passive, back to active, restarted): a typed event, not lost data.
    #[error("{iface}: CAN controller {event} (error frame)")]
    Controller {
        /// Interface name.
        iface: String,
        /// The state change.
        event: BusEvent,
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
            | BusError::Controller { .. }
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

impl BusError {
    /// The controller state change this error reports, if it is one (bus-off, warning,
    /// error passive, active again, restarted): the runtime counts and logs these, and
    /// faults on bus-off.
    pub fn bus_event(&self) -> Option<BusEvent> {
        match self {
            BusError::BusOff { .. } => Some(BusEvent::BusOff),
            BusError::Controller { event, .. } => Some(*event),
            _ => None,
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
    /// Opens the connection to the interface again (after a bus-off: a fresh socket has no
    /// stale queued frames and error state). Backends without a connection of their own do
    /// nothing.
    fn reopen(&mut self) -> Result<(), BusError> {
        Ok(())
    }
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
    fn reopen(&mut self) -> Result<(), BusError> {
        (**self).reopen()
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
