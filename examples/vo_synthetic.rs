//! Runs the client VO (no IPC) on a synthetic scenario rendered in memory and prints the
//! tracking rate, ATE after Sim(3) alignment and timings.
//! `cargo run --release --example vo_synthetic -- loop 400 [--no-rs]`
use datasets::sim::{Scenario, SimParams, SimWorld};
use slam_core::features::GrayImage;
use slam_core::metrics::{evaluate, Alignment, EvalParams};
use slam_core::vo::{VoFrame, VoParams, VoState, VoTracker};

fn main() -> anyhow::Result<()> {
    let args: Vec<String> = std::env::args().collect();
    let scenario: Scenario = args
        .get(1)
        .map_or("loop", |s| s.as_str())
        .parse()
        .map_err(anyhow::Error::msg)?;
    let frames: usize = args.get(2).map_or(Ok(300), |s| s.parse())?;
    let rs = !args.iter().any(|a| a == "--no-rs");
    let mut p = SimParams::new(scenario);
    p.frames = Some(frames);
    p.seed = 3;
    if args.iter().any(|a| a == "--gs") {
        p.readout_ms = Some(0.0);
    }
    let gyro = args.iter().any(|a| a == "--gyro");
    // Gyro only for the first N frames (then the motion model), for diagnosis.
    let gyro_frames: usize = args
        .iter()
        .position(|a| a == "--gyro-frames")
        .and_then(|i| args.get(i + 1))
        .and_then(|s| s.parse().ok())
        .unwrap_or(0);
    let world = SimWorld::new(p)?;
    let cam = world.calib().model;
    let readout = world.calib().readout_ns;
    let params = VoParams {
        rolling_shutter: rs,
        ..VoParams::default()
    };
    let mut vo = VoTracker::new(params, cam)?;
    if !args.iter().any(|a| a == "--inline") {
        // Local mapping on its own thread, as in the tracker service.
        tracker::mapping_thread::LocalMappingThread::attach(&mut vo)?;
    }
    let mut img = vec![0u8; (cam.width * cam.height) as usize];
    let (mut est_t, mut est, mut gt_t, mut gt) = (vec![], vec![], vec![], vec![]);
    let mut totals = vec![];
    let mut kfs = 0;
    let mut sessions = 1;
    for k in 0..world.n_frames() {
        world.render_frame_into(k, &mut img)?;
        let t = world.frame_time_ns(k);
        let image = GrayImage::from_packed(&img, cam.width as usize, cam.height as usize)?;
        let out = vo.process(&VoFrame {
            image,
            t_ns: t,
            readout_ns: readout,
            angular_velocity: (gyro || k < gyro_frames).then(|| {
                // A perfect gyro: ω from the ground truth, R_wc(t+h) = R_wc(t) Exp(ω h).
                let h = 1_000_000;
                let a = world.pose_cam_at(t - h).rotation;
                let b = world.pose_cam_at(t + h).rotation;
                (a.inverse() * b).scaled_axis() / 2e-3
            }),
        })?;
        totals.push(out.times.total);
        gt_t.push(t);
        gt.push(world.pose_cam_at(world.frame_capture_time_ns(k)));
        if out.new_session {
            sessions += 1;
        }
        if out.keyframe.is_some() {
            kfs += 1;
        }
        if let (VoState::Tracking, Some(t_cw)) = (out.state, out.t_cw) {
            est_t.push(t);
            est.push(t_cw.inverse());
        }
        if k % 50 == 0 {
            eprintln!(
                "frame {k}: {:?} tracked {} kfs {} points {} total {:.1} ms",
                out.state,
                out.tracked,
                vo.with_map(|m| m.keyframes.len()),
                vo.with_map(|m| m.points.len()),
                out.times.total
            );
        }
    }
    let r = evaluate(
        &gt_t,
        &gt,
        &est_t,
        &est,
        &EvalParams {
            alignment: Alignment::Sim3,
            ..Default::default()
        },
    )?;
    totals.sort_by(f32::total_cmp);
    println!(
        "{} frames, tracked {} ({:.1}%), keyframes {kfs}, sessions {sessions}; ATE rmse {:.4} m over {:.2} m = {:.3}%; total p50 {:.2} ms p90 {:.2} ms",
        world.n_frames(),
        est.len(),
        100.0 * est.len() as f64 / world.n_frames() as f64,
        r.ape.rmse,
        r.ref_path_length_m,
        100.0 * r.ape.rmse / r.ref_path_length_m,
        totals[totals.len() / 2],
        totals[totals.len() * 9 / 10]
    );
    Ok(())
}
