//! The synthetic world: textured rectangles (a room with free-standing panels).
//!
//! World frame: z up, gravity `(0, 0, -9.81)`. The room spans x in [-10, 10], y in [-7, 7],
//! z in [0, 4] m (floor, ceiling and four walls), with five panels standing in front of the
//! walls that occlude them (depth discontinuities, vertical edges for rolling-shutter tests).

use std::sync::Arc;

use nalgebra::Vector3;

use super::rng::mix_seed;
use super::texture::MipTexture;

/// Largest number of rectangles a scene may hold (the renderer keeps per-row plane data on
/// the stack).
pub const MAX_RECTS: usize = 16;

/// A textured, double-sided rectangle `origin + s·axis_u + w·axis_v`, `s in [0, size_u]`,
/// `w in [0, size_v]` (metres).
#[derive(Debug, Clone)]
pub struct Rect {
    /// Corner of the rectangle (texture coordinate (0, 0)), world frame.
    pub origin: Vector3<f64>,
    /// Unit vector along the first side.
    pub axis_u: Vector3<f64>,
    /// Unit vector along the second side (orthogonal to `axis_u`).
    pub axis_v: Vector3<f64>,
    /// Length of the first side, m.
    pub size_u: f64,
    /// Length of the second side, m.
    pub size_v: f64,
    /// Its texture.
    pub texture: Arc<MipTexture>,
}

impl Rect {
    /// Unit normal `axis_u x axis_v`.
    pub fn normal(&self) -> Vector3<f64> {
        self.axis_u.cross(&self.axis_v)
    }

    /// The world point at texture coordinates `(s, w)` metres.
    pub fn point(&self, s: f64, w: f64) -> Vector3<f64> {
        self.origin + self.axis_u * s + self.axis_v * w
    }
}

/// A world made of textured rectangles.
#[derive(Debug, Clone)]
pub struct Scene {
    /// The rectangles (at most [`MAX_RECTS`]).
    pub rects: Vec<Rect>,
}

/// (origin, axis u, axis v, size u, size v, texel size) of a rectangle to build.
type RectSpec = (Vector3<f64>, Vector3<f64>, Vector3<f64>, f64, f64, f64);

/// Index of the first panel in [`Scene::room`] (0-5 are floor, ceiling and walls).
pub const FIRST_PANEL: usize = 6;

impl Scene {
    /// The default room (see the module docs). Textures depend on `seed` only, so every
    /// agent of a scenario sees the same world.
    pub fn room(seed: u64) -> Self {
        let (x0, x1, y0, y1, h) = (-10.0, 10.0, -7.0, 7.0, 4.0);
        let ex = Vector3::x();
        let ey = Vector3::y();
        let ez = Vector3::z();
        let mut specs: Vec<RectSpec> = vec![
            // floor, ceiling (1.5 cm texels: large and seen obliquely)
            (Vector3::new(x0, y0, 0.0), ex, ey, x1 - x0, y1 - y0, 0.015),
            (Vector3::new(x0, y0, h), ex, ey, x1 - x0, y1 - y0, 0.015),
            // walls y = y0, y = y1, x = x0, x = x1 (1 cm texels)
            (Vector3::new(x0, y0, 0.0), ex, ez, x1 - x0, h, 0.01),
            (Vector3::new(x0, y1, 0.0), ex, ez, x1 - x0, h, 0.01),
            (Vector3::new(x0, y0, 0.0), ey, ez, y1 - y0, h, 0.01),
            (Vector3::new(x1, y0, 0.0), ey, ez, y1 - y0, h, 0.01),
        ];
        // Panels: (centre x, centre y, facing angle of the normal, width, bottom, top).
        let panels = [
            (8.2, -2.0, std::f64::consts::PI + 0.35, 1.6, 0.0, 2.2),
            (-8.0, 1.5, -0.26, 2.0, 0.0, 1.8),
            (2.0, 5.6, -std::f64::consts::FRAC_PI_2, 1.8, 0.0, 2.0),
            (
                -3.0,
                -5.7,
                std::f64::consts::FRAC_PI_2 + 0.44,
                1.5,
                0.0,
                2.4,
            ),
            (-6.6, 4.9, -0.9, 1.2, 0.6, 2.2),
        ];
        for (cx, cy, a, wdt, z0, z1) in panels {
            let n = Vector3::new(f64::cos(a), f64::sin(a), 0.0);
            let u = ez.cross(&n); // horizontal, so u x v = ... (v = z)
            let origin = Vector3::new(cx, cy, z0) - u * (0.5 * wdt);
            specs.push((origin, u, ez, wdt, z1 - z0, 0.01));
        }
        let rects = specs
            .into_iter()
            .enumerate()
            .map(
                |(i, (origin, axis_u, axis_v, size_u, size_v, texel))| Rect {
                    origin,
                    axis_u,
                    axis_v,
                    size_u,
                    size_v,
                    texture: Arc::new(MipTexture::dead_leaves(
                        size_u,
                        size_v,
                        texel,
                        mix_seed(seed, &[0x5CE7E, i as u64]),
                    )),
                },
            )
            .collect();
        Self { rects }
    }

    /// The nearest rectangle hit by the ray `origin + t·dir` (t > 1e-6): `(index, t)`.
    /// Reference (f64, slow) implementation used by tests and tools.
    pub fn raycast(&self, origin: &Vector3<f64>, dir: &Vector3<f64>) -> Option<(usize, f64)> {
        let mut best: Option<(usize, f64)> = None;
        for (i, r) in self.rects.iter().enumerate() {
            let n = r.normal();
            let den = n.dot(dir);
            if den.abs() < 1e-12 {
                continue;
            }
            let t = n.dot(&(r.origin - origin)) / den;
            if t <= 1e-6 || best.is_some_and(|(_, bt)| t >= bt) {
                continue;
            }
            let q = origin + dir * t - r.origin;
            let (s, w) = (q.dot(&r.axis_u), q.dot(&r.axis_v));
            if (0.0..=r.size_u).contains(&s) && (0.0..=r.size_v).contains(&w) {
                best = Some((i, t));
            }
        }
        best
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn room_is_closed_and_panels_occlude_walls() {
        let scene = Scene::room(1);
        assert!(scene.rects.len() <= MAX_RECTS);
        let o = Vector3::new(0.0, 0.0, 1.5);
        for k in 0..64 {
            let a = f64::from(k) * 0.1;
            let d = Vector3::new(a.cos(), a.sin(), 0.3 * (3.0 * a).sin());
            assert!(scene.raycast(&o, &d).is_some(), "ray {k} escapes the room");
        }
        // Looking from the centre towards panel 0 (in front of the x = 10 wall).
        let (i, t) = scene
            .raycast(&o, &Vector3::new(8.2, -2.0, 0.0))
            .expect("hit");
        assert_eq!(i, FIRST_PANEL);
        assert!(t < 1.01);
    }
}
