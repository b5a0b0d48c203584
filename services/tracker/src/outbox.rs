//! Keyframes on their way to the mapper: every keyframe leaving the client map (window
//! eviction, new session, end of stream) is published as a keyframe message and kept until
//! the mapper acknowledges it on the feedback service; unacknowledged ones are re-sent
//! (e.g. to a restarted mapper). Nothing is dropped while it is unacknowledged.
use std::collections::BTreeMap;

use iceoryx2::port::publisher::Publisher;
use shm_schema::time::monotonic_ns;
use shm_schema::topics::{Ipc, MAX_KEYPOINTS};
use shm_schema::{
    Intrinsics, KeyframeHeader, KeypointRecord, MsgMeta, Pose, FLAG_RESEND, NO_MAP_POINT,
};
use slam_core::vo::Keyframe;

/// One keyframe message, ready to (re-)send.
struct Pending {
    header: KeyframeHeader,
    records: Vec<KeypointRecord>,
    /// 0 while queued (not sent yet).
    last_sent_ns: i64,
}

/// Keyframe messages in flight (sent, unacknowledged) at most: the mapper's buffer holds
/// `KEYFRAME_BUFFER` (64) per client, so a burst (end of stream, new session) is paced.
pub const MAX_IN_FLIGHT: usize = 32;

/// Keyframes sent and not yet acknowledged.
pub struct Outbox {
    client: u32,
    next_seq: u64,
    pending: BTreeMap<(u32, u64), Pending>,
    /// Client poses `T_ck` of the keyframes sent, as sent, by (session, id): pose feedback
    /// refers to one of them (kept after the acknowledgement until newer feedback came).
    sent_poses: BTreeMap<(u32, u64), nalgebra::Isometry3<f64>>,
    /// Keyframe messages sent (first sends).
    pub sent: u64,
    /// Re-sends.
    pub resent: u64,
    /// Acknowledged keyframes.
    pub acked: u64,
}

/// Camera-to-map pose of a keyframe as a wire [`Pose`] (`T_ck`, p_c = R_ck p_k + t_ck).
pub fn wire_pose(t_cw: &nalgebra::Isometry3<f64>) -> Pose {
    shoal_runtime::wire::wire_from_iso(&t_cw.inverse())
}

/// The keyframe message of `kf` of VO session `session` (seed §3.3: its pose in the client
/// map, keypoints, descriptors and client map-point ids); `meta.seq` is set when sent.
pub fn keyframe_message(
    client: u32,
    kf: &Keyframe,
    session: u32,
) -> (KeyframeHeader, Vec<KeypointRecord>) {
    let c = &kf.camera;
    let n = kf.features.len().min(MAX_KEYPOINTS);
    let records: Vec<KeypointRecord> = (0..n)
        .map(|i| {
            let k = kf.features.keypoints[i];
            KeypointRecord {
                u: k.x,
                v: k.y,
                angle: k.angle,
                response: k.response,
                octave: k.octave as u32,
                reserved: 0,
                map_point_id: kf.points.get(i).copied().flatten().unwrap_or(NO_MAP_POINT),
                descriptor: kf.features.descriptors[i],
            }
        })
        .collect();
    let header = KeyframeHeader {
        meta: MsgMeta::new(client, session, 0, 0),
        keyframe_id: kf.id,
        t_ns: kf.t_ns,
        pose_ck: wire_pose(&kf.t_cw),
        intrinsics: Intrinsics {
            pinhole: [c.fx, c.fy, c.cx, c.cy],
            distortion: [c.k1, c.k2, c.p1, c.p2, c.k3],
        },
        width: c.width,
        height: c.height,
        n_keypoints: n as u32,
        reserved: 0,
    };
    (header, records)
}

impl Outbox {
    /// An empty outbox for `client`.
    pub fn new(client: u32) -> Self {
        Self {
            client,
            next_seq: 0,
            pending: BTreeMap::new(),
            sent_poses: BTreeMap::new(),
            sent: 0,
            resent: 0,
            acked: 0,
        }
    }

    /// Number of keyframes waiting for an acknowledgement (sent or still queued).
    pub fn pending(&self) -> usize {
        self.pending.len()
    }

    /// Keyframes sent (published at least once) and not acknowledged yet.
    pub fn in_flight(&self) -> usize {
        self.pending
            .values()
            .filter(|p| p.last_sent_ns != 0)
            .count()
    }

    /// Converts and publishes `kf` of VO session `session`, keeping it until acknowledged.
    pub fn send(
        &mut self,
        publisher: &Publisher<Ipc, [KeypointRecord], KeyframeHeader>,
        kf: &Keyframe,
        session: u32,
    ) -> anyhow::Result<()> {
        let (header, records) = keyframe_message(self.client, kf, session);
        self.send_message(publisher, header, records)
    }

    /// Publishes a keyframe message built by [`keyframe_message`] (e.g. one recovered from
    /// the spool of a killed predecessor), keeping it until acknowledged. Its session and id
    /// are the header's; the sequence number is this outbox's.
    pub fn send_message(
        &mut self,
        publisher: &Publisher<Ipc, [KeypointRecord], KeyframeHeader>,
        mut header: KeyframeHeader,
        records: Vec<KeypointRecord>,
    ) -> anyhow::Result<()> {
        let session = header.meta.session_id;
        header.meta = MsgMeta::new(self.client, session, self.next_seq, 0);
        self.next_seq += 1;
        let key = (session, header.keyframe_id);
        if let Some(t_ck) = shoal_runtime::wire::iso_from_wire(&header.pose_ck) {
            self.sent_poses.insert(key, t_ck);
        }
        self.pending.insert(
            key,
            Pending {
                header,
                records,
                last_sent_ns: 0,
            },
        );
        self.pump(publisher)
    }

    /// Sends queued keyframes while fewer than [`MAX_IN_FLIGHT`] are unacknowledged.
    pub fn pump(
        &mut self,
        publisher: &Publisher<Ipc, [KeypointRecord], KeyframeHeader>,
    ) -> anyhow::Result<()> {
        let mut in_flight = self
            .pending
            .values()
            .filter(|p| p.last_sent_ns != 0)
            .count();
        for p in self.pending.values_mut() {
            if in_flight >= MAX_IN_FLIGHT {
                break;
            }
            if p.last_sent_ns == 0 {
                publish(publisher, p, false)?;
                self.sent += 1;
                in_flight += 1;
            }
        }
        Ok(())
    }

    /// The client pose `T_ck` of keyframe `id` of `session` as it was sent (the client map
    /// may have refined it since; the server's feedback refers to the pose sent).
    pub fn sent_pose(&self, session: u32, id: u64) -> Option<nalgebra::Isometry3<f64>> {
        self.sent_poses.get(&(session, id)).copied()
    }

    /// Forgets the sent poses of keyframes before `id` of `session` (feedback comes in
    /// handling order, so they will not be referred to again).
    pub fn forget_sent_before(&mut self, session: u32, id: u64) {
        self.sent_poses = self.sent_poses.split_off(&(session, id));
    }

    /// Sent poses remembered.
    pub fn sent_poses_kept(&self) -> usize {
        self.sent_poses.len()
    }

    /// The mapper applied keyframe `id` of `session`.
    pub fn ack(&mut self, session: u32, id: u64) {
        if self.pending.remove(&(session, id)).is_some() {
            self.acked += 1;
        }
    }

    /// Re-sends keyframes unacknowledged for longer than `after_ns` (and sends queued ones).
    pub fn resend_stale(
        &mut self,
        publisher: &Publisher<Ipc, [KeypointRecord], KeyframeHeader>,
        after_ns: i64,
    ) -> anyhow::Result<()> {
        let now = monotonic_ns();
        for p in self.pending.values_mut() {
            if p.last_sent_ns != 0 && now - p.last_sent_ns > after_ns {
                publish(publisher, p, true)?;
                self.resent += 1;
            }
        }
        self.pump(publisher)
    }
}

fn publish(
    publisher: &Publisher<Ipc, [KeypointRecord], KeyframeHeader>,
    p: &mut Pending,
    resend: bool,
) -> anyhow::Result<()> {
    let sample = publisher.loan_slice_uninit(p.records.len())?;
    let mut sample = sample.write_from_slice(&p.records);
    let mut h = p.header;
    if resend {
        h.meta.flags |= FLAG_RESEND;
    }
    p.last_sent_ns = monotonic_ns();
    h.meta.publish_mono_ns = p.last_sent_ns;
    *sample.user_header_mut() = h;
    sample.send()?;
    Ok(())
}
