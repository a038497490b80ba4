//! PURE: Klipper's backlash compensation as klipcal meets it. Mainline Klipper has none; two
//! branches do: PR 7259 (dmbutyugin, the seed's, shared/seeds/004) with `[backlash_compensation]`
//! `x_backlash`/`y_backlash`/`z_backlash` (≥ 0) and `smooth_time` (default 0.005, ≤ 0.1),
//! the `SET_BACKLASH_COMPENSATION` command answering
//! `x_backlash:<v> y_backlash:<v> z_backlash:<v> smooth_time:<v>` and no status object; and
//! PR 7157 with `[backlash]` `x`/`y`/`z`, or `a`/`b`/`z` under `kinematics: corexy`, with no
//! command and no status. Here: which one a printer has, the command from typed values, its
//! reply parsed, the dual-carriage `[delayed_gcode]` include of the seed, and the config values
//! to edit. No I/O.

use std::collections::BTreeMap;

use serde::{Deserialize, Serialize};
use serde_json::Value;

use super::gcode_cmd::{format_num, GcodeCmd};
use super::Error;

/// The command PR 7259 registers.
pub const SET_CMD: &str = "SET_BACKLASH_COMPENSATION";
/// PR 7259's section.
pub const SEED_SECTION: &str = "backlash_compensation";
/// PR 7157's section.
pub const PR7157_SECTION: &str = "backlash";
/// PR 7259's run-time limit on SMOOTH_TIME, s.
pub const MAX_SMOOTH_TIME_S: f64 = 0.1;

/// Which backlash compensation the printer's Klipper has.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case", tag = "branch")]
pub enum Branch {
    /// PR 7259: `[backlash_compensation]` + `SET_BACKLASH_COMPENSATION`.
    Seed,
    /// PR 7157: `[backlash]` (config only); `corexy` when it compensates motors A/B.
    Pr7157 {
        /// `kinematics: corexy` in `[backlash]`.
        corexy: bool,
    },
    /// Neither.
    Neither,
}

/// What detection found, with the words a user reads.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Detection {
    /// The branch.
    #[serde(flatten)]
    pub branch: Branch,
    /// The config has a `[dual_carriage]` (PR 7259 then refuses non-zero config values).
    pub dual_carriage: bool,
    /// Why, or what Klipper lacks.
    pub why: String,
}

impl Detection {
    /// Whether values can be applied at all.
    pub fn can_apply(&self) -> bool {
        self.branch != Branch::Neither
    }
}

/// Detects the branch from Moonraker's `printer.gcode.help` answer (an object keyed by
/// command) and `configfile.config` (section → options as written).
///
/// # Errors
/// [`Error::Settings`] when the help answer is not a JSON object.
pub fn detect(help: &Value, cfg: &super::RawConfig) -> Result<Detection, Error> {
    let help = help.as_object().ok_or_else(|| {
        Error::Settings("printer.gcode.help: expected an object of commands".into())
    })?;
    let has_cmd = help.keys().any(|k| k.eq_ignore_ascii_case(SET_CMD));
    let dual_carriage = cfg.contains_key("dual_carriage");
    let det = |branch, why: String| Detection {
        branch,
        dual_carriage,
        why,
    };
    if has_cmd {
        return Ok(det(
            Branch::Seed,
            "SET_BACKLASH_COMPENSATION is registered: the [backlash_compensation] module of \
             Klipper PR 7259 (dmbutyugin's branch)"
                .into(),
        ));
    }
    if let Some(sec) = cfg.get(PR7157_SECTION) {
        let kin = sec
            .get("kinematics")
            .map_or("cartesian", String::as_str)
            .trim()
            .to_ascii_lowercase();
        return Ok(det(
            Branch::Pr7157 {
                corexy: kin == "corexy",
            },
            format!(
                "the config has a [backlash] section (Klipper PR 7157, kinematics {kin}): \
                 values are set in the config and take effect after a restart"
            ),
        ));
    }
    Ok(det(
        Branch::Neither,
        "Klipper has no SET_BACKLASH_COMPENSATION command (the [backlash_compensation] module \
         of Klipper PR 7259) and the config has no [backlash] section (Klipper PR 7157); \
         mainline Klipper has no backlash compensation. klipcal measures and reports; to \
         apply, run one of those branches and add its section"
            .into(),
    ))
}

/// Values for `SET_BACKLASH_COMPENSATION`; `None` leaves a value as it is.
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize)]
pub struct SetBacklash {
    /// X_BACKLASH, mm (≥ 0).
    pub x_mm: Option<f64>,
    /// Y_BACKLASH, mm (≥ 0).
    pub y_mm: Option<f64>,
    /// Z_BACKLASH, mm (≥ 0).
    pub z_mm: Option<f64>,
    /// SMOOTH_TIME, s (0..0.1).
    pub smooth_time_s: Option<f64>,
}

fn check_range(name: &str, v: f64, lo: f64, hi: f64) -> Result<(), Error> {
    if v.is_finite() && v >= lo && v <= hi {
        Ok(())
    } else {
        Err(Error::Backlash(format!(
            "{name}={v}; expected a number from {lo} to {hi}"
        )))
    }
}

/// The `SET_BACKLASH_COMPENSATION …` line (PR 7259's parameter names and limits).
///
/// # Errors
/// [`Error::Backlash`] for a negative or non-finite backlash, a SMOOTH_TIME outside 0..0.1 s,
/// or no value at all (the bare command only reports).
pub fn set_backlash_command(v: &SetBacklash) -> Result<String, Error> {
    let mut cmd = GcodeCmd::new(SET_CMD);
    let mut any = false;
    for (key, val) in [
        ("X_BACKLASH", v.x_mm),
        ("Y_BACKLASH", v.y_mm),
        ("Z_BACKLASH", v.z_mm),
    ] {
        if let Some(mm) = val {
            check_range(key, mm, 0.0, 10.0)?;
            cmd = cmd.num(key, mm);
            any = true;
        }
    }
    if let Some(t) = v.smooth_time_s {
        check_range("SMOOTH_TIME", t, 0.0, MAX_SMOOTH_TIME_S)?;
        cmd = cmd.num("SMOOTH_TIME", t);
        any = true;
    }
    if !any {
        return Err(Error::Backlash(
            "no value to set; expected at least one of X_BACKLASH, Y_BACKLASH, Z_BACKLASH, \
             SMOOTH_TIME"
                .into(),
        ));
    }
    cmd.build()
}

/// PR 7259's answer to `SET_BACKLASH_COMPENSATION`.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct BacklashReply {
    /// x_backlash, mm.
    pub x_mm: f64,
    /// y_backlash, mm.
    pub y_mm: f64,
    /// z_backlash, mm.
    pub z_mm: f64,
    /// smooth_time, s.
    pub smooth_time_s: f64,
}

impl BacklashReply {
    /// Whether every value `want` sets reads back (within 1e-6).
    pub fn agrees_with(&self, want: &SetBacklash) -> bool {
        let same = |got: f64, w: Option<f64>| w.map_or(true, |w| (got - w).abs() <= 1e-6);
        same(self.x_mm, want.x_mm)
            && same(self.y_mm, want.y_mm)
            && same(self.z_mm, want.z_mm)
            && same(self.smooth_time_s, want.smooth_time_s)
    }
}

/// Parses the reply line (console lines may carry Klipper's `// ` prefix; the last matching
/// line of `text` wins).
///
/// # Errors
/// [`Error::Backlash`] when no line has all of `x_backlash:`, `y_backlash:`, `z_backlash:`
/// and `smooth_time:` with numbers.
pub fn parse_reply(text: &str) -> Result<BacklashReply, Error> {
    let parse_line = |line: &str| -> Option<BacklashReply> {
        let line = line.trim().trim_start_matches("//").trim();
        let mut m: BTreeMap<&str, f64> = BTreeMap::new();
        for tok in line.split_whitespace() {
            let (k, v) = tok.split_once(':')?;
            m.insert(k, v.parse().ok().filter(|x: &f64| x.is_finite())?);
        }
        Some(BacklashReply {
            x_mm: *m.get("x_backlash")?,
            y_mm: *m.get("y_backlash")?,
            z_mm: *m.get("z_backlash")?,
            smooth_time_s: *m.get("smooth_time")?,
        })
    };
    text.lines().rev().find_map(parse_line).ok_or_else(|| {
        Error::Backlash(format!(
            "no SET_BACKLASH_COMPENSATION reply in {text:?}; expected \
             'x_backlash:<mm> y_backlash:<mm> z_backlash:<mm> smooth_time:<s>'"
        ))
    })
}

/// A carriage and its values, for the dual-carriage include.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct CarriageBacklash {
    /// The name `SET_DUAL_CARRIAGE CARRIAGE=` takes.
    pub carriage: String,
    /// What `SET_BACKLASH_COMPENSATION` sets while it is the active carriage.
    pub values: SetBacklash,
}

/// The name of the klipcal-managed include for a dual-carriage printer with PR 7259.
pub const DUAL_CARRIAGE_INCLUDE: &str = "klipcal_backlash.cfg";

/// The klipcal-managed include for a dual-carriage printer with PR 7259 (the seed's recipe:
/// non-zero values cannot sit in `[backlash_compensation]` there, so a `[delayed_gcode]`
/// selects each carriage and sets its values, the primary last so it is active after start).
///
/// # Errors
/// A carriage name outside `[A-Za-z0-9_.-]`, or a value [`set_backlash_command`] refuses.
pub fn dual_carriage_include(
    primary: &CarriageBacklash,
    dual: &CarriageBacklash,
) -> Result<String, Error> {
    let select = |c: &CarriageBacklash| {
        GcodeCmd::new("SET_DUAL_CARRIAGE")
            .word("CARRIAGE", &c.carriage)
            .build()
    };
    Ok(format!(
        "# Written by klipcal (backlash): per-carriage backlash compensation for Klipper PR 7259.\n\
         # With dual_carriage, [backlash_compensation] must hold no non-zero values; each\n\
         # carriage is selected and set here, the primary last. Managed file: edits are replaced.\n\
         [delayed_gcode klipcal_backlash]\n\
         initial_duration: 0.1\n\
         gcode:\n  {}\n  {}\n  {}\n  {}\n",
        select(dual)?,
        set_backlash_command(&dual.values)?,
        select(primary)?,
        set_backlash_command(&primary.values)?,
    ))
}

/// The `(section, key, value)` triples to edit in place for `values` (axis → mm), plus
/// `smooth_time` for PR 7259. Axes: x, y, z for PR 7259 and cartesian PR 7157; a, b, z for
/// PR 7157 on corexy.
///
/// # Errors
/// [`Error::Backlash`] for Neither, an axis the branch has no key for, or a bad number.
pub fn config_values(
    branch: Branch,
    values: &BTreeMap<String, f64>,
    smooth_time_s: Option<f64>,
) -> Result<Vec<(String, String, String)>, Error> {
    let (section, keys, suffix): (&str, &[&str], &str) = match branch {
        Branch::Seed => (SEED_SECTION, &["x", "y", "z"], "_backlash"),
        Branch::Pr7157 { corexy: false } => (PR7157_SECTION, &["x", "y", "z"], ""),
        Branch::Pr7157 { corexy: true } => (PR7157_SECTION, &["a", "b", "z"], ""),
        Branch::Neither => {
            return Err(Error::Backlash(
                "Klipper has no backlash compensation module; nothing to write".into(),
            ))
        }
    };
    let mut out = Vec::new();
    for (axis, mm) in values {
        if !keys.contains(&axis.as_str()) {
            return Err(Error::Backlash(format!(
                "[{section}] has no key for axis {axis}; expected one of {}",
                keys.join(", ")
            )));
        }
        check_range(axis, *mm, 0.0, 10.0)?;
        out.push((
            section.to_string(),
            format!("{axis}{suffix}"),
            format_num(*mm, 4)?,
        ));
    }
    if let Some(t) = smooth_time_s {
        if branch != Branch::Seed {
            return Err(Error::Backlash(
                "smooth_time exists only in PR 7259's [backlash_compensation]".into(),
            ));
        }
        if !(t.is_finite() && t > 0.0 && t <= MAX_SMOOTH_TIME_S) {
            return Err(Error::Backlash(format!(
                "smooth_time {t}; expected above 0 and at most 0.1 s"
            )));
        }
        out.push((section.to_string(), "smooth_time".into(), format_num(t, 4)?));
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;
    use serde_json::json;

    #[test]
    fn detection_tells_the_seed_branch_pr_7157_and_neither_apart() {
        let help =
            json!({"G28": "", "SET_BACKLASH_COMPENSATION": "Set backlash compensation parameters"});
        let raw = |v: Value| -> super::super::RawConfig { serde_json::from_value(v).unwrap() };
        let d = detect(
            &help,
            &raw(json!({"backlash_compensation": {"x_backlash": "0"}})),
        )
        .unwrap();
        assert_eq!(d.branch, Branch::Seed);
        let cfg = raw(json!({"backlash": {"kinematics": "corexy", "a": "0.0"}}));
        let d = detect(&json!({"G28": ""}), &cfg).unwrap();
        assert_eq!(d.branch, Branch::Pr7157 { corexy: true });
        let d = detect(&json!({"G28": ""}), &raw(json!({"backlash": {"x": "0"}}))).unwrap();
        assert_eq!(d.branch, Branch::Pr7157 { corexy: false });
        let d = detect(&json!({"G28": ""}), &raw(json!({"dual_carriage": {}}))).unwrap();
        assert_eq!(d.branch, Branch::Neither);
        assert!(d.dual_carriage && !d.can_apply());
        assert!(
            d.why.contains("PR 7259") && d.why.contains("PR 7157"),
            "{}",
            d.why
        );
        assert!(detect(&json!([]), &raw(json!({}))).is_err());
    }

    #[test]
    fn the_command_is_built_from_typed_values_within_pr_7259_limits() {
        // The seed's example: SET_BACKLASH_COMPENSATION X_BACKLASH=0.02 Y_BACKLASH=0.03 SMOOTH_TIME=0.005
        let v = SetBacklash {
            x_mm: Some(0.02),
            y_mm: Some(0.03),
            z_mm: None,
            smooth_time_s: Some(0.005),
        };
        assert_eq!(
            set_backlash_command(&v).unwrap(),
            "SET_BACKLASH_COMPENSATION X_BACKLASH=0.02 Y_BACKLASH=0.03 SMOOTH_TIME=0.005"
        );
        for (bad, needle) in [
            (
                SetBacklash {
                    x_mm: Some(-0.01),
                    ..v
                },
                "X_BACKLASH=-0.01",
            ),
            (
                SetBacklash {
                    smooth_time_s: Some(0.2),
                    ..v
                },
                "SMOOTH_TIME=0.2",
            ),
            (
                SetBacklash {
                    y_mm: Some(f64::NAN),
                    ..v
                },
                "Y_BACKLASH=NaN",
            ),
            (SetBacklash::default(), "no value to set"),
        ] {
            let e = set_backlash_command(&bad).unwrap_err().to_string();
            assert!(e.contains(needle), "{e}");
        }
    }

    #[test]
    fn the_reply_is_parsed_and_compared() {
        let text = "SET_BACKLASH_COMPENSATION X_BACKLASH=0.08\n\
                    // x_backlash:0.08 y_backlash:0.0 z_backlash:0.0 smooth_time:0.005000";
        let r = parse_reply(text).unwrap();
        assert_eq!(r.x_mm, 0.08);
        assert_eq!(r.smooth_time_s, 0.005);
        assert!(r.agrees_with(&SetBacklash {
            x_mm: Some(0.08),
            ..SetBacklash::default()
        }));
        assert!(!r.agrees_with(&SetBacklash {
            y_mm: Some(0.05),
            ..SetBacklash::default()
        }));
        assert!(parse_reply("// x_backlash:0.1 y_backlash:0.1").is_err());
    }

    #[test]
    fn the_dual_carriage_include_follows_the_seed_recipe() {
        let c = |name: &str, x: f64| CarriageBacklash {
            carriage: name.into(),
            values: SetBacklash {
                x_mm: Some(x),
                y_mm: Some(0.05),
                z_mm: None,
                smooth_time_s: Some(0.005),
            },
        };
        let text = dual_carriage_include(&c("0", 0.015), &c("1", 0.02)).unwrap();
        let gcode: Vec<&str> = text
            .lines()
            .skip_while(|l| *l != "gcode:")
            .skip(1)
            .map(str::trim)
            .collect();
        assert_eq!(
            gcode,
            [
                "SET_DUAL_CARRIAGE CARRIAGE=1",
                "SET_BACKLASH_COMPENSATION X_BACKLASH=0.02 Y_BACKLASH=0.05 SMOOTH_TIME=0.005",
                "SET_DUAL_CARRIAGE CARRIAGE=0",
                "SET_BACKLASH_COMPENSATION X_BACKLASH=0.015 Y_BACKLASH=0.05 SMOOTH_TIME=0.005",
            ]
        );
        assert!(text.contains("[delayed_gcode klipcal_backlash]\ninitial_duration: 0.1\n"));
        let bad = c("a b", 0.0);
        assert!(dual_carriage_include(&bad, &bad).is_err());
    }

    #[test]
    fn config_values_use_each_branchs_keys() {
        let v: BTreeMap<String, f64> = [("x".to_string(), 0.08), ("y".to_string(), 0.05)].into();
        let seed = config_values(Branch::Seed, &v, Some(0.005)).unwrap();
        assert_eq!(
            seed,
            [
                (
                    "backlash_compensation".into(),
                    "x_backlash".into(),
                    "0.08".into()
                ),
                (
                    "backlash_compensation".into(),
                    "y_backlash".into(),
                    "0.05".into()
                ),
                (
                    "backlash_compensation".into(),
                    "smooth_time".into(),
                    "0.005".into()
                ),
            ]
        );
        let e = config_values(Branch::Pr7157 { corexy: true }, &v, None).unwrap_err();
        assert!(e.to_string().contains("expected one of a, b, z"), "{e}");
        let ab: BTreeMap<String, f64> = [("a".to_string(), 0.1)].into();
        assert_eq!(
            config_values(Branch::Pr7157 { corexy: true }, &ab, None).unwrap()[0],
            ("backlash".into(), "a".into(), "0.1".into())
        );
        assert!(config_values(Branch::Neither, &v, None).is_err());
        assert!(config_values(Branch::Pr7157 { corexy: false }, &v, Some(0.005)).is_err());
    }
}
