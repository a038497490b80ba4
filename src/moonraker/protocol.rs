//! PURE: Moonraker's JSON-RPC 2.0 frames — building requests and replies, classifying what
//! arrives. No socket, no clock.

use serde_json::{json, Value};

use super::Error;

/// An error object as Moonraker (or we) put it in a JSON-RPC reply.
#[derive(Debug, Clone, PartialEq)]
pub struct RpcError {
    /// JSON-RPC or HTTP-like code (Moonraker uses e.g. 400, 404, -32601).
    pub code: i64,
    /// Moonraker's message.
    pub message: String,
}

/// One frame received from Moonraker, classified.
#[derive(Debug, Clone, PartialEq)]
pub(crate) enum Incoming {
    /// The reply to one of our requests.
    Response {
        /// The id we sent.
        id: u64,
        /// The result, or Moonraker's error.
        outcome: Result<Value, RpcError>,
    },
    /// A notification: Moonraker's `notify_*` events, and remote methods called from Klipper
    /// macros (these carry no id, so no reply can reach the macro).
    Notification {
        /// Method name.
        method: String,
        /// Parameters (`null` when absent).
        params: Value,
    },
    /// A request Moonraker forwards to us as an agent (from `/server/extensions/request`):
    /// it expects a reply carrying the same id.
    Call {
        /// Moonraker's id, echoed back verbatim.
        id: Value,
        /// Method name.
        method: String,
        /// Arguments (`null` when absent).
        params: Value,
    },
}

/// Builds a request frame.
pub(crate) fn request(id: u64, method: &str, params: &Value) -> String {
    let mut frame = json!({"jsonrpc": "2.0", "method": method, "id": id});
    if !params.is_null() {
        frame["params"] = params.clone();
    }
    frame.to_string()
}

/// Builds the reply to a [`Incoming::Call`].
pub(crate) fn reply(id: &Value, outcome: &Result<Value, RpcError>) -> String {
    match outcome {
        // Moonraker treats a null result as an error: send an empty object instead.
        Ok(Value::Null) => json!({"jsonrpc": "2.0", "id": id, "result": {}}).to_string(),
        Ok(v) => json!({"jsonrpc": "2.0", "id": id, "result": v}).to_string(),
        Err(e) => json!({"jsonrpc": "2.0", "id": id,
                          "error": {"code": e.code, "message": e.message}})
        .to_string(),
    }
}

/// Classifies one text frame.
///
/// # Errors
/// [`Error::Protocol`] for text that is not a JSON-RPC 2.0 object.
pub(crate) fn parse(text: &str) -> Result<Incoming, Error> {
    let v: Value = serde_json::from_str(text)
        .map_err(|e| Error::Protocol(format!("frame is not JSON ({e}): {}", clip(text))))?;
    let Value::Object(mut obj) = v else {
        return Err(Error::Protocol(format!(
            "frame is not a JSON object: {}",
            clip(text)
        )));
    };
    let method = obj.remove("method");
    let params = obj.remove("params").unwrap_or(Value::Null);
    let id = obj.remove("id");
    match (method, id) {
        (Some(Value::String(method)), None | Some(Value::Null)) => {
            Ok(Incoming::Notification { method, params })
        }
        (Some(Value::String(method)), Some(id)) => Ok(Incoming::Call { id, method, params }),
        (None, Some(id)) => {
            let id = id.as_u64().ok_or_else(|| {
                Error::Protocol(format!("reply id {id} is not one of ours: {}", clip(text)))
            })?;
            if let Some(err) = obj.remove("error") {
                let code = err.get("code").and_then(Value::as_i64).unwrap_or(0);
                let message = err
                    .get("message")
                    .and_then(Value::as_str)
                    .map_or_else(|| err.to_string(), str::to_string);
                Ok(Incoming::Response {
                    id,
                    outcome: Err(RpcError { code, message }),
                })
            } else {
                let result = obj.remove("result").unwrap_or(Value::Null);
                Ok(Incoming::Response {
                    id,
                    outcome: Ok(result),
                })
            }
        }
        _ => Err(Error::Protocol(format!(
            "frame has neither a method nor an id: {}",
            clip(text)
        ))),
    }
}

fn clip(text: &str) -> String {
    let mut end = text.len().min(200);
    while !text.is_char_boundary(end) {
        end -= 1;
    }
    text[..end].to_string()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_reply_with_a_result_is_matched_by_id() {
        let inc = parse(r#"{"jsonrpc":"2.0","result":{"a":1},"id":7}"#).unwrap();
        assert_eq!(
            inc,
            Incoming::Response {
                id: 7,
                outcome: Ok(json!({"a": 1}))
            }
        );
    }

    #[test]
    fn moonrakers_error_code_and_message_are_kept() {
        let inc = parse(
            r#"{"jsonrpc":"2.0","error":{"code":400,"message":"Klippy Disconnected"},"id":3}"#,
        )
        .unwrap();
        let Incoming::Response { id, outcome } = inc else {
            panic!("not a response")
        };
        assert_eq!(id, 3);
        assert_eq!(
            outcome,
            Err(RpcError {
                code: 400,
                message: "Klippy Disconnected".into()
            })
        );
    }

    #[test]
    fn a_remote_method_from_a_macro_arrives_without_an_id() {
        let inc =
            parse(r#"{"jsonrpc":"2.0","method":"klipcal_status","params":{"x":"1"}}"#).unwrap();
        assert_eq!(
            inc,
            Incoming::Notification {
                method: "klipcal_status".into(),
                params: json!({"x": "1"})
            }
        );
    }

    #[test]
    fn an_agent_request_keeps_moonrakers_large_id_for_the_reply() {
        let inc =
            parse(r#"{"jsonrpc":"2.0","method":"klipcal_status","id":140234567890123}"#).unwrap();
        let Incoming::Call { id, method, params } = inc else {
            panic!("not a call")
        };
        assert_eq!(method, "klipcal_status");
        assert_eq!(params, Value::Null);
        let back: Value = serde_json::from_str(&reply(&id, &Ok(json!({"ok": true})))).unwrap();
        assert_eq!(back["id"], json!(140_234_567_890_123_u64));
        assert_eq!(back["result"]["ok"], json!(true));
    }

    #[test]
    fn a_null_result_is_sent_as_an_empty_object_because_moonraker_reads_null_as_failure() {
        let back: Value = serde_json::from_str(&reply(&json!(5), &Ok(Value::Null))).unwrap();
        assert_eq!(back["result"], json!({}));
    }

    #[test]
    fn an_error_reply_carries_code_and_message() {
        let e = RpcError {
            code: 400,
            message: "bad pair".into(),
        };
        let back: Value = serde_json::from_str(&reply(&json!(5), &Err(e))).unwrap();
        assert_eq!(back["error"]["code"], json!(400));
        assert_eq!(back["error"]["message"], json!("bad pair"));
        assert!(back.get("result").is_none());
    }

    #[test]
    fn requests_omit_null_params() {
        let v: Value = serde_json::from_str(&request(1, "server.info", &Value::Null)).unwrap();
        assert!(v.get("params").is_none());
        assert_eq!(v["method"], "server.info");
        let v: Value = serde_json::from_str(&request(
            2,
            "printer.gcode.script",
            &json!({"script": "G28"}),
        ))
        .unwrap();
        assert_eq!(v["params"]["script"], "G28");
    }

    #[test]
    fn garbage_is_a_protocol_error_not_a_panic() {
        for text in [
            "",
            "nope",
            "[1,2]",
            "{}",
            r#"{"id":"abc"}"#,
            "{\"method\":5}",
        ] {
            assert!(matches!(parse(text), Err(Error::Protocol(_))), "{text}");
        }
    }
}
