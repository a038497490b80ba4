//! The [`Calibration`] trait every calibration implements, and what the hold-limit watchdog
//! needs of a waiting session ([`Hold`]). The routing over the calibrations is
//! `jobs::registry`, which holds each by its type and matches on the typed call
//! (`jobs::call::Call`); the calibrations import only this.

use std::future::Future;

use anyhow::Context;
use serde::de::DeserializeOwned;
use serde_json::Value;

use super::answer::SessionAnswer;
use super::envelope::SessionState;
use super::status::SessionStatus;
use super::table::{self, Op, OpSpec};
use crate::store::SessionRow;

/// What the hold-limit watchdog needs of a waiting session.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Hold {
    /// Unix time the hold started (the print's end, …).
    pub since_unix: f64,
    /// Longest hold, s.
    pub max_s: f64,
}

/// What a calibration declares once: its kind, its name, its states, its operations and how
/// its stored session shows in the status. Every calibration gets [`Declared`] from it.
pub trait Declare {
    /// The store's kind (`ab`, `mesh`, `backlash`).
    const KIND: &'static str;
    /// How a user calls it, with its article ("an A/B calibration").
    const TITLE: &'static str;
    /// Its session's states.
    type State: SessionState;
    /// Its stored session.
    type Session: DeserializeOwned;
    /// Its typed calls, one per operation.
    type Call: 'static;
    /// Its operations (see [`table`]).
    const OPS: &'static [Op<Self::Call>];

    /// A session as `klipcal_status` shows it.
    ///
    /// # Errors
    /// What the calibration cannot read of it.
    fn session_status(&self, s: &Self::Session) -> anyhow::Result<SessionStatus>;
}

/// A calibration's declaration as the registry reads it for every kind at once
/// (`&dyn Declared`: its kind, states and status; no call goes through it); written once,
/// for every [`Declare`].
pub trait Declared {
    /// [`Declare::KIND`].
    fn kind(&self) -> &'static str;
    /// The names of its final states (from its [`SessionState`]): the store counts a session in
    /// one of them as ended.
    fn final_states(&self) -> Vec<String>;
    /// [`Declare::TITLE`].
    fn title(&self) -> &'static str;
    /// Its operations' declarations.
    fn ops(&self) -> Vec<&'static OpSpec>;
    /// Its stored session as `klipcal_status` shows it.
    ///
    /// # Errors
    /// A damaged document.
    fn status(&self, row: &SessionRow) -> anyhow::Result<SessionStatus>;
}

impl<T: Declare> Declared for T {
    fn kind(&self) -> &'static str {
        T::KIND
    }

    fn final_states(&self) -> Vec<String> {
        T::State::final_names()
    }

    fn title(&self) -> &'static str {
        T::TITLE
    }

    fn ops(&self) -> Vec<&'static OpSpec> {
        table::specs(T::OPS).collect()
    }

    fn status(&self, row: &SessionRow) -> anyhow::Result<SessionStatus> {
        let s: T::Session = serde_json::from_value(row.doc.clone())
            .with_context(|| format!("reading stored session {}", row.id))?;
        self.session_status(&s)
    }
}

/// One calibration: its calls, its session's resume, cancel and hold. The registry holds each
/// by its type (no trait object): these are static calls.
pub trait Calibration: Declare + Send + Sync {
    /// Answers one of its calls, typed at the boundary.
    fn handle(&self, call: Self::Call) -> impl Future<Output = anyhow::Result<Value>> + Send;
    /// Picks its session up after a daemon start or reconnect.
    fn resume(&self, row: &SessionRow) -> impl Future<Output = ()> + Send;
    /// Ends its session safely (prints cancelled, heaters off, prompt closed).
    fn cancel(
        &self,
        row: &SessionRow,
        reason: &str,
    ) -> impl Future<Output = anyhow::Result<SessionAnswer>> + Send;
    /// When its session holds heaters on while waiting on the user: since when, how long.
    fn held(&self, row: &SessionRow) -> Option<Hold>;
    /// Records that the hold limit turned the heaters off.
    fn heaters_turned_off(&self, row: &SessionRow) -> impl Future<Output = ()> + Send;
    /// A camera frame it keeps for the page (`seq`, or the newest), JPEG.
    fn snapshot_jpeg(&self, _seq: Option<u64>) -> Option<Vec<u8>> {
        None
    }
    /// Runs once the daemon is connected (e.g. a follower the settings switch on).
    fn connected(&self) -> impl Future<Output = ()> + Send {
        async {}
    }
}
