//! Descriptor matching for loop verification (seed §3.4.2): point-to-point matches between
//! two kept keyframes (brute force or grouped by vocabulary node, as ORB-SLAM's
//! `SearchByBoW`), and guided matching of a neighbourhood's points projected by a Sim(3).

use std::collections::HashSet;

use nalgebra::{Isometry3, Point3, Vector3};

use crate::features::{hamming, FeatureGrid};
use crate::lie::Sim3;
use crate::place::{Descriptor, FeatureVector};
use crate::server::KeptKeyframe;
use crate::vo::PointId;

const NONE: u32 = u32::MAX;

/// A putative 3D-3D correspondence between two kept keyframes.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct PointMatch {
    /// Index into the query keyframe's [`KeptKeyframe::points`].
    pub q: u32,
    /// Index into the matched keyframe's [`KeptKeyframe::points`].
    pub m: u32,
    /// Hamming distance of the two keypoints' descriptors.
    pub distance: u32,
}

/// `point index` of every keypoint of `kf` (`NONE` for keypoints without a point). Points
/// whose keypoint index is out of range are ignored.
fn point_of_keypoint(kf: &KeptKeyframe) -> Vec<u32> {
    let mut v = vec![NONE; kf.features.keypoints.len()];
    for (i, p) in kf.points.iter().enumerate() {
        if let Some(slot) = v.get_mut(p.keypoint as usize) {
            *slot = i as u32;
        }
    }
    v
}

/// Descriptor of point `i` of `kf` (`None` when its keypoint index is out of range).
#[inline]
fn point_descriptor(kf: &KeptKeyframe, i: usize) -> Option<&Descriptor> {
    let kp = kf.points.get(i)?.keypoint as usize;
    kf.features.descriptors.get(kp)
}

/// Matches the points of `q` to the points of `m` by descriptor: nearest neighbour at
/// Hamming distance `<= max_distance`, nearest / second-nearest `< ratio`, one match per
/// point of `m` (the closest). With `guides = Some((fv_q, fv_m))` (the keyframes'
/// [`FeatureVector`]s), only features under the same vocabulary node are compared
/// (ORB-SLAM's `SearchByBoW`); with `None`, every pair of points is (a few hundred points
/// each: ~10⁵ distances).
///
/// Seed §3.4.2: the matched 3D points that Umeyama's RANSAC runs on.
pub fn match_kept_points(
    q: &KeptKeyframe,
    m: &KeptKeyframe,
    guides: Option<(&FeatureVector, &FeatureVector)>,
    max_distance: u32,
    ratio: f32,
) -> Vec<PointMatch> {
    // best_for_m[j] = (distance, q point) of the best accepted match of m's point j.
    let mut best_for_m = vec![(NONE, NONE); m.points.len()];
    let mut consider = |iq: usize, cands: &mut dyn Iterator<Item = usize>| {
        let Some(dq) = point_descriptor(q, iq) else {
            return;
        };
        let (mut best, mut best_j, mut second) = (NONE, NONE, NONE);
        for jm in cands {
            let Some(dm) = point_descriptor(m, jm) else {
                continue;
            };
            let d = hamming(dq, dm);
            if d < best {
                second = best;
                best = d;
                best_j = jm as u32;
            } else if d < second {
                second = d;
            }
        }
        if best_j == NONE || best > max_distance {
            return;
        }
        if second != NONE && best as f32 >= ratio * second as f32 {
            return;
        }
        let slot = &mut best_for_m[best_j as usize];
        if best < slot.0 {
            *slot = (best, iq as u32);
        }
    };
    match guides {
        None => {
            for iq in 0..q.points.len() {
                consider(iq, &mut (0..m.points.len()));
            }
        }
        Some((fv_q, fv_m)) => {
            let pq = point_of_keypoint(q);
            let pm = point_of_keypoint(m);
            let lookup = |table: &[u32], f: u32| table.get(f as usize).copied().unwrap_or(NONE);
            fv_q.for_each_common(fv_m, |fq, fm| {
                for &f in fq {
                    let iq = lookup(&pq, f);
                    if iq == NONE {
                        continue;
                    }
                    let mut cands = fm
                        .iter()
                        .map(|&g| lookup(&pm, g))
                        .filter(|&j| j != NONE)
                        .map(|j| j as usize);
                    consider(iq as usize, &mut cands);
                }
            });
        }
    }
    let mut out: Vec<PointMatch> = best_for_m
        .iter()
        .enumerate()
        .filter(|(_, b)| b.1 != NONE)
        .map(|(jm, &(d, iq))| PointMatch {
            q: iq,
            m: jm as u32,
            distance: d,
        })
        .collect();
    // One match per query point too (a query point may win two m points).
    out.sort_unstable_by_key(|pm| (pm.q, pm.distance));
    out.dedup_by_key(|pm| pm.q);
    out
}

/// A server point of the matched keyframe's neighbourhood, expressed in the matched
/// keyframe's camera frame, for guided matching (seed §3.4.2).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct NeighbourhoodPoint {
    /// Server point id.
    pub point: PointId,
    /// The point in the matched keyframe's camera frame.
    pub p_m: Vector3<f64>,
    /// Descriptor of one keypoint observing it.
    pub descriptor: Descriptor,
    /// Pyramid octave of that keypoint (sets the search radius).
    pub octave: u8,
    /// Which keyframe gave it: 0 for the candidate itself, `n` for its `n`-th best
    /// covisible neighbour.
    pub rank: u16,
}

/// The points of `m` and of its `neighbours` (each given with `T_mn`, its camera frame →
/// `m`'s camera frame, e.g. `T_sm⁻¹ T_sn` from the server poses), one entry per server
/// point (the first observation wins, `m`'s own first). Non-finite points are skipped.
pub fn neighbourhood_points<'a>(
    m: &KeptKeyframe,
    neighbours: impl IntoIterator<Item = (&'a KeptKeyframe, Isometry3<f64>)>,
) -> Vec<NeighbourhoodPoint> {
    let mut seen = HashSet::new();
    let mut out = Vec::with_capacity(m.points.len() * 4);
    let mut push = |kf: &KeptKeyframe, t_mn: &Isometry3<f64>, rank: u16| {
        for p in &kf.points {
            let kp = p.keypoint as usize;
            let (Some(k), Some(d)) = (
                kf.features.keypoints.get(kp),
                kf.features.descriptors.get(kp),
            ) else {
                continue;
            };
            let p_m = (t_mn * Point3::from(p.p_k)).coords;
            if !p_m.iter().all(|v| v.is_finite()) || !seen.insert(p.point) {
                continue;
            }
            out.push(NeighbourhoodPoint {
                rank,
                point: p.point,
                p_m,
                descriptor: *d,
                octave: k.octave,
            });
        }
    };
    push(m, &Isometry3::identity(), 0);
    for (i, (n, t_mn)) in neighbours.into_iter().enumerate() {
        push(n, &t_mn, u16::try_from(i + 1).unwrap_or(u16::MAX));
    }
    out
}

/// Descriptor matches of `q`'s points against a candidate's neighbourhood points
/// ([`neighbourhood_points`]) from its first `window` keyframes (the candidate and its
/// best covisible ones), brute force: each query point's nearest neighbourhood point
/// at Hamming distance `<= max_distance` passing the `ratio` test, each neighbourhood point
/// kept by its closest query point. `PointMatch::m` indexes `points`. Matching the whole
/// covisible window instead of the one candidate keyframe (ORB-SLAM3's place recognition)
/// finds the candidate's place even when few of its own keypoints have points: on a
/// revisit by another session the two keyframes' points are different subsets of the scene.
pub fn match_neighbourhood(
    q: &KeptKeyframe,
    points: &[NeighbourhoodPoint],
    window: usize,
    max_distance: u32,
    ratio: f32,
) -> Vec<PointMatch> {
    let mut best_for_m = vec![(NONE, NONE); points.len()];
    for (iq, p) in q.points.iter().enumerate() {
        let Some(dq) = q.features.descriptors.get(p.keypoint as usize) else {
            continue;
        };
        let (mut best, mut best_j, mut second) = (NONE, NONE, NONE);
        let in_window = points
            .iter()
            .enumerate()
            .filter(|(_, np)| usize::from(np.rank) < window);
        for (j, np) in in_window {
            let d = hamming(dq, &np.descriptor);
            if d < best {
                (second, best, best_j) = (best, d, j as u32);
            } else if d < second {
                second = d;
            }
        }
        let unambiguous = second == NONE || (best as f32) < ratio * second as f32;
        if best_j != NONE && best <= max_distance && unambiguous {
            let slot = &mut best_for_m[best_j as usize];
            if best < slot.0 {
                *slot = (best, iq as u32);
            }
        }
    }
    best_for_m
        .iter()
        .enumerate()
        .filter(|(_, b)| b.1 != NONE)
        .map(|(j, &(d, iq))| PointMatch {
            q: iq,
            m: j as u32,
            distance: d,
        })
        .collect()
}

/// One guided match: query keypoint and neighbourhood point index.
#[derive(Debug, Clone, Copy)]
pub(crate) struct GuidedMatch {
    pub q_keypoint: u32,
    pub point: u32,
}

/// Projects every neighbourhood point not in `skip_points` into `q` with `s_qm` and matches
/// it to the closest free query keypoint (`q_taken[k] == false`) within `radius_px ·
/// scale_factor^octave` (the query features' pyramid scale) at Hamming distance
/// `<= max_distance` (ORB-SLAM's loop `SearchByProjection`). Each query keypoint keeps its
/// closest point.
#[allow(clippy::too_many_arguments)]
pub(crate) fn guided_matches(
    q: &KeptKeyframe,
    s_qm: &Sim3,
    points: &[NeighbourhoodPoint],
    skip_points: &HashSet<PointId>,
    q_taken: &[bool],
    radius_px: f32,
    max_distance: u32,
) -> Vec<GuidedMatch> {
    let kps = &q.features.keypoints;
    let (w, h) = (q.camera.width as usize, q.camera.height as usize);
    let Ok(mut grid) = FeatureGrid::new(w.max(1), h.max(1), 32.0) else {
        return Vec::new();
    };
    grid.build(kps);
    // best[k] = (distance, point index) for query keypoint k.
    let mut best = vec![(NONE, NONE); kps.len()];
    for (ip, np) in points.iter().enumerate() {
        if skip_points.contains(&np.point) {
            continue;
        }
        let p_q = s_qm.transform_point(&np.p_m);
        let Some(uv) = q.camera.project(&p_q) else {
            continue;
        };
        if !q.camera.contains(&uv) {
            continue;
        }
        let r = radius_px * q.features.scale.level_scale(np.octave.min(31));
        let (mut bd, mut bk) = (NONE, NONE);
        grid.for_each_in_window(kps, uv.x as f32, uv.y as f32, r, 0, u8::MAX, |k| {
            if q_taken.get(k).copied().unwrap_or(true) {
                return;
            }
            let Some(d) = q.features.descriptors.get(k) else {
                return;
            };
            let dist = hamming(&np.descriptor, d);
            if dist < bd {
                bd = dist;
                bk = k as u32;
            }
        });
        if bk != NONE && bd <= max_distance && bd < best[bk as usize].0 {
            best[bk as usize] = (bd, ip as u32);
        }
    }
    best.iter()
        .enumerate()
        .filter(|(_, b)| b.1 != NONE)
        .map(|(k, &(_, point))| GuidedMatch {
            q_keypoint: k as u32,
            point,
        })
        .collect()
}
