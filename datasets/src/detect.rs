//! Format auto-detection: [`open`] picks the reader from the folder layout.
//!
//! - `mav0/` (or the folder is itself a `mav0` with `cam0/` or `imu0/`) → EuRoC ASL;
//! - `image_0/` + `times.txt` → KITTI odometry;
//! - `movie_metadata.csv` → phone logger;
//! - `frame_timestamps.csv` + `gyro.csv` + `accl.csv` + `frames/` → GoPro clip;
//! - `cam0/` + `imu0.csv` + `config.yaml` → AprilGrid detections (feature tracks).

use std::path::Path;

use crate::{april, euroc, gopro, kitti, phone, Dataset, DatasetError, DatasetKind};

/// The kind of dataset in `path`, without reading it. `NotFound` for a missing folder,
/// `UnknownFormat` when no layout matches.
pub fn detect(path: &Path) -> Result<DatasetKind, DatasetError> {
    if !path.exists() {
        return Err(DatasetError::NotFound {
            path: path.into(),
            what: "dataset folder".into(),
        });
    }
    if !path.is_dir() {
        return Err(DatasetError::UnknownFormat {
            path: path.into(),
            detail: "not a folder; a dataset is a folder (EuRoC, KITTI or phone logger)".into(),
        });
    }
    // Before EuRoC: its `cam0/` would pass for a bare `mav0`.
    if april::is_april_layout(path) {
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
                     (AprilGrid detections)"
                .into(),
        })
    }
}

/// Opens the dataset in `path` with the reader its layout calls for.
pub fn open(path: &Path) -> Result<Dataset, DatasetError> {
    match detect(path)? {
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
    let mut ds = open(path)?;
    if let Some(file) = calibration {
        let c = crate::calibration::CalibrationFile::read(file)?;
        c.apply_to(&mut ds).map_err(|detail| DatasetError::Parse {
            path: file.to_path_buf(),
            line: 0,
            detail: format!("does not fit the dataset {}: {detail}", path.display()),
        })?;
    }
    Ok(ds)
}
