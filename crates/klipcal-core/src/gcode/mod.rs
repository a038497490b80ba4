//! PURE: the pylon job generator — geometry → toolpaths → G-code text + layout + SVG preview.
//! No I/O and no clock: callers read printer facts, pass the time in, and write the files.
//!
//! The job prints freestanding slab pylons in groups of three (seed 000, §2.2): pylon 1's outer
//! face to the far face of pylon 2 is D1, to the far face of pylon 3 is D2. [`plan`] places the
//! groups on the bed, [`slice`] turns each pylon into per-layer toolpaths, [`emit`] writes the
//! G-code with a PrusaSlicer-style header Moonraker's metadata parser reads, [`svg`] draws the
//! preview.

mod emit;
mod estimate;
mod plan;
mod slice;
mod svg;
#[cfg(test)]
mod tests;

use crate::layout::Layout;

/// A generator error a user can cause (bad options, a bed too small for the layout).
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum Error {
    /// An option or printer fact is out of range.
    #[error("{name} = {value}: expected {expected}")]
    Invalid {
        /// Option name as the user spells it, e.g. `--d2`.
        name: &'static str,
        /// The value given.
        value: String,
        /// What would be accepted.
        expected: String,
    },
    /// The groups do not fit the printable area or would touch each other.
    #[error("{message}")]
    DoesNotFit {
        /// What does not fit and by how much, with the suggestion.
        message: String,
        /// The largest whole-mm D2 that fits, when one does.
        suggested_d2_mm: Option<f64>,
    },
    /// The printer's Klipper config lacks a fact the job needs, or has a bad value.
    #[error("{0}")]
    Config(String),
    /// A start or end template has a character or placeholder that is not allowed.
    #[error("{which} template {template:?}: {reason}")]
    Template {
        /// `start` or `end`.
        which: &'static str,
        /// The template text.
        template: String,
        /// What is wrong and what is expected.
        reason: String,
    },
}

/// Printer kinematics the generator knows.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Kinematics {
    /// CoreXY: stepper_x (A) moves along +45°, stepper_y (B) along −45°.
    CoreXy,
    /// Cartesian: stepper_x moves along X, stepper_y along Y.
    Cartesian,
}

impl Kinematics {
    /// The name Klipper and `layout.json` use.
    pub fn as_str(self) -> &'static str {
        match self {
            Kinematics::CoreXy => "corexy",
            Kinematics::Cartesian => "cartesian",
        }
    }

    /// Parses `corexy` or `cartesian`.
    ///
    /// # Errors
    /// Any other kinematics.
    pub fn parse(text: &str) -> Result<Self, Error> {
        match text.trim().to_ascii_lowercase().as_str() {
            "corexy" => Ok(Kinematics::CoreXy),
            "cartesian" => Ok(Kinematics::Cartesian),
            other => Err(Error::Invalid {
                name: "kinematics",
                value: other.to_string(),
                expected: "corexy or cartesian".into(),
            }),
        }
    }
}

/// Which groups to print.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum LayoutKind {
    /// Two groups along the motor directions (the paper's model).
    Paper,
    /// Four groups: the motor directions plus the two others (X/Y or both diagonals).
    Full,
}

impl LayoutKind {
    /// Parses `paper` or `full`.
    ///
    /// # Errors
    /// Any other name.
    pub fn parse(text: &str) -> Result<Self, Error> {
        match text.trim().to_ascii_lowercase().as_str() {
            "paper" => Ok(LayoutKind::Paper),
            "full" => Ok(LayoutKind::Full),
            other => Err(Error::Invalid {
                name: "--layout",
                value: other.to_string(),
                expected: "paper or full".into(),
            }),
        }
    }

    /// `paper` or `full`.
    pub fn as_str(self) -> &'static str {
        match self {
            LayoutKind::Paper => "paper",
            LayoutKind::Full => "full",
        }
    }
}

/// The printer facts the generator needs (filled from a Klipper config by the caller).
#[derive(Debug, Clone, PartialEq)]
pub struct Machine {
    /// Kinematics.
    pub kinematics: Kinematics,
    /// stepper_x position_min, mm.
    pub x_min_mm: f64,
    /// stepper_x position_max, mm.
    pub x_max_mm: f64,
    /// stepper_y position_min, mm.
    pub y_min_mm: f64,
    /// stepper_y position_max, mm.
    pub y_max_mm: f64,
    /// stepper_z position_max, mm, when known.
    pub z_max_mm: Option<f64>,
    /// Extruder nozzle diameter, mm.
    pub nozzle_diameter_mm: f64,
    /// Filament diameter, mm.
    pub filament_diameter_mm: f64,
    /// The start macro the slicer calls (`PRINT_START`, `START_PRINT` or the one configured
    /// as `ab.start_macro`), upper case as Klipper registers it; `None` without one.
    pub start_macro: Option<String>,
    /// `[printer] max_velocity`, restored at the end when known.
    pub max_velocity_mm_s: Option<f64>,
    /// `[printer] max_accel`, restored at the end when known.
    pub max_accel_mm_s2: Option<f64>,
    /// `[printer] square_corner_velocity` for the time estimate (Klipper's default 5 mm/s).
    pub square_corner_velocity_mm_s: Option<f64>,
}

impl Machine {
    /// The generator's printer facts from a loaded Klipper config, with optional overrides of
    /// the kinematics and the nozzle and filament diameters (the daemon passes none).
    ///
    /// # Errors
    /// [`Error::Config`]: a config without the facts the job needs, or kinematics other than
    /// corexy and cartesian without an override.
    pub fn from_config(
        config: &crate::klipper::Config,
        kinematics: Option<Kinematics>,
        nozzle_diameter_mm: Option<f64>,
        filament_diameter_mm: Option<f64>,
        start_macro: Option<&str>,
    ) -> Result<Machine, Error> {
        use crate::klipper;
        let number = |section: &str, key: &str| -> Result<Option<f64>, Error> {
            match config.get(section, key) {
                None => Ok(None),
                Some(raw) => raw.trim().parse::<f64>().map(Some).map_err(|_| {
                    Error::Config(format!("[{section}] {key} = '{raw}' is not a number"))
                }),
            }
        };
        let facts = klipper::PrinterFacts::from_config(config)
            .map_err(|e| Error::Config(format!("reading the printer facts: {e}")))?;
        let kinematics = match (kinematics, &facts.kinematics) {
            (Some(k), _) => k,
            (None, klipper::Kinematics::CoreXy) => Kinematics::CoreXy,
            (None, klipper::Kinematics::Cartesian) => Kinematics::Cartesian,
            (None, klipper::Kinematics::Other(k)) => {
                return Err(Error::Config(format!(
                    "[printer] kinematics = {k}: the pylon job supports corexy and cartesian; \
                     pass --kinematics to override"
                )))
            }
        };
        let nozzle_diameter_mm =
            nozzle_diameter_mm
                .or(facts.nozzle_diameter_mm)
                .ok_or_else(|| {
                    Error::Config("no [extruder] nozzle_diameter; pass --nozzle-diameter".into())
                })?;
        let filament_diameter_mm = filament_diameter_mm
            .or(facts.filament_diameter_mm)
            .ok_or_else(|| {
                Error::Config("no [extruder] filament_diameter; pass --filament-diameter".into())
            })?;
        Ok(Machine {
            kinematics,
            x_min_mm: facts.stepper_x.position_min_mm,
            x_max_mm: facts.stepper_x.position_max_mm,
            y_min_mm: facts.stepper_y.position_min_mm,
            y_max_mm: facts.stepper_y.position_max_mm,
            z_max_mm: number("stepper_z", "position_max")?,
            nozzle_diameter_mm,
            filament_diameter_mm,
            start_macro: match klipper::find_start_macro(config, start_macro) {
                Ok(klipper::StartMacro::Found { command, .. }) => Some(command),
                Ok(klipper::StartMacro::NotFound) => None,
                Ok(klipper::StartMacro::Ambiguous(both)) => {
                    return Err(Error::Config(format!(
                        "the config defines {}: set ab.start_macro in klipcal.toml to the one \
                         your slicer calls",
                        both.join(" and ")
                    )))
                }
                Err(e) => return Err(Error::Config(e.to_string())),
            },
            max_velocity_mm_s: number("printer", "max_velocity")?,
            max_accel_mm_s2: number("printer", "max_accel")?,
            square_corner_velocity_mm_s: number("printer", "square_corner_velocity")?,
        })
    }

    /// A square printer from 0 to `size_mm` in X and Y with a 0.4 mm nozzle and 1.75 mm
    /// filament and no other facts known: the fixture of tests, benchmarks and previews.
    pub fn square_bed(kinematics: Kinematics, size_mm: f64) -> Self {
        Machine {
            kinematics,
            x_min_mm: 0.0,
            x_max_mm: size_mm,
            y_min_mm: 0.0,
            y_max_mm: size_mm,
            z_max_mm: None,
            nozzle_diameter_mm: 0.4,
            filament_diameter_mm: 1.75,
            start_macro: None,
            max_velocity_mm_s: None,
            max_accel_mm_s2: None,
            square_corner_velocity_mm_s: None,
        }
    }
}

/// Everything about the job that is not a printer fact. [`Options::default`] is the paper's
/// practical procedure (shared/seeds/README.md).
#[derive(Debug, Clone, PartialEq)]
pub struct Options {
    /// Which groups.
    pub layout: LayoutKind,
    /// Outer edge-to-edge distance pylon 1 → pylon 2, mm.
    pub d1_mm: f64,
    /// Outer edge-to-edge distance pylon 1 → pylon 3, mm.
    pub d2_mm: f64,
    /// Where the groups cross; the middle of the printable area when `None`.
    pub center_mm: Option<[f64; 2]>,
    /// Slab thickness along the measuring direction, mm.
    pub pylon_thickness_mm: f64,
    /// Slab length across the measuring direction, rounded ends included, mm.
    pub pylon_length_mm: f64,
    /// Slab height, mm.
    pub pylon_height_mm: f64,
    /// Height of the top chamfer, mm.
    pub chamfer_height_mm: f64,
    /// Thickness at the very top of the chamfer, mm.
    pub chamfer_top_thickness_mm: f64,
    /// Layer height, mm.
    pub layer_height_mm: f64,
    /// First layer height, mm.
    pub first_layer_height_mm: f64,
    /// Extrusion line width; `None` = 1.25 × nozzle diameter (0.5 mm for a 0.4 mm nozzle).
    pub line_width_mm: Option<f64>,
    /// Perimeters per side (fewer when the slab is too thin for them; the rest is solid infill).
    pub perimeters: u32,
    /// Flow factor applied to every extrusion (0.93 = 7 % under-extrusion).
    pub flow: f64,
    /// Print speed, mm/s.
    pub speed_mm_s: f64,
    /// First-layer print speed, mm/s.
    pub first_layer_speed_mm_s: f64,
    /// Travel speed, mm/s.
    pub travel_speed_mm_s: f64,
    /// Acceleration set with SET_VELOCITY_LIMIT, mm/s².
    pub accel_mm_s2: f64,
    /// Retraction length, mm of filament.
    pub retract_mm: f64,
    /// Retraction speed, mm/s.
    pub retract_speed_mm_s: f64,
    /// Z lift during travel between pylons, mm.
    pub z_hop_mm: f64,
    /// Bed temperature, °C (left on at the end).
    pub bed_temp_c: f64,
    /// Nozzle temperature, °C.
    pub nozzle_temp_c: f64,
    /// Filament density for the weight estimate, g/cm³.
    pub filament_density_g_cm3: f64,
    /// Free border kept inside the printable area, mm.
    pub edge_margin_mm: f64,
    /// Smallest gap between pylons of different groups, mm.
    pub group_gap_mm: f64,
    /// Start when the printer has a start macro; placeholders `{start_macro}` (its name:
    /// `PRINT_START`, `START_PRINT`, or `ab.start_macro`), `{bed_temp_c}` and `{nozzle_temp_c}`.
    pub print_start_template: String,
    /// Extra end G-code after the built-in end (e.g. `PRINT_END`); `None` keeps the bed on.
    pub end_template: Option<String>,
    /// Dwell after the bed reached temperature (paper §3.1: thermal equilibrium first), s.
    pub bed_soak_s: f64,
    /// Time written in the header (`; generated by … on …`), Unix seconds, UTC.
    pub generated_at_unix_s: i64,
}

impl Default for Options {
    fn default() -> Self {
        Self {
            layout: LayoutKind::Paper,
            d1_mm: 10.0,
            d2_mm: 150.0,
            center_mm: None,
            pylon_thickness_mm: 3.6,
            pylon_length_mm: 53.6,
            pylon_height_mm: 8.0,
            chamfer_height_mm: 0.3,
            chamfer_top_thickness_mm: 3.0,
            layer_height_mm: 0.2,
            first_layer_height_mm: 0.2,
            line_width_mm: None,
            perimeters: 5,
            flow: 0.93,
            speed_mm_s: 60.0,
            first_layer_speed_mm_s: 25.0,
            travel_speed_mm_s: 150.0,
            accel_mm_s2: 800.0,
            retract_mm: 0.8,
            retract_speed_mm_s: 35.0,
            z_hop_mm: 0.4,
            bed_temp_c: 80.0,
            nozzle_temp_c: 240.0,
            filament_density_g_cm3: 1.27,
            edge_margin_mm: 5.0,
            group_gap_mm: 3.0,
            print_start_template: "{start_macro} BED={bed_temp_c} EXTRUDER={nozzle_temp_c}".into(),
            end_template: None,
            bed_soak_s: 0.0,
            generated_at_unix_s: 0,
        }
    }
}

impl Options {
    /// The line width used: the explicit one, else 1.25 × nozzle diameter.
    pub fn line_width(&self, machine: &Machine) -> f64 {
        self.line_width_mm
            .unwrap_or(1.25 * machine.nozzle_diameter_mm)
    }
}

/// Figures of a generated job, also written into the G-code header.
#[derive(Debug, Clone, PartialEq)]
pub struct Summary {
    /// Filament length, mm.
    pub filament_mm: f64,
    /// Filament weight, g.
    pub filament_g: f64,
    /// Estimated print time (motion only, plus the soak), s.
    pub estimated_time_s: f64,
    /// Number of layers.
    pub layers: usize,
    /// Line width used, mm.
    pub line_width_mm: f64,
    /// The paper's scale precision bound for this D1/D2 (seed 000, §3.7), as a fraction.
    pub precision_bound: f64,
}

/// A generated job.
#[derive(Debug, Clone, PartialEq)]
pub struct Job {
    /// The G-code text.
    pub gcode: String,
    /// What the user measures, for `layout.json`.
    pub layout: Layout,
    /// The preview drawing.
    pub svg: String,
    /// Figures of the job.
    pub summary: Summary,
}

/// Generates the pylon job for `machine` with `options`.
///
/// # Errors
/// An option out of range, a template with a forbidden character, or a layout that does not
/// fit the printable area (the message says by how much and suggests a `--d2` that fits).
pub fn generate(machine: &Machine, options: &Options) -> Result<Job, Error> {
    validate(machine, options)?;
    let placed = plan::place(machine, options)?;
    let line_width_mm = options.line_width(machine);
    let layers = slice::slice_all(&placed, options, line_width_mm);
    let emitted = emit::emit(machine, options, &placed, &layers, line_width_mm)?;
    let layout = plan::to_layout(machine, options, &placed);
    let svg = svg::render(machine, options, &placed, &layout);
    Ok(Job {
        gcode: emitted.gcode,
        layout,
        svg,
        summary: emitted.summary,
    })
}

fn check(name: &'static str, value: f64, ok: bool, expected: &str) -> Result<(), Error> {
    if ok && value.is_finite() {
        Ok(())
    } else {
        Err(Error::Invalid {
            name,
            value: format!("{value}"),
            expected: expected.to_string(),
        })
    }
}

/// Every setting in its range, checked in this order (the first wrong one is reported): the
/// printer, the pylons' shape, the motion, the print's temperatures and placement.
fn validate(m: &Machine, o: &Options) -> Result<(), Error> {
    validate_machine(m)?;
    validate_shape(m, o)?;
    validate_motion(o)?;
    validate_print(m, o)
}

/// The printer's nozzle, filament and axis limits.
fn validate_machine(m: &Machine) -> Result<(), Error> {
    check(
        "--nozzle-diameter",
        m.nozzle_diameter_mm,
        m.nozzle_diameter_mm >= 0.1 && m.nozzle_diameter_mm <= 2.0,
        "between 0.1 and 2.0 mm",
    )?;
    check(
        "--filament-diameter",
        m.filament_diameter_mm,
        m.filament_diameter_mm >= 1.0 && m.filament_diameter_mm <= 3.5,
        "between 1.0 and 3.5 mm",
    )?;
    check(
        "stepper_x position_max",
        m.x_max_mm,
        m.x_max_mm > m.x_min_mm,
        "greater than stepper_x position_min",
    )?;
    check(
        "stepper_y position_max",
        m.y_max_mm,
        m.y_max_mm > m.y_min_mm,
        "greater than stepper_y position_min",
    )?;
    Ok(())
}

/// The lines, layers, pylons, chamfer and distances.
fn validate_shape(m: &Machine, o: &Options) -> Result<(), Error> {
    let w = o.line_width(m);
    check(
        "line width",
        w,
        w >= 0.8 * m.nozzle_diameter_mm && w <= 2.0 * m.nozzle_diameter_mm,
        "between 0.8 and 2 × the nozzle diameter",
    )?;
    check(
        "--layer-height",
        o.layer_height_mm,
        o.layer_height_mm >= 0.04 && o.layer_height_mm <= 0.8 * m.nozzle_diameter_mm,
        "between 0.04 mm and 0.8 × the nozzle diameter",
    )?;
    check(
        "first layer height",
        o.first_layer_height_mm,
        o.first_layer_height_mm >= 0.04 && o.first_layer_height_mm <= 0.8 * m.nozzle_diameter_mm,
        "between 0.04 mm and 0.8 × the nozzle diameter",
    )?;
    check(
        "pylon thickness",
        o.pylon_thickness_mm,
        o.pylon_thickness_mm >= 4.0 * w,
        "at least 4 line widths",
    )?;
    check(
        "pylon length",
        o.pylon_length_mm,
        o.pylon_length_mm >= o.pylon_thickness_mm,
        "at least the pylon thickness",
    )?;
    check(
        "pylon height",
        o.pylon_height_mm,
        o.pylon_height_mm >= o.first_layer_height_mm + o.chamfer_height_mm
            && o.pylon_height_mm <= 100.0,
        "between the first layer plus the chamfer and 100 mm",
    )?;
    let inset = (o.pylon_thickness_mm - o.chamfer_top_thickness_mm) / 2.0;
    check(
        "chamfer top thickness",
        o.chamfer_top_thickness_mm,
        inset >= 0.0 && o.chamfer_top_thickness_mm >= 2.0 * w,
        "between 2 line widths and the pylon thickness",
    )?;
    check(
        "chamfer height",
        o.chamfer_height_mm,
        o.chamfer_height_mm >= 0.0 && o.chamfer_height_mm < o.pylon_height_mm,
        "between 0 and the pylon height",
    )?;
    check(
        "--d1",
        o.d1_mm,
        o.d1_mm >= 2.0 * o.pylon_thickness_mm + 1.0,
        &format!(
            "at least two pylon thicknesses plus 1 mm ({:.1} mm)",
            2.0 * o.pylon_thickness_mm + 1.0
        ),
    )?;
    let min_d2 = plan::min_d2(o);
    check(
        "--d2",
        o.d2_mm,
        o.d2_mm >= min_d2,
        &format!("at least --d1 + 20 mm ({min_d2:.1} mm)"),
    )?;
    Ok(())
}

/// Flow, speeds, acceleration, retraction and hops.
fn validate_motion(o: &Options) -> Result<(), Error> {
    check(
        "flow",
        o.flow,
        o.flow > 0.5 && o.flow <= 1.5,
        "between 0.5 and 1.5",
    )?;
    check(
        "speed",
        o.speed_mm_s,
        o.speed_mm_s > 0.0 && o.speed_mm_s <= 1000.0,
        "between 0 and 1000 mm/s",
    )?;
    check(
        "first layer speed",
        o.first_layer_speed_mm_s,
        o.first_layer_speed_mm_s > 0.0 && o.first_layer_speed_mm_s <= 1000.0,
        "between 0 and 1000 mm/s",
    )?;
    check(
        "travel speed",
        o.travel_speed_mm_s,
        o.travel_speed_mm_s > 0.0 && o.travel_speed_mm_s <= 1000.0,
        "between 0 and 1000 mm/s",
    )?;
    check(
        "accel",
        o.accel_mm_s2,
        o.accel_mm_s2 > 0.0 && o.accel_mm_s2 <= 100_000.0,
        "between 0 and 100000 mm/s²",
    )?;
    check(
        "retract",
        o.retract_mm,
        (0.0..=20.0).contains(&o.retract_mm),
        "between 0 and 20 mm",
    )?;
    check(
        "retract speed",
        o.retract_speed_mm_s,
        o.retract_speed_mm_s > 0.0,
        "greater than 0 mm/s",
    )?;
    check(
        "z hop",
        o.z_hop_mm,
        (0.0..=5.0).contains(&o.z_hop_mm),
        "between 0 and 5 mm",
    )?;
    Ok(())
}

/// Temperatures, filament, placement on the bed, soak and perimeters.
fn validate_print(m: &Machine, o: &Options) -> Result<(), Error> {
    check(
        "--bed-temp",
        o.bed_temp_c,
        (0.0..=150.0).contains(&o.bed_temp_c),
        "between 0 and 150 °C",
    )?;
    check(
        "--nozzle-temp",
        o.nozzle_temp_c,
        (150.0..=350.0).contains(&o.nozzle_temp_c),
        "between 150 and 350 °C",
    )?;
    check(
        "filament density",
        o.filament_density_g_cm3,
        o.filament_density_g_cm3 > 0.5 && o.filament_density_g_cm3 < 3.0,
        "between 0.5 and 3 g/cm³",
    )?;
    check(
        "edge margin",
        o.edge_margin_mm,
        o.edge_margin_mm >= 0.0,
        "0 mm or more",
    )?;
    check(
        "group gap",
        o.group_gap_mm,
        o.group_gap_mm >= 0.5,
        "0.5 mm or more",
    )?;
    check(
        "bed soak",
        o.bed_soak_s,
        (0.0..=7200.0).contains(&o.bed_soak_s),
        "between 0 and 7200 s",
    )?;
    if o.perimeters == 0 || o.perimeters > 20 {
        return Err(Error::Invalid {
            name: "perimeters",
            value: o.perimeters.to_string(),
            expected: "between 1 and 20".into(),
        });
    }
    if let Some(c) = o.center_mm {
        check(
            "--center x",
            c[0],
            c[0] > m.x_min_mm && c[0] < m.x_max_mm,
            "inside stepper_x limits",
        )?;
        check(
            "--center y",
            c[1],
            c[1] > m.y_min_mm && c[1] < m.y_max_mm,
            "inside stepper_y limits",
        )?;
    }
    Ok(())
}
