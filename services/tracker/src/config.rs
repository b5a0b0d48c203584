//! The tracker's configuration ([`TrackerConfig`], the `[tracker]` section of
//! `shoal config --print`) and the command-line flags that override it in a manual run
//! ([`TrackerFlags`]; also what `shoal run --tracker-arg`, deprecated, is mapped through).
use std::path::PathBuf;

use serde::{Deserialize, Serialize};

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

/// Everything the tracker service can be configured with (the launcher's wiring, client
/// index, status file, spool and replay mode, stays on its command line).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct TrackerConfig {
    /// Most keyframes in the client map (seed: N = 100); older ones go to the server.
    pub window: usize,
    /// ORB features per frame.
    pub features: usize,
    /// Rolling-shutter compensation (`false`: off, for comparison).
    pub rolling_shutter: bool,
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
}

impl Default for TrackerConfig {
    fn default() -> Self {
        Self {
            window: 100,
            features: 1000,
            rolling_shutter: true,
            vo: true,
            local_mapping: LocalMapping::Thread,
            imu_wait_ms: 40,
            lockstep_sync: true,
            frame_log: None,
            work_ms: 0,
            debug_init: false,
        }
    }
}

/// The tracker's options as command-line flags (each overrides its [`TrackerConfig`] key).
#[derive(Debug, Clone, Default, clap::Args)]
pub struct TrackerFlags {
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
}

impl TrackerFlags {
    /// Sets the keys of `cfg` that these flags give.
    pub fn apply(&self, cfg: &mut TrackerConfig) {
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
