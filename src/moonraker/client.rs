//! The websocket actor and its cloneable handle. One task owns the socket; handles send
//! `(request, oneshot)` over a channel and await the reply. The actor identifies as an agent,
//! registers remote methods and subscriptions again after every reconnect, fans notifications
//! out to subscribers, and hands agent calls (from macros and `/server/extensions/request`)
//! to the daemon. It must not know what the calls mean.

use std::collections::HashMap;
use std::sync::{Arc, Mutex};
use std::time::Duration;

use futures_util::{SinkExt, StreamExt};
use serde_json::{json, Map, Value};
use tokio::sync::{broadcast, mpsc, oneshot, watch};
use tokio_tungstenite::tungstenite::Message;
use tokio_util::sync::CancellationToken;
use tracing::{debug, info, warn};

use super::answers::{BedMeshStatus, ConfigFile, HeaterStatus, WebcamList};
use super::protocol::{self, Incoming, RpcError};
use super::Error;

/// How to connect, and what to set up after each connect.
#[derive(Debug, Clone)]
pub struct ClientOptions {
    /// `ws://host:port/websocket`.
    pub url: String,
    /// Sent in `server.connection.identify` when set.
    pub api_key: Option<String>,
    /// `client_name` in `server.connection.identify`.
    pub client_name: String,
    /// Identify as an agent (the daemon) or as a plain client (`check`, tests): Moonraker
    /// accepts one agent per name.
    pub agent: bool,
    /// Per-request reply timeout.
    pub request_timeout: Duration,
    /// First reconnect delay.
    pub reconnect_min: Duration,
    /// Backoff cap.
    pub reconnect_max: Duration,
    /// Remote methods registered for Klipper macros after every connect.
    pub remote_methods: Vec<String>,
    /// Printer objects subscribed after every connect and Klipper restart
    /// (object name → list of fields, or null for all).
    pub subscriptions: Map<String, Value>,
}

/// The connection's state.
#[derive(Debug, Clone, PartialEq)]
pub enum ConnState {
    /// Trying to connect; holds the last failure, if any.
    Connecting(Option<String>),
    /// Connected and identified; `klippy_state` as Moonraker last reported it.
    Connected {
        /// `ready`, `startup`, `shutdown`, `error` or `disconnected`.
        klippy_state: String,
    },
    /// The actor has stopped (shutdown).
    Stopped,
}

/// What subscribers receive.
#[derive(Debug, Clone, PartialEq)]
pub enum Event {
    /// Connected and identified (also after a reconnect).
    Connected,
    /// The websocket closed.
    Disconnected,
    /// `notify_klippy_ready`.
    KlippyReady,
    /// `notify_klippy_shutdown`.
    KlippyShutdown,
    /// `notify_klippy_disconnected`.
    KlippyDisconnected,
    /// `notify_status_update`: the changed fields, object → field → value.
    Status(Map<String, Value>),
    /// `notify_gcode_response`: one console line.
    GcodeResponse(String),
    /// `notify_agent_event`.
    AgentEvent(Value),
    /// Any other notification.
    Other {
        /// Method name.
        method: String,
        /// Parameters.
        params: Value,
    },
}

/// A remote method call for the daemon to handle.
#[derive(Debug)]
pub struct AgentCall {
    /// Method name, one of [`ClientOptions::remote_methods`].
    pub method: String,
    /// Arguments (macro parameters or the HTTP request's `arguments`).
    pub params: Value,
    /// Where the reply goes: `None` for a macro call (no reply can reach a macro; answer
    /// on the console instead).
    pub responder: Option<Responder>,
}

/// Sends the reply to one forwarded request.
#[derive(Debug)]
pub struct Responder {
    id: Value,
    tx: mpsc::UnboundedSender<Cmd>,
}

impl Responder {
    /// Sends the result (or error) back to Moonraker, which answers the HTTP caller.
    pub(crate) fn send(self, outcome: Result<Value, RpcError>) {
        let _ = self.tx.send(Cmd::Reply {
            id: self.id,
            outcome,
        });
    }
}

#[derive(Debug)]
enum Cmd {
    Request {
        method: String,
        params: Value,
        tx: oneshot::Sender<Result<Value, Error>>,
    },
    Reply {
        id: Value,
        outcome: Result<Value, RpcError>,
    },
}

struct Shared {
    opts: ClientOptions,
    tx: mpsc::UnboundedSender<Cmd>,
    events: broadcast::Sender<Event>,
    state: watch::Sender<ConnState>,
    status: Mutex<Map<String, Value>>,
    subscriptions: Mutex<Map<String, Value>>,
    cancel: CancellationToken,
    /// Set once this client has identified; a refusal after that is not fatal.
    identified_once: std::sync::atomic::AtomicBool,
    /// Why the client gave up for good (Moonraker refused to identify the agent).
    fatal: Mutex<Option<String>>,
    /// The websocket is open (the client may still be identifying itself).
    socket_open: std::sync::atomic::AtomicBool,
}

/// The cloneable handle to the Moonraker connection.
#[derive(Clone)]
pub struct Moonraker {
    shared: Arc<Shared>,
}

impl std::fmt::Debug for Moonraker {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Moonraker")
            .field("url", &self.shared.opts.url)
            .finish()
    }
}

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
        });
        let handle = Moonraker {
            shared: shared.clone(),
        };
        tokio::spawn(actor(handle.clone(), rx, agent_tx));
        (handle, agent_rx)
    }

    /// The websocket URL.
    pub(crate) fn url(&self) -> &str {
        &self.shared.opts.url
    }

    /// Receives every event from now on.
    pub fn events(&self) -> broadcast::Receiver<Event> {
        self.shared.events.subscribe()
    }

    /// The connection state now.
    pub(crate) fn state(&self) -> ConnState {
        self.shared.state.borrow().clone()
    }

    /// Whether the websocket is open now: connected, or identifying itself right after
    /// connecting (so [`Moonraker::wait_connected`] is a matter of moments).
    pub(crate) fn socket_open(&self) -> bool {
        self.shared
            .socket_open
            .load(std::sync::atomic::Ordering::SeqCst)
    }

    /// A watch on the connection state.
    pub fn state_watch(&self) -> watch::Receiver<ConnState> {
        self.shared.state.subscribe()
    }

    /// Why the client stopped for good, when it did: Moonraker refused to identify this
    /// client on its first connection (another agent with the same name, a wrong API key).
    /// The client then cancels its token, so the daemon stops and reports this.
    pub(crate) fn fatal_error(&self) -> Option<String> {
        lock(&self.shared.fatal).clone()
    }

    /// The merged status of every subscribed object, as last reported.
    pub fn status(&self) -> Map<String, Value> {
        lock(&self.shared.status).clone()
    }

    /// Waits until connected and identified, at most `limit`.
    ///
    /// # Errors
    /// [`Error::NotConnected`] with the last connect failure when the time runs out.
    pub async fn wait_connected(&self, limit: Duration) -> Result<(), Error> {
        let mut rx = self.shared.state.subscribe();
        let waited = tokio::time::timeout(limit, async {
            rx.wait_for(|s| matches!(s, ConnState::Connected { .. } | ConnState::Stopped))
                .await
                .map(|s| matches!(*s, ConnState::Connected { .. }))
        })
        .await;
        match waited {
            Ok(Ok(true)) => Ok(()),
            Ok(_) => Err(Error::Shutdown),
            Err(_) => {
                let why = match self.state() {
                    ConnState::Connecting(Some(e)) => format!("{} ({e})", self.url()),
                    _ => self.url().to_string(),
                };
                Err(Error::NotConnected(why))
            }
        }
    }

    /// Whether `e` means Moonraker is unreachable right now ([`Error::is_unreachable`] with this
    /// connection's state): an outage to wait out, not a failure.
    pub(crate) fn is_unreachable(&self, e: &Error) -> bool {
        e.is_unreachable(matches!(self.state(), ConnState::Connected { .. }))
    }

    /// Waits for Moonraker to be back after an outage, however long: connected again, and
    /// Klipper ready or `klippy_limit` spent waiting for it once connected (Klipper itself may
    /// be down; the caller then sees in what state). False when the client stopped (shutdown).
    pub(crate) async fn wait_back(&self, klippy_limit: Duration) -> bool {
        let mut rx = self.shared.state.subscribe();
        loop {
            let connected = rx
                .wait_for(|s| matches!(s, ConnState::Connected { .. } | ConnState::Stopped))
                .await
                .map(|s| matches!(*s, ConnState::Connected { .. }));
            if !matches!(connected, Ok(true)) {
                return false;
            }
            let ready = tokio::time::timeout(
                klippy_limit,
                rx.wait_for(|s| match s {
                    ConnState::Connected { klippy_state } => klippy_state == "ready",
                    _ => true,
                }),
            )
            .await;
            match ready {
                // Klipper did not get ready in time: back, in whatever state Klipper is.
                Err(_) => return true,
                Ok(Err(_)) => return false,
                Ok(Ok(s)) => match &*s {
                    ConnState::Connected { .. } => return true,
                    ConnState::Stopped => return false,
                    // Lost again before Klipper was ready: wait for the next connection.
                    ConnState::Connecting(_) => {}
                },
            }
        }
    }

    /// Calls a Moonraker method and awaits the reply. Waits for the connection (up to the
    /// request timeout) when it is being re-established.
    ///
    /// # Errors
    /// Moonraker's refusal, a timeout, or a lost connection.
    pub async fn call(&self, method: &str, params: Value) -> Result<Value, Error> {
        self.call_within(method, params, self.shared.opts.request_timeout)
            .await
    }

    /// [`Moonraker::call`] with its own time limit (a long G-code such as BED_MESH_CALIBRATE).
    ///
    /// # Errors
    /// As [`Moonraker::call`].
    pub(crate) async fn call_within(
        &self,
        method: &str,
        params: Value,
        limit: Duration,
    ) -> Result<Value, Error> {
        let timeout_err = || Error::Timeout {
            method: method.to_string(),
            timeout_s: limit.as_secs_f64(),
        };
        let deadline = tokio::time::Instant::now() + limit;
        if !matches!(self.state(), ConnState::Connected { .. }) {
            match self.wait_connected(limit).await {
                Ok(()) => {}
                Err(Error::NotConnected(why)) => return Err(Error::NotConnected(why)),
                Err(e) => return Err(e),
            }
        }
        let fut = self.call_raw(method, params, limit);
        tokio::time::timeout_at(deadline, fut)
            .await
            .map_err(|_| timeout_err())?
    }

    async fn call_raw(&self, method: &str, params: Value, limit: Duration) -> Result<Value, Error> {
        let (tx, rx) = oneshot::channel();
        self.shared
            .tx
            .send(Cmd::Request {
                method: method.to_string(),
                params,
                tx,
            })
            .map_err(|_| Error::Shutdown)?;
        match tokio::time::timeout(limit, rx).await {
            Ok(Ok(r)) => r,
            Ok(Err(_)) => Err(Error::Disconnected(method.to_string())),
            Err(_) => Err(Error::Timeout {
                method: method.to_string(),
                timeout_s: limit.as_secs_f64(),
            }),
        }
    }

    /// Runs a G-code script and waits until Klipper has executed it.
    ///
    /// # Errors
    /// Klipper's error (e.g. `Must home axis first`) as [`Error::Rpc`]. An unknown command is
    /// not an error here: Klipper reports it on the console as `// Unknown command`.
    pub async fn gcode(&self, script: &str) -> Result<(), Error> {
        self.call("printer.gcode.script", json!({ "script": script }))
            .await
            .map(|_| ())
    }

    /// [`Moonraker::gcode`] with its own time limit.
    ///
    /// # Errors
    /// As [`Moonraker::gcode`].
    pub async fn gcode_within(&self, script: &str, limit: Duration) -> Result<(), Error> {
        self.call_within("printer.gcode.script", json!({ "script": script }), limit)
            .await
            .map(|_| ())
    }

    /// `server.info`.
    ///
    /// # Errors
    /// As [`Moonraker::call`].
    pub(crate) async fn server_info(&self) -> Result<Value, Error> {
        self.call("server.info", Value::Null).await
    }

    /// `printer.info`.
    ///
    /// # Errors
    /// As [`Moonraker::call`].
    pub async fn printer_info(&self) -> Result<Value, Error> {
        self.call("printer.info", Value::Null).await
    }

    /// `printer.objects.list`: the names of every printer object.
    ///
    /// # Errors
    /// As [`Moonraker::call`].
    pub(crate) async fn objects_list(&self) -> Result<Vec<String>, Error> {
        let v = self.call("printer.objects.list", Value::Null).await?;
        Ok(v["objects"]
            .as_array()
            .map(|a| {
                a.iter()
                    .filter_map(|s| s.as_str().map(str::to_string))
                    .collect()
            })
            .unwrap_or_default())
    }

    /// `printer.objects.query`: object name → fields (null for all). Returns object → status.
    ///
    /// # Errors
    /// As [`Moonraker::call`].
    pub async fn objects_query(&self, objects: Value) -> Result<Map<String, Value>, Error> {
        let v = self
            .call("printer.objects.query", json!({ "objects": objects }))
            .await?;
        match v.get("status") {
            Some(Value::Object(m)) => Ok(m.clone()),
            _ => Err(Error::Protocol(format!("query reply without status: {v}"))),
        }
    }

    async fn resubscribe(&self, raw: bool) -> Result<Map<String, Value>, Error> {
        let objects = Value::Object(lock(&self.shared.subscriptions).clone());
        let params = json!({ "objects": objects });
        let v = if raw {
            self.call_raw(
                "printer.objects.subscribe",
                params,
                self.shared.opts.request_timeout,
            )
            .await?
        } else {
            self.call("printer.objects.subscribe", params).await?
        };
        let status = match v.get("status") {
            Some(Value::Object(m)) => m.clone(),
            _ => Map::new(),
        };
        merge_status(&mut lock(&self.shared.status), &status);
        Ok(status)
    }

    /// `printer.print.start` for a file under the `gcodes` root.
    ///
    /// # Errors
    /// As [`Moonraker::call`]; Moonraker refuses while a print runs.
    pub async fn print_start(&self, filename: &str) -> Result<(), Error> {
        self.call("printer.print.start", json!({ "filename": filename }))
            .await
            .map(|_| ())
    }

    /// `printer.firmware_restart`.
    ///
    /// # Errors
    /// As [`Moonraker::call`].
    pub async fn firmware_restart(&self) -> Result<(), Error> {
        self.call("printer.firmware_restart", Value::Null)
            .await
            .map(|_| ())
    }

    /// Klipper's configfile object, typed: `config` (text as written) and the `settings` klipcal
    /// reads (parsed, with Klipper's defaults).
    ///
    /// # Errors
    /// As [`Moonraker::call`]; [`Error::Protocol`] when the answer is malformed.
    pub async fn configfile(&self) -> Result<ConfigFile, Error> {
        let mut m = self
            .objects_query(json!({ "configfile": ["config", "settings"] }))
            .await?;
        ConfigFile::parse(m.remove("configfile").unwrap_or_else(|| json!({})))
    }

    /// Klipper's `bed_mesh` status, typed: the `fields` asked for (`profile_name`,
    /// `probed_matrix`, `profiles`).
    ///
    /// # Errors
    /// As [`Moonraker::call`]; [`Error::Protocol`] when the answer is malformed.
    pub async fn bed_mesh(&self, fields: &[&str]) -> Result<BedMeshStatus, Error> {
        let mut m = self.objects_query(json!({ "bed_mesh": fields })).await?;
        BedMeshStatus::parse(m.remove("bed_mesh").unwrap_or_else(|| json!({})))
    }

    /// A heater's or temperature sensor's status, typed: the `fields` asked for (`temperature`,
    /// `target`, `power`); all `None` when Klipper has no object `name`.
    ///
    /// # Errors
    /// As [`Moonraker::call`]; [`Error::Protocol`] when the answer is malformed.
    pub(crate) async fn heater(&self, name: &str, fields: &[&str]) -> Result<HeaterStatus, Error> {
        let mut m = self.objects_query(json!({ name: fields })).await?;
        HeaterStatus::parse(name, m.remove(name).unwrap_or_else(|| json!({})))
    }

    /// Moonraker's webcams (`server.webcams.list`), typed.
    ///
    /// # Errors
    /// As [`Moonraker::call`]; [`Error::Protocol`] when the answer is malformed.
    pub(crate) async fn webcams(&self) -> Result<WebcamList, Error> {
        WebcamList::parse(self.call("server.webcams.list", json!({})).await?)
    }

    fn set_state(&self, s: ConnState) {
        self.shared.state.send_replace(s);
    }

    fn emit(&self, e: Event) {
        let _ = self.shared.events.send(e);
    }

    /// After connect: identify, register remote methods, subscribe when Klipper is ready.
    async fn setup(&self) -> Result<(), Error> {
        let opts = &self.shared.opts;
        let mut ident = json!({
            "client_name": opts.client_name,
            "version": env!("CARGO_PKG_VERSION"),
            "type": if opts.agent { "agent" } else { "other" },
            "url": "https://github.com/klipcal/klipcal",
        });
        if let Some(key) = &opts.api_key {
            ident["api_key"] = json!(key);
        }
        let r = match self
            .call_raw(
                "server.connection.identify",
                ident,
                self.shared.opts.request_timeout,
            )
            .await
        {
            Ok(r) => r,
            Err(e) => {
                use std::sync::atomic::Ordering;
                // A refusal on the first connection will not go away by retrying (the name is
                // taken by another running daemon, or the API key is wrong): stop, with
                // Moonraker's reason. Later, a refusal may be our own previous connection not
                // yet closed on Moonraker's side, so it is only logged.
                if e.is_refusal() && !self.shared.identified_once.load(Ordering::SeqCst) {
                    let why = match &e {
                        Error::Rpc { message, .. } => message.clone(),
                        other => other.to_string(),
                    };
                    *lock(&self.shared.fatal) = Some(format!(
                        "Moonraker at {} refused to register klipcal as agent `{}`: {why}{}",
                        opts.url,
                        opts.client_name,
                        if why.contains("already registered") {
                            " (another klipcal is already serving this printer; stop it first, \
                             or give this one its own Moonraker)"
                        } else {
                            ""
                        }
                    ));
                    self.shared.cancel.cancel();
                }
                return Err(e);
            }
        };
        self.shared
            .identified_once
            .store(true, std::sync::atomic::Ordering::SeqCst);
        debug!(connection_id = %r["connection_id"], "identified as agent");
        for m in &opts.remote_methods {
            if let Err(e) = self
                .call_raw(
                    "connection.register_remote_method",
                    json!({ "method_name": m }),
                    self.shared.opts.request_timeout,
                )
                .await
            {
                warn!(method = %m, error = %e, "could not register remote method");
            }
        }
        let info = self
            .call_raw("server.info", Value::Null, self.shared.opts.request_timeout)
            .await?;
        let klippy_state = info["klippy_state"]
            .as_str()
            .unwrap_or("unknown")
            .to_string();
        if klippy_state == "ready" {
            if let Err(e) = self.resubscribe(true).await {
                warn!(error = %e, "subscribe failed");
            }
        }
        self.set_state(ConnState::Connected { klippy_state });
        self.emit(Event::Connected);
        Ok(())
    }

    fn set_klippy_state(&self, klippy_state: &str) {
        self.shared.state.send_if_modified(|s| match s {
            ConnState::Connected { klippy_state: k } if k != klippy_state => {
                *k = klippy_state.to_string();
                true
            }
            _ => false,
        });
    }
}

fn lock<T>(m: &Mutex<T>) -> std::sync::MutexGuard<'_, T> {
    m.lock().unwrap_or_else(std::sync::PoisonError::into_inner)
}

fn merge_status(into: &mut Map<String, Value>, diff: &Map<String, Value>) {
    for (obj, fields) in diff {
        match (into.get_mut(obj), fields) {
            (Some(Value::Object(old)), Value::Object(new)) => {
                for (k, v) in new {
                    old.insert(k.clone(), v.clone());
                }
            }
            _ => {
                into.insert(obj.clone(), fields.clone());
            }
        }
    }
}

enum Pending {
    Waiting {
        method: String,
        tx: oneshot::Sender<Result<Value, Error>>,
    },
}

async fn actor(
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
