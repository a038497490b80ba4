//! Backlash on the bench (seed 004): a test plays the person at the nozzle camera by reading
//! the bench's true nozzle position (comms/nozzle_true.json, with ±1.5 µm of sub-pixel noise)
//! while it jogs through G-code as `calib::backlash_guide` directs; the statistics must find the
//! simulated play, and after SET_BACKLASH_COMPENSATION (PR 7259's stand-in) or PR 7157's
//! `[backlash]` a re-measurement must find it gone. Detection of each branch on real Klipper
//! answers.

use std::time::Duration;

use klipcal::calib::backlash::{analyse, BacklashParams};
use klipcal::calib::backlash_guide::{Guide, GuideAxis, GuideParams, Phase, Press};
use klipcal::klipper::backlash::{detect, parse_reply, set_backlash_command, Branch, SetBacklash};
use klipcal::moonraker::{Files, Moonraker};
use serde_json::{json, Value};

use crate::bench::{extension_request, Bench, Daemon};

pub fn nozzle(bench: &Bench) -> [f64; 3] {
    let path = bench.dir.path().join("comms/nozzle_true.json");
    let v: Value = serde_json::from_str(&std::fs::read_to_string(&path).unwrap()).unwrap();
    let n = &v["nozzle"];
    [0, 1, 2].map(|i| n[i].as_f64().unwrap())
}

async fn move_to(m: &Moonraker, p: [f64; 3]) {
    let line = klipcal::klipper::GcodeCmd::new("G1")
        .axis('X', p[0])
        .axis('Y', p[1])
        .axis('F', 3000.0)
        .build()
        .unwrap();
    m.gcode(&line).await.unwrap();
}

/// Measures one axis the way a person at the camera would; `point` is the camera point
/// (commanded), `mark` the true nozzle position the person saw centred when it was saved.
async fn measure(
    bench: &Bench,
    m: &Moonraker,
    axis: GuideAxis,
    point: [f64; 3],
    mark: [f64; 3],
    rng: &mut fastrand::Rng,
) -> Vec<klipcal::calib::backlash::Cycle> {
    let params = GuideParams {
        cycles: 3,
        ..GuideParams::default()
    };
    let (mut g, mut step) = Guide::start(axis, axis.coord(point), params, rng.u64(..)).unwrap();
    let mut presses = 0;
    loop {
        for &s in &step.moves_mm {
            move_to(m, axis.point_at(point, s)).await;
        }
        if step.phase == Phase::Done {
            return g.cycles;
        }
        let dir = if step.phase == Phase::Plus { 1.0 } else { -1.0 };
        let noise = (rng.f64() * 2.0 - 1.0) * 0.0015;
        let seen = dir * (axis.coord(nozzle(bench)) - axis.coord(mark)) + noise;
        let fine = g.fine_mm();
        let press = if step.crossing {
            // Centred pressed: at each fine jog still centred (Fine) until it looks past, then
            // Past twice.
            if seen > fine / 2.0 {
                Press::Past
            } else {
                Press::Fine
            }
        } else if seen >= -fine / 2.0 {
            Press::Centred
        } else if seen < -0.12 {
            Press::Coarse
        } else {
            Press::Fine
        };
        step = g.press(press).unwrap();
        presses += 1;
        assert!(presses < 2000, "the procedure does not converge");
    }
}

pub async fn connect(bench: &Bench) -> (Moonraker, tokio_util::sync::CancellationToken) {
    let (m, c) = bench.client(json!({}));
    m.wait_connected(Duration::from_secs(30)).await.unwrap();
    (m, c)
}

async fn detection(m: &Moonraker) -> klipcal::klipper::backlash::Detection {
    let help = m.call("printer.gcode.help", json!({})).await.unwrap();
    let cfg = m.configfile().await.unwrap();
    detect(&help, &cfg.config).unwrap()
}

/// Puts the nozzle on the camera point from the − side and returns the mark the person sees.
pub async fn set_point(bench: &Bench, m: &Moonraker, point: [f64; 3]) -> [f64; 3] {
    m.gcode("G28\nG90").await.unwrap();
    move_to(m, [point[0] - 1.0, point[1] - 1.0, point[2]]).await;
    move_to(m, point).await;
    nozzle(bench)
}

/// What PR 7259's `SET_BACKLASH_COMPENSATION` reports now (the bare command's reply).
pub async fn reply_now(m: &Moonraker) -> klipcal::klipper::backlash::BacklashReply {
    m.gcode("SET_BACKLASH_COMPENSATION").await.unwrap();
    parse_reply(&last_reply(m).await).unwrap()
}

pub async fn last_reply(m: &Moonraker) -> String {
    let store = m
        .call("server.gcode_store", json!({"count": 20}))
        .await
        .unwrap();
    store["gcode_store"]
        .as_array()
        .unwrap()
        .iter()
        .filter_map(|e| e["message"].as_str())
        .collect::<Vec<_>>()
        .join("\n")
}

#[tokio::test]
async fn x_and_y_measured_at_the_camera_then_compensated_by_set_backlash_compensation() {
    let bench = Bench::start_args(
        "cartesian",
        &[
            "--backlash-module",
            "seed",
            "--play",
            r#"{"x": 0.08, "y": 0.05}"#,
        ],
    );
    let (m, _c) = connect(&bench).await;
    assert_eq!(detection(&m).await.branch, Branch::Seed);
    let point = [100.0, 100.0, 0.0];
    let mark = set_point(&bench, &m, point).await;
    let mut rng = fastrand::Rng::with_seed(12);
    let p = BacklashParams::default();
    let mut set = SetBacklash::default();
    for (axis, truth) in [(GuideAxis::X, 0.08), (GuideAxis::Y, 0.05)] {
        let cycles = measure(&bench, &m, axis, point, mark, &mut rng).await;
        let r = analyse(axis.name(), &cycles, Some(3000.0), &p).unwrap();
        assert!(
            (r.backlash_mm - truth).abs() <= 3.0 * r.uncertainty_mm + 0.002,
            "{axis:?}: measured {r:?}, simulated {truth}"
        );
        assert!(r.compensate, "{r:?}");
        match axis {
            GuideAxis::X => set.x_mm = Some(r.backlash_mm),
            _ => set.y_mm = Some(r.backlash_mm),
        }
        set.smooth_time_s = Some(r.smooth_time_s.max(set.smooth_time_s.unwrap_or(0.0)));
    }
    let cmd = set_backlash_command(&set).unwrap();
    m.gcode(&cmd).await.unwrap();
    let reply = parse_reply(&last_reply(&m).await).unwrap();
    assert!(reply.agrees_with(&set), "{reply:?} vs {set:?}");
    // Re-measured with compensation: what is left is within a fine jog of zero.
    let mark = set_point(&bench, &m, point).await;
    for axis in [GuideAxis::X, GuideAxis::Y] {
        let cycles = measure(&bench, &m, axis, point, mark, &mut rng).await;
        let r = analyse(axis.name(), &cycles, Some(3000.0), &p).unwrap();
        assert!(r.backlash_mm <= 0.012, "{axis:?} after compensation: {r:?}");
        assert!(!r.compensate);
    }
    // Bad values are refused by Klipper's own limits too (SMOOTH_TIME ≤ 0.1).
    assert!(m
        .gcode("SET_BACKLASH_COMPENSATION SMOOTH_TIME=0.2")
        .await
        .unwrap_err()
        .to_string()
        .contains("SMOOTH_TIME must have maximum of 0.1"));
}

#[tokio::test]
async fn pr_7157_a_and_b_on_corexy_are_measured_and_removed_by_the_config() {
    let bench = Bench::start_args(
        "corexy",
        &[
            "--backlash-module",
            "pr7157",
            "--play",
            r#"{"a": 0.1, "b": 0.04}"#,
        ],
    );
    let (m, _c) = connect(&bench).await;
    assert_eq!(detection(&m).await.branch, Branch::Pr7157 { corexy: true });
    let point = [150.0, 150.0, 0.0];
    let mark = set_point(&bench, &m, point).await;
    let mut rng = fastrand::Rng::with_seed(7);
    let p = BacklashParams::default();
    let mut found = std::collections::BTreeMap::new();
    for (axis, truth) in [(GuideAxis::A, 0.1), (GuideAxis::B, 0.04)] {
        let cycles = measure(&bench, &m, axis, point, mark, &mut rng).await;
        let r = analyse(axis.name(), &cycles, None, &p).unwrap();
        assert!(
            (r.backlash_mm - truth).abs() <= 3.0 * r.uncertainty_mm + 0.002,
            "{axis:?}: {r:?} vs {truth}"
        );
        found.insert(axis.name().to_string(), r.backlash_mm);
    }
    // PR 7157 has no command: the values go into [backlash] and Klipper restarts.
    let cfg_path = bench.dir.path().join("config/printer.cfg");
    let cfg = klipcal::klipper::Config::load(&klipcal::fsio::FsFiles, &cfg_path).unwrap();
    let values =
        klipcal::klipper::backlash::config_values(Branch::Pr7157 { corexy: true }, &found, None)
            .unwrap();
    let triples: Vec<(&str, &str, &str)> = values
        .iter()
        .map(|(s, k, v)| (s.as_str(), k.as_str(), v.as_str()))
        .collect();
    for edit in klipcal::klipper::set_values(&cfg, &triples).unwrap() {
        std::fs::write(&edit.path, &edit.new_text).unwrap();
    }
    m.gcode("RESTART").await.ok();
    // Klipper is back and reads the written values.
    let want = values[0].2.as_str();
    crate::bench::poll(Duration::from_secs(60), || async {
        let got = m.configfile().await.ok()?;
        let a = got.config.get("backlash").and_then(|s| s.get("a"));
        (a.map(String::as_str) == Some(want)).then_some(())
    })
    .await
    .expect("klippy back after RESTART with the written [backlash] a");
    let mark = set_point(&bench, &m, point).await;
    for axis in [GuideAxis::A, GuideAxis::B] {
        let cycles = measure(&bench, &m, axis, point, mark, &mut rng).await;
        let r = analyse(axis.name(), &cycles, None, &p).unwrap();
        assert!(r.backlash_mm <= 0.012, "{axis:?} after [backlash]: {r:?}");
    }
}

#[tokio::test]
async fn a_printer_with_neither_branch_is_detected_with_what_klipper_lacks() {
    let bench = Bench::start_args("cartesian", &["--play", r#"{"x": 0.03}"#]);
    let (m, _c) = connect(&bench).await;
    let d = detection(&m).await;
    assert_eq!(d.branch, Branch::Neither);
    assert!(d.why.contains("SET_BACKLASH_COMPENSATION"), "{}", d.why);
    assert!(!d.can_apply());
    // Klipper itself does not know the command.
    m.gcode("SET_BACKLASH_COMPENSATION X_BACKLASH=0.03")
        .await
        .ok();
    assert!(last_reply(&m).await.contains("Unknown command"));
    // Measuring still works and says whether backlash matters.
    let point = [100.0, 100.0, 0.0];
    let mark = set_point(&bench, &m, point).await;
    let mut rng = fastrand::Rng::with_seed(3);
    let cycles = measure(&bench, &m, GuideAxis::X, point, mark, &mut rng).await;
    let r = analyse("x", &cycles, None, &BacklashParams::default()).unwrap();
    assert!(
        (r.backlash_mm - 0.03).abs() <= 3.0 * r.uncertainty_mm + 0.002,
        "{r:?}"
    );
}

/// The daemon on `bench` with `toml`, the printer homed and the camera point saved at `point`
/// (KLIPCAL_BACKLASH_SET_POINT); returns the daemon, a client and the mark the person sees
/// there.
pub async fn at_the_camera(
    bench: &Bench,
    toml: &str,
    point: [f64; 3],
) -> (
    Daemon,
    Moonraker,
    tokio_util::sync::CancellationToken,
    [f64; 3],
) {
    let d = Daemon::ready(bench, toml).await;
    let (m, c) = connect(bench).await;
    let mark = set_point(bench, &m, point).await;
    extension_request(&bench.files(), "klipcal_backlash_set_point", json!({}))
        .await
        .unwrap();
    (d, m, c, mark)
}

/// KLIPCAL_BACKLASH_APPLY through the API: its answer, which must say `done` (the daemon's
/// log on failure).
pub async fn apply_done(bench: &Bench, d: &Daemon) -> Value {
    let r = extension_request(&bench.files(), "klipcal_backlash_apply", json!({}))
        .await
        .unwrap_or_else(|e| panic!("apply: {e}\n{}", d.log_text()));
    assert_eq!(r["state"], "done", "{r}");
    r
}

/// What Klipper's config holds for `keys` of `section` after an apply (and its restart): each
/// must be there, a number.
pub async fn config_values(m: &Moonraker, section: &str, keys: &[&str]) -> Vec<f64> {
    let cf = m.configfile().await.unwrap();
    keys.iter()
        .map(|k| {
            cf.settings
                .option(section, k)
                .and_then(Value::as_f64)
                .unwrap_or_else(|| {
                    panic!(
                        "[{section}] {k} after apply: {:?}",
                        cf.settings.section(section)
                    )
                })
        })
        .collect()
}

/// Presses `button` in the jog dialog (the remote method its macro calls). A refusal that says
/// the way on ("press Overshot": the nozzle looked centred where the approach began, or right
/// after a coarse jog) is followed as a person would; any other refusal fails the test.
pub async fn press_jog(files: &Files, d: &Daemon, button: &str) -> Value {
    match extension_request(files, "klipcal_backlash_jog", json!({"press": button})).await {
        Ok(r) => r,
        Err(e) if e.contains("press Overshot") => {
            extension_request(files, "klipcal_backlash_jog", json!({"press": "overshot"}))
                .await
                .unwrap_or_else(|e| panic!("press overshot: {e}\n{}", d.log_text()))
        }
        Err(e) => panic!("press {button}: {e}\n{}", d.log_text()),
    }
}
