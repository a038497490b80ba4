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

/// The benchmarks' [`nozzle_photos::Fixtures`]: the real photographs in the source checkout.
///
/// # Errors
/// The file cannot be read (with its path).
pub fn nozzle_fixture(file: &str) -> anyhow::Result<Vec<u8>> {
    let path = nozzle_photos::dir().join(file);
    std::fs::read(&path).map_err(|e| anyhow::anyhow!("{}: {e}", path.display()))
}
