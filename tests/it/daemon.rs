//! The foundation against the bench: agent identity, status updates, G-code, upload + print,
//! a macro reaching the daemon, `klipcal_status` over HTTP, surviving Moonraker and Klipper
//! restarts, clean SIGTERM shutdown, and `klipcal check`.

use std::process::Command;
use std::time::Duration;

use klipcal::moonraker::{Event, Moonraker};
use serde_json::{json, Value};

use crate::bench::{agent_listed, extension_request, klipcal_ok, poll, wait_event, Bench, Daemon};

const LONG: Duration = Duration::from_secs(30);

async fn daemon_ready(bench: &Bench) -> Daemon {
    Daemon::ready(bench, "").await
}

/// Runs KLIPCAL_STATUS from the console and waits for the daemon's RESPOND line.
async fn macro_round_trip(m: &Moonraker) -> Option<String> {
    let mut rx = m.events();
    m.gcode("KLIPCAL_STATUS").await.ok()?;
    let e = wait_event(&mut rx, Duration::from_secs(10), |e| {
        // The status has several lines: one response `// klipcal …⏎// …` (issue 40 item 6).
        matches!(e, Event::GcodeResponse(l) if l.trim_start_matches("// ").starts_with("klipcal") && l.contains("rotation_distance"))
    })
    .await?;
    match e {
        Event::GcodeResponse(l) => Some(l),
        _ => None,
    }
}

#[tokio::test]
async fn the_daemon_identifies_as_an_agent_named_klipcal() {
    let bench = Bench::start("corexy");
    let _d = daemon_ready(&bench).await;
    let v = bench.files().get("/server/extensions/list").await.unwrap();
    let agent = v["agents"]
        .as_array()
        .unwrap()
        .iter()
        .find(|a| a["name"] == "klipcal")
        .cloned()
        .unwrap();
    assert_eq!(agent["version"], env!("CARGO_PKG_VERSION"));
}

#[tokio::test]
async fn status_updates_arrive_several_times_a_second() {
    let bench = Bench::start("corexy");
    let (m, _c) =
        bench.client(json!({"heater_bed": ["temperature", "power"], "extruder": ["temperature"]}));
    m.wait_connected(LONG).await.unwrap();
    // Heat so the plant's temperatures keep changing.
    m.gcode("SET_HEATER_TEMPERATURE HEATER=heater_bed TARGET=60")
        .await
        .unwrap();
    let mut rx = m.events();
    let start = tokio::time::Instant::now();
    let mut n = 0;
    while start.elapsed() < Duration::from_secs(3) {
        if wait_event(&mut rx, Duration::from_secs(1), |e| {
            matches!(e, Event::Status(_))
        })
        .await
        .is_some()
        {
            n += 1;
        }
    }
    assert!(n >= 6, "only {n} status updates in 3 s");
    let status = m.status();
    assert!(
        status["heater_bed"]["temperature"].as_f64().is_some(),
        "{status:?}"
    );
}

#[tokio::test]
async fn gcode_runs_and_klipper_errors_come_back_as_errors() {
    let bench = Bench::start("corexy");
    let (m, _c) = bench.client(json!({}));
    m.wait_connected(LONG).await.unwrap();
    m.gcode("G28\nG90\nG1 X100 Y50 F6000\nM400").await.unwrap();
    let st = m
        .objects_query(json!({"toolhead": ["position"]}))
        .await
        .unwrap();
    let pos = &st["toolhead"]["position"];
    assert_eq!(
        (pos[0].as_f64(), pos[1].as_f64()),
        (Some(100.0), Some(50.0)),
        "{pos}"
    );
    let err = m.gcode("G1 X9999").await.unwrap_err();
    assert!(err.is_refusal(), "{err}");
    assert!(err.to_string().contains("out of range"), "{err}");
    // An unknown command is not an RPC error: Klipper says so on the console.
    let mut rx = m.events();
    m.gcode("NOT_A_COMMAND_KC").await.unwrap();
    let e = wait_event(&mut rx, Duration::from_secs(5), |e| {
        matches!(e, Event::GcodeResponse(l) if l.contains("Unknown command") && l.contains("NOT_A_COMMAND_KC"))
    })
    .await;
    assert!(e.is_some());
}

#[tokio::test]
async fn an_uploaded_job_prints_to_completion() {
    let bench = Bench::start("corexy");
    let (m, _c) = bench.client(json!({"print_stats": ["state", "filename"]}));
    m.wait_connected(LONG).await.unwrap();
    let job = "G28\nG90\nG1 X20 Y20 Z5 F6000\nG1 X120 Y20\nG1 X120 Y120\nM400\n";
    let r = bench
        .files()
        .upload("gcodes", "klipcal/it_square.gcode", job.as_bytes().to_vec())
        .await
        .unwrap();
    assert_eq!(r["item"]["path"], "klipcal/it_square.gcode", "{r}");
    let back = bench
        .files()
        .download("gcodes", "klipcal/it_square.gcode")
        .await
        .unwrap();
    assert_eq!(back, job.as_bytes());
    m.print_start("klipcal/it_square.gcode").await.unwrap();
    let done = poll(LONG, || async {
        let st = m
            .objects_query(json!({"print_stats": ["state", "filename"]}))
            .await
            .ok()?;
        (st["print_stats"]["state"] == "complete").then(|| st["print_stats"]["filename"].clone())
    })
    .await;
    assert_eq!(done, Some(json!("klipcal/it_square.gcode")));
}

#[tokio::test]
async fn a_macro_reaches_the_daemon_and_its_answer_shows_on_the_console() {
    let bench = Bench::start("corexy");
    let _d = daemon_ready(&bench).await;
    let (m, _c) = bench.client(json!({}));
    m.wait_connected(LONG).await.unwrap();
    let line = macro_round_trip(&m).await.expect("no RESPOND from klipcal");
    assert!(line.contains("stepper_x rotation_distance 40"), "{line}");
}

#[tokio::test]
async fn klipcal_status_over_http_returns_the_printer_summary() {
    let bench = Bench::start("corexy");
    let _d = daemon_ready(&bench).await;
    let v = extension_request(&bench.files(), "klipcal_status", json!({}))
        .await
        .unwrap();
    assert_eq!(v["daemon"]["version"], env!("CARGO_PKG_VERSION"));
    assert_eq!(v["connection"]["moonraker"], "connected");
    assert_eq!(v["printer"]["kinematics"], "corexy");
    assert_eq!(
        v["printer"]["steppers"][0]["rotation_distance_mm"],
        json!(40.0)
    );
    assert_eq!(v["printer"]["features"]["exclude_object"], json!(true));
    let err = extension_request(&bench.files(), "klipcal_nope", json!({}))
        .await
        .unwrap_err();
    assert!(
        err.contains("unknown method") && err.contains("klipcal_status"),
        "{err}"
    );
}

#[tokio::test]
async fn the_daemon_survives_moonraker_restarting() {
    let bench = Bench::start("corexy");
    let d = daemon_ready(&bench).await;
    bench.stop_one("moonraker");
    tokio::time::sleep(Duration::from_millis(500)).await;
    bench.start_one("moonraker");
    let files = bench.files();
    let listed = poll(LONG, || async { agent_listed(&files).await.then_some(()) }).await;
    assert!(
        listed.is_some(),
        "klipcal did not come back:\n{}",
        d.log_text()
    );
    let (m, _c) = bench.client(json!({}));
    m.wait_connected(LONG).await.unwrap();
    // Klipper may still be connecting to the new Moonraker: retry until the macro answers.
    let line = poll(LONG, || macro_round_trip(&m)).await;
    assert!(
        line.is_some(),
        "macro no longer reaches klipcal:\n{}",
        d.log_text()
    );
}

#[tokio::test]
async fn the_daemon_survives_a_firmware_restart() {
    let bench = Bench::start("corexy");
    let d = daemon_ready(&bench).await;
    let (m, _c) = bench.client(json!({}));
    m.wait_connected(LONG).await.unwrap();
    let mut rx = m.events();
    m.firmware_restart().await.unwrap();
    let ready = wait_event(&mut rx, LONG, |e| *e == Event::KlippyReady).await;
    assert!(ready.is_some(), "Klipper did not come back ready");
    let line = poll(LONG, || macro_round_trip(&m)).await;
    assert!(
        line.is_some(),
        "macro no longer reaches klipcal:\n{}",
        d.log_text()
    );
}

#[tokio::test]
async fn sigterm_stops_the_daemon_cleanly_within_two_seconds() {
    let bench = Bench::start("corexy");
    let mut d = daemon_ready(&bench).await;
    let st = d
        .terminate(Duration::from_secs(2))
        .expect("still running 2 s after SIGTERM");
    assert!(st.success(), "exit status {st:?}");
    assert!(d.log_text().contains("klipcal stopped"), "{}", d.log_text());
    let files = bench.files();
    let gone = poll(Duration::from_secs(5), || async {
        (!agent_listed(&files).await).then_some(())
    })
    .await;
    assert!(gone.is_some(), "Moonraker still lists the agent");
}

#[tokio::test]
async fn sigterm_waits_for_every_session_task_before_it_stops() {
    // Issue 24 step 6: the runner of a soaking session and the hold watchdog are the daemon's
    // tasks; shutdown waits for them (within its deadline) before it closes the socket.
    let bench = Bench::start("corexy");
    let mut d = daemon_ready(&bench).await;
    let files = bench.files();
    extension_request(&files, "klipcal_ab_start", json!({"bed": 60}))
        .await
        .unwrap();
    let heating = poll(Duration::from_secs(60), || async {
        let st = extension_request(&files, "klipcal_status", json!({}))
            .await
            .ok()?;
        matches!(st["session"]["state"].as_str(), Some("heating" | "soaking")).then_some(())
    })
    .await;
    assert!(heating.is_some(), "no session heating:\n{}", d.log_text());
    let st = d
        .terminate(Duration::from_secs(3))
        .expect("still running 3 s after SIGTERM");
    assert!(st.success(), "exit status {st:?}");
    let log = d.log_text();
    assert!(
        log.contains("every session task stopped"),
        "shutdown did not wait for the session tasks:\n{log}"
    );
    let stopped = log.find("every session task stopped").unwrap();
    assert!(log[stopped..].contains("klipcal stopped"), "{log}");
}

#[test]
fn check_prints_a_correct_summary_of_the_corexy_bench() {
    let bench = Bench::start("corexy");
    let out = Command::new(env!("CARGO_BIN_EXE_klipcal"))
        .args(["check", "--moonraker", &bench.ws_url()])
        .env("HOME", bench.dir.path())
        .output()
        .unwrap();
    let text = String::from_utf8_lossy(&out.stdout);
    assert!(
        out.status.success(),
        "{text}\n{}",
        String::from_utf8_lossy(&out.stderr)
    );
    assert!(text.contains("Kinematics      corexy"), "{text}");
    assert!(
        text.contains("stepper_x       rotation_distance 40 mm"),
        "{text}"
    );
    assert!(
        text.contains("Bed limits      X 0..300 mm, Y 0..300 mm"),
        "{text}"
    );
    assert!(text.contains("heater_bed"), "{text}");
    assert!(text.contains("PRINT_START macro           yes"), "{text}");
    let out = Command::new(env!("CARGO_BIN_EXE_klipcal"))
        .args(["check", "--json", "--moonraker", &bench.ws_url()])
        .env("HOME", bench.dir.path())
        .output()
        .unwrap();
    let v: Value = serde_json::from_slice(&out.stdout).unwrap();
    assert_eq!(v["steppers"][1]["name"], "stepper_y");
    assert_eq!(v["features"]["skew_correction"], json!(true));
}

#[test]
fn check_on_the_cartesian_bench_reports_cartesian_kinematics() {
    let bench = Bench::start("cartesian");
    let out = klipcal_ok(
        Command::new(env!("CARGO_BIN_EXE_klipcal"))
            .args(["check", "--json", "--moonraker", &bench.ws_url()])
            .env("HOME", bench.dir.path()),
    );
    let v: Value = serde_json::from_slice(&out.stdout).unwrap();
    assert_eq!(v["kinematics"], "cartesian");
    assert_eq!(v["axis_max_mm"], json!([235.0, 235.0]));
}

#[test]
fn check_without_moonraker_fails_with_a_clear_reason() {
    let port = std::net::TcpListener::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap()
        .port();
    let out = Command::new(env!("CARGO_BIN_EXE_klipcal"))
        .args([
            "check",
            "--moonraker",
            &format!("ws://127.0.0.1:{port}/websocket"),
        ])
        .env("HOME", "/nonexistent")
        .output()
        .unwrap();
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("cannot reach Moonraker"), "{err}");
    assert!(err.contains(&port.to_string()), "{err}");
}
