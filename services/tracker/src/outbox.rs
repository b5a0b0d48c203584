//! Keyframes on their way to the mapper: every keyframe leaving the client map (window
//! eviction, new session, end of stream) is published as a keyframe message and kept until
//! the mapper acknowledges it on the feedback service; unacknowledged ones are re-sent
//! (e.g. to a restarted mapper). Nothing is dropped while it is unacknowledged.
//!
//! Pure bookkeeping: it decides what to (re-)send and hands the messages to its caller, which
//! publishes them ([`KeyframeMsg`]); times are the caller's `now_ns`.
use std::collections::BTreeMap;

use shm_schema::topics::{MAX_IMU_RECORDS, MAX_KEYPOINTS};
use shm_schema::{
    ImuRecord, KeyframeHeader, KeyframeRecord, KeypointRecord, MsgMeta, Pose, FLAG_RESEND,
    NO_MAP_POINT,
};
use slam_core::vo::keyframe_imu::KeyframeImu;
use slam_core::vo::Keyframe;

/// A keyframe message (header, keypoint records, IMU records) as it goes on the wire.
#[derive(Debug, Clone)]
pub struct KeyframeMsg {
    /// Header: session, id, pose, intrinsics, IMU segment borders and calibration.
    pub header: KeyframeHeader,
    /// One record per keypoint, shared by the outbox and the messages it hands out (a
    /// re-send copies the header only).
    pub records: std::sync::Arc<[KeypointRecord]>,
    /// The IMU segment since the previous keyframe (`header.n_imu` samples, borders
    /// interpolated, `VI_NOTES.md` §4 Fig. 5.4); empty for a monocular client.
    pub imu: std::sync::Arc<[ImuRecord]>,
    /// Samples of the segment left out because it was longer than [`MAX_IMU_RECORDS`]
    /// (counted and logged by the sender; not on the wire).
    pub imu_cut: usize,
}

impl KeyframeMsg {
    /// The keyframe's (VO session, id).
    pub fn key(&self) -> (u32, u64) {
        (self.header.meta.session_id, self.header.keyframe_id)
    }

    /// The payload as published: the keypoint records, then the IMU records.
    pub fn payload(&self) -> Vec<KeyframeRecord> {
        let kps = self.records.iter().map(|r| KeyframeRecord::from(*r));
        kps.chain(self.imu.iter().map(|r| KeyframeRecord::from(*r)))
            .collect()
    }
}

/// One keyframe message, ready to (re-)send.
struct Pending {
    msg: KeyframeMsg,
    /// When it was last published (`None` while queued: a clock reading of 0, as the
    /// in-process tests give, is a send like any other).
    last_sent_ns: Option<i64>,
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
/// map, keypoints, descriptors and client map-point ids); `meta.seq` is set when sent. Its
/// pose and velocity are moved by `to_session`, from the client's present world to the
/// session's own (`slam_core::vio::anchor`; the identity for a client never anchored).
pub fn keyframe_message(
    client: u32,
    kf: &Keyframe,
    session: u32,
    to_session: &nalgebra::Isometry3<f64>,
) -> KeyframeMsg {
    let (intrinsics, width, height) = shoal_runtime::wire::intrinsics_from_camera(&kf.camera);
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
        pose_ck: shoal_runtime::wire::wire_from_iso(&(to_session * kf.t_cw.inverse())),
        intrinsics,
        width,
        height,
        n_keypoints: n as u32,
        inertial: kf.inertial.is_some() as u32,
        velocity_w: kf
            .inertial
            .map_or([0.0; 3], |i| (to_session.rotation * i.v_wb).into()),
        gyro_bias: kf.inertial.map_or([0.0; 3], |i| i.biases.gyro.into()),
        accel_bias: kf.inertial.map_or([0.0; 3], |i| i.biases.accel.into()),
        ..KeyframeHeader::default()
    };
    let (header, imu, imu_cut) = with_imu_segment(header, kf.imu.as_ref());
    KeyframeMsg {
        header,
        records: records.into(),
        imu: imu.into(),
        imu_cut,
    }
}

/// `header` with the IMU fields of segment `seg` (issue 19; `None`: a monocular client,
/// unchanged), its records (borders interpolated at exactly the previous keyframe's and
/// this keyframe's IMU times, [`KeyframeImu::interpolated_samples`]; none for a session's
/// first keyframe or an incomplete segment), and the samples cut beyond
/// [`MAX_IMU_RECORDS`] (the segment then ends at its last record, before the keyframe).
fn with_imu_segment(
    mut header: KeyframeHeader,
    seg: Option<&KeyframeImu>,
) -> (KeyframeHeader, Vec<ImuRecord>, usize) {
    let Some(seg) = seg else {
        return (header, Vec::new(), 0);
    };
    header.has_imu = 1;
    header.imu_t1_ns = seg.t_ns;
    header.imu_calib = shoal_runtime::wire::wire_from_imu_calibration(&seg.calib);
    let mut samples = seg.interpolated_samples().unwrap_or_default();
    let cut = samples.len().saturating_sub(MAX_IMU_RECORDS);
    samples.truncate(MAX_IMU_RECORDS);
    let records: Vec<ImuRecord> = samples
        .iter()
        .map(shoal_runtime::wire::imu_record)
        .collect();
    header.n_imu = records.len() as u32;
    header.imu_t0_ns = records.first().map_or(0, |r| r.t_ns);
    (header, records, cut)
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
            .filter(|p| p.last_sent_ns.is_some())
            .count()
    }

    /// Queues a keyframe message built by [`keyframe_message`] (or recovered from the spool
    /// of a killed predecessor), keeps it until acknowledged and appends to `out` what is to
    /// be published now. Its session and id are the header's; the sequence number is this
    /// outbox's.
    pub fn send(&mut self, mut msg: KeyframeMsg, now_ns: i64, out: &mut Vec<KeyframeMsg>) {
        let session = msg.header.meta.session_id;
        msg.header.meta = MsgMeta::new(self.client, session, self.next_seq, 0);
        self.next_seq += 1;
        let key = msg.key();
        if let Some(t_ck) = shoal_runtime::wire::iso_from_wire(&msg.header.pose_ck) {
            self.sent_poses.insert(key, t_ck);
        }
        self.pending.insert(
            key,
            Pending {
                msg,
                last_sent_ns: None,
            },
        );
        self.pump(now_ns, out);
    }

    /// Sends queued keyframes while fewer than [`MAX_IN_FLIGHT`] are unacknowledged.
    fn pump(&mut self, now_ns: i64, out: &mut Vec<KeyframeMsg>) {
        let mut in_flight = self.in_flight();
        for p in self.pending.values_mut() {
            if in_flight >= MAX_IN_FLIGHT {
                break;
            }
            if p.last_sent_ns.is_none() {
                out.push(stamp(p, now_ns, false));
                self.sent += 1;
                in_flight += 1;
            }
        }
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
    pub fn resend_stale(&mut self, now_ns: i64, after_ns: i64, out: &mut Vec<KeyframeMsg>) {
        for p in self.pending.values_mut() {
            if p.last_sent_ns.is_some_and(|t| now_ns - t > after_ns) {
                out.push(stamp(p, now_ns, true));
                self.resent += 1;
            }
        }
        self.pump(now_ns, out);
    }
}

/// The message of `p` as published at `now_ns` (a re-send flagged [`FLAG_RESEND`]).
fn stamp(p: &mut Pending, now_ns: i64, resend: bool) -> KeyframeMsg {
    let mut msg = p.msg.clone();
    if resend {
        msg.header.meta.flags |= FLAG_RESEND;
    }
    p.last_sent_ns = Some(now_ns);
    msg.header.meta.publish_mono_ns = now_ns;
    msg
}

#[cfg(test)]
mod tests {
    use super::*;

    fn msg(session: u32, id: u64) -> KeyframeMsg {
        let mut header = KeyframeHeader::default();
        header.meta.session_id = session;
        header.keyframe_id = id;
        header.pose_ck = Pose::IDENTITY;
        KeyframeMsg {
            header,
            records: vec![KeypointRecord::default(); 3].into(),
            imu: Vec::new().into(),
            imu_cut: 0,
        }
    }

    /// A segment of `n` samples 2.5 ms apart, the keyframes at both ends (between samples).
    fn segment(n: i64, t_prev: Option<i64>) -> KeyframeImu {
        use slam_core::imu::{ImuMeasurement, PreintegrationParams};
        let samples = (0..n)
            .map(|k| ImuMeasurement {
                t_ns: k * 2_500_000,
                gyro: nalgebra::Vector3::new(0.1, 0.0, 0.0),
                accel: nalgebra::Vector3::new(0.0, 0.0, 9.81),
            })
            .collect();
        let preint = PreintegrationParams::new(&Default::default(), &Default::default());
        KeyframeImu {
            t_prev_ns: t_prev,
            t_ns: (n - 1) * 2_500_000 - 1_000_000,
            samples,
            calib: slam_core::vo::keyframe_imu::ImuCalibration {
                preint: preint.expect("params"),
                t_bc: nalgebra::Isometry3::translation(0.1, 0.0, 0.0),
                t_d_ns: 7,
            },
        }
    }

    /// The IMU part of a message (issue 19): a monocular keyframe's header is unchanged; a
    /// session's first keyframe carries the calibration and no record; a segment has its
    /// borders exact; one longer than `MAX_IMU_RECORDS` is cut to that many records, and
    /// the cut is reported for counting.
    #[test]
    fn imu_segments_on_the_wire_and_cut_beyond_the_limit() {
        let h = KeyframeHeader::default();
        let (mono, recs, cut) = with_imu_segment(h, None);
        assert_eq!((mono, recs.len(), cut), (h, 0, 0));
        let (first, recs, cut) = with_imu_segment(h, Some(&segment(10, None)));
        assert_eq!((first.has_imu, first.n_imu, recs.len(), cut), (1, 0, 0, 0));
        assert_eq!(first.imu_calib.t_d_ns, 7);
        assert_eq!(first.imu_calib.pose_bc.t[0], 0.1);
        let seg = segment(100, Some(1_000_000));
        let (vi, recs, cut) = with_imu_segment(h, Some(&seg));
        assert_eq!((vi.n_imu as usize, recs.len(), cut), (100, 100, 0));
        assert_eq!((vi.imu_t0_ns, vi.imu_t1_ns), (1_000_000, seg.t_ns));
        assert_eq!((recs[0].t_ns, recs[99].t_ns), (1_000_000, seg.t_ns));
        let long = segment(MAX_IMU_RECORDS as i64 + 50, Some(1_000_000));
        let (cut_h, recs, cut) = with_imu_segment(h, Some(&long));
        assert_eq!(
            (cut_h.n_imu as usize, recs.len()),
            (MAX_IMU_RECORDS, MAX_IMU_RECORDS)
        );
        assert_eq!(cut, 50);
        assert!(
            recs[MAX_IMU_RECORDS - 1].t_ns < long.t_ns,
            "ends before the keyframe"
        );
    }

    /// A burst beyond the in-flight limit is paced; acknowledgements let the rest out; an
    /// unacknowledged keyframe is re-sent after the timeout, flagged, and counted.
    #[test]
    fn paces_bursts_and_resends_stale() {
        let mut ob = Outbox::new(2);
        let mut out = vec![];
        for id in 0..(MAX_IN_FLIGHT as u64 + 5) {
            ob.send(msg(7, id), 1_000, &mut out);
        }
        assert_eq!(out.len(), MAX_IN_FLIGHT);
        assert_eq!((ob.sent, ob.pending(), ob.in_flight()), (32, 37, 32));
        assert!(out
            .iter()
            .enumerate()
            .all(|(i, m)| m.header.meta.seq == i as u64
                && m.header.meta.client_id == 2
                && m.header.meta.publish_mono_ns == 1_000));
        for id in 0..5 {
            ob.ack(7, id);
        }
        ob.ack(7, 0); // a second acknowledgement counts once
        out.clear();
        ob.resend_stale(2_000, 10_000, &mut out);
        assert_eq!(out.len(), 5, "the queued five go out");
        assert_eq!((ob.acked, ob.sent, ob.resent), (5, 37, 0));
        out.clear();
        ob.resend_stale(20_000, 10_000, &mut out);
        assert_eq!(out.len(), 32);
        assert!(out.iter().all(|m| m.header.meta.flags & FLAG_RESEND != 0));
        assert_eq!(ob.resent, 32);
        assert!(ob.sent_pose(7, 6).is_some());
        ob.forget_sent_before(7, 6);
        assert!(ob.sent_pose(7, 5).is_none() && ob.sent_pose(7, 6).is_some());
    }
}
