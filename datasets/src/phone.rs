//! Phone logger reader (an Android camera + IMU logger; e.g. `phone_honorv10`):
//! - `movie_metadata.csv`: a header row, then one row per video frame with (matched by column
//!   name) `Timestamp[nanosec]`, `fx[px]`, `fy[px]`, `Exposure time[nanosec]`,
//!   `Frame readout time[nanosec]` (other columns are ignored);
//! - `frames/NNNN.png`: the decoded video frames, frame k (1-based) = data row k;
//! - `gyro_accel.csv`: `Timestamp[nanosec],gx,gy,gz,ax,ay,az[,Unix time]`, same clock.
//!
//! Time stamps: Android's `SENSOR_TIMESTAMP` is the start of exposure of the first row. Row v
//! starts its exposure at `t + v t_r / N` and is exposed for `e`, so the middle row
//! (v = N/2, seed eq. 2.61-2.63) at the middle of its exposure is at
//! `t_mid = t + t_r / 2 + e / 2`, which is what [`crate::FrameRecord::t_ns`] holds.
//! The camera and IMU share CLOCK_BOOTTIME, so t_d = 0.
//!
//! Calibration: the metadata gives only the focal length, so the principal point is the image
//! centre `(w/2, h/2)` and there is no distortion; the image size is read from the first
//! frame's PNG header.

use std::path::{Path, PathBuf};

use nalgebra::Isometry3;

use crate::euroc::read_imu_csv;
use crate::image_io::image_size;
use crate::text::{data_lines, fields, is_header, issue, parse_i64, read_text, Monotonic};
use crate::{
    CameraCalib, Dataset, DatasetError, DatasetKind, FrameRecord, IssueKind, PinholeRadtan,
};

/// True when `dir` has a `movie_metadata.csv`.
pub fn is_phone(dir: &Path) -> bool {
    dir.join("movie_metadata.csv").is_file()
}

/// Column index by name, ignoring the `[unit]` suffix and case.
fn column(header: &[&str], name: &str) -> Option<usize> {
    header.iter().position(|h| {
        h.split('[')
            .next()
            .unwrap_or("")
            .trim()
            .eq_ignore_ascii_case(name)
    })
}

/// The number of digits of the frame file names (e.g. 4 for `0001.png`), from the folder.
fn frame_name_width(frames_dir: &Path) -> usize {
    let Ok(entries) = std::fs::read_dir(frames_dir) else {
        return 4;
    };
    entries
        .filter_map(|e| e.ok())
        .filter_map(|e| {
            let name = e.file_name().to_str()?.to_string();
            let stem = name.strip_suffix(".png")?;
            (!stem.is_empty() && stem.bytes().all(|b| b.is_ascii_digit())).then_some(stem.len())
        })
        .min()
        .unwrap_or(4)
}

/// Opens a phone-logger folder.
pub fn read(dir: &Path) -> Result<Dataset, DatasetError> {
    if !dir.is_dir() {
        return Err(DatasetError::NotFound {
            path: dir.into(),
            what: "phone dataset folder".into(),
        });
    }
    let meta = dir.join("movie_metadata.csv");
    let text = read_text(&meta, "phone movie_metadata.csv")?;
    let mut lines = data_lines(&text).peekable();
    let header: Vec<&str> = match lines.peek() {
        Some((_, l)) if is_header(l) => fields(l, true),
        _ => {
            return Err(DatasetError::Parse {
                path: meta,
                line: 1,
                detail: "missing the header row".into(),
            });
        }
    };
    let header_line = lines.next().map(|(n, _)| n).unwrap_or(1);
    let col = |name: &str| column(&header, name);
    let (Some(c_t), Some(c_fx)) = (col("Timestamp"), col("fx")) else {
        return Err(DatasetError::Parse {
            path: meta,
            line: header_line,
            detail: "header needs `Timestamp[nanosec]` and `fx[px]` columns".into(),
        });
    };
    let (c_fy, c_exp, c_ro) = (col("fy"), col("Exposure time"), col("Frame readout time"));

    let frames_dir = dir.join("frames");
    if !frames_dir.is_dir() {
        return Err(DatasetError::NotFound {
            path: frames_dir,
            what: "phone frames folder".into(),
        });
    }
    let width = frame_name_width(&frames_dir);
    let mut issues = Vec::new();
    let mut mono = Monotonic::default();
    let mut frames = Vec::new();
    let mut focal: Option<(f64, f64)> = None;
    for (k, (line, l)) in lines.enumerate() {
        let f = fields(l, true);
        let get_i = |c: Option<usize>| c.map(|c| f.get(c).and_then(|s| parse_i64(s)));
        let fx = f
            .get(c_fx)
            .and_then(|s| s.parse::<f64>().ok())
            .filter(|v| *v > 0.0 && v.is_finite());
        let fy = match c_fy {
            Some(c) => f
                .get(c)
                .and_then(|s| s.parse::<f64>().ok())
                .filter(|v| *v > 0.0 && v.is_finite()),
            None => fx,
        };
        let parsed = (|| {
            let t = f.get(c_t).and_then(|s| parse_i64(s))?;
            let exposure = get_i(c_exp).unwrap_or(Some(0)).filter(|v| *v >= 0)?;
            let readout = get_i(c_ro).unwrap_or(Some(0)).filter(|v| *v >= 0)?;
            let t_mid = t.checked_add(exposure / 2)?.checked_add(readout / 2)?;
            Some((t_mid, exposure, readout, fx?, fy?))
        })();
        let Some((t_ns, exposure_ns, readout_ns, fx, fy)) = parsed else {
            issues.push(issue(
                &meta,
                line,
                IssueKind::MalformedLine,
                format!("cannot parse frame row `{l}`"),
            ));
            continue;
        };
        if !mono.accept(t_ns, &meta, line, &mut issues) {
            continue;
        }
        let path: PathBuf = frames_dir.join(format!("{:0width$}.png", k + 1));
        if !path.is_file() {
            issues.push(issue(
                &meta,
                line,
                IssueKind::MissingImage,
                format!("{} does not exist; frame dropped", path.display()),
            ));
            continue;
        }
        focal.get_or_insert((fx, fy));
        frames.push(FrameRecord {
            t_ns,
            path,
            exposure_ns,
            readout_ns,
            source: crate::FrameSource::File,
        });
    }

    let (w, h) = match frames.first() {
        Some(f) => image_size(&f.path)?,
        None => (0, 0),
    };
    let (fx, fy) = focal.unwrap_or((1.0, 1.0));
    let rate_hz = match (frames.first(), frames.last()) {
        (Some(a), Some(b)) if b.t_ns > a.t_ns => {
            (frames.len() - 1) as f64 / ((b.t_ns - a.t_ns) as f64 * 1e-9)
        }
        _ => 0.0,
    };
    let camera = CameraCalib {
        model: PinholeRadtan::pinhole(w, h, fx, fy, f64::from(w) / 2.0, f64::from(h) / 2.0),
        t_bs: android_rear_camera_t_bs(),
        t_bs_given: false,
        readout_ns: frames.first().map_or(0, |f| f.readout_ns),
        time_offset_ns: 0,
        rate_hz,
    };
    let imu_csv = dir.join("gyro_accel.csv");
    let imu = if imu_csv.is_file() {
        read_imu_csv(&imu_csv, &mut issues)?
    } else {
        issues.push(issue(
            &imu_csv,
            0,
            IssueKind::MissingFile,
            "no IMU data in this dataset",
        ));
        Vec::new()
    };
    Ok(Dataset {
        kind: DatasetKind::Phone,
        root: dir.into(),
        camera,
        frames,
        imu,
        ground_truth: None,
        issues,
        first_row_stamps: false,
        imu_calib: None,
    })
}

/// The camera-IMU transform a phone's axis conventions imply, not a calibration (hence
/// `t_bs_given = false`): Android's sensor axes (x right, y up, z out of the screen, in the
/// natural portrait orientation) and the rear camera's (x right, y down in a portrait image,
/// z looking out of the back): `R_bc = diag(1, -1, -1)`, a half turn about x; the lever arm
/// (a few cm) unknown, zero. Only orientations of frames vision does not pose use it (no
/// inertial initialisation without given extrinsics). Unverified on the `phone_honorv10`
/// clip: it turns 0.15° per 0.1 s, too little for `benches/scripts/phone_axes.py` to tell
/// the axis candidates apart.
pub fn android_rear_camera_t_bs() -> Isometry3<f64> {
    Isometry3::from_parts(
        nalgebra::Translation3::identity(),
        nalgebra::UnitQuaternion::from_axis_angle(
            &nalgebra::Vector3::x_axis(),
            std::f64::consts::PI,
        ),
    )
}
