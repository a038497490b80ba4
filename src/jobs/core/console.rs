//! What a user reads on Klipper's console: klipcal's answers (`RESPOND PREFIX=klipcal`), its
//! errors (`RESPOND TYPE=error`, which Mainsail and Fluidd colour), and the Mainsail/Fluidd
//! prompt dialogs (`action:prompt_*`). The only builder of RESPOND lines; every text is made
//! safe for Klipper's parser, never pasted raw.

use std::cell::RefCell;
use std::future::Future;
use std::sync::{Mutex, PoisonError};
use std::time::{Duration, Instant};

use tracing::warn;

use crate::klipper::gcode_cmd::{self, GcodeCmd};
use crate::moonraker::Moonraker;

/// `RESPOND PREFIX=klipcal MSG="…"` for one line of text.
#[must_use]
pub(crate) fn respond_line(msg: &str) -> String {
    GcodeCmd::new("RESPOND")
        .word("PREFIX", gcode_cmd::RESPOND_PREFIX)
        .text_lossy("MSG", msg)
        .build()
        .unwrap_or_else(|_| "RESPOND PREFIX=klipcal MSG=\"(unprintable answer)\"".to_string())
}

/// `RESPOND TYPE=error MSG="klipcal: …"` for one line of an error.
#[must_use]
pub(crate) fn error_line(msg: &str) -> String {
    GcodeCmd::new("RESPOND")
        .word("TYPE", "error")
        .text_lossy("MSG", &format!("klipcal: {msg}"))
        .build()
        .unwrap_or_else(|_| "RESPOND TYPE=error MSG=\"klipcal: (unprintable error)\"".to_string())
}

/// The console script for a message: one RESPOND per line (Klipper's RESPOND is one line).
#[must_use]
pub(crate) fn answer_script(msg: &str, is_error: bool) -> String {
    msg.lines()
        .filter(|l| !l.trim().is_empty())
        .map(|l| {
            if is_error {
                error_line(l)
            } else {
                respond_line(l)
            }
        })
        .collect::<Vec<_>>()
        .join("\n")
}

/// klipcal.cfg's helper that says an answer of several lines as one console row (Klipper's
/// `action_respond_info`: one response, a `// ` before each line). Moonraker and the front ends
/// keep one row per response, and a RESPOND is one line: a status or a measuring guide of seven
/// lines was seven rows (issue 40 item 6).
pub(crate) const SAY_MACRO: &str = "_KLIPCAL_SAY";

/// Where one line of [`SAY_MACRO`]'s `MSG` ends (a G-code line cannot hold a line break; the
/// macro turns this back into one).
pub(crate) const SAY_LINE_END: char = '␤';

/// `_KLIPCAL_SAY MSG="…"` for answer lines (each made safe as a RESPOND's text).
#[must_use]
fn say_line(lines: &[String]) -> Option<String> {
    let text = lines
        .iter()
        .map(|l| gcode_cmd::sanitize_text(l).replace(SAY_LINE_END, " "))
        .collect::<Vec<_>>()
        .join(&SAY_LINE_END.to_string());
    GcodeCmd::new(SAY_MACRO).text("MSG", &text).build().ok()
}

/// The text of one of klipcal's answer lines (`RESPOND PREFIX=klipcal MSG="…"`, as
/// [`respond_line`] builds it).
fn answer_text(line: &str) -> Option<&str> {
    line.strip_prefix(&format!(
        "RESPOND PREFIX={} MSG=\"",
        gcode_cmd::RESPOND_PREFIX
    ))?
    .strip_suffix('"')
}

/// `script` with each run of two or more of klipcal's answer lines said as one console row
/// through [`SAY_MACRO`]; errors (red, one line each) and dialog actions (one response each,
/// as the front ends' prompt parsers read them) stay as they are.
#[must_use]
pub(crate) fn one_row_per_answer(script: &str) -> String {
    let mut out: Vec<String> = Vec::new();
    let mut run: Vec<String> = Vec::new();
    let flush = |run: &mut Vec<String>, out: &mut Vec<String>| {
        match run.len() {
            0 => {}
            1 => out.push(respond_line(&run[0])),
            _ => match say_line(run) {
                Some(l) => out.push(l),
                None => out.extend(run.iter().map(|t| respond_line(t))),
            },
        }
        run.clear();
    };
    for line in script.lines() {
        match answer_text(line) {
            Some(t) => run.push(t.to_string()),
            None => {
                flush(&mut run, &mut out);
                out.push(line.to_string());
            }
        }
    }
    flush(&mut run, &mut out);
    out.join("\n")
}

/// Whether Klipper has [`SAY_MACRO`] (an older klipcal.cfg has not), checked at most once a
/// minute.
async fn say_macro_known(m: &Moonraker) -> bool {
    static KNOWN: Mutex<Option<(Instant, bool)>> = Mutex::new(None);
    let fresh = |k: &Option<(Instant, bool)>| {
        k.filter(|(at, _)| at.elapsed() < Duration::from_secs(60))
            .map(|(_, known)| known)
    };
    if let Some(known) = fresh(&KNOWN.lock().unwrap_or_else(PoisonError::into_inner)) {
        return known;
    }
    let name = format!("gcode_macro {SAY_MACRO}");
    let known = m
        .objects_list()
        .await
        .is_ok_and(|objects| objects.iter().any(|o| o.eq_ignore_ascii_case(&name)));
    *KNOWN.lock().unwrap_or_else(PoisonError::into_inner) = Some((Instant::now(), known));
    known
}

/// The argument a dialog's button adds to its G-code: the number of the question it answers
/// (see [`Prompt::script_asked`]); any operation takes it.
pub(crate) const ASK_ARG: &str = "ASK";

/// The prompt action that closes any open dialog.
pub(crate) const PROMPT_END: &str = "RESPOND TYPE=command MSG=action:prompt_end";

/// A prompt button: label, the G-code it runs, its colour (`primary`, `secondary`, `info`,
/// `warning`, `error`).
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Button {
    /// Label.
    pub label: String,
    /// The macro it runs (klipcal's own macro names only).
    pub gcode: String,
    /// Colour.
    pub style: String,
}

impl Button {
    /// A button.
    #[must_use]
    pub(crate) fn new(label: &str, gcode: &str, style: &str) -> Self {
        Self {
            label: label.into(),
            gcode: gcode.into(),
            style: style.into(),
        }
    }

    /// The footer's Cancel of a session dialog: it asks first (`_KLIPCAL_CANCEL_ASK`, a macro in
    /// klipcal.cfg, shows "end the session?" with Yes → `KLIPCAL_CANCEL` and Back →
    /// `_KLIPCAL_PROMPT_BACK`), so one tap beside the other buttons ends nothing.
    #[must_use]
    pub(crate) fn cancel_asking() -> Self {
        Self::new("Cancel session…", "_KLIPCAL_CANCEL_ASK", "error")
    }
}

/// A Mainsail/Fluidd prompt dialog.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct Prompt {
    /// Title.
    pub title: String,
    /// Text lines.
    pub lines: Vec<String>,
    /// Buttons in the body.
    pub buttons: Vec<Button>,
    /// Buttons in the footer (kept apart from the body's, e.g. Close or Cancel).
    pub footer: Vec<Button>,
}

impl Prompt {
    /// The G-code script that shows the dialog (closing any dialog open before), its buttons
    /// without a question number.
    #[must_use]
    #[cfg(test)]
    pub(crate) fn script(&self) -> String {
        self.script_asked(None)
    }

    /// [`Prompt::script`] with every button's G-code carrying `ASK=<ask>`, the number of the
    /// question the dialog asks: klipcal refuses a press whose question it no longer asks
    /// (issue 40: a stale dialog's End cancelled the round that had started since).
    #[must_use]
    pub(crate) fn script_asked(&self, ask: Option<u64>) -> String {
        let gcode = |b: &Button| match ask {
            Some(n) => format!("{} {ASK_ARG}={n}", b.gcode),
            None => b.gcode.clone(),
        };
        let mut actions = vec![format!("prompt_begin {}", self.title)];
        actions.extend(self.lines.iter().map(|l| format!("prompt_text {l}")));
        for b in &self.buttons {
            actions.push(format!(
                "prompt_button {}|{}|{}",
                b.label,
                gcode(b),
                b.style
            ));
        }
        for b in &self.footer {
            actions.push(format!(
                "prompt_footer_button {}|{}|{}",
                b.label,
                gcode(b),
                b.style
            ));
        }
        actions.push("prompt_show".into());
        actions
            .iter()
            .filter_map(|a| gcode_cmd::respond_action(&gcode_cmd::sanitize_text(a)).ok())
            .collect::<Vec<_>>()
            .join("\n")
    }
}

/// What the console says when the user closed klipcal's dialog without answering it (Mainsail's
/// ✕, a tap outside it in Fluidd; both send `action:prompt_end`): what still waits and how to
/// answer without the dialog (issue 26 A.1: a closed decision is never lost).
#[must_use]
pub(crate) fn closed_notice(p: &Prompt) -> String {
    let title = p.title.strip_prefix("klipcal: ").unwrap_or(&p.title);
    let answers: Vec<String> = p
        .buttons
        .iter()
        .filter(|b| !b.gcode.starts_with('_'))
        .map(|b| format!("{} = {}", b.label, b.gcode))
        .collect();
    let cancel = p
        .buttons
        .iter()
        .chain(&p.footer)
        .any(|b| b.gcode == Button::cancel_asking().gcode);
    let mut said = format!("dialog \"{title}\" closed");
    if !answers.is_empty() {
        said.push_str(", still waiting for your answer: ");
        said.push_str(&answers.join(", "));
    }
    if cancel {
        said.push_str(", KLIPCAL_CANCEL ends the session");
    }
    said.push_str(". _KLIPCAL_PROMPT_BACK shows the dialog again");
    said
}

/// A change to klipcal's dialog.
#[derive(Debug, Clone, PartialEq, Eq)]
pub(crate) enum PromptChange {
    /// Show this dialog script (it begins a new dialog, replacing any open one).
    Show(String),
    /// Close the dialog.
    End,
}

impl PromptChange {
    /// The console script that makes the change.
    #[must_use]
    pub(crate) fn script(&self) -> String {
        match self {
            Self::Show(s) => s.clone(),
            Self::End => PROMPT_END.to_string(),
        }
    }
}

tokio::task_local! {
    static HELD: RefCell<Option<PromptChange>>;
}

/// Runs one call holding back its dialog changes, so that the console reads the call's answer
/// first and the dialog after it, in one script (Mainsail and Fluidd show every script klipcal
/// sends as a command line after a reload). Only the last change survives: it is the dialog's
/// state when the call ends (a `prompt_begin` replaces whatever was open).
pub(crate) async fn holding_prompts<F: Future>(f: F) -> (F::Output, Option<PromptChange>) {
    HELD.scope(RefCell::new(None), async move {
        let out = f.await;
        let change = HELD.with(|h| h.borrow_mut().take());
        (out, change)
    })
    .await
}

/// Holds `change` back for the call running now; false outside a call (send it now).
#[must_use]
pub(crate) fn hold(change: PromptChange) -> bool {
    HELD.try_with(|h| *h.borrow_mut() = Some(change)).is_ok()
}

/// Drops a held change (a dialog closed at once, e.g. before a long operation).
pub(crate) fn drop_held() {
    let _ = HELD.try_with(|h| h.borrow_mut().take());
}

/// An answer's lines, then the dialog change, as one console script.
#[must_use]
pub(crate) fn answer_then_prompt(answer: &str, change: Option<&PromptChange>) -> String {
    [
        answer.to_string(),
        change.map(PromptChange::script).unwrap_or_default(),
    ]
    .into_iter()
    .filter(|s| !s.is_empty())
    .collect::<Vec<_>>()
    .join("\n")
}

/// Sends a console script (answers, dialog changes); a failure is logged, not raised: the
/// console is a courtesy, the session goes on.
pub(crate) async fn send_script(m: &Moonraker, script: &str) {
    send(m, script, "console script not shown").await;
}

/// Says `msg` on the console.
pub(crate) async fn say(m: &Moonraker, msg: &str) {
    send(m, &answer_script(msg, false), "console message not shown").await;
}

/// Says `msg` on the console as an error.
pub(crate) async fn error(m: &Moonraker, msg: &str) {
    send(m, &answer_script(msg, true), "console error not shown").await;
}

async fn send(m: &Moonraker, script: &str, what: &str) {
    if script.is_empty() {
        return;
    }
    let script = if script.lines().filter(|l| answer_text(l).is_some()).count() > 1
        && say_macro_known(m).await
    {
        one_row_per_answer(script)
    } else {
        script.to_string()
    };
    let ends = script.lines().filter(|l| l.trim() == PROMPT_END).count();
    OWN_ENDS.expect(m.url(), ends);
    if let Err(e) = m.console_script(&script).await {
        OWN_ENDS.forget(m.url(), ends);
        warn!(error = %e, "{what}");
    }
}

/// The closes klipcal sent whose echo (`// action:prompt_end` on the console) has not come
/// back yet, per Moonraker. The echo of klipcal's own close can reach the close watcher after
/// klipcal has already shown its next dialog (the watcher is another task, and a loaded host
/// delays it): counting the closes sent, not reading the dialog's state when the echo is
/// read, tells klipcal's echo from the user's ✕ whatever the order.
static OWN_ENDS: OwnEnds = OwnEnds(Mutex::new(Vec::new()));

/// How long an echo is waited for before its close is forgotten (a lost notification).
const ECHO_WAIT: Duration = Duration::from_secs(120);

struct OwnEnds(Mutex<Vec<(String, Instant)>>);

impl OwnEnds {
    fn lock(&self) -> std::sync::MutexGuard<'_, Vec<(String, Instant)>> {
        let mut v = self.0.lock().unwrap_or_else(PoisonError::into_inner);
        v.retain(|(_, at)| at.elapsed() < ECHO_WAIT);
        v
    }

    fn expect(&self, url: &str, n: usize) {
        let mut v = self.lock();
        for _ in 0..n {
            v.push((url.to_string(), Instant::now()));
        }
    }

    fn forget(&self, url: &str, n: usize) {
        for _ in 0..n {
            self.take(url);
        }
    }

    fn take(&self, url: &str) -> bool {
        let mut v = self.lock();
        let Some(i) = v.iter().position(|(u, _)| u == url) else {
            return false;
        };
        v.remove(i);
        true
    }
}

/// Whether a close seen on `m`'s console is the echo of one klipcal sent (it is then counted
/// off); false for a close klipcal did not send (the user's ✕ or tap outside).
pub(crate) fn own_close_echo(m: &Moonraker) -> bool {
    OWN_ENDS.take(m.url())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_close_echo_is_klipcals_only_as_often_as_klipcal_sent_one_on_that_printer() {
        let ends = OwnEnds(Mutex::new(Vec::new()));
        ends.expect("ws://a", 2);
        ends.expect("ws://b", 1);
        // klipcal's two echoes on printer a, late or not; a third close there is the user's.
        assert!(ends.take("ws://a") && ends.take("ws://a"));
        assert!(!ends.take("ws://a"));
        // A send that failed leaves no echo to wait for.
        ends.forget("ws://b", 1);
        assert!(!ends.take("ws://b"));
    }

    #[test]
    fn console_answers_cannot_break_out_of_the_respond_command() {
        let line = respond_line("a \"quoted\" # not a comment; 5*2 \\ end\nnext");
        assert!(line.starts_with("RESPOND PREFIX=klipcal MSG=\""), "{line}");
        assert_eq!(line.matches('"').count(), 2, "{line}");
        for bad in ['#', ';', '*', '\\', '\n'] {
            assert!(!line.contains(bad), "{line}");
        }
        assert!(
            line.contains("not a comment") && line.contains("next"),
            "{line}"
        );
    }

    #[test]
    fn an_answer_of_several_lines_is_one_console_row() {
        let answer = answer_script("first\nsecond \"quoted\" ␤ here\nthird", false);
        let dialog = PromptChange::End.script();
        let error = answer_script("bad", true);
        let script = [
            answer.as_str(),
            dialog.as_str(),
            &respond_line("alone"),
            &error,
        ]
        .join("\n");
        let s = one_row_per_answer(&script);
        let lines: Vec<&str> = s.lines().collect();
        assert_eq!(
            lines,
            [
                "_KLIPCAL_SAY MSG=\"first␤second 'quoted'   here␤third\"",
                PROMPT_END,
                "RESPOND PREFIX=klipcal MSG=\"alone\"",
                "RESPOND TYPE=error MSG=\"klipcal: bad\"",
            ]
        );
        // Nothing to join: the script as it was.
        let one = respond_line("only");
        assert_eq!(one_row_per_answer(&one), one);
        // The macro klipcal.cfg defines turns the line ends back into line breaks.
        let cfg = crate::jobs::registry::macros_cfg();
        let body = cfg
            .split(&format!("[gcode_macro {SAY_MACRO}]"))
            .nth(1)
            .expect("klipcal.cfg has no _KLIPCAL_SAY");
        let body = body.split("\n[").next().unwrap_or_default();
        assert!(
            body.contains(&format!("|replace(\"{SAY_LINE_END}\", \"\\n\")"))
                && body.contains("action_respond_info(\"klipcal \""),
            "{body}"
        );
    }

    #[test]
    fn errors_go_out_as_klipper_errors_one_line_each() {
        let s = answer_script("first problem\nsecond; with a semicolon", true);
        let lines: Vec<&str> = s.lines().collect();
        assert_eq!(lines.len(), 2, "{s}");
        assert!(lines[0].starts_with("RESPOND TYPE=error MSG=\"klipcal: first problem\""));
        assert!(!lines[1].contains(';'), "{s}");
    }

    #[test]
    fn a_prompt_keeps_footer_buttons_apart_and_ends_with_show() {
        let p = Prompt {
            title: "klipcal: new rotation distances".into(),
            lines: vec!["stepper_x: 40 → 40.08".into()],
            buttons: vec![Button::new("Apply", "KLIPCAL_AB_APPLY", "primary")],
            footer: vec![Button::new("Close", "_KLIPCAL_PROMPT_CLOSE", "secondary")],
        };
        let s = p.script();
        let lines: Vec<&str> = s.lines().collect();
        assert!(lines[0].contains("action:prompt_begin klipcal"), "{s}");
        assert!(lines[2].contains("prompt_button Apply|KLIPCAL_AB_APPLY|primary"));
        assert!(lines[3].contains("prompt_footer_button Close|_KLIPCAL_PROMPT_CLOSE|secondary"));
        assert!(lines[4].contains("action:prompt_show"));
    }

    #[test]
    fn every_button_carries_the_question_it_answers() {
        let p = Prompt {
            title: "klipcal: round 2?".into(),
            lines: vec!["x".into()],
            buttons: vec![Button::new("Print round 2", "KLIPCAL_AB_START", "primary")],
            footer: vec![Button::new("End", "_KLIPCAL_CANCEL_ASK", "secondary")],
        };
        let s = p.script_asked(Some(7));
        assert!(
            s.contains("prompt_button Print round 2|KLIPCAL_AB_START ASK=7|primary"),
            "{s}"
        );
        assert!(
            s.contains("prompt_footer_button End|_KLIPCAL_CANCEL_ASK ASK=7|secondary"),
            "{s}"
        );
        // What the console says to type keeps the bare command (it acts on the session now).
        assert!(!closed_notice(&p).contains("ASK"), "{}", closed_notice(&p));
    }

    #[test]
    fn a_closed_dialog_says_what_waits_and_how_to_answer() {
        let p = Prompt {
            title: "klipcal: the bed has not settled".into(),
            lines: vec!["x".into()],
            buttons: vec![
                Button::new("Print now", "KLIPCAL_SOAK_CHOICE CHOICE=print", "warning"),
                Button::new("Wait 10 min", "KLIPCAL_SOAK_CHOICE CHOICE=wait", "primary"),
            ],
            footer: vec![Button::cancel_asking()],
        };
        let said = closed_notice(&p);
        assert_eq!(
            said,
            "dialog \"the bed has not settled\" closed, still waiting for your answer: \
             Print now = KLIPCAL_SOAK_CHOICE CHOICE=print, Wait 10 min = KLIPCAL_SOAK_CHOICE \
             CHOICE=wait, KLIPCAL_CANCEL ends the session. _KLIPCAL_PROMPT_BACK shows the \
             dialog again"
        );
        // A console line Klipper takes whole.
        let line = respond_line(&said);
        assert_eq!(line.matches('"').count(), 2, "{line}");
        // A dialog with only its own Close: nothing to answer, only how to see it again.
        let measuring = Prompt {
            title: "klipcal: measure the pylons (round 1)".into(),
            buttons: vec![Button::new(
                "Close and type readings",
                "_KLIPCAL_PROMPT_CLOSE",
                "primary",
            )],
            ..Prompt::default()
        };
        assert_eq!(
            closed_notice(&measuring),
            "dialog \"measure the pylons (round 1)\" closed. _KLIPCAL_PROMPT_BACK shows the \
             dialog again"
        );
    }

    #[tokio::test]
    async fn a_call_holds_back_its_dialog_changes_and_keeps_only_the_last() {
        let show = PromptChange::Show(
            Prompt {
                title: "klipcal: t".into(),
                lines: vec!["x".into()],
                ..Prompt::default()
            }
            .script(),
        );
        let (out, held) = holding_prompts(async {
            assert!(hold(PromptChange::End));
            assert!(hold(show.clone()));
            7
        })
        .await;
        assert_eq!((out, held.clone()), (7, Some(show.clone())));
        let (_, held) = holding_prompts(async {
            assert!(hold(show.clone()));
            assert!(hold(PromptChange::End));
        })
        .await;
        assert_eq!(held, Some(PromptChange::End));
        // Outside a call nothing is held: the caller sends at once.
        assert!(!hold(PromptChange::End));
        // The answer comes first, the dialog after it, in one script.
        let s = answer_then_prompt(&answer_script("saved", false), Some(&show));
        let lines: Vec<&str> = s.lines().collect();
        assert!(lines[0].starts_with("RESPOND PREFIX=klipcal"), "{s}");
        assert!(lines[1].contains("action:prompt_begin"), "{s}");
        assert_eq!(answer_then_prompt("", None), "");
    }
}
