//! Real printer configs against the bench's klippy: the daemon reads exactly the files Klipper
//! reads; AWD companions; never writing through a symlink out of the config root or into
//! another project's git checkout.

use std::collections::BTreeSet;
use std::time::Duration;

use klipcal::jobs::printer_config::{self, ValueSet};
use klipcal::moonraker::{Files, Moonraker};
use serde_json::json;

use crate::bench::Bench;

const RESTART: Duration = Duration::from_secs(90);

async fn upload(files: &Files, rel: &str, text: &str) {
    files
        .upload("config", rel, text.as_bytes().to_vec())
        .await
        .unwrap_or_else(|e| panic!("upload {rel}: {e}"));
}

async fn download(files: &Files, rel: &str) -> String {
    String::from_utf8(files.download("config", rel).await.unwrap()).unwrap()
}

/// Adds `line` after `[include steppers.cfg]` in the bench's printer.cfg.
async fn add_to_printer_cfg(files: &Files, line: &str) {
    let text = download(files, "printer.cfg").await;
    let new = text.replacen(
        "[include steppers.cfg]\n",
        &format!("[include steppers.cfg]\n{line}\n"),
        1,
    );
    assert_ne!(new, text);
    upload(files, "printer.cfg", &new).await;
}

async fn restart(m: &Moonraker) -> (String, String) {
    printer_config::restart_with(m, "FIRMWARE_RESTART", RESTART)
        .await
        .unwrap()
}

#[tokio::test]
async fn the_daemon_reads_every_file_klippers_includes_match_whatever_the_extension() {
    let bench = Bench::start("corexy");
    let (m, _c) = bench.client(json!({}));
    let files = bench.files();
    m.wait_connected(Duration::from_secs(30)).await.unwrap();
    upload(
        &files,
        "kc_inc/extra.cfg",
        "[gcode_macro KC_FROM_CFG]\ngcode:\n  M117 a\n",
    )
    .await;
    upload(
        &files,
        "kc_inc/extra.cfg.bak",
        "[gcode_macro KC_FROM_BAK]\ngcode:\n  M117 b\n",
    )
    .await;
    add_to_printer_cfg(&files, "[include kc_inc/*]").await;
    let (state, msg) = restart(&m).await;
    assert_eq!(state, "ready", "{msg}");
    let cf = m.configfile().await.unwrap();
    let klipper: BTreeSet<String> = cf.config.keys().cloned().collect();
    assert!(klipper.contains("gcode_macro KC_FROM_BAK"), "{klipper:?}");
    let pc = printer_config::fetch(&m, &files).await.unwrap();
    let ours: BTreeSet<String> = pc
        .config
        .sections()
        .iter()
        .map(|s| s.name.clone())
        .collect();
    assert_eq!(ours, klipper, "klipcal reads the sections Klipper runs");
    // every option too, value for value
    for s in pc.config.sections() {
        for o in &s.options {
            assert_eq!(
                cf.config
                    .get(&s.name)
                    .and_then(|opts| opts.get(&o.key))
                    .map(String::as_str),
                Some(o.value.as_str()),
                "[{}] {}",
                s.name,
                o.key
            );
        }
    }

    // A folder matched by the pattern: Klipper fails, and so does klipcal, naming it.
    upload(&files, "kc_inc/old/x.cfg", "[gcode_macro KC_OLD]\ngcode:\n").await;
    let (state, msg) = restart(&m).await;
    assert_eq!(state, "error", "{msg}");
    assert!(msg.contains("Unable to open config file"), "{msg}");
    assert!(msg.contains("kc_inc/old"), "{msg}");
    let err = printer_config::fetch(&m, &files).await.err().unwrap();
    let err = format!("{err:#}");
    assert!(err.contains("kc_inc/old"), "{err}");
    assert!(err.contains("it is a folder"), "{err}");
}

fn rd(cf: &klipcal::moonraker::ConfigFile, section: &str) -> f64 {
    cf.settings
        .option(section, "rotation_distance")
        .and_then(serde_json::Value::as_f64)
        .unwrap_or_else(|| {
            panic!(
                "no {section} rotation_distance in {:?}",
                cf.settings.section(section)
            )
        })
}

fn set(section: &str, value: &str) -> ValueSet {
    ValueSet {
        section: section.into(),
        key: "rotation_distance".into(),
        value: value.into(),
    }
}

const AWD: &str = "
[stepper_x1]
step_pin: PD0
dir_pin: PD1
enable_pin: !PD2
microsteps: 16
rotation_distance: 40

[stepper_y1]
step_pin: PD4
dir_pin: PD5
enable_pin: !PD6
microsteps: 32
rotation_distance: 20
gear_ratio: 1:2
";

#[tokio::test]
async fn awd_companion_steppers_are_written_and_verified_with_their_axis() {
    let bench = Bench::start("corexy");
    let (m, _c) = bench.client(json!({}));
    let files = bench.files();
    m.wait_connected(Duration::from_secs(30)).await.unwrap();
    let steppers = download(&files, "steppers.cfg").await;
    upload(&files, "steppers.cfg", &format!("{steppers}{AWD}")).await;
    let (state, msg) = restart(&m).await;
    assert_eq!(state, "ready", "{msg}");

    let pc = printer_config::fetch(&m, &files).await.unwrap();
    let values = [set("stepper_x", "40.2"), set("stepper_y", "39.9")];
    let report = printer_config::apply(&m, &files, &pc, &values, "t12a")
        .await
        .unwrap();
    let cf = m.configfile().await.unwrap();
    assert_eq!(rd(&cf, "stepper_x"), 40.2);
    assert_eq!(rd(&cf, "stepper_x1"), 40.2);
    assert_eq!(rd(&cf, "stepper_y"), 39.9);
    // its own value scaled by the same factor: 20 × 39.9 / 40 = 19.95
    assert_eq!(rd(&cf, "stepper_y1"), 19.95);
    assert_eq!(report.changes.len(), 4, "{report:?}");
    assert!(
        report.notes.iter().any(|n| n.contains("[stepper_y1]")),
        "{report:?}"
    );

    // A companion moving 2.5 % differently: refused with the reason, nothing written.
    let now = download(&files, "steppers.cfg").await;
    let odd = now.replacen(
        "[stepper_x1]\nstep_pin: PD0\ndir_pin: PD1\nenable_pin: !PD2\nmicrosteps: 16\nrotation_distance: 40.2",
        "[stepper_x1]\nstep_pin: PD0\ndir_pin: PD1\nenable_pin: !PD2\nmicrosteps: 16\nrotation_distance: 41.2",
        1,
    );
    assert_ne!(odd, now);
    upload(&files, "steppers.cfg", &odd).await;
    let (state, msg) = restart(&m).await;
    assert_eq!(state, "ready", "{msg}");
    let pc = printer_config::fetch(&m, &files).await.unwrap();
    let err = printer_config::apply(&m, &files, &pc, &[set("stepper_x", "40")], "t12b")
        .await
        .err()
        .unwrap();
    let err = format!("{err:#}");
    assert!(err.contains("[stepper_x1] drives the same axis"), "{err}");
    assert!(err.contains("2.5 % apart"), "{err}");
    assert_eq!(download(&files, "steppers.cfg").await, odd);
}

#[tokio::test]
async fn values_in_a_symlinked_or_foreign_checkout_go_to_the_overrides_include() {
    let bench = Bench::start("corexy");
    let (m, _c) = bench.client(json!({}));
    let files = bench.files();
    m.wait_connected(Duration::from_secs(30)).await.unwrap();
    let roots = files.get("/server/files/roots").await.unwrap();
    let root = roots
        .as_array()
        .unwrap()
        .iter()
        .find(|r| r["name"] == "config")
        .and_then(|r| r["path"].as_str())
        .map(std::path::PathBuf::from)
        .unwrap();
    let steppers = download(&files, "steppers.cfg").await;

    // 1. Klippain-style: the steppers live in another project's checkout outside the config
    //    folder, reached through a symlink.
    let outside = bench.dir.path().join("theme-project");
    std::fs::create_dir_all(outside.join("config")).unwrap();
    std::fs::create_dir_all(outside.join(".git")).unwrap();
    std::fs::write(outside.join("config/steppers.cfg"), &steppers).unwrap();
    std::os::unix::fs::symlink(outside.join("config"), root.join("theme")).unwrap();
    let printer = download(&files, "printer.cfg").await;
    let printer = printer.replacen("[include steppers.cfg]", "[include theme/steppers.cfg]", 1);
    upload(&files, "printer.cfg", &printer).await;
    let (state, msg) = restart(&m).await;
    assert_eq!(state, "ready", "{msg}");
    let pc = printer_config::fetch(&m, &files).await.unwrap();
    let report = printer_config::apply(&m, &files, &pc, &[set("stepper_x", "40.2")], "t13a")
        .await
        .unwrap();
    assert_eq!(
        std::fs::read_to_string(outside.join("config/steppers.cfg")).unwrap(),
        steppers,
        "the other project's file is untouched"
    );
    let notes = report.notes.join(" | ");
    assert!(
        notes.contains("symlink that leads out of the config folder"),
        "{notes}"
    );
    assert!(notes.contains("klipcal_overrides.cfg"), "{notes}");
    assert!(
        report.files.contains(&"klipcal_overrides.cfg".to_string()),
        "{report:?}"
    );
    let cf = m.configfile().await.unwrap();
    assert_eq!(rd(&cf, "stepper_x"), 40.2, "Klipper runs the override");
    assert_eq!(rd(&cf, "stepper_y"), 40.0);
    let over = download(&files, "klipcal_overrides.cfg").await;
    assert!(
        over.contains("[stepper_x]\nrotation_distance: 40.2\n"),
        "{over}"
    );
    assert!(download(&files, "printer.cfg")
        .await
        .contains("[include klipcal_overrides.cfg]"));

    // 2. A git checkout inside the config folder (no symlink): also not klipcal's to edit.
    std::fs::create_dir_all(root.join("vendor/.git")).unwrap();
    std::fs::write(root.join("vendor/.git/HEAD"), "ref: refs/heads/main\n").unwrap();
    let vendored = steppers.replacen("[stepper_x]", "[stepper_y]\n[stepper_x]", 0);
    std::fs::write(root.join("vendor/steppers.cfg"), &vendored).unwrap();
    let printer = download(&files, "printer.cfg").await;
    let printer = printer.replacen(
        "[include theme/steppers.cfg]",
        "[include vendor/steppers.cfg]",
        1,
    );
    upload(&files, "printer.cfg", &printer).await;
    let (state, msg) = restart(&m).await;
    assert_eq!(state, "ready", "{msg}");
    let pc = printer_config::fetch(&m, &files).await.unwrap();
    let report = printer_config::apply(&m, &files, &pc, &[set("stepper_y", "39.8")], "t13b")
        .await
        .unwrap();
    assert_eq!(
        std::fs::read_to_string(root.join("vendor/steppers.cfg")).unwrap(),
        vendored
    );
    let notes = report.notes.join(" | ");
    assert!(notes.contains("another project's git checkout"), "{notes}");
    let cf = m.configfile().await.unwrap();
    assert_eq!(rd(&cf, "stepper_y"), 39.8);
    assert_eq!(rd(&cf, "stepper_x"), 40.2, "the earlier override stays");
}
