//! The recorder: where poses leave the pipeline. Subscribes to every client's `poses`
//! service, keeps the tracked trajectory and the latency histograms.
use hdrhistogram::Histogram;
use shm_schema::topics::{self, Ipc};
use shm_schema::{PoseSource, TrackState, TrackedPose};

/// Percentiles (milliseconds of a latency, millimetres of a distance).
#[derive(Debug, Clone, Default, serde::Serialize)]
pub struct Percentiles {
    /// Number of samples.
    pub n: u64,
    /// Median.
    pub p50: f64,
    /// 90th percentile.
    pub p90: f64,
    /// 99th percentile.
    pub p99: f64,
    /// Largest.
    pub max: f64,
    /// Mean.
    pub mean: f64,
}

/// A latency histogram in microseconds (1 µs .. 60 s, 3 significant digits).
pub struct LatencyHist(Histogram<u64>);

impl Default for LatencyHist {
    fn default() -> Self {
        Self::new()
    }
}

impl LatencyHist {
    /// An empty histogram.
    pub fn new() -> Self {
        // 1 µs .. 60 s with 3 significant figures: valid bounds, cannot fail.
        Self(Histogram::new_with_bounds(1, 60_000_000, 3).expect("valid histogram bounds"))
    }

    /// Records a duration in nanoseconds (clamped to the histogram's range).
    pub fn record_ns(&mut self, ns: i64) {
        self.0.saturating_record((ns.max(0) as u64 / 1000).max(1));
    }

    /// Records a distance in metres, as micrometres in place of microseconds, so that
    /// [`LatencyHist::percentiles`] reads in millimetres (1 µm .. 60 m).
    pub fn record_m(&mut self, m: f64) {
        self.record_ns((m * 1e9) as i64);
    }

    /// Percentiles in ms.
    pub fn percentiles(&self) -> Percentiles {
        let h = &self.0;
        let ms = |v: u64| v as f64 / 1000.0;
        Percentiles {
            n: h.len(),
            p50: ms(h.value_at_quantile(0.5)),
            p90: ms(h.value_at_quantile(0.9)),
            p99: ms(h.value_at_quantile(0.99)),
            max: ms(h.max()),
            mean: h.mean() / 1000.0,
        }
    }
}

/// What became of one frame of a client, as the recorder saw it (the reason of an unposed
/// frame in `frames_unposed`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum FrameFate {
    /// No pose message for it (not replayed, dropped, or corrupt).
    #[default]
    Unseen,
    /// Handled before the VO session's map existed and never given a pose later.
    BeforeInit,
    /// Handled while tracking was lost (relocalisation failed).
    Lost,
    /// A valid pose: tracked, or found later (backfill / backward tracking).
    Posed,
}

/// Largest dataset index the recorder keeps per-frame state for (2^27 frames: 128 MiB of
/// states at most, 77 days at 20 Hz): a bogus index must not make it allocate more.
const MAX_FRAME_INDEX: u64 = 1 << 27;

/// What the recorder keeps of one client.
pub struct ClientRecord {
    subscriber: iceoryx2::port::subscriber::Subscriber<Ipc, TrackedPose, ()>,
    /// Poses received (one per frame the tracker handled; a frame handled twice, by a
    /// tracker that died before acknowledging it and by its restarted successor, twice).
    pub poses: u64,
    /// Distinct frames (dataset indices) with a pose: the frames the tracker handled, exact
    /// across tracker restarts (a killed tracker's own counters lag its last status write).
    pub frames_posed: u64,
    /// Which dataset indices have a pose (bit set).
    posed: Vec<u64>,
    /// What became of each frame (dataset index).
    fates: Vec<FrameFate>,
    /// Frame time → dataset index of the frames handled without a valid pose, to place the
    /// late poses of backfilled frames (which carry only their time).
    unposed_at: std::collections::HashMap<i64, u64>,
    /// Frames with a valid pose when they were tracked.
    pub tracked: u64,
    /// Frames given a pose later, when the VO initialised (`FLAG_BACKFILL`).
    pub backfilled: u64,
    /// Frames with a valid pose in the server map.
    pub tracked_server: u64,
    /// Valid poses, in arrival order (backfilled ones arrive late): (t_ns, pose).
    pub trajectory: Vec<(i64, shm_schema::Pose)>,
    /// The VO session of each pose of `trajectory` (its map frame).
    pub trajectory_sessions: Vec<u32>,
    /// Gyro-propagated orientations of frames with no pose (visual-inertial client before
    /// its inertial initialisation): (t_ns, camera-to-world rotation `q`, [`TrackState`]
    /// as `u32`, VO session).
    pub orientations: Vec<(i64, [f64; 4], u32, u32)>,
    /// Valid poses by where they came from ([`shm_schema::PoseSource`] as index).
    pub pose_sources: [u64; 5],
    /// World moves taken (`FLAG_WORLD_MOVE`): each re-expressed the earlier poses and
    /// orientations of its session.
    pub world_moves: u64,
    /// Of the poses in `trajectory`: in a metric, gravity-aligned world when last
    /// (re-)expressed (count).
    pub metric_poses: u64,
    /// Valid server-map poses: (t_ns, pose, server map id).
    pub server_trajectory: Vec<(i64, shm_schema::Pose, u64)>,
    /// True once the tracker sent its end of stream.
    pub ended: bool,
    /// Messages of another schema version.
    pub bad_messages: u64,
    /// Frame publish → pose publish of this client's frames.
    pub publish_to_pose: LatencyHist,
    /// Per tracked frame with a server-map pose, the distance between its camera centre as
    /// tracked and in the server map (a visual-inertial client anchored to its map:
    /// centimetres; otherwise the two frames' offset; [`LatencyHist::record_m`]: the
    /// percentiles read in mm).
    pub live_server_gap: LatencyHist,
}

impl ClientRecord {
    /// Notes a pose of frame `index`; counts it once.
    fn mark_posed(&mut self, index: u64) {
        // The ingest sets indices below the dataset's length; a bogus one must not make the
        // launcher allocate gigabytes.
        if index >= MAX_FRAME_INDEX {
            return;
        }
        let (word, bit) = ((index / 64) as usize, 1u64 << (index % 64));
        if word >= self.posed.len() {
            self.posed.resize(word + 1, 0);
        }
        if self.posed[word] & bit == 0 {
            self.posed[word] |= bit;
            self.frames_posed += 1;
        }
    }

    /// Notes the state a frame was handled in; a valid pose is final.
    fn note_fate(&mut self, index: u64, t_ns: i64, state: Option<TrackState>) {
        if index >= MAX_FRAME_INDEX {
            return;
        }
        let i = index as usize;
        if i >= self.fates.len() {
            self.fates.resize(i + 1, FrameFate::Unseen);
        }
        let fate = match state {
            Some(TrackState::Tracking) => FrameFate::Posed,
            Some(TrackState::Lost) => FrameFate::Lost,
            _ => FrameFate::BeforeInit,
        };
        if self.fates[i] == FrameFate::Posed {
            return;
        }
        self.fates[i] = fate;
        if fate == FrameFate::Posed {
            self.unposed_at.remove(&t_ns);
        } else {
            self.unposed_at.insert(t_ns, index);
        }
    }

    /// A late pose of the frame at `t_ns` (backfill, backward tracking).
    fn note_late_pose(&mut self, t_ns: i64) {
        if let Some(i) = self.unposed_at.remove(&t_ns) {
            self.fates[i as usize] = FrameFate::Posed;
        }
    }

    /// Re-expresses the poses and orientations of VO session `session` received so far in
    /// the world the tracker moved it to: `x' = s R x + t` (positions), `R_wc' = R R_wc`
    /// (`FLAG_WORLD_MOVE`; `move_pose` holds `R` and `t`).
    fn move_world(&mut self, session: u32, s: f64, move_pose: &shm_schema::Pose) {
        let Some(r) = shoal_runtime::wire::rotation_from_wire(move_pose) else {
            return;
        };
        if !(s.is_finite() && s > 0.0) {
            return;
        }
        let t_move = nalgebra::Vector3::from(move_pose.t);
        if !t_move.iter().all(|x| x.is_finite()) {
            return;
        }
        self.world_moves += 1;
        let moved = |p: &shm_schema::Pose| {
            let t = r * (nalgebra::Vector3::from(p.t) * s) + t_move;
            let q = shoal_runtime::wire::rotation_from_wire(p).map(|q| r * q);
            q.map(|q| shm_schema::Pose {
                t: t.into(),
                q: [q.i, q.j, q.k, q.w],
            })
        };
        for (pose, sess) in self.trajectory.iter_mut().zip(&self.trajectory_sessions) {
            if *sess == session {
                if let Some(m) = moved(&pose.1) {
                    pose.1 = m;
                }
            }
        }
        for o in self.orientations.iter_mut().filter(|o| o.3 == session) {
            let p = shm_schema::Pose {
                t: [0.0; 3],
                q: o.1,
            };
            if let Some(m) = moved(&p) {
                o.1 = m.q;
            }
        }
    }

    /// Frames with a valid pose, and of the frames handled without one: (before the
    /// initialisation, while lost).
    pub fn fate_counts(&self) -> (u64, u64, u64) {
        let n = |f: FrameFate| self.fates.iter().filter(|&&x| x == f).count() as u64;
        (
            n(FrameFate::Posed),
            n(FrameFate::BeforeInit),
            n(FrameFate::Lost),
        )
    }
}

/// The recorder of all clients.
pub struct Recorder {
    /// Per client.
    pub clients: Vec<ClientRecord>,
    /// Frame publish → pose publish.
    pub publish_to_pose: LatencyHist,
    /// Frame publish → frame taken by the tracker.
    pub publish_to_receive: LatencyHist,
    /// Inside the tracker: the whole tracking step.
    pub tracker_total: LatencyHist,
}

impl Recorder {
    /// Subscribes to the poses of `n_clients` clients.
    pub fn new(node: &iceoryx2::node::Node<Ipc>, n_clients: u32) -> anyhow::Result<Self> {
        let mut clients = Vec::new();
        for c in 0..n_clients {
            let service = topics::poses_service(node, c)?;
            clients.push(ClientRecord {
                subscriber: topics::subscriber(&service)?,
                poses: 0,
                frames_posed: 0,
                posed: Vec::new(),
                fates: Vec::new(),
                unposed_at: std::collections::HashMap::new(),
                tracked: 0,
                tracked_server: 0,
                backfilled: 0,
                trajectory: Vec::new(),
                trajectory_sessions: Vec::new(),
                orientations: Vec::new(),
                pose_sources: [0; 5],
                world_moves: 0,
                metric_poses: 0,
                server_trajectory: Vec::new(),
                ended: false,
                bad_messages: 0,
                publish_to_pose: LatencyHist::new(),
                live_server_gap: LatencyHist::new(),
            });
        }
        Ok(Self {
            clients,
            publish_to_pose: LatencyHist::new(),
            publish_to_receive: LatencyHist::new(),
            tracker_total: LatencyHist::new(),
        })
    }

    /// Distinct frames with a pose, per client.
    pub fn frames_posed(&self) -> Vec<u64> {
        self.clients.iter().map(|c| c.frames_posed).collect()
    }

    /// Takes every pose waiting; returns how many were taken.
    pub fn drain(&mut self) -> anyhow::Result<usize> {
        let mut n = 0;
        for rec in self.clients.iter_mut() {
            while let Some(sample) = rec.subscriber.receive()? {
                n += 1;
                let p = *sample.payload();
                if p.meta.check().is_err() {
                    rec.bad_messages += 1;
                    continue;
                }
                if p.meta.is_end_of_stream() {
                    rec.ended = true;
                    continue;
                }
                if p.meta.flags & shm_schema::FLAG_WORLD_MOVE != 0 {
                    rec.move_world(p.meta.session_id, p.world_scale, &p.pose);
                    continue;
                }
                if p.meta.flags & shm_schema::FLAG_BACKFILL != 0 {
                    // An earlier frame's pose found at initialisation: no latency stamps.
                    if TrackState::from_u32(p.state) == Some(TrackState::Tracking) {
                        rec.backfilled += 1;
                        rec.trajectory.push((p.t_ns, p.pose));
                        rec.trajectory_sessions.push(p.meta.session_id);
                        rec.note_late_pose(p.t_ns);
                    }
                    continue;
                }
                rec.poses += 1;
                rec.mark_posed(p.dataset_index);
                rec.note_fate(p.dataset_index, p.t_ns, TrackState::from_u32(p.state));
                let latency_ns = p.meta.publish_mono_ns - p.frame_publish_mono_ns;
                self.publish_to_pose.record_ns(latency_ns);
                rec.publish_to_pose.record_ns(latency_ns);
                self.publish_to_receive
                    .record_ns(p.frame_receive_mono_ns - p.frame_publish_mono_ns);
                self.tracker_total
                    .record_ns((p.stage_ms[shm_schema::stage::TOTAL] as f64 * 1e6).round() as i64);
                let source = PoseSource::from_u32(p.source).unwrap_or(PoseSource::None);
                if source == PoseSource::OrientationOnly {
                    let o = (p.t_ns, p.pose.q, p.state, p.meta.session_id);
                    rec.orientations.push(o);
                }
                if TrackState::from_u32(p.state) == Some(TrackState::Tracking) {
                    rec.tracked += 1;
                    rec.pose_sources[source as usize] += 1;
                    rec.metric_poses += u64::from(p.metric != 0);
                    rec.trajectory.push((p.t_ns, p.pose));
                    rec.trajectory_sessions.push(p.meta.session_id);
                    if p.has_server_pose != 0 {
                        let d = nalgebra::Vector3::from(p.pose.t)
                            - nalgebra::Vector3::from(p.server_pose.t);
                        rec.live_server_gap.record_m(d.norm());
                        rec.tracked_server += 1;
                        rec.server_trajectory
                            .push((p.t_ns, p.server_pose, p.server_map_id));
                    }
                }
            }
        }
        Ok(n)
    }
}

/// Writes a TUM trajectory of wire poses (`t tx ty tz qx qy qz qw`, t in seconds, nine
/// decimals, the quaternion as received) with [`datasets::trajectory::write_tum_file`].
pub fn write_tum(path: &std::path::Path, poses: &[(i64, shm_schema::Pose)]) -> std::io::Result<()> {
    use datasets::trajectory::{write_tum_file, TumDigits, TumRow};
    write_tum_file(
        path,
        Some("# t tx ty tz qx qy qz qw (camera-to-world, shoal)"),
        poses.iter().map(|(t_ns, p)| TumRow {
            t_ns: *t_ns,
            t: p.t,
            q: p.q,
        }),
        TumDigits::Fixed9,
    )
}
