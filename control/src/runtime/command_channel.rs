//! The command port's channel: from the command sources (files, stdin, keyboard, ROS 2) to
//! the cycle thread, with a priority lane.
//!
//! ```text
//!  sources ── try_send ──┬─ Motion, Legs ──────────► motion queue (bounded; full: dropped, counted)
//!                        └─ Stop, Rearm, EndOfStream, Shutdown ─► priority lane (bounded)
//!                                                                  full: coalesced, never lost
//!  cycle ── take(max) ── priority lane first (all of it), then ≤ max motion commands
//! ```
//!
//! A stop or a re-arm never waits behind motion commands: the cycle takes every request of the
//! lane before any motion command, so a burst of motion lines (or a producer that floods the
//! queue) can neither drop nor delay them. A full motion queue drops the new command and
//! counts it ([`CommandReceiver::dropped`]; the cycle's records and the state port carry the
//! count, the run summary reports it as `dropped_commands`).
//!
//! The lane is bounded too. Should more requests arrive between two cycles than it holds,
//! the newest of stop and re-arm is kept in one slot (the operator's latest word) together
//! with "end of stream" and "shutdown" flags, and the cycle applies that slot right after the
//! lane's queued requests, which were all sent before it: the order of what acts is the
//! order of sending, and nothing a source asked last is lost.
//!
//! The cycle thread never blocks and never takes a lock here: both queues are
//! `std::sync::mpsc::sync_channel`s, whose non-blocking receive takes no lock as long as no
//! sender is blocked in `send` (senders here only use `try_send`); the senders serialise
//! their access to the overflow slot with a mutex only they use. Nothing here allocates after
//! construction.

use crate::service::ports::{CommandEvent, CommandKind};
use std::sync::atomic::{AtomicU64, AtomicU8, Ordering};
use std::sync::mpsc::{Receiver, SyncSender, TryRecvError, TrySendError};
use std::sync::{Arc, Mutex};

/// Motion commands the queue holds (the cycle takes up to
/// [`super::MAX_COMMANDS_PER_CYCLE`] a cycle).
pub const MOTION_QUEUE: usize = 256;
/// Requests (stop, re-arm, end of stream, shutdown) the priority lane holds.
pub const PRIORITY_LANE: usize = 64;

// The overflow slot: bits 0–1 the newest of stop (1) and re-arm (2), bit 2 end of stream,
// bit 3 shutdown.
const SLOT_STOP: u8 = 1;
const SLOT_REARM: u8 = 2;
const SLOT_LAST: u8 = 3;
const SLOT_END: u8 = 4;
const SLOT_SHUTDOWN: u8 = 8;

#[derive(Debug, Default)]
struct Shared {
    dropped: AtomicU64,
    coalesced: AtomicU64,
    slot: AtomicU8,
    senders: Mutex<()>,
}

/// The sending side (cheap to clone; one per source).
#[derive(Clone, Debug)]
pub struct CommandSender {
    motion: SyncSender<CommandEvent>,
    lane: SyncSender<CommandEvent>,
    shared: Arc<Shared>,
}

/// The cycle's side.
#[derive(Debug)]
pub struct CommandReceiver {
    motion: Receiver<CommandEvent>,
    lane: Receiver<CommandEvent>,
    shared: Arc<Shared>,
    lane_capacity: usize,
}

/// A command channel holding `motion` motion commands and `lane` priority requests (each at
/// least 1).
pub fn command_channel(motion: usize, lane: usize) -> (CommandSender, CommandReceiver) {
    let (mtx, mrx) = std::sync::mpsc::sync_channel(motion.max(1));
    let (ltx, lrx) = std::sync::mpsc::sync_channel(lane.max(1));
    let shared = Arc::new(Shared::default());
    (
        CommandSender {
            motion: mtx,
            lane: ltx,
            shared: shared.clone(),
        },
        CommandReceiver {
            motion: mrx,
            lane: lrx,
            shared,
            lane_capacity: lane.max(1),
        },
    )
}

/// Whether a command goes through the priority lane.
pub fn is_priority(kind: &CommandKind) -> bool {
    !matches!(kind, CommandKind::Motion(_) | CommandKind::Legs(_))
}

impl CommandSender {
    /// Queues a command without blocking. A motion command finding its queue full is dropped,
    /// counted and returned in `Err(Full)`; a priority request is never refused while the
    /// cycle takes commands (see the module docs). `Err(Disconnected)` once the cycle is gone.
    pub fn try_send(&self, ev: CommandEvent) -> Result<(), TrySendError<CommandEvent>> {
        if !is_priority(&ev.kind) {
            return match self.motion.try_send(ev) {
                Err(TrySendError::Full(ev)) => {
                    self.shared.dropped.fetch_add(1, Ordering::Relaxed);
                    Err(TrySendError::Full(ev))
                }
                r => r,
            };
        }
        // Senders only: the cycle never takes this lock.
        let _g = self
            .shared
            .senders
            .lock()
            .unwrap_or_else(|e| e.into_inner());
        if self.shared.slot.load(Ordering::Acquire) == 0 {
            match self.lane.try_send(ev) {
                Ok(()) => return Ok(()),
                Err(TrySendError::Disconnected(ev)) => return Err(TrySendError::Disconnected(ev)),
                Err(TrySendError::Full(_)) => {}
            }
        }
        let bits = match ev.kind {
            CommandKind::Stop => SLOT_STOP,
            CommandKind::Rearm => SLOT_REARM,
            CommandKind::EndOfStream => SLOT_END,
            _ => SLOT_SHUTDOWN,
        };
        let _ = self
            .shared
            .slot
            .fetch_update(Ordering::AcqRel, Ordering::Acquire, |s| {
                Some(if bits & SLOT_LAST != 0 {
                    (s & !SLOT_LAST) | bits
                } else {
                    s | bits
                })
            });
        self.shared.coalesced.fetch_add(1, Ordering::Relaxed);
        Ok(())
    }

    /// Motion commands dropped so far because their queue was full.
    pub fn dropped(&self) -> u64 {
        self.shared.dropped.load(Ordering::Relaxed)
    }

    /// Counts a command its source had to drop before sending it (e.g. a timed line that found
    /// the source's own schedule full), so that the run's `dropped` count has it.
    pub fn note_dropped(&self) {
        self.shared.dropped.fetch_add(1, Ordering::Relaxed);
    }
}

impl CommandReceiver {
    /// Hands every waiting priority request to `f`, in the order sent, then at most `max`
    /// motion commands. Never blocks, takes no lock, allocates nothing.
    pub fn take(&self, max: usize, mut f: impl FnMut(CommandEvent)) {
        // Read the slot first: while it is set no sender adds to the lane, so the lane's
        // requests all came before it and are drained completely below (module docs).
        let slot_seen = self.shared.slot.load(Ordering::Acquire);
        for _ in 0..self.lane_capacity {
            match self.lane.try_recv() {
                Ok(ev) => f(ev),
                Err(TryRecvError::Empty | TryRecvError::Disconnected) => break,
            }
        }
        if slot_seen != 0 {
            let s = self.shared.slot.swap(0, Ordering::AcqRel);
            let kind = |kind| CommandEvent { t: 0.0, kind };
            match s & SLOT_LAST {
                SLOT_STOP => f(kind(CommandKind::Stop)),
                SLOT_REARM => f(kind(CommandKind::Rearm)),
                _ => {}
            }
            if s & SLOT_END != 0 {
                f(kind(CommandKind::EndOfStream));
            }
            if s & SLOT_SHUTDOWN != 0 {
                f(kind(CommandKind::Shutdown));
            }
        }
        for _ in 0..max {
            match self.motion.try_recv() {
                Ok(ev) => f(ev),
                Err(_) => break,
            }
        }
    }

    /// Motion commands dropped so far because their queue was full.
    pub fn dropped(&self) -> u64 {
        self.shared.dropped.load(Ordering::Relaxed)
    }

    /// Priority requests that found the lane full and were coalesced into its overflow slot.
    pub fn coalesced(&self) -> u64 {
        self.shared.coalesced.load(Ordering::Relaxed)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::service::ports::MotionCommand;

    fn motion(vx: f64) -> CommandEvent {
        let mut m = MotionCommand::default();
        m.twist.vx = vx;
        CommandEvent {
            t: 0.0,
            kind: CommandKind::Motion(m),
        }
    }

    fn ev(kind: CommandKind) -> CommandEvent {
        CommandEvent { t: 0.0, kind }
    }

    fn take_all(rx: &CommandReceiver, max: usize) -> Vec<CommandKind> {
        let mut v = Vec::new();
        rx.take(max, |e| v.push(e.kind));
        v
    }

    #[test]
    fn a_stop_behind_a_full_motion_queue_is_taken_first_and_drops_are_counted() {
        let (tx, rx) = command_channel(8, 4);
        for k in 0..20 {
            let r = tx.try_send(motion(k as f64));
            assert_eq!(r.is_ok(), k < 8, "command {k}");
        }
        tx.try_send(ev(CommandKind::Stop))
            .expect("a stop is never refused");
        for k in 0..5 {
            let _ = tx.try_send(motion(100.0 + k as f64));
        }
        assert_eq!(tx.dropped(), 17);
        assert_eq!(rx.dropped(), 17);
        let got = take_all(&rx, 3);
        assert_eq!(got[0], CommandKind::Stop, "{got:?}");
        assert_eq!(
            got.len(),
            4,
            "the stop, then at most 3 motion commands: {got:?}"
        );
        assert!(matches!(got[1], CommandKind::Motion(m) if m.twist.vx == 0.0));
    }

    #[test]
    fn a_flood_of_requests_beyond_the_lane_keeps_the_order_and_the_last_word() {
        let (tx, rx) = command_channel(4, 2);
        // Lane of 2: stop, rearm fit; the rest coalesce (the newest of stop/rearm, and the
        // end of the stream).
        for k in [
            CommandKind::Stop,
            CommandKind::Rearm,
            CommandKind::Stop,
            CommandKind::EndOfStream,
            CommandKind::Rearm,
            CommandKind::Stop,
        ] {
            tx.try_send(ev(k)).unwrap();
        }
        assert_eq!(rx.coalesced(), 4);
        let got = take_all(&rx, 64);
        assert_eq!(
            got,
            vec![
                CommandKind::Stop,
                CommandKind::Rearm,
                CommandKind::Stop,
                CommandKind::EndOfStream
            ]
        );
        // The slot is empty again; the lane takes requests in order once more.
        tx.try_send(ev(CommandKind::Rearm)).unwrap();
        assert_eq!(take_all(&rx, 64), vec![CommandKind::Rearm]);
        assert!(take_all(&rx, 64).is_empty());
    }

    #[test]
    fn requests_from_several_threads_all_arrive_or_are_coalesced_never_lost() {
        let (tx, rx) = command_channel(16, 8);
        let senders: Vec<_> = (0..4)
            .map(|i| {
                let tx = tx.clone();
                std::thread::spawn(move || {
                    for k in 0..2000 {
                        let kind = if (k + i) % 2 == 0 {
                            CommandKind::Stop
                        } else {
                            CommandKind::Rearm
                        };
                        tx.try_send(ev(kind)).unwrap();
                        let _ = tx.try_send(motion(k as f64));
                    }
                    tx.try_send(ev(CommandKind::Stop)).unwrap();
                })
            })
            .collect();
        let mut requests = 0u64;
        let mut last = None;
        let mut drain = |rx: &CommandReceiver| {
            rx.take(64, |e| {
                if is_priority(&e.kind) {
                    requests += 1;
                    last = Some(e.kind);
                }
            })
        };
        while senders.iter().any(|s| !s.is_finished()) {
            drain(&rx);
        }
        for s in senders {
            s.join().unwrap();
        }
        drain(&rx);
        drain(&rx);
        // Each request was taken or coalesced into a taken slot; every sender's last word is
        // a stop, so the last request the cycle took is a stop.
        assert!(
            requests + rx.coalesced() >= 4 * 2001,
            "{requests} + {}",
            rx.coalesced()
        );
        assert_eq!(last, Some(CommandKind::Stop));
    }
}
