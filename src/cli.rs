//! The command line: clap definitions of every command. Parsing only; `app` runs them.

use std::path::PathBuf;

use clap::{Args, Parser, Subcommand, ValueEnum};

/// klipcal: calibration daemon for Klipper printers (Moonraker agent).
#[derive(Debug, Parser)]
#[command(name = "klipcal", version, about, long_about = None)]
pub struct Cli {
    /// Settings file (default: ~/printer_data/config/klipcal.toml when present, else built-in defaults).
    #[arg(long, global = true, value_name = "PATH")]
    pub config: Option<PathBuf>,
    /// Moonraker websocket URL; overrides `moonraker.url` from the settings file.
    #[arg(long, global = true, value_name = "URL")]
    pub moonraker: Option<String>,
    /// The command to run.
    #[command(subcommand)]
    pub command: Command,
}

/// Every command.
#[derive(Debug, Subcommand)]
pub enum Command {
    /// Run the daemon: connect to Moonraker as an agent and serve calibrations.
    Serve,
    /// Connect to Moonraker, print what klipcal sees of the printer, and exit.
    Check(CheckArgs),
    /// Offline: solve rotation distances and skew from a pylon layout and caliper readings.
    Solve(SolveArgs),
    /// Benchmarks: print measured figures beside their targets.
    #[command(subcommand)]
    Bench(BenchCommand),
}

/// `klipcal check`
#[derive(Debug, Args)]
pub struct CheckArgs {
    /// Print the summary as one JSON object instead of text.
    #[arg(long)]
    pub json: bool,
}

/// `klipcal bench …`
#[derive(Debug, Subcommand)]
pub enum BenchCommand {
    /// Resident memory and CPU of a running daemon beside Moonraker's and klippy's.
    Footprint(FootprintArgs),
    /// Closed-loop calibration accuracy on simulated machines, against the paper and the bound.
    Metrology(MetrologyArgs),
}

/// `klipcal solve`
#[derive(Debug, Args)]
pub struct SolveArgs {
    /// layout.json of the printed job.
    #[arg(long, value_name = "PATH")]
    pub layout: PathBuf,
    /// Readings: JSON `{"A-D1":[10.02,…],…}` or CSV `pair,reading` rows, mm.
    #[arg(long, value_name = "PATH")]
    pub readings: PathBuf,
    /// Klipper printer.cfg (its [include]s are followed).
    #[arg(long, value_name = "PATH")]
    pub printer_cfg: PathBuf,
    /// Print one JSON object instead of text.
    #[arg(long)]
    pub json: bool,
    /// CoreXY: where the shear goes (`motors`: A/B rotation distances, as the paper;
    /// `klipper-skew`: matched belts, skewed frame).
    #[arg(long, value_enum, default_value_t = ShearToArg::Motors)]
    pub shear_to: ShearToArg,
    /// Klipper xy skew factor that was active during the print (0 = skew correction off).
    #[arg(long, default_value_t = 0.0, value_name = "FACTOR")]
    pub current_xy_skew: f64,
    /// The previous round's `solve --json` output, to check the last correction helped.
    #[arg(long, value_name = "PATH")]
    pub previous: Option<PathBuf>,
    /// Caliper precision as a 3σ bound, mm.
    #[arg(long, default_value_t = 0.02, value_name = "MM")]
    pub caliper_precision_mm: f64,
    /// Caliper trueness (accuracy), ± mm.
    #[arg(long, default_value_t = 0.02, value_name = "MM")]
    pub caliper_trueness_mm: f64,
    /// Bed temperature band during print and measurement, ± K.
    #[arg(long, default_value_t = 2.0, value_name = "K")]
    pub bed_temp_band_k: f64,
}

/// `--shear-to`
#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
pub enum ShearToArg {
    /// A/B rotation distances absorb the shear.
    Motors,
    /// Klipper's skew_correction takes the shear; A and B get one common scale.
    KlipperSkew,
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
}
