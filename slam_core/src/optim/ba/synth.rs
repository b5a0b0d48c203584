//! Synthetic bundle-adjustment scenes (for tests, benchmarks and the mapper's own tests):
//! keyframes on a smooth sideways trajectory looking at a volume of points, each point
//! tracked over a few consecutive keyframes, pixel noise scaled by the octave's σ, a share of
//! gross outliers, then poses and points perturbed.

use nalgebra::{Isometry3, Translation3, UnitQuaternion, Vector2, Vector3};

use super::problem::BaProblem;
use crate::camera::PinholeRadtan;
use crate::features::ORB_SCALE_FACTOR;
use crate::optim::inv_sigma2_for_octave;
use crate::CoreError;

/// Parameters of [`synthetic_scene`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SyntheticBaConfig {
    /// Number of keyframes (10).
    pub n_keyframes: usize,
    /// Number of points (1000).
    pub n_points: usize,
    /// Each point is tracked over this many consecutive keyframes at most (5 gives ~5
    /// observations per point).
    pub track_length: usize,
    /// Pixel noise standard deviation at octave 0, pixels (1.0).
    pub noise_px: f64,
    /// Share of observations replaced by a random pixel (0.05).
    pub outlier_ratio: f64,
    /// Keyframes `0..n_fixed` are flagged fixed (2: gauge and scale).
    pub n_fixed: usize,
    /// Standard deviation of the position perturbation of free keyframes, metres (0.05).
    pub pose_sigma_t: f64,
    /// Standard deviation of the rotation perturbation of free keyframes, radians (0.01).
    pub pose_sigma_r: f64,
    /// Standard deviation of the point perturbation, metres per axis (0.05).
    pub point_sigma: f64,
    /// Camera of every keyframe (EuRoC cam0, with distortion).
    pub camera: PinholeRadtan,
    /// Random seed.
    pub seed: u64,
}

impl Default for SyntheticBaConfig {
    fn default() -> Self {
        Self {
            n_keyframes: 10,
            n_points: 1000,
            track_length: 5,
            noise_px: 1.0,
            outlier_ratio: 0.05,
            n_fixed: 2,
            pose_sigma_t: 0.05,
            pose_sigma_r: 0.01,
            point_sigma: 0.05,
            camera: PinholeRadtan::euroc_cam0(),
            seed: 1,
        }
    }
}

/// A synthetic scene: the perturbed problem to solve and the ground truth.
#[derive(Debug, Clone, PartialEq)]
pub struct SyntheticBa {
    /// Perturbed poses and points, noisy observations (the solver's input).
    pub problem: BaProblem,
    /// True poses and points (same observations).
    pub truth: BaProblem,
    /// Which observations are gross outliers (indexed like the observations).
    pub outlier: Vec<bool>,
}

/// SplitMix64 with Box-Muller normals: a small deterministic generator.
struct Rng(u64);

impl Rng {
    fn next_u64(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^ (z >> 31)
    }
    fn uniform(&mut self, lo: f64, hi: f64) -> f64 {
        lo + (hi - lo) * ((self.next_u64() >> 11) as f64 / (1u64 << 53) as f64)
    }
    fn normal(&mut self) -> f64 {
        let u1 = self.uniform(0.0, 1.0).max(1e-300);
        let u2 = self.uniform(0.0, 1.0);
        (-2.0 * u1.ln()).sqrt() * (2.0 * std::f64::consts::PI * u2).cos()
    }
    fn normal3(&mut self, s: f64) -> Vector3<f64> {
        Vector3::new(self.normal(), self.normal(), self.normal()) * s
    }
}

/// The true camera-to-world pose of keyframe `k`: a sideways arc (x right, 0.15 m apart)
/// with a little forward motion and yaw, cameras looking along +z.
fn true_t_wc(k: usize) -> Isometry3<f64> {
    let s = k as f64;
    let pos = Vector3::new(0.15 * s, 0.02 * (0.7 * s).sin(), 0.03 * s);
    let rot = UnitQuaternion::from_scaled_axis(Vector3::new(
        0.01 * (0.5 * s).cos(),
        -0.02 * s,
        0.01 * s.sin(),
    ));
    Isometry3::from_parts(Translation3::from(pos), rot)
}

/// Builds a scene; see the module docs. Errors with `InvalidArgument` on fewer than 2
/// keyframes, no point, a track length below 2 or non-finite / negative parameters.
pub fn synthetic_scene(cfg: &SyntheticBaConfig) -> Result<SyntheticBa, CoreError> {
    let params = [
        cfg.noise_px,
        cfg.outlier_ratio,
        cfg.pose_sigma_t,
        cfg.pose_sigma_r,
        cfg.point_sigma,
    ];
    if cfg.n_keyframes < 2
        || cfg.n_points == 0
        || cfg.track_length < 2
        || !params.iter().all(|v| v.is_finite() && *v >= 0.0)
    {
        return Err(CoreError::InvalidArgument(
            "synthetic BA scene: invalid configuration".into(),
        ));
    }
    let mut rng = Rng(cfg.seed);
    let cam = cfg.camera;
    let mut truth = BaProblem::new();
    for k in 0..cfg.n_keyframes {
        truth.add_keyframe(true_t_wc(k).inverse(), cam, k < cfg.n_fixed);
    }
    let mut outlier = Vec::new();
    let (w, h) = (f64::from(cam.width), f64::from(cam.height));
    let mut tries = 0usize;
    while truth.points.len() < cfg.n_points && tries < 100 * cfg.n_points {
        tries += 1;
        // A track of consecutive keyframes and a point seen by its middle keyframe.
        let len = cfg.track_length.min(cfg.n_keyframes);
        let first = (rng.uniform(0.0, (cfg.n_keyframes - len + 1) as f64) as usize)
            .min(cfg.n_keyframes - len);
        let mid = first + len / 2;
        let depth = rng.uniform(3.0, 8.0);
        let bearing = cam.unproject(&Vector2::new(
            rng.uniform(20.0, w - 20.0),
            rng.uniform(20.0, h - 20.0),
        ));
        let p_c = bearing * (depth / bearing.z);
        let p_w = (true_t_wc(mid) * nalgebra::Point3::from(p_c)).coords;
        // Observations in every keyframe of the track where the point is visible.
        let mut obs = Vec::with_capacity(len);
        for k in first..first + len {
            let t_cw = truth.keyframes[k].t_cw;
            let q = (t_cw * nalgebra::Point3::from(p_w)).coords;
            if let Some(uv) = cam.project(&q) {
                if cam.contains(&uv) {
                    obs.push((k, uv));
                }
            }
        }
        if obs.len() < 2 {
            continue;
        }
        let j = truth.add_point(p_w, false);
        for (k, uv) in obs {
            let octave = match rng.uniform(0.0, 1.0) {
                x if x < 0.5 => 0,
                x if x < 0.75 => 1,
                x if x < 0.9 => 2,
                _ => 3,
            };
            let sigma = ORB_SCALE_FACTOR.powi(octave as i32) * cfg.noise_px;
            let is_out = rng.uniform(0.0, 1.0) < cfg.outlier_ratio;
            let pixel = if is_out {
                // A random pixel at least 30 px away from the true projection.
                loop {
                    let c = Vector2::new(rng.uniform(0.0, w - 1.0), rng.uniform(0.0, h - 1.0));
                    if (c - uv).norm() > 30.0 {
                        break c;
                    }
                }
            } else {
                uv + Vector2::new(rng.normal(), rng.normal()) * sigma
            };
            truth.add_observation(k, j, pixel, inv_sigma2_for_octave(octave, ORB_SCALE_FACTOR));
            outlier.push(is_out);
        }
    }
    let mut problem = truth.clone();
    for kf in problem.keyframes.iter_mut().filter(|k| !k.fixed) {
        let t_wc = kf.t_cw.inverse();
        let pos = t_wc.translation.vector + rng.normal3(cfg.pose_sigma_t);
        let rot = UnitQuaternion::from_scaled_axis(rng.normal3(cfg.pose_sigma_r)) * t_wc.rotation;
        kf.t_cw = Isometry3::from_parts(Translation3::from(pos), rot).inverse();
    }
    for p in problem.points.iter_mut() {
        p.p_w += rng.normal3(cfg.point_sigma);
    }
    Ok(SyntheticBa {
        problem,
        truth,
        outlier,
    })
}
