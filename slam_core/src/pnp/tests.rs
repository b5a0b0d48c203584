//! Tests of [`super::solve_pnp_ransac`].

use nalgebra::{Isometry3, Point3, Translation3, UnitQuaternion, Vector2, Vector3};

use super::*;
use crate::twoview::synth::{box_point, Rng};

fn truth() -> Isometry3<f64> {
    Isometry3::from_parts(
        Translation3::new(-0.4, 0.2, 0.8),
        UnitQuaternion::from_euler_angles(-0.2, 0.5, 0.1),
    )
}

/// `n` correspondences (pixel noise `noise_px` at f = 458, a fraction `outliers` with random
/// observations).
fn scene(
    seed: u64,
    n: usize,
    noise_px: f64,
    outliers: f64,
) -> (Vec<Vector3<f64>>, Vec<Vector2<f64>>, Vec<bool>) {
    let mut rng = Rng::new(seed);
    let t_wc = truth().inverse();
    let (mut pw, mut xn, mut out) = (Vec::new(), Vec::new(), Vec::new());
    for _ in 0..n {
        let pc = box_point(&mut rng);
        pw.push((t_wc * Point3::from(pc)).coords);
        let o = rng.0.next_f64() < outliers;
        let x = if o {
            Vector2::new(rng.uniform(-0.8, 0.8), rng.uniform(-0.5, 0.5))
        } else {
            Vector2::new(pc.x / pc.z, pc.y / pc.z) + rng.normal2(noise_px / 458.0)
        };
        xn.push(x);
        out.push(o);
    }
    (pw, xn, out)
}

fn errors(a: &Isometry3<f64>, b: &Isometry3<f64>) -> (f64, f64) {
    (
        (a.rotation.inverse() * b.rotation).angle().to_degrees(),
        (a.inverse().translation.vector - b.inverse().translation.vector).norm(),
    )
}

#[test]
fn epnp_is_exact_without_noise() {
    let (pw, xn, _) = scene(1, 50, 0.0, 0.0);
    let mut s = epnp::EpnpScratch::default();
    for n in [5, 6, 50] {
        let pose = epnp::epnp(&pw, &xn, 0..n, &mut s).expect("pose");
        let (r, t) = errors(&pose, &truth());
        assert!(r < 1e-6 && t < 1e-6, "n = {n}: {r} deg {t} m");
    }
    // Exactly 4 points: EPnP's β approximations are not exact there; still a nearby pose.
    let pose = epnp::epnp(&pw, &xn, 0..4, &mut s).expect("pose");
    assert!(errors(&pose, &truth()).0 < 2.0);
    // Planar points.
    let t_wc = truth().inverse();
    let pw: Vec<_> = (0..20)
        .map(|i| {
            let f = i as f64;
            let pc = Vector3::new((f * 0.9).sin(), (f * 1.7).cos() * 0.6, 3.0);
            (t_wc * Point3::from(pc)).coords
        })
        .collect();
    let xn: Vec<_> = pw
        .iter()
        .map(|p| {
            let q = truth() * Point3::from(*p);
            Vector2::new(q.x / q.z, q.y / q.z)
        })
        .collect();
    let pose = epnp::epnp(&pw, &xn, 0..20, &mut s).expect("planar pose");
    let (r, t) = errors(&pose, &truth());
    assert!(r < 1e-4 && t < 1e-4, "planar: {r} deg {t} m");
}

#[test]
fn ransac_recovers_pose_with_outliers() {
    for seed in 1..=5 {
        let (pw, xn, out) = scene(seed, 200, 1.0, 0.3);
        let w = vec![1.0; pw.len()];
        let res = solve_pnp_ransac(
            &pw,
            &xn,
            &w,
            &PnpParams {
                pixel_scale: 458.0,
                seed,
                ..PnpParams::default()
            },
        )
        .expect("pose");
        let (r, t) = errors(&res.t_cw, &truth());
        let kept = (0..pw.len()).filter(|&i| out[i] && res.inliers[i]).count();
        eprintln!(
            "seed {seed}: {r:.4} deg, {:.2} mm, {} inliers, {} iterations, outliers kept {kept}",
            t * 1e3,
            res.n_inliers,
            res.iterations
        );
        assert!(r < 0.1 && t < 0.01, "{r} deg {t} m");
        assert!(kept <= 2);
        assert_eq!(res.n_inliers, res.inliers.iter().filter(|&&b| b).count());
    }
}

#[test]
fn refuses_bad_input() {
    let (pw, xn, _) = scene(3, 30, 1.0, 0.0);
    let w = vec![1.0; 30];
    let p = PnpParams::default();
    assert!(matches!(
        solve_pnp_ransac(&pw, &xn[..29], &w, &p),
        Err(CoreError::InvalidArgument(_))
    ));
    assert!(matches!(
        solve_pnp_ransac(&pw[..10], &xn[..10], &w[..10], &p),
        Err(CoreError::NotEnoughData(_))
    ));
    let mut bad = w.clone();
    bad[0] = 0.0;
    assert!(solve_pnp_ransac(&pw, &xn, &bad, &p).is_err());
    assert!(solve_pnp_ransac(
        &pw,
        &xn,
        &w,
        &PnpParams {
            sample_size: 3,
            ..p
        }
    )
    .is_err());
    // Pure noise: no pose.
    let mut rng = Rng::new(5);
    let junk: Vec<_> = (0..30)
        .map(|_| Vector2::new(rng.uniform(-1.0, 1.0), rng.uniform(-1.0, 1.0)))
        .collect();
    assert!(matches!(
        solve_pnp_ransac(&pw, &junk, &w, &p),
        Err(CoreError::Degenerate(_))
    ));
    // All points identical: no panic.
    let same = vec![Vector3::new(1.0, 2.0, 3.0); 30];
    assert!(solve_pnp_ransac(&same, &xn, &w, &p).is_err());
}
