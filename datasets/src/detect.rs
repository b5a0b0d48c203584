//! Format auto-detection: [`open`] picks the reader from the folder layout.
//!
//! - `mav0/` (or the folder is itself a `mav0` with `cam0/` or `imu0/`) → EuRoC ASL;
//! - `image_0/` + `times.txt` → KITTI odometry;
//! - `movie_metadata.csv` → phone logger.

use std::path::Path;

use crate::{euroc, kitti, phone, Dataset, DatasetError, DatasetKind};

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
    if euroc::mav0_dir(path).is_some() {
        Ok(DatasetKind::Euroc)
    } else if kitti::is_kitti(path) {
        Ok(DatasetKind::Kitti)
    } else if phone::is_phone(path) {
        Ok(DatasetKind::Phone)
    } else {
        Err(DatasetError::UnknownFormat {
            path: path.into(),
            detail: "expected `mav0/` (EuRoC), `image_0/` + `times.txt` (KITTI) or \
                     `movie_metadata.csv` (phone logger)"
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
    }
}
