//! Image pyramid (fixed-point bilinear resize) and the 7x7 Gaussian blur used before BRIEF.
//!
//! All levels share the stride of level 0, so one table of pixel offsets serves every level.

use super::image::{GrayBuffer, GrayImage};
use super::simd::dispatch;
use crate::CoreError;

/// Fractional bits of the bilinear weights.
const W_BITS: u32 = 7;
const W_ONE: u16 = 1 << W_BITS;

/// Precomputed source index and weight of every output column / row of one resize.
#[derive(Debug, Clone, Default)]
struct Axis {
    /// First source index.
    idx: Vec<u32>,
    /// Weight of `idx + 1` in 1/128.
    w: Vec<u16>,
}

impl Axis {
    /// Pixel-centre aligned mapping of `dst` samples onto `src` samples (as OpenCV's linear
    /// resize): `s = (d + 0.5) * src / dst - 0.5`, clamped to the source.
    fn new(src: usize, dst: usize) -> Self {
        let ratio = src as f64 / dst as f64;
        let mut idx = Vec::with_capacity(dst);
        let mut w = Vec::with_capacity(dst);
        for d in 0..dst {
            let s = ((d as f64 + 0.5) * ratio - 0.5).max(0.0);
            let mut i = s.floor() as usize;
            let mut f = s - i as f64;
            if i + 1 >= src {
                i = src.saturating_sub(2);
                f = if src >= 2 { 1.0 } else { 0.0 };
            }
            idx.push(i as u32);
            w.push((f * W_ONE as f64).round() as u16);
        }
        Self { idx, w }
    }
}

/// An image pyramid with preallocated levels.
#[derive(Debug, Clone)]
pub struct Pyramid {
    levels: Vec<GrayBuffer>,
    scales: Vec<f32>,
    x_axes: Vec<Axis>,
    y_axes: Vec<Axis>,
    /// One row of vertically blended values (scratch).
    row: Vec<u16>,
}

impl Pyramid {
    /// A pyramid of `n_levels` for `width` x `height` images; level `l` has size
    /// `round(width / factor^l) x round(height / factor^l)` (at least 1 x 1).
    pub fn new(
        width: usize,
        height: usize,
        n_levels: usize,
        factor: f32,
    ) -> Result<Self, CoreError> {
        if n_levels == 0 || !(factor > 1.0 && factor.is_finite()) {
            return Err(CoreError::InvalidArgument(format!(
                "pyramid needs >= 1 level and a factor > 1 (got {n_levels}, {factor})"
            )));
        }
        let mut levels = Vec::with_capacity(n_levels);
        let mut scales = Vec::with_capacity(n_levels);
        let mut x_axes = Vec::with_capacity(n_levels);
        let mut y_axes = Vec::with_capacity(n_levels);
        let (mut pw, mut ph) = (width, height);
        for l in 0..n_levels {
            let scale = (factor as f64).powi(l as i32);
            let w = ((width as f64 / scale).round() as usize).max(1);
            let h = ((height as f64 / scale).round() as usize).max(1);
            levels.push(GrayBuffer::new(w, h, width)?);
            scales.push(scale as f32);
            x_axes.push(Axis::new(pw, w));
            y_axes.push(Axis::new(ph, h));
            (pw, ph) = (w, h);
        }
        Ok(Self {
            levels,
            scales,
            x_axes,
            y_axes,
            row: vec![0; width],
        })
    }

    /// Number of levels.
    pub fn n_levels(&self) -> usize {
        self.levels.len()
    }

    /// Level `l` (level 0 is a copy of the input).
    pub fn level(&self, l: usize) -> Option<GrayImage<'_>> {
        self.levels.get(l).map(|b| b.view())
    }

    /// Scale of level `l` relative to level 0 (`factor^l`).
    pub fn scale(&self, l: usize) -> Option<f32> {
        self.scales.get(l).copied()
    }

    /// Rebuilds every level from `img`, which must have the size given at construction.
    pub fn build(&mut self, img: &GrayImage<'_>) -> Result<(), CoreError> {
        let Some(first) = self.levels.first_mut() else {
            return Err(CoreError::InvalidArgument("empty pyramid".into()));
        };
        if img.width() != first.width() || img.height() != first.height() {
            return Err(CoreError::InvalidArgument(format!(
                "image is {}x{}, the pyramid was made for {}x{}",
                img.width(),
                img.height(),
                first.width(),
                first.height()
            )));
        }
        for y in 0..img.height() {
            first.row_mut(y).copy_from_slice(img.row(y));
        }
        for l in 1..self.levels.len() {
            let (prev, rest) = self.levels.split_at_mut(l);
            resize_bilinear(
                &prev[l - 1],
                &mut rest[0],
                &self.x_axes[l],
                &self.y_axes[l],
                &mut self.row,
            );
        }
        Ok(())
    }
}

dispatch! {
    /// Bilinear resize of `src` into `dst` with precomputed axes: vertical blend of two
    /// source rows (vectorised), then a horizontal gather.
    fn resize_bilinear(
        src: &GrayBuffer,
        dst: &mut GrayBuffer,
        xa: &Axis,
        ya: &Axis,
        row: &mut [u16],
    ) => resize_bilinear_impl
}

#[inline(always)]
fn resize_bilinear_impl(
    src: &GrayBuffer,
    dst: &mut GrayBuffer,
    xa: &Axis,
    ya: &Axis,
    row: &mut [u16],
) {
    let (sw, sh) = (src.width(), src.height());
    let (dw, dh) = (dst.width(), dst.height());
    if sw < 2 || row.len() < sw || xa.idx.len() < dw || ya.idx.len() < dh {
        return;
    }
    let row = &mut row[..sw];
    let (xi, xw) = (&xa.idx[..dw], &xa.w[..dw]);
    for dy in 0..dh {
        let y0 = (ya.idx[dy] as usize).min(sh - 1);
        let y1 = (y0 + 1).min(sh - 1);
        let wy = ya.w[dy];
        let r0 = &src.view().row(y0)[..sw];
        let r1 = &src.view().row(y1)[..sw];
        for ((o, &a), &b) in row.iter_mut().zip(r0).zip(r1) {
            *o = a as u16 * (W_ONE - wy) + b as u16 * wy;
        }
        let out = &mut dst.row_mut(dy)[..dw];
        for ((o, &i), &wx) in out.iter_mut().zip(xi).zip(xw) {
            // Axis::new keeps i + 1 < sw.
            let i = (i as usize).min(sw - 2);
            let pair = &row[i..i + 2];
            let v = pair[0] as u32 * (W_ONE - wx) as u32 + pair[1] as u32 * wx as u32;
            *o = ((v + (1 << (2 * W_BITS - 1))) >> (2 * W_BITS)) as u8;
        }
    }
}

/// Integer 7-tap approximation of a Gaussian with sigma 2 (sums to 256).
const GAUSS7: [u16; 7] = [18, 34, 49, 54, 49, 34, 18];

/// Reflect-101 index (`-1 -> 1`, `n -> n - 2`) for `i` in `-3..n + 3`, `n >= 4`.
#[inline]
fn reflect101(i: isize, n: usize) -> usize {
    let n = n as isize;
    let r = if i < 0 {
        -i
    } else if i >= n {
        2 * n - 2 - i
    } else {
        i
    };
    r.clamp(0, n - 1) as usize
}

/// 7x7 Gaussian blur (sigma 2, reflect-101 borders) of `src` into `dst` (resized to the size of
/// `src` within its capacity); `tmp` is one row of scratch, grown once.
///
/// Fixed point, 16-bit lanes throughout: the vertical pass keeps 8 fractional bits, rounded
/// to integers before the horizontal pass (error at most one grey level).
pub(crate) fn gaussian_blur7(src: &GrayImage<'_>, dst: &mut GrayBuffer, tmp: &mut Vec<u16>) {
    let (w, h) = (src.width(), src.height());
    if w < 4 || h < 4 || dst.set_size(w, h).is_err() {
        // Too small to blur meaningfully: copy.
        for y in 0..h.min(dst.height()) {
            let n = w.min(dst.width());
            dst.row_mut(y)[..n].copy_from_slice(&src.row(y)[..n]);
        }
        return;
    }
    tmp.clear();
    tmp.resize(w + 6, 0);
    for y in 0..h {
        let rows: [&[u8]; 7] =
            std::array::from_fn(|k| src.row(reflect101(y as isize + k as isize - 3, h)));
        blur_row(rows, &mut tmp[..w + 6], dst.row_mut(y));
    }
}

dispatch! {
    /// One output row of [`gaussian_blur7`].
    fn blur_row(rows: [&[u8]; 7], tmp: &mut [u16], out: &mut [u8]) => blur_row_impl
}

#[inline(always)]
fn blur_row_impl(rows: [&[u8]; 7], tmp: &mut [u16], out: &mut [u8]) {
    let w = out.len();
    if tmp.len() != w + 6 || rows.iter().any(|r| r.len() < w) {
        return;
    }
    let [a, b, c, d, e, f, g] = rows.map(|r| &r[..w]);
    let [k0, k1, k2, k3, ..] = GAUSS7;
    {
        let t = &mut tmp[3..w + 3];
        for x in 0..w {
            let v = k0 * (a[x] as u16 + g[x] as u16)
                + k1 * (b[x] as u16 + f[x] as u16)
                + k2 * (c[x] as u16 + e[x] as u16)
                + k3 * d[x] as u16;
            t[x] = (v + 128) >> 8;
        }
    }
    for k in 0..3 {
        tmp[k] = tmp[3 + reflect101(k as isize - 3, w)];
        tmp[w + 3 + k] = tmp[3 + reflect101((w + k) as isize, w)];
    }
    let (t0, t1, t2, t3, t4, t5, t6) = (
        &tmp[..w],
        &tmp[1..w + 1],
        &tmp[2..w + 2],
        &tmp[3..w + 3],
        &tmp[4..w + 4],
        &tmp[5..w + 5],
        &tmp[6..w + 6],
    );
    for x in 0..w {
        let v = k0 * (t0[x] + t6[x]) + k1 * (t1[x] + t5[x]) + k2 * (t2[x] + t4[x]) + k3 * t3[x];
        out[x] = ((v + 128) >> 8) as u8;
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn level_sizes_and_constant_image() {
        let (w, h) = (752, 480);
        let data = vec![77u8; w * h];
        let img = GrayImage::from_packed(&data, w, h).unwrap();
        let mut p = Pyramid::new(w, h, 8, crate::features::ORB_SCALE_FACTOR as f32).unwrap();
        p.build(&img).unwrap();
        let l1 = p.level(1).unwrap();
        assert_eq!((l1.width(), l1.height()), (627, 400));
        let l7 = p.level(7).unwrap();
        assert_eq!((l7.width(), l7.height()), (210, 134));
        for l in 0..8 {
            let v = p.level(l).unwrap();
            for y in 0..v.height() {
                assert!(v.row(y).iter().all(|&x| x == 77));
            }
        }
        let wrong = GrayImage::from_packed(&data, w - 1, h).unwrap();
        assert!(p.build(&wrong).is_err());
    }

    #[test]
    fn resize_of_ramp_is_close_to_exact() {
        let (w, h) = (120, 90);
        let data: Vec<u8> = (0..w * h).map(|i| ((i % w) * 2) as u8).collect();
        let img = GrayImage::from_packed(&data, w, h).unwrap();
        let mut p = Pyramid::new(w, h, 2, crate::features::ORB_SCALE_FACTOR as f32).unwrap();
        p.build(&img).unwrap();
        let l1 = p.level(1).unwrap();
        for x in 1..l1.width() - 1 {
            let s = (x as f64 + 0.5) * (w as f64 / l1.width() as f64) - 0.5;
            let exact = 2.0 * s;
            let got = l1.row(10)[x] as f64;
            assert!((got - exact).abs() <= 1.0, "x={x} got {got} exact {exact}");
        }
    }

    #[test]
    fn blur_keeps_constant_and_smooths_impulse() {
        let (w, h) = (40, 30);
        let mut data = vec![100u8; w * h];
        let img = GrayImage::from_packed(&data, w, h).unwrap();
        let mut dst = GrayBuffer::new(w, h, w).unwrap();
        let mut tmp = Vec::new();
        gaussian_blur7(&img, &mut dst, &mut tmp);
        assert!(dst.data().iter().all(|&v| v == 100));
        data.iter_mut().for_each(|v| *v = 0);
        data[15 * w + 20] = 255;
        let img = GrayImage::from_packed(&data, w, h).unwrap();
        gaussian_blur7(&img, &mut dst, &mut tmp);
        let c = dst.view().row(15)[20];
        // 255 * 54 * 54 / 65536 ~ 11.3 (rounded twice)
        assert!((11..=12).contains(&c), "{c}");
        let side = dst.view().row(15)[17]; // 255 * 54 * 18 / 65536 ~ 3.8
        assert!((3..=4).contains(&side), "{side}");
        assert_eq!(dst.view().row(15)[24], 0);
    }
}
