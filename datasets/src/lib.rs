//! Dataset readers (EuRoC ASL, KITTI odometry, phone logger, GoPro, AprilGrid detections,
//! MCAP files and ROS 2 bags), trajectory IO and the synthetic world generator.
//!
//! Every reader produces the same plain [`Dataset`]: camera calibration, the list of frames
//! (mid-row timestamps after the camera-IMU offset), IMU samples and optional ground truth.
//! Readers are lenient where it is safe: a malformed or non-monotonic line is skipped and
//! recorded in [`Dataset::issues`] (file + line), so the pipeline can count it and go on.
#![deny(missing_docs)]

pub mod april;
pub mod calibration;
pub mod detect;
pub mod error;
pub mod euroc;
pub mod gopro;
pub mod image_folder;
pub mod image_io;
pub mod kalibr;
pub mod kitti;
pub mod mcap_bag;
pub mod phone;
pub mod ros1_bag;
pub mod sim;
mod text;
pub mod trajectory;

use std::path::PathBuf;

pub use detect::{open, open_with, FrameRange, OpenOptions};
pub use error::DatasetError;
pub use image_io::{decode_gray, decode_gray_into, image_size};
pub use slam_core::camera::PinholeRadtan;

/// Which reader produced a [`Dataset`].
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum DatasetKind {
    /// EuRoC ASL layout (`mav0/cam0`, `mav0/imu0`, ...), also written by `shoal sim`.
    Euroc,
    /// KITTI odometry (`image_0/`, `times.txt`, `calib.txt`, optional `poses.txt`).
    Kitti,
    /// The phone logger format (`frames/`, `movie_metadata.csv`, `gyro_accel.csv`).
    Phone,
    /// A GoPro clip with its GPMF streams (`frames/*.jpg`, `frame_timestamps.csv`,
    /// `gyro.csv`, `accl.csv`).
    GoPro,
    /// Numbered images with a calibration and no timestamps (`images/`, `K.txt`, optional
    /// `D.txt` and ground truth; [`image_folder`]): frame `k` at `k / fps`.
    ImageFolder,
    /// Feature tracks instead of images: AprilGrid detections (`cam0/<t_ns>.csv`,
    /// `imu0.csv`, `config.yaml`; [`april`]). Each frame's [`FrameRecord::path`] is its
    /// detections file, which the camera ingest sends as a feature frame.
    AprilTracks,
    /// An MCAP recording or a rosbag2 folder with MCAP storage ([`mcap_bag`]); each frame
    /// is a message in the file ([`FrameSource::Mcap`]).
    Mcap,
    /// A ROS 1 bag ([`ros1_bag`]); each frame is a message in it ([`FrameSource::Ros1`]).
    Ros1Bag,
}

/// Camera calibration and timing of a dataset's camera.
#[derive(Debug, Clone, PartialEq)]
pub struct CameraCalib {
    /// Intrinsics, distortion and resolution.
    pub model: PinholeRadtan,
    /// Camera pose in the body (IMU) frame, `T_BS` (x_B = T_BS x_S). Identity when unknown.
    pub t_bs: nalgebra::Isometry3<f64>,
    /// `T_BS` was given by the dataset (a calibrated camera-IMU extrinsic), not assumed: the
    /// visual-inertial mode needs it.
    pub t_bs_given: bool,
    /// Default rolling-shutter readout time t_r of a whole frame in ns (0 = global shutter).
    pub readout_ns: i64,
    /// Camera-IMU time offset t_d in ns, already added to every [`FrameRecord::t_ns`].
    pub time_offset_ns: i64,
    /// Nominal frame rate in Hz (0 when unknown).
    pub rate_hz: f64,
}

/// One camera frame: an image file, or an image message in a recording.
#[derive(Debug, Clone, PartialEq)]
pub struct FrameRecord {
    /// Time of the middle row (and middle of the exposure), ns on the sensor clock, t_d applied.
    pub t_ns: i64,
    /// Image file (8-bit grayscale PNG expected; other PNGs are converted to gray).
    pub path: PathBuf,
    /// Exposure time in ns (0 when unknown).
    pub exposure_ns: i64,
    /// Rolling-shutter readout time of this frame in ns (0 = global shutter).
    pub readout_ns: i64,
    /// Where the pixels are: the image file `path`, or a message in the recording `path`.
    pub source: FrameSource,
}

/// Where a frame's pixels are ([`FrameReader`] reads either).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum FrameSource {
    /// The image file [`FrameRecord::path`] (PNG or JPEG).
    #[default]
    File,
    /// An image message of the MCAP file [`FrameRecord::path`].
    Mcap(mcap_bag::McapFrameRef),
    /// An image message of the ROS 1 bag [`FrameRecord::path`].
    Ros1(ros1_bag::Ros1FrameRef),
}

/// Reads frames as 8-bit gray whatever their [`FrameSource`]; an MCAP frame is read from
/// its file on demand ([`mcap_bag::McapFrameLoader`]). One per replaying thread.
#[derive(Debug, Default)]
pub struct FrameReader {
    mcap: mcap_bag::McapFrameLoader,
    ros1: ros1_bag::Ros1FrameLoader,
}

impl FrameReader {
    /// Decodes `frame` as 8-bit gray into `dst` (`width * height` bytes); a frame that
    /// cannot be read or decoded, or is of another size, is an error naming its file.
    pub fn read_gray_into(
        &mut self,
        frame: &FrameRecord,
        dst: &mut [u8],
        width: u32,
        height: u32,
    ) -> Result<(), DatasetError> {
        match &frame.source {
            FrameSource::File => decode_gray_into(&frame.path, dst, width, height),
            FrameSource::Mcap(at) => self
                .mcap
                .read_gray_into(&frame.path, at, dst, width, height),
            FrameSource::Ros1(at) => self
                .ros1
                .read_gray_into(&frame.path, at, dst, width, height),
        }
    }
}

/// One IMU sample (body frame), seed eq. 2.53-2.56 measurements.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ImuSample {
    /// Sample time, ns on the sensor clock.
    pub t_ns: i64,
    /// Angular rate w_m, rad/s.
    pub gyro: [f64; 3],
    /// Specific force a_m, m/s².
    pub accel: [f64; 3],
}

impl slam_core::imu::TimedImuSample for ImuSample {
    fn t_ns(&self) -> i64 {
        self.t_ns
    }
    fn gyro(&self) -> nalgebra::Vector3<f64> {
        self.gyro.into()
    }
    fn accel(&self) -> nalgebra::Vector3<f64> {
        self.accel.into()
    }
}

/// A pose with its time stamp.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct StampedPose {
    /// Time, ns on the sensor clock.
    pub t_ns: i64,
    /// The pose (camera-to-world for ground truth of the camera).
    pub pose: nalgebra::Isometry3<f64>,
}

/// The kinds of [`InputIssue`]. The services count them as errors of the same names
/// (`shoal_runtime::ErrorKind`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum IssueKind {
    /// A line that does not parse (`malformed_line`), e.g. a truncated IMU line.
    MalformedLine,
    /// A timestamp not after the previous one (`non_monotonic`); the line is skipped.
    NonMonotonic,
    /// An image the index names that does not exist (`missing_image`); the frame is dropped.
    MissingImage,
    /// A file of the layout this dataset lacks (`missing_file`), e.g. no IMU data.
    MissingFile,
    /// A pose without a valid time (`missing_time`).
    MissingTime,
    /// Times and poses of different counts (`length_mismatch`).
    LengthMismatch,
    /// A recorded message that does not decode, or of an unknown encoding (`bad_message`);
    /// it is skipped.
    BadMessage,
    /// A recording cut short or with a damaged chunk (`truncated_file`): what is before
    /// the damage (or around a damaged chunk) is used.
    TruncatedFile,
}

impl IssueKind {
    /// Every kind.
    pub const ALL: &'static [IssueKind] = &[
        Self::MalformedLine,
        Self::NonMonotonic,
        Self::MissingImage,
        Self::MissingFile,
        Self::MissingTime,
        Self::LengthMismatch,
        Self::BadMessage,
        Self::TruncatedFile,
    ];

    /// The kind's short machine-friendly name.
    pub fn as_str(self) -> &'static str {
        match self {
            Self::MalformedLine => "malformed_line",
            Self::NonMonotonic => "non_monotonic",
            Self::MissingImage => "missing_image",
            Self::MissingFile => "missing_file",
            Self::MissingTime => "missing_time",
            Self::LengthMismatch => "length_mismatch",
            Self::BadMessage => "bad_message",
            Self::TruncatedFile => "truncated_file",
        }
    }
}

impl std::fmt::Display for IssueKind {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.as_str())
    }
}

/// A problem found while reading a dataset that did not stop the read (a skipped line, a
/// non-monotonic timestamp, a missing image). Counted and reported by the services.
#[derive(Debug, Clone, PartialEq)]
pub struct InputIssue {
    /// The file.
    pub path: PathBuf,
    /// 1-based line (0 when not tied to a line).
    pub line: usize,
    /// What is wrong (its name, e.g. `malformed_line`: [`IssueKind::as_str`]).
    pub kind: IssueKind,
    /// Human-readable detail.
    pub detail: String,
}

/// A dataset, fully indexed (images are decoded on demand).
#[derive(Debug, Clone)]
pub struct Dataset {
    /// Which reader produced it.
    pub kind: DatasetKind,
    /// The folder it was read from.
    pub root: PathBuf,
    /// Camera calibration.
    pub camera: CameraCalib,
    /// Frames in strictly increasing time order.
    pub frames: Vec<FrameRecord>,
    /// IMU samples in strictly increasing time order (empty when the dataset has none).
    pub imu: Vec<ImuSample>,
    /// Camera-to-world ground truth of cam0 (at frame times where available), if any.
    pub ground_truth: Option<Vec<StampedPose>>,
    /// Problems met and skipped while reading.
    pub issues: Vec<InputIssue>,
    /// The frames' times were first-row stamps (a ROS bag's): `t_ns` = stamp + t_r/2 + t_d,
    /// so a calibration file with another t_r moves them by half the difference too.
    pub first_row_stamps: bool,
    /// The IMU calibration the recording carries (a shoal-written MCAP's), in place of an
    /// `imu0/sensor.yaml`.
    pub imu_calib: Option<euroc::ImuSensorCalib>,
}

/// IMU kept on each side of a frame range ([`Dataset::select_frames`]), ns.
const RANGE_IMU_MARGIN_NS: i64 = 1_000_000_000;

impl Dataset {
    /// Keeps frames `range` only, with their own times (`shoal run --frames A..B`): the
    /// ground truth between the first and last kept frame, and the IMU from
    /// [`RANGE_IMU_MARGIN_NS`] before to as much after. An error when the range starts past
    /// the last frame; an end past it is the end.
    pub fn select_frames(&mut self, range: crate::FrameRange) -> Result<(), DatasetError> {
        let n = self.frames.len();
        let end = range.end.unwrap_or(n).min(n);
        if range.start >= end {
            return Err(DatasetError::InvalidConfig {
                detail: format!(
                    "--frames {range}: {} has {n} frames (0..{n})",
                    self.root.display()
                ),
            });
        }
        self.frames.truncate(end);
        self.frames.drain(..range.start);
        let (t0, t1) = (self.frames[0].t_ns, self.frames[self.frames.len() - 1].t_ns);
        if let Some(gt) = &mut self.ground_truth {
            gt.retain(|p| (t0..=t1).contains(&p.t_ns));
        }
        let m = RANGE_IMU_MARGIN_NS;
        self.imu.retain(|s| (t0 - m..=t1 + m).contains(&s.t_ns));
        Ok(())
    }
}
