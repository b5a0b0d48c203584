//! The tracker's counters and its crash-recovery state, as types: the one list of their
//! names (the status file's `counters` and `resume`), which the launcher reads back with the
//! same types, so a renamed counter does not compile instead of reading 0.
use serde::{Deserialize, Serialize};

/// Counters of the tracker, carried on over restarts (a successor resumes them).
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct TrackerCounters {
    /// Distinct frames handled (a pose published for each).
    pub frames_received: u64,
    /// Frames tracked (a valid pose when handled).
    pub frames_tracked: u64,
    /// Poses published (one per frame handled).
    pub poses_published: u64,
    /// Re-sends of frames already handled (acknowledged again).
    pub frames_duplicate: u64,
    /// Frames missing in the sequence (dropped upstream).
    pub frames_gap: u64,
    /// Frames missing at a restart (handled by the predecessor after its last status write,
    /// or published while no tracker ran).
    pub frames_gap_at_restart: u64,
    /// Frames whose rolling shutter was compensated with the gyro.
    pub frames_gyro_rs: u64,
    /// Frames seen while initialising, posed afterwards.
    pub frames_backfilled: u64,
    /// Frames published with a server-map pose.
    pub frames_server_pose: u64,
    /// VO sessions started after a tracking loss.
    pub vo_sessions_started: u64,
    /// Keyframe messages sent (first sends).
    pub keyframes_sent: u64,
    /// Keyframe re-sends.
    pub keyframes_resent: u64,
    /// Keyframes whose acknowledgement this tracker (or a predecessor) saw.
    pub keyframes_acked_seen: u64,
    /// Keyframes a killed predecessor had sent without seeing the acknowledgement.
    pub keyframes_unacked_at_crash: u64,
    /// Keyframes a killed predecessor had queued, never sent.
    pub keyframes_unsent_at_crash: u64,
    /// Keyframes written to the spool.
    pub keyframes_spooled: u64,
    /// Keyframes recovered from a killed predecessor's spool and sent.
    pub keyframes_recovered: u64,
    /// Keyframe messages queued with an IMU segment (issue 19; recovered ones included).
    pub keyframes_with_imu: u64,
    /// IMU records in those messages.
    pub keyframe_imu_samples: u64,
    /// Keyframe messages whose IMU segment was cut to `MAX_IMU_RECORDS` samples.
    pub keyframe_imu_cut: u64,
    /// Feedback messages taken.
    pub feedback_received: u64,
    /// Pose feedback used for server-map poses.
    pub pose_feedback_used: u64,
    /// Pose feedback that referred to no keyframe sent, or was invalid.
    pub pose_feedback_unusable: u64,
    /// Pose feedback on an older keyframe than the one already taken (lock-step's
    /// "finished" answers come after the feedback on newer keyframes): not used.
    pub pose_feedback_older: u64,
    /// IMU samples taken.
    pub imu_samples_received: u64,
    /// IMU samples published again by a restarted ingest (already taken).
    pub imu_samples_duplicate: u64,
    /// IMU samples missing in the sequence.
    pub imu_samples_dropped: u64,
    /// 1 when lock-step synchronisation is on.
    pub lockstep_sync: u64,
    /// Lock-step: frames that waited in vain for their gyro samples.
    pub lockstep_imu_timeouts: u64,
    /// Lock-step: waits for the server to finish a keyframe that timed out.
    pub lockstep_server_timeouts: u64,
    /// 1: local mapping in its own thread, 0: inline; none while no VO ran.
    pub local_mapping_thread: Option<u64>,
    /// Lock-step: waits for local mapping that timed out.
    pub local_mapping_sync_timeouts: u64,
    /// Visual-inertial mode: frames tracked with the IMU (its predicted pose as the search
    /// window and prior; metric and gravity-aligned).
    pub frames_vio: u64,
    /// Visual-inertial mode: frames posed by the IMU alone (a visual dropout).
    pub frames_inertial: u64,
    /// Visual-inertial mode: frames with only a gyro-propagated orientation (before the
    /// inertial initialisation, when vision gave no pose).
    pub frames_orientation_only: u64,
    /// IMU samples not used: non-finite or saturated values.
    pub imu_samples_refused: u64,
    /// Gaps in the IMU stream longer than the visual-inertial client bridges.
    pub imu_gaps: u64,
    /// Replays of the IMU samples since a resumed session's newest keyframe asked of the
    /// IMU ingest (lock-step; `shm_schema::FLAG_IMU_REPLAY`).
    pub imu_replays_asked: u64,
    /// The client's own world moves (the inertial initialisation, its refinements and the
    /// windows' corrections; anchor moves are counted in `vio.anchor`).
    pub world_moves: u64,
    /// Visual-inertial sessions resumed from a killed predecessor's spool (issue 17).
    pub vio_resumes: u64,
    /// Spooled keyframes a resumed session took back into its VO window (sent when they
    /// leave it, not at the start as `keyframes_recovered` are).
    pub keyframes_resumed: u64,
    /// Keyframes and points of the saved map the client localises in before its VO
    /// initialises (`tracker.prior_map`, `core/prior.rs`; this start's).
    pub prior_map_keyframes: u64,
    /// See `prior_map_keyframes`.
    pub prior_map_points: u64,
    /// Frames tried against the prior map.
    pub prior_map_frames_tried: u64,
    /// 1 when a frame relocalised in the prior map (the session continued there).
    pub prior_map_relocalised: u64,
    /// That frame's time (mid-row), ns.
    pub prior_map_relocalised_t_ns: u64,
    /// Prior keyframes that left the VO's window (never sent).
    pub prior_keyframes_dropped: u64,
}

/// The visual-inertial client's state, in the tracker's status (`details`) and the run
/// report (`clients[i].vio`).
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct VioReport {
    /// Where the inertial initialisation stands: `collecting`, `refused`, `initialised`,
    /// or `disabled` (it cannot run: see `reason`).
    pub status: String,
    /// Why it is not initialised (the last refusal, or what is missing), if so.
    pub reason: Option<String>,
    /// Attempts of the inertial initialisation (all sessions).
    pub attempts: u64,
    /// Refinements done after the initialisation (0-2).
    pub refinements: u64,
    /// Refinements computed but not applied: local mapping's window tracked the states
    /// (`slam_core::vio::VioParams::refinements_with_window`).
    pub refinements_skipped: u64,
    /// Frame time of the first initialisation, ns (IMU clock).
    pub initialised_t_ns: Option<i64>,
    /// Seconds from the client's first frame to the first initialisation.
    pub initialised_after_s: Option<f64>,
    /// Scale found by the first initialisation (metric / monocular).
    pub scale: Option<f64>,
    /// Its 1σ, % (of `log scale`).
    pub scale_sigma_percent: Option<f64>,
    /// Gyro bias of the last frame's state, rad/s (effective, body frame).
    pub gyro_bias: Option<[f64; 3]>,
    /// Accelerometer bias of the last frame's state, m/s².
    pub accel_bias: Option<[f64; 3]>,
    /// Visual-inertial windows of local mapping solved and applied (this tracker's life).
    pub vi_windows: u64,
    /// Keyframes with an inertial state for which no window could be built.
    pub vi_windows_skipped: u64,
    /// Windows whose solve failed (skipped, counted).
    pub vi_windows_failed: u64,
    /// Mean time of a window (build, solve, write back), ms.
    pub vi_window_ms_mean: Option<f64>,
    /// Longest window, ms.
    pub vi_window_ms_max: Option<f64>,
    /// The device rested before the visual-inertial initialisation: gyro bias and gravity.
    pub static_init: Option<StaticReport>,
    /// Sessions resumed from a killed predecessor's spool, all restarts (a resumed session
    /// is `initialised`: the initialisation fields above are its predecessor's).
    pub resumed: u64,
    /// The spooled keyframe the current session resumed from (its velocity and biases).
    pub resumed_from_keyframe: Option<u64>,
    /// Keyframes rebuilt into the resumed client map.
    pub resumed_keyframes: Option<u64>,
    /// Map points rebuilt into it.
    pub resumed_points: Option<u64>,
    /// Frames the resumed client handled until vision posed one (1: its first frame).
    pub resumed_after_frames: Option<u64>,
    /// Host time from the successor's spool read to that frame's pose, ms.
    pub resumed_after_ms: Option<f64>,
    /// Sensor time from the keyframe resumed from to that frame, s.
    pub resumed_gap_s: Option<f64>,
    /// Why the last restart did not resume its predecessor's session (it started anew).
    pub resume_refused: Option<String>,
    /// Anchors of the client's world to its metric server map (`None`: anchoring off).
    pub anchor: Option<AnchorReport>,
}

/// Anchors of a visual-inertial client's world to its server map
/// (`slam_core::vio::anchor`), this tracker's life.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct AnchorReport {
    /// Anchor moves applied.
    pub applied: u64,
    /// Asked for and dropped (another world move first, a new session, local mapping busy
    /// beyond the timeout); the next feedback asks again.
    pub dropped: u64,
    /// Applied moves into another server map (a merge).
    pub new_maps: u64,
    /// Largest translation of a move within one map (a drift correction), m.
    pub max_translation_m: f64,
    /// Largest yaw of a move within one map, degrees.
    pub max_yaw_deg: f64,
    /// Largest translation of a move into another map, m.
    pub max_new_map_m: f64,
    /// Server map of the last anchor.
    pub map_id: Option<u64>,
}

impl AnchorReport {
    /// Counts move `r`, applied.
    pub fn count(&mut self, r: &slam_core::vio::anchor::AnchorRequest) {
        let t = r.delta.translation.vector.norm();
        self.applied += 1;
        self.map_id = Some(r.map_id.raw());
        if r.new_map {
            self.new_maps += 1;
            self.max_new_map_m = self.max_new_map_m.max(t);
        } else {
            let yaw = slam_core::vio::anchor::yaw_of(&r.delta.rotation).abs();
            self.max_translation_m = self.max_translation_m.max(t);
            self.max_yaw_deg = self.max_yaw_deg.max(yaw.to_degrees());
        }
    }
}

/// The static initialisation ([`slam_core::imu::static_init`]).
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct StaticReport {
    /// End of the static window, ns (IMU clock).
    pub t_ns: i64,
    /// Window length, s.
    pub window_s: f64,
    /// Gyro bias (mean corrected rate), rad/s, body frame.
    pub gyro_bias: [f64; 3],
    /// "Up" (unit mean specific force) in the body frame.
    pub up_b: [f64; 3],
    /// "Up" in the world of the session's orientations then (when the frame had one).
    pub up_w: Option<[f64; 3]>,
    /// Norm of the mean specific force, m/s².
    pub accel_norm: f64,
    /// Largest per-axis spread over the window: gyro rad/s, accelerometer m/s².
    pub gyro_std: f64,
    /// See `gyro_std`.
    pub accel_std: f64,
}

/// Format version of [`TrackerResume`].
pub const RESUME_VERSION: u32 = 1;

/// What a restarted tracker needs of its killed predecessor besides the counters.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct TrackerResume {
    /// Sequence number of the last frame handled.
    pub last_frame_seq: Option<u64>,
    /// Keyframes sent and not acknowledged.
    pub keyframes_unacked: u64,
    /// Keyframes queued behind the in-flight limit.
    pub keyframes_queued: u64,
}
