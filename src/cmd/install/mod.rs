//! `klipcal install` / `klipcal uninstall`: puts klipcal on a printer host in one command and
//! takes it off again. The edits are planned by the pure [`plan`] (the same config reader the
//! calibrations use decides what Klipper already reads), every edited file is backed up, and
//! a manifest (`printer_data/klipcal/install.json`) records each file's original bytes so
//! uninstall restores them byte for byte — or, where the user changed a file since, takes out
//! only klipcal's own lines. `--dry-run` prints every change as a diff and writes nothing.

//!
//! The layout: [`plan`] decides the edits (pure); `files` reads, writes and diffs; `manifest`
//! records what install did; `host` finds the printer, its Moonraker and systemd; `webcam`
//! registers the page with Moonraker; this file runs install, `uninstall` undoes it.

mod files;
mod host;
mod manifest;
pub mod plan;
mod uninstall;
mod webcam;

pub(crate) use uninstall::uninstall;

use std::io::IsTerminal;
use std::path::PathBuf;
use std::process::ExitCode;

use anyhow::{anyhow, bail, Context};
use serde_json::json;

use crate::config::Config;
use files::{diff, expand, read_opt, tilde, write_atomic};
use host::{
    ask, layout, nix_is_root, not_printing, printer, printer_config, restart, systemctl,
    systemd_available, taken_http_ports, target_asset, unit_text, Printer,
};
use manifest::{load_manifest, manifest_path, Change, Entry, Manifest};
use webcam::webcam_plan;

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
    let bin_dir = expand(a.bin_dir.as_deref().unwrap_or(&match &p.instance {
        None => "~/klipcal".to_string(),
        Some(i) => format!("~/klipcal-{i}"),
    }));
    let asset = target_asset();
    let t = Target {
        cfg_dir: pd.join("config"),
        bin: bin_dir.join(&asset),
        pd,
        p,
        bin_dir,
        asset,
    };

    let mut changes = Changes::default();
    let settings_text = t.plan_settings(&mut changes)?;
    t.plan_printer_cfg(a, moonraker.as_ref(), &mut changes)
        .await?;
    let rinfo = t.plan_moonraker(a, &manifest, &mut changes)?;
    let changes = changes.0;

    let exe = std::env::current_exe().context("finding klipcal's own binary")?;
    let exe_bytes = std::fs::read(&exe).with_context(|| format!("reading {}", exe.display()))?;
    let copy_binary = std::fs::read(&t.bin).ok().as_deref() != Some(exe_bytes.as_slice());
    let unit = Unit::plan(a, &t);
    let webcam = webcam_plan(a, moonraker.as_ref(), &manifest, settings_text.as_deref()).await;

    if changes.is_empty() && !copy_binary && !unit.write && webcam.is_none() {
        println!(
            "klipcal is installed in {}; nothing to change",
            t.pd.display()
        );
        return Ok(ExitCode::SUCCESS);
    }
    if a.dry_run {
        t.print_dry_run(
            &changes,
            copy_binary.then_some(&exe),
            &unit,
            webcam.as_ref(),
        );
        return Ok(ExitCode::SUCCESS);
    }

    let mut manifest = manifest;
    manifest.version = env!("CARGO_PKG_VERSION").into();
    let backup = t.write_changes(&changes, &mut manifest)?;
    if copy_binary {
        write_atomic(&t.bin, &exe_bytes)?;
        use std::os::unix::fs::PermissionsExt;
        std::fs::set_permissions(&t.bin, std::fs::Permissions::from_mode(0o755))?;
        println!("copied  {}", t.bin.display());
    }
    // The binary and release_info.json are klipcal's own files: removed on uninstall.
    manifest.files.remove(&rinfo);
    for p in [&t.bin, &rinfo] {
        if !manifest.created.contains(p) {
            manifest.created.push(p.clone());
        }
    }
    t.install_unit(a, &unit, copy_binary, &mut manifest)?;
    if let (Some(w), Some(files)) = (&webcam, &moonraker) {
        match webcam::register(files, w.uid.as_deref(), &w.url).await {
            Ok(uid) => {
                println!("{}", w.done());
                manifest.webcam = Some(uid);
            }
            Err(e) => println!(
                "note: Moonraker did not take the webcam {} ({e:#}); add it by hand (docs/page-and-api.md: \
                 Inside Mainsail or Fluidd)",
                webcam::NAME
            ),
        }
    }
    write_atomic(
        &manifest_path(&t.pd),
        serde_json::to_string_pretty(&manifest)?.as_bytes(),
    )?;
    if !changes.is_empty() {
        println!("backups in {}", backup.display());
    }
    if let (Some(files), false) = (&moonraker, a.no_restart) {
        restart(
            files,
            &changes.iter().map(|c| c.path.clone()).collect::<Vec<_>>(),
            &t.pd,
        )
        .await;
    }
    Ok(ExitCode::SUCCESS)
}

/// Where install puts things on this printer.
struct Target {
    /// The printer_data folder.
    pd: PathBuf,
    p: Printer,
    /// `printer_data/config`.
    cfg_dir: PathBuf,
    /// The binary's folder (the update_manager's `path`), the release asset's name, and the
    /// binary's path in that folder.
    bin_dir: PathBuf,
    asset: String,
    bin: PathBuf,
}

/// The text changes install plans, each only when it changes the file.
#[derive(Default)]
struct Changes(Vec<Change>);

impl Changes {
    fn push(
        &mut self,
        path: PathBuf,
        before: Option<String>,
        after: String,
        added: Vec<String>,
        section: Option<String>,
    ) {
        if before.as_deref() != Some(after.as_str()) {
            self.0.push(Change {
                path,
                before,
                after,
                added_lines: added,
                section,
            });
        }
    }
}

/// The systemd unit: its path and text, and whether it is to be written.
struct Unit {
    path: PathBuf,
    text: String,
    write: bool,
}

impl Unit {
    fn plan(a: &InstallArgs, t: &Target) -> Unit {
        let path = PathBuf::from(format!("/etc/systemd/system/{}.service", t.p.service));
        let use_systemd = !a.no_systemd && systemd_available();
        let text = unit_text(&t.bin, &t.p);
        let write = use_systemd && read_opt(&path).ok().flatten().as_deref() != Some(text.as_str());
        Unit { path, text, write }
    }
}

impl Target {
    /// The macros, replaced on upgrade; the settings only when absent (this printer's
    /// Moonraker, its own data folder and a page port of its own). Returns the settings the
    /// daemon will run with (for the page's address).
    fn plan_settings(&self, changes: &mut Changes) -> anyhow::Result<Option<String>> {
        let macros = self.cfg_dir.join("klipcal.cfg");
        changes.push(
            macros.clone(),
            read_opt(&macros)?,
            crate::jobs::registry::macros_cfg(),
            vec![],
            None,
        );
        let settings = self.cfg_dir.join("klipcal.toml");
        let mut settings_text = read_opt(&settings)?;
        if let Some(before) = read_opt(&settings)? {
            match Config::parse(&before) {
                Err(e) => println!(
                    "note: {} is kept as it is, but klipcal cannot read it: {e}",
                    settings.display()
                ),
                Ok(c) if c.moonraker.url != self.p.url => println!(
                    "note: {} is kept as it is, but its moonraker.url {} is not this printer's \
                     Moonraker ({}); edit it",
                    settings.display(),
                    c.moonraker.url,
                    self.p.url
                ),
                Ok(_) => {}
            }
        } else {
            let port = plan::http_port(self.p.port, &taken_http_ports(&self.pd));
            let text = plan::settings(
                SETTINGS,
                &self.p.url,
                &tilde(&self.pd.join("klipcal")),
                port,
            );
            settings_text = Some(text.clone());
            changes.push(settings, None, text, vec![], None);
        }
        Ok(settings_text)
    }

    /// printer.cfg: the include (and `[respond]`, asked for when Klipper lacks it), checked
    /// against what Klipper reads now.
    async fn plan_printer_cfg(
        &self,
        a: &InstallArgs,
        moonraker: Option<&crate::moonraker::Files>,
        changes: &mut Changes,
    ) -> anyhow::Result<()> {
        let printer_cfg = self.cfg_dir.join("printer.cfg");
        let text = read_opt(&printer_cfg)?.unwrap_or_default();
        let loaded = crate::klipper::Config::load(&crate::fsio::FsFiles, &printer_cfg)
            .map_err(|e| anyhow!("reading the printer's config as Klipper would: {e}"))?;
        // Kalico loads `respond` without a section (Klipper's printer.info says which it is;
        // the running RESPOND itself says nothing of the file, which may have changed since).
        let respond_by_default = match moonraker {
            Some(f) => f.get("/printer/info").await.is_ok_and(|i| {
                crate::klipper::Dialect::of_app(i["app"].as_str())
                    == crate::klipper::Dialect::Kalico
            }),
            None => false,
        };
        let add_respond = if plan::has_respond(&loaded) || respond_by_default {
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
            changes.push(printer_cfg.clone(), Some(text.clone()), after, added, None);
        }
        Ok(())
    }

    /// moonraker.conf's update_manager entry Moonraker can update a binary with;
    /// moonraker.asvc, so Moonraker may restart klipcal; release_info.json next to the binary
    /// (what Moonraker's executable type reads), whose path is returned.
    fn plan_moonraker(
        &self,
        a: &InstallArgs,
        manifest: &Manifest,
        changes: &mut Changes,
    ) -> anyhow::Result<PathBuf> {
        let p = &self.p;
        let conf = self.cfg_dir.join("moonraker.conf");
        let conf_text = read_opt(&conf)?.unwrap_or_default();
        let section =
            plan::update_manager_section(&self.bin_dir.display().to_string(), &a.repo, &p.service);
        let ours = manifest
            .files
            .get(&conf)
            .is_some_and(|e| e.section.is_some());
        if let Some(after) = plan::moonraker_conf(&conf_text, &section, ours)? {
            changes.push(
                conf.clone(),
                Some(conf_text),
                after,
                vec![],
                Some(format!("[update_manager {}]", p.service)),
            );
        }
        let asvc = self.pd.join("moonraker.asvc");
        let asvc_before = read_opt(&asvc)?;
        if let Some(after) = plan::asvc(
            asvc_before.as_deref(),
            MOONRAKER_DEFAULT_SERVICES,
            &p.service,
        ) {
            changes.push(
                asvc.clone(),
                asvc_before,
                after,
                vec![p.service.clone()],
                None,
            );
        }
        let (owner, name) = a
            .repo
            .split_once('/')
            .ok_or_else(|| anyhow!("--repo {:?}: expected owner/name", a.repo))?;
        let rinfo = self.bin_dir.join("release_info.json");
        let rinfo_text = serde_json::to_string_pretty(&json!({
            "project_name": name, "project_owner": owner,
            "version": format!("v{}", env!("CARGO_PKG_VERSION")), "asset_name": self.asset,
        }))? + "\n";
        changes.push(rinfo.clone(), read_opt(&rinfo)?, rinfo_text, vec![], None);
        Ok(rinfo)
    }

    /// `--dry-run`: every change as a diff, the copy (`copy`: the binary to copy), the unit
    /// and the webcam; nothing written.
    fn print_dry_run(
        &self,
        changes: &[Change],
        copy: Option<&PathBuf>,
        unit: &Unit,
        webcam: Option<&webcam::WebcamChange>,
    ) {
        for c in changes {
            print!("{}", diff(&c.path, c.before.as_deref(), Some(&c.after)));
        }
        if let Some(exe) = copy {
            println!("copy {} -> {}", exe.display(), self.bin.display());
        }
        if unit.write {
            print!(
                "{}",
                diff(
                    &unit.path,
                    read_opt(&unit.path).ok().flatten().as_deref(),
                    Some(&unit.text)
                )
            );
            println!(
                "systemctl daemon-reload && systemctl enable --now {}",
                self.p.service
            );
        }
        if let Some(w) = webcam {
            println!("{}", w.describe());
        }
        println!("(dry run: nothing written)");
    }

    /// Backs up every file about to be edited, then writes the changes, each recorded in the
    /// manifest. Returns the backup folder.
    fn write_changes(
        &self,
        changes: &[Change],
        manifest: &mut Manifest,
    ) -> anyhow::Result<PathBuf> {
        let stamp = humantime::format_rfc3339_seconds(std::time::SystemTime::now())
            .to_string()
            .replace(':', "-");
        let backup = self
            .cfg_dir
            .join(format!("klipcal_backups/install-{stamp}"));
        for c in changes {
            if let Some(before) = &c.before {
                let name = c
                    .path
                    .file_name()
                    .map(|n| n.to_os_string())
                    .unwrap_or_default();
                write_atomic(&backup.join(name), before.as_bytes())?;
            }
        }
        for c in changes {
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
        Ok(backup)
    }

    /// The systemd unit written, enabled and started (restarted when the binary changed);
    /// without systemd, how to start klipcal.
    fn install_unit(
        &self,
        a: &InstallArgs,
        unit: &Unit,
        copied: bool,
        manifest: &mut Manifest,
    ) -> anyhow::Result<()> {
        let service = &self.p.service;
        if unit.write {
            let tmp = std::env::temp_dir().join("klipcal.service");
            std::fs::write(&tmp, &unit.text)?;
            let st = std::process::Command::new(if nix_is_root() { "cp" } else { "sudo" })
                .args(if nix_is_root() { vec![] } else { vec!["cp"] })
                .arg(&tmp)
                .arg(&unit.path)
                .status()?;
            if !st.success() {
                bail!("could not write {}", unit.path.display());
            }
            manifest.unit = Some(unit.path.clone());
            systemctl(&["daemon-reload"])?;
            systemctl(&["enable", "--now", service])?;
            if copied {
                systemctl(&["restart", service])?;
            }
            println!("service  {service} enabled and started");
        } else if a.no_systemd || !systemd_available() {
            println!(
                "note: no systemd service installed; start it with: {} --config {} serve",
                self.bin.display(),
                self.pd.join("config/klipcal.toml").display()
            );
        }
        Ok(())
    }
}
