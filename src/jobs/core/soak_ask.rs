//! The soak question (issue 38, item 1): when `soak.bed` or `soak.frame` is not set, the first
//! soak asks what is on the bed, where its thermistor is and whether the printer is enclosed,
//! with buttons in Mainsail's and Fluidd's dialog and on klipcal's page; the macro
//! `KLIPCAL_SOAK_BED` and `/api/soak/bed` answer too. An answer is written to klipcal.toml
//! (`config::edit`: backed up, comments kept, a broken file refused whole) and the running
//! soak uses it at once (it watches [`AskState::generation`]). A dialog closed by mistake is
//! shown again when the bed reaches its band, and the console and the page keep the question.

use serde::Serialize;

use super::console::{Button, Prompt};
use super::session::Core;
use super::soak::SoakSettings;
use super::user;
use crate::calib::soak::ask::{self, Answers, Frame, Sensor, Step, Surface};

/// The question's state, one per daemon (in the [`Core`]).
#[derive(Debug, Default)]
pub(crate) struct AskState {
    /// The settings file the answers go to (set once by the registry).
    pub settings: Option<SoakSettings>,
    /// Answers given but not yet written (what is on the bed, before where its thermistor is).
    pub answers: Answers,
    /// Counts the answers written: a soak whose count differs reads `[soak]` again.
    pub generation: u64,
    /// A soak is running and asks (its build is not set).
    pub asking: bool,
    /// How often the dialog was shown in this soak (it is shown again once, at the band, when
    /// it was closed without an answer).
    pub shown: u8,
    /// What the soak running now says (none between soaks).
    pub live: Option<super::soak::LiveSoak>,
}

/// The question as the status shows it (the page's buttons).
#[derive(Debug, Clone, PartialEq, Serialize)]
pub(crate) struct QuestionStatus {
    /// The question.
    pub title: String,
    /// What each answer means.
    pub text: String,
    /// The answers.
    pub answers: Vec<AnswerStatus>,
}

/// One answer of [`QuestionStatus`].
#[derive(Debug, Clone, PartialEq, Serialize)]
pub(crate) struct AnswerStatus {
    /// The button's label.
    pub label: String,
    /// The argument it sets (`surface`, `sensor`, `frame`) ...
    pub arg: String,
    /// ... to this word.
    pub value: String,
}

/// The step still to ask, from `[soak]` as the file says now.
fn next_step(core: &Core) -> Option<Step> {
    let (settings, answers) = {
        let st = core.ask_state();
        (st.settings.clone()?, st.answers)
    };
    let (p, _) = settings.now();
    answers.next(&p.bed, &p.frame)
}

/// The dialog of a step.
fn prompt(step: &Step) -> Prompt {
    Prompt {
        title: step.title.into(),
        lines: step.lines.clone(),
        buttons: step
            .answers
            .iter()
            .map(|(label, arg, word)| {
                Button::new(
                    label,
                    &format!("KLIPCAL_SOAK_BED {}={word}", arg.to_uppercase()),
                    if *word == "unknown" {
                        "secondary"
                    } else {
                        "primary"
                    },
                )
            })
            .collect(),
        footer: Vec::new(),
    }
}

/// Whether the dialog open now is the soak question's.
#[must_use]
pub(crate) fn showing(core: &Core) -> bool {
    core.dialog_title()
        .is_some_and(|t| ASK_TITLES.contains(&t.as_str()))
}

/// Whether the question still waits in this soak (shown, or closed and to be shown again):
/// another dialog (the offer to print now) waits for it.
#[must_use]
pub(crate) fn pending(core: &Core) -> bool {
    let st = core.ask_state();
    st.asking && st.shown < 2
}

/// Every step's title.
const ASK_TITLES: [&str; 3] = [
    "klipcal: what is on your bed?",
    "klipcal: where is the bed's thermistor?",
    "klipcal: is the printer enclosed?",
];

/// A soak starts (`again`: the bed reached its band): asks the step still to ask, when the
/// build is not set.
pub(crate) async fn ask(core: &Core, again: bool) {
    let Some(step) = next_step(core) else {
        core.ask_state().asking = false;
        return;
    };
    // Shown again only when it is not showing (closed without an answer), once.
    let on_screen = showing(core);
    {
        let mut st = core.ask_state();
        if again && (!st.asking || st.shown >= 2 || on_screen) {
            return;
        }
        st.asking = true;
        st.shown += 1;
    }
    // The dialog alone (issue 40 item 6: a console row said the same): its rows show the
    // question and each button's macro in the console too, and a close without an answer
    // says there how to answer.
    core.prompt(&prompt(&step)).await;
}

/// The soak ended (settled, or its session did): nothing is asked any more until the next.
pub(crate) fn soak_ended(core: &Core) {
    let mut st = core.ask_state();
    st.asking = false;
    st.shown = 0;
    st.live = None;
}

/// The soak as STATUS and the page show it: the question while it is asked, the running soak's
/// line and how it was worked out.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub(crate) struct SoakView {
    /// The question still to answer.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub question: Option<QuestionStatus>,
    /// The running soak.
    #[serde(flatten, skip_serializing_if = "Option::is_none")]
    pub live: Option<super::soak::LiveSoak>,
}

/// [`SoakView`] now; none when no soak runs.
#[must_use]
pub(crate) fn view(core: &Core) -> Option<SoakView> {
    let question = status(core);
    let live = core.ask_state().live.clone();
    (question.is_some() || live.is_some()).then_some(SoakView { question, live })
}

/// The question as the status shows it, while a soak asks.
#[must_use]
pub(crate) fn status(core: &Core) -> Option<QuestionStatus> {
    if !core.ask_state().asking {
        return None;
    }
    let step = next_step(core)?;
    Some(QuestionStatus {
        title: step.title.trim_start_matches("klipcal: ").to_string(),
        text: step.lines.join(" "),
        answers: step
            .answers
            .iter()
            .map(|(label, arg, word)| AnswerStatus {
                label: (*label).into(),
                arg: (*arg).into(),
                value: (*word).into(),
            })
            .collect(),
    })
}

/// An answer, typed at the boundary: any of the three, at least one.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct BuildAnswer {
    /// `SURFACE=`.
    pub(crate) surface: Option<Surface>,
    /// `SENSOR=`.
    pub(crate) sensor: Option<Sensor>,
    /// `FRAME=`.
    pub(crate) frame: Option<Frame>,
}

impl BuildAnswer {
    /// From the macro's words (each checked by the command table against its choices).
    ///
    /// # Errors
    /// None of the three given, or a thermistor without what is on the bed.
    pub(crate) fn from_words(
        surface: Option<&str>,
        sensor: Option<&str>,
        frame: Option<&str>,
    ) -> anyhow::Result<Self> {
        let a = Self {
            surface: surface.and_then(Surface::from_word),
            sensor: sensor.and_then(Sensor::from_word),
            frame: frame.and_then(Frame::from_word),
        };
        if a.surface.is_none() && a.sensor.is_none() && a.frame.is_none() {
            return Err(user(
                "KLIPCAL_SOAK_BED: no answer given; expected SURFACE=steel|glass|bare|unknown, \
                 SENSOR=plate|pad|unknown and/or FRAME=open|enclosed|unknown",
            ));
        }
        Ok(a)
    }
}

/// `KLIPCAL_SOAK_BED`: takes an answer, writes what it settles to klipcal.toml, and asks the
/// next step (or closes the dialog).
///
/// # Errors
/// A thermistor without what is on the bed, or the settings file refused (it does not load:
/// nothing written) or not written.
pub(crate) async fn answer(core: &Core, a: BuildAnswer) -> anyhow::Result<BedAnswer> {
    let (settings, mut answers) = {
        let st = core.ask_state();
        let s = st
            .settings
            .clone()
            .ok_or_else(|| anyhow::anyhow!("the soak settings are not known to the core"))?;
        (s, st.answers)
    };
    if let Some(s) = a.surface {
        answers.surface = Some(s);
        answers.sensor = None;
    }
    if let Some(s) = a.sensor {
        if answers.surface.is_none() {
            return Err(user(
                "KLIPCAL_SOAK_BED: SENSOR needs what is on the bed first: add \
                 SURFACE=steel|glass|bare|unknown",
            ));
        }
        answers.sensor = Some(s);
    }
    if let Some(f) = a.frame {
        answers.frame = Some(f);
    }
    let bed = answers
        .surface
        .and_then(|s| ask::bed_setting(s, answers.sensor));
    let mut values: Vec<(&str, &str, String)> = Vec::new();
    if let Some(b) = bed {
        values.push(("bed", b, ask::comment_for("bed", b, &answers)));
    }
    if let Some(f) = a.frame.map(Frame::setting) {
        values.push(("frame", f, ask::comment_for("frame", f, &answers)));
    }
    let mut said = Vec::new();
    if !values.is_empty() {
        let path = settings.file();
        let stamp = super::printer_config::stamp(super::session::now_unix() as u64);
        let written = crate::config::edit::set_soak_keys(&path, &values, &stamp)
            .map_err(|e| user(format!("{e:#}")))?;
        settings.written_to(&path);
        let set: Vec<String> = values
            .iter()
            .map(|(k, v, _)| format!("soak.{k} = \"{v}\""))
            .collect();
        said.push(format!(
            "{} written to {}{}",
            set.join(" and "),
            written.path.display(),
            written
                .backup
                .map(|b| format!(" (backup: {})", b.display()))
                .unwrap_or_default()
        ));
    }
    {
        let mut st = core.ask_state();
        st.answers = Answers {
            surface: if bed.is_some() { None } else { answers.surface },
            sensor: None,
            frame: None,
        };
        if !values.is_empty() {
            st.generation += 1;
        }
    }
    let asking = core.ask_state().asking;
    match next_step(core).filter(|_| asking) {
        Some(step) => {
            said.push(format!(
                "next: {}",
                step.title.trim_start_matches("klipcal: ")
            ));
            core.prompt(&prompt(&step)).await;
        }
        None => {
            if asking {
                core.ask_state().asking = false;
                said.push("the soak under way uses it now".into());
            } else {
                said.push("the next soak uses it".into());
            }
            if showing(core) {
                core.prompt_end().await;
            }
        }
    }
    Ok(BedAnswer {
        message: said.join("; "),
        bed,
        frame: a.frame.map(Frame::setting),
    })
}

/// `klipcal_soak_bed`'s answer: what was written, the settings now.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub(crate) struct BedAnswer {
    /// What the console shows.
    pub message: String,
    /// `soak.bed` as written, when the answer made it whole.
    pub bed: Option<&'static str>,
    /// `soak.frame` as written.
    pub frame: Option<&'static str>,
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn an_answer_needs_one_word_and_a_thermistor_needs_its_surface() {
        assert!(BuildAnswer::from_words(None, None, None).is_err());
        let a = BuildAnswer::from_words(Some("steel"), None, Some("open")).unwrap();
        assert_eq!(a.surface, Some(Surface::Steel));
        assert_eq!(a.frame, Some(Frame::Open));
    }

    #[test]
    fn each_step_is_a_dialog_of_macro_buttons() {
        let step = Answers::default().next("", "").unwrap();
        let p = prompt(&step);
        assert_eq!(p.title, "klipcal: what is on your bed?");
        assert!(ASK_TITLES.contains(&p.title.as_str()));
        let gcodes: Vec<&str> = p.buttons.iter().map(|b| b.gcode.as_str()).collect();
        assert_eq!(
            gcodes,
            [
                "KLIPCAL_SOAK_BED SURFACE=steel",
                "KLIPCAL_SOAK_BED SURFACE=glass",
                "KLIPCAL_SOAK_BED SURFACE=bare",
                "KLIPCAL_SOAK_BED SURFACE=unknown"
            ]
        );
        assert!(p.lines.iter().any(|l| l.contains("min")), "{p:?}");
        // The dialog's own script is one RESPOND per action, none broken by the text.
        assert!(p
            .script()
            .lines()
            .all(|l| l.starts_with("RESPOND TYPE=command")));
    }
}
