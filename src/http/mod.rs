//! The daemon's own HTTP server: the page (`/`), the JSON API (`/api/…`) and the plots.
//! Every operation goes through [`crate::agent::dispatch`], the one entry point the remote
//! methods use too, so the page, curl and the macros get the same checks and messages. The
//! [`guard`] runs before every handler. Nothing a request carries becomes G-code text here:
//! requests become typed arguments that the calibrations validate.

pub mod guard;
pub mod page;

use std::net::SocketAddr;
use std::sync::Arc;

use axum::body::Bytes;
use axum::extract::{ConnectInfo, DefaultBodyLimit, Path, Query, Request, State};
use axum::http::{header, HeaderValue, StatusCode};
use axum::middleware::Next;
use axum::response::{IntoResponse, Response};
use axum::routing::{get, post};
use axum::Router;
use serde_json::{json, Value};
use tokio_util::sync::CancellationToken;

use crate::agent::{dispatch, result_json};
use crate::calib::soak::SoakParams;
use crate::config::HttpConfig;
use crate::jobs::{Calibrations, Route};
use crate::moonraker::{Moonraker, RpcError};
use crate::plots;

/// Largest request body accepted (a long list of readings is a few hundred bytes).
pub(crate) const MAX_BODY_BYTES: usize = 64 * 1024;

/// What the handlers share.
pub(crate) struct Http {
    m: Moonraker,
    cals: Option<Calibrations>,
    guard: guard::Guard,
    soak: SoakParams,
}

type Shared = Arc<Http>;

/// The page's address as a user types it on a phone: the bound address when it names one; for
/// an unspecified bind (`0.0.0.0`, every interface) the host's address on its default route,
/// else its name with `.local` (what Mainsail's own hosts answer to); a loopback bind says the
/// page is on this host only.
#[must_use]
pub(crate) fn page_address(
    bound: SocketAddr,
    primary_ip: Option<std::net::IpAddr>,
    hostname: Option<&str>,
) -> String {
    let port = bound.port();
    let host = |ip: std::net::IpAddr| match ip {
        std::net::IpAddr::V6(v6) => format!("[{v6}]"),
        v4 => v4.to_string(),
    };
    if bound.ip().is_loopback() {
        return format!(
            "http://{}:{port}/ (this host only: [http] bind)",
            host(bound.ip())
        );
    }
    if !bound.ip().is_unspecified() {
        return format!("http://{}:{port}/", host(bound.ip()));
    }
    match (primary_ip, hostname.filter(|h| !h.is_empty())) {
        (Some(ip), _) if !ip.is_loopback() && !ip.is_unspecified() => {
            format!("http://{}:{port}/", host(ip))
        }
        (_, Some(name)) if name.contains('.') => format!("http://{name}:{port}/"),
        (_, Some(name)) => format!("http://{name}.local:{port}/"),
        _ => format!("port {port} of this host"),
    }
}

/// This host's address on its default route (no packet is sent: a UDP socket only picks the
/// source address the kernel would use), and its name.
fn host_identity() -> (Option<std::net::IpAddr>, Option<String>) {
    let ip = std::net::UdpSocket::bind("0.0.0.0:0")
        .and_then(|s| s.connect("192.0.2.1:9").map(|()| s))
        .and_then(|s| s.local_addr())
        .ok()
        .map(|a| a.ip());
    let name = std::fs::read_to_string("/proc/sys/kernel/hostname")
        .ok()
        .map(|n| n.trim().to_string());
    (ip, name)
}

/// [`page_address`] of the bound address on this host.
#[must_use]
pub fn page_address_here(bound: SocketAddr) -> String {
    let (ip, name) = host_identity();
    page_address(bound, ip, name.as_deref())
}

/// Why the page could not start, in a user's words: the address and, when it is taken, what
/// to do about it.
#[must_use]
pub(crate) fn page_off_words(bind: &str, e: &anyhow::Error) -> String {
    let in_use = e.chain().any(|c| {
        c.downcast_ref::<std::io::Error>()
            .is_some_and(|io| io.kind() == std::io::ErrorKind::AddrInUse)
    }) || format!("{e:#}").contains("in use");
    if in_use {
        format!(
            "another program listens on {bind} ([http] bind in klipcal.toml); set another port \
             there (e.g. 7151) and restart klipcal"
        )
    } else {
        format!("{e:#}")
    }
}

/// Binds `[http] bind` and serves until `cancel`; returns the bound address.
///
/// # Errors
/// Bad settings or an address that cannot be bound (in use, not this host's).
pub(crate) async fn start(
    cfg: &HttpConfig,
    m: Moonraker,
    cals: Option<Calibrations>,
    soak: SoakParams,
    cancel: CancellationToken,
) -> anyhow::Result<SocketAddr> {
    let shared = Arc::new(Http {
        m,
        cals,
        guard: guard::Guard::new(cfg)?,
        soak,
    });
    let listener = tokio::net::TcpListener::bind(&cfg.bind)
        .await
        .map_err(|e| anyhow::anyhow!("cannot listen on {} ([http] bind): {e}", cfg.bind))?;
    let addr = listener.local_addr()?;
    let app = router(shared).into_make_service_with_connect_info::<SocketAddr>();
    tokio::spawn(async move {
        let served = axum::serve(listener, app)
            .with_graceful_shutdown(async move { cancel.cancelled().await })
            .await;
        if let Err(e) = served {
            tracing::error!(error = %e, "the HTTP server stopped");
        }
    });
    Ok(addr)
}

fn router(shared: Shared) -> Router {
    Router::new()
        .route("/", get(index))
        .route("/api/status", get(status).post(status_op))
        .route("/api/sessions", get(sessions))
        .route("/api/sessions/{id}", get(session))
        .route("/api/sessions/{id}/diagram.svg", get(diagram))
        .route("/api/sessions/{id}/convergence.svg", get(convergence))
        .route("/api/plots/soak.svg", get(soak_plot))
        .route("/api/backlash/snapshot.jpg", get(backlash_snapshot))
        .route("/api/backlash/live.jpg", get(backlash_live))
        .route("/api/{*op}", post(operation))
        .fallback(not_found)
        .method_not_allowed_fallback(method_not_allowed)
        .layer(DefaultBodyLimit::max(MAX_BODY_BYTES))
        .layer(axum::middleware::from_fn_with_state(
            shared.clone(),
            guarded,
        ))
        .with_state(shared)
}

async fn guarded(
    State(h): State<Shared>,
    ConnectInfo(peer): ConnectInfo<SocketAddr>,
    req: Request,
    next: Next,
) -> Response {
    if let Err((code, message)) = h.guard.check(peer.ip(), req.method(), req.headers()) {
        tracing::info!(%peer, path = %req.uri().path(), %message, "HTTP request refused");
        return error(code, &message);
    }
    let mut res = next.run(req).await;
    let hd = res.headers_mut();
    hd.insert(header::CACHE_CONTROL, HeaderValue::from_static("no-store"));
    hd.insert(
        header::X_CONTENT_TYPE_OPTIONS,
        HeaderValue::from_static("nosniff"),
    );
    hd.insert(
        header::CONTENT_SECURITY_POLICY,
        HeaderValue::from_static(
            "default-src 'self'; img-src 'self' data:; style-src 'self' 'unsafe-inline'; \
             script-src 'self' 'unsafe-inline'; connect-src 'self'",
        ),
    );
    res
}

/// A JSON error in the shape the agent's HTTP callers get.
fn error(code: StatusCode, message: &str) -> Response {
    let body = json!({"ok": false, "error": {"code": code.as_u16(), "message": message}});
    (code, axum::Json(body)).into_response()
}

fn answer(outcome: Result<Value, RpcError>) -> Response {
    let code = match &outcome {
        Ok(_) => StatusCode::OK,
        Err(e) => match e.code {
            400 => StatusCode::BAD_REQUEST,
            404 | -32601 => StatusCode::NOT_FOUND,
            409 => StatusCode::CONFLICT,
            503 => StatusCode::SERVICE_UNAVAILABLE,
            _ => StatusCode::INTERNAL_SERVER_ERROR,
        },
    };
    (code, axum::Json(result_json(outcome))).into_response()
}

/// A method the path does not take (a POST to a page, a GET of an operation): said, not an
/// empty 405.
async fn method_not_allowed(method: axum::http::Method, uri: axum::http::Uri) -> Response {
    let path = uri.path();
    let how = if path.starts_with("/api/") && Route::of_path(&path[5..]).is_some() {
        "it is an operation: POST it with a JSON body of arguments"
    } else {
        "it is read with GET; operations are POSTs under /api/ (see docs/page-and-api.md)"
    };
    error(
        StatusCode::METHOD_NOT_ALLOWED,
        &format!("{method} {path} is not accepted: {how}"),
    )
}

async fn not_found() -> Response {
    error(
        StatusCode::NOT_FOUND,
        "no such page; the page is at / and the API under /api/ (see docs/page-and-api.md)",
    )
}

async fn status(State(h): State<Shared>) -> Response {
    answer(dispatch(&h.m, h.cals.as_ref(), Route::status(), &json!({})).await)
}

fn no_sessions() -> Response {
    error(
        StatusCode::SERVICE_UNAVAILABLE,
        "calibration sessions are not available (no session database)",
    )
}

#[derive(serde::Deserialize)]
struct ListQuery {
    limit: Option<usize>,
}

async fn sessions(
    State(h): State<Shared>,
    q: Result<Query<ListQuery>, axum::extract::rejection::QueryRejection>,
) -> Response {
    let Some(cals) = &h.cals else {
        return no_sessions();
    };
    let limit = match q {
        Ok(Query(q)) => q.limit.unwrap_or(50).clamp(1, 500),
        Err(_) => {
            return error(
                StatusCode::BAD_REQUEST,
                "limit: expected a whole number, e.g. /api/sessions?limit=20",
            )
        }
    };
    match cals.sessions(limit) {
        Ok(list) => answer(Ok(json!({"sessions": list}))),
        Err(e) => error(StatusCode::INTERNAL_SERVER_ERROR, &format!("{e:#}")),
    }
}

fn session_doc(h: &Http, id: &str) -> Result<Value, (StatusCode, String)> {
    let Some(cals) = &h.cals else {
        return Err((
            StatusCode::SERVICE_UNAVAILABLE,
            "calibration sessions are not available (no session database)".into(),
        ));
    };
    let Ok(id) = id.parse::<i64>() else {
        return Err((
            StatusCode::BAD_REQUEST,
            format!("session id {id:?}: expected a whole number, e.g. /api/sessions/3"),
        ));
    };
    match cals.session(id) {
        Ok(Some(v)) => Ok(v),
        Ok(None) => Err((
            StatusCode::NOT_FOUND,
            format!("no session {id}; /api/sessions lists them"),
        )),
        Err(e) => Err((StatusCode::INTERNAL_SERVER_ERROR, format!("{e:#}"))),
    }
}

async fn session(State(h): State<Shared>, Path(id): Path<String>) -> Response {
    match session_doc(&h, &id) {
        Ok(v) => answer(Ok(json!({"session": v}))),
        Err((code, why)) => error(code, &why),
    }
}

fn svg(text: String) -> Response {
    (
        [(header::CONTENT_TYPE, "image/svg+xml; charset=utf-8")],
        text,
    )
        .into_response()
}

/// The session's layout diagram (as uploaded next to the job), for the readings form.
async fn diagram(State(h): State<Shared>, Path(id): Path<String>) -> Response {
    let doc = match session_doc(&h, &id) {
        Ok(v) => v,
        Err((code, why)) => return error(code, &why),
    };
    match fetch_diagram(&h, &doc).await {
        Some(text) => svg(text),
        None => error(
            StatusCode::NOT_FOUND,
            &format!("session {id} has no layout diagram"),
        ),
    }
}

async fn fetch_diagram(h: &Http, doc: &Value) -> Option<String> {
    let path = doc["diagram"].as_str()?;
    let cals = h.cals.as_ref()?;
    let bytes = cals.core().files().download("config", path).await.ok()?;
    let text = String::from_utf8(bytes).ok()?;
    text.trim_start().starts_with("<svg").then_some(text)
}

async fn convergence(State(h): State<Shared>, Path(id): Path<String>) -> Response {
    let doc = match session_doc(&h, &id) {
        Ok(v) => v,
        Err((code, why)) => return error(code, &why),
    };
    match plots::convergence_of_status(&doc) {
        Ok(text) => svg(text),
        Err(why) => error(StatusCode::NOT_FOUND, &why),
    }
}

/// The bed over Moonraker's temperature store (~20 min at 1 Hz) with the soak detector's fit
/// replayed over the same samples.
async fn soak_plot(State(h): State<Shared>) -> Response {
    let live = h
        .cals
        .as_ref()
        .and_then(|c| c.core().ask_state().live.clone());
    match crate::jobs::soak::soak_picture(&h.m, &h.soak, live).await {
        Ok(text) => svg(text),
        Err(why) => error(StatusCode::SERVICE_UNAVAILABLE, &why),
    }
}

#[derive(serde::Deserialize)]
struct SeqQuery {
    seq: Option<u64>,
}

/// The backlash measurement's camera frame (`?seq=N` as the status names it, or the newest),
/// served from klipcal's memory: the page shows it even where the webcam's own address is not
/// reachable (inside Mainsail's iframe, on a phone).
async fn backlash_snapshot(
    State(h): State<Shared>,
    q: Result<Query<SeqQuery>, axum::extract::rejection::QueryRejection>,
) -> Response {
    let Some(cals) = &h.cals else {
        return no_sessions();
    };
    let Ok(Query(q)) = q else {
        return error(
            StatusCode::BAD_REQUEST,
            "seq: expected a whole number, e.g. /api/backlash/snapshot.jpg?seq=3",
        );
    };
    match cals.snapshot_jpeg(q.seq) {
        Some(jpeg) => ([(header::CONTENT_TYPE, "image/jpeg")], jpeg).into_response(),
        None => error(
            StatusCode::NOT_FOUND,
            &match q.seq {
                Some(n) => format!(
                    "camera frame {n} is no longer kept (klipcal keeps the newest few); \
                     /api/status names the newest"
                ),
                None => "no camera frame since klipcal started: frames are kept while \
                         KLIPCAL_BACKLASH_CAMERA measures"
                    .to_string(),
            },
        ),
    }
}

/// A frame taken now from the nozzle camera (`[backlash] webcam`), served by klipcal: the
/// page's live picture beside its jog buttons, reachable where the webcam's own address is
/// not (inside Mainsail's iframe, on a phone).
async fn backlash_live(State(h): State<Shared>) -> Response {
    let Some(cals) = &h.cals else {
        return no_sessions();
    };
    match cals.live_jpeg().await {
        Ok(jpeg) => (
            [
                (header::CONTENT_TYPE, "image/jpeg"),
                (header::CACHE_CONTROL, "no-store"),
            ],
            jpeg,
        )
            .into_response(),
        Err(e) => error(StatusCode::BAD_GATEWAY, &format!("{e:#}")),
    }
}

async fn index(State(h): State<Shared>) -> Response {
    let st = dispatch(&h.m, h.cals.as_ref(), Route::status(), &json!({})).await;
    let status = result_json(st);
    let diagram = match status.get("session") {
        Some(s) if matches!(s["state"].as_str(), Some("measuring" | "solved")) => {
            fetch_diagram(&h, s).await
        }
        _ => None,
    };
    (
        [(header::CONTENT_TYPE, "text/html; charset=utf-8")],
        page::render(&status, diagram.as_deref()),
    )
        .into_response()
}

/// `POST /api/status`: the status as an operation (arguments checked like any other's).
async fn status_op(
    State(h): State<Shared>,
    body: Result<Bytes, axum::extract::rejection::BytesRejection>,
) -> Response {
    run_operation(&h, "status", body).await
}

async fn operation(
    State(h): State<Shared>,
    Path(op): Path<String>,
    body: Result<Bytes, axum::extract::rejection::BytesRejection>,
) -> Response {
    run_operation(&h, &op, body).await
}

async fn run_operation(
    h: &Http,
    op: &str,
    body: Result<Bytes, axum::extract::rejection::BytesRejection>,
) -> Response {
    let Some(route) = Route::of_path(op) else {
        let known = crate::jobs::registry::operation_paths();
        return error(
            StatusCode::NOT_FOUND,
            &format!("unknown operation /api/{op}; known: {}", known.join(", ")),
        );
    };
    let body = match body {
        Ok(b) => b,
        Err(rej) if rej.status() == StatusCode::PAYLOAD_TOO_LARGE => {
            return error(
                StatusCode::PAYLOAD_TOO_LARGE,
                &format!(
                    "the request body is over the limit of {} KiB (a long list of readings is a \
                     few hundred bytes)",
                    MAX_BODY_BYTES / 1024
                ),
            )
        }
        Err(rej) => return error(rej.status(), &format!("request body: {}", rej.body_text())),
    };
    let mut args = if body.iter().all(u8::is_ascii_whitespace) {
        json!({})
    } else {
        match serde_json::from_slice::<Value>(&body) {
            Ok(v @ Value::Object(_)) => v,
            Ok(_) => {
                return error(
                    StatusCode::BAD_REQUEST,
                    "expected a JSON object of arguments, e.g. {\"pair\": \"A-D1\", \"values\": [10.02, 10.03]}",
                )
            }
            Err(e) => {
                return error(
                    StatusCode::BAD_REQUEST,
                    &format!("the body is not valid JSON ({e}); expected an object of arguments"),
                )
            }
        }
    };
    if let (Some(flag), Value::Object(o)) = (route.sets, &mut args) {
        o.insert(flag.into(), json!(1));
    }
    tracing::info!(%op, "HTTP call");
    let outcome = dispatch(&h.m, h.cals.as_ref(), route, &args).await;
    // An operation the table marks (the cancel) is said on the console too: a user at the
    // printer's front end sees why the session stopped (a macro's answer reaches the console
    // by the agent).
    if let (Some(echo), Ok(v)) = (route.spec.echo, &outcome) {
        let said = v["message"].as_str().unwrap_or(echo.fallback).to_string();
        let m = h.m.clone();
        tokio::spawn(async move {
            crate::jobs::core::console::say(&m, &format!("klipcal: {said} ({})", echo.note)).await;
        });
    }
    answer(outcome)
}

#[cfg(test)]
mod address_tests {
    use super::page_address;

    #[test]
    fn the_pages_address_is_one_a_phone_can_open() {
        let any = "0.0.0.0:7150".parse().unwrap();
        let lan = "192.168.1.23".parse().ok();
        assert_eq!(
            page_address(any, lan, Some("voron")),
            "http://192.168.1.23:7150/"
        );
        assert_eq!(
            page_address(any, None, Some("voron")),
            "http://voron.local:7150/"
        );
        assert_eq!(
            page_address(any, None, Some("voron.lan")),
            "http://voron.lan:7150/"
        );
        assert_eq!(
            page_address("10.0.0.5:7151".parse().unwrap(), None, None),
            "http://10.0.0.5:7151/"
        );
        assert!(
            page_address("127.0.0.1:7150".parse().unwrap(), lan, None).contains("this host only")
        );
        assert_eq!(page_address(any, None, None), "port 7150 of this host");
    }
}
