//! The client VO (no IPC) on synthetic frames rendered in memory, against ground truth.
//! Issue targets: synthetic `loop` (global shutter) ATE after Sim(3) alignment ≤ 0.5% of the
//! distance travelled, every frame tracked. The frames seen before the two-view
//! initialisation succeeds get their poses when it does (`VoOutput::backfill`).
use datasets::sim::{Scenario, SimParams, SimWorld};
use slam_core::features::GrayImage;
use slam_core::metrics::{evaluate, Alignment, EvalParams};
use slam_core::vo::{VoDiagnostic, VoFrame, VoParams, VoState, VoTracker};
use tracker::mapping_thread::LocalMappingThread;

struct VoRun {
    frames: usize,
    tracked: usize,
    sessions: usize,
    ate_rmse: f64,
    path: f64,
}

/// The VO with local mapping on the tracker service's thread (as in a run).
fn run_vo(scenario: Scenario, frames: usize, params: VoParams) -> VoRun {
    let mut p = SimParams::new(scenario);
    p.frames = Some(frames);
    p.seed = 3;
    let world = SimWorld::new(p).unwrap();
    let cal = world.calib();
    let cam = cal.model;
    let mut vo = VoTracker::new(params, cam).unwrap();
    LocalMappingThread::attach(&mut vo).unwrap();
    let mut img = vec![0u8; (cam.width * cam.height) as usize];
    let (mut est_t, mut est, mut gt_t, mut gt) = (vec![], vec![], vec![], vec![]);
    let mut sessions = 1;
    for k in 0..world.n_frames() {
        world.render_frame_into(k, &mut img).unwrap();
        let t = world.frame_time_ns(k);
        let image = GrayImage::from_packed(&img, cam.width as usize, cam.height as usize).unwrap();
        let out = vo
            .process(&VoFrame {
                image,
                t_ns: t,
                readout_ns: cal.readout_ns,
                angular_velocity: None,
            })
            .unwrap();
        sessions += out.new_session as usize;
        for (t_b, t_cw) in &out.backfill {
            est_t.push(*t_b);
            est.push(t_cw.inverse());
        }
        gt_t.push(t);
        gt.push(world.pose_cam_at(world.frame_capture_time_ns(k)));
        if let (VoState::Tracking, Some(t_cw)) = (out.state, out.t_cw) {
            est_t.push(t);
            est.push(t_cw.inverse());
        }
    }
    let mut order: Vec<usize> = (0..est_t.len()).collect();
    order.sort_by_key(|&i| est_t[i]);
    let (est_t, est): (Vec<i64>, Vec<_>) = order.iter().map(|&i| (est_t[i], est[i])).unzip();
    let params = EvalParams {
        alignment: Alignment::Sim3,
        ..Default::default()
    };
    let r = evaluate(&gt_t, &gt, &est_t, &est, &params).unwrap();
    VoRun {
        frames: world.n_frames(),
        tracked: est.len(),
        sessions,
        ate_rmse: r.ape.rmse,
        path: r.ref_path_length_m,
    }
}

#[test]
fn synthetic_loop_global_shutter_accuracy() {
    let r = run_vo(Scenario::Loop, 400, VoParams::default());
    let pct = 100.0 * r.ate_rmse / r.path;
    eprintln!(
        "loop: {}/{} frames tracked, ATE {:.4} m over {:.2} m = {pct:.3}%",
        r.tracked, r.frames, r.ate_rmse, r.path
    );
    assert_eq!(r.sessions, 1, "no tracking loss");
    assert_eq!(r.tracked, r.frames, "every frame has a pose");
    assert!(pct <= 0.5, "ATE {pct:.3}% of the distance (target 0.5%)");
}

/// Relocalisation: after tracking is lost (blank frames), the camera reappears at a place
/// it saw before, far from where it was lost; the tracker finds it in its client map again,
/// in the same session, with the pose it had there the first time.
#[test]
fn relocalises_at_a_known_place() {
    let mut p = SimParams::new(Scenario::Loop);
    p.frames = Some(240);
    p.seed = 3;
    let world = SimWorld::new(p).unwrap();
    let cal = world.calib();
    let cam = cal.model;
    // Local mapping inline (`VoTracker::new` starts no thread).
    let mut vo = VoTracker::new(VoParams::default(), cam).unwrap();
    let mut img = vec![0u8; (cam.width * cam.height) as usize];
    let dt = world.frame_time_ns(1) - world.frame_time_ns(0);
    let mut t = 0;
    let step = |vo: &mut VoTracker, img: &[u8], t: i64| {
        let image = GrayImage::from_packed(img, cam.width as usize, cam.height as usize).unwrap();
        vo.process(&VoFrame {
            image,
            t_ns: t,
            readout_ns: 0,
            angular_velocity: None,
        })
        .unwrap()
    };
    let revisit = 60;
    let mut first_pose = None;
    for k in 0..world.n_frames() {
        world.render_frame_into(k, &mut img).unwrap();
        t = world.frame_time_ns(k);
        let out = step(&mut vo, &img, t);
        if k == revisit {
            first_pose = out.t_cw;
        }
    }
    let first_pose = first_pose.expect("frame 60 tracked");
    assert_eq!(vo.state(), VoState::Tracking);
    let session = vo.session_id();
    // Lost: three blank frames.
    let blank = vec![128u8; img.len()];
    for _ in 0..3 {
        t += dt;
        let out = step(&mut vo, &blank, t);
        assert_eq!(out.state, VoState::Lost);
    }
    // The camera is back where it was at frame 60 (images of frames 60, 61, ...).
    let mut found = None;
    for j in 0..5 {
        world.render_frame_into(revisit + j, &mut img).unwrap();
        t += dt;
        let out = step(&mut vo, &img, t);
        if out.state == VoState::Tracking {
            found = Some((j, out.t_cw.unwrap()));
            break;
        }
    }
    let (j, pose) = found.expect("relocalised within 5 frames");
    assert!(vo.relocalizations() >= 1, "by relocalisation");
    assert_eq!(vo.session_id(), session, "no new session");
    let c_first = first_pose.inverse().translation.vector;
    let c_now = pose.inverse().translation.vector;
    // Ground-truth motion between frame 60 and frame 60 + j, in map units via the ratio of
    // the map's scale (median depth 1) — compare with the first visit's own neighbour.
    let gt_move = (world
        .pose_cam_at(world.frame_capture_time_ns(revisit + j))
        .translation
        .vector
        - world
            .pose_cam_at(world.frame_capture_time_ns(revisit))
            .translation
            .vector)
        .norm();
    let err = (c_now - c_first).norm();
    eprintln!("relocalised after {j} frames; centre {err:.4} map units from the first visit (gt moved {gt_move:.3} m)");
    let rot = (pose.rotation.inverse() * first_pose.rotation)
        .angle()
        .to_degrees();
    assert!(j > 0 || err < 0.02, "same image, same place: {err}");
    assert!(err < 0.1 + 2.0 * gt_move, "place error {err}");
    assert!(rot < 2.0 + 20.0 * gt_move, "rotation error {rot} deg");
}

/// Poses (`t_ns`, `T_cw`) and keyframe ids the VO gives for the first `frames` frames of
/// `scenario` (seed 3), in frame order.
fn vo_poses(
    scenario: Scenario,
    frames: usize,
    params: VoParams,
    thread: bool,
) -> Vec<(i64, Option<nalgebra::Isometry3<f64>>, Option<u64>)> {
    let mut p = SimParams::new(scenario);
    p.frames = Some(frames);
    p.seed = 3;
    let world = SimWorld::new(p).unwrap();
    let cal = world.calib();
    let cam = cal.model;
    let mut vo = VoTracker::new(params, cam).unwrap();
    if thread {
        LocalMappingThread::attach(&mut vo).unwrap();
    }
    let mut img = vec![0u8; (cam.width * cam.height) as usize];
    let mut out = Vec::new();
    for k in 0..world.n_frames() {
        world.render_frame_into(k, &mut img).unwrap();
        let t = world.frame_time_ns(k);
        let image = GrayImage::from_packed(&img, cam.width as usize, cam.height as usize).unwrap();
        let o = vo
            .process(&VoFrame {
                image,
                t_ns: t,
                readout_ns: cal.readout_ns,
                angular_velocity: None,
            })
            .unwrap();
        out.push((t, o.t_cw, o.keyframe));
    }
    assert_eq!(vo.local_mapping_sync_timeouts(), 0);
    out
}

/// With `sync_local_mapping` (lock-step replay) the local-mapping thread is waited for
/// before a frame uses the map and the frame after a keyframe sees its new points: the
/// tracker takes exactly the decisions and poses of inline local mapping, so they no longer
/// depend on the thread's timing. (Without the synchronisation the keyframe rule asks
/// whether local mapping is idle, and the poses differ from inline mapping's.)
#[test]
fn mapping_thread_with_sync_matches_inline_mapping() {
    let frames = 200;
    let inline = vo_poses(Scenario::Loop, frames, VoParams::default(), false);
    let threaded = vo_poses(
        Scenario::Loop,
        frames,
        VoParams {
            sync_local_mapping: true,
            ..VoParams::default()
        },
        true,
    );
    let keyframes = inline.iter().filter(|f| f.2.is_some()).count();
    assert!(
        keyframes >= 10,
        "{keyframes} keyframes: local mapping barely ran"
    );
    assert_eq!(inline.len(), threaded.len());
    for (a, b) in inline.iter().zip(&threaded) {
        assert_eq!(a.2, b.2, "keyframe decision at t = {} ns", a.0);
        assert_eq!(a.1, b.1, "pose at t = {} ns", a.0);
    }
}

/// Flat grey but for nine small squares (side `side` px) spread over the view, centred
/// at the quarter points (most of a lens covered: few features, well spread).
fn cover_but_patches(img: &mut [u8], width: usize, side: usize) {
    let height = img.len() / width;
    let inside = |c: usize, n: usize| {
        (1..4).any(|i| (c as isize - (i * n / 4) as isize).unsigned_abs() < side / 2)
    };
    for (y, row) in img.chunks_mut(width).enumerate() {
        for (x, v) in row.iter_mut().enumerate() {
            if !(inside(x, width) && inside(y, height)) {
                *v = 128;
            }
        }
    }
}

/// Frames before the two-view reference (issue 15, part 2): on the first frames most of
/// the view is covered, too few features for the initialiser's reference but enough to be
/// tracked. Once the map exists (from the first uncovered frames), the covered frames
/// before the reference are tracked backwards against it. Every frame gets a pose, close to
/// the ground truth.
#[test]
fn frames_before_the_reference_are_tracked_backwards() {
    let mut p = SimParams::new(Scenario::Loop);
    p.frames = Some(120);
    p.seed = 3;
    let world = SimWorld::new(p).unwrap();
    let cam = world.calib().model;
    // A reference needs 250 features (the covered frames have fewer).
    let params = VoParams {
        init_min_matches: 250,
        ..VoParams::default()
    };
    let mut vo = VoTracker::new(params, cam).unwrap();
    let mut img = vec![0u8; (cam.width * cam.height) as usize];
    let fed: Vec<usize> = (0..world.n_frames()).collect();
    // Frames 0-11 covered: 108/120 frames posed without backward tracking.
    const COVERED: usize = 12;
    let (mut est_t, mut est) = (vec![], vec![]);
    let mut init_frame = None;
    let mut diagnostics = vec![];
    for (i, &k) in fed.iter().enumerate() {
        world.render_frame_into(k, &mut img).unwrap();
        if k < COVERED {
            cover_but_patches(&mut img, cam.width as usize, 70);
        }
        let t = world.frame_time_ns(k);
        let image = GrayImage::from_packed(&img, cam.width as usize, cam.height as usize).unwrap();
        let out = vo
            .process(&VoFrame {
                image,
                t_ns: t,
                readout_ns: 0,
                angular_velocity: None,
            })
            .unwrap();
        if init_frame.is_none() && out.state == VoState::Tracking {
            init_frame = Some(i);
        }
        diagnostics.extend(out.diagnostics.iter().cloned());
        if !out.backfill.is_empty() {
            eprintln!("frame {k}: {} late poses", out.backfill.len());
        }
        for (t_b, t_cw) in &out.backfill {
            est_t.push(*t_b);
            est.push(t_cw.inverse());
        }
        if let (VoState::Tracking, Some(t_cw)) = (out.state, out.t_cw) {
            est_t.push(t);
            est.push(t_cw.inverse());
        }
    }
    let init_frame = init_frame.expect("initialised");
    let mut order: Vec<usize> = (0..est_t.len()).collect();
    order.sort_by_key(|&i| est_t[i]);
    let (est_t, est): (Vec<i64>, Vec<_>) = order.iter().map(|&i| (est_t[i], est[i])).unzip();
    let gt_t: Vec<i64> = fed.iter().map(|&k| world.frame_time_ns(k)).collect();
    let gt: Vec<_> = fed
        .iter()
        .map(|&k| world.pose_cam_at(world.frame_capture_time_ns(k)))
        .collect();
    let r = evaluate(
        &gt_t,
        &gt,
        &est_t,
        &est,
        &EvalParams {
            alignment: Alignment::Sim3,
            ..Default::default()
        },
    )
    .unwrap();
    eprintln!(
        "{}/{} frames posed, ATE {:.4} m (max {:.4} m) over {:.2} m",
        est_t.len(),
        fed.len(),
        r.ape.rmse,
        r.ape.max,
        r.ref_path_length_m
    );
    // Without backward tracking: 108/120 frames posed (ATE 0.0075 m, worst 0.032 m); with
    // it 120/120 (ATE 0.0145 m, worst 0.052 m: the covered frames have 18-33 inliers).
    assert!(
        init_frame >= COVERED,
        "initialised on the uncovered frames: at {init_frame}"
    );
    assert_eq!(est_t.len(), fed.len(), "every fed frame has a pose");
    // What the walk did comes back with the frames (`debug_init` prints it).
    assert!(
        diagnostics.iter().any(|d| matches!(
            d,
            VoDiagnostic::BackwardStart { before, .. } if *before >= COVERED
        )),
        "{diagnostics:?}"
    );
    assert!(r.ape.rmse < 0.02, "ATE {:.4} m", r.ape.rmse);
    assert!(r.ape.max < 0.07, "worst pose {:.4} m", r.ape.max);
}
