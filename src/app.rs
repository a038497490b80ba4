//! Builds and runs each command: the daemon's tasks and the one shutdown token every task
//! listens to, `check`, and the benches. Owns the tokio runtime and logging set-up.

use std::process::ExitCode;
use std::time::Duration;

use anyhow::Context;
use serde_json::{Map, Value};
use tokio_util::sync::CancellationToken;
use tracing::info;

use crate::cli::{BenchPassArgs, Cli, Command};
use crate::config::Config;
use crate::moonraker::{ClientOptions, ConnState, Moonraker};

/// Runs the parsed command line; returns the process exit code.
///
/// # Errors
/// Bad settings, or a command that failed; the message says why.
pub fn run(cli: Cli) -> anyhow::Result<ExitCode> {
    let cli_config = cli.config.clone();
    let mut config = Config::load(cli.config.as_deref()).context("loading settings")?;
    // install/uninstall read a printer's Moonraker from its own folder unless told.
    let explicit_url = cli.moonraker.clone();
    if let Some(url) = cli.moonraker {
        config.moonraker.url = url;
        config.validate().context("--moonraker")?;
    }
    // Only the daemon logs at the configured level; one-shot commands print their own output.
    let level = match cli.command {
        Command::Serve => config.log.level.as_str(),
        _ => "warn",
    };
    init_tracing(level);
    for key in &config.retired_keys {
        tracing::warn!(
            "settings: {key} is no longer used (the soak detector's statistics are not \
             settings any more); ignored — remove it from the file"
        );
    }
    let rt = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .context("starting the async runtime")?;
    match cli.command {
        Command::Serve => rt.block_on(serve(config)),
        Command::Bench(b) => bench(&b, cli_config.as_deref()),
        Command::Check(args) => rt.block_on(check(config, args.json)),
        Command::Install(a) => rt.block_on(crate::cmd::install::install(
            &a,
            &config,
            explicit_url.as_deref(),
        )),
        Command::Uninstall(a) => rt.block_on(crate::cmd::install::uninstall(
            &a,
            &config,
            explicit_url.as_deref(),
        )),
        Command::Pylons(args) => {
            crate::cmd::pylons::run(&args)?;
            Ok(ExitCode::SUCCESS)
        }
        Command::Solve(args) => crate::cmd::solve::run(&args),
        Command::SoakDetect(a) => crate::cmd::soak::detect(&a, &config.soak),
        Command::Mesh(crate::cli::MeshCommand::Fit(a)) => crate::cmd::mesh::fit_cmd(&a),
        Command::Mesh(crate::cli::MeshCommand::Profiles(a)) => crate::cmd::mesh::profiles_cmd(&a),
        Command::Backlash(crate::cli::BacklashCommand::Solve(a)) => {
            crate::cmd::backlash::solve(&a, &config.backlash)
        }
        Command::Backlash(crate::cli::BacklashCommand::Image(a)) => crate::cmd::backlash::image(&a),
        Command::Macros(a) => {
            if a.readme {
                let table = crate::jobs::table::markdown(crate::jobs::registry::all_ops());
                match &a.write {
                    Some(path) => crate::cmd::write_operations_table(path, &table)?,
                    None => print!("{table}"),
                }
            } else {
                print!("{}", crate::jobs::registry::macros_cfg());
            }
            Ok(ExitCode::SUCCESS)
        }
    }
}

/// `klipcal bench …`: the benchmarks live in their own binary, `klipcal-bench`, built beside
/// this one from a source checkout (`cargo build --workspace`); the printer's build has none.
fn bench(b: &BenchPassArgs, config: Option<&std::path::Path>) -> anyhow::Result<ExitCode> {
    let exe = std::env::current_exe().context("locating the klipcal binary")?;
    let bench = exe.with_file_name("klipcal-bench");
    if !bench.is_file() {
        anyhow::bail!(
            "no klipcal-bench beside {}: the benchmarks and their simulators are not part of the \
             printer's build; from a source checkout run `cargo run -p klipcal-bench --release -- \
             …` (or `cargo build --workspace` first)",
            exe.display()
        );
    }
    let mut cmd = std::process::Command::new(&bench);
    if let Some(path) = config {
        cmd.arg("--config").arg(path);
    }
    // exec: the bench runs as this process (a bench.py that stops `klipcal bench camera` stops
    // the camera, not a parent that leaves it behind).
    let err = std::os::unix::process::CommandExt::exec(cmd.args(&b.args));
    Err(anyhow::Error::new(err).context(format!("running {}", bench.display())))
}

fn init_tracing(level: &str) {
    use tracing_subscriber::filter::{LevelFilter, Targets};
    // RUST_LOG as `target=level` pairs (`klipcal=debug,warn`); a plain target filter keeps
    // the regex engine out of the binary (see `klipcal bench footprint`).
    let filter = std::env::var("RUST_LOG")
        .ok()
        .and_then(|v| v.parse::<Targets>().ok())
        .unwrap_or_else(|| {
            Targets::new()
                .with_target("klipcal", level.parse().unwrap_or(LevelFilter::INFO))
                .with_default(LevelFilter::WARN)
        });
    use std::io::IsTerminal;
    use tracing_subscriber::layer::SubscriberExt;
    use tracing_subscriber::util::SubscriberInitExt;
    // Colour only on a terminal: log files and journald get plain text.
    // The Targets filter decides; the formatter itself lets every level through.
    let builder = tracing_subscriber::fmt()
        .with_max_level(LevelFilter::TRACE)
        .with_writer(std::io::stderr)
        .with_ansi(std::io::stderr().is_terminal())
        .with_target(false);
    // journald stamps every line itself.
    if std::env::var_os("JOURNAL_STREAM").is_some() {
        let _ = builder.without_time().finish().with(filter).try_init();
    } else {
        let _ = builder.finish().with(filter).try_init();
    }
}

/// Client options from the settings, with the agent's remote methods.
pub(crate) fn client_options(config: &Config) -> ClientOptions {
    let m = &config.moonraker;
    let mut subscriptions = Map::new();
    for obj in ["print_stats", "heater_bed", "webhooks"] {
        subscriptions.insert(obj.to_string(), Value::Null);
    }
    ClientOptions {
        url: m.url.clone(),
        api_key: (!m.api_key.is_empty()).then(|| m.api_key.clone()),
        client_name: "klipcal".into(),
        agent: true,
        request_timeout: Duration::from_secs_f64(m.request_timeout_s),
        reconnect_min: Duration::from_secs_f64(m.reconnect_min_s),
        reconnect_max: Duration::from_secs_f64(m.reconnect_max_s),
        remote_methods: crate::jobs::registry::all_methods().to_vec(),
        subscriptions,
    }
}

/// Cancels `token` on SIGINT or SIGTERM.
fn cancel_on_signal(token: CancellationToken) -> anyhow::Result<()> {
    use tokio::signal::unix::{signal, SignalKind};
    let mut term = signal(SignalKind::terminate()).context("installing the SIGTERM handler")?;
    let mut int = signal(SignalKind::interrupt()).context("installing the SIGINT handler")?;
    tokio::spawn(async move {
        tokio::select! {
            _ = term.recv() => info!("SIGTERM: shutting down"),
            _ = int.recv() => info!("SIGINT: shutting down"),
            () = token.cancelled() => {}
        }
        token.cancel();
    });
    Ok(())
}

async fn serve(config: Config) -> anyhow::Result<ExitCode> {
    let cancel = CancellationToken::new();
    cancel_on_signal(cancel.clone())?;
    info!(version = env!("CARGO_PKG_VERSION"), url = %config.moonraker.url, "klipcal starting");
    let (m, calls) = Moonraker::spawn(client_options(&config), cancel.clone());
    // Tells klipcal's macros in Klipper that the service answers (they say "asking" otherwise).
    let online = tokio::spawn(m.clone().keep_online(cancel.clone()));
    let files = crate::moonraker::Files::new(
        &config.http_base(),
        (!config.moonraker.api_key.is_empty()).then(|| config.moonraker.api_key.clone()),
        Duration::from_secs_f64(config.moonraker.request_timeout_s.max(60.0)),
    )?;
    let data_dir = crate::config::expand_home(&config.daemon.data_dir);
    let cals = match crate::store::Store::open(&data_dir) {
        Ok(store) => Some(crate::jobs::Calibrations::new(
            crate::jobs::Core::new(m.clone(), files, store, cancel.clone()),
            &config,
        )),
        Err(e) => {
            tracing::error!(error = %e, "calibration sessions disabled");
            None
        }
    };
    if let Some(c) = cals.clone() {
        c.core().spawn(c.clone().hold_watchdog());
        c.core().spawn(crate::jobs::core::bed_log::recorder(
            c.core().clone(),
            config.soak.skip_below_c,
        ));
        c.core().spawn(c.core().clone().watch_closes());
        let m2 = m.clone();
        let c2 = c.clone();
        let stop = cancel.clone();
        c.core().spawn(async move {
            tokio::select! {
                () = stop.cancelled() => {}
                r = m2.wait_connected(Duration::from_secs(86_400)) => {
                    if r.is_ok() {
                        c2.resume().await;
                    }
                }
            }
        });
    }
    if config.http.enabled {
        match crate::http::start(
            &config.http,
            m.clone(),
            cals.clone(),
            config.soak.clone(),
            cancel.clone(),
        )
        .await
        {
            Ok(addr) => {
                info!("page and API on http://{addr}/ ([http] bind)");
                if let Some(c) = &cals {
                    c.core().set_page(crate::http::page_address_here(addr));
                }
            }
            Err(e) => {
                let why = crate::http::page_off_words(&config.http.bind, &e);
                tracing::error!("klipcal's page and API are off: {why}");
                // Said where a user looks, not only in the log: at start on stderr (the
                // service's journal), on the console once Moonraker is there, and in
                // KLIPCAL_STATUS.
                eprintln!("klipcal: its page and API are off: {why}");
                if let Some(c) = &cals {
                    c.core().set_page_off(why.clone());
                    let (m2, core, stop) = (m.clone(), c.core().clone(), cancel.clone());
                    c.core().spawn(async move {
                        tokio::select! {
                            () = stop.cancelled() => {}
                            r = m2.wait_connected(Duration::from_secs(86_400)) => {
                                if r.is_ok() {
                                    core.console_error(&format!(
                                        "klipcal's page is off: {why}"
                                    ))
                                    .await;
                                }
                            }
                        }
                    });
                }
            }
        }
    }
    let agent = tokio::spawn(crate::agent::serve(m.clone(), cals.clone(), calls));
    cancel.cancelled().await;
    // Every task the sessions started (runners, the follower, the watchdog, the resume) ends
    // with the token; wait for them, within a deadline, before the socket closes.
    if let Some(c) = &cals {
        let running = c.core().running_tasks();
        if c.core().stopped(Duration::from_millis(1500)).await {
            info!(tasks = running, "every session task stopped");
        } else {
            tracing::warn!(
                still_running = c.core().running_tasks(),
                "session tasks still running 1.5 s after shutdown; stopping anyway"
            );
        }
    }
    // The macros say "asking" again from now (a second at most).
    let _ = tokio::time::timeout(Duration::from_millis(1500), online).await;
    // Every task selects on the token; give them a moment to close the socket cleanly.
    let mut state = m.state_watch();
    let _ = tokio::time::timeout(
        Duration::from_millis(1500),
        state.wait_for(|s| *s == ConnState::Stopped),
    )
    .await;
    agent.abort();
    if let Some(why) = m.fatal_error() {
        anyhow::bail!("{why}");
    }
    info!("klipcal stopped");
    Ok(ExitCode::SUCCESS)
}

async fn check(config: Config, as_json: bool) -> anyhow::Result<ExitCode> {
    let cancel = CancellationToken::new();
    let mut opts = client_options(&config);
    opts.remote_methods.clear();
    opts.agent = false;
    opts.client_name = "klipcal-check".into();
    opts.subscriptions.clear();
    let (m, _calls) = Moonraker::spawn(opts, cancel.clone());
    let limit = Duration::from_secs_f64(config.moonraker.request_timeout_s.min(10.0));
    let result = async {
        m.wait_connected(limit).await.with_context(|| {
            "cannot reach Moonraker; is it running, and is moonraker.url (or --moonraker) right?"
                .to_string()
        })?;
        crate::printer::gather(&m)
            .await
            .context("asking Moonraker about the printer")
    }
    .await;
    cancel.cancel();
    let summary = result?;
    if as_json {
        println!("{}", serde_json::to_string_pretty(&summary)?);
    } else {
        print!("{}", summary.render());
    }
    Ok(match summary.problem() {
        Some(p) => {
            eprintln!("klipcal check: {p}");
            ExitCode::from(2)
        }
        None => ExitCode::SUCCESS,
    })
}
