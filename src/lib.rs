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
//!   G-code command text built from typed values, never from pasted user text.
//! - [`gcode`]: PURE. The pylon job generator (geometry → toolpaths → G-code text + layout).
//! - [`calib`]: PURE. The math: statistics, differential scale, geometry fit, error budget.
//! - [`layout`]: PURE. The `layout.json` types shared by the pylon generator and the solver.
//! - [`printer`]: the printer summary (`check`, `klipcal_status`) built from Moonraker answers.
//! - [`bench`]: benchmarks reported by `klipcal bench …` (figures beside their targets).
//! - [`soak_cmd`]: the thermal soak commands: `soak-detect` (replay a bed trace through
//!   [`calib::soak`]) and `bench soak` (simulated beds).

pub mod agent;
pub mod app;
pub mod bench;
pub mod calib;
pub mod cli;
pub mod config;
pub mod gcode;
pub mod klipper;
pub mod layout;
pub mod moonraker;
pub mod printer;
pub mod soak_cmd;
