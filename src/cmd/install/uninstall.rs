//! `klipcal uninstall`: restores each file install changed from the manifest (or takes out only
//! klipcal's lines where the user changed it since), removes the service, the created files and
//! the webcam, and says what data it leaves in place.

use std::path::{Path, PathBuf};
use std::process::ExitCode;
use std::time::Duration;

use anyhow::{bail, Context};

use super::files::{diff, expand, read_opt, tree_size, write_atomic};
use super::host::{layout, nix_is_root, not_printing, printer, printer_config, restart, systemctl};
use super::manifest::{load_manifest, manifest_path, Manifest};
use super::{plan, webcam, UninstallArgs};
use crate::config::Config;

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
    let writes = planned_writes(&manifest)?;
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
        remove_service(u, &service)?;
    }
    apply_writes(&writes)?;
    remove_created(&manifest.created)?;
    if let Some(uid) = &manifest.webcam {
        remove_webcam(moonraker.as_ref(), uid).await;
    }
    std::fs::remove_file(manifest_path(&pd))?;
    let _ = std::fs::remove_dir(pd.join("klipcal")); // only when nothing else is in it
    println!("klipcal uninstalled from {}", pd.display());
    print_left_in_place(&pd, data_dir);
    if let Some(files) = &moonraker {
        // A daemon this uninstall did not stop (started by hand, or by another unit).
        let stopped = manifest.unit.is_some() && !a.no_systemd;
        warn_if_still_connected(files, stopped, &p.url).await;
    }
    if let (Some(files), false) = (&moonraker, a.no_restart) {
        let changed: Vec<PathBuf> = writes.iter().map(|w| w.0.clone()).collect();
        restart(files, &changed, &pd).await;
    }
    Ok(ExitCode::SUCCESS)
}

/// A file uninstall writes: its path, its text now, what it gets (`None`: removed), and
/// whether only klipcal's lines are taken out (the user changed it since install).
type Write = (PathBuf, Option<String>, Option<String>, bool);

/// Each file install changed: restored when it is as install left it, else cleaned of
/// klipcal's lines; one install created and the user changed since is theirs now.
fn planned_writes(manifest: &Manifest) -> anyhow::Result<Vec<Write>> {
    let mut writes: Vec<Write> = Vec::new();
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
    Ok(writes)
}

/// The systemd unit `u` of `service`: stopped, disabled, removed.
fn remove_service(u: &Path, service: &str) -> anyhow::Result<()> {
    systemctl(&["disable", "--now", service])?;
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
    Ok(())
}

fn apply_writes(writes: &[Write]) -> anyhow::Result<()> {
    for (p, _, after, partial) in writes {
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
    Ok(())
}

/// The files install created (binary, release_info.json), and their folder when empty.
fn remove_created(created: &[PathBuf]) -> anyhow::Result<()> {
    for p in created {
        match std::fs::remove_file(p) {
            Ok(()) => println!("removed  {}", p.display()),
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => {}
            Err(e) => bail!("removing {}: {e}", p.display()),
        }
        if let Some(dir) = p.parent() {
            let _ = std::fs::remove_dir(dir); // only when empty
        }
    }
    Ok(())
}

/// The iframe webcam install registered with Moonraker, or how to remove it by hand.
async fn remove_webcam(moonraker: Option<&crate::moonraker::Files>, uid: &str) {
    match moonraker {
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

/// What uninstall leaves: klipcal's data, pictures, backups and prints.
fn print_left_in_place(pd: &Path, data_dir: PathBuf) {
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
}

/// A klipcal daemon still connected to Moonraker after uninstall (one it did not stop,
/// started by hand or by another unit): waits up to 5 s when uninstall `stopped` the service,
/// then warns.
async fn warn_if_still_connected(files: &crate::moonraker::Files, stopped: bool, url: &str) {
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
                 ({url}); uninstall did not stop it (started by hand or by another service?): \
                 stop it, it still acts on this printer"
            );
            break;
        }
        tokio::time::sleep(Duration::from_millis(300)).await;
    }
}
