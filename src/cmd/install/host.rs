//! The printer host as install and uninstall see it: the printer_data layout, which Moonraker
//! serves it, whether a print runs, the page ports taken, the systemd unit and the restarts.

use std::io::{BufRead, Write};
use std::path::{Path, PathBuf};
use std::time::Duration;

use anyhow::{anyhow, bail, Context};
use serde_json::json;

use super::files::{expand, read_opt};
use super::plan;
use crate::config::Config;

/// The layout klipcal expects: `DIR/config/printer.cfg` and `DIR/config/moonraker.conf`.
pub(super) fn layout(printer_data: &str) -> anyhow::Result<PathBuf> {
    let pd = expand(printer_data);
    for f in ["config/printer.cfg", "config/moonraker.conf"] {
        if !pd.join(f).is_file() {
            bail!(
                "no printer_data layout at {}: expected {} (point --printer-data at the folder \
                 that holds Klipper's and Moonraker's config/)",
                pd.display(),
                pd.join(f).display()
            );
        }
    }
    Ok(pd)
}

/// One printer on this host as install sees it: its folder, its Moonraker, its names.
pub(super) struct Printer {
    pub(super) pd: PathBuf,
    /// Moonraker's websocket, from the folder's moonraker.conf `[server]` (or `--moonraker`).
    pub(super) url: String,
    /// Moonraker's port, from moonraker.conf.
    pub(super) port: u16,
    /// `printer_2` for `printer_2_data`; `None` for `printer_data`.
    pub(super) instance: Option<String>,
    /// `klipcal` or `klipcal-printer_2`.
    pub(super) service: String,
}

/// Reads which Moonraker serves `pd`, from its own moonraker.conf: never the default port's
/// printer when the folder is another's. `explicit` is `--moonraker`, when given.
pub(super) fn printer(pd: &Path, explicit: Option<&str>) -> anyhow::Result<Printer> {
    let conf_path = pd.join("config/moonraker.conf");
    let conf = read_opt(&conf_path)?.unwrap_or_default();
    let (host, port) =
        plan::moonraker_address(&conf).map_err(|e| anyhow!("{}: {e}", conf_path.display()))?;
    let theirs = plan::moonraker_url(&host, port);
    let url = match explicit {
        Some(u) => {
            if u != theirs {
                println!(
                    "note: --moonraker {u}, while {} says this printer's Moonraker listens at \
                     {theirs}",
                    conf_path.display()
                );
            }
            u.to_string()
        }
        None => theirs,
    };
    let instance = pd
        .file_name()
        .and_then(|n| plan::instance(&n.to_string_lossy()));
    let service = plan::service_name(instance.as_deref());
    Ok(Printer {
        pd: pd.to_path_buf(),
        url,
        port,
        instance,
        service,
    })
}

/// The settings install and uninstall talk to this printer's Moonraker with: its URL, and the
/// API key of its own klipcal.toml when there is one (else the one given with `--config`).
pub(super) fn printer_config(config: &Config, p: &Printer) -> Config {
    let mut c = config.clone();
    if let Ok(Some(text)) = read_opt(&p.pd.join("config/klipcal.toml")) {
        if let Ok(own) = Config::parse(&text) {
            c.moonraker.api_key = own.moonraker.api_key;
        }
    }
    c.moonraker.url = p.url.clone();
    c
}

/// Page ports this printer's klipcal must not take: those other printers' klipcal.toml
/// (beside this printer_data folder) name, and those a program listens on now.
pub(super) fn taken_http_ports(pd: &Path) -> Vec<u16> {
    let mut taken = Vec::new();
    if let Some(parent) = pd.parent() {
        for e in std::fs::read_dir(parent).into_iter().flatten().flatten() {
            if e.path() == pd {
                continue;
            }
            let f = e.path().join("config/klipcal.toml");
            if let Ok(Some(t)) = read_opt(&f) {
                if let Ok(c) = Config::parse(&t) {
                    if let Ok(a) = c.http.bind.parse::<std::net::SocketAddr>() {
                        taken.push(a.port());
                    }
                }
            }
        }
    }
    for port in 7150..7250u16 {
        if std::net::TcpListener::bind(("0.0.0.0", port)).is_err() {
            taken.push(port);
        }
    }
    taken
}

/// Refuses while a print runs; says so when Moonraker cannot be asked.
pub(super) async fn not_printing(
    config: &Config,
) -> anyhow::Result<Option<crate::moonraker::Files>> {
    let files = crate::moonraker::Files::new(
        &config.http_base(),
        (!config.moonraker.api_key.is_empty()).then(|| config.moonraker.api_key.clone()),
        Duration::from_secs(5),
    )?;
    match files.get("/printer/objects/query?print_stats=state").await {
        Ok(v) => {
            let state = v["status"]["print_stats"]["state"]
                .as_str()
                .unwrap_or("")
                .to_string();
            if matches!(state.as_str(), "printing" | "paused") {
                bail!("Klipper is {state}: klipcal installs only while the printer is idle");
            }
            Ok(Some(files))
        }
        Err(e) => {
            println!(
                "note: Moonraker at {} did not answer ({e}); cannot check that no print runs, \
                 and Klipper and Moonraker are not restarted",
                config.http_base()
            );
            Ok(None)
        }
    }
}

pub(super) fn ask(question: &str) -> bool {
    print!("{question} [Y/n] ");
    let _ = std::io::stdout().flush();
    let mut line = String::new();
    if std::io::stdin().lock().read_line(&mut line).is_err() {
        return false;
    }
    !line.trim().to_ascii_lowercase().starts_with('n')
}

pub(super) fn target_asset() -> String {
    let arch = match std::env::consts::ARCH {
        "arm" => "armv7",
        other => other,
    };
    format!("klipcal-{arch}-linux")
}

pub(super) fn systemd_available() -> bool {
    Path::new("/run/systemd/system").is_dir()
}

pub(super) fn unit_text(bin: &Path, p: &Printer) -> String {
    let user = std::env::var("SUDO_USER")
        .or_else(|_| std::env::var("USER"))
        .unwrap_or_else(|_| "pi".into());
    // This printer's Moonraker (KIAUH names a second one moonraker-printer_2).
    let moonraker = p
        .instance
        .as_ref()
        .map_or_else(|| "moonraker".to_string(), |i| format!("moonraker-{i}"));
    let name = p
        .instance
        .as_ref()
        .map_or_else(String::new, |i| format!(" ({i})"));
    format!(
        "# written by klipcal install; klipcal uninstall removes it\n\
         [Unit]\nDescription=klipcal calibration daemon for Klipper{name} (Moonraker agent)\n\
         After=network-online.target {moonraker}.service\nWants={moonraker}.service\n\n\
         [Service]\nType=simple\nUser={user}\nExecStart={} --config {} serve\n\
         Restart=on-failure\nRestartSec=5\nKillSignal=SIGTERM\nTimeoutStopSec=10\n\n\
         [Install]\nWantedBy=multi-user.target\n",
        bin.display(),
        p.pd.join("config/klipcal.toml").display()
    )
}

pub(super) fn systemctl(args: &[&str]) -> anyhow::Result<()> {
    let mut cmd = if nix_is_root() {
        std::process::Command::new("systemctl")
    } else {
        let mut c = std::process::Command::new("sudo");
        c.arg("systemctl");
        c
    };
    let st = cmd.args(args).status().context("running systemctl")?;
    if !st.success() {
        bail!("systemctl {} failed ({st})", args.join(" "));
    }
    Ok(())
}

/// Whether klipcal runs as root (then no `sudo` is needed for the systemd steps).
pub(super) fn nix_is_root() -> bool {
    use std::os::unix::fs::MetadataExt;
    std::fs::metadata("/proc/self").is_ok_and(|m| m.uid() == 0)
}

/// Restarts Klipper when its config changed and Moonraker when its did.
pub(super) async fn restart(files: &crate::moonraker::Files, changed: &[PathBuf], pd: &Path) {
    let cfg = pd.join("config");
    let klipper = changed
        .iter()
        .any(|p| p.starts_with(&cfg) && p.extension().is_some_and(|e| e == "cfg"));
    let moonraker = changed
        .iter()
        .any(|p| p.ends_with("moonraker.conf") || p.ends_with("moonraker.asvc"));
    if klipper {
        match files.post("/printer/restart", &json!({})).await {
            Ok(_) => println!("Klipper restarted to load klipcal.cfg"),
            Err(e) => println!("note: restart Klipper yourself (RESTART): {e}"),
        }
    }
    if moonraker {
        match files.post("/server/restart", &json!({})).await {
            Ok(_) => println!("Moonraker restarted to load [update_manager klipcal]"),
            Err(e) => println!("note: restart Moonraker yourself: {e}"),
        }
    }
}
