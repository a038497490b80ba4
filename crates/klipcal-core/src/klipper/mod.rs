//! PURE: Klipper config files (parse, follow includes, edit one value in place, the SAVE_CONFIG
//! block) and G-code command text built from typed values. No I/O beyond what callers pass in.
//!
//! - [`backlash`]: backlash compensation branches (PR 7259's `[backlash_compensation]`, PR 7157's
//!   `[backlash]`): detection, `SET_BACKLASH_COMPENSATION` and its reply, config values.
//! - [`bed_mesh`]: bed-mesh profiles read and written as Klipper does; VGB profile names.
//! - [`config`]: the parser ([`Config::load`] over a [`Files`] reader) with source positions.
//! - [`kalico`]: where Kalico's configfile reads differently ([`Dialect::Kalico`]: `${…}`
//!   references, `!!include` in values, recursive `**` includes) and its refusals said plainly.
//! - [`files`]: the [`Files`] trait, the in-memory [`MemFiles`], Python-compatible globbing.
//! - [`edit`]: [`set_value`] / [`set_values`]: values replaced in place in the files Klipper
//!   reads them from.
//! - [`plan`]: [`plan_values`]: AWD companions scaled together, and values that live in files
//!   klipcal must not touch written to `klipcal_overrides.cfg` instead.
//! - [`gcode_cmd`]: [`GcodeCmd`] and helpers (`SET_SKEW`, `RESPOND`, …): G-code lines from
//!   typed values, names checked against `[A-Za-z0-9_.-]`, numbers without exponents.
//! - [`start_macro`]: [`find_start_macro`], the start macro the slicer calls (configured,
//!   `PRINT_START` or `START_PRINT`).
//! - [`klippy_log`]: the bed's history in a klippy.log (`Stats` lines, the config dump's
//!   `[heater_bed]` max_power and control), per start of Klipper.
//! - [`facts`]: [`PrinterFacts`], the few settings klipcal needs, from a [`Config`] or from
//!   Moonraker's `configfile.config` JSON through one code path.

pub mod backlash;
pub mod bed_mesh;
pub mod config;
pub mod edit;
pub mod facts;
pub mod files;
pub mod gcode_cmd;
pub mod kalico;
pub mod klippy_log;
pub mod plan;
pub mod start_macro;

use std::path::PathBuf;

pub use config::Config;
pub use edit::set_values;
pub use facts::{Kinematics, PrinterFacts, Stepper};
pub use files::{Files, MemFiles};
pub use gcode_cmd::GcodeCmd;
pub use kalico::Dialect;
pub use plan::{add_include, plan_values, Protected};
pub use start_macro::{find_start_macro, StartMacro};

/// Klipper's options as written (`configfile.config`): section → option → text.
pub type RawConfig = std::collections::BTreeMap<String, std::collections::BTreeMap<String, String>>;

/// Everything that can go wrong reading Klipper config text or building G-code text.
#[derive(Debug, thiserror::Error)]
pub enum Error {
    /// A file could not be read (or a folder listed while globbing).
    #[error("cannot read Klipper config file {path}: {cause}")]
    Read {
        /// The file or glob pattern.
        path: PathBuf,
        /// The I/O error. In the message, and deliberately not the error's `source()`: a `{:#}`
        /// chain would print it twice.
        cause: std::io::Error,
    },
    /// `[include x]` without wildcards naming a file that does not exist.
    #[error(
        "{path} line {line}: include file '{pattern}' does not exist \
         (an include without wildcards must name an existing file)"
    )]
    IncludeNotFound {
        /// The including file.
        path: PathBuf,
        /// 1-based line of the `[include]`.
        line: usize,
        /// The resolved pattern.
        pattern: PathBuf,
    },
    /// A file includes itself, directly or through others.
    #[error("recursive include of config file '{path}' (include chain: {chain})")]
    IncludeCycle {
        /// The file included again.
        path: PathBuf,
        /// The include chain, outermost first.
        chain: String,
    },
    /// A line Klipper's parser rejects.
    #[error("{path} line {line}: {message}")]
    Syntax {
        /// The file.
        path: PathBuf,
        /// 1-based line.
        line: usize,
        /// What is wrong and what is expected.
        message: String,
    },
    /// A section klipcal needs is absent.
    #[error("the Klipper config has no [{section}] section; {expected}")]
    MissingSection {
        /// Section name.
        section: String,
        /// Why it is needed.
        expected: String,
    },
    /// A required option is absent.
    #[error("[{section}] has no '{key}' option; expected {expected}")]
    MissingOption {
        /// Section name.
        section: String,
        /// Option name.
        key: String,
        /// What a valid value looks like.
        expected: String,
    },
    /// An option's value cannot be used.
    #[error("[{section}] {key} = '{value}' is not valid; expected {expected}")]
    BadValue {
        /// Section name.
        section: String,
        /// Option name.
        key: String,
        /// The raw value.
        value: String,
        /// What a valid value looks like.
        expected: String,
    },
    /// The option to edit is not defined in any file.
    #[error("[{section}] {key} is not defined in any config file; klipcal only changes existing options (add it by hand first)")]
    NotDefined {
        /// Section name.
        section: String,
        /// Option name.
        key: String,
    },
    /// The option to edit spans several lines.
    #[error("[{section}] {key} spans lines {first_line}-{last_line} of {path}; klipcal only edits one-line values")]
    MultiLineValue {
        /// Section name.
        section: String,
        /// Option name.
        key: String,
        /// File holding it.
        path: PathBuf,
        /// First line.
        first_line: usize,
        /// Last line.
        last_line: usize,
    },
    /// The option's value is a Kalico reference (`${constants.rd_x}`): klipcal does not edit
    /// through it.
    #[error(
        "[{section}] {key} is written as '{written}', which Kalico reads from {places}; klipcal \
         does not change a value written as a reference (the constant is yours, and may serve \
         other options): set the new value {new_value} there yourself, or write \
         '{key}: {new_value}' in place of the reference, then restart Klipper"
    )]
    InReference {
        /// Section name.
        section: String,
        /// Option name.
        key: String,
        /// The value as written.
        written: String,
        /// Where each referenced value is defined.
        places: String,
        /// The value klipcal would have written.
        new_value: String,
    },
    /// The replacement value would not read back as written.
    #[error("cannot set [{section}] {key} to '{value}': {reason}")]
    BadNewValue {
        /// Section name.
        section: String,
        /// Option name.
        key: String,
        /// The refused value.
        value: String,
        /// Why.
        reason: String,
    },
    /// Re-reading the edited files did not give the expected config (an internal bug).
    #[error("config edit check failed: {0}")]
    EditCheck(String),
    /// A G-code command, parameter or value name outside `[A-Za-z0-9_.-]+`.
    #[error("G-code {what} '{name}' is not allowed; expected letters, digits, '_', '.' or '-'")]
    BadName {
        /// What the name is (command name, parameter name, value).
        what: String,
        /// The refused name.
        name: String,
    },
    /// A G-code number that is NaN or infinite.
    #[error("G-code parameter {key} = {value} is not a finite number")]
    BadNumber {
        /// Parameter name.
        key: String,
        /// The value.
        value: f64,
    },
    /// Text Klipper would not read back unchanged inside `"..."`.
    #[error("G-code parameter {key} text {value:?} cannot be sent: {reason}")]
    BadText {
        /// Parameter name.
        key: String,
        /// The refused text.
        value: String,
        /// Why.
        reason: String,
    },
    /// A backlash compensation value or reply klipcal cannot use.
    #[error("backlash compensation: {0}")]
    Backlash(String),
    /// The printer's kinematics has no `[stepper_x]`/`[stepper_y]` pair to calibrate.
    #[error(
        "kinematics {kinematics} is not supported: klipcal calibrates printers whose X and Y \
         are driven by [stepper_x] and [stepper_y] (cartesian, corexy and their hybrid, \
         limited and corexz variants)"
    )]
    UnsupportedKinematics {
        /// `[printer] kinematics` as written.
        kinematics: String,
    },
    /// A stepper still configured with the `step_distance` Klipper no longer reads.
    #[error(
        "[{section}] uses step_distance: {step_distance}, which Klipper no longer reads (it \
         needs rotation_distance since January 2021). Klipper converts it as rotation_distance \
         = full_steps_per_rotation × microsteps × step_distance = {conversion}; replace the \
         step_distance line with that"
    )]
    StepDistance {
        /// Section name.
        section: String,
        /// The old value, as written.
        step_distance: String,
        /// The worked conversion, e.g. `200 × 16 × 0.0125 = 40 → rotation_distance: 40`.
        conversion: String,
    },
    /// Steppers of one axis that cannot be changed together.
    #[error("{0}")]
    Companion(String),
    /// A value cannot be written where it would win without touching a protected file.
    #[error("{0}")]
    Protected(String),
    /// Moonraker's `configfile.config` JSON does not have the expected shape.
    #[error("Moonraker configfile.config is malformed: {0}")]
    Settings(String),
    /// Bed-mesh profiles that cannot be used together, in words naming the profiles, the
    /// options and what is expected.
    #[error("{0}")]
    MeshProfiles(String),
}
