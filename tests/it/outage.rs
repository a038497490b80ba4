//! Faults on the bench (issue 25 B): the page and `/api/status` answer at once while Moonraker
//! is down.

use std::time::{Duration, Instant};

use serde_json::{json, Value};

use crate::bench::{extension_request, poll, Bench, Daemon};
use crate::session::{session, settings};

/// Waits until the session is in one of `states`; panics with the status and the daemon's log.
async fn wait_states(bench: &Bench, d: &Daemon, states: &[&str], limit: Duration) -> Value {
    let got = poll(limit, || async {
        let s = session(bench).await;
        states.iter().any(|st| s["state"] == *st).then_some(s)
    })
    .await;
    match got {
        Some(s) => s,
        None => panic!(
            "session never in {states:?}: {}\n{}",
            session(bench).await,
            d.log_text()
        ),
    }
}

/// The daemon's own `/api/status`, and how long it took to answer.
async fn api_status(base: &str) -> (Value, Duration) {
    let c = reqwest::Client::builder()
        .timeout(Duration::from_secs(60))
        .build()
        .unwrap();
    let t0 = Instant::now();
    let v = c
        .get(format!("{base}/api/status"))
        .send()
        .await
        .unwrap()
        .json::<Value>()
        .await
        .unwrap_or(Value::Null);
    (v, t0.elapsed())
}

/// Starts an A/B session on a 60 °C bed and waits until it heats or soaks.
async fn soaking_session(bench: &Bench, d: &Daemon) -> Value {
    extension_request(&bench.files(), "klipcal_ab_start", json!({"bed": 60}))
        .await
        .unwrap();
    wait_states(bench, d, &["heating", "soaking"], Duration::from_secs(120)).await
}

#[tokio::test]
async fn the_page_and_api_status_answer_at_once_while_moonraker_is_down() {
    let bench = Bench::start("corexy");
    let d = Daemon::ready(&bench, &settings(600.0)).await;
    let base = d.page_url().await;
    let s = soaking_session(&bench, &d).await;
    bench.stop_one("moonraker");
    tokio::time::sleep(Duration::from_secs(2)).await;
    let (st, took) = api_status(&base).await;
    assert!(
        took < Duration::from_secs(1),
        "/api/status took {took:?}: {st}"
    );
    assert_eq!(st["connection"]["moonraker"], "unreachable", "{st}");
    assert!(
        st["connection"]["last_error"]
            .as_str()
            .is_some_and(|e| !e.is_empty()),
        "{st}"
    );
    assert_eq!(st["session"]["id"], s["id"], "{st}");
    let t0 = Instant::now();
    let page = reqwest::get(format!("{base}/"))
        .await
        .unwrap()
        .text()
        .await
        .unwrap();
    assert!(t0.elapsed() < Duration::from_secs(1), "{:?}", t0.elapsed());
    assert!(page.contains("Moonraker is unreachable"), "{page}");
    // The session's card is still there (from the database).
    assert!(
        page.contains(&format!("A/B calibration · session {} ·", s["id"])),
        "{page}"
    );
}
