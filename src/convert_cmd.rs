//! `shoal convert --to mcap IN OUT`: any dataset `shoal run` reads (EuRoC, KITTI, phone,
//! GoPro, an image folder, an MCAP file or ROS 2 bag) as an MCAP file of ROS 2 messages
//! ([`datasets::mcap_bag::write`]), with the dataset's calibration (or `--calib`'s) and its
//! IMU model in the `shoal` metadata record, so `shoal run --dataset OUT` replays the same
//! frames, IMU samples and times.
use std::path::PathBuf;

use datasets::mcap_bag::write::{Compression, WriteSettings};

/// Output formats of `convert`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum Target {
    /// MCAP with CDR-encoded ROS 2 messages.
    Mcap,
}

/// Chunk compressions of `convert --to mcap`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum CompressionArg {
    /// zstd (the default, as rosbag2).
    Zstd,
    /// LZ4.
    Lz4,
    /// None.
    None,
}

/// Arguments of `shoal convert`.
#[derive(clap::Args, Debug)]
pub struct ConvertArgs {
    /// Output format.
    #[arg(long = "to", value_enum)]
    pub to: Target,
    /// The dataset to convert (any format `shoal run` reads).
    pub input: PathBuf,
    /// The file to write.
    pub output: PathBuf,
    /// Calibration file put in place of the dataset's own (as `shoal run --calib`).
    #[arg(long, value_name = "FILE")]
    pub calib: Option<PathBuf>,
    /// Image topic of an MCAP / ROS 2 / ROS 1 bag input (default: found by message type).
    #[arg(long)]
    pub image_topic: Option<String>,
    /// IMU topic of an MCAP / ROS 2 / ROS 1 bag input (default: found by message type).
    #[arg(long)]
    pub imu_topic: Option<String>,
    /// Frame rate of an input without timestamps (an image folder: frame k at k / FPS s;
    /// default 20), as `shoal run --fps`.
    #[arg(long)]
    pub fps: Option<f64>,
    /// Only frames A to B-1 of the input (`A..B`, or `A..`), at their own times, as `shoal
    /// run --frames`.
    #[arg(long, value_name = "A..B")]
    pub frames: Option<datasets::FrameRange>,
    /// Chunk compression.
    #[arg(long, value_enum, default_value = "zstd")]
    pub compression: CompressionArg,
    /// Chunk size in bytes (default 1 MiB).
    #[arg(long)]
    pub chunk_bytes: Option<u64>,
}

/// Runs `convert`: prints what was written and any frame that could not be read.
pub fn run(args: &ConvertArgs) -> anyhow::Result<()> {
    let Target::Mcap = args.to;
    let options = datasets::OpenOptions {
        calib: args.calib.clone(),
        topics: datasets::mcap_bag::Topics {
            image: args.image_topic.clone(),
            imu: args.imu_topic.clone(),
        },
        fps: args.fps,
        frames: args.frames,
    };
    let ds = datasets::open_with(&args.input, &options)?;
    for i in &ds.issues {
        eprintln!("{}: {} ({})", i.path.display(), i.detail, i.kind);
    }
    let imu = match (&args.calib, crate::launcher::modes::dataset_imu(&ds)) {
        (Some(file), _) => Some(datasets::calibration::CalibrationFile::read(file)?.imu_calib()),
        (None, Some(y)) => Some(y?.0),
        (None, None) => None,
    };
    let settings = WriteSettings {
        compression: match args.compression {
            CompressionArg::Zstd => Compression::Zstd,
            CompressionArg::Lz4 => Compression::Lz4,
            CompressionArg::None => Compression::None,
        },
        chunk_bytes: args.chunk_bytes,
    };
    let start = std::time::Instant::now();
    let s = datasets::mcap_bag::write::write_dataset(&ds, imu.as_ref(), &args.output, &settings)?;
    for why in &s.skipped_frames {
        eprintln!("skipped a frame: {why}");
    }
    println!(
        "{}: {} frames, {} IMU samples, {} ground-truth poses, {:.1} MB in {:.1} s{}",
        args.output.display(),
        s.frames,
        s.imu_samples,
        s.poses,
        s.bytes as f64 / 1e6,
        start.elapsed().as_secs_f64(),
        if s.skipped_frames.is_empty() {
            String::new()
        } else {
            format!(" ({} frames skipped)", s.skipped_frames.len())
        }
    );
    Ok(())
}
