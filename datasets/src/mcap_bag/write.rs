//! `shoal convert --to mcap`: any dataset `shoal run` reads, as an MCAP file of CDR-encoded
//! ROS 2 messages with `ros2msg` schemas (profile `ros2`: ROS 2 tools, Foxglove and the
//! `mcap` Python packages read it), chunked and compressed:
//!
//! - [`IMAGE_TOPIC`]: `sensor_msgs/msg/Image`, `mono8`, stamped with the frame's middle-row
//!   time (t_d applied), as the frames are replayed;
//! - [`CAMERA_INFO_TOPIC`]: one `sensor_msgs/msg/CameraInfo` (`plumb_bob`);
//! - [`IMU_TOPIC`]: `sensor_msgs/msg/Imu` (no orientation: covariance[0] = -1);
//! - [`GROUND_TRUTH_TOPIC`]: `geometry_msgs/msg/PoseStamped`, camera-to-world, when the
//!   dataset has ground truth;
//! - the `shoal` metadata record ([`super::meta`]): the stamps are middle-row times (read
//!   back unchanged), the calibration ROS messages lack (T_BS, t_r, t_d, IMU model).
//!
//! Messages are written in time order (log time = header stamp); the file is written to a
//! temporary name and renamed when complete.

use std::collections::BTreeMap;
use std::fs::File;
use std::io::BufWriter;
use std::path::{Path, PathBuf};

use mcap::records::{MessageHeader, Metadata};

use super::meta::{self, ShoalMeta};
use super::msgs::{self, names, Bytes, Header, Time};
use crate::euroc::ImuSensorCalib;
use crate::{Dataset, DatasetError, DatasetKind, FrameReader};

/// Topic of the images.
pub const IMAGE_TOPIC: &str = "/cam0/image_raw";
/// Topic of the camera calibration.
pub const CAMERA_INFO_TOPIC: &str = "/cam0/camera_info";
/// Topic of the IMU samples.
pub const IMU_TOPIC: &str = "/imu0";
/// Topic of the ground truth (camera-to-world of cam0).
pub const GROUND_TRUTH_TOPIC: &str = "/cam0/ground_truth";
/// `frame_id` of the images and camera info.
const CAMERA_FRAME: &str = "cam0";

/// Chunk compression.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum Compression {
    /// zstd (rosbag2's and the MCAP tools' default).
    #[default]
    Zstd,
    /// LZ4 (faster to write and read, larger).
    Lz4,
    /// None.
    None,
}

/// How to write.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct WriteSettings {
    /// Chunk compression.
    pub compression: Compression,
    /// Chunk size in bytes (`None`: the `mcap` crate's default, 1 MiB).
    pub chunk_bytes: Option<u64>,
}

/// What was written.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct WriteSummary {
    /// Frames written.
    pub frames: usize,
    /// IMU samples written.
    pub imu_samples: usize,
    /// Ground-truth poses written.
    pub poses: usize,
    /// Frames that could not be read from the source (each: why), not written.
    pub skipped_frames: Vec<String>,
    /// Size of the file, bytes.
    pub bytes: u64,
}

/// The channel ids of the file being written.
struct Channels {
    image: u16,
    info: u16,
    imu: u16,
    gt: Option<u16>,
}

/// An MCAP file of ROS 2 messages being written: the `shoal` metadata record first, then
/// messages as they come (per-channel sequence numbers), to a temporary name renamed by
/// [`StreamWriter::finish`]. [`write_dataset`] writes a whole dataset through it; a run's
/// recording (`shoal run --record`) writes what crosses shared memory as it comes.
pub struct StreamWriter {
    w: mcap::Writer<BufWriter<File>>,
    tmp: PathBuf,
    out: PathBuf,
    ch: Channels,
    seq: BTreeMap<u16, u32>,
    /// Counts of what was written.
    pub summary: WriteSummary,
}

impl StreamWriter {
    /// Starts the file `out` (written as `out.tmp` until [`Self::finish`]) with `meta`
    /// (the camera, middle-row stamps, the IMU model) and the image, camera-info and IMU
    /// channels (and the ground-truth one when `meta` names it).
    pub fn create(
        out: &Path,
        meta: &ShoalMeta,
        settings: &WriteSettings,
    ) -> Result<Self, DatasetError> {
        let mut tmp = out.as_os_str().to_owned();
        tmp.push(".tmp");
        let tmp = PathBuf::from(tmp);
        let file = File::create(&tmp).map_err(|source| DatasetError::Io {
            path: tmp.clone(),
            source,
        })?;
        let mcap_err = |e: mcap::McapError| io_error(out, e);
        let mut w = options(settings)
            .create(BufWriter::with_capacity(1 << 20, file))
            .map_err(mcap_err)?;
        w.write_metadata(&Metadata {
            name: meta::RECORD.into(),
            metadata: meta::to_map(meta),
        })
        .map_err(mcap_err)?;
        let ch = add_channels(&mut w, meta.ground_truth_topic.is_some()).map_err(mcap_err)?;
        Ok(Self {
            w,
            tmp,
            out: out.to_path_buf(),
            ch,
            seq: BTreeMap::new(),
            summary: WriteSummary::default(),
        })
    }

    /// Adds a channel of `schema_name` (`ros2msg` text `schema`, CDR messages) on `topic`;
    /// its id for [`Self::put`].
    pub fn add_channel(
        &mut self,
        schema_name: &str,
        schema: &str,
        topic: &str,
    ) -> Result<u16, DatasetError> {
        let none = BTreeMap::new();
        let id = (self.w.add_schema(schema_name, "ros2msg", schema.as_bytes()))
            .map_err(|e| io_error(&self.out, e))?;
        (self.w.add_channel(id, topic, "cdr", &none)).map_err(|e| io_error(&self.out, e))
    }

    /// Adds a channel of another encoding (Foxglove's protobuf schemas in a recording):
    /// `schema_name` with `schema_encoding` data `schema`, `message_encoding` messages on
    /// `topic`; its id for [`Self::put`].
    pub fn add_encoded_channel(
        &mut self,
        schema_name: &str,
        schema_encoding: &str,
        schema: &[u8],
        message_encoding: &str,
        topic: &str,
    ) -> Result<u16, DatasetError> {
        let none = BTreeMap::new();
        let id = (self.w.add_schema(schema_name, schema_encoding, schema))
            .map_err(|e| io_error(&self.out, e))?;
        (self.w.add_channel(id, topic, message_encoding, &none)).map_err(|e| io_error(&self.out, e))
    }

    /// Writes an encoded message on `channel` at log time `t_ns`.
    pub fn put(&mut self, channel: u16, t_ns: i64, data: &[u8]) -> Result<(), DatasetError> {
        let log_time = u64::try_from(t_ns).map_err(|_| DatasetError::InvalidConfig {
            detail: format!(
                "{}: time {t_ns} ns is negative; MCAP log times are unsigned",
                self.out.display()
            ),
        })?;
        let seq = self.seq.entry(channel).or_insert(0);
        *seq += 1;
        let header = MessageHeader {
            channel_id: channel,
            sequence: *seq,
            log_time,
            publish_time: log_time,
        };
        (self.w.write_to_known_channel(&header, data)).map_err(|e| io_error(&self.out, e))
    }

    /// Encodes `msg` (CDR, `hint` bytes expected) and writes it on `channel` at `t_ns`.
    pub fn put_msg<T: serde::Serialize>(
        &mut self,
        channel: u16,
        t_ns: i64,
        msg: &T,
        hint: usize,
    ) -> Result<(), DatasetError> {
        let data = encode(msg, hint, &self.out)?;
        self.put(channel, t_ns, &data)
    }

    /// `t_ns` as a ROS time (an error names the file when it does not fit).
    pub fn ros_time(&self, t_ns: i64) -> Result<Time, DatasetError> {
        ros_time(t_ns, &self.out)
    }

    /// The camera's `sensor_msgs/msg/CameraInfo` at `t_ns`.
    pub fn camera_info(
        &mut self,
        camera: &crate::CameraCalib,
        t_ns: i64,
    ) -> Result<(), DatasetError> {
        let info = camera_info(camera, ros_time(t_ns, &self.out)?);
        let data = encode(&info, 512, &self.out)?;
        self.put(self.ch.info, t_ns, &data)
    }

    /// A `mono8` image of `width` x `height` (rows of `width` bytes) at `t_ns`.
    pub fn image(
        &mut self,
        t_ns: i64,
        width: u32,
        height: u32,
        pixels: &[u8],
    ) -> Result<(), DatasetError> {
        let img = msgs::Image {
            header: Header {
                stamp: ros_time(t_ns, &self.out)?,
                frame_id: CAMERA_FRAME.into(),
            },
            height,
            width,
            encoding: "mono8".into(),
            is_bigendian: 0,
            step: width,
            data: Bytes(pixels),
        };
        let data = encode(&img, pixels.len() + 128, &self.out)?;
        self.put(self.ch.image, t_ns, &data)?;
        self.summary.frames += 1;
        Ok(())
    }

    /// An IMU sample.
    pub fn imu(&mut self, s: &crate::ImuSample) -> Result<(), DatasetError> {
        let data = encode(&imu_msg(s, ros_time(s.t_ns, &self.out)?), 400, &self.out)?;
        self.put(self.ch.imu, s.t_ns, &data)?;
        self.summary.imu_samples += 1;
        Ok(())
    }

    /// A `geometry_msgs/msg/PoseStamped` of `pose` in `frame_id` at `t_ns` on `channel`
    /// (`None`: the ground-truth channel).
    pub fn pose(
        &mut self,
        channel: Option<u16>,
        t_ns: i64,
        pose: &nalgebra::Isometry3<f64>,
        frame_id: &str,
    ) -> Result<(), DatasetError> {
        let Some(channel) = channel.or(self.ch.gt) else {
            return Ok(());
        };
        let m = pose_msg(pose, frame_id, ros_time(t_ns, &self.out)?);
        let data = encode(&m, 128, &self.out)?;
        self.put(channel, t_ns, &data)?;
        self.summary.poses += usize::from(Some(channel) == self.ch.gt);
        Ok(())
    }

    /// Ends the file (summary, index) and renames it to its name; returns what was
    /// written.
    pub fn finish(mut self) -> Result<WriteSummary, DatasetError> {
        self.w.finish().map_err(|e| io_error(&self.out, e))?;
        drop(self.w);
        std::fs::rename(&self.tmp, &self.out).map_err(|source| DatasetError::Io {
            path: self.out.clone(),
            source,
        })?;
        self.summary.bytes = std::fs::metadata(&self.out).map(|m| m.len()).unwrap_or(0);
        Ok(self.summary)
    }

    /// Drops the unfinished file.
    pub fn abandon(self) {
        let tmp = self.tmp.clone();
        drop(self);
        let _ = std::fs::remove_file(tmp);
    }
}

fn io_error(out: &Path, e: mcap::McapError) -> DatasetError {
    DatasetError::Io {
        path: out.to_path_buf(),
        source: std::io::Error::other(e.to_string()),
    }
}

/// Writes `ds` (with its IMU calibration `imu`, if known) to the MCAP file `out`.
pub fn write_dataset(
    ds: &Dataset,
    imu: Option<&ImuSensorCalib>,
    out: &Path,
    settings: &WriteSettings,
) -> Result<WriteSummary, DatasetError> {
    if ds.kind == DatasetKind::AprilTracks {
        return Err(DatasetError::InvalidConfig {
            detail: format!(
                "{}: a dataset of feature tracks has no images to write",
                ds.root.display()
            ),
        });
    }
    let meta = ShoalMeta {
        camera: ds.camera.clone(),
        imu: imu.copied(),
        middle_row: true,
        ground_truth_topic: ds.ground_truth.as_ref().map(|_| GROUND_TRUTH_TOPIC.into()),
    };
    let mut w = StreamWriter::create(out, &meta, settings)?;
    if let Err(e) = write_messages(ds, &mut w) {
        w.abandon();
        return Err(e);
    }
    if w.summary.frames == 0 && !ds.frames.is_empty() {
        let detail = format!(
            "{}: not written: none of the {} frames could be read (first: {})",
            out.display(),
            ds.frames.len(),
            w.summary.skipped_frames.first().map_or("", String::as_str)
        );
        w.abandon();
        return Err(DatasetError::InvalidConfig { detail });
    }
    w.finish()
}

fn options(settings: &WriteSettings) -> mcap::WriteOptions {
    let compression = match settings.compression {
        Compression::Zstd => Some(mcap::Compression::Zstd),
        Compression::Lz4 => Some(mcap::Compression::Lz4),
        Compression::None => None,
    };
    let mut o = mcap::WriteOptions::new()
        .profile("ros2")
        .library(format!("shoal {}", env!("CARGO_PKG_VERSION")))
        .compression(compression)
        // One thread: the machine is shared, and the output does not depend on it.
        .compression_threads(0);
    if let Some(bytes) = settings.chunk_bytes {
        o = o.chunk_size(Some(bytes));
    }
    o
}

fn add_channels<W: std::io::Write + std::io::Seek>(
    w: &mut mcap::Writer<W>,
    ground_truth: bool,
) -> mcap::McapResult<Channels> {
    let none = BTreeMap::new();
    let mut channel = |schema: &str, text: String, topic: &str| -> mcap::McapResult<u16> {
        let id = w.add_schema(schema, "ros2msg", text.as_bytes())?;
        w.add_channel(id, topic, "cdr", &none)
    };
    Ok(Channels {
        image: channel(names::IMAGE, msgs::image_schema(), IMAGE_TOPIC)?,
        info: channel(
            names::CAMERA_INFO,
            msgs::camera_info_schema(),
            CAMERA_INFO_TOPIC,
        )?,
        imu: channel(names::IMU, msgs::imu_schema(), IMU_TOPIC)?,
        gt: if ground_truth {
            Some(channel(
                names::POSE_STAMPED,
                msgs::pose_stamped_schema(),
                GROUND_TRUTH_TOPIC,
            )?)
        } else {
            None
        },
    })
}

fn ros_time(t_ns: i64, out: &Path) -> Result<Time, DatasetError> {
    Time::from_ns(t_ns).ok_or_else(|| DatasetError::InvalidConfig {
        detail: format!(
            "{}: time {t_ns} ns does not fit a ROS time (int32 seconds)",
            out.display()
        ),
    })
}

fn encode<T: serde::Serialize>(m: &T, hint: usize, out: &Path) -> Result<Vec<u8>, DatasetError> {
    msgs::encode(m, hint).map_err(|detail| DatasetError::InvalidConfig {
        detail: format!("{}: {detail}", out.display()),
    })
}

/// The camera info, then frames, IMU samples and poses merged in time order.
fn write_messages(ds: &Dataset, w: &mut StreamWriter) -> Result<(), DatasetError> {
    let t0 = [
        ds.frames.first().map(|f| f.t_ns),
        ds.imu.first().map(|s| s.t_ns),
    ]
    .into_iter()
    .flatten()
    .min()
    .unwrap_or(0);
    w.camera_info(&ds.camera, t0)?;
    let (width, height) = (ds.camera.model.width, ds.camera.model.height);
    let mut pixels = vec![0u8; width as usize * height as usize];
    let mut reader = FrameReader::default();
    let no_poses = Vec::new();
    let poses = ds.ground_truth.as_ref().unwrap_or(&no_poses);
    let (mut f, mut i, mut p) = (0, 0, 0);
    loop {
        let tf = ds.frames.get(f).map_or(i64::MAX, |x| x.t_ns);
        let ti = ds.imu.get(i).map_or(i64::MAX, |x| x.t_ns);
        let tp = poses.get(p).map_or(i64::MAX, |x| x.t_ns);
        let t = tf.min(ti).min(tp);
        if t == i64::MAX {
            return Ok(());
        }
        if ti == t {
            w.imu(&ds.imu[i])?;
            i += 1;
        } else if tf == t {
            let frame = &ds.frames[f];
            f += 1;
            match reader.read_gray_into(frame, &mut pixels, width, height) {
                Ok(()) => w.image(t, width, height, &pixels)?,
                Err(e) => w.summary.skipped_frames.push(e.to_string()),
            }
        } else {
            w.pose(None, t, &poses[p].pose, "world")?;
            p += 1;
        }
    }
}

fn camera_info(camera: &crate::CameraCalib, stamp: Time) -> msgs::CameraInfo<'static> {
    let m = &camera.model;
    msgs::CameraInfo {
        header: Header {
            stamp,
            frame_id: CAMERA_FRAME.into(),
        },
        height: m.height,
        width: m.width,
        distortion_model: "plumb_bob".into(),
        d: vec![m.k1, m.k2, m.p1, m.p2, m.k3],
        k: [m.fx, 0.0, m.cx, 0.0, m.fy, m.cy, 0.0, 0.0, 1.0],
        r: [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0],
        p: [
            m.fx, 0.0, m.cx, 0.0, 0.0, m.fy, m.cy, 0.0, 0.0, 0.0, 1.0, 0.0,
        ],
        binning_x: 0,
        binning_y: 0,
        roi: msgs::RegionOfInterest::default(),
    }
}

fn imu_msg(s: &crate::ImuSample, stamp: Time) -> msgs::Imu<'static> {
    let mut no_orientation = [0.0; 9];
    no_orientation[0] = -1.0;
    let v = |a: [f64; 3]| msgs::Vector3 {
        x: a[0],
        y: a[1],
        z: a[2],
    };
    msgs::Imu {
        header: Header {
            stamp,
            frame_id: "imu0".into(),
        },
        orientation: msgs::Quaternion::default(),
        orientation_covariance: no_orientation,
        angular_velocity: v(s.gyro),
        angular_velocity_covariance: [0.0; 9],
        linear_acceleration: v(s.accel),
        linear_acceleration_covariance: [0.0; 9],
    }
}

/// `pose` as a `geometry_msgs/msg/PoseStamped` in `frame_id` at `stamp`.
pub fn pose_msg(
    pose: &nalgebra::Isometry3<f64>,
    frame_id: &str,
    stamp: Time,
) -> msgs::PoseStamped<'static> {
    let (t, q) = (pose.translation.vector, pose.rotation.quaternion());
    msgs::PoseStamped {
        header: Header {
            stamp,
            frame_id: frame_id.to_string().into(),
        },
        pose: msgs::Pose {
            position: msgs::Vector3 {
                x: t.x,
                y: t.y,
                z: t.z,
            },
            orientation: msgs::Quaternion {
                x: q.i,
                y: q.j,
                z: q.k,
                w: q.w,
            },
        },
    }
}
