//! The mapper's ports: every client's keyframe subscriber and feedback publisher, the loop
//! closer's keyframe publisher, the corrections and resync subscribers, and the event loop
//! that feeds a [`Mapper`] and publishes what it returns.
use std::time::{Duration, Instant};

use iceoryx2::node::Node;
use iceoryx2::port::publisher::Publisher;
use iceoryx2::port::subscriber::Subscriber;
use shm_schema::topics::{self, Ipc};
use shm_schema::{
    CorrectionHeader, CorrectionRecord, Feedback, KeyframeHeader, KeyframeRecord,
    LoopKeyframeHeader, LoopKeypointRecord, ResyncRequest,
};
use shoal_runtime::{ErrorKind, ServiceStart, Status};

use crate::core::{Mapper, Out};
use crate::worker::Report;
use crate::{Params, SERVICE_NAME};

/// The mapper's shared-memory ports.
struct Ports {
    node: Node<Ipc>,
    keyframes: Vec<Subscriber<Ipc, [KeyframeRecord], KeyframeHeader>>,
    feedback: Vec<Publisher<Ipc, Feedback, ()>>,
    loop_keyframes: Publisher<Ipc, [LoopKeypointRecord], LoopKeyframeHeader>,
    corrections: Subscriber<Ipc, [CorrectionRecord], CorrectionHeader>,
    resync: Subscriber<Ipc, ResyncRequest, ()>,
}

impl Ports {
    fn open(node: Node<Ipc>, clients: u32) -> anyhow::Result<Self> {
        let mut keyframes = Vec::new();
        let mut feedback = Vec::new();
        for c in 0..clients {
            let kfs = topics::keyframes_service(&node, c)?;
            keyframes.push(topics::keyframe_subscriber(&kfs)?);
            feedback.push(topics::publisher(&topics::feedback_service(&node, c)?)?);
        }
        let loop_service = topics::loop_keyframes_service(&node)?;
        let corr_service = topics::corrections_service(&node)?;
        Ok(Self {
            loop_keyframes: topics::slice_publisher(&loop_service, topics::MAX_KEYPOINTS)?,
            corrections: topics::slice_subscriber(&corr_service, topics::CORRECTION_BUFFER)?,
            resync: topics::subscriber(&topics::resync_service(&node)?)?,
            keyframes,
            feedback,
            node,
        })
    }

    /// Publishes what the mapper returned, in order.
    fn publish(&self, m: &mut Mapper) -> anyhow::Result<()> {
        for o in m.take_out() {
            match o {
                Out::Feedback(f) => {
                    if let Some(p) = self.feedback.get(f.meta.client_id as usize) {
                        p.send_copy(f)?;
                    }
                }
                Out::LoopKeyframe(h, recs) => {
                    let out = self.loop_keyframes.loan_slice_uninit(recs.len())?;
                    let mut out = out.write_from_slice(&recs);
                    *out.user_header_mut() = *h;
                    out.send()?;
                }
            }
        }
        Ok(())
    }

    /// Takes every waiting keyframe message; returns how many.
    fn keyframes(&self, m: &mut Mapper) -> anyhow::Result<usize> {
        let mut n = 0;
        for (c, sub) in self.keyframes.iter().enumerate() {
            while let Some(kf) = sub.receive()? {
                n += 1;
                let h = *kf.user_header();
                if let Err(e) = h.meta.check() {
                    let detail = format!("keyframe of client {c}: {e}");
                    m.status.error(ErrorKind::SchemaVersion, detail);
                    continue;
                }
                m.receive(c as u32, &h, kf.payload())?;
                self.publish(m)?;
            }
        }
        Ok(n)
    }

    /// Takes every waiting correction of the loop closer; returns how many.
    fn corrections(&self, m: &mut Mapper) -> anyhow::Result<usize> {
        let mut n = 0;
        while let Some(c) = self.corrections.receive()? {
            n += 1;
            let h = *c.user_header();
            if let Err(e) = h.meta.check() {
                let detail = format!("correction: {e}");
                m.status.error(ErrorKind::SchemaVersion, detail);
                continue;
            }
            m.receive_correction(&h, c.payload())?;
            self.publish(m)?;
        }
        Ok(n)
    }

    /// Takes every waiting resync request of a (restarted) loop closer; returns how many.
    fn resync(&self, m: &mut Mapper) -> anyhow::Result<usize> {
        let mut n = 0;
        while let Some(req) = self.resync.receive()? {
            n += 1;
            let req = *req;
            if let Err(e) = req.meta.check() {
                let detail = format!("resync request: {e}");
                m.status.error(ErrorKind::SchemaVersion, detail);
                continue;
            }
            m.resync(&req);
            self.publish(m)?;
        }
        Ok(n)
    }

    /// Takes the handlers' outcomes and publishes what follows; returns how many.
    fn outcomes(
        &self,
        m: &mut Mapper,
        rx: &crossbeam_channel::Receiver<Report>,
    ) -> anyhow::Result<usize> {
        let n = m.drain_outcomes(rx)?;
        self.publish(m)?;
        Ok(n)
    }
}

/// At the stop: the handlers finish what they have queued (at most `drain_seconds`) and
/// write their files; their outcomes are still published. Returns whether every handler
/// thread ended and was joined (its final maps kept, for `--save-map`).
fn drain(
    m: &mut Mapper,
    ports: &Ports,
    rx: &crossbeam_channel::Receiver<Report>,
    drain_seconds: f64,
) -> anyhow::Result<bool> {
    let queued: usize = m.workers.iter().map(|w| w.queued()).sum();
    m.status.set_value("queued_at_stop", queued as f64);
    for w in m.workers.iter_mut() {
        w.close();
    }
    let deadline = Instant::now() + Duration::from_secs_f64(drain_seconds.max(0.0));
    loop {
        ports.outcomes(m, rx)?;
        let running = m.workers.iter().any(|w| !w.is_finished());
        if !running || Instant::now() > deadline {
            break;
        }
        std::thread::sleep(Duration::from_millis(5));
    }
    ports.outcomes(m, rx)?;
    let mut all_joined = true;
    for (i, w) in m.workers.iter_mut().enumerate() {
        if !w.is_finished() {
            all_joined = false;
        } else if !w.join() {
            all_joined = false;
            let detail = format!("handler thread {i} panicked");
            m.status.error(ErrorKind::Handler, detail);
        }
    }
    Ok(all_joined)
}

/// Serves keyframes until SIGINT/SIGTERM, then lets the handlers finish their queues.
pub fn run(params: &Params) -> anyhow::Result<Status> {
    let cfg = params.config()?;
    let mut start = ServiceStart::open(
        SERVICE_NAME,
        "mapper",
        params.status.clone(),
        params.ipc_prefix.clone(),
    )?;
    let (results_tx, results_rx) = crossbeam_channel::unbounded();
    let mut m = Mapper::new(params, &cfg, std::mem::take(&mut start.status), results_tx);
    // The loaded maps first (the journal's corrections may name them), then the journal.
    if let Some(path) = &params.load_map {
        crate::saved::load(&mut m, path)?;
    }
    // Rebuild the maps from the journal before taking new keyframes.
    if let Some(path) = &params.journal {
        m.open_journal(path)?;
    }
    let ports = Ports::open(start.node, params.clients)?;
    let mut trimmer = shoal_runtime::HeapTrimmer::new(Duration::from_secs(5));
    shoal_runtime::signal_ready();
    loop {
        let mut busy = ports.keyframes(&mut m)? > 0;
        busy |= ports.corrections(&mut m)? > 0;
        busy |= ports.outcomes(&mut m, &results_rx)? > 0;
        busy |= ports.resync(&mut m)? > 0;
        if start.file.due(Duration::from_millis(200)) {
            let _ = start.file.write(m.status_now());
        }
        if !busy {
            trimmer.maybe_trim();
            if ports.node.wait(Duration::from_millis(1)).is_err() {
                break;
            }
        }
    }
    let all_joined = drain(&mut m, &ports, &results_rx, cfg.drain_seconds)?;
    if let Some(path) = &params.save_map {
        crate::saved::save(&mut m, path, all_joined);
    } else if m.localize_only {
        crate::saved::check_frozen(&mut m);
    }
    m.status.finished = true;
    start.file.write(m.status_now())?;
    Ok(std::mem::take(&mut m.status))
}
