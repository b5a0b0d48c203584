//! Format auto-detection: [`open`] picks the reader from the folder layout.
//!
//! - `mav0/` (or the folder is itself a `mav0` with `cam0/` or `imu0/`) → EuRoC ASL;
//! - `image_0/` + `times.txt` → KITTI odometry;
//! - `movie_metadata.csv` → phone logger;
//! - `frame_timestamps.csv` + `gyro.csv` + `accl.csv` + `frames/` → GoPro clip;
//! - `cam0/` + `imu0.csv` + `config.yaml` → AprilGrid detections (feature tracks);
//! - `images/` + `K.txt` → an image folder without timestamps;
//! - a file starting with the MCAP magic, or a folder with a rosbag2 `metadata.yaml` →
//!   MCAP / ROS 2 bag ([`crate::mcap_bag`]).
//!
//! [`open_with`] also takes what `shoal run` may say of any dataset ([`OpenOptions`]): a
//! calibration file, an MCAP recording's topics, the frame rate of an index-only sequence,
//! and a range of its frames.

use std::path::{Path, PathBuf};

use crate::{
    april, euroc, gopro, image_folder, kitti, mcap_bag, phone, ros1_bag, Dataset, DatasetError,
    DatasetKind,
};

/// How to open a dataset ([`open_with`]).
#[derive(Debug, Clone, Default, PartialEq)]
pub struct OpenOptions {
    /// A calibration file to put in place of the dataset's own (`--calib`, [`open_with`]).
    pub calib: Option<PathBuf>,
    /// The topics of an MCAP recording (`--image-topic`, `--imu-topic`); ignored for the
    /// other formats.
    pub topics: mcap_bag::Topics,
    /// Frame rate of a sequence without timestamps (an image folder, `--fps`), Hz.
    pub fps: Option<f64>,
    /// Only these frames (`--frames`, [`Dataset::select_frames`]).
    pub frames: Option<FrameRange>,
}

/// The kind of dataset in `path`, without reading it. `NotFound` for a missing folder,
/// `UnknownFormat` when no layout matches.
pub fn detect(path: &Path) -> Result<DatasetKind, DatasetError> {
    if !path.exists() {
        return Err(DatasetError::NotFound {
            path: path.into(),
            what: "dataset folder".into(),
        });
    }
    if mcap_bag::is_mcap_file(path) {
        return Ok(DatasetKind::Mcap);
    }
    if ros1_bag::is_ros1_bag(path) {
        return Ok(DatasetKind::Ros1Bag);
    }
    if !path.is_dir() {
        return Err(DatasetError::UnknownFormat {
            path: path.into(),
            detail: "neither an MCAP file, a ROS 1 bag nor a folder (EuRoC, KITTI, phone logger, GoPro, \
                     AprilGrid detections, rosbag2)"
                .into(),
        });
    }
    // Before EuRoC: its `cam0/` would pass for a bare `mav0`.
    if mcap_bag::is_rosbag2(path) {
        Ok(DatasetKind::Mcap)
    } else if april::is_april_layout(path) {
        Ok(DatasetKind::AprilTracks)
    } else if euroc::mav0_dir(path).is_some() {
        Ok(DatasetKind::Euroc)
    } else if kitti::is_kitti(path) {
        Ok(DatasetKind::Kitti)
    } else if phone::is_phone(path) {
        Ok(DatasetKind::Phone)
    } else if gopro::is_gopro(path) {
        Ok(DatasetKind::GoPro)
    } else if image_folder::is_image_folder(path) {
        Ok(DatasetKind::ImageFolder)
    } else {
        Err(DatasetError::UnknownFormat {
            path: path.into(),
            detail: "expected `mav0/` (EuRoC), `image_0/` + `times.txt` (KITTI), \
                     `movie_metadata.csv` (phone logger) or `frame_timestamps.csv` + \
                     `gyro.csv` + `accl.csv` (GoPro), `cam0/` + `imu0.csv` + `config.yaml` \
                     (AprilGrid detections), `images/` + `K.txt` (image folder) or \
                     `metadata.yaml` (rosbag2)"
                .into(),
        })
    }
}

/// Opens the dataset in `path` with the reader its layout calls for (an image folder at
/// [`image_folder::DEFAULT_FPS`]).
pub fn open(path: &Path) -> Result<Dataset, DatasetError> {
    open_reader(path, &OpenOptions::default())
}

/// [`open`] with the options' topics (an MCAP recording's).
fn open_reader(path: &Path, options: &OpenOptions) -> Result<Dataset, DatasetError> {
    match detect(path)? {
        DatasetKind::Mcap => mcap_bag::read(path, &options.topics, options.calib.is_some()),
        DatasetKind::Ros1Bag => ros1_bag::read(path, &options.topics, options.calib.is_some()),
        DatasetKind::Euroc => euroc::read(path),
        DatasetKind::Kitti => kitti::read(path),
        DatasetKind::Phone => phone::read(path),
        DatasetKind::GoPro => gopro::read(path),
        DatasetKind::AprilTracks => april::open(path),
        DatasetKind::ImageFolder => image_folder::read(path, options.fps),
    }
}

/// Frames `start` to `end - 1` of a sequence (0-based, in the dataset's frame order; `end`
/// `None`: to the last), as `shoal run --frames A..B` (or `A..`) gives them.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct FrameRange {
    /// First frame.
    pub start: usize,
    /// One past the last frame (`None`: the end of the sequence).
    pub end: Option<usize>,
}

impl std::str::FromStr for FrameRange {
    type Err = String;

    fn from_str(s: &str) -> Result<Self, Self::Err> {
        let bad = || format!("`{s}`: expected a frame range `A..B` (frames A to B-1) or `A..`");
        let (a, b) = s.split_once("..").ok_or_else(bad)?;
        let start = a.trim().parse().map_err(|_| bad())?;
        let end = match b.trim() {
            "" => None,
            b => Some(b.parse().map_err(|_| bad())?),
        };
        if end.is_some_and(|e| e <= start) {
            return Err(format!("`{s}`: the range holds no frame (B must exceed A)"));
        }
        Ok(Self { start, end })
    }
}

impl serde::Serialize for FrameRange {
    fn serialize<S: serde::Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
        s.collect_str(self)
    }
}

impl<'de> serde::Deserialize<'de> for FrameRange {
    fn deserialize<D: serde::Deserializer<'de>>(d: D) -> Result<Self, D::Error> {
        let s = String::deserialize(d)?;
        s.parse().map_err(serde::de::Error::custom)
    }
}

impl std::fmt::Display for FrameRange {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self.end {
            Some(e) => write!(f, "{}..{e}", self.start),
            None => write!(f, "{}..", self.start),
        }
    }
}

/// Opens the dataset in `path` as `options` say: the reader (with an MCAP recording's
/// topics, an image folder's frame rate); the calibration file in place of the dataset's
/// own ([`crate::calibration::CalibrationFile::apply_to`]: camera model, `T_BS`, `t_r`,
/// and the frames re-stamped with its `t_d`; one that cannot be read or does not fit the
/// dataset is an error naming the file); then the frame range.
pub fn open_with(path: &Path, options: &OpenOptions) -> Result<Dataset, DatasetError> {
    let mut ds = open_reader(path, options)?;
    if let Some(file) = &options.calib {
        let c = crate::calibration::CalibrationFile::read(file)?;
        c.apply_to(&mut ds).map_err(|detail| DatasetError::Parse {
            path: file.to_path_buf(),
            line: 0,
            detail: format!("does not fit the dataset {}: {detail}", path.display()),
        })?;
    }
    if let Some(r) = options.frames {
        ds.select_frames(r)?;
    }
    Ok(ds)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::{FrameRecord, ImuSample, StampedPose};

    #[test]
    fn frame_ranges_parse_and_refuse_empty_ones() {
        let r: FrameRange = "450..736".parse().expect("range");
        assert_eq!((r.start, r.end), (450, Some(736)));
        assert_eq!(r.to_string(), "450..736");
        let r: FrameRange = "10..".parse().expect("open range");
        assert_eq!((r.start, r.end), (10, None));
        for bad in ["5", "a..9", "9..9", "9..3", "..4"] {
            assert!(bad.parse::<FrameRange>().is_err(), "{bad}");
        }
    }

    fn dataset(n: usize) -> Dataset {
        let t = |k: usize| k as i64 * 50_000_000;
        Dataset {
            kind: DatasetKind::Euroc,
            root: "x".into(),
            camera: crate::CameraCalib {
                model: crate::PinholeRadtan::pinhole(8, 8, 1.0, 1.0, 4.0, 4.0),
                t_bs: Default::default(),
                t_bs_given: false,
                readout_ns: 0,
                time_offset_ns: 0,
                rate_hz: 20.0,
            },
            frames: (0..n)
                .map(|k| FrameRecord {
                    t_ns: t(k),
                    path: format!("{k}.png").into(),
                    exposure_ns: 0,
                    readout_ns: 0,
                    source: Default::default(),
                })
                .collect(),
            imu: (0..n * 10)
                .map(|i| ImuSample {
                    t_ns: i as i64 * 5_000_000,
                    gyro: [0.0; 3],
                    accel: [0.0; 3],
                })
                .collect(),
            ground_truth: Some(
                (0..n)
                    .map(|k| StampedPose {
                        t_ns: t(k),
                        pose: Default::default(),
                    })
                    .collect(),
            ),
            issues: Vec::new(),
            first_row_stamps: false,
            imu_calib: None,
        }
    }

    #[test]
    fn a_frame_range_keeps_its_frames_times_truth_and_imu_around_them() {
        let mut ds = dataset(100);
        ds.select_frames("40..60".parse().expect("range"))
            .expect("select");
        assert_eq!(ds.frames.len(), 20);
        assert_eq!(ds.frames[0].path, std::path::PathBuf::from("40.png"));
        assert_eq!(ds.frames[0].t_ns, 2_000_000_000, "the dataset's own times");
        let gt = ds.ground_truth.as_ref().expect("truth");
        assert_eq!((gt.len(), gt[0].t_ns), (20, 2_000_000_000));
        let (a, b) = (ds.imu[0].t_ns, ds.imu[ds.imu.len() - 1].t_ns);
        assert_eq!(
            (a, b),
            (1_000_000_000, 3_950_000_000),
            "1 s either side, to the end"
        );
        let mut ds = dataset(10);
        ds.select_frames("5..".parse().expect("range"))
            .expect("to the end");
        assert_eq!(ds.frames.len(), 5);
        let mut ds = dataset(10);
        let e = ds.select_frames("12..20".parse().expect("range"));
        assert!(e
            .expect_err("past the end")
            .to_string()
            .contains("10 frames"));
    }
}
