//! The benchmarks' command line: `klipcal-bench <benchmark> …` (also reached as `klipcal bench …`
//! from a source checkout).

use std::path::PathBuf;

use clap::{Args, Parser, Subcommand};

/// klipcal-bench: klipcal's benchmarks, each figure beside its target and anchor.
#[derive(Debug, Parser)]
#[command(name = "klipcal-bench", version, about, long_about = None)]
pub struct Cli {
    /// klipcal's settings file (the soak and backlash settings the benchmarks run with;
    /// default: ~/printer_data/config/klipcal.toml when present, else built-in defaults).
    #[arg(long, global = true, value_name = "PATH")]
    pub config: Option<PathBuf>,
    /// The benchmark.
    #[command(subcommand)]
    pub command: BenchCommand,
}

/// `klipcal bench mesh`
#[derive(Debug, Args)]
pub struct BenchMeshArgs {
    /// Seed of the probe and sensor noise.
    #[arg(long, default_value_t = 2)]
    pub seed: u64,
    /// Probe noise, one σ, µm.
    #[arg(long, default_value_t = 1.0)]
    pub noise_um: f64,
    /// Hours of heating (then as many of cooling).
    #[arg(long, default_value_t = 2.0)]
    pub hours: f64,
    /// A mesh each time the frame moved by this, °C.
    #[arg(long, default_value_t = 1.0)]
    pub step_c: f64,
    /// Profile tolerance, µm.
    #[arg(long, default_value_t = 5.0)]
    pub tolerance_um: f64,
}

/// `klipcal bench …`
#[derive(Debug, Subcommand)]
pub enum BenchCommand {
    /// Resident memory and CPU of a running daemon beside Moonraker's and klippy's.
    Footprint(FootprintArgs),
    /// Closed-loop calibration accuracy on simulated machines, against the paper and the bound.
    Metrology(MetrologyArgs),
    /// The thermal soak detector on simulated beds, against the 1 % moment and a fixed preheat.
    Soak(BenchSoakArgs),
    /// Thermal bed-mesh compensation on simulated gantries, against VGB's two-mesh method.
    Mesh(BenchMeshArgs),
    /// The guided backlash procedure on simulated axes and people, beside the seed's single pass.
    Backlash(BenchBacklashArgs),
    /// The bench's nozzle camera: an HTTP snapshot server (`/?action=snapshot`, `/snapshot`)
    /// drawing the simulated nozzle (tests/bench/bench.py --camera starts it).
    Camera(BenchCameraArgs),
}

/// `klipcal bench camera`
#[derive(Debug, Args)]
pub struct BenchCameraArgs {
    /// The bench's simulated nozzle (`[klipcal_backlash_sim] state_file`).
    #[arg(long, value_name = "PATH")]
    pub state_file: PathBuf,
    /// Loopback port to serve on.
    #[arg(long)]
    pub port: u16,
    /// The camera as JSON: look (ring, dark_tip, empty, two_nozzles, saturated, flat), width,
    /// height, px_per_mm, rotation_deg, mirror, centre_mm, offset_px, radius_px, seed, ring_mm,
    /// ring_tau_s, drop_every; or photo (a labelled picture of tests/fixtures/nozzle, e.g.
    /// tamv-nozzle or ktamv-frame, instead of look and radius_px), zoom, reach_mm.
    #[arg(long, default_value = "{}")]
    pub spec: String,
}

/// `klipcal bench backlash`
#[derive(Debug, Args)]
pub struct BenchBacklashArgs {
    /// Simulated axes per model and person.
    #[arg(long, default_value_t = 1000)]
    pub axes: usize,
    /// RNG seed.
    #[arg(long, default_value_t = 4)]
    pub seed: u64,
    /// Rendered camera pictures per image family (detection figures).
    #[arg(long, default_value_t = 100)]
    pub camera_images: usize,
    /// Simulated axes per model for the camera procedure (each renders about 40 pictures).
    #[arg(long, default_value_t = 40)]
    pub camera_axes: usize,
    /// Simulated axes per real photo and model for the end-to-end lines on real-photo frames
    /// (each makes about 40 frames from the photo).
    #[arg(long, default_value_t = 10)]
    pub photo_axes: usize,
    /// Only the guided flow's lines (no camera pictures rendered).
    #[arg(long)]
    pub guided_only: bool,
}

/// `klipcal bench metrology`
#[derive(Debug, Args)]
pub struct MetrologyArgs {
    /// Random machines per scenario.
    #[arg(long, default_value_t = 1000)]
    pub machines: usize,
    /// RNG seed.
    #[arg(long, default_value_t = 4)]
    pub seed: u64,
    /// Print limit of the convergence loop.
    #[arg(long, default_value_t = 8)]
    pub max_prints: usize,
}

/// `klipcal bench footprint`
#[derive(Debug, Args)]
pub struct FootprintArgs {
    /// PID of the klipcal daemon to measure.
    #[arg(long)]
    pub klipcal_pid: u32,
    /// PID of Moonraker.
    #[arg(long)]
    pub moonraker_pid: u32,
    /// PID of klippy.
    #[arg(long)]
    pub klippy_pid: u32,
    /// Seconds to measure.
    #[arg(long, default_value_t = 60.0)]
    pub seconds: f64,
    /// The daemon's binary, for its size.
    #[arg(long, value_name = "PATH")]
    pub binary: Option<PathBuf>,
    /// Milliseconds from the daemon's start to "connected to Moonraker" (measured by the
    /// caller, e.g. tests/bench-footprint.sh).
    #[arg(long, value_name = "MS")]
    pub startup_ms: Option<f64>,
    /// The daemon's page (`http://127.0.0.1:7150`): polled while measuring as an open page
    /// does (status every 3 s, the soak plot every 15 s).
    #[arg(long, value_name = "URL")]
    pub page_url: Option<String>,
}

/// `klipcal bench soak`
#[derive(Debug, Args)]
pub struct BenchSoakArgs {
    /// Number of random simulated beds.
    #[arg(long, default_value_t = 400)]
    pub beds: usize,
    /// Seed of the random beds (the same seed gives the same beds).
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
    /// Also print every bed that failed a target, with the detector's explanation.
    #[arg(long)]
    pub show_failures: bool,
    /// Run only these beds: `all` (every family, the default), `four-node` (the four-node beds
    /// under both controls, their ports and grid), `pid` (four-node beds under Klipper's PID,
    /// its port and the grid) or `mpc` (four-node beds under Kalico's MPC and its port).
    #[arg(long, default_value = "all", value_parser = ["all", "four-node", "pid", "mpc"])]
    pub family: String,
}
