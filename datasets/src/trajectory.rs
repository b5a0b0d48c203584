//! Trajectory files: TUM (`t tx ty tz qx qy qz qw`, t in seconds, `#` comments) and KITTI
//! (12 numbers per line: the 3x4 row-major camera-to-world matrix; time stamps from a
//! separate times file, or the line index when there is none).
//!
//! Reading is lenient: a malformed line or a non-monotonic / duplicate stamp is skipped and
//! recorded in [`Trajectory::issues`] (file + 1-based line). TUM stamps are parsed from the
//! decimal text straight to integer ns (no f64 round trip), so `1403715273.262142976` is
//! exact; writing prints `seconds.nnnnnnnnn`, so a write/read round trip is lossless.

use std::fmt::Write as _;
use std::path::Path;

use nalgebra::{Isometry3, Matrix3, Rotation3, Translation3, UnitQuaternion};
use slam_core::geometry::{interpolate_pose_at, pose_from_pq};

use crate::text::{data_lines, fields, issue, parse_f64s, read_text, Monotonic};
use crate::{DatasetError, InputIssue, IssueKind, StampedPose};

/// A trajectory file format.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum TrajectoryFormat {
    /// `t tx ty tz qx qy qz qw` (8 columns).
    Tum,
    /// 3x4 row-major pose matrix (12 columns).
    Kitti,
}

/// A trajectory read from a file.
#[derive(Debug, Clone)]
pub struct Trajectory {
    /// The poses in file order. Without time stamps (KITTI without a times file) `t_ns` is
    /// the 0-based line index of the pose.
    pub poses: Vec<StampedPose>,
    /// False when `t_ns` holds line indices rather than times.
    pub timestamped: bool,
    /// The format the file was read as.
    pub format: TrajectoryFormat,
    /// Lines skipped while reading.
    pub issues: Vec<InputIssue>,
}

/// Parses a time in seconds given as decimal text (optionally with an exponent) to integer ns,
/// rounding half away from zero. Exact for any number of digits: no f64 round trip.
pub fn parse_seconds_ns(text: &str) -> Option<i64> {
    let s = text.trim();
    let (mant, exp) = match s.find(['e', 'E']) {
        Some(i) => (&s[..i], s[i + 1..].parse::<i32>().ok()?),
        None => (s, 0),
    };
    let (neg, mant) = match mant.strip_prefix('-') {
        Some(m) => (true, m),
        None => (false, mant.strip_prefix('+').unwrap_or(mant)),
    };
    let (ip, fp) = mant.split_once('.').unwrap_or((mant, ""));
    if (ip.is_empty() && fp.is_empty()) || !ip.bytes().chain(fp.bytes()).all(|b| b.is_ascii_digit())
    {
        return None;
    }
    let digits = format!("{ip}{fp}");
    let digits = digits.trim_start_matches('0');
    if digits.len() > 36 {
        return None;
    }
    let m: i128 = if digits.is_empty() {
        0
    } else {
        digits.parse().ok()?
    };
    let shift = 9i64 + i64::from(exp) - fp.len() as i64;
    let v = if shift >= 0 {
        m.checked_mul(10i128.checked_pow(u32::try_from(shift).ok()?)?)?
    } else if shift < -38 {
        0
    } else {
        let d = 10i128.pow((-shift) as u32);
        (m + d / 2) / d
    };
    i64::try_from(if neg { -v } else { v }).ok()
}

/// Integer ns shown as seconds with 9 decimals (`-1.500000000`, `12.000000001`), exactly.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Seconds(pub i64);

impl std::fmt::Display for Seconds {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let a = i128::from(self.0).unsigned_abs();
        let sign = if self.0 < 0 { "-" } else { "" };
        write!(f, "{sign}{}.{:09}", a / 1_000_000_000, a % 1_000_000_000)
    }
}

/// Formats integer ns as seconds text with 9 decimals (`-1.500000000`, `12.000000001`).
pub fn format_seconds(t_ns: i64) -> String {
    Seconds(t_ns).to_string()
}

/// Detects the format from the column count of the first data line (8 → TUM, 12 → KITTI).
pub fn detect_format(path: &Path) -> Result<TrajectoryFormat, DatasetError> {
    let text = read_text(path, "trajectory file")?;
    let Some((line, first)) = data_lines(&text).next() else {
        return Err(DatasetError::Parse {
            path: path.into(),
            line: 0,
            detail: "no poses".into(),
        });
    };
    match fields(first, false).len() {
        8 => Ok(TrajectoryFormat::Tum),
        12 => Ok(TrajectoryFormat::Kitti),
        n => Err(DatasetError::Parse {
            path: path.into(),
            line,
            detail: format!("{n} columns: expected 8 (TUM) or 12 (KITTI)"),
        }),
    }
}

/// Reads a trajectory of either format (detected by [`detect_format`]); KITTI files are read
/// without time stamps.
pub fn read_trajectory(path: &Path) -> Result<Trajectory, DatasetError> {
    match detect_format(path)? {
        TrajectoryFormat::Tum => read_tum(path),
        TrajectoryFormat::Kitti => read_kitti(path, None),
    }
}

/// Reads a TUM trajectory file.
pub fn read_tum(path: &Path) -> Result<Trajectory, DatasetError> {
    let text = read_text(path, "TUM trajectory file")?;
    let mut poses = Vec::new();
    let mut issues = Vec::new();
    let mut mono = Monotonic::default();
    for (line, l) in data_lines(&text) {
        let f = fields(l, false);
        let parsed = if f.len() == 8 {
            parse_seconds_ns(f[0])
                .zip(parse_f64s(&f[1..]))
                .and_then(|(t, v)| {
                    pose_from_pq([v[0], v[1], v[2]], [v[6], v[3], v[4], v[5]]).map(|p| (t, p))
                })
        } else {
            None
        };
        let Some((t_ns, pose)) = parsed else {
            issues.push(issue(
                path,
                line,
                IssueKind::MalformedLine,
                format!("expected `t tx ty tz qx qy qz qw`, got `{l}`"),
            ));
            continue;
        };
        if mono.accept(t_ns, path, line, &mut issues) {
            poses.push(StampedPose { t_ns, pose });
        }
    }
    Ok(Trajectory {
        poses,
        timestamped: true,
        format: TrajectoryFormat::Tum,
        issues,
    })
}

/// A pose from 12 row-major numbers of a 3x4 matrix; `None` unless the 3x3 block is a
/// rotation to within 1e-2 (it is re-orthonormalised).
pub fn pose_from_3x4(v: &[f64]) -> Option<Isometry3<f64>> {
    if v.len() != 12 || !v.iter().all(|x| x.is_finite()) {
        return None;
    }
    let m = Matrix3::new(v[0], v[1], v[2], v[4], v[5], v[6], v[8], v[9], v[10]);
    if (m.transpose() * m - Matrix3::identity()).norm() > 1e-2 || m.determinant() <= 0.0 {
        return None;
    }
    let r = Rotation3::from_matrix_eps(&m, 1e-12, 100, Rotation3::identity());
    Some(Isometry3::from_parts(
        Translation3::new(v[3], v[7], v[11]),
        UnitQuaternion::from_rotation_matrix(&r),
    ))
}

/// Reads a times file (one time in seconds per line, KITTI `times.txt`): entry k is the
/// k-th non-empty line, `None` where it is malformed (with an issue recorded).
pub fn read_times(path: &Path) -> Result<(Vec<Option<i64>>, Vec<InputIssue>), DatasetError> {
    let text = read_text(path, "times file")?;
    let mut issues = Vec::new();
    let times = data_lines(&text)
        .map(|(line, l)| {
            let t = parse_seconds_ns(l);
            if t.is_none() {
                issues.push(issue(
                    path,
                    line,
                    IssueKind::MalformedLine,
                    format!("not a time in seconds: `{l}`"),
                ));
            }
            t
        })
        .collect();
    Ok((times, issues))
}

/// Reads a KITTI pose file. With `times`, pose k gets the k-th time of that file (a pose
/// without a valid, increasing time is skipped); without, `t_ns` is the line index k.
pub fn read_kitti(path: &Path, times: Option<&Path>) -> Result<Trajectory, DatasetError> {
    let text = read_text(path, "KITTI pose file")?;
    let (stamps, mut issues) = match times {
        Some(tp) => {
            let (t, i) = read_times(tp)?;
            (Some(t), i)
        }
        None => (None, Vec::new()),
    };
    let mut poses = Vec::new();
    let mut mono = Monotonic::default();
    let mut count = 0usize;
    for (k, (line, l)) in data_lines(&text).enumerate() {
        count = k + 1;
        let Some(pose) = parse_f64s(&fields(l, false))
            .as_deref()
            .and_then(pose_from_3x4)
        else {
            issues.push(issue(
                path,
                line,
                IssueKind::MalformedLine,
                "expected 12 numbers of a 3x4 [R|t] pose",
            ));
            continue;
        };
        let t_ns = match &stamps {
            None => k as i64,
            Some(ts) => match ts.get(k).copied().flatten() {
                Some(t) => t,
                None => {
                    issues.push(issue(
                        path,
                        line,
                        IssueKind::MissingTime,
                        format!("no valid time for pose {k}"),
                    ));
                    continue;
                }
            },
        };
        if mono.accept(t_ns, path, line, &mut issues) {
            poses.push(StampedPose { t_ns, pose });
        }
    }
    if let (Some(ts), Some(tp)) = (&stamps, times) {
        if ts.len() != count {
            issues.push(issue(
                tp,
                0,
                IssueKind::LengthMismatch,
                format!("{} times for {count} poses", ts.len()),
            ));
        }
    }
    Ok(Trajectory {
        poses,
        timestamped: stamps.is_some(),
        format: TrajectoryFormat::Kitti,
        issues,
    })
}

/// How a TUM file prints the seven pose numbers.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum TumDigits {
    /// The shortest text that reads back to the same `f64` (`{}`): lossless.
    Exact,
    /// Nine decimals (`{:.9}`), as the pipeline's outputs.
    Fixed9,
    /// Scientific with 17 digits after the point (`{:.17e}`), as the g2o tools.
    Sci17,
}

/// One TUM row: the time and the pose's translation and rotation quaternion as stored
/// (`[x, y, z, w]`, not renormalised: a wire pose is written as received).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TumRow {
    /// Time, ns.
    pub t_ns: i64,
    /// `[tx, ty, tz]`.
    pub t: [f64; 3],
    /// `[qx, qy, qz, qw]`.
    pub q: [f64; 4],
}

impl TumRow {
    /// The row of pose `pose` at `t_ns`.
    pub fn from_pose(t_ns: i64, pose: &Isometry3<f64>) -> Self {
        let v = pose.translation.vector;
        let q = pose.rotation.quaternion();
        Self {
            t_ns,
            t: [v.x, v.y, v.z],
            q: [q.i, q.j, q.k, q.w],
        }
    }
}

impl From<&StampedPose> for TumRow {
    fn from(p: &StampedPose) -> Self {
        Self::from_pose(p.t_ns, &p.pose)
    }
}

/// Appends the TUM line `stamp tx ty tz qx qy qz qw` and a newline to `out`: `stamp` as it
/// displays (a time as [`Seconds`], or a vertex id), the translation `t` and the quaternion
/// `q_xyzw` as `digits` says. The one TUM line writer of the workspace.
pub fn push_tum_line(
    out: &mut String,
    stamp: impl std::fmt::Display,
    t: &[f64; 3],
    q_xyzw: &[f64; 4],
    digits: TumDigits,
) {
    let _ = write!(out, "{stamp}");
    for v in t.iter().chain(q_xyzw) {
        let _ = match digits {
            TumDigits::Exact => write!(out, " {v}"),
            TumDigits::Fixed9 => write!(out, " {v:.9}"),
            TumDigits::Sci17 => write!(out, " {v:.17e}"),
        };
    }
    out.push('\n');
}

/// The text of a TUM file: the comment line `header` (written as given, e.g. `# t tx ty tz
/// qx qy qz qw`), then a line per row (time in [`Seconds`]).
pub fn tum_text(
    header: Option<&str>,
    rows: impl IntoIterator<Item = TumRow>,
    digits: TumDigits,
) -> String {
    let mut s = String::new();
    if let Some(h) = header {
        s.push_str(h);
        s.push('\n');
    }
    for r in rows {
        push_tum_line(&mut s, Seconds(r.t_ns), &r.t, &r.q, digits);
    }
    s
}

/// Writes a TUM file ([`tum_text`]) atomically: to `<path>.tmp`, then renamed over `path`.
pub fn write_tum_file(
    path: &Path,
    header: Option<&str>,
    rows: impl IntoIterator<Item = TumRow>,
    digits: TumDigits,
) -> std::io::Result<()> {
    let text = tum_text(header, rows, digits);
    let mut tmp = path.as_os_str().to_owned();
    tmp.push(".tmp");
    let tmp = std::path::PathBuf::from(tmp);
    std::fs::write(&tmp, text)?;
    std::fs::rename(&tmp, path)
}

/// One TUM line: `t tx ty tz qx qy qz qw` (t in seconds with 9 decimals, full f64 precision
/// elsewhere), without the newline.
pub fn format_tum_line(p: &StampedPose) -> String {
    let r = TumRow::from(p);
    let mut s = String::new();
    push_tum_line(&mut s, Seconds(r.t_ns), &r.t, &r.q, TumDigits::Exact);
    s.pop();
    s
}

fn write_file(path: &Path, text: &str) -> Result<(), DatasetError> {
    std::fs::write(path, text).map_err(|source| DatasetError::Io {
        path: path.into(),
        source,
    })
}

/// Writes a TUM file (with a `#` header line, lossless numbers, [`write_tum_file`]).
pub fn write_tum(path: &Path, poses: &[StampedPose]) -> Result<(), DatasetError> {
    write_tum_file(
        path,
        Some("# timestamp tx ty tz qx qy qz qw"),
        poses.iter().map(TumRow::from),
        TumDigits::Exact,
    )
    .map_err(|source| DatasetError::Io {
        path: path.into(),
        source,
    })
}

/// Writes a KITTI pose file (no stamps; write them with [`write_times`] if needed).
pub fn write_kitti(path: &Path, poses: &[StampedPose]) -> Result<(), DatasetError> {
    let mut s = String::new();
    for p in poses {
        let r = p.pose.rotation.to_rotation_matrix();
        let t = p.pose.translation.vector;
        for i in 0..3 {
            let sep = if i == 2 { "\n" } else { " " };
            let _ = write!(s, "{} {} {} {}{sep}", r[(i, 0)], r[(i, 1)], r[(i, 2)], t[i]);
        }
    }
    write_file(path, &s)
}

/// Writes a KITTI-style times file (seconds, one per line).
pub fn write_times(path: &Path, poses: &[StampedPose]) -> Result<(), DatasetError> {
    let s: String = poses
        .iter()
        .map(|p| format_seconds(p.t_ns) + "\n")
        .collect();
    write_file(path, &s)
}

/// The pose at `t_ns` interpolated (lerp + slerp) between the two neighbouring samples of a
/// time-sorted trajectory; exact samples are returned as is; `None` outside its time range.
pub fn interpolate_at(traj: &[StampedPose], t_ns: i64) -> Option<Isometry3<f64>> {
    let i = traj.partition_point(|p| p.t_ns < t_ns);
    let b = traj.get(i)?;
    if b.t_ns == t_ns {
        return Some(b.pose);
    }
    let a = traj.get(i.checked_sub(1)?)?;
    Some(interpolate_pose_at(a.t_ns, &a.pose, b.t_ns, &b.pose, t_ns))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn seconds_text_is_exact() {
        assert_eq!(
            parse_seconds_ns("1403715273.262142976"),
            Some(1_403_715_273_262_142_976)
        );
        assert_eq!(parse_seconds_ns("1.038752e-01"), Some(103_875_200));
        assert_eq!(parse_seconds_ns("0.000000e+00"), Some(0));
        assert_eq!(parse_seconds_ns("-1.5"), Some(-1_500_000_000));
        assert_eq!(parse_seconds_ns("2"), Some(2_000_000_000));
        assert_eq!(parse_seconds_ns(".0000000015"), Some(2));
        assert_eq!(parse_seconds_ns("1e-20"), Some(0));
        for bad in ["", "abc", "1.2.3", "1e", "nan", "1e400", "-"] {
            assert_eq!(parse_seconds_ns(bad), None, "{bad}");
        }
        assert_eq!(
            format_seconds(1_403_715_273_262_142_976),
            "1403715273.262142976"
        );
        assert_eq!(format_seconds(-1_500_000_000), "-1.500000000");
        assert_eq!(format_seconds(1_000_000_050_000_001), "1000000.050000001");
        assert_eq!(format_seconds(5), "0.000000005");
    }

    /// The TUM writer prints what the copies it replaced printed, byte for byte.
    #[test]
    fn tum_lines_keep_their_formats() {
        let pose = Isometry3::from_parts(
            Translation3::new(1.25, -0.1, 1e-7),
            UnitQuaternion::from_euler_angles(0.3, -0.2, 2.9),
        );
        let (t, q) = (pose.translation.vector, pose.rotation.quaternion());
        let p = StampedPose {
            t_ns: -1_403_715_273_262_142_976,
            pose,
        };
        let stamp = format_seconds(p.t_ns);
        assert_eq!(
            format_tum_line(&p),
            format!(
                "{stamp} {} {} {} {} {} {} {}",
                t.x, t.y, t.z, q.i, q.j, q.k, q.w
            )
        );
        let r = TumRow::from(&p);
        assert_eq!(
            tum_text(Some("# h"), [r], TumDigits::Fixed9),
            format!(
                "# h\n{stamp} {:.9} {:.9} {:.9} {:.9} {:.9} {:.9} {:.9}\n",
                t.x, t.y, t.z, q.i, q.j, q.k, q.w
            )
        );
        let mut s = String::new();
        push_tum_line(&mut s, 12u64, &r.t, &r.q, TumDigits::Sci17);
        assert_eq!(
            s,
            format!(
                "12 {:.17e} {:.17e} {:.17e} {:.17e} {:.17e} {:.17e} {:.17e}\n",
                t.x, t.y, t.z, q.i, q.j, q.k, q.w
            )
        );
        let dir = std::env::temp_dir().join(format!("shoal_tum_{}", std::process::id()));
        std::fs::create_dir_all(&dir).expect("dir");
        let path = dir.join("t.txt");
        write_tum(&path, &[p]).expect("write");
        assert_eq!(
            std::fs::read_to_string(&path).expect("read"),
            format!(
                "# timestamp tx ty tz qx qy qz qw\n{}\n",
                format_tum_line(&p)
            )
        );
        assert!(!dir.join("t.txt.tmp").exists());
        let back = read_tum(&path).expect("read");
        assert_eq!(back.poses[0].t_ns, p.t_ns);
        let _ = std::fs::remove_dir_all(&dir);
    }

    #[test]
    fn interpolation_inside_only() {
        let p = |t, x| StampedPose {
            t_ns: t,
            pose: Isometry3::translation(x, 0.0, 0.0),
        };
        let traj = [p(10, 0.0), p(20, 1.0)];
        assert_eq!(
            interpolate_at(&traj, 15).map(|q| q.translation.x),
            Some(0.5)
        );
        assert_eq!(
            interpolate_at(&traj, 10).map(|q| q.translation.x),
            Some(0.0)
        );
        assert_eq!(
            interpolate_at(&traj, 20).map(|q| q.translation.x),
            Some(1.0)
        );
        assert!(interpolate_at(&traj, 9).is_none() && interpolate_at(&traj, 21).is_none());
    }
}
