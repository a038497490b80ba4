//! The sign of the skew correction on the real Klipper (issue 4 §2): after the SET_SKEW the
//! solver prints, Klipper's toolhead position for a commanded G1 X100 Y100 moves the way the
//! model (`calib::skew::klipper_toolhead_xy`) says.

use std::time::Duration;

use klipcal::calib::skew::{klipper_toolhead_xy, set_skew_command};
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
