//! Starting the calibration filter from any device state (issue 18: "`R_cb` … when no
//! `R_cb` is given (a new device), it is first estimated from gyro vs visual rotations and
//! then held fixed"; "initialisation succeeds with |t_d| up to 100 ms"; `VI_NOTES.md` §0,
//! §1). Pure: plain data in (the first seconds of IMU samples and feature tracks, a starting
//! camera that may be poor), plain data out ([`InitResult`]); no IO, no clocks.
//!
//! [`initialize`] runs four steps:
//! 1. [`visual::visual_rotations`]: the camera's rotation between frames
//!    [`InitParams::pair_gap`] apart (rotation-only RANSAC, then the epipolar refinement).
//! 2. [`timing::coarse_time_offset`]: `t_d` from the correlation of the visual and gyro
//!    rotation *angles*, which do not depend on `R_cb`, over ±[`InitParams::max_shift_s`].
//! 3. `R_cb` (unless given) and the gyro bias from the hand-eye rotation constraint
//!    `ΔR_b = R_bc R_c R_bcᵀ` with the gyro intervals shifted by `t_d`
//!    ([`crate::imu::extrinsic_rotation`], refused without rotation about ≥ 2 axes); then
//!    [`timing::fine_time_offset`] refines `t_d` on the full rotation residual, and `R_cb`
//!    is estimated once more at the refined `t_d`.
//!    A camera that turned about one axis only fixes `R_cb` about that axis alone; with
//!    [`InitParams::axis_snap`] the estimate is then replaced by the nearest signed axis
//!    permutation ([`AxisSnap`]: a square mount assumed, reported as such).
//! 4. [`gravity_from_motion`]: the starting orientation `R_gb` (roll and pitch) from the
//!    mean specific force over the window rotated into the first body frame by the gyro
//!    (`R_gb(t) a_s(t) = a_g(t) - g`, and a hand-held device's mean acceleration over
//!    seconds is ~0); its σ from an assumed velocity change over the window.
//!
//! [`filter_start`] turns the result into the filter's [`CalibState`] and [`CalibPriors`].
//!
//! **Step 4 as built**: [`align::align`] (gravity, velocity and biases from the gyro-rotated
//! translation directions and the preintegration); when it fails, [`gravity_from_motion`]
//! with `v = 0`.
//!
//! **Measured** (`init/tests.rs`, 8 s of the simulation, camera 5 px and k1/k2 0.025 off,
//! `t_r` 5 ms off, `R_cb` unknown from identity, 3 % outlier observations): `t_d` +100 ms →
//! error 2.8 ms, −100 ms → 2.3 ms (0.2-0.7 ms from the true camera; the 2 ms is not
//! met from this camera); `R_cb` 0.19° / 0.78°; tilt 3.5° / 5.7° (the `T`-model errors of
//! the simulation: 1.3° with everything else true); then the filter from this start: `t_d`
//! within 0.1 ms after 10 s and 40 s. Real data (`datasets/tests/calib_init_real.rs`):
//! EuRoC AprilGrid, 20 s, reference intrinsics: `R_cb` 0.73° from `T_BS`, `t_d` −0.46 ms
//! (intrinsics 10 px off and no distortion: 8.5° after 30 s); GoPro: `t_d` −11 ms, `R_cb`
//! barely observable (1σ 23°: gimbal-stabilised, small rotations), 10.5° from an axis
//! permutation; the alignment fails there (|g| 15.8).

pub mod align;
pub mod timing;
pub mod visual;

use nalgebra::{Rotation3, Vector3};

use super::integrate::segments;
use super::params::CalibPriors;
use super::state::{CalibState, NavState};
use super::{ImuSample, Observation};
use crate::camera::PinholeRadtan;
use crate::imu::extrinsic_rotation::{
    estimate_extrinsic_rotation, ExtrinsicRotation, ExtrinsicRotationError, ExtrinsicRotationParams,
};
use crate::imu::{ImuBiases, ImuIntrinsics, ImuNoise, Preintegrated, PreintegrationParams};
pub use timing::{GyroTrack, TimeOffsetQuality};
pub use visual::VisualRotation;

/// One frame of tracks: its middle-row stamp (camera clock, `t_mid` of `VI_NOTES.md` §1)
/// and its `(track, pixel)` observations.
#[derive(Debug, Clone, PartialEq)]
pub struct InitFrame {
    /// Middle-row stamp, ns, as given to [`super::CalibFilter::add_frame`].
    pub t_mid_ns: i64,
    /// The observations.
    pub observations: Vec<Observation>,
}

/// Settings of [`initialize`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct InitParams {
    /// Frames between the two views of a visual rotation (3 at 30 Hz: 0.1 s).
    pub pair_gap: usize,
    /// Fewest shared tracks (and inliers) of a pair.
    pub min_matches: usize,
    /// Iterations of the two-point rotation-only RANSAC.
    pub ransac_iterations: usize,
    /// Angular bound of that RANSAC, rad: loose, it only drops mismatches (parallax is
    /// allowed for by the epipolar refinement).
    pub rotation_ransac_rad: f64,
    /// Epipolar (Sampson) inlier bound and Cauchy scale, px at the starting focal length.
    pub inlier_px: f64,
    /// Levenberg-Marquardt iterations of the epipolar refinement.
    pub refine_iterations: usize,
    /// RANSAC seed.
    pub seed: u64,
    /// `t_d` search half-width, s (the issue: |t_d| up to 100 ms; default 200 ms).
    pub max_shift_s: f64,
    /// Grid step of the coarse search, s.
    pub shift_step_s: f64,
    /// Least distance of the "second peak" from the coarse peak, s.
    pub peak_separation_s: f64,
    /// Half-width of the fine `t_d` search around the coarse value, s.
    pub fine_half_width_s: f64,
    /// Grid step of the fine search, s.
    pub fine_step_s: f64,
    /// Refine `t_d` once more with [`align::epipolar_time_offset`] (off by default: on the
    /// simulation it removes the 2-4 ms bias of the rotation fit when `R_cb` is exact, but an
    /// estimated `R_cb` 0.8° off drives it to the edge of its window).
    pub epipolar_time: bool,
    /// Least correlation peak accepted (below: [`InitError::NoTimeOffset`]).
    pub min_peak: f64,
    /// IMU noise densities (the preintegrations of the `R_cb` fit).
    pub imu_noise: ImuNoise,
    /// Settings of the `R_cb` fit.
    pub extrinsic: ExtrinsicRotationParams,
    /// Assumed velocity change over the gravity window, m/s: `σ_θ ≈ Δv / (T g)`.
    pub velocity_change: f64,
    /// Least `σ_θ` returned, rad.
    pub min_sigma_theta: f64,
    /// Starting velocity 1σ, m/s, when the alignment fails (the start is then taken at
    /// rest: `v = 0`).
    pub sigma_velocity: f64,
    /// Frames between the two views of a translation direction ([`align`]).
    pub translation_gap: usize,
    /// Relinearisations of the alignment.
    pub align_iterations: usize,
    /// 1σ of one alignment row (camera displacement across its direction), m.
    pub align_sigma_m: f64,
    /// Prior of a gyro-bias step of the alignment, rad/s: tight by default, i.e. the bias is
    /// in effect not estimated there. Measured on the simulation with `T` errors of the
    /// prior's size: free, the bias absorbs the `T_s a_s` (g-sensitivity) and `T_g` errors
    /// and the tilt error grows from 1.3° to 1.8°, the velocity error from 0.14 to 0.6 m/s.
    pub align_gyro_bias_prior: f64,
    /// Damping prior of an accelerometer-bias step of the alignment, m/s².
    pub align_accel_bias_prior: f64,
    /// Least `σ_θ` / σ_v reported by the alignment, rad and m/s: its covariance ignores the
    /// `T`-model errors, which give ~1.3° and ~0.15 m/s on the simulation.
    pub align_min_sigma: (f64, f64),
    /// The square-mount prior of [`AxisSnap`] (`None`: an `R_cb` whose 1σ exceeds
    /// [`ExtrinsicRotationParams::max_sigma_rad`] fails the initialisation).
    pub axis_snap: Option<AxisSnap>,
}

/// A device whose camera and IMU axes are mounted square to each other (phones, action
/// cameras): when the camera turned about fewer than two axes, `R_cb` is determined only
/// about the turn's axis (its 1σ exceeds [`ExtrinsicRotationParams::max_sigma_rad`]); it is
/// then replaced by the nearest signed axis permutation ([`nearest_axis_permutation`]) when
/// the estimate lies within [`Self::max_angle_rad`] of it and its 1σ is below
/// [`Self::max_fit_sigma_rad`]. Otherwise the initialisation fails as before.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct AxisSnap {
    /// Largest angle from the estimate to the permutation, rad.
    pub max_angle_rad: f64,
    /// Largest 1σ of the estimate itself, rad.
    pub max_fit_sigma_rad: f64,
    /// 1σ of a snapped `R_cb` used downstream (the assumed accuracy of a square mount;
    /// widens the `T_g`, `T_a` priors in [`filter_start`]), rad.
    pub sigma_rad: f64,
}

impl Default for AxisSnap {
    fn default() -> Self {
        Self {
            max_angle_rad: 20f64.to_radians(),
            max_fit_sigma_rad: 45f64.to_radians(),
            sigma_rad: 2f64.to_radians(),
        }
    }
}

/// The proper signed axis permutation nearest `r` (of the 24) and the angle between them.
pub fn nearest_axis_permutation(r: &Rotation3<f64>) -> (Rotation3<f64>, f64) {
    let mut best = (Rotation3::identity(), f64::INFINITY);
    for perm in [
        [0, 1, 2],
        [0, 2, 1],
        [1, 0, 2],
        [1, 2, 0],
        [2, 0, 1],
        [2, 1, 0],
    ] {
        for signs in 0..8u32 {
            let mut m = nalgebra::Matrix3::zeros();
            for (row, &col) in perm.iter().enumerate() {
                m[(row, col)] = if signs & (1 << row) == 0 { 1.0 } else { -1.0 };
            }
            if m.determinant() < 0.0 {
                continue;
            }
            let p = Rotation3::from_matrix_unchecked(m);
            let angle = (p.inverse() * r).angle();
            if angle < best.1 {
                best = (p, angle);
            }
        }
    }
    best
}

impl Default for InitParams {
    fn default() -> Self {
        Self {
            pair_gap: 3,
            min_matches: 12,
            ransac_iterations: 64,
            rotation_ransac_rad: 0.03,
            inlier_px: 2.0,
            refine_iterations: 15,
            seed: 0x1417,
            max_shift_s: 0.2,
            shift_step_s: 0.001,
            peak_separation_s: 0.04,
            fine_half_width_s: 0.01,
            fine_step_s: 0.0005,
            epipolar_time: false,
            min_peak: 0.5,
            imu_noise: ImuNoise::default(),
            extrinsic: ExtrinsicRotationParams {
                visual_sigma_rad: 0.003,
                ..Default::default()
            },
            velocity_change: 1.0,
            min_sigma_theta: 0.02,
            sigma_velocity: 1.5,
            translation_gap: 6,
            align_iterations: 4,
            align_sigma_m: 0.005,
            align_gyro_bias_prior: 1e-3,
            align_accel_bias_prior: 0.3,
            align_min_sigma: (0.03, 0.3),
            axis_snap: None,
        }
    }
}

/// What [`initialize`] found.
#[derive(Debug, Clone, PartialEq)]
pub struct InitResult {
    /// Time offset `t_d`, s: the IMU time of a frame's middle row is `t_mid + t_d`.
    pub t_d_s: f64,
    /// How well the coarse search was determined, and the fine fit's residual.
    pub t_d_quality: TimeOffsetQuality,
    /// Camera-from-body rotation `R_cb` (the given one when one was given).
    pub r_cb: Rotation3<f64>,
    /// Whether `r_cb` was given (not estimated).
    pub r_cb_given: bool,
    /// RMS hand-eye residual angle of the `R_cb` fit, rad.
    pub r_cb_residual_rad: f64,
    /// 1σ of `R_cb` about its worst axis, rad (0 when given; when snapped,
    /// [`AxisSnap::sigma_rad`]).
    pub r_cb_sigma_rad: f64,
    /// When `R_cb` was snapped to an axis permutation ([`AxisSnap`]): the fit's own 1σ and
    /// its angle to the permutation, rad.
    pub r_cb_snap: Option<(f64, f64)>,
    /// Pairs the `R_cb` fit rejected.
    pub r_cb_outliers: usize,
    /// Gyro bias of the `R_cb` fit, rad/s (zero when that fit was refused with a given
    /// `R_cb`): absorbs the visual rotations' systematic errors, kept as a diagnostic.
    pub hand_eye_gyro_bias: Vector3<f64>,
    /// Biases: the alignment's when it succeeded, else the hand-eye gyro bias and a zero
    /// accelerometer bias.
    pub biases: ImuBiases,
    /// `|g|` found by the alignment (NaN when it failed and the mean specific force gave
    /// gravity), m/s².
    pub gravity_norm: f64,
    /// Time of the starting state, ns (IMU clock): the first IMU sample.
    pub t_start_ns: i64,
    /// Starting orientation `R_gb` (gravity along `-z`; yaw arbitrary).
    pub r_gb: Rotation3<f64>,
    /// Starting velocity (zero: not observed here), m/s.
    pub v_gb: Vector3<f64>,
    /// 1σ of the orientation (roll and pitch), rad.
    pub sigma_theta_rad: f64,
    /// 1σ of the velocity, m/s.
    pub sigma_velocity: f64,
    /// Visual rotations found (all pairs) and used (covered by the IMU for every shift).
    pub rotations_found: usize,
    /// Visual rotations used by the time and rotation fits.
    pub rotations_used: usize,
}

/// Why [`initialize`] failed.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum InitError {
    /// Too few visual rotations (tracks too short, too few matches), or too little IMU
    /// around them.
    #[error("{found} visual rotations ({used} inside the IMU span ± the t_d search): too few")]
    TooFewRotations {
        /// Visual rotations found.
        found: usize,
        /// Covered by the IMU for every shift.
        used: usize,
    },
    /// The angle correlation has no clear peak (no motion, or unrelated streams).
    #[error("time offset not found: correlation peak {peak:.3} (second peak {second:.3})")]
    NoTimeOffset {
        /// Correlation peak.
        peak: f64,
        /// Highest other local maximum.
        second: f64,
    },
    /// `R_cb` could not be estimated (the camera did not turn about two axes).
    #[error("camera-IMU rotation: {0}")]
    Rotation(#[from] ExtrinsicRotationError),
    /// No IMU samples.
    #[error("no IMU samples")]
    NoImu,
}

/// What the initialisation starts from besides the data.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct InitGuess {
    /// Starting camera (may be poor: e.g. focal 0.7 × width, no distortion).
    pub camera: PinholeRadtan,
    /// Readout time guess, s (0: global shutter); used to move every bearing to its frame's
    /// middle-row time in a second pass ([`visual::Derotation`]).
    pub t_r: f64,
    /// `R_cb` when known: then held as given (only `t_d`, the gyro bias and gravity are
    /// estimated).
    pub r_cb: Option<Rotation3<f64>>,
    /// Body origin in the camera frame (guess; the alignment's lever arm), m.
    pub p_cb: Vector3<f64>,
}

/// Runs the four steps (module docs) on `imu` (sorted, IMU clock) and `frames` (sorted,
/// camera clock). With a rolling shutter (`guess.t_r ≠ 0`) steps 1 and 3 are repeated once
/// with the bearings moved to their middle-row times by the first pass's gyro, `R_cb` and
/// `t_d`: the rows' time skew otherwise scales the visual rotations by `~ f ω t_r / N`
/// (3 % at 1.5 rad/s, 25 ms) and biases `R_cb` by ~1.5° (measured on the simulation).
pub fn initialize(
    imu: &[ImuSample],
    frames: &[InitFrame],
    guess: &InitGuess,
    params: &InitParams,
) -> Result<InitResult, InitError> {
    let first = imu.first().ok_or(InitError::NoImu)?;
    let strict_sigma = params.extrinsic.max_sigma_rad;
    let mut relaxed = *params;
    if let (Some(snap), None) = (params.axis_snap, guess.r_cb) {
        relaxed.extrinsic.max_sigma_rad = strict_sigma.max(snap.max_fit_sigma_rad);
    }
    let params = &relaxed;
    let raw = GyroTrack::new(imu, &Vector3::zeros());
    let rots = visual::visual_rotations(frames, &guess.camera, None, params);
    let used = timing::covered(&rots, &raw, params.max_shift_s);
    if used.len() < params.extrinsic.min_pairs.max(10) {
        return Err(InitError::TooFewRotations {
            found: rots.len(),
            used: used.len(),
        });
    }
    let (coarse, mut quality) =
        timing::coarse_time_offset(&used, &raw, params).ok_or(InitError::NoTimeOffset {
            peak: f64::NAN,
            second: f64::NAN,
        })?;
    if quality.peak.is_nan() || quality.peak < params.min_peak {
        return Err(InitError::NoTimeOffset {
            peak: quality.peak,
            second: quality.second_peak,
        });
    }
    let r_cb = guess.r_cb;
    let (mut t_d, mut fit, mut fine_rms) =
        refine_rotation_and_time(imu, &used, coarse, r_cb, params)?;
    let mut counts = (rots.len(), used.len());
    let mut last_rots = rots.clone();
    if guess.t_r != 0.0 {
        let gyro = GyroTrack::new(imu, &fit.gyro_bias);
        let d = visual::Derotation {
            gyro: &gyro,
            r_cb: fit.r_bc.inverse(),
            t_d,
            t_r: guess.t_r,
        };
        last_rots = visual::visual_rotations(frames, &guess.camera, Some(&d), params);
        let used = timing::covered(&last_rots, &raw, params.max_shift_s);
        (t_d, fit, fine_rms) = refine_rotation_and_time(imu, &used, t_d, r_cb, params)?;
        counts = (last_rots.len(), used.len());
    }
    let input = align::AlignInput {
        imu,
        frames,
        camera: &guess.camera,
        r_cb: r_cb.unwrap_or_else(|| fit.r_bc.inverse()),
        p_cb: guess.p_cb,
        t_d,
        t_r: guess.t_r,
        biases: ImuBiases::default(),
    };
    let epipolar = params
        .epipolar_time
        .then(|| align::epipolar_time_offset(&input, t_d, params))
        .flatten();
    quality.visual_s = t_d;
    if let Some(t) = epipolar {
        t_d = t;
        let used = timing::covered(&last_rots, &raw, params.max_shift_s);
        fit = refit(imu, &used, t_d, r_cb, params)?;
    }
    quality.fine_rms_rad = fine_rms;
    let given = r_cb.is_some();
    let (r_cb, snap) = match r_cb {
        Some(r) => (r, None),
        None => snapped(&fit, strict_sigma, params.axis_snap)?,
    };
    let start = start_state(imu, frames, guess, r_cb, t_d, &fit, params);
    Ok(InitResult {
        t_d_s: t_d,
        t_d_quality: quality,
        r_cb,
        r_cb_given: given,
        r_cb_residual_rad: fit.rms_rad,
        r_cb_sigma_rad: match (given, snap) {
            (true, _) => 0.0,
            (false, Some(_)) => params.axis_snap.map_or(fit.sigma_rad, |a| a.sigma_rad),
            (false, None) => fit.sigma_rad,
        },
        r_cb_snap: snap,
        r_cb_outliers: fit.outliers,
        hand_eye_gyro_bias: fit.gyro_bias,
        biases: start.biases,
        gravity_norm: start.gravity_norm,
        t_start_ns: first.t_ns,
        r_gb: start.r_gb,
        v_gb: start.v_gb,
        sigma_theta_rad: start.sigma_theta,
        sigma_velocity: start.sigma_velocity,
        rotations_found: counts.0,
        rotations_used: counts.1,
    })
}

/// `(fit σ, angle to the permutation)` of a snapped `R_cb`, rad.
type Snap = Option<(f64, f64)>;

/// The estimated `R_cb` when its 1σ is within `strict` rad; else the nearest axis
/// permutation under `snap` ([`AxisSnap`]) with its [`Snap`]; else not observable.
fn snapped(
    fit: &ExtrinsicRotation,
    strict: f64,
    snap: Option<AxisSnap>,
) -> Result<(Rotation3<f64>, Snap), InitError> {
    let r_cb = fit.r_bc.inverse();
    if fit.sigma_rad <= strict {
        return Ok((r_cb, None));
    }
    let (perm, angle) = nearest_axis_permutation(&r_cb);
    match snap {
        Some(s) if angle <= s.max_angle_rad && fit.sigma_rad <= s.max_fit_sigma_rad => {
            Ok((perm, Some((fit.sigma_rad, angle))))
        }
        _ => Err(ExtrinsicRotationError::NotObservable {
            sigma_deg: fit.sigma_rad.to_degrees(),
        }
        .into()),
    }
}

/// Step 4: [`align::align`], or when it fails [`gravity_from_motion`] with `v = 0`.
fn start_state(
    imu: &[ImuSample],
    frames: &[InitFrame],
    guess: &InitGuess,
    r_cb: Rotation3<f64>,
    t_d: f64,
    fit: &ExtrinsicRotation,
    params: &InitParams,
) -> align::Alignment {
    let input = align::AlignInput {
        imu,
        frames,
        camera: &guess.camera,
        r_cb,
        p_cb: guess.p_cb,
        t_d,
        t_r: guess.t_r,
        biases: ImuBiases::default(),
    };
    if let Some(mut a) = align::align(&input, params) {
        a.sigma_theta = a.sigma_theta.max(params.align_min_sigma.0);
        a.sigma_velocity = a.sigma_velocity.max(params.align_min_sigma.1);
        return a;
    }
    let gyro = GyroTrack::new(imu, &fit.gyro_bias);
    let (r_gb, sigma_theta) = gravity_from_motion(imu, &gyro, params);
    align::Alignment {
        r_gb,
        v_gb: Vector3::zeros(),
        biases: ImuBiases {
            gyro: fit.gyro_bias,
            accel: Vector3::zeros(),
        },
        gravity_norm: f64::NAN,
        sigma_theta,
        sigma_velocity: params.sigma_velocity,
        pairs: 0,
    }
}

/// `R_bc`, `b_g` at `t_d` ([`fit_rotation`]), or the given `R_cb` with the fit's `b_g` (zero
/// if refused).
fn refit(
    imu: &[ImuSample],
    used: &[&VisualRotation],
    t_d: f64,
    r_cb: Option<Rotation3<f64>>,
    params: &InitParams,
) -> Result<ExtrinsicRotation, InitError> {
    let fit = fit_rotation(imu, used, t_d, params);
    match (fit, r_cb) {
        (Ok(f), Some(r)) => Ok(ExtrinsicRotation {
            r_bc: r.inverse(),
            ..f
        }),
        (Err(_), Some(r)) => Ok(ExtrinsicRotation {
            r_bc: r.inverse(),
            gyro_bias: Vector3::zeros(),
            sigma_rad: 0.0,
            rms_rad: f64::NAN,
            outliers: 0,
        }),
        (Ok(f), None) => Ok(f),
        (Err(e), None) => Err(e.into()),
    }
}

/// Step 3: `R_bc` and `b_g` at the coarse `t_d`, the fine `t_d` with them, and `R_bc`, `b_g`
/// again at the fine `t_d`. With a given `R_cb` the fit only supplies `b_g` (zero if it is
/// refused) and the fine search uses the given rotation.
fn refine_rotation_and_time(
    imu: &[ImuSample],
    used: &[&VisualRotation],
    coarse: f64,
    r_cb: Option<Rotation3<f64>>,
    params: &InitParams,
) -> Result<(f64, ExtrinsicRotation, f64), InitError> {
    let fit_at = |t_d: f64| refit(imu, used, t_d, r_cb, params);
    let first = fit_at(coarse)?;
    let gyro = GyroTrack::new(imu, &first.gyro_bias);
    let (t_d, _) = timing::fine_time_offset(used, &gyro, &first.r_bc, coarse, params)
        .unwrap_or((coarse, f64::NAN));
    let fit = fit_at(t_d)?;
    let gyro = GyroTrack::new(imu, &fit.gyro_bias);
    let rms = timing::fine_time_offset(used, &gyro, &fit.r_bc, t_d, params)
        .map_or(f64::NAN, |(_, rms)| rms);
    Ok((t_d, fit, rms))
}

/// `R_bc` and `b_g` from the visual rotations and the gyro preintegrated over the intervals
/// shifted by `t_d` ([`estimate_extrinsic_rotation`]; its `R_c,ij = R_wc,iᵀ R_wc,j` is our
/// [`VisualRotation::r_c`]).
pub fn fit_rotation(
    imu: &[ImuSample],
    rots: &[&VisualRotation],
    t_d: f64,
    params: &InitParams,
) -> Result<ExtrinsicRotation, ExtrinsicRotationError> {
    let pre_params = PreintegrationParams::new(&params.imu_noise, &ImuIntrinsics::default())
        .expect("finite noise densities and identity intrinsics");
    let (mut r_c, mut pre) = (Vec::new(), Vec::new());
    for r in rots {
        let shift = t_d * 1e9;
        let Some(segs) = segments(imu, r.t0_ns as f64 + shift, r.t1_ns as f64 + shift) else {
            continue;
        };
        let mut p = Preintegrated::new(ImuBiases::default(), pre_params);
        for (dt, g, a) in segs {
            p.integrate(dt, &g, &a);
        }
        r_c.push(r.r_c);
        pre.push(p);
    }
    estimate_extrinsic_rotation(&r_c, &pre, &params.extrinsic)
}

/// Step 4: `R_gb` at the first sample from the mean specific force rotated into the first
/// body frame, `f̄ = (1/T) ∫ R_b0,b(t) a_s(t) dt`; since `R_gb(t) a_s = a_g - g`,
/// `R_gb0 f̄ = ā_g + (0, 0, 9.81)` and with `ā_g ≈ 0` (`|ā_g| ≤ Δv / T`) `R_gb0` turns `f̄`
/// onto `+z` (the smallest such rotation: yaw is unobservable and arbitrary). Returns
/// `(R_gb0, σ_θ)` with `σ_θ = max(atan(Δv / (T g)), min)` ([`InitParams::velocity_change`]).
pub fn gravity_from_motion(
    imu: &[ImuSample],
    gyro: &GyroTrack,
    params: &InitParams,
) -> (Rotation3<f64>, f64) {
    let mut f = Vector3::zeros();
    let mut span = 0.0;
    for w in imu.windows(2) {
        let dt = (w[1].t_ns - w[0].t_ns) as f64 * 1e-9;
        let Some(q) = gyro.at(w[0].t_ns as f64) else {
            continue;
        };
        f += q * (0.5 * (w[0].accel + w[1].accel)) * dt;
        span += dt;
    }
    let r = Rotation3::rotation_between(&f, &Vector3::z()).unwrap_or_else(|| {
        // f̄ pointing down: a half turn about x.
        Rotation3::from_axis_angle(&Vector3::x_axis(), std::f64::consts::PI)
    });
    let g = crate::imu::GRAVITY;
    let sigma = (params.velocity_change / (span.max(1e-3) * g)).atan();
    (r, sigma.max(params.min_sigma_theta))
}

/// Settings of [`filter_start`]: the priors after initialisation.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct StartPriors {
    /// `t_d` prior after initialisation, s (the issue: small, e.g. 5 ms).
    pub t_d: f64,
}

impl Default for StartPriors {
    fn default() -> Self {
        Self { t_d: 0.005 }
    }
}

/// The filter's starting state and priors from an [`InitResult`]: `guess` supplies what the
/// initialisation does not estimate (camera, `p_cb`, `t_r`, `T` matrices, accelerometer
/// bias); the result sets the time, `R_gb`, `v_gb = 0`, `R_cb`, `t_d` and the gyro bias.
/// Priors: `θ` and velocity from the result's σ, `t_d` from `start`, and the `T_g`, `T_a`
/// element priors widened by `R_cb`'s 1σ (a mis-rotation of the fixed `R_cb` is absorbed by
/// `T_g` and `T_a`, `VI_NOTES.md` §2).
pub fn filter_start(
    init: &InitResult,
    guess: &CalibState,
    priors: &CalibPriors,
    start: &StartPriors,
) -> (CalibState, CalibPriors) {
    let mut s = *guess;
    s.t_ns = init.t_start_ns;
    s.nav = NavState {
        r_gb: init.r_gb,
        p_gb: Vector3::zeros(),
        v_gb: init.v_gb,
    };
    s.r_cb = init.r_cb;
    s.t_d = init.t_d_s;
    s.biases = init.biases;
    let widen = |p: f64| p.hypot(init.r_cb_sigma_rad);
    let p = CalibPriors {
        theta: init.sigma_theta_rad,
        velocity: init.sigma_velocity,
        t_d: start.t_d,
        t_g: widen(priors.t_g),
        t_a: widen(priors.t_a),
        ..*priors
    };
    (s, p)
}

#[cfg(test)]
mod tests;
