//! The thermal bed-mesh commands: `klipcal mesh fit` and `klipcal mesh profiles` read VGB's
//! (`COLDxx.x`/`HOTxx.x`/`TESTxx.x`) and klipcal's profiles from a printer.cfg and run the pure
//! model in [`crate::calib::mesh`]; `klipcal bench mesh` runs it on simulated gantries. Owns the
//! gantry simulator (the same surface formula as the bench's simulated probe); no model logic.
// Their benchmark's simulators are unused in the printer's build (no `bench` feature), where
// the linker drops them; `bench` is only built from a source checkout.
#![cfg_attr(not(feature = "bench"), allow(dead_code, unused_imports))]

use std::process::ExitCode;

use anyhow::{bail, Context};
use rand::rngs::StdRng;
use rand::{Rng, SeedableRng};
use serde_json::{json, Value};

use crate::calib::mesh::{
    self, judge, lomo, plan_profiles, quantisation_um, select, vgb_grid, vgb_lomo, vgb_two_mesh,
    Capture, Fit, Phase,
};
use crate::calib::mesh_follow::{Decision, FollowPolicy, Follower};
use crate::cli::{BenchMeshArgs, MeshFitArgs, MeshProfilesArgs};
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

fn profile_at(fit: &Fit, template: &MeshProfile, t: f64) -> MeshProfile {
    let pts = fit.predict(t).points_mm;
    let xc = template.params.x_count;
    MeshProfile {
        name: format!("klipcal_{t:.2}"),
        params: template.params.clone(),
        points_mm: pts.chunks(xc).map(<[f64]>::to_vec).collect(),
    }
}

/// Size in bytes of the `profiles` part of Klipper's `bed_mesh` status for these profiles.
fn status_json_bytes(profiles: &[MeshProfile]) -> usize {
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

// ------------------------------------------------------------------ simulated gantries

/// One simulated gantry: the surface formula of tests/bench/klippy_extras/klipcal_bench.py.
#[derive(Debug, Clone, Copy)]
struct Surface {
    taco: bool,
    saturating: bool,
    lin_um_per_c: f64,
    quad_um_per_c2: f64,
    max_um: f64,
    sat_c: f64,
}

impl Surface {
    fn z_um(&self, u: f64, v: f64, gantry_c: f64) -> f64 {
        let bed = 30.0 * u - 20.0 * v + 15.0 * (1.3 * u + 0.4).sin() * (1.1 * v - 0.3).cos();
        let d = (gantry_c - 25.0).max(0.0);
        let amp = if self.saturating {
            self.max_um * (1.0 - (-d / self.sat_c).exp())
        } else {
            self.lin_um_per_c * d + self.quad_um_per_c2 * d * d
        };
        let bow = if self.taco {
            -amp * (1.0 - u * u) + 0.1 * amp * u * v
        } else {
            -amp * (1.0 - 0.5 * (u * u + v * v))
        };
        bed + bow
    }
}

/// Gantry + frame thermistor nodes of tests/bench/plant.py, bed plate at `plate_c`.
struct Thermal {
    gantry_c: f64,
    frame_c: f64,
}

impl Thermal {
    fn step(&mut self, dt_s: f64, plate_c: f64) {
        let goal = 25.0 + 0.15 * (plate_c - 25.0);
        self.gantry_c += dt_s * (goal - self.gantry_c) / 3600.0;
        self.frame_c += dt_s * (self.gantry_c - self.frame_c) / 120.0;
    }
}

/// Gaussian noise of σ `sd` (Box–Muller).
fn gauss(rng: &mut StdRng, sd: f64) -> f64 {
    let u1: f64 = rng.random::<f64>().max(1e-300);
    let u2: f64 = rng.random::<f64>();
    sd * (-2.0 * u1.ln()).sqrt() * (std::f64::consts::TAU * u2).cos()
}

const GRID: usize = 7;
const PROBE_S: f64 = 2.5;

/// A heating run with a 7×7 mesh every `step_c` of frame temperature (each point at its own
/// probe moment), then a cooling run.
fn simulate(s: &Surface, rng: &mut StdRng, noise_um: f64, hours: f64, step_c: f64) -> Vec<Capture> {
    let mut th = Thermal {
        gantry_c: 25.0,
        frame_c: 25.0,
    };
    let mut out = Vec::new();
    let mut last_c = f64::NEG_INFINITY;
    let mut t = 0.0;
    let dt = 1.0;
    let end = hours * 3600.0;
    while t < 2.0 * end {
        let heating = t < end;
        let plate = if heating { 100.0 } else { 25.0 };
        if (th.frame_c - last_c).abs() >= step_c {
            last_c = th.frame_c;
            let mut c = Capture {
                name: format!("cap{}", out.len()),
                temps_c: Vec::new(),
                points_mm: Vec::new(),
                phase: if heating {
                    Phase::Heating
                } else {
                    Phase::Cooling
                },
            };
            for j in 0..GRID {
                for i in 0..GRID {
                    // Serpentine order, as bed_mesh probes.
                    let ii = if j % 2 == 0 { i } else { GRID - 1 - i };
                    let (u, v) = (
                        2.0 * ii as f64 / (GRID - 1) as f64 - 1.0,
                        2.0 * j as f64 / (GRID - 1) as f64 - 1.0,
                    );
                    let z = s.z_um(u, v, th.gantry_c) + gauss(rng, noise_um);
                    c.temps_c.push(th.frame_c);
                    c.points_mm.push(z / 1000.0);
                    th.step(PROBE_S, plate);
                    t += PROBE_S;
                }
            }
            // Store row-major (x ascending) like Klipper's probed matrix.
            let mut temps = vec![0.0; GRID * GRID];
            let mut pts = vec![0.0; GRID * GRID];
            for (k, (tc, z)) in c.temps_c.iter().zip(&c.points_mm).enumerate() {
                let (j, i) = (k / GRID, k % GRID);
                let ii = if j % 2 == 0 { i } else { GRID - 1 - i };
                temps[j * GRID + ii] = *tc;
                pts[j * GRID + ii] = *z;
            }
            c.temps_c = temps;
            c.points_mm = pts;
            out.push(c);
        }
        th.step(dt, plate);
        t += dt;
    }
    out
}

fn template() -> MeshProfile {
    MeshProfile {
        name: "t".into(),
        params: bed_mesh::MeshParams {
            x_count: GRID,
            y_count: GRID,
            mesh_x_pps: 2,
            mesh_y_pps: 2,
            algo: "lagrange".into(),
            tension: 0.2,
            min_x: 20.0,
            max_x: 280.0,
            min_y: 20.0,
            max_y: 280.0,
        },
        points_mm: Vec::new(),
    }
}

/// `klipcal bench mesh`: prediction error, profile count and loads on simulated gantries.
///
/// # Errors
/// A simulation that produces unusable captures (a bug).
#[cfg(feature = "bench")]
pub(crate) fn bench(a: &BenchMeshArgs) -> anyhow::Result<ExitCode> {
    let mut rng = StdRng::seed_from_u64(a.seed);
    let gantries = [
        (
            "bowl, quadratic bow",
            Surface {
                taco: false,
                saturating: false,
                lin_um_per_c: 6.0,
                quad_um_per_c2: 0.15,
                max_um: 0.0,
                sat_c: 1.0,
            },
        ),
        (
            "taco, saturating bow",
            Surface {
                taco: true,
                saturating: true,
                lin_um_per_c: 0.0,
                quad_um_per_c2: 0.0,
                max_um: 160.0,
                sat_c: 8.0,
            },
        ),
    ];
    let mut failed = false;
    let mark = |ok: bool| if ok { "ok" } else { "FAILED" };
    println!(
        "bench mesh: 7×7 meshes, probe noise {} µm, heating {} h then cooling; seed {}",
        a.noise_um, a.hours, a.seed
    );
    for (label, s) in gantries {
        let caps = simulate(&s, &mut rng, a.noise_um, a.hours, a.step_c);
        let heat: Vec<&Capture> = caps.iter().filter(|c| c.phase == Phase::Heating).collect();
        let cool: Vec<&Capture> = caps.iter().filter(|c| c.phase == Phase::Cooling).collect();
        let sel = select(&heat)?;
        let chosen = sel
            .models
            .iter()
            .find(|m| m.0 == sel.fit.kind)
            .map(|m| m.1)
            .context("no LOMO")?;
        let vgb = vgb_lomo(&heat).context("no VGB LOMO")?;
        let (lo, hi) = sel.fit.range_c;
        println!(
            "\n{label}: {} heating + {} cooling meshes over {lo:.2}..{hi:.2} °C",
            heat.len(),
            cool.len()
        );
        for (k, st) in &sel.models {
            println!(
                "  LOMO {:<10} max {:5.1} µm  mean {:4.1} µm  rms {:4.1} µm",
                k.name(),
                st.max_um,
                st.mean_um,
                st.rms_um
            );
        }
        let ok = chosen.max_um <= 10.0;
        failed |= !ok;
        println!(
            "  heating prediction ({}): max {:5.1} µm (target ≤ 10) mean {:4.1} µm  | VGB two-mesh same data: max {:5.1} µm mean {:4.1} µm | VGB published: 17.7 max, 4 mean  [{}]",
            sel.fit.kind.name(), chosen.max_um, chosen.mean_um, vgb.max_um, vgb.mean_um, mark(ok)
        );
        if let Some(lin) = lomo(&heat, mesh::ModelKind::Linear) {
            println!(
                "  (klipcal linear with per-point temperatures: max {:.1} µm)",
                lin.max_um
            );
        }
        if !cool.is_empty() {
            // The daemon's choice on the same meshes (calib::mesh::select_directions).
            let d = mesh::select_directions(&caps.iter().collect::<Vec<_>>(), a.tolerance_um)?;
            println!("  directions: {}", d.directions.describe(a.tolerance_um));
        }
        let plan = plan_profiles(&sel.fit, lo, hi, a.tolerance_um)?;
        let grid = vgb_grid(lo, hi, 0.1);
        let vgb_fit = vgb_two_mesh(&heat)?;
        let vgb_q = quantisation_um(&vgb_fit, &grid, lo, hi.min(vgb_fit.range_c.1));
        let ours: Vec<MeshProfile> = plan
            .temps_c
            .iter()
            .map(|&t| profile_at(&sel.fit, &template(), t))
            .collect();
        let theirs: Vec<MeshProfile> = grid
            .iter()
            .map(|&t| profile_at(&vgb_fit, &template(), t))
            .collect();
        let ok = plan.temps_c.len() * 5 <= grid.len();
        failed |= !ok;
        println!(
            "  profiles at {} µm: {} (worst {:.2} µm), status JSON {} B | VGB 0.1 °C: {} (worst {:.2} µm), status JSON {} B | target ≤ 1/5 ({})  [{}]",
            a.tolerance_um, plan.temps_c.len(), plan.max_quantisation_um, status_json_bytes(&ours),
            grid.len(), vgb_q, status_json_bytes(&theirs), grid.len() / 5, mark(ok)
        );
        // A 2-hour print starting at the cold end: frame warms as in the heating run.
        let mut th = Thermal {
            gantry_c: 25.0 + 0.2 * (hi - lo),
            frame_c: lo + 0.2 * (hi - lo),
        };
        let policy = FollowPolicy {
            tolerance_um: a.tolerance_um,
            ..FollowPolicy::default()
        };
        let mut fo = Follower::new(policy, &sel.fit, &plan.temps_c, None);
        let (mut loads, mut worst) = (0usize, 0.0f64);
        for k in 0..7200 {
            th.step(1.0, 100.0);
            let t = f64::from(k);
            let reading = th.frame_c + gauss(&mut rng, 0.05);
            match fo.push(t, reading, false) {
                Decision::Load { .. } => loads += 1,
                Decision::RefuseJump { .. } | Decision::Stopped { .. } => break,
                Decision::Keep { .. } => {}
            }
            let loaded = fo
                .loaded()
                .and_then(|(_, lt)| plan.temps_c.iter().position(|&x| x == lt));
            if let Some(i) = loaded {
                let want = sel.fit.predict(th.frame_c).points_mm;
                worst = worst.max(mesh::max_abs_diff_um(&want, &ours[i].flat_mm()));
            }
        }
        println!(
            "  2-hour print: {loads} profile loads (worst residual {worst:.1} µm) | VGB: 720 loads (one per 10 s)  [{}]",
            mark(loads < 720)
        );
        failed |= loads >= 720;
    }
    Ok(if failed {
        ExitCode::FAILURE
    } else {
        ExitCode::SUCCESS
    })
}
