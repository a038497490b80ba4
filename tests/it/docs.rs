//! The documentation a user reads: README.md stays a short front page with the install command
//! near the top; README.md and docs/*.md keep their lines wrapped, speak to users (no internal
//! source or issue numbers), link only to pages, anchors and pictures that exist; every picture
//! in docs/images is linked, a PNG and small; `klipcal macros --readme --write` puts the
//! operations table into a page.

use std::collections::BTreeSet;
use std::path::{Path, PathBuf};
use std::process::Command;

use crate::bench::repo;

/// The front page's length, lines (a Klipper user reads it in two minutes).
const README_LINES_MAX: usize = 120;
/// The install command stands within this many lines of the top.
const INSTALL_WITHIN: usize = 40;
/// The longest line outside tables and code, characters.
const LINE_MAX: usize = 200;
/// The largest picture, bytes.
const IMAGE_BYTES_MAX: u64 = 150 * 1024;

/// README.md and every page under docs/, with their text.
fn user_docs() -> Vec<(PathBuf, String)> {
    let mut paths = vec![repo().join("README.md")];
    let mut pages: Vec<PathBuf> = std::fs::read_dir(repo().join("docs"))
        .expect("a docs/ folder")
        .map(|e| e.unwrap().path())
        .filter(|p| p.extension().is_some_and(|e| e == "md"))
        .collect();
    pages.sort();
    paths.extend(pages);
    paths
        .into_iter()
        .map(|p| {
            let text = std::fs::read_to_string(&p).unwrap();
            (p, text)
        })
        .collect()
}

/// The lines of a markdown text that are prose: not in a fenced or indented code block, not a
/// table row. Each with its 1-based number.
fn prose_lines(text: &str) -> Vec<(usize, &str)> {
    let mut fenced = false;
    let mut out = Vec::new();
    for (i, line) in text.lines().enumerate() {
        let t = line.trim_start();
        if t.starts_with("```") {
            fenced = !fenced;
            continue;
        }
        if fenced || line.starts_with("    ") || t.starts_with('|') {
            continue;
        }
        out.push((i + 1, line));
    }
    out
}

/// "issue 12", "Issue #3", "seed 004": numbers that mean nothing to a user.
fn internal_reference(line: &str) -> Option<String> {
    let lower = line.to_lowercase();
    if let Some(at) = lower.find("seed 00") {
        return Some(line[at..].chars().take(12).collect());
    }
    let mut rest = lower.as_str();
    while let Some(at) = rest.find("issue") {
        let after = rest[at + 5..].trim_start_matches([' ', '#']);
        if after.starts_with(|c: char| c.is_ascii_digit()) && rest[at + 5..].len() > after.len() {
            return Some(rest[at..].chars().take(12).collect());
        }
        rest = &rest[at + 5..];
    }
    None
}

/// GitHub's anchor of a heading: lower case, punctuation dropped, spaces as hyphens.
fn anchor(heading: &str) -> String {
    heading
        .trim()
        .to_lowercase()
        .chars()
        .filter(|c| c.is_alphanumeric() || *c == ' ' || *c == '-' || *c == '_')
        .map(|c| if c == ' ' { '-' } else { c })
        .collect()
}

fn anchors(text: &str) -> BTreeSet<String> {
    let mut fenced = false;
    let mut out = BTreeSet::new();
    for line in text.lines() {
        if line.trim_start().starts_with("```") {
            fenced = !fenced;
        }
        if !fenced && line.starts_with('#') {
            out.insert(anchor(line.trim_start_matches('#')));
        }
    }
    out
}

/// Every relative link target of a markdown text: `](target)`.
fn links(text: &str) -> Vec<String> {
    text.split("](")
        .skip(1)
        .filter_map(|rest| rest.split(')').next())
        .filter(|t| !t.starts_with("http://") && !t.starts_with("https://"))
        .map(str::to_string)
        .collect()
}

#[test]
fn docs_are_short_wrapped_and_speak_to_users() {
    let docs = user_docs();
    let mut problems = Vec::new();
    let (_, readme) = &docs[0];
    let n = readme.lines().count();
    if n > README_LINES_MAX {
        problems.push(format!(
            "README.md has {n} lines; the front page keeps to {README_LINES_MAX}: move the rest to docs/"
        ));
    }
    let install = readme
        .lines()
        .position(|l| l.starts_with("    ") && l.contains("releases/latest/download"));
    if !install.is_some_and(|i| i < INSTALL_WITHIN) {
        problems.push(format!(
            "README.md: the install command is not within its first {INSTALL_WITHIN} lines ({install:?})"
        ));
    }
    for page in [
        "rotation-distance",
        "bed-soak",
        "thermal-mesh",
        "backlash",
        "page-and-api",
        "operations",
        "install",
        "troubleshooting",
        "benchmarks",
        "development",
    ] {
        let file = format!("docs/{page}.md");
        if !docs.iter().any(|(p, _)| p.ends_with(&file)) {
            problems.push(format!("{file} is missing"));
        }
        if !readme.contains(&format!("]({file})")) {
            problems.push(format!("README.md does not link {file}"));
        }
    }
    for (path, text) in &docs {
        let name = path.strip_prefix(repo()).unwrap().display().to_string();
        for (i, line) in prose_lines(text) {
            let chars = line.chars().count();
            if chars > LINE_MAX {
                problems.push(format!(
                    "{name}:{i}: {chars} characters (wrap at {LINE_MAX})"
                ));
            }
        }
        for (i, line) in text.lines().enumerate() {
            if let Some(r) = internal_reference(line) {
                problems.push(format!(
                    "{name}:{}: \"{r}…\": name the paper or thread instead",
                    i + 1
                ));
            }
        }
        problems.extend(broken_links(path, text));
    }
    assert!(problems.is_empty(), "{}", problems.join("\n"));
}

/// Links to files that do not exist, or to anchors their page does not have.
fn broken_links(path: &Path, text: &str) -> Vec<String> {
    let dir = path.parent().unwrap();
    let name = path.file_name().unwrap().to_string_lossy().to_string();
    let mut out = Vec::new();
    for target in links(text) {
        let (file, frag) = match target.split_once('#') {
            Some((f, a)) => (f, Some(a)),
            None => (target.as_str(), None),
        };
        let file_path = if file.is_empty() {
            path.to_path_buf()
        } else {
            dir.join(file)
        };
        if !file_path.exists() {
            out.push(format!("{name}: link to {target}: no such file"));
            continue;
        }
        if let Some(a) = frag {
            let page = std::fs::read_to_string(&file_path).unwrap_or_default();
            if !anchors(&page).contains(a) {
                out.push(format!("{name}: link to {target}: no such heading"));
            }
        }
    }
    out
}

#[test]
fn every_picture_is_linked_small_and_a_png() {
    let linked: BTreeSet<String> = user_docs()
        .iter()
        .flat_map(|(_, t)| links(t))
        .filter_map(|l| l.rsplit('/').next().map(str::to_string))
        .collect();
    let mut problems = Vec::new();
    let dir = repo().join("docs/images");
    let mut n = 0;
    for e in std::fs::read_dir(&dir).expect("docs/images") {
        let p = e.unwrap().path();
        let name = p.file_name().unwrap().to_string_lossy().to_string();
        n += 1;
        let bytes = std::fs::read(&p).unwrap();
        if !bytes.starts_with(b"\x89PNG") {
            problems.push(format!("{name} is not a PNG"));
        }
        if bytes.len() as u64 > IMAGE_BYTES_MAX {
            problems.push(format!(
                "{name}: {} bytes (at most {IMAGE_BYTES_MAX})",
                bytes.len()
            ));
        }
        if !linked.contains(&name) {
            problems.push(format!("{name} is linked from no page"));
        }
    }
    assert!(n > 0, "no pictures in docs/images");
    assert!(problems.is_empty(), "{}", problems.join("\n"));
}

#[test]
fn the_console_filter_the_browser_tests_use_is_the_one_the_docs_give() {
    let page = std::fs::read_to_string(repo().join("docs/page-and-api.md")).unwrap();
    assert!(
        page.contains(crate::frontends::CONSOLE_FILTER),
        "docs/page-and-api.md does not give the console filter tests/it/frontends.rs checks"
    );
}

#[test]
fn macros_readme_write_puts_the_table_into_a_page() {
    let dir = tempfile::tempdir().unwrap();
    let current = std::fs::read_to_string(repo().join("docs/operations.md")).unwrap();
    let stale = current.replace("| `KLIPCAL_STATUS` |", "| `KLIPCAL_STATUS_OLD` |");
    assert_ne!(stale, current);
    let page = dir.path().join("operations.md");
    std::fs::write(&page, &stale).unwrap();
    let run = |args: &[&str]| {
        Command::new(env!("CARGO_BIN_EXE_klipcal"))
            .args(args)
            .output()
            .unwrap()
    };
    let p = page.to_str().unwrap();
    let out = run(&["macros", "--readme", "--write", p]);
    assert!(out.status.success(), "{out:?}");
    assert_eq!(std::fs::read_to_string(&page).unwrap(), current);
    let again = run(&["macros", "--readme", "--write", p]);
    assert!(String::from_utf8_lossy(&again.stdout).contains("already current"));
    // A file without the markers is refused by name and left as it was.
    let bare = dir.path().join("bare.md");
    std::fs::write(&bare, "# no table here\n").unwrap();
    let out = run(&["macros", "--readme", "--write", bare.to_str().unwrap()]);
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(
        err.contains("bare.md") && err.contains("<!-- operations -->"),
        "{err}"
    );
    assert_eq!(std::fs::read_to_string(&bare).unwrap(), "# no table here\n");
    // Without --readme, --write is refused by the command line.
    assert!(!run(&["macros", "--write", p]).status.success());
}

#[test]
fn the_internal_reference_check_catches_what_it_should() {
    assert!(internal_reference("as in seed 004's thread").is_some());
    assert!(internal_reference("fixed in issue 27").is_some());
    assert!(internal_reference("see Issue #12").is_some());
    assert!(internal_reference("issue numbers are not named").is_none());
    assert!(internal_reference("random seed 4").is_none());
    assert_eq!(
        anchor("Checking a nozzle camera"),
        "checking-a-nozzle-camera"
    );
    assert_eq!(anchor(" klipcal's page and API"), "klipcals-page-and-api");
}
