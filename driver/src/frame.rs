//! Checked classic CAN 2.0A frames.
//!
//! [`CanFrame`] is a newtype that can only hold what a classic base-format data frame can
//! carry on the wire: an 11-bit identifier (≤ 0x7FF) and 0..=8 data bytes. Every value of the
//! type is therefore valid, and the rest of the crate never re-checks it.

use std::time::Duration;

/// Largest 11-bit (CAN 2.0A, base format) identifier.
pub const MAX_STANDARD_ID: u16 = 0x7FF;
/// Largest classic CAN payload, in bytes.
pub const MAX_DATA_LEN: usize = 8;

/// Why a [`CanFrame`] could not be built.
#[derive(Debug, Clone, Copy, PartialEq, Eq, thiserror::Error)]
pub enum FrameError {
    /// The identifier does not fit 11 bits.
    #[error("CAN id 0x{id:X} does not fit 11 bits (max 0x7FF); rollbase uses classic base-format ids only")]
    IdOutOfRange {
        /// The rejected identifier.
        id: u32,
    },
    /// More than 8 data bytes were given.
    #[error("CAN payload of {len} bytes is longer than the classic CAN maximum of 8 bytes")]
    TooLong {
        /// The rejected length.
        len: usize,
    },
}

/// A classic CAN 2.0A data frame: 11-bit id and up to 8 data bytes.
///
/// Bytes beyond `len` are always zero, so the derived equality and hash only depend on
/// the id and the `len` meaningful bytes.
#[derive(Copy, Clone, Debug, PartialEq, Eq, Hash)]
pub struct CanFrame {
    id: u16,
    len: u8,
    data: [u8; MAX_DATA_LEN],
}

impl CanFrame {
    /// Builds a frame; fails when `id > 0x7FF` or `data.len() > 8`.
    pub fn new(id: u16, data: &[u8]) -> Result<CanFrame, FrameError> {
        if id > MAX_STANDARD_ID {
            return Err(FrameError::IdOutOfRange { id: u32::from(id) });
        }
        if data.len() > MAX_DATA_LEN {
            return Err(FrameError::TooLong { len: data.len() });
        }
        let mut buf = [0u8; MAX_DATA_LEN];
        buf[..data.len()].copy_from_slice(data);
        Ok(CanFrame {
            id,
            // data.len() <= 8 was checked above.
            len: data.len() as u8,
            data: buf,
        })
    }

    /// The 11-bit identifier.
    pub fn id(&self) -> u16 {
        self.id
    }

    /// The `len()` data bytes.
    pub fn data(&self) -> &[u8] {
        &self.data[..usize::from(self.len)]
    }

    /// Number of data bytes (the DLC of a classic frame), 0..=8.
    pub fn len(&self) -> usize {
        usize::from(self.len)
    }

    /// True when the frame carries no data bytes.
    pub fn is_empty(&self) -> bool {
        self.len == 0
    }

    /// Returns a copy with bit `bit` (0 = LSB of byte 0) of the payload inverted.
    ///
    /// Used by fault injection; a `bit` beyond the payload leaves the frame unchanged.
    pub fn with_flipped_bit(&self, bit: usize) -> CanFrame {
        let mut out = *self;
        if bit < self.len() * 8 {
            out.data[bit / 8] ^= 1 << (bit % 8);
        }
        out
    }
}

/// A frame together with the bus time at which it was on the wire.
///
/// For the virtual bus the timestamp is the bus clock (virtual time, or time since the bus
/// was created in wall-clock mode); for SocketCAN it is the kernel receive time (or the
/// receive time read from `CLOCK_REALTIME`) as a duration since the Unix epoch.
#[derive(Copy, Clone, Debug, PartialEq, Eq, Hash)]
pub struct TimestampedFrame {
    /// Bus time of the frame.
    pub timestamp: Duration,
    /// The frame.
    pub frame: CanFrame,
}

/// Largest number of frames one call of the cycle may emit (SYNC, heartbeat, NMT and SDO
/// requests of up to 24 devices, or the setpoints of 8 wheels).
pub const FRAME_BUF_CAPACITY: usize = 64;

/// A fixed-capacity list of frames to send, so the cycle never allocates. Frames pushed
/// beyond the capacity are counted in [`FrameBuf::overflow`], never silently lost.
#[derive(Clone, Debug)]
pub struct FrameBuf {
    frames: [CanFrame; FRAME_BUF_CAPACITY],
    len: usize,
    overflow: u32,
}

impl Default for FrameBuf {
    fn default() -> Self {
        Self::new()
    }
}

impl FrameBuf {
    /// An empty buffer.
    pub fn new() -> Self {
        // Id 0 with no data is a valid classic frame.
        let blank = CanFrame {
            id: 0,
            len: 0,
            data: [0; MAX_DATA_LEN],
        };
        Self {
            frames: [blank; FRAME_BUF_CAPACITY],
            len: 0,
            overflow: 0,
        }
    }

    /// Appends a frame; returns false (and counts it) when the buffer is full.
    pub fn push(&mut self, f: CanFrame) -> bool {
        if self.len < FRAME_BUF_CAPACITY {
            self.frames[self.len] = f;
            self.len += 1;
            true
        } else {
            self.overflow = self.overflow.saturating_add(1);
            false
        }
    }

    /// The frames, in the order pushed.
    pub fn as_slice(&self) -> &[CanFrame] {
        &self.frames[..self.len]
    }

    /// Number of frames.
    pub fn len(&self) -> usize {
        self.len
    }

    /// True when no frame was pushed.
    pub fn is_empty(&self) -> bool {
        self.len == 0
    }

    /// Empties the buffer (the overflow count is kept).
    pub fn clear(&mut self) {
        self.len = 0;
    }

    /// Frames refused because the buffer was full, since creation.
    pub fn overflow(&self) -> u32 {
        self.overflow
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn rejects_29_bit_ids_and_long_payloads() {
        assert_eq!(
            CanFrame::new(0x800, &[]),
            Err(FrameError::IdOutOfRange { id: 0x800 })
        );
        assert_eq!(
            CanFrame::new(0x100, &[0; 9]),
            Err(FrameError::TooLong { len: 9 })
        );
        let f = CanFrame::new(0x7FF, &[1, 2, 3]).expect("valid frame");
        assert_eq!(f.id(), 0x7FF);
        assert_eq!(f.data(), &[1, 2, 3]);
        assert_eq!(f.len(), 3);
    }

    #[test]
    fn frame_buf_is_bounded_and_counts_overflow() {
        let mut b = FrameBuf::new();
        let f = CanFrame::new(0x80, &[]).expect("valid");
        for _ in 0..FRAME_BUF_CAPACITY {
            assert!(b.push(f));
        }
        assert!(!b.push(f));
        assert_eq!((b.len(), b.overflow()), (FRAME_BUF_CAPACITY, 1));
        b.clear();
        assert!(b.is_empty());
        assert_eq!(b.overflow(), 1);
    }

    #[test]
    fn equality_ignores_nothing_but_unused_bytes() {
        let a = CanFrame::new(0x10, &[1, 2]).expect("valid");
        let b = CanFrame::new(0x10, &[1, 2, 0]).expect("valid");
        assert_ne!(a, b, "different DLC must differ");
        assert_eq!(a.with_flipped_bit(9).data(), &[1, 0]);
        assert_eq!(a.with_flipped_bit(16), a, "bit beyond payload is a no-op");
    }
}
