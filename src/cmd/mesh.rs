//! The thermal bed-mesh commands: `klipcal mesh fit` and `klipcal mesh profiles` read VGB's
//! (`COLDxx.x`/`HOTxx.x`/`TESTxx.x`) and klipcal's profiles from a printer.cfg and run the pure
//! model in [`crate::calib::mesh`] (`klipcal-bench mesh` runs it on simulated gantries); no model
//! logic.

use std::process::ExitCode;

use anyhow::{bail, Context};
use serde_json::{json, Value};

use crate::calib::mesh::{
    self, judge, plan_profiles, select, vgb_grid, vgb_two_mesh, Capture, Fit, Phase,
};
use crate::cli::{MeshFitArgs, MeshProfilesArgs};
use crate::fsio::FsFiles;
use crate::klipper::bed_mesh::{self, MeshProfile, VgbKind};
use crate::klipper::Config;

/// The COLD and HOT meshes and the TEST meshes of a printer.cfg, the profile the others are
/// shaped like, and every other profile with why it is not used.
struct Loaded {
    fitted: Vec<Capture>,
    tests: Vec<(String, f64, Capture)>,
    template: MeshProfile,
    ignored: Vec<(String, String)>,
}

/// `name (why); …` of the profiles not used, or nothing.
fn ignored_words(ignored: &[(String, String)]) -> String {
    ignored
        .iter()
        .map(|(n, why)| format!("{n} ({why})"))
        .collect::<Vec<_>>()
        .join("; ")
}

fn load(path: &std::path::Path) -> anyhow::Result<Loaded> {
    let cfg = Config::load(&FsFiles, path)
        .with_context(|| format!("reading the Klipper config {}", path.display()))?;
    let all =
        bed_mesh::profiles(&cfg).with_context(|| format!("Klipper config {}", path.display()))?;
    let vgb: Vec<(&MeshProfile, VgbKind, f64)> = all
        .iter()
        .filter_map(|p| bed_mesh::vgb_kind(&p.name).map(|(k, t)| (p, k, t)))
        .collect();
    let ignored: Vec<(String, String)> = all
        .iter()
        .filter_map(|p| bed_mesh::vgb_ignored_why(&p.name).map(|why| (p.name.clone(), why)))
        .collect();
    let used: Vec<&MeshProfile> = vgb.iter().map(|v| v.0).collect();
    bed_mesh::check_same_params(&used)
        .with_context(|| format!("Klipper config {}", path.display()))?;
    let mut fitted = Vec::new();
    let mut tests = Vec::new();
    for (p, kind, t) in &vgb {
        let c = Capture::uniform(&p.name, *t, p.flat_mm(), Phase::Heating);
        match kind {
            VgbKind::Test => tests.push((p.name.clone(), *t, c)),
            _ => fitted.push(c),
        }
    }
    if fitted.len() < 2 {
        let others = if ignored.is_empty() {
            String::new()
        } else {
            format!("; not used: {}", ignored_words(&ignored))
        };
        bail!(
            "{}: found {} COLDxx.x/HOTxx.x bed_mesh profiles; expected at least a COLD and a HOT mesh in the SAVE_CONFIG block (e.g. [bed_mesh COLD27.3] and [bed_mesh HOT36.6]){others}",
            path.display(),
            fitted.len()
        );
    }
    Ok(Loaded {
        fitted,
        tests,
        template: used[0].clone(),
        ignored,
    })
}

fn test_json(name: &str, t: f64, s: &mesh::ErrorStats) -> Value {
    json!({"name": name, "temp_c": t, "max_abs_um": s.max_um, "mean_abs_um": s.mean_um, "mse_mm2": s.mse_mm2})
}

/// `klipcal mesh fit`.
///
/// # Errors
/// An unreadable config, or profiles that cannot be fitted.
pub(crate) fn fit_cmd(a: &MeshFitArgs) -> anyhow::Result<ExitCode> {
    let l = load(&a.printer_cfg)?;
    let refs: Vec<&Capture> = l.fitted.iter().collect();
    let sel = select(&refs)?;
    let vgb = vgb_two_mesh(&refs)?;
    let models: Vec<Value> = sel
        .models
        .iter()
        .map(|(k, s)| json!({"name": k.name(), "cv_max_um": s.max_um, "cv_mean_um": s.mean_um, "cv_rms_um": s.rms_um}))
        .collect();
    let tests: Vec<Value> = l
        .tests
        .iter()
        .map(|(n, t, c)| test_json(n, *t, &judge(&sel.fit, c)))
        .collect();
    let vtests: Vec<Value> = l
        .tests
        .iter()
        .map(|(n, t, c)| test_json(n, *t, &judge(&vgb, c)))
        .collect();
    let ignored: Vec<Value> = l
        .ignored
        .iter()
        .map(|(n, why)| json!({"name": n, "why": why}))
        .collect();
    let fitted: Vec<Value> = l
        .fitted
        .iter()
        .map(|c| json!({"name": c.name, "temp_c": c.temps_c.first()}))
        .collect();
    let out = json!({"models": models, "chosen": sel.fit.kind.name(), "tests": tests,
        "vgb_linear": {"tests": vtests}, "range_c": [sel.fit.range_c.0, sel.fit.range_c.1],
        "fitted": fitted, "ignored": ignored});
    if a.json {
        println!("{out}");
    } else {
        println!(
            "{} meshes fitted ({}) over {:.2}..{:.2} °C; model: {}",
            refs.len(),
            l.fitted
                .iter()
                .map(|c| format!(
                    "{} at {:.1} °C",
                    c.name,
                    c.temps_c.first().copied().unwrap_or(f64::NAN)
                ))
                .collect::<Vec<_>>()
                .join(", "),
            sel.fit.range_c.0,
            sel.fit.range_c.1,
            sel.fit.kind.name()
        );
        for (n, why) in &l.ignored {
            println!("  not used: {n} ({why})");
        }
        if sel.models.is_empty() {
            println!("  (leave-one-mesh-out needs a mesh between the coldest and the hottest)");
        }
        for (k, s) in &sel.models {
            println!(
                "  LOMO {:<10} max {:6.1} µm  mean {:5.1} µm  rms {:5.1} µm",
                k.name(),
                s.max_um,
                s.mean_um,
                s.rms_um
            );
        }
        for ((n, t, c), _) in l.tests.iter().zip(&tests) {
            let (k, v) = (judge(&sel.fit, c), judge(&vgb, c));
            println!(
                "  {n} ({t:.1} °C): klipcal max {:.1} µm mean {:.1} µm MSE {:.2e} | VGB linear max {:.1} µm mean {:.1} µm MSE {:.2e}",
                k.max_um, k.mean_um, k.mse_mm2, v.max_um, v.mean_um, v.mse_mm2
            );
        }
    }
    Ok(ExitCode::SUCCESS)
}

pub fn profile_at(fit: &Fit, template: &MeshProfile, t: f64) -> MeshProfile {
    let pts = fit.predict(t).points_mm;
    let xc = template.params.x_count;
    MeshProfile {
        name: format!("klipcal_{t:.2}"),
        params: template.params.clone(),
        points_mm: pts.chunks(xc).map(<[f64]>::to_vec).collect(),
    }
}

/// Size in bytes of the `profiles` part of Klipper's `bed_mesh` status for these profiles.
pub fn status_json_bytes(profiles: &[MeshProfile]) -> usize {
    let mut m = serde_json::Map::new();
    for p in profiles {
        let pm = &p.params;
        m.insert(
            p.name.clone(),
            json!({"points": p.points_mm.iter().map(|r| r.iter().map(|z| (z * 1e6).round() / 1e6).collect::<Vec<_>>()).collect::<Vec<_>>(),
                   "mesh_params": {"min_x": pm.min_x, "max_x": pm.max_x, "min_y": pm.min_y, "max_y": pm.max_y,
                   "x_count": pm.x_count, "y_count": pm.y_count, "mesh_x_pps": pm.mesh_x_pps, "mesh_y_pps": pm.mesh_y_pps,
                   "algo": pm.algo, "tension": pm.tension}}),
        );
    }
    Value::Object(m).to_string().len()
}

/// `klipcal mesh profiles`.
///
/// # Errors
/// An unreadable config, a bad range or tolerance, or an unwritable output file.
pub(crate) fn profiles_cmd(a: &MeshProfilesArgs) -> anyhow::Result<ExitCode> {
    let l = load(&a.printer_cfg)?;
    let refs: Vec<&Capture> = l.fitted.iter().collect();
    let sel = select(&refs)?;
    let (lo, hi) = (
        a.from.unwrap_or(sel.fit.range_c.0),
        a.to.unwrap_or(sel.fit.range_c.1),
    );
    let mut notes = Vec::new();
    if !l.ignored.is_empty() {
        notes.push(format!("not used: {}", ignored_words(&l.ignored)));
    }
    if lo < sel.fit.range_c.0 || hi > sel.fit.range_c.1 {
        notes.push(format!(
            "the range {lo:.2}..{hi:.2} °C goes beyond the captured {:.2}..{:.2} °C: the model is clamped there (no extrapolation) — capture meshes over the range you need",
            sel.fit.range_c.0, sel.fit.range_c.1
        ));
    }
    let plan = plan_profiles(&sel.fit, lo, hi, a.tolerance_um)?;
    let profiles: Vec<MeshProfile> = plan
        .temps_c
        .iter()
        .map(|&t| profile_at(&sel.fit, &l.template, t))
        .collect();
    let mut block = String::new();
    for p in &profiles {
        block.push_str("#*#\n");
        block.push_str(&bed_mesh::format_profile(p));
    }
    std::fs::write(&a.out, &block).with_context(|| format!("writing {}", a.out.display()))?;
    let vgb_count = vgb_grid(lo, hi, 0.1).len();
    if a.json {
        println!(
            "{}",
            json!({"temps_c": plan.temps_c, "count": plan.temps_c.len(), "max_quantisation_um": plan.max_quantisation_um,
                   "vgb_count_at_0_1c": vgb_count, "model": sel.fit.kind.name(), "notes": notes})
        );
    } else {
        println!(
            "{} profiles over {lo:.2}..{hi:.2} °C (VGB's 0.1 °C set: {vgb_count}); worst nearest-profile error {:.2} µm (tolerance {} µm); written to {}",
            plan.temps_c.len(),
            plan.max_quantisation_um,
            a.tolerance_um,
            a.out.display()
        );
        for n in notes {
            println!("  note: {n}");
        }
    }
    Ok(ExitCode::SUCCESS)
}
