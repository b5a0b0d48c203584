//! The scale of the ORB pyramid, carried with the features it produced.
//!
//! A keypoint detected on level `o` of a pyramid with factor `s` has a patch `s^o` times
//! the level-0 one and a position noise `σ = s^o` pixels (ORB-SLAM's convention; Mur-Artal
//! et al. 2015, section V). Everything that weighs or searches keypoints by octave reads the
//! factor and the per-level tables from the [`PyramidScale`] of the feature set
//! ([`super::OrbFeatures::scale`]), computed once by the extractor.

use std::sync::Arc;

use crate::optim::inv_sigma2_for_octave;

/// Scale between two consecutive ORB pyramid levels (ORB-SLAM's 1.2): the extractor's
/// default ([`super::OrbParams::scale_factor`]) and the factor of feature sets that do not
/// come from an extractor. The one place this number is written.
///
/// The shared-memory keyframe messages (`shm_schema::KeypointRecord`,
/// `shm_schema::LoopKeypointRecord`) carry each keypoint's octave but not the factor: the
/// server side (mapper, loop closer) rebuilds their features with this constant, which
/// therefore must be the clients' extractor factor.
pub const ORB_SCALE_FACTOR: f64 = 1.2;

/// Default number of ORB pyramid levels (ORB-SLAM's 8).
pub const ORB_N_LEVELS: usize = 8;

/// Most pyramid levels an extractor supports (and the size of the tables).
pub const MAX_LEVELS: usize = 32;

/// Per-level scale and keypoint uncertainty of one ORB pyramid, computed once.
///
/// Octaves at or beyond [`MAX_LEVELS`] (possible in keypoints read from a message) fall
/// back to computing the same formulas. The tables are shared (cloning is a reference-count
/// increment, no allocation).
#[derive(Debug, Clone, PartialEq)]
#[cfg_attr(
    feature = "serde",
    derive(serde::Serialize, serde::Deserialize),
    serde(into = "ScaleParams", from = "ScaleParams")
)]
pub struct PyramidScale {
    /// Scale between consecutive levels.
    factor: f64,
    /// Levels of the pyramid (1..=[`MAX_LEVELS`]).
    n_levels: usize,
    tables: Arc<Tables>,
}

/// The per-octave tables of a [`PyramidScale`].
#[derive(Debug, PartialEq)]
struct Tables {
    /// `factor^o` in single precision (`(factor as f32).powi(o)`): search radii, patch sizes.
    level_scale: [f32; MAX_LEVELS],
    /// `1 / σ²` with `σ = factor^o` pixels ([`inv_sigma2_for_octave`]).
    inv_sigma2: [f64; MAX_LEVELS],
    /// `σ²` as `1 / inv_sigma2` (so that `σ²` and `1 / σ²` are exact reciprocals).
    sigma2: [f64; MAX_LEVELS],
}

impl PyramidScale {
    /// The tables of a pyramid of `n_levels` levels (clamped to 1..=[`MAX_LEVELS`]) with
    /// `factor` between levels (> 1; the extractor checks it).
    pub fn new(factor: f64, n_levels: usize) -> Self {
        let inv_sigma2: [f64; MAX_LEVELS] =
            std::array::from_fn(|o| inv_sigma2_for_octave(o as u32, factor));
        Self {
            factor,
            n_levels: n_levels.clamp(1, MAX_LEVELS),
            tables: Arc::new(Tables {
                level_scale: std::array::from_fn(|o| powi_f32(factor as f32, o as u32)),
                inv_sigma2,
                sigma2: inv_sigma2.map(|w| 1.0 / w),
            }),
        }
    }

    /// Scale between two consecutive levels.
    pub fn factor(&self) -> f64 {
        self.factor
    }

    /// Number of levels of the pyramid.
    pub fn n_levels(&self) -> usize {
        self.n_levels
    }

    /// The coarsest octave, `n_levels - 1`.
    pub fn max_octave(&self) -> u8 {
        (self.n_levels - 1).min(u8::MAX as usize) as u8
    }

    /// Scale of octave `o` relative to level 0, `factor^o` (single precision, as the
    /// search windows and patch sizes use it).
    pub fn level_scale(&self, octave: u8) -> f32 {
        match self.tables.level_scale.get(octave as usize) {
            Some(&s) => s,
            None => powi_f32(self.factor as f32, u32::from(octave)),
        }
    }

    /// Information `1 / σ²` (pixels⁻²) of a keypoint of octave `o`, `σ = factor^o`.
    pub fn inv_sigma2(&self, octave: u8) -> f64 {
        match self.tables.inv_sigma2.get(octave as usize) {
            Some(&w) => w,
            None => inv_sigma2_for_octave(u32::from(octave), self.factor),
        }
    }

    /// Variance `σ²` (pixels²) of a keypoint of octave `o`.
    pub fn sigma2(&self, octave: u8) -> f64 {
        match self.tables.sigma2.get(octave as usize) {
            Some(&s) => s,
            None => 1.0 / inv_sigma2_for_octave(u32::from(octave), self.factor),
        }
    }
}

/// `a^n` by binary exponentiation: the algorithm `f32::powi` / `f64::powi` run at run time
/// (compiler-builtins' `__powisf2` / `__powidf2`), written out so that the result does not
/// depend on whether the compiler folds a constant call (LLVM folds `powi` of constants with
/// the host's `pow`, which can differ in the last bit).
fn powi_by_squaring<T: Copy + std::ops::Mul<Output = T>>(a: T, n: u32, one: T) -> T {
    let (mut base, mut n, mut acc) = (a, n, one);
    loop {
        if n & 1 == 1 {
            acc = acc * base;
        }
        n >>= 1;
        if n == 0 {
            return acc;
        }
        base = base * base;
    }
}

/// [`powi_by_squaring`] in single precision.
pub(crate) fn powi_f32(a: f32, n: u32) -> f32 {
    powi_by_squaring(a, n, 1.0)
}

/// [`powi_by_squaring`] in double precision.
pub(crate) fn powi_f64(a: f64, n: u32) -> f64 {
    powi_by_squaring(a, n, 1.0)
}

impl Default for PyramidScale {
    /// [`ORB_SCALE_FACTOR`] and [`ORB_N_LEVELS`].
    fn default() -> Self {
        Self::new(ORB_SCALE_FACTOR, ORB_N_LEVELS)
    }
}

/// What a saved [`PyramidScale`] holds: the tables are rebuilt from it.
#[cfg(feature = "serde")]
#[derive(serde::Serialize, serde::Deserialize)]
struct ScaleParams {
    factor: f64,
    n_levels: usize,
}

#[cfg(feature = "serde")]
impl From<PyramidScale> for ScaleParams {
    fn from(s: PyramidScale) -> Self {
        Self {
            factor: s.factor,
            n_levels: s.n_levels,
        }
    }
}

#[cfg(feature = "serde")]
impl From<ScaleParams> for PyramidScale {
    fn from(p: ScaleParams) -> Self {
        Self::new(p.factor, p.n_levels)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn tables_match_the_formulas() {
        let s = PyramidScale::default();
        assert_eq!(s.n_levels(), ORB_N_LEVELS);
        assert_eq!(s.max_octave(), 7);
        for o in [0u8, 1, 3, 7, 31, 32, 200] {
            // Opaque inputs: `powi` evaluated at run time (not folded by the compiler).
            let (f, o32) = (std::hint::black_box(ORB_SCALE_FACTOR), u32::from(o));
            let o = std::hint::black_box(o);
            assert_eq!(s.level_scale(o), (f as f32).powi(i32::from(o)));
            assert_eq!(s.inv_sigma2(o), inv_sigma2_for_octave(o32, f));
            assert_eq!(s.sigma2(o), 1.0 / inv_sigma2_for_octave(o32, f));
        }
        assert_eq!(s.inv_sigma2(0), 1.0);
    }

    #[test]
    fn binary_exponentiation_is_powi() {
        for f in [ORB_SCALE_FACTOR, 1.5, 2.0, 1.1] {
            for n in 0..=255u32 {
                let (f, n) = std::hint::black_box((f, n));
                assert_eq!(powi_f32(f as f32, n), (f as f32).powi(n as i32), "{f}^{n}");
                assert_eq!(powi_f64(f, n), f.powi(n as i32), "{f}^{n}");
            }
        }
    }
}
