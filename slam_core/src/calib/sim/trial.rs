//! One Monte-Carlo trial of the calibration filter on a [`Scenario`]: the per-frame driver
//! [`Trial`] (shared with the synthetic tests) and [`run_trial`], which draws a scenario
//! from a seed, starts the filter at nominal and records a per-epoch trace.

use nalgebra::DVector;

use super::{nominal_calibration, Motion, Rng, Scenario};
use crate::calib::params::{CalibParams, CalibPriors};
use crate::calib::state::CalibState;
use crate::calib::{CalibError, CalibFilter, FrameReport, CORE_DIM, IDX_TG, IDX_TR};
use crate::imu::ImuBiases;

/// First calibration entry of the traces (`T_g`; the walking biases are left out).
pub const CALIB_FIRST: usize = IDX_TG;
/// Entries `T_g .. t_r` of the traces (40).
pub const CALIB_DIM: usize = IDX_TR + 1 - IDX_TG;

/// The motion of a trial.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum MotionKind {
    /// [`Motion::calib`]: the seed's Fig. 4.4.
    Calib,
    /// [`Motion::phone`]: walking with a hand-held phone.
    Phone,
}

impl MotionKind {
    /// The motion.
    pub fn motion(self) -> Motion {
        match self {
            Self::Calib => Motion::calib(),
            Self::Phone => Motion::phone(),
        }
    }
}

/// What one trial does.
#[derive(Debug, Clone, Copy)]
pub struct TrialConfig {
    /// The motion.
    pub kind: MotionKind,
    /// Simulated duration, s.
    pub seconds_s: f64,
    /// Seed of the draws (truth, start, landmarks, noise).
    pub seed: u64,
    /// Spacing of the recorded epochs, s (rounded to whole frames).
    pub epoch_period_s: f64,
    /// Filter tuning.
    pub params: CalibParams,
    /// Prior 1σ: both the spread of the true values and the filter's prior.
    pub priors: CalibPriors,
}

impl TrialConfig {
    /// Default tuning with the scenario's pixel σ (0.5 px), epochs every 0.5 s.
    pub fn new(kind: MotionKind, seconds_s: f64, seed: u64) -> Self {
        Self {
            kind,
            seconds_s,
            seed,
            epoch_period_s: 0.5,
            params: CalibParams {
                pixel_sigma: 0.5,
                ..Default::default()
            },
            priors: CalibPriors::default(),
        }
    }
}

/// The calibration block `T_g .. t_r` at one epoch.
#[derive(Debug, Clone, PartialEq)]
pub struct Epoch {
    /// Time, s.
    pub t_s: f64,
    /// Estimate − truth, [`CALIB_DIM`] entries in error-state order.
    pub err: Vec<f64>,
    /// 1σ of the same entries.
    pub sigma: Vec<f64>,
    /// `eᵀ P⁻¹ e` of the block (∞ if its covariance is not positive definite).
    pub nees: f64,
}

/// What [`run_trial`] recorded.
#[derive(Debug, Clone, PartialEq)]
pub struct TrialTrace {
    /// Every `epoch_period_s`, from the first period to the end.
    pub epochs: Vec<Epoch>,
    /// Per frame, the wall time of [`CalibFilter::add_frame`], ms (from the caller's clock).
    pub update_ms: Vec<f64>,
    /// Features used, gated and failed over the run.
    pub used: usize,
    /// Features rejected by the χ² gate.
    pub gated: usize,
    /// Features that failed triangulation or prediction.
    pub failed: usize,
    /// The covariance was symmetric positive semi-definite at the end.
    pub positive: bool,
}

/// One frame of a [`Trial`].
#[derive(Debug, Clone, Copy)]
pub struct FrameStep {
    /// Frame number (1-based).
    pub k: i64,
    /// Middle-row time, s.
    pub t_s: f64,
    /// What the filter did.
    pub report: FrameReport,
    /// Wall time of `add_frame`, ms.
    pub update_ms: f64,
}

/// Drives a filter through a scenario one frame at a time: IMU up to 100 ms past the
/// frame, then the frame's observations.
pub struct Trial<'a> {
    sc: &'a Scenario,
    filter: CalibFilter,
    rng: Rng,
    biases: ImuBiases,
    k_imu: i64,
    k_frame: i64,
}

impl<'a> Trial<'a> {
    /// A filter at `init` on `sc`; `rng` draws the sensor noise.
    pub fn new(
        sc: &'a Scenario,
        params: CalibParams,
        priors: CalibPriors,
        init: CalibState,
        rng: Rng,
    ) -> Self {
        Self {
            sc,
            filter: CalibFilter::new(params, priors, init),
            rng,
            biases: sc.truth.biases,
            k_imu: 0,
            k_frame: 0,
        }
    }

    /// The filter.
    pub fn filter(&self) -> &CalibFilter {
        &self.filter
    }

    /// Feeds the next frame; `now_ns` is the caller's clock (only differences are used).
    pub fn step(&mut self, now_ns: &mut impl FnMut() -> u64) -> Result<FrameStep, CalibError> {
        let sc = self.sc;
        self.k_frame += 1;
        let t_mid_ns = self.k_frame * sc.frame_period_ns;
        while self.k_imu * sc.imu_period_ns <= t_mid_ns + 100_000_000 {
            let s = sc.imu_sample(self.k_imu, &mut self.biases, &mut self.rng);
            self.filter.push_imu(s);
            self.k_imu += 1;
        }
        let obs = sc.frame(t_mid_ns, &mut self.rng);
        let t0 = now_ns();
        let report = self.filter.add_frame(t_mid_ns, &obs)?;
        let update_ms = now_ns().saturating_sub(t0) as f64 * 1e-6;
        Ok(FrameStep {
            k: self.k_frame,
            t_s: t_mid_ns as f64 * 1e-9,
            report,
            update_ms,
        })
    }

    /// Estimate − truth of the core state's calibration part (biases against the current
    /// true, walking ones; the body entries are 0).
    pub fn error(&self) -> DVector<f64> {
        let mut truth = self.sc.truth;
        truth.biases = self.biases;
        self.filter.state().calib_vector() - truth.calib_vector()
    }

    /// The calibration block `T_g .. t_r` now, at time `t_s`.
    pub fn epoch(&self, t_s: f64) -> Epoch {
        let err = self.error().rows(CALIB_FIRST, CALIB_DIM).into_owned();
        let p = self.filter.covariance();
        let block = p.view((CALIB_FIRST, CALIB_FIRST), (CALIB_DIM, CALIB_DIM));
        let nees = block
            .into_owned()
            .cholesky()
            .map_or(f64::INFINITY, |c| err.dot(&c.solve(&err)));
        Epoch {
            t_s,
            sigma: (0..CALIB_DIM)
                .map(|i| p[(CALIB_FIRST + i, CALIB_FIRST + i)].max(0.0).sqrt())
                .collect(),
            err: err.iter().copied().collect(),
            nees,
        }
    }
}

/// The start of a trial: the nominal calibration, zero biases and the true body state at 0
/// moved by a draw from the body prior (θ, p, v).
pub fn nominal_start(sc: &Scenario, priors: &CalibPriors, rng: &mut Rng) -> CalibState {
    nominal_calibration(body_start(sc, priors, rng).nav)
}

/// The truth at 0 with the body state (θ, p, v) moved by a draw from the body prior and
/// zero biases.
pub fn body_start(sc: &Scenario, priors: &CalibPriors, rng: &mut Rng) -> CalibState {
    let mut s = sc.truth;
    s.nav = sc.motion.at(0.0).nav;
    let mut dx = DVector::zeros(CORE_DIM);
    for k in 0..3 {
        dx[k] = rng.normal() * priors.theta;
        dx[3 + k] = rng.normal() * priors.position;
        dx[6 + k] = rng.normal() * priors.velocity;
    }
    s.retract(&dx);
    s.biases = ImuBiases::default();
    s
}

/// One Monte-Carlo trial (`shoal bench calibrate`): truth drawn around nominal with the
/// prior σ ([`Scenario::monte_carlo`]), the filter started at nominal (so the starting
/// errors are the draws: `t_d` 10 ms, `t_r` 5 ms, pinhole 5 px, `p_cb` 2 cm, `T_g`/`T_a`
/// 5e-3, `T_s` 1e-3, distortion 0.05/0.01 at 1σ), `seconds_s` of IMU and frames.
/// `now_ns` times each update (pass a monotonic clock, or `|| 0`).
pub fn run_trial(
    cfg: &TrialConfig,
    mut now_ns: impl FnMut() -> u64,
) -> Result<TrialTrace, CalibError> {
    let mut rng = Rng::new(cfg.seed);
    let sc = Scenario::monte_carlo(cfg.kind.motion(), &cfg.priors, &mut rng);
    let init = nominal_start(&sc, &cfg.priors, &mut rng);
    let mut trial = Trial::new(&sc, cfg.params, cfg.priors, init, rng);
    let frames = (cfg.seconds_s * 1e9 / sc.frame_period_ns as f64).round() as i64;
    let every = ((cfg.epoch_period_s * 1e9 / sc.frame_period_ns as f64).round() as i64).max(1);
    let mut out = TrialTrace {
        epochs: Vec::new(),
        update_ms: Vec::with_capacity(frames as usize),
        used: 0,
        gated: 0,
        failed: 0,
        positive: true,
    };
    for _ in 0..frames {
        let step = trial.step(&mut now_ns)?;
        out.update_ms.push(step.update_ms);
        out.used += step.report.used;
        out.gated += step.report.gated;
        out.failed += step.report.failed;
        if step.k % every == 0 {
            out.epochs.push(trial.epoch(step.t_s));
        }
    }
    out.positive = trial.filter().covariance_is_positive();
    Ok(out)
}

/// The σ of the calibration block's entries in the prior (the starting σ of a trial).
pub fn prior_sigma(priors: &CalibPriors) -> Vec<f64> {
    let d = priors.covariance().diagonal();
    (0..CALIB_DIM).map(|i| d[CALIB_FIRST + i].sqrt()).collect()
}
