//! Procedural "dead leaves" textures with mip levels, generated once per plane.
//!
//! A texture is many random shapes (axis-aligned and rotated rectangles, discs) of random
//! grey with a mild linear gradient each, painted coarse-to-fine over a shaded background,
//! with sizes spread log-uniformly from 3 cm to 1.2 m. The result
//! is scale-invariant clutter with corners at every scale and no repetition, which gives
//! FAST/ORB plenty of distinctive features. Shape edges are anti-aliased from their signed
//! distance. Mip levels are 2x2 box averages; sampling is bilinear within a level and
//! linear across two levels (trilinear).

use super::rng::Rng;

/// One mip level inside [`MipTexture::data`].
#[derive(Debug, Clone, Copy, PartialEq)]
struct Level {
    offset: usize,
    w: usize,
    h: usize,
    /// Texels per metre along u and v.
    scale_u: f32,
    scale_v: f32,
    /// Largest coordinate that keeps `x0 + 1` inside the level.
    max_x: f32,
    max_y: f32,
}

/// A grey texture covering a `size_u x size_v` metre rectangle, with mip levels.
#[derive(Debug, Clone)]
pub struct MipTexture {
    data: Vec<u8>,
    /// Mip levels, finest first (unused entries repeat the coarsest one).
    levels: [Level; MAX_LEVELS],
    n_levels: usize,
    /// Texels per metre of level 0 (geometric mean of u and v).
    texels_per_m: f32,
}

/// Largest level count (level 0 included); a power of two.
const MAX_LEVELS: usize = 8;

impl MipTexture {
    /// Generates a dead-leaves texture for a `size_u x size_v` m rectangle with about
    /// `texel_m` metre texels. Deterministic for `seed`.
    pub fn dead_leaves(size_u: f64, size_v: f64, texel_m: f64, seed: u64) -> Self {
        let align = 1usize << (MAX_LEVELS - 1);
        let dim = |size: f64| {
            let n = (size / texel_m).ceil().max(1.0) as usize;
            n.div_ceil(align) * align
        };
        let (w, h) = (dim(size_u), dim(size_v));
        let base = paint(w, h, size_u, size_v, seed);
        Self::from_level0(&base, w, h, size_u, size_v)
    }

    /// Builds the mip chain from a level-0 image (`w x h`, row-major, values 0-255).
    fn from_level0(base: &[f32], w: usize, h: usize, size_u: f64, size_v: f64) -> Self {
        let mut data: Vec<u8> = base
            .iter()
            .map(|&v| v.round().clamp(0.0, 255.0) as u8)
            .collect();
        let mut levels = vec![make_level(0, w, h, size_u, size_v)];
        let (mut cw, mut ch, mut coff) = (w, h, 0usize);
        while levels.len() < MAX_LEVELS && cw >= 4 && ch >= 4 && cw % 2 == 0 && ch % 2 == 0 {
            let (nw, nh) = (cw / 2, ch / 2);
            let noff = data.len();
            for y in 0..nh {
                for x in 0..nw {
                    let i = coff + 2 * y * cw + 2 * x;
                    let s = u32::from(data[i])
                        + u32::from(data[i + 1])
                        + u32::from(data[i + cw])
                        + u32::from(data[i + cw + 1]);
                    data.push(((s + 2) / 4) as u8);
                }
            }
            levels.push(make_level(noff, nw, nh, size_u, size_v));
            (cw, ch, coff) = (nw, nh, noff);
        }
        let texels_per_m = ((w as f64 / size_u) * (h as f64 / size_v)).sqrt() as f32;
        Self {
            data,
            levels: {
                let mut arr = [levels[levels.len() - 1]; MAX_LEVELS];
                arr[..levels.len()].copy_from_slice(&levels);
                arr
            },
            n_levels: levels.len(),
            texels_per_m,
        }
    }

    /// Texels per metre of the finest level.
    pub fn texels_per_m(&self) -> f32 {
        self.texels_per_m
    }

    /// Number of mip levels.
    pub fn n_levels(&self) -> usize {
        self.n_levels
    }

    /// Bilinear sample of level `lvl` at plane coordinates `(s, w)` metres (clamped to edge).
    #[inline(always)]
    fn bilinear(&self, lvl: usize, s: f32, w: f32) -> f32 {
        // MAX_LEVELS is a power of two: the mask lets the compiler drop the bounds check.
        let l = &self.levels[lvl & (MAX_LEVELS - 1)];
        let x = (s * l.scale_u - 0.5).clamp(0.0, l.max_x);
        let y = (w * l.scale_v - 0.5).clamp(0.0, l.max_y);
        let (x0, y0) = (x as usize, y as usize);
        let (fx, fy) = (x - x0 as f32, y - y0 as f32);
        let i = l.offset + y0 * l.w + x0;
        let d = &self.data[i..i + l.w + 2];
        let top = f32::from(d[0]) + fx * (f32::from(d[1]) - f32::from(d[0]));
        let bot = f32::from(d[l.w]) + fx * (f32::from(d[l.w + 1]) - f32::from(d[l.w]));
        top + fy * (bot - top)
    }

    /// Trilinear sample at `(s, w)` metres for a pixel footprint of `footprint_m` metres.
    #[inline(always)]
    pub fn sample(&self, s: f32, w: f32, footprint_m: f32) -> f32 {
        let texels = footprint_m * self.texels_per_m;
        self.sample_lod(s, w, fast_log2(texels.max(1.0)))
    }

    /// Sample at `(s, w)` metres at level of detail `lod` (log2 of the footprint in level-0
    /// texels). Levels are blended linearly inside a transition band around each half
    /// level (`frac` in [0.25, 0.75]) and taken alone outside it: continuous like trilinear
    /// filtering, with one bilinear fetch for about half of the pixels.
    #[inline(always)]
    pub fn sample_lod(&self, s: f32, w: f32, lod: f32) -> f32 {
        let top = self.n_levels - 1;
        if lod <= 0.25 {
            return self.bilinear(0, s, w);
        }
        if lod >= top as f32 {
            return self.bilinear(top, s, w);
        }
        let l0 = lod as usize;
        let f = lod - l0 as f32;
        if f <= 0.25 {
            self.bilinear(l0, s, w)
        } else if f >= 0.75 {
            self.bilinear(l0 + 1, s, w)
        } else {
            let a = self.bilinear(l0, s, w);
            let b = self.bilinear(l0 + 1, s, w);
            a + (2.0 * f - 0.5) * (b - a)
        }
    }
}

/// log2 for positive normal floats, max error ~0.005 (enough to pick mip levels).
#[inline(always)]
pub(crate) fn fast_log2(x: f32) -> f32 {
    let bits = x.to_bits();
    let exp = ((bits >> 23) & 0xff) as f32 - 127.0;
    let m = f32::from_bits((bits & 0x007f_ffff) | 0x3f80_0000); // in [1, 2)
                                                                // Quadratic fit of log2(m) on [1, 2].
    exp + (-0.344_845 * m + 2.024_658) * m - 1.674_873
}

fn make_level(offset: usize, w: usize, h: usize, size_u: f64, size_v: f64) -> Level {
    Level {
        offset,
        w,
        h,
        scale_u: (w as f64 / size_u) as f32,
        scale_v: (h as f64 / size_v) as f32,
        max_x: (w as f32 - 1.001).max(0.0),
        max_y: (h as f32 - 1.001).max(0.0),
    }
}

/// Paints the level-0 image: shaded background plus dead-leaves shapes, coarse to fine.
fn paint(w: usize, h: usize, size_u: f64, size_v: f64, seed: u64) -> Vec<f32> {
    let mut rng = Rng::new(seed);
    let (tu, tv) = (w as f64 / size_u, h as f64 / size_v); // texels per metre
                                                           // Background: smooth shading with random direction and period.
    let (a, ph) = (rng.range(0.0, std::f64::consts::TAU), rng.range(0.0, 6.3));
    let period = rng.range(3.0, 8.0);
    let (ca, sa) = (a.cos(), a.sin());
    let mut img = vec![0f32; w * h];
    for y in 0..h {
        for x in 0..w {
            let (u, v) = (x as f64 / tu, y as f64 / tv);
            let d = u * ca + v * sa;
            img[y * w + x] =
                (128.0 + 60.0 * (std::f64::consts::TAU * d / period + ph).sin()) as f32;
        }
    }
    let area = size_u * size_v;
    let (r_min, r_max) = (0.03_f64, 1.2_f64);
    let octaves = (r_max / r_min).log2().ceil() as i32;
    // Painted coarse to fine: with coverage c per octave the finest octave shows on a fraction
    // 1 - e^-c of the surface, the next on (1 - e^-c) e^-c, ...: c = 0.4 keeps every scale
    // visible instead of letting the finest shapes turn into noise at a distance.
    let coverage_per_octave = 0.4;
    for o in (0..octaves).rev() {
        let lo = r_min * 2f64.powi(o);
        let hi = (lo * 2.0).min(r_max);
        // Mean area of shapes in this octave, ~3.4 r^2 (discs pi r^2, rectangles 4 r^2).
        let mean_r2 = (lo * lo + lo * hi + hi * hi) / 3.0;
        let n = (coverage_per_octave * area / (3.4 * mean_r2)).ceil() as usize;
        for _ in 0..n {
            let r = lo * (hi / lo).powf(rng.uniform());
            let shape = Shape::random(&mut rng, size_u, size_v, r);
            shape.paint(&mut img, w, h, tu, tv);
        }
    }
    img
}

#[derive(Debug, Clone, Copy)]
enum Kind {
    Rect {
        hu: f64,
        hv: f64,
        cos: f64,
        sin: f64,
    },
    Disc {
        r: f64,
    },
}

#[derive(Debug, Clone, Copy)]
struct Shape {
    kind: Kind,
    cu: f64,
    cv: f64,
    grey: f64,
    gu: f64,
    gv: f64,
    bound: f64,
}

impl Shape {
    fn random(rng: &mut Rng, size_u: f64, size_v: f64, r: f64) -> Self {
        let cu = rng.range(-r, size_u + r);
        let cv = rng.range(-r, size_v + r);
        let grey = rng.range(15.0, 240.0);
        // Gradient: up to ~40 grey levels across the shape.
        let gmag = rng.range(0.0, 20.0) / r;
        let ga = rng.range(0.0, std::f64::consts::TAU);
        let pick = rng.uniform();
        let kind = if pick < 0.3 {
            Kind::Disc { r }
        } else {
            let aspect = rng.range(0.25, 1.0).sqrt();
            let (hu, hv) = if rng.uniform() < 0.5 {
                (r * aspect, r / aspect)
            } else {
                (r / aspect, r * aspect)
            };
            let angle = if pick < 0.65 {
                0.0
            } else {
                rng.range(0.0, std::f64::consts::PI)
            };
            Kind::Rect {
                hu,
                hv,
                cos: angle.cos(),
                sin: angle.sin(),
            }
        };
        let bound = match kind {
            Kind::Disc { r } => r,
            Kind::Rect { hu, hv, .. } => hu.hypot(hv),
        };
        Self {
            kind,
            cu,
            cv,
            grey,
            gu: gmag * ga.cos(),
            gv: gmag * ga.sin(),
            bound,
        }
    }

    /// Alpha-blends the shape into `img` (coverage from the signed distance in texels).
    fn paint(&self, img: &mut [f32], w: usize, h: usize, tu: f64, tv: f64) {
        let x0 = ((self.cu - self.bound) * tu).floor().max(0.0) as usize;
        let x1 = (((self.cu + self.bound) * tu).ceil().max(0.0) as usize).min(w);
        let y0 = ((self.cv - self.bound) * tv).floor().max(0.0) as usize;
        let y1 = (((self.cv + self.bound) * tv).ceil().max(0.0) as usize).min(h);
        let texel = 1.0 / tu.min(tv);
        for y in y0..y1 {
            let dv = (y as f64 + 0.5) / tv - self.cv;
            let row = &mut img[y * w..(y + 1) * w];
            for (x, px) in row.iter_mut().enumerate().take(x1).skip(x0) {
                let du = (x as f64 + 0.5) / tu - self.cu;
                let sd = match self.kind {
                    Kind::Disc { r } => r - du.hypot(dv),
                    Kind::Rect { hu, hv, cos, sin } => {
                        let lu = cos * du + sin * dv;
                        let lv = -sin * du + cos * dv;
                        (hu - lu.abs()).min(hv - lv.abs())
                    }
                };
                let alpha = (sd / texel + 0.5).clamp(0.0, 1.0);
                if alpha > 0.0 {
                    let val = self.grey + self.gu * du + self.gv * dv;
                    *px += (alpha * (val - f64::from(*px))) as f32;
                }
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn fast_log2_is_close() {
        for x in [1.0f32, 1.5, 2.0, 3.3, 17.0, 1000.0] {
            assert!((fast_log2(x) - x.log2()).abs() < 0.01, "{x}");
        }
    }

    #[test]
    fn texture_is_deterministic_textured_and_has_mips() {
        let a = MipTexture::dead_leaves(1.3, 0.7, 0.01, 5);
        let b = MipTexture::dead_leaves(1.3, 0.7, 0.01, 5);
        assert_eq!(a.data, b.data);
        assert!(a.n_levels() >= 5);
        let l0 = a.levels[0];
        assert_eq!((l0.w % 128, l0.h % 128), (0, 0));
        // Plenty of contrast: standard deviation of level 0 well above 30 grey levels.
        let px = &a.data[..l0.w * l0.h];
        let mean = px.iter().map(|&v| f64::from(v)).sum::<f64>() / px.len() as f64;
        let var = px
            .iter()
            .map(|&v| (f64::from(v) - mean).powi(2))
            .sum::<f64>()
            / px.len() as f64;
        assert!(var.sqrt() > 30.0, "std {}", var.sqrt());
        // Sampling stays in range everywhere, including outside the rectangle.
        for (s, w, f) in [
            (0.0, 0.0, 0.001),
            (1.3, 0.7, 0.05),
            (-1.0, 5.0, 10.0),
            (0.5, 0.3, 0.02),
        ] {
            let v = a.sample(s, w, f);
            assert!((0.0..=255.0).contains(&v));
        }
    }
}
