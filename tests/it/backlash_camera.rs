//! KLIPCAL_BACKLASH_CAMERA (issue 27) on the bench: the bench's nozzle camera (`klipcal bench
//! camera`, registered in Moonraker as `[webcam nozzle]`) draws the simulated nozzle, play
//! included; the macro, run by Klipper through Moonraker, must measure the configured play
//! within its stated ± and within 3 µm, and apply it through the verified path. With no webcam,
//! or a picture without a sure nozzle, it is refused with the reason on every road in.

use std::process::{Child, Command, Stdio};
use std::time::Duration;

use serde_json::{json, Value};

use crate::backlash::{apply_done, at_the_camera, config_values, last_reply, reply_now};
use crate::bench::{assert_refused_everywhere, extension_request, free_port, poll, Bench, Daemon};
use crate::browser::{artifact, Browser};

const TRUE_X_MM: f64 = 0.08;

fn klipcal_bin() -> &'static str {
    crate::bench::klipcal_with_bench()
}

/// The bench with its nozzle camera (`klipcal bench camera`, this build, drawing `camera`):
/// `kinematics`, the compensation `module`, the drawn `play` (bench.py's --play JSON) and any
/// `more` arguments.
fn camera_bench(
    kinematics: &str,
    module: &str,
    play: &str,
    camera: &Value,
    more: &[&str],
) -> Bench {
    let camera = camera.to_string();
    let mut args = vec![
        "--backlash-module",
        module,
        "--play",
        play,
        "--camera",
        &camera,
        "--klipcal-bin",
        klipcal_bin(),
    ];
    args.extend_from_slice(more);
    Bench::start_args(kinematics, &args)
}

/// A camera test's rig: the bench with its camera (`camera_bench`), the daemon up with a 0.2 s
/// camera settle, homed, and the camera point saved at `xy` (`at_the_camera`).
struct Rig {
    bench: Bench,
    camera: Value,
    d: Daemon,
    m: klipcal::moonraker::Moonraker,
    _c: tokio_util::sync::CancellationToken,
    files: klipcal::moonraker::Files,
}

impl Rig {
    async fn start(
        kinematics: &str,
        module: &str,
        play: &str,
        camera: Value,
        more: &[&str],
        xy: [f64; 2],
    ) -> Self {
        let bench = camera_bench(kinematics, module, play, &camera, more);
        let (d, m, _c, _) = at_the_camera(
            &bench,
            "[backlash]\ncamera_settle_s = 0.2\n",
            [xy[0], xy[1], 0.0],
        )
        .await;
        let files = bench.files();
        Self {
            bench,
            camera,
            d,
            m,
            _c,
            files,
        }
    }
}

/// The session in `klipcal_status` once it is no longer measuring.
async fn wait_measured(files: &klipcal::moonraker::Files, d: &Daemon) -> Value {
    let done = poll(Duration::from_secs(300), || async {
        let st = extension_request(files, "klipcal_status", json!({}))
            .await
            .ok()?;
        let s = st["session"].clone();
        // A measurement ends measured or failed; a cancelled session is an earlier one still
        // shown until the camera's session starts (the macro's call is answered after it).
        (s["kind"] == "backlash" && s["state"] != "measuring" && s["state"] != "cancelled")
            .then_some(s)
    })
    .await;
    done.unwrap_or_else(|| panic!("the camera measurement did not end\n{}", d.log_text()))
}

/// Runs `KLIPCAL_BACKLASH_CAMERA AXIS=X CYCLES=5` as a user does (the macro, through Klipper)
/// and checks X's result against the bench's true play: within 3 µm and inside its ±2u, from 5
/// cycles. Returns the status and the measured play, mm.
async fn camera_macro_measures_x(
    m: &klipcal::moonraker::Moonraker,
    files: &klipcal::moonraker::Files,
    d: &Daemon,
    truth_mm: f64,
    what: &str,
) -> (Value, f64) {
    m.gcode("KLIPCAL_BACKLASH_CAMERA AXIS=X CYCLES=5")
        .await
        .unwrap();
    let s = wait_measured(files, d).await;
    assert_eq!(s["state"], "measured", "{s}\n{}", d.log_text());
    let x = &s["results"]["x"];
    let b = x["backlash_mm"].as_f64().unwrap();
    let u = x["uncertainty_mm"].as_f64().unwrap();
    let err = b - truth_mm;
    eprintln!(
        "{what}: {b:.4} mm ± {u:.4}, error {:+.1} µm; report {}",
        err * 1e3,
        s["camera"]["x"]
    );
    assert!(err.abs() <= 0.003, "error {err} mm over 3 µm: {s}");
    assert!(
        err.abs() <= 2.0 * u + 1e-4,
        "error {err} mm outside ±2·{u}: {s}"
    );
    assert_eq!(x["cycles"], 5, "{s}");
    (s, b)
}

#[tokio::test]
async fn the_camera_macro_measures_the_benchs_play_within_its_stated_error_and_applies_it() {
    let camera = json!({"look": "dark_tip", "px_per_mm": 80, "rotation_deg": 23,
        "offset_px": [15, -10], "centre_mm": [100, 100], "seed": 5, "drop_every": 9});
    let play = format!(r#"{{"x": {TRUE_X_MM}, "y": 0.05}}"#);
    let rig = Rig::start("cartesian", "seed", &play, camera, &[], [100.0, 100.0]).await;
    let Rig {
        bench, d, m, files, ..
    } = &rig;
    let (s, b) = camera_macro_measures_x(m, files, d, TRUE_X_MM, "camera").await;
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
    let said = last_reply(m).await;
    assert!(
        said.contains("X: 0.0") && said.contains("KLIPCAL_BACKLASH_APPLY"),
        "{said}"
    );
    // Applied through the verified path: SET_BACKLASH_COMPENSATION reports the value.
    apply_done(bench, d).await;
    let now = reply_now(m).await;
    assert!(
        (now.x_mm - (b * 1e4).round() / 1e4).abs() < 1e-9,
        "Klipper runs {now:?}, measured {b}"
    );
}

/// Issue 37, item 5: the whole camera flow — the scale's ±0.5 mm moves, five cycles, apply —
/// on real picture content: the bench camera serves a kTAMV nozzle-camera frame (a published
/// photo: defocused, a filament blob, bed sparkles) moved where klippy's nozzle is, turned,
/// lit, noisy and JPEG-compressed. The macro, run by Klipper, must measure the configured
/// play within its stated ± and 3 µm and apply it. The camera is first checked to serve that
/// photo, not the renderer's nozzle: a snapshot matches the photo moved to where the camera
/// maps klippy's true nozzle, and not the same photo 0.25 mm away.
#[tokio::test]
async fn the_camera_macro_measures_the_play_from_real_photo_frames_and_applies_it() {
    const X: f64 = 0.07;
    let camera = json!({"photo": "ktamv-frame", "width": 320, "height": 240, "px_per_mm": 80,
        "rotation_deg": -9, "offset_px": [8, -5], "centre_mm": [100, 100], "seed": 37});
    let play = format!(r#"{{"x": {X}, "y": 0.04}}"#);
    let rig = Rig::start(
        "cartesian",
        "seed",
        &play,
        camera.clone(),
        &[],
        [100.0, 100.0],
    )
    .await;
    let Rig {
        bench, d, m, files, ..
    } = &rig;
    // What the camera serves: the photo where klippy's nozzle is.
    let url = bench.info["camera"]["snapshot_url"].as_str().unwrap();
    let jpeg = reqwest::get(url).await.unwrap().bytes().await.unwrap();
    let (w, h, grey) = klipcal::calib::nozzle::decode_gray(&jpeg).unwrap();
    assert_eq!((w, h), (320, 240));
    let at = crate::backlash::nozzle(bench);
    use klipcal_core::photo_camera::{ncc, photo, Lighting, PhotoCamera, Placement};
    let pc = PhotoCamera::new(
        &photo(
            &|f| Ok(std::fs::read(klipcal_core::nozzle_photos::dir().join(f))?),
            "ktamv-frame",
        )
        .unwrap(),
        &Placement {
            width: 320,
            height: 240,
            rotation_deg: -9.0,
            home_px: drawn_px(&camera, [100.0, 100.0]),
            reach_px: 0.75 * 80.0,
            zoom: None,
        },
        Lighting::draw(&mut fastrand::Rng::with_seed(1)),
    )
    .unwrap();
    let there = ncc(&pc.clean(drawn_px(&camera, [at[0], at[1]])), &grey);
    let off = ncc(&pc.clean(drawn_px(&camera, [at[0] + 0.25, at[1]])), &grey);
    assert!(
        there > 0.95 && off < 0.9,
        "the snapshot against the photo at the nozzle {there:.3}, 0.25 mm away {off:.3}"
    );
    let (s, b) = camera_macro_measures_x(m, files, d, X, "real-photo camera").await;
    let scale = &s["camera"]["x"]["scale"];
    let sx = scale["x"]["scale_px_per_mm"].as_f64().unwrap();
    let rot = scale["rotation_deg"].as_f64().unwrap();
    assert!(
        (sx - 80.0).abs() < 0.8 && (rot + 9.0).abs() < 0.5,
        "scale {sx} px/mm at {rot}°, drawn at 80 px/mm, −9°: {s}"
    );
    apply_done(bench, d).await;
    let now = reply_now(m).await;
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
    let (d, m, _c, _) = at_the_camera(&bench, "", [100.0, 100.0, 0.0]).await;
    let files = bench.files();
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
    let bench = camera_bench(
        "cartesian",
        "none",
        r#"{"x": 0.06}"#,
        &json!({"look": "ring", "seed": 8}),
        &[],
    );
    let (d, m, _c, _) = at_the_camera(
        &bench,
        "[backlash]\ncamera_settle_s = 0.1\n",
        [100.0, 100.0, 0.0],
    )
    .await;
    let files = bench.files();
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
    crate::backlash::set_point(&bench, &m, [100.0, 100.0, 0.0]).await;
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

/// The session once `key`'s result is in and the measurement is over (measured or failed).
async fn wait_result(files: &klipcal::moonraker::Files, d: &Daemon, key: &str) -> Value {
    let done = poll(Duration::from_secs(300), || async {
        let st = extension_request(files, "klipcal_status", json!({}))
            .await
            .ok()?;
        let s = st["session"].clone();
        let over = s["kind"] == "backlash"
            && (s["state"] == "failed"
                || (s["state"] == "measured" && !s["results"][key].is_null()));
        over.then_some(s)
    })
    .await;
    done.unwrap_or_else(|| {
        panic!(
            "the camera measurement of {key} did not end\n{}",
            d.log_text()
        )
    })
}

/// Runs `KLIPCAL_BACKLASH_CAMERA {args}` through Klipper and checks `key`'s result against the
/// drawn play: within 3 µm, issue 27's camera target (p95 ≤ 3 µm). Under load CoreXY A read
/// 1.5–1.7 µm high, every cycle 1.2–2.4 µm high: frames came 0.5 s apart, so the first frame
/// after the settle, still ringing by 1–1.8 µm, was averaged with two still ones (see
/// `settled` in src/jobs/backlash/camera.rs); with the reading from the frames after it, A
/// read +0.8 µm (cycles +0.6 to +1.0) and B −0.8 µm under the same load. What stays is the
/// detection's sub-pixel error at the two positions, the same in every cycle. With a reading
/// taken when only two frames agreed, A read 2.1 µm high on an idle machine. Not against the
/// stated ± alone: on these cameras it is 0.2–0.8 µm.
async fn camera_axis(
    m: &klipcal::moonraker::Moonraker,
    files: &klipcal::moonraker::Files,
    d: &Daemon,
    args: &str,
    key: &str,
    drawn_mm: f64,
) -> Value {
    m.gcode(&format!("KLIPCAL_BACKLASH_CAMERA {args}"))
        .await
        .unwrap();
    let s = wait_result(files, d, key).await;
    assert_eq!(s["state"], "measured", "{args}: {s}\n{}", d.log_text());
    let r = &s["results"][key];
    let b = r["backlash_mm"].as_f64().unwrap();
    let u = r["uncertainty_mm"].as_f64().unwrap();
    let err = b - drawn_mm;
    let per_cycle: Vec<String> = s["camera"][key]["cycles"]
        .as_array()
        .into_iter()
        .flatten()
        .map(|c| {
            let f = |k: &str| c[k].as_f64().unwrap_or(f64::NAN) * 1e3;
            format!(
                "{:+.2} ({:+.2} / {:+.2})",
                f("backlash_mm") - drawn_mm * 1e3,
                f("plus_mm"),
                f("minus_mm")
            )
        })
        .collect();
    eprintln!(
        "camera {args}: {key} {b:.4} mm ± {u:.4}, drawn {drawn_mm}, error {:+.1} µm; per \
         cycle error µm (approach from below / above, µm from the camera point) {}",
        err * 1e3,
        per_cycle.join(", ")
    );
    assert!(err.abs() <= 0.003, "{key}: error {err} mm over 3 µm: {s}");
    assert!(u > 0.0 && u < 0.003, "{key}: stated ± {u}: {s}");
    assert_eq!(
        s["camera"][key]["cycles"].as_array().map(Vec::len),
        Some(4),
        "{s}"
    );
    s
}

/// PR 7157's `[backlash]` on CoreXY: A and B, the motors' directions, read from the camera
/// through Klipper (the bench plays each motor's joint), then written to `[backlash]` by apply.
#[tokio::test]
async fn pr_7157_a_and_b_on_corexy_are_measured_from_the_camera_and_written_to_backlash() {
    const A: f64 = 0.06;
    const B: f64 = 0.04;
    let camera = json!({"look": "ring", "px_per_mm": 70, "rotation_deg": -12,
        "offset_px": [-20, 12], "centre_mm": [150, 150], "seed": 12});
    let play = format!(r#"{{"a": {A}, "b": {B}}}"#);
    let rig = Rig::start("corexy", "pr7157", &play, camera, &[], [150.0, 150.0]).await;
    let Rig {
        bench, d, m, files, ..
    } = &rig;
    camera_axis(m, files, d, "AXIS=A CYCLES=4", "a", A).await;
    let s = camera_axis(m, files, d, "AXIS=B CYCLES=4", "b", B).await;
    // The seed's CoreXY question, answered from the camera's A and B.
    assert!(
        s["corexy_answer"]
            .as_str()
            .is_some_and(|a| a.contains("motors A")),
        "{s}"
    );
    let r = apply_done(bench, d).await;
    let written = config_values(m, "backlash", &["a", "b"]).await;
    for ((k, drawn), w) in [("a", A), ("b", B)].into_iter().zip(written) {
        let want = r["values"][k].as_f64().unwrap();
        assert!(
            (w - want).abs() < 1e-6 && (w - drawn).abs() <= 0.003,
            "[backlash] {k}: {w} against {want} (drawn {drawn})",
        );
    }
}

/// Dual carriage (IDEX): each carriage's X read from the camera with the carriage selected
/// (CARRIAGE=0, then 1, each with its own play), and the shared Y, through Klipper.
#[tokio::test]
async fn dual_carriage_x_of_each_carriage_and_y_are_measured_from_the_camera() {
    const X0: f64 = 0.07;
    const X1: f64 = 0.045;
    const Y: f64 = 0.03;
    let camera = json!({"look": "dark_tip", "px_per_mm": 90, "rotation_deg": 8,
        "offset_px": [10, 5], "centre_mm": [100, 100], "seed": 21});
    let play = format!(r#"{{"x": {X0}, "x1": {X1}, "y": {Y}}}"#);
    let more = ["--dual-carriage"];
    let rig = Rig::start("cartesian", "seed", &play, camera, &more, [100.0, 100.0]).await;
    let Rig {
        bench, d, m, files, ..
    } = &rig;
    camera_axis(m, files, d, "AXIS=X CARRIAGE=0 CYCLES=4", "x@0", X0).await;
    camera_axis(m, files, d, "AXIS=X CARRIAGE=1 CYCLES=4", "x@1", X1).await;
    let seen = std::fs::read_to_string(bench.dir.path().join("comms/nozzle_true.json")).unwrap();
    assert!(seen.contains("\"carriage\": 1"), "{seen}");
    let s = camera_axis(m, files, d, "AXIS=Y CYCLES=4", "y", Y).await;
    // Each carriage's X is its own: the two differ as drawn.
    let x0 = s["results"]["x@0"]["backlash_mm"].as_f64().unwrap();
    let x1 = s["results"]["x@1"]["backlash_mm"].as_f64().unwrap();
    assert!((x0 - x1 - (X0 - X1)).abs() <= 0.004, "{s}");
}

/// Where the bench camera draws the nozzle at machine (x, y) mm (`klipcal bench camera`'s
/// mapping: scale, rotation, mirror, offset), px with pixel centres at integers.
fn drawn_px(spec: &Value, xy: [f64; 2]) -> [f64; 2] {
    let f = |k: &str, d: f64| spec[k].as_f64().unwrap_or(d);
    let (s, th) = (f("px_per_mm", 80.0), f("rotation_deg", 0.0).to_radians());
    let m = if spec["mirror"] == json!(false) {
        1.0
    } else {
        -1.0
    };
    let o = [
        f("width", 640.0) / 2.0 + spec["offset_px"][0].as_f64().unwrap_or(0.0),
        f("height", 480.0) / 2.0 + spec["offset_px"][1].as_f64().unwrap_or(0.0),
    ];
    let c = [
        spec["centre_mm"][0].as_f64().unwrap_or(100.0),
        spec["centre_mm"][1].as_f64().unwrap_or(100.0),
    ];
    let (dx, dy) = (xy[0] - c[0], xy[1] - c[1]);
    [
        o[0] + s * th.cos() * dx - m * s * th.sin() * dy,
        o[1] + s * th.sin() * dx + m * s * th.cos() * dy,
    ]
}

/// The page's frame and its marks as the browser lays them out: the mark's centre in the
/// image's pixels (from the SVG), the same point from the screen boxes (where a person sees
/// it over the picture), the image's natural size and whether it loaded.
const READ_FIGURE: &str = "(() => {
    const img = document.querySelector('#snapimg'), g = document.querySelector('#found');
    const t = g.transform.baseVal.consolidate().matrix;
    const ir = img.getBoundingClientRect(), gr = g.querySelector('circle').getBoundingClientRect();
    const k = img.naturalWidth / ir.width;
    return {loaded: img.complete && img.naturalWidth > 0, w: img.naturalWidth, h: img.naturalHeight,
        seq: document.querySelector('#snapshot').dataset.seq, mark: [t.e - 0.5, t.f - 0.5],
        screen: [(gr.left + gr.width / 2 - ir.left) * k - 0.5, (gr.top + gr.height / 2 - ir.top) * k - 0.5],
        caption: document.querySelector('#snapcap').textContent,
        approaches: document.querySelectorAll('#snapmarks circle.approach').length,
        cycles: [...document.querySelectorAll('.camera[data-key=\"x\"] tr.cycle td.b')].map(td => td.textContent),
        median: (document.querySelector('.camera[data-key=\"x\"] tr.median td') || {}).textContent,
        spread: (document.querySelector('.camera[data-key=\"x\"] tr.spread td') || {}).textContent};
})()";

/// The served frame is a JPEG; the guard stands before it as before the page (an address
/// outside trusted_clients is refused); a frame no longer kept, or a number that is not one, is
/// said.
async fn the_frame_is_served_guarded_and_its_misses_said(base: &str, seq: u64) {
    let r = reqwest::get(format!("{base}/api/backlash/snapshot.jpg?seq={seq}"))
        .await
        .unwrap();
    assert_eq!(r.headers()["content-type"], "image/jpeg");
    assert!(r.bytes().await.unwrap().starts_with(&[0xff, 0xd8]));
    // The guard stands before it as before the page: an address outside trusted_clients is
    // refused.
    let r = crate::http::client_from("127.0.0.2")
        .get(format!("{base}/api/backlash/snapshot.jpg?seq={seq}"))
        .send()
        .await
        .unwrap();
    assert_eq!(r.status().as_u16(), 403);
    // A frame no longer kept, or a number that is not one, is said.
    let r = reqwest::get(format!("{base}/api/backlash/snapshot.jpg?seq=1"))
        .await
        .unwrap();
    assert_eq!(r.status().as_u16(), 404);
    assert!(r.text().await.unwrap().contains("no longer kept"));
    let r = reqwest::get(format!("{base}/api/backlash/snapshot.jpg?seq=x"))
        .await
        .unwrap();
    assert_eq!(r.status().as_u16(), 400);
}

/// The page's figure at `size` (`f`, read by READ_FIGURE) shows the frame `seq` of the status
/// `s`: the mark at the detector's finding `found`, which is where the bench drew the nozzle
/// (`want`), over that point of the picture on the screen; each approach marked; the cycles,
/// median and spread as the status gives them.
fn the_figure_shows_what_the_status_says(
    size: &str,
    f: &Value,
    s: &Value,
    seq: u64,
    found: [f64; 2],
    want: [f64; 2],
) {
    assert_eq!(f["seq"], json!(seq.to_string()), "{f}");
    assert_eq!((f["w"].as_u64(), f["h"].as_u64()), (Some(640), Some(480)));
    let at = |k: &str, i: usize| f[k][i].as_f64().unwrap();
    for i in 0..2 {
        // The mark is the detector's finding, which is where the bench drew the nozzle…
        assert!(
            (at("mark", i) - found[i]).abs() < 1e-3,
            "{f} {}",
            s["snapshot"]
        );
        assert!(
            (found[i] - want[i]).abs() < 0.3,
            "found {found:?}, drawn {want:?}"
        );
        // … and on the screen it sits over that point of the picture.
        assert!(
            (at("screen", i) - want[i]).abs() < 1.5,
            "{size}: the mark is drawn at {:?} of the picture, the nozzle at {want:?}",
            f["screen"]
        );
    }
    assert!(
        f["caption"]
            .as_str()
            .unwrap()
            .contains(&format!("nozzle at ({:.2}, {:.2}) px", found[0], found[1])),
        "{f}"
    );
    // Each cycle's two approaches are marked; the table says what the status says.
    assert_eq!(f["approaches"], json!(6), "{f}");
    let cycles: Vec<String> = s["camera"]["x"]["cycles"]
        .as_array()
        .unwrap()
        .iter()
        .map(|c| format!("{:.4}", c["backlash_mm"].as_f64().unwrap()))
        .collect();
    assert_eq!(f["cycles"], json!(cycles), "{f}");
    let r = &s["results"]["x"];
    assert_eq!(
        f["median"],
        json!(format!(
            "{:.4} ± {:.4}",
            r["backlash_mm"].as_f64().unwrap(),
            r["uncertainty_mm"].as_f64().unwrap()
        ))
    );
    assert_eq!(
        f["spread"],
        json!(format!("{:.4}", r["spread_mm"].as_f64().unwrap()))
    );
}

/// Issue 27 Build 4: klipcal's page shows the camera measurement — the newest frame, served by
/// klipcal itself, with the nozzle marked where the detector found it (which is where the bench
/// drew it), each approach's position, and the per-cycle values with their median and spread
/// as the status gives them; at a desktop's and a phone's size, in Chromium.
#[tokio::test]
async fn the_page_shows_the_newest_frame_with_the_found_nozzle_and_the_cycles() {
    let camera = json!({"look": "ring", "px_per_mm": 80, "rotation_deg": 15,
        "offset_px": [12, -8], "centre_mm": [100, 100], "seed": 3});
    let bench = camera_bench("cartesian", "seed", r#"{"x": 0.07}"#, &camera, &[]);
    let (d, m, _c, _) = at_the_camera(
        &bench,
        "[backlash]\ncamera_settle_s = 0.2\n[http]\nbind = \"127.0.0.1:0\"\n\
         trusted_clients = [\"127.0.0.1/32\"]\n",
        [100.0, 100.0, 0.0],
    )
    .await;
    let files = bench.files();
    let base = d.page_url().await;
    // No frame yet: said, not an empty image.
    let r = reqwest::get(format!("{base}/api/backlash/snapshot.jpg"))
        .await
        .unwrap();
    assert_eq!(r.status(), 404);
    assert!(r.text().await.unwrap().contains("no camera frame"));
    m.gcode("KLIPCAL_BACKLASH_CAMERA AXIS=X CYCLES=3")
        .await
        .unwrap();
    let mut b = Browser::start().await;
    b.set_viewport(1280, 900, false).await;
    b.open(&format!("{base}/")).await;
    // While it measures, the frame shows and follows the measurement.
    assert!(
        b.wait_for(
            "document.querySelector('#snapimg') && document.querySelector('#snapimg').naturalWidth > 0",
            Duration::from_secs(60)
        )
        .await,
        "no camera frame on the page while measuring\n{}",
        d.log_text()
    );
    let first = b.eval(READ_FIGURE).await;
    let s = wait_measured(&files, &d).await;
    assert_eq!(s["state"], "measured", "{s}\n{}", d.log_text());
    assert!(
        b.wait_for(
            "document.querySelectorAll('.camera[data-key=\"x\"] tr.median').length === 1",
            Duration::from_secs(20)
        )
        .await,
        "the page did not follow to the result"
    );
    let st = extension_request(&files, "klipcal_status", json!({}))
        .await
        .unwrap();
    let s = &st["session"];
    let snap = &s["snapshot"];
    let seq = snap["seq"].as_u64().unwrap();
    assert!(
        first["seq"].as_str().unwrap().parse::<u64>().unwrap() < seq,
        "{first} {snap}"
    );
    the_frame_is_served_guarded_and_its_misses_said(&base, seq).await;
    let truth = crate::backlash::nozzle(&bench);
    let want = drawn_px(&camera, [truth[0], truth[1]]);
    let found = [
        snap["centre_px"][0].as_f64().unwrap(),
        snap["centre_px"][1].as_f64().unwrap(),
    ];
    for (size, (w, h, phone)) in [("desktop", (1280, 900, false)), ("phone", (390, 844, true))] {
        b.set_viewport(w, h, phone).await;
        b.open(&format!("{base}/")).await;
        assert!(
            b.wait_for(
                "document.querySelector('#snapimg').naturalWidth > 0",
                Duration::from_secs(20)
            )
            .await
        );
        let f = b.eval(READ_FIGURE).await;
        b.screenshot(&artifact(&format!("backlash-camera-{size}.png")))
            .await;
        if size == "desktop" {
            // The documentation's picture (KLIPCAL_DOC_IMAGES=1): the page's backlash section,
            // the snapshot with the found nozzle marked and the cycles under it.
            let section = artifact("backlash-camera-section.png");
            b.screenshot_element("#backlash", 8.0, &section).await;
            crate::browser::doc_image(&section, "backlash-camera.png", 800);
        }
        eprintln!("{size}: {f}; status {found:?}; drawn {want:?}");
        the_figure_shows_what_the_status_says(size, &f, s, seq, found, want);
    }
}

/// Where image pixel `p` of the page's snapshot is on the screen now (CSS px of the window),
/// scrolled into view; None while the page reloads.
async fn at_screen(b: &mut Browser, p: [f64; 2]) -> Option<[f64; 2]> {
    let v = b
        .eval(&format!(
            "(() => {{ const fig = document.querySelector('#snapshot'),
                img = document.querySelector('#snapimg');
            if (!fig || !img || !img.naturalWidth) return null;
            fig.scrollIntoView({{block: 'center'}});
            const r = img.getBoundingClientRect(), k = r.width / img.naturalWidth;
            return [r.left + ({} + 0.5) * k, r.top + ({} + 0.5) * k]; }})()",
            p[0], p[1]
        ))
        .await;
    Some([v[0].as_f64()?, v[1].as_f64()?])
}

/// Issue 27 Build 4, the click-in-snapshot flow: on a camera the detector refuses (two nozzles
/// in the picture: an IDEX's other toolhead), KLIPCAL_BACKLASH_CLICK has the person click the
/// nozzle's tip in each snapshot on klipcal's page. The test clicks in Chromium where the bench
/// drew the nozzle, off by up to 2 screen pixels (seeded); the clicks of the ±0.5 mm moves give
/// the scale, the cycles' clicks the backlash, through the same statistics. It must find the
/// drawn play within its stated ± with far fewer presses than the jog flow's ~250–300.
#[tokio::test]
async fn clicking_the_tip_in_snapshots_on_the_page_measures_the_drawn_play() {
    click_flow((1280, 900, false), 4, 27, "backlash-clicks.png").await;
}

/// The same on a phone-sized page (390×844, the phone's layout): the picture is 4.5 times
/// smaller on the screen, so the same 2-pixel slips of the finger are larger in the picture.
#[tokio::test]
async fn clicking_the_tip_on_a_phone_sized_page_measures_the_drawn_play() {
    click_flow((390, 844, true), 9, 5, "backlash-clicks-phone.png").await;
}

/// The click flow's rig: the bench drawing `camera` with `true_x` mm of play on X (cartesian,
/// the seed module), the camera point at (100, 100). The click flow takes its snapshot at least
/// 1 s after the move, whatever the settle (the bench's 10 µm ring is gone by then).
async fn click_rig(camera: Value, true_x: f64) -> Rig {
    let play = format!(r#"{{"x": {true_x}}}"#);
    Rig::start("cartesian", "seed", &play, camera, &[], [100.0, 100.0]).await
}

impl Rig {
    /// KLIPCAL_BACKLASH_CLICK of X through Klipper, as a user runs it.
    async fn run_click_macro(&self, cycles: usize) {
        self.m
            .gcode(&format!("KLIPCAL_BACKLASH_CLICK AXIS=X CYCLES={cycles}"))
            .await
            .unwrap();
    }

    /// A `klipcal_backlash_tip` post's refusal.
    async fn tip_refused(&self, tip: Value) -> String {
        extension_request(&self.files, "klipcal_backlash_tip", tip)
            .await
            .unwrap_err()
    }
}

/// How a click test clicks: how it learns that a snapshot waits, and how it clicks the tip.
trait Clicker {
    /// The number of the snapshot waiting for a click after `done` (the last one clicked), or
    /// None when there is none yet (the status is asked again).
    async fn prompt(&mut self, rig: &Rig, session: &Value, done: u64) -> Option<u64>;
    /// Clicks the tip, drawn at `drawn` px, in snapshot `seq` (seen in session `s`); whether
    /// the click was taken.
    async fn click(&mut self, rig: &Rig, s: &Value, seq: u64, drawn: [f64; 2]) -> bool;
}

/// The measured X of a click flow: the reading, its ± and the camera's report.
struct Clicked {
    got: f64,
    u: f64,
    cam: Value,
    s: Value,
}

/// The click loop: until the backlash session is no longer measuring, waits for each snapshot
/// that asks for a click and clicks where the bench drew the nozzle. The session must end
/// measured, from one click for each of the 6 scale snapshots and 2 for each of `cycles`, and
/// read the drawn `true_x` within its stated ±2u; `what` names the run in the printed figures.
async fn click_until_measured(
    rig: &Rig,
    clicker: &mut impl Clicker,
    key: &str,
    true_x: f64,
    cycles: usize,
    what: &str,
) -> Clicked {
    let mut done = 0u64;
    let s = loop {
        let st = extension_request(&rig.files, "klipcal_status", json!({}))
            .await
            .unwrap();
        let s = st["session"].clone();
        // Over when this axis's result is in or it failed (an earlier axis's session shows
        // measured until this one's starts).
        let over = s["state"] == "failed" || !s["results"][key].is_null();
        if s["kind"] == "backlash" && s["state"] != "measuring" && over {
            break s;
        }
        let Some(seq) = clicker.prompt(rig, &s, done).await else {
            continue;
        };
        let truth = crate::backlash::nozzle(&rig.bench);
        let drawn = drawn_px(&rig.camera, [truth[0], truth[1]]);
        if clicker.click(rig, &s, seq, drawn).await {
            done = seq;
        }
    };
    assert_eq!(s["state"], "measured", "{s}\n{}", rig.d.log_text());
    let r = &s["results"][key];
    let got = r["backlash_mm"].as_f64().unwrap();
    let u = r["uncertainty_mm"].as_f64().unwrap();
    let cam = s["camera"][key].clone();
    eprintln!(
        "{what}: {got:.4} mm ± {u:.4}, drawn {true_x}, error {:+.1} µm; {} clicks, refined {}, \
         kept {}, scale {} px/mm (drawn 80)",
        (got - true_x) * 1e3,
        cam["clicks"],
        cam["refined"],
        cam["kept"],
        cam["scale"]["x"]["scale_px_per_mm"]
    );
    assert_eq!(cam["clicks"], json!(6 + 2 * cycles), "{cam}");
    assert!(
        (got - true_x).abs() <= 2.0 * u,
        "measured {got} ± {u}, drawn {true_x}: {s}"
    );
    Clicked { got, u, cam, s }
}

/// Clicks as a person does on klipcal's page in Chromium: waits for the page to show the
/// snapshot that asks for a click, a first tap near the tip zooms in there, the second is the
/// click, off by up to 2 screen pixels (seeded); counts every press.
struct PageClicks {
    b: Browser,
    rng: fastrand::Rng,
    presses: usize,
    refused_checked: bool,
}

impl Clicker for PageClicks {
    async fn prompt(&mut self, rig: &Rig, s: &Value, done: u64) -> Option<u64> {
        assert!(s["state"] != "failed", "{s}\n{}", rig.d.log_text());
        assert!(
            self.presses < 60,
            "no end after {} presses: {s}",
            self.presses
        );
        let ready = format!(
            "document.querySelector('#snapshot[data-click=\"1\"][data-ready=\"1\"]') && +document.querySelector('#snapshot').dataset.seq > {done}"
        );
        if !self.b.wait_for(&ready, Duration::from_secs(10)).await {
            return None; // the next snapshot is still coming (the status is asked again)
        }
        // None while the page is reloading.
        self.b
            .eval("(document.querySelector('#snapshot') || {dataset: {}}).dataset.seq || null")
            .await
            .as_str()
            .and_then(|v| v.parse::<u64>().ok())
    }

    async fn click(&mut self, rig: &Rig, _: &Value, seq: u64, drawn: [f64; 2]) -> bool {
        if !self.refused_checked {
            // Another frame's number, or a point outside the picture: refused by name, and
            // the snapshot still waits.
            let e = rig
                .tip_refused(json!({"x": 10, "y": 10, "frame": seq + 5}))
                .await;
            assert!(
                e.contains(&format!("waiting for a click is frame {seq}")),
                "{e}"
            );
            let e = rig
                .tip_refused(json!({"x": 700, "y": 10, "frame": seq}))
                .await;
            assert!(e.contains("outside the 640×480 picture"), "{e}");
            self.refused_checked = true;
        }
        let b = &mut self.b;
        let zoomed = b
            .eval("(document.querySelector('.stage') || {style: {}}).style.transform || ''")
            .await
            != json!("");
        if !zoomed {
            // Whole picture: a first click near the tip zooms in there.
            let Some(p) = at_screen(b, drawn).await else {
                return false;
            };
            b.tap(p[0] + 3.0, p[1] - 2.0).await;
            self.presses += 1;
            if !b
                .wait_for(
                    "document.querySelector('.stage').style.transform !== ''",
                    Duration::from_secs(5),
                )
                .await
            {
                return false; // the page reloaded under the click: a press lost, counted
            }
        }
        let Some(p) = at_screen(b, drawn).await else {
            return false;
        };
        let err = [self.rng.f64() * 4.0 - 2.0, self.rng.f64() * 4.0 - 2.0];
        b.tap(p[0] + err[0], p[1] + err[1]).await;
        self.presses += 1;
        b.wait_for(
            "document.querySelector('#clickhelp').textContent.includes('saved')",
            Duration::from_secs(10),
        )
        .await
    }
}

/// Runs KLIPCAL_BACKLASH_CLICK through Klipper and clicks each snapshot in Chromium at `size`;
/// `camera_seed` draws the camera, `click_seed` the slips.
async fn click_flow(size: (u32, u32, bool), camera_seed: u64, click_seed: u64, shot: &str) {
    const TRUE_X: f64 = 0.06;
    const CYCLES: usize = 3;
    let camera = json!({"look": "two_nozzles", "px_per_mm": 80, "rotation_deg": -20,
        "offset_px": [-10, 6], "centre_mm": [100, 100], "seed": camera_seed});
    let rig = click_rig(camera, TRUE_X).await;
    // The detector cannot read this camera: the automatic measurement says why.
    let e = extension_request(&rig.files, "klipcal_backlash_camera", json!({"axis": "X"}))
        .await
        .unwrap_err();
    assert!(e.contains("no sure nozzle"), "{e}");
    // A click with nothing waiting for it is refused with what to do.
    let e = rig.tip_refused(json!({"x": 10, "y": 10, "frame": 1})).await;
    assert!(e.contains("KLIPCAL_BACKLASH_CLICK"), "{e}");
    rig.run_click_macro(CYCLES).await;
    let base = rig.d.page_url().await;
    let mut b = Browser::start().await;
    b.set_viewport(size.0, size.1, size.2).await;
    b.open(&format!("{base}/")).await;
    let mut page = PageClicks {
        b,
        rng: fastrand::Rng::with_seed(click_seed),
        presses: 0,
        refused_checked: false,
    };
    let what = format!("clicks at {size:?}");
    let Clicked { u, cam, .. } =
        click_until_measured(&rig, &mut page, "x", TRUE_X, CYCLES, &what).await;
    let (presses, mut b) = (page.presses, page.b);
    eprintln!("{what}: {presses} presses");
    assert!(presses <= 6 + 2 * CYCLES + 1, "{presses} presses");
    let sx = cam["scale"]["x"]["scale_px_per_mm"].as_f64().unwrap();
    assert!((sx - 80.0).abs() < 1.6, "scale {sx} px/mm, drawn at 80");
    assert!(u < 0.01, "± {u} mm");
    // The page shows the clicked cycles as the status does.
    b.open(&format!("{base}/")).await;
    let cycles = b
        .eval("[...document.querySelectorAll('.camera[data-key=\"x\"] tr.cycle td.b')].map(td => td.textContent)")
        .await;
    let want: Vec<String> = cam["cycles"]
        .as_array()
        .unwrap()
        .iter()
        .map(|c| format!("{:.4}", c["backlash_mm"].as_f64().unwrap()))
        .collect();
    assert_eq!(cycles, json!(want));
    b.screenshot(&artifact(shot)).await;
    // Issue 40 item 8: no table of the measured axis scrolls sideways (a phone showed half
    // the results table), and the page itself does not either.
    let wide = b
        .eval(
            "JSON.stringify({page: document.documentElement.scrollWidth - window.innerWidth,
              wide: [...document.querySelectorAll('.scroll')]
                .filter(c => c.scrollWidth > c.clientWidth + 1)
                .map(c => [c.scrollWidth, c.clientWidth, c.textContent.slice(0, 60)])})",
        )
        .await;
    let wide: Value = serde_json::from_str(wide.as_str().unwrap()).unwrap();
    assert!(
        wide["page"].as_f64().unwrap() <= 1.0 && wide["wide"] == json!([]),
        "{what}: scrolls sideways: {wide}"
    );
}

/// Clicks posted to `klipcal_backlash_tip` off by up to 6 px on each axis (seeded), with the
/// stated sd of such a click, as soon as the status shows a snapshot waiting for one.
struct PostedClicks {
    rng: fastrand::Rng,
    posted: usize,
    most: usize,
}

impl Clicker for PostedClicks {
    async fn prompt(&mut self, _: &Rig, s: &Value, done: u64) -> Option<u64> {
        let snap = &s["snapshot"];
        let seq = snap["seq"].as_u64().unwrap_or(0);
        if snap["click"] != json!(true) || seq <= done {
            tokio::time::sleep(Duration::from_millis(100)).await;
            return None;
        }
        Some(seq)
    }

    async fn click(&mut self, rig: &Rig, s: &Value, seq: u64, drawn: [f64; 2]) -> bool {
        let off = [12.0 * self.rng.f64() - 6.0, 12.0 * self.rng.f64() - 6.0];
        let (x, y) = (drawn[0] + off[0], drawn[1] + off[1]);
        extension_request(
            &rig.files,
            "klipcal_backlash_tip",
            json!({"x": x, "y": y, "frame": seq, "sd": 3.5}),
        )
        .await
        .unwrap();
        self.posted += 1;
        assert!(
            self.posted <= self.most,
            "more snapshots than readings: {s}"
        );
        true
    }
}

/// The clicks only locate the nozzle; the offsets are measured from the pictures: clicks
/// posted off by up to 6 px on each axis (75 µm at 80 px/mm, as a finger on a phone) give the
/// drawn play within its stated ± and within 3 µm, every click after the first refined against
/// it. Taken as clicked, the same clicks read it tens of µm off with a ± of tens of µm.
#[tokio::test]
async fn clicks_posted_off_by_pixels_are_refined_from_the_pictures() {
    const TRUE_X: f64 = 0.07;
    const CYCLES: usize = 4;
    let camera = json!({"look": "two_nozzles", "px_per_mm": 80, "rotation_deg": 35,
        "offset_px": [8, -12], "centre_mm": [100, 100], "seed": 11});
    let rig = click_rig(camera, TRUE_X).await;
    rig.run_click_macro(CYCLES).await;
    let mut posted = PostedClicks {
        rng: fastrand::Rng::with_seed(31),
        posted: 0,
        most: 6 + 2 * CYCLES,
    };
    let what = "clicks off by up to 6 px";
    let Clicked { got, u, cam, .. } =
        click_until_measured(&rig, &mut posted, "x", TRUE_X, CYCLES, what).await;
    // Every click after the first (the reference) refined from the pictures, none kept.
    assert_eq!(cam["refined"], json!(5 + 2 * CYCLES), "{cam}");
    assert_eq!(cam["kept"], json!([]), "{cam}");
    assert!(
        (got - TRUE_X).abs() <= 0.003,
        "measured {got}, drawn {TRUE_X}"
    );
    assert!(u <= 0.003, "± {u} mm");
}

/// Taps as a person on a phone gives them on klipcal's page inside Mainsail's webcam frame:
/// waits in the frame for the snapshot that asks for a tap; a first tap near the tip zooms in
/// there, the second lands 2.4–4.2 picture px from the tip in a random direction (seeded), as
/// a touch (the page then states its touch precision). Each tap is a touch click dispatched
/// on the picture at the window point over that pixel, inside the frame's document: a
/// synthetic tap at window coordinates reached Mainsail's frame once in three runs of
/// headless Chromium's emulated phone (`the_pages_jog_buttons_work_inside_mainsails_webcam_frame`).
struct FrameTaps {
    b: Browser,
    inside: String,
    rng: fastrand::Rng,
    /// Each tap's distance from the tip, picture px, and the precision the page stated.
    taps: Vec<(f64, f64)>,
}

impl Clicker for FrameTaps {
    async fn prompt(&mut self, rig: &Rig, s: &Value, done: u64) -> Option<u64> {
        assert!(s["state"] != "failed", "{s}\n{}", rig.d.log_text());
        assert!(
            self.taps.len() < 60,
            "no end after {} taps: {s}",
            self.taps.len()
        );
        let ready = format!(
            "(() => {{ const f = document.querySelector('#snapshot[data-click=\"1\"][data-ready=\"1\"]');
               return f && !f.dataset.sent && +f.dataset.seq > {done} ? +f.dataset.seq : null; }})()"
        );
        for _ in 0..20 {
            let seq = self.b.eval_in_frame(&self.inside, &ready).await;
            if let Some(seq) = seq.as_ref().and_then(Value::as_u64) {
                return Some(seq);
            }
            tokio::time::sleep(Duration::from_millis(250)).await;
        }
        None
    }

    async fn click(&mut self, _: &Rig, _: &Value, seq: u64, drawn: [f64; 2]) -> bool {
        let r = 2.4 + 1.8 * self.rng.f64();
        let a = std::f64::consts::TAU * self.rng.f64();
        let tap = [drawn[0] + r * a.cos(), drawn[1] + r * a.sin()];
        let js = format!(
            "(() => {{ const fig = document.querySelector('#snapshot[data-click=\"1\"][data-ready=\"1\"]');
               if (!fig || +fig.dataset.seq !== {seq} || fig.dataset.sent) return null;
               const img = document.querySelector('#snapimg'), snap = fig.querySelector('.snap');
               fig.scrollIntoView({{block: 'center'}});
               const press = p => {{ const q = img.getBoundingClientRect(), k = q.width / img.naturalWidth;
                 snap.dispatchEvent(new PointerEvent('click', {{bubbles: true, cancelable: true,
                   pointerType: 'touch', clientX: q.left + (p[0] + 0.5) * k, clientY: q.top + (p[1] + 0.5) * k}})); }};
               if (document.querySelector('.stage').style.transform === '') press([{hx}, {hy}]);
               if (document.querySelector('.stage').style.transform === '') return null;
               press([{tx}, {ty}]);
               return img.naturalWidth / img.getBoundingClientRect().width * 3; }})()",
            hx = drawn[0] + 3.0,
            hy = drawn[1] - 2.0,
            tx = tap[0],
            ty = tap[1],
        );
        let Some(sd) = self
            .b
            .eval_in_frame(&self.inside, &js)
            .await
            .and_then(|v| v.as_f64())
        else {
            return false;
        };
        self.taps.push((r, sd));
        let saved = "document.querySelector('#clickhelp').textContent.includes('saved')";
        for _ in 0..40 {
            if self.b.eval_in_frame(&self.inside, saved).await == Some(json!(true)) {
                return true;
            }
            tokio::time::sleep(Duration::from_millis(250)).await;
        }
        false
    }
}

/// Issue 37 item 6, the case found in real Mainsail on a phone: KLIPCAL_BACKLASH_CLICK of X,
/// then of Y, run through Klipper on a CoreXY bench whose motors A and B each have 0.050 mm of
/// play (so X and Y both lose (a + b)/2 = 0.050 mm at a reversal); the camera serves frames made
/// from a real photo (kTAMV's frame, 320×240, 80 px/mm, turned 3°, lit, noisy, JPEG). The taps
/// are given on klipcal's page shown as Mainsail's iframe webcam at 390×844, each 2.4–4.2 px
/// off the tip (seeded). Each axis must read 0.050 mm within its ±2u, and the CoreXY answer
/// must not say "X and Y differ" (it said so from Y 0.0612 ± 0.0046 in the finding).
#[tokio::test]
async fn taps_a_few_px_off_in_mainsails_webcam_frame_on_a_phone_read_the_play_on_both_axes() {
    use crate::frontends::{FrontEnd, Kind, Ui};
    const PLAY: f64 = 0.05;
    const CYCLES: usize = 4;
    let camera = json!({"photo": "ktamv-frame", "width": 320, "height": 240, "px_per_mm": 80,
        "rotation_deg": 3, "offset_px": [0, 0], "centre_mm": [150, 150], "seed": 37});
    let play = format!(r#"{{"a": {PLAY}, "b": {PLAY}}}"#);
    let rig = Rig::start("corexy", "seed", &play, camera, &[], [150.0, 150.0]).await;
    let base = rig.d.page_url().await;
    crate::page_phone::page_as_webcam(&rig.files, &base).await;
    let fe = FrontEnd::serve(Kind::Mainsail, &rig.bench).await;
    let mut b = Browser::start().await;
    let mut ui = Ui::open(&mut b, &fe, "mainsail-click-phone").await;
    ui.phone().await;
    ui.b.eval("document.querySelector('#app').__vue__.$router.push('/cam').catch(() => {}), true")
        .await;
    drop(ui);
    let mut taps = FrameTaps {
        b,
        inside: format!("{base}/"),
        rng: fastrand::Rng::with_seed(37),
        taps: Vec::new(),
    };
    let mut got = serde_json::Map::new();
    let mut last = Value::Null;
    for key in ["x", "y"] {
        rig.m
            .gcode(&format!(
                "KLIPCAL_BACKLASH_CLICK AXIS={} CYCLES={CYCLES}",
                key.to_uppercase()
            ))
            .await
            .unwrap();
        let from = taps.taps.len();
        let what = format!("{key} tapped 2.4–4.2 px off in Mainsail's frame at 390×844");
        let c = click_until_measured(&rig, &mut taps, key, PLAY, CYCLES, &what).await;
        let t = &taps.taps[from..];
        let (lo, hi) = t
            .iter()
            .fold((f64::MAX, 0.0f64), |(l, h), x| (l.min(x.0), h.max(x.0)));
        let sd: Vec<String> = t.iter().map(|x| format!("{:.2}", x.1)).collect();
        eprintln!(
            "{key}: {:.4} ± {:.4} mm (truth {PLAY}, ±2u {:.4}–{:.4}); taps {lo:.1}–{hi:.1} px \
             off, stated sd {}; cycles {}",
            c.got,
            c.u,
            c.got - 2.0 * c.u,
            c.got + 2.0 * c.u,
            sd.join(" "),
            c.cam["cycles"]
        );
        got.insert(key.into(), json!([c.got, c.u]));
        last = c.s;
    }
    taps.b
        .screenshot(&artifact("page-phone/mainsail-webcam-clicks.png"))
        .await;
    let answer = last["corexy_answer"].as_str().unwrap_or_default();
    eprintln!("CoreXY answer: {answer}");
    assert!(answer.contains("X and Y"), "no X/Y answer: {last}");
    assert!(
        !answer.contains("X and Y differ"),
        "same play on X and Y ({PLAY} mm), measured {got:?}, and the answer: {answer}"
    );
}
