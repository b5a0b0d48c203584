//! EuRoC ASL reader (also the layout `shoal sim` writes).
//!
//! Layout (`root/mav0/...`, or `root` being the `mav0` folder itself):
//! - `cam0/sensor.yaml`: `T_BS` (4x4 row-major, camera in body frame), `rate_hz`,
//!   `resolution [w, h]`, `intrinsics [fu, fv, cu, cv]`, `distortion_coefficients
//!   [k1, k2, p1, p2(, k3)]` (radial-tangential, seed eq. 2.57-2.60), and the optional keys of
//!   our generator `readout_time_ns` (rolling-shutter t_r, seed eq. 2.61-2.63) and
//!   `time_offset_ns` (camera-IMU offset t_d, added to every frame time). The OpenCV
//!   `%YAML:1.0` directive line is stripped before parsing.
//! - `cam0/data.csv`: `#timestamp [ns],filename`, images in `cam0/data/`.
//! - `imu0/data.csv`: `t [ns], w xyz [rad/s], a xyz [m/s²]`.
//! - `imu0/sensor.yaml` (not needed by [`read`]; [`read_imu_sensor_yaml`]): noise densities,
//!   and from our generator the true `T_g`, `T_s`, `T_a`, initial biases, t_d and t_r.
//! - ground truth, camera-to-world: `groundtruth_cam0.txt` (TUM, camera-to-world, written by
//!   our generator beside `mav0/`) is preferred when present. Its stamps are the frames'
//!   `data.csv` stamps (camera clock), so t_d is added to them as to the frames; the poses
//!   are at the true mid-row capture times. Otherwise the body poses of
//!   `state_groundtruth_estimate0/data.csv` or `gt0/data.csv` (`t, p xyz, q wxyz, ...`) are
//!   mapped to the camera, `T_WC = T_WB T_BS`. Ground truth is sampled at every frame time
//!   (lerp + slerp between the neighbouring samples when stamps differ); frames outside the
//!   ground-truth time range get no entry.
//!
//! Folders without `cam0` (e.g. an IMU + ground-truth excerpt) still open: zero frames, a
//! placeholder calibration (0x0 image, unit focal length, identity `T_BS`), the IMU samples,
//! and the whole ground-truth stream as body poses (T_BS = identity) at its own stamps.
//! A `cam0` folder with no frames likewise keeps the whole stream, mapped to the camera.
//! `imu0` is optional (a `missing_file` issue is recorded); `cam0/data.csv` and
//! `cam0/sensor.yaml` are required when `cam0` exists.

use std::path::{Path, PathBuf};

use nalgebra::{Isometry3, Matrix3, Rotation3, Translation3, UnitQuaternion, Vector3};
use serde::Deserialize;
use slam_core::geometry::pose_from_pq;
use slam_core::imu::{ImuBiases, ImuIntrinsics, ImuNoise};

use crate::sim::GtState;
use crate::text::{
    data_lines, fields, is_header, issue, parse_f64s, parse_i64, read_text, Monotonic,
};
use crate::trajectory::{interpolate_at, read_tum};
use crate::{
    CameraCalib, Dataset, DatasetError, DatasetKind, FrameRecord, ImuSample, InputIssue, IssueKind,
    PinholeRadtan, StampedPose,
};

#[derive(Deserialize)]
struct MatYaml {
    rows: usize,
    cols: usize,
    data: Vec<f64>,
}

#[derive(Deserialize)]
struct SensorYaml {
    #[serde(rename = "T_BS")]
    t_bs: Option<MatYaml>,
    rate_hz: Option<f64>,
    resolution: Vec<u32>,
    intrinsics: Vec<f64>,
    distortion_model: Option<String>,
    distortion_coefficients: Option<Vec<f64>>,
    readout_time_ns: Option<f64>,
    time_offset_ns: Option<f64>,
}

/// The `mav0` folder of a dataset root (or `root` itself when it is the mav0 folder).
pub fn mav0_dir(root: &Path) -> Option<PathBuf> {
    let m = root.join("mav0");
    if m.is_dir() {
        return Some(m);
    }
    let is_mav0 = root.join("cam0").is_dir() || root.join("imu0").is_dir();
    is_mav0.then(|| root.to_path_buf())
}

fn parse_err(path: &Path, detail: impl Into<String>) -> DatasetError {
    DatasetError::Parse {
        path: path.to_path_buf(),
        line: 0,
        detail: detail.into(),
    }
}

/// A placeholder calibration for a dataset without a camera: 0x0 pixels, unit focal length,
/// identity `T_BS`, global shutter, no offset.
pub fn no_camera_calib() -> CameraCalib {
    CameraCalib {
        model: PinholeRadtan::pinhole(0, 0, 1.0, 1.0, 0.0, 0.0),
        t_bs: Isometry3::identity(),
        t_bs_given: false,
        readout_ns: 0,
        time_offset_ns: 0,
        rate_hz: 0.0,
    }
}

/// Parses a `cam0/sensor.yaml`. Missing/invalid resolution or intrinsics, an unsupported
/// distortion model or a `T_BS` that is not a rigid transform are hard errors.
pub fn read_sensor_yaml(path: &Path) -> Result<CameraCalib, DatasetError> {
    let text = strip_yaml_directive(&read_text(path, "camera sensor.yaml")?);
    let y: SensorYaml = serde_saphyr::from_str(&text)
        .map_err(|e| parse_err(path, format!("invalid camera YAML: {e}")))?;
    let [w, h] = y.resolution[..] else {
        return Err(parse_err(path, "`resolution` must be [width, height]"));
    };
    let [fx, fy, cx, cy] = y.intrinsics[..] else {
        return Err(parse_err(path, "`intrinsics` must be [fu, fv, cu, cv]"));
    };
    if !(fx > 0.0
        && fy > 0.0
        && cx.is_finite()
        && cy.is_finite()
        && fx.is_finite()
        && fy.is_finite())
    {
        return Err(parse_err(
            path,
            format!("invalid intrinsics {:?}", y.intrinsics),
        ));
    }
    if let Some(m) = &y.distortion_model {
        if !matches!(
            m.as_str(),
            "radial-tangential" | "radtan" | "plumb_bob" | "none"
        ) {
            return Err(parse_err(
                path,
                format!("unsupported distortion model `{m}`"),
            ));
        }
    }
    let mut model = PinholeRadtan::pinhole(w, h, fx, fy, cx, cy);
    match y.distortion_coefficients.as_deref() {
        None | Some([]) => {}
        Some(&[k1, k2, p1, p2]) => (model.k1, model.k2, model.p1, model.p2) = (k1, k2, p1, p2),
        Some(&[k1, k2, p1, p2, k3]) => {
            (model.k1, model.k2, model.p1, model.p2, model.k3) = (k1, k2, p1, p2, k3)
        }
        Some(d) => {
            return Err(parse_err(
                path,
                format!("expected 4 or 5 distortion coefficients, got {}", d.len()),
            ))
        }
    }
    let t_bs = match &y.t_bs {
        None => Isometry3::identity(),
        Some(m) => isometry_from_rows(m)
            .ok_or_else(|| parse_err(path, "`T_BS` is not a 4x4 rigid transform"))?,
    };
    let ns = |v: Option<f64>, key: &str| -> Result<i64, DatasetError> {
        match v {
            None => Ok(0),
            Some(x) if x.is_finite() && x.abs() < 1e15 => Ok(x.round() as i64),
            Some(x) => Err(parse_err(path, format!("invalid `{key}`: {x}"))),
        }
    };
    let readout_ns = ns(y.readout_time_ns, "readout_time_ns")?;
    if readout_ns < 0 {
        return Err(parse_err(path, "`readout_time_ns` is negative"));
    }
    Ok(CameraCalib {
        model,
        t_bs_given: y.t_bs.is_some(),
        t_bs,
        readout_ns,
        time_offset_ns: ns(y.time_offset_ns, "time_offset_ns")?,
        rate_hz: y
            .rate_hz
            .filter(|r| r.is_finite() && *r > 0.0)
            .unwrap_or(0.0),
    })
}

/// OpenCV writes a `%YAML:1.0` directive that YAML parsers reject; blank it (keeping the
/// line count so parser line numbers still match the file).
fn strip_yaml_directive(text: &str) -> String {
    text.lines()
        .map(|l| {
            if l.trim_start().starts_with("%YAML") {
                ""
            } else {
                l
            }
        })
        .collect::<Vec<_>>()
        .join("\n")
}

#[derive(Deserialize)]
struct ImuSensorYaml {
    rate_hz: Option<f64>,
    gyroscope_noise_density: f64,
    gyroscope_random_walk: f64,
    accelerometer_noise_density: f64,
    accelerometer_random_walk: f64,
    #[serde(rename = "T_g")]
    t_g: Option<MatYaml>,
    #[serde(rename = "T_s")]
    t_s: Option<MatYaml>,
    #[serde(rename = "T_a")]
    t_a: Option<MatYaml>,
    initial_gyro_bias: Option<Vec<f64>>,
    initial_accel_bias: Option<Vec<f64>>,
    time_offset_ns: Option<f64>,
    readout_time_ns: Option<f64>,
}

/// What an `imu0/sensor.yaml` holds: the EuRoC / Kalibr noise model, and the true IMU
/// errors our generator adds (seed eq. 2.53-2.56; `None` when absent, as in real EuRoC).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ImuSensorCalib {
    /// Sample rate, Hz (0 when absent).
    pub rate_hz: f64,
    /// Noise densities and bias random walks.
    pub noise: ImuNoise,
    /// `T_g`, `T_s`, `T_a` (all three keys present; missing ones would be ideal).
    pub intrinsics: Option<ImuIntrinsics>,
    /// Biases at the first sample.
    pub initial_biases: Option<ImuBiases>,
    /// Camera-IMU offset t_d, ns (capture time = camera stamp + t_d).
    pub time_offset_ns: Option<i64>,
    /// Rolling-shutter readout t_r, ns.
    pub readout_ns: Option<i64>,
}

/// Parses an `imu0/sensor.yaml` (EuRoC keys plus our generator's `T_g`, `T_s`, `T_a`,
/// `initial_gyro_bias`, `initial_accel_bias`, `time_offset_ns`, `readout_time_ns`).
/// Negative or non-finite densities, and matrices or vectors of the wrong size, are errors.
pub fn read_imu_sensor_yaml(path: &Path) -> Result<ImuSensorCalib, DatasetError> {
    let text = strip_yaml_directive(&read_text(path, "IMU sensor.yaml")?);
    let y: ImuSensorYaml = serde_saphyr::from_str(&text)
        .map_err(|e| parse_err(path, format!("invalid IMU YAML: {e}")))?;
    let noise = ImuNoise {
        gyro_noise_density: y.gyroscope_noise_density,
        accel_noise_density: y.accelerometer_noise_density,
        gyro_bias_rw: y.gyroscope_random_walk,
        accel_bias_rw: y.accelerometer_random_walk,
    };
    let densities = [
        noise.gyro_noise_density,
        noise.accel_noise_density,
        noise.gyro_bias_rw,
        noise.accel_bias_rw,
    ];
    if densities.iter().any(|d| !(d.is_finite() && *d >= 0.0)) {
        return Err(parse_err(path, "noise densities must be finite and >= 0"));
    }
    let mat3 = |m: &Option<MatYaml>, key: &str| -> Result<Option<Matrix3<f64>>, DatasetError> {
        let Some(m) = m else { return Ok(None) };
        if m.rows != 3 || m.cols != 3 || m.data.len() != 9 || !m.data.iter().all(|v| v.is_finite())
        {
            return Err(parse_err(
                path,
                format!("`{key}` must be a finite 3x3 matrix"),
            ));
        }
        Ok(Some(Matrix3::from_row_slice(&m.data)))
    };
    let vec3 = |v: &Option<Vec<f64>>, key: &str| -> Result<Option<Vector3<f64>>, DatasetError> {
        match v.as_deref() {
            None => Ok(None),
            Some(&[x, y, z]) if [x, y, z].iter().all(|c| c.is_finite()) => {
                Ok(Some(Vector3::new(x, y, z)))
            }
            Some(_) => Err(parse_err(path, format!("`{key}` must be 3 finite numbers"))),
        }
    };
    let (t_g, t_s, t_a) = (
        mat3(&y.t_g, "T_g")?,
        mat3(&y.t_s, "T_s")?,
        mat3(&y.t_a, "T_a")?,
    );
    let intrinsics = (t_g.is_some() || t_s.is_some() || t_a.is_some()).then(|| {
        let ideal = ImuIntrinsics::default();
        ImuIntrinsics {
            t_g: t_g.unwrap_or(ideal.t_g),
            t_s: t_s.unwrap_or(ideal.t_s),
            t_a: t_a.unwrap_or(ideal.t_a),
        }
    });
    let (bg, ba) = (
        vec3(&y.initial_gyro_bias, "initial_gyro_bias")?,
        vec3(&y.initial_accel_bias, "initial_accel_bias")?,
    );
    let initial_biases = (bg.is_some() || ba.is_some()).then(|| ImuBiases {
        gyro: bg.unwrap_or_default(),
        accel: ba.unwrap_or_default(),
    });
    let ns = |v: Option<f64>, key: &str| -> Result<Option<i64>, DatasetError> {
        match v {
            None => Ok(None),
            Some(x) if x.is_finite() && x.abs() < 1e15 => Ok(Some(x.round() as i64)),
            Some(x) => Err(parse_err(path, format!("invalid `{key}`: {x}"))),
        }
    };
    Ok(ImuSensorCalib {
        rate_hz: y
            .rate_hz
            .filter(|r| r.is_finite() && *r > 0.0)
            .unwrap_or(0.0),
        noise,
        intrinsics,
        initial_biases,
        time_offset_ns: ns(y.time_offset_ns, "time_offset_ns")?,
        readout_ns: ns(y.readout_time_ns, "readout_time_ns")?,
    })
}

fn isometry_from_rows(m: &MatYaml) -> Option<Isometry3<f64>> {
    if m.rows != 4 || m.cols != 4 || m.data.len() != 16 || !m.data.iter().all(|v| v.is_finite()) {
        return None;
    }
    let d = &m.data;
    let r = Matrix3::new(d[0], d[1], d[2], d[4], d[5], d[6], d[8], d[9], d[10]);
    if (r.transpose() * r - Matrix3::identity()).norm() > 1e-3 || r.determinant() <= 0.0 {
        return None;
    }
    let rot = Rotation3::from_matrix_eps(&r, 1e-12, 100, Rotation3::identity());
    Some(Isometry3::from_parts(
        Translation3::new(d[3], d[7], d[11]),
        UnitQuaternion::from_rotation_matrix(&rot),
    ))
}

/// Reads `cam0/data.csv`: frames with `t + t_d`, images that exist.
fn read_frames(
    cam0: &Path,
    calib: &CameraCalib,
    issues: &mut Vec<InputIssue>,
) -> Result<Vec<FrameRecord>, DatasetError> {
    let csv = cam0.join("data.csv");
    let text = read_text(&csv, "cam0 frame list (data.csv)")?;
    let mut mono = Monotonic::default();
    let mut frames = Vec::new();
    for (line, l) in data_lines(&text) {
        let f = fields(l, true);
        let t = (f.len() >= 2 && !f[1].is_empty())
            .then(|| parse_i64(f[0]))
            .flatten();
        let Some(t) = t.and_then(|t| t.checked_add(calib.time_offset_ns)) else {
            issues.push(issue(
                &csv,
                line,
                IssueKind::MalformedLine,
                format!("expected `timestamp_ns,filename`, got `{l}`"),
            ));
            continue;
        };
        if !mono.accept(t, &csv, line, issues) {
            continue;
        }
        let path = cam0.join("data").join(f[1]);
        if !path.is_file() {
            issues.push(issue(
                &csv,
                line,
                IssueKind::MissingImage,
                format!("{} does not exist; frame dropped", path.display()),
            ));
            continue;
        }
        frames.push(FrameRecord {
            t_ns: t,
            path,
            exposure_ns: 0,
            readout_ns: calib.readout_ns,
            source: crate::FrameSource::File,
        });
    }
    Ok(frames)
}

/// Reads an IMU CSV: `t [ns], w xyz, a xyz` (EuRoC `imu0/data.csv`, phone `gyro_accel.csv`;
/// an optional named header row and extra trailing columns are accepted).
pub fn read_imu_csv(
    path: &Path,
    issues: &mut Vec<InputIssue>,
) -> Result<Vec<ImuSample>, DatasetError> {
    let text = read_text(path, "IMU data.csv")?;
    let mut mono = Monotonic::default();
    let mut out = Vec::new();
    for (i, (line, l)) in data_lines(&text).enumerate() {
        if i == 0 && is_header(l) {
            continue; // a named header row (phone logger) rather than a `#` comment
        }
        let f = fields(l, true);
        // Extra trailing columns (e.g. the phone's `Unix time`) are ignored.
        let parsed = (f.len() >= 7)
            .then(|| parse_i64(f[0]).zip(parse_f64s(&f[1..7])))
            .flatten();
        let Some((t_ns, v)) = parsed else {
            issues.push(issue(
                path,
                line,
                IssueKind::MalformedLine,
                format!("expected `t,wx,wy,wz,ax,ay,az`, got `{l}`"),
            ));
            continue;
        };
        if mono.accept(t_ns, path, line, issues) {
            out.push(ImuSample {
                t_ns,
                gyro: [v[0], v[1], v[2]],
                accel: [v[3], v[4], v[5]],
            });
        }
    }
    Ok(out)
}

/// Reads an ASL ground-truth CSV (`t, p xyz, q wxyz, ...`): body-to-world poses.
pub fn read_gt_csv(
    path: &Path,
    issues: &mut Vec<InputIssue>,
) -> Result<Vec<StampedPose>, DatasetError> {
    let text = read_text(path, "ground-truth data.csv")?;
    let mut mono = Monotonic::default();
    let mut out = Vec::new();
    for (line, l) in data_lines(&text) {
        let f = fields(l, true);
        let parsed = (f.len() >= 8)
            .then(|| parse_i64(f[0]).zip(parse_f64s(&f[1..8])))
            .flatten()
            .and_then(|(t, v)| {
                pose_from_pq([v[0], v[1], v[2]], [v[3], v[4], v[5], v[6]]).map(|p| (t, p))
            });
        let Some((t_ns, pose)) = parsed else {
            issues.push(issue(
                path,
                line,
                IssueKind::MalformedLine,
                format!("expected `t,px,py,pz,qw,qx,qy,qz,...`, got `{l}`"),
            ));
            continue;
        };
        if mono.accept(t_ns, path, line, issues) {
            out.push(StampedPose { t_ns, pose });
        }
    }
    Ok(out)
}

/// Reads an ASL ground-truth CSV with the full state (`t, p xyz, q wxyz, v xyz, b_g xyz,
/// b_a xyz`: EuRoC `state_groundtruth_estimate0/data.csv`, the `gt0` excerpt, and what
/// `shoal sim` writes) as body states. Lines with fewer than 17 numbers are skipped and
/// recorded as `malformed_line` issues.
pub fn read_gt_states_csv(
    path: &Path,
    issues: &mut Vec<InputIssue>,
) -> Result<Vec<GtState>, DatasetError> {
    let text = read_text(path, "ground-truth data.csv")?;
    let mut mono = Monotonic::default();
    let mut out = Vec::new();
    for (line, l) in data_lines(&text) {
        let f = fields(l, true);
        let parsed = (f.len() >= 17)
            .then(|| parse_i64(f[0]).zip(parse_f64s(&f[1..17])))
            .flatten()
            .and_then(|(t, v)| {
                let pose = pose_from_pq([v[0], v[1], v[2]], [v[3], v[4], v[5], v[6]])?;
                let vec = |k: usize| Vector3::new(v[k], v[k + 1], v[k + 2]);
                Some(GtState {
                    t_ns: t,
                    p_wb: pose.translation.vector,
                    q_wb: pose.rotation,
                    v_w: vec(7),
                    biases: ImuBiases {
                        gyro: vec(10),
                        accel: vec(13),
                    },
                })
            });
        let Some(state) = parsed else {
            issues.push(issue(
                path,
                line,
                IssueKind::MalformedLine,
                format!("expected `t,p xyz,q wxyz,v xyz,b_g xyz,b_a xyz`, got `{l}`"),
            ));
            continue;
        };
        if mono.accept(state.t_ns, path, line, issues) {
            out.push(state);
        }
    }
    Ok(out)
}

/// Camera-to-world ground truth: the generator's TUM file if present, else the ASL CSV
/// mapped through `T_BS`. `None` when the dataset has none.
fn read_ground_truth(
    root: &Path,
    mav0: &Path,
    t_bs: &Isometry3<f64>,
    time_offset_ns: i64,
    issues: &mut Vec<InputIssue>,
) -> Result<Option<Vec<StampedPose>>, DatasetError> {
    let parent = mav0.parent().unwrap_or(root);
    for dir in [root, parent] {
        let tum = dir.join("groundtruth_cam0.txt");
        if tum.is_file() {
            let t = read_tum(&tum)?;
            issues.extend(t.issues);
            // Stamped like `cam0/data.csv` (camera clock): move to the IMU clock with t_d.
            let poses = t
                .poses
                .into_iter()
                .filter_map(|p| {
                    Some(StampedPose {
                        t_ns: p.t_ns.checked_add(time_offset_ns)?,
                        pose: p.pose,
                    })
                })
                .collect();
            return Ok(Some(poses));
        }
    }
    for sub in ["state_groundtruth_estimate0", "gt0"] {
        let csv = mav0.join(sub).join("data.csv");
        if csv.is_file() {
            let body = read_gt_csv(&csv, issues)?;
            let cam = body
                .into_iter()
                .map(|p| StampedPose {
                    t_ns: p.t_ns,
                    pose: p.pose * t_bs,
                })
                .collect();
            return Ok(Some(cam));
        }
    }
    Ok(None)
}

/// Opens an EuRoC ASL dataset (see the module docs).
pub fn read(root: &Path) -> Result<Dataset, DatasetError> {
    if !root.is_dir() {
        return Err(DatasetError::NotFound {
            path: root.into(),
            what: "EuRoC dataset folder".into(),
        });
    }
    let mav0 = mav0_dir(root).ok_or_else(|| DatasetError::NotFound {
        path: root.join("mav0"),
        what: "EuRoC mav0 folder".into(),
    })?;
    let mut issues = Vec::new();
    let cam0 = mav0.join("cam0");
    let (camera, frames) = if cam0.is_dir() {
        let calib = read_sensor_yaml(&cam0.join("sensor.yaml"))?;
        let frames = read_frames(&cam0, &calib, &mut issues)?;
        (calib, frames)
    } else {
        (no_camera_calib(), Vec::new())
    };
    let imu_csv = mav0.join("imu0").join("data.csv");
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
    let gt = read_ground_truth(
        root,
        &mav0,
        &camera.t_bs,
        camera.time_offset_ns,
        &mut issues,
    )?;
    let ground_truth = gt.map(|gt| {
        if frames.is_empty() {
            gt
        } else {
            frames
                .iter()
                .filter_map(|f| {
                    interpolate_at(&gt, f.t_ns).map(|pose| StampedPose { t_ns: f.t_ns, pose })
                })
                .collect()
        }
    });
    Ok(Dataset {
        kind: DatasetKind::Euroc,
        root: root.into(),
        camera,
        frames,
        imu,
        ground_truth,
        issues,
        first_row_stamps: false,
        imu_calib: None,
    })
}
