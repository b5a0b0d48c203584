//! The camera ingest's configuration ([`CameraIngestConfig`], the `[camera_ingest]`
//! section of `shoal config --print`) and the flags that override it in a manual run.
use serde::{Deserialize, Serialize};

/// What the camera ingest can be configured with (the dataset, client, pacing and rate are
/// the run's, on its command line).
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct CameraIngestConfig {
    /// Lock-step: re-send a frame when its acknowledgement has not come after this many ms.
    pub resend_ms: u64,
    /// Lock-step: give up waiting for an acknowledgement (and count the frame as unacked)
    /// after this many ms.
    pub ack_timeout_ms: u64,
}

impl Default for CameraIngestConfig {
    fn default() -> Self {
        Self {
            resend_ms: 1000,
            ack_timeout_ms: 60_000,
        }
    }
}

/// The camera ingest's options as flags (each overrides its [`CameraIngestConfig`] key).
#[derive(Debug, Clone, Default, clap::Args)]
pub struct CameraIngestFlags {
    /// Lock-step re-send period, ms (`resend_ms`).
    #[arg(long)]
    pub resend_ms: Option<u64>,
    /// Lock-step acknowledgement timeout, ms (`ack_timeout_ms`).
    #[arg(long)]
    pub ack_timeout_ms: Option<u64>,
}

impl CameraIngestFlags {
    /// Sets the keys of `cfg` that these flags give.
    pub fn apply(&self, cfg: &mut CameraIngestConfig) {
        if let Some(v) = self.resend_ms {
            cfg.resend_ms = v;
        }
        if let Some(v) = self.ack_timeout_ms {
            cfg.ack_timeout_ms = v;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use shoal_runtime::config::{parse, to_toml};

    #[test]
    fn defaults_round_trip_and_unknown_keys_fail() {
        let d = CameraIngestConfig::default();
        assert_eq!((d.resend_ms, d.ack_timeout_ms), (1000, 60_000));
        assert_eq!(
            parse::<CameraIngestConfig>(&to_toml(&d).unwrap(), "t").unwrap(),
            d
        );
        assert!(parse::<CameraIngestConfig>("resend = 1", "t").is_err());
    }
}
