//! ORB orientation (intensity centroid) and rotated BRIEF kernels.
//!
//! Orientation: `atan2(m01, m10)` of the first-order moments over a disk of radius 15 around
//! the keypoint (on the unblurred level). Each of the 31 patch rows is a fixed 32-wide dot
//! product with precomputed weights (zero outside the disk), which vectorises well.
//!
//! Descriptor: 256 intensity tests on the blurred level at the pattern points rotated by the
//! keypoint angle. As proposed in the ORB paper, the angle is quantised to `bins` steps and the
//! rotated pattern of every step is precomputed as pixel offsets for the (shared) row stride.

use super::fast::Candidate;
use super::pattern::BIT_PATTERN_31;
use super::simd::dispatch;

/// Radius of the orientation patch.
pub(crate) const HALF_PATCH: usize = 15;
/// Patch rows.
const ROWS: usize = 2 * HALF_PATCH + 1;
/// Patch row width processed (31 used + 1 zero-weight column for a power-of-two width).
const COLS: usize = 32;
/// Largest distance (pixels, per axis) of a rotated pattern point from the centre.
pub(crate) const PATTERN_REACH: usize = 19;

/// Weights of the moment sums over the disk.
#[derive(Debug, Clone)]
pub(crate) struct OrientationTable {
    /// `u` weights (column offset inside the disk, 0 outside).
    wx: [[i16; COLS]; ROWS],
    /// 1 inside the disk, 0 outside.
    mask: [[i16; COLS]; ROWS],
}

impl OrientationTable {
    /// Disk `u^2 + v^2 <= 15.5^2` (symmetric under swapping axes, so no direction is favoured).
    pub(crate) fn new() -> Self {
        let mut wx = [[0i16; COLS]; ROWS];
        let mut mask = [[0i16; COLS]; ROWS];
        let r2 = (HALF_PATCH as f64 + 0.5).powi(2);
        for (r, (wrow, mrow)) in wx.iter_mut().zip(mask.iter_mut()).enumerate() {
            let v = r as f64 - HALF_PATCH as f64;
            for i in 0..ROWS {
                let u = i as f64 - HALF_PATCH as f64;
                if u * u + v * v <= r2 {
                    wrow[i] = u as i16;
                    mrow[i] = 1;
                }
            }
        }
        Self { wx, mask }
    }

    /// Orientation in degrees `[0, 360)` of the keypoint at `(x, y)`; needs
    /// `HALF_PATCH <= x < w - HALF_PATCH - 1` and `HALF_PATCH <= y < h - HALF_PATCH`.
    /// Returns 0 when the patch does not fit `img`.
    #[inline(always)]
    pub(crate) fn angle(&self, img: &[u8], stride: usize, x: usize, y: usize) -> f32 {
        if x < HALF_PATCH || y < HALF_PATCH {
            return 0.0;
        }
        let mut m10 = 0i32;
        let mut m01 = 0i32;
        for r in 0..ROWS {
            let start = (y + r - HALF_PATCH) * stride + x - HALF_PATCH;
            let Some(px) = img.get(start..).and_then(|s| s.first_chunk::<COLS>()) else {
                return 0.0;
            };
            let (wrow, mrow) = (&self.wx[r], &self.mask[r]);
            let mut sx = 0i32;
            let mut s = 0i32;
            for i in 0..COLS {
                let p = px[i] as i16 as i32;
                sx += wrow[i] as i32 * p;
                s += mrow[i] as i32 * p;
            }
            m10 += sx;
            m01 += (r as i32 - HALF_PATCH as i32) * s;
        }
        let deg = (m01 as f32).atan2(m10 as f32).to_degrees();
        if deg < 0.0 {
            deg + 360.0
        } else {
            deg
        }
    }
}

dispatch! {
    /// Orientations of the candidates `cands[keep[i]]`, appended to `out`.
    pub(crate) fn orientations(
        table: &OrientationTable,
        img: &[u8],
        stride: usize,
        cands: &[Candidate],
        keep: &[u32],
        out: &mut Vec<f32>,
    ) => orientations_impl
}

#[inline(always)]
fn orientations_impl(
    table: &OrientationTable,
    img: &[u8],
    stride: usize,
    cands: &[Candidate],
    keep: &[u32],
    out: &mut Vec<f32>,
) {
    for &i in keep {
        let a = match cands.get(i as usize) {
            Some(c) => table.angle(img, stride, c.x as usize, c.y as usize),
            None => 0.0,
        };
        out.push(a);
    }
}

/// Rotated BRIEF patterns as pixel offsets, one set per quantised angle.
#[derive(Debug, Clone)]
pub(crate) struct DescriptorTable {
    bins: usize,
    stride: usize,
    /// `bins * 512` offsets: for test `i`, points `2i` and `2i + 1`.
    offsets: Vec<isize>,
}

impl DescriptorTable {
    /// Tables for `bins` angles (`bins >= 1`) and row stride `stride`.
    pub(crate) fn new(bins: usize, stride: usize) -> Self {
        let bins = bins.max(1);
        let mut offsets = Vec::with_capacity(bins * 512);
        for b in 0..bins {
            let a = (b as f64) * std::f64::consts::TAU / bins as f64;
            let (s, c) = a.sin_cos();
            for t in &BIT_PATTERN_31 {
                for (px, py) in [(t[0], t[1]), (t[2], t[3])] {
                    let (px, py) = (px as f64, py as f64);
                    let rx = (px * c - py * s).round() as isize;
                    let ry = (px * s + py * c).round() as isize;
                    offsets.push(ry * stride as isize + rx);
                }
            }
        }
        Self {
            bins,
            stride,
            offsets,
        }
    }

    /// Row stride the offsets were made for.
    pub(crate) fn stride(&self) -> usize {
        self.stride
    }

    /// Descriptor of the keypoint at pixel index `center` of `img` (the blurred level) with
    /// angle `deg`; `None` when a test point falls outside `img`.
    #[inline]
    pub(crate) fn describe(&self, img: &[u8], center: usize, deg: f32) -> Option<[u8; 32]> {
        let step = 360.0 / self.bins as f32;
        let b = ((deg / step).round() as isize).rem_euclid(self.bins as isize) as usize;
        let offs = self.offsets.get(b * 512..(b + 1) * 512)?;
        // The window that every offset lands in, checked once.
        let reach = PATTERN_REACH * self.stride + PATTERN_REACH;
        let lo = center.checked_sub(reach)?;
        let win = img.get(lo..center + reach + 1)?;
        let c = reach as isize;
        let mut d = [0u8; 32];
        for (byte, o) in d.iter_mut().zip(offs.chunks_exact(16)) {
            let mut v = 0u8;
            for k in 0..8 {
                let a = win.get((c + o[2 * k]) as usize).copied().unwrap_or(0);
                let b = win.get((c + o[2 * k + 1]) as usize).copied().unwrap_or(0);
                v |= ((a < b) as u8) << k;
            }
            *byte = v;
        }
        Some(d)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn orientation_points_to_the_bright_side() {
        let (w, h) = (64, 64);
        let t = OrientationTable::new();
        // Bright on the right: angle ~0. Bright below: ~90 (image y down).
        let right: Vec<u8> = (0..w * h)
            .map(|i| if i % w > 32 { 200 } else { 10 })
            .collect();
        let a = t.angle(&right, w, 32, 32);
        assert!(!(2.0..=358.0).contains(&a), "{a}");
        let below: Vec<u8> = (0..w * h)
            .map(|i| if i / w > 32 { 200 } else { 10 })
            .collect();
        let a = t.angle(&below, w, 32, 32);
        assert!((a - 90.0).abs() < 2.0, "{a}");
        // Disk symmetric: the mask is its own transpose.
        for r in 0..ROWS {
            for i in 0..ROWS {
                assert_eq!(t.mask[r][i], t.mask[i][r]);
            }
        }
    }

    #[test]
    fn pattern_reach_bound_holds() {
        let stride = 1000;
        let table = DescriptorTable::new(30, stride);
        for &o in &table.offsets {
            let ry = (o as f64 / stride as f64).round() as isize;
            let rx = o - ry * stride as isize;
            assert!(rx.unsigned_abs() < PATTERN_REACH && ry.unsigned_abs() < PATTERN_REACH);
        }
    }

    #[test]
    fn descriptor_needs_room() {
        let table = DescriptorTable::new(30, 50);
        let img = vec![0u8; 50 * 50];
        assert!(table.describe(&img, 25 * 50 + 25, 10.0).is_some());
        assert!(table.describe(&img, 5 * 50 + 25, 10.0).is_none());
    }
}
