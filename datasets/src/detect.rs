//! Format auto-detection: [`open`] picks the reader from the folder layout.
//!
//! - `mav0/` (or the folder is itself a `mav0` with `cam0/` or `imu0/`) → EuRoC ASL;
//! - `image_0/` + `times.txt` → KITTI odometry;
//! - `movie_metadata.csv` → phone logger;
//! - `frame_timestamps.csv` + `gyro.csv` + `accl.csv` + `frames/` → GoPro clip;
//! - `cam0/` + `imu0.csv` + `config.yaml` → AprilGrid detections (feature tracks);
//! - a file starting with the MCAP magic, or a folder with a rosbag2 `metadata.yaml` →
//!   MCAP / ROS 2 bag ([`crate::mcap_bag`]).

use std::path::{Path, PathBuf};

use crate::{april, euroc, gopro, kitti, mcap_bag, phone, Dataset, DatasetError, DatasetKind};

/// How to open a dataset ([`open_with`]).
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct OpenOptions {
    /// A calibration file to put in place of the dataset's own (`--calib`).
    pub calib: Option<PathBuf>,
    /// The topics of an MCAP recording (`--image-topic`, `--imu-topic`); ignored for the
    /// other formats.
    pub topics: mcap_bag::Topics,
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
    if !path.is_dir() {
        return Err(DatasetError::UnknownFormat {
            path: path.into(),
            detail: "neither an MCAP file nor a folder (EuRoC, KITTI, phone logger, GoPro, \
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
    } else {
        Err(DatasetError::UnknownFormat {
            path: path.into(),
            detail: "expected `mav0/` (EuRoC), `image_0/` + `times.txt` (KITTI), \
                     `movie_metadata.csv` (phone logger) or `frame_timestamps.csv` + \
                     `gyro.csv` + `accl.csv` (GoPro) or `cam0/` + `imu0.csv` + `config.yaml` \
                     (AprilGrid detections) or `metadata.yaml` (rosbag2)"
                .into(),
        })
    }
}

/// Opens the dataset in `path` with the reader its layout calls for.
pub fn open(path: &Path) -> Result<Dataset, DatasetError> {
    open_reader(path, &OpenOptions::default())
}

/// [`open`] with the options' topics (an MCAP recording's).
fn open_reader(path: &Path, options: &OpenOptions) -> Result<Dataset, DatasetError> {
    match detect(path)? {
        DatasetKind::Mcap => mcap_bag::read(path, &options.topics, options.calib.is_some()),
        DatasetKind::Euroc => euroc::read(path),
        DatasetKind::Kitti => kitti::read(path),
        DatasetKind::Phone => phone::read(path),
        DatasetKind::GoPro => gopro::read(path),
        DatasetKind::AprilTracks => april::open(path),
    }
}

/// Opens the dataset in `path` ([`open`]) and, with `calibration`, puts that calibration file
/// in place of the dataset's own ([`crate::calibration::CalibrationFile::apply_to`]: camera
/// model, `T_BS`, `t_r`, and the frames re-stamped with its `t_d`). A calibration that cannot
/// be read or does not fit the dataset is an error naming the file.
pub fn open_calibrated(path: &Path, calibration: Option<&Path>) -> Result<Dataset, DatasetError> {
    open_with(
        path,
        &OpenOptions {
            calib: calibration.map(Path::to_path_buf),
            ..OpenOptions::default()
        },
    )
}

/// Opens the dataset in `path` with `options`: [`open_calibrated`] with an MCAP
/// recording's topics.
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
    Ok(ds)
}
