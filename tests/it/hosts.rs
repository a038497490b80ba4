//! What differs between the Klipper hosts klipcal runs on (Klipper's 2023 klippy, Kalico 2026),
//! each test run on the host the bench was given (`KLIPCAL_KLIPPY`, tests/run-all.sh runs both):
//! Kalico's default extras, its `idle_timeout: 0`, and its config references, includes and
//! recursive include globs read as Kalico's own loader reads them.

use std::collections::BTreeSet;
use std::time::Duration;

use serde_json::{json, Value};

use crate::bench::{extension_request, on_kalico, Bench, Daemon};
use crate::session::{measure_all, reconfigure, session, settings, wait_state, PLANT};
use klipcal::jobs::printer_config;

const ROUND: Duration = Duration::from_secs(400);

/// The bench's printer.cfg without `[exclude_object]` and `[respond]`.
fn without_default_extras(t: &str) -> String {
    t.replacen("[exclude_object]\n\n[respond]\n\n", "", 1)
}

/// Waits until the session has failed or reached `state`, and returns it.
async fn settled(bench: &Bench, state: &str) -> Value {
    crate::bench::poll(ROUND, || async {
        let s = session(bench).await;
        (s["state"] == state || s["state"] == "failed").then_some(s)
    })
    .await
    .unwrap_or_else(|| panic!("the session never reached {state} nor failed"))
}

/// Measures, solves and applies the round in `measuring`; returns apply's answer or refusal.
async fn solve_and_apply(bench: &Bench, s: &Value) -> Result<Value, String> {
    let files = bench.files();
    measure_all(bench, s["pairs"].as_array().unwrap()).await;
    extension_request(&files, "klipcal_solve", json!({}))
        .await
        .unwrap();
    extension_request(&files, "klipcal_apply", json!({})).await
}

#[tokio::test]
async fn an_ab_round_needs_what_klipper_runs_not_sections_in_its_config() {
    let bench = Bench::start_with("corexy", Some(PLANT));
    let files = bench.files();
    if on_kalico() {
        // Kalico can switch exclude_object off while its section stays: refused, saying so.
        reconfigure(&bench, |t| {
            t.replacen(
                "[exclude_object]\n",
                "[exclude_object]\nenable_exclude_object: False\n",
                1,
            )
        })
        .await;
        let _d = Daemon::ready(&bench, &settings(600.0)).await;
        extension_request(&files, "klipcal_ab_start", json!({"bed": 0}))
            .await
            .unwrap();
        let s = wait_state(&bench, "failed", ROUND).await.to_string();
        assert!(s.contains("enable_exclude_object: False?"), "{s}");
        assert!(!s.contains("[respond]"), "{s}");
    }
    // Neither section: Kalico loads both anyway, Klipper neither.
    reconfigure(&bench, |t| {
        without_default_extras(&t.replacen("enable_exclude_object: False\n", "", 1))
    })
    .await;
    let _d = Daemon::ready(&bench, &settings(600.0)).await;
    extension_request(&files, "klipcal_ab_start", json!({"bed": 0}))
        .await
        .unwrap();
    let s = settled(&bench, "measuring").await;
    if on_kalico() {
        assert_eq!(s["state"], "measuring", "{s}");
    } else {
        let text = s.to_string();
        assert_eq!(s["state"], "failed", "{s}");
        assert!(
            text.contains("[respond]") && text.contains("[exclude_object]"),
            "{s}"
        );
        // With the sections (valid on both hosts) the round runs.
        reconfigure(&bench, |t| {
            t.replacen(
                "[skew_correction]\n",
                "[exclude_object]\n\n[respond]\n\n[skew_correction]\n",
                1,
            )
        })
        .await;
        extension_request(&files, "klipcal_ab_start", json!({"bed": 0}))
            .await
            .unwrap();
    }
    let s = wait_state(&bench, "measuring", ROUND).await;
    let applied = solve_and_apply(&bench, &s).await.unwrap();
    assert!(
        ["applied", "converged"].contains(&applied["state"].as_str().unwrap_or("")),
        "{applied}"
    );
}

/// The last `idle_timeout: Timeout set to X s` on the console, and every console line.
async fn idle_timeout_on_console(bench: &Bench) -> (Option<f64>, Vec<String>) {
    let (m, _c) = bench.client(json!({}));
    m.wait_connected(Duration::from_secs(30)).await.unwrap();
    let lines: Vec<String> = crate::mainsail::history(&m)
        .await
        .into_iter()
        .map(|(_, msg)| msg)
        .collect();
    let last = lines.iter().rev().find_map(|l| {
        l.split("Timeout set to ")
            .nth(1)?
            .split_whitespace()
            .next()?
            .parse()
            .ok()
    });
    (last, lines)
}

#[tokio::test]
async fn the_idle_timeout_after_a_session_is_what_it_was_before() {
    let bench = Bench::start_with("corexy", Some(PLANT));
    // Kalico: 0 means never (the 2023 Klipper refuses 0; the bench's 3600 stays there).
    let configured = if on_kalico() {
        reconfigure(&bench, |t| {
            t.replacen(
                "[idle_timeout]\ntimeout: 3600\n",
                "[idle_timeout]\ntimeout: 0\n",
                1,
            )
        })
        .await;
        0.0
    } else {
        3600.0
    };
    let _d = Daemon::ready(&bench, &settings(600.0)).await;
    let files = bench.files();
    extension_request(&files, "klipcal_ab_start", json!({"bed": 60}))
        .await
        .unwrap();
    // The session holds the bed: Klipper's idle timeout is its bound meanwhile.
    let held = crate::bench::poll(ROUND, || async {
        let (t, _) = idle_timeout_on_console(&bench).await;
        t.filter(|t| *t != configured)
    })
    .await
    .expect("the session set a hold");
    assert!(held <= 3600.0, "hold {held}");
    extension_request(&files, "klipcal_cancel", json!({}))
        .await
        .unwrap();
    let s = wait_state(&bench, "cancelled", Duration::from_secs(60)).await;
    assert_eq!(s["heaters_off"], json!(true), "{s}");
    let restored = crate::bench::poll(Duration::from_secs(30), || async {
        let (t, lines) = idle_timeout_on_console(&bench).await;
        t.filter(|t| *t != held).map(|t| (t, lines))
    })
    .await;
    let (t, lines) = restored.expect("the idle timeout was set again after the session");
    assert!(
        !lines.iter().any(|l| l.contains("TIMEOUT must be above")),
        "{lines:?}"
    );
    if on_kalico() {
        // Never, as `timeout: 0` means: ten years, said on the console.
        assert!(t >= 3.0e8, "restored to {t}");
        assert!(
            lines.iter().any(|l| l.contains("idle timeout back to off")),
            "{lines:?}"
        );
    } else {
        assert_eq!(t, 3600.0);
    }
}

fn value<'a>(c: &'a klipcal::klipper::Config, section: &str, key: &str) -> Option<&'a str> {
    let s = c.sections().iter().find(|s| s.name == section)?;
    s.options
        .iter()
        .find(|o| o.key == key)
        .map(|o| o.value.as_str())
}

async fn upload(files: &klipcal::moonraker::Files, rel: &str, text: &str) {
    files
        .upload("config", rel, text.as_bytes().to_vec())
        .await
        .unwrap_or_else(|e| panic!("upload {rel}: {e}"));
}

#[tokio::test]
async fn the_config_is_read_as_the_running_klipper_reads_it_references_and_all() {
    let bench = Bench::start_with("corexy", Some(PLANT));
    let files = bench.files();
    // A recursive include glob: Kalico follows `**` to any depth, Klipper as one `*`.
    upload(
        &files,
        "kc_inc/top.cfg",
        "[gcode_macro KC_TOP]\ngcode:\n  M117 top\n",
    )
    .await;
    upload(
        &files,
        "kc_inc/sub/mid.cfg",
        "[gcode_macro KC_MID]\ngcode:\n  M117 mid\n",
    )
    .await;
    upload(
        &files,
        "kc_inc/sub/deep/low.cfg",
        "[gcode_macro KC_LOW]\ngcode:\n  M117 low\n",
    )
    .await;
    let mut add = "[include kc_inc/**/*.cfg]\n".to_string();
    if on_kalico() {
        // References (nested, same-section, `:`), and a macro body from a file.
        upload(&files, "kc_macros/hello.gcode", "M117 hello\n").await;
        add.push_str(
            "[constants]\nrd_x: ${rd}\nrd: 40\nbed: 60\n\n\
             [gcode_macro KC_REF]\ndescription: bed ${constants:bed} C\ngcode: !!include kc_macros/hello.gcode\n",
        );
        let path = bench.dir.path().join("config/steppers.cfg");
        let text = std::fs::read_to_string(&path).unwrap();
        let new = text.replacen(
            "rotation_distance: 40\n",
            "rotation_distance: ${constants.rd_x}\n",
            1,
        );
        assert_ne!(new, text);
        std::fs::write(&path, new).unwrap();
    }
    reconfigure(&bench, |t| {
        t.replacen(
            "[include klipcal.cfg]",
            &format!("{add}\n[include klipcal.cfg]"),
            1,
        )
    })
    .await;
    let (m, _c) = bench.client(json!({}));
    m.wait_connected(Duration::from_secs(30)).await.unwrap();
    let cf = m.configfile().await.unwrap();
    let pc = printer_config::fetch(&m, &files).await.unwrap();
    let ours: BTreeSet<String> = pc
        .config
        .sections()
        .iter()
        .map(|s| s.name.clone())
        .collect();
    let klipper: BTreeSet<String> = cf.config.keys().cloned().collect();
    assert_eq!(ours, klipper, "klipcal reads the sections Klipper runs");
    assert!(klipper.contains("gcode_macro KC_MID"), "{klipper:?}");
    assert_eq!(klipper.contains("gcode_macro KC_TOP"), on_kalico());
    assert_eq!(klipper.contains("gcode_macro KC_LOW"), on_kalico());
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
    if !on_kalico() {
        return;
    }
    assert_eq!(
        value(&pc.config, "stepper_x", "rotation_distance"),
        Some("40")
    );
    assert_eq!(
        value(&pc.config, "gcode_macro KC_REF", "description"),
        Some("bed 60 C")
    );
    // An A/B round on it; the apply is refused with where to edit instead, and nothing is
    // written.
    let before = std::fs::read_to_string(bench.dir.path().join("config/steppers.cfg")).unwrap();
    let _d = Daemon::ready(&bench, &settings(600.0)).await;
    extension_request(&files, "klipcal_ab_start", json!({"bed": 0}))
        .await
        .unwrap();
    let s = wait_state(&bench, "measuring", ROUND).await;
    let e = solve_and_apply(&bench, &s).await.unwrap_err();
    assert!(e.contains("'${constants.rd_x}'"), "{e}");
    assert!(
        e.contains("[constants] rd_x: 40 in") && e.contains("printer.cfg line"),
        "{e}"
    );
    assert_eq!(
        std::fs::read_to_string(bench.dir.path().join("config/steppers.cfg")).unwrap(),
        before
    );
    assert_eq!(session(&bench).await["state"], "solved");
}

#[tokio::test]
async fn an_uncalibrated_mpc_bed_is_refused_in_plain_words() {
    if !on_kalico() {
        // `control: mpc` is Kalico's; Klipper 0.12 refuses the config.
        return;
    }
    let bench = Bench::start_with("corexy", Some(PLANT));
    // A bed switched to MPC, never calibrated (no block_heat_capacity & co).
    reconfigure(&bench, |t| {
        let at = t.find("\n[heater_bed]\n").unwrap();
        let (head, tail) = t.split_at(at);
        format!(
            "{head}{}",
            tail.replacen("control: pid\n", "control: mpc\nheater_power: 200\n", 1)
        )
    })
    .await;
    let _d = Daemon::ready(&bench, &settings(600.0)).await;
    extension_request(&bench.files(), "klipcal_ab_start", json!({"bed": 60}))
        .await
        .unwrap();
    let s = wait_state(&bench, "failed", ROUND).await.to_string();
    assert!(s.contains("Kalico will not heat heater_bed"), "{s}");
    assert!(s.contains("MPC_CALIBRATE HEATER=heater_bed"), "{s}");
    assert!(
        !s.contains("Cannot activate"),
        "Kalico's own text is replaced: {s}"
    );
}
