//! Online camera-IMU calibration with a rolling-shutter MSCKF (issue 18; seed chapter 4;
//! `VI_NOTES.md` §0-§3): pure functions and one filter type, no threads, IO or clocks.
//!
//! **State** (`VI_NOTES.md` §3, "State"): the nominal [`CalibState`] and an error state of
//! [`CORE_DIM`] = 55 entries plus [`CLONE_DIM`] = 9 per cloned body state, in the order
//! ```text
//! dθ dp dv b_g b_a | T_g T_s T_a (row-major, §2) | p_cb | fx fy cx cy | k1 k2 p1 p2 | t_d t_r | clones (dθ dp dv)
//! ```
//! with `R_gb = Exp(dθ) R̂_gb` (§0, a global-frame rotation error) and every other entry
//! additive (`T = T̂ + δT`). `R_cb` is held fixed. Times are `i64` ns on the IMU clock; `t_d`
//! and `t_r` are kept in seconds in the state.
//!
//! **Files.** [`state`] the nominal state and its retraction; [`params`] the tuning, the
//! priors and the estimate with 1σ; [`propagate`] the IMU model with the T-model and the
//! discrete transition (§3 "Propagation"); [`measure`] the prediction of one observation at
//! its own row time and its Jacobians (§3 "Measurement in row v of image j"); [`triangulate`]
//! the anchored inverse-depth Gauss-Newton; [`update`] the null-space projection, χ² gate,
//! QR compression and EKF update (§3 "Update"); `rows` one feature's projected rows;
//! [`filter`] the [`CalibFilter`] that wires them; [`init`] the start from any device state
//! (`t_d`, `R_cb`, gravity, velocity, biases from the first seconds); [`online`] the
//! filter fed frame by frame (the tracker's `calib` mode); [`sim`] the synthetic scenarios
//! (`calib`, `phone`) and the Monte-Carlo trial of `shoal bench calibrate`.
//!
//! **Status** (synthetic tests in `tests.rs`, seed Fig. 4.4-like scenario, one run per
//! seed): after 60 s every issue target is met on the three seeds tried, ≥ 99.4 % of
//! (entry, epoch) pairs lie within ±3σ, mean NEES of the 40 calibration entries 41-52.
//! Monte-Carlo (`shoal bench calibrate`, [`sim::run_trial`], BENCHMARKS.md): 15 runs of
//! 120 s with truth drawn around nominal meet every target at 60 s, 99.5 % within ±3σ, the
//! averaged NEES in its 95 % band at 85 % of epochs (out in the first ~10 s: `t_r`); on the
//! walking `phone` motion the filter is inconsistent (intrinsics and distortion
//! overconfident from the first updates).
//! Known limits: `t_r` is overconfident in the first ~10 s (biased positive by ~0.5-1 ms
//! at 5 s, 3-5σ, also with a true `t_r = 0`; caused by noise on the *row* coordinate only,
//! cause not found yet: reproduce with the `diagnostic_run` test and `CALIB_NOISE_AXIS=v`);
//! clones are capped by dropping the oldest only. Starting errors far beyond the prior
//! (`t_d` 100 ms, `R_cb` unknown, a moving start) are handled by [`init`] first
//! ([`init::initialize`], then [`init::filter_start`]).
//!
//! ```no_run
//! use slam_core::calib::{CalibFilter, CalibParams, CalibPriors, CalibState, ImuSample};
//! # fn run(state: CalibState, imu: Vec<ImuSample>) -> Result<(), slam_core::calib::CalibError> {
//! let mut filter = CalibFilter::new(CalibParams::default(), CalibPriors::default(), state);
//! for s in imu {
//!     filter.push_imu(s);
//! }
//! filter.add_frame(33_333_333, &[])?; // middle-row time, (track, pixel) observations
//! let est = filter.estimate();
//! println!("t_d = {} ± {} s", est.t_d.value, est.t_d.sigma);
//! # Ok(()) }
//! ```

use nalgebra::Vector2;

pub mod filter;
pub mod init;
pub mod integrate;
pub mod measure;
pub mod online;
pub mod params;
pub mod propagate;
mod rows;
pub mod state;
pub mod triangulate;
pub mod update;

pub mod sim;
#[cfg(test)]
mod tests;

pub use filter::{CalibError, CalibFilter, FrameReport};
pub use params::{CalibEstimate, CalibParams, CalibPriors, ParamEstimate};
pub use state::{CalibState, CloneState, NavState};

/// Error-state index of `dθ` (rotation of `R_gb`, global frame).
pub const IDX_THETA: usize = 0;
/// Error-state index of `dp` (position `p_gb`).
pub const IDX_P: usize = 3;
/// Error-state index of `dv` (velocity `v_gb`).
pub const IDX_V: usize = 6;
/// Error-state index of the gyro bias `b_g`.
pub const IDX_BG: usize = 9;
/// Error-state index of the accelerometer bias `b_a`.
pub const IDX_BA: usize = 12;
/// Error-state index of `T_g` (9 entries, row-major).
pub const IDX_TG: usize = 15;
/// Error-state index of `T_s` (9 entries, row-major).
pub const IDX_TS: usize = 24;
/// Error-state index of `T_a` (9 entries, row-major).
pub const IDX_TA: usize = 33;
/// Error-state index of the lever arm `p_cb` (body origin in the camera frame).
pub const IDX_PCB: usize = 42;
/// Error-state index of `fx, fy, cx, cy`.
pub const IDX_INTR: usize = 45;
/// Error-state index of `k1, k2, p1, p2`.
pub const IDX_DIST: usize = 49;
/// Error-state index of the time offset `t_d` (s).
pub const IDX_TD: usize = 53;
/// Error-state index of the readout time `t_r` (s).
pub const IDX_TR: usize = 54;
/// Dimension of the error state without clones.
pub const CORE_DIM: usize = 55;
/// Error-state entries per clone: `dθ, dp, dv`.
pub const CLONE_DIM: usize = 9;
/// The camera block `p_cb .. t_r` (13 contiguous entries) the measurement touches.
pub const CAM_BLOCK: usize = 13;

pub use crate::ids::TrackId;

/// One feature observation in a frame: `uv = (column, row)` in pixels, pixel centres at
/// integer coordinates ([`crate::camera::PinholeRadtan`]).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Observation {
    /// The track it belongs to.
    pub track: TrackId,
    /// Pixel `(u, v)`: column and row.
    pub uv: Vector2<f64>,
}

/// One raw IMU sample on the IMU clock (`a_m`, `ω_m` of seed eq. 2.55-2.56): the
/// preintegration's type.
pub use crate::imu::ImuMeasurement as ImuSample;

/// The lever arm `p_cb` (the body origin in the camera frame, m; the seed's Table 4.1) of a
/// camera-to-body transform `T_BS` (EuRoC's `sensor.yaml`, Kalibr's `T_cam_imu`⁻¹):
/// `p_cb = −R_cb p_bc` with `R_cb = R_bcᵀ`.
pub fn lever_arm_of_t_bs(t_bs: &nalgebra::Isometry3<f64>) -> nalgebra::Vector3<f64> {
    -(t_bs.rotation.inverse() * t_bs.translation.vector)
}
