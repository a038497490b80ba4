//! The thermal soak commands: `klipcal soak-detect` replays a recorded bed trace (CSV) through
//! the pure detector in [`crate::calib::soak`]; `klipcal bench soak` runs it on simulated beds.
//! Owns the trace file format and the bed simulator; holds no detection logic of its own.

use std::path::{Path, PathBuf};
use std::process::ExitCode;

use crate::calib::soak::{SoakDetector, SoakParams, SoakStatus};
use crate::cli::SoakDetectArgs;

/// One line of a bed trace.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TraceSample {
    /// Time of the sample.
    pub t_s: f64,
    /// Heater power, fraction of full power (0..1).
    pub power: f64,
    /// Bed temperature.
    pub temp_c: f64,
    /// Bed target temperature.
    pub target_c: f64,
}

/// What the trace columns must be, quoted in every error.
const EXPECTED: &str = "expected `t_s,power,temp_c,target_c` (numbers; power 0..1; t_s increasing)";

/// A bed trace that cannot be used.
#[derive(Debug, thiserror::Error)]
pub enum TraceError {
    /// The file could not be read.
    #[error("cannot read trace {path}")]
    Read {
        /// The path tried.
        path: PathBuf,
        /// The I/O error.
        source: std::io::Error,
    },
    /// One line is malformed.
    #[error("line {line}: {message}; {EXPECTED}")]
    Line {
        /// 1-based line number.
        line: usize,
        /// What is wrong with it.
        message: String,
    },
    /// No sample lines at all.
    #[error("no samples; {EXPECTED}")]
    Empty,
}

/// Parses a bed trace: comma-separated `t_s,power,temp_c,target_c`, one sample a line.
/// A first line that does not start with a number is a header; blank lines and lines starting
/// with `#` are skipped.
///
/// # Errors
/// The first bad line, named by number, with what was wrong and what is expected.
pub fn parse_trace(text: &str) -> Result<Vec<TraceSample>, TraceError> {
    let mut out: Vec<TraceSample> = Vec::new();
    let mut seen_line = false;
    for (i, raw) in text.lines().enumerate() {
        let line_no = i + 1;
        let line = raw.trim().trim_start_matches('\u{feff}');
        if line.is_empty() || line.starts_with('#') {
            continue;
        }
        let first_line = !seen_line;
        seen_line = true;
        let fields: Vec<&str> = line.split(',').map(str::trim).collect();
        let is_header = first_line
            && fields
                .first()
                .is_some_and(|f| f.parse::<f64>().is_err() && !f.is_empty());
        if is_header {
            continue;
        }
        let bad = |message: String| TraceError::Line {
            line: line_no,
            message,
        };
        if fields.len() != 4 {
            return Err(bad(format!("{} fields", fields.len())));
        }
        let mut v = [0.0f64; 4];
        for (k, (name, f)) in ["t_s", "power", "temp_c", "target_c"]
            .iter()
            .zip(&fields)
            .enumerate()
        {
            v[k] = match f.parse::<f64>() {
                Ok(x) if x.is_finite() => x,
                _ => return Err(bad(format!("{name} `{f}` is not a number"))),
            };
        }
        let [t_s, power, temp_c, target_c] = v;
        if !(0.0..=1.0).contains(&power) {
            return Err(bad(format!(
                "power {power} is outside 0..1 (a fraction of full power, not a percentage)"
            )));
        }
        if let Some(prev) = out.last() {
            if t_s <= prev.t_s {
                return Err(bad(format!(
                    "t_s {t_s} is not later than the previous sample's {}",
                    prev.t_s
                )));
            }
        }
        out.push(TraceSample {
            t_s,
            power,
            temp_c,
            target_c,
        });
    }
    if out.is_empty() {
        return Err(TraceError::Empty);
    }
    Ok(out)
}

/// Reads and parses a trace file.
///
/// # Errors
/// The file cannot be read, or a line is malformed ([`parse_trace`]).
pub(crate) fn read_trace(path: &Path) -> Result<Vec<TraceSample>, TraceError> {
    let text = std::fs::read_to_string(path).map_err(|source| TraceError::Read {
        path: path.to_path_buf(),
        source,
    })?;
    parse_trace(&text)
}

/// What the detector concluded about a whole trace.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub(crate) struct TraceVerdict {
    /// When it declared equilibrium, or `None`.
    pub stable_at_s: Option<f64>,
    /// The status after the last sample (or at the declaration).
    pub status: SoakStatus,
    /// Why, in words.
    pub reason: String,
    /// Time of the last sample read (the replay stops at the declaration).
    pub last_t_s: f64,
}

/// Replays a trace through a fresh detector, stopping at the first declaration.
pub(crate) fn replay(samples: &[TraceSample], params: &SoakParams) -> TraceVerdict {
    let mut d = SoakDetector::new(params.clone());
    let mut status = SoakStatus::Heating;
    for s in samples {
        status = d.push(s.t_s, s.power, s.temp_c, s.target_c);
        if let SoakStatus::Stable { at_s } = status {
            return TraceVerdict {
                stable_at_s: Some(at_s),
                status,
                reason: d.explanation().to_string(),
                last_t_s: s.t_s,
            };
        }
    }
    TraceVerdict {
        stable_at_s: None,
        status,
        reason: d.explanation().to_string(),
        last_t_s: samples.last().map_or(0.0, |s| s.t_s),
    }
}

/// `klipcal soak-detect --trace PATH [--json]`.
///
/// # Errors
/// An unreadable or malformed trace (the message names the line and what is expected).
pub(crate) fn detect(args: &SoakDetectArgs, params: &SoakParams) -> anyhow::Result<ExitCode> {
    let trace = match (&args.trace, &args.klippy_log) {
        (Some(trace), _) => trace,
        (None, Some(log)) => return detect_log(log, args.json, params),
        (None, None) => anyhow::bail!("give --trace FILE or --klippy-log FILE"),
    };
    let samples = read_trace(trace).map_err(|e| match e {
        TraceError::Read { .. } => anyhow::Error::new(e),
        other => anyhow::Error::new(other).context(format!("trace {}", trace.display())),
    })?;
    let v = replay(&samples, params);
    if args.json {
        println!("{}", serde_json::to_string_pretty(&v)?);
        return Ok(ExitCode::SUCCESS);
    }
    match (&v.status, v.stable_at_s) {
        (_, Some(at)) => println!("stable at {at:.1} s ({:.1} min)", at / 60.0),
        (SoakStatus::Skipped, None) => println!("soak skipped"),
        (_, None) => println!(
            "not stable by the end of the trace ({:.1} s, {:.1} min)",
            v.last_t_s,
            v.last_t_s / 60.0
        ),
    }
    println!("why: {}", v.reason);
    Ok(ExitCode::SUCCESS)
}

/// One hold of the bed at a heated target in a klippy.log, as the detector judged it.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct LogHold {
    /// Klipper's eventtime when the target was set, s.
    pub from_eventtime_s: f64,
    /// The target before, °C.
    pub from_target_c: f64,
    /// The target held, °C.
    pub target_c: f64,
    /// How long the target was held in the log, s.
    pub held_s: f64,
    /// Seconds after the target was set that the bed was declared stable.
    pub stable_after_s: Option<f64>,
    /// The detector's word at the declaration or at the end of the hold.
    pub reason: String,
}

/// Every hold of the bed at a heated target in one start of Klipper, judged by a detector
/// that sees the whole history (as the daemon would), with `max_power` when the log gives it.
#[must_use]
pub fn log_holds(
    stats: &[crate::klipper::klippy_log::BedStat],
    max_power: Option<f64>,
    params: &SoakParams,
) -> Vec<LogHold> {
    let mut d = SoakDetector::new(params.clone());
    if let Some(m) = max_power {
        d.set_max_power(m);
    }
    let mut holds: Vec<LogHold> = Vec::new();
    let mut prev_target: Option<f64> = None;
    // A hold not declared keeps the detector's word at its end: taken when the target
    // changes (before the detector forgets) and after the last line.
    let close = |holds: &mut Vec<LogHold>, d: &SoakDetector, held: Option<f64>| {
        let open = |h: &&mut LogHold| {
            h.stable_after_s.is_none() && held.is_some_and(|t| (h.target_c - t).abs() <= 0.05)
        };
        if let Some(h) = holds.last_mut().filter(open) {
            h.reason = d.explanation().to_string();
        }
    };
    for s in stats {
        if prev_target.map_or(true, |t| (t - s.target_c).abs() > 0.05) {
            close(&mut holds, &d, prev_target);
            if s.target_c > params.skip_below_c {
                holds.push(LogHold {
                    from_eventtime_s: s.eventtime_s,
                    from_target_c: prev_target.unwrap_or(0.0),
                    target_c: s.target_c,
                    held_s: 0.0,
                    stable_after_s: None,
                    reason: String::new(),
                });
            }
            prev_target = Some(s.target_c);
        }
        let status = d.push(s.eventtime_s, s.pwm, s.temp_c, s.target_c);
        if let Some(h) = holds
            .last_mut()
            .filter(|h| (h.target_c - s.target_c).abs() <= 0.05)
        {
            h.held_s = s.eventtime_s - h.from_eventtime_s;
            if let (None, SoakStatus::Stable { at_s }) = (h.stable_after_s, status) {
                h.stable_after_s = Some(at_s - h.from_eventtime_s);
                h.reason = d.explanation().to_string();
            }
        }
    }
    close(&mut holds, &d, prev_target);
    holds
}

/// `klipcal soak-detect --klippy-log PATH [--json]`.
fn detect_log(path: &Path, json: bool, params: &SoakParams) -> anyhow::Result<ExitCode> {
    let bytes = std::fs::read(path)
        .map_err(|e| anyhow::anyhow!("cannot read klippy.log {}: {e}", path.display()))?;
    let text = String::from_utf8_lossy(&bytes);
    let sessions = crate::klipper::klippy_log::parse(&text);
    let mut out = Vec::new();
    for s in &sessions {
        let max_power = s.max_power.or(s.has_config.then_some(1.0));
        for h in log_holds(&s.stats, max_power, params) {
            out.push((h, max_power, s.control.clone()));
        }
    }
    if json {
        let holds: Vec<serde_json::Value> = out
            .iter()
            .map(|(h, m, c)| {
                let mut v = serde_json::to_value(h).unwrap_or_default();
                v["max_power"] = serde_json::json!(m);
                v["control"] = serde_json::json!(c);
                v
            })
            .collect();
        println!(
            "{}",
            serde_json::to_string_pretty(&serde_json::json!({ "holds": holds }))?
        );
        return Ok(ExitCode::SUCCESS);
    }
    if out.is_empty() {
        println!(
            "no hold of the bed at a heated target (above {:.0} °C) in {}: expected `Stats …: … \
             heater_bed: target=… temp=… pwm=…` lines",
            params.skip_below_c,
            path.display()
        );
        if let Some(why) = crate::klipper::klippy_log::why_no_stats(&text) {
            println!("  why: {why}");
        }
        return Ok(ExitCode::SUCCESS);
    }
    for (h, m, c) in &out {
        let said = match h.stable_after_s {
            Some(s) => format!("stable after {:.1} min", s / 60.0),
            None => "not stable within the hold".to_string(),
        };
        println!(
            "eventtime {:.1}: {:.0} -> {:.0} °C, held {:.1} min ({}, max_power {}): {said}",
            h.from_eventtime_s,
            h.from_target_c,
            h.target_c,
            h.held_s / 60.0,
            c.as_deref().unwrap_or("control unknown"),
            m.map_or("unknown, learnt from the heat-up".to_string(), |m| format!(
                "{m:.2}"
            )),
        );
        println!("  why: {}", h.reason);
    }
    Ok(ExitCode::SUCCESS)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Each hold of a klippy.log keeps the detector's word at its own end: a bed heated to
    /// 60 °C, switched off, heated again is two holds, and the first does not say what the
    /// detector said of the unheated bed.
    #[test]
    fn each_log_hold_keeps_its_own_last_word() {
        use crate::klipper::klippy_log::BedStat;
        let mut stats = Vec::new();
        for (from, to, target, temp) in [
            (0, 600, 60.0, 59.9),
            (600, 700, 0.0, 40.0),
            (700, 900, 60.0, 58.5),
        ] {
            for k in from..to {
                stats.push(BedStat {
                    eventtime_s: f64::from(k),
                    target_c: target,
                    temp_c: temp + 0.01 * f64::from(k % 3),
                    pwm: 0.3 + 0.01 * f64::from(k % 5),
                });
            }
        }
        let holds = log_holds(&stats, Some(1.0), &SoakParams::default());
        assert_eq!(holds.len(), 2, "{holds:?}");
        assert_eq!((holds[0].held_s, holds[1].from_target_c), (599.0, 0.0));
        for h in &holds {
            assert!(
                !h.reason.is_empty() && !h.reason.contains("unheated"),
                "{h:?}"
            );
        }
    }

    fn expect_line_error(text: &str, line: usize, needle: &str) {
        match parse_trace(text) {
            Err(TraceError::Line { line: l, message }) => {
                assert_eq!(l, line, "{message}");
                assert!(message.contains(needle), "{message}");
            }
            other => panic!("expected an error on line {line}, got {other:?}"),
        }
    }

    #[test]
    fn a_trace_with_a_header_comments_and_blank_lines_parses() {
        let text = "t_s,power,temp_c,target_c\n# comment\n0,1,25,60\n\n1, 0.5 ,59.5,60\n";
        let s = parse_trace(text).unwrap();
        assert_eq!(s.len(), 2);
        assert_eq!(
            s[1],
            TraceSample {
                t_s: 1.0,
                power: 0.5,
                temp_c: 59.5,
                target_c: 60.0
            }
        );
    }

    #[test]
    fn bad_trace_lines_are_named_with_what_is_wrong() {
        expect_line_error("t_s,power,temp_c,target_c\n0,1,25\n", 2, "3 fields");
        expect_line_error("0,1,25,60\n1,x,25,60\n", 2, "power `x` is not a number");
        expect_line_error("0,45,25,60\n", 1, "outside 0..1");
        expect_line_error("0,1,25,60\n0,1,25,60\n", 2, "not later");
        expect_line_error("0,1,25,60\nt_s,power,temp_c,target_c\n", 2, "t_s `t_s`");
        let err = parse_trace("0,1,25\n").unwrap_err().to_string();
        assert!(
            err.contains("expected `t_s,power,temp_c,target_c`"),
            "{err}"
        );
        assert!(matches!(
            parse_trace("t_s,power\n\n"),
            Err(TraceError::Empty)
        ));
    }

    #[test]
    fn replaying_a_decaying_trace_reports_when_and_why() {
        let mut text = String::from("t_s,power,temp_c,target_c\n");
        for i in 0..6000 {
            let t = f64::from(i);
            let (p, temp) = if t < 300.0 {
                (1.0, 25.0 + 35.0 * t / 300.0)
            } else {
                (0.3 + 0.5 * (-(t - 300.0) / 400.0).exp(), 60.0)
            };
            text.push_str(&format!("{t},{p},{temp},60\n"));
        }
        let samples = parse_trace(&text).unwrap();
        let v = replay(&samples, &SoakParams::default());
        let moment = 300.0 + 400.0 * 50f64.ln();
        let at = v.stable_at_s.expect("declared");
        assert!(at >= moment && at <= 1.5 * moment + 60.0, "{at}");
        assert!(v.reason.contains("power stopped falling"), "{}", v.reason);
        let json = serde_json::to_value(&v).unwrap();
        assert_eq!(json["stable_at_s"].as_f64(), Some(at));
    }

    #[test]
    fn a_trace_that_never_settles_reports_null() {
        let samples: Vec<TraceSample> = (0..600)
            .map(|i| TraceSample {
                t_s: f64::from(i),
                power: 1.0,
                temp_c: 30.0,
                target_c: 60.0,
            })
            .collect();
        let v = replay(&samples, &SoakParams::default());
        assert_eq!(v.stable_at_s, None);
        assert_eq!(
            serde_json::to_value(&v).unwrap()["stable_at_s"],
            serde_json::Value::Null
        );
        assert!(v.reason.contains("from the target"), "{}", v.reason);
    }
}
