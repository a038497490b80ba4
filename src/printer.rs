//! The printer summary shown by `check` and returned by `klipcal_status`: what klipcal sees of
//! the printer, built from Moonraker's answers. Building it is pure (`from_answers`); only
//! `gather` talks to Moonraker.

use serde::Serialize;
use serde_json::{json, Map, Value};

use crate::moonraker::answers::{PrinterInfo, ServerInfo, SummaryObjects};
use crate::moonraker::{self, Moonraker};

/// One X/Y stepper as Klipper runs it.
#[derive(Debug, Clone, PartialEq, Serialize, Default)]
pub struct Stepper {
    /// `stepper_x` or `stepper_y`.
    pub name: String,
    /// mm per full rotation.
    pub rotation_distance_mm: Option<f64>,
    /// Microsteps per full step.
    pub microsteps: Option<u64>,
    /// Full steps per rotation.
    pub full_steps_per_rotation: Option<u64>,
    /// Travel limits.
    pub position_min_mm: Option<f64>,
    /// Travel limits.
    pub position_max_mm: Option<f64>,
}

/// Which features klipcal relies on are available.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub(crate) struct Features {
    /// A `PRINT_START` macro.
    pub print_start: bool,
    /// `[skew_correction]` (SET_SKEW).
    pub skew_correction: bool,
    /// `[bed_mesh]`.
    pub bed_mesh: bool,
    /// `[exclude_object]`.
    pub exclude_object: bool,
    /// `[respond]` (RESPOND, needed for console answers to macros).
    pub respond: bool,
    /// `SET_BACKLASH_COMPENSATION`.
    pub set_backlash_compensation: bool,
    /// `[virtual_sdcard]` (needed to print uploaded jobs).
    pub virtual_sdcard: bool,
}

impl Features {
    /// What the running Klipper has loaded, from its objects (`printer.objects.list`) and its
    /// commands (`printer.gcode.help`), not from the config text: Kalico loads `respond` and
    /// `exclude_object` without a section, and its `[exclude_object] enable_exclude_object:
    /// False` (`enable_respond`, `enable_force_move` likewise) keeps the object but registers no
    /// commands, so a feature counts only when its commands are there.
    pub(crate) fn running(objects: &[String], help: &Map<String, Value>) -> Features {
        let has_obj = |n: &str| objects.iter().any(|o| o == n);
        let has_cmd = |n: &str| help.contains_key(n) || help.contains_key(&n.to_lowercase());
        Features {
            print_start: has_cmd("PRINT_START"),
            skew_correction: has_cmd("SET_SKEW"),
            bed_mesh: has_obj("bed_mesh"),
            exclude_object: has_obj("exclude_object") && has_cmd("EXCLUDE_OBJECT_DEFINE"),
            respond: has_cmd("RESPOND"),
            set_backlash_compensation: has_cmd("SET_BACKLASH_COMPENSATION"),
            virtual_sdcard: has_obj("virtual_sdcard"),
        }
    }
}

/// [`Features::running`], asked of Moonraker.
///
/// # Errors
/// Moonraker failures.
pub(crate) async fn running_features(m: &Moonraker) -> Result<Features, moonraker::Error> {
    let objects = m.objects_list().await?;
    let help = match m.call("printer.gcode.help", Value::Null).await? {
        Value::Object(h) => h,
        _ => Map::new(),
    };
    Ok(Features::running(&objects, &help))
}

/// Everything `check` prints.
#[derive(Debug, Clone, PartialEq, Serialize, Default)]
pub(crate) struct Summary {
    /// Moonraker's version.
    pub moonraker_version: String,
    /// Klipper's state: ready, startup, shutdown, error, disconnected.
    pub klippy_state: String,
    /// Klipper's message for its state.
    pub klippy_message: String,
    /// Klipper's version.
    pub klipper_version: String,
    /// `corexy`, `cartesian`, …
    pub kinematics: Option<String>,
    /// stepper_x and stepper_y.
    pub steppers: Vec<Stepper>,
    /// Bed limits from the toolhead: [x_min, y_min] and [x_max, y_max].
    pub axis_min_mm: Option<[f64; 2]>,
    /// See `axis_min_mm`.
    pub axis_max_mm: Option<[f64; 2]>,
    /// Heaters.
    pub heaters: Vec<String>,
    /// Temperature sensors.
    pub sensors: Vec<String>,
    /// Print state (`standby`, `printing`, `paused`, `complete`, …).
    pub print_state: Option<String>,
    /// Features.
    pub features: Option<Features>,
}

/// The objects `gather` queries.
pub(crate) fn query_objects() -> Value {
    json!({
        "configfile": ["settings"],
        "toolhead": ["axis_minimum", "axis_maximum"],
        "heaters": null,
        "print_stats": ["state"],
    })
}

fn xy(v: &[f64]) -> Option<[f64; 2]> {
    Some([*v.first()?, *v.get(1)?])
}

impl Summary {
    /// Builds the summary from `server.info`, `printer.info`, and — when Klipper is ready —
    /// `printer.objects.list`, `printer.gcode.help` and a query of [`query_objects`].
    ///
    /// # Errors
    /// [`moonraker::Error::Protocol`] when Klipper's `heaters` object is malformed.
    pub(crate) fn from_answers(
        server_info: &ServerInfo,
        printer_info: Option<&PrinterInfo>,
        objects: Option<&[String]>,
        gcode_help: Option<&Map<String, Value>>,
        status: Option<&SummaryObjects>,
    ) -> Result<Self, moonraker::Error> {
        let klippy_state = printer_info
            .map(|p| p.state.clone())
            .or_else(|| server_info.klippy_state.clone())
            .unwrap_or_else(|| "unknown".into());
        let mut out = Summary {
            moonraker_version: server_info.moonraker_version.clone(),
            klippy_state,
            klippy_message: printer_info
                .map(|p| p.state_message.clone())
                .unwrap_or_default(),
            klipper_version: printer_info
                .map(|p| p.software_version.clone())
                .unwrap_or_default(),
            kinematics: None,
            steppers: Vec::new(),
            axis_min_mm: None,
            axis_max_mm: None,
            heaters: Vec::new(),
            sensors: Vec::new(),
            print_state: None,
            features: None,
        };
        if let Some(st) = status {
            let settings = st.configfile.as_ref().map(|c| &c.settings);
            out.kinematics = settings
                .and_then(|s| s.printer.as_ref())
                .and_then(|p| p.kinematics.clone());
            for (name, sec) in settings
                .into_iter()
                .flat_map(|s| [("stepper_x", &s.stepper_x), ("stepper_y", &s.stepper_y)])
            {
                let Some(sec) = sec else { continue };
                out.steppers.push(Stepper {
                    name: name.to_string(),
                    rotation_distance_mm: sec.rotation_distance,
                    microsteps: sec.microsteps,
                    full_steps_per_rotation: sec.full_steps_per_rotation,
                    position_min_mm: sec.position_min,
                    position_max_mm: sec.position_max,
                });
            }
            if let Some(th) = &st.toolhead {
                out.axis_min_mm = th.axis_minimum.as_deref().and_then(xy);
                out.axis_max_mm = th.axis_maximum.as_deref().and_then(xy);
            }
            if let Some(h) = &st.heaters {
                out.heaters.clone_from(&h.available_heaters);
                out.sensors.clone_from(&h.available_sensors);
            }
            out.print_state = st.print_stats.as_ref().and_then(|p| p.state.clone());
        }
        if let (Some(objs), Some(help)) = (objects, gcode_help) {
            out.features = Some(Features::running(objs, help));
        }
        Ok(out)
    }

    /// Why the printer cannot be calibrated now, if it cannot.
    pub(crate) fn problem(&self) -> Option<String> {
        if self.klippy_state != "ready" {
            let msg = self.klippy_message.trim();
            return Some(if msg.is_empty() {
                format!("Klipper is not ready (state: {})", self.klippy_state)
            } else {
                format!("Klipper is not ready (state: {}): {msg}", self.klippy_state)
            });
        }
        None
    }

    /// The summary as readable text, one fact a line.
    pub(crate) fn render(&self) -> String {
        let mut t = String::new();
        let yes = |b: bool| if b { "yes" } else { "no" };
        let opt = |v: Option<f64>| v.map_or("?".to_string(), |x| format!("{x}"));
        t.push_str(&format!("Moonraker       {}\n", self.moonraker_version));
        t.push_str(&format!(
            "Klipper         {} ({})\n",
            if self.klipper_version.is_empty() {
                "?"
            } else {
                &self.klipper_version
            },
            self.klippy_state
        ));
        if let Some(p) = self.problem() {
            t.push_str(&format!("Problem         {p}\n"));
        }
        if let Some(k) = &self.kinematics {
            t.push_str(&format!("Kinematics      {k}\n"));
        }
        for s in &self.steppers {
            t.push_str(&format!(
                "{:<15} rotation_distance {} mm, microsteps {}, full steps {}, travel {}..{} mm\n",
                s.name,
                opt(s.rotation_distance_mm),
                s.microsteps.map_or("?".into(), |v| v.to_string()),
                s.full_steps_per_rotation
                    .map_or("?".into(), |v| v.to_string()),
                opt(s.position_min_mm),
                opt(s.position_max_mm),
            ));
        }
        if let (Some(a), Some(b)) = (self.axis_min_mm, self.axis_max_mm) {
            t.push_str(&format!(
                "Bed limits      X {}..{} mm, Y {}..{} mm\n",
                a[0], b[0], a[1], b[1]
            ));
        }
        if !self.heaters.is_empty() {
            t.push_str(&format!("Heaters         {}\n", self.heaters.join(", ")));
        }
        if !self.sensors.is_empty() {
            t.push_str(&format!("Temp. sensors   {}\n", self.sensors.join(", ")));
        }
        if let Some(p) = &self.print_state {
            t.push_str(&format!("Print state     {p}\n"));
        }
        if let Some(f) = &self.features {
            t.push_str("Features\n");
            let rows = [
                ("PRINT_START macro", f.print_start, ""),
                (
                    "skew_correction",
                    f.skew_correction,
                    "add [skew_correction]",
                ),
                ("bed_mesh", f.bed_mesh, "add [bed_mesh]"),
                ("exclude_object", f.exclude_object, "add [exclude_object]"),
                (
                    "respond",
                    f.respond,
                    "add [respond] (klipcal answers macros with RESPOND)",
                ),
                ("SET_BACKLASH_COMPENSATION", f.set_backlash_compensation, ""),
                (
                    "virtual_sdcard",
                    f.virtual_sdcard,
                    "add [virtual_sdcard] path: ~/printer_data/gcodes",
                ),
            ];
            for (name, ok, hint) in rows {
                let hint = if !ok && !hint.is_empty() {
                    format!("  → {hint}")
                } else {
                    String::new()
                };
                t.push_str(&format!("  {name:<27} {}{hint}\n", yes(ok)));
            }
        }
        t
    }
}

/// Asks Moonraker for everything in the summary.
///
/// # Errors
/// When Moonraker cannot be asked at all, or an answer read is malformed; Klipper not being
/// ready is not an error (the summary says so).
pub(crate) async fn gather(m: &Moonraker) -> Result<Summary, moonraker::Error> {
    let server_info = m.server_info().await?;
    let printer_info = m.printer_info().await.ok();
    let ready = printer_info.as_ref().is_some_and(PrinterInfo::ready);
    if !ready {
        return Summary::from_answers(&server_info, printer_info.as_ref(), None, None, None);
    }
    let objects = m.objects_list().await?;
    let help = match m.call("printer.gcode.help", Value::Null).await? {
        Value::Object(h) => h,
        _ => Map::new(),
    };
    let status = SummaryObjects::parse(&m.objects_query(query_objects()).await?)?;
    Summary::from_answers(
        &server_info,
        printer_info.as_ref(),
        Some(&objects),
        Some(&help),
        Some(&status),
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    type Answers = (
        ServerInfo,
        PrinterInfo,
        Vec<String>,
        Map<String, Value>,
        Map<String, Value>,
    );

    fn answers() -> Answers {
        let server = json!({"moonraker_version": "v0.11.0", "klippy_state": "ready"});
        let printer = json!({"state": "ready", "state_message": "Printer is ready",
                             "software_version": "v0.12.0-276"});
        let objects = vec![
            "bed_mesh".to_string(),
            "exclude_object".into(),
            "toolhead".into(),
        ];
        let help = json!({"SET_SKEW": "", "RESPOND": "", "PRINT_START": "",
                          "EXCLUDE_OBJECT_DEFINE": ""});
        let status = json!({
            "configfile": {"settings": {
                "printer": {"kinematics": "corexy"},
                "stepper_x": {"rotation_distance": 40.0, "microsteps": 16,
                              "full_steps_per_rotation": 200, "position_min": 0.0, "position_max": 300.0},
                "stepper_y": {"rotation_distance": 40.0, "microsteps": 16,
                              "full_steps_per_rotation": 200, "position_min": 0.0, "position_max": 300.0}}},
            "toolhead": {"axis_minimum": [0.0, 0.0, 0.0, 0.0], "axis_maximum": [300.0, 300.0, 250.0, 0.0]},
            "heaters": {"available_heaters": ["heater_bed", "extruder"],
                        "available_sensors": ["heater_bed", "extruder"]},
            "print_stats": {"state": "standby"}
        });
        let Value::Object(help) = help else {
            unreachable!()
        };
        let Value::Object(status) = status else {
            unreachable!()
        };
        (
            ServerInfo::parse(server).unwrap(),
            PrinterInfo::parse(printer).unwrap(),
            objects,
            help,
            status,
        )
    }

    fn typed(status: &Map<String, Value>) -> SummaryObjects {
        SummaryObjects::parse(status).unwrap()
    }

    #[test]
    fn a_ready_corexy_printer_is_summarised_with_its_steppers_and_features() {
        let (server, printer, objects, help, status) = answers();
        let s = Summary::from_answers(
            &server,
            Some(&printer),
            Some(&objects),
            Some(&help),
            Some(&typed(&status)),
        )
        .unwrap();
        assert_eq!(s.kinematics.as_deref(), Some("corexy"));
        assert_eq!(s.steppers.len(), 2);
        assert_eq!(s.steppers[0].rotation_distance_mm, Some(40.0));
        assert_eq!(s.steppers[1].microsteps, Some(16));
        assert_eq!(s.axis_max_mm, Some([300.0, 300.0]));
        let f = s.features.clone().unwrap();
        assert!(f.print_start && f.skew_correction && f.bed_mesh && f.exclude_object && f.respond);
        assert!(!f.set_backlash_compensation && !f.virtual_sdcard);
        assert!(s.problem().is_none());
        let text = s.render();
        assert!(text.contains("rotation_distance 40 mm"), "{text}");
        assert!(
            text.contains("virtual_sdcard              no  → add [virtual_sdcard]"),
            "{text}"
        );
    }

    #[test]
    fn a_feature_counts_when_klipper_runs_it_whatever_the_config_says() {
        let objs = |names: &[&str]| names.iter().map(|s| s.to_string()).collect::<Vec<_>>();
        let help = |cmds: &[&str]| {
            cmds.iter()
                .map(|c| (c.to_string(), Value::String(String::new())))
                .collect::<Map<String, Value>>()
        };
        // Kalico with no [exclude_object]/[respond] sections: loaded by default.
        let f = Features::running(
            &objs(&["exclude_object", "toolhead"]),
            &help(&["RESPOND", "EXCLUDE_OBJECT_DEFINE"]),
        );
        assert!(f.exclude_object && f.respond);
        // Kalico's enable_exclude_object: False keeps the object, not its commands.
        let f = Features::running(&objs(&["exclude_object"]), &help(&[]));
        assert!(!f.exclude_object && !f.respond);
    }

    #[test]
    fn klipper_not_ready_is_a_problem_with_its_message() {
        let (server, _, _, _, _) = answers();
        let printer = PrinterInfo::parse(json!({"state": "error",
            "state_message": "Option 'x' is not valid", "software_version": "v0.12"}))
        .unwrap();
        let s = Summary::from_answers(&server, Some(&printer), None, None, None).unwrap();
        let p = s.problem().unwrap();
        assert!(
            p.contains("error") && p.contains("Option 'x' is not valid"),
            "{p}"
        );
        assert!(s.features.is_none());
    }

    #[test]
    fn heaters_come_from_the_typed_heaters_object_and_a_malformed_one_is_an_error() {
        let (server, printer, objects, help, mut status) = answers();
        let s = Summary::from_answers(
            &server,
            Some(&printer),
            Some(&objects),
            Some(&help),
            Some(&typed(&status)),
        )
        .unwrap();
        assert_eq!(s.heaters, ["heater_bed", "extruder"]);
        assert!(s.render().contains("Heaters         heater_bed, extruder"));
        status.insert("heaters".into(), json!({"available_heaters": "heater_bed"}));
        let e = SummaryObjects::parse(&status).unwrap_err().to_string();
        assert!(e.contains("heaters object"), "{e}");
    }
}
