//! PURE: the question a first soak asks when `soak.bed` or `soak.frame` is not set (issue 38,
//! item 1): what is on the bed, where its thermistor is, whether the printer is enclosed. The
//! answers' names (as the macro `KLIPCAL_SOAK_BED` and the API take them), the `[soak]` values
//! they stand for, and what each costs in minutes.

/// What is on the bed (`SURFACE=`).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Surface {
    /// A spring-steel sheet on a magnet.
    Steel,
    /// Glass on clips.
    Glass,
    /// The bare aluminium plate (PEI film or nothing).
    Bare,
    /// The user does not know: the weakest bed is assumed.
    Unknown,
}

/// Where the bed's thermistor is (`SENSOR=`).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Sensor {
    /// In (or screwed to) the aluminium plate.
    Plate,
    /// In the silicone heater pad under it.
    Pad,
    /// Not known: the pad (the slower) is assumed.
    Unknown,
}

/// Whether the printer is enclosed (`FRAME=`).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Frame {
    /// No enclosure.
    Open,
    /// An enclosure (or a frame built in a box).
    Enclosed,
    /// Not known: an enclosure is assumed.
    Unknown,
}

/// The words the macro and the API take for each answer, in the order the dialog offers them.
pub const SURFACE_WORDS: &[&str] = &["steel", "glass", "bare", "unknown"];
/// See [`SURFACE_WORDS`].
pub const SENSOR_WORDS: &[&str] = &["plate", "pad", "unknown"];
/// See [`SURFACE_WORDS`].
pub const FRAME_WORDS: &[&str] = &["open", "enclosed", "unknown"];

impl Surface {
    /// From its word (one of [`SURFACE_WORDS`]).
    #[must_use]
    pub fn from_word(w: &str) -> Option<Self> {
        Some(match w {
            "steel" => Self::Steel,
            "glass" => Self::Glass,
            "bare" => Self::Bare,
            "unknown" => Self::Unknown,
            _ => return None,
        })
    }
}

impl Sensor {
    /// From its word (one of [`SENSOR_WORDS`]).
    #[must_use]
    pub fn from_word(w: &str) -> Option<Self> {
        Some(match w {
            "plate" => Self::Plate,
            "pad" => Self::Pad,
            "unknown" => Self::Unknown,
            _ => return None,
        })
    }
}

impl Frame {
    /// From its word (one of [`FRAME_WORDS`]).
    #[must_use]
    pub fn from_word(w: &str) -> Option<Self> {
        Some(match w {
            "open" => Self::Open,
            "enclosed" => Self::Enclosed,
            "unknown" => Self::Unknown,
            _ => return None,
        })
    }

    /// The `soak.frame` value it stands for.
    #[must_use]
    pub fn setting(self) -> &'static str {
        match self {
            Self::Open => "open",
            Self::Enclosed => "enclosed",
            Self::Unknown => "unknown",
        }
    }
}

/// The `soak.bed` value for what is on the bed and where its thermistor is (`None`: the
/// thermistor is still to be asked). A surface not known is `"unknown"` (the weakest bed is
/// assumed, the question is not asked again); a thermistor not known is the pad, the slower of
/// the two for that surface.
#[must_use]
pub fn bed_setting(surface: Surface, sensor: Option<Sensor>) -> Option<&'static str> {
    let sensor = match (surface, sensor) {
        (Surface::Unknown, _) => return Some("unknown"),
        (_, None) => return None,
        (_, Some(s)) => s,
    };
    let plate = sensor == Sensor::Plate;
    Some(match (surface, plate) {
        (Surface::Steel, true) => "steel-plate",
        (Surface::Steel, false) => "steel-pad",
        (Surface::Glass, true) => "glass-plate",
        (Surface::Glass, false) => "glass-pad",
        (Surface::Bare, true) => "bare-plate",
        _ => "bare-pad",
    })
}

/// A `soak.bed` or `soak.frame` value that still asks the question: not set at all.
/// (`"unknown"` was answered "don't know": it assumes the same as unset and is not asked again.)
#[must_use]
pub fn unanswered(value: &str) -> bool {
    value.is_empty()
}

/// A `soak.bed` or `soak.frame` value that names nothing (unset or "don't know"): the weakest
/// bed, an enclosure.
#[must_use]
pub fn not_named(value: &str) -> bool {
    value.is_empty() || value == "unknown"
}

/// Median minutes from the bed reaching its band to the print, `klipcal bench soak` (seed 1,
/// PID beds; issue 38's table): what each answer means for a user. The rule is the same for
/// every answer (the surface within `soak.surface_budget_c`); a named build only lets klipcal
/// rule out less.
pub struct Minutes;

impl Minutes {
    /// Steel on a magnet, open frame, build named.
    pub const STEEL_OPEN: u32 = 17;
    /// Glass, open frame, build named.
    pub const GLASS_OPEN: u32 = 33;
    /// Steel in an enclosure, build named.
    pub const STEEL_ENCLOSED: u32 = 82;
    /// Nothing named (the weakest bed in an enclosure), steel beds on open frames.
    pub const DEFAULTS_OPEN: u32 = 104;
}

/// About how long a soak takes for the build `[soak]` names (`bed`, `frame`), minutes: the
/// figure the soak's first line says before its own estimate comes ([`Minutes`]).
#[must_use]
pub fn typical_minutes(bed: &str, frame: &str) -> u32 {
    match (not_named(bed), frame == "open", bed.starts_with("glass")) {
        (true, _, _) => Minutes::DEFAULTS_OPEN,
        (false, true, true) => Minutes::GLASS_OPEN,
        (false, true, false) => Minutes::STEEL_OPEN,
        (false, false, _) => Minutes::STEEL_ENCLOSED,
    }
}

/// One step of the question: its title, its text (one row each), and its answers as (label,
/// argument, word).
#[derive(Debug, Clone, PartialEq)]
pub struct Step {
    /// The dialog's title.
    pub title: &'static str,
    /// Its text rows.
    pub lines: Vec<String>,
    /// The answers: button label, the argument (`surface`, `sensor`, `frame`) and its word.
    pub answers: Vec<(&'static str, &'static str, &'static str)>,
}

/// The answers given so far (a step at a time; the bed is written once surface and sensor are
/// known).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct Answers {
    /// What is on the bed.
    pub surface: Option<Surface>,
    /// Where the thermistor is.
    pub sensor: Option<Sensor>,
    /// Open or enclosed.
    pub frame: Option<Frame>,
}

impl Answers {
    /// The step still to ask, when `bed` and `frame` (the `[soak]` values now) leave one.
    #[must_use]
    pub fn next(&self, bed: &str, frame: &str) -> Option<Step> {
        if unanswered(bed) {
            match self.surface {
                None => return Some(surface_step()),
                Some(s) if bed_setting(s, self.sensor).is_none() => {
                    return Some(sensor_step(s));
                }
                Some(_) => {}
            }
        }
        (unanswered(frame) && self.frame.is_none()).then(frame_step)
    }
}

fn surface_step() -> Step {
    Step {
        title: "klipcal: what is on your bed?",
        lines: vec![format!(
            "klipcal waits after the bed reaches its temperature until the print surface has \
             stopped warming. Naming your bed lets it wait only as long as your bed needs: \
             steel sheet on a magnet about {} min on an open printer, glass about {} min, a \
             bare plate less. Don't know: the slowest bed is assumed, about {} min.",
            Minutes::STEEL_OPEN,
            Minutes::GLASS_OPEN,
            Minutes::DEFAULTS_OPEN
        )],
        answers: vec![
            ("Steel sheet on a magnet", "surface", "steel"),
            ("Glass", "surface", "glass"),
            ("Bare plate", "surface", "bare"),
            ("Don't know", "surface", "unknown"),
        ],
    }
}

fn sensor_step(surface: Surface) -> Step {
    let what = match surface {
        Surface::Glass => "glass",
        Surface::Bare => "a bare plate",
        _ => "a steel sheet",
    };
    Step {
        title: "klipcal: where is the bed's thermistor?",
        lines: vec![format!(
            "With {what}: in the aluminium plate (screwed in or in a hole of it), or in the \
             silicone heater pad under it (most stock beds; its wires leave the pad). In the \
             plate is the faster: the plate is held at its temperature. Don't know: the pad \
             is assumed, a few minutes longer."
        )],
        answers: vec![
            ("In the plate", "sensor", "plate"),
            ("In the heater pad", "sensor", "pad"),
            ("Don't know", "sensor", "unknown"),
        ],
    }
}

fn frame_step() -> Step {
    Step {
        title: "klipcal: is the printer enclosed?",
        lines: vec![format!(
            "In an enclosure the air keeps warming for an hour or more, and klipcal waits \
             for it (a steel bed about {} min). On an open printer it waits only for the bed \
             itself (about {} min). Don't know: an enclosure is assumed.",
            Minutes::STEEL_ENCLOSED,
            Minutes::STEEL_OPEN
        )],
        answers: vec![
            ("Open, no enclosure", "frame", "open"),
            ("Enclosed", "frame", "enclosed"),
            ("Don't know", "frame", "unknown"),
        ],
    }
}

/// A comment written above a value the question wrote, saying what was answered.
#[must_use]
pub fn comment_for(key: &str, value: &str, answers: &Answers) -> String {
    match (key, value) {
        ("bed", "unknown") => "answered \"don't know\" in klipcal's soak question: the slowest \
                               bed (glass on clips, thermistor in the pad) is assumed; naming \
                               yours shortens every soak"
            .into(),
        ("bed", _) if answers.sensor == Some(Sensor::Unknown) => format!(
            "answered in klipcal's soak question; the thermistor's place was not known, so the \
             pad (the slower) is assumed: \"{}\" if it is in the plate",
            value.replace("-pad", "-plate")
        ),
        ("frame", "unknown") => "answered \"don't know\" in klipcal's soak question: an \
                                 enclosure is assumed (up to tau_max_s)"
            .into(),
        _ => "answered in klipcal's soak question".into(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::calib::soak::BED_PRESETS;

    #[test]
    fn every_surface_and_sensor_names_a_preset_or_unknown() {
        for s in SURFACE_WORDS {
            let surface = Surface::from_word(s).unwrap();
            for t in SENSOR_WORDS {
                let bed = bed_setting(surface, Sensor::from_word(t)).unwrap();
                assert!(
                    bed == "unknown" || BED_PRESETS.iter().any(|b| b.name == bed),
                    "{s}/{t}: {bed}"
                );
            }
        }
        // A thermistor not known is the pad: the weaker coupling of the two.
        let g = |n: &str| BED_PRESETS.iter().find(|b| b.name == n).unwrap().g;
        assert!(g("steel-pad") < g("steel-plate"));
        assert_eq!(
            bed_setting(Surface::Steel, Some(Sensor::Unknown)),
            Some("steel-pad")
        );
        assert_eq!(bed_setting(Surface::Glass, None), None);
        assert_eq!(bed_setting(Surface::Unknown, None), Some("unknown"));
        assert_eq!(Surface::from_word("granite"), None);
    }

    #[test]
    fn the_question_asks_only_what_is_not_set_one_step_at_a_time() {
        let none = Answers::default();
        assert_eq!(
            none.next("", "").unwrap().title,
            "klipcal: what is on your bed?"
        );
        assert_eq!(
            none.next("steel-pad", "").unwrap().title,
            "klipcal: is the printer enclosed?"
        );
        assert!(none.next("steel-pad", "open").is_none());
        // "unknown" was answered: not asked again.
        assert!(none.next("unknown", "unknown").is_none());
        let steel = Answers {
            surface: Some(Surface::Steel),
            ..Answers::default()
        };
        let step = steel.next("", "").unwrap();
        assert_eq!(step.title, "klipcal: where is the bed's thermistor?");
        assert!(step.lines[0].contains("steel sheet"), "{:?}", step.lines);
        let both = Answers {
            sensor: Some(Sensor::Plate),
            ..steel
        };
        assert_eq!(
            both.next("", "").unwrap().title,
            "klipcal: is the printer enclosed?"
        );
        // Every step says what its answers mean in minutes.
        for step in [surface_step(), sensor_step(Surface::Glass), frame_step()] {
            assert!(step.lines.iter().any(|l| l.contains("min")), "{step:?}");
            assert!(step.answers.iter().any(|a| a.0 == "Don't know"), "{step:?}");
        }
    }
}
