//! Local mapping steps of the client VO (seed §3.3): new map points by triangulation with
//! neighbour keyframes, and culling of recent points that are rarely re-found.
use nalgebra::Vector2;

use super::map::{ClientMap, KfId};
use crate::features::{match_brute_force, MatchParams};
use crate::twoview::triangulate::{
    check_point, projection_matrix, triangulate_dlt, CheckView, TriangulationCheck,
};

/// Triangulates new points between keyframe `k` and up to `n_neighbours` of its best
/// covisible keyframes (or the previous keyframes when it has no covisible ones yet), from
/// descriptor matches of keypoints without a map point, checked by the epipolar constraint,
/// positive depth, reprojection error (χ² 5.991) and parallax. Returns the points created.
pub fn create_points_with_neighbours(map: &mut ClientMap, k: KfId, n_neighbours: usize) -> usize {
    let mut neighbours = map.covisible(k, n_neighbours, 1);
    if neighbours.len() < 2 {
        for id in map.keyframes.keys().rev().copied() {
            if id != k && !neighbours.contains(&id) && neighbours.len() < n_neighbours.min(3) {
                neighbours.push(id);
            }
        }
    }
    let mut created = 0;
    let check = TriangulationCheck::default();
    for n in neighbours {
        let (Some(kf1), Some(kf2)) = (map.keyframes.get(&k), map.keyframes.get(&n)) else {
            continue;
        };
        // Enough baseline for the scene depth.
        let baseline = (kf1.center() - kf2.center()).norm();
        let depth = map.median_depth(n).unwrap_or(1.0);
        if baseline / depth.max(1e-9) < 0.01 {
            continue;
        }
        let free1: Vec<usize> = (0..kf1.points.len())
            .filter(|i| kf1.points[*i].is_none())
            .collect();
        let free2: Vec<usize> = (0..kf2.points.len())
            .filter(|i| kf2.points[*i].is_none())
            .collect();
        let d1: Vec<[u8; 32]> = free1.iter().map(|i| kf1.features.descriptors[*i]).collect();
        let d2: Vec<[u8; 32]> = free2.iter().map(|i| kf2.features.descriptors[*i]).collect();
        let mut matches = Vec::new();
        let mp = MatchParams {
            ratio: 0.6,
            ..MatchParams::default()
        };
        match_brute_force(&d1, &d2, &mp, &mut matches);
        // Relative pose 1 → 2 for the epipolar test in normalised coordinates.
        let t_21 = kf2.t_cw * kf1.t_cw.inverse();
        let r = t_21.rotation.to_rotation_matrix();
        let e = crate::lie::skew(&t_21.translation.vector) * r.matrix();
        let (p1, p2) = (projection_matrix(&kf1.t_cw), projection_matrix(&kf2.t_cw));
        let cam1 = kf1.camera;
        let mut new_points = Vec::new();
        for m in &matches {
            let (i1, i2) = (free1[m.query as usize], free2[m.train as usize]);
            let (k1, k2) = (kf1.features.keypoints[i1], kf2.features.keypoints[i2]);
            let px1 = Vector2::new(k1.x as f64, k1.y as f64);
            let px2 = Vector2::new(k2.x as f64, k2.y as f64);
            let b1 = cam1.unproject(&px1);
            let b2 = kf2.camera.unproject(&px2);
            let x1 = b1 / b1.z;
            let x2 = b2 / b2.z;
            // Distance of x2 to the epipolar line E x1, in pixels (≈ fx × normalised).
            let l = e * x1;
            let dist = x2.dot(&l).abs() / (l.x * l.x + l.y * l.y).sqrt().max(1e-12) * cam1.fx;
            let sigma2 = kf2.features.scale.sigma2(k2.octave);
            if dist * dist > 3.84 * sigma2 {
                continue;
            }
            let Some(p_w) = triangulate_dlt(&p1, &b1, &p2, &b2) else {
                continue;
            };
            let views = [
                CheckView {
                    t_cw: kf1.t_cw,
                    pixel: px1,
                    inv_sigma2: kf1.features.scale.inv_sigma2(k1.octave),
                },
                CheckView {
                    t_cw: kf2.t_cw,
                    pixel: px2,
                    inv_sigma2: kf2.features.scale.inv_sigma2(k2.octave),
                },
            ];
            if check_point(&p_w, &views, &cam1, &check).is_err() {
                continue;
            }
            new_points.push((p_w, i1 as u32, i2 as u32));
        }
        for (p_w, i1, i2) in new_points {
            // Both keypoints may have been taken by an earlier neighbour in this loop.
            let free = map
                .keyframes
                .get(&k)
                .is_some_and(|kf| kf.points[i1 as usize].is_none())
                && map
                    .keyframes
                    .get(&n)
                    .is_some_and(|kf| kf.points[i2 as usize].is_none());
            if free {
                map.add_point(p_w, k, &[(k, i1), (n, i2)]);
                created += 1;
            }
        }
        map.update_covisibility(n);
    }
    map.update_covisibility(k);
    created
}

/// Culls recent points (created in the last keyframes before `current`) that tracking
/// rarely re-finds (found/visible < 0.25) or that, after two more keyframes, are seen by
/// fewer than 2 keyframes (ORB-SLAM's MapPointCulling).
pub fn cull_recent_points(map: &mut ClientMap, current: KfId) {
    let bad: Vec<u64> = map
        .points
        .values()
        .filter(|p| {
            let age = current.saturating_sub(p.first_kf);
            (age >= 1 && p.visible >= 4 && p.found_ratio() < 0.25)
                || (age >= 2 && p.observations.len() < 2)
        })
        .map(|p| p.id)
        .collect();
    for p in bad {
        map.erase_point(p);
    }
}

/// Local bundle adjustment around keyframe `k` (ORB-SLAM's LocalBundleAdjustment): `k` and
/// its covisible keyframes are free (the oldest keyframe of the map stays fixed as the
/// gauge), the keyframes that also see those points are fixed; the local points are free.
/// Outlier observations are removed from the map afterwards. Returns the BA report.
///
/// The three steps are also available apart ([`prepare_local_ba`], the solve, and
/// [`apply_local_ba`]) so that a local-mapping thread can solve without holding the map.
pub fn local_bundle_adjustment(
    map: &mut ClientMap,
    k: KfId,
    ba: &mut crate::optim::ba::BundleAdjuster,
    problem: &mut crate::optim::ba::BaProblem,
    n_neighbours: usize,
) -> Option<crate::optim::ba::BaReport> {
    let job = prepare_local_ba(map, k, problem, n_neighbours)?;
    let report = ba
        .optimize(problem, &crate::optim::ba::BaParams::local())
        .ok()?;
    apply_local_ba(map, &job, problem, ba.inliers());
    Some(report)
}

/// The map elements of a local BA problem built by [`prepare_local_ba`], in problem order.
#[derive(Debug, Clone, Default)]
pub struct LocalBaJob {
    /// Keyframe of each problem keyframe.
    pub kf_ids: Vec<KfId>,
    /// The free (local) keyframes.
    pub local: Vec<KfId>,
    /// Point of each problem point.
    pub pt_ids: Vec<u64>,
    /// `(point, keyframe, keypoint)` of each problem observation.
    pub obs_keys: Vec<(u64, KfId, u32)>,
}

/// Builds the local BA problem around keyframe `k` into `problem` (a snapshot: the map is
/// not needed while it is solved). `None` when there is too little to adjust.
pub fn prepare_local_ba(
    map: &ClientMap,
    k: KfId,
    problem: &mut crate::optim::ba::BaProblem,
    n_neighbours: usize,
) -> Option<LocalBaJob> {
    map.keyframes.get(&k)?;
    let mut local: Vec<KfId> = vec![k];
    local.extend(map.covisible(k, n_neighbours, 1));
    prepare_ba(map, local, problem)
}

/// Global bundle adjustment of a whole map (seed §3.4.2, after a loop correction): every
/// keyframe is free except the oldest (the gauge), every point is free. Outlier
/// observations are removed afterwards. `None` when there is too little to adjust.
pub fn global_bundle_adjustment(
    map: &mut ClientMap,
    ba: &mut crate::optim::ba::BundleAdjuster,
    problem: &mut crate::optim::ba::BaProblem,
) -> Option<crate::optim::ba::BaReport> {
    let job = prepare_global_ba(map, problem)?;
    let report = ba
        .optimize(problem, &crate::optim::ba::BaParams::local())
        .ok()?;
    apply_local_ba(map, &job, problem, ba.inliers());
    Some(report)
}

/// The problem of [`global_bundle_adjustment`] (every keyframe free but the oldest, every
/// point), for a caller that solves it elsewhere (the server's global BA thread).
pub fn prepare_global_ba(
    map: &ClientMap,
    problem: &mut crate::optim::ba::BaProblem,
) -> Option<LocalBaJob> {
    let all: Vec<KfId> = map.keyframes.keys().copied().collect();
    prepare_ba(map, all, problem)
}

/// Builds a BA problem in which the keyframes `local` are free (except the map's oldest
/// keyframe, the gauge), the points they see are free, and the other keyframes that see
/// those points are fixed.
fn prepare_ba(
    map: &ClientMap,
    local: Vec<KfId>,
    problem: &mut crate::optim::ba::BaProblem,
) -> Option<LocalBaJob> {
    use std::collections::HashMap;
    let first = *map.keyframes.keys().next()?;
    let mut kf_index: HashMap<KfId, usize> = HashMap::new();
    let mut pt_index: HashMap<u64, usize> = HashMap::new();
    let mut job = LocalBaJob::default();
    problem.clear();
    for id in &local {
        let kf = map.keyframes.get(id)?;
        kf_index.insert(*id, problem.add_keyframe(kf.t_cw, kf.camera, *id == first));
        job.kf_ids.push(*id);
    }
    for id in &local {
        let kf = &map.keyframes[id];
        for p in kf.points.iter().flatten() {
            if pt_index.contains_key(p) {
                continue;
            }
            if let Some(mp) = map.points.get(p) {
                pt_index.insert(*p, problem.add_point(mp.p_w, false));
                job.pt_ids.push(*p);
            }
        }
    }
    // Fixed keyframes: others that see local points.
    for (pi, p) in job.pt_ids.iter().enumerate() {
        let Some(mp) = map.points.get(p) else {
            continue;
        };
        for (kid, i) in &mp.observations {
            let ki = match kf_index.get(kid) {
                Some(ki) => *ki,
                None => {
                    let kf = map.keyframes.get(kid)?;
                    let ki = problem.add_keyframe(kf.t_cw, kf.camera, true);
                    kf_index.insert(*kid, ki);
                    job.kf_ids.push(*kid);
                    ki
                }
            };
            let kf = &map.keyframes[kid];
            let kp = kf.features.keypoints[*i as usize];
            problem.add_observation(
                ki,
                pi,
                nalgebra::Vector2::new(kp.x as f64, kp.y as f64),
                kf.features.scale.inv_sigma2(kp.octave),
            );
            job.obs_keys.push((*p, *kid, *i));
        }
    }
    if problem.observations.len() < 20 {
        return None;
    }
    job.local = local;
    Some(job)
}

/// Writes a solved local BA back into the map: keyframe poses, point positions, and the
/// removal of outlier observations (`inliers` per observation). Keyframes and points that
/// left the map since [`prepare_local_ba`] (evicted, culled) are skipped, so the map may
/// change while the problem is solved.
pub fn apply_local_ba(
    map: &mut ClientMap,
    job: &LocalBaJob,
    problem: &crate::optim::ba::BaProblem,
    inliers: &[bool],
) {
    for (ki, id) in job.kf_ids.iter().enumerate() {
        if let (Some(kf), Some(pk)) = (map.keyframes.get_mut(id), problem.keyframes.get(ki)) {
            if !pk.fixed {
                kf.t_cw = pk.t_cw;
            }
        }
    }
    for (pi, p) in job.pt_ids.iter().enumerate() {
        if let (Some(mp), Some(pp)) = (map.points.get_mut(p), problem.points.get(pi)) {
            mp.p_w = pp.p_w;
        }
    }
    remove_outlier_observations(map, &job.obs_keys, inliers);
    refresh_adjusted(map, &job.local, &job.pt_ids);
}

/// Removes the observations `obs_keys[j]` = `(point, keyframe, keypoint)` whose
/// `inliers[j]` is false from the map (a point left with fewer than 2 observations is
/// erased); entries no longer in the map are skipped. Shared by the visual local BA and
/// the visual-inertial window ([`super::vi_window`]).
pub(crate) fn remove_outlier_observations(
    map: &mut ClientMap,
    obs_keys: &[(u64, KfId, u32)],
    inliers: &[bool],
) {
    for (j, (p, kid, i)) in obs_keys.iter().enumerate() {
        if inliers.get(j).copied().unwrap_or(true) {
            continue;
        }
        let erase = match map.points.get_mut(p) {
            Some(mp) => {
                mp.observations.retain(|o| *o != (*kid, *i));
                mp.observations.len() < 2
            }
            None => false,
        };
        if let Some(kf) = map.keyframes.get_mut(kid) {
            if kf.points.get(*i as usize).copied().flatten() == Some(*p) {
                kf.points[*i as usize] = None;
            }
        }
        if erase {
            map.erase_point(*p);
        }
    }
}

/// After an adjustment: the covisibility of the keyframes `kfs` and the viewing direction
/// and descriptor of the points `points` (those still in the map).
pub(crate) fn refresh_adjusted(map: &mut ClientMap, kfs: &[KfId], points: &[u64]) {
    for id in kfs {
        if map.keyframes.contains_key(id) {
            map.update_covisibility(*id);
        }
    }
    for p in points {
        if map.points.contains_key(p) {
            map.update_point(*p);
        }
    }
}
