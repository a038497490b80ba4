//! The benchmarks, one module each, and the daemon's offline commands they build on.

pub mod backlash;
pub mod bench;
pub mod bench_camera;
pub mod mesh_bench;
pub(crate) mod par;
pub mod soak_bench;
pub mod soak_families;
pub mod soak_four_node;
pub mod soak_noise;
pub mod soak_real;

pub use klipcal::cmd::soak;
pub use klipcal_core::camera_render;
pub use klipcal_core::nozzle_photos;
pub use klipcal_core::optic_render;
pub use klipcal_core::photo_camera;
