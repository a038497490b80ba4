//! The actor task that owns the websocket: connects and reconnects with backoff, runs one
//! session per connection (requests out, replies matched by id, agent calls and notifications
//! fanned out), and fails every waiting request when the connection drops or the daemon stops.

use std::collections::HashMap;
use std::sync::{Arc, Mutex};
use std::time::Duration;

use futures_util::{SinkExt, StreamExt};
use serde_json::{Map, Value};
use tokio::sync::{broadcast, mpsc, oneshot, watch};
use tokio_tungstenite::tungstenite::Message;
use tokio_util::sync::CancellationToken;
use tracing::{debug, info, warn};

use super::client::{
    lock, merge_status, AgentCall, ClientOptions, Cmd, ConnState, Event, Moonraker, Responder,
    Shared,
};
use super::protocol::{self, Incoming};
use super::Error;

impl Moonraker {
    /// Starts the actor task. It runs until `cancel` fires. Agent calls arrive on the returned
    /// receiver.
    pub fn spawn(
        opts: ClientOptions,
        cancel: CancellationToken,
    ) -> (Moonraker, mpsc::UnboundedReceiver<AgentCall>) {
        let (tx, rx) = mpsc::unbounded_channel();
        let (agent_tx, agent_rx) = mpsc::unbounded_channel();
        let (events, _) = broadcast::channel(1024);
        let (state, _) = watch::channel(ConnState::Connecting(None));
        let shared = Arc::new(Shared {
            subscriptions: Mutex::new(opts.subscriptions.clone()),
            opts,
            tx,
            events,
            state,
            status: Mutex::new(Map::new()),
            cancel,
            identified_once: std::sync::atomic::AtomicBool::new(false),
            fatal: Mutex::new(None),
            socket_open: std::sync::atomic::AtomicBool::new(false),
            console_route: Mutex::new(super::klippy::ConsoleRoute::default()),
        });
        let handle = Moonraker {
            shared: shared.clone(),
        };
        tokio::spawn(actor(handle.clone(), rx, agent_tx));
        (handle, agent_rx)
    }
}

enum Pending {
    Waiting {
        method: String,
        tx: oneshot::Sender<Result<Value, Error>>,
    },
}

pub(super) async fn actor(
    handle: Moonraker,
    mut rx: mpsc::UnboundedReceiver<Cmd>,
    agent_tx: mpsc::UnboundedSender<AgentCall>,
) {
    let shared = handle.shared.clone();
    let opts = &shared.opts;
    let mut backoff = opts.reconnect_min;
    // The reason last reported at warn level: a failing connection is reported once, and again
    // only when the reason changes (not at every retry).
    let mut reported: Option<String> = None;
    let report = |reported: &mut Option<String>, why: String| {
        if reported.as_deref() != Some(why.as_str()) {
            let msg = format!(
                "cannot reach Moonraker at {}: {why}; retrying every {} s at most",
                opts.url,
                fmt_secs(opts.reconnect_max)
            );
            // Only the daemon (the agent) reports at warn; `check` says it in its own words.
            if opts.agent {
                warn!("{msg}");
            } else {
                debug!("{msg}");
            }
            *reported = Some(why);
        }
    };
    loop {
        if shared.cancel.is_cancelled() {
            break;
        }
        let connect = tokio::time::timeout(
            opts.request_timeout,
            tokio_tungstenite::connect_async(opts.url.as_str()),
        );
        let result = tokio::select! {
            () = shared.cancel.cancelled() => break,
            r = connect => r,
        };
        match result {
            Ok(Ok((ws, _))) => {
                info!(url = %opts.url, "connected to Moonraker");
                backoff = opts.reconnect_min;
                reported = None;
                shared
                    .socket_open
                    .store(true, std::sync::atomic::Ordering::SeqCst);
                session(&handle, ws, &mut rx, &agent_tx).await;
                shared
                    .socket_open
                    .store(false, std::sync::atomic::Ordering::SeqCst);
                handle.set_state(ConnState::Connecting(Some("connection closed".into())));
                handle.emit(Event::Disconnected);
                if shared.cancel.is_cancelled() {
                    break;
                }
                warn!(url = %opts.url, "Moonraker connection lost; reconnecting");
            }
            Ok(Err(e)) => {
                debug!(error = %e, "connect failed");
                let why = connect_failure(&e);
                handle.set_state(ConnState::Connecting(Some(why.clone())));
                report(&mut reported, why);
            }
            Err(_) => {
                let why = format!("no answer within {} s", fmt_secs(opts.request_timeout));
                handle.set_state(ConnState::Connecting(Some(why.clone())));
                report(&mut reported, why);
            }
        }
        // Wait before the next try; requests made meanwhile fail at once.
        let sleep = tokio::time::sleep(backoff);
        tokio::pin!(sleep);
        loop {
            tokio::select! {
                () = shared.cancel.cancelled() => break,
                () = &mut sleep => break,
                cmd = rx.recv() => match cmd {
                    Some(Cmd::Request { tx, .. }) => {
                        let _ = tx.send(Err(Error::NotConnected(opts.url.clone())));
                    }
                    Some(Cmd::Reply { .. }) => {}
                    None => break,
                },
            }
        }
        backoff = (backoff * 2).min(opts.reconnect_max);
    }
    handle.set_state(ConnState::Stopped);
    rx.close();
    while let Ok(cmd) = rx.try_recv() {
        if let Cmd::Request { tx, .. } = cmd {
            let _ = tx.send(Err(Error::Shutdown));
        }
    }
}

/// A short reason for a failed websocket connect, in a user's words
/// (`connection refused`, `host not found`, `HTTP 404 Not Found`).
fn connect_failure(e: &tokio_tungstenite::tungstenite::Error) -> String {
    use std::io::ErrorKind;
    use tokio_tungstenite::tungstenite::Error as WsError;
    match e {
        WsError::Io(io) => match io.kind() {
            ErrorKind::ConnectionRefused => "connection refused".into(),
            ErrorKind::ConnectionReset => "connection reset".into(),
            ErrorKind::TimedOut => "timed out".into(),
            ErrorKind::NotFound => "host not found".into(),
            _ => {
                let text = io.to_string();
                if text.contains("failed to lookup address") || text.contains("Name or service") {
                    "host not found".into()
                } else {
                    text
                }
            }
        },
        WsError::Http(resp) => format!("HTTP {} (is the URL's path /websocket?)", resp.status()),
        WsError::Url(u) => format!("bad URL: {u}"),
        other => other.to_string(),
    }
}

/// Seconds without a needless fraction: 1 → "1", 0.5 → "0.5".
fn fmt_secs(d: Duration) -> String {
    let s = d.as_secs_f64();
    if (s - s.round()).abs() < 1e-9 {
        format!("{s:.0}")
    } else {
        format!("{s:.1}")
    }
}

type Ws =
    tokio_tungstenite::WebSocketStream<tokio_tungstenite::MaybeTlsStream<tokio::net::TcpStream>>;

async fn session(
    handle: &Moonraker,
    ws: Ws,
    rx: &mut mpsc::UnboundedReceiver<Cmd>,
    agent_tx: &mpsc::UnboundedSender<AgentCall>,
) {
    let shared = &handle.shared;
    let (mut sink, mut stream) = ws.split();
    let mut pending: HashMap<u64, Pending> = HashMap::new();
    let mut next_id: u64 = 1;
    let setup = {
        let h = handle.clone();
        tokio::spawn(async move {
            if let Err(e) = h.setup().await {
                warn!(error = %e, "agent setup failed");
            }
        })
    };
    loop {
        tokio::select! {
            () = shared.cancel.cancelled() => {
                let _ = sink.send(Message::Close(None)).await;
                break;
            }
            cmd = rx.recv() => {
                let Some(cmd) = cmd else { break };
                let text = match cmd {
                    Cmd::Request { method, params, tx } => {
                        let id = next_id;
                        next_id += 1;
                        let text = protocol::request(id, &method, &params);
                        pending.insert(id, Pending::Waiting { method, tx });
                        text
                    }
                    Cmd::Reply { id, outcome } => protocol::reply(&id, &outcome),
                };
                if let Err(e) = sink.send(Message::Text(text.into())).await {
                    debug!(error = %e, "send failed");
                    break;
                }
            }
            msg = stream.next() => {
                let text = match msg {
                    Some(Ok(Message::Text(t))) => t.to_string(),
                    Some(Ok(Message::Binary(b))) => String::from_utf8_lossy(&b).into_owned(),
                    Some(Ok(Message::Close(_))) | None => break,
                    Some(Ok(_)) => continue,
                    Some(Err(e)) => {
                        debug!(error = %e, "websocket error");
                        break;
                    }
                };
                match protocol::parse(&text) {
                    Ok(inc) => dispatch(handle, inc, &mut pending, agent_tx),
                    Err(e) => warn!(error = %e, "ignored a frame"),
                }
            }
        }
    }
    setup.abort();
    // Not connected any more before anyone hears of the lost replies, so that a caller who
    // looks at the state on `Disconnected` sees the outage.
    handle.set_state(ConnState::Connecting(Some("connection closed".into())));
    for (_, p) in pending.drain() {
        let Pending::Waiting { method, tx } = p;
        let _ = tx.send(Err(Error::Disconnected(method)));
    }
}

fn dispatch(
    handle: &Moonraker,
    inc: Incoming,
    pending: &mut HashMap<u64, Pending>,
    agent_tx: &mpsc::UnboundedSender<AgentCall>,
) {
    let shared = &handle.shared;
    match inc {
        Incoming::Response { id, outcome } => {
            if let Some(Pending::Waiting { method, tx }) = pending.remove(&id) {
                let r = outcome.map_err(|e| Error::Rpc {
                    method,
                    code: e.code,
                    message: e.message,
                });
                let _ = tx.send(r);
            }
        }
        Incoming::Call { id, method, params } => {
            let responder = Responder {
                id,
                tx: shared.tx.clone(),
            };
            // Every forwarded request goes to the daemon, which answers unknown methods
            // with the list of known ones.
            let _ = agent_tx.send(AgentCall {
                method,
                params,
                responder: Some(responder),
            });
        }
        Incoming::Notification { method, params } => {
            if shared.opts.remote_methods.contains(&method) {
                let _ = agent_tx.send(AgentCall {
                    method,
                    params,
                    responder: None,
                });
                return;
            }
            let event = match method.as_str() {
                "notify_status_update" => {
                    let diff = match params.get(0) {
                        Some(Value::Object(m)) => m.clone(),
                        _ => Map::new(),
                    };
                    merge_status(&mut lock(&shared.status), &diff);
                    Event::Status(diff)
                }
                "notify_gcode_response" => Event::GcodeResponse(
                    params
                        .get(0)
                        .and_then(Value::as_str)
                        .unwrap_or_default()
                        .to_string(),
                ),
                "notify_klippy_ready" => {
                    handle.set_klippy_state("ready");
                    let h = handle.clone();
                    tokio::spawn(async move {
                        if let Err(e) = h.resubscribe(true).await {
                            warn!(error = %e, "subscribe after Klipper restart failed");
                        }
                    });
                    Event::KlippyReady
                }
                "notify_klippy_shutdown" => {
                    handle.set_klippy_state("shutdown");
                    Event::KlippyShutdown
                }
                "notify_klippy_disconnected" => {
                    handle.set_klippy_state("disconnected");
                    Event::KlippyDisconnected
                }
                "notify_agent_event" => Event::AgentEvent(params),
                _ => Event::Other { method, params },
            };
            let _ = shared.events.send(event);
        }
    }
}
