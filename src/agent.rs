//! The agent's remote methods: what macros (via `action_call_remote_method`) and HTTP callers
//! (via Moonraker's `/server/extensions/request`) can ask of the daemon. A macro gets no reply,
//! so its answer goes to the console with `RESPOND`; an HTTP caller gets JSON.

use serde_json::{json, Value};
use tracing::info;

use crate::jobs::console::{self, answer_script, holding_prompts};
use crate::jobs::core::status::SessionsStatus;
use crate::jobs::core::CoreCall;
use crate::jobs::{is_user_error, Calibrations, Call, Route};
use crate::moonraker::{AgentCall, ConnState, Moonraker, RpcError};
use crate::printer;

/// Answers agent calls until the channel closes.
pub(crate) async fn serve(
    m: Moonraker,
    cals: Option<Calibrations>,
    mut calls: tokio::sync::mpsc::UnboundedReceiver<AgentCall>,
) {
    while let Some(call) = calls.recv().await {
        let m = m.clone();
        let cals = cals.clone();
        tokio::spawn(async move { handle(&m, cals.as_ref(), call).await });
    }
}

fn rpc_error(e: &anyhow::Error) -> RpcError {
    RpcError {
        code: if is_user_error(e) { 400 } else { 500 },
        message: format!("{e:#}"),
    }
}

/// The one entry point for every operation, behind the remote methods and the HTTP API alike:
/// the same requests, checks and messages.
///
/// # Errors
/// No session database (503), a user's mistake (400, the message
/// says what was wrong and what is expected), or the daemon's failure (500).
pub(crate) async fn dispatch(
    m: &Moonraker,
    cals: Option<&Calibrations>,
    route: Route,
    args: &Value,
) -> Result<Value, RpcError> {
    let method = route.spec.method.unwrap_or(route.spec.macro_name);
    let (outcome, change) = holding_prompts(answer(m, cals, method, Some(route), args)).await;
    if let Some(c) = change {
        console::send_script(m, &c.script()).await;
    }
    outcome.and_then(Answer::into_json)
}

/// What an operation answers: the status, typed (the console's summary reads its fields), or
/// another operation's JSON.
enum Answer {
    Status(Box<StatusAnswer>),
    Json(Value),
}

impl Answer {
    fn into_json(self) -> Result<Value, RpcError> {
        match self {
            Answer::Status(a) => {
                serde_json::to_value(a).map_err(|e| rpc_error(&anyhow::Error::from(e)))
            }
            Answer::Json(v) => Ok(v),
        }
    }

    /// The answer on the console, for a macro's caller.
    fn console_text(&self) -> String {
        match self {
            Answer::Status(a) => status_text(a),
            Answer::Json(v) => v["message"]
                .as_str()
                .map_or_else(|| v.to_string(), str::to_string),
        }
    }
}

/// A call's outcome; its dialog changes are held by the caller (see [`holding_prompts`]).
/// `route` is the method's operation (`None`: not one of klipcal's).
async fn answer(
    m: &Moonraker,
    cals: Option<&Calibrations>,
    method: &str,
    route: Option<Route>,
    args: &Value,
) -> Result<Answer, RpcError> {
    if let Some(route) = route.filter(|r| r.spec.by_agent) {
        // Read whole first: a status call with an unknown argument is refused like any other.
        // (The other calls are read after a dialog button's question number is taken out.)
        if route.parse(args).map_err(|e| rpc_error(&e))? == Call::Core(CoreCall::Status) {
            // The status answers at once, whatever Moonraker's state: while it is unreachable,
            // the printer's part is null and `connection` says why (the sessions come from
            // the database).
            return Ok(Answer::Status(Box::new(status_answer(m, cals).await?)));
        }
    }
    let Some(cals) = cals else {
        return Err(RpcError {
            code: 503,
            message: "calibration sessions are not available (no session database)".into(),
        });
    };
    let Some(route) = route else {
        return Err(RpcError {
            code: -32601,
            message: format!(
                "unknown method `{method}`; known: {}",
                crate::jobs::registry::all_methods().join(", ")
            ),
        });
    };
    // A dialog's button carries its question's number: a press of a dialog klipcal no longer
    // asks is refused before it acts (issue 40).
    let call = async {
        let args = cals.core().take_ask(args, route.spec.macro_name).await?;
        route.parse(&args)
    };
    match call.await {
        Ok(call) => cals.call(call).await,
        Err(e) => Err(e),
    }
    .map(Answer::Json)
    .map_err(|e| rpc_error(&e))
}

/// An outcome as JSON for an HTTP caller: the result with `"ok": true`, or
/// `{"ok": false, "error": {"code", "message"}}` (the console's message).
#[must_use]
pub(crate) fn result_json(outcome: Result<Value, RpcError>) -> Value {
    match outcome {
        Ok(Value::Object(mut o)) => {
            o.insert("ok".into(), json!(true));
            Value::Object(o)
        }
        Ok(other) => json!({"ok": true, "result": other}),
        Err(e) => json!({"ok": false, "error": {"code": e.code, "message": e.message}}),
    }
}

async fn handle(m: &Moonraker, cals: Option<&Calibrations>, call: AgentCall) {
    info!(method = %call.method, from = if call.responder.is_some() { "http" } else { "macro" }, "agent call");
    let route = Route::of_method(&call.method);
    let (outcome, change) =
        holding_prompts(answer(m, cals, &call.method, route, &call.params)).await;
    let script = match call.responder {
        // Moonraker's HTTP endpoint drops an agent's error message (it answers 424 "Agent
        // klipcal RPC error"), so failures travel as a JSON result the caller can read.
        Some(r) => {
            r.send(Ok(result_json(outcome.and_then(Answer::into_json))));
            change.map(|c| c.script()).unwrap_or_default()
        }
        // A macro's caller reads the console: the answer first, then the dialog, one script.
        None => {
            let text = match &outcome {
                Ok(a) => answer_script(&a.console_text(), false),
                Err(e) => answer_script(&e.message, true),
            };
            console::answer_then_prompt(&text, change.as_ref())
        }
    };
    console::send_script(m, &script).await;
}

/// `klipcal_status`'s answer (the agent's, `/api/status`'s and the page's).
#[derive(Debug, Clone, serde::Serialize)]
pub(crate) struct StatusAnswer {
    /// klipcal's name and version.
    pub daemon: DaemonInfo,
    /// Where klipcal's page is, or why it is off; `None` without sessions or page.
    pub page: Option<PageInfo>,
    /// Moonraker's connection.
    pub connection: Connection,
    /// The printer's summary; `None` while Moonraker is unreachable or it cannot be read.
    pub printer: Option<printer::Summary>,
    /// The sessions: the active (or newest) one and each kind's last.
    #[serde(flatten)]
    pub sessions: SessionsStatus,
}

/// Where klipcal's page is (`{"address"}`), or why it is off (`{"off"}`).
#[derive(Debug, Clone, serde::Serialize)]
pub(crate) struct PageInfo {
    /// The page's address.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub address: Option<String>,
    /// Why the page is off.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub off: Option<String>,
}

/// klipcal's name and version.
#[derive(Debug, Clone, serde::Serialize)]
pub(crate) struct DaemonInfo {
    /// `klipcal`.
    pub name: &'static str,
    /// The crate's version.
    pub version: &'static str,
}

/// Moonraker's connection as the status shows it.
#[derive(Debug, Clone, Default, serde::Serialize)]
pub(crate) struct Connection {
    /// `connected`, `unreachable` or `stopped`.
    pub moonraker: &'static str,
    /// Klipper's state, when connected.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub klippy_state: Option<String>,
    /// The last error (present, maybe null, while unreachable; present when the summary
    /// failed).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub last_error: Option<Option<String>>,
    /// What unreachable means for a user, in words.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub message: Option<String>,
}

async fn status_answer(
    m: &Moonraker,
    cals: Option<&Calibrations>,
) -> Result<StatusAnswer, RpcError> {
    if m.socket_open() {
        // Just connected, still identifying (a call can arrive meanwhile): moments away.
        let _ = m.wait_connected(std::time::Duration::from_secs(2)).await;
    }
    let (connection, summary) = match m.state() {
        ConnState::Connected { klippy_state } => {
            let mut c = Connection {
                moonraker: "connected",
                klippy_state: Some(klippy_state),
                ..Connection::default()
            };
            let summary = match printer::gather(m).await {
                Ok(s) => Some(s),
                Err(e) => {
                    c.last_error = Some(Some(e.to_string()));
                    None
                }
            };
            (c, summary)
        }
        ConnState::Connecting(why) => (
            Connection {
                moonraker: "unreachable",
                message: Some(format!(
                    "Moonraker is unreachable at {}{}; klipcal keeps retrying, and a running \
                     session waits for it",
                    m.url(),
                    why.as_deref()
                        .map(|w| format!(" ({w})"))
                        .unwrap_or_default()
                )),
                last_error: Some(why),
                ..Connection::default()
            },
            None,
        ),
        ConnState::Stopped => (
            Connection {
                moonraker: "stopped",
                ..Connection::default()
            },
            None,
        ),
    };
    let sessions = match cals {
        Some(c) => c.status().map_err(|e| rpc_error(&e))?,
        None => SessionsStatus::default(),
    };
    // Where klipcal's page is, or why it is off (its port taken: said here, not only in the log).
    let page = cals
        .map(Calibrations::core)
        .and_then(|core| match (core.page(), core.page_off()) {
            (Some(address), _) => Some(PageInfo {
                address: Some(address.to_string()),
                off: None,
            }),
            (None, Some(why)) => Some(PageInfo {
                address: None,
                off: Some(why.to_string()),
            }),
            _ => None,
        });
    Ok(StatusAnswer {
        daemon: DaemonInfo {
            name: "klipcal",
            version: env!("CARGO_PKG_VERSION"),
        },
        page,
        connection,
        printer: summary,
        sessions,
    })
}

/// The status on the console: klipcal and Klipper, the steppers' rotation_distance, the
/// page, and the session with its progress, why it ended and what it still needs.
fn status_text(a: &StatusAnswer) -> String {
    let p = a.printer.as_ref();
    let mut t = format!(
        "klipcal {} connected; Klipper {}",
        a.daemon.version,
        p.map_or("?", |p| p.klippy_state.as_str())
    );
    if let Some(k) = p.and_then(|p| p.kinematics.as_deref()) {
        t.push_str(&format!(", kinematics {k}"));
    }
    for s in p.map(|p| p.steppers.as_slice()).unwrap_or_default() {
        // As JSON writes it (40.0, null), as it always read.
        t.push_str(&format!(
            "\n{} rotation_distance {}",
            s.name,
            Value::from(s.rotation_distance_mm)
        ));
    }
    match &a.page {
        Some(PageInfo { off: Some(why), .. }) => {
            t.push_str(&format!("\nklipcal's page is off: {why}"));
        }
        Some(PageInfo {
            address: Some(address),
            ..
        }) => t.push_str(&format!("\npage: {address}")),
        _ => {}
    }
    if let Some(sess) = &a.sessions.session {
        let h = &sess.head;
        // "cancelled — cancelled" and "solved — solved; apply with …" said the state twice:
        // a progress that begins with the state stands for it, and why a session ended.
        let starts_with_state = h
            .progress
            .strip_prefix(h.state.as_str())
            .is_some_and(|rest| {
                rest.is_empty() || rest.starts_with(|c: char| !c.is_alphanumeric() && c != '_')
            });
        if starts_with_state {
            t.push_str(&format!("\nsession {}: {}", h.id, h.progress));
        } else {
            t.push_str(&format!("\nsession {}: {}", h.id, h.state));
            if !h.progress.is_empty() {
                t.push_str(&format!(" — {}", h.progress));
            }
        }
        if let Some(why) = h.reason.as_deref().filter(|r| !r.is_empty()) {
            if h.progress != why {
                t.push_str(&format!(" ({why})"));
            }
        }
        for m in &sess.console_lines {
            t.push_str(&format!("\n  {m}"));
        }
    }
    if let Some(soak) = &a.sessions.soak {
        if let Some(live) = &soak.live {
            t.push_str(&format!("\nbed soak: {}", live.derivation));
        }
        if let Some(q) = &soak.question {
            let answers: Vec<String> = q
                .answers
                .iter()
                .map(|a| {
                    format!(
                        "{}: KLIPCAL_SOAK_BED {}={}",
                        a.label,
                        a.arg.to_uppercase(),
                        a.value
                    )
                })
                .collect();
            t.push_str(&format!(
                "\nklipcal asks: {} {} ({})",
                q.title,
                q.text,
                answers.join(", ")
            ));
        }
    }
    t
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::jobs::core::envelope::StatusHead;
    use crate::jobs::core::status::SessionStatus;

    fn answer(printer: Option<printer::Summary>) -> StatusAnswer {
        StatusAnswer {
            daemon: DaemonInfo {
                name: "klipcal",
                version: "0.1.0",
            },
            page: None,
            connection: Connection::default(),
            printer,
            sessions: SessionsStatus::default(),
        }
    }

    fn ready() -> printer::Summary {
        printer::Summary {
            klippy_state: "ready".into(),
            ..printer::Summary::default()
        }
    }

    fn session(id: i64, state: &str, progress: &str, reason: Option<&str>) -> SessionStatus {
        let head = StatusHead {
            id,
            state: state.into(),
            progress: progress.into(),
            reason: reason.map(str::to_string),
            notes: vec![],
            finished: false,
        };
        SessionStatus::new("ab", head, &json!({})).unwrap()
    }

    #[test]
    fn the_status_answer_on_the_console_names_state_and_rotation_distances() {
        let a = answer(Some(printer::Summary {
            kinematics: Some("corexy".into()),
            steppers: vec![printer::Stepper {
                name: "stepper_x".into(),
                rotation_distance_mm: Some(40.0),
                ..printer::Stepper::default()
            }],
            ..ready()
        }));
        let t = Answer::Status(Box::new(a)).console_text();
        assert_eq!(
            t,
            "klipcal 0.1.0 connected; Klipper ready, kinematics corexy\n\
             stepper_x rotation_distance 40.0"
        );
        // Moonraker unreachable: no printer part.
        assert_eq!(
            status_text(&answer(None)),
            "klipcal 0.1.0 connected; Klipper ?"
        );
    }

    #[test]
    fn the_status_says_where_the_page_is_or_why_it_is_off() {
        let mut a = answer(Some(printer::Summary::default()));
        a.page = Some(PageInfo {
            address: None,
            off: Some("another program listens on 0.0.0.0:7150".into()),
        });
        let t = status_text(&a);
        assert!(
            t.contains("klipcal's page is off: another program listens on 0.0.0.0:7150"),
            "{t}"
        );
        a.page = Some(PageInfo {
            address: Some("http://10.0.0.5:7150/".into()),
            off: None,
        });
        assert!(status_text(&a).contains("page: http://10.0.0.5:7150/"));
    }

    #[test]
    fn a_finished_session_on_the_console_says_why_not_its_state_twice() {
        let mut a = answer(Some(ready()));
        a.sessions.session = Some(session(
            3,
            "cancelled",
            "cancelled",
            Some("cancelled by the user"),
        ));
        let t = status_text(&a);
        assert!(
            t.contains("session 3: cancelled (cancelled by the user)"),
            "{t}"
        );
        assert!(!t.contains("cancelled — cancelled"), "{t}");
        a.sessions.session = Some(session(4, "soaking", "bed at 60 °C, settling", None));
        let t = status_text(&a);
        assert!(
            t.contains("session 4: soaking — bed at 60 °C, settling"),
            "{t}"
        );
        // Issue 40: "solved — solved; apply with …".
        a.sessions.session = Some(session(
            5,
            "solved",
            "solved; apply with KLIPCAL_AB_APPLY",
            None,
        ));
        let t = status_text(&a);
        assert!(
            t.contains("session 5: solved; apply with KLIPCAL_AB_APPLY"),
            "{t}"
        );
        assert!(!t.contains("solved — solved"), "{t}");
    }

    #[test]
    fn the_readings_still_missing_are_listed_under_the_session() {
        let mut a = answer(Some(ready()));
        a.sessions.session = Some(
            session(5, "measuring", "waiting for caliper readings", None)
                .with_console_lines(vec!["A-D1: 3 more".into(), "A-D2: 5 more".into()]),
        );
        let t = status_text(&a);
        assert!(
            t.ends_with("session 5: measuring — waiting for caliper readings\n  A-D1: 3 more\n  A-D2: 5 more"),
            "{t}"
        );
        // Not in the JSON: the A/B body has them as `missing`.
        let v = Answer::Status(Box::new(a)).into_json().unwrap();
        assert!(v["session"].get("console_lines").is_none(), "{v}");
    }

    #[test]
    fn another_operation_answers_the_console_with_its_message() {
        let a = Answer::Json(json!({"session": 2, "message": "session 2 started"}));
        assert_eq!(a.console_text(), "session 2 started");
        let a = Answer::Json(json!({"following": false}));
        assert_eq!(a.console_text(), "{\"following\":false}");
    }
}
