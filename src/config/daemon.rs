//! `[moonraker]`, `[log]`, `[daemon]`: how the daemon reaches Moonraker, logs, and where it
//! keeps its files.

use serde::Deserialize;

use super::Error;

/// `[moonraker]`
#[derive(Debug, Clone, Deserialize, PartialEq)]
#[serde(default, deny_unknown_fields)]
pub struct MoonrakerConfig {
    /// Websocket URL, `ws://host:port/websocket`.
    pub url: String,
    /// API key, sent when Moonraker requires authorization; empty for none.
    pub api_key: String,
    /// How long one request may wait for its reply.
    pub request_timeout_s: f64,
    /// First reconnect delay.
    pub reconnect_min_s: f64,
    /// Cap of the exponential reconnect backoff.
    pub reconnect_max_s: f64,
}

/// `[log]`
#[derive(Debug, Clone, Deserialize, PartialEq)]
#[serde(default, deny_unknown_fields)]
pub struct LogConfig {
    /// `error`, `warn`, `info`, `debug` or `trace`; `RUST_LOG` overrides.
    pub level: String,
}

/// `[daemon]`
#[derive(Debug, Clone, Deserialize, PartialEq)]
#[serde(default, deny_unknown_fields)]
pub struct DaemonConfig {
    /// Where the daemon keeps its database; `~` expands to the home folder.
    pub data_dir: String,
}

impl Default for MoonrakerConfig {
    fn default() -> Self {
        Self {
            url: "ws://127.0.0.1:7125/websocket".into(),
            api_key: String::new(),
            request_timeout_s: 30.0,
            reconnect_min_s: 0.5,
            reconnect_max_s: 30.0,
        }
    }
}

impl Default for LogConfig {
    fn default() -> Self {
        Self {
            level: "info".into(),
        }
    }
}

impl Default for DaemonConfig {
    fn default() -> Self {
        Self {
            data_dir: "~/printer_data/klipcal".into(),
        }
    }
}

impl MoonrakerConfig {
    /// Checks the `[moonraker]` values.
    ///
    /// # Errors
    /// The first key whose value is out of range.
    pub(super) fn validate(&self) -> Result<(), Error> {
        let m = self;
        if m.url.starts_with("wss://") {
            return Err(Error::Invalid {
                key: "moonraker.url",
                value: format!("{:?}", m.url),
                expected: "a plain ws:// URL: klipcal runs on the printer host and talks to \
                           Moonraker over loopback (\"ws://127.0.0.1:7125/websocket\"); TLS \
                           is not built in",
            });
        }
        if !m.url.starts_with("ws://") {
            return Err(Error::Invalid {
                key: "moonraker.url",
                value: format!("{:?}", m.url),
                expected: "a websocket URL such as \"ws://127.0.0.1:7125/websocket\"",
            });
        }
        let positive = [
            ("moonraker.request_timeout_s", m.request_timeout_s),
            ("moonraker.reconnect_min_s", m.reconnect_min_s),
            ("moonraker.reconnect_max_s", m.reconnect_max_s),
        ];
        for (key, v) in positive {
            if !(v.is_finite() && v > 0.0 && v <= 86_400.0) {
                return Err(Error::Invalid {
                    key,
                    value: v.to_string(),
                    expected: "a number of seconds above 0 and at most 86400",
                });
            }
        }
        if m.reconnect_max_s < m.reconnect_min_s {
            return Err(Error::Invalid {
                key: "moonraker.reconnect_max_s",
                value: m.reconnect_max_s.to_string(),
                expected: "a value not below moonraker.reconnect_min_s",
            });
        }
        Ok(())
    }
}

impl LogConfig {
    /// Checks the `[log]` level.
    ///
    /// # Errors
    /// The first key whose value is out of range.
    pub(super) fn validate(&self) -> Result<(), Error> {
        if !["error", "warn", "info", "debug", "trace"].contains(&self.level.as_str()) {
            return Err(Error::Invalid {
                key: "log.level",
                value: format!("{:?}", self.level),
                expected: "one of \"error\", \"warn\", \"info\", \"debug\", \"trace\"",
            });
        }
        Ok(())
    }
}
