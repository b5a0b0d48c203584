//! Message types. All are `#[repr(C)]`, `Copy`, fixed-size and [`ZeroCopySend`]; sizes and
//! alignments are checked at compile time at the bottom of this file.
use bytemuck::{Pod, Zeroable};
use iceoryx2::prelude::ZeroCopySend;

use crate::{MAGIC, SCHEMA_VERSION};

/// Flag: the last message of a stream (end of the dataset). Carries no data.
pub const FLAG_END_OF_STREAM: u32 = 1;
/// Flag: this message is a re-send of one published before (e.g. after a consumer restart).
pub const FLAG_RESEND: u32 = 1 << 1;
/// A [`TrackedPose`] of an earlier frame, found later (the frames seen while the VO was
/// initialising get their poses once the map exists); not a new frame, no latency stamps.
pub const FLAG_BACKFILL: u32 = 1 << 2;
/// `MsgMeta::flags` bit: a loop keyframe re-sent to a restarted loop closer (already
/// searched for loops); with [`FLAG_END_OF_STREAM`] and no keypoints, the end of the
/// resynchronisation.
pub const FLAG_RESYNC: u32 = 1 << 3;
/// `MsgMeta::flags` bit of a [`Feedback`] in lock-step replay: the server has finished this
/// keyframe (handled it, and the loop closer has searched it and any correction it found is
/// applied). The tracker waits for it, so the server's answers reach it at the same point
/// of the stream on every run.
pub const FLAG_HANDLED: u32 = 1 << 4;
/// A [`TrackedPose`] that moves the world of its VO session (no frame): every earlier pose
/// of that session (`meta.session_id`), as published, is to be re-expressed by the
/// similarity `x' = s R x + t` with `s = world_scale`, `R` the rotation in `pose.q` and `t`
/// in `pose.t`. A visual-inertial client sends it when its inertial initialisation (or a
/// refinement) moves its monocular map into the metric, gravity-aligned world (`t` zero),
/// and when it anchors its world to its metric server map (`s` = 1; `slam_core::vio::anchor`).
pub const FLAG_WORLD_MOVE: u32 = 1 << 5;
/// A [`LoopKeyframeHeader`] of a keyframe whose server map is metric and gravity-aligned (a
/// visual-inertial client's, `VI_NOTES.md` §4 "Server"): loops and merges between such
/// maps have 4 degrees of freedom (x, y, z, yaw). On a [`Feedback`]: its pose is of a
/// metric keyframe in such a map, and a visual-inertial client may anchor its world to it.
pub const FLAG_INERTIAL_MAP: u32 = 1 << 6;
/// A [`FrameAck`] that acknowledges no frame: a restarted tracker continuing its killed
/// predecessor's visual-inertial session asks its IMU ingest to publish again, in
/// lock-step, the samples from the one at or before `frame_t_ns` on (its session's newest
/// keyframe: the samples since then died with the predecessor, and the next keyframe's IMU
/// segment needs them). `frame_seq` is 0, so a consumer that reads it as an
/// acknowledgement learns nothing from it.
pub const FLAG_IMU_REPLAY: u32 = 1 << 7;

/// Common head of every message: identity, version and the publish stamp.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, ZeroCopySend)]
#[type_name("shoal::v4::MsgMeta")]
#[repr(C)]
pub struct MsgMeta {
    /// [`MAGIC`].
    pub magic: u32,
    /// [`SCHEMA_VERSION`] of the publisher.
    pub schema_version: u32,
    /// Client (camera/phone) index.
    pub client_id: u32,
    /// VO session of the client (a tracker restarts it after tracking failure or a restart).
    pub session_id: u32,
    /// Sequence number on this stream, from 0, without gaps unless data was dropped.
    pub seq: u64,
    /// Host `CLOCK_MONOTONIC` ns when the message was published.
    pub publish_mono_ns: i64,
    /// Bit set of `FLAG_*`.
    pub flags: u32,
    /// Reserved, zero.
    pub reserved: u32,
}

/// A received message whose head does not match this binary.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum MetaError {
    /// The magic number is wrong: the bytes are not a shoal message.
    BadMagic(u32),
    /// The message was written by a binary of another schema version.
    SchemaVersion {
        /// Version in the message.
        found: u32,
        /// Version of this binary.
        expected: u32,
    },
}

impl core::fmt::Display for MetaError {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        match self {
            MetaError::BadMagic(m) => write!(f, "not a shoal message (magic {m:#010x})"),
            MetaError::SchemaVersion { found, expected } => write!(
                f,
                "message of schema version {found}, this binary speaks version {expected}"
            ),
        }
    }
}

impl std::error::Error for MetaError {}

impl MsgMeta {
    /// A head for a new message of this schema version.
    pub fn new(client_id: u32, session_id: u32, seq: u64, publish_mono_ns: i64) -> Self {
        Self {
            magic: MAGIC,
            schema_version: SCHEMA_VERSION,
            client_id,
            session_id,
            seq,
            publish_mono_ns,
            flags: 0,
            reserved: 0,
        }
    }

    /// Checks magic and schema version.
    pub fn check(&self) -> Result<(), MetaError> {
        if self.magic != MAGIC {
            return Err(MetaError::BadMagic(self.magic));
        }
        if self.schema_version != SCHEMA_VERSION {
            return Err(MetaError::SchemaVersion {
                found: self.schema_version,
                expected: SCHEMA_VERSION,
            });
        }
        Ok(())
    }

    /// True when the end-of-stream flag is set.
    pub fn is_end_of_stream(&self) -> bool {
        self.flags & FLAG_END_OF_STREAM != 0
    }
}

/// A rigid pose `T_ab` (maps b-frame points into frame a): translation and a unit
/// quaternion in Hamilton convention, stored `[x, y, z, w]` (TUM order).
#[derive(Debug, Clone, Copy, PartialEq, ZeroCopySend)]
#[type_name("shoal::v4::Pose")]
#[repr(C)]
pub struct Pose {
    /// Translation `t_ab`.
    pub t: [f64; 3],
    /// Rotation `q_ab` as `[x, y, z, w]`.
    pub q: [f64; 4],
}

impl Default for Pose {
    fn default() -> Self {
        Self::IDENTITY
    }
}

impl Pose {
    /// The identity pose.
    pub const IDENTITY: Pose = Pose {
        t: [0.0; 3],
        q: [0.0, 0.0, 0.0, 1.0],
    };
}

/// Pixel formats of [`FrameHeader::pixel_format`].
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[repr(u32)]
pub enum PixelFormat {
    /// 8-bit gray, one byte per pixel.
    Gray8 = 1,
    /// No pixels: feature observations of a frame whose features were found upstream
    /// (e.g. AprilGrid corners), [`FeatureRecord::BYTES`] bytes each, as many as the
    /// payload holds; `width` and `height` are still the image's.
    Features = 2,
}

impl PixelFormat {
    /// The format of a header's `pixel_format`, if known.
    pub fn from_u32(v: u32) -> Option<Self> {
        match v {
            1 => Some(Self::Gray8),
            2 => Some(Self::Features),
            _ => None,
        }
    }
}

/// One feature observation of a [`PixelFormat::Features`] frame: its track and pixel
/// (column, row; pixel centres at integer coordinates), little-endian `u64, f32, f32`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct FeatureRecord {
    /// Track id: the same feature in every frame it is seen in.
    pub track: u64,
    /// Column, px.
    pub u: f32,
    /// Row, px.
    pub v: f32,
}

impl FeatureRecord {
    /// Bytes per record in the payload.
    pub const BYTES: usize = 16;

    /// Writes the record to `out` (`BYTES` long).
    pub fn write(&self, out: &mut [u8]) {
        out[..8].copy_from_slice(&self.track.to_le_bytes());
        out[8..12].copy_from_slice(&self.u.to_le_bytes());
        out[12..16].copy_from_slice(&self.v.to_le_bytes());
    }

    /// Reads the record at the start of `b` (`BYTES` long).
    pub fn read(b: &[u8]) -> Self {
        let word = |r: std::ops::Range<usize>| -> [u8; 4] { b[r].try_into().unwrap_or([0; 4]) };
        Self {
            track: u64::from_le_bytes(b[..8].try_into().unwrap_or([0; 8])),
            u: f32::from_le_bytes(word(8..12)),
            v: f32::from_le_bytes(word(12..16)),
        }
    }

    /// The records of a feature payload; `None` when its length is not a whole number of
    /// records.
    pub fn all(payload: &[u8]) -> Option<impl Iterator<Item = Self> + '_> {
        payload
            .len()
            .is_multiple_of(Self::BYTES)
            .then(|| payload.chunks_exact(Self::BYTES).map(Self::read))
    }
}

/// Camera intrinsics and radial-tangential distortion (seed eq. 2.57-2.60).
#[derive(Debug, Clone, Copy, Default, PartialEq, ZeroCopySend)]
#[type_name("shoal::v4::Intrinsics")]
#[repr(C)]
pub struct Intrinsics {
    /// `[fx, fy, cx, cy]` in pixels.
    pub pinhole: [f64; 4],
    /// `[k1, k2, p1, p2, k3]`.
    pub distortion: [f64; 5],
}

/// User header of a frame sample; the payload is the `[u8]` pixel slice
/// (`stride * height` bytes). Published by `camera_ingest`, read in place by the tracker.
#[derive(Debug, Clone, Copy, Default, PartialEq, ZeroCopySend)]
#[type_name("shoal::v4::FrameHeader")]
#[repr(C)]
pub struct FrameHeader {
    /// Identity, version, sequence number (= frame index in the stream), publish stamp.
    pub meta: MsgMeta,
    /// Image width in pixels.
    pub width: u32,
    /// Image height in pixels (rolling-shutter row count N).
    pub height: u32,
    /// Bytes per row.
    pub stride: u32,
    /// A [`PixelFormat`] as `u32`.
    pub pixel_format: u32,
    /// Index of the frame in its dataset.
    pub dataset_index: u64,
    /// Sensor time of the middle row, ns, after adding the camera-IMU offset t_d.
    pub t_mid_ns: i64,
    /// Rolling-shutter readout time t_r of the whole frame, ns (0 = global shutter).
    pub readout_ns: i64,
    /// Exposure time, ns (0 = unknown).
    pub exposure_ns: i64,
    /// Camera-IMU time offset t_d already applied to `t_mid_ns`, ns.
    pub time_offset_ns: i64,
    /// Camera intrinsics and distortion.
    pub intrinsics: Intrinsics,
    /// Camera pose in the body (IMU) frame, `T_BS` (x_B = R_BS x_S + t_BS), so that the
    /// tracker can rotate gyro rates into the camera for rolling-shutter compensation.
    pub t_bs: Pose,
}

impl FrameHeader {
    /// Capture time of pixel row `row` (seed eq. 2.61-2.63), see [`crate::time::row_time_ns`].
    pub fn row_time_ns(&self, row: u32) -> i64 {
        crate::time::row_time_ns(self.t_mid_ns, self.readout_ns, row, self.height)
    }

    /// Number of pixel bytes the slice must hold (a [`PixelFormat::Features`] frame: 0, its
    /// payload is as long as its records).
    pub fn payload_len(&self) -> usize {
        if self.pixel_format == PixelFormat::Features as u32 {
            return 0;
        }
        self.stride as usize * self.height as usize
    }
}

/// One IMU sample (body frame), published by `imu_ingest`.
#[derive(Debug, Clone, Copy, Default, PartialEq, ZeroCopySend)]
#[type_name("shoal::v4::ImuMsg")]
#[repr(C)]
pub struct ImuMsg {
    /// Identity, version, sequence number, publish stamp.
    pub meta: MsgMeta,
    /// Sensor time, ns (same clock as frame times).
    pub t_ns: i64,
    /// Angular rate, rad/s.
    pub gyro: [f64; 3],
    /// Specific force, m/s².
    pub accel: [f64; 3],
}

/// Sent by a frame consumer (the tracker) when it has taken a frame. In lock-step replay
/// the ingests wait for it before publishing the next frame (and the IMU samples up to it).
#[derive(Debug, Clone, Copy, Default, PartialEq, ZeroCopySend)]
#[type_name("shoal::v4::FrameAck")]
#[repr(C)]
pub struct FrameAck {
    /// Identity; `meta.seq` is the ack's own sequence number.
    pub meta: MsgMeta,
    /// Sequence number of the frame taken.
    pub frame_seq: u64,
    /// `t_mid_ns` of the frame taken.
    pub frame_t_ns: i64,
}

/// State of the tracker for one frame ([`TrackedPose::state`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[repr(u32)]
pub enum TrackState {
    /// No tracker algorithm ran (plumbing only) or the system is not initialised yet.
    NotInitialized = 0,
    /// Two-view initialisation in progress.
    Initializing = 1,
    /// Tracking: the pose is valid.
    Tracking = 2,
    /// Lost: relocalisation is being tried; the pose is not valid.
    Lost = 3,
}

impl TrackState {
    /// From the wire value; unknown values map to `None`.
    pub fn from_u32(v: u32) -> Option<Self> {
        match v {
            0 => Some(Self::NotInitialized),
            1 => Some(Self::Initializing),
            2 => Some(Self::Tracking),
            3 => Some(Self::Lost),
            _ => None,
        }
    }

    /// Its name in reports and files.
    pub fn name(self) -> &'static str {
        match self {
            Self::NotInitialized => "not_initialized",
            Self::Initializing => "initializing",
            Self::Tracking => "tracking",
            Self::Lost => "lost",
        }
    }
}

/// Indices into [`TrackedPose::stage_ms`].
pub mod stage {
    /// Image pyramid.
    pub const PYRAMID: usize = 0;
    /// FAST detection and distribution.
    pub const DETECT: usize = 1;
    /// Orientation and rBRIEF descriptors.
    pub const DESCRIBE: usize = 2;
    /// Descriptor matching.
    pub const MATCH: usize = 3;
    /// Pose optimisation.
    pub const POSE_OPT: usize = 4;
    /// Local-map tracking.
    pub const LOCAL_MAP: usize = 5;
    /// Keyframe decision and creation.
    pub const KEYFRAME: usize = 6;
    /// Whole tracking step inside the tracker.
    pub const TOTAL: usize = 7;
    /// Number of stages.
    pub const COUNT: usize = 8;
    /// Names, in index order (used in reports).
    pub const NAMES: [&str; COUNT] = [
        "pyramid",
        "detect",
        "describe",
        "match",
        "pose_opt",
        "local_map",
        "keyframe",
        "total",
    ];
}

/// Per-frame output of the tracker: pose, state, latency stamps and stage timings.
#[derive(Debug, Clone, Copy, Default, PartialEq, ZeroCopySend)]
#[type_name("shoal::v4::TrackedPose")]
#[repr(C)]
pub struct TrackedPose {
    /// Identity; `meta.seq` is the frame's sequence number, `meta.publish_mono_ns` the pose
    /// publish stamp.
    pub meta: MsgMeta,
    /// Frame time (`FrameHeader::t_mid_ns`).
    pub t_ns: i64,
    /// Index of the frame in its dataset.
    pub dataset_index: u64,
    /// Camera-to-map pose `T_cam_to_client_map`, valid when `state` is `Tracking`.
    pub pose: Pose,
    /// Camera pose in the server map (from feedback, seed eq. 3.1/3.4), valid when
    /// `has_server_pose != 0`.
    pub server_pose: Pose,
    /// Server map `server_pose` is in (the map id of the feedback it comes from); a map
    /// merged into another keeps its id here for the poses reported before the merge.
    pub server_map_id: u64,
    /// A [`TrackState`] as `u32`.
    pub state: u32,
    /// 1 when `server_pose` is valid.
    pub has_server_pose: u32,
    /// Number of map points matched in this frame.
    pub tracked_points: u32,
    /// 1 when this frame became a keyframe.
    pub is_keyframe: u32,
    /// `FrameHeader::meta.publish_mono_ns` of the frame (ingest publish).
    pub frame_publish_mono_ns: i64,
    /// When the tracker took the frame.
    pub frame_receive_mono_ns: i64,
    /// Per-stage times in ms, see [`stage`].
    pub stage_ms: [f32; stage::COUNT],
    /// Where the pose came from: a [`PoseSource`] as `u32`.
    pub source: u32,
    /// 1 when `pose` is in a metric, gravity-aligned world (z up; a visual-inertial client
    /// after its inertial initialisation).
    pub metric: u32,
    /// With [`FLAG_WORLD_MOVE`]: the scale `s` of the world move; else 0.
    pub world_scale: f64,
}

/// Where a [`TrackedPose`]'s pose came from ([`TrackedPose::source`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[repr(u32)]
pub enum PoseSource {
    /// No pose (`state` says why).
    None = 0,
    /// Vision alone (a monocular client, or a visual-inertial one before its inertial
    /// initialisation): up to scale.
    Visual = 1,
    /// Vision with the IMU (the IMU-predicted pose as prior): metric, gravity-aligned.
    VisualInertial = 2,
    /// The IMU alone, through a visual dropout (`state` is `Tracking`; drifts with time).
    Inertial = 3,
    /// Only the orientation (`pose.q`, gyro-propagated, `pose.t` zero; `state` is not
    /// `Tracking`): written to `orientation_c{i}.txt`, not to the trajectory.
    OrientationOnly = 4,
}

impl PoseSource {
    /// From the wire value; unknown values map to `None`.
    pub fn from_u32(v: u32) -> Option<Self> {
        match v {
            0 => Some(Self::None),
            1 => Some(Self::Visual),
            2 => Some(Self::VisualInertial),
            3 => Some(Self::Inertial),
            4 => Some(Self::OrientationOnly),
            _ => None,
        }
    }

    /// Its name in reports and files.
    pub fn name(self) -> &'static str {
        match self {
            Self::None => "none",
            Self::Visual => "visual",
            Self::VisualInertial => "visual_inertial",
            Self::Inertial => "inertial",
            Self::OrientationOnly => "orientation_only",
        }
    }
}

/// Header of a keyframe message (tracker → mapper, seed §3.3: pose in the client map +
/// keypoints + descriptors; for a visual-inertial client also velocity, biases and the IMU
/// segment since the previous keyframe, `VI_NOTES.md` §4 "Server", Fig. 5.4). The payload is
/// a slice of [`KeyframeRecord`]s: the first [`Self::n_keypoints`] are [`KeypointRecord`]s,
/// the next [`Self::n_imu`] are [`ImuRecord`]s (read them with [`Self::keypoints`] and
/// [`Self::imu_records`]); one message, so the segment is acknowledged, spooled, journaled
/// and re-sent with its keyframe.
#[derive(Debug, Clone, Copy, Default, PartialEq, ZeroCopySend)]
#[type_name("shoal::v4::KeyframeHeader")]
#[repr(C)]
pub struct KeyframeHeader {
    /// Identity (client, session); `meta.seq` counts keyframe messages of the client.
    pub meta: MsgMeta,
    /// Keyframe id, unique per client across sessions.
    pub keyframe_id: u64,
    /// Frame time of the keyframe, ns.
    pub t_ns: i64,
    /// Pose of the keyframe in the client map, `T_ck` (p_c = R_ck p_k + t_ck; absolute).
    pub pose_ck: Pose,
    /// Intrinsics of the camera.
    pub intrinsics: Intrinsics,
    /// Image width.
    pub width: u32,
    /// Image height.
    pub height: u32,
    /// Number of keypoint records in the payload.
    pub n_keypoints: u32,
    /// 1 when the keyframe comes from a visual-inertial client after its inertial
    /// initialisation: `pose_ck` is then metric and gravity-aligned, and the velocity and
    /// biases below are valid (a monocular server may ignore them).
    pub inertial: u32,
    /// Velocity of the IMU body in the client map, m/s (valid with `inertial`).
    pub velocity_w: [f64; 3],
    /// Gyro bias, rad/s (effective, body frame; valid with `inertial`).
    pub gyro_bias: [f64; 3],
    /// Accelerometer bias, m/s² (effective, body frame; valid with `inertial`).
    pub accel_bias: [f64; 3],
    /// IMU records in the payload after the keypoints (at most
    /// [`crate::topics::MAX_IMU_RECORDS`]): the samples over `[imu_t0_ns, imu_t1_ns]`, the
    /// first and the last linearly interpolated at exactly those borders (Fig. 5.4), so the
    /// segments of consecutive keyframes share their border sample. 0 for a monocular
    /// client, for a session's first keyframe, and for a segment the client could not
    /// complete (no sample yet beyond a border).
    pub n_imu: u32,
    /// 1 when the client is visual-inertial: `imu_t1_ns` and `imu_calib` are valid (also
    /// with `n_imu` = 0).
    pub has_imu: u32,
    /// Start of the IMU segment, ns on the IMU clock: the previous keyframe's
    /// `imu_t1_ns` (valid with `n_imu` > 0).
    pub imu_t0_ns: i64,
    /// This keyframe's time on the IMU clock, `t_ns + t_d`, ns (valid with `has_imu`).
    pub imu_t1_ns: i64,
    /// The client's fixed IMU calibration, to preintegrate the segment on the server
    /// (valid with `has_imu`).
    pub imu_calib: ImuCalib,
}

/// The fixed IMU calibration of a visual-inertial client (`VI_NOTES.md` §1.4, §4 "Server":
/// the server re-integrates the keyframes' segments with it).
#[derive(Debug, Clone, Copy, PartialEq, ZeroCopySend)]
#[type_name("shoal::v4::ImuCalib")]
#[repr(C)]
pub struct ImuCalib {
    /// Camera pose in the body (IMU) frame, `T_bc` (`p_b = R_bc p_c + t_bc`, EuRoC
    /// `T_BS`), metric.
    pub pose_bc: Pose,
    /// Camera-IMU time offset `t_d`: `t_imu = t_cam + t_d`, ns.
    pub t_d_ns: i64,
    /// Gyro white noise density σ_g, rad/s/√Hz.
    pub gyro_noise_density: f64,
    /// Accelerometer white noise density σ_a, m/s²/√Hz.
    pub accel_noise_density: f64,
    /// Gyro bias random walk σ_bg, rad/s²/√Hz.
    pub gyro_bias_rw: f64,
    /// Accelerometer bias random walk σ_ba, m/s³/√Hz.
    pub accel_bias_rw: f64,
    /// Accelerometer scale/misalignment `T_a`, column-major (identity: ideal).
    pub t_a: [f64; 9],
    /// Gyro scale/misalignment `T_g`, column-major (identity: ideal).
    pub t_g: [f64; 9],
    /// Gyro g-sensitivity `T_s`, rad/s per m/s², column-major (zero: ideal).
    pub t_s: [f64; 9],
}

impl Default for ImuCalib {
    fn default() -> Self {
        const I: [f64; 9] = [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0];
        Self {
            pose_bc: Pose::IDENTITY,
            t_d_ns: 0,
            gyro_noise_density: 0.0,
            accel_noise_density: 0.0,
            gyro_bias_rw: 0.0,
            accel_bias_rw: 0.0,
            t_a: I,
            t_g: I,
            t_s: [0.0; 9],
        }
    }
}

/// One IMU sample of a keyframe message's segment (64 bytes), body frame, raw (not
/// corrected by the intrinsics).
#[derive(Debug, Clone, Copy, Default, PartialEq, ZeroCopySend, Pod, Zeroable)]
#[type_name("shoal::v4::ImuRecord")]
#[repr(C)]
pub struct ImuRecord {
    /// Time, ns on the IMU clock.
    pub t_ns: i64,
    /// Angular rate `ω_m`, rad/s.
    pub gyro: [f64; 3],
    /// Specific force `a_m`, m/s².
    pub accel: [f64; 3],
    /// Reserved, zero.
    pub reserved: u64,
}

/// One 64-byte, 8-aligned slot of a keyframe message's payload: a [`KeypointRecord`] or an
/// [`ImuRecord`], as the header says ([`KeyframeHeader::keypoints`],
/// [`KeyframeHeader::imu_records`]); built with `From` either of them.
#[derive(Debug, Clone, Copy, Default, PartialEq, ZeroCopySend, Pod, Zeroable)]
#[type_name("shoal::v4::KeyframeRecord")]
#[repr(C)]
pub struct KeyframeRecord {
    /// The record's bytes, as words (for the alignment).
    pub words: [u64; 8],
}

impl From<KeypointRecord> for KeyframeRecord {
    fn from(r: KeypointRecord) -> Self {
        bytemuck::cast(r)
    }
}

impl From<ImuRecord> for KeyframeRecord {
    fn from(r: ImuRecord) -> Self {
        bytemuck::cast(r)
    }
}

/// A keyframe payload that does not hold what its header says.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum PayloadError {
    /// Fewer records than `n_keypoints`.
    Keypoints {
        /// `n_keypoints` of the header.
        n_keypoints: u32,
        /// Records in the payload.
        len: usize,
    },
    /// The records after the keypoints are not `n_imu`.
    Imu {
        /// `n_imu` of the header.
        n_imu: u32,
        /// Records after the keypoints.
        after_keypoints: usize,
    },
}

impl core::fmt::Display for PayloadError {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        match self {
            Self::Keypoints { n_keypoints, len } => write!(
                f,
                "header says {n_keypoints} keypoints, payload holds {len} records"
            ),
            Self::Imu {
                n_imu,
                after_keypoints,
            } => write!(
                f,
                "header says {n_imu} IMU records, payload holds {after_keypoints} after the keypoints"
            ),
        }
    }
}

impl std::error::Error for PayloadError {}

impl KeyframeHeader {
    /// The keypoint records of `payload`: its first `n_keypoints` records.
    pub fn keypoints<'a>(
        &self,
        payload: &'a [KeyframeRecord],
    ) -> Result<&'a [KeypointRecord], PayloadError> {
        let n = self.n_keypoints as usize;
        let recs = payload.get(..n).ok_or(PayloadError::Keypoints {
            n_keypoints: self.n_keypoints,
            len: payload.len(),
        })?;
        // Cannot fail: both record types are 64 bytes, 8-aligned (checked at compile time
        // at the bottom of this file).
        Ok(bytemuck::cast_slice(recs))
    }

    /// The IMU records of `payload`: the `n_imu` records after the keypoints, which must
    /// end the payload.
    pub fn imu_records<'a>(
        &self,
        payload: &'a [KeyframeRecord],
    ) -> Result<&'a [ImuRecord], PayloadError> {
        let rest = payload
            .get(self.n_keypoints as usize..)
            .ok_or(PayloadError::Keypoints {
                n_keypoints: self.n_keypoints,
                len: payload.len(),
            })?;
        if rest.len() != self.n_imu as usize {
            return Err(PayloadError::Imu {
                n_imu: self.n_imu,
                after_keypoints: rest.len(),
            });
        }
        // Cannot fail (as above).
        Ok(bytemuck::cast_slice(rest))
    }
}

/// `map_point_id` of a keypoint with no map point.
pub const NO_MAP_POINT: u64 = u64::MAX;

/// One keypoint of a keyframe message (64 bytes).
#[derive(Debug, Clone, Copy, PartialEq, ZeroCopySend, Pod, Zeroable)]
#[type_name("shoal::v4::KeypointRecord")]
#[repr(C)]
pub struct KeypointRecord {
    /// Pixel u (distorted image), level-0 coordinates.
    pub u: f32,
    /// Pixel v.
    pub v: f32,
    /// Orientation, degrees.
    pub angle: f32,
    /// FAST response.
    pub response: f32,
    /// Pyramid level.
    pub octave: u32,
    /// Reserved, zero.
    pub reserved: u32,
    /// Client map-point id, or [`NO_MAP_POINT`].
    pub map_point_id: u64,
    /// 256-bit rBRIEF descriptor.
    pub descriptor: [u8; 32],
}

impl Default for KeypointRecord {
    fn default() -> Self {
        Self {
            u: 0.0,
            v: 0.0,
            angle: 0.0,
            response: 0.0,
            octave: 0,
            reserved: 0,
            map_point_id: NO_MAP_POINT,
            descriptor: [0; 32],
        }
    }
}

/// Header of a frame's tracked features (tracker → viewers, `tracker.publish_features`);
/// the payload is a slice of [`TrackedFeature`]s.
#[derive(Debug, Clone, Copy, Default, PartialEq, ZeroCopySend)]
#[type_name("shoal::v4::TrackedFeaturesHeader")]
#[repr(C)]
pub struct TrackedFeaturesHeader {
    /// Identity; `meta.seq` is the frame's sequence number.
    pub meta: MsgMeta,
    /// Frame time (`FrameHeader::t_mid_ns`).
    pub t_ns: i64,
    /// Number of features in the payload.
    pub n_features: u32,
    /// Reserved, zero.
    pub reserved: u32,
}

/// A keypoint of a tracked frame matched to a map point (16 bytes).
#[derive(Debug, Clone, Copy, Default, PartialEq, ZeroCopySend)]
#[type_name("shoal::v4::TrackedFeature")]
#[repr(C)]
pub struct TrackedFeature {
    /// Client map-point id.
    pub map_point_id: u64,
    /// Pixel u (distorted image), level-0 coordinates.
    pub u: f32,
    /// Pixel v.
    pub v: f32,
}

/// Mapper → tracker: acknowledgement and pose feedback (seed §3.4.1).
#[derive(Debug, Clone, Copy, Default, PartialEq, ZeroCopySend)]
#[type_name("shoal::v4::Feedback")]
#[repr(C)]
pub struct Feedback {
    /// Identity (client the feedback is for).
    pub meta: MsgMeta,
    /// Id of the last keyframe the mapper applied (journaled) for this client.
    pub acked_keyframe_id: u64,
    /// Session of that keyframe.
    pub acked_session_id: u32,
    /// 1 when `server_pose` / `scale_ratio` are valid.
    pub has_pose: u32,
    /// Server-map pose of the client's last keyframe, `T_sk`.
    pub server_pose: Pose,
    /// Scale ratio lambda (server / client, eq. 3.2-3.3).
    pub scale_ratio: f64,
    /// Id of the server map the client's keyframes are in.
    pub server_map_id: u64,
}

/// Most covisible neighbours listed in a [`LoopKeyframeHeader`].
pub const MAX_LOOP_COVISIBLE: usize = 32;

/// Header of a loop keyframe message (mapper → loop closer): a keyframe the mapper kept in
/// a server map, with what place recognition and loop geometry need (seed §3.4.1-3.4.2);
/// the payload is a slice of [`LoopKeypointRecord`]s.
#[derive(Debug, Clone, Copy, PartialEq, ZeroCopySend)]
#[type_name("shoal::v4::LoopKeyframeHeader")]
#[repr(C)]
pub struct LoopKeyframeHeader {
    /// Identity (client, session of the keyframe; `meta.seq` counts loop keyframe messages
    /// of the mapper).
    pub meta: MsgMeta,
    /// Server map the keyframe is in.
    pub map_id: u64,
    /// Server keyframe id (unique across clients).
    pub kf_id: u64,
    /// Client keyframe id.
    pub client_kf_id: u64,
    /// Frame time, ns.
    pub t_ns: i64,
    /// Server pose `T_sk` (camera → server map) when it was kept.
    pub pose_sk: Pose,
    /// Intrinsics of the camera.
    pub intrinsics: Intrinsics,
    /// Image width.
    pub width: u32,
    /// Image height.
    pub height: u32,
    /// Number of keypoint records in the payload.
    pub n_keypoints: u32,
    /// Valid entries of `covisible_ids` / `covisible_weights`.
    pub n_covisible: u32,
    /// Covisible server keyframes, best first.
    pub covisible_ids: [u64; MAX_LOOP_COVISIBLE],
    /// Their weights (shared points).
    pub covisible_weights: [u32; MAX_LOOP_COVISIBLE],
}

impl Default for LoopKeyframeHeader {
    fn default() -> Self {
        Self {
            meta: MsgMeta::default(),
            map_id: 0,
            kf_id: 0,
            client_kf_id: 0,
            t_ns: 0,
            pose_sk: Pose::IDENTITY,
            intrinsics: Intrinsics::default(),
            width: 0,
            height: 0,
            n_keypoints: 0,
            n_covisible: 0,
            covisible_ids: [0; MAX_LOOP_COVISIBLE],
            covisible_weights: [0; MAX_LOOP_COVISIBLE],
        }
    }
}

/// One keypoint of a loop keyframe message (88 bytes).
#[derive(Debug, Clone, Copy, PartialEq, ZeroCopySend)]
#[type_name("shoal::v4::LoopKeypointRecord")]
#[repr(C)]
pub struct LoopKeypointRecord {
    /// Pixel u (distorted image), level-0 coordinates.
    pub u: f32,
    /// Pixel v.
    pub v: f32,
    /// Orientation, degrees.
    pub angle: f32,
    /// FAST response.
    pub response: f32,
    /// Pyramid level.
    pub octave: u32,
    /// 1 when the keypoint has a server map point (`point_id`, `p_k` valid).
    pub has_point: u32,
    /// Server map-point id.
    pub point_id: u64,
    /// The point in the keyframe's camera frame.
    pub p_k: [f64; 3],
    /// 256-bit rBRIEF descriptor.
    pub descriptor: [u8; 32],
}

impl Default for LoopKeypointRecord {
    fn default() -> Self {
        Self {
            u: 0.0,
            v: 0.0,
            angle: 0.0,
            response: 0.0,
            octave: 0,
            has_point: 0,
            point_id: 0,
            p_k: [0.0; 3],
            descriptor: [0; 32],
        }
    }
}

/// Loop closer → mapper: send the keyframes of all server maps, from index `next` of the
/// mapper's snapshot (`next = 0` takes a new snapshot), at most `max` of them (DESIGN.md: a
/// restarted loop closer rebuilds its keyframe database from the mapper).
#[derive(Debug, Clone, Copy, Default, PartialEq, ZeroCopySend)]
#[type_name("shoal::v4::ResyncRequest")]
#[repr(C)]
pub struct ResyncRequest {
    /// Identity (`meta.seq` counts requests).
    pub meta: MsgMeta,
    /// First snapshot index wanted.
    pub next: u64,
    /// Most keyframes to send in this batch.
    pub max: u32,
    /// Reserved, zero.
    pub reserved: u32,
}

/// [`CorrectionHeader::kind`]: merge map `from_map` into `into_map` by `sim3`.
pub const CORRECTION_MERGE: u32 = 1;
/// [`CorrectionHeader::kind`]: per-keyframe pose-graph corrections of map `into_map`.
pub const CORRECTION_POSE_GRAPH: u32 = 2;
/// [`CorrectionHeader::kind`] in lock-step replay: no correction, the loop closer has
/// finished the loop keyframe `query_kf` (`meta.seq`: that keyframe message's `meta.seq`);
/// sent after any correction it found, on the same topic, so the mapper knows when the
/// keyframe is settled. No records.
pub const CORRECTION_DONE: u32 = 3;
/// [`CorrectionRecord::kind`]: keyframe `a` moves by the similarity `delta`.
pub const RECORD_KEYFRAME_DELTA: u32 = 1;
/// [`CorrectionRecord::kind`]: point `a` is the same 3-D point as `b` (fuse `a` into `b`).
pub const RECORD_POINT_PAIR: u32 = 2;

/// Header of a correction (loop closer → mapper, seed §3.4.2-3.4.3); the payload is a slice
/// of [`CorrectionRecord`]s. The loop closer computes, the mapper (owner of the maps)
/// applies.
#[derive(Debug, Clone, Copy, PartialEq, ZeroCopySend)]
#[type_name("shoal::v4::CorrectionHeader")]
#[repr(C)]
pub struct CorrectionHeader {
    /// Identity (`client_id` of the query keyframe; `meta.seq` counts corrections).
    pub meta: MsgMeta,
    /// Correction id (unique per loop closer run).
    pub correction_id: u64,
    /// [`CORRECTION_MERGE`] or [`CORRECTION_POSE_GRAPH`].
    pub kind: u32,
    /// Number of records in the payload.
    pub n_records: u32,
    /// Server keyframe id of the query (current) keyframe of the loop.
    pub query_kf: u64,
    /// Server keyframe id of the matched keyframe.
    pub matched_kf: u64,
    /// Merge: the map that is moved. Pose graph: the corrected map.
    pub from_map: u64,
    /// Merge: the map it joins. Pose graph: the corrected map.
    pub into_map: u64,
    /// Merge: `S_into_from` (rotation and translation; `x_into = s R x_from + t`). Pose
    /// graph: the correction for keyframes without a record (newer than the loop closer
    /// knew).
    pub sim3: Pose,
    /// Scale of `sim3`.
    pub scale: f64,
    /// Inlier matches of the loop.
    pub inliers: u32,
    /// Reserved, zero.
    pub reserved: u32,
}

impl Default for CorrectionHeader {
    fn default() -> Self {
        Self {
            meta: MsgMeta::default(),
            correction_id: 0,
            kind: 0,
            n_records: 0,
            query_kf: 0,
            matched_kf: 0,
            from_map: 0,
            into_map: 0,
            sim3: Pose::IDENTITY,
            scale: 1.0,
            inliers: 0,
            reserved: 0,
        }
    }
}

/// One record of a correction (88 bytes).
#[derive(Debug, Clone, Copy, PartialEq, ZeroCopySend)]
#[type_name("shoal::v4::CorrectionRecord")]
#[repr(C)]
pub struct CorrectionRecord {
    /// [`RECORD_KEYFRAME_DELTA`] or [`RECORD_POINT_PAIR`].
    pub kind: u32,
    /// Reserved, zero.
    pub reserved: u32,
    /// Keyframe id, or the point to fuse.
    pub a: u64,
    /// The point to fuse into (point pairs), else 0.
    pub b: u64,
    /// Keyframe deltas: `Δ_k` (rotation, translation), map → map.
    pub delta: Pose,
    /// Scale of `delta`.
    pub scale: f64,
}

impl Default for CorrectionRecord {
    fn default() -> Self {
        Self {
            kind: 0,
            reserved: 0,
            a: 0,
            b: 0,
            delta: Pose::IDENTITY,
            scale: 1.0,
        }
    }
}

const _: () = {
    use core::mem::{align_of, size_of};
    assert!(size_of::<MsgMeta>() == 40 && align_of::<MsgMeta>() == 8);
    assert!(size_of::<Pose>() == 56 && align_of::<Pose>() == 8);
    assert!(size_of::<Intrinsics>() == 72);
    assert!(size_of::<FrameHeader>() == 40 + 24 + 32 + 72 + 56);
    assert!(size_of::<ImuMsg>() == 40 + 8 + 48);
    assert!(size_of::<FrameAck>() == 56);
    assert!(size_of::<TrackedPose>() == 40 + 16 + 112 + 8 + 16 + 16 + 32 + 16);
    assert!(size_of::<ImuCalib>() == 56 + 8 + 32 + 3 * 72);
    assert!(size_of::<KeyframeHeader>() == 40 + 16 + 56 + 72 + 16 + 72 + 8 + 16 + 312);
    assert!(size_of::<KeypointRecord>() == 64 && align_of::<KeypointRecord>() == 8);
    assert!(size_of::<ImuRecord>() == 64 && align_of::<ImuRecord>() == 8);
    assert!(size_of::<KeyframeRecord>() == 64 && align_of::<KeyframeRecord>() == 8);
    assert!(size_of::<Feedback>() == 40 + 16 + 56 + 16);
    assert!(size_of::<LoopKeypointRecord>() == 88 && align_of::<LoopKeypointRecord>() == 8);
    assert!(size_of::<LoopKeyframeHeader>() == 40 + 32 + 56 + 72 + 16 + 8 * 32 + 4 * 32);
    assert!(size_of::<CorrectionHeader>() == 40 + 16 + 32 + 56 + 16);
    assert!(size_of::<CorrectionRecord>() == 24 + 56 + 8);
    assert!(size_of::<ResyncRequest>() == 40 + 16);
};

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn meta_check_rejects_other_versions() {
        let mut m = MsgMeta::new(0, 0, 5, 1);
        assert_eq!(m.check(), Ok(()));
        m.schema_version = SCHEMA_VERSION + 1;
        let err = m.check().unwrap_err();
        assert!(err.to_string().contains("schema version"), "{err}");
        m.magic = 0;
        assert!(matches!(m.check(), Err(MetaError::BadMagic(0))));
    }

    /// Feature records survive the payload bytes; a payload cut inside a record is refused.
    #[test]
    fn feature_records_round_trip() {
        let recs = [
            FeatureRecord {
                track: 7,
                u: 1.25,
                v: 479.5,
            },
            FeatureRecord {
                track: u64::MAX,
                u: -0.5,
                v: 0.0,
            },
        ];
        let mut buf = vec![0u8; 2 * FeatureRecord::BYTES];
        for (r, b) in recs.iter().zip(buf.chunks_exact_mut(FeatureRecord::BYTES)) {
            r.write(b);
        }
        let back: Vec<_> = FeatureRecord::all(&buf).expect("whole").collect();
        assert_eq!(back, recs);
        assert!(FeatureRecord::all(&buf[..20]).is_none());
        assert_eq!(PixelFormat::from_u32(2), Some(PixelFormat::Features));
        assert_eq!(PixelFormat::from_u32(9), None);
    }

    /// The type name of `T` as iceoryx2 matches it between processes.
    fn type_name<T: ZeroCopySend>() -> &'static str {
        // SAFETY: only reads the name; the layouts are this crate's own.
        unsafe { <T as ZeroCopySend>::type_name() }
    }

    /// Every `#[type_name("shoal::vN::Type")]` in this file names the struct it is on, under
    /// the current [`SCHEMA_VERSION`] (a bump of the version must rename them all, so that
    /// iceoryx2 refuses to connect binaries of different layouts), and every message type
    /// derives its name from one.
    #[test]
    fn type_names_carry_the_schema_version() {
        let prefix = format!("shoal::v{SCHEMA_VERSION}::");
        let src = include_str!("messages.rs");
        let derives = src
            .lines()
            .filter(|l| l.trim_start().starts_with("#[derive(") && l.contains("ZeroCopySend"))
            .count();
        let mut named = Vec::new();
        let mut lines = src.lines();
        while let Some(l) = lines.next() {
            let Some(rest) = l.trim().strip_prefix("#[type_name(\"") else {
                continue;
            };
            let name = rest.strip_suffix("\")]").expect("one string literal");
            let ty = lines
                .by_ref()
                .find_map(|l| l.trim().strip_prefix("pub struct "))
                .and_then(|r| r.split([' ', '{']).next())
                .expect("a struct after the type_name");
            assert_eq!(name, format!("{prefix}{ty}"), "type_name of {ty}");
            named.push(name);
        }
        assert_eq!(
            named.len(),
            derives,
            "a ZeroCopySend type without a type_name"
        );
        let names = [
            type_name::<MsgMeta>(),
            type_name::<Pose>(),
            type_name::<Intrinsics>(),
            type_name::<FrameHeader>(),
            type_name::<ImuMsg>(),
            type_name::<FrameAck>(),
            type_name::<TrackedPose>(),
            type_name::<KeyframeHeader>(),
            type_name::<KeypointRecord>(),
            type_name::<ImuCalib>(),
            type_name::<ImuRecord>(),
            type_name::<KeyframeRecord>(),
            type_name::<Feedback>(),
            type_name::<TrackedFeaturesHeader>(),
            type_name::<TrackedFeature>(),
            type_name::<LoopKeyframeHeader>(),
            type_name::<LoopKeypointRecord>(),
            type_name::<ResyncRequest>(),
            type_name::<CorrectionHeader>(),
            type_name::<CorrectionRecord>(),
        ];
        assert_eq!(names.len(), named.len(), "a message type missing here");
        for n in names {
            assert!(n.starts_with(&prefix), "{n} is not under {prefix}");
            assert!(named.contains(&n), "{n}");
        }
    }

    /// A payload of keypoints then IMU records reads back as both, in place; a header
    /// promising more records than the payload holds is refused for the part it concerns.
    #[test]
    fn keyframe_payload_holds_keypoints_then_imu_records() {
        let kp = KeypointRecord {
            u: 3.5,
            map_point_id: 9,
            descriptor: [7; 32],
            ..KeypointRecord::default()
        };
        let imu = ImuRecord {
            t_ns: -5,
            gyro: [0.1, 0.2, 0.3],
            accel: [1.0, 2.0, 9.81],
            reserved: 0,
        };
        let payload: Vec<KeyframeRecord> = vec![kp.into(), kp.into(), imu.into()];
        let mut h = KeyframeHeader {
            n_keypoints: 2,
            n_imu: 1,
            ..KeyframeHeader::default()
        };
        assert_eq!(h.keypoints(&payload), Ok(&[kp, kp][..]));
        assert_eq!(h.imu_records(&payload), Ok(&[imu][..]));
        h.n_imu = 2;
        assert_eq!(h.keypoints(&payload), Ok(&[kp, kp][..]));
        let e = h.imu_records(&payload).unwrap_err();
        assert!(e.to_string().contains("2 IMU records"), "{e}");
        h.n_keypoints = 4;
        assert!(matches!(
            h.keypoints(&payload),
            Err(PayloadError::Keypoints { len: 3, .. })
        ));
        assert!(h.imu_records(&payload).is_err());
        h.n_keypoints = 0;
        h.n_imu = 0;
        assert!(h.imu_records(&payload).is_err(), "records nobody declared");
    }

    #[test]
    fn track_state_round_trip() {
        for s in [
            TrackState::NotInitialized,
            TrackState::Initializing,
            TrackState::Tracking,
        ] {
            assert_eq!(TrackState::from_u32(s as u32), Some(s));
        }
        assert_eq!(TrackState::from_u32(99), None);
    }
}
