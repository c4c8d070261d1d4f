//! Singularity avoidance (seed 001): ICR potential fields, leg repulsion and the return loop.
//!
//! # What it does
//!
//! A platform with steered wheels is singular (seed 000, singularity A) when the
//! instantaneous centre of rotation (ICR) lies on a wheel's contact point: that wheel's
//! velocity vanishes and its steering angle is undefined; nearby, the steering rate grows
//! like (tangential ICR speed) / (ICR–wheel distance). [`Avoidance`] sits between the
//! trajectory and the tracking controller and modifies the reference (z*, ż*, z̈*) so that
//! the ICR of the *modified* reference twist keeps away from every wheel (seed 001, Fig. 6):
//!
//! ```text
//!   nominal z*, ż*, z̈* ──────────────────────────────(+)──► modified reference ──► controller
//!                                                       ▲ δ, δ̇, δ̈
//!   ICR of (ż*+δ̇) ─► fields (6–8, 20) ─► δ̈ = repulsion (9–15, 16–19)   inside a field
//!                                        δ̈ = −r1 δ̇ − r2 δ              outside every field
//! ```
//!
//! # The ICR (seed 001 eqs. 1–5) and the repulsion (eqs. 9–15), derived
//!
//! Body twist (v_b, ω) with v_b = Rᵀ(θ)(ẋ, ẏ), ω = θ̇. A body point q moves with
//! v_b + ω S q, S = [[0, −1], [1, 0]] (rotation by +90°). It is at rest at
//! z = S v_b / ω = (−ẏ_b, ẋ_b)/θ̇, which is eq. 1 with eqs. 2–3:
//! v/|θ̇| (cos γ, sin γ), γ = atan2(sgn θ̇ ẋ_b, −sgn θ̇ ẏ_b) ([`icr_from_twist`],
//! [`icr_polar`], [`icr_direction`]).
//!
//! Eq. 4: ż = J_ICR (γ̇, θ̈) + (cos γ, sin γ) v̇ / |θ̇| with J_ICR's columns ∂z/∂γ and
//! ∂z/∂θ̇ ([`icr_jacobian`]; note that the paper's "∂z/∂θ · θ̇" means ∂z/∂θ̇ · θ̈).
//! det J_ICR = v²/θ̇³ (eq. 5): full rank unless v = 0 (pure rotation, ICR at the centre,
//! far from every wheel, so no repulsion is needed) or θ̇ → ∞; θ̇ → 0 puts the ICR at
//! infinity, which is simply "far" here — no explicit ICR is formed then.
//!
//! Eq. 9 asks for ż_des = F_rep(d) p, p the unit vector from the singular point to the
//! ICR; with v̇ = 0 (the paper's choice, kept: the push only rotates the body velocity and
//! changes θ̇, never the speed) eq. 10 gives (γ̇_des, θ̈_des) = J_ICR⁻¹ F_rep p. In
//! closed form (|z| = r, z ⊥ S z): ∂z/∂γ = S z, ∂z/∂θ̇ = −z/θ̇, hence
//! γ̇_des = F (pᵀ S z)/r², θ̈_des = −θ̇ F (pᵀ z)/r². Eqs. 11–15 turn γ̇ into body
//! accelerations (ẍ, ÿ)_des = γ̇_des (−ẏ_b, ẋ_b) = γ̇_des S v_b ([`icr_repulsion`]).
//! These are changes of d/dt v_b; the frame-rotation term −θ̇ S v_b of d/dt v_b does not
//! change with an added acceleration, so the world-frame addition is simply
//! R(θ)(ẍ, ÿ)_des (Sect. IV-E: "this transformation only affects ẍ and ÿ").
//!
//! # Which point is singular when legs move (a documented generalisation of eq. 7)
//!
//! With leg rates the wheel velocity in the body frame is
//! u_i = v_b + ω S P_i + λ̇_i g_i (g_i = (cos α_i, sin α_i)). Since
//! ω S (P_i − z) = v_b + ω S P_i, one gets u_i = ω S (z_s,i − z) with the *effective
//! singular point* z_s,i = P_i − (λ̇_i/ω) S g_i. The wheel is at rest (singularity A) exactly
//! when the ICR is at z_s,i, and its steering angle is perpendicular to z − z_s,i. So the
//! distance used in the fields is d_i = |z − z_s,i| = |u_i| / |ω|, which is eq. 7 when
//! λ̇_i = 0 (z_s,i = P_i, the contact point) and stays right when the nominal or the
//! avoidance moves a leg (at λ̇ = 0.1 m/s, ω = 1 rad/s the true singular point is 10 cm off
//! the contact point). It needs no ICR at all, so θ̇ = 0 is harmless (d = ∞).
//!
//! # Fields (eqs. 6–8, 20)
//!
//! V_rep = −F_max/(3 d_s²)(d − d_s)³ and F_rep = F_max/d_s² (d − d_s)² inside d ≤ d_s, zero
//! outside: F_rep and its slope are continuous at d = d_s ([`repulsive_potential`],
//! [`repulsive_force`]). The radius follows eq. 20, d_s,i = c2 + c3 λ_i,0, where λ_i,0 is the
//! leg's equilibrium, here the *nominal* leg λ*_i(t) ([`field_radius`]).
//! [`AvoidanceConfig::validate`] checks on a grid over the leg range (with the leg deviation
//! bound) that the fields of every wheel pair never overlap and never contain the platform
//! centre; at run time every radius is additionally capped to half the distance to the
//! nearest other singular point and to 0.8 |z_s,i|, so that fields cannot overlap even for
//! unusual leg rates (a guarantee by construction, not by tuning).
//!
//! F_max is an ICR speed (m/s). The push F p needs platform accelerations with
//! |Δa_wheel| ≤ F |θ̇| (1 + λ_max/r) at ICR radius r; keeping this under the wheel
//! acceleration limit r_w ω̇_max gives [`feasible_f_max`].
//!
//! # Leg repulsion (eqs. 16–19)
//!
//! For the wheel whose field holds the ICR, F_w = −pᵀ g F_rep (eq. 18), and every free leg
//! follows m_w δλ̈ + d_w δλ̇ + c1 δλ³ = F_w (eqs. 16, 17, 19 written for the deviation
//! δλ = λ_des − λ_i,0 from the nominal leg, so the damper does not brake the nominal leg
//! motion). The progressive spring and a hard clamp keep λ* + δλ inside
//! [λ_min, λ_max] and |δλ| ≤ `leg_max_deviation`; the leg rate is clamped to the platform's
//! leg speed limit. Units are virtual: F in m/s, m_w in s, d_w dimensionless, c1 in 1/(m² s).
//!
//! # Return loop (Fig. 6)
//!
//! δ ∈ z-space (world x, y, θ, legs). Inside a field: δ̈ = (R(θ)(ẍ, ÿ)_des, θ̈_des, λ̈_des);
//! outside every field: δ̈ = −r1 δ̇ − r2 δ for every component (r1 = 2ζω_n, r2 = ω_n² set the
//! poles). The state is integrated with semi-implicit Euler at the cycle period and snapped
//! to exactly zero once |δ|, |δ̇| are below `settle_tolerance` outside every field; while
//! the state is exactly zero and the ICR is outside every field, [`Avoidance::step`] returns
//! the nominal sample itself (bit-identical).
//!
//! # Pre-planned trajectories: the avoidance before the run, the time scaling after it
//!
//! Run online on a time-scaled trajectory (nominal → scaling → [`Avoidance::step`] →
//! controller), the filter adds accelerations and, near a wheel, steering rates that no
//! timing budgeted: the scaling planned the *nominal* path within the limits, and whatever
//! is added after it is not. Measured on issue 23's lockstep runs (both profiles): the
//! seed-001 experiment tracked its avoided reference to 14.8 mm, pivots about a wheel to
//! 42–58 mm (two of four faulted), ICR sweeps to 3–22 mm, against a 5 mm bound. So with a
//! pre-planned trajectory the order is reversed ([`AvoidedTrajectory`], used by the runtime
//! whenever the avoidance is on):
//!
//! ```text
//!   z*(t) ─► Avoidance::step at the cycle period, offline ─► z*(t) + δ(t) ─► time scaling ─► controller
//! ```
//!
//! * **The ICR is a property of the path, not of its timing.** Along a path z(τ) run on a
//!   clock τ(t), every velocity is z' ṡ, so v_b and θ̇ scale by the same ṡ and the ICR
//!   z = S v_b/θ̇ (eq. 1) and every distance d_i = |u_i|/|θ̇| are unchanged. The fields keep
//!   the ICR of the avoided path where they put it at any timing: the time scaling, which
//!   only changes ṡ, keeps what the avoidance did, and the avoidance, computed first, needs
//!   no knowledge of the timing that follows.
//! * **The avoided path is the filter's, unchanged.** δ_k is the deviation the filter holds
//!   at cycle k when fed the nominal at t_k = k Δt — the same dynamics (push, leg law,
//!   return loop, clamps) and the same numbers as online, from the start of the trajectory
//!   to its end and on, with the trajectory at its goal, until the return loop has brought
//!   δ back to exactly zero (at most [`MAX_RETURN_S`]; a deviation that never returns is
//!   refused before the run, [`AvoidanceError::Unsettled`]).
//! * **Continuous to the derivatives the DFL needs.** The filter integrates with
//!   semi-implicit Euler (δ̇_{k+1} = δ̇_k + δ̈_k Δt, δ_{k+1} = δ_k + δ̇_{k+1} Δt), which is the
//!   Störmer–Verlet recursion δ_{k+1} − 2δ_k + δ_{k−1} = δ̈_k Δt². The uniform cubic B-spline
//!   with control points δ_k has, at knot k, the value (δ_{k−1} + 4δ_k + δ_{k+1})/6 =
//!   δ_k + δ̈_k Δt²/6, the rate (δ_{k+1} − δ_{k−1})/(2Δt) = δ̇_k + δ̈_k Δt/2 and the
//!   acceleration (δ_{k+1} − 2δ_k + δ_{k−1})/Δt² = δ̈_k exactly: it is the filter's output
//!   to 1.6 µm per m/s² and 2 mm/s per m/s² (at Δt = 4 ms), it is C² (its acceleration is
//!   piecewise linear, the filter's δ̈_k at the knots) and its jerk is piecewise constant,
//!   (δ̈_{k+1} − δ̈_k)/Δt. Added to the nominal (C² with bounded jerk), the avoided path is C²
//!   with bounded jerk: a path [`crate::timescale::ScaledTrajectory`] can time, and whose
//!   derivatives the time scaling and the DFL read exactly (no numerical differentiation).
//! * **Within every limit.** The avoided path is then time-scaled like any other
//!   ([`crate::timescale`]): every wheel speed and acceleration, steering rate and
//!   acceleration and leg speed within its share, C² clock, steering references for the
//!   wheels the ICR rests on, dwells at stops. The runtime always scales an avoided path
//!   (with the default margins when the scaling is off): it is a path the avoidance made,
//!   not the timing the user gave, and only its scaling keeps it within the limits. The
//!   controller then follows a reference within the limits, and its errors are measured
//!   against it.
//! * **What the record shows.** Each cycle records the filter's state at the path time the
//!   clock has reached (active, ICR, distances, radii, δ): the seed-001 experiment still
//!   shows its avoidance acting where the nominal ICR passes the wheels.
//! * **Cost.** One pass of the filter per cycle of the trajectory before the run (as online),
//!   and 8 (3 + n) bytes per cycle of δ over the stretches where it is not zero (56 bytes a
//!   cycle, 14 kB per second of avoided motion); nothing else is stored. Per cycle of the
//!   run, [`AvoidedTrajectory::state_at`] gives the record (no allocation).
//!
//! # Live commands: the avoidance at the velocity level
//!
//! Everything above filters a *trajectory*: a reference with a pose to return to. A live
//! command (the base service, [`crate::shaper`]) is a twist held until the next one. It
//! defines no pose, and the reference the controller follows must be C² and within every
//! actuator limit, which the shaper guarantees for the goals it plans and for nothing added
//! after it. Run on the shaped reference, [`Avoidance::step`] breaks both: its push and its
//! return loop add accelerations (and, near the wheel, steering rates) the shaper did not
//! budget; under a held command whose ICR rests in a field (a deliberate pivot) the push
//! never stops and the return loop pulls the ICR back into the field; and the steering
//! reference the shaper gives for slow wheels belongs to the unmodified reference. (Measured
//! on the pivot of tests/tests/e2e_drive.rs: 15 mm position error, steering commands at the
//! 6 rad/s limit, the pivot wheel turning 18° while slow; 21 mm even with F_max = 0.05.) So
//! with live commands the avoidance acts on the command, before the shaper
//! ([`avoid_twist`], applied by [`crate::shaper::Shaper`] when the runtime has avoidance on):
//!
//! * **The steady state of the push.** Under a constant command, the push of eqs. 9–15 moves
//!   the ICR along p (from the singular point to the ICR) at constant |v| until
//!   F_rep(d) = 0 (eq. 8), i.e. to the field's edge d = d_start, and stops there.
//!   [`avoid_twist`] returns that end point at once: the twist with the command's speed |v|
//!   and sense of rotation whose ICR is z' = P_k + d_start,k p, i.e. |θ̇'| = |v|/|z'| and
//!   v' = −θ̇' S z' (v + θ̇ S z = 0 at the ICR). A command whose ICR is outside every field
//!   passes unchanged (bit for bit). The return loop has nothing to do at this level: it
//!   returns a pose to its nominal, and a velocity command has no nominal pose; the twist is
//!   the command's again as soon as the command's ICR leaves the field.
//! * **Legs.** In that steady state the leg law (eq. 19) sees F_w = −pᵀg F_rep = 0, hence
//!   c1 δλ³ = 0 and δλ = 0: the legs take no part at the velocity level, and they follow the
//!   leg targets the command gives (the footprint is the operator's choice, e.g. for a narrow
//!   door). `legs_free` makes no difference for live commands ("on" and "locked" give the
//!   same motion). The fields are those of the platform at the leg targets: contact points
//!   P_i = λ_i g_i, radii by eq. 20 with λ_i,0 = λ_i, capped as in [`Avoidance::step`].
//! * **Why the result is within every limit.** The avoided twist is the shaper's goal like any
//!   command: one factor scales it into the speed limits, the transitions to it are timed
//!   within the acceleration and steering limits, align-first and the platform-wide flip
//!   apply (the shaper's docs derive each for an arbitrary goal). Nothing is added to the
//!   shaped reference afterwards, so the controller follows a C² reference within the limits
//!   and its errors are measured against that reference.
//! * **A held command is one goal.** The goal depends only on the command, the leg targets
//!   and the side below, so a command held (or repeated) gives the same goal every cycle and
//!   the shaper cruises on it.
//! * **Resting on or crossing the wheel.** p is undefined when the command's ICR rests on the
//!   contact point (within [`ICR_ON_WHEEL`]): it is then the side of the field used last, or
//!   outward along the leg (at constant |v| that slows the rotation by |P|/(|P| + d_start):
//!   0.77 for the Justin default). When the command's ICR crosses the wheel, p turns by about
//!   π; it is then taken as *exactly* the opposite of the side used last. The wheel's
//!   velocities at the two goals are then exactly opposite, the shaper's segment between them
//!   passes through the wheel's zero on a line, and the wheel reverses its roll without
//!   steering (shaper docs: such a segment does not turn the wheel). Within [`SIDE_TOLERANCE`]
//!   of the side used last, p is that side itself, so that goals computed from slightly
//!   different contact points (the shaper's legs start from their measurement) stay exactly
//!   on one line for that wheel. Any other change of p is a new goal the shaper plans like
//!   any other (sweeping round, or stopping, aligning and going when that is quicker).
//! * **A deliberate pivot about a wheel** cannot both be executed and keep the ICR out of the
//!   field. With the avoidance on, the avoidance wins: the platform turns about the point
//!   d_start beyond the wheel, outward along its leg, at the commanded speed of the base, and
//!   the pivot wheel rolls at |θ̇'| d_start, steered by its direction of travel. It has to be
//!   that way round: a field that any command may enter keeps nothing out, and "on" is a
//!   choice of the operator. To pivot about a wheel, run with the avoidance off: the shaper
//!   then holds that wheel's steering (it is at rest) and it neither chatters nor flips
//!   (tests/tests/e2e_drive.rs).
//! * **What it does not keep out.** Only goals are kept out of the fields. A transition
//!   between two goals is a straight line in q̇ and may pass through a field for a moment;
//!   when the command's ICR crosses a wheel it passes through the wheel itself, at the exact
//!   roll reversal above. The shaper times every such transition within the steering limits.

use crate::platform::Platform;
use crate::types::{ReferenceSample, ZVec, MAX_WHEELS};
use nalgebra::Matrix2;
use serde::{Deserialize, Serialize};

/// Errors in an avoidance configuration; the message names the field and what to do.
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
pub enum AvoidanceError {
    /// A configuration value is out of range.
    #[error("avoidance field `{field}` = {value}: {reason}")]
    Invalid {
        /// Name of the field in [`AvoidanceConfig`].
        field: &'static str,
        /// The offending value.
        value: f64,
        /// What is wrong and what is expected.
        reason: &'static str,
    },
    /// Eq. 20 makes two fields overlap somewhere in the leg range.
    #[error(
        "avoidance fields of wheels {a} and {b} overlap at legs ({lambda_a:.3}, {lambda_b:.3}) m: \
         radii sum {radii:.3} m > distance {distance:.3} m; lower c2/c3 or leg_max_deviation"
    )]
    Overlap {
        /// First wheel index.
        a: usize,
        /// Second wheel index.
        b: usize,
        /// Leg of wheel `a` where it happens (m).
        lambda_a: f64,
        /// Leg of wheel `b` where it happens (m).
        lambda_b: f64,
        /// Sum of the two field radii (m).
        radii: f64,
        /// Distance between the two contact points (m).
        distance: f64,
    },
    /// Along a pre-planned trajectory the return loop had not brought the deviation back
    /// to zero this long after the trajectory's end ([`AvoidedTrajectory::plan`]).
    #[error(
        "the avoidance's deviation from the trajectory ({deviation:.4}) has not returned to \
         zero {after_s} s after its end; end the trajectory with the ICR away from the wheels \
         or run with the avoidance off"
    )]
    Unsettled {
        /// Time after the end (s).
        after_s: f64,
        /// Largest component of the remaining deviation (m or rad).
        deviation: f64,
    },
    /// Eq. 20 makes a field reach the platform centre (where the ICR of a pure rotation is).
    #[error(
        "avoidance field of wheel {wheel} (radius {radius:.3} m) reaches the platform centre at \
         leg {lambda:.3} m; lower c2/c3"
    )]
    CoversCentre {
        /// Wheel index.
        wheel: usize,
        /// Leg where it happens (m).
        lambda: f64,
        /// Field radius there (m).
        radius: f64,
    },
}

/// Tuning of the singularity avoidance (serde; every field has the documented default).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct AvoidanceConfig {
    /// Master switch; when false [`Avoidance::step`] returns the nominal sample unchanged.
    /// Default true.
    pub enabled: bool,
    /// Use the legs (eqs. 16–19); when false the legs stay on their nominal trajectory.
    /// Default true.
    pub legs_free: bool,
    /// F_max (m/s): the ICR speed of the push at d = 0 (eq. 8). Default 1.6, about
    /// [`feasible_f_max`] for the Justin default at θ̇ = 1 rad/s and r = 0.44 m.
    pub f_max: f64,
    /// c2 (m) of eq. 20. Default 0.0.
    pub c2: f64,
    /// c3 (dimensionless) of eq. 20. Default 0.3 (radius 0.111–0.168 m over 0.37–0.56 m).
    pub c3: f64,
    /// m_w (s), virtual leg mass of eqs. 16/19. Default 0.02 (a light, fast leg; see docs/avoidance.md).
    pub leg_mass: f64,
    /// d_w (dimensionless), virtual leg damper of eqs. 16/19. Default 0.3.
    pub leg_damping: f64,
    /// c1 (1/(m² s)), progressive spring of eq. 17. Default 1400 (the spring balances F = 0.3 m/s at 6 cm).
    pub leg_c1: f64,
    /// r1 (1/s), velocity gain of the return loop (Fig. 6). Default 2·3 = 6 (ω_n = 3, ζ = 1).
    pub r1: f64,
    /// r2 (1/s²), position gain of the return loop (Fig. 6). Default 3² = 9.
    pub r2: f64,
    /// Largest leg deviation |δλ| the leg repulsion may command (m). Default 0.08.
    pub leg_max_deviation: f64,
    /// Width of the blend of the return gains r1(d), r2(d) (Fig. 6): they rise from zero at
    /// the field edge to their full value at d = (1 + return_blend)·d_start, with a quintic
    /// smoothstep in d/d_start of the nearest field. Default 0.5.
    pub return_blend: f64,
    /// Share of the steer-rate limit a leg's deviation acceleration may use at its own
    /// wheel: |δλ̈_i| ≤ share · φ̇_max · |θ̇| · d_i, because λ̈_i g_i enters u̇_i and so the
    /// steering rate with weight 1/|u_i| = 1/(|θ̇| d_i). Default 0.5.
    pub leg_steer_share: f64,
    /// Below this (m, rad, m/s, rad/s per component) the deviation is snapped to exactly zero
    /// once the ICR is outside every field. Default 1e-5 (10 µm, the wire resolution of the
    /// leg extension).
    pub settle_tolerance: f64,
}

impl Default for AvoidanceConfig {
    fn default() -> Self {
        Self {
            enabled: true,
            legs_free: true,
            f_max: 1.6,
            c2: 0.0,
            c3: 0.3,
            leg_mass: 0.02,
            leg_damping: 0.3,
            leg_c1: 1400.0,
            r1: 6.0,
            r2: 9.0,
            leg_max_deviation: 0.08,
            return_blend: 0.5,
            leg_steer_share: 0.5,
            settle_tolerance: 1e-5,
        }
    }
}

impl AvoidanceConfig {
    /// Checks every value and that the eq.-20 fields never overlap or cover the centre over
    /// the platform's leg range (grid check, 25 × 25 leg pairs, legs displaced by up to
    /// `leg_max_deviation`). The error names the field or the wheel pair.
    pub fn validate(&self, p: &Platform) -> Result<(), AvoidanceError> {
        let check = |field: &'static str, value: f64, min: f64, reason: &'static str| {
            if !value.is_finite() || value < min {
                Err(AvoidanceError::Invalid {
                    field,
                    value,
                    reason,
                })
            } else {
                Ok(())
            }
        };
        let pos = "must be a finite number greater than zero";
        let nonneg = "must be a finite number, zero or more";
        check("f_max", self.f_max, f64::MIN_POSITIVE, pos)?;
        if !self.c2.is_finite() {
            return Err(AvoidanceError::Invalid {
                field: "c2",
                value: self.c2,
                reason: "must be a finite number (m)",
            });
        }
        check("c3", self.c3, 0.0, nonneg)?;
        check("leg_mass", self.leg_mass, f64::MIN_POSITIVE, pos)?;
        check("leg_damping", self.leg_damping, 0.0, nonneg)?;
        check("leg_c1", self.leg_c1, 0.0, nonneg)?;
        check("r1", self.r1, f64::MIN_POSITIVE, pos)?;
        check("r2", self.r2, f64::MIN_POSITIVE, pos)?;
        check("leg_max_deviation", self.leg_max_deviation, 0.0, nonneg)?;
        check("return_blend", self.return_blend, 0.0, nonneg)?;
        check("leg_steer_share", self.leg_steer_share, 0.0, nonneg)?;
        check("settle_tolerance", self.settle_tolerance, 0.0, nonneg)?;
        let n = p.n().min(MAX_WHEELS);
        const G: usize = 25;
        for i in 0..n {
            let wi = &p.wheels[i];
            for a in 0..G {
                let l0i =
                    wi.lambda_min + (wi.lambda_max - wi.lambda_min) * a as f64 / (G - 1) as f64;
                let ri = field_radius(self, l0i);
                if ri <= 0.0 {
                    return Err(AvoidanceError::Invalid {
                        field: "c2",
                        value: self.c2,
                        reason: "eq. 20 gives a field radius of zero or less in the leg range; raise c2 or c3",
                    });
                }
                let li_min = (l0i - self.leg_max_deviation).max(wi.lambda_min);
                if ri >= li_min {
                    return Err(AvoidanceError::CoversCentre {
                        wheel: i,
                        lambda: li_min,
                        radius: ri,
                    });
                }
                for j in 0..i {
                    let wj = &p.wheels[j];
                    for b in 0..G {
                        let l0j = wj.lambda_min
                            + (wj.lambda_max - wj.lambda_min) * b as f64 / (G - 1) as f64;
                        let radii = ri + field_radius(self, l0j);
                        for si in [-1.0, 0.0, 1.0] {
                            for sj in [-1.0, 0.0, 1.0] {
                                let li = (l0i + si * self.leg_max_deviation)
                                    .clamp(wi.lambda_min, wi.lambda_max);
                                let lj = (l0j + sj * self.leg_max_deviation)
                                    .clamp(wj.lambda_min, wj.lambda_max);
                                let dx = li * wi.alpha.cos() - lj * wj.alpha.cos();
                                let dy = li * wi.alpha.sin() - lj * wj.alpha.sin();
                                let distance = dx.hypot(dy);
                                if radii > distance {
                                    return Err(AvoidanceError::Overlap {
                                        a: j,
                                        b: i,
                                        lambda_a: lj,
                                        lambda_b: li,
                                        radii,
                                        distance,
                                    });
                                }
                            }
                        }
                    }
                }
            }
        }
        Ok(())
    }
}

/// Field radius of eq. 20, d_start = c2 + c3 λ_0 (m), for a leg equilibrium λ_0 (m).
pub fn field_radius(cfg: &AvoidanceConfig, lambda0: f64) -> f64 {
    cfg.c2 + cfg.c3 * lambda0
}

/// Repulsive potential of eq. 6: −F_max/(3 d_s²)(d − d_s)³ for d ≤ d_s, else 0 (m²/s).
pub fn repulsive_potential(d: f64, d_start: f64, f_max: f64) -> f64 {
    if d_start <= 0.0 || d > d_start || d.is_nan() {
        return 0.0;
    }
    let e = d - d_start;
    -f_max / (3.0 * d_start * d_start) * e * e * e
}

/// Repulsive "force" of eq. 8 (an ICR speed, m/s): F_max (d − d_s)²/d_s² for d ≤ d_s, else 0.
/// Negative distances are treated as zero (F = F_max).
pub fn repulsive_force(d: f64, d_start: f64, f_max: f64) -> f64 {
    if d_start <= 0.0 || d >= d_start || d.is_nan() {
        return 0.0;
    }
    let e = d.max(0.0) - d_start;
    f_max * e * e / (d_start * d_start)
}

/// The largest F_max whose push keeps every wheel's added acceleration within the wheel
/// acceleration limit: F ≤ r_w ω̇_max / (|θ̇| (1 + λ_max / r)) at rotation rate `omega`
/// (rad/s) and ICR radius `radius` (m). See the module docs for the bound.
pub fn feasible_f_max(p: &Platform, omega: f64, radius: f64) -> f64 {
    let lmax = p.wheels.iter().map(|w| w.lambda_max).fold(0.0f64, f64::max);
    let a = p.wheel_radius * p.limits.wheel_accel;
    let denom = omega.abs() * (1.0 + lmax / radius.abs().max(1e-6));
    if denom > 0.0 {
        a / denom
    } else {
        f64::INFINITY
    }
}

/// ICR in the body frame from the body twist (eqs. 1–3): z = (−ẏ_b, ẋ_b)/θ̇.
/// `None` when θ̇ = 0 (ICR at infinity: "far") or the result is not finite.
pub fn icr_from_twist(vx: f64, vy: f64, omega: f64) -> Option<[f64; 2]> {
    if omega == 0.0 {
        return None;
    }
    let z = [-vy / omega, vx / omega];
    if z[0].is_finite() && z[1].is_finite() {
        Some(z)
    } else {
        None
    }
}

/// Direction γ of the ICR from the body origin (eq. 3): atan2(sgn θ̇ ẋ_b, −sgn θ̇ ẏ_b).
pub fn icr_direction(vx: f64, vy: f64, omega: f64) -> f64 {
    let s = if omega < 0.0 { -1.0 } else { 1.0 };
    (s * vx).atan2(-s * vy)
}

/// ICR from speed, direction and rotation rate (eq. 1): v/|θ̇| (cos γ, sin γ).
pub fn icr_polar(v: f64, gamma: f64, omega: f64) -> [f64; 2] {
    let r = v / omega.abs();
    [r * gamma.cos(), r * gamma.sin()]
}

/// J_ICR of eq. 4: columns ∂z/∂γ and ∂z/∂θ̇ of eq. 1, so that
/// ż = J_ICR (γ̇, θ̈) + (cos γ, sin γ) v̇/|θ̇|. Its determinant is v²/θ̇³ (eq. 5).
pub fn icr_jacobian(v: f64, gamma: f64, omega: f64) -> Matrix2<f64> {
    let (s, c) = gamma.sin_cos();
    let a = v / omega.abs();
    let b = omega.signum() * v / (omega * omega);
    Matrix2::new(-a * s, -b * c, a * c, -b * s)
}

/// What the ICR push asks of the platform (eqs. 10 and 15).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct IcrPush {
    /// γ̇_des (rad/s).
    pub gamma_rate: f64,
    /// θ̈_des (rad/s²).
    pub theta_accel: f64,
    /// (ẍ, ÿ)_des in the body frame (m/s²), eq. 15.
    pub accel_body: [f64; 2],
}

/// Platform accelerations that move the ICR with velocity `zdot` (m/s, body frame) while
/// keeping the speed |v_b| (eqs. 10, 15). `None` when the ICR is undefined or at the
/// centre (θ̇ = 0 or v_b = 0: eq. 5, no control needed there).
pub fn icr_repulsion(vx: f64, vy: f64, omega: f64, zdot: [f64; 2]) -> Option<IcrPush> {
    let z = icr_from_twist(vx, vy, omega)?;
    let r2 = z[0] * z[0] + z[1] * z[1];
    if r2.is_nan() || r2 <= 1e-12 {
        return None;
    }
    // S z = (−z_y, z_x); J⁻¹ in closed form (module docs).
    let gamma_rate = (zdot[0] * -z[1] + zdot[1] * z[0]) / r2;
    let theta_accel = -omega * (zdot[0] * z[0] + zdot[1] * z[1]) / r2;
    let accel_body = [-gamma_rate * vy, gamma_rate * vx];
    let out = IcrPush {
        gamma_rate,
        theta_accel,
        accel_body,
    };
    if gamma_rate.is_finite() && theta_accel.is_finite() {
        Some(out)
    } else {
        None
    }
}

/// Scale of the return gains r1(d), r2(d) for the smallest ratio d_i/d_start,i: 0 at the
/// field edge, 1 from (1 + return_blend) on, quintic smoothstep in between (C2, so the
/// reference acceleration does not jump when the ICR leaves a field).
pub fn return_gain_scale(cfg: &AvoidanceConfig, ratio: f64) -> f64 {
    if ratio.is_nan() {
        return 1.0;
    }
    if ratio <= 1.0 {
        return 0.0;
    }
    if cfg.return_blend <= 0.0 {
        return 1.0;
    }
    smoothstep((ratio - 1.0) / cfg.return_blend)[1]
}

/// Desired leg acceleration of eq. 19 for a leg deviation `dev` (m) and its rate
/// `dev_rate` (m/s) under the repulsive input `f_w` (eq. 18, m/s).
pub fn leg_acceleration(cfg: &AvoidanceConfig, f_w: f64, dev: f64, dev_rate: f64) -> f64 {
    (f_w - cfg.leg_damping * dev_rate - cfg.leg_c1 * dev * dev * dev) / cfg.leg_mass
}

/// Per-cycle record of the avoidance (Copy; the runtime records it every cycle).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct AvoidanceState {
    /// The ICR lies inside a wheel's field this cycle (repulsion acting).
    pub active: bool,
    /// The deviation is non-zero (returning to nominal, or being pushed).
    pub deviating: bool,
    /// ICR of the modified reference twist in the body frame (m); `None` at infinity.
    pub icr_body: Option<[f64; 2]>,
    /// Wheel whose singular point is nearest to the ICR (relative to its field radius).
    pub nearest_wheel: Option<usize>,
    /// Smallest ICR–singular-point distance d_i = |u_i|/|θ̇| (m); infinite when θ̇ = 0.
    pub min_distance: f64,
    /// Field radius per wheel this cycle (m), after the no-overlap cap.
    pub d_start: [f64; MAX_WHEELS],
    /// Repulsive force F_rep (m/s) acting this cycle (0 when inactive).
    pub force: f64,
    /// Deviation δ added to z* (m, m, rad, m …), world frame for x, y.
    pub deviation: ZVec,
    /// Deviation rate δ̇ added to ż*.
    pub deviation_rate: ZVec,
    /// Deviation acceleration δ̈ added to z̈* (avoidance output or return loop).
    pub deviation_accel: ZVec,
}

impl Default for AvoidanceState {
    fn default() -> Self {
        Self {
            active: false,
            deviating: false,
            icr_body: None,
            nearest_wheel: None,
            min_distance: f64::INFINITY,
            d_start: [0.0; MAX_WHEELS],
            force: 0.0,
            deviation: ZVec::zeros(),
            deviation_rate: ZVec::zeros(),
            deviation_accel: ZVec::zeros(),
        }
    }
}

/// Geometry of the fields for one reference twist (no allocation).
#[derive(Clone, Copy, Debug)]
struct FieldScan {
    icr: Option<[f64; 2]>,
    /// Per-wheel effective singular point z_s,i (body frame), valid when θ̇ ≠ 0.
    dist: [f64; MAX_WHEELS],
    radius: [f64; MAX_WHEELS],
    /// Unit push direction p (singular point → ICR), body frame.
    push: [[f64; 2]; MAX_WHEELS],
    nearest: Option<usize>,
    /// Smallest d_i / d_start,i.
    min_ratio: f64,
    min_distance: f64,
    inside: Option<usize>,
}

/// Scans the fields of the reference `r` (z, ż in world frame; legs included).
fn scan_fields(
    p: &Platform,
    cfg: &AvoidanceConfig,
    r: &ReferenceSample,
    nominal_legs: &ZVec,
) -> FieldScan {
    let n = p.n().min(r.n).min(MAX_WHEELS);
    let (s, c) = r.z[2].sin_cos();
    // Body-frame velocity v_b = Rᵀ(θ) (ẋ, ẏ).
    let vx = c * r.dz[0] + s * r.dz[1];
    let vy = -s * r.dz[0] + c * r.dz[1];
    let omega = r.dz[2];
    let icr = icr_from_twist(vx, vy, omega);
    let mut out = FieldScan {
        icr,
        dist: [f64::INFINITY; MAX_WHEELS],
        radius: [0.0; MAX_WHEELS],
        push: [[0.0; 2]; MAX_WHEELS],
        nearest: None,
        min_ratio: f64::INFINITY,
        min_distance: f64::INFINITY,
        inside: None,
    };
    let mut zs = [[f64::INFINITY; 2]; MAX_WHEELS];
    for i in 0..n {
        let w = &p.wheels[i];
        let (ga_s, ga_c) = w.alpha.sin_cos();
        let lam = r.z[3 + i];
        let lam_rate = r.dz[3 + i];
        // u_i = v_b + ω S P_i + λ̇ g_i.
        let ux = vx - omega * lam * ga_s + lam_rate * ga_c;
        let uy = vy + omega * lam * ga_c + lam_rate * ga_s;
        out.radius[i] = field_radius(cfg, nominal_legs[3 + i]).max(0.0);
        if omega != 0.0 {
            let d = ux.hypot(uy) / omega.abs();
            if d.is_finite() {
                out.dist[i] = d;
                // u = ω S (z_s − z)  ⇒  z − z_s = −S⁻¹ u / ω = S u / ω = (−u_y, u_x)/ω.
                let (ex, ey) = (-uy / omega, ux / omega);
                if d > 0.0 {
                    out.push[i] = [ex / d, ey / d];
                } else {
                    // ICR exactly on the singular point: push outward along the leg
                    // (deterministic; lowers |θ̇| at constant speed).
                    out.push[i] = [ga_c, ga_s];
                }
                if let Some(z) = icr {
                    zs[i] = [z[0] - ex, z[1] - ey];
                }
            }
        }
    }
    // No-overlap cap: half the distance to the nearest other singular point, and 0.8 |z_s|
    // so that no field reaches the platform centre.
    for i in 0..n {
        if !zs[i][0].is_finite() {
            continue;
        }
        let mut cap = 0.8 * zs[i][0].hypot(zs[i][1]);
        for (j, zj) in zs.iter().enumerate().take(n) {
            if j != i && zj[0].is_finite() {
                cap = cap.min(0.5 * (zs[i][0] - zj[0]).hypot(zs[i][1] - zj[1]));
            }
        }
        out.radius[i] = out.radius[i].min(cap);
    }
    let mut best = f64::INFINITY;
    for i in 0..n {
        let d = out.dist[i];
        if d < out.min_distance {
            out.min_distance = d;
        }
        if out.radius[i] > 0.0 && d.is_finite() {
            let ratio = d / out.radius[i];
            if ratio < best {
                best = ratio;
                out.nearest = Some(i);
            }
        }
    }
    out.min_ratio = best;
    if best < 1.0 {
        out.inside = out.nearest;
    }
    out
}

/// The singularity avoidance filter on the reference (Fig. 6 of seed 001).
#[derive(Clone, Debug)]
pub struct Avoidance {
    cfg: AvoidanceConfig,
    error: Option<AvoidanceError>,
    delta: ZVec,
    delta_rate: ZVec,
    last_accel: ZVec,
}

impl Avoidance {
    /// Creates the filter. If `cfg` fails [`AvoidanceConfig::validate`] for `p`, the filter
    /// is built disabled (pass-through) and the reason is available from
    /// [`Avoidance::config_error`]; use [`Avoidance::try_new`] to get the error instead.
    pub fn new(p: &Platform, cfg: AvoidanceConfig) -> Self {
        match Self::try_new(p, cfg) {
            Ok(a) => a,
            Err(e) => Self {
                cfg: AvoidanceConfig {
                    enabled: false,
                    ..cfg
                },
                error: Some(e),
                delta: ZVec::zeros(),
                delta_rate: ZVec::zeros(),
                last_accel: ZVec::zeros(),
            },
        }
    }

    /// Creates the filter after validating `cfg` against `p`.
    pub fn try_new(p: &Platform, cfg: AvoidanceConfig) -> Result<Self, AvoidanceError> {
        cfg.validate(p)?;
        Ok(Self {
            cfg,
            error: None,
            delta: ZVec::zeros(),
            delta_rate: ZVec::zeros(),
            last_accel: ZVec::zeros(),
        })
    }

    /// The configuration in use (with `enabled = false` if it was rejected).
    pub fn config(&self) -> &AvoidanceConfig {
        &self.cfg
    }

    /// Why the configuration was rejected by [`Avoidance::new`], if it was.
    pub fn config_error(&self) -> Option<&AvoidanceError> {
        self.error.as_ref()
    }

    /// Clears the deviation (e.g. when a new trajectory starts).
    pub fn reset(&mut self) {
        self.delta = ZVec::zeros();
        self.delta_rate = ZVec::zeros();
        self.last_accel = ZVec::zeros();
    }

    /// Takes the nominal reference (z*, ż*, z̈*, jerk) and returns the modified reference fed
    /// to the tracking controller (nominal + deviation) and this cycle's record. `dt` is the
    /// cycle period (s). Pure apart from the deviation state; no allocation.
    ///
    /// When the ICR is outside every field and the deviation is exactly zero, the nominal
    /// sample is returned unchanged (bit-identical). Non-finite input or `dt` passes the
    /// nominal through and leaves the state untouched.
    pub fn step(
        &mut self,
        p: &Platform,
        nominal: &ReferenceSample,
        dt: f64,
    ) -> (ReferenceSample, AvoidanceState) {
        let mut st = AvoidanceState::default();
        let n = p.n().min(nominal.n).min(MAX_WHEELS);
        let finite = nominal.z.iter().all(|v| v.is_finite())
            && nominal.dz.iter().all(|v| v.is_finite())
            && nominal.ddz.iter().all(|v| v.is_finite());
        if !(self.cfg.enabled && finite && dt.is_finite() && dt > 0.0) {
            return (*nominal, st);
        }
        let zero_state = self.is_zero();
        let mut modified = *nominal;
        if !zero_state {
            modified.z += self.delta;
            modified.dz += self.delta_rate;
        }
        let scan = scan_fields(p, &self.cfg, &modified, &nominal.z);
        st.icr_body = scan.icr;
        st.nearest_wheel = scan.nearest;
        st.min_distance = scan.min_distance;
        st.d_start = scan.radius;

        if zero_state && scan.inside.is_none() {
            return (*nominal, st);
        }

        let mut acc = ZVec::zeros();
        let cfg = self.cfg;
        if let Some(k) = scan.inside {
            st.active = true;
            let f = repulsive_force(scan.dist[k], scan.radius[k], cfg.f_max);
            st.force = f;
            let pk = scan.push[k];
            let (s, c) = modified.z[2].sin_cos();
            let vx = c * modified.dz[0] + s * modified.dz[1];
            let vy = -s * modified.dz[0] + c * modified.dz[1];
            if let Some(push) = icr_repulsion(vx, vy, modified.dz[2], [f * pk[0], f * pk[1]]) {
                let [ax, ay] = push.accel_body;
                acc[0] = c * ax - s * ay;
                acc[1] = s * ax + c * ay;
                acc[2] = push.theta_accel;
            }
            if cfg.legs_free {
                for i in 0..n {
                    let w = &p.wheels[i];
                    let f_w = if i == k {
                        let (gs, gc) = w.alpha.sin_cos();
                        -(pk[0] * gc + pk[1] * gs) * f
                    } else {
                        0.0
                    };
                    acc[3 + i] =
                        leg_acceleration(&cfg, f_w, self.delta[3 + i], self.delta_rate[3 + i]);
                }
            }
        } else {
            let g = return_gain_scale(&cfg, scan.min_ratio);
            for j in 0..3 + n {
                acc[j] = g * (-cfg.r1 * self.delta_rate[j] - cfg.r2 * self.delta[j]);
            }
        }
        if !cfg.legs_free {
            for j in 3..3 + n {
                // Locked legs: any leftover leg deviation still returns (only possible if the
                // mode was switched while deviating).
                acc[j] = -cfg.r1 * self.delta_rate[j] - cfg.r2 * self.delta[j];
            }
        }
        // Leg accelerations near a singular point turn the wheel: bound their share.
        let w_abs = modified.dz[2].abs();
        for i in 0..n {
            let lim = cfg.leg_steer_share * p.limits.steer_rate * w_abs * scan.dist[i];
            if lim.is_finite() {
                acc[3 + i] = acc[3 + i].clamp(-lim, lim);
            }
        }
        for v in acc.iter_mut() {
            if !v.is_finite() {
                *v = 0.0;
            }
        }

        modified.ddz += acc;
        // Jerk: nominal jerk plus the backward difference of δ̈ (a step at field entry/exit
        // shows up once as a finite spike; controllers that use jerk see a bounded value).
        let jerk = (acc - self.last_accel) / dt;
        modified.dddz += jerk;
        self.last_accel = acc;

        st.deviation = self.delta;
        st.deviation_rate = self.delta_rate;
        st.deviation_accel = acc;
        st.deviating = true;

        // Integrate (semi-implicit Euler) for the next cycle.
        self.delta_rate += acc * dt;
        self.delta += self.delta_rate * dt;
        // Legs: stay inside [λ_min, λ_max] (around the next nominal, approximated by the
        // current one), |δλ| ≤ leg_max_deviation, |λ̇| ≤ leg speed limit.
        for i in 0..n {
            let w = &p.wheels[i];
            let j = 3 + i;
            let lo = (w.lambda_min - nominal.z[j])
                .max(-cfg.leg_max_deviation)
                .min(0.0);
            let hi = (w.lambda_max - nominal.z[j])
                .min(cfg.leg_max_deviation)
                .max(0.0);
            if self.delta[j] < lo {
                self.delta[j] = lo;
                self.delta_rate[j] = self.delta_rate[j].max(0.0);
            } else if self.delta[j] > hi {
                self.delta[j] = hi;
                self.delta_rate[j] = self.delta_rate[j].min(0.0);
            }
            let vmax = p.limits.leg_speed;
            let lo_v = -vmax - nominal.dz[j];
            let hi_v = vmax - nominal.dz[j];
            if lo_v <= hi_v {
                self.delta_rate[j] = self.delta_rate[j].clamp(lo_v, hi_v);
            }
        }
        if !st.active {
            let tol = cfg.settle_tolerance;
            let small = self.delta.iter().all(|v| v.abs() <= tol)
                && self.delta_rate.iter().all(|v| v.abs() <= tol);
            if small {
                self.reset();
            }
        }
        (modified, st)
    }

    fn is_zero(&self) -> bool {
        self.delta.iter().all(|v| *v == 0.0) && self.delta_rate.iter().all(|v| *v == 0.0)
    }
}

/// Outcome of [`avoid_twist`]: the twist to execute and where its ICR was put.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct TwistAvoidance {
    /// The twist to execute (v_x, v_y, ω; base frame): the command's own, or the one with
    /// the same speed |v| whose ICR is on the edge of the field the command's ICR lay in.
    pub twist: [f64; 3],
    /// The command's ICR lay inside a field and was moved to its edge.
    pub active: bool,
    /// The wheel whose field held the command's ICR (the nearest relative to its radius,
    /// when inside none).
    pub wheel: Option<usize>,
    /// Distance (m) of the command's ICR from the nearest singular point (∞ when θ̇ = 0).
    pub distance: f64,
    /// Field radius per wheel (m), eq. 20 after the no-overlap cap.
    pub d_start: [f64; MAX_WHEELS],
    /// Unit direction (body frame) from that wheel's contact point to the ICR put on the
    /// field's edge; zero when not active.
    pub push: [f64; 2],
}

impl Default for TwistAvoidance {
    fn default() -> Self {
        Self {
            twist: [0.0; 3],
            active: false,
            wheel: None,
            distance: f64::INFINITY,
            d_start: [0.0; MAX_WHEELS],
            push: [0.0; 2],
        }
    }
}

/// ICR–contact-point distance (m) at or below which the command's ICR counts as resting on
/// the contact point (1 mm: the contact point is known to the leg's measurement, which the
/// shaper's leg targets start from): the push direction is then the side used last for that
/// wheel, or outward along its leg.
pub const ICR_ON_WHEEL: f64 = 1e-3;

/// Angle (rad) within which the direction from the contact point to the command's ICR counts
/// as the side used last, or as its opposite (5°; [`avoid_twist`]).
pub const SIDE_TOLERANCE: f64 = 0.087_266_462_599_716_48;

/// Singularity avoidance of a velocity command (module docs, "Live commands"): when the
/// ICR of `twist` (v_x, v_y, ω in the base frame) lies inside a wheel's field, returns the
/// twist with the same speed |v| and the same sense of rotation whose ICR is on that field's
/// edge, in the direction p from the wheel's contact point to the command's ICR — the steady
/// state of seed 001's push (eqs. 9–15), where F_rep = 0. `legs` (m) are the leg extensions
/// the command is executed with (contact points λ_i g_i; field radii by eq. 20 with
/// λ_i,0 = λ_i, capped as in [`Avoidance::step`]); `leg_dirs` the unit leg directions g_i in
/// the body frame. `sides[k]`, when a unit vector, is the side of wheel k's field the ICR was
/// put on last: when the command's ICR rests on the contact point (closer than
/// [`ICR_ON_WHEEL`]) p is that side (outward along the leg when there is none); when its
/// direction is within [`SIDE_TOLERANCE`] of that side, p is exactly the side, and within it
/// of the opposite direction (the ICR crossed the wheel), exactly the opposite side. So a held
/// command gives the same twist every cycle, and an ICR crossing the wheel gives two goals
/// whose velocities of that wheel are exactly opposite.
/// A pure translation (θ̇ = 0), a pure rotation and a disabled configuration pass the twist
/// through.
pub fn avoid_twist(
    cfg: &AvoidanceConfig,
    leg_dirs: &[[f64; 2]],
    legs: &[f64],
    twist: [f64; 3],
    sides: &[[f64; 2]],
) -> TwistAvoidance {
    let mut out = TwistAvoidance {
        twist,
        ..TwistAvoidance::default()
    };
    let n = leg_dirs.len().min(legs.len()).min(MAX_WHEELS);
    let [vx, vy, om] = twist;
    if !(cfg.enabled && vx.is_finite() && vy.is_finite() && om.is_finite()) {
        return out;
    }
    let mut pts = [[0.0; 2]; MAX_WHEELS];
    for i in 0..n {
        pts[i] = [legs[i] * leg_dirs[i][0], legs[i] * leg_dirs[i][1]];
    }
    // Radii: eq. 20, capped to half the distance to the nearest other contact point and to
    // 0.8 of the distance to the centre (as in `scan_fields`), so fields never overlap and the
    // edge of one is outside every other.
    for i in 0..n {
        let mut cap = 0.8 * pts[i][0].hypot(pts[i][1]);
        for j in 0..n {
            if j != i {
                cap = cap.min(0.5 * (pts[i][0] - pts[j][0]).hypot(pts[i][1] - pts[j][1]));
            }
        }
        out.d_start[i] = field_radius(cfg, legs[i]).max(0.0).min(cap);
    }
    let Some(z) = icr_from_twist(vx, vy, om) else {
        return out;
    };
    let mut best = f64::INFINITY;
    for (i, (pt, r)) in pts.iter().zip(&out.d_start).take(n).enumerate() {
        let d = (z[0] - pt[0]).hypot(z[1] - pt[1]);
        out.distance = out.distance.min(d);
        if *r > 0.0 && d / r < best {
            best = d / r;
            out.wheel = Some(i);
        }
    }
    let Some(k) = out.wheel else {
        return out;
    };
    if best >= 1.0 {
        return out;
    }
    let (pk, r) = (pts[k], out.d_start[k]);
    let e = [z[0] - pk[0], z[1] - pk[1]];
    let d = e[0].hypot(e[1]);
    let side = sides.get(k).copied().filter(|h| h[0].hypot(h[1]) > 0.5);
    let cos_side = SIDE_TOLERANCE.cos();
    let p = match (d > ICR_ON_WHEEL, side) {
        (true, Some(h)) => {
            let c = (e[0] * h[0] + e[1] * h[1]) / d;
            if c >= cos_side {
                // Still on that side: exactly it (the wheel keeps its direction).
                h
            } else if c <= -cos_side {
                // Crossed to the far side of the wheel: exactly the opposite side, so that
                // the wheel's velocity passes through zero on a line (a roll reversal, no
                // steering).
                [-h[0], -h[1]]
            } else {
                [e[0] / d, e[1] / d]
            }
        }
        (true, None) => [e[0] / d, e[1] / d],
        (false, Some(h)) => h,
        (false, None) => leg_dirs[k],
    };
    let zn = [pk[0] + r * p[0], pk[1] + r * p[1]];
    let rn = zn[0].hypot(zn[1]);
    let speed = vx.hypot(vy);
    if !(rn > 0.0 && speed.is_finite()) {
        return out;
    }
    // v + ω S z = 0 at the new ICR, with |v| kept: |ω'| = |v|/|z'|, sign of ω kept.
    let omn = om.signum() * speed / rn;
    out.twist = [omn * zn[1], -omn * zn[0], omn];
    out.active = true;
    out.push = p;
    out
}

/// Longest time (s) the return loop may take after a trajectory's end to bring the deviation
/// back to zero in [`AvoidedTrajectory::plan`] (ten times the settling time of the default
/// return loop, ω_n = 3 rad/s).
pub const MAX_RETURN_S: f64 = 20.0;

/// Seed 001's avoidance applied to a pre-planned trajectory before the run (module docs,
/// "Pre-planned trajectories"): the nominal z*(t) plus the deviation δ(t) the filter
/// [`Avoidance::step`] produces along it at the cycle period, δ interpolated by the uniform
/// cubic B-spline whose control points are the filter's δ_k. The result is C² with bounded
/// jerk, so [`crate::timescale::ScaledTrajectory`] can time it within every limit.
pub struct AvoidedTrajectory {
    inner: Box<dyn crate::trajectory::Trajectory>,
    platform: Platform,
    cfg: AvoidanceConfig,
    n: usize,
    /// Cycle period of the filter (s): the knot spacing.
    dt: f64,
    /// Runs of consecutive knots whose δ_k is not zero: (first knot, δ of each, 3 + n
    /// values per knot). δ_k is zero between them, so only the avoided stretches cost memory.
    spans: Vec<(usize, Vec<f64>)>,
    /// Knot intervals [a, b) in which the repulsion acted (the filter's `active`).
    active: Vec<(usize, usize)>,
    /// Duration: the inner one, or the end of the return loop after it (s).
    duration: f64,
}

impl std::fmt::Debug for AvoidedTrajectory {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("AvoidedTrajectory")
            .field("n", &self.n)
            .field("dt", &self.dt)
            .field("spans", &self.spans.len())
            .field("active", &self.active)
            .field("duration", &self.duration)
            .finish()
    }
}

impl AvoidedTrajectory {
    /// Runs [`Avoidance::step`] with `cfg` along `inner` at the platform's cycle period, from
    /// its start to its end and on, with the trajectory at its goal, until the return loop
    /// has brought the deviation back to exactly zero. Fails when `cfg` is invalid for `p`,
    /// or when the deviation has not returned [`MAX_RETURN_S`] after the end.
    pub fn plan(
        p: &Platform,
        inner: Box<dyn crate::trajectory::Trajectory>,
        cfg: AvoidanceConfig,
    ) -> Result<Self, AvoidanceError> {
        let mut av = Avoidance::try_new(p, cfg)?;
        let dt = p.dt();
        let n = p.n().min(inner.n_legs()).min(MAX_WHEELS);
        let m = 3 + n;
        let end = inner.duration();
        if !(end.is_finite() && end >= 0.0 && dt > 0.0 && dt.is_finite()) {
            return Err(AvoidanceError::Invalid {
                field: "trajectory duration",
                value: end,
                reason: "must be a finite time of zero or more",
            });
        }
        let last_nominal = (end / dt).ceil() as usize;
        let last_allowed = last_nominal + (MAX_RETURN_S / dt).ceil() as usize;
        let mut spans: Vec<(usize, Vec<f64>)> = Vec::new();
        let mut active: Vec<(usize, usize)> = Vec::new();
        let mut last_nonzero = None;
        let mut k = 0usize;
        loop {
            let t = k as f64 * dt;
            let nominal = inner.sample(t.min(end));
            let (_, st) = av.step(p, &nominal, dt);
            let d = &st.deviation.as_slice()[..m];
            if d.iter().any(|v| *v != 0.0) {
                match spans.last_mut() {
                    Some((first, values)) if *first + values.len() / m == k => {
                        values.extend_from_slice(d)
                    }
                    _ => spans.push((k, d.to_vec())),
                }
                last_nonzero = Some(k);
            }
            if st.active {
                match active.last_mut() {
                    Some((_, b)) if *b == k => *b = k + 1,
                    _ => active.push((k, k + 1)),
                }
            }
            if k >= last_nominal && av.is_zero() && !st.active {
                break;
            }
            if k >= last_allowed {
                return Err(AvoidanceError::Unsettled {
                    after_s: MAX_RETURN_S,
                    deviation: av.delta.amax(),
                });
            }
            k += 1;
        }
        // Control point j shapes the B-spline over ((j − 2) Δt, (j + 2) Δt): after the last
        // non-zero one δ is zero, at rest.
        let duration = match last_nonzero {
            Some(j) => end.max((j + 2) as f64 * dt),
            None => end,
        };
        Ok(Self {
            inner,
            platform: p.clone(),
            cfg,
            n,
            dt,
            spans,
            active,
            duration,
        })
    }

    /// The trajectory the avoidance was applied to.
    pub fn inner(&self) -> &dyn crate::trajectory::Trajectory {
        self.inner.as_ref()
    }

    /// The knot nearest to time `t` (s).
    fn knot(&self, t: f64) -> usize {
        if t.is_finite() && t > 0.0 {
            (t.min(self.duration) / self.dt).round() as usize
        } else {
            0
        }
    }

    /// The filter's record at the knot nearest to time `t` (s): whether the repulsion acted
    /// there and δ_k as the filter had them; the ICR, its distances and the field radii of
    /// the avoided path there, the rate and acceleration of δ from the B-spline. No
    /// allocation.
    pub fn state_at(&self, t: f64) -> AvoidanceState {
        let k = self.knot(t);
        let tk = k as f64 * self.dt;
        let r = crate::trajectory::Trajectory::sample(self, tk);
        let nominal = self.inner.sample(tk.min(self.inner.duration()));
        let scan = scan_fields(&self.platform, &self.cfg, &r, &nominal.z);
        let i = self.active.partition_point(|&(a, _)| a <= k);
        let active = i > 0 && k < self.active[i - 1].1;
        let delta = self.point(k as isize);
        let [_, rate, accel, _] = self.deviation(tk);
        let force = match scan.nearest {
            Some(w) if active => repulsive_force(scan.dist[w], scan.radius[w], self.cfg.f_max),
            _ => 0.0,
        };
        AvoidanceState {
            active,
            deviating: active || !self.zero_around(tk),
            icr_body: scan.icr,
            nearest_wheel: scan.nearest,
            min_distance: scan.min_distance,
            d_start: scan.radius,
            force,
            deviation: delta,
            deviation_rate: rate,
            deviation_accel: accel,
        }
    }

    /// Control point k of the B-spline: δ_k, zero outside the spans.
    fn point(&self, k: isize) -> ZVec {
        let mut out = ZVec::zeros();
        if k < 0 {
            return out;
        }
        let k = k as usize;
        let m = 3 + self.n;
        let i = self.spans.partition_point(|(first, _)| *first <= k);
        if i == 0 {
            return out;
        }
        let (first, values) = &self.spans[i - 1];
        let j = k - first;
        if let Some(d) = values.get(j * m..(j + 1) * m) {
            out.as_mut_slice()[..m].copy_from_slice(d);
        }
        out
    }

    /// Whether the four control points that make the B-spline at `t` are all zero.
    fn zero_around(&self, t: f64) -> bool {
        let k = (t / self.dt).max(0.0).floor() as isize;
        (k - 1..=k + 2).all(|j| self.point(j).iter().all(|v| *v == 0.0))
    }

    /// δ, δ̇, δ̈, δ⃛ at time `t` (uniform cubic B-spline over the knots).
    fn deviation(&self, t: f64) -> [ZVec; 4] {
        let x = (t / self.dt).max(0.0);
        let k = x.floor();
        let u = x - k;
        let k = k as isize;
        let (c0, c1, c2, c3) = (
            self.point(k - 1),
            self.point(k),
            self.point(k + 1),
            self.point(k + 2),
        );
        let v = 1.0 - u;
        let h = self.dt;
        let pos = (c0 * (v * v * v)
            + c1 * (3.0 * u * u * u - 6.0 * u * u + 4.0)
            + c2 * (-3.0 * u * u * u + 3.0 * u * u + 3.0 * u + 1.0)
            + c3 * (u * u * u))
            / 6.0;
        let vel = (c0 * (-3.0 * v * v)
            + c1 * (9.0 * u * u - 12.0 * u)
            + c2 * (-9.0 * u * u + 6.0 * u + 3.0)
            + c3 * (3.0 * u * u))
            / (6.0 * h);
        let acc = (c0 * v + c1 * (3.0 * u - 2.0) + c2 * (1.0 - 3.0 * u) + c3 * u) / (h * h);
        let jerk = (c1 * 3.0 - c0 - c2 * 3.0 + c3) / (h * h * h);
        [pos, vel, acc, jerk]
    }
}

impl crate::trajectory::Trajectory for AvoidedTrajectory {
    fn sample(&self, t: f64) -> ReferenceSample {
        let t = if t.is_finite() {
            t.clamp(0.0, self.duration)
        } else {
            0.0
        };
        let mut r = self.inner.sample(t.min(self.inner.duration()));
        r.t = t;
        if self.zero_around(t) {
            // No deviation here: the nominal sample itself, bit for bit.
            return r;
        }
        let [d, dd, ddd, dddd] = self.deviation(t);
        let c = 3 + self.n;
        for j in 0..c {
            r.z[j] += d[j];
            r.dz[j] += dd[j];
            r.ddz[j] += ddd[j];
            r.dddz[j] += dddd[j];
        }
        r
    }
    fn duration(&self) -> f64 {
        self.duration
    }
    fn n_legs(&self) -> usize {
        self.inner.n_legs()
    }
    fn timed_at(&self, t: f64) -> bool {
        self.inner.timed_at(t.min(self.inner.duration()))
    }
    fn waypoint_near(&self, t: f64) -> Option<usize> {
        self.inner.waypoint_near(t.min(self.inner.duration()))
    }
    fn stops(&self) -> Vec<(f64, f64)> {
        // The inner stops where the deviation is zero around them (the B-spline's support:
        // two knots either side); the end of the return loop is found by the time scaling.
        self.inner
            .stops()
            .into_iter()
            .filter(|&(a, b)| {
                let lo = (a / self.dt).floor() as isize - 2;
                let hi = (b / self.dt).ceil() as isize + 2;
                (lo..=hi).all(|k| self.point(k).iter().all(|v| *v == 0.0))
            })
            .collect()
    }
    fn avoidance_at(&self, t: f64) -> Option<AvoidanceState> {
        Some(self.state_at(t))
    }
}

/// Analytic steering rate φ̇_i = (u × u̇)/|u|² and rolling speed |u_i| (m/s) of every wheel
/// for a reference sample (what a perfect tracker commands). u̇_i = v̇_b + θ̈ S P_i +
/// θ̇ λ̇_i S g_i + λ̈_i g_i with v̇_b = Rᵀ a_w − θ̇ S v_b. A wheel at rest gives rate 0 if
/// u̇ = 0 too, else +∞ (the singularity itself).
pub fn reference_wheel_rates(
    p: &Platform,
    r: &ReferenceSample,
) -> ([f64; MAX_WHEELS], [f64; MAX_WHEELS]) {
    let n = p.n().min(r.n).min(MAX_WHEELS);
    let (s, c) = r.z[2].sin_cos();
    let vx = c * r.dz[0] + s * r.dz[1];
    let vy = -s * r.dz[0] + c * r.dz[1];
    let w = r.dz[2];
    let wd = r.ddz[2];
    let ax = c * r.ddz[0] + s * r.ddz[1] + w * vy;
    let ay = -s * r.ddz[0] + c * r.ddz[1] - w * vx;
    let mut rates = [0.0; MAX_WHEELS];
    let mut speeds = [0.0; MAX_WHEELS];
    for i in 0..n {
        let (gs, gc) = p.wheels[i].alpha.sin_cos();
        let (l, ld, ldd) = (r.z[3 + i], r.dz[3 + i], r.ddz[3 + i]);
        let ux = vx - w * l * gs + ld * gc;
        let uy = vy + w * l * gc + ld * gs;
        let udx = ax - wd * l * gs - w * ld * gs + ldd * gc;
        let udy = ay + wd * l * gc + w * ld * gc + ldd * gs;
        let n2 = ux * ux + uy * uy;
        let cross = ux * udy - uy * udx;
        speeds[i] = n2.sqrt();
        rates[i] = if n2 > 0.0 {
            cross / n2
        } else if cross == 0.0 && udx == 0.0 && udy == 0.0 {
            0.0
        } else {
            f64::INFINITY
        };
    }
    (rates, speeds)
}

/// Quintic smoothstep σ(τ) = 10τ³ − 15τ⁴ + 6τ⁵ and its derivatives and integral, τ ∈ [0, 1]
/// (returns (∫σ, σ, σ', σ'', σ''')).
fn smoothstep(tau: f64) -> [f64; 5] {
    let t = tau.clamp(0.0, 1.0);
    let t2 = t * t;
    let t3 = t2 * t;
    [
        t2 * t2 * (2.5 - 3.0 * t + t2),
        t3 * (10.0 - 15.0 * t + 6.0 * t2),
        30.0 * t2 * (1.0 - 2.0 * t + t2),
        60.0 * t * (1.0 - 3.0 * t + 2.0 * t2),
        60.0 - 360.0 * t + 360.0 * t2,
    ]
}

/// A scalar with a piecewise rate profile: between knots (t_k, v_k) the rate moves from
/// v_k to v_{k+1} along a quintic smoothstep (C2 rate, C3 position); constant after the
/// last knot. Position starts at `q0`. Fixed size, no allocation.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct RateProfile {
    knots: [(f64, f64); 8],
    len: usize,
    q0: f64,
    /// Position at each knot.
    q_at: [f64; 8],
}

impl RateProfile {
    /// Builds a profile from up to 8 knots (time s, rate) with increasing times.
    /// Returns `None` if there are no knots, more than 8, or the times do not increase.
    pub fn new(q0: f64, knots: &[(f64, f64)]) -> Option<Self> {
        if knots.is_empty() || knots.len() > 8 {
            return None;
        }
        let mut k = [(0.0, 0.0); 8];
        k[..knots.len()].copy_from_slice(knots);
        for w in knots.windows(2) {
            if w[1].0.is_nan() || w[0].0.is_nan() || w[1].0 <= w[0].0 {
                return None;
            }
        }
        let mut q_at = [q0; 8];
        for j in 1..knots.len() {
            let (t0, v0) = k[j - 1];
            let (t1, v1) = k[j];
            let tt = t1 - t0;
            q_at[j] = q_at[j - 1] + v0 * tt + (v1 - v0) * tt * smoothstep(1.0)[0];
        }
        Some(Self {
            knots: k,
            len: knots.len(),
            q0,
            q_at,
        })
    }

    /// (position, rate, rate', rate'') at time t.
    pub fn sample(&self, t: f64) -> [f64; 4] {
        let k = &self.knots;
        if t <= k[0].0 {
            return [self.q0 + k[0].1 * (t - k[0].0), k[0].1, 0.0, 0.0];
        }
        for j in 1..self.len {
            let (t0, v0) = k[j - 1];
            let (t1, v1) = k[j];
            if t <= t1 {
                let tt = t1 - t0;
                let s = smoothstep((t - t0) / tt);
                let dv = v1 - v0;
                return [
                    self.q_at[j - 1] + v0 * (t - t0) + dv * tt * s[0],
                    v0 + dv * s[1],
                    dv * s[2] / tt,
                    dv * s[3] / (tt * tt),
                ];
            }
        }
        let (tl, vl) = k[self.len - 1];
        [self.q_at[self.len - 1] + vl * (t - tl), vl, 0.0, 0.0]
    }
}

/// The seed-001 style experiment (Sect. V): a smooth (C3, quintic-smoothstep rate
/// profiles) trajectory whose nominal ICR sweeps past the wheels.
///
/// Timeline (defaults from [`Seed001Scenario::new`], wheel legs on the Justin default):
/// 0–1.5 s spin up to 2.1 rad/s on the spot with the legs at λ_max = 0.56 m (wheel spin
/// 2.1·0.56/0.085 = 13.8 rad/s: the spin limit, as in the paper); hold 1 s; 2.5–4 s slow
/// the rotation to ω1 while accelerating along the world x axis to v1 = r_icr ω1 and
/// retracting the legs to λ_0 = 0.465 m (the ICR moves out from the centre to r_icr);
/// 4 s – 4 s + T: the ICR circles the centre at r_icr = 0.44 m in the body frame, 2.5 cm
/// inside the wheel circle, passing the wheels one after the other; then 1.5 s in which the
/// translation stops (the ICR moves in to the centre, away from every wheel), 2 s of pure
/// rotation (the return loop finishes there), 1.5 s in which the rotation stops, and a 1 s
/// still tail.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Seed001Scenario {
    n: usize,
    travel: RateProfile,
    heading: RateProfile,
    leg_times: [f64; 2],
    legs_start: [f64; MAX_WHEELS],
    legs_end: [f64; MAX_WHEELS],
    duration: f64,
}

impl Seed001Scenario {
    /// Builds the scenario for platform `p` with the ICR circling at `r_icr` (m) with body
    /// rotation `omega1` (rad/s) for `circling` seconds.
    pub fn with(p: &Platform, r_icr: f64, omega1: f64, circling: f64) -> Self {
        let w_peak = 2.1;
        let v1 = r_icr * omega1;
        let t3 = 4.0 + circling.max(0.1);
        let t4 = t3 + 1.5;
        let t5 = t4 + 2.0;
        let t6 = t5 + 1.5;
        // Knot times are strictly increasing by construction.
        let heading = RateProfile::new(
            0.0,
            &[
                (0.0, 0.0),
                (1.5, w_peak),
                (2.5, w_peak),
                (4.0, omega1),
                (t5, omega1),
                (t6, 0.0),
            ],
        );
        let travel = RateProfile::new(0.0, &[(2.5, 0.0), (4.0, v1), (t3, v1), (t4, 0.0)]);
        let n = p.n().min(MAX_WHEELS);
        let mut legs_start = [0.0; MAX_WHEELS];
        let mut legs_end = [0.0; MAX_WHEELS];
        for i in 0..n {
            legs_start[i] = p.wheels[i].lambda_max;
            legs_end[i] = p.wheels[i].lambda_nominal;
        }
        let fallback = RateProfile {
            knots: [(0.0, 0.0); 8],
            len: 1,
            q0: 0.0,
            q_at: [0.0; 8],
        };
        Self {
            n,
            travel: travel.unwrap_or(fallback),
            heading: heading.unwrap_or(fallback),
            leg_times: [2.5, 4.0],
            legs_start,
            legs_end,
            duration: t6 + 1.0,
        }
    }

    /// The default scenario: r_icr = 0.44 m, ω1 = 1.0 rad/s, 4.8 s of circling.
    pub fn new(p: &Platform) -> Self {
        Self::with(p, 0.44, 1.0, 4.8)
    }

    /// Total duration (s), including the still tail.
    pub fn duration(&self) -> f64 {
        self.duration
    }

    /// Number of legs.
    pub fn n_legs(&self) -> usize {
        self.n
    }

    /// The reference at time t (s); no allocation.
    pub fn sample(&self, t: f64) -> ReferenceSample {
        let mut r = ReferenceSample {
            t,
            n: self.n,
            ..Default::default()
        };
        let s = self.travel.sample(t);
        let h = self.heading.sample(t);
        // Travel along world x.
        r.z[0] = s[0];
        r.dz[0] = s[1];
        r.ddz[0] = s[2];
        r.dddz[0] = s[3];
        r.z[2] = h[0];
        r.dz[2] = h[1];
        r.ddz[2] = h[2];
        r.dddz[2] = h[3];
        let (ta, tb) = (self.leg_times[0], self.leg_times[1]);
        let tt = tb - ta;
        let sg = smoothstep((t - ta) / tt);
        let inside = t > ta && t < tb;
        for i in 0..self.n {
            let dl = self.legs_end[i] - self.legs_start[i];
            r.z[3 + i] = self.legs_start[i] + dl * sg[1];
            if inside {
                r.dz[3 + i] = dl * sg[2] / tt;
                r.ddz[3 + i] = dl * sg[3] / (tt * tt);
                r.dddz[3 + i] = dl * sg[4] / (tt * tt * tt);
            }
        }
        r
    }
}

/// The three ways the experiment is run.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum ExperimentMode {
    /// Avoidance switched off.
    Off,
    /// Avoidance on, legs kept on their nominal trajectory.
    LegsLocked,
    /// Avoidance on, leg repulsion active.
    LegsFree,
}

/// Measured outcome of one experiment run.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ExperimentResult {
    /// Peak |φ̇| per wheel (rad/s).
    pub peak_steer_rate: [f64; MAX_WHEELS],
    /// Peak |ω| per wheel (rad/s).
    pub peak_wheel_speed: [f64; MAX_WHEELS],
    /// Smallest ICR–singular-point distance over the run (m).
    pub min_icr_wheel_distance: f64,
    /// Largest |(x, y) − (x*, y*)| (m).
    pub max_translation_deviation: f64,
    /// Largest |θ − θ*| (rad).
    pub max_rotation_deviation: f64,
    /// Largest leg deviation |λ − λ*| (m).
    pub max_leg_deviation: f64,
    /// Longest time from leaving the last field of an episode until the deviation is back
    /// under 1 mm / 0.001 rad for good, or the next field entry (s).
    pub return_time: f64,
    /// Cycles with the repulsion active.
    pub active_cycles: usize,
    /// Largest tracking error of the plant w.r.t. the modified reference, position or leg
    /// (m); 0 for the reference-only run.
    pub max_tracking_error: f64,
    /// Peak |steer-rate command| per wheel actually sent (rad/s), after the controller's
    /// desaturation; equals `peak_steer_rate` for the reference-only run.
    pub peak_command_steer_rate: [f64; MAX_WHEELS],
    /// Largest |command|/limit the controller saw before desaturating (1 = at a limit).
    pub max_limit_ratio: f64,
}

/// Tuning used for the experiment's `LegsLocked`/`LegsFree` modes: the default
/// configuration with `legs_free` set by the mode.
pub fn experiment_config(mode: ExperimentMode) -> AvoidanceConfig {
    AvoidanceConfig {
        enabled: mode != ExperimentMode::Off,
        legs_free: mode == ExperimentMode::LegsFree,
        ..AvoidanceConfig::default()
    }
}

/// Runs the scenario with the avoidance only (perfect tracking assumed): the plant is the
/// modified reference itself, steering rates are the reference's analytic ones.
pub fn run_reference_experiment(
    p: &Platform,
    scenario: &Seed001Scenario,
    cfg: AvoidanceConfig,
) -> ExperimentResult {
    let dt = p.dt();
    let mut av = Avoidance::new(p, cfg);
    let steps = (scenario.duration() / dt).ceil() as usize;
    let mut acc = ResultAccumulator::new(p.n().min(MAX_WHEELS));
    for k in 0..=steps {
        let t = k as f64 * dt;
        let nominal = scenario.sample(t);
        let (m, st) = av.step(p, &nominal, dt);
        let (rates, speeds) = reference_wheel_rates(p, &m);
        acc.push(t, &nominal, &m, &st, &rates, &speeds, p.wheel_radius);
        for i in 0..acc.n {
            acc.res.peak_command_steer_rate[i] = acc.res.peak_steer_rate[i];
        }
    }
    acc.finish()
}

struct ResultAccumulator {
    n: usize,
    res: ExperimentResult,
    exit_time: Option<f64>,
    settled: bool,
    was_active: bool,
}

impl ResultAccumulator {
    fn new(n: usize) -> Self {
        Self {
            n,
            res: ExperimentResult {
                peak_steer_rate: [0.0; MAX_WHEELS],
                peak_wheel_speed: [0.0; MAX_WHEELS],
                min_icr_wheel_distance: f64::INFINITY,
                max_translation_deviation: 0.0,
                max_rotation_deviation: 0.0,
                max_leg_deviation: 0.0,
                return_time: 0.0,
                active_cycles: 0,
                max_tracking_error: 0.0,
                peak_command_steer_rate: [0.0; MAX_WHEELS],
                max_limit_ratio: 0.0,
            },
            exit_time: None,
            settled: true,
            was_active: false,
        }
    }

    /// `actual` is the achieved z (the plant, or the modified reference).
    #[allow(clippy::too_many_arguments)]
    fn push(
        &mut self,
        t: f64,
        nominal: &ReferenceSample,
        actual: &ReferenceSample,
        st: &AvoidanceState,
        steer_rates: &[f64; MAX_WHEELS],
        speeds: &[f64; MAX_WHEELS],
        wheel_radius: f64,
    ) {
        let r = &mut self.res;
        for i in 0..self.n {
            r.peak_steer_rate[i] = r.peak_steer_rate[i].max(steer_rates[i].abs());
            r.peak_wheel_speed[i] = r.peak_wheel_speed[i].max(speeds[i].abs() / wheel_radius);
            r.max_leg_deviation = r
                .max_leg_deviation
                .max((actual.z[3 + i] - nominal.z[3 + i]).abs());
        }
        r.min_icr_wheel_distance = r.min_icr_wheel_distance.min(st.min_distance);
        let et = (actual.z[0] - nominal.z[0]).hypot(actual.z[1] - nominal.z[1]);
        let er = crate::angle::diff(actual.z[2], nominal.z[2]).abs();
        r.max_translation_deviation = r.max_translation_deviation.max(et);
        r.max_rotation_deviation = r.max_rotation_deviation.max(er);
        if st.active {
            r.active_cycles += 1;
            self.exit_time = None;
            self.settled = false;
        } else if self.was_active {
            self.exit_time = Some(t);
        }
        if !st.active && !self.settled {
            if let Some(te) = self.exit_time {
                r.return_time = r.return_time.max(t - te);
            }
            if et < 1e-3 && er < 1e-3 {
                self.settled = true;
            }
        }
        self.was_active = st.active;
    }

    fn finish(self) -> ExperimentResult {
        self.res
    }
}

/// ICR–singular-point distance d_i = |u_i|/|θ̇| of every wheel for a reference sample (m),
/// infinite when θ̇ = 0 (used to measure runs with the avoidance switched off).
pub fn icr_wheel_distances(p: &Platform, r: &ReferenceSample) -> [f64; MAX_WHEELS] {
    scan_fields(p, &AvoidanceConfig::default(), r, &r.z).dist
}

impl crate::trajectory::Trajectory for Seed001Scenario {
    fn sample(&self, t: f64) -> ReferenceSample {
        Seed001Scenario::sample(self, t)
    }
    fn duration(&self) -> f64 {
        self.duration
    }
    fn n_legs(&self) -> usize {
        self.n
    }
}

/// The seed-001 experiment trajectory for `p` ([`Seed001Scenario::new`]).
pub fn seed001_scenario(p: &Platform) -> Seed001Scenario {
    Seed001Scenario::new(p)
}

/// Which tracking controller closes the loop in [`run_experiment_with`].
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum ControllerKind {
    /// Dynamic feedback linearization (seed 000).
    Dfl,
    /// The kinematic controller.
    Kinematic,
}

/// Runs the seed-001 experiment in lockstep on [`crate::ideal_plant::IdealPlant`] with the
/// DFL controller (see [`run_experiment_with`]).
pub fn run_experiment(p: &Platform, mode: ExperimentMode) -> ExperimentResult {
    run_experiment_with(p, mode, ControllerKind::Dfl, &experiment_config(mode))
}

/// Runs [`seed001_scenario`] in lockstep at the platform's cycle rate: open-loop alignment
/// to the initial wheel angles, then per cycle nominal sample → [`Avoidance::step`] (unless
/// `mode` is `Off`) → controller → [`crate::ideal_plant::IdealPlant`]. Deviations are those
/// the avoidance commands (modified reference against the nominal one); the plant's own
/// tracking error against the modified reference (position and legs) is reported separately
/// in `max_tracking_error`. `peak_steer_rate` is the analytic steering rate the (modified)
/// reference demands, `peak_command_steer_rate` what the controller sent.
pub fn run_experiment_with(
    p: &Platform,
    mode: ExperimentMode,
    controller: ControllerKind,
    cfg: &AvoidanceConfig,
) -> ExperimentResult {
    use crate::dfl::{alignment_command, ControlInput, DflController, TrackingController};
    use crate::ideal_plant::IdealPlant;
    use crate::kinematic::KinematicController;
    let scenario = seed001_scenario(p);
    let dt = p.dt();
    let n = p.n().min(MAX_WHEELS);
    let r0 = scenario.sample(0.0);
    let mut legs = [0.0; MAX_WHEELS];
    for (i, l) in legs.iter_mut().enumerate().take(n) {
        *l = r0.z[3 + i];
    }
    let mut plant = IdealPlant::new(p, r0.pose(), &legs[..n], &[0.0; MAX_WHEELS][..n]);
    for _ in 0..2500 {
        let (cmd, err) = alignment_command(p, &plant.measurement(), &r0);
        if err < 1e-6 {
            break;
        }
        plant.step(p, &cmd, dt);
    }
    let mut dfl = DflController::new(p);
    let mut kin = KinematicController::new(p);
    let ctrl: &mut dyn TrackingController = match controller {
        ControllerKind::Dfl => &mut dfl,
        ControllerKind::Kinematic => &mut kin,
    };
    ctrl.reset(p, &r0);
    let mut av = Avoidance::new(
        p,
        AvoidanceConfig {
            enabled: mode != ExperimentMode::Off,
            legs_free: mode == ExperimentMode::LegsFree,
            ..*cfg
        },
    );
    let mut acc = ResultAccumulator::new(n);
    let steps = (scenario.duration() / dt).ceil() as usize;
    for k in 0..=steps {
        let t = k as f64 * dt;
        let nominal = scenario.sample(t);
        let (reference, mut st) = av.step(p, &nominal, dt);
        if mode == ExperimentMode::Off {
            st.min_distance = icr_wheel_distances(p, &nominal)
                .iter()
                .fold(f64::INFINITY, |a, b| a.min(*b));
        }
        let m = plant.measurement();
        let q = plant.pose();
        let tl = plant.legs();
        let mut track = (reference.z[0] - q.x).hypot(reference.z[1] - q.y);
        for (i, l) in tl.iter().enumerate().take(n) {
            track = track.max((reference.z[3 + i] - l).abs());
        }
        let (rates, speeds) = reference_wheel_rates(p, &reference);
        acc.push(
            t,
            &nominal,
            &reference,
            &st,
            &rates,
            &speeds,
            p.wheel_radius,
        );
        let out = ctrl.step(
            p,
            &ControlInput {
                measured_twist: None,
                t,
                dt,
                measurement: &m,
                pose: q,
                reference: &reference,
            },
        );
        let res = &mut acc.res;
        res.max_tracking_error = res.max_tracking_error.max(track);
        res.max_limit_ratio = res.max_limit_ratio.max(out.limit_ratio);
        for i in 0..n {
            res.peak_command_steer_rate[i] =
                res.peak_command_steer_rate[i].max(out.command.wheels[i].steer_rate.abs());
        }
        plant.step(p, &out.command, dt);
    }
    acc.finish()
}

#[cfg(test)]
mod tests {
    use super::*;

    fn icr_of(vx: f64, vy: f64, w: f64) -> [f64; 2] {
        icr_from_twist(vx, vy, w).unwrap()
    }

    #[test]
    fn icr_matches_eqs_1_to_3() {
        for &(vx, vy, w) in &[(0.3, -0.2, 0.7), (-0.5, 0.1, -1.3), (0.0, 0.4, 2.0)] {
            let z = icr_of(vx, vy, w);
            let v = f64::hypot(vx, vy);
            let zp = icr_polar(v, icr_direction(vx, vy, w), w);
            assert!((z[0] - zp[0]).abs() < 1e-12 && (z[1] - zp[1]).abs() < 1e-12);
            // The body point at the ICR is at rest: v + ω S z = 0.
            assert!((vx - w * z[1]).abs() < 1e-12 && (vy + w * z[0]).abs() < 1e-12);
        }
        assert!(icr_from_twist(1.0, 0.0, 0.0).is_none());
    }

    #[test]
    fn icr_jacobian_matches_finite_differences_and_eq_5() {
        let h = 1e-6;
        for &(v, g, w) in &[(0.4, 0.3, 0.9), (0.7, -2.0, -1.4), (0.2, 3.0, 0.3)] {
            let j = icr_jacobian(v, g, w);
            let zg1 = icr_polar(v, g + h, w);
            let zg0 = icr_polar(v, g - h, w);
            let zw1 = icr_polar(v, g, w + h);
            let zw0 = icr_polar(v, g, w - h);
            for k in 0..2 {
                let dg = (zg1[k] - zg0[k]) / (2.0 * h);
                let dw = (zw1[k] - zw0[k]) / (2.0 * h);
                assert!(
                    (j[(k, 0)] - dg).abs() < 1e-6,
                    "∂z/∂γ row {k}: {} vs {dg}",
                    j[(k, 0)]
                );
                assert!(
                    (j[(k, 1)] - dw).abs() < 1e-6,
                    "∂z/∂θ̇ row {k}: {} vs {dw}",
                    j[(k, 1)]
                );
            }
            let det = j.determinant();
            assert!((det - v * v / (w * w * w)).abs() < 1e-9 * det.abs().max(1.0));
        }
    }

    #[test]
    fn repulsion_moves_the_icr_as_asked() {
        // Advance the body twist by the pushed accelerations and difference the ICR.
        let h = 1e-6;
        for &(vx, vy, w, zd) in &[
            (0.3, -0.2, 0.7, [0.5, -0.1]),
            (-0.4, 0.35, -1.2, [-0.2, 0.3]),
        ] {
            let push = icr_repulsion(vx, vy, w, zd).unwrap();
            // Paper route: (γ̇, θ̈) = J⁻¹ ż (eq. 10).
            let v = f64::hypot(vx, vy);
            let g = icr_direction(vx, vy, w);
            let sol =
                icr_jacobian(v, g, w).try_inverse().unwrap() * nalgebra::Vector2::new(zd[0], zd[1]);
            assert!((sol[0] - push.gamma_rate).abs() < 1e-9);
            assert!((sol[1] - push.theta_accel).abs() < 1e-9);
            // Constant speed (eq. 13): a ⊥ v.
            let a = push.accel_body;
            assert!((a[0] * vx + a[1] * vy).abs() < 1e-12);
            let z0 = icr_of(vx, vy, w);
            let z1 = icr_of(vx + h * a[0], vy + h * a[1], w + h * push.theta_accel);
            for k in 0..2 {
                let zdot = (z1[k] - z0[k]) / h;
                assert!(
                    (zdot - zd[k]).abs() < 1e-4,
                    "ż[{k}] = {zdot}, wanted {}",
                    zd[k]
                );
            }
        }
        assert!(icr_repulsion(0.0, 0.0, 1.0, [1.0, 0.0]).is_none());
        assert!(icr_repulsion(1.0, 0.0, 0.0, [1.0, 0.0]).is_none());
    }

    #[test]
    fn force_is_continuous_at_the_field_edge_and_zero_outside() {
        let (ds, fm) = (0.14, 1.6);
        let eps = 1e-9;
        assert_eq!(repulsive_force(ds + eps, ds, fm), 0.0);
        assert_eq!(repulsive_force(ds + 0.3, ds, fm), 0.0);
        assert_eq!(repulsive_force(ds, ds, fm), 0.0);
        assert!(repulsive_force(ds - eps, ds, fm) < 1e-15);
        assert!(repulsive_force(ds - 0.01, ds, fm) > 0.0);
        assert!((repulsive_force(0.0, ds, fm) - fm).abs() < 1e-12);
        // Eq. 8 is −dV/dd of eq. 6.
        for &d in &[0.01, 0.07, 0.13] {
            let h = 1e-7;
            let num = -(repulsive_potential(d + h, ds, fm) - repulsive_potential(d - h, ds, fm))
                / (2.0 * h);
            assert!((num - repulsive_force(d, ds, fm)).abs() < 1e-6);
        }
        // Monotone decreasing towards the edge.
        let mut last = f64::INFINITY;
        for k in 0..=100 {
            let f = repulsive_force(ds * k as f64 / 100.0, ds, fm);
            assert!(f <= last);
            last = f;
        }
    }

    #[test]
    fn default_config_is_valid_and_overlaps_are_rejected() {
        let p = Platform::justin();
        AvoidanceConfig::default().validate(&p).unwrap();
        let big = AvoidanceConfig {
            c3: 0.6,
            ..Default::default()
        };
        assert!(matches!(
            big.validate(&p),
            Err(AvoidanceError::Overlap { .. }) | Err(AvoidanceError::CoversCentre { .. })
        ));
        let bad = AvoidanceConfig {
            f_max: f64::NAN,
            ..Default::default()
        };
        assert!(matches!(
            bad.validate(&p),
            Err(AvoidanceError::Invalid { field: "f_max", .. })
        ));
        // `new` with a bad config is a pass-through that says why.
        let a = Avoidance::new(&p, bad);
        assert!(a.config_error().is_some() && !a.config().enabled);
    }

    #[test]
    fn far_from_singular_gives_identical_commands_on_and_off() {
        use crate::dfl::{ControlInput, DflController};
        use crate::ideal_plant::IdealPlant;
        let p = Platform::justin();
        // ICR circling at 0.2 m: never inside a field (they start at 0.465 − 0.14 m).
        let sc = Seed001Scenario::with(&p, 0.2, 1.0, 3.0);
        let dt = p.dt();
        let r0 = sc.sample(0.0);
        let legs: [f64; 4] = [r0.z[3], r0.z[4], r0.z[5], r0.z[6]];
        let run = |on: bool| {
            let mut plant = IdealPlant::new(&p, r0.pose(), &legs, &[0.0; 4]);
            let mut c = DflController::new(&p);
            c.reset(&p, &r0);
            let mut av = Avoidance::new(
                &p,
                AvoidanceConfig {
                    enabled: on,
                    ..Default::default()
                },
            );
            let mut cmds = Vec::new();
            let mut ever_active = false;
            for k in 0..(sc.duration() / dt) as usize {
                let t = k as f64 * dt;
                let nominal = sc.sample(t);
                let (r, st) = av.step(&p, &nominal, dt);
                ever_active |= st.active || st.deviating;
                let m = plant.measurement();
                let out = c.step(
                    &p,
                    &ControlInput {
                        measured_twist: None,
                        t,
                        dt,
                        measurement: &m,
                        pose: plant.pose(),
                        reference: &r,
                    },
                );
                cmds.push(out.command);
                plant.step(&p, &out.command, dt);
            }
            (cmds, ever_active)
        };
        let (on, active) = run(true);
        let (off, _) = run(false);
        assert!(!active);
        assert_eq!(on.len(), off.len());
        for (a, b) in on.iter().zip(off.iter()) {
            for i in 0..4 {
                assert_eq!(
                    a.wheels[i].wheel_speed.to_bits(),
                    b.wheels[i].wheel_speed.to_bits()
                );
                assert_eq!(
                    a.wheels[i].steer_rate.to_bits(),
                    b.wheels[i].steer_rate.to_bits()
                );
            }
        }
    }

    /// A reference rotating about wheel 0's contact point: the nominal ICR sits exactly on
    /// the wheel (d = 0) and then sweeps through it.
    fn pivot_sample(p: &Platform, t: f64) -> ReferenceSample {
        let w = &p.wheels[0];
        let l = w.lambda_nominal;
        let (pc, ps) = (l * w.alpha.cos(), l * w.alpha.sin());
        // θ̇ = 0.8 rad/s about P_0 plus a slow sideways drift that carries the ICR across.
        let om = 0.8;
        let drift = 0.05 * (t - 1.0);
        let th = om * t;
        let (s, c) = th.sin_cos();
        let mut r = ReferenceSample {
            t,
            n: p.n(),
            ..Default::default()
        };
        // Body velocity v_b = −ω S P + drift along the leg normal → ICR = P + drift-shift.
        let vbx = om * ps;
        let vby = -om * pc + drift;
        r.z[2] = th;
        r.dz[0] = c * vbx - s * vby;
        r.dz[1] = s * vbx + c * vby;
        r.dz[2] = om;
        for i in 0..p.n() {
            r.z[3 + i] = p.wheels[i].lambda_nominal;
        }
        r
    }

    #[test]
    fn icr_exactly_on_a_wheel_gives_finite_bounded_output() {
        let p = Platform::justin();
        // Exactly on the wheel.
        let r = pivot_sample(&p, 1.0);
        let d = icr_wheel_distances(&p, &r);
        assert!(d[0] < 1e-12, "d0 = {}", d[0]);
        for legs_free in [false, true] {
            let mut av = Avoidance::new(
                &p,
                AvoidanceConfig {
                    legs_free,
                    ..Default::default()
                },
            );
            let mut max_acc: f64 = 0.0;
            for k in 0..1000 {
                let t = k as f64 * p.dt();
                let (m, st) = av.step(&p, &pivot_sample(&p, t), p.dt());
                for v in
                    m.z.iter()
                        .chain(m.dz.iter())
                        .chain(m.ddz.iter())
                        .chain(m.dddz.iter())
                {
                    assert!(v.is_finite());
                }
                assert!(st.min_distance.is_finite() && st.force.is_finite());
                if k == 250 {
                    assert!(st.active, "the repulsion acts at d = 0");
                }
                max_acc = max_acc.max(st.deviation_accel.amax());
                let (rates, _) = reference_wheel_rates(&p, &m);
                for r in rates.iter().take(4) {
                    assert!(r.is_finite());
                }
            }
            assert!(max_acc < 20.0, "accelerations bounded: {max_acc}");
        }
    }

    #[test]
    fn zero_twist_and_pure_translation_are_harmless() {
        let p = Platform::justin();
        let mut av = Avoidance::new(&p, AvoidanceConfig::default());
        let mut r = ReferenceSample {
            n: 4,
            ..Default::default()
        };
        for i in 0..4 {
            r.z[3 + i] = 0.465;
        }
        let (m, st) = av.step(&p, &r, 0.004);
        assert_eq!(m, r);
        assert!(!st.active && st.icr_body.is_none() && st.min_distance == f64::INFINITY);
        r.dz[0] = 0.5;
        let (m, st) = av.step(&p, &r, 0.004);
        assert_eq!(m, r);
        assert!(!st.active);
        // Pure rotation: ICR at the centre, no repulsion.
        r.dz[0] = 0.0;
        r.dz[2] = 1.0;
        let (m, st) = av.step(&p, &r, 0.004);
        assert_eq!(m, r);
        assert!(!st.active && st.min_distance > 0.3);
    }

    #[test]
    fn an_avoided_path_that_never_enters_a_field_is_the_nominal_bit_for_bit() {
        use crate::trajectory::Trajectory;
        let p = Platform::justin();
        // ICR circling at 0.2 m: never inside a field.
        let sc = Seed001Scenario::with(&p, 0.2, 1.0, 3.0);
        let a = AvoidedTrajectory::plan(&p, Box::new(sc), AvoidanceConfig::default()).unwrap();
        assert_eq!(a.duration().to_bits(), sc.duration().to_bits());
        for k in 0..=3000 {
            let t = sc.duration() * k as f64 / 3000.0;
            assert_eq!(a.sample(t), sc.sample(t), "t = {t}");
            assert!(!a.state_at(t).active);
        }
    }

    #[test]
    fn the_avoided_path_is_the_filters_output_c2_and_returns_to_the_goal() {
        use crate::trajectory::Trajectory;
        let p = Platform::justin();
        let dt = p.dt();
        let sc = Seed001Scenario::new(&p);
        let cfg = AvoidanceConfig::default();
        let a = AvoidedTrajectory::plan(&p, Box::new(sc), cfg).unwrap();
        // The filter online, on the same nominal samples.
        let mut online = Avoidance::new(&p, cfg);
        let (mut max_dz, mut max_ddz, mut max_dev): (f64, f64, f64) = (0.0, 0.0, 0.0);
        let (mut active, mut snaps, mut off_knots) = (0, 0, 0);
        let knots = (a.duration() / dt).round() as usize;
        for k in 0..=knots {
            let t = k as f64 * dt;
            let (m, st) = online.step(&p, &sc.sample(t.min(sc.duration())), dt);
            let s = a.sample(t);
            active += usize::from(st.active);
            snaps += usize::from(st.deviating && online.is_zero());
            assert_eq!(a.state_at(t).active, st.active, "t = {t}");
            let mut off = false;
            for j in 0..7 {
                let acc = st.deviation_accel[j].abs();
                // Value and rate at a knot: the filter's, to δ̈ Δt²/6 and δ̈ Δt/2 (and the
                // settle tolerance where the filter snaps its deviation to zero).
                let tol = cfg.settle_tolerance;
                assert!(
                    (s.z[j] - m.z[j]).abs() <= acc * dt * dt / 6.0 + tol,
                    "z[{j}] at {t}: {} vs {}",
                    s.z[j],
                    m.z[j]
                );
                assert!(
                    (s.dz[j] - m.dz[j]).abs() <= acc * dt / 2.0 + tol / dt,
                    "ż[{j}] at {t}"
                );
                let e = (s.ddz[j] - m.ddz[j]).abs();
                if e > 1e-6 {
                    off = true;
                } else {
                    max_dz = max_dz.max((s.dz[j] - m.dz[j]).abs() - acc * dt / 2.0);
                }
                max_ddz = max_ddz.max(e);
                max_dev = max_dev.max((s.z[j] - sc.sample(t.min(sc.duration())).z[j]).abs());
            }
            off_knots += usize::from(off);
            // C²: no jump of z, ż, z̈ across the knot (the jerk is piecewise constant).
            let (b, c) = (a.sample(t - 1e-7), a.sample(t + 1e-7));
            for j in 0..7 {
                let jerk = b.dddz[j].abs().max(c.dddz[j].abs());
                assert!(
                    (c.ddz[j] - b.ddz[j]).abs() <= jerk * 2e-7 + 1e-6,
                    "z̈[{j}] at {t}"
                );
                assert!((c.dz[j] - b.dz[j]).abs() <= 1e-6, "ż[{j}] at {t}");
            }
        }
        println!(
            "seed 001 avoided: {active} active knots, largest deviation {max_dev:.4}, \
             rate excess {max_dz:.2e}, {off_knots} knots whose acceleration is not the \
             filter's ({snaps} snaps to zero; largest difference {max_ddz:.2e})"
        );
        assert!(active > 100, "the avoidance acts along seed 001: {active}");
        assert!(max_dev > 0.02, "and moves the path: {max_dev}");
        assert!(max_dz <= 1e-9, "{max_dz}");
        // At a knot the B-spline's acceleration is the filter's δ̈, except next to the
        // filter's snaps of δ to zero (the snap is a jump online; a blip of acceleration
        // here, at most 2 × tolerance / Δt²).
        assert!(off_knots <= 3 * snaps, "{off_knots} knots, {snaps} snaps");
        assert!(
            max_ddz <= 2.0 * cfg.settle_tolerance / (dt * dt),
            "{max_ddz}"
        );
        // It ends at the nominal goal, at rest, the deviation returned to zero.
        let end = a.sample(a.duration());
        let goal = sc.sample(sc.duration());
        assert!(a.duration() >= sc.duration());
        for j in 0..7 {
            assert!((end.z[j] - goal.z[j]).abs() < 1e-12, "z[{j}]");
            assert!(end.dz[j] == 0.0 && end.ddz[j] == 0.0, "at rest: {end:?}");
        }
    }

    #[test]
    fn the_time_scaled_avoided_path_keeps_the_icr_where_the_avoidance_put_it() {
        use crate::timescale::{ScaledTrajectory, TimeScaleConfig, VERIFY_TOLERANCE};
        use crate::trajectory::Trajectory;
        let p = Platform::justin();
        let sc = Seed001Scenario::new(&p);
        let avoided =
            AvoidedTrajectory::plan(&p, Box::new(sc), AvoidanceConfig::default()).unwrap();
        let reference =
            AvoidedTrajectory::plan(&p, Box::new(sc), AvoidanceConfig::default()).unwrap();
        let scaled =
            ScaledTrajectory::plan(&p, Box::new(avoided), TimeScaleConfig::default()).unwrap();
        let timing = scaled.timing().unwrap();
        println!("seed 001 avoided and scaled: {timing:?}");
        // Within every limit (the nominal asks 5× the steering acceleration limit).
        assert!(timing.max_ratio <= 1.0 + VERIFY_TOLERANCE, "{timing:?}");
        assert!(timing.min_scale < 1.0, "slowed somewhere: {timing:?}");
        // The clock changes the timing, not the ICR: every ICR–wheel distance of the scaled
        // reference is the avoided path's at the clock's path time.
        let mut checked = 0;
        for k in 0..=4000 {
            let t = scaled.duration() * k as f64 / 4000.0;
            let (tau, v, _, _) = scaled.clock(t);
            if v < 1e-3 {
                continue;
            }
            let ds = icr_wheel_distances(&p, &scaled.sample(t));
            let da = icr_wheel_distances(&p, &reference.sample(tau));
            for i in 0..4 {
                if da[i].is_finite() && da[i] < 1.0 {
                    assert!(
                        (ds[i] - da[i]).abs() <= 1e-9 * (1.0 + da[i]),
                        "t {t} wheel {i}"
                    );
                    checked += 1;
                }
            }
            assert_eq!(
                scaled.avoidance_at(t).unwrap().active,
                reference.state_at(tau).active
            );
        }
        assert!(checked > 1000, "{checked}");
    }

    /// Leg directions and legs of the Justin default, for [`avoid_twist`].
    fn justin_geometry(p: &Platform) -> ([[f64; 2]; 4], [f64; 4]) {
        let mut dirs = [[0.0; 2]; 4];
        let mut legs = [0.0; 4];
        for i in 0..4 {
            let (s, c) = p.wheels[i].alpha.sin_cos();
            dirs[i] = [c, s];
            legs[i] = p.wheels[i].lambda_nominal;
        }
        (dirs, legs)
    }

    /// The twist whose ICR is `z` (body frame) rotating at `om`.
    fn twist_about(z: [f64; 2], om: f64) -> [f64; 3] {
        [om * z[1], -om * z[0], om]
    }

    #[test]
    fn a_command_outside_every_field_passes_unchanged() {
        let p = Platform::justin();
        let (dirs, legs) = justin_geometry(&p);
        let cfg = AvoidanceConfig::default();
        for tw in [
            twist_about([0.2, 0.1], 0.7),
            twist_about([0.465 * 0.8 + 0.2, 0.465 * 0.6], -0.5),
            [0.4, -0.2, 0.0],
            [0.0, 0.0, 1.0],
            [0.0; 3],
        ] {
            let a = avoid_twist(&cfg, &dirs, &legs, tw, &[]);
            assert!(!a.active);
            assert_eq!(a.twist.map(f64::to_bits), tw.map(f64::to_bits));
        }
        // Off: unchanged whatever the command.
        let off = AvoidanceConfig {
            enabled: false,
            ..Default::default()
        };
        let pivot = twist_about([legs[0] * dirs[0][0], legs[0] * dirs[0][1]], 0.6);
        let a = avoid_twist(&off, &dirs, &legs, pivot, &[]);
        assert!(!a.active && a.twist == pivot);
        let nan = avoid_twist(&cfg, &dirs, &legs, [f64::NAN, 0.0, 1.0], &[]);
        assert!(!nan.active);
    }

    #[test]
    fn an_icr_inside_a_field_goes_to_its_edge_at_the_same_speed() {
        let p = Platform::justin();
        let (dirs, legs) = justin_geometry(&p);
        let cfg = AvoidanceConfig::default();
        let pk = [legs[2] * dirs[2][0], legs[2] * dirs[2][1]];
        let ds = field_radius(&cfg, legs[2]);
        for (off, om) in [
            ([0.03, -0.05], 0.8),
            ([-0.1, 0.02], -1.3),
            ([0.0, 0.12], 0.4),
        ] {
            let z = [pk[0] + off[0], pk[1] + off[1]];
            let tw = twist_about(z, om);
            let a = avoid_twist(&cfg, &dirs, &legs, tw, &[]);
            assert!(a.active && a.wheel == Some(2));
            let zn = icr_from_twist(a.twist[0], a.twist[1], a.twist[2]).unwrap();
            // On the edge, along the direction wheel → commanded ICR.
            let e = [zn[0] - pk[0], zn[1] - pk[1]];
            assert!((e[0].hypot(e[1]) - ds).abs() < 1e-12);
            let d = off[0].hypot(off[1]);
            assert!((e[0] / ds - off[0] / d).abs() < 1e-9 && (e[1] / ds - off[1] / d).abs() < 1e-9);
            // Same speed of the base, same sense of rotation (eq. 13: v̇ = 0).
            assert!((a.twist[0].hypot(a.twist[1]) - tw[0].hypot(tw[1])).abs() < 1e-12);
            assert_eq!(a.twist[2].signum(), om.signum());
            // And that is outside every field.
            let again = avoid_twist(&cfg, &dirs, &legs, a.twist, &[]);
            assert!(again.distance >= ds - 1e-12);
        }
    }

    #[test]
    fn an_icr_on_the_wheel_goes_outward_or_to_the_side_used_last() {
        let p = Platform::justin();
        let (dirs, legs) = justin_geometry(&p);
        let cfg = AvoidanceConfig::default();
        let pk = [legs[1] * dirs[1][0], legs[1] * dirs[1][1]];
        let ds = field_radius(&cfg, legs[1]);
        // A pivot about wheel 2 (0.5 mm off, within ICR_ON_WHEEL): outward along the leg.
        let tw = twist_about([pk[0] + 5e-4, pk[1]], 0.6);
        let a = avoid_twist(&cfg, &dirs, &legs, tw, &[]);
        assert!(a.active && a.wheel == Some(1));
        assert_eq!(a.push, dirs[1]);
        let zn = icr_from_twist(a.twist[0], a.twist[1], a.twist[2]).unwrap();
        let r = legs[1] + ds;
        assert!((zn[0] - r * dirs[1][0]).abs() < 1e-12 && (zn[1] - r * dirs[1][1]).abs() < 1e-12);
        // |θ̇| drops by |P|/(|P| + d_s) at the same speed.
        let ratio = (tw[2] / a.twist[2]) * legs[1] / r;
        assert!((ratio - 1.0).abs() < 2e-3, "{ratio}");
        // With a side remembered, that side.
        let side = [0.0, -1.0];
        let sides = [[0.0; 2], side, [0.0; 2], [0.0; 2]];
        let b = avoid_twist(&cfg, &dirs, &legs, tw, &sides);
        assert_eq!(b.push, side);
    }

    #[test]
    fn an_icr_crossing_the_wheel_reverses_its_roll_exactly() {
        let p = Platform::justin();
        let (dirs, legs) = justin_geometry(&p);
        let cfg = AvoidanceConfig::default();
        let pk = [legs[0] * dirs[0][0], legs[0] * dirs[0][1]];
        let om = 0.4;
        // The ICR moves along x through wheel 1's contact point, 20 µm to the side of it.
        let mut sides = [[0.0; 2]; 4];
        let mut last: Option<[f64; 3]> = None;
        let contact = |tw: [f64; 3]| [tw[0] - tw[2] * pk[1], tw[1] + tw[2] * pk[0]];
        for k in -30..=30 {
            let z = [pk[0] + 0.004 * k as f64, pk[1] + 2e-5];
            let a = avoid_twist(&cfg, &dirs, &legs, twist_about(z, om), &sides);
            let inside = (0.004 * k as f64).abs() < field_radius(&cfg, legs[0]);
            assert_eq!(a.active, inside, "k {k}");
            if a.active {
                sides[0] = a.push;
                if let Some(prev) = last {
                    // Wheel 1's velocity keeps its direction exactly, or reverses it exactly.
                    let (u0, u1) = (contact(prev), contact(a.twist));
                    let c = (u0[0] * u1[1] - u0[1] * u1[0]).abs();
                    assert!(c < 1e-15, "k {k}: cross {c}");
                }
                last = Some(a.twist);
            } else {
                sides[0] = [0.0; 2];
                last = None;
            }
        }
        // The same command twice gives the same twist (a held command is one goal).
        let z = [pk[0] + 0.01, pk[1] + 0.003];
        let a = avoid_twist(&cfg, &dirs, &legs, twist_about(z, om), &[]);
        assert!(a.active);
        let c = avoid_twist(&cfg, &dirs, &legs, twist_about(z, om), &[a.push]);
        assert_eq!(a.twist, c.twist);
    }
}
