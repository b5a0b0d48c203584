//! The IMU preintegration's hot loop allocates nothing: integrating a window of any length
//! (single steps or interpolated windows over a slice of samples), the bias correction and
//! the residual with its Jacobians make no heap allocation. Own test binary: it installs a
//! counting global allocator.

mod common;

use common::allocations;
use nalgebra::Vector3;
use slam_core::imu::{
    gravity_w, ImuBiases, ImuIntrinsics, ImuMeasurement, ImuNoise, NavState, Preintegrated,
    PreintegrationParams,
};

#[test]
fn preintegration_allocates_nothing() {
    let mut k = ImuIntrinsics::default();
    k.t_s[(0, 1)] = 1e-3;
    let params = PreintegrationParams::new(&ImuNoise::default(), &k).expect("params");
    let samples: Vec<ImuMeasurement> = (0..2000)
        .map(|i| {
            let t = i as f64 * 0.005;
            ImuMeasurement {
                t_ns: i * 5_000_000,
                gyro: Vector3::new(t.sin(), 0.3 * t.cos(), 0.1),
                accel: Vector3::new(0.5 * t.cos(), 0.2, 9.81),
            }
        })
        .collect();
    let b = ImuBiases::default();
    let before = allocations();
    let mut pre = Preintegrated::new(b, params);
    for s in &samples[..400] {
        pre.integrate(0.005, &s.gyro, &s.accel);
    }
    assert!(pre.integrate_window(&samples, 2_001_000_000, 9_003_000_000));
    let s0 = NavState {
        r: nalgebra::Rotation3::identity(),
        p: Vector3::zeros(),
        v: Vector3::zeros(),
        biases: b,
    };
    let s1 = pre.predict(&s0, &gravity_w());
    let res = pre.residual(&s0, &s1, &gravity_w());
    let cov = pre.residual_covariance();
    let (r, v, p) = pre.corrected(&b);
    assert_eq!(allocations(), before, "the preintegration allocated");
    assert!(res.r.norm() < 1e-9 && cov[(0, 0)] > 0.0);
    assert!(r.matrix()[(0, 0)].is_finite() && v.norm().is_finite() && p.norm().is_finite());
}
