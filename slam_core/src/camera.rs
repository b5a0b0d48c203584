//! Camera models: pinhole with radial-tangential (Brown) distortion, seed eq. 2.57-2.60.

use nalgebra::{Matrix2, Matrix2x3, Matrix2x4, Matrix2x6, Vector2, Vector3};

use crate::lie::skew;
use crate::rolling_shutter::ReadoutDirection;

/// Pinhole camera with radial-tangential distortion (seed eq. 2.57-2.60).
///
/// Projection of a point `(x, y, z)` in the camera frame (z forward, x right, y down):
/// `x_n = (x/z, y/z)`, `r² = |x_n|²`,
/// `x_d = x_n (1 + k1 r² + k2 r⁴ + k3 r⁶) + [2 p1 x y + p2 (r² + 2x²); 2 p2 x y + p1 (r² + 2y²)]`,
/// `u = fx x_d + cx`, `v = fy y_d + cy`.
#[derive(Debug, Clone, Copy, PartialEq)]
#[cfg_attr(feature = "serde", derive(serde::Serialize, serde::Deserialize))]
pub struct PinholeRadtan {
    /// Image width in pixels.
    pub width: u32,
    /// Image height in pixels (the rolling-shutter row count N).
    pub height: u32,
    /// Focal length along u, pixels.
    pub fx: f64,
    /// Focal length along v, pixels.
    pub fy: f64,
    /// Principal point u, pixels.
    pub cx: f64,
    /// Principal point v, pixels.
    pub cy: f64,
    /// Radial coefficient r².
    pub k1: f64,
    /// Radial coefficient r⁴.
    pub k2: f64,
    /// Tangential coefficient p1.
    pub p1: f64,
    /// Tangential coefficient p2.
    pub p2: f64,
    /// Radial coefficient r⁶.
    pub k3: f64,
    /// The rolling shutter's line order (rows top to bottom unless said).
    pub readout: ReadoutDirection,
}

impl PinholeRadtan {
    /// A pinhole camera without distortion.
    pub fn pinhole(width: u32, height: u32, fx: f64, fy: f64, cx: f64, cy: f64) -> Self {
        Self::from_coefficients(width, height, [fx, fy, cx, cy], [0.0; 5])
    }

    /// A camera of pinhole coefficients `[fx, fy, cx, cy]` and radial-tangential ones
    /// `[k1, k2, p1, p2, k3]` (eq. 2.57-2.60), the order of calibration files and messages.
    pub fn from_coefficients(
        width: u32,
        height: u32,
        pinhole: [f64; 4],
        distortion: [f64; 5],
    ) -> Self {
        let [fx, fy, cx, cy] = pinhole;
        let [k1, k2, p1, p2, k3] = distortion;
        Self {
            width,
            height,
            fx,
            fy,
            cx,
            cy,
            k1,
            k2,
            p1,
            p2,
            k3,
            readout: ReadoutDirection::TopToBottom,
        }
    }

    /// The line coordinate of pixel `uv` in the rolling shutter's readout order and the
    /// number of lines ([`ReadoutDirection::line`]; `(v, height)` for rows top to bottom).
    #[inline]
    pub fn readout_line(&self, uv: &Vector2<f64>) -> (f64, u32) {
        self.readout.line(uv.x, uv.y, self.width, self.height)
    }

    /// Where pixel `uv` lies in the readout, from `-½` (first line) to `½` (last): its
    /// capture time is `t_mid + readout_fraction · t_r`.
    #[inline]
    pub fn readout_fraction(&self, uv: &Vector2<f64>) -> f64 {
        let (line, n) = self.readout_line(uv);
        line / f64::from(n.max(1)) - 0.5
    }

    /// True when all distortion coefficients are zero.
    pub fn is_undistorted(&self) -> bool {
        self.k1 == 0.0 && self.k2 == 0.0 && self.p1 == 0.0 && self.p2 == 0.0 && self.k3 == 0.0
    }
}

/// Largest number of Newton steps [`PinholeRadtan::undistort`] takes.
const UNDISTORT_MAX_ITERS: usize = 30;
/// Residual (normalised image units) at which [`PinholeRadtan::undistort`] stops early.
const UNDISTORT_TOL: f64 = 1e-14;

impl PinholeRadtan {
    /// Projects a point given in the camera frame to pixel coordinates (seed eq. 2.57-2.60).
    ///
    /// Returns `None` when the point is not in front of the camera (`z <= 1e-9`). The result
    /// may lie outside the image; check it with [`PinholeRadtan::contains`]. Pixel centres
    /// are at integer coordinates (OpenCV / Kalibr convention).
    pub fn project(&self, p_c: &Vector3<f64>) -> Option<Vector2<f64>> {
        if p_c.z <= 1e-9 || !p_c.iter().all(|v| v.is_finite()) {
            return None;
        }
        let xn = Vector2::new(p_c.x / p_c.z, p_c.y / p_c.z);
        let xd = self.distort(&xn);
        Some(Vector2::new(
            self.fx * xd.x + self.cx,
            self.fy * xd.y + self.cy,
        ))
    }

    /// [`PinholeRadtan::project`] with the Jacobian `∂uv/∂p_c` (2x3) of the pixel with respect
    /// to the camera-frame point, through the distortion:
    /// `∂uv/∂p_c = diag(fx, fy) · ∂distort/∂x_n · ∂x_n/∂p_c`,
    /// `∂x_n/∂p_c = [1/z, 0, -x/z²; 0, 1/z, -y/z²]`. `None` when the point is not in front of
    /// the camera (as [`PinholeRadtan::project`]). The one copy of the projection Jacobian:
    /// bundle adjustment, the pose-only optimiser and the Sim(3) refinement chain it with
    /// `∂p_c/∂(their unknowns)` ([`pose_jacobian`] for an SE(3) pose).
    #[inline]
    pub fn project_with_jacobian(
        &self,
        p_c: &Vector3<f64>,
    ) -> Option<(Vector2<f64>, Matrix2x3<f64>)> {
        let uv = self.project(p_c)?;
        let iz = 1.0 / p_c.z;
        let xn = Vector2::new(p_c.x * iz, p_c.y * iz);
        let dxn_dp = Matrix2x3::new(iz, 0.0, -xn.x * iz, 0.0, iz, -xn.y * iz);
        let mut du_dp = if self.is_undistorted() {
            dxn_dp
        } else {
            self.distort_jacobian(&xn) * dxn_dp
        };
        du_dp.row_mut(0).scale_mut(self.fx);
        du_dp.row_mut(1).scale_mut(self.fy);
        Some((uv, du_dp))
    }

    /// Jacobian (2x4) of the pixel of a camera-frame point `p_c` with respect to the pinhole
    /// coefficients `(fx, fy, cx, cy)` (`VI_NOTES.md` §2): `[x_d, 0, 1, 0; 0, y_d, 0, 1]`.
    /// `None` when the point is not in front of the camera.
    pub fn pinhole_jacobian(&self, p_c: &Vector3<f64>) -> Option<Matrix2x4<f64>> {
        if p_c.z <= 1e-9 {
            return None;
        }
        let xd = self.distort(&Vector2::new(p_c.x / p_c.z, p_c.y / p_c.z));
        Some(Matrix2x4::new(xd.x, 0.0, 1.0, 0.0, 0.0, xd.y, 0.0, 1.0))
    }

    /// Jacobian (2x4) of the pixel of a camera-frame point `p_c` with respect to the
    /// distortion coefficients `(k1, k2, p1, p2)` (`VI_NOTES.md` §2, k3 held fixed): columns
    /// `k_i: r^(2i) (fx x_n, fy y_n)`, `p1: (2 fx x_n y_n, fy (r² + 2 y_n²))`,
    /// `p2: (fx (r² + 2 x_n²), 2 fy x_n y_n)`. `None` when the point is not in front.
    pub fn distortion_jacobian(&self, p_c: &Vector3<f64>) -> Option<Matrix2x4<f64>> {
        if p_c.z <= 1e-9 {
            return None;
        }
        let (x, y) = (p_c.x / p_c.z, p_c.y / p_c.z);
        let r2 = x * x + y * y;
        let (fx, fy) = (self.fx, self.fy);
        Some(Matrix2x4::new(
            fx * x * r2,
            fx * x * r2 * r2,
            2.0 * fx * x * y,
            fx * (r2 + 2.0 * x * x),
            fy * y * r2,
            fy * y * r2 * r2,
            fy * (r2 + 2.0 * y * y),
            2.0 * fy * x * y,
        ))
    }

    /// Applies the radial-tangential distortion to normalised coordinates `x_n = (x/z, y/z)`
    /// (seed eq. 2.58-2.59).
    pub fn distort(&self, xn: &Vector2<f64>) -> Vector2<f64> {
        let (x, y) = (xn.x, xn.y);
        let r2 = x * x + y * y;
        let radial = 1.0 + r2 * (self.k1 + r2 * (self.k2 + r2 * self.k3));
        let xy2 = 2.0 * x * y;
        Vector2::new(
            x * radial + self.p1 * xy2 + self.p2 * (r2 + 2.0 * x * x),
            y * radial + self.p2 * xy2 + self.p1 * (r2 + 2.0 * y * y),
        )
    }

    /// Jacobian `d x_d / d x_n` of [`PinholeRadtan::distort`] at `x_n`.
    pub fn distort_jacobian(&self, xn: &Vector2<f64>) -> Matrix2<f64> {
        let (x, y) = (xn.x, xn.y);
        let r2 = x * x + y * y;
        let radial = 1.0 + r2 * (self.k1 + r2 * (self.k2 + r2 * self.k3));
        // d radial / d r2
        let dr = self.k1 + r2 * (2.0 * self.k2 + 3.0 * self.k3 * r2);
        let dxx = radial + 2.0 * x * x * dr + 2.0 * self.p1 * y + 6.0 * self.p2 * x;
        let dxy = 2.0 * x * y * dr + 2.0 * self.p1 * x + 2.0 * self.p2 * y;
        let dyx = 2.0 * x * y * dr + 2.0 * self.p2 * y + 2.0 * self.p1 * x;
        let dyy = radial + 2.0 * y * y * dr + 2.0 * self.p2 * x + 6.0 * self.p1 * y;
        Matrix2::new(dxx, dxy, dyx, dyy)
    }

    /// Inverts [`PinholeRadtan::distort`]: distorted normalised coordinates -> normalised
    /// coordinates (inverse of seed eq. 2.58-2.59).
    ///
    /// Damped Newton iterations started at `x_d` (a step that does not reduce the residual
    /// is halved), falling back to the classic fixed-point update when the Jacobian is
    /// singular. Converges to ~1e-14 within a few steps inside the image of usual lenses;
    /// for points where the model is not invertible it returns the best iterate found.
    pub fn undistort(&self, xd: &Vector2<f64>) -> Vector2<f64> {
        if self.is_undistorted() || !xd.iter().all(|v| v.is_finite()) {
            return *xd;
        }
        let mut x = *xd;
        let mut res = self.distort(&x) - xd;
        let mut err = res.norm_squared();
        for _ in 0..UNDISTORT_MAX_ITERS {
            if err < UNDISTORT_TOL * UNDISTORT_TOL {
                break;
            }
            let step = match self.distort_jacobian(&x).try_inverse() {
                Some(j_inv) => -(j_inv * res),
                None => -res,
            };
            let mut scale = 1.0;
            let mut improved = false;
            for _ in 0..12 {
                let cand = x + step * scale;
                let cand_res = self.distort(&cand) - xd;
                let cand_err = cand_res.norm_squared();
                if cand_err.is_finite() && cand_err < err {
                    x = cand;
                    res = cand_res;
                    err = cand_err;
                    improved = true;
                    break;
                }
                scale *= 0.5;
            }
            if !improved {
                break;
            }
        }
        x
    }

    /// Pixel -> unit bearing vector in the camera frame (inverse of seed eq. 2.57-2.60).
    pub fn unproject(&self, uv: &Vector2<f64>) -> Vector3<f64> {
        let xd = Vector2::new((uv.x - self.cx) / self.fx, (uv.y - self.cy) / self.fy);
        let xn = self.undistort(&xd);
        Vector3::new(xn.x, xn.y, 1.0).normalize()
    }

    /// True when pixel `uv` lies inside the image, pixel centres at integer coordinates:
    /// `-0.5 <= u < width - 0.5` and the same for `v`.
    pub fn contains(&self, uv: &Vector2<f64>) -> bool {
        uv.x >= -0.5
            && uv.y >= -0.5
            && uv.x < f64::from(self.width) - 0.5
            && uv.y < f64::from(self.height) - 0.5
    }

    /// `f32` fast path of [`PinholeRadtan::project`] for hot loops (same model, same
    /// conventions). Returns `None` when `z <= 1e-6`.
    #[inline]
    pub fn project_f32(&self, p_c: [f32; 3]) -> Option<[f32; 2]> {
        let [x, y, z] = p_c;
        if z <= 1e-6 || !z.is_finite() {
            return None;
        }
        let (xn, yn) = (x / z, y / z);
        let (k1, k2, k3) = (self.k1 as f32, self.k2 as f32, self.k3 as f32);
        let (p1, p2) = (self.p1 as f32, self.p2 as f32);
        let r2 = xn * xn + yn * yn;
        let radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3));
        let xy2 = 2.0 * xn * yn;
        let xd = xn * radial + p1 * xy2 + p2 * (r2 + 2.0 * xn * xn);
        let yd = yn * radial + p2 * xy2 + p1 * (r2 + 2.0 * yn * yn);
        Some([
            self.fx as f32 * xd + self.cx as f32,
            self.fy as f32 * yd + self.cy as f32,
        ])
    }

    /// Unit bearings of every pixel centre, row-major (`width * height` entries), computed
    /// once with [`PinholeRadtan::unproject`]; the per-pixel table of renderers and
    /// undistortion maps.
    pub fn bearing_table_f32(&self) -> Vec<[f32; 3]> {
        let mut out = Vec::with_capacity(self.width as usize * self.height as usize);
        for v in 0..self.height {
            for u in 0..self.width {
                let b = self.unproject(&Vector2::new(f64::from(u), f64::from(v)));
                out.push([b.x as f32, b.y as f32, b.z as f32]);
            }
        }
        out
    }

    /// The EuRoC MAV `cam0` calibration (752x480), a handy realistic default.
    pub fn euroc_cam0() -> Self {
        Self {
            width: 752,
            height: 480,
            fx: 458.654,
            fy: 457.296,
            cx: 367.215,
            cy: 248.375,
            k1: -0.28340811,
            k2: 0.07395907,
            p1: 0.00019359,
            p2: 1.76187114e-05,
            k3: 0.0,
            readout: ReadoutDirection::TopToBottom,
        }
    }
}

/// Jacobian (2x6) of a pixel with respect to the left pose increment `T_cw ← Exp(δ) T_cw`,
/// `δ = [ω; v]` (rotation first, as [`crate::lie`]), given `∂uv/∂p` (from
/// [`PinholeRadtan::project_with_jacobian`], possibly chained with a fixed rotation) and the
/// point `p = T_cw p_w` the increment moves: `∂p/∂δ = [-[p]x | I]`, so the columns are
/// `[-∂uv/∂p [p]x | ∂uv/∂p]`.
#[inline]
pub fn pose_jacobian(d_uv_dp: &Matrix2x3<f64>, p: &Vector3<f64>) -> Matrix2x6<f64> {
    let mut j = Matrix2x6::zeros();
    j.fixed_view_mut::<2, 3>(0, 0)
        .copy_from(&(-(d_uv_dp * skew(p))));
    j.fixed_view_mut::<2, 3>(0, 3).copy_from(d_uv_dp);
    j
}

#[cfg(test)]
mod tests {
    use super::*;

    fn euroc() -> PinholeRadtan {
        let pinhole = [458.654, 457.296, 367.215, 248.375];
        PinholeRadtan::from_coefficients(
            752,
            480,
            pinhole,
            [-0.2834, 0.0740, 0.00019, 1.76e-5, 0.0],
        )
    }

    #[test]
    fn pixel_round_trip_over_the_whole_image() {
        let cam = euroc();
        let mut worst: f64 = 0.0;
        for v in (0..480).step_by(7).chain([479]) {
            for u in (0..752).step_by(7).chain([751]) {
                let uv = Vector2::new(f64::from(u), f64::from(v));
                let b = cam.unproject(&uv);
                assert!((b.norm() - 1.0).abs() < 1e-12);
                let back = cam.project(&(b * 3.7)).expect("in front");
                worst = worst.max((back - uv).norm());
            }
        }
        assert!(worst < 1e-9, "worst round-trip error {worst} px");
    }

    #[test]
    fn point_round_trip_and_f32_path() {
        let cam = euroc();
        for p in [
            Vector3::new(0.3, -0.2, 1.0),
            Vector3::new(-1.5, 0.9, 2.0),
            Vector3::new(0.0, 0.0, 5.0),
        ] {
            let uv = cam.project(&p).expect("in front");
            let b = cam.unproject(&uv);
            assert!((b - p.normalize()).norm() < 1e-10);
            let f = cam
                .project_f32([p.x as f32, p.y as f32, p.z as f32])
                .expect("in front");
            assert!((f64::from(f[0]) - uv.x).abs() < 1e-2);
            assert!((f64::from(f[1]) - uv.y).abs() < 1e-2);
        }
        assert!(cam.project(&Vector3::new(0.0, 0.0, -1.0)).is_none());
        assert!(cam.project_f32([0.0, 0.0, 0.0]).is_none());
    }

    #[test]
    fn jacobian_matches_finite_differences() {
        let cam = euroc();
        let x = Vector2::new(0.4, -0.3);
        let j = cam.distort_jacobian(&x);
        let h = 1e-6;
        for c in 0..2 {
            let mut dx = Vector2::zeros();
            dx[c] = h;
            let num = (cam.distort(&(x + dx)) - cam.distort(&(x - dx))) / (2.0 * h);
            assert!((num - j.column(c)).norm() < 1e-8);
        }
    }

    #[test]
    fn projection_jacobians_match_finite_differences() {
        let h = 1e-6;
        for cam in [
            euroc(),
            PinholeRadtan::pinhole(640, 480, 500.0, 510.0, 320.0, 240.0),
        ] {
            let p = Vector3::new(0.4, -0.3, 2.5);
            let (uv, j) = cam.project_with_jacobian(&p).expect("in front");
            assert_eq!(Some(uv), cam.project(&p));
            for c in 0..3 {
                let mut d = Vector3::zeros();
                d[c] = h;
                let num =
                    (cam.project(&(p + d)).unwrap() - cam.project(&(p - d)).unwrap()) / (2.0 * h);
                assert!((num - j.column(c)).norm() < 1e-5, "column {c}");
            }
            // Pose Jacobian: left increment Exp(δ) applied to p.
            let jp = pose_jacobian(&j, &p);
            for c in 0..6 {
                let mut d = nalgebra::Vector6::zeros();
                d[c] = h;
                let f = |d: &nalgebra::Vector6<f64>| {
                    let t = crate::lie::se3_exp(d);
                    cam.project(&(t * nalgebra::Point3::from(p)).coords)
                        .unwrap()
                };
                let num = (f(&d) - f(&-d)) / (2.0 * h);
                assert!((num - jp.column(c)).norm() < 1e-4, "pose column {c}");
            }
        }
        assert!(euroc()
            .project_with_jacobian(&Vector3::new(0.0, 0.0, -1.0))
            .is_none());
    }

    #[test]
    fn coefficient_jacobians_match_finite_differences() {
        let cam = euroc();
        let p = Vector3::new(0.5, -0.35, 2.0);
        let jp = cam.pinhole_jacobian(&p).expect("in front");
        let jd = cam.distortion_jacobian(&p).expect("in front");
        let h = 1e-7;
        let perturb = |c: usize, d: f64| {
            let mut k = cam;
            match c {
                0 => k.fx += d,
                1 => k.fy += d,
                2 => k.cx += d,
                3 => k.cy += d,
                4 => k.k1 += d,
                5 => k.k2 += d,
                6 => k.p1 += d,
                _ => k.p2 += d,
            }
            k.project(&p).unwrap()
        };
        for c in 0..8 {
            let num = (perturb(c, h) - perturb(c, -h)) / (2.0 * h);
            let ana = if c < 4 {
                jp.column(c)
            } else {
                jd.column(c - 4)
            };
            assert!(
                (num - ana).norm() < 1e-5 * (1.0 + num.norm()),
                "coefficient {c}"
            );
        }
        assert!(cam
            .pinhole_jacobian(&Vector3::new(0.0, 0.0, -1.0))
            .is_none());
        assert!(cam
            .distortion_jacobian(&Vector3::new(0.0, 0.0, -1.0))
            .is_none());
    }

    #[test]
    fn undistort_is_identity_without_distortion_and_handles_nan() {
        let cam = PinholeRadtan::pinhole(640, 480, 500.0, 500.0, 320.0, 240.0);
        let x = Vector2::new(0.25, -0.5);
        assert_eq!(cam.undistort(&x), x);
        let d = euroc().undistort(&Vector2::new(f64::NAN, 0.0));
        assert!(d.x.is_nan());
    }

    #[test]
    fn bearing_table_has_one_unit_entry_per_pixel() {
        let cam = PinholeRadtan::pinhole(8, 4, 5.0, 5.0, 3.5, 1.5);
        let t = cam.bearing_table_f32();
        assert_eq!(t.len(), 32);
        let c = t[8 + 3];
        assert!((c[0] * c[0] + c[1] * c[1] + c[2] * c[2] - 1.0).abs() < 1e-6);
        assert!(cam.contains(&Vector2::new(7.4, 3.4)) && !cam.contains(&Vector2::new(7.6, 0.0)));
    }
}
