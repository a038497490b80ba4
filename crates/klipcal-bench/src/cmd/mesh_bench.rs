//! `klipcal-bench mesh`: the thermal mesh model on simulated gantries (prediction error, profile
//! count and loads). Owns the gantry simulator (the same surface formula as the bench's
//! simulated probe); the model is [`crate::calib::mesh`], the profiles made as `klipcal mesh`
//! makes them.

use std::process::ExitCode;

use anyhow::Context;

use rand::rngs::StdRng;
use rand::{Rng, SeedableRng};

use crate::calib::mesh::{
    self, lomo, plan_profiles, quantisation_um, select, vgb_grid, vgb_lomo, vgb_two_mesh, Capture,
    Phase,
};
use crate::calib::mesh_follow::{Decision, FollowPolicy, Follower};
use crate::cli::BenchMeshArgs;
use crate::klipper::bed_mesh::{self, MeshProfile};
use klipcal::cmd::mesh::{profile_at, status_json_bytes};

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
    println!(
        "bench mesh: 7×7 meshes, probe noise {} µm, heating {} h then cooling; seed {}",
        a.noise_um, a.hours, a.seed
    );
    for (label, s) in gantries {
        failed |= !gantry(label, &s, a, &mut rng)?;
    }
    Ok(if failed {
        ExitCode::FAILURE
    } else {
        ExitCode::SUCCESS
    })
}

/// One simulated gantry: the heating prediction against VGB's two meshes, the profiles against
/// VGB's 0.1 °C grid, and a 2-hour print followed. Returns whether every target was met.
fn gantry(label: &str, s: &Surface, a: &BenchMeshArgs, rng: &mut StdRng) -> anyhow::Result<bool> {
    let mut failed = false;
    let mark = |ok: bool| if ok { "ok" } else { "FAILED" };
    let caps = simulate(s, rng, a.noise_um, a.hours, a.step_c);
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
    let (loads, worst) = follow_print(&sel.fit, &plan.temps_c, &ours, a.tolerance_um, rng);
    println!(
        "  2-hour print: {loads} profile loads (worst residual {worst:.1} µm) | VGB: 720 loads (one per 10 s)  [{}]",
        mark(loads < 720)
    );
    failed |= loads >= 720;
    Ok(!failed)
}

/// A 2-hour print starting at the cold end of the fit's range, the frame warming as in the
/// heating run, followed with the profiles at `temps_c` (`ours`). Returns the profile loads
/// and the worst residual of the profile loaded, µm.
fn follow_print(
    fit: &mesh::Fit,
    temps_c: &[f64],
    ours: &[MeshProfile],
    tolerance_um: f64,
    rng: &mut StdRng,
) -> (usize, f64) {
    let (lo, hi) = fit.range_c;
    let mut th = Thermal {
        gantry_c: 25.0 + 0.2 * (hi - lo),
        frame_c: lo + 0.2 * (hi - lo),
    };
    let policy = FollowPolicy {
        tolerance_um,
        ..FollowPolicy::default()
    };
    let mut fo = Follower::new(policy, fit, temps_c, None);
    let (mut loads, mut worst) = (0usize, 0.0f64);
    for k in 0..7200 {
        th.step(1.0, 100.0);
        let t = f64::from(k);
        let reading = th.frame_c + gauss(rng, 0.05);
        match fo.push(t, reading, false) {
            Decision::Load { .. } => loads += 1,
            Decision::RefuseJump { .. } | Decision::Stopped { .. } => break,
            Decision::Keep { .. } => {}
        }
        let loaded = fo
            .loaded()
            .and_then(|(_, lt)| temps_c.iter().position(|&x| x == lt));
        if let Some(i) = loaded {
            let want = fit.predict(th.frame_c).points_mm;
            worst = worst.max(mesh::max_abs_diff_um(&want, &ours[i].flat_mm()));
        }
    }
    (loads, worst)
}
