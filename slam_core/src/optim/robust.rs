//! Robust kernels on the squared Mahalanobis error `s = χ² = rᵀ Ω r` (the g2o convention:
//! the cost of a residual is `ρ(s)`, and iteratively reweighted least squares scales its
//! normal-equation contribution by `ρ'(s)`).

/// A robust loss applied to a squared error.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum RobustKernel {
    /// Plain least squares: `ρ(s) = s`.
    None,
    /// Huber with threshold `delta` on `√s`: `ρ(s) = s` for `s ≤ δ²`, else `2δ√s - δ²`.
    /// ORB-SLAM uses `δ = √5.991` for monocular observations.
    Huber {
        /// Threshold on the (whitened) residual norm.
        delta: f64,
    },
    /// Cauchy: `ρ(s) = c² ln(1 + s / c²)`.
    Cauchy {
        /// Scale `c`.
        c: f64,
    },
}

impl RobustKernel {
    /// The robust cost `ρ(s)` of a squared error `s ≥ 0`.
    #[inline]
    pub fn cost(&self, s: f64) -> f64 {
        match *self {
            Self::None => s,
            Self::Huber { delta } => {
                if s <= delta * delta {
                    s
                } else {
                    2.0 * delta * s.sqrt() - delta * delta
                }
            }
            Self::Cauchy { c } => {
                let c2 = c * c;
                c2 * (s / c2).ln_1p()
            }
        }
    }

    /// The IRLS weight `ρ'(s)` of a squared error `s ≥ 0` (1 for small errors).
    #[inline]
    pub fn weight(&self, s: f64) -> f64 {
        match *self {
            Self::None => 1.0,
            Self::Huber { delta } => {
                if s <= delta * delta {
                    1.0
                } else {
                    delta / s.sqrt()
                }
            }
            Self::Cauchy { c } => {
                let c2 = c * c;
                c2 / (c2 + s)
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn kernels_are_consistent() {
        for k in [
            RobustKernel::None,
            RobustKernel::Huber { delta: 2.0 },
            RobustKernel::Cauchy { c: 1.5 },
        ] {
            for s in [0.0, 0.5, 3.9, 4.1, 100.0] {
                // weight = d cost / d s
                let h = 1e-6;
                let num = (k.cost(s + h) - k.cost((s - h).max(0.0))) / (s + h - (s - h).max(0.0));
                assert!((num - k.weight(s)).abs() < 1e-4, "{k:?} at {s}");
                assert!(k.cost(s) <= s + 1e-12);
            }
        }
    }
}
