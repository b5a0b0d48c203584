//! Mapper service: owns the server maps of all clients (seed §3.4.1).
//!
//! The main thread takes every client's keyframe messages from shared memory, checks their
//! schema version, converts them ([`convert`]), journals them whole ([`shoal_runtime::journal`]) and only
//! then acknowledges them on the client's feedback service (the tracker keeps a keyframe
//! until it is acknowledged). Duplicates (re-sends) are acknowledged again but not re-applied.
//! Each client has its own [`slam_core::server::KeyframeHandler`] on its own thread
//! ([`worker`]), created when its first keyframe arrives. For every handled keyframe the
//! main thread publishes pose feedback (server pose of the keyframe, scale ratio, server map
//! id) and forwards the keyframes the handler kept to the loop closer (with their points in
//! their own frame and their covisible neighbours).
//!
//! Corrections from the loop closer (seed §3.4.2-3.4.3: map merges, pose-graph corrections)
//! are journaled and then applied by the worker hosting the map; a merge of maps hosted by
//! two workers first hands one worker's group over to the other, so merged clients share
//! one map. The mapper owns the maps; the loop closer only computes.
//!
//! A restarted mapper replays its journal through fresh handlers before it takes new
//! keyframes, following the journaled idle-step schedule, so it rebuilds the same maps.
//! Outputs: `OUT/keyframes_server_c{i}.txt` (and `keyframes_client_c{i}.txt`), written
//! periodically and at the end; figures in the status file (`maps`, `keyframes`, `points`,
//! per client `c{i}.keyframes_received`, `c{i}.keyframes_kept`, ...).
#![deny(missing_docs)]

pub mod convert;
pub mod lockstep;
pub mod worker;

use std::collections::{BTreeMap, HashSet};
use std::path::PathBuf;
use std::time::{Duration, Instant};

use anyhow::Context;
use crossbeam_channel::Receiver;
use iceoryx2::port::publisher::Publisher;
use shm_schema::time::monotonic_ns;
use shm_schema::topics::{self, Ipc};
use shm_schema::{
    CorrectionHeader, CorrectionRecord, Feedback, KeyframeHeader, KeypointRecord,
    LoopKeyframeHeader, LoopKeypointRecord, MsgMeta,
};
use shoal_runtime::{ReplayMode, Status, StatusFile};
use slam_core::server::{HandlerParams, KeyframeStatus, MapId};

use convert::Correction;
use shoal_runtime::journal::{Entry, Journal};
use worker::{CorrectionOutcome, Job, MapFigures, MapSize, Outcome, Report, Worker};

type LoopPublisher = Publisher<Ipc, [LoopKeypointRecord], LoopKeyframeHeader>;

/// Parameters of the mapper service.
#[derive(Debug, Clone, clap::Parser)]
#[command(name = "mapper", about = "Server mapper service")]
pub struct Params {
    /// Number of clients (client indices 0..N).
    #[arg(long, default_value_t = 1)]
    pub clients: u32,
    /// Status file (JSON).
    #[arg(long)]
    pub status: Option<PathBuf>,
    /// Append-only journal of applied keyframes (replayed on start).
    #[arg(long)]
    pub journal: Option<PathBuf>,
    /// Output folder for the server keyframe trajectories (default: the journal's folder).
    #[arg(long)]
    pub out: Option<PathBuf>,
    /// iceoryx2 resource prefix (default: $SHOAL_IPC_PREFIX or "shoal_").
    #[arg(long)]
    pub ipc_prefix: Option<String>,
    /// Keyframes near the predicted pose searched for a revisit (0: none, so that a revisit
    /// is left to loop closing; for ablations).
    #[arg(long, default_value_t = HandlerParams::default().spatial_keyframes)]
    pub spatial_keyframes: usize,
    /// Global BA when a kept keyframe re-observes at least this many points of a place
    /// seen more than 5 s before (a revisit; at most one per 5 s of data). 0: never (an
    /// ablation: the revisit then only links the keyframes locally).
    #[arg(long, default_value_t = HandlerParams::default().revisit_min_points)]
    pub revisit_points: usize,
    /// Forget a client point not referenced by the last this-many keyframe ids of its
    /// client session (must exceed the id span of the client VO's window; 0: never; memory
    /// on long runs, BENCHMARKS.md "Long run").
    #[arg(long, default_value_t = HandlerParams::default().assoc_horizon_kfs)]
    pub assoc_horizon: u64,
    /// At the end, wait at most this long (s) for the handlers to finish their queues.
    #[arg(long, default_value_t = 50.0)]
    pub drain_seconds: f64,
    /// Replay mode of the run (the launcher passes it). In lock-step the mapper runs the
    /// idle step after every keyframe and tells the tracker when a keyframe is finished
    /// ([`lockstep`]), so the server maps are the same on every run.
    #[arg(long, default_value = "realtime")]
    pub mode: ReplayMode,
    /// In lock-step, do not synchronise (as in real time; for benchmarks).
    #[arg(long)]
    pub no_lockstep_sync: bool,
}

/// The service's name in reports.
pub const SERVICE_NAME: &str = "mapper";

/// Runs the service; returns the process exit code.
pub fn main_with(params: Params) -> i32 {
    shoal_runtime::exit_code(SERVICE_NAME, run(&params))
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
struct Mapper {
    handler_params: HandlerParams,
    /// Keyframes of all maps for a restarted loop closer (taken on its first request).
    resync: Vec<slam_core::server::KeptKeyframe>,
    clients: Vec<Client>,
    workers: Vec<Worker>,
    /// Latest size of every server map.
    map_sizes: BTreeMap<MapId, MapSize>,
    loop_seq: u64,
    journal: Option<Journal>,
    out: Option<PathBuf>,
    results_tx: crossbeam_channel::Sender<Report>,
    status: Status,
    /// Lock-step synchronisation (`None`: free-running).
    sync: Option<lockstep::LockstepSync>,
}

impl Mapper {
    /// Queues a keyframe for its client's handler, starting the handler on first use.
    fn queue(&mut self, c: u32, job: Job) -> anyhow::Result<()> {
        let w = match self.clients[c as usize].worker {
            Some(w) => w,
            None => {
                self.workers.push(
                    Worker::spawn(
                        c,
                        self.handler_params.clone(),
                        self.out.clone(),
                        self.results_tx.clone(),
                    )
                    .context("starting a handler thread")?,
                );
                self.status.add("handlers_started", 1);
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
    /// ever join, so a map stays with its creator's handler).
    fn host_of(&self, m: MapId) -> Option<usize> {
        self.clients.get((m >> 32) as usize)?.worker
    }

    /// Sends a correction to the worker hosting its map(s); for a merge of maps hosted by
    /// two workers, the `from` worker first hands its whole group over to the `into` one.
    fn dispatch(&mut self, corr: Correction, replay: bool) -> anyhow::Result<()> {
        let (w, from) = match &corr {
            Correction::Merge { from, into, .. } => {
                let (Some(wf), Some(wi)) = (self.host_of(*from), self.host_of(*into)) else {
                    self.status.add("corrections_refused", 1);
                    self.status.error(
                        "correction",
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
                    self.status.add("handler_groups_joined", 1);
                }
                (wi, Some(*from))
            }
            Correction::PoseGraph { map, .. } => {
                let Some(w) = self.host_of(*map) else {
                    self.status.add("corrections_refused", 1);
                    self.status.error(
                        "correction",
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
    fn receive_correction(
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
        self.status.add("corrections_received", 1);
        let corr = match convert::correction(h, records) {
            Ok(c) => c,
            Err(e) => {
                self.status.add("corrections_refused", 1);
                self.status.error("bad_correction", e);
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
    fn resync(
        &mut self,
        req: &shm_schema::ResyncRequest,
        loop_pub: &LoopPublisher,
    ) -> anyhow::Result<()> {
        self.status.add("resync_requests", 1);
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
            let client = (k.kf_id >> 40) as u32;
            let mut meta = MsgMeta::new(client, 0, self.loop_seq, monotonic_ns());
            meta.flags |= shm_schema::FLAG_RESYNC;
            let (intr, w, h) = shoal_runtime::wire::intrinsics_from_camera(&k.camera);
            let (lh, recs) = convert::loop_keyframe(k, meta, &intr, w, h);
            let out = loop_pub.loan_slice_uninit(recs.len())?;
            let mut out = out.write_from_slice(&recs);
            *out.user_header_mut() = lh;
            out.send()?;
            self.loop_seq += 1;
            self.status.add("resync_keyframes_sent", 1);
        }
        if to == self.resync.len() {
            let mut meta = MsgMeta::new(0, 0, self.loop_seq, monotonic_ns());
            meta.flags |= shm_schema::FLAG_RESYNC | shm_schema::FLAG_END_OF_STREAM;
            let out = loop_pub.loan_slice_uninit(0)?;
            let mut out = out.write_from_slice(&[]);
            *out.user_header_mut() = LoopKeyframeHeader {
                meta,
                ..LoopKeyframeHeader::default()
            };
            out.send()?;
            self.loop_seq += 1;
        }
        Ok(())
    }

    /// A worker applied (or refused) a correction: publish the moved poses, update figures.
    fn correction_outcome(
        &mut self,
        o: CorrectionOutcome,
        fbs: &[Publisher<Ipc, Feedback, ()>],
    ) -> anyhow::Result<()> {
        if let Some(s) = self.sync.as_mut() {
            s.correction_finished();
        }
        match &o.result {
            Ok(summary) => {
                self.status
                    .add(&format!("corrections_applied_{}", o.kind), 1);
                if o.replay {
                    self.status.add("corrections_replayed", 1);
                }
                self.status
                    .add("correction_apply_us", (o.apply_ms * 1e3) as u64);
                eprintln!(
                    "mapper: correction {}: {summary} ({:.1} ms)",
                    o.id, o.apply_ms
                );
            }
            Err(e) => {
                self.status.add("corrections_refused", 1);
                self.status
                    .error("correction", format!("correction {}: {e}", o.id));
            }
        }
        for f in &o.feedback {
            if let Some(fb) = fbs.get(f.client_id as usize) {
                self.send_feedback(f, fb)?;
            }
        }
        for (c, fig) in &o.figures {
            self.set_figures(*c, *fig);
        }
        if let Some(m) = o.absorbed {
            // Merged away: the `maps` / `keyframes` / `points` gauges count live maps only.
            self.map_sizes.remove(&m);
        }
        self.set_map_sizes(&o.maps);
        Ok(())
    }

    fn set_map_sizes(&mut self, maps: &[MapSize]) {
        for m in maps {
            self.map_sizes.insert(m.id, *m);
        }
        let (n, kfs, pts) = self.map_sizes.values().fold((0, 0, 0), |a, m| {
            (a.0 + 1, a.1 + m.keyframes as u64, a.2 + m.points as u64)
        });
        let c = &mut self.status.counters;
        c.insert("maps".into(), n);
        c.insert("keyframes".into(), kfs);
        c.insert("points".into(), pts);
    }

    fn set_figures(&mut self, c: u32, f: MapFigures) {
        let s = &mut self.status;
        let mut set = |k: String, v: u64| {
            s.counters.insert(k, v);
        };
        set(format!("c{c}.keyframes_kept"), f.stats.kept);
        set(format!("c{c}.keyframes_discarded"), f.stats.discarded);
        set(format!("c{c}.keyframes_culled"), f.stats.culled);
        set(format!("c{c}.revisit_global_ba"), f.stats.revisit_global_ba);
        set(
            format!("c{c}.kept_at_session_end"),
            f.stats.kept_at_session_end,
        );
        set(format!("c{c}.maps"), f.stats.maps);
        set(format!("c{c}.server_keyframes"), f.keyframes as u64);
        if let Some(m) = f.map_id {
            set(format!("c{c}.map_id"), m);
        }
        s.set_value(&format!("c{c}.lambda"), f.lambda);
        if let Some(cl) = self.clients.get_mut(c as usize) {
            cl.figures = f;
        }
    }

    /// Publishes pose feedback (server pose of the last keyframe, λ, map id) to a client.
    fn send_feedback(
        &mut self,
        f: &slam_core::server::ServerFeedback,
        fb: &Publisher<Ipc, Feedback, ()>,
    ) -> anyhow::Result<()> {
        let Some((map_id, t_sk, lambda)) = f.pose else {
            return Ok(());
        };
        let c = f.client_id;
        let Some(cl) = self.clients.get_mut(c as usize) else {
            return Ok(());
        };
        let msg = Feedback {
            meta: MsgMeta::new(c, f.acked_session_id, cl.fb_seq, monotonic_ns()),
            acked_keyframe_id: f.acked_keyframe_id,
            acked_session_id: f.acked_session_id,
            has_pose: 1,
            server_pose: convert::wire_from_iso(&t_sk),
            scale_ratio: lambda,
            server_map_id: map_id,
        };
        fb.send_copy(msg)?;
        cl.fb_seq += 1;
        self.status.add(&format!("c{c}.pose_feedback_sent"), 1);
        Ok(())
    }

    /// Lock-step: tells the trackers which keyframes are finished ([`lockstep`]): a
    /// [`shm_schema::FLAG_HANDLED`] feedback with the pose feedback after the keyframe.
    fn send_finished(&mut self, fbs: &[Publisher<Ipc, Feedback, ()>]) -> anyhow::Result<()> {
        let Some(sync) = self.sync.as_mut() else {
            return Ok(());
        };
        for (k, timed_out) in sync.take_finished(Instant::now()) {
            if timed_out {
                self.status.add("lockstep_loop_timeouts", 1);
            }
            let (Some(fb), Some(cl)) = (
                fbs.get(k.client as usize),
                self.clients.get_mut(k.client as usize),
            ) else {
                continue;
            };
            let mut meta = MsgMeta::new(k.client, k.session, cl.fb_seq, monotonic_ns());
            meta.flags |= shm_schema::FLAG_HANDLED;
            let (map_id, t_sk, lambda) =
                k.pose.unwrap_or((0, nalgebra::Isometry3::identity(), 1.0));
            fb.send_copy(Feedback {
                meta,
                acked_keyframe_id: k.kf_id,
                acked_session_id: k.session,
                has_pose: k.pose.is_some() as u32,
                server_pose: convert::wire_from_iso(&t_sk),
                scale_ratio: lambda,
                server_map_id: map_id,
            })?;
            cl.fb_seq += 1;
            let c = k.client;
            self.status.add(&format!("c{c}.keyframes_finished"), 1);
            if k.pose.is_some() {
                self.status.add(&format!("c{c}.pose_feedback_sent"), 1);
            }
        }
        Ok(())
    }

    /// Rebuilds the maps from the journal's entries (before any new keyframe is taken).
    fn replay(&mut self, entries: Vec<Entry>) -> anyhow::Result<usize> {
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
            let (client, header, records) = match e {
                Entry::Keyframe {
                    client,
                    header,
                    records,
                } => (client, header, records),
                Entry::Correction { header, records } => {
                    match convert::correction(&header, &records) {
                        Ok(c) => self.dispatch(c, true)?,
                        Err(e) => self.status.error("journal", e),
                    }
                    continue;
                }
                Entry::Idle { .. } => continue,
            };
            if client as usize >= self.clients.len() {
                self.status.error(
                    "journal",
                    format!("keyframe of client {client} in the journal, serving fewer"),
                );
                continue;
            }
            let key = (header.meta.session_id, header.keyframe_id);
            match convert::server_keyframe(client, &header, &records) {
                Ok(kf) => {
                    self.clients[client as usize].applied.insert(key);
                    let job = Job::Keyframe {
                        kf,
                        idle: Some(idle.contains(&(client, key.0, key.1))),
                        replay: true,
                    };
                    self.queue(client, job)?;
                    n += 1;
                }
                Err(e) => self.status.error("journal", e),
            }
        }
        Ok(n)
    }

    /// One keyframe message of client `c`: journal, queue, acknowledge.
    fn receive(
        &mut self,
        c: u32,
        h: &KeyframeHeader,
        records: &[KeypointRecord],
        fb: &Publisher<Ipc, Feedback, ()>,
    ) -> anyhow::Result<()> {
        let s = &mut self.status;
        s.add(&format!("c{c}.keyframes_received"), 1);
        s.add(
            &format!("c{c}.keyframe_bytes"),
            (std::mem::size_of::<KeyframeHeader>() + std::mem::size_of_val(records)) as u64,
        );
        let key = (h.meta.session_id, h.keyframe_id);
        if self.clients[c as usize].applied.contains(&key) {
            s.add(&format!("c{c}.keyframes_duplicate"), 1);
        } else {
            match convert::server_keyframe(c, h, records) {
                Err(e) => {
                    // Acknowledged (a re-send would not be better) but not applied.
                    s.error("bad_keyframe", format!("client {c}: {e}"));
                }
                Ok(kf) => {
                    if let Some(j) = self.journal.as_mut() {
                        j.append(&Entry::Keyframe {
                            client: c,
                            header: Box::new(*h),
                            records: records.to_vec(),
                        })
                        .context("writing the journal")?;
                    }
                    let cl = &mut self.clients[c as usize];
                    cl.applied.insert(key);
                    cl.waiting.insert(key, (*h, records.to_vec()));
                    s.add(&format!("c{c}.keyframes_applied"), 1);
                    self.queue(
                        c,
                        Job::Keyframe {
                            kf,
                            // Lock-step: the idle step after every keyframe, whatever
                            // the queue (the live default idles when the queue is empty).
                            idle: self.sync.is_some().then_some(true),
                            replay: false,
                        },
                    )?;
                }
            }
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
        fb.send_copy(ack)?;
        cl.fb_seq += 1;
        self.status.add(&format!("c{c}.keyframes_acked"), 1);
        Ok(())
    }

    /// A handler's outcome: journal the idle step, forward kept keyframes, publish feedback,
    /// update the figures.
    fn outcome(
        &mut self,
        o: Outcome,
        fb: &Publisher<Ipc, Feedback, ()>,
        loop_pub: &LoopPublisher,
    ) -> anyhow::Result<()> {
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
        let s = &mut self.status;
        let cl = &mut self.clients[c as usize];
        let mut loop_seq = None;
        match &o.result {
            Err(e) => {
                s.error("handler", format!("client {c} keyframe {}: {e}", o.kf_id));
                cl.waiting.remove(&key);
            }
            Ok(r) => {
                let name = match r.status {
                    KeyframeStatus::First => "first",
                    KeyframeStatus::MapCreated => "map_created",
                    KeyframeStatus::Kept => "kept",
                    KeyframeStatus::Discarded => "discarded",
                    KeyframeStatus::Duplicate => "duplicate",
                };
                s.add(&format!("c{c}.handled_{name}"), 1);
                if o.replay {
                    s.add(&format!("c{c}.keyframes_replayed"), 1);
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
                        let out = loop_pub.loan_slice_uninit(recs.len())?;
                        let mut out = out.write_from_slice(&recs);
                        *out.user_header_mut() = lh;
                        out.send()?;
                        loop_seq = Some(self.loop_seq);
                        self.loop_seq += 1;
                        s.add(&format!("c{c}.keyframes_forwarded"), 1);
                    }
                }
                // The first keyframe of a session waits for the second (map creation); the
                // newest discarded one for the session's end (it may be inserted then).
                let keep = matches!(r.status, KeyframeStatus::First | KeyframeStatus::Discarded);
                cl.waiting.retain(|k, _| *k > key || (keep && *k == key));
            }
        }
        s.add(&format!("c{c}.handle_us"), (o.handle_ms * 1e3) as u64);
        s.add(&format!("c{c}.idle_us"), (o.idle_ms * 1e3) as u64);
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
            self.send_feedback(f, fb)?;
        }
        self.set_figures(c, o.figures);
        self.set_map_sizes(&o.maps);
        Ok(())
    }
}

fn drain_outcomes(
    m: &mut Mapper,
    rx: &Receiver<Report>,
    fbs: &[Publisher<Ipc, Feedback, ()>],
    loop_pub: &LoopPublisher,
) -> anyhow::Result<usize> {
    let mut n = 0;
    while let Ok(r) = rx.try_recv() {
        match r {
            Report::Keyframe(o) => {
                let c = o.client as usize;
                m.outcome(*o, &fbs[c], loop_pub)?;
            }
            Report::Correction(o) => m.correction_outcome(*o, fbs)?,
        }
        n += 1;
    }
    m.send_finished(fbs)?;
    Ok(n)
}

/// Serves keyframes until SIGINT/SIGTERM, then lets the handlers finish their queues.
pub fn run(params: &Params) -> anyhow::Result<Status> {
    let mut file = StatusFile::new(params.status.clone());
    let status = shoal_runtime::resume_status(&file, SERVICE_NAME);
    let out = params.out.clone().or_else(|| {
        params
            .journal
            .as_ref()
            .and_then(|j| j.parent().map(|p| p.to_path_buf()))
    });
    let (results_tx, results_rx) = crossbeam_channel::unbounded();
    let mut m = Mapper {
        resync: Vec::new(),
        handler_params: HandlerParams {
            spatial_keyframes: params.spatial_keyframes,
            revisit_min_points: params.revisit_points,
            assoc_horizon_kfs: params.assoc_horizon,
            ..HandlerParams::default()
        },
        workers: Vec::new(),
        map_sizes: BTreeMap::new(),
        loop_seq: 0,
        clients: (0..params.clients)
            .map(|_| Client {
                worker: None,
                applied: HashSet::new(),
                waiting: BTreeMap::new(),
                fb_seq: 0,
                figures: MapFigures::default(),
            })
            .collect(),
        journal: None,
        out,
        results_tx,
        status,
        sync: (params.mode == ReplayMode::Lockstep && !params.no_lockstep_sync)
            .then(|| lockstep::LockstepSync::new(lockstep::LOOP_SYNC_TIMEOUT)),
    };
    // Rebuild the maps from the journal before taking new keyframes.
    if let Some(path) = &params.journal {
        let (j, contents) = Journal::open(path)
            .with_context(|| format!("opening the journal {}", path.display()))?;
        if let Some(p) = contents.problem {
            m.status
                .error("journal", format!("{}: {p}", path.display()));
        }
        let n = m.replay(contents.entries)?;
        m.status.set_value("journal_keyframes_on_start", n as f64);
        m.journal = Some(j);
    }
    let prefix = params
        .ipc_prefix
        .clone()
        .unwrap_or_else(topics::prefix_from_env);
    topics::check_foreign_versions(&prefix)?;
    let node = topics::create_node("mapper", &prefix)?;
    let mut subs = Vec::new();
    let mut fbs = Vec::new();
    for c in 0..params.clients {
        subs.push(topics::keyframe_subscriber(&topics::keyframes_service(
            &node, c,
        )?)?);
        fbs.push(topics::publisher(&topics::feedback_service(&node, c)?)?);
    }
    let loop_pub = topics::slice_publisher(
        &topics::loop_keyframes_service(&node)?,
        topics::MAX_KEYPOINTS,
    )?;
    let resync_sub = topics::subscriber(&topics::resync_service(&node)?)?;
    let mut trimmer = shoal_runtime::HeapTrimmer::new(Duration::from_secs(5));
    let corr_sub = topics::slice_subscriber(
        &topics::corrections_service(&node)?,
        topics::CORRECTION_BUFFER,
    )?;
    shoal_runtime::signal_ready();

    loop {
        let mut idle = true;
        for (c, sub) in subs.iter().enumerate() {
            while let Some(kf) = sub.receive()? {
                idle = false;
                let h = *kf.user_header();
                if let Err(e) = h.meta.check() {
                    m.status
                        .error("schema_version", format!("keyframe of client {c}: {e}"));
                    continue;
                }
                m.receive(c as u32, &h, kf.payload(), &fbs[c])?;
            }
        }
        while let Some(c) = corr_sub.receive()? {
            idle = false;
            let h = *c.user_header();
            if let Err(e) = h.meta.check() {
                m.status.error("schema_version", format!("correction: {e}"));
                continue;
            }
            m.receive_correction(&h, c.payload())?;
        }
        if drain_outcomes(&mut m, &results_rx, &fbs, &loop_pub)? > 0 {
            idle = false;
        }
        while let Some(req) = resync_sub.receive()? {
            idle = false;
            let req = *req;
            if let Err(e) = req.meta.check() {
                m.status
                    .error("schema_version", format!("resync request: {e}"));
                continue;
            }
            m.resync(&req, &loop_pub)?;
        }
        let _ = file.write_every(&m.status, Duration::from_millis(200));
        if idle {
            trimmer.maybe_trim();
        }
        if idle && node.wait(Duration::from_millis(1)).is_err() {
            break;
        }
    }
    // Stop: the handlers finish what they have queued and write their files.
    let queued: usize = m.workers.iter().map(|w| w.queued()).sum();
    m.status.set_value("queued_at_stop", queued as f64);
    for w in m.workers.iter_mut() {
        w.close();
    }
    let deadline = Instant::now() + Duration::from_secs_f64(params.drain_seconds.max(0.0));
    loop {
        drain_outcomes(&mut m, &results_rx, &fbs, &loop_pub)?;
        let running = m.workers.iter().any(|w| !w.is_finished());
        if !running || Instant::now() > deadline {
            break;
        }
        std::thread::sleep(Duration::from_millis(5));
    }
    drain_outcomes(&mut m, &results_rx, &fbs, &loop_pub)?;
    for (i, w) in m.workers.iter_mut().enumerate() {
        if w.is_finished() && !w.join() {
            m.status
                .error("handler", format!("handler thread {i} panicked"));
        }
    }
    m.status.finished = true;
    file.write(&m.status)?;
    Ok(m.status)
}
