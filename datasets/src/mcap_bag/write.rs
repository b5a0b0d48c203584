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
use std::path::Path;

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
    let mcap_err = |e: mcap::McapError| DatasetError::Io {
        path: out.to_path_buf(),
        source: std::io::Error::other(e.to_string()),
    };
    let mut tmp = out.as_os_str().to_owned();
    tmp.push(".tmp");
    let tmp = std::path::PathBuf::from(tmp);
    let file = File::create(&tmp).map_err(|source| DatasetError::Io {
        path: tmp.clone(),
        source,
    })?;
    let mut w = options(settings)
        .create(BufWriter::with_capacity(1 << 20, file))
        .map_err(mcap_err)?;
    let meta = ShoalMeta {
        camera: ds.camera.clone(),
        imu: imu.copied(),
        middle_row: true,
        ground_truth_topic: ds.ground_truth.as_ref().map(|_| GROUND_TRUTH_TOPIC.into()),
    };
    w.write_metadata(&Metadata {
        name: meta::RECORD.into(),
        metadata: meta::to_map(&meta),
    })
    .map_err(mcap_err)?;
    let ch = add_channels(&mut w, ds.ground_truth.is_some()).map_err(mcap_err)?;
    let mut summary = WriteSummary::default();
    let mut writer = MessageWriter {
        w: &mut w,
        out,
        seq: BTreeMap::new(),
    };
    write_messages(ds, &ch, &mut writer, &mut summary)?;
    w.finish().map_err(mcap_err)?;
    drop(w);
    if summary.frames == 0 && !ds.frames.is_empty() {
        let _ = std::fs::remove_file(&tmp);
        return Err(DatasetError::InvalidConfig {
            detail: format!(
                "{}: not written: none of the {} frames could be read (first: {})",
                out.display(),
                ds.frames.len(),
                summary.skipped_frames.first().map_or("", String::as_str)
            ),
        });
    }
    std::fs::rename(&tmp, out).map_err(|source| DatasetError::Io {
        path: out.to_path_buf(),
        source,
    })?;
    summary.bytes = std::fs::metadata(out).map(|m| m.len()).unwrap_or(0);
    Ok(summary)
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

/// Writes encoded messages with per-channel sequence numbers.
struct MessageWriter<'a, W: std::io::Write + std::io::Seek> {
    w: &'a mut mcap::Writer<W>,
    out: &'a Path,
    seq: BTreeMap<u16, u32>,
}

impl<W: std::io::Write + std::io::Seek> MessageWriter<'_, W> {
    fn put(&mut self, channel: u16, t_ns: i64, data: &[u8]) -> Result<(), DatasetError> {
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
        self.w
            .write_to_known_channel(&header, data)
            .map_err(|e| DatasetError::Io {
                path: self.out.to_path_buf(),
                source: std::io::Error::other(e.to_string()),
            })
    }
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
fn write_messages<W: std::io::Write + std::io::Seek>(
    ds: &Dataset,
    ch: &Channels,
    w: &mut MessageWriter<W>,
    summary: &mut WriteSummary,
) -> Result<(), DatasetError> {
    let out = w.out;
    let t0 = [
        ds.frames.first().map(|f| f.t_ns),
        ds.imu.first().map(|s| s.t_ns),
    ]
    .into_iter()
    .flatten()
    .min()
    .unwrap_or(0);
    let info = camera_info(ds, ros_time(t0, out)?);
    w.put(ch.info, t0, &encode(&info, 512, out)?)?;
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
            let s = &ds.imu[i];
            w.put(
                ch.imu,
                t,
                &encode(&imu_msg(s, ros_time(t, out)?), 400, out)?,
            )?;
            (i, summary.imu_samples) = (i + 1, summary.imu_samples + 1);
        } else if tf == t {
            let frame = &ds.frames[f];
            f += 1;
            if let Err(e) = reader.read_gray_into(frame, &mut pixels, width, height) {
                summary.skipped_frames.push(e.to_string());
                continue;
            }
            let img = msgs::Image {
                header: Header {
                    stamp: ros_time(t, out)?,
                    frame_id: CAMERA_FRAME.into(),
                },
                height,
                width,
                encoding: "mono8".into(),
                is_bigendian: 0,
                step: width,
                data: Bytes(&pixels),
            };
            w.put(ch.image, t, &encode(&img, pixels.len() + 128, out)?)?;
            summary.frames += 1;
        } else if let Some(gt) = ch.gt {
            let m = pose_msg(&poses[p], ros_time(t, out)?);
            w.put(gt, t, &encode(&m, 128, out)?)?;
            (p, summary.poses) = (p + 1, summary.poses + 1);
        } else {
            p += 1;
        }
    }
}

fn camera_info(ds: &Dataset, stamp: Time) -> msgs::CameraInfo<'static> {
    let m = &ds.camera.model;
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

fn pose_msg(p: &crate::StampedPose, stamp: Time) -> msgs::PoseStamped<'static> {
    let (t, q) = (p.pose.translation.vector, p.pose.rotation.quaternion());
    msgs::PoseStamped {
        header: Header {
            stamp,
            frame_id: "world".into(),
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
