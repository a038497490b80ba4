//! The pylon job through the real Klipper host (issue 3): every fixture's job runs through
//! klippy in batch mode with no error and no out-of-range move; uploaded through the bench's
//! Moonraker, its metadata parses and it prints to completion with every pylon listed by
//! exclude_object.

use std::process::Command;
use std::time::Duration;

use klipcal::gcode::{generate, Error, Job, Kinematics, LayoutKind, Machine, Options};
use serde_json::{json, Value};

use crate::bench::{klipcal_ok, poll, repo, Bench};

fn machine(kinematics: Kinematics, size_mm: f64) -> Machine {
    Machine {
        z_max_mm: Some(size_mm.min(250.0)),
        max_velocity_mm_s: Some(300.0),
        max_accel_mm_s2: Some(3000.0),
        ..Machine::square_bed(kinematics, size_mm)
    }
}

/// The job for a fixture, with the generator's suggested D2 when the default does not fit;
/// `None` when the layout cannot fit at all.
fn job(m: &Machine, layout: LayoutKind) -> Option<Job> {
    let o = Options {
        layout,
        generated_at_unix_s: 0,
        ..Options::default()
    };
    match generate(m, &o) {
        Ok(j) => Some(j),
        Err(Error::DoesNotFit {
            suggested_d2_mm: Some(d2),
            ..
        }) => Some(generate(m, &Options { d2_mm: d2, ..o }).expect("suggested D2 fits")),
        Err(Error::DoesNotFit { .. }) => None,
        Err(e) => panic!("{e}"),
    }
}

fn batch(kinematics: &str, size: u32, gcode: &str) -> Value {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("job.gcode");
    std::fs::write(&path, gcode).unwrap();
    let out = Command::new("python3")
        .arg(repo().join("tests/bench/bench.py"))
        .args([
            "batch",
            "--kinematics",
            kinematics,
            "--size",
            &size.to_string(),
        ])
        .arg("--gcode")
        .arg(&path)
        .arg("--work-dir")
        .arg(dir.path().join("work"))
        .output()
        .unwrap();
    let text = String::from_utf8_lossy(&out.stdout);
    let line = text
        .lines()
        .rev()
        .find(|l| l.starts_with('{'))
        .unwrap_or("{}");
    let mut v: Value = serde_json::from_str(line).unwrap_or(json!({}));
    v["exit_ok"] = json!(out.status.success());
    v["stderr"] = json!(String::from_utf8_lossy(&out.stderr));
    v
}

#[test]
fn every_fixture_job_runs_through_klippy_in_batch_mode_without_error() {
    let fixtures = [
        ("corexy", Kinematics::CoreXy, 120),
        ("corexy", Kinematics::CoreXy, 250),
        ("corexy", Kinematics::CoreXy, 300),
        ("corexy", Kinematics::CoreXy, 350),
        ("cartesian", Kinematics::Cartesian, 235),
    ];
    let mut ran = 0;
    for (name, kin, size) in fixtures {
        let m = machine(kin, f64::from(size));
        for layout in [LayoutKind::Paper, LayoutKind::Full] {
            let Some(j) = job(&m, layout) else {
                // Only the full layout on the 120 mm bed may be refused.
                assert!(
                    size == 120 && layout == LayoutKind::Full,
                    "{name} {size} {layout:?}"
                );
                continue;
            };
            let v = batch(name, size, &j.gcode);
            assert!(
                v["exit_ok"] == json!(true) && v["ok"] == json!(true),
                "{name} {size} {layout:?}: {v}"
            );
            assert_eq!(v["errors"], json!([]), "{name} {size} {layout:?}");
            ran += 1;
        }
    }
    assert_eq!(ran, 9);
}

#[test]
fn the_batch_check_rejects_an_out_of_range_move() {
    let v = batch("corexy", 250, "G28\nG90\nG1 X400 Y10 F3000\n");
    assert_eq!(v["exit_ok"], json!(false), "{v}");
}

#[tokio::test]
async fn the_job_uploads_with_metadata_and_prints_with_every_pylon_excludable() {
    let bench = Bench::start("corexy");
    let dir = bench.dir.path();
    let (gcode, layout) = (dir.join("pylons.gcode"), dir.join("layout.json"));
    klipcal_ok(
        Command::new(env!("CARGO_BIN_EXE_klipcal"))
            .args([
                "pylons",
                "--printer-cfg",
                bench.info["printer_cfg"].as_str().unwrap(),
            ])
            .arg("--out")
            .arg(&gcode)
            .arg("--layout-out")
            .arg(&layout)
            .args(["--bed-temp", "70", "--nozzle-temp", "230"]),
    );
    let layout: Value = serde_json::from_str(&std::fs::read_to_string(&layout).unwrap()).unwrap();
    let ids: Vec<String> = layout["pylons"]
        .as_array()
        .unwrap()
        .iter()
        .map(|p| p["id"].as_str().unwrap().to_string())
        .collect();
    assert_eq!(ids.len(), 6);

    let files = bench.files();
    files
        .upload(
            "gcodes",
            "klipcal/pylons.gcode",
            std::fs::read(&gcode).unwrap(),
        )
        .await
        .unwrap();
    let meta = poll(Duration::from_secs(20), || async {
        files
            .get("/server/files/metadata?filename=klipcal/pylons.gcode")
            .await
            .ok()
            .filter(|m| m.get("estimated_time").is_some())
    })
    .await
    .expect("metadata");
    assert!(meta["estimated_time"].as_f64().unwrap() > 600.0, "{meta}");
    assert!(meta["filament_total"].as_f64().unwrap() > 1000.0, "{meta}");
    assert_eq!(meta["layer_height"], json!(0.2), "{meta}");
    assert_eq!(meta["first_layer_height"], json!(0.2), "{meta}");
    assert_eq!(meta["object_height"], json!(8.0), "{meta}");
    assert_eq!(meta["first_layer_bed_temp"], json!(70.0), "{meta}");
    assert_eq!(meta["first_layer_extr_temp"], json!(230.0), "{meta}");

    let (m, _c) = bench.client(json!({}));
    m.wait_connected(Duration::from_secs(30)).await.unwrap();
    m.print_start("klipcal/pylons.gcode").await.unwrap();
    let done = poll(Duration::from_secs(120), || async {
        let st = m
            .objects_query(
                json!({"print_stats": ["state"], "exclude_object": ["objects"],
                                  "heater_bed": ["target"], "extruder": ["target"]}),
            )
            .await
            .ok()?;
        (st["print_stats"]["state"] == "complete").then_some(st)
    })
    .await
    .expect("the print did not complete");
    let mut listed: Vec<String> = done["exclude_object"]["objects"]
        .as_array()
        .unwrap()
        .iter()
        .map(|o| o["name"].as_str().unwrap().to_string())
        .collect();
    listed.sort();
    let mut want = ids.clone();
    want.sort();
    assert_eq!(listed, want);
    // Readings are taken on the hot bed: the job leaves the bed on and the nozzle off.
    assert_eq!(done["heater_bed"]["target"], json!(70.0));
    assert_eq!(done["extruder"]["target"], json!(0.0));
}
