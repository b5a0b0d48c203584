//! Loop closer service (seed §3.4.2-3.4.3): place recognition over the keyframes of every
//! server map, Sim(3) verification, and the corrections that follow (merge of two maps, or
//! pose graph optimisation within one), which it sends to the mapper.
//!
//! Where things live: a loop keyframe message enters in [`run`] and becomes a
//! [`KeptKeyframe`] ([`keyframe_from_wire`]); detection and the Sim(3) are
//! [`slam_core::loop_closing::LoopDetector::add`]; the pose graph is
//! [`slam_core::pgo::correct_loop`]; the correction leaves as a [`CorrectionHeader`]
//! message ([`Closer::merge`], [`Closer::pose_graph`]).
//!
//! Ownership (DESIGN.md): this service owns the keyframe database and the pose graph; it
//! never touches a map. The mapper owns the maps and applies the corrections. The loop
//! closer keeps its own copy of keyframe poses and moves them with its own corrections.
#![deny(missing_docs)]

pub mod config;
pub mod saved;

pub use config::{LoopCloserConfig, LoopCloserFlags};

use std::collections::{BTreeSet, HashMap};
use std::path::PathBuf;
use std::sync::Arc;
use std::time::{Duration, Instant};

use anyhow::Context;
use iceoryx2::port::publisher::Publisher;
use nalgebra::Vector3;
use serde::{Deserialize, Serialize};
use shm_schema::time::monotonic_ns;
use shm_schema::topics::{self, Ipc};
use shm_schema::{
    CorrectionHeader, CorrectionRecord, LoopKeyframeHeader, LoopKeypointRecord, MsgMeta,
    CORRECTION_MERGE, CORRECTION_POSE_GRAPH, FLAG_INERTIAL_MAP, MAX_LOOP_COVISIBLE,
    RECORD_KEYFRAME_DELTA, RECORD_POINT_PAIR,
};
use shoal_runtime::wire::{
    camera_from_intrinsics, iso_from_wire, valid_intrinsics, wire_from_sim3, wire_keypoint,
};
use shoal_runtime::{ErrorKind, PerClient, ReplayMode, ServiceStart, Status};
use slam_core::features::OrbFeatures;
use slam_core::ids::KeyframeId;
use slam_core::lie::Sim3;
use slam_core::loop_closing::{LoopDetector, LoopDetectorParams, LoopMatch};
use slam_core::pgo::{
    correct_loop, correct_loop_four_dof, yaw, GraphKeyframe, LoopConstraint, LoopGraphParams,
    PgoMethod,
};
use slam_core::place::Vocabulary;
use slam_core::server::{KeptKeyframe, KeptPoint, MapFrame, MapId};

/// The vocabulary shipped with the project (`assets/orb_vocab.bin`), built in.
static SHIPPED_VOCABULARY: &[u8] = include_bytes!("../../../assets/orb_vocab.bin");

/// The loop closer service's command line: the launcher's wiring (status, IPC prefix,
/// replay mode) and the configuration ([`LoopCloserConfig`]: a `--config` file, which the
/// launcher writes, and flags overriding it).
#[derive(Debug, Clone, clap::Parser)]
#[command(name = "loop_closer", about = "Loop closer service")]
pub struct Params {
    /// Status file (JSON).
    #[arg(long)]
    pub status: Option<PathBuf>,
    /// iceoryx2 resource prefix (default: $SHOAL_IPC_PREFIX or "shoal_").
    #[arg(long)]
    pub ipc_prefix: Option<String>,
    /// Replay mode of the run (the launcher passes it). In lock-step the loop closer tells
    /// the mapper when it has finished each loop keyframe ([`shm_schema::CORRECTION_DONE`],
    /// after any correction it found; unless `lockstep_sync = false`), so corrections land
    /// at the same point of the keyframe stream on every run.
    #[arg(long, default_value = "realtime")]
    pub mode: ReplayMode,
    /// A saved-map file whose keyframes are inserted before the first live one
    /// ([`saved::load`]; the launcher has checked it).
    #[arg(long)]
    pub load_map: Option<PathBuf>,
    /// Localise in the loaded maps without adding to them: they are frozen, and a live map
    /// that matches one relocalises in it ([`Closer::freeze`]).
    #[arg(long)]
    pub localize_only: bool,
    /// Configuration file (TOML, the keys of `[loop_closer]` in `shoal config --print`).
    #[arg(long)]
    pub config: Option<PathBuf>,
    /// Options overriding the configuration file.
    #[command(flatten)]
    pub options: LoopCloserFlags,
}

impl Params {
    /// The configuration: the `--config` file (else the defaults), the flags over it, and
    /// `SHOAL_DEBUG_LOOP` (set: `debug_loop = true`).
    pub fn config(&self) -> Result<LoopCloserConfig, shoal_runtime::config::ConfigError> {
        shoal_runtime::config::resolve(self.config.as_ref(), |c: &mut LoopCloserConfig| {
            self.options.apply(c);
            c.debug_loop |= std::env::var_os("SHOAL_DEBUG_LOOP").is_some();
        })
    }
}

/// The service's name in reports.
pub const SERVICE_NAME: &str = "loop_closer";

/// Counters and gauges of the loop closer (the status file's `counters`, per client
/// `c{i}.{name}`), carried on over restarts. The loop closer has no crash-recovery state in
/// its status file: a restarted loop closer rebuilds its keyframe database from the mapper
/// (resynchronisation).
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct LoopCloserCounters {
    /// Loops found within one map.
    pub loops: u64,
    /// Loops found between two maps (merges).
    pub merges: u64,
    /// Of `loops`, those corrected by the 4-DoF pose graph (a metric, gravity-aligned map).
    pub loops_four_dof: u64,
    /// Of `merges`, those of two metric, gravity-aligned maps (yaw and translation only).
    pub merges_four_dof: u64,
    /// Corrections sent to the mapper.
    pub corrections_sent: u64,
    /// Time spent in loop detection, µs.
    pub detect_us: u64,
    /// Gauge: keyframes in the database.
    pub database_keyframes: u64,
    /// Keyframes the mapper re-sent to this start (resynchronisation).
    pub resync_keyframes: u64,
    /// Per client (`c{i}.{name}`).
    #[serde(flatten)]
    pub clients: PerClient<LoopCloserClientCounters>,
}

/// Counters of one client at the loop closer.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct LoopCloserClientCounters {
    /// Live loop keyframes received (resynchronisation not counted).
    pub keyframes_received: u64,
}

impl LoopCloserCounters {
    /// Client `c`'s counters (zeros when nothing was counted for it).
    pub fn client(&self, c: u32) -> LoopCloserClientCounters {
        self.clients.get(c).cloned().unwrap_or_default()
    }
}

/// Runs the service; returns the process exit code.
pub fn main_with(params: Params) -> i32 {
    shoal_runtime::exit_code(SERVICE_NAME, run(&params))
}

/// Converts a loop keyframe message into the detector's input. Errors (with a reason) on an
/// unusable message: record count not matching the header, a non-finite pose or point, bad
/// intrinsics.
pub fn keyframe_from_wire(
    h: &LoopKeyframeHeader,
    records: &[LoopKeypointRecord],
) -> Result<KeptKeyframe, String> {
    if h.n_keypoints as usize != records.len() {
        return Err(format!(
            "loop keyframe {:#x}: header says {} keypoints, payload holds {}",
            h.kf_id,
            h.n_keypoints,
            records.len()
        ));
    }
    let t_sk = iso_from_wire(&h.pose_sk)
        .ok_or_else(|| format!("loop keyframe {:#x}: invalid pose", h.kf_id))?;
    if !valid_intrinsics(&h.intrinsics, h.width) {
        return Err(format!("loop keyframe {:#x}: invalid intrinsics", h.kf_id));
    }
    let camera = camera_from_intrinsics(&h.intrinsics, h.width, h.height);
    // Octaves only on the wire: the default pyramid scale (`ORB_SCALE_FACTOR`) applies.
    let mut features = OrbFeatures::with_capacity(records.len());
    let mut points = Vec::new();
    for (i, r) in records.iter().enumerate() {
        features
            .keypoints
            .push(wire_keypoint(r.u, r.v, r.angle, r.response, r.octave));
        features.descriptors.push(r.descriptor);
        if r.has_point != 0 {
            let p_k = Vector3::new(r.p_k[0], r.p_k[1], r.p_k[2]);
            if !p_k.iter().all(|v| v.is_finite()) {
                return Err(format!(
                    "loop keyframe {:#x}: keypoint {i}: non-finite point",
                    h.kf_id
                ));
            }
            points.push(KeptPoint {
                keypoint: i as u32,
                point: r.point_id,
                p_k,
            });
        }
    }
    let n = (h.n_covisible as usize).min(MAX_LOOP_COVISIBLE);
    let covisible = h.covisible_ids[..n]
        .iter()
        .copied()
        .zip(h.covisible_weights[..n].iter().copied())
        .collect();
    Ok(KeptKeyframe {
        map_id: MapId::from_raw(h.map_id),
        kf_id: h.kf_id,
        client_kf_id: h.client_kf_id,
        t_ns: h.t_ns,
        t_sk,
        camera,
        features,
        points,
        covisible,
        frame: if h.meta.flags & FLAG_INERTIAL_MAP != 0 {
            MapFrame::INERTIAL
        } else {
            MapFrame::VISUAL
        },
    })
}

/// The loop closer's state: the detector (keyframe database and stored keyframes), the
/// loop constraints per map, and the correction counter.
pub struct Closer {
    detector: LoopDetector,
    loops: HashMap<MapId, Vec<LoopConstraint>>,
    graph: LoopGraphParams,
    next_id: u64,
    /// Print every query's statistics on stderr.
    debug_queries: bool,
    /// Maps frozen by `--localize-only` (the loaded ones): a live map that matches one
    /// relocalises in it; they never move.
    frozen: BTreeSet<MapId>,
}

/// A correction ready to send.
#[derive(Debug, Clone)]
pub struct Outgoing {
    /// Header.
    pub header: CorrectionHeader,
    /// Records.
    pub records: Vec<CorrectionRecord>,
    /// One-line summary for the log.
    pub summary: String,
    /// The correction has 4 degrees of freedom (x, y, z, yaw): metric, gravity-aligned maps.
    pub four_dof: bool,
}

impl Closer {
    /// A loop closer over `vocabulary` with pose-graph `method`.
    pub fn new(vocabulary: Vocabulary, method: PgoMethod) -> Self {
        Self {
            detector: LoopDetector::new(Arc::new(vocabulary), LoopDetectorParams::default()),
            loops: HashMap::new(),
            graph: LoopGraphParams {
                method,
                ..LoopGraphParams::default()
            },
            next_id: 1,
            debug_queries: false,
            frozen: BTreeSet::new(),
        }
    }

    /// Every query's statistics go to stderr (`debug_loop`).
    pub fn set_debug_queries(&mut self, on: bool) {
        self.debug_queries = on;
    }

    /// Keyframes stored.
    pub fn keyframes(&self) -> usize {
        self.detector.len()
    }

    /// Stores a keyframe re-sent by the mapper after a restart (no loop search).
    pub fn insert(&mut self, kf: KeptKeyframe) {
        self.detector.insert(kf);
    }

    /// Stores a keyframe of a saved map with its BoW and feature vectors (no loop search).
    pub fn insert_with_vectors(
        &mut self,
        kf: KeptKeyframe,
        bow: slam_core::place::BowVector,
        fv: slam_core::place::FeatureVector,
    ) {
        self.detector.insert_with_vectors(kf, bow, fv);
    }

    /// The detector's feature-vector level ([`LoopDetectorParams::feature_level`]).
    pub fn feature_level(&self) -> Option<usize> {
        self.detector.params().feature_level
    }

    /// Adds a keyframe: a verified loop gives the correction to send. With
    /// [`Closer::set_debug_queries`], every query's statistics go to stderr.
    pub fn add(&mut self, kf: KeptKeyframe) -> Result<Option<Outgoing>, String> {
        let client = KeyframeId::from_raw(kf.kf_id).client().raw();
        let (q_points, q_covis) = (kf.points.len(), kf.covisible.len());
        let found = self.detector.add(kf);
        if self.debug_queries {
            eprintln!(
                "loop_closer: query {:?} ({} points, {} covisible)",
                self.detector.last_query(),
                q_points,
                q_covis
            );
            let d = self.detector.last_detail();
            let top: Vec<String> = (d.candidates.iter().take(8))
                .map(|(c, m, s)| format!("{c:#x}@{:#x}:{s:.3}", m.raw()))
                .collect();
            eprintln!("loop_closer:   candidates [{}]", top.join(" "));
            for (c, why) in &d.rejected {
                eprintln!("loop_closer:   rejected {c:#x}: {why:?}");
            }
        }
        let Some(m) = found else {
            return Ok(None);
        };
        if self.frozen.contains(&m.query_map) {
            return Err(format!(
                "loop {:#x}-{:#x}: map {:#x} is frozen (--localize-only)",
                m.query, m.matched, m.query_map
            ));
        }
        if m.query_map != m.matched_map {
            Ok(Some(self.merge(client, &m)?))
        } else {
            Ok(Some(self.pose_graph(client, &m)?))
        }
    }

    fn header(&mut self, client: u32, kind: u32, m: &LoopMatch, s: &Sim3) -> CorrectionHeader {
        let (sim3, scale) = wire_from_sim3(s);
        let id = self.next_id;
        self.next_id += 1;
        CorrectionHeader {
            meta: MsgMeta::new(client, 0, id, monotonic_ns()),
            correction_id: id,
            kind,
            query_kf: m.query,
            matched_kf: m.matched,
            from_map: m.query_map.raw(),
            into_map: m.matched_map.raw(),
            sim3,
            scale,
            inliers: m.inliers as u32,
            ..CorrectionHeader::default()
        }
    }

    fn pairs(m: &LoopMatch) -> Vec<CorrectionRecord> {
        m.point_pairs
            .iter()
            .map(|(a, b)| CorrectionRecord {
                kind: RECORD_POINT_PAIR,
                a: *a,
                b: *b,
                ..CorrectionRecord::default()
            })
            .collect()
    }

    /// The query's map joins the matched keyframe's map (seed §3.4.2): with `T_Qq`, `T_Mm`
    /// the two keyframes' poses in their maps and `S_qm` the loop similarity,
    /// `S_MQ = T_Mm S_qm⁻¹ T_Qq⁻¹` takes the query map into the matched one.
    pub fn merge(&mut self, client: u32, m: &LoopMatch) -> Result<Outgoing, String> {
        let (Some(q), Some(mk)) = (
            self.detector.keyframe(m.query),
            self.detector.keyframe(m.matched),
        ) else {
            return Err(format!(
                "loop {:#x}-{:#x}: keyframe not stored",
                m.query, m.matched
            ));
        };
        let t_qq = Sim3::from_isometry(&q.t_sk, 1.0);
        let t_mm = Sim3::from_isometry(&mk.t_sk, 1.0);
        let c_q = q.t_sk.translation.vector;
        let s_mq = t_mm.compose(&m.s_qm.inverse()).compose(&t_qq.inverse());
        let (q_inertial, m_inertial) = (
            self.map_is_inertial(m.query_map),
            self.map_is_inertial(m.matched_map),
        );
        // `VI_NOTES.md` §4 "Loops and merges": two metric, gravity-aligned maps differ by
        // x, y, z and yaw; a visual map joins an inertial one by a similarity, and it is the
        // visual map that moves, so the merged map stays metric and gravity-aligned.
        // A frozen map (`--localize-only`) never moves: the query's map relocalises in it.
        let frozen = self.frozen.contains(&m.matched_map);
        let (from, into, s, dof) = match (q_inertial, m_inertial) {
            (true, true) => (m.query_map, m.matched_map, four_dof(&s_mq, &c_q), "4-DoF"),
            (true, false) if !frozen => (m.matched_map, m.query_map, s_mq.inverse(), "Sim(3)"),
            _ => (m.query_map, m.matched_map, s_mq, "Sim(3)"),
        };
        let mut header = self.header(client, CORRECTION_MERGE, m, &s);
        header.from_map = from.raw();
        header.into_map = into.raw();
        let records = Self::pairs(m);
        header.n_records = records.len() as u32;
        self.detector.rename_map(from, into, &s);
        let mut moved = self.loops.remove(&from).unwrap_or_default();
        moved.push(LoopConstraint {
            query: m.query,
            matched: m.matched,
            s_qm: m.s_qm,
        });
        self.loops.entry(into).or_default().extend(moved);
        Ok(Outgoing {
            summary: format!(
                "merge ({dof}): keyframe {:#x} (map {:#x}) matches {:#x} (map {:#x}), {} inliers, \
                 loop scale {:.4}; map {from:#x} into {into:#x}",
                m.query, m.query_map, m.matched, m.matched_map, m.inliers, s_mq.s
            ),
            header,
            records,
            four_dof: q_inertial && m_inertial,
        })
    }

    /// Freezes map `map` (`--localize-only`): see [`Closer::merge`].
    pub fn freeze(&mut self, map: MapId) {
        self.frozen.insert(map);
    }

    /// Whether map `map` is metric and gravity-aligned (one of its keyframes says so: a
    /// visual map merged into an inertial one keeps its keyframes' old flags).
    fn map_is_inertial(&self, map: MapId) -> bool {
        self.detector
            .keyframes_of_map(map)
            .any(|k| k.frame.is_inertial())
    }

    /// A loop within one map: the pose graph of the map's keyframes (as this service knows
    /// them) with every loop found in it, the matched keyframe fixed (seed §3.4.3).
    pub fn pose_graph(&mut self, client: u32, m: &LoopMatch) -> Result<Outgoing, String> {
        let map = m.query_map;
        let list = self.loops.entry(map).or_default();
        list.push(LoopConstraint {
            query: m.query,
            matched: m.matched,
            s_qm: m.s_qm,
        });
        let loops = list.clone();
        let kfs: Vec<GraphKeyframe> = self
            .detector
            .keyframes_of_map(map)
            .map(|k| GraphKeyframe {
                id: k.kf_id,
                t_wk: k.t_sk,
                covisible: self
                    .detector
                    .covisible(k.kf_id)
                    .map(<[_]>::to_vec)
                    .unwrap_or_default(),
            })
            .collect();
        let t0 = Instant::now();
        let inertial = self.map_is_inertial(map);
        let correct = if inertial {
            correct_loop_four_dof
        } else {
            correct_loop
        };
        let c = match correct(&kfs, &loops, m.matched, &self.graph) {
            Ok(c) if c.report.final_cost <= c.report.initial_cost => c,
            Ok(c) => {
                // The optimiser made the graph worse: the loop contradicts the map (or the
                // solve failed); sending it would damage the map.
                self.loops.entry(map).or_default().pop();
                return Err(format!(
                    "loop {:#x}-{:#x} (scale {:.4}) refused: pose graph cost {:.3e} -> {:.3e}",
                    m.query, m.matched, m.s_qm.s, c.report.initial_cost, c.report.final_cost
                ));
            }
            Err(e) => {
                self.loops.entry(map).or_default().pop();
                return Err(e.to_string());
            }
        };
        let ms = t0.elapsed().as_secs_f64() * 1e3;
        let fallback = c.deltas.get(&m.query).copied().unwrap_or_default();
        let mut header = self.header(client, CORRECTION_POSE_GRAPH, m, &fallback);
        let mut records: Vec<CorrectionRecord> = c
            .deltas
            .iter()
            .map(|(k, d)| {
                let (delta, scale) = wire_from_sim3(d);
                CorrectionRecord {
                    kind: RECORD_KEYFRAME_DELTA,
                    a: *k,
                    delta,
                    scale,
                    ..CorrectionRecord::default()
                }
            })
            .collect();
        records.extend(Self::pairs(m));
        header.n_records = records.len() as u32;
        for (k, d) in &c.deltas {
            self.detector.apply_correction(*k, d);
        }
        Ok(Outgoing {
            summary: format!(
                "loop: keyframe {:#x} matches {:#x} in map {map:#x}, {} inliers, scale {:.4}; {} pose graph of {} keyframes, {} + {} edges, cost {:.3e} -> {:.3e}, {} iterations, {ms:.1} ms",
                m.query,
                m.matched,
                m.inliers,
                m.s_qm.s,
                if inertial { "4-DoF" } else { "Sim(3)" },
                kfs.len(),
                c.edges.0,
                c.edges.1,
                c.report.initial_cost,
                c.report.final_cost,
                c.report.iterations
            ),
            header,
            records,
            four_dof: inertial,
        })
    }
}

/// The 4-DoF part of a map-to-map similarity `s` between two metric, gravity-aligned maps
/// (`VI_NOTES.md` §4): scale 1, its rotation's yaw only, and the translation that takes
/// `c` (the query keyframe's centre) where `s` takes it.
fn four_dof(s: &Sim3, c: &nalgebra::Vector3<f64>) -> Sim3 {
    let r = nalgebra::UnitQuaternion::from_axis_angle(
        &nalgebra::Vector3::z_axis(),
        yaw(&s.r.to_rotation_matrix()),
    );
    Sim3::new(r, s.transform_point(c) - r * c, 1.0)
}

/// Keyframes asked of the mapper per resynchronisation batch (fewer than the loop
/// keyframe topic's buffer, so a batch never overflows it).
const RESYNC_BATCH: u32 = 32;

/// A message the loop closer publishes.
#[derive(Debug, Clone)]
pub enum Out {
    /// A correction (or, in lock-step, a [`shm_schema::CORRECTION_DONE`] marker) to the
    /// mapper.
    Correction(Outgoing),
    /// A request for a batch of the mapper's keyframes (resynchronisation).
    Resync(shm_schema::ResyncRequest),
}

/// Rebuilding the keyframe database from the mapper at start-up (DESIGN.md: a restarted
/// loop closer resynchronises from the mapper): batches of [`RESYNC_BATCH`] keyframes are
/// asked for until the mapper's end marker; a request without progress is repeated.
struct Resync {
    received: u64,
    asked: u64,
    asked_at_ns: i64,
    seq: u64,
    done: bool,
}

impl Resync {
    fn ask(&mut self, next: u64, now_ns: i64) -> Out {
        let req = shm_schema::ResyncRequest {
            meta: MsgMeta::new(0, 0, self.seq, now_ns),
            next,
            max: RESYNC_BATCH,
            reserved: 0,
        };
        self.seq += 1;
        self.asked = next;
        self.asked_at_ns = now_ns;
        Out::Resync(req)
    }
}

/// The loop closer without its ports: loop keyframe messages in ([`LoopCloserCore::on_keyframe`]),
/// corrections, lock-step markers and resync requests out ([`Out`]).
pub struct LoopCloserCore {
    closer: Closer,
    resync: Resync,
    /// Lock-step synchronisation with the mapper.
    sync: bool,
    detect_only: bool,
    /// Errors (the counters are put in by [`LoopCloserCore::status_now`]).
    pub status: Status,
    /// The counters, carried on from a killed predecessor.
    pub counters: LoopCloserCounters,
}

impl LoopCloserCore {
    /// A core resuming `status`; its first outputs (a resync request, unless this is the
    /// first start of a lock-step run) are in the returned list.
    pub fn new(
        closer: Closer,
        params: &Params,
        cfg: &LoopCloserConfig,
        status: Status,
        now_ns: i64,
    ) -> (Self, Vec<Out>) {
        let sync = params.mode == ReplayMode::Lockstep && cfg.lockstep_sync;
        let mut core = Self {
            closer,
            resync: Resync {
                received: 0,
                asked: 0,
                asked_at_ns: now_ns,
                seq: 0,
                done: false,
            },
            sync,
            detect_only: cfg.detect_only,
            counters: status.counters_as(),
            status,
        };
        let mut out = vec![];
        if sync && core.status.starts == 1 {
            // Lock-step, first start of the run: the maps are empty (the launcher starts the
            // mapper and loop closer before any tracker), nothing to resynchronise. Asking
            // anyway races with the mapper's start (a lost request is repeated 2 s later and
            // then re-sends keyframes already forwarded live), which would make runs differ.
            core.resync.done = true;
        } else {
            out.push(core.resync.ask(0, now_ns));
        }
        (core, out)
    }

    /// The status as of now (the counters put in), to write.
    pub fn status_now(&mut self) -> &Status {
        self.status.put_counters(&self.counters);
        &self.status
    }

    /// Periodic work: a resynchronisation without progress for 2 s (mapper not up yet, or
    /// a lost batch) is asked again from where it is.
    pub fn on_tick(&mut self, now_ns: i64) -> Vec<Out> {
        let r = &mut self.resync;
        if !r.done && now_ns - r.asked_at_ns > 2_000_000_000 {
            let next = r.received;
            return vec![r.ask(next, now_ns)];
        }
        vec![]
    }

    /// One loop keyframe message of the mapper (live, or of a resynchronisation).
    pub fn on_keyframe(
        &mut self,
        h: &LoopKeyframeHeader,
        records: &[LoopKeypointRecord],
        now_ns: i64,
    ) -> Vec<Out> {
        if let Err(e) = h.meta.check() {
            let detail = format!("loop keyframe: {e}");
            self.status.error(ErrorKind::SchemaVersion, detail);
            return vec![];
        }
        if h.meta.flags & shm_schema::FLAG_RESYNC != 0 {
            return self.on_resync_keyframe(h, records, now_ns);
        }
        let c = h.meta.client_id;
        self.counters.clients.of(c).keyframes_received += 1;
        let mut out = vec![];
        match keyframe_from_wire(h, records) {
            Ok(kf) => self.search(kf, &mut out),
            Err(e) => self.status.error(ErrorKind::BadKeyframe, e),
        }
        if self.sync {
            out.push(Out::Correction(done_marker(h, now_ns)));
        }
        out
    }

    fn on_resync_keyframe(
        &mut self,
        h: &LoopKeyframeHeader,
        records: &[LoopKeypointRecord],
        now_ns: i64,
    ) -> Vec<Out> {
        let r = &mut self.resync;
        if r.done {
            return vec![];
        }
        if h.meta.flags & shm_schema::FLAG_END_OF_STREAM != 0 {
            r.done = true;
            self.counters.resync_keyframes = r.received;
            return vec![];
        }
        match keyframe_from_wire(h, records) {
            Ok(kf) => self.closer.insert(kf),
            Err(e) => self
                .status
                .error(ErrorKind::BadKeyframe, format!("resync: {e}")),
        }
        let r = &mut self.resync;
        r.received += 1;
        if r.received >= r.asked + u64::from(RESYNC_BATCH) {
            let next = r.received;
            return vec![r.ask(next, now_ns)];
        }
        vec![]
    }

    /// Searches a loop for a live keyframe; a verified one gives a correction.
    fn search(&mut self, kf: KeptKeyframe, out: &mut Vec<Out>) {
        let t0 = Instant::now();
        let result = self.closer.add(kf);
        let (s, n) = (&mut self.status, &mut self.counters);
        n.detect_us += t0.elapsed().as_micros() as u64;
        n.database_keyframes = self.closer.keyframes() as u64;
        let c = match result {
            Ok(None) => return,
            Ok(Some(c)) => c,
            Err(e) => return s.error(ErrorKind::Loop, e),
        };
        if c.header.kind == CORRECTION_MERGE {
            n.merges += 1;
            n.merges_four_dof += u64::from(c.four_dof);
        } else {
            n.loops += 1;
            n.loops_four_dof += u64::from(c.four_dof);
        }
        eprintln!("loop_closer: {}", c.summary);
        if self.detect_only {
            return;
        }
        if c.records.len() > topics::MAX_CORRECTION_RECORDS {
            let detail = format!("{} records exceed the message", c.records.len());
            s.error(ErrorKind::Correction, detail);
        } else {
            out.push(Out::Correction(c));
            n.corrections_sent += 1;
        }
    }
}

/// Lock-step: loop keyframe message `h` is finished (a [`shm_schema::CORRECTION_DONE`]
/// marker on the corrections topic, behind any correction).
fn done_marker(h: &LoopKeyframeHeader, now_ns: i64) -> Outgoing {
    Outgoing {
        header: CorrectionHeader {
            meta: MsgMeta::new(h.meta.client_id, 0, h.meta.seq, now_ns),
            kind: shm_schema::CORRECTION_DONE,
            query_kf: h.kf_id,
            ..CorrectionHeader::default()
        },
        records: Vec::new(),
        summary: String::new(),
        four_dof: false,
    }
}

/// Publishes the core's outputs, in order.
fn publish(
    corrections: &Publisher<Ipc, [CorrectionRecord], CorrectionHeader>,
    resync: &Publisher<Ipc, shm_schema::ResyncRequest, ()>,
    out: Vec<Out>,
) -> anyhow::Result<()> {
    for o in out {
        match o {
            Out::Correction(c) => {
                let sample = corrections.loan_slice_uninit(c.records.len())?;
                let mut sample = sample.write_from_slice(&c.records);
                *sample.user_header_mut() = c.header;
                sample.send()?;
            }
            Out::Resync(r) => {
                resync.send_copy(r)?;
            }
        }
    }
    Ok(())
}

/// The configured vocabulary, else the shipped one.
pub fn vocabulary(cfg: &LoopCloserConfig) -> anyhow::Result<Vocabulary> {
    Ok(match &cfg.vocabulary {
        Some(p) => Vocabulary::load(p)
            .with_context(|| format!("loading the vocabulary {}", p.display()))?,
        None => Vocabulary::from_bytes(SHIPPED_VOCABULARY)
            .context("the built-in vocabulary is corrupt")?,
    })
}

/// Receives keyframes until SIGINT/SIGTERM; detects loops and sends corrections.
pub fn run(params: &Params) -> anyhow::Result<Status> {
    let cfg = params.config()?;
    let mut closer = Closer::new(vocabulary(&cfg)?, cfg.method);
    closer.set_debug_queries(cfg.debug_loop);
    let loaded = (params.load_map.as_deref())
        .map(|path| {
            let vocabulary_id = saved::vocabulary_id(&cfg);
            saved::load(&mut closer, path, vocabulary_id, params.localize_only)
        })
        .transpose()?;
    let mut start = ServiceStart::open(
        SERVICE_NAME,
        "loop_closer",
        params.status.clone(),
        params.ipc_prefix.clone(),
    )?;
    let node = &start.node;
    let keyframes = topics::slice_subscriber(
        &topics::loop_keyframes_service(node)?,
        topics::KEYFRAME_BUFFER,
    )?;
    let corrections = topics::slice_publisher(
        &topics::corrections_service(node)?,
        topics::MAX_CORRECTION_RECORDS,
    )?;
    let resync = topics::publisher(&topics::resync_service(node)?)?;
    let status = std::mem::take(&mut start.status);
    let (mut core, out) = LoopCloserCore::new(closer, params, &cfg, status, monotonic_ns());
    if let Some(l) = loaded {
        core.status
            .set_value("map_loaded_keyframes", l.keyframes as f64);
        core.status.set_value("map_load_ms", l.ms);
        let from_file = f64::from(u8::from(l.vectors_from_file));
        core.status
            .set_value("map_loaded_vectors_from_file", from_file);
    }
    publish(&corrections, &resync, out)?;
    shoal_runtime::signal_ready();
    loop {
        publish(&corrections, &resync, core.on_tick(monotonic_ns()))?;
        let mut idle = true;
        while let Some(msg) = keyframes.receive()? {
            idle = false;
            let out = core.on_keyframe(msg.user_header(), msg.payload(), monotonic_ns());
            drop(msg);
            publish(&corrections, &resync, out)?;
        }
        if start.file.due(Duration::from_millis(200)) {
            let _ = start.file.write(core.status_now());
        }
        if idle && node.wait(Duration::from_millis(1)).is_err() {
            break;
        }
    }
    core.status.finished = true;
    start.file.write(core.status_now())?;
    Ok(core.status)
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::{UnitQuaternion, Vector3};

    /// Between two metric, gravity-aligned maps a merge keeps only yaw and translation of
    /// the loop's similarity, and takes the query keyframe's centre where it took it.
    #[test]
    fn a_merge_of_inertial_maps_is_four_dof() {
        let r = UnitQuaternion::from_euler_angles(0.02, -0.01, 0.7);
        let s = Sim3::new(r, Vector3::new(1.0, -2.0, 0.5), 1.03);
        let c = Vector3::new(3.0, 4.0, 1.5);
        let f = four_dof(&s, &c);
        assert_eq!(f.s, 1.0);
        let axis = f.r.axis().map_or(Vector3::z(), |a| a.into_inner());
        assert!((axis - Vector3::z()).norm() < 1e-12, "{axis}");
        assert!((f.r.angle() - 0.7).abs() < 1e-3, "{}", f.r.angle());
        assert!((f.transform_point(&c) - s.transform_point(&c)).norm() < 1e-12);
    }

    /// A loop keyframe message flagged `FLAG_INERTIAL_MAP` is of a metric, gravity-aligned
    /// map; without the flag, of a visual one.
    #[test]
    fn the_map_frame_comes_from_the_loop_keyframe_flag() {
        let mut h = LoopKeyframeHeader {
            pose_sk: shoal_runtime::wire::wire_from_iso(&nalgebra::Isometry3::identity()),
            width: 640,
            height: 480,
            ..LoopKeyframeHeader::default()
        };
        h.intrinsics.pinhole = [500.0, 500.0, 320.0, 240.0];
        let visual = keyframe_from_wire(&h, &[]).expect("valid message");
        assert_eq!(visual.frame, MapFrame::VISUAL);
        h.meta.flags |= FLAG_INERTIAL_MAP;
        let inertial = keyframe_from_wire(&h, &[]).expect("valid message");
        assert_eq!(inertial.frame, MapFrame::INERTIAL);
    }

    /// The counters keep the names report.json and its readers know (`loops`, `merges`,
    /// `c0.keyframes_received`, ...) and come back whole from the status file.
    #[test]
    fn counter_names_in_the_status_file() {
        let mut c = LoopCloserCounters {
            merges: 1,
            resync_keyframes: 4,
            ..LoopCloserCounters::default()
        };
        c.clients.of(1).keyframes_received = 9;
        let mut s = Status::new(SERVICE_NAME);
        s.put_counters(&c);
        for k in [
            "loops",
            "merges",
            "resync_keyframes",
            "c1.keyframes_received",
        ] {
            assert!(s.counters.contains_key(k), "{k}: {:?}", s.counters);
        }
        let text = serde_json::to_string(&s).unwrap();
        let back: Status = serde_json::from_str(&text).unwrap();
        assert_eq!(back.counters_as::<LoopCloserCounters>(), c);
        assert_eq!(c.client(1).keyframes_received, 9);
        assert_eq!(c.client(0).keyframes_received, 0);
    }
}
