//! Typed service configurations on disk: one serde struct per service (`TrackerConfig` in
//! `services/tracker`, `MapperConfig`, ...), each `#[serde(deny_unknown_fields, default)]`,
//! read from and written as TOML. The launcher writes every service's whole configuration
//! to `OUT/config/<service>.toml` and starts it with `--config FILE`; a user's file for
//! `shoal run --config` holds them all as sections (`[tracker]`, `[mapper]`, ...).
//!
//! A key the struct does not know is an error naming the file, the line and the key, and
//! the service exits with [`crate::EXIT_CONFIG`] (not restarted).
use std::path::{Path, PathBuf};

use serde::de::DeserializeOwned;
use serde::Serialize;

/// A configuration that cannot be read: which file (or other source) and why.
#[derive(Debug)]
pub struct ConfigError {
    /// The file, or what else was parsed (e.g. `--set tracker.window=10`).
    pub source: String,
    /// Why (for TOML: line, column and the key, as the parser says).
    pub reason: String,
}

impl std::fmt::Display for ConfigError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "config {}: {}", self.source, self.reason.trim_end())
    }
}

impl std::error::Error for ConfigError {}

impl ConfigError {
    /// An error of `source`.
    pub fn new(source: impl Into<String>, reason: impl std::fmt::Display) -> Self {
        Self {
            source: source.into(),
            reason: reason.to_string(),
        }
    }
}

/// Parses TOML `text` (from `source`, named in errors) into `T`.
pub fn parse<T: DeserializeOwned>(text: &str, source: &str) -> Result<T, ConfigError> {
    toml::from_str(text).map_err(|e| ConfigError::new(source, e))
}

/// Reads the TOML file `path` into `T`.
pub fn load<T: DeserializeOwned>(path: &Path) -> Result<T, ConfigError> {
    let name = format!("file {}", path.display());
    let text = std::fs::read_to_string(path).map_err(|e| ConfigError::new(&name, e))?;
    parse(&text, &name)
}

/// `value` as TOML text.
pub fn to_toml<T: Serialize>(value: &T) -> Result<String, ConfigError> {
    toml::to_string(value).map_err(|e| ConfigError::new("(serialising)", e))
}

/// Writes `value` as TOML to `path` (its folder created).
pub fn write<T: Serialize>(path: &Path, value: &T) -> anyhow::Result<()> {
    if let Some(dir) = path.parent() {
        std::fs::create_dir_all(dir)?;
    }
    std::fs::write(path, to_toml(value)?)
        .map_err(|e| anyhow::anyhow!("writing {}: {e}", path.display()))
}

/// A service's configuration: from `file` when given (else the defaults), then the
/// command-line overrides of a manual run.
pub fn resolve<T: DeserializeOwned + Default>(
    file: Option<&PathBuf>,
    overrides: impl FnOnce(&mut T),
) -> Result<T, ConfigError> {
    let mut cfg = match file {
        Some(p) => load(p)?,
        None => T::default(),
    };
    overrides(&mut cfg);
    Ok(cfg)
}

/// Parses option flags `F` (a service's overrides, e.g. `tracker::TrackerFlags`) from
/// `args` alone (no program name), as a command named `name` in errors.
pub fn parse_flags<F: clap::Args + clap::FromArgMatches>(
    name: &'static str,
    args: impl IntoIterator<Item = impl Into<std::ffi::OsString> + Clone>,
) -> Result<F, clap::Error> {
    let cmd = F::augment_args(clap::Command::new(name).no_binary_name(true));
    let matches = cmd.try_get_matches_from(args)?;
    F::from_arg_matches(&matches)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[derive(Debug, PartialEq, serde::Serialize, serde::Deserialize)]
    #[serde(deny_unknown_fields, default)]
    struct Demo {
        window: usize,
        name: Option<String>,
    }

    impl Default for Demo {
        fn default() -> Self {
            Self {
                window: 100,
                name: None,
            }
        }
    }

    #[test]
    fn defaults_fill_missing_keys_and_unknown_keys_are_named() {
        let d: Demo = parse("", "test").expect("empty");
        assert_eq!(d, Demo::default());
        let d: Demo = parse("window = 7", "test").expect("window");
        assert_eq!(d.window, 7);
        let e = parse::<Demo>("window = 7\nwindw = 8\n", "file x.toml").unwrap_err();
        let msg = e.to_string();
        assert!(msg.starts_with("config file x.toml:"), "{msg}");
        assert!(msg.contains("windw") && msg.contains("line 2"), "{msg}");
        let e = parse::<Demo>("window = \"ten\"", "test").unwrap_err();
        assert!(e.to_string().contains("window"), "{e}");
    }

    #[test]
    fn round_trip_and_files() {
        let d = Demo {
            window: 3,
            name: Some("a".into()),
        };
        let text = to_toml(&d).expect("toml");
        assert_eq!(parse::<Demo>(&text, "t").expect("back"), d);
        let dir = std::env::temp_dir().join(format!("shoal_cfg_{}", std::process::id()));
        let path = dir.join("sub").join("demo.toml");
        write(&path, &d).expect("write");
        let back: Demo = resolve(Some(&path), |c: &mut Demo| c.window += 1).expect("load");
        assert_eq!(back.window, 4);
        let missing = load::<Demo>(&dir.join("none.toml")).unwrap_err();
        assert!(missing.to_string().contains("none.toml"), "{missing}");
        let _ = std::fs::remove_dir_all(&dir);
    }
}
