//! The mapper's configuration ([`MapperConfig`], the `[mapper]` section of
//! `shoal config --print`) and the flags that override it in a manual run
//! ([`MapperFlags`]; also what `shoal run --mapper-arg`, deprecated, is mapped through).
use serde::{Deserialize, Serialize};
use slam_core::server::HandlerParams;

/// Everything the mapper service can be configured with (the launcher's wiring, clients,
/// status, journal, output folder and replay mode, stays on its command line).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct MapperConfig {
    /// Keyframes near the predicted pose searched for a revisit (0: none, so that a revisit
    /// is left to loop closing; for ablations).
    pub spatial_keyframes: usize,
    /// Global BA when a kept keyframe re-observes at least this many points of a place seen
    /// more than 5 s before (a revisit; at most one per 5 s of data). 0: never.
    pub revisit_points: usize,
    /// Forget a client point not referenced by the last this-many keyframe ids of its
    /// client session (must exceed the id span of the client VO's window; 0: never).
    pub assoc_horizon: u64,
    /// At the end, wait at most this long (s) for the handlers to finish their queues.
    pub drain_seconds: f64,
    /// In lock-step, run the idle step after every keyframe and tell the tracker when a
    /// keyframe is finished, so the server maps are the same on every run (`false`: as in
    /// real time, for benchmarks).
    pub lockstep_sync: bool,
}

impl Default for MapperConfig {
    fn default() -> Self {
        let h = HandlerParams::default();
        Self {
            spatial_keyframes: h.spatial_keyframes,
            revisit_points: h.revisit_min_points,
            assoc_horizon: h.assoc_horizon_kfs,
            drain_seconds: 50.0,
            lockstep_sync: true,
        }
    }
}

/// The mapper's options as command-line flags (each overrides its [`MapperConfig`] key).
#[derive(Debug, Clone, Default, clap::Args)]
pub struct MapperFlags {
    /// Revisit search breadth (`spatial_keyframes`).
    #[arg(long)]
    pub spatial_keyframes: Option<usize>,
    /// Points of a revisit that trigger a global BA (`revisit_points`).
    #[arg(long)]
    pub revisit_points: Option<usize>,
    /// Client point association horizon in keyframe ids (`assoc_horizon`).
    #[arg(long)]
    pub assoc_horizon: Option<u64>,
    /// Longest wait for the handlers at the end, s (`drain_seconds`).
    #[arg(long)]
    pub drain_seconds: Option<f64>,
    /// In lock-step, do not synchronise (`lockstep_sync = false`).
    #[arg(long)]
    pub no_lockstep_sync: bool,
}

impl MapperFlags {
    /// Sets the keys of `cfg` that these flags give.
    pub fn apply(&self, cfg: &mut MapperConfig) {
        if let Some(v) = self.spatial_keyframes {
            cfg.spatial_keyframes = v;
        }
        if let Some(v) = self.revisit_points {
            cfg.revisit_points = v;
        }
        if let Some(v) = self.assoc_horizon {
            cfg.assoc_horizon = v;
        }
        if let Some(v) = self.drain_seconds {
            cfg.drain_seconds = v;
        }
        if self.no_lockstep_sync {
            cfg.lockstep_sync = false;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use shoal_runtime::config::{parse, parse_flags, to_toml};

    #[test]
    fn defaults_round_trip_and_flags_override() {
        let d = MapperConfig::default();
        assert_eq!(d.drain_seconds, 50.0);
        assert!(d.lockstep_sync);
        let back: MapperConfig = parse(&to_toml(&d).expect("toml"), "t").expect("parse");
        assert_eq!(back, d);
        assert!(parse::<MapperConfig>("spatial = 0", "t").is_err());
        let mut cfg = d.clone();
        let f: MapperFlags =
            parse_flags("mapper", ["--spatial-keyframes=0", "--no-lockstep-sync"]).expect("flags");
        f.apply(&mut cfg);
        assert_eq!(cfg.spatial_keyframes, 0);
        assert!(!cfg.lockstep_sync);
        assert_eq!(cfg.assoc_horizon, d.assoc_horizon);
    }
}
