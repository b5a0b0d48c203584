//! Loop and merge candidate detection over all server maps (seed §3.4.2): keyframe
//! database query with the covisibility threshold, ORB-SLAM-style consistency groups over
//! consecutive keyframes of the querying map, then Sim(3) verification.

use std::collections::{HashMap, HashSet};
use std::sync::Arc;

use nalgebra::{Isometry3, Translation3};

use super::matching::{guided_matches, neighbourhood_points, NeighbourhoodPoint};
use super::sim3_ransac::{verify_sim3, Sim3Params, Sim3Reject};
use super::LoopMatch;
use crate::lie::Sim3;
use crate::place::{min_score_among, BowVector, FeatureVector, KeyframeDatabase, Vocabulary};
use crate::server::{KeptKeyframe, MapId};
use crate::vo::KfId;

/// Parameters of [`LoopDetector`] (seed §3.4.2; defaults from ORB-SLAM's loop closing).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LoopDetectorParams {
    /// Consecutive keyframes of a map whose candidates must be consistent (share a
    /// keyframe between their covisibility groups) before a candidate is verified: the
    /// seed's 3. The first keyframe with a candidate counts as 1 (ORB-SLAM's
    /// `mnCovisibilityConsistencyTh = 3` starts at 0, i.e. needs 4 keyframes).
    pub consistency: usize,
    /// Neighbours sharing at least this many points set the score threshold (ORB-SLAM's
    /// covisibility graph edges: 15). All covisible keyframes are excluded from the
    /// candidates whatever their weight. If no neighbour reaches it, all known neighbours
    /// set the threshold.
    pub min_covisibility_weight: u32,
    /// Database results considered per query (best first).
    pub max_candidates: usize,
    /// A candidate is kept when the accumulated score of its covisibility group (its own
    /// score plus those of its best `group_neighbours` neighbours that are candidates too)
    /// reaches this fraction of the best group's (ORB-SLAM: 0.75).
    pub accumulated_score_ratio: f32,
    /// Neighbours of a candidate in its accumulated score (ORB-SLAM: 10).
    pub group_neighbours: usize,
    /// After a loop of a map, this many of its keyframes are not queried (ORB-SLAM: 10):
    /// the correction has yet to reach the map.
    pub min_keyframes_after_loop: usize,
    /// Covisible neighbours of the matched keyframe whose points are projected in guided
    /// matching (best first).
    pub neighbourhood_size: usize,
    /// Vocabulary level of the [`FeatureVector`] nodes (1 = children of the root) that
    /// group descriptor matching; `None` = brute force over the points.
    pub feature_level: Option<usize>,
    /// Geometric verification.
    pub sim3: Sim3Params,
    /// Session continuation: the first keyframes of a map are verified directly against
    /// the newest keyframes of the same client's other maps made at most this long (s)
    /// before them, without the bag-of-words threshold or the consistency test. A VO that
    /// restarted (a killed tracker, a new VO session after tracking loss) usually starts
    /// where the old one stopped; that time adjacency is the prior, the Sim(3) verification
    /// the proof. 0 disables it.
    pub continuation_window_s: f64,
    /// Keyframes of the other map tried per query in session continuation (newest first).
    pub continuation_candidates: usize,
    /// Geometric verification in session continuation: the time prior allows fewer
    /// keyframe-to-keyframe matches to start the Sim(3) (the two keyframes are up to a
    /// second apart), but the final test is the same: `min_inliers` after guided matching
    /// of the old keyframe's neighbourhood.
    pub continuation_sim3: Sim3Params,
    /// Merge candidates (keyframes of another map above the threshold) verified per query
    /// at once, without waiting for [`LoopDetectorParams::consistency`] later keyframes of
    /// the querying map (ORB-SLAM3's place recognition checks the query's covisible
    /// keyframes instead). A server keeps few keyframes of a session that revisits a mapped
    /// place, so consecutive-query consistency may never be reached there. 0 disables it.
    pub merge_candidates: usize,
    /// A verified merge must be confirmed in this many of the query's best covisible
    /// keyframes: the similarity carried to each by the query map's poses, the matched
    /// neighbourhood's points projected and matched there.
    pub merge_confirmations: usize,
    /// Guided matches a query neighbour needs to confirm a merge.
    pub merge_confirm_matches: usize,
    /// Geometric verification of those merges: the query's points matched against the
    /// candidate and its 20 best covisible keyframes with a looser ratio test (0.9), and
    /// the repeated structure test on. A real revisit by another session,
    /// `vamr_checkerboard` frame 522 against frame 9 of the first session (9 mm and 2.3°
    /// apart), gets 7 matches between the two keyframes' own points at 0.75 and 13 by
    /// brute force, too few; against the window it is verified with about 240 inliers after
    /// guided matching (ratio 0.8 and 0.85 each lost it in one of two set-ups: the
    /// board's corners all look alike).
    pub merge_sim3: Sim3Params,
}

impl Default for LoopDetectorParams {
    fn default() -> Self {
        Self {
            consistency: 3,
            min_covisibility_weight: 15,
            max_candidates: 30,
            accumulated_score_ratio: 0.75,
            group_neighbours: 10,
            min_keyframes_after_loop: 10,
            neighbourhood_size: 20,
            feature_level: Some(2),
            sim3: Sim3Params::default(),
            continuation_window_s: 5.0,
            continuation_candidates: 3,
            continuation_sim3: Sim3Params {
                min_matches: 12,
                min_ransac_inliers: 10,
                min_refined_inliers: 10,
                ..Sim3Params::default()
            },
            merge_candidates: 3,
            merge_confirmations: 1,
            merge_confirm_matches: 30,
            merge_sim3: Sim3Params {
                ratio: 0.9,
                window_keyframes: 21,
                rival_ratio: 0.7,
                ..Sim3Params::default()
            },
        }
    }
}

/// What the last [`LoopDetector::add`] query did (for status reports and tests).
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct QueryStats {
    /// The queried keyframe.
    pub query: KfId,
    /// Its map.
    pub map_id: MapId,
    /// Not queried: the map had a loop less than
    /// [`LoopDetectorParams::min_keyframes_after_loop`] keyframes ago.
    pub cooldown: bool,
    /// The seed's threshold (lowest score against the known covisible neighbours);
    /// `None` when no neighbour is known (no query).
    pub min_score: Option<f32>,
    /// Candidates after the accumulated-score filter.
    pub candidates: usize,
    /// Candidates consistent over [`LoopDetectorParams::consistency`] queries.
    pub consistent: usize,
    /// Consistent candidates verified geometrically (stops at the first success).
    pub verified: usize,
    /// Session-continuation candidates verified geometrically.
    pub continuation: usize,
    /// Merge candidates verified at once ([`LoopDetectorParams::merge_candidates`]).
    pub merge_verified: usize,
}

/// What the last query saw, for debugging (`debug_loop`): the database's candidates above
/// the threshold (best first, with their map and score) and each verified candidate's
/// rejection.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct QueryDetail {
    /// Candidates above the threshold: (keyframe, its map, score), best first.
    pub candidates: Vec<(KfId, MapId, f32)>,
    /// Candidates verified without success, and the stage that rejected them.
    pub rejected: Vec<(KfId, Sim3Reject)>,
}

/// A keyframe known to the detector.
#[derive(Debug, Clone)]
struct Stored {
    /// The keyframe; its `t_sk` and `map_id` follow corrections and merges.
    kf: KeptKeyframe,
    bow: BowVector,
    fv: FeatureVector,
    /// Covisible keyframes (symmetric: later keyframes listing this one are added), best
    /// first.
    covis: Vec<(KfId, u32)>,
}

/// A consistency group: a candidate and its covisible keyframes (sorted ids), and the
/// number of consecutive queries it has been consistent over.
#[derive(Debug, Clone)]
struct Group {
    members: Vec<KfId>,
    count: usize,
}

/// Detection state of one querying map.
#[derive(Debug, Clone, Default)]
struct MapState {
    groups: Vec<Group>,
    /// Keyframes added since the map's last loop (`None`: no loop yet).
    since_loop: Option<usize>,
}

/// The loop detector of seed §3.4.2 over the keyframes of all server maps.
///
/// Each [`add`](LoopDetector::add)ed keyframe is queried against the database (candidates
/// from its own map are loops, from other maps merges), then inserted. It keeps the
/// keyframes with a current pose estimate per keyframe: call
/// [`update_pose`](LoopDetector::update_pose), [`set_map`](LoopDetector::set_map) and
/// [`rename_map`](LoopDetector::rename_map) when the mapper corrects or merges maps, and
/// [`remove`](LoopDetector::remove) for culled keyframes.
#[derive(Debug, Clone)]
pub struct LoopDetector {
    vocabulary: Arc<Vocabulary>,
    db: KeyframeDatabase,
    kfs: HashMap<KfId, Stored>,
    maps: HashMap<MapId, MapState>,
    /// Maps renamed by [`LoopDetector::rename_map`]: `from → (into, S_into_from)`. A
    /// keyframe of `from` that arrives later (the mapper made it before it applied the
    /// merge) is moved into `into` first.
    merged: HashMap<MapId, (MapId, Sim3)>,
    params: LoopDetectorParams,
    last: QueryStats,
    detail: QueryDetail,
}

/// Inserts `(id, w)` into a best-first covisibility list (replacing an older weight).
fn upsert_covis(list: &mut Vec<(KfId, u32)>, id: KfId, w: u32) {
    list.retain(|e| e.0 != id);
    let at = list.partition_point(|e| e.1 >= w);
    list.insert(at, (id, w));
}

impl LoopDetector {
    /// An empty detector over `vocabulary`.
    pub fn new(vocabulary: Arc<Vocabulary>, params: LoopDetectorParams) -> Self {
        let db = KeyframeDatabase::new(vocabulary.n_words());
        Self {
            vocabulary,
            db,
            kfs: HashMap::new(),
            maps: HashMap::new(),
            merged: HashMap::new(),
            params,
            last: QueryStats::default(),
            detail: QueryDetail::default(),
        }
    }

    /// What the last [`LoopDetector::add`] query did.
    pub fn last_query(&self) -> &QueryStats {
        &self.last
    }

    /// The candidates and rejections of the last query.
    pub fn last_detail(&self) -> &QueryDetail {
        &self.detail
    }

    /// The parameters.
    pub fn params(&self) -> &LoopDetectorParams {
        &self.params
    }

    /// Number of keyframes stored.
    pub fn len(&self) -> usize {
        self.kfs.len()
    }

    /// Whether no keyframe is stored.
    pub fn is_empty(&self) -> bool {
        self.kfs.is_empty()
    }

    /// The stored keyframe `kf_id` (with its current pose and map).
    pub fn keyframe(&self, kf_id: KfId) -> Option<&KeptKeyframe> {
        self.kfs.get(&kf_id).map(|s| &s.kf)
    }

    /// The covisible keyframes of `kf_id` known to the detector (symmetric), best first.
    pub fn covisible(&self, kf_id: KfId) -> Option<&[(KfId, u32)]> {
        self.kfs.get(&kf_id).map(|s| s.covis.as_slice())
    }

    /// Detects a loop or merge for `kf` (seed §3.4.2), then stores it in the database (in
    /// all cases; a keyframe with a known id replaces the stored one).
    ///
    /// Threshold: the lowest BoW score between `kf` and its covisible neighbours the
    /// detector knows (no known neighbour: no detection). Candidates: database keyframes
    /// at or above it that are neither `kf` nor its neighbours, from any map, filtered by
    /// the accumulated score of their covisibility groups. A candidate whose group has
    /// been consistent over [`LoopDetectorParams::consistency`] consecutive keyframes of
    /// `kf`'s map is verified by [`compute_sim3`], best score first; the first verified
    /// one is returned.
    pub fn add(&mut self, kf: KeptKeyframe) -> Option<LoopMatch> {
        self.store(kf, true)
    }

    /// Stores `kf` without querying the database (a keyframe of a resynchronisation after a
    /// restart: its loops were closed before). A keyframe with a known id replaces the
    /// stored one.
    pub fn insert(&mut self, kf: KeptKeyframe) {
        self.store(kf, false);
    }

    /// [`LoopDetector::insert`] with the keyframe's BoW and feature vectors already made
    /// (a saved map's, with this detector's vocabulary and
    /// [`LoopDetectorParams::feature_level`]).
    pub fn insert_with_vectors(&mut self, kf: KeptKeyframe, bow: BowVector, fv: FeatureVector) {
        self.store_vectors(kf, Some((bow, fv)), false);
    }

    fn store(&mut self, kf: KeptKeyframe, query: bool) -> Option<LoopMatch> {
        self.store_vectors(kf, None, query)
    }

    fn store_vectors(
        &mut self,
        mut kf: KeptKeyframe,
        vectors: Option<(BowVector, FeatureVector)>,
        query: bool,
    ) -> Option<LoopMatch> {
        // A keyframe of a map merged away: into the map it joined (a chain of merges is
        // followed; map ids are never reused, so it ends).
        let mut hops = 0;
        while let Some((into, s)) = self.merged.get(&kf.map_id).copied() {
            move_keyframe(&mut kf, &s, into);
            hops += 1;
            if hops > self.merged.len() {
                break;
            }
        }
        let id = kf.kf_id;
        if self.kfs.contains_key(&id) {
            self.remove(id);
        }
        let (bow, fv) = match (vectors, self.params.feature_level) {
            (Some(v), _) => v,
            (None, Some(level)) => self
                .vocabulary
                .transform_with_features(&kf.features.descriptors, level),
            (None, None) => (
                self.vocabulary.transform(&kf.features.descriptors),
                FeatureVector::default(),
            ),
        };
        let found = if query {
            self.detect(&kf, &bow, &fv)
        } else {
            None
        };
        // Store: symmetric covisibility with the known neighbours.
        let mut covis = Vec::with_capacity(kf.covisible.len());
        for &(n, w) in &kf.covisible {
            if n == id {
                continue;
            }
            if let Some(s) = self.kfs.get_mut(&n) {
                upsert_covis(&mut s.covis, id, w);
            }
            upsert_covis(&mut covis, n, w);
        }
        self.db.add(id, &bow);
        let state = self.maps.entry(kf.map_id).or_default();
        if !query {
            // Resynchronised keyframes do not count towards the cooldown.
        } else if found.is_some() {
            state.groups.clear();
            state.since_loop = Some(0);
        } else if let Some(n) = state.since_loop.as_mut() {
            *n += 1;
        }
        self.kfs.insert(id, Stored { kf, bow, fv, covis });
        found
    }

    /// The detection of [`LoopDetector::add`], before `kf` is stored.
    fn detect(
        &mut self,
        kf: &KeptKeyframe,
        bow: &BowVector,
        fv: &FeatureVector,
    ) -> Option<LoopMatch> {
        let p = self.params;
        self.last = QueryStats {
            query: kf.kf_id,
            map_id: kf.map_id,
            ..QueryStats::default()
        };
        self.detail = QueryDetail::default();
        if self
            .maps
            .entry(kf.map_id)
            .or_default()
            .since_loop
            .is_some_and(|n| n < p.min_keyframes_after_loop)
        {
            self.last.cooldown = true;
            return None;
        }
        if let Some(found) = self.continuation(kf, fv) {
            return Some(found);
        }
        let state = self.maps.entry(kf.map_id).or_default();
        // Neighbours: the keyframe's own covisibility list.
        let mut neighbours: HashSet<KfId> = kf.covisible.iter().map(|e| e.0).collect();
        neighbours.remove(&kf.kf_id);
        let strong = kf
            .covisible
            .iter()
            .filter(|e| e.1 >= p.min_covisibility_weight)
            .filter_map(|e| self.kfs.get(&e.0).map(|s| &s.bow));
        let min_score = min_score_among(bow, strong).or_else(|| {
            min_score_among(
                bow,
                neighbours
                    .iter()
                    .filter_map(|n| self.kfs.get(n).map(|s| &s.bow)),
            )
        });
        let Some(min_score) = min_score else {
            state.groups.clear();
            return None;
        };
        self.last.min_score = Some(min_score);
        let cands = self.db.query(
            bow,
            min_score,
            |c| c == kf.kf_id || neighbours.contains(&c),
            p.max_candidates,
        );
        self.detail.candidates = cands
            .iter()
            .filter_map(|&(c, s)| self.kfs.get(&c).map(|st| (c, st.kf.map_id, s)))
            .collect();
        let cands = self.filter_by_group_score(&cands);
        let enough = self.update_consistency(kf.map_id, &cands);
        self.last.candidates = cands.len();
        self.last.consistent = enough.len();
        let mut considered = 0;
        for &(m_id, _) in &enough {
            considered += 1;
            self.last.verified = considered;
            if let Some(mut found) = self.verify(kf, fv, m_id, &p.sim3) {
                found.candidates_considered = considered;
                return Some(found);
            }
        }
        self.merge(kf, fv, &cands, &enough)
    }

    /// Merge candidates verified at once and confirmed in the query's neighbours (see
    /// [`LoopDetectorParams::merge_candidates`]); the first confirmed one is returned.
    fn merge(
        &mut self,
        kf: &KeptKeyframe,
        fv: &FeatureVector,
        cands: &[(KfId, f32)],
        tried: &[(KfId, f32)],
    ) -> Option<LoopMatch> {
        let p = self.params;
        let other_map: Vec<KfId> = cands
            .iter()
            .filter(|c| !tried.iter().any(|t| t.0 == c.0))
            .filter(|c| self.kfs.get(&c.0).is_some_and(|s| s.kf.map_id != kf.map_id))
            .take(p.merge_candidates)
            .map(|c| c.0)
            .collect();
        for m_id in other_map {
            self.last.merge_verified += 1;
            let Some(mut found) = self.verify(kf, fv, m_id, &p.merge_sim3) else {
                continue;
            };
            let confirmed = self.confirmations(kf, &found);
            if confirmed >= p.merge_confirmations {
                found.candidates_considered = self.last.merge_verified;
                return Some(found);
            }
            self.detail
                .rejected
                .push((m_id, Sim3Reject::Unconfirmed(confirmed)));
        }
        None
    }

    /// How many of `q`'s best covisible keyframes (of its map, known here; at most
    /// [`LoopDetectorParams::merge_confirmations`] + 1 tried) see the matched
    /// neighbourhood where `found`'s similarity, carried by the query map's poses
    /// (`S_nm = T_nq S_qm`), puts it: at least
    /// [`LoopDetectorParams::merge_confirm_matches`] guided descriptor matches.
    fn confirmations(&self, q: &KeptKeyframe, found: &LoopMatch) -> usize {
        let p = self.params;
        let Some(points) = self.neighbourhood(found.matched).map(|n| n.0) else {
            return 0;
        };
        let sim3 = &p.sim3;
        q.covisible
            .iter()
            .filter_map(|(n, _)| self.kfs.get(n))
            .filter(|n| n.kf.map_id == q.map_id && n.kf.kf_id != q.kf_id)
            .take(p.merge_confirmations + 1)
            .filter(|n| {
                let t_nq = n.kf.t_sk.inverse() * q.t_sk;
                let s_nm = Sim3::from_isometry(&t_nq, 1.0).compose(&found.s_qm);
                let taken = vec![false; n.kf.features.keypoints.len()];
                let matches = guided_matches(
                    &n.kf,
                    &s_nm,
                    &points,
                    &HashSet::new(),
                    &taken,
                    sim3.guided_radius_px,
                    sim3.guided_max_distance,
                );
                matches.len() >= p.merge_confirm_matches
            })
            .count()
    }

    /// Session continuation (see [`LoopDetectorParams::continuation_window_s`]): the newest
    /// keyframes of the same client's other maps made shortly before `kf`, verified by
    /// [`compute_sim3`]; the first verified one is returned.
    fn continuation(&mut self, kf: &KeptKeyframe, fv: &FeatureVector) -> Option<LoopMatch> {
        let p = self.params;
        if p.continuation_window_s <= 0.0 || p.continuation_candidates == 0 {
            return None;
        }
        let window_ns = (p.continuation_window_s * 1e9) as i64;
        let client = kf.map_id.client();
        let mut cands: Vec<(i64, KfId)> = self
            .kfs
            .values()
            .filter(|s| s.kf.map_id != kf.map_id && s.kf.map_id.client() == client)
            .filter(|s| (0..=window_ns).contains(&(kf.t_ns - s.kf.t_ns)))
            .map(|s| (s.kf.t_ns, s.kf.kf_id))
            .collect();
        cands.sort_by(|a, b| b.cmp(a));
        for (_, m_id) in cands.into_iter().take(p.continuation_candidates) {
            self.last.continuation += 1;
            if let Some(found) = self.verify(kf, fv, m_id, &p.continuation_sim3) {
                return Some(found);
            }
        }
        None
    }

    /// Keeps the candidates whose covisibility group's accumulated score reaches
    /// `accumulated_score_ratio` of the best group's (ORB-SLAM's `DetectLoopCandidates`).
    fn filter_by_group_score(&self, cands: &[(KfId, f32)]) -> Vec<(KfId, f32)> {
        let score_of: HashMap<KfId, f32> = cands.iter().copied().collect();
        let acc: Vec<f32> = cands
            .iter()
            .map(|&(c, s)| {
                let group = self.kfs.get(&c).map_or(&[][..], |st| st.covis.as_slice());
                s + group
                    .iter()
                    .take(self.params.group_neighbours)
                    .filter_map(|(n, _)| score_of.get(n))
                    .sum::<f32>()
            })
            .collect();
        let best = acc.iter().copied().fold(0.0f32, f32::max);
        cands
            .iter()
            .zip(&acc)
            .filter(|(_, &a)| a >= self.params.accumulated_score_ratio * best)
            .map(|(c, _)| *c)
            .collect()
    }

    /// ORB-SLAM's consistency groups for `map`: each candidate's group (itself and its
    /// covisible keyframes) continues every previous group it shares a keyframe with;
    /// returns the candidates consistent over `consistency` consecutive queries, in the
    /// given (best-first) order.
    fn update_consistency(&mut self, map: MapId, cands: &[(KfId, f32)]) -> Vec<(KfId, f32)> {
        let threshold = self.params.consistency.max(1);
        let prev = self
            .maps
            .get_mut(&map)
            .map(|s| std::mem::take(&mut s.groups))
            .unwrap_or_default();
        let mut continued = vec![false; prev.len()];
        let mut current: Vec<Group> = Vec::new();
        let mut enough = Vec::new();
        for &(c, s) in cands {
            let mut members: Vec<KfId> = self
                .kfs
                .get(&c)
                .map(|st| st.covis.iter().map(|e| e.0).collect())
                .unwrap_or_default();
            members.push(c);
            members.sort_unstable();
            members.dedup();
            let mut consistent_somewhere = false;
            let mut enough_here = false;
            for (g, prev_group) in prev.iter().enumerate() {
                let shares = members
                    .iter()
                    .any(|m| prev_group.members.binary_search(m).is_ok());
                if !shares {
                    continue;
                }
                consistent_somewhere = true;
                let count = prev_group.count + 1;
                if !continued[g] {
                    current.push(Group {
                        members: members.clone(),
                        count,
                    });
                    continued[g] = true;
                }
                if count >= threshold && !enough_here {
                    enough.push((c, s));
                    enough_here = true;
                }
            }
            if !consistent_somewhere {
                if threshold <= 1 {
                    enough.push((c, s));
                }
                current.push(Group { members, count: 1 });
            }
        }
        if let Some(st) = self.maps.get_mut(&map) {
            st.groups = current;
        }
        enough
    }

    /// The points of stored keyframe `m_id` and of its best covisible keyframes of the same
    /// map, in `m_id`'s frame, and the keyframes used (`m_id` first).
    fn neighbourhood(&self, m_id: KfId) -> Option<(Vec<NeighbourhoodPoint>, Vec<KfId>)> {
        let m = self.kfs.get(&m_id)?;
        let t_ms = m.kf.t_sk.inverse();
        let mut used = vec![m_id];
        let neighbours: Vec<(&KeptKeyframe, Isometry3<f64>)> = m
            .covis
            .iter()
            .filter_map(|(n, _)| self.kfs.get(n))
            .filter(|n| n.kf.map_id == m.kf.map_id)
            .take(self.params.neighbourhood_size)
            .map(|n| {
                used.push(n.kf.kf_id);
                (&n.kf, t_ms * n.kf.t_sk)
            })
            .collect();
        Some((neighbourhood_points(&m.kf, neighbours), used))
    }

    /// Geometric verification of candidate `m_id` for `q`, with `m`'s neighbourhood.
    fn verify(
        &mut self,
        q: &KeptKeyframe,
        fv_q: &FeatureVector,
        m_id: KfId,
        sim3: &Sim3Params,
    ) -> Option<LoopMatch> {
        let (points, used) = self.neighbourhood(m_id)?;
        let m = self.kfs.get(&m_id)?;
        let matched_map = m.kf.map_id;
        let guides = self.params.feature_level.map(|_| (fv_q, &m.fv));
        let r = match verify_sim3(q, &m.kf, guides, &points, sim3) {
            Ok(r) => r,
            Err(why) => {
                self.detail.rejected.push((m_id, why));
                return None;
            }
        };
        Some(LoopMatch {
            query: q.kf_id,
            query_map: q.map_id,
            matched: m_id,
            matched_map,
            s_qm: r.s_qm,
            point_pairs: r.point_pairs,
            extra_observations: r.extra_observations,
            inliers: r.inliers,
            candidates_considered: 0,
            matched_neighbourhood: used,
        })
    }

    /// Forgets keyframe `kf_id` (culled by the mapper); returns whether it was stored.
    pub fn remove(&mut self, kf_id: KfId) -> bool {
        let Some(s) = self.kfs.remove(&kf_id) else {
            return false;
        };
        self.db.remove(kf_id);
        for (n, _) in &s.covis {
            if let Some(ns) = self.kfs.get_mut(n) {
                ns.covis.retain(|e| e.0 != kf_id);
            }
        }
        true
    }

    /// Replaces the covisible keyframes of `kf_id` (symmetrically); returns whether it is
    /// stored.
    pub fn update_covisibility(&mut self, kf_id: KfId, covisible: &[(KfId, u32)]) -> bool {
        let Some(old) = self.kfs.get(&kf_id).map(|s| s.covis.clone()) else {
            return false;
        };
        for (n, _) in &old {
            if let Some(ns) = self.kfs.get_mut(n) {
                ns.covis.retain(|e| e.0 != kf_id);
            }
        }
        let mut list = Vec::with_capacity(covisible.len());
        for &(n, w) in covisible {
            if n == kf_id {
                continue;
            }
            if let Some(ns) = self.kfs.get_mut(&n) {
                upsert_covis(&mut ns.covis, kf_id, w);
            }
            upsert_covis(&mut list, n, w);
        }
        if let Some(s) = self.kfs.get_mut(&kf_id) {
            s.covis = list;
        }
        true
    }

    /// Sets the current server pose `T_sk` of `kf_id` (after a correction); returns whether
    /// it is stored.
    pub fn update_pose(&mut self, kf_id: KfId, t_sk: Isometry3<f64>) -> bool {
        match self.kfs.get_mut(&kf_id) {
            Some(s) => {
                s.kf.t_sk = t_sk;
                true
            }
            None => false,
        }
    }

    /// The stored keyframes of map `map_id` (any order).
    pub fn keyframes_of_map(&self, map_id: MapId) -> impl Iterator<Item = &KeptKeyframe> + '_ {
        self.kfs
            .values()
            .map(|s| &s.kf)
            .filter(move |k| k.map_id == map_id)
    }

    /// Moves `kf_id` by a pose-graph correction `Δ` (map → map similarity, seed §3.4.3):
    /// its pose becomes `Δ ∘ T_sk` (rotation `R_Δ R_k`, centre `Δ(c_k)`) and its points in
    /// its own frame are scaled by `s_Δ`. Returns whether it is stored.
    pub fn apply_correction(&mut self, kf_id: KfId, delta: &Sim3) -> bool {
        let ok = delta.s.is_finite() && delta.s > 0.0 && delta.t.iter().all(|v| v.is_finite());
        let Some(st) = self.kfs.get_mut(&kf_id).filter(|_| ok) else {
            return false;
        };
        let kf = &mut st.kf;
        let centre = delta.transform_point(&kf.t_sk.translation.vector);
        kf.t_sk = Isometry3::from_parts(Translation3::from(centre), delta.r * kf.t_sk.rotation);
        for p in &mut kf.points {
            p.p_k *= delta.s;
        }
        true
    }

    /// Moves `kf_id` to map `map_id` (pose unchanged); returns whether it is stored.
    pub fn set_map(&mut self, kf_id: KfId, map_id: MapId) -> bool {
        match self.kfs.get_mut(&kf_id) {
            Some(s) => {
                s.kf.map_id = map_id;
                true
            }
            None => false,
        }
    }

    /// Merges map `from` into map `into` (seed §3.4.2: c's map transformed by `S~` and
    /// merged into m's map): every keyframe of `from` gets map `into` and the pose
    /// `S_into_from ∘ T_sk` (rotation `R_s R_k`, centre `s R_s c_k + t_s`), and its points
    /// in its own frame are scaled by `s` (the camera frame of `into` has `into`'s scale).
    /// The consistency state of `from` is dropped. Returns the number of keyframes moved;
    /// 0 (nothing changed) when `s_into_from` is not a finite similarity with `s > 0`.
    pub fn rename_map(&mut self, from: MapId, into: MapId, s_into_from: &Sim3) -> usize {
        let s = s_into_from;
        let ok = s.s.is_finite()
            && s.s > 0.0
            && s.t.iter().chain(s.r.coords.iter()).all(|v| v.is_finite());
        if !ok || from == into {
            return 0;
        }
        let mut moved = 0;
        for st in self.kfs.values_mut().filter(|st| st.kf.map_id == from) {
            move_keyframe(&mut st.kf, s, into);
            moved += 1;
        }
        self.maps.remove(&from);
        self.merged.insert(from, (into, *s));
        moved
    }
}

/// Moves keyframe `kf` into map `into` by the similarity `s` (into ← its map): its pose, and
/// its points (in its own frame) by the scale.
fn move_keyframe(kf: &mut KeptKeyframe, s: &Sim3, into: MapId) {
    let centre = s.transform_point(&kf.t_sk.translation.vector);
    kf.t_sk = Isometry3::from_parts(Translation3::from(centre), s.r * kf.t_sk.rotation);
    for p in &mut kf.points {
        p.p_k *= s.s;
    }
    kf.map_id = into;
}
