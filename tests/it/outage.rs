//! Faults on the bench (issue 25 B): a session rides out Moonraker being stopped, Klipper owns
//! the heaters when klipcal is gone, and the page and `/api/status` answer at once while
//! Moonraker is down.

use std::time::{Duration, Instant};

use serde_json::{json, Value};

use crate::bench::{agent_listed, extension_request, poll, Bench, Daemon};
use crate::session::{reconfigure, session, settings};

/// A plate so slow that the soak is still going long after the outage (1 simulated second per
/// real second, a 2000 s plate).
const SLOW_PLANT: &str = r#"{"accel": 1, "bed": {"tau_plate_s": 2000.0, "tau_heater_s": 20.0}}"#;

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

/// The bed's target as Klipper has it.
async fn bed_target(bench: &Bench) -> Option<f64> {
    let v = bench
        .files()
        .get("/printer/objects/query?heater_bed=target")
        .await
        .ok()?;
    v["status"]["heater_bed"]["target"].as_f64()
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
async fn an_ab_soak_rides_out_moonraker_stopped_for_90_s_and_cancels_after() {
    let bench = Bench::start_with("corexy", Some(SLOW_PLANT));
    let d = Daemon::ready(&bench, &settings(600.0)).await;
    let base = d.page_url().await;
    let s = soaking_session(&bench, &d).await;
    let id = s["id"].clone();
    bench.stop_one("moonraker");
    // The outage lasts longer than the daemon's request timeout (30 s) three times over.
    let down = Instant::now();
    tokio::time::sleep(Duration::from_secs(10)).await;
    // A cancel from the page meanwhile answers at once that nothing can be stopped now, and
    // leaves the session to go on.
    let c = reqwest::Client::new();
    let t0 = Instant::now();
    let r = c
        .post(format!("{base}/api/cancel"))
        .header("content-type", "application/json")
        .body("{}")
        .send()
        .await
        .unwrap();
    let took = t0.elapsed();
    let v: Value = r.json().await.unwrap_or(Value::Null);
    assert!(took < Duration::from_secs(1), "cancel took {took:?}: {v}");
    let msg = v["error"]["message"].as_str().unwrap_or("");
    assert!(
        msg.contains("Moonraker is unreachable")
            && msg.contains("cancel again once Moonraker is back"),
        "{v}"
    );
    tokio::time::sleep(Duration::from_secs(90).saturating_sub(down.elapsed())).await;
    bench.start_one("moonraker");
    let files = bench.files();
    poll(Duration::from_secs(60), || async {
        agent_listed(&files).await.then_some(())
    })
    .await
    .unwrap_or_else(|| panic!("klipcal did not reconnect:\n{}", d.log_text()));
    // The session goes on: never failed, the bed still held at its target by the session.
    for _ in 0..10 {
        let s = session(&bench).await;
        assert_eq!(s["id"], id, "{s}");
        assert!(
            matches!(
                s["state"].as_str(),
                Some("heating" | "soaking" | "printing" | "holding" | "measuring")
            ),
            "the session did not survive the outage: {s}\n{}",
            d.log_text()
        );
        assert_eq!(bed_target(&bench).await, Some(60.0), "bed not held");
        tokio::time::sleep(Duration::from_secs(1)).await;
    }
    // It said so in its log.
    let back = poll(Duration::from_secs(30), || async {
        d.log_text()
            .contains("Moonraker is back; resuming the session")
            .then_some(())
    })
    .await;
    assert!(
        back.is_some(),
        "no resume after the outage:\n{}",
        d.log_text()
    );
    // The console said what happened, once Moonraker was back.
    let (m, _c) = bench.client(json!({}));
    m.wait_connected(Duration::from_secs(30)).await.unwrap();
    let h = crate::mainsail::history(&m).await;
    assert!(
        h.iter()
            .any(|(_, msg)| msg.contains("Moonraker was unreachable for")),
        "{h:?}"
    );
    // KLIPCAL_CANCEL, typed on the console, ends it with the heaters off.
    m.gcode("KLIPCAL_CANCEL").await.unwrap();
    wait_states(&bench, &d, &["cancelled"], Duration::from_secs(30)).await;
    let off = poll(Duration::from_secs(10), || async {
        (bed_target(&bench).await == Some(0.0)).then_some(())
    })
    .await;
    assert!(off.is_some(), "bed still on after KLIPCAL_CANCEL");
}

#[tokio::test]
async fn a_soak_whose_klipper_restarted_during_the_outage_ends_with_the_reason_once_back() {
    let bench = Bench::start_with("corexy", Some(SLOW_PLANT));
    let d = Daemon::ready(&bench, &settings(600.0)).await;
    let s = soaking_session(&bench, &d).await;
    bench.stop_one("moonraker");
    // Klipper restarts meanwhile (its host rebooted, a firmware restart): the bed is cold.
    bench.stop_one("klippy");
    bench.start_one("klippy");
    tokio::time::sleep(Duration::from_secs(35)).await;
    bench.start_one("moonraker");
    let failed = wait_states(&bench, &d, &["failed"], Duration::from_secs(90)).await;
    assert_eq!(failed["id"], s["id"]);
    let reason = failed["reason"].as_str().unwrap_or("");
    assert!(
        reason.contains("bed's target is now 0") && reason.contains("Klipper restarted"),
        "{failed}"
    );
    assert_eq!(bed_target(&bench).await, Some(0.0));
    let (m, _c) = bench.client(json!({}));
    m.wait_connected(Duration::from_secs(30)).await.unwrap();
    let h = crate::mainsail::history(&m).await;
    assert!(
        h.iter()
            .any(|(_, msg)| msg.contains("Moonraker was unreachable for"))
            && h.iter()
                .any(|(_, msg)| msg.contains("A/B calibration failed")
                    && msg.contains("Klipper restarted")
                    && msg.contains("heaters off")),
        "{h:?}"
    );
}

#[tokio::test]
async fn klippers_idle_timeout_turns_the_bed_off_when_the_daemon_is_killed_mid_soak() {
    let bench = Bench::start_with("corexy", Some(SLOW_PLANT));
    // Klipper's own idle_timeout, able to fire on the bench (tests/bench/klippy_extras/
    // klipcal_idle.py), with its configured timeout of an hour.
    reconfigure(&bench, |cfg| {
        cfg.replacen("[idle_timeout]", "[klipcal_idle]\n\n[idle_timeout]", 1)
    })
    .await;
    let soak_max_s = 20.0;
    let toml = settings(600.0).replace("soak_max_s = 600.0", &format!("soak_max_s = {soak_max_s}"));
    let mut d = Daemon::ready(&bench, &toml).await;
    soaking_session(&bench, &d).await;
    // The soak's first look at the bed (it bounds the idle timeout) comes right after.
    tokio::time::sleep(Duration::from_secs(3)).await;
    let started = Instant::now();
    d.child.kill().unwrap();
    d.child.wait().unwrap();
    // Klipper alone: the bed stays on for the soak's own limit (its remaining time plus a
    // minute's slack, src/jobs/soak.rs), and goes off by itself after it.
    let limit = Duration::from_secs_f64(soak_max_s + 60.0);
    tokio::time::sleep(Duration::from_secs(5)).await;
    assert_eq!(
        bed_target(&bench).await,
        Some(60.0),
        "the bed went off early"
    );
    let off = poll(limit + Duration::from_secs(20), || async {
        (bed_target(&bench).await == Some(0.0)).then_some(started.elapsed())
    })
    .await;
    match off {
        Some(after) => assert!(after <= limit + Duration::from_secs(5), "{after:?}"),
        None => panic!(
            "the bed was still on {:?} after klipcal was killed mid-soak",
            started.elapsed()
        ),
    }
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

#[tokio::test]
async fn a_thermal_mesh_capture_rides_out_moonraker_stopped_for_40_s_and_keeps_its_meshes() {
    use crate::mesh_job::{mesh_session, mesh_settings, PLANT};
    let bench = Bench::start_args("corexy", &["--variant", "mesh", "--plant-json", PLANT]);
    let d = Daemon::ready(&bench, &mesh_settings()).await;
    extension_request(&bench.files(), "klipcal_mesh_capture", json!({"bed": 60}))
        .await
        .unwrap();
    let first = poll(Duration::from_secs(300), || async {
        let s = mesh_session(&bench).await;
        (s["meshes"].as_u64().unwrap_or(0) >= 1).then_some(s)
    })
    .await
    .unwrap_or_else(|| panic!("no mesh stored\n{}", d.log_text()));
    let before: Vec<f64> = serde_json::from_value(first["frame_c"].clone()).unwrap();
    bench.stop_one("moonraker");
    // Longer than the daemon's request timeout (30 s).
    tokio::time::sleep(Duration::from_secs(40)).await;
    bench.start_one("moonraker");
    let done = poll(Duration::from_secs(600), || async {
        let s = mesh_session(&bench).await;
        matches!(s["state"].as_str(), Some("done" | "failed" | "cancelled")).then_some(s)
    })
    .await
    .unwrap_or_else(|| panic!("capture never ended\n{}", d.log_text()));
    assert_eq!(done["state"], "done", "{done}\n{}", d.log_text());
    let after: Vec<f64> = serde_json::from_value(done["frame_c"].clone()).unwrap();
    assert_eq!(&after[..before.len()], &before[..], "meshes lost");
    assert!(after.len() > before.len(), "{after:?}");
    assert!(
        d.log_text()
            .contains("Moonraker is back; resuming the session"),
        "{}",
        d.log_text()
    );
    assert_eq!(bed_target(&bench).await, Some(0.0), "heaters left on");
}
