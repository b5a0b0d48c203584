//! ROS 1 bags (issue 21; EuRoC and TUM-VI ship theirs this way): `shoal run --dataset
//! FILE.bag`, read with the `rosbag` crate (the container: records, chunks, bz2/lz4
//! compression, the index) and [`msgs`] (the messages).
//!
//! **What is read**: images from `sensor_msgs/Image` (`mono8`, `rgb8`, `bgr8`) or
//! `sensor_msgs/CompressedImage` (JPEG, PNG), turned into 8-bit gray as an MCAP's are
//! ([`crate::mcap_bag::pixels`]); IMU samples from `sensor_msgs/Imu`; the camera from the
//! first `sensor_msgs/CameraInfo` of the image topic's namespace (or the only one).
//! Topics as for MCAP: `--image-topic` / `--imu-topic`, else by type (raw before
//! compressed, then by name).
//!
//! **Times**: header stamps, the first row's time (the camera-driver convention): the
//! dataset is [`crate::Dataset::first_row_stamps`], and a calibration file adds its
//! `t_r/2 + t_d`.
//!
//! **Streaming**: opening reads the bag once, one chunk at a time, and keeps each image's
//! chunk and place in it ([`Ros1FrameRef`]); the replay reads images on demand
//! ([`Ros1FrameLoader`], which keeps the last chunk's images). The bag is memory-mapped.
//!
//! **Bad input**: a file that is not a ROS 1 bag, one without its index (not closed
//! properly: `rosbag reindex` it), a missing topic that was asked for or no usable image is
//! an error naming the file (and its topics). A message that does not parse, a
//! non-increasing stamp or a frame of another size is skipped and kept as an issue; a
//! damaged chunk is skipped whole.

pub mod msgs;

use std::collections::BTreeMap;
use std::path::Path;

use rosbag::{ChunkRecord, IndexRecord, MessageRecord, RosBag};

use crate::mcap_bag::pixels::{self, ImageKind};
use crate::mcap_bag::CameraInfoValues;
use crate::{
    Dataset, DatasetError, DatasetKind, FrameRecord, FrameSource, ImuSample, InputIssue, IssueKind,
};

/// The first bytes of a ROS 1 bag (format 2.0).
const MAGIC: &[u8] = b"#ROSBAG V2.0\n";

/// Where an image message is: its chunk and its place among the chunk's records.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Ros1FrameRef {
    /// File offset of the chunk record.
    pub chunk_pos: u64,
    /// Index among the chunk's records (connections included).
    pub index: u32,
    /// Raw or compressed.
    pub kind: ImageKind,
}

/// True for a file that starts with the ROS 1 bag magic.
pub fn is_ros1_bag(path: &Path) -> bool {
    use std::io::Read;
    let mut head = [0u8; 13];
    path.is_file()
        && std::fs::File::open(path)
            .and_then(|mut f| f.read_exact(&mut head))
            .is_ok()
        && head[..] == *MAGIC
}

/// A topic of the bag: its message type.
type Topics = BTreeMap<String, String>;

/// The bag's connections: id → (topic, message type).
type Connections = BTreeMap<u32, (String, String)>;

/// Opens the bag at `path` after checking what the `rosbag` crate takes on trust (it
/// panics on them): the bag header's `index_pos` must lie between the end of the header
/// record and the end of the file (a bag cut short loses its index).
fn open_bag(path: &Path) -> Result<RosBag, String> {
    use std::io::Read;
    let mut f = std::fs::File::open(path).map_err(|e| format!("cannot open: {e}"))?;
    let len = f.metadata().map_err(|e| format!("cannot read: {e}"))?.len();
    // The header record is padded to 4 KiB.
    let mut head = Vec::new();
    (&mut f)
        .take(64 * 1024)
        .read_to_end(&mut head)
        .map_err(|e| format!("cannot read: {e}"))?;
    let (start, index_pos) = header_span(&head).ok_or_else(|| {
        "not a readable ROS 1 bag (format 2.0): its header record does not parse".to_string()
    })?;
    if index_pos < start || index_pos > len {
        return Err(format!(
            "the bag's index is at byte {index_pos}, outside its {len} bytes (a bag cut short, \
             or not closed properly: `rosbag reindex` it)"
        ));
    }
    RosBag::new(path).map_err(|e| format!("not a readable ROS 1 bag: {e}"))
}

/// The end of the bag header record and its `index_pos` field.
fn header_span(b: &[u8]) -> Option<(u64, u64)> {
    let u32_at = |p: usize| -> Option<usize> {
        let s = b.get(p..p + 4)?;
        Some(u32::from_le_bytes([s[0], s[1], s[2], s[3]]) as usize)
    };
    let mut p = MAGIC.len();
    let header_len = u32_at(p)?;
    let header = b.get(p + 4..p + 4 + header_len)?;
    p += 4 + header_len;
    let data_len = u32_at(p)?;
    let start = (p + 4 + data_len) as u64;
    let mut q = 0;
    while q + 4 <= header.len() {
        let n = u32::from_le_bytes([header[q], header[q + 1], header[q + 2], header[q + 3]]);
        let field = header.get(q + 4..q + 4 + n as usize)?;
        if let Some(v) = field.strip_prefix(b"index_pos=") {
            let v: [u8; 8] = v.try_into().ok()?;
            return Some((start, u64::from_le_bytes(v)));
        }
        q += 4 + n as usize;
    }
    None
}

/// The bag's connections (id → topic, type) and chunk positions, from its index.
fn index_of(bag: &RosBag) -> Result<(Connections, Vec<u64>), String> {
    let (mut conns, mut chunks) = (BTreeMap::new(), Vec::new());
    for r in bag.index_records() {
        match r.map_err(|e| format!("the index does not read: {e}"))? {
            IndexRecord::Connection(c) => {
                conns.insert(c.id, (c.topic.to_string(), c.tp.to_string()));
            }
            IndexRecord::ChunkInfo(ci) => chunks.push(ci.chunk_pos),
            IndexRecord::IndexData(_) => {}
        }
    }
    if chunks.is_empty() {
        return Err(
            "no chunk in the index (a bag not closed properly: `rosbag reindex` it)".into(),
        );
    }
    Ok((conns, chunks))
}

/// Calls `f(index, connection id, stamp-less bytes)` for every message of the chunk at
/// `pos`.
fn for_messages(bag: &RosBag, pos: u64, mut f: impl FnMut(u32, u32, &[u8])) -> Result<(), String> {
    let mut it = bag.chunk_records();
    it.seek(pos)
        .map_err(|e| format!("chunk at byte {pos}: {e}"))?;
    let chunk = match it.next() {
        Some(Ok(ChunkRecord::Chunk(c))) => c,
        Some(Ok(_)) => return Err(format!("no chunk at byte {pos}")),
        Some(Err(e)) => return Err(format!("chunk at byte {pos}: {e}")),
        None => return Err(format!("no record at byte {pos}")),
    };
    for (i, m) in chunk.messages().enumerate() {
        match m.map_err(|e| format!("chunk at byte {pos}, record {i}: {e}"))? {
            MessageRecord::MessageData(d) => f(i as u32, d.conn_id, d.data),
            MessageRecord::Connection(_) => {}
        }
    }
    Ok(())
}

/// The image topic: the asked one, else the first raw image topic by name, else the first
/// compressed one.
fn choose_image_topic(topics: &Topics, asked: Option<&str>) -> Result<(String, ImageKind), String> {
    let kind = |tp: &str| match tp {
        "sensor_msgs/Image" => Some(ImageKind::Ros1Raw),
        "sensor_msgs/CompressedImage" => Some(ImageKind::Ros1Compressed),
        _ => None,
    };
    if let Some(t) = asked {
        let tp = topics.get(t).ok_or_else(|| format!("no topic {t}"))?;
        return kind(tp)
            .map(|k| (t.to_string(), k))
            .ok_or_else(|| format!("topic {t} is {tp}, not an image"));
    }
    let pick = |want: ImageKind| {
        (topics.iter()).find_map(|(t, tp)| (kind(tp) == Some(want)).then(|| (t.clone(), want)))
    };
    pick(ImageKind::Ros1Raw)
        .or_else(|| pick(ImageKind::Ros1Compressed))
        .ok_or_else(|| "no sensor_msgs/Image or sensor_msgs/CompressedImage topic".into())
}

/// A topic of type `tp`: the asked one, else the first by name.
fn choose_topic(topics: &Topics, asked: Option<&str>, tp: &str) -> Result<Option<String>, String> {
    if let Some(t) = asked {
        return match topics.get(t) {
            Some(x) if x == tp => Ok(Some(t.to_string())),
            Some(x) => Err(format!("topic {t} is {x}, not {tp}")),
            None => Err(format!("no topic {t}")),
        };
    }
    Ok(topics
        .iter()
        .find(|(_, x)| *x == tp)
        .map(|(t, _)| t.clone()))
}

/// What one pass over the chunks collects.
#[derive(Default)]
struct Collected {
    frames: Vec<(FrameRecord, u32, u32)>,
    imu: Vec<ImuSample>,
    info: Option<CameraInfoValues>,
    issues: Vec<InputIssue>,
}

/// Reads the ROS 1 bag `path`.
pub fn read(
    path: &Path,
    asked: &crate::mcap_bag::Topics,
    calib_given: bool,
) -> Result<Dataset, DatasetError> {
    let bad = |detail: String| DatasetError::Parse {
        path: path.to_path_buf(),
        line: 0,
        detail,
    };
    let bag = open_bag(path).map_err(bad)?;
    let (conns, chunks) = index_of(&bag).map_err(bad)?;
    let topics: Topics = conns.values().cloned().collect();
    let with_topics = |e: String| {
        let list: Vec<String> = topics.iter().map(|(t, tp)| format!("{t} ({tp})")).collect();
        bad(format!("{e}; the bag has {}", list.join(", ")))
    };
    let (image_topic, kind) =
        choose_image_topic(&topics, asked.image.as_deref()).map_err(with_topics)?;
    let imu_topic =
        choose_topic(&topics, asked.imu.as_deref(), "sensor_msgs/Imu").map_err(with_topics)?;
    let namespace = image_topic.rsplit_once('/').map_or("", |(ns, _)| ns);
    let infos: Vec<&String> = (topics.iter())
        .filter(|(_, tp)| *tp == "sensor_msgs/CameraInfo")
        .map(|(t, _)| t)
        .collect();
    let info_topic = (infos.iter())
        .find(|t| t.rsplit_once('/').map_or("", |(ns, _)| ns) == namespace)
        .or(if infos.len() == 1 {
            infos.first()
        } else {
            None
        })
        .map(|t| t.to_string());
    let topic_of = |id: u32| conns.get(&id).map(|(t, _)| t.as_str());
    let mut c = Collected::default();
    for pos in chunks {
        let mut on_message = |i: u32, conn: u32, data: &[u8]| {
            let topic = topic_of(conn);
            if topic == Some(image_topic.as_str()) {
                add_frame(&mut c, path, &image_topic, kind, pos, i, data);
            } else if topic.is_some() && topic == imu_topic.as_deref() {
                add_imu(&mut c, path, data);
            } else if topic.is_some() && topic == info_topic.as_deref() && c.info.is_none() {
                c.info = msgs::camera_info(data).ok();
            }
        };
        if let Err(e) = for_messages(&bag, pos, &mut on_message) {
            let detail = format!("{e}; the chunk is skipped");
            c.issues.push(issue(path, IssueKind::TruncatedFile, detail));
        }
    }
    dataset(path, c, calib_given, imu_topic.is_some()).map_err(with_topics)
}

fn issue(path: &Path, kind: IssueKind, detail: String) -> InputIssue {
    InputIssue {
        path: path.to_path_buf(),
        line: 0,
        kind,
        detail,
    }
}

/// One image message: kept when it parses, is after the previous frame and of its size.
fn add_frame(
    c: &mut Collected,
    path: &Path,
    topic: &str,
    kind: ImageKind,
    chunk_pos: u64,
    index: u32,
    data: &[u8],
) {
    let why = match pixels::probe(kind, data) {
        Err(e) => Some((IssueKind::BadMessage, e, 0)),
        Ok(p) => match c.frames.last() {
            Some((prev, _, _)) if p.stamp_ns <= prev.t_ns => Some((
                IssueKind::NonMonotonic,
                format!("stamp not after the previous frame's {} ns", prev.t_ns),
                p.stamp_ns,
            )),
            Some((_, w, h)) if (p.width, p.height) != (*w, *h) => Some((
                IssueKind::BadMessage,
                format!("size {}x{}, the first frame's {w}x{h}", p.width, p.height),
                p.stamp_ns,
            )),
            _ => {
                let rec = FrameRecord {
                    t_ns: p.stamp_ns,
                    path: path.to_path_buf(),
                    exposure_ns: 0,
                    readout_ns: 0,
                    source: FrameSource::Ros1(Ros1FrameRef {
                        chunk_pos,
                        index,
                        kind,
                    }),
                };
                c.frames.push((rec, p.width, p.height));
                None
            }
        },
    };
    if let Some((k, why, stamp)) = why {
        let detail = format!(
            "topic {topic}, image at stamp {stamp} ns (chunk at byte {chunk_pos}, record \
             {index}): {why}; skipped"
        );
        c.issues.push(issue(path, k, detail));
    }
}

/// One IMU message: kept when it parses and is after the previous sample.
fn add_imu(c: &mut Collected, path: &Path, data: &[u8]) {
    let sample = msgs::imu(data).and_then(|(t, gyro, accel)| {
        let t_ns = t.to_ns().ok_or("a stamp with nanoseconds beyond 1e9")?;
        Ok(ImuSample { t_ns, gyro, accel })
    });
    match (sample, c.imu.last()) {
        (Ok(s), Some(prev)) if s.t_ns <= prev.t_ns => {
            let detail = format!(
                "IMU sample at stamp {} ns not after the previous one's {} ns; skipped",
                s.t_ns, prev.t_ns
            );
            c.issues.push(issue(path, IssueKind::NonMonotonic, detail));
        }
        (Ok(s), _) => c.imu.push(s),
        (Err(e), _) => {
            let detail = format!("an IMU message does not parse: {e}; skipped");
            c.issues.push(issue(path, IssueKind::BadMessage, detail));
        }
    }
}

/// The dataset from what was collected.
fn dataset(
    path: &Path,
    mut c: Collected,
    calib_given: bool,
    has_imu: bool,
) -> Result<Dataset, String> {
    let Some(&(_, width, height)) = c.frames.first() else {
        let first = c
            .issues
            .first()
            .map(|i| format!(" (first problem: {})", i.detail));
        return Err(format!("no usable image{}", first.unwrap_or_default()));
    };
    let model = crate::mcap_bag::camera_model(c.info.as_ref(), width, height, calib_given)?;
    if !has_imu {
        let detail = "no sensor_msgs/Imu topic: no IMU stream".to_string();
        c.issues.push(issue(path, IssueKind::MissingFile, detail));
    }
    let frames: Vec<FrameRecord> = c.frames.into_iter().map(|f| f.0).collect();
    let camera = crate::mcap_bag::ros_camera(model, &frames);
    Ok(Dataset {
        kind: DatasetKind::Ros1Bag,
        root: path.to_path_buf(),
        camera,
        frames,
        imu: c.imu,
        ground_truth: None,
        issues: c.issues,
        first_row_stamps: true,
        imu_calib: None,
    })
}

/// Reads images of ROS 1 bags on demand; keeps the bag last read mapped and the last
/// chunk's image messages. One per replaying thread.
#[derive(Default)]
pub struct Ros1FrameLoader {
    bag: Option<(std::path::PathBuf, RosBag)>,
    /// (chunk position, its image messages by index).
    cached: Option<(u64, BTreeMap<u32, Vec<u8>>)>,
}

impl std::fmt::Debug for Ros1FrameLoader {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let bag = self.bag.as_ref().map(|(p, _)| p);
        f.debug_struct("Ros1FrameLoader")
            .field("bag", &bag)
            .finish()
    }
}

impl Ros1FrameLoader {
    /// Decodes the image `at` of the bag `path` as 8-bit gray into `dst`.
    pub fn read_gray_into(
        &mut self,
        path: &Path,
        at: &Ros1FrameRef,
        dst: &mut [u8],
        width: u32,
        height: u32,
    ) -> Result<(), DatasetError> {
        let place = format!(
            "image in the chunk at byte {}, record {}",
            at.chunk_pos, at.index
        );
        let bytes = self.message(path, at);
        pixels::decode_message_into(path, &place, at.kind, bytes, dst, (width, height))
    }

    fn message(&mut self, path: &Path, at: &Ros1FrameRef) -> Result<&[u8], String> {
        if self.bag.as_ref().is_none_or(|(p, _)| p != path) {
            let bag = open_bag(path).map_err(|e| format!("cannot open: {e}"))?;
            self.bag = Some((path.to_path_buf(), bag));
            self.cached = None;
        }
        if self
            .cached
            .as_ref()
            .is_none_or(|(pos, _)| *pos != at.chunk_pos)
        {
            let Some((_, bag)) = self.bag.as_ref() else {
                return Err("the bag is not open".into());
            };
            let mut all = BTreeMap::new();
            for_messages(bag, at.chunk_pos, |i, _, data| {
                all.insert(i, data.to_vec());
            })?;
            self.cached = Some((at.chunk_pos, all));
        }
        (self.cached.as_ref())
            .and_then(|(_, m)| m.get(&at.index))
            .map(Vec::as_slice)
            .ok_or_else(|| format!("no record {} in the chunk", at.index))
    }
}
