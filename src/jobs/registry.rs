//! The calibrations the daemon runs, each behind the [`Calibration`] trait, and
//! [`Calibrations`]: routes a remote method to the calibration that owns it, cancels the active
//! session whatever its kind, resumes after a restart, builds the status (the active session
//! of any kind and the last result of each kind), and guards the heaters of every kind with
//! one hold-limit watchdog.

use std::sync::Arc;
use std::time::Duration;

use futures_util::future::BoxFuture;
use serde_json::{json, Map, Value};
use tracing::{info, warn};

use super::args::Args;
use super::session::{hold_expired, now_unix, Core};
use super::user;
use crate::store::SessionRow;

/// What the hold-limit watchdog needs of a waiting session.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Hold {
    /// Unix time the hold started (the print's end, …).
    pub since_unix: f64,
    /// Longest hold, s.
    pub max_s: f64,
}

/// One calibration: its remote methods, its session's resume, cancel and status.
pub trait Calibration: Send + Sync {
    /// The store's kind (`ab`, `mesh`, `backlash`).
    fn kind(&self) -> &'static str;
    /// How a user calls it, with its article ("an A/B calibration").
    fn title(&self) -> &'static str;
    /// The remote methods it answers.
    fn methods(&self) -> &'static [&'static str];
    /// Answers one of [`Calibration::methods`].
    fn call<'a>(&'a self, method: &'a str, args: &'a Value)
        -> BoxFuture<'a, anyhow::Result<Value>>;
    /// Picks its session up after a daemon start or reconnect.
    fn resume<'a>(&'a self, row: &'a SessionRow) -> BoxFuture<'a, ()>;
    /// Ends its session safely (prints cancelled, heaters off, prompt closed).
    fn cancel<'a>(
        &'a self,
        row: &'a SessionRow,
        reason: &'a str,
    ) -> BoxFuture<'a, anyhow::Result<Value>>;
    /// Its session as `klipcal_status` shows it.
    ///
    /// # Errors
    /// A damaged document.
    fn status(&self, row: &SessionRow) -> anyhow::Result<Value>;
    /// When its session holds heaters on while waiting on the user: since when, how long.
    fn held(&self, row: &SessionRow) -> Option<Hold>;
    /// Records that the hold limit turned the heaters off.
    fn heaters_turned_off<'a>(&'a self, row: &'a SessionRow) -> BoxFuture<'a, ()>;
    /// Runs once the daemon is connected (e.g. a follower the settings switch on).
    fn connected(&self) -> BoxFuture<'_, ()> {
        Box::pin(async {})
    }
}

/// The methods every daemon answers besides the calibrations' own.
pub const COMMON_METHODS: &[&str] = &["klipcal_status", "klipcal_cancel", "klipcal_prompt_back"];

/// Every remote method the daemon registers with Moonraker.
#[must_use]
pub fn all_methods() -> Vec<String> {
    COMMON_METHODS
        .iter()
        .chain(super::ab::METHODS)
        .chain(super::backlash::METHODS)
        .chain(super::mesh::METHODS)
        .map(|s| (*s).to_string())
        .collect()
}

/// The daemon's calibrations over one core.
#[derive(Clone)]
pub struct Calibrations {
    core: Core,
    list: Vec<Arc<dyn Calibration>>,
}

impl Calibrations {
    /// Every calibration klipcal has, over `core`, each with its own sections of the settings.
    #[must_use]
    pub fn new(core: Core, config: &crate::config::Config) -> Self {
        let list: Vec<Arc<dyn Calibration>> = vec![
            Arc::new(super::ab::Ab::new(
                core.clone(),
                super::ab::AbSettings {
                    defaults: config.ab.clone(),
                    soak: config.soak.clone(),
                },
            )),
            Arc::new(super::backlash::Backlash::new(
                core.clone(),
                config.backlash.clone(),
            )),
            Arc::new(super::mesh::Mesh::new(
                core.clone(),
                config.mesh.clone(),
                config.soak.clone(),
            )),
        ];
        for c in &list {
            core.register_kind(c.kind(), c.title());
        }
        Self { core, list }
    }

    /// The shared core.
    #[must_use]
    pub fn core(&self) -> &Core {
        &self.core
    }

    fn by_kind(&self, kind: &str) -> Option<&Arc<dyn Calibration>> {
        self.list.iter().find(|c| c.kind() == kind)
    }

    /// Whether `method` is one of the calibrations' or the common ones.
    #[must_use]
    pub fn knows(&self, method: &str) -> bool {
        COMMON_METHODS.contains(&method) || self.list.iter().any(|c| c.methods().contains(&method))
    }

    /// Answers a remote method (except `klipcal_status`, which the agent builds with the
    /// printer summary around [`Calibrations::status`]).
    ///
    /// # Errors
    /// The calibration's error (user errors say what was wrong and what is expected).
    pub async fn call(&self, method: &str, args: &Value) -> anyhow::Result<Value> {
        match method {
            "klipcal_cancel" => {
                let a = Args::parse(args, "KLIPCAL_CANCEL", &["reason"])?;
                let reason = a
                    .text("reason")
                    .unwrap_or_else(|| "cancelled by the user".into());
                self.cancel(&reason).await
            }
            "klipcal_prompt_back" => {
                Args::parse(args, "KLIPCAL_PROMPT_BACK", &[])?;
                Ok(if self.core.prompt_again().await {
                    json!({"message": ""})
                } else {
                    self.core.prompt_end().await;
                    json!({"message": "no klipcal dialog to go back to"})
                })
            }
            "klipcal_prompt_close" => {
                self.core.prompt_end().await;
                Ok(
                    json!({"message": "prompt closed; type readings on the console (KLIPCAL_MEASURE) or on klipcal's page"}),
                )
            }
            _ => match self.list.iter().find(|c| c.methods().contains(&method)) {
                Some(c) => c.call(method, args).await,
                None => Err(user(format!("unknown method {method}"))),
            },
        }
    }

    /// Cancels the active session, whatever its kind.
    ///
    /// # Errors
    /// No session to cancel.
    pub async fn cancel(&self, reason: &str) -> anyhow::Result<Value> {
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
        let c = self
            .by_kind(&row.kind)
            .ok_or_else(|| anyhow::anyhow!("session {} has unknown kind {}", row.id, row.kind))?;
        c.cancel(&row, reason).await
    }

    /// Resumes the active session after a daemon start or a reconnect.
    pub async fn resume(&self) {
        for c in &self.list {
            c.connected().await;
        }
        let row = match self.core.active() {
            Ok(Some(r)) => r,
            Ok(None) => return,
            Err(e) => {
                warn!(error = %e, "cannot read the active session");
                return;
            }
        };
        match self.by_kind(&row.kind) {
            Some(c) => c.resume(&row).await,
            None => warn!(session = row.id, kind = %row.kind, "active session of an unknown kind"),
        }
    }

    /// `session`: the active session of any kind, or else the newest one (so a session that
    /// just ended still shows how); `last`: per kind, its newest session, final or not.
    ///
    /// # Errors
    /// A damaged database.
    pub fn status(&self) -> anyhow::Result<Value> {
        let row = match self.core.active()? {
            Some(row) => Some(row),
            None => self.core.store().latest_session()?,
        };
        let session = match row {
            Some(row) => match self.by_kind(&row.kind) {
                Some(c) => with_kind(c.status(&row)?, &row.kind),
                None => Value::Null,
            },
            None => Value::Null,
        };
        let mut last = Map::new();
        for c in &self.list {
            if let Some(row) = self.core.store().latest_session_of(c.kind())? {
                last.insert(c.kind().into(), with_kind(c.status(&row)?, c.kind()));
            }
        }
        Ok(json!({"session": session, "last": last}))
    }

    /// One session as [`Calibrations::status`] shows it, whatever its state; `None` when there
    /// is no such session.
    ///
    /// # Errors
    /// A damaged database.
    pub fn session(&self, id: i64) -> anyhow::Result<Option<Value>> {
        let Some(row) = self.core.store().session(id)? else {
            return Ok(None);
        };
        Ok(match self.by_kind(&row.kind) {
            Some(c) => Some(with_kind(c.status(&row)?, &row.kind)),
            None => Some(json!({"id": row.id, "kind": row.kind, "state": row.state})),
        })
    }

    /// The newest sessions, at most `limit`, without their documents.
    ///
    /// # Errors
    /// A damaged database.
    pub fn sessions(&self, limit: usize) -> anyhow::Result<Vec<crate::store::SessionSummary>> {
        Ok(self.core.store().sessions(limit)?)
    }

    /// Turns the heaters off once a waiting session's hold limit has passed. Runs until
    /// shutdown.
    pub async fn hold_watchdog(self) {
        loop {
            tokio::select! {
                () = self.core.shutdown().cancelled() => return,
                () = tokio::time::sleep(Duration::from_secs(1)) => {}
            }
            let Ok(Some(row)) = self.core.active() else {
                continue;
            };
            let Some(c) = self.by_kind(&row.kind) else {
                continue;
            };
            let Some(hold) = c.held(&row) else { continue };
            if !hold_expired(Some(hold.since_unix), hold.max_s, now_unix()) {
                continue;
            }
            info!(session = row.id, "hold limit reached: heaters off");
            if self.core.heaters_off().await.is_ok() {
                c.heaters_turned_off(&row).await;
            }
        }
    }
}

fn with_kind(mut v: Value, kind: &str) -> Value {
    if let Value::Object(o) = &mut v {
        o.insert("kind".into(), json!(kind));
    }
    v
}

#[cfg(test)]
mod tests {
    use super::*;

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
        let mut out: Vec<(String, String)> = Vec::new();
        for line in MACROS.lines() {
            if let Some(name) = line
                .strip_prefix("[gcode_macro ")
                .and_then(|l| l.strip_suffix(']'))
            {
                out.push((name.to_string(), String::new()));
            } else if let Some(last) = out.last_mut() {
                if line.starts_with("  ") {
                    last.1.push_str(line.trim());
                    last.1.push('\n');
                }
            }
        }
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
    fn every_macro_says_it_asked_and_calls_a_registered_method() {
        let methods = all_methods();
        for (name, gcode) in macros() {
            if let Some(call) = gcode.split("action_call_remote_method(\"").nth(1) {
                let method: String = call.chars().take_while(|c| *c != '"').collect();
                assert!(methods.contains(&method), "{name} calls {method}");
                // Said by Klipper itself, before the call goes out (issue 9 item 9).
                let asked = gcode.lines().position(|l| {
                    l.trim_start().starts_with("RESPOND ")
                        && l.contains("MSG=\"asking the klipcal service...\"")
                });
                let calls = gcode
                    .lines()
                    .position(|l| l.contains("action_call_remote_method("));
                assert!(
                    asked.is_some() && asked < calls,
                    "{name} gives no feedback when the service is down"
                );
            }
        }
        let readme = include_str!("../../README.md");
        let trouble = readme
            .split("## Troubleshooting")
            .nth(1)
            .expect("README has no Troubleshooting section");
        assert!(
            trouble.contains("asking the klipcal service...") && trouble.contains("Unknown method"),
            "README's troubleshooting does not name a macro without the service"
        );
        for m in &methods {
            assert!(MACROS.contains(&format!("\"{m}\"")), "no macro calls {m}");
        }
    }
}
