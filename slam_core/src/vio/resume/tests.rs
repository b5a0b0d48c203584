//! A resumed client starts initialised at the newest stored keyframe's state: the coupler
//! runs nothing, the navigator holds the stored pose, velocity and biases, propagates them
//! through the gap when the IMU covers it, and re-anchors on a visual pose with a velocity
//! uncertainty grown by the gap when it does not.
use nalgebra::{Isometry3, Translation3, UnitQuaternion, Vector3};

use super::*;
use crate::camera::PinholeRadtan;
use crate::features::OrbFeatures;
use crate::imu::coupler::CouplerStatus;
use crate::imu::{ImuBiases, ImuMeasurement, PreintegrationParams};
use crate::vio::NavParams;
use crate::vo::{ClientMap, Keyframe, VoParams};

/// Stored keyframe time (camera clock = IMU clock here), ns.
const T_KF: i64 = 5_000_000_000;

fn keyframe(
    id: u64,
    t_ns: i64,
    t_cw: Isometry3<f64>,
    inertial: Option<KeyframeInertial>,
) -> Keyframe {
    Keyframe {
        id,
        t_ns,
        t_cw,
        camera: PinholeRadtan::pinhole(640, 480, 500.0, 500.0, 320.0, 240.0),
        readout_ns: 0,
        features: OrbFeatures::default(),
        points: vec![],
        inertial,
        imu: None,
    }
}

fn params() -> VioParams {
    let preint =
        PreintegrationParams::new(&Default::default(), &Default::default()).expect("preint");
    // A camera looking forward from a body with x forward, z up (a drone's).
    let r_bc = UnitQuaternion::from_euler_angles(
        -std::f64::consts::FRAC_PI_2,
        0.0,
        -std::f64::consts::FRAC_PI_2,
    );
    let t_bc = Isometry3::from_parts(Translation3::new(0.05, 0.0, 0.02), r_bc);
    VioParams::new(preint, t_bc)
}

fn biases() -> ImuBiases {
    ImuBiases {
        gyro: Vector3::new(0.002, -0.001, 0.0015),
        accel: Vector3::new(0.05, -0.03, 0.08),
    }
}

/// The body at `p_wb` (level, x forward) as the camera pose of `params().t_bc`.
fn camera_at(p_wb: Vector3<f64>) -> Isometry3<f64> {
    let t_wb = Isometry3::from_parts(Translation3::from(p_wb), UnitQuaternion::identity());
    (t_wb * params().t_bc).inverse()
}

/// A VO holding a stored session: an old keyframe without inertial state, the newest at
/// body position (1, 2, 3) moving at `v` with [`biases`].
fn stored_vo(v: Vector3<f64>, newest_inertial: bool) -> VoTracker {
    let cam = PinholeRadtan::pinhole(640, 480, 500.0, 500.0, 320.0, 240.0);
    let mut vo = VoTracker::new(VoParams::default(), cam).expect("vo");
    let mut map = ClientMap::new(1, 0);
    map.insert_keyframe(keyframe(
        3,
        T_KF - 500_000_000,
        camera_at(Vector3::zeros()),
        None,
    ));
    let inertial = newest_inertial.then_some(KeyframeInertial {
        v_wb: v,
        biases: biases(),
        refined: 0,
    });
    map.insert_keyframe(keyframe(
        8,
        T_KF,
        camera_at(Vector3::new(1.0, 2.0, 3.0)),
        inertial,
    ));
    vo.resume_session(map).expect("resume_session");
    vo
}

/// Level body, constant velocity: the accelerometer reads gravity's reaction, plus the
/// biases on both sensors.
fn still_imu(t_ns: i64) -> ImuMeasurement {
    ImuMeasurement {
        t_ns,
        gyro: biases().gyro,
        accel: Vector3::new(0.0, 0.0, crate::imu::GRAVITY) + biases().accel,
    }
}

/// Resuming needs a keyframe, and the newest one's inertial state.
#[test]
fn resuming_a_session_not_initialised_inertially_is_refused() {
    let cam = PinholeRadtan::pinhole(640, 480, 500.0, 500.0, 320.0, 240.0);
    let empty = VoTracker::new(VoParams::default(), cam).expect("vo");
    assert!(matches!(
        VioTracker::resume(empty, params(), 2),
        Err(CoreError::Resume(_))
    ));
    let mono = stored_vo(Vector3::zeros(), false);
    match VioTracker::resume(mono, params(), 2) {
        Err(CoreError::Resume(why)) => assert!(why.contains("not initialised inertially"), "{why}"),
        Err(e) => panic!("{e}"),
        Ok(_) => panic!("resumed a monocular session"),
    }
}

/// The resumed client is metric from the start, says where it resumed from, and its
/// coupler neither attempts nor stores anything.
#[test]
fn a_resumed_client_is_initialised_and_runs_no_initialisation() {
    let v_wb = Vector3::new(0.8, -0.3, 0.1);
    let mut vio = VioTracker::resume(stored_vo(v_wb, true), params(), 2).expect("resumed");
    let st = vio.status();
    assert!(st.is_metric(), "{st:?}");
    let VioStatus::Resumed { from, coasting } = st.clone() else {
        panic!("{st:?}");
    };
    assert_eq!(
        (from.keyframe_id, from.keyframe_t_ns, from.anchored_t_ns),
        (8, T_KF, None)
    );
    assert!(
        coasting,
        "the first frame is searched around the IMU's prediction"
    );
    for k in 0..100 {
        vio.on_imu(still_imu(T_KF + k * 5_000_000)).expect("sample");
    }
    assert_eq!(
        vio.coupler().status(),
        &CouplerStatus::Initialised { refinements: 2 }
    );
    assert_eq!(vio.coupler().attempts(), 0);
    assert_eq!(vio.coupler().span_s(), 0.0);
    let nav = vio.nav.as_ref().expect("navigator");
    assert_eq!(nav.t_ns(), T_KF);
    assert_eq!(nav.state().v, v_wb);
    assert_eq!(nav.state().biases, biases());
    let back = nav.camera_pose(nav.state());
    let stored = camera_at(Vector3::new(1.0, 2.0, 3.0));
    assert!((back.translation.vector - stored.translation.vector).norm() < 1e-12);
    assert_eq!(from.refinements, 2);
}

/// A predecessor that had not refined its initialisation leaves the refinements to the
/// successor: its coupler keeps the successor's samples and its keyframes after them, not
/// the stored keyframes before them.
#[test]
fn refinements_not_done_continue_over_the_successors_own_keyframes() {
    let mut vio =
        VioTracker::resume(stored_vo(Vector3::zeros(), true), params(), 0).expect("resumed");
    assert_eq!(
        vio.coupler().status(),
        &CouplerStatus::Initialised { refinements: 0 }
    );
    for k in 0..100 {
        vio.on_imu(still_imu(T_KF + 100_000_000 + k * 5_000_000))
            .expect("sample");
    }
    vio.coupler.set_keyframe(T_KF, Isometry3::identity());
    assert_eq!(vio.coupler().span_s(), 0.0, "a stored keyframe is not kept");
    vio.coupler
        .set_keyframe(T_KF + 200_000_000, Isometry3::identity());
    vio.coupler
        .set_keyframe(T_KF + 400_000_000, Isometry3::identity());
    assert!((vio.coupler().span_s() - 0.2).abs() < 1e-9);
    assert_eq!(
        vio.coupler.step(),
        None,
        "no refinement before 5 s of keyframes"
    );
}

/// With the IMU over the gap, the stored state is propagated: constant velocity with the
/// stored biases taken out of the samples lands where the body is 0.2 s later.
#[test]
fn the_stored_state_is_propagated_through_the_gap() {
    let v_wb = Vector3::new(0.8, -0.3, 0.1);
    let mut vio = VioTracker::resume(stored_vo(v_wb, true), params(), 2).expect("resumed");
    for k in -4..=60 {
        vio.on_imu(still_imu(T_KF + k * 5_000_000)).expect("sample");
    }
    let t = T_KF + 200_000_000;
    let pred = vio
        .predict(t, &Vector3::zeros())
        .expect("prediction over the gap");
    let p_true = Vector3::new(1.0, 2.0, 3.0) + v_wb * 0.2;
    assert!(
        (pred.nav.p - p_true).norm() < 1e-6,
        "{} vs {p_true}",
        pred.nav.p
    );
    assert!((pred.nav.v - v_wb).norm() < 1e-6);
}

/// Without the IMU over the gap, the navigator re-anchors on the first visual pose: the
/// stored velocity kept, its 1σ grown by the unmodelled acceleration over the gap.
#[test]
fn without_the_imu_the_navigator_reanchors_with_a_grown_velocity_sigma() {
    let v_wb = Vector3::new(0.8, -0.3, 0.1);
    let vio = VioTracker::resume(stored_vo(v_wb, true), params(), 2).expect("resumed");
    let mut nav = vio.nav.clone().expect("navigator");
    let p = NavParams::default();
    assert!((nav.velocity_sigma() - p.initial_velocity_sigma).abs() < 1e-12);
    let seen = camera_at(Vector3::new(1.2, 1.9, 3.0));
    nav.reset_to(&seen, T_KF + 400_000_000);
    let expected = (p.initial_velocity_sigma.powi(2) + (p.unmodelled_accel * 0.4).powi(2)).sqrt();
    assert!(
        (nav.velocity_sigma() - expected).abs() < 1e-9,
        "{}",
        nav.velocity_sigma()
    );
    assert_eq!(nav.state().v, v_wb);
    assert_eq!(nav.t_ns(), T_KF + 400_000_000);
    let back = nav.camera_pose(nav.state());
    assert!((back.translation.vector - seen.translation.vector).norm() < 1e-12);
}
