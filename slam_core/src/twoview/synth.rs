//! Synthetic scenes for the tests of the two-view, PnP and pose-optimisation modules.

use nalgebra::{Isometry3, Point3, Vector2, Vector3};

use crate::camera::PinholeRadtan;
use crate::ransac::SplitMix64;

/// Gaussian samples from the seeded generator (Box-Muller).
pub(crate) struct Rng(pub SplitMix64);

impl Rng {
    pub fn new(seed: u64) -> Self {
        Self(SplitMix64::new(seed))
    }
    pub fn uniform(&mut self, lo: f64, hi: f64) -> f64 {
        lo + (hi - lo) * self.0.next_f64()
    }
    pub fn normal(&mut self) -> f64 {
        let u1 = self.0.next_f64().max(1e-300);
        let u2 = self.0.next_f64();
        (-2.0 * u1.ln()).sqrt() * (2.0 * std::f64::consts::PI * u2).cos()
    }
    pub fn normal2(&mut self, sigma: f64) -> Vector2<f64> {
        Vector2::new(self.normal(), self.normal()) * sigma
    }
}

/// A random point in a box in front of a camera at the origin looking along +z.
pub(crate) fn box_point(rng: &mut Rng) -> Vector3<f64> {
    let z = rng.uniform(1.5, 4.5);
    Vector3::new(
        rng.uniform(-0.85, 0.85) * z,
        rng.uniform(-0.55, 0.55) * z,
        z,
    )
}

/// A random point on the plane `nᵀX = d` seen by a camera at the origin.
pub(crate) fn plane_point(rng: &mut Rng, n: &Vector3<f64>, d: f64) -> Vector3<f64> {
    let ray = Vector3::new(rng.uniform(-0.7, 0.7), rng.uniform(-0.5, 0.5), 1.0);
    ray * (d / n.dot(&ray))
}

/// Matches of a two-view scene in normalised coordinates.
pub(crate) struct TwoViewScene {
    pub x1: Vec<Vector2<f64>>,
    pub x2: Vec<Vector2<f64>>,
    pub outlier: Vec<bool>,
}

/// Projects `n` points drawn by `gen` (frame 1) into view 1 (identity) and view 2 (`t_21`),
/// keeps those inside both images, adds Gaussian pixel noise and replaces a fraction
/// `outliers` of the matches in view 2 by random pixels.
pub(crate) fn two_view_scene(
    rng: &mut Rng,
    cam: &PinholeRadtan,
    t_21: &Isometry3<f64>,
    n: usize,
    noise_px: f64,
    outliers: f64,
    mut gen: impl FnMut(&mut Rng) -> Vector3<f64>,
) -> TwoViewScene {
    let mut s = TwoViewScene {
        x1: Vec::new(),
        x2: Vec::new(),
        outlier: Vec::new(),
    };
    let norm = |uv: Vector2<f64>| Vector2::new((uv.x - cam.cx) / cam.fx, (uv.y - cam.cy) / cam.fy);
    while s.x1.len() < n {
        let p = gen(rng);
        let q = t_21 * Point3::from(p);
        let (Some(u1), Some(u2)) = (cam.project(&p), cam.project(&q.coords)) else {
            continue;
        };
        if !cam.contains(&u1) || !cam.contains(&u2) {
            continue;
        }
        let is_out = rng.0.next_f64() < outliers;
        let u2 = if is_out {
            Vector2::new(
                rng.uniform(0.0, f64::from(cam.width)),
                rng.uniform(0.0, f64::from(cam.height)),
            )
        } else {
            u2 + rng.normal2(noise_px)
        };
        s.x1.push(norm(u1 + rng.normal2(noise_px)));
        s.x2.push(norm(u2));
        s.outlier.push(is_out);
    }
    s
}
