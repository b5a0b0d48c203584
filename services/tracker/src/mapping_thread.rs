//! The local-mapping thread of the client VO (seed §3.3: "two threads, tracking and local
//! mapping"). `slam_core` keeps the steps ([`LocalMapper::step`]) and starts no thread; this
//! service owns the thread and its channel. The tracking thread inserts a keyframe and hands
//! its id over a crossbeam channel ([`LocalMappingRunner::submit`]); the thread maps the
//! keyframes in the order given, each step holding the shared map's lock only for its own
//! reads and writes. While keyframes wait in the channel, a step skips the local BA.
//!
//! In lock-step the VO waits before each frame until the thread is idle
//! (`VoParams::sync_local_mapping`): it then takes the decisions of inline local mapping,
//! whatever the thread's timing.
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::{Arc, Mutex};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

use crossbeam_channel::{Receiver, Sender};
use slam_core::vo::{
    KfId, LocalMapper, LocalMappingRunner, LocalMappingStats, SharedMap, VoTracker,
};

/// Handle of the local-mapping thread; dropping it ends the thread (after the keyframes
/// queued) and joins it.
pub struct LocalMappingThread {
    tx: Option<Sender<KfId>>,
    pending: Arc<AtomicUsize>,
    stats: Arc<Mutex<LocalMappingStats>>,
    handle: Option<JoinHandle<()>>,
}

impl LocalMappingThread {
    /// Starts the thread: `mapper`'s steps on `map`.
    pub fn spawn(map: SharedMap, mapper: LocalMapper) -> std::io::Result<Self> {
        let (tx, rx) = crossbeam_channel::unbounded();
        let pending = Arc::new(AtomicUsize::new(0));
        let stats = Arc::new(Mutex::new(LocalMappingStats::default()));
        let (pending_t, stats_t) = (Arc::clone(&pending), Arc::clone(&stats));
        let handle = std::thread::Builder::new()
            .name("local-mapping".into())
            .spawn(move || run(&map, &rx, &pending_t, &stats_t, mapper))?;
        Ok(Self {
            tx: Some(tx),
            pending,
            stats,
            handle: Some(handle),
        })
    }

    /// Starts a local-mapping thread for `vo` (its shared map and parameters) and hands
    /// the VO's local mapping to it. Before the first frame.
    pub fn attach(vo: &mut VoTracker) -> std::io::Result<()> {
        let thread = Self::spawn(vo.shared_map(), vo.local_mapper())?;
        vo.set_local_mapping(Box::new(thread));
        Ok(())
    }
}

impl LocalMappingRunner for LocalMappingThread {
    fn submit(&self, k: KfId) {
        if let Some(tx) = &self.tx {
            self.pending.fetch_add(1, Ordering::SeqCst);
            if tx.send(k).is_err() {
                self.pending.fetch_sub(1, Ordering::SeqCst);
            }
        }
    }

    fn idle(&self) -> bool {
        self.pending.load(Ordering::SeqCst) == 0
    }

    fn wait_idle(&self, timeout: Duration) -> bool {
        let start = Instant::now();
        while !self.idle() {
            if start.elapsed() > timeout || self.handle.as_ref().is_none_or(|h| h.is_finished()) {
                return self.idle();
            }
            std::thread::sleep(Duration::from_micros(200));
        }
        true
    }

    fn stats(&self) -> LocalMappingStats {
        *self.stats.lock().unwrap_or_else(|e| e.into_inner())
    }
}

impl Drop for LocalMappingThread {
    fn drop(&mut self) {
        self.tx = None;
        if let Some(h) = self.handle.take() {
            let _ = h.join();
        }
    }
}

/// The thread's body: one [`LocalMapper::step`] per keyframe received.
fn run(
    map: &SharedMap,
    rx: &Receiver<KfId>,
    pending: &AtomicUsize,
    stats: &Mutex<LocalMappingStats>,
    mut mapper: LocalMapper,
) {
    while let Ok(k) = rx.recv() {
        let step = mapper.step(map, k, || !rx.is_empty());
        stats.lock().unwrap_or_else(|e| e.into_inner()).add(&step);
        pending.fetch_sub(1, Ordering::SeqCst);
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use datasets::sim::{Scenario, SimParams, SimWorld};
    use slam_core::features::GrayImage;
    use slam_core::vo::{VoFrame, VoParams};

    /// Poses and keyframe decisions of the VO on 60 frames of the synthetic `loop`,
    /// local mapping inline or on the thread (synchronised, as in lock-step).
    fn poses(thread: bool) -> Vec<(Option<nalgebra::Isometry3<f64>>, Option<KfId>)> {
        let mut p = SimParams::new(Scenario::Loop);
        p.frames = Some(60);
        p.seed = 3;
        let world = SimWorld::new(p).expect("world");
        let cal = world.calib();
        let cam = cal.model;
        let params = VoParams {
            sync_local_mapping: true,
            ..VoParams::default()
        };
        let mut vo = VoTracker::new(params, cam).expect("vo");
        if thread {
            LocalMappingThread::attach(&mut vo).expect("thread");
        }
        assert_eq!(vo.local_mapping_runner(), thread);
        let mut img = vec![0u8; (cam.width * cam.height) as usize];
        let mut out = vec![];
        for k in 0..world.n_frames() {
            world.render_frame_into(k, &mut img).expect("render");
            let image = GrayImage::from_packed(&img, cam.width as usize, cam.height as usize)
                .expect("image");
            let o = vo
                .process(&VoFrame {
                    image,
                    t_ns: world.frame_time_ns(k),
                    readout_ns: cal.readout_ns,
                    angular_velocity: None,
                })
                .expect("process");
            out.push((o.t_cw, o.keyframe));
        }
        assert_eq!(vo.local_mapping_sync_timeouts(), 0);
        out
    }

    /// The thread, synchronised before each frame, takes exactly the decisions and poses
    /// of inline local mapping (the lock-step guarantee).
    #[test]
    fn synchronised_thread_matches_inline_mapping() {
        let inline = poses(false);
        let threaded = poses(true);
        let keyframes = inline.iter().filter(|f| f.1.is_some()).count();
        assert!(
            keyframes >= 3,
            "{keyframes} keyframes: local mapping barely ran"
        );
        assert_eq!(inline, threaded);
    }
}
