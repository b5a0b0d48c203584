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

use nalgebra::{Isometry3, Translation3, Vector2};

use super::{LastFrame, VoFrame, VoOutput, VoState, VoTracker};
use crate::features::{match_two_frames_windowed, OrbFeatures, WindowMatchParams};
use crate::optim::{PoseObservation, PoseOptParams};
use crate::twoview::{initialize, normalize_pixels, TwoViewParams};
use crate::vo::map::Keyframe;

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

impl VoTracker {
    /// One frame of initialisation; on success the map holds two keyframes and the state is
    /// `Tracking`.
    pub(super) fn try_initialize(
        &mut self,
        frame: &VoFrame<'_>,
        feats: &OrbFeatures,
        out: &mut VoOutput,
    ) {
        let enough = feats.len() >= self.params.init_min_matches;
        let Some(init) = self.init.as_mut() else {
            if enough {
                self.set_init_ref(frame, feats);
            }
            return;
        };
        let m0 = Instant::now();
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
            out.times.matching = m0.elapsed().as_secs_f32() * 1e3;
            self.init_matches = matches;
            // Too far from the reference: start again from this frame.
            if enough {
                self.set_init_ref(frame, feats);
            }
            return;
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
        let px = |f: &OrbFeatures, i: u32| {
            let k = f.keypoints[i as usize];
            Vector2::new(k.x as f64, k.y as f64)
        };
        let p1: Vec<Vector2<f64>> = matches
            .iter()
            .map(|m| px(&init.reference.features, m.query))
            .collect();
        let p2: Vec<Vector2<f64>> = matches.iter().map(|m| px(feats, m.train)).collect();
        let (mut x1, mut x2) = (Vec::new(), Vec::new());
        normalize_pixels(&self.camera, &p1, &mut x1);
        normalize_pixels(&self.camera, &p2, &mut x2);
        out.times.matching = m0.elapsed().as_secs_f32() * 1e3;
        let tv = TwoViewParams::for_camera(&self.camera);
        let res = match initialize(&x1, &x2, &tv) {
            Ok(r) => r,
            Err(e) => {
                if std::env::var_os("SHOAL_DEBUG_INIT").is_some() {
                    eprintln!(
                        "init: {} matches after {} frames: {e}",
                        matches.len(),
                        init.frames.len()
                    );
                }
                self.init_matches = matches;
                return;
            }
        };
        // Scale: median depth of the initial points = 1 (the map's unit).
        let mut depths: Vec<f64> = res
            .points
            .iter()
            .zip(&res.triangulated)
            .filter(|(_, t)| **t)
            .map(|(p, _)| p.z)
            .collect();
        if depths.len() < 50 {
            self.init_matches = matches;
            return;
        }
        depths.sort_by(f64::total_cmp);
        let s = 1.0 / depths[depths.len() / 2].max(1e-9);
        let t_21 = res.pose_21();
        let t_cw2 = Isometry3::from_parts((t_21.translation.vector * s).into(), t_21.rotation);
        let Some(init) = self.init.take() else {
            return;
        };
        let id1 = self.next_kf_id;
        let id2 = id1 + 1;
        self.next_kf_id += 2;
        let n1 = init.reference.features.len();
        let kf1 = Keyframe {
            id: id1,
            t_ns: init.reference.t_ns,
            t_cw: Isometry3::identity(),
            camera: self.camera,
            readout_ns: 0,
            features: init.reference.features,
            points: vec![None; n1],
        };
        let kf2 = Keyframe {
            id: id2,
            t_ns: frame.t_ns,
            t_cw: t_cw2,
            camera: self.camera,
            readout_ns: frame.readout_ns,
            features: feats.clone(),
            points: vec![None; feats.len()],
        };
        self.map.insert_keyframe(kf1);
        self.map.insert_keyframe(kf2);
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
        self.init_matches = matches;
        self.map.update_covisibility(id1);
        self.map.update_covisibility(id2);
        // Poses of the reference and of the frames in between.
        out.backfill
            .push((init.reference.t_ns, Isometry3::identity()));
        let span = (frame.t_ns - init.reference.t_ns) as f64;
        for f in init.frames.iter().filter(|f| f.t_ns != frame.t_ns) {
            let a = if span > 0.0 {
                (f.t_ns - init.reference.t_ns) as f64 / span
            } else {
                1.0
            };
            if let Some(pose) = self.backfill_pose(f, &ref_points, &t_cw2, a) {
                out.backfill.push((f.t_ns, pose));
            }
        }
        let dt = (frame.t_ns - init.reference.t_ns) as f64 * 1e-9;
        self.velocity = Some((t_cw2, dt.max(1e-6)));
        if let Some(&(t_prev, pose_prev)) = out.backfill.last() {
            // The motion model from the last backfilled frame when there is one.
            let dt = (frame.t_ns - t_prev) as f64 * 1e-9;
            if dt > 0.0 && t_prev != init.reference.t_ns {
                self.velocity = Some((t_cw2 * pose_prev.inverse(), dt));
            }
        }
        self.ref_kf = Some(id2);
        self.last = Some(self.last_from_kf(id2));
        self.state = VoState::Tracking;
        self.frames_since_kf = 0;
        out.t_cw = Some(t_cw2);
        out.keyframe = Some(id2);
        out.tracked = self.map.keyframes.get(&id2).map_or(0, |k| k.n_points());
    }

    /// Motion-only optimisation of a frame seen while initialising, from the pose
    /// interpolated at fraction `a` between the reference (identity) and `t_cw2`.
    fn backfill_pose(
        &mut self,
        f: &InitFrame,
        ref_points: &[Option<(crate::vo::PointId, nalgebra::Vector3<f64>)>],
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
