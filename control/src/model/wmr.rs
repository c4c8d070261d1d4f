//! General wheeled-mobile-robot models (seed 003, lecture on state-space models; seed 004,
//! Sect. 2, after Campion, Bastin and d'Andréa-Novel).
//!
//! A wheel is described in the body frame by its polar position (l, α), its orientation
//! β (fixed, or a steering coordinate), radius r, and for an off-centred caster the offset
//! d, for a Swedish wheel the roller angle γ. With ṗ_R = R(θ) ṗ the body-frame velocity
//! (R(θ) = [[c, s, 0], [−s, c, 0], [0, 0, 1]], seed 003), the constraints are
//!
//! ```text
//! rolling   (all conventional):  [−sin(α+β), cos(α+β), l cos β] ṗ_R + r φ̇ = 0
//! sliding   (fixed, steerable):  [ cos(α+β), sin(α+β), l sin β] ṗ_R = 0
//! sliding   (off-centred caster):[ cos(α+β), sin(α+β), d + l sin β] ṗ_R + d β̇ = 0
//! rolling   (Swedish, γ):        [−sin(α+β+γ), cos(α+β+γ), l cos(β+γ)] ṗ_R + r cos γ φ̇ = 0
//! ```
//!
//! stacked as J₁(β) ṗ_R + J₂ φ̇ = 0, C₁c(β_c) ṗ_R + C₂c β̇_c = 0, C₁*(β_s) ṗ_R = 0 with
//! C₁* = [C₁f; C₁s(β_s)]. Degree of mobility δm = 3 − rank C₁*(β_s); degree of
//! steerability δs = rank C₁s(β_s). Posture kinematic model ṗ = Rᵀ(θ) Σ(β_s) η with the
//! columns of Σ a basis of N(C₁*) (seed 003 eqs. 1–3), and the configuration kinematic
//! model q̇ = S(q) u, q = (p, β_s, β_c, φ), u = (η, ζ) (seed 003 eqs. 19–20):
//!
//! ```text
//! S(q) = [ Rᵀ(θ) Σ        0 ]
//!        [ 0              I ]
//!        [ −C₂c⁻¹ C₁c Σ   0 ]
//!        [ −J₂⁻¹ J₁ Σ     0 ]
//! ```
//!
//! which satisfies D(q) S(q) = 0 for the constraint Jacobian
//! D(q) = [[J₁ R, 0, 0, J₂], [C₁c R, 0, C₂c, 0], [C₁* R, 0, 0, 0]] (columns p, β_s, β_c, φ).
//!
//! This module is analysis code (construction-time, allocating `DMatrix`), not used in
//! the 250 Hz path.

// Index loops over parallel per-wheel arrays read better than zipped iterators here.
#![allow(clippy::needless_range_loop)]

use nalgebra::{DMatrix, DVector};

/// Kind of a wheel (seed 003/004 classification).
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum WheelKind {
    /// Fixed conventional wheel with constant orientation β.
    Fixed {
        /// Orientation β (rad).
        beta: f64,
    },
    /// Centred steerable wheel; β is a steering coordinate β_s.
    Steerable,
    /// Off-centred (caster) wheel with offset d (m); β is a passive coordinate β_c.
    Caster {
        /// Caster offset d (m).
        d: f64,
    },
    /// Swedish wheel with orientation β and roller angle γ (rad).
    Swedish {
        /// Orientation β (rad).
        beta: f64,
        /// Roller angle γ (rad).
        gamma: f64,
    },
}

/// One wheel: kind, polar position (l, α) in the body frame and radius r.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Wheel {
    /// Kind.
    pub kind: WheelKind,
    /// Distance l from the body origin (m).
    pub l: f64,
    /// Polar angle α (rad).
    pub alpha: f64,
    /// Radius r (m).
    pub r: f64,
}

/// A wheel set with its current steering (β_s) and caster (β_c) angles, in wheel order.
#[derive(Clone, Debug, PartialEq)]
pub struct Robot {
    /// The wheels.
    pub wheels: Vec<Wheel>,
}

const RANK_TOL: f64 = 1e-9;

fn rank(m: &DMatrix<f64>) -> usize {
    if m.nrows() == 0 {
        return 0;
    }
    m.clone()
        .svd(false, false)
        .singular_values
        .iter()
        .filter(|s| **s > RANK_TOL)
        .count()
}

impl Robot {
    /// Number of steerable (centred) wheels.
    pub fn n_steer(&self) -> usize {
        self.wheels
            .iter()
            .filter(|w| matches!(w.kind, WheelKind::Steerable))
            .count()
    }
    /// Number of casters.
    pub fn n_caster(&self) -> usize {
        self.wheels
            .iter()
            .filter(|w| matches!(w.kind, WheelKind::Caster { .. }))
            .count()
    }

    /// β of wheel `i` given the angles `angles[i]` for steerable wheels and casters.
    fn beta(&self, i: usize, angles: &[f64]) -> f64 {
        match self.wheels[i].kind {
            WheelKind::Fixed { beta } | WheelKind::Swedish { beta, .. } => beta,
            _ => angles.get(i).copied().unwrap_or(0.0),
        }
    }

    /// Rolling-constraint matrices J₁ (N × 3) and J₂ (N × N diagonal).
    pub fn rolling(&self, angles: &[f64]) -> (DMatrix<f64>, DMatrix<f64>) {
        let n = self.wheels.len();
        let mut j1 = DMatrix::zeros(n, 3);
        let mut j2 = DMatrix::zeros(n, n);
        for (i, w) in self.wheels.iter().enumerate() {
            let b = self.beta(i, angles);
            let (g, scale) = match w.kind {
                WheelKind::Swedish { gamma, .. } => (gamma, gamma.cos()),
                _ => (0.0, 1.0),
            };
            j1[(i, 0)] = -(w.alpha + b + g).sin();
            j1[(i, 1)] = (w.alpha + b + g).cos();
            j1[(i, 2)] = w.l * (b + g).cos();
            j2[(i, i)] = w.r * scale;
        }
        (j1, j2)
    }

    /// Sliding constraints of the fixed and steerable wheels: C₁* (rows in wheel order)
    /// and the steerable part C₁s.
    pub fn sliding(&self, angles: &[f64]) -> (DMatrix<f64>, DMatrix<f64>) {
        let mut star = Vec::new();
        let mut steer = Vec::new();
        for (i, w) in self.wheels.iter().enumerate() {
            let b = self.beta(i, angles);
            let row = [(w.alpha + b).cos(), (w.alpha + b).sin(), w.l * b.sin()];
            match w.kind {
                WheelKind::Fixed { .. } => star.push(row),
                WheelKind::Steerable => {
                    star.push(row);
                    steer.push(row);
                }
                _ => {}
            }
        }
        let mk = |rows: &[[f64; 3]]| DMatrix::from_fn(rows.len(), 3, |r, c| rows[r][c]);
        (mk(&star), mk(&steer))
    }

    /// Caster sliding constraints C₁c (N_c × 3) and C₂c = diag(d).
    pub fn caster(&self, angles: &[f64]) -> (DMatrix<f64>, DMatrix<f64>) {
        let idx: Vec<usize> = (0..self.wheels.len())
            .filter(|&i| matches!(self.wheels[i].kind, WheelKind::Caster { .. }))
            .collect();
        let mut c1 = DMatrix::zeros(idx.len(), 3);
        let mut c2 = DMatrix::zeros(idx.len(), idx.len());
        for (k, &i) in idx.iter().enumerate() {
            let w = self.wheels[i];
            let d = match w.kind {
                WheelKind::Caster { d } => d,
                _ => 0.0,
            };
            let b = self.beta(i, angles);
            c1[(k, 0)] = (w.alpha + b).cos();
            c1[(k, 1)] = (w.alpha + b).sin();
            c1[(k, 2)] = d + w.l * b.sin();
            c2[(k, k)] = d;
        }
        (c1, c2)
    }

    /// Degrees of mobility and steerability (δm, δs) at the given angles.
    pub fn mobility(&self, angles: &[f64]) -> (usize, usize) {
        let (star, steer) = self.sliding(angles);
        (3 - rank(&star).min(3), rank(&steer))
    }

    /// Σ(β_s): an orthonormal basis of N(C₁*) (3 × δm).
    pub fn sigma(&self, angles: &[f64]) -> DMatrix<f64> {
        let (star, _) = self.sliding(angles);
        if star.nrows() == 0 {
            return DMatrix::identity(3, 3);
        }
        let mut padded = DMatrix::zeros(star.nrows().max(3), 3);
        padded.view_mut((0, 0), (star.nrows(), 3)).copy_from(&star);
        let svd = padded.svd(false, true);
        let vt = svd.v_t.unwrap_or_else(|| DMatrix::zeros(3, 3));
        let cols: Vec<DVector<f64>> = (0..3)
            .filter(|&k| svd.singular_values[k] <= RANK_TOL)
            .map(|k| vt.row(k).transpose())
            .collect();
        if cols.is_empty() {
            DMatrix::zeros(3, 0)
        } else {
            DMatrix::from_columns(&cols)
        }
    }

    /// Posture velocity ṗ (world frame) from wheel spin rates by least squares on the
    /// rolling constraints of the conventional non-caster wheels and Swedish wheels plus the
    /// sliding constraints C₁*: [−J₁; C₁*] ṗ_R = [J₂ φ̇; 0], ṗ = Rᵀ(θ) ṗ_R.
    pub fn forward_kinematics(
        &self,
        angles: &[f64],
        theta: f64,
        rates: &[f64],
    ) -> Option<[f64; 3]> {
        let (j1, j2) = self.rolling(angles);
        let (star, _) = self.sliding(angles);
        let mut rows: Vec<[f64; 4]> = Vec::new();
        for (i, w) in self.wheels.iter().enumerate() {
            if matches!(w.kind, WheelKind::Caster { .. }) {
                continue;
            }
            let rhs = j2[(i, i)] * rates.get(i).copied().unwrap_or(0.0);
            rows.push([-j1[(i, 0)], -j1[(i, 1)], -j1[(i, 2)], rhs]);
        }
        for r in 0..star.nrows() {
            rows.push([star[(r, 0)], star[(r, 1)], star[(r, 2)], 0.0]);
        }
        let a = DMatrix::from_fn(rows.len(), 3, |r, c| rows[r][c]);
        let b = DVector::from_fn(rows.len(), |r, _| rows[r][3]);
        let x = (a.transpose() * &a).lu().solve(&(a.transpose() * b))?;
        let (s, c) = theta.sin_cos();
        Some([c * x[0] - s * x[1], s * x[0] + c * x[1], x[2]])
    }

    /// Configuration kinematic model S(q) (rows p, β_s, β_c, φ; columns η, ζ).
    pub fn configuration_model(&self, angles: &[f64], theta: f64) -> DMatrix<f64> {
        let sigma = self.sigma(angles);
        let dm = sigma.ncols();
        let (ns, nc, n) = (self.n_steer(), self.n_caster(), self.wheels.len());
        let rt = rot_t(theta);
        let (j1, j2) = self.rolling(angles);
        let (c1c, c2c) = self.caster(angles);
        let mut s = DMatrix::zeros(3 + ns + nc + n, dm + ns);
        s.view_mut((0, 0), (3, dm)).copy_from(&(&rt * &sigma));
        for k in 0..ns {
            s[(3 + k, dm + k)] = 1.0;
        }
        if nc > 0 {
            let inv =
                DMatrix::from_diagonal(
                    &c2c.diagonal().map(|d| if d != 0.0 { 1.0 / d } else { 0.0 }),
                );
            s.view_mut((3 + ns, 0), (nc, dm))
                .copy_from(&(-(inv * &c1c * &sigma)));
        }
        let inv2 =
            DMatrix::from_diagonal(&j2.diagonal().map(|d| if d != 0.0 { 1.0 / d } else { 0.0 }));
        s.view_mut((3 + ns + nc, 0), (n, dm))
            .copy_from(&(-(inv2 * &j1 * &sigma)));
        s
    }

    /// Constraint Jacobian D(q) with D(q) q̇ = 0 (columns p, β_s, β_c, φ).
    pub fn constraint_jacobian(&self, angles: &[f64], theta: f64) -> DMatrix<f64> {
        let (ns, nc, n) = (self.n_steer(), self.n_caster(), self.wheels.len());
        let r = rot_t(theta).transpose();
        let (j1, j2) = self.rolling(angles);
        let (c1c, c2c) = self.caster(angles);
        let (star, _) = self.sliding(angles);
        let cols = 3 + ns + nc + n;
        let mut d = DMatrix::zeros(n + nc + star.nrows(), cols);
        d.view_mut((0, 0), (n, 3)).copy_from(&(&j1 * &r));
        d.view_mut((0, 3 + ns + nc), (n, n)).copy_from(&j2);
        if nc > 0 {
            d.view_mut((n, 0), (nc, 3)).copy_from(&(&c1c * &r));
            d.view_mut((n, 3 + ns), (nc, nc)).copy_from(&c2c);
        }
        if star.nrows() > 0 {
            d.view_mut((n + nc, 0), (star.nrows(), 3))
                .copy_from(&(&star * &r));
        }
        d
    }
}

/// Rᵀ(θ) (body → world) as a 3 × 3 matrix.
fn rot_t(theta: f64) -> DMatrix<f64> {
    let (s, c) = theta.sin_cos();
    DMatrix::from_row_slice(3, 3, &[c, -s, 0.0, s, c, 0.0, 0.0, 0.0, 1.0])
}

/// Seed 000's platform as a WMR: n centred steerable wheels at (λ_i, α_i) (fixed legs).
pub fn from_platform(p: &crate::model::platform::Platform, legs: &[f64]) -> Robot {
    Robot {
        wheels: p
            .wheels
            .iter()
            .enumerate()
            .map(|(i, w)| Wheel {
                kind: WheelKind::Steerable,
                l: legs.get(i).copied().unwrap_or(w.lambda_nominal),
                alpha: w.alpha,
                r: p.wheel_radius,
            })
            .collect(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::f64::consts::{FRAC_PI_2, FRAC_PI_4, PI};

    fn w(kind: WheelKind, l: f64, alpha: f64) -> Wheel {
        Wheel {
            kind,
            l,
            alpha,
            r: 0.1,
        }
    }

    /// The lecture's five three-wheel types with angles that give mobility.
    fn types() -> Vec<((usize, usize), Robot, Vec<f64>)> {
        let l = 0.3;
        vec![
            (
                (3, 0),
                Robot {
                    wheels: (0..3)
                        .map(|k| {
                            w(
                                WheelKind::Swedish {
                                    beta: 0.0,
                                    gamma: 0.0,
                                },
                                l,
                                2.0 * PI * k as f64 / 3.0,
                            )
                        })
                        .collect(),
                },
                vec![0.0; 3],
            ),
            (
                (2, 0),
                Robot {
                    wheels: vec![
                        w(WheelKind::Fixed { beta: 0.0 }, l, FRAC_PI_2),
                        w(WheelKind::Fixed { beta: PI }, l, -FRAC_PI_2),
                        w(WheelKind::Caster { d: 0.05 }, l, PI),
                    ],
                },
                vec![0.0, 0.0, 0.7],
            ),
            (
                (2, 1),
                Robot {
                    wheels: vec![
                        w(WheelKind::Steerable, l, 0.0),
                        w(WheelKind::Caster { d: 0.05 }, l, 2.0),
                        w(WheelKind::Caster { d: 0.05 }, l, -2.0),
                    ],
                },
                vec![0.4, 0.1, -0.3],
            ),
            (
                (1, 1),
                Robot {
                    wheels: vec![
                        w(WheelKind::Fixed { beta: 0.0 }, l, FRAC_PI_2),
                        w(WheelKind::Fixed { beta: PI }, l, -FRAC_PI_2),
                        w(WheelKind::Steerable, 0.5, 0.0),
                    ],
                },
                vec![0.0, 0.0, 0.3],
            ),
            (
                (1, 2),
                // two steerable wheels (front/back) whose axles meet, plus a caster
                Robot {
                    wheels: vec![
                        w(WheelKind::Steerable, l, 0.0),
                        w(WheelKind::Steerable, l, PI),
                        w(WheelKind::Caster { d: 0.05 }, l, FRAC_PI_2),
                    ],
                },
                vec![0.3, -0.5, 0.2],
            ),
        ]
    }

    #[test]
    fn table_of_types_is_reproduced() {
        for (expect, robot, angles) in types() {
            assert_eq!(robot.mobility(&angles), expect, "robot {robot:?}");
            assert_eq!(robot.sigma(&angles).ncols(), expect.0);
        }
    }

    #[test]
    fn configuration_model_satisfies_d_times_s_equals_zero() {
        for (_, robot, angles) in types() {
            for &th in &[0.0, 0.8, -2.3] {
                let s = robot.configuration_model(&angles, th);
                let d = robot.constraint_jacobian(&angles, th);
                let prod = &d * &s;
                assert!(prod.amax() < 1e-12, "D·S = {prod}");
            }
        }
    }

    #[test]
    fn lecture_differential_drive_example() {
        // θ = π/4, r = 1, d = 0.5; the lecture's wheel "1" (rate 3) is the one whose
        // forward spin alone turns the robot counter-clockwise, i.e. the wheel at
        // y = −d/2 (its Method 1); the other spins at 1. Expected ṗ = (√2, √2, 4).
        let d = 0.5;
        let robot = Robot {
            wheels: vec![
                Wheel {
                    kind: WheelKind::Fixed { beta: PI },
                    l: d / 2.0,
                    alpha: -FRAC_PI_2,
                    r: 1.0,
                },
                Wheel {
                    kind: WheelKind::Fixed { beta: 0.0 },
                    l: d / 2.0,
                    alpha: FRAC_PI_2,
                    r: 1.0,
                },
            ],
        };
        // With these (α, β) the rolling constraints read r φ̇_1 = ẋ_R + (d/2) θ̇ and
        // r φ̇_2 = ẋ_R − (d/2) θ̇: positive spin rolls forward.
        let p = robot
            .forward_kinematics(&[0.0, 0.0], FRAC_PI_4, &[3.0, 1.0])
            .unwrap();
        let s2 = 2f64.sqrt();
        assert!(
            (p[0] - s2).abs() < 1e-12 && (p[1] - s2).abs() < 1e-12 && (p[2] - 4.0).abs() < 1e-12,
            "{p:?}"
        );
        assert_eq!(robot.mobility(&[0.0, 0.0]), (2, 0));
    }

    #[test]
    fn justin_with_fixed_legs_is_type_1_2() {
        // seed 000, footnote 2: the fixed-leg model (7) is of type (1, 2)
        let p = crate::model::platform::Platform::justin();
        let robot = from_platform(&p, &[0.45; 4]);
        // wheels coordinated on an ICR at (0, 2) m in the body frame
        let angles: Vec<f64> = robot
            .wheels
            .iter()
            .map(|wh| {
                let (x, y) = (wh.l * wh.alpha.cos(), wh.l * wh.alpha.sin());
                // wheel plane ⟂ to the ray from the ICR; Campion's rolling direction is
                // (−sin(α+β), cos(α+β)), i.e. at angle α + β + π/2
                let plane = (-(x - 0.0)).atan2(y - 2.0);
                plane - wh.alpha - FRAC_PI_2
            })
            .collect();
        assert_eq!(robot.mobility(&angles), (1, 2));
        // uncoordinated wheels: no mobility
        assert_eq!(robot.mobility(&[0.0, 0.3, 0.9, 1.4]).0, 0);
    }
}
