//! PURE: Klipper bed-mesh profiles — read every `[bed_mesh NAME]` section of a loaded
//! [`Config`] as `klippy/extras/bed_mesh.py` (`ProfileManager`) does, write profiles into the
//! SAVE_CONFIG block as `ProfileManager.save_profile` + `configfile` write them, and recognise
//! VGB's `COLDxx.x` / `HOTxx.x` / `TESTxx.x` profiles. Never touches files.

use super::config::{Config, Section, SAVE_CONFIG_MARKER};
use super::gcode_cmd::GcodeCmd;
use super::Error;

/// `bed_mesh.PROFILE_VERSION`: profiles with another version are ignored by Klipper.
pub const PROFILE_VERSION: i64 = 1;
/// Prefix of the profiles klipcal owns; all others are the user's and are never touched.
pub const KLIPCAL_PREFIX: &str = "klipcal_";

/// `bed_mesh.PROFILE_OPTIONS`, in the order Klipper writes them (the same names as the
/// `mesh_params` of Klipper's `bed_mesh` status).
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct MeshParams {
    /// Probed points along X.
    pub x_count: usize,
    /// Probed points along Y.
    pub y_count: usize,
    /// Interpolated points per segment along X.
    pub mesh_x_pps: usize,
    /// Interpolated points per segment along Y.
    pub mesh_y_pps: usize,
    /// `lagrange` or `bicubic`.
    pub algo: String,
    /// Bicubic tension.
    pub tension: f64,
    /// Mesh extent, mm.
    pub min_x: f64,
    /// Mesh extent, mm.
    pub max_x: f64,
    /// Mesh extent, mm.
    pub min_y: f64,
    /// Mesh extent, mm.
    pub max_y: f64,
}

/// One bed-mesh profile: its name (after `bed_mesh `), parameters and probed points
/// (`points_mm[row y][column x]`, z relative to the probe's reference).
#[derive(Debug, Clone, PartialEq)]
pub struct MeshProfile {
    /// Profile name, e.g. `COLD27.3` or `klipcal_31.25`.
    pub name: String,
    /// Mesh parameters.
    pub params: MeshParams,
    /// Probed z, mm, `y_count` rows of `x_count` values.
    pub points_mm: Vec<Vec<f64>>,
}

impl MeshProfile {
    /// The points row-major (y rows, x columns) in one vector.
    #[must_use]
    pub fn flat_mm(&self) -> Vec<f64> {
        self.points_mm.iter().flatten().copied().collect()
    }
}

/// What a VGB profile name says.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum VgbKind {
    /// `COLDxx.x`: the cold reference mesh.
    Cold,
    /// `HOTxx.x`: the hot reference mesh.
    Hot,
    /// `TESTxx.x`: a check mesh, judged and never fitted.
    Test,
}

fn bad(section: &str, key: &str, value: &str, expected: &str) -> Error {
    Error::BadValue {
        section: section.into(),
        key: key.into(),
        value: value.into(),
        expected: expected.into(),
    }
}

fn get<'a>(s: &'a Section, key: &str) -> Result<&'a str, Error> {
    s.option(key)
        .map(|o| o.value.as_str())
        .ok_or_else(|| Error::MissingOption {
            section: s.name.clone(),
            key: key.into(),
            expected: "every bed_mesh profile option Klipper writes (version, points, x_count, y_count, mesh_x_pps, mesh_y_pps, algo, tension, min_x, max_x, min_y, max_y)".into(),
        })
}

fn get_f(s: &Section, key: &str) -> Result<f64, Error> {
    let v = get(s, key)?;
    v.trim()
        .parse::<f64>()
        .ok()
        .filter(|x| x.is_finite())
        .ok_or_else(|| bad(&s.name, key, v, "a number"))
}

fn get_u(s: &Section, key: &str) -> Result<usize, Error> {
    let v = get(s, key)?;
    v.trim()
        .parse::<usize>()
        .ok()
        .filter(|&n| n >= 1)
        .ok_or_else(|| bad(&s.name, key, v, "a positive whole number"))
}

/// Parses one `[bed_mesh NAME]` section. `Ok(None)` when its `version` is not
/// [`PROFILE_VERSION`] (Klipper ignores such profiles too).
///
/// # Errors
/// A missing option, a value that is not a number, or points that do not form
/// `y_count` rows of `x_count` values.
pub fn parse_profile(s: &Section) -> Result<Option<MeshProfile>, Error> {
    let name = s
        .name
        .strip_prefix("bed_mesh ")
        .ok_or_else(|| Error::Settings(format!("[{}] is not a bed_mesh profile", s.name)))?
        .to_string();
    let version = s
        .option("version")
        .map_or(Ok(0), |o| o.value.trim().parse::<i64>())
        .map_err(|_| bad(&s.name, "version", get(s, "version").unwrap_or(""), "1"))?;
    if version != PROFILE_VERSION {
        return Ok(None);
    }
    let params = MeshParams {
        x_count: get_u(s, "x_count")?,
        y_count: get_u(s, "y_count")?,
        mesh_x_pps: get(s, "mesh_x_pps")?.trim().parse().map_err(|_| {
            bad(
                &s.name,
                "mesh_x_pps",
                get(s, "mesh_x_pps").unwrap_or(""),
                "a whole number",
            )
        })?,
        mesh_y_pps: get(s, "mesh_y_pps")?.trim().parse().map_err(|_| {
            bad(
                &s.name,
                "mesh_y_pps",
                get(s, "mesh_y_pps").unwrap_or(""),
                "a whole number",
            )
        })?,
        algo: get(s, "algo")?.trim().to_string(),
        tension: get_f(s, "tension")?,
        min_x: get_f(s, "min_x")?,
        max_x: get_f(s, "max_x")?,
        min_y: get_f(s, "min_y")?,
        max_y: get_f(s, "max_y")?,
    };
    // configfile.getlists(seps=(',', '\n')): lines, then comma-separated values; empty parts dropped.
    let raw = get(s, "points")?;
    let mut rows = Vec::new();
    for line in raw.split('\n').map(str::trim).filter(|l| !l.is_empty()) {
        let mut row = Vec::new();
        for part in line.split(',').map(str::trim).filter(|p| !p.is_empty()) {
            let z: f64 = part
                .parse()
                .ok()
                .filter(|z: &f64| z.is_finite())
                .ok_or_else(|| bad(&s.name, "points", part, "comma-separated numbers in mm"))?;
            row.push(z);
        }
        rows.push(row);
    }
    if rows.len() != params.y_count || rows.iter().any(|r| r.len() != params.x_count) {
        let shape: Vec<String> = rows.iter().map(|r| r.len().to_string()).collect();
        return Err(bad(
            &s.name,
            "points",
            &format!("{} rows of [{}] values", rows.len(), shape.join(", ")),
            &format!(
                "{} rows (y_count) of {} values (x_count)",
                params.y_count, params.x_count
            ),
        ));
    }
    Ok(Some(MeshProfile {
        name,
        params,
        points_mm: rows,
    }))
}

/// Every compatible `[bed_mesh NAME]` profile of the config, in config order.
///
/// # Errors
/// The first profile that cannot be read, naming it.
pub fn profiles(cfg: &Config) -> Result<Vec<MeshProfile>, Error> {
    let mut out = Vec::new();
    for s in cfg.sections() {
        if s.name.starts_with("bed_mesh ") {
            if let Some(p) = parse_profile(s)? {
                out.push(p);
            }
        }
    }
    Ok(out)
}

/// The mesh parameters as `(option, value)` in Klipper's words and order.
fn param_words(m: &MeshParams) -> [(&'static str, String); 10] {
    [
        ("x_count", m.x_count.to_string()),
        ("y_count", m.y_count.to_string()),
        ("mesh_x_pps", m.mesh_x_pps.to_string()),
        ("mesh_y_pps", m.mesh_y_pps.to_string()),
        ("algo", m.algo.clone()),
        ("tension", py_float(m.tension)),
        ("min_x", py_float(m.min_x)),
        ("max_x", py_float(m.max_x)),
        ("min_y", py_float(m.min_y)),
        ("max_y", py_float(m.max_y)),
    ]
}

/// Checks that every profile has the same mesh parameters as the first (VGB's generator
/// copied the first profile's and produced wrong-sized meshes when they differed).
///
/// # Errors
/// The first profile that differs, naming it, each option that differs with both values,
/// and what is expected.
pub fn check_same_params(profiles: &[&MeshProfile]) -> Result<(), Error> {
    let Some(first) = profiles.first() else {
        return Ok(());
    };
    let want = param_words(&first.params);
    for p in &profiles[1..] {
        let diff: Vec<String> = param_words(&p.params)
            .iter()
            .zip(&want)
            .filter(|(a, b)| a.1 != b.1)
            .map(|((k, v), (_, w))| format!("{k} = {v} where {} has {k} = {w}", first.name))
            .collect();
        if !diff.is_empty() {
            return Err(Error::MeshProfiles(format!(
                "[bed_mesh {}] has {}; expected every profile used together to be probed with \
                 the same [bed_mesh] settings (take {} again with the settings {} was taken with)",
                p.name,
                diff.join(", "),
                p.name,
                first.name
            )));
        }
    }
    Ok(())
}

/// Why a profile is not one of VGB's (`None` when it is): klipcal's own, a VGB-like name
/// in the wrong case or without a temperature, or another name.
#[must_use]
pub fn vgb_ignored_why(name: &str) -> Option<String> {
    if vgb_kind(name).is_some() {
        return None;
    }
    if name.starts_with(KLIPCAL_PREFIX) {
        return Some("klipcal's own profile".into());
    }
    let upper = name.to_ascii_uppercase();
    for kind in ["COLD", "HOT", "TEST"] {
        if let Some(rest) = upper.strip_prefix(kind) {
            if vgb_kind(&upper).is_some() {
                return Some(format!(
                    "VGB's names are upper case: expected {kind}{}",
                    &name[kind.len()..]
                ));
            }
            return Some(format!(
                "'{}' after {kind} is not a frame temperature: expected {kind} then °C from \
                 -50 to 200, e.g. {kind}31.2",
                &name[name.len() - rest.len()..]
            ));
        }
    }
    Some("not a VGB name (COLDxx.x, HOTxx.x or TESTxx.x)".into())
}

/// The VGB kind and temperature of a profile named `COLDxx.x`, `HOTxx.x` or `TESTxx.x`.
#[must_use]
pub fn vgb_kind(name: &str) -> Option<(VgbKind, f64)> {
    let (kind, rest) = if let Some(r) = name.strip_prefix("COLD") {
        (VgbKind::Cold, r)
    } else if let Some(r) = name.strip_prefix("HOT") {
        (VgbKind::Hot, r)
    } else if let Some(r) = name.strip_prefix("TEST") {
        (VgbKind::Test, r)
    } else {
        return None;
    };
    let t: f64 = rest.parse().ok()?;
    (t.is_finite() && (-50.0..=200.0).contains(&t)).then_some((kind, t))
}

/// Python's `str(float)` for the values Klipper writes (`20.0`, `0.2`, `280.5`).
fn py_float(x: f64) -> String {
    if x.fract() == 0.0 && x.abs() < 1e15 {
        format!("{x:.1}")
    } else {
        format!("{x}")
    }
}

/// The profile as SAVE_CONFIG writes it (`#*# ` lines, no trailing blank line): version,
/// points (`"%.6f"` values, each row on its own `\t  ` line), then the mesh parameters.
#[must_use]
pub fn format_profile(p: &MeshProfile) -> String {
    let mut out = format!(
        "#*# [bed_mesh {}]\n#*# version = {PROFILE_VERSION}\n#*# points =\n",
        p.name
    );
    for row in &p.points_mm {
        let vals: Vec<String> = row.iter().map(|z| format!("{z:.6}")).collect();
        out.push_str(&format!("#*# \t  {}\n", vals.join(", ")));
    }
    for (k, v) in param_words(&p.params) {
        out.push_str(&format!("#*# {k} = {v}\n"));
    }
    out
}

/// The G-code script that loads profile `name` and, when `offset_mm` (X, Y) is not zero, sets
/// `BED_MESH_OFFSET` again right after: `BED_MESH_PROFILE LOAD=` builds a new mesh whose
/// offsets are zero. One script, so Klipper runs nothing between the two lines.
///
/// # Errors
/// A name outside `[A-Za-z0-9_.-]`, or an offset that is not a finite number.
pub fn load_script(name: &str, offset_mm: (f64, f64)) -> Result<String, Error> {
    let load = GcodeCmd::new("BED_MESH_PROFILE")
        .word("LOAD", name)
        .build()?;
    if offset_mm == (0.0, 0.0) {
        return Ok(load);
    }
    let offset = GcodeCmd::new("BED_MESH_OFFSET")
        .num("X", offset_mm.0)
        .num("Y", offset_mm.1)
        .build()?;
    Ok(format!("{load}\n{offset}"))
}

/// The names of the `[bed_mesh klipcal_*]` profiles in printer.cfg's SAVE_CONFIG block (the
/// ones [`replace_klipcal_profiles`] replaces), in file order.
#[must_use]
pub fn klipcal_profile_names(text: &str) -> Vec<String> {
    let Some(i) = text.find(&format!("\n{SAVE_CONFIG_MARKER}\n")) else {
        return Vec::new();
    };
    text[i..]
        .lines()
        .filter_map(|l| {
            let name = l
                .strip_prefix("#*# [bed_mesh ")?
                .trim_end()
                .strip_suffix(']')?;
            name.starts_with(KLIPCAL_PREFIX).then(|| name.to_string())
        })
        .collect()
}

/// The printer.cfg text with every `[bed_mesh klipcal_*]` profile of its SAVE_CONFIG block
/// replaced by `new` (the user's other sections kept byte for byte). A file without a block
/// gets Klipper's header appended.
///
/// # Errors
/// A profile in `new` whose name is not `klipcal_` + `[A-Za-z0-9_.-]`.
pub fn replace_klipcal_profiles(text: &str, new: &[MeshProfile]) -> Result<String, Error> {
    for p in new {
        let ok = p.name.starts_with(KLIPCAL_PREFIX)
            && p.name
                .chars()
                .all(|c| c.is_ascii_alphanumeric() || "_.-".contains(c));
        if !ok {
            return Err(Error::BadName {
                what: "bed_mesh profile".into(),
                name: p.name.clone(),
            });
        }
    }
    let (head, block) = match text.find(&format!("\n{SAVE_CONFIG_MARKER}\n")) {
        Some(i) => (&text[..=i], &text[i + 1..]),
        None => (text, ""),
    };
    let mut out = head.to_string();
    if block.is_empty() {
        if !out.ends_with('\n') {
            out.push('\n');
        }
        out.push_str(&format!(
            "{SAVE_CONFIG_MARKER}\n#*# DO NOT EDIT THIS BLOCK OR BELOW. The contents are auto-generated.\n#*#\n"
        ));
    } else {
        // Keep every line except those of klipcal's sections (header up to the next header).
        let mut skipping = false;
        for line in block.split_inclusive('\n') {
            if let Some(h) = line.trim_end().strip_prefix("#*# [") {
                skipping = h.starts_with(&format!("bed_mesh {KLIPCAL_PREFIX}"));
            }
            if !skipping {
                out.push_str(line);
            }
        }
        if !out.ends_with('\n') {
            out.push('\n');
        }
    }
    for p in new {
        if !out.ends_with("#*#\n") {
            out.push_str("#*#\n");
        }
        out.push_str(&format_profile(p));
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::klipper::MemFiles;
    use std::path::Path;

    const CFG: &str = "[printer]\nkinematics: none\n\n\
#*# <---------------------- SAVE_CONFIG ---------------------->\n\
#*# DO NOT EDIT THIS BLOCK OR BELOW. The contents are auto-generated.\n\
#*#\n\
#*# [bed_mesh COLD27.3]\n#*# version = 1\n#*# points =\n\
#*# \t0.010000, 0.020000\n#*# \t-0.010000, 0.000000\n\
#*# x_count = 2\n#*# y_count = 2\n#*# mesh_x_pps = 2\n#*# mesh_y_pps = 2\n\
#*# algo = lagrange\n#*# tension = 0.2\n#*# min_x = 20.0\n#*# max_x = 280.0\n\
#*# min_y = 20.0\n#*# max_y = 280.0\n#*#\n\
#*# [bed_mesh HOT36.6]\n#*# version = 1\n#*# points =\n\
#*# \t0.030000, 0.040000\n#*# \t-0.030000, 0.000000\n\
#*# x_count = 2\n#*# y_count = 2\n#*# mesh_x_pps = 2\n#*# mesh_y_pps = 2\n\
#*# algo = lagrange\n#*# tension = 0.2\n#*# min_x = 20.0\n#*# max_x = 280.0\n\
#*# min_y = 20.0\n#*# max_y = 250.0\n";

    fn load(text: &str) -> Config {
        let files = MemFiles::new().with("/c/printer.cfg", text);
        Config::load(&files, Path::new("/c/printer.cfg")).expect("config")
    }

    #[test]
    fn vgb_profiles_are_read_with_their_points_and_temperatures() {
        let ps = profiles(&load(CFG)).unwrap();
        assert_eq!(ps.len(), 2);
        assert_eq!(ps[0].points_mm, vec![vec![0.01, 0.02], vec![-0.01, 0.0]]);
        assert_eq!(vgb_kind(&ps[0].name), Some((VgbKind::Cold, 27.3)));
        assert_eq!(vgb_kind(&ps[1].name), Some((VgbKind::Hot, 36.6)));
        assert_eq!(vgb_kind("TEST31.2"), Some((VgbKind::Test, 31.2)));
        assert_eq!(vgb_kind("default"), None);
    }

    #[test]
    fn every_profiles_parameters_are_checked_not_only_the_first() {
        let ps = profiles(&load(CFG)).unwrap();
        let err = check_same_params(&ps.iter().collect::<Vec<_>>()).unwrap_err();
        assert!(err.to_string().contains("HOT36.6"), "{err}");
        assert!(err.to_string().contains("250"), "{err}");
    }

    #[test]
    fn differing_parameters_are_named_by_profile_and_option_in_klippers_words() {
        // Issue 26 B.5: no Rust struct, no Moonraker, the option and both values.
        let ps = profiles(&load(CFG)).unwrap();
        let err = check_same_params(&ps.iter().collect::<Vec<_>>())
            .unwrap_err()
            .to_string();
        assert!(
            err.starts_with("[bed_mesh HOT36.6] has ") && err.contains("where COLD27.3 has"),
            "{err}"
        );
        assert!(
            !err.contains("MeshParams") && !err.contains("Moonraker") && !err.contains('{'),
            "{err}"
        );
        assert!(err.contains("expected every profile"), "{err}");
    }

    #[test]
    fn profiles_that_are_not_vgbs_say_why() {
        assert_eq!(vgb_ignored_why("HOT36"), None);
        assert_eq!(vgb_ignored_why("COLD27.3"), None);
        let why = vgb_ignored_why("cold27.3").unwrap();
        assert!(
            why.contains("upper case") && why.contains("COLD27.3"),
            "{why}"
        );
        let why = vgb_ignored_why("HOTabc").unwrap();
        assert!(why.contains("'abc'") && why.contains("HOT31.2"), "{why}");
        let why = vgb_ignored_why("HOT999").unwrap();
        assert!(why.contains("'999'"), "{why}");
        assert!(vgb_ignored_why("default")
            .unwrap()
            .contains("not a VGB name"));
        assert!(vgb_ignored_why("klipcal_30.00")
            .unwrap()
            .contains("klipcal"));
    }

    #[test]
    fn points_of_the_wrong_shape_are_refused_by_name() {
        let text = CFG.replace("#*# \t-0.010000, 0.000000\n", "#*# \t-0.010000\n");
        let err = profiles(&load(&text)).unwrap_err().to_string();
        assert!(
            err.contains("bed_mesh COLD27.3") && err.contains("2 rows"),
            "{err}"
        );
    }

    #[test]
    fn written_profiles_read_back_identically_and_replace_only_klipcal_ones() {
        let ps = profiles(&load(CFG)).unwrap();
        let mut mine = ps[0].clone();
        mine.name = "klipcal_30.00".into();
        mine.points_mm[1][0] = -0.0123456;
        let once = replace_klipcal_profiles(CFG, &[mine.clone()]).unwrap();
        let twice = replace_klipcal_profiles(&once, &[mine.clone()]).unwrap();
        assert_eq!(once, twice, "rewriting replaces, never duplicates");
        assert!(
            once.starts_with(CFG),
            "the user's block is kept byte for byte"
        );
        let back = profiles(&load(&once)).unwrap();
        let got = back.iter().find(|p| p.name == "klipcal_30.00").unwrap();
        assert_eq!(got.params, mine.params);
        assert_eq!(got.points_mm[1][0], -0.012346, "%.6f as Klipper writes");
        let cleared = replace_klipcal_profiles(&once, &[]).unwrap();
        assert_eq!(profiles(&load(&cleared)).unwrap().len(), 2);
    }

    #[test]
    fn a_file_without_a_block_gets_klippers_header() {
        let ps = profiles(&load(CFG)).unwrap();
        let mut mine = ps[0].clone();
        mine.name = "klipcal_25.50".into();
        let out = replace_klipcal_profiles("[printer]\nkinematics: none\n", &[mine]).unwrap();
        let cfg = load(&out);
        assert_eq!(profiles(&cfg).unwrap()[0].name, "klipcal_25.50");
        assert!(out.contains("#*# min_x = 20.0\n#*# max_x = 280.0\n"));
    }

    #[test]
    fn foreign_names_are_refused() {
        let ps = profiles(&load(CFG)).unwrap();
        let err = replace_klipcal_profiles(CFG, &[ps[0].clone()]).unwrap_err();
        assert!(err.to_string().contains("COLD27.3"), "{err}");
    }

    #[test]
    fn a_load_sets_a_nonzero_offset_again_in_the_same_script() {
        assert_eq!(
            load_script("klipcal_30.00", (0.0, 0.0)).unwrap(),
            "BED_MESH_PROFILE LOAD=klipcal_30.00"
        );
        assert_eq!(
            load_script("klipcal_30.00", (5.0, -3.25)).unwrap(),
            "BED_MESH_PROFILE LOAD=klipcal_30.00\nBED_MESH_OFFSET X=5 Y=-3.25"
        );
        assert!(load_script("klipcal 30", (0.0, 0.0)).is_err());
        assert!(load_script("klipcal_30.00", (f64::NAN, 0.0)).is_err());
    }
}
