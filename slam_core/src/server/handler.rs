//! The keyframe handler of one client (seed §3.4.1): builds the client's server map from its
//! first two keyframes, then predicts (eq. 3.1, 3.4), refines and keeps or discards each
//! next keyframe, tracks the scale ratio (eq. 3.2-3.3), and when idle runs local BA and
//! culls redundant keyframes. A new VO session starts a new server map.
//!
//! Plain data, no threads: the mapper service owns one handler per client and calls
//! [`KeyframeHandler::handle`] per keyframe and [`KeyframeHandler::idle_step`] when its
//! queue is empty. The maps are not inside the handler: they are a [`ServerMaps`] store the
//! caller passes in, so that after a merge (seed §3.4.2) the handlers of several clients
//! continue in one shared map. Everything is deterministic: the same sequence of `handle` and
//! `idle_step` calls on a fresh handler gives the same maps bit for bit (so a mapper can
//! rebuild from a journal; calling `idle_step` once after each `handle` is a schedule that
//! a journal of keyframes alone reproduces).
use std::collections::BTreeMap;

use nalgebra::Isometry3;

use super::correction::{scale_ratio_after_loop, transform_pose};
use super::global_ba::{GlobalBa, GlobalBaApplied};
use super::refine::Refiner;
use super::scale::{measured_scale_ratio, predict_server_pose, smooth_scale_ratio};
use super::server_map::ServerMap;
use super::types::{
    FeedbackPose, HandleReport, KeptKeyframe, KeyframeStatus, MapFrame, MapId, ServerFeedback,
    ServerKeyframe,
};
use crate::ids::{ClientId, KeyframeId, MapPointId};
use crate::imu::window::{ViSolver, ViWindow};
use crate::lie::Sim3;
use crate::optim::ba::{BaProblem, BaReport, BundleAdjuster};
use crate::optim::PoseOptParams;
use crate::vo::keyframe_imu::{join_segments, KeyframeImu};
use crate::vo::kf_culling::{cull_redundant_keyframes, KfCullingParams};
use crate::vo::local_mapping::{
    create_points_with_neighbours, cull_recent_points, local_bundle_adjustment,
};
use crate::vo::vi_window::{
    apply_vi_window, prepare_vi_window, ViMappingMode, ViMappingParams, ViWindowJob,
};
use crate::vo::{KfId, PointId};
use crate::CoreError;

/// The server maps a handler works in, by id (shared by the handlers of merged clients).
pub type ServerMaps = BTreeMap<MapId, ServerMap>;

/// Parameters of the handler; defaults follow the seed where it gives a value.
#[derive(Debug, Clone)]
pub struct HandlerParams {
    /// Scale-ratio smoothing factor α of eq. 3.3 (seed: 0.2).
    pub alpha: f64,
    /// Scale-ratio update factor β after a loop, eq. 3.6 (seed: 0.9).
    pub beta: f64,
    /// Keep a keyframe seeing fewer than this fraction of its reference keyframe's points
    /// (seed: 0.9).
    pub keep_ref_ratio: f64,
    /// Keep a keyframe seeing fewer than this many points (seed: 50).
    pub keep_min_points: usize,
    /// Best covisible keyframes of the reference in the local map.
    pub local_keyframes: usize,
    /// Keyframes near the predicted pose added to the local map (revisits).
    pub spatial_keyframes: usize,
    /// "Near": camera centres within this many median scene depths of the reference.
    pub spatial_radius: f64,
    /// "Near": cosine of the angle between optical axes at least this.
    pub spatial_min_cos: f64,
    /// Window radius (pixels at octave 0) of the first projection search around the
    /// prediction.
    pub search_radius: f32,
    /// Fewer inliers than this: the refinement is not trusted, the pose is the prediction.
    pub min_refine_inliers: usize,
    /// Inliers needed to measure the scale ratio (eq. 3.2).
    pub min_inliers_for_scale: usize,
    /// The scale ratio is measured only when the server translation between the keyframes
    /// is at least this many median scene depths (a ratio of two tiny lengths is noise).
    pub min_translation_for_scale: f64,
    /// Neighbour keyframes for triangulating new points.
    pub triangulation_neighbours: usize,
    /// Covisible keyframes free in local BA.
    pub ba_neighbours: usize,
    /// Redundant keyframe culling.
    pub culling: KfCullingParams,
    /// Pose-only optimisation.
    pub pose_opt: PoseOptParams,
    /// Revisit: a kept keyframe re-observes at least this many points whose other
    /// observers are all older than [`Self::revisit_min_age_s`] (points of a place seen
    /// before, found by the revisit search, not tracked continuously). Such a keyframe ties
    /// the new end of the trajectory to the old one, and a global BA then spreads the drift
    /// accumulated in between over the loop (what the seed gets from a loop correction, here
    /// without one: the prediction was close enough for the revisit search to match).
    /// 0 disables it.
    pub revisit_min_points: usize,
    /// Age (s) of the observers that makes a point "seen before".
    pub revisit_min_age_s: f64,
    /// At most one revisit global BA per this many seconds of data.
    pub revisit_cooldown_s: f64,
    /// Client points not referenced by the last this-many client keyframe ids of their
    /// session are forgotten ([`ServerMap::forget_unseen`]). Must exceed the id span of the
    /// client VO's window (the seed's window is 100 keyframes; culled VO keyframes widen
    /// the span); 0 keeps every association.
    pub assoc_horizon_kfs: u64,
    /// Local BA of a metric, gravity-aligned map (a visual-inertial client's, `VI_NOTES.md`
    /// §4 "Local BA (Fig. 5.5)"): the client's visual-inertial window
    /// ([`crate::vo::vi_window`]) on the server map, its keyframes linked by the IMU
    /// segments the client sent; [`ViMappingMode::Off`] keeps the visual local BA.
    pub vi: ViMappingParams,
}

impl Default for HandlerParams {
    fn default() -> Self {
        Self {
            alpha: 0.2,
            beta: 0.9,
            keep_ref_ratio: 0.9,
            keep_min_points: 50,
            local_keyframes: 10,
            spatial_keyframes: 10,
            spatial_radius: 0.5,
            spatial_min_cos: 0.7,
            search_radius: 15.0,
            min_refine_inliers: 15,
            min_inliers_for_scale: 30,
            min_translation_for_scale: 0.02,
            triangulation_neighbours: 10,
            ba_neighbours: 10,
            culling: KfCullingParams::default(),
            pose_opt: PoseOptParams::default(),
            revisit_min_points: 20,
            revisit_min_age_s: 5.0,
            revisit_cooldown_s: 5.0,
            assoc_horizon_kfs: 300,
            vi: ViMappingParams {
                gauge_first_windows: false,
                // The server keeps about one client keyframe in three: 30 of its keyframes
                // span the time 10 of the client's do (measured on `drone`, issue 19: 4-DoF
                // ATE 0.0277 m with 10, 0.0203 m with 20, 0.0169 m with 30; the client's
                // own keyframes 0.0178 m).
                keyframes: 30,
                ..ViMappingParams::default()
            },
        }
    }
}

/// Counters of a handler.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct HandlerStats {
    /// Keyframes received (duplicates included).
    pub received: u64,
    /// Keyframes inserted in a server map (the two of each map creation included).
    pub kept: u64,
    /// Keyframes refined and discarded.
    pub discarded: u64,
    /// Duplicates ignored.
    pub duplicates: u64,
    /// Keyframes culled as redundant.
    pub culled: u64,
    /// Server maps created.
    pub maps: u64,
    /// Global BAs run because a kept keyframe revisited an old place.
    pub revisit_global_ba: u64,
    /// Global BAs of its current map applied (after a loop, a merge or a revisit).
    pub global_bas: u64,
    /// Visual-inertial local BAs solved (metric, gravity-aligned maps).
    pub vi_windows: u64,
    /// Visual-inertial local BAs that could not be built or failed (the visual one ran).
    pub vi_windows_skipped: u64,
    /// Keyframes discarded when handled and inserted when their session ended (its last).
    pub kept_at_session_end: u64,
    /// Keyframes localised in a frozen map (`--localize-only`: refined, never inserted).
    pub localised: u64,
    /// Times its map relocalised in a frozen map ([`KeyframeHandler::apply_relocalisation`]),
    /// or a session's first keyframe joined a loaded map (`handler_join.rs`).
    pub relocalisations: u64,
    /// Sessions whose first keyframe joined the loaded map it names (`handler_join.rs`).
    pub joined: u64,
}

/// What an idle step did.
#[derive(Debug, Clone)]
pub struct IdleReport {
    /// Local BA report (`None` when the problem was too small or failed).
    pub ba: Option<BaReport>,
    /// Keyframes culled as redundant.
    pub culled: Vec<KfId>,
    /// Global BA (after a loop correction) instead of local BA.
    pub global: bool,
    /// The local BA was the visual-inertial window (a metric, gravity-aligned map).
    pub vi_window: bool,
}

/// The last keyframe handled in the current session (keyframe `j` of eq. 3.1-3.4).
#[derive(Debug, Clone, Copy)]
struct Last {
    client_kf_id: KfId,
    t_ck: Isometry3<f64>,
    t_sk: Isometry3<f64>,
    lambda: f64,
    /// Its server keyframe when it was kept (its pose may since have moved in BA).
    server_kf: Option<KfId>,
    /// A metric keyframe in a metric map: its scale ratio is 1 (λ only a monitor).
    metric: bool,
}

impl Last {
    /// The scale ratio predictions and the client's feedback use (eq. 3.1, 3.4): 1 for a
    /// metric keyframe in a metric map (`VI_NOTES.md` §4 "Server"), else the smoothed λ.
    fn lambda_used(&self) -> f64 {
        if self.metric {
            1.0
        } else {
            self.lambda
        }
    }
}

/// The newest keyframe of the session when it was discarded, kept aside: if the session
/// ends there (a new session starts: the VO restarted, e.g. a killed tracker), it is
/// inserted after all, so that the old map reaches as close as possible to where the new
/// one starts (the loop closer's session continuation matches the two).
#[derive(Debug)]
struct Held {
    kf: ServerKeyframe,
    map: MapId,
    t_sk: Isometry3<f64>,
    frame_points: Vec<Option<PointId>>,
}

/// The server keyframe handler of one client.
#[derive(Debug)]
pub struct KeyframeHandler {
    client_id: u32,
    params: HandlerParams,
    current: Option<MapId>,
    session: Option<u32>,
    first: Option<ServerKeyframe>,
    last: Option<Last>,
    acked: Option<(KfId, u32)>,
    reference: Option<KfId>,
    latest_kept: Option<KfId>,
    converged: bool,
    global_ba: bool,
    /// Time (ns) of the keyframe that triggered the last revisit global BA.
    last_revisit_ba: Option<i64>,
    held: Option<Held>,
    /// Client keyframe id of the last [`ServerMap::forget_unseen`].
    last_forget: KfId,
    /// The IMU since the last keyframe inserted in the map, through the keyframes
    /// discarded since (their segments joined): the next inserted keyframe's segment is
    /// joined to it, so that consecutive server keyframes stay linked by the IMU
    /// (`VI_NOTES.md` §4, Fig. 5.4).
    discarded_imu: Option<KeyframeImu>,
    next_point_id: PointId,
    stats: HandlerStats,
    refiner: Refiner,
    frame_points: Vec<Option<PointId>>,
    ba: BundleAdjuster,
    ba_problem: BaProblem,
    vi_solver: ViSolver,
    vi_window: ViWindow,
    vi_job: ViWindowJob,
}

impl KeyframeHandler {
    /// A handler for client `client_id` (its server point ids start at
    /// [`MapPointId::first_of_client`]).
    pub fn new(client_id: u32, params: HandlerParams) -> Self {
        Self {
            client_id,
            params,
            current: None,
            session: None,
            first: None,
            last: None,
            acked: None,
            reference: None,
            latest_kept: None,
            converged: true,
            global_ba: false,
            last_revisit_ba: None,
            held: None,
            last_forget: 0,
            discarded_imu: None,
            next_point_id: MapPointId::first_of_client(ClientId::new(client_id)).raw(),
            stats: HandlerStats::default(),
            refiner: Refiner::default(),
            frame_points: Vec::new(),
            ba: BundleAdjuster::new(),
            ba_problem: BaProblem::new(),
            vi_solver: ViSolver::new(),
            vi_window: ViWindow::empty(),
            vi_job: ViWindowJob::default(),
        }
    }

    /// Client id.
    pub fn client_id(&self) -> u32 {
        self.client_id
    }

    /// Parameters.
    pub fn params(&self) -> &HandlerParams {
        &self.params
    }

    /// Counters.
    pub fn stats(&self) -> HandlerStats {
        self.stats
    }

    /// Id of the server map of the current session.
    pub fn current_map_id(&self) -> Option<MapId> {
        self.current
    }

    /// The server map of the current session in `maps`.
    pub fn current_map<'a>(&self, maps: &'a ServerMaps) -> Option<&'a ServerMap> {
        self.current.and_then(|m| maps.get(&m))
    }

    /// Current scale ratio `λ` (1 before a map exists).
    pub fn lambda(&self) -> f64 {
        self.last.map_or(1.0, |l| l.lambda)
    }

    /// Whether local BA and culling are done since the last kept keyframe.
    pub fn is_converged(&self) -> bool {
        self.converged
    }

    /// Pose feedback for the client: server pose of its last keyframe and `λ` (seed
    /// §3.4.1), with the acknowledgement of the last keyframe applied.
    pub fn feedback(&self, maps: &ServerMaps) -> Option<ServerFeedback> {
        let (acked_keyframe_id, acked_session_id) = self.acked?;
        let pose = match (self.current, self.last) {
            (Some(map_id), Some(l)) => Some(FeedbackPose {
                map_id,
                t_sk: self.last_server_pose(maps, &l),
                lambda: l.lambda_used(),
                metric: l.metric,
            }),
            _ => None,
        };
        Some(ServerFeedback {
            client_id: self.client_id,
            acked_keyframe_id,
            acked_session_id,
            pose,
        })
    }

    /// Server pose of the last keyframe: from the map when it was kept (BA may have moved
    /// it), else the pose it got when handled.
    fn last_server_pose(&self, maps: &ServerMaps, l: &Last) -> Isometry3<f64> {
        l.server_kf
            .and_then(|k| self.current_map(maps).and_then(|m| m.pose(k)))
            .unwrap_or(l.t_sk)
    }

    /// Handles one keyframe of this client (seed §3.4.1). Invalid input is refused with an
    /// error and leaves the handler unchanged; a keyframe of an older session, or whose id
    /// is not above the last one of its session, is a [`KeyframeStatus::Duplicate`].
    pub fn handle(
        &mut self,
        maps: &mut ServerMaps,
        kf: ServerKeyframe,
    ) -> Result<HandleReport, CoreError> {
        kf.validate()?;
        if kf.client_id != self.client_id {
            return Err(CoreError::InvalidArgument(format!(
                "keyframe of client {} given to the handler of client {}",
                kf.client_id, self.client_id
            )));
        }
        self.stats.received += 1;
        let last_id = self
            .last
            .map(|l| l.client_kf_id)
            .or(self.first.as_ref().map(|f| f.id));
        let duplicate = match self.session {
            Some(s) if kf.session_id < s => true,
            Some(s) if kf.session_id == s => last_id.is_some_and(|l| kf.id <= l),
            _ => false,
        };
        if duplicate {
            self.stats.duplicates += 1;
            return Ok(self.report(kf.id, KeyframeStatus::Duplicate));
        }
        self.acked = Some((kf.id, kf.session_id));
        if self.session != Some(kf.session_id) || self.becomes_inertial(maps, &kf) {
            let report = self.start_over(maps, kf);
            if let Some(joined) = self.join_named_map(maps) {
                return joined.map(|mut r| {
                    r.kept.splice(0..0, report.kept);
                    r
                });
            }
            return Ok(report);
        }
        if self.current.is_none() {
            let Some(first) = self.first.take() else {
                // Unreachable by construction (a session starts with `first`); start over.
                let id = kf.id;
                self.first = Some(kf);
                return Ok(self.report(id, KeyframeStatus::First));
            };
            return Ok(self.create_map(maps, first, kf));
        }
        self.track(maps, kf)
    }

    /// A new session, or the session's world became metric and gravity-aligned (the
    /// client's inertial initialisation) while its server map was built from its earlier,
    /// visual keyframes, which are in another frame and unit: the last keyframe of the old
    /// map joins it if it was discarded, and a new server map starts once there are two
    /// keyframes (the loop closer may merge the two maps with a similarity).
    fn start_over(&mut self, maps: &mut ServerMaps, kf: ServerKeyframe) -> HandleReport {
        let closed = self.insert_held(maps);
        self.discarded_imu = None;
        self.session = Some(kf.session_id);
        self.current = None;
        self.last = None;
        self.reference = None;
        self.latest_kept = None;
        self.converged = true;
        let id = kf.id;
        self.first = Some(kf);
        let mut report = self.report(id, KeyframeStatus::First);
        report.kept.extend(closed);
        report
    }

    /// Whether `kf` is the session's first visual-inertial keyframe after visual ones (the
    /// current map, or the first keyframe waiting for one, is not inertial).
    fn becomes_inertial(&self, maps: &ServerMaps, kf: &ServerKeyframe) -> bool {
        if !kf.is_inertial() {
            return false;
        }
        match (&self.first, self.current_map(maps)) {
            (Some(first), _) => !first.is_inertial(),
            (None, Some(m)) => !m.frame.is_inertial(),
            (None, None) => false,
        }
    }

    fn report(&self, client_kf_id: KfId, status: KeyframeStatus) -> HandleReport {
        HandleReport {
            client_kf_id,
            status,
            map_id: self.current,
            t_sk: None,
            t_sk_predicted: None,
            lambda_measured: None,
            lambda: self.lambda(),
            inliers: 0,
            new_points: 0,
            kept: Vec::new(),
        }
    }

    /// The session's first server map from its first two keyframes: the server frame is
    /// the client map frame at that moment (so `λ = 1`); points from the client's own
    /// correspondences and from descriptor matches (epipolar, depth, reprojection and
    /// parallax checks).
    fn create_map(
        &mut self,
        maps: &mut ServerMaps,
        first: ServerKeyframe,
        second: ServerKeyframe,
    ) -> HandleReport {
        let id = MapId::new(ClientId::new(self.client_id), self.stats.maps as u32);
        self.stats.maps += 1;
        let session = second.session_id;
        let owner = (self.client_id, session);
        // Point ids of this client's range may also have been used by other handlers in a
        // map merged with one of ours: start after every counter of the store.
        let first_point = maps
            .values()
            .map(|m| m.map.next_point_id())
            .filter(|p| {
                MapPointId::from_raw(*p).client()
                    == MapPointId::from_raw(self.next_point_id).client()
            })
            .fold(self.next_point_id, u64::max);
        let frame = if first.is_inertial() && second.is_inertial() {
            MapFrame::INERTIAL
        } else {
            MapFrame::VISUAL
        };
        let mut map = ServerMap::new(id, self.client_id, session, first_point, frame);
        map.touch(owner, first.id, &first.client_points);
        map.touch(owner, second.id, &second.client_points);
        let none1 = vec![None; first.features.len()];
        let none2 = vec![None; second.features.len()];
        let k1 = map.insert(&first, &first.t_ck, &none1);
        let k2 = map.insert(&second, &second.t_ck, &none2);
        let mut created = map.triangulate_client_tracks(owner, k1, &first.client_points);
        created += map.triangulate_client_tracks(owner, k2, &second.client_points);
        created += create_points_with_neighbours(&mut map.map, k2, 1);
        map.map.update_covisibility(k1);
        map.map.update_covisibility(k2);
        self.next_point_id = map.map.next_point_id();
        let kept: Vec<KeptKeyframe> = [(k1, first.id), (k2, second.id)]
            .iter()
            .filter_map(|(k, c)| map.kept_summary(*k, *c))
            .collect();
        maps.insert(id, map);
        self.current = Some(id);
        self.last = Some(Last {
            client_kf_id: second.id,
            t_ck: second.t_ck,
            t_sk: second.t_ck,
            lambda: 1.0,
            server_kf: Some(k2),
            metric: frame.is_inertial(),
        });
        self.reference = Some(k2);
        self.latest_kept = Some(k2);
        self.converged = false;
        self.stats.kept += 2;
        HandleReport {
            client_kf_id: second.id,
            status: KeyframeStatus::MapCreated,
            map_id: Some(id),
            t_sk: Some(second.t_ck),
            t_sk_predicted: None,
            lambda_measured: None,
            lambda: 1.0,
            inliers: 0,
            new_points: created,
            kept,
        }
    }

    /// Next keyframe `k` of a session with a map: predict, refine, measure and smooth the
    /// scale ratio, keep or discard.
    fn track(
        &mut self,
        maps: &mut ServerMaps,
        mut kf: ServerKeyframe,
    ) -> Result<HandleReport, CoreError> {
        if let (Some(d), Some(seg)) = (self.discarded_imu.as_ref(), kf.imu.as_mut()) {
            join_segments(d, seg);
        }
        let (Some(map_id), Some(last)) = (self.current, self.last) else {
            return Err(CoreError::InvalidArgument(
                "no server map to track in".into(),
            ));
        };
        let t_sj = self.last_server_pose(maps, &last);
        let owner = (kf.client_id, kf.session_id);
        let Some(map) = maps.get_mut(&map_id) else {
            return Err(CoreError::InvalidArgument(format!(
                "server map {map_id} missing"
            )));
        };
        map.touch(owner, kf.id, &kf.client_points);
        // Forget client points the VO erased, every quarter horizon (not only in idle steps:
        // once a long run revisits a finished map, keyframes are rarely kept and idle steps
        // rarely run).
        let horizon = self.params.assoc_horizon_kfs;
        if horizon > 0 && kf.id >= self.last_forget.saturating_add(horizon / 4) {
            map.forget_unseen(horizon);
            self.last_forget = kf.id;
        }
        // Eq. 3.1, 3.4; in a metric map the scale ratio of a metric keyframe is 1, the
        // smoothed λ only a monitor (`VI_NOTES.md` §4 "Server").
        let metric = map.frame.is_inertial() && kf.is_inertial();
        let lambda_pred = if metric { 1.0 } else { last.lambda };
        let pred = predict_server_pose(&last.t_ck, &t_sj, lambda_pred, &kf.t_ck);
        let refined = self.refiner.refine(
            map,
            &kf,
            &pred,
            self.reference,
            &self.params,
            &mut self.frame_points,
        )?;
        let t_sk = refined.t_sk;
        // Eq. 3.2-3.3.
        let depth = self
            .reference
            .and_then(|r| map.map.median_depth(r))
            .unwrap_or(1.0);
        let measured = if refined.inliers >= self.params.min_inliers_for_scale {
            let min_client = self.params.min_translation_for_scale * depth / last.lambda.max(1e-9);
            measured_scale_ratio(&t_sj, &t_sk, &last.t_ck, &kf.t_ck, min_client)
        } else {
            None
        };
        let lambda = smooth_scale_ratio(last.lambda, measured, self.params.alpha);
        // The client's point ids now name these server points.
        for (i, s) in self.frame_points.iter().enumerate() {
            if let (Some(s), Some(Some(c))) = (s, kf.client_points.get(i)) {
                map.associate(owner, *c, *s);
            }
        }
        // Reference keyframe: the one sharing most of the matched points.
        let reference = map
            .map
            .keyframe_sharing_most(self.frame_points.iter().flatten());
        let ref_points = reference.map_or(0, |r| {
            let min_obs = if map.map.keyframes.len() <= 2 { 2 } else { 3 };
            map.map.tracked_points(r, min_obs)
        });
        // A frozen map (`--localize-only`) only localises: nothing is inserted.
        let frozen = map.is_frozen();
        let keep = !frozen
            && (refined.inliers < self.params.keep_min_points
                || (refined.inliers as f64) < self.params.keep_ref_ratio * ref_points as f64);
        let mut report = HandleReport {
            client_kf_id: kf.id,
            status: KeyframeStatus::Discarded,
            map_id: Some(map_id),
            t_sk: Some(t_sk),
            t_sk_predicted: Some(pred),
            lambda_measured: measured,
            lambda,
            inliers: refined.inliers,
            new_points: 0,
            kept: Vec::new(),
        };
        let mut server_kf = None;
        if keep {
            self.discarded_imu = None;
            let id = map.insert(&kf, &t_sk, &self.frame_points);
            let mut created = map.triangulate_client_tracks(owner, id, &kf.client_points);
            created += create_points_with_neighbours(
                &mut map.map,
                id,
                self.params.triangulation_neighbours,
            );
            cull_recent_points(&mut map.map, id);
            self.next_point_id = map.map.next_point_id();
            report.status = KeyframeStatus::Kept;
            report.new_points = created;
            report.kept.extend(map.kept_summary(id, kf.id));
            self.reference = Some(id);
            self.latest_kept = Some(id);
            self.converged = false;
            self.stats.kept += 1;
            server_kf = Some(id);
            if self.is_revisit(map, id) {
                self.global_ba = true;
                self.last_revisit_ba = map.map.keyframes.get(&id).map(|k| k.t_ns);
                self.stats.revisit_global_ba += 1;
            }
        } else {
            self.stats.discarded += 1;
            self.stats.localised += u64::from(frozen);
            self.discarded_imu = kf.imu.clone();
            if reference.is_some() {
                self.reference = reference;
            }
        }
        self.last = Some(Last {
            client_kf_id: kf.id,
            t_ck: kf.t_ck,
            t_sk,
            lambda,
            server_kf,
            metric,
        });
        self.held = match server_kf {
            Some(_) => None,
            None if frozen => None,
            None => Some(Held {
                kf,
                map: map_id,
                t_sk,
                frame_points: self.frame_points.clone(),
            }),
        };
        Ok(report)
    }

    /// Inserts the held keyframe (the ended session's last one, discarded when handled) into
    /// its map, as a kept keyframe would have been; returns its summary for loop closing.
    fn insert_held(&mut self, maps: &mut ServerMaps) -> Option<KeptKeyframe> {
        let h = self.held.take()?;
        let map = maps.get_mut(&h.map)?;
        let owner = (h.kf.client_id, h.kf.session_id);
        map.touch(owner, h.kf.id, &h.kf.client_points);
        // Points matched then may have been culled or fused since.
        let points: Vec<Option<PointId>> = h
            .frame_points
            .iter()
            .map(|p| p.filter(|p| map.map.points.contains_key(p)))
            .collect();
        let id = map.insert(&h.kf, &h.t_sk, &points);
        map.triangulate_client_tracks(owner, id, &h.kf.client_points);
        create_points_with_neighbours(&mut map.map, id, self.params.triangulation_neighbours);
        cull_recent_points(&mut map.map, id);
        self.next_point_id = self.next_point_id.max(map.map.next_point_id());
        self.stats.kept += 1;
        self.stats.kept_at_session_end += 1;
        map.kept_summary(id, h.kf.id)
    }

    /// Whether kept keyframe `id` revisits an old place (see
    /// [`HandlerParams::revisit_min_points`]) outside the cooldown of the last revisit BA.
    fn is_revisit(&self, map: &ServerMap, id: KfId) -> bool {
        let p = &self.params;
        let Some(kf) = map.map.keyframes.get(&id) else {
            return false;
        };
        let cooldown_ns = (p.revisit_cooldown_s * 1e9) as i64;
        if p.revisit_min_points == 0
            || self
                .last_revisit_ba
                .is_some_and(|t| kf.t_ns - t < cooldown_ns)
        {
            return false;
        }
        let min_age_ns = (p.revisit_min_age_s * 1e9) as i64;
        let old = |k: &KfId| {
            *k != id
                && map
                    .map
                    .keyframes
                    .get(k)
                    .is_some_and(|o| kf.t_ns - o.t_ns >= min_age_ns)
        };
        let seen_before = kf
            .points
            .iter()
            .flatten()
            .filter_map(|pid| map.map.points.get(pid))
            .filter(|mp| {
                let mut others = mp.observations.iter().map(|(k, _)| k).filter(|k| **k != id);
                let mut any = false;
                others.all(|k| {
                    any = true;
                    old(k)
                }) && any
            })
            .count();
        seen_before >= p.revisit_min_points
    }

    /// One idle step (seed §3.4.1, "when idle and not locally converged"): local BA around
    /// the latest kept keyframe (the tracker's sparse BA), then culling of redundant
    /// keyframes around it. Returns `None` when already converged.
    pub fn idle_step(&mut self, maps: &mut ServerMaps) -> Option<IdleReport> {
        if self.converged {
            return None;
        }
        self.converged = true;
        let k = self.latest_kept?;
        let map = maps.get_mut(&self.current?)?;
        if map.is_frozen() {
            self.global_ba = false;
            return None;
        }
        if std::mem::take(&mut self.global_ba) {
            // Seed §3.4.2: global BA after a loop correction, here the handler's next idle
            // step when nobody took it to run elsewhere ([`Self::take_global_ba`]; the
            // mapper runs it on a thread of its own). Its workspace is its own and freed
            // afterwards: it scales with every observation of the map (≈ 27 MiB at 70
            // keyframes), and kept in the handler it only ever grew (BENCHMARKS.md, "Long
            // run"); the local BA's stays bounded by its window.
            let mut gba = GlobalBa::prepare(map, &self.params.vi)?;
            let vi = gba.is_inertial();
            let applied = gba
                .solve(&self.params.vi.solver)
                .then(|| gba.apply(map))
                .flatten();
            if let Some(a) = &applied {
                self.after_global_ba(a);
            }
            return Some(IdleReport {
                ba: None,
                culled: Vec::new(),
                global: applied.is_some(),
                vi_window: vi,
            });
        }
        let vi_window = map.frame.is_inertial() && self.vi_local_ba(map, k);
        let visual = !vi_window || self.params.vi.mode == ViMappingMode::AfterVisualBa;
        let ba = visual
            .then(|| {
                local_bundle_adjustment(
                    &mut map.map,
                    k,
                    &mut self.ba,
                    &mut self.ba_problem,
                    self.params.ba_neighbours,
                )
            })
            .flatten();
        let mut protected = vec![k];
        protected.extend(self.reference);
        protected.extend(self.last.and_then(|l| l.server_kf));
        let culled = cull_redundant_keyframes(&mut map.map, k, &protected, &self.params.culling);
        self.stats.culled += culled.len() as u64;
        map.prune_associations();
        Some(IdleReport {
            ba,
            culled,
            global: false,
            vi_window,
        })
    }

    /// The visual-inertial local BA of keyframe `k` (`VI_NOTES.md` §4 "Local BA (Fig.
    /// 5.5)"): the client's window ([`prepare_vi_window`]: the last N IMU-linked keyframes
    /// free, the one before them fixed with its IMU factor, older covisible keyframes fixed)
    /// on the server map, the IMU re-integrated from the segments at the current biases.
    /// Returns whether it was solved and written back.
    fn vi_local_ba(&mut self, map: &mut ServerMap, k: KfId) -> bool {
        if self.params.vi.mode == ViMappingMode::Off {
            return false;
        }
        let (w, job) = (&mut self.vi_window, &mut self.vi_job);
        if prepare_vi_window(&map.map, k, &self.params.vi, w, job).is_err() {
            self.stats.vi_windows_skipped += 1;
            return false;
        }
        let solved = self.vi_solver.optimize(w, &self.params.vi.solver).is_ok() && w.is_finite();
        if !solved {
            self.stats.vi_windows_skipped += 1;
            return false;
        }
        apply_vi_window(&mut map.map, job, w);
        self.stats.vi_windows += 1;
        true
    }

    /// Map `from` was merged into map `into` by the similarity `s_into_from`
    /// ([`super::correction::merge_maps`], done by the caller on the store): if this
    /// client's current map was `from`, it continues in `into`; the pose of its last
    /// keyframe follows the map and its scale ratio is updated by eq. 3.6. A global BA is
    /// due at the next idle step. Returns whether this handler was affected.
    /// `global_ba` asks for the global BA (one handler of a map is enough).
    pub fn apply_merge(
        &mut self,
        from: MapId,
        into: MapId,
        s_into_from: &Sim3,
        global_ba: bool,
    ) -> bool {
        if self.current != Some(from) {
            return false;
        }
        self.current = Some(into);
        self.after_correction(s_into_from, global_ba);
        true
    }

    /// Map `from` relocalised in the frozen map `into` (`--localize-only`,
    /// [`super::correction::relocalise_in_frozen`]; `dropped` is `from` moved into `into`'s
    /// frame by `s_into_from`): if this client's current map was `from`, it localises its
    /// keyframes in `into` from now on, starting from the pose of its last keyframe carried
    /// into that frame and from `reference`; its scale ratio follows eq. 3.6. Nothing is
    /// inserted, no BA runs. Returns whether this handler was affected.
    pub fn apply_relocalisation(
        &mut self,
        from: MapId,
        into: MapId,
        s_into_from: &Sim3,
        dropped: &ServerMap,
        reference: Option<KfId>,
    ) -> bool {
        if self.current != Some(from) {
            return false;
        }
        self.current = Some(into);
        self.held = None;
        if let Some(l) = self.last.as_mut() {
            l.t_sk = l
                .server_kf
                .and_then(|k| dropped.pose(k))
                .unwrap_or_else(|| transform_pose(s_into_from, &l.t_sk));
            l.server_kf = None;
            l.lambda = scale_ratio_after_loop(l.lambda, s_into_from.s, self.params.beta);
        }
        self.reference = reference;
        self.latest_kept = None;
        self.converged = true;
        self.global_ba = false;
        self.discarded_imu = None;
        self.stats.relocalisations += 1;
        true
    }

    /// The current map was corrected by a pose graph optimisation (done by the caller with
    /// [`super::correction::apply_pose_corrections`]); `delta_last` is the correction that
    /// moved this client's newest keyframe. The pose of the last keyframe follows it, `λ`
    /// is updated by eq. 3.6 and a global BA is due at the next idle step.
    /// `global_ba` asks for the global BA (one handler of a map is enough).
    pub fn apply_correction(&mut self, map: MapId, delta_last: &Sim3, global_ba: bool) -> bool {
        if self.current != Some(map) {
            return false;
        }
        self.after_correction(delta_last, global_ba);
        true
    }

    /// Newest keyframe of this client handled in its current map: `(client keyframe id,
    /// server keyframe id when it was kept)`.
    pub fn last_keyframe(&self) -> Option<(KfId, Option<KfId>)> {
        self.last.map(|l| (l.client_kf_id, l.server_kf))
    }

    fn after_correction(&mut self, s: &Sim3, global_ba: bool) {
        // A held keyframe's pose and matches are from before the correction.
        self.held = None;
        if let Some(l) = self.last.as_mut() {
            if l.server_kf.is_none() {
                l.t_sk = transform_pose(s, &l.t_sk);
            }
            l.lambda = scale_ratio_after_loop(l.lambda, s.s, self.params.beta);
        }
        if global_ba {
            self.global_ba = true;
            self.converged = false;
        }
    }

    /// Takes a pending global BA request (after a loop, a merge or a revisit) to run it
    /// elsewhere ([`GlobalBa`]); else the next idle step runs it. True when one was pending.
    pub fn take_global_ba(&mut self) -> bool {
        std::mem::take(&mut self.global_ba)
    }

    /// A global BA of the current map was applied: counted, and the pending pose of a last
    /// keyframe that was not kept follows its client's correction.
    pub fn after_global_ba(&mut self, applied: &GlobalBaApplied) {
        self.stats.global_bas += 1;
        if let (Some(l), Some(d)) = (
            self.last.as_mut(),
            applied.client_deltas.get(&self.client_id),
        ) {
            if l.server_kf.is_none() {
                l.t_sk = d * l.t_sk;
            }
        }
        self.held = None;
        self.converged = false;
    }

    /// Server id of client keyframe `kf_id` of this client.
    pub fn server_kf_id(&self, kf_id: KfId) -> KfId {
        KeyframeId::new(ClientId::new(self.client_id), kf_id).raw()
    }
}

#[path = "handler_join.rs"]
mod join;
pub use join::{names_loaded_points, MIN_JOIN_POINTS};

#[cfg(test)]
#[path = "handler_tests.rs"]
mod tests;
