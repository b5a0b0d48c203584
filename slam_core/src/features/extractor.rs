//! The ORB extractor: pyramid, FAST per level, quadtree spreading, orientation, rotated BRIEF.

use std::time::{Duration, Instant};

use super::distribute::{distribute, QuadtreeScratch};
use super::fast::{self, Candidate, FastConfig};
use super::image::{GrayBuffer, GrayImage};
use super::orb::{orientations, DescriptorTable, OrientationTable, PATTERN_REACH};
use super::pyramid::{gaussian_blur7, Pyramid};
use super::scale::{PyramidScale, MAX_LEVELS, ORB_N_LEVELS, ORB_SCALE_FACTOR};
use crate::CoreError;

/// Diameter of the ORB patch at level 0 (keypoint `size` is this times the level scale).
pub const PATCH_SIZE: f32 = 31.0;

/// Parameters of [`OrbExtractor`].
#[derive(Debug, Clone, PartialEq)]
pub struct OrbParams {
    /// Total number of keypoints wanted over all levels.
    pub n_features: usize,
    /// Scale between two consecutive pyramid levels (> 1; default [`ORB_SCALE_FACTOR`]).
    /// The image pyramid resamples with its single-precision value; the features carry it
    /// in [`OrbFeatures::scale`].
    pub scale_factor: f64,
    /// Number of pyramid levels (1..=32).
    pub n_levels: usize,
    /// FAST threshold tried first in every detection cell.
    pub fast_threshold: u8,
    /// FAST threshold used in cells with no corner at `fast_threshold`.
    pub fast_min_threshold: u8,
    /// Level `l` gets a share of `n_features` proportional to `scale_factor^(-exponent * l)`:
    /// 2 is proportional to the level's area; ORB-SLAM2's and OpenCV's code use 1.
    pub level_share_exponent: f32,
    /// Quantisation of the keypoint angle for the precomputed rotated BRIEF patterns
    /// (30 = 12 degree steps, as in the ORB paper).
    pub angle_bins: usize,
}

impl Default for OrbParams {
    fn default() -> Self {
        Self {
            n_features: 1000,
            scale_factor: ORB_SCALE_FACTOR,
            n_levels: ORB_N_LEVELS,
            fast_threshold: 20,
            fast_min_threshold: 7,
            level_share_exponent: 2.0,
            angle_bins: 30,
        }
    }
}

/// A keypoint in level-0 pixel coordinates.
#[derive(Debug, Clone, Copy, PartialEq)]
#[cfg_attr(feature = "serde", derive(serde::Serialize, serde::Deserialize))]
pub struct KeyPoint {
    /// Column (level-0 pixels).
    pub x: f32,
    /// Row (level-0 pixels).
    pub y: f32,
    /// Orientation in degrees, `[0, 360)`, measured from +x towards +y (image down).
    pub angle: f32,
    /// FAST score on its level.
    pub response: f32,
    /// Diameter of the described patch in level-0 pixels (`31 * scale`).
    pub size: f32,
    /// Pyramid level it was detected on.
    pub octave: u8,
}

impl KeyPoint {
    /// A keypoint on level 0 at `(x, y)` with no orientation and a unit response (synthetic
    /// features: tests, measurements made elsewhere).
    pub fn at_level0(x: f32, y: f32) -> Self {
        Self {
            x,
            y,
            angle: 0.0,
            response: 1.0,
            size: 31.0,
            octave: 0,
        }
    }
}

/// Keypoints and their 256-bit descriptors (`descriptors[i]` belongs to `keypoints[i]`),
/// with the scale of the pyramid they were detected on.
#[derive(Debug, Clone, Default)]
#[cfg_attr(feature = "serde", derive(serde::Serialize, serde::Deserialize))]
pub struct OrbFeatures {
    /// Keypoints, grouped by level (level 0 first).
    pub keypoints: Vec<KeyPoint>,
    /// Rotated BRIEF descriptors, 32 bytes each.
    pub descriptors: Vec<[u8; 32]>,
    /// Scale factor and per-octave tables of the pyramid (set by [`OrbExtractor`]; features
    /// built otherwise, e.g. from keyframe messages, have [`PyramidScale::default`]).
    pub scale: PyramidScale,
}

impl OrbFeatures {
    /// Empty feature set with room for `n` features, with the default pyramid scale.
    pub fn with_capacity(n: usize) -> Self {
        Self {
            keypoints: Vec::with_capacity(n),
            descriptors: Vec::with_capacity(n),
            scale: PyramidScale::default(),
        }
    }

    /// Makes `self` a copy of `other`, reusing `self`'s buffers (no allocation once they
    /// have grown).
    pub fn copy_from(&mut self, other: &OrbFeatures) {
        self.keypoints.clear();
        self.keypoints.extend_from_slice(&other.keypoints);
        self.descriptors.clear();
        self.descriptors.extend_from_slice(&other.descriptors);
        self.scale.clone_from(&other.scale);
    }

    /// Number of features.
    pub fn len(&self) -> usize {
        self.keypoints.len()
    }

    /// Whether there is no feature.
    pub fn is_empty(&self) -> bool {
        self.keypoints.is_empty()
    }

    /// Removes all features, keeping the capacity (and the scale).
    pub fn clear(&mut self) {
        self.keypoints.clear();
        self.descriptors.clear();
    }
}

/// Time spent in each stage of one [`OrbExtractor::extract_timed`] call.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct OrbTimings {
    /// Building the pyramid.
    pub pyramid: Duration,
    /// FAST and quadtree spreading, all levels.
    pub detect: Duration,
    /// Intensity-centroid orientation.
    pub orient: Duration,
    /// Gaussian blur and rotated BRIEF.
    pub describe: Duration,
}

impl OrbTimings {
    /// Sum of the stages.
    pub fn total(&self) -> Duration {
        self.pyramid + self.detect + self.orient + self.describe
    }
}

/// Margin (level pixels) where no keypoint is detected: the rotated pattern reaches 19 pixels.
const EDGE: usize = PATTERN_REACH;

/// ORB feature extractor for images of one size; every buffer is allocated in [`Self::new`].
#[derive(Debug, Clone)]
pub struct OrbExtractor {
    params: OrbParams,
    width: usize,
    height: usize,
    pyramid: Pyramid,
    /// The pyramid's scale tables, copied into every extracted feature set.
    scale: PyramidScale,
    per_level: Vec<usize>,
    blurred: GrayBuffer,
    blur_tmp: Vec<u16>,
    score: Vec<u8>,
    cands: Vec<Candidate>,
    keep: Vec<u32>,
    angles: Vec<f32>,
    quad: QuadtreeScratch,
    orientation: OrientationTable,
    brief: DescriptorTable,
}

impl OrbExtractor {
    /// An extractor for `width` x `height` images (at least 2 * 19 + 1 = 39 pixels each way).
    pub fn new(params: OrbParams, width: usize, height: usize) -> Result<Self, CoreError> {
        if width < 2 * EDGE + 1 || height < 2 * EDGE + 1 {
            return Err(CoreError::InvalidArgument(format!(
                "image {width}x{height} is smaller than the ORB border allows (39x39)"
            )));
        }
        let valid = (1..=MAX_LEVELS).contains(&params.n_levels)
            && params.scale_factor > 1.0
            && params.scale_factor.is_finite()
            && params.level_share_exponent.is_finite()
            && params.level_share_exponent >= 0.0
            && (1..=4096).contains(&params.angle_bins);
        if !valid {
            return Err(CoreError::InvalidArgument(format!(
                "invalid ORB parameters {params:?}"
            )));
        }
        let pyramid = Pyramid::new(width, height, params.n_levels, pyramid_factor(&params))?;
        let per_level = features_per_level(&params);
        let max_cands = (width * height / 16).max(1024);
        let max_per_level = per_level.iter().copied().max().unwrap_or(0);
        Ok(Self {
            blurred: GrayBuffer::new(width, height, width)?,
            blur_tmp: Vec::with_capacity(width + 6),
            score: vec![0; width * height],
            cands: Vec::with_capacity(max_cands),
            keep: Vec::with_capacity(4 * max_per_level + 64),
            angles: Vec::with_capacity(4 * max_per_level + 64),
            quad: QuadtreeScratch::with_capacity(max_cands, 4 * max_per_level + 64),
            orientation: OrientationTable::new(),
            brief: DescriptorTable::new(params.angle_bins, width),
            per_level,
            pyramid,
            scale: PyramidScale::new(params.scale_factor, params.n_levels),
            params,
            width,
            height,
        })
    }

    /// The parameters.
    pub fn params(&self) -> &OrbParams {
        &self.params
    }

    /// Target number of keypoints of each level.
    pub fn features_per_level(&self) -> &[usize] {
        &self.per_level
    }

    /// The scale tables of the pyramid (as carried by the extracted features).
    pub fn scale(&self) -> &PyramidScale {
        &self.scale
    }

    /// Scale of level `l` relative to level 0.
    pub fn level_scale(&self, l: usize) -> Option<f32> {
        self.pyramid.scale(l)
    }

    /// The pyramid of the last extracted image.
    pub fn pyramid(&self) -> &Pyramid {
        &self.pyramid
    }

    /// Extracts features of `img` into `out` (cleared first; its capacity is reused).
    ///
    /// Errors when `img` is not of the size given to [`Self::new`].
    pub fn extract(&mut self, img: &GrayImage<'_>, out: &mut OrbFeatures) -> Result<(), CoreError> {
        self.run(img, out, None)
    }

    /// As [`Self::extract`], also measuring each stage into `timings`.
    pub fn extract_timed(
        &mut self,
        img: &GrayImage<'_>,
        out: &mut OrbFeatures,
        timings: &mut OrbTimings,
    ) -> Result<(), CoreError> {
        self.run(img, out, Some(timings))
    }

    /// As [`Self::extract`] on a raw buffer with rows `stride` bytes apart.
    pub fn extract_raw(
        &mut self,
        data: &[u8],
        width: usize,
        height: usize,
        stride: usize,
        out: &mut OrbFeatures,
    ) -> Result<(), CoreError> {
        let img = GrayImage::new(data, width, height, stride)?;
        self.run(&img, out, None)
    }

    fn run(
        &mut self,
        img: &GrayImage<'_>,
        out: &mut OrbFeatures,
        timings: Option<&mut OrbTimings>,
    ) -> Result<(), CoreError> {
        if img.width() != self.width || img.height() != self.height {
            return Err(CoreError::InvalidArgument(format!(
                "image is {}x{}, the extractor was made for {}x{}",
                img.width(),
                img.height(),
                self.width,
                self.height
            )));
        }
        out.clear();
        out.scale.clone_from(&self.scale);
        let mut clock = Clock::new(timings.is_some());
        self.pyramid.build(img)?;
        let mut t = OrbTimings {
            pyramid: clock.lap(),
            ..OrbTimings::default()
        };
        let stride = self.width;
        let cfg = FastConfig {
            border: EDGE,
            th_ini: self.params.fast_threshold,
            th_min: self.params.fast_min_threshold,
        };
        for l in 0..self.pyramid.n_levels() {
            let (Some(level), Some(scale)) = (self.pyramid.level(l), self.pyramid.scale(l)) else {
                continue;
            };
            let (w, h) = (level.width(), level.height());
            let want = self.per_level.get(l).copied().unwrap_or(0);
            if want == 0 || w < 2 * EDGE + 1 || h < 2 * EDGE + 1 {
                continue;
            }
            let data = level.data();
            fast::detect(data, stride, w, h, cfg, &mut self.score, &mut self.cands);
            let area = (
                EDGE as u32,
                EDGE as u32,
                (w - EDGE) as u32,
                (h - EDGE) as u32,
            );
            distribute(&self.cands, area, want, &mut self.quad, &mut self.keep);
            t.detect += clock.lap();

            let first = out.keypoints.len();
            self.angles.clear();
            orientations(
                &self.orientation,
                data,
                stride,
                &self.cands,
                &self.keep,
                &mut self.angles,
            );
            for (&i, &angle) in self.keep.iter().zip(&self.angles) {
                let c = self.cands[i as usize];
                out.keypoints.push(KeyPoint {
                    x: c.x as f32 * scale,
                    y: c.y as f32 * scale,
                    angle,
                    response: c.score as f32,
                    size: PATCH_SIZE * scale,
                    octave: l as u8,
                });
            }
            t.orient += clock.lap();

            gaussian_blur7(&level, &mut self.blurred, &mut self.blur_tmp);
            let blurred = self.blurred.data();
            let inv = 1.0 / scale;
            for kp in &out.keypoints[first..] {
                let x = (kp.x * inv).round() as usize;
                let y = (kp.y * inv).round() as usize;
                let d = self
                    .brief
                    .describe(blurred, y * stride + x, kp.angle)
                    .unwrap_or([0; 32]);
                out.descriptors.push(d);
            }
            t.describe += clock.lap();
        }
        debug_assert_eq!(self.brief.stride(), stride);
        if let Some(dst) = timings {
            *dst = t;
        }
        Ok(())
    }
}

/// The factor the image pyramid resamples with (single precision, as the level sizes and
/// the per-level budget have always been computed).
fn pyramid_factor(p: &OrbParams) -> f32 {
    p.scale_factor as f32
}

/// Per-level keypoint budget: geometric shares, the last level taking the remainder.
fn features_per_level(p: &OrbParams) -> Vec<usize> {
    let f = f64::from(pyramid_factor(p)).powf(-(p.level_share_exponent as f64));
    let n = p.n_features as f64;
    let levels = p.n_levels;
    let mut per = Vec::with_capacity(levels);
    let mut desired = if (1.0 - f).abs() < 1e-12 {
        n / levels as f64
    } else {
        n * (1.0 - f) / (1.0 - f.powi(levels as i32))
    };
    let mut sum = 0usize;
    for _ in 0..levels.saturating_sub(1) {
        let k = (desired.round() as usize).min(p.n_features - sum);
        per.push(k);
        sum += k;
        desired *= f;
    }
    per.push(p.n_features - sum);
    per
}

/// Stage clock that does nothing when timing is off.
struct Clock(Option<Instant>);

impl Clock {
    fn new(on: bool) -> Self {
        Self(on.then(Instant::now))
    }

    fn lap(&mut self) -> Duration {
        match &mut self.0 {
            Some(t) => {
                let now = Instant::now();
                let d = now - *t;
                *t = now;
                d
            }
            None => Duration::ZERO,
        }
    }
}
