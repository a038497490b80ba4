//! The agent's remote methods: what macros (via `action_call_remote_method`) and HTTP callers
//! (via Moonraker's `/server/extensions/request`) can ask of the daemon. A macro gets no reply,
//! so its answer goes to the console with `RESPOND`; an HTTP caller gets JSON.

use serde_json::{json, Value};
use tracing::{info, warn};

use crate::jobs::ab::is_user_error;
use crate::jobs::Jobs;
use crate::klipper::gcode_cmd::{self, GcodeCmd};
use crate::moonraker::{AgentCall, ConnState, Moonraker, RpcError};
use crate::printer;

/// Every remote method the daemon registers.
pub const METHODS: &[&str] = &[
    "klipcal_status",
    "klipcal_ab_start",
    "klipcal_measure",
    "klipcal_solve",
    "klipcal_apply",
    "klipcal_cancel",
];

/// Answers agent calls until the channel closes.
pub async fn serve(
    m: Moonraker,
    jobs: Option<Jobs>,
    mut calls: tokio::sync::mpsc::UnboundedReceiver<AgentCall>,
) {
    while let Some(call) = calls.recv().await {
        let m = m.clone();
        let jobs = jobs.clone();
        tokio::spawn(async move { handle(&m, jobs.as_ref(), call).await });
    }
}

fn rpc_error(e: &anyhow::Error) -> RpcError {
    RpcError {
        code: if is_user_error(e) { 400 } else { 500 },
        message: format!("{e:#}"),
    }
}

async fn job_call(jobs: Option<&Jobs>, method: &str, args: &Value) -> Result<Value, RpcError> {
    let Some(jobs) = jobs else {
        return Err(RpcError {
            code: 503,
            message: "calibration sessions are not available (no session database)".into(),
        });
    };
    let r = match method {
        "klipcal_ab_start" => jobs.start(args).await,
        "klipcal_measure" => jobs.measure(args).await,
        "klipcal_solve" => jobs.solve().await,
        "klipcal_apply" => jobs.apply(args).await,
        "klipcal_cancel" => jobs.cancel(args).await,
        _ => unreachable!("only job methods are routed here"),
    };
    r.map_err(|e| rpc_error(&e))
}

async fn handle(m: &Moonraker, jobs: Option<&Jobs>, call: AgentCall) {
    info!(method = %call.method, from = if call.responder.is_some() { "http" } else { "macro" }, "agent call");
    let outcome = match call.method.as_str() {
        "klipcal_status" => status(m, jobs).await,
        "klipcal_ab_start" | "klipcal_measure" | "klipcal_solve" | "klipcal_apply"
        | "klipcal_cancel" => job_call(jobs, &call.method, &call.params).await,
        other => Err(RpcError {
            code: -32601,
            message: format!("unknown method `{other}`; known: {}", METHODS.join(", ")),
        }),
    };
    match call.responder {
        // Moonraker's HTTP endpoint drops an agent's error message (it answers 424 "Agent
        // klipcal RPC error"), so failures travel as a JSON result the caller can read.
        Some(r) => r.send(Ok(match outcome {
            Ok(Value::Object(mut o)) => {
                o.insert("ok".into(), json!(true));
                Value::Object(o)
            }
            Ok(other) => json!({"ok": true, "result": other}),
            Err(e) => json!({"ok": false, "error": {"code": e.code, "message": e.message}}),
        })),
        None => {
            let text = match &outcome {
                Ok(v) => console_text(&call.method, v),
                Err(e) => format!("error: {}", e.message),
            };
            for line in text.lines() {
                if let Err(e) = m.gcode(&respond_line(line)).await {
                    warn!(error = %e, "could not answer on the console");
                    break;
                }
            }
        }
    }
}

async fn status(m: &Moonraker, jobs: Option<&Jobs>) -> Result<Value, RpcError> {
    let summary = printer::gather(m).await.map_err(|e| RpcError {
        code: 503,
        message: e.to_string(),
    })?;
    let connection = match m.state() {
        ConnState::Connected { klippy_state } => {
            json!({"moonraker": "connected", "klippy_state": klippy_state})
        }
        ConnState::Connecting(why) => json!({"moonraker": "connecting", "last_error": why}),
        ConnState::Stopped => json!({"moonraker": "stopped"}),
    };
    Ok(json!({
        "daemon": {"name": "klipcal", "version": env!("CARGO_PKG_VERSION")},
        "connection": connection,
        "printer": summary,
        "session": match jobs {
            Some(j) => j.status().map_err(|e| rpc_error(&e))?,
            None => Value::Null,
        },
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
            if let Some(sess) = v.get("session").filter(|s| !s.is_null()) {
                t.push_str(&format!(
                    "\nsession {}: {} — {}",
                    sess["id"],
                    sess["state"].as_str().unwrap_or("?"),
                    sess["progress"].as_str().unwrap_or("")
                ));
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

/// `RESPOND PREFIX=klipcal MSG="…"`, the message made safe for Klipper's parser (characters
/// that would end or break the command are replaced).
fn respond_line(msg: &str) -> String {
    GcodeCmd::new("RESPOND")
        .word("PREFIX", gcode_cmd::RESPOND_PREFIX)
        .text_lossy("MSG", msg)
        .build()
        .unwrap_or_else(|_| "RESPOND PREFIX=klipcal MSG=\"(unprintable answer)\"".to_string())
}

#[cfg(test)]
mod tests {
    use super::*;

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
    fn the_status_answer_on_the_console_names_state_and_rotation_distances() {
        let v = json!({"daemon": {"version": "0.1.0"}, "printer": {"klippy_state": "ready",
            "kinematics": "corexy", "steppers": [{"name": "stepper_x", "rotation_distance_mm": 40.0}]}});
        let t = console_text("klipcal_status", &v);
        assert!(t.contains("Klipper ready"), "{t}");
        assert!(t.contains("stepper_x rotation_distance 40.0"), "{t}");
    }
}
