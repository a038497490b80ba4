//! `klipcal install` / `klipcal uninstall`: puts klipcal on a printer host in one command and
//! takes it off again. The edits are planned by the pure [`plan`] (the same config reader the
//! calibrations use decides what Klipper already reads), every edited file is backed up, and
//! a manifest (`printer_data/klipcal/install.json`) records each file's original bytes so
//! uninstall restores them byte for byte — or, where the user changed a file since, takes out
//! only klipcal's own lines. `--dry-run` prints every change as a diff and writes nothing.

pub mod plan;
mod webcam;

use std::collections::BTreeMap;
use std::io::{BufRead, IsTerminal, Write};
use std::path::{Path, PathBuf};
use std::process::ExitCode;
use std::time::Duration;

use anyhow::{anyhow, bail, Context};
use serde::{Deserialize, Serialize};
use serde_json::json;

use crate::config::Config;

/// The Klipper macros users include (replaced on every install: users don't edit it).
/// The documented settings file (written only when absent).
const SETTINGS: &str = include_str!("../../../config/klipcal.toml");
/// What Moonraker writes to a missing moonraker.asvc (its `default_allowed_services` asset).
const MOONRAKER_DEFAULT_SERVICES: &str = "klipper_mcu\nwebcamd\nMoonCord\nKlipperScreen\n\
     moonraker-telegram-bot\nmoonraker-obico\nsonar\ncrowsnest\noctoeverywhere\nratos-configurator\n";

/// `klipcal install`.
#[derive(Debug, Clone, clap::Args)]
pub struct InstallArgs {
    /// The printer_data folder Klipper and Moonraker use.
    #[arg(long, value_name = "DIR", default_value = "~/printer_data")]
    pub printer_data: String,
    /// Where the binary and its release_info.json go (the update_manager's `path`); default
    /// `~/klipcal`, or `~/klipcal-printer_2` for `~/printer_2_data`.
    #[arg(long, value_name = "DIR")]
    pub bin_dir: Option<String>,
    /// Print every change as a diff and write nothing.
    #[arg(long)]
    pub dry_run: bool,
    /// Do not install or start the systemd service (e.g. in a container).
    #[arg(long)]
    pub no_systemd: bool,
    /// Do not restart Klipper and Moonraker afterwards.
    #[arg(long)]
    pub no_restart: bool,
    /// Answer yes to every question: add `[respond]` to printer.cfg when missing, and show
    /// klipcal's page in Mainsail and Fluidd as an iframe webcam.
    #[arg(long)]
    pub yes: bool,
    /// Show klipcal's page in Mainsail and Fluidd without asking: register it with Moonraker
    /// as the webcam `klipcal`, service iframe (uninstall removes it).
    #[arg(long, conflicts_with = "no_webcam")]
    pub webcam: bool,
    /// Do not offer the webcam.
    #[arg(long)]
    pub no_webcam: bool,
    /// The GitHub repository (owner/name) Moonraker fetches releases from.
    #[arg(long, default_value = "klipcal/klipcal")]
    pub repo: String,
}

/// `klipcal uninstall`.
#[derive(Debug, Clone, clap::Args)]
pub struct UninstallArgs {
    /// The printer_data folder klipcal was installed into.
    #[arg(long, value_name = "DIR", default_value = "~/printer_data")]
    pub printer_data: String,
    /// Print every change as a diff and write nothing.
    #[arg(long)]
    pub dry_run: bool,
    /// Leave the systemd service alone.
    #[arg(long)]
    pub no_systemd: bool,
    /// Do not restart Klipper and Moonraker afterwards.
    #[arg(long)]
    pub no_restart: bool,
}

/// One file install changed.
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
struct Entry {
    /// Its bytes before the first install (`None`: install created it).
    original: Option<String>,
    /// What install wrote last.
    installed: String,
    /// Whole lines install added (taken out again if the user changed the file since).
    #[serde(default)]
    added_lines: Vec<String>,
    /// A section install added (`[update_manager klipcal]`).
    #[serde(default)]
    section: Option<String>,
}

/// What install did, for uninstall.
#[derive(Debug, Clone, Default, Serialize, Deserialize, PartialEq)]
struct Manifest {
    version: String,
    /// Text files by absolute path.
    files: BTreeMap<PathBuf, Entry>,
    /// Files install created outright (binary, release_info.json): removed on uninstall.
    created: Vec<PathBuf>,
    /// The systemd unit, when install wrote one.
    unit: Option<PathBuf>,
    /// The uid of the iframe webcam install registered with Moonraker (klipcal's page).
    #[serde(default)]
    webcam: Option<String>,
}

/// A planned text change.
struct Change {
    path: PathBuf,
    before: Option<String>,
    after: String,
    added_lines: Vec<String>,
    section: Option<String>,
}

fn expand(path: &str) -> PathBuf {
    crate::config::expand_home(path)
}

fn read_opt(path: &Path) -> anyhow::Result<Option<String>> {
    match std::fs::read(path) {
        Ok(b) => Ok(Some(String::from_utf8(b).with_context(|| {
            format!(
                "{} is not UTF-8 text; klipcal edits only text files",
                path.display()
            )
        })?)),
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => Ok(None),
        Err(e) => Err(anyhow!("cannot read {}: {e}", path.display())),
    }
}

/// Writes `bytes` to `path` through a temporary file and a rename.
fn write_atomic(path: &Path, bytes: &[u8]) -> anyhow::Result<()> {
    if let Some(dir) = path.parent() {
        std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
    }
    let tmp = path.with_extension("klipcal-tmp");
    std::fs::write(&tmp, bytes).with_context(|| format!("writing {}", tmp.display()))?;
    std::fs::rename(&tmp, path).with_context(|| format!("replacing {}", path.display()))
}

fn diff(path: &Path, before: Option<&str>, after: Option<&str>) -> String {
    let name = path.display().to_string();
    similar::TextDiff::from_lines(before.unwrap_or(""), after.unwrap_or(""))
        .unified_diff()
        .context_radius(2)
        .header(
            &if before.is_some() {
                format!("a{name}")
            } else {
                "/dev/null".into()
            },
            &if after.is_some() {
                format!("b{name}")
            } else {
                "/dev/null".into()
            },
        )
        .to_string()
}

/// The layout klipcal expects: `DIR/config/printer.cfg` and `DIR/config/moonraker.conf`.
fn layout(printer_data: &str) -> anyhow::Result<PathBuf> {
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
struct Printer {
    pd: PathBuf,
    /// Moonraker's websocket, from the folder's moonraker.conf `[server]` (or `--moonraker`).
    url: String,
    /// Moonraker's port, from moonraker.conf.
    port: u16,
    /// `printer_2` for `printer_2_data`; `None` for `printer_data`.
    instance: Option<String>,
    /// `klipcal` or `klipcal-printer_2`.
    service: String,
}

/// Reads which Moonraker serves `pd`, from its own moonraker.conf: never the default port's
/// printer when the folder is another's. `explicit` is `--moonraker`, when given.
fn printer(pd: &Path, explicit: Option<&str>) -> anyhow::Result<Printer> {
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
fn printer_config(config: &Config, p: &Printer) -> Config {
    let mut c = config.clone();
    if let Ok(Some(text)) = read_opt(&p.pd.join("config/klipcal.toml")) {
        if let Ok(own) = Config::parse(&text) {
            c.moonraker.api_key = own.moonraker.api_key;
        }
    }
    c.moonraker.url = p.url.clone();
    c
}

/// `path` with the home folder written as `~` (as the settings file's comments do).
fn tilde(path: &Path) -> String {
    let home = expand("~");
    match path.strip_prefix(&home) {
        Ok(rel) if home != Path::new("~") => format!("~/{}", rel.display()),
        _ => path.display().to_string(),
    }
}

/// Page ports this printer's klipcal must not take: those other printers' klipcal.toml
/// (beside this printer_data folder) name, and those a program listens on now.
fn taken_http_ports(pd: &Path) -> Vec<u16> {
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
async fn not_printing(config: &Config) -> anyhow::Result<Option<crate::moonraker::Files>> {
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

fn manifest_path(pd: &Path) -> PathBuf {
    pd.join("klipcal/install.json")
}

fn load_manifest(pd: &Path) -> anyhow::Result<Option<Manifest>> {
    match read_opt(&manifest_path(pd))? {
        Some(t) => Ok(Some(serde_json::from_str(&t).with_context(|| {
            format!("reading {}", manifest_path(pd).display())
        })?)),
        None => Ok(None),
    }
}

fn ask(question: &str) -> bool {
    print!("{question} [Y/n] ");
    let _ = std::io::stdout().flush();
    let mut line = String::new();
    if std::io::stdin().lock().read_line(&mut line).is_err() {
        return false;
    }
    !line.trim().to_ascii_lowercase().starts_with('n')
}

fn target_asset() -> String {
    let arch = match std::env::consts::ARCH {
        "arm" => "armv7",
        other => other,
    };
    format!("klipcal-{arch}-linux")
}

fn systemd_available() -> bool {
    Path::new("/run/systemd/system").is_dir()
}

fn unit_text(bin: &Path, p: &Printer) -> String {
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

fn systemctl(args: &[&str]) -> anyhow::Result<()> {
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
fn nix_is_root() -> bool {
    use std::os::unix::fs::MetadataExt;
    std::fs::metadata("/proc/self").is_ok_and(|m| m.uid() == 0)
}

/// `klipcal install`.
///
/// # Errors
/// No printer_data layout, a print running, a conflict (named), or an I/O failure.
pub(crate) async fn install(
    a: &InstallArgs,
    config: &Config,
    explicit_url: Option<&str>,
) -> anyhow::Result<ExitCode> {
    let pd = layout(&a.printer_data)?;
    let p = printer(&pd, explicit_url)?;
    let config = &printer_config(config, &p);
    println!(
        "printer {}: Moonraker at {}, service {}",
        pd.display(),
        p.url,
        p.service
    );
    let moonraker = not_printing(config).await?;
    let manifest = load_manifest(&pd)?.unwrap_or_default();
    let cfg_dir = pd.join("config");
    let bin_dir = expand(a.bin_dir.as_deref().unwrap_or(&match &p.instance {
        None => "~/klipcal".to_string(),
        Some(i) => format!("~/klipcal-{i}"),
    }));
    let asset = target_asset();
    let bin = bin_dir.join(&asset);

    let mut changes: Vec<Change> = Vec::new();
    let mut push = |path: PathBuf,
                    before: Option<String>,
                    after: String,
                    added: Vec<String>,
                    section: Option<String>| {
        if before.as_deref() != Some(after.as_str()) {
            changes.push(Change {
                path,
                before,
                after,
                added_lines: added,
                section,
            });
        }
    };
    // The macros, replaced on upgrade; the settings only when absent.
    let macros = cfg_dir.join("klipcal.cfg");
    push(
        macros.clone(),
        read_opt(&macros)?,
        crate::jobs::registry::macros_cfg(),
        vec![],
        None,
    );
    let settings = cfg_dir.join("klipcal.toml");
    // The settings the daemon will run with (for the page's address).
    let mut settings_text = read_opt(&settings)?;
    if let Some(before) = read_opt(&settings)? {
        match Config::parse(&before) {
            Err(e) => println!(
                "note: {} is kept as it is, but klipcal cannot read it: {e}",
                settings.display()
            ),
            Ok(c) if c.moonraker.url != p.url => println!(
                "note: {} is kept as it is, but its moonraker.url {} is not this printer's \
                 Moonraker ({}); edit it",
                settings.display(),
                c.moonraker.url,
                p.url
            ),
            Ok(_) => {}
        }
    } else {
        // This printer's Moonraker, its own data folder and a page port of its own.
        let port = plan::http_port(p.port, &taken_http_ports(&pd));
        let text = plan::settings(SETTINGS, &p.url, &tilde(&pd.join("klipcal")), port);
        settings_text = Some(text.clone());
        push(settings, None, text, vec![], None);
    }
    // printer.cfg: the include (and [respond]), checked against what Klipper reads now.
    let printer_cfg = cfg_dir.join("printer.cfg");
    let text = read_opt(&printer_cfg)?.unwrap_or_default();
    let loaded = crate::klipper::Config::load(&crate::fsio::FsFiles, &printer_cfg)
        .map_err(|e| anyhow!("reading the printer's config as Klipper would: {e}"))?;
    let add_respond = if plan::has_respond(&loaded) {
        false
    } else if a.yes || a.dry_run {
        true
    } else if std::io::stdin().is_terminal() {
        ask("Klipper has no [respond]; klipcal answers on the console with RESPOND. Add [respond] to printer.cfg?")
    } else {
        println!("note: printer.cfg has no [respond]; klipcal's console answers need it (run with --yes to add it)");
        false
    };
    if let Some(after) = plan::printer_cfg(
        &text,
        &loaded,
        &crate::jobs::registry::macros_cfg(),
        add_respond,
    )? {
        let added: Vec<String> = [plan::INCLUDE_LINE, plan::RESPOND_LINE]
            .iter()
            .filter(|l| {
                after.lines().filter(|x| x.trim() == **l).count()
                    > text.lines().filter(|x| x.trim() == **l).count()
            })
            .map(|l| (*l).to_string())
            .collect();
        push(printer_cfg.clone(), Some(text.clone()), after, added, None);
    }
    // moonraker.conf: the update_manager entry Moonraker can update a binary with.
    let conf = cfg_dir.join("moonraker.conf");
    let conf_text = read_opt(&conf)?.unwrap_or_default();
    let section = plan::update_manager_section(&bin_dir.display().to_string(), &a.repo, &p.service);
    let ours = manifest
        .files
        .get(&conf)
        .is_some_and(|e| e.section.is_some());
    if let Some(after) = plan::moonraker_conf(&conf_text, &section, ours)? {
        push(
            conf.clone(),
            Some(conf_text),
            after,
            vec![],
            Some(format!("[update_manager {}]", p.service)),
        );
    }
    // moonraker.asvc: Moonraker may restart klipcal (its update_manager needs that).
    let asvc = pd.join("moonraker.asvc");
    let asvc_before = read_opt(&asvc)?;
    if let Some(after) = plan::asvc(
        asvc_before.as_deref(),
        MOONRAKER_DEFAULT_SERVICES,
        &p.service,
    ) {
        push(
            asvc.clone(),
            asvc_before,
            after,
            vec![p.service.clone()],
            None,
        );
    }
    // release_info.json next to the binary: what Moonraker's executable type reads.
    let (owner, name) = a
        .repo
        .split_once('/')
        .ok_or_else(|| anyhow!("--repo {:?}: expected owner/name", a.repo))?;
    let rinfo = bin_dir.join("release_info.json");
    let rinfo_text = serde_json::to_string_pretty(&json!({
        "project_name": name, "project_owner": owner,
        "version": format!("v{}", env!("CARGO_PKG_VERSION")), "asset_name": asset,
    }))? + "\n";
    push(rinfo.clone(), read_opt(&rinfo)?, rinfo_text, vec![], None);

    let exe = std::env::current_exe().context("finding klipcal's own binary")?;
    let exe_bytes = std::fs::read(&exe).with_context(|| format!("reading {}", exe.display()))?;
    let copy_binary = std::fs::read(&bin).ok().as_deref() != Some(exe_bytes.as_slice());
    let unit_path = PathBuf::from(format!("/etc/systemd/system/{}.service", p.service));
    let use_systemd = !a.no_systemd && systemd_available();
    let unit = unit_text(&bin, &p);
    let write_unit =
        use_systemd && read_opt(&unit_path).ok().flatten().as_deref() != Some(unit.as_str());

    let webcam = webcam_plan(a, moonraker.as_ref(), &manifest, settings_text.as_deref()).await;

    if changes.is_empty() && !copy_binary && !write_unit && webcam.is_none() {
        println!(
            "klipcal is installed in {}; nothing to change",
            pd.display()
        );
        return Ok(ExitCode::SUCCESS);
    }
    if a.dry_run {
        for c in &changes {
            print!("{}", diff(&c.path, c.before.as_deref(), Some(&c.after)));
        }
        if copy_binary {
            println!("copy {} -> {}", exe.display(), bin.display());
        }
        if write_unit {
            print!(
                "{}",
                diff(
                    &unit_path,
                    read_opt(&unit_path).ok().flatten().as_deref(),
                    Some(&unit)
                )
            );
            println!(
                "systemctl daemon-reload && systemctl enable --now {}",
                p.service
            );
        }
        if let Some(w) = &webcam {
            println!("{}", w.describe());
        }
        println!("(dry run: nothing written)");
        return Ok(ExitCode::SUCCESS);
    }

    // Back up every file about to be edited, then write.
    let stamp = humantime::format_rfc3339_seconds(std::time::SystemTime::now())
        .to_string()
        .replace(':', "-");
    let backup = cfg_dir.join(format!("klipcal_backups/install-{stamp}"));
    let mut manifest = manifest;
    manifest.version = env!("CARGO_PKG_VERSION").into();
    for c in &changes {
        if let Some(before) = &c.before {
            let name = c
                .path
                .file_name()
                .map(|n| n.to_os_string())
                .unwrap_or_default();
            write_atomic(&backup.join(name), before.as_bytes())?;
        }
    }
    for c in &changes {
        write_atomic(&c.path, c.after.as_bytes())?;
        let e = manifest
            .files
            .entry(c.path.clone())
            .or_insert_with(|| Entry {
                original: c.before.clone(),
                installed: String::new(),
                added_lines: vec![],
                section: None,
            });
        e.installed = c.after.clone();
        for l in &c.added_lines {
            if !e.added_lines.contains(l) {
                e.added_lines.push(l.clone());
            }
        }
        if c.section.is_some() {
            e.section = c.section.clone();
        }
        println!(
            "{} {}",
            if c.before.is_some() {
                "edited "
            } else {
                "created"
            },
            c.path.display()
        );
    }
    if copy_binary {
        write_atomic(&bin, &exe_bytes)?;
        use std::os::unix::fs::PermissionsExt;
        std::fs::set_permissions(&bin, std::fs::Permissions::from_mode(0o755))?;
        println!("copied  {}", bin.display());
    }
    // The binary and release_info.json are klipcal's own files: removed on uninstall.
    manifest.files.remove(&rinfo);
    for p in [&bin, &rinfo] {
        if !manifest.created.contains(p) {
            manifest.created.push(p.clone());
        }
    }
    if write_unit {
        let tmp = std::env::temp_dir().join("klipcal.service");
        std::fs::write(&tmp, &unit)?;
        let st = std::process::Command::new(if nix_is_root() { "cp" } else { "sudo" })
            .args(if nix_is_root() { vec![] } else { vec!["cp"] })
            .arg(&tmp)
            .arg(&unit_path)
            .status()?;
        if !st.success() {
            bail!("could not write {}", unit_path.display());
        }
        manifest.unit = Some(unit_path.clone());
        systemctl(&["daemon-reload"])?;
        systemctl(&["enable", "--now", &p.service])?;
        if copy_binary {
            systemctl(&["restart", &p.service])?;
        }
        println!("service  {} enabled and started", p.service);
    } else if a.no_systemd || !systemd_available() {
        println!(
            "note: no systemd service installed; start it with: {} --config {} serve",
            bin.display(),
            pd.join("config/klipcal.toml").display()
        );
    }
    if let (Some(w), Some(files)) = (&webcam, &moonraker) {
        match webcam::register(files, w.uid.as_deref(), &w.url).await {
            Ok(uid) => {
                println!("{}", w.done());
                manifest.webcam = Some(uid);
            }
            Err(e) => println!(
                "note: Moonraker did not take the webcam {} ({e:#}); add it by hand (README: \
                 Inside Mainsail or Fluidd)",
                webcam::NAME
            ),
        }
    }
    write_atomic(
        &manifest_path(&pd),
        serde_json::to_string_pretty(&manifest)?.as_bytes(),
    )?;
    if !changes.is_empty() {
        println!("backups in {}", backup.display());
    }
    if let (Some(files), false) = (&moonraker, a.no_restart) {
        restart(
            files,
            &changes.iter().map(|c| c.path.clone()).collect::<Vec<_>>(),
            &pd,
        )
        .await;
    }
    Ok(ExitCode::SUCCESS)
}

/// A webcam install adds or updates.
struct WebcamChange {
    /// The webcam to update (klipcal's own, from an earlier install); `None` adds one.
    uid: Option<String>,
    url: String,
    /// The address it had.
    from: Option<String>,
}

impl WebcamChange {
    fn describe(&self) -> String {
        match &self.from {
            None => format!(
                "add Moonraker webcam {} (service {}): {}",
                webcam::NAME,
                webcam::SERVICE,
                self.url
            ),
            Some(from) => format!(
                "update Moonraker webcam {}: {from} -> {}",
                webcam::NAME,
                self.url
            ),
        }
    }

    fn done(&self) -> String {
        format!(
            "webcam   {} {} in Moonraker: klipcal's page {} shows in Mainsail (\"HTML Iframe\") \
             and Fluidd's webcam panels",
            webcam::NAME,
            if self.from.is_some() {
                "updated"
            } else {
                "added"
            },
            self.url
        )
    }
}

/// Whether install adds (or updates) klipcal's page as an iframe webcam: asked on a terminal,
/// `--webcam`/`--yes` add it, `--no-webcam` skips it; needs Moonraker and the page on.
async fn webcam_plan(
    a: &InstallArgs,
    moonraker: Option<&crate::moonraker::Files>,
    manifest: &Manifest,
    settings: Option<&str>,
) -> Option<WebcamChange> {
    if a.no_webcam {
        return None;
    }
    let files = moonraker?;
    let Some(c) = settings.and_then(|t| Config::parse(t).ok()) else {
        println!("note: klipcal.toml does not read; no webcam for klipcal's page");
        return None;
    };
    if !c.http.enabled {
        println!("note: klipcal's page is off ([http] enabled = false); no webcam for it");
        return None;
    }
    let Ok(bind) = c.http.bind.parse::<std::net::SocketAddr>() else {
        return None;
    };
    let url = crate::http::page_address_here(bind);
    if !url.starts_with("http://") || url.contains(' ') {
        println!(
            "note: klipcal's page is at {url}, which a browser elsewhere cannot open; no webcam \
             for it"
        );
        return None;
    }
    let list = match webcam::list(files).await {
        Ok(l) => l,
        Err(e) => {
            println!("note: Moonraker's webcam list did not answer ({e:#}); no webcam added");
            return None;
        }
    };
    match webcam::decide(&list, manifest.webcam.as_deref(), &url) {
        webcam::Decision::Nothing { .. } => None,
        webcam::Decision::Foreign { url: theirs } => {
            println!(
                "note: Moonraker has a webcam named {} already ({theirs}) that klipcal did not \
                 add: left as it is",
                webcam::NAME
            );
            None
        }
        webcam::Decision::Update { uid, from } => Some(WebcamChange {
            uid: Some(uid),
            url,
            from: Some(from),
        }),
        webcam::Decision::Add => {
            let add = if a.webcam || a.yes || a.dry_run {
                true
            } else if std::io::stdin().is_terminal() {
                ask(&format!(
                    "Show klipcal's page ({url}) inside Mainsail and Fluidd, as the iframe webcam \
                     \"{}\"?",
                    webcam::NAME
                ))
            } else {
                println!(
                    "note: klipcal's page ({url}) can show inside Mainsail and Fluidd as an \
                     iframe webcam: run with --webcam to add it"
                );
                false
            };
            add.then_some(WebcamChange {
                uid: None,
                url,
                from: None,
            })
        }
    }
}

/// Files under `dir` and their bytes (0, 0 when it does not exist).
fn tree_size(dir: &Path) -> (usize, u64) {
    let mut out = (0, 0);
    let Ok(rd) = std::fs::read_dir(dir) else {
        return out;
    };
    for e in rd.flatten() {
        let Ok(t) = e.file_type() else { continue };
        if t.is_dir() {
            let (n, b) = tree_size(&e.path());
            out = (out.0 + n, out.1 + b);
        } else {
            out = (
                out.0 + 1,
                out.1 + e.metadata().map(|m| m.len()).unwrap_or(0),
            );
        }
    }
    out
}

/// Restarts Klipper when its config changed and Moonraker when its did.
async fn restart(files: &crate::moonraker::Files, changed: &[PathBuf], pd: &Path) {
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

/// `klipcal uninstall`.
///
/// # Errors
/// No install recorded, a print running, or an I/O failure.
pub(crate) async fn uninstall(
    a: &UninstallArgs,
    config: &Config,
    explicit_url: Option<&str>,
) -> anyhow::Result<ExitCode> {
    let pd = layout(&a.printer_data)?;
    let Some(manifest) = load_manifest(&pd)? else {
        bail!(
            "klipcal install has not run on {} (no {}); nothing to undo",
            pd.display(),
            manifest_path(&pd).display()
        );
    };
    let p = printer(&pd, explicit_url)?;
    let config = &printer_config(config, &p);
    // Where this printer's klipcal kept its data, read before its settings file goes.
    let data_dir = read_opt(&pd.join("config/klipcal.toml"))
        .ok()
        .flatten()
        .and_then(|t| Config::parse(&t).ok())
        .map_or_else(|| pd.join("klipcal"), |c| expand(&c.daemon.data_dir));
    let service = manifest
        .unit
        .as_ref()
        .and_then(|u| u.file_stem())
        .map_or_else(|| p.service.clone(), |s| s.to_string_lossy().to_string());
    let moonraker = not_printing(config).await?;
    let mut writes: Vec<(PathBuf, Option<String>, Option<String>, bool)> = Vec::new();
    for (path, e) in &manifest.files {
        let current = read_opt(path)?;
        match current {
            None => {}
            Some(cur) if cur == e.installed => {
                writes.push((path.clone(), Some(cur), e.original.clone(), false));
            }
            Some(cur) => {
                let after = plan::remove_additions(&cur, &e.added_lines, e.section.as_deref());
                if e.original.is_none() && after == cur {
                    println!(
                        "kept    {} (changed since install: it is yours now)",
                        path.display()
                    );
                } else if after != cur {
                    writes.push((path.clone(), Some(cur), Some(after), true));
                }
            }
        }
    }
    if a.dry_run {
        for (p, before, after, _) in &writes {
            print!("{}", diff(p, before.as_deref(), after.as_deref()));
        }
        for p in &manifest.created {
            println!("remove {}", p.display());
        }
        if let Some(u) = &manifest.unit {
            println!("systemctl disable --now {service}; remove {}", u.display());
        }
        if manifest.webcam.is_some() {
            println!("remove Moonraker webcam {}", webcam::NAME);
        }
        println!("(dry run: nothing written)");
        return Ok(ExitCode::SUCCESS);
    }
    if let (Some(u), false) = (&manifest.unit, a.no_systemd) {
        systemctl(&["disable", "--now", &service])?;
        let st = std::process::Command::new(if nix_is_root() { "rm" } else { "sudo" })
            .args(if nix_is_root() { vec![] } else { vec!["rm"] })
            .args(["-f"])
            .arg(u)
            .status()?;
        if !st.success() {
            bail!("could not remove {}", u.display());
        }
        systemctl(&["daemon-reload"])?;
        println!("service  {service} stopped and removed");
    }
    for (p, _, after, partial) in &writes {
        match after {
            Some(t) => write_atomic(p, t.as_bytes())?,
            None => std::fs::remove_file(p).with_context(|| format!("removing {}", p.display()))?,
        }
        println!(
            "{} {}",
            match (after, partial) {
                (None, _) => "removed ",
                (Some(_), false) => "restored",
                (Some(_), true) => "cleaned ",
            },
            p.display()
        );
    }
    for p in &manifest.created {
        match std::fs::remove_file(p) {
            Ok(()) => println!("removed  {}", p.display()),
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => {}
            Err(e) => bail!("removing {}: {e}", p.display()),
        }
        if let Some(dir) = p.parent() {
            let _ = std::fs::remove_dir(dir); // only when empty
        }
    }
    if let Some(uid) = &manifest.webcam {
        match &moonraker {
            Some(files) => match webcam::remove(files, uid).await {
                Ok(true) => println!("removed  Moonraker webcam {}", webcam::NAME),
                Ok(false) => {}
                Err(e) => println!(
                    "note: Moonraker did not remove the webcam {} ({e:#}); remove it in \
                     Mainsail's or Fluidd's webcam settings",
                    webcam::NAME
                ),
            },
            None => println!(
                "note: remove the webcam {} in Mainsail's or Fluidd's webcam settings (Moonraker \
                 did not answer)",
                webcam::NAME
            ),
        }
    }
    std::fs::remove_file(manifest_path(&pd))?;
    let _ = std::fs::remove_dir(pd.join("klipcal")); // only when nothing else is in it
    println!("klipcal uninstalled from {}", pd.display());
    let cfg = pd.join("config");
    let left: Vec<String> = [
        (data_dir, "klipcal's database: sessions, readings, results"),
        (
            cfg.join("klipcal"),
            "pictures and plots of the calibrations",
        ),
        (
            cfg.join("klipcal_backups"),
            "copies of config files from before klipcal's edits",
        ),
        (pd.join("gcodes/klipcal"), "the calibration prints' G-code"),
    ]
    .into_iter()
    .filter_map(|(dir, what)| {
        let (n, bytes) = tree_size(&dir);
        (n > 0).then(|| {
            format!(
                "  {} ({n} file(s), {:.0} KB): {what}",
                dir.display(),
                bytes as f64 / 1024.0
            )
        })
    })
    .collect();
    if !left.is_empty() {
        println!("left in place (yours to keep or delete):");
        for l in &left {
            println!("{l}");
        }
    }
    if let Some(files) = &moonraker {
        // A daemon this uninstall did not stop (started by hand, or by another unit).
        let stopped = manifest.unit.is_some() && !a.no_systemd;
        let limit = Duration::from_secs(if stopped { 5 } else { 0 });
        let start = std::time::Instant::now();
        loop {
            let connected = files
                .get("/server/extensions/list")
                .await
                .ok()
                .and_then(|v| v["agents"].as_array().cloned())
                .is_some_and(|a| a.iter().any(|x| x["name"] == "klipcal"));
            if !connected {
                break;
            }
            if start.elapsed() >= limit {
                println!(
                    "warning: a klipcal daemon is still connected to this printer's Moonraker \
                     ({}); uninstall did not stop it (started by hand or by another service?): \
                     stop it, it still acts on this printer",
                    p.url
                );
                break;
            }
            tokio::time::sleep(Duration::from_millis(300)).await;
        }
    }
    if let (Some(files), false) = (&moonraker, a.no_restart) {
        let changed: Vec<PathBuf> = writes.iter().map(|w| w.0.clone()).collect();
        restart(files, &changed, &pd).await;
    }
    Ok(ExitCode::SUCCESS)
}
