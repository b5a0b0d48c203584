//! `shoal bench read`: how fast a dataset's frames are read and decoded to gray, the camera
//! ingest's work per frame (issue 21: an MCAP recording against the folder it came from),
//! with the time to open (index) the dataset and the process's peak resident memory.
use std::path::PathBuf;
use std::time::Instant;

use serde::Serialize;

/// Arguments of `bench read`.
#[derive(clap::Args, Debug)]
pub struct ReadArgs {
    /// Dataset (any format `shoal run` reads).
    #[arg(long)]
    pub dataset: PathBuf,
    /// Image topic of an MCAP / ROS 2 bag dataset.
    #[arg(long)]
    pub image_topic: Option<String>,
    /// Read the frames this many times (after opening once).
    #[arg(long, default_value_t = 1)]
    pub passes: usize,
    /// Print JSON.
    #[arg(long)]
    pub json: bool,
}

/// What `bench read` measures.
#[derive(Debug, Serialize)]
struct ReadReport {
    dataset: String,
    frames: usize,
    width: u32,
    height: u32,
    open_s: f64,
    read_s: f64,
    frames_per_s: f64,
    megapixels_per_s: f64,
    peak_rss_mib: Option<f64>,
}

/// The process's peak resident set (`VmHWM`), MiB.
fn peak_rss_mib() -> Option<f64> {
    let s = std::fs::read_to_string("/proc/self/status").ok()?;
    let line = s.lines().find(|l| l.starts_with("VmHWM:"))?;
    let kib: f64 = line.split_whitespace().nth(1)?.parse().ok()?;
    Some(kib / 1024.0)
}

/// Runs the benchmark.
pub fn run(args: &ReadArgs) -> anyhow::Result<()> {
    let t0 = Instant::now();
    let options = datasets::OpenOptions {
        topics: datasets::mcap_bag::Topics {
            image: args.image_topic.clone(),
            imu: None,
        },
        ..Default::default()
    };
    let ds = datasets::open_with(&args.dataset, &options)?;
    let open_s = t0.elapsed().as_secs_f64();
    let (w, h) = (ds.camera.model.width, ds.camera.model.height);
    let mut buf = vec![0u8; w as usize * h as usize];
    let mut reader = datasets::FrameReader::default();
    let mut checksum = 0u64;
    let t1 = Instant::now();
    for _ in 0..args.passes.max(1) {
        for f in &ds.frames {
            reader.read_gray_into(f, &mut buf, w, h)?;
            checksum = checksum.wrapping_add(u64::from(buf[buf.len() / 2]));
        }
    }
    let read_s = t1.elapsed().as_secs_f64();
    let n = ds.frames.len() * args.passes.max(1);
    let rep = ReadReport {
        dataset: args.dataset.display().to_string(),
        frames: n,
        width: w,
        height: h,
        open_s,
        read_s,
        frames_per_s: n as f64 / read_s,
        megapixels_per_s: n as f64 * f64::from(w) * f64::from(h) / read_s / 1e6,
        peak_rss_mib: peak_rss_mib(),
    };
    if args.json {
        println!("{}", serde_json::to_string_pretty(&rep)?);
    } else {
        println!(
            "{}: {} frames {}x{}: open {:.3} s, read {:.3} s = {:.1} frames/s ({:.1} Mpx/s), \
             peak RSS {:.1} MiB (checksum {checksum})",
            rep.dataset,
            rep.frames,
            w,
            h,
            rep.open_s,
            rep.read_s,
            rep.frames_per_s,
            rep.megapixels_per_s,
            rep.peak_rss_mib.unwrap_or(f64::NAN)
        );
    }
    Ok(())
}
