//! socketcand backend: a CAN bus reached over TCP with the socketcand ASCII protocol in raw
//! mode, so rollbase runs on machines without kernel CAN (the controller, the simulator and
//! Python tools as separate processes sharing one bus served by `rollbase bridge` or by a
//! real socketcand daemon on a SocketCAN host).
//!
//! # The protocol (raw mode), as the tools speak it
//!
//! Every protocol element is ASCII text between `<` and `>`, with single spaces between
//! tokens; elements are not separated by newlines. The exchange of a client is:
//!
//! ```text
//! server: < hi >
//! client: < open vcan0 >           server: < ok >      (or < error … > and close)
//! client: < rawmode >              server: < ok >
//! server: < frame 181 1700000000.123456 0011223344556677 >   (every frame on the bus)
//! client: < send 201 6 00 11 22 33 44 55 >                    (one frame onto the bus)
//! ```
//!
//! - `frame`: id in upper-case hex, 3 digits for an 11-bit id (8 for 29-bit), the receive
//!   time `SECONDS.MICROSECONDS` (6 digits) since the Unix epoch, then the data bytes as
//!   contiguous upper-case hex pairs. This is what socketcand's raw mode writes
//!   (`state_raw.c`: `"< frame %03X %ld.%06ld "`, then `"%02X"` per byte, then `" >"`; a frame
//!   without data therefore has two spaces before `>`). socketcand's protocol document shows
//!   the bytes space-separated; python-can parses the bytes with `bytearray.fromhex`, which
//!   accepts both, and so does [`parse_element`].
//! - `send`: id in hex (3 digits = 11-bit, 8 digits = 29-bit), the DLC, then one token per
//!   byte, each one or two hex digits. socketcand reads it with
//!   `sscanf("< %*s %x %hhu %hhx …")`; python-can writes the DLC with `{:X}` and the bytes with
//!   `{:x}` (no zero padding: `< send 201 6 0 11 22 33 44 55 >`). rollbase writes two
//!   upper-case digits per byte, which both accept.
//! - python-can reads `< hi >` and each `< ok >` with a single `recv()` and compares the text
//!   exactly, so a server must send them as separate writes with nothing appended (the
//!   rollbase bridge waits a little after the raw-mode `< ok >` before the first frame).
//!
//! # The client
//!
//! [`SocketcandBus`] implements [`CanBus`]: it connects (2 s timeout), does the handshake
//! above (each reply awaited at most 2 s), sends `< echo >` (its reply is skipped; it tells
//! the rollbase bridge that the handshake reply was read), then puts the socket in non-blocking mode with
//! `TCP_NODELAY`. `send` never blocks: the element goes into an output buffer that is written
//! as far as the socket takes it and flushed again on every later call (a buffer above
//! [`MAX_PENDING_OUTPUT`] bytes refuses new frames with [`BusError::QueueFull`]). Received
//! frames carry the server's timestamp (a duration since the Unix epoch, like SocketCAN's
//! kernel timestamps). Extended-id, RTR and CAN FD frames are skipped (rollbase uses none);
//! a server `< error CLASS TIME >` element (a CAN error frame: socketcand sends its error
//! class, not its data) is decoded by [`error_element_event`] into [`BusError::BusOff`] or
//! the retryable [`BusError::Controller`] (restarted; a controller problem of unknown level),
//! any other error element and a malformed element are the retryable
//! [`BusError::ErrorFrame`]; the server closing the connection is
//! [`BusError::Closed`].
//!
//! Bus names: `socketcand://HOST:PORT/CHANNEL` ([`SocketcandUrl`]), e.g.
//! `socketcand://127.0.0.1:29536/vcan0`; the port defaults to [`DEFAULT_PORT`] (29536,
//! socketcand's default) and an IPv6 host is written in brackets (`socketcand://[::1]:29536/vcan0`).

use std::fmt::Write as _;
use std::io::{self, Read, Write};
use std::net::{SocketAddr, TcpStream, ToSocketAddrs};
use std::os::fd::AsRawFd;
use std::time::{Duration, Instant};

use super::{BusError, BusEvent, CanBus};
use crate::frame::{CanFrame, TimestampedFrame, MAX_DATA_LEN, MAX_STANDARD_ID};

/// The URL scheme that selects this backend in [`super::open`].
pub const SCHEME: &str = "socketcand://";
/// socketcand's default TCP port.
pub const DEFAULT_PORT: u16 = 29536;
/// Longest protocol element accepted (a 29-bit `frame` with 8 bytes is 51 characters; error
/// texts are longer). Longer input without `>` is discarded as garbage.
pub const MAX_ELEMENT_LEN: usize = 256;
/// Output bytes the client buffers while the socket does not take them (about 1400 frames).
pub const MAX_PENDING_OUTPUT: usize = 64 * 1024;
/// Longest channel (interface) name socketcand accepts.
pub const MAX_CHANNEL_LEN: usize = 16;
/// How long connecting and each handshake reply may take.
pub const HANDSHAKE_TIMEOUT: Duration = Duration::from_secs(2);

/// A parsed `socketcand://HOST:PORT/CHANNEL` bus name.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct SocketcandUrl {
    /// Host name or address (IPv6 without brackets).
    pub host: String,
    /// TCP port.
    pub port: u16,
    /// The bus (interface) name to open on the server, e.g. `vcan0`.
    pub channel: String,
}

impl SocketcandUrl {
    /// Parses `socketcand://HOST[:PORT]/CHANNEL`; errors name the part that is wrong.
    pub fn parse(name: &str) -> Result<SocketcandUrl, BusError> {
        let bad = |reason: String| BusError::InvalidName {
            name: name.to_string(),
            reason,
        };
        let rest = name.strip_prefix(SCHEME).ok_or_else(|| {
            bad(format!(
                "a socketcand bus name starts with `{SCHEME}`, e.g. socketcand://127.0.0.1:{DEFAULT_PORT}/vcan0"
            ))
        })?;
        let (hostport, channel) = rest.split_once('/').ok_or_else(|| {
            bad("missing `/CHANNEL` after the host, e.g. socketcand://127.0.0.1:29536/vcan0".into())
        })?;
        check_channel(channel).map_err(|r| bad(format!("channel {channel:?}: {r}")))?;
        let (host, port) = if let Some(v6) = hostport.strip_prefix('[') {
            let (h, after) = v6
                .split_once(']')
                .ok_or_else(|| bad("IPv6 host without closing `]`".into()))?;
            let port = match after.strip_prefix(':') {
                Some(p) => Some(p),
                None if after.is_empty() => None,
                None => return Err(bad(format!("unexpected {after:?} after `]`"))),
            };
            (h.to_string(), port)
        } else {
            match hostport.rsplit_once(':') {
                Some((h, p)) => (h.to_string(), Some(p)),
                None => (hostport.to_string(), None),
            }
        };
        if host.is_empty() {
            return Err(bad("the host is empty".into()));
        }
        let port = match port {
            None => DEFAULT_PORT,
            Some(p) => p
                .parse::<u16>()
                .ok()
                .filter(|&p| p != 0)
                .ok_or_else(|| bad(format!("port {p:?} is not a number in 1..=65535")))?,
        };
        Ok(SocketcandUrl {
            host,
            port,
            channel: channel.to_string(),
        })
    }

    /// `HOST:PORT` for `ToSocketAddrs` (IPv6 hosts in brackets).
    pub fn host_port(&self) -> String {
        if self.host.contains(':') {
            format!("[{}]:{}", self.host, self.port)
        } else {
            format!("{}:{}", self.host, self.port)
        }
    }
}

impl std::fmt::Display for SocketcandUrl {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "{SCHEME}{}/{}", self.host_port(), self.channel)
    }
}

/// Checks a channel name as socketcand does (at most 16 characters, no whitespace or `<>`).
pub fn check_channel(channel: &str) -> Result<(), &'static str> {
    if channel.is_empty() {
        Err("the channel name is empty")
    } else if channel.len() > MAX_CHANNEL_LEN {
        Err("socketcand channel names are at most 16 characters")
    } else if channel
        .chars()
        .any(|c| c.is_whitespace() || c == '<' || c == '>' || c == '/' || c.is_control())
    {
        Err("channel names cannot contain whitespace, '/', '<', '>' or control characters")
    } else {
        Ok(())
    }
}

/// Why a protocol element could not be used.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum ProtocolError {
    /// Text between elements that is not whitespace, or an element that is not `< … >`.
    #[error("socketcand: unexpected text {text:?} outside `< … >` elements")]
    Garbage {
        /// The text (at most 40 characters).
        text: String,
    },
    /// An element longer than [`MAX_ELEMENT_LEN`] without a closing `>`.
    #[error("socketcand: element longer than {max} bytes without a closing `>`; discarded")]
    Overlong {
        /// The limit.
        max: usize,
    },
    /// The element is not ASCII/UTF-8 text.
    #[error("socketcand: element is not text")]
    NotText,
    /// A known command with wrong arguments.
    #[error("socketcand: bad `{command}` element {element:?}: {reason}")]
    BadArguments {
        /// The command word.
        command: &'static str,
        /// The element (at most 80 characters).
        element: String,
        /// What is wrong.
        reason: String,
    },
}

/// At most `n` characters of `s` for a message, printable ASCII only (anything else is shown
/// as `?`): a `{:?}` of the result is at most 2n + 2 bytes, so an error reply to hostile
/// input stays short (the `socketcand_server` fuzz target found 869-byte replies to a
/// 256-byte element of control characters, each escaped as `\u{12}`).
fn clip(s: &str, n: usize) -> String {
    s.chars()
        .take(n)
        .map(|c| {
            if c.is_ascii_graphic() || c == ' ' {
                c
            } else {
                '?'
            }
        })
        .collect()
}

/// A token of a bad element, as shown in the error.
fn tok_shown(s: &str) -> String {
    clip(s, 24)
}

/// One protocol element, in either direction.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Element {
    /// `< hi >`: the server's greeting.
    Hi,
    /// `< ok >`.
    Ok,
    /// `< open CHANNEL >`.
    Open(String),
    /// `< rawmode >`.
    RawMode,
    /// `< bcmmode >`.
    BcmMode,
    /// `< echo >` (answered with the same element).
    Echo,
    /// `< frame ID SEC.USEC DATA >` with an 11-bit id: a frame received on the bus.
    Frame(TimestampedFrame),
    /// `< send ID DLC B… >` with an 11-bit id: a frame to put on the bus.
    Send(CanFrame),
    /// A frame rollbase does not represent (29-bit id, RTR, CAN FD): `frame`, `send`,
    /// `rtr`, `fdframe`, `fdsend`, `sendrtr` with the command word.
    Unsupported(String),
    /// `< error TEXT >`: an error reply, or a CAN error frame in raw mode.
    Error(String),
    /// Any other command (word and arguments as sent).
    Other(String),
}

fn parse_hex_u32(s: &str) -> Option<u32> {
    if s.is_empty() || s.len() > 8 || !s.bytes().all(|b| b.is_ascii_hexdigit()) {
        return None;
    }
    u32::from_str_radix(s, 16).ok()
}

/// Parses `SECONDS[.FRACTION]` (1..=9 fraction digits) into a duration.
fn parse_timestamp(s: &str) -> Option<Duration> {
    let (sec, frac) = match s.split_once('.') {
        Some((a, b)) => (a, b),
        None => (s, ""),
    };
    if sec.is_empty() || !sec.bytes().all(|b| b.is_ascii_digit()) {
        return None;
    }
    let secs: u64 = sec.parse().ok()?;
    if frac.len() > 9 || !frac.bytes().all(|b| b.is_ascii_digit()) {
        return None;
    }
    let mut nanos = 0u32;
    for (i, b) in frac.bytes().enumerate() {
        nanos += u32::from(b - b'0') * 10u32.pow(8 - i as u32);
    }
    Some(Duration::new(secs, nanos))
}

/// Parses one element `< … >` (as returned by [`Framer::next_element`]). Pure; allocates
/// only for the rare text-carrying elements (open, error, other).
pub fn parse_element(element: &str) -> Result<Element, ProtocolError> {
    let inner = element
        .strip_prefix('<')
        .and_then(|s| s.strip_suffix('>'))
        .ok_or_else(|| ProtocolError::Garbage {
            text: clip(element, 40),
        })?;
    let mut tokens = inner.split_ascii_whitespace();
    let Some(word) = tokens.next() else {
        return Ok(Element::Other(String::new()));
    };
    let bad = |command: &'static str, reason: String| ProtocolError::BadArguments {
        command,
        element: clip(element, 80),
        reason,
    };
    match word {
        "hi" => Ok(Element::Hi),
        "ok" => Ok(Element::Ok),
        "rawmode" => Ok(Element::RawMode),
        "bcmmode" => Ok(Element::BcmMode),
        "echo" => Ok(Element::Echo),
        "error" => Ok(Element::Error(
            inner.trim().trim_start_matches("error").trim().to_string(),
        )),
        "open" => {
            let ch = tokens
                .next()
                .ok_or_else(|| bad("open", "missing channel name".into()))?;
            if tokens.next().is_some() {
                return Err(bad("open", "more than one channel name".into()));
            }
            check_channel(ch).map_err(|r| bad("open", r.into()))?;
            Ok(Element::Open(ch.to_string()))
        }
        "frame" => {
            let id_s = tokens
                .next()
                .ok_or_else(|| bad("frame", "missing id".into()))?;
            let id = parse_hex_u32(id_s)
                .ok_or_else(|| bad("frame", format!("id {:?} is not hex", tok_shown(id_s))))?;
            let ts_s = tokens
                .next()
                .ok_or_else(|| bad("frame", "missing timestamp".into()))?;
            let timestamp = parse_timestamp(ts_s).ok_or_else(|| {
                bad(
                    "frame",
                    format!(
                        "timestamp {:?} is not SECONDS.MICROSECONDS",
                        tok_shown(ts_s)
                    ),
                )
            })?;
            let mut data = [0u8; MAX_DATA_LEN];
            let mut n = 0usize;
            for tok in tokens {
                if tok.len() % 2 != 0 || !tok.bytes().all(|b| b.is_ascii_hexdigit()) {
                    return Err(bad(
                        "frame",
                        format!("data {:?} is not hex byte pairs", tok_shown(tok)),
                    ));
                }
                for pair in tok.as_bytes().chunks(2) {
                    if n == MAX_DATA_LEN {
                        return Err(bad("frame", "more than 8 data bytes".into()));
                    }
                    // Two ASCII hex digits checked above.
                    let s = std::str::from_utf8(pair).unwrap_or("00");
                    data[n] = u8::from_str_radix(s, 16).unwrap_or(0);
                    n += 1;
                }
            }
            if id_s.len() != 3 {
                return Ok(Element::Unsupported("frame".into()));
            }
            let id = u16::try_from(id)
                .ok()
                .filter(|&i| i <= MAX_STANDARD_ID)
                .ok_or_else(|| bad("frame", format!("11-bit id {id_s} is above 7FF")))?;
            let frame = CanFrame::new(id, &data[..n]).map_err(|e| bad("frame", e.to_string()))?;
            Ok(Element::Frame(TimestampedFrame { timestamp, frame }))
        }
        "send" => {
            let id_s = tokens
                .next()
                .ok_or_else(|| bad("send", "missing id".into()))?;
            let id = parse_hex_u32(id_s)
                .ok_or_else(|| bad("send", format!("id {:?} is not hex", tok_shown(id_s))))?;
            let dlc_s = tokens
                .next()
                .ok_or_else(|| bad("send", "missing DLC".into()))?;
            let dlc: usize = dlc_s
                .parse()
                .ok()
                .filter(|&d| d <= MAX_DATA_LEN)
                .ok_or_else(|| bad("send", format!("DLC {:?} is not 0..8", tok_shown(dlc_s))))?;
            let mut data = [0u8; MAX_DATA_LEN];
            let mut n = 0usize;
            for tok in tokens {
                if n == dlc {
                    return Err(bad("send", format!("more data bytes than DLC {dlc}")));
                }
                if tok.is_empty() || tok.len() > 2 || !tok.bytes().all(|b| b.is_ascii_hexdigit()) {
                    return Err(bad(
                        "send",
                        format!("data byte {:?} is not 1 or 2 hex digits", tok_shown(tok)),
                    ));
                }
                data[n] = u8::from_str_radix(tok, 16).unwrap_or(0);
                n += 1;
            }
            if n != dlc {
                return Err(bad("send", format!("DLC {dlc} but {n} data bytes")));
            }
            if id_s.len() == 8 {
                return Ok(Element::Unsupported("send".into()));
            }
            let id = u16::try_from(id)
                .ok()
                .filter(|&i| i <= MAX_STANDARD_ID)
                .ok_or_else(|| {
                    bad(
                        "send",
                        format!("id {id_s} is above 7FF (29-bit ids are written with 8 digits)"),
                    )
                })?;
            let frame = CanFrame::new(id, &data[..n]).map_err(|e| bad("send", e.to_string()))?;
            Ok(Element::Send(frame))
        }
        "rtr" | "fdframe" | "fdsend" | "sendrtr" => Ok(Element::Unsupported(word.to_string())),
        _ => Ok(Element::Other(inner.trim().to_string())),
    }
}

/// Appends `< frame ID SEC.USEC DATA >` exactly as socketcand's raw mode writes it.
pub fn format_frame_into(out: &mut String, tf: &TimestampedFrame) {
    let _ = write!(
        out,
        "< frame {:03X} {}.{:06} ",
        tf.frame.id(),
        tf.timestamp.as_secs(),
        tf.timestamp.subsec_micros()
    );
    for b in tf.frame.data() {
        let _ = write!(out, "{b:02X}");
    }
    out.push_str(" >");
}

/// Appends `< send ID DLC B… >` (3-digit id, decimal DLC, two hex digits per byte).
pub fn format_send_into(out: &mut String, frame: &CanFrame) {
    let _ = write!(out, "< send {:03X} {}", frame.id(), frame.len());
    for b in frame.data() {
        let _ = write!(out, " {b:02X}");
    }
    out.push_str(" >");
}

/// Splits a TCP byte stream into `< … >` elements. Keeps at most one partial element;
/// whitespace between elements is skipped, other text is reported once per run as
/// [`ProtocolError::Garbage`].
#[derive(Debug, Default)]
pub struct Framer {
    buf: Vec<u8>,
    pos: usize,
}

impl Framer {
    /// An empty framer.
    pub fn new() -> Framer {
        Framer {
            buf: Vec::with_capacity(8192),
            pos: 0,
        }
    }

    /// Appends received bytes (drops the already consumed prefix first; no allocation once
    /// the buffer has grown to the largest read plus one partial element).
    pub fn extend(&mut self, bytes: &[u8]) {
        if self.pos > 0 {
            self.buf.drain(..self.pos);
            self.pos = 0;
        }
        self.buf.extend_from_slice(bytes);
    }

    /// True when no unconsumed bytes are buffered.
    pub fn is_empty(&self) -> bool {
        self.pos >= self.buf.len()
    }

    /// Unconsumed bytes buffered.
    pub fn buffered(&self) -> usize {
        self.buf.len().saturating_sub(self.pos)
    }

    /// The next complete element (`<` … `>` inclusive), `None` when more bytes are needed.
    pub fn next_element(&mut self) -> Option<Result<&str, ProtocolError>> {
        let rest = &self.buf[self.pos..];
        let Some(lt) = rest.iter().position(|&b| b == b'<') else {
            // Nothing but (possibly) garbage: consume it.
            let garbage = !rest.iter().all(|b| b.is_ascii_whitespace());
            let text = clip(String::from_utf8_lossy(rest).trim(), 40);
            self.pos = self.buf.len();
            return garbage.then_some(Err(ProtocolError::Garbage { text }));
        };
        if !rest[..lt].iter().all(|b| b.is_ascii_whitespace()) {
            let text = clip(String::from_utf8_lossy(&rest[..lt]).trim(), 40);
            self.pos += lt;
            return Some(Err(ProtocolError::Garbage { text }));
        }
        let start = self.pos + lt;
        let body = &self.buf[start + 1..];
        match body.iter().position(|&b| b == b'<' || b == b'>') {
            Some(i) if body[i] == b'<' => {
                // An element that never closed: report it, resume at the next '<'.
                let text = clip(
                    &String::from_utf8_lossy(&self.buf[start..start + 1 + i]),
                    40,
                );
                self.pos = start + 1 + i;
                Some(Err(ProtocolError::Garbage { text }))
            }
            Some(i) => {
                let end = start + 1 + i + 1;
                self.pos = end;
                Some(std::str::from_utf8(&self.buf[start..end]).map_err(|_| ProtocolError::NotText))
            }
            None => {
                if self.buf.len() - start > MAX_ELEMENT_LEN {
                    self.pos = self.buf.len();
                    Some(Err(ProtocolError::Overlong {
                        max: MAX_ELEMENT_LEN,
                    }))
                } else {
                    self.pos = start;
                    None
                }
            }
        }
    }
}

/// Why a server element carried no frame for the client ([`ClientDecoder::next_frame`]).
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum ClientDecodeError {
    /// `< error TEXT >` from the server (a CAN error frame in raw mode, or a reply).
    #[error("socketcand error element: {0}")]
    ErrorElement(String),
    /// A malformed element or text outside elements.
    #[error("{0}")]
    Malformed(ProtocolError),
}

/// The controller state change a raw-mode `< error CLASS SECONDS.MICROS >` element reports:
/// socketcand (linux-can/socketcand `state_raw.c`) sends a CAN error frame as its error class
/// (the identifier without the error flag, hex) and its timestamp, without the data bytes, so
/// a controller problem's level (warning or passive) is not known
/// ([`BusEvent::Controller`]); bus-off and restarted are. `None` for other text (an error
/// reply, other error classes).
pub fn error_element_event(text: &str) -> Option<BusEvent> {
    let mut it = text.split_whitespace();
    let class = it.next()?;
    let stamp = it.next()?;
    if it.next().is_some()
        || class.is_empty()
        || class.len() > 8
        || !class.bytes().all(|b| b.is_ascii_hexdigit())
        || !stamp.bytes().all(|b| b.is_ascii_digit() || b == b'.')
    {
        return None;
    }
    let class = u32::from_str_radix(class, 16).ok()?;
    BusEvent::from_error_frame(class, &[])
}

/// The client side of the protocol without I/O: bytes from the server in, frames out. This is
/// exactly what [`SocketcandBus`] runs on every received byte (and what the
/// `socketcand_client` fuzz target feeds with arbitrary bytes).
#[derive(Debug, Default)]
pub struct ClientDecoder {
    framer: Framer,
    stats: SocketcandStats,
}

impl ClientDecoder {
    /// An empty decoder.
    pub fn new() -> ClientDecoder {
        ClientDecoder {
            framer: Framer::new(),
            stats: SocketcandStats::default(),
        }
    }

    /// Appends bytes received from the server.
    pub fn extend(&mut self, bytes: &[u8]) {
        self.framer.extend(bytes);
    }

    /// The next frame among the buffered elements; `Ok(None)` when more bytes are needed.
    /// Frames rollbase does not represent (29-bit, RTR, FD) and replies without a frame are
    /// skipped (the former counted); an error element or a malformed element is returned as
    /// an error (counted), and decoding goes on after it with the next call.
    pub fn next_frame(&mut self) -> Result<Option<TimestampedFrame>, ClientDecodeError> {
        while let Some(r) = self.framer.next_element() {
            match r.and_then(parse_element) {
                Ok(Element::Frame(tf)) => {
                    self.stats.frames_in += 1;
                    return Ok(Some(tf));
                }
                Ok(Element::Unsupported(_)) => self.stats.skipped += 1,
                Ok(Element::Error(msg)) => {
                    self.stats.error_elements += 1;
                    return Err(ClientDecodeError::ErrorElement(msg));
                }
                // Replies to our own commands (none are sent after the handshake) and
                // server chatter carry no frames.
                Ok(_) => {}
                Err(e) => {
                    self.stats.malformed += 1;
                    return Err(ClientDecodeError::Malformed(e));
                }
            }
        }
        Ok(None)
    }

    /// Counters so far (`frames_out` is always 0: the decoder sends nothing).
    pub fn stats(&self) -> SocketcandStats {
        self.stats
    }

    /// Bytes buffered and not yet consumed (at most one partial element after
    /// [`ClientDecoder::next_frame`] returned `Ok(None)`).
    pub fn buffered(&self) -> usize {
        self.framer.buffered()
    }
}

/// `< error TEXT >` with the protocol's delimiters in TEXT replaced by `'`, so the reply is
/// always exactly one element.
pub fn error_element(text: &str) -> String {
    let clean: String = text
        .chars()
        .map(|c| if c == '<' || c == '>' { '\'' } else { c })
        .collect();
    format!("< error {clean} >")
}

/// Where a client of a server stands in the handshake.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum ServerMode {
    /// Connected, no channel opened yet.
    #[default]
    NoBus,
    /// A channel is open (socketcand's BCM mode: `send` works, nothing is forwarded).
    Bcm,
    /// Raw mode: every frame on the channel is forwarded to the client.
    Raw,
}

/// What the server does about one element, besides the reply.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum ServerAction {
    /// Nothing.
    None,
    /// Open this channel (the reply is `< ok >` unless the server refuses it).
    Open(String),
    /// The client switched to raw mode: forward frames to it (after the settle time).
    EnterRaw,
    /// Put this frame on the channel.
    Send(CanFrame),
}

/// The outcome of [`ServerSession::handle`].
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct ServerStep {
    /// The element to send back, if any (always exactly one `< … >` element).
    pub reply: Option<String>,
    /// What to do.
    pub action: ServerAction,
    /// This element shows the client has read the raw-mode `< ok >` (any element after it
    /// other than a repeated `< rawmode >`): a server that holds frames back for
    /// python-can's exact `< ok >` comparison may forward them now, and must subscribe the
    /// client before acting on the element (its reply may come at once).
    pub read_raw_ok: bool,
}

/// The server side of the protocol (raw mode; `send` also in BCM mode) without I/O: one
/// parsed client element in, the reply and the action out. `rollbase bridge` runs every
/// element a client sends through it, and the `socketcand_server` fuzz target feeds it
/// arbitrary bytes.
#[derive(Debug, Default)]
pub struct ServerSession {
    mode: ServerMode,
    raw_ok_unread: bool,
}

impl ServerSession {
    /// A client that has just been greeted with `< hi >`.
    pub fn new() -> ServerSession {
        ServerSession::default()
    }

    /// The client's mode.
    pub fn mode(&self) -> ServerMode {
        self.mode
    }

    /// Handles one element from the client (or the framing/parsing error it gave).
    pub fn handle(&mut self, parsed: Result<Element, ProtocolError>) -> ServerStep {
        let read_raw_ok = self.mode == ServerMode::Raw
            && self.raw_ok_unread
            && !matches!(parsed, Ok(Element::RawMode));
        if read_raw_ok {
            self.raw_ok_unread = false;
        }
        let ok = || Some("< ok >".to_string());
        let (reply, action) = match (parsed, self.mode) {
            (Ok(Element::Echo), _) => (Some("< echo >".to_string()), ServerAction::None),
            (Ok(Element::Open(ch)), ServerMode::NoBus) => {
                self.mode = ServerMode::Bcm;
                (ok(), ServerAction::Open(ch))
            }
            (Ok(Element::Open(_)), _) => (
                Some(error_element("a channel is already open on this connection")),
                ServerAction::None,
            ),
            (Ok(Element::RawMode), ServerMode::Bcm) => {
                self.mode = ServerMode::Raw;
                self.raw_ok_unread = true;
                (ok(), ServerAction::EnterRaw)
            }
            (Ok(Element::RawMode), ServerMode::Raw) => (ok(), ServerAction::None),
            (Ok(Element::BcmMode), ServerMode::Bcm) => (ok(), ServerAction::None),
            (Ok(Element::BcmMode), ServerMode::Raw) => (
                Some(error_element(
                    "bcm mode is not supported by rollbase bridge; use rawmode",
                )),
                ServerAction::None,
            ),
            (Ok(Element::Send(frame)), ServerMode::Bcm | ServerMode::Raw) => {
                (None, ServerAction::Send(frame))
            }
            (Ok(Element::Unsupported(w)), _) => (
                Some(error_element(&format!(
                    "{w}: 29-bit, RTR and CAN FD frames are not carried by rollbase bridge"
                ))),
                ServerAction::None,
            ),
            (Ok(Element::Hi | Element::Ok | Element::Frame(_) | Element::Error(_)), _) => (
                Some(error_element("unexpected server element from a client")),
                ServerAction::None,
            ),
            (Ok(Element::Other(cmd)), _) if cmd.is_empty() => {
                (Some(error_element("empty command")), ServerAction::None)
            }
            (Ok(Element::Other(cmd)), _) => (
                Some(error_element(&format!(
                    "unknown or unsupported command {:?} (rollbase bridge speaks raw mode: open, rawmode, send, echo)",
                    clip(cmd.split_whitespace().next().unwrap_or(""), 40)
                ))),
                ServerAction::None,
            ),
            (Ok(_), ServerMode::NoBus) => (
                Some(error_element("open a channel first: < open vcan0 >")),
                ServerAction::None,
            ),
            (Err(e), _) => (Some(error_element(&e.to_string())), ServerAction::None),
        };
        ServerStep {
            reply,
            action,
            read_raw_ok,
        }
    }
}

/// Counters of a [`SocketcandBus`].
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct SocketcandStats {
    /// Frames received and returned.
    pub frames_in: u64,
    /// Frames queued for sending.
    pub frames_out: u64,
    /// Frames skipped because rollbase does not represent them (29-bit, RTR, FD).
    pub skipped: u64,
    /// Malformed elements and text outside elements.
    pub malformed: u64,
    /// `< error … >` elements from the server.
    pub error_elements: u64,
}

/// A socketcand raw-mode client: one TCP connection, one bus.
#[derive(Debug)]
pub struct SocketcandBus {
    stream: TcpStream,
    url: SocketcandUrl,
    label: String,
    decoder: ClientDecoder,
    out: Vec<u8>,
    out_pos: usize,
    text: String,
    frames_out: u64,
}

fn io_err(label: &str, op: &'static str, e: &io::Error, hint: &str) -> BusError {
    match e.kind() {
        io::ErrorKind::BrokenPipe
        | io::ErrorKind::ConnectionReset
        | io::ErrorKind::ConnectionAborted
        | io::ErrorKind::UnexpectedEof => BusError::Closed {
            iface: label.to_string(),
        },
        _ => BusError::Io {
            iface: label.to_string(),
            op,
            errno: e.raw_os_error(),
            message: format!("{e}{hint}"),
        },
    }
}

impl SocketcandBus {
    /// Connects to `socketcand://HOST:PORT/CHANNEL`, opens the channel and switches to raw
    /// mode. Errors say what failed: name, connection (is a server running?), handshake.
    pub fn open(name: &str) -> Result<SocketcandBus, BusError> {
        let url = SocketcandUrl::parse(name)?;
        let label = url.to_string();
        let hint = format!(
            "; is a socketcand server running there? start one with `rollbase bridge --listen {}`",
            url.host_port()
        );
        let addrs: Vec<SocketAddr> = url
            .host_port()
            .to_socket_addrs()
            .map_err(|e| io_err(&label, "resolve host", &e, ""))?
            .collect();
        let mut last = None;
        let mut stream = None;
        for a in &addrs {
            match TcpStream::connect_timeout(a, HANDSHAKE_TIMEOUT) {
                Ok(s) => {
                    stream = Some(s);
                    break;
                }
                Err(e) => last = Some(e),
            }
        }
        let stream = match (stream, last) {
            (Some(s), _) => s,
            (None, Some(e)) => return Err(io_err(&label, "connect", &e, &hint)),
            (None, None) => {
                return Err(BusError::InvalidName {
                    name: name.to_string(),
                    reason: format!("host {:?} resolves to no address", url.host),
                })
            }
        };
        let setup = |r: io::Result<()>, op| r.map_err(|e| io_err(&label, op, &e, ""));
        setup(stream.set_nodelay(true), "set TCP_NODELAY")?;
        setup(
            stream.set_read_timeout(Some(HANDSHAKE_TIMEOUT)),
            "set read timeout",
        )?;
        let mut bus = SocketcandBus {
            stream,
            label,
            decoder: ClientDecoder::new(),
            out: Vec::with_capacity(MAX_PENDING_OUTPUT),
            out_pos: 0,
            text: String::with_capacity(64),
            frames_out: 0,
            url,
        };
        bus.expect(Element::Hi, "the greeting `< hi >`")?;
        let open = format!("< open {} >", bus.url.channel);
        bus.write_handshake(&open)?;
        bus.expect(Element::Ok, "`< ok >` after `< open … >`")?;
        bus.write_handshake("< rawmode >")?;
        bus.expect(Element::Ok, "`< ok >` after `< rawmode >`")?;
        // Tells a server that delays frames until the client has read the `< ok >` (the
        // rollbase bridge does, for python-can's sake) that we have; the `< echo >` reply is
        // skipped like any non-frame element.
        bus.write_handshake("< echo >")?;
        let label = bus.label.clone();
        let setup = |r: io::Result<()>, op| r.map_err(|e| io_err(&label, op, &e, ""));
        setup(bus.stream.set_read_timeout(None), "clear read timeout")?;
        setup(bus.stream.set_nonblocking(true), "set non-blocking")?;
        Ok(bus)
    }

    /// The bus URL this client is connected to.
    pub fn url(&self) -> &SocketcandUrl {
        &self.url
    }

    /// Counters since the connection was opened.
    pub fn stats(&self) -> SocketcandStats {
        SocketcandStats {
            frames_out: self.frames_out,
            ..self.decoder.stats()
        }
    }

    fn write_handshake(&mut self, s: &str) -> Result<(), BusError> {
        self.stream
            .write_all(s.as_bytes())
            .map_err(|e| io_err(&self.label, "handshake write", &e, ""))
    }

    fn handshake_error(&self, what: String) -> BusError {
        BusError::Io {
            iface: self.label.clone(),
            op: "socketcand handshake",
            errno: None,
            message: what,
        }
    }

    /// Blocks (read timeout set) until the next element; it must be `want`.
    fn expect(&mut self, want: Element, what: &str) -> Result<(), BusError> {
        let mut buf = [0u8; 512];
        loop {
            if let Some(r) = self.decoder.framer.next_element() {
                let el = r.and_then(parse_element);
                return match el {
                    Ok(e) if e == want => Ok(()),
                    Ok(Element::Error(msg)) => Err(if want == Element::Ok {
                        BusError::NoSuchInterface {
                            iface: self.label.clone(),
                            hint: format!(
                                "the server refused channel {:?}: {msg}",
                                self.url.channel
                            ),
                        }
                    } else {
                        self.handshake_error(format!("server error instead of {what}: {msg}"))
                    }),
                    Ok(other) => Err(self.handshake_error(format!(
                        "expected {what}, got {other:?}; is this a socketcand server?"
                    ))),
                    Err(e) => Err(self.handshake_error(format!(
                        "expected {what}: {e}; is this a socketcand server?"
                    ))),
                };
            }
            match self.stream.read(&mut buf) {
                Ok(0) => {
                    return Err(self.handshake_error(format!(
                        "the server closed the connection while waiting for {what}"
                    )))
                }
                Ok(n) => self.decoder.extend(&buf[..n]),
                Err(e) if e.kind() == io::ErrorKind::Interrupted => {}
                Err(e)
                    if matches!(
                        e.kind(),
                        io::ErrorKind::WouldBlock | io::ErrorKind::TimedOut
                    ) =>
                {
                    return Err(self.handshake_error(format!(
                        "no {what} within {:?}; is this a socketcand server?",
                        HANDSHAKE_TIMEOUT
                    )))
                }
                Err(e) => return Err(io_err(&self.label, "handshake read", &e, "")),
            }
        }
    }

    /// Writes as much pending output as the socket takes now.
    fn flush_out(&mut self) -> Result<(), BusError> {
        while self.out_pos < self.out.len() {
            match self.stream.write(&self.out[self.out_pos..]) {
                Ok(0) => {
                    return Err(BusError::Closed {
                        iface: self.label.clone(),
                    })
                }
                Ok(n) => self.out_pos += n,
                Err(e) if e.kind() == io::ErrorKind::WouldBlock => break,
                Err(e) if e.kind() == io::ErrorKind::Interrupted => {}
                Err(e) => return Err(io_err(&self.label, "send", &e, "")),
            }
        }
        if self.out_pos == self.out.len() {
            self.out.clear();
            self.out_pos = 0;
        }
        Ok(())
    }

    /// The next buffered frame, skipping what rollbase ignores; errors for error/malformed
    /// elements (retryable).
    fn next_buffered(&mut self) -> Result<Option<TimestampedFrame>, BusError> {
        self.decoder.next_frame().map_err(|e| {
            let event = match &e {
                ClientDecodeError::ErrorElement(text) => error_element_event(text),
                ClientDecodeError::Malformed(_) => None,
            };
            match event {
                Some(BusEvent::BusOff) => BusError::BusOff {
                    iface: self.label.clone(),
                },
                Some(event) => BusError::Controller {
                    iface: self.label.clone(),
                    event,
                },
                None => BusError::ErrorFrame {
                    iface: self.label.clone(),
                    detail: e.to_string(),
                },
            }
        })
    }

    fn wait(&self, timeout: Duration) -> Result<(), BusError> {
        let mut events = libc::POLLIN;
        if self.out_pos < self.out.len() {
            events |= libc::POLLOUT;
        }
        let mut pfd = libc::pollfd {
            fd: self.stream.as_raw_fd(),
            events,
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
            if e.kind() != io::ErrorKind::Interrupted {
                return Err(io_err(&self.label, "ppoll", &e, ""));
            }
        }
        Ok(())
    }
}

impl CanBus for SocketcandBus {
    fn send(&mut self, frame: &CanFrame) -> Result<(), BusError> {
        self.flush_out()?;
        if self.out.len() - self.out_pos > MAX_PENDING_OUTPUT {
            return Err(BusError::QueueFull {
                iface: self.label.clone(),
                capacity: MAX_PENDING_OUTPUT / 40,
            });
        }
        self.text.clear();
        format_send_into(&mut self.text, frame);
        self.out.extend_from_slice(self.text.as_bytes());
        self.frames_out += 1;
        self.flush_out()
    }

    fn try_recv(&mut self) -> Result<Option<TimestampedFrame>, BusError> {
        self.flush_out()?;
        let mut buf = [0u8; 4096];
        loop {
            if let Some(f) = self.next_buffered()? {
                return Ok(Some(f));
            }
            match self.stream.read(&mut buf) {
                Ok(0) => {
                    return Err(BusError::Closed {
                        iface: self.label.clone(),
                    })
                }
                Ok(n) => self.decoder.extend(&buf[..n]),
                Err(e) if e.kind() == io::ErrorKind::WouldBlock => return Ok(None),
                Err(e) if e.kind() == io::ErrorKind::Interrupted => {}
                Err(e) => return Err(io_err(&self.label, "receive", &e, "")),
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
            self.wait(deadline - now)?;
        }
    }

    fn name(&self) -> &str {
        &self.url.channel
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn error_elements_carry_bus_events() {
        assert_eq!(
            error_element_event("040 1700000000.000400"),
            Some(BusEvent::BusOff)
        );
        assert_eq!(
            error_element_event("100 1700000000.000400"),
            Some(BusEvent::Restarted)
        );
        assert_eq!(
            error_element_event("004 1700000000.000400"),
            Some(BusEvent::Controller)
        );
        // Lost arbitration (0x002), an error reply and junk are not state changes.
        assert_eq!(error_element_event("002 1700000000.000400"), None);
        assert_eq!(error_element_event("unknown command"), None);
        assert_eq!(error_element_event("040"), None);
        assert_eq!(error_element_event("040 1.0 extra"), None);
    }
    use std::net::TcpListener;

    fn frame(id: u16, data: &[u8]) -> CanFrame {
        CanFrame::new(id, data).expect("valid frame")
    }

    #[test]
    fn url_parsing_and_errors() {
        let u = SocketcandUrl::parse("socketcand://127.0.0.1:29536/vcan0").expect("url");
        assert_eq!(
            (u.host.as_str(), u.port, u.channel.as_str()),
            ("127.0.0.1", 29536, "vcan0")
        );
        assert_eq!(u.to_string(), "socketcand://127.0.0.1:29536/vcan0");
        let u = SocketcandUrl::parse("socketcand://localhost/can1").expect("default port");
        assert_eq!(u.port, DEFAULT_PORT);
        let u = SocketcandUrl::parse("socketcand://[::1]:4000/vcan0").expect("v6");
        assert_eq!((u.host.as_str(), u.port), ("::1", 4000));
        assert_eq!(u.host_port(), "[::1]:4000");
        for (bad, needle) in [
            ("tcp://x/vcan0", "starts with"),
            ("socketcand://127.0.0.1:29536", "missing `/CHANNEL`"),
            ("socketcand://127.0.0.1:0/vcan0", "port \"0\""),
            ("socketcand://127.0.0.1:http/vcan0", "port \"http\""),
            ("socketcand://:29536/vcan0", "host is empty"),
            ("socketcand://h/", "channel \"\""),
            ("socketcand://h/a_name_longer_than_16", "at most 16"),
            ("socketcand://h/v can", "whitespace"),
        ] {
            let e = SocketcandUrl::parse(bad).expect_err(bad);
            assert!(
                matches!(e, BusError::InvalidName { .. }) && e.to_string().contains(needle),
                "{bad}: {e}"
            );
        }
    }

    #[test]
    fn frame_element_is_exactly_socketcands_format() {
        let tf = TimestampedFrame {
            timestamp: Duration::new(1_700_000_000, 123_456_789),
            frame: frame(0x181, &[0x00, 0x11, 0x22, 0x33, 0x44, 0x55, 0x66, 0x77]),
        };
        let mut s = String::new();
        format_frame_into(&mut s, &tf);
        assert_eq!(s, "< frame 181 1700000000.123456 0011223344556677 >");
        let back = parse_element(&s).expect("parse");
        let mut want = tf;
        want.timestamp = Duration::new(1_700_000_000, 123_456_000);
        assert_eq!(back, Element::Frame(want));
        // No data: socketcand writes two spaces before '>'.
        s.clear();
        format_frame_into(
            &mut s,
            &TimestampedFrame {
                timestamp: Duration::from_millis(23_424),
                frame: frame(0x7, &[]),
            },
        );
        assert_eq!(s, "< frame 007 23.424000  >");
        assert!(matches!(parse_element(&s), Ok(Element::Frame(f)) if f.frame.is_empty()));
        // The protocol document's spaced bytes parse too.
        assert_eq!(
            parse_element("< frame 123 23.424242 11 22 33 44 >"),
            Ok(Element::Frame(TimestampedFrame {
                timestamp: Duration::new(23, 424_242_000),
                frame: frame(0x123, &[0x11, 0x22, 0x33, 0x44]),
            }))
        );
        assert_eq!(
            parse_element("< frame 1AAAAAAA 1.5 01F1 >"),
            Ok(Element::Unsupported("frame".into()))
        );
    }

    #[test]
    fn send_element_both_spellings() {
        let mut s = String::new();
        format_send_into(&mut s, &frame(0x201, &[0, 0x11, 0x22, 0x33, 0x44, 0xAB]));
        assert_eq!(s, "< send 201 6 00 11 22 33 44 AB >");
        assert_eq!(
            parse_element(&s),
            Ok(Element::Send(frame(
                0x201,
                &[0, 0x11, 0x22, 0x33, 0x44, 0xAB]
            )))
        );
        // python-can's spelling: unpadded lower-case bytes.
        assert_eq!(
            parse_element("< send 201 6 0 11 22 33 44 ab >"),
            Ok(Element::Send(frame(
                0x201,
                &[0, 0x11, 0x22, 0x33, 0x44, 0xAB]
            )))
        );
        s.clear();
        format_send_into(&mut s, &frame(0x123, &[]));
        assert_eq!(s, "< send 123 0 >");
        assert_eq!(
            parse_element("< send 123 0  >"),
            Ok(Element::Send(frame(0x123, &[])))
        );
        assert_eq!(
            parse_element("< send 1AAAAAAA 2 1 F1 >"),
            Ok(Element::Unsupported("send".into()))
        );
    }

    #[test]
    fn malformed_elements_name_the_problem() {
        for (el, needle) in [
            ("< send 201 3 01 02 >", "DLC 3 but 2"),
            ("< send 201 1 01 02 >", "more data bytes than DLC 1"),
            ("< send 201 9 >", "DLC \"9\""),
            ("< send 201 1 123 >", "1 or 2 hex digits"),
            ("< send 800 0 >", "above 7FF"),
            ("< send xyz 0 >", "not hex"),
            ("< frame 181 12:00 00 >", "timestamp"),
            ("< frame 181 1.0 0 >", "hex byte pairs"),
            ("< frame 181 1.0 000102030405060708 >", "more than 8"),
            ("< open >", "missing channel"),
        ] {
            let e = parse_element(el).expect_err(el);
            assert!(e.to_string().contains(needle), "{el}: {e}");
        }
        assert_eq!(parse_element("< hi >"), Ok(Element::Hi));
        assert_eq!(parse_element("<ok>"), Ok(Element::Ok));
        assert_eq!(
            parse_element("< open vcan0 >"),
            Ok(Element::Open("vcan0".into()))
        );
        assert_eq!(
            parse_element("< error could not open bus >"),
            Ok(Element::Error("could not open bus".into()))
        );
        assert_eq!(
            parse_element("< add 1 0 123 0 >"),
            Ok(Element::Other("add 1 0 123 0".into()))
        );
    }

    #[test]
    fn error_replies_to_hostile_elements_stay_short_and_printable() {
        // Found by the socketcand_server fuzz target: a `send` element full of control
        // characters got an 869-byte reply (each character escaped as `\u{12}`).
        let mut bad = String::from("<\t send");
        bad.push_str(&"\t".repeat(40));
        bad.push_str(&"\u{12}".repeat(150));
        bad.push_str(" 1 >");
        let mut session = ServerSession::new();
        session.handle(Ok(Element::Open("vcan0".into())));
        let mut f = Framer::new();
        f.extend(bad.as_bytes());
        let el = f.next_element().expect("one element");
        let step = session.handle(el.and_then(parse_element));
        let reply = step.reply.expect("an error reply");
        assert!(reply.starts_with("< error "), "{reply}");
        assert!(reply.len() <= 400, "{} bytes: {reply}", reply.len());
        assert!(
            reply
                .chars()
                .all(|c| c.is_ascii_graphic() || c == ' ' || c == '`'),
            "{reply}"
        );
        // Every token of every argument error is shown the same way.
        for el in [
            format!("< send {} 1 01 >", "\u{12}".repeat(100)),
            format!("< send 123 {} >", "\u{12}".repeat(100)),
            format!("< send 123 1 {} >", "\u{12}".repeat(100)),
            format!("< frame {} 1.0 >", "\u{12}".repeat(100)),
            format!("< frame 123 {} >", "\u{12}".repeat(100)),
            format!("< frame 123 1.0 {} >", "\u{12}".repeat(100)),
        ] {
            let e = parse_element(&el).expect_err(&el).to_string();
            assert!(e.len() <= 300, "{} bytes: {e}", e.len());
            assert!(!e.contains("\\u{12}") && !e.contains('\u{12}'), "{e}");
        }
        // Garbage outside elements likewise.
        let mut f = Framer::new();
        f.extend("\u{12}".repeat(200).as_bytes());
        let e = f
            .next_element()
            .expect("garbage")
            .expect_err("garbage")
            .to_string();
        assert!(e.len() <= 200 && !e.contains("\\u{12}"), "{e}");
    }

    #[test]
    fn framer_splits_partial_and_concatenated_elements() {
        let mut f = Framer::new();
        f.extend(b"< hi >< ok >\n< fra");
        assert_eq!(f.next_element(), Some(Ok("< hi >")));
        assert_eq!(f.next_element(), Some(Ok("< ok >")));
        assert_eq!(f.next_element(), None);
        f.extend(b"me 181 1.000001 00 >junk< echo >");
        assert_eq!(f.next_element(), Some(Ok("< frame 181 1.000001 00 >")));
        assert!(matches!(
            f.next_element(),
            Some(Err(ProtocolError::Garbage { text })) if text == "junk"
        ));
        assert_eq!(f.next_element(), Some(Ok("< echo >")));
        assert_eq!(f.next_element(), None);
        assert!(f.is_empty());
        // An unterminated element followed by a good one.
        f.extend(b"< send 1 <ok>");
        assert!(matches!(
            f.next_element(),
            Some(Err(ProtocolError::Garbage { .. }))
        ));
        assert_eq!(f.next_element(), Some(Ok("<ok>")));
        // Overlong garbage is discarded, then parsing resumes.
        f.extend(b"<");
        f.extend(&[b'a'; MAX_ELEMENT_LEN + 1]);
        assert_eq!(
            f.next_element(),
            Some(Err(ProtocolError::Overlong {
                max: MAX_ELEMENT_LEN
            }))
        );
        f.extend(b"< hi >");
        assert_eq!(f.next_element(), Some(Ok("< hi >")));
    }

    /// A scripted server: greets, checks the handshake, then sends `frames` and returns what
    /// the client sent.
    fn scripted_server(
        open_reply: &'static str,
        frames: Vec<String>,
    ) -> (u16, std::thread::JoinHandle<String>) {
        let l = TcpListener::bind("127.0.0.1:0").expect("bind");
        let port = l.local_addr().expect("addr").port();
        let h = std::thread::spawn(move || {
            let (mut s, _) = l.accept().expect("accept");
            s.set_read_timeout(Some(Duration::from_secs(5)))
                .expect("timeout");
            s.write_all(b"< hi >").expect("hi");
            let mut got = String::new();
            fn read_until(s: &mut TcpStream, got: &mut String, needle: &str) -> bool {
                let mut buf = [0u8; 256];
                while !got.contains(needle) {
                    let n = s.read(&mut buf).unwrap_or(0);
                    if n == 0 {
                        return false;
                    }
                    got.push_str(&String::from_utf8_lossy(&buf[..n]));
                }
                true
            }
            if !read_until(&mut s, &mut got, "< open vcan0 >") {
                return got;
            }
            s.write_all(open_reply.as_bytes()).expect("open reply");
            if open_reply != "< ok >" || !read_until(&mut s, &mut got, "< rawmode >") {
                return got;
            }
            s.write_all(b"< ok >").expect("raw ok");
            for f in &frames {
                s.write_all(f.as_bytes()).expect("frame");
            }
            read_until(&mut s, &mut got, "< send 201 2 0A 0B >");
            got
        });
        (port, h)
    }

    #[test]
    fn client_handshake_receive_and_send() {
        let frames = vec![
            "< frame 080 1700000000.000100 01000AC5 >".to_string(),
            "< frame 1AAAAAAA 1700000000.000200 00 >".to_string(),
            "< frame 181 1700000000.000300 0011 >< error 004 1700000000.000400 >".to_string(),
        ];
        let (port, server) = scripted_server("< ok >", frames);
        let mut bus =
            SocketcandBus::open(&format!("socketcand://127.0.0.1:{port}/vcan0")).expect("open");
        assert_eq!(bus.name(), "vcan0");
        let deadline = Instant::now() + Duration::from_secs(5);
        let a = bus.recv_until(deadline).expect("recv").expect("frame");
        assert_eq!(a.frame, frame(0x080, &[0x01, 0x00, 0x0A, 0xC5]));
        assert_eq!(a.timestamp, Duration::new(1_700_000_000, 100_000));
        let b = bus.recv_until(deadline).expect("recv").expect("frame");
        assert_eq!(b.frame, frame(0x181, &[0x00, 0x11]));
        let e = bus.recv_until(deadline).expect_err("error element");
        assert!(
            matches!(
                e,
                BusError::Controller {
                    event: BusEvent::Controller,
                    ..
                }
            ) && e.is_retryable(),
            "{e:?}"
        );
        assert_eq!(bus.stats().skipped, 1, "the 29-bit frame is skipped");
        CanBus::send(&mut bus, &frame(0x201, &[0x0A, 0x0B])).expect("send");
        let got = server.join().expect("server");
        assert!(
            got.ends_with("< rawmode >< echo >< send 201 2 0A 0B >"),
            "{got}"
        );
        // The server closed: the bus says so (not retryable).
        let e = loop {
            match bus.recv_until(Instant::now() + Duration::from_secs(5)) {
                Err(e) => break e,
                Ok(None) => continue,
                Ok(Some(f)) => panic!("unexpected frame {f:?}"),
            }
        };
        assert!(
            matches!(e, BusError::Closed { .. }) && !e.is_retryable(),
            "{e:?}"
        );
    }

    #[test]
    fn refused_channel_and_no_server_are_clear_errors() {
        let (port, server) = scripted_server("< error could not open bus >", vec![]);
        let e = SocketcandBus::open(&format!("socketcand://127.0.0.1:{port}/vcan0"))
            .expect_err("refused");
        assert!(
            matches!(e, BusError::NoSuchInterface { .. })
                && e.to_string().contains("could not open bus"),
            "{e}"
        );
        let _ = server.join();
        // A port nobody listens on (bound, then closed).
        let port = TcpListener::bind("127.0.0.1:0")
            .and_then(|l| l.local_addr())
            .expect("free port")
            .port();
        let e = SocketcandBus::open(&format!("socketcand://127.0.0.1:{port}/vcan0"))
            .expect_err("no server");
        assert!(e.to_string().contains("rollbase bridge"), "{e}");
        assert!(!e.is_retryable());
    }

    #[test]
    fn a_server_that_is_not_socketcand_is_named() {
        let l = TcpListener::bind("127.0.0.1:0").expect("bind");
        let port = l.local_addr().expect("addr").port();
        let h = std::thread::spawn(move || {
            let (mut s, _) = l.accept().expect("accept");
            let _ = s.write_all(b"SSH-2.0-OpenSSH_9.2\r\n");
            std::thread::sleep(Duration::from_millis(200));
        });
        let e = SocketcandBus::open(&format!("socketcand://127.0.0.1:{port}/vcan0"))
            .expect_err("not socketcand");
        assert!(e.to_string().contains("is this a socketcand server"), "{e}");
        let _ = h.join();
    }
}
