//! MCAP recordings and ROS 2 bags (issue 21): `shoal run --dataset FILE.mcap` or a rosbag2
//! folder (`metadata.yaml` + `.mcap` storage), and the MCAP files `shoal convert --to mcap`
//! writes ([`write`]).
//!
//! **What is read** (CDR-encoded ROS 2 messages, the `mcap` crate for the container and
//! `cdr-encoding` for the messages, [`msgs`]): images from `sensor_msgs/msg/Image` (`mono8`,
//! `rgb8`, `bgr8`), `sensor_msgs/msg/CompressedImage` (JPEG, PNG) or Foxglove's
//! `RawImage`/`CompressedImage`, all turned into 8-bit gray; IMU samples from
//! `sensor_msgs/msg/Imu`; the camera model from the first `sensor_msgs/msg/CameraInfo`
//! (`plumb_bob`/radial-tangential); ground truth from the `geometry_msgs/msg/PoseStamped`
//! topic a shoal file names.
//!
//! **Topics**: `--image-topic` / `--imu-topic` ([`Topics`]), else found by schema: a raw
//! image topic before a compressed one (a bag with both `image_raw` and
//! `image_raw/compressed` replays the lossless one), then the alphabetically first name
//! (`/cam0/...` before `/cam1/...`). The `CameraInfo` is that of the image topic's namespace
//! (`/cam0/image_raw` → `/cam0/camera_info`), or the only one.
//!
//! **Times** (`VI_NOTES.md` §1): a ROS header stamp is the first row's time (the camera
//! drivers' convention), so a frame's middle-row time is `stamp + t_r/2 + t_d`. Such a
//! dataset is marked [`crate::Dataset::first_row_stamps`]: without `--calib`, t_r = t_d = 0
//! (ROS messages carry neither) and the frame time is the stamp; a calibration file adds its
//! `t_r/2 + t_d`. A file shoal wrote says in its `shoal` metadata record ([`meta`]) that its
//! stamps are middle-row times already, and carries its calibration; it is not converted
//! twice.
//!
//! **Streaming**: opening reads the file once, one chunk in memory at a time, and keeps only
//! each image's place in the file ([`McapFrameRef`]); the replay reads images on demand
//! ([`McapFrameLoader`], which keeps the last chunk's images), so memory does not grow with
//! the file.
//!
//! **Bad input**: a missing topic that was asked for, a file that is not MCAP, or a
//! recording without a usable image is an error naming the file (and the topics it has). A
//! message that does not decode, an unknown pixel encoding or compressed format, a
//! non-increasing stamp or a frame of another size is skipped and kept as an issue (topic,
//! message number, file offset); a damaged chunk is skipped whole; a file cut short is read
//! up to the cut. Not read here: ROS 1 bags ([`crate::ros1_bag`]), protobuf/JSON-encoded messages, `/tf_static` (give
//! T_BS with `--calib`), per-frame exposure.

pub mod meta;
pub mod msgs;
pub mod pixels;
mod scan;
pub mod view_msgs;
pub mod write;

use std::collections::BTreeMap;
use std::fs::File;
use std::path::{Path, PathBuf};

use crate::{
    CameraCalib, Dataset, DatasetError, DatasetKind, FrameRecord, FrameSource, ImuSample,
    InputIssue, IssueKind, PinholeRadtan, StampedPose,
};
pub use pixels::ImageKind;
pub use scan::CameraInfoValues;
use scan::{ChannelInfo, FileIndex, ImageEntry};

/// Where an image message is: the top-level record holding it (a chunk, or the message
/// itself) and its place among the chunk's records.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct McapFrameRef {
    /// File offset of the record (its opcode byte).
    pub record_offset: u64,
    /// Length of the record's body.
    pub record_len: u64,
    /// Index among the chunk's records; `None` when the record is the message.
    pub in_chunk: Option<u32>,
    /// The message's channel id.
    pub channel: u16,
    /// The message type.
    pub kind: ImageKind,
}

/// Which topics to replay; `None`: found by message type (module docs).
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct Topics {
    /// Image topic (`--image-topic`).
    pub image: Option<String>,
    /// IMU topic (`--imu-topic`).
    pub imu: Option<String>,
}

/// True for a file that starts with the MCAP magic.
pub fn is_mcap_file(path: &Path) -> bool {
    use std::io::Read;
    let mut head = [0u8; 8];
    path.is_file()
        && File::open(path)
            .and_then(|mut f| f.read_exact(&mut head))
            .is_ok()
        && head[..] == *::mcap::MAGIC
}

/// True for a rosbag2 folder (`metadata.yaml` beside its storage files).
pub fn is_rosbag2(path: &Path) -> bool {
    path.join("metadata.yaml").is_file()
}

/// The `rosbag2_bagfile_information` keys this reader uses.
#[derive(serde::Deserialize)]
struct BagInfo {
    storage_identifier: String,
    #[serde(default)]
    relative_file_paths: Vec<String>,
}

#[derive(serde::Deserialize)]
struct BagMetadata {
    rosbag2_bagfile_information: BagInfo,
}

/// The MCAP files of a dataset path: the file itself, or a rosbag2 folder's files in the
/// order of its `metadata.yaml` (or the folder's `.mcap` files by name when it lists none).
pub fn files_of(path: &Path) -> Result<Vec<PathBuf>, DatasetError> {
    if path.is_file() {
        return Ok(vec![path.to_path_buf()]);
    }
    let yaml = path.join("metadata.yaml");
    let text = crate::text::read_text(&yaml, "rosbag2 metadata.yaml")?;
    let meta: BagMetadata = serde_saphyr::from_str(&text).map_err(|e| DatasetError::Parse {
        path: yaml.clone(),
        line: 0,
        detail: format!("not a rosbag2 metadata file: {e}"),
    })?;
    let info = meta.rosbag2_bagfile_information;
    if info.storage_identifier != "mcap" {
        return Err(DatasetError::UnknownFormat {
            path: path.into(),
            detail: format!(
                "rosbag2 storage `{}`; shoal reads `mcap` storage (convert with `ros2 bag \
                 convert`)",
                info.storage_identifier
            ),
        });
    }
    let mut files: Vec<PathBuf> = info
        .relative_file_paths
        .iter()
        .map(|f| path.join(f))
        .collect();
    if files.is_empty() {
        let rd = std::fs::read_dir(path).map_err(|source| DatasetError::Io {
            path: path.into(),
            source,
        })?;
        files = rd
            .filter_map(|e| e.ok().map(|e| e.path()))
            .filter(|p| p.extension().is_some_and(|x| x == "mcap"))
            .collect();
        files.sort();
    }
    if let Some(missing) = files.iter().find(|f| !f.is_file()) {
        return Err(DatasetError::NotFound {
            path: missing.clone(),
            what: format!("storage file listed in {}", yaml.display()),
        });
    }
    if files.is_empty() {
        return Err(DatasetError::NotFound {
            path: path.into(),
            what: "rosbag2 .mcap storage files".into(),
        });
    }
    Ok(files)
}

/// An issue of kind `kind` about the file `path` as a whole (line 0).
pub(crate) fn issue_at(path: &Path, kind: IssueKind, detail: String) -> InputIssue {
    InputIssue {
        path: path.to_path_buf(),
        line: 0,
        kind,
        detail,
    }
}

/// Opens an MCAP file or rosbag2 folder as a [`Dataset`] (module docs). `calib_given`: a
/// calibration file will replace the recording's own, so a recording without a
/// `CameraInfo` is accepted.
pub fn read(path: &Path, topics: &Topics, calib_given: bool) -> Result<Dataset, DatasetError> {
    let files = files_of(path)?;
    let mut indexes = Vec::with_capacity(files.len());
    for f in &files {
        indexes.push((f.clone(), scan::index_file(f)?));
    }
    let shoal = shoal_meta(&indexes)?;
    let all = all_topics(&indexes);
    // A damaged file explains a missing topic or image: the error says so.
    let damage: Option<String> = indexes.iter().find_map(|(f, idx)| {
        idx.issues
            .first()
            .map(|i| format!("{}: {}", f.display(), i.detail))
    });
    let bad = |detail: String| DatasetError::Parse {
        path: path.to_path_buf(),
        line: 0,
        detail: match &damage {
            Some(d) => format!("{detail} (the file is damaged: {d})"),
            None => detail,
        },
    };
    let image_topic = choose_image_topic(&all, topics.image.as_deref()).map_err(bad)?;
    let imu_topic =
        choose_topic(&all, topics.imu.as_deref(), msgs::names::IMU, "IMU").map_err(bad)?;
    let mut issues: Vec<InputIssue> = Vec::new();
    for (_, idx) in &indexes {
        issues.extend(idx.issues.iter().cloned());
    }
    let frames = collect_frames(&indexes, &image_topic, &mut issues);
    let Some(first) = frames.first() else {
        let mut detail = format!("no usable image on topic {image_topic}");
        if let Some(i) = issues.iter().find(|i| i.kind == IssueKind::BadMessage) {
            detail.push_str(&format!(" (first problem: {})", i.detail));
        }
        return Err(bad(detail));
    };
    let (width, height) = (first.1, first.2);
    let imu = match &imu_topic {
        Some(t) => collect_imu(&indexes, t, &mut issues),
        None => {
            issues.push(issue_at(
                path,
                IssueKind::MissingFile,
                format!("no {} topic: no IMU stream", msgs::names::IMU),
            ));
            Vec::new()
        }
    };
    let frames: Vec<FrameRecord> = frames.into_iter().map(|f| f.0).collect();
    let (camera, imu_calib, gt_topic) = match &shoal {
        Some(m) if m.middle_row => (m.camera.clone(), m.imu, m.ground_truth_topic.clone()),
        _ => {
            let (info, info_problem) = camera_info_of(&indexes, &all, &image_topic);
            let model = camera_model(info, width, height, calib_given)
                .map_err(|e| bad(format!("{e}{}", info_problem.unwrap_or_default())))?;
            (ros_camera(model, &frames), None, None)
        }
    };
    let frames = frames
        .into_iter()
        .map(|f| FrameRecord {
            readout_ns: camera.readout_ns,
            ..f
        })
        .collect();
    let ground_truth = gt_topic.map(|t| collect_poses(&indexes, &t, &mut issues));
    Ok(Dataset {
        kind: DatasetKind::Mcap,
        root: path.to_path_buf(),
        camera,
        frames,
        imu,
        ground_truth,
        issues,
        first_row_stamps: !shoal.as_ref().is_some_and(|m| m.middle_row),
        imu_calib,
    })
}

/// The `shoal` metadata record of the first file, if any; a damaged one is an error.
fn shoal_meta(indexes: &[(PathBuf, FileIndex)]) -> Result<Option<meta::ShoalMeta>, DatasetError> {
    let Some((path, idx)) = indexes.first() else {
        return Ok(None);
    };
    idx.metadata
        .get(meta::RECORD)
        .map(|m| {
            meta::from_map(m).map_err(|detail| DatasetError::Parse {
                path: path.clone(),
                line: 0,
                detail: format!("metadata record `{}`: {detail}", meta::RECORD),
            })
        })
        .transpose()
}

/// Every topic of the files with its channel (the first seen).
fn all_topics(indexes: &[(PathBuf, FileIndex)]) -> BTreeMap<String, ChannelInfo> {
    let mut all = BTreeMap::new();
    for (_, idx) in indexes {
        for c in idx.channels.values() {
            all.entry(c.topic.clone()).or_insert_with(|| c.clone());
        }
    }
    all
}

fn topic_list(all: &BTreeMap<String, ChannelInfo>) -> String {
    let v: Vec<String> = all
        .values()
        .map(|c| format!("{} ({}, {})", c.topic, c.schema, c.encoding))
        .collect();
    if v.is_empty() {
        "none".into()
    } else {
        v.join(", ")
    }
}

/// The image topic: `asked`, else the best image channel (module docs).
fn choose_image_topic(
    all: &BTreeMap<String, ChannelInfo>,
    asked: Option<&str>,
) -> Result<String, String> {
    let usable = |c: &ChannelInfo| c.encoding == "cdr" && ImageKind::of_schema(&c.schema).is_some();
    if let Some(t) = asked {
        let c = all
            .get(t)
            .ok_or_else(|| format!("no topic {t}; the file has: {}", topic_list(all)))?;
        if !usable(c) {
            return Err(format!(
                "topic {t} is {} encoded as {}: shoal reads images from CDR-encoded \
                 sensor_msgs/msg/Image, sensor_msgs/msg/CompressedImage, \
                 foxglove_msgs/msg/RawImage or foxglove_msgs/msg/CompressedImage",
                c.schema, c.encoding
            ));
        }
        return Ok(t.to_string());
    }
    all.values()
        .filter(|c| usable(c))
        .min_by_key(|c| (ImageKind::of_schema(&c.schema), c.topic.clone()))
        .map(|c| c.topic.clone())
        .ok_or_else(|| {
            format!(
                "no image topic (CDR sensor_msgs/msg/Image, CompressedImage or their Foxglove \
                 equivalents); the file has: {}",
                topic_list(all)
            )
        })
}

/// The topic of schema `schema`: `asked` (which must be of that schema), else the first by
/// name, else none.
fn choose_topic(
    all: &BTreeMap<String, ChannelInfo>,
    asked: Option<&str>,
    schema: &str,
    what: &str,
) -> Result<Option<String>, String> {
    let usable = |c: &ChannelInfo| c.encoding == "cdr" && c.schema == schema;
    match asked {
        Some(t) => match all.get(t) {
            None => Err(format!(
                "no {what} topic {t}; the file has: {}",
                topic_list(all)
            )),
            Some(c) if !usable(c) => Err(format!(
                "topic {t} is {} encoded as {}, not CDR {schema}",
                c.schema, c.encoding
            )),
            Some(_) => Ok(Some(t.to_string())),
        },
        None => Ok(all.values().find(|c| usable(c)).map(|c| c.topic.clone())),
    }
}

/// The channels of `topic` in each file, with their data, in file order.
fn channels_of<'a>(
    indexes: &'a [(PathBuf, FileIndex)],
    topic: &'a str,
) -> impl Iterator<Item = (&'a PathBuf, &'a scan::ChannelData)> + 'a {
    indexes.iter().flat_map(move |(path, idx)| {
        idx.channels
            .iter()
            .filter(move |(_, c)| c.topic == topic)
            .filter_map(move |(id, _)| idx.data.get(id).map(|d| (path, d)))
    })
}

/// The frames of `topic` with strictly increasing stamps and the first frame's size, each
/// with its size; the others become issues.
fn collect_frames(
    indexes: &[(PathBuf, FileIndex)],
    topic: &str,
    issues: &mut Vec<InputIssue>,
) -> Vec<(FrameRecord, u32, u32)> {
    let mut out: Vec<(FrameRecord, u32, u32)> = Vec::new();
    for (path, data) in channels_of(indexes, topic) {
        issues.extend(data.issues.iter().cloned());
        for e in &data.images {
            if let Some(why) = frame_problem(out.last(), e) {
                let kind = if why.starts_with("stamp") {
                    IssueKind::NonMonotonic
                } else {
                    IssueKind::BadMessage
                };
                let detail = format!(
                    "topic {topic}, image at stamp {} ns (record at byte {}): {why}; skipped",
                    e.stamp_ns, e.at.record_offset
                );
                issues.push(issue_at(path, kind, detail));
                continue;
            }
            let rec = FrameRecord {
                t_ns: e.stamp_ns,
                path: path.clone(),
                exposure_ns: 0,
                readout_ns: 0,
                source: FrameSource::Mcap(e.at),
            };
            out.push((rec, e.width, e.height));
        }
    }
    out
}

/// Why `e` cannot follow `last`, if it cannot.
fn frame_problem(last: Option<&(FrameRecord, u32, u32)>, e: &ImageEntry) -> Option<String> {
    let (prev, w, h) = last?;
    if e.stamp_ns <= prev.t_ns {
        return Some(format!(
            "stamp not after the previous frame's {} ns",
            prev.t_ns
        ));
    }
    ((e.width, e.height) != (*w, *h)).then(|| {
        format!(
            "size {}x{}, the first frame's is {w}x{h}",
            e.width, e.height
        )
    })
}

/// The IMU samples of `topic` with strictly increasing stamps.
fn collect_imu(
    indexes: &[(PathBuf, FileIndex)],
    topic: &str,
    issues: &mut Vec<InputIssue>,
) -> Vec<ImuSample> {
    let mut out: Vec<ImuSample> = Vec::new();
    for (path, data) in channels_of(indexes, topic) {
        issues.extend(data.issues.iter().cloned());
        for s in &data.imu {
            if let Some(prev) = out.last().filter(|p| s.t_ns <= p.t_ns) {
                issues.push(issue_at(
                    path,
                    IssueKind::NonMonotonic,
                    format!(
                        "topic {topic}, IMU sample at stamp {} ns not after the previous one's \
                         {} ns; skipped",
                        s.t_ns, prev.t_ns
                    ),
                ));
                continue;
            }
            out.push(*s);
        }
    }
    out
}

/// The stamped poses of `topic` (ground truth), in increasing time.
fn collect_poses(
    indexes: &[(PathBuf, FileIndex)],
    topic: &str,
    issues: &mut Vec<InputIssue>,
) -> Vec<StampedPose> {
    let mut out: Vec<StampedPose> = Vec::new();
    for (_, data) in channels_of(indexes, topic) {
        issues.extend(data.issues.iter().cloned());
        for p in &data.poses {
            if out.last().is_none_or(|q| p.t_ns > q.t_ns) {
                out.push(*p);
            }
        }
    }
    out
}

/// The first `CameraInfo` of the image topic's namespace, or of the only such topic; and
/// when that topic has none that decodes, why (for the error message).
fn camera_info_of<'a>(
    indexes: &'a [(PathBuf, FileIndex)],
    all: &'a BTreeMap<String, ChannelInfo>,
    image_topic: &str,
) -> (Option<&'a scan::CameraInfoValues>, Option<String>) {
    let infos: Vec<&String> = all
        .values()
        .filter(|c| c.schema == msgs::names::CAMERA_INFO && c.encoding == "cdr")
        .map(|c| &c.topic)
        .collect();
    let ns = image_topic.rsplit_once('/').map_or("", |(ns, _)| ns);
    let same_ns = format!("{ns}/camera_info");
    let only = if infos.len() == 1 {
        infos.first()
    } else {
        None
    };
    let Some(topic) = infos.iter().find(|t| **t == &same_ns).or(only) else {
        return (None, None);
    };
    let info = channels_of(indexes, topic).find_map(|(_, d)| d.camera_info.as_ref());
    let problem = channels_of(indexes, topic)
        .find_map(|(_, d)| d.issues.first())
        .map(|i| format!(" ({})", i.detail));
    (info, if info.is_none() { problem } else { None })
}

/// The camera model of a `CameraInfo` for images of `width` x `height`. Without one
/// (or with an uncalibrated one) only a calibration file can give it.
pub(crate) fn camera_model(
    info: Option<&scan::CameraInfoValues>,
    width: u32,
    height: u32,
    calib_given: bool,
) -> Result<PinholeRadtan, String> {
    let from_info = info.map(|c| {
        if (c.width, c.height) != (width, height) {
            return Err(format!(
                "CameraInfo is for {}x{} images, the images are {width}x{height}",
                c.width, c.height
            ));
        }
        let k = c.k;
        if !(k[0] > 0.0 && k[4] > 0.0) {
            return Err("CameraInfo is uncalibrated (K has no focal length)".into());
        }
        let d = match (c.distortion_model.as_str(), c.d.as_slice()) {
            (_, []) => [0.0; 5],
            ("plumb_bob" | "radtan", [k1, k2, p1, p2]) => [*k1, *k2, *p1, *p2, 0.0],
            ("plumb_bob" | "radtan", [k1, k2, p1, p2, k3]) => [*k1, *k2, *p1, *p2, *k3],
            (m, d) => {
                return Err(format!(
                    "CameraInfo distortion `{m}` with {} coefficients; shoal reads plumb_bob \
                     (k1 k2 p1 p2 [k3])",
                    d.len()
                ))
            }
        };
        Ok(PinholeRadtan::from_coefficients(
            width,
            height,
            [k[0], k[4], k[2], k[5]],
            d,
        ))
    });
    match (from_info, calib_given) {
        (Some(Ok(m)), _) => Ok(m),
        // Replaced by the calibration file right after.
        (_, true) => Ok(PinholeRadtan::from_coefficients(
            width,
            height,
            [
                width as f64,
                width as f64,
                width as f64 / 2.0,
                height as f64 / 2.0,
            ],
            [0.0; 5],
        )),
        (Some(Err(e)), false) => Err(format!("{e}: give the camera model with --calib")),
        (None, false) => Err(format!(
            "no usable {} message: give the camera model with --calib",
            msgs::names::CAMERA_INFO
        )),
    }
}

/// Frame rate from the median stamp difference (0 with fewer than two frames).
/// The camera of a ROS recording: `model` (from its `CameraInfo`), no T_BS, t_r or t_d
/// (ROS messages carry none: `--calib` gives them), the frames' rate.
pub(crate) fn ros_camera(model: PinholeRadtan, frames: &[FrameRecord]) -> CameraCalib {
    CameraCalib {
        model,
        t_bs: nalgebra::Isometry3::identity(),
        t_bs_given: false,
        readout_ns: 0,
        time_offset_ns: 0,
        rate_hz: rate_of(frames),
    }
}

fn rate_of(frames: &[FrameRecord]) -> f64 {
    let mut dt: Vec<i64> = frames.windows(2).map(|w| w[1].t_ns - w[0].t_ns).collect();
    if dt.is_empty() {
        return 0.0;
    }
    let mid = dt.len() / 2;
    let median = *dt.select_nth_unstable(mid).1;
    1e9 / median as f64
}

/// Reads MCAP image messages on demand (the replay's side of [`McapFrameRef`]). It keeps
/// the images of the last chunk it read, so a replay in order decompresses each chunk once;
/// memory stays at one chunk.
#[derive(Debug, Default)]
pub struct McapFrameLoader {
    file: Option<(PathBuf, File)>,
    /// (file, chunk offset) of the cached chunk.
    cached_chunk: Option<(PathBuf, u64)>,
    /// The cached chunk's messages of one channel: (index in the chunk, message bytes).
    cached: Vec<(u32, Vec<u8>)>,
    buf: Vec<u8>,
}

impl McapFrameLoader {
    /// Decodes the image message `at` of the file `path` as 8-bit gray into `dst`.
    pub fn read_gray_into(
        &mut self,
        path: &Path,
        at: &McapFrameRef,
        dst: &mut [u8],
        width: u32,
        height: u32,
    ) -> Result<(), DatasetError> {
        let place = format!("message in the record at byte {}", at.record_offset);
        let bytes = self.message(path, at);
        pixels::decode_message_into(path, &place, at.kind, bytes, dst, (width, height))
    }

    /// The bytes of message `at`.
    fn message(&mut self, path: &Path, at: &McapFrameRef) -> Result<&[u8], String> {
        let Some(i) = at.in_chunk else {
            self.read_record(path, at)?;
            return match ::mcap::parse_record(::mcap::records::op::MESSAGE, &self.buf) {
                Ok(::mcap::records::Record::Message { data, .. }) => {
                    let range = self.buf.len() - data.len()..self.buf.len();
                    Ok(&self.buf[range])
                }
                Ok(_) => Err("not a message record".into()),
                Err(e) => Err(format!("message record does not parse: {e}")),
            };
        };
        let key = (path.to_path_buf(), at.record_offset);
        if self.cached_chunk.as_ref() != Some(&key) {
            self.cached_chunk = None;
            self.read_record(path, at)?;
            self.cached = chunk_messages(&self.buf, at.channel)?;
            self.cached_chunk = Some(key);
        }
        self.cached
            .iter()
            .find(|(k, _)| *k == i)
            .map(|(_, m)| m.as_slice())
            .ok_or_else(|| format!("no message {i} of channel {} in the chunk", at.channel))
    }

    /// Reads the body of the record `at` into `self.buf`.
    fn read_record(&mut self, path: &Path, at: &McapFrameRef) -> Result<(), String> {
        if self.file.as_ref().is_none_or(|(p, _)| p != path) {
            let f = File::open(path).map_err(|e| format!("cannot open: {e}"))?;
            self.file = Some((path.to_path_buf(), f));
        }
        let (_, file) = self.file.as_mut().expect("opened above");
        scan::read_record(file, at.record_offset, at.record_len, &mut self.buf)
            .map(|_| ())
            .map_err(|e| format!("cannot read the record: {e}"))
    }
}

/// The messages of `channel` in the chunk record `body`, with their index in the chunk.
fn chunk_messages(body: &[u8], channel: u16) -> Result<Vec<(u32, Vec<u8>)>, String> {
    let (header, data) = match ::mcap::parse_record(::mcap::records::op::CHUNK, body) {
        Ok(::mcap::records::Record::Chunk { header, data }) => (header, data),
        Ok(_) => return Err("not a chunk record".into()),
        Err(e) => return Err(format!("chunk record does not parse: {e}")),
    };
    let reader = ::mcap::read::ChunkReader::new(header, &data).map_err(|e| e.to_string())?;
    let mut out = Vec::new();
    for (i, rec) in reader.enumerate() {
        match rec.map_err(|e| format!("chunk is damaged: {e}"))? {
            ::mcap::records::Record::Message { header, data } if header.channel_id == channel => {
                out.push((i as u32, data.into_owned()));
            }
            _ => {}
        }
    }
    Ok(out)
}
