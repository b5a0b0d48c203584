//! Spreading keypoints over the image: ORB-SLAM-style quadtree, one keypoint per leaf.
//!
//! The area is cut into `round(w / h)` vertical strips, then nodes holding more than one
//! candidate are split into four until there are at least `n` nodes (or nothing can split);
//! when a full round of splits would overshoot `n`, the most populated nodes are split first.
//! Each leaf keeps its strongest candidate. Nodes are index ranges into one array that is
//! partitioned in place, so nothing is allocated once the scratch vectors have grown.

use super::fast::Candidate;

/// A quadtree node: a box and the range of candidate indices inside it.
#[derive(Debug, Clone, Copy)]
struct Node {
    x0: u32,
    y0: u32,
    x1: u32,
    y1: u32,
    start: u32,
    end: u32,
}

impl Node {
    fn len(&self) -> usize {
        (self.end - self.start) as usize
    }
}

/// Scratch of [`distribute`], reused across calls.
#[derive(Debug, Default, Clone)]
pub(crate) struct QuadtreeScratch {
    idx: Vec<u32>,
    nodes: Vec<Node>,
    next: Vec<Node>,
    order: Vec<u32>,
    strip_count: Vec<u32>,
}

impl QuadtreeScratch {
    /// Scratch sized for `cands` candidates and `nodes` quadtree nodes.
    pub(crate) fn with_capacity(cands: usize, nodes: usize) -> Self {
        Self {
            idx: Vec::with_capacity(cands),
            nodes: Vec::with_capacity(nodes),
            next: Vec::with_capacity(nodes),
            order: Vec::with_capacity(nodes),
            strip_count: Vec::with_capacity(65),
        }
    }
}

/// Strict "better" order of candidates: score, then raster position (deterministic ties).
#[inline]
fn better(a: &Candidate, b: &Candidate) -> bool {
    (a.score, std::cmp::Reverse(a.y), std::cmp::Reverse(a.x))
        > (b.score, std::cmp::Reverse(b.y), std::cmp::Reverse(b.x))
}

/// Partitions `idx[range]` so that candidates with `pred` come first; returns the split point.
fn partition(idx: &mut [u32], cands: &[Candidate], pred: impl Fn(&Candidate) -> bool) -> usize {
    let mut i = 0;
    for j in 0..idx.len() {
        if pred(&cands[idx[j] as usize]) {
            idx.swap(i, j);
            i += 1;
        }
    }
    i
}

/// Splits `node` into up to four non-empty children, pushed to `out`. Returns how many of the
/// pushed children hold more than one candidate.
fn split(node: &Node, idx: &mut [u32], cands: &[Candidate], out: &mut Vec<Node>) -> usize {
    let mx = node.x0 + (node.x1 - node.x0).div_ceil(2);
    let my = node.y0 + (node.y1 - node.y0).div_ceil(2);
    let (s, e) = (node.start as usize, node.end as usize);
    let top = s + partition(&mut idx[s..e], cands, |c| (c.y as u32) < my);
    let tl = s + partition(&mut idx[s..top], cands, |c| (c.x as u32) < mx);
    let bl = top + partition(&mut idx[top..e], cands, |c| (c.x as u32) < mx);
    let boxes = [
        (node.x0, node.y0, mx, my, s, tl),
        (mx, node.y0, node.x1, my, tl, top),
        (node.x0, my, mx, node.y1, top, bl),
        (mx, my, node.x1, node.y1, bl, e),
    ];
    let mut splittable = 0;
    for (x0, y0, x1, y1, a, b) in boxes {
        if b > a {
            splittable += (b - a > 1) as usize;
            out.push(Node {
                x0,
                y0,
                x1,
                y1,
                start: a as u32,
                end: b as u32,
            });
        }
    }
    splittable
}

/// Keeps at most `n` candidates spread over `[x0, x1) x [y0, y1)`; their indices into `cands`
/// are written to `keep` (cleared first), strongest first within no particular spatial order.
pub(crate) fn distribute(
    cands: &[Candidate],
    area: (u32, u32, u32, u32),
    n: usize,
    s: &mut QuadtreeScratch,
    keep: &mut Vec<u32>,
) {
    keep.clear();
    if n == 0 || cands.is_empty() {
        return;
    }
    let (x0, y0, x1, y1) = area;
    let (w, h) = (x1.saturating_sub(x0).max(1), y1.saturating_sub(y0).max(1));
    // Initial vertical strips, filled by a counting sort.
    let n_strips = ((w as f32 / h as f32).round() as usize).clamp(1, 64);
    let strip_w = w.div_ceil(n_strips as u32).max(1);
    let strip_of =
        |c: &Candidate| (((c.x as u32).saturating_sub(x0) / strip_w) as usize).min(n_strips - 1);
    s.strip_count.clear();
    s.strip_count.resize(n_strips + 1, 0);
    for c in cands {
        s.strip_count[strip_of(c) + 1] += 1;
    }
    for i in 0..n_strips {
        s.strip_count[i + 1] += s.strip_count[i];
    }
    s.idx.clear();
    s.idx.resize(cands.len(), 0);
    s.nodes.clear();
    for i in 0..n_strips {
        let (a, b) = (s.strip_count[i], s.strip_count[i + 1]);
        if b > a {
            let sx0 = x0 + i as u32 * strip_w;
            s.nodes.push(Node {
                x0: sx0,
                y0,
                x1: (sx0 + strip_w).min(x1.max(sx0 + 1)),
                y1,
                start: a,
                end: b,
            });
        }
    }
    {
        // Scatter indices into their strips (strip_count[i] becomes the running cursor).
        let cursor = &mut s.strip_count;
        for (i, c) in cands.iter().enumerate() {
            let st = strip_of(c);
            s.idx[cursor[st] as usize] = i as u32;
            cursor[st] += 1;
        }
    }

    // Full rounds of splitting. Unlike ORB-SLAM, a round that leaves the node count unchanged
    // (all points in one child) does not stop the division; boxes shrink every round, and the
    // round cap guards against duplicate positions.
    for _round in 0..64 {
        if s.nodes.iter().all(|nd| nd.len() <= 1) {
            break;
        }
        s.next.clear();
        let mut splittable = 0;
        for node in &s.nodes {
            if node.len() > 1 {
                splittable += split(node, &mut s.idx, cands, &mut s.next);
            } else {
                s.next.push(*node);
            }
        }
        std::mem::swap(&mut s.nodes, &mut s.next);
        if s.nodes.len() >= n {
            break;
        }
        if s.nodes.len() + 3 * splittable > n {
            split_largest_first(cands, n, s);
            break;
        }
    }

    // One candidate per leaf: its strongest.
    for node in &s.nodes {
        let range = &s.idx[node.start as usize..node.end as usize];
        let mut best = range[0];
        for &i in &range[1..] {
            if better(&cands[i as usize], &cands[best as usize]) {
                best = i;
            }
        }
        keep.push(best);
    }
    if keep.len() > n {
        keep.select_nth_unstable_by(n - 1, |&a, &b| {
            let (ca, cb) = (&cands[a as usize], &cands[b as usize]);
            if better(ca, cb) {
                std::cmp::Ordering::Less
            } else if better(cb, ca) {
                std::cmp::Ordering::Greater
            } else {
                std::cmp::Ordering::Equal
            }
        });
        keep.truncate(n);
    }
}

/// Splits the most populated nodes one at a time until there are `n` nodes or none can split.
fn split_largest_first(cands: &[Candidate], n: usize, s: &mut QuadtreeScratch) {
    loop {
        let prev = s.nodes.len();
        s.order.clear();
        s.order.extend(
            s.nodes
                .iter()
                .enumerate()
                .filter(|(_, nd)| nd.len() > 1)
                .map(|(i, _)| i as u32),
        );
        let nodes = &s.nodes;
        s.order
            .sort_unstable_by_key(|&i| (std::cmp::Reverse(nodes[i as usize].len()), i));
        for k in 0..s.order.len() {
            let i = s.order[k] as usize;
            let node = s.nodes[i];
            let before = s.nodes.len();
            split(&node, &mut s.idx, cands, &mut s.nodes);
            // The first child takes the parent's slot (indices below `before` stay valid).
            if s.nodes.len() > before {
                s.nodes[i] = s.nodes[before];
                s.nodes.swap_remove(before);
            }
            if s.nodes.len() >= n {
                return;
            }
        }
        if s.nodes.len() == prev || s.nodes.len() >= n {
            return;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn keeps_the_strongest_spread_over_the_area() {
        // A dense 100x100 block of candidates in the top-left corner plus 4 isolated weak ones.
        let mut cands = Vec::new();
        for y in 20..120u16 {
            for x in 20..120u16 {
                let score = 10 + ((x * 7 + y * 13) % 200) as u8;
                cands.push(Candidate { x, y, score });
            }
        }
        for (x, y) in [(500u16, 40u16), (500, 300), (300, 300), (40, 300)] {
            cands.push(Candidate { x, y, score: 1 });
        }
        let mut s = QuadtreeScratch::default();
        let mut keep = Vec::new();
        distribute(&cands, (19, 19, 621, 461), 20, &mut s, &mut keep);
        assert_eq!(keep.len(), 20);
        // Isolated weak corners take slots from the stronger dense block: they are alone in
        // their nodes (at most 3 leaves beyond `n` are trimmed, weakest first).
        let kept: Vec<Candidate> = keep.iter().map(|&i| cands[i as usize]).collect();
        assert!(kept.iter().filter(|c| c.score == 1).count() >= 1);
        // Within the block, kept points are spread, not clustered on the strongest scores.
        let block: Vec<&Candidate> = kept.iter().filter(|c| c.score > 1).collect();
        let (min_x, max_x) = (
            block.iter().map(|c| c.x).min(),
            block.iter().map(|c| c.x).max(),
        );
        let (min_y, max_y) = (
            block.iter().map(|c| c.y).min(),
            block.iter().map(|c| c.y).max(),
        );
        assert!(max_x.unwrap() - min_x.unwrap() > 60 && max_y.unwrap() - min_y.unwrap() > 60);
        // Deterministic and without duplicates.
        let mut again = Vec::new();
        distribute(&cands, (19, 19, 621, 461), 20, &mut s, &mut again);
        assert_eq!(keep, again);
        let mut sorted = keep.clone();
        sorted.sort_unstable();
        sorted.dedup();
        assert_eq!(sorted.len(), keep.len());
        // Fewer candidates than wanted: all are kept.
        distribute(&cands[..3], (19, 19, 621, 461), 20, &mut s, &mut keep);
        assert_eq!(keep.len(), 3);
    }
}
