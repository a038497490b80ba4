//! klipcal-bench: every benchmark of klipcal and the simulators behind them (simulated machines,
//! beds, gantries, axes, people and the nozzle camera), apart from the daemon so that none of
//! them is in the printer's binary. Figures are printed beside their targets and anchors.
//!
//! The modules keep the paths they had inside the daemon: the core's and the daemon's modules
//! are brought in under the same names.

use std::process::ExitCode;

use anyhow::Context;
use clap::Parser;

use klipcal::{config, jobs};
use klipcal_core::{calib, klipper, layout};

mod bench_metrology;
mod cli;
mod cmd;

use cli::{BenchCommand, Cli};

fn main() -> ExitCode {
    // Rust ignores SIGPIPE, so printing to a reader that has gone (`klipcal-bench soak | head`)
    // panics; end quietly there instead.
    // SAFETY: setting a signal's disposition to its default before any thread starts.
    unsafe {
        libc::signal(libc::SIGPIPE, libc::SIG_DFL);
    }
    let cli = Cli::parse();
    match run(cli) {
        Ok(code) => code,
        Err(e) => {
            eprintln!("klipcal-bench: {e:#}");
            ExitCode::FAILURE
        }
    }
}

fn run(cli: Cli) -> anyhow::Result<ExitCode> {
    let config = config::Config::load(cli.config.as_deref()).context("loading settings")?;
    let rt = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .context("starting the async runtime")?;
    match cli.command {
        BenchCommand::Footprint(a) => rt.block_on(cmd::bench::footprint(&a)),
        BenchCommand::Metrology(args) => cmd::bench::metrology(&args),
        BenchCommand::Soak(a) => cmd::soak_bench::bench(&a, &config.soak),
        BenchCommand::Mesh(a) => cmd::mesh_bench::bench(&a),
        BenchCommand::Backlash(a) => cmd::backlash::bench(&a, &config.backlash),
        BenchCommand::Camera(a) => rt.block_on(cmd::bench_camera::serve(&a)),
    }
}
