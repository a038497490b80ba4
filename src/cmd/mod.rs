//! The offline commands, each the thin shell of one CLI command: read files, call the pure
//! modules, print. No calibration logic and no Moonraker session here. The benchmarks and their
//! simulators are in their own crate (`crates/klipcal-bench`), not in the printer's binary.

pub mod backlash;
pub mod install;
pub mod mesh;
pub mod pylons;
pub mod soak;
pub mod solve;
