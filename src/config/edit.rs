//! Writes an answer into the settings file (the soak question's `[soak] bed` and `frame`):
//! the file as it is must load, its comments and layout are kept (edited with `toml_edit`, not
//! written again from the parsed values), a copy goes to `klipcal_backups/<stamp>/` beside it
//! first, the new text must load whole before it replaces the file, and it replaces it in one
//! rename. A file that does not load is refused whole: nothing is written.

use std::path::{Path, PathBuf};

use super::Config;

/// What [`set_soak_keys`] did.
#[derive(Debug, Clone, PartialEq, Eq)]
pub(crate) struct Written {
    /// The settings file written.
    pub path: PathBuf,
    /// Where its earlier text went (none: there was no file).
    pub backup: Option<PathBuf>,
}

/// Marks the comment line [`set_soak_keys`] writes above a value, so that the next answer
/// replaces it instead of adding another.
const ANSWER_MARK: &str = "# (klipcal) ";

/// Sets `[soak]` keys of the settings file at `path` to text values, each with a comment line
/// above it (`values`: key, value, comment); `stamp` names the backup folder.
///
/// # Errors
/// The file does not load as it is (its error, nothing written), the result would not load, or
/// the backup or the write failed (the file is then unchanged).
pub(crate) fn set_soak_keys(
    path: &Path,
    values: &[(&str, &str, String)],
    stamp: &str,
) -> anyhow::Result<Written> {
    use anyhow::Context;
    let old = match std::fs::read_to_string(path) {
        Ok(t) => Some(t),
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => None,
        Err(e) => return Err(anyhow::anyhow!("cannot read {}: {e}", path.display())),
    };
    let text = old.clone().unwrap_or_default();
    Config::parse(&text).map_err(|e| {
        anyhow::anyhow!(
            "{} does not load as it is ({e}): nothing written; fix the file, then answer again",
            path.display()
        )
    })?;
    let new = edited(&text, values)?;
    Config::parse(&new).map_err(|e| {
        anyhow::anyhow!(
            "the answer would leave {} unreadable ({e}): nothing written",
            path.display()
        )
    })?;
    let dir = path.parent().unwrap_or_else(|| Path::new("."));
    let backup = match &old {
        Some(old) => {
            let name = path.file_name().unwrap_or_else(|| "klipcal.toml".as_ref());
            let folder = dir.join("klipcal_backups").join(stamp);
            std::fs::create_dir_all(&folder)
                .with_context(|| format!("creating the backup folder {}", folder.display()))?;
            let b = folder.join(name);
            std::fs::write(&b, old).with_context(|| format!("backing up to {}", b.display()))?;
            Some(b)
        }
        None => None,
    };
    let tmp = dir.join(format!(
        ".{}.klipcal-new",
        path.file_name()
            .map_or("klipcal.toml".into(), |n| n.to_string_lossy())
    ));
    std::fs::write(&tmp, &new).with_context(|| format!("writing {}", tmp.display()))?;
    std::fs::rename(&tmp, path).with_context(|| format!("replacing {}", path.display()))?;
    Ok(Written {
        path: path.to_path_buf(),
        backup,
    })
}

/// `text` with the `[soak]` keys set, every other byte kept.
fn edited(text: &str, values: &[(&str, &str, String)]) -> anyhow::Result<String> {
    let mut doc: toml_edit::DocumentMut = text
        .parse()
        .map_err(|e| anyhow::anyhow!("the settings file is not TOML: {e}"))?;
    let soak = doc
        .entry("soak")
        .or_insert_with(toml_edit::table)
        .as_table_mut()
        .ok_or_else(|| anyhow::anyhow!("soak is not a table in the settings file"))?;
    for (key, value, comment) in values {
        let mut item = toml_edit::value(*value);
        if let Some(old) = soak.get(key).and_then(toml_edit::Item::as_value) {
            // The old value's own trailing comment stays with the new one.
            if let Some(v) = item.as_value_mut() {
                *v.decor_mut() = old.decor().clone();
            }
        }
        // An existing key keeps its own decor (the comment lines above it): only its value is
        // replaced (`insert` would replace the key too).
        match soak.get_mut(key) {
            Some(slot) => *slot = item,
            None => {
                soak.insert(key, item);
            }
        }
        let mut k = soak
            .key_mut(key)
            .ok_or_else(|| anyhow::anyhow!("soak.{key} was not written"))?;
        let decor = k.leaf_decor_mut();
        let prefix = decor
            .prefix()
            .and_then(|p| p.as_str())
            .unwrap_or("")
            .to_string();
        let kept: String = prefix
            .split_inclusive('\n')
            .filter(|l| !l.trim_start().starts_with(ANSWER_MARK.trim_end()))
            .collect();
        let one_line = comment.replace(['\n', '\r'], " ");
        decor.set_prefix(format!("{kept}{ANSWER_MARK}{one_line}\n"));
    }
    Ok(doc.to_string())
}

#[cfg(test)]
mod tests {
    use super::*;

    const FILE: &str =
        "# my printer\n[moonraker]\nurl = \"ws://127.0.0.1:7125/websocket\" # local\n\n\
                        [soak]\n# my own note on the budget\nsurface_budget_c = 0.8\n\
                        # Your bed's build\nbed = \"\" # set me\nframe = \"\"\n";

    #[test]
    fn an_answer_is_written_with_a_backup_and_every_comment_kept() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("klipcal.toml");
        std::fs::write(&path, FILE).unwrap();
        let w = set_soak_keys(
            &path,
            &[
                ("bed", "steel-pad", "answered in the soak question".into()),
                ("frame", "open", "answered in the soak question".into()),
            ],
            "20261201-230000",
        )
        .unwrap();
        let new = std::fs::read_to_string(&path).unwrap();
        for kept in [
            "# my printer",
            "# local",
            "# my own note on the budget",
            "# Your bed's build",
            "# set me",
            "surface_budget_c = 0.8",
        ] {
            assert!(new.contains(kept), "{kept} lost:\n{new}");
        }
        assert!(new.contains("bed = \"steel-pad\""), "{new}");
        assert!(
            new.contains("# (klipcal) answered in the soak question\nframe = \"open\""),
            "{new}"
        );
        let backup = w.backup.expect("a backup");
        assert!(backup.starts_with(dir.path().join("klipcal_backups/20261201-230000")));
        assert_eq!(std::fs::read_to_string(&backup).unwrap(), FILE);
        let cfg = Config::load(Some(&path)).unwrap();
        assert_eq!(
            (cfg.soak.bed.as_str(), cfg.soak.frame.as_str()),
            ("steel-pad", "open")
        );
        assert_eq!(cfg.soak.surface_budget_c, 0.8);
        // A second answer replaces the first's comment, not adds to it.
        set_soak_keys(
            &path,
            &[("bed", "glass-pad", "again".into())],
            "20261201-230100",
        )
        .unwrap();
        let again = std::fs::read_to_string(&path).unwrap();
        assert_eq!(again.matches("# (klipcal)").count(), 2, "{again}");
        assert!(
            again.contains("# (klipcal) again\nbed = \"glass-pad\" # set me"),
            "{again}"
        );
    }

    #[test]
    fn a_broken_file_is_refused_whole_and_left_as_it_was() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("klipcal.toml");
        for broken in [
            "[soak]\nbed = \"steel-pad\nframe = \"open\"\n",
            "[soak]\nbin_s = 0\n",
            "[soak]\nbedd = \"x\"\n",
        ] {
            std::fs::write(&path, broken).unwrap();
            let e = set_soak_keys(&path, &[("frame", "open", "x".into())], "s").unwrap_err();
            assert!(e.to_string().contains("nothing written"), "{e}");
            assert_eq!(std::fs::read_to_string(&path).unwrap(), broken);
            assert!(!dir.path().join("klipcal_backups").exists());
        }
        // A value the settings refuse is refused before anything is written.
        std::fs::write(&path, FILE).unwrap();
        let e = set_soak_keys(&path, &[("frame", "closed", "x".into())], "s").unwrap_err();
        assert!(e.to_string().contains("soak.frame"), "{e}");
        assert_eq!(std::fs::read_to_string(&path).unwrap(), FILE);
    }

    #[test]
    fn no_file_yet_is_created_with_the_soak_table() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("klipcal.toml");
        let w = set_soak_keys(&path, &[("frame", "enclosed", "asked".into())], "s").unwrap();
        assert_eq!(w.backup, None);
        let cfg = Config::load(Some(&path)).unwrap();
        assert_eq!(cfg.soak.frame, "enclosed");
    }
}
