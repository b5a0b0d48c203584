//! Step 4 of [`super::initialize`]: gravity, the starting velocity and the IMU biases from
//! the camera's translation *directions* and the preintegrated IMU (a scale-free variant of
//! the VINS-Mono alignment of `VI_NOTES.md` §4 "VI initialisation").
//!
//! With `R_cb`, `t_d` and the gyro known, the rotation between frames `i, j` is the gyro's,
//! `R_ji = R_cb ΔR_b(τ_i, τ_j)ᵀ R_cbᵀ` (`τ = t_mid + t_d`), and the epipolar constraint
//! `x_jᵀ [t]× R_ji x_i = 0` is linear in the translation: `t ⟂ m_k = R_ji b_i × b_j`, so `t` is
//! the eigenvector of the smallest eigenvalue of `Σ m_k m_kᵀ` (sign by cheirality). The
//! camera centre moves along `u = R_b0,b(τ_i) R_bc (−R_jiᵀ t)` (first body frame b0).
//! In b0, with the preintegration from the start (Forster et al.; `VI_NOTES.md` §4),
//! ```text
//! c(τ) = v0 τ' + ½ g τ'² + Δp(τ) + J^p_g δb_g + J^p_a δb_a + ΔR(τ) p_bc,   τ' = τ − t0
//! u × (c(τ_j) − c(τ_i)) = 0                      (2 independent rows per pair)
//! ```
//! is linear in `x = (v0, g, δb_g, δb_a)` (12 unknowns; weak priors on the biases). It is
//! solved with Huber reweighting, re-integrated at the new biases and solved again. `R_gb0`
//! turns `−g` onto `+z` (yaw arbitrary), `v_g = R_gb0 v0`; `|g|` is a check (9.81).

use nalgebra::{Matrix3, SMatrix, SVector, Vector3};

use super::visual::Derotation;
use super::{GyroTrack, InitFrame, InitParams};
use crate::calib::integrate::segments;
use crate::calib::{ImuSample, TrackId};
use crate::camera::PinholeRadtan;
use crate::imu::{ImuBiases, ImuIntrinsics, Preintegrated, PreintegrationParams};
use crate::lie::skew;

type Rot = nalgebra::Rotation3<f64>;
type Vec12 = SVector<f64, 12>;
type Mat12 = SMatrix<f64, 12, 12>;
/// Matched bearings of one frame pair.
type Matched = Vec<(Vector3<f64>, Vector3<f64>)>;

/// What the alignment found.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Alignment {
    /// `R_gb` at the start (gravity along `−z`).
    pub r_gb: Rot,
    /// Velocity at the start in the global frame, m/s.
    pub v_gb: Vector3<f64>,
    /// Gyro and accelerometer biases.
    pub biases: ImuBiases,
    /// `|g|` found, m/s² (9.81 when the data fit).
    pub gravity_norm: f64,
    /// 1σ of the gravity direction, rad (from the normal matrix and the residuals).
    pub sigma_theta: f64,
    /// 1σ of the velocity, m/s (largest axis).
    pub sigma_velocity: f64,
    /// Pairs used.
    pub pairs: usize,
}

/// The known parts of the problem.
pub struct AlignInput<'a> {
    /// IMU samples from the start.
    pub imu: &'a [ImuSample],
    /// Frames.
    pub frames: &'a [InitFrame],
    /// Starting camera.
    pub camera: &'a PinholeRadtan,
    /// Camera-from-body rotation.
    pub r_cb: Rot,
    /// Body origin in the camera frame (the guess), m.
    pub p_cb: Vector3<f64>,
    /// Time offset, s.
    pub t_d: f64,
    /// Readout time guess, s.
    pub t_r: f64,
    /// Starting biases.
    pub biases: ImuBiases,
}

/// Runs the alignment (module docs); `None` when it is not determined.
pub fn align(input: &AlignInput, params: &InitParams) -> Option<Alignment> {
    let mut biases = input.biases;
    let mut last = None;
    for _ in 0..params.align_iterations.max(1) {
        let sys = System::build(input, &biases, params)?;
        let (x, cov) = sys.solve(params)?;
        biases.gyro += x.fixed_rows::<3>(6);
        biases.accel += x.fixed_rows::<3>(9);
        last = Some((x, cov, sys.pairs));
    }
    let (x, cov, pairs) = last?;
    let g_b0 = Vector3::new(x[3], x[4], x[5]);
    let r_gb = Rot::rotation_between(&(-g_b0), &Vector3::z())?;
    let g_cov = cov.fixed_view::<3, 3>(3, 3).into_owned();
    let v_cov = cov.fixed_view::<3, 3>(0, 0).into_owned();
    Some(Alignment {
        r_gb,
        v_gb: r_gb * Vector3::new(x[0], x[1], x[2]),
        biases,
        gravity_norm: g_b0.norm(),
        sigma_theta: g_cov.symmetric_eigen().eigenvalues.max().max(0.0).sqrt() / g_b0.norm(),
        sigma_velocity: v_cov.symmetric_eigen().eigenvalues.max().max(0.0).sqrt(),
        pairs,
    })
}

/// One pair's linear rows: `[u]× (A_j − A_i) x = −[u]× (k_j − k_i)`.
struct Rows {
    a: SMatrix<f64, 3, 12>,
    b: Vector3<f64>,
}

/// The stacked pairs at one linearisation.
struct System {
    rows: Vec<Rows>,
    pairs: usize,
}

/// The body state terms at one time: `A(τ)` (3×12) and `k(τ)`.
struct Snapshot {
    a: SMatrix<f64, 3, 12>,
    k: Vector3<f64>,
    /// `R_b0,b(τ)`.
    r: Rot,
}

impl System {
    fn build(input: &AlignInput, biases: &ImuBiases, params: &InitParams) -> Option<Self> {
        let gyro = GyroTrack::new(input.imu, &biases.gyro);
        let derot = Derotation {
            gyro: &gyro,
            r_cb: input.r_cb,
            t_d: input.t_d,
            t_r: input.t_r,
        };
        let snaps = snapshots(input, biases, params)?;
        let bearings: Vec<Vec<(TrackId, Vector3<f64>)>> = input
            .frames
            .iter()
            .map(|f| frame_bearings(f, input.camera, &derot))
            .collect();
        let p_bc = -(input.r_cb.inverse() * input.p_cb);
        let gap = params.translation_gap.max(1);
        let mut rows = Vec::new();
        for i in 0..input.frames.len().saturating_sub(gap) {
            let j = i + gap;
            let (Some(si), Some(sj)) = (&snaps[i], &snaps[j]) else {
                continue;
            };
            let r_ji = input.r_cb * (si.r.inverse() * sj.r).inverse() * input.r_cb.inverse();
            let Some(t) = translation_direction(&bearings[i], &bearings[j], &r_ji, params) else {
                continue;
            };
            let u = si.r * (input.r_cb.inverse() * (-(r_ji.inverse() * t)));
            let ux = skew(&u);
            let lever = sj.r * p_bc - si.r * p_bc;
            rows.push(Rows {
                a: ux * (sj.a - si.a),
                b: -(ux * (sj.k - si.k + lever)),
            });
        }
        let pairs = rows.len();
        (pairs >= 10).then_some(Self { rows, pairs })
    }

    /// Huber-reweighted least squares with weak bias priors; `(x, covariance)`.
    fn solve(&self, params: &InitParams) -> Option<(Vec12, Mat12)> {
        let s = params.align_sigma_m;
        let mut w: Vec<f64> = vec![1.0; self.rows.len()];
        let mut out = None;
        for _ in 0..3 {
            let (mut h, mut g) = (Mat12::zeros(), Vec12::zeros());
            for (r, wk) in self.rows.iter().zip(&w) {
                h += r.a.transpose() * r.a * (wk / (s * s));
                g += r.a.transpose() * r.b * (wk / (s * s));
            }
            for k in 0..3 {
                h[(6 + k, 6 + k)] += 1.0 / params.align_gyro_bias_prior.powi(2);
                h[(9 + k, 9 + k)] += 1.0 / params.align_accel_bias_prior.powi(2);
            }
            let chol = h.cholesky()?;
            let x = chol.solve(&g);
            let res: Vec<f64> = self
                .rows
                .iter()
                .map(|r| (r.a * x - r.b).norm() / s)
                .collect();
            let chi2: f64 = res.iter().zip(&w).map(|(e, wk)| wk * e * e).sum();
            let dof = (2 * self.rows.len()).saturating_sub(12).max(1) as f64;
            let spread = (chi2 / dof).max(1.0);
            out = Some((x, chol.inverse() * spread));
            w = res
                .iter()
                .map(|&e| if e <= 2.0 { 1.0 } else { 2.0 / e })
                .collect();
        }
        out
    }
}

/// Every frame's bearings, moved to the middle-row time.
fn frame_bearings(
    f: &InitFrame,
    camera: &PinholeRadtan,
    derot: &Derotation,
) -> Vec<(TrackId, Vector3<f64>)> {
    let mut v: Vec<_> = f
        .observations
        .iter()
        .map(|o| {
            let b = camera.unproject(&o.uv);
            let fraction = camera.readout_fraction(&o.uv);
            (o.track, derot.apply(f.t_mid_ns, fraction, &b))
        })
        .collect();
    v.sort_by_key(|p| p.0);
    v
}

/// The preintegration from the first sample to every frame's `τ = t_mid + t_d` as `A(τ)`,
/// `k(τ)`, `R(τ)`; `None` entries outside the samples.
fn snapshots(
    input: &AlignInput,
    biases: &ImuBiases,
    params: &InitParams,
) -> Option<Vec<Option<Snapshot>>> {
    let pre_params =
        PreintegrationParams::new(&params.imu_noise, &ImuIntrinsics::default()).ok()?;
    let (t0, t1) = (
        input.imu.first()?.t_ns as f64,
        input.imu.last()?.t_ns as f64,
    );
    let mut pre = Preintegrated::new(*biases, pre_params);
    let mut at = t0;
    let mut out = Vec::with_capacity(input.frames.len());
    for f in input.frames {
        let tau = f.t_mid_ns as f64 + input.t_d * 1e9;
        if tau < at || tau > t1 {
            out.push(None);
            continue;
        }
        for (dt, g, a) in segments(input.imu, at, tau)? {
            pre.integrate(dt, &g, &a);
        }
        at = tau;
        let ts = (tau - t0) * 1e-9;
        let mut a = SMatrix::<f64, 3, 12>::zeros();
        a.fixed_view_mut::<3, 3>(0, 0)
            .copy_from(&(Matrix3::identity() * ts));
        a.fixed_view_mut::<3, 3>(0, 3)
            .copy_from(&(Matrix3::identity() * (0.5 * ts * ts)));
        a.fixed_view_mut::<3, 3>(0, 6).copy_from(&pre.d_p_d_bg());
        a.fixed_view_mut::<3, 3>(0, 9).copy_from(&pre.d_p_d_ba());
        out.push(Some(Snapshot {
            a,
            k: pre.delta_p(),
            r: pre.delta_r(),
        }));
    }
    Some(out)
}

/// The unit translation `t` (`X_j = R_ji X_i + t`) with the rotation known (module docs):
/// the smallest eigenvector of `Σ m mᵀ`, the worst third of the points dropped once, the
/// sign by cheirality. `None` with too few points or no majority in front.
fn translation_direction(
    bi: &[(TrackId, Vector3<f64>)],
    bj: &[(TrackId, Vector3<f64>)],
    r_ji: &Rot,
    params: &InitParams,
) -> Option<Vector3<f64>> {
    let pairs = merge(bi, bj);
    if pairs.len() < params.min_matches {
        return None;
    }
    let m: Vec<Vector3<f64>> = pairs.iter().map(|(a, b)| (r_ji * a).cross(b)).collect();
    let smallest = |keep: &dyn Fn(usize) -> bool| -> Vector3<f64> {
        let mut s = Matrix3::zeros();
        for (_, mk) in m.iter().enumerate().filter(|(k, _)| keep(*k)) {
            s += mk * mk.transpose();
        }
        let e = s.symmetric_eigen();
        e.eigenvectors.column(e.eigenvalues.imin()).into_owned()
    };
    let t = smallest(&|_| true);
    let mut err: Vec<f64> = m.iter().map(|mk| mk.dot(&t).abs()).collect();
    let mut sorted = err.clone();
    sorted.sort_by(f64::total_cmp);
    let bound = sorted[sorted.len() * 2 / 3];
    err.iter_mut()
        .for_each(|e| *e = if *e <= bound { 1.0 } else { 0.0 });
    let t = smallest(&|k| err[k] > 0.5);
    let mut front = 0i64;
    for (a, b) in &pairs {
        // d_j b_j = d_i R b_i + t: least squares in (d_i, d_j).
        let ra = r_ji * a;
        let m2 = nalgebra::Matrix3x2::from_columns(&[ra, -b]);
        if let Some(d) = (m2.transpose() * m2)
            .try_inverse()
            .map(|i| i * m2.transpose() * (-t))
        {
            front += if d[0] > 0.0 && d[1] > 0.0 {
                1
            } else if d[0] < 0.0 && d[1] < 0.0 {
                -1
            } else {
                0
            };
        }
    }
    (front != 0).then(|| if front > 0 { t } else { -t })
}

/// The bearings of the tracks in both sorted lists.
fn merge(
    a: &[(TrackId, Vector3<f64>)],
    b: &[(TrackId, Vector3<f64>)],
) -> Vec<(Vector3<f64>, Vector3<f64>)> {
    let (mut i, mut j, mut out) = (0, 0, Vec::new());
    while i < a.len() && j < b.len() {
        match a[i].0.cmp(&b[j].0) {
            std::cmp::Ordering::Less => i += 1,
            std::cmp::Ordering::Greater => j += 1,
            std::cmp::Ordering::Equal => {
                out.push((a[i].1, b[j].1));
                i += 1;
                j += 1;
            }
        }
    }
    out
}

/// The epipolar time offset: `t_d` minimising, over a grid around `t_d0`
/// (±[`InitParams::fine_half_width_s`]), the summed epipolar residual of the tracks with
/// the *gyro's* rotation between the frames shifted by `s` and the translation direction
/// solved per pair (`λ_min(Σ m mᵀ)` of [`translation_direction`], the worst third of a
/// pair's points dropped). Unlike the visual rotations of step 1, no rotation is fitted to
/// the tracks, so the rotation-translation ambiguity of short baselines (which correlates
/// the visual rotations' errors with the velocity, and through it with time) does not
/// enter. `input.t_d` is the derotation's offset. `None` without usable pairs.
pub fn epipolar_time_offset(input: &AlignInput, t_d0: f64, params: &InitParams) -> Option<f64> {
    let gyro = GyroTrack::new(input.imu, &input.biases.gyro);
    let derot = Derotation {
        gyro: &gyro,
        r_cb: input.r_cb,
        t_d: input.t_d,
        t_r: input.t_r,
    };
    let bearings: Vec<Vec<(TrackId, Vector3<f64>)>> = input
        .frames
        .iter()
        .map(|f| frame_bearings(f, input.camera, &derot))
        .collect();
    let gap = params.pair_gap.max(1);
    let pairs: Vec<(usize, Matched)> = (0..input.frames.len().saturating_sub(gap))
        .map(|i| (i, merge(&bearings[i], &bearings[i + gap])))
        .filter(|(_, m)| m.len() >= params.min_matches)
        .collect();
    let cost = |s: f64| -> f64 {
        pairs
            .iter()
            .map(|(i, m)| {
                let (f0, f1) = (&input.frames[*i], &input.frames[*i + gap]);
                let d = gyro.delta(f0.t_mid_ns as f64 + s * 1e9, f1.t_mid_ns as f64 + s * 1e9);
                d.map_or(f64::INFINITY, |d| {
                    let r_ji = input.r_cb * d.inverse() * input.r_cb.inverse();
                    pair_epipolar_cost(m, &r_ji)
                })
            })
            .sum()
    };
    let step = params.fine_step_s;
    let n = (params.fine_half_width_s / step).round() as i64;
    let shifts: Vec<f64> = (-n..=n).map(|k| t_d0 + k as f64 * step).collect();
    let costs: Vec<f64> = shifts.iter().map(|&s| cost(s)).collect();
    let (k, &c) = costs
        .iter()
        .enumerate()
        .filter(|(_, c)| c.is_finite())
        .min_by(|a, b| a.1.total_cmp(b.1))?;
    if k == 0 || k + 1 == costs.len() {
        return Some(shifts[k]);
    }
    let (a, b) = (costs[k - 1], costs[k + 1]);
    let den = a - 2.0 * c + b;
    let off = if den > 0.0 {
        (0.5 * (a - b) / den).clamp(-1.0, 1.0)
    } else {
        0.0
    };
    Some(shifts[k] + off * step)
}

/// `Σ (m·t)²` over the best two thirds of the points, `t` the smallest eigenvector.
fn pair_epipolar_cost(m: &[(Vector3<f64>, Vector3<f64>)], r_ji: &Rot) -> f64 {
    let ms: Vec<Vector3<f64>> = m.iter().map(|(a, b)| (r_ji * a).cross(b)).collect();
    let mut s = Matrix3::zeros();
    for mk in &ms {
        s += mk * mk.transpose();
    }
    let e = s.symmetric_eigen();
    let t = e.eigenvectors.column(e.eigenvalues.imin()).into_owned();
    let mut r: Vec<f64> = ms.iter().map(|mk| mk.dot(&t).powi(2)).collect();
    r.sort_by(f64::total_cmp);
    r[..r.len() * 2 / 3].iter().sum()
}
