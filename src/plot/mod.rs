//! Plots a person can read, as PNG: the top view of an estimated trajectory over its ground
//! truth (after alignment) with loop closures and map merges marked, and the latency plot of
//! `shoal bench tracking` ([`latency`]). Text is drawn with our own 5×7 bitmap font
//! ([`font`]), so plotting needs no font file nor drawing dependency.
//!
//! The trajectory view plane is spanned by the two axes along which the ground truth extends
//! most (x-y for EuRoC / synthetic z-up worlds, x-z for KITTI's camera frame), with equal
//! scale on both, a grid with tick labels in metres, a 1-2-5 scale bar and a legend.
pub mod canvas;
pub mod convergence;
pub mod events;
pub mod font;
pub mod latency;

use std::path::Path;

use nalgebra::Vector3;

use canvas::{nice_step, text_height, text_width, tick_label, Canvas, Rgb, BLACK, GRID};

/// Ground truth: dark grey, 3 pixels wide.
pub const GT_COLOUR: Rgb = [90, 90, 90];
/// The estimate: red, 2 pixels wide.
pub const EST_COLOUR: Rgb = [220, 40, 30];
/// Loop closures: green rings (and a line to the matched place).
pub const LOOP_COLOUR: Rgb = [0, 150, 60];
/// Map merges: blue diamonds.
pub const MERGE_COLOUR: Rgb = [30, 90, 230];

/// Image width, pixels.
pub const WIDTH: u32 = 900;
/// Image height, pixels.
pub const HEIGHT: u32 = 930;
/// The square plot area: left and top edge, side, pixels.
const PLOT: (i64, i64, i64) = (100, 80, 770);

/// What happened at a marked place.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum MarkKind {
    /// A pose-graph correction (loop closed within one map).
    Loop,
    /// A map merge (two maps joined).
    Merge,
}

/// A loop closure or merge at a place of the estimate.
#[derive(Debug, Clone)]
pub struct Mark {
    /// Loop or merge.
    pub kind: MarkKind,
    /// Where on the (aligned) estimate: the query keyframe.
    pub at: Vector3<f64>,
    /// The matched keyframe, when it is on the same trajectory.
    pub to: Option<Vector3<f64>>,
}

/// What a trajectory plot shows.
#[derive(Debug, Clone, Default)]
pub struct TrajectoryPlot<'a> {
    /// First title line (dataset, client, which trajectory).
    pub title: String,
    /// Second title line (ATE, alignment).
    pub subtitle: String,
    /// Estimated positions after alignment, in time order.
    pub est: &'a [Vector3<f64>],
    /// Ground-truth positions, in time order.
    pub gt: &'a [Vector3<f64>],
    /// Loop closures and merges.
    pub marks: Vec<Mark>,
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

/// World (metres, view axes) ↔ pixels of the plot area.
struct View {
    ax: usize,
    ay: usize,
    /// World coordinates of the plot area's bottom-left corner, m.
    x0: f64,
    y0: f64,
    /// Side of the plot area, m.
    span: f64,
}

impl View {
    fn fit(pts: &[&Vector3<f64>], ax: usize, ay: usize) -> anyhow::Result<Self> {
        let (mut lo, mut hi) = ((f64::MAX, f64::MAX), (f64::MIN, f64::MIN));
        for p in pts {
            lo = (lo.0.min(p[ax]), lo.1.min(p[ay]));
            hi = (hi.0.max(p[ax]), hi.1.max(p[ay]));
        }
        anyhow::ensure!(lo.0 <= hi.0 && lo.0.is_finite(), "nothing to plot");
        // 6% margin around the data.
        let span = (hi.0 - lo.0).max(hi.1 - lo.1).max(1e-6) * 1.12;
        let (cx, cy) = ((lo.0 + hi.0) / 2.0, (lo.1 + hi.1) / 2.0);
        Ok(Self {
            ax,
            ay,
            x0: cx - span / 2.0,
            y0: cy - span / 2.0,
            span,
        })
    }

    fn scale(&self) -> f64 {
        PLOT.2 as f64 / self.span
    }

    /// Pixel of world value `x` along the horizontal axis.
    fn px_x(&self, x: f64) -> f64 {
        PLOT.0 as f64 + (x - self.x0) * self.scale()
    }

    /// Pixel of world value `y` along the vertical axis (world up is image up).
    fn px_y(&self, y: f64) -> f64 {
        (PLOT.1 + PLOT.2) as f64 - (y - self.y0) * self.scale()
    }

    fn px(&self, p: &Vector3<f64>) -> (f64, f64) {
        (self.px_x(p[self.ax]), self.px_y(p[self.ay]))
    }
}

/// Grid, frame, tick labels in metres and axis names.
fn draw_axes(c: &mut Canvas, v: &View) {
    let (l, t, s) = PLOT;
    let step = nice_step(v.span / 5.0);
    let first = |lo: f64| (lo / step).ceil() as i64;
    let last = |lo: f64| ((lo + v.span) / step).floor() as i64;
    for k in first(v.x0)..=last(v.x0) {
        let x = v.px_x(k as f64 * step);
        c.line((x, t as f64), (x, (t + s) as f64), GRID, 1);
        c.line((x, (t + s) as f64), (x, (t + s + 6) as f64), BLACK, 1);
        let label = tick_label(k as f64 * step, step);
        let w = text_width(&label, 2);
        c.text(x.round() as i64 - w / 2, t + s + 10, &label, 2, BLACK);
    }
    for k in first(v.y0)..=last(v.y0) {
        let y = v.px_y(k as f64 * step);
        c.line((l as f64, y), ((l + s) as f64, y), GRID, 1);
        c.line(((l - 6) as f64, y), (l as f64, y), BLACK, 1);
        let label = tick_label(k as f64 * step, step);
        let w = text_width(&label, 2);
        c.text(
            l - 10 - w,
            y.round() as i64 - text_height(2) / 2,
            &label,
            2,
            BLACK,
        );
    }
    c.frame(l, t, l + s, t + s, BLACK);
    let name = |a: usize| format!("{} [m]", ["x", "y", "z"][a]);
    let xname = name(v.ax);
    let w = text_width(&xname, 2);
    c.text(l + s / 2 - w / 2, t + s + 36, &xname, 2, BLACK);
    let yname = name(v.ay);
    let w = text_width(&yname, 2);
    c.text_up(14, t + s / 2 + w / 2, &yname, 2, BLACK);
}

/// A polyline with a start square.
fn draw_series(c: &mut Canvas, v: &View, pts: &[Vector3<f64>], col: Rgb, width: i64) {
    for pair in pts.windows(2) {
        c.line(v.px(&pair[0]), v.px(&pair[1]), col, width);
    }
    if let Some(p) = pts.first() {
        c.square(v.px(p), 5, col);
    }
}

/// The symbol of a mark kind at `p`.
fn draw_symbol(c: &mut Canvas, kind: MarkKind, p: (f64, f64)) {
    match kind {
        MarkKind::Loop => c.ring(p, 9.0, LOOP_COLOUR),
        MarkKind::Merge => c.diamond(p, 8, MERGE_COLOUR),
    }
}

fn draw_marks(c: &mut Canvas, v: &View, marks: &[Mark]) {
    for m in marks {
        if let Some(to) = &m.to {
            let col = match m.kind {
                MarkKind::Loop => LOOP_COLOUR,
                MarkKind::Merge => MERGE_COLOUR,
            };
            c.line(v.px(&m.at), v.px(to), col, 1);
            c.square(v.px(to), 3, col);
        }
        draw_symbol(c, m.kind, v.px(&m.at));
    }
}

/// Number of the points of `pts` (pixels) inside the box.
fn points_in(pts: &[(f64, f64)], x0: i64, y0: i64, x1: i64, y1: i64) -> usize {
    let (x0, y0, x1, y1) = (x0 as f64, y0 as f64, x1 as f64, y1 as f64);
    pts.iter()
        .filter(|p| p.0 >= x0 && p.0 <= x1 && p.1 >= y0 && p.1 <= y1)
        .count()
}

/// The corner box (`w` × `h`, 10 pixels inside the plot area) covering the fewest of `pts`;
/// returns its top-left corner.
fn free_corner(pts: &[(f64, f64)], w: i64, h: i64) -> (i64, i64) {
    let (l, t, s) = PLOT;
    let corners = [
        (l + s - 10 - w, t + 10),
        (l + 10, t + 10),
        (l + s - 10 - w, t + s - 10 - h),
        (l + 10, t + s - 10 - h),
    ];
    corners
        .into_iter()
        .min_by_key(|(x, y)| points_in(pts, *x, *y, x + w, y + h))
        .unwrap_or(corners[0])
}

/// Legend entries: ground truth, estimate, loops and merges with their counts.
fn draw_legend(c: &mut Canvas, p: &TrajectoryPlot, pts: &[(f64, f64)]) -> (i64, i64) {
    let loops = p.marks.iter().filter(|m| m.kind == MarkKind::Loop).count();
    let merges = p.marks.len() - loops;
    let entries = [
        ("ground truth".to_string(), None),
        ("estimate".to_string(), None),
        (format!("loop closure ({loops})"), Some(MarkKind::Loop)),
        (format!("map merge ({merges})"), Some(MarkKind::Merge)),
    ];
    let w = 60
        + entries
            .iter()
            .map(|e| text_width(&e.0, 2))
            .max()
            .unwrap_or(0);
    let h = 12 + 26 * entries.len() as i64;
    let (x, y) = free_corner(pts, w, h);
    c.fill(x, y, x + w, y + h, [255, 255, 255]);
    c.frame(x, y, x + w, y + h, BLACK);
    for (k, (label, kind)) in entries.iter().enumerate() {
        let cy = y + 19 + 26 * k as i64;
        let sw = (x + 10, x + 44);
        match (k, kind) {
            (0, _) => c.line(
                (sw.0 as f64, cy as f64),
                (sw.1 as f64, cy as f64),
                GT_COLOUR,
                3,
            ),
            (1, _) => c.line(
                (sw.0 as f64, cy as f64),
                (sw.1 as f64, cy as f64),
                EST_COLOUR,
                2,
            ),
            (_, Some(kind)) => draw_symbol(c, *kind, ((sw.0 + sw.1) as f64 / 2.0, cy as f64)),
            _ => {}
        }
        c.text(x + 52, cy - text_height(2) / 2, label, 2, BLACK);
    }
    (x, y)
}

/// A labelled 1-2-5 scale bar (about a fifth of the plot) in the free bottom corner.
fn draw_scale_bar(c: &mut Canvas, v: &View, pts: &[(f64, f64)], legend: (i64, i64)) {
    let bar_m = nice_step(v.span / 5.0);
    let bar_px = (bar_m * v.scale()).round() as i64;
    let label = format!("{} m", tick_label(bar_m, bar_m));
    let (w, h) = (bar_px.max(text_width(&label, 2)) + 20, 44);
    let (l, t, s) = PLOT;
    let mut corner = free_corner(pts, w, h);
    if corner.1 == t + 10 || corner == legend {
        // Only the bottom corners (the legend prefers a top one).
        let left = (l + 10, t + s - 10 - h);
        let right = (l + s - 10 - w, t + s - 10 - h);
        corner = if points_in(pts, left.0, left.1, left.0 + w, left.1 + h)
            <= points_in(pts, right.0, right.1, right.0 + w, right.1 + h)
        {
            left
        } else {
            right
        };
    }
    let (x, y) = corner;
    c.fill(x, y, x + w, y + h, [255, 255, 255]);
    c.text(x + 10, y + 6, &label, 2, BLACK);
    let by = (y + 32) as f64;
    c.line(
        ((x + 10) as f64, by),
        ((x + 10 + bar_px) as f64, by),
        BLACK,
        3,
    );
    for end in [x + 10, x + 10 + bar_px] {
        c.line((end as f64, by - 6.0), (end as f64, by + 6.0), BLACK, 2);
    }
}

/// Renders the plot.
pub fn render_trajectory(p: &TrajectoryPlot) -> anyhow::Result<image::RgbImage> {
    let (ax, ay) = view_axes(if p.gt.is_empty() { p.est } else { p.gt });
    let all: Vec<&Vector3<f64>> = p.est.iter().chain(p.gt.iter()).collect();
    let v = View::fit(&all, ax, ay)?;
    let mut c = Canvas::new(WIDTH, HEIGHT);
    draw_axes(&mut c, &v);
    draw_series(&mut c, &v, p.gt, GT_COLOUR, 3);
    draw_series(&mut c, &v, p.est, EST_COLOUR, 2);
    draw_marks(&mut c, &v, &p.marks);
    let pts: Vec<(f64, f64)> = all.iter().map(|q| v.px(q)).collect();
    let legend = draw_legend(&mut c, p, &pts);
    draw_scale_bar(&mut c, &v, &pts, legend);
    c.text(20, 12, &p.title, 2, BLACK);
    c.text(20, 36, &p.subtitle, 2, BLACK);
    c.into_image()
}

/// Writes the plot to `path` (PNG).
pub fn write_trajectory(p: &TrajectoryPlot, path: &Path) -> anyhow::Result<()> {
    render_trajectory(p)?.save(path)?;
    tracing::info!("plot {}", path.display());
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

    fn count(
        img: &image::RgbImage,
        x: std::ops::Range<u32>,
        y: std::ops::Range<u32>,
        c: Rgb,
    ) -> usize {
        y.flat_map(|y| x.clone().map(move |x| (x, y)))
            .filter(|(x, y)| img.get_pixel(*x, *y).0 == c)
            .count()
    }

    /// A circle (ground truth) and the estimate 5% larger, with one loop and one merge: the
    /// title, the legend, tick labels, the scale bar and both series are drawn, in colours
    /// far apart.
    #[test]
    fn trajectory_plot_has_title_legend_axes_and_marks() {
        let gt: Vec<_> = (0..200)
            .map(|i| {
                Vector3::new(
                    10.0 * (i as f64 * 0.03).cos(),
                    10.0 * (i as f64 * 0.03).sin(),
                    0.5,
                )
            })
            .collect();
        let est: Vec<_> = gt.iter().map(|p| p * 1.05).collect();
        let marks = vec![
            Mark {
                kind: MarkKind::Loop,
                at: est[150],
                to: Some(est[10]),
            },
            Mark {
                kind: MarkKind::Merge,
                at: est[100],
                to: None,
            },
        ];
        let plot = TrajectoryPlot {
            title: "loop - client 0 - trajectory".into(),
            subtitle: "ATE 0.123 m (0.5%), Sim(3) alignment".into(),
            est: &est,
            gt: &gt,
            marks,
        };
        let img = render_trajectory(&plot).unwrap();
        assert_eq!(img.dimensions(), (WIDTH, HEIGHT));
        let dist = |a: Rgb, b: Rgb| {
            (0..3)
                .map(|i| (a[i] as i32 - b[i] as i32).abs())
                .sum::<i32>()
        };
        assert!(
            dist(GT_COLOUR, EST_COLOUR) > 150,
            "series colours too close"
        );
        // Title band: both lines of text.
        let line1 = count(&img, 0..WIDTH, 12..26, BLACK);
        let line2 = count(&img, 0..WIDTH, 36..50, BLACK);
        assert!(line1 > 150 && line2 > 150, "title pixels {line1} / {line2}");
        // Both series inside the plot area.
        let (l, t, s) = (PLOT.0 as u32, PLOT.1 as u32, PLOT.2 as u32);
        assert!(count(&img, l..l + s, t..t + s, GT_COLOUR) > 1000);
        assert!(count(&img, l..l + s, t..t + s, EST_COLOUR) > 1000);
        assert!(
            count(&img, l..l + s, t..t + s, LOOP_COLOUR) > 50,
            "loop marked"
        );
        assert!(
            count(&img, l..l + s, t..t + s, MERGE_COLOUR) > 50,
            "merge marked"
        );
        // Tick labels below and left of the plot area.
        assert!(
            count(&img, l..l + s, t + s + 10..t + s + 24, BLACK) > 100,
            "x ticks"
        );
        assert!(count(&img, 30..l - 8, t..t + s, BLACK) > 100, "y ticks");
        // The legend box: a framed white box whose swatches are the two series colours.
        let legend = img
            .enumerate_pixels()
            .filter(|(x, y, px)| {
                px.0 == GT_COLOUR
                    && *x < l + s
                    && *y > t
                    && img.get_pixel(*x + 20, *y).0 == GT_COLOUR
                    && img.get_pixel(*x, *y + 26).0 == EST_COLOUR
            })
            .count();
        assert!(legend > 0, "legend swatches (ground truth above estimate)");
    }
}
