//! klipcal's console scripts straight to Klipper's API socket (the unix socket Moonraker itself
//! talks to), so that Moonraker stores only their answers (issue 40 item 6). Moonraker keeps
//! every `printer.gcode.script` a client sends as a "command" row of its console history, which
//! Mainsail and Fluidd list after a reload beside the answer it printed: two rows for each of
//! klipcal's answers and dialogs. Klipper's responses still reach Moonraker (it subscribes to
//! Klipper's output), so every front end shows them, live and after a reload.
//!
//! Only a script of `RESPOND` lines (and `GET_CURRENT_SKEW`, a report) goes this way
//! ([`respond_only`]): nothing that moves, heats, restarts or configures, so none of klipcal's guards (which sit in front of those) is passed
//! by. The socket is the one Moonraker names (`server.config` → `server.klippy_uds_address`),
//! used once the Klipper answering on it is the one Moonraker talks to (its `info` the same as
//! `printer.info`: two printers on one host each have their own socket, and a klipcal talking
//! to another host's Moonraker must not speak on this host's Klipper). Anything else — no such
//! socket, no permission, another Klipper, a send that fails before it was delivered — goes
//! through Moonraker as before.

use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

use serde_json::{json, Value};
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::UnixStream;
use tracing::{debug, info};

use super::client::lock;
use super::{Error, Moonraker};

/// How long a verified route is trusted before it is checked again.
const RECHECK: Duration = Duration::from_secs(300);

/// Klipper's API messages end with this byte.
const ETX: u8 = 0x03;

/// Where klipcal's console scripts go.
#[derive(Debug, Clone, Default)]
pub(super) enum ConsoleRoute {
    /// Not checked yet (or a send failed): check before the next send.
    #[default]
    Unknown,
    /// Klipper's API socket, checked at `checked`.
    Direct { path: PathBuf, checked: Instant },
    /// Through Moonraker, decided at `checked` (and why, for the log).
    Moonraker { checked: Instant },
}

/// The commands a console script may hold: Klipper's `RESPOND`, klipcal.cfg's `_KLIPCAL_SAY`
/// (one `action_respond_info`: several lines of an answer as one response), and
/// `GET_CURRENT_SKEW` (a report of `[skew_correction]`, which changes nothing).
const CONSOLE_COMMANDS: [&str; 3] = ["RESPOND", "_KLIPCAL_SAY", "GET_CURRENT_SKEW"];

/// Whether every line of `script` is a console command ([`CONSOLE_COMMANDS`]): the only
/// scripts sent past Moonraker. Klipper reads a line's first word as its command, and
/// klipcal's lines carry no line break (`gcode_cmd` builds them), so a script that passes
/// cannot move, heat or configure anything.
#[must_use]
pub(crate) fn respond_only(script: &str) -> bool {
    let mut lines = script.lines().filter(|l| !l.trim().is_empty()).peekable();
    lines.peek().is_some()
        && lines.all(|l| {
            let mut words = l.split_whitespace();
            words
                .next()
                .is_some_and(|w| CONSOLE_COMMANDS.iter().any(|c| w.eq_ignore_ascii_case(c)))
                && !l.contains(['\r', '\0'])
        })
}

/// Whether the Klipper answering `info` on the socket is the one Moonraker's `printer.info`
/// describes: the same config file, log, host and installation (its state may differ a moment).
#[must_use]
pub(crate) fn same_klippy(moonraker: &Value, socket: &Value) -> bool {
    const IDENTITY: [&str; 6] = [
        "config_file",
        "log_file",
        "hostname",
        "klipper_path",
        "python_path",
        "software_version",
    ];
    socket["config_file"].is_string()
        && IDENTITY.iter().all(|k| moonraker.get(*k) == socket.get(*k))
}

/// What went wrong on the socket.
#[derive(Debug)]
pub(super) enum SocketError {
    /// The request surely did not reach Klipper (connect or write failed): send it another way.
    NotSent(String),
    /// Klipper may have run it (the answer was lost or late): do not send it again.
    Unanswered(String),
    /// Klipper refused it.
    Klipper(String),
}

/// One request on Klipper's API socket: `{"id", "method", "params"}` then ETX; the answer is
/// the message with the same id (Klipper may first send output of an earlier subscription on
/// this connection; there is none here).
pub(super) async fn request(
    path: &Path,
    method: &str,
    params: Value,
    limit: Duration,
) -> Result<Value, SocketError> {
    let sent = async {
        let mut s = UnixStream::connect(path)
            .await
            .map_err(|e| SocketError::NotSent(format!("{}: {e}", path.display())))?;
        let mut req = serde_json::to_vec(&json!({"id": 1, "method": method, "params": params}))
            .map_err(|e| SocketError::NotSent(e.to_string()))?;
        req.push(ETX);
        s.write_all(&req)
            .await
            .map_err(|e| SocketError::NotSent(format!("{}: {e}", path.display())))?;
        Ok(s)
    };
    let mut s = tokio::time::timeout(limit, sent)
        .await
        .map_err(|_| SocketError::NotSent(format!("{}: no connection", path.display())))??;
    let answer = async {
        let mut buf = Vec::new();
        let mut chunk = [0u8; 4096];
        loop {
            let n = s
                .read(&mut chunk)
                .await
                .map_err(|e| SocketError::Unanswered(e.to_string()))?;
            if n == 0 {
                return Err(SocketError::Unanswered("Klipper closed the socket".into()));
            }
            buf.extend_from_slice(&chunk[..n]);
            while let Some(end) = buf.iter().position(|b| *b == ETX) {
                let msg: Vec<u8> = buf.drain(..=end).collect();
                let v: Value = serde_json::from_slice(&msg[..msg.len() - 1])
                    .map_err(|e| SocketError::Unanswered(format!("not JSON: {e}")))?;
                if v["id"] != json!(1) {
                    continue;
                }
                if let Some(e) = v.get("error") {
                    return Err(SocketError::Klipper(
                        e["message"]
                            .as_str()
                            .map_or_else(|| e.to_string(), str::to_string),
                    ));
                }
                return Ok(v["result"].clone());
            }
        }
    };
    tokio::time::timeout(limit, answer)
        .await
        .map_err(|_| SocketError::Unanswered(format!("no answer within {limit:?}")))?
}

/// Moonraker's socket to Klipper, when Klipper answers on it as the Klipper Moonraker talks to.
async fn verified_socket(m: &Moonraker, limit: Duration) -> Result<PathBuf, String> {
    let config = m
        .call("server.config", Value::Null)
        .await
        .map_err(|e| e.to_string())?;
    let named = config["config"]["server"]["klippy_uds_address"]
        .as_str()
        .ok_or("Moonraker's server.config names no klippy_uds_address")?;
    let path = match (named.strip_prefix("~/"), std::env::var_os("HOME")) {
        (Some(rest), Some(home)) => Path::new(&home).join(rest),
        _ => PathBuf::from(named),
    };
    let moonraker_info = m
        .call("printer.info", Value::Null)
        .await
        .map_err(|e| e.to_string())?;
    let socket_info = request(&path, "info", json!({}), limit)
        .await
        .map_err(|e| format!("{}: {e:?}", path.display()))?;
    if same_klippy(&moonraker_info, &socket_info) {
        Ok(path)
    } else {
        Err(format!(
            "{} answers for another Klipper ({} there, {} through Moonraker)",
            path.display(),
            socket_info["config_file"],
            moonraker_info["config_file"]
        ))
    }
}

impl Moonraker {
    /// Sends one of klipcal's console scripts (answers, errors, dialog changes): a script of
    /// RESPOND lines straight to Klipper's API socket when that is the Klipper Moonraker talks
    /// to, so that Moonraker stores only the answers; anything else, or when the socket cannot
    /// be used, through Moonraker ([`Moonraker::gcode`]).
    ///
    /// # Errors
    /// Klipper's refusal, or Moonraker's errors as [`Moonraker::gcode`].
    pub(crate) async fn console_script(&self, script: &str) -> Result<(), Error> {
        if !respond_only(script) {
            return self.gcode(script).await;
        }
        let limit = self.shared.opts.request_timeout;
        let Some(path) = self.console_socket(limit).await else {
            return self.gcode(script).await;
        };
        match request(&path, "gcode/script", json!({ "script": script }), limit).await {
            Ok(_) => Ok(()),
            Err(SocketError::NotSent(why)) => {
                debug!(%why, "Klipper's socket refused the console script: through Moonraker");
                *lock(&self.shared.console_route) = ConsoleRoute::Unknown;
                self.gcode(script).await
            }
            Err(SocketError::Unanswered(why)) => {
                *lock(&self.shared.console_route) = ConsoleRoute::Unknown;
                Err(Error::Protocol(format!(
                    "Klipper's API socket {}: {why}",
                    path.display()
                )))
            }
            Err(SocketError::Klipper(message)) => Err(Error::Rpc {
                method: "gcode/script".into(),
                code: 400,
                message,
            }),
        }
    }

    /// The socket console scripts go to, checked again after [`RECHECK`] or a failed send.
    async fn console_socket(&self, limit: Duration) -> Option<PathBuf> {
        let now = Instant::now();
        match lock(&self.shared.console_route).clone() {
            ConsoleRoute::Direct { path, checked } if now - checked < RECHECK => return Some(path),
            ConsoleRoute::Moonraker { checked } if now - checked < RECHECK => return None,
            _ => {}
        }
        let route = match verified_socket(self, limit).await {
            Ok(path) => ConsoleRoute::Direct { path, checked: now },
            Err(why) => {
                debug!(%why, "klipcal's console answers go through Moonraker");
                ConsoleRoute::Moonraker { checked: now }
            }
        };
        let before = std::mem::replace(&mut *lock(&self.shared.console_route), route.clone());
        // Said in the log when the road changes, not at every check.
        match (&before, &route) {
            (ConsoleRoute::Direct { path: a, .. }, ConsoleRoute::Direct { path: b, .. })
                if a == b => {}
            (ConsoleRoute::Moonraker { .. }, ConsoleRoute::Moonraker { .. }) => {}
            (_, ConsoleRoute::Direct { path, .. }) => {
                info!(socket = %path.display(), "klipcal's console answers go to Klipper's API socket");
            }
            (_, _) => info!(
                "klipcal's console answers go through Moonraker (Klipper's API socket is not \
                 usable from here; RUST_LOG=klipcal=debug says why)"
            ),
        }
        match route {
            ConsoleRoute::Direct { path, .. } => Some(path),
            _ => None,
        }
    }
}

/// klipcal.cfg's helper that keeps, in Klipper, that klipcal is there for SECONDS more (its
/// `[delayed_gcode _KLIPCAL_OFFLINE]` ends that on Klipper's clock): the macros a user calls
/// say "asking the klipcal service..." only once it has ended (issue 40 item 6: six rows of a
/// round), so that a stopped service still shows.
pub(crate) const ONLINE_MACRO: &str = "_KLIPCAL_ONLINE";

/// How long one word of [`ONLINE_MACRO`] holds, and how often klipcal says it again.
pub(crate) const ONLINE_LEASE_S: u32 = 30;
const ONLINE_EVERY: Duration = Duration::from_secs(10);

/// The script that says klipcal is there for `seconds` more (0: gone).
#[must_use]
pub(crate) fn online_script(seconds: u32) -> String {
    format!("{ONLINE_MACRO} SECONDS={seconds}")
}

/// When to say [`ONLINE_MACRO`] again after `e`: an older klipcal.cfg without the macro, once
/// a minute at most; anything else (Klipper restarting, as after Apply's FIRMWARE_RESTART,
/// which also forgets the last word) in two seconds, so that the macros do not say "asking"
/// for a minute while klipcal answers (CI on Kalico: round 2's KLIPCAL_STATUS did).
fn online_retry(e: &SocketError) -> Duration {
    match e {
        SocketError::Klipper(m) if m.to_lowercase().contains("unknown command") => {
            Duration::from_secs(60)
        }
        _ => Duration::from_secs(2),
    }
}

impl Moonraker {
    /// Says in Klipper, every [`ONLINE_EVERY`] while klipcal is connected and registered with
    /// Moonraker, that it answers for [`ONLINE_LEASE_S`] more; at shutdown that it is gone.
    /// Only on Klipper's API socket (no console row); where that socket cannot be used, or
    /// klipcal.cfg has no such macro yet, nothing is said and the macros always say "asking".
    /// One word at a time: a Klipper busy with a long command answers it once done.
    pub(crate) async fn keep_online(self, stop: tokio_util::sync::CancellationToken) {
        let mut said: Option<PathBuf> = None;
        loop {
            let next = tokio::select! {
                () = stop.cancelled() => break,
                next = self.say_online(&mut said) => next,
            };
            tokio::select! {
                () = stop.cancelled() => break,
                () = tokio::time::sleep(next) => {}
            }
        }
        if let Some(path) = said {
            let limit = Duration::from_secs(1);
            let _ = request(
                &path,
                "gcode/script",
                json!({"script": online_script(0)}),
                limit,
            )
            .await;
        }
    }

    /// One word of [`Moonraker::keep_online`]; how long until the next.
    async fn say_online(&self, said: &mut Option<PathBuf>) -> Duration {
        let ready = matches!(
            self.state(),
            super::ConnState::Connected { ref klippy_state } if klippy_state == "ready"
        );
        let limit = self.shared.opts.request_timeout;
        let path = match ready {
            true => self.console_socket(limit).await,
            false => None,
        };
        // Not ready yet (klipcal starting, Klipper restarting): looked at again in a second,
        // so that the macros stop saying "asking" soon after.
        let Some(path) = path else {
            return Duration::from_secs(1);
        };
        let script = online_script(ONLINE_LEASE_S);
        match request(
            &path,
            "gcode/script",
            json!({ "script": script }),
            ONLINE_EVERY * 12,
        )
        .await
        {
            Ok(_) => {
                *said = Some(path);
                ONLINE_EVERY
            }
            Err(e) => {
                debug!(error = ?e, "klipcal could not say in Klipper that it is there");
                online_retry(&e)
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_word_lost_to_a_restart_is_said_again_in_seconds_a_missing_macro_in_a_minute() {
        // klipcal.log on Kalico after Apply's FIRMWARE_RESTART: the next word waited a minute.
        let reset = SocketError::Unanswered("Connection reset by peer (os error 104)".into());
        assert_eq!(online_retry(&reset), Duration::from_secs(2));
        let refused = SocketError::NotSent("No such file or directory".into());
        assert_eq!(online_retry(&refused), Duration::from_secs(2));
        let old_cfg = SocketError::Klipper("Unknown command:\"_KLIPCAL_ONLINE\"".into());
        assert_eq!(online_retry(&old_cfg), Duration::from_secs(60));
    }

    #[test]
    fn only_respond_scripts_go_past_moonraker() {
        assert!(respond_only(
            "RESPOND PREFIX=klipcal MSG=\"a\"\nRESPOND TYPE=command MSG=action:prompt_end"
        ));
        assert!(respond_only("respond msg=\"x\"\n\n"));
        assert!(respond_only(
            "_KLIPCAL_SAY MSG=\"a␤b\"\nRESPOND TYPE=command MSG=action:prompt_show"
        ));
        // A report that changes nothing.
        assert!(respond_only("RESPOND MSG=\"why\"\nGET_CURRENT_SKEW"));
        for not in [
            "",
            "\n",
            "RESPOND MSG=\"a\"\nG1 X10",
            "SET_IDLE_TIMEOUT TIMEOUT=600\nRESPOND MSG=\"a\"",
            "RESPONDX MSG=\"a\"",
            "_KLIPCAL_SAY_MORE MSG=\"a\"",
            "TURN_OFF_HEATERS",
            "GET_CURRENT_SKEW\nSET_SKEW CLEAR=1",
            "RESPOND MSG=\"a\"\rG28",
        ] {
            assert!(!respond_only(not), "{not:?}");
        }
    }

    #[test]
    fn the_socket_is_used_only_for_the_klipper_moonraker_talks_to() {
        let ours = json!({
            "state": "ready", "hostname": "pi", "config_file": "/home/pi/printer_data/config/printer.cfg",
            "log_file": "/home/pi/printer_data/logs/klippy.log", "software_version": "v0.12.0",
            "klipper_path": "/home/pi/klipper", "python_path": "/home/pi/klippy-env/bin/python"
        });
        let mut moonraker = ours.clone();
        moonraker["state"] = json!("startup");
        assert!(same_klippy(&moonraker, &ours));
        // The second printer on the host.
        let mut other = ours.clone();
        other["config_file"] = json!("/home/pi/printer_2_data/config/printer.cfg");
        assert!(!same_klippy(&moonraker, &other));
        // Another host's Klipper with the same layout.
        let mut remote = ours.clone();
        remote["hostname"] = json!("voron");
        assert!(!same_klippy(&remote, &ours));
        // Something that is not Klipper's info.
        assert!(!same_klippy(&json!({}), &json!({})));
    }

    /// A Klipper API socket that answers `info` and records the scripts it runs.
    async fn fake_klippy(
        dir: &Path,
        info: Value,
    ) -> (PathBuf, tokio::sync::mpsc::UnboundedReceiver<String>) {
        let path = dir.join("klippy.sock");
        let listener = tokio::net::UnixListener::bind(&path).unwrap();
        let (tx, rx) = tokio::sync::mpsc::unbounded_channel();
        tokio::spawn(async move {
            while let Ok((mut s, _)) = listener.accept().await {
                let mut buf = Vec::new();
                let mut chunk = [0u8; 1024];
                while !buf.contains(&ETX) {
                    let n = s.read(&mut chunk).await.unwrap();
                    if n == 0 {
                        break;
                    }
                    buf.extend_from_slice(&chunk[..n]);
                }
                let req: Value = serde_json::from_slice(&buf[..buf.len() - 1]).unwrap();
                let answer = match req["method"].as_str() {
                    Some("info") => json!({"id": req["id"], "result": info}),
                    Some("gcode/script") => {
                        let script = req["params"]["script"].as_str().unwrap().to_string();
                        let _ = tx.send(script);
                        // Output of another request first, then the answer.
                        json!({"id": req["id"], "result": {}})
                    }
                    _ => json!({"id": req["id"], "error": {"message": "no such method"}}),
                };
                let mut out = serde_json::to_vec(&json!({"id": 99, "result": {}})).unwrap();
                out.push(ETX);
                out.extend(serde_json::to_vec(&answer).unwrap());
                out.push(ETX);
                s.write_all(&out).await.unwrap();
            }
        });
        (path, rx)
    }

    #[tokio::test]
    async fn a_request_reads_its_own_answer_and_says_whether_it_was_sent() {
        let dir = tempfile::tempdir().unwrap();
        let info = json!({"config_file": "/c/printer.cfg", "hostname": "h"});
        let (path, mut scripts) = fake_klippy(dir.path(), info.clone()).await;
        let limit = Duration::from_secs(5);
        assert_eq!(
            request(&path, "info", json!({}), limit).await.unwrap(),
            info
        );
        request(
            &path,
            "gcode/script",
            json!({"script": "RESPOND MSG=\"hi\""}),
            limit,
        )
        .await
        .unwrap();
        assert_eq!(scripts.recv().await.unwrap(), "RESPOND MSG=\"hi\"");
        assert!(matches!(
            request(&path, "nope", json!({}), limit).await,
            Err(SocketError::Klipper(m)) if m == "no such method"
        ));
        // No socket there: not sent, so it may go through Moonraker.
        assert!(matches!(
            request(&dir.path().join("none.sock"), "info", json!({}), limit).await,
            Err(SocketError::NotSent(_))
        ));
    }
}
