//! Matching map points to a frame by projection (ORB-SLAM's `SearchByProjection`): each
//! point is projected with a predicted pose and matched against the frame's keypoints in a
//! window around the prediction. Caller-owned outputs; no allocation per point.
//!
//! [`LocalMapMatcher`] is the one matcher of a frame against a map by projection: the
//! client's tracking (last frame's points, then the local map) and the server's refinement
//! of a keyframe pose (seed §3.4.1) both use it, with their own [`ProjSearchParams`] and
//! local keyframes.
use std::collections::HashSet;

use nalgebra::{Isometry3, Point3, Vector2, Vector3};

use crate::camera::PinholeRadtan;
use crate::features::{match_in_window, FeatureGrid, OrbFeatures, TH_HIGH, TH_LOW};
use crate::optim::PoseObservation;
use crate::vo::map::{ClientMap, KfId, PointId};

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

/// Parameters of [`search_by_projection`] and [`LocalMapMatcher::search`]: everything the
/// client's tracking and the server's refinement set differently.
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
    /// [`LocalMapMatcher::search`] leaves out the candidates already matched to a keypoint
    /// of the frame, so that a second search after a pose update cannot match a point twice
    /// (the server's refinement). `false` (the constructors): every candidate is searched
    /// (the client's searches start from a frame without matches of its candidates).
    pub skip_matched_points: bool,
}

impl ProjSearchParams {
    /// Search from the last frame with the motion model (ORB-SLAM: th = 15, TH_HIGH).
    pub fn motion_model() -> Self {
        Self {
            radius: 15.0,
            max_distance: TH_HIGH,
            ratio: 1.0,
            octave_tolerance: 1,
            skip_matched_points: false,
        }
    }

    /// Search of the local map (ORB-SLAM: ~4 px × scale, TH_HIGH with ratio 0.8).
    pub fn local_map() -> Self {
        Self {
            radius: 5.0,
            max_distance: TH_HIGH,
            ratio: 0.8,
            octave_tolerance: 1,
            skip_matched_points: false,
        }
    }

    /// A tight search for fusing / reference matching (TH_LOW).
    pub fn tight() -> Self {
        Self {
            radius: 4.0,
            max_distance: TH_LOW,
            ratio: 0.8,
            octave_tolerance: 1,
            skip_matched_points: false,
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

/// Matching of a frame against map points by projection, with reusable buffers (no
/// allocation per frame once grown): choose the candidates (the points of the local
/// keyframes, [`Self::gather_local_map`], or of an earlier frame,
/// [`Self::gather_frame`]), then [`Self::search`] them around their projections with a
/// predicted pose. Matches are kept per keypoint as map point ids (`frame_points`).
#[derive(Debug, Default)]
pub struct LocalMapMatcher {
    keyframes: Vec<KfId>,
    seen: HashSet<PointId>,
    cands: Vec<ProjCandidate>,
    taken: Vec<bool>,
    found: Vec<Option<(usize, u32)>>,
}

impl LocalMapMatcher {
    /// An empty matcher.
    pub fn new() -> Self {
        Self::default()
    }

    /// The local keyframes become `reference` (when it is in `map`) and its `covisible`
    /// best covisible keyframes (ORB-SLAM's local map, K1 ∪ the best of K2).
    pub fn select_keyframes(&mut self, map: &ClientMap, reference: Option<KfId>, covisible: usize) {
        self.keyframes.clear();
        if let Some(r) = reference.filter(|r| map.keyframes.contains_key(r)) {
            self.keyframes.push(r);
            self.keyframes.extend(map.covisible(r, covisible, 1));
        }
    }

    /// Adds `k` to the local keyframes (once).
    pub fn add_keyframe(&mut self, k: KfId) {
        if !self.keyframes.contains(&k) {
            self.keyframes.push(k);
        }
    }

    /// The local keyframes.
    pub fn keyframes(&self) -> &[KfId] {
        &self.keyframes
    }

    /// No candidates.
    pub fn clear_candidates(&mut self) {
        self.cands.clear();
    }

    /// The candidates of the next [`Self::search`].
    pub fn candidates(&self) -> &[ProjCandidate] {
        &self.cands
    }

    /// Candidates: the points of the local keyframes, each once, without those already in
    /// `frame_points`; each predicts its octave from the first local keyframe that sees it.
    pub fn gather_local_map(&mut self, map: &ClientMap, frame_points: &[Option<PointId>]) {
        self.cands.clear();
        self.seen.clear();
        self.seen.extend(frame_points.iter().flatten().copied());
        for k in &self.keyframes {
            let Some(kf) = map.keyframes.get(k) else {
                continue;
            };
            for (i, p) in kf.points.iter().enumerate() {
                let Some(p) = p else { continue };
                if !self.seen.insert(*p) {
                    continue;
                }
                if let Some(mp) = map.points.get(p) {
                    self.cands.push(ProjCandidate {
                        p_w: mp.p_w,
                        descriptor: mp.descriptor,
                        octave: kf.features.keypoints.get(i).map_or(0, |kp| kp.octave),
                        tag: *p,
                    });
                }
            }
        }
    }

    /// Candidates: the map points matched in an earlier frame (`points` per keypoint of
    /// `features`), at that frame's octaves (the motion-model search).
    pub fn gather_frame(
        &mut self,
        map: &ClientMap,
        points: &[Option<PointId>],
        features: &OrbFeatures,
    ) {
        self.cands.clear();
        for (i, p) in points.iter().enumerate() {
            let Some(mp) = p.and_then(|p| map.points.get(&p)) else {
                continue;
            };
            self.cands.push(ProjCandidate {
                p_w: mp.p_w,
                descriptor: mp.descriptor,
                octave: features.keypoints.get(i).map_or(0, |kp| kp.octave),
                tag: mp.id,
            });
        }
    }

    /// Projection search ([`search_by_projection`]) of the candidates not yet in
    /// `frame_points` into the keypoints of `feats` (indexed by `grid`) not yet matched,
    /// with the pose `t_cw`; fills those keypoints' `frame_points`. With
    /// [`ProjSearchParams::skip_matched_points`], candidates found in `frame_points` are
    /// first dropped from the candidates (a point is matched once). Returns the matched keypoints of
    /// `frame_points` (earlier matches included).
    #[allow(clippy::too_many_arguments)]
    pub fn search(
        &mut self,
        t_cw: &Isometry3<f64>,
        camera: &PinholeRadtan,
        feats: &OrbFeatures,
        grid: &FeatureGrid,
        params: &ProjSearchParams,
        frame_points: &mut [Option<PointId>],
    ) -> usize {
        self.taken.clear();
        self.taken.extend(frame_points.iter().map(|x| x.is_some()));
        if params.skip_matched_points && self.taken.iter().any(|&t| t) {
            self.seen.clear();
            self.seen.extend(frame_points.iter().flatten().copied());
            let seen = &self.seen;
            self.cands.retain(|c| !seen.contains(&c.tag));
        }
        search_by_projection(
            &self.cands,
            t_cw,
            camera,
            feats,
            grid,
            params,
            &self.taken,
            &mut self.found,
        );
        for (k, f) in self.found.iter().enumerate() {
            if let Some((ci, _)) = f {
                frame_points[k] = Some(self.cands[*ci].tag);
            }
        }
        frame_points.iter().filter(|x| x.is_some()).count()
    }
}

/// The pose-only optimiser's observations of the matched keypoints: `obs` gets one per
/// keypoint `k` of `feats` with a point of `map` in `frame_points[k]`, `obs_kp` its `k`.
/// The lines of `camera`'s image ([`PinholeRadtan::readout_line`]) are read out over
/// `readout_ns` (0: global shutter).
pub fn pose_observations(
    map: &ClientMap,
    feats: &OrbFeatures,
    frame_points: &[Option<PointId>],
    (readout_ns, camera): (i64, &PinholeRadtan),
    obs: &mut Vec<PoseObservation>,
    obs_kp: &mut Vec<usize>,
) {
    obs.clear();
    obs_kp.clear();
    for (k, p) in frame_points.iter().enumerate() {
        let Some(mp) = p.and_then(|p| map.points.get(&p)) else {
            continue;
        };
        let Some(kp) = feats.keypoints.get(k) else {
            continue;
        };
        let pixel = Vector2::new(kp.x as f64, kp.y as f64);
        let dt = if readout_ns == 0 {
            0.0
        } else {
            crate::rolling_shutter::pixel_offset_s(camera, readout_ns, &pixel)
        };
        obs.push(PoseObservation {
            point_w: mp.p_w,
            pixel,
            inv_sigma2: feats.scale.inv_sigma2(kp.octave),
            dt,
        });
        obs_kp.push(k);
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::features::KeyPoint;
    use crate::vo::map::Keyframe;

    fn keypoint(x: f64, y: f64) -> KeyPoint {
        KeyPoint::at_level0(x as f32, y as f32)
    }

    /// A map with one keyframe at the origin seeing 20 points, and that keyframe's features.
    fn scene(cam: &PinholeRadtan) -> (ClientMap, OrbFeatures) {
        let mut state = 7u64;
        let mut byte = || {
            state = state.wrapping_mul(6364136223846793005).wrapping_add(1);
            (state >> 56) as u8
        };
        let pts: Vec<Vector3<f64>> = (0..20)
            .map(|i| {
                let f = i as f64;
                Vector3::new(-1.0 + 0.1 * f, 0.05 * (i % 5) as f64 - 0.1, 4.0 + 0.05 * f)
            })
            .collect();
        let mut feats = OrbFeatures::default();
        for p in &pts {
            let uv = cam.project(p).expect("in front");
            feats.keypoints.push(keypoint(uv.x, uv.y));
            feats.descriptors.push(std::array::from_fn(|_| byte()));
        }
        let mut map = ClientMap::new(1, 100);
        map.insert_keyframe(Keyframe {
            id: 0,
            t_ns: 0,
            t_cw: Isometry3::identity(),
            camera: *cam,
            readout_ns: 0,
            features: feats.clone(),
            points: vec![None; pts.len()],
            inertial: None,
            imu: None,
        });
        for (i, p) in pts.iter().enumerate() {
            map.add_point(*p, 0, &[(0, i as u32)]);
        }
        (map, feats)
    }

    #[test]
    fn local_map_matcher_finds_the_local_points_and_can_match_each_once() {
        let cam = PinholeRadtan::pinhole(640, 480, 500.0, 500.0, 320.0, 240.0);
        let (map, mut frame) = scene(&cam);
        // A second keypoint with the descriptor of keypoint 0, 8 pixels to the right.
        let k0 = frame.keypoints[0];
        frame
            .keypoints
            .push(keypoint(f64::from(k0.x) + 8.0, f64::from(k0.y)));
        frame.descriptors.push(frame.descriptors[0]);
        let mut grid = FeatureGrid::new(640, 480, 16.0).expect("grid");
        grid.build(&frame.keypoints);
        for skip in [false, true] {
            let mut m = LocalMapMatcher::new();
            let mut fp = vec![None; frame.len()];
            m.select_keyframes(&map, Some(0), 5);
            assert_eq!(m.keyframes(), &[0]);
            m.gather_local_map(&map, &fp);
            assert_eq!(m.candidates().len(), 20);
            let p = ProjSearchParams {
                skip_matched_points: skip,
                ..ProjSearchParams::local_map()
            };
            let t = Isometry3::identity();
            assert_eq!(m.search(&t, &cam, &frame, &grid, &p, &mut fp), 20);
            // Each point on its own keypoint (point ids from 100 on).
            for (k, id) in fp.iter().enumerate().take(20).skip(1) {
                assert_eq!(*id, Some(100 + k as u64));
            }
            // A second search from a pose that moves point 100 (depth 4 m) 8 pixels right:
            // the free duplicate keypoint takes it again unless matched points are skipped.
            let moved = Isometry3::translation(8.0 * 4.0 / 500.0, 0.0, 0.0);
            let n = m.search(&moved, &cam, &frame, &grid, &p, &mut fp);
            assert_eq!(n, if skip { 20 } else { 21 });
            // Matched points are no candidates of the local map.
            m.gather_local_map(&map, &fp);
            assert!(m.candidates().is_empty());
            let (mut obs, mut obs_kp) = (Vec::new(), Vec::new());
            pose_observations(&map, &frame, &fp, (0, &cam), &mut obs, &mut obs_kp);
            assert_eq!(obs.len(), n);
            assert!(obs.iter().all(|o| o.dt == 0.0 && o.inv_sigma2 == 1.0));
            assert_eq!(obs_kp[1], 1);
        }
    }
}
