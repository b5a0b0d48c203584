//! Steps 2-3 of [`super::initialize`]: the gyro's orientation track and the time offset `t_d`
//! (`VI_NOTES.md` §1: the IMU time of a frame's middle row is `t_mid + t_d`).
//!
//! **Coarse** ([`coarse_time_offset`]): the rotation angle of a rigid body between two
//! instants is the same in every frame attached to it, `|Log(R_cb ΔR_b R_cbᵀ)| = |ΔR_b|`,
//! so the visual angles `θ_v,k = |Log R_c,k|` can be compared with the gyro's angles over
//! the shifted intervals `θ_g,k(s) = |Log ΔR_b(t0_k + s, t1_k + s)|` before `R_cb` is
//! known. `t_d` maximises the normalised cross-correlation `ρ(s)` of the two sequences over
//! `|s| ≤` [`super::InitParams::max_shift_s`] on a grid, refined by a parabola through the
//! peak and its neighbours. Quality: the peak `ρ`, and the highest other local maximum of
//! `ρ` (an ambiguity: periodic motion gives several peaks).
//!
//! **Fine** ([`fine_time_offset`]): once `R_bc` and the gyro bias are known, the full
//! residual `Σ |Log(ΔR_b(s)ᵀ R_bc R_c,k R_bcᵀ)|²` (the hand-eye constraint of
//! [`crate::imu::extrinsic_rotation`]) is minimised over a small grid around the coarse
//! value, again with a parabola; pairs beyond 3 × the median residual are left out.

use nalgebra::{Rotation3, UnitQuaternion, Vector3};

use super::visual::VisualRotation;
use super::InitParams;
use crate::calib::ImuSample;
use crate::lie::{quat_exp, so3_log};

/// The gyro-integrated body orientation `R_b0,b(t)` at every sample, bias-corrected.
pub struct GyroTrack {
    t_ns: Vec<i64>,
    q: Vec<UnitQuaternion<f64>>,
    /// Mean corrected rate over `[t_k, t_k+1]`.
    w: Vec<Vector3<f64>>,
}

impl GyroTrack {
    /// Integrates `ω_m - b_g` with the trapezoidal rate per sample interval.
    pub fn new(samples: &[ImuSample], gyro_bias: &Vector3<f64>) -> Self {
        let mut q = Vec::with_capacity(samples.len());
        let mut w = Vec::with_capacity(samples.len());
        let mut cur = UnitQuaternion::identity();
        for (k, s) in samples.iter().enumerate() {
            q.push(cur);
            let rate = samples
                .get(k + 1)
                .map_or(Vector3::zeros(), |n| 0.5 * (s.gyro + n.gyro) - gyro_bias);
            w.push(rate);
            if let Some(n) = samples.get(k + 1) {
                cur *= quat_exp(&(rate * ((n.t_ns - s.t_ns) as f64 * 1e-9)));
            }
        }
        Self {
            t_ns: samples.iter().map(|s| s.t_ns).collect(),
            q,
            w,
        }
    }

    /// First and last sample times, ns.
    pub fn span(&self) -> Option<(i64, i64)> {
        Some((*self.t_ns.first()?, *self.t_ns.last()?))
    }

    /// `R_b0,b(t)`, `t` in ns; `None` outside the samples.
    pub fn at(&self, t_ns: f64) -> Option<UnitQuaternion<f64>> {
        let (t0, t1) = self.span()?;
        if t_ns < t0 as f64 || t_ns > t1 as f64 {
            return None;
        }
        let k = self
            .t_ns
            .partition_point(|&t| (t as f64) <= t_ns)
            .saturating_sub(1);
        let dt = (t_ns - self.t_ns[k] as f64) * 1e-9;
        Some(self.q[k] * quat_exp(&(self.w[k] * dt)))
    }

    /// The body's turn `ΔR_b = R_b0,b(t0)ᵀ R_b0,b(t1)` between two IMU-clock times (ns).
    pub fn delta(&self, t0_ns: f64, t1_ns: f64) -> Option<Rotation3<f64>> {
        Some((self.at(t0_ns)?.inverse() * self.at(t1_ns)?).to_rotation_matrix())
    }
}

/// The coarse `t_d` and its quality.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TimeOffsetQuality {
    /// Coarse estimate from the angle correlation, s.
    pub coarse_s: f64,
    /// Normalised cross-correlation of the visual and gyro angles at the coarse peak.
    pub peak: f64,
    /// The highest other local maximum of the correlation (1 would be fully ambiguous).
    pub second_peak: f64,
    /// Where that other maximum lies, s.
    pub second_peak_s: f64,
    /// Visual rotations that entered the correlation.
    pub pairs: usize,
    /// RMS rotation residual at the rotation-fit `t_d` with its `R_cb`, rad.
    pub fine_rms_rad: f64,
    /// `t_d` of the rotation fit (step 3), before the epipolar refinement, s.
    pub visual_s: f64,
}

/// The pairs whose shifted intervals stay inside the gyro track for every `|s| ≤ max`.
pub fn covered<'a>(
    rots: &'a [VisualRotation],
    gyro: &GyroTrack,
    max_shift_s: f64,
) -> Vec<&'a VisualRotation> {
    let Some((a, b)) = gyro.span() else {
        return Vec::new();
    };
    let m = max_shift_s * 1e9;
    rots.iter()
        .filter(|r| r.t0_ns as f64 - m >= a as f64 && r.t1_ns as f64 + m <= b as f64)
        .collect()
}

/// Normalised cross-correlation of two equally long sequences (NaN without spread).
fn ncc(a: &[f64], b: &[f64]) -> f64 {
    let n = a.len() as f64;
    let (ma, mb) = (a.iter().sum::<f64>() / n, b.iter().sum::<f64>() / n);
    let (mut sab, mut saa, mut sbb) = (0.0, 0.0, 0.0);
    for (x, y) in a.iter().zip(b) {
        sab += (x - ma) * (y - mb);
        saa += (x - ma).powi(2);
        sbb += (y - mb).powi(2);
    }
    sab / (saa * sbb).sqrt()
}

/// The vertex of the parabola through `(-1, a), (0, b), (1, c)`, clamped to `[-1, 1]`.
fn parabola_vertex(a: f64, b: f64, c: f64) -> f64 {
    let den = a - 2.0 * b + c;
    if den.abs() < 1e-300 {
        0.0
    } else {
        (0.5 * (a - c) / den).clamp(-1.0, 1.0)
    }
}

/// Coarse `t_d` from the angle correlation (module docs): `(t_d s, quality)`, or `None`
/// when the correlation is undefined (no motion, no pairs).
pub fn coarse_time_offset(
    rots: &[&VisualRotation],
    gyro: &GyroTrack,
    params: &InitParams,
) -> Option<(f64, TimeOffsetQuality)> {
    let theta_v: Vec<f64> = rots.iter().map(|r| so3_log(&r.r_c).norm()).collect();
    let n = (params.max_shift_s / params.shift_step_s).round() as i64;
    let shifts: Vec<f64> = (-n..=n).map(|k| k as f64 * params.shift_step_s).collect();
    let rho: Vec<f64> = shifts
        .iter()
        .map(|s| {
            let theta_g: Option<Vec<f64>> = rots
                .iter()
                .map(|r| {
                    let d = gyro.delta(r.t0_ns as f64 + s * 1e9, r.t1_ns as f64 + s * 1e9)?;
                    Some(so3_log(&d).norm())
                })
                .collect();
            theta_g.map_or(f64::NAN, |g| ncc(&theta_v, &g))
        })
        .collect();
    let (ipk, &peak) = rho
        .iter()
        .enumerate()
        .filter(|(_, v)| v.is_finite())
        .max_by(|a, b| a.1.total_cmp(b.1))?;
    let off = if ipk > 0 && ipk + 1 < rho.len() {
        parabola_vertex(rho[ipk - 1], peak, rho[ipk + 1])
    } else {
        0.0
    };
    let t_d = shifts[ipk] + off * params.shift_step_s;
    let (second_peak_s, second_peak) = second_maximum(&shifts, &rho, t_d, params.peak_separation_s);
    Some((
        t_d,
        TimeOffsetQuality {
            coarse_s: t_d,
            peak,
            second_peak,
            second_peak_s,
            pairs: rots.len(),
            fine_rms_rad: f64::NAN,
            visual_s: f64::NAN,
        },
    ))
}

/// The highest local maximum of `rho` farther than `sep` from `at` (`(NaN, -1)` if none).
fn second_maximum(shifts: &[f64], rho: &[f64], at: f64, sep: f64) -> (f64, f64) {
    let mut best = (f64::NAN, -1.0);
    for k in 1..rho.len().saturating_sub(1) {
        let local = rho[k] >= rho[k - 1] && rho[k] >= rho[k + 1];
        if local && (shifts[k] - at).abs() > sep && rho[k] > best.1 {
            best = (shifts[k], rho[k]);
        }
    }
    best
}

/// Squared hand-eye residual angles `|Log(ΔR_b(s)ᵀ R_bc R_c R_bcᵀ)|²` of the pairs at shift
/// `s` (s); `None` if a pair leaves the gyro track.
fn residuals(
    rots: &[&VisualRotation],
    gyro: &GyroTrack,
    r_bc: &Rotation3<f64>,
    s: f64,
) -> Option<Vec<f64>> {
    rots.iter()
        .map(|r| {
            let d = gyro.delta(r.t0_ns as f64 + s * 1e9, r.t1_ns as f64 + s * 1e9)?;
            Some(so3_log(&(d.inverse() * r_bc * r.r_c * r_bc.inverse())).norm_squared())
        })
        .collect()
}

/// `Σ |φ_v,k − D φ_g,k(s)|²` in the camera frame: the visual rotation vectors
/// `φ_v = Log R_c` against the gyro's `φ_g = R_cb Log ΔR_b(s)`, with the per-axis scale `D`
/// fitted in closed form at each `s`. `D` absorbs the starting camera's focal-length error
/// (a focal length off by ε scales the rotations about the camera's x and y axes by
/// ~1 + ε) and most of a rolling shutter's stretch, which would otherwise pull `t_d` (on the
/// simulation: 2.6 ms with a camera 5 px off, 0.7 ms with the true camera).
fn scaled_cost(
    rots: &[&VisualRotation],
    gyro: &GyroTrack,
    r_bc: &Rotation3<f64>,
    s: f64,
) -> Option<f64> {
    let r_cb = r_bc.inverse();
    let pairs: Vec<(Vector3<f64>, Vector3<f64>)> = rots
        .iter()
        .map(|r| {
            let d = gyro.delta(r.t0_ns as f64 + s * 1e9, r.t1_ns as f64 + s * 1e9)?;
            Some((so3_log(&r.r_c), r_cb * so3_log(&d)))
        })
        .collect::<Option<_>>()?;
    let mut cost = 0.0;
    for a in 0..3 {
        let (vg, gg) = pairs.iter().fold((0.0, 0.0), |(x, y), (v, g)| {
            (x + v[a] * g[a], y + g[a] * g[a])
        });
        let d = if gg > 0.0 { vg / gg } else { 1.0 };
        cost += pairs
            .iter()
            .map(|(v, g)| (v[a] - d * g[a]).powi(2))
            .sum::<f64>();
    }
    Some(cost)
}

/// Fine `t_d` around `t_d0` (module docs): `(t_d s, RMS residual rad)`. `gyro` must be
/// bias-corrected.
pub fn fine_time_offset(
    rots: &[&VisualRotation],
    gyro: &GyroTrack,
    r_bc: &Rotation3<f64>,
    t_d0: f64,
    params: &InitParams,
) -> Option<(f64, f64)> {
    let mut at0 = residuals(rots, gyro, r_bc, t_d0)?;
    let keep_below = {
        let mut sorted = at0.clone();
        sorted.sort_by(f64::total_cmp);
        9.0 * sorted[sorted.len() / 2]
    };
    let keep: Vec<bool> = at0.iter().map(|&e| e <= keep_below).collect();
    let kept: Vec<&VisualRotation> = rots
        .iter()
        .zip(&keep)
        .filter(|(_, &k)| k)
        .map(|(r, _)| *r)
        .collect();
    let cost = |s: f64| scaled_cost(&kept, gyro, r_bc, s).unwrap_or(f64::INFINITY);
    let step = params.fine_step_s;
    let n = (params.fine_half_width_s / step).round() as i64;
    let shifts: Vec<f64> = (-n..=n).map(|k| t_d0 + k as f64 * step).collect();
    let costs: Vec<f64> = shifts.iter().map(|&s| cost(s)).collect();
    let (imin, &cmin) = costs.iter().enumerate().min_by(|a, b| a.1.total_cmp(b.1))?;
    let off = if imin > 0 && imin + 1 < costs.len() {
        parabola_vertex(costs[imin - 1], cmin, costs[imin + 1])
    } else {
        0.0
    };
    let t_d = shifts[imin] + off * step;
    at0 = residuals(rots, gyro, r_bc, t_d)?;
    let used: Vec<f64> = at0
        .iter()
        .zip(&keep)
        .filter(|(_, &k)| k)
        .map(|(v, _)| *v)
        .collect();
    let rms = (used.iter().sum::<f64>() / used.len().max(1) as f64).sqrt();
    Some((t_d, rms))
}
