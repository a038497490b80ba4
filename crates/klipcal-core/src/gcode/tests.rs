//! Tests of the generated jobs through their own G-code: a small interpreter replays the text
//! (not the generator's intent) and checks the measured faces, extruded volume, bounds and
//! travel moves for every printer fixture of issue 3.

use super::*;

/// One replayed move.
#[derive(Debug, Clone)]
struct Move {
    from: [f64; 3],
    to: [f64; 3],
    /// Filament fed during the move, mm (relative).
    e: f64,
    object: Option<String>,
    line: usize,
}

impl Move {
    fn xy_len(&self) -> f64 {
        let d = (self.to[0] - self.from[0]).hypot(self.to[1] - self.from[1]);
        if d.is_nan() {
            0.0
        } else {
            d
        }
    }
}

/// The replayed job.
#[derive(Debug, Default)]
struct Replay {
    moves: Vec<Move>,
    defined: Vec<String>,
    starts: Vec<String>,
    ends: Vec<String>,
}

fn word(text: &str, letter: char) -> Option<f64> {
    text.split_whitespace()
        .skip(1)
        .find(|w| w.starts_with(letter))
        .map(|w| {
            w[1..]
                .parse::<f64>()
                .unwrap_or_else(|_| panic!("bad number in {text}"))
        })
}

fn param<'a>(text: &'a str, key: &str) -> Option<&'a str> {
    text.split_whitespace()
        .find_map(|w| w.strip_prefix(key).and_then(|r| r.strip_prefix('=')))
}

fn replay(gcode: &str) -> Replay {
    let mut r = Replay::default();
    let mut pos = [f64::NAN; 3];
    let mut e_abs = 0.0;
    let mut relative_e = false;
    let mut object: Option<String> = None;
    for (n, raw) in gcode.lines().enumerate() {
        let text = raw.split(';').next().unwrap_or("").trim();
        if text.is_empty() {
            continue;
        }
        let cmd = text.split_whitespace().next().unwrap_or("");
        match cmd {
            "G0" | "G1" => {
                let mut to = pos;
                for (i, c) in ['X', 'Y', 'Z'].iter().enumerate() {
                    if let Some(v) = word(text, *c) {
                        to[i] = v;
                    }
                }
                let e = match word(text, 'E') {
                    Some(v) if relative_e => v,
                    Some(v) => {
                        let d = v - e_abs;
                        e_abs = v;
                        d
                    }
                    None => 0.0,
                };
                r.moves.push(Move {
                    from: pos,
                    to,
                    e,
                    object: object.clone(),
                    line: n + 1,
                });
                pos = to;
            }
            "G91" => panic!("line {}: relative XYZ is not expected", n + 1),
            "M82" => relative_e = false,
            "M83" => relative_e = true,
            "G92" => {
                if let Some(v) = word(text, 'E') {
                    e_abs = v;
                }
            }
            "G28" => pos = [f64::NAN; 3],
            "EXCLUDE_OBJECT_DEFINE" => {
                r.defined
                    .push(param(text, "NAME").unwrap_or("").to_string());
            }
            "EXCLUDE_OBJECT_START" => {
                assert!(object.is_none(), "line {}: nested object", n + 1);
                let name = param(text, "NAME").unwrap_or("").to_string();
                r.starts.push(name.clone());
                object = Some(name);
            }
            "EXCLUDE_OBJECT_END" => {
                let name = param(text, "NAME").unwrap_or("").to_string();
                assert_eq!(object.as_deref(), Some(name.as_str()), "line {}", n + 1);
                r.ends.push(name);
                object = None;
            }
            _ => {}
        }
    }
    r
}

/// Issue 3's printer fixtures: (name, kinematics, bed size).
const FIXTURES: [(&str, Kinematics, f64); 5] = [
    ("corexy-120", Kinematics::CoreXy, 120.0),
    ("corexy-250", Kinematics::CoreXy, 250.0),
    ("corexy-300", Kinematics::CoreXy, 300.0),
    ("corexy-350", Kinematics::CoreXy, 350.0),
    ("cartesian-235", Kinematics::Cartesian, 235.0),
];

fn machine(kinematics: Kinematics, size_mm: f64) -> Machine {
    Machine {
        z_max_mm: Some(size_mm.min(250.0)),
        max_velocity_mm_s: Some(300.0),
        max_accel_mm_s2: Some(3000.0),
        ..Machine::square_bed(kinematics, size_mm)
    }
}

/// Generates the fixture's job, taking the suggested `--d2` when the default does not fit.
/// `None` when the layout cannot fit at all.
fn job_for(m: &Machine, layout: LayoutKind) -> Option<(Options, Job)> {
    let o = Options {
        layout,
        ..Options::default()
    };
    match generate(m, &o) {
        Ok(job) => Some((o, job)),
        Err(Error::DoesNotFit {
            message,
            suggested_d2_mm,
        }) => {
            let d2 = suggested_d2_mm?;
            assert!(message.contains(&format!("Try --d2 {d2}")), "{message}");
            let o = Options { d2_mm: d2, ..o };
            Some((o.clone(), generate(m, &o).expect("the suggested --d2 fits")))
        }
        Err(other) => panic!("unexpected error {other}"),
    }
}

type FixtureJob = (String, Machine, Options, Job);

/// Every fixture's jobs, generated once for all tests.
fn all_jobs() -> &'static [FixtureJob] {
    static JOBS: std::sync::OnceLock<Vec<FixtureJob>> = std::sync::OnceLock::new();
    JOBS.get_or_init(generate_all)
}

fn generate_all() -> Vec<FixtureJob> {
    let mut out = Vec::new();
    for (name, kin, size) in FIXTURES {
        let m = machine(kin, size);
        for layout in [LayoutKind::Paper, LayoutKind::Full] {
            match job_for(&m, layout) {
                Some((o, job)) => {
                    out.push((format!("{name}/{}", layout.as_str()), m.clone(), o, job))
                }
                None => assert_eq!(
                    layout,
                    LayoutKind::Full,
                    "{name}: the paper layout must always get a usable job"
                ),
            }
        }
    }
    out
}

/// Solid volume of one pylon: a stadium prism with the top chamfer (Simpson's rule is exact
/// for the chamfer, whose section area is quadratic in the inset).
fn solid_volume_mm3(o: &Options) -> f64 {
    let area = |inset: f64| {
        let r = o.pylon_thickness_mm / 2.0 - inset;
        2.0 * r * (o.pylon_length_mm - o.pylon_thickness_mm) + std::f64::consts::PI * r * r
    };
    let total = (o.pylon_thickness_mm - o.chamfer_top_thickness_mm) / 2.0;
    let c = o.chamfer_height_mm;
    area(0.0) * (o.pylon_height_mm - c)
        + c / 6.0 * (area(0.0) + 4.0 * area(total / 2.0) + area(total))
}

#[test]
fn every_fixture_gets_a_paper_job_and_the_big_ones_a_full_job() {
    let jobs = all_jobs();
    let names: Vec<&str> = jobs.iter().map(|j| j.0.as_str()).collect();
    for must in [
        "corexy-120/paper",
        "corexy-250/paper",
        "corexy-250/full",
        "corexy-300/full",
        "corexy-350/full",
        "cartesian-235/paper",
        "cartesian-235/full",
    ] {
        assert!(names.contains(&must), "{must} missing from {names:?}");
    }
}

#[test]
fn outer_measured_faces_of_each_pair_are_nominal_within_a_micrometre() {
    for (name, m, o, job) in all_jobs() {
        let w = o.line_width(m);
        let r = replay(&job.gcode);
        let chamfer_start = o.pylon_height_mm - o.chamfer_height_mm;
        for pair in &job.layout.pairs {
            let rad = pair.direction_deg.to_radians();
            let u = [rad.cos(), rad.sin()];
            // extruding moves of both pylons, per layer below the chamfer
            let mut layers: std::collections::BTreeMap<i64, (f64, f64)> = Default::default();
            for mv in r.moves.iter().filter(|mv| mv.e > 0.0 && mv.xy_len() > 0.0) {
                let Some(obj) = &mv.object else { continue };
                if obj != &pair.from && obj != &pair.to {
                    continue;
                }
                if mv.to[2] > chamfer_start {
                    continue;
                }
                let key = (mv.to[2] * 1000.0).round() as i64;
                let entry = layers
                    .entry(key)
                    .or_insert((f64::INFINITY, f64::NEG_INFINITY));
                for p in [mv.from, mv.to] {
                    let s = p[0] * u[0] + p[1] * u[1];
                    entry.0 = entry.0.min(s);
                    entry.1 = entry.1.max(s);
                }
            }
            assert!(
                layers.len() >= 30,
                "{name} {}: only {} layers",
                pair.id,
                layers.len()
            );
            for (z, (lo, hi)) in layers {
                let measured = hi - lo + w;
                assert!(
                    (measured - pair.nominal_mm).abs() < 1e-3,
                    "{name} {} at z {z} µm: {measured} vs {}",
                    pair.id,
                    pair.nominal_mm
                );
            }
        }
    }
}

#[test]
fn each_pylon_extrudes_its_solid_volume_times_flow_within_3_percent() {
    for (name, m, o, job) in all_jobs() {
        let area = std::f64::consts::PI * m.filament_diameter_mm.powi(2) / 4.0;
        let r = replay(&job.gcode);
        let expected = solid_volume_mm3(o) * o.flow;
        for p in &job.layout.pylons {
            let fed: f64 = r
                .moves
                .iter()
                .filter(|mv| mv.object.as_deref() == Some(p.id.as_str()) && mv.xy_len() > 0.0)
                .map(|mv| mv.e)
                .sum();
            let volume = fed * area;
            let err = (volume - expected) / expected;
            assert!(
                err.abs() < 0.03,
                "{name} {}: {volume:.1} mm³ vs {expected:.1} mm³ ({:.2} %)",
                p.id,
                100.0 * err
            );
        }
    }
}

#[test]
fn every_move_stays_inside_the_printable_area() {
    for (name, m, _o, job) in all_jobs() {
        for mv in replay(&job.gcode).moves {
            let [x, y, z] = mv.to;
            assert!(
                x.is_nan() || (m.x_min_mm..=m.x_max_mm).contains(&x),
                "{name} line {}: x {x}",
                mv.line
            );
            assert!(
                y.is_nan() || (m.y_min_mm..=m.y_max_mm).contains(&y),
                "{name} line {}: y {y}",
                mv.line
            );
            let zmax = m.z_max_mm.unwrap_or(f64::INFINITY);
            assert!(
                z.is_nan() || (0.0..=zmax).contains(&z),
                "{name} line {}: z {z}",
                mv.line
            );
        }
    }
}

#[test]
fn nothing_is_extruded_while_travelling() {
    for (name, _m, o, job) in all_jobs() {
        let r = replay(&job.gcode);
        let pylons = &job.layout.pylons;
        let mut layer_z = f64::NAN;
        let mut pending_e = 0.0_f64;
        for mv in &r.moves {
            if mv.xy_len() == 0.0 {
                // pure E (retract/unretract) or Z moves: the net never exceeds one retraction
                pending_e += mv.e;
                assert!(
                    pending_e.abs() <= o.retract_mm + 1e-9,
                    "{name} line {}: filament state {pending_e}",
                    mv.line
                );
                continue;
            }
            if mv.e <= 0.0 {
                assert!(
                    mv.e == 0.0,
                    "{name} line {}: retraction while moving",
                    mv.line
                );
                continue;
            }
            // an extruding XY move: inside an object, at layer height, inside that pylon
            let obj = mv
                .object
                .as_deref()
                .unwrap_or_else(|| panic!("{name} line {}: extrusion outside an object", mv.line));
            assert!(
                pending_e.abs() < 1e-9 || pending_e > 0.0,
                "{name} line {}: extruding while retracted",
                mv.line
            );
            if (mv.to[2] - layer_z).abs() > 1e-9 {
                layer_z = mv.to[2];
            }
            assert!(
                (mv.from[2] - mv.to[2]).abs() < 1e-12,
                "{name} line {}: Z moves",
                mv.line
            );
            let p = pylons
                .iter()
                .find(|p| p.id == obj)
                .unwrap_or_else(|| panic!("{name}: unknown object {obj}"));
            let rad = p.normal_deg.to_radians();
            let (u, a) = ([rad.cos(), rad.sin()], [-rad.sin(), rad.cos()]);
            let half = (p.length - p.thickness) / 2.0;
            for q in [mv.from, mv.to] {
                let d = [q[0] - p.center[0], q[1] - p.center[1]];
                let s = d[0] * u[0] + d[1] * u[1];
                let t = d[0] * a[0] + d[1] * a[1];
                let excess = (t.abs() - half).max(0.0);
                assert!(
                    s.hypot(excess) <= p.thickness / 2.0 + 1e-6,
                    "{name} line {}: extrusion outside pylon {obj}",
                    mv.line
                );
            }
            // after an extruding move the toolhead is not at a hop height
            assert!(mv.to[2] <= o.pylon_height_mm + 1e-9);
        }
    }
}

#[test]
fn seams_sit_on_the_rounded_ends_never_on_a_measured_face() {
    for (name, m, o, job) in all_jobs() {
        let r = replay(&job.gcode);
        let mut prev_extruding = false;
        for mv in &r.moves {
            let extruding = mv.e > 0.0 && mv.xy_len() > 0.0;
            if extruding && !prev_extruding {
                let obj = mv.object.as_deref().unwrap_or("");
                let p = job
                    .layout
                    .pylons
                    .iter()
                    .find(|p| p.id == obj)
                    .unwrap_or_else(|| panic!("{name}: unknown object {obj}"));
                let rad = p.normal_deg.to_radians();
                let (u, a) = ([rad.cos(), rad.sin()], [-rad.sin(), rad.cos()]);
                let d = [mv.from[0] - p.center[0], mv.from[1] - p.center[1]];
                let s = d[0] * u[0] + d[1] * u[1];
                let t = d[0] * a[0] + d[1] * a[1];
                let on_straight_part = t.abs() < (p.length - p.thickness) / 2.0 - 1e-3;
                let on_outer_line = s.abs() > p.thickness / 2.0 - o.line_width(m) - 1e-3;
                assert!(
                    !(on_straight_part && on_outer_line),
                    "{name} line {}: a path starts on a measured face",
                    mv.line
                );
            }
            if mv.xy_len() > 0.0 {
                prev_extruding = extruding;
            }
        }
    }
}

#[test]
fn every_pylon_is_an_excludable_object_on_every_layer() {
    for (name, _m, _o, job) in all_jobs() {
        let r = replay(&job.gcode);
        let ids: Vec<String> = job.layout.pylons.iter().map(|p| p.id.clone()).collect();
        assert_eq!(r.defined, ids, "{name}");
        for id in &ids {
            let starts = r.starts.iter().filter(|s| *s == id).count();
            assert_eq!(starts, job.summary.layers, "{name} {id}");
            assert_eq!(r.ends.iter().filter(|s| *s == id).count(), starts);
        }
    }
}

#[test]
fn the_header_and_footer_carry_what_moonraker_parses() {
    let m = machine(Kinematics::CoreXy, 300.0);
    let o = Options {
        generated_at_unix_s: 1_795_262_400,
        ..Options::default()
    };
    let job = generate(&m, &o).expect("fits");
    let g = &job.gcode;
    assert!(g.starts_with(&format!(
        "; generated by klipcal {} on 2026-11-21 at 12:00:00 UTC\n",
        env!("CARGO_PKG_VERSION")
    )));
    for line in [
        "; layer_height = 0.2\n",
        "; first_layer_height = 0.2\n",
        "; first_layer_temperature = 240\n",
        "; first_layer_bed_temperature = 80\n",
        "; nozzle_diameter = 0.4\n",
        ";BEFORE_LAYER_CHANGE\n;8\n",
    ] {
        assert!(g.contains(line), "missing {line:?}");
    }
    let total = format!("; filament used [mm] = {:.2}\n", job.summary.filament_mm);
    assert!(g.contains(&total));
    let replayed: f64 = replay(g)
        .moves
        .iter()
        .filter(|mv| mv.xy_len() > 0.0)
        .map(|mv| mv.e)
        .sum();
    assert!((replayed - job.summary.filament_mm).abs() < 0.01);
    assert!(g.contains("; estimated printing time (normal mode) = "));
    assert!(
        job.summary.estimated_time_s > 600.0,
        "{}",
        job.summary.estimated_time_s
    );
}

#[test]
fn the_job_keeps_the_bed_on_and_turns_the_nozzle_off() {
    let m = machine(Kinematics::CoreXy, 250.0);
    let job = generate(&m, &Options::default()).expect("fits");
    let tail: Vec<&str> = job
        .gcode
        .lines()
        .skip_while(|l| !l.starts_with("; end"))
        .collect();
    assert!(tail.contains(&"M104 S0"));
    assert!(!tail
        .iter()
        .any(|l| l.starts_with("M140") || l.starts_with("M190")));
    assert!(!job.gcode.contains("PRINT_END"));
    assert!(job.gcode.contains("SET_VELOCITY_LIMIT ACCEL=800\n"));
    assert!(job.gcode.contains("\nM83\n") && job.gcode.contains("\nG90\n"));
}

#[test]
fn a_printer_with_print_start_gets_the_macro_with_both_temperatures() {
    let mut m = machine(Kinematics::CoreXy, 250.0);
    m.start_macro = Some("PRINT_START".into());
    let job = generate(&m, &Options::default()).expect("fits");
    assert!(job.gcode.contains("\nPRINT_START BED=80 EXTRUDER=240\n"));
    assert!(!job.gcode.contains("\nG28\n"));
    // The macro the printer has, by its name (issue 9 item 15: 67 real configs call it
    // START_PRINT).
    m.start_macro = Some("START_PRINT".into());
    let job = generate(&m, &Options::default()).expect("fits");
    assert!(job.gcode.contains("\nSTART_PRINT BED=80 EXTRUDER=240\n"));
    assert!(!job.gcode.contains("PRINT_START"));
    m.start_macro = None;
    let job = generate(&m, &Options::default()).expect("fits");
    assert!(!job.gcode.contains("PRINT_START"));
    let heat = job.gcode.find("M109 S240").unwrap_or(usize::MAX);
    let first_object = job.gcode.find("EXCLUDE_OBJECT_START").unwrap_or(0);
    assert!(job.gcode.contains("\nG28\n") && heat < first_object);
}

#[test]
fn full_layout_on_120_mm_says_which_layout_to_use() {
    let m = machine(Kinematics::CoreXy, 120.0);
    let o = Options {
        layout: LayoutKind::Full,
        ..Options::default()
    };
    match generate(&m, &o) {
        Err(Error::DoesNotFit { message: text, .. }) => {
            assert!(text.contains("--layout paper"), "{text}");
            assert!(text.contains("by ") || text.contains("overlap"), "{text}");
        }
        Ok(_) => panic!("four 150 mm groups cannot fit a 120 mm bed"),
        Err(other) => panic!("{other}"),
    }
}

#[test]
fn a_bed_soak_dwells_after_the_bed_heats_and_counts_in_the_estimate() {
    for start_macro in [None, Some("PRINT_START".to_string())] {
        let mut m = machine(Kinematics::CoreXy, 250.0);
        m.start_macro = start_macro.clone();
        let plain = generate(&m, &Options::default()).expect("fits");
        let o = Options {
            bed_soak_s: 600.0,
            ..Options::default()
        };
        let soaked = generate(&m, &o).expect("fits");
        let g = &soaked.gcode;
        let (bed, dwell, nozzle) = (
            g.find("M190 S80").unwrap_or(usize::MAX),
            g.find("G4 P600000").unwrap_or(usize::MAX),
            g.find("M109 S240").unwrap_or(usize::MAX),
        );
        assert!(bed < dwell && dwell < nozzle, "{start_macro:?}");
        let added = soaked.summary.estimated_time_s - plain.summary.estimated_time_s;
        assert!((added - 600.0).abs() < 1e-6, "{added}");
    }
}
