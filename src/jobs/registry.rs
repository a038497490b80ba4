//! The calibrations the daemon runs, each held by its type, and [`Calibrations`]: answers a
//! typed [`Call`] (matched, no trait object), cancels the active session whatever its kind,
//! resumes after a restart, builds the status (the active session of any kind and the last
//! result of each kind), and guards the heaters of every kind with one hold-limit watchdog.
//! The routing of a method or a path to its call is `jobs::call`.

use std::sync::Arc;
use std::time::Duration;

use std::collections::BTreeMap;

use serde_json::{json, Value};
use tracing::{info, warn};

pub use super::call::all_ops;
pub(crate) use super::call::{all_methods, macros_cfg, operation_paths, Call};
use crate::jobs::core::answer::{reply, Said, SessionAnswer};
use crate::jobs::core::calibration::Declared;
use crate::jobs::core::session::{hold_expired, now_unix, Core};
use crate::jobs::core::soak::SoakSettings;
use crate::jobs::core::status::SessionsStatus;
use crate::jobs::core::{Calibration, CoreCall};
use crate::jobs::user;

use super::ab::Ab;
use super::backlash::Backlash;
use super::mesh::Mesh;

/// The daemon's calibrations over one core.
#[derive(Clone)]
pub struct Calibrations {
    core: Core,
    ab: Arc<Ab>,
    backlash: Arc<Backlash>,
    mesh: Arc<Mesh>,
}

/// A stored session's calibration, by its kind.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Kind {
    Ab,
    Backlash,
    Mesh,
}

impl Kind {
    fn of(kind: &str) -> Option<Self> {
        [Kind::Ab, Kind::Backlash, Kind::Mesh]
            .into_iter()
            .find(|k| k.name() == kind)
    }

    fn name(self) -> &'static str {
        match self {
            Kind::Ab => super::ab::KIND,
            Kind::Backlash => super::backlash::KIND,
            Kind::Mesh => super::mesh::KIND,
        }
    }
}

/// Runs `$body` with `$c` bound to the calibration of `$kind` (a static call on its type).
macro_rules! on_kind {
    ($cals:expr, $kind:expr, |$c:ident| $body:expr) => {
        match $kind {
            Kind::Ab => {
                let $c = &*$cals.ab;
                $body
            }
            Kind::Backlash => {
                let $c = &*$cals.backlash;
                $body
            }
            Kind::Mesh => {
                let $c = &*$cals.mesh;
                $body
            }
        }
    };
}

impl Calibrations {
    /// Every calibration klipcal has, over `core`, each with its own sections of the settings.
    #[must_use]
    pub(crate) fn new(core: Core, config: &crate::config::Config) -> Self {
        // One soak settings for every calibration: an answer to the soak question names the
        // file for all of them.
        let soak = SoakSettings::of(config);
        core.ask_state().settings = Some(soak.clone());
        let cals = Self {
            ab: Arc::new(Ab::new(
                core.clone(),
                super::ab::AbSettings {
                    defaults: config.ab.clone(),
                    soak: soak.clone(),
                },
            )),
            backlash: Arc::new(Backlash::new(core.clone(), config.backlash.clone())),
            mesh: Arc::new(Mesh::new(core.clone(), config.mesh.clone(), soak)),
            core,
        };
        for c in cals.declared() {
            cals.core.register_kind(c.kind(), c.title());
            cals.core.store().add_final_states(c.final_states());
        }
        cals
    }

    /// Each calibration's declaration, in the order the status lists them.
    fn declared(&self) -> [&dyn Declared; 3] {
        [&*self.ab, &*self.backlash, &*self.mesh]
    }

    fn declared_of(&self, kind: &str) -> Option<&dyn Declared> {
        Some(on_kind!(self, Kind::of(kind)?, |c| c as &dyn Declared))
    }

    /// The shared core.
    #[must_use]
    pub(crate) fn core(&self) -> &Core {
        &self.core
    }

    /// The backlash measurement's camera frame kept for the page (`seq`, or the newest), JPEG.
    #[must_use]
    pub fn snapshot_jpeg(&self, seq: Option<u64>) -> Option<Vec<u8>> {
        self.backlash.snapshot_jpeg(seq)
    }

    /// A frame taken now from the nozzle camera (`[backlash] webcam`), JPEG.
    ///
    /// # Errors
    /// The webcam could not be chosen or did not answer (said which and why).
    pub async fn live_jpeg(&self) -> anyhow::Result<Vec<u8>> {
        self.backlash.live_jpeg().await
    }

    /// Answers a typed call (except `klipcal_status`, which the agent builds with the printer
    /// summary around [`Calibrations::status`]).
    ///
    /// # Errors
    /// The calibration's error (user errors say what was wrong and what is expected).
    pub(crate) async fn call(&self, call: Call) -> anyhow::Result<Value> {
        match call {
            Call::Core(c) => self.core_call(c).await,
            Call::Ab(c) => self.ab.handle(c).await,
            Call::Backlash(c) => self.backlash.handle(c).await,
            Call::Mesh(c) => self.mesh.handle(c).await,
        }
    }

    async fn core_call(&self, call: CoreCall) -> anyhow::Result<Value> {
        match call {
            CoreCall::Cancel(reason) => reply(self.cancel(&reason).await),
            CoreCall::SoakBed(a) => reply(crate::jobs::core::soak_ask::answer(&self.core, a).await),
            // The helpers only ask; klipcal closes or replaces the dialog itself, marked as
            // its own before it is sent, so a close klipcal did not send is the user's.
            CoreCall::PromptBack => reply(Ok(if self.core.prompt_again().await {
                Said {
                    message: String::new(),
                }
            } else {
                // The cancel question (shown by Klipper) closes whatever klipcal believes.
                self.core.prompt_end_any().await;
                Said {
                    message: "no klipcal dialog to go back to".into(),
                }
            })),
            CoreCall::PromptClose => {
                self.core.prompt_end_any().await;
                reply(Ok(Said {
                    message: format!(
                        "type readings on the console: KLIPCAL_MEASURE PAIR=... VALUES=... \
                         (or on {})",
                        self.core
                            .page_road()
                            .unwrap_or_else(|| "klipcal's page".into())
                    ),
                }))
            }
            CoreCall::Status => Err(anyhow::anyhow!(
                "klipcal_status is answered by the agent with the printer's summary"
            )),
        }
    }

    /// Cancels the active session, whatever its kind.
    ///
    /// # Errors
    /// No session to cancel.
    pub(crate) async fn cancel(&self, reason: &str) -> anyhow::Result<SessionAnswer> {
        let row = self
            .core
            .active()?
            .ok_or_else(|| user("no calibration session to cancel"))?;
        if let Some(why) = self.core.unreachable_now() {
            // Nothing on the printer can be stopped now: say so rather than mark the session
            // cancelled over a print or heaters still running.
            return Err(user(format!(
                "Moonraker is unreachable ({why}): klipcal cannot stop a print or turn the \
                 heaters off now. Session {} waits for Moonraker and goes on (Klipper's idle \
                 timeout turns the heaters off after the phase's limit if it stays away); \
                 cancel again once Moonraker is back",
                row.id
            )));
        }
        self.core.stop_runner();
        let kind = Kind::of(&row.kind)
            .ok_or_else(|| anyhow::anyhow!("session {} has unknown kind {}", row.id, row.kind))?;
        let answer = on_kind!(self, kind, |c| c.cancel(&row, reason).await);
        // The cancel question's dialog (opened in Klipper) closes with the answer, whatever
        // klipcal believed shown: Fluidd kept "end the session?" open after a cancel.
        self.core.prompt_end_any().await;
        answer
    }

    /// Resumes the active session after a daemon start or a reconnect.
    pub(crate) async fn resume(&self) {
        self.ab.connected().await;
        self.backlash.connected().await;
        self.mesh.connected().await;
        let row = match self.core.active() {
            Ok(Some(r)) => r,
            Ok(None) => return,
            Err(e) => {
                warn!(error = %e, "cannot read the active session");
                return;
            }
        };
        match Kind::of(&row.kind) {
            Some(kind) => on_kind!(self, kind, |c| c.resume(&row).await),
            None => warn!(session = row.id, kind = %row.kind, "active session of an unknown kind"),
        }
    }

    /// `session`: the active session of any kind, or else the newest one (so a session that
    /// just ended still shows how); `last`: per kind, its newest session, final or not.
    ///
    /// # Errors
    /// A damaged database.
    pub(crate) fn status(&self) -> anyhow::Result<SessionsStatus> {
        let row = match self.core.active()? {
            Some(row) => Some(row),
            None => self.core.store().latest_session()?,
        };
        let session = match row {
            Some(row) => match self.declared_of(&row.kind) {
                Some(c) => Some(c.status(&row)?),
                None => None,
            },
            None => None,
        };
        let mut last = BTreeMap::new();
        for c in self.declared() {
            if let Some(row) = self.core.store().latest_session_of(c.kind())? {
                last.insert(c.kind().into(), c.status(&row)?);
            }
        }
        Ok(SessionsStatus {
            session,
            last,
            soak: crate::jobs::core::soak_ask::view(&self.core),
        })
    }

    /// One session as [`Calibrations::status`] shows it, whatever its state; `None` when there
    /// is no such session.
    ///
    /// # Errors
    /// A damaged database.
    pub(crate) fn session(&self, id: i64) -> anyhow::Result<Option<Value>> {
        let Some(row) = self.core.store().session(id)? else {
            return Ok(None);
        };
        Ok(match self.declared_of(&row.kind) {
            Some(c) => Some(serde_json::to_value(c.status(&row)?)?),
            None => Some(json!({"id": row.id, "kind": row.kind, "state": row.state})),
        })
    }

    /// The newest sessions, at most `limit`, without their documents.
    ///
    /// # Errors
    /// A damaged database.
    pub(crate) fn sessions(
        &self,
        limit: usize,
    ) -> anyhow::Result<Vec<crate::store::SessionSummary>> {
        Ok(self.core.store().sessions(limit)?)
    }

    /// Turns the heaters off once a waiting session's hold limit has passed. Runs until
    /// shutdown.
    pub(crate) async fn hold_watchdog(self) {
        loop {
            tokio::select! {
                () = self.core.shutdown().cancelled() => return,
                () = tokio::time::sleep(Duration::from_secs(1)) => {}
            }
            let Ok(Some(row)) = self.core.active() else {
                continue;
            };
            let Some(kind) = Kind::of(&row.kind) else {
                continue;
            };
            let Some(hold) = on_kind!(self, kind, |c| c.held(&row)) else {
                continue;
            };
            if !hold_expired(Some(hold.since_unix), hold.max_s, now_unix()) {
                continue;
            }
            info!(session = row.id, "hold limit reached: heaters off");
            if self.core.heaters_off_reported("the hold limit").await {
                on_kind!(self, kind, |c| c.heaters_turned_off(&row).await);
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::jobs::core::table::{self, ArgKind, OpSpec};
    use serde_json::json;

    const MACROS: &str = include_str!("../../config/klipcal.cfg");

    /// The fields Mainsail and Fluidd offer for a macro: they scan each line of its G-code for
    /// the first `params.NAME` inside a `{ … }` block (so a second one on the same line is
    /// never found).
    fn ui_fields(gcode: &str) -> Vec<String> {
        let mut out = Vec::new();
        for line in gcode.lines() {
            let Some(open) = line.find('{') else { continue };
            let Some(at) = line[open..].find("params.") else {
                continue;
            };
            let name: String = line[open + at + 7..]
                .chars()
                .take_while(|c| c.is_ascii_alphanumeric() || *c == '_')
                .collect();
            out.push(name);
        }
        out
    }

    fn macros() -> Vec<(String, String)> {
        macros_of(MACROS)
    }

    fn macros_of(text: &str) -> Vec<(String, String)> {
        let mut out: Vec<(String, String)> = Vec::new();
        for line in text.lines() {
            if let Some(name) = line
                .strip_prefix("[gcode_macro ")
                .and_then(|l| l.strip_suffix(']'))
            {
                out.push((name.to_string(), String::new()));
            } else if line.starts_with('[') {
                // Another section (`[delayed_gcode _KLIPCAL_OFFLINE]`): no macro's G-code.
                out.push((String::new(), String::new()));
            } else if let Some(last) = out.last_mut() {
                if line.starts_with("  ") {
                    last.1.push_str(line.trim());
                    last.1.push('\n');
                }
            }
        }
        out.retain(|(name, _)| !name.is_empty());
        out
    }

    #[test]
    fn every_macro_parameter_gets_a_field_in_mainsail_and_fluidd() {
        let all = macros();
        let fields = |name: &str| {
            let g = &all.iter().find(|(n, _)| n == name).unwrap().1;
            ui_fields(g)
        };
        assert_eq!(
            fields("KLIPCAL_MEASURE"),
            ["PAIR", "VALUES", "VALUE", "CLEAR"]
        );
        assert_eq!(fields("KLIPCAL_AB_START"), ["BED", "EXTRUDER", "LAYOUT"]);
        assert_eq!(fields("KLIPCAL_AB_APPLY"), ["FORCE"]);
        for (name, gcode) in &all {
            // Every parameter the macro reads is one a UI shows.
            assert_eq!(
                gcode.matches("params.").count(),
                ui_fields(gcode).len(),
                "{name}"
            );
        }
    }

    #[test]
    fn klipcal_cfg_is_the_command_tables_macros() {
        // `klipcal macros > config/klipcal.cfg` writes it again after a change to the table.
        assert_eq!(
            MACROS,
            macros_cfg(),
            "config/klipcal.cfg differs from the command table: run `klipcal macros > config/klipcal.cfg`"
        );
    }

    #[test]
    fn the_docs_table_of_operations_is_the_command_tables() {
        let page = include_str!("../../docs/operations.md");
        let inner = table::between_markers(page).expect("docs/operations.md has no table");
        assert_eq!(
            inner,
            table::markdown(all_ops()),
            "docs/operations.md's operations differ from the command table: \
             `klipcal macros --readme --write docs/operations.md`"
        );
        // Writing it into the page is idempotent and leaves the rest of the page as it was.
        let written = table::with_table(page, &table::markdown(all_ops())).unwrap();
        assert_eq!(written, page);
        let changed = table::with_table(page, "| x |\n").unwrap();
        assert!(changed.contains("<!-- operations -->\n| x |\n<!-- /operations -->"));
        assert_eq!(
            changed.split("| x |").next(),
            page.split("| macro |").next()
        );
        assert!(table::with_table("no markers", "x").is_err());
    }

    #[test]
    fn every_operation_is_declared_once_with_its_own_names() {
        let ops = all_ops();
        let mut seen = std::collections::BTreeSet::new();
        for op in ops {
            for name in [op.method, Some(op.macro_name), op.http]
                .into_iter()
                .flatten()
            {
                assert!(seen.insert(name), "{name} is declared twice");
            }
            assert!(
                op.macro_name.starts_with("KLIPCAL_") || op.macro_name.starts_with("_KLIPCAL_")
            );
            if let Some(m) = op.method {
                assert!(m.starts_with("klipcal_"), "{m}");
                assert!(op.http.is_some(), "{m} has no HTTP path");
            }
            let mut args = std::collections::BTreeSet::new();
            for a in op.args {
                assert!(
                    args.insert(a.name),
                    "{} takes {} twice",
                    op.macro_name,
                    a.name
                );
                assert_eq!(a.name, a.name.to_lowercase());
                assert!(!a.help.is_empty() && !a.expect.is_empty(), "{}", a.name);
                // The declared default is one the argument's own getter accepts.
                if !a.default.is_empty() {
                    let spec: &'static OpSpec = op;
                    let args = table::Args::parse(&json!({}), spec).unwrap();
                    let ok = match a.kind {
                        ArgKind::Number { .. } => args.num(a).is_ok(),
                        ArgKind::Whole { .. } => args.int(a).is_ok(),
                        ArgKind::Flag => args.flag(a).is_ok(),
                        ArgKind::Choice(_) => args.choice(a).is_ok(),
                        ArgKind::Text | ArgKind::Readings => true,
                    };
                    assert!(
                        ok,
                        "{} {}: default {} refused",
                        op.macro_name, a.name, a.default
                    );
                }
            }
        }
        // Every remote method is registered and routed to a calibration or the core.
        assert_eq!(
            all_methods().len(),
            ops.iter().filter(|o| o.method.is_some()).count()
        );
    }

    #[test]
    fn no_macro_line_is_cut_short_by_klippers_gcode_parser() {
        // klippy/gcode.py ends a command at ';' anywhere (also inside a RESPOND message): the
        // macro after it would be malformed. Checked on the generated text and on the file.
        for text in [macros_cfg(), MACROS.to_string()] {
            for (name, gcode) in macros_of(&text) {
                for line in gcode.lines() {
                    assert_eq!(table::gcode_line_problem(line), None, "{name}: {line}");
                }
            }
        }
    }

    #[test]
    fn the_dialogs_helpers_are_hidden_from_the_macro_panels() {
        // Mainsail and Fluidd hide macros whose name starts with '_' (issue 26 A.5): the
        // buttons left are the ones a user presses, the dialogs' helpers are not among them.
        let visible: Vec<&str> = all_ops()
            .iter()
            .map(|o| o.macro_name)
            .filter(|n| !n.starts_with('_'))
            .collect();
        for helper in [
            "_KLIPCAL_PROMPT_BACK",
            "_KLIPCAL_PROMPT_CLOSE",
            "_KLIPCAL_CANCEL_ASK",
            "_KLIPCAL_BACKLASH_JOG",
            "_KLIPCAL_BACKLASH_TIP",
        ] {
            assert!(
                all_ops().iter().any(|o| o.macro_name == helper),
                "{helper} is not declared"
            );
            assert!(!visible.contains(&&helper[1..]), "{helper} shows");
        }
        // 16 a user presses, KLIPCAL_BACKLASH_CAMERA and KLIPCAL_BACKLASH_CLICK (issue 27), and
        // KLIPCAL_SOAK_BED (issue 38: the bed named from the panel, before any soak asks).
        assert!(
            visible.len() <= 19,
            "{} buttons: {visible:?}",
            visible.len()
        );
    }

    #[test]
    fn every_example_can_be_typed_on_a_gcode_line_as_it_is() {
        // Klipper splits parameters at spaces and ends a command at ';', '#' or '*': an example
        // a user copies from a field hint or the docs must arrive whole.
        for op in all_ops() {
            for a in op.args {
                assert!(
                    !a.example.is_empty() && !a.example.contains([' ', ';', '#', '*', '"', '=']),
                    "{} {}={:?}",
                    op.macro_name,
                    a.name.to_uppercase(),
                    a.example
                );
            }
        }
    }

    #[test]
    fn a_semicolon_in_a_macro_message_is_caught() {
        // The defect of issue 25 A.1: MESH_CHECK's RESPOND had "…check; klipcal resumes…".
        let bad = "[gcode_macro X]\ngcode:\n  RESPOND PREFIX=klipcal MSG=\"paused; resumes\"\n";
        let found: Vec<_> = macros_of(bad)
            .iter()
            .flat_map(|(_, g)| {
                g.lines()
                    .filter_map(table::gcode_line_problem)
                    .collect::<Vec<_>>()
            })
            .collect();
        assert_eq!(found.len(), 1);
    }

    #[test]
    fn the_asking_line_waits_on_the_services_word_which_klippers_timer_ends() {
        // Issue 40 item 6: "asking" only while the service has not said it answers; the word
        // (`_KLIPCAL_ONLINE SECONDS=n`) starts the timer whose G-code takes it back.
        for (name, gcode) in macros() {
            if gcode.contains("asking the klipcal service...") {
                assert!(
                    gcode.contains("not printer[\"gcode_macro _KLIPCAL_ONLINE\"].on"),
                    "{name}: {gcode}"
                );
            }
        }
        let online = &macros()
            .into_iter()
            .find(|(n, _)| n == crate::moonraker::ONLINE_MACRO)
            .expect("klipcal.cfg has no _KLIPCAL_ONLINE")
            .1;
        assert!(online.contains("VARIABLE=on VALUE={1 if s > 0 else 0}"));
        assert!(online.contains("UPDATE_DELAYED_GCODE ID=_KLIPCAL_OFFLINE DURATION={s}"));
        let timer = MACROS
            .split("[delayed_gcode _KLIPCAL_OFFLINE]")
            .nth(1)
            .expect("klipcal.cfg has no _KLIPCAL_OFFLINE timer");
        let timer = timer.split("\n[").next().unwrap_or("");
        assert!(
            timer.contains("SET_GCODE_VARIABLE MACRO=_KLIPCAL_ONLINE VARIABLE=on VALUE=0"),
            "{timer}"
        );
    }

    #[test]
    fn every_macro_says_it_asked_and_calls_a_registered_method() {
        let methods = all_methods();
        for (name, gcode) in macros() {
            if let Some(call) = gcode.split("action_call_remote_method(\"").nth(1) {
                let method: String = call.chars().take_while(|c| *c != '"').collect();
                assert!(methods.contains(&method), "{name} calls {method}");
                // Said by Klipper itself, before the call goes out (issue 9 item 9), by every
                // macro a user calls; not by the helpers pressed in klipcal's dialogs (issue 26
                // A.4: a backlash axis's jog presses added a row each).
                let asked = gcode.lines().position(|l| {
                    l.trim_start().starts_with("RESPOND ")
                        && l.contains("MSG=\"asking the klipcal service...\"")
                });
                let calls = gcode
                    .lines()
                    .position(|l| l.contains("action_call_remote_method("));
                if name.starts_with('_') {
                    assert_eq!(asked, None, "{name}, a dialog's helper, says it asks");
                } else {
                    assert!(
                        asked.is_some() && asked < calls,
                        "{name} gives no feedback when the service is down"
                    );
                }
            }
        }
        let trouble = include_str!("../../docs/troubleshooting.md");
        assert!(
            trouble.contains("asking the klipcal service...") && trouble.contains("Unknown method"),
            "docs/troubleshooting.md does not name a macro without the service"
        );
        for m in methods {
            assert!(MACROS.contains(&format!("\"{m}\"")), "no macro calls {m}");
        }
    }
}
