//! The cloneable handle to the Moonraker connection and the types it carries. One task owns
//! the socket (`connection`, started by [`Moonraker::spawn`]); handles send `(request,
//! oneshot)` over a channel and await the reply. The actor identifies as an agent, registers
//! remote methods and subscriptions again after every reconnect (`setup`, here), fans
//! notifications out to subscribers, and hands agent calls (from macros and
//! `/server/extensions/request`) to the daemon. It must not know what the calls mean. The typed
//! queries on the handle are in `queries`.

use std::sync::{Arc, Mutex};
use std::time::Duration;

use serde_json::{json, Map, Value};
use tokio::sync::{broadcast, mpsc, oneshot, watch};
use tokio_util::sync::CancellationToken;
use tracing::{debug, warn};

use super::protocol::RpcError;
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
    pub(super) id: Value,
    pub(super) tx: mpsc::UnboundedSender<Cmd>,
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
pub(super) enum Cmd {
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

pub(super) struct Shared {
    pub(super) opts: ClientOptions,
    pub(super) tx: mpsc::UnboundedSender<Cmd>,
    pub(super) events: broadcast::Sender<Event>,
    pub(super) state: watch::Sender<ConnState>,
    pub(super) status: Mutex<Map<String, Value>>,
    pub(super) subscriptions: Mutex<Map<String, Value>>,
    pub(super) cancel: CancellationToken,
    /// Set once this client has identified; a refusal after that is not fatal.
    pub(super) identified_once: std::sync::atomic::AtomicBool,
    /// Why the client gave up for good (Moonraker refused to identify the agent).
    pub(super) fatal: Mutex<Option<String>>,
    /// The websocket is open (the client may still be identifying itself).
    pub(super) socket_open: std::sync::atomic::AtomicBool,
    /// Where klipcal's console scripts go (Klipper's API socket or Moonraker; `klippy`).
    pub(super) console_route: Mutex<super::klippy::ConsoleRoute>,
}

/// The cloneable handle to the Moonraker connection.
#[derive(Clone)]
pub struct Moonraker {
    pub(super) shared: Arc<Shared>,
}

impl std::fmt::Debug for Moonraker {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Moonraker")
            .field("url", &self.shared.opts.url)
            .finish()
    }
}

impl Moonraker {
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

    pub(super) async fn call_raw(
        &self,
        method: &str,
        params: Value,
        limit: Duration,
    ) -> Result<Value, Error> {
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

    pub(super) async fn resubscribe(&self, raw: bool) -> Result<Map<String, Value>, Error> {
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

    pub(super) fn set_state(&self, s: ConnState) {
        self.shared.state.send_replace(s);
    }

    pub(super) fn emit(&self, e: Event) {
        let _ = self.shared.events.send(e);
    }

    /// After connect: identify, register remote methods, subscribe when Klipper is ready.
    pub(super) async fn setup(&self) -> Result<(), Error> {
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

    pub(super) fn set_klippy_state(&self, klippy_state: &str) {
        self.shared.state.send_if_modified(|s| match s {
            ConnState::Connected { klippy_state: k } if k != klippy_state => {
                *k = klippy_state.to_string();
                true
            }
            _ => false,
        });
    }
}

pub(super) fn lock<T>(m: &Mutex<T>) -> std::sync::MutexGuard<'_, T> {
    m.lock().unwrap_or_else(std::sync::PoisonError::into_inner)
}

pub(super) fn merge_status(into: &mut Map<String, Value>, diff: &Map<String, Value>) {
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
