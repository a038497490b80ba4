//! Where Kalico's configfile (2026.10, `klippy/configfile.py`) reads a config differently from
//! Klipper's, reproduced for [`super::Config::load_as`] with [`Dialect::Kalico`]. PURE.
//!
//! - **References** (`SectionInterpolation`): every value read has each `${section.option}`,
//!   `${section:option}` or `${option}` (same section) replaced by that option's own value,
//!   itself read the same way (so references nest), at most 10 replacements per value. The
//!   option name is matched lowercased, the section as written; a missing one is an error when
//!   the value is read, and Kalico reads every value at start (its `configfile` status). The
//!   pattern's guard against `\${` never applies (its look-behind is optional), so `\${a.b}`
//!   is replaced too and keeps the backslash; a `\${` left after the replacements becomes `${`.
//! - **`!!include FILE` inside a value** (macro bodies): the file name is made absolute against
//!   the including file's folder, and must exist.
//! - **`[include]` globs are recursive**: a `**` component matches any depth of folders.

use std::path::{Path, PathBuf};

use super::config::Section;
use super::Error;

/// Whose rules the config is read by.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum Dialect {
    /// Klipper's klippy (`configfile.py` 0.12 and today's).
    #[default]
    Klipper,
    /// Kalico's klippy: references, `!!include` in values, recursive `**` includes.
    Kalico,
}

impl Dialect {
    /// The dialect of the Klipper that Moonraker's `printer.info` describes: Kalico says
    /// `"app": "Kalico"` (earlier releases of the fork: `"DangerKlipper"`).
    #[must_use]
    pub fn of_app(app: Option<&str>) -> Dialect {
        match app.map(str::to_ascii_lowercase).as_deref() {
            Some("kalico" | "dangerklipper" | "danger-klipper") => Dialect::Kalico,
            _ => Dialect::Klipper,
        }
    }
}

/// Python's `configparser.MAX_INTERPOLATION_DEPTH`.
const MAX_REPLACEMENTS: usize = 10;

/// One `${…}` found in a value: its byte range and the (section, option) it names.
struct Reference {
    start: usize,
    end: usize,
    section: Option<String>,
    option: String,
}

/// The leftmost `${…}` as Kalico's `_KEYCRE` finds it.
fn find_reference(value: &str) -> Option<Reference> {
    let mut from = 0;
    while let Some(at) = value[from..].find("${") {
        let start = from + at;
        let body_start = start + 2;
        let body_len = value[body_start..]
            .find(['$', '{', '}'])
            .unwrap_or(value.len() - body_start);
        let body = &value[body_start..body_start + body_len];
        if !body.is_empty() && value[body_start + body_len..].starts_with('}') {
            // (?:(?P<section>[^.:${}]+)[.:])? then (?P<option>[^${}]+)
            let (section, option) = match body.find(['.', ':']) {
                Some(i) if i > 0 && i + 1 < body.len() => {
                    (Some(body[..i].to_string()), body[i + 1..].to_string())
                }
                _ => (None, body.to_string()),
            };
            return Some(Reference {
                start,
                end: body_start + body_len + 1,
                section,
                option,
            });
        }
        from = start + 1;
    }
    None
}

/// The value of `[section] key` as Kalico reads it, references replaced. `chain` holds the
/// options being read (a reference back into it is refused, where Python recurses until it
/// gives up).
fn read(
    sections: &[Section],
    section: &str,
    key: &str,
    chain: &mut Vec<String>,
) -> Result<String, String> {
    let here = format!("[{section}] {key}");
    if chain.contains(&here) {
        return Err(format!("references loop: {} -> {here}", chain.join(" -> ")));
    }
    let raw = sections
        .iter()
        .find(|s| s.name == section)
        .ok_or_else(|| format!("there is no section [{section}]"))?
        .option(key)
        .ok_or_else(|| format!("[{section}] has no option '{}'", key.to_lowercase()))?
        .value
        .clone();
    chain.push(here);
    let out = replace_references(sections, section, &raw, chain);
    chain.pop();
    out
}

fn replace_references(
    sections: &[Section],
    section: &str,
    raw: &str,
    chain: &mut Vec<String>,
) -> Result<String, String> {
    let mut value = raw.to_string();
    for _ in 0..MAX_REPLACEMENTS {
        let Some(r) = find_reference(&value) else {
            break;
        };
        let target_section = r.section.as_deref().unwrap_or(section);
        let text = read(sections, target_section, &r.option, chain)?;
        value = format!("{}{}{}", &value[..r.start], text, &value[r.end..]);
    }
    Ok(value.replace("\\${", "${"))
}

/// Every option's value with its references replaced (what Kalico reports and runs), each
/// `(section index, option index, value)` whose value changed.
///
/// # Errors
/// [`Error::BadValue`] naming the option whose reference names nothing, or loops.
pub(crate) fn resolve_references(
    sections: &[Section],
) -> Result<Vec<(usize, usize, String)>, Error> {
    let mut changed = Vec::new();
    for (si, s) in sections.iter().enumerate() {
        for (oi, o) in s.options.iter().enumerate() {
            if !o.value.contains("${") {
                continue;
            }
            let value = replace_references(sections, &s.name, &o.value, &mut Vec::new()).map_err(
                |why| Error::BadValue {
                    section: s.name.clone(),
                    key: o.key.clone(),
                    value: o.value.clone(),
                    expected: format!(
                        "references (${{section.option}}) Kalico can follow; here {why}"
                    ),
                },
            )?;
            if value != o.value {
                changed.push((si, oi, value));
            }
        }
    }
    Ok(changed)
}

/// The references in a raw value, as `(section, option)` (section `None`: the value's own).
#[must_use]
pub(crate) fn references_in(raw: &str) -> Vec<(Option<String>, String)> {
    let mut out = Vec::new();
    let mut rest = raw;
    while let Some(r) = find_reference(rest) {
        out.push((r.section, r.option.to_lowercase()));
        rest = &rest[r.end..];
    }
    out
}

/// Kalico's `_fix_include_path` on one line: `!!include NAME` (to the end of the line) becomes
/// `!!include /absolute/NAME`, resolved against `dir`. Returns the line and the file named, so
/// that the caller checks it exists.
#[must_use]
pub(crate) fn fix_value_include(line: &str, dir: &Path) -> Option<(String, PathBuf)> {
    let at = line.find("!!include ")?;
    let name = &line[at + "!!include ".len()..];
    let path = dir.join(name);
    Some((format!("{}!!include {}", &line[..at], path.display()), path))
}

/// True when an `[include]` pattern is globbed recursively by Kalico (a `**` component).
#[must_use]
pub(crate) fn is_recursive(pattern: &Path) -> bool {
    pattern.components().any(|c| c.as_os_str() == "**")
}

/// Kalico's refusal to heat a `control: mpc` heater that is not calibrated yet ("Cannot
/// activate 'heater_bed' as MPC control is not fully configured. Run 'MPC_CALIBRATE' or …"),
/// said in plain words with what to do, when `msg` holds it.
#[must_use]
pub fn mpc_refusal(msg: &str) -> Option<String> {
    if !msg.contains("MPC control is not fully configured") {
        return None;
    }
    let heater = msg
        .split("Cannot activate '")
        .nth(1)
        .and_then(|r| r.split('\'').next())
        .filter(|h| {
            !h.is_empty()
                && h.chars()
                    .all(|c| c.is_ascii_alphanumeric() || "_ ".contains(c))
        })
        .unwrap_or("the heater");
    Some(format!(
        "Kalico will not heat {heater}: its [{heater}] uses control: mpc, which has not been \
         calibrated yet. Run MPC_CALIBRATE HEATER={heater} once (the heater heats and cools by \
         itself for a few minutes), then SAVE_CONFIG; or set block_heat_capacity, \
         sensor_responsiveness and ambient_transfer under [{heater}]. Then start again"
    ))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn references_are_found_as_kalicos_pattern_finds_them() {
        assert_eq!(
            references_in("${constants.rd_x}"),
            vec![(Some("constants".into()), "rd_x".into())]
        );
        assert_eq!(
            references_in("a ${c:B} b ${own}"),
            vec![(Some("c".into()), "b".into()), (None, "own".into())]
        );
        // `a.b.c`: the section ends at the first dot; `${.x}` and `${a.}` have no section.
        assert_eq!(
            references_in("${a.b.c}${.x}${a.}"),
            vec![
                (Some("a".into()), "b.c".into()),
                (None, ".x".into()),
                (None, "a.".into())
            ]
        );
        assert!(references_in("${} ${a{b} $x {y}").is_empty());
    }

    use crate::klipper::{set_values, Config, Error, MemFiles};

    fn kalico(files: &MemFiles) -> Result<Config, Error> {
        Config::load_as(files, Path::new("/c/printer.cfg"), Dialect::Kalico)
    }

    #[test]
    fn references_includes_and_recursive_globs_are_read_as_kalico_reads_them() {
        let files = MemFiles::new()
            .with(
                "/c/printer.cfg",
                "[include conf.d/**/*.cfg]\n[constants]\nrd_x: ${rd}\nrd: 40.5\n\
                 [stepper_x]\nrotation_distance: ${constants.rd_x}\nmicrosteps: ${ms}\nms: 16\n\
                 [gcode_macro A]\ngcode: !!include macros/a.gcode\n",
            )
            .with("/c/conf.d/top.cfg", "[top]\nx: 1\n")
            .with("/c/conf.d/deep/er/low.cfg", "[low]\nx: ${constants:rd}\n")
            .with("/c/conf.d/.hidden/h.cfg", "[hidden]\nx: 1\n")
            .with("/c/macros/a.gcode", "M117 a\n");
        let c = kalico(&files).unwrap();
        assert_eq!(c.get("stepper_x", "rotation_distance"), Some("40.5"));
        assert_eq!(
            c.option("stepper_x", "rotation_distance")
                .unwrap()
                .written
                .as_deref(),
            Some("${constants.rd_x}")
        );
        assert_eq!(c.get("stepper_x", "microsteps"), Some("16"));
        assert_eq!(c.get("low", "x"), Some("40.5"));
        assert!(c.has_section("top") && !c.has_section("hidden"));
        assert_eq!(
            c.get("gcode_macro A", "gcode"),
            Some("!!include /c/macros/a.gcode")
        );
        // Klipper reads the same text literally, and `**` as `*` (one folder level).
        let k = Config::load(&files, Path::new("/c/printer.cfg")).unwrap();
        assert_eq!(
            k.get("stepper_x", "rotation_distance"),
            Some("${constants.rd_x}")
        );
        assert!(!k.has_section("top") && !k.has_section("low"));
    }

    #[test]
    fn a_reference_to_nothing_or_a_loop_is_refused_by_name() {
        let one = |text: &str| {
            kalico(&MemFiles::new().with("/c/printer.cfg", text))
                .unwrap_err()
                .to_string()
        };
        let e = one("[a]\nx: ${constants.nope}\n[constants]\n");
        assert!(e.contains("[a] x") && e.contains("no option 'nope'"), "{e}");
        let e = one("[a]\nx: ${y}\ny: ${x}\n");
        assert!(e.contains("loop"), "{e}");
        let e = one("[a]\ngcode: !!include missing.gcode\n");
        assert!(e.contains("missing.gcode"), "{e}");
    }

    #[test]
    fn an_edit_of_a_value_written_as_a_reference_is_refused_with_where_to_edit() {
        let files = MemFiles::new().with(
            "/c/printer.cfg",
            "[constants]\nrd: 40\n[stepper_x]\nrotation_distance: ${constants.rd}\n\
             [stepper_y]\nrotation_distance: ${constants.rd}\n",
        );
        let c = kalico(&files).unwrap();
        let e = set_values(&c, &[("stepper_x", "rotation_distance", "40.1")])
            .unwrap_err()
            .to_string();
        assert!(e.contains("'${constants.rd}'"), "{e}");
        assert!(
            e.contains("[constants] rd: 40 in /c/printer.cfg line 2"),
            "{e}"
        );
        assert!(e.contains("used by 2 options") && e.contains("40.1"), "{e}");
        // The constant itself is an ordinary value.
        assert!(set_values(&c, &[("constants", "rd", "40.1")]).is_ok());
    }

    #[test]
    fn an_uncalibrated_mpc_heater_is_explained_with_what_to_run() {
        // Kalico 2026.10's control_mpc.py text, as Moonraker passes it on.
        let kalico = "Cannot activate 'heater_bed' as MPC control is not fully configured.\n\n\
                      Run 'MPC_CALIBRATE' or ensure 'block_heat_capacity', \
                      'sensor_responsiveness', and 'ambient_transfer' settings are defined for \
                      'heater_bed'.";
        let said = mpc_refusal(kalico).unwrap();
        assert!(
            said.starts_with("Kalico will not heat heater_bed"),
            "{said}"
        );
        assert!(said.contains("MPC_CALIBRATE HEATER=heater_bed"), "{said}");
        assert!(!said.contains('\n'), "one console line: {said}");
        assert_eq!(mpc_refusal("Extrude below minimum temp"), None);
    }

    #[test]
    fn the_app_name_says_kalico() {
        assert_eq!(Dialect::of_app(Some("Kalico")), Dialect::Kalico);
        assert_eq!(Dialect::of_app(Some("Klipper")), Dialect::Klipper);
        assert_eq!(Dialect::of_app(None), Dialect::Klipper);
    }

    #[test]
    fn a_value_include_is_made_absolute() {
        let (line, path) =
            fix_value_include("gcode: !!include macros/start.gcode", Path::new("/c")).unwrap();
        assert_eq!(line, "gcode: !!include /c/macros/start.gcode");
        assert_eq!(path, Path::new("/c/macros/start.gcode"));
        assert!(fix_value_include("gcode: M117 hi", Path::new("/c")).is_none());
    }
}
