//! Runs the client VO (no IPC) on a dataset folder (EuRoC / KITTI / phone layout) and prints
//! the tracking rate, the first tracked frame and, with ground truth, the ATE after Sim(3)
//! alignment. A quick loop for tuning the tracker on real images:
//! `cargo run --release --example vo_dataset -- ../shared/data/kitti07 [--no-rs] [-v]`
use std::path::Path;

use slam_core::features::GrayImage;
use slam_core::metrics::{evaluate, Alignment, EvalParams};
use slam_core::vo::{VoFrame, VoParams, VoState, VoTracker};

fn main() -> anyhow::Result<()> {
    let args: Vec<String> = std::env::args().collect();
    let path = args
        .get(1)
        .ok_or_else(|| anyhow::anyhow!("usage: vo_dataset DIR [--no-rs] [-v]"))?;
    let verbose = args.iter().any(|a| a == "-v");
    let ds = datasets::detect::open(Path::new(path))?;
    let cam = ds.camera.model;
    let params = VoParams {
        rolling_shutter: !args.iter().any(|a| a == "--no-rs"),
        ..VoParams::default()
    };
    let mut vo = VoTracker::new(params, cam)?;
    tracker::mapping_thread::LocalMappingThread::attach(&mut vo)?;
    let mut img = vec![0u8; (cam.width * cam.height) as usize];
    let (mut est_t, mut est) = (vec![], vec![]);
    let mut first_tracked = None;
    let mut totals = vec![];
    let mut kfs = 0;
    for (k, f) in ds.frames.iter().enumerate() {
        if let Err(e) =
            datasets::image_io::decode_gray_into(&f.path, &mut img, cam.width, cam.height)
        {
            eprintln!("frame {k}: {e}");
            continue;
        }
        let image = GrayImage::from_packed(&img, cam.width as usize, cam.height as usize)?;
        let out = vo.process(&VoFrame {
            image,
            t_ns: f.t_ns,
            readout_ns: f.readout_ns,
            angular_velocity: None,
        })?;
        totals.push(out.times.total);
        kfs += usize::from(out.keyframe.is_some());
        for (t, t_cw) in &out.backfill {
            est_t.push(*t);
            est.push(t_cw.inverse());
        }
        if let (VoState::Tracking, Some(t_cw)) = (out.state, out.t_cw) {
            first_tracked.get_or_insert(k);
            est_t.push(f.t_ns);
            est.push(t_cw.inverse());
        }
        if verbose {
            eprintln!(
                "frame {k}: {:?} tracked {} kf {:?} kfs {} points {} total {:.1} ms",
                out.state,
                out.tracked,
                out.keyframe,
                vo.with_map(|m| m.keyframes.len()),
                vo.with_map(|m| m.points.len()),
                out.times.total
            );
        }
    }
    totals.sort_by(f32::total_cmp);
    let mut order: Vec<usize> = (0..est_t.len()).collect();
    order.sort_by_key(|&i| est_t[i]);
    let (est_t, est): (Vec<i64>, Vec<_>) = order.iter().map(|&i| (est_t[i], est[i])).unzip();
    let n = ds.frames.len();
    println!(
        "{n} frames, tracked {} ({:.1}%), first tracked frame {first_tracked:?}, keyframes {kfs}; total p50 {:.2} ms p90 {:.2} ms",
        est.len(),
        100.0 * est.len() as f64 / n.max(1) as f64,
        totals.get(totals.len() / 2).copied().unwrap_or(0.0),
        totals.get(totals.len() * 9 / 10).copied().unwrap_or(0.0),
    );
    if let Some(gt) = &ds.ground_truth {
        if est.len() >= 3 {
            let gt_t: Vec<i64> = gt.iter().map(|p| p.t_ns).collect();
            let gt_p: Vec<_> = gt.iter().map(|p| p.pose).collect();
            let r = evaluate(
                &gt_t,
                &gt_p,
                &est_t,
                &est,
                &EvalParams {
                    alignment: Alignment::Sim3,
                    ..Default::default()
                },
            )?;
            println!(
                "ATE rmse {:.4} m over {:.2} m = {:.3}% ({} pairs)",
                r.ape.rmse,
                r.ref_path_length_m,
                100.0 * r.ape.rmse / r.ref_path_length_m,
                r.pairs.len()
            );
        }
    }
    Ok(())
}
