//! One keyframe handler per client on its own thread: keyframes come in on a crossbeam
//! channel, outcomes (handle report, feedback, map figures) go back to the main thread,
//! which owns the iceoryx2 ports. When the queue is empty after a keyframe the handler runs
//! its idle step (local BA + culling) until converged; the outcome says whether it did, so
//! the main thread can journal it and a replay can follow the same schedule.
use std::io::Write;
use std::path::{Path, PathBuf};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

use crossbeam_channel::{Receiver, RecvTimeoutError, Sender};
use nalgebra::Isometry3;
use slam_core::server::{
    HandleReport, HandlerParams, HandlerStats, KeyframeHandler, KeyframeStatus, ServerFeedback,
    ServerKeyframe,
};

/// How often a busy handler rewrites its trajectory files.
const WRITE_EVERY: Duration = Duration::from_secs(2);

/// A keyframe for a handler.
#[derive(Debug)]
pub struct Job {
    /// The keyframe.
    pub kf: ServerKeyframe,
    /// Run the idle step after it: `Some` to follow a journaled schedule (replay), `None`
    /// to decide live (when the queue is empty).
    pub idle: Option<bool>,
    /// True when replayed from the journal (not to be acknowledged or forwarded again).
    pub replay: bool,
}

/// Map figures of one client's handler.
#[derive(Debug, Clone, Copy, Default)]
pub struct MapFigures {
    /// Handler counters.
    pub stats: HandlerStats,
    /// Server maps of the client.
    pub maps: usize,
    /// Keyframes in them.
    pub keyframes: usize,
    /// Points in them.
    pub points: usize,
    /// Current scale ratio.
    pub lambda: f64,
}

/// What a handler did with one keyframe.
#[derive(Debug)]
pub struct Outcome {
    /// Client index.
    pub client: u32,
    /// VO session of the keyframe.
    pub session: u32,
    /// Client keyframe id.
    pub kf_id: u64,
    /// The handler's report, or why it refused the keyframe.
    pub result: Result<HandleReport, String>,
    /// The idle step ran after it.
    pub idled: bool,
    /// Replayed from the journal.
    pub replay: bool,
    /// Pose feedback after it (and after the idle step).
    pub feedback: Option<ServerFeedback>,
    /// Map figures after it.
    pub figures: MapFigures,
    /// Time in `handle`, ms.
    pub handle_ms: f64,
    /// Time in the idle step, ms.
    pub idle_ms: f64,
}

/// A running handler thread.
#[derive(Debug)]
pub struct Worker {
    tx: Option<Sender<Job>>,
    thread: Option<JoinHandle<()>>,
}

impl Worker {
    /// Starts the handler thread of `client`; its trajectory files go to `out` (if any).
    pub fn spawn(
        client: u32,
        params: HandlerParams,
        out: Option<PathBuf>,
        results: Sender<Outcome>,
    ) -> std::io::Result<Self> {
        let (tx, rx) = crossbeam_channel::unbounded();
        let thread = std::thread::Builder::new()
            .name(format!("handler_c{client}"))
            .spawn(move || serve(client, params, out, rx, results))?;
        Ok(Self {
            tx: Some(tx),
            thread: Some(thread),
        })
    }

    /// Queues a keyframe; false when the thread is gone.
    pub fn send(&self, job: Job) -> bool {
        self.tx.as_ref().is_some_and(|tx| tx.send(job).is_ok())
    }

    /// Keyframes waiting.
    pub fn queued(&self) -> usize {
        self.tx.as_ref().map_or(0, |tx| tx.len())
    }

    /// Closes the queue: the thread handles what is queued, writes its files and ends.
    pub fn close(&mut self) {
        self.tx = None;
    }

    /// True once the thread has ended.
    pub fn is_finished(&self) -> bool {
        self.thread.as_ref().is_none_or(|t| t.is_finished())
    }

    /// Joins an ended thread; false if it panicked.
    pub fn join(&mut self) -> bool {
        self.thread.take().is_none_or(|t| t.join().is_ok())
    }
}

/// Most keyframes handled in a row without an idle step.
const MAX_WITHOUT_IDLE: usize = 4;

fn figures(h: &KeyframeHandler) -> MapFigures {
    MapFigures {
        stats: h.stats(),
        maps: h.maps().len(),
        keyframes: h.maps().values().map(|m| m.map.keyframes.len()).sum(),
        points: h.maps().values().map(|m| m.map.points.len()).sum(),
        lambda: h.lambda(),
    }
}

fn serve(
    client: u32,
    params: HandlerParams,
    out: Option<PathBuf>,
    rx: Receiver<Job>,
    results: Sender<Outcome>,
) {
    let mut h = KeyframeHandler::new(client, params);
    // Client poses of the keyframes of the current session, as received.
    let mut client_kfs: Vec<(i64, Isometry3<f64>)> = Vec::new();
    // (keyframe time, keyframes and points in the current map) after each keyframe.
    let mut growth: Vec<(i64, usize, usize)> = Vec::new();
    let mut session = None;
    let mut dirty = false;
    let mut last_write = Instant::now();
    // Keyframes handled since the last idle step (local BA + culling).
    let mut since_idle = 0usize;
    loop {
        let job = match rx.recv_timeout(Duration::from_millis(200)) {
            Ok(j) => j,
            Err(RecvTimeoutError::Timeout) => {
                if dirty && last_write.elapsed() > WRITE_EVERY {
                    write_files(out.as_deref(), client, &h, &client_kfs, &growth);
                    dirty = false;
                    last_write = Instant::now();
                }
                continue;
            }
            Err(RecvTimeoutError::Disconnected) => break,
        };
        let (kf_session, kf_id, t_ns, t_ck) =
            (job.kf.session_id, job.kf.id, job.kf.t_ns, job.kf.t_ck);
        let t0 = Instant::now();
        let result = h.handle(job.kf).map_err(|e| e.to_string());
        let handle_ms = t0.elapsed().as_secs_f64() * 1e3;
        if let Ok(r) = &result {
            if r.status != KeyframeStatus::Duplicate {
                if session != Some(kf_session) {
                    client_kfs.clear();
                    session = Some(kf_session);
                }
                client_kfs.push((t_ns, t_ck));
                dirty = true;
            }
        }
        // Idle when the queue is empty, and at least every MAX_WITHOUT_IDLE keyframes even
        // in a burst (a client that sends its whole window at the end of its stream would
        // otherwise get no local BA at all while its map grows). The journal records the
        // decision, so a replay takes the same schedule.
        let idled = result.is_ok()
            && job
                .idle
                .unwrap_or_else(|| rx.is_empty() || since_idle + 1 >= MAX_WITHOUT_IDLE);
        since_idle = if idled { 0 } else { since_idle + 1 };
        let t1 = Instant::now();
        if idled {
            while h.idle_step().is_some() {}
        }
        let idle_ms = t1.elapsed().as_secs_f64() * 1e3;
        if let Some(m) = h.current_map() {
            growth.push((t_ns, m.map.keyframes.len(), m.map.points.len()));
        }
        let outcome = Outcome {
            client,
            session: kf_session,
            kf_id,
            result,
            idled,
            replay: job.replay,
            feedback: h.feedback(),
            figures: figures(&h),
            handle_ms,
            idle_ms,
        };
        if results.send(outcome).is_err() {
            break;
        }
        if dirty && last_write.elapsed() > WRITE_EVERY {
            write_files(out.as_deref(), client, &h, &client_kfs, &growth);
            dirty = false;
            last_write = Instant::now();
        }
    }
    write_files(out.as_deref(), client, &h, &client_kfs, &growth);
}

/// `OUT/keyframes_server_c{c}.txt`: the server keyframe poses `T_sk` of the client's
/// current server map (earlier maps of older sessions in `..._m{n}.txt`);
/// `OUT/keyframes_client_c{c}.txt`: the client poses `T_ck` of every keyframe of the current
/// session as received (the client VO's keyframes, for comparison);
/// `OUT/map_growth_c{c}.txt`: map size after each keyframe.
fn write_files(
    out: Option<&Path>,
    client: u32,
    h: &KeyframeHandler,
    client_kfs: &[(i64, Isometry3<f64>)],
    growth: &[(i64, usize, usize)],
) {
    let Some(out) = out else { return };
    let mut text = String::from("# t_ns keyframes points (client's current server map)\n");
    for (t, k, p) in growth {
        text.push_str(&format!("{t} {k} {p}\n"));
    }
    let _ = std::fs::write(out.join(format!("map_growth_c{client}.txt")), text);
    let current = h.current_map().map(|m| m.id);
    for (id, m) in h.maps() {
        let name = if Some(*id) == current {
            format!("keyframes_server_c{client}.txt")
        } else {
            format!("keyframes_server_c{client}_m{}.txt", id & 0xffff_ffff)
        };
        let _ = write_tum(&out.join(name), &m.trajectory());
    }
    let _ = write_tum(
        &out.join(format!("keyframes_client_c{client}.txt")),
        client_kfs,
    );
}

/// Writes a TUM trajectory (`t tx ty tz qx qy qz qw`, t in seconds) atomically.
pub fn write_tum(path: &Path, poses: &[(i64, Isometry3<f64>)]) -> std::io::Result<()> {
    let tmp = path.with_extension("txt.tmp");
    {
        let mut f = std::io::BufWriter::new(std::fs::File::create(&tmp)?);
        writeln!(f, "# t tx ty tz qx qy qz qw (camera-to-map, shoal mapper)")?;
        for (t, p) in poses {
            let q = p.rotation.quaternion();
            let v = p.translation.vector;
            let a = t.unsigned_abs();
            let sign = if *t < 0 { "-" } else { "" };
            writeln!(
                f,
                "{sign}{}.{:09} {:.9} {:.9} {:.9} {:.9} {:.9} {:.9} {:.9}",
                a / 1_000_000_000,
                a % 1_000_000_000,
                v.x,
                v.y,
                v.z,
                q.i,
                q.j,
                q.k,
                q.w
            )?;
        }
        f.flush()?;
    }
    std::fs::rename(&tmp, path)
}
