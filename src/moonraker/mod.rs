//! The Moonraker client: protocol types (pure, `protocol`), the websocket actor that owns the
//! socket (`connection`), the cloneable handle every task uses (`client`) with its typed
//! queries (`queries`, answers typed in `answers`), HTTP file transfer (`http`), and klipcal's
//! console scripts straight to Klipper's API socket when it is the one Moonraker uses (`klippy`). It knows
//! nothing of calibrations: it carries requests, replies, notifications and agent calls.

pub mod answers;
mod client;
mod connection;
mod http;
mod klippy;
pub mod protocol;
mod queries;

pub use answers::ConfigFile;
pub use client::{AgentCall, ClientOptions, ConnState, Event, Moonraker};
pub use http::Files;
pub(crate) use klippy::ONLINE_MACRO;
pub use protocol::RpcError;

/// Everything that can go wrong talking to Moonraker.
#[derive(Debug, thiserror::Error)]
pub enum Error {
    /// Not connected to Moonraker right now (it is retried in the background).
    #[error("not connected to Moonraker at {0}")]
    NotConnected(String),
    /// Moonraker answered with an error.
    #[error("Moonraker refused `{method}`: {message} (code {code})")]
    Rpc {
        /// The method called.
        method: String,
        /// Moonraker's code.
        code: i64,
        /// Moonraker's message (Klipper's error text for G-code).
        message: String,
    },
    /// No reply within the configured time.
    #[error("no reply from Moonraker to `{method}` within {timeout_s} s")]
    Timeout {
        /// The method called.
        method: String,
        /// The limit that passed.
        timeout_s: f64,
    },
    /// The connection dropped before the reply came.
    #[error("connection to Moonraker lost while waiting for `{0}`")]
    Disconnected(String),
    /// The daemon is shutting down.
    #[error("klipcal is shutting down")]
    Shutdown,
    /// Moonraker sent something that is not JSON-RPC, or not what was expected.
    #[error("unexpected data from Moonraker: {0}")]
    Protocol(String),
    /// An HTTP request failed.
    #[error("HTTP {method} {url}: {message}")]
    Http {
        /// GET or POST.
        method: &'static str,
        /// The URL.
        url: String,
        /// What went wrong, with Moonraker's message when it sent one.
        message: String,
    },
}

impl Error {
    /// Whether the error came from Moonraker or Klipper refusing the request (as opposed to
    /// the connection).
    pub fn is_refusal(&self) -> bool {
        matches!(self, Error::Rpc { .. })
    }

    /// Whether the error says Moonraker could not be reached rather than that a request went
    /// wrong: no connection or a lost one, or no reply (a timeout, an HTTP transfer failing)
    /// while the websocket is down (`connected` is the connection's state now). An outage is
    /// waited out; every other error is a real failure.
    #[must_use]
    pub(crate) fn is_unreachable(&self, connected: bool) -> bool {
        match self {
            Error::NotConnected(_) | Error::Disconnected(_) => true,
            Error::Timeout { .. } | Error::Http { .. } => !connected,
            Error::Rpc { .. } | Error::Shutdown | Error::Protocol(_) => false,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::Error;

    #[test]
    fn only_a_lost_connection_or_no_answer_while_down_is_an_outage() {
        let timeout = Error::Timeout {
            method: "printer.objects.query".into(),
            timeout_s: 30.0,
        };
        let refused = Error::Rpc {
            method: "printer.gcode.script".into(),
            code: 400,
            message: "Must home axis first".into(),
        };
        for connected in [true, false] {
            assert!(
                Error::NotConnected("ws://x (connection refused)".into()).is_unreachable(connected)
            );
            assert!(Error::Disconnected("printer.info".into()).is_unreachable(connected));
            assert!(!refused.is_unreachable(connected));
            assert!(!Error::Shutdown.is_unreachable(connected));
        }
        // A request that hangs while connected is a real failure; without a connection, it is
        // the outage.
        assert!(!timeout.is_unreachable(true));
        assert!(timeout.is_unreachable(false));
    }
}
