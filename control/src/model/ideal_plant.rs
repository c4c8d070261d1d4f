//! Pure kinematic plant for lockstep experiments and tests.
//!
//! Perfect rolling, no noise, no actuator dynamics: each wheel spins exactly at its
//! commanded rate and steers exactly at its commanded steering rate (the angle is the
//! exact integral of the rate). Every cycle is split into [`SUBSTEPS`] sub-intervals; in
//! each, the wheel contact velocities w_i = r ω_i (cos φ_i, sin φ_i) are evaluated at the
//! sub-interval's midpoint angle and the body twist (v_x, v_y, ω) and leg rates λ̇ are the
//! least-squares solution of the 2n rolling equations in 3 + n unknowns
//!
//! ```text
//! w_i = (v_x, v_y) + ω λ_i e⊥_i + λ̇_i e_i,   i = 1 … n
//! ```
//!
//! (the body-frame contact velocity of DESIGN.md / seed 000 eq. 18, solved for the
//! platform motion). The pose is integrated exactly on SE(2)
//! ([`crate::model::kinematics::se2_integrate`]), the legs are integrated and clamped at
//! [λ_min, λ_max]; a leg pushed against its stop is held (λ̇_i = 0) and the remaining
//! unknowns are solved again. Consistent commands give a zero residual; inconsistent
//! ones (a wheel fighting the others) give the least-squares compromise, which is how a
//! real platform with compliant tyres would roughly behave.
//!
//! Non-finite command values are treated as zero; a non-positive or non-finite `dt`
//! leaves the plant unchanged.

// Index loops over parallel per-wheel arrays read better than zipped iterators here.
#![allow(clippy::needless_range_loop)]

use crate::angle;
use crate::model::kinematics::se2_integrate;
use crate::model::platform::Platform;
use crate::types::{Command, Measurement, Pose, Twist, WheelMeasurement, MAX_WHEELS, Z_MAX};
use nalgebra::{SMatrix, SVector};

/// Sub-intervals per [`IdealPlant::step`].
pub const SUBSTEPS: usize = 8;

type NMat = SMatrix<f64, Z_MAX, Z_MAX>;
type NVec = SVector<f64, Z_MAX>;

/// The ideal kinematic plant (see the module docs).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct IdealPlant {
    n: usize,
    pose: Pose,
    legs: [f64; MAX_WHEELS],
    steer: [f64; MAX_WHEELS],
    leg_rates: [f64; MAX_WHEELS],
    cmd: Command,
    twist_body: Twist,
    residual: f64,
}

fn fin(v: f64) -> f64 {
    if v.is_finite() {
        v
    } else {
        0.0
    }
}

impl IdealPlant {
    /// A plant at `pose` with leg extensions `legs` (clamped to each leg's range; missing
    /// entries at the nominal extension) and steering angles `steer` (missing: 0).
    pub fn new(p: &Platform, pose: Pose, legs: &[f64], steer: &[f64]) -> Self {
        let n = p.n().min(MAX_WHEELS);
        let mut l = [0.0; MAX_WHEELS];
        let mut s = [0.0; MAX_WHEELS];
        for (i, w) in p.wheels.iter().enumerate().take(n) {
            let li = legs.get(i).copied().map(fin).unwrap_or(w.lambda_nominal);
            l[i] = li.clamp(w.lambda_min, w.lambda_max);
            s[i] = steer.get(i).copied().map(fin).unwrap_or(0.0);
        }
        Self {
            n,
            pose,
            legs: l,
            steer: s,
            leg_rates: [0.0; MAX_WHEELS],
            cmd: Command::zero(n),
            twist_body: Twist::default(),
            residual: 0.0,
        }
    }

    /// Advances the plant by `dt` seconds under command `cmd` (held constant over `dt`).
    pub fn step(&mut self, p: &Platform, cmd: &Command, dt: f64) {
        if !(dt.is_finite() && dt > 0.0) {
            return;
        }
        let n = self.n;
        let mut c = Command::zero(n);
        for i in 0..n.min(cmd.n) {
            c.wheels[i].wheel_speed = fin(cmd.wheels[i].wheel_speed);
            c.wheels[i].steer_rate = fin(cmd.wheels[i].steer_rate);
        }
        self.cmd = c;
        let h = dt / SUBSTEPS as f64;
        let r = p.wheel_radius;
        for _ in 0..SUBSTEPS {
            let mut w = [[0.0; 2]; MAX_WHEELS];
            for (i, wi) in w.iter_mut().enumerate().take(n) {
                let phi = self.steer[i] + 0.5 * h * c.wheels[i].steer_rate;
                let v = r * c.wheels[i].wheel_speed;
                *wi = [v * phi.cos(), v * phi.sin()];
            }
            let (tw, rates, res) = self.solve(p, &w);
            self.twist_body = tw;
            self.residual = res;
            self.pose = se2_integrate(self.pose, &tw, h);
            for (i, wc) in p.wheels.iter().enumerate().take(n) {
                self.leg_rates[i] = rates[i];
                self.legs[i] = (self.legs[i] + rates[i] * h).clamp(wc.lambda_min, wc.lambda_max);
                self.steer[i] += h * c.wheels[i].steer_rate;
            }
        }
        for i in 0..n {
            self.steer[i] = angle::wrap(self.steer[i]);
        }
    }

    /// Least squares for (v_x, v_y, ω, λ̇) given body contact velocities; legs at a stop
    /// and pushed outward are held.
    fn solve(&self, p: &Platform, w: &[[f64; 2]; MAX_WHEELS]) -> (Twist, [f64; MAX_WHEELS], f64) {
        let n = self.n;
        let mut fixed = [false; MAX_WHEELS];
        let mut x = NVec::zeros();
        for _ in 0..=n {
            let mut a: NMat = NMat::zeros();
            let mut b: NVec = NVec::zeros();
            for (i, wc) in p.wheels.iter().enumerate().take(n) {
                let (sa, ca) = wc.alpha.sin_cos();
                let l = self.legs[i];
                // rows: [1, 0, −λ sα, …, cα (col 3+i)], [0, 1, λ cα, …, sα]
                let rows: [([f64; 3], f64, f64); 2] = [
                    ([1.0, 0.0, -l * sa], ca, w[i][0]),
                    ([0.0, 1.0, l * ca], sa, w[i][1]),
                ];
                for (g, e, rhs) in rows {
                    let le = if fixed[i] { 0.0 } else { e };
                    let mut row = NVec::zeros();
                    row[0] = g[0];
                    row[1] = g[1];
                    row[2] = g[2];
                    row[3 + i] = le;
                    a += row * row.transpose();
                    b += row * rhs;
                }
            }
            for k in 3..Z_MAX {
                let i = k - 3;
                if i >= n || fixed[i] {
                    a[(k, k)] = 1.0;
                    b[k] = 0.0;
                }
            }
            x = a.lu().solve(&b).unwrap_or_else(NVec::zeros);
            let mut changed = false;
            for (i, wc) in p.wheels.iter().enumerate().take(n) {
                if fixed[i] {
                    continue;
                }
                let rate = x[3 + i];
                if (self.legs[i] >= wc.lambda_max && rate > 0.0)
                    || (self.legs[i] <= wc.lambda_min && rate < 0.0)
                {
                    fixed[i] = true;
                    changed = true;
                }
            }
            if !changed {
                break;
            }
        }
        let tw = Twist {
            vx: x[0],
            vy: x[1],
            omega: x[2],
        };
        let mut rates = [0.0; MAX_WHEELS];
        let mut sq = 0.0;
        for (i, wc) in p.wheels.iter().enumerate().take(n) {
            rates[i] = if fixed[i] { 0.0 } else { x[3 + i] };
            let u = contact(wc.alpha, self.legs[i], &tw, rates[i]);
            sq += (u[0] - w[i][0]).powi(2) + (u[1] - w[i][1]).powi(2);
        }
        (tw, rates, (sq / n.max(1) as f64).sqrt())
    }

    /// What the wheel modules would report: steering angle (wrapped), the commanded
    /// steering and spin rates (realised exactly), leg extension and leg rate.
    pub fn measurement(&self) -> Measurement {
        let mut m = Measurement {
            n: self.n,
            ..Measurement::default()
        };
        for i in 0..self.n {
            m.wheels[i] = WheelMeasurement {
                steer_angle: angle::wrap(self.steer[i]),
                steer_rate: self.cmd.wheels[i].steer_rate,
                wheel_speed: self.cmd.wheels[i].wheel_speed,
                leg: self.legs[i],
                leg_rate: self.leg_rates[i],
            };
        }
        m
    }

    /// True pose.
    pub fn pose(&self) -> Pose {
        self.pose
    }

    /// True leg extensions (entries past n are zero).
    pub fn legs(&self) -> [f64; MAX_WHEELS] {
        self.legs
    }

    /// Body twist of the last sub-interval.
    pub fn twist_body(&self) -> Twist {
        self.twist_body
    }

    /// RMS per-wheel mismatch (m/s) of the last sub-interval's least-squares solution:
    /// zero for consistent commands, large when wheels fight each other.
    pub fn residual(&self) -> f64 {
        self.residual
    }
}

fn contact(alpha: f64, l: f64, tw: &Twist, rate: f64) -> [f64; 2] {
    let (sa, ca) = alpha.sin_cos();
    [
        tw.vx - tw.omega * l * sa + rate * ca,
        tw.vy + tw.omega * l * ca + rate * sa,
    ]
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::model::kinematics::wheel_velocity_body;

    /// Commands that realise body twist `tw` and leg rates `rates` at the current state.
    fn consistent(p: &Platform, plant: &IdealPlant, tw_world: &Twist, rates: &[f64]) -> Command {
        let m = plant.measurement();
        let mut c = Command::zero(p.n());
        for i in 0..p.n() {
            let u = wheel_velocity_body(
                p,
                i,
                plant.pose().theta,
                m.wheels[i].leg,
                tw_world,
                rates[i],
            );
            let phi = m.wheels[i].steer_angle;
            c.wheels[i].wheel_speed = (u[0] * phi.cos() + u[1] * phi.sin()) / p.wheel_radius;
        }
        c
    }

    #[test]
    fn translation_with_aligned_wheels_moves_exactly() {
        let p = Platform::justin();
        let dir: f64 = 0.7;
        let mut plant = IdealPlant::new(&p, Pose::default(), &[0.45; 4], &[dir; 4]);
        let tw = Twist {
            vx: 0.2 * dir.cos(),
            vy: 0.2 * dir.sin(),
            omega: 0.0,
        };
        for _ in 0..250 {
            let c = consistent(&p, &plant, &tw, &[0.0; 4]);
            plant.step(&p, &c, 0.004);
            assert!(plant.residual() < 1e-12);
        }
        let q = plant.pose();
        assert!((q.x - 0.2 * dir.cos()).abs() < 1e-12 && (q.y - 0.2 * dir.sin()).abs() < 1e-12);
        assert!(q.theta.abs() < 1e-12);
    }

    #[test]
    fn legs_extend_and_clamp_at_the_stop() {
        let p = Platform::justin();
        // each wheel steered along its leg and rolling outward: legs extend, body stays.
        let steer: Vec<f64> = p.wheels.iter().map(|w| w.alpha).collect();
        let mut plant = IdealPlant::new(&p, Pose::default(), &[0.50; 4], &steer);
        let mut c = Command::zero(4);
        for i in 0..4 {
            c.wheels[i].wheel_speed = 0.05 / p.wheel_radius;
        }
        plant.step(&p, &c, 0.4);
        for i in 0..4 {
            assert!((plant.legs()[i] - 0.52).abs() < 1e-12);
            assert!((plant.measurement().wheels[i].leg_rate - 0.05).abs() < 1e-12);
        }
        assert!(plant.pose().x.abs() < 1e-12 && plant.pose().y.abs() < 1e-12);
        plant.step(&p, &c, 2.0);
        for i in 0..4 {
            assert!(
                (plant.legs()[i] - 0.56).abs() < 1e-12,
                "leg {i} = {}",
                plant.legs()[i]
            );
        }
        // pushing further: the legs stay at the stop and the body does not move
        plant.step(&p, &c, 1.0);
        for i in 0..4 {
            assert!((plant.legs()[i] - 0.56).abs() < 1e-12);
            assert_eq!(plant.measurement().wheels[i].leg_rate, 0.0);
        }
        assert!(plant.pose().x.abs() < 1e-9 && plant.pose().y.abs() < 1e-9);
        assert!(plant.residual() > 0.04);
    }

    #[test]
    fn steering_integrates_the_rate_and_garbage_is_ignored() {
        let p = Platform::justin();
        let mut plant = IdealPlant::new(&p, Pose::default(), &[0.45; 4], &[0.0; 4]);
        let mut c = Command::zero(4);
        c.wheels[0].steer_rate = 1.0;
        c.wheels[1].steer_rate = f64::NAN;
        c.wheels[2].wheel_speed = f64::INFINITY;
        plant.step(&p, &c, 0.5);
        let m = plant.measurement();
        assert!((m.wheels[0].steer_angle - 0.5).abs() < 1e-12);
        assert_eq!(m.wheels[1].steer_angle, 0.0);
        assert_eq!(plant.pose(), Pose::default());
        plant.step(&p, &c, f64::NAN);
        plant.step(&p, &c, -1.0);
        assert!((plant.measurement().wheels[0].steer_angle - 0.5).abs() < 1e-12);
    }
}
