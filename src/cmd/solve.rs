//! `klipcal solve`: reads layout.json, the readings (JSON or CSV) and the Klipper config, runs
//! the pure solver in `calib::solve`, and prints text or JSON. File reading and printing only;
//! no calibration math here.

use std::path::Path;
use std::process::ExitCode;

use anyhow::Context;

use crate::calib::metric::{Kinematics, ShearTo};
use crate::calib::readings::parse_readings;
use crate::calib::skew::SkewClass;
use crate::calib::solve::{solve, MotionFacts, Solution, SolveOptions, StepperFacts};
use crate::cli::{ShearToArg, SolveArgs};
use crate::fsio::FsFiles;
use crate::klipper::{Config, PrinterFacts};
use crate::layout::Layout;

/// The solver's printer facts from Klipper's.
///
/// # Errors
/// Kinematics other than corexy or cartesian.
pub(crate) fn motion_facts(f: &PrinterFacts) -> anyhow::Result<MotionFacts> {
    let kinematics = match &f.kinematics {
        crate::klipper::Kinematics::CoreXy => Kinematics::CoreXy,
        crate::klipper::Kinematics::Cartesian => Kinematics::Cartesian,
        crate::klipper::Kinematics::Other(k) => {
            anyhow::bail!("[printer] kinematics = {k}: expected corexy or cartesian")
        }
    };
    let stepper = |s: &crate::klipper::Stepper| StepperFacts {
        rotation_distance_mm: s.rotation_distance_mm,
        microsteps: s.microsteps,
        full_steps_per_rotation: s.full_steps_per_rotation,
        gear_ratio: s.gear_ratio,
    };
    Ok(MotionFacts {
        kinematics,
        stepper_x: stepper(&f.stepper_x),
        stepper_y: stepper(&f.stepper_y),
    })
}

fn previous_round(path: &Path) -> anyhow::Result<Vec<(String, f64)>> {
    let text = std::fs::read_to_string(path)
        .with_context(|| format!("reading the previous solution {}", path.display()))?;
    let v: serde_json::Value = serde_json::from_str(&text).with_context(|| {
        format!(
            "{}: expected the JSON printed by `klipcal solve --json`",
            path.display()
        )
    })?;
    let groups = v["groups"].as_array().with_context(|| {
        format!(
            "{}: no `groups` array; expected the JSON printed by `klipcal solve --json`",
            path.display()
        )
    })?;
    Ok(groups
        .iter()
        .filter_map(|g| Some((g["group"].as_str()?.to_string(), g["scale"].as_f64()?)))
        .collect())
}

/// Reads the three inputs and solves; the solution's warnings include config notes.
///
/// # Errors
/// Unreadable files, a bad layout, readings or printer config; the message names the file,
/// pair or option and what is expected.
pub(crate) fn load_and_solve(args: &SolveArgs) -> anyhow::Result<Solution> {
    let layout_text = std::fs::read_to_string(&args.layout)
        .with_context(|| format!("reading the layout {}", args.layout.display()))?;
    let layout: Layout = serde_json::from_str(&layout_text).with_context(|| {
        format!(
            "{}: not a layout.json written by `klipcal pylons`",
            args.layout.display()
        )
    })?;
    let readings_text = std::fs::read_to_string(&args.readings)
        .with_context(|| format!("reading the readings {}", args.readings.display()))?;
    let raw = parse_readings(&readings_text)
        .with_context(|| format!("readings {}", args.readings.display()))?;
    let config = Config::load(&FsFiles, &args.printer_cfg)
        .with_context(|| format!("reading the Klipper config {}", args.printer_cfg.display()))?;
    let pf = PrinterFacts::from_config(&config)
        .with_context(|| format!("Klipper config {}", args.printer_cfg.display()))?;
    let facts = motion_facts(&pf)?;
    let mut opts = SolveOptions {
        shear_to: match args.shear_to {
            ShearToArg::Motors => ShearTo::Motors,
            ShearToArg::KlipperSkew => ShearTo::KlipperSkew,
        },
        current_xy_factor: args.current_xy_skew,
        ..SolveOptions::default()
    };
    opts.budget.caliper_precision_3sigma_mm = args.caliper_precision_mm;
    opts.budget.instrument_trueness_mm = args.caliper_trueness_mm;
    opts.budget.temp_band_k = args.bed_temp_band_k;
    if let Some(d) = pf.filament_diameter_mm {
        opts.budget.filament_diameter_mm = d;
    }
    if let Some(p) = &args.previous {
        opts.previous = Some(previous_round(p)?);
    }
    let mut sol = solve(&layout, &raw, &facts, &opts).context("solving")?;
    if pf.has_skew_correction && args.current_xy_skew == 0.0 {
        sol.warnings.push(
            "the config has [skew_correction]: if a skew profile was active during the print, pass its factor with --current-xy-skew (the paper asks for skew correction off while calibrating)".into(),
        );
    }
    Ok(sol)
}

/// Runs `klipcal solve`: prints the solution as text, or as one JSON object with `--json`.
///
/// # Errors
/// See [`load_and_solve`].
pub(crate) fn run(args: &SolveArgs) -> anyhow::Result<ExitCode> {
    let sol = load_and_solve(args)?;
    if args.json {
        println!("{}", serde_json::to_string_pretty(&sol)?);
    } else {
        print!("{}", format_solution(&sol));
    }
    Ok(ExitCode::SUCCESS)
}

/// Human-readable solution.
#[must_use]
pub(crate) fn format_solution(s: &Solution) -> String {
    use std::fmt::Write as _;
    let mut o = String::new();
    let _ = writeln!(
        o,
        "klipcal solve — {}, {} group(s), {} fit (χ² {:.2} on {} dof)",
        s.kinematics.name(),
        s.groups.len(),
        if s.fit.full {
            "full in-plane"
        } else {
            "motor-direction"
        },
        s.fit.chi2,
        s.fit.dof
    );
    write_groups(&mut o, s);
    for (name, st) in [("stepper_x", &s.stepper_x), ("stepper_y", &s.stepper_y)] {
        let _ = writeln!(
            o,
            "[{name}] ({}): rotation_distance {:.4} → {:.4} mm  (scale {:.6} ± {:.6}; steps/mm {:.3} → {:.3})",
            st.direction,
            st.rotation_distance_old,
            st.rotation_distance_new,
            st.scale,
            st.uncertainty,
            st.steps_per_mm_old,
            st.steps_per_mm_new
        );
    }
    write_skew(&mut o, s);
    if let (Some(v), Some(u)) = (s.anisotropy.value, s.anisotropy.uncertainty) {
        let _ = writeln!(
            o,
            "X/Y anisotropy: {:+.4} % ± {:.4} %{}{}",
            v * 100.0,
            u * 100.0,
            if s.anisotropy.significant {
                " (significant)"
            } else {
                ""
            },
            if s.anisotropy.left_after_correction {
                ", not corrected by A/B"
            } else {
                ""
            }
        );
    }
    let b = &s.error_budget;
    let _ = writeln!(
        o,
        "error budget: ε_bed {:.1} µm + ε_filament {:.1} µm + ε_measurement {:.1} µm + ε_motor {:.2} µm = ε_max {:.1} µm; precision {:.2e} ({:.0} µm/100 mm), accuracy {:.3} %",
        b.bed_mm * 1e3,
        b.filament_mm * 1e3,
        b.measurement_mm * 1e3,
        b.motor_mm * 1e3,
        b.max_mm * 1e3,
        b.precision,
        b.precision * 1e5,
        b.accuracy * 100.0
    );
    let _ = writeln!(
        o,
        "converged: {}",
        if s.converged {
            "yes — keep these values"
        } else {
            "no — apply the new values and print again"
        }
    );
    for w in &s.warnings {
        let _ = writeln!(o, "warning: {w}");
    }
    o
}

/// A line per group: its scale, the fitted one and its pairs' centres.
fn write_groups(o: &mut String, s: &Solution) {
    use std::fmt::Write as _;
    for g in &s.groups {
        let pairs: Vec<String> = g
            .pairs
            .iter()
            .map(|p| format!("{} {:.3} mm", p.pair, p.centre_mm))
            .collect();
        let _ = writeln!(
            o,
            "  group {:<3} {:>+6.1}°  α {:.6} ± {:.6}  fitted {:.6}{}  ({})",
            g.group,
            g.direction_deg,
            g.scale,
            g.uncertainty,
            g.fitted,
            if g.flagged { "  FLAGGED" } else { "" },
            pairs.join(", ")
        );
    }
}

/// The skew: measured, and the command that sets it or why it is left off.
fn write_skew(o: &mut String, s: &Solution) {
    use std::fmt::Write as _;
    let sk = &s.skew;
    if !sk.observed {
        let _ = writeln!(
            o,
            "skew: not observed by this layout{}",
            if s.kinematics == Kinematics::CoreXy {
                " (on a CoreXY the A/B correction removes the shear anyway)"
            } else {
                " (print the `full` layout to fit it)"
            }
        );
    } else {
        let _ = writeln!(
            o,
            "skew: measured shear {:+.3}° ± {:.3}° ({} by Prusa's thresholds 0.12°/0.25°)",
            sk.measured_shear_deg.unwrap_or(0.0),
            sk.measured_shear_uncertainty_deg.unwrap_or(0.0),
            match sk.class {
                Some(SkewClass::Extreme) => "extreme",
                Some(SkewClass::Mild) => "mild",
                _ => "perfect",
            }
        );
        match &sk.set_skew {
            Some(cmd) => {
                let _ = writeln!(
                    o,
                    "  set: {cmd}   (xy factor {:.6} ± {:.6}, {:+.3}°), then SKEW_PROFILE SAVE=… and SAVE_CONFIG",
                    sk.xy_factor.unwrap_or(0.0),
                    sk.uncertainty.unwrap_or(0.0),
                    sk.angle_deg.unwrap_or(0.0)
                );
            }
            None => {
                let _ = writeln!(
                    o,
                    "  absorbed by the A/B rotation distances: leave skew correction off"
                );
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::calib::sim::simulated_layout;

    const STEPPERS: &str = "[stepper_x]\nstep_pin: PB0\ndir_pin: PB1\nenable_pin: !PB2\nmicrosteps: 64\nrotation_distance: 40\nfull_steps_per_rotation: 400\nendstop_pin: PB3\nposition_endstop: 300\nposition_max: 300\n[stepper_y]\nstep_pin: PC0\ndir_pin: PC1\nenable_pin: !PC2\nmicrosteps: 32\nrotation_distance: 40\nendstop_pin: PC3\nposition_endstop: 300\nposition_max: 300\n";

    fn args(dir: &Path, readings: &str) -> SolveArgs {
        SolveArgs {
            layout: dir.join("layout.json"),
            readings: dir.join(readings),
            printer_cfg: dir.join("printer.cfg"),
            json: false,
            shear_to: ShearToArg::Motors,
            current_xy_skew: 0.0,
            previous: None,
            caliper_precision_mm: 0.02,
            caliper_trueness_mm: 0.02,
            bed_temp_band_k: 2.0,
        }
    }

    fn write_inputs(dir: &Path) {
        let layout = simulated_layout(Kinematics::CoreXy, false, 10.0, 150.0);
        let w = |name: &str, text: &str| std::fs::write(dir.join(name), text).expect("write");
        w(
            "layout.json",
            &serde_json::to_string(&layout).expect("json"),
        );
        w("printer.cfg", "[include steppers/*.cfg]\n[printer]\nkinematics: corexy\nmax_velocity: 300\nmax_accel: 3000\n");
        std::fs::create_dir(dir.join("steppers")).expect("mkdir");
        w("steppers/xy.cfg", STEPPERS);
        let mut csv = String::from("pair,reading\n");
        for (pair, d) in [
            ("A-D1", 10.05),
            ("A-D2", 150.61),
            ("B-D1", 10.04),
            ("B-D2", 149.62),
        ] {
            for delta in [0.0, 0.01, -0.01, 0.0, 0.005] {
                csv.push_str(&format!("{pair},{:.3}\n", d + delta));
            }
        }
        w("readings.csv", &csv);
    }

    #[test]
    fn csv_readings_and_an_included_stepper_config_solve_end_to_end() {
        let dir = tempfile::tempdir().expect("tempdir");
        write_inputs(dir.path());
        let sol = load_and_solve(&args(dir.path(), "readings.csv")).expect("solves");
        assert!((sol.stepper_x.scale - 140.56 / 140.0).abs() < 1e-9);
        assert!((sol.stepper_x.rotation_distance_new - 40.0 * 140.56 / 140.0).abs() < 1e-7);
        // stepper_y: 200 full steps (default) × 32 microsteps / 40 mm
        assert!((sol.stepper_y.steps_per_mm_old - 160.0).abs() < 1e-9);
        let text = format_solution(&sol);
        assert!(
            text.contains("rotation_distance 40.0000 → 40.1600"),
            "{text}"
        );
    }

    #[test]
    fn a_missing_readings_file_names_the_file() {
        let dir = tempfile::tempdir().expect("tempdir");
        write_inputs(dir.path());
        let err = load_and_solve(&args(dir.path(), "nope.json")).unwrap_err();
        assert!(format!("{err:#}").contains("nope.json"));
    }
}
