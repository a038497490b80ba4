//! Builds and runs each command: the daemon's tasks and shutdown token, `check`, the benches.

use std::process::ExitCode;

use anyhow::Context;

use crate::cli::{BenchCommand, Cli, Command};
use crate::config::Config;

/// Runs the parsed command line; returns the process exit code.
///
/// # Errors
/// Bad settings, or a command that failed; the message says why.
pub fn run(cli: Cli) -> anyhow::Result<ExitCode> {
    let mut config = Config::load(cli.config.as_deref()).context("loading settings")?;
    if let Some(url) = cli.moonraker {
        config.moonraker.url = url;
    }
    match cli.command {
        Command::Serve => {
            anyhow::bail!("serve: not built yet")
        }
        Command::Check(_args) => anyhow::bail!("check: not built yet"),
        Command::Solve(args) => crate::solve_cmd::run(&args),
        Command::Bench(BenchCommand::Metrology(args)) => crate::bench::metrology(&args),
        Command::Bench(_b) => anyhow::bail!("bench: not built yet"),
    }
}
