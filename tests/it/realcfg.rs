//! Real printer configs against the bench's klippy: the daemon reads exactly the files Klipper
//! reads; AWD companions; never writing through a symlink out of the config root or into
//! another project's git checkout.

use std::collections::BTreeSet;
use std::time::Duration;

use klipcal::jobs::printer_config;
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
    let klipper: BTreeSet<String> = cf["config"].as_object().unwrap().keys().cloned().collect();
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
                cf["config"][&s.name][&o.key].as_str(),
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
