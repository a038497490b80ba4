//! Moonraker's and Klipper's answers that the jobs read, typed at the client: each is parsed
//! once, where it arrives, and a malformed one is an [`Error::Protocol`] naming what was wrong
//! (never a panic, never a silent default). A field Klipper may leave out has its default
//! (`#[serde(default)]`, Klipper's own default where it has one); fields klipcal does not read
//! are ignored.

use std::collections::BTreeMap;

use serde::de::DeserializeOwned;
use serde::Deserialize;
use serde_json::{Map, Value};

use super::Error;

/// Klipper's `configfile` object.
#[derive(Debug, Clone, Default)]
pub struct ConfigFile {
    /// `config`: every option as written in the files, section → option → text.
    pub config: crate::klipper::RawConfig,
    /// `settings`: the options Klipper runs with, parsed and with its defaults.
    pub settings: Settings,
}

/// The parts of `configfile.settings` that klipcal reads.
#[derive(Debug, Clone, Default)]
pub struct Settings {
    /// `[printer]`.
    pub printer: PrinterSettings,
    /// `[heater_bed]`, when the printer has one.
    pub heater_bed: Option<HeaterSettings>,
    /// Chamber or enclosure thermometers, as Klipper names their objects
    /// (`temperature_sensor chamber`, `temperature_fan chamber`, …): every
    /// `[temperature_sensor …]` and `[temperature_fan …]` whose name says chamber or enclosure,
    /// the plainest name first (see [`chamber_sensors`]).
    pub chamber_sensors: Vec<String>,
    /// `[idle_timeout]` (Klipper always loads it; absent only in an odd answer).
    pub idle_timeout: Option<IdleTimeoutSettings>,
    /// `[bed_mesh]`.
    pub bed_mesh: Option<BedMeshSettings>,
    /// `[dual_carriage]`.
    pub dual_carriage: Option<DualCarriageSettings>,
    /// The probe: the first section named like a probe (`[probe]`, `[bltouch]`,
    /// `[smart_effector]`, `[probe_eddy_current …]`, `[… probe]`) that has a `z_offset`.
    pub probe: Option<ProbeSettings>,
    /// `[stepper_*]` sections by name.
    pub steppers: BTreeMap<String, StepperSettings>,
    /// PR 7157's `[backlash]`: its numeric options (mm), by option name.
    pub backlash: Option<BTreeMap<String, f64>>,
    /// Every section as Klipper sent it, for the config editor's check of the values it wrote
    /// (it reads the sections and options the user's edit names).
    sections: BTreeMap<String, Map<String, Value>>,
}

/// `[printer]`.
#[derive(Debug, Clone, Default, Deserialize)]
#[serde(default)]
pub struct PrinterSettings {
    /// `kinematics` (`cartesian`, `corexy`, …).
    pub kinematics: String,
    /// `max_accel`, mm/s².
    pub max_accel: Option<f64>,
}

/// A heater's section.
#[derive(Debug, Clone, Default, Deserialize)]
#[serde(default)]
pub struct HeaterSettings {
    /// `max_power`, 0–1.
    pub max_power: Option<f64>,
    /// `control`: `pid`, `watermark`, or Kalico's `mpc`, `pid_v`, `dual_loop_pid`.
    #[serde(deserialize_with = "heater_control")]
    pub control: Option<HeaterControl>,
    /// Kalico's MPC: `heater_power`, W.
    pub heater_power: Option<f64>,
    /// Kalico's MPC: `block_heat_capacity`, J/K (after MPC_CALIBRATE).
    pub block_heat_capacity: Option<f64>,
    /// Kalico's MPC: `ambient_transfer`, W/K (after MPC_CALIBRATE).
    pub ambient_transfer: Option<f64>,
    /// Kalico's MPC: `sensor_responsiveness`, K/s/K (after MPC_CALIBRATE).
    pub sensor_responsiveness: Option<f64>,
}

/// A heater's `control`.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum HeaterControl {
    /// Klipper's `pid` (and Kalico's `pid_v`, `dual_loop_pid`).
    Pid,
    /// `watermark` (bang-bang).
    Watermark,
    /// Kalico's model-predictive control: after the band its power dips below its final value
    /// and keeps a limit cycle.
    Mpc,
    /// Anything else, as written.
    Other(String),
}

fn heater_control<'de, D: serde::Deserializer<'de>>(
    d: D,
) -> Result<Option<HeaterControl>, D::Error> {
    let v: Option<String> = Option::deserialize(d)?;
    Ok(v.map(|c| match c.trim().to_lowercase().as_str() {
        "pid" | "pid_v" | "dual_loop_pid" => HeaterControl::Pid,
        "watermark" => HeaterControl::Watermark,
        "mpc" => HeaterControl::Mpc,
        other => HeaterControl::Other(other.to_string()),
    }))
}

/// `[idle_timeout]`.
#[derive(Debug, Clone, Default, Deserialize)]
#[serde(default)]
pub struct IdleTimeoutSettings {
    /// `timeout`, s.
    pub timeout: Option<f64>,
}

/// `[bed_mesh]`.
#[derive(Debug, Clone, Deserialize)]
#[serde(default)]
pub struct BedMeshSettings {
    /// `fade_start`, mm (Klipper's default 1).
    pub fade_start: f64,
    /// `fade_end`, mm (Klipper's default 0: no fade).
    pub fade_end: f64,
}

impl Default for BedMeshSettings {
    fn default() -> Self {
        Self {
            fade_start: 1.0,
            fade_end: 0.0,
        }
    }
}

/// `[dual_carriage]`.
#[derive(Debug, Clone, Default, Deserialize)]
#[serde(default)]
pub struct DualCarriageSettings {
    /// `axis` as written (`x` or `y`).
    pub axis: Option<String>,
    /// `position_endstop`, mm.
    pub position_endstop: Option<f64>,
}

impl DualCarriageSettings {
    /// The axis with two carriages, lower case (`x` when not said).
    #[must_use]
    pub(crate) fn axis(&self) -> String {
        self.axis.as_deref().unwrap_or("x").to_ascii_lowercase()
    }
}

/// A probe's offsets, mm (0 where not set).
#[derive(Debug, Clone, Default, Deserialize, PartialEq)]
#[serde(default)]
pub struct ProbeSettings {
    /// `x_offset`.
    pub x_offset: f64,
    /// `y_offset`.
    pub y_offset: f64,
    /// `z_offset`.
    pub z_offset: f64,
}

/// A `[stepper_*]` section.
#[derive(Debug, Clone, Default, Deserialize)]
#[serde(default)]
pub struct StepperSettings {
    /// `position_endstop`, mm (none with a probe as the Z endstop).
    pub position_endstop: Option<f64>,
}

/// Klipper's `bed_mesh` status object: the fields asked for (the others empty).
#[derive(Debug, Clone, Default, Deserialize)]
#[serde(default)]
pub struct BedMeshStatus {
    /// The mesh loaded now (`""` with none; `None` when not asked for or not reported).
    pub profile_name: Option<String>,
    /// The last probed points, `[row y][column x]`, mm.
    pub probed_matrix: Vec<Vec<f64>>,
    /// Every profile Klipper knows, by name.
    pub profiles: BTreeMap<String, BedMeshProfileStatus>,
}

/// One profile in the `bed_mesh` status (its `points` are not read).
#[derive(Debug, Clone, Deserialize)]
pub struct BedMeshProfileStatus {
    /// Its parameters.
    pub mesh_params: crate::klipper::bed_mesh::MeshParams,
}

impl BedMeshStatus {
    /// Parses Klipper's `bed_mesh` status object.
    ///
    /// # Errors
    /// [`Error::Protocol`] naming what is malformed.
    pub fn parse(v: Value) -> Result<Self, Error> {
        serde_json::from_value(v).map_err(|e| bad("bed_mesh status", e))
    }
}

/// Moonraker's `server.webcams.list` answer (the `result` of `/server/webcams/list`).
#[derive(Debug, Clone, Default, Deserialize)]
pub(crate) struct WebcamList {
    /// Every webcam Moonraker knows (none when the answer has no list).
    #[serde(default)]
    pub webcams: Vec<WebcamEntry>,
}

/// One webcam in Moonraker's list: the fields klipcal reads.
#[derive(Debug, Clone, Deserialize)]
#[serde(default)]
pub(crate) struct WebcamEntry {
    /// Its name.
    #[serde(deserialize_with = "text_or_null")]
    pub name: String,
    /// Moonraker's id for it.
    #[serde(deserialize_with = "text_or_null")]
    pub uid: String,
    /// The streamer (`mjpegstreamer-adaptive`, `iframe`, …).
    #[serde(deserialize_with = "text_or_null")]
    pub service: String,
    /// Shown in the frontends (Moonraker's default: yes).
    pub enabled: bool,
    /// The still picture's URL, maybe relative (`/webcam/?action=snapshot`).
    #[serde(deserialize_with = "text_or_null")]
    pub snapshot_url: String,
    /// The stream's URL (an iframe webcam's page).
    #[serde(deserialize_with = "text_or_null")]
    pub stream_url: String,
}

impl Default for WebcamEntry {
    fn default() -> Self {
        Self {
            name: String::new(),
            uid: String::new(),
            service: String::new(),
            enabled: true,
            snapshot_url: String::new(),
            stream_url: String::new(),
        }
    }
}

/// Text, with `null` as empty (older Moonraker sends `null` for an unset URL).
fn text_or_null<'de, D: serde::Deserializer<'de>>(d: D) -> Result<String, D::Error> {
    Ok(Option::<String>::deserialize(d)?.unwrap_or_default())
}

impl WebcamList {
    /// Parses the `server.webcams.list` answer.
    ///
    /// # Errors
    /// [`Error::Protocol`] naming what is malformed.
    pub(crate) fn parse(v: Value) -> Result<Self, Error> {
        serde_json::from_value(v).map_err(|e| bad_moonraker("webcam list", e))
    }
}

/// Klipper's `heaters` object.
#[derive(Debug, Clone, Default, Deserialize, PartialEq)]
#[serde(default)]
pub(crate) struct HeatersStatus {
    /// Every heater (`extruder`, `heater_bed`, `heater_generic …`).
    pub available_heaters: Vec<String>,
    /// Every temperature sensor, heaters included.
    pub available_sensors: Vec<String>,
}

impl HeatersStatus {
    /// Parses Klipper's `heaters` status object.
    ///
    /// # Errors
    /// [`Error::Protocol`] naming what is malformed.
    pub(crate) fn parse(v: Value) -> Result<Self, Error> {
        serde_json::from_value(v).map_err(|e| bad("heaters object", e))
    }
}

/// A heater's or temperature sensor's status (`heater_bed`, `extruder`,
/// `temperature_sensor …`): the fields asked for, `None` when not asked for or when Klipper has
/// no such object.
#[derive(Debug, Clone, Copy, Default, Deserialize, PartialEq)]
#[serde(default)]
pub(crate) struct HeaterStatus {
    /// Measured, °C.
    pub temperature: Option<f64>,
    /// Target, °C (0: off).
    pub target: Option<f64>,
    /// PWM duty, 0–1.
    pub power: Option<f64>,
}

impl HeaterStatus {
    /// Parses the status object of the heater or sensor `name`.
    ///
    /// # Errors
    /// [`Error::Protocol`] naming the object and what is malformed.
    pub(crate) fn parse(name: &str, v: Value) -> Result<Self, Error> {
        serde_json::from_value(v).map_err(|e| bad(&format!("{name} status"), e))
    }
}

/// The raw answer: sections kept whole until each known one is parsed.
#[derive(Deserialize)]
struct RawConfigFile {
    #[serde(default)]
    config: crate::klipper::RawConfig,
    #[serde(default)]
    settings: BTreeMap<String, Map<String, Value>>,
}

fn is_probe(name: &str) -> bool {
    name == "probe"
        || name == "bltouch"
        || name == "smart_effector"
        || name.starts_with("probe_eddy_current")
        || name.ends_with(" probe")
}

fn bad(what: &str, e: impl std::fmt::Display) -> Error {
    Error::Protocol(format!("Klipper's {what} is not as expected: {e}"))
}

fn bad_moonraker(what: &str, e: impl std::fmt::Display) -> Error {
    Error::Protocol(format!("Moonraker's {what} is not as expected: {e}"))
}

impl ConfigFile {
    /// Parses Klipper's `configfile` status object (`config` and `settings`).
    ///
    /// # Errors
    /// [`Error::Protocol`] naming the part that is malformed: not an object, an option as
    /// written that is not text, or a setting klipcal reads of the wrong type.
    pub(crate) fn parse(v: Value) -> Result<Self, Error> {
        let raw: RawConfigFile =
            serde_json::from_value(v).map_err(|e| bad("configfile object", e))?;
        let sections = raw.settings;
        fn section<T: DeserializeOwned>(
            sections: &BTreeMap<String, Map<String, Value>>,
            name: &str,
        ) -> Result<Option<T>, Error> {
            sections
                .get(name)
                .map(|m| {
                    serde_json::from_value(Value::Object(m.clone()))
                        .map_err(|e| bad(&format!("configfile.settings [{name}]"), e))
                })
                .transpose()
        }
        let probe = match sections
            .iter()
            .find(|(k, v)| is_probe(k) && v.contains_key("z_offset"))
        {
            Some((name, _)) => section(&sections, name)?,
            None => None,
        };
        let mut steppers = BTreeMap::new();
        for name in sections.keys().filter(|k| k.starts_with("stepper_")) {
            if let Some(s) = section(&sections, name)? {
                steppers.insert(name.clone(), s);
            }
        }
        let backlash = sections.get("backlash").map(|o| {
            o.iter()
                .filter_map(|(k, v)| v.as_f64().map(|f| (k.clone(), f)))
                .collect()
        });
        let settings = Settings {
            printer: section(&sections, "printer")?.unwrap_or_default(),
            heater_bed: section(&sections, "heater_bed")?,
            chamber_sensors: chamber_sensors(sections.keys()),
            idle_timeout: section(&sections, "idle_timeout")?,
            bed_mesh: section(&sections, "bed_mesh")?,
            dual_carriage: section(&sections, "dual_carriage")?,
            probe,
            steppers,
            backlash,
            sections,
        };
        Ok(Self {
            config: raw.config,
            settings,
        })
    }
}

/// The chamber or enclosure thermometers among the config's sections: `temperature_sensor …`
/// and `temperature_fan …` whose name holds `chamber` or `enclosure` (either case); the
/// shortest name first (`temperature_sensor chamber` before `temperature_sensor chamber_top`),
/// a sensor before a fan.
#[must_use]
pub fn chamber_sensors<'a>(sections: impl Iterator<Item = &'a String>) -> Vec<String> {
    let mut v: Vec<(usize, usize, String)> = sections
        .filter_map(|k| {
            let lower = k.to_lowercase();
            let (kind, name) = lower.split_once(char::is_whitespace)?;
            let rank = match kind {
                "temperature_sensor" => 0,
                "temperature_fan" => 1,
                _ => return None,
            };
            let name = name.trim();
            (name.contains("chamber") || name.contains("enclosure"))
                .then(|| (name.len(), rank, format!("{kind} {name}")))
        })
        .collect();
    v.sort();
    v.into_iter().map(|x| x.2).collect()
}

impl Settings {
    /// A setting as Klipper runs it, by section and option (either case), for checking a value
    /// klipcal wrote into the config.
    #[must_use]
    pub fn option(&self, section: &str, option: &str) -> Option<&Value> {
        self.section(section)?.get(&option.to_lowercase())
    }

    /// A whole section as Klipper runs it (either case), for messages and tests.
    #[must_use]
    pub fn section(&self, section: &str) -> Option<&Map<String, Value>> {
        self.sections.get(&section.to_lowercase())
    }

    /// The axis `[dual_carriage]` moves, lower case (`x` when not said or without one).
    #[must_use]
    pub(crate) fn dual_carriage_axis(&self) -> String {
        self.dual_carriage
            .as_ref()
            .map_or_else(|| "x".into(), DualCarriageSettings::axis)
    }

    /// `position_endstop` of a stepper section or of `[dual_carriage]`.
    #[must_use]
    pub(crate) fn position_endstop(&self, section: &str) -> Option<f64> {
        if section == "dual_carriage" {
            self.dual_carriage.as_ref()?.position_endstop
        } else {
            self.steppers.get(section)?.position_endstop
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use serde_json::json;

    fn fixture(name: &str) -> Value {
        let path = format!(
            "{}/tests/fixtures/moonraker/{name}",
            env!("CARGO_MANIFEST_DIR")
        );
        let text = std::fs::read_to_string(&path).unwrap_or_else(|e| panic!("{path}: {e}"));
        serde_json::from_str(&text).unwrap()
    }

    /// Issue 38: `control: mpc` in `[heater_bed]` (Kalico) and its MPC parameters, and a
    /// chamber thermometer, are facts read from Klipper's configfile.
    #[test]
    fn an_mpc_bed_and_a_chamber_sensor_are_read_from_the_configfile() {
        let v = json!({
            "config": {},
            "settings": {
                "heater_bed": {"control": "mpc", "heater_power": 400.0, "max_power": 1.0,
                    "block_heat_capacity": 1234.5, "ambient_transfer": 1.43,
                    "sensor_responsiveness": 0.0228},
                "temperature_fan chamber_fan": {"sensor_type": "Generic 3950"},
                "temperature_sensor chamber": {"sensor_type": "Generic 3950"},
                "temperature_sensor raspberry_pi": {"sensor_type": "temperature_host"},
                "temperature_sensor enclosure_top": {"sensor_type": "Generic 3950"},
            }
        });
        let s = ConfigFile::parse(v).unwrap().settings;
        let bed = s.heater_bed.as_ref().unwrap();
        assert_eq!(bed.control, Some(HeaterControl::Mpc));
        assert_eq!(bed.heater_power, Some(400.0));
        assert_eq!(bed.block_heat_capacity, Some(1234.5));
        assert_eq!(bed.sensor_responsiveness, Some(0.0228));
        assert_eq!(
            s.chamber_sensors,
            [
                "temperature_sensor chamber",
                "temperature_fan chamber_fan",
                "temperature_sensor enclosure_top"
            ]
        );
        // Klipper's PID bed (the bench's configfile) and a bed without control said.
        let cf = ConfigFile::parse(fixture("configfile-corexy-pr7157.json")).unwrap();
        assert!(matches!(
            cf.settings.heater_bed.unwrap().control,
            Some(HeaterControl::Pid) | None
        ));
        assert!(cf.settings.chamber_sensors.is_empty());
        // A control that is not text is refused whole, naming the section.
        let bad = json!({"config": {}, "settings": {"heater_bed": {"control": 3}}});
        let e = ConfigFile::parse(bad).unwrap_err().to_string();
        assert!(e.contains("[heater_bed]"), "{e}");
    }

    #[test]
    fn the_bench_configfile_parses_into_the_settings_jobs_read() {
        let cf = ConfigFile::parse(fixture("configfile-corexy-pr7157.json")).unwrap();
        let s = &cf.settings;
        assert_eq!(s.printer.kinematics, "corexy");
        assert_eq!(s.printer.max_accel, Some(3000.0));
        assert_eq!(s.heater_bed.as_ref().unwrap().max_power, Some(1.0));
        assert_eq!(s.idle_timeout.as_ref().unwrap().timeout, Some(3600.0));
        let bm = s.bed_mesh.as_ref().unwrap();
        assert_eq!((bm.fade_start, bm.fade_end), (1.0, 0.0));
        assert!(s.dual_carriage.is_none());
        assert!(s.probe.is_none(), "the plain bench has no probe");
        assert_eq!(s.position_endstop("stepper_x"), Some(0.0));
        assert_eq!(s.position_endstop("dual_carriage"), None);
        let backlash = s.backlash.as_ref().unwrap();
        assert_eq!(
            backlash,
            &BTreeMap::from([("a".into(), 0.0), ("b".into(), 0.0), ("z".into(), 0.0)]),
            "the numbers of [backlash], its kinematics left out"
        );
        assert_eq!(
            s.option("STEPPER_X", "Rotation_Distance"),
            Some(&json!(40.0))
        );
        assert_eq!(s.option("stepper_x", "no_such"), None);
        assert_eq!(cf.config["stepper_x"]["rotation_distance"], "40");
        assert_eq!(cf.config["backlash"]["kinematics"], "corexy");
    }

    #[test]
    fn the_probe_is_found_by_its_section_name_and_z_offset() {
        let cf = ConfigFile::parse(fixture("configfile-mesh-probe.json")).unwrap();
        assert_eq!(
            cf.settings.probe,
            Some(ProbeSettings {
                x_offset: 0.0,
                y_offset: 0.0,
                z_offset: 1.0
            }),
            "[klipcal_bench probe] of the mesh bench"
        );
        let cf = ConfigFile::parse(json!({"settings": {
            "bltouch": {"x_offset": -40.5, "y_offset": 12, "z_offset": 2.1},
            "probe_unrelated": {"z_offset": 9},
        }}))
        .unwrap();
        assert_eq!(
            cf.settings.probe,
            Some(ProbeSettings {
                x_offset: -40.5,
                y_offset: 12.0,
                z_offset: 2.1
            })
        );
    }

    #[test]
    fn options_klipper_leaves_out_take_their_defaults() {
        let cf =
            ConfigFile::parse(json!({"settings": {"bed_mesh": {}, "dual_carriage": {}}})).unwrap();
        let s = &cf.settings;
        assert_eq!(s.printer.kinematics, "");
        assert_eq!(s.printer.max_accel, None);
        let bm = s.bed_mesh.as_ref().unwrap();
        assert_eq!((bm.fade_start, bm.fade_end), (1.0, 0.0));
        assert_eq!(s.dual_carriage.as_ref().unwrap().axis(), "x");
        assert!(s.heater_bed.is_none() && s.backlash.is_none() && s.probe.is_none());
        assert!(cf.config.is_empty());
        // An empty answer (Klipper not ready) is empty settings, not an error.
        assert!(ConfigFile::parse(json!({})).is_ok());
    }

    #[test]
    fn the_bench_bed_mesh_status_parses_with_its_profiles() {
        let bm = BedMeshStatus::parse(fixture("bed_mesh-status.json")).unwrap();
        assert_eq!(bm.profile_name.as_deref(), Some(""), "no mesh loaded");
        assert_eq!(
            bm.probed_matrix,
            vec![Vec::<f64>::new()],
            "nothing probed yet: [[]]"
        );
        assert_eq!(bm.profiles.keys().collect::<Vec<_>>(), ["default", "hot"]);
        let hot = &bm.profiles["hot"];
        assert_eq!((hot.mesh_params.x_count, hot.mesh_params.y_count), (3, 3));
        assert_eq!(hot.mesh_params.max_x, 280.0);
        // Only the fields asked for: the others are empty, not an error.
        let bm = BedMeshStatus::parse(json!({"profile_name": "hot"})).unwrap();
        assert_eq!(bm.profile_name.as_deref(), Some("hot"));
        assert!(bm.profiles.is_empty() && bm.probed_matrix.is_empty());
        assert_eq!(BedMeshStatus::parse(json!({})).unwrap().profile_name, None);
        for bad in [
            json!({"probed_matrix": [[0.1, "x"]]}),
            json!({"profiles": {"p": {"points": []}}}),
            json!({"profiles": {"p": {"mesh_params": {"x_count": "3"}}}}),
            json!({"profile_name": 3}),
        ] {
            let e = BedMeshStatus::parse(bad.clone()).unwrap_err().to_string();
            assert!(e.contains("bed_mesh status"), "{bad}: {e}");
        }
    }

    #[test]
    fn a_malformed_answer_is_an_error_naming_what_was_wrong() {
        let cases = [
            (json!(null), "configfile object"),
            (json!([1, 2]), "configfile object"),
            (
                json!({"settings": {"printer": {"max_accel": "fast"}}}),
                "[printer]",
            ),
            (
                json!({"settings": {"bed_mesh": {"fade_end": "10"}}}),
                "[bed_mesh]",
            ),
            (json!({"settings": {"printer": 3}}), "configfile object"),
            (
                json!({"config": {"printer": {"max_accel": 3000}}}),
                "configfile object",
            ),
            (
                json!({"settings": {"stepper_x": {"position_endstop": [0]}}}),
                "[stepper_x]",
            ),
        ];
        for (answer, named) in cases {
            let e = ConfigFile::parse(answer.clone()).unwrap_err();
            assert!(matches!(e, Error::Protocol(_)), "{answer}: {e}");
            let text = e.to_string();
            assert!(text.contains(named), "{answer}: {text}");
        }
    }

    #[test]
    fn the_bench_webcam_list_parses_and_a_malformed_one_is_refused_by_name() {
        let list = WebcamList::parse(fixture("webcams-list.json")["result"].clone()).unwrap();
        assert_eq!(list.webcams.len(), 1);
        let cam = &list.webcams[0];
        assert_eq!(
            (cam.name.as_str(), cam.service.as_str(), cam.enabled),
            ("nozzle", "mjpegstreamer-adaptive", true)
        );
        assert_eq!(cam.snapshot_url, "http://127.0.0.1:54299/?action=snapshot");
        assert_eq!(cam.uid, "fb09faf6-ade1-56e8-b58d-4c20f3eb5258");
        // Fields left out: enabled (Moonraker's default), URLs empty; null URLs are empty.
        let list =
            WebcamList::parse(json!({"webcams": [{"name": "n", "snapshot_url": null}]})).unwrap();
        assert!(list.webcams[0].enabled && list.webcams[0].snapshot_url.is_empty());
        assert!(WebcamList::parse(json!({})).unwrap().webcams.is_empty());
        for bad in [
            json!({"webcams": {"name": "n"}}),
            json!({"webcams": [{"name": 3}]}),
            json!({"webcams": [{"enabled": "yes"}]}),
            json!(null),
            json!("webcams"),
        ] {
            let e = WebcamList::parse(bad.clone()).unwrap_err();
            assert!(matches!(e, Error::Protocol(_)), "{bad}: {e}");
            assert!(e.to_string().contains("webcam list"), "{bad}: {e}");
        }
    }

    #[test]
    fn the_bench_heaters_parse_and_a_malformed_one_is_refused_by_name() {
        let h = HeatersStatus::parse(fixture("heaters-status.json")).unwrap();
        assert_eq!(h.available_heaters, ["heater_bed", "extruder"]);
        assert_eq!(
            h.available_sensors,
            ["heater_bed", "temperature_sensor frame", "extruder"]
        );
        let objs = fixture("heater-objects-status.json");
        let bed = HeaterStatus::parse("heater_bed", objs["heater_bed"].clone()).unwrap();
        assert_eq!(
            bed,
            HeaterStatus {
                temperature: Some(21.99),
                target: Some(0.0),
                power: Some(0.0)
            }
        );
        let ex = HeaterStatus::parse("extruder", objs["extruder"].clone()).unwrap();
        assert_eq!(ex.temperature, Some(21.99));
        let frame = HeaterStatus::parse(
            "temperature_sensor frame",
            objs["temperature_sensor frame"].clone(),
        )
        .unwrap();
        assert_eq!((frame.temperature, frame.target), (Some(25.0), None));
        let hot = HeaterStatus::parse("heater_bed", fixture("heater_bed-heating.json")).unwrap();
        assert_eq!(hot.target, Some(60.0));
        assert!(hot.power.unwrap() > 0.0 && hot.temperature.unwrap() > 59.0);
        // An object Klipper does not have (no heated bed) is all None, not an error.
        assert_eq!(
            HeaterStatus::parse("heater_bed", json!({})).unwrap(),
            HeaterStatus::default()
        );
        for (name, bad) in [
            ("heater_bed", json!({"target": "60"})),
            ("heater_bed", json!(null)),
            ("extruder", json!({"temperature": [21.0]})),
        ] {
            let e = HeaterStatus::parse(name, bad.clone()).unwrap_err();
            assert!(matches!(e, Error::Protocol(_)), "{bad}: {e}");
            assert!(
                e.to_string().contains(&format!("{name} status")),
                "{bad}: {e}"
            );
        }
        for bad in [
            json!({"available_heaters": "heater_bed"}),
            json!({"available_sensors": [1]}),
        ] {
            let e = HeatersStatus::parse(bad.clone()).unwrap_err();
            assert!(e.to_string().contains("heaters object"), "{bad}: {e}");
        }
    }
}

/// `printer.info`: Klipper's state and where its config is.
#[derive(Debug, Clone, Default, Deserialize, PartialEq, Eq)]
#[serde(default)]
pub struct PrinterInfo {
    /// `ready`, `startup`, `error`, `shutdown`.
    #[serde(deserialize_with = "text_or_null")]
    pub state: String,
    /// Klipper's words about its state.
    #[serde(deserialize_with = "text_or_null")]
    pub state_message: String,
    /// Klipper's version.
    #[serde(deserialize_with = "text_or_null")]
    pub software_version: String,
    /// The main config file, as Klipper read it.
    pub config_file: Option<String>,
    /// `Klipper`, or Kalico's name.
    pub app: Option<String>,
}

impl PrinterInfo {
    /// Parses the `printer.info` answer.
    ///
    /// # Errors
    /// [`Error::Protocol`] naming what is malformed.
    pub(crate) fn parse(v: Value) -> Result<Self, Error> {
        serde_json::from_value(v).map_err(|e| bad("printer.info answer", e))
    }

    /// Whether Klipper is ready.
    #[must_use]
    pub fn ready(&self) -> bool {
        self.state == "ready"
    }
}

/// `server.info`: Moonraker's version and what it knows of Klipper.
#[derive(Debug, Clone, Default, Deserialize, PartialEq, Eq)]
#[serde(default)]
pub struct ServerInfo {
    /// Klipper's state as Moonraker sees it.
    pub klippy_state: Option<String>,
    /// Moonraker's version.
    #[serde(deserialize_with = "text_or_null")]
    pub moonraker_version: String,
}

impl ServerInfo {
    /// Parses the `server.info` answer.
    ///
    /// # Errors
    /// [`Error::Protocol`] naming what is malformed.
    pub(crate) fn parse(v: Value) -> Result<Self, Error> {
        serde_json::from_value(v).map_err(|e| bad_moonraker("server.info answer", e))
    }
}

/// One of Moonraker's file roots (`/server/files/roots`).
#[derive(Debug, Clone, Default, Deserialize, PartialEq, Eq)]
#[serde(default)]
pub struct FileRoot {
    /// `config`, `gcodes`, …
    pub name: String,
    /// Its folder on the host.
    pub path: String,
}

/// One file of a root's listing (`/server/files/list`).
#[derive(Debug, Clone, Default, Deserialize, PartialEq, Eq)]
#[serde(default)]
pub struct ListedFile {
    /// Relative to the root.
    pub path: String,
}

/// Parses a list answer of Moonraker's file API (`what` names it in the error).
///
/// # Errors
/// [`Error::Protocol`] naming what is malformed.
pub(crate) fn parse_list<T: DeserializeOwned>(what: &str, v: Value) -> Result<Vec<T>, Error> {
    serde_json::from_value(v).map_err(|e| bad_moonraker(what, e))
}

/// The objects the printer summary queries (`configfile` settings, `toolhead` limits,
/// `heaters`, `print_stats`), each absent when Klipper has no such object.
#[derive(Debug, Clone, Default, PartialEq)]
pub(crate) struct SummaryObjects {
    /// `configfile`.
    pub configfile: Option<SummaryConfig>,
    /// `toolhead`.
    pub toolhead: Option<ToolheadLimits>,
    /// `heaters`.
    pub heaters: Option<HeatersStatus>,
    /// `print_stats`.
    pub print_stats: Option<PrintStats>,
}

/// `configfile.settings`, the parts the summary shows.
#[derive(Debug, Clone, Default, Deserialize, PartialEq)]
#[serde(default)]
pub(crate) struct SummaryConfig {
    /// The sections.
    pub settings: SummarySettings,
}

/// The sections the summary shows.
#[derive(Debug, Clone, Default, Deserialize, PartialEq)]
#[serde(default)]
pub(crate) struct SummarySettings {
    /// `[printer]`.
    pub printer: Option<SummaryPrinter>,
    /// `[stepper_x]`.
    pub stepper_x: Option<SummaryStepper>,
    /// `[stepper_y]`.
    pub stepper_y: Option<SummaryStepper>,
}

/// `[printer]`'s kinematics.
#[derive(Debug, Clone, Default, Deserialize, PartialEq, Eq)]
#[serde(default)]
pub(crate) struct SummaryPrinter {
    /// `corexy`, `cartesian`, …
    pub kinematics: Option<String>,
}

/// A stepper's settings the summary shows.
#[derive(Debug, Clone, Default, Deserialize, PartialEq)]
#[serde(default)]
pub(crate) struct SummaryStepper {
    /// mm.
    pub rotation_distance: Option<f64>,
    /// Microsteps.
    pub microsteps: Option<u64>,
    /// Full steps per rotation.
    pub full_steps_per_rotation: Option<u64>,
    /// mm.
    pub position_min: Option<f64>,
    /// mm.
    pub position_max: Option<f64>,
}

/// `toolhead`'s limits.
#[derive(Debug, Clone, Default, Deserialize, PartialEq)]
#[serde(default)]
pub(crate) struct ToolheadLimits {
    /// X, Y, Z, E, mm.
    pub axis_minimum: Option<Vec<f64>>,
    /// X, Y, Z, E, mm.
    pub axis_maximum: Option<Vec<f64>>,
}

/// `print_stats`' state.
#[derive(Debug, Clone, Default, Deserialize, PartialEq, Eq)]
#[serde(default)]
pub(crate) struct PrintStats {
    /// `standby`, `printing`, `paused`, `complete`, …
    pub state: Option<String>,
}

impl SummaryObjects {
    /// Parses the summary's objects query, each object on its own.
    ///
    /// # Errors
    /// [`Error::Protocol`] naming the object and what is malformed.
    pub(crate) fn parse(st: &Map<String, Value>) -> Result<Self, Error> {
        fn object<T: DeserializeOwned>(
            st: &Map<String, Value>,
            name: &str,
        ) -> Result<Option<T>, Error> {
            st.get(name)
                .map(|v| {
                    serde_json::from_value(v.clone()).map_err(|e| bad(&format!("{name} object"), e))
                })
                .transpose()
        }
        Ok(Self {
            configfile: object(st, "configfile")?,
            toolhead: object(st, "toolhead")?,
            heaters: st
                .get("heaters")
                .cloned()
                .map(HeatersStatus::parse)
                .transpose()?,
            print_stats: object(st, "print_stats")?,
        })
    }
}
