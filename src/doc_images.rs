//! The pictures of docs/images that klipcal's own drawing code makes: the pylon layout (the
//! diagram the measuring step uploads) and the soak plot (the page's, on a real printer's bed
//! trace). With `KLIPCAL_DOC_IMAGES=1` (scripts/doc-images.sh) the test writes them; without it,
//! it draws them and checks that what is committed is there and no bigger than the docs allow.
//! The browser tests write the screenshots the same way (tests/it/browser.rs, `doc_image`).

use std::path::{Path, PathBuf};

use crate::calib::mesh::{self, Capture, ModelKind, Phase};
use crate::calib::soak::{SoakDetector, SoakParams, SoakStatus};
use crate::gcode::{self, Kinematics, Machine, Options};
use plotters::prelude::*;

use crate::plots::{self, BedSample, DecayCurve};

const BLUE_: RGBColor = RGBColor(0x1c, 0x7e, 0xd6);
const RED_: RGBColor = RGBColor(0xd9, 0x48, 0x0f);
const GREY: RGBColor = RGBColor(0x86, 0x8e, 0x96);

/// The largest picture in docs/images, bytes (the docs test checks the same).
const IMAGE_BYTES_MAX: usize = 150 * 1024;

/// The checkout's root: the folder above this crate that holds docs/.
fn repo_root() -> PathBuf {
    let mut dir = PathBuf::from(env!("CARGO_MANIFEST_DIR"));
    while !dir.join("docs").is_dir() {
        assert!(dir.pop(), "no docs/ above {}", env!("CARGO_MANIFEST_DIR"));
    }
    dir
}

/// A file somewhere under `root` (not in target/ or .git), by name.
fn find(root: &Path, name: &str) -> Option<PathBuf> {
    for e in std::fs::read_dir(root).ok()?.flatten() {
        let p = e.path();
        let file = e.file_name();
        if file == name {
            return Some(p);
        }
        let skip = [".git", "target", ".bench", "docs"];
        if p.is_dir() && !skip.iter().any(|s| file == *s) {
            if let Some(found) = find(&p, name) {
                return Some(found);
            }
        }
    }
    None
}

/// The pylon layout of the paper's procedure on a 300 mm CoreXY, as the measuring step shows
/// it: where each pair's calipers go.
fn pylons_svg() -> String {
    let machine = Machine::square_bed(Kinematics::CoreXy, 300.0);
    gcode::generate(&machine, &Options::default())
        .expect("the paper's layout fits a 300 mm bed")
        .svg
}

/// A real bed's soak (a CoreXY's klippy.log, heated from cold to 80 °C, in the soak fixtures),
/// replayed through the detector with the default settings, drawn as the page draws it at the
/// moment 20 minutes after the heat-up began: the power's fitted decay and its ETA.
fn soak_svg() -> String {
    let root = repo_root();
    let path = find(&root, "ryszardwpl-vzbot-old-1.csv").expect("the real soak trace fixture");
    let text = std::fs::read_to_string(&path).unwrap();
    let mut det = SoakDetector::new(SoakParams::default());
    det.set_max_power(1.0);
    let mut samples = Vec::new();
    let mut eta = None;
    for line in text.lines().filter(|l| !l.starts_with('#')).skip(1) {
        let v: Vec<f64> = line.split(',').map(|f| f.parse().unwrap()).collect();
        let s = BedSample {
            t_s: v[0],
            power: v[1],
            temp_c: v[2],
            target_c: v[3],
        };
        eta = match det.push(s.t_s, s.power, s.temp_c, s.target_c) {
            SoakStatus::Soaking { eta_s, .. } => eta_s,
            _ => None,
        };
        samples.push(s);
        if s.t_s >= 20.0 * 60.0 {
            break;
        }
    }
    let now = samples.last().unwrap().t_s;
    let fit = det.fit().map(|f| DecayCurve {
        now_s: now,
        tau_s: f.tau_s,
        final_power: f.final_power,
        remaining: f.remaining,
    });
    assert!(fit.is_some(), "no fit 20 min into the real trace");
    plots::soak_svg(&samples, fit, eta, &plots::soak_title(&samples)).unwrap()
}

/// One mesh point of a thermal mesh fit, for the mesh profile plot: the captured meshes'
/// heights at that point, the model, and the profiles written for it.
#[derive(Debug, Clone, PartialEq)]
struct MeshPointPlot {
    /// Each captured mesh at this point: (frame °C, z µm).
    meshes: Vec<(f64, f64)>,
    /// The model over the captured range: (frame °C, z µm), ascending in °C.
    model: Vec<(f64, f64)>,
    /// What the follower loads over the same range: (frame °C, z µm of the nearest profile).
    loaded: Vec<(f64, f64)>,
    /// The profiles' temperatures, °C.
    profiles_c: Vec<f64>,
}

/// The mesh profile plot: how one mesh point moves with the frame temperature (the captured
/// meshes as dots, the model as a line) and the steps of the profiles that cover it, in the
/// style of klipcal's other plots (the page does not show it yet: drawn for the docs only).
///
/// # Errors
/// No meshes or model, or plotters failed.
fn mesh_point_svg(p: &MeshPointPlot, title: &str) -> Result<String, String> {
    let all = || p.meshes.iter().chain(&p.model).chain(&p.loaded);
    if p.meshes.is_empty() || p.model.is_empty() {
        return Err("plot: no meshes yet".into());
    }
    let (x0, x1) = all().fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), q| {
        (a.min(q.0), b.max(q.0))
    });
    let (y0, y1) = all().fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), q| {
        (a.min(q.1), b.max(q.1))
    });
    let pad = ((y1 - y0) * 0.08).max(1.0);
    let mut out = String::new();
    {
        let root = SVGBackend::with_string(&mut out, (720, 360)).into_drawing_area();
        root.fill(&WHITE).map_err(|e| e.to_string())?;
        let mut chart = ChartBuilder::on(&root)
            .caption(title, ("sans-serif", 16))
            .margin(10)
            .x_label_area_size(32)
            .y_label_area_size(52)
            .build_cartesian_2d(x0 - 0.2..x1 + 0.2, y0 - pad..y1 + pad)
            .map_err(|e| e.to_string())?;
        chart
            .configure_mesh()
            .x_desc("frame temperature, °C")
            .y_desc("z, µm")
            .light_line_style(WHITE.mix(0.0))
            .draw()
            .map_err(|e| e.to_string())?;
        chart
            .draw_series(LineSeries::new(p.model.clone(), BLUE_.stroke_width(2)))
            .map_err(|e| e.to_string())?
            .label("model")
            .legend(|(x, y)| PathElement::new(vec![(x, y), (x + 16, y)], BLUE_));
        chart
            .draw_series(LineSeries::new(p.loaded.clone(), RED_.stroke_width(2)))
            .map_err(|e| e.to_string())?
            .label(format!("{} profiles loaded", p.profiles_c.len()))
            .legend(|(x, y)| PathElement::new(vec![(x, y), (x + 16, y)], RED_));
        chart
            .draw_series(p.meshes.iter().map(|q| Circle::new(*q, 4, GREY.filled())))
            .map_err(|e| e.to_string())?
            .label("captured meshes")
            .legend(|(x, y)| Circle::new((x + 8, y), 4, GREY.filled()));
        chart
            .configure_series_labels()
            .position(SeriesLabelPosition::UpperLeft)
            .background_style(WHITE.mix(0.85))
            .border_style(GREY)
            .draw()
            .map_err(|e| e.to_string())?;
        root.present().map_err(|e| e.to_string())?;
    }
    Ok(out)
}

/// A simulated 300 mm gantry warming from 22 to 32 °C (a bow along X of 8 µm per °C in the
/// middle, the figure docs/thermal-mesh.md gives for such a gantry, and 1 µm of probe noise),
/// captured every 0.5 °C on a 5×5 mesh, fitted and covered with profiles by klipcal's own code
/// at the default 5 µm tolerance; the plot shows the middle point.
fn mesh_profiles_svg() -> String {
    let mut rng = fastrand::Rng::with_seed(2);
    let caps: Vec<Capture> = (0..=20)
        .map(|k| {
            let t = 22.0 + 0.5 * f64::from(k);
            let points = (0..25)
                .map(|i| {
                    let x = f64::from(i % 5) / 4.0 * 2.0 - 1.0;
                    let bow = -0.008 * (t - 22.0) * (1.0 - x * x);
                    bow + 0.001 * (rng.f64() * 2.0 - 1.0)
                })
                .collect();
            Capture::uniform(&format!("m{k}"), t, points, Phase::Heating)
        })
        .collect();
    let refs: Vec<&Capture> = caps.iter().collect();
    let fit = mesh::fit(&refs, ModelKind::Linear).unwrap();
    let (lo, hi) = fit.range_c;
    let plan = mesh::plan_profiles(&fit, lo, hi, 5.0).unwrap();
    let mid = 12;
    let um = |mm: f64| mm * 1000.0;
    let grid: Vec<f64> = (0..=400)
        .map(|k| lo + (hi - lo) * f64::from(k) / 400.0)
        .collect();
    let plot = MeshPointPlot {
        meshes: caps
            .iter()
            .map(|c| (c.temps_c[mid], um(c.points_mm[mid])))
            .collect(),
        model: grid
            .iter()
            .map(|&t| (t, um(fit.predict_point(mid, t))))
            .collect(),
        loaded: grid
            .iter()
            .map(|&t| {
                let p = plan.temps_c[mesh::nearest(&plan.temps_c, t)];
                (t, um(fit.predict_point(mid, p)))
            })
            .collect(),
        profiles_c: plan.temps_c.clone(),
    };
    mesh_point_svg(&plot, "the middle mesh point as the frame warms").unwrap()
}

/// A PNG again without its alpha channel (the pictures are drawn on white) at PNG's best
/// compression: about half the size.
fn compact(png: &[u8]) -> Vec<u8> {
    use image::codecs::png::{CompressionType, FilterType, PngEncoder};
    use image::ImageEncoder;
    let rgb = image::load_from_memory(png).unwrap().to_rgb8();
    let mut out = Vec::new();
    PngEncoder::new_with_quality(&mut out, CompressionType::Best, FilterType::Adaptive)
        .write_image(
            rgb.as_raw(),
            rgb.width(),
            rgb.height(),
            image::ExtendedColorType::Rgb8,
        )
        .unwrap();
    out
}

#[test]
fn doc_images() {
    let dir = repo_root().join("docs/images");
    let write = std::env::var("KLIPCAL_DOC_IMAGES").is_ok_and(|v| v == "1");
    for (name, svg, width) in [
        ("pylons.png", pylons_svg(), plots::PNG_WIDTH_PX),
        ("soak.png", soak_svg(), 720),
        ("mesh-profiles.png", mesh_profiles_svg(), 720),
    ] {
        let png = compact(&plots::svg_to_png(&svg, width).unwrap());
        assert!(
            png.len() <= IMAGE_BYTES_MAX,
            "{name}: {} bytes, at most {IMAGE_BYTES_MAX}",
            png.len()
        );
        let path = dir.join(name);
        if write {
            std::fs::create_dir_all(&dir).unwrap();
            std::fs::write(&path, &png).unwrap();
            println!("wrote {} ({} bytes)", path.display(), png.len());
        } else {
            assert!(
                path.exists(),
                "{} is missing: run scripts/doc-images.sh",
                path.display()
            );
        }
    }
}
