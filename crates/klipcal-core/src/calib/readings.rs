//! PURE: caliper readings — parse the user's text (JSON map or `pair,reading` CSV) and reduce
//! each pair's readings to a robust centre with its uncertainty. No file access: callers pass text.

use std::collections::BTreeMap;

use super::Error;

/// Readings per pair id, in pair-id order; values in mm, not yet validated.
pub type RawReadings = BTreeMap<String, Vec<f64>>;

/// Parses readings text: a JSON object when it starts with `{`, otherwise `pair,reading` CSV.
///
/// # Errors
/// Malformed JSON or CSV, a non-number, or a value that is not an array; the message names the
/// pair (or CSV line) and what is expected.
pub fn parse_readings(text: &str) -> Result<RawReadings, Error> {
    if text.trim_start().starts_with('{') {
        parse_json(text)
    } else {
        parse_csv(text)
    }
}

/// Parses `{"A-D1":[10.02,10.03,…],…}`.
///
/// # Errors
/// See [`parse_readings`].
pub fn parse_json(text: &str) -> Result<RawReadings, Error> {
    let value: serde_json::Value =
        serde_json::from_str(text).map_err(|e| Error::ReadingsJson(e.to_string()))?;
    let serde_json::Value::Object(map) = value else {
        return Err(Error::ReadingsJson("the top level is not an object".into()));
    };
    let mut out = RawReadings::new();
    for (pair, v) in map {
        let serde_json::Value::Array(items) = v else {
            return Err(Error::ReadingsJson(format!(
                "pair {pair}: {v} is not an array of readings"
            )));
        };
        let mut values = Vec::with_capacity(items.len());
        for (i, item) in items.iter().enumerate() {
            match item.as_f64() {
                Some(x) if x.is_finite() => values.push(x),
                _ => {
                    return Err(Error::NotANumber {
                        pair,
                        index: i + 1,
                        found: item.to_string(),
                    })
                }
            }
        }
        out.insert(pair, values);
    }
    Ok(out)
}

/// Parses `pair,reading` rows; blank lines, `#` comments and a `pair,reading` header are skipped.
///
/// # Errors
/// See [`parse_readings`].
pub fn parse_csv(text: &str) -> Result<RawReadings, Error> {
    let mut out = RawReadings::new();
    for (i, raw_line) in text.lines().enumerate() {
        let line = raw_line.trim();
        if line.is_empty() || line.starts_with('#') {
            continue;
        }
        let fields: Vec<&str> = line.split(',').map(str::trim).collect();
        if fields.len() != 2 || fields[0].is_empty() {
            return Err(Error::ReadingsCsv {
                line: i + 1,
                message: format!("`{line}` has {} field(s)", fields.len()),
            });
        }
        let (pair, text_value) = (fields[0], fields[1]);
        if out.is_empty() && pair.eq_ignore_ascii_case("pair") {
            continue; // header
        }
        let entry = out.entry(pair.to_string()).or_default();
        match text_value.parse::<f64>() {
            Ok(x) if x.is_finite() => entry.push(x),
            _ => {
                return Err(Error::NotANumber {
                    pair: pair.to_string(),
                    index: entry.len() + 1,
                    found: format!("`{text_value}` (CSV line {})", i + 1),
                })
            }
        }
    }
    if out.is_empty() {
        return Err(Error::ReadingsCsv {
            line: 0,
            message: "no readings found".into(),
        });
    }
    Ok(out)
}

/// How readings are reduced to a centre.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct CentreRules {
    /// Fewer readings than this is an error (default 3).
    pub min_readings: usize,
    /// Readings farther than this many scaled MADs from the median are outliers (default 3).
    pub outlier_mads: f64,
    /// Floor of the scaled MAD, mm, so identical readings do not reject every other one
    /// (default 0.01 mm, a caliper's resolution).
    pub mad_floor_mm: f64,
    /// Kept readings spreading (max − min) more than this get a warning (default 0.02 mm).
    pub spread_warn_mm: f64,
    /// The stated caliper precision as one standard deviation, mm (default 0.02 mm / 3).
    pub caliper_sigma_mm: f64,
    /// The caliper's last digit, mm (`ab.caliper_resolution_mm`, default 0.01).
    pub resolution_mm: f64,
}

impl Default for CentreRules {
    fn default() -> Self {
        Self {
            min_readings: 3,
            outlier_mads: 3.0,
            mad_floor_mm: 0.01,
            spread_warn_mm: 0.02,
            caliper_sigma_mm: 0.02 / 3.0,
            resolution_mm: 0.01,
        }
    }
}

/// One pair's readings reduced to a centre.
#[derive(Debug, Clone, PartialEq)]
pub struct PairCentre {
    /// Pair id.
    pub pair: String,
    /// Median of the kept readings, mm.
    pub centre_mm: f64,
    /// Standard uncertainty of the centre, mm: 1.253 σ/√n with σ the larger of the stated caliper
    /// precision and the observed standard deviation.
    pub u_mm: f64,
    /// Observed sample standard deviation of the kept readings, mm (0 with fewer than 2).
    pub observed_sigma_mm: f64,
    /// Max − min of the kept readings, mm.
    pub spread_mm: f64,
    /// Readings kept.
    pub n_used: usize,
    /// Readings rejected as outliers, mm.
    pub rejected_mm: Vec<f64>,
}

/// Standard uncertainty of the median of `n` readings, mm, from two parts:
/// - their scatter, 1.253 σ/√n, with σ the larger of the stated caliper precision and the
///   readings' own standard deviation (their spread);
/// - the caliper's rounding to its last digit r, r/√12, not divided by √n: a person repeating
///   a reading mostly reads the same digits again, so the rounding is common to the readings
///   and does not average out.
///
/// Checked by `klipcal bench metrology` with human readings: the stated 95 % interval
/// (± 1.96 u of the scale) holds the exact correction 95–97 % of the time.
#[must_use]
pub fn centre_uncertainty(rules: &CentreRules, observed_sigma_mm: f64, n: usize) -> f64 {
    let sigma = rules.caliper_sigma_mm.max(observed_sigma_mm);
    let scatter = 1.253 * sigma / (n.max(1) as f64).sqrt();
    scatter.hypot(rules.resolution_mm / 12f64.sqrt())
}

/// Median of a non-empty slice (NaN-free); `None` when empty.
#[must_use]
pub fn median(values: &[f64]) -> Option<f64> {
    if values.is_empty() {
        return None;
    }
    let mut v = values.to_vec();
    v.sort_by(f64::total_cmp);
    let n = v.len();
    Some(if n % 2 == 1 {
        v[n / 2]
    } else {
        0.5 * (v[n / 2 - 1] + v[n / 2])
    })
}

/// Reduces one pair's readings to a robust centre and collects warnings.
///
/// Rule: m = median of all readings, MAD = median |x − m|, scaled MAD = max(1.4826·MAD,
/// `mad_floor_mm`); readings with |x − m| > `outlier_mads` × scaled MAD are rejected, and the
/// centre is the median of the rest. Warnings: outliers rejected, spread above `spread_warn_mm`.
///
/// # Errors
/// Fewer than `min_readings` readings, or a reading that is not a positive finite number.
pub fn centre(
    pair: &str,
    readings_mm: &[f64],
    rules: &CentreRules,
) -> Result<(PairCentre, Vec<String>), Error> {
    for (i, &x) in readings_mm.iter().enumerate() {
        if !x.is_finite() {
            return Err(Error::NotANumber {
                pair: pair.into(),
                index: i + 1,
                found: x.to_string(),
            });
        }
        if x <= 0.0 {
            return Err(Error::NonPositive {
                pair: pair.into(),
                index: i + 1,
                value: x,
            });
        }
    }
    let (Some(m), true) = (median(readings_mm), readings_mm.len() >= rules.min_readings) else {
        return Err(Error::TooFewReadings {
            pair: pair.into(),
            count: readings_mm.len(),
            min: rules.min_readings,
        });
    };
    let deviations: Vec<f64> = readings_mm.iter().map(|x| (x - m).abs()).collect();
    let mad = median(&deviations).unwrap_or(0.0);
    let limit = rules.outlier_mads * (1.4826 * mad).max(rules.mad_floor_mm);
    let (kept, rejected): (Vec<f64>, Vec<f64>) =
        readings_mm.iter().partition(|x| (*x - m).abs() <= limit);
    let centre_mm = median(&kept).unwrap_or(m);
    let n = kept.len();
    let observed_sigma_mm = if n >= 2 {
        let mean = kept.iter().sum::<f64>() / n as f64;
        (kept.iter().map(|x| (x - mean).powi(2)).sum::<f64>() / (n - 1) as f64).sqrt()
    } else {
        0.0
    };
    let (lo, hi) = kept
        .iter()
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), &x| {
            (lo.min(x), hi.max(x))
        });
    let spread_mm = hi - lo;
    let u_mm = centre_uncertainty(rules, observed_sigma_mm, n);
    let mut warnings = Vec::new();
    if !rejected.is_empty() {
        warnings.push(format!(
            "pair {pair}: rejected outlier reading(s) {} mm (more than {:.3} mm from the median {m:.3})",
            rejected.iter().map(|x| format!("{x}")).collect::<Vec<_>>().join(", "),
            limit
        ));
    }
    if spread_mm > rules.spread_warn_mm + 1e-9 {
        warnings.push(format!(
            "pair {pair}: readings spread {spread_mm:.3} mm, more than {:.3} mm; measure again with steady force",
            rules.spread_warn_mm
        ));
    }
    Ok((
        PairCentre {
            pair: pair.into(),
            centre_mm,
            u_mm,
            observed_sigma_mm,
            spread_mm,
            n_used: n,
            rejected_mm: rejected,
        },
        warnings,
    ))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn centre_is_the_median_of_five_readings() {
        let (c, w) = centre(
            "A-D1",
            &[10.02, 10.03, 10.01, 10.02, 10.04],
            &CentreRules::default(),
        )
        .expect("valid readings");
        assert!((c.centre_mm - 10.02).abs() < 1e-12);
        assert_eq!(c.n_used, 5);
        // seed README: readings should agree within 0.02 mm; these span 0.03 mm.
        assert!(w.iter().all(|m| m.contains("spread")), "{w:?}");
    }

    #[test]
    fn a_reading_far_from_the_others_is_rejected_and_named() {
        let (c, w) = centre(
            "B-D2",
            &[150.02, 150.03, 150.01, 150.02, 150.40],
            &CentreRules::default(),
        )
        .expect("valid readings");
        assert_eq!(c.rejected_mm, vec![150.40]);
        assert!((c.centre_mm - 150.02).abs() < 1e-12);
        assert!(w
            .iter()
            .any(|m| m.contains("B-D2") && m.contains("outlier")));
    }

    #[test]
    fn readings_spreading_more_than_20_um_are_flagged() {
        let (_, w) = centre(
            "A-D2",
            &[150.00, 150.01, 150.02, 150.03, 150.025],
            &CentreRules::default(),
        )
        .expect("valid readings");
        assert!(
            w.iter().any(|m| m.contains("A-D2") && m.contains("spread")),
            "{w:?}"
        );
        let (_, w) = centre(
            "A-D2",
            &[150.00, 150.01, 150.02, 150.01, 150.015],
            &CentreRules::default(),
        )
        .expect("valid readings");
        assert!(w.is_empty(), "{w:?}");
    }

    #[test]
    fn fewer_than_three_readings_is_an_error_naming_the_pair() {
        let err = centre("A-D1", &[10.0, 10.01], &CentreRules::default()).unwrap_err();
        assert!(matches!(err, Error::TooFewReadings { count: 2, .. }));
        assert!(err.to_string().contains("A-D1"));
    }

    #[test]
    fn zero_or_negative_readings_are_errors() {
        let err = centre("A-D1", &[10.0, 0.0, 10.01], &CentreRules::default()).unwrap_err();
        assert!(matches!(err, Error::NonPositive { index: 2, .. }));
        let err = centre("A-D1", &[-1.0, 10.0, 10.01], &CentreRules::default()).unwrap_err();
        assert!(err.to_string().contains("positive"));
    }

    #[test]
    fn uncertainty_of_the_median_follows_the_paper_for_five_readings() {
        // seed 000 §3.4: 3σ = 20 µm, five readings, median → 3σ_median ≈ 11.2 µm.
        let paper = CentreRules {
            resolution_mm: 0.0,
            ..CentreRules::default()
        };
        let (c, _) = centre("A-D1", &[10.0; 5], &paper).expect("valid");
        assert!(
            (3.0 * c.u_mm * 1000.0 - 11.2).abs() < 0.05,
            "{}",
            3.0 * c.u_mm * 1000.0
        );
    }

    #[test]
    fn the_calipers_last_digit_is_part_of_the_uncertainty() {
        // Five readings that agree to the digit: their rounding (0.01 mm / √12 = 2.9 µm) is
        // common to them and adds to the 3.7 µm of their scatter: 4.7 µm.
        let (c, _) = centre("A-D1", &[10.0; 5], &CentreRules::default()).expect("valid");
        assert!((c.u_mm * 1000.0 - 4.72).abs() < 0.01, "{}", c.u_mm * 1000.0);
        // A coarser caliper (0.02 mm) states more.
        let coarse = CentreRules {
            resolution_mm: 0.02,
            ..CentreRules::default()
        };
        let (c2, _) = centre("A-D1", &[10.0; 5], &coarse).expect("valid");
        assert!(c2.u_mm > c.u_mm + 0.001, "{} vs {}", c2.u_mm, c.u_mm);
        // Readings that spread more than the stated precision: their spread is used.
        let (c3, _) = centre(
            "A-D1",
            &[10.0, 10.02, 9.98, 10.03, 9.97],
            &CentreRules::default(),
        )
        .expect("valid");
        assert!(c3.u_mm > 0.01, "{}", c3.u_mm);
    }

    #[test]
    fn json_non_numbers_name_the_pair_and_position() {
        let err = parse_readings(r#"{"A-D1":[10.0,"x",10.1]}"#).unwrap_err();
        assert!(matches!(err, Error::NotANumber { ref pair, index: 2, .. } if pair == "A-D1"));
        let err = parse_readings(r#"{"A-D1":10.0}"#).unwrap_err();
        assert!(err.to_string().contains("A-D1"));
        assert!(parse_readings("[1,2]").is_err());
    }

    #[test]
    fn csv_rows_group_by_pair_and_skip_a_header() {
        let r = parse_readings("pair,reading\nA-D1,10.02\nA-D1, 10.03\n# c\n\nA-D2,150.1\n")
            .expect("valid csv");
        assert_eq!(r["A-D1"], vec![10.02, 10.03]);
        assert_eq!(r["A-D2"], vec![150.1]);
        let err = parse_readings("A-D1,10.0\nA-D1,ten\n").unwrap_err();
        assert!(matches!(err, Error::NotANumber { ref pair, index: 2, .. } if pair == "A-D1"));
        assert!(matches!(
            parse_readings("A-D1;10.0").unwrap_err(),
            Error::ReadingsCsv { line: 1, .. }
        ));
    }
}
