//! What a viewer shows of a run, in Foxglove's schemas (issue 21): built once from what
//! the recorder takes from shared memory ([`super::record`]) and sent both into the
//! recording (`--record`, beside its ROS 2 topics) and to Foxglove's WebSocket server
//! (`--viz`, [`Live`]).
//!
//! - `/shoal/transforms` (`foxglove.FrameTransforms`): the camera in its VO map
//!   (`map` → `cam0`) at every tracked frame, and the camera in the IMU body frame
//!   (`imu0` → `cam0`) once when the calibration has it;
//! - `/shoal/trajectory` and `/shoal/server_trajectory` (`foxglove.PosesInFrame`): the
//!   camera path so far in the VO map and in the server map (from the feedback), once a
//!   second of data time and at the end; `/shoal/keyframes`: the keyframes sent so far;
//! - `/cam0/features` (`foxglove.ImageAnnotations`): the frame's keypoints that matched a
//!   map point, stamped as the frame's image so that the Image panel draws them on it;
//! - at the end, from the saved-map file: `/shoal/map_points` (`foxglove.PointCloud`) and
//!   `/shoal/loops` (`foxglove.SceneUpdate`, a line between the keyframes of each loop the
//!   loop closer found, and of each merge), both in `server_map`;
//! - live only (the file has them as ROS 2 messages): `/cam0/image` (`foxglove.RawImage`)
//!   and `/shoal/latency` (JSON `{"ms": …}`, publish to pose).
use std::collections::{BTreeMap, HashMap};
use std::sync::{Arc, Mutex};

use foxglove::messages as fg;
use foxglove::Encode;
use nalgebra::Isometry3;

/// The topics.
pub mod topic {
    /// Camera transforms.
    pub const TRANSFORMS: &str = "/shoal/transforms";
    /// The camera path in the VO map.
    pub const TRAJECTORY: &str = "/shoal/trajectory";
    /// The camera path in the server map.
    pub const SERVER_TRAJECTORY: &str = "/shoal/server_trajectory";
    /// The keyframes sent.
    pub const KEYFRAMES: &str = "/shoal/keyframes";
    /// The tracked features on the image.
    pub const FEATURES: &str = "/cam0/features";
    /// The server map's points.
    pub const MAP_POINTS: &str = "/shoal/map_points";
    /// Loop and merge edges.
    pub const LOOPS: &str = "/shoal/loops";
    /// The image (live).
    pub const IMAGE: &str = "/cam0/image";
    /// Frame publish to pose publish, ms (live).
    pub const LATENCY: &str = "/shoal/latency";
}

/// The VO map's frame.
pub const MAP_FRAME: &str = "map";
/// The server map's frame.
pub const SERVER_FRAME: &str = "server_map";
/// The trajectories are sent at most this often (data time), ns.
const PATH_PERIOD_NS: i64 = 1_000_000_000;

/// One message for a viewer.
#[derive(Debug, Clone)]
pub enum ViewMsg {
    /// `foxglove.FrameTransforms`.
    Transforms(fg::FrameTransforms),
    /// `foxglove.PosesInFrame` on a topic.
    Poses(&'static str, fg::PosesInFrame),
    /// `foxglove.ImageAnnotations`.
    Annotations(fg::ImageAnnotations),
    /// `foxglove.PointCloud`.
    Cloud(fg::PointCloud),
    /// `foxglove.SceneUpdate`.
    Scene(fg::SceneUpdate),
    /// `foxglove.RawImage` (live only).
    Image(fg::RawImage),
    /// A latency, ms (live only).
    Latency(f64),
}

/// JSON schema of [`ViewMsg::Latency`].
const LATENCY_SCHEMA: &str = r#"{"type":"object","properties":{"ms":{"type":"number"}}}"#;

impl ViewMsg {
    /// Its topic.
    pub fn topic(&self) -> &'static str {
        match self {
            Self::Transforms(_) => topic::TRANSFORMS,
            Self::Poses(t, _) => t,
            Self::Annotations(_) => topic::FEATURES,
            Self::Cloud(_) => topic::MAP_POINTS,
            Self::Scene(_) => topic::LOOPS,
            Self::Image(_) => topic::IMAGE,
            Self::Latency(_) => topic::LATENCY,
        }
    }

    /// Whether the recording file takes it (it has images and latencies as ROS 2
    /// messages already).
    pub fn in_file(&self) -> bool {
        !matches!(self, Self::Image(_) | Self::Latency(_))
    }

    /// Its schema and message encoding.
    pub fn schema(&self) -> (foxglove::Schema, &'static str) {
        fn of<T: Encode>() -> foxglove::Schema {
            T::get_schema().expect("Foxglove's message types have schemas")
        }
        let schema = match self {
            Self::Transforms(_) => of::<fg::FrameTransforms>(),
            Self::Poses(..) => of::<fg::PosesInFrame>(),
            Self::Annotations(_) => of::<fg::ImageAnnotations>(),
            Self::Cloud(_) => of::<fg::PointCloud>(),
            Self::Scene(_) => of::<fg::SceneUpdate>(),
            Self::Image(_) => of::<fg::RawImage>(),
            Self::Latency(_) => {
                let data = LATENCY_SCHEMA.as_bytes();
                return (
                    foxglove::Schema::new("shoal.Latency", "jsonschema", data),
                    "json",
                );
            }
        };
        (schema, "protobuf")
    }

    /// Its encoding.
    pub fn encode(&self) -> Vec<u8> {
        fn enc<T: Encode>(m: &T) -> Vec<u8> {
            let mut buf = Vec::with_capacity(m.encoded_len().unwrap_or(256));
            // Encoding into a growing Vec cannot run out of room.
            let _ = m.encode(&mut buf);
            buf
        }
        match self {
            Self::Transforms(m) => enc(m),
            Self::Poses(_, m) => enc(m),
            Self::Annotations(m) => enc(m),
            Self::Cloud(m) => enc(m),
            Self::Scene(m) => enc(m),
            Self::Image(m) => enc(m),
            Self::Latency(ms) => format!("{{\"ms\":{ms}}}").into_bytes(),
        }
    }
}

/// A time in Foxglove's form (negative times, which no recording holds, clamp to 0).
pub fn stamp(t_ns: i64) -> fg::Timestamp {
    let t = t_ns.max(0);
    fg::Timestamp::new((t / 1_000_000_000) as u32, (t % 1_000_000_000) as u32)
}

/// A pose in Foxglove's form.
pub fn pose(p: &Isometry3<f64>) -> fg::Pose {
    let (t, q) = (p.translation.vector, p.rotation.quaternion());
    fg::Pose {
        position: Some(fg::Vector3 {
            x: t.x,
            y: t.y,
            z: t.z,
        }),
        orientation: Some(fg::Quaternion {
            x: q.i,
            y: q.j,
            z: q.k,
            w: q.w,
        }),
    }
}

/// `child` at `p` in `parent`, at `t_ns`.
pub fn transform(t_ns: i64, p: &Isometry3<f64>, parent: &str, child: &str) -> fg::FrameTransform {
    let fg::Pose {
        position,
        orientation,
    } = pose(p);
    fg::FrameTransform {
        timestamp: Some(stamp(t_ns)),
        parent_frame_id: parent.into(),
        child_frame_id: child.into(),
        translation: position,
        rotation: orientation,
    }
}

/// What the end of a run adds: the server map's points and its keyframes' centres.
#[derive(Debug, Clone, Default)]
pub struct MapView {
    /// Points, server map frame.
    pub points: Vec<[f32; 3]>,
    /// Keyframe centres by server keyframe id (every map of the file).
    pub centres: HashMap<u64, [f64; 3]>,
}

/// A loop or merge the loop closer sent: its kind and the two keyframes.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct LoopEdge {
    /// A merge (two maps joined) rather than a loop in one map.
    pub merge: bool,
    /// The query keyframe.
    pub query: u64,
    /// The keyframe it matched.
    pub matched: u64,
}

/// The viewer's state of one client: the paths so far, and the loops.
#[derive(Debug, Default)]
pub struct ViewState {
    /// Frame-id prefix (`c1/` with several clients live; empty in a file).
    prefix: String,
    trajectory: Vec<fg::Pose>,
    server: Vec<fg::Pose>,
    keyframes: Vec<fg::Pose>,
    last_path_ns: Option<i64>,
    last_t_ns: i64,
    loops: Vec<LoopEdge>,
}

impl ViewState {
    /// A state whose frame ids start with `prefix`.
    pub fn new(prefix: &str) -> Self {
        Self {
            prefix: prefix.to_string(),
            ..Self::default()
        }
    }

    fn frame(&self, id: &str) -> String {
        format!("{}{id}", self.prefix)
    }

    /// The camera-IMU transform, once (`T_BS`: the camera in the body frame).
    pub fn camera_imu(&self, t_ns: i64, t_bs: &Isometry3<f64>) -> ViewMsg {
        let (imu, cam) = (self.frame("imu0"), self.frame("cam0"));
        ViewMsg::Transforms(fg::FrameTransforms {
            transforms: vec![transform(t_ns, t_bs, &imu, &cam)],
        })
    }

    /// A frame's poses (camera-to-map, VO and server map), and the paths when due.
    pub fn pose(
        &mut self,
        t_ns: i64,
        vo: Option<&Isometry3<f64>>,
        server: Option<&Isometry3<f64>>,
        out: &mut Vec<ViewMsg>,
    ) {
        self.last_t_ns = self.last_t_ns.max(t_ns);
        if let Some(p) = vo {
            let (map, cam) = (self.frame(MAP_FRAME), self.frame("cam0"));
            out.push(ViewMsg::Transforms(fg::FrameTransforms {
                transforms: vec![transform(t_ns, p, &map, &cam)],
            }));
            self.trajectory.push(pose(p));
        }
        if let Some(p) = server {
            self.server.push(pose(p));
        }
        let due = self
            .last_path_ns
            .is_none_or(|last| t_ns - last >= PATH_PERIOD_NS);
        if due && (vo.is_some() || server.is_some()) {
            self.last_path_ns = Some(t_ns);
            self.paths(t_ns, out);
        }
    }

    /// Both paths as they are.
    fn paths(&self, t_ns: i64, out: &mut Vec<ViewMsg>) {
        let paths = [
            (topic::TRAJECTORY, MAP_FRAME, &self.trajectory),
            (topic::SERVER_TRAJECTORY, SERVER_FRAME, &self.server),
        ];
        for (topic, frame, poses) in paths {
            if !poses.is_empty() {
                out.push(ViewMsg::Poses(topic, self.poses(t_ns, frame, poses)));
            }
        }
    }

    fn poses(&self, t_ns: i64, frame: &str, poses: &[fg::Pose]) -> fg::PosesInFrame {
        fg::PosesInFrame {
            timestamp: Some(stamp(t_ns)),
            frame_id: self.frame(frame),
            poses: poses.to_vec(),
        }
    }

    /// A keyframe the tracker sent (camera-to-map): every keyframe so far.
    pub fn keyframe(&mut self, t_ns: i64, p: &Isometry3<f64>) -> ViewMsg {
        self.keyframes.push(pose(p));
        let poses = self.poses(t_ns, MAP_FRAME, &self.keyframes);
        ViewMsg::Poses(topic::KEYFRAMES, poses)
    }

    /// A frame's tracked features (pixels of keypoints matched to map points).
    pub fn features(t_ns: i64, pixels: &[[f32; 2]]) -> ViewMsg {
        let green = fg::Color {
            r: 0.1,
            g: 0.9,
            b: 0.2,
            a: 1.0,
        };
        let points = pixels.iter().map(|p| fg::Point2 {
            // Foxglove's origin is the top-left pixel's corner; ours its centre.
            x: f64::from(p[0]) + 0.5,
            y: f64::from(p[1]) + 0.5,
        });
        ViewMsg::Annotations(fg::ImageAnnotations {
            points: vec![fg::PointsAnnotation {
                timestamp: Some(stamp(t_ns)),
                r#type: fg::points_annotation::Type::Points as i32,
                points: points.collect(),
                outline_color: Some(green),
                fill_color: Some(green),
                thickness: 3.0,
                ..Default::default()
            }],
            ..Default::default()
        })
    }

    /// The frame's image (live), 8-bit gray rows.
    pub fn image(&self, t_ns: i64, width: u32, height: u32, pixels: Vec<u8>) -> ViewMsg {
        ViewMsg::Image(fg::RawImage {
            timestamp: Some(stamp(t_ns)),
            frame_id: self.frame("cam0"),
            width,
            height,
            encoding: "mono8".into(),
            step: width,
            data: pixels.into(),
        })
    }

    /// A correction of the loop closer: kept for the end (its keyframes' final places).
    pub fn correction(&mut self, edge: LoopEdge) {
        self.loops.push(edge);
    }

    /// The end: the final paths, the map's points and the loop edges between its
    /// keyframes' final centres.
    pub fn finish(&self, map: Option<&MapView>, out: &mut Vec<ViewMsg>) {
        let t_ns = self.last_t_ns;
        self.paths(t_ns, out);
        let Some(map) = map else { return };
        out.push(ViewMsg::Cloud(self.cloud(t_ns, &map.points)));
        out.push(ViewMsg::Scene(self.loop_lines(t_ns, &map.centres)));
    }

    fn cloud(&self, t_ns: i64, points: &[[f32; 3]]) -> fg::PointCloud {
        use fg::packed_element_field::NumericType;
        let field = |name: &str, offset: u32| fg::PackedElementField {
            name: name.into(),
            offset,
            r#type: NumericType::Float32 as i32,
        };
        let data: Vec<u8> = points
            .iter()
            .flatten()
            .flat_map(|c| c.to_le_bytes())
            .collect();
        fg::PointCloud {
            timestamp: Some(stamp(t_ns)),
            frame_id: self.frame(SERVER_FRAME),
            pose: Some(pose(&Isometry3::identity())),
            point_stride: 12,
            fields: vec![field("x", 0), field("y", 4), field("z", 8)],
            data: data.into(),
        }
    }

    /// One entity of line segments (`LINE_LIST`): loops orange, merges blue; an edge whose
    /// keyframes the map no longer has (culled) is left out.
    fn loop_lines(&self, t_ns: i64, centres: &HashMap<u64, [f64; 3]>) -> fg::SceneUpdate {
        let colour = |merge: bool| fg::Color {
            r: if merge { 0.2 } else { 1.0 },
            g: if merge { 0.5 } else { 0.55 },
            b: if merge { 1.0 } else { 0.0 },
            a: 1.0,
        };
        let point = |c: &[f64; 3]| fg::Point3 {
            x: c[0],
            y: c[1],
            z: c[2],
        };
        let (mut points, mut colors) = (vec![], vec![]);
        for e in &self.loops {
            if let (Some(a), Some(b)) = (centres.get(&e.query), centres.get(&e.matched)) {
                points.extend([point(a), point(b)]);
                colors.extend([colour(e.merge), colour(e.merge)]);
            }
        }
        let line = fg::LinePrimitive {
            r#type: fg::line_primitive::Type::LineList as i32,
            pose: Some(pose(&Isometry3::identity())),
            thickness: 3.0,
            scale_invariant: true,
            points,
            colors,
            ..Default::default()
        };
        fg::SceneUpdate {
            entities: vec![fg::SceneEntity {
                timestamp: Some(stamp(t_ns)),
                frame_id: self.frame(SERVER_FRAME),
                id: "loops".into(),
                lines: vec![line],
                ..Default::default()
            }],
            ..Default::default()
        }
    }
}

/// The live viewer: Foxglove's WebSocket server (`--viz`), its channels made as topics
/// first come. A message is encoded only when a viewer subscribes to its topic, so with
/// nobody connected a run pays nothing but the recorder's shared-memory reads.
pub struct Live {
    context: Arc<foxglove::Context>,
    server: Mutex<Option<foxglove::WebSocketServerHandle>>,
    channels: Mutex<BTreeMap<String, Arc<foxglove::RawChannel>>>,
    /// The address it listens on.
    pub addr: std::net::SocketAddr,
}

impl Live {
    /// Listens on `host:port` (port 0: any free one).
    pub fn start(host: &str, port: u16) -> anyhow::Result<Arc<Self>> {
        let context = foxglove::Context::new();
        let server = foxglove::WebSocketServer::new()
            .name("shoal")
            .bind(host, port)
            .context(&context)
            .start_blocking()
            .map_err(|e| anyhow::anyhow!("--viz: cannot serve on {host}:{port}: {e}"))?;
        let ip = host.parse().unwrap_or(std::net::Ipv4Addr::LOCALHOST.into());
        let addr = std::net::SocketAddr::new(ip, server.port());
        Ok(Arc::new(Self {
            context,
            server: Mutex::new(Some(server)),
            channels: Mutex::new(BTreeMap::new()),
            addr,
        }))
    }

    /// Viewers connected now.
    pub fn clients(&self) -> usize {
        let server = self.server.lock().unwrap_or_else(|e| e.into_inner());
        server.as_ref().map_or(0, |s| s.client_count())
    }

    /// The channel of `topic` (with `prefix`) for messages like `m`.
    fn channel(&self, prefix: &str, m: &ViewMsg) -> Option<Arc<foxglove::RawChannel>> {
        let topic = format!("{prefix}{}", m.topic());
        let mut channels = self.channels.lock().unwrap_or_else(|e| e.into_inner());
        if let Some(c) = channels.get(&topic) {
            return Some(c.clone());
        }
        let (schema, encoding) = m.schema();
        let c = foxglove::ChannelBuilder::new(&topic)
            .schema(schema)
            .message_encoding(encoding)
            .context(&self.context)
            .build_raw()
            .ok()?;
        channels.insert(topic, c.clone());
        Some(c)
    }

    /// Makes the channels of a client's topics (with `prefix`), so that a viewer sees and
    /// can subscribe to them before their first message.
    pub fn advertise(&self, prefix: &str) {
        let kinds = [
            ViewMsg::Transforms(Default::default()),
            ViewMsg::Poses(topic::TRAJECTORY, Default::default()),
            ViewMsg::Poses(topic::SERVER_TRAJECTORY, Default::default()),
            ViewMsg::Poses(topic::KEYFRAMES, Default::default()),
            ViewMsg::Annotations(Default::default()),
            ViewMsg::Cloud(Default::default()),
            ViewMsg::Scene(Default::default()),
            ViewMsg::Image(Default::default()),
            ViewMsg::Latency(0.0),
        ];
        for m in &kinds {
            self.channel(prefix, m);
        }
    }

    /// Whether a viewer subscribes to `topic` (with `prefix`).
    pub fn wants(&self, prefix: &str, topic: &str) -> bool {
        let channels = self.channels.lock().unwrap_or_else(|e| e.into_inner());
        channels
            .get(&format!("{prefix}{topic}"))
            .is_some_and(|c| c.has_sinks())
    }

    /// Sends `m` at log time `t_ns` to the viewers subscribed to its topic.
    pub fn send(&self, prefix: &str, t_ns: i64, m: &ViewMsg) {
        let Some(c) = self.channel(prefix, m) else {
            return;
        };
        if c.has_sinks() {
            let meta = foxglove::PartialMetadata::with_log_time(t_ns.max(0) as u64);
            c.log_with_meta(&m.encode(), meta);
        }
    }

    /// Stops serving.
    pub fn stop(&self) {
        let server = self.server.lock().unwrap_or_else(|e| e.into_inner()).take();
        if let Some(s) = server {
            s.stop().wait_blocking();
        }
    }
}
