//! Tracker service of one client: where frames are consumed and poses leave.
//!
//! It takes every frame from shared memory in place (the VO reads the pixels inside the
//! sample, no copy), checks its schema version and sequence number (gaps = frames dropped
//! upstream), runs the client VO of `slam_core::vo` (seed §3.3) on it, acknowledges it
//! (lock-step pacing) and publishes one [`TrackedPose`] per frame (pose, state, latency
//! stamps, per-stage timings). Keyframes leaving the client map are sent to the mapper and
//! kept in an [`outbox::Outbox`] until acknowledged. It drains and checks the IMU stream and
//! keeps its counters in a status file.
//!
//! Rolling shutter: when the IMU stream is live, the mean gyro rate over each frame's readout
//! ([`imu::ImuInput::camera_rate`]) rotates every keypoint to the mid-row time; without it
//! the VO uses its motion model. The frames seen while the VO initialises get their poses
//! once the map exists; they are published afterwards flagged [`FLAG_BACKFILL`].
//!
//! With `--frame-log` it writes, per frame, sequence number, dataset index,
//! timestamps, size and an FNV-1a checksum of the pixels it read from shared memory (and per
//! IMU sample its time), which the end-to-end tests compare with the dataset.
#![deny(missing_docs)]

use std::io::Write;
use std::path::PathBuf;
use std::time::Duration;

use anyhow::Context;
use shm_schema::time::monotonic_ns;
use shm_schema::topics;
use shm_schema::{
    stage, FrameAck, MsgMeta, Pose, TrackState, TrackedPose, FLAG_BACKFILL, FLAG_END_OF_STREAM,
};
use shoal_runtime::{ReplayMode, Status, StatusFile};
use slam_core::features::GrayImage;
use slam_core::vo::{VoFrame, VoOutput, VoParams, VoState, VoTracker};

/// Keyframe ids of one life of the tracker process: `start << KF_ID_BITS_PER_START` on
/// (2^28 keyframes per life, 4096 lives within the server's 40-bit client keyframe ids).
const KF_ID_BITS_PER_START: u32 = 28;

fn new_vo(params: &Params, h: &shm_schema::FrameHeader) -> anyhow::Result<VoTracker> {
    let camera = shoal_runtime::camera_from_intrinsics(&h.intrinsics, h.width, h.height);
    let mut vp = VoParams {
        rolling_shutter: !params.no_rs,
        window: params.window.max(2),
        local_mapping_thread: !params.inline_mapping,
        sync_local_mapping: params.lockstep_sync(),
        ..VoParams::default()
    };
    vp.orb.n_features = params.features;
    Ok(VoTracker::new(vp, camera)?)
}

fn run_vo(
    vo: &mut VoTracker,
    pixels: &[u8],
    h: &shm_schema::FrameHeader,
    angular_velocity: Option<nalgebra::Vector3<f64>>,
) -> anyhow::Result<VoOutput> {
    let image = GrayImage::new(
        pixels,
        h.width as usize,
        h.height as usize,
        h.stride as usize,
    )?;
    Ok(vo.process(&VoFrame {
        image,
        t_ns: h.t_mid_ns,
        readout_ns: h.readout_ns,
        angular_velocity,
    })?)
}

/// The last usable pose feedback: keyframe `j`'s client pose as sent, its server pose and
/// the scale ratio (seed eq. 3.1, 3.4), for frames of the same VO session.
struct ServerRef {
    session: u32,
    map_id: u64,
    t_cj: nalgebra::Isometry3<f64>,
    t_sj: nalgebra::Isometry3<f64>,
    lambda: f64,
}

impl ServerRef {
    /// From a feedback message with a pose, if the keyframe is one this tracker sent and
    /// the values are valid.
    fn from_feedback(f: &shm_schema::Feedback, outbox: &outbox::Outbox) -> Option<Self> {
        let t_cj = outbox.sent_pose(f.acked_session_id, f.acked_keyframe_id)?;
        let p = &f.server_pose;
        let finite = p.t.iter().chain(p.q.iter()).all(|v| v.is_finite());
        if !(finite && f.scale_ratio.is_finite() && f.scale_ratio > 0.0) {
            return None;
        }
        let q = nalgebra::Quaternion::new(p.q[3], p.q[0], p.q[1], p.q[2]);
        if q.norm() < 1e-6 {
            return None;
        }
        let t_sj = nalgebra::Isometry3::from_parts(
            nalgebra::Translation3::new(p.t[0], p.t[1], p.t[2]),
            nalgebra::UnitQuaternion::from_quaternion(q),
        );
        Some(Self {
            session: f.acked_session_id,
            map_id: f.server_map_id,
            t_cj,
            t_sj,
            lambda: f.scale_ratio,
        })
    }

    /// The server-map pose (wire, camera → server map) of a frame with client pose `t_cf`.
    fn frame_pose(&self, t_cf: &nalgebra::Isometry3<f64>) -> Pose {
        shoal_runtime::wire::wire_from_iso(&slam_core::server::frame_pose_in_server_map(
            &self.t_cj,
            &self.t_sj,
            self.lambda,
            t_cf,
        ))
    }
}

/// The keyframe counters of the status file, kept current: a SIGKILLed tracker must leave
/// exact figures behind (keyframes are few, so the status is written whenever one is sent or
/// acknowledged). Counters carry on from the previous start; the keyframes a killed tracker
/// had sent without seeing their acknowledgement are counted as `keyframes_unacked_at_crash`
/// by its successor (the mapper applied them; their acknowledgements went to a dead process),
/// so that `keyframes_acked_seen + keyframes_unacked_at_crash == keyframes_sent`.
struct KeyframeCounts {
    sent_base: u64,
    resent_base: u64,
    acked_base: u64,
    written: (u64, u64, u64),
}

impl KeyframeCounts {
    fn resume(status: &mut Status) -> Self {
        let unacked = status.values.remove("keyframes_unacked").unwrap_or(0.0) as u64;
        let queued = status.values.remove("keyframes_queued").unwrap_or(0.0) as u64;
        if status.starts > 1 {
            status.add("keyframes_unacked_at_crash", unacked);
            // Queued behind the in-flight limit, never sent: lost with the process (as are
            // the keyframes still in its VO window).
            status.add("keyframes_unsent_at_crash", queued);
        }
        Self {
            sent_base: status.get("keyframes_sent"),
            resent_base: status.get("keyframes_resent"),
            acked_base: status.get("keyframes_acked_seen"),
            written: (0, 0, 0),
        }
    }

    /// Puts the outbox's counts into `status`.
    fn set(&self, outbox: &outbox::Outbox, status: &mut Status) {
        let mut put = |k: &str, v: u64| {
            status.counters.insert(k.to_string(), v);
        };
        put("keyframes_sent", self.sent_base + outbox.sent);
        put("keyframes_resent", self.resent_base + outbox.resent);
        put("keyframes_acked_seen", self.acked_base + outbox.acked);
        let in_flight = outbox.in_flight();
        status.set_value("keyframes_unacked", in_flight as f64);
        status.set_value("keyframes_queued", (outbox.pending() - in_flight) as f64);
    }

    /// Writes the status now if a keyframe was sent, re-sent or acknowledged since the last
    /// call (a failed write is retried at the next change or periodic write).
    fn sync(&mut self, outbox: &outbox::Outbox, status: &mut Status, file: &mut StatusFile) {
        let now = (outbox.sent, outbox.resent, outbox.acked);
        if now != self.written {
            self.set(outbox, status);
            if file.write(status).is_ok() {
                self.written = now;
            }
        }
    }
}

/// Parameters of the tracker service.
#[derive(Debug, Clone, clap::Parser)]
#[command(name = "tracker", about = "Client tracker service")]
pub struct Params {
    /// Client index.
    #[arg(long, default_value_t = 0)]
    pub client: u32,
    /// Status file (JSON).
    #[arg(long)]
    pub status: Option<PathBuf>,
    /// iceoryx2 resource prefix (default: $SHOAL_IPC_PREFIX or "shoal_").
    #[arg(long)]
    pub ipc_prefix: Option<String>,
    /// Write a per-frame / per-IMU-sample log (tests).
    #[arg(long)]
    pub frame_log: Option<PathBuf>,
    /// Sleep this many ms per frame (to simulate a slow consumer in tests).
    #[arg(long, default_value_t = 0)]
    pub work_ms: u64,
    /// Do not run the VO (transport only: replay and IPC tests).
    #[arg(long)]
    pub no_vo: bool,
    /// Turn rolling-shutter compensation off (for comparison).
    #[arg(long)]
    pub no_rs: bool,
    /// Keyframe spool folder: keyframes created and not yet sent are kept there, so that a
    /// restarted tracker sends its killed predecessor's VO window (none: not kept).
    #[arg(long)]
    pub spool: Option<PathBuf>,
    /// Most keyframes in the client map (seed: N = 100).
    #[arg(long, default_value_t = 100)]
    pub window: usize,
    /// ORB features per frame.
    #[arg(long, default_value_t = 1000)]
    pub features: usize,
    /// Wait at most this long (ms) for the gyro samples up to a frame's last row.
    #[arg(long, default_value_t = 40)]
    pub imu_wait_ms: u64,
    /// Local mapping inline in the tracking thread (after each new keyframe) instead of its
    /// own thread: slower per keyframe, but a lock-step replay then takes the same
    /// decisions on every run and machine.
    #[arg(long)]
    pub inline_mapping: bool,
    /// Replay mode of the run (the launcher passes it): in lock-step the tracker
    /// synchronises with its local-mapping thread and with the server (see
    /// [`Params::lockstep_sync`]).
    #[arg(long, default_value = "realtime")]
    pub mode: ReplayMode,
    /// In lock-step, do not synchronise (free-running threads and server, as in real time:
    /// faster, but not reproducible; for benchmarks).
    #[arg(long)]
    pub no_lockstep_sync: bool,
}

impl Params {
    /// Lock-step synchronisation: each frame waits for local mapping to finish before it
    /// uses the map (its ORB extraction overlaps the mapping), and a frame that sent
    /// keyframes waits, before its pose is published and acknowledged, until the server has
    /// finished them ([`shm_schema::FLAG_HANDLED`]); the gyro wait has no short deadline.
    /// So no decision depends on thread timing: a lock-step replay is reproducible.
    pub fn lockstep_sync(&self) -> bool {
        self.mode == ReplayMode::Lockstep && !self.no_lockstep_sync
    }

    /// How long a frame waits for the gyro samples up to its last row.
    fn imu_wait_ns(&self) -> i64 {
        if self.lockstep_sync() {
            IMU_SYNC_TIMEOUT.as_nanos() as i64
        } else {
            self.imu_wait_ms as i64 * 1_000_000
        }
    }
}

/// Lock-step: longest wait for the server to finish a keyframe ([`shm_schema::FLAG_HANDLED`])
/// or for the gyro samples of a frame; a longer wait is counted in `lockstep_sync_timeouts`
/// and the tracker goes on.
const SERVER_SYNC_TIMEOUT: Duration = Duration::from_secs(30);
const IMU_SYNC_TIMEOUT: Duration = Duration::from_secs(5);

/// What the tracker knows from the server's feedback.
#[derive(Default)]
struct ServerState {
    /// Client index.
    client: u32,
    /// Lock-step synchronisation on (else `handled` stays empty).
    sync: bool,
    /// The last usable pose feedback.
    server_ref: Option<ServerRef>,
    /// Lock-step: keyframes (session, id) the server has finished and no frame waited for
    /// yet.
    handled: std::collections::HashSet<(u32, u64)>,
}

type FeedbackSub = iceoryx2::port::subscriber::Subscriber<topics::Ipc, shm_schema::Feedback, ()>;
type KeyframePub = iceoryx2::port::publisher::Publisher<
    topics::Ipc,
    [shm_schema::KeypointRecord],
    shm_schema::KeyframeHeader,
>;

/// Takes the mapper's feedback of client `c`: acknowledgements (outbox), pose feedback and,
/// in lock-step, which keyframes the server has finished. Returns the messages taken.
fn take_feedback(
    sub: &FeedbackSub,
    outbox: &mut outbox::Outbox,
    server: &mut ServerState,
    status: &mut Status,
) -> anyhow::Result<usize> {
    let (mut n, c) = (0, server.client);
    while let Some(fb) = sub.receive()? {
        n += 1;
        let f = *fb.payload();
        if f.meta.check().is_err() {
            status.error("schema_version", format!("feedback of client {c}"));
            continue;
        }
        status.add("feedback_received", 1);
        outbox.ack(f.acked_session_id, f.acked_keyframe_id);
        if f.has_pose != 0 {
            match ServerRef::from_feedback(&f, outbox) {
                Some(r) => {
                    outbox.forget_sent_before(f.acked_session_id, f.acked_keyframe_id);
                    server.server_ref = Some(r);
                    status.add("pose_feedback_used", 1);
                }
                None => status.add("pose_feedback_unusable", 1),
            }
        }
        if server.sync && f.meta.flags & shm_schema::FLAG_HANDLED != 0 {
            server
                .handled
                .insert((f.acked_session_id, f.acked_keyframe_id));
        }
    }
    Ok(n)
}

/// Lock-step: waits until the server has finished keyframe `key` (session, id), taking
/// feedback meanwhile and re-sending keyframes left unacknowledged (a restarted mapper);
/// after [`SERVER_SYNC_TIMEOUT`] it gives up and counts `lockstep_sync_timeouts`.
fn wait_handled(
    key: (u32, u64),
    node: &iceoryx2::node::Node<topics::Ipc>,
    sub: &FeedbackSub,
    kf_pub: &KeyframePub,
    outbox: &mut outbox::Outbox,
    server: &mut ServerState,
    status: &mut Status,
) -> anyhow::Result<()> {
    let start = std::time::Instant::now();
    loop {
        take_feedback(sub, outbox, server, status)?;
        if server.handled.remove(&key) {
            server.handled.clear();
            return Ok(());
        }
        if start.elapsed() > SERVER_SYNC_TIMEOUT {
            status.add("lockstep_server_timeouts", 1);
            return Ok(());
        }
        outbox.resend_stale(kf_pub, 2_000_000_000)?;
        if node.wait(Duration::from_micros(200)).is_err() {
            return Ok(());
        }
    }
}

pub mod imu;
pub mod outbox;
pub mod spool;

/// The service's name in reports.
pub fn service_name(client: u32) -> String {
    format!("tracker:{client}")
}

/// Runs the service; returns the process exit code.
pub fn main_with(params: Params) -> i32 {
    shoal_runtime::exit_code(&service_name(params.client), run(&params))
}

/// FNV-1a 64-bit hash of `bytes` (pixel checksums in frame logs).
pub fn fnv1a(bytes: &[u8]) -> u64 {
    let mut h: u64 = 0xcbf2_9ce4_8422_2325;
    for &b in bytes {
        h ^= b as u64;
        h = h.wrapping_mul(0x0000_0100_0000_01b3);
    }
    h
}

/// Opens the keyframe spool and sends what a killed predecessor left in it (its VO window),
/// before this process starts its own session. A spool that cannot be opened is an error
/// in the status, and the tracker runs without it.
fn open_spool(
    params: &Params,
    kf_pub: &iceoryx2::port::publisher::Publisher<
        topics::Ipc,
        [shm_schema::KeypointRecord],
        shm_schema::KeyframeHeader,
    >,
    outbox: &mut outbox::Outbox,
    status: &mut Status,
) -> anyhow::Result<Option<spool::Spool>> {
    let Some(dir) = &params.spool else {
        return Ok(None);
    };
    let mut sp = match spool::Spool::open(dir) {
        Ok(s) => s,
        Err(e) => {
            status.error("spool", format!("{}: {e}", dir.display()));
            return Ok(None);
        }
    };
    let rec = sp.recover(params.client);
    for e in rec.errors {
        status.error("spool", e);
    }
    for k in rec.keyframes {
        let (session, id) = (k.header.meta.session_id, k.header.keyframe_id);
        outbox.send_message(kf_pub, k.header, k.records)?;
        sp.sent(session, id);
        status.add("keyframes_recovered", 1);
    }
    Ok(Some(sp))
}

/// Writes the keyframes of the VO map newer than `last` (of session `session`) to the spool.
fn spool_new_keyframes(
    v: &VoTracker,
    sp: &mut spool::Spool,
    client: u32,
    session: u32,
    last: &mut Option<(u32, u64)>,
    status: &mut Status,
) {
    let after = last.filter(|l| l.0 == session).map(|l| l.1);
    let new: Vec<_> = v.with_map(|m| {
        m.keyframes
            .range(after.map_or(0, |a| a + 1)..)
            .map(|(id, kf)| (*id, outbox::keyframe_message(client, kf, session)))
            .collect()
    });
    for (id, (h, r)) in new {
        if let Err(e) = sp.write(client, &h, &r) {
            status.error("spool", format!("keyframe {id}: {e}"));
        }
        *last = Some((session, id));
        status.add("keyframes_spooled", 1);
    }
}

/// Consumes frames until the end of the stream or SIGINT/SIGTERM.
pub fn run(params: &Params) -> anyhow::Result<Status> {
    let name = service_name(params.client);
    let mut file = StatusFile::new(params.status.clone());
    let mut status = shoal_runtime::resume_status(&file, &name);
    let prefix = params
        .ipc_prefix
        .clone()
        .unwrap_or_else(topics::prefix_from_env);
    topics::check_foreign_versions(&prefix)?;
    let node = topics::create_node(&format!("tracker_c{}", params.client), &prefix)?;
    let c = params.client;
    let frames = topics::frames_service(&node, c)?;
    let frame_sub = topics::frame_subscriber(&frames, c)?;
    let imu = topics::imu_service(&node, c)?;
    let imu_sub = topics::subscriber(&imu)?;
    let ack_pub = topics::publisher(&topics::frame_ack_service(&node, c)?)?;
    let pose_pub = topics::publisher(&topics::poses_service(&node, c)?)?;
    let feedback_sub = topics::subscriber(&topics::feedback_service(&node, c)?)?;
    let mut log = match &params.frame_log {
        Some(p) => Some(std::io::BufWriter::new(
            std::fs::OpenOptions::new()
                .create(true)
                .append(true)
                .open(p)
                .with_context(|| format!("open frame log {}", p.display()))?,
        )),
        None => None,
    };
    // A restarted tracker starts a new VO session (design: faults): session ids carry the
    // start count in their high bits, the VO's own session counter in the low ones.
    let session_base = (status.starts as u32) << 16;
    let session_id = session_base | 1;
    let kf_pub = topics::keyframe_publisher(&topics::keyframes_service(&node, c)?)?;
    let mut outbox = outbox::Outbox::new(c);
    let mut kf_counts = KeyframeCounts::resume(&mut status);
    let mut spool = open_spool(params, &kf_pub, &mut outbox, &mut status)?;
    // Newest keyframe written to the spool: (VO session, id).
    let mut spooled: Option<(u32, u64)> = None;
    kf_counts.sync(&outbox, &mut status, &mut file);
    let sync = params.lockstep_sync();
    let mut server = ServerState {
        client: c,
        sync,
        ..ServerState::default()
    };
    status.counters.insert("lockstep_sync".into(), sync as u64);
    // Waits of the VO's local-mapping synchronisation that timed out, before this start.
    let vo_timeouts_base = status.get("local_mapping_sync_timeouts");
    let mut vo: Option<VoTracker> = None;
    shoal_runtime::signal_ready();

    let mut last_seq: Option<u64> = status.values.get("last_frame_seq").map(|v| *v as u64);
    // After a restart `last_frame_seq` is the dead process's last status write: the first
    // frame's jump past it also covers frames that process handled after that write.
    let mut first_after_restart = status.starts > 1;
    let mut imu_in = imu::ImuInput::default();
    // Lock-step: a frame waited in vain for the IMU stream's first sample.
    let mut imu_never_came = false;
    let mut ack_seq = 0u64;
    let mut ended = false;
    // After the frames' end of stream, wait this long at most for the IMU's.
    let mut end_deadline: Option<i64> = None;
    loop {
        if ended
            && ((imu_in.ended && outbox.pending() == 0)
                || end_deadline.is_some_and(|d| monotonic_ns() > d))
        {
            break;
        }
        let mut idle = true;
        // IMU first, so that a frame's IMU data is in before the frame is handled.
        if imu_in.drain(&imu_sub, &mut status, c, log.as_mut())? > 0 {
            idle = false;
        }
        if take_feedback(&feedback_sub, &mut outbox, &mut server, &mut status)? > 0 {
            idle = false;
        }
        outbox.resend_stale(&kf_pub, 2_000_000_000)?;
        kf_counts.sync(&outbox, &mut status, &mut file);
        if ended {
            if node.wait(Duration::from_micros(200)).is_err() {
                break;
            }
            continue;
        }
        if let Some(sample) = frame_sub.receive()? {
            idle = false;
            let recv = monotonic_ns();
            let h = *sample.user_header();
            if let Err(e) = h.meta.check() {
                status.error("schema_version", format!("frame of client {c}: {e}"));
                continue;
            }
            let eos = h.meta.is_end_of_stream();
            let t_ns = if eos { i64::MAX } else { h.t_mid_ns };
            let ack = FrameAck {
                meta: MsgMeta::new(c, session_id, ack_seq, monotonic_ns()),
                frame_seq: h.meta.seq,
                frame_t_ns: t_ns,
            };
            if eos {
                ended = true;
                if let Some(v) = vo.as_mut() {
                    let sess = session_base | v.session_id();
                    for kf in v.drain_keyframes() {
                        outbox.send(&kf_pub, &kf, sess)?;
                        if let Some(sp) = spool.as_mut() {
                            sp.sent(sess, kf.id);
                        }
                        // Lock-step: one at a time, so the server handles the window's
                        // keyframes on the same schedule on every run.
                        if sync {
                            kf_counts.sync(&outbox, &mut status, &mut file);
                            let (sub, st) = (&feedback_sub, &mut status);
                            wait_handled(
                                (sess, kf.id),
                                &node,
                                sub,
                                &kf_pub,
                                &mut outbox,
                                &mut server,
                                st,
                            )?;
                        }
                    }
                    kf_counts.sync(&outbox, &mut status, &mut file);
                }
                ack_pub.send_copy(ack)?;
                status.set_value("end_of_stream_seq", h.meta.seq as f64);
                let mut meta = MsgMeta::new(c, session_id, h.meta.seq, monotonic_ns());
                meta.flags = FLAG_END_OF_STREAM;
                pose_pub.send_copy(TrackedPose {
                    meta,
                    ..TrackedPose::default()
                })?;
                end_deadline = Some(monotonic_ns() + 5_000_000_000);
                continue;
            }
            if last_seq.is_some_and(|l| h.meta.seq <= l) {
                // A re-send of a frame already handled (e.g. the camera restarted): ack again.
                status.add("frames_duplicate", 1);
                ack_pub.send_copy(ack)?;
                ack_seq += 1;
                continue;
            }
            let expected = last_seq.map_or(0, |l| l + 1);
            if h.meta.seq > expected {
                let gap = if first_after_restart {
                    "frames_gap_at_restart"
                } else {
                    "frames_gap"
                };
                status.add(gap, h.meta.seq - expected);
            }
            first_after_restart = false;
            last_seq = Some(h.meta.seq);
            let pixels = sample.payload();
            if pixels.len() != h.payload_len() {
                status.error(
                    "bad_frame",
                    format!(
                        "frame {}: {} bytes, header says {}",
                        h.meta.seq,
                        pixels.len(),
                        h.payload_len()
                    ),
                );
            }
            if let Some(l) = log.as_mut() {
                writeln!(
                    l,
                    "frame {} {} {} {} {} {} {} {:016x}",
                    h.meta.seq,
                    h.dataset_index,
                    h.t_mid_ns,
                    h.readout_ns,
                    h.width,
                    h.height,
                    pixels.len(),
                    fnv1a(pixels)
                )?;
            }
            if params.work_ms > 0 {
                std::thread::sleep(Duration::from_millis(params.work_ms));
            }
            let mut stage_ms = [0f32; stage::COUNT];
            let mut state = TrackState::NotInitialized;
            let mut pose_out = Pose::IDENTITY;
            let mut t_cf: Option<nalgebra::Isometry3<f64>> = None;
            let mut tracked = 0;
            let mut is_kf = 0;
            let mut vo_session = session_id;
            if !params.no_vo && pixels.len() >= h.payload_len() && h.width > 0 {
                if vo.is_none() {
                    let mut v = new_vo(params, &h)?;
                    // Keyframe ids stay unique per client across restarts of this process
                    // (the server names keyframes by them): each life gets its own range.
                    v.start_keyframe_ids_at(u64::from(session_base >> 16) << KF_ID_BITS_PER_START);
                    status
                        .counters
                        .insert("local_mapping_thread".into(), !params.inline_mapping as u64);
                    vo = Some(v);
                }
                // Rolling shutter: the gyro over the frame's readout, waiting a little for
                // the samples up to its last row when the IMU stream is live.
                let omega = if params.no_rs || h.readout_ns == 0 {
                    None
                } else {
                    let need = h.t_mid_ns + h.readout_ns / 2;
                    let deadline = monotonic_ns() + params.imu_wait_ns();
                    // Lock-step: also before the first IMU sample (whether it is in before
                    // the first frames would otherwise change the initialisation).
                    let missing = |imu: &imu::ImuInput| {
                        let short = imu.newest_ns().is_none_or(|t| t < need);
                        if sync && !imu_never_came {
                            short && !imu.ended
                        } else {
                            short && imu.live()
                        }
                    };
                    while missing(&imu_in) && monotonic_ns() < deadline {
                        if imu_in.drain(&imu_sub, &mut status, c, log.as_mut())? == 0
                            && node.wait(Duration::from_micros(200)).is_err()
                        {
                            break;
                        }
                    }
                    if sync && missing(&imu_in) {
                        status.add("lockstep_imu_timeouts", 1);
                        // No IMU at all (e.g. its ingest keeps failing): wait no more for
                        // its start.
                        imu_never_came |= imu_in.newest_ns().is_none();
                    }
                    imu_in.camera_rate(&h)
                };
                if omega.is_some() {
                    status.add("frames_gyro_rs", 1);
                }
                if let Some(v) = vo.as_mut() {
                    match run_vo(v, pixels, &h, omega) {
                        Ok(o) => {
                            state = match o.state {
                                VoState::NotInitialized => TrackState::NotInitialized,
                                VoState::Initializing => TrackState::Initializing,
                                VoState::Tracking => TrackState::Tracking,
                                VoState::Lost => TrackState::Lost,
                            };
                            if let (TrackState::Tracking, Some(t)) = (state, o.t_cw) {
                                pose_out = outbox::wire_pose(&t);
                                t_cf = Some(t.inverse());
                            }
                            tracked = o.tracked as u32;
                            is_kf = o.keyframe.is_some() as u32;
                            let t = &o.times;
                            stage_ms[stage::PYRAMID] = t.pyramid;
                            stage_ms[stage::DETECT] = t.detect;
                            stage_ms[stage::DESCRIBE] = t.describe;
                            stage_ms[stage::MATCH] = t.matching;
                            stage_ms[stage::POSE_OPT] = t.pose_opt;
                            stage_ms[stage::LOCAL_MAP] = t.local_map;
                            stage_ms[stage::KEYFRAME] = t.keyframe;
                            if o.new_session {
                                status.add("vo_sessions_started", 1);
                            }
                            // Evicted keyframes belong to the session they were made in.
                            let sess =
                                session_base | v.session_id().saturating_sub(o.new_session as u32);
                            for kf in &o.evicted {
                                outbox.send(&kf_pub, kf, sess)?;
                                if let Some(sp) = spool.as_mut() {
                                    sp.sent(sess, kf.id);
                                }
                            }
                            kf_counts.sync(&outbox, &mut status, &mut file);
                            // Lock-step: the server's answers to these keyframes (pose
                            // feedback) are in before this frame's server pose.
                            if let (true, Some(last)) = (sync, o.evicted.last()) {
                                let (sub, st) = (&feedback_sub, &mut status);
                                wait_handled(
                                    (sess, last.id),
                                    &node,
                                    sub,
                                    &kf_pub,
                                    &mut outbox,
                                    &mut server,
                                    st,
                                )?;
                            }
                            vo_session = session_base | v.session_id();
                            // Keyframes enter the VO map only with a frame that reports one
                            // (two at initialisation): no map lock on the other frames.
                            if let (Some(sp), Some(_)) = (spool.as_mut(), o.keyframe) {
                                spool_new_keyframes(
                                    v,
                                    sp,
                                    c,
                                    vo_session,
                                    &mut spooled,
                                    &mut status,
                                );
                            }
                            // Poses of the frames seen while initialising.
                            for (t_ns, t_cw) in &o.backfill {
                                let mut meta =
                                    MsgMeta::new(c, vo_session, h.meta.seq, monotonic_ns());
                                meta.flags = FLAG_BACKFILL;
                                pose_pub.send_copy(TrackedPose {
                                    meta,
                                    t_ns: *t_ns,
                                    pose: outbox::wire_pose(t_cw),
                                    state: TrackState::Tracking as u32,
                                    ..TrackedPose::default()
                                })?;
                                status.add("frames_backfilled", 1);
                            }
                        }
                        Err(e) => status.error("vo", format!("frame {}: {e}", h.meta.seq)),
                    }
                }
            }
            drop(sample);
            ack_pub.send_copy(ack)?;
            ack_seq += 1;
            status.add("frames_received", 1);
            if state == TrackState::Tracking {
                status.add("frames_tracked", 1);
            }
            // Pose in the server map from the last feedback (eq. 3.1, 3.4), same VO session.
            let server_pose = t_cf.and_then(|t| {
                server
                    .server_ref
                    .as_ref()
                    .filter(|r| r.session == vo_session)
                    .map(|r| (r.frame_pose(&t), r.map_id))
            });
            if server_pose.is_some() {
                status.add("frames_server_pose", 1);
            }
            let out = monotonic_ns();
            stage_ms[stage::TOTAL] = (out - recv) as f32 * 1e-6;
            let pose = TrackedPose {
                meta: MsgMeta::new(c, vo_session, h.meta.seq, out),
                t_ns: h.t_mid_ns,
                dataset_index: h.dataset_index,
                pose: pose_out,
                server_pose: server_pose.map_or(Pose::IDENTITY, |p| p.0),
                server_map_id: server_pose.map_or(0, |p| p.1),
                state: state as u32,
                has_server_pose: server_pose.is_some() as u32,
                tracked_points: tracked,
                is_keyframe: is_kf,
                frame_publish_mono_ns: h.meta.publish_mono_ns,
                frame_receive_mono_ns: recv,
                stage_ms,
            };
            pose_pub.send_copy(pose)?;
            status.add("poses_published", 1);
            status.set_value("last_frame_seq", h.meta.seq as f64);
            if let Some(v) = vo.as_ref() {
                status.set_value("vo_relocalizations", v.relocalizations() as f64);
                status.set_value("keyframes_culled", v.keyframes_culled() as f64);
                status.counters.insert(
                    "local_mapping_sync_timeouts".into(),
                    vo_timeouts_base + v.local_mapping_sync_timeouts() as u64,
                );
            }
            let _ = file.write_every(&status, Duration::from_millis(200));
        }
        if idle && node.wait(Duration::from_micros(100)).is_err() {
            break;
        }
    }
    if let Some(l) = log.as_mut() {
        l.flush()?;
    }
    kf_counts.set(&outbox, &mut status);
    status.set_value("sent_poses_kept", outbox.sent_poses_kept() as f64);
    status.finished = ended;
    file.write(&status)?;
    Ok(status)
}
