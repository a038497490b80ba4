//! The agent's remote methods: what macros (via `action_call_remote_method`) and HTTP callers
//! (via Moonraker's `/server/extensions/request`) can ask of the daemon. A macro gets no reply,
//! so its answer goes to the console with `RESPOND`; an HTTP caller gets JSON.

use serde_json::{json, Value};
use tracing::{info, warn};

use crate::jobs::console::{self, answer_script, holding_prompts};
use crate::jobs::{is_user_error, Calibrations};
use crate::moonraker::{AgentCall, ConnState, Moonraker, RpcError};
use crate::printer;

/// Answers agent calls until the channel closes.
pub async fn serve(
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
/// Unknown method (-32601), no session database (503), a user's mistake (400, the message
/// says what was wrong and what is expected), or the daemon's failure (500).
pub async fn dispatch(
    m: &Moonraker,
    cals: Option<&Calibrations>,
    method: &str,
    args: &Value,
) -> Result<Value, RpcError> {
    let (outcome, change) = holding_prompts(answer(m, cals, method, args)).await;
    if let Some(c) = change {
        console::send_script(m, &c.script()).await;
    }
    outcome
}

/// A call's outcome; its dialog changes are held by the caller (see [`holding_prompts`]).
async fn answer(
    m: &Moonraker,
    cals: Option<&Calibrations>,
    method: &str,
    args: &Value,
) -> Result<Value, RpcError> {
    if crate::jobs::registry::is_core_method(method) {
        // Read whole first: a status call with an unknown argument is refused like any other.
        if crate::jobs::core::CoreCall::parse(method, args).map_err(|e| rpc_error(&e))?
            == crate::jobs::core::CoreCall::Status
        {
            return status(m, cals).await;
        }
    }
    let Some(cals) = cals else {
        return Err(RpcError {
            code: 503,
            message: "calibration sessions are not available (no session database)".into(),
        });
    };
    if !cals.knows(method) {
        return Err(RpcError {
            code: -32601,
            message: format!(
                "unknown method `{method}`; known: {}",
                crate::jobs::registry::all_methods().join(", ")
            ),
        });
    }
    cals.call(method, args).await.map_err(|e| rpc_error(&e))
}

/// An outcome as JSON for an HTTP caller: the result with `"ok": true`, or
/// `{"ok": false, "error": {"code", "message"}}` (the console's message).
#[must_use]
pub fn result_json(outcome: Result<Value, RpcError>) -> Value {
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
    let (outcome, change) = holding_prompts(answer(m, cals, &call.method, &call.params)).await;
    let script = match call.responder {
        // Moonraker's HTTP endpoint drops an agent's error message (it answers 424 "Agent
        // klipcal RPC error"), so failures travel as a JSON result the caller can read.
        Some(r) => {
            r.send(Ok(result_json(outcome)));
            change.map(|c| c.script()).unwrap_or_default()
        }
        // A macro's caller reads the console: the answer first, then the dialog, one script.
        None => {
            let text = match &outcome {
                Ok(v) => answer_script(&console_text(&call.method, v), false),
                Err(e) => answer_script(&e.message, true),
            };
            console::answer_then_prompt(&text, change.as_ref())
        }
    };
    if !script.is_empty() {
        if let Err(e) = m.gcode(&script).await {
            warn!(error = %e, "could not answer on the console");
        }
    }
}

/// The status answers at once, whatever Moonraker's state: while it is unreachable, the
/// printer's part is null and `connection` says why (the sessions come from the database).
async fn status(m: &Moonraker, cals: Option<&Calibrations>) -> Result<Value, RpcError> {
    if m.socket_open() {
        // Just connected, still identifying (a call can arrive meanwhile): moments away.
        let _ = m.wait_connected(std::time::Duration::from_secs(2)).await;
    }
    let (connection, summary) = match m.state() {
        ConnState::Connected { klippy_state } => {
            let mut c = json!({"moonraker": "connected", "klippy_state": klippy_state});
            let summary = match printer::gather(m).await {
                Ok(s) => json!(s),
                Err(e) => {
                    c["last_error"] = json!(e.to_string());
                    Value::Null
                }
            };
            (c, summary)
        }
        ConnState::Connecting(why) => (
            json!({"moonraker": "unreachable", "last_error": why,
                   "message": format!("Moonraker is unreachable at {}{}; klipcal keeps \
                                       retrying, and a running session waits for it",
                                      m.url(), why.as_deref().map(|w| format!(" ({w})")).unwrap_or_default())}),
            Value::Null,
        ),
        ConnState::Stopped => (json!({"moonraker": "stopped"}), Value::Null),
    };
    let sessions = match cals {
        Some(c) => c.status().map_err(|e| rpc_error(&e))?,
        None => json!({"session": null, "last": {}}),
    };
    // Where klipcal's page is, or why it is off (its port taken: said here, not only in the log).
    let page = match cals.map(Calibrations::core) {
        Some(core) => match (core.page(), core.page_off()) {
            (Some(address), _) => json!({"address": address}),
            (None, Some(why)) => json!({"off": why}),
            _ => Value::Null,
        },
        None => Value::Null,
    };
    Ok(json!({
        "daemon": {"name": "klipcal", "version": env!("CARGO_PKG_VERSION")},
        "page": page,
        "connection": connection,
        "printer": summary,
        "session": sessions["session"],
        "last": sessions["last"],
    }))
}

fn console_text(method: &str, v: &Value) -> String {
    match method {
        "klipcal_status" => {
            let p = &v["printer"];
            let mut t = format!(
                "klipcal {} connected; Klipper {}",
                v["daemon"]["version"].as_str().unwrap_or("?"),
                p["klippy_state"].as_str().unwrap_or("?")
            );
            if let Some(k) = p["kinematics"].as_str() {
                t.push_str(&format!(", kinematics {k}"));
            }
            if let Some(steppers) = p["steppers"].as_array() {
                for s in steppers {
                    t.push_str(&format!(
                        "\n{} rotation_distance {}",
                        s["name"].as_str().unwrap_or("?"),
                        s["rotation_distance_mm"]
                    ));
                }
            }
            if let Some(why) = v["page"]["off"].as_str() {
                t.push_str(&format!("\nklipcal's page is off: {why}"));
            } else if let Some(address) = v["page"]["address"].as_str() {
                t.push_str(&format!("\npage: {address}"));
            }
            if let Some(sess) = v.get("session").filter(|s| !s.is_null()) {
                let state = sess["state"].as_str().unwrap_or("?");
                t.push_str(&format!("\nsession {}: {state}", sess["id"]));
                // "cancelled — cancelled" said nothing: the progress when it adds to the state,
                // and why a session ended.
                match sess["progress"].as_str() {
                    Some(p) if !p.is_empty() && p != state => t.push_str(&format!(" — {p}")),
                    _ => {}
                }
                if let Some(why) = sess["reason"].as_str().filter(|r| !r.is_empty()) {
                    if sess["progress"].as_str() != Some(why) {
                        t.push_str(&format!(" ({why})"));
                    }
                }
                for m in sess["missing"].as_array().into_iter().flatten() {
                    t.push_str(&format!("\n  {}", m.as_str().unwrap_or("")));
                }
            }
            t
        }
        _ => v["message"]
            .as_str()
            .map_or_else(|| v.to_string(), str::to_string),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_status_answer_on_the_console_names_state_and_rotation_distances() {
        let v = json!({"daemon": {"version": "0.1.0"}, "printer": {"klippy_state": "ready",
            "kinematics": "corexy", "steppers": [{"name": "stepper_x", "rotation_distance_mm": 40.0}]}});
        let t = console_text("klipcal_status", &v);
        assert!(t.contains("Klipper ready"), "{t}");
        assert!(t.contains("stepper_x rotation_distance 40.0"), "{t}");
    }

    #[test]
    fn the_status_says_where_the_page_is_or_why_it_is_off() {
        let v = json!({"daemon": {"version": "0.1.0"}, "printer": {},
            "page": {"off": "another program listens on 0.0.0.0:7150"}});
        let t = console_text("klipcal_status", &v);
        assert!(
            t.contains("klipcal's page is off: another program listens on 0.0.0.0:7150"),
            "{t}"
        );
        let v = json!({"daemon": {}, "printer": {}, "page": {"address": "http://10.0.0.5:7150/"}});
        assert!(console_text("klipcal_status", &v).contains("page: http://10.0.0.5:7150/"));
    }

    #[test]
    fn a_finished_session_on_the_console_says_why_not_its_state_twice() {
        let v = json!({"daemon": {"version": "0.1.0"}, "printer": {"klippy_state": "ready"},
            "session": {"id": 3, "state": "cancelled", "progress": "cancelled",
                        "reason": "cancelled by the user"}});
        let t = console_text("klipcal_status", &v);
        assert!(
            t.contains("session 3: cancelled (cancelled by the user)"),
            "{t}"
        );
        assert!(!t.contains("cancelled — cancelled"), "{t}");
        let v = json!({"daemon": {}, "printer": {}, "session": {"id": 4, "state": "soaking",
            "progress": "bed at 60 °C, settling", "reason": null}});
        let t = console_text("klipcal_status", &v);
        assert!(
            t.contains("session 4: soaking — bed at 60 °C, settling"),
            "{t}"
        );
    }
}
