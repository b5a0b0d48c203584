//! `shoal run --record FILE.mcap` (issue 21): what crosses shared memory, recorded as the
//! run goes, as an MCAP file of ROS 2 messages that `shoal run --dataset FILE.mcap` replays
//! ([`datasets::mcap_bag::write::StreamWriter`], the layout of `shoal convert --to mcap`):
//!
//! - the frames each tracker receives (`/cam0/image_raw`, `mono8`, stamped with their
//!   middle-row time `FrameHeader::t_mid_ns`, t_d applied) and the IMU samples
//!   (`/imu0`), with the camera (`/cam0/camera_info`) and the `shoal` metadata record (the
//!   calibration ROS messages lack: `T_BS`, t_r, t_d, the IMU model), so that a replay
//!   re-runs the estimation on the same input;
//! - the tracker's poses (`/shoal/pose`, `geometry_msgs/msg/PoseStamped`, camera-to-map of
//!   its VO session, frames it tracked), which a replay ignores;
//! - the dataset's ground truth, when it has one (`/cam0/ground_truth`), for the replay's
//!   evaluation.
//!
//! One file per client (`FILE` with one client; `STEM_c{i}.mcap` with several). Per client,
//! a receiving thread takes the messages from shared memory as soon as they come (it copies
//! the pixels and nothing else) and a writing thread, at a lower priority, encodes them and
//! compresses them with LZ4, so a slow disk or compression never holds a frame in the
//! subscriber's buffer nor takes the trackers' CPU. A frame the recorder
//! missed (a gap in the frames' sequence numbers) is counted in the report.
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{mpsc, Arc};
use std::thread::JoinHandle;
use std::time::Duration;

use anyhow::Context;
use datasets::mcap_bag::meta::ShoalMeta;
use datasets::mcap_bag::write::{StreamWriter, WriteSettings, GROUND_TRUTH_TOPIC};
use serde::Serialize;
use shm_schema::topics;
use shm_schema::{PixelFormat, TrackState};

/// Topic of the recorded tracker poses.
pub const POSE_TOPIC: &str = "/shoal/pose";

/// What the recording of one client holds (`report.json` `record`).
#[derive(Debug, Clone, Default, Serialize, PartialEq)]
pub struct RecordReport {
    /// The file.
    pub file: String,
    /// Frames, IMU samples and tracker poses written.
    pub frames: u64,
    /// IMU samples written.
    pub imu_samples: u64,
    /// Tracker poses written.
    pub poses: u64,
    /// Frames published that the recorder did not receive (gaps in their sequence).
    pub frames_missed: u64,
    /// Frames not written: not 8-bit gray (a feature-track dataset), or malformed.
    pub frames_skipped: u64,
    /// Size of the file, bytes.
    pub bytes: u64,
    /// Why the file could not be written (it is then removed).
    pub error: Option<String>,
}

/// One message taken from shared memory.
enum Item {
    Frame {
        t_ns: i64,
        width: u32,
        height: u32,
        pixels: Vec<u8>,
    },
    Imu(datasets::ImuSample),
    Pose {
        t_ns: i64,
        pose: nalgebra::Isometry3<f64>,
    },
    Skipped,
}

/// The recording threads of one client.
struct ClientRecording {
    receiver: JoinHandle<anyhow::Result<u64>>,
    writer: JoinHandle<RecordReport>,
}

/// The run's recording: started before the services, stopped after them.
pub struct Recording {
    stop: Arc<AtomicBool>,
    clients: Vec<ClientRecording>,
}

/// The file of client `c` of `n` for `--record path`.
pub fn file_of(path: &Path, c: usize, n: usize) -> PathBuf {
    if n <= 1 {
        return path.to_path_buf();
    }
    let stem = path
        .file_stem()
        .map_or("record".into(), |s| s.to_string_lossy());
    path.with_file_name(format!("{stem}_c{c}.mcap"))
}

impl Recording {
    /// Subscribes to every client's frames, IMU and poses (before any service publishes)
    /// and starts writing; `metas[c]` is client `c`'s calibration record, `truth[c]` its
    /// dataset's ground truth.
    pub fn start(
        path: &Path,
        prefix: &str,
        metas: Vec<ShoalMeta>,
        truth: Vec<Vec<datasets::StampedPose>>,
    ) -> anyhow::Result<Self> {
        let stop = Arc::new(AtomicBool::new(false));
        let n = metas.len();
        let mut clients = Vec::new();
        for (c, (meta, truth)) in metas.into_iter().zip(truth).enumerate() {
            let file = file_of(path, c, n);
            let (tx, rx) = mpsc::channel();
            let writer = std::thread::Builder::new()
                .name(format!("record-write-{c}"))
                .spawn(move || write(&file, &meta, &truth, &rx))
                .context("starting a recording thread")?;
            let (ready_tx, ready_rx) = mpsc::sync_channel(1);
            let (prefix, stop) = (prefix.to_string(), stop.clone());
            let receiver = std::thread::Builder::new()
                .name(format!("record-recv-{c}"))
                .spawn(move || receive(c as u32, &prefix, &stop, &tx, &ready_tx))
                .context("starting a recording thread")?;
            match ready_rx.recv_timeout(Duration::from_secs(10)) {
                Ok(Ok(())) => {}
                Ok(Err(e)) => anyhow::bail!("--record: client {c}: {e}"),
                Err(_) => anyhow::bail!("--record: client {c}: the recorder did not subscribe"),
            }
            clients.push(ClientRecording { receiver, writer });
        }
        Ok(Self { stop, clients })
    }

    /// Takes what is left in shared memory, ends the files; one report per client.
    pub fn finish(self) -> Vec<RecordReport> {
        self.stop.store(true, Ordering::SeqCst);
        let mut reports = Vec::new();
        for c in self.clients {
            let received = c.receiver.join();
            let mut r = c.writer.join().unwrap_or_else(|_| RecordReport {
                error: Some("the recording thread panicked".into()),
                ..RecordReport::default()
            });
            match received {
                Ok(Ok(missed)) => r.frames_missed = missed,
                Ok(Err(e)) => r.error = r.error.or(Some(e.to_string())),
                Err(_) => r.error = r.error.or(Some("the receiving thread panicked".into())),
            }
            reports.push(r);
        }
        reports
    }
}

/// Takes client `c`'s frames, IMU samples and poses from shared memory until `stop` (then
/// once more); returns the frames missed.
fn receive(
    c: u32,
    prefix: &str,
    stop: &AtomicBool,
    tx: &mpsc::Sender<Item>,
    ready: &mpsc::SyncSender<Result<(), String>>,
) -> anyhow::Result<u64> {
    let open = || -> anyhow::Result<_> {
        let node = topics::create_node(&format!("recorder_c{c}"), prefix)?;
        let frames = topics::frame_subscriber(&topics::frames_service(&node, c)?, c)?;
        let imu = topics::subscriber(&topics::imu_service(&node, c)?)?;
        let poses = topics::subscriber(&topics::poses_service(&node, c)?)?;
        Ok((node, frames, imu, poses))
    };
    let (node, frames, imu, poses) = match open() {
        Ok(p) => {
            let _ = ready.send(Ok(()));
            p
        }
        Err(e) => {
            let _ = ready.send(Err(e.to_string()));
            return Err(e);
        }
    };
    let (mut next_seq, mut missed) = (None::<u64>, 0u64);
    loop {
        let last_round = stop.load(Ordering::SeqCst);
        let mut busy = false;
        while let Some(s) = frames.receive()? {
            busy = true;
            let h = s.user_header();
            if h.meta.is_end_of_stream() {
                continue;
            }
            missed += next_seq.map_or(0, |n| h.meta.seq.saturating_sub(n));
            next_seq = Some(h.meta.seq + 1);
            let gray = h.pixel_format == PixelFormat::Gray8 as u32;
            let len = (h.width as usize) * (h.height as usize);
            let item = match s.payload().get(..len) {
                Some(px) if gray && h.stride == h.width => Item::Frame {
                    t_ns: h.t_mid_ns,
                    width: h.width,
                    height: h.height,
                    pixels: px.to_vec(),
                },
                _ => Item::Skipped,
            };
            let _ = tx.send(item);
        }
        while let Some(s) = imu.receive()? {
            busy = true;
            let m = *s.payload();
            if m.meta.is_end_of_stream() {
                continue;
            }
            let sample = datasets::ImuSample {
                t_ns: m.t_ns,
                gyro: m.gyro,
                accel: m.accel,
            };
            let _ = tx.send(Item::Imu(sample));
        }
        while let Some(s) = poses.receive()? {
            busy = true;
            let p = s.payload();
            let tracking = TrackState::from_u32(p.state) == Some(TrackState::Tracking);
            let pose = shoal_runtime::wire::iso_from_wire(&p.pose).filter(|_| tracking);
            if let Some(pose) = pose {
                let _ = tx.send(Item::Pose { t_ns: p.t_ns, pose });
            }
        }
        if last_round {
            return Ok(missed);
        }
        if !busy && node.wait(Duration::from_millis(1)).is_err() {
            return Ok(missed);
        }
    }
}

/// Writes what `rx` brings to `file` until every sender is gone.
fn write(
    file: &Path,
    meta: &ShoalMeta,
    truth: &[datasets::StampedPose],
    rx: &mpsc::Receiver<Item>,
) -> RecordReport {
    let mut r = RecordReport {
        file: file.display().to_string(),
        ..RecordReport::default()
    };
    // LZ4 and a lower priority: the recording must not take the trackers' CPU
    // (BENCHMARKS.md "Recording": zstd at normal priority cost ~10% of tracking p50).
    lower_priority();
    let settings = WriteSettings {
        compression: datasets::mcap_bag::write::Compression::Lz4,
        chunk_bytes: None,
    };
    let result = (|| -> Result<_, datasets::DatasetError> {
        let mut w = StreamWriter::create(file, meta, &settings)?;
        let poses = w.add_channel(
            datasets::mcap_bag::msgs::names::POSE_STAMPED,
            &datasets::mcap_bag::msgs::pose_stamped_schema(),
            POSE_TOPIC,
        )?;
        let mut first = true;
        for item in rx {
            match item {
                Item::Frame {
                    t_ns,
                    width,
                    height,
                    pixels,
                } => {
                    if std::mem::take(&mut first) {
                        w.camera_info(&meta.camera, t_ns)?;
                        for p in truth {
                            w.pose(None, p.t_ns, &p.pose, "world")?;
                        }
                    }
                    w.image(t_ns, width, height, &pixels)?;
                }
                Item::Imu(s) => w.imu(&s)?,
                Item::Pose { t_ns, pose } => {
                    w.pose(Some(poses), t_ns, &pose, "map")?;
                    r.poses += 1;
                }
                Item::Skipped => r.frames_skipped += 1,
            }
        }
        w.finish()
    })();
    match result {
        Ok(s) => {
            r.frames = s.frames as u64;
            r.imu_samples = s.imu_samples as u64;
            r.bytes = s.bytes;
        }
        Err(e) => {
            r.error = Some(e.to_string());
            let mut tmp = file.as_os_str().to_owned();
            tmp.push(".tmp");
            let _ = std::fs::remove_file(tmp);
        }
    }
    r
}

/// Lowers the calling thread's scheduling priority (nice +10; Linux threads have their
/// own): best effort, a failure leaves it as it was.
fn lower_priority() {
    // SAFETY: plain system calls on the calling thread, no memory handed over.
    unsafe {
        let tid = libc::syscall(libc::SYS_gettid) as libc::id_t;
        libc::setpriority(libc::PRIO_PROCESS, tid, 10);
    }
}

/// Client `c`'s calibration record for the recording: the dataset's camera (with
/// `--calib`'s in its place) and IMU model, middle-row stamps, and the ground-truth topic
/// when the dataset has one.
pub fn meta_of(ds: &datasets::Dataset, calib: Option<&Path>) -> anyhow::Result<ShoalMeta> {
    let imu = match (calib, super::modes::dataset_imu(ds)) {
        (Some(file), _) => Some(datasets::calibration::CalibrationFile::read(file)?.imu_calib()),
        (None, Some(y)) => y.ok().map(|y| y.0),
        (None, None) => None,
    };
    Ok(ShoalMeta {
        camera: ds.camera.clone(),
        imu,
        middle_row: true,
        ground_truth_topic: ds.ground_truth.as_ref().map(|_| GROUND_TRUTH_TOPIC.into()),
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    /// One client records to the file asked for; several to one file each.
    #[test]
    fn one_file_per_client() {
        let p = Path::new("/tmp/run.mcap");
        assert_eq!(file_of(p, 0, 1), p);
        assert_eq!(file_of(p, 1, 2), Path::new("/tmp/run_c1.mcap"));
    }
}
