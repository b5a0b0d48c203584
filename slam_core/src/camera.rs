//! Camera models: pinhole with radial-tangential (Brown) distortion, seed eq. 2.57-2.60.

/// Pinhole camera with radial-tangential distortion (seed eq. 2.57-2.60).
///
/// Projection of a point `(x, y, z)` in the camera frame (z forward, x right, y down):
/// `x_n = (x/z, y/z)`, `r² = |x_n|²`,
/// `x_d = x_n (1 + k1 r² + k2 r⁴ + k3 r⁶) + [2 p1 x y + p2 (r² + 2x²); 2 p2 x y + p1 (r² + 2y²)]`,
/// `u = fx x_d + cx`, `v = fy y_d + cy`.
#[derive(Debug, Clone, Copy, PartialEq)]
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
}

impl PinholeRadtan {
    /// A pinhole camera without distortion.
    pub fn pinhole(width: u32, height: u32, fx: f64, fy: f64, cx: f64, cy: f64) -> Self {
        Self { width, height, fx, fy, cx, cy, k1: 0.0, k2: 0.0, p1: 0.0, p2: 0.0, k3: 0.0 }
    }

    /// True when all distortion coefficients are zero.
    pub fn is_undistorted(&self) -> bool {
        self.k1 == 0.0 && self.k2 == 0.0 && self.p1 == 0.0 && self.p2 == 0.0 && self.k3 == 0.0
    }
}
