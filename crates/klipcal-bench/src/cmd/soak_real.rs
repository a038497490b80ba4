//! Bed traces from real printers' klippy.log files (`tests/fixtures/soak/real`): heat-ups and
//! target steps as Klipper's `Stats` lines logged them (1 Hz, `heater_bed: target temp pwm`),
//! each file's `# ` header naming its source, its heater's control and `max_power`, and whether
//! a print ran while the target was held. No true moment is known for them (a print runs in
//! each, and the power wanders with it), so what is checked is what must hold on any bed: no
//! declaration before the bed reached its band and settled, none while it is out of the band.
//! Reads files only through [`load_dir`]; the checks themselves are pure.

use std::path::Path;

use super::soak::{parse_trace, TraceSample};
use crate::calib::soak::{SoakDetector, SoakParams, SoakStatus};

/// Where the real traces live in the source tree.
pub(crate) const REAL_DIR: &str = concat!(
    env!("CARGO_MANIFEST_DIR"),
    "/../../tests/fixtures/soak/real"
);

/// One real trace and what its header says of the printer.
#[derive(Debug, Clone)]
pub(crate) struct RealTrace {
    /// The file's name without `.csv`.
    pub name: String,
    /// The samples, t_s from the target change.
    pub samples: Vec<TraceSample>,
    /// `[heater_bed] max_power` from the log's config dump (1.0 when not set).
    pub max_power: f64,
    /// `[heater_bed] control`: `pid` or `watermark`.
    pub control: String,
    /// The target change, e.g. `0 -> 70`.
    pub step: String,
    /// A print ran while the target was held.
    pub printing: bool,
}

/// The value of a `# key: value` header line.
fn header<'a>(text: &'a str, key: &str) -> Option<&'a str> {
    text.lines()
        .take_while(|l| l.starts_with('#'))
        .find_map(|l| l.strip_prefix("# ")?.strip_prefix(key)?.strip_prefix(':'))
        .map(str::trim)
}

/// Parses one real trace: the `# ` header (control, max_power, step, print during hold) and
/// the samples.
///
/// # Errors
/// A header line missing, or a sample line that does not parse; named with the file.
pub(crate) fn parse_real(name: &str, text: &str) -> Result<RealTrace, String> {
    let need = |key: &str| header(text, key).ok_or_else(|| format!("{name}: no `# {key}:` line"));
    let control = need("heater_bed control")?.to_string();
    let max_power = need("heater_bed max_power")?
        .split_whitespace()
        .next()
        .and_then(|v| v.parse::<f64>().ok())
        .filter(|v| (0.0..=1.0).contains(v) && *v > 0.0)
        .ok_or_else(|| format!("{name}: max_power is not a number in 0..1"))?;
    let step = need("step")?
        .split(" (")
        .next()
        .unwrap_or_default()
        .to_string();
    let printing = need("print_during_hold")?.starts_with("yes");
    let samples = parse_trace(text).map_err(|e| format!("{name}: {e}"))?;
    Ok(RealTrace {
        name: name.to_string(),
        samples,
        max_power,
        control,
        step,
        printing,
    })
}

/// Every `*.csv` in `dir`, parsed, by name.
///
/// # Errors
/// The folder or a file cannot be read, or a file does not parse.
pub(crate) fn load_dir(dir: &Path) -> Result<Vec<RealTrace>, String> {
    let entries = std::fs::read_dir(dir).map_err(|e| format!("{}: {e}", dir.display()))?;
    let mut paths: Vec<_> = entries
        .filter_map(Result::ok)
        .map(|e| e.path())
        .filter(|p| p.extension().is_some_and(|x| x == "csv"))
        .collect();
    paths.sort();
    paths
        .iter()
        .map(|p| {
            let text = std::fs::read_to_string(p).map_err(|e| format!("{}: {e}", p.display()))?;
            let name = p
                .file_stem()
                .map_or_else(String::new, |s| s.to_string_lossy().into());
            parse_real(&name, &text)
        })
        .collect()
}

/// What the detector did on one real trace.
#[derive(Debug, Clone)]
pub(crate) struct RealOutcome {
    /// The first sample inside the band, s.
    pub reach_s: Option<f64>,
    /// When the detector declared the bed stable, s.
    pub declared_s: Option<f64>,
    /// The detector's explanation, at the declaration or at the end of the trace.
    pub why: String,
    /// The largest fall (or rise) still possible at the end, fraction of full power.
    pub remaining_upper: Option<f64>,
    /// The bin noise the test used at the end (standard deviation, fraction of full power).
    pub test_sd: Option<f64>,
    /// The coupling the rule used, in a few words, and why.
    pub coupling: String,
    /// What must not happen on any bed and did: declared before the band was reached and the
    /// settling and minimum soak had passed, or while the temperature was out of the band.
    pub violations: Vec<String>,
}

/// Runs the detector over a real trace with its heater's `max_power`, checking on the way
/// that no declaration comes before the bed reached its band plus `settle_s` + `min_soak_s`,
/// nor while the temperature is out of the band.
#[must_use]
pub(crate) fn run_real(trace: &RealTrace, params: &SoakParams) -> RealOutcome {
    let mut det = SoakDetector::new(params.clone());
    det.set_max_power(trace.max_power);
    let in_band = |s: &TraceSample| (s.temp_c - s.target_c).abs() <= params.temp_band_c;
    let reach_s = trace.samples.iter().find(|s| in_band(s)).map(|s| s.t_s);
    let mut violations = Vec::new();
    let mut declared_s = None;
    for s in &trace.samples {
        if let SoakStatus::Stable { at_s } = det.push(s.t_s, s.power, s.temp_c, s.target_c) {
            let earliest =
                reach_s.map_or(f64::INFINITY, |r| r + params.settle_s + params.min_soak_s);
            if at_s < earliest {
                violations.push(format!(
                    "declared at {:.1} min, before the band was reached and settled ({:.1} min)",
                    at_s / 60.0,
                    earliest / 60.0
                ));
            }
            if !in_band(s) {
                violations.push(format!(
                    "declared at {:.1} min with the temperature {:.1} °C out of the band around {:.1} °C",
                    at_s / 60.0,
                    s.temp_c,
                    s.target_c
                ));
            }
            declared_s = Some(at_s);
            break;
        }
    }
    let fit = det.fit();
    let coupling = det.coupling().short_why();
    RealOutcome {
        coupling,
        reach_s,
        declared_s,
        why: det.explanation().to_string(),
        remaining_upper: fit.map(|f| f.remaining_upper),
        test_sd: fit.map(|f| f.test_sd),
        violations,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn all() -> Vec<RealTrace> {
        load_dir(Path::new(REAL_DIR)).expect("the real traces load")
    }

    #[test]
    fn every_real_trace_names_its_source_control_and_max_power() {
        let traces = all();
        assert!(traces.len() >= 10, "{} traces", traces.len());
        for t in &traces {
            let text = std::fs::read_to_string(Path::new(REAL_DIR).join(format!("{}.csv", t.name)))
                .unwrap();
            assert!(header(&text, "source_repo").is_some(), "{}", t.name);
            assert!(
                ["pid", "watermark"].contains(&t.control.as_str()),
                "{}",
                t.name
            );
            assert!(
                t.samples.len() > 600,
                "{}: {} samples",
                t.name,
                t.samples.len()
            );
        }
        // The set holds what the issue names: a watermark bed, a pwm-capped bed, a step down.
        assert!(traces.iter().any(|t| t.control == "watermark"));
        assert!(traces.iter().any(|t| t.max_power < 0.75));
        assert!(traces.iter().any(|t| t.step == "60 -> 55"));
    }

    /// On beds nobody simulated (issue 10: recorded klippy.log traces, prints running, a
    /// pwm-capped bed, a watermark bed, a step down, a heater fault): never declared before
    /// the bed reached its band and settled, never while out of it.
    #[test]
    fn no_real_trace_is_declared_before_it_settled_or_while_out_of_its_band() {
        let params = SoakParams::default();
        let bad: Vec<String> = all()
            .iter()
            .flat_map(|t| {
                run_real(t, &params)
                    .violations
                    .into_iter()
                    .map(move |v| format!("{}: {v}", t.name))
            })
            .collect();
        assert!(bad.is_empty(), "{}", bad.join("\n"));
    }

    /// A heater that failed while holding 70 °C (its power stuck at 1.0 while the bed fell to
    /// 38 °C): the detector ends in Heating and names the temperature, it never called the
    /// failing bed stable.
    #[test]
    fn a_bed_whose_heater_fails_is_never_stable() {
        let traces = all();
        let fault = traces
            .iter()
            .find(|t| t.name == "gutterguys-klipperconfig-1")
            .expect("the fault trace");
        let out = run_real(fault, &SoakParams::default());
        assert_eq!(out.declared_s, None, "{}", out.why);
        assert!(out.why.contains("from the target 70.0 °C"), "{}", out.why);
    }

    /// What the console says on real beds reads as a power a heater can give: the fits of
    /// wandering beds headed for −183 % or 25 556 % and were printed as such.
    #[test]
    fn the_explanations_on_real_beds_state_no_impossible_power() {
        for t in &all() {
            let why = run_real(t, &SoakParams::default()).why;
            for (i, _) in why.match_indices(" %") {
                let num: String = why[..i]
                    .chars()
                    .rev()
                    .take_while(|c| c.is_ascii_digit() || *c == '.' || *c == '-')
                    .collect::<Vec<_>>()
                    .into_iter()
                    .rev()
                    .collect();
                let v: f64 = num.parse().unwrap_or(0.0);
                assert!((-5.0..=105.0).contains(&v), "{}: {why}", t.name);
            }
        }
    }

    /// The bed capped at max_power 0.6 (issue 10: measure saturation against it), replayed as
    /// `klipcal soak-detect` does, without its config: the cap is learnt from the heat-up.
    #[test]
    fn the_capped_real_bed_shows_its_max_power_in_its_heat_up() {
        let traces = all();
        let capped = traces
            .iter()
            .find(|t| t.max_power < 0.75)
            .expect("a capped bed");
        let mut det = SoakDetector::new(SoakParams::default());
        for s in &capped.samples {
            det.push(s.t_s, s.power, s.temp_c, s.target_c);
        }
        assert!(
            (det.max_power() - capped.max_power).abs() < 1e-9,
            "{}: learnt {}, config {}",
            capped.name,
            det.max_power(),
            capped.max_power
        );
        // Beds at full power learn nothing lower.
        for t in traces.iter().filter(|t| t.max_power == 1.0) {
            let mut det = SoakDetector::new(SoakParams::default());
            for s in &t.samples {
                det.push(s.t_s, s.power, s.temp_c, s.target_c);
            }
            assert_eq!(det.max_power(), 1.0, "{}", t.name);
        }
    }

    /// A real trace written back as the klippy.log it came from (config dump, then a `Stats`
    /// line a second, the target set from 0 after 30 s).
    pub(crate) fn as_klippy_log(t: &RealTrace) -> String {
        let mut log = format!(
            "Starting Klippy...\n===== Config file =====\n[heater_bed]\nheater_pin = PA1\n\
             control = {}\nmax_power = {}\n=======================\n",
            t.control, t.max_power
        );
        for k in 0..30 {
            log += &format!(
                "Stats {:.1}: gcodein=0 heater_bed: target=0 temp=22.0 pwm=0.000 sysload=0.1\n",
                1000.0 + f64::from(k)
            );
        }
        for x in &t.samples {
            log += &format!(
                "Stats {:.1}: gcodein=0  mcu: mcu_awake=0.003 heater_bed: target={} temp={} \
                 pwm={:.3} extruder: target=0 temp=21.0 pwm=0.000\n",
                1030.0 + x.t_s,
                x.target_c,
                x.temp_c,
                x.power
            );
        }
        log
    }

    /// `klipcal soak-detect --klippy-log` reads back what the log holds and judges each hold
    /// as a replay of the same samples does: the real beds written back as their logs give
    /// every sample, max_power from the config dump, one hold as long as the trace, and the
    /// same declaration.
    #[test]
    fn a_klippy_log_gives_the_same_holds_as_its_trace() {
        let params = SoakParams::default();
        for t in &all() {
            let sessions = crate::klipper::klippy_log::parse(&as_klippy_log(t));
            assert_eq!(sessions.len(), 1, "{}", t.name);
            let session = &sessions[0];
            assert_eq!(session.max_power, Some(t.max_power), "{}", t.name);
            assert_eq!(session.stats.len(), 30 + t.samples.len(), "{}", t.name);
            for (b, x) in session.stats[30..].iter().zip(&t.samples) {
                assert!((b.eventtime_s - 1030.0 - x.t_s).abs() < 0.06, "{}", t.name);
                assert!(
                    (b.pwm - x.power).abs() < 6e-4 && b.temp_c == x.temp_c,
                    "{}",
                    t.name
                );
            }
            let holds = crate::cmd::soak::log_holds(&session.stats, session.max_power, &params);
            assert_eq!(holds.len(), 1, "{}: {holds:?}", t.name);
            let h = &holds[0];
            let end = t.samples.last().map_or(0.0, |s| s.t_s);
            assert!((h.held_s - end).abs() < 0.1, "{}", t.name);
            // The same samples replayed as a trace, with the same max_power.
            let mut d = SoakDetector::new(params.clone());
            d.set_max_power(t.max_power);
            let declared = session.stats.iter().find_map(|b| {
                match d.push(b.eventtime_s, b.pwm, b.temp_c, b.target_c) {
                    SoakStatus::Stable { at_s } => Some(at_s - h.from_eventtime_s),
                    _ => None,
                }
            });
            assert_eq!(h.stable_after_s, declared, "{}", t.name);
            assert!(!h.reason.is_empty(), "{}", t.name);
        }
    }

    #[test]
    fn header_values_are_read_and_missing_ones_named() {
        let text = "# heater_bed control: watermark\n# heater_bed max_power: 0.6 (set)\n\
                    # step: 0 -> 60 (step-up-from-low)\n# print_during_hold: no (idle)\n\
                    t_s,power,temp_c,target_c\n0,0.6,20,60\n1,0.6,21,60\n";
        let t = parse_real("x", text).unwrap();
        assert_eq!(
            (t.control.as_str(), t.max_power, t.step.as_str(), t.printing),
            ("watermark", 0.6, "0 -> 60", false)
        );
        let e = parse_real("y", "t_s,power,temp_c,target_c\n0,0.5,20,60\n").unwrap_err();
        assert!(e.contains("y: no `# heater_bed control:` line"), "{e}");
    }
}
