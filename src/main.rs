//! The `klipcal` binary: parse the command line, start logging, run the chosen command.
//! Everything else lives in the library; this file stays thin.

use clap::Parser;

fn main() -> std::process::ExitCode {
    let cli = klipcal::cli::Cli::parse();
    // Rust ignores SIGPIPE, so printing to a reader that has gone (`klipcal-bench soak | head`)
    // panics; a one-shot command ends quietly there instead. The daemon keeps ignoring it (a
    // closed log or child pipe must not end it).
    #[cfg(unix)]
    if !matches!(cli.command, klipcal::cli::Command::Serve) {
        // SAFETY: setting a signal's disposition to its default before any thread starts.
        unsafe {
            libc::signal(libc::SIGPIPE, libc::SIG_DFL);
        }
    }
    match klipcal::app::run(cli) {
        Ok(code) => code,
        Err(err) => {
            eprintln!("klipcal: {err:#}");
            std::process::ExitCode::FAILURE
        }
    }
}
