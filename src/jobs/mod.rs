//! The only place where Moonraker I/O meets the math: one state machine per calibration,
//! persisted in the store before each step acts, resumed after any restart.

pub mod ab;
pub mod printer_config;

pub use ab::Jobs;

/// An error a user caused (a bad reading, a command at the wrong time): the message says what
/// was wrong and what is expected. Everything else is an internal failure.
#[derive(Debug, thiserror::Error)]
#[error("{0}")]
pub struct UserError(pub String);

/// Builds a [`UserError`].
pub(crate) fn user(msg: impl Into<String>) -> anyhow::Error {
    anyhow::Error::new(UserError(msg.into()))
}
