//! `[http]`: the daemon's page and API settings, their defaults and checks.

use serde::Deserialize;

use super::Error;

/// `[http]`: the daemon's page and API (`src/http/`).
#[derive(Debug, Clone, Deserialize, PartialEq)]
#[serde(default, deny_unknown_fields)]
pub struct HttpConfig {
    /// Serve the page and API at all.
    pub enabled: bool,
    /// Address and port to listen on; `0.0.0.0:7150` listens on the LAN.
    pub bind: String,
    /// Addresses (CIDR ranges) allowed without an API key; the default is what a standard
    /// Moonraker install trusts: loopback, the private ranges, link-local.
    pub trusted_clients: Vec<String>,
    /// When set, a request carrying `X-Api-Key: <this>` is allowed from any address.
    pub api_key: String,
    /// Host names (besides IP addresses, `localhost`, single-label names and `*.local`) a
    /// changing request may be addressed to: a guard against DNS rebinding.
    pub host_names: Vec<String>,
}

impl Default for HttpConfig {
    fn default() -> Self {
        Self {
            enabled: true,
            bind: "0.0.0.0:7150".into(),
            trusted_clients: [
                "127.0.0.0/8",
                "10.0.0.0/8",
                "172.16.0.0/12",
                "192.168.0.0/16",
                "169.254.0.0/16",
                "::1/128",
                "fe80::/10",
            ]
            .iter()
            .map(|s| (*s).to_string())
            .collect(),
            api_key: String::new(),
            host_names: Vec::new(),
        }
    }
}

impl HttpConfig {
    /// The trusted ranges, parsed.
    ///
    /// # Errors
    /// An entry that is not an address or a CIDR range.
    pub(crate) fn trusted(&self) -> Result<Vec<ipnet::IpNet>, Error> {
        self.trusted_clients
            .iter()
            .map(|t| {
                t.parse::<ipnet::IpNet>()
                    .or_else(|_| t.parse::<std::net::IpAddr>().map(ipnet::IpNet::from))
                    .map_err(|_| Error::Invalid {
                        key: "http.trusted_clients",
                        value: format!("{t:?}"),
                        expected: "addresses or CIDR ranges such as \"192.168.1.0/24\" or \"::1\"",
                    })
            })
            .collect()
    }

    /// Checks the `[http]` values.
    ///
    /// # Errors
    /// The first key whose value is out of range.
    pub(super) fn validate(&self) -> Result<(), Error> {
        if self.bind.parse::<std::net::SocketAddr>().is_err() {
            return Err(Error::Invalid {
                key: "http.bind",
                value: format!("{:?}", self.bind),
                expected: "an address and port such as \"0.0.0.0:7150\" or \"127.0.0.1:7150\"",
            });
        }
        self.trusted()?;
        if let Some(h) = self.host_names.iter().find(|h| {
            h.is_empty()
                || !h
                    .chars()
                    .all(|c| c.is_ascii_alphanumeric() || c == '.' || c == '-')
        }) {
            return Err(Error::Invalid {
                key: "http.host_names",
                value: format!("{h:?}"),
                expected: "host names such as \"printer.example.org\"",
            });
        }
        Ok(())
    }
}
