//! Rolling-shutter row timing, seed eq. 2.61-2.63.
//!
//! Rows are read top to bottom with a constant line delay `d = t_r / N`. The capture time of
//! image row coordinate `v` is
//!
//! ```text
//! t(v) = t_mid + (v - N/2) * t_r / N
//! ```
//!
//! **Convention.** `v` is the continuous pixel coordinate of the row with pixel centres at
//! integer values (the same convention as [`crate::camera::PinholeRadtan::project`]): row
//! index `i` is read at `t(i)`, so the first row is at `t_mid - t_r/2` and the last at
//! `t_mid + t_r/2 - t_r/N`. A projected point with image coordinate `v` is captured at
//! `t(v)` directly, with no half-pixel shift. The synthetic renderer (`datasets::sim`) uses
//! exactly [`row_time_ns`] with `row = i as f64` for row `i`.
//!
//! `t_mid` is the corrected frame time (image stamp + t_d), `t_r = 0` is a global shutter.

use nalgebra::{Vector2, Vector3};

use crate::camera::PinholeRadtan;

/// The order in which a rolling shutter reads the image's lines. Sensors read along their
/// long side (`VI_NOTES.md` §1, seed 2.5): a landscape frame top to bottom, but a phone's
/// portrait frame (720x1280 from a 1280x720 sensor turned by 90°) along image x. The row
/// formulas of this module then apply to the line coordinate of
/// [`ReadoutDirection::line`] (and [`PinholeRadtan::readout_line`]) instead of `v`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
#[cfg_attr(feature = "serde", derive(serde::Serialize, serde::Deserialize))]
pub enum ReadoutDirection {
    /// Rows, first row (`v = 0`) first: the default.
    #[default]
    TopToBottom,
    /// Rows, last row first.
    BottomToTop,
    /// Columns, first column (`u = 0`) first.
    LeftToRight,
    /// Columns, last column first.
    RightToLeft,
}

impl ReadoutDirection {
    /// Every direction.
    pub const ALL: [Self; 4] = [
        Self::TopToBottom,
        Self::BottomToTop,
        Self::LeftToRight,
        Self::RightToLeft,
    ];

    /// The name in calibration and configuration files (`"top-to-bottom"`, ...).
    pub fn name(self) -> &'static str {
        match self {
            Self::TopToBottom => "top-to-bottom",
            Self::BottomToTop => "bottom-to-top",
            Self::LeftToRight => "left-to-right",
            Self::RightToLeft => "right-to-left",
        }
    }

    /// The direction of a [`ReadoutDirection::name`].
    pub fn from_name(name: &str) -> Option<Self> {
        Self::ALL.into_iter().find(|d| d.name() == name)
    }

    /// [`ReadoutDirection::from_name`], or an error naming the known directions.
    pub fn parse(name: &str) -> Result<Self, String> {
        Self::from_name(name).ok_or_else(|| {
            let known: Vec<&str> = Self::ALL.iter().map(|d| d.name()).collect();
            format!("\"{name}\": expected one of {}", known.join(", "))
        })
    }

    /// The line coordinate of pixel `(u, v)` in readout order and the number of lines, in a
    /// `width x height` image: `(v, height)` top to bottom, `(height - 1 - v, height)`
    /// bottom to top, `(u, width)` left to right, `(width - 1 - u, width)` right to left.
    /// Line `l` is read at `t_mid + (l - N/2) t_r / N` ([`row_offset_s`]).
    #[inline]
    pub fn line(self, u: f64, v: f64, width: u32, height: u32) -> (f64, u32) {
        match self {
            Self::TopToBottom => (v, height),
            Self::BottomToTop => (f64::from(height) - 1.0 - v, height),
            Self::LeftToRight => (u, width),
            Self::RightToLeft => (f64::from(width) - 1.0 - u, width),
        }
    }
}
use crate::features::KeyPoint;
use crate::lie::so3_exp;

/// Capture time (ns) of image row coordinate `row` of a frame whose middle row is captured
/// at `t_mid_ns` and whose full readout takes `readout_ns` (seed eq. 2.61-2.63):
/// `t(v) = t_mid + (v - N/2) t_r / N`, rounded to the nearest ns.
///
/// With `n_rows == 0` or `readout_ns == 0` (global shutter) this returns `t_mid_ns`.
#[inline]
pub fn row_time_ns(t_mid_ns: i64, readout_ns: i64, row: f64, n_rows: u32) -> i64 {
    t_mid_ns + row_offset_ns(readout_ns, row, n_rows)
}

/// The offset `t(v) - t_mid` in ns (rounded), see [`row_time_ns`].
#[inline]
pub fn row_offset_ns(readout_ns: i64, row: f64, n_rows: u32) -> i64 {
    if n_rows == 0 || readout_ns == 0 || !row.is_finite() {
        return 0;
    }
    let n = f64::from(n_rows);
    ((row - 0.5 * n) * readout_ns as f64 / n).round() as i64
}

/// The offset `t(v) - t_mid` in seconds (not rounded), for continuous-time models.
#[inline]
pub fn row_offset_s(readout_ns: i64, row: f64, n_rows: u32) -> f64 {
    if n_rows == 0 {
        return 0.0;
    }
    let n = f64::from(n_rows);
    (row - 0.5 * n) * readout_ns as f64 * 1e-9 / n
}

/// The offset `t - t_mid` in seconds of pixel `uv` of `camera`, whose lines are read in its
/// [`PinholeRadtan::readout_line`] order over `readout_ns` ([`row_offset_s`] of the line).
#[inline]
pub fn pixel_offset_s(camera: &PinholeRadtan, readout_ns: i64, uv: &Vector2<f64>) -> f64 {
    let (line, n) = camera.readout_line(uv);
    row_offset_s(readout_ns, line, n)
}

/// Inverse of [`row_time_ns`]: the (continuous) row coordinate captured at `t_ns`.
///
/// Returns `None` for a global shutter (`readout_ns == 0`) or `n_rows == 0`, where every
/// row has the same time. The result may lie outside `[0, N)` when `t_ns` is outside the
/// frame's readout interval.
pub fn row_at_time(t_mid_ns: i64, readout_ns: i64, t_ns: i64, n_rows: u32) -> Option<f64> {
    if readout_ns == 0 || n_rows == 0 {
        return None;
    }
    let n = f64::from(n_rows);
    Some(0.5 * n + (t_ns - t_mid_ns) as f64 * n / readout_ns as f64)
}

/// Capture times (ns) of the first (`row = 0`) and last (`row = N-1`) rows of a frame.
pub fn frame_row_span_ns(t_mid_ns: i64, readout_ns: i64, n_rows: u32) -> (i64, i64) {
    let last = f64::from(n_rows.saturating_sub(1));
    (
        row_time_ns(t_mid_ns, readout_ns, 0.0, n_rows),
        row_time_ns(t_mid_ns, readout_ns, last, n_rows),
    )
}

/// Solves the rolling-shutter projection fixed point `v = project_v(t(v))`.
///
/// `project_v(t_ns)` returns the image row coordinate of the observed 3D point when the
/// camera pose at time `t_ns` is used (or `None` when it is behind the camera). Starting at
/// the middle row, the iteration `v_{k+1} = project_v(t(v_k))` converges quickly because
/// image motion during the readout is a small fraction of the frame. Returns the row
/// coordinate and its capture time once two iterates differ by less than `tol_rows`, or
/// `None` when it does not converge in `max_iters` steps or the point leaves the view.
pub fn solve_row_fixed_point<F>(
    t_mid_ns: i64,
    readout_ns: i64,
    n_rows: u32,
    tol_rows: f64,
    max_iters: usize,
    mut project_v: F,
) -> Option<(f64, i64)>
where
    F: FnMut(i64) -> Option<f64>,
{
    let mut v = 0.5 * f64::from(n_rows);
    for _ in 0..max_iters.max(1) {
        let t = row_time_ns(t_mid_ns, readout_ns, v, n_rows);
        let next = project_v(t)?;
        if !next.is_finite() {
            return None;
        }
        if (next - v).abs() < tol_rows {
            return Some((next, row_time_ns(t_mid_ns, readout_ns, next, n_rows)));
        }
        v = next;
    }
    None
}

/// Rotates every keypoint's bearing from its row's capture time to the frame's mid-row time
/// (rolling-shutter compensation of rotation, seed eq. 2.61-2.63), in place.
///
/// `omega` is the camera's angular velocity in its own frame (rad/s; the gyro rate rotated
/// into the camera, or the motion model's angular velocity). With
/// `R_wc(t_mid + dt) = R_wc(t_mid) Exp(ω dt)`, a bearing seen at row time `t_mid + dt` is
/// `b_mid = Exp(ω dt) b_row` at mid-row time. The translation during the readout is left
/// to the pose optimiser's velocity model. Keypoints stay in distorted pixel coordinates.
pub fn derotate_keypoints(
    camera: &PinholeRadtan,
    readout_ns: i64,
    omega: &Vector3<f64>,
    keypoints: &mut [KeyPoint],
) {
    if readout_ns == 0 || camera.height == 0 || omega.norm_squared() == 0.0 {
        return;
    }
    for k in keypoints {
        let dt = pixel_offset_s(camera, readout_ns, &Vector2::new(k.x as f64, k.y as f64));
        let r = so3_exp(&(omega * dt));
        let b = r * camera.unproject(&Vector2::new(k.x as f64, k.y as f64));
        if let Some(p) = camera.project(&b) {
            k.x = p.x as f32;
            k.y = p.y as f32;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn middle_row_is_t_mid_and_ends_are_half_readout_away() {
        let (t, tr, n) = (1_000_000_000, 30_000_000, 480);
        assert_eq!(row_time_ns(t, tr, 240.0, n), t);
        assert_eq!(row_time_ns(t, tr, 0.0, n), t - 15_000_000);
        assert_eq!(row_time_ns(t, tr, 480.0, n), t + 15_000_000);
        assert_eq!(
            frame_row_span_ns(t, tr, n),
            (t - 15_000_000, t + 15_000_000 - 62_500)
        );
        assert_eq!(row_time_ns(t, 0, 17.0, n), t);
        assert_eq!(row_time_ns(t, tr, 17.0, 0), t);
        assert!((row_offset_s(tr, 0.0, n) + 0.015).abs() < 1e-15);
    }

    #[test]
    fn readout_lines_follow_the_direction() {
        let (w, h) = (720, 1280);
        let lines: Vec<(f64, u32)> = ReadoutDirection::ALL
            .iter()
            .map(|d| d.line(10.0, 100.0, w, h))
            .collect();
        assert_eq!(
            lines,
            vec![(100.0, 1280), (1179.0, 1280), (10.0, 720), (709.0, 720)]
        );
        for d in ReadoutDirection::ALL {
            assert_eq!(ReadoutDirection::from_name(d.name()), Some(d));
            // The first line read is at -t_r/2, the middle one at t_mid, either way.
            let first = match d {
                ReadoutDirection::TopToBottom => (5.0, 0.0),
                ReadoutDirection::BottomToTop => (5.0, 1279.0),
                ReadoutDirection::LeftToRight => (0.0, 5.0),
                ReadoutDirection::RightToLeft => (719.0, 5.0),
            };
            let (l, n) = d.line(first.0, first.1, w, h);
            assert!(
                (row_offset_s(20_000_000, l, n) + 0.010).abs() < 1e-12,
                "{d:?}"
            );
        }
        assert_eq!(ReadoutDirection::from_name("sideways"), None);
    }

    #[test]
    fn inverse_round_trips() {
        let (t, tr, n) = (5_000_000_000, 20_000_000, 480);
        for row in [0.0, 13.25, 239.5, 479.0] {
            let tt = row_time_ns(t, tr, row, n);
            let back = row_at_time(t, tr, tt, n).expect("rolling shutter");
            assert!((back - row).abs() < 1e-3, "{row} -> {back}");
        }
        assert!(row_at_time(t, 0, t, n).is_none());
    }

    #[test]
    fn fixed_point_finds_row_of_moving_point() {
        // A point moving down the image at 2000 px/s, at row 100 at t_mid.
        let (t_mid, tr, n) = (1_000_000_000_i64, 30_000_000_i64, 480);
        let f = |t: i64| Some(100.0 + 2000.0 * (t - t_mid) as f64 * 1e-9);
        let (v, t) = solve_row_fixed_point(t_mid, tr, n, 1e-6, 50, f).expect("converges");
        // Closed form: v = 100 + 2000 (v - 240) 30e-3 / 480.
        let a = 2000.0 * 0.03 / 480.0;
        let expect = (100.0 - 240.0 * a) / (1.0 - a);
        assert!((v - expect).abs() < 1e-4, "{v} vs {expect}");
        assert_eq!(t, row_time_ns(t_mid, tr, v, n));
        assert!(solve_row_fixed_point(t_mid, tr, n, 1e-6, 5, |_| None).is_none());
    }

    #[test]
    fn derotation_undoes_a_rotating_rolling_shutter() {
        // A camera turning at ω: a static point seen at row time t_mid + dt lands where the
        // mid-row camera would see Exp(-ω dt) applied to it; derotation brings it back.
        let cam = PinholeRadtan::pinhole(752, 480, 458.0, 457.0, 367.0, 248.0);
        let omega = Vector3::new(0.4, -2.5, 0.8);
        let tr = 30_000_000;
        let p_mid = Vector3::new(0.7, -0.4, 3.0);
        let expect = cam.project(&p_mid).unwrap();
        // Fixed point: the row at which the point is captured.
        let mut v = expect.y;
        let mut px = expect;
        for _ in 0..20 {
            let dt = row_offset_s(tr, v, cam.height);
            let p_row = so3_exp(&(-omega * dt)) * p_mid;
            px = cam.project(&p_row).unwrap();
            v = px.y;
        }
        assert!((px - expect).norm() > 3.0, "the shutter moves the point");
        let mut kps = [KeyPoint {
            x: px.x as f32,
            y: px.y as f32,
            angle: 0.0,
            response: 0.0,
            size: 31.0,
            octave: 0,
        }];
        derotate_keypoints(&cam, tr, &omega, &mut kps);
        let got = Vector2::new(kps[0].x as f64, kps[0].y as f64);
        assert!((got - expect).norm() < 1e-2, "{got} vs {expect}");
    }
}
