//! Tests of the preintegration: exact synthetic motion, Monte-Carlo NEES, bias and residual
//! Jacobians against finite differences, windows with interpolated ends.

use nalgebra::{Matrix3, Rotation3, Vector3};

use super::*;
use crate::imu::{gravity_w, measure, specific_force_b, ImuBiases, ImuIntrinsics, ImuNoise};
use crate::twoview::synth::Rng;

/// A smooth, aggressive analytic motion: `R(t) = Rz(α) Ry(β) Rx(γ)` and `p(t)` sums of
/// sinusoids, with exact velocity, acceleration and body rate.
struct Motion;

/// `(value, d1, d2)` of `Σ amp sin(w t + ph)`.
fn sines(t: f64, terms: &[(f64, f64, f64)]) -> (f64, f64, f64) {
    terms
        .iter()
        .fold((0.0, 0.0, 0.0), |(v, d1, d2), &(a, w, ph)| {
            let (s, c) = (w * t + ph).sin_cos();
            (v + a * s, d1 + a * w * c, d2 - a * w * w * s)
        })
}

/// True state at one time: orientation, position, velocity, world acceleration, body rate.
struct Truth {
    r: Matrix3<f64>,
    p: Vector3<f64>,
    v: Vector3<f64>,
    a: Vector3<f64>,
    w: Vector3<f64>,
}

impl Motion {
    fn at(t: f64) -> Truth {
        let (al, dal, _) = sines(t, &[(1.2, 0.9, 0.3), (0.4, 2.3, 1.0)]);
        let (be, dbe, _) = sines(t, &[(0.5, 1.3, 0.7), (0.1, 4.0, 0.2)]);
        let (ga, dga, _) = sines(t, &[(0.6, 1.7, -0.4), (0.15, 3.1, 0.0)]);
        let rz = Rotation3::from_axis_angle(&Vector3::z_axis(), al);
        let ry = Rotation3::from_axis_angle(&Vector3::y_axis(), be);
        let rx = Rotation3::from_axis_angle(&Vector3::x_axis(), ga);
        let r = (rz * ry * rx).into_inner();
        // ω_b = γ̇ e_x + Rxᵀ β̇ e_y + Rxᵀ Ryᵀ α̇ e_z.
        let w = Vector3::x() * dga
            + rx.inverse() * (Vector3::y() * dbe)
            + rx.inverse() * ry.inverse() * (Vector3::z() * dal);
        let px = sines(t, &[(2.0, 1.1, 0.0), (0.3, 3.3, 0.5)]);
        let py = sines(t, &[(1.5, 0.8, 1.2), (0.2, 2.9, -0.3)]);
        let pz = sines(t, &[(0.5, 1.9, 0.1), (0.1, 5.0, 0.0)]);
        Truth {
            r,
            p: Vector3::new(px.0, py.0, pz.0),
            v: Vector3::new(px.1, py.1, pz.1),
            a: Vector3::new(px.2, py.2, pz.2),
            w,
        }
    }
}

/// Samples of `Motion` at `hz` over `[0, dur]` s (times in ns), through the seed's model with
/// raw biases `b`, intrinsics `k` and, when `noise` is given, discrete white noise.
fn samples(
    hz: f64,
    dur: f64,
    b: &ImuBiases,
    k: &ImuIntrinsics,
    noise: Option<(&ImuNoise, &mut Rng)>,
) -> Vec<ImuMeasurement> {
    let period_ns = (1e9 / hz).round() as i64;
    let n = (dur * 1e9 / period_ns as f64).round() as usize;
    let dt = period_ns as f64 * 1e-9;
    let mut noise = noise;
    (0..=n)
        .map(|i| {
            let t_ns = i as i64 * period_ns;
            let s = Motion::at(t_ns as f64 * 1e-9);
            let (mut a, mut g) = measure(&specific_force_b(&s.r, &s.a), &s.w, b, k);
            if let Some((nz, rng)) = noise.as_mut() {
                let (sg, sa) = nz.discrete_white_sigma(dt);
                for c in 0..3 {
                    a[c] += sa * rng.normal();
                    g[c] += sg * rng.normal();
                }
            }
            ImuMeasurement {
                t_ns,
                gyro: g,
                accel: a,
            }
        })
        .collect()
}

/// True deltas `(ΔR, Δv, Δp)` between `t0` and `t1` seconds.
fn true_deltas(t0: f64, t1: f64) -> (Matrix3<f64>, Vector3<f64>, Vector3<f64>) {
    let (i, j) = (Motion::at(t0), Motion::at(t1));
    let dt = t1 - t0;
    let g = gravity_w();
    let rit = i.r.transpose();
    (
        rit * j.r,
        rit * (j.v - i.v - g * dt),
        rit * (j.p - i.p - i.v * dt - g * (0.5 * dt * dt)),
    )
}

/// The error `[Log(ΔR_trueᵀ ΔR̂); Δv̂ - Δv; Δp̂ - Δp]` of a preintegration against the truth.
fn error(pre: &Preintegrated, t0: f64, t1: f64) -> Vector9 {
    let (r, v, p) = true_deltas(t0, t1);
    let mut e = Vector9::zeros();
    let dr = so3_log(&Rotation3::from_matrix_unchecked(
        r.transpose() * pre.delta_r().matrix(),
    ));
    e.fixed_rows_mut::<3>(0).copy_from(&dr);
    e.fixed_rows_mut::<3>(3).copy_from(&(pre.delta_v() - v));
    e.fixed_rows_mut::<3>(6).copy_from(&(pre.delta_p() - p));
    e
}

fn ns(t: f64) -> i64 {
    (t * 1e9).round() as i64
}

fn raw_biases() -> ImuBiases {
    ImuBiases {
        gyro: Vector3::new(0.02, -0.01, 0.015),
        accel: Vector3::new(0.1, -0.2, 0.15),
    }
}

fn intrinsics() -> ImuIntrinsics {
    let mut k = ImuIntrinsics::default();
    k.t_a += Matrix3::new(5e-3, 2e-3, -1e-3, 0.0, -4e-3, 3e-3, 0.0, 0.0, 6e-3);
    k.t_g += Matrix3::new(-3e-3, 1e-3, 2e-3, 4e-3, 5e-3, -2e-3, 1e-3, -3e-3, 2e-3);
    k.t_s = Matrix3::new(1e-3, -5e-4, 2e-4, 3e-4, 8e-4, -1e-4, -2e-4, 4e-4, 1e-3);
    k
}

/// Noise-free samples through the seed's model (with and without intrinsics) over 0.1-2 s
/// windows whose ends fall between samples (interpolated): the deltas converge to the exact
/// motion at second order (the midpoint rule on the linearly interpolated signal), ~1e-6 at
/// 1000 Hz on this aggressive motion (rates up to ~3 rad/s with 5 rad/s harmonics, 5 m/s²).
#[test]
fn exact_motion_matches_truth() {
    for (k, name) in [
        (ImuIntrinsics::default(), "ideal"),
        (intrinsics(), "T_a T_g T_s"),
    ] {
        let params = PreintegrationParams::new(&ImuNoise::zero(), &k).unwrap();
        let b_eff = params.correction.effective_biases(&raw_biases());
        let mut worst_at = Vec::new();
        for hz in [200.0, 1000.0] {
            let s = samples(hz, 6.0, &raw_biases(), &k, None);
            let mut worst = [0.0f64; 3];
            for (t0, len) in [
                (0.5013, 0.1),
                (1.0, 0.5),
                (2.2037, 1.0),
                (3.0, 2.0),
                (0.0021, 2.0),
            ] {
                let pre = Preintegrated::from_window(&s, ns(t0), ns(t0 + len), b_eff, params)
                    .expect("bracketed");
                assert!((pre.delta_t() - len).abs() < 1e-9);
                let e = error(&pre, t0, t0 + len);
                for (w, blk) in worst.iter_mut().zip(0..3) {
                    *w = w.max(e.fixed_rows::<3>(3 * blk).norm());
                }
            }
            println!(
                "{name} {hz} Hz: worst |δφ| {:.2e} rad, |δv| {:.2e} m/s, |δp| {:.2e} m",
                worst[0], worst[1], worst[2]
            );
            worst_at.push(worst);
        }
        let (w200, w1000) = (worst_at[0], worst_at[1]);
        assert!(w200.iter().all(|w| *w < 5e-4), "{name} 200 Hz: {w200:?}");
        assert!(w1000.iter().all(|w| *w < 2e-5), "{name} 1000 Hz: {w1000:?}");
        // Second order: 5x the rate, ~25x smaller errors.
        for b in 0..3 {
            assert!(
                w200[b] / w1000[b] > 15.0,
                "{name}: order {w200:?} {w1000:?}"
            );
        }
    }
}

/// Two consecutive windows sharing a border compose to the whole window; unbracketed
/// windows are refused.
#[test]
fn windows_compose_and_must_be_bracketed() {
    let k = ImuIntrinsics::default();
    let params = PreintegrationParams::new(&ImuNoise::default(), &k).unwrap();
    let s = samples(200.0, 3.0, &raw_biases(), &k, None);
    let b = raw_biases();
    // Split at a sample time: both halves use the very same steps as the whole.
    let (t0, tm, t1) = (ns(0.3021), s[223].t_ns, ns(2.0));
    let whole = Preintegrated::from_window(&s, t0, t1, b, params).unwrap();
    let a = Preintegrated::from_window(&s, t0, tm, b, params).unwrap();
    let c = Preintegrated::from_window(&s, tm, t1, b, params).unwrap();
    let r = a.delta_r().matrix() * c.delta_r().matrix();
    let v = a.delta_v() + a.delta_r() * c.delta_v();
    let p = a.delta_p() + a.delta_v() * c.delta_t() + a.delta_r() * c.delta_p();
    assert!((r - whole.delta_r().matrix()).norm() < 1e-12);
    assert!((v - whole.delta_v()).norm() < 1e-12);
    assert!((p - whole.delta_p()).norm() < 1e-12);
    // Chaining the second window onto the first is the whole window, covariance included.
    let mut chained = a.clone();
    assert!(chained.integrate_window(&s, tm, t1));
    assert!((chained.covariance() - whole.covariance()).norm() < 1e-12 * whole.covariance().norm());
    assert!((chained.bias_jacobian() - whole.bias_jacobian()).norm() < 1e-12);
    // Exactly on sample times, and empty.
    assert!(Preintegrated::from_window(&s, s[10].t_ns, s[20].t_ns, b, params).is_some());
    let empty = Preintegrated::from_window(&s, t0, t0, b, params).unwrap();
    assert_eq!(empty.delta_t(), 0.0);
    // Not bracketed.
    assert!(Preintegrated::from_window(&s, -1, t1, b, params).is_none());
    assert!(Preintegrated::from_window(&s, t0, s.last().unwrap().t_ns + 1, b, params).is_none());
    assert!(Preintegrated::from_window(&s, t1, t0, b, params).is_none());
    assert!(Preintegrated::from_window::<ImuMeasurement>(&[], 0, 0, b, params).is_none());
}

/// Upper `p` quantile of χ²(k) (Wilson-Hilferty; relative error < 1e-4 for k ≥ 100).
fn chi2_quantile(k: f64, z: f64) -> f64 {
    let h = 2.0 / (9.0 * k);
    k * (1.0 - h + z * h.sqrt()).powi(3)
}

/// Mean NEES (9 dof) over `runs` noisy runs of one window; returns it with the 95 % band.
fn monte_carlo_nees(
    k: &ImuIntrinsics,
    runs: usize,
    hz: f64,
    t0: f64,
    len: f64,
    seed: u64,
) -> (f64, f64, f64) {
    let noise = ImuNoise::default();
    let params = PreintegrationParams::new(&noise, k).unwrap();
    let b_eff = params.correction.effective_biases(&raw_biases());
    let mut rng = Rng::new(seed);
    let mut sum = 0.0;
    for _ in 0..runs {
        let s = samples(
            hz,
            t0 + len + 0.05,
            &raw_biases(),
            k,
            Some((&noise, &mut rng)),
        );
        let pre = Preintegrated::from_window(&s, ns(t0), ns(t0 + len), b_eff, params).unwrap();
        let e = error(&pre, t0, t0 + len);
        let info = pre
            .covariance()
            .cholesky()
            .expect("covariance positive definite");
        sum += e.dot(&info.solve(&e));
    }
    let n = runs as f64;
    let dof = 9.0 * n;
    (
        sum / n,
        chi2_quantile(dof, -1.959_964) / n,
        chi2_quantile(dof, 1.959_964) / n,
    )
}

/// 1000 runs with the ADIS16448 white noise: the mean NEES of `[δφ; δv; δp]` lies in the
/// 95 % χ²(9·1000)/1000 band, with and without intrinsics, for 1 s windows at 200 Hz and
/// 0.1 s windows at 1000 Hz (100 steps each or more).
///
/// Sampled white noise averaged by the midpoint rule makes consecutive steps share a sample:
/// the sum over a window holds the two end samples with weight ½, so the true covariance is
/// smaller than the modelled one by ~1/(2N) for N steps. At 200 Hz over 0.1 s (N = 20) that
/// is -2.5 % (mean NEES ~8.8, printed, not asserted).
#[test]
fn monte_carlo_nees_in_band() {
    for (k, name) in [
        (ImuIntrinsics::default(), "ideal"),
        (intrinsics(), "T_a T_g T_s"),
    ] {
        for (hz, len, seed, assert) in [
            (200.0, 1.0, 7, true),
            (1000.0, 0.1, 11, true),
            (200.0, 0.1, 13, false),
        ] {
            let (nees, lo, hi) = monte_carlo_nees(&k, 1000, hz, 0.4, len, seed);
            println!(
                "{name}, {len} s window at {hz} Hz: mean NEES {nees:.3} over 1000 runs, 95 % band [{lo:.3}, {hi:.3}]"
            );
            if assert {
                assert!(
                    nees > lo && nees < hi,
                    "{name} {len} s: NEES {nees} not in [{lo}, {hi}]"
                );
            }
        }
    }
}

/// The bias Jacobians are the derivatives of re-integration (central differences).
#[test]
fn bias_jacobians_match_reintegration() {
    let k = intrinsics();
    let params = PreintegrationParams::new(&ImuNoise::default(), &k).unwrap();
    let s = samples(200.0, 2.5, &raw_biases(), &k, None);
    let b0 = params.correction.effective_biases(&raw_biases());
    let run = |b: ImuBiases| Preintegrated::from_window(&s, ns(0.2), ns(2.2), b, params).unwrap();
    let base = run(b0);
    let jac = base.bias_jacobian();
    let h = 1e-5;
    for c in 0..6 {
        let shift = |sgn: f64| {
            let mut b = b0;
            if c < 3 {
                b.gyro[c] += sgn * h;
            } else {
                b.accel[c - 3] += sgn * h;
            }
            run(b)
        };
        let (plus, minus) = (shift(1.0), shift(-1.0));
        let mut num = Vector9::zeros();
        let dphi = so3_log(&Rotation3::from_matrix_unchecked(
            minus.delta_r().matrix().transpose() * plus.delta_r().matrix(),
        ));
        num.fixed_rows_mut::<3>(0).copy_from(&(dphi / (2.0 * h)));
        num.fixed_rows_mut::<3>(3)
            .copy_from(&((plus.delta_v() - minus.delta_v()) / (2.0 * h)));
        num.fixed_rows_mut::<3>(6)
            .copy_from(&((plus.delta_p() - minus.delta_p()) / (2.0 * h)));
        let err = (num - jac.column(c)).norm();
        assert!(
            err < 1e-6 * (1.0 + num.norm()),
            "bias column {c}: {err} ({num} vs {})",
            jac.column(c)
        );
        // ∂φ/∂b_a is zero.
        if c >= 3 {
            assert_eq!(jac.fixed_view::<3, 1>(0, c).norm(), 0.0);
        }
    }
    // First-order correction: its error against re-integration is second order (halving
    // the bias change divides it by ~4) and small against the change itself.
    let first_order_error = |scale: f64| {
        let mut b1 = b0;
        b1.gyro += Vector3::new(1e-3, -2e-3, 1e-3) * scale;
        b1.accel += Vector3::new(2e-2, 1e-2, -3e-2) * scale;
        let exact = run(b1);
        let (r, v, p) = base.corrected(&b1);
        let er = so3_log(&Rotation3::from_matrix_unchecked(
            r.matrix().transpose() * exact.delta_r().matrix(),
        ));
        let change = (exact.delta_v() - base.delta_v()).norm();
        (
            [
                er.norm(),
                (v - exact.delta_v()).norm(),
                (p - exact.delta_p()).norm(),
            ],
            change,
        )
    };
    let (e1, change) = first_order_error(1.0);
    let (e2, _) = first_order_error(0.5);
    println!("first-order bias correction error {e1:?} (Δv change {change:.3e})");
    assert!(e1[1] < 0.02 * change, "{e1:?} vs {change}");
    for b in 0..3 {
        let ratio = e1[b] / e2[b];
        assert!((3.5..4.5).contains(&ratio), "block {b}: ratio {ratio}");
    }
    let (r0, v0, p0) = base.corrected(&b0);
    assert_eq!(
        (r0, v0, p0),
        (base.delta_r(), base.delta_v(), base.delta_p())
    );
}

/// A random rotation vector, translation etc. in a box of half-width `s`.
fn rand3(rng: &mut Rng, s: f64) -> Vector3<f64> {
    Vector3::new(rng.uniform(-s, s), rng.uniform(-s, s), rng.uniform(-s, s))
}

/// The residual's Jacobians w.r.t. both states match central differences of the residual
/// under [`NavState::retract`], at states off the preintegration (non-zero residual) and
/// biases off the linearisation point.
#[test]
fn residual_jacobians_match_finite_differences() {
    let k = intrinsics();
    let params = PreintegrationParams::new(&ImuNoise::default(), &k).unwrap();
    let s = samples(200.0, 2.0, &raw_biases(), &k, None);
    let b0 = params.correction.effective_biases(&raw_biases());
    let pre = Preintegrated::from_window(&s, ns(0.1), ns(1.6), b0, params).unwrap();
    let g = gravity_w();
    let mut rng = Rng::new(5);
    for trial in 0..4 {
        let t = Motion::at(0.1);
        let si = NavState {
            r: Rotation3::from_matrix_unchecked(t.r) * so3_exp(&rand3(&mut rng, 0.05)),
            p: t.p + rand3(&mut rng, 0.1),
            v: t.v + rand3(&mut rng, 0.1),
            biases: ImuBiases {
                gyro: b0.gyro + rand3(&mut rng, 2e-3),
                accel: b0.accel + rand3(&mut rng, 5e-2),
            },
        };
        let mut sj = pre.predict(&si, &g);
        sj = sj.retract(&Vector15::from_fn(|_, _| rng.uniform(-0.05, 0.05)));
        if trial == 0 {
            // At the prediction itself the residual is zero.
            let r0 = pre.residual(&si, &pre.predict(&si, &g), &g).r;
            assert!(r0.norm() < 1e-12, "{r0}");
        }
        let res = pre.residual(&si, &sj, &g);
        let h = 1e-6;
        for c in 0..15 {
            let mut d = Vector15::zeros();
            d[c] = h;
            let num_i = (pre.residual(&si.retract(&d), &sj, &g).r
                - pre.residual(&si.retract(&-d), &sj, &g).r)
                / (2.0 * h);
            let num_j = (pre.residual(&si, &sj.retract(&d), &g).r
                - pre.residual(&si, &sj.retract(&-d), &g).r)
                / (2.0 * h);
            let ei = (num_i - res.jac_i.column(c)).norm();
            let ej = (num_j - res.jac_j.column(c)).norm();
            assert!(
                ei < 1e-7 * (1.0 + num_i.norm()),
                "trial {trial} ∂r/∂x_i col {c}: {ei}\n{num_i}\n{}",
                res.jac_i.column(c)
            );
            assert!(
                ej < 1e-7 * (1.0 + num_j.norm()),
                "trial {trial} ∂r/∂x_j col {c}: {ej}"
            );
        }
    }
    let cov = pre.residual_covariance();
    let (bg, ba) = params.bias_walk;
    assert!(
        (cov[(9, 9)] - bg * bg * 1.5).abs() < 1e-18
            && (cov[(14, 14)] - ba * ba * 1.5).abs() < 1e-15
    );
    assert_eq!(cov.fixed_view::<9, 9>(0, 0), *pre.covariance());
}

/// Predicting state j from the true state i reproduces the true state j (noise-free).
#[test]
fn predict_reaches_the_true_state() {
    let k = ImuIntrinsics::default();
    let params = PreintegrationParams::new(&ImuNoise::zero(), &k).unwrap();
    let s = samples(1000.0, 2.0, &raw_biases(), &k, None);
    let pre = Preintegrated::from_window(&s, ns(0.25), ns(1.75), raw_biases(), params).unwrap();
    let (ti, tj) = (Motion::at(0.25), Motion::at(1.75));
    let si = NavState {
        r: Rotation3::from_matrix_unchecked(ti.r),
        p: ti.p,
        v: ti.v,
        biases: raw_biases(),
    };
    let sj = pre.predict(&si, &gravity_w());
    let errs = [
        (sj.p - tj.p).norm(),
        (sj.v - tj.v).norm(),
        (sj.r.matrix() - tj.r).norm(),
    ];
    assert!(errs.iter().all(|e| *e < 2e-5), "{errs:?}");
}

#[test]
fn corrections_and_params() {
    let k = intrinsics();
    let c = MeasurementCorrection::new(&k).unwrap();
    let raw = raw_biases();
    let eff = c.effective_biases(&raw);
    let back = c.raw_biases(&eff);
    assert!((back.gyro - raw.gyro).norm() < 1e-15 && (back.accel - raw.accel).norm() < 1e-15);
    // The corrected measurement minus effective biases is the true (ω, a_s).
    let (a_s, w) = (Vector3::new(0.3, -1.0, 9.7), Vector3::new(0.5, 1.0, -0.2));
    let (a_m, w_m) = measure(&a_s, &w, &raw, &k);
    let (wc, ac) = c.apply(&w_m, &a_m);
    assert!((wc - eff.gyro - w).norm() < 1e-14 && (ac - eff.accel - a_s).norm() < 1e-14);
    let mut bad = k;
    bad.t_g = Matrix3::zeros();
    assert!(MeasurementCorrection::new(&bad).is_err());
    bad = k;
    bad.t_s[(0, 0)] = f64::NAN;
    assert!(MeasurementCorrection::new(&bad).is_err());
    let n = ImuNoise {
        accel_noise_density: -1.0,
        ..ImuNoise::default()
    };
    assert!(PreintegrationParams::new(&n, &k).is_err());
    // Ideal intrinsics: raw noise, biases unchanged.
    let p = PreintegrationParams::new(&ImuNoise::default(), &ImuIntrinsics::default()).unwrap();
    assert_eq!(p.correction.effective_biases(&raw), raw);
    let sg = ImuNoise::default().gyro_noise_density;
    assert!((p.noise_cov[(0, 0)] - sg * sg).abs() < 1e-20 && p.noise_cov[(0, 3)] == 0.0);
    // A zero or negative step changes nothing.
    let mut pre = Preintegrated::new(raw, p);
    let before = pre.clone();
    pre.integrate(0.0, &w_m, &a_m);
    pre.integrate(-1e-3, &w_m, &a_m);
    pre.integrate(f64::NAN, &w_m, &a_m);
    assert_eq!(pre, before);
}
