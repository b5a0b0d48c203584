//! Top-view PNG plot of an estimated trajectory over its ground truth (after alignment).
//!
//! The view plane is spanned by the two axes along which the ground truth extends most
//! (x-y for EuRoC / synthetic z-up worlds, x-z for KITTI's camera frame). Ground truth is
//! drawn in grey, the estimate in red, start points as small squares, with a 1-2-5 scale bar.
use std::path::Path;

use nalgebra::Vector3;

const SIZE: u32 = 800;
const MARGIN: f64 = 40.0;

struct Canvas {
    w: u32,
    h: u32,
    px: Vec<u8>,
}

impl Canvas {
    fn new(w: u32, h: u32) -> Self {
        Self {
            w,
            h,
            px: vec![255; (w * h * 3) as usize],
        }
    }

    fn put(&mut self, x: i64, y: i64, c: [u8; 3]) {
        if x >= 0 && y >= 0 && (x as u32) < self.w && (y as u32) < self.h {
            let i = ((y as u32 * self.w + x as u32) * 3) as usize;
            self.px[i..i + 3].copy_from_slice(&c);
        }
    }

    fn line(&mut self, a: (f64, f64), b: (f64, f64), c: [u8; 3], width: i64) {
        let n = ((b.0 - a.0).abs().max((b.1 - a.1).abs()).ceil() as i64).max(1);
        for s in 0..=n {
            let t = s as f64 / n as f64;
            let (x, y) = (a.0 + (b.0 - a.0) * t, a.1 + (b.1 - a.1) * t);
            for dx in 0..width {
                for dy in 0..width {
                    self.put(x.round() as i64 + dx, y.round() as i64 + dy, c);
                }
            }
        }
    }

    fn square(&mut self, p: (f64, f64), r: i64, c: [u8; 3]) {
        for dx in -r..=r {
            for dy in -r..=r {
                self.put(p.0.round() as i64 + dx, p.1.round() as i64 + dy, c);
            }
        }
    }
}

/// The two axes with the largest extent of `pts` (ascending axis order).
fn view_axes(pts: &[Vector3<f64>]) -> (usize, usize) {
    let mut ext = [0.0f64; 3];
    for (a, e) in ext.iter_mut().enumerate() {
        let (lo, hi) = pts.iter().fold((f64::MAX, f64::MIN), |(lo, hi), p| {
            (lo.min(p[a]), hi.max(p[a]))
        });
        *e = if pts.is_empty() { 0.0 } else { hi - lo };
    }
    let drop = (0..3)
        .min_by(|a, b| ext[*a].total_cmp(&ext[*b]))
        .unwrap_or(2);
    let keep: Vec<usize> = (0..3).filter(|a| *a != drop).collect();
    (keep[0], keep[1])
}

/// Writes the plot of `est` (aligned) over `gt` to `path` (PNG).
pub fn top_view(
    est: &[Vector3<f64>],
    gt: &[Vector3<f64>],
    title_path: &Path,
) -> anyhow::Result<()> {
    let (ax, ay) = view_axes(if gt.is_empty() { est } else { gt });
    let all = est.iter().chain(gt.iter());
    let (mut lo, mut hi) = ((f64::MAX, f64::MAX), (f64::MIN, f64::MIN));
    for p in all {
        lo = (lo.0.min(p[ax]), lo.1.min(p[ay]));
        hi = (hi.0.max(p[ax]), hi.1.max(p[ay]));
    }
    anyhow::ensure!(lo.0 <= hi.0, "nothing to plot");
    let span = (hi.0 - lo.0).max(hi.1 - lo.1).max(1e-6);
    let scale = (SIZE as f64 - 2.0 * MARGIN) / span;
    // World up (larger second axis) is image up.
    let to_px = |p: &Vector3<f64>| {
        (
            MARGIN + (p[ax] - lo.0) * scale,
            SIZE as f64 - MARGIN - (p[ay] - lo.1) * scale,
        )
    };
    let mut c = Canvas::new(SIZE, SIZE);
    for (pts, col, w) in [(gt, [150, 150, 150], 3), (est, [220, 30, 30], 2)] {
        for pair in pts.windows(2) {
            c.line(to_px(&pair[0]), to_px(&pair[1]), col, w);
        }
        if let Some(p) = pts.first() {
            c.square(to_px(p), 5, col);
        }
    }
    // Scale bar: the largest 1-2-5 length under a quarter of the plot.
    let target = span / 4.0;
    let mut bar = 10f64.powf(target.log10().floor());
    for m in [2.0, 5.0] {
        if bar * m <= target {
            bar *= m;
        }
    }
    let y = SIZE as f64 - MARGIN / 2.0;
    c.line((MARGIN, y), (MARGIN + bar * scale, y), [0, 0, 0], 2);
    let img = image::RgbImage::from_raw(SIZE, SIZE, c.px)
        .ok_or_else(|| anyhow::anyhow!("canvas size"))?;
    img.save(title_path)?;
    tracing::info!("plot {} (scale bar {bar} m)", title_path.display());
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn axes_follow_the_largest_extent() {
        let pts: Vec<_> = (0..10)
            .map(|i| Vector3::new(i as f64, 0.1, -(i as f64) * 2.0))
            .collect();
        assert_eq!(view_axes(&pts), (0, 2));
    }

    #[test]
    fn writes_a_png() {
        let dir = tempfile::tempdir().unwrap();
        let gt: Vec<_> = (0..50)
            .map(|i| Vector3::new((i as f64 * 0.1).cos(), (i as f64 * 0.1).sin(), 0.0))
            .collect();
        let est: Vec<_> = gt.iter().map(|p| p * 1.05).collect();
        let path = dir.path().join("p.png");
        top_view(&est, &gt, &path).unwrap();
        let img = image::open(&path).unwrap().to_rgb8();
        assert_eq!(img.dimensions(), (SIZE, SIZE));
        assert!(img.pixels().any(|p| p.0 == [220, 30, 30]), "estimate drawn");
        assert!(
            img.pixels().any(|p| p.0 == [150, 150, 150]),
            "ground truth drawn"
        );
    }
}
