//! PURE: the calibration math — statistics, differential scale, geometry fit, error budget.
//! No I/O, no clock: time and readings come in as arguments; files are read by the callers.
//!
//! - [`readings`]: caliper readings → robust centre per pair (parse JSON/CSV text, outliers).
//! - [`differential`]: the paper's method — scale α per group, new rotation_distance, steps/mm,
//!   convergence and the A/B swap check between rounds.
//! - [`budget`]: the paper's error budget (section 3): ε_bed, ε_filament, ε_measurement, ε_motor.
//! - [`metric`]: the in-plane metric fitted from every group at once, mapped onto the
//!   corrections the printer has (rotation distances, Klipper skew).
//! - [`skew`]: Klipper's skew correction (`calc_skew_factor`, its inverse, the toolhead
//!   position it commands), the classic AC/BD/AD method and the Prusa-style point fit.
//! - [`solve`]: layout + readings + printer facts → one [`solve::Solution`].
//! - [`soak`]: thermal equilibrium of the bed from its heater power (paper §3.1), with an ETA.
//! - [`mesh`]: thermal bed-mesh model (seed 002): per-point z(T), LOMO cross-validation, VGB's
//!   two-mesh method beside it, the fewest profiles within a tolerance.
//! - [`mesh_capture`]: the frame temperature each probe point of a mesh was taken at.
//! - [`mesh_follow`]: when to load which profile while printing (tolerance, hysteresis, interval,
//!   jump limit, stale sensor).
//! - [`backlash`]: backlash per axis from the seed's camera cycles (seed 004): median, spread,
//!   uncertainty, outliers, verdict, smooth_time from an acceleration budget.
//! - [`backlash_guide`]: the guided camera procedure as a resumable state machine.
//! - [`nozzle`]: the nozzle found in a camera picture to sub-pixel precision, or refused with
//!   the reason (issue 27).
//! - [`camera_scale`]: pixels → mm and the camera's rotation from known moves; the seed's
//!   backlash cycle from two detected centres.

pub mod backlash;
pub mod backlash_guide;
pub mod budget;
pub mod camera_scale;
#[cfg(test)]
mod click_flow_test;
pub mod differential;
pub mod entry;
pub mod mesh;
pub mod mesh_capture;
pub mod mesh_follow;
pub mod metric;
pub mod nozzle;
pub mod readings;
#[cfg(any(test, feature = "sim"))]
pub mod sim;
pub mod skew;
pub mod soak;
pub mod solve;

/// Everything the calibration math can reject. Messages name the pair or group and say what
/// is expected.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum Error {
    /// The readings text is not valid JSON of the expected shape.
    #[error("readings: {0}; expected a JSON object mapping pair ids to arrays of mm readings, e.g. {{\"A-D1\":[10.02,10.03,10.01]}}")]
    ReadingsJson(String),
    /// A CSV line could not be read.
    #[error(
        "readings CSV line {line}: {message}; expected `pair,reading` rows, e.g. `A-D1,10.02`"
    )]
    ReadingsCsv {
        /// 1-based line number.
        line: usize,
        /// What was wrong.
        message: String,
    },
    /// A reading that is not a finite number.
    #[error("pair {pair}: reading #{index} is {found}; expected a number of millimetres")]
    NotANumber {
        /// Pair id.
        pair: String,
        /// 1-based position in the pair's list.
        index: usize,
        /// What was found instead.
        found: String,
    },
    /// A zero or negative reading.
    #[error("pair {pair}: reading #{index} is {value} mm; expected a positive distance in mm")]
    NonPositive {
        /// Pair id.
        pair: String,
        /// 1-based position in the pair's list.
        index: usize,
        /// The reading.
        value: f64,
    },
    /// Too few readings for a robust centre.
    #[error("pair {pair}: {count} reading(s); expected at least {min} (the paper takes 5)")]
    TooFewReadings {
        /// Pair id.
        pair: String,
        /// How many were given.
        count: usize,
        /// The minimum.
        min: usize,
    },
    /// A reading for a pair the layout does not have.
    #[error("pair {pair} is not in the layout; expected one of: {known}")]
    UnknownPair {
        /// Pair id.
        pair: String,
        /// The layout's pair ids, comma separated.
        known: String,
    },
    /// A layout pair without readings.
    #[error("pair {pair} has no readings; expected an array of mm readings for every pair in the layout")]
    MissingPair {
        /// Pair id.
        pair: String,
    },
    /// The far pair of a group did not read longer than the near one.
    #[error("group {group}: {far} reads {far_mm:.3} mm, not more than {near} at {near_mm:.3} mm; expected the longer nominal distance to read longer (pairs swapped or mislabelled?)")]
    NotIncreasing {
        /// Group id.
        group: String,
        /// Near pair id.
        near: String,
        /// Its centre reading.
        near_mm: f64,
        /// Far pair id.
        far: String,
        /// Its centre reading.
        far_mm: f64,
    },
    /// A scale beyond what a belt printer can plausibly be off.
    #[error("group {group} (pairs {pairs}): scale {scale:.5} is {pct:+.2} % off; expected within ±{limit_pct} % — check the readings and that they belong to these pairs")]
    ScaleOutOfRange {
        /// Group id.
        group: String,
        /// Pair ids of the group.
        pairs: String,
        /// The scale found.
        scale: f64,
        /// (scale − 1) in percent.
        pct: f64,
        /// The limit in percent.
        limit_pct: f64,
    },
    /// The layout cannot be solved as given.
    #[error("layout: {0}")]
    Layout(String),
    /// A printer fact the solver needs is unusable.
    #[error("printer facts: {0}")]
    Facts(String),
    /// A fit that has too few or degenerate inputs.
    #[error("fit: {0}")]
    Fit(String),
    /// Backlash readings that are not the expected shape or values.
    #[error("backlash readings: {0}")]
    BacklashReadings(String),
    /// Backlash settings out of range.
    #[error("backlash settings: {0}")]
    BacklashParams(String),
    /// A guided backlash measurement step that cannot be taken.
    #[error("backlash guide: {0}")]
    BacklashGuide(String),
    /// Camera sightings that do not give a scale.
    #[error("camera scale: {0}")]
    CameraScale(String),
}
