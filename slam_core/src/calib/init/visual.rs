//! Step 1 of [`super::initialize`]: the camera's relative rotations between frames a few
//! frames apart, from feature tracks only (no IMU, no `R_cb`).
//!
//! Per pair of frames `(i, j)`: the tracks seen in both are undistorted with the starting
//! camera to bearings `b_i`, `b_j`; a rotation-only RANSAC (two-point Kabsch,
//! `b_j ≈ R_ji b_i`) with a loose angular bound drops gross mismatches; then the
//! two-view motion `(R_ji, t)` (`X_j = R_ji X_i + t`, `|t| = 1`) is refined by damped
//! Gauss-Newton on the Sampson distance of the epipolar constraint `x_jᵀ [t]× R_ji x_i = 0`
//! (Hartley & Zisserman §11.4.3), Cauchy-weighted, from the rotation-only estimate and
//! three starting directions of `t`; the best is refitted on its inliers. Starting at the
//! rotation-only estimate keeps the refinement on the physical solution (not the "twisted
//! pair" 180° away) and, with a planar scene (AprilGrid) or no parallax (distant scene),
//! where `t` is not determined, the damping leaves `R` at the rotation-only value.
//!
//! Rolling shutter: the rotation is that of the middle rows to first order (features
//! spread over the rows), which is the frame stamp's convention (`VI_NOTES.md` §1).

use std::collections::HashMap;

use nalgebra::{Matrix3, SMatrix, SVector, Vector2, Vector3};

use super::{GyroTrack, InitFrame, InitParams};
use crate::calib::TrackId;
use crate::camera::PinholeRadtan;
use crate::lie::{skew, so3_exp};
use crate::ransac::{sample_distinct, SplitMix64};
use crate::twoview::{decompose_essential, essential_from_fundamental, fundamental_8point};

type Rot = nalgebra::Rotation3<f64>;

/// The camera's rotation between two frames (camera-clock middle-row stamps).
#[derive(Debug, Clone, PartialEq)]
pub struct VisualRotation {
    /// Stamp of the first frame, ns (camera clock: `t_mid` as given).
    pub t0_ns: i64,
    /// Stamp of the second frame, ns.
    pub t1_ns: i64,
    /// `R_c0c1 = R_wc0ᵀ R_wc1`: the second camera's orientation in the first's frame.
    pub r_c: Rot,
    /// Tracks seen in both frames.
    pub matches: usize,
    /// Matches within [`InitParams::inlier_px`] of their epipolar line at the solution.
    pub inliers: usize,
    /// RMS Sampson distance of the inliers, px.
    pub rms_px: f64,
}

/// Rolling-shutter compensation of a bearing (`VI_NOTES.md` §1: row `v` is taken at
/// `t_mid + t_d + (v/N - ½) t_r`): the bearing seen at its row's time is turned into the
/// middle row's camera frame with the gyro, `b_mid = R_cb ΔR_b(τ_mid, τ_row) R_cbᵀ b_row`.
pub struct Derotation<'a> {
    /// Bias-corrected gyro track.
    pub gyro: &'a GyroTrack,
    /// Camera-from-body rotation.
    pub r_cb: Rot,
    /// Time offset, s.
    pub t_d: f64,
    /// Readout time, s.
    pub t_r: f64,
}

impl Derotation<'_> {
    /// The bearing `b` seen `fraction` of the readout from the middle line
    /// ([`PinholeRadtan::readout_fraction`]) of the frame stamped `t_mid_ns`, in the middle
    /// line's camera frame (unchanged where the gyro does not reach).
    pub fn apply(&self, t_mid_ns: i64, fraction: f64, b: &Vector3<f64>) -> Vector3<f64> {
        let t0 = t_mid_ns as f64 + self.t_d * 1e9;
        let t1 = t0 + fraction * self.t_r * 1e9;
        self.gyro
            .delta(t0, t1)
            .map_or(*b, |d| self.r_cb * (d * (self.r_cb.inverse() * b)))
    }
}

/// The visual rotations of the frame pairs `(i, i + pair_gap)` (every `i`), skipping pairs
/// with fewer than [`InitParams::min_matches`] inliers. `frames` sorted by time. With
/// `derotate`, every bearing is first moved to its frame's middle-row time.
pub fn visual_rotations(
    frames: &[InitFrame],
    camera: &PinholeRadtan,
    derotate: Option<&Derotation>,
    params: &InitParams,
) -> Vec<VisualRotation> {
    let gap = params.pair_gap.max(1);
    let bearings: Vec<HashMap<TrackId, Vector3<f64>>> = frames
        .iter()
        .map(|f| {
            f.observations
                .iter()
                .map(|o| {
                    let b = camera.unproject(&o.uv);
                    let b = derotate.map_or(b, |d| {
                        d.apply(f.t_mid_ns, camera.readout_fraction(&o.uv), &b)
                    });
                    (o.track, b)
                })
                .collect()
        })
        .collect();
    let focal = (camera.fx * camera.fy).abs().sqrt();
    let mut out = Vec::new();
    for i in 0..frames.len().saturating_sub(gap) {
        let (b0, b1) = matched(&bearings[i], &bearings[i + gap]);
        if b0.len() < params.min_matches {
            continue;
        }
        let seed = params.seed ^ (i as u64).wrapping_mul(0x9E37_79B9);
        let Some(fit) = pair_rotation(&b0, &b1, focal, params, seed) else {
            continue;
        };
        if fit.inliers >= params.min_matches {
            out.push(VisualRotation {
                t0_ns: frames[i].t_mid_ns,
                t1_ns: frames[i + gap].t_mid_ns,
                r_c: fit.r_10.inverse(),
                matches: b0.len(),
                inliers: fit.inliers,
                rms_px: fit.rms_px,
            });
        }
    }
    out
}

/// The bearings of the tracks seen in both frames, in the same order.
fn matched(
    a: &HashMap<TrackId, Vector3<f64>>,
    b: &HashMap<TrackId, Vector3<f64>>,
) -> (Vec<Vector3<f64>>, Vec<Vector3<f64>>) {
    let mut ids: Vec<_> = a.keys().filter(|k| b.contains_key(k)).copied().collect();
    ids.sort_unstable();
    ids.iter().map(|k| (a[k], b[k])).unzip()
}

/// The fit of one pair: `R_10` (`X_1 = R_10 X_0 + t`).
struct PairFit {
    r_10: Rot,
    inliers: usize,
    rms_px: f64,
}

/// Rotation-only RANSAC, then the epipolar refinement from three directions of `t`, then a
/// refit on the inliers (module docs).
fn pair_rotation(
    b0: &[Vector3<f64>],
    b1: &[Vector3<f64>],
    focal: f64,
    params: &InitParams,
    seed: u64,
) -> Option<PairFit> {
    let (r0, inl) = rotation_ransac(b0, b1, params, seed)?;
    let (x0, x1) = normalised(b0, b1, &inl);
    let scale = params.inlier_px / focal;
    let mut best: Option<(f64, Rot, Vector3<f64>)> = None;
    for (r_start, t_start) in starts(&x0, &x1, &r0) {
        // Graduated: a wide Cauchy scale first (few local minima), then the fine one.
        let (r, t) = refine_epipolar(
            &x0,
            &x1,
            r_start,
            t_start,
            10.0 * scale,
            params.refine_iterations,
        );
        let (r, t) = refine_epipolar(&x0, &x1, r, t, scale, params.refine_iterations);
        let cost = robust_cost(&x0, &x1, &r, &t, scale);
        if best.as_ref().is_none_or(|b| cost < b.0) {
            best = Some((cost, r, t));
        }
    }
    let (_, r, t) = best?;
    // Refit on the epipolar inliers of all matches.
    let all: Vec<bool> = vec![true; b0.len()];
    let (ax0, ax1) = normalised(b0, b1, &all);
    let keep: Vec<bool> = sampson_all(&ax0, &ax1, &r, &t)
        .iter()
        .map(|d| d.abs() < scale)
        .collect();
    let (kx0, kx1) = normalised(b0, b1, &keep);
    if kx0.len() < 8 {
        return None;
    }
    let (r, t) = refine_epipolar(&kx0, &kx1, r, t, scale, params.refine_iterations);
    let d = sampson_all(&kx0, &kx1, &r, &t);
    let rms = (d.iter().map(|v| v * v).sum::<f64>() / d.len() as f64).sqrt() * focal;
    Some(PairFit {
        r_10: r,
        inliers: d.iter().filter(|v| v.abs() < scale).count(),
        rms_px: rms,
    })
}

/// Starting motions of the refinement: the rotation-only `R0` with `t` along each axis, and
/// the linear eight-point essential matrix's rotation nearest `R0` with its `t` (the linear
/// solution is exact without noise, but degenerate for a planar scene or no parallax).
fn starts(x0: &[Vector2<f64>], x1: &[Vector2<f64>], r0: &Rot) -> Vec<(Rot, Vector3<f64>)> {
    let mut out: Vec<(Rot, Vector3<f64>)> = [Vector3::x(), Vector3::y(), Vector3::z()]
        .into_iter()
        .map(|t| (*r0, t))
        .collect();
    let linear = fundamental_8point(x0, x1)
        .ok()
        .and_then(|f| essential_from_fundamental(&f))
        .and_then(|e| decompose_essential(&e).ok());
    if let Some(motions) = linear {
        let nearest = motions.iter().min_by(|a, b| {
            (r0.inverse() * a.0)
                .angle()
                .total_cmp(&(r0.inverse() * b.0).angle())
        });
        out.extend(nearest.copied());
    }
    out
}

/// Normalised image coordinates `(x/z, y/z)` of the kept bearings (in front of both).
fn normalised(
    b0: &[Vector3<f64>],
    b1: &[Vector3<f64>],
    keep: &[bool],
) -> (Vec<Vector2<f64>>, Vec<Vector2<f64>>) {
    b0.iter()
        .zip(b1)
        .zip(keep)
        .filter(|((a, b), &k)| k && a.z > 1e-6 && b.z > 1e-6)
        .map(|((a, b), _)| (a.xy() / a.z, b.xy() / b.z))
        .unzip()
}

/// Kabsch: the rotation `R` minimising `Σ |b1 - R b0|²` over the indexed pairs.
fn kabsch(b0: &[Vector3<f64>], b1: &[Vector3<f64>], idx: impl Iterator<Item = usize>) -> Rot {
    let mut h = Matrix3::zeros();
    for i in idx {
        h += b1[i] * b0[i].transpose();
    }
    let svd = h.svd(true, true);
    let (u, v_t) = (svd.u.unwrap_or_default(), svd.v_t.unwrap_or_default());
    let d = (u * v_t).determinant().signum();
    Rot::from_matrix_unchecked(u * Matrix3::from_diagonal(&Vector3::new(1.0, 1.0, d)) * v_t)
}

/// Two-point rotation-only RANSAC with the angular bound [`InitParams::rotation_ransac_rad`];
/// returns `R_10` refitted on its inliers and the inlier mask.
fn rotation_ransac(
    b0: &[Vector3<f64>],
    b1: &[Vector3<f64>],
    params: &InitParams,
    seed: u64,
) -> Option<(Rot, Vec<bool>)> {
    let mut rng = SplitMix64::new(seed);
    let cos_bound = params.rotation_ransac_rad.cos();
    let inliers = |r: &Rot| -> Vec<bool> {
        b0.iter()
            .zip(b1)
            .map(|(a, b)| (r * a).dot(b) > cos_bound)
            .collect()
    };
    let mut best: Option<(usize, Rot)> = None;
    let mut pick = [0usize; 2];
    for _ in 0..params.ransac_iterations {
        if !sample_distinct(&mut rng, b0.len(), &mut pick) {
            return None;
        }
        let r = kabsch(b0, b1, pick.iter().copied());
        let n = inliers(&r).iter().filter(|&&k| k).count();
        if best.as_ref().is_none_or(|b| n > b.0) {
            best = Some((n, r));
        }
    }
    let (_, r) = best?;
    let mask = inliers(&r);
    let r = kabsch(b0, b1, (0..b0.len()).filter(|&i| mask[i]));
    let mask = inliers(&r);
    Some((r, mask))
}

/// Signed Sampson distances (normalised units) of `x1ᵀ E x0 = 0`, `E = [t]× R`.
fn sampson_all(x0: &[Vector2<f64>], x1: &[Vector2<f64>], r: &Rot, t: &Vector3<f64>) -> Vec<f64> {
    let e = skew(t) * r.matrix();
    x0.iter()
        .zip(x1)
        .map(|(a, b)| {
            let (ha, hb) = (a.push(1.0), b.push(1.0));
            let (ea, etb) = (e * ha, e.transpose() * hb);
            let den = (ea.x * ea.x + ea.y * ea.y + etb.x * etb.x + etb.y * etb.y).sqrt();
            if den > 0.0 {
                hb.dot(&ea) / den
            } else {
                0.0
            }
        })
        .collect()
}

/// Σ Cauchy loss `s² ln(1 + (d/s)²)` of the Sampson distances.
fn robust_cost(x0: &[Vector2<f64>], x1: &[Vector2<f64>], r: &Rot, t: &Vector3<f64>, s: f64) -> f64 {
    sampson_all(x0, x1, r, t)
        .iter()
        .map(|d| s * s * (1.0 + (d / s).powi(2)).ln())
        .sum()
}

/// Two unit vectors orthogonal to `t` (the tangent of the sphere at `t`).
fn tangent(t: &Vector3<f64>) -> (Vector3<f64>, Vector3<f64>) {
    let a = if t.x.abs() < 0.9 {
        Vector3::x()
    } else {
        Vector3::y()
    };
    let u = t.cross(&a).normalize();
    (u, t.cross(&u))
}

/// Applies the 5-vector step `(δθ, α)`: `R ← Exp(δθ) R`, `t ← normalise(t + α₁ u + α₂ w)`.
fn apply_step(r: &Rot, t: &Vector3<f64>, dx: &SVector<f64, 5>) -> (Rot, Vector3<f64>) {
    let (u, w) = tangent(t);
    let r = so3_exp(&Vector3::new(dx[0], dx[1], dx[2])) * r;
    (r, (t + u * dx[3] + w * dx[4]).normalize())
}

/// Levenberg-Marquardt on `(R, t)` minimising the Cauchy-weighted Sampson distances (scale
/// `s`, normalised units), numeric Jacobian (5 unknowns).
fn refine_epipolar(
    x0: &[Vector2<f64>],
    x1: &[Vector2<f64>],
    mut r: Rot,
    mut t: Vector3<f64>,
    s: f64,
    iterations: usize,
) -> (Rot, Vector3<f64>) {
    let mut lambda = 1e-3;
    let mut cost = robust_cost(x0, x1, &r, &t, s);
    for _ in 0..iterations {
        let d0 = sampson_all(x0, x1, &r, &t);
        let jac: Vec<Vec<f64>> = (0..5)
            .map(|k| {
                let mut dx = SVector::<f64, 5>::zeros();
                dx[k] = 1e-7;
                let (rk, tk) = apply_step(&r, &t, &dx);
                let dk = sampson_all(x0, x1, &rk, &tk);
                dk.iter().zip(&d0).map(|(a, b)| (a - b) / 1e-7).collect()
            })
            .collect();
        let (mut h, mut g) = (SMatrix::<f64, 5, 5>::zeros(), SVector::<f64, 5>::zeros());
        for (i, d) in d0.iter().enumerate() {
            let w = 1.0 / (1.0 + (d / s).powi(2));
            let j = SVector::<f64, 5>::from_fn(|k, _| jac[k][i]);
            h += j * j.transpose() * w;
            g += j * (w * d);
        }
        let mut improved = false;
        for _ in 0..8 {
            let mut hd = h;
            for k in 0..5 {
                hd[(k, k)] += lambda * (h[(k, k)] + 1e-12);
            }
            let Some(dx) = hd.cholesky().map(|c| c.solve(&-g)) else {
                lambda *= 10.0;
                continue;
            };
            let (rn, tn) = apply_step(&r, &t, &dx);
            let cn = robust_cost(x0, x1, &rn, &tn, s);
            if cn < cost {
                (r, t, cost) = (rn, tn, cn);
                lambda = (lambda * 0.3).max(1e-9);
                improved = dx.norm() > 1e-10;
                break;
            }
            lambda *= 10.0;
        }
        if !improved {
            break;
        }
    }
    (r, t)
}
