//! The only place where Moonraker I/O meets the math. The session core every calibration
//! shares ([`core`](self::core): stored documents, one active session, the runner, the printer
//! guards, console and prompts, the bed soak, the command table, the config transaction, the
//! [`Calibration`] trait); one folder per calibration, each reading like a klippy/extras module
//! (`ab`, `backlash`, `mesh`); and `registry`, the one module that lists the calibrations:
//! routing, status, cancel, resume, the hold watchdog. The calibrations import the core, never
//! the registry.

pub mod ab;
pub mod backlash;
mod call;
pub mod core;
pub mod mesh;
pub mod registry;

// The core's modules at their former paths (`jobs::table`, …), for callers outside `jobs`.
pub use self::core::{console, printer_config, soak, table};

pub(crate) use self::core::user;
pub use self::core::{is_user_error, Core};
pub(crate) use call::{Call, Route};
pub use registry::Calibrations;
