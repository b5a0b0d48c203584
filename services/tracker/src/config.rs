//! The tracker's configuration ([`TrackerConfig`], the `[tracker]` section of
//! `shoal config --print`) and the command-line flags that override it in a manual run
//! ([`TrackerFlags`]; also what `shoal run --tracker-arg`, deprecated, is mapped through).
use std::path::PathBuf;

use serde::{Deserialize, Serialize};
use slam_core::rolling_shutter::ReadoutDirection;

/// Where the client VO's local mapping runs.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum LocalMapping {
    /// Its own thread (seed §3.3, [`crate::mapping_thread`]).
    Thread,
    /// In the tracking thread, after each new keyframe (slower per keyframe; a lock-step
    /// replay takes the same decisions either way).
    Inline,
}

/// What a client runs (`shoal run --mode`; `tracker.mode`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize, clap::ValueEnum)]
#[serde(rename_all = "lowercase")]
pub enum ClientMode {
    /// `vio` when the client's dataset has an IMU stream and camera-IMU extrinsics, else
    /// `mono` (the launcher decides per client and writes the decision into each tracker's
    /// configuration; a tracker started by hand with `auto` runs `mono`).
    #[default]
    Auto,
    /// Monocular visual odometry (seed ch. 3): up to scale; the gyro only de-rotates
    /// rolling-shutter rows.
    Mono,
    /// Visual-inertial (seed ch. 5): inertial initialisation, IMU-predicted tracking,
    /// metric and gravity-aligned poses.
    Vio,
    /// Online camera-IMU calibration (seed ch. 4): the rolling-shutter MSCKF of
    /// `slam_core::calib` estimates the camera model, t_d, t_r, the lever arm and the IMU's
    /// errors, and poses every frame; no keyframes go to the server.
    Calib,
}

impl ClientMode {
    /// Its name in reports.
    pub fn name(self) -> &'static str {
        match self {
            Self::Auto => "auto",
            Self::Mono => "mono",
            Self::Vio => "vio",
            Self::Calib => "calib",
        }
    }
}

/// The IMU calibration a visual-inertial client uses (`[tracker.imu]`): the launcher
/// writes it per client from the dataset's `imu0/sensor.yaml` (EuRoC keys; the IMU
/// intrinsics of seed eq. 2.53-2.56 when given). Noise densities are continuous-time, as in
/// Kalibr's `imu.yaml`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct ImuCalibConfig {
    /// Gyro white noise density, rad/s/√Hz.
    pub gyroscope_noise_density: f64,
    /// Accelerometer white noise density, m/s²/√Hz.
    pub accelerometer_noise_density: f64,
    /// Gyro bias random walk, rad/s²/√Hz.
    pub gyroscope_random_walk: f64,
    /// Accelerometer bias random walk, m/s³/√Hz.
    pub accelerometer_random_walk: f64,
    /// Gyro scale and misalignment `T_g`, row-major (identity when not given).
    pub t_g: [f64; 9],
    /// Gyro g-sensitivity `T_s`, rad/s per m/s², row-major (zero when not given).
    pub t_s: [f64; 9],
    /// Accelerometer scale and misalignment `T_a`, row-major (identity when not given).
    pub t_a: [f64; 9],
    /// The camera-IMU extrinsics (the frames' `T_BS`) were given by the dataset; without
    /// them the visual-inertial client does not initialise, and says so.
    pub extrinsics_given: bool,
    /// Where these values come from (a file, or `default`: EuRoC's ADIS16448 figures).
    pub source: String,
}

const IDENTITY3: [f64; 9] = [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0];

impl Default for ImuCalibConfig {
    /// EuRoC's ADIS16448 noise, ideal intrinsics, extrinsics not given.
    fn default() -> Self {
        Self {
            gyroscope_noise_density: 1.6968e-4,
            accelerometer_noise_density: 2.0e-3,
            gyroscope_random_walk: 1.9393e-5,
            accelerometer_random_walk: 3.0e-3,
            t_g: IDENTITY3,
            t_s: [0.0; 9],
            t_a: IDENTITY3,
            extrinsics_given: false,
            source: "default".into(),
        }
    }
}

impl ImuCalibConfig {
    /// Checks the values (finite, densities ≥ 0, `T_g` and `T_a` invertible) and builds the
    /// preintegration settings; the error names the key.
    pub fn preintegration(&self) -> Result<slam_core::imu::PreintegrationParams, String> {
        let (noise, intrinsics) = self.noise_and_intrinsics()?;
        slam_core::imu::PreintegrationParams::new(&noise, &intrinsics)
            .map_err(|e| format!("tracker.imu: {e}"))
    }

    /// The noise densities and the IMU intrinsics, checked (finite, densities ≥ 0); the
    /// error names the key.
    pub fn noise_and_intrinsics(
        &self,
    ) -> Result<(slam_core::imu::ImuNoise, slam_core::imu::ImuIntrinsics), String> {
        use nalgebra::Matrix3;
        let densities = [
            ("gyroscope_noise_density", self.gyroscope_noise_density),
            (
                "accelerometer_noise_density",
                self.accelerometer_noise_density,
            ),
            ("gyroscope_random_walk", self.gyroscope_random_walk),
            ("accelerometer_random_walk", self.accelerometer_random_walk),
        ];
        if let Some((k, v)) = densities
            .iter()
            .find(|(_, v)| !(v.is_finite() && *v >= 0.0))
        {
            return Err(format!("tracker.imu.{k} = {v}: must be finite and >= 0"));
        }
        let mat = |m: &[f64; 9], key: &str| {
            if m.iter().all(|v| v.is_finite()) {
                Ok(Matrix3::from_row_slice(m))
            } else {
                Err(format!("tracker.imu.{key} has a non-finite element"))
            }
        };
        let noise = slam_core::imu::ImuNoise {
            gyro_noise_density: self.gyroscope_noise_density,
            accel_noise_density: self.accelerometer_noise_density,
            gyro_bias_rw: self.gyroscope_random_walk,
            accel_bias_rw: self.accelerometer_random_walk,
        };
        let intrinsics = slam_core::imu::ImuIntrinsics {
            t_g: mat(&self.t_g, "t_g")?,
            t_s: mat(&self.t_s, "t_s")?,
            t_a: mat(&self.t_a, "t_a")?,
        };
        Ok((noise, intrinsics))
    }
}

/// When the calibration filter starts from its initialisation (`tracker.calib.init`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum CalibInit {
    /// When the camera-IMU extrinsics are not given (a new device).
    Auto,
    /// Always (e.g. stamps whose offset to the IMU is unknown, up to ±200 ms).
    Always,
    /// Never: gravity from the mean specific force, the given `R_cb` and `t_d`.
    Never,
}

/// The calibration mode's settings (`[tracker.calib]`): the prior 1σ of the starting
/// calibration (`VI_NOTES.md` §3 "Priors") and the filter's pixel noise.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct CalibModeConfig {
    /// Pixel noise σ per coordinate, px.
    pub pixel_sigma: f64,
    /// Smallest parallax of a used feature (largest baseline over depth, rad; 0.02 by
    /// default). Features below it are not used: their depth absorbs model errors at a poor
    /// start. A clip with almost no translation (a hand-held phone) needs a smaller one.
    pub min_parallax_rad: f64,
    /// Use the features below `min_parallax_rad`, fitted with a prior on their inverse depth
    /// (within what low parallax allows over their baseline). Their depth is still
    /// projected out of the rows, so they constrain rotation, the camera and the timing,
    /// not the lever arm or scale: a clip without translation (a hand-held phone) needs
    /// them.
    pub low_parallax: bool,
    /// Largest reprojection RMS of a triangulated feature of the image front end, px: ORB
    /// tracks can hold mismatches, which a loose bound lets in (10 px put p_cb 10 mm off on
    /// the rendered `calib` scene in 20 s, 4 px 3 mm).
    pub max_triangulation_rms_px: f64,
    /// The same for given feature tracks (AprilGrid detections: no mismatches), px. A tight
    /// bound locks out a filter started from a poor camera: every feature fails and nothing
    /// corrects the camera (EuRoC AprilGrid from the start at 4 px).
    pub max_triangulation_rms_given_px: f64,
    /// `fx, fy`, px.
    pub focal_sigma_px: f64,
    /// `cx, cy`, px.
    pub principal_point_sigma_px: f64,
    /// `k1, k2`.
    pub radial_sigma: f64,
    /// `p1, p2`.
    pub tangential_sigma: f64,
    /// `t_d`, ms.
    pub t_d_sigma_ms: f64,
    /// `t_r`, ms.
    pub t_r_sigma_ms: f64,
    /// Each coordinate of the lever arm `p_cb`, m.
    pub p_cb_sigma_m: f64,
    /// Each element of `T_g` and `T_a`.
    pub t_ga_sigma: f64,
    /// Each element of `T_s`, rad/s per m/s².
    pub t_s_sigma: f64,
    /// When the filter starts from `slam_core::calib::init` (t_d searched over ±200 ms,
    /// `R_cb` estimated from gyro vs visual rotations when not given, gravity and velocity
    /// from the motion) over the first `init_seconds`: `"auto"` (when the dataset gives no
    /// camera-IMU extrinsics), `"always"` or `"never"` (gravity from the mean specific force).
    pub init: CalibInit,
    /// Seconds of frames the initialisation uses.
    pub init_seconds: f64,
    /// Seconds of IMU before the first updated frame from which the filter takes its
    /// starting roll and pitch (the mean specific force, gyro-rotated): 2 s by default; a
    /// clip whose IMU starts with its frames (the 0.8 s phone clip) needs a shorter one.
    pub start_seconds: f64,
    /// Per-frame estimates and σ written here as CSV (the launcher sets
    /// `OUT/calib_c{c}.csv`); `{c}` is the client index.
    pub log: Option<PathBuf>,
}

impl Default for CalibModeConfig {
    fn default() -> Self {
        let p = slam_core::calib::CalibPriors::default();
        Self {
            pixel_sigma: 1.0,
            min_parallax_rad: slam_core::calib::CalibParams::default().min_parallax,
            low_parallax: false,
            max_triangulation_rms_px: 4.0,
            max_triangulation_rms_given_px: slam_core::calib::CalibParams::default()
                .max_triangulation_rms,
            focal_sigma_px: p.focal,
            principal_point_sigma_px: p.principal_point,
            radial_sigma: p.radial,
            tangential_sigma: p.tangential,
            t_d_sigma_ms: p.t_d * 1e3,
            t_r_sigma_ms: p.t_r * 1e3,
            p_cb_sigma_m: p.p_cb,
            t_ga_sigma: p.t_g,
            t_s_sigma: p.t_s,
            init: CalibInit::Auto,
            init_seconds: 8.0,
            start_seconds: 2.0,
            log: None,
        }
    }
}

impl CalibModeConfig {
    /// The filter's priors: these σ over the defaults (attitude, velocity, biases).
    pub fn priors(&self) -> slam_core::calib::CalibPriors {
        slam_core::calib::CalibPriors {
            focal: self.focal_sigma_px,
            principal_point: self.principal_point_sigma_px,
            radial: self.radial_sigma,
            tangential: self.tangential_sigma,
            t_d: self.t_d_sigma_ms * 1e-3,
            t_r: self.t_r_sigma_ms * 1e-3,
            p_cb: self.p_cb_sigma_m,
            t_g: self.t_ga_sigma,
            t_a: self.t_ga_sigma,
            t_s: self.t_s_sigma,
            ..slam_core::calib::CalibPriors::default()
        }
    }

    /// Checks that every σ is positive and finite; the error names the key.
    pub fn validate(&self) -> Result<(), String> {
        let keys = [
            ("pixel_sigma", self.pixel_sigma),
            ("min_parallax_rad", self.min_parallax_rad),
            ("max_triangulation_rms_px", self.max_triangulation_rms_px),
            (
                "max_triangulation_rms_given_px",
                self.max_triangulation_rms_given_px,
            ),
            ("focal_sigma_px", self.focal_sigma_px),
            ("principal_point_sigma_px", self.principal_point_sigma_px),
            ("radial_sigma", self.radial_sigma),
            ("tangential_sigma", self.tangential_sigma),
            ("t_d_sigma_ms", self.t_d_sigma_ms),
            ("t_r_sigma_ms", self.t_r_sigma_ms),
            ("p_cb_sigma_m", self.p_cb_sigma_m),
            ("t_ga_sigma", self.t_ga_sigma),
            ("t_s_sigma", self.t_s_sigma),
            ("init_seconds", self.init_seconds),
            ("start_seconds", self.start_seconds),
        ];
        match keys.iter().find(|(_, v)| !(v.is_finite() && *v > 0.0)) {
            Some((k, v)) => Err(format!("tracker.calib.{k} = {v}: must be finite and > 0")),
            None => Ok(()),
        }
    }
}

/// Everything the tracker service can be configured with (the launcher's wiring, client
/// index, status file, spool and replay mode, stays on its command line).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct TrackerConfig {
    /// What the client runs: `"auto"`, `"mono"` or `"vio"` ([`ClientMode`]).
    pub mode: ClientMode,
    /// The IMU calibration of the visual-inertial mode.
    pub imu: ImuCalibConfig,
    /// The calibration mode's priors and log.
    pub calib: CalibModeConfig,
    /// Most keyframes in the client map (seed: N = 100); older ones go to the server.
    pub window: usize,
    /// ORB features per frame.
    pub features: usize,
    /// Rolling-shutter compensation (`false`: off, for comparison).
    pub rolling_shutter: bool,
    /// The order the camera's rolling shutter reads the lines: `"top-to-bottom"` (the
    /// default), `"bottom-to-top"`, `"left-to-right"` or `"right-to-left"`
    /// (`slam_core::rolling_shutter::ReadoutDirection`; the launcher writes the dataset's or
    /// the calibration file's `camera.readout_direction`).
    #[serde(with = "readout_name")]
    pub readout_direction: ReadoutDirection,
    /// Run the VO (`false`: transport only, for replay and IPC tests).
    pub vo: bool,
    /// Where local mapping runs: `"thread"` or `"inline"`.
    pub local_mapping: LocalMapping,
    /// Real time: wait at most this long (ms) for the gyro samples up to a frame's last row.
    pub imu_wait_ms: u64,
    /// In lock-step, synchronise with local mapping and with the server so that no decision
    /// depends on thread timing (`false`: free-running, faster, not reproducible).
    pub lockstep_sync: bool,
    /// Write a per-frame / per-IMU-sample log here (tests); `{c}` is the client index.
    pub frame_log: Option<PathBuf>,
    /// Sleep this many ms per frame (a slow consumer, for tests).
    pub work_ms: u64,
    /// Print the initialiser's and the backward walk's diagnostics on stderr (also set by
    /// the environment variable `SHOAL_DEBUG_INIT`).
    pub debug_init: bool,
    /// Publish each tracked frame's keypoints matched to map points (the `features` topic,
    /// for a recording or a live viewer; the launcher sets it with `--record` / `--viz`).
    pub publish_features: bool,
    /// A visual-inertial client anchors its world to its metric, gravity-aligned server
    /// map from the server's feedback (`slam_core::vio::anchor`).
    pub anchor: AnchorConfig,
    /// After the end of the stream, wait at most this long (s) for the server's
    /// acknowledgement of every keyframe; what is still unacknowledged then stays in the
    /// spool and is sent by the next tracker started on the same output folder. Unset: 5 s,
    /// or [`REMOTE_END_WAIT_S`] for a client of a remote server (the launcher's `connect`),
    /// which may be away for a while (a partition, a restart).
    pub end_wait_s: Option<f64>,
    /// Keep a keyframe's spool file until the mapper acknowledges it, not only until it is
    /// sent: the spool is then the on-disk queue of every unacknowledged keyframe, which a
    /// tracker started after a crash sends again (the mapper applies a keyframe once). The
    /// launcher sets it for a client of a remote server, where a keyframe may stay
    /// unacknowledged for as long as the network is down. At most [`SPOOL_MAX_FILES`]
    /// files; beyond, a keyframe is kept in memory only and the spool error says so.
    pub spool_until_ack: bool,
    /// A saved map (`shoal run --save-map`) to localise in before the monocular VO has
    /// initialised: the client starts its session in that map at the first frame it
    /// relocalises in it (`core/prior.rs`). `shoal run --load-map` sets it for its
    /// monocular clients; unset, the client starts from nothing.
    pub prior_map: Option<PathBuf>,
}

/// Most files in a spool that keeps keyframes until acknowledged (≈ 70 kB each: ≈ 280 MB,
/// half an hour of one client's keyframes at 2.4 a second).
pub const SPOOL_MAX_FILES: usize = 4096;

/// A remote client's default end wait, s ([`TrackerConfig::end_wait_s`]).
pub const REMOTE_END_WAIT_S: f64 = 120.0;

/// A local client's default end wait, s ([`TrackerConfig::end_wait_s`]).
pub const LOCAL_END_WAIT_S: f64 = 5.0;

/// The `anchor` table ([`slam_core::vio::anchor::AnchorParams`]).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct AnchorConfig {
    /// Anchor at all (`false`: the client's poses stay in its own world; each frame's
    /// server-map pose still comes with it, from the feedback, eq. 3.1 and 3.4).
    pub enabled: bool,
    /// Smallest change of the anchor applied, m (or `min_yaw_deg`).
    pub min_translation_m: f64,
    /// Smallest change of the anchor's yaw applied, degrees (or `min_translation_m`).
    pub min_yaw_deg: f64,
}

impl Default for AnchorConfig {
    fn default() -> Self {
        let p = slam_core::vio::anchor::AnchorParams::default();
        Self {
            enabled: p.enabled,
            min_translation_m: p.min_translation_m,
            min_yaw_deg: p.min_yaw_deg,
        }
    }
}

impl AnchorConfig {
    /// As the core's parameters.
    pub fn params(&self) -> slam_core::vio::anchor::AnchorParams {
        slam_core::vio::anchor::AnchorParams {
            enabled: self.enabled,
            min_translation_m: self.min_translation_m,
            min_yaw_deg: self.min_yaw_deg,
        }
    }
}

impl Default for TrackerConfig {
    fn default() -> Self {
        Self {
            mode: ClientMode::Auto,
            imu: ImuCalibConfig::default(),
            calib: CalibModeConfig::default(),
            window: 100,
            features: 1000,
            rolling_shutter: true,
            readout_direction: ReadoutDirection::TopToBottom,
            vo: true,
            local_mapping: LocalMapping::Thread,
            imu_wait_ms: 40,
            lockstep_sync: true,
            frame_log: None,
            work_ms: 0,
            debug_init: false,
            publish_features: false,
            anchor: AnchorConfig::default(),
            end_wait_s: None,
            spool_until_ack: false,
            prior_map: None,
        }
    }
}

/// [`ReadoutDirection`] by its name in configuration files.
mod readout_name {
    use serde::{Deserialize, Deserializer, Serializer};
    use slam_core::rolling_shutter::ReadoutDirection;

    pub fn serialize<S: Serializer>(d: &ReadoutDirection, s: S) -> Result<S::Ok, S::Error> {
        s.serialize_str(d.name())
    }

    pub fn deserialize<'de, D: Deserializer<'de>>(d: D) -> Result<ReadoutDirection, D::Error> {
        let name = String::deserialize(d)?;
        ReadoutDirection::parse(&name)
            .map_err(|e| serde::de::Error::custom(format!("readout_direction {e}")))
    }
}

/// The tracker's options as command-line flags (each overrides its [`TrackerConfig`] key).
#[derive(Debug, Clone, Default, clap::Args)]
pub struct TrackerFlags {
    /// What the client runs (`mode`).
    #[arg(long = "client-mode", value_enum)]
    pub client_mode: Option<ClientMode>,
    /// Most keyframes in the client map (`window`).
    #[arg(long)]
    pub window: Option<usize>,
    /// ORB features per frame (`features`).
    #[arg(long)]
    pub features: Option<usize>,
    /// Turn rolling-shutter compensation off (`rolling_shutter = false`).
    #[arg(long)]
    pub no_rs: bool,
    /// Do not run the VO, transport only (`vo = false`).
    #[arg(long)]
    pub no_vo: bool,
    /// Local mapping inline in the tracking thread (`local_mapping = "inline"`).
    #[arg(long)]
    pub inline_mapping: bool,
    /// Wait at most this long (ms) for the gyro samples of a frame (`imu_wait_ms`).
    #[arg(long)]
    pub imu_wait_ms: Option<u64>,
    /// In lock-step, do not synchronise (`lockstep_sync = false`).
    #[arg(long)]
    pub no_lockstep_sync: bool,
    /// Per-frame / per-IMU-sample log (`frame_log`).
    #[arg(long)]
    pub frame_log: Option<PathBuf>,
    /// Sleep this many ms per frame (`work_ms`).
    #[arg(long)]
    pub work_ms: Option<u64>,
    /// Print the initialiser's diagnostics (`debug_init = true`).
    #[arg(long)]
    pub debug_init: bool,
    /// A visual-inertial client does not anchor its world to the server map
    /// (`anchor.enabled = false`).
    #[arg(long)]
    pub no_anchor: bool,
}

impl TrackerFlags {
    /// Sets the keys of `cfg` that these flags give.
    pub fn apply(&self, cfg: &mut TrackerConfig) {
        if let Some(m) = self.client_mode {
            cfg.mode = m;
        }
        if let Some(v) = self.window {
            cfg.window = v;
        }
        if let Some(v) = self.features {
            cfg.features = v;
        }
        if self.no_rs {
            cfg.rolling_shutter = false;
        }
        if self.no_vo {
            cfg.vo = false;
        }
        if self.inline_mapping {
            cfg.local_mapping = LocalMapping::Inline;
        }
        if let Some(v) = self.imu_wait_ms {
            cfg.imu_wait_ms = v;
        }
        if self.no_lockstep_sync {
            cfg.lockstep_sync = false;
        }
        if let Some(p) = &self.frame_log {
            cfg.frame_log = Some(p.clone());
        }
        if let Some(v) = self.work_ms {
            cfg.work_ms = v;
        }
        if self.debug_init {
            cfg.debug_init = true;
        }
        if self.no_anchor {
            cfg.anchor.enabled = false;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use shoal_runtime::config::parse_flags;

    #[test]
    fn defaults_are_the_former_flag_defaults_and_round_trip() {
        let d = TrackerConfig::default();
        assert_eq!(
            (d.window, d.features, d.imu_wait_ms, d.work_ms),
            (100, 1000, 40, 0)
        );
        assert!(d.rolling_shutter && d.vo && d.lockstep_sync && !d.debug_init);
        assert_eq!(d.local_mapping, LocalMapping::Thread);
        let text = shoal_runtime::config::to_toml(&d).expect("toml");
        let back: TrackerConfig = shoal_runtime::config::parse(&text, "t").expect("parse");
        assert_eq!(back, d);
        let e = shoal_runtime::config::parse::<TrackerConfig>("windows = 3", "t").unwrap_err();
        assert!(e.to_string().contains("windows"), "{e}");
        let e = shoal_runtime::config::parse::<TrackerConfig>("local_mapping = \"x\"", "t");
        assert!(e.is_err());
    }

    #[test]
    fn flags_override_the_file() {
        let mut cfg: TrackerConfig =
            shoal_runtime::config::parse("window = 5\nfeatures = 400", "t").expect("parse");
        let flags: TrackerFlags = parse_flags(
            "tracker",
            [
                "--window=10",
                "--no-rs",
                "--inline-mapping",
                "--frame-log",
                "/tmp/f_{c}.log",
            ],
        )
        .expect("flags");
        flags.apply(&mut cfg);
        assert_eq!((cfg.window, cfg.features), (10, 400));
        assert!(!cfg.rolling_shutter && cfg.vo);
        assert_eq!(cfg.local_mapping, LocalMapping::Inline);
        assert_eq!(cfg.frame_log, Some(PathBuf::from("/tmp/f_{c}.log")));
        assert!(parse_flags::<TrackerFlags>("tracker", ["--windw=3"]).is_err());
    }
}
