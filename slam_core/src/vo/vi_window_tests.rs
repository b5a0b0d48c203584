//! Tests of the map side of the visual-inertial window: a client map whose keyframe states
//! are chained by their own IMU segments (exact IMU, exact pixels, optionally a rolling
//! shutter), perturbed, then one window built, solved and written back.

use nalgebra::{Isometry3, Rotation3, Translation3, UnitQuaternion, Vector2, Vector3};

use super::*;
use crate::camera::PinholeRadtan;
use crate::features::{KeyPoint, OrbFeatures};
use crate::imu::window::tests::{rand3, t_bc, true_biases as biases};
use crate::imu::window::ViSolver;
use crate::imu::{ImuMeasurement, ImuNoise, PreintegrationParams};
use crate::lie::{so3_log, Sim3};
use crate::rolling_shutter::row_offset_s;
use crate::twoview::synth::Rng;
use crate::vo::keyframe_imu::{bracket, ImuCalibration, KeyframeImu};
use crate::vo::map::Keyframe;

const KF_STEP_NS: i64 = 250_000_000;
const IMU_STEP_NS: i64 = 5_000_000;

/// IMU samples every 5 ms from -0.1 s to the last keyframe + 0.1 s (raw: biases added).
fn samples(n_kf: usize) -> Vec<ImuMeasurement> {
    let b = biases();
    let end = (n_kf as i64 - 1) * KF_STEP_NS + 100_000_000;
    (-20..=end / IMU_STEP_NS)
        .map(|k| {
            let t = (k * IMU_STEP_NS) as f64 * 1e-9;
            let w = Vector3::new(0.3 * (2.0 * t).sin(), 0.2 * (3.0 * t).cos(), 0.3);
            let a = Vector3::new(1.5 * (1.5 * t).sin(), 0.8 * (2.5 * t).cos(), 9.81);
            ImuMeasurement {
                t_ns: k * IMU_STEP_NS,
                gyro: w + b.gyro,
                accel: a + b.accel,
            }
        })
        .collect()
}

/// A map of `n_kf` keyframes 0.25 s apart whose states follow their own IMU segments, each
/// with an inertial state refined `refined` times, and the points they see (exact pixels
/// in a rolling shutter of `readout_ns`). Returns the map and the true states.
fn scene(n_kf: usize, readout_ns: i64, refined: u32) -> (ClientMap, Vec<NavState>) {
    let preint =
        PreintegrationParams::new(&ImuNoise::default(), &Default::default()).expect("params");
    let calib = ImuCalibration {
        preint,
        t_bc: t_bc(),
        t_d_ns: 0,
    };
    let imu = samples(n_kf);
    let mut truth = vec![NavState {
        r: Rotation3::from_scaled_axis(Vector3::new(0.02, -0.03, 0.4)),
        p: Vector3::new(0.0, 0.0, 1.0),
        v: Vector3::new(1.0, 0.2, 0.1),
        biases: biases(),
    }];
    for k in 1..n_kf {
        let t0 = (k as i64 - 1) * KF_STEP_NS;
        let pre = Preintegrated::from_window(&imu, t0, t0 + KF_STEP_NS, biases(), preint)
            .expect("covered");
        truth.push(pre.predict(&truth[k - 1], &gravity_w()));
    }
    let camera = PinholeRadtan::euroc_cam0();
    let mut map = ClientMap::new(1, 0);
    let mut rng = Rng::new(5);
    let mut points = Vec::new();
    for s in &truth {
        let t_wc = s.camera_pose(&t_bc()).inverse();
        for _ in 0..30 {
            let uv = Vector2::new(rng.uniform(40.0, 710.0), rng.uniform(40.0, 440.0));
            let p_c = camera.unproject(&uv) * rng.uniform(3.0, 8.0);
            points.push(t_wc.transform_point(&p_c.into()).coords);
        }
    }
    // Point `i` has id `i` (the map numbers its points from 0); observations come below.
    for p in &points {
        map.add_point(*p, 0, &[]);
    }
    for (k, s) in truth.iter().enumerate() {
        let t_ns = k as i64 * KF_STEP_NS;
        let mut features = OrbFeatures::default();
        let mut seen = Vec::new();
        for (i, p) in points.iter().enumerate() {
            if let Some(uv) = rs_pixel(&camera, s, p, readout_ns) {
                features
                    .keypoints
                    .push(KeyPoint::at_level0(uv.x as f32, uv.y as f32));
                features.descriptors.push([0; 32]);
                seen.push(i);
            }
        }
        let t_prev = (k > 0).then(|| t_ns - KF_STEP_NS);
        map.insert_keyframe(Keyframe {
            id: k as KfId,
            t_ns,
            t_cw: s.camera_pose(&t_bc()),
            camera,
            readout_ns,
            points: vec![None; features.keypoints.len()],
            features,
            inertial: Some(KeyframeInertial {
                v_wb: s.v,
                biases: s.biases,
                refined,
            }),
            imu: Some(KeyframeImu {
                t_prev_ns: t_prev,
                t_ns,
                samples: bracket(&imu, t_prev.unwrap_or(t_ns), t_ns).to_vec(),
                calib,
            }),
        });
        for (slot, i) in seen.into_iter().enumerate() {
            map.add_observation(i as PointId, k as KfId, slot as u32);
        }
    }
    // Points seen once give no depth: erase them.
    let single: Vec<PointId> = map
        .points
        .values()
        .filter(|p| p.observations.len() < 2)
        .map(|p| p.id)
        .collect();
    for p in single {
        map.erase_point(p);
    }
    for k in 0..n_kf as KfId {
        map.update_covisibility(k);
    }
    (map, truth)
}

/// The pixel of `p_w` in a rolling shutter: the row's camera moved by the velocity over
/// the row's time (fixed point), `None` outside the image.
fn rs_pixel(
    camera: &PinholeRadtan,
    s: &NavState,
    p_w: &Vector3<f64>,
    readout_ns: i64,
) -> Option<Vector2<f64>> {
    let mut dt = 0.0;
    let mut uv = Vector2::zeros();
    for _ in 0..5 {
        uv = reprojection_jacobians(camera, &t_bc(), s, p_w, dt)?.0;
        dt = row_offset_s(readout_ns, uv.y, camera.height);
    }
    camera.contains(&uv).then_some(uv)
}

/// Largest errors of the map's keyframes against the truth: position m, rotation rad,
/// velocity m/s, gyro bias, accel bias.
fn errors(map: &ClientMap, truth: &[NavState]) -> [f64; 5] {
    let mut e = [0.0f64; 5];
    for (k, t) in truth.iter().enumerate() {
        let kf = &map.keyframes[&(k as KfId)];
        let i = kf.inertial.expect("inertial");
        let s = NavState::from_camera(&kf.t_cw, &t_bc(), i.v_wb, i.biases);
        e[0] = e[0].max((s.p - t.p).norm());
        e[1] = e[1].max(so3_log(&(t.r.inverse() * s.r)).norm());
        e[2] = e[2].max((s.v - t.v).norm());
        e[3] = e[3].max((s.biases.gyro - t.biases.gyro).norm());
        e[4] = e[4].max((s.biases.accel - t.biases.accel).norm());
    }
    e
}

/// The window's settings, converged to the exact solution of exact data.
fn exact() -> ViMappingParams {
    ViMappingParams {
        solver: ViParams {
            max_iterations: 50,
            cost_tolerance: 1e-14,
            step_tolerance: 1e-12,
            ..Default::default()
        },
        ..Default::default()
    }
}

/// Builds, solves and writes back the window of the newest keyframe.
fn run_window(map: &mut ClientMap, params: &ViMappingParams) -> usize {
    let newest = *map.keyframes.keys().next_back().expect("keyframes");
    let (mut w, mut job) = (ViWindow::empty(), ViWindowJob::default());
    prepare_vi_window(map, newest, params, &mut w, &mut job).expect("window");
    let rep = ViSolver::new()
        .optimize(&mut w, &params.solver)
        .expect("solved");
    assert!(rep.last.cost < 1e-6 * rep.initial.cost.max(1.0), "{rep:?}");
    apply_vi_window(map, &mut job, &mut w);
    w.keyframes.len()
}

/// Perturbs keyframes `1..` (pose, velocity, biases) and every point.
fn perturb(map: &mut ClientMap, seed: u64) {
    let mut rng = Rng::new(seed);
    for kf in map.keyframes.values_mut().skip(1) {
        let d = Isometry3::from_parts(
            Translation3::from(rand3(&mut rng, 0.05)),
            UnitQuaternion::from_scaled_axis(rand3(&mut rng, 0.02)),
        );
        kf.t_cw = d * kf.t_cw;
        let i = kf.inertial.as_mut().expect("inertial");
        i.v_wb += rand3(&mut rng, 0.1);
        i.biases.gyro += rand3(&mut rng, 0.002);
        i.biases.accel += rand3(&mut rng, 0.05);
    }
    for p in map.points.values_mut() {
        p.p_w += rand3(&mut rng, 0.03);
    }
}

/// A window whose oldest keyframe was refined before: it is fixed, the others return to
/// the truth (global and rolling shutter), their states count the refinement, and no world
/// correction is left.
#[test]
fn a_window_returns_a_perturbed_map_to_the_truth() {
    for readout_ns in [0, 25_000_000] {
        let (mut map, truth) = scene(8, readout_ns, 1);
        let oldest = map.keyframes[&0].t_cw;
        perturb(&mut map, 3);
        assert!(errors(&map, &truth)[0] > 0.01);
        let n = run_window(&mut map, &exact());
        assert_eq!(n, 8);
        let e = errors(&map, &truth);
        assert!(
            e[0] < 1e-5 && e[1] < 1e-6 && e[2] < 1e-5,
            "{readout_ns}: {e:?}"
        );
        assert!(e[3] < 1e-6 && e[4] < 1e-4, "{readout_ns}: {e:?}");
        assert_eq!(map.keyframes[&0].t_cw, oldest);
        assert_eq!(map.keyframes[&7].inertial.map(|i| i.refined), Some(2));
        assert!(map.world_correction.is_none());
    }
}

/// The first window after the initialisation (no refined state) in a world off by 1.5° of
/// tilt and 5 % of scale: it leaves the similarity that undoes it as the world correction,
/// and the map, once moved by it, has the true tilt, scale, velocities and biases (up to the
/// unobservable position and yaw). No window runs while the correction is pending.
#[test]
fn a_first_window_leaves_gravity_and_scale_as_a_world_correction() {
    let (mut map, truth) = scene(8, 0, 0);
    let r_err = UnitQuaternion::from_scaled_axis(Vector3::new(0.026, 0.0, 0.0));
    map.transform_world(&Sim3::new(r_err, Vector3::zeros(), 1.05));
    let n = run_window(&mut map, &exact());
    assert_eq!(n, 8);
    let c = map.world_correction.expect("a correction");
    assert!((c.s * 1.05 - 1.0).abs() < 1e-4, "scale {}", c.s);
    assert!(c.r.angle_to(&r_err.inverse()) < 1e-3, "{c:?}");
    let newest = 7;
    let (mut w, mut job) = (ViWindow::empty(), ViWindowJob::default());
    let p = ViMappingParams::default();
    let skip = prepare_vi_window(&map, newest, &p, &mut w, &mut job);
    assert_eq!(skip, Err(ViSkip::CorrectionPending));
    map.transform_world(&c);
    map.world_correction = None;
    let kf = |k: KfId| {
        let kf = &map.keyframes[&k];
        let i = kf.inertial.expect("inertial");
        NavState::from_camera(&kf.t_cw, &t_bc(), i.v_wb, i.biases)
    };
    let (s0, t0) = (kf(0), &truth[0]);
    for (k, t) in truth.iter().enumerate() {
        let s = kf(k as KfId);
        let tilt = (s.r.inverse() * Vector3::z()).angle(&(t.r.inverse() * Vector3::z()));
        assert!(tilt < 1e-5, "{k}: tilt {tilt}");
        let (ds, dt) = (s.p - s0.p, t.p - t0.p);
        assert!((ds.norm() - dt.norm()).abs() < 1e-4, "{k}: distance");
        assert!((ds.z - dt.z).abs() < 1e-4, "{k}: height");
        assert!(
            (s.r.inverse() * s.v - t.r.inverse() * t.v).norm() < 1e-4,
            "{k}: velocity"
        );
        assert!(
            (s.biases.accel - t.biases.accel).norm() < 1e-3,
            "{k}: accel bias"
        );
    }
    assert!(matches!(
        prepare_vi_window(&map, newest, &p, &mut w, &mut job),
        Ok(())
    ));
}

/// Keyframes before the initialisation (no inertial state) get their velocity and biases
/// from their neighbours; a keyframe without one, or not linked by the IMU, is no window.
#[test]
fn missing_states_and_links_are_handled() {
    let (mut map, truth) = scene(6, 0, 1);
    for k in 1..4 {
        map.keyframes.get_mut(&k).expect("kf").inertial = None;
    }
    map.keyframes
        .get_mut(&0)
        .expect("kf")
        .inertial
        .as_mut()
        .expect("i")
        .refined = 1;
    run_window(&mut map, &exact());
    let e = errors(&map, &truth);
    assert!(e[0] < 1e-5 && e[2] < 1e-5, "{e:?}");
    let p = ViMappingParams::default();
    let (mut w, mut job) = (ViWindow::empty(), ViWindowJob::default());
    map.keyframes.get_mut(&5).expect("kf").inertial = None;
    assert_eq!(
        prepare_vi_window(&map, 5, &p, &mut w, &mut job),
        Err(ViSkip::NotInertial)
    );
    map.keyframes.get_mut(&5).expect("kf").inertial = map.keyframes[&4].inertial;
    map.keyframes
        .get_mut(&4)
        .and_then(|k| k.imu.as_mut())
        .expect("imu")
        .t_prev_ns = Some(1);
    assert_eq!(
        prepare_vi_window(&map, 5, &p, &mut w, &mut job),
        Err(ViSkip::ShortChain)
    );
    // The same scene with exact states: the window on keyframe 5 from keyframe 0 on.
    let (map, _) = scene(6, 0, 1);
    prepare_vi_window(&map, 5, &p, &mut w, &mut job).expect("window");
    assert_eq!((w.keyframes.len(), w.n_visual, w.preints.len()), (6, 0, 5));
    // A longer map: the chain is N + 1 keyframes, older ones join fixed and visual only.
    let (map, _) = scene(14, 0, 1);
    prepare_vi_window(&map, 13, &p, &mut w, &mut job).expect("window");
    let chain = p.keyframes + 1;
    assert!(
        w.n_visual > 0 && w.n_visual <= p.fixed_covisible,
        "{}",
        w.n_visual
    );
    assert_eq!(w.keyframes.len(), w.n_visual + chain);
    assert_eq!(w.preints.len(), chain - 1);
    assert!(w.keyframes[..=w.n_visual].iter().all(|k| k.fixed));
    assert!(w.keyframes[w.n_visual + 1..].iter().all(|k| !k.fixed));
    assert_eq!(job.kf_ids[w.n_visual], 14 - chain as KfId);
}

/// Camera centres of the map's keyframes and of the truth, and the least-squares scale
/// `s` of the map's about keyframe 0's (`|truth - truth_0| ≈ s |map - map_0|`).
fn scale_to_truth(map: &ClientMap, truth: &[NavState]) -> f64 {
    let centre = |s: &NavState| s.camera_pose(&t_bc()).inverse().translation.vector;
    let kf_centre = |k: usize| map.keyframes[&(k as KfId)].center();
    let (m0, t0) = (kf_centre(0), centre(&truth[0]));
    let (mut num, mut den) = (0.0, 0.0);
    for (k, t) in truth.iter().enumerate() {
        let (dm, dt) = (kf_centre(k) - m0, centre(t) - t0);
        num += dm.norm() * dt.norm();
        den += dm.norm_squared();
    }
    num / den
}

/// A session tracked by the window (every state refined) in a world 8 % too large, as an
/// inertial initialisation accepted off in scale leaves it: the window of a new keyframe
/// (N = 10 free keyframes, older covisible ones fixed) keeps the wrong scale and leaves no
/// correction; the session window the client asks for (`session_window_from_ns`) takes all
/// 24 keyframes and leaves the similarity that brings the map to the true scale (and tilt).
#[test]
fn a_session_window_corrects_the_scale_of_a_tracked_session() {
    let (mut map, truth) = scene(24, 0, 1);
    let r_err = UnitQuaternion::from_scaled_axis(Vector3::new(0.0, 0.01, 0.0));
    map.transform_world(&Sim3::new(r_err, Vector3::zeros(), 1.08));
    assert!((scale_to_truth(&map, &truth) * 1.08 - 1.0).abs() < 1e-9);
    let p = exact();
    let (mut w, mut job) = (ViWindow::empty(), ViWindowJob::default());
    let newest = 23;
    let mut window = map.clone();
    prepare_vi_window(&window, newest, &p, &mut w, &mut job).expect("window");
    assert_eq!(w.keyframes.len(), p.keyframes + 1 + p.fixed_covisible);
    ViSolver::new().optimize(&mut w, &p.solver).expect("solved");
    apply_vi_window(&mut window, &mut job, &mut w);
    assert!(window.world_correction.is_none());
    let s = scale_to_truth(&window, &truth);
    assert!(
        (s * 1.08 - 1.0).abs() < 0.01,
        "a window moved the scale: {s}"
    );

    map.session_window_from_ns = Some(map.keyframes[&newest].t_ns);
    prepare_vi_window(&map, newest, &p, &mut w, &mut job).expect("window");
    assert_eq!((w.keyframes.len(), w.n_visual), (24, 0));
    ViSolver::new().optimize(&mut w, &p.solver).expect("solved");
    apply_vi_window(&mut map, &mut job, &mut w);
    assert_eq!(map.session_window_from_ns, None);
    let c = map.world_correction.take().expect("a correction");
    map.transform_world(&c);
    let s = scale_to_truth(&map, &truth);
    assert!(
        (s - 1.0).abs() < 1e-3,
        "scale after the session window: {s}"
    );
    assert!(c.r.angle_to(&r_err.inverse()) < 1e-3, "{c:?}");
    let e = errors(&map, &truth);
    assert!(e[3] < 1e-4 && e[4] < 1e-2, "biases {e:?}");
}

/// The first window after the initialisation (no refined state) is a session window: the
/// whole IMU chain, not N + 1 keyframes.
#[test]
fn the_first_window_takes_the_whole_session() {
    let (map, _) = scene(16, 0, 0);
    let p = ViMappingParams::default();
    let (mut w, mut job) = (ViWindow::empty(), ViWindowJob::default());
    prepare_vi_window(&map, 15, &p, &mut w, &mut job).expect("window");
    assert!(16 > p.keyframes + 1);
    assert_eq!((w.keyframes.len(), w.n_visual), (16, 0));
    assert!(w.prior.is_some() && w.keyframes.iter().all(|k| !k.fixed));
}
