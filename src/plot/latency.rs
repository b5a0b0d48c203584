//! The latency plot of `shoal bench tracking`: a histogram of the per-frame tracking time
//! with its p50 / p90 / p99 marked, and one bar per stage (mean, with a whisker to the p90).
use std::path::Path;

use super::canvas::{nice_step, text_height, text_width, tick_label, Canvas, Rgb, BLACK, GRID};

/// Histogram bars.
pub const HIST_COLOUR: Rgb = [70, 120, 200];
/// Stage bars.
pub const STAGE_COLOUR: Rgb = [230, 130, 40];
/// Percentile markers of the histogram.
pub const PERCENTILE_COLOUR: Rgb = [200, 30, 30];

/// Image width, pixels.
pub const WIDTH: u32 = 900;
/// Histogram panel: left, top, width, height, pixels.
const HIST: (i64, i64, i64, i64) = (100, 100, 760, 300);
/// Stage panel: left, top, width, row height, pixels.
const STAGES: (i64, i64, i64, i64) = (230, 500, 630, 34);
/// Histogram bins.
const BINS: usize = 40;

/// One stage's figures, ms.
#[derive(Debug, Clone)]
pub struct Stage {
    /// Stage name.
    pub name: String,
    /// Mean, ms.
    pub mean_ms: f64,
    /// 90th percentile, ms.
    pub p90_ms: f64,
}

/// What the latency plot shows.
#[derive(Debug, Clone, Default)]
pub struct LatencyPlot {
    /// First title line.
    pub title: String,
    /// Second title line.
    pub subtitle: String,
    /// Per-frame tracking time, ms.
    pub per_frame_ms: Vec<f64>,
    /// Per-stage figures, in pipeline order.
    pub stages: Vec<Stage>,
}

/// The `q` quantile of sorted `v` (nearest rank).
fn quantile(sorted: &[f64], q: f64) -> f64 {
    if sorted.is_empty() {
        return 0.0;
    }
    let k = ((q * sorted.len() as f64).ceil() as usize).clamp(1, sorted.len());
    sorted[k - 1]
}

/// About `n` 1-2-5 ticks over 0..=`max`: the step and each (value, label).
fn ticks(max: f64, n: f64) -> (f64, Vec<(f64, String)>) {
    let step = nice_step(max.max(1e-9) / n);
    let k = (max / step).floor() as i64;
    (
        step,
        (0..=k)
            .map(|i| (i as f64 * step, tick_label(i as f64 * step, step)))
            .collect(),
    )
}

fn draw_histogram(c: &mut Canvas, per_frame_ms: &[f64]) {
    let (l, t, w, h) = HIST;
    let mut sorted = per_frame_ms.to_vec();
    sorted.sort_by(f64::total_cmp);
    let top_ms = sorted.last().copied().unwrap_or(1.0).max(1e-3) * 1.05;
    let mut counts = [0usize; BINS];
    for v in &sorted {
        counts[((v / top_ms * BINS as f64) as usize).min(BINS - 1)] += 1;
    }
    let peak = counts.iter().copied().max().unwrap_or(1).max(1) as f64 * 1.1;
    let x_of = |ms: f64| l as f64 + ms / top_ms * w as f64;
    let y_of = |n: f64| (t + h) as f64 - n / peak * h as f64;
    let (_, yt) = ticks(peak, 4.0);
    for (n, label) in yt.iter().filter(|(n, _)| n.fract() == 0.0) {
        let y = y_of(*n);
        c.line((l as f64, y), ((l + w) as f64, y), GRID, 1);
        let lw = text_width(label, 2);
        c.text(
            l - 10 - lw,
            y.round() as i64 - text_height(2) / 2,
            label,
            2,
            BLACK,
        );
    }
    let bin_px = w as f64 / BINS as f64;
    for (b, n) in counts.iter().enumerate().filter(|(_, n)| **n > 0) {
        let x0 = (l as f64 + b as f64 * bin_px).round() as i64;
        let x1 = (l as f64 + (b + 1) as f64 * bin_px).round() as i64 - 2;
        c.fill(
            x0 + 1,
            y_of(*n as f64).round() as i64,
            x1,
            t + h,
            HIST_COLOUR,
        );
    }
    for (q, name) in [(0.5, "p50"), (0.9, "p90"), (0.99, "p99")] {
        let v = quantile(&sorted, q);
        let x = x_of(v);
        c.line((x, t as f64), (x, (t + h) as f64), PERCENTILE_COLOUR, 2);
        let label = format!("{name} {v:.1} ms");
        let row = [0.5, 0.9, 0.99].iter().position(|p| *p == q).unwrap_or(0) as i64;
        let lw = text_width(&label, 2);
        // Right of the line, or left of it near the right edge.
        let lx = if x as i64 + 6 + lw < l + w {
            x.round() as i64 + 6
        } else {
            x.round() as i64 - 6 - lw
        };
        let ly = t + 8 + row * 22;
        c.fill(
            lx - 2,
            ly - 2,
            lx + lw + 2,
            ly + text_height(2) + 2,
            [255, 255, 255],
        );
        c.text(lx, ly, &label, 2, PERCENTILE_COLOUR);
    }
    let (_, xt) = ticks(top_ms, 6.0);
    for (ms, label) in &xt {
        let x = x_of(*ms);
        c.line((x, (t + h) as f64), (x, (t + h + 6) as f64), BLACK, 1);
        let lw = text_width(label, 2);
        c.text(x.round() as i64 - lw / 2, t + h + 10, label, 2, BLACK);
    }
    c.frame(l, t, l + w, t + h, BLACK);
    let name = "tracking time per frame [ms]";
    c.text(
        l + w / 2 - text_width(name, 2) / 2,
        t + h + 34,
        name,
        2,
        BLACK,
    );
    c.text_up(
        14,
        t + h / 2 + text_width("frames", 2) / 2,
        "frames",
        2,
        BLACK,
    );
}

fn draw_stages(c: &mut Canvas, stages: &[Stage]) {
    let (l, t, w, row) = STAGES;
    let max_ms = stages
        .iter()
        .map(|s| s.p90_ms.max(s.mean_ms))
        .fold(1e-3, f64::max)
        * 1.05;
    let x_of = |ms: f64| l as f64 + ms / max_ms * w as f64;
    let bottom = t + row * stages.len() as i64;
    let (_, xt) = ticks(max_ms, 6.0);
    for (ms, label) in &xt {
        let x = x_of(*ms);
        c.line((x, t as f64), (x, bottom as f64), GRID, 1);
        c.line((x, bottom as f64), (x, (bottom + 6) as f64), BLACK, 1);
        let lw = text_width(label, 2);
        c.text(x.round() as i64 - lw / 2, bottom + 10, label, 2, BLACK);
    }
    for (k, s) in stages.iter().enumerate() {
        let y = t + row * k as i64;
        let lw = text_width(&s.name, 2);
        c.text(
            l - 10 - lw,
            y + row / 2 - text_height(2) / 2,
            &s.name,
            2,
            BLACK,
        );
        let x1 = x_of(s.mean_ms).round() as i64;
        c.fill(l, y + 6, x1.max(l + 1), y + row - 6, STAGE_COLOUR);
        let xp = x_of(s.p90_ms);
        let cy = (y + row / 2) as f64;
        c.line((x1 as f64, cy), (xp, cy), BLACK, 1);
        c.line((xp, cy - 6.0), (xp, cy + 6.0), BLACK, 2);
        let label = format!("{:.2} / {:.2}", s.mean_ms, s.p90_ms);
        let lw = text_width(&label, 2);
        let ty = y + row / 2 - text_height(2) / 2;
        if xp as i64 + 8 + lw < WIDTH as i64 {
            c.text(xp as i64 + 8, ty, &label, 2, BLACK);
        } else {
            // No room right of the whisker: inside the bar, in white.
            c.text(l + 6, ty, &label, 2, [255, 255, 255]);
        }
    }
    c.line((l as f64, t as f64), (l as f64, bottom as f64), BLACK, 1);
    c.line(
        (l as f64, bottom as f64),
        ((l + w) as f64, bottom as f64),
        BLACK,
        1,
    );
    let name = "per stage: mean (bar) and p90 (whisker) [ms]";
    c.text(
        l + w / 2 - text_width(name, 2) / 2,
        bottom + 34,
        name,
        2,
        BLACK,
    );
}

/// Renders the plot.
pub fn render_latency(p: &LatencyPlot) -> anyhow::Result<image::RgbImage> {
    anyhow::ensure!(!p.per_frame_ms.is_empty(), "no frames to plot");
    let height = STAGES.1 + STAGES.3 * p.stages.len() as i64 + 70;
    let mut c = Canvas::new(WIDTH, height as u32);
    c.text(20, 12, &p.title, 2, BLACK);
    c.text(20, 36, &p.subtitle, 2, BLACK);
    draw_histogram(&mut c, &p.per_frame_ms);
    draw_stages(&mut c, &p.stages);
    c.into_image()
}

/// Writes the plot to `path` (PNG).
pub fn write_latency(p: &LatencyPlot, path: &Path) -> anyhow::Result<()> {
    render_latency(p)?.save(path)?;
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn latency_plot_has_histogram_percentiles_and_stage_bars() {
        // 100 frames: 90 at 10-19 ms, 10 slow ones at 40 ms.
        let per_frame_ms: Vec<f64> = (0..100)
            .map(|i| if i < 90 { 10.0 + (i % 10) as f64 } else { 40.0 })
            .collect();
        let stages = ["pyramid", "detect", "describe"]
            .iter()
            .enumerate()
            .map(|(k, n)| Stage {
                name: n.to_string(),
                mean_ms: 2.0 * (k + 1) as f64,
                p90_ms: 3.0 * (k + 1) as f64,
            })
            .collect();
        let p = LatencyPlot {
            title: "bench tracking".into(),
            subtitle: "100 frames".into(),
            per_frame_ms,
            stages,
        };
        let img = render_latency(&p).unwrap();
        let count = |c: Rgb, y: std::ops::Range<u32>| {
            img.enumerate_pixels()
                .filter(|(_, py, px)| y.contains(py) && px.0 == c)
                .count()
        };
        let (t, h) = (HIST.1 as u32, HIST.3 as u32);
        assert!(count(HIST_COLOUR, t..t + h) > 2000, "histogram bars");
        assert!(count(PERCENTILE_COLOUR, t..t + h) > 500, "percentile lines");
        assert!(count(BLACK, 12..26) > 50, "title");
        // Three stage bars, longer for the slower stage.
        let bar_len = |k: u32| {
            // Above the value labels (drawn inside a bar without room right of it).
            let y = STAGES.1 as u32 + STAGES.3 as u32 * k + 7;
            (0..WIDTH)
                .filter(|x| img.get_pixel(*x, y).0 == STAGE_COLOUR)
                .count()
        };
        let (a, b, c) = (bar_len(0), bar_len(1), bar_len(2));
        assert!(a > 20 && b > a && c > b, "stage bars {a} {b} {c}");
        assert!(
            (c as f64 / a as f64 - 3.0).abs() < 0.1,
            "bars proportional to the mean"
        );
    }
}
