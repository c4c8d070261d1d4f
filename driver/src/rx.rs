//! The stateful receive path: decode plus rolling-counter supervision and statistics.
//!
//! Each stream (message kind, node) has its own 4-bit rolling counter. Rules:
//! - The first frame of a stream (or the first after [`Receiver::reset_stream`]) is accepted
//!   whatever its counter.
//! - Then the counter must be `(last + 1) mod 16`.
//! - `counter == last` is a repeated (stale or duplicated) frame: rejected as
//!   [`RxError::RepeatedCounter`] under every policy; the stream state is unchanged.
//! - Any other counter is a skip: `lost = (got − last − 1) mod 16` frames went missing
//!   (modulo 16, so 16 or more consecutive losses are undetectable by the counter alone; the
//!   caller's staleness timeout covers that). The stream re-synchronises to `got`, so the next
//!   in-sequence frame is accepted. With [`CounterPolicy::RejectSkipped`] (the default) the
//!   skipping frame itself is rejected as [`RxError::SkippedCounter`]; with
//!   [`CounterPolicy::AcceptWithLoss`] it is returned as `Ok` (AUTOSAR E2E's "OK, some data
//!   lost") and only counted in [`RxStats::skipped`] / [`RxStats::lost`].
//!
//! Frames that fail [`decode`] do not touch the stream state. No allocation per frame.

use crate::codec::{decode, DecodeError, Message};
use crate::frame::CanFrame;
use crate::protocol::{MessageKind, MAX_NODE};

/// Why the receiver rejected a frame.
#[derive(Debug, Clone, Copy, PartialEq, Eq, thiserror::Error)]
pub enum RxError {
    /// The frame did not decode.
    #[error(transparent)]
    Decode(#[from] DecodeError),
    /// Same counter as the previous frame of the stream (stale or duplicated frame).
    #[error("{kind} node {node}: repeated rolling counter {counter} (stale or duplicated frame), frame dropped")]
    RepeatedCounter {
        /// Message kind.
        kind: MessageKind,
        /// Node (0 for SYNC).
        node: u8,
        /// The repeated counter.
        counter: u8,
    },
    /// The counter jumped: frames were lost.
    #[error("{kind} node {node}: rolling counter jumped from expected {expected} to {got}, {lost} frame(s) lost")]
    SkippedCounter {
        /// Message kind.
        kind: MessageKind,
        /// Node (0 for SYNC).
        node: u8,
        /// Counter that was expected.
        expected: u8,
        /// Counter received.
        got: u8,
        /// Frames lost: `(got − last − 1) mod 16`.
        lost: u8,
    },
}

/// Counts of accepted and rejected frames, by reason.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct RxStats {
    /// Frames returned as `Ok`.
    pub accepted: u64,
    /// [`DecodeError::BadCrc`].
    pub bad_crc: u64,
    /// [`DecodeError::WrongDlc`].
    pub wrong_dlc: u64,
    /// [`DecodeError::UnknownId`].
    pub unknown_id: u64,
    /// [`DecodeError::OutOfRange`].
    pub out_of_range: u64,
    /// [`RxError::RepeatedCounter`].
    pub repeated: u64,
    /// Counter skips (rejected, or accepted under [`CounterPolicy::AcceptWithLoss`]).
    pub skipped: u64,
    /// Sum of the `lost` frame counts of all skips.
    pub lost: u64,
    /// Other decode errors ([`DecodeError::BadNode`], [`DecodeError::BadEnum`]).
    pub other: u64,
}

impl RxStats {
    /// All rejected frames (every counter except `accepted` and `lost`; a skip accepted under
    /// [`CounterPolicy::AcceptWithLoss`] is counted in `skipped` but was not rejected, so this
    /// is an upper bound in that mode).
    pub fn rejected(&self) -> u64 {
        self.bad_crc
            + self.wrong_dlc
            + self.unknown_id
            + self.out_of_range
            + self.repeated
            + self.skipped
            + self.other
    }
}

/// What to do with a frame whose counter skipped ahead.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub enum CounterPolicy {
    /// Reject it as [`RxError::SkippedCounter`] (and re-synchronise).
    #[default]
    RejectSkipped,
    /// Accept it, counting the loss (AUTOSAR E2E "OK, some lost").
    AcceptWithLoss,
}

const NO_COUNTER: u8 = 0xFF;
const STREAMS_PER_KIND: usize = MAX_NODE as usize + 1;

/// Stateful receiver: decode + rolling-counter check + statistics.
#[derive(Debug, Clone)]
pub struct Receiver {
    last: [[u8; STREAMS_PER_KIND]; MessageKind::ALL.len()],
    policy: CounterPolicy,
    stats: RxStats,
}

impl Default for Receiver {
    fn default() -> Self {
        Self::new()
    }
}

impl Receiver {
    /// A receiver with [`CounterPolicy::RejectSkipped`] and no stream history.
    pub fn new() -> Self {
        Self::with_policy(CounterPolicy::RejectSkipped)
    }

    /// A receiver with the given skip policy.
    pub fn with_policy(policy: CounterPolicy) -> Self {
        Receiver {
            last: [[NO_COUNTER; STREAMS_PER_KIND]; MessageKind::ALL.len()],
            policy,
            stats: RxStats::default(),
        }
    }

    /// The skip policy.
    pub fn policy(&self) -> CounterPolicy {
        self.policy
    }

    /// Decodes `frame` and checks its rolling counter; updates the statistics.
    pub fn accept(&mut self, frame: &CanFrame) -> Result<Message, RxError> {
        let msg = match decode(frame) {
            Ok(m) => m,
            Err(e) => {
                let s = &mut self.stats;
                match e {
                    DecodeError::BadCrc { .. } => s.bad_crc += 1,
                    DecodeError::WrongDlc { .. } => s.wrong_dlc += 1,
                    DecodeError::UnknownId { .. } => s.unknown_id += 1,
                    DecodeError::OutOfRange { .. } => s.out_of_range += 1,
                    DecodeError::BadNode { .. } | DecodeError::BadEnum { .. } => s.other += 1,
                }
                return Err(RxError::Decode(e));
            }
        };
        let kind = msg.kind();
        let node = msg.node;
        let got = msg.counter;
        let slot = &mut self.last[kind.index()][usize::from(node & MAX_NODE)];
        let last = *slot;
        if last == NO_COUNTER {
            *slot = got;
            self.stats.accepted += 1;
            return Ok(msg);
        }
        let expected = (last + 1) & 0x0F;
        if got == expected {
            *slot = got;
            self.stats.accepted += 1;
            return Ok(msg);
        }
        if got == last {
            self.stats.repeated += 1;
            return Err(RxError::RepeatedCounter {
                kind,
                node,
                counter: got,
            });
        }
        let lost = got.wrapping_sub(last).wrapping_sub(1) & 0x0F;
        *slot = got;
        self.stats.skipped += 1;
        self.stats.lost += u64::from(lost);
        match self.policy {
            CounterPolicy::RejectSkipped => Err(RxError::SkippedCounter {
                kind,
                node,
                expected,
                got,
                lost,
            }),
            CounterPolicy::AcceptWithLoss => {
                self.stats.accepted += 1;
                Ok(msg)
            }
        }
    }

    /// Statistics since creation (or [`reset_stats`](Self::reset_stats)).
    pub fn stats(&self) -> &RxStats {
        &self.stats
    }

    /// Zeroes the statistics (stream state is kept).
    pub fn reset_stats(&mut self) {
        self.stats = RxStats::default();
    }

    /// Forgets the counter history of one stream: its next frame is accepted whatever its
    /// counter (use after a module reboot or a deliberate pause).
    pub fn reset_stream(&mut self, kind: MessageKind, node: u8) {
        self.last[kind.index()][usize::from(node & MAX_NODE)] = NO_COUNTER;
    }

    /// Forgets the counter history of every stream.
    pub fn reset_all_streams(&mut self) {
        self.last = [[NO_COUNTER; STREAMS_PER_KIND]; MessageKind::ALL.len()];
    }
}
