//! The tracker's ports: iceoryx2 subscribers and publishers around a [`TrackerCore`], the
//! frame log, the keyframe spool and the status file. [`run`] takes one event at a time
//! (IMU, feedback, frame) and carries out what the core returns ([`Out`]).
use std::io::Write;
use std::time::Duration;

use anyhow::Context;
use iceoryx2::node::Node;
use iceoryx2::port::publisher::Publisher;
use iceoryx2::port::subscriber::Subscriber;
use shm_schema::time::monotonic_ns;
use shm_schema::topics::{self, Ipc};
use shm_schema::{
    Feedback, FrameAck, FrameHeader, ImuMsg, KeyframeHeader, KeyframeRecord, TrackedPose,
};
use shoal_runtime::{ErrorKind, ServiceStart, Status, StatusFile};

use crate::core::{CoreConfig, FrameIn, FrameStep, KeyframeKey, Out, TrackerCore};
use crate::outbox::KeyframeMsg;
use crate::{fnv1a, spool, Params, TrackerConfig};

/// Lock-step: longest wait for the server to finish a keyframe ([`shm_schema::FLAG_HANDLED`]);
/// a longer wait is counted in `lockstep_server_timeouts` and the tracker goes on.
const SERVER_SYNC_TIMEOUT: Duration = Duration::from_secs(30);

type FrameSub = Subscriber<Ipc, [u8], FrameHeader>;
type KeyframePub = Publisher<Ipc, [KeyframeRecord], KeyframeHeader>;
type FeaturesPub = Publisher<Ipc, [shm_schema::TrackedFeature], shm_schema::TrackedFeaturesHeader>;

/// The tracker's shared-memory ports and files.
struct Ports {
    node: Node<Ipc>,
    frames: FrameSub,
    imu: Subscriber<Ipc, ImuMsg, ()>,
    feedback: Subscriber<Ipc, Feedback, ()>,
    acks: Publisher<Ipc, FrameAck, ()>,
    poses: Publisher<Ipc, TrackedPose, ()>,
    /// A frame's tracked features (`publish_features`).
    features: Option<FeaturesPub>,
    keyframes: KeyframePub,
    log: Option<std::io::BufWriter<std::fs::File>>,
    /// The calibration mode's log (`tracker.calib.log`).
    calib_log: Option<std::io::BufWriter<std::fs::File>>,
    spool: Option<spool::Spool>,
    file: StatusFile,
    /// Keyframe traffic in the status file last written.
    written: (u64, u64, u64),
}

impl Ports {
    fn open(
        params: &Params,
        cfg: &TrackerConfig,
        node: Node<Ipc>,
        file: StatusFile,
    ) -> anyhow::Result<Self> {
        let c = params.client;
        let frames = topics::frame_subscriber(&topics::frames_service(&node, c)?, c)?;
        let append = |p: &std::path::Path, what: &str| -> anyhow::Result<_> {
            Ok(std::io::BufWriter::new(
                std::fs::OpenOptions::new()
                    .create(true)
                    .append(true)
                    .open(p)
                    .with_context(|| format!("open {what} {}", p.display()))?,
            ))
        };
        let log = cfg
            .frame_log
            .as_deref()
            .map(|p| append(p, "frame log"))
            .transpose()?;
        let calib_log = cfg
            .calib
            .log
            .as_deref()
            .map(|p| append(p, "calibration log"))
            .transpose()?;
        Ok(Self {
            imu: topics::subscriber(&topics::imu_service(&node, c)?)?,
            feedback: topics::subscriber(&topics::feedback_service(&node, c)?)?,
            acks: topics::publisher(&topics::frame_ack_service(&node, c)?)?,
            poses: topics::publisher(&topics::poses_service(&node, c)?)?,
            features: (cfg.publish_features)
                .then(|| {
                    let service = topics::features_service(&node, c)?;
                    topics::slice_publisher(&service, topics::MAX_TRACKED_FEATURES)
                })
                .transpose()?,
            keyframes: topics::keyframe_publisher(&topics::keyframes_service(&node, c)?)?,
            frames,
            node,
            log,
            calib_log,
            spool: None,
            file,
            written: (0, 0, 0),
        })
    }

    /// Carries out the core's outputs, in order.
    fn exec(&mut self, out: Vec<Out>, status: &mut Status) -> anyhow::Result<()> {
        for o in out {
            match o {
                Out::Ack(a) => {
                    self.acks.send_copy(a)?;
                }
                Out::Pose(p) => {
                    self.poses.send_copy(p)?;
                }
                Out::Keyframe(m) => publish_keyframe(&self.keyframes, &m)?,
                Out::Features(h, f) => {
                    if let Some(p) = &self.features {
                        publish_features(p, h, &f)?;
                    }
                }
                Out::SpoolWrite(e) => self.spool_write(&e, status),
                Out::CalibLog(line) => {
                    if let Some(l) = self.calib_log.as_mut() {
                        writeln!(l, "{line}").context("write calibration log")?;
                    }
                }
                Out::SpoolSent((session, id)) => {
                    if let Some(sp) = self.spool.as_mut() {
                        sp.sent(session, id);
                    }
                }
            }
        }
        Ok(())
    }

    fn spool_write(&mut self, e: &spool::SpoolEntry, status: &mut Status) {
        let (Some(sp), m) = (self.spool.as_mut(), &e.msg) else {
            return;
        };
        let c = m.header.meta.client_id;
        if let Err(e) = sp.write(c, m, &e.points) {
            let detail = format!("keyframe {}: {e}", m.header.keyframe_id);
            status.error(ErrorKind::Spool, detail);
        }
    }

    /// Takes every waiting IMU sample into the core; returns how many were taken.
    fn drain_imu(&mut self, core: &mut TrackerCore) -> anyhow::Result<usize> {
        let mut n = 0;
        while let Some(s) = self.imu.receive()? {
            n += 1;
            let m = *s.payload();
            if core.on_imu(&m) {
                if let Some(l) = self.log.as_mut() {
                    writeln!(l, "imu {} {}", m.meta.seq, m.t_ns)?;
                }
            }
        }
        Ok(n)
    }

    /// Takes every waiting feedback message into the core; returns how many were taken.
    fn drain_feedback(&mut self, core: &mut TrackerCore) -> anyhow::Result<usize> {
        let mut n = 0;
        while let Some(fb) = self.feedback.receive()? {
            n += 1;
            let f = fb.payload();
            core.on_feedback(f);
            if let Some(sp) = self.spool.as_mut() {
                sp.acked(f.acked_session_id, f.acked_keyframe_id);
            }
        }
        Ok(n)
    }

    /// Writes the status when keyframes were sent, re-sent or acknowledged since the last
    /// write (a failed write is retried at the next change or periodic write).
    fn sync_status(&mut self, core: &mut TrackerCore) {
        let now = core.keyframe_progress();
        if now != self.written {
            core.put_keyframe_counts();
            if self.file.write(core.status()).is_ok() {
                self.written = now;
            }
        }
    }

    /// Re-sends stale keyframes and writes the status if keyframe traffic changed.
    fn tick(&mut self, core: &mut TrackerCore) -> anyhow::Result<()> {
        let out = core.on_tick(monotonic_ns());
        self.exec(out, core.status_mut())?;
        self.sync_status(core);
        Ok(())
    }

    /// Lock-step: waits until the server has finished keyframe `key`, taking feedback and
    /// re-sending unacknowledged keyframes meanwhile (a restarted mapper); gives up after
    /// [`SERVER_SYNC_TIMEOUT`] and counts `lockstep_server_timeouts`.
    fn wait_handled(&mut self, key: KeyframeKey, core: &mut TrackerCore) -> anyhow::Result<()> {
        let start = std::time::Instant::now();
        loop {
            self.drain_feedback(core)?;
            if core.take_handled(key) {
                return Ok(());
            }
            if start.elapsed() > SERVER_SYNC_TIMEOUT {
                core.count_server_timeout();
                return Ok(());
            }
            let out = core.on_tick(monotonic_ns());
            self.exec(out, core.status_mut())?;
            if self.node.wait(Duration::from_micros(200)).is_err() {
                return Ok(());
            }
        }
    }

    /// Waits (a little, or in lock-step until it comes) for the gyro samples up to the
    /// last row of the frame `h`.
    fn wait_gyro(
        &mut self,
        core: &mut TrackerCore,
        h: &FrameHeader,
        len: usize,
        wait_ns: i64,
    ) -> anyhow::Result<()> {
        let Some(need) = core.imu_needed_ns(h, len) else {
            return Ok(());
        };
        let deadline = monotonic_ns() + core.imu_wait_ns(wait_ns);
        while core.imu_missing(need) && monotonic_ns() < deadline {
            if self.drain_imu(core)? == 0 && self.node.wait(Duration::from_micros(200)).is_err() {
                break;
            }
        }
        Ok(())
    }

    /// The frames' end of stream: the VO window goes to the mapper (in lock-step one
    /// keyframe at a time), then the end of stream is acknowledged and passed on.
    fn end_of_stream(&mut self, core: &mut TrackerCore, h: &FrameHeader) -> anyhow::Result<()> {
        let held = core.release_held(monotonic_ns());
        self.exec(held, core.status_mut())?;
        for kf in core.take_window() {
            let (key, out) = core.send_window_keyframe(&kf, monotonic_ns());
            self.exec(out, core.status_mut())?;
            if core.config().lockstep_sync {
                self.sync_status(core);
                self.wait_handled(key, core)?;
            }
        }
        self.sync_status(core);
        let out = core.end_of_stream(h, monotonic_ns());
        self.exec(out, core.status_mut())
    }

    /// Takes one frame, if one is waiting; returns whether one was.
    fn frame(&mut self, core: &mut TrackerCore, cfg: &TrackerConfig) -> anyhow::Result<bool> {
        let Some(sample) = self.frames.receive()? else {
            return Ok(false);
        };
        let recv_ns = monotonic_ns();
        let header = *sample.user_header();
        let pixels = sample.payload();
        self.wait_gyro(
            core,
            &header,
            pixels.len(),
            cfg.imu_wait_ms as i64 * 1_000_000,
        )?;
        if cfg.work_ms > 0 && !header.meta.is_end_of_stream() {
            std::thread::sleep(Duration::from_millis(cfg.work_ms));
        }
        let frame = FrameIn {
            header,
            pixels,
            recv_ns,
            now_ns: monotonic_ns(),
        };
        let step = core.track(frame)?;
        if cfg.debug_init {
            for d in core.diagnostics() {
                eprintln!("{d}");
            }
        }
        match step {
            FrameStep::Done(out) => self.exec(out, core.status_mut())?,
            FrameStep::EndOfStream(h) => self.end_of_stream(core, &h)?,
            FrameStep::Tracked(mut t) => {
                if let Some(l) = self.log.as_mut() {
                    write_frame_log(l, &header, pixels)?;
                }
                drop(sample);
                self.exec(std::mem::take(&mut t.out), core.status_mut())?;
                self.sync_status(core);
                if let Some(key) = t.await_handled {
                    self.wait_handled(key, core)?;
                }
                let out = core.publish_frame(t, monotonic_ns());
                self.exec(out, core.status_mut())?;
                // The counters go into the status only when a periodic write is due.
                if self.file.due(Duration::from_millis(200)) {
                    let _ = self.file.write(core.status());
                }
            }
        }
        Ok(true)
    }
}

/// One line of the frame log: sequence number, dataset index, times, size and the pixels'
/// FNV-1a checksum.
fn write_frame_log(l: &mut impl Write, h: &FrameHeader, pixels: &[u8]) -> std::io::Result<()> {
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
    )
}

/// Publishes a keyframe message: header, keypoint records then IMU records into one loaned
/// sample (`KeyframeHeader::keypoints`, `KeyframeHeader::imu_records`).
/// Publishes a frame's tracked features (a full slice is cut at its capacity).
fn publish_features(
    publisher: &FeaturesPub,
    h: shm_schema::TrackedFeaturesHeader,
    f: &[shm_schema::TrackedFeature],
) -> anyhow::Result<()> {
    let f = &f[..f.len().min(topics::MAX_TRACKED_FEATURES)];
    let sample = publisher.loan_slice_uninit(f.len())?;
    let mut sample = sample.write_from_fn(|i| f[i]);
    *sample.user_header_mut() = shm_schema::TrackedFeaturesHeader {
        n_features: f.len() as u32,
        ..h
    };
    sample.send()?;
    Ok(())
}

fn publish_keyframe(publisher: &KeyframePub, m: &KeyframeMsg) -> anyhow::Result<()> {
    let (n_kp, n_imu) = (m.records.len(), m.imu.len());
    let sample = publisher.loan_slice_uninit(n_kp + n_imu)?;
    let mut sample = sample.write_from_fn(|i| match i.checked_sub(n_kp) {
        None => KeyframeRecord::from(m.records[i]),
        Some(j) => KeyframeRecord::from(m.imu[j]),
    });
    *sample.user_header_mut() = m.header;
    sample.send()?;
    Ok(())
}

/// Opens the keyframe spool and gives the core what a killed predecessor left in it (its
/// VO window): sent before this process starts its own session, or held to resume the
/// predecessor's visual-inertial session (`core/resume.rs`). A spool that cannot be opened
/// is an error in the status, and the tracker runs without it.
fn open_spool(
    params: &Params,
    cfg: &TrackerConfig,
    ports: &mut Ports,
    core: &mut TrackerCore,
) -> anyhow::Result<()> {
    let Some(dir) = &params.spool else {
        return Ok(());
    };
    let mut sp = match spool::Spool::open(dir) {
        Ok(s) if cfg.spool_until_ack => s.until_acked(),
        Ok(s) => s,
        Err(e) => {
            let detail = format!("{}: {e}", dir.display());
            core.status_mut().error(ErrorKind::Spool, detail);
            return Ok(());
        }
    };
    let rec = sp.recover(params.client);
    for e in rec.errors {
        core.status_mut().error(ErrorKind::Spool, e);
    }
    ports.spool = Some(sp);
    let out = core.recover_spool(rec.keyframes, monotonic_ns());
    ports.exec(out, core.status_mut())
}

/// Gives the core the saved map of `tracker.prior_map` to localise in before its VO
/// initialises (`core/prior.rs`): the file's map with the most keyframes. A file that
/// cannot be used is an error in the status (`map_file`), and the client starts as without
/// it (the launcher checked the file before any service started).
fn load_prior_map(cfg: &TrackerConfig, core: &mut TrackerCore) {
    let Some(path) = &cfg.prior_map else {
        return;
    };
    match prior_from_file(path) {
        Ok(map) => core.set_prior_map(map),
        Err(e) => {
            let detail = format!("{}: prior map not used: {e}", path.display());
            core.status_mut().error(ErrorKind::MapFile, detail);
        }
    }
}

/// The client form of the largest map in saved-map file `path`.
fn prior_from_file(path: &std::path::Path) -> Result<slam_core::vo::ClientMap, String> {
    let loaded = map_store::load(path).map_err(|e| e.to_string())?;
    let largest = (loaded.file.maps.iter())
        .max_by_key(|m| m.map.map.keyframes.len())
        .ok_or("the file holds no map")?;
    let prior = slam_core::vo::prior_client_map(&largest.map.map).map_err(|e| e.to_string())?;
    Ok(prior.map)
}

/// Consumes frames until the end of the stream or SIGINT/SIGTERM.
pub fn run(params: &Params) -> anyhow::Result<Status> {
    let cfg = params.config()?;
    let c = params.client;
    let start = ServiceStart::open(
        &crate::service_name(c),
        &format!("tracker_c{c}"),
        params.status.clone(),
        params.ipc_prefix.clone(),
    )?;
    let mut core = TrackerCore::new(CoreConfig::new(params, &cfg), start.status);
    load_prior_map(&cfg, &mut core);
    let mut ports = Ports::open(params, &cfg, start.node, start.file)?;
    open_spool(params, &cfg, &mut ports, &mut core)?;
    ports.sync_status(&mut core);
    shoal_runtime::signal_ready();
    let mut end_deadline: Option<i64> = None;
    loop {
        if core.ended() && (core.drained() || end_deadline.is_some_and(|d| monotonic_ns() > d)) {
            break;
        }
        // IMU first, so that a frame's IMU data is in before the frame is handled.
        let mut busy = ports.drain_imu(&mut core)? > 0;
        busy |= ports.drain_feedback(&mut core)? > 0;
        ports.tick(&mut core)?;
        if core.ended() {
            if ports.node.wait(Duration::from_micros(200)).is_err() {
                break;
            }
            continue;
        }
        busy |= ports.frame(&mut core, &cfg)?;
        if core.ended() && end_deadline.is_none() {
            // After the frames' end of stream: the IMU's, and the server's acknowledgements.
            let wait_s = (cfg.end_wait_s).unwrap_or(crate::config::LOCAL_END_WAIT_S);
            end_deadline = Some(monotonic_ns() + (wait_s.max(0.0) * 1e9) as i64);
        }
        if !busy && ports.node.wait(Duration::from_micros(100)).is_err() {
            break;
        }
    }
    if let Some(l) = ports.log.as_mut() {
        l.flush()?;
    }
    if let Some(l) = ports.calib_log.as_mut() {
        l.flush()?;
    }
    let status = core.finish();
    ports.file.write(&status)?;
    Ok(status)
}
