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
//!   (`queries`, answers typed in `answers`), the agent's remote methods, HTTP file transfer.
//! - [`jobs`]: the only place Moonraker I/O meets the math. `jobs::core`, the session core
//!   every calibration shares (stored sessions, one active session, runner, printer guards,
//!   console and prompts, bed soak, the command table, config transaction, the `Calibration`
//!   trait, the session envelope and its `SessionState` trait, the typed status); one folder per calibration (`jobs::ab`, `jobs::mesh`: capture, import, follow,
//!   check; `jobs::backlash`: guide, dual carriage, apply, the camera — its steps, `webcam`,
//!   `frames` — and the click flow); and `jobs::registry`, the one module
//!   that lists the calibrations (routing, status, cancel, resume, the hold watchdog). The
//!   calibrations import the core, never the registry.
//! - [`klipper`]: PURE. Klipper config text (parse, includes, edit one value in place),
//!   G-code command text built from typed values, never from pasted user text, and the bed's
//!   history read from klippy.log text. Files reach it through the `klipper::Files` trait;
//!   [`fsio`] is the small std::fs implementation.
//! - [`gcode`]: PURE. The pylon job generator (printer facts → geometry → toolpaths → G-code
//!   text + layout).
//! - [`calib`]: PURE. The math: statistics, differential scale, geometry fit, error budget,
//!   thermal soak detection (`calib::soak`: settings, `stack` presets, `coupling`
//!   identification, `detector` and its `decide` test, `nnls`), the bed-mesh fit and the frame
//!   temperature of each probe point.
//! - [`layout`]: PURE. The `layout.json` types shared by the pylon generator and the solver.
//! - [`plots`]: PURE. The plots people look at (bed soak with its fitted decay, convergence
//!   over rounds) as SVG text, drawn with plotters.
//! - [`http`]: the daemon's own page and JSON API (axum): the address/key/origin guard in front,
//!   every operation through `agent::dispatch`, the same checks and messages as the macros.
//!   `http::page`: the page's frame, one file per calibration's section (`ab`, `mesh`,
//!   `backlash`) and its inline style and script (`assets`).
//! - [`printer`]: the printer summary (`check`, `klipcal_status`) built from Moonraker answers.
//! - [`store`]: sessions and readings in an embedded SQLite database, written before each step acts.
//! - [`cmd`]: the offline commands, each a thin shell: `pylons`, `solve`, `soak-detect`,
//!   `mesh fit` / `mesh profiles`, `backlash solve`, the benchmarks of `klipcal bench …`
//!   (figures beside their targets), and `install`/`uninstall` (`cmd::install`: the pure
//!   `plan`, then `files`, `manifest`, `host`, `webcam`, `uninstall`). `cmd::backlash`: the
//!   offline `backlash solve`/`image`, then its bench's simulated axes and people (`models`),
//!   the guided bench (`guided`) and the camera and click bench (`camera`).

pub mod agent;
pub mod app;
pub mod calib;
pub mod cli;
pub mod cmd;
pub mod config;
pub mod fsio;
pub mod gcode;
pub mod http;
pub mod jobs;
pub mod klipper;
pub mod layout;
pub mod moonraker;
pub mod plots;
pub mod printer;
pub mod store;
