//! The ray-casting renderer: per-pixel bearings precomputed once (undistortion), then per
//! row one camera pose (rolling shutter: each row at its own time) and per pixel a
//! ray-rectangle intersection plus a trilinear texture lookup. `f32` in the pixel loop, no
//! allocation per frame.

use nalgebra::{Isometry3, Vector3};
use slam_core::camera::PinholeRadtan;

use super::rng::splitmix64;
use super::scene::{Scene, MAX_RECTS};
use crate::DatasetError;

/// Per-pixel Gaussian-like noise, deterministic for `seed` (0 sigma = off).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PixelNoise {
    /// Seed of this frame's noise.
    pub seed: u64,
    /// Standard deviation in grey levels.
    pub sigma: f32,
}

/// One rectangle expressed in the camera frame of the current row.
#[derive(Debug, Clone, Copy, Default)]
struct RowPlane {
    /// Normal in the camera frame.
    n: [f32; 3],
    /// `n_W · (origin - c)`: ray parameter `t = dist / (n · b)`.
    dist: f32,
    /// Axis u in the camera frame and texture coordinate of the camera centre along it.
    u: [f32; 3],
    s0: f32,
    /// Axis v in the camera frame and texture coordinate of the camera centre along it.
    v: [f32; 3],
    w0: f32,
    size_u: f32,
    size_v: f32,
}

#[inline(always)]
fn dot(a: &[f32; 3], b: &[f32; 3]) -> f32 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}

/// A hit: rectangle index, ray length, |cos incidence|, texture coordinates.
struct Hit {
    idx: usize,
    t: f32,
    cos: f32,
    s: f32,
    w: f32,
}

#[inline(always)]
fn cast(planes: &[RowPlane], b: &[f32; 3]) -> Option<Hit> {
    let mut best: Option<Hit> = None;
    let mut best_t = f32::INFINITY;
    for (idx, p) in planes.iter().enumerate() {
        let den = dot(&p.n, b);
        let t = p.dist / den;
        if t > 1e-4 && t < best_t {
            let s = p.s0 + t * dot(&p.u, b);
            let w = p.w0 + t * dot(&p.v, b);
            if s >= 0.0 && s <= p.size_u && w >= 0.0 && w <= p.size_v {
                best_t = t;
                best = Some(Hit {
                    idx,
                    t,
                    cos: den.abs(),
                    s,
                    w,
                });
            }
        }
    }
    best
}

/// Renders a [`Scene`] through a [`PinholeRadtan`] camera.
#[derive(Debug, Clone)]
pub struct Renderer {
    cam: PinholeRadtan,
    /// Unit bearing (x, y, z) and angular size of the pixel (rad), row-major.
    rays: Vec<[f32; 4]>,
}

impl Renderer {
    /// Precomputes the per-pixel bearings (one undistortion per pixel, done once).
    pub fn new(cam: PinholeRadtan) -> Self {
        let bearings = cam.bearing_table_f32();
        let (w, h) = (cam.width as usize, cam.height as usize);
        let mut rays = Vec::with_capacity(bearings.len());
        for (i, b) in bearings.iter().enumerate() {
            let (x, y) = (i % w, i / w);
            // Angular pixel size from the neighbours (forward differences; backward at the end).
            let nb = |j: usize| bearings.get(j).copied().unwrap_or(*b);
            let bx = if x + 1 < w {
                nb(i + 1)
            } else if x > 0 {
                nb(i - 1)
            } else {
                *b
            };
            let by = if y + 1 < h {
                nb(i + w)
            } else if y > 0 {
                nb(i - w)
            } else {
                *b
            };
            let d = |a: [f32; 3]| {
                ((a[0] - b[0]).powi(2) + (a[1] - b[1]).powi(2) + (a[2] - b[2]).powi(2)).sqrt()
            };
            let ang = (d(bx) * d(by)).sqrt().max(1e-6);
            rays.push([b[0], b[1], b[2], ang]);
        }
        Self { cam, rays }
    }

    /// The camera.
    pub fn camera(&self) -> &PinholeRadtan {
        &self.cam
    }

    fn check_dst(&self, dst: &[u8], scene: &Scene) -> Result<(), DatasetError> {
        let need = self.cam.width as usize * self.cam.height as usize;
        if dst.len() != need {
            return Err(DatasetError::InvalidConfig {
                detail: format!(
                    "render buffer has {} bytes, the image needs {need}",
                    dst.len()
                ),
            });
        }
        if scene.rects.len() > MAX_RECTS {
            return Err(DatasetError::InvalidConfig {
                detail: format!(
                    "scene has {} rectangles, at most {MAX_RECTS}",
                    scene.rects.len()
                ),
            });
        }
        Ok(())
    }

    /// Per-row plane data for camera pose `t_wc` (camera-to-world).
    fn row_planes(scene: &Scene, t_wc: &Isometry3<f64>, out: &mut [RowPlane; MAX_RECTS]) -> usize {
        let c = t_wc.translation.vector;
        let r = t_wc.rotation.to_rotation_matrix();
        let to_cam = |v: &Vector3<f64>| {
            let x = r.transpose() * v;
            [x.x as f32, x.y as f32, x.z as f32]
        };
        let n = scene.rects.len().min(MAX_RECTS);
        for (rect, p) in scene.rects.iter().zip(out.iter_mut()) {
            let normal = rect.normal();
            let oc = c - rect.origin;
            *p = RowPlane {
                n: to_cam(&normal),
                dist: (-normal.dot(&oc)) as f32,
                u: to_cam(&rect.axis_u),
                s0: rect.axis_u.dot(&oc) as f32,
                v: to_cam(&rect.axis_v),
                w0: rect.axis_v.dot(&oc) as f32,
                size_u: rect.size_u as f32,
                size_v: rect.size_v as f32,
            };
        }
        n
    }

    /// Renders an 8-bit grey image into `dst` (`width * height` bytes, row-major).
    /// `pose_of_row(v)` gives the camera-to-world pose used for image row `v` (the same pose
    /// for every row renders a global-shutter image). Pixels whose ray hits nothing are 0.
    pub fn render_into<P>(
        &self,
        scene: &Scene,
        mut pose_of_row: P,
        noise: PixelNoise,
        dst: &mut [u8],
    ) -> Result<(), DatasetError>
    where
        P: FnMut(u32) -> Isometry3<f64>,
    {
        self.check_dst(dst, scene)?;
        let w = self.cam.width as usize;
        let mut planes = [RowPlane::default(); MAX_RECTS];
        // Sum of four uniform bytes has std 147.80; scale it to sigma.
        let noise_scale = noise.sigma / 147.8;
        for (v, (row, rays)) in dst
            .chunks_exact_mut(w)
            .zip(self.rays.chunks_exact(w))
            .enumerate()
        {
            let pose = pose_of_row(v as u32);
            let n = Self::row_planes(scene, &pose, &mut planes);
            let planes = &planes[..n];
            let mut rng_state = noise.seed ^ (v as u64).wrapping_mul(0x9E37_79B9_7F4A_7C15);
            let mut bits = 0u64;
            for (x, (px, ray)) in row.iter_mut().zip(rays).enumerate() {
                let b = [ray[0], ray[1], ray[2]];
                let mut val = match cast(planes, &b) {
                    Some(hit) => {
                        let footprint = hit.t * ray[3] / hit.cos.max(0.05).sqrt();
                        scene.rects[hit.idx].texture.sample(hit.s, hit.w, footprint)
                    }
                    None => 0.0,
                };
                if noise_scale > 0.0 {
                    if x % 2 == 0 {
                        bits = splitmix64(&mut rng_state);
                    }
                    let q = (bits >> (32 * (x % 2))) as u32;
                    let sum = (q & 0xff) + ((q >> 8) & 0xff) + ((q >> 16) & 0xff) + (q >> 24);
                    val += (sum as f32 - 510.0) * noise_scale;
                }
                *px = (val + 0.5).clamp(0.0, 255.0) as u8;
            }
        }
        Ok(())
    }

    /// Renders the index + 1 of the rectangle seen by each pixel (0 = nothing), with the
    /// same per-row poses as [`Renderer::render_into`]. For tests and masks.
    pub fn render_labels_into<P>(
        &self,
        scene: &Scene,
        mut pose_of_row: P,
        dst: &mut [u8],
    ) -> Result<(), DatasetError>
    where
        P: FnMut(u32) -> Isometry3<f64>,
    {
        self.check_dst(dst, scene)?;
        let w = self.cam.width as usize;
        let mut planes = [RowPlane::default(); MAX_RECTS];
        for (v, (row, rays)) in dst
            .chunks_exact_mut(w)
            .zip(self.rays.chunks_exact(w))
            .enumerate()
        {
            let pose = pose_of_row(v as u32);
            let n = Self::row_planes(scene, &pose, &mut planes);
            for (px, ray) in row.iter_mut().zip(rays) {
                *px =
                    cast(&planes[..n], &[ray[0], ray[1], ray[2]]).map_or(0, |h| (h.idx + 1) as u8);
            }
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::{Translation3, UnitQuaternion};

    #[test]
    fn labels_match_reference_raycast() {
        let scene = Scene::room(3);
        let cam = PinholeRadtan::pinhole(64, 48, 40.0, 40.0, 31.5, 23.5);
        let r = Renderer::new(cam);
        // Camera at (5, -1, 1.5) looking along +x (towards panel 0 and the x = 10 wall).
        let rot =
            UnitQuaternion::from_rotation_matrix(&nalgebra::Rotation3::from_matrix_unchecked(
                nalgebra::Matrix3::new(0.0, 0.0, 1.0, -1.0, 0.0, 0.0, 0.0, -1.0, 0.0),
            ));
        let pose = Isometry3::from_parts(Translation3::new(5.0, -1.0, 1.5), rot);
        let mut labels = vec![0u8; 64 * 48];
        r.render_labels_into(&scene, |_| pose, &mut labels)
            .expect("render");
        let mut checked = 0;
        for v in (0..48u32).step_by(3) {
            for u in (0..64u32).step_by(3) {
                let b = cam.unproject(&nalgebra::Vector2::new(f64::from(u), f64::from(v)));
                let d = pose.rotation * b;
                let want = scene
                    .raycast(&pose.translation.vector, &d)
                    .map_or(0, |(i, _)| i + 1);
                if labels[(v * 64 + u) as usize] as usize == want {
                    checked += 1;
                }
            }
        }
        // f32 vs f64 may disagree on a pixel exactly on an edge; nearly all must match.
        assert!(checked >= 16 * 22 - 3, "{checked}");
        assert!(labels.contains(&7), "panel 0 visible");
        let mut img = vec![0u8; 64 * 48];
        r.render_into(
            &scene,
            |_| pose,
            PixelNoise {
                seed: 1,
                sigma: 2.0,
            },
            &mut img,
        )
        .expect("render");
        assert!(img.iter().any(|&p| p != img[0]));
        assert!(r
            .render_into(
                &scene,
                |_| pose,
                PixelNoise {
                    seed: 1,
                    sigma: 0.0
                },
                &mut img[1..]
            )
            .is_err());
    }
}
