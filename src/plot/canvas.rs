//! An RGB pixel canvas with lines, boxes, markers and bitmap text (the plots' only drawing
//! code; no font or drawing dependency).
use super::font::{drop_rows, glyph, GLYPH_H, GLYPH_W};

/// An RGB colour.
pub type Rgb = [u8; 3];

/// Black (text, axes).
pub const BLACK: Rgb = [0, 0, 0];
/// Light grey (grid lines).
pub const GRID: Rgb = [225, 225, 225];

/// A white RGB image being drawn on; pixel (0, 0) is the top-left corner.
pub struct Canvas {
    /// Width, pixels.
    pub w: u32,
    /// Height, pixels.
    pub h: u32,
    px: Vec<u8>,
}

impl Canvas {
    /// A white canvas of `w` × `h` pixels.
    pub fn new(w: u32, h: u32) -> Self {
        Self {
            w,
            h,
            px: vec![255; (w * h * 3) as usize],
        }
    }

    /// Sets pixel (x, y) to `c` (outside the canvas: nothing).
    pub fn put(&mut self, x: i64, y: i64, c: Rgb) {
        if x >= 0 && y >= 0 && (x as u32) < self.w && (y as u32) < self.h {
            let i = ((y as u32 * self.w + x as u32) * 3) as usize;
            self.px[i..i + 3].copy_from_slice(&c);
        }
    }

    /// A line from `a` to `b` of `width` pixels.
    pub fn line(&mut self, a: (f64, f64), b: (f64, f64), c: Rgb, width: i64) {
        let n = ((b.0 - a.0).abs().max((b.1 - a.1).abs()).ceil() as i64).max(1);
        let off = (width - 1) / 2;
        for s in 0..=n {
            let t = s as f64 / n as f64;
            let (x, y) = (a.0 + (b.0 - a.0) * t, a.1 + (b.1 - a.1) * t);
            for dx in 0..width {
                for dy in 0..width {
                    self.put(x.round() as i64 + dx - off, y.round() as i64 + dy - off, c);
                }
            }
        }
    }

    /// A filled rectangle with corners (x0, y0) and (x1, y1) (inclusive).
    pub fn fill(&mut self, x0: i64, y0: i64, x1: i64, y1: i64, c: Rgb) {
        for y in y0.min(y1)..=y0.max(y1) {
            for x in x0.min(x1)..=x0.max(x1) {
                self.put(x, y, c);
            }
        }
    }

    /// The outline of a rectangle (1 pixel).
    pub fn frame(&mut self, x0: i64, y0: i64, x1: i64, y1: i64, c: Rgb) {
        let (a, b) = ((x0 as f64, y0 as f64), (x1 as f64, y1 as f64));
        self.line(a, (b.0, a.1), c, 1);
        self.line((b.0, a.1), b, c, 1);
        self.line(b, (a.0, b.1), c, 1);
        self.line((a.0, b.1), a, c, 1);
    }

    /// A filled square of half-size `r` centred on `p`.
    pub fn square(&mut self, p: (f64, f64), r: i64, c: Rgb) {
        let (x, y) = (p.0.round() as i64, p.1.round() as i64);
        self.fill(x - r, y - r, x + r, y + r, c);
    }

    /// A ring of radius `r` (2 pixels thick) centred on `p`.
    pub fn ring(&mut self, p: (f64, f64), r: f64, c: Rgb) {
        let steps = (r * 8.0).ceil().max(16.0) as usize;
        let at = |k: usize| {
            let a = k as f64 / steps as f64 * std::f64::consts::TAU;
            (p.0 + r * a.cos(), p.1 + r * a.sin())
        };
        for k in 0..steps {
            self.line(at(k), at(k + 1), c, 2);
        }
    }

    /// A filled diamond of half-diagonal `r` centred on `p`.
    pub fn diamond(&mut self, p: (f64, f64), r: i64, c: Rgb) {
        let (x, y) = (p.0.round() as i64, p.1.round() as i64);
        for dy in -r..=r {
            let half = r - dy.abs();
            self.fill(x - half, y + dy, x + half, y + dy, c);
        }
    }

    /// Draws `text` with its top-left corner at (x, y), glyphs scaled `scale`×; returns the
    /// width drawn, pixels.
    pub fn text(&mut self, x: i64, y: i64, text: &str, scale: i64, c: Rgb) -> i64 {
        for (k, ch) in text.chars().enumerate() {
            let gx = x + k as i64 * advance(scale);
            for (row, bits) in glyph(ch).iter().enumerate() {
                let row = row + drop_rows(ch);
                for col in 0..GLYPH_W {
                    if bits & (0x10 >> col) != 0 {
                        let (px, py) = (gx + col as i64 * scale, y + row as i64 * scale);
                        self.fill(px, py, px + scale - 1, py + scale - 1, c);
                    }
                }
            }
        }
        text_width(text, scale)
    }

    /// Draws `text` rotated a quarter turn counter-clockwise (reading upwards), its
    /// bottom-left corner at (x, y).
    pub fn text_up(&mut self, x: i64, y: i64, text: &str, scale: i64, c: Rgb) {
        for (k, ch) in text.chars().enumerate() {
            let gy = y - k as i64 * advance(scale);
            for (row, bits) in glyph(ch).iter().enumerate() {
                let row = row + drop_rows(ch);
                for col in 0..GLYPH_W {
                    if bits & (0x10 >> col) != 0 {
                        let (px, py) = (x + row as i64 * scale, gy - (col as i64 + 1) * scale);
                        self.fill(px, py, px + scale - 1, py + scale - 1, c);
                    }
                }
            }
        }
    }

    /// The image.
    pub fn into_image(self) -> anyhow::Result<image::RgbImage> {
        image::RgbImage::from_raw(self.w, self.h, self.px)
            .ok_or_else(|| anyhow::anyhow!("canvas size"))
    }
}

/// Horizontal distance between glyphs at `scale`, pixels.
pub fn advance(scale: i64) -> i64 {
    (GLYPH_W as i64 + 1) * scale
}

/// Height of a text line at `scale`, pixels.
pub fn text_height(scale: i64) -> i64 {
    GLYPH_H as i64 * scale
}

/// Width of `text` at `scale`, pixels.
pub fn text_width(text: &str, scale: i64) -> i64 {
    (text.chars().count() as i64 * advance(scale) - scale).max(0)
}

/// The largest 1-2-5 × 10^k step not above `target` (`target` > 0).
pub fn nice_step(target: f64) -> f64 {
    let base = 10f64.powf(target.log10().floor());
    [5.0, 2.0, 1.0]
        .into_iter()
        .map(|m| base * m)
        .find(|s| *s <= target * (1.0 + 1e-9))
        .unwrap_or(base)
}

/// `v` printed with as many decimals as `step` needs (`step` a 1-2-5 step).
pub fn tick_label(v: f64, step: f64) -> String {
    let decimals = (-step.log10().floor()).max(0.0) as usize;
    let s = format!("{v:.decimals$}");
    // "-0" and "-0.0" read as 0.
    if s.trim_start_matches('-')
        .chars()
        .all(|c| c == '0' || c == '.')
    {
        s.trim_start_matches('-').to_string()
    } else {
        s
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn steps_are_1_2_5() {
        assert_eq!(nice_step(0.7), 0.5);
        assert_eq!(nice_step(3.0), 2.0);
        assert_eq!(nice_step(1.0), 1.0);
        assert_eq!(nice_step(99.0), 50.0);
        assert_eq!(tick_label(-0.0001, 0.5), "0.0");
        assert_eq!(tick_label(2.5, 0.5), "2.5");
        assert_eq!(tick_label(-20.0, 10.0), "-20");
    }

    #[test]
    fn text_draws_its_glyphs() {
        let mut c = Canvas::new(40, 20);
        assert_eq!(c.text(1, 1, "1m", 2, BLACK), 22);
        let img = c.into_image().unwrap();
        // '1' has its foot row (0x0E) at row 6: pixels 1 + 2..8 of x, y 13..14.
        assert_eq!(img.get_pixel(1 + 2 * 2, 1 + 6 * 2).0, BLACK);
        assert_eq!(img.get_pixel(1, 1).0, [255, 255, 255]);
    }
}
