//! `klipcal pylons`: reads the printer's Klipper config (following its [include]s), turns it and
//! the flags into the pure generator's inputs, runs [`crate::gcode::generate`] and writes the
//! G-code, layout.json and SVG. The only I/O of the pylon job; no generation logic here.

use std::path::Path;

use anyhow::{bail, Context};

use crate::cli::PylonsArgs;
use crate::fsio::FsFiles;
use crate::gcode::{self, Kinematics, LayoutKind, Machine, Options};
use crate::klipper::Config;

/// The generator's printer facts from a loaded config and the overriding flags.
///
/// # Errors
/// Missing or bad config values the flags do not override; kinematics other than corexy and
/// cartesian.
pub(crate) fn machine_from(config: &Config, args: &PylonsArgs) -> anyhow::Result<Machine> {
    let kinematics = args
        .kinematics
        .as_deref()
        .map(Kinematics::parse)
        .transpose()?;
    Ok(Machine::from_config(
        config,
        kinematics,
        args.nozzle_diameter,
        args.filament_diameter,
        None,
    )?)
}

/// Parses `X,Y`.
fn parse_center(text: &str) -> anyhow::Result<[f64; 2]> {
    let mut parts = text.split(',').map(|p| p.trim().parse::<f64>());
    match (parts.next(), parts.next(), parts.next()) {
        (Some(Ok(x)), Some(Ok(y)), None) if x.is_finite() && y.is_finite() => Ok([x, y]),
        _ => bail!("--center {text}: expected two numbers X,Y in mm, e.g. 150,150"),
    }
}

/// The generator's options from the flags.
///
/// # Errors
/// A bad `--layout` or `--center`.
pub(crate) fn options_from(args: &PylonsArgs, generated_at_unix_s: i64) -> anyhow::Result<Options> {
    let mut o = Options {
        layout: LayoutKind::parse(&args.layout)?,
        d1_mm: args.d1,
        d2_mm: args.d2,
        center_mm: args.center.as_deref().map(parse_center).transpose()?,
        bed_temp_c: args.bed_temp,
        nozzle_temp_c: args.nozzle_temp,
        layer_height_mm: args.layer_height,
        first_layer_height_mm: args.layer_height,
        pylon_length_mm: args.pylon_length,
        end_template: args.end_template.clone(),
        bed_soak_s: args.bed_soak_s,
        generated_at_unix_s,
        ..Options::default()
    };
    if let Some(t) = &args.start_template {
        o.print_start_template.clone_from(t);
    }
    Ok(o)
}

fn write(path: &Path, text: &str) -> anyhow::Result<()> {
    std::fs::write(path, text).with_context(|| format!("writing {}", path.display()))
}

/// Runs `klipcal pylons`: prints a one-paragraph summary on success.
///
/// # Errors
/// An unreadable or invalid Klipper config, bad flags, a layout that does not fit (with the
/// suggested `--d2`), or a file that cannot be written.
pub(crate) fn run(args: &PylonsArgs) -> anyhow::Result<()> {
    let config = Config::load(&FsFiles, &args.printer_cfg)
        .with_context(|| format!("reading {}", args.printer_cfg.display()))?;
    let machine = machine_from(&config, args)?;
    let now_s = std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map_or(0, |d| i64::try_from(d.as_secs()).unwrap_or(0));
    let options = options_from(args, now_s)?;
    let job = gcode::generate(&machine, &options)?;
    write(&args.out, &job.gcode)?;
    let layout = serde_json::to_string_pretty(&job.layout).context("encoding layout.json")?;
    write(&args.layout_out, &(layout + "\n"))?;
    if let Some(svg) = &args.svg {
        write(svg, &job.svg)?;
    }
    let s = &job.summary;
    println!(
        "{} layout, {}: {} pylons, D1 = {} mm, D2 = {} mm (scale precision bound {:.3} %), \
         {} layers, {:.0} min, {:.2} m / {:.1} g of filament → {}",
        options.layout.as_str(),
        machine.kinematics.as_str(),
        job.layout.pylons.len(),
        options.d1_mm,
        options.d2_mm,
        100.0 * s.precision_bound,
        s.layers,
        s.estimated_time_s / 60.0,
        s.filament_mm / 1000.0,
        s.filament_g,
        args.out.display()
    );
    Ok(())
}

#[cfg(test)]
mod tests {
    use std::path::PathBuf;

    use clap::Parser;

    use super::*;
    use crate::cli::{Cli, Command};
    use crate::klipper::MemFiles;

    const CFG: &str =
        "[include hw.cfg]\n[printer]\nkinematics: corexy\nmax_velocity: 300\nmax_accel: 3000\n\
        [gcode_macro PRINT_START]\ngcode:\n  G28\n";
    const HW: &str =
        "[stepper_x]\nrotation_distance: 40\nmicrosteps: 16\nposition_min: -5\nposition_max: 245\n\
        step_pin: x\ndir_pin: x\nenable_pin: x\nendstop_pin: x\nposition_endstop: 245\n\
        [stepper_y]\nrotation_distance: 40\nmicrosteps: 16\nposition_max: 250\n\
        step_pin: y\ndir_pin: y\nenable_pin: y\nendstop_pin: y\nposition_endstop: 250\n\
        [stepper_z]\nposition_max: 230\n\
        [extruder]\nnozzle_diameter: 0.4\nfilament_diameter: 1.750\n";

    fn args(extra: &[&str]) -> PylonsArgs {
        let mut argv = vec![
            "klipcal",
            "pylons",
            "--printer-cfg",
            "/cfg/printer.cfg",
            "--out",
            "j.gcode",
            "--layout-out",
            "l.json",
        ];
        argv.extend_from_slice(extra);
        match Cli::parse_from(argv).command {
            Command::Pylons(a) => *a,
            other => panic!("parsed {other:?}"),
        }
    }

    fn config() -> Config {
        let mut files = MemFiles::default();
        files.insert(PathBuf::from("/cfg/printer.cfg"), CFG);
        files.insert(PathBuf::from("/cfg/hw.cfg"), HW);
        Config::load(&files, Path::new("/cfg/printer.cfg")).expect("test config loads")
    }

    #[test]
    fn printer_facts_come_from_the_config_and_its_includes() {
        let m = machine_from(&config(), &args(&[])).expect("facts");
        assert_eq!(m.kinematics, Kinematics::CoreXy);
        assert_eq!(
            (m.x_min_mm, m.x_max_mm, m.y_min_mm, m.y_max_mm),
            (-5.0, 245.0, 0.0, 250.0)
        );
        assert_eq!(m.z_max_mm, Some(230.0));
        assert_eq!(m.filament_diameter_mm, 1.75);
        assert_eq!(m.start_macro.as_deref(), Some("PRINT_START"));
        assert_eq!(m.max_accel_mm_s2, Some(3000.0));
    }

    #[test]
    fn the_start_macro_the_printer_has_is_the_one_the_job_calls() {
        let load = |macros: &str| {
            let mut files = MemFiles::default();
            let cfg = CFG.replace("[gcode_macro PRINT_START]\ngcode:\n  G28\n", macros);
            files.insert(PathBuf::from("/cfg/printer.cfg"), &cfg);
            files.insert(PathBuf::from("/cfg/hw.cfg"), HW);
            Config::load(&files, Path::new("/cfg/printer.cfg")).expect("test config loads")
        };
        let start = "[gcode_macro start_print]\ngcode:\n  G28\n";
        let both = format!("{start}[gcode_macro PRINT_START]\ngcode:\n  G28\n");
        // A START_PRINT printer (issue 9 item 15), named as Klipper registers it.
        let m = Machine::from_config(&load(start), None, None, None, None).expect("facts");
        assert_eq!(m.start_macro.as_deref(), Some("START_PRINT"));
        let job = gcode::generate(&m, &Options::default()).expect("fits");
        assert!(job.gcode.contains("\nSTART_PRINT BED=80 EXTRUDER=240\n"));
        assert!(!job.gcode.contains("PRINT_START"));
        // Both defined: the configured one wins; none configured, the job refuses to guess.
        let m = Machine::from_config(&load(&both), None, None, None, Some("print_start"))
            .expect("configured");
        assert_eq!(m.start_macro.as_deref(), Some("PRINT_START"));
        let e = Machine::from_config(&load(&both), None, None, None, Some(""))
            .expect_err("ambiguous")
            .to_string();
        assert!(
            e.contains("PRINT_START and START_PRINT") && e.contains("ab.start_macro"),
            "{e}"
        );
        // A configured macro the config lacks is named.
        let e = Machine::from_config(&load(start), None, None, None, Some("MY_START"))
            .expect_err("missing")
            .to_string();
        assert!(e.contains("MY_START"), "{e}");
        // None at all: the job heats and homes itself.
        let m = Machine::from_config(&load(""), None, None, None, None).expect("facts");
        assert_eq!(m.start_macro, None);
    }

    #[test]
    fn flags_override_the_config() {
        let a = args(&[
            "--kinematics",
            "cartesian",
            "--nozzle-diameter",
            "0.6",
            "--center",
            "120,130",
        ]);
        let m = machine_from(&config(), &a).expect("facts");
        assert_eq!(m.kinematics, Kinematics::Cartesian);
        assert_eq!(m.nozzle_diameter_mm, 0.6);
        let o = options_from(&a, 0).expect("options");
        assert_eq!(o.center_mm, Some([120.0, 130.0]));
        assert!(options_from(&args(&["--center", "120"]), 0).is_err());
        assert!(options_from(&args(&["--layout", "diagonal"]), 0).is_err());
    }
}
