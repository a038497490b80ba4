//! The `klipcal` binary: parse the command line, start logging, run the chosen command.
//! Everything else lives in the library; this file stays thin.

use clap::Parser;

fn main() -> std::process::ExitCode {
    let cli = klipcal::cli::Cli::parse();
    match klipcal::app::run(cli) {
        Ok(code) => code,
        Err(err) => {
            eprintln!("klipcal: {err:#}");
            std::process::ExitCode::FAILURE
        }
    }
}
