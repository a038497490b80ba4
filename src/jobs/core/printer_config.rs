//! The printer's Klipper config as Moonraker serves it: fetch every file of the `config` root
//! into memory (so the pure parser follows includes and globs), and write edited values back —
//! backup first, edit in place, FIRMWARE_RESTART, confirm through configfile.settings, restore
//! the backups byte for byte when Klipper does not come back. Only while the printer is idle.

use std::path::{Path, PathBuf};
use std::time::Duration;

use anyhow::{anyhow, bail, Context};
use serde::{Deserialize, Serialize};
use serde_json::{json, Value};

use crate::klipper::{self, Config, MemFiles};
use crate::moonraker::answers::{parse_list, FileRoot, ListedFile, PrinterInfo};
use crate::moonraker::{Event, Files, Moonraker};

/// The loaded config and where its files live.
pub struct PrinterConfig {
    /// The parsed config.
    pub config: Config,
    /// Absolute folder of Moonraker's `config` root.
    pub root: PathBuf,
    /// Files of the config klipcal must not write (a symlink leading out of the config root,
    /// another project's git checkout), with the reason.
    pub protected: Vec<klipper::Protected>,
}

/// One value to write: `[section] key = value`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ValueSet {
    /// Section, e.g. `stepper_x`.
    pub section: String,
    /// Option, e.g. `rotation_distance`.
    pub key: String,
    /// New value text.
    pub value: String,
}

/// What an apply did.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ApplyReport {
    /// Files changed, relative to the config root.
    pub files: Vec<String>,
    /// Where the backups went, relative to the config root.
    pub backup_dir: String,
    /// `(section, key, old, new)` for each value (AWD companions included).
    pub changes: Vec<(String, String, String, String)>,
    /// What the user should know: companions scaled with the axis, values written to
    /// `klipcal_overrides.cfg` instead of a protected file, and why.
    #[serde(default)]
    pub notes: Vec<String>,
}

/// `printer.info`, waiting up to 15 s while Moonraker is still reconnecting to Klipper (it
/// answers "Klippy Host not connected" for a moment after a restart reports ready).
async fn printer_info_settled(m: &Moonraker) -> anyhow::Result<PrinterInfo> {
    let deadline = tokio::time::Instant::now() + Duration::from_secs(15);
    loop {
        match m.printer_info().await {
            Ok(v) => return Ok(v),
            Err(e)
                if tokio::time::Instant::now() < deadline
                    && e.to_string().contains("Klippy Host not connected") =>
            {
                tokio::time::sleep(Duration::from_millis(250)).await;
            }
            Err(e) => return Err(e.into()),
        }
    }
}

/// Reads the config Klipper runs (`printer.info` → `config_file`) through Moonraker: exactly
/// the files its `[include]` patterns match in Moonraker's listing of the `config` root,
/// whatever their extension (`[include configs/*]` also reads `steppers.cfg.bak`, as Klipper
/// does), downloading each once. A pattern matching a folder fails, as it fails Klipper.
///
/// # Errors
/// Moonraker failures, or a config Klipper's own rules reject.
pub async fn fetch(m: &Moonraker, files: &Files) -> anyhow::Result<PrinterConfig> {
    let roots: Vec<FileRoot> = parse_list("file roots", files.get("/server/files/roots").await?)?;
    let root = roots
        .into_iter()
        .find(|r| r.name == "config")
        .map(|r| PathBuf::from(r.path))
        .ok_or_else(|| anyhow!("Moonraker has no `config` root"))?;
    let info = printer_info_settled(m).await?;
    let main = info
        .config_file
        .as_deref()
        .map(PathBuf::from)
        .ok_or_else(|| anyhow!("printer.info names no config_file"))?;
    let listed: Vec<String> = parse_list::<ListedFile>(
        "config file list",
        files.get("/server/files/list?root=config").await?,
    )?
    .into_iter()
    .map(|f| f.path)
    .collect();
    let mut remote = Listed::new(&root, &listed);
    // Kalico reads references, value includes and recursive include globs.
    let dialect = klipper::Dialect::of_app(info.app.as_deref());
    // Load; every file the loader asked for and did not have is downloaded, then load again
    // (each round reaches one include level deeper).
    loop {
        let result = Config::load_as(&remote, &main, dialect);
        let wanted = remote.take_wanted();
        if wanted.is_empty() {
            let config = result.with_context(|| format!("reading {}", main.display()))?;
            let protected = protected_files(&root, &listed, &config);
            return Ok(PrinterConfig {
                config,
                root,
                protected,
            });
        }
        for path in wanted {
            let rel = path
                .strip_prefix(&root)
                .map(|p| p.to_string_lossy().into_owned())
                .unwrap_or_default();
            let bytes = files
                .download("config", &rel)
                .await
                .with_context(|| format!("downloading config/{rel}"))?;
            remote.insert(path, bytes);
        }
    }
}

/// The config's files klipcal must not write, and why: reached through a symlink that leaves
/// the config root, or inside another project's git checkout (a folder below the root with its
/// own `.git`; the root itself being a git repository is the user's own backup and fine).
/// Looked at on the local file system when the root is there (klipcal runs beside Moonraker),
/// and in Moonraker's listing (which shows `.git` folders) in any case.
fn protected_files(root: &Path, listed: &[String], config: &Config) -> Vec<klipper::Protected> {
    let mut out: Vec<klipper::Protected> = Vec::new();
    let real_root = std::fs::canonicalize(root).ok();
    let git_dirs: Vec<PathBuf> = listed
        .iter()
        .filter_map(|rel| {
            let p = Path::new(rel);
            let mut dir = PathBuf::new();
            for c in p.components() {
                if c.as_os_str() == ".git" {
                    return (!dir.as_os_str().is_empty()).then(|| root.join(&dir));
                }
                dir.push(c);
            }
            None
        })
        .collect();
    for f in config.files() {
        let mut reason = None;
        if let (Some(real_root), Ok(real)) = (&real_root, std::fs::canonicalize(&f.path)) {
            if !real.starts_with(real_root) {
                reason = Some(format!(
                    "it is reached through a symlink that leads out of the config folder {} \
                     (to {})",
                    root.display(),
                    real.display()
                ));
            } else {
                reason = real
                    .ancestors()
                    .skip(1)
                    .take_while(|a| *a != real_root.as_path())
                    .find(|a| a.join(".git").exists())
                    .map(git_reason);
            }
        }
        if reason.is_none() {
            reason = git_dirs
                .iter()
                .find(|d| f.path.starts_with(d))
                .map(|d| git_reason(d));
        }
        if let Some(reason) = reason {
            out.push(klipper::Protected {
                path: f.path.clone(),
                reason,
            });
        }
    }
    out
}

fn git_reason(dir: &Path) -> String {
    format!(
        "it lies in {}, another project's git checkout (its own .git), whose updates would \
         undo or clash with the change",
        dir.display()
    )
}

/// Moonraker's file listing of the config root as a [`klipper::Files`]: globs match the
/// listing (files and the folders holding them), reads answer from what was downloaded and
/// note what is still wanted.
struct Listed {
    /// Every listed file, with its name so far (empty until downloaded).
    listing: MemFiles,
    listed: std::collections::BTreeSet<PathBuf>,
    texts: std::collections::BTreeMap<PathBuf, Result<String, String>>,
    wanted: std::cell::RefCell<std::collections::BTreeSet<PathBuf>>,
}

impl Listed {
    fn new(root: &Path, rel_paths: &[String]) -> Listed {
        let mut listing = MemFiles::new();
        let mut listed = std::collections::BTreeSet::new();
        for rel in rel_paths {
            let p = klipper::files::normalize_path(&root.join(rel));
            listing.insert(&p, "");
            listed.insert(p);
        }
        Listed {
            listing,
            listed,
            texts: Default::default(),
            wanted: Default::default(),
        }
    }

    fn take_wanted(&mut self) -> Vec<PathBuf> {
        std::mem::take(&mut *self.wanted.borrow_mut())
            .into_iter()
            .collect()
    }

    fn insert(&mut self, path: PathBuf, bytes: Vec<u8>) {
        let text = String::from_utf8(bytes).map_err(|_| {
            "it is not UTF-8 text (Klipper cannot read it either); save it as UTF-8".to_string()
        });
        self.texts.insert(path, text);
    }
}

impl klipper::Files for Listed {
    fn read(&self, path: &Path) -> std::io::Result<String> {
        let key = klipper::files::normalize_path(path);
        match self.texts.get(&key) {
            Some(Ok(text)) => Ok(text.clone()),
            Some(Err(why)) => Err(std::io::Error::new(
                std::io::ErrorKind::InvalidData,
                why.clone(),
            )),
            None if self.listed.contains(&key) => {
                self.wanted.borrow_mut().insert(key);
                Err(std::io::Error::new(
                    std::io::ErrorKind::WouldBlock,
                    "not downloaded yet",
                ))
            }
            None => self.listing.read(&key),
        }
    }

    fn glob(&self, pattern: &Path) -> std::io::Result<Vec<PathBuf>> {
        self.listing.glob(pattern)
    }

    fn glob_recursive(&self, pattern: &Path) -> std::io::Result<Vec<PathBuf>> {
        self.listing.glob_recursive(pattern)
    }
}

impl PrinterConfig {
    /// `path` relative to the `config` root.
    ///
    /// # Errors
    /// A path outside the `config` root.
    pub(crate) fn rel(&self, path: &Path) -> anyhow::Result<String> {
        path.strip_prefix(&self.root)
            .map(|p| p.to_string_lossy().into_owned())
            .map_err(|_| {
                anyhow!(
                    "{} is outside Moonraker's config folder {}; klipcal edits only files there",
                    path.display(),
                    self.root.display()
                )
            })
    }
}

async fn klipper_state(m: &Moonraker) -> Option<(String, String)> {
    let info = m.printer_info().await.ok()?;
    Some((info.state, info.state_message))
}

/// Runs a G-code that restarts Klipper (`FIRMWARE_RESTART`, `SAVE_CONFIG`) and waits until
/// Klipper is ready or has failed; returns its final state and message.
///
/// # Errors
/// Moonraker failures, or Klipper not coming back within `limit`.
pub async fn restart_with(
    m: &Moonraker,
    gcode: &str,
    limit: Duration,
) -> anyhow::Result<(String, String)> {
    let mut rx = m.events();
    if gcode == "FIRMWARE_RESTART" {
        m.firmware_restart().await?;
    } else if let Err(e) = m.gcode(gcode).await {
        // SAVE_CONFIG's reply may be cut off by the restart it triggers.
        if e.is_refusal() {
            return Err(e.into());
        }
    }
    let deadline = tokio::time::Instant::now() + limit;
    // Wait for the restart to begin, then for ready (notify_klippy_ready) or a settled error.
    let mut saw_ready = false;
    while tokio::time::Instant::now() < deadline {
        match tokio::time::timeout(Duration::from_millis(500), rx.recv()).await {
            Ok(Ok(Event::KlippyReady)) => {
                saw_ready = true;
                break;
            }
            Ok(_) => {}
            Err(_) => {
                if let Some((state, msg)) = klipper_state(m).await {
                    if state == "error" || state == "shutdown" {
                        return Ok((state, msg));
                    }
                }
            }
        }
    }
    if !saw_ready {
        if let Some(s) = klipper_state(m).await {
            return Ok(s);
        }
        bail!("Klipper did not come back within {} s", limit.as_secs());
    }
    Ok(klipper_state(m)
        .await
        .unwrap_or(("ready".into(), String::new())))
}

/// Writes the values where Klipper reads them ([`klipper::plan_values`]: every stepper of an
/// axis together, AWD included; a value defined in a protected file goes to
/// `klipcal_overrides.cfg`, included last), restarts Klipper, and confirms every value through
/// `configfile.settings`; on failure restores every touched file from its backup (removing a
/// file it created), restarts again and returns Klipper's message. The report's `notes` say
/// what was done beyond the values asked for, and why.
///
/// # Errors
/// A value that cannot be edited, a Moonraker failure, or Klipper failing on the new config
/// (after the rollback).
pub async fn apply(
    m: &Moonraker,
    files: &Files,
    pc: &PrinterConfig,
    values: &[ValueSet],
    stamp: &str,
) -> anyhow::Result<ApplyReport> {
    let triples: Vec<(String, String, String)> = values
        .iter()
        .map(|v| (v.section.clone(), v.key.clone(), v.value.clone()))
        .collect();
    let plan = klipper::plan_values(&pc.config, &triples, &pc.protected).map_err(|e| match e {
        klipper::Error::InReference { .. } => super::user(e.to_string()),
        e => e.into(),
    })?;
    let backup_dir = format!("klipcal_backups/{stamp}");
    let mut report = ApplyReport {
        files: Vec::new(),
        backup_dir: backup_dir.clone(),
        changes: plan
            .changes
            .iter()
            .map(|c| {
                (
                    c.section.clone(),
                    c.key.clone(),
                    c.old_value.clone(),
                    c.new_value.clone(),
                )
            })
            .collect(),
        notes: plan.notes.clone(),
    };
    let writes: Vec<FileWrite> = plan
        .files
        .iter()
        .map(|f| {
            Ok(FileWrite {
                rel: pc.rel(&f.path)?,
                old: f.old_text.clone().map(String::into_bytes),
                new: f.new_text.clone().into_bytes(),
            })
        })
        .collect::<anyhow::Result<_>>()?;
    report.files = writes.iter().map(|w| w.rel.clone()).collect();
    let values: Vec<ValueSet> = plan
        .values
        .iter()
        .map(|(section, key, value)| ValueSet {
            section: section.clone(),
            key: key.clone(),
            value: value.clone(),
        })
        .collect();
    transact(
        m,
        files,
        &writes,
        &backup_dir,
        "FIRMWARE_RESTART",
        || async { Ok(verify(m, &values).await.err().map(|e| format!("{e:#}"))) },
    )
    .await?;
    Ok(report)
}

/// One file of a config transaction: its path relative to the `config` root, its bytes
/// before (`None` when the transaction creates it) and after.
#[derive(Debug, Clone, PartialEq, Eq)]
pub(crate) struct FileWrite {
    /// Relative to Moonraker's `config` root.
    pub rel: String,
    /// The bytes now; `None` for a file the transaction creates.
    pub old: Option<Vec<u8>>,
    /// The bytes to write.
    pub new: Vec<u8>,
}

/// The config transaction every calibration writes through: each existing file is backed up
/// under `backup_dir` (relative to the `config` root) before anything is written, the new
/// bytes are uploaded, Klipper is restarted with `restart_gcode` (`FIRMWARE_RESTART` or
/// `RESTART`), and `verify` runs once it is ready (`Some(why)`: the new config is refused).
/// When Klipper does not come back ready or `verify` refuses, every file is put back byte for
/// byte (files the transaction created are removed), Klipper is restarted again, and the
/// error says why, what was restored and the state Klipper is in.
///
/// # Errors
/// Moonraker failures, a refused config (after the rollback), or a failing rollback.
pub(crate) async fn transact<F, Fut>(
    m: &Moonraker,
    files: &Files,
    writes: &[FileWrite],
    backup_dir: &str,
    restart_gcode: &str,
    verify: F,
) -> anyhow::Result<()>
where
    F: FnOnce() -> Fut,
    Fut: std::future::Future<Output = anyhow::Result<Option<String>>>,
{
    for w in writes {
        if let Some(old) = &w.old {
            files
                .upload("config", &format!("{backup_dir}/{}", w.rel), old.clone())
                .await
                .with_context(|| format!("backing up {}", w.rel))?;
        }
    }
    for w in writes {
        files
            .upload("config", &w.rel, w.new.clone())
            .await
            .with_context(|| format!("writing {}", w.rel))?;
    }
    let (state, msg) = restart_with(m, restart_gcode, Duration::from_secs(90)).await?;
    let refused = if state == "ready" {
        verify().await?
    } else {
        Some(format!(
            "Klipper came up in state `{state}`: {}",
            msg.trim()
        ))
    };
    let Some(why) = refused else {
        return Ok(());
    };
    let mut restored = Vec::new();
    let mut removed = Vec::new();
    for w in writes {
        match &w.old {
            Some(old) => {
                files
                    .upload("config", &w.rel, old.clone())
                    .await
                    .with_context(|| format!("restoring {} from {backup_dir}", w.rel))?;
                restored.push(w.rel.as_str());
            }
            None => {
                files
                    .delete("config", &w.rel)
                    .await
                    .with_context(|| format!("removing {}, which klipcal created", w.rel))?;
                removed.push(w.rel.as_str());
            }
        }
    }
    let after = match restart_with(m, restart_gcode, Duration::from_secs(90)).await {
        Ok((s, _)) if s == "ready" => "Klipper is ready again".to_string(),
        Ok((s, msg)) => format!("Klipper is {s} after the restore: {}", msg.trim()),
        Err(e) => format!("Klipper did not come back after the restore: {e:#}"),
    };
    let mut what = Vec::new();
    if !restored.is_empty() {
        what.push(format!(
            "{} {} restored from config/{backup_dir}",
            restored.join(", "),
            if restored.len() == 1 { "was" } else { "were" }
        ));
    }
    if !removed.is_empty() {
        what.push(format!("{} (new) removed", removed.join(", ")));
    }
    Err(super::user(format!(
        "{why}; rolled back: {}; {after}",
        what.join(", ")
    )))
}

async fn verify(m: &Moonraker, values: &[ValueSet]) -> anyhow::Result<()> {
    let cf = m.configfile().await?;
    for v in values {
        let got = cf
            .settings
            .option(&v.section, &v.key)
            .unwrap_or(&Value::Null);
        let want: Option<f64> = v.value.parse().ok();
        let ok = match (got.as_f64(), want) {
            (Some(g), Some(w)) => (g - w).abs() <= 1e-9 * w.abs().max(1.0),
            _ => got == &json!(v.value),
        };
        if !ok {
            bail!(
                "Klipper runs [{}] {} = {got}, not the {} written",
                v.section,
                v.key,
                v.value
            );
        }
    }
    Ok(())
}

/// A timestamp for backup folders (UTC, `YYYYMMDD-HHMMSS`), from the Unix time.
pub(crate) fn stamp(unix_s: u64) -> String {
    let t = std::time::UNIX_EPOCH + Duration::from_secs(unix_s);
    humantime::format_rfc3339_seconds(t)
        .to_string()
        .chars()
        .filter(|c| c.is_ascii_digit() || *c == 'T')
        .map(|c| if c == 'T' { '-' } else { c })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn backup_folder_stamps_are_civil_utc_times() {
        assert_eq!(stamp(0), "19700101-000000");
        assert_eq!(stamp(1_795_000_000), "20261118-110640");
    }

    #[test]
    fn values_parse_back_to_the_same_json() {
        let v = ValueSet {
            section: "stepper_x".into(),
            key: "rotation_distance".into(),
            value: "40.1".into(),
        };
        let back: ValueSet = serde_json::from_value(json!(v)).unwrap();
        assert_eq!(back, v);
    }
}
