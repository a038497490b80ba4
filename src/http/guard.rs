//! Who may use the page and API, decided from the peer address and the request's headers
//! before any handler runs: trusted address ranges or the API key; for changing requests, a
//! JSON POST addressed to this host from this host's own page (no cross-site form, no DNS
//! rebinding). Pure: headers and addresses in, a verdict out.

use std::net::IpAddr;

use axum::http::{header, HeaderMap, Method, StatusCode};

use crate::config::HttpConfig;

/// The checks, built once from `[http]`.
#[derive(Debug, Clone)]
pub(crate) struct Guard {
    trusted: Vec<ipnet::IpNet>,
    api_key: Option<String>,
    host_names: Vec<String>,
}

/// Why a request is refused: the status and a message that says what to change.
pub(crate) type Refusal = (StatusCode, String);

impl Guard {
    /// The guard for these settings.
    ///
    /// # Errors
    /// A `trusted_clients` entry that is not an address or range.
    pub(crate) fn new(cfg: &HttpConfig) -> Result<Self, crate::config::Error> {
        Ok(Self {
            trusted: cfg.trusted()?,
            api_key: (!cfg.api_key.is_empty()).then(|| cfg.api_key.clone()),
            host_names: cfg
                .host_names
                .iter()
                .map(|h| h.to_ascii_lowercase())
                .collect(),
        })
    }

    /// Allows or refuses one request.
    ///
    /// # Errors
    /// The refusal: 403 (address, key, origin, host), 405 (not POST) or 415 (not JSON).
    pub(crate) fn check(
        &self,
        peer: IpAddr,
        method: &Method,
        headers: &HeaderMap,
    ) -> Result<(), Refusal> {
        let peer = peer.to_canonical();
        let key = headers.get("x-api-key").and_then(|v| v.to_str().ok());
        let key_ok = match (&self.api_key, key) {
            (Some(want), Some(got)) => same(want.as_bytes(), got.as_bytes()),
            _ => false,
        };
        if !key_ok && !self.trusted.iter().any(|n| n.contains(&peer)) {
            let why = if key.is_some() && self.api_key.is_some() {
                "the X-Api-Key header does not match [http] api_key".to_string()
            } else {
                format!(
                    "{peer} is not in [http] trusted_clients; add its range there, or send \
                     the X-Api-Key header with [http] api_key"
                )
            };
            return Err((StatusCode::FORBIDDEN, format!("klipcal: {why}")));
        }
        if matches!(*method, Method::GET | Method::HEAD) {
            return Ok(());
        }
        if *method != Method::POST {
            return Err((
                StatusCode::METHOD_NOT_ALLOWED,
                format!("{method} is not accepted: changes are POST requests with a JSON body"),
            ));
        }
        let json = headers
            .get(header::CONTENT_TYPE)
            .and_then(|v| v.to_str().ok())
            .and_then(|v| v.split(';').next())
            .is_some_and(|t| t.trim().eq_ignore_ascii_case("application/json"));
        if !json {
            return Err((
                StatusCode::UNSUPPORTED_MEDIA_TYPE,
                "changes are accepted only as JSON (Content-Type: application/json)".into(),
            ));
        }
        let host = headers
            .get(header::HOST)
            .and_then(|v| v.to_str().ok())
            .unwrap_or("");
        if headers
            .get("sec-fetch-site")
            .and_then(|v| v.to_str().ok())
            .is_some_and(|s| s.eq_ignore_ascii_case("cross-site"))
        {
            return Err((
                StatusCode::FORBIDDEN,
                "cross-site request refused: changes come from klipcal's own page or a tool \
                 like curl"
                    .into(),
            ));
        }
        if let Some(origin) = headers.get(header::ORIGIN) {
            let origin = origin.to_str().unwrap_or("");
            let origin_host = origin.split_once("://").map_or("", |(_, h)| h);
            if origin_host.is_empty() || !origin_host.eq_ignore_ascii_case(host) {
                return Err((
                    StatusCode::FORBIDDEN,
                    format!(
                        "cross-site request refused: Origin {origin:?} is not this page \
                         (Host {host:?})"
                    ),
                ));
            }
        }
        if !self.host_allowed(host) {
            return Err((
                StatusCode::FORBIDDEN,
                format!(
                    "Host {host:?} is not a name klipcal accepts changes on; add it to \
                     [http] host_names"
                ),
            ));
        }
        Ok(())
    }

    /// IP addresses, `localhost`, single-label names, `*.local` and the configured names.
    fn host_allowed(&self, host: &str) -> bool {
        let name = if let Some(rest) = host.strip_prefix('[') {
            rest.split(']').next().unwrap_or("")
        } else {
            host.rsplit_once(':').map_or(host, |(h, port)| {
                if port.chars().all(|c| c.is_ascii_digit()) {
                    h
                } else {
                    host
                }
            })
        }
        .to_ascii_lowercase();
        if name.is_empty() {
            return false;
        }
        name.parse::<IpAddr>().is_ok()
            || name == "localhost"
            || !name.contains('.')
            || name.ends_with(".local")
            || self.host_names.contains(&name)
    }
}

/// Compares two keys in time independent of where they differ.
fn same(a: &[u8], b: &[u8]) -> bool {
    a.len() == b.len() && a.iter().zip(b).fold(0u8, |acc, (x, y)| acc | (x ^ y)) == 0
}

#[cfg(test)]
mod tests {
    use super::*;
    use axum::http::HeaderValue;

    fn guard(trusted: &[&str], key: &str) -> Guard {
        Guard::new(&HttpConfig {
            trusted_clients: trusted.iter().map(|s| (*s).to_string()).collect(),
            api_key: key.into(),
            host_names: vec!["printer.example.org".into()],
            ..HttpConfig::default()
        })
        .unwrap()
    }

    fn headers(pairs: &[(&'static str, &str)]) -> HeaderMap {
        let mut h = HeaderMap::new();
        for (k, v) in pairs {
            h.insert(*k, HeaderValue::from_str(v).unwrap());
        }
        h
    }

    fn post_json(host: &str) -> HeaderMap {
        headers(&[("content-type", "application/json"), ("host", host)])
    }

    #[test]
    fn an_address_outside_the_trusted_ranges_is_refused_unless_it_brings_the_key() {
        let g = guard(&["127.0.0.1/32"], "s3cret");
        let lan: IpAddr = "192.168.1.20".parse().unwrap();
        let (code, msg) = g.check(lan, &Method::GET, &HeaderMap::new()).unwrap_err();
        assert_eq!(code, StatusCode::FORBIDDEN);
        assert!(
            msg.contains("192.168.1.20") && msg.contains("trusted_clients"),
            "{msg}"
        );
        assert!(g
            .check(lan, &Method::GET, &headers(&[("x-api-key", "s3cret")]))
            .is_ok());
        let (_, msg) = g
            .check(lan, &Method::GET, &headers(&[("x-api-key", "guess")]))
            .unwrap_err();
        assert!(msg.contains("does not match"), "{msg}");
        assert!(g
            .check(
                "127.0.0.1".parse().unwrap(),
                &Method::GET,
                &HeaderMap::new()
            )
            .is_ok());
    }

    #[test]
    fn the_default_ranges_are_what_moonraker_trusts_and_mapped_ipv4_counts_as_ipv4() {
        let g = Guard::new(&HttpConfig::default()).unwrap();
        for ok in [
            "127.0.0.1",
            "10.1.2.3",
            "172.20.0.5",
            "192.168.0.9",
            "169.254.3.3",
            "::1",
            "fe80::1",
            "::ffff:192.168.1.5",
        ] {
            assert!(
                g.check(ok.parse().unwrap(), &Method::GET, &HeaderMap::new())
                    .is_ok(),
                "{ok}"
            );
        }
        for bad in ["8.8.8.8", "172.32.0.1", "2001:db8::1", "::ffff:8.8.8.8"] {
            assert!(
                g.check(bad.parse().unwrap(), &Method::GET, &HeaderMap::new())
                    .is_err(),
                "{bad}"
            );
        }
    }

    #[test]
    fn changes_must_be_json_posts_from_this_page() {
        let g = guard(&["127.0.0.0/8"], "");
        let me: IpAddr = "127.0.0.1".parse().unwrap();
        assert!(g
            .check(me, &Method::POST, &post_json("127.0.0.1:7150"))
            .is_ok());
        // A form post (what a cross-site page can send without asking) is refused.
        let form = headers(&[
            ("content-type", "application/x-www-form-urlencoded"),
            ("host", "127.0.0.1:7150"),
        ]);
        assert_eq!(
            g.check(me, &Method::POST, &form).unwrap_err().0,
            StatusCode::UNSUPPORTED_MEDIA_TYPE
        );
        assert_eq!(
            g.check(me, &Method::PUT, &post_json("h")).unwrap_err().0,
            StatusCode::METHOD_NOT_ALLOWED
        );
        let mut cross = post_json("127.0.0.1:7150");
        cross.insert("origin", HeaderValue::from_static("http://evil.example"));
        let (code, msg) = g.check(me, &Method::POST, &cross).unwrap_err();
        assert_eq!(code, StatusCode::FORBIDDEN);
        assert!(msg.contains("evil.example"), "{msg}");
        let mut same_page = post_json("127.0.0.1:7150");
        same_page.insert("origin", HeaderValue::from_static("http://127.0.0.1:7150"));
        assert!(g.check(me, &Method::POST, &same_page).is_ok());
        let mut fetch_meta = post_json("127.0.0.1:7150");
        fetch_meta.insert("sec-fetch-site", HeaderValue::from_static("cross-site"));
        assert!(g.check(me, &Method::POST, &fetch_meta).is_err());
    }

    #[test]
    fn changes_addressed_to_a_foreign_dns_name_are_refused_against_rebinding() {
        let g = guard(&["0.0.0.0/0"], "");
        let me: IpAddr = "192.168.1.2".parse().unwrap();
        for ok in [
            "192.168.1.9:7150",
            "[fe80::1]:7150",
            "localhost:7150",
            "voron:7150",
            "voron.local",
            "printer.example.org:7150",
        ] {
            assert!(g.check(me, &Method::POST, &post_json(ok)).is_ok(), "{ok}");
        }
        let (code, msg) = g
            .check(me, &Method::POST, &post_json("attacker.example.com:7150"))
            .unwrap_err();
        assert_eq!(code, StatusCode::FORBIDDEN);
        assert!(msg.contains("host_names"), "{msg}");
        // Reading is not a change: GET is not held to the host rule.
        assert!(g
            .check(
                me,
                &Method::GET,
                &headers(&[("host", "attacker.example.com")])
            )
            .is_ok());
    }

    #[test]
    fn a_bad_trusted_range_is_named_at_load() {
        let e = crate::config::Config::parse("[http]\ntrusted_clients = [\"192.168.1.0/33\"]\n")
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("http.trusted_clients") && e.contains("192.168.1.0/33"),
            "{e}"
        );
        let e = crate::config::Config::parse("[http]\nbind = \"7150\"\n")
            .unwrap_err()
            .to_string();
        assert!(e.contains("http.bind"), "{e}");
    }
}
