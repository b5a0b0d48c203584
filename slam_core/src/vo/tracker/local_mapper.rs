//! The local-mapping thread of the client VO (seed §3.3: "two threads, tracking and local
//! mapping"). The tracking thread inserts a keyframe (and triangulates with its reference
//! keyframe itself, seed change 3) and hands its id over a crossbeam channel; this thread
//! then triangulates with the other neighbours, culls recent points, runs the local bundle
//! adjustment on a snapshot of the local map (the map is not locked while it is solved),
//! writes the result back and culls redundant keyframes (`vo::kf_culling`; culled
//! keyframes are dropped, not sent to the server, as the seed's trash list).
//!
//! The map is shared as `Arc<Mutex<ClientMap>>`; each step holds the lock only for its own
//! reads and writes. While keyframes wait in the channel, only the newest one gets a BA
//! (ORB-SLAM aborts a running BA when a keyframe arrives, to the same effect).
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::{Arc, Mutex, MutexGuard};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

use crossbeam_channel::{Receiver, Sender};

use crate::optim::ba::{BaParams, BaProblem, BundleAdjuster};
use crate::vo::kf_culling::{cull_redundant_keyframes, KfCullingParams};
use crate::vo::local_mapping::{
    apply_local_ba, create_points_with_neighbours, cull_recent_points, prepare_local_ba,
};
use crate::vo::map::{ClientMap, KfId};
use crate::CoreError;

/// Locks the shared map; a panic elsewhere while holding it does not make the map unusable
/// (its invariants are restored by every step before it unlocks).
pub(crate) fn lock(map: &Mutex<ClientMap>) -> MutexGuard<'_, ClientMap> {
    map.lock().unwrap_or_else(|e| e.into_inner())
}

/// What the local-mapping steps do for one keyframe.
#[derive(Debug, Clone, Copy)]
pub(crate) struct LocalMappingParams {
    /// Neighbour keyframes to triangulate with and to adjust.
    pub neighbours: usize,
    /// Run the local bundle adjustment.
    pub local_ba: bool,
}

/// The local-mapping steps for keyframe `k`, inline (single-threaded mode): triangulation
/// with neighbours, culling of recent points, local BA, culling of redundant keyframes.
/// Returns the keyframes culled.
pub(crate) fn map_keyframe_inline(
    map: &mut ClientMap,
    k: KfId,
    p: &LocalMappingParams,
    ba: &mut BundleAdjuster,
    problem: &mut BaProblem,
) -> usize {
    create_points_with_neighbours(map, k, p.neighbours);
    cull_recent_points(map, k);
    if p.local_ba {
        if let Some(job) = prepare_local_ba(map, k, problem, p.neighbours) {
            if ba.optimize(problem, &BaParams::local()).is_ok() {
                apply_local_ba(map, &job, problem, ba.inliers());
            }
        }
    }
    cull_redundant_keyframes(map, k, &[], &KfCullingParams::default()).len()
}

/// Handle of the local-mapping thread.
pub(crate) struct LocalMappingThread {
    tx: Option<Sender<KfId>>,
    pending: Arc<AtomicUsize>,
    culled: Arc<AtomicUsize>,
    handle: Option<JoinHandle<()>>,
}

impl LocalMappingThread {
    /// Starts the thread on `map`.
    pub fn spawn(map: Arc<Mutex<ClientMap>>, p: LocalMappingParams) -> Result<Self, CoreError> {
        let (tx, rx) = crossbeam_channel::unbounded();
        let pending = Arc::new(AtomicUsize::new(0));
        let culled = Arc::new(AtomicUsize::new(0));
        let (pending_t, culled_t) = (Arc::clone(&pending), Arc::clone(&culled));
        let handle = std::thread::Builder::new()
            .name("local-mapping".into())
            .spawn(move || run(&map, &rx, &pending_t, &culled_t, &p))
            .map_err(|e| CoreError::InvalidArgument(format!("local-mapping thread: {e}")))?;
        Ok(Self {
            tx: Some(tx),
            pending,
            culled,
            handle: Some(handle),
        })
    }

    /// Keyframes culled as redundant so far.
    pub fn culled(&self) -> usize {
        self.culled.load(Ordering::Relaxed)
    }

    /// Queues keyframe `k`.
    pub fn submit(&self, k: KfId) {
        if let Some(tx) = &self.tx {
            self.pending.fetch_add(1, Ordering::SeqCst);
            if tx.send(k).is_err() {
                self.pending.fetch_sub(1, Ordering::SeqCst);
            }
        }
    }

    /// No keyframe waiting or being mapped.
    pub fn idle(&self) -> bool {
        self.pending.load(Ordering::SeqCst) == 0
    }

    /// Waits until idle (at most `timeout`); returns whether it is.
    pub fn wait_idle(&self, timeout: Duration) -> bool {
        let start = Instant::now();
        while !self.idle() {
            if start.elapsed() > timeout || self.handle.as_ref().is_none_or(|h| h.is_finished()) {
                return self.idle();
            }
            std::thread::sleep(Duration::from_micros(200));
        }
        true
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

fn run(
    map: &Mutex<ClientMap>,
    rx: &Receiver<KfId>,
    pending: &AtomicUsize,
    culled: &AtomicUsize,
    p: &LocalMappingParams,
) {
    let mut ba = BundleAdjuster::new();
    let mut problem = BaProblem::new();
    while let Ok(k) = rx.recv() {
        let job = {
            let mut m = lock(map);
            if m.keyframes.contains_key(&k) {
                create_points_with_neighbours(&mut m, k, p.neighbours);
                cull_recent_points(&mut m, k);
                if p.local_ba && rx.is_empty() {
                    prepare_local_ba(&m, k, &mut problem, p.neighbours)
                } else {
                    None
                }
            } else {
                None
            }
        };
        let solved = job.filter(|_| ba.optimize(&mut problem, &BaParams::local()).is_ok());
        {
            let mut m = lock(map);
            if let Some(job) = solved {
                apply_local_ba(&mut m, &job, &problem, ba.inliers());
            }
            if m.keyframes.contains_key(&k) {
                let n = cull_redundant_keyframes(&mut m, k, &[], &KfCullingParams::default());
                culled.fetch_add(n.len(), Ordering::Relaxed);
            }
        }
        pending.fetch_sub(1, Ordering::SeqCst);
    }
}
