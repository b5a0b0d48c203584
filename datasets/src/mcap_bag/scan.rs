//! The index pass: one read through an MCAP file, one chunk in memory at a time. It keeps
//! where each image message is (its chunk's file offset and its place in the chunk), the
//! image's stamp and size, every IMU sample, the first camera calibration message, stamped
//! poses and shoal's metadata, per channel; the pixels stay in the file.
//!
//! The `mcap` crate's sans-IO reader frames the top-level records (magic, opcode, length)
//! and parses them; chunks are emitted whole, so this pass knows each chunk's file offset
//! (the crate's readers do not report offsets), and decompresses and walks them with the
//! crate's `ChunkReader`. A chunk whose records or CRC fail is skipped whole (an issue naming
//! its offset): its messages are not used, the chunks after it are. A file cut short keeps
//! every record before the cut.

use std::collections::{BTreeMap, HashMap};
use std::fs::File;
use std::io::{Read, Seek, SeekFrom};
use std::path::Path;

use mcap::records::{MessageHeader, Record};
use mcap::sans_io::{LinearReadEvent, LinearReader, LinearReaderOptions};

use super::msgs::{self, names};
use super::pixels::{self, ImageKind};
use super::{issue_at, McapFrameRef};
use crate::{DatasetError, ImuSample, InputIssue, IssueKind, StampedPose};

/// An MCAP channel: topic, schema name and message encoding.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct ChannelInfo {
    /// Topic name.
    pub topic: String,
    /// Schema name (`sensor_msgs/msg/Image`, ...; empty without a schema).
    pub schema: String,
    /// Message encoding (`cdr` for ROS 2).
    pub encoding: String,
}

/// An image message found by the index pass.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ImageEntry {
    /// Header stamp, ns.
    pub stamp_ns: i64,
    /// Size.
    pub width: u32,
    /// Size.
    pub height: u32,
    /// Where it is.
    pub at: McapFrameRef,
}

/// The first usable `CameraInfo` of a channel, as numbers.
#[derive(Debug, Clone, PartialEq)]
pub struct CameraInfoValues {
    /// Size.
    pub width: u32,
    /// Size.
    pub height: u32,
    /// Distortion model name.
    pub distortion_model: String,
    /// Distortion coefficients.
    pub d: Vec<f64>,
    /// Intrinsic matrix, rows.
    pub k: [f64; 9],
}

/// What one channel holds (only the parts its schema gives).
#[derive(Debug, Default)]
pub struct ChannelData {
    /// Image messages in file order (the ones that probe well).
    pub images: Vec<ImageEntry>,
    /// IMU samples in file order.
    pub imu: Vec<ImuSample>,
    /// Stamped poses in file order.
    pub poses: Vec<StampedPose>,
    /// The first camera calibration.
    pub camera_info: Option<CameraInfoValues>,
    /// Messages seen (the 1-based number of the next one is `count + 1`).
    pub count: usize,
    /// Problems with this channel's messages.
    pub issues: Vec<InputIssue>,
}

/// The outcome of the index pass over one file.
#[derive(Debug, Default)]
pub struct FileIndex {
    /// Channels by id.
    pub channels: BTreeMap<u16, ChannelInfo>,
    /// Their messages by channel id.
    pub data: HashMap<u16, ChannelData>,
    /// Metadata records by name (the last of a name wins).
    pub metadata: HashMap<String, BTreeMap<String, String>>,
    /// Problems with the file as a whole (truncation, damaged chunks).
    pub issues: Vec<InputIssue>,
    /// The header's profile (`ros2` for rosbag2).
    pub profile: String,
}

/// Largest record the pass buffers (a chunk or a message), 1 GiB: beyond it the file is
/// taken as damaged.
const MAX_RECORD_BYTES: usize = 1 << 30;

/// Reads `path` once (module docs). Errors only when the file cannot be opened or is not
/// an MCAP file at all; damage later in the file becomes issues.
pub fn index_file(path: &Path) -> Result<FileIndex, DatasetError> {
    let io = |source| DatasetError::Io {
        path: path.to_path_buf(),
        source,
    };
    let mut file = File::open(path).map_err(io)?;
    let file_len = file.metadata().map_err(io)?.len();
    let mut reader = LinearReader::new_with_options(
        LinearReaderOptions::default()
            .with_emit_chunks(true)
            .with_record_length_limit(MAX_RECORD_BYTES),
    );
    let mut pass = Pass {
        path,
        index: FileIndex::default(),
        schemas: HashMap::new(),
    };
    // File offset of the next top-level record (after the 8-byte magic).
    let mut offset = mcap::MAGIC.len() as u64;
    let mut read_to = 0u64;
    while let Some(event) = reader.next_event() {
        match event {
            Ok(LinearReadEvent::ReadRequest(need)) => {
                if read_to + need as u64 > file_len && read_to < file_len {
                    // Read what is left; the reader reports the end.
                    let left = (file_len - read_to) as usize;
                    let n = read_fully(&mut file, reader.insert(left)).map_err(io)?;
                    read_to += n as u64;
                    reader.notify_read(n);
                } else if read_to >= file_len {
                    reader.notify_read(0);
                } else {
                    let n = read_fully(&mut file, reader.insert(need)).map_err(io)?;
                    read_to += n as u64;
                    reader.notify_read(n);
                }
            }
            Ok(LinearReadEvent::Record { opcode, data }) => {
                let len = data.len() as u64;
                if offset == mcap::MAGIC.len() as u64 && opcode != mcap::records::op::HEADER {
                    return Err(not_mcap(path, "no header record after the magic"));
                }
                let done = pass.record(opcode, data, offset);
                offset += 9 + len;
                if done {
                    return Ok(pass.index);
                }
            }
            Err(mcap::McapError::BadMagic) => return Err(not_mcap(path, "no MCAP magic")),
            Err(e) => {
                pass.index.issues.push(issue_at(
                    path,
                    IssueKind::TruncatedFile,
                    format!(
                        "the file cannot be read past byte {offset} ({e}; {file_len} bytes in \
                         all): the messages before it are used, any after it are lost"
                    ),
                ));
                return Ok(pass.index);
            }
        }
    }
    Ok(pass.index)
}

fn not_mcap(path: &Path, why: &str) -> DatasetError {
    DatasetError::UnknownFormat {
        path: path.to_path_buf(),
        detail: format!("not an MCAP file ({why})"),
    }
}

/// Reads into `buf` until it is full or the file ends; the bytes read.
fn read_fully(file: &mut File, buf: &mut [u8]) -> std::io::Result<usize> {
    let mut n = 0;
    while n < buf.len() {
        match file.read(&mut buf[n..])? {
            0 => break,
            k => n += k,
        }
    }
    Ok(n)
}

/// Reads the body of the top-level record at `offset` (`len` bytes after its opcode and
/// length) into `buf`.
pub fn read_record(
    file: &mut File,
    offset: u64,
    len: u64,
    buf: &mut Vec<u8>,
) -> std::io::Result<u8> {
    file.seek(SeekFrom::Start(offset))?;
    let mut head = [0u8; 9];
    file.read_exact(&mut head)?;
    let stored = u64::from_le_bytes(head[1..].try_into().expect("8 bytes"));
    if stored != len {
        return Err(std::io::Error::new(
            std::io::ErrorKind::InvalidData,
            format!("record length {stored} at byte {offset}, the index says {len}"),
        ));
    }
    buf.resize(len as usize, 0);
    file.read_exact(buf)?;
    Ok(head[0])
}

/// The index pass's state.
struct Pass<'p> {
    path: &'p Path,
    index: FileIndex,
    /// Schema names by id.
    schemas: HashMap<u16, String>,
}

impl Pass<'_> {
    /// Takes one top-level record at `offset`; true at the end of the data section.
    fn record(&mut self, opcode: u8, body: &[u8], offset: u64) -> bool {
        let rec = match mcap::parse_record(opcode, body) {
            Ok(r) => r,
            Err(e) => {
                self.file_issue(
                    offset,
                    format!("record (opcode {opcode:#04x}) does not parse: {e}"),
                );
                return false;
            }
        };
        match rec {
            Record::Header(h) => self.index.profile = h.profile,
            Record::Chunk { header, data } => self.chunk(header, &data, offset, body.len() as u64),
            Record::Message { header, data } => {
                let at = McapFrameRef {
                    record_offset: offset,
                    record_len: body.len() as u64,
                    in_chunk: None,
                    channel: header.channel_id,
                    kind: ImageKind::RosRaw,
                };
                self.message(&header, &data, at);
            }
            Record::DataEnd(_) | Record::Footer(_) => return true,
            other => self.definition(other),
        }
        false
    }

    /// Schema, channel and metadata records (top level or in a chunk).
    fn definition(&mut self, rec: Record) {
        match rec {
            Record::Schema { header, .. } => {
                self.schemas.insert(header.id, header.name);
            }
            Record::Channel(c) => {
                let schema = self.schemas.get(&c.schema_id).cloned().unwrap_or_default();
                self.index.channels.insert(
                    c.id,
                    ChannelInfo {
                        topic: c.topic,
                        schema,
                        encoding: c.message_encoding,
                    },
                );
            }
            Record::Metadata(m) => {
                self.index.metadata.insert(m.name, m.metadata);
            }
            _ => {}
        }
    }

    /// A chunk: its messages are taken only when the whole chunk decompresses and its CRC
    /// holds.
    fn chunk(&mut self, header: mcap::records::ChunkHeader, data: &[u8], offset: u64, len: u64) {
        let reader = match mcap::read::ChunkReader::new(header, data) {
            Ok(r) => r,
            Err(e) => {
                self.file_issue(
                    offset,
                    format!("chunk cannot be read: {e}; its messages are skipped"),
                );
                return;
            }
        };
        let mut pending = Vec::new();
        for (i, rec) in reader.enumerate() {
            match rec {
                Ok(Record::Message { header, data }) => {
                    let at = McapFrameRef {
                        record_offset: offset,
                        record_len: len,
                        in_chunk: Some(i as u32),
                        channel: header.channel_id,
                        kind: ImageKind::RosRaw,
                    };
                    if self.wanted(header.channel_id) {
                        // Kept until the whole chunk has checked out.
                        pending.push((header, at, data.into_owned()));
                    }
                }
                Ok(other) => self.definition(other),
                Err(e) => {
                    self.file_issue(
                        offset,
                        format!(
                            "chunk is damaged ({e}): its {} messages read so far and the rest \
                             are skipped",
                            pending.len()
                        ),
                    );
                    return;
                }
            }
        }
        for (header, at, data) in pending {
            self.message(&header, &data, at);
        }
    }

    /// Whether messages of `channel` are worth keeping until the chunk checks out.
    fn wanted(&self, channel: u16) -> bool {
        self.index
            .channels
            .get(&channel)
            .is_some_and(|c| c.encoding == "cdr" && is_read_schema(&c.schema))
    }

    /// One message of a channel the reader knows.
    fn message(&mut self, header: &MessageHeader, data: &[u8], mut at: McapFrameRef) {
        let Some(info) = self.index.channels.get(&header.channel_id) else {
            return;
        };
        if info.encoding != "cdr" || !is_read_schema(&info.schema) {
            return;
        }
        let (topic, schema) = (info.topic.clone(), info.schema.clone());
        let ch = self.index.data.entry(header.channel_id).or_default();
        ch.count += 1;
        let n = ch.count;
        let bad = |detail: String| {
            issue_at(
                self.path,
                IssueKind::BadMessage,
                format!(
                    "topic {topic}, message {n} (record at byte {}): {detail}",
                    at.record_offset
                ),
            )
        };
        if let Some(kind) = ImageKind::of_schema(&schema) {
            at.kind = kind;
            match pixels::probe(kind, data) {
                Ok(p) => ch.images.push(ImageEntry {
                    stamp_ns: p.stamp_ns,
                    width: p.width,
                    height: p.height,
                    at,
                }),
                Err(e) => ch.issues.push(bad(e)),
            }
            return;
        }
        let outcome = match schema.as_str() {
            names::IMU => imu_sample(data).map(|s| ch.imu.push(s)),
            names::POSE_STAMPED => stamped_pose(data).map(|p| ch.poses.push(p)),
            names::CAMERA_INFO if ch.camera_info.is_none() => {
                camera_info(data).map(|c| ch.camera_info = Some(c))
            }
            _ => Ok(()),
        };
        if let Err(e) = outcome {
            ch.issues.push(bad(e));
        }
    }

    fn file_issue(&mut self, offset: u64, detail: String) {
        self.index.issues.push(issue_at(
            self.path,
            IssueKind::TruncatedFile,
            format!("record at byte {offset}: {detail}"),
        ));
    }
}

/// The schemas the reader takes messages of.
fn is_read_schema(schema: &str) -> bool {
    ImageKind::of_schema(schema).is_some()
        || matches!(
            schema,
            names::IMU | names::CAMERA_INFO | names::POSE_STAMPED
        )
}

fn stamp(t: msgs::Time) -> Result<i64, String> {
    t.to_ns()
        .ok_or_else(|| format!("header stamp nanosec {} is not below 1e9", t.nanosec))
}

fn imu_sample(data: &[u8]) -> Result<ImuSample, String> {
    let m: msgs::Imu = msgs::decode(data)?;
    let (w, a) = (m.angular_velocity, m.linear_acceleration);
    Ok(ImuSample {
        t_ns: stamp(m.header.stamp)?,
        gyro: [w.x, w.y, w.z],
        accel: [a.x, a.y, a.z],
    })
}

fn stamped_pose(data: &[u8]) -> Result<StampedPose, String> {
    let m: msgs::PoseStamped = msgs::decode(data)?;
    let (p, q) = (m.pose.position, m.pose.orientation);
    let quat = nalgebra::Quaternion::new(q.w, q.x, q.y, q.z);
    if !(quat.norm() - 1.0).abs().lt(&1e-6) {
        return Err(format!(
            "orientation is not a unit quaternion (norm {})",
            quat.norm()
        ));
    }
    Ok(StampedPose {
        t_ns: stamp(m.header.stamp)?,
        pose: nalgebra::Isometry3::from_parts(
            nalgebra::Translation3::new(p.x, p.y, p.z),
            nalgebra::UnitQuaternion::new_unchecked(quat),
        ),
    })
}

fn camera_info(data: &[u8]) -> Result<CameraInfoValues, String> {
    let m: msgs::CameraInfo = msgs::decode(data)?;
    Ok(CameraInfoValues {
        width: m.width,
        height: m.height,
        distortion_model: m.distortion_model.to_string(),
        d: m.d,
        k: m.k,
    })
}
