//! The backlash commands: `klipcal backlash solve` (a readings file through
//! [`crate::calib::backlash`]) and `klipcal backlash image FILE` (the nozzle in a user's own
//! camera picture through [`crate::calib::nozzle`]). Holds no statistics of its own; the
//! benchmark with its simulated axes and people is `klipcal-bench backlash`.

use std::path::Path;
use std::process::ExitCode;

use anyhow::Context;

use crate::calib::backlash::{self, AxisResult, BacklashParams, Verdict};
use crate::calib::nozzle::{self, DetectParams, Gray};
use crate::cli::{BacklashImageArgs, BacklashSolveArgs};
use crate::config::BacklashConfig;

/// `klipcal backlash solve --readings FILE [--max-accel MM_S2] [--json]`.
///
/// # Errors
/// An unreadable file, or readings refused by [`backlash::solve`] (the message names the axis
/// and cycle and says what is expected).
pub(crate) fn solve(
    args: &BacklashSolveArgs,
    settings: &BacklashConfig,
) -> anyhow::Result<ExitCode> {
    let text = std::fs::read_to_string(&args.readings)
        .with_context(|| format!("cannot read readings file {}", args.readings.display()))?;
    let results = solve_text(&text, args.max_accel, &settings.params())
        .with_context(|| format!("readings file {}", args.readings.display()))?;
    if args.json {
        println!("{}", serde_json::to_string_pretty(&results)?);
        return Ok(ExitCode::SUCCESS);
    }
    print!("{}", render(&results, args.max_accel, &args.readings));
    Ok(ExitCode::SUCCESS)
}

/// `klipcal backlash image FILE [--json]`: where the nozzle is, or why the picture is refused.
/// Exits 0 with a centre, 1 with a refusal (the reason printed), and with an error for a file
/// that cannot be read or decoded.
///
/// # Errors
/// An unreadable file, or bytes that are not a JPEG or PNG picture.
pub(crate) fn image(args: &BacklashImageArgs) -> anyhow::Result<ExitCode> {
    let bytes = std::fs::read(&args.file)
        .with_context(|| format!("cannot read picture {}", args.file.display()))?;
    let (w, h, grey) =
        nozzle::decode_gray(&bytes).with_context(|| format!("picture {}", args.file.display()))?;
    let found = nozzle::detect(
        &Gray {
            width: w,
            height: h,
            data: &grey,
        },
        &DetectParams::default(),
    );
    let ok = found.is_ok();
    print!("{}", image_report(&args.file, w, h, &found, args.json)?);
    Ok(if ok {
        ExitCode::SUCCESS
    } else {
        ExitCode::FAILURE
    })
}

fn image_report(
    path: &Path,
    w: usize,
    h: usize,
    found: &Result<nozzle::Detection, nozzle::Refusal>,
    json: bool,
) -> anyhow::Result<String> {
    if json {
        let v = match found {
            Ok(d) => serde_json::json!({
                "file": path.display().to_string(), "width": w, "height": h, "found": true,
                "centre_px": d.centre_px, "uncertainty_px": d.uncertainty_px,
                "diagnostics": d.diagnostics,
            }),
            Err(r) => serde_json::json!({
                "file": path.display().to_string(), "width": w, "height": h, "found": false,
                "refusal": r, "message": r.to_string(),
            }),
        };
        return Ok(format!("{}\n", serde_json::to_string_pretty(&v)?));
    }
    Ok(match found {
        Ok(d) => {
            let g = &d.diagnostics;
            format!(
                "nozzle in {} ({w}×{h}): centre ({:.2}, {:.2}) px ± {:.2} px\n  \
                 {} on a background of {:.0} grey levels, contrast {:.0}, noise sd {:.1}; \
                 radius {:.1} px, edge scatter {:.2} px, {} candidate(s), {:.1} % clipped\n",
                path.display(),
                d.centre_px[0],
                d.centre_px[1],
                d.uncertainty_px,
                match g.polarity {
                    nozzle::Polarity::Bright => "brighter than",
                    nozzle::Polarity::Dark => "darker than",
                },
                g.background,
                g.contrast,
                g.noise_sd,
                g.radius_px,
                g.scatter_px,
                g.candidates,
                100.0 * g.clipped_fraction,
            )
        }
        Err(r) => format!(
            "no nozzle position from {} ({w}×{h}): {r}\n",
            path.display()
        ),
    })
}

fn solve_text(
    text: &str,
    max_accel: Option<f64>,
    params: &BacklashParams,
) -> Result<std::collections::BTreeMap<String, AxisResult>, crate::calib::Error> {
    backlash::solve(text, max_accel, params)
}

fn render(
    results: &std::collections::BTreeMap<String, AxisResult>,
    max_accel: Option<f64>,
    path: &Path,
) -> String {
    let mut out = format!("backlash from {}\n", path.display());
    for (axis, r) in results {
        let verdict = match r.verdict {
            Verdict::NotNeeded => "no compensation needed (seed: 0.01–0.02 mm needs none)",
            Verdict::Borderline if r.compensate => "borderline: compensate",
            Verdict::Borderline => "borderline: no compensation",
            Verdict::Needed => "compensate (seed: ~0.05 mm certainly needs it)",
        };
        out.push_str(&format!(
            "  {axis}: {:.4} mm ± {:.4} (cycles within {:.4} mm of each other, {} cycles{}; {}) \
             — {verdict}\n",
            r.backlash_mm,
            r.uncertainty_mm,
            r.spread_mm,
            r.cycles,
            if r.outliers.is_empty() {
                String::new()
            } else {
                format!(
                    ", cycle {} left out as an outlier",
                    r.outliers
                        .iter()
                        .map(ToString::to_string)
                        .collect::<Vec<_>>()
                        .join(", ")
                )
            },
            if r.jog_share >= 0.9 {
                "as close as the jog step allows"
            } else {
                "they scatter more than the jog step explains: the play or the readings vary"
            },
        ));
        if r.compensate {
            out.push_str(&format!(
                "     smooth_time {:.4} s{} → extra acceleration {:.0} mm/s²{}\n",
                r.smooth_time_s,
                if r.smooth_time_raised {
                    " (raised from the seed's 0.005 s)"
                } else {
                    ""
                },
                r.extra_accel_mm_s2,
                max_accel.map_or(String::new(), |a| format!(" (max_accel {a:.0})")),
            ));
        }
    }
    // Motor directions measured: a CoreXY printer, and the seed's open question answered.
    if results.contains_key("a") || results.contains_key("b") {
        if let Some(t) = backlash::corexy_xy_answer(results) {
            out.push_str(&format!("  CoreXY, x_backlash = y_backlash? {t}\n"));
        }
    }
    out
}

// ---------------------------------------------------------------------------------------------

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn solve_text_renders_each_axis_and_refuses_bad_files() {
        let r = solve_text(
            r#"{"x": [[100.05, 100.0], [100.06, 100.0], [100.05, 100.0]]}"#,
            Some(3000.0),
            &BacklashParams::default(),
        )
        .unwrap();
        let text = render(&r, Some(3000.0), Path::new("r.json"));
        assert!(text.contains("x: 0.0500 mm"), "{text}");
        assert!(text.contains("smooth_time 0.0058 s (raised"), "{text}");
        assert!(solve_text("{\"x\": 1}", None, &BacklashParams::default()).is_err());
    }

    #[test]
    fn the_solve_text_uses_words_a_user_can_use() {
        // Issue 27's walk: "jog resolution 100 % of the variance" and a spread that included
        // the outlier were not words a user can use.
        let r = solve_text(
            r#"{"x": [[0.05, 0], [0.051, 0], [0.049, 0], [0.15, 0], [0.05, 0]]}"#,
            None,
            &BacklashParams::default(),
        )
        .unwrap();
        let text = render(&r, None, Path::new("r.json"));
        assert!(
            !text.contains("variance") && !text.contains("jog resolution"),
            "{text}"
        );
        assert!(
            text.contains("within 0.0020 mm of each other")
                && text.contains("cycle 4 left out as an outlier"),
            "{text}"
        );
    }
}
