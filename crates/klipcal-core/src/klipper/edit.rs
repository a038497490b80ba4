//! Changes one option's value in place: finds the definition Klipper uses and returns that
//! file's new full text with only the value bytes replaced. PURE: the caller writes the file.
//!
//! Which definition is edited: the effective one, i.e. the last definition in Klipper's reading
//! order (main file and includes in order, then the SAVE_CONFIG block). When the regular config
//! (main file + includes) defines an option, Klipper drops the SAVE_CONFIG block's copy at load
//! (`configfile._strip_duplicates` comments it out), so the regular definition is edited and
//! the block's stale copy is left as it is (it stays ignored). An option only the block defines
//! (`[skew_correction name]`, `[bed_mesh default]`, PID values…) is edited inside the block,
//! keeping its `#*# ` prefix. Note for callers: a later SAVE_CONFIG that stores the same option
//! comments out the main file's definition, and fails ("conflicts with included value") when
//! the definition is in an included file.

use std::path::PathBuf;

use super::config::{py_isspace, Config};
use super::files::MemFiles;
use super::Error;

/// One value changed.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct ValueChange {
    /// Section name as written.
    pub section: String,
    /// Lowercased option name.
    pub key: String,
    /// 1-based line changed.
    pub line: usize,
    /// True when the changed line is in the SAVE_CONFIG block.
    pub in_save_config: bool,
    /// The value before the edit.
    pub old_value: String,
    /// The value written.
    pub new_value: String,
}

/// One file to rewrite.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct FileEdit {
    /// The file to write (as read, normalised).
    pub path: PathBuf,
    /// Its index in [`Config::files`].
    pub file: usize,
    /// The file's complete new text; identical to the old text except the value bytes.
    pub new_text: String,
    /// The values changed in this file, in file order.
    pub changes: Vec<ValueChange>,
}

/// Replaces the effective value of `[section] key` (key case-insensitive, section exact) with
/// `new_value`, returning the file to rewrite.
///
/// The new text is checked by parsing the edited set of files again: the option must read back
/// as `new_value` and every other effective option must be unchanged.
///
/// # Errors
/// [`Error::NotDefined`] when no file defines the option (klipcal does not add options);
/// [`Error::MultiLineValue`] for values spanning several lines (G-code blocks, mesh points);
/// [`Error::BadNewValue`] when `new_value` holds a line break, a `#`, a `;` after whitespace or
/// at the start, or surrounding whitespace (Klipper would read it differently);
/// [`Error::EditCheck`] if the re-parse disagrees (a bug, never expected).
#[cfg(test)]
pub fn set_value(
    config: &Config,
    section: &str,
    key: &str,
    new_value: &str,
) -> Result<FileEdit, Error> {
    let mut edits = set_values(config, &[(section, key, new_value)])?;
    edits
        .pop()
        .ok_or_else(|| Error::EditCheck("no file to edit".into()))
}

/// Several values at once (e.g. `rotation_distance` of `stepper_x` and `stepper_y`): one
/// [`FileEdit`] per file touched, in [`Config::files`] order. All or nothing: any refused value
/// fails the whole call.
///
/// # Errors
/// As [`set_value`]; also [`Error::BadNewValue`] when one option is named twice.
pub fn set_values(config: &Config, values: &[(&str, &str, &str)]) -> Result<Vec<FileEdit>, Error> {
    // (file, value span, change), sorted so each file's changes are in text order
    let mut planned: Vec<(usize, std::ops::Range<usize>, ValueChange)> = Vec::new();
    for &(section, key, new_value) in values {
        check_new_value(section, key, new_value)?;
        let option = config
            .option(section, key)
            .ok_or_else(|| Error::NotDefined {
                section: section.to_string(),
                key: key.to_lowercase(),
            })?;
        let origin = &option.origin;
        if let Some(written) = &option.written {
            return Err(in_reference(
                config,
                section,
                &option.key,
                written,
                new_value,
            ));
        }
        if origin.last_line != origin.first_line || option.value.contains('\n') {
            return Err(Error::MultiLineValue {
                section: section.to_string(),
                key: option.key.clone(),
                path: origin.path.clone(),
                first_line: origin.first_line,
                last_line: origin.last_line,
            });
        }
        if planned
            .iter()
            .any(|(_, _, c)| c.section == section && c.key == option.key)
        {
            return Err(Error::BadNewValue {
                section: section.to_string(),
                key: option.key.clone(),
                value: new_value.to_string(),
                reason: "the option is named twice in one edit".into(),
            });
        }
        planned.push((
            origin.file,
            origin.value_span.clone(),
            ValueChange {
                section: section.to_string(),
                key: option.key.clone(),
                line: origin.first_line,
                in_save_config: origin.in_save_config,
                old_value: option.value.clone(),
                new_value: new_value.to_string(),
            },
        ));
    }
    planned.sort_by_key(|(file, span, _)| (*file, span.start));
    let mut edits: Vec<FileEdit> = Vec::new();
    for (file, _, change) in planned {
        if edits.last().map(|e| e.file) != Some(file) {
            edits.push(FileEdit {
                path: config.files()[file].path.clone(),
                file,
                new_text: String::new(),
                changes: Vec::new(),
            });
        }
        if let Some(edit) = edits.last_mut() {
            edit.changes.push(change);
        }
    }
    for edit in &mut edits {
        edit.new_text = apply(config, edit)?;
    }
    verify(config, &edits)?;
    Ok(edits)
}

/// The refusal for a value Kalico reads through a reference (`${constants.rd_x}`): klipcal
/// does not edit it, since the reference is what the user wrote (and the constant may serve
/// other options); the message names where each referenced value is defined and what to write.
fn in_reference(config: &Config, section: &str, key: &str, written: &str, new: &str) -> Error {
    let places: Vec<String> = super::kalico::references_in(written)
        .into_iter()
        .map(|(sec, opt)| {
            let sec = sec.unwrap_or_else(|| section.to_string());
            let users = config
                .sections()
                .iter()
                .flat_map(|s| s.options.iter().map(move |o| (s, o)))
                .filter(|(s, o)| {
                    o.written.as_deref().is_some_and(|w| {
                        super::kalico::references_in(w)
                            .iter()
                            .any(|(rs, ro)| rs.as_deref().unwrap_or(&s.name) == sec && *ro == opt)
                    })
                })
                .count();
            let shared = if users > 1 {
                format!(", used by {users} options")
            } else {
                String::new()
            };
            match config.option(&sec, &opt) {
                Some(o) => format!(
                    "[{sec}] {opt}: {} in {} line {}{shared}",
                    o.value,
                    o.origin.path.display(),
                    o.origin.first_line
                ),
                None => format!("[{sec}] {opt}"),
            }
        })
        .collect();
    Error::InReference {
        section: section.to_string(),
        key: key.to_string(),
        written: written.to_string(),
        places: places.join("; "),
        new_value: new.to_string(),
    }
}

/// The file's text with every change's value bytes replaced.
fn apply(config: &Config, edit: &FileEdit) -> Result<String, Error> {
    let old_text = &config.files()[edit.file].text;
    let mut out = String::with_capacity(old_text.len() + 64);
    let mut pos = 0;
    for change in &edit.changes {
        let span = config
            .option(&change.section, &change.key)
            .map(|o| o.origin.value_span.clone())
            .ok_or_else(|| {
                Error::EditCheck(format!("[{}] {} vanished", change.section, change.key))
            })?;
        out.push_str(&old_text[pos..span.start]);
        out.push_str(&change.new_value);
        pos = span.end;
    }
    out.push_str(&old_text[pos..]);
    Ok(out)
}

fn check_new_value(section: &str, key: &str, value: &str) -> Result<(), Error> {
    let bad = |reason: &str| Error::BadNewValue {
        section: section.to_string(),
        key: key.to_lowercase(),
        value: value.to_string(),
        reason: reason.to_string(),
    };
    if value.contains(['\n', '\r']) {
        return Err(bad("it must be a single line"));
    }
    if value.contains('#') {
        return Err(bad("Klipper reads '#' as the start of a comment"));
    }
    let mut prev: Option<char> = None;
    for c in value.chars() {
        if c == ';' && prev.map_or(true, py_isspace) {
            return Err(bad(
                "Klipper reads ';' at the start or after a space as a comment",
            ));
        }
        prev = Some(c);
    }
    if value.starts_with(py_isspace) || value.ends_with(py_isspace) {
        return Err(bad("Klipper strips leading and trailing whitespace"));
    }
    Ok(())
}

/// Re-parses the files with the edits applied and compares every effective option.
fn verify(config: &Config, edits: &[FileEdit]) -> Result<(), Error> {
    let mut files = MemFiles::new();
    for (i, f) in config.files().iter().enumerate() {
        let text = edits
            .iter()
            .find(|e| e.file == i)
            .map_or(f.text.as_str(), |e| e.new_text.as_str());
        files.insert(&f.path, text);
    }
    let main = &config.files()[0].path;
    let after = Config::load_as(&files, main, config.dialect())
        .map_err(|e| Error::EditCheck(format!("the edited config no longer loads: {e}")))?;
    let flatten = |c: &Config| -> Vec<(String, String, String)> {
        c.sections()
            .iter()
            .flat_map(|s| {
                s.options
                    .iter()
                    // As written: a Kalico reference's value follows its constant.
                    .map(move |o| {
                        let text = o.written.as_ref().unwrap_or(&o.value);
                        (s.name.clone(), o.key.clone(), text.clone())
                    })
            })
            .collect()
    };
    let mut expected = flatten(config);
    for change in edits.iter().flat_map(|e| &e.changes) {
        for entry in &mut expected {
            if entry.0 == change.section && entry.1 == change.key {
                entry.2.clone_from(&change.new_value);
            }
        }
    }
    if flatten(&after) != expected {
        return Err(Error::EditCheck(
            "re-reading the edited files does not give the new values with every other option \
             unchanged"
                .into(),
        ));
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::super::config::tests::{fixture, fixture_files, PRINTER_CFG, STEPPERS_CFG};
    use super::*;
    use std::path::Path;

    #[test]
    fn a_value_in_an_included_file_is_replaced_keeping_every_other_byte() {
        let cfg = fixture();
        let edit = set_value(&cfg, "stepper_y", "rotation_distance", "40.1234").unwrap();
        assert_eq!(
            edit.path,
            PathBuf::from("/home/pi/printer_data/config/steppers.cfg")
        );
        assert_eq!(edit.changes[0].old_value, "40");
        assert!(!edit.changes[0].in_save_config);
        let expected = STEPPERS_CFG.replacen(
            "rotation_distance = 40 ; GT2 20T",
            "rotation_distance = 40.1234 ; GT2 20T",
            1,
        );
        assert_ne!(expected, STEPPERS_CFG);
        assert_eq!(edit.new_text, expected);
    }

    #[test]
    fn the_last_regular_definition_is_edited_not_the_ignored_save_config_copy() {
        // microsteps: 16 in steppers.cfg, 32 later in printer.cfg, 64 in SAVE_CONFIG (ignored)
        let cfg = fixture();
        let edit = set_value(&cfg, "stepper_x", "MICROSTEPS", "8").unwrap();
        assert_eq!(edit.file, 0);
        assert_eq!(edit.changes[0].old_value, "32");
        let expected = PRINTER_CFG.replacen(
            "[stepper_x]\nmicrosteps: 32",
            "[stepper_x]\nmicrosteps: 8",
            1,
        );
        assert_ne!(expected, PRINTER_CFG);
        assert_eq!(edit.new_text, expected);
        assert!(edit.new_text.contains("#*# microsteps = 64"));
    }

    #[test]
    fn an_option_only_in_the_save_config_block_is_edited_inside_the_block() {
        let cfg = fixture();
        let edit = set_value(&cfg, "skew_correction calilantern", "xy_skew", "-0.00093").unwrap();
        assert!(edit.changes[0].in_save_config);
        let expected = PRINTER_CFG.replacen("#*# xy_skew = 0.0012", "#*# xy_skew = -0.00093", 1);
        assert_ne!(expected, PRINTER_CFG);
        assert_eq!(edit.new_text, expected);
    }

    #[test]
    fn every_single_line_option_of_the_fixture_can_be_edited_and_reads_back() {
        let cfg = fixture();
        let mut edited = 0;
        for s in cfg.sections() {
            for o in &s.options {
                if o.value.contains('\n') {
                    continue;
                }
                let edit = set_value(&cfg, &s.name, &o.key, "7.25").unwrap();
                let mut files = fixture_files();
                files.insert(&edit.path, edit.new_text.clone());
                let after = Config::load(
                    &files,
                    Path::new("/home/pi/printer_data/config/printer.cfg"),
                )
                .unwrap();
                assert_eq!(
                    after.get(&s.name, &o.key),
                    Some("7.25"),
                    "[{}] {}",
                    s.name,
                    o.key
                );
                let old = &cfg.files()[edit.file].text;
                assert_eq!(
                    edit.new_text.len() as isize - old.len() as isize,
                    4 - o.value.len() as isize
                );
                edited += 1;
            }
        }
        assert!(edited > 25, "only {edited} options edited");
    }

    #[test]
    fn several_values_in_one_file_and_across_files_are_edited_together() {
        // values: the converged A/B result quoted in shared/seeds/README.md (source 000)
        let cfg = fixture();
        let edits = set_values(
            &cfg,
            &[
                ("stepper_y", "rotation_distance", "39.94284"),
                ("stepper_x", "rotation_distance", "40.10289"),
                ("skew_correction calilantern", "xy_skew", "0.0009"),
            ],
        )
        .unwrap();
        assert_eq!(edits.len(), 2);
        assert_eq!(edits[0].file, 0);
        assert_eq!(
            edits[0].new_text,
            PRINTER_CFG.replacen("#*# xy_skew = 0.0012", "#*# xy_skew = 0.0009", 1)
        );
        let expected = STEPPERS_CFG
            .replacen(
                "rotation_distance: 40\n",
                "rotation_distance: 40.10289\n",
                1,
            )
            .replacen(
                "rotation_distance = 40 ;",
                "rotation_distance = 39.94284 ;",
                1,
            );
        assert_eq!(edits[1].new_text, expected);
        let keys: Vec<&str> = edits[1]
            .changes
            .iter()
            .map(|c| c.section.as_str())
            .collect();
        assert_eq!(
            keys,
            ["stepper_x", "stepper_y"],
            "changes are in file order"
        );
        assert!(set_values(
            &cfg,
            &[
                ("stepper_x", "microsteps", "8"),
                ("stepper_x", "Microsteps", "4")
            ]
        )
        .is_err());
    }

    #[test]
    fn crlf_line_endings_and_comments_survive_an_edit() {
        let text = "[stepper_x]\r\nrotation_distance:40   # measured\r\nmicrosteps: 16\r\n";
        let files = MemFiles::new().with("/p.cfg", text);
        let cfg = Config::load(&files, Path::new("/p.cfg")).unwrap();
        let edit = set_value(&cfg, "stepper_x", "rotation_distance", "39.87").unwrap();
        assert_eq!(
            edit.new_text,
            "[stepper_x]\r\nrotation_distance:39.87   # measured\r\nmicrosteps: 16\r\n"
        );
    }

    #[test]
    fn multi_line_values_and_unknown_options_are_refused() {
        let cfg = fixture();
        assert!(matches!(
            set_value(&cfg, "gcode_macro PRINT_START", "gcode", "G28"),
            Err(Error::MultiLineValue { .. })
        ));
        assert!(matches!(
            set_value(&cfg, "bed_mesh default", "points", "0"),
            Err(Error::MultiLineValue { .. })
        ));
        assert!(matches!(
            set_value(&cfg, "stepper_x", "no_such_option", "1"),
            Err(Error::NotDefined { .. })
        ));
    }

    #[test]
    fn values_klipper_would_read_differently_are_refused() {
        let cfg = fixture();
        for v in ["40\n[x]", "40 # c", "40 ;c", ";40", " 40", "40 ", "4\r0"] {
            let r = set_value(&cfg, "stepper_y", "rotation_distance", v);
            assert!(matches!(r, Err(Error::BadNewValue { .. })), "{v:?}: {r:?}");
        }
        // a ';' inside a word is not a comment
        assert!(set_value(&cfg, "printer", "max_velocity", "a;b").is_ok());
    }
}
