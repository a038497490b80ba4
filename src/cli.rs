//! The command line: clap definitions of every command. Parsing only; `app` runs them.

use std::path::PathBuf;

use clap::{Args, Parser, Subcommand};

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
    /// Benchmarks: print measured figures beside their targets.
    #[command(subcommand)]
    Bench(BenchCommand),
    /// Offline: replay a recorded bed trace through the thermal soak detector and print when
    /// it declares equilibrium, and why.
    SoakDetect(SoakDetectArgs),
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
    /// The thermal soak detector on simulated beds, against the 1 % moment and a fixed preheat.
    Soak(BenchSoakArgs),
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

/// `klipcal soak-detect`
#[derive(Debug, Args)]
pub struct SoakDetectArgs {
    /// CSV trace with columns `t_s,power,temp_c,target_c` (power 0..1; a header row is allowed).
    #[arg(long, value_name = "PATH")]
    pub trace: PathBuf,
    /// Print one JSON object (`{"stable_at_s": …, …}`) instead of text.
    #[arg(long)]
    pub json: bool,
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
}
