//! PURE: what `klipcal install` changes in the text files of a printer_data folder and how
//! `klipcal uninstall` takes it back. File contents in, new contents (or a refusal naming the
//! conflict) out; the shell in `install/mod.rs` reads, backs up, writes and records.

use crate::klipper::Config;

/// The include line klipcal adds to printer.cfg.
pub const INCLUDE_LINE: &str = "[include klipcal.cfg]";
/// The section Klipper needs for klipcal's console answers and prompts.
pub const RESPOND_LINE: &str = "[respond]";
/// The service name Moonraker may restart (moonraker.asvc) and the update_manager entry.
pub const SERVICE: &str = "klipcal";

/// Why the install refuses.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("{0}")]
pub struct Conflict(pub String);

/// The macro names config/klipcal.cfg defines (`[gcode_macro NAME]`, lower-cased).
#[must_use]
pub fn macro_sections(macros_cfg: &str) -> Vec<String> {
    macros_cfg
        .lines()
        .filter_map(|l| {
            let l = l.trim();
            let name = l.strip_prefix('[')?.strip_suffix(']')?;
            name.to_ascii_lowercase()
                .starts_with("gcode_macro ")
                .then(|| name.to_ascii_lowercase())
        })
        .collect()
}

/// Whether the loaded config already reads a `klipcal.cfg` at the config root.
fn reads_klipcal_cfg(loaded: &Config) -> bool {
    loaded
        .files()
        .iter()
        .any(|f| f.path.file_name().is_some_and(|n| n == "klipcal.cfg"))
}

/// printer.cfg with `[include klipcal.cfg]` (and `[respond]` when `add_respond`), or `None`
/// when nothing is to change. `loaded` is the printer's config as Klipper reads it now.
///
/// # Errors
/// A macro of klipcal's already defined by another file (named with its place).
pub fn printer_cfg(
    text: &str,
    loaded: &Config,
    macros_cfg: &str,
    add_respond: bool,
) -> Result<Option<String>, Conflict> {
    let reads = reads_klipcal_cfg(loaded);
    let ours = macro_sections(macros_cfg);
    for sec in loaded.sections() {
        let name = sec.name.to_ascii_lowercase();
        if !ours.contains(&name) {
            continue;
        }
        let from = sec
            .options
            .first()
            .map(|o| o.origin.path.clone())
            .unwrap_or_default();
        if from.file_name().is_some_and(|n| n == "klipcal.cfg") {
            continue;
        }
        return Err(Conflict(format!(
            "[{}] is already defined in {}: klipcal.cfg defines it too; rename or remove \
             yours, then install again",
            sec.name,
            from.display()
        )));
    }
    let need_include = !reads;
    let need_respond = add_respond && !loaded.has_section("respond");
    if !need_include && !need_respond {
        return Ok(None);
    }
    let mut add = String::new();
    if need_include {
        add.push_str(INCLUDE_LINE);
        add.push('\n');
    }
    if need_respond {
        add.push_str(RESPOND_LINE);
        add.push('\n');
    }
    Ok(Some(insert_at_top(text, &add)))
}

/// Inserts `block` after the file's opening comment lines (before its first section), with a
/// blank line after it.
fn insert_at_top(text: &str, block: &str) -> String {
    let mut at = 0;
    for line in text.split_inclusive('\n') {
        let t = line.trim();
        if t.starts_with('#') || t.starts_with(';') {
            at += line.len();
        } else {
            break;
        }
    }
    let (head, tail) = text.split_at(at);
    let sep = if head.is_empty() || head.ends_with('\n') {
        ""
    } else {
        "\n"
    };
    format!("{head}{sep}{block}\n{tail}")
}

/// Whether the printer's config has `[respond]`.
#[must_use]
pub fn has_respond(loaded: &Config) -> bool {
    loaded.has_section("respond")
}

/// moonraker.asvc with `klipcal` listed, or `None` when it is. A missing file is created with
/// Moonraker's default services (what Moonraker itself would write) and klipcal.
#[must_use]
pub fn asvc(current: Option<&str>, moonraker_defaults: &str) -> Option<String> {
    let text = current.unwrap_or(moonraker_defaults);
    let listed = text.lines().any(|l| {
        let l = l.trim();
        l == SERVICE || l == "klipcal.service"
    });
    if listed && current.is_some() {
        return None;
    }
    let mut out = text.to_string();
    if !listed {
        if !out.is_empty() && !out.ends_with('\n') {
            out.push('\n');
        }
        out.push_str(SERVICE);
        out.push('\n');
    }
    Some(out)
}

/// The `[update_manager klipcal]` section: the `executable` type (one binary from the
/// release's assets, named in release_info.json; the folder is not wiped on update).
#[must_use]
pub fn update_manager_section(bin_dir: &str, repo: &str) -> String {
    format!(
        "[update_manager {SERVICE}]\n\
         # added by klipcal install; klipcal uninstall removes it\n\
         type: executable\n\
         channel: stable\n\
         repo: {repo}\n\
         path: {bin_dir}\n\
         managed_services: {SERVICE}\n"
    )
}

/// The byte range of `[header]`'s section in `text`: from its header line to the next
/// section header (or the end), trailing blank lines excluded.
fn section_span(text: &str, header: &str) -> Option<(usize, usize)> {
    let mut pos = 0;
    let mut start = None;
    let mut end_content = 0;
    for line in text.split_inclusive('\n') {
        let t = line.trim();
        let is_header = t.starts_with('[') && t.ends_with(']');
        match start {
            None if is_header && t.eq_ignore_ascii_case(header) => {
                start = Some(pos);
                end_content = pos + line.len();
            }
            Some(s) if is_header => return Some((s, end_content)),
            Some(_) if !t.is_empty() => end_content = pos + line.len(),
            _ => {}
        }
        pos += line.len();
    }
    start.map(|s| (s, end_content))
}

/// moonraker.conf with klipcal's update_manager section, or `None` when it is there as is.
/// `ours` says the present section is klipcal's own from an earlier install (then it is
/// replaced; otherwise a different one is a conflict).
///
/// # Errors
/// A different `[update_manager klipcal]` that klipcal did not write.
pub fn moonraker_conf(text: &str, section: &str, ours: bool) -> Result<Option<String>, Conflict> {
    let header = section.lines().next().unwrap_or("");
    match section_span(text, header) {
        Some((s, e)) => {
            if text[s..e] == *section {
                return Ok(None);
            }
            if !ours {
                return Err(Conflict(format!(
                    "moonraker.conf already has {header} that klipcal did not write; remove it \
                     (or rename it) and install again"
                )));
            }
            Ok(Some(format!("{}{section}{}", &text[..s], &text[e..])))
        }
        None => {
            let mut out = text.to_string();
            if !out.is_empty() && !out.ends_with('\n') {
                out.push('\n');
            }
            if !out.is_empty() {
                out.push('\n');
            }
            out.push_str(section);
            Ok(Some(out))
        }
    }
}

/// Takes klipcal's additions out of a file the user changed since the install: the lines it
/// added (`added`) and the update_manager section, leaving everything else.
#[must_use]
pub fn remove_additions(
    text: &str,
    added_lines: &[String],
    section_header: Option<&str>,
) -> String {
    let mut out = text.to_string();
    if let Some(h) = section_header {
        if let Some((s, e)) = section_span(&out, h) {
            // with the blank line install put before the section
            let s = if out[..s].ends_with("\n\n") { s - 1 } else { s };
            out = format!("{}{}", &out[..s], &out[e..]);
        }
    }
    for line in added_lines {
        let mut kept = String::with_capacity(out.len());
        let mut removed = false;
        for l in out.split_inclusive('\n') {
            if !removed && l.trim() == line.trim() {
                removed = true;
                continue;
            }
            kept.push_str(l);
        }
        out = kept;
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::klipper::MemFiles;
    use std::path::Path;

    const MACROS: &str = "[gcode_macro KLIPCAL_STATUS]\ngcode:\n  RESPOND MSG=hi\n";

    fn loaded(files: &MemFiles) -> Config {
        Config::load(files, Path::new("/pd/config/printer.cfg")).unwrap()
    }

    #[test]
    fn the_include_goes_after_the_opening_comments_once() {
        let text = "# my printer\n# notes\n[printer]\nkinematics: corexy\n";
        let files = MemFiles::new().with("/pd/config/printer.cfg", text);
        let out = printer_cfg(text, &loaded(&files), MACROS, true)
            .unwrap()
            .unwrap();
        assert_eq!(
            out,
            "# my printer\n# notes\n[include klipcal.cfg]\n[respond]\n\n[printer]\nkinematics: corexy\n"
        );
        // Installed: nothing more to change.
        let files = MemFiles::new()
            .with("/pd/config/printer.cfg", out.clone())
            .with("/pd/config/klipcal.cfg", MACROS);
        assert_eq!(
            printer_cfg(&out, &loaded(&files), MACROS, true).unwrap(),
            None
        );
    }

    #[test]
    fn an_include_that_already_reads_klipcal_cfg_is_enough() {
        let text = "[include klip*.cfg]\n[respond]\n[printer]\nkinematics: corexy\n";
        let files = MemFiles::new()
            .with("/pd/config/printer.cfg", text)
            .with("/pd/config/klipcal.cfg", MACROS);
        assert_eq!(
            printer_cfg(text, &loaded(&files), MACROS, true).unwrap(),
            None
        );
    }

    #[test]
    fn a_macro_of_ours_defined_elsewhere_is_a_conflict_named_with_its_file() {
        let text = "[include macros.cfg]\n[printer]\nkinematics: corexy\n";
        let files = MemFiles::new().with("/pd/config/printer.cfg", text).with(
            "/pd/config/macros.cfg",
            "[gcode_macro klipcal_status]\ngcode:\n  M117 x\n",
        );
        let e = printer_cfg(text, &loaded(&files), MACROS, false).unwrap_err();
        assert!(
            e.0.contains("klipcal_status") && e.0.contains("macros.cfg"),
            "{e}"
        );
    }

    #[test]
    fn respond_is_added_only_when_asked_for_and_missing() {
        let text = "[printer]\nkinematics: corexy\n";
        let files = MemFiles::new().with("/pd/config/printer.cfg", text);
        let out = printer_cfg(text, &loaded(&files), MACROS, false)
            .unwrap()
            .unwrap();
        assert!(
            out.starts_with("[include klipcal.cfg]\n\n[printer]"),
            "{out}"
        );
        assert!(!out.contains("[respond]"));
    }

    #[test]
    fn asvc_lists_klipcal_once_and_a_missing_file_keeps_moonrakers_defaults() {
        assert_eq!(asvc(Some("klipper_mcu\nklipcal\n"), ""), None);
        assert_eq!(
            asvc(Some("klipper_mcu"), "").unwrap(),
            "klipper_mcu\nklipcal\n"
        );
        assert_eq!(asvc(None, "crowsnest\n").unwrap(), "crowsnest\nklipcal\n");
    }

    #[test]
    fn the_update_manager_section_is_added_replaced_when_ours_and_refused_when_not() {
        let sec = update_manager_section("~/klipcal", "klipcal/klipcal");
        let conf = "[server]\nhost: 0.0.0.0\n";
        let out = moonraker_conf(conf, &sec, false).unwrap().unwrap();
        assert_eq!(out, format!("{conf}\n{sec}"));
        assert_eq!(moonraker_conf(&out, &sec, false).unwrap(), None);
        let theirs = format!("{conf}\n[update_manager klipcal]\ntype: git_repo\npath: ~/klipcal\n\n[webcam x]\nservice: iframe\n");
        let e = moonraker_conf(&theirs, &sec, false).unwrap_err();
        assert!(e.0.contains("did not write"), "{e}");
        let replaced = moonraker_conf(&theirs, &sec, true).unwrap().unwrap();
        assert!(replaced.contains("type: executable") && !replaced.contains("git_repo"));
        assert!(
            replaced.ends_with("\n[webcam x]\nservice: iframe\n"),
            "{replaced}"
        );
    }

    #[test]
    fn additions_come_out_of_a_file_the_user_changed_since() {
        let sec = update_manager_section("~/klipcal", "klipcal/klipcal");
        let installed = format!("[server]\nhost: 0.0.0.0\n\n{sec}");
        let changed = format!("{installed}\n[webcam cam]\nservice: mjpegstreamer\n");
        let back = remove_additions(&changed, &[], Some("[update_manager klipcal]"));
        assert_eq!(
            back,
            "[server]\nhost: 0.0.0.0\n\n[webcam cam]\nservice: mjpegstreamer\n"
        );
        let cfg = "[include klipcal.cfg]\n\n[printer]\nkinematics: corexy\n[fan]\npin: PA1\n";
        let back = remove_additions(cfg, &[INCLUDE_LINE.to_string()], None);
        assert_eq!(back, "\n[printer]\nkinematics: corexy\n[fan]\npin: PA1\n");
    }
}
