//! The file work install and uninstall share: reading text files whole, writing them through
//! a rename, the diff `--dry-run` prints, and sizes of what uninstall leaves in place.

use std::path::{Path, PathBuf};

use anyhow::{anyhow, Context};

pub(super) fn expand(path: &str) -> PathBuf {
    crate::config::expand_home(path)
}

pub(super) fn read_opt(path: &Path) -> anyhow::Result<Option<String>> {
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
pub(super) fn write_atomic(path: &Path, bytes: &[u8]) -> anyhow::Result<()> {
    if let Some(dir) = path.parent() {
        std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
    }
    let tmp = path.with_extension("klipcal-tmp");
    std::fs::write(&tmp, bytes).with_context(|| format!("writing {}", tmp.display()))?;
    std::fs::rename(&tmp, path).with_context(|| format!("replacing {}", path.display()))
}

pub(super) fn diff(path: &Path, before: Option<&str>, after: Option<&str>) -> String {
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

/// `path` with the home folder written as `~` (as the settings file's comments do).
pub(super) fn tilde(path: &Path) -> String {
    let home = expand("~");
    match path.strip_prefix(&home) {
        Ok(rel) if home != Path::new("~") => format!("~/{}", rel.display()),
        _ => path.display().to_string(),
    }
}

/// Files under `dir` and their bytes (0, 0 when it does not exist).
pub(super) fn tree_size(dir: &Path) -> (usize, u64) {
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
