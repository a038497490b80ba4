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

/// A printer.cfg whose SAVE_CONFIG block holds `profiles` (name, how far every point sits
/// below the base, mm, and max_x), each a 3×3 mesh.
fn vgb_cfg(profiles: &[(&str, f64, f64)]) -> String {
    let mut text = String::from(
        "[printer]\nkinematics: none\n\n#*# <---------------------- SAVE_CONFIG ---------------------->\n\
         #*# DO NOT EDIT THIS BLOCK OR BELOW. The contents are auto-generated.\n#*#\n",
    );
    for (name, dz, max_x) in profiles {
        let p = MeshProfile {
            name: (*name).into(),
            params: klipcal::klipper::bed_mesh::MeshParams {
                x_count: 3,
                y_count: 3,
                mesh_x_pps: 2,
                mesh_y_pps: 2,
                algo: "lagrange".into(),
                tension: 0.2,
                min_x: 20.0,
                max_x: *max_x,
                min_y: 20.0,
                max_y: 280.0,
            },
            points_mm: (0..3)
                .map(|y| (0..3).map(|x| 0.01 * f64::from(x - y) - dz).collect())
                .collect(),
        };
        text.push_str(&klipcal::klipper::bed_mesh::format_profile(&p));
        text.push_str("#*#\n");
    }
    text
}

fn mesh_fit(cfg: &str) -> std::process::Output {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("printer.cfg");
    std::fs::write(&path, cfg).unwrap();
    std::process::Command::new(env!("CARGO_BIN_EXE_klipcal"))
        .args(["mesh", "fit", "--printer-cfg"])
        .arg(&path)
        .output()
        .unwrap()
}

#[test]
fn mesh_fit_lists_the_profiles_it_ignores_and_words_its_errors_for_the_user() {
    // Issue 26 B.5. HOT36 is a frame temperature (36 °C); cold27.3 is not VGB's case.
    let out = mesh_fit(&vgb_cfg(&[
        ("COLD25.0", 0.0, 280.0),
        ("HOT36", 0.044, 280.0),
        ("cold27.3", 0.01, 280.0),
        ("default", 0.0, 280.0),
    ]));
    let text = String::from_utf8_lossy(&out.stdout);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    assert!(
        text.contains("COLD25.0 at 25.0 °C") && text.contains("HOT36 at 36.0 °C"),
        "{text}"
    );
    assert!(
        text.contains("not used: cold27.3 (VGB's names are upper case: expected COLD27.3)"),
        "{text}"
    );
    assert!(text.contains("not used: default (not a VGB name"), "{text}");

    // Profiles probed with different meshes: the profile, the option and both values.
    let out = mesh_fit(&vgb_cfg(&[
        ("COLD25.0", 0.0, 280.0),
        ("HOT35.0", 0.04, 270.0),
    ]));
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success());
    assert!(
        err.contains("[bed_mesh HOT35.0] has max_x = 270.0 where COLD25.0 has max_x = 280.0"),
        "{err}"
    );
    assert!(
        !err.contains("Moonraker") && !err.contains("MeshParams"),
        "{err}"
    );

    // Too few to fit: the ignored ones are named with why.
    let out = mesh_fit(&vgb_cfg(&[
        ("COLD25.0", 0.0, 280.0),
        ("hot35.0", 0.04, 280.0),
    ]));
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success());
    assert!(
        err.contains("found 1 COLDxx.x/HOTxx.x")
            && err.contains("hot35.0 (VGB's names are upper case: expected HOT35.0)"),
        "{err}"
    );
}
