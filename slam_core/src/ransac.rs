//! Deterministic RANSAC helpers: a small seeded random generator, distinct-index sampling
//! and the classic adaptive iteration count.
//!
//! Every estimator of this crate that uses RANSAC (two-view initialisation, PnP) takes a
//! `seed` and draws its minimal sets from [`SplitMix64`], so a run is reproducible bit for
//! bit on every platform (no dependency on `rand`).

/// A tiny, fast, seedable generator (SplitMix64, Steele, Lea & Flood 2014). Not
/// cryptographic; good enough to draw RANSAC samples.
#[derive(Debug, Clone)]
pub struct SplitMix64 {
    state: u64,
}

impl SplitMix64 {
    /// A generator started from `seed` (any value, 0 included).
    pub fn new(seed: u64) -> Self {
        Self { state: seed }
    }

    /// The next 64 random bits.
    #[inline]
    pub fn next_u64(&mut self) -> u64 {
        self.state = self.state.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.state;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^ (z >> 31)
    }

    /// A uniform integer in `0..n` (`n > 0`; returns 0 when `n == 0`). Uses Lemire's
    /// multiply-shift, whose bias is below 2⁻³² for the sizes used here.
    #[inline]
    pub fn below(&mut self, n: usize) -> usize {
        if n == 0 {
            return 0;
        }
        ((u128::from(self.next_u64()) * n as u128) >> 64) as usize
    }

    /// A uniform `f64` in `[0, 1)`.
    #[inline]
    pub fn next_f64(&mut self) -> f64 {
        (self.next_u64() >> 11) as f64 * (1.0 / (1u64 << 53) as f64)
    }
}

/// Fills `out` with `out.len()` distinct indices drawn uniformly from `0..n`.
///
/// Rejection sampling, meant for the small sets of RANSAC (`out.len()` ≤ 8). Returns
/// `false` (leaving `out` unspecified) when `n < out.len()`.
pub fn sample_distinct(rng: &mut SplitMix64, n: usize, out: &mut [usize]) -> bool {
    if n < out.len() {
        return false;
    }
    let mut k = 0;
    while k < out.len() {
        let c = rng.below(n);
        if !out[..k].contains(&c) {
            out[k] = c;
            k += 1;
        }
    }
    true
}

/// The number of RANSAC iterations that draws at least one all-inlier sample of size
/// `sample_size` with probability `confidence`, given the inlier ratio `inlier_ratio`:
/// `log(1 - p) / log(1 - w^s)` (Fischler & Bolles 1981), clamped to `[1, max_iters]`.
pub fn adaptive_iterations(
    inlier_ratio: f64,
    sample_size: usize,
    confidence: f64,
    max_iters: usize,
) -> usize {
    let w = inlier_ratio.clamp(0.0, 1.0);
    let p = confidence.clamp(0.0, 1.0 - 1e-12);
    let ws = w.powi(sample_size.min(64) as i32);
    if ws >= 1.0 - 1e-15 {
        return 1;
    }
    if ws <= 0.0 {
        return max_iters.max(1);
    }
    let k = (1.0 - p).ln() / (1.0 - ws).ln();
    if !k.is_finite() {
        return max_iters.max(1);
    }
    (k.ceil() as usize).clamp(1, max_iters.max(1))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn deterministic_and_distinct() {
        let mut a = SplitMix64::new(7);
        let mut b = SplitMix64::new(7);
        for _ in 0..100 {
            assert_eq!(a.next_u64(), b.next_u64());
        }
        let mut s = [0usize; 8];
        for _ in 0..1000 {
            assert!(sample_distinct(&mut a, 10, &mut s));
            for i in 0..8 {
                assert!(s[i] < 10);
                assert!(!s[..i].contains(&s[i]));
            }
        }
        assert!(!sample_distinct(&mut a, 3, &mut s));
        let f = a.next_f64();
        assert!((0.0..1.0).contains(&f));
        assert_eq!(a.below(0), 0);
    }

    #[test]
    fn iteration_count() {
        assert_eq!(adaptive_iterations(1.0, 4, 0.99, 200), 1);
        assert_eq!(adaptive_iterations(0.0, 4, 0.99, 200), 200);
        // 50% inliers, 8-point samples, 99%: ~1177 iterations.
        let k = adaptive_iterations(0.5, 8, 0.99, 10_000);
        assert!((1170..=1180).contains(&k), "{k}");
    }
}
