//! The file-reading abstraction the config loader uses ([`Files`]), an in-memory implementation
//! for tests and for text fetched over the network ([`MemFiles`]), and Python-`glob` compatible
//! pattern matching. PURE: never touches the file system (the std::fs adapter is the daemon's `fsio`).

use std::collections::BTreeMap;
use std::io;
use std::path::{Component, Path, PathBuf};

/// Where the config loader gets file text and `[include]` glob matches from.
///
/// `read` returns the whole file as text. `glob` returns the paths matching `pattern` with
/// Python `glob.glob` semantics (`*`, `?`, `[set]`, `[!set]` within one path component; a
/// wildcard component never matches a name starting with `.` unless the pattern does; a pattern
/// without wildcards returns itself when it exists). Order does not matter: the loader sorts.
pub trait Files {
    /// The text of the file at `path`.
    ///
    /// # Errors
    /// Any I/O error (missing file, not UTF-8, permission).
    fn read(&self, path: &Path) -> io::Result<String>;

    /// The existing paths matching `pattern`.
    ///
    /// # Errors
    /// An I/O error while listing a folder.
    fn glob(&self, pattern: &Path) -> io::Result<Vec<PathBuf>>;

    /// The existing paths matching `pattern` with Python's `glob.glob(…, recursive=True)` (as
    /// Kalico includes): a `**` component matches zero or more folders (not hidden ones).
    ///
    /// # Errors
    /// An I/O error while listing a folder; the default refuses, saying it cannot.
    fn glob_recursive(&self, pattern: &Path) -> io::Result<Vec<PathBuf>> {
        Err(io::Error::new(
            io::ErrorKind::Unsupported,
            format!(
                "a recursive include ({}) cannot be followed here",
                pattern.display()
            ),
        ))
    }
}

/// Files held in memory, keyed by their lexically normalised path (`a/./b/../c` → `a/c`).
/// Folders exist only through the files in them, so `missing/../x.cfg` finds `x.cfg` here where
/// a real file system (and Klipper) would not. As Python's `glob`, a pattern also matches those
/// folders (`configs/*` matches `configs/sub`); reading a folder fails, as Klipper's `open()`.
#[derive(Debug, Clone, Default)]
pub struct MemFiles {
    files: BTreeMap<PathBuf, String>,
}

impl MemFiles {
    /// An empty set of files.
    pub fn new() -> Self {
        Self::default()
    }

    /// Adds (or replaces) a file; returns `self` for chaining.
    #[must_use]
    pub fn with(mut self, path: impl AsRef<Path>, text: impl Into<String>) -> Self {
        self.insert(path, text);
        self
    }

    /// Adds (or replaces) a file.
    pub fn insert(&mut self, path: impl AsRef<Path>, text: impl Into<String>) {
        self.files
            .insert(normalize_path(path.as_ref()), text.into());
    }
}

impl Files for MemFiles {
    fn read(&self, path: &Path) -> io::Result<String> {
        let path = normalize_path(path);
        if let Some(text) = self.files.get(&path) {
            return Ok(text.clone());
        }
        if self.is_dir(&path) {
            return Err(folder_error());
        }
        Err(io::Error::new(io::ErrorKind::NotFound, "no such file"))
    }

    fn glob(&self, pattern: &Path) -> io::Result<Vec<PathBuf>> {
        let pattern = normalize_path(pattern);
        let mut found: Vec<PathBuf> = self
            .files
            .keys()
            .flat_map(|p| p.ancestors().skip(1).chain(std::iter::once(p.as_path())))
            .filter(|p| p.parent().is_some() && path_matches(&pattern, p))
            .map(Path::to_path_buf)
            .collect();
        found.sort();
        found.dedup();
        Ok(found)
    }

    fn glob_recursive(&self, pattern: &Path) -> io::Result<Vec<PathBuf>> {
        Ok(self.glob_recursive_mem(pattern))
    }
}

fn components(p: &Path) -> Vec<String> {
    p.components()
        .map(|c| c.as_os_str().to_string_lossy().into_owned())
        .collect()
}

/// Whether a path (as components) matches a pattern whose `**` components match zero or more
/// components that are not hidden (Python's recursive glob); other components as
/// [`component_matches`].
pub fn recursive_matches(pattern: &[String], path: &[String]) -> bool {
    match pattern.split_first() {
        None => path.is_empty(),
        Some((p, rest)) if p == "**" => (0..=path.len()).any(|n| {
            path[..n].iter().all(|c| !c.starts_with('.')) && recursive_matches(rest, &path[n..])
        }),
        Some((p, rest)) => path
            .split_first()
            .is_some_and(|(f, more)| component_matches(p, f) && recursive_matches(rest, more)),
    }
}

impl MemFiles {
    /// [`Files::glob_recursive`] over these files.
    fn glob_recursive_mem(&self, pattern: &Path) -> Vec<PathBuf> {
        let pattern = normalize_path(pattern);
        let pc: Vec<String> = components(&pattern);
        let mut found: Vec<PathBuf> = self
            .files
            .keys()
            .flat_map(|p| p.ancestors().skip(1).chain(std::iter::once(p.as_path())))
            .filter(|p| p.parent().is_some() && recursive_matches(&pc, &components(p)))
            .map(Path::to_path_buf)
            .collect();
        found.sort();
        found.dedup();
        found
    }

    /// True when some file lies under `path` (normalised).
    fn is_dir(&self, path: &Path) -> bool {
        self.files.keys().any(|p| p != path && p.starts_with(path))
    }
}

/// The error for reading a folder as a config file (what `open()` gives Klipper, which then
/// stops with "Unable to open config file …").
pub fn folder_error() -> io::Error {
    io::Error::other(
        "it is a folder, not a file (an [include] pattern matched it; Klipper stops on it too \
         with \"Unable to open config file\"); make the pattern match files only, e.g. *.cfg",
    )
}

/// Lexical normalisation like Python's `os.path.normpath`: drops `.` components and resolves
/// `..` against the preceding component (never above the root).
pub fn normalize_path(path: &Path) -> PathBuf {
    let mut out: Vec<Component<'_>> = Vec::new();
    for c in path.components() {
        match c {
            Component::CurDir => {}
            Component::ParentDir => match out.last() {
                Some(Component::Normal(_)) => {
                    out.pop();
                }
                Some(Component::RootDir) | Some(Component::Prefix(_)) => {}
                _ => out.push(c),
            },
            other => out.push(other),
        }
    }
    if out.is_empty() {
        return PathBuf::from(".");
    }
    out.iter().collect()
}

/// True when the text holds a glob wildcard (`*`, `?` or `[`), as Python's `glob.has_magic`.
pub fn has_magic(text: &str) -> bool {
    text.contains(['*', '?', '['])
}

/// Whether `path` matches `pattern` component by component (both already normalised).
fn path_matches(pattern: &Path, path: &Path) -> bool {
    let pc: Vec<_> = pattern.components().collect();
    let fc: Vec<_> = path.components().collect();
    pc.len() == fc.len()
        && pc.iter().zip(&fc).all(|(p, f)| {
            let (p, f) = (
                p.as_os_str().to_string_lossy(),
                f.as_os_str().to_string_lossy(),
            );
            component_matches(&p, &f)
        })
}

/// Whether one file-name component matches one pattern component, as Python's `glob` does:
/// `fnmatch` for wildcard components (hidden names only when the pattern starts with `.`),
/// equality otherwise.
pub fn component_matches(pattern: &str, name: &str) -> bool {
    if !has_magic(pattern) {
        return pattern == name;
    }
    if name.starts_with('.') && !pattern.starts_with('.') {
        return false;
    }
    let pat = parse_fnmatch(pattern);
    let name: Vec<char> = name.chars().collect();
    fnmatch_tokens(&pat, &name)
}

#[derive(Debug)]
enum Tok {
    Lit(char),
    Any,
    Star,
    Set {
        negate: bool,
        items: Vec<(char, char)>,
    },
}

/// Tokenises a pattern like Python's `fnmatch.translate` (an unclosed `[` is a literal).
fn parse_fnmatch(pattern: &str) -> Vec<Tok> {
    let chars: Vec<char> = pattern.chars().collect();
    let mut toks = Vec::new();
    let mut i = 0;
    while i < chars.len() {
        let c = chars[i];
        i += 1;
        match c {
            '*' => {
                if !matches!(toks.last(), Some(Tok::Star)) {
                    toks.push(Tok::Star);
                }
            }
            '?' => toks.push(Tok::Any),
            '[' => {
                let mut j = i;
                if j < chars.len() && chars[j] == '!' {
                    j += 1;
                }
                if j < chars.len() && chars[j] == ']' {
                    j += 1;
                }
                while j < chars.len() && chars[j] != ']' {
                    j += 1;
                }
                if j >= chars.len() {
                    toks.push(Tok::Lit('['));
                    continue;
                }
                let mut body = &chars[i..j];
                let negate = body.first() == Some(&'!');
                if negate {
                    body = &body[1..];
                }
                let mut items = Vec::new();
                let mut k = 0;
                while k < body.len() {
                    if k + 2 < body.len() && body[k + 1] == '-' {
                        items.push((body[k], body[k + 2]));
                        k += 3;
                    } else {
                        items.push((body[k], body[k]));
                        k += 1;
                    }
                }
                toks.push(Tok::Set { negate, items });
                i = j + 1;
            }
            other => toks.push(Tok::Lit(other)),
        }
    }
    toks
}

fn fnmatch_tokens(toks: &[Tok], name: &[char]) -> bool {
    // dp[j] = tokens consumed so far can match name[..j]
    let mut dp = vec![false; name.len() + 1];
    dp[0] = true;
    for tok in toks {
        let mut next = vec![false; name.len() + 1];
        match tok {
            Tok::Star => {
                let mut reach = false;
                for j in 0..=name.len() {
                    reach |= dp[j];
                    next[j] = reach;
                }
            }
            _ => {
                for j in 0..name.len() {
                    if dp[j] && single_matches(tok, name[j]) {
                        next[j + 1] = true;
                    }
                }
            }
        }
        dp = next;
    }
    dp[name.len()]
}

fn single_matches(tok: &Tok, c: char) -> bool {
    match tok {
        Tok::Lit(l) => *l == c,
        Tok::Any => true,
        Tok::Star => true,
        Tok::Set { negate, items } => {
            let hit = items.iter().any(|(lo, hi)| *lo <= c && c <= *hi);
            hit != *negate
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn star_matches_any_name_but_not_hidden_ones() {
        assert!(component_matches("*.cfg", "macros.cfg"));
        assert!(!component_matches("*.cfg", ".hidden.cfg"));
        assert!(component_matches(".*.cfg", ".hidden.cfg"));
        assert!(!component_matches("*.cfg", "macros.conf"));
    }

    #[test]
    fn sets_ranges_and_negation_follow_fnmatch() {
        assert!(component_matches("fan[0-9].cfg", "fan3.cfg"));
        assert!(!component_matches("fan[!0-9].cfg", "fan3.cfg"));
        assert!(component_matches("fan[!0-9].cfg", "fanx.cfg"));
        assert!(component_matches("a?c", "abc"));
        // an unclosed bracket is a literal character
        assert!(component_matches("a[b", "a[b"));
    }

    #[test]
    fn memory_glob_matches_whole_components_only() {
        let files = MemFiles::new()
            .with("/cfg/printer.cfg", "")
            .with("/cfg/macros/a.cfg", "")
            .with("/cfg/macros/sub/b.cfg", "");
        let found = files.glob(Path::new("/cfg/./macros/*.cfg")).unwrap();
        assert_eq!(found, vec![PathBuf::from("/cfg/macros/a.cfg")]);
    }

    #[test]
    fn a_pattern_matches_folders_too_and_reading_one_fails() {
        let files = MemFiles::new()
            .with("/cfg/configs/a.cfg", "")
            .with("/cfg/configs/a.cfg.bak", "")
            .with("/cfg/configs/sub/b.cfg", "");
        let found = files.glob(Path::new("/cfg/configs/*")).unwrap();
        assert_eq!(
            found,
            [
                "/cfg/configs/a.cfg",
                "/cfg/configs/a.cfg.bak",
                "/cfg/configs/sub"
            ]
            .map(PathBuf::from)
        );
        let err = files.read(Path::new("/cfg/configs/sub")).unwrap_err();
        assert!(err.to_string().contains("it is a folder"), "{err}");
        assert_eq!(
            files.read(Path::new("/cfg/nothing")).unwrap_err().kind(),
            io::ErrorKind::NotFound
        );
    }

    #[test]
    fn normalisation_resolves_dot_and_dot_dot() {
        assert_eq!(
            normalize_path(Path::new("/a/./b/../c")),
            PathBuf::from("/a/c")
        );
        assert_eq!(normalize_path(Path::new("/../a")), PathBuf::from("/a"));
        assert_eq!(normalize_path(Path::new("../a")), PathBuf::from("../a"));
    }
}
