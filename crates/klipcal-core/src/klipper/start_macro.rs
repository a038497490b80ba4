//! [`find_start_macro`]: which `[gcode_macro …]` a slicer calls to start a print — the one the
//! user configured, else `PRINT_START` or `START_PRINT` (both names are common: Voron's configs
//! say PRINT_START, Klippain and many others START_PRINT). PURE: works on section names.

use super::config::Config;
use super::Error;

/// The names slicer profiles commonly call, in the order they are reported.
pub const COMMON_START_MACROS: [&str; 2] = ["PRINT_START", "START_PRINT"];

/// The outcome of looking for the start macro.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum StartMacro {
    /// The macro to use.
    Found {
        /// The G-code command, upper case as Klipper registers it (`START_PRINT`).
        command: String,
        /// Its config section as written (`gcode_macro start_print`), to read its `gcode`.
        section: String,
        /// True when it came from the settings (`[ab] start_macro`), not from its name.
        configured: bool,
    },
    /// More than one common name is defined and none is configured: ask which one the slicer
    /// calls (and suggest setting `[ab] start_macro`). Commands upper case, in
    /// [`COMMON_START_MACROS`] order.
    Ambiguous(Vec<String>),
    /// No macro with a common name, none configured: ask for the name (or print without one).
    NotFound,
}

/// Finds the start macro in a loaded config; see [`find_start_macro_in`].
///
/// # Errors
/// As [`find_start_macro_in`].
pub fn find_start_macro(config: &Config, configured: Option<&str>) -> Result<StartMacro, Error> {
    find_start_macro_in(
        config.sections().iter().map(|s| s.name.as_str()),
        configured,
    )
}

/// Finds the start macro among config section names (a [`Config`]'s, or the keys of
/// Moonraker's `configfile.config`). Macro names match case-insensitively, as Klipper
/// registers G-code commands upper case. `configured` (from `[ab] start_macro`; `None` or
/// empty for "find it") wins when set.
///
/// # Errors
/// [`Error::BadName`] for a configured name outside `[A-Za-z0-9_]`; [`Error::MissingSection`]
/// when the configured macro is not defined (naming the common ones that are).
pub fn find_start_macro_in<'a>(
    section_names: impl IntoIterator<Item = &'a str>,
    configured: Option<&str>,
) -> Result<StartMacro, Error> {
    // (command upper case, section as written)
    let macros: Vec<(String, &str)> = section_names
        .into_iter()
        .filter_map(|s| {
            let mut words = s.split_whitespace();
            (words.next() == Some("gcode_macro"))
                .then(|| words.next())
                .flatten()
                .filter(|_| words.next().is_none())
                .map(|name| (name.to_uppercase(), s))
        })
        .collect();
    let lookup = |cmd: &str| macros.iter().find(|(c, _)| c == cmd).map(|(_, s)| *s);
    let common: Vec<String> = COMMON_START_MACROS
        .iter()
        .filter(|c| lookup(c).is_some())
        .map(|c| c.to_string())
        .collect();
    if let Some(name) = configured.map(str::trim).filter(|n| !n.is_empty()) {
        if !name.chars().all(|c| c.is_ascii_alphanumeric() || c == '_') {
            return Err(Error::BadName {
                what: "start macro name (ab.start_macro)".into(),
                name: name.to_string(),
            });
        }
        let command = name.to_uppercase();
        return match lookup(&command) {
            Some(section) => Ok(StartMacro::Found {
                command,
                section: section.to_string(),
                configured: true,
            }),
            None => Err(Error::MissingSection {
                section: format!("gcode_macro {command}"),
                expected: format!(
                    "ab.start_macro names it as the macro your slicer calls{}",
                    if common.is_empty() {
                        String::new()
                    } else {
                        format!("; the config defines {}", common.join(" and "))
                    }
                ),
            }),
        };
    }
    Ok(match common.as_slice() {
        [] => StartMacro::NotFound,
        [one] => StartMacro::Found {
            command: one.clone(),
            section: lookup(one).unwrap_or_default().to_string(),
            configured: false,
        },
        _ => StartMacro::Ambiguous(common),
    })
}

#[cfg(test)]
mod tests {
    use super::super::files::MemFiles;
    use super::*;
    use std::path::Path;

    fn load(text: &str) -> Config {
        Config::load(&MemFiles::new().with("/p.cfg", text), Path::new("/p.cfg")).unwrap()
    }

    #[test]
    fn start_print_is_found_as_well_as_print_start() {
        let cfg = load("[gcode_macro start_print]\ngcode:\n  G28\n[gcode_macro PARK]\ngcode:\n");
        assert_eq!(
            find_start_macro(&cfg, None).unwrap(),
            StartMacro::Found {
                command: "START_PRINT".into(),
                section: "gcode_macro start_print".into(),
                configured: false
            }
        );
        let cfg = load("[gcode_macro PRINT_START]\ngcode:\n  G28\n");
        assert!(matches!(
            find_start_macro(&cfg, Some("")).unwrap(),
            StartMacro::Found { ref command, .. } if command == "PRINT_START"
        ));
    }

    #[test]
    fn the_configured_name_wins_and_must_exist() {
        let text = "[gcode_macro PRINT_START]\ngcode:\n[gcode_macro My_Start]\ngcode:\n";
        let cfg = load(text);
        assert_eq!(
            find_start_macro(&cfg, Some("MY_START")).unwrap(),
            StartMacro::Found {
                command: "MY_START".into(),
                section: "gcode_macro My_Start".into(),
                configured: true
            }
        );
        let err = find_start_macro(&cfg, Some("START_PRINT")).unwrap_err();
        let msg = err.to_string();
        assert!(msg.contains("[gcode_macro START_PRINT]"), "{msg}");
        assert!(msg.contains("the config defines PRINT_START"), "{msg}");
        assert!(matches!(
            find_start_macro(&cfg, Some("START PRINT")),
            Err(Error::BadName { .. })
        ));
    }

    #[test]
    fn both_common_names_or_none_mean_ask() {
        let both = load("[gcode_macro START_PRINT]\ngcode:\n[gcode_macro PRINT_START]\ngcode:\n");
        assert_eq!(
            find_start_macro(&both, None).unwrap(),
            StartMacro::Ambiguous(vec!["PRINT_START".into(), "START_PRINT".into()])
        );
        let none = load("[gcode_macro PRINT_STARTX]\ngcode:\n[printer]\nkinematics: corexy\n");
        assert_eq!(find_start_macro(&none, None).unwrap(), StartMacro::NotFound);
    }

    #[test]
    fn moonraker_section_names_work_the_same() {
        let names = ["printer", "gcode_macro start_print", "stepper_x"];
        assert!(matches!(
            find_start_macro_in(names, None).unwrap(),
            StartMacro::Found { ref command, .. } if command == "START_PRINT"
        ));
    }
}
