//! [`plan_values`]: where and how new values are written so that Klipper runs them — every
//! stepper of an axis (AWD: `[stepper_x1]`, …) scaled together, and never into a file klipcal
//! must not touch (a symlink leaving the config folder, another project's git checkout): there
//! the value goes to `klipcal_overrides.cfg`, included last by the main file, where a later
//! definition wins. PURE: file texts in, file texts out; callers say which files are protected.

use std::path::{Path, PathBuf};

use super::config::{Config, SAVE_CONFIG_MARKER};
use super::edit::{set_values, FileEdit, ValueChange};
use super::facts::{parse_gear_ratio, py_float};
use super::files::MemFiles;
use super::Error;

/// The klipcal-managed include that holds values which cannot be written where they are
/// defined; it sits beside the main file and is included at the end of its regular part.
pub const OVERRIDES_FILE: &str = "klipcal_overrides.cfg";

/// Largest relative difference in travel per motor turn between steppers of one axis that
/// klipcal scales together (1 %).
pub const COMPANION_TOLERANCE: f64 = 0.01;

/// `(section, key, value)`.
pub type Triple = (String, String, String);

/// A file klipcal must not write, and why (said to the user).
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Protected {
    /// The file, as the config read it.
    pub path: PathBuf,
    /// Why, e.g. "it is reached through a symlink leading out of the config folder".
    pub reason: String,
}

/// One file to write.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct PlannedFile {
    /// The file.
    pub path: PathBuf,
    /// Its text now; `None` when the plan creates it.
    pub old_text: Option<String>,
    /// Its text after the write.
    pub new_text: String,
}

/// What [`plan_values`] decided.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct WritePlan {
    /// Files to write (existing ones changed, new ones created), in read order.
    pub files: Vec<PlannedFile>,
    /// Every value written, companions included.
    pub changes: Vec<ValueChange>,
    /// `(section, key, value)` of every value written, companions included: what Klipper must
    /// report after the restart.
    pub values: Vec<(String, String, String)>,
    /// Sentences for the user: companions scaled, values moved to the overrides file and why.
    pub notes: Vec<String>,
}

/// Plans writing `values` (`(section, key, new value)`): companions added (see
/// [`companion_values`]), each value edited where Klipper reads it unless that file is
/// `protected`, in which case it is written to [`OVERRIDES_FILE`] (created and included at the
/// end of the main file when needed). All or nothing.
///
/// # Errors
/// As [`companion_values`] and [`set_values`]; [`Error::Protected`] when the main file itself
/// is protected, or a value still would not win from the overrides file.
pub fn plan_values(
    config: &Config,
    values: &[(String, String, String)],
    protected: &[Protected],
) -> Result<WritePlan, Error> {
    let (values, mut notes) = companion_values(config, values)?;
    let main = config.files()[0].path.clone();
    if let Some(p) = find_protected(protected, &main) {
        return Err(Error::Protected(format!(
            "the main config file {} is not klipcal's to change: {}",
            main.display(),
            p.reason
        )));
    }
    // Values whose definition is in a protected file move to the overrides file.
    let mut moved: Vec<Moved<'_>> = Vec::new();
    for v in &values {
        let origin = config.option(&v.0, &v.1).map(|o| o.origin.path.clone());
        if let Some(path) = origin {
            if let Some(p) = find_protected(protected, &path) {
                moved.push((v, p, path));
            }
        }
    }
    let working = if moved.is_empty() {
        config.clone()
    } else {
        with_overrides(config, &moved, &mut notes)?
    };
    let triples: Vec<(&str, &str, &str)> = values
        .iter()
        .map(|(s, k, v)| (s.as_str(), k.as_str(), v.as_str()))
        .collect();
    let edits = set_values(&working, &triples)?;
    let (files, changes) = planned_files(config, &working, &edits, protected)?;
    Ok(WritePlan {
        files,
        changes,
        values,
        notes,
    })
}

/// A value whose definition is in a protected file: the value, why the file is protected, the
/// file.
type Moved<'a> = (&'a (String, String, String), &'a Protected, PathBuf);

fn find_protected<'a>(protected: &'a [Protected], path: &Path) -> Option<&'a Protected> {
    protected.iter().find(|x| x.path == path)
}

/// The config with the `moved` values' current definitions copied into [`OVERRIDES_FILE`]
/// (created and included at the end of the main file when needed): the same effective config,
/// with those values now defined where they win. A note per value says so.
fn with_overrides(
    config: &Config,
    moved: &[Moved<'_>],
    notes: &mut Vec<String>,
) -> Result<Config, Error> {
    let main = config.files()[0].path.clone();
    let mut files = MemFiles::new();
    for f in config.files() {
        files.insert(&f.path, f.text.clone());
    }
    let dir = main.parent().unwrap_or(Path::new("/"));
    let over_path = dir.join(OVERRIDES_FILE);
    let existing = config.files().iter().find(|f| f.path == over_path);
    let mut over_text = match existing {
        Some(f) => f.text.clone(),
        None => "# Written by klipcal: values that cannot be changed where they are defined\n\
                 # (another project's files). Included at the end of printer.cfg, so these\n\
                 # definitions win. Edit them here.\n"
            .to_string(),
    };
    if !over_text.is_empty() && !over_text.ends_with('\n') {
        over_text.push('\n');
    }
    for ((section, key, _), _, _) in moved {
        let old = config.get(section, key).unwrap_or_default();
        over_text.push_str(&format!("\n[{section}]\n{key}: {old}\n"));
    }
    files.insert(&over_path, over_text);
    if existing.is_none() {
        let new = add_include(
            &config.files()[0].text,
            OVERRIDES_FILE,
            "klipcal: its overrides, read last so they win",
        );
        files.insert(&main, new);
    }
    let working = Config::load_as(&files, &main, config.dialect())
        .map_err(|e| Error::Protected(format!("adding {OVERRIDES_FILE} breaks the config: {e}")))?;
    // Same effective config, only now defined in the overrides file.
    let flat = |c: &Config| -> Vec<(String, String, String)> {
        c.sections()
            .iter()
            .flat_map(|s| {
                s.options
                    .iter()
                    .map(move |o| (s.name.clone(), o.key.clone(), o.value.clone()))
            })
            .collect()
    };
    if flat(&working) != flat(config) {
        return Err(Error::Protected(format!(
            "adding {OVERRIDES_FILE} would change other settings; add `[include \
             {OVERRIDES_FILE}]` at the end of {} by hand",
            main.display()
        )));
    }
    for ((section, key, _), p, path) in moved {
        let now = working.option(section, key).map(|o| o.origin.path.clone());
        if now.as_deref() != Some(over_path.as_path()) {
            return Err(Error::Protected(format!(
                "[{section}] {key} is defined in {} ({}), and a definition in {} would not \
                 win: a later one in {} does; move `[include {OVERRIDES_FILE}]` to the end \
                 of {}",
                path.display(),
                p.reason,
                over_path.display(),
                now.map_or("?".into(), |p| p.display().to_string()),
                main.display()
            )));
        }
        notes.push(format!(
            "[{section}] {key} is defined in {}, which klipcal does not change: {}. The new \
             value is written to {} instead, included at the end of {} so Klipper reads it \
             last and it wins",
            path.display(),
            p.reason,
            over_path.display(),
            main.display()
        ));
    }
    Ok(working)
}

/// The files whose text the edits change (new ones included), in read order, and every value
/// changed; refused when one of them is protected.
fn planned_files(
    config: &Config,
    working: &Config,
    edits: &[FileEdit],
    protected: &[Protected],
) -> Result<(Vec<PlannedFile>, Vec<ValueChange>), Error> {
    let mut planned = Vec::new();
    let mut changes = Vec::new();
    for (i, f) in working.files().iter().enumerate() {
        let new_text = edits
            .iter()
            .find(|e| e.file == i)
            .map_or(f.text.clone(), |e| e.new_text.clone());
        if let Some(e) = edits.iter().find(|e| e.file == i) {
            changes.extend(e.changes.iter().cloned());
        }
        let old_text = config
            .files()
            .iter()
            .find(|o| o.path == f.path)
            .map(|o| o.text.clone());
        if old_text.as_deref() != Some(new_text.as_str()) {
            if find_protected(protected, &f.path).is_some() {
                return Err(Error::EditCheck(format!(
                    "the plan would write the protected file {}",
                    f.path.display()
                )));
            }
            planned.push(PlannedFile {
                path: f.path.clone(),
                old_text,
                new_text,
            });
        }
    }
    Ok((planned, changes))
}

/// `text` (a main config file) with `[include <file>]` after a `# <comment>` line appended at
/// the end of its regular part: before the SAVE_CONFIG block, read after everything else.
pub fn add_include(text: &str, file: &str, comment: &str) -> String {
    let at = text
        .find(&format!("\n{SAVE_CONFIG_MARKER}"))
        .map_or(text.len(), |i| i + 1);
    let mut new = text[..at].to_string();
    if !new.is_empty() && !new.ends_with('\n') {
        new.push('\n');
    }
    new.push_str(&format!("\n# {comment}\n[include {file}]\n"));
    if at < text.len() {
        new.push('\n');
    }
    new.push_str(&text[at..]);
    new
}

/// Adds, for every `rotation_distance` of a `[stepper_<axis>]`, the same change to the other
/// steppers of that axis — `[stepper_<axis>1]`, `2`, … up to the first gap, as Klipper's
/// `LookupMultiRail` finds them — each scaled from its own value by the same factor. A
/// companion the caller already names is left as given. Returns the values and notes.
///
/// # Errors
/// [`Error::Companion`] when a companion has no `rotation_distance`, or moves more than
/// [`COMPANION_TOLERANCE`] differently per motor turn (then the factor cannot be carried over
/// safely); [`Error::BadValue`] for a value that is not a number above 0.
pub fn companion_values(
    config: &Config,
    values: &[(String, String, String)],
) -> Result<(Vec<Triple>, Vec<String>), Error> {
    let mut out: Vec<(String, String, String)> = values.to_vec();
    let mut notes = Vec::new();
    for (section, key, new_text) in values {
        if !key.eq_ignore_ascii_case("rotation_distance") {
            continue;
        }
        let Some(axis) = section.strip_prefix("stepper_") else {
            continue;
        };
        if axis.is_empty() || axis.ends_with(|c: char| c.is_ascii_digit()) {
            continue;
        }
        let number = |sec: &str, text: &str| -> Result<f64, Error> {
            py_float(text)
                .filter(|v| *v > 0.0)
                .ok_or_else(|| Error::BadValue {
                    section: sec.to_string(),
                    key: "rotation_distance".into(),
                    value: text.to_string(),
                    expected: "a number of mm above 0".into(),
                })
        };
        let travel = |sec: &str| -> Result<Option<(f64, f64, String)>, Error> {
            let Some(rd) = config.get(sec, "rotation_distance") else {
                return Ok(None);
            };
            let rd_mm = number(sec, rd)?;
            let gear = match config.get(sec, "gear_ratio") {
                Some(t) => parse_gear_ratio(sec, t)?,
                None => 1.0,
            };
            Ok(Some((rd_mm, rd_mm / gear, rd.to_string())))
        };
        let Some((old_mm, old_travel, old_text)) = travel(section)? else {
            continue;
        };
        let new_mm = number(section, new_text)?;
        let factor = new_mm / old_mm;
        for i in 1..99 {
            let comp = format!("{section}{i}");
            if !config.has_section(&comp) {
                break;
            }
            if out
                .iter()
                .any(|(s, k, _)| *s == comp && k.eq_ignore_ascii_case("rotation_distance"))
            {
                continue;
            }
            let Some((c_mm, c_travel, c_text)) = travel(&comp)? else {
                return Err(Error::Companion(format!(
                    "[{comp}] drives the same axis as [{section}] but has no rotation_distance; \
                     klipcal must change both together"
                )));
            };
            let diff = (c_travel / old_travel - 1.0).abs();
            if diff > COMPANION_TOLERANCE {
                return Err(Error::Companion(format!(
                    "[{comp}] drives the same axis as [{section}] but moves {c_travel:.4} mm \
                     per motor turn where [{section}] moves {old_travel:.4} mm ({:.1} % apart, \
                     more than {:.0} %); klipcal scales both by the same factor only when they \
                     agree. Check both sections' rotation_distance and gear_ratio",
                    diff * 100.0,
                    COMPANION_TOLERANCE * 100.0
                )));
            }
            let new_c = if c_text.trim() == old_text.trim() {
                new_text.clone()
            } else {
                let s = format!("{:.6}", c_mm * factor);
                s.trim_end_matches('0').trim_end_matches('.').to_string()
            };
            notes.push(format!(
                "[{comp}] drives the same axis as [{section}]: its rotation_distance is scaled \
                 by the same factor ({c_text} → {new_c})"
            ));
            out.push((comp, "rotation_distance".into(), new_c));
        }
    }
    Ok((out, notes))
}

#[cfg(test)]
mod tests {
    use super::*;

    const MAIN: &str = "[include theme/steppers.cfg]\n[printer]\nkinematics: corexy\n";
    const AWD: &str = "[stepper_x]\nrotation_distance: 40\nmicrosteps: 16\n\
        [stepper_x1]\nrotation_distance: 40\n\
        [stepper_y]\nrotation_distance: 40\n\
        [stepper_y1]\nrotation_distance: 20\ngear_ratio: 1:2\n";

    fn load(main: &str, steppers: &str) -> Config {
        let files = MemFiles::new()
            .with("/c/printer.cfg", main)
            .with("/c/theme/steppers.cfg", steppers);
        Config::load(&files, Path::new("/c/printer.cfg")).unwrap()
    }

    fn v(s: &str, k: &str, val: &str) -> (String, String, String) {
        (s.into(), k.into(), val.into())
    }

    /// The planned files as a config again.
    fn reload(cfg: &Config, plan: &WritePlan) -> Config {
        let mut files = MemFiles::new();
        for f in cfg.files() {
            files.insert(&f.path, f.text.clone());
        }
        for f in &plan.files {
            files.insert(&f.path, f.new_text.clone());
        }
        Config::load(&files, Path::new("/c/printer.cfg")).unwrap()
    }

    #[test]
    fn awd_companions_get_their_own_value_scaled_by_the_same_factor() {
        let cfg = load(MAIN, AWD);
        let plan = plan_values(
            &cfg,
            &[
                v("stepper_x", "rotation_distance", "40.2"),
                v("stepper_y", "rotation_distance", "39.9"),
            ],
            &[],
        )
        .unwrap();
        let after = reload(&cfg, &plan);
        assert_eq!(after.get("stepper_x", "rotation_distance"), Some("40.2"));
        assert_eq!(after.get("stepper_x1", "rotation_distance"), Some("40.2"));
        assert_eq!(after.get("stepper_y", "rotation_distance"), Some("39.9"));
        // 20 × 39.9 / 40 = 19.95 (gear 1:2: same 40 mm per motor turn)
        assert_eq!(after.get("stepper_y1", "rotation_distance"), Some("19.95"));
        assert_eq!(plan.values.len(), 4);
        assert_eq!(plan.notes.len(), 2, "{:?}", plan.notes);
        assert!(plan.notes[0].contains("[stepper_x1] drives the same axis as [stepper_x]"));
    }

    #[test]
    fn a_companion_that_moves_differently_refuses_the_whole_apply() {
        let cfg = load(
            MAIN,
            &AWD.replacen(
                "[stepper_x1]\nrotation_distance: 40",
                "[stepper_x1]\nrotation_distance: 40.5",
                1,
            ),
        );
        let err = plan_values(&cfg, &[v("stepper_x", "rotation_distance", "40.2")], &[])
            .unwrap_err()
            .to_string();
        assert!(err.contains("[stepper_x1] drives the same axis"), "{err}");
        assert!(err.contains("1.2 % apart"), "{err}");
        // within 1 %: scaled from its own value, 40.3 × 40.2 / 40 = 40.5015
        let cfg = load(
            MAIN,
            &AWD.replacen(
                "[stepper_x1]\nrotation_distance: 40",
                "[stepper_x1]\nrotation_distance: 40.3",
                1,
            ),
        );
        let plan = plan_values(&cfg, &[v("stepper_x", "rotation_distance", "40.2")], &[]).unwrap();
        assert_eq!(
            reload(&cfg, &plan).get("stepper_x1", "rotation_distance"),
            Some("40.5015")
        );
        // a companion without rotation_distance is refused too
        let cfg = load(
            MAIN,
            "[stepper_x]\nrotation_distance: 40\n[stepper_x1]\nmicrosteps: 16\n",
        );
        let err = plan_values(&cfg, &[v("stepper_x", "rotation_distance", "40.2")], &[])
            .unwrap_err()
            .to_string();
        assert!(err.contains("has no rotation_distance"), "{err}");
    }

    #[test]
    fn a_value_in_a_protected_file_goes_to_the_overrides_include_read_last() {
        let main = format!(
            "{MAIN}\n#*# <---------------------- SAVE_CONFIG ---------------------->\n\
             #*# DO NOT EDIT THIS BLOCK OR BELOW. The contents are auto-generated.\n#*#\n\
             #*# [stepper_z]\n#*# position_endstop = 1.5\n"
        );
        let cfg = load(
            &main,
            "[stepper_x]\nrotation_distance: 40\n[stepper_y]\nrotation_distance: 40\n",
        );
        let protected = [Protected {
            path: "/c/theme/steppers.cfg".into(),
            reason: "it lies in /c/theme, another project's git checkout".into(),
        }];
        let plan = plan_values(
            &cfg,
            &[v("stepper_x", "rotation_distance", "40.2")],
            &protected,
        )
        .unwrap();
        let paths: Vec<_> = plan.files.iter().map(|f| f.path.clone()).collect();
        assert_eq!(
            paths,
            [
                PathBuf::from("/c/printer.cfg"),
                PathBuf::from("/c/klipcal_overrides.cfg")
            ]
        );
        assert!(plan.files[1].old_text.is_none());
        let printer = &plan.files[0].new_text;
        let inc = printer.find("[include klipcal_overrides.cfg]").unwrap();
        assert!(inc < printer.find(SAVE_CONFIG_MARKER).unwrap(), "{printer}");
        assert!(plan.files[1]
            .new_text
            .ends_with("[stepper_x]\nrotation_distance: 40.2\n"));
        assert!(
            plan.notes[0].contains("/c/theme/steppers.cfg"),
            "{:?}",
            plan.notes
        );
        assert!(plan.notes[0].contains("git checkout"), "{:?}", plan.notes);
        assert!(
            plan.notes[0].contains("/c/klipcal_overrides.cfg"),
            "{:?}",
            plan.notes
        );
        let after = reload(&cfg, &plan);
        let o = after.option("stepper_x", "rotation_distance").unwrap();
        assert_eq!(o.value, "40.2");
        assert_eq!(o.origin.path, PathBuf::from("/c/klipcal_overrides.cfg"));
        assert_eq!(after.get("stepper_y", "rotation_distance"), Some("40"));
        assert_eq!(after.get("stepper_z", "position_endstop"), Some("1.5"));

        // Once it exists and is included, the value is edited there in place.
        let mut files = MemFiles::new();
        for f in cfg.files() {
            files.insert(&f.path, f.text.clone());
        }
        for f in &plan.files {
            files.insert(&f.path, f.new_text.clone());
        }
        let cfg2 = Config::load(&files, Path::new("/c/printer.cfg")).unwrap();
        let plan2 = plan_values(
            &cfg2,
            &[v("stepper_x", "rotation_distance", "40.1")],
            &protected,
        )
        .unwrap();
        assert_eq!(plan2.files.len(), 1);
        assert_eq!(
            plan2.files[0].path,
            PathBuf::from("/c/klipcal_overrides.cfg")
        );
        assert!(plan2.notes.is_empty());
    }

    #[test]
    fn a_protected_main_file_is_refused() {
        let cfg = load(MAIN, AWD);
        let err = plan_values(
            &cfg,
            &[v("stepper_x", "rotation_distance", "40.2")],
            &[Protected {
                path: "/c/printer.cfg".into(),
                reason: "a symlink".into(),
            }],
        )
        .unwrap_err();
        assert!(matches!(err, Error::Protected(_)), "{err}");
    }
}
