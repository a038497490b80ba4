//! The offline commands, each the thin shell of one CLI command: read files, call the pure
//! modules, print. No calibration logic and no Moonraker session here.

pub mod backlash;
#[cfg(feature = "bench")]
pub mod bench;
#[cfg(feature = "bench")]
pub(crate) mod bench_camera;
pub(crate) mod camera_render;
pub mod install;
pub mod mesh;
pub mod pylons;
pub mod soak;
#[cfg(feature = "bench")]
pub mod soak_bench;
#[cfg(feature = "bench")]
pub mod soak_families;
#[cfg(feature = "bench")]
pub mod soak_four_node;
#[cfg(feature = "bench")]
pub(crate) mod soak_noise;
#[cfg(feature = "bench")]
pub mod soak_real;
pub mod solve;
