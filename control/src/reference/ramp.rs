//! A rest-to-rest motion of one scalar parameter from 0 to 1 under position-dependent
//! velocity and acceleration caps: the time-optimal profile on a grid (the classic forward /
//! backward pass of path-velocity planning, here in one dimension), executed on a clock, and
//! able to brake to rest at any moment within its acceleration caps.
//!
//! It is the one profile generator behind the shaper's transitions ([`crate::reference::shaper`]) and
//! the time scaling of trajectories ([`crate::reference::timescale`]).
//!
//! # Planning
//!
//! Grid points 0 = s_0 < s_1 < … < s_{k−1} = 1 with a velocity cap v̄_j at each point and an
//! acceleration cap ā_j on each segment [s_j, s_{j+1}]. With x = ṡ², a constant acceleration
//! a on a segment makes x linear in s (x' = 2a), so:
//!
//! ```text
//! forward:   v_0 = 0,      v_{j+1} = min(v̄_{j+1}, √(v_j² + 2 ā_j Δs_j))
//! backward:  v_{k−1} = 0,  v_j     = min(v_j,     √(v_{j+1}² + 2 ā_j Δs_j))
//! segment:   a_j = (v_{j+1}² − v_j²) / (2 Δs_j),  Δt_j = 2 Δs_j / (v_j + v_{j+1})
//! ```
//!
//! |a_j| ≤ ā_j on every segment and v_j ≤ v̄_j at every point: the profile never exceeds a
//! cap at the grid points, and between them the acceleration is constant. The caller puts
//! grid points where its caps change quickly.
//!
//! # Execution and braking
//!
//! [`Ramp::advance`] moves the clock by dt and returns (s, ṡ, s̈) exactly on the planned
//! piecewise-constant-acceleration profile. [`Ramp::brake`] switches to stopping as soon
//! as the caps allow: from then on ṡ decreases at the acceleration cap of the segment it is
//! in (never more), so ṡ stays continuous and the parameter comes to rest short of 1. No
//! allocation: fixed arrays of [`GRID`] points.

/// Largest number of grid points of a ramp.
pub const GRID: usize = 192;

/// Velocities below this are treated as rest (1/s in the parameter).
const V_EPS: f64 = 1e-12;

/// A planned rest-to-rest profile of a parameter s ∈ [0, 1] and its execution state.
#[derive(Clone, Copy, Debug)]
pub struct Ramp {
    k: usize,
    s: [f64; GRID],
    v: [f64; GRID],
    a: [f64; GRID],
    t: [f64; GRID],
    acap: [f64; GRID],
    seg: usize,
    tau: f64,
    pos: f64,
    vel: f64,
    acc: f64,
    braking: bool,
    done: bool,
}

impl Default for Ramp {
    fn default() -> Self {
        Self {
            k: 0,
            s: [0.0; GRID],
            v: [0.0; GRID],
            a: [0.0; GRID],
            t: [0.0; GRID],
            acap: [0.0; GRID],
            seg: 0,
            tau: 0.0,
            pos: 0.0,
            vel: 0.0,
            acc: 0.0,
            braking: false,
            done: true,
        }
    }
}

impl Ramp {
    /// Plans the profile. `s` are the grid points (ascending, first 0, last 1; at most
    /// [`GRID`]), `vcap[j]` the velocity cap at `s[j]`, `acap[j]` the acceleration cap on the
    /// segment from `s[j]` to `s[j+1]` (the last entry is unused). Non-finite or
    /// non-positive caps are floored to a tiny positive value (the profile then crawls
    /// there instead of stalling).
    pub fn plan(s: &[f64], vcap: &[f64], acap: &[f64]) -> Self {
        let mut r = Ramp::default();
        let k = s.len().min(vcap.len()).min(acap.len()).min(GRID);
        if k < 2 {
            return r;
        }
        let floor = |x: f64| if x.is_finite() && x > 1e-12 { x } else { 1e-12 };
        r.k = k;
        for j in 0..k {
            r.s[j] = s[j];
            r.v[j] = floor(vcap[j]);
            r.acap[j] = floor(acap[j]);
        }
        r.v[0] = 0.0;
        for j in 0..k - 1 {
            let ds = (r.s[j + 1] - r.s[j]).max(0.0);
            let reach = (r.v[j] * r.v[j] + 2.0 * r.acap[j] * ds).sqrt();
            r.v[j + 1] = r.v[j + 1].min(reach);
        }
        r.v[k - 1] = 0.0;
        for j in (0..k - 1).rev() {
            let ds = (r.s[j + 1] - r.s[j]).max(0.0);
            let reach = (r.v[j + 1] * r.v[j + 1] + 2.0 * r.acap[j] * ds).sqrt();
            r.v[j] = r.v[j].min(reach);
        }
        r.t[0] = 0.0;
        for j in 0..k - 1 {
            let ds = (r.s[j + 1] - r.s[j]).max(0.0);
            let (v0, v1) = (r.v[j], r.v[j + 1]);
            if ds <= 0.0 {
                r.a[j] = 0.0;
                r.t[j + 1] = r.t[j];
                continue;
            }
            r.a[j] = (v1 * v1 - v0 * v0) / (2.0 * ds);
            let sum = v0 + v1;
            r.t[j + 1] = r.t[j] + if sum > V_EPS { 2.0 * ds / sum } else { 0.0 };
        }
        r.done = false;
        r
    }

    /// The planned velocity at the `j`-th grid point (0 past the last).
    pub fn planned_velocity(&self, j: usize) -> f64 {
        if j < self.k {
            self.v[j]
        } else {
            0.0
        }
    }

    /// Duration of the planned profile (s).
    pub fn duration(&self) -> f64 {
        if self.k < 2 {
            0.0
        } else {
            self.t[self.k - 1]
        }
    }

    /// The parameter, its rate and acceleration now.
    pub fn state(&self) -> (f64, f64, f64) {
        (self.pos, self.vel, self.acc)
    }

    /// True once the parameter is at rest at the end (or where braking stopped it).
    pub fn done(&self) -> bool {
        self.done
    }

    /// True while braking.
    pub fn braking(&self) -> bool {
        self.braking
    }

    /// Largest velocity of the planned profile.
    pub fn peak_velocity(&self) -> f64 {
        self.v[..self.k].iter().copied().fold(0.0, f64::max)
    }

    /// ∫ s dt over the whole planned profile (for distances covered by quantities that fade
    /// with s, e.g. a leg rate scaled by (1 − s)).
    pub fn integral_of_s(&self) -> f64 {
        let mut sum = 0.0;
        for j in 0..self.k.saturating_sub(1) {
            let dt = self.t[j + 1] - self.t[j];
            // s(t) = s_j + v_j τ + a_j τ²/2 integrated over [0, dt].
            sum += self.s[j] * dt + 0.5 * self.v[j] * dt * dt + self.a[j] * dt * dt * dt / 6.0;
        }
        sum
    }

    /// Time (s) [`Ramp::brake`] would take to bring the parameter to rest from now, at the
    /// acceleration cap of the current segment.
    pub fn brake_time(&self) -> f64 {
        if self.done || self.k < 2 {
            return 0.0;
        }
        let a = self.acap[self.segment_of(self.pos)];
        if a > 0.0 {
            self.vel / a
        } else {
            0.0
        }
    }

    /// Stops as soon as the acceleration caps allow (see the module docs).
    pub fn brake(&mut self) {
        if !self.done {
            self.braking = true;
        }
    }

    /// Advances the clock by `dt` seconds; returns (s, ṡ, s̈) at the new time.
    pub fn advance(&mut self, dt: f64) -> (f64, f64, f64) {
        if self.done || self.k < 2 || dt.is_nan() || dt <= 0.0 {
            self.vel = 0.0;
            self.acc = 0.0;
            return self.state();
        }
        if self.braking {
            // Decelerate at the cap of the segment we are in.
            let j = self.segment_of(self.pos);
            let d = self.acap[j];
            let v1 = (self.vel - d * dt).max(0.0);
            let used = if d > 0.0 { (self.vel - v1) / d } else { dt };
            self.pos += 0.5 * (self.vel + v1) * used;
            self.vel = v1;
            self.acc = -d;
            if self.pos >= 1.0 {
                self.pos = 1.0;
                self.vel = 0.0;
            }
            if self.vel <= V_EPS {
                self.vel = 0.0;
                self.acc = 0.0;
                self.done = true;
            }
            return self.state();
        }
        self.tau += dt;
        let end = self.t[self.k - 1];
        if self.tau >= end {
            self.pos = 1.0;
            self.vel = 0.0;
            self.acc = 0.0;
            self.done = true;
            return self.state();
        }
        while self.seg + 1 < self.k - 1 && self.t[self.seg + 1] <= self.tau {
            self.seg += 1;
        }
        let j = self.seg;
        let h = self.tau - self.t[j];
        self.pos = (self.s[j] + self.v[j] * h + 0.5 * self.a[j] * h * h).min(1.0);
        self.vel = (self.v[j] + self.a[j] * h).max(0.0);
        self.acc = self.a[j];
        self.state()
    }

    fn segment_of(&self, pos: f64) -> usize {
        let mut j = 0;
        while j + 2 < self.k && self.s[j + 1] <= pos {
            j += 1;
        }
        j
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn uniform(k: usize) -> Vec<f64> {
        (0..k).map(|j| j as f64 / (k - 1) as f64).collect()
    }

    #[test]
    fn constant_caps_give_a_trapezoid_within_the_caps() {
        let s = uniform(65);
        let vcap = vec![2.0; 65];
        let acap = vec![10.0; 65];
        let mut r = Ramp::plan(&s, &vcap, &acap);
        // Trapezoid: 0.2 s to reach 2.0 (0.2 of the way), cruise 0.3 s, 0.2 s down: 0.7 s.
        assert!((r.duration() - 0.7).abs() < 0.02, "{}", r.duration());
        let dt = 1e-3;
        let (mut s_prev, mut v_prev) = (0.0, 0.0);
        while !r.done() {
            let (s, v, a) = r.advance(dt);
            assert!(v <= 2.0 + 1e-9 && a.abs() <= 10.0 + 1e-9);
            assert!(s >= s_prev - 1e-15, "monotonic");
            assert!(
                (v - v_prev).abs() <= 10.0 * dt + 1e-9,
                "velocity continuous"
            );
            s_prev = s;
            v_prev = v;
        }
        assert_eq!(r.state(), (1.0, 0.0, 0.0));
    }

    #[test]
    fn a_low_cap_in_the_middle_is_respected_and_reached_in_time() {
        let s = uniform(101);
        let mut vcap = vec![5.0; 101];
        for v in vcap.iter_mut().take(60).skip(40) {
            *v = 0.5;
        }
        let acap = vec![20.0; 101];
        let mut r = Ramp::plan(&s, &vcap, &acap);
        let dt = 1e-4;
        while !r.done() {
            let (s, v, _) = r.advance(dt);
            if (0.4..=0.59).contains(&s) {
                assert!(v <= 0.5 + 20.0 * 0.01 * 2.0, "s {s} v {v}");
            }
        }
    }

    #[test]
    fn braking_stops_short_within_the_cap_and_keeps_velocity_continuous() {
        let s = uniform(33);
        let mut r = Ramp::plan(&s, &[1.0; 33], &[4.0; 33]);
        let dt = 0.004;
        for _ in 0..100 {
            r.advance(dt);
        }
        let (s0, v0, _) = r.state();
        assert!(v0 > 0.9 && s0 < 0.6);
        r.brake();
        let mut prev = v0;
        let mut n = 0;
        while !r.done() {
            let (_, v, a) = r.advance(dt);
            assert!(prev - v <= 4.0 * dt + 1e-12 && a >= -4.0 - 1e-12);
            prev = v;
            n += 1;
        }
        let (s1, v1, _) = r.state();
        assert_eq!(v1, 0.0);
        // Stopped within v²/(2a) (+ one step) of where braking began.
        assert!(s1 - s0 <= v0 * v0 / 8.0 + v0 * dt + 1e-9, "{s0} → {s1}");
        assert!(n <= (v0 / 4.0 / dt).ceil() as usize + 1);
    }

    #[test]
    fn integral_of_s_matches_numerical_integration() {
        let s = uniform(41);
        let mut r = Ramp::plan(&s, &[1.5; 41], &[3.0; 41]);
        let want = r.integral_of_s();
        let dt = 1e-5;
        let mut sum = 0.0;
        while !r.done() {
            let before = r.state().0;
            let (after, _, _) = r.advance(dt);
            sum += 0.5 * (before + after) * dt;
        }
        assert!((sum - want).abs() < 1e-4, "{sum} vs {want}");
    }
}
