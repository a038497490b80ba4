//! What an operation answers, typed: each handler returns a struct deriving `Serialize` (these
//! shared ones, or its calibration's own beside it) whose `message` the console shows; the
//! registry serializes it once (`reply`), into the JSON the page, the API and the agent's
//! HTTP callers read.

use serde::Serialize;
use serde_json::Value;

/// A message alone (the dialogs' helpers, the soak question's answer without a bed).
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Said {
    /// What the console shows.
    pub message: String,
}

/// A session's step: which session, the state it is in now, what happened.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct SessionAnswer {
    /// The session's id.
    pub session: i64,
    /// Its state now.
    pub state: String,
    /// What the console shows.
    pub message: String,
}

/// A handler's typed answer as the JSON every caller reads.
///
/// # Errors
/// The handler's error, or an answer that cannot be written as JSON.
pub(crate) fn reply<T: Serialize>(answer: anyhow::Result<T>) -> anyhow::Result<Value> {
    Ok(serde_json::to_value(answer?)?)
}
