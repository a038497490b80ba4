//! klipcal: a calibration daemon for Klipper printers, run beside Moonraker as an agent.
//!
//! The architecture map, one paragraph per module. Data flows one way:
//! Moonraker → [`jobs`] (which asks the pure [`calib`], [`gcode`] and [`klipper`] functions)
//! → [`store`] → back out through [`moonraker`] (G-code, uploads) and [`http`].
//!
//! - [`cli`]: clap definitions of every command (`serve`, `check`, the offline commands).
//! - [`agent`]: the remote methods macros and HTTP callers reach; answers on the console or in JSON.
//! - [`app`]: builds the daemon, owns the tasks and the shutdown token; runs each command.
//! - [`config`]: daemon settings, TOML with embedded defaults; unknown keys are errors.
//! - [`moonraker`]: the Moonraker client — protocol types (pure), the websocket actor that owns
//!   the socket, the cloneable handle, the agent's remote methods, HTTP file transfer.
//! - [`klipper`]: PURE. Klipper config text (parse, includes, edit one value in place) and
//!   G-code command text built from typed values, never from pasted user text. Files reach it
//!   through the `klipper::Files` trait; [`fsio`] is the small std::fs implementation.
//! - [`gcode`]: PURE. The pylon job generator (geometry → toolpaths → G-code text + layout).
//! - [`calib`]: PURE. The math: statistics, differential scale, geometry fit, error budget.
//! - [`pylons_cmd`]: `klipcal pylons` — reads the Klipper config, runs [`gcode`], writes the files.
//! - [`jobs`]: the only place Moonraker I/O meets the math: one persisted state machine per calibration.
//! - [`layout`]: PURE. The `layout.json` types shared by the pylon generator and the solver.
//! - [`printer`]: the printer summary (`check`, `klipcal_status`) built from Moonraker answers.
//! - [`store`]: sessions and readings in an embedded SQLite database, written before each step acts.
//! - [`bench`]: benchmarks reported by `klipcal bench …` (figures beside their targets).
//! - [`solve_cmd`]: `klipcal solve` — reads layout, readings and printer config, prints the
//!   pure solver's result.
//! - [`backlash_cmd`]: `backlash solve` (camera readings → per-axis backlash) and
//!   `bench backlash` (the guided procedure on simulated axes and people).
//! - [`soak_cmd`]: the thermal soak commands: `soak-detect` (replay a bed trace through
//!   [`calib::soak`]) and `bench soak` (simulated beds).

pub mod agent;
pub mod app;
pub mod backlash_cmd;
pub mod bench;
pub mod calib;
pub mod cli;
pub mod config;
pub mod fsio;
pub mod gcode;
pub mod jobs;
pub mod klipper;
pub mod layout;
pub mod moonraker;
pub mod printer;
pub mod pylons_cmd;
pub mod soak_cmd;
pub mod solve_cmd;
pub mod store;
