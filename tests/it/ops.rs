//! One loop over klipcal's command table (issue 24 step 1, issue 25 A.3): every operation is
//! reached the way users reach it — its macro text run by Klipper through Moonraker's
//! `printer/gcode/script`, the remote method through Moonraker's `/server/extensions/request`,
//! and the daemon's own API — with typical and edge arguments, idle and inside a print. Klipper
//! raises no error other than klipcal's own refusal; an unknown argument is refused by name on
//! all three roads; a macro that pauses the print really pauses it; no operation disturbs a
//! print it does not own.

use std::time::Duration;

use klipcal::jobs::registry::all_ops;
use klipcal::jobs::table::{MacroBody, OpSpec};
use klipcal::moonraker::{Event, Moonraker};
use serde_json::{json, Value};

use crate::bench::{extension_request, poll, Bench, Daemon};

/// The macro line with each argument at its declared example (`lower`: names in lower case, as
/// a user may type them; Klipper upper-cases them).
fn typical(op: &OpSpec, lower: bool) -> String {
    let mut line = op.macro_name.to_string();
    for a in op.args {
        let name = if lower {
            a.name.to_string()
        } else {
            a.name.to_uppercase()
        };
        line.push_str(&format!(" {name}={}", a.example));
    }
    line
}

/// Runs `line` through Klipper and returns Klipper's error, if any, and the console lines that
/// followed until `done` says enough or `wait` passed.
async fn run(
    m: &Moonraker,
    line: &str,
    wait: Duration,
    done: impl Fn(&[String]) -> bool,
) -> (Option<String>, Vec<String>) {
    let mut rx = m.events();
    let outcome = m.gcode(line).await.err().map(|e| e.to_string());
    let mut lines = Vec::new();
    let deadline = tokio::time::Instant::now() + wait;
    while !done(&lines) {
        match tokio::time::timeout_at(deadline, rx.recv()).await {
            Ok(Ok(Event::GcodeResponse(l))) => lines.push(l),
            Ok(Ok(_)) | Ok(Err(tokio::sync::broadcast::error::RecvError::Lagged(_))) => {}
            _ => break,
        }
    }
    (outcome, lines)
}

/// Enough when klipcal answered (remote operations), or at once (local ones).
fn answered_if(remote: bool) -> impl Fn(&[String]) -> bool {
    move |lines| !remote || klipcal_answered(lines)
}

/// Whether klipcal answered on the console after saying it was asked (its answer, or its
/// refusal in red); a helper (`_KLIPCAL_…`, pressed in klipcal's dialogs) does not say it asks
/// (issue 26 A.4), so its answer counts from the start.
fn klipcal_answered(lines: &[String]) -> bool {
    let from = lines
        .iter()
        .position(|l| l.contains("asking the klipcal service..."))
        .map_or(0, |i| i + 1);
    lines[from..].iter().any(|l| {
        // An answer of several lines comes as one response (`// klipcal …`, issue 40).
        l.starts_with("klipcal ") || l.starts_with("// klipcal ") || l.starts_with("!! klipcal: ")
    })
}

/// The print's state (`print_stats.state`), empty when it cannot be read.
pub(crate) async fn print_state(m: &Moonraker) -> String {
    m.objects_query(json!({"print_stats": ["state"]}))
        .await
        .ok()
        .and_then(|v| v["print_stats"]["state"].as_str().map(str::to_string))
        .unwrap_or_default()
}

async fn wait_print_state(m: &Moonraker, want: &str, limit: Duration) -> bool {
    poll(limit, || async {
        (print_state(m).await == want).then_some(())
    })
    .await
    .is_some()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn every_operation_is_reachable_on_each_road_and_refuses_an_unknown_argument_by_name() {
    let bench = Bench::start("corexy");
    let d = Daemon::ready(&bench, "").await;
    let files = bench.files();
    let (m, _c) = bench.client(json!({}));
    m.wait_connected(Duration::from_secs(30)).await.unwrap();
    let base = d.page_url().await;
    let http = reqwest::Client::new();
    let ops = all_ops();
    assert!(ops.len() >= 20, "the table lost operations: {}", ops.len());

    // Idle: the unknown argument on every road, then typical and edge arguments.
    for op in ops {
        refuses_an_unknown_argument_on_every_road(op, &files, &http, &base, &m).await;
        typical_calls_are_answered(op, &m).await;
    }
    // Whatever the typical calls started ends here, heaters off.
    let _ = extension_request(&files, "klipcal_cancel", json!({})).await;

    // Inside a print klipcal does not own: nothing moves, heats or ends it, except the mesh
    // check, whose macro pauses it for klipcal (which resumes or cancels it).
    files
        .upload(
            "gcodes",
            "users.gcode",
            b"BENCH_SLEEP SECONDS=600\n".to_vec(),
        )
        .await
        .unwrap();
    for op in ops {
        if print_state(&m).await != "printing" {
            m.gcode("CANCEL_PRINT").await.ok();
            m.print_start("users.gcode").await.unwrap();
            assert!(
                wait_print_state(&m, "printing", Duration::from_secs(30)).await,
                "the user's print did not start"
            );
        }
        leaves_a_users_print_alone(op, &files, &m).await;
    }
    m.gcode("CANCEL_PRINT").await.ok();
}

/// Idle, an unknown argument is refused by name on every road: the remote method, the API
/// (400, the same message) and the macro (klipcal's refusal on the console; a macro that runs
/// in Klipper alone refuses it itself).
async fn refuses_an_unknown_argument_on_every_road(
    op: &OpSpec,
    files: &klipcal::moonraker::Files,
    http: &reqwest::Client,
    base: &str,
    m: &Moonraker,
) {
    let unknown = format!("{} ZZTOP=1", op.macro_name);
    let want = "unknown argument ZZTOP";
    match (op.method, op.body) {
        (Some(method), _) => {
            let e = extension_request(files, method, json!({"zztop": 1}))
                .await
                .expect_err(&format!("{method} took ZZTOP"));
            assert!(e.contains(want), "{method}: {e}");
            let path = op.http.expect("a remote operation has an HTTP path");
            let r = http
                .post(format!("{base}/api/{path}"))
                .header("content-type", "application/json")
                .body(json!({"zztop": 1}).to_string())
                .send()
                .await
                .unwrap();
            assert_eq!(r.status().as_u16(), 400, "/api/{path}");
            let v: Value = r.json().await.unwrap();
            assert_eq!(v["error"]["message"], json!(e), "/api/{path}");
            let (err, lines) = run(m, &unknown, Duration::from_secs(10), |l| {
                l.iter().any(|l| l.contains(want))
            })
            .await;
            assert_eq!(err, None, "{unknown}: Klipper raised an error");
            assert!(
                lines
                    .iter()
                    .any(|l| l.starts_with("!! klipcal: ") && l.contains(want)),
                "{unknown}: no refusal by name on the console: {lines:#?}"
            );
        }
        (None, MacroBody::Local(_)) => {
            // A macro that runs in Klipper alone refuses the parameter itself.
            let (err, _) = run(m, &unknown, Duration::ZERO, |_| true).await;
            assert!(
                err.as_deref().is_some_and(|e| e.contains(want)),
                "{unknown}: {err:?}"
            );
        }
        (None, MacroBody::Remote { .. }) => {
            panic!("{}: remote without a method", op.macro_name)
        }
    }
}

/// Idle, the macro bare and with its typical arguments (upper and lower case) raises no
/// Klipper error, and klipcal answers a remote one.
async fn typical_calls_are_answered(op: &OpSpec, m: &Moonraker) {
    for line in [
        op.macro_name.to_string(),
        typical(op, false),
        typical(op, true),
    ] {
        let remote = op.method.is_some();
        let (err, lines) = run(m, &line, Duration::from_secs(10), answered_if(remote)).await;
        assert_eq!(err, None, "{line}: Klipper raised an error");
        if op.method.is_some() {
            assert!(
                klipcal_answered(&lines),
                "{line}: klipcal did not answer: {lines:#?}"
            );
        }
    }
}

/// Inside a print klipcal does not own, the typical call leaves it printing (the mesh check's
/// macro pauses it for klipcal) and starts no session.
async fn leaves_a_users_print_alone(op: &OpSpec, files: &klipcal::moonraker::Files, m: &Moonraker) {
    let line = typical(op, false);
    let pauses = matches!(op.body, MacroBody::Remote { after, .. }
        if after.iter().any(|l| l.trim() == "PAUSE"));
    let remote = op.method.is_some();
    let (err, lines) = run(m, &line, Duration::from_secs(10), answered_if(remote)).await;
    assert_eq!(err, None, "{line} in a print: Klipper raised an error");
    if op.method.is_some() {
        assert!(
            klipcal_answered(&lines),
            "{line} in a print: klipcal did not answer: {lines:#?}"
        );
    }
    if pauses {
        let paused = poll(Duration::from_secs(10), || async {
            matches!(print_state(m).await.as_str(), "paused" | "cancelled").then_some(())
        })
        .await;
        assert!(paused.is_some(), "{line}: the print was not paused");
        assert!(
            lines.iter().all(|l| !l.contains("Malformed")),
            "{line}: {lines:#?}"
        );
    } else {
        assert_eq!(
            print_state(m).await,
            "printing",
            "{line} disturbed the user's print: {lines:#?}"
        );
    }
    let st = extension_request(files, "klipcal_status", json!({}))
        .await
        .unwrap();
    assert!(
        st["session"].is_null()
            || matches!(
                st["session"]["state"].as_str(),
                Some("cancelled" | "failed" | "converged" | "applied")
            ),
        "{line} started a session in a print: {}",
        st["session"]
    );
}
