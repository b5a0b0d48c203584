//! Convergence plots of `shoal calibrate` (issue 18, after the seed's Fig. 4.5-4.6): one
//! panel per parameter, its estimate over time (red) inside its ±3σ band (light red), and,
//! when known, the reference value (grey) it should reach. Panels are grouped in rows
//! (camera, distortion, time, lever arm, IMU).
use std::path::Path;

use super::canvas::{nice_step, text_width, tick_label, Canvas, Rgb, BLACK, GRID};
use super::EST_COLOUR;

/// The ±3σ band.
const BAND: Rgb = [250, 205, 200];
/// The reference value.
const REFERENCE: Rgb = [90, 90, 90];
/// One panel's size, pixels.
const PANEL: (i64, i64) = (300, 190);
/// Panels per row.
const COLUMNS: i64 = 4;

/// One parameter over time.
#[derive(Debug, Clone, Default)]
pub struct Series {
    /// Its name and unit (`fx [px]`).
    pub name: String,
    /// `(t_s, estimate, σ)` in time order.
    pub points: Vec<(f64, f64, f64)>,
    /// The value it should reach, when known.
    pub reference: Option<f64>,
}

/// A convergence plot: a title and rows of panels.
#[derive(Debug, Clone, Default)]
pub struct ConvergencePlot {
    /// Title line.
    pub title: String,
    /// Rows of panels (a group each, at most [`COLUMNS`] per row).
    pub rows: Vec<Vec<Series>>,
}

/// The y range of a series: its estimates ± 3σ after the first tenth of the run (the
/// start's wide band would flatten the rest), and the reference.
fn y_range(s: &Series) -> (f64, f64) {
    let skip = s.points.len() / 10;
    let (mut lo, mut hi) = (f64::INFINITY, f64::NEG_INFINITY);
    for &(_, v, sd) in &s.points[skip..] {
        lo = lo.min(v - 3.0 * sd);
        hi = hi.max(v + 3.0 * sd);
    }
    if let Some(r) = s.reference {
        lo = lo.min(r);
        hi = hi.max(r);
    }
    if !(lo.is_finite() && hi.is_finite()) {
        return (-1.0, 1.0);
    }
    let pad = ((hi - lo) * 0.08).max(1e-12 + lo.abs() * 1e-9);
    (lo - pad, hi + pad)
}

/// Draws series `s` in the panel whose top-left corner is `(x0, y0)`.
fn draw_panel(c: &mut Canvas, s: &Series, x0: i64, y0: i64) {
    let (pw, ph) = PANEL;
    let (l, t, r, b) = (x0 + 62, y0 + 22, x0 + pw - 10, y0 + ph - 26);
    c.text(x0 + 62, y0 + 6, &s.name, 1, BLACK);
    let (Some(first), Some(last)) = (s.points.first(), s.points.last()) else {
        return;
    };
    let (t0, t1) = (first.0, last.0.max(first.0 + 1e-9));
    let (lo, hi) = y_range(s);
    let px = |t_s: f64| l as f64 + (t_s - t0) / (t1 - t0) * (r - l) as f64;
    let py = |v: f64| b as f64 - ((v - lo) / (hi - lo)).clamp(-0.05, 1.05) * (b - t) as f64;
    let step = nice_step((hi - lo) / 4.0);
    let mut v = (lo / step).ceil() * step;
    while v <= hi {
        let y = py(v);
        c.line((l as f64, y), (r as f64, y), GRID, 1);
        let label = tick_label(v, step);
        c.text(
            l - 4 - text_width(&label, 1),
            y as i64 - 3,
            &label,
            1,
            BLACK,
        );
        v += step;
    }
    for &(t_s, v, sd) in &s.points {
        let x = px(t_s);
        c.line((x, py(v - 3.0 * sd)), (x, py(v + 3.0 * sd)), BAND, 1);
    }
    if let Some(rv) = s.reference {
        c.line((l as f64, py(rv)), (r as f64, py(rv)), REFERENCE, 2);
    }
    for w in s.points.windows(2) {
        c.line(
            (px(w[0].0), py(w[0].1)),
            (px(w[1].0), py(w[1].1)),
            EST_COLOUR,
            1,
        );
    }
    c.frame(l, t, r, b, BLACK);
    let end = format!("{:.0} s", t1 - t0);
    c.text(r - text_width(&end, 1), b + 6, &end, 1, BLACK);
    c.text(l, b + 6, "0", 1, BLACK);
}

/// Renders the plot.
pub fn render_convergence(p: &ConvergencePlot) -> anyhow::Result<image::RgbImage> {
    let rows: Vec<&[Series]> = p
        .rows
        .iter()
        .flat_map(|r| r.chunks(COLUMNS as usize))
        .collect();
    let (pw, ph) = PANEL;
    let mut c = Canvas::new((pw * COLUMNS) as u32, (40 + ph * rows.len() as i64) as u32);
    c.text(12, 12, &p.title, 2, BLACK);
    for (i, row) in rows.iter().enumerate() {
        for (j, s) in row.iter().enumerate() {
            draw_panel(&mut c, s, j as i64 * pw, 40 + i as i64 * ph);
        }
    }
    c.into_image()
}

/// Writes the plot as a PNG at `path`.
pub fn write_convergence(p: &ConvergencePlot, path: &Path) -> anyhow::Result<()> {
    let img = render_convergence(p)?;
    img.save(path)
        .map_err(|e| anyhow::anyhow!("writing {}: {e}", path.display()))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A panel shows the band, the estimate and the reference: each colour is drawn, and
    /// the image grows a row of panels per group row.
    #[test]
    fn panels_show_estimate_band_and_reference() {
        let s = |name: &str| Series {
            name: name.into(),
            points: (0..200)
                .map(|k| {
                    let t = k as f64 * 0.1;
                    (t, 450.0 + 5.0 * (-t).exp(), 5.0 * (-0.2 * t).exp() + 0.3)
                })
                .collect(),
            reference: Some(450.0),
        };
        let p = ConvergencePlot {
            title: "t".into(),
            rows: vec![vec![s("fx [px]"), s("fy [px]")], vec![s("cx [px]")]],
        };
        let img = render_convergence(&p).expect("render");
        assert_eq!(img.height() as i64, 40 + 2 * PANEL.1);
        let has = |c: Rgb| img.pixels().any(|px| px.0 == c);
        assert!(has(BAND) && has(EST_COLOUR) && has(REFERENCE));
    }
}
