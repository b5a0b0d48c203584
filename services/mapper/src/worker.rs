//! Keyframe handler threads. A worker thread hosts a *group*: the server maps it owns and
//! the handlers of the clients whose keyframes go into them. Each client starts in a group
//! of its own, so clients are handled in parallel; when the loop closer merges maps hosted
//! by two groups, the one group hands everything over to the other (the handlers of merged
//! clients then share one map and run on one thread, in the order the main thread queued
//! their keyframes). Keyframes and corrections come in on a crossbeam channel; reports
//! (handle results, feedback, map figures) go back to the main thread, which owns the
//! iceoryx2 ports.
//!
//! After a keyframe the handler runs its idle step (local BA + culling) when its queue is
//! empty or, in a backlog, every few keyframes (lock-step: [`MAX_WITHOUT_IDLE`]; real time:
//! the adaptive interval of [`pacing`]); the report says whether it did, so the main thread
//! can journal it and a replay can follow the same schedule. A correction or a revisit
//! starts a global BA on the group's own global BA thread ([`global_ba`]; in replays too,
//! so it needs no journal entry); lock-step waits for it, real time goes on meanwhile.
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

use crossbeam_channel::{Receiver, Sender};
use datasets::trajectory::{write_tum_file, TumDigits, TumRow};
use nalgebra::Isometry3;
use slam_core::ids::KeyframeId;
use slam_core::lie::Sim3;
use slam_core::server::{
    apply_pose_corrections, merge_maps, relocalise_in_frozen, HandleReport, HandlerParams,
    HandlerStats, KeptKeyframe, KeyframeHandler, KeyframeStatus, MapFrame, MapId, ServerFeedback,
    ServerKeyframe, ServerMaps,
};
use slam_core::vo::PointId;

use crate::convert::Correction;

mod global_ba;
mod pacing;
pub use global_ba::GlobalBaOutcome;
use global_ba::GlobalBaRunner;
use pacing::IdlePacing;

/// How often a busy handler rewrites its trajectory files.
const WRITE_EVERY: Duration = Duration::from_secs(2);

/// Most keyframes handled in a row without an idle step.
pub const MAX_WITHOUT_IDLE: usize = 4;

/// Work for a worker thread.
#[derive(Debug)]
pub enum Job {
    /// A keyframe for its client's handler (created on first use).
    Keyframe {
        /// The keyframe (boxed: with its IMU segment it is large beside the other jobs).
        kf: Box<ServerKeyframe>,
        /// Run the idle step after it: `Some` to follow a journaled schedule (replay),
        /// `None` to decide live.
        idle: Option<bool>,
        /// True when replayed from the journal (not to be acknowledged or forwarded again).
        replay: bool,
    },
    /// A loop correction on maps of this group.
    Correction {
        /// The correction.
        correction: Correction,
        /// True when replayed from the journal.
        replay: bool,
    },
    /// Hand all maps and handlers over (on `to`) and end.
    HandOver {
        /// Where the group goes.
        to: Sender<Group>,
    },
    /// The loop closer's summaries of every keyframe of every map of the group (for a
    /// restarted loop closer), with their current poses.
    Snapshot {
        /// Where they go.
        reply: Sender<Vec<KeptKeyframe>>,
    },
    /// Host maps loaded from a saved-map file (maps without a live client's handler; a
    /// live client's map merges into them through the usual corrections).
    Host {
        /// The maps.
        maps: ServerMaps,
    },
    /// Wait for a group handed over by another worker and host it too.
    TakeOver {
        /// Where it comes from.
        from: Receiver<Group>,
    },
}

/// Size and kind of one server map.
#[derive(Debug, Clone, PartialEq, Eq, Default)]
pub struct MapSize {
    /// Map id.
    pub id: MapId,
    /// Keyframes.
    pub keyframes: usize,
    /// Points.
    pub points: usize,
    /// Clients with keyframes in it, ascending.
    pub clients: Vec<u32>,
    /// Metric and gravity-aligned, or not.
    pub frame: MapFrame,
}

/// Map figures of one client's handler.
#[derive(Debug, Clone, Copy, Default)]
pub struct MapFigures {
    /// Handler counters.
    pub stats: HandlerStats,
    /// Current server map of the client.
    pub map_id: Option<MapId>,
    /// The client's own keyframes in it.
    pub keyframes: usize,
    /// Current scale ratio.
    pub lambda: f64,
}

/// What a handler did with one keyframe.
#[derive(Debug)]
pub struct Outcome {
    /// Client index.
    pub client: u32,
    /// VO session of the keyframe.
    pub session: u32,
    /// Client keyframe id.
    pub kf_id: u64,
    /// The handler's report, or why it refused the keyframe.
    pub result: Result<HandleReport, String>,
    /// The idle step ran after it.
    pub idled: bool,
    /// Replayed from the journal.
    pub replay: bool,
    /// Pose feedback after it (and after the idle step).
    pub feedback: Option<ServerFeedback>,
    /// Map figures of the client after it.
    pub figures: MapFigures,
    /// Sizes of all maps of the worker's group.
    pub maps: Vec<MapSize>,
    /// Time in `handle`, ms.
    pub handle_ms: f64,
    /// Time in the idle step, ms.
    pub idle_ms: f64,
    /// Jobs queued behind this keyframe when it was handled (the group's backlog).
    pub queued: usize,
    /// The group's idle interval after it ([`pacing`]).
    pub idle_interval: usize,
}

/// The two kinds of correction.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum CorrectionKind {
    /// A map merged into another.
    Merge,
    /// A pose graph correction within one map.
    PoseGraph,
}

/// What a worker did with a correction.
#[derive(Debug)]
pub struct CorrectionOutcome {
    /// Correction id.
    pub id: u64,
    /// Merge or pose graph correction.
    pub kind: CorrectionKind,
    /// A one-line summary, or why it was refused.
    pub result: Result<String, String>,
    /// Replayed from the journal.
    pub replay: bool,
    /// Feedback of every client of the group (their server poses moved).
    pub feedback: Vec<ServerFeedback>,
    /// Figures of every client of the group.
    pub figures: Vec<(u32, MapFigures)>,
    /// Sizes of all maps of the group.
    pub maps: Vec<MapSize>,
    /// The map a successful merge absorbed (it no longer exists).
    pub absorbed: Option<MapId>,
    /// Time to apply it (merge or corrections, fusion, global BA), ms.
    pub apply_ms: f64,
}

/// A report of a worker to the main thread.
#[derive(Debug)]
pub enum Report {
    /// A keyframe was handled.
    Keyframe(Box<Outcome>),
    /// A correction was applied (or refused).
    Correction(Box<CorrectionOutcome>),
    /// A global BA was applied (or dropped).
    GlobalBa(Box<GlobalBaOutcome>),
}

/// A running worker thread.
#[derive(Debug)]
pub struct Worker {
    tx: Option<Sender<Job>>,
    thread: Option<JoinHandle<ServerMaps>>,
    /// The group's maps at the thread's end (none when it handed them over), once joined.
    final_maps: ServerMaps,
}

impl Worker {
    /// Starts a worker thread (named after the client it is first started for) and its
    /// global BA thread ([`global_ba`]); its trajectory files go to `out` (if any). In
    /// `lockstep` it waits for its global BAs and idles on a fixed schedule ([`pacing`]),
    /// so that a run is reproducible.
    pub fn spawn(
        first_client: u32,
        params: HandlerParams,
        out: Option<PathBuf>,
        results: Sender<Report>,
        lockstep: bool,
    ) -> std::io::Result<Self> {
        let (tx, rx) = crossbeam_channel::unbounded();
        let name = format!("handlers_c{first_client}");
        let gba = GlobalBaRunner::spawn(&name, params.vi, lockstep)?;
        let thread = std::thread::Builder::new()
            .name(name)
            .spawn(move || serve(params, out, rx, results, gba, lockstep))?;
        Ok(Self {
            tx: Some(tx),
            thread: Some(thread),
            final_maps: ServerMaps::new(),
        })
    }

    /// Queues a job; false when the thread is gone.
    pub fn send(&self, job: Job) -> bool {
        self.tx.as_ref().is_some_and(|tx| tx.send(job).is_ok())
    }

    /// Jobs waiting.
    pub fn queued(&self) -> usize {
        self.tx.as_ref().map_or(0, |tx| tx.len())
    }

    /// Closes the queue: the thread handles what is queued, writes its files and ends.
    pub fn close(&mut self) {
        self.tx = None;
    }

    /// True once the thread has ended.
    pub fn is_finished(&self) -> bool {
        self.thread.as_ref().is_none_or(|t| t.is_finished())
    }

    /// Joins an ended thread (keeping its final maps, [`Worker::take_maps`]); false if it
    /// panicked.
    pub fn join(&mut self) -> bool {
        match self.thread.take().map(|t| t.join()) {
            Some(Ok(maps)) => {
                self.final_maps = maps;
                true
            }
            Some(Err(_)) => false,
            None => true,
        }
    }

    /// The maps the group held when its thread ended (after [`Worker::join`]; empty for a
    /// group handed over to another).
    pub fn take_maps(&mut self) -> ServerMaps {
        std::mem::take(&mut self.final_maps)
    }
}

/// Per-client state inside a group.
#[derive(Debug)]
struct ClientState {
    h: KeyframeHandler,
    /// Client poses of the keyframes of the current session, as received.
    client_kfs: Vec<(i64, Isometry3<f64>)>,
    /// (keyframe time, keyframes and points in the current map) after each keyframe.
    growth: Vec<(i64, usize, usize)>,
    session: Option<u32>,
    /// Keyframes handled since the last idle step.
    since_idle: usize,
    /// `--localize-only`: (time, `T_sk`) of the client's keyframes in a frozen map: those
    /// localised in it, and those of its maps that relocalised there (moved into its frame).
    localised: Vec<(i64, Isometry3<f64>)>,
}

/// The maps and handlers a worker hosts.
#[derive(Debug, Default)]
pub struct Group {
    maps: ServerMaps,
    clients: BTreeMap<u32, ClientState>,
    /// Corrections (merges, pose graphs) applied to each map: a global BA solved across
    /// one is stale ([`global_ba`]).
    generations: BTreeMap<MapId, u64>,
    /// When to idle in a backlog (real time).
    pacing: IdlePacing,
}

/// Size and kind of server map `m`.
pub fn map_size(m: &slam_core::server::ServerMap) -> MapSize {
    MapSize {
        id: m.id,
        keyframes: m.map.keyframes.len(),
        points: m.map.points.len(),
        clients: m
            .map
            .keyframes
            .keys()
            .map(|k| KeyframeId::from_raw(*k).client().raw())
            .collect::<std::collections::BTreeSet<u32>>()
            .into_iter()
            .collect(),
        frame: m.frame,
    }
}

impl Group {
    fn sizes(&self) -> Vec<MapSize> {
        self.maps.values().map(map_size).collect()
    }

    fn figures(&self, c: u32) -> MapFigures {
        let Some(cs) = self.clients.get(&c) else {
            return MapFigures::default();
        };
        let map = cs.h.current_map(&self.maps);
        MapFigures {
            stats: cs.h.stats(),
            map_id: map.map(|m| m.id),
            keyframes: map.map_or(0, |m| {
                m.map
                    .keyframes
                    .keys()
                    .filter(|k| KeyframeId::from_raw(**k).client().raw() == c)
                    .count()
            }),
            lambda: cs.h.lambda(),
        }
    }

    /// Applies a correction; the summary or why it was refused.
    fn apply(&mut self, c: &Correction) -> Result<String, String> {
        match c {
            Correction::Merge {
                from,
                into,
                s_into_from,
                pairs,
                ..
            } => {
                let frozen = |m: &MapId| self.maps.get(m).is_some_and(|m| m.is_frozen());
                if frozen(into) {
                    return self.relocalise(*from, *into, s_into_from, pairs);
                }
                if frozen(from) {
                    return Err(format!(
                        "map {from:#x} is frozen (--localize-only): it does not merge into {into:#x}"
                    ));
                }
                let r = merge_maps(&mut self.maps, *from, *into, s_into_from, pairs)
                    .map_err(|e| e.to_string())?;
                for m in [from, into] {
                    *self.generations.entry(*m).or_insert(0) += 1;
                }
                let mut first = true;
                for cs in self.clients.values_mut() {
                    if cs.h.apply_merge(*from, *into, s_into_from, first) {
                        first = false;
                    }
                }
                Ok(format!(
                    "map {from:#x} merged into {into:#x} (scale {:.4}): {} keyframes moved, {} points fused",
                    s_into_from.s, r.keyframes_moved, r.points_fused
                ))
            }
            Correction::PoseGraph {
                map,
                deltas,
                fallback,
                pairs,
                ..
            } => {
                let Some(m) = self.maps.get_mut(map) else {
                    return Err(format!("pose-graph correction of unknown map {map:#x}"));
                };
                if m.is_frozen() {
                    return Err(format!(
                        "map {map:#x} is frozen (--localize-only): no pose-graph correction"
                    ));
                }
                let r = apply_pose_corrections(&mut m.map, deltas, fallback);
                *self.generations.entry(*map).or_insert(0) += 1;
                let fused = slam_core::server::correction::fuse_points(m, pairs);
                let mut first = true;
                for cs in self.clients.values_mut() {
                    let delta =
                        cs.h.last_keyframe()
                            .and_then(|(_, k)| k)
                            .and_then(|k| deltas.get(&k))
                            .unwrap_or(fallback);
                    if cs.h.apply_correction(*map, delta, first) {
                        first = false;
                    }
                }
                Ok(format!(
                    "map {map:#x}: {} keyframes corrected, {} by the fallback, {} points moved, {fused} fused",
                    r.keyframes_corrected, r.keyframes_fallback, r.points_moved
                ))
            }
        }
    }
}

impl Group {
    /// A live map matched a frozen one (`--localize-only`): it leaves the store and its
    /// clients localise in the frozen map, which stays as it is
    /// ([`slam_core::server::relocalise_in_frozen`]).
    fn relocalise(
        &mut self,
        from: MapId,
        into: MapId,
        s: &Sim3,
        pairs: &[(PointId, PointId)],
    ) -> Result<String, String> {
        let r = relocalise_in_frozen(&mut self.maps, from, into, s, pairs)
            .map_err(|e| e.to_string())?;
        *self.generations.entry(from).or_insert(0) += 1;
        for (c, cs) in &mut self.clients {
            cs.h.apply_relocalisation(from, into, s, &r.dropped, r.reference);
            let kfs = r.dropped.map.keyframes.iter();
            let mine = kfs.filter(|(k, _)| KeyframeId::from_raw(**k).client().raw() == *c);
            cs.localised
                .extend(mine.map(|(_, kf)| (kf.t_ns, kf.t_cw.inverse())));
        }
        Ok(format!(
            "map {from:#x} relocalised in frozen map {into:#x} (scale {:.4}): its {} keyframes \
             left out, reference keyframe {}",
            s.s,
            r.dropped.map.keyframes.len(),
            r.reference.map_or("none".into(), |k| format!("{k:#x}"))
        ))
    }

    /// Every kept keyframe of the group's maps (a restarted loop closer's resync).
    fn snapshot(&self) -> Vec<slam_core::server::KeptKeyframe> {
        self.maps
            .values()
            .flat_map(|m| {
                let kfs = m.map.keyframes.keys();
                kfs.filter_map(move |k| m.kept_summary(*k, KeyframeId::from_raw(*k).client_kf()))
            })
            .collect()
    }
}

/// Applies a correction and starts the global BA it asks for (live and in replays; in
/// lock-step it is done before the local BAs, and returned); with an output folder, a
/// pose-graph correction's map is written before and after (and after its global BA in
/// lock-step only).
fn correct(
    g: &mut Group,
    gba: &mut GlobalBaRunner,
    out: Option<&std::path::Path>,
    correction: Correction,
    replay: bool,
) -> (CorrectionOutcome, Vec<GlobalBaOutcome>) {
    let t0 = Instant::now();
    let snapshot = |g: &Group, when: &str| {
        if let (Some(out), Correction::PoseGraph { id, map, .. }) = (out, &correction) {
            if let Some(m) = g.maps.get(map) {
                let path = out.join(format!("correction_{id}_{when}.txt"));
                let _ = write_tum(&path, &m.trajectory());
            }
        }
    };
    snapshot(g, "before");
    let result = g.apply(&correction);
    let mut gbas = Vec::new();
    if result.is_ok() {
        gbas = gba.request(g);
        for cs in g.clients.values_mut() {
            while cs.h.idle_step(&mut g.maps).is_some() {}
        }
        snapshot(g, "after");
    }
    let clients: Vec<u32> = g.clients.keys().copied().collect();
    let absorbed = match (&correction, &result) {
        (Correction::Merge { from, .. }, Ok(_)) => Some(*from),
        _ => None,
    };
    let outcome = CorrectionOutcome {
        id: correction.id(),
        kind: match correction {
            Correction::Merge { .. } => CorrectionKind::Merge,
            Correction::PoseGraph { .. } => CorrectionKind::PoseGraph,
        },
        result,
        replay,
        feedback: g
            .clients
            .values()
            .filter_map(|cs| cs.h.feedback(&g.maps))
            .collect(),
        figures: clients.iter().map(|c| (*c, g.figures(*c))).collect(),
        maps: g.sizes(),
        absorbed,
        apply_ms: t0.elapsed().as_secs_f64() * 1e3,
    };
    (outcome, gbas)
}

fn serve(
    params: HandlerParams,
    out: Option<PathBuf>,
    rx: Receiver<Job>,
    results: Sender<Report>,
    mut gba: GlobalBaRunner,
    lockstep: bool,
) -> ServerMaps {
    let mut g = Group::default();
    let mut dirty = false;
    let mut last_write = Instant::now();
    let done = gba.done().clone();
    loop {
        let job = crossbeam_channel::select! {
            recv(rx) -> j => match j {
                Ok(j) => Some(j),
                Err(_) => break,
            },
            recv(done) -> s => {
                if let Ok(s) = s {
                    dirty = true;
                    let o = gba.finish(&mut g, s);
                    if results.send(Report::GlobalBa(Box::new(o))).is_err() {
                        break;
                    }
                }
                None
            },
            default(Duration::from_millis(200)) => None,
        };
        let (report, gbas) = match job {
            None => {
                if dirty && last_write.elapsed() > WRITE_EVERY {
                    write_files(out.as_deref(), &g);
                    dirty = false;
                    last_write = Instant::now();
                }
                continue;
            }
            Some(Job::HandOver { to }) => {
                write_files(out.as_deref(), &g);
                let _ = to.send(std::mem::take(&mut g));
                return ServerMaps::new();
            }
            Some(Job::Host { maps }) => {
                g.maps.extend(maps);
                continue;
            }
            Some(Job::Snapshot { reply }) => {
                let _ = reply.send(g.snapshot());
                continue;
            }
            Some(Job::TakeOver { from }) => {
                if let Ok(other) = from.recv() {
                    g.maps.extend(other.maps);
                    g.clients.extend(other.clients);
                    g.generations.extend(other.generations);
                }
                continue;
            }
            Some(Job::Correction { correction, replay }) => {
                dirty = true;
                let (o, gbas) = correct(&mut g, &mut gba, out.as_deref(), correction, replay);
                (Report::Correction(Box::new(o)), gbas)
            }
            Some(Job::Keyframe { kf, idle, replay }) => {
                dirty = true;
                let job = KeyframeJob {
                    kf: *kf,
                    idle,
                    replay,
                    lockstep,
                };
                let (o, gbas) = handle(&mut g, &mut gba, &params, job, &rx);
                (Report::Keyframe(Box::new(o)), gbas)
            }
        };
        let sent = gbas
            .into_iter()
            .all(|o| results.send(Report::GlobalBa(Box::new(o))).is_ok());
        if !sent || results.send(report).is_err() {
            break;
        }
        if dirty && last_write.elapsed() > WRITE_EVERY {
            write_files(out.as_deref(), &g);
            dirty = false;
            last_write = Instant::now();
        }
    }
    gba.stop();
    write_files(out.as_deref(), &g);
    g.maps
}

/// A keyframe job as [`handle`] takes it.
struct KeyframeJob {
    kf: ServerKeyframe,
    /// The journaled idle decision (replay), else decided here.
    idle: Option<bool>,
    replay: bool,
    lockstep: bool,
}

/// Handles a keyframe, starts the global BA it asks for (a revisit; in lock-step it is done
/// before the idle step, and returned), then runs the idle step if due.
fn handle(
    g: &mut Group,
    gba: &mut GlobalBaRunner,
    params: &HandlerParams,
    job: KeyframeJob,
    rx: &Receiver<Job>,
) -> (Outcome, Vec<GlobalBaOutcome>) {
    let KeyframeJob {
        kf,
        idle,
        replay,
        lockstep,
    } = job;
    let client = kf.client_id;
    let cs = g.clients.entry(client).or_insert_with(|| ClientState {
        h: KeyframeHandler::new(client, params.clone()),
        client_kfs: Vec::new(),
        growth: Vec::new(),
        session: None,
        since_idle: 0,
        localised: Vec::new(),
    });
    let (kf_session, kf_id, t_ns, t_ck) = (kf.session_id, kf.id, kf.t_ns, kf.t_ck);
    let t0 = Instant::now();
    let result = cs.h.handle(&mut g.maps, kf).map_err(|e| e.to_string());
    let handle_ms = t0.elapsed().as_secs_f64() * 1e3;
    if let Ok(r) = &result {
        if r.status != KeyframeStatus::Duplicate {
            if cs.session != Some(kf_session) {
                cs.client_kfs.clear();
                cs.session = Some(kf_session);
            }
            cs.client_kfs.push((t_ns, t_ck));
        }
        let in_frozen = |m: MapId| g.maps.get(&m).is_some_and(|m| m.is_frozen());
        if let (Some(m), Some(t_sk)) = (r.map_id, r.t_sk) {
            if in_frozen(m) {
                cs.localised.push((t_ns, t_sk));
            }
        }
    }
    // Idle when the queue is empty, and at least every MAX_WITHOUT_IDLE keyframes even
    // in a burst (a client that sends its whole window at the end of its stream would
    // otherwise get no local BA at all while its map grows). The journal records the
    // decision, so a replay takes the same schedule.
    g.pacing.on_keyframe(client, t_ns, handle_ms);
    let queued = rx.len();
    let idled = result.is_ok()
        && idle.unwrap_or_else(|| {
            if lockstep {
                queued == 0 || cs.since_idle + 1 >= MAX_WITHOUT_IDLE
            } else {
                g.pacing
                    .idle_due(cs.since_idle, queued == 0, MAX_WITHOUT_IDLE)
            }
        });
    cs.since_idle = if idled { 0 } else { cs.since_idle + 1 };
    let t1 = Instant::now();
    let mut gbas = Vec::new();
    if idled {
        gbas = gba.request(g);
    }
    let cs = g
        .clients
        .get_mut(&client)
        .expect("the client's state was created above");
    if idled {
        while cs.h.idle_step(&mut g.maps).is_some() {}
    }
    let idle_ms = t1.elapsed().as_secs_f64() * 1e3;
    if idled {
        g.pacing.on_idle(idle_ms);
    }
    if let Some(m) = cs.h.current_map(&g.maps) {
        cs.growth
            .push((t_ns, m.map.keyframes.len(), m.map.points.len()));
    }
    let feedback = cs.h.feedback(&g.maps);
    let outcome = Outcome {
        client,
        session: kf_session,
        kf_id,
        result,
        idled,
        replay,
        feedback,
        figures: g.figures(client),
        maps: g.sizes(),
        handle_ms,
        idle_ms,
        queued,
        idle_interval: g.pacing.interval(MAX_WITHOUT_IDLE),
    };
    (outcome, gbas)
}

/// Per client `c` of the group: `OUT/keyframes_server_c{c}.txt`, the server poses `T_sk` of
/// the client's keyframes in its current server map (after a merge that map also holds
/// other clients' keyframes, in the same frame); its earlier maps (older sessions, not
/// merged) in `..._m{n}.txt`; `OUT/keyframes_client_c{c}.txt`, the client poses `T_ck` of
/// every keyframe of the current session as received (the client VO's keyframes, for
/// comparison); `OUT/map_growth_c{c}.txt`, the size of its map after each keyframe;
/// `--localize-only`: while the client localises in a frozen map, `keyframes_server_c{c}.txt`
/// holds the poses its keyframes were localised at there, and those of its maps that
/// relocalised there (in `..._localised.txt` once it is in a map of its own again);
/// `OUT/imu_segments_server_c{c}.txt` for a visual-inertial client ([`imu_segments_text`]).
/// (Pose-graph corrections also leave `OUT/correction_{id}_before.txt` / `_after.txt`: the
/// corrected map's keyframes right before and after the correction and its global BA.)
fn write_files(out: Option<&Path>, g: &Group) {
    let Some(out) = out else { return };
    for (c, cs) in &g.clients {
        let mut text = String::from("# t_ns keyframes points (client's current server map)\n");
        for (t, k, p) in &cs.growth {
            text.push_str(&format!("{t} {k} {p}\n"));
        }
        let _ = std::fs::write(out.join(format!("map_growth_c{c}.txt")), text);
        let current = cs.h.current_map_id();
        if let Some(text) = current
            .and_then(|m| g.maps.get(&m))
            .and_then(|m| imu_segments_text(m, *c))
        {
            let _ = std::fs::write(out.join(format!("imu_segments_server_c{c}.txt")), text);
        }
        let in_frozen = current
            .and_then(|m| g.maps.get(&m))
            .is_some_and(|m| m.is_frozen());
        if !cs.localised.is_empty() {
            let name = if in_frozen {
                format!("keyframes_server_c{c}.txt")
            } else {
                format!("keyframes_server_c{c}_localised.txt")
            };
            let mut poses = cs.localised.clone();
            poses.sort_by_key(|p| p.0);
            poses.dedup_by_key(|p| p.0);
            let _ = write_tum(&out.join(name), &poses);
        }
        for (id, m) in &g.maps {
            let mine = |k: &u64| KeyframeId::from_raw(*k).client().raw() == *c;
            let name = if Some(*id) == current && !in_frozen {
                format!("keyframes_server_c{c}.txt")
            } else if id.client().raw() == *c && m.map.keyframes.keys().any(mine) {
                format!("keyframes_server_c{c}_m{}.txt", id.index())
            } else {
                continue;
            };
            let traj: Vec<(i64, Isometry3<f64>)> = m
                .map
                .keyframes
                .iter()
                .filter(|(k, _)| mine(k))
                .map(|(_, kf)| (kf.t_ns, kf.t_cw.inverse()))
                .collect();
            let _ = write_tum(&out.join(name), &traj);
        }
        let _ = write_tum(
            &out.join(format!("keyframes_client_c{c}.txt")),
            &cs.client_kfs,
        );
    }
}

/// The IMU segments of client `c`'s keyframes in server map `m` (issue 19), one line per
/// keyframe in id order: frame time, the segment's start and end on the IMU clock (start -1
/// without a predecessor), its samples, first and last sample times, and 1 when it links the
/// client's keyframe before it in the map (`KeyframeImu::links`). `None` when none of them
/// has a segment (a monocular client).
fn imu_segments_text(m: &slam_core::server::ServerMap, c: u32) -> Option<String> {
    let mut text =
        String::from("# t_ns imu_t0_ns imu_t1_ns samples first_sample_ns last_sample_ns linked\n");
    let mut prev: Option<&slam_core::vo::keyframe_imu::KeyframeImu> = None;
    let mut any = false;
    for (k, kf) in &m.map.keyframes {
        if KeyframeId::from_raw(*k).client().raw() != c {
            continue;
        }
        let Some(seg) = &kf.imu else {
            prev = None;
            continue;
        };
        any = true;
        let first = seg.samples.first().map_or(-1, |s| s.t_ns);
        let last = seg.samples.last().map_or(-1, |s| s.t_ns);
        let linked = prev.is_some_and(|p| seg.links(p));
        text.push_str(&format!(
            "{} {} {} {} {first} {last} {}\n",
            kf.t_ns,
            seg.t_prev_ns.unwrap_or(-1),
            seg.t_ns,
            seg.samples.len(),
            u8::from(linked)
        ));
        prev = Some(seg);
    }
    any.then_some(text)
}

/// Writes a TUM trajectory (`t tx ty tz qx qy qz qw`, t in seconds, nine decimals)
/// atomically ([`datasets::trajectory::write_tum_file`]).
fn write_tum(path: &Path, poses: &[(i64, Isometry3<f64>)]) -> std::io::Result<()> {
    write_tum_file(
        path,
        Some("# t tx ty tz qx qy qz qw (camera-to-map, shoal mapper)"),
        poses.iter().map(|(t, p)| TumRow::from_pose(*t, p)),
        TumDigits::Fixed9,
    )
}
