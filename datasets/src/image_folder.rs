//! Image-folder reader, for sequences that come as numbered images and a calibration only
//! (e.g. the VAMR course's hand-held checkerboard sequence):
//!
//! - `images/`: the frames, JPEG or PNG, in file-name order (frame `k` = the `k`-th, 0-based);
//! - `K.txt`: the 3x3 camera matrix (9 numbers, row by row; `fx 0 cx  0 fy cy  0 0 1`);
//! - `D.txt` (optional): distortion, OpenCV order `k1 k2 [p1 p2 [k3]]`, on normalised
//!   coordinates (2 numbers: radial only);
//! - ground truth (optional): `groundtruth_tum.txt` (TUM `index tx ty tz qx qy qz qw`,
//!   camera to world, the 0-based frame index in the time column) or else `poses.txt`
//!   (per frame `wx wy wz tx ty tz`: axis-angle and translation of `T_CW`, world to camera).
//!
//! No timestamps: frame `k` is at `k / fps` seconds ([`DEFAULT_FPS`] unless `shoal run
//! --fps` says otherwise), and its ground truth takes the same time. Global shutter, no IMU.

use std::path::{Path, PathBuf};

use nalgebra::{Isometry3, Translation3, UnitQuaternion, Vector3};

use crate::image_io::image_size;
use crate::text::{data_lines, fields, issue, parse_f64s, read_text};
use crate::trajectory::read_tum;
use crate::{
    CameraCalib, Dataset, DatasetError, DatasetKind, FrameRecord, InputIssue, IssueKind,
    PinholeRadtan, StampedPose,
};

/// Frame rate given to an index-only sequence when none is set (`--fps`), Hz.
pub const DEFAULT_FPS: f64 = 20.0;

/// True when `dir` looks like an image folder (`images/` and `K.txt`).
pub fn is_image_folder(dir: &Path) -> bool {
    dir.join("images").is_dir() && dir.join("K.txt").is_file()
}

/// Opens an image folder, frame `k` at `k / fps` s (`fps`: [`DEFAULT_FPS`] when `None`).
pub fn read(dir: &Path, fps: Option<f64>) -> Result<Dataset, DatasetError> {
    let fps = fps.unwrap_or(DEFAULT_FPS);
    if !(fps.is_finite() && fps > 0.0) {
        return Err(DatasetError::InvalidConfig {
            detail: format!("--fps {fps}: a frame rate must be positive"),
        });
    }
    let images = image_files(&dir.join("images"))?;
    let t_of = |k: usize| (k as f64 * 1e9 / fps).round() as i64;
    let frames: Vec<FrameRecord> = images
        .iter()
        .enumerate()
        .map(|(k, path)| FrameRecord {
            t_ns: t_of(k),
            path: path.clone(),
            exposure_ns: 0,
            readout_ns: 0,
            source: Default::default(),
        })
        .collect();
    let (width, height) = match frames.first() {
        Some(f) => image_size(&f.path)?,
        None => (0, 0),
    };
    let mut model = read_k(&dir.join("K.txt"), width, height)?;
    let d_path = dir.join("D.txt");
    if d_path.is_file() {
        read_d(&d_path, &mut model)?;
    }
    let mut issues = Vec::new();
    let ground_truth = read_ground_truth(dir, frames.len(), &t_of, &mut issues)?;
    Ok(Dataset {
        kind: DatasetKind::ImageFolder,
        root: dir.into(),
        camera: CameraCalib {
            model,
            t_bs: Isometry3::identity(),
            t_bs_given: false,
            readout_ns: 0,
            time_offset_ns: 0,
            rate_hz: fps,
        },
        frames,
        imu: Vec::new(),
        ground_truth,
        issues,
        first_row_stamps: false,
        imu_calib: None,
    })
}

/// The JPEG and PNG files of `dir`, sorted by name.
fn image_files(dir: &Path) -> Result<Vec<PathBuf>, DatasetError> {
    let entries = std::fs::read_dir(dir).map_err(|source| DatasetError::Io {
        path: dir.into(),
        source,
    })?;
    let mut files: Vec<PathBuf> = entries
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| {
            p.extension()
                .and_then(|x| x.to_str())
                .is_some_and(|x| matches!(x.to_ascii_lowercase().as_str(), "jpg" | "jpeg" | "png"))
        })
        .collect();
    files.sort();
    if files.is_empty() {
        return Err(DatasetError::NotFound {
            path: dir.into(),
            what: "JPEG or PNG images".into(),
        });
    }
    Ok(files)
}

/// All numbers of a small text file, with the file named in errors.
fn numbers(path: &Path, what: &str) -> Result<Vec<f64>, DatasetError> {
    let text = read_text(path, what)?;
    let mut out = Vec::new();
    for (line, l) in data_lines(&text) {
        let v = parse_f64s(&fields(l, l.contains(','))).ok_or_else(|| DatasetError::Parse {
            path: path.into(),
            line,
            detail: format!("expected numbers, got `{l}`"),
        })?;
        out.extend(v);
    }
    Ok(out)
}

/// `K.txt`: the camera matrix.
fn read_k(path: &Path, width: u32, height: u32) -> Result<PinholeRadtan, DatasetError> {
    let k = numbers(path, "camera matrix K.txt")?;
    let bad = |detail: String| DatasetError::Parse {
        path: path.into(),
        line: 0,
        detail,
    };
    if k.len() != 9 {
        return Err(bad(format!(
            "a 3x3 matrix needs 9 numbers, found {}",
            k.len()
        )));
    }
    let (fx, cx, fy, cy) = (k[0], k[2], k[4], k[5]);
    if !(fx > 0.0 && fy > 0.0 && k[8] == 1.0 && k[3] == 0.0 && k[6] == 0.0 && k[7] == 0.0) {
        return Err(bad(format!(
            "not a camera matrix `fx s cx 0 fy cy 0 0 1` with fx, fy > 0: {k:?}"
        )));
    }
    Ok(PinholeRadtan::pinhole(width, height, fx, fy, cx, cy))
}

/// `D.txt`: `k1 k2 [p1 p2 [k3]]` into `model`.
fn read_d(path: &Path, model: &mut PinholeRadtan) -> Result<(), DatasetError> {
    let d = numbers(path, "distortion D.txt")?;
    let at = |i: usize| d.get(i).copied().unwrap_or(0.0);
    if !matches!(d.len(), 2 | 4 | 5) {
        return Err(DatasetError::Parse {
            path: path.into(),
            line: 0,
            detail: format!("expected `k1 k2 [p1 p2 [k3]]`, found {} numbers", d.len()),
        });
    }
    (model.k1, model.k2, model.p1, model.p2, model.k3) = (at(0), at(1), at(2), at(3), at(4));
    Ok(())
}

/// The ground truth, one pose per frame that has one, at the frame's time.
fn read_ground_truth(
    dir: &Path,
    n_frames: usize,
    t_of: &dyn Fn(usize) -> i64,
    issues: &mut Vec<InputIssue>,
) -> Result<Option<Vec<StampedPose>>, DatasetError> {
    let tum = dir.join("groundtruth_tum.txt");
    let by_index: Vec<(usize, Isometry3<f64>)> = if tum.is_file() {
        let traj = read_tum(&tum)?;
        issues.extend(traj.issues);
        traj.poses
            .iter()
            .filter(|p| p.t_ns % 1_000_000_000 == 0 && p.t_ns >= 0)
            .map(|p| ((p.t_ns / 1_000_000_000) as usize, p.pose))
            .collect()
    } else if dir.join("poses.txt").is_file() {
        read_axis_angle_poses(&dir.join("poses.txt"), issues)?
    } else {
        return Ok(None);
    };
    Ok(Some(
        by_index
            .into_iter()
            .filter(|(k, _)| *k < n_frames)
            .map(|(k, pose)| StampedPose {
                t_ns: t_of(k),
                pose,
            })
            .collect(),
    ))
}

/// `poses.txt`: line `k` is frame `k`'s `wx wy wz tx ty tz` of `T_CW`; returns `T_WC`.
fn read_axis_angle_poses(
    path: &Path,
    issues: &mut Vec<InputIssue>,
) -> Result<Vec<(usize, Isometry3<f64>)>, DatasetError> {
    let text = read_text(path, "poses.txt")?;
    let mut out = Vec::new();
    for (k, (line, l)) in data_lines(&text).enumerate() {
        match parse_f64s(&fields(l, false)).filter(|v| v.len() == 6) {
            Some(v) => {
                let r = UnitQuaternion::from_scaled_axis(Vector3::new(v[0], v[1], v[2]));
                let t_cw = Isometry3::from_parts(Translation3::new(v[3], v[4], v[5]), r);
                out.push((k, t_cw.inverse()));
            }
            None => issues.push(issue(
                path,
                line,
                IssueKind::MalformedLine,
                format!("expected `wx wy wz tx ty tz`, got `{l}`; frame {k} has no ground truth"),
            )),
        }
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn folder(k: &str, d: Option<&str>, gt: &[(&str, &str)]) -> tempfile::TempDir {
        let dir = tempfile::tempdir().expect("tmp");
        let images = dir.path().join("images");
        std::fs::create_dir(&images).expect("images");
        for name in ["img_0002.png", "img_0001.png", "img_0003.png", "notes.txt"] {
            let img = image::GrayImage::from_pixel(8, 6, image::Luma([7u8]));
            if name.ends_with(".png") {
                img.save(images.join(name)).expect("png");
            } else {
                std::fs::write(images.join(name), "x").expect("txt");
            }
        }
        std::fs::write(dir.path().join("K.txt"), k).expect("K");
        if let Some(d) = d {
            std::fs::write(dir.path().join("D.txt"), d).expect("D");
        }
        for (name, text) in gt {
            std::fs::write(dir.path().join(name), text).expect("gt");
        }
        dir
    }

    const K: &str = "420.5 0 355.2\n0 420.6 250.3\n0 0 1\n";

    #[test]
    fn frames_in_name_order_at_index_over_fps_with_k_d_and_tum_truth() {
        let gt =
            "# index tx ty tz qx qy qz qw\n0 1 2 3 0 0 0 1\n2 4 5 6 0 0 0 1\n9 0 0 0 0 0 0 1\n";
        let dir = folder(K, Some("-0.3 0.08\n"), &[("groundtruth_tum.txt", gt)]);
        let ds = read(dir.path(), Some(25.0)).expect("read");
        assert_eq!(ds.kind, DatasetKind::ImageFolder);
        let names: Vec<_> = ds
            .frames
            .iter()
            .map(|f| f.path.file_name().unwrap().to_str().unwrap().to_string())
            .collect();
        assert_eq!(names, ["img_0001.png", "img_0002.png", "img_0003.png"]);
        let times: Vec<i64> = ds.frames.iter().map(|f| f.t_ns).collect();
        assert_eq!(times, [0, 40_000_000, 80_000_000]);
        let m = &ds.camera.model;
        assert_eq!(
            (m.width, m.height, m.fx, m.fy, m.cx, m.cy),
            (8, 6, 420.5, 420.6, 355.2, 250.3)
        );
        assert_eq!((m.k1, m.k2, m.p1, m.p2, m.k3), (-0.3, 0.08, 0.0, 0.0, 0.0));
        assert_eq!(ds.camera.rate_hz, 25.0);
        let gt = ds.ground_truth.expect("truth");
        // Index 9 has no frame: dropped.
        assert_eq!(gt.len(), 2);
        assert_eq!(gt[1].t_ns, 80_000_000);
        assert_eq!(gt[1].pose.translation.vector, Vector3::new(4.0, 5.0, 6.0));
        assert_eq!(
            read(dir.path(), None).expect("read").frames[1].t_ns,
            50_000_000
        );
    }

    #[test]
    fn axis_angle_poses_are_world_to_camera_and_bad_lines_are_counted() {
        let poses = "0 0 1.5707963267948966 1 0 0\nnot a pose\n0 0 0 0 0 2\n";
        let dir = folder(K, None, &[("poses.txt", poses)]);
        let ds = read(dir.path(), None).expect("read");
        let gt = ds.ground_truth.expect("truth");
        assert_eq!(gt.len(), 2);
        // T_CW = (R_z(90°), (1, 0, 0)): the camera centre is -R^T t = (0, 1, 0).
        let c = gt[0].pose.translation.vector;
        assert!((c - Vector3::new(0.0, 1.0, 0.0)).norm() < 1e-12, "{c}");
        assert_eq!(gt[1].t_ns, 100_000_000, "line 2 is frame 2");
        assert_eq!(ds.issues.len(), 1);
        assert_eq!(ds.issues[0].kind, IssueKind::MalformedLine);
    }

    #[test]
    fn bad_calibration_and_rate_are_refused_naming_the_file() {
        let dir = folder("1 2 3\n", None, &[]);
        let e = read(dir.path(), None).expect_err("K").to_string();
        assert!(e.contains("K.txt") && e.contains("9 numbers"), "{e}");
        let dir = folder(K, Some("1 2 3\n"), &[]);
        let e = read(dir.path(), None).expect_err("D").to_string();
        assert!(e.contains("D.txt") && e.contains("k1 k2"), "{e}");
        let e = read(dir.path(), Some(0.0)).expect_err("fps").to_string();
        assert!(e.contains("fps"), "{e}");
    }
}
