//! The sign of the skew correction on the real Klipper (issue 4 §2): after the SET_SKEW the
//! solver prints, Klipper's toolhead position for a commanded G1 X100 Y100 moves the way the
//! model (`calib::skew::klipper_toolhead_xy`) says.

use std::time::Duration;

use klipcal::calib::skew::{klipper_toolhead_xy, set_skew_command, xy_factor_from_positions};
use serde_json::json;

use crate::bench::Bench;

#[tokio::test]
async fn klipper_moves_the_toolhead_the_way_the_skew_model_predicts() {
    let bench = Bench::start("corexy");
    let (m, _c) = bench.client(json!({}));
    m.wait_connected(Duration::from_secs(30)).await.unwrap();
    m.gcode("G28\nG90").await.unwrap();
    for xy in [0.01, -0.02] {
        let cmd = set_skew_command(xy).unwrap();
        m.gcode(&cmd).await.unwrap();
        // Klipper applies a new factor to moves issued after SET_SKEW.
        m.gcode("G1 X50 Y50 F6000\nG1 X100 Y100 F6000\nM400")
            .await
            .unwrap();
        let st = m
            .objects_query(json!({"toolhead": ["position"]}))
            .await
            .unwrap();
        let pos = &st["toolhead"]["position"];
        let got = [pos[0].as_f64().unwrap(), pos[1].as_f64().unwrap()];
        let want = klipper_toolhead_xy([100.0, 100.0], xy);
        assert!(
            (got[0] - want[0]).abs() < 1e-3 && (got[1] - want[1]).abs() < 1e-3,
            "{cmd}: Klipper {got:?}, model {want:?}"
        );
        // The shift is real, not zero: X moves by −y·xy.
        assert!((got[0] - 100.0).abs() > 0.5, "{got:?}");
    }
    m.gcode("SET_SKEW CLEAR=1").await.unwrap();
}

/// Klipper's XY skew factor as klipcal reads it without GET_CURRENT_SKEW, at Z = 0.
async fn factor_at_z0(m: &klipcal::moonraker::Moonraker) -> Option<f64> {
    m.gcode("G90\nG1 X100 Y120 Z0 F6000\nM400").await.unwrap();
    let st = m
        .objects_query(json!({"gcode_move": ["position"], "toolhead": ["position"]}))
        .await
        .unwrap();
    let xyz = |v: &serde_json::Value| [0, 1, 2].map(|i| v[i].as_f64().unwrap());
    xy_factor_from_positions(
        xyz(&st["gcode_move"]["position"]),
        xyz(&st["toolhead"]["position"]),
    )
}

#[tokio::test]
async fn a_session_reads_and_restores_the_skew_without_klippers_answer_on_the_console() {
    // Issue 26 A.7: GET_CURRENT_SKEW's four lines leaked into the console at every start.
    let bench = Bench::start("corexy");
    let d = crate::bench::Daemon::ready(&bench, &crate::session::settings(600.0)).await;
    let (m, _c) = bench.client(json!({}));
    m.wait_connected(Duration::from_secs(30)).await.unwrap();
    let xy = 0.004;
    m.gcode("G28").await.unwrap();
    m.gcode(&set_skew_command(xy).unwrap()).await.unwrap();
    // The positions tell Klipper's factor (what klipcal reads), checked against the factor set.
    let read = factor_at_z0(&m)
        .await
        .expect("the positions tell the factor");
    assert!((read - xy).abs() < 1e-6, "read {read}, set {xy}");

    let from = crate::mainsail::history(&m).await.len();
    m.gcode("KLIPCAL_AB_START BED=0").await.unwrap();
    let s = crate::bench::poll(Duration::from_secs(120), || async {
        let s = crate::session::session(&bench).await;
        matches!(
            s["state"].as_str(),
            Some("printing" | "measuring" | "failed" | "cancelled")
        )
        .then_some(s)
    })
    .await
    .unwrap_or_else(|| panic!("the session never printed\n{}", d.log_text()));
    assert_eq!(s["state"], "printing", "{s}\n{}", d.log_text());
    let h = crate::mainsail::history(&m).await.split_off(from);
    let leaked: Vec<&(String, String)> = h
        .iter()
        .filter(|(_, t)| t.contains("GET_CURRENT_SKEW") || t.contains("Current Printer Skew"))
        .collect();
    assert!(leaked.is_empty(), "{leaked:#?}");
    // The factor was read: the session says it cleared it for the calibration print.
    assert!(
        h.iter()
            .any(|(_, t)| t.contains("skew correction (XY factor 0.004000) cleared")),
        "{h:#?}"
    );

    // Cancelled, the session puts the user's skew back.
    let at_cancel = crate::mainsail::history(&m).await.len();
    m.gcode("KLIPCAL_CANCEL").await.unwrap();
    crate::bench::poll(Duration::from_secs(60), || async {
        (crate::session::session(&bench).await["state"] == "cancelled").then_some(())
    })
    .await
    .expect("cancelled");
    let back = crate::bench::poll(Duration::from_secs(30), || async {
        let st = m
            .objects_query(json!({"print_stats": ["state"]}))
            .await
            .ok()?;
        (st["print_stats"]["state"] != "printing").then_some(())
    })
    .await;
    assert!(back.is_some());
    let restored = factor_at_z0(&m)
        .await
        .expect("the positions tell the factor");
    assert!(
        (restored - xy).abs() < 1e-6,
        "restored {restored}, was {xy}"
    );
    // A cancel closes the dialog once: Calibrations::cancel closes it after the calibration's
    // own cancel, which no longer closes it too.
    let h = crate::mainsail::history(&m).await.split_off(at_cancel);
    let ends = h
        .iter()
        .filter(|(k, msg)| k == "response" && msg == "// action:prompt_end")
        .count();
    assert_eq!(ends, 1, "{h:#?}");
    drop(d);
}
