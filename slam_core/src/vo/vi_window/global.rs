//! The global visual-inertial BA of a metric, gravity-aligned map (seed §5.4, Fig. 5.6:
//! after a loop or a merge, "then VI global BA"; `VI_NOTES.md` Table 5.1, "global BA =
//! all"): every keyframe and point of the map in one [`ViWindow`], solved by the window's
//! own [`crate::imu::window::ViSolver`] (no second copy of the factors).
//!
//! **Chains.** Keyframes in id order (on the server, a client's keyframes are consecutive
//! and in time order: the id holds the client above the keyframe number); a keyframe is
//! linked to the one before it when its IMU segment continues that one's
//! ([`super::super::keyframe_imu::KeyframeImu::links`]) and both have an inertial state.
//! Each client's run of linked keyframes is one chain ([`ViWindow::chain_starts`]); a
//! keyframe without segment or state (a monocular client's, merged into the metric map) is a
//! chain of one and moves only its pose: the BA sets its scale from the points it shares
//! with the metric keyframes. Each distinct camera and `t_bc` is one rig.
//!
//! **Gauge.** Position and yaw are unobservable (roll and pitch are seen through gravity):
//! the oldest keyframe of the first chain is fixed, with its IMU factor to the next, as the
//! window fixes its oldest keyframe. Points seen once keep their position (no depth).
//!
//! **Write-back** ([`apply_global_vi`]): the free keyframes' poses (each through its own
//! `t_bc`), the linked ones' velocity and biases, the points, and the removal of the
//! observations above the 95 % χ²(2) gate, as after a window. What entered the map after
//! the problem was built is left to the caller (the server propagates the correction).
use nalgebra::{Isometry3, Vector2};

use super::{apply_points_and_outliers, ViSkip, ViWindowJob};
use crate::imu::window::{ViKeyframe, ViObservation, ViRig, ViWindow};
use crate::imu::{gravity_w, NavState, Preintegrated};
use crate::rolling_shutter::pixel_offset_s;
use crate::vo::map::{ClientMap, KeyframeInertial, KfId};

/// Fewest observations for a global BA.
const MIN_OBSERVATIONS: usize = 20;

/// Builds the global visual-inertial BA of `map` into `w` and `job` (module docs). Errors
/// when no keyframe pair of the map is IMU-linked (a visual map: the visual global BA is
/// the one to run) or too little is observed.
pub fn prepare_global_vi(
    map: &ClientMap,
    w: &mut ViWindow,
    job: &mut ViWindowJob,
) -> Result<(), ViSkip> {
    *w = ViWindow::empty();
    job.kf_ids.clear();
    job.refined.clear();
    global_keyframes(map, w, job);
    let linked = linked_flags(w);
    let gauge = linked.iter().position(|l| *l).ok_or(ViSkip::ShortChain)?;
    w.keyframes[gauge].fixed = true;
    global_points(map, w, job, &linked);
    if w.observations.len() < MIN_OBSERVATIONS {
        return Err(ViSkip::FewObservations);
    }
    job.gauged = false;
    job.asked = false;
    w.gravity_w = gravity_w();
    Ok(())
}

/// Whether each keyframe of `w` has an IMU factor (to the keyframe before or after it).
fn linked_flags(w: &ViWindow) -> Vec<bool> {
    let mut linked = vec![false; w.keyframes.len()];
    let mut starts = w.chain_starts.iter().peekable();
    for k in 1..w.keyframes.len() {
        if starts.next_if(|&&c| c as usize == k).is_none() {
            linked[k - 1] = true;
            linked[k] = true;
        }
    }
    linked
}

/// The keyframes, their rigs, chains and preintegrations (module docs, "Chains").
fn global_keyframes(map: &ClientMap, w: &mut ViWindow, job: &mut ViWindowJob) {
    let mut prev: Option<KfId> = None;
    for (id, kf) in &map.keyframes {
        let t_bc = kf
            .imu
            .as_ref()
            .map_or(Isometry3::identity(), |s| s.calib.t_bc);
        let rig = rig_of(
            w,
            ViRig {
                camera: kf.camera,
                t_bc,
            },
        );
        let i = kf.inertial.unwrap_or_default();
        let state = NavState::from_camera(&kf.t_cw, &t_bc, i.v_wb, i.biases);
        let k = w.keyframes.len();
        w.keyframes.push(ViKeyframe {
            t_ns: kf.imu.as_ref().map_or(kf.t_ns, |s| s.t_ns),
            state,
            fixed: false,
            rig,
        });
        job.kf_ids.push(*id);
        job.refined.push(i.refined);
        let pre = prev.and_then(|p| link(map, p, *id, &w.keyframes[k - 1]));
        match pre {
            Some(pre) => w.preints.push(pre),
            None if k > 0 => w.chain_starts.push(k as u32),
            None => {}
        }
        prev = Some(*id);
    }
}

/// The preintegration from keyframe `a` (window state `sa`) to `b` when `b`'s segment
/// continues `a`'s and both have an inertial state.
fn link(map: &ClientMap, a: KfId, b: KfId, sa: &ViKeyframe) -> Option<Preintegrated> {
    let (ka, kb) = (map.keyframes.get(&a)?, map.keyframes.get(&b)?);
    ka.inertial.zip(kb.inertial)?;
    let (seg_a, seg_b) = (ka.imu.as_ref()?, kb.imu.as_ref()?);
    if !seg_b.links(seg_a) {
        return None;
    }
    Preintegrated::from_window(
        &seg_b.samples,
        sa.t_ns,
        seg_b.t_ns,
        sa.state.biases,
        seg_b.calib.preint,
    )
}

/// Index of `rig` in `w` (0 = the window's own camera and `t_bc`, set by the first
/// keyframe), added when new.
fn rig_of(w: &mut ViWindow, rig: ViRig) -> u16 {
    if w.keyframes.is_empty() {
        w.camera = rig.camera;
        w.t_bc = rig.t_bc;
        return 0;
    }
    if w.camera == rig.camera && w.t_bc == rig.t_bc {
        return 0;
    }
    match w.extra_rigs.iter().position(|r| *r == rig) {
        Some(i) => i as u16 + 1,
        None => {
            w.extra_rigs.push(rig);
            w.extra_rigs.len() as u16
        }
    }
}

/// Every point of the map and its observations in every keyframe (a rolling-shutter row's
/// time only for keyframes with an IMU factor: the others' velocity is unknown).
fn global_points(map: &ClientMap, w: &mut ViWindow, job: &mut ViWindowJob, linked: &[bool]) {
    job.pt_ids.clear();
    job.point_index.clear();
    job.obs_keys.clear();
    w.points_w.clear();
    w.observations.clear();
    for (c, id) in job.kf_ids.iter().enumerate() {
        let kf = &map.keyframes[id];
        for (i, p) in kf.points.iter().enumerate() {
            let Some(mp) = p.and_then(|p| map.points.get(&p)) else {
                continue;
            };
            let pid = p.unwrap_or_default();
            let point = *job.point_index.entry(pid).or_insert_with(|| {
                job.pt_ids.push(pid);
                w.points_w.push(mp.p_w);
                job.pt_ids.len() as u32 - 1
            });
            let kp = kf.features.keypoints[i];
            let uv = Vector2::new(f64::from(kp.x), f64::from(kp.y));
            let dt_s = if linked[c] {
                pixel_offset_s(&kf.camera, kf.readout_ns, &uv)
            } else {
                0.0
            };
            w.observations.push(ViObservation {
                kf: c as u32,
                point,
                uv,
                sigma_px: kf.features.scale.sigma2(kp.octave).sqrt(),
                dt_s,
            });
            job.obs_keys.push((pid, *id, i as u32));
        }
    }
}

/// Writes a solved global BA back into `map` (module docs, "Write-back"); keyframes and
/// points no longer in the map are skipped. Returns the observations removed.
pub fn apply_global_vi(map: &mut ClientMap, job: &mut ViWindowJob, w: &ViWindow) -> usize {
    let linked = linked_flags(w);
    for (c, (id, kf)) in job.kf_ids.iter().zip(&w.keyframes).enumerate() {
        let Some(m) = map.keyframes.get_mut(id).filter(|_| !kf.fixed) else {
            continue;
        };
        m.t_cw = kf.state.camera_pose(w.rig(c).1);
        if let Some(i) = m.inertial.as_mut().filter(|_| linked[c]) {
            *i = KeyframeInertial {
                v_wb: kf.state.v,
                biases: kf.state.biases,
                refined: job.refined[c] + 1,
            };
        }
    }
    apply_points_and_outliers(map, job, w)
}
