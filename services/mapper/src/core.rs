//! The mapper's core: the main thread's state and decisions without the iceoryx2 ports.
//! Keyframes, corrections, resync requests and the handlers' outcomes go in; the messages to
//! publish (feedback to each client, keyframes to the loop closer) come out as [`Out`], in
//! order, taken by the ports with [`Mapper::take_out`]. The handlers run on their own
//! threads ([`crate::worker`]).
use std::collections::{BTreeMap, HashSet};
use std::path::PathBuf;
use std::time::{Duration, Instant};

use anyhow::Context;
use crossbeam_channel::Receiver;
use shm_schema::time::monotonic_ns;
use shm_schema::{
    CorrectionHeader, CorrectionRecord, Feedback, KeyframeHeader, KeyframeRecord, KeypointRecord,
    LoopKeyframeHeader, LoopKeypointRecord, MsgMeta,
};
use shoal_runtime::journal::{Entry, Journal, OpenError};
use shoal_runtime::wire::{intrinsics_from_camera, wire_from_iso};
use shoal_runtime::{ErrorKind, ReplayMode, Status};
use slam_core::ids::{KeyframeId, MapId};
use slam_core::server::{HandlerParams, KeyframeStatus};

use crate::convert::{self, Correction};
use crate::counters::{MapSummary, MapperCounters, MapperDetails};
use crate::worker::{
    CorrectionKind, CorrectionOutcome, GlobalBaOutcome, Job, MapFigures, MapSize, Outcome, Report,
    Worker,
};
use crate::{lockstep, MapperConfig, Params};

/// A message the mapper publishes.
#[derive(Debug, Clone)]
pub enum Out {
    /// Feedback to the client of `meta.client_id` (acknowledgement, pose, lock-step
    /// "finished").
    Feedback(Feedback),
    /// A kept keyframe (or a resync snapshot's keyframe or end marker) to the loop closer.
    LoopKeyframe(Box<LoopKeyframeHeader>, Vec<LoopKeypointRecord>),
}

type KfKey = (u32, u64);

/// Per-client state of the main thread.
struct Client {
    /// Index of the worker hosting the client's handler (and the maps it created).
    worker: Option<usize>,
    /// Applied (journaled) keyframes: (session, id).
    applied: HashSet<KfKey>,
    /// Messages of applied keyframes waiting for their outcome (to forward kept ones).
    waiting: BTreeMap<KfKey, (KeyframeHeader, Vec<KeypointRecord>)>,
    fb_seq: u64,
    figures: MapFigures,
}

/// The main thread's state apart from the iceoryx2 ports.
pub struct Mapper {
    handler_params: HandlerParams,
    /// Keyframes of all maps for a restarted loop closer (taken on its first request).
    resync: Vec<slam_core::server::KeptKeyframe>,
    clients: Vec<Client>,
    /// The handler threads.
    pub workers: Vec<Worker>,
    /// Latest size of every server map.
    map_sizes: BTreeMap<MapId, MapSize>,
    loop_seq: u64,
    /// The journal of applied keyframes and corrections.
    pub journal: Option<Journal>,
    out_dir: Option<PathBuf>,
    results_tx: crossbeam_channel::Sender<Report>,
    /// Errors and gauges (the counters are put in by [`Mapper::status_now`]).
    pub status: Status,
    /// The counters, carried on from a killed predecessor.
    pub counters: MapperCounters,
    /// Lock-step synchronisation (`None`: free-running).
    sync: Option<lockstep::LockstepSync>,
    /// Lock-step: the handler threads wait for their global BAs and idle on a fixed
    /// schedule (a reproducible run).
    lockstep: bool,
    /// Messages to publish, in order.
    out: Vec<Out>,
    /// The worker hosting the maps of each client of a loaded map file (clients without a
    /// handler, [`map_store::remap`]).
    saved_hosts: BTreeMap<u32, usize>,
    /// `--localize-only`: the loaded maps are frozen.
    pub localize_only: bool,
    /// `--localize-only`: the digest of each frozen map as loaded ([`crate::saved::check_frozen`]).
    pub frozen_digests: BTreeMap<MapId, Option<u32>>,
}

impl Mapper {
    /// A mapper for `params`' clients with configuration `cfg`, resuming `status`; the
    /// handlers report on `results_tx`.
    pub fn new(
        params: &Params,
        cfg: &MapperConfig,
        status: Status,
        results_tx: crossbeam_channel::Sender<Report>,
    ) -> Self {
        let out_dir = params.out.clone().or_else(|| {
            let journal_dir = params.journal.as_ref().and_then(|j| j.parent());
            journal_dir.map(|p| p.to_path_buf())
        });
        let client = || Client {
            worker: None,
            applied: HashSet::new(),
            waiting: BTreeMap::new(),
            fb_seq: 0,
            figures: MapFigures::default(),
        };
        let sync = params.mode == ReplayMode::Lockstep && cfg.lockstep_sync;
        Self {
            counters: status.counters_as(),
            resync: Vec::new(),
            handler_params: HandlerParams {
                spatial_keyframes: cfg.spatial_keyframes,
                revisit_min_points: cfg.revisit_points,
                assoc_horizon_kfs: cfg.assoc_horizon,
                ..HandlerParams::default()
            },
            workers: Vec::new(),
            map_sizes: BTreeMap::new(),
            loop_seq: 0,
            clients: (0..params.clients).map(|_| client()).collect(),
            journal: None,
            out_dir,
            results_tx,
            status,
            sync: sync.then(|| lockstep::LockstepSync::new(lockstep::LOOP_SYNC_TIMEOUT)),
            lockstep: params.mode == ReplayMode::Lockstep,
            out: Vec::new(),
            saved_hosts: BTreeMap::new(),
            localize_only: params.localize_only,
            frozen_digests: BTreeMap::new(),
        }
    }

    /// Hosts the maps of a loaded map file on a worker of their own (before any keyframe
    /// and before the journal's replay, whose corrections may name them): they have no
    /// handler; live clients' maps merge into them through the usual corrections.
    pub fn host_loaded(&mut self, maps: Vec<slam_core::server::ServerMap>) -> anyhow::Result<()> {
        let Some(first) = maps.first() else {
            return Ok(());
        };
        let worker = Worker::spawn(
            first.client_id,
            self.handler_params.clone(),
            self.out_dir.clone(),
            self.results_tx.clone(),
            self.lockstep,
        )
        .context("starting the loaded maps' thread")?;
        self.workers.push(worker);
        let w = self.workers.len() - 1;
        let sizes: Vec<MapSize> = maps.iter().map(crate::worker::map_size).collect();
        for m in &maps {
            self.saved_hosts.insert(m.id.client().raw(), w);
        }
        let maps = maps.into_iter().map(|m| (m.id, m)).collect();
        if !self.workers[w].send(Job::Host { maps }) {
            anyhow::bail!("the loaded maps' thread is gone");
        }
        self.set_map_sizes(&sizes);
        Ok(())
    }

    /// The final maps of every worker (after the drain joined them), by map id.
    pub fn take_final_maps(&mut self) -> slam_core::server::ServerMaps {
        let mut all = slam_core::server::ServerMaps::new();
        for w in &mut self.workers {
            all.extend(w.take_maps());
        }
        all
    }

    /// Opens the journal at `path` and rebuilds the maps from it (before any new keyframe).
    /// A journal of another version (or without a version header) is not replayed: it is an
    /// error in the status, counted in `journals_rejected`, moved to `<path>.rejected`, and
    /// the mapper starts with a new journal.
    pub fn open_journal(&mut self, path: &std::path::Path) -> anyhow::Result<()> {
        let context = || format!("opening the journal {}", path.display());
        let (j, contents) = match Journal::open(path) {
            Err(OpenError::Version(e)) => {
                self.counters.journals_rejected += 1;
                let aside = Journal::set_aside(path).with_context(context)?;
                self.status.error(
                    ErrorKind::Journal,
                    format!("{e}: not replayed, moved to {}", aside.display()),
                );
                Journal::open(path).with_context(context)?
            }
            r => r.with_context(context)?,
        };
        if let Some(p) = contents.problem {
            self.status
                .error(ErrorKind::Journal, format!("{}: {p}", path.display()));
        }
        let n = self.replay(contents.entries)?;
        self.status
            .set_value("journal_keyframes_on_start", n as f64);
        self.journal = Some(j);
        Ok(())
    }

    /// Queues a keyframe for its client's handler, starting the handler on first use: on
    /// the loaded maps' worker when the keyframe names their points (its session may join
    /// a loaded map, `slam_core::server::names_loaded_points`), else on a worker of its own.
    fn queue(&mut self, c: u32, job: Job) -> anyhow::Result<()> {
        let loaded_host = || match &job {
            Job::Keyframe { kf, .. } if slam_core::server::names_loaded_points(kf) => {
                self.saved_hosts.values().next().copied()
            }
            _ => None,
        };
        let w = match self.clients[c as usize].worker.or_else(loaded_host) {
            Some(w) => {
                self.clients[c as usize].worker = Some(w);
                w
            }
            None => {
                self.workers.push(
                    Worker::spawn(
                        c,
                        self.handler_params.clone(),
                        self.out_dir.clone(),
                        self.results_tx.clone(),
                        self.lockstep,
                    )
                    .context("starting a handler thread")?,
                );
                self.counters.handlers_started += 1;
                let w = self.workers.len() - 1;
                self.clients[c as usize].worker = Some(w);
                w
            }
        };
        if !self.workers[w].send(job) {
            anyhow::bail!("the handler thread of client {c} is gone");
        }
        Ok(())
    }

    /// The worker hosting map `m`: the one hosting the client that created it (groups only
    /// ever join, so a map stays with its creator's handler), or for a loaded map the one
    /// hosting it.
    fn host_of(&self, m: MapId) -> Option<usize> {
        match self.clients.get(m.client().index()) {
            Some(c) => c.worker,
            None => self.saved_hosts.get(&m.client().raw()).copied(),
        }
    }

    /// Sends a correction to the worker hosting its map(s); for a merge of maps hosted by
    /// two workers, the `from` worker first hands its whole group over to the `into` one.
    fn dispatch(&mut self, corr: Correction, replay: bool) -> anyhow::Result<()> {
        let (w, from) = match &corr {
            Correction::Merge { from, into, .. } => {
                let (Some(wf), Some(wi)) = (self.host_of(*from), self.host_of(*into)) else {
                    self.counters.corrections_refused += 1;
                    self.status.error(
                        ErrorKind::Correction,
                        format!(
                            "correction {}: merge of map {from:#x} into {into:#x}: a map has no handler",
                            corr.id()
                        ),
                    );
                    return Ok(());
                };
                if wf != wi {
                    let (tx, rx) = crossbeam_channel::bounded(1);
                    if !self.workers[wf].send(Job::HandOver { to: tx })
                        || !self.workers[wi].send(Job::TakeOver { from: rx })
                    {
                        anyhow::bail!("a handler thread is gone");
                    }
                    self.workers[wf].close();
                    for cl in &mut self.clients {
                        if cl.worker == Some(wf) {
                            cl.worker = Some(wi);
                        }
                    }
                    for w in self.saved_hosts.values_mut() {
                        if *w == wf {
                            *w = wi;
                        }
                    }
                    self.counters.handler_groups_joined += 1;
                }
                (wi, Some(*from))
            }
            Correction::PoseGraph { map, .. } => {
                let Some(w) = self.host_of(*map) else {
                    self.counters.corrections_refused += 1;
                    self.status.error(
                        ErrorKind::Correction,
                        format!("correction {}: map {map:#x} has no handler", corr.id()),
                    );
                    return Ok(());
                };
                (w, None)
            }
        };
        if let Some(f) = from {
            self.map_sizes.remove(&f);
        }
        if !self.workers[w].send(Job::Correction {
            correction: corr,
            replay,
        }) {
            anyhow::bail!("a handler thread is gone");
        }
        if let Some(s) = self.sync.as_mut() {
            s.correction_dispatched();
        }
        Ok(())
    }

    /// A correction message from the loop closer: decode, journal, dispatch.
    pub fn receive_correction(
        &mut self,
        h: &CorrectionHeader,
        records: &[CorrectionRecord],
    ) -> anyhow::Result<()> {
        if h.kind == shm_schema::CORRECTION_DONE {
            // Lock-step: the loop closer finished a loop keyframe (not a correction).
            if let Some(s) = self.sync.as_mut() {
                s.loop_done(h.meta.seq);
            }
            return Ok(());
        }
        self.counters.corrections_received += 1;
        let corr = match convert::correction(h, records) {
            Ok(c) => c,
            Err(e) => {
                self.counters.corrections_refused += 1;
                self.status.error(ErrorKind::BadCorrection, e);
                return Ok(());
            }
        };
        if let Some(j) = self.journal.as_mut() {
            j.append(&Entry::Correction {
                header: Box::new(*h),
                records: records.to_vec(),
            })
            .context("writing the journal")?;
        }
        self.dispatch(corr, false)
    }

    /// A resynchronisation request of the loop closer: keyframes `next..next + max` of the
    /// snapshot of all maps (a new snapshot when `next` is 0), then, after the last one,
    /// an end marker.
    pub fn resync(&mut self, req: &shm_schema::ResyncRequest) {
        self.counters.resync_requests += 1;
        if req.next == 0 {
            // A restarted loop closer: what it missed is in the snapshot.
            let next_seq = self.loop_seq;
            if let Some(s) = self.sync.as_mut() {
                s.loop_closer_restarted(next_seq);
            }
            self.resync.clear();
            for w in &self.workers {
                let (tx, rx) = crossbeam_channel::bounded(1);
                if w.send(Job::Snapshot { reply: tx }) {
                    // A worker finishes its queue first; a handed-over one answers nothing.
                    if let Ok(kfs) = rx.recv_timeout(Duration::from_secs(20)) {
                        self.resync.extend(kfs);
                    }
                }
            }
            self.resync.sort_by_key(|k| k.kf_id);
        }
        let from = (req.next as usize).min(self.resync.len());
        let to = (from + req.max as usize).min(self.resync.len());
        for k in &self.resync[from..to] {
            let client = KeyframeId::from_raw(k.kf_id).client().raw();
            let mut meta = MsgMeta::new(client, 0, self.loop_seq, monotonic_ns());
            meta.flags |= shm_schema::FLAG_RESYNC;
            let (intr, w, h) = intrinsics_from_camera(&k.camera);
            let (lh, recs) = convert::loop_keyframe(k, meta, &intr, w, h);
            self.out.push(Out::LoopKeyframe(Box::new(lh), recs));
            self.loop_seq += 1;
            self.counters.resync_keyframes_sent += 1;
        }
        if to == self.resync.len() {
            let mut meta = MsgMeta::new(0, 0, self.loop_seq, monotonic_ns());
            meta.flags |= shm_schema::FLAG_RESYNC | shm_schema::FLAG_END_OF_STREAM;
            let end = LoopKeyframeHeader {
                meta,
                ..LoopKeyframeHeader::default()
            };
            self.out.push(Out::LoopKeyframe(Box::new(end), vec![]));
            self.loop_seq += 1;
        }
    }

    /// A worker applied (or refused) a correction: publish the moved poses, update figures.
    fn correction_outcome(&mut self, o: CorrectionOutcome) {
        if let Some(s) = self.sync.as_mut() {
            s.correction_finished();
        }
        match &o.result {
            Ok(summary) => {
                let n = &mut self.counters;
                match o.kind {
                    CorrectionKind::Merge => n.corrections_applied_merge += 1,
                    CorrectionKind::PoseGraph => n.corrections_applied_pose_graph += 1,
                }
                if o.replay {
                    n.corrections_replayed += 1;
                }
                n.correction_apply_us += (o.apply_ms * 1e3) as u64;
                eprintln!(
                    "mapper: correction {}: {summary} ({:.1} ms)",
                    o.id, o.apply_ms
                );
            }
            Err(e) => {
                self.counters.corrections_refused += 1;
                self.status
                    .error(ErrorKind::Correction, format!("correction {}: {e}", o.id));
            }
        }
        for f in &o.feedback {
            self.send_feedback(f);
        }
        for (c, fig) in &o.figures {
            self.set_figures(*c, *fig);
        }
        if let Some(m) = o.absorbed {
            // Merged away: the `maps` / `keyframes` / `points` gauges count live maps only.
            self.map_sizes.remove(&m);
        }
        self.set_map_sizes(&o.maps);
    }

    /// A global BA's outcome: counted, its feedback published (when it did not run
    /// within a keyframe or correction, whose feedback follows), figures updated.
    fn global_ba_outcome(&mut self, o: GlobalBaOutcome) {
        let n = &mut self.counters;
        let solve_us = (o.solve_ms * 1e3) as u64;
        n.global_ba_us += solve_us;
        n.global_ba_max_us = n.global_ba_max_us.max(solve_us);
        n.global_ba_apply_us += (o.apply_ms * 1e3) as u64;
        match &o.applied {
            Some(a) => {
                n.global_bas += 1;
                n.global_bas_inertial += u64::from(o.inertial);
                n.global_ba_keyframes_propagated += a.keyframes_propagated as u64;
                eprintln!(
                    "mapper: global {} BA of map {:#x}: {} keyframes in {:.0} ms, {} propagated",
                    if o.inertial {
                        "visual-inertial"
                    } else {
                        "visual"
                    },
                    o.map.raw(),
                    o.keyframes,
                    o.solve_ms,
                    a.keyframes_propagated
                );
            }
            None => n.global_bas_dropped += 1,
        }
        for f in &o.feedback {
            self.send_feedback(f);
        }
        for (c, fig) in &o.figures {
            self.set_figures(*c, *fig);
        }
        self.set_map_sizes(&o.maps);
    }

    fn set_map_sizes(&mut self, maps: &[MapSize]) {
        for m in maps {
            self.map_sizes.insert(m.id, m.clone());
        }
        let (n, kfs, pts) = self.map_sizes.values().fold((0, 0, 0), |a, m| {
            (a.0 + 1, a.1 + m.keyframes as u64, a.2 + m.points as u64)
        });
        let c = &mut self.counters;
        (c.maps, c.keyframes, c.points) = (n, kfs, pts);
    }

    /// The live maps as the report lists them (the status file's `details`).
    fn details(&self) -> MapperDetails {
        MapperDetails {
            maps: self
                .map_sizes
                .values()
                .map(|m| MapSummary {
                    id: m.id.raw(),
                    clients: m.clients.clone(),
                    keyframes: m.keyframes as u64,
                    points: m.points as u64,
                    metric: m.frame.metric,
                    gravity_aligned: m.frame.gravity_aligned,
                })
                .collect(),
        }
    }

    fn set_figures(&mut self, c: u32, f: MapFigures) {
        let n = self.counters.clients.of(c);
        n.keyframes_kept = f.stats.kept;
        n.keyframes_discarded = f.stats.discarded;
        n.keyframes_culled = f.stats.culled;
        n.revisit_global_ba = f.stats.revisit_global_ba;
        n.kept_at_session_end = f.stats.kept_at_session_end;
        n.keyframes_localised = f.stats.localised;
        n.relocalisations = f.stats.relocalisations;
        n.sessions_joined = f.stats.joined;
        n.global_bas = f.stats.global_bas;
        n.vi_windows = f.stats.vi_windows;
        n.vi_windows_skipped = f.stats.vi_windows_skipped;
        n.maps = f.stats.maps;
        n.server_keyframes = f.keyframes as u64;
        if let Some(m) = f.map_id {
            n.map_id = Some(m.raw());
        }
        self.status.set_value(&format!("c{c}.lambda"), f.lambda);
        if let Some(cl) = self.clients.get_mut(c as usize) {
            cl.figures = f;
        }
    }

    /// Publishes pose feedback (server pose of the last keyframe, λ, map id) to a client.
    fn send_feedback(&mut self, f: &slam_core::server::ServerFeedback) {
        let Some(pose) = f.pose else {
            return;
        };
        let c = f.client_id;
        let Some(cl) = self.clients.get_mut(c as usize) else {
            return;
        };
        let msg = Feedback {
            meta: feedback_meta(c, f.acked_session_id, cl.fb_seq, Some(&pose)),
            acked_keyframe_id: f.acked_keyframe_id,
            acked_session_id: f.acked_session_id,
            has_pose: 1,
            server_pose: wire_from_iso(&pose.t_sk),
            scale_ratio: pose.lambda,
            server_map_id: pose.map_id.raw(),
        };
        self.out.push(Out::Feedback(msg));
        cl.fb_seq += 1;
        self.counters.clients.of(c).pose_feedback_sent += 1;
    }

    /// Lock-step: tells the trackers which keyframes are finished ([`lockstep`]): a
    /// [`shm_schema::FLAG_HANDLED`] feedback with the pose feedback after the keyframe.
    fn send_finished(&mut self) {
        let Some(sync) = self.sync.as_mut() else {
            return;
        };
        for (k, timed_out) in sync.take_finished(Instant::now()) {
            if timed_out {
                self.counters.lockstep_loop_timeouts += 1;
            }
            let Some(cl) = self.clients.get_mut(k.client as usize) else {
                continue;
            };
            let mut meta = feedback_meta(k.client, k.session, cl.fb_seq, k.pose.as_ref());
            meta.flags |= shm_schema::FLAG_HANDLED;
            let (map_id, t_sk, lambda) = k.pose.map_or(
                (MapId::default(), nalgebra::Isometry3::identity(), 1.0),
                |p| (p.map_id, p.t_sk, p.lambda),
            );
            self.out.push(Out::Feedback(Feedback {
                meta,
                acked_keyframe_id: k.kf_id,
                acked_session_id: k.session,
                has_pose: k.pose.is_some() as u32,
                server_pose: wire_from_iso(&t_sk),
                scale_ratio: lambda,
                server_map_id: map_id.raw(),
            }));
            cl.fb_seq += 1;
            let n = self.counters.clients.of(k.client);
            n.keyframes_finished += 1;
            if k.pose.is_some() {
                n.pose_feedback_sent += 1;
            }
        }
    }

    /// Rebuilds the maps from the journal's entries (before any new keyframe is taken).
    pub fn replay(&mut self, entries: Vec<Entry>) -> anyhow::Result<usize> {
        let idle: HashSet<(u32, u32, u64)> = entries
            .iter()
            .filter_map(|e| match e {
                Entry::Idle {
                    client,
                    session,
                    kf_id,
                } => Some((*client, *session, *kf_id)),
                _ => None,
            })
            .collect();
        let mut n = 0;
        for e in entries {
            let (client, header, records, imu) = match e {
                Entry::Keyframe {
                    client,
                    header,
                    records,
                    imu,
                } => (client, header, records, imu),
                Entry::Correction { header, records } => {
                    match convert::correction(&header, &records) {
                        Ok(c) => self.dispatch(c, true)?,
                        Err(e) => self.status.error(ErrorKind::Journal, e),
                    }
                    continue;
                }
                Entry::Idle { .. } => continue,
                Entry::MapPoints { .. } => {
                    let detail = "map points of a spooled keyframe (a spool file's entry)";
                    self.status.error(ErrorKind::Journal, detail);
                    continue;
                }
            };
            if client as usize >= self.clients.len() {
                self.status.error(
                    ErrorKind::Journal,
                    format!("keyframe of client {client} in the journal, serving fewer"),
                );
                continue;
            }
            let key = (header.meta.session_id, header.keyframe_id);
            // An IMU part refused live is refused again (the keyframe was visual-only then
            // too), already counted: not an error of the replay.
            match convert::server_keyframe(client, &header, &records, Ok(&imu)) {
                Ok(convert::Converted { kf, .. }) => {
                    self.clients[client as usize].applied.insert(key);
                    let job = Job::Keyframe {
                        kf: Box::new(kf),
                        idle: Some(idle.contains(&(client, key.0, key.1))),
                        replay: true,
                    };
                    self.queue(client, job)?;
                    n += 1;
                }
                Err(e) => self.status.error(ErrorKind::Journal, e),
            }
        }
        Ok(n)
    }

    /// Counts a keyframe message of client `c` as received: bytes (header and payload),
    /// IMU segment and samples.
    fn count_received(&mut self, c: u32, h: &KeyframeHeader, payload: &[KeyframeRecord]) {
        let n = self.counters.clients.of(c);
        n.keyframes_received += 1;
        n.keyframe_bytes +=
            (std::mem::size_of::<KeyframeHeader>() + std::mem::size_of_val(payload)) as u64;
        if h.n_imu > 0 {
            n.keyframes_with_imu += 1;
            n.imu_samples_received += u64::from(h.n_imu);
        }
    }

    /// One keyframe message of client `c` (header and payload: keypoints, then the IMU
    /// segment): journal, queue, acknowledge. Keypoints that do not match the header are a
    /// `bad_keyframe` (acknowledged, not applied); an IMU segment that does not hold is a
    /// `bad_imu_segment`, counted, and the keyframe is applied visual-only.
    pub fn receive(
        &mut self,
        c: u32,
        h: &KeyframeHeader,
        payload: &[KeyframeRecord],
    ) -> anyhow::Result<()> {
        self.count_received(c, h, payload);
        let key = (h.meta.session_id, h.keyframe_id);
        if self.clients[c as usize].applied.contains(&key) {
            self.counters.clients.of(c).keyframes_duplicate += 1;
        } else {
            self.apply(c, h, payload)?;
        }
        let cl = &mut self.clients[c as usize];
        let ack = Feedback {
            meta: MsgMeta::new(c, h.meta.session_id, cl.fb_seq, monotonic_ns()),
            acked_keyframe_id: h.keyframe_id,
            acked_session_id: h.meta.session_id,
            has_pose: 0,
            scale_ratio: 1.0,
            ..Feedback::default()
        };
        self.out.push(Out::Feedback(ack));
        cl.fb_seq += 1;
        self.counters.clients.of(c).keyframes_acked += 1;
        Ok(())
    }

    /// Converts, journals and queues a new keyframe message of client `c` (see
    /// [`Self::receive`]).
    fn apply(
        &mut self,
        c: u32,
        h: &KeyframeHeader,
        payload: &[KeyframeRecord],
    ) -> anyhow::Result<()> {
        let imu = h.imu_records(payload).map_err(|e| e.to_string());
        let converted = h
            .keypoints(payload)
            .map_err(|e| format!("keyframe {}: {e}", h.keyframe_id))
            .and_then(|records| {
                Ok((
                    records,
                    convert::server_keyframe(c, h, records, imu.clone())?,
                ))
            });
        let (records, convert::Converted { kf, imu_refused }) = match converted {
            Ok(x) => x,
            Err(e) => {
                // Acknowledged (a re-send would not be better) but not applied.
                let detail = format!("client {c}: {e}");
                self.status.error(ErrorKind::BadKeyframe, detail);
                return Ok(());
            }
        };
        if let Some(e) = imu_refused {
            self.counters.clients.of(c).imu_segments_refused += 1;
            let detail = format!("client {c}: {e}; used visual-only");
            self.status.error(ErrorKind::BadImuSegment, detail);
        }
        if let Some(j) = self.journal.as_mut() {
            j.append(&Entry::Keyframe {
                client: c,
                header: Box::new(*h),
                records: records.to_vec(),
                imu: imu.as_deref().unwrap_or_default().to_vec(),
            })
            .context("writing the journal")?;
        }
        let key = (h.meta.session_id, h.keyframe_id);
        let cl = &mut self.clients[c as usize];
        cl.applied.insert(key);
        cl.waiting.insert(key, (*h, records.to_vec()));
        self.counters.clients.of(c).keyframes_applied += 1;
        // Lock-step: the idle step after every keyframe, whatever the queue (the live
        // default idles when the queue is empty).
        let idle = self.sync.is_some().then_some(true);
        let job = Job::Keyframe {
            kf: Box::new(kf),
            idle,
            replay: false,
        };
        self.queue(c, job)
    }

    /// A handler's outcome: journal the idle step, forward kept keyframes, publish feedback,
    /// update the figures.
    fn outcome(&mut self, o: Outcome) -> anyhow::Result<()> {
        let c = o.client;
        let key = (o.session, o.kf_id);
        if o.idled && !o.replay {
            if let Some(j) = self.journal.as_mut() {
                j.append(&Entry::Idle {
                    client: c,
                    session: o.session,
                    kf_id: o.kf_id,
                })
                .context("writing the journal")?;
            }
        }
        let n = self.counters.clients.of(c);
        let cl = &mut self.clients[c as usize];
        let mut loop_seq = None;
        match &o.result {
            Err(e) => {
                let detail = format!("client {c} keyframe {}: {e}", o.kf_id);
                self.status.error(ErrorKind::Handler, detail);
                cl.waiting.remove(&key);
            }
            Ok(r) => {
                *match r.status {
                    KeyframeStatus::First => &mut n.handled_first,
                    KeyframeStatus::MapCreated => &mut n.handled_map_created,
                    KeyframeStatus::Kept => &mut n.handled_kept,
                    KeyframeStatus::Discarded => &mut n.handled_discarded,
                    KeyframeStatus::Duplicate => &mut n.handled_duplicate,
                } += 1;
                if o.replay {
                    n.keyframes_replayed += 1;
                }
                for k in &r.kept {
                    // Usually of this outcome's session; the previous session's last keyframe
                    // when it was inserted at the session's end (client keyframe ids are
                    // unique per client across sessions and tracker restarts).
                    let wkey = cl
                        .waiting
                        .keys()
                        .rev()
                        .find(|w| w.1 == k.client_kf_id)
                        .copied();
                    if let Some((h, _)) = wkey.and_then(|w| cl.waiting.remove(&w)) {
                        let session = wkey.map_or(o.session, |w| w.0);
                        let meta = MsgMeta::new(c, session, self.loop_seq, monotonic_ns());
                        let (lh, recs) =
                            convert::loop_keyframe(k, meta, &h.intrinsics, h.width, h.height);
                        self.out.push(Out::LoopKeyframe(Box::new(lh), recs));
                        loop_seq = Some(self.loop_seq);
                        self.loop_seq += 1;
                        n.keyframes_forwarded += 1;
                    }
                }
                // The first keyframe of a session waits for the second (map creation); the
                // newest discarded one for the session's end (it may be inserted then).
                let keep = matches!(r.status, KeyframeStatus::First | KeyframeStatus::Discarded);
                cl.waiting.retain(|k, _| *k > key || (keep && *k == key));
            }
        }
        n.handle_us += (o.handle_ms * 1e3) as u64;
        n.idle_us += (o.idle_ms * 1e3) as u64;
        n.handler_queue_max = n.handler_queue_max.max(o.queued as u64);
        n.idle_interval = o.idle_interval as u64;
        n.idle_interval_max = n.idle_interval_max.max(o.idle_interval as u64);
        if let Some(sync) = self.sync.as_mut() {
            // Lock-step: the feedback goes out once the keyframe is finished.
            sync.push(lockstep::Settling {
                client: c,
                session: o.session,
                kf_id: o.kf_id,
                pose: o.feedback.as_ref().and_then(|f| f.pose),
                loop_seq,
                since: Instant::now(),
            });
        } else if let Some(f) = &o.feedback {
            self.send_feedback(f);
        }
        self.set_figures(c, o.figures);
        self.set_map_sizes(&o.maps);
        Ok(())
    }
}

impl Mapper {
    /// Takes the handlers' outcomes waiting on `rx`; returns how many.
    pub fn drain_outcomes(&mut self, rx: &Receiver<Report>) -> anyhow::Result<usize> {
        let mut n = 0;
        while let Ok(r) = rx.try_recv() {
            match r {
                Report::Keyframe(o) => self.outcome(*o)?,
                Report::Correction(o) => self.correction_outcome(*o),
                Report::GlobalBa(o) => self.global_ba_outcome(*o),
            }
            n += 1;
        }
        self.send_finished();
        Ok(n)
    }

    /// The status as of now (the counters put in), to write.
    pub fn status_now(&mut self) -> &Status {
        self.status.put_counters(&self.counters);
        self.status.set_details(&self.details());
        &self.status
    }

    /// The messages to publish, in order (taken).
    pub fn take_out(&mut self) -> std::vec::Drain<'_, Out> {
        self.out.drain(..)
    }
}

/// The meta of a feedback message to client `c`: [`shm_schema::FLAG_INERTIAL_MAP`] when its
/// pose is of a metric keyframe in a metric, gravity-aligned map (the client may anchor to
/// it, `slam_core::vio::anchor`).
fn feedback_meta(
    c: u32,
    session: u32,
    seq: u64,
    pose: Option<&slam_core::server::FeedbackPose>,
) -> MsgMeta {
    let mut meta = MsgMeta::new(c, session, seq, monotonic_ns());
    if pose.is_some_and(|p| p.metric) {
        meta.flags |= shm_schema::FLAG_INERTIAL_MAP;
    }
    meta
}

#[cfg(test)]
mod tests {
    use clap::Parser;

    use super::*;

    /// A journal without the version header (as an older binary wrote it) is not replayed:
    /// the mapper records and counts the error, moves the file aside and starts a new
    /// journal, which it then replays like any other.
    #[test]
    fn a_journal_of_another_version_is_set_aside_and_counted() {
        let dir = std::env::temp_dir().join(format!("shoal_mapper_journal_{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        std::fs::create_dir_all(&dir).expect("dir");
        let path = dir.join("mapper_journal.bin");
        let old = shoal_runtime::journal::encode_entry(&Entry::Idle {
            client: 0,
            session: 1,
            kf_id: 3,
        });
        std::fs::write(&path, &old).expect("write");
        let params = crate::Params::parse_from(["mapper", "--clients", "1"]);
        let (tx, _rx) = crossbeam_channel::unbounded();
        let cfg = params.config().expect("default configuration");
        let mut m = Mapper::new(&params, &cfg, Status::new("mapper"), tx);
        m.open_journal(&path).expect("starts fresh");
        assert_eq!(m.counters.journals_rejected, 1);
        assert_eq!(m.status.errors_of(ErrorKind::Journal), 1);
        let detail = &m.status.errors[0].detail;
        assert!(detail.contains("no journal header"), "{detail}");
        assert!(detail.contains(&path.display().to_string()), "{detail}");
        assert_eq!(
            std::fs::read(dir.join("mapper_journal.bin.rejected")).expect("set aside"),
            old
        );
        drop(m);
        // The new journal is of this version: a second start replays it without an error.
        let (tx, _rx) = crossbeam_channel::unbounded();
        let mut m = Mapper::new(&params, &cfg, Status::new("mapper"), tx);
        m.open_journal(&path).expect("reopen");
        assert_eq!(m.counters.journals_rejected, 0);
        assert!(m.status.errors.is_empty(), "{:?}", m.status.errors);
        let _ = std::fs::remove_dir_all(&dir);
    }

    /// A message of client 0 at `t_s` seconds: one keypoint, then (when `imu` is given) a
    /// visual-inertial client's segment of those records.
    fn message(
        id: u64,
        t_s: i64,
        imu: Option<Vec<shm_schema::ImuRecord>>,
    ) -> (KeyframeHeader, Vec<KeyframeRecord>) {
        let mut h = KeyframeHeader {
            meta: MsgMeta::new(0, 1, id, 0),
            keyframe_id: id,
            t_ns: t_s * 1_000_000_000,
            width: 640,
            height: 480,
            n_keypoints: 1,
            ..KeyframeHeader::default()
        };
        h.intrinsics.pinhole = [400.0, 400.0, 320.0, 240.0];
        let mut payload = vec![KeyframeRecord::from(KeypointRecord::default())];
        if let Some(imu) = imu {
            h.has_imu = 1;
            h.imu_t1_ns = h.t_ns;
            h.n_imu = imu.len() as u32;
            h.imu_t0_ns = imu.first().map_or(0, |r| r.t_ns);
            payload.extend(imu.into_iter().map(KeyframeRecord::from));
        }
        (h, payload)
    }

    /// IMU records every 0.5 s from `t0_s` to `t1_s`.
    fn segment(t0_s: i64, t1_s: i64) -> Vec<shm_schema::ImuRecord> {
        (2 * t0_s..=2 * t1_s)
            .map(|k| shm_schema::ImuRecord {
                t_ns: k * 500_000_000,
                ..Default::default()
            })
            .collect()
    }

    /// Issue 19: keyframes with good and malformed IMU segments are all applied (journaled,
    /// acknowledged); a malformed segment (times out of order, a NaN, more records declared
    /// than the slice holds) is a counted `bad_imu_segment` and the keyframe goes on
    /// visual-only. The journal keeps each message with its segment as received, and a
    /// restarted mapper replays all of them without an error.
    #[test]
    fn malformed_segments_are_counted_and_the_keyframes_applied() {
        let dir = std::env::temp_dir().join(format!("shoal_mapper_imu_{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        std::fs::create_dir_all(&dir).expect("dir");
        let path = dir.join("mapper_journal.bin");
        let params = crate::Params::parse_from(["mapper", "--clients", "1"]);
        let cfg = params.config().expect("default configuration");
        let (tx, _rx) = crossbeam_channel::unbounded();
        let mut m = Mapper::new(&params, &cfg, Status::new("mapper"), tx);
        m.open_journal(&path).expect("journal");
        let mut unordered = segment(2, 3);
        unordered.swap(0, 1);
        let mut nan = segment(3, 4);
        nan[1].accel[0] = f64::NAN;
        let (h_short, mut short) = message(5, 5, Some(segment(4, 5)));
        short.pop();
        let msgs = [
            message(1, 1, Some(Vec::new())),
            message(2, 2, Some(segment(1, 2))),
            message(3, 3, Some(unordered)),
            message(4, 4, Some(nan)),
            (h_short, short),
            message(6, 6, None),
        ];
        for (h, payload) in &msgs {
            m.receive(0, h, payload).expect("received");
        }
        let n = m.counters.client(0);
        assert_eq!(n.keyframes_applied, 6);
        assert_eq!(n.keyframes_acked, 6);
        assert_eq!(n.keyframes_with_imu, 4, "messages with records");
        assert_eq!(n.imu_samples_received, 3 + 3 + 3 + 3);
        assert_eq!(n.imu_segments_refused, 3);
        assert_eq!(m.status.errors_of(ErrorKind::BadImuSegment), 3);
        assert_eq!(m.status.errors_of(ErrorKind::BadKeyframe), 0);
        let bytes = 6 * std::mem::size_of::<KeyframeHeader>() + (6 + 3 + 3 + 3 + 2) * 64;
        assert_eq!(n.keyframe_bytes, bytes as u64);
        drop(m);
        let j = shoal_runtime::journal::read_journal(&path).expect("journal");
        let imu_lens: Vec<usize> = j
            .entries
            .iter()
            .filter_map(|e| match e {
                Entry::Keyframe { imu, .. } => Some(imu.len()),
                _ => None,
            })
            .collect();
        assert_eq!(imu_lens, vec![0, 3, 3, 3, 0, 0]);
        let (tx, _rx) = crossbeam_channel::unbounded();
        let mut m = Mapper::new(&params, &cfg, Status::new("mapper"), tx);
        m.open_journal(&path).expect("replay");
        assert!(m.status.errors.is_empty(), "{:?}", m.status.errors);
        assert_eq!(
            m.status.values.get("journal_keyframes_on_start"),
            Some(&6.0)
        );
        let _ = std::fs::remove_dir_all(&dir);
    }
}
