//! The IMU ingest's configuration ([`ImuIngestConfig`], the `[imu_ingest]` section of
//! `shoal config --print`) and the flags that override it in a manual run.
use serde::{Deserialize, Serialize};

/// What the IMU ingest can be configured with (the dataset, client, pacing and rate are the
/// run's, on its command line).
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct ImuIngestConfig {
    /// Lock-step: publish samples up to this many ms past the last acknowledged frame.
    pub lookahead_ms: u64,
}

impl Default for ImuIngestConfig {
    fn default() -> Self {
        Self { lookahead_ms: 100 }
    }
}

/// The IMU ingest's options as flags (each overrides its [`ImuIngestConfig`] key).
#[derive(Debug, Clone, Default, clap::Args)]
pub struct ImuIngestFlags {
    /// Lock-step look-ahead past the last acknowledged frame, ms (`lookahead_ms`).
    #[arg(long)]
    pub lookahead_ms: Option<u64>,
}

impl ImuIngestFlags {
    /// Sets the keys of `cfg` that these flags give.
    pub fn apply(&self, cfg: &mut ImuIngestConfig) {
        if let Some(v) = self.lookahead_ms {
            cfg.lookahead_ms = v;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use shoal_runtime::config::{parse, to_toml};

    #[test]
    fn defaults_round_trip_and_unknown_keys_fail() {
        let d = ImuIngestConfig::default();
        assert_eq!(d.lookahead_ms, 100);
        assert_eq!(
            parse::<ImuIngestConfig>(&to_toml(&d).unwrap(), "t").unwrap(),
            d
        );
        assert!(parse::<ImuIngestConfig>("lookahead = 1", "t").is_err());
    }
}
