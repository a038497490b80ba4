//! klipcal-core: the pure part of klipcal. Time and data in, values out: no I/O, no clock, no
//! async runtime, no network or database crate in this crate's dependencies (the `purity`
//! test keeps it so), and no file, socket, process or clock call of the standard library
//! (this crate's `clippy.toml`, denied under `-D warnings`). The daemon (`klipcal`) and the benchmarks (`klipcal-bench`) build on it.
//!
//! - [`calib`]: the math: statistics, differential scale, geometry fit, error budget, the bed
//!   soak (`calib::soak`), the thermal bed-mesh model, backlash, the nozzle in a picture.
//! - [`gcode`]: the pylon job generator (printer facts → geometry → toolpaths → G-code text +
//!   layout).
//! - [`klipper`]: Klipper's config text (parse, includes, edit one value in place), G-code
//!   command text built from typed values, the bed's history read from klippy.log text. Files
//!   reach it through the `klipper::Files` trait (the daemon's `fsio` implements it).
//! - [`layout`]: the `layout.json` types shared by the pylon generator and the solver.
//! - [`plots`]: the plots people look at (bed soak, convergence) as SVG text, and as PNG.
//! - `camera_render` and `calib::sim` (feature `sim`, and this crate's tests): simulated
//!   nozzle-camera pictures and a simulated machine for the benchmarks and the tests; never in
//!   the printer's build. `nozzle_photos` (the same): the real nozzle photographs of
//!   `tests/fixtures/nozzle`, their bytes read from the source checkout by the tests and the
//!   bench;
//!   `photo_camera` (the same): a nozzle camera whose frames are one of those photographs
//!   moved where the simulated nozzle is (the bench's camera server and `klipcal bench
//!   backlash`); `optic_render` (the same): a second nozzle camera written apart from
//!   `camera_render`, a shaded nozzle photographed through a lens onto a Bayer sensor.

pub mod calib;
#[cfg(any(test, feature = "sim"))]
pub mod camera_render;
pub mod gcode;
pub mod klipper;
pub mod layout;
#[cfg(any(test, feature = "sim"))]
pub mod nozzle_photos;
#[cfg(any(test, feature = "sim"))]
pub mod optic_render;
#[cfg(any(test, feature = "sim"))]
pub mod photo_camera;
pub mod plots;

#[cfg(test)]
mod purity {
    use std::collections::{BTreeMap, BTreeSet};

    /// Crates that do I/O (network, database, async runtime, HTTP): none may be reachable from
    /// this crate's dependencies.
    const IO_CRATES: [&str; 9] = [
        "tokio",
        "mio",
        "axum",
        "hyper",
        "reqwest",
        "rusqlite",
        "socket2",
        "tungstenite",
        "h2",
    ];

    /// Every package reachable from `klipcal-core` in the workspace's Cargo.lock (its
    /// dev-dependencies, seeded random numbers, included).
    fn reachable() -> BTreeSet<String> {
        let lock: toml::Table = include_str!("../../../Cargo.lock")
            .parse()
            .expect("Cargo.lock");
        let mut deps: BTreeMap<String, Vec<String>> = BTreeMap::new();
        for p in lock["package"].as_array().expect("packages") {
            let name = p["name"].as_str().expect("name").to_owned();
            let list = p.get("dependencies").and_then(toml::Value::as_array);
            let names = list.into_iter().flatten().filter_map(|d| {
                d.as_str()
                    .map(|s| s.split(' ').next().unwrap_or(s).to_owned())
            });
            deps.entry(name).or_default().extend(names);
        }
        let mut seen = BTreeSet::new();
        let mut todo = vec!["klipcal-core".to_owned()];
        while let Some(n) = todo.pop() {
            if seen.insert(n.clone()) {
                todo.extend(deps.get(&n).into_iter().flatten().cloned());
            }
        }
        seen
    }

    #[test]
    fn no_io_crate_is_reachable_from_the_core() {
        let seen = reachable();
        assert!(
            seen.contains("nalgebra") && seen.contains("image"),
            "{seen:?}"
        );
        let io: Vec<_> = seen
            .iter()
            .filter(|n| IO_CRATES.iter().any(|c| n.starts_with(c)))
            .collect();
        assert!(io.is_empty(), "the pure core reaches I/O crates: {io:?}");
    }
}
