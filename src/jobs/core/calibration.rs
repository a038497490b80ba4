//! The [`Calibration`] trait every calibration implements, and what the hold-limit watchdog
//! needs of a waiting session ([`Hold`]). The routing over the calibrations is
//! `jobs::registry`, which lists them; the calibrations import only this.

use futures_util::future::BoxFuture;
use serde_json::Value;

use super::table::OpSpec;
use crate::store::SessionRow;

/// What the hold-limit watchdog needs of a waiting session.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Hold {
    /// Unix time the hold started (the print's end, …).
    pub since_unix: f64,
    /// Longest hold, s.
    pub max_s: f64,
}

/// One calibration: its remote methods, its session's resume, cancel and status.
pub trait Calibration: Send + Sync {
    /// The store's kind (`ab`, `mesh`, `backlash`).
    fn kind(&self) -> &'static str;
    /// The names of its final states (from its [`super::envelope::SessionState`]): the store
    /// counts a session in one of them as ended.
    fn final_states(&self) -> Vec<String>;
    /// How a user calls it, with its article ("an A/B calibration").
    fn title(&self) -> &'static str;
    /// Its operations (see [`table`]).
    fn ops(&self) -> Vec<&'static OpSpec>;
    /// Answers the remote method of one of [`Calibration::ops`].
    fn call<'a>(&'a self, method: &'a str, args: &'a Value)
        -> BoxFuture<'a, anyhow::Result<Value>>;
    /// Picks its session up after a daemon start or reconnect.
    fn resume<'a>(&'a self, row: &'a SessionRow) -> BoxFuture<'a, ()>;
    /// Ends its session safely (prints cancelled, heaters off, prompt closed).
    fn cancel<'a>(
        &'a self,
        row: &'a SessionRow,
        reason: &'a str,
    ) -> BoxFuture<'a, anyhow::Result<Value>>;
    /// Its session as `klipcal_status` shows it.
    ///
    /// # Errors
    /// A damaged document.
    fn status(&self, row: &SessionRow) -> anyhow::Result<super::status::SessionStatus>;
    /// When its session holds heaters on while waiting on the user: since when, how long.
    fn held(&self, row: &SessionRow) -> Option<Hold>;
    /// Records that the hold limit turned the heaters off.
    fn heaters_turned_off<'a>(&'a self, row: &'a SessionRow) -> BoxFuture<'a, ()>;
    /// A camera frame it keeps for the page (`seq`, or the newest), JPEG.
    fn snapshot_jpeg(&self, _seq: Option<u64>) -> Option<Vec<u8>> {
        None
    }
    /// Runs once the daemon is connected (e.g. a follower the settings switch on).
    fn connected(&self) -> BoxFuture<'_, ()> {
        Box::pin(async {})
    }
}
