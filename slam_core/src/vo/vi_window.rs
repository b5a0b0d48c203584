//! The sliding-window visual-inertial optimisation of a visual-inertial client's local
//! mapping (issue 17; `VI_NOTES.md` §4 "Local BA (Fig. 5.5)", Table 5.1 "local BA = window
//! poses, v, b, points vs reprojections + IMU"): the map side of [`crate::imu::window`].
//! [`prepare_vi_window`] builds the window of a new keyframe from the client map (a
//! snapshot: the map may change while it is solved), [`apply_vi_window`] writes it back.
//!
//! **Which keyframes.** The new keyframe and the keyframes before it in time, as long as
//! each is linked to the next by its IMU segment ([`super::keyframe_imu`]), at most
//! [`ViMappingParams::keyframes`] (N = 10) free ones plus the one before them: the *chain*.
//! Besides, up to [`ViMappingParams::fixed_covisible`] older keyframes that see the
//! window's points, fixed with their observations only (ORB-SLAM3's local inertial BA, Mur-
//! Artal & Tardós 2017): they tie the points, and so the scale, to the rest of the map. The
//! window runs only on a keyframe with an inertial state, i.e. once the world is metric and
//! gravity-aligned (the visual-inertial client gives keyframes an inertial state after its
//! inertial initialisation, never before). Its size is bounded: N + 1 + 10 keyframes.
//!
//! **Old states are fixed, not marginalised** ([`crate::imu::window`] module docs: a
//! marginalisation prior must keep its linearisation point or it adds information along
//! the unobservable directions, and it fills the keyframe band; a keyframe leaving this
//! window has been refined by up to N windows). The oldest keyframe of the chain is fixed
//! *with its IMU factor* to the next: it anchors position, yaw, velocity, biases and,
//! through the IMU factor, gravity.
//!
//! **First windows** (`VI_NOTES.md` §4, "then VI BA"): when no keyframe of the map has a
//! state refined by an earlier window (right after the inertial initialisation; a resumed
//! session's keyframes count as refined: its scale and gravity were corrected before),
//! every chain keyframe is free, with a 4-DoF gauge prior on the oldest one's position and
//! yaw ([`gauge_prior`]), and no covisible keyframe: the window may then correct the
//! initialisation's gravity direction and scale. That correction is a similarity of the
//! whole session, not of the window alone (the map outside the window and the poses
//! published since the initialisation must follow): its rotation (the mean change of the
//! keyframe orientations) and scale (of the positions about the gauged keyframe) are taken
//! out of the solution, which is written back in the map's present world, and left in
//! [`ClientMap::world_correction`] for the client to apply as a world move, like a
//! refinement of the initialisation (`crate::vio`). No window runs until it is applied.
//!
//! **Session windows** (ORB-SLAM3's visual-inertial BA after the initialisation and at its
//! refinements, `VI_NOTES.md` §4): the first windows, and the window of a keyframe the
//! client asked for ([`ClientMap::session_window_from_ns`], some seconds after its
//! initialisation), take the whole IMU chain of the session (at most
//! [`ViMappingParams::session_keyframes`]), gauged as above. Ten keyframes of a gentle
//! motion do not tell the scale (and a point seen by one of them only is held fixed, an
//! anchor at the old scale); the whole session's keyframes and points do: on the gentle
//! `two-agents` paths (in-process, seeds 3 and 7) initialisations accepted 4.8-14 % off in
//! scale come within 0.8-1.6 % (still all too small: see the client's report).
//!
//! **States.** Pose from the keyframe's camera pose and `T_bc`; velocity and biases from its
//! inertial state; a keyframe made before the initialisation has none: its velocity is the
//! finite difference of its neighbours' positions, its biases those of the nearest later
//! keyframe. The IMU is re-integrated between consecutive keyframes at the biases of the
//! earlier one. Points: those seen by the free keyframes, observed by every keyframe of
//! the window (σ = the keypoint octave's; a rolling-shutter row's time after the keyframe,
//! seed eq. 2.61, so the window moves its camera by the velocity, `crate::imu::window`).
//! After the solve, observations above the 95 % χ²(2) gate (or behind their camera) leave
//! the map, as after the visual local BA.
use std::collections::HashMap;

use nalgebra::{Isometry3, Translation3, UnitQuaternion, Vector2, Vector3};

use super::map::{ClientMap, KeyframeInertial, KfId, PointId};
use crate::imu::window::{
    gauge_prior, reprojection_jacobians, ViKeyframe, ViObservation, ViParams, ViWindow,
};
use crate::imu::{gravity_w, ImuBiases, NavState, Preintegrated};
use crate::lie::Sim3;
use crate::rolling_shutter::pixel_offset_s;

/// The 95 % gate of χ²(2).
const CHI2_2DOF_95: f64 = 5.991;

/// What local mapping adjusts once the world is metric.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ViMappingMode {
    /// The visual local BA only (the visual-inertial window never runs).
    Off,
    /// The visual local BA, then the visual-inertial window.
    AfterVisualBa,
    /// The visual-inertial window instead of the visual local BA (the visual BA when the
    /// window cannot run or fails).
    InsteadOfVisualBa,
}

/// Settings of the visual-inertial window of local mapping.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ViMappingParams {
    /// What runs.
    pub mode: ViMappingMode,
    /// Free keyframes N of a window (the one before them is added, fixed or gauged).
    pub keyframes: usize,
    /// Most keyframes of a session window (module docs, "Session windows").
    pub session_keyframes: usize,
    /// The solver.
    pub solver: ViParams,
    /// Gauge prior of a window without a refined oldest state: position 1σ, m.
    pub gauge_sigma_m: f64,
    /// Gauge prior: yaw 1σ, rad.
    pub gauge_sigma_rad: f64,
    /// Fewest observations for a window.
    pub min_observations: usize,
    /// Most older covisible keyframes added fixed, with their observations only (they
    /// anchor the points to the rest of the map, as in ORB-SLAM3's local inertial BA).
    pub fixed_covisible: usize,
    /// Gauge the first windows of a map (module docs, "First windows"): right for the
    /// client, whose initialisation's gravity and scale the first windows correct; the
    /// server's maps of visual-inertial keyframes are already in the client's corrected
    /// world, so there every window fixes its oldest keyframe.
    pub gauge_first_windows: bool,
}

impl Default for ViMappingParams {
    fn default() -> Self {
        Self {
            mode: ViMappingMode::InsteadOfVisualBa,
            keyframes: 10,
            session_keyframes: 100,
            solver: ViParams::default(),
            gauge_sigma_m: 1e-3,
            gauge_sigma_rad: 1e-3,
            min_observations: 20,
            fixed_covisible: 10,
            gauge_first_windows: true,
        }
    }
}

/// Why no window was built for a keyframe.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ViSkip {
    /// The keyframe has no inertial state or IMU segment (not initialised, a monocular
    /// client, or no longer in the map).
    NotInertial,
    /// Fewer than two keyframes linked to it by the IMU.
    ShortChain,
    /// Too few observations.
    FewObservations,
    /// The map waits for the client to apply a gravity correction
    /// ([`ClientMap::world_correction`]): its states are not in the gravity-aligned
    /// world until then.
    CorrectionPending,
}

/// The map elements of a window built by [`prepare_vi_window`], in window order, and
/// reusable buffers.
#[derive(Debug, Default)]
pub struct ViWindowJob {
    /// Keyframe of each window keyframe (the fixed covisible ones, then the IMU chain in
    /// time order).
    pub kf_ids: Vec<KfId>,
    /// Point of each window point.
    pub pt_ids: Vec<PointId>,
    /// `(point, keyframe, keypoint)` of each window observation.
    pub obs_keys: Vec<(PointId, KfId, u32)>,
    /// Refinements of each keyframe's inertial state before the window.
    refined: Vec<u32>,
    /// Body orientation and camera centre of each window keyframe before the window.
    r_before: Vec<UnitQuaternion<f64>>,
    c_before: Vec<Vector3<f64>>,
    point_index: HashMap<PointId, u32>,
    inliers: Vec<bool>,
    /// The window was gauged (module docs, "First windows").
    gauged: bool,
    /// The window is one the client asked for (module docs, "Session windows").
    asked: bool,
    /// The IMU chain, oldest first.
    chain: Vec<KfId>,
    /// Covisible keyframes outside the chain and their observations of window points.
    counts: HashMap<KfId, u32>,
    covisible: Vec<(KfId, u32)>,
}

/// The keyframes before `k` (and `k`) linked by their IMU segments, at most `max`, oldest
/// first, into `out`.
fn imu_chain(map: &ClientMap, k: KfId, max: usize, out: &mut Vec<KfId>) {
    out.clear();
    let Some(mut cur) = map.keyframes.get(&k) else {
        return;
    };
    out.push(k);
    while out.len() < max {
        let Some((_, prev)) = map.keyframes.range(..cur.id).next_back() else {
            break;
        };
        match (&cur.imu, &prev.imu) {
            (Some(a), Some(b)) if a.links(b) => {}
            _ => break,
        }
        out.push(prev.id);
        cur = prev;
    }
    out.reverse();
}

/// Builds the window of keyframe `k` into `w` and `job` (module docs).
pub fn prepare_vi_window(
    map: &ClientMap,
    k: KfId,
    params: &ViMappingParams,
    w: &mut ViWindow,
    job: &mut ViWindowJob,
) -> Result<(), ViSkip> {
    let newest = map.keyframes.get(&k).ok_or(ViSkip::NotInertial)?;
    let (Some(_), Some(seg)) = (newest.inertial, newest.imu.as_ref()) else {
        return Err(ViSkip::NotInertial);
    };
    if map.world_correction.is_some() {
        return Err(ViSkip::CorrectionPending);
    }
    let (t_bc, camera) = (seg.calib.t_bc, newest.camera);
    // Gauged: the session's first windows, while no keyframe of the map is refined (a
    // resumed session's keyframes count as refined: its scale and gravity are not
    // corrected twice), and the session windows the client asks for.
    let asked = map.session_window_from_ns.is_some_and(|t| newest.t_ns >= t);
    let gauged = asked
        || params.gauge_first_windows
            && !map
                .keyframes
                .values()
                .any(|k| k.inertial.is_some_and(|i| i.refined > 0));
    let max = if gauged {
        params.session_keyframes.max(params.keyframes + 1)
    } else {
        params.keyframes + 1
    };
    imu_chain(map, k, max, &mut job.chain);
    if job.chain.len() < 3 {
        return Err(ViSkip::ShortChain);
    }
    collect_points(map, job, w, gauged);
    let n_visual = if gauged {
        0
    } else {
        covisible_keyframes(map, job, params.fixed_covisible)
    };
    job.kf_ids.clear();
    job.kf_ids
        .extend(job.covisible.iter().take(n_visual).map(|c| c.0));
    job.kf_ids.extend(job.chain.iter());
    w.n_visual = n_visual;
    job.gauged = gauged;
    job.asked = asked;
    window_states(map, job, w, &t_bc, gauged);
    window_preints(map, job, w).ok_or(ViSkip::ShortChain)?;
    window_observations(map, job, w);
    if w.observations.len() < params.min_observations {
        return Err(ViSkip::FewObservations);
    }
    w.t_bc = t_bc;
    w.camera = camera;
    w.gravity_w = gravity_w();
    let a = w.n_visual;
    w.prior = gauged.then(|| {
        let s = w.keyframes[a].state;
        gauge_prior(a, &s, params.gauge_sigma_m, params.gauge_sigma_rad)
    });
    Ok(())
}

/// The points seen by the free keyframes of the chain (all of them when `gauged`, else all
/// but the oldest).
fn collect_points(map: &ClientMap, job: &mut ViWindowJob, w: &mut ViWindow, gauged: bool) {
    job.pt_ids.clear();
    job.point_index.clear();
    w.points_w.clear();
    for id in job.chain.iter().skip(usize::from(!gauged)) {
        for p in map.keyframes[id].points.iter().flatten() {
            let Some(mp) = map.points.get(p) else {
                continue;
            };
            if let std::collections::hash_map::Entry::Vacant(e) = job.point_index.entry(*p) {
                e.insert(job.pt_ids.len() as u32);
                job.pt_ids.push(*p);
                w.points_w.push(mp.p_w);
            }
        }
    }
}

/// The keyframes outside the chain that observe the most window points, at most `max`,
/// into `job.covisible` (most observations first, then by id); returns how many.
fn covisible_keyframes(map: &ClientMap, job: &mut ViWindowJob, max: usize) -> usize {
    job.counts.clear();
    for p in &job.pt_ids {
        for (kf, _) in map.points.get(p).map_or(&[][..], |mp| &mp.observations[..]) {
            if !job.chain.contains(kf) {
                *job.counts.entry(*kf).or_insert(0) += 1;
            }
        }
    }
    job.covisible.clear();
    job.covisible
        .extend(job.counts.iter().map(|(k, n)| (*k, *n)));
    job.covisible
        .sort_unstable_by(|a, b| b.1.cmp(&a.1).then(a.0.cmp(&b.0)));
    job.covisible.truncate(max);
    job.covisible.len()
}

/// The keyframe states of the window (module docs, "States"): the covisible keyframes
/// fixed, the oldest of the chain fixed unless `gauged`.
fn window_states(
    map: &ClientMap,
    job: &mut ViWindowJob,
    w: &mut ViWindow,
    t_bc: &nalgebra::Isometry3<f64>,
    gauged: bool,
) {
    w.keyframes.clear();
    job.refined.clear();
    job.r_before.clear();
    job.c_before.clear();
    for (c, id) in job.kf_ids.iter().enumerate() {
        let kf = &map.keyframes[id];
        let i = kf.inertial.unwrap_or_default();
        let v = kf.inertial.map_or(Vector3::zeros(), |i| i.v_wb);
        job.refined.push(i.refined);
        let state = NavState::from_camera(&kf.t_cw, t_bc, v, i.biases);
        job.r_before
            .push(UnitQuaternion::from_rotation_matrix(&state.r));
        job.c_before.push(kf.center());
        w.keyframes.push(ViKeyframe {
            rig: 0,
            t_ns: kf.imu.as_ref().map_or(kf.t_ns, |s| s.t_ns),
            state,
            fixed: c < w.n_visual || (c == w.n_visual && !gauged),
        });
    }
    fill_missing_states(map, job, w);
}

/// Velocity (finite difference of the neighbours' positions) and biases (the nearest later
/// keyframe's) of chain keyframes without an inertial state.
fn fill_missing_states(map: &ClientMap, job: &ViWindowJob, w: &mut ViWindow) {
    let (n0, n) = (w.n_visual, w.keyframes.len());
    let mut biases: Option<ImuBiases> = None;
    for c in (n0..n).rev() {
        match map.keyframes[&job.kf_ids[c]].inertial {
            Some(i) => biases = Some(i.biases),
            None => {
                let (a, b) = (c.saturating_sub(1).max(n0), (c + 1).min(n - 1));
                let (ka, kb) = (&w.keyframes[a], &w.keyframes[b]);
                let dt = (kb.t_ns - ka.t_ns) as f64 * 1e-9;
                let v = (dt > 0.0).then(|| (kb.state.p - ka.state.p) / dt);
                let s = &mut w.keyframes[c].state;
                s.v = v.unwrap_or(s.v);
                s.biases = biases.unwrap_or_default();
            }
        }
    }
}

/// The IMU re-integrated between consecutive chain keyframes at the earlier one's biases;
/// `None` when a segment does not cover its span.
fn window_preints(map: &ClientMap, job: &ViWindowJob, w: &mut ViWindow) -> Option<()> {
    w.preints.clear();
    for c in w.n_visual + 1..job.kf_ids.len() {
        let seg = map.keyframes[&job.kf_ids[c]].imu.as_ref()?;
        let (a, b) = (&w.keyframes[c - 1], &w.keyframes[c]);
        let pre = Preintegrated::from_window(
            &seg.samples,
            a.t_ns,
            b.t_ns,
            a.state.biases,
            seg.calib.preint,
        )?;
        w.preints.push(pre);
    }
    Some(())
}

/// The observations of the window points in every window keyframe.
fn window_observations(map: &ClientMap, job: &mut ViWindowJob, w: &mut ViWindow) {
    job.obs_keys.clear();
    w.observations.clear();
    for (c, id) in job.kf_ids.iter().enumerate() {
        let kf = &map.keyframes[id];
        for (i, p) in kf.points.iter().enumerate() {
            let Some(&point) = p.and_then(|p| job.point_index.get(&p)) else {
                continue;
            };
            let kp = kf.features.keypoints[i];
            let uv = Vector2::new(f64::from(kp.x), f64::from(kp.y));
            w.observations.push(ViObservation {
                kf: c as u32,
                point,
                uv,
                sigma_px: kf.features.scale.sigma2(kp.octave).sqrt(),
                dt_s: pixel_offset_s(&kf.camera, kf.readout_ns, &uv),
            });
            job.obs_keys
                .push((job.pt_ids[point as usize], *id, i as u32));
        }
    }
}

/// Writes a solved window back into the map (module docs): the free keyframes' poses and
/// inertial states, the points, and the removal of outlier observations. Keyframes and
/// points that left the map meanwhile are skipped. Returns the observations removed.
pub fn apply_vi_window(map: &mut ClientMap, job: &mut ViWindowJob, w: &mut ViWindow) -> usize {
    if job.gauged {
        let c = split_world_correction(job, w);
        map.world_correction = Some(map.world_correction.map_or(c, |old| c.compose(&old)));
    }
    if job.asked {
        map.session_window_from_ns = None;
    }
    for (c, ((id, kf), refined)) in job
        .kf_ids
        .iter()
        .zip(&w.keyframes)
        .zip(&job.refined)
        .enumerate()
    {
        let Some(m) = map.keyframes.get_mut(id).filter(|_| !kf.fixed) else {
            continue;
        };
        m.t_cw = kf.state.camera_pose(w.rig(c).1);
        m.inertial = Some(KeyframeInertial {
            v_wb: kf.state.v,
            biases: kf.state.biases,
            refined: refined + 1,
        });
    }
    apply_points_and_outliers(map, job, w)
}

/// The write-back shared by a window and the global BA, after the keyframes: the points,
/// then the removal of the observations above the gate (and the refresh of what moved).
/// Returns the observations removed.
fn apply_points_and_outliers(map: &mut ClientMap, job: &mut ViWindowJob, w: &ViWindow) -> usize {
    for (p, p_w) in job.pt_ids.iter().zip(&w.points_w) {
        if let Some(mp) = map.points.get_mut(p) {
            mp.p_w = *p_w;
        }
    }
    job.inliers.clear();
    job.inliers
        .extend(w.observations.iter().map(|o| inlier(w, o)));
    let removed = job.inliers.iter().filter(|i| !**i).count();
    super::local_mapping::remove_outlier_observations(map, &job.obs_keys, &job.inliers);
    super::local_mapping::refresh_adjusted(map, &job.kf_ids, &job.pt_ids);
    removed
}

/// The world correction of a gauged window (module docs, "First windows"): `R`, the mean
/// change of its keyframes' orientations, and `s`, the least-squares scale of their camera
/// centres about the gauged keyframe's, `c`, given `R` (camera centres and points are what
/// a world move scales, [`ClientMap::transform_world`]). The solution is re-expressed by
/// the inverse, `x ↦ c + R⁻¹ (x - c) / s`, in the map's present world, and the similarity
/// about `c`, `x ↦ c + s R (x - c)`, is left for the client to apply to the whole session
/// as a world move (the gauged keyframe stays where it is, and the move does not depend on
/// where the world's origin is: an anchored world, `vio::anchor`, gets the same correction).
/// The scale stays 1 when the keyframes are too close together to tell it.
fn split_world_correction(job: &ViWindowJob, w: &mut ViWindow) -> Sim3 {
    let mut sum = nalgebra::Vector4::zeros();
    for (kf, before) in w.keyframes.iter().zip(&job.r_before) {
        let d = UnitQuaternion::from_rotation_matrix(&kf.state.r) * before.inverse();
        let q = d.into_inner().coords;
        sum += if q.dot(&sum) < 0.0 { -q } else { q };
    }
    let r = UnitQuaternion::from_quaternion(nalgebra::Quaternion::from(sum));
    let centre = |s: &NavState| s.camera_pose(&w.t_bc).inverse().translation.vector;
    let c = job.c_before[0];
    let (mut num, mut den) = (0.0, 0.0);
    for (kf, before) in w.keyframes.iter().zip(&job.c_before) {
        num += (centre(&kf.state) - c).dot(&(r * (before - c)));
        den += (before - c).norm_squared();
    }
    let scale = Some(num / den)
        .filter(|s| den > 1e-4 && (0.5..2.0).contains(s))
        .unwrap_or(1.0);
    let (r_inv, s_inv) = (r.inverse(), 1.0 / scale);
    let back = |p: &Vector3<f64>| c + r_inv * (p - c) * s_inv;
    for kf in &mut w.keyframes {
        let st = &mut kf.state;
        let t_wc = st.camera_pose(&w.t_bc).inverse();
        let t_wc = Isometry3::from_parts(
            Translation3::from(back(&t_wc.translation.vector)),
            r_inv * t_wc.rotation,
        );
        *st = NavState::from_camera(&t_wc.inverse(), &w.t_bc, r_inv * st.v * s_inv, st.biases);
    }
    for p in &mut w.points_w {
        *p = back(p);
    }
    Sim3::new(r, c - r * c * scale, scale)
}

/// Whether an observation is in front of its camera and within the 95 % χ²(2) gate.
fn inlier(w: &ViWindow, o: &ViObservation) -> bool {
    let st = &w.keyframes[o.kf as usize].state;
    let p = &w.points_w[o.point as usize];
    let (camera, t_bc) = w.rig(o.kf as usize);
    reprojection_jacobians(camera, t_bc, st, p, o.dt_s)
        .is_some_and(|(uv, _, _)| ((uv - o.uv) / o.sigma_px).norm_squared() <= CHI2_2DOF_95)
}

mod global;
pub use global::{apply_global_vi, prepare_global_vi};

#[cfg(test)]
#[path = "vi_window_tests.rs"]
mod tests;
