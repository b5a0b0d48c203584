//! GoPro clips with their GPMF metadata, extracted as in `../shared/data/gopro_karma_rs_imu`
//! (issue 18): `frames/NNNNNN.jpg` (frame index k in file k + 1), `frame_timestamps.csv`
//! (`index, pts_s, picture_type`), `gyro.csv` and `accl.csv` (`time_s, three axes`), all on
//! the MP4 timeline.
//!
//! **IMU axes.** GPMF stores both streams in the order (z, x, y) ("Gyroscope (z,x,y)";
//! "Accelerometer (up/down, right/left, forward/back)"): the body frame here is (x, y, z) =
//! (right/left, forward/back, up/down), i.e. stored columns (1, 2, 0) of both (a cyclic
//! permutation, so right-handed; an accelerometer at rest reads +9.8 on z when the camera
//! is level). The signs are the stream's: the camera-IMU rotation is unknown and is
//! estimated from gyro vs visual rotations, whose fit shows an axis of the wrong sign.
//!
//! **Rates and clocks.** The gyro (~400 Hz) gives the sample times; the accelerometer
//! (~200 Hz) is interpolated linearly to them (gyro samples outside its span are left out).
//! Camera and IMU share the MP4 timeline up to an unknown offset t_d; the frame stamps are
//! taken as middle-row times with t_d = 0 and t_r = 0 until a calibration
//! (`--calib`, `shoal calibrate`) gives them.
//!
//! **Camera.** Unknown intrinsics: the generic guess of issue 18 (focal 0.7 × width,
//! centred principal point, no distortion); `T_BS` unknown (identity, not given).
use std::path::Path;

use nalgebra::Isometry3;

use crate::image_io::image_size;
use crate::text::{data_lines, fields, issue, parse_f64s, read_text, Monotonic};
use crate::{
    CameraCalib, Dataset, DatasetError, DatasetKind, FrameRecord, ImuSample, InputIssue, IssueKind,
    PinholeRadtan,
};

/// Whether `dir` has this layout.
pub fn is_gopro(dir: &Path) -> bool {
    ["frame_timestamps.csv", "gyro.csv", "accl.csv"]
        .iter()
        .all(|f| dir.join(f).is_file())
        && dir.join("frames").is_dir()
}

/// Reads the clip at `dir` (module docs).
pub fn read(dir: &Path) -> Result<Dataset, DatasetError> {
    let mut issues = Vec::new();
    let frames = read_frames(dir, &mut issues)?;
    let first = frames.first().ok_or_else(|| DatasetError::NotFound {
        path: dir.join("frames"),
        what: "any frame listed in frame_timestamps.csv".into(),
    })?;
    let (w, h) = image_size(&first.path)?;
    let gyro = read_axes(&dir.join("gyro.csv"), &mut issues)?;
    let accl = read_axes(&dir.join("accl.csv"), &mut issues)?;
    let imu = merge(&gyro, &accl);
    let rate_hz = frame_rate(&frames);
    let f = 0.7 * f64::from(w);
    let camera = CameraCalib {
        model: PinholeRadtan::pinhole(w, h, f, f, f64::from(w) / 2.0, f64::from(h) / 2.0),
        t_bs: Isometry3::identity(),
        t_bs_given: false,
        readout_ns: 0,
        time_offset_ns: 0,
        rate_hz,
    };
    Ok(Dataset {
        kind: DatasetKind::GoPro,
        root: dir.to_path_buf(),
        camera,
        frames,
        imu,
        ground_truth: None,
        issues,
        first_row_stamps: false,
        imu_calib: None,
    })
}

/// The frames of `frame_timestamps.csv` whose image exists, in time order.
fn read_frames(dir: &Path, issues: &mut Vec<InputIssue>) -> Result<Vec<FrameRecord>, DatasetError> {
    let path = dir.join("frame_timestamps.csv");
    let text = read_text(&path, "frame_timestamps.csv")?;
    let mut mono = Monotonic::default();
    let mut out = Vec::new();
    for (line, l) in data_lines(&text) {
        let f = fields(l, true);
        let parsed = (f.len() >= 2)
            .then(|| Some((f[0].parse::<usize>().ok()?, f[1].parse::<f64>().ok()?)))
            .flatten()
            .filter(|(_, t)| t.is_finite() && *t >= 0.0);
        let Some((index, pts_s)) = parsed else {
            issues.push(issue(
                &path,
                line,
                IssueKind::MalformedLine,
                format!("expected `index,pts_s,type`, got `{l}`"),
            ));
            continue;
        };
        let image = dir.join("frames").join(format!("{:06}.jpg", index + 1));
        if !image.is_file() {
            issues.push(issue(
                &path,
                line,
                IssueKind::MissingImage,
                format!("{} does not exist", image.display()),
            ));
            continue;
        }
        let t_ns = (pts_s * 1e9).round() as i64;
        if mono.accept(t_ns, &path, line, issues) {
            out.push(FrameRecord {
                t_ns,
                path: image,
                exposure_ns: 0,
                readout_ns: 0,
                source: crate::FrameSource::File,
            });
        }
    }
    Ok(out)
}

/// `(t_ns, [x, y, z])` of a GPMF stream file, reordered from the stored (z, x, y).
fn read_axes(
    path: &Path,
    issues: &mut Vec<InputIssue>,
) -> Result<Vec<(i64, [f64; 3])>, DatasetError> {
    let text = read_text(path, "GPMF stream CSV")?;
    let mut mono = Monotonic::default();
    let mut out = Vec::new();
    for (line, l) in data_lines(&text) {
        let f = fields(l, true);
        let Some(v) = (f.len() == 4).then(|| parse_f64s(&f)).flatten() else {
            issues.push(issue(
                path,
                line,
                IssueKind::MalformedLine,
                format!("expected `time_s,a,b,c`, got `{l}`"),
            ));
            continue;
        };
        let t_ns = (v[0] * 1e9).round() as i64;
        if mono.accept(t_ns, path, line, issues) {
            out.push((t_ns, [v[2], v[3], v[1]]));
        }
    }
    Ok(out)
}

/// IMU samples at the gyro's times with the accelerometer interpolated linearly.
fn merge(gyro: &[(i64, [f64; 3])], accl: &[(i64, [f64; 3])]) -> Vec<ImuSample> {
    let mut out = Vec::with_capacity(gyro.len());
    let mut j = 0;
    for &(t_ns, g) in gyro {
        while j + 1 < accl.len() && accl[j + 1].0 < t_ns {
            j += 1;
        }
        let (Some(a), Some(b)) = (accl.get(j), accl.get(j + 1)) else {
            continue;
        };
        if t_ns < a.0 || t_ns > b.0 {
            continue;
        }
        let s = (t_ns - a.0) as f64 / (b.0 - a.0) as f64;
        let accel = std::array::from_fn(|k| a.1[k] + s * (b.1[k] - a.1[k]));
        out.push(ImuSample {
            t_ns,
            gyro: g,
            accel,
        });
    }
    out
}

/// Frames per second from the first and last stamps (0 with fewer than two frames).
fn frame_rate(frames: &[FrameRecord]) -> f64 {
    match (frames.first(), frames.last()) {
        (Some(a), Some(b)) if b.t_ns > a.t_ns => {
            (frames.len() - 1) as f64 * 1e9 / (b.t_ns - a.t_ns) as f64
        }
        _ => 0.0,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn streams_are_reordered_and_merged_at_gyro_times() {
        let gyro = [
            (0, [1.0, 2.0, 3.0]),
            (5, [1.0, 2.0, 3.0]),
            (15, [4.0, 5.0, 6.0]),
            (25, [0.0; 3]),
        ];
        let accl = [
            (2, [0.0, 0.0, 0.0]),
            (12, [10.0, 20.0, 30.0]),
            (22, [10.0, 20.0, 30.0]),
        ];
        let m = merge(&gyro, &accl);
        assert_eq!(m.iter().map(|s| s.t_ns).collect::<Vec<_>>(), [5, 15]);
        assert_eq!(m[0].accel, [3.0, 6.0, 9.0]);
        assert_eq!(m[1].accel, [10.0, 20.0, 30.0]);
        assert_eq!(m[1].gyro, [4.0, 5.0, 6.0]);
    }

    #[test]
    fn a_small_clip_is_read_with_bad_lines_counted() {
        let dir = tempfile::tempdir().expect("tmp");
        let d = dir.path();
        std::fs::create_dir(d.join("frames")).expect("frames");
        let img = image::GrayImage::from_pixel(64, 48, image::Luma([100u8]));
        for k in 1..=2 {
            img.save(d.join(format!("frames/{k:06}.jpg")))
                .expect("jpeg");
        }
        std::fs::write(
            d.join("frame_timestamps.csv"),
            "# h\n0,0.0,I\n1,0.0333,P\n2,0.0667,P\nx,y\n",
        )
        .expect("ts");
        std::fs::write(
            d.join("gyro.csv"),
            "# h\n0.001,0.1,0.2,0.3\n0.004,0.1,0.2,0.3\n0.003,1,1,1\n",
        )
        .expect("gyro");
        std::fs::write(
            d.join("accl.csv"),
            "# h\n0.0,9.8,0.1,0.2\n0.005,9.8,0.1,0.2\n",
        )
        .expect("accl");
        assert!(is_gopro(d));
        let ds = read(d).expect("read");
        assert_eq!(ds.frames.len(), 2);
        assert_eq!(ds.frames[1].t_ns, 33_300_000);
        assert_eq!(
            (ds.camera.model.width, ds.camera.model.fx),
            (64, 0.7 * 64.0)
        );
        assert!(!ds.camera.t_bs_given);
        assert_eq!(ds.imu.len(), 2);
        assert_eq!(ds.imu[0].gyro, [0.2, 0.3, 0.1]);
        assert_eq!(ds.imu[0].accel, [0.1, 0.2, 9.8]);
        let kinds: Vec<_> = ds.issues.iter().map(|i| i.kind).collect();
        assert_eq!(
            kinds,
            [
                IssueKind::MissingImage,
                IssueKind::MalformedLine,
                IssueKind::NonMonotonic
            ]
        );
        let (w, h, px) = crate::decode_gray(&ds.frames[0].path).expect("decode jpeg");
        assert_eq!((w, h), (64, 48));
        assert!(px.iter().all(|&p| (98..=102).contains(&p)));
    }
}
