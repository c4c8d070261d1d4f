//! `candump -L` log files, so captures interoperate with can-utils (`candump -L`,
//! `canplayer`, `log2asc`) and python-can (`CanutilsLogReader`/`Writer`).
//!
//! One frame per line: `(<seconds>.<micro>) <interface> <frame>` with `<frame>` one of
//! - `181#0011223344556677` — data frame: 3 hex digits of id, `#`, 0..=8 bytes as hex pairs;
//! - `181#R` / `181#R3` — remote frame, optionally with its DLC (0..=8).
//!
//! Written exactly as candump writes them: 6 fraction digits, upper-case hex, no byte
//! separators. On reading, 1..=9 fraction digits and lower-case hex are accepted too, and so
//! is the direction flag python-can's `CanutilsLogWriter` appends (` R` received, ` T` sent). Lines
//! rollbase cannot represent are reported as [`CandumpError::Unsupported`], never panics:
//! CAN FD (`##`), 29-bit ids and error frames (8-digit ids), and classic frames with a raw
//! DLC above 8 (`_` suffix).

use std::io::{self, BufRead, Write};
use std::time::Duration;

use crate::frame::{CanFrame, TimestampedFrame};
use crate::protocol::MessageKind;
use crate::rx::{Receiver, RxStats};

/// One log line.
///
/// A remote (RTR) frame is represented by its id and a `frame.len()` equal to its DLC with
/// zero data bytes; [`parse_line_with_kind`] / [`CandumpReader::remote_frames`] tell it apart.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct LogEntry {
    /// Time of the frame (since the Unix epoch for real captures).
    pub timestamp: Duration,
    /// Interface name as logged (e.g. `vcan0`).
    pub interface: String,
    /// The frame.
    pub frame: CanFrame,
}

impl LogEntry {
    /// An entry.
    pub fn new(timestamp: Duration, interface: &str, frame: CanFrame) -> LogEntry {
        LogEntry {
            timestamp,
            interface: interface.to_string(),
            frame,
        }
    }
}

/// Data or remote frame.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Hash)]
pub enum FrameKind {
    /// A data frame (`id#data`).
    #[default]
    Data,
    /// A remote frame (`id#R` or `id#R<dlc>`).
    Remote,
}

/// Why a line could not be read.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum CandumpError {
    /// The line does not follow the `candump -L` format.
    #[error("candump log line {line}, column {column}: bad token {token:?}: expected {expected}")]
    Syntax {
        /// 1-based line number.
        line: usize,
        /// 1-based byte column where the bad token starts.
        column: usize,
        /// The offending token (at most 40 characters).
        token: String,
        /// What was expected there.
        expected: &'static str,
    },
    /// A valid candump line that rollbase cannot represent.
    #[error("candump log line {line}, column {column}: unsupported frame {token:?}: {what}")]
    Unsupported {
        /// 1-based line number.
        line: usize,
        /// 1-based byte column of the frame token.
        column: usize,
        /// The frame token (at most 40 characters).
        token: String,
        /// What is not supported.
        what: &'static str,
    },
    /// Reading failed.
    #[error("candump log line {line}: read error: {message}")]
    Io {
        /// 1-based line number.
        line: usize,
        /// OS error text.
        message: String,
    },
    /// The line is not UTF-8 text (the reader goes on with the next line).
    #[error("candump log line {line}, column {column}: not UTF-8 text (a damaged or binary line)")]
    NotUtf8 {
        /// 1-based line number.
        line: usize,
        /// 1-based byte column of the first invalid byte.
        column: usize,
    },
    /// The line is longer than [`crate::input::MAX_CANDUMP_LINE_BYTES`]: no `candump -L` line
    /// is (the longest is about 180 bytes), so the input is not a candump log and the reader
    /// stops there instead of reading an endless line into memory.
    #[error("candump log line {line} is longer than {cap} bytes (a candump -L line is at most about 180): this is not a candump log; reading stopped")]
    LineTooLong {
        /// 1-based line number.
        line: usize,
        /// The cap (bytes).
        cap: usize,
    },
}

impl CandumpError {
    fn set_line(mut self, n: usize) -> Self {
        match &mut self {
            CandumpError::Syntax { line, .. }
            | CandumpError::Unsupported { line, .. }
            | CandumpError::Io { line, .. }
            | CandumpError::NotUtf8 { line, .. }
            | CandumpError::LineTooLong { line, .. } => *line = n,
        }
        self
    }

    /// The 1-based line number of the log the error is about ([`parse_line`] alone reports
    /// line 1; [`CandumpReader`] the line of the file).
    pub fn line(&self) -> usize {
        match self {
            CandumpError::Syntax { line, .. }
            | CandumpError::Unsupported { line, .. }
            | CandumpError::Io { line, .. }
            | CandumpError::NotUtf8 { line, .. }
            | CandumpError::LineTooLong { line, .. } => *line,
        }
    }
}

fn clip(s: &str) -> String {
    s.chars().take(40).collect()
}

fn syntax(column: usize, token: &str, expected: &'static str) -> CandumpError {
    CandumpError::Syntax {
        line: 1,
        column,
        token: clip(token),
        expected,
    }
}

fn unsupported(column: usize, token: &str, what: &'static str) -> CandumpError {
    CandumpError::Unsupported {
        line: 1,
        column,
        token: clip(token),
        what,
    }
}

fn hex_val(c: u8) -> Option<u8> {
    match c {
        b'0'..=b'9' => Some(c - b'0'),
        b'a'..=b'f' => Some(c - b'a' + 10),
        b'A'..=b'F' => Some(c - b'A' + 10),
        _ => None,
    }
}

/// Splits off the next space-separated token; returns (token, its 1-based column, rest).
fn next_token(s: &str, offset: usize) -> Option<(&str, usize, &str, usize)> {
    let trimmed = s.trim_start_matches(char::is_whitespace);
    let start = offset + (s.len() - trimmed.len());
    if trimmed.is_empty() {
        return None;
    }
    let end = trimmed
        .find(|c: char| c.is_whitespace())
        .unwrap_or(trimmed.len());
    Some((&trimmed[..end], start + 1, &trimmed[end..], start + end))
}

fn parse_timestamp(tok: &str, column: usize) -> Result<Duration, CandumpError> {
    const EXPECTED: &str = "a timestamp like (1700000000.123456)";
    let inner = tok
        .strip_prefix('(')
        .and_then(|t| t.strip_suffix(')'))
        .ok_or_else(|| syntax(column, tok, EXPECTED))?;
    let (secs, frac) = inner
        .split_once('.')
        .ok_or_else(|| syntax(column, tok, EXPECTED))?;
    if secs.is_empty()
        || frac.is_empty()
        || frac.len() > 9
        || !secs.bytes().all(|b| b.is_ascii_digit())
        || !frac.bytes().all(|b| b.is_ascii_digit())
    {
        return Err(syntax(column, tok, EXPECTED));
    }
    let s: u64 = secs
        .parse()
        .map_err(|_| syntax(column, tok, "seconds that fit 64 bits"))?;
    let mut nanos: u32 = 0;
    for (i, b) in frac.bytes().enumerate() {
        nanos += u32::from(b - b'0') * 10u32.pow(8 - i as u32);
    }
    Ok(Duration::new(s, nanos))
}

fn parse_frame(tok: &str, column: usize) -> Result<(CanFrame, FrameKind), CandumpError> {
    let Some((id_s, rest)) = tok.split_once('#') else {
        return Err(syntax(column, tok, "a frame like 181#0011223344556677"));
    };
    if rest.starts_with('#') {
        return Err(unsupported(
            column,
            tok,
            "CAN FD frames (##) are not supported",
        ));
    }
    if !id_s.bytes().all(|b| hex_val(b).is_some()) || id_s.is_empty() {
        return Err(syntax(column, tok, "a hexadecimal CAN id before '#'"));
    }
    if id_s.len() == 8 {
        return Err(unsupported(
            column,
            tok,
            "29-bit (extended) ids and error frames are not supported",
        ));
    }
    if id_s.len() != 3 {
        return Err(syntax(column, tok, "a 3-digit (11-bit) hexadecimal CAN id"));
    }
    let id = id_s.bytes().fold(0u16, |acc, b| {
        (acc << 4) | u16::from(hex_val(b).unwrap_or(0))
    });
    if id > 0x7FF {
        return Err(syntax(column, tok, "an 11-bit CAN id (at most 7FF)"));
    }
    if let Some(r) = rest.strip_prefix(['R', 'r']) {
        let dlc = match r.as_bytes() {
            [] => 0,
            [d] if d.is_ascii_digit() && *d <= b'8' => usize::from(d - b'0'),
            _ => return Err(syntax(column, tok, "R or R0..R8 for a remote frame")),
        };
        let frame = CanFrame::new(id, &[0u8; 8][..dlc])
            .map_err(|_| syntax(column, tok, "a valid remote frame"))?;
        return Ok((frame, FrameKind::Remote));
    }
    if rest.contains('_') {
        return Err(unsupported(
            column,
            tok,
            "classic frames with a raw DLC above 8 (_ suffix) are not supported",
        ));
    }
    let bytes = rest.as_bytes();
    if bytes.len() % 2 != 0 || bytes.len() > 16 {
        return Err(syntax(
            column,
            tok,
            "0 to 8 data bytes as pairs of hex digits",
        ));
    }
    let mut data = [0u8; 8];
    for (i, pair) in bytes.chunks(2).enumerate() {
        match (hex_val(pair[0]), hex_val(pair[1])) {
            (Some(h), Some(l)) => data[i] = (h << 4) | l,
            _ => return Err(syntax(column, tok, "data bytes as hex digits")),
        }
    }
    let frame = CanFrame::new(id, &data[..bytes.len() / 2])
        .map_err(|_| syntax(column, tok, "0 to 8 data bytes"))?;
    Ok((frame, FrameKind::Data))
}

/// Parses one `candump -L` line (a trailing `\n` / `\r\n` is allowed). Errors report line 1;
/// [`CandumpReader`] reports the real line number. Remote frames are accepted (see
/// [`LogEntry`]); use [`parse_line_with_kind`] to tell them apart.
pub fn parse_line(line: &str) -> Result<LogEntry, CandumpError> {
    parse_line_with_kind(line).map(|(e, _)| e)
}

/// Like [`parse_line`], also returning whether the frame is a data or a remote frame.
pub fn parse_line_with_kind(line: &str) -> Result<(LogEntry, FrameKind), CandumpError> {
    let line = line.trim_end_matches(['\n', '\r']);
    let (ts_tok, ts_col, rest, off) = next_token(line, 0)
        .ok_or_else(|| syntax(1, line, "a timestamp like (1700000000.123456)"))?;
    let timestamp = parse_timestamp(ts_tok, ts_col)?;
    let (if_tok, _if_col, rest, off) = next_token(rest, off)
        .ok_or_else(|| syntax(off + 1, "", "an interface name after the timestamp"))?;
    let (fr_tok, fr_col, rest, off) = next_token(rest, off)
        .ok_or_else(|| syntax(off + 1, "", "a frame like 181#0011223344556677"))?;
    let (frame, kind) = parse_frame(fr_tok, fr_col)?;
    // python-can's CanutilsLogWriter appends the direction: ` R` (received) or ` T` (sent).
    let (rest, off) = match next_token(rest, off) {
        Some(("R" | "T", _, r, o)) => (r, o),
        _ => (rest, off),
    };
    if let Some((extra, col, _, _)) = next_token(rest, off) {
        return Err(syntax(
            col,
            extra,
            "end of line after the frame (or one direction flag R or T)",
        ));
    }
    Ok((
        LogEntry {
            timestamp,
            interface: if_tok.to_string(),
            frame,
        },
        kind,
    ))
}

/// Formats a data-frame entry exactly as `candump -L` does (no trailing newline).
pub fn format_line(entry: &LogEntry) -> String {
    format_line_with_kind(entry, FrameKind::Data)
}

/// Formats an entry as a data or remote frame (`id#R<dlc>`, the DLC omitted when 0).
pub fn format_line_with_kind(entry: &LogEntry, kind: FrameKind) -> String {
    use std::fmt::Write as _;
    let mut s = String::with_capacity(48);
    let _ = write!(
        s,
        "({}.{:06}) {} {:03X}#",
        entry.timestamp.as_secs(),
        entry.timestamp.subsec_micros(),
        entry.interface,
        entry.frame.id()
    );
    match kind {
        FrameKind::Remote => {
            s.push('R');
            if !entry.frame.is_empty() {
                let _ = write!(s, "{}", entry.frame.len());
            }
        }
        FrameKind::Data => {
            for b in entry.frame.data() {
                let _ = write!(s, "{b:02X}");
            }
        }
    }
    s
}

/// Writes `candump -L` lines.
#[derive(Debug)]
pub struct CandumpWriter<W: Write> {
    out: W,
}

impl<W: Write> CandumpWriter<W> {
    /// Wraps a writer (use a `BufWriter` for files).
    pub fn new(out: W) -> Self {
        CandumpWriter { out }
    }

    /// Writes one entry and a newline.
    pub fn write(&mut self, entry: &LogEntry) -> io::Result<()> {
        writeln!(self.out, "{}", format_line(entry))
    }

    /// Writes one entry as a data or remote frame.
    pub fn write_with_kind(&mut self, entry: &LogEntry, kind: FrameKind) -> io::Result<()> {
        writeln!(self.out, "{}", format_line_with_kind(entry, kind))
    }

    /// Writes one received data frame.
    pub fn write_frame(&mut self, interface: &str, frame: &TimestampedFrame) -> io::Result<()> {
        self.write(&LogEntry::new(frame.timestamp, interface, frame.frame))
    }

    /// Flushes the underlying writer.
    pub fn flush(&mut self) -> io::Result<()> {
        self.out.flush()
    }

    /// Returns the underlying writer.
    pub fn into_inner(self) -> W {
        self.out
    }
}

/// Reads `candump -L` lines; an iterator of entries. Blank lines are skipped; a line that
/// cannot be parsed (bad syntax, not UTF-8) is reported with its line number and reading goes
/// on with the next line; a read error or a line longer than
/// [`crate::input::MAX_CANDUMP_LINE_BYTES`] (not a candump log: `/dev/zero`, a binary file)
/// ends the iteration after being reported once. No more than the cap is ever held in memory.
#[derive(Debug)]
pub struct CandumpReader<R: BufRead> {
    input: R,
    line: usize,
    buf: Vec<u8>,
    done: bool,
    remote: u64,
    last_kind: FrameKind,
}

impl<R: BufRead> CandumpReader<R> {
    /// Wraps a buffered reader.
    pub fn new(input: R) -> Self {
        CandumpReader {
            input,
            line: 0,
            buf: Vec::with_capacity(64),
            done: false,
            remote: 0,
            last_kind: FrameKind::Data,
        }
    }

    /// Whether the entry last yielded was a data or a remote frame (a remote frame's entry
    /// holds its DLC and no data: show it as a request, not as zero bytes).
    pub fn last_kind(&self) -> FrameKind {
        self.last_kind
    }

    /// Remote frames read so far (they are yielded like data frames, see [`LogEntry`]).
    pub fn remote_frames(&self) -> u64 {
        self.remote
    }

    /// Number of the last line read.
    pub fn line(&self) -> usize {
        self.line
    }
}

impl<R: BufRead> Iterator for CandumpReader<R> {
    type Item = Result<LogEntry, CandumpError>;

    fn next(&mut self) -> Option<Self::Item> {
        while !self.done {
            self.line += 1;
            let cap = crate::input::MAX_CANDUMP_LINE_BYTES;
            match crate::input::read_line(&mut self.input, &mut self.buf, cap) {
                Ok(crate::input::Line::Eof) => {
                    self.done = true;
                    return None;
                }
                Ok(crate::input::Line::Complete) => {}
                Ok(crate::input::Line::TooLong) => {
                    self.done = true;
                    return Some(Err(CandumpError::LineTooLong {
                        line: self.line,
                        cap,
                    }));
                }
                Err(e) => {
                    self.done = true;
                    return Some(Err(CandumpError::Io {
                        line: self.line,
                        message: e.to_string(),
                    }));
                }
            }
            let text = match std::str::from_utf8(&self.buf) {
                Ok(t) => t,
                Err(e) => {
                    return Some(Err(CandumpError::NotUtf8 {
                        line: self.line,
                        column: e.valid_up_to() + 1,
                    }))
                }
            };
            if text.trim().is_empty() {
                continue;
            }
            return Some(match parse_line_with_kind(text) {
                Ok((entry, kind)) => {
                    if kind == FrameKind::Remote {
                        self.remote += 1;
                    }
                    self.last_kind = kind;
                    Ok(entry)
                }
                Err(e) => Err(e.set_line(self.line)),
            });
        }
        None
    }
}

/// Counters of a bus monitor (`rollbase monitor`): frames seen, accepted per kind, rejected,
/// unparsable log lines, and the receiver's rejection breakdown.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct MonitorStats {
    /// Frames passed to [`describe`].
    pub frames: u64,
    /// Accepted frames per message kind (indexed by [`MessageKind::index`]).
    pub accepted: [u64; 5],
    /// Frames the receiver rejected.
    pub rejected: u64,
    /// Log lines that could not be parsed (counted by the caller).
    pub unparsable: u64,
    /// The receiver statistics after the last frame.
    pub rx: RxStats,
}

impl std::fmt::Display for MonitorStats {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "frames: {}, accepted:", self.frames)?;
        for k in MessageKind::ALL {
            write!(f, " {k} {}", self.accepted[k.index()])?;
        }
        let r = &self.rx;
        write!(
            f,
            "; rejected: {} (bad CRC {}, wrong DLC {}, unknown id {}, out of range {}, repeated {}, \
             skipped {} with {} lost, other {}); unparsable lines: {}",
            self.rejected,
            r.bad_crc,
            r.wrong_dlc,
            r.unknown_id,
            r.out_of_range,
            r.repeated,
            r.skipped,
            r.lost,
            r.other,
            self.unparsable
        )
    }
}

/// One human-readable monitor line for a received frame: timestamp, id, bytes, then the
/// decoded message or why the receiver rejected it. Updates `rx` and `stats`.
pub fn describe(
    rx: &mut Receiver,
    stats: &mut MonitorStats,
    timestamp: Duration,
    frame: &CanFrame,
) -> String {
    use std::fmt::Write as _;
    stats.frames += 1;
    let mut s = String::with_capacity(128);
    let _ = write!(
        s,
        "({}.{:06}) {:03X} [{}]",
        timestamp.as_secs(),
        timestamp.subsec_micros(),
        frame.id(),
        frame.len()
    );
    for b in frame.data() {
        let _ = write!(s, " {b:02X}");
    }
    for _ in frame.len()..8 {
        s.push_str("   ");
    }
    match rx.accept(frame) {
        Ok(m) => {
            stats.accepted[m.kind().index()] += 1;
            let _ = write!(s, "  {m}");
        }
        Err(e) => {
            stats.rejected += 1;
            let _ = write!(s, "  REJECTED: {e}");
        }
    }
    stats.rx = *rx.stats();
    s
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn parses_the_reference_line() {
        let e = parse_line("(1700000000.123456) vcan0 181#0011223344556677").expect("parse");
        assert_eq!(e.timestamp, Duration::new(1_700_000_000, 123_456_000));
        assert_eq!(e.interface, "vcan0");
        assert_eq!(e.frame.id(), 0x181);
        assert_eq!(
            e.frame.data(),
            &[0x00, 0x11, 0x22, 0x33, 0x44, 0x55, 0x66, 0x77]
        );
        assert_eq!(
            format_line(&e),
            "(1700000000.123456) vcan0 181#0011223344556677"
        );
    }

    #[test]
    fn empty_remote_and_lowercase_frames() {
        let e = parse_line("(0.000001) can0 080#\n").expect("parse");
        assert!(e.frame.is_empty());
        assert_eq!(format_line(&e), "(0.000001) can0 080#");
        let (r, kind) = parse_line_with_kind("(5.5) can0 7ff#R3").expect("parse");
        assert_eq!(kind, FrameKind::Remote);
        assert_eq!((r.frame.id(), r.frame.len()), (0x7FF, 3));
        assert_eq!(r.timestamp, Duration::from_millis(5500));
        assert_eq!(format_line_with_kind(&r, kind), "(5.500000) can0 7FF#R3");
        let (r0, k0) = parse_line_with_kind("(1.0) x 123#R").expect("parse");
        assert_eq!(format_line_with_kind(&r0, k0), "(1.000000) x 123#R");
        assert_eq!(
            parse_line_with_kind("(1.0) x 123#").expect("parse").1,
            FrameKind::Data
        );
        let mut rd = CandumpReader::new("(1.0) x 123#R\n(1.0) x 123#\n".as_bytes());
        assert!(rd.next().is_some() && rd.next().is_some() && rd.next().is_none());
        assert_eq!(rd.remote_frames(), 1);
        let l = parse_line("(1.000000) can0 1ab#deadbeef\r\n").expect("parse");
        assert_eq!(format_line(&l), "(1.000000) can0 1AB#DEADBEEF");
    }

    #[test]
    fn python_can_direction_flags_are_accepted() {
        let r = parse_line("(1700000000.123456) vcan0 080#00000033 R\n").expect("rx");
        let t = parse_line("(1700000000.123456) vcan0 080#00000033 T").expect("tx");
        assert_eq!(r, t);
        assert_eq!(r.frame.data(), &[0, 0, 0, 0x33]);
        let e = parse_line("(1.0) vcan0 080#00 X").expect_err("unknown flag");
        assert!(
            matches!(e, CandumpError::Syntax { column: 20, .. }),
            "{e:?}"
        );
        assert!(
            parse_line("(1.0) vcan0 080#00 R T").is_err(),
            "one flag at most"
        );
    }

    #[test]
    fn errors_name_column_and_token() {
        let e = parse_line("(1.0) vcan0 181##0011").expect_err("fd");
        assert!(
            matches!(e, CandumpError::Unsupported { column: 13, .. }),
            "{e:?}"
        );
        let e = parse_line("(1.0) vcan0 12345678#00").expect_err("eff");
        assert!(matches!(e, CandumpError::Unsupported { .. }));
        let e = parse_line("(1.0) vcan0 181#001").expect_err("odd");
        assert!(
            matches!(e, CandumpError::Syntax { column: 13, ref token, .. } if token == "181#001"),
            "{e:?}"
        );
        let e = parse_line("1.0 vcan0 181#00").expect_err("ts");
        assert!(matches!(e, CandumpError::Syntax { column: 1, .. }));
        let e = parse_line("(1.0) vcan0 800#00").expect_err("id");
        assert!(e.to_string().contains("7FF"), "{e}");
        let e = parse_line("(1.0) vcan0 181#00 extra").expect_err("extra");
        assert!(
            matches!(e, CandumpError::Syntax { column: 20, .. }),
            "{e:?}"
        );
        let e = parse_line("(1.0) vcan0").expect_err("no frame");
        assert!(matches!(e, CandumpError::Syntax { .. }));
        let e = parse_line("(1.0) vcan0 181#11223344556677889900").expect_err("long");
        assert!(matches!(e, CandumpError::Syntax { .. }));
        let e = parse_line("(1.0) vcan0 181#R9").expect_err("rtr dlc");
        assert!(matches!(e, CandumpError::Syntax { .. }));
        let e = parse_line("(1.0) vcan0 181#1122334455667788_E").expect_err("len8");
        assert!(matches!(e, CandumpError::Unsupported { .. }));
        let e = parse_line("(99999999999999999999.0) vcan0 181#").expect_err("overflow");
        assert!(matches!(e, CandumpError::Syntax { .. }));
    }

    #[test]
    fn reader_reports_line_numbers_and_skips_blank_lines() {
        let log = "(1.000000) vcan0 080#0102\n\n(2.000000) vcan0 zz#\n(3.000000) vcan0 181#\n";
        let items: Vec<_> = CandumpReader::new(log.as_bytes()).collect();
        assert_eq!(items.len(), 3);
        assert!(items[0].is_ok());
        assert!(
            matches!(items[1], Err(CandumpError::Syntax { line: 3, .. })),
            "{:?}",
            items[1]
        );
        assert_eq!(items[2].as_ref().map(|e| e.frame.id()), Ok(0x181));
    }

    #[test]
    fn reader_goes_on_after_a_non_utf8_line_and_stops_at_an_endless_one() {
        let mut log = b"(1.000000) vcan0 080#0102\n(1.5) vcan0 \xff\xfe#00\n".to_vec();
        log.extend_from_slice(b"(2.000000) vcan0 181#\n");
        let items: Vec<_> = CandumpReader::new(log.as_slice()).collect();
        assert_eq!(items.len(), 3);
        assert_eq!(
            items[1],
            Err(CandumpError::NotUtf8 {
                line: 2,
                column: 13
            })
        );
        assert!(items[2].is_ok(), "{:?}", items[2]);
        assert_eq!(items[1].as_ref().unwrap_err().line(), 2);
        let mut log = b"(1.000000) vcan0 080#0102\n".to_vec();
        log.extend(std::iter::repeat_n(b'0', 10_000));
        log.extend_from_slice(b"\n(2.000000) vcan0 181#\n");
        let items: Vec<_> = CandumpReader::new(log.as_slice()).collect();
        assert_eq!(items.len(), 2, "reading stops at the endless line");
        assert!(matches!(
            items[1],
            Err(CandumpError::LineTooLong { line: 2, cap: 4096 })
        ));
    }

    #[test]
    fn describe_decodes_and_counts() {
        let mut rx = Receiver::new();
        let mut st = MonitorStats::default();
        let sync = CanFrame::new(0x080, &[0x34, 0x12, 0x05, 0x58]).expect("frame");
        let line = describe(&mut rx, &mut st, Duration::from_millis(1500), &sync);
        assert_eq!(
            line,
            "(1.500000) 080 [4] 34 12 05 58              SYNC #5 cycle=4660"
        );
        let line = describe(&mut rx, &mut st, Duration::ZERO, &sync);
        assert!(
            line.contains("REJECTED: SYNC node 0: repeated rolling counter 5"),
            "{line}"
        );
        assert_eq!(
            (st.frames, st.accepted[0], st.rejected, st.rx.repeated),
            (2, 1, 1, 1)
        );
        assert!(st.to_string().contains("repeated 1"), "{st}");
    }

    #[test]
    fn writer_then_reader_round_trip() {
        let mut w = CandumpWriter::new(Vec::new());
        let f = TimestampedFrame {
            timestamp: Duration::new(1_700_000_000, 999_999_000),
            frame: CanFrame::new(0x284, &[1, 2, 3, 4, 5, 6, 7, 8]).expect("frame"),
        };
        w.write_frame("vcan0", &f).expect("write");
        w.flush().expect("flush");
        let bytes = w.into_inner();
        assert_eq!(
            String::from_utf8(bytes.clone()).expect("utf8"),
            "(1700000000.999999) vcan0 284#0102030405060708\n"
        );
        let back: Vec<_> = CandumpReader::new(bytes.as_slice()).collect();
        assert_eq!(back, vec![Ok(LogEntry::new(f.timestamp, "vcan0", f.frame))]);
    }
}
