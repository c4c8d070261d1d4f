//! SocketCAN backend (Linux kernel CAN: `vcan0`, `can0`, any CAN interface).
//!
//! [`SocketCanBus`] is a raw `CAN_RAW` socket in non-blocking mode: `send` and `try_recv`
//! never block, `recv_until` waits with `ppoll` (nanosecond timeout, so a deadline inside a
//! 4 ms cycle is honoured without millisecond rounding). Receive timestamps come from the
//! kernel (`SO_TIMESTAMPNS`, the time the frame entered the socket layer) and fall back to
//! `CLOCK_REALTIME` at the moment of reading; both are durations since the Unix epoch.
//!
//! By default the socket receives every standard-format (11-bit) data frame; extended-id and
//! remote frames are filtered out in the kernel (rollbase uses neither), CAN FD frames are
//! not enabled. Error frames for bus-off, controller problems, TX timeouts and restarts are
//! enabled and decoded ([`BusEvent::from_error_frame`]): bus-off is [`BusError::BusOff`]
//! (not retryable), a controller state change (warning, error passive, active again,
//! restarted) the retryable [`BusError::Controller`] with its [`BusEvent`], anything else the
//! retryable [`BusError::ErrorFrame`]. After a bus-off, [`CanBus::reopen`] opens a fresh
//! socket (the interface itself is restarted by the kernel's `restart-ms`, which needs
//! CAP_NET_ADMIN to set and is not done by the process). [`SocketCanBus::set_filters`] narrows reception, e.g. to
//! [`protocol_filters`].
//!
//! [`AsyncSocketCanBus`] is the tokio face (socketcan's `tokio::CanSocket`).

use std::io;
use std::os::fd::AsRawFd;
use std::time::{Duration, Instant, SystemTime, UNIX_EPOCH};

use libc::{CAN_ERR_BUSOFF, CAN_ERR_CRTL, CAN_ERR_RESTARTED, CAN_ERR_TX_TIMEOUT};

use socketcan::{CanFilter, EmbeddedFrame, Id, Socket, SocketOptions, StandardId};

use super::{AsyncCanBus, BusError, BusEvent, CanBus};
use crate::frame::{CanFrame, TimestampedFrame};
use crate::protocol::{MessageKind, MESSAGES};

/// Longest Linux interface name (IFNAMSIZ − 1).
const MAX_IFNAME: usize = 15;

/// Error classes delivered as error frames.
const ERROR_MASK: u32 = CAN_ERR_BUSOFF | CAN_ERR_CRTL | CAN_ERR_TX_TIMEOUT | CAN_ERR_RESTARTED;

fn check_name(iface: &str) -> Result<(), BusError> {
    let reason = if iface.is_empty() {
        Some("the interface name is empty")
    } else if iface.len() > MAX_IFNAME {
        Some("Linux interface names are at most 15 bytes")
    } else if iface
        .chars()
        .any(|c| c == '/' || c.is_whitespace() || c == '\0')
    {
        Some("interface names cannot contain '/', whitespace or NUL")
    } else {
        None
    };
    match reason {
        Some(r) => Err(BusError::InvalidName {
            name: iface.to_string(),
            reason: r.to_string(),
        }),
        None => Ok(()),
    }
}

/// True unless creating an `AF_CAN` socket fails with `EAFNOSUPPORT` (kernel without CAN).
pub fn af_can_supported() -> bool {
    // SAFETY: plain socket(2)/close(2) calls with constant arguments; the fd is closed
    // immediately and never escapes.
    unsafe {
        let fd = libc::socket(
            libc::AF_CAN,
            libc::SOCK_RAW | libc::SOCK_CLOEXEC,
            libc::CAN_RAW,
        );
        if fd >= 0 {
            libc::close(fd);
            true
        } else {
            io::Error::last_os_error().raw_os_error() != Some(libc::EAFNOSUPPORT)
        }
    }
}

fn missing_hint(iface: &str) -> String {
    if iface.starts_with("vcan") {
        format!(
            "create it with `sudo modprobe vcan && sudo ip link add dev {iface} type vcan && sudo ip link set up {iface}`"
        )
    } else {
        format!(
            "check that the CAN adapter is connected and its driver loaded (`ip link show`), then \
             `sudo ip link set {iface} type can bitrate 1000000 && sudo ip link set up {iface}`; \
             for a virtual interface use a vcanN name"
        )
    }
}

fn map_io(iface: &str, op: &'static str, e: &io::Error) -> BusError {
    let errno = e.raw_os_error();
    match errno {
        Some(libc::EAGAIN) | Some(libc::ENOBUFS) => BusError::WouldBlock {
            iface: iface.to_string(),
        },
        Some(libc::ENETDOWN) => BusError::InterfaceDown {
            iface: iface.to_string(),
        },
        Some(libc::ENODEV) | Some(libc::ENXIO) => {
            if af_can_supported() {
                BusError::NoSuchInterface {
                    iface: iface.to_string(),
                    hint: missing_hint(iface),
                }
            } else {
                BusError::AfCanUnsupported {
                    iface: iface.to_string(),
                }
            }
        }
        Some(libc::EAFNOSUPPORT) | Some(libc::EPROTONOSUPPORT) => BusError::AfCanUnsupported {
            iface: iface.to_string(),
        },
        _ => BusError::Io {
            iface: iface.to_string(),
            op,
            errno,
            message: e.to_string(),
        },
    }
}

fn would_block(e: &io::Error) -> bool {
    e.kind() == io::ErrorKind::WouldBlock
}

/// Acceptance filters `(id, mask)` that pass exactly the rollbase protocol ids: SYNC and
/// each per-node block `base..=base+15` (mask 0x7F0).
pub fn protocol_filters() -> Vec<(u16, u16)> {
    MESSAGES
        .iter()
        .map(|m| {
            if m.per_node {
                (m.base_id, 0x7F0)
            } else {
                (m.base_id, 0x7FF)
            }
        })
        .collect()
}

/// Kernel filter for `(id, mask)` on standard data frames only.
fn kernel_filter(id: u16, mask: u16) -> CanFilter {
    CanFilter::new(
        u32::from(id & 0x7FF),
        u32::from(mask & 0x7FF) | libc::CAN_EFF_FLAG | libc::CAN_RTR_FLAG,
    )
}

fn to_socketcan(iface: &str, frame: &CanFrame) -> Result<socketcan::CanFrame, BusError> {
    let invalid = || BusError::Io {
        iface: iface.to_string(),
        op: "build frame",
        errno: None,
        message: format!(
            "id 0x{:X} / {} bytes not representable",
            frame.id(),
            frame.len()
        ),
    };
    let id = StandardId::new(frame.id()).ok_or_else(invalid)?;
    socketcan::CanFrame::new(id, frame.data()).ok_or_else(invalid)
}

/// Converts a received socketcan frame: `Ok(None)` for frames rollbase ignores (extended
/// ids, remote frames), errors for error frames.
fn from_socketcan(
    iface: &str,
    frame: socketcan::CanFrame,
    at: Duration,
) -> Result<Option<TimestampedFrame>, BusError> {
    match frame {
        socketcan::CanFrame::Data(d) => match d.id() {
            Id::Standard(sid) => {
                Ok(CanFrame::new(sid.as_raw(), d.data())
                    .ok()
                    .map(|frame| TimestampedFrame {
                        timestamp: at,
                        frame,
                    }))
            }
            Id::Extended(_) => Ok(None),
        },
        socketcan::CanFrame::Remote(_) => Ok(None),
        socketcan::CanFrame::Error(e) => {
            match BusEvent::from_error_frame(e.error_bits(), e.data()) {
                Some(BusEvent::BusOff) => Err(BusError::BusOff {
                    iface: iface.to_string(),
                }),
                Some(event) => Err(BusError::Controller {
                    iface: iface.to_string(),
                    event,
                }),
                None => Err(BusError::ErrorFrame {
                    iface: iface.to_string(),
                    detail: e.into_error().to_string(),
                }),
            }
        }
    }
}

fn since_epoch(t: Option<SystemTime>) -> Duration {
    t.unwrap_or_else(SystemTime::now)
        .duration_since(UNIX_EPOCH)
        .unwrap_or_default()
}

/// Blocking-free SocketCAN bus.
#[derive(Debug)]
pub struct SocketCanBus {
    sock: socketcan::CanSocket,
    iface: String,
}

impl SocketCanBus {
    /// Opens `iface`, sets non-blocking mode, kernel timestamps, the standard-data-frame
    /// filter and the error-frame mask.
    pub fn open(iface: &str) -> Result<SocketCanBus, BusError> {
        check_name(iface)?;
        let sock = socketcan::CanSocket::open(iface).map_err(|e| map_io(iface, "open", &e))?;
        let setup = |r: io::Result<()>, op| r.map_err(|e| map_io(iface, op, &e));
        setup(sock.set_nonblocking(true), "set non-blocking")?;
        // Timestamps are a nicety: fall back to the read time if the option is refused.
        let _ = sock.set_recv_timestamp(true);
        setup(sock.set_filters(&[kernel_filter(0, 0)]), "set filters")?;
        setup(sock.set_error_filter(ERROR_MASK), "set error filter")?;
        Ok(SocketCanBus {
            sock,
            iface: iface.to_string(),
        })
    }

    /// Replaces the acceptance filters: a standard data frame is received when
    /// `frame.id & mask == id & mask` for any `(id, mask)`. An empty slice receives no data
    /// frames (error frames still arrive).
    pub fn set_filters(&mut self, filters: &[(u16, u16)]) -> Result<(), BusError> {
        let f: Vec<CanFilter> = filters.iter().map(|&(i, m)| kernel_filter(i, m)).collect();
        let r = if f.is_empty() {
            self.sock.set_filter_drop_all()
        } else {
            self.sock.set_filters(&f)
        };
        r.map_err(|e| map_io(&self.iface, "set filters", &e))
    }

    /// Receives frames of the sending socket too (`CAN_RAW_RECV_OWN_MSGS`), e.g. to confirm
    /// transmission.
    pub fn set_receive_own(&mut self, enable: bool) -> Result<(), BusError> {
        self.sock
            .set_recv_own_msgs(enable)
            .map_err(|e| map_io(&self.iface, "set recv own msgs", &e))
    }

    fn wait_readable(&self, timeout: Duration) -> Result<(), BusError> {
        let mut pfd = libc::pollfd {
            fd: self.sock.as_raw_fd(),
            events: libc::POLLIN,
            revents: 0,
        };
        let ts = libc::timespec {
            tv_sec: libc::time_t::try_from(timeout.as_secs()).unwrap_or(libc::time_t::MAX),
            tv_nsec: libc::c_long::from(timeout.subsec_nanos() as i32),
        };
        // SAFETY: pfd and ts are valid for the duration of the call; nfds = 1.
        let r = unsafe { libc::ppoll(&mut pfd, 1, &ts, std::ptr::null()) };
        if r < 0 {
            let e = io::Error::last_os_error();
            if e.raw_os_error() != Some(libc::EINTR) {
                return Err(map_io(&self.iface, "ppoll", &e));
            }
        }
        Ok(())
    }
}

impl CanBus for SocketCanBus {
    fn send(&mut self, frame: &CanFrame) -> Result<(), BusError> {
        let f = to_socketcan(&self.iface, frame)?;
        self.sock
            .write_frame(&f)
            .map_err(|e| map_io(&self.iface, "send", &e))
    }

    fn try_recv(&mut self) -> Result<Option<TimestampedFrame>, BusError> {
        loop {
            match self.sock.read_frame_with_timestamps() {
                Ok((f, ts)) => {
                    if let Some(tf) = from_socketcan(&self.iface, f, since_epoch(ts.socket))? {
                        return Ok(Some(tf));
                    }
                }
                Err(e) if would_block(&e) => return Ok(None),
                Err(e) if e.kind() == io::ErrorKind::Interrupted => {}
                Err(e) => return Err(map_io(&self.iface, "receive", &e)),
            }
        }
    }

    fn recv_until(&mut self, deadline: Instant) -> Result<Option<TimestampedFrame>, BusError> {
        loop {
            if let Some(f) = self.try_recv()? {
                return Ok(Some(f));
            }
            let now = Instant::now();
            if now >= deadline {
                return Ok(None);
            }
            self.wait_readable(deadline - now)?;
        }
    }

    fn name(&self) -> &str {
        &self.iface
    }

    fn reopen(&mut self) -> Result<(), BusError> {
        let fresh = SocketCanBus::open(&self.iface)?;
        self.sock = fresh.sock;
        Ok(())
    }
}

/// SocketCAN bus for tokio tasks. Must be opened inside a tokio runtime with IO enabled.
#[derive(Debug)]
pub struct AsyncSocketCanBus {
    sock: socketcan::tokio::CanSocket,
    iface: String,
}

impl AsyncSocketCanBus {
    /// Opens `iface` (same setup as [`SocketCanBus::open`]).
    pub fn open(iface: &str) -> Result<AsyncSocketCanBus, BusError> {
        check_name(iface)?;
        let sock =
            socketcan::tokio::CanSocket::open(iface).map_err(|e| map_io(iface, "open", &e))?;
        let _ = sock.set_recv_timestamp(true);
        sock.set_filters(&[kernel_filter(0, 0)])
            .map_err(|e| map_io(iface, "set filters", &e))?;
        sock.set_error_filter(ERROR_MASK)
            .map_err(|e| map_io(iface, "set error filter", &e))?;
        Ok(AsyncSocketCanBus {
            sock,
            iface: iface.to_string(),
        })
    }

    /// Interface name.
    pub fn name(&self) -> &str {
        &self.iface
    }
}

impl AsyncCanBus for AsyncSocketCanBus {
    async fn send(&mut self, frame: &CanFrame) -> Result<(), BusError> {
        let f = to_socketcan(&self.iface, frame)?;
        self.sock
            .write_frame(f)
            .await
            .map_err(|e| map_io(&self.iface, "send", &e))
    }

    async fn recv(&mut self) -> Result<TimestampedFrame, BusError> {
        loop {
            let (f, t) = self
                .sock
                .read_frame_with_timestamp()
                .await
                .map_err(|e| map_io(&self.iface, "receive", &e))?;
            if let Some(tf) = from_socketcan(&self.iface, f, since_epoch(Some(t)))? {
                return Ok(tf);
            }
        }
    }
}

/// The message kinds a filter list passes (for diagnostics).
pub fn filtered_kinds(filters: &[(u16, u16)]) -> Vec<MessageKind> {
    MESSAGES
        .iter()
        .filter(|m| {
            filters
                .iter()
                .any(|&(id, mask)| m.base_id & mask == id & mask)
        })
        .map(|m| m.kind)
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    fn errno(n: i32) -> io::Error {
        io::Error::from_raw_os_error(n)
    }

    #[test]
    fn errno_mapping_and_retryability() {
        let e = map_io("can0", "send", &errno(libc::ENOBUFS));
        assert!(matches!(e, BusError::WouldBlock { .. }) && e.is_retryable());
        let e = map_io("can0", "send", &errno(libc::EAGAIN));
        assert!(matches!(e, BusError::WouldBlock { .. }) && e.is_retryable());
        let e = map_io("can0", "send", &errno(libc::ENETDOWN));
        assert!(matches!(e, BusError::InterfaceDown { .. }) && !e.is_retryable());
        assert!(e.to_string().contains("sudo ip link set up can0"), "{e}");
        let e = map_io("vcan0", "open", &errno(libc::EAFNOSUPPORT));
        assert!(matches!(e, BusError::AfCanUnsupported { .. }) && !e.is_retryable());
        assert!(e.to_string().contains("--bus virtual"), "{e}");
        let e = map_io("can0", "receive", &errno(libc::EIO));
        assert!(
            matches!(
                e,
                BusError::Io {
                    errno: Some(libc::EIO),
                    ..
                }
            ) && !e.is_retryable()
        );
        let e = map_io("can0", "receive", &errno(libc::EINTR));
        assert!(e.is_retryable());
    }

    #[test]
    fn missing_interface_hints() {
        assert_eq!(
            missing_hint("vcan0"),
            "create it with `sudo modprobe vcan && sudo ip link add dev vcan0 type vcan && sudo ip link set up vcan0`"
        );
        assert!(missing_hint("can1").contains("bitrate 1000000"));
    }

    #[test]
    fn protocol_filters_pass_exactly_the_protocol_ids() {
        let f = protocol_filters();
        let pass = |id: u16| f.iter().any(|&(i, m)| id & m == i & m);
        for id in 0..=0x7FFu16 {
            let known = crate::protocol::classify(id).is_some();
            // Per-node base ids (node 0) pass the block filter and are rejected by decode.
            let base = crate::protocol::MESSAGES
                .iter()
                .any(|m| m.per_node && m.base_id == id);
            assert_eq!(pass(id), known || base, "id 0x{id:03X}");
        }
        assert_eq!(filtered_kinds(&f).len(), 5);
    }

    #[test]
    fn socketcan_frame_conversion_round_trip() {
        let f = CanFrame::new(0x2A5, &[1, 2, 3]).expect("frame");
        let s = to_socketcan("x", &f).expect("convert");
        let back = from_socketcan("x", s, Duration::from_secs(1))
            .expect("data frame")
            .expect("kept");
        assert_eq!(back.frame, f);
        assert_eq!(back.timestamp, Duration::from_secs(1));
    }

    #[test]
    fn error_frames_map_to_bus_off_and_retryable_errors() {
        let busoff = socketcan::CanErrorFrame::new_error(CAN_ERR_BUSOFF, &[0; 8]).expect("frame");
        let e = from_socketcan("can0", busoff.into(), Duration::ZERO).expect_err("bus-off");
        assert!(matches!(e, BusError::BusOff { .. }) && !e.is_retryable());
        assert_eq!(e.bus_event(), Some(BusEvent::BusOff));
        let ctrl = |d1: u8| {
            let f = socketcan::CanErrorFrame::new_error(CAN_ERR_CRTL, &[0, d1, 0, 0, 0, 0, 0, 0])
                .expect("frame");
            from_socketcan("can0", f.into(), Duration::ZERO).expect_err("controller")
        };
        for (d1, want) in [
            (0x04, BusEvent::Warning),
            (0x08, BusEvent::Warning),
            (0x10, BusEvent::ErrorPassive),
            (0x20, BusEvent::ErrorPassive),
            (0x40, BusEvent::Active),
        ] {
            let e = ctrl(d1);
            assert!(
                matches!(e, BusError::Controller { event, .. } if event == want)
                    && e.is_retryable(),
                "data[1] = {d1:#04x}: {e:?}"
            );
            assert_eq!(e.bus_event(), Some(want));
        }
        // An RX overflow is a controller problem, not a state change.
        let e = ctrl(0x01);
        assert!(matches!(e, BusError::ErrorFrame { .. }) && e.bus_event().is_none());
        let restarted =
            socketcan::CanErrorFrame::new_error(CAN_ERR_RESTARTED, &[0; 8]).expect("frame");
        let e = from_socketcan("can0", restarted.into(), Duration::ZERO).expect_err("restart");
        assert_eq!(e.bus_event(), Some(BusEvent::Restarted));
    }
}
