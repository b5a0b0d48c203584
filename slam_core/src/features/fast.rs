//! FAST-9 corner detection with per-cell threshold fallback and 3x3 non-maximum suppression.
//!
//! The score of a pixel `p` is the largest `t` such that 9 contiguous pixels of the radius-3
//! Bresenham circle are all brighter than `p + t` or all darker than `p - t` (minus one, it is
//! `max over arcs of min over the arc of |I_k - p|` with the sign fixed per arc). A pixel is a
//! corner at threshold `t` iff its score is `> t`. Computing the score directly with saturating
//! `u8` arithmetic gives both the test and the response in one branch-free pass that the compiler
//! vectorises over a block of 32 pixels; a cheap test on the four compass pixels (an arc of 9
//! always holds two consecutive ones) skips blocks with no possible corner.

use super::simd::dispatch;

/// Pixels processed together by the vectorised kernel (also the width of a detection cell).
pub(crate) const BLOCK: usize = 32;
/// Height of a detection cell, in rows.
pub(crate) const CELL_ROWS: usize = 32;

/// The 16 circle offsets `(dx, dy)`, clockwise from the top.
pub(crate) const CIRCLE: [(isize, isize); 16] = [
    (0, -3),
    (1, -3),
    (2, -2),
    (3, -1),
    (3, 0),
    (3, 1),
    (2, 2),
    (1, 3),
    (0, 3),
    (-1, 3),
    (-2, 2),
    (-3, 1),
    (-3, 0),
    (-3, -1),
    (-2, -2),
    (-1, -3),
];

/// A FAST corner on one pyramid level (level pixel coordinates).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) struct Candidate {
    /// Column.
    pub x: u16,
    /// Row.
    pub y: u16,
    /// FAST score (> the threshold used in its cell).
    pub score: u8,
}

/// Max over the 16 arcs of 9 contiguous values of the min over the arc.
#[inline(always)]
fn arc9_max(v: &[u8; 16]) -> u8 {
    let mut m2 = [0u8; 16];
    for k in 0..16 {
        m2[k] = v[k].min(v[(k + 1) & 15]);
    }
    let mut m4 = [0u8; 16];
    for k in 0..16 {
        m4[k] = m2[k].min(m2[(k + 2) & 15]);
    }
    let mut best = 0u8;
    for k in 0..16 {
        let m8 = m4[k].min(m4[(k + 4) & 15]);
        best = best.max(m8.min(v[(k + 8) & 15]));
    }
    best
}

/// FAST score of pixel `p` given its 16 circle values.
#[inline(always)]
fn score_from_circle(p: u8, c: &[u8; 16]) -> u8 {
    let mut bright = [0u8; 16];
    let mut dark = [0u8; 16];
    for k in 0..16 {
        bright[k] = c[k].saturating_sub(p);
        dark[k] = p.saturating_sub(c[k]);
    }
    arc9_max(&bright).max(arc9_max(&dark))
}

/// FAST score at `(x, y)` (scalar reference; needs a 3-pixel margin).
pub(crate) fn score_at(img: &[u8], stride: usize, x: usize, y: usize) -> u8 {
    let at = |dx: isize, dy: isize| {
        let xx = (x as isize + dx) as usize;
        let yy = (y as isize + dy) as usize;
        img[yy * stride + xx]
    };
    let mut c = [0u8; 16];
    for (k, &(dx, dy)) in CIRCLE.iter().enumerate() {
        c[k] = at(dx, dy);
    }
    score_from_circle(at(0, 0), &c)
}

/// Scores of the `BLOCK` pixels `(bx..bx + BLOCK, y)`, zero where not `> t`.
///
/// `rows[j]` is row `y + j - 3` starting at column `bx - 3`. Returns whether any score is `> t`.
#[inline(always)]
fn block_scores(rows: &[&[u8; BLOCK + 6]; 7], t: u8, out: &mut [u8; BLOCK]) -> bool {
    let [r0, r1, r2, r3, r4, r5, r6] = *rows;
    // Compass test: a corner at `t` has two consecutive compass pixels beyond `t`.
    let mut any = 0u8;
    for i in 0..BLOCK {
        let p = r3[i + 3];
        let (n, e, s, w) = (r0[i + 3], r3[i + 6], r6[i + 3], r3[i]);
        let bn = n.saturating_sub(p);
        let be = e.saturating_sub(p);
        let bs = s.saturating_sub(p);
        let bw = w.saturating_sub(p);
        let dn = p.saturating_sub(n);
        let de = p.saturating_sub(e);
        let ds = p.saturating_sub(s);
        let dw = p.saturating_sub(w);
        let b = bn.min(be).max(be.min(bs)).max(bs.min(bw)).max(bw.min(bn));
        let d = dn.min(de).max(de.min(ds)).max(ds.min(dw)).max(dw.min(dn));
        any |= (b.max(d) > t) as u8;
    }
    if any == 0 {
        *out = [0; BLOCK];
        return false;
    }
    let mut found = 0u8;
    for i in 0..BLOCK {
        let c = [
            r0[i + 3],
            r0[i + 4],
            r1[i + 5],
            r2[i + 6],
            r3[i + 6],
            r4[i + 6],
            r5[i + 5],
            r6[i + 4],
            r6[i + 3],
            r6[i + 2],
            r5[i + 1],
            r4[i],
            r3[i],
            r2[i],
            r1[i + 1],
            r0[i + 2],
        ];
        let s = score_from_circle(r3[i + 3], &c);
        let keep = s > t;
        found |= keep as u8;
        out[i] = if keep { s } else { 0 };
    }
    found != 0
}

/// The 7 row windows around `(bx, y)` for [`block_scores`].
#[inline(always)]
fn block_rows(img: &[u8], stride: usize, bx: usize, y: usize) -> Option<[&[u8; BLOCK + 6]; 7]> {
    let row = |j: usize| -> Option<&[u8; BLOCK + 6]> {
        let start = (y + j - 3) * stride + bx - 3;
        img.get(start..)?.first_chunk::<{ BLOCK + 6 }>()
    };
    Some([
        row(0)?,
        row(1)?,
        row(2)?,
        row(3)?,
        row(4)?,
        row(5)?,
        row(6)?,
    ])
}

/// Scores of row `y`, columns `x0..x1` (`x1 - x0 <= BLOCK`), thresholded at `t`, written to
/// `score[y * stride + x]`. Returns whether any is `> t`.
#[inline(always)]
#[allow(clippy::too_many_arguments)]
fn score_span(
    img: &[u8],
    stride: usize,
    w: usize,
    y: usize,
    x0: usize,
    x1: usize,
    t: u8,
    score: &mut [u8],
) -> bool {
    // The block starts at x0, or ends at the last usable column when x0 is too close to it.
    let bx = x0.min(w.saturating_sub(3 + BLOCK)).max(3);
    let mut tmp = [0u8; BLOCK];
    let mut found = false;
    if bx + BLOCK + 3 <= w && bx <= x0 {
        if let Some(rows) = block_rows(img, stride, bx, y) {
            found = block_scores(&rows, t, &mut tmp);
            let dst = &mut score[y * stride + x0..y * stride + x1];
            dst.copy_from_slice(&tmp[x0 - bx..x1 - bx]);
            return found && dst.iter().any(|&s| s != 0);
        }
    }
    // Narrow image: scalar path.
    for x in x0..x1 {
        let s = score_at(img, stride, x, y);
        let v = if s > t { s } else { 0 };
        found |= v != 0;
        score[y * stride + x] = v;
    }
    found
}

/// Detection parameters of one level.
#[derive(Debug, Clone, Copy)]
pub(crate) struct FastConfig {
    /// Margin (pixels) from the image edge where no corner is reported.
    pub border: usize,
    /// Threshold used first in every cell.
    pub th_ini: u8,
    /// Threshold used in cells with no corner at `th_ini`.
    pub th_min: u8,
}

/// Detects FAST corners of a `w` x `h` level (rows `stride` apart) into `out` (cleared first).
///
/// `score` is scratch of at least `h * stride` bytes. Corners lie in
/// `[border, w - border) x [border, h - border)`, on a grid of `BLOCK` x `CELL_ROWS` cells each
/// thresholded at `th_ini`, or `th_min` when it had no corner at `th_ini`; then a 3x3
/// non-maximum suppression keeps strict local maxima (ties go to the first in raster order).
pub(crate) fn detect(
    img: &[u8],
    stride: usize,
    w: usize,
    h: usize,
    cfg: FastConfig,
    score: &mut [u8],
    out: &mut Vec<Candidate>,
) {
    out.clear();
    detect_cells(img, stride, w, h, cfg, score, out);
}

dispatch! {
    /// Scoring over the cells, then suppression (see [`detect`]).
    fn detect_cells(
        img: &[u8],
        stride: usize,
        w: usize,
        h: usize,
        cfg: FastConfig,
        score: &mut [u8],
        out: &mut Vec<Candidate>,
    ) => detect_cells_impl
}

#[inline(always)]
fn detect_cells_impl(
    img: &[u8],
    stride: usize,
    w: usize,
    h: usize,
    cfg: FastConfig,
    score: &mut [u8],
    out: &mut Vec<Candidate>,
) {
    let b = cfg.border.max(3);
    if w < 2 * b + 1 || h < 2 * b + 1 || score.len() < h * stride || img.len() < h * stride {
        return;
    }
    let (ax0, ax1, ay0, ay1) = (b, w - b, b, h - b);
    let mut cy0 = ay0;
    while cy0 < ay1 {
        let cy1 = (cy0 + CELL_ROWS).min(ay1);
        let mut cx0 = ax0;
        while cx0 < ax1 {
            let cx1 = (cx0 + BLOCK).min(ax1);
            let mut found = false;
            for y in cy0..cy1 {
                found |= score_span(img, stride, w, y, cx0, cx1, cfg.th_ini, score);
            }
            if !found && cfg.th_min < cfg.th_ini {
                for y in cy0..cy1 {
                    score_span(img, stride, w, y, cx0, cx1, cfg.th_min, score);
                }
            }
            cx0 = cx1;
        }
        cy0 = cy1;
    }
    // Zero the ring around the area so that suppression can read one pixel outside it.
    for x in ax0 - 1..=ax1 {
        score[(ay0 - 1) * stride + x] = 0;
        score[ay1 * stride + x] = 0;
    }
    for y in ay0..ay1 {
        score[y * stride + ax0 - 1] = 0;
        score[y * stride + ax1] = 0;
    }
    suppress(score, stride, ax0, ax1, ay0, ay1, out);
}

/// 3x3 non-maximum suppression over the area; pushes the survivors to `out`.
#[inline(always)]
fn suppress(
    score: &[u8],
    stride: usize,
    ax0: usize,
    ax1: usize,
    ay0: usize,
    ay1: usize,
    out: &mut Vec<Candidate>,
) {
    const CHUNK: usize = 64;
    if ax1 - ax0 < CHUNK {
        return suppress_scalar(score, stride, ax0, ax1, ay0, ay1, out);
    }
    for y in ay0..ay1 {
        let up = &score[(y - 1) * stride..y * stride];
        let mid = &score[y * stride..(y + 1) * stride];
        let down = &score[(y + 1) * stride..(y + 2) * stride];
        let mut x = ax0;
        while x < ax1 {
            // Chunks of fixed size; the last one overlaps the previous (skip `x - xs` pixels).
            let xs = x.min(ax1 - CHUNK);
            let window = |r: &[u8]| r.get(xs - 1..)?.first_chunk::<{ CHUNK + 2 }>().copied();
            let (Some(u), Some(m), Some(d)) = (window(up), window(mid), window(down)) else {
                break;
            };
            // Strict maximum over the neighbours before in raster order, >= over those after.
            let mut keep = [0u8; CHUNK];
            for i in 0..CHUNK {
                let s = m[i + 1];
                let before = u[i].max(u[i + 1]).max(u[i + 2]).max(m[i]);
                let after = m[i + 2].max(d[i]).max(d[i + 1]).max(d[i + 2]);
                keep[i] = ((s > before) & (s >= after) & (s != 0)) as u8;
            }
            keep[..x - xs].fill(0);
            for (wi, word) in keep.chunks_exact(8).enumerate() {
                let mut bits = u64::from_le_bytes([
                    word[0], word[1], word[2], word[3], word[4], word[5], word[6], word[7],
                ]);
                while bits != 0 {
                    let i = wi * 8 + (bits.trailing_zeros() / 8) as usize;
                    bits &= bits - 1;
                    out.push(Candidate {
                        x: (xs + i) as u16,
                        y: y as u16,
                        score: m[i + 1],
                    });
                }
            }
            x = xs + CHUNK;
        }
    }
}

/// [`suppress`] for areas narrower than a chunk.
fn suppress_scalar(
    score: &[u8],
    stride: usize,
    ax0: usize,
    ax1: usize,
    ay0: usize,
    ay1: usize,
    out: &mut Vec<Candidate>,
) {
    for y in ay0..ay1 {
        let at = |dx: usize, dy: usize, x: usize| score[(y + dy - 1) * stride + x + dx - 1];
        for x in ax0..ax1 {
            let s = at(1, 1, x);
            let before = at(0, 0, x)
                .max(at(1, 0, x))
                .max(at(2, 0, x))
                .max(at(0, 1, x));
            let after = at(2, 1, x)
                .max(at(0, 2, x))
                .max(at(1, 2, x))
                .max(at(2, 2, x));
            if s != 0 && s > before && s >= after {
                out.push(Candidate {
                    x: x as u16,
                    y: y as u16,
                    score: s,
                });
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Naive FAST-9 test straight from the definition.
    fn naive_is_corner(img: &[u8], stride: usize, x: usize, y: usize, t: u8) -> bool {
        let p = img[y * stride + x] as i32;
        let c: Vec<i32> = CIRCLE
            .iter()
            .map(|&(dx, dy)| {
                img[(y as isize + dy) as usize * stride + (x as isize + dx) as usize] as i32
            })
            .collect();
        (0..16).any(|k| (0..9).all(|j| c[(k + j) % 16] > p + t as i32))
            || (0..16).any(|k| (0..9).all(|j| c[(k + j) % 16] < p - t as i32))
    }

    fn noise_image(w: usize, h: usize, seed: u64) -> Vec<u8> {
        let mut s = seed;
        (0..w * h)
            .map(|i| {
                s = s
                    .wrapping_mul(6364136223846793005)
                    .wrapping_add(1442695040888963407);
                let n = (s >> 33) as u32 % 60;
                let (x, y) = (i % w, i / w);
                let blob = if ((x / 9) + (y / 7)) % 3 == 0 {
                    120
                } else {
                    40
                };
                (blob + n) as u8
            })
            .collect()
    }

    #[test]
    fn score_matches_definition() {
        let (w, h) = (80, 60);
        let img = noise_image(w, h, 7);
        for y in 3..h - 3 {
            for x in 3..w - 3 {
                let s = score_at(&img, w, x, y);
                for t in [5u8, 20, 40] {
                    assert_eq!(s > t, naive_is_corner(&img, w, x, y, t), "({x},{y}) t={t}");
                }
            }
        }
    }

    #[test]
    fn block_kernel_matches_scalar() {
        let (w, h) = (101, 50);
        let img = noise_image(w, h, 3);
        let mut score = vec![0u8; w * h];
        for y in 3..h - 3 {
            for (x0, x1) in [(3, 35), (35, 67), (67, 98), (90, 98)] {
                score_span(&img, w, w, y, x0, x1, 10, &mut score);
                for x in x0..x1 {
                    let s = score_at(&img, w, x, y);
                    assert_eq!(score[y * w + x], if s > 10 { s } else { 0 });
                }
            }
        }
    }

    #[test]
    fn detect_finds_isolated_corner_and_suppresses() {
        let (w, h) = (100, 80);
        let mut img = vec![50u8; w * h];
        // A bright 10x10 square: its corners are FAST corners.
        for y in 30..40 {
            for x in 40..50 {
                img[y * w + x] = 200;
            }
        }
        let mut score = vec![0u8; w * h];
        let mut out = Vec::new();
        let cfg = FastConfig {
            border: 19,
            th_ini: 20,
            th_min: 7,
        };
        detect(&img, w, w, h, cfg, &mut score, &mut out);
        assert!(!out.is_empty());
        for c in &out {
            let near = |a: u16, b: u16| (a as i32 - b as i32).abs() <= 3;
            assert!(
                (near(c.x, 40) || near(c.x, 49)) && (near(c.y, 30) || near(c.y, 39)),
                "{c:?}"
            );
        }
        // Each square corner is found; suppression leaves few responses around it.
        for (cx, cy) in [(40, 30), (49, 30), (40, 39), (49, 39)] {
            assert!(
                out.iter()
                    .any(|c| c.x.abs_diff(cx) <= 2 && c.y.abs_diff(cy) <= 2),
                "{out:?}"
            );
        }
        assert!(out.len() <= 12, "{out:?}");
    }
}
