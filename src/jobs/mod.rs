//! The only place where Moonraker I/O meets the math. A session core every calibration shares
//! (`session`: stored documents, one active session, the runner, the printer guards; `console`:
//! answers and prompts; `soak`: the bed soak step; `table`: the command table and the typed arguments read against it; `printer_config`:
//! the config transaction; `registry`: routing, status, cancel, resume, the hold watchdog), and
//! one file per calibration, each reading like a klippy/extras module: `ab`, `backlash`, `mesh`.

pub mod ab;
pub mod backlash;
pub mod console;
pub mod mesh;
pub mod printer_config;
pub mod registry;
pub mod session;
pub mod soak;
pub mod table;

pub use registry::{Calibration, Calibrations};
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
