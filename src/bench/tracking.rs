//! `shoal bench tracking`: latency of the tracking core on a dataset, per stage and in total,
//! measured (1) inside the tracker, in this process, one tracking thread, images decoded
//! before timing, and (2) through the whole pipeline, from frame publish (camera ingest) to
//! pose publish (tracker), in a lock-step `shoal run`.
use std::path::PathBuf;

use serde::Serialize;
use slam_core::features::GrayImage;
use slam_core::vo::{VoFrame, VoParams, VoTracker};

use crate::launcher::recorder::{LatencyHist, Percentiles};

/// Arguments of `shoal bench tracking`.
#[derive(clap::Args, Debug)]
pub struct TrackingArgs {
    /// Dataset folder (any supported format).
    #[arg(long)]
    pub dataset: PathBuf,
    /// At most this many frames.
    #[arg(long)]
    pub max_frames: Option<usize>,
    /// ORB features per frame.
    #[arg(long, default_value_t = 1000)]
    pub features: usize,
    /// Skip the pipeline run (inside-the-tracker figures only).
    #[arg(long)]
    pub no_pipeline: bool,
    /// Output folder of the pipeline run.
    #[arg(long, default_value = "out/bench_tracking")]
    pub out: PathBuf,
    /// Print one JSON object.
    #[arg(long)]
    pub json: bool,
    /// Write a latency plot (PNG): histogram of the per-frame tracking time and per-stage
    /// bars.
    #[arg(long)]
    pub plot: Option<PathBuf>,
    /// `mono` (the chapter-3 VO, the default) or `vio` (the visual-inertial client, fed the
    /// dataset's IMU up to each frame's last row; needs an IMU and camera-IMU extrinsics).
    #[arg(long, value_enum, default_value = "mono")]
    pub mode: tracker::ClientMode,
}

#[derive(Serialize)]
struct TrackingReport {
    dataset: String,
    width: u32,
    height: u32,
    frames: usize,
    frames_tracked: usize,
    /// `mono` or `vio`.
    mode: String,
    /// Frames tracked with the IMU's prediction (`vio`).
    frames_vio: usize,
    /// Frames posed by the IMU alone through a visual dropout (`vio`).
    frames_inertial: usize,
    /// Frames posed in a metric, gravity-aligned world (`vio`, after the initialisation).
    frames_metric: usize,
    /// The whole client step per frame (the VO, and in `vio` the IMU prediction, the
    /// initialisation attempts and world moves), ms.
    client_total_ms: Percentiles,
    pyramid_ms: Percentiles,
    detect_ms: Percentiles,
    describe_ms: Percentiles,
    orb_extract_ms: Percentiles,
    match_ms: Percentiles,
    pose_opt_ms: Percentiles,
    local_map_ms: Percentiles,
    keyframe_ms: Percentiles,
    total_ms: Percentiles,
    publish_to_pose_ms: Option<Percentiles>,
}

/// Runs the benchmark.
pub fn run(args: &TrackingArgs) -> anyhow::Result<()> {
    let ds = datasets::open(&args.dataset)?;
    let cam = ds.camera.model;
    let n = args.max_frames.unwrap_or(usize::MAX).min(ds.frames.len());
    let mut client = new_client(&ds, args)?;
    let mut img = vec![0u8; (cam.width * cam.height) as usize];
    let mut acc = InProcess::default();
    let mut imu_next = 0;
    let mut frames = datasets::FrameReader::default();
    for rec in ds.frames.iter().take(n) {
        frames.read_gray_into(rec, &mut img, cam.width, cam.height)?;
        let image = GrayImage::from_packed(&img, cam.width as usize, cam.height as usize)?;
        // The IMU up to the frame's last row, as the tracker service waits for it.
        let last_row_ns = rec.t_ns + rec.readout_ns / 2;
        while let Some(m) = ds.imu.get(imu_next).filter(|m| m.t_ns <= last_row_ns) {
            let _ = client.on_imu(slam_core::imu::ImuMeasurement {
                t_ns: m.t_ns,
                gyro: m.gyro.into(),
                accel: m.accel.into(),
            });
            imu_next += 1;
        }
        let t0 = std::time::Instant::now();
        let out = client.process(&VoFrame {
            image,
            t_ns: rec.t_ns,
            readout_ns: rec.readout_ns,
            angular_velocity: None,
        })?;
        acc.record(&out, t0.elapsed());
    }
    let publish_to_pose_ms = if args.no_pipeline {
        None
    } else {
        Some(pipeline_latency(args)?)
    };
    let rep = acc.report(&ds, n, args.mode, publish_to_pose_ms);
    if let Some(path) = &args.plot {
        write_plot(&rep, acc.per_frame_ms, path)?;
    }
    if args.json {
        println!("{}", serde_json::to_string(&rep)?);
    } else {
        print_text(&rep);
    }
    Ok(())
}

/// What the in-process loop gathers per frame.
#[derive(Default)]
struct InProcess {
    /// Stage histograms: pyramid, detect, describe, ORB, match, pose_opt, local_map,
    /// keyframe, total.
    stages: [LatencyHist; 9],
    client_total: LatencyHist,
    tracked: usize,
    /// Frames by [`shm_schema::PoseSource`].
    sources: [usize; 5],
    metric: usize,
    per_frame_ms: Vec<f64>,
}

impl InProcess {
    /// One frame's output and the time of the whole client step.
    fn record(&mut self, out: &tracker::core::ClientOutput, step: std::time::Duration) {
        self.client_total.record_ns(step.as_nanos() as i64);
        self.tracked += out.t_cw.is_some() as usize;
        self.sources[out.source as usize] += 1;
        self.metric += (out.metric && out.t_cw.is_some()) as usize;
        let t = out.vo.times;
        self.per_frame_ms.push(t.total as f64);
        let orb = t.pyramid + t.detect + t.describe;
        for (hist, ms) in self.stages.iter_mut().zip([
            t.pyramid,
            t.detect,
            t.describe,
            orb,
            t.matching,
            t.pose_opt,
            t.local_map,
            t.keyframe,
            t.total,
        ]) {
            hist.record_ns((ms as f64 * 1e6) as i64);
        }
    }

    /// The report of `frames` frames of `ds` in `mode`.
    fn report(
        &self,
        ds: &datasets::Dataset,
        frames: usize,
        mode: tracker::ClientMode,
        publish_to_pose_ms: Option<Percentiles>,
    ) -> TrackingReport {
        let p = |i: usize| self.stages[i].percentiles();
        TrackingReport {
            dataset: ds.root.display().to_string(),
            width: ds.camera.model.width,
            height: ds.camera.model.height,
            frames,
            frames_tracked: self.tracked,
            mode: mode.name().to_string(),
            frames_vio: self.sources[shm_schema::PoseSource::VisualInertial as usize],
            frames_inertial: self.sources[shm_schema::PoseSource::Inertial as usize],
            frames_metric: self.metric,
            client_total_ms: self.client_total.percentiles(),
            pyramid_ms: p(0),
            detect_ms: p(1),
            describe_ms: p(2),
            orb_extract_ms: p(3),
            match_ms: p(4),
            pose_opt_ms: p(5),
            local_map_ms: p(6),
            keyframe_ms: p(7),
            total_ms: p(8),
            publish_to_pose_ms,
        }
    }
}

/// Frame publish → pose publish through a lock-step `shoal run` of the same frames.
fn pipeline_latency(args: &TrackingArgs) -> anyhow::Result<Percentiles> {
    let mut cfg = crate::launcher::RunConfig::new(vec![args.dataset.clone()], args.out.clone());
    cfg.max_frames = args.max_frames;
    cfg.progress = false;
    cfg.ipc_prefix = format!("shoal_benchtrk_{}_", std::process::id());
    cfg.tracker.mode = args.mode;
    Ok(crate::launcher::run(&cfg)?.latency_ms.publish_to_pose)
}

/// The report as text, a row per stage.
fn print_text(rep: &TrackingReport) {
    println!(
        "{} ({}x{}), {} frames, {} tracked; mode {}: {} with the IMU, {} by the IMU alone, {} metric",
        rep.dataset,
        rep.width,
        rep.height,
        rep.frames,
        rep.frames_tracked,
        rep.mode,
        rep.frames_vio,
        rep.frames_inertial,
        rep.frames_metric
    );
    let row = |name: &str, q: &Percentiles| {
        println!(
            "{name:<16} p50 {:>7.2}  p90 {:>7.2}  p99 {:>7.2}  max {:>7.2} ms",
            q.p50, q.p90, q.p99, q.max
        )
    };
    row("pyramid", &rep.pyramid_ms);
    row("detect", &rep.detect_ms);
    row("describe", &rep.describe_ms);
    row("orb_extract", &rep.orb_extract_ms);
    row("match", &rep.match_ms);
    row("pose_opt", &rep.pose_opt_ms);
    row("local_map", &rep.local_map_ms);
    row("keyframe", &rep.keyframe_ms);
    row("total", &rep.total_ms);
    row("client_total", &rep.client_total_ms);
    if let Some(q) = &rep.publish_to_pose_ms {
        row("publish_to_pose", q);
    }
}

/// The client of `args.mode` for `ds`, its local mapping on its own thread as in the
/// tracker service.
fn new_client(
    ds: &datasets::Dataset,
    args: &TrackingArgs,
) -> anyhow::Result<tracker::core::Client> {
    let mut params = VoParams::default();
    params.orb.n_features = args.features;
    let mut vo = VoTracker::new(params, ds.camera.model)?;
    tracker::mapping_thread::LocalMappingThread::attach(&mut vo)?;
    if args.mode != tracker::ClientMode::Vio {
        return Ok(tracker::core::Client::Mono(Box::new(vo)));
    }
    let setup = crate::launcher::modes::client_setup(tracker::ClientMode::Vio, ds, None);
    anyhow::ensure!(
        setup.imu.extrinsics_given && !ds.imu.is_empty(),
        "--mode vio: {}",
        setup.reason
    );
    let preint = setup.imu.preintegration().map_err(anyhow::Error::msg)?;
    let p = slam_core::vio::VioParams::new(preint, ds.camera.t_bs);
    Ok(tracker::core::Client::Vio(Box::new(
        slam_core::vio::VioTracker::new(vo, p),
    )))
}

/// The latency plot of `rep` and the per-frame times to `path`.
fn write_plot(
    rep: &TrackingReport,
    per_frame_ms: Vec<f64>,
    path: &std::path::Path,
) -> anyhow::Result<()> {
    let stage = |name: &str, q: &Percentiles| crate::plot::latency::Stage {
        name: name.to_string(),
        mean_ms: q.mean,
        p90_ms: q.p90,
    };
    let name = std::path::Path::new(&rep.dataset)
        .file_name()
        .map_or_else(|| rep.dataset.clone(), |n| n.to_string_lossy().into_owned());
    let plot = crate::plot::latency::LatencyPlot {
        title: format!(
            "shoal bench tracking: {name} ({}x{})",
            rep.width, rep.height
        ),
        subtitle: format!(
            "{} frames, {} tracked; in-process, one thread, decoding not timed",
            rep.frames, rep.frames_tracked
        ),
        per_frame_ms,
        stages: vec![
            stage("pyramid", &rep.pyramid_ms),
            stage("detect", &rep.detect_ms),
            stage("describe", &rep.describe_ms),
            stage("matching", &rep.match_ms),
            stage("pose_opt", &rep.pose_opt_ms),
            stage("local_map", &rep.local_map_ms),
            stage("keyframe", &rep.keyframe_ms),
            stage("total", &rep.total_ms),
        ],
    };
    crate::plot::latency::write_latency(&plot, path)?;
    eprintln!("latency plot: {}", path.display());
    Ok(())
}
