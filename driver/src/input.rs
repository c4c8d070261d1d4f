//! Bounded reading of input files: one helper for every crate, so no file handed to the
//! command line (`--config /dev/zero`, a FIFO, a multi-gigabyte file by mistake) can make a
//! process read without end or grow its memory without bound.
//!
//! - [`read_text`] reads a whole text file of at most `cap` bytes. A regular file longer than
//!   the cap is refused from its metadata before anything is read; anything else (a character
//!   device like `/dev/zero`, a pipe) is read through [`std::io::Read::take`] with `cap + 1`
//!   bytes at most, so at most `cap + 1` bytes are ever held in memory.
//! - [`read_line`] reads one `\n`-terminated line of at most `cap` bytes from a buffered
//!   reader, without ever holding more than `cap` bytes of it.
//!
//! # The caps
//!
//! - [`MAX_CONFIG_BYTES`] = 1 MiB for the TOML configuration files (platform, plant, fault
//!   schedule). The largest real file is the platform file with a full `[cia402]` table, about
//!   3 KiB; a fault schedule with a thousand events is about 60 KiB. 1 MiB is 300 times the
//!   largest real file, and parsing 1 MiB of TOML takes tens of milliseconds.
//! - [`MAX_TRAJECTORY_BYTES`] = 8 MiB for waypoint files: one waypoint is about 90 bytes of
//!   TOML, so 8 MiB holds about 90 000 waypoints — one every 0.4 s for the 10-hour limit on
//!   trajectory times (`rollbase_control::reference::trajectory::MAX_WAYPOINT_TIME_S`).
//! - [`MAX_CANDUMP_LINE_BYTES`] = 4 KiB per `candump -L` line: the longest valid line (a CAN
//!   FD frame with 64 data bytes, a 16-byte interface name, a 20-character timestamp and a
//!   direction flag) is about 180 bytes. A candump log itself has no size cap: an hour of
//!   capture at 3 250 frames/s is about 500 MB, read line by line.

use std::io::{BufRead, Read};
use std::path::Path;

/// Cap on a TOML configuration file (platform, plant, fault schedule): 1 MiB (module docs).
pub const MAX_CONFIG_BYTES: u64 = 1 << 20;

/// Cap on a device description file (EDS/DCF, CiA 306): 8 MiB. A single-axis drive's EDS
/// is 100–600 KiB (every object, sub-index and its attributes spelt out); multi-axis drives
/// and encoders with many vendor objects reach 2–3 MiB.
pub const MAX_EDS_BYTES: u64 = 8 << 20;

/// Cap on a waypoint file: 8 MiB (module docs).
pub const MAX_TRAJECTORY_BYTES: u64 = 8 << 20;

/// Cap on one `candump -L` log line: 4 KiB (module docs).
pub const MAX_CANDUMP_LINE_BYTES: usize = 4096;

/// Why an input file could not be read.
#[derive(Debug, thiserror::Error)]
pub enum InputError {
    /// The file could not be opened or read.
    #[error("cannot read {what} {path}: {source}")]
    Io {
        /// What the file is for (e.g. "platform file").
        what: &'static str,
        /// File path.
        path: String,
        /// Underlying IO error.
        source: std::io::Error,
    },
    /// The file is longer than the cap.
    #[error("{what} {path} is larger than {cap_text}, the limit for such a file (the real ones are a few KiB): is it the right file? (`/dev/zero` and other endless inputs are refused this way)", cap_text = human_bytes(*cap))]
    TooLarge {
        /// What the file is for.
        what: &'static str,
        /// File path.
        path: String,
        /// The cap (bytes).
        cap: u64,
    },
    /// The file is not UTF-8 text.
    #[error(
        "{what} {path} is not UTF-8 text (invalid byte at offset {offset}): is it the right file?"
    )]
    NotUtf8 {
        /// What the file is for.
        what: &'static str,
        /// File path.
        path: String,
        /// Byte offset of the first invalid byte.
        offset: usize,
    },
}

/// `1 MiB`, `4 KiB`, `100 bytes`.
pub fn human_bytes(n: u64) -> String {
    if n >= 1 << 20 && n % (1 << 20) == 0 {
        format!("{} MiB", n >> 20)
    } else if n >= 1 << 10 && n % (1 << 10) == 0 {
        format!("{} KiB", n >> 10)
    } else {
        format!("{n} bytes")
    }
}

/// Reads the whole text file at `path`, of at most `cap` bytes (see the module docs); `what`
/// names the file in errors ("platform file", "waypoint file" …).
pub fn read_text(path: &Path, cap: u64, what: &'static str) -> Result<String, InputError> {
    let bytes = read_bytes(path, cap, what)?;
    String::from_utf8(bytes).map_err(|e| InputError::NotUtf8 {
        what,
        path: path.display().to_string(),
        offset: e.utf8_error().valid_up_to(),
    })
}

/// [`read_text`] for files that are not always UTF-8: device description files (EDS/DCF)
/// from vendors' tools are often ISO 8859-1 ("°", "µ" in names). UTF-8 text is taken as
/// it is; anything else is read as ISO 8859-1 (every byte one character), which never fails.
pub fn read_text_latin1(path: &Path, cap: u64, what: &'static str) -> Result<String, InputError> {
    let bytes = read_bytes(path, cap, what)?;
    Ok(match String::from_utf8(bytes) {
        Ok(s) => s,
        Err(e) => e.into_bytes().iter().map(|&b| char::from(b)).collect(),
    })
}

/// The bytes of a file of at most `cap` bytes (see the module docs).
pub fn read_bytes(path: &Path, cap: u64, what: &'static str) -> Result<Vec<u8>, InputError> {
    let io = |source| InputError::Io {
        what,
        path: path.display().to_string(),
        source,
    };
    let too_large = || InputError::TooLarge {
        what,
        path: path.display().to_string(),
        cap,
    };
    let file = std::fs::File::open(path).map_err(io)?;
    if let Ok(m) = file.metadata() {
        if m.is_file() && m.len() > cap {
            return Err(too_large());
        }
    }
    let mut bytes = Vec::new();
    file.take(cap.saturating_add(1))
        .read_to_end(&mut bytes)
        .map_err(io)?;
    if bytes.len() as u64 > cap {
        return Err(too_large());
    }
    Ok(bytes)
}

/// What [`read_line`] found.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Line {
    /// End of input: nothing was read.
    Eof,
    /// A line (with its `\n`, unless it was the last line without one) is in the buffer.
    Complete,
    /// The line's content is longer than the cap: the buffer holds its first `cap` bytes, the
    /// rest of the line is still unread.
    TooLong,
}

/// Reads one line (up to and including `\n`) into `buf` (cleared first), whose content
/// (without the `\n`) is at most `cap` bytes; see [`Line`]. Never holds more than `cap + 1`
/// bytes.
pub fn read_line<R: BufRead + ?Sized>(
    input: &mut R,
    buf: &mut Vec<u8>,
    cap: usize,
) -> std::io::Result<Line> {
    buf.clear();
    loop {
        let chunk = match input.fill_buf() {
            Ok(c) => c,
            Err(e) if e.kind() == std::io::ErrorKind::Interrupted => continue,
            Err(e) => return Err(e),
        };
        if chunk.is_empty() {
            return Ok(if buf.is_empty() {
                Line::Eof
            } else {
                Line::Complete
            });
        }
        let room = cap - buf.len().min(cap);
        match chunk.iter().position(|&b| b == b'\n') {
            Some(i) if i <= room => {
                buf.extend_from_slice(&chunk[..=i]);
                input.consume(i + 1);
                return Ok(Line::Complete);
            }
            _ if room == 0 => return Ok(Line::TooLong),
            _ => {
                let take = chunk.len().min(room);
                buf.extend_from_slice(&chunk[..take]);
                input.consume(take);
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn endless_inputs_stop_at_the_cap() {
        let e = read_text(Path::new("/dev/zero"), 4096, "platform file").unwrap_err();
        assert!(matches!(e, InputError::TooLarge { cap: 4096, .. }), "{e}");
        let msg = e.to_string();
        assert!(
            msg.contains("/dev/zero") && msg.contains("4 KiB") && msg.contains("platform file"),
            "{msg}"
        );
        let mut zeros = std::io::BufReader::new(std::fs::File::open("/dev/zero").unwrap());
        let mut buf = Vec::new();
        assert_eq!(read_line(&mut zeros, &mut buf, 100).unwrap(), Line::TooLong);
        assert_eq!(buf.len(), 100);
        let mut exact = &b"abcd\nabcde"[..];
        assert_eq!(read_line(&mut exact, &mut buf, 4).unwrap(), Line::Complete);
        assert_eq!(buf, b"abcd\n");
        assert_eq!(read_line(&mut exact, &mut buf, 4).unwrap(), Line::TooLong);
    }

    #[test]
    fn files_within_the_cap_are_read_whole_and_bad_ones_are_named() {
        let dir = std::env::temp_dir().join(format!("rollbase-input-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let p = dir.join("ok.toml");
        std::fs::write(&p, "a = 1\n").unwrap();
        assert_eq!(read_text(&p, 6, "x").unwrap(), "a = 1\n");
        assert!(matches!(
            read_text(&p, 5, "x"),
            Err(InputError::TooLarge { cap: 5, .. })
        ));
        std::fs::write(&p, b"a = \xff\n").unwrap();
        assert!(matches!(
            read_text(&p, 100, "x"),
            Err(InputError::NotUtf8 { offset: 4, .. })
        ));
        let missing = read_text(&dir.join("missing.toml"), 100, "fault file").unwrap_err();
        assert!(missing.to_string().contains("fault file"), "{missing}");
        let _ = std::fs::remove_dir_all(dir);
    }

    #[test]
    fn lines_are_split_and_long_ones_reported() {
        let text = b"ab\ncdefgh\n\nlast";
        let mut r = std::io::BufReader::with_capacity(3, &text[..]);
        let mut buf = Vec::new();
        let mut got = Vec::new();
        loop {
            match read_line(&mut r, &mut buf, 4).unwrap() {
                Line::Eof => break,
                k => got.push((k, String::from_utf8(buf.clone()).unwrap())),
            }
        }
        assert_eq!(
            got,
            vec![
                (Line::Complete, "ab\n".into()),
                (Line::TooLong, "cdef".into()),
                (Line::Complete, "gh\n".into()),
                (Line::Complete, "\n".into()),
                (Line::Complete, "last".into()),
            ]
        );
        assert_eq!(human_bytes(1 << 20), "1 MiB");
        assert_eq!(human_bytes(100), "100 bytes");
    }
}
