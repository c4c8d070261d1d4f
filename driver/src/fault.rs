//! Deterministic fault injection on a transmit path (pure: no clock, no IO).
//!
//! A [`FaultInjector`] is fed every frame a sender puts on the bus, together with the send
//! time, and emits zero, one or two `(deliver_at, frame)` pairs:
//! - **drop** with probability `drop_prob` (nothing is emitted);
//! - **corrupt** with probability `corrupt_prob`: one payload bit chosen by the RNG is
//!   inverted (the protocol CRC-8 detects every single-bit error, so the receiver rejects it
//!   as a bad CRC);
//! - **delay**: `deliver_at = now + delay + U[0, jitter)`, and never earlier than the
//!   previous frame's delivery time: a CAN controller sends its queue in order, so jitter
//!   delays but never reorders one sender's frames;
//! - **duplicate** with probability `duplicate_prob`: the same frame is emitted twice at the
//!   same delivery time (as after a lost acknowledgement and automatic retransmission).
//!
//! Exactly five random numbers are drawn per frame whatever the model, so the fate of frame
//! k depends only on the seed and k: changing one probability does not reshuffle the others.

use std::time::Duration;

use crate::frame::CanFrame;
use crate::rng::Rng;

/// Probabilities and delays of the injected faults. `Default` injects nothing.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct FaultModel {
    /// Probability that a frame is lost, in [0, 1].
    pub drop_prob: f64,
    /// Probability that a frame is delivered twice, in [0, 1].
    pub duplicate_prob: f64,
    /// Probability that one payload bit is flipped, in [0, 1].
    pub corrupt_prob: f64,
    /// Fixed delivery delay.
    pub delay: Duration,
    /// Additional uniformly distributed delay in [0, jitter).
    pub jitter: Duration,
}

/// A [`FaultModel`] field is invalid.
#[derive(Debug, Clone, Copy, PartialEq, thiserror::Error)]
pub enum FaultModelError {
    /// A probability is outside [0, 1] or NaN.
    #[error("fault model {field} = {value} is not a probability; use a value in [0, 1]")]
    BadProbability {
        /// Field name.
        field: &'static str,
        /// Rejected value.
        value: f64,
    },
}

impl FaultModel {
    /// A model that injects nothing.
    pub fn none() -> FaultModel {
        FaultModel::default()
    }

    /// Checks that every probability lies in [0, 1].
    pub fn validate(&self) -> Result<(), FaultModelError> {
        for (field, value) in [
            ("drop_prob", self.drop_prob),
            ("duplicate_prob", self.duplicate_prob),
            ("corrupt_prob", self.corrupt_prob),
        ] {
            if !(0.0..=1.0).contains(&value) {
                return Err(FaultModelError::BadProbability { field, value });
            }
        }
        Ok(())
    }

    /// True when the model can change anything.
    pub fn is_active(&self) -> bool {
        self.drop_prob > 0.0
            || self.duplicate_prob > 0.0
            || self.corrupt_prob > 0.0
            || !self.delay.is_zero()
            || !self.jitter.is_zero()
    }
}

/// What a [`FaultInjector`] did so far.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct FaultStats {
    /// Frames fed in.
    pub frames: u64,
    /// Frames dropped.
    pub dropped: u64,
    /// Frames duplicated.
    pub duplicated: u64,
    /// Frames corrupted.
    pub corrupted: u64,
    /// Frames delivered later than sent.
    pub delayed: u64,
}

/// Applies a [`FaultModel`] deterministically from a seed.
#[derive(Debug, Clone)]
pub struct FaultInjector {
    model: FaultModel,
    rng: Rng,
    last_delivery: Duration,
    stats: FaultStats,
}

impl FaultInjector {
    /// An injector for `model` with its own RNG seeded by `seed`.
    ///
    /// Probabilities outside [0, 1] act as clamped (p ≤ 0 never, p ≥ 1 always); call
    /// [`FaultModel::validate`] first to reject them.
    pub fn new(model: FaultModel, seed: u64) -> FaultInjector {
        FaultInjector {
            model,
            rng: Rng::new(seed),
            last_delivery: Duration::ZERO,
            stats: FaultStats::default(),
        }
    }

    /// The model in use.
    pub fn model(&self) -> &FaultModel {
        &self.model
    }

    /// Replaces the model (the RNG stream continues).
    pub fn set_model(&mut self, model: FaultModel) {
        self.model = model;
    }

    /// Counts so far.
    pub fn stats(&self) -> &FaultStats {
        &self.stats
    }

    /// Feeds one frame sent at `now`; calls `out(deliver_at, frame)` zero, one or two times.
    pub fn apply(
        &mut self,
        now: Duration,
        frame: &CanFrame,
        out: &mut impl FnMut(Duration, CanFrame),
    ) {
        // Fixed number of draws per frame (see module docs).
        let u_drop = self.rng.next_f64();
        let u_corrupt = self.rng.next_f64();
        let bit_draw = self.rng.next_u64();
        let u_jitter = self.rng.next_f64();
        let u_dup = self.rng.next_f64();
        self.stats.frames += 1;
        if u_drop < self.model.drop_prob {
            self.stats.dropped += 1;
            return;
        }
        let mut f = *frame;
        if u_corrupt < self.model.corrupt_prob && !frame.is_empty() {
            let bits = frame.len() as u64 * 8;
            // bit < 64.
            f = frame.with_flipped_bit(((u128::from(bit_draw) * u128::from(bits)) >> 64) as usize);
            self.stats.corrupted += 1;
        }
        let jitter = self.model.jitter.mul_f64(u_jitter);
        let mut at = now.saturating_add(self.model.delay).saturating_add(jitter);
        if at < self.last_delivery {
            at = self.last_delivery;
        }
        self.last_delivery = at;
        if at > now {
            self.stats.delayed += 1;
        }
        out(at, f);
        if u_dup < self.model.duplicate_prob {
            self.stats.duplicated += 1;
            out(at, f);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn run(model: FaultModel, seed: u64, n: usize) -> Vec<(Duration, CanFrame)> {
        let mut inj = FaultInjector::new(model, seed);
        let mut out = Vec::new();
        for i in 0..n {
            let f = CanFrame::new(0x181, &[i as u8, 0, 0, 0, 0, 0, 0, 0]).expect("frame");
            inj.apply(Duration::from_millis(i as u64), &f, &mut |t, f| {
                out.push((t, f))
            });
        }
        out
    }

    #[test]
    fn no_faults_is_identity() {
        let out = run(FaultModel::none(), 1, 50);
        assert_eq!(out.len(), 50);
        for (i, (t, f)) in out.iter().enumerate() {
            assert_eq!(*t, Duration::from_millis(i as u64));
            assert_eq!(f.data()[0], i as u8);
        }
    }

    #[test]
    fn drop_rate_close_to_probability_and_seed_deterministic() {
        let m = FaultModel {
            drop_prob: 0.2,
            ..FaultModel::none()
        };
        let a = run(m, 9, 5000);
        let b = run(m, 9, 5000);
        let c = run(m, 10, 5000);
        assert_eq!(a, b);
        assert_ne!(a, c);
        // Binomial(5000, 0.8): mean 4000, sd 28.
        assert!((a.len() as i64 - 4000).abs() < 150, "delivered {}", a.len());
    }

    #[test]
    fn corruption_flips_exactly_one_bit() {
        let m = FaultModel {
            corrupt_prob: 1.0,
            ..FaultModel::none()
        };
        let out = run(m, 3, 200);
        assert_eq!(out.len(), 200);
        for (i, (_, f)) in out.iter().enumerate() {
            let orig = [i as u8, 0, 0, 0, 0, 0, 0, 0];
            let flipped: u32 = f
                .data()
                .iter()
                .zip(orig.iter())
                .map(|(a, b)| (a ^ b).count_ones())
                .sum();
            assert_eq!(flipped, 1, "frame {i}");
        }
    }

    #[test]
    fn jitter_never_reorders_and_delay_applies() {
        let m = FaultModel {
            delay: Duration::from_micros(300),
            jitter: Duration::from_millis(3),
            ..FaultModel::none()
        };
        let out = run(m, 5, 500);
        assert_eq!(out.len(), 500);
        for (i, w) in out.windows(2).enumerate() {
            assert!(w[1].0 >= w[0].0, "reordered at {i}");
        }
        for (i, (t, _)) in out.iter().enumerate() {
            assert!(*t >= Duration::from_millis(i as u64) + Duration::from_micros(300));
        }
        // Frames keep send order.
        for (i, (_, f)) in out.iter().enumerate() {
            assert_eq!(f.data()[0], i as u8);
        }
    }

    #[test]
    fn duplicates_arrive_back_to_back() {
        let m = FaultModel {
            duplicate_prob: 0.5,
            ..FaultModel::none()
        };
        let mut inj = FaultInjector::new(m, 11);
        let mut dup = 0;
        for i in 0..1000u32 {
            let f = CanFrame::new(0x80, &[i as u8]).expect("frame");
            let mut got = Vec::new();
            inj.apply(Duration::from_millis(u64::from(i)), &f, &mut |t, f| {
                got.push((t, f))
            });
            assert!(got.iter().all(|&(_, g)| g == f));
            if got.len() == 2 {
                dup += 1;
                assert_eq!(got[0].0, got[1].0);
            }
        }
        assert_eq!(inj.stats().duplicated, dup);
        assert!((dup as i64 - 500).abs() < 80, "duplicated {dup}");
    }

    #[test]
    fn validate_names_the_field() {
        let m = FaultModel {
            corrupt_prob: 1.5,
            ..FaultModel::none()
        };
        let e = m.validate().expect_err("must fail");
        assert!(e.to_string().contains("corrupt_prob"));
        assert!(FaultModel::none().validate().is_ok());
        let nan = FaultModel {
            drop_prob: f64::NAN,
            ..FaultModel::none()
        };
        assert!(nan.validate().is_err());
    }
}
