//! The loop closer's configuration ([`LoopCloserConfig`], the `[loop_closer]` section of
//! `shoal config --print`) and the flags that override it in a manual run
//! ([`LoopCloserFlags`]; also what `shoal run --loop-closer-arg`, deprecated, is mapped
//! through).
use std::path::PathBuf;

use serde::{Deserialize, Serialize};
use slam_core::pgo::PgoMethod;

/// Everything the loop closer service can be configured with (the launcher's wiring,
/// status, IPC prefix and replay mode, stays on its command line).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct LoopCloserConfig {
    /// Vocabulary file (none: the shipped `assets/orb_vocab.bin`, built in).
    pub vocabulary: Option<PathBuf>,
    /// Pose graph optimisation of loops within one map: `"stepwise"`, `"direct"` or
    /// `"stepwise+direct"`. Default by measurement (BENCHMARKS.md, "Loop closing"): on the
    /// drifting `loop` the stepwise solution gave the lowest server keyframe ATE after the
    /// correction and global BA, in 1 ms instead of 15-22 ms.
    #[serde(with = "method")]
    pub method: PgoMethod,
    /// Detect and report loops but send no correction.
    pub detect_only: bool,
    /// In lock-step, tell the mapper when each loop keyframe is finished
    /// ([`shm_schema::CORRECTION_DONE`]), so corrections land at the same point of the
    /// keyframe stream on every run (`false`: as in real time, for benchmarks).
    pub lockstep_sync: bool,
    /// Print every query's statistics on stderr (also set by the environment variable
    /// `SHOAL_DEBUG_LOOP`).
    pub debug_loop: bool,
}

impl Default for LoopCloserConfig {
    fn default() -> Self {
        Self {
            vocabulary: None,
            method: PgoMethod::Stepwise,
            detect_only: false,
            lockstep_sync: true,
            debug_loop: false,
        }
    }
}

/// [`PgoMethod`] by the names of `shoal pgo --method`.
mod method {
    use serde::{Deserialize, Deserializer, Serializer};
    use slam_core::pgo::PgoMethod;

    pub fn serialize<S: Serializer>(m: &PgoMethod, s: S) -> Result<S::Ok, S::Error> {
        s.serialize_str(match m {
            PgoMethod::Stepwise => "stepwise",
            PgoMethod::Direct => "direct",
            PgoMethod::StepwiseDirect => "stepwise+direct",
        })
    }

    pub fn deserialize<'de, D: Deserializer<'de>>(d: D) -> Result<PgoMethod, D::Error> {
        String::deserialize(d)?
            .parse()
            .map_err(serde::de::Error::custom)
    }
}

/// The loop closer's options as command-line flags (each overrides its
/// [`LoopCloserConfig`] key).
#[derive(Debug, Clone, Default, clap::Args)]
pub struct LoopCloserFlags {
    /// Vocabulary file (`vocabulary`).
    #[arg(long)]
    pub vocabulary: Option<PathBuf>,
    /// Pose graph optimisation: stepwise | direct | stepwise+direct (`method`).
    #[arg(long, value_parser = clap::value_parser!(PgoMethod))]
    pub method: Option<PgoMethod>,
    /// Detect and report loops but send no correction (`detect_only = true`).
    #[arg(long)]
    pub detect_only: bool,
    /// In lock-step, do not synchronise (`lockstep_sync = false`).
    #[arg(long)]
    pub no_lockstep_sync: bool,
    /// Print every query's statistics (`debug_loop = true`).
    #[arg(long)]
    pub debug_loop: bool,
}

impl LoopCloserFlags {
    /// Sets the keys of `cfg` that these flags give.
    pub fn apply(&self, cfg: &mut LoopCloserConfig) {
        if let Some(p) = &self.vocabulary {
            cfg.vocabulary = Some(p.clone());
        }
        if let Some(m) = self.method {
            cfg.method = m;
        }
        if self.detect_only {
            cfg.detect_only = true;
        }
        if self.no_lockstep_sync {
            cfg.lockstep_sync = false;
        }
        if self.debug_loop {
            cfg.debug_loop = true;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use shoal_runtime::config::{parse, parse_flags, to_toml};

    #[test]
    fn defaults_round_trip_methods_by_name_and_flags_override() {
        let d = LoopCloserConfig::default();
        let text = to_toml(&d).expect("toml");
        assert!(text.contains("method = \"stepwise\""), "{text}");
        assert_eq!(parse::<LoopCloserConfig>(&text, "t").expect("parse"), d);
        let c: LoopCloserConfig = parse("method = \"stepwise+direct\"", "t").expect("method");
        assert_eq!(c.method, PgoMethod::StepwiseDirect);
        let e = parse::<LoopCloserConfig>("method = \"best\"", "t").unwrap_err();
        assert!(e.to_string().contains("unknown method"), "{e}");
        let mut cfg = d.clone();
        let f: LoopCloserFlags =
            parse_flags("loop closer", ["--method", "direct", "--detect-only"]).expect("flags");
        f.apply(&mut cfg);
        assert_eq!(cfg.method, PgoMethod::Direct);
        assert!(cfg.detect_only && cfg.lockstep_sync);
    }
}
