//! Daemon settings: a TOML file whose every key has an embedded default, so `klipcal serve`
//! runs with no file on a standard printer host. Unknown keys and bad values are errors that
//! name the key, the value and what is expected. Reads no environment beyond `HOME`.
//!
//! One file per section: `daemon` (`[moonraker]`, `[log]`, `[daemon]`), `ab`, `mesh`,
//! `backlash`, `http`; `[soak]` is `calib::soak::SoakParams`. Each section checks its own
//! ranges; `Config::validate` asks each in turn and returns the first error. `edit` writes an
//! answer into the file (the soak question's), comments kept, backed up first.

mod ab;
mod backlash;
mod daemon;
pub(crate) mod edit;
mod http;
mod mesh;

pub use ab::AbConfig;
pub use backlash::BacklashConfig;
pub use daemon::{DaemonConfig, LogConfig, MoonrakerConfig};
pub use http::HttpConfig;
pub use mesh::MeshConfig;

use std::path::{Path, PathBuf};

use serde::Deserialize;

/// A settings error a user can cause.
#[derive(Debug, thiserror::Error)]
pub enum Error {
    /// The file could not be read.
    #[error("cannot read config file {path}: {cause}")]
    Read {
        /// The path tried.
        path: PathBuf,
        /// The I/O error. Shown in the message, and deliberately not the error's `source()`:
        /// a `{:#}` chain would print it twice.
        cause: std::io::Error,
    },
    /// The file is not valid TOML or has an unknown key or a value of the wrong type.
    #[error("config file {path}: {message}")]
    Parse {
        /// The path read.
        path: PathBuf,
        /// toml's message, which names the line, the key and what was expected.
        message: String,
    },
    /// A `[soak]` key has a value out of range.
    #[error("config key {0}")]
    Soak(#[from] crate::calib::soak::SoakParamsError),
    /// A `[backlash]` key has a value out of range.
    #[error("config [backlash]: {0}")]
    Backlash(String),
    /// A key has a value out of range.
    #[error("config key `{key}` = {value}: expected {expected}")]
    Invalid {
        /// Dotted key name, e.g. `moonraker.url`.
        key: &'static str,
        /// The value found.
        value: String,
        /// What would be accepted.
        expected: &'static str,
    },
}

/// All settings. See `config/klipcal.toml` for every key and its default.
#[derive(Debug, Clone, Default, Deserialize, PartialEq)]
#[serde(default, deny_unknown_fields)]
pub struct Config {
    /// How to reach Moonraker.
    pub moonraker: MoonrakerConfig,
    /// Logging.
    pub log: LogConfig,
    /// The daemon's own files.
    pub daemon: DaemonConfig,
    /// Differential A/B (X/Y) calibration sessions.
    pub ab: AbConfig,
    /// Thermal soak detection (bed power watching, paper §3.1).
    pub soak: crate::calib::soak::SoakParams,
    /// Backlash measurement (seed 004): verdict thresholds, smooth_time budget, jog sizes.
    pub backlash: BacklashConfig,
    /// The daemon's own HTTP API and page.
    pub http: HttpConfig,
    /// Thermal bed-mesh compensation (seed 002): capture, fit, profiles, follow, check.
    pub mesh: MeshConfig,
    /// Keys of earlier versions found in the file and ignored (for a warning at start).
    #[serde(skip)]
    pub retired_keys: Vec<String>,
    /// The file the settings were read from (none: the embedded defaults, or text parsed).
    #[serde(skip)]
    pub(crate) path: Option<PathBuf>,
}

/// The conventional path, `~/printer_data/config/klipcal.toml`.
pub(crate) fn default_path() -> PathBuf {
    expand_home("~/printer_data/config/klipcal.toml")
}

/// Expands a leading `~/` to `$HOME/`.
pub fn expand_home(path: &str) -> PathBuf {
    match (path.strip_prefix("~/"), std::env::var_os("HOME")) {
        (Some(rest), Some(home)) => Path::new(&home).join(rest),
        _ => PathBuf::from(path),
    }
}

impl Config {
    /// Loads settings: `explicit` must exist; without it the default path is read when present,
    /// else the embedded defaults are used.
    ///
    /// # Errors
    /// An unreadable file, bad TOML, an unknown key or a value out of range.
    pub fn load(explicit: Option<&Path>) -> Result<Self, Error> {
        let path = match explicit {
            Some(p) => p.to_path_buf(),
            None => {
                let p = default_path();
                if !p.exists() {
                    return Ok(Self::default());
                }
                p
            }
        };
        let text = std::fs::read_to_string(&path).map_err(|cause| Error::Read {
            path: path.clone(),
            cause,
        })?;
        let mut cfg = Self::parse(&text).map_err(|e| match e {
            Error::Parse { message, .. } => Error::Parse {
                path: path.clone(),
                message,
            },
            other => other,
        })?;
        cfg.path = Some(path);
        Ok(cfg)
    }

    /// Parses and validates TOML text.
    ///
    /// # Errors
    /// Bad TOML, an unknown key or a value out of range.
    pub fn parse(text: &str) -> Result<Self, Error> {
        let parse_error = |e: toml::de::Error| Error::Parse {
            path: PathBuf::new(),
            message: e.to_string(),
        };
        let mut table: toml::Table = toml::from_str(text).map_err(parse_error)?;
        // `[soak]` keys of earlier versions are read and ignored (named in a warning), so an
        // old settings file still loads.
        let mut retired = Vec::new();
        if let Some(toml::Value::Table(soak)) = table.get_mut("soak") {
            for key in crate::calib::soak::RETIRED_KEYS {
                if soak.remove(*key).is_some() {
                    retired.push(format!("soak.{key}"));
                }
            }
        }
        let mut cfg: Config = table.try_into().map_err(parse_error)?;
        cfg.retired_keys = retired;
        cfg.validate()?;
        Ok(cfg)
    }

    /// Checks every value's range (also after a command-line override).
    ///
    /// # Errors
    /// The first key whose value is out of range.
    pub(crate) fn validate(&self) -> Result<(), Error> {
        self.moonraker.validate()?;
        self.ab.validate()?;
        self.http.validate()?;
        self.mesh.validate()?;
        self.soak.validate()?;
        self.backlash.validate().map_err(Error::Backlash)?;
        self.log.validate()
    }

    /// The HTTP base URL derived from the websocket URL (`ws://h:p/websocket` → `http://h:p`).
    pub(crate) fn http_base(&self) -> String {
        let url = &self.moonraker.url;
        let (scheme, rest) = ("http://", url.strip_prefix("ws://").unwrap_or(url));
        let host = rest.split('/').next().unwrap_or(rest);
        format!("{scheme}{host}")
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn empty_file_gives_the_embedded_defaults() {
        let cfg = Config::parse("").unwrap();
        assert_eq!(cfg, Config::default());
        assert_eq!(cfg.moonraker.url, "ws://127.0.0.1:7125/websocket");
        assert_eq!(cfg.http_base(), "http://127.0.0.1:7125");
    }

    #[test]
    fn the_documented_example_parses_and_equals_the_defaults() {
        let text = include_str!("../../config/klipcal.toml");
        assert_eq!(Config::parse(text).unwrap(), Config::default());
    }

    #[test]
    fn an_unknown_key_is_named_in_the_error() {
        let err = Config::parse("[moonraker]\nurll = \"ws://x/websocket\"\n").unwrap_err();
        let msg = err.to_string();
        assert!(msg.contains("urll"), "{msg}");
        assert!(msg.contains("url"), "{msg}");
    }

    #[test]
    fn a_bad_value_names_key_value_and_expectation() {
        let err = Config::parse("[moonraker]\nrequest_timeout_s = -1.0\n").unwrap_err();
        let msg = err.to_string();
        assert!(msg.contains("moonraker.request_timeout_s"), "{msg}");
        assert!(msg.contains("-1"), "{msg}");
        assert!(msg.contains("expected"), "{msg}");
        let err = Config::parse("[log]\nlevel = \"loud\"\n").unwrap_err();
        assert!(err.to_string().contains("\"loud\""));
        let err = Config::parse("[moonraker]\nurl = \"http://x\"\n").unwrap_err();
        assert!(err.to_string().contains("moonraker.url"));
    }

    #[test]
    fn a_value_of_the_wrong_type_is_an_error_naming_the_key() {
        let err = Config::parse("[moonraker]\nrequest_timeout_s = \"ten\"\n").unwrap_err();
        let msg = err.to_string();
        assert!(msg.contains("request_timeout_s"), "{msg}");
    }

    #[test]
    fn a_settings_file_that_cannot_be_read_names_its_cause_once() {
        let err = Config::load(Some(Path::new("/nonexistent/klipcal.toml"))).unwrap_err();
        let shown = format!("{:#}", anyhow::Error::new(err));
        assert_eq!(shown.matches("No such file").count(), 1, "{shown}");
        assert!(shown.contains("/nonexistent/klipcal.toml"), "{shown}");
    }
}
