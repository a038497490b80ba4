//! [`PrinterFacts`]: the few Klipper settings klipcal needs (kinematics, X/Y stepper geometry,
//! nozzle, which helper sections exist), validated as klippy does. One code path serves a parsed
//! [`Config`] and Moonraker's `configfile.config` JSON. PURE: no I/O.

#[cfg(test)]
use serde_json::Value;

use super::config::Config;
use super::Error;

/// The printer's kinematics (`[printer] kinematics`).
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Kinematics {
    /// `corexy`: X and Y motors are the A and B belts.
    CoreXy,
    /// `cartesian`.
    Cartesian,
    /// Anything else, as written (`delta`, `hybrid_corexy`, …).
    Other(String),
}

/// Geometry of one stepper section (`[stepper_x]`, `[stepper_y]`), with Klipper's defaults.
#[derive(Debug, Clone, PartialEq)]
pub struct Stepper {
    /// `rotation_distance` (mm of travel per motor rotation, > 0).
    pub rotation_distance_mm: f64,
    /// `microsteps` (≥ 1).
    pub microsteps: u32,
    /// `full_steps_per_rotation` (default 200, a multiple of 4).
    pub full_steps_per_rotation: u32,
    /// The product of the `gear_ratio` pairs (`80:20, 2:1` → 8.0), default 1.0.
    pub gear_ratio: f64,
    /// `position_min` (default 0).
    pub position_min_mm: f64,
    /// `position_max` (required, above `position_min`).
    pub position_max_mm: f64,
}

impl Stepper {
    /// Microsteps per mm of travel: full steps × microsteps × gear ratio / rotation distance.
    #[cfg(test)]
    pub fn steps_per_mm(&self) -> f64 {
        f64::from(self.full_steps_per_rotation) * f64::from(self.microsteps) * self.gear_ratio
            / self.rotation_distance_mm
    }
}

/// What klipcal needs to know about a printer's Klipper config.
#[derive(Debug, Clone, PartialEq)]
pub struct PrinterFacts {
    /// `[printer] kinematics`.
    pub kinematics: Kinematics,
    /// `[stepper_x]`.
    pub stepper_x: Stepper,
    /// `[stepper_y]`.
    pub stepper_y: Stepper,
    /// `[extruder] nozzle_diameter`, when there is an extruder.
    pub nozzle_diameter_mm: Option<f64>,
    /// `[extruder] filament_diameter`, when there is an extruder.
    pub filament_diameter_mm: Option<f64>,
    /// A `[gcode_macro PRINT_START]` exists (macro name case-insensitive).
    pub has_print_start: bool,
    /// `[skew_correction]` exists.
    pub has_skew_correction: bool,
    /// `[bed_mesh]` exists.
    pub has_bed_mesh: bool,
    /// `[exclude_object]` exists in the config text (Kalico loads it without one: whether
    /// Klipper runs it is `printer::Features::running`).
    pub has_exclude_object: bool,
    /// `[respond]` exists in the config text (as for `has_exclude_object`).
    pub has_respond: bool,
    /// `[virtual_sdcard]` exists (uploaded G-code files can be printed).
    pub has_virtual_sdcard: bool,
    /// `[pause_resume]` exists.
    pub has_pause_resume: bool,
    /// `[backlash_compensation]` exists.
    pub has_backlash_compensation: bool,
    /// `[heater_bed]` exists.
    pub has_heater_bed: bool,
}

impl PrinterFacts {
    /// Facts from a loaded config (effective values, SAVE_CONFIG merged).
    ///
    /// # Errors
    /// [`Error::MissingSection`], [`Error::MissingOption`] or [`Error::BadValue`] naming the
    /// section, option, value and what is expected.
    pub fn from_config(config: &Config) -> Result<PrinterFacts, Error> {
        facts_from(&ConfigSource(config))
    }

    /// Facts from Moonraker's `configfile.config` status object (section → option → raw string,
    /// as Klipper reports it). The whole `configfile` status object (with a `config` key) is
    /// accepted too. JSON numbers and booleans are taken as their text.
    ///
    /// # Errors
    /// [`Error::Settings`] when the JSON is not an object of objects; otherwise as
    /// [`PrinterFacts::from_config`].
    #[cfg(test)]
    pub fn from_settings(settings: &Value) -> Result<PrinterFacts, Error> {
        let obj = settings.as_object().ok_or_else(|| {
            Error::Settings("expected a JSON object mapping section names to options".into())
        })?;
        let obj = match (obj.get("printer"), obj.get("config")) {
            (None, Some(Value::Object(inner))) => inner,
            _ => obj,
        };
        facts_from(&JsonSource(obj))
    }
}

/// Read access shared by the two inputs.
trait Source {
    fn section_names(&self) -> Vec<String>;
    fn get(&self, section: &str, key: &str) -> Result<Option<String>, Error>;
    fn has_section(&self, section: &str) -> bool {
        self.section_names().iter().any(|s| s == section)
    }
}

struct ConfigSource<'a>(&'a Config);

impl Source for ConfigSource<'_> {
    fn section_names(&self) -> Vec<String> {
        self.0.sections().iter().map(|s| s.name.clone()).collect()
    }
    fn get(&self, section: &str, key: &str) -> Result<Option<String>, Error> {
        Ok(self.0.get(section, key).map(str::to_string))
    }
}

#[cfg(test)]
struct JsonSource<'a>(&'a serde_json::Map<String, Value>);

#[cfg(test)]
impl Source for JsonSource<'_> {
    fn section_names(&self) -> Vec<String> {
        self.0.keys().cloned().collect()
    }
    fn get(&self, section: &str, key: &str) -> Result<Option<String>, Error> {
        let Some(sec) = self.0.get(section) else {
            return Ok(None);
        };
        let sec = sec.as_object().ok_or_else(|| {
            Error::Settings(format!("section '{section}' is not an object of options"))
        })?;
        let key = key.to_lowercase();
        let value = sec.get(&key).or_else(|| {
            sec.iter()
                .find(|(k, _)| k.to_lowercase() == key)
                .map(|(_, v)| v)
        });
        match value {
            None => Ok(None),
            Some(Value::String(s)) => Ok(Some(s.clone())),
            Some(Value::Number(n)) => Ok(Some(n.to_string())),
            Some(Value::Bool(b)) => Ok(Some(if *b { "True" } else { "False" }.to_string())),
            Some(other) => Err(Error::Settings(format!(
                "[{section}] {key} is {other}; expected a string value"
            ))),
        }
    }
}

fn facts_from(src: &dyn Source) -> Result<PrinterFacts, Error> {
    if !src.has_section("printer") {
        return Err(Error::MissingSection {
            section: "printer".into(),
            expected: "every Klipper config has one, with 'kinematics'".into(),
        });
    }
    let kin = required(
        src,
        "printer",
        "kinematics",
        "a kinematics name such as corexy",
    )?;
    let kin_name = kin.trim();
    // Kinematics whose motion has no [stepper_x]/[stepper_y] (klippy/kinematics/*.py).
    if [
        "delta",
        "rotary_delta",
        "deltesian",
        "polar",
        "winch",
        "none",
    ]
    .contains(&kin_name)
    {
        return Err(Error::UnsupportedKinematics {
            kinematics: kin_name.to_string(),
        });
    }
    let kinematics = match kin_name {
        "corexy" => Kinematics::CoreXy,
        "cartesian" => Kinematics::Cartesian,
        other => Kinematics::Other(other.to_string()),
    };
    let stepper_x = stepper(src, "stepper_x")?;
    let stepper_y = stepper(src, "stepper_y")?;
    let (nozzle_diameter_mm, filament_diameter_mm) = if src.has_section("extruder") {
        (
            opt_float_above(src, "extruder", "nozzle_diameter", 0.0)?,
            opt_float_above(src, "extruder", "filament_diameter", 0.0)?,
        )
    } else {
        (None, None)
    };
    let has_print_start = src.section_names().iter().any(|s| {
        let mut words = s.split_whitespace();
        words.next() == Some("gcode_macro")
            && words
                .next()
                .is_some_and(|n| n.eq_ignore_ascii_case("PRINT_START"))
            && words.next().is_none()
    });
    Ok(PrinterFacts {
        kinematics,
        stepper_x,
        stepper_y,
        nozzle_diameter_mm,
        filament_diameter_mm,
        has_print_start,
        has_skew_correction: src.has_section("skew_correction"),
        has_bed_mesh: src.has_section("bed_mesh"),
        has_exclude_object: src.has_section("exclude_object"),
        has_respond: src.has_section("respond"),
        has_virtual_sdcard: src.has_section("virtual_sdcard"),
        has_pause_resume: src.has_section("pause_resume"),
        has_backlash_compensation: src.has_section("backlash_compensation"),
        has_heater_bed: src.has_section("heater_bed"),
    })
}

/// `stepper.parse_step_distance` + `PrinterRail` position limits, for a linear axis.
fn stepper(src: &dyn Source, section: &str) -> Result<Stepper, Error> {
    if !src.has_section(section) {
        return Err(Error::MissingSection {
            section: section.into(),
            expected: "klipcal calibrates the X and Y steppers and needs their settings".into(),
        });
    }
    if src.get(section, "rotation_distance")?.is_none() {
        if let Some(sd) = src.get(section, "step_distance")? {
            return Err(step_distance_error(src, section, &sd)?);
        }
    }
    let rd_text = required(src, section, "rotation_distance", "a number of mm above 0")?;
    let rotation_distance_mm = parse_float(
        section,
        "rotation_distance",
        &rd_text,
        "a number of mm above 0",
    )?;
    if rotation_distance_mm <= 0.0 {
        return Err(bad(
            section,
            "rotation_distance",
            &rd_text,
            "a number of mm above 0",
        ));
    }
    let ms_text = required(src, section, "microsteps", "an integer of at least 1")?;
    let microsteps = parse_uint(section, "microsteps", &ms_text, "an integer of at least 1")?;
    if microsteps < 1 {
        return Err(bad(
            section,
            "microsteps",
            &ms_text,
            "an integer of at least 1",
        ));
    }
    const FULL: &str = "a positive integer multiple of 4 (usually 200 or 400)";
    let full_steps_per_rotation = match src.get(section, "full_steps_per_rotation")? {
        None => 200,
        Some(t) => {
            let v = parse_uint(section, "full_steps_per_rotation", &t, FULL)?;
            if v < 1 || v % 4 != 0 {
                return Err(bad(section, "full_steps_per_rotation", &t, FULL));
            }
            v
        }
    };
    let gear_ratio = match src.get(section, "gear_ratio")? {
        None => 1.0,
        Some(t) => parse_gear_ratio(section, &t)?,
    };
    let position_min_mm = match src.get(section, "position_min")? {
        None => 0.0,
        Some(t) => parse_float(section, "position_min", &t, "a number of mm")?,
    };
    let max_expect = format!("a number of mm above position_min ({position_min_mm})");
    let max_text = required(src, section, "position_max", &max_expect)?;
    let position_max_mm = parse_float(section, "position_max", &max_text, &max_expect)?;
    if position_max_mm <= position_min_mm {
        return Err(bad(section, "position_max", &max_text, &max_expect));
    }
    Ok(Stepper {
        rotation_distance_mm,
        microsteps,
        full_steps_per_rotation,
        gear_ratio,
        position_min_mm,
        position_max_mm,
    })
}

/// The refusal for an old `step_distance` config, with Klipper's conversion worked out when
/// the numbers are there (`rotation_distance = full_steps × microsteps × step_distance`).
fn step_distance_error(src: &dyn Source, section: &str, sd_text: &str) -> Result<Error, Error> {
    let full = src
        .get(section, "full_steps_per_rotation")?
        .and_then(|t| py_int(&t))
        .unwrap_or(200);
    let microsteps = src.get(section, "microsteps")?.and_then(|t| py_int(&t));
    let sd = py_float(sd_text);
    let conversion = match (microsteps, sd) {
        (Some(ms), Some(sd)) => {
            let rd = full as f64 * ms as f64 * sd;
            let rd = format!("{:.6}", rd);
            let rd = rd.trim_end_matches('0').trim_end_matches('.');
            format!(
                "{full} × {ms} × {} = {rd} → rotation_distance: {rd}",
                sd_text.trim()
            )
        }
        _ => format!(
            "{full} × microsteps × {} (add `microsteps:` too: the driver's microstep setting, \
             e.g. 16)",
            sd_text.trim()
        ),
    };
    Ok(Error::StepDistance {
        section: section.to_string(),
        step_distance: sd_text.trim().to_string(),
        conversion,
    })
}

/// `getlists('gear_ratio', seps=(':', ','), count=2, parser=float)`, multiplied out.
pub fn parse_gear_ratio(section: &str, text: &str) -> Result<f64, Error> {
    const EXPECT: &str = "pairs like '80:20, 2:1' (each 'driven:driving', numbers above 0)";
    let mut result = 1.0;
    for pair in text.split(',').map(str::trim).filter(|p| !p.is_empty()) {
        let parts: Vec<&str> = pair.split(':').map(str::trim).collect();
        if parts.len() != 2 {
            return Err(bad(section, "gear_ratio", text, EXPECT));
        }
        let g1 = py_float(parts[0]).ok_or_else(|| bad(section, "gear_ratio", text, EXPECT))?;
        let g2 = py_float(parts[1]).ok_or_else(|| bad(section, "gear_ratio", text, EXPECT))?;
        if g1 <= 0.0 || g2 <= 0.0 {
            return Err(bad(section, "gear_ratio", text, EXPECT));
        }
        result *= g1 / g2;
    }
    Ok(result)
}

fn required(src: &dyn Source, section: &str, key: &str, expected: &str) -> Result<String, Error> {
    src.get(section, key)?.ok_or_else(|| Error::MissingOption {
        section: section.into(),
        key: key.into(),
        expected: expected.into(),
    })
}

fn opt_float_above(
    src: &dyn Source,
    section: &str,
    key: &str,
    above: f64,
) -> Result<Option<f64>, Error> {
    let expected = format!("a number of mm above {above}");
    match src.get(section, key)? {
        None => Ok(None),
        Some(t) => {
            let v = parse_float(section, key, &t, &expected)?;
            if v <= above {
                return Err(bad(section, key, &t, &expected));
            }
            Ok(Some(v))
        }
    }
}

fn bad(section: &str, key: &str, value: &str, expected: &str) -> Error {
    Error::BadValue {
        section: section.into(),
        key: key.into(),
        value: value.into(),
        expected: expected.into(),
    }
}

fn parse_float(section: &str, key: &str, text: &str, expected: &str) -> Result<f64, Error> {
    py_float(text).ok_or_else(|| bad(section, key, text, expected))
}

fn parse_uint(section: &str, key: &str, text: &str, expected: &str) -> Result<u32, Error> {
    py_int(text)
        .and_then(|v| u32::try_from(v).ok())
        .ok_or_else(|| bad(section, key, text, expected))
}

/// Python `float(text)` for finite values (underscores between digits allowed, surrounding
/// whitespace ignored); None for anything else, including inf and nan.
pub fn py_float(text: &str) -> Option<f64> {
    let t = remove_digit_underscores(text.trim())?;
    t.parse::<f64>().ok().filter(|v| v.is_finite())
}

/// Python `int(text)` (base 10, sign, underscores between digits, whitespace ignored).
fn py_int(text: &str) -> Option<i64> {
    let t = remove_digit_underscores(text.trim())?;
    let digits = t.strip_prefix(['+', '-']).unwrap_or(&t);
    if digits.is_empty() || !digits.chars().all(|c| c.is_ascii_digit()) {
        return None;
    }
    t.parse::<i64>().ok()
}

/// Removes `_` that sit between two digits; None when an underscore sits anywhere else.
fn remove_digit_underscores(text: &str) -> Option<String> {
    let chars: Vec<char> = text.chars().collect();
    let mut out = String::with_capacity(text.len());
    for (i, &c) in chars.iter().enumerate() {
        if c == '_' {
            let before = i > 0 && chars[i - 1].is_ascii_digit();
            let after = chars.get(i + 1).is_some_and(char::is_ascii_digit);
            if !(before && after) {
                return None;
            }
        } else {
            out.push(c);
        }
    }
    Some(out)
}

#[cfg(test)]
mod tests {
    use super::super::config::tests::fixture;
    use super::super::files::MemFiles;
    use super::*;
    use serde_json::json;
    use std::path::Path;

    fn load(text: &str) -> Config {
        Config::load(&MemFiles::new().with("/p.cfg", text), Path::new("/p.cfg")).unwrap()
    }

    const MINIMAL: &str = "[printer]\nkinematics: corexy\n\
        [stepper_x]\nrotation_distance: 40\nmicrosteps: 16\nposition_max: 250\n\
        [stepper_y]\nrotation_distance: 40\nmicrosteps: 16\nposition_max: 250\n";

    #[test]
    fn the_corexy_fixture_gives_its_stepper_geometry_and_features() {
        let f = PrinterFacts::from_config(&fixture()).unwrap();
        assert_eq!(f.kinematics, Kinematics::CoreXy);
        // steppers.cfg says rotation_distance 40; printer.cfg overrides microsteps to 32
        assert_eq!(f.stepper_x.rotation_distance_mm, 40.0);
        assert_eq!(f.stepper_x.microsteps, 32);
        assert_eq!(f.stepper_x.full_steps_per_rotation, 200);
        assert_eq!(f.stepper_x.position_min_mm, -2.0);
        assert_eq!(f.stepper_x.position_max_mm, 250.0);
        assert_eq!(f.stepper_x.steps_per_mm(), 200.0 * 32.0 / 40.0);
        // gear_ratio 80:20, 2:1 multiplies to 8; position_min defaults to 0
        assert_eq!(f.stepper_y.gear_ratio, 8.0);
        assert_eq!(f.stepper_y.position_min_mm, 0.0);
        assert_eq!(f.nozzle_diameter_mm, Some(0.4));
        assert_eq!(f.filament_diameter_mm, Some(1.75));
        assert!(f.has_print_start);
        assert!(f.has_skew_correction && f.has_bed_mesh && f.has_exclude_object);
        assert!(f.has_respond && f.has_virtual_sdcard && f.has_heater_bed);
        assert!(!f.has_pause_resume && !f.has_backlash_compensation);
    }

    #[test]
    fn moonraker_configfile_config_gives_the_same_facts_as_the_parsed_files() {
        let cfg = fixture();
        let mut obj = serde_json::Map::new();
        for s in cfg.sections() {
            let opts: serde_json::Map<String, Value> = s
                .options
                .iter()
                .map(|o| (o.key.clone(), Value::String(o.value.clone())))
                .collect();
            obj.insert(s.name.clone(), Value::Object(opts));
        }
        let from_json = PrinterFacts::from_settings(&Value::Object(obj)).unwrap();
        assert_eq!(from_json, PrinterFacts::from_config(&cfg).unwrap());
    }

    #[test]
    fn a_realistic_moonraker_configfile_status_is_understood() {
        // Shape of `printer.objects.query {configfile: [config]}` → result.status.configfile
        let status = json!({
            "config": {
                "mcu": {"serial": "/dev/serial/by-id/usb-Klipper_stm32f446xx_1234-if00"},
                "printer": {"kinematics": "cartesian", "max_velocity": "300", "max_accel": "3000"},
                "stepper_x": {"step_pin": "PF13", "dir_pin": "PF12", "enable_pin": "!PF14",
                    "microsteps": "16", "rotation_distance": "39.95", "endstop_pin": "^PG6",
                    "position_endstop": "0", "position_max": "235", "homing_speed": "50"},
                "stepper_y": {"step_pin": "PG0", "microsteps": "16", "rotation_distance": "40.02",
                    "full_steps_per_rotation": "400", "position_min": "-5",
                    "position_endstop": "0", "position_max": "235"},
                "extruder": {"nozzle_diameter": "0.600", "filament_diameter": "1.750"},
                "heater_bed": {"heater_pin": "PA1", "sensor_type": "EPCOS 100K B57560G104F"},
                "gcode_macro print_start": {"gcode": "\nG28\nM190 S{params.BED}"},
                "pause_resume": {},
                "bed_mesh default": {"version": "1", "points": "\n0.01, 0.02\n0.03, 0.04"}
            },
            "save_config_pending": false
        });
        let f = PrinterFacts::from_settings(&status).unwrap();
        assert_eq!(f.kinematics, Kinematics::Cartesian);
        assert_eq!(f.stepper_x.rotation_distance_mm, 39.95);
        assert_eq!(f.stepper_y.full_steps_per_rotation, 400);
        assert_eq!(f.stepper_y.position_min_mm, -5.0);
        assert_eq!(f.nozzle_diameter_mm, Some(0.6));
        assert!(f.has_print_start, "macro names are case-insensitive");
        assert!(f.has_pause_resume && f.has_heater_bed);
        assert!(
            !f.has_bed_mesh,
            "a bed_mesh profile is not the [bed_mesh] section"
        );
        assert!(!f.has_respond);
    }

    #[test]
    fn defaults_apply_when_options_are_absent() {
        let f = PrinterFacts::from_config(&load(MINIMAL)).unwrap();
        assert_eq!(f.stepper_x.gear_ratio, 1.0);
        assert_eq!(f.stepper_x.full_steps_per_rotation, 200);
        assert_eq!(f.stepper_x.position_min_mm, 0.0);
        assert_eq!(f.nozzle_diameter_mm, None);
        assert!(!f.has_print_start);
    }

    #[test]
    fn a_non_numeric_rotation_distance_names_section_key_value_and_expectation() {
        let text = MINIMAL.replacen("rotation_distance: 40", "rotation_distance: forty", 1);
        let err = PrinterFacts::from_config(&load(&text)).unwrap_err();
        let msg = err.to_string();
        assert!(matches!(err, Error::BadValue { .. }));
        assert!(
            msg.contains("[stepper_x]") && msg.contains("rotation_distance"),
            "{msg}"
        );
        assert!(msg.contains("'forty'") && msg.contains("above 0"), "{msg}");
    }

    #[test]
    fn values_klipper_rejects_are_rejected() {
        for (from, to) in [
            ("rotation_distance: 40", "rotation_distance: 0"),
            ("microsteps: 16", "microsteps: 0"),
            ("microsteps: 16", "microsteps: 16.0"),
            ("position_max: 250", "position_max: -1"),
            (
                "microsteps: 16",
                "microsteps: 16\nfull_steps_per_rotation: 202",
            ),
            ("microsteps: 16", "microsteps: 16\ngear_ratio: 80:0"),
            ("microsteps: 16", "microsteps: 16\ngear_ratio: 80"),
        ] {
            let text = MINIMAL.replacen(from, to, 1);
            let err = PrinterFacts::from_config(&load(&text));
            assert!(matches!(err, Err(Error::BadValue { .. })), "{to}: {err:?}");
        }
    }

    #[test]
    fn python_number_syntax_is_accepted() {
        let text = MINIMAL.replacen("rotation_distance: 40", "rotation_distance: 4_0.5", 1);
        let f = PrinterFacts::from_config(&load(&text)).unwrap();
        assert_eq!(f.stepper_x.rotation_distance_mm, 40.5);
        assert_eq!(py_float(" 1e1 "), Some(10.0));
        assert_eq!(py_float("inf"), None);
        assert_eq!(py_int("+16"), Some(16));
    }

    #[test]
    fn kinematics_without_x_and_y_steppers_are_refused_by_name() {
        for kin in ["delta", "polar", "winch", "rotary_delta", "deltesian"] {
            let cfg = load(&format!(
                "[printer]\nkinematics: {kin}\n[stepper_a]\nrotation_distance: 40\n"
            ));
            let err = PrinterFacts::from_config(&cfg).unwrap_err();
            assert_eq!(
                err.to_string().split(':').next(),
                Some(format!("kinematics {kin} is not supported").as_str()),
                "{err}"
            );
            let json = json!({"printer": {"kinematics": kin}, "stepper_a": {}});
            let err = PrinterFacts::from_settings(&json).unwrap_err();
            assert!(matches!(err, Error::UnsupportedKinematics { .. }), "{err}");
        }
        // variants that do have [stepper_x]/[stepper_y] are read as before
        let hybrid = MINIMAL.replacen("corexy", "hybrid_corexy", 1);
        let f = PrinterFacts::from_config(&load(&hybrid)).unwrap();
        assert_eq!(f.kinematics, Kinematics::Other("hybrid_corexy".into()));
    }

    #[test]
    fn an_old_step_distance_config_is_told_klippers_conversion() {
        // rotation_distance = full_steps × microsteps × step_distance = 200 × 16 × 0.0125 = 40
        let text = MINIMAL.replacen("rotation_distance: 40", "step_distance: 0.0125", 1);
        let err = PrinterFacts::from_config(&load(&text)).unwrap_err();
        let msg = err.to_string();
        assert!(matches!(err, Error::StepDistance { .. }), "{msg}");
        assert!(
            msg.starts_with("[stepper_x] uses step_distance: 0.0125"),
            "{msg}"
        );
        assert!(
            msg.contains("full_steps_per_rotation × microsteps × step_distance"),
            "{msg}"
        );
        assert!(
            msg.contains("200 × 16 × 0.0125 = 40 → rotation_distance: 40"),
            "{msg}"
        );
        // 400-step motor, no microsteps line (old configs set them in the driver)
        let text = "[printer]\nkinematics: corexy\n[stepper_x]\nstep_distance: 0.00625\n\
                    full_steps_per_rotation: 400\nposition_max: 250\n";
        let msg = PrinterFacts::from_config(&load(text))
            .unwrap_err()
            .to_string();
        assert!(msg.contains("400 × microsteps × 0.00625"), "{msg}");
        assert!(msg.contains("add `microsteps:`"), "{msg}");
    }

    #[test]
    fn missing_stepper_sections_and_options_are_named() {
        let err = PrinterFacts::from_config(&load("[printer]\nkinematics: corexy\n")).unwrap_err();
        assert!(matches!(err, Error::MissingSection { ref section, .. } if section == "stepper_x"));
        let text = MINIMAL.replacen("microsteps: 16\n", "", 1);
        let err = PrinterFacts::from_config(&load(&text)).unwrap_err();
        assert!(matches!(err, Error::MissingOption { ref key, .. } if key == "microsteps"));
    }

    #[test]
    fn malformed_json_is_a_settings_error() {
        assert!(matches!(
            PrinterFacts::from_settings(&json!([1])),
            Err(Error::Settings(_))
        ));
        let bad = json!({"printer": {"kinematics": ["corexy"]}});
        assert!(matches!(
            PrinterFacts::from_settings(&bad),
            Err(Error::Settings(_))
        ));
    }
}
