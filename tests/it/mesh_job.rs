//! The daemon's thermal mesh (issue 11) on the mesh-variant bench (simulated probe, a frame
//! thermistor fed by the plant, a gantry bow that grows with the frame): a capture through
//! the macro-facing remote method heats, soaks, takes meshes as the frame warms, fits and
//! writes `klipcal_<T>` profiles Klipper loads; following loads them; the reference check
//! passes on the same bed and halts on a shifted one; fade and bad arguments are refused.

use std::time::Duration;

use klipcal::moonraker::Moonraker;
use serde_json::{json, Value};

use crate::bench::{extension_request, poll, Bench, Daemon};
use crate::session::settings;

pub const PLANT: &str = r#"{"accel": 20, "bed": {"tau_plate_s": 100.0, "tau_heater_s": 20.0},
    "frame": {"gain": 0.6, "tau_s": 1200.0, "lag_s": 30.0}}"#;

pub fn mesh_settings() -> String {
    // The [soak] of the A/B bench tests (fast plant), and a capture that ends after 4 meshes.
    let base = settings(600.0);
    format!(
        "{base}[mesh]\nbed_temp_c = 60.0\nstep_c = 0.5\ninterval_s = 120.0\nsettle_c = 0.01\n\
         min_meshes = 3\nmax_meshes = 4\nmax_s = 900.0\nsoak_max_s = 600.0\ntolerance_um = 5.0\n\
         follow_interval_s = 1.0\njump_limit_um = 1000.0\n"
    )
}

pub async fn mesh_session(bench: &Bench) -> Value {
    extension_request(&bench.files(), "klipcal_status", json!({}))
        .await
        .map(|v| v["last"]["mesh"].clone())
        .unwrap_or(Value::Null)
}

/// Bad arguments to the capture and the follower are refused by name; following needs a
/// capture first.
async fn bad_capture_and_follow_arguments_are_refused_by_name(files: &klipcal::moonraker::Files) {
    let e = extension_request(files, "klipcal_mesh_capture", json!({"bde": 60}))
        .await
        .unwrap_err();
    assert!(e.contains("unknown argument BDE"), "{e}");
    let e = extension_request(files, "klipcal_mesh_follow", json!({"enable": "yes"}))
        .await
        .unwrap_err();
    assert!(e.contains("ENABLE=yes"), "{e}");
    let e = extension_request(files, "klipcal_mesh_follow", json!({}))
        .await
        .unwrap_err();
    assert!(
        e.contains("KLIPCAL_MESH_CAPTURE"),
        "following needs a capture first: {e}"
    );
}

/// Klipper knows a `klipcal_<T>` profile for each temperature of the result.
async fn klipper_knows_the_profiles(m: &Moonraker, temps: &[f64]) {
    let st = m
        .objects_query(json!({"bed_mesh": ["profiles"]}))
        .await
        .unwrap();
    let known: Vec<String> = st["bed_mesh"]["profiles"]
        .as_object()
        .unwrap()
        .keys()
        .cloned()
        .collect();
    for t in temps {
        let name = format!("klipcal_{t:.2}");
        assert!(known.contains(&name), "{name} not in {known:?}");
    }
}

/// The klipcal profile Klipper has loaded, once it has one within `limit`.
async fn klipcal_profile_loaded(m: &Moonraker, limit: Duration) -> Option<String> {
    poll(limit, || async {
        let st = m
            .objects_query(json!({"bed_mesh": ["profile_name"]}))
            .await
            .ok()?;
        let name = st["bed_mesh"]["profile_name"].as_str()?.to_string();
        name.starts_with("klipcal_").then_some(name)
    })
    .await
}

#[tokio::test]
async fn capture_fit_profiles_follow_and_check_on_the_bench() {
    let bench = Bench::start_args("corexy", &["--variant", "mesh", "--plant-json", PLANT]);
    // The capture below ends at mesh.max_meshes while the frame still warms: following right
    // after runs a little past the captured range, which mesh.range_margin_c allows (by
    // default following stops at the range's ends).
    let d = Daemon::ready(
        &bench,
        &format!("{}range_margin_c = 1.0\n", mesh_settings()),
    )
    .await;
    let files = bench.files();
    bad_capture_and_follow_arguments_are_refused_by_name(&files).await;

    extension_request(&files, "klipcal_mesh_capture", json!({}))
        .await
        .unwrap();
    let done = poll(Duration::from_secs(600), || async {
        let s = mesh_session(&bench).await;
        matches!(s["state"].as_str(), Some("done" | "failed")).then_some(s)
    })
    .await
    .unwrap_or_else(|| panic!("capture never finished: {}\n{}", "", d.log_text()));
    assert_eq!(done["state"], "done", "{done}\n{}", d.log_text());
    assert!(done["meshes"].as_u64().unwrap() >= 3, "{done}");
    // The frame warmed while the meshes were taken, and each mesh is stamped with it.
    let frames: Vec<f64> = serde_json::from_value(done["frame_c"].clone()).unwrap();
    assert!(
        frames.last().unwrap() > frames.first().unwrap(),
        "{frames:?}"
    );
    let result = &done["result"];
    let temps: Vec<f64> = serde_json::from_value(result["profiles_c"].clone()).unwrap();
    assert!(!temps.is_empty(), "{result}");
    // The profiles are in printer.cfg's SAVE_CONFIG block and Klipper knows them.
    let cfg = std::fs::read_to_string(bench.dir.path().join("config/printer.cfg")).unwrap();
    assert!(
        cfg.contains("#*# [bed_mesh klipcal_"),
        "no profiles in printer.cfg"
    );
    let (m, _c) = bench.client(json!({}));
    m.wait_connected(Duration::from_secs(30)).await.unwrap();
    klipper_knows_the_profiles(&m, &temps).await;
    // The heaters went off at the end of the capture.
    let hb = m
        .objects_query(json!({"heater_bed": ["target"]}))
        .await
        .unwrap();
    assert_eq!(hb["heater_bed"]["target"], json!(0.0));

    // Following loads a klipcal profile.
    extension_request(&files, "klipcal_mesh_follow", json!({"enable": "1"}))
        .await
        .unwrap();
    let loaded = klipcal_profile_loaded(&m, Duration::from_secs(30)).await;
    assert!(
        loaded.is_some(),
        "no klipcal profile loaded: {}\n{}",
        mesh_session(&bench).await,
        d.log_text()
    );
    let s = mesh_session(&bench).await;
    assert_eq!(s["follow"]["following"], json!(true), "{s}");
    // Klipper restarted mid-follow: the restart drops the mesh; the follower loads it again.
    bench.stop_one("klippy");
    bench.start_one("klippy");
    let again = klipcal_profile_loaded(&m, Duration::from_secs(60)).await;
    assert!(
        again.is_some(),
        "no klipcal profile after the restart\n{}",
        d.log_text()
    );
    extension_request(&files, "klipcal_mesh_follow", json!({"enable": "0"}))
        .await
        .unwrap();

    // The reference check passes on the same bed.
    let r = extension_request(&files, "klipcal_mesh_check", json!({}))
        .await
        .unwrap();
    assert!(
        r["message"].as_str().unwrap().contains("check passed"),
        "{r}"
    );

    // A shifted bed (a swapped plate): the check refuses with the point and the difference.
    let surface = bench.dir.path().join("comms/surface.json");
    let mut sp: Value = serde_json::from_str(&std::fs::read_to_string(&surface).unwrap()).unwrap();
    sp["tilt_x_um"] = json!(900.0);
    std::fs::write(&surface, sp.to_string()).unwrap();
    bench.restart_klippy().await;
    let e = extension_request(&files, "klipcal_mesh_check", json!({}))
        .await
        .unwrap_err();
    assert!(
        e.contains("from the model") && e.contains("limit 0.5 mm"),
        "{e}"
    );
    drop(d);
}

#[tokio::test]
async fn a_capture_started_over_http_survives_kill_9_and_following_refuses_a_fading_mesh() {
    let bench = Bench::start_args("corexy", &["--variant", "mesh", "--plant-json", PLANT]);
    let mut d = Daemon::ready(&bench, &mesh_settings()).await;
    let files = bench.files();
    // Started through the daemon's own API.
    let base = d.page_url().await;
    let r = reqwest::Client::new()
        .post(format!("{base}/api/mesh/capture"))
        .header("content-type", "application/json")
        .body(r#"{"bed": 60}"#)
        .send()
        .await
        .unwrap();
    assert_eq!(
        r.status().as_u16(),
        200,
        "{}",
        r.text().await.unwrap_or_default()
    );
    // Killed (-9) once a mesh is stored: the stored meshes survive and the capture goes on.
    let first = poll(Duration::from_secs(300), || async {
        let s = mesh_session(&bench).await;
        (s["meshes"].as_u64().unwrap_or(0) >= 1).then_some(s)
    })
    .await
    .unwrap_or_else(|| panic!("no mesh stored\n{}", d.log_text()));
    let _ = d.child.kill();
    let _ = d.child.wait();
    let before: Vec<f64> = serde_json::from_value(first["frame_c"].clone()).unwrap();
    let d2 = Daemon::ready(&bench, &mesh_settings()).await;
    let done = poll(Duration::from_secs(600), || async {
        let s = mesh_session(&bench).await;
        matches!(s["state"].as_str(), Some("done" | "failed")).then_some(s)
    })
    .await
    .expect("capture finished after the restart");
    assert_eq!(done["state"], "done", "{done}\n{}", d2.log_text());
    let after: Vec<f64> = serde_json::from_value(done["frame_c"].clone()).unwrap();
    assert_eq!(
        &after[..before.len()],
        &before[..],
        "meshes stored before the kill were lost"
    );
    assert!(after.len() > before.len(), "{after:?}");
    assert!(
        d2.log_text().contains("resuming thermal mesh session"),
        "{}",
        d2.log_text()
    );

    // With [bed_mesh] fading, following is refused and says how to fix it.
    let path = bench.dir.path().join("config/printer.cfg");
    let cfg = std::fs::read_to_string(&path).unwrap();
    std::fs::write(
        &path,
        cfg.replacen(
            "[bed_mesh]\n",
            "[bed_mesh]\nfade_start: 1\nfade_end: 10\n",
            1,
        ),
    )
    .unwrap();
    bench.restart_klippy().await;
    let e = extension_request(&files, "klipcal_mesh_follow", json!({"enable": "1"}))
        .await
        .unwrap_err();
    assert!(e.contains("fade_end: 0"), "{e}");
    drop(d2);
}

#[tokio::test]
async fn vgb_profiles_in_the_config_are_imported_fitted_and_written_as_klipcal_profiles() {
    use klipcal::klipper::bed_mesh::{format_profile, profiles, MeshProfile};
    let bench = Bench::start("corexy");
    let path = bench.dir.path().join("config/printer.cfg");
    let text = std::fs::read_to_string(&path).unwrap();
    let cfg = klipcal::klipper::Config::load(&klipcal::fsio::FsFiles, &path).unwrap();
    let base = profiles(&cfg).unwrap().remove(0);
    // VGB's set: a cold and a hot mesh (the centre sags 40 µm per 10 °C) and a test mesh.
    let mk = |name: &str, temp: f64| MeshProfile {
        name: name.into(),
        params: base.params.clone(),
        points_mm: base
            .points_mm
            .iter()
            .map(|r| r.iter().map(|z| z - 0.004 * (temp - 25.0)).collect())
            .collect(),
    };
    let mut block = String::new();
    for (n, t) in [("COLD25.0", 25.0), ("HOT35.0", 35.0), ("TEST30.0", 30.0)] {
        block.push_str(&format_profile(&mk(n, t)));
        block.push_str("#*#\n");
    }
    assert!(
        text.contains("#*# <---"),
        "the bench config has a SAVE_CONFIG block"
    );
    std::fs::write(&path, format!("{text}{block}")).unwrap();
    bench.stop_one("klippy");
    bench.start_one("klippy");
    let d = Daemon::ready(&bench, "").await;
    let files = bench.files();
    let r = extension_request(&files, "klipcal_mesh_import", json!({}))
        .await
        .unwrap_or_else(|e| panic!("import: {e}\n{}", d.log_text()));
    assert_eq!(r["imported"], json!(["COLD25.0", "HOT35.0"]), "{r}");
    // TEST30.0 is judged against the model of the other two (it lies on their line), and the
    // answer says so (issue 26 B.2); nothing klipcal wrote before, nothing replaced.
    assert_eq!(r["tests"][0]["name"], "TEST30.0", "{r}");
    assert!(r["tests"][0]["max_um"].as_f64().unwrap() < 1.0, "{r}");
    assert_eq!(r["tests"][0]["within_tolerance"], json!(true), "{r}");
    let msg = r["message"].as_str().unwrap();
    assert!(
        msg.contains("TEST30.0 is 0.0 µm from the model at most")
            && msg.contains("within the 5 µm tolerance"),
        "{msg}"
    );
    assert!(!msg.contains("replaces"), "{msg}");
    let done = poll(Duration::from_secs(120), || async {
        let s = mesh_session(&bench).await;
        matches!(s["state"].as_str(), Some("done" | "failed")).then_some(s)
    })
    .await
    .expect("import finished");
    assert_eq!(done["state"], "done", "{done}\n{}", d.log_text());
    assert!(done["notes"].to_string().contains("TEST30.0 is"), "{done}");
    // Imported meshes are not said to be taken while the frame warmed.
    let directions = done["result"]["directions"].as_str().unwrap();
    assert!(
        directions.contains("imported") && !directions.contains("warmed"),
        "{directions}"
    );
    let first: Vec<String> = serde_json::from_value(done["result"]["profiles_c"].clone())
        .map(|t: Vec<f64>| t.iter().map(|t| format!("klipcal_{t:.2}")).collect())
        .unwrap();
    // Imported again: the answer and the result name the klipcal profiles it replaces.
    let r = extension_request(&files, "klipcal_mesh_import", json!({}))
        .await
        .unwrap_or_else(|e| panic!("second import: {e}\n{}", d.log_text()));
    assert_eq!(r["replaces"], json!(first), "{r}");
    assert!(
        r["message"]
            .as_str()
            .unwrap()
            .contains(&format!("replaces the {} klipcal profiles", first.len())),
        "{r}"
    );
    let again = poll(Duration::from_secs(120), || async {
        let s = mesh_session(&bench).await;
        (s["id"] != done["id"] && matches!(s["state"].as_str(), Some("done" | "failed")))
            .then_some(s)
    })
    .await
    .expect("second import finished");
    assert_eq!(again["state"], "done", "{again}\n{}", d.log_text());
    assert_eq!(again["result"]["replaced"], json!(first), "{again}");
    assert!(
        again["progress"]
            .as_str()
            .unwrap()
            .contains("they replace the"),
        "{again}"
    );
    // The written profiles sit between the two meshes, with the user's VGB ones kept.
    let after = std::fs::read_to_string(&path).unwrap();
    assert!(
        after.contains("#*# [bed_mesh klipcal_"),
        "no klipcal profiles written"
    );
    assert!(after.contains("#*# [bed_mesh COLD25.0]") && after.contains("#*# [bed_mesh TEST30.0]"));
    let temps: Vec<f64> = serde_json::from_value(done["result"]["profiles_c"].clone()).unwrap();
    assert!(temps.iter().all(|t| (25.0..=35.0).contains(t)), "{temps:?}");
    // Mismatched mesh parameters are refused, naming the profile.
    let mut odd = mk("HOT40.0", 40.0);
    odd.params.max_x -= 10.0;
    std::fs::write(&path, format!("{after}{}#*#\n", format_profile(&odd))).unwrap();
    bench.restart_klippy().await;
    let e = extension_request(&files, "klipcal_mesh_import", json!({}))
        .await
        .unwrap_err();
    assert!(e.contains("HOT40.0"), "{e}");
    drop(d);
}

/// VGB's `COLD25.0` and `HOT35.0` profiles for the bench's printer.cfg (the centre and every
/// point sag 40 µm per 10 °C from the bench's `default` profile), as SAVE_CONFIG lines.
pub fn vgb_block(bench: &Bench) -> String {
    use klipcal::klipper::bed_mesh::{format_profile, profiles, MeshProfile};
    let path = bench.dir.path().join("config/printer.cfg");
    let cfg = klipcal::klipper::Config::load(&klipcal::fsio::FsFiles, &path).unwrap();
    let base = profiles(&cfg).unwrap().remove(0);
    let mut block = String::new();
    for (name, temp) in [("COLD25.0", 25.0), ("HOT35.0", 35.0)] {
        let p = MeshProfile {
            name: name.into(),
            params: base.params.clone(),
            points_mm: base
                .points_mm
                .iter()
                .map(|r| r.iter().map(|z| z - 0.004 * (temp - 25.0)).collect())
                .collect(),
        };
        block.push_str(&format_profile(&p));
        block.push_str("#*#\n");
    }
    block
}

/// Every file under `dir` (recursively), by path relative to it.
fn snapshot(dir: &std::path::Path) -> std::collections::BTreeMap<String, Vec<u8>> {
    let mut out = std::collections::BTreeMap::new();
    let mut stack = vec![dir.to_path_buf()];
    while let Some(d) = stack.pop() {
        for e in std::fs::read_dir(&d).unwrap() {
            let p = e.unwrap().path();
            if p.is_dir() {
                stack.push(p);
            } else {
                let rel = p.strip_prefix(dir).unwrap().to_string_lossy().into_owned();
                out.insert(rel, std::fs::read(&p).unwrap());
            }
        }
    }
    out
}

#[tokio::test]
async fn a_profile_write_klipper_refuses_is_rolled_back_byte_for_byte() {
    let bench = Bench::start("corexy");
    let files = bench.files();
    let path = bench.dir.path().join("config/printer.cfg");
    let text = std::fs::read_to_string(&path).unwrap();
    // VGB's COLD and HOT meshes to import: every fitted profile lies within ±0.1 mm.
    let block = vgb_block(&bench);
    // The user's [bed_mesh] fades towards z = 0.5 mm: Klipper starts with it (profiles are
    // only read at start) but refuses to load any mesh whose z range does not hold 0.5 mm
    // ("fade_target lies outside of mesh z range", bed_mesh.py set_mesh).
    let faded = format!("{text}{block}").replacen(
        "[bed_mesh]\n",
        "[bed_mesh]\nfade_start: 1\nfade_end: 10\nfade_target: 0.5\n",
        1,
    );
    assert_ne!(
        faded,
        format!("{text}{block}"),
        "no [bed_mesh] in the bench"
    );
    std::fs::write(&path, faded).unwrap();
    bench.stop_one("klippy");
    bench.start_one("klippy");
    let ready = || async {
        let v = files.get("/server/info").await.ok()?;
        (v["klippy_state"] == "ready").then_some(())
    };
    assert!(poll(Duration::from_secs(60), ready).await.is_some());
    let d = Daemon::ready(&bench, "").await;
    let config_dir = bench.dir.path().join("config");
    let before = snapshot(&config_dir);

    extension_request(&files, "klipcal_mesh_import", json!({}))
        .await
        .unwrap_or_else(|e| panic!("import: {e}\n{}", d.log_text()));
    let failed = poll(Duration::from_secs(180), || async {
        let s = mesh_session(&bench).await;
        matches!(s["state"].as_str(), Some("done" | "failed")).then_some(s)
    })
    .await
    .unwrap_or_else(|| panic!("the write never ended\n{}", d.log_text()));
    // The session failed and says which profile Klipper refused, in Klipper's words, and
    // that the config went back.
    assert_eq!(failed["state"], "failed", "{failed}\n{}", d.log_text());
    let reason = failed["reason"].as_str().unwrap_or("");
    assert!(
        reason.contains("Klipper refused to load profile klipcal_")
            && reason.contains("fade_target lies outside of mesh z range")
            && reason.contains("printer.cfg was restored")
            && reason.contains("Klipper is ready again"),
        "{reason}"
    );
    // The profiles were really written: the backup holds the file as it was.
    let after = snapshot(&config_dir);
    let backups: Vec<&String> = after
        .keys()
        .filter(|k| k.starts_with("klipcal_backups/"))
        .collect();
    assert_eq!(backups.len(), 1, "{backups:?}");
    assert_eq!(after[backups[0]], before["printer.cfg"]);
    // Every config file's bytes are as before; the backup is the only new file.
    for (name, bytes) in &before {
        assert!(
            after.get(name) == Some(bytes),
            "{name} differs after the rollback"
        );
    }
    assert_eq!(after.len(), before.len() + 1, "{:?}", after.keys());
    // Klipper is ready with the config of before: the user's profiles, no klipcal ones.
    assert!(poll(Duration::from_secs(30), ready).await.is_some());
    let (m, _c) = bench.client(json!({}));
    m.wait_connected(Duration::from_secs(30)).await.unwrap();
    let st = m
        .objects_query(json!({"bed_mesh": ["profiles"]}))
        .await
        .unwrap();
    let known: Vec<&String> = st["bed_mesh"]["profiles"]
        .as_object()
        .unwrap()
        .keys()
        .collect();
    assert!(known.iter().any(|k| *k == "COLD25.0"), "{known:?}");
    assert!(
        !known.iter().any(|k| k.starts_with("klipcal_")),
        "{known:?}"
    );
    drop(d);
}

#[tokio::test]
async fn following_sets_the_kept_bed_mesh_offset_again_after_each_load() {
    // The mesh bench (a frame sensor at 25 °C) with VGB's profiles imported: 25–35 °C.
    let bench = Bench::start_args("corexy", &["--variant", "mesh", "--plant-json", PLANT]);
    let files = bench.files();
    let path = bench.dir.path().join("config/printer.cfg");
    let text = std::fs::read_to_string(&path).unwrap();
    std::fs::write(&path, format!("{text}{}", vgb_block(&bench))).unwrap();
    bench.restart_klippy().await;
    let d = Daemon::ready(
        &bench,
        "[mesh]\nfollow_interval_s = 1.0\njump_limit_um = 1000.0\n",
    )
    .await;
    extension_request(&files, "klipcal_mesh_import", json!({}))
        .await
        .unwrap_or_else(|e| panic!("import: {e}\n{}", d.log_text()));
    let done = poll(Duration::from_secs(120), || async {
        let s = mesh_session(&bench).await;
        matches!(s["state"].as_str(), Some("done" | "failed")).then_some(s)
    })
    .await
    .expect("import finished");
    assert_eq!(done["state"], "done", "{done}\n{}", d.log_text());

    let (m, _c) = bench.client(json!({}));
    m.wait_connected(Duration::from_secs(30)).await.unwrap();
    // Klipper's own report of the active mesh's offsets (its status does not carry them).
    let offsets = || async {
        let mut rx = m.events();
        m.gcode("BED_MESH_OUTPUT").await.unwrap();
        let e = crate::bench::wait_event(&mut rx, Duration::from_secs(10), |e| {
            matches!(e, klipcal::moonraker::Event::GcodeResponse(l) if l.contains("Mesh Offsets:"))
        })
        .await;
        match e {
            Some(klipcal::moonraker::Event::GcodeResponse(l)) => l
                .lines()
                .find(|l| l.contains("Mesh Offsets:"))
                .unwrap_or("")
                .trim()
                .to_string(),
            _ => String::new(),
        }
    };
    let active = || async {
        let st = m
            .objects_query(json!({"bed_mesh": ["profile_name"]}))
            .await
            .ok()?;
        let name = st["bed_mesh"]["profile_name"].as_str()?.to_string();
        name.starts_with("klipcal_").then_some(name)
    };
    // The user's mesh with an offset set through klipcal.cfg's macro.
    m.gcode("BED_MESH_PROFILE LOAD=default\nKLIPCAL_MESH_OFFSET X=5 Y=-3")
        .await
        .unwrap();
    assert_eq!(offsets().await, "Mesh Offsets: X=5.0000, Y=-3.0000");
    let r = extension_request(&files, "klipcal_mesh_follow", json!({"enable": "1"}))
        .await
        .unwrap();
    assert!(
        r["message"]
            .as_str()
            .unwrap()
            .contains("KLIPCAL_MESH_OFFSET"),
        "{r}"
    );
    // The follower's load (which zeroes the offsets) sets the kept offset again.
    let loaded = poll(Duration::from_secs(30), active).await;
    assert!(
        loaded.is_some(),
        "no klipcal profile loaded\n{}",
        d.log_text()
    );
    assert_eq!(offsets().await, "Mesh Offsets: X=5.0000, Y=-3.0000");
    let s = poll(Duration::from_secs(10), || async {
        let s = mesh_session(&bench).await;
        (s["follow"]["offset_mm"] == json!([5.0, -3.0])).then_some(s)
    })
    .await;
    assert!(s.is_some(), "{}", mesh_session(&bench).await);
    // A new X through the macro (Y kept), then a load by hand drops it: the follower loads its
    // profile again and sets the offset the user set last.
    m.gcode("KLIPCAL_MESH_OFFSET X=2").await.unwrap();
    m.gcode("BED_MESH_PROFILE LOAD=hot").await.unwrap();
    let again = poll(Duration::from_secs(30), active).await;
    assert!(again.is_some(), "not loaded again\n{}", d.log_text());
    assert_eq!(offsets().await, "Mesh Offsets: X=2.0000, Y=-3.0000");
    // A value Klipper refuses stops the macro: the kept offset stays.
    assert!(m.gcode("KLIPCAL_MESH_OFFSET X=abc").await.is_err());
    let st = m
        .objects_query(json!({"gcode_macro KLIPCAL_MESH_OFFSET": ["x", "y"]}))
        .await
        .unwrap();
    assert_eq!(
        st["gcode_macro KLIPCAL_MESH_OFFSET"],
        json!({"x": 2.0, "y": -3.0})
    );
    extension_request(&files, "klipcal_mesh_follow", json!({"enable": "0"}))
        .await
        .unwrap();
    drop(d);
}

#[tokio::test]
async fn every_bad_argument_to_the_mesh_methods_is_refused_by_name() {
    let bench = Bench::start("corexy");
    let d = Daemon::ready(&bench, "").await;
    let files = bench.files();
    let (m, _c) = bench.client(json!({}));
    m.wait_connected(Duration::from_secs(30)).await.unwrap();
    let cases = bad_mesh_calls();
    crate::bench::assert_refused_everywhere(&bench, &d, &m, "mesh", &cases).await;
    // Positional arguments name the command and say what is expected.
    let e = extension_request(&files, "klipcal_mesh_capture", json!([60]))
        .await
        .unwrap_err();
    assert!(
        e.contains("KLIPCAL_MESH_CAPTURE: arguments must be named"),
        "{e}"
    );
    the_offset_macro_refuses_what_bed_mesh_offset_would_not_take(&m).await;
    // Nothing was started: no session, the bed cold, no mesh loaded.
    assert_eq!(mesh_session(&bench).await, Value::Null);
    let st = m
        .objects_query(json!({"heater_bed": ["target"], "bed_mesh": ["profile_name"]}))
        .await
        .unwrap();
    assert_eq!(st["heater_bed"]["target"], json!(0.0));
    assert_eq!(st["bed_mesh"]["profile_name"], json!(""));
    assert!(!d.log_text().contains("following the frame temperature"));
    drop(d);
}

/// The mesh methods' bad calls: (remote method, arguments, what the refusal names, the same
/// through its macro).
fn bad_mesh_calls() -> Vec<crate::bench::BadCall<'static>> {
    vec![
        (
            "capture",
            json!({"bde": 60}),
            "unknown argument BDE",
            Some("KLIPCAL_MESH_CAPTURE BDE=60"),
        ),
        (
            "capture",
            json!({"bed": "60", "extruder": 200}),
            "unknown argument EXTRUDER",
            Some("KLIPCAL_MESH_CAPTURE BED=60 EXTRUDER=200"),
        ),
        (
            "capture",
            json!({"bed": "hot"}),
            "BED=hot is not a number",
            Some("KLIPCAL_MESH_CAPTURE BED=hot"),
        ),
        (
            "capture",
            json!({"bed": 131}),
            "BED=131: expected a bed temperature from 0",
            Some("KLIPCAL_MESH_CAPTURE BED=131"),
        ),
        (
            "capture",
            json!({"bed": -5}),
            "BED=-5: expected a bed temperature from 0",
            Some("KLIPCAL_MESH_CAPTURE BED=-5"),
        ),
        (
            "capture",
            json!({"bed": "nan"}),
            "BED=nan is not a number",
            Some("KLIPCAL_MESH_CAPTURE BED=nan"),
        ),
        (
            "capture",
            json!({"bed": "inf"}),
            "BED=inf is not a number",
            None,
        ),
        (
            "capture",
            json!({"bed": true}),
            "BED=true is not a number",
            None,
        ),
        (
            "capture",
            json!({"bed": [60]}),
            "BED=[60] is not a number",
            None,
        ),
        (
            "capture",
            json!({"bed": {"c": 60}}),
            "BED={\"c\":60} is not a number",
            None,
        ),
        (
            "capture",
            json!({"bed": 60, "BED": 70}),
            "argument BED given twice",
            None,
        ),
        (
            "import",
            json!({"force": 1}),
            "unknown argument FORCE",
            Some("KLIPCAL_MESH_IMPORT FORCE=1"),
        ),
        (
            "follow",
            json!({"enable": "yes"}),
            "ENABLE=yes: expected 1 (follow) or 0 (stop)",
            Some("KLIPCAL_MESH_FOLLOW ENABLE=yes"),
        ),
        (
            "follow",
            json!({"enable": 2}),
            "ENABLE=2: expected 1",
            Some("KLIPCAL_MESH_FOLLOW ENABLE=2"),
        ),
        (
            "follow",
            json!({"enable": "-1"}),
            "ENABLE=-1: expected 1",
            None,
        ),
        (
            "follow",
            json!({"enable": [1]}),
            "ENABLE=[1]: expected 1",
            None,
        ),
        (
            "follow",
            json!({"enabel": 0}),
            "unknown argument ENABEL",
            Some("KLIPCAL_MESH_FOLLOW ENABEL=0"),
        ),
        (
            "check",
            json!({"x": 1}),
            "unknown argument X; it takes no arguments",
            Some("KLIPCAL_MESH_CHECK X=1"),
        ),
    ]
}

/// klipcal.cfg's offset macro refuses what BED_MESH_OFFSET would ignore or not parse, and
/// keeps nothing.
async fn the_offset_macro_refuses_what_bed_mesh_offset_would_not_take(m: &Moonraker) {
    let e = m.gcode("KLIPCAL_MESH_OFFSET X=1 Z=2").await.unwrap_err();
    assert!(
        e.to_string().contains("unknown argument Z; it takes X, Y"),
        "{e}"
    );
    for (line, want) in [
        ("KLIPCAL_MESH_OFFSET X=abc", "X=abc is not a number of mm"),
        (
            "KLIPCAL_MESH_OFFSET X=1 Y=nan",
            "Y=nan is not a number of mm",
        ),
        ("KLIPCAL_MESH_OFFSET Y=1e9", "Y=1e9 is not a number of mm"),
    ] {
        let e = m.gcode(line).await.expect_err(line);
        assert!(e.to_string().contains(want), "{line}: {e}");
    }
    // None of them kept anything.
    let st = m
        .objects_query(json!({"gcode_macro KLIPCAL_MESH_OFFSET": ["x", "y"]}))
        .await
        .unwrap();
    assert_eq!(
        st["gcode_macro KLIPCAL_MESH_OFFSET"],
        json!({"x": 0.0, "y": 0.0})
    );
}

/// Klipper's bed_mesh status: the active profile and every profile's points.
async fn klipper_meshes(m: &klipcal::moonraker::Moonraker) -> (String, Value) {
    let st = m
        .objects_query(json!({"bed_mesh": ["profile_name", "profiles"]}))
        .await
        .unwrap();
    (
        st["bed_mesh"]["profile_name"]
            .as_str()
            .unwrap_or("")
            .to_string(),
        st["bed_mesh"]["profiles"].clone(),
    )
}

#[tokio::test]
async fn a_cancelled_recapture_keeps_the_finished_one_and_never_touches_the_users_mesh() {
    // Issue 26 B.1 and B.4. Session 1: VGB's profiles imported (25–35 °C), profiles written.
    let bench = Bench::start_args("corexy", &["--variant", "mesh", "--plant-json", PLANT]);
    let files = bench.files();
    let path = bench.dir.path().join("config/printer.cfg");
    let text = std::fs::read_to_string(&path).unwrap();
    std::fs::write(&path, format!("{text}{}", vgb_block(&bench))).unwrap();
    bench.restart_klippy().await;
    let d = Daemon::ready(&bench, &mesh_settings()).await;
    extension_request(&files, "klipcal_mesh_import", json!({}))
        .await
        .unwrap_or_else(|e| panic!("import: {e}\n{}", d.log_text()));
    let first = poll(Duration::from_secs(120), || async {
        let s = mesh_session(&bench).await;
        matches!(s["state"].as_str(), Some("done" | "failed")).then_some(s)
    })
    .await
    .expect("import finished");
    assert_eq!(first["state"], "done", "{first}\n{}", d.log_text());
    let first_id = first["id"].as_i64().unwrap();

    // The user has their `hot` mesh loaded; Klipper's `default` holds their default mesh.
    let (m, _c) = bench.client(json!({}));
    m.wait_connected(Duration::from_secs(30)).await.unwrap();
    m.gcode("BED_MESH_PROFILE LOAD=hot").await.unwrap();
    let (_, before) = klipper_meshes(&m).await;
    assert!(before["default"]["points"].is_array(), "{before}");

    // Session 2: a re-capture, cancelled once it has taken a mesh.
    extension_request(&files, "klipcal_mesh_capture", json!({}))
        .await
        .unwrap();
    let taken = poll(Duration::from_secs(600), || async {
        let s = mesh_session(&bench).await;
        (s["meshes"].as_u64().unwrap_or(0) >= 1 || s["state"] == "failed").then_some(s)
    })
    .await
    .unwrap_or_else(|| panic!("no capture mesh\n{}", d.log_text()));
    assert_eq!(taken["state"], "capturing", "{taken}\n{}", d.log_text());
    // Between meshes the user's mesh is the active one, and their `default` is untouched:
    // the capture mesh went to klipcal's own profile.
    let (active, during) = klipper_meshes(&m).await;
    assert_eq!(active, "hot", "the capture left its mesh loaded");
    assert_eq!(
        during["default"], before["default"],
        "the capture's BED_MESH_CALIBRATE overwrote the user's default profile"
    );
    assert!(
        during["klipcal_capture"]["points"].is_array(),
        "{:?}",
        during.as_object().map(|o| o.keys().collect::<Vec<_>>())
    );
    extension_request(&files, "klipcal_cancel", json!({}))
        .await
        .unwrap();
    let cancelled = poll(Duration::from_secs(60), || async {
        let s = mesh_session(&bench).await;
        (s["state"] == "cancelled").then_some(s)
    })
    .await
    .expect("the capture was cancelled");
    assert!(cancelled["id"].as_i64().unwrap() > first_id, "{cancelled}");
    // After the cancel: the user's mesh still loaded, the capture profile gone from memory
    // (and from what a SAVE_CONFIG would write), `default` as before.
    let after = poll(Duration::from_secs(120), || async {
        let (active, profiles) = klipper_meshes(&m).await;
        profiles["klipcal_capture"]
            .is_null()
            .then_some((active, profiles))
    })
    .await
    .unwrap_or_else(|| panic!("klipcal_capture still in Klipper\n{}", d.log_text()));
    assert_eq!(after.0, "hot");
    assert_eq!(after.1["default"], before["default"]);

    // The bench's file-output klippy counts as busy ("Printing") after any move until it
    // restarts, and the follower never loads while Klipper is busy: restart it.
    bench.restart_klippy().await;
    // The cancelled session 2 wrote nothing: session 1's profiles rule for FOLLOW and CHECK.
    let r = extension_request(&files, "klipcal_mesh_follow", json!({"enable": "1"}))
        .await
        .unwrap_or_else(|e| panic!("follow after a cancelled re-capture: {e}"));
    assert_eq!(r["session"], json!(first_id), "{r}");
    let loaded = poll(Duration::from_secs(30), || async {
        let (active, _) = klipper_meshes(&m).await;
        active.starts_with("klipcal_").then_some(active)
    })
    .await;
    assert!(
        loaded.is_some(),
        "no klipcal profile loaded: {}\n{}",
        mesh_session(&bench).await["follow"],
        d.log_text()
    );
    extension_request(&files, "klipcal_mesh_follow", json!({"enable": "0"}))
        .await
        .unwrap();
    // The check runs against session 1's model (its verdict depends on the bench's surface,
    // which VGB's made-up profiles do not match: only the refusal to run is a failure).
    let check = extension_request(&files, "klipcal_mesh_check", json!({})).await;
    let text = match &check {
        Ok(v) => v["message"].as_str().unwrap_or("").to_string(),
        Err(e) => e.clone(),
    };
    assert!(
        text.contains("check passed") || text.contains("from the model"),
        "{text}"
    );
    drop(d);
}

/// The command and response rows Moonraker's console store holds (what a reloaded Mainsail or
/// Fluidd lists), after `from` rows.
async fn console_since(m: &klipcal::moonraker::Moonraker, from: usize) -> Vec<(String, String)> {
    crate::mainsail::history(m).await.split_off(from)
}

#[tokio::test]
async fn a_capture_from_the_macro_says_what_a_user_needs_and_nothing_about_printing() {
    // Issue 26 A.7 and B.7, through the macros as a user runs them.
    let bench = Bench::start_args("corexy", &["--variant", "mesh", "--plant-json", PLANT]);
    let d = Daemon::ready(&bench, &mesh_settings()).await;
    let (m, _c) = bench.client(json!({}));
    m.wait_connected(Duration::from_secs(30)).await.unwrap();

    // BED=0 on a cold bed: nothing warms the frame, and the start says so (it used to take
    // three meshes at the same frame temperature and then fail on "meshes span 25.00..25.00").
    let from = crate::mainsail::history(&m).await.len();
    m.gcode("KLIPCAL_MESH_CAPTURE BED=0").await.unwrap();
    let started = poll(Duration::from_secs(20), || async {
        let rows = console_since(&m, from).await;
        rows.iter()
            .any(|(_, t)| t.contains("thermal mesh capture started"))
            .then_some(rows)
    })
    .await
    .unwrap_or_else(|| panic!("no start answer\n{}", d.log_text()));
    let said: Vec<&String> = started
        .iter()
        .filter(|(k, _)| k == "response")
        .map(|(_, t)| t)
        .collect();
    assert!(
        said.iter()
            .any(|t| t.contains("BED=0") && t.contains("frame") && t.contains("not warm")),
        "no warning that the frame cannot warm: {said:#?}"
    );
    m.gcode("KLIPCAL_CANCEL").await.unwrap();
    poll(Duration::from_secs(60), || async {
        (mesh_session(&bench).await["state"] == "cancelled").then_some(())
    })
    .await
    .expect("the BED=0 capture was cancelled");

    // A heated capture: the bed's target is sent once, and its soak lines say nothing of a
    // print (nothing prints during a capture).
    let from = crate::mainsail::history(&m).await.len();
    m.gcode("KLIPCAL_MESH_CAPTURE").await.unwrap();
    let taken = poll(Duration::from_secs(600), || async {
        let s = mesh_session(&bench).await;
        (s["meshes"].as_u64().unwrap_or(0) >= 1 || s["state"] == "failed").then_some(s)
    })
    .await
    .unwrap_or_else(|| panic!("no capture mesh\n{}", d.log_text()));
    assert_eq!(taken["state"], "capturing", "{taken}");
    let rows = console_since(&m, from).await;
    let heater: Vec<&String> = rows
        .iter()
        .filter(|(k, t)| k == "command" && t.contains("SET_HEATER_TEMPERATURE"))
        .map(|(_, t)| t)
        .collect();
    assert_eq!(heater.len(), 1, "the bed's target sent {heater:#?}");
    let printing: Vec<&String> = rows
        .iter()
        .filter(|(k, t)| {
            k == "response"
                && t.contains("thermal mesh")
                && (t.contains("print now")
                    || t.contains("prints now")
                    || t.contains("printing")
                    || t.contains("CHOICE=print"))
        })
        .map(|(_, t)| t)
        .collect();
    assert!(
        printing.is_empty(),
        "a capture's lines speak of printing: {printing:#?}"
    );
    // Issue 38 item 9: soak.frame is not set in these settings, and the capture's soak asks
    // the same question as an A/B round's, with the same buttons (its dialog alone since
    // issue 40 item 6).
    assert!(
        rows.iter().any(|(k, t)| k == "response"
            && t.contains("prompt_begin klipcal: is the printer enclosed?")),
        "the capture's soak did not ask: {rows:#?}"
    );
    assert!(
        rows.iter().any(|(k, t)| k == "response"
            && t.contains("prompt_button Open, no enclosure|KLIPCAL_SOAK_BED FRAME=open")),
        "no dialog button: {rows:#?}"
    );
    m.gcode("KLIPCAL_CANCEL").await.unwrap();
    poll(Duration::from_secs(60), || async {
        (mesh_session(&bench).await["state"] == "cancelled").then_some(())
    })
    .await
    .expect("the capture was cancelled");
    drop(d);
}
