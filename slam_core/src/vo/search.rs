//! Matching map points to a frame by projection (ORB-SLAM's `SearchByProjection`): each
//! point is projected with a predicted pose and matched against the frame's keypoints in a
//! window around the prediction. Caller-owned outputs; no allocation per point.
use nalgebra::{Isometry3, Point3, Vector3};

use crate::camera::PinholeRadtan;
use crate::features::{match_in_window, FeatureGrid, OrbFeatures, TH_HIGH, TH_LOW};

/// A map point to look for.
#[derive(Debug, Clone, Copy)]
pub struct ProjCandidate {
    /// Point in the world frame.
    pub p_w: Vector3<f64>,
    /// Its descriptor.
    pub descriptor: [u8; 32],
    /// Octave where it was last seen (predicts the scale in the new frame).
    pub octave: u8,
    /// Caller's tag (map point id).
    pub tag: u64,
}

/// Parameters of [`search_by_projection`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ProjSearchParams {
    /// Window radius at octave 0, pixels (scaled by `scale_factor^octave` of the frame's
    /// pyramid, [`OrbFeatures::scale`]).
    pub radius: f32,
    /// Largest descriptor distance accepted.
    pub max_distance: u32,
    /// Best / second-best distance ratio (1.0 = no ratio test).
    pub ratio: f32,
    /// Octaves searched around the predicted one.
    pub octave_tolerance: u8,
}

impl ProjSearchParams {
    /// Search from the last frame with the motion model (ORB-SLAM: th = 15, TH_HIGH).
    pub fn motion_model() -> Self {
        Self {
            radius: 15.0,
            max_distance: TH_HIGH,
            ratio: 1.0,
            octave_tolerance: 1,
        }
    }

    /// Search of the local map (ORB-SLAM: ~4 px × scale, TH_HIGH with ratio 0.8).
    pub fn local_map() -> Self {
        Self {
            radius: 5.0,
            max_distance: TH_HIGH,
            ratio: 0.8,
            octave_tolerance: 1,
        }
    }

    /// A tight search for fusing / reference matching (TH_LOW).
    pub fn tight() -> Self {
        Self {
            radius: 4.0,
            max_distance: TH_LOW,
            ratio: 0.8,
            octave_tolerance: 1,
        }
    }
}

/// Matches `candidates` into `frame` (indexed by `grid`) projected with `t_cw`. For each
/// keypoint only the best candidate is kept. `out[k] = Some(candidate index)` per keypoint
/// `k` (cleared and resized here); keypoints already taken in `taken` are skipped. Returns
/// the number of matches.
#[allow(clippy::too_many_arguments)]
pub fn search_by_projection(
    candidates: &[ProjCandidate],
    t_cw: &Isometry3<f64>,
    camera: &PinholeRadtan,
    frame: &OrbFeatures,
    grid: &FeatureGrid,
    params: &ProjSearchParams,
    taken: &[bool],
    out: &mut Vec<Option<(usize, u32)>>,
) -> usize {
    out.clear();
    out.resize(frame.len(), None);
    let max_oct = frame.scale.max_octave();
    for (ci, c) in candidates.iter().enumerate() {
        let p_c = t_cw * Point3::from(c.p_w);
        if p_c.z <= 0.05 {
            continue;
        }
        let Some(uv) = camera.project(&p_c.coords) else {
            continue;
        };
        if !camera.contains(&uv) {
            continue;
        }
        let r = params.radius * frame.scale.level_scale(c.octave);
        let lo = c.octave.saturating_sub(params.octave_tolerance);
        let hi = (c.octave + params.octave_tolerance).min(max_oct);
        let Some(m) = match_in_window(
            grid,
            frame,
            (uv.x as f32, uv.y as f32),
            r,
            (lo, hi),
            &c.descriptor,
        ) else {
            continue;
        };
        if m.distance > params.max_distance || taken.get(m.index).copied().unwrap_or(true) {
            continue;
        }
        if params.ratio < 1.0
            && m.second_distance != u32::MAX
            && m.distance as f32 > params.ratio * m.second_distance as f32
        {
            continue;
        }
        match out[m.index] {
            Some((_, d)) if d <= m.distance => {}
            _ => out[m.index] = Some((ci, m.distance)),
        }
    }
    out.iter().filter(|o| o.is_some()).count()
}
