//! NON-PURE adapter: [`FsFiles`], the std::fs implementation of [`crate::klipper::Files`]
//! (read a file, expand an `[include]` glob). Holds no logic beyond listing folders; the
//! matching rules live in the pure `klipper::files`.

use std::io;
use std::path::{Component, Path, PathBuf};

use crate::klipper::files::{component_matches, has_magic, recursive_matches};
use crate::klipper::Files;

/// Reads Klipper config files from the local file system.
#[derive(Debug, Clone, Copy, Default)]
pub struct FsFiles;

impl Files for FsFiles {
    fn read(&self, path: &Path) -> io::Result<String> {
        std::fs::read_to_string(path)
    }

    fn glob(&self, pattern: &Path) -> io::Result<Vec<PathBuf>> {
        let comps: Vec<Component<'_>> = pattern.components().collect();
        let mut candidates: Vec<PathBuf> = vec![PathBuf::new()];
        for (i, comp) in comps.iter().enumerate() {
            let last = i + 1 == comps.len();
            let text = comp.as_os_str().to_string_lossy();
            let is_pattern = matches!(comp, Component::Normal(_)) && has_magic(&text);
            let mut next = Vec::new();
            for base in &candidates {
                if !is_pattern {
                    let p = base.join(comp.as_os_str());
                    // Python glob: literal parts must exist (lexists for the last one)
                    let exists = if last {
                        std::fs::symlink_metadata(&p).is_ok()
                    } else {
                        p.is_dir()
                    };
                    if exists || matches!(comp, Component::RootDir | Component::Prefix(_)) {
                        next.push(p);
                    }
                    continue;
                }
                let dir = if base.as_os_str().is_empty() {
                    Path::new(".")
                } else {
                    base.as_path()
                };
                let Ok(entries) = std::fs::read_dir(dir) else {
                    continue;
                };
                for entry in entries {
                    let entry = entry?;
                    let name = entry.file_name();
                    let name = name.to_string_lossy();
                    if component_matches(&text, &name) {
                        let p = base.join(entry.file_name());
                        if last || p.is_dir() {
                            next.push(p);
                        }
                    }
                }
            }
            candidates = next;
        }
        Ok(candidates)
    }

    fn glob_recursive(&self, pattern: &Path) -> io::Result<Vec<PathBuf>> {
        // Every path below the pattern's literal start, matched by the pure rule.
        let base: PathBuf = pattern
            .components()
            .take_while(|c| !has_magic(&c.as_os_str().to_string_lossy()))
            .collect();
        let mut all = Vec::new();
        walk(&base, &mut all)?;
        let comps = |p: &Path| -> Vec<String> {
            p.components()
                .map(|c| c.as_os_str().to_string_lossy().into_owned())
                .collect()
        };
        let pc = comps(pattern);
        Ok(all
            .into_iter()
            .filter(|p| recursive_matches(&pc, &comps(p)))
            .collect())
    }
}

/// Every file and folder below `dir` (symlinked folders not followed).
fn walk(dir: &Path, out: &mut Vec<PathBuf>) -> io::Result<()> {
    let Ok(entries) = std::fs::read_dir(dir) else {
        return Ok(());
    };
    for entry in entries {
        let entry = entry?;
        let p = entry.path();
        out.push(p.clone());
        if entry.file_type()?.is_dir() {
            walk(&p, out)?;
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::klipper::Config;

    #[test]
    fn a_config_with_glob_includes_loads_from_disk() {
        let dir = tempfile::tempdir().unwrap();
        let root = dir.path();
        std::fs::create_dir(root.join("macros")).unwrap();
        std::fs::write(
            root.join("printer.cfg"),
            "[include macros/*.cfg]\n[a]\nx: 1\n",
        )
        .unwrap();
        std::fs::write(root.join("macros/b.cfg"), "[a]\ny: b\n").unwrap();
        std::fs::write(root.join("macros/a.cfg"), "[a]\ny: a\nz: 3\n").unwrap();
        std::fs::write(root.join("macros/.hidden.cfg"), "[a]\ny: hidden\n").unwrap();
        let cfg = Config::load(&FsFiles, &root.join("printer.cfg")).unwrap();
        assert_eq!(cfg.get("a", "y"), Some("b"));
        assert_eq!(cfg.get("a", "z"), Some("3"));
        assert_eq!(
            cfg.files().len(),
            3,
            "the hidden file is not matched by '*'"
        );
    }

    #[test]
    fn a_missing_literal_include_is_reported() {
        let dir = tempfile::tempdir().unwrap();
        std::fs::write(dir.path().join("printer.cfg"), "[include nope.cfg]\n").unwrap();
        assert!(Config::load(&FsFiles, &dir.path().join("printer.cfg")).is_err());
    }
}
