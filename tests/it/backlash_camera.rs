//! KLIPCAL_BACKLASH_CAMERA (issue 27) on the bench: the bench's nozzle camera (`klipcal bench
//! camera`, registered in Moonraker as `[webcam nozzle]`) draws the simulated nozzle, play
//! included; the macro, run by Klipper through Moonraker, must measure the configured play
//! within its stated ± and within 3 µm, and apply it through the verified path. With no webcam,
//! or a picture without a sure nozzle, it is refused with the reason on every road in.

use std::process::{Child, Command, Stdio};
use std::time::Duration;

use serde_json::{json, Value};

use crate::backlash::{connect, last_reply, reply_now, set_point};
use crate::bench::{assert_refused_everywhere, extension_request, free_port, poll, Bench, Daemon};

const TRUE_X_MM: f64 = 0.08;

fn klipcal_bin() -> &'static str {
    env!("CARGO_BIN_EXE_klipcal")
}

/// The session in `klipcal_status` once it is no longer measuring.
async fn wait_measured(files: &klipcal::moonraker::Files, d: &Daemon) -> Value {
    let done = poll(Duration::from_secs(300), || async {
        let st = extension_request(files, "klipcal_status", json!({}))
            .await
            .ok()?;
        let s = st["session"].clone();
        (s["kind"] == "backlash" && s["state"] != "measuring").then_some(s)
    })
    .await;
    done.unwrap_or_else(|| panic!("the camera measurement did not end\n{}", d.log_text()))
}

#[tokio::test]
async fn the_camera_macro_measures_the_benchs_play_within_its_stated_error_and_applies_it() {
    let camera = json!({"look": "dark_tip", "px_per_mm": 80, "rotation_deg": 23,
        "offset_px": [15, -10], "centre_mm": [100, 100], "seed": 5, "drop_every": 9});
    let bench = Bench::start_args(
        "cartesian",
        &[
            "--backlash-module",
            "seed",
            "--play",
            &format!(r#"{{"x": {TRUE_X_MM}, "y": 0.05}}"#),
            "--camera",
            &camera.to_string(),
            "--klipcal-bin",
            klipcal_bin(),
        ],
    );
    let d = Daemon::ready(&bench, "[backlash]\ncamera_settle_s = 0.2\n").await;
    let files = bench.files();
    let (m, _c) = connect(&bench).await;
    set_point(&bench, &m, [100.0, 100.0, 0.0]).await;
    extension_request(&files, "klipcal_backlash_set_point", json!({}))
        .await
        .unwrap();
    // As a user runs it: the macro, through Klipper.
    m.gcode("KLIPCAL_BACKLASH_CAMERA AXIS=X CYCLES=5")
        .await
        .unwrap();
    let s = wait_measured(&files, &d).await;
    assert_eq!(s["state"], "measured", "{s}\n{}", d.log_text());
    let x = &s["results"]["x"];
    let b = x["backlash_mm"].as_f64().unwrap();
    let u = x["uncertainty_mm"].as_f64().unwrap();
    let err = b - TRUE_X_MM;
    eprintln!(
        "camera: {b:.4} mm ± {u:.4}, error {:+.1} µm; report {}",
        err * 1e3,
        s["camera"]["x"]
    );
    assert!(err.abs() <= 0.003, "error {err} mm over 3 µm: {s}");
    assert!(
        err.abs() <= 2.0 * u + 1e-4,
        "error {err} mm outside ±2·{u}: {s}"
    );
    assert_eq!(x["cycles"], 5, "{s}");
    let cam = &s["camera"]["x"];
    assert_eq!(cam["webcam"]["name"], "nozzle", "{cam}");
    assert_eq!(cam["cycles"].as_array().map(Vec::len), Some(5), "{cam}");
    let scale = &cam["scale"];
    let sx = scale["x"]["scale_px_per_mm"].as_f64().unwrap();
    assert!(
        (sx - 80.0).abs() < 0.8,
        "scale {sx} px/mm, drawn at 80: {cam}"
    );
    let rot = scale["rotation_deg"].as_f64().unwrap();
    assert!(
        (rot - 23.0).abs() < 0.5,
        "rotation {rot}°, drawn at 23°: {cam}"
    );
    assert_eq!(scale["mirrored"], true, "{cam}");
    // Every 9th frame was blank: taken again, not read as a nozzle.
    assert!(cam["refused_frames"].as_u64().unwrap() > 0, "{cam}");
    // No presses: the console says the result without a prompt.
    let said = last_reply(&m).await;
    assert!(
        said.contains("X: 0.0") && said.contains("KLIPCAL_BACKLASH_APPLY"),
        "{said}"
    );
    // Applied through the verified path: SET_BACKLASH_COMPENSATION reports the value.
    let r = extension_request(&files, "klipcal_backlash_apply", json!({}))
        .await
        .unwrap_or_else(|e| panic!("apply: {e}\n{}", d.log_text()));
    assert_eq!(r["state"], "done", "{r}");
    let now = reply_now(&m).await;
    assert!(
        (now.x_mm - (b * 1e4).round() / 1e4).abs() < 1e-9,
        "Klipper runs {now:?}, measured {b}"
    );
}

/// `klipcal bench camera` started by the test itself (a second webcam the test registers).
struct OwnCamera(Child);

impl Drop for OwnCamera {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

#[tokio::test]
async fn no_webcam_or_no_sure_nozzle_is_refused_with_the_reason_on_every_road() {
    let bench = Bench::start_args("cartesian", &["--backlash-module", "seed"]);
    let d = Daemon::ready(&bench, "").await;
    let files = bench.files();
    let (m, _c) = connect(&bench).await;
    set_point(&bench, &m, [100.0, 100.0, 0.0]).await;
    extension_request(&files, "klipcal_backlash_set_point", json!({}))
        .await
        .unwrap();
    assert_refused_everywhere(
        &bench,
        &d,
        &m,
        "backlash",
        &[
            (
                "camera",
                json!({"axis": "X"}),
                "Moonraker lists no webcam",
                Some("KLIPCAL_BACKLASH_CAMERA AXIS=X"),
            ),
            (
                "camera",
                json!({"axis": "Z"}),
                "cannot see Z move",
                Some("KLIPCAL_BACKLASH_CAMERA AXIS=Z"),
            ),
            ("camera", json!({"axis": "X", "cycles": 0}), "CYCLES", None),
        ],
    )
    .await;
    // A webcam whose picture is overexposed: refused before anything moves, with the reason.
    let port = free_port();
    let state = bench.dir.path().join("comms/still_nozzle.json");
    std::fs::write(&state, r#"{"nozzle": [100, 100, 0], "moves": 1}"#).unwrap();
    let _cam = OwnCamera(
        Command::new(klipcal_bin())
            .args(["bench", "camera", "--state-file"])
            .arg(&state)
            .args([
                "--port",
                &port.to_string(),
                "--spec",
                r#"{"look": "saturated", "seed": 2}"#,
            ])
            .stdin(Stdio::null())
            .stdout(Stdio::null())
            .stderr(Stdio::null())
            .spawn()
            .unwrap(),
    );
    let url = format!("http://127.0.0.1:{port}/snapshot");
    let up = poll(Duration::from_secs(20), || async {
        reqwest::get(&url)
            .await
            .ok()?
            .status()
            .is_success()
            .then_some(())
    })
    .await;
    assert!(up.is_some(), "the test's camera did not start");
    files
        .post(
            "/server/webcams/item",
            &json!({"name": "nozzle", "snapshot_url": url, "stream_url": url}),
        )
        .await
        .unwrap();
    let before = crate::backlash::nozzle(&bench);
    let e = extension_request(&files, "klipcal_backlash_camera", json!({"axis": "X"}))
        .await
        .unwrap_err();
    assert!(
        e.contains("webcam 'nozzle'") && e.contains("saturated"),
        "{e}"
    );
    assert_eq!(
        crate::backlash::nozzle(&bench),
        before,
        "it moved before refusing"
    );
    // Two webcams and none named: the user is told to name one.
    files
        .post(
            "/server/webcams/item",
            &json!({"name": "bed", "snapshot_url": url, "stream_url": url}),
        )
        .await
        .unwrap();
    let e = extension_request(&files, "klipcal_backlash_camera", json!({"axis": "X"}))
        .await
        .unwrap_err();
    assert!(e.contains("2 webcams") && e.contains("webcam = "), "{e}");
}

/// Issue 27's walk: on a printer with no compensation module the start says so and the "next:"
/// line offers no APPLY that would be refused; KLIPCAL_BACKLASH_SET_POINT is refused while an
/// axis is being measured (it used to move the point under the readings).
#[tokio::test]
async fn without_a_module_the_start_says_so_and_set_point_waits_for_the_measurement() {
    let bench = Bench::start_args(
        "cartesian",
        &[
            "--backlash-module",
            "none",
            "--play",
            r#"{"x": 0.06}"#,
            "--camera",
            r#"{"look": "ring", "seed": 8}"#,
            "--klipcal-bin",
            klipcal_bin(),
        ],
    );
    let d = Daemon::ready(&bench, "[backlash]\ncamera_settle_s = 0.1\n").await;
    let files = bench.files();
    let (m, _c) = connect(&bench).await;
    set_point(&bench, &m, [100.0, 100.0, 0.0]).await;
    extension_request(&files, "klipcal_backlash_set_point", json!({}))
        .await
        .unwrap();
    // Guided: told at the start.
    let r = extension_request(&files, "klipcal_backlash_start", json!({"axis": "X"}))
        .await
        .unwrap();
    let msg = r["message"].as_str().unwrap_or("");
    assert!(
        msg.contains("cannot apply") && msg.contains("PR 7259"),
        "the start does not say the printer cannot apply: {msg}"
    );
    // The point stays put while the axis is measured.
    let e = extension_request(&files, "klipcal_backlash_set_point", json!({}))
        .await
        .expect_err("SET_POINT was accepted during a measurement");
    assert!(
        e.contains("cannot move during it") && e.contains("KLIPCAL_CANCEL"),
        "{e}"
    );
    extension_request(&files, "klipcal_cancel", json!({}))
        .await
        .unwrap();
    set_point(&bench, &m, [100.0, 100.0, 0.0]).await;
    extension_request(&files, "klipcal_backlash_set_point", json!({}))
        .await
        .unwrap();
    // Camera, two cycles: the result, and no APPLY offered.
    m.gcode("KLIPCAL_BACKLASH_CAMERA AXIS=X CYCLES=2")
        .await
        .unwrap();
    let s = wait_measured(&files, &d).await;
    assert_eq!(s["state"], "measured", "{s}\n{}", d.log_text());
    let said = last_reply(&m).await;
    let next = said
        .lines()
        .rev()
        .find(|l| l.contains("next:"))
        .unwrap_or_else(|| panic!("no next: line in {said}"));
    assert!(
        !next.contains("KLIPCAL_BACKLASH_APPLY") && next.contains("nothing can be applied"),
        "{next}"
    );
    assert!(
        !s["progress"]
            .as_str()
            .unwrap_or("")
            .contains("KLIPCAL_BACKLASH_APPLY"),
        "{s}"
    );
}
