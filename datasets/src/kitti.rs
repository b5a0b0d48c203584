//! KITTI odometry reader: `image_0/NNNNNN.png` (left gray camera), `times.txt` (seconds, one
//! per frame), `calib.txt` (`P0: fx 0 cx 0 0 fy cy 0 0 0 1 0`, rectified: no distortion) and
//! optional ground truth `poses.txt` (3x4 camera-to-world per frame). The dev-kit layout
//! `dataset/sequences/07/` is supported too: its ground truth is `dataset/poses/07.txt`.
//!
//! Frame k is the k-th non-empty line of `times.txt` and `image_0/{k:06}.png`; pose line k
//! belongs to frame k. Global shutter (readout 0), no IMU. The image size comes from the
//! first frame's PNG header; the rate from the first and last stamps.

use std::path::{Path, PathBuf};

use nalgebra::Isometry3;

use crate::image_io::image_size;
use crate::text::{data_lines, fields, issue, parse_f64s, read_text, Monotonic};
use crate::trajectory::{read_kitti, read_times};
use crate::{
    CameraCalib, Dataset, DatasetError, DatasetKind, FrameRecord, IssueKind, PinholeRadtan,
    StampedPose,
};

/// True when `dir` looks like a KITTI odometry sequence (`image_0/` and `times.txt`).
pub fn is_kitti(dir: &Path) -> bool {
    dir.join("image_0").is_dir() && dir.join("times.txt").is_file()
}

/// Parses `P0` of a KITTI `calib.txt` into `(fx, fy, cx, cy)`.
pub fn read_p0(path: &Path) -> Result<(f64, f64, f64, f64), DatasetError> {
    let text = read_text(path, "KITTI calib.txt")?;
    for (line, l) in data_lines(&text) {
        let Some(rest) = l.strip_prefix("P0:") else {
            continue;
        };
        let p = parse_f64s(&fields(rest, false))
            .filter(|p| p.len() == 12)
            .ok_or_else(|| DatasetError::Parse {
                path: path.into(),
                line,
                detail: "P0 needs 12 numbers".into(),
            })?;
        let (fx, cx, fy, cy) = (p[0], p[2], p[5], p[6]);
        if !(fx > 0.0 && fy > 0.0) {
            return Err(DatasetError::Parse {
                path: path.into(),
                line,
                detail: "P0 has a non-positive focal length".into(),
            });
        }
        return Ok((fx, fy, cx, cy));
    }
    Err(DatasetError::Parse {
        path: path.into(),
        line: 0,
        detail: "no `P0:` line".into(),
    })
}

/// The ground-truth file of a sequence: `poses.txt` inside it, else `../../poses/<name>.txt`.
fn poses_file(dir: &Path) -> Option<PathBuf> {
    let local = dir.join("poses.txt");
    if local.is_file() {
        return Some(local);
    }
    let name = dir.file_name()?.to_str()?;
    let devkit = dir
        .parent()?
        .parent()?
        .join("poses")
        .join(format!("{name}.txt"));
    devkit.is_file().then_some(devkit)
}

/// Opens a KITTI odometry sequence folder.
pub fn read(dir: &Path) -> Result<Dataset, DatasetError> {
    if !dir.is_dir() {
        return Err(DatasetError::NotFound {
            path: dir.into(),
            what: "KITTI sequence folder".into(),
        });
    }
    let image_dir = dir.join("image_0");
    if !image_dir.is_dir() {
        return Err(DatasetError::NotFound {
            path: image_dir,
            what: "KITTI image_0 folder".into(),
        });
    }
    let (fx, fy, cx, cy) = read_p0(&dir.join("calib.txt"))?;
    let times_path = dir.join("times.txt");
    let (times, mut issues) = read_times(&times_path)?;
    let times_text = read_text(&times_path, "KITTI times.txt")?;
    let lines: Vec<usize> = data_lines(&times_text).map(|(n, _)| n).collect();

    let mut mono = Monotonic::default();
    let mut frames = Vec::new();
    let mut frame_index = Vec::new(); // k of each kept frame
    for (k, t) in times.iter().enumerate() {
        let line = lines.get(k).copied().unwrap_or(0);
        let Some(t_ns) = *t else { continue };
        if !mono.accept(t_ns, &times_path, line, &mut issues) {
            continue;
        }
        let path = image_dir.join(format!("{k:06}.png"));
        if !path.is_file() {
            issues.push(issue(
                &times_path,
                line,
                IssueKind::MissingImage,
                format!("{} does not exist; frame dropped", path.display()),
            ));
            continue;
        }
        frames.push(FrameRecord {
            t_ns,
            path,
            exposure_ns: 0,
            readout_ns: 0,
            source: crate::FrameSource::File,
        });
        frame_index.push(k);
    }

    let (width, height) = match frames.first() {
        Some(f) => image_size(&f.path)?,
        None => (0, 0),
    };
    let rate_hz = match (frames.first(), frames.last()) {
        (Some(a), Some(b)) if b.t_ns > a.t_ns => {
            (frames.len() - 1) as f64 / ((b.t_ns - a.t_ns) as f64 * 1e-9)
        }
        _ => 0.0,
    };
    let camera = CameraCalib {
        model: PinholeRadtan::pinhole(width, height, fx, fy, cx, cy),
        t_bs: Isometry3::identity(),
        t_bs_given: false,
        readout_ns: 0,
        time_offset_ns: 0,
        rate_hz,
    };

    let ground_truth = match poses_file(dir) {
        None => None,
        Some(p) => {
            // Read by index (t_ns = pose line index k), then stamp with the frame times.
            let traj = read_kitti(&p, None)?;
            issues.extend(traj.issues);
            let by_k: std::collections::HashMap<i64, Isometry3<f64>> =
                traj.poses.iter().map(|s| (s.t_ns, s.pose)).collect();
            Some(
                frames
                    .iter()
                    .zip(&frame_index)
                    .filter_map(|(f, &k)| {
                        by_k.get(&(k as i64)).map(|pose| StampedPose {
                            t_ns: f.t_ns,
                            pose: *pose,
                        })
                    })
                    .collect(),
            )
        }
    };
    Ok(Dataset {
        kind: DatasetKind::Kitti,
        root: dir.into(),
        camera,
        frames,
        imu: Vec::new(),
        ground_truth,
        issues,
        first_row_stamps: false,
        imu_calib: None,
    })
}
