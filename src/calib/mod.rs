//! PURE: the calibration math — statistics, differential scale, geometry fit, error budget.
//! No I/O, no clock: time and readings come in as arguments.

pub mod soak;
