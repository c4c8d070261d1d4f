//! Plain SI value types shared by every part of the control stack.
//!
//! Everything here is `Copy` and fixed-size so the 250 Hz cycle never allocates:
//! per-wheel data lives in arrays of [`MAX_WHEELS`] with a live count `n`, and the
//! output vector z = (x, y, θ, λ_1 … λ_n) lives in a [`ZVec`] of length [`Z_MAX`]
//! whose entries past `3 + n` are zero.

use nalgebra::SVector;

/// Largest number of wheel modules a platform file may declare.
pub const MAX_WHEELS: usize = 8;
/// Length of the output vector z = (x, y, θ, λ_1 … λ_MAX_WHEELS).
pub const Z_MAX: usize = 3 + MAX_WHEELS;
/// Output-space vector z = (x, y, θ, λ_1 … λ_n, 0 …) in SI units (m, m, rad, m …).
pub type ZVec = SVector<f64, Z_MAX>;

/// Posture ξ = (x, y, θ) of the body frame in the world frame (m, m, rad).
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct Pose {
    /// World x of the body origin O_B (m).
    pub x: f64,
    /// World y of the body origin O_B (m).
    pub y: f64,
    /// Heading of the body X axis w.r.t. the world X axis (rad), not wrapped.
    pub theta: f64,
}

/// Planar velocity of the body (m/s, m/s, rad/s). The frame is stated where it is used.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct Twist {
    /// Velocity along x (m/s).
    pub vx: f64,
    /// Velocity along y (m/s).
    pub vy: f64,
    /// Angular velocity θ̇ (rad/s).
    pub omega: f64,
}

/// What one wheel module measures, in SI units.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct WheelMeasurement {
    /// Steering angle φ_i of the wheel plane w.r.t. the body X axis (rad), wrapped to (−π, π].
    pub steer_angle: f64,
    /// Steering rate φ̇_i (rad/s).
    pub steer_rate: f64,
    /// Wheel spin rate ω_i (rad/s); the rolling speed is `r · ω_i`.
    pub wheel_speed: f64,
    /// Leg extension λ_i (m).
    pub leg: f64,
    /// Leg extension rate λ̇_i (m/s).
    pub leg_rate: f64,
}

/// One cycle's measurements of all wheel modules.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct Measurement {
    /// Number of live wheels (the first `n` entries of `wheels`).
    pub n: usize,
    /// Per-wheel measurements; entries past `n` are unused.
    pub wheels: [WheelMeasurement; MAX_WHEELS],
}

/// Setpoint for one wheel module, in SI units.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct WheelCommand {
    /// Wheel spin rate setpoint ω_i (rad/s).
    pub wheel_speed: f64,
    /// Steering rate setpoint v_φi (rad/s).
    pub steer_rate: f64,
}

/// One cycle's setpoints for all wheel modules.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct Command {
    /// Number of live wheels (the first `n` entries of `wheels`).
    pub n: usize,
    /// Per-wheel setpoints; entries past `n` are zero.
    pub wheels: [WheelCommand; MAX_WHEELS],
}

impl Command {
    /// All-zero command (wheels stopped, steering held) for `n` wheels.
    pub fn zero(n: usize) -> Self {
        Self {
            n,
            wheels: [WheelCommand::default(); MAX_WHEELS],
        }
    }
}

/// The reference z*(t) and its derivatives at one instant.
///
/// z = (x, y, θ, λ_1 … λ_n) with x, y, θ in the world frame.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct ReferenceSample {
    /// Time of the sample (s, from the trajectory start).
    pub t: f64,
    /// Number of legs in the sample (entries `3 + n ..` are zero).
    pub n: usize,
    /// z*(t).
    pub z: ZVec,
    /// ż*(t).
    pub dz: ZVec,
    /// z̈*(t).
    pub ddz: ZVec,
    /// z⃛*(t) (jerk), for controllers that differentiate the feedforward once more.
    pub dddz: ZVec,
    /// Steering reference for wheels whose reference contact speed is below
    /// [`crate::reference::limits::HOLD_SPEED`] (`valid = false`: the source gives none, and the
    /// controllers steer such wheels as they always did).
    pub steer: SteerReference,
}

/// The steering angle each wheel should hold (or steer to, at the given rate) while its
/// reference contact speed is too small to steer by its direction of travel: a wheel the
/// ICR rests on, a platform at rest, the wheels turning in place before rolling
/// (align-first). Sources that know the geometry of the motion (the live-command shaper,
/// time-scaled trajectories) fill it; the controllers follow it for slow wheels.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct SteerReference {
    /// Whether the source filled it.
    pub valid: bool,
    /// Steering angle per wheel (rad).
    pub angle: [f64; MAX_WHEELS],
    /// Steering rate per wheel (rad/s): non-zero while aligning.
    pub rate: [f64; MAX_WHEELS],
    /// Steering acceleration per wheel (rad/s²).
    pub accel: [f64; MAX_WHEELS],
}

impl ReferenceSample {
    /// Posture part of z*.
    pub fn pose(&self) -> Pose {
        Pose {
            x: self.z[0],
            y: self.z[1],
            theta: self.z[2],
        }
    }
    /// World-frame velocity part of ż*.
    pub fn twist_world(&self) -> Twist {
        Twist {
            vx: self.dz[0],
            vy: self.dz[1],
            omega: self.dz[2],
        }
    }
}
