//! The session core every calibration shares: stored session documents, one active session
//! and the runner (`session`), the printer guards and the dialog (`session::guards`); answers
//! and prompts on the console (`console`); the bed soak step (`soak`) and its question of the
//! bed's build (`soak_ask`); the command table and
//! the typed arguments read against it (`table`); the config transaction (`printer_config`);
//! the session envelope every stored document shares and what a calibration says of its states
//! (`envelope`); the status as typed structs (`status`);
//! the [`Calibration`] trait a calibration implements (`calibration`) and the operations every
//! daemon answers besides the calibrations' own (`ops`). Nothing here knows a calibration: the
//! routing over them is `jobs::registry`.

pub mod answer;
pub mod bed_log;
pub mod calibration;
pub mod console;
pub mod envelope;
pub mod ops;
pub mod printer_config;
pub mod session;
pub mod soak;
pub mod soak_ask;
pub mod status;
pub mod table;

pub use calibration::{Calibration, Declare, Hold};
pub use envelope::{Envelope, SessionState};
pub use ops::{CoreCall, CORE_OPS};
pub use session::Core;

/// An error a user caused (a bad reading, a command at the wrong time): the message says what
/// was wrong and what is expected. Everything else is an internal failure.
#[derive(Debug, thiserror::Error)]
#[error("{0}")]
pub struct UserError(pub String);

/// Builds a [`UserError`].
pub(crate) fn user(msg: impl Into<String>) -> anyhow::Error {
    anyhow::Error::new(UserError(msg.into()))
}

/// Whether an error is the user's (a 400 answer) rather than the daemon's.
#[must_use]
pub fn is_user_error(e: &anyhow::Error) -> bool {
    e.chain().any(|c| c.downcast_ref::<UserError>().is_some())
}
