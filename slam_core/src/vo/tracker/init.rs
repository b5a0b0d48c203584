//! Two-view initialisation of a VO session (seed §3.3; ORB-SLAM's monocular initialiser):
//! a reference frame, windowed matching of every later frame against it (each window
//! follows the feature's last matched position, so the baseline can grow over many frames
//! of forward motion), homography/essential selection in [`crate::twoview::initialize`],
//! and a map of two keyframes scaled to a median depth of 1.
//!
//! Frames between the reference and the initialising frame are not lost: once the map
//! exists, each of them gets a pose by motion-only optimisation against the new points
//! ("backfill"), so every frame from the reference on has a pose.
use std::time::Instant;

use nalgebra::{Isometry3, Translation3, Vector2, Vector3};

use super::{LastFrame, VoDiagnostic, VoFrame, VoOutput, VoState, VoTracker};
use crate::features::{match_two_frames_windowed, OrbFeatures, WindowMatchParams};
use crate::optim::{PoseObservation, PoseOptParams};
use crate::twoview::{initialize, normalize_pixels, TwoViewParams, TwoViewResult};
use crate::vo::map::{Keyframe, KfId, PointId};

/// Most frames remembered for the backfill.
const MAX_BACKFILL: usize = 64;

/// A frame seen while initialising: its matches to the reference.
pub(super) struct InitFrame {
    t_ns: i64,
    /// `(reference feature, pixel, information 1/σ² of its octave)`.
    obs: Vec<(u32, [f32; 2], f64)>,
}

/// The initialiser's state.
pub(super) struct InitState {
    reference: LastFrame,
    /// Last matched position of each reference feature (the centre of its next window).
    prev: Vec<[f32; 2]>,
    frames: Vec<InitFrame>,
}

/// A reference feature's map point and its position (world = reference camera frame),
/// indexed by reference feature; `None` where no point was made.
type RefPoints = Vec<Option<(PointId, Vector3<f64>)>>;

/// Milliseconds since `t0`.
fn ms_since(t0: Instant) -> f32 {
    t0.elapsed().as_secs_f32() * 1e3
}

/// Scale making the median depth of the triangulated points 1 (the map's unit); `None`
/// with fewer than 50 of them.
fn median_depth_scale(res: &TwoViewResult) -> Option<f64> {
    let mut depths: Vec<f64> = res
        .points
        .iter()
        .zip(&res.triangulated)
        .filter(|(_, t)| **t)
        .map(|(p, _)| p.z)
        .collect();
    if depths.len() < 50 {
        return None;
    }
    depths.sort_by(f64::total_cmp);
    Some(1.0 / depths[depths.len() / 2].max(1e-9))
}

impl VoTracker {
    /// One frame of initialisation; on success the map holds two keyframes and the state is
    /// `Tracking`. Steps: 1. windowed matching against the reference frame (a new reference
    /// when it fails), 2. two-view geometry ([`initialize`]), 3. scale (median depth 1),
    /// 4. the map of two keyframes, 5. poses of the frames in between (backfill), 6. the
    /// motion model and the tracking state.
    pub(super) fn try_initialize(
        &mut self,
        frame: &VoFrame<'_>,
        feats: &OrbFeatures,
        out: &mut VoOutput,
    ) {
        let enough = feats.len() >= self.params.init_min_matches;
        if self.init.is_none() {
            if enough {
                self.set_init_ref(frame, feats);
            }
            return;
        }
        // 1. Matches to the reference.
        let m0 = Instant::now();
        let Some(matches) = self.match_init_reference(frame, feats) else {
            out.times.matching = ms_since(m0);
            // Too far from the reference: start again from this frame.
            if enough {
                self.set_init_ref(frame, feats);
            }
            return;
        };
        // 2. Two-view geometry.
        let (x1, x2) = self.normalized_init_matches(feats, &matches);
        out.times.matching = ms_since(m0);
        let tv = TwoViewParams::for_camera(&self.camera);
        let res = match initialize(&x1, &x2, &tv) {
            Ok(r) => r,
            Err(e) => {
                out.diagnostics.push(VoDiagnostic::InitFailed {
                    matches: matches.len(),
                    frames: self.init.as_ref().map_or(0, |i| i.frames.len()),
                    reason: e.to_string(),
                });
                self.init_matches = matches;
                return;
            }
        };
        // 3. Scale: median depth of the initial points = 1 (the map's unit).
        let Some(s) = median_depth_scale(&res) else {
            self.init_matches = matches;
            return;
        };
        let t_21 = res.pose_21();
        let t_cw2 = Isometry3::from_parts((t_21.translation.vector * s).into(), t_21.rotation);
        let Some(InitState {
            reference, frames, ..
        }) = self.init.take()
        else {
            return;
        };
        // 4. The map.
        let t_ref = reference.t_ns;
        let (id2, ref_points) =
            self.create_initial_map(reference, frame, feats, &matches, &res, s, &t_cw2);
        self.init_matches = matches;
        // 5. Poses of the reference and of the frames in between.
        self.backfill_init_frames(t_ref, &frames, frame.t_ns, &ref_points, &t_cw2, out);
        // 6. Motion model and state.
        self.start_tracking_after_init(frame.t_ns, t_ref, t_cw2, id2, out);
    }

    /// Windowed matching of `feats` against the reference (each window around the
    /// feature's last matched position, which is then updated); the frame's matches are
    /// remembered for the backfill. `None` (the buffer given back) with fewer than
    /// `init_min_matches`.
    fn match_init_reference(
        &mut self,
        frame: &VoFrame<'_>,
        feats: &OrbFeatures,
    ) -> Option<Vec<crate::features::Match>> {
        let init = self.init.as_mut()?;
        let mut matches = std::mem::take(&mut self.init_matches);
        let wp = WindowMatchParams {
            radius: 100.0,
            ..WindowMatchParams::default()
        };
        let matched = match_two_frames_windowed(
            &init.reference.features,
            feats,
            &self.grid,
            Some(&init.prev),
            &wp,
            &mut matches,
        );
        if matched.is_err() || matches.len() < self.params.init_min_matches {
            self.init_matches = matches;
            return None;
        }
        for m in &matches {
            let k = feats.keypoints[m.train as usize];
            init.prev[m.query as usize] = [k.x, k.y];
        }
        if init.frames.len() < MAX_BACKFILL {
            init.frames.push(InitFrame {
                t_ns: frame.t_ns,
                obs: matches
                    .iter()
                    .map(|m| {
                        let k = feats.keypoints[m.train as usize];
                        (m.query, [k.x, k.y], feats.scale.inv_sigma2(k.octave))
                    })
                    .collect(),
            });
        }
        Some(matches)
    }

    /// Undistorted normalised coordinates of the matches in the reference (`x1`) and in
    /// the frame (`x2`).
    fn normalized_init_matches(
        &self,
        feats: &OrbFeatures,
        matches: &[crate::features::Match],
    ) -> (Vec<Vector2<f64>>, Vec<Vector2<f64>>) {
        let px = |f: &OrbFeatures, i: u32| {
            let k = f.keypoints[i as usize];
            Vector2::new(k.x as f64, k.y as f64)
        };
        let (mut x1, mut x2) = (Vec::new(), Vec::new());
        if let Some(init) = &self.init {
            let p1: Vec<Vector2<f64>> = matches
                .iter()
                .map(|m| px(&init.reference.features, m.query))
                .collect();
            normalize_pixels(&self.camera, &p1, &mut x1);
        }
        let p2: Vec<Vector2<f64>> = matches.iter().map(|m| px(feats, m.train)).collect();
        normalize_pixels(&self.camera, &p2, &mut x2);
        (x1, x2)
    }

    /// Step 4: the reference (identity) and the frame (`t_cw2`) become keyframes, the
    /// triangulated matches (scaled by `s`) map points. Returns the second keyframe's id and
    /// the reference features' points.
    #[allow(clippy::too_many_arguments)]
    fn create_initial_map(
        &mut self,
        reference: LastFrame,
        frame: &VoFrame<'_>,
        feats: &OrbFeatures,
        matches: &[crate::features::Match],
        res: &TwoViewResult,
        s: f64,
        t_cw2: &Isometry3<f64>,
    ) -> (KfId, RefPoints) {
        let id1 = self.next_kf_id;
        let id2 = id1 + 1;
        self.next_kf_id += 2;
        let n1 = reference.features.len();
        let (imu1, imu2) = (
            self.keyframe_imu(reference.t_ns),
            self.keyframe_imu(frame.t_ns),
        );
        self.map.insert_keyframe(Keyframe {
            id: id1,
            t_ns: reference.t_ns,
            t_cw: Isometry3::identity(),
            camera: self.camera,
            readout_ns: 0,
            features: reference.features,
            points: vec![None; n1],
            inertial: None,
            imu: imu1,
        });
        self.map.insert_keyframe(Keyframe {
            id: id2,
            t_ns: frame.t_ns,
            t_cw: *t_cw2,
            camera: self.camera,
            readout_ns: frame.readout_ns,
            features: feats.clone(),
            points: vec![None; feats.len()],
            inertial: None,
            imu: imu2,
        });
        // Reference feature -> (point, position) for the backfill.
        let mut ref_points = vec![None; n1];
        for (k, m) in matches.iter().enumerate() {
            if res.triangulated[k] {
                let p = res.points[k] * s;
                let id = self
                    .map
                    .add_point(p, id1, &[(id1, m.query), (id2, m.train)]);
                ref_points[m.query as usize] = Some((id, p));
            }
        }
        self.map.update_covisibility(id1);
        self.map.update_covisibility(id2);
        (id2, ref_points)
    }

    /// Step 5: the reference's pose (identity) and those of the frames between it (at
    /// `t_ref`) and the initialising frame (at `t_ns`), into `out.backfill`.
    fn backfill_init_frames(
        &mut self,
        t_ref: i64,
        frames: &[InitFrame],
        t_ns: i64,
        ref_points: &RefPoints,
        t_cw2: &Isometry3<f64>,
        out: &mut VoOutput,
    ) {
        out.backfill.push((t_ref, Isometry3::identity()));
        let span = (t_ns - t_ref) as f64;
        for f in frames.iter().filter(|f| f.t_ns != t_ns) {
            let a = if span > 0.0 {
                (f.t_ns - t_ref) as f64 / span
            } else {
                1.0
            };
            if let Some(pose) = self.backfill_pose(f, ref_points, t_cw2, a) {
                out.backfill.push((f.t_ns, pose));
            }
        }
    }

    /// Step 6: the motion model (from the last backfilled frame when there is one, else
    /// from the reference) and the tracking state with keyframe `id2` as reference.
    fn start_tracking_after_init(
        &mut self,
        t_ns: i64,
        t_ref: i64,
        t_cw2: Isometry3<f64>,
        id2: KfId,
        out: &mut VoOutput,
    ) {
        let dt = (t_ns - t_ref) as f64 * 1e-9;
        self.velocity = Some((t_cw2, dt.max(1e-6)));
        if let Some(&(t_prev, pose_prev)) = out.backfill.last() {
            let dt = (t_ns - t_prev) as f64 * 1e-9;
            if dt > 0.0 && t_prev != t_ref {
                self.velocity = Some((t_cw2 * pose_prev.inverse(), dt));
            }
        }
        self.ref_kf = Some(id2);
        self.last = Some(self.last_from_kf(id2));
        self.state = VoState::Tracking;
        self.frames_since_kf = 0;
        out.t_cw = Some(t_cw2);
        out.keyframe = Some(id2);
        self.keyframe_poses(&mut out.keyframe_poses);
        out.tracked = self.map.keyframes.get(&id2).map_or(0, |k| k.n_points());
    }

    /// Motion-only optimisation of a frame seen while initialising, from the pose
    /// interpolated at fraction `a` between the reference (identity) and `t_cw2`.
    fn backfill_pose(
        &mut self,
        f: &InitFrame,
        ref_points: &[Option<(PointId, Vector3<f64>)>],
        t_cw2: &Isometry3<f64>,
        a: f64,
    ) -> Option<Isometry3<f64>> {
        self.obs.clear();
        for &(q, px, inv_sigma2) in &f.obs {
            let Some((_, p_w)) = ref_points.get(q as usize).copied().flatten() else {
                continue;
            };
            self.obs.push(PoseObservation {
                point_w: p_w,
                pixel: Vector2::new(px[0] as f64, px[1] as f64),
                inv_sigma2,
                dt: 0.0,
            });
        }
        if self.obs.len() < self.params.min_inliers {
            return None;
        }
        let guess = Isometry3::from_parts(
            Translation3::from(t_cw2.translation.vector * a),
            Isometry3::<f64>::identity()
                .rotation
                .slerp(&t_cw2.rotation, a),
        );
        self.inliers.clear();
        self.inliers.resize(self.obs.len(), true);
        let res = self
            .optimizer
            .optimize(
                &self.camera,
                &guess,
                &self.obs,
                None,
                &PoseOptParams::default(),
                &mut self.inliers,
            )
            .ok()?;
        (res.n_inliers >= self.params.min_inliers).then_some(res.t_cw)
    }

    pub(super) fn set_init_ref(&mut self, frame: &VoFrame<'_>, feats: &OrbFeatures) {
        self.init = Some(InitState {
            reference: LastFrame {
                t_ns: frame.t_ns,
                t_cw: Isometry3::identity(),
                features: feats.clone(),
                points: Vec::new(),
            },
            prev: feats.keypoints.iter().map(|k| [k.x, k.y]).collect(),
            frames: Vec::new(),
        });
        self.state = VoState::Initializing;
    }
}
