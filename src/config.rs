//! The run's configuration, typed: [`RunConfig`] holds the run options (datasets, replay
//! mode, output folder, limits, faults) and one section per service, each the service's
//! own serde struct (`[tracker]` = [`tracker::TrackerConfig`], `[mapper]`,
//! `[loop_closer]`, `[camera_ingest]`, `[imu_ingest]`), all with
//! `deny_unknown_fields`: a misspelt key is an error naming the file, line and key.
//!
//! Where it comes from, later over earlier ([`RunConfig::resolve`]): the defaults
//! (`shoal config --print`), a user's TOML file (`shoal run --config FILE`), `--set
//! KEY=VALUE` overrides, the `shoal run` flags, and the deprecated pass-through flags
//! (`--tracker-arg`, `--mapper-arg`, `--loop-closer-arg`), mapped onto the sections'
//! keys through each service's own flags ([`Deprecated::apply`]). The launcher then gives
//! every service its whole section as a file (`OUT/config/*.toml`, `--config FILE`).
use std::path::{Path, PathBuf};
use std::time::Duration;

use serde::{Deserialize, Serialize};
use shoal_runtime::config::{parse_flags, ConfigError};
use shoal_runtime::ReplayMode;

use crate::launcher::faults::{ChaosSpec, KillSpec};

/// Everything a run needs (recorded in full in the report's `provenance.config`, and
/// written to `OUT/config/run.toml`, which `shoal run --config` takes back).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct RunConfig {
    /// One dataset per client (EuRoC ASL, KITTI odometry, phone logger; auto-detected).
    pub datasets: Vec<PathBuf>,
    /// Calibration files put in place of the datasets' own (`shoal run --calib`): none, one
    /// for every dataset, or one per dataset in the order of `datasets`.
    pub calib: Vec<PathBuf>,
    /// Image topic of MCAP / ROS 2 / ROS 1 bag datasets (`--image-topic`; default: found by
    /// message type).
    pub image_topic: Option<String>,
    /// IMU topic of MCAP / ROS 2 / ROS 1 bag datasets (`--imu-topic`; default: found by type).
    pub imu_topic: Option<String>,
    /// Per-client modes (`shoal run --mode` given once per dataset, issue 19: mixed
    /// monocular and visual-inertial clients), in the order of `datasets`; empty: every
    /// client runs `tracker.mode`.
    pub client_modes: Vec<tracker::ClientMode>,
    /// Replay mode: `"lockstep"` (nothing dropped, reproducible) or `"realtime"`.
    pub mode: ReplayMode,
    /// Speed factor in real time (1.0 = the dataset's clock).
    pub rate: f64,
    /// Output folder.
    pub out: PathBuf,
    /// iceoryx2 resource prefix of the run (default: $SHOAL_IPC_PREFIX or `shoal_`).
    pub ipc_prefix: String,
    /// Show a progress bar (on a terminal).
    pub progress: bool,
    /// Replay at most this many frames per client.
    pub max_frames: Option<usize>,
    /// Frame rate of datasets without timestamps (image folders: frame `k` at `k / fps`
    /// s), Hz; their default is 20.
    pub fps: Option<f64>,
    /// Only frames `A..B` (A to B-1, 0-based; `A..` to the end) of the datasets, at their
    /// own times: none, one range for every dataset, or one per dataset in the order of
    /// `datasets` (e.g. two sessions of one sequence as two clients).
    pub frames: Vec<datasets::FrameRange>,
    /// Give up (stop everything, report) after this many seconds.
    pub max_seconds: Option<f64>,
    /// Most restarts of a crash-looping service before it is given up: crashes in a row,
    /// each within `child::STABLE_AFTER` of being ready (a service that runs a while between
    /// kills, e.g. under `chaos`, is always restarted).
    pub max_restarts: u32,
    /// Kill schedule (`--kill SERVICE@SECONDS`), e.g. `["tracker:0@3.5", "mapper@f200"]`.
    #[serde(with = "specs")]
    pub kills: Vec<KillSpec>,
    /// Chaos (`--chaos SEED:PERIOD`), e.g. `"7:2.0"`.
    #[serde(with = "spec")]
    pub chaos: Option<ChaosSpec>,
    /// A saved-map file the server starts from (`--load-map`; checked whole before any
    /// service starts).
    pub load_map: Option<PathBuf>,
    /// Where the server's maps are saved at the end of the run (`--save-map`, atomically).
    pub save_map: Option<PathBuf>,
    /// Localise in the loaded map without adding to it (`--localize-only`; needs
    /// `load_map`, excludes `save_map`).
    pub localize_only: bool,
    /// Record what crosses shared memory to this MCAP file (`--record`; one file per
    /// client, `STEM_c{i}.mcap`, with several).
    pub record: Option<PathBuf>,
    /// Serve the run live to Foxglove's WebSocket protocol on this `HOST:PORT` (`--viz`).
    pub viz: Option<String>,
    /// With `viz`: wait up to this long for a viewer before the run starts, s (0: none).
    pub viz_wait_s: f64,
    /// The server of a remote client (`shoal client --connect tcp/HOST:PORT`): no mapper
    /// nor loop closer run here; a bridge carries the keyframes and the feedback.
    pub connect: Option<String>,
    /// A remote client's name: the server keeps its slot across reconnects (default: the
    /// host name and the dataset's folder name).
    pub client_name: Option<String>,
    /// Only known clients (`--auth FILE`, `NAME:PASSWORD` lines): `shoal serve` takes only
    /// the clients of the file, each under its own name, and may then listen on any address;
    /// `shoal client` presents its one line (its name is the line's).
    pub auth: Option<PathBuf>,
    /// `shoal serve` on a `tls/HOST:PORT` endpoint: its TLS certificate (chain), PEM.
    pub tls_cert: Option<PathBuf>,
    /// `shoal serve` on a `tls/HOST:PORT` endpoint: its TLS private key, PEM.
    pub tls_key: Option<PathBuf>,
    /// `shoal client` of a `tls/HOST:PORT` server: the CA certificate (PEM) the server's
    /// certificate must chain to.
    pub tls_ca: Option<PathBuf>,
    /// `shoal serve`: the endpoint the server listens on (`tcp/HOST:PORT`).
    pub listen: Option<String>,
    /// `shoal serve`: how many remote clients the server takes.
    pub server_clients: u32,
    /// `shoal serve`: the most keyframes a second its mapper is given, all remote clients
    /// together (0: no limit); more are refused, and their trackers send them again.
    pub server_max_keyframe_rate: f64,
    /// Every tracker (`{c}` in `frame_log` is the client index).
    pub tracker: tracker::TrackerConfig,
    /// The mapper.
    pub mapper: mapper::MapperConfig,
    /// The loop closer.
    pub loop_closer: loop_closer::LoopCloserConfig,
    /// Every camera ingest.
    pub camera_ingest: camera_ingest::CameraIngestConfig,
    /// Every IMU ingest.
    pub imu_ingest: imu_ingest::ImuIngestConfig,
}

/// `server_max_keyframe_rate`'s default: the mapper and loop closer took 11 and 24 ms per
/// keyframe (BENCHMARKS.md), so 20 a second (eight clients' worth at 2.4 each) leaves a
/// 2-core server room to spare.
pub const DEFAULT_MAX_KEYFRAME_RATE: f64 = 20.0;

impl Default for RunConfig {
    fn default() -> Self {
        Self {
            datasets: Vec::new(),
            calib: Vec::new(),
            image_topic: None,
            imu_topic: None,
            client_modes: Vec::new(),
            mode: ReplayMode::Lockstep,
            rate: 1.0,
            out: PathBuf::from("out"),
            ipc_prefix: shm_schema::topics::prefix_from_env(),
            progress: true,
            max_frames: None,
            fps: None,
            frames: Vec::new(),
            max_seconds: None,
            max_restarts: 20,
            kills: Vec::new(),
            chaos: None,
            load_map: None,
            save_map: None,
            localize_only: false,
            record: None,
            viz: None,
            viz_wait_s: 0.0,
            connect: None,
            client_name: None,
            auth: None,
            tls_cert: None,
            tls_key: None,
            tls_ca: None,
            listen: None,
            server_clients: 4,
            server_max_keyframe_rate: DEFAULT_MAX_KEYFRAME_RATE,
            tracker: Default::default(),
            mapper: Default::default(),
            loop_closer: Default::default(),
            camera_ingest: Default::default(),
            imu_ingest: Default::default(),
        }
    }
}

/// Kill specs as the strings given on the command line.
mod specs {
    use serde::{Deserialize, Deserializer, Serializer};

    use crate::launcher::faults::KillSpec;

    pub fn serialize<S: Serializer>(k: &[KillSpec], s: S) -> Result<S::Ok, S::Error> {
        s.collect_seq(k.iter().map(|k| k.text.as_str()))
    }

    pub fn deserialize<'de, D: Deserializer<'de>>(d: D) -> Result<Vec<KillSpec>, D::Error> {
        Vec::<String>::deserialize(d)?
            .iter()
            .map(|t| t.parse().map_err(serde::de::Error::custom))
            .collect()
    }
}

/// A chaos spec as the string given on the command line.
mod spec {
    use serde::{Deserialize, Deserializer, Serializer};

    use crate::launcher::faults::ChaosSpec;

    pub fn serialize<S: Serializer>(c: &Option<ChaosSpec>, s: S) -> Result<S::Ok, S::Error> {
        match c {
            Some(c) => s.serialize_some(&c.text),
            None => s.serialize_none(),
        }
    }

    pub fn deserialize<'de, D: Deserializer<'de>>(d: D) -> Result<Option<ChaosSpec>, D::Error> {
        Option::<String>::deserialize(d)?
            .map(|t| t.parse().map_err(serde::de::Error::custom))
            .transpose()
    }
}

/// What `shoal config --print` puts before the defaults.
const HEADER: &str = "\
# shoal run configuration: `shoal run --config FILE` (every key optional; flags and
# `--set KEY=VALUE` override the file). Keys unset by default, not shown below:
# max_frames, max_seconds, chaos (\"SEED:PERIOD\"), tracker.frame_log,
# loop_closer.vocabulary.
";

impl RunConfig {
    /// Defaults for `datasets` written to `out`.
    pub fn new(datasets: Vec<PathBuf>, out: PathBuf) -> Self {
        Self {
            datasets,
            out,
            ..Self::default()
        }
    }

    /// `max_seconds` as a duration.
    pub fn max_duration(&self) -> Option<Duration> {
        self.max_seconds.map(Duration::from_secs_f64)
    }

    /// The configuration of `file` (if any) with the `--set KEY=VALUE` overrides `sets`
    /// over it (a value that is not TOML is taken as a string: `--set
    /// tracker.frame_log=/tmp/f.log`).
    pub fn resolve(file: Option<&Path>, sets: &[String]) -> Result<Self, ConfigError> {
        let mut table = toml::Table::new();
        if let Some(path) = file {
            let name = format!("file {}", path.display());
            let text = std::fs::read_to_string(path).map_err(|e| ConfigError::new(&name, e))?;
            // Typed first: errors then say the line and the key.
            shoal_runtime::config::parse::<Self>(&text, &name)?;
            table = toml::from_str(&text).map_err(|e| ConfigError::new(&name, e))?;
        }
        for s in sets {
            let source = format!("--set {s}");
            let set = set_table(s).map_err(|e| ConfigError::new(&source, e))?;
            Self::from_table(set.clone()).map_err(|e| ConfigError::new(&source, e))?;
            merge(&mut table, set);
        }
        Self::from_table(table).map_err(|e| ConfigError::new("(file and --set)", e))
    }

    fn from_table(t: toml::Table) -> Result<Self, toml::de::Error> {
        toml::Value::Table(t).try_into()
    }

    /// The configuration as TOML, with a header saying how to use it and which keys are
    /// unset (`shoal config --print`; parses back to the same configuration).
    pub fn to_toml_with_header(&self) -> Result<String, ConfigError> {
        Ok(format!(
            "{HEADER}\n{}",
            shoal_runtime::config::to_toml(self)?
        ))
    }

    /// Checks what a run needs: a dataset, a positive rate.
    pub fn validate(&self) -> anyhow::Result<()> {
        anyhow::ensure!(
            !self.datasets.is_empty(),
            "no dataset: give --dataset PATH or `datasets = [...]` in the --config file"
        );
        anyhow::ensure!(
            self.rate > 0.0 && self.rate.is_finite(),
            "rate must be positive (got {})",
            self.rate
        );
        if let Some(s) = self.max_seconds {
            anyhow::ensure!(s > 0.0, "max_seconds must be positive (got {s})");
        }
        if let Some(f) = self.fps {
            anyhow::ensure!(f > 0.0 && f.is_finite(), "fps must be positive (got {f})");
        }
        anyhow::ensure!(
            self.calib.len() <= 1 || self.calib.len() == self.datasets.len(),
            "{} calibration files for {} datasets: give one for all or one per dataset",
            self.calib.len(),
            self.datasets.len()
        );
        anyhow::ensure!(
            self.frames.len() <= 1 || self.frames.len() == self.datasets.len(),
            "{} frame ranges for {} datasets: give --frames once for all or once per dataset",
            self.frames.len(),
            self.datasets.len()
        );
        anyhow::ensure!(
            self.client_modes.is_empty() || self.client_modes.len() == self.datasets.len(),
            "{} client modes for {} datasets: give --mode once for all or once per dataset",
            self.client_modes.len(),
            self.datasets.len()
        );
        Ok(())
    }

    /// The frame range of client `client`'s dataset (`frames`), if any.
    pub fn frames_of(&self, client: usize) -> Option<datasets::FrameRange> {
        match self.frames.as_slice() {
            [] => None,
            [one] => Some(*one),
            many => many.get(client).copied(),
        }
    }

    /// The mode client `client` runs: its own (`client_modes`), else `tracker.mode`.
    pub fn mode_of(&self, client: usize) -> tracker::ClientMode {
        self.client_modes
            .get(client)
            .copied()
            .unwrap_or(self.tracker.mode)
    }

    /// How to open client `client`'s dataset: its calibration file, the MCAP topics, `fps`
    /// and its frame range.
    pub fn open_options(&self, client: usize) -> datasets::OpenOptions {
        datasets::OpenOptions {
            calib: self.calib_of(client).map(Path::to_path_buf),
            topics: datasets::mcap_bag::Topics {
                image: self.image_topic.clone(),
                imu: self.imu_topic.clone(),
            },
            fps: self.fps,
            frames: self.frames_of(client),
        }
    }

    /// The calibration file of client `client`, if any (`calib`).
    pub fn calib_of(&self, client: usize) -> Option<&Path> {
        match self.calib.as_slice() {
            [] => None,
            [one] => Some(one),
            many => many.get(client).map(PathBuf::as_path),
        }
    }

    /// The configuration file of service `desc` (its section; for a tracker, `{c}` in
    /// `frame_log` replaced by its client index), as the launcher writes it.
    pub fn service_toml(
        &self,
        desc: &crate::launcher::topology::ServiceDesc,
    ) -> Result<String, ConfigError> {
        use crate::launcher::topology::Kind;
        use shoal_runtime::config::to_toml;
        match desc.kind {
            Kind::Tracker => {
                let mut t = self.tracker.clone();
                let c = desc.client.unwrap_or(0).to_string();
                let per_client = |p: PathBuf| PathBuf::from(p.to_string_lossy().replace("{c}", &c));
                t.frame_log = t.frame_log.map(per_client);
                t.calib.log = t.calib.log.map(per_client);
                to_toml(&t)
            }
            Kind::Mapper => to_toml(&self.mapper),
            Kind::LoopCloser => to_toml(&self.loop_closer),
            Kind::CameraIngest => to_toml(&self.camera_ingest),
            Kind::ImuIngest => to_toml(&self.imu_ingest),
            // The bridge's settings are on its command line.
            Kind::Bridge => Ok(String::new()),
        }
    }
}

/// `KEY=VALUE` as a TOML table (`tracker.window=10` → `{tracker = {window = 10}}`); a
/// value that is no TOML value is a string.
fn set_table(s: &str) -> Result<toml::Table, String> {
    let (key, value) = s
        .split_once('=')
        .ok_or_else(|| "expected KEY=VALUE, e.g. tracker.window=10".to_string())?;
    let (key, value) = (key.trim(), value.trim());
    if key.is_empty()
        || !key.split('.').all(|k| {
            !k.is_empty()
                && k.chars()
                    .all(|c| c.is_ascii_alphanumeric() || c == '_' || c == '-')
        })
    {
        return Err(format!("'{key}' is not a key (e.g. tracker.window)"));
    }
    toml::from_str(&format!("{key} = {value}")).or_else(|_| {
        let quoted = toml::Value::String(value.to_string()).to_string();
        toml::from_str(&format!("{key} = {quoted}")).map_err(|e| e.to_string())
    })
}

/// Merges `over` into `base`: tables key by key, anything else replaced.
fn merge(base: &mut toml::Table, over: toml::Table) {
    for (k, v) in over {
        match (base.get_mut(&k), v) {
            (Some(toml::Value::Table(b)), toml::Value::Table(o)) => merge(b, o),
            (_, v) => {
                base.insert(k, v);
            }
        }
    }
}

/// The deprecated pass-through flags of `shoal run`, as given (`{c}` kept: the launcher
/// replaces it per client).
#[derive(Debug, Clone, Default)]
pub struct Deprecated {
    /// `--tracker-arg` values, in order.
    pub tracker: Vec<String>,
    /// `--mapper-arg` values.
    pub mapper: Vec<String>,
    /// `--loop-closer-arg` values.
    pub loop_closer: Vec<String>,
}

impl Deprecated {
    /// Maps the flags onto `cfg` (each service's flags parse them: an unknown one is an
    /// error naming it). Returns the keys they set, as `section.key = value`, for the
    /// deprecation warning (empty when none was given).
    pub fn apply(&self, cfg: &mut RunConfig) -> anyhow::Result<Vec<String>> {
        let mut set = Vec::new();
        if !self.tracker.is_empty() {
            let f: tracker::TrackerFlags = parse_deprecated("--tracker-arg", &self.tracker)?;
            let before = cfg.tracker.clone();
            f.apply(&mut cfg.tracker);
            set.extend(changed("tracker", &before, &cfg.tracker));
        }
        if !self.mapper.is_empty() {
            let f: mapper::MapperFlags = parse_deprecated("--mapper-arg", &self.mapper)?;
            let before = cfg.mapper.clone();
            f.apply(&mut cfg.mapper);
            set.extend(changed("mapper", &before, &cfg.mapper));
        }
        if !self.loop_closer.is_empty() {
            let f: loop_closer::LoopCloserFlags =
                parse_deprecated("--loop-closer-arg", &self.loop_closer)?;
            let before = cfg.loop_closer.clone();
            f.apply(&mut cfg.loop_closer);
            set.extend(changed("loop_closer", &before, &cfg.loop_closer));
        }
        Ok(set)
    }

    /// Whether any was given.
    pub fn is_empty(&self) -> bool {
        self.tracker.is_empty() && self.mapper.is_empty() && self.loop_closer.is_empty()
    }

    /// The one warning for a run that used them.
    pub fn warning(set: &[String]) -> String {
        let example = set.first().map_or_else(
            || "tracker.window=10".to_string(),
            |s| s.replacen(" = ", "=", 1),
        );
        format!(
            "warning: --tracker-arg, --mapper-arg and --loop-closer-arg are deprecated and will \
             be removed; mapped onto the configuration as: {}. Use `--set {example}` or a \
             --config file (`shoal config --print` shows every key).",
            if set.is_empty() {
                "(no change)".to_string()
            } else {
                set.join(", ")
            }
        )
    }
}

fn parse_deprecated<F: clap::Args + clap::FromArgMatches>(
    flag: &'static str,
    args: &[String],
) -> anyhow::Result<F> {
    parse_flags(flag, args).map_err(|e| {
        let msg = e.render().to_string();
        let first = msg
            .lines()
            .next()
            .unwrap_or("")
            .trim_start_matches("error: ");
        anyhow::anyhow!(
            "{flag} {}: {first} (known: `shoal service {} --help`; or set the key in a \
             --config file, `shoal config --print`)",
            args.join(" "),
            match flag {
                "--tracker-arg" => "tracker",
                "--mapper-arg" => "mapper",
                _ => "loop-closer",
            }
        )
    })
}

/// The keys of `after` that differ from `before`, as `section.key = value`.
fn changed<T: Serialize>(section: &str, before: &T, after: &T) -> Vec<String> {
    let table = |v: &T| toml::Table::try_from(v).unwrap_or_default();
    let (b, a) = (table(before), table(after));
    a.iter()
        .filter(|(k, v)| b.get(*k) != Some(*v))
        .map(|(k, v)| format!("{section}.{k} = {v}"))
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    fn tmp(name: &str, text: &str) -> PathBuf {
        let dir = std::env::temp_dir().join(format!("shoal_runcfg_{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let p = dir.join(name);
        std::fs::write(&p, text).unwrap();
        p
    }

    #[test]
    fn printed_defaults_parse_back_with_unknown_keys_denied() {
        let d = RunConfig::default();
        let text = d.to_toml_with_header().expect("print");
        for section in ["[tracker]", "[mapper]", "[loop_closer]", "[camera_ingest]"] {
            assert!(text.contains(section), "{section} missing:\n{text}");
        }
        assert!(text.contains("[imu_ingest]") && text.contains("window = 100"));
        let back: RunConfig = shoal_runtime::config::parse(&text, "printed").expect("parse");
        assert_eq!(back, d);
        let file = tmp("printed.toml", &text);
        assert_eq!(RunConfig::resolve(Some(&file), &[]).expect("file"), d);
    }

    #[test]
    fn frame_ranges_and_fps_come_from_the_file_once_or_per_dataset() {
        let dir = tempfile::tempdir().expect("tmp");
        let file = dir.path().join("run.toml");
        std::fs::write(
            &file,
            "datasets = [\"a\", \"b\"]\nfps = 30.0\nframes = [\"0..300\", \"450..\"]\n",
        )
        .expect("write");
        let c = RunConfig::resolve(Some(&file), &[]).expect("resolve");
        assert!(c.validate().is_ok());
        let (a, b) = (c.open_options(0), c.open_options(1));
        assert_eq!(
            (a.fps, a.frames.map(|r| r.to_string())),
            (Some(30.0), Some("0..300".into()))
        );
        assert_eq!(b.frames.map(|r| r.to_string()), Some("450..".into()));
        let back: RunConfig =
            toml::from_str(&c.to_toml_with_header().expect("toml")).expect("parse");
        assert_eq!(back.frames, c.frames);
        let mut one = c.clone();
        one.frames.truncate(1);
        assert_eq!(one.frames_of(1), one.frames_of(0), "one range for all");
        let mut three = c.clone();
        three.frames.push("1..2".parse().expect("range"));
        let e = three.validate().unwrap_err().to_string();
        assert!(e.contains("3 frame ranges for 2 datasets"), "{e}");
        let bad = RunConfig::resolve(None, &["frames = [\"9..3\"]".into()]);
        assert!(bad.is_err(), "an empty range is refused");
        let mut slow = c;
        slow.fps = Some(0.0);
        assert!(slow.validate().is_err());
    }

    #[test]
    fn client_modes_are_one_per_dataset_or_none() {
        use tracker::ClientMode;
        let mut c = RunConfig {
            datasets: vec!["a".into(), "b".into()],
            ..RunConfig::default()
        };
        c.tracker.mode = ClientMode::Vio;
        assert!(c.validate().is_ok());
        assert_eq!(c.mode_of(1), ClientMode::Vio, "tracker.mode for all");
        c.client_modes = vec![ClientMode::Mono, ClientMode::Vio];
        assert!(c.validate().is_ok());
        assert_eq!(
            (c.mode_of(0), c.mode_of(1)),
            (ClientMode::Mono, ClientMode::Vio)
        );
        c.client_modes.push(ClientMode::Mono);
        let e = c.validate().unwrap_err().to_string();
        assert!(e.contains("3 client modes for 2 datasets"), "{e}");
    }

    #[test]
    fn defaults_are_the_former_flag_defaults() {
        let d = RunConfig::default();
        assert_eq!(d.mode, ReplayMode::Lockstep);
        assert_eq!((d.rate, d.max_restarts, d.progress), (1.0, 20, true));
        assert_eq!(d.out, PathBuf::from("out"));
        assert_eq!(d.tracker, tracker::TrackerConfig::default());
        assert_eq!(d.tracker.window, 100);
        assert_eq!(d.mapper.drain_seconds, 50.0);
        assert_eq!(d.camera_ingest.resend_ms, 1000);
        assert_eq!(d.imu_ingest.lookahead_ms, 100);
    }

    #[test]
    fn a_user_file_sets_sections_and_unknown_keys_name_file_and_key() {
        let file = tmp(
            "user.toml",
            "datasets = [\"a\", \"b\"]\nmode = \"realtime\"\nrate = 2.0\nkills = [\"mapper@f20\"]\n\
             chaos = \"7:2.0\"\n[tracker]\nwindow = 10\nlocal_mapping = \"inline\"\n\
             [loop_closer]\nmethod = \"direct\"\n",
        );
        let c = RunConfig::resolve(Some(&file), &[]).expect("user file");
        assert_eq!(c.datasets.len(), 2);
        assert_eq!((c.mode, c.rate), (ReplayMode::Realtime, 2.0));
        assert_eq!(c.kills[0].text, "mapper@f20");
        assert_eq!(c.chaos.as_ref().map(|s| s.seed), Some(7));
        assert_eq!(c.tracker.window, 10);
        assert_eq!(c.tracker.local_mapping, tracker::LocalMapping::Inline);
        assert_eq!(c.tracker.features, 1000, "unset keys keep their defaults");
        assert_eq!(c.loop_closer.method, slam_core::pgo::PgoMethod::Direct);

        let bad = tmp("bad.toml", "[tracker]\nwindow = 10\nwindw = 3\n");
        let e = RunConfig::resolve(Some(&bad), &[]).unwrap_err().to_string();
        assert!(e.contains("bad.toml") && e.contains("windw"), "{e}");
        assert!(e.contains("line 3"), "{e}");
        let bad = tmp("bad_top.toml", "dataset = [\"a\"]\n");
        let e = RunConfig::resolve(Some(&bad), &[]).unwrap_err().to_string();
        assert!(e.contains("bad_top.toml") && e.contains("`dataset`"), "{e}");
        let bad = tmp("bad_section.toml", "[tracer]\nwindow = 1\n");
        let e = RunConfig::resolve(Some(&bad), &[]).unwrap_err().to_string();
        assert!(e.contains("tracer"), "{e}");
        let bad = tmp("bad_kill.toml", "kills = [\"mapper\"]\n");
        assert!(RunConfig::resolve(Some(&bad), &[]).is_err());
    }

    #[test]
    fn set_overrides_the_file_and_checks_keys() {
        let file = tmp("set.toml", "[tracker]\nwindow = 10\nfeatures = 400\n");
        let sets = [
            "tracker.window=5".to_string(),
            "tracker.frame_log=/tmp/f_{c}.log".to_string(),
            "mapper.spatial_keyframes = 0".to_string(),
            "max_frames=20".to_string(),
        ];
        let c = RunConfig::resolve(Some(&file), &sets).expect("sets");
        assert_eq!((c.tracker.window, c.tracker.features), (5, 400));
        assert_eq!(c.tracker.frame_log, Some(PathBuf::from("/tmp/f_{c}.log")));
        assert_eq!(c.mapper.spatial_keyframes, 0);
        assert_eq!(c.max_frames, Some(20));
        let e = RunConfig::resolve(None, &["tracker.windw=5".into()]).unwrap_err();
        assert!(e.to_string().contains("--set tracker.windw=5"), "{e}");
        assert!(e.to_string().contains("windw"), "{e}");
        assert!(RunConfig::resolve(None, &["tracker.window=ten".into()]).is_err());
        assert!(RunConfig::resolve(None, &["window".into()]).is_err());
    }

    #[test]
    fn deprecated_pass_through_maps_onto_the_sections() {
        let mut c = RunConfig::default();
        let d = Deprecated {
            tracker: vec![
                "--window=10".into(),
                "--no-vo".into(),
                "--frame-log".into(),
                "/tmp/log_{c}.txt".into(),
                "--inline-mapping".into(),
            ],
            mapper: vec!["--spatial-keyframes=0".into(), "--no-lockstep-sync".into()],
            loop_closer: vec!["--detect-only".into()],
        };
        let set = d.apply(&mut c).expect("known flags");
        assert_eq!(c.tracker.window, 10);
        assert!(!c.tracker.vo);
        assert_eq!(c.tracker.local_mapping, tracker::LocalMapping::Inline);
        assert_eq!(c.tracker.frame_log, Some(PathBuf::from("/tmp/log_{c}.txt")));
        assert_eq!(c.mapper.spatial_keyframes, 0);
        assert!(!c.mapper.lockstep_sync && c.loop_closer.detect_only);
        assert!(set.contains(&"tracker.window = 10".to_string()), "{set:?}");
        assert!(set.contains(&"tracker.vo = false".to_string()), "{set:?}");
        let w = Deprecated::warning(&set);
        assert!(
            w.contains("deprecated") && w.contains("--set tracker."),
            "{w}"
        );

        let unknown = Deprecated {
            tracker: vec!["--windw=10".into()],
            ..Deprecated::default()
        };
        let e = unknown.apply(&mut c).unwrap_err().to_string();
        assert!(
            e.contains("--tracker-arg --windw=10") && e.contains("windw"),
            "{e}"
        );
        // The launcher's wiring is not an option.
        let wiring = Deprecated {
            tracker: vec!["--client=3".into()],
            ..Deprecated::default()
        };
        assert!(wiring.apply(&mut c).is_err());
    }

    #[test]
    fn each_service_gets_its_section_with_the_client_substituted() {
        use crate::launcher::topology::{Kind, ServiceDesc};
        let mut c = RunConfig::default();
        c.tracker.window = 10;
        c.tracker.frame_log = Some(PathBuf::from("/tmp/log_{c}.txt"));
        let desc = ServiceDesc {
            kind: Kind::Tracker,
            client: Some(1),
        };
        let text = c.service_toml(&desc).expect("tracker");
        let t: tracker::TrackerConfig = shoal_runtime::config::parse(&text, "t").expect("back");
        assert_eq!(t.window, 10);
        assert_eq!(t.frame_log, Some(PathBuf::from("/tmp/log_1.txt")));
        let desc = ServiceDesc {
            kind: Kind::Mapper,
            client: None,
        };
        let m: mapper::MapperConfig =
            shoal_runtime::config::parse(&c.service_toml(&desc).expect("mapper"), "m")
                .expect("back");
        assert_eq!(m, c.mapper);
    }
}
