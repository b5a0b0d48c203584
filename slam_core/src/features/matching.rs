//! Descriptor matching: Hamming distance, brute force with ratio test, rotation consistency,
//! and windowed search through a grid index of keypoints.

use super::extractor::{KeyPoint, OrbFeatures};
use crate::CoreError;

/// Strict distance threshold of ORB-SLAM (initialisation, local map search).
pub const TH_LOW: u32 = 50;
/// Loose distance threshold of ORB-SLAM (fusion, relocalisation).
pub const TH_HIGH: u32 = 100;

/// Hamming distance between two 256-bit descriptors (four 64-bit popcounts).
#[inline(always)]
pub fn hamming(a: &[u8; 32], b: &[u8; 32]) -> u32 {
    let mut d = 0;
    for (x, y) in a.chunks_exact(8).zip(b.chunks_exact(8)) {
        let x = u64::from_le_bytes([x[0], x[1], x[2], x[3], x[4], x[5], x[6], x[7]]);
        let y = u64::from_le_bytes([y[0], y[1], y[2], y[3], y[4], y[5], y[6], y[7]]);
        d += (x ^ y).count_ones();
    }
    d
}

/// A correspondence between feature `query` of one set and feature `train` of another.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Match {
    /// Index in the first (query) set.
    pub query: u32,
    /// Index in the second (train) set.
    pub train: u32,
    /// Hamming distance of the two descriptors.
    pub distance: u32,
}

/// Acceptance rules of a match.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct MatchParams {
    /// Largest accepted distance (e.g. [`TH_LOW`] or [`TH_HIGH`]).
    pub max_distance: u32,
    /// Nearest / second-nearest distance ratio test: accept when `best < ratio * second`
    /// (typical 0.7..0.9; 1.0 disables it).
    pub ratio: f32,
    /// Keep at most one match per train feature (the closest; ties to the lower query index).
    pub unique: bool,
}

impl Default for MatchParams {
    fn default() -> Self {
        Self {
            max_distance: TH_LOW,
            ratio: 0.8,
            unique: true,
        }
    }
}

/// Best and second-best distances among candidates.
#[derive(Debug, Clone, Copy)]
struct Best {
    index: u32,
    distance: u32,
    second: u32,
}

impl Best {
    const NONE: Best = Best {
        index: u32::MAX,
        distance: u32::MAX,
        second: u32::MAX,
    };

    #[inline(always)]
    fn offer(&mut self, index: u32, d: u32) {
        if d < self.distance {
            self.second = self.distance;
            self.distance = d;
            self.index = index;
        } else if d < self.second {
            self.second = d;
        }
    }

    fn accepted(&self, p: &MatchParams) -> bool {
        self.index != u32::MAX
            && self.distance <= p.max_distance
            && (self.second == u32::MAX || (self.distance as f32) < p.ratio * self.second as f32)
    }
}

#[inline(always)]
fn brute_force_impl(query: &[[u8; 32]], train: &[[u8; 32]], p: &MatchParams, out: &mut Vec<Match>) {
    for (qi, q) in query.iter().enumerate() {
        let mut best = Best::NONE;
        for (ti, t) in train.iter().enumerate() {
            best.offer(ti as u32, hamming(q, t));
        }
        if best.accepted(p) {
            out.push(Match {
                query: qi as u32,
                train: best.index,
                distance: best.distance,
            });
        }
    }
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "popcnt")]
fn brute_force_popcnt(
    query: &[[u8; 32]],
    train: &[[u8; 32]],
    p: &MatchParams,
    out: &mut Vec<Match>,
) {
    brute_force_impl(query, train, p, out)
}

/// Matches every `query` descriptor to its nearest `train` descriptor; keeps those passing
/// `params` (distance, ratio, uniqueness). `out` is cleared first and sorted by query.
pub fn match_brute_force(
    query: &[[u8; 32]],
    train: &[[u8; 32]],
    params: &MatchParams,
    out: &mut Vec<Match>,
) {
    out.clear();
    #[cfg(target_arch = "x86_64")]
    if std::arch::is_x86_feature_detected!("popcnt") {
        // SAFETY: the CPU supports popcnt (checked just above).
        unsafe { brute_force_popcnt(query, train, params, out) };
        return finish(out, params);
    }
    brute_force_impl(query, train, params, out);
    finish(out, params)
}

/// Uniqueness per train feature, then order by query.
fn finish(out: &mut Vec<Match>, params: &MatchParams) {
    if params.unique {
        keep_unique_train(out);
    }
}

/// Keeps the closest match of each train feature; leaves `matches` sorted by query.
pub fn keep_unique_train(matches: &mut Vec<Match>) {
    matches.sort_unstable_by_key(|m| (m.train, m.distance, m.query));
    matches.dedup_by_key(|m| m.train);
    matches.sort_unstable_by_key(|m| m.query);
}

/// Rotation-consistency check of ORB-SLAM: histogram of `angle(query) - angle(train)` in
/// `bins` bins (30 in ORB-SLAM); keeps matches in the three fullest bins (the second and third
/// only when they hold more than a tenth of the first). Returns how many were removed.
pub fn rotation_consistency(
    matches: &mut Vec<Match>,
    query_kps: &[KeyPoint],
    train_kps: &[KeyPoint],
    bins: usize,
) -> usize {
    const MAX_BINS: usize = 360;
    let bins = bins.clamp(1, MAX_BINS);
    let bin_of = |m: &Match| -> Option<usize> {
        let a = query_kps.get(m.query as usize)?.angle;
        let b = train_kps.get(m.train as usize)?.angle;
        let rot = (a - b).rem_euclid(360.0);
        Some(((rot / 360.0 * bins as f32).round() as usize) % bins)
    };
    let mut hist = [0u32; MAX_BINS];
    for m in matches.iter() {
        if let Some(b) = bin_of(m) {
            hist[b] += 1;
        }
    }
    let (top, _) = three_maxima(&hist[..bins]);
    let before = matches.len();
    matches.retain(|m| bin_of(m).is_some_and(|b| top.contains(&Some(b))));
    before - matches.len()
}

/// Indices of the three fullest bins (the lowest index wins ties); the second and third are
/// `None` when empty or not above a tenth of the first.
fn three_maxima(hist: &[u32]) -> ([Option<usize>; 3], [u32; 3]) {
    let mut idx = [None; 3];
    let mut val = [0u32; 3];
    for (i, &h) in hist.iter().enumerate() {
        if h == 0 {
            continue;
        }
        if h > val[0] {
            idx = [Some(i), idx[0], idx[1]];
            val = [h, val[0], val[1]];
        } else if h > val[1] {
            idx = [idx[0], Some(i), idx[1]];
            val = [val[0], h, val[1]];
        } else if h > val[2] {
            idx[2] = Some(i);
            val[2] = h;
        }
    }
    for k in 1..3 {
        if (val[k] as f32) <= 0.1 * val[0] as f32 {
            idx[k] = None;
        }
    }
    (idx, val)
}

/// Uniform grid index of keypoints (level-0 pixel coordinates) for windowed searches.
///
/// Built once per frame by a counting sort; queries allocate nothing.
#[derive(Debug, Clone)]
pub struct FeatureGrid {
    inv_cell: f32,
    cols: usize,
    rows: usize,
    /// `cols * rows + 1` prefix offsets into `items`.
    start: Vec<u32>,
    /// Keypoint indices, grouped by cell.
    items: Vec<u32>,
}

impl FeatureGrid {
    /// A grid over `width` x `height` pixels with square cells of `cell_size` pixels.
    pub fn new(width: usize, height: usize, cell_size: f32) -> Result<Self, CoreError> {
        if width == 0 || height == 0 || !(cell_size >= 1.0 && cell_size.is_finite()) {
            return Err(CoreError::InvalidArgument(format!(
                "grid {width}x{height} with cell {cell_size} is invalid"
            )));
        }
        let cols = (width as f32 / cell_size).ceil() as usize;
        let rows = (height as f32 / cell_size).ceil() as usize;
        Ok(Self {
            inv_cell: 1.0 / cell_size,
            cols,
            rows,
            start: vec![0; cols * rows + 1],
            items: Vec::with_capacity(4096),
        })
    }

    #[inline]
    fn cell_coord(&self, v: f32, n: usize) -> usize {
        ((v * self.inv_cell).floor().max(0.0) as usize).min(n - 1)
    }

    /// Indexes `kps` (points outside the image go to the border cells).
    pub fn build(&mut self, kps: &[KeyPoint]) {
        self.start.iter_mut().for_each(|s| *s = 0);
        for k in kps {
            let c = self.cell_coord(k.y, self.rows) * self.cols + self.cell_coord(k.x, self.cols);
            self.start[c + 1] += 1;
        }
        for c in 0..self.cols * self.rows {
            self.start[c + 1] += self.start[c];
        }
        self.items.clear();
        self.items.resize(kps.len(), 0);
        // Fill back to front so that `start[c]` ends at the first slot of cell `c`.
        for (i, k) in kps.iter().enumerate().rev() {
            let c = self.cell_coord(k.y, self.rows) * self.cols + self.cell_coord(k.x, self.cols);
            self.start[c + 1] -= 1;
            self.items[self.start[c + 1] as usize] = i as u32;
        }
        // After the loop start[c + 1] is the first slot of cell c; shift back.
        for c in 0..self.cols * self.rows {
            self.start[c] = self.start[c + 1];
        }
        self.start[self.cols * self.rows] = kps.len() as u32;
    }

    /// Calls `f(i)` for every keypoint `i` with `|x - kx| <= r`, `|y - ky| <= r` and octave in
    /// `min_octave..=max_octave`, in increasing cell order.
    #[allow(clippy::too_many_arguments)]
    pub fn for_each_in_window(
        &self,
        kps: &[KeyPoint],
        x: f32,
        y: f32,
        r: f32,
        min_octave: u8,
        max_octave: u8,
        mut f: impl FnMut(usize),
    ) {
        if !(x.is_finite() && y.is_finite() && r >= 0.0) {
            return;
        }
        let (c0, c1) = (
            self.cell_coord(x - r, self.cols),
            self.cell_coord(x + r, self.cols),
        );
        let (r0, r1) = (
            self.cell_coord(y - r, self.rows),
            self.cell_coord(y + r, self.rows),
        );
        for row in r0..=r1 {
            let a = self.start[row * self.cols + c0] as usize;
            let b = self.start[row * self.cols + c1 + 1] as usize;
            for &i in &self.items[a..b] {
                let Some(k) = kps.get(i as usize) else {
                    continue;
                };
                if (k.x - x).abs() <= r
                    && (k.y - y).abs() <= r
                    && k.octave >= min_octave
                    && k.octave <= max_octave
                {
                    f(i as usize);
                }
            }
        }
    }
}

/// Result of [`match_in_window`].
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct WindowMatch {
    /// Index of the best feature.
    pub index: usize,
    /// Its Hamming distance.
    pub distance: u32,
    /// Distance of the second best (`u32::MAX` when there is none).
    pub second_distance: u32,
}

/// Best feature of `features` (indexed by `grid`) within `radius` pixels of `(x, y)`, with an
/// octave in `octaves`, for `descriptor`; `None` when the window holds no such feature.
pub fn match_in_window(
    grid: &FeatureGrid,
    features: &OrbFeatures,
    (x, y): (f32, f32),
    radius: f32,
    octaves: (u8, u8),
    descriptor: &[u8; 32],
) -> Option<WindowMatch> {
    let mut best = Best::NONE;
    grid.for_each_in_window(
        &features.keypoints,
        x,
        y,
        radius,
        octaves.0,
        octaves.1,
        |i| {
            if let Some(d) = features.descriptors.get(i) {
                best.offer(i as u32, hamming(descriptor, d));
            }
        },
    );
    (best.index != u32::MAX).then_some(WindowMatch {
        index: best.index as usize,
        distance: best.distance,
        second_distance: best.second,
    })
}

/// Parameters of [`match_two_frames_windowed`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct WindowMatchParams {
    /// Distance, ratio and uniqueness rules.
    pub accept: MatchParams,
    /// Half-size of the square search window, level-0 pixels.
    pub radius: f32,
    /// Only features of the first frame with an octave up to this are matched (ORB-SLAM's
    /// initialisation uses 0).
    pub max_octave: u8,
    /// Features of the second frame must be within this many octaves of the first's.
    pub octave_tolerance: u8,
    /// Rotation-consistency bins (0 disables the check; ORB-SLAM uses 30).
    pub rotation_bins: usize,
}

impl Default for WindowMatchParams {
    fn default() -> Self {
        Self {
            accept: MatchParams {
                max_distance: TH_LOW,
                ratio: 0.9,
                unique: true,
            },
            radius: 100.0,
            max_octave: 0,
            octave_tolerance: 0,
            rotation_bins: 30,
        }
    }
}

/// Matches `f1` to `f2` by searching, for each feature of `f1`, a window of `f2` around its
/// predicted position (`predicted[i]`, or the feature's own position when `None`), as in
/// ORB-SLAM's initialisation. `grid2` must index `f2`. `out` is cleared and sorted by query.
pub fn match_two_frames_windowed(
    f1: &OrbFeatures,
    f2: &OrbFeatures,
    grid2: &FeatureGrid,
    predicted: Option<&[[f32; 2]]>,
    params: &WindowMatchParams,
    out: &mut Vec<Match>,
) -> Result<(), CoreError> {
    out.clear();
    if let Some(p) = predicted {
        if p.len() != f1.len() {
            return Err(CoreError::InvalidArgument(format!(
                "{} predicted positions for {} features",
                p.len(),
                f1.len()
            )));
        }
    }
    for (i, (k, d)) in f1.keypoints.iter().zip(&f1.descriptors).enumerate() {
        if k.octave > params.max_octave {
            continue;
        }
        let (x, y) = match predicted {
            Some(p) => (p[i][0], p[i][1]),
            None => (k.x, k.y),
        };
        let octs = (
            k.octave.saturating_sub(params.octave_tolerance),
            k.octave.saturating_add(params.octave_tolerance),
        );
        let Some(m) = match_in_window(grid2, f2, (x, y), params.radius, octs, d) else {
            continue;
        };
        let best = Best {
            index: m.index as u32,
            distance: m.distance,
            second: m.second_distance,
        };
        if best.accepted(&params.accept) {
            out.push(Match {
                query: i as u32,
                train: best.index,
                distance: best.distance,
            });
        }
    }
    if params.accept.unique {
        keep_unique_train(out);
    }
    if params.rotation_bins > 0 {
        rotation_consistency(out, &f1.keypoints, &f2.keypoints, params.rotation_bins);
    }
    Ok(())
}
