//! klipcal: a calibration daemon for Klipper printers, run beside Moonraker as an agent.
//!
//! The architecture map, one paragraph per module. Data flows one way:
//! Moonraker → [`jobs`] (which asks the pure [`calib`], [`gcode`] and [`klipper`] functions)
//! → [`store`] → back out through [`moonraker`] (G-code, uploads) and the agent's answers.
//!
//! - [`cli`]: clap definitions of every command (`serve`, `check`, the offline commands).
//! - [`app`]: builds the daemon, owns the tasks and the shutdown token; runs each command.
//! - [`agent`]: the remote methods macros and HTTP callers reach; `agent::dispatch` is the one
//!   entry point behind them; answers on the console (RESPOND) or in JSON.
//! - [`config`]: daemon settings, TOML with embedded defaults; unknown keys are errors. One file
//!   per section (`ab`, `mesh`, `backlash`, `http`, `daemon`), each checking its own ranges.
//! - [`moonraker`]: the Moonraker client — protocol types (pure), the websocket actor that owns
//!   the socket (`connection`), the cloneable handle (`client`) and its typed queries
//!   (`queries`, answers typed in `answers`), the agent's remote methods, HTTP file transfer,
//!   and klipcal's console scripts straight to Klipper's API socket (`klippy`).
//! - [`jobs`]: the only place Moonraker I/O meets the math. `jobs::core`, the session core
//!   every calibration shares (stored sessions, one active session, runner, printer guards,
//!   console and prompts, bed soak, the command table, config transaction, the `Calibration`
//!   trait, the session envelope and its `SessionState` trait, the typed status); one folder per calibration (`jobs::ab`, `jobs::mesh`: capture, import, follow,
//!   check; `jobs::backlash`: guide, dual carriage, apply, the camera — its steps, `webcam`,
//!   `frames` — and the click flow); `jobs::call`, the one parse of a method or path into a
//!   typed `Call`; and `jobs::registry`, the one module that lists the calibrations (matching
//!   the call, status, cancel, resume, the hold watchdog). The calibrations import the core,
//!   never the registry.
//! - [`calib`], [`gcode`], [`klipper`], [`layout`], [`plots`]: PURE, the `klipcal-core` crate
//!   (crates/klipcal-core), re-exported here under the paths the daemon has always used. Its
//!   dependencies have no I/O crate (a test walks Cargo.lock): the calibration math (statistics,
//!   differential scale, geometry fit, error budget, bed soak, thermal mesh, backlash, the nozzle
//!   in a picture), the pylon G-code, Klipper's config text (read by Klipper's rules or Kalico's, `klipper::Dialect`) and G-code command text built from
//!   typed values, the plots. Files reach it through the `klipper::Files` trait; [`fsio`] is
//!   the small std::fs implementation.
//! - [`http`]: the daemon's own page and JSON API (axum): the address/key/origin guard in front,
//!   every operation through `agent::dispatch`, the same checks and messages as the macros.
//!   `http::page`: the page's frame, one file per calibration's section (`ab`, `mesh`,
//!   `backlash`) and its inline style and script (`assets`).
//! - [`printer`]: the printer summary (`check`, `klipcal_status`) built from Moonraker answers.
//! - [`store`]: sessions and readings in an embedded SQLite database, written before each step acts.
//! - [`cmd`]: the offline commands, each a thin shell: `pylons`, `solve`, `soak-detect`,
//!   `mesh fit` / `mesh profiles`, `backlash solve` / `image`, and `install`/`uninstall`
//!   (`cmd::install`: the pure `plan`, then `files`, `manifest`, `host`, `webcam`,
//!   `uninstall`). The benchmarks and every simulator are in their own crate
//!   (crates/klipcal-bench, binary `klipcal-bench`; `klipcal bench …` runs it from a checkout).

pub mod agent;
pub mod app;
pub mod cli;
pub mod cmd;
pub mod config;
#[cfg(test)]
mod doc_images;
pub mod fsio;
pub mod http;
pub mod jobs;
pub mod moonraker;
pub mod printer;
pub mod store;

// The pure core, its own crate (`crates/klipcal-core`), under the paths the daemon has always
// used.
pub use klipcal_core::{calib, gcode, klipper, layout, plots};
