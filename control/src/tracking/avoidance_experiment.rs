//! Seed 001's experiment, run as a pure program: the scenario's reference through the
//! singularity avoidance ([`crate::reference::avoidance`]) and, in closed loop, a tracking
//! controller on the ideal kinematic plant ([`crate::model::ideal_plant`]), with the
//! measures the seed reports (deviations, distances to the singular points, rates).
//!
//! It lives with the controllers because it closes the loop through them; the avoidance
//! itself does not depend on any controller.

use crate::model::platform::Platform;
use crate::reference::avoidance::{
    icr_wheel_distances, reference_wheel_rates, seed001_scenario, Avoidance, AvoidanceConfig,
    Seed001Scenario,
};
use crate::reference::status::AvoidanceState;
use crate::types::{ReferenceSample, MAX_WHEELS};

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

/// Which tracking controller closes the loop in [`run_experiment_with`].
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum ControllerKind {
    /// Dynamic feedback linearization (seed 000).
    Dfl,
    /// The kinematic controller.
    Kinematic,
}

/// Runs the seed-001 experiment in lockstep on [`crate::model::ideal_plant::IdealPlant`] with the
/// DFL controller (see [`run_experiment_with`]).
pub fn run_experiment(p: &Platform, mode: ExperimentMode) -> ExperimentResult {
    run_experiment_with(p, mode, ControllerKind::Dfl, &experiment_config(mode))
}

/// Runs [`seed001_scenario`] in lockstep at the platform's cycle rate: open-loop alignment
/// to the initial wheel angles, then per cycle nominal sample → [`Avoidance::step`] (unless
/// `mode` is `Off`) → controller → [`crate::model::ideal_plant::IdealPlant`]. Deviations are those
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
    use crate::model::ideal_plant::IdealPlant;
    use crate::tracking::dfl::{
        alignment_command, ControlInput, DflController, TrackingController,
    };
    use crate::tracking::kinematic::KinematicController;
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
