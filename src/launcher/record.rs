//! `shoal run --record FILE.mcap` (issue 21): what crosses shared memory, recorded as the
//! run goes, as an MCAP file of ROS 2 messages that `shoal run --dataset FILE.mcap` replays
//! ([`datasets::mcap_bag::write::StreamWriter`], the layout of `shoal convert --to mcap`):
//!
//! - the frames each tracker receives (`/cam0/image_raw`, `mono8`, stamped with their
//!   middle-row time `FrameHeader::t_mid_ns`, t_d applied) and the IMU samples
//!   (`/imu0`), with the camera (`/cam0/camera_info`) and the `shoal` metadata record (the
//!   calibration ROS messages lack: `T_BS`, t_r, t_d, the IMU model), so that a replay
//!   re-runs the estimation on the same input;
//! - for viewers (Foxglove, RViz; a replay ignores them): the tracker's poses
//!   (`/shoal/pose`, `geometry_msgs/msg/PoseStamped`, camera-to-map of its VO session, and
//!   the same as `/tf` `map` → `cam0`; the camera-IMU transform as `/tf_static` `imu0` →
//!   `cam0` when the calibration has one), the keyframes it sends (`/shoal/keyframe`), its
//!   poses in the server map from the feedback (`/shoal/server_pose`, frame `server_map`),
//!   each frame's publish-to-pose latency (`/shoal/latency_ms`, `std_msgs/msg/Float64`), and
//!   at the end the points of its server map (`/shoal/map`, `sensor_msgs/msg/PointCloud2`,
//!   from the saved-map file: `--save-map`'s, the loaded one under `--localize-only`, else
//!   `OUT/record_map.shoalmap`, which the mapper then writes); the loop closer's
//!   corrections (merges and loops) as `/rosout` log lines (`rcl_interfaces/msg/Log`, at the
//!   time of the last frame recorded; in client 0's file only, they are the host's);
//! - the dataset's ground truth, when it has one (`/cam0/ground_truth`), for the replay's
//!   evaluation.
//!
//! One file per client (`FILE` with one client; `STEM_c{i}.mcap` with several). Per client,
//! a receiving thread takes the messages from shared memory as soon as they come (it copies
//! the pixels and nothing else) and a writing thread, at a lower priority, encodes them and
//! compresses them with LZ4, so a slow disk or compression never holds a frame in the
//! subscriber's buffer nor takes the trackers' CPU. A frame the recorder
//! missed (a gap in the frames' sequence numbers) is counted in the report.
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{mpsc, Arc};
use std::thread::JoinHandle;
use std::time::Duration;

use anyhow::Context;
use datasets::mcap_bag::meta::ShoalMeta;
use datasets::mcap_bag::write::{StreamWriter, WriteSettings, GROUND_TRUTH_TOPIC};
use serde::Serialize;
use shm_schema::topics;
use shm_schema::{PixelFormat, TrackState};

use super::view::{self, Live, ViewMsg, ViewState};

/// Topic of the recorded tracker poses.
pub const POSE_TOPIC: &str = "/shoal/pose";
/// The same as `nav_msgs/msg/Odometry` (RViz).
pub const ODOMETRY_TOPIC: &str = "/shoal/odometry";

/// What the recording of one client holds (`report.json` `record`).
#[derive(Debug, Clone, Default, Serialize, PartialEq)]
pub struct RecordReport {
    /// The file.
    pub file: String,
    /// Frames written.
    pub frames: u64,
    /// IMU samples written.
    pub imu_samples: u64,
    /// Tracker poses written (frames it tracked; `/shoal/pose`).
    pub poses: u64,
    /// Keyframes the tracker sent (`/shoal/keyframe`).
    pub keyframes: u64,
    /// Points of the client's final server map (`/shoal/map`, at the end).
    pub map_points: u64,
    /// The loop closer's corrections (`/rosout`; client 0's recording only: they are the
    /// host's).
    pub corrections: u64,
    /// Frames published that the recorder did not receive (gaps in their sequence).
    pub frames_missed: u64,
    /// Frames whose tracked features were recorded (`/cam0/features`).
    pub feature_frames: u64,
    /// Frames not written: not 8-bit gray (a feature-track dataset), or malformed.
    pub frames_skipped: u64,
    /// Size of the file, bytes.
    pub bytes: u64,
    /// Why the file could not be written (it is then removed).
    pub error: Option<String>,
}

/// One message taken from shared memory.
enum Item {
    Frame {
        t_ns: i64,
        width: u32,
        height: u32,
        pixels: Vec<u8>,
    },
    Imu(datasets::ImuSample),
    Pose {
        t_ns: i64,
        /// Camera-to-map in the VO session's map, when tracked.
        pose: Option<nalgebra::Isometry3<f64>>,
        /// Camera-to-map in the server map, when the feedback gave one.
        server: Option<nalgebra::Isometry3<f64>>,
        /// Frame publish to pose publish, ms (a live pose's).
        latency_ms: Option<f64>,
    },
    Keyframe {
        t_ns: i64,
        pose: nalgebra::Isometry3<f64>,
    },
    /// The frame's keypoints matched to map points (`tracker.publish_features`).
    Features {
        t_ns: i64,
        pixels: Vec<[f32; 2]>,
    },
    /// The client's final server map: points and keyframe centres (end of the run).
    Map(super::view::MapView),
    /// A loop closer's correction, as a log line and an edge.
    Correction(String, super::view::LoopEdge),
    Skipped,
}

/// The recording threads of one client.
struct ClientRecording {
    receiver: JoinHandle<anyhow::Result<u64>>,
    writer: JoinHandle<RecordReport>,
    /// For what comes after the services: the map's points.
    tx: mpsc::Sender<Item>,
}

/// The run's recording, into a file (`--record`), to live viewers (`--viz`) or both:
/// started before the services, stopped after them.
pub struct Recording {
    stop: Arc<AtomicBool>,
    clients: Vec<ClientRecording>,
}

/// The file of client `c` of `n` for `--record path`.
pub fn file_of(path: &Path, c: usize, n: usize) -> PathBuf {
    if n <= 1 {
        return path.to_path_buf();
    }
    let stem = path
        .file_stem()
        .map_or("record".into(), |s| s.to_string_lossy());
    path.with_file_name(format!("{stem}_c{c}.mcap"))
}

impl Recording {
    /// Subscribes to every client's frames, IMU and poses (before any service publishes)
    /// and starts writing to `path` (when given) and sending to `live` (when given);
    /// `metas[c]` is client `c`'s calibration record, `truth[c]` its dataset's ground
    /// truth.
    pub fn start(
        path: Option<&Path>,
        live: Option<Arc<Live>>,
        prefix: &str,
        metas: Vec<ShoalMeta>,
        truth: Vec<Vec<datasets::StampedPose>>,
    ) -> anyhow::Result<Self> {
        let stop = Arc::new(AtomicBool::new(false));
        let n = metas.len();
        let mut clients = Vec::new();
        for (c, (meta, truth)) in metas.into_iter().zip(truth).enumerate() {
            let file = path.map(|p| file_of(p, c, n));
            let live = live.clone().map(|l| LiveOut::new(l, c, n));
            let keep_pixels = Pixels {
                file: file.is_some(),
                live: live.clone(),
            };
            let (tx, rx) = mpsc::channel();
            let tx_end = tx.clone();
            let writer = std::thread::Builder::new()
                .name(format!("record-write-{c}"))
                .spawn(move || write(file.as_deref(), live, &meta, &truth, &rx))
                .context("starting a recording thread")?;
            let (ready_tx, ready_rx) = mpsc::sync_channel(1);
            let (prefix, stopped) = (prefix.to_string(), stop.clone());
            let receiver = std::thread::Builder::new()
                .name(format!("record-recv-{c}"))
                .spawn(move || receive(c as u32, &prefix, &keep_pixels, &stopped, &tx, &ready_tx))
                .context("starting a recording thread")?;
            let failed = match ready_rx.recv_timeout(Duration::from_secs(10)) {
                Ok(Ok(())) => None,
                Ok(Err(e)) => Some(e),
                Err(_) => Some("the recorder did not subscribe".to_string()),
            };
            if let Some(e) = failed {
                // The threads already started end (their files are left unfinished).
                stop.store(true, Ordering::SeqCst);
                anyhow::bail!("--record: client {c}: {e}");
            }
            clients.push(ClientRecording {
                receiver,
                writer,
                tx: tx_end,
            });
        }
        Ok(Self { stop, clients })
    }

    /// Takes what is left in shared memory, adds each client's server map points from the
    /// saved-map file `maps` ([`map_points`]), ends the files; one report per client.
    pub fn finish(self, maps: Option<&Path>) -> Vec<RecordReport> {
        self.stop.store(true, Ordering::SeqCst);
        let file = maps.and_then(|p| map_store::read(p).ok()).map(|(_, f)| f);
        let mut reports = Vec::new();
        for (i, c) in self.clients.into_iter().enumerate() {
            let received = c.receiver.join();
            if let Some(f) = &file {
                let _ = c.tx.send(Item::Map(map_view(f, i as u32)));
            }
            drop(c.tx);
            let mut r = c.writer.join().unwrap_or_else(|_| RecordReport {
                error: Some("the recording thread panicked".into()),
                ..RecordReport::default()
            });
            match received {
                Ok(Ok(missed)) => r.frames_missed = missed,
                Ok(Err(e)) => r.error = r.error.or(Some(e.to_string())),
                Err(_) => r.error = r.error.or(Some("the receiving thread panicked".into())),
            }
            reports.push(r);
        }
        reports
    }
}

/// A subscriber of the run's shared memory.
type Sub<T, H = ()> = iceoryx2::port::subscriber::Subscriber<topics::Ipc, T, H>;

/// The recorder's subscriptions of one client.
struct Subscriptions {
    node: iceoryx2::node::Node<topics::Ipc>,
    frames: Sub<[u8], shm_schema::FrameHeader>,
    imu: Sub<shm_schema::ImuMsg>,
    poses: Sub<shm_schema::TrackedPose>,
    keyframes: Sub<[shm_schema::KeyframeRecord], shm_schema::KeyframeHeader>,
    features: Sub<[shm_schema::TrackedFeature], shm_schema::TrackedFeaturesHeader>,
    /// Host-wide: client 0's recording takes them (the service has few subscriber slots).
    corrections: Option<Sub<[shm_schema::CorrectionRecord], shm_schema::CorrectionHeader>>,
    /// The next frame's sequence number, and the frames missed so far.
    next_seq: Option<u64>,
    missed: u64,
}

impl Subscriptions {
    fn open(c: u32, prefix: &str) -> anyhow::Result<Self> {
        let node = topics::create_node(&format!("recorder_c{c}"), prefix)?;
        let corrections = (c == 0)
            .then(|| {
                let service = topics::corrections_service(&node)?;
                topics::slice_subscriber(&service, topics::CORRECTION_BUFFER)
            })
            .transpose()?;
        Ok(Self {
            frames: topics::frame_subscriber(&topics::frames_service(&node, c)?, c)?,
            imu: topics::subscriber(&topics::imu_service(&node, c)?)?,
            poses: topics::subscriber(&topics::poses_service(&node, c)?)?,
            keyframes: topics::keyframe_subscriber(&topics::keyframes_service(&node, c)?)?,
            features: topics::slice_subscriber(
                &topics::features_service(&node, c)?,
                topics::POSE_BUFFER,
            )?,
            corrections,
            node,
            next_seq: None,
            missed: 0,
        })
    }

    /// Takes everything waiting and sends it to the writer; whether anything was.
    fn drain(&mut self, pixels: &Pixels, tx: &mpsc::Sender<Item>) -> anyhow::Result<bool> {
        let mut busy = false;
        let keep_pixels = pixels.wanted();
        while let Some(s) = self.frames.receive()? {
            busy = true;
            let h = s.user_header();
            if h.meta.is_end_of_stream() {
                continue;
            }
            self.missed += self.next_seq.map_or(0, |n| h.meta.seq.saturating_sub(n));
            self.next_seq = Some(h.meta.seq + 1);
            let _ = tx.send(frame_item(h, s.payload(), keep_pixels));
        }
        while let Some(s) = self.imu.receive()? {
            busy = true;
            let m = *s.payload();
            if !m.meta.is_end_of_stream() {
                let (t_ns, gyro, accel) = (m.t_ns, m.gyro, m.accel);
                let _ = tx.send(Item::Imu(datasets::ImuSample { t_ns, gyro, accel }));
            }
        }
        while let Some(s) = self.poses.receive()? {
            busy = true;
            if let Some(item) = pose_item(s.payload()) {
                let _ = tx.send(item);
            }
        }
        while let Some(s) = self.keyframes.receive()? {
            busy = true;
            let h = s.user_header();
            if let Some(pose) = shoal_runtime::wire::iso_from_wire(&h.pose_ck) {
                let _ = tx.send(Item::Keyframe { t_ns: h.t_ns, pose });
            }
        }
        while let Some(s) = self.features.receive()? {
            busy = true;
            let (h, f) = (s.user_header(), s.payload());
            let n = (h.n_features as usize).min(f.len());
            let pixels = f[..n].iter().map(|f| [f.u, f.v]).collect();
            let _ = tx.send(Item::Features {
                t_ns: h.t_ns,
                pixels,
            });
        }
        while let Some(s) = (self.corrections.as_ref().map(|c| c.receive()))
            .transpose()?
            .flatten()
        {
            busy = true;
            if let Some(item) = correction_item(s.user_header()) {
                let _ = tx.send(item);
            }
        }
        Ok(busy)
    }
}

/// A frame as the recording keeps it: 8-bit gray rows of `width` bytes (copied only when
/// `keep_pixels`), else skipped.
fn frame_item(h: &shm_schema::FrameHeader, payload: &[u8], keep_pixels: bool) -> Item {
    let gray = h.pixel_format == PixelFormat::Gray8 as u32;
    let len = (h.width as usize) * (h.height as usize);
    match payload.get(..len) {
        Some(px) if gray && h.stride == h.width => Item::Frame {
            t_ns: h.t_mid_ns,
            width: h.width,
            height: h.height,
            pixels: if keep_pixels { px.to_vec() } else { Vec::new() },
        },
        _ => Item::Skipped,
    }
}

/// Whether the receiver copies a frame's pixels: for a file always, for live viewers only
/// while one watches the image.
struct Pixels {
    file: bool,
    live: Option<LiveOut>,
}

impl Pixels {
    fn wanted(&self) -> bool {
        self.file || (self.live.as_ref()).is_some_and(|l| l.wants(view::topic::IMAGE))
    }
}

/// Client `c`'s side of the live viewer: its topics and frames prefixed by `/c{c}` when
/// the run has several clients.
#[derive(Clone)]
struct LiveOut {
    live: Arc<Live>,
    /// Topic prefix (`/c1`), and frame-id prefix (`c1/`).
    topics: String,
    frames: String,
}

impl LiveOut {
    fn new(live: Arc<Live>, c: usize, n: usize) -> Self {
        let (topics, frames) = if n > 1 {
            (format!("/c{c}"), format!("c{c}/"))
        } else {
            (String::new(), String::new())
        };
        live.advertise(&topics);
        Self {
            live,
            topics,
            frames,
        }
    }

    fn wants(&self, topic: &str) -> bool {
        self.live.wants(&self.topics, topic)
    }

    fn send(&self, t_ns: i64, m: &ViewMsg) {
        self.live.send(&self.topics, t_ns, m);
    }
}

/// Takes client `c`'s messages from shared memory until `stop` (then once more); returns
/// the frames missed. `ready` says whether it subscribed.
fn receive(
    c: u32,
    prefix: &str,
    pixels: &Pixels,
    stop: &AtomicBool,
    tx: &mpsc::Sender<Item>,
    ready: &mpsc::SyncSender<Result<(), String>>,
) -> anyhow::Result<u64> {
    let mut subs = match Subscriptions::open(c, prefix) {
        Ok(s) => {
            let _ = ready.send(Ok(()));
            s
        }
        Err(e) => {
            let _ = ready.send(Err(e.to_string()));
            return Err(e);
        }
    };
    loop {
        let last_round = stop.load(Ordering::SeqCst);
        let busy = subs.drain(pixels, tx)?;
        if last_round || (!busy && subs.node.wait(Duration::from_millis(1)).is_err()) {
            return Ok(subs.missed);
        }
    }
}

/// The frame of the VO session's map (`/shoal/pose`, `/shoal/keyframe`, `/tf`).
use view::MAP_FRAME;
/// The frame of the server map (`/shoal/server_pose`, `/shoal/map`).
use view::SERVER_FRAME;

/// The viewers' channels of a recording.
struct ViewChannels {
    pose: u16,
    tf: u16,
    tf_static: u16,
    keyframe: u16,
    server_pose: u16,
    latency: u16,
    odometry: u16,
    map: u16,
    log: u16,
}

impl ViewChannels {
    fn add(w: &mut StreamWriter) -> Result<Self, datasets::DatasetError> {
        use datasets::mcap_bag::{msgs, view_msgs as v};
        let (pose, tf) = (msgs::pose_stamped_schema(), v::tf_message_schema());
        let mut ch = |name: &str, schema: &str, topic: &str| w.add_channel(name, schema, topic);
        Ok(Self {
            pose: ch(msgs::names::POSE_STAMPED, &pose, POSE_TOPIC)?,
            tf: ch(v::names::TF_MESSAGE, &tf, "/tf")?,
            tf_static: ch(v::names::TF_MESSAGE, &tf, "/tf_static")?,
            keyframe: ch(msgs::names::POSE_STAMPED, &pose, "/shoal/keyframe")?,
            server_pose: ch(msgs::names::POSE_STAMPED, &pose, "/shoal/server_pose")?,
            latency: ch(v::names::FLOAT64, &v::float64_schema(), "/shoal/latency_ms")?,
            odometry: ch(v::names::ODOMETRY, &v::odometry_schema(), ODOMETRY_TOPIC)?,
            map: ch(
                v::names::POINT_CLOUD2,
                &v::point_cloud2_schema(),
                "/shoal/map",
            )?,
            log: ch(v::names::LOG, &v::log_schema(), "/rosout")?,
        })
    }

    /// `/tf_static`: the camera in the IMU body frame (`imu0` → `cam0`, `T_BS`), when the
    /// calibration gives it.
    fn camera_imu(
        &self,
        w: &mut StreamWriter,
        t_ns: i64,
        camera: &datasets::CameraCalib,
    ) -> Result<(), datasets::DatasetError> {
        if !camera.t_bs_given {
            return Ok(());
        }
        let tf = Self::transform(w, t_ns, &camera.t_bs, "imu0", "cam0")?;
        w.put_msg(self.tf_static, t_ns, &tf, 160)
    }

    /// A one-transform `/tf` message: `child` at `pose` in `parent`.
    fn transform(
        w: &StreamWriter,
        t_ns: i64,
        pose: &nalgebra::Isometry3<f64>,
        parent: &str,
        child: &str,
    ) -> Result<datasets::mcap_bag::view_msgs::TfMessage<'static>, datasets::DatasetError> {
        use datasets::mcap_bag::view_msgs as v;
        let m = datasets::mcap_bag::write::pose_msg(pose, parent, w.ros_time(t_ns)?);
        Ok(v::TfMessage {
            transforms: vec![v::TransformStamped {
                header: m.header,
                child_frame_id: child.to_string().into(),
                transform: v::Transform {
                    translation: m.pose.position,
                    rotation: m.pose.orientation,
                },
            }],
        })
    }

    /// A tracked frame: its pose (and `/tf` map → cam0), its server-map pose, its latency.
    fn pose(
        &self,
        w: &mut StreamWriter,
        t_ns: i64,
        pose: Option<&nalgebra::Isometry3<f64>>,
        server: Option<&nalgebra::Isometry3<f64>>,
        latency_ms: Option<f64>,
    ) -> Result<(), datasets::DatasetError> {
        use datasets::mcap_bag::view_msgs as v;
        if let Some(p) = pose {
            w.pose(Some(self.pose), t_ns, p, MAP_FRAME)?;
            let tf = Self::transform(w, t_ns, p, MAP_FRAME, "cam0")?;
            w.put_msg(self.tf, t_ns, &tf, 160)?;
            w.put_msg(self.odometry, t_ns, &Self::odometry(w, t_ns, p)?, 760)?;
        }
        if let Some(p) = server {
            w.pose(Some(self.server_pose), t_ns, p, SERVER_FRAME)?;
        }
        match latency_ms {
            Some(data) => w.put_msg(self.latency, t_ns, &v::Float64 { data }, 16),
            None => Ok(()),
        }
    }

    /// `cam0`'s pose in `map` as odometry: no velocity (the tracker sends none), the
    /// covariances all zero (unknown).
    fn odometry(
        w: &StreamWriter,
        t_ns: i64,
        pose: &nalgebra::Isometry3<f64>,
    ) -> Result<datasets::mcap_bag::view_msgs::Odometry<'static>, datasets::DatasetError> {
        use datasets::mcap_bag::{msgs, view_msgs as v};
        let m = datasets::mcap_bag::write::pose_msg(pose, MAP_FRAME, w.ros_time(t_ns)?);
        let zero = msgs::Vector3 {
            x: 0.0,
            y: 0.0,
            z: 0.0,
        };
        Ok(v::Odometry {
            header: m.header,
            child_frame_id: "cam0".into(),
            pose: v::PoseWithCovariance {
                pose: m.pose,
                covariance: v::Covariance6([0.0; 36]),
            },
            twist: v::TwistWithCovariance {
                twist: v::Twist {
                    linear: zero,
                    angular: zero,
                },
                covariance: v::Covariance6([0.0; 36]),
            },
        })
    }

    /// A log line of `name` at `t_ns` (`/rosout`).
    fn log(
        &self,
        w: &mut StreamWriter,
        t_ns: i64,
        name: &str,
        msg: &str,
    ) -> Result<(), datasets::DatasetError> {
        let line = datasets::mcap_bag::view_msgs::Log {
            stamp: w.ros_time(t_ns)?,
            level: 20,
            name: name.into(),
            msg: msg.into(),
            file: "".into(),
            function: "".into(),
            line: 0,
        };
        w.put_msg(self.log, t_ns, &line, msg.len() + 64)
    }

    /// The server map's points at `t_ns`.
    fn map(
        &self,
        w: &mut StreamWriter,
        t_ns: i64,
        points: &[[f32; 3]],
    ) -> Result<(), datasets::DatasetError> {
        use datasets::mcap_bag::{msgs, view_msgs as v};
        let data: Vec<u8> = points
            .iter()
            .flatten()
            .flat_map(|c| c.to_le_bytes())
            .collect();
        let header = msgs::Header {
            stamp: w.ros_time(t_ns)?,
            frame_id: SERVER_FRAME.into(),
        };
        w.put_msg(
            self.map,
            t_ns,
            &v::PointCloud2::xyz(header, &data),
            data.len() + 256,
        )
    }
}

/// A correction as a log line (kind, keyframes, maps, scale, inliers) and an edge
/// between its keyframes (`None`: the loop closer's lock-step "done" message, or another
/// schema's).
fn correction_item(h: &shm_schema::CorrectionHeader) -> Option<Item> {
    let (kind, merge) = match h.kind {
        shm_schema::CORRECTION_MERGE => ("merge", true),
        shm_schema::CORRECTION_POSE_GRAPH => ("loop (pose graph)", false),
        _ => return None,
    };
    h.meta.check().ok()?;
    let line = format!(
        "correction {}: {kind}: keyframe {:#x} matches {:#x}, map {:#x} into {:#x}, scale {:.4}, \
         {} inliers",
        h.correction_id, h.query_kf, h.matched_kf, h.from_map, h.into_map, h.scale, h.inliers
    );
    let edge = view::LoopEdge {
        merge,
        query: h.query_kf,
        matched: h.matched_kf,
    };
    Some(Item::Correction(line, edge))
}

/// A pose message as the recording keeps it: not the end of the stream nor a move of the
/// VO world (`FLAG_WORLD_MOVE`: its pose is a transform, not a camera's); a pose found
/// later (`FLAG_BACKFILL`) has no latency.
fn pose_item(p: &shm_schema::TrackedPose) -> Option<Item> {
    if p.meta.is_end_of_stream() || p.meta.flags & shm_schema::FLAG_WORLD_MOVE != 0 {
        return None;
    }
    let tracking = TrackState::from_u32(p.state) == Some(TrackState::Tracking);
    let live = p.meta.flags & shm_schema::FLAG_BACKFILL == 0;
    let wire = shoal_runtime::wire::iso_from_wire;
    Some(Item::Pose {
        t_ns: p.t_ns,
        pose: wire(&p.pose).filter(|_| tracking),
        server: wire(&p.server_pose).filter(|_| p.has_server_pose != 0),
        latency_ms: (live && p.frame_publish_mono_ns > 0)
            .then(|| (p.meta.publish_mono_ns - p.frame_publish_mono_ns) as f64 * 1e-6),
    })
}

/// The file side of a recording: the ROS 2 writer, its viewer channels, and the Foxglove
/// channels made as their topics first come.
struct FileOut {
    w: StreamWriter,
    ch: ViewChannels,
    fg: BTreeMap<&'static str, u16>,
    /// No frame written yet (the camera, its transform and the ground truth go first).
    first: bool,
}

impl FileOut {
    fn create(file: &Path, meta: &ShoalMeta) -> Result<Self, datasets::DatasetError> {
        let settings = WriteSettings {
            compression: datasets::mcap_bag::write::Compression::Lz4,
            chunk_bytes: None,
        };
        let mut w = StreamWriter::create(file, meta, &settings)?;
        let ch = ViewChannels::add(&mut w)?;
        Ok(Self {
            w,
            ch,
            fg: BTreeMap::new(),
            first: true,
        })
    }

    /// Drops the unfinished file.
    fn abandon(self) {
        self.w.abandon();
    }

    /// Writes a viewer message in Foxglove's schema at `t_ns`.
    fn view(&mut self, t_ns: i64, m: &ViewMsg) -> Result<(), datasets::DatasetError> {
        if !m.in_file() {
            return Ok(());
        }
        let id = match self.fg.get(m.topic()) {
            Some(id) => *id,
            None => {
                let (schema, encoding) = m.schema();
                let id = self.w.add_encoded_channel(
                    &schema.name,
                    &schema.encoding,
                    &schema.data,
                    encoding,
                    m.topic(),
                )?;
                *self.fg.entry(m.topic()).or_insert(id)
            }
        };
        self.w.put(id, t_ns, &m.encode())
    }

    /// Writes what crosses shared memory (the ROS 2 topics), counting it in `r`.
    fn item(
        &mut self,
        item: &Item,
        meta: &ShoalMeta,
        truth: &[datasets::StampedPose],
        last_t: i64,
        r: &mut RecordReport,
    ) -> Result<(), datasets::DatasetError> {
        let (w, ch) = (&mut self.w, &self.ch);
        match item {
            Item::Frame {
                t_ns,
                width,
                height,
                pixels,
            } => {
                if std::mem::take(&mut self.first) {
                    w.camera_info(&meta.camera, *t_ns)?;
                    ch.camera_imu(w, *t_ns, &meta.camera)?;
                    for p in truth {
                        w.pose(None, p.t_ns, &p.pose, "world")?;
                    }
                }
                w.image(*t_ns, *width, *height, pixels)?;
            }
            Item::Imu(s) => w.imu(s)?,
            Item::Pose {
                t_ns,
                pose,
                server,
                latency_ms,
            } => {
                r.poses += u64::from(pose.is_some());
                ch.pose(w, *t_ns, pose.as_ref(), server.as_ref(), *latency_ms)?;
            }
            Item::Keyframe { t_ns, pose } => {
                w.pose(Some(ch.keyframe), *t_ns, pose, MAP_FRAME)?;
                r.keyframes += 1;
            }
            Item::Features { .. } => r.feature_frames += 1,
            Item::Map(m) => {
                r.map_points = m.points.len() as u64;
                ch.map(w, last_t, &m.points)?;
            }
            Item::Correction(line, _) => {
                ch.log(w, last_t, "loop_closer", line)?;
                r.corrections += 1;
            }
            Item::Skipped => r.frames_skipped += 1,
        }
        Ok(())
    }
}

/// What the viewers get of `item` (Foxglove's schemas), from the client's view state.
fn view_of(
    view: &mut ViewState,
    item: &Item,
    meta: &ShoalMeta,
    first_frame: bool,
    out: &mut Vec<ViewMsg>,
) {
    match item {
        Item::Frame { t_ns, .. } if first_frame && meta.camera.t_bs_given => {
            out.push(view.camera_imu(*t_ns, &meta.camera.t_bs));
        }
        Item::Pose {
            t_ns, pose, server, ..
        } => view.pose(*t_ns, pose.as_ref(), server.as_ref(), out),
        Item::Keyframe { t_ns, pose } => out.push(view.keyframe(*t_ns, pose)),
        Item::Features { t_ns, pixels } => out.push(ViewState::features(*t_ns, pixels)),
        Item::Correction(_, edge) => view.correction(*edge),
        Item::Map(m) => view.finish(Some(m), out),
        _ => {}
    }
}

/// Sends what `rx` brings to `file` (when given) and to the live viewers (when given)
/// until every sender is gone.
fn write(
    file: Option<&Path>,
    live: Option<LiveOut>,
    meta: &ShoalMeta,
    truth: &[datasets::StampedPose],
    rx: &mpsc::Receiver<Item>,
) -> RecordReport {
    let mut r = RecordReport {
        file: file.map(|f| f.display().to_string()).unwrap_or_default(),
        ..RecordReport::default()
    };
    // LZ4 and a lower priority: the recording must not take the trackers' CPU
    // (BENCHMARKS.md "Recording": zstd at normal priority cost ~10% of tracking p50).
    lower_priority();
    let mut out = file.and_then(|f| match FileOut::create(f, meta) {
        Ok(o) => Some(o),
        Err(e) => {
            r.error = Some(e.to_string());
            None
        }
    });
    let frames = live.as_ref().map_or("", |l| l.frames.as_str());
    let mut view = ViewState::new(frames);
    let (mut first, mut last_t, mut msgs) = (true, 0, Vec::new());
    let mut ended = false;
    for item in rx {
        msgs.clear();
        let first_frame = matches!(item, Item::Frame { .. }) && std::mem::take(&mut first);
        ended |= matches!(item, Item::Map(_));
        view_of(&mut view, &item, meta, first_frame, &mut msgs);
        if let Some(o) = out.as_mut() {
            let written = (o.item(&item, meta, truth, last_t, &mut r)).and_then(|()| {
                msgs.iter()
                    .try_for_each(|m| o.view(item_t(&item, last_t), m))
            });
            if let Err(e) = written {
                r.error = Some(e.to_string());
                if let Some(o) = out.take() {
                    o.abandon();
                }
            }
        }
        if let Item::Frame { t_ns, .. } = &item {
            last_t = last_t.max(*t_ns);
        }
        if let Some(l) = &live {
            send_live(l, &view, item, last_t, &msgs);
        }
    }
    if !ended {
        // No map at the end (no saved-map file): the final paths still go out.
        msgs.clear();
        view.finish(None, &mut msgs);
        for m in &msgs {
            if let Some(o) = out.as_mut() {
                let _ = o.view(last_t, m);
            }
            if let Some(l) = &live {
                l.send(last_t, m);
            }
        }
    }
    if let Some(o) = out {
        match o.w.finish() {
            Ok(s) => {
                r.frames = s.frames as u64;
                r.imu_samples = s.imu_samples as u64;
                r.bytes = s.bytes;
            }
            Err(e) => r.error = Some(e.to_string()),
        }
    }
    r
}

/// The log time of the viewer messages of `item`: its own, else the last frame's.
fn item_t(item: &Item, last_t: i64) -> i64 {
    match item {
        Item::Frame { t_ns, .. }
        | Item::Pose { t_ns, .. }
        | Item::Keyframe { t_ns, .. }
        | Item::Features { t_ns, .. } => *t_ns,
        _ => last_t,
    }
}

/// Sends `msgs` (and the image and latency, which only live viewers get) of `item`.
fn send_live(l: &LiveOut, view: &ViewState, item: Item, last_t: i64, msgs: &[ViewMsg]) {
    let t_ns = item_t(&item, last_t);
    for m in msgs {
        l.send(t_ns, m);
    }
    match item {
        Item::Frame {
            t_ns,
            width,
            height,
            pixels,
        } if !pixels.is_empty() && l.wants(view::topic::IMAGE) => {
            l.send(t_ns, &view.image(t_ns, width, height, pixels));
        }
        Item::Pose {
            t_ns,
            latency_ms: Some(ms),
            ..
        } => l.send(t_ns, &ViewMsg::Latency(ms)),
        _ => {}
    }
}

/// Client `c`'s server map in `file`: the points of the largest map holding keyframes of
/// it, else (a `--localize-only` run, whose file is the loaded one) of the largest map;
/// the centres of every map's keyframes (the ends of the loop edges).
pub fn map_view(file: &map_store::MapFile, c: u32) -> view::MapView {
    let size = |m: &&map_store::SavedMap| m.map.map.keyframes.len();
    let mine = file
        .maps
        .iter()
        .filter(|m| m.clients.contains(&c))
        .max_by_key(size);
    let centres = (file.maps.iter())
        .flat_map(|m| m.map.map.keyframes.iter())
        .map(|(id, k)| (*id, k.center().into()))
        .collect();
    let Some(m) = mine.or_else(|| file.maps.iter().max_by_key(size)) else {
        return view::MapView {
            centres,
            ..Default::default()
        };
    };
    let p = m.map.map.points.values();
    let points = p
        .map(|p| [p.p_w.x as f32, p.p_w.y as f32, p.p_w.z as f32])
        .collect();
    view::MapView { points, centres }
}

/// The saved-map file a recording (or the live viewer) takes the server map's points from: `--save-map`'s,
/// else the loaded one under `--localize-only` (unchanged), else one the mapper writes
/// for it in the output folder.
pub fn map_file(cfg: &crate::config::RunConfig) -> Option<PathBuf> {
    if cfg.record.is_none() && cfg.viz.is_none() {
        return None;
    }
    match (&cfg.save_map, cfg.localize_only) {
        (Some(p), _) => Some(p.clone()),
        (None, true) => cfg.load_map.clone(),
        (None, false) => Some(cfg.out.join(MAP_FILE)),
    }
}

/// The saved-map file the mapper writes for a recording without `--save-map`.
pub const MAP_FILE: &str = "record_map.shoalmap";

/// Lowers the calling thread's scheduling priority (nice +10; Linux threads have their
/// own): best effort, a failure leaves it as it was.
fn lower_priority() {
    // SAFETY: plain system calls on the calling thread, no memory handed over.
    unsafe {
        let tid = libc::syscall(libc::SYS_gettid) as libc::id_t;
        libc::setpriority(libc::PRIO_PROCESS, tid, 10);
    }
}

/// Client `c`'s calibration record for the recording: the dataset's camera (with
/// `--calib`'s in its place) and IMU model, middle-row stamps, and the ground-truth topic
/// when the dataset has one.
pub fn meta_of(ds: &datasets::Dataset, calib: Option<&Path>) -> anyhow::Result<ShoalMeta> {
    let imu = match (calib, super::modes::dataset_imu(ds)) {
        (Some(file), _) => Some(datasets::calibration::CalibrationFile::read(file)?.imu_calib()),
        (None, Some(y)) => y.ok().map(|y| y.0),
        (None, None) => None,
    };
    Ok(ShoalMeta {
        camera: ds.camera.clone(),
        imu,
        middle_row: true,
        ground_truth_topic: ds.ground_truth.as_ref().map(|_| GROUND_TRUTH_TOPIC.into()),
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    /// One client records to the file asked for; several to one file each.
    #[test]
    fn one_file_per_client() {
        let p = Path::new("/tmp/run.mcap");
        assert_eq!(file_of(p, 0, 1), p);
        assert_eq!(file_of(p, 1, 2), Path::new("/tmp/run_c1.mcap"));
    }
}
