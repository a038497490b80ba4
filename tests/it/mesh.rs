//! Thermal bed-mesh profiles on the real Klipper (issue 11 §4): profiles written by
//! `klipper::bed_mesh::replace_klipcal_profiles` into the SAVE_CONFIG block load with
//! `BED_MESH_PROFILE LOAD=` after a restart, with exactly the points written; the mesh-variant
//! bench's simulated probe answers PROBE and BED_MESH_CALIBRATE from its surface.

use std::path::Path;
use std::time::Duration;

use klipcal::fsio::FsFiles;
use klipcal::klipper::bed_mesh::{profiles, replace_klipcal_profiles, MeshProfile};
use klipcal::klipper::Config;
use serde_json::json;

use crate::bench::Bench;

#[tokio::test]
async fn profiles_klipcal_writes_load_in_klipper_with_the_points_written() {
    let bench = Bench::start("corexy");
    let cfg_path = Path::new(&bench.run_dir()).join("config/printer.cfg");
    let text = std::fs::read_to_string(&cfg_path).unwrap();
    let cfg = Config::load(&FsFiles, &cfg_path).unwrap();
    let base = profiles(&cfg).unwrap().remove(0);
    let mk = |name: &str, dz: f64| MeshProfile {
        name: name.into(),
        params: base.params.clone(),
        points_mm: base
            .points_mm
            .iter()
            .map(|r| r.iter().map(|z| z - dz).collect())
            .collect(),
    };
    let mine = [mk("klipcal_30.00", 0.0123456), mk("klipcal_33.50", 0.0312)];
    let out = replace_klipcal_profiles(&text, &mine).unwrap();
    std::fs::write(&cfg_path, &out).unwrap();
    bench.stop_one("klippy");
    bench.start_one("klippy");
    let (m, _c) = bench.client(json!({}));
    m.wait_connected(Duration::from_secs(30)).await.unwrap();
    for p in &mine {
        m.gcode(&format!("BED_MESH_PROFILE LOAD={}", p.name))
            .await
            .unwrap_or_else(|e| panic!("Klipper refused {}: {e}", p.name));
        let st = m
            .objects_query(json!({"bed_mesh": ["profile_name", "probed_matrix"]}))
            .await
            .unwrap();
        assert_eq!(st["bed_mesh"]["profile_name"], p.name.as_str());
        let got: Vec<Vec<f64>> =
            serde_json::from_value(st["bed_mesh"]["probed_matrix"].clone()).unwrap();
        // Same shape first: a zip over an empty or shorter matrix would compare nothing.
        assert!(!p.points_mm.is_empty(), "{}: nothing written", p.name);
        assert_eq!(
            got.iter().map(Vec::len).collect::<Vec<_>>(),
            p.points_mm.iter().map(Vec::len).collect::<Vec<_>>(),
            "{}: Klipper's matrix has another shape than the one written",
            p.name
        );
        for (gr, wr) in got.iter().zip(&p.points_mm) {
            for (g, w) in gr.iter().zip(wr) {
                assert!((g - w).abs() < 6e-7, "{}: Klipper {g}, written {w}", p.name);
            }
        }
    }
    // The user's profiles are still there.
    m.gcode("BED_MESH_PROFILE LOAD=hot").await.unwrap();
}
