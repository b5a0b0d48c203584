//! The calibration mode (`tracker.mode = "calib"`, issue 18): the frames go to
//! [`slam_core::calib::online::OnlineCalibrator`] (images through its ORB feature tracks, or
//! the feature records of a [`shm_schema::PixelFormat::Features`] frame), the IMU samples
//! too. Every frame whose update ran is posed (metric, gravity-aligned; a frame that waited
//! for its IMU is posed later, as a backfilled pose). No keyframe goes to the server. The
//! estimate with its 1σ is the status's details ([`CalibReport`], `report.json`'s
//! `clients[i].calib`) and, per frame, a CSV row of the log (`tracker.calib.log`).
use nalgebra::Vector2;
use serde::{Deserialize, Serialize};
use shm_schema::{FeatureRecord, FrameHeader, PixelFormat, PoseSource, TrackState};
use shoal_runtime::ErrorKind;
use slam_core::calib::online::{FrameResult, OnlineCalibrator, OnlineParams, OnlineStart};
use slam_core::calib::{CalibEstimate, CalibParams, CalibPriors, Observation, ParamEstimate};
use slam_core::features::GrayImage;
use slam_core::ids::TrackId;

use super::frame::{FrameIn, Tracked};
use super::{Out, TrackerCore};

/// A value with its 1σ, and the prior 1σ it started with.
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize, Deserialize)]
pub struct Estimate {
    /// The estimate.
    pub value: f64,
    /// Its 1σ now.
    pub sigma: f64,
    /// Its 1σ at the start.
    pub prior_sigma: f64,
}

/// The calibration as estimated (units in the names; `t_d_ns` is the whole camera-IMU
/// offset: the one the frames' stamps carried plus the filter's correction).
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct CalibValues {
    /// `fx, fy, cx, cy`, px.
    pub intrinsics: [Estimate; 4],
    /// `k1, k2, p1, p2`.
    pub distortion: [Estimate; 4],
    /// Camera-IMU time offset: IMU time of a frame's middle row = camera stamp + `t_d`, ns.
    pub t_d_ns: Estimate,
    /// The part of `t_d_ns` the frames' stamps already carried, ns.
    pub t_d_applied_ns: f64,
    /// Rolling-shutter readout time of a frame, ns.
    pub t_r_ns: Estimate,
    /// Lever arm: the body (IMU) origin in the camera frame, m.
    pub p_cb_m: [Estimate; 3],
    /// Camera pose in the body frame `T_BS` (row-major 4x4) with the estimated lever arm
    /// and the rotation held fixed.
    pub t_bs: [[f64; 4]; 4],
    /// Gyro scale and misalignment `T_g`, row-major.
    pub t_g: [Estimate; 9],
    /// Gyro g-sensitivity `T_s`, rad/s per m/s², row-major.
    pub t_s: [Estimate; 9],
    /// Accelerometer scale and misalignment `T_a`, row-major.
    pub t_a: [Estimate; 9],
    /// Gyro bias, rad/s.
    pub gyro_bias: [Estimate; 3],
    /// Accelerometer bias, m/s².
    pub accel_bias: [Estimate; 3],
}

/// What the calibration filter's initialisation found (`slam_core::calib::init`).
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct InitReport {
    /// Why it failed (the filter then started from the mean specific force).
    pub error: Option<String>,
    /// Its t_d correction of the stamps, ms, and the correlation peak it came from.
    pub t_d_ms: Option<f64>,
    /// See `t_d_ms`.
    pub t_d_peak: Option<f64>,
    /// `R_cb` was estimated (not given), its 1σ and residual, degrees.
    pub r_cb_estimated: bool,
    /// See `r_cb_estimated`.
    pub r_cb_sigma_deg: Option<f64>,
    /// See `r_cb_estimated`.
    pub r_cb_residual_deg: Option<f64>,
    /// Visual rotations found and used.
    pub rotations: [usize; 2],
    /// `R_cb` was not observable (the camera turned about fewer than two axes) and was
    /// snapped to the nearest axis permutation (`slam_core::calib::init::AxisSnap`): the
    /// fit's own 1σ and its angle to the permutation, degrees.
    pub r_cb_snapped_deg: Option<[f64; 2]>,
    /// `R_cb` (camera from body), rows.
    pub r_cb: Option<[[f64; 3]; 3]>,
    /// Tries of the initialisation (it waits for more rotation after a failed one).
    pub tries: u32,
}

/// The calibration mode's report (the status's details; `report.json` `clients[i].calib`).
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct CalibReport {
    /// The filter started (it needs [`OnlineParams::start_window_ns`] of IMU first).
    pub started: bool,
    /// How: `static` (at rest over the start window) or `moving`.
    pub start: Option<String>,
    /// Image size `[width, height]` (rows for Kalibr's `line_delay`).
    pub image: [u32; 2],
    /// Frames whose update ran.
    pub frames_updated: u64,
    /// Frames the filter refused (e.g. their IMU never came), the last reason below.
    pub frames_refused: u64,
    /// Frames before the start.
    pub frames_before_start: u64,
    /// Frames dropped from a full queue (their IMU did not come in time).
    pub frames_dropped: u64,
    /// Mean features per updated frame, and mean features used per update.
    pub features_per_frame: f64,
    /// See `features_per_frame`.
    pub features_used_per_frame: f64,
    /// Features the χ² gate refused, and features that could not be triangulated (too little
    /// parallax, reprojection RMS over the gross-outlier bound, behind a camera), in total.
    #[serde(default)]
    pub features_gated: u64,
    /// See `features_gated`.
    #[serde(default)]
    pub features_failed: u64,
    /// Of the used features, those with too little parallax, fitted with the depth prior
    /// (`tracker.calib.low_parallax`), in total.
    #[serde(default)]
    pub features_low_parallax: u64,
    /// Updates whose iterated step could not lower the cost from the prior, so nothing was
    /// applied (the linearisation was not trusted; `FrameReport::refused`).
    #[serde(default)]
    pub updates_refused: u64,
    /// The filter's update time per frame, ms (p50, p99, max).
    pub update_ms: [f64; 3],
    /// Why the last refused frame was refused.
    pub last_refusal: Option<String>,
    /// The initialisation (`tracker.calib.init`): what it found, or why it failed.
    pub init: Option<InitReport>,
    /// The estimate now, with 1σ.
    pub estimate: Option<CalibValues>,
    /// Parameters whose σ did not shrink below half their prior σ: not determined by this
    /// run's motion, so not to be taken as estimates.
    pub not_converged: Vec<String>,
    /// Entries that moved more than [`IMPLAUSIBLE_PRIOR_SIGMAS`] prior σ from where the
    /// filter started (`T_a.yy`, `fx`, ...): a small σ does not make them right; the start,
    /// the prior or the estimate is wrong (GoPro: T_a.yy 1.25 ± 0.03 from 1 ± 0.05).
    #[serde(default)]
    pub implausible: Vec<String>,
}

/// The calibration client of a tracker in `calib` mode.
pub struct CalibClient {
    cal: OnlineCalibrator,
    priors: CalibPriors,
    applied_t_d_ns: i64,
    image: [u32; 2],
    updated: u64,
    refused: u64,
    features: u64,
    used: u64,
    updates_refused: u64,
    gated: u64,
    failed: u64,
    low_parallax: u64,
    update_ms: Vec<f32>,
    last_refusal: Option<String>,
    log_header_sent: bool,
}

/// Prior 1σ of each lever-arm coordinate when no extrinsics are given, m.
const NEW_DEVICE_P_CB_SIGMA_M: f64 = 0.1;

/// Update times kept for the percentiles.
const MAX_TIMES: usize = 200_000;

/// An estimate this many prior σ from its start is implausible.
pub const IMPLAUSIBLE_PRIOR_SIGMAS: f64 = 4.0;

/// The names of the entries more than [`IMPLAUSIBLE_PRIOR_SIGMAS`] start σ from their start.
fn moved_far<S: AsRef<str>>(
    names: &[S],
    xs: &[ParamEstimate],
    starts: &[ParamEstimate],
) -> Vec<String> {
    names
        .iter()
        .zip(xs.iter().zip(starts))
        .filter(|(_, (x, x0))| (x.value - x0.value).abs() > IMPLAUSIBLE_PRIOR_SIGMAS * x0.sigma)
        .map(|(n, _)| n.as_ref().to_string())
        .collect()
}

/// σ above this fraction of the prior σ: not converged.
const CONVERGED_FRACTION: f64 = 0.5;

impl CalibClient {
    /// A client for frames like `h`, with the IMU noise `noise` and the mode's settings.
    pub fn new(
        h: &FrameHeader,
        cfg: &crate::CalibModeConfig,
        noise: slam_core::imu::ImuNoise,
        imu: slam_core::imu::ImuIntrinsics,
        features: usize,
        extrinsics_given: bool,
        readout: slam_core::rolling_shutter::ReadoutDirection,
    ) -> Result<Self, String> {
        cfg.validate()?;
        let t_bs = shoal_runtime::wire::iso_from_wire(&h.t_bs)
            .ok_or("the frames' T_BS is not a rigid transform")?;
        let mut camera =
            shoal_runtime::wire::camera_from_intrinsics(&h.intrinsics, h.width, h.height);
        camera.readout = readout;
        let start = OnlineStart {
            camera,
            t_bs,
            t_r_s: h.readout_ns as f64 * 1e-9,
            imu,
            biases: Default::default(),
            r_cb_given: extrinsics_given,
        };
        let init = match cfg.init {
            crate::CalibInit::Always => true,
            crate::CalibInit::Auto => !extrinsics_given,
            crate::CalibInit::Never => false,
        };
        let mut priors = cfg.priors();
        if !extrinsics_given {
            // A new device: the lever arm is not known to centimetres either.
            priors.p_cb = priors.p_cb.max(NEW_DEVICE_P_CB_SIGMA_M);
        }
        let params = OnlineParams {
            filter: CalibParams {
                imu_noise: noise,
                pixel_sigma: cfg.pixel_sigma,
                min_parallax: cfg.min_parallax_rad,
                low_parallax: cfg.low_parallax,
                max_triangulation_rms: if h.pixel_format == PixelFormat::Features as u32 {
                    cfg.max_triangulation_rms_given_px
                } else {
                    cfg.max_triangulation_rms_px
                },
                ..CalibParams::default()
            },
            priors,
            orb_features: features,
            init_seconds: init.then_some(cfg.init_seconds),
            start_window_ns: (cfg.start_seconds * 1e9) as i64,
            ..OnlineParams::default()
        };
        Ok(Self {
            cal: OnlineCalibrator::new(params, start),
            priors,
            applied_t_d_ns: h.time_offset_ns,
            image: [h.width, h.height],
            updated: 0,
            refused: 0,
            features: 0,
            used: 0,
            updates_refused: 0,
            gated: 0,
            failed: 0,
            low_parallax: 0,
            update_ms: Vec::new(),
            last_refusal: None,
            log_header_sent: false,
        })
    }

    /// The calibrator.
    pub fn calibrator(&self) -> &OnlineCalibrator {
        &self.cal
    }

    /// One IMU sample.
    pub fn push_imu(&mut self, s: slam_core::imu::ImuMeasurement) {
        self.cal.push_imu(s);
    }

    /// The frame's features (images tracked now), then the updates that ran.
    fn add_frame(&mut self, f: &FrameIn) -> Result<Vec<FrameResult>, String> {
        let h = &f.header;
        let tag = h.meta.seq;
        if h.pixel_format == PixelFormat::Features as u32 {
            let obs = feature_observations(f.pixels).ok_or_else(|| {
                format!("frame {tag}: {} bytes of feature records", f.pixels.len())
            })?;
            return Ok(self.cal.add_observations(tag, h.t_mid_ns, obs));
        }
        let (w, ht, stride) = (h.width as usize, h.height as usize, h.stride as usize);
        let image = GrayImage::new(f.pixels, w, ht, stride).map_err(|e| e.to_string())?;
        self.cal
            .add_image(tag, h.t_mid_ns, &image)
            .map_err(|e| format!("frame {tag}: {e}"))
    }

    /// Counts an update's figures; its error, if refused.
    fn count(&mut self, r: &FrameResult) -> Option<String> {
        if let Some(e) = &r.error {
            self.refused += 1;
            self.last_refusal = Some(e.to_string());
            return Some(format!("frame {} at {} ns: {e}", r.tag, r.t_mid_ns));
        }
        if let Some(rep) = r.report {
            self.updated += 1;
            self.features += r.features as u64;
            self.used += rep.used as u64;
            self.updates_refused += u64::from(rep.refused);
            self.gated += rep.gated as u64;
            self.failed += rep.failed as u64;
            self.low_parallax += rep.low_parallax as u64;
            if self.update_ms.len() < MAX_TIMES {
                self.update_ms.push(r.update_ms);
            }
        }
        None
    }

    /// The report as of now.
    pub fn report(&self) -> CalibReport {
        let est = self.cal.filter().map(|f| f.estimate());
        let n = self.updated.max(1) as f64;
        CalibReport {
            started: est.is_some(),
            start: self.cal.start_kind().map(|k| k.name().to_string()),
            image: self.image,
            frames_updated: self.updated,
            frames_refused: self.refused,
            frames_before_start: self.cal.before_start,
            frames_dropped: self.cal.dropped,
            features_per_frame: self.features as f64 / n,
            features_used_per_frame: self.used as f64 / n,
            updates_refused: self.updates_refused,
            features_gated: self.gated,
            features_failed: self.failed,
            features_low_parallax: self.low_parallax,
            update_ms: percentiles(&self.update_ms),
            last_refusal: self.last_refusal.clone(),
            init: self.cal.init_result.as_ref().map(|r| InitReport {
                tries: self.cal.init_tries,
                ..init_report(r)
            }),
            implausible: self.implausible(),
            not_converged: est
                .as_ref()
                .map_or_else(Vec::new, |e| self.not_converged(e)),
            estimate: est.map(|e| self.values(&e)),
        }
    }

    /// The prior σ the filter started with (the configured ones before it started).
    fn start_priors(&self) -> CalibPriors {
        self.cal.filter().map_or(self.priors, |f| *f.priors())
    }

    /// The estimate as report values.
    fn values(&self, e: &CalibEstimate) -> CalibValues {
        let p = &self.start_priors();
        let v = |x: &ParamEstimate, prior: f64| Estimate {
            value: x.value,
            sigma: x.sigma,
            prior_sigma: prior,
        };
        let ns = |x: &ParamEstimate, prior: f64, add: f64| Estimate {
            value: x.value * 1e9 + add,
            sigma: x.sigma * 1e9,
            prior_sigma: prior * 1e9,
        };
        let pp = [p.focal, p.focal, p.principal_point, p.principal_point];
        let dd = [p.radial, p.radial, p.tangential, p.tangential];
        let s = self.cal.filter().map(|f| *f.state());
        let t_bs = s.map_or([[0.0; 4]; 4], |s| {
            let r_bs = s.r_cb.inverse();
            let t = -(r_bs * s.p_cb);
            let mut m = [[0.0; 4]; 4];
            for (r, row) in m.iter_mut().enumerate().take(3) {
                for (c, x) in row.iter_mut().enumerate().take(3) {
                    *x = r_bs[(r, c)];
                }
                row[3] = t[r];
            }
            m[3][3] = 1.0;
            m
        });
        CalibValues {
            intrinsics: std::array::from_fn(|k| v(&e.pinhole[k], pp[k])),
            distortion: std::array::from_fn(|k| v(&e.distortion[k], dd[k])),
            t_d_ns: ns(&e.t_d, p.t_d, self.applied_t_d_ns as f64),
            t_d_applied_ns: self.applied_t_d_ns as f64,
            t_r_ns: ns(&e.t_r, p.t_r, 0.0),
            p_cb_m: std::array::from_fn(|k| v(&e.p_cb[k], p.p_cb)),
            t_bs,
            t_g: std::array::from_fn(|k| v(&e.t_g[k], p.t_g)),
            t_s: std::array::from_fn(|k| v(&e.t_s[k], p.t_s)),
            t_a: std::array::from_fn(|k| v(&e.t_a[k], p.t_a)),
            gyro_bias: std::array::from_fn(|k| v(&e.gyro_bias[k], p.gyro_bias)),
            accel_bias: std::array::from_fn(|k| v(&e.accel_bias[k], p.accel_bias)),
        }
    }

    /// The parameters (groups for the matrices) whose σ stayed above
    /// [`CONVERGED_FRACTION`] of the prior's.
    fn implausible(&self) -> Vec<String> {
        let Some(f) = self.cal.filter() else {
            return Vec::new();
        };
        let (e, (_, s0)) = (f.estimate(), f.start());
        const M: [&str; 9] = ["xx", "xy", "xz", "yx", "yy", "yz", "zx", "zy", "zz"];
        let mat = |g: &str| M.map(|m| format!("{g}.{m}"));
        [
            moved_far(&["fx", "fy", "cx", "cy"], &e.pinhole, &s0.pinhole),
            moved_far(&["k1", "k2", "p1", "p2"], &e.distortion, &s0.distortion),
            moved_far(&["t_d", "t_r"], &[e.t_d, e.t_r], &[s0.t_d, s0.t_r]),
            moved_far(&["p_cb.x", "p_cb.y", "p_cb.z"], &e.p_cb, &s0.p_cb),
            moved_far(&mat("T_g"), &e.t_g, &s0.t_g),
            moved_far(&mat("T_s"), &e.t_s, &s0.t_s),
            moved_far(&mat("T_a"), &e.t_a, &s0.t_a),
        ]
        .concat()
    }

    fn not_converged(&self, e: &CalibEstimate) -> Vec<String> {
        let p = &self.start_priors();
        let ratio = |xs: &[ParamEstimate], prior: f64| {
            xs.iter().map(|x| x.sigma / prior).sum::<f64>() / xs.len() as f64
        };
        let groups: [(&str, f64); 15] = [
            ("fx", ratio(&e.pinhole[0..1], p.focal)),
            ("fy", ratio(&e.pinhole[1..2], p.focal)),
            ("cx", ratio(&e.pinhole[2..3], p.principal_point)),
            ("cy", ratio(&e.pinhole[3..4], p.principal_point)),
            ("k1", ratio(&e.distortion[0..1], p.radial)),
            ("k2", ratio(&e.distortion[1..2], p.radial)),
            ("p1", ratio(&e.distortion[2..3], p.tangential)),
            ("p2", ratio(&e.distortion[3..4], p.tangential)),
            ("t_d", ratio(&[e.t_d], p.t_d)),
            ("t_r", ratio(&[e.t_r], p.t_r)),
            ("p_cb.x", ratio(&e.p_cb[0..1], p.p_cb)),
            ("p_cb.y", ratio(&e.p_cb[1..2], p.p_cb)),
            ("p_cb.z", ratio(&e.p_cb[2..3], p.p_cb)),
            ("T_g", ratio(&e.t_g, p.t_g)),
            ("T_a", ratio(&e.t_a, p.t_a)),
        ];
        let mut out: Vec<String> = groups
            .iter()
            .filter(|(_, r)| *r > CONVERGED_FRACTION)
            .map(|(n, _)| n.to_string())
            .collect();
        if ratio(&e.t_s, p.t_s) > CONVERGED_FRACTION {
            out.push("T_s".into());
        }
        let init_failed = matches!(self.cal.init_result, Some(Err(_)));
        if init_failed && !self.cal.start().r_cb_given {
            // A new device whose initialisation failed: `R_cb` is the starting guess, held
            // fixed, and nothing estimated with it is to be taken.
            out.push("R_cb".into());
        }
        out
    }

    /// The CSV header of the log.
    pub fn log_header() -> String {
        let mut cols = vec!["t_s".to_string()];
        for n in LOG_NAMES {
            cols.push(n.to_string());
            cols.push(format!("{n}_sigma"));
        }
        cols.join(",")
    }

    /// The log's row of the estimate after an update at `t_mid_ns`.
    fn log_row(&self, t_mid_ns: i64) -> Option<String> {
        let v = self.values(&self.cal.filter()?.estimate());
        let mut cells = vec![format!("{:.6}", t_mid_ns as f64 * 1e-9)];
        for x in log_values(&v) {
            cells.push(format!("{:.9e}", x.value));
            cells.push(format!("{:.3e}", x.sigma));
        }
        Some(cells.join(","))
    }
}

/// The report of an initialisation's result.
fn init_report(
    r: &Result<slam_core::calib::init::InitResult, slam_core::calib::init::InitError>,
) -> InitReport {
    match r {
        Err(e) => InitReport {
            error: Some(e.to_string()),
            ..InitReport::default()
        },
        Ok(i) => InitReport {
            error: None,
            t_d_ms: Some(i.t_d_s * 1e3),
            t_d_peak: Some(i.t_d_quality.peak),
            r_cb_estimated: !i.r_cb_given,
            r_cb_sigma_deg: Some(i.r_cb_sigma_rad.to_degrees()),
            r_cb_residual_deg: Some(i.r_cb_residual_rad.to_degrees()),
            rotations: [i.rotations_found, i.rotations_used],
            r_cb_snapped_deg: i.r_cb_snap.map(|(s, a)| [s.to_degrees(), a.to_degrees()]),
            r_cb: Some(std::array::from_fn(|r| {
                std::array::from_fn(|c| i.r_cb[(r, c)])
            })),
            tries: 0,
        },
    }
}

/// The log's columns, in the order of [`log_values`].
pub const LOG_NAMES: [&str; 19] = [
    "fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "t_d_ms", "t_r_ms", "p_cb_x", "p_cb_y",
    "p_cb_z", "T_g_xx", "T_g_yy", "T_g_zz", "T_a_xx", "T_a_yy", "T_a_zz",
];

/// The logged values of `v` ([`LOG_NAMES`]); times in ms.
fn log_values(v: &CalibValues) -> Vec<Estimate> {
    let ms = |e: Estimate| Estimate {
        value: e.value * 1e-6,
        sigma: e.sigma * 1e-6,
        prior_sigma: e.prior_sigma * 1e-6,
    };
    let mut out = Vec::with_capacity(LOG_NAMES.len());
    out.extend(v.intrinsics);
    out.extend(v.distortion);
    out.push(ms(v.t_d_ns));
    out.push(ms(v.t_r_ns));
    out.extend(v.p_cb_m);
    out.extend([v.t_g[0], v.t_g[4], v.t_g[8], v.t_a[0], v.t_a[4], v.t_a[8]]);
    out
}

/// The observations of a feature payload (`None`: not a whole number of records); records
/// with non-finite pixels are left out.
pub fn feature_observations(payload: &[u8]) -> Option<Vec<Observation>> {
    Some(
        FeatureRecord::all(payload)?
            .filter(|r| r.u.is_finite() && r.v.is_finite())
            .map(|r| Observation {
                track: TrackId(r.track),
                uv: Vector2::new(f64::from(r.u), f64::from(r.v)),
            })
            .collect(),
    )
}

/// p50, p99 and max of `ms`.
fn percentiles(ms: &[f32]) -> [f64; 3] {
    if ms.is_empty() {
        return [0.0; 3];
    }
    let mut v = ms.to_vec();
    v.sort_by(f32::total_cmp);
    let at = |q: f64| f64::from(v[((v.len() - 1) as f64 * q).round() as usize]);
    [at(0.5), at(0.99), at(1.0)]
}

impl TrackerCore {
    /// The calibration mode's client for frames like `h` (created with the first frame; the
    /// IMU samples held until then given to it).
    fn calib_client(&mut self, h: &FrameHeader) -> Option<&mut CalibClient> {
        if self.calib.is_none() && self.calib_disabled.is_none() {
            let imu = self.cfg.imu.noise_and_intrinsics();
            let made = imu.and_then(|(noise, intr)| {
                let given = self.cfg.imu.extrinsics_given;
                CalibClient::new(
                    h,
                    &self.cfg.calib,
                    noise,
                    intr,
                    self.cfg.features,
                    given,
                    self.cfg.readout,
                )
            });
            match made {
                Ok(mut c) => {
                    for s in std::mem::take(&mut self.pending_imu) {
                        c.push_imu(s);
                    }
                    self.calib = Some(Box::new(c));
                }
                Err(e) => {
                    let detail = format!("client {}: calibration mode: {e}", self.cfg.client);
                    self.status.error(ErrorKind::ImuCalibration, detail);
                    self.calib_disabled = Some(e);
                }
            }
        }
        self.calib.as_deref_mut()
    }

    /// Runs the calibration filter on the frame: its own pose when its update ran now, the
    /// poses of earlier frames that waited for their IMU as backfilled ones.
    pub(super) fn run_calib(&mut self, f: &FrameIn, t: &mut Tracked) {
        let h = f.header;
        self.first_frame_ns.get_or_insert(h.t_mid_ns);
        let Some(c) = self.calib_client(&h) else {
            return;
        };
        let results = match c.add_frame(f) {
            Ok(r) => r,
            Err(e) => {
                self.status.error(ErrorKind::BadFrame, e);
                return;
            }
        };
        let mut out = vec![];
        for r in &results {
            self.calib_result(r, &mut out);
            if r.tag == h.meta.seq {
                t.set_calib_pose(r.t_cw, r.features as u32);
            } else if let Some(t_cw) = r.t_cw {
                t.add_backfill(r.t_mid_ns, t_cw);
            }
        }
        t.out.extend(out);
    }

    /// Counts one update, its log row and its refusal.
    fn calib_result(&mut self, r: &FrameResult, out: &mut Vec<Out>) {
        let Some(c) = self.calib.as_deref_mut() else {
            return;
        };
        if let Some(e) = c.count(r) {
            self.status.error(ErrorKind::Calib, e);
        }
        if r.report.is_none() || !self.cfg.calib_log {
            return;
        }
        if !c.log_header_sent {
            c.log_header_sent = true;
            out.push(Out::CalibLog(CalibClient::log_header()));
        }
        if let Some(row) = c.log_row(r.t_mid_ns) {
            out.push(Out::CalibLog(row));
        }
    }

    /// At the end of the stream: the frames still waiting for their IMU, updated with what
    /// came, as backfilled poses (`FLAG_BACKFILL`) of the end-of-stream header `h`.
    pub(super) fn flush_calib(&mut self, h: &FrameHeader, now_ns: i64) -> Vec<Out> {
        let Some(c) = self.calib.as_deref_mut() else {
            return vec![];
        };
        let results = c.cal.flush();
        let mut out = vec![];
        for r in &results {
            self.calib_result(r, &mut out);
            if let Some(t_cw) = r.t_cw {
                out.push(Out::Pose(self.backfill_pose(h, r.t_mid_ns, &t_cw, now_ns)));
            }
        }
        out
    }

    /// The calibration report (`None` outside the calibration mode).
    pub fn calib_report(&self) -> Option<CalibReport> {
        if self.cfg.mode != crate::ClientMode::Calib {
            return None;
        }
        Some(match (&self.calib, &self.calib_disabled) {
            (Some(c), _) => c.report(),
            (None, Some(why)) => CalibReport {
                last_refusal: Some(why.clone()),
                ..CalibReport::default()
            },
            (None, None) => CalibReport::default(),
        })
    }
}

impl Tracked {
    /// The calibration filter's pose of the frame (`None`: not updated).
    fn set_calib_pose(&mut self, t_cw: Option<nalgebra::Isometry3<f64>>, features: u32) {
        self.t_cw = t_cw;
        self.tracked = features;
        if t_cw.is_some() {
            self.state = TrackState::Tracking;
            self.source = PoseSource::VisualInertial;
            self.metric = true;
        }
    }
}
