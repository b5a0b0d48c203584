//! Tuning, priors and the estimate of the calibration filter (`VI_NOTES.md` §3 "Priors").

use nalgebra::{DMatrix, DVector};

use super::state::CalibState;
use super::{
    CORE_DIM, IDX_BA, IDX_BG, IDX_DIST, IDX_INTR, IDX_P, IDX_PCB, IDX_TA, IDX_TD, IDX_TG,
    IDX_THETA, IDX_TR, IDX_TS, IDX_V,
};
use crate::imu::ImuNoise;

/// Tuning of [`super::CalibFilter`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct CalibParams {
    /// IMU noise densities (continuous time).
    pub imu_noise: ImuNoise,
    /// Pixel noise σ per coordinate, px.
    pub pixel_sigma: f64,
    /// Most clones kept; past it the oldest is dropped after its tracks are used.
    pub max_clones: usize,
    /// Fewest observations a track needs to be used (null space leaves `2M - 3` rows).
    pub min_track_len: usize,
    /// Most features in one update (the longest tracks first); 0 = no limit.
    pub max_features_per_update: usize,
    /// Random walk of `t_d`, s/√s (`VI_NOTES.md` §1: drifting stamps); 0 = constant.
    pub t_d_random_walk: f64,
    /// Smallest parallax of a used feature: largest camera baseline over its depth, rad.
    pub min_parallax: f64,
    /// Largest Gauss-Newton reprojection RMS (px) for a triangulated feature to be used. The
    /// default, 10 px, is for tracks without mismatches (simulated, AprilGrid detections):
    /// at 4 px a filter started from a poor camera is locked out (every feature fails, and
    /// nothing corrects the camera: EuRoC AprilGrid from the start). Image tracks
    /// can hold mismatches and want 4 px (`tracker.calib.max_triangulation_rms_px`).
    pub max_triangulation_rms: f64,
    /// Use features below `min_parallax`, fitted with a prior on their depth
    /// ([`super::triangulate::triangulate`]): their rows constrain the rotations, the camera
    /// and the timing. Off: they are not used.
    pub low_parallax: bool,
    /// Use first-estimate Jacobians (FEJ) for p and v (propagation and measurement).
    pub fej: bool,
    /// Most relinearisations of one update (iterated EKF); 1 = plain EKF.
    pub max_iterations: usize,
    /// Relinearise only when the first correction moves some core entry by more than this
    /// many prior σ (large corrections are where linearisation errors bite: the start).
    pub iterate_above_sigma: f64,
}

impl Default for CalibParams {
    fn default() -> Self {
        Self {
            imu_noise: ImuNoise::default(),
            pixel_sigma: 1.0,
            max_clones: 12,
            min_track_len: 5,
            max_features_per_update: 60,
            t_d_random_walk: 0.0,
            max_triangulation_rms: 10.0,
            min_parallax: 0.02,
            low_parallax: false,
            fej: true,
            max_iterations: 4,
            iterate_above_sigma: 0.3,
        }
    }
}

/// Prior 1σ of every block of the core state (`VI_NOTES.md` §3 "Priors", the KSWF values).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct CalibPriors {
    /// Orientation, rad.
    pub theta: f64,
    /// Position, m.
    pub position: f64,
    /// Velocity, m/s.
    pub velocity: f64,
    /// Gyro bias, rad/s.
    pub gyro_bias: f64,
    /// Accelerometer bias, m/s².
    pub accel_bias: f64,
    /// Each element of `T_g`.
    pub t_g: f64,
    /// Each element of `T_s`, rad/s per m/s².
    pub t_s: f64,
    /// Each element of `T_a`.
    pub t_a: f64,
    /// Each coordinate of `p_cb`, m.
    pub p_cb: f64,
    /// `fx, fy`, px.
    pub focal: f64,
    /// `cx, cy`, px.
    pub principal_point: f64,
    /// `k1, k2`.
    pub radial: f64,
    /// `p1, p2`.
    pub tangential: f64,
    /// `t_d`, s.
    pub t_d: f64,
    /// `t_r`, s.
    pub t_r: f64,
}

impl Default for CalibPriors {
    fn default() -> Self {
        Self {
            theta: 0.01,
            position: 0.01,
            velocity: 0.05,
            gyro_bias: 0.02,
            accel_bias: 0.1,
            t_g: 5e-3,
            t_s: 1e-3,
            t_a: 5e-3,
            p_cb: 0.02,
            focal: 5.0,
            principal_point: 5.0,
            radial: 0.05,
            tangential: 0.01,
            t_d: 0.010,
            t_r: 0.005,
        }
    }
}

impl CalibPriors {
    /// The diagonal prior covariance of the core state.
    pub fn covariance(&self) -> DMatrix<f64> {
        let mut d = DVector::zeros(CORE_DIM);
        let blocks = [
            (IDX_THETA, 3, self.theta),
            (IDX_P, 3, self.position),
            (IDX_V, 3, self.velocity),
            (IDX_BG, 3, self.gyro_bias),
            (IDX_BA, 3, self.accel_bias),
            (IDX_TG, 9, self.t_g),
            (IDX_TS, 9, self.t_s),
            (IDX_TA, 9, self.t_a),
            (IDX_PCB, 3, self.p_cb),
            (IDX_INTR, 2, self.focal),
            (IDX_INTR + 2, 2, self.principal_point),
            (IDX_DIST, 2, self.radial),
            (IDX_DIST + 2, 2, self.tangential),
            (IDX_TD, 1, self.t_d),
            (IDX_TR, 1, self.t_r),
        ];
        for (at, n, s) in blocks {
            for k in 0..n {
                d[at + k] = s * s;
            }
        }
        DMatrix::from_diagonal(&d)
    }
}

/// A value with its 1σ.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct ParamEstimate {
    /// The estimate.
    pub value: f64,
    /// Its standard deviation (square root of the covariance's diagonal).
    pub sigma: f64,
}

/// Every calibration parameter with its 1σ (units as in [`CalibState`]).
#[derive(Debug, Clone, PartialEq)]
pub struct CalibEstimate {
    /// Gyro bias, rad/s.
    pub gyro_bias: [ParamEstimate; 3],
    /// Accelerometer bias, m/s².
    pub accel_bias: [ParamEstimate; 3],
    /// `T_g`, row-major.
    pub t_g: [ParamEstimate; 9],
    /// `T_s`, row-major.
    pub t_s: [ParamEstimate; 9],
    /// `T_a`, row-major.
    pub t_a: [ParamEstimate; 9],
    /// `p_cb`, m.
    pub p_cb: [ParamEstimate; 3],
    /// `fx, fy, cx, cy`, px.
    pub pinhole: [ParamEstimate; 4],
    /// `k1, k2, p1, p2`.
    pub distortion: [ParamEstimate; 4],
    /// `t_d`, s.
    pub t_d: ParamEstimate,
    /// `t_r`, s.
    pub t_r: ParamEstimate,
}

impl CalibEstimate {
    /// Reads the estimate from the nominal state and the core covariance.
    pub fn from_state(state: &CalibState, p: &DMatrix<f64>) -> Self {
        let v = state.calib_vector();
        let at = |i: usize| ParamEstimate {
            value: v[i],
            sigma: p[(i, i)].max(0.0).sqrt(),
        };
        Self {
            gyro_bias: std::array::from_fn(|k| at(IDX_BG + k)),
            accel_bias: std::array::from_fn(|k| at(IDX_BA + k)),
            t_g: std::array::from_fn(|k| at(IDX_TG + k)),
            t_s: std::array::from_fn(|k| at(IDX_TS + k)),
            t_a: std::array::from_fn(|k| at(IDX_TA + k)),
            p_cb: std::array::from_fn(|k| at(IDX_PCB + k)),
            pinhole: std::array::from_fn(|k| at(IDX_INTR + k)),
            distortion: std::array::from_fn(|k| at(IDX_DIST + k)),
            t_d: at(IDX_TD),
            t_r: at(IDX_TR),
        }
    }
}
