//! Calibration recordings given as AprilGrid detections (issue 18): the layout of
//! `../shared/data/euroc_imu_april` (yac's test data from EuRoC's camera-IMU calibration
//! sequence): `cam0/<t_ns>.csv` (one file per frame, one line per detected corner),
//! `imu0.csv` (EuRoC's `t, w xyz, a xyz`) and `config.yaml` (starting intrinsics, IMU noise).
//!
//! A corner keeps its `(tag_id, corner_idx)` across frames, so each corner is a feature
//! track with perfect data association; the calibration filter uses it like a natural
//! feature of unknown position. Its position on the target is read too, only for checks
//! (never for the filter, issue 18). The stamps are the camera's (a global shutter: the
//! middle row's time is the stamp). Malformed lines and files are skipped and recorded as
//! [`InputIssue`]s (file and line), like every reader's.
use std::path::{Path, PathBuf};

use serde::Deserialize;
use slam_core::imu::ImuNoise;

use crate::text::{data_lines, fields, issue, parse_f64s, parse_i64, read_text};
use crate::{DatasetError, ImuSample, InputIssue, IssueKind, PinholeRadtan};

pub use slam_core::ids::TrackId;

/// One detected corner in one frame.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TrackObservation {
    /// Its track (`tag_id · 4 + corner_idx`).
    pub track: TrackId,
    /// Pixel position (distorted), `[u, v]`.
    pub uv: [f64; 2],
    /// Its position on the target, m (for checks only).
    pub target_m: [f64; 3],
}

/// The corners of one frame.
#[derive(Debug, Clone, PartialEq)]
pub struct TrackFrame {
    /// The frame's stamp, ns (camera clock).
    pub t_ns: i64,
    /// Its corners.
    pub observations: Vec<TrackObservation>,
}

/// A recording of feature tracks and IMU samples.
#[derive(Debug, Clone)]
pub struct TrackDataset {
    /// The folder read.
    pub root: PathBuf,
    /// Starting camera model of `config.yaml`.
    pub camera: PinholeRadtan,
    /// IMU noise of `config.yaml`.
    pub noise: ImuNoise,
    /// IMU rate of `config.yaml`, Hz.
    pub imu_rate_hz: f64,
    /// Frames in time order (frames without a corner included).
    pub frames: Vec<TrackFrame>,
    /// IMU samples in time order.
    pub imu: Vec<ImuSample>,
    /// Problems met and skipped.
    pub issues: Vec<InputIssue>,
}

#[derive(Deserialize)]
struct Config {
    imu0: ImuConfig,
    cam0: CamConfig,
}

#[derive(Deserialize)]
struct ImuConfig {
    rate: f64,
    sigma_a_c: f64,
    sigma_g_c: f64,
    sigma_aw_c: f64,
    sigma_gw_c: f64,
}

#[derive(Deserialize)]
struct CamConfig {
    resolution: [u32; 2],
    proj_model: String,
    dist_model: String,
    proj_params: [f64; 4],
    dist_params: [f64; 4],
}

/// Whether `root` has this layout (`cam0/` of CSV files, `imu0.csv`, `config.yaml`).
pub fn is_april_layout(root: &Path) -> bool {
    root.join("cam0").is_dir()
        && root.join("imu0.csv").is_file()
        && root.join("config.yaml").is_file()
}

/// Reads the recording at `root` (module docs).
pub fn read(root: &Path) -> Result<TrackDataset, DatasetError> {
    let (camera, noise, imu_rate_hz) = read_config(&root.join("config.yaml"))?;
    let mut issues = Vec::new();
    let imu = crate::euroc::read_imu_csv(&root.join("imu0.csv"), &mut issues)?;
    let mut files = frame_files(&root.join("cam0"))?;
    files.sort();
    let mut frames = Vec::with_capacity(files.len());
    for (t_ns, path) in files {
        match read_frame(&path, t_ns, &mut issues) {
            Ok(f) => frames.push(f),
            Err(e) => issues.push(issue(&path, 0, IssueKind::MalformedLine, e.to_string())),
        }
    }
    Ok(TrackDataset {
        root: root.to_path_buf(),
        camera,
        noise,
        imu_rate_hz,
        frames,
        imu,
        issues,
    })
}

/// Opens the recording as a [`crate::Dataset`] of kind
/// [`crate::DatasetKind::AprilTracks`] for the pipeline: one [`crate::FrameRecord`] per
/// detections file (read again by the camera ingest, [`read_frame`]), the IMU samples, the
/// starting camera model of `config.yaml`, no camera-IMU extrinsics (`T_BS` unknown:
/// `shoal calibrate --init` gives them) and a global shutter.
pub fn open(root: &Path) -> Result<crate::Dataset, DatasetError> {
    let (model, _, _) = read_config(&root.join("config.yaml"))?;
    let mut issues = Vec::new();
    let imu = crate::euroc::read_imu_csv(&root.join("imu0.csv"), &mut issues)?;
    let mut files = frame_files(&root.join("cam0"))?;
    files.sort();
    let frames: Vec<crate::FrameRecord> = files
        .into_iter()
        .map(|(t_ns, path)| crate::FrameRecord {
            t_ns,
            path,
            exposure_ns: 0,
            readout_ns: 0,
            source: crate::FrameSource::File,
        })
        .collect();
    let camera = crate::CameraCalib {
        model,
        t_bs: nalgebra::Isometry3::identity(),
        t_bs_given: false,
        readout_ns: 0,
        time_offset_ns: 0,
        rate_hz: median_rate_hz(&frames),
    };
    Ok(crate::Dataset {
        kind: crate::DatasetKind::AprilTracks,
        root: root.to_path_buf(),
        camera,
        frames,
        imu,
        ground_truth: None,
        issues,
        first_row_stamps: false,
        imu_calib: None,
    })
}

/// The IMU noise of the recording's `config.yaml`.
pub fn read_noise(root: &Path) -> Result<ImuNoise, DatasetError> {
    Ok(read_config(&root.join("config.yaml"))?.1)
}

/// The frame rate from the median spacing of the stamps (0 with fewer than two frames).
fn median_rate_hz(frames: &[crate::FrameRecord]) -> f64 {
    let mut dt: Vec<i64> = frames.windows(2).map(|w| w[1].t_ns - w[0].t_ns).collect();
    dt.sort_unstable();
    match dt.get(dt.len() / 2) {
        Some(&d) if d > 0 => 1e9 / d as f64,
        _ => 0.0,
    }
}

fn read_config(path: &Path) -> Result<(PinholeRadtan, ImuNoise, f64), DatasetError> {
    let bad = |detail: String| DatasetError::Parse {
        path: path.to_path_buf(),
        line: 0,
        detail,
    };
    let text = read_text(path, "AprilGrid config.yaml")?;
    let c: Config = serde_saphyr::from_str(&text).map_err(|e| bad(format!("invalid YAML: {e}")))?;
    let cam = c.cam0;
    if cam.proj_model != "pinhole" || !cam.dist_model.starts_with("radtan") {
        return Err(bad(format!(
            "cam0 is {}/{}: only pinhole/radtan4 is read",
            cam.proj_model, cam.dist_model
        )));
    }
    let [k1, k2, p1, p2] = cam.dist_params;
    let [w, h] = cam.resolution;
    let camera = PinholeRadtan::from_coefficients(w, h, cam.proj_params, [k1, k2, p1, p2, 0.0]);
    let i = c.imu0;
    let noise = ImuNoise {
        gyro_noise_density: i.sigma_g_c,
        accel_noise_density: i.sigma_a_c,
        gyro_bias_rw: i.sigma_gw_c,
        accel_bias_rw: i.sigma_aw_c,
    };
    let ok = [i.rate, i.sigma_g_c, i.sigma_a_c, i.sigma_gw_c, i.sigma_aw_c]
        .iter()
        .all(|v| v.is_finite() && *v >= 0.0);
    if !ok || w == 0 || h == 0 || cam.proj_params.iter().any(|v| !v.is_finite() || *v <= 0.0) {
        return Err(bad(
            "negative, zero or non-finite rate, noise, size or intrinsics".into(),
        ));
    }
    Ok((camera, noise, i.rate))
}

/// The `<t_ns>.csv` files of `dir` with their stamps (other files are ignored).
fn frame_files(dir: &Path) -> Result<Vec<(i64, PathBuf)>, DatasetError> {
    let entries = std::fs::read_dir(dir).map_err(|source| DatasetError::Io {
        path: dir.to_path_buf(),
        source,
    })?;
    Ok(entries
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| p.extension().is_some_and(|x| x == "csv"))
        .filter_map(|p| Some((p.file_stem()?.to_str()?.parse().ok()?, p)))
        .collect())
}

/// One frame's corners: `ts, tag_rows, tag_cols, tag_size, tag_spacing, kp_x, kp_y, p_x,
/// p_y, p_z, tag_id, corner_idx`. A line whose stamp is not the file's is malformed.
/// The corners of the frame stamped `t_ns` in its detections file `path`; malformed lines
/// are skipped and recorded in `issues` (file and line).
pub fn read_frame(
    path: &Path,
    t_ns: i64,
    issues: &mut Vec<InputIssue>,
) -> Result<TrackFrame, DatasetError> {
    let text = read_text(path, "AprilGrid detections")?;
    let mut observations = Vec::new();
    for (line, l) in data_lines(&text) {
        let f = fields(l, true);
        let parsed = (f.len() == 12)
            .then(|| {
                let t = parse_i64(f[0]).filter(|&t| t == t_ns)?;
                let v = parse_f64s(&f[5..10])?;
                let id = f[10].parse::<u32>().ok()?;
                let corner = f[11].parse::<u32>().ok().filter(|&c| c < 4)?;
                Some((t, v, u64::from(id) * 4 + u64::from(corner)))
            })
            .flatten()
            .filter(|(_, v, _)| v.iter().all(|x| x.is_finite()));
        let Some((_, v, track)) = parsed else {
            issues.push(issue(
                path,
                line,
                IssueKind::MalformedLine,
                format!("expected 12 fields with this file's stamp and a corner 0-3, got `{l}`"),
            ));
            continue;
        };
        observations.push(TrackObservation {
            track: TrackId(track),
            uv: [v[0], v[1]],
            target_m: [v[2], v[3], v[4]],
        });
    }
    Ok(TrackFrame { t_ns, observations })
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A small recording in the layout, with a malformed line and a foreign stamp.
    fn write_sample(dir: &Path) {
        std::fs::create_dir_all(dir.join("cam0")).expect("dir");
        std::fs::write(
            dir.join("config.yaml"),
            "settings:\n  verbose: true\nimu0:\n  rate: 200.0\n  sigma_a_c: 0.002\n  \
             sigma_g_c: 1.6968e-04\n  sigma_aw_c: 0.003\n  sigma_gw_c: 1.9393e-05\n  g: 9.81\n\
             cam0:\n  resolution: [752, 480]\n  proj_model: \"pinhole\"\n  dist_model: \"radtan4\"\n  \
             proj_params: [458.654, 457.296, 367.215, 248.375]\n  dist_params: [-0.28, 0.07, 0.0002, 1.7e-05]\n",
        )
        .expect("config");
        std::fs::write(
            dir.join("imu0.csv"),
            "#ts,wx,wy,wz,ax,ay,az\n100,0.1,0.2,0.3,9.3,0.1,0.2\n105,0.1,0.2,0.3,9.3,0.1,0.2\n",
        )
        .expect("imu");
        let head =
            "#ts,tag_rows,tag_cols,tag_size,tag_spacing,kp_x,kp_y,p_x,p_y,p_z,tag_id,corner_idx\n";
        std::fs::write(
            dir.join("cam0/200.csv"),
            format!(
                "{head}200,6,6,0.088,0.3,175.9,336.8,0.0,0.0,0.0,0,0\n\
                 200,6,6,0.088,0.3,213.3,334.5,0.088,0.0,0.0,5,3\n\
                 200,6,6,0.088,0.3,nan,334.5,0.088,0.0,0.0,5,2\n\
                 999,6,6,0.088,0.3,1.0,2.0,0.088,0.0,0.0,5,1\n"
            ),
        )
        .expect("frame");
        std::fs::write(dir.join("cam0/150.csv"), head).expect("empty frame");
        std::fs::write(dir.join("cam0/notes.txt"), "x").expect("other");
    }

    #[test]
    fn detections_become_tracks_and_bad_lines_are_counted() {
        let dir = tempfile::tempdir().expect("tmp");
        write_sample(dir.path());
        assert!(is_april_layout(dir.path()));
        let ds = read(dir.path()).expect("read");
        assert_eq!(ds.camera.width, 752);
        assert!((ds.noise.accel_bias_rw - 0.003).abs() < 1e-12);
        assert_eq!(ds.imu.len(), 2);
        assert_eq!(
            ds.frames.iter().map(|f| f.t_ns).collect::<Vec<_>>(),
            [150, 200]
        );
        let obs = &ds.frames[1].observations;
        assert_eq!(obs.len(), 2);
        assert_eq!((obs[0].track, obs[1].track), (TrackId(0), TrackId(23)));
        assert_eq!(obs[1].uv, [213.3, 334.5]);
        assert_eq!(ds.issues.len(), 2, "{:?}", ds.issues);
        assert!(ds
            .issues
            .iter()
            .all(|i| i.kind == IssueKind::MalformedLine && i.line >= 4));
    }

    /// `datasets::open` finds the layout and gives the pipeline one frame per detections
    /// file, with the starting camera and no extrinsics.
    #[test]
    fn the_layout_opens_as_a_dataset_of_feature_frames() {
        let dir = tempfile::tempdir().expect("tmp");
        write_sample(dir.path());
        let ds = crate::open(dir.path()).expect("open");
        assert_eq!(ds.kind, crate::DatasetKind::AprilTracks);
        assert_eq!(ds.frames.len(), 2);
        assert!(ds.frames[1].path.ends_with("cam0/200.csv"));
        assert!(!ds.camera.t_bs_given);
        assert!((ds.camera.rate_hz - 1e9 / 50.0).abs() < 1e-3);
        assert_eq!(ds.camera.model.width, 752);
        let mut issues = vec![];
        let f = read_frame(&ds.frames[1].path, 200, &mut issues).expect("frame");
        assert_eq!((f.observations.len(), issues.len()), (2, 2));
    }
}
