//! The daemon's guided backlash session (issue 12) on the bench with the seed branch's module
//! and a simulated play: a test plays the person at the camera (the bench's true nozzle
//! position, a human's sub-pixel noise) and presses the prompt's jog buttons through the
//! remote methods; the daemon is killed (-9) mid-measurement and picks up where it was; the
//! measured backlash matches the simulated one within its uncertainty; apply sets it with
//! SET_BACKLASH_COMPENSATION and writes it into the config.

use std::time::Duration;

use serde_json::{json, Value};

use crate::backlash::{connect, nozzle, set_point};
use crate::bench::{extension_request, Bench, Daemon};

const TRUE_X_MM: f64 = 0.08;

/// One press as a person at the camera would choose it.
fn choose(seen_mm: f64) -> &'static str {
    if seen_mm >= -0.003 {
        "centred"
    } else if seen_mm < -0.12 {
        "coarse"
    } else {
        "fine"
    }
}

#[tokio::test]
async fn a_guided_x_measurement_survives_kill_9_matches_the_play_and_is_applied() {
    let bench = Bench::start_args(
        "cartesian",
        &[
            "--backlash-module",
            "seed",
            "--play",
            &format!(r#"{{"x": {TRUE_X_MM}}}"#),
        ],
    );
    let mut d = Daemon::ready(&bench, "[backlash]\ncycles = 3\n").await;
    let files = bench.files();
    let (m, _c) = connect(&bench).await;
    let point = [100.0, 100.0, 0.0];
    let mark = set_point(&bench, &m, point).await;
    extension_request(&files, "klipcal_backlash_set_point", json!({}))
        .await
        .unwrap();
    // Bad arguments are refused by name.
    let e = extension_request(&files, "klipcal_backlash_start", json!({"axis": "Q"}))
        .await
        .unwrap_err();
    assert!(e.contains('Q'), "{e}");
    let e = extension_request(&files, "klipcal_backlash_jog", json!({"press": "sideways"}))
        .await
        .unwrap_err();
    assert!(
        e.to_lowercase().contains("sideways") || e.contains("no backlash axis"),
        "{e}"
    );

    let r = extension_request(
        &files,
        "klipcal_backlash_start",
        json!({"axis": "X", "cycles": 3}),
    )
    .await
    .unwrap();
    assert_eq!(r["state"], "measuring", "{r}");
    let mut rng = fastrand::Rng::with_seed(7);
    let mut phase = "Plus".to_string();
    let mut presses = 0;
    let mut killed = false;
    let measured: Value = loop {
        // Klipper has finished the move the previous answer asked for.
        tokio::time::sleep(Duration::from_millis(50)).await;
        let dir = if phase == "Plus" { 1.0 } else { -1.0 };
        let noise = (rng.f64() * 2.0 - 1.0) * 0.0015;
        let seen = dir * (nozzle(&bench)[0] - mark[0]) + noise;
        let r = extension_request(
            &files,
            "klipcal_backlash_jog",
            json!({"press": choose(seen)}),
        )
        .await
        .unwrap_or_else(|e| panic!("press {}: {e}\n{}", choose(seen), d.log_text()));
        presses += 1;
        assert!(presses < 400, "the procedure does not converge");
        if r["state"] == "measured" {
            break r;
        }
        phase = r["phase"].as_str().unwrap_or("Plus").to_string();
        if !killed && r["cycle"].as_u64() == Some(2) {
            // kill -9 mid-measurement: every press was saved before the machine moved.
            let _ = d.child.kill();
            let _ = d.child.wait();
            d = Daemon::ready(&bench, "[backlash]\ncycles = 3\n").await;
            killed = true;
        }
    };
    assert!(killed, "the measurement ended before the second cycle");
    let x = &measured["results"]["x"];
    let b = x["backlash_mm"].as_f64().unwrap();
    let u = x["uncertainty_mm"].as_f64().unwrap();
    assert!(
        (b - TRUE_X_MM).abs() <= 3.0 * u + 0.003,
        "measured {b} ± {u}, simulated {TRUE_X_MM}: {measured}"
    );
    assert_eq!(x["cycles"].as_u64(), Some(3), "{measured}");

    // While a print runs, apply is refused and nothing changes.
    files
        .upload(
            "gcodes",
            "other.gcode",
            b"BENCH_SLEEP SECONDS=60\n".to_vec(),
        )
        .await
        .unwrap();
    m.print_start("other.gcode").await.unwrap();
    let printing = crate::bench::poll(Duration::from_secs(30), || async {
        let st = m
            .objects_query(json!({"print_stats": ["state"]}))
            .await
            .ok()?;
        (st["print_stats"]["state"] == "printing").then_some(())
    })
    .await;
    assert!(printing.is_some(), "the other print did not start");
    let e = extension_request(&files, "klipcal_backlash_apply", json!({}))
        .await
        .unwrap_err();
    assert!(e.contains("a print is printing"), "{e}");
    m.gcode("CANCEL_PRINT").await.unwrap();
    let idle = crate::bench::poll(Duration::from_secs(30), || async {
        let st = m
            .objects_query(json!({"print_stats": ["state"]}))
            .await
            .ok()?;
        (st["print_stats"]["state"] != "printing").then_some(())
    })
    .await;
    assert!(idle.is_some());

    // Apply: SET_BACKLASH_COMPENSATION with its reply checked, and the value in the config.
    let r = extension_request(&files, "klipcal_backlash_apply", json!({}))
        .await
        .unwrap_or_else(|e| panic!("apply: {e}\n{}", d.log_text()));
    assert_eq!(r["state"], "done", "{r}");
    let applied = r["values"]["x"].as_f64().unwrap();
    assert!((applied - b).abs() < 1e-3, "{r}");
    let cf = m.configfile().await.unwrap();
    let written = cf["settings"]["backlash_compensation"]["x_backlash"].as_f64();
    assert!(
        written.is_some_and(|w| (w - applied).abs() < 1e-3),
        "config after restart: {}",
        cf["settings"]["backlash_compensation"]
    );
    drop(d);
}
