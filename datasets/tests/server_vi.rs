//! The server keyframe handler on a visual-inertial client's keyframes (issue 19; seed ch. 5,
//! `VI_NOTES.md` §4 "Server"), in process on the rendered synthetic `drone`: the client's
//! keyframes carry their velocity, biases and IMU segment; the server map built from them is
//! metric and gravity-aligned, its local BA is the visual-inertial window linked by the
//! segments, and its keyframes are more accurate than the client's own.
//!
//! The client (the visual-inertial tracker with a 10-keyframe window, so that keyframes are
//! evicted and sent while it runs) runs once per test binary.
use std::sync::OnceLock;

use datasets::sim::{Scenario, SimParams, SimWorld};
use nalgebra::{Isometry3, Vector3};
use slam_core::imu::{ImuMeasurement, PreintegrationParams};
use slam_core::metrics::{evaluate, Alignment, EvalParams, EvalResult};
use slam_core::server::{HandlerParams, KeyframeHandler, ServerKeyframe, ServerMaps};
use slam_core::vio::{VioParams, VioTracker};
use slam_core::vo::{ViMappingMode, VoFrame, VoParams, VoTracker};

const CLIENT: u32 = 4;
/// Seconds of `drone` the client flies.
const SECONDS: f64 = 30.0;

struct Run {
    world: SimWorld,
    keyframes: Vec<ServerKeyframe>,
}

fn run() -> &'static Run {
    static RUN: OnceLock<Run> = OnceLock::new();
    RUN.get_or_init(|| {
        let mut p = SimParams::new(Scenario::Drone);
        p.seed = 3;
        p.frames = Some((SECONDS * p.rate_hz) as usize);
        let world = SimWorld::new(p).expect("sim world");
        let keyframes = run_client(&world);
        Run { world, keyframes }
    })
}

/// The visual-inertial client: the keyframes it sends (evicted from its window, then the
/// rest of the window at the end).
fn run_client(world: &SimWorld) -> Vec<ServerKeyframe> {
    let sensor = world.params();
    let preint = PreintegrationParams::new(&sensor.noise, &sensor.imu_intrinsics).expect("preint");
    let cam = world.calib().model;
    let vo = VoTracker::new(
        VoParams {
            window: 10,
            ..VoParams::default()
        },
        cam,
    )
    .expect("vo");
    let mut vio = VioTracker::new(vo, VioParams::new(preint, world.calib().t_bs));
    let imu = world.imu_samples();
    let mut next_imu = 0;
    let mut img = vec![0u8; (cam.width * cam.height) as usize];
    let mut out = Vec::new();
    for k in 0..world.n_frames() {
        let t_ns = world.frame_capture_time_ns(k);
        while next_imu < imu.len() && imu[next_imu].t_ns <= t_ns + 50_000_000 {
            let s = imu[next_imu];
            vio.on_imu(ImuMeasurement {
                t_ns: s.t_ns,
                gyro: Vector3::from(s.gyro),
                accel: Vector3::from(s.accel),
            })
            .expect("valid IMU");
            next_imu += 1;
        }
        let frame = VoFrame {
            t_ns,
            ..world.vo_frame(k, &mut img).expect("render")
        };
        let session = vio.vo().session_id();
        let o = vio.process(&frame).expect("vio step");
        let s = if o.vo.new_session {
            session
        } else {
            vio.vo().session_id()
        };
        out.extend(
            o.vo.evicted
                .iter()
                .map(|kf| ServerKeyframe::from_vo(CLIENT, s, kf)),
        );
    }
    let s = vio.vo().session_id();
    let rest = vio.vo_mut().drain_keyframes();
    out.extend(rest.iter().map(|kf| ServerKeyframe::from_vo(CLIENT, s, kf)));
    out
}

/// The server map's keyframes after handling every keyframe (one idle step after each, the
/// schedule a journal replays), and the handler.
fn serve(keyframes: &[ServerKeyframe], params: HandlerParams) -> (KeyframeHandler, ServerMaps) {
    let mut h = KeyframeHandler::new(CLIENT, params);
    let mut maps = ServerMaps::new();
    for kf in keyframes {
        h.handle(&mut maps, kf.clone()).expect("handle");
        while h.idle_step(&mut maps).is_some() {}
    }
    (h, maps)
}

fn eval(world: &SimWorld, traj: &[(i64, Isometry3<f64>)], alignment: Alignment) -> EvalResult {
    let t: Vec<i64> = traj.iter().map(|p| p.0).collect();
    let est: Vec<Isometry3<f64>> = traj.iter().map(|p| p.1).collect();
    let reference: Vec<Isometry3<f64>> = t
        .iter()
        .map(|t| world.pose_cam_at(t + world.time_offset_ns()))
        .collect();
    let p = EvalParams {
        alignment,
        ..Default::default()
    };
    evaluate(&t, &reference, &t, &est, &p).expect("evaluate")
}

/// `(4-DoF ATE m, tilt RMSE deg, Sim(3) scale)` of a trajectory.
fn figures(world: &SimWorld, traj: &[(i64, Isometry3<f64>)]) -> (f64, f64, f64) {
    let four = eval(world, traj, Alignment::FourDof);
    let sim3 = eval(world, traj, Alignment::Sim3);
    let tilt = four.tilt_deg.map_or(f64::NAN, |t| t.rmse);
    (four.ape.rmse, tilt, sim3.alignment.scale)
}

/// The server map of the visual-inertial client is metric and gravity-aligned, its local BA
/// is the visual-inertial window, and its keyframes beat the client's (4-DoF alignment: the
/// only freedom a metric, gravity-aligned map has) and the visual-only server's.
#[test]
fn a_visual_inertial_client_gets_a_metric_gravity_aligned_server_map() {
    let run = run();
    let world = &run.world;
    let kfs = &run.keyframes;
    let inertial = kfs.iter().filter(|k| k.is_inertial()).count();
    let first_inertial = kfs.iter().position(|k| k.is_inertial());
    println!(
        "client: {} keyframes sent, {inertial} visual-inertial (first at index {first_inertial:?})",
        kfs.len()
    );
    assert!(
        inertial * 10 >= kfs.len() * 8,
        "most keyframes are sent after the inertial initialisation"
    );
    let client_traj: Vec<(i64, Isometry3<f64>)> = kfs
        .iter()
        .filter(|k| k.is_inertial())
        .map(|k| (k.t_ns, k.t_ck))
        .collect();
    let mut params = HandlerParams::default();
    if let Ok(v) = std::env::var("SERVER_VI_N") {
        params.vi.keyframes = v.parse().expect("SERVER_VI_N");
    }
    if std::env::var("SERVER_VI_AFTER").is_ok() {
        params.vi.mode = ViMappingMode::AfterVisualBa;
    }
    if let Ok(v) = std::env::var("SERVER_VI_COV") {
        params.vi.fixed_covisible = v.parse().expect("SERVER_VI_COV");
    }
    let t0 = std::time::Instant::now();
    let (h, maps) = serve(kfs, params);
    let per_kf_ms = t0.elapsed().as_secs_f64() * 1e3 / kfs.len() as f64;
    let visual_params = HandlerParams {
        vi: slam_core::vo::ViMappingParams {
            mode: ViMappingMode::Off,
            ..HandlerParams::default().vi
        },
        ..HandlerParams::default()
    };
    let (hv, maps_v) = serve(kfs, visual_params);
    let map = h.current_map(&maps).expect("a server map");
    let map_v = hv.current_map(&maps_v).expect("a server map");
    let (c_ate, c_tilt, c_s) = figures(world, &client_traj);
    let (s_ate, s_tilt, s_s) = figures(world, &map.trajectory());
    let (v_ate, v_tilt, v_s) = figures(world, &map_v.trajectory());
    let st = h.stats();
    println!(
        "4-DoF ATE / tilt RMSE / Sim(3) scale: client keyframes {c_ate:.4} m / {c_tilt:.3}° / \
         {c_s:.4}; server (visual-inertial BA) {s_ate:.4} m / {s_tilt:.3}° / {s_s:.4} \
         ({} keyframes, {} VI windows, {} skipped, {} maps); server (visual BA) {v_ate:.4} m / \
         {v_tilt:.3}° / {v_s:.4} ({} keyframes); path {:.1} m; visual-inertial server \
         {per_kf_ms:.1} ms per keyframe (handle + idle, wall)",
        map.map.keyframes.len(),
        st.vi_windows,
        st.vi_windows_skipped,
        st.maps,
        map_v.map.keyframes.len(),
        world.path_length_m(),
    );
    assert!(
        map.frame.metric && map.frame.gravity_aligned,
        "{:?}",
        map.frame
    );
    assert!(
        st.vi_windows * 2 >= st.kept,
        "the local BA of most kept keyframes is visual-inertial: {st:?}"
    );
    assert!((s_s - 1.0).abs() < 0.01, "server map scale {s_s}");
    assert!(s_tilt < 0.5, "server map tilt {s_tilt}°");
    // Measured (seed 3, deterministic): 0.0169 m (0.044% of the path) against the client's
    // refined keyframes' 0.0178 m and the visual BA's 0.0351 m. The bounds: the issue's
    // 0.1% of the distance, on par with the client's keyframes (its window refined each of
    // them ten times), and clearly better than a visual local BA on the same keyframes.
    assert!(
        s_ate <= 1e-3 * world.path_length_m(),
        "server keyframes {s_ate:.4} m over {:.1} m",
        world.path_length_m()
    );
    assert!(
        s_ate <= 1.1 * c_ate,
        "server keyframes {s_ate:.4} m vs the client's {c_ate:.4} m"
    );
    assert!(
        s_ate < 0.75 * v_ate,
        "visual-inertial BA {s_ate:.4} m vs visual BA {v_ate:.4} m"
    );
}
