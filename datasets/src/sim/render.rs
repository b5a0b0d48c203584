//! The ray-casting renderer: per-pixel bearings precomputed once (undistortion), then per
//! row one camera pose (rolling shutter: each row at its own time) and per pixel a
//! ray-rectangle intersection plus a trilinear texture lookup. `f32` in the pixel loop, no
//! allocation per frame.

use nalgebra::{Isometry3, Vector3};
use slam_core::camera::PinholeRadtan;

use super::rng::{splitmix64, Rng};
use super::scene::{Scene, MAX_RECTS};
use super::texture::{fast_log2, MipTexture};
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
    /// Level-0 texels per metre of the rectangle's texture.
    texels_per_m: f32,
    /// Index of the rectangle in the scene.
    idx: u32,
}

/// Keeps the part of a convex polygon with `plane · p >= 0` (Sutherland-Hodgman).
fn clip(poly: &[[f64; 3]], plane: [f64; 3], out: &mut [[f64; 3]; 8]) -> usize {
    let d = |p: &[f64; 3]| plane[0] * p[0] + plane[1] * p[1] + plane[2] * p[2];
    let mut n = 0;
    for (i, a) in poly.iter().enumerate() {
        let b = &poly[(i + 1) % poly.len()];
        let (da, db) = (d(a), d(b));
        if da >= 0.0 && n < 8 {
            out[n] = *a;
            n += 1;
        }
        if (da >= 0.0) != (db >= 0.0) && n < 8 {
            let f = da / (da - db);
            out[n] = [
                a[0] + f * (b[0] - a[0]),
                a[1] + f * (b[1] - a[1]),
                a[2] + f * (b[2] - a[2]),
            ];
            n += 1;
        }
    }
    n
}

/// True when the quadrilateral `corners` (camera frame) intersects the cone
/// `xmin <= x/z <= xmax, ymin <= y/z <= ymax` (a row's rays lie inside it).
fn quad_in_cone(corners: &[[f64; 3]; 4], cone: &[f64; 4]) -> bool {
    let [xmin, xmax, ymin, ymax] = *cone;
    let planes = [
        [1.0, 0.0, -xmin],
        [-1.0, 0.0, xmax],
        [0.0, 1.0, -ymin],
        [0.0, -1.0, ymax],
    ];
    let mut a = [[0.0; 3]; 8];
    let mut b = [[0.0; 3]; 8];
    a[..4].copy_from_slice(corners);
    let mut n = 4;
    for (i, pl) in planes.iter().enumerate() {
        n = if i % 2 == 0 {
            clip(&a[..n], *pl, &mut b)
        } else {
            clip(&b[..n], *pl, &mut a)
        };
        if n == 0 {
            return false;
        }
    }
    true
}

/// Renders a [`Scene`] through a [`PinholeRadtan`] camera.
#[derive(Debug, Clone)]
pub struct Renderer {
    cam: PinholeRadtan,
    /// Unit bearings (x, y, z components) and angular pixel sizes (rad), row-major,
    /// structure-of-arrays so the ray-plane pass vectorises.
    bx: Vec<f32>,
    by: Vec<f32>,
    bz: Vec<f32>,
    ang: Vec<f32>,
    /// Per row, a cone `[xmin, xmax, ymin, ymax]` (in x/z, y/z) containing all its rays, used
    /// to skip rectangles a row cannot see.
    row_cones: Vec<[f64; 4]>,
    /// Standard-normal values, windows of which are the per-pixel noise.
    noise_table: Vec<f32>,
}

/// Length of [`Renderer`]'s noise table.
const NOISE_TABLE: usize = 1 << 18;

impl Renderer {
    /// Precomputes the per-pixel bearings (one undistortion per pixel, done once).
    pub fn new(cam: PinholeRadtan) -> Self {
        let bearings = cam.bearing_table_f32();
        let (w, h) = (cam.width as usize, cam.height as usize);
        let n_px = bearings.len();
        let (mut bx, mut by, mut bz, mut angs) = (
            Vec::with_capacity(n_px),
            Vec::with_capacity(n_px),
            Vec::with_capacity(n_px),
            Vec::with_capacity(n_px),
        );
        for (i, b) in bearings.iter().enumerate() {
            let (x, y) = (i % w, i / w);
            // Angular pixel size from the neighbours (forward differences; backward at the end).
            let nb = |j: usize| bearings.get(j).copied().unwrap_or(*b);
            let right = if x + 1 < w {
                nb(i + 1)
            } else if x > 0 {
                nb(i - 1)
            } else {
                *b
            };
            let below = if y + 1 < h {
                nb(i + w)
            } else if y > 0 {
                nb(i - w)
            } else {
                *b
            };
            let d = |a: [f32; 3]| {
                ((a[0] - b[0]).powi(2) + (a[1] - b[1]).powi(2) + (a[2] - b[2]).powi(2)).sqrt()
            };
            let ang = (d(right) * d(below)).sqrt().max(1e-6);
            bx.push(b[0]);
            by.push(b[1]);
            bz.push(b[2]);
            angs.push(ang);
        }
        let margin = 2e-3; // about one pixel, for f32 rounding of the bearings
        let row_cones = bearings
            .chunks_exact(w.max(1))
            .map(|row| {
                let mut c = [
                    f64::INFINITY,
                    f64::NEG_INFINITY,
                    f64::INFINITY,
                    f64::NEG_INFINITY,
                ];
                for b in row {
                    let (x, y) = (f64::from(b[0] / b[2]), f64::from(b[1] / b[2]));
                    c = [c[0].min(x), c[1].max(x), c[2].min(y), c[3].max(y)];
                }
                [c[0] - margin, c[1] + margin, c[2] - margin, c[3] + margin]
            })
            .collect();
        let mut rng = Rng::new(0x006E_015E);
        let noise_table = (0..NOISE_TABLE).map(|_| rng.normal() as f32).collect();
        Self {
            cam,
            bx,
            by,
            bz,
            ang: angs,
            row_cones,
            noise_table,
        }
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

    /// Per-row plane data for camera pose `t_wc` (camera-to-world) of the rectangles that
    /// may be visible inside `cone`; returns how many were written.
    fn row_planes(
        scene: &Scene,
        t_wc: &Isometry3<f64>,
        cone: &[f64; 4],
        out: &mut [RowPlane; MAX_RECTS],
    ) -> usize {
        let c = t_wc.translation.vector;
        let rt = t_wc.rotation.to_rotation_matrix().transpose();
        let to_cam = |v: &Vector3<f64>| {
            let x = rt * v;
            [x.x as f32, x.y as f32, x.z as f32]
        };
        let mut n = 0;
        for (i, rect) in scene.rects.iter().enumerate().take(MAX_RECTS) {
            let corners = [
                (0.0, 0.0),
                (rect.size_u, 0.0),
                (rect.size_u, rect.size_v),
                (0.0, rect.size_v),
            ]
            .map(|(s, w)| {
                let p = rt * (rect.point(s, w) - c);
                [p.x, p.y, p.z]
            });
            if !quad_in_cone(&corners, cone) {
                continue;
            }
            let normal = rect.normal();
            let oc = c - rect.origin;
            out[n] = RowPlane {
                n: to_cam(&normal),
                dist: (-normal.dot(&oc)) as f32,
                u: to_cam(&rect.axis_u),
                s0: rect.axis_u.dot(&oc) as f32,
                v: to_cam(&rect.axis_v),
                w0: rect.axis_v.dot(&oc) as f32,
                size_u: rect.size_u as f32,
                size_v: rect.size_v as f32,
                texels_per_m: rect.texture.texels_per_m(),
                idx: i as u32,
            };
            n += 1;
        }
        n
    }

    /// Renders an 8-bit grey image into `dst` (`width * height` bytes, row-major).
    /// `pose_of_row(v)` gives the camera-to-world pose used for image row `v` (the same pose
    /// for every row renders a global-shutter image). Pixels whose ray hits nothing are 0.
    pub fn render_into<P>(
        &self,
        scene: &Scene,
        pose_of_row: P,
        noise: PixelNoise,
        dst: &mut [u8],
    ) -> Result<(), DatasetError>
    where
        P: FnMut(u32) -> Isometry3<f64>,
    {
        let sigma = noise.sigma;
        let mut vals = [0f32; CHUNK];
        self.for_each_chunk(scene, pose_of_row, dst, |v, x0, hits, out| {
            let n = out.len().min(CHUNK);
            for (i, val) in vals[..n].iter_mut().enumerate() {
                *val = match hits.texture(i) {
                    Some(tex) => tex.sample_lod(hits.s[i], hits.w[i], hits.lod[i]),
                    None => 0.0,
                };
            }
            if sigma > 0.0 {
                // A pseudo-random window of the normal table per (frame, row, chunk).
                let mut st = noise.seed ^ ((v as u64) << 32 | x0 as u64);
                let off = (splitmix64(&mut st) % (NOISE_TABLE - CHUNK) as u64) as usize;
                for (val, z) in vals[..n].iter_mut().zip(&self.noise_table[off..off + n]) {
                    *val += sigma * z;
                }
            }
            for (px, val) in out.iter_mut().zip(&vals[..n]) {
                *px = (val + 0.5).clamp(0.0, 255.0) as u8;
            }
        })
    }

    /// Renders the index + 1 of the rectangle seen by each pixel (0 = nothing), with the
    /// same per-row poses as [`Renderer::render_into`]. For tests and masks.
    pub fn render_labels_into<P>(
        &self,
        scene: &Scene,
        pose_of_row: P,
        dst: &mut [u8],
    ) -> Result<(), DatasetError>
    where
        P: FnMut(u32) -> Isometry3<f64>,
    {
        self.for_each_chunk(scene, pose_of_row, dst, |_, _, hits, out| {
            for (i, px) in out.iter_mut().enumerate() {
                *px = hits.rect_index(i).map_or(0, |r| (r + 1).min(255) as u8);
            }
        })
    }

    /// Casts the rays of every row in chunks of [`CHUNK`] pixels and hands the hits to `shade`
    /// (row, first column, hits, output pixels).
    fn for_each_chunk<P, S>(
        &self,
        scene: &Scene,
        mut pose_of_row: P,
        dst: &mut [u8],
        mut shade: S,
    ) -> Result<(), DatasetError>
    where
        P: FnMut(u32) -> Isometry3<f64>,
        S: FnMut(usize, usize, &ChunkHits<'_>, &mut [u8]),
    {
        self.check_dst(dst, scene)?;
        let w = self.cam.width as usize;
        let mut planes = [RowPlane::default(); MAX_RECTS];
        let mut hits = ChunkHits::new(scene);
        for (v, (row, cone)) in dst.chunks_exact_mut(w).zip(&self.row_cones).enumerate() {
            let pose = pose_of_row(v as u32);
            let n = Self::row_planes(scene, &pose, cone, &mut planes);
            for (c, out) in row.chunks_mut(CHUNK).enumerate() {
                let base = v * w + c * CHUNK;
                let len = out.len();
                hits.cast(
                    &planes[..n],
                    base,
                    &self.bx[base..base + len],
                    &self.by[base..base + len],
                    &self.bz[base..base + len],
                );
                hits.lods(&self.ang[base..base + len]);
                shade(v, c * CHUNK, &hits, out);
            }
        }
        Ok(())
    }
}

/// Pixels per ray-casting chunk.
const CHUNK: usize = 64;
/// "No hit" marker in [`ChunkHits::idx`].
const NO_HIT: u32 = u32::MAX;

/// The nearest hits of one chunk of rays (structure of arrays, vectorisable).
struct ChunkHits<'a> {
    /// Texture of each scene rectangle (by index).
    textures: [Option<&'a MipTexture>; MAX_RECTS],
    /// Index of the chunk's first pixel in the image.
    base: usize,
    t: [f32; CHUNK],
    /// |cos| of the incidence angle.
    cos: [f32; CHUNK],
    /// Texels per metre of the hit texture.
    tpm: [f32; CHUNK],
    /// Level of detail (log2 of the pixel footprint in level-0 texels), see [`Self::lods`].
    lod: [f32; CHUNK],
    s: [f32; CHUNK],
    w: [f32; CHUNK],
    /// Rectangle index in the scene, or [`NO_HIT`].
    idx: [u32; CHUNK],
}

impl<'a> ChunkHits<'a> {
    fn new(scene: &'a Scene) -> Self {
        let mut textures = [None; MAX_RECTS];
        for (t, r) in textures.iter_mut().zip(&scene.rects) {
            *t = Some(&*r.texture);
        }
        Self {
            textures,
            base: 0,
            t: [0.0; CHUNK],
            cos: [0.0; CHUNK],
            tpm: [0.0; CHUNK],
            lod: [0.0; CHUNK],
            s: [0.0; CHUNK],
            w: [0.0; CHUNK],
            idx: [NO_HIT; CHUNK],
        }
    }

    /// Intersects the rays `(bx, by, bz)` (at most [`CHUNK`]) with `planes`, nearest first.
    fn cast(&mut self, planes: &[RowPlane], base: usize, bx: &[f32], by: &[f32], bz: &[f32]) {
        self.base = base;
        self.t = [f32::INFINITY; CHUNK];
        self.idx = [NO_HIT; CHUNK];
        let n = bx.len().min(by.len()).min(bz.len()).min(CHUNK);
        let (bx, by, bz) = (&bx[..n], &by[..n], &bz[..n]);
        for p in planes {
            let (t_best, cos, tpm, s_out, w_out, idx) = (
                &mut self.t[..n],
                &mut self.cos[..n],
                &mut self.tpm[..n],
                &mut self.s[..n],
                &mut self.w[..n],
                &mut self.idx[..n],
            );
            for i in 0..n {
                let (x, y, z) = (bx[i], by[i], bz[i]);
                let den = p.n[0] * x + p.n[1] * y + p.n[2] * z;
                let t = p.dist / den;
                let s = p.s0 + t * (p.u[0] * x + p.u[1] * y + p.u[2] * z);
                let w = p.w0 + t * (p.v[0] * x + p.v[1] * y + p.v[2] * z);
                let ok = (t > 1e-4)
                    & (t < t_best[i])
                    & (s >= 0.0)
                    & (s <= p.size_u)
                    & (w >= 0.0)
                    & (w <= p.size_v);
                t_best[i] = if ok { t } else { t_best[i] };
                cos[i] = if ok { den.abs() } else { cos[i] };
                tpm[i] = if ok { p.texels_per_m } else { tpm[i] };
                s_out[i] = if ok { s } else { s_out[i] };
                w_out[i] = if ok { w } else { w_out[i] };
                idx[i] = if ok { p.idx } else { idx[i] };
            }
        }
    }

    /// Computes the level of detail of every hit from the angular pixel sizes `ang`:
    /// footprint = t · ang / sqrt(|cos|) (geometric mean of the two axes of the footprint).
    fn lods(&mut self, ang: &[f32]) {
        let n = ang.len().min(CHUNK);
        let (lod, t, cos, tpm) = (
            &mut self.lod[..n],
            &self.t[..n],
            &self.cos[..n],
            &self.tpm[..n],
        );
        for i in 0..n {
            let texels = t[i] * ang[i] * tpm[i] / cos[i].max(0.05).sqrt();
            // Misses have t = inf: clamp to a finite value so the log stays defined.
            lod[i] = fast_log2(texels.clamp(1.0, 65536.0));
        }
    }

    /// Scene rectangle hit by pixel `i` of the chunk.
    #[inline(always)]
    fn rect_index(&self, i: usize) -> Option<usize> {
        let k = self.idx[i];
        (k != NO_HIT).then_some(k as usize)
    }

    /// Texture of the rectangle hit by pixel `i`.
    #[inline(always)]
    fn texture(&self, i: usize) -> Option<&'a MipTexture> {
        self.textures.get(self.rect_index(i)?).copied().flatten()
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
