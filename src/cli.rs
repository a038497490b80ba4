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
    /// Benchmarks, from a source checkout: runs `klipcal-bench …` (the benchmarks' own binary,
    /// built beside this one; the printer's build does not carry it).
    #[command(disable_help_flag = true)]
    Bench(BenchPassArgs),
    /// Generate the pylon calibration print (G-code, layout.json, optional SVG preview) offline.
    Pylons(Box<PylonsArgs>),
    /// Offline: replay a recorded bed trace through the thermal soak detector and print when
    /// it declares equilibrium, and why.
    SoakDetect(SoakDetectArgs),
    /// Offline thermal bed-mesh compensation: fit VGB/klipcal meshes, write profiles.
    #[command(subcommand)]
    Mesh(MeshCommand),
    /// Install klipcal into a printer_data folder: binary, macros, settings, includes,
    /// Moonraker's update_manager entry, the systemd service.
    Install(crate::cmd::install::InstallArgs),
    /// Take klipcal off again: every edited file restored, what install added removed.
    Uninstall(crate::cmd::install::UninstallArgs),
    /// Print klipcal's Klipper macros (config/klipcal.cfg), generated from its command table.
    Macros(MacrosArgs),
    /// Offline backlash commands (docs/backlash.md).
    #[command(subcommand)]
    Backlash(BacklashCommand),
}

/// `klipcal bench …`: everything after `bench` goes to `klipcal-bench` unchanged.
#[derive(Debug, Args)]
pub struct BenchPassArgs {
    /// The benchmark and its options (`klipcal-bench --help` lists them).
    #[arg(trailing_var_arg = true, allow_hyphen_values = true, num_args = 0..)]
    pub args: Vec<std::ffi::OsString>,
}

/// `klipcal macros`
#[derive(Debug, Args)]
pub struct MacrosArgs {
    /// Print the table of every operation (macro, remote method, HTTP path, arguments) for
    /// docs/operations.md instead of the macros.
    #[arg(long)]
    pub readme: bool,
    /// With --readme: put the table into FILE between its `<!-- operations -->` markers
    /// (e.g. docs/operations.md) instead of printing it.
    #[arg(long, value_name = "FILE", requires = "readme")]
    pub write: Option<PathBuf>,
}

/// `klipcal mesh …`
#[derive(Debug, Subcommand)]
pub enum MeshCommand {
    /// Fit z(T) per mesh point from the COLD/HOT (and capture) profiles; judge TEST profiles.
    Fit(MeshFitArgs),
    /// Write the fewest `[bed_mesh klipcal_<T>]` profiles within a tolerance.
    Profiles(MeshProfilesArgs),
}

/// `klipcal mesh fit`
#[derive(Debug, Args)]
pub struct MeshFitArgs {
    /// Klipper printer.cfg (its [include]s are followed).
    #[arg(long, value_name = "PATH")]
    pub printer_cfg: PathBuf,
    /// Print one JSON object instead of text.
    #[arg(long)]
    pub json: bool,
}

/// `klipcal mesh profiles`
#[derive(Debug, Args)]
pub struct MeshProfilesArgs {
    /// Klipper printer.cfg (its [include]s are followed).
    #[arg(long, value_name = "PATH")]
    pub printer_cfg: PathBuf,
    /// Largest error of the nearest profile anywhere in the range, µm.
    #[arg(long, default_value_t = 5.0, value_name = "UM")]
    pub tolerance_um: f64,
    /// Lowest frame temperature, °C (default: the coldest mesh).
    #[arg(long, value_name = "C")]
    pub from: Option<f64>,
    /// Highest frame temperature, °C (default: the hottest mesh).
    #[arg(long, value_name = "C")]
    pub to: Option<f64>,
    /// Where to write the SAVE_CONFIG profile block to paste.
    #[arg(long, value_name = "PATH")]
    pub out: PathBuf,
    /// Print one JSON object instead of text.
    #[arg(long)]
    pub json: bool,
}

/// `klipcal check`
#[derive(Debug, Args)]
pub struct CheckArgs {
    /// Print the summary as one JSON object instead of text.
    #[arg(long)]
    pub json: bool,
}

/// `klipcal backlash …`
#[derive(Debug, Subcommand)]
pub enum BacklashCommand {
    /// Backlash per axis from camera readings: median, spread, uncertainty, outliers, verdict,
    /// smooth_time.
    Solve(BacklashSolveArgs),
    /// Where the nozzle is in a camera picture (JPEG or PNG), px ± px, or why it is refused:
    /// to check a nozzle camera before measuring backlash with it.
    Image(BacklashImageArgs),
}

/// `klipcal backlash image`
#[derive(Debug, Args)]
pub struct BacklashImageArgs {
    /// A snapshot of the nozzle seen from below (JPEG or PNG).
    #[arg(value_name = "FILE")]
    pub file: PathBuf,
    /// Print one JSON object instead of text.
    #[arg(long)]
    pub json: bool,
}

/// `klipcal backlash solve`
#[derive(Debug, Args)]
pub struct BacklashSolveArgs {
    /// JSON `{"x": [[x1_mm, x2_mm], …], "y": …, "z": …}` (X1 approached moving +, X2 moving −;
    /// an optional third number per cycle is its fine jog, mm).
    #[arg(long, value_name = "FILE")]
    pub readings: PathBuf,
    /// [printer] max_accel, mm/s²: smooth_time is raised until 2·b/t² fits the budget.
    #[arg(long, value_name = "MM_S2")]
    pub max_accel: Option<f64>,
    /// Print one JSON object per axis instead of text.
    #[arg(long)]
    pub json: bool,
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

/// `klipcal pylons`
#[derive(Debug, Args)]
pub struct PylonsArgs {
    /// The printer's Klipper config (printer.cfg); its [include]s are followed.
    #[arg(long, value_name = "PATH")]
    pub printer_cfg: PathBuf,
    /// Kinematics, overriding [printer] kinematics: corexy or cartesian.
    #[arg(long, value_name = "corexy|cartesian")]
    pub kinematics: Option<String>,
    /// `paper`: two groups along the motor directions; `full`: four groups (adds the other two
    /// directions, for scale along X and Y and the shear from one print).
    #[arg(long, default_value = "paper", value_name = "paper|full")]
    pub layout: String,
    /// Outer edge-to-edge distance pylon 1 → pylon 2, mm.
    #[arg(long, default_value_t = 10.0, value_name = "MM")]
    pub d1: f64,
    /// Outer edge-to-edge distance pylon 1 → pylon 3, mm.
    #[arg(long, default_value_t = 150.0, value_name = "MM")]
    pub d2: f64,
    /// Bed temperature, °C (the bed stays on at the end).
    #[arg(long, default_value_t = 80.0, value_name = "C")]
    pub bed_temp: f64,
    /// Nozzle temperature, °C.
    #[arg(long, default_value_t = 240.0, value_name = "C")]
    pub nozzle_temp: f64,
    /// Filament diameter, mm (default: [extruder] filament_diameter).
    #[arg(long, value_name = "MM")]
    pub filament_diameter: Option<f64>,
    /// Nozzle diameter, mm (default: [extruder] nozzle_diameter).
    #[arg(long, value_name = "MM")]
    pub nozzle_diameter: Option<f64>,
    /// Layer height, mm.
    #[arg(long, default_value_t = 0.2, value_name = "MM")]
    pub layer_height: f64,
    /// Where the groups cross, printer X,Y mm (default: the middle of the printable area).
    #[arg(long, value_name = "X,Y")]
    pub center: Option<String>,
    /// Pylon length, mm (shorter pylons let a full layout fit a small bed).
    #[arg(long, default_value_t = 53.6, value_name = "MM")]
    pub pylon_length: f64,
    /// Start command used when the config has a start macro (PRINT_START or START_PRINT);
    /// placeholders {start_macro} (its name), {bed_temp_c} and {nozzle_temp_c}.
    #[arg(long, value_name = "TEXT")]
    pub start_template: Option<String>,
    /// Extra G-code after the built-in end (e.g. PRINT_END, which usually turns the bed off).
    #[arg(long, value_name = "TEXT")]
    pub end_template: Option<String>,
    /// Seconds to dwell after the bed reached temperature, before the nozzle heats.
    #[arg(long, default_value_t = 0.0, value_name = "S")]
    pub bed_soak_s: f64,
    /// Where to write the G-code.
    #[arg(long, value_name = "PATH")]
    pub out: PathBuf,
    /// Where to write layout.json.
    #[arg(long, value_name = "PATH")]
    pub layout_out: PathBuf,
    /// Where to write the SVG preview.
    #[arg(long, value_name = "PATH")]
    pub svg: Option<PathBuf>,
}

/// `klipcal soak-detect`
#[derive(Debug, Args)]
#[command(group(clap::ArgGroup::new("input").required(true).args(["trace", "klippy_log"])))]
pub struct SoakDetectArgs {
    /// CSV trace with columns `t_s,power,temp_c,target_c` (power 0..1; a header row is allowed).
    #[arg(long, value_name = "PATH")]
    pub trace: Option<PathBuf>,
    /// A klippy.log instead: every hold of the bed at a heated target in its `Stats` lines,
    /// judged one by one, with the bed's `max_power` from the log's config dump.
    #[arg(long, value_name = "PATH")]
    pub klippy_log: Option<PathBuf>,
    /// Print one JSON object (`{"stable_at_s": …, …}`; with `--klippy-log`, `{"holds": […]}`)
    /// instead of text.
    #[arg(long)]
    pub json: bool,
}
