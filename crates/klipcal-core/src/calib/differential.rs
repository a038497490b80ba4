//! PURE: the paper's differential method (seed 000 §2.2, §3.6): the scale α of one group of
//! pylons from its pair centres, the new rotation_distance, steps/mm, convergence across rounds.

use serde::Serialize;

use super::Error;

/// Scales further than this from 1 are rejected as input errors (±5 %).
pub const SCALE_LIMIT: f64 = 0.05;

/// One pair's centre reading as the group fit needs it.
#[derive(Debug, Clone, PartialEq)]
pub struct PairPoint {
    /// Pair id.
    pub pair: String,
    /// Commanded outer edge-to-edge distance D, mm.
    pub nominal_mm: f64,
    /// Centre reading d, mm.
    pub centre_mm: f64,
    /// Standard uncertainty of the centre, mm.
    pub u_mm: f64,
}

/// The scale of one group.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct GroupScale {
    /// Group id.
    pub group: String,
    /// Measuring direction, degrees from +X.
    pub direction_deg: f64,
    /// α = (d2 − d1)/(D2 − D1) (the weighted slope of d over D with more than two pairs).
    pub scale: f64,
    /// Standard uncertainty of α.
    pub uncertainty: f64,
    /// D2 − D1 (largest minus smallest nominal), mm.
    pub span_mm: f64,
    /// Largest nominal D2, mm.
    pub d2_mm: f64,
    /// Smallest nominal D1, mm.
    pub d1_mm: f64,
    /// Pair ids, nearest first.
    pub pairs: Vec<String>,
}

/// α for one group: (d2 − d1)/(D2 − D1) for two pairs; with more pairs along the same line, the
/// slope of d over D weighted by 1/u² (which is the same formula for two).
///
/// # Errors
/// Fewer than two distinct nominals, a farther pair not reading longer, or |α − 1| > 5 %.
pub fn group_scale(
    group: &str,
    direction_deg: f64,
    points: &[PairPoint],
) -> Result<GroupScale, Error> {
    let mut pts: Vec<&PairPoint> = points.iter().collect();
    pts.sort_by(|a, b| a.nominal_mm.total_cmp(&b.nominal_mm));
    let pair_names = || {
        pts.iter()
            .map(|p| p.pair.as_str())
            .collect::<Vec<_>>()
            .join(", ")
    };
    let (Some(first), Some(last)) = (pts.first(), pts.last()) else {
        return Err(Error::Layout(format!("group {group} has no pairs")));
    };
    let span_mm = last.nominal_mm - first.nominal_mm;
    if pts.len() < 2 || span_mm <= 1e-9 {
        return Err(Error::Layout(format!(
            "group {group} ({}) needs two pairs with different nominal distances",
            pair_names()
        )));
    }
    for w in pts.windows(2) {
        if w[1].centre_mm <= w[0].centre_mm && w[1].nominal_mm > w[0].nominal_mm {
            return Err(Error::NotIncreasing {
                group: group.into(),
                near: w[0].pair.clone(),
                near_mm: w[0].centre_mm,
                far: w[1].pair.clone(),
                far_mm: w[1].centre_mm,
            });
        }
    }
    let weights: Vec<f64> = pts.iter().map(|p| 1.0 / p.u_mm.max(1e-6).powi(2)).collect();
    let sw: f64 = weights.iter().sum();
    let xm = pts
        .iter()
        .zip(&weights)
        .map(|(p, w)| w * p.nominal_mm)
        .sum::<f64>()
        / sw;
    let ym = pts
        .iter()
        .zip(&weights)
        .map(|(p, w)| w * p.centre_mm)
        .sum::<f64>()
        / sw;
    let sxx: f64 = pts
        .iter()
        .zip(&weights)
        .map(|(p, w)| w * (p.nominal_mm - xm).powi(2))
        .sum();
    let sxy: f64 = pts
        .iter()
        .zip(&weights)
        .map(|(p, w)| w * (p.nominal_mm - xm) * (p.centre_mm - ym))
        .sum();
    let scale = sxy / sxx;
    if (scale - 1.0).abs() > SCALE_LIMIT {
        return Err(Error::ScaleOutOfRange {
            group: group.into(),
            pairs: pair_names(),
            scale,
            pct: (scale - 1.0) * 100.0,
            limit_pct: SCALE_LIMIT * 100.0,
        });
    }
    Ok(GroupScale {
        group: group.into(),
        direction_deg,
        scale,
        uncertainty: (1.0 / sxx).sqrt(),
        span_mm,
        d2_mm: last.nominal_mm,
        d1_mm: first.nominal_mm,
        pairs: pts.iter().map(|p| p.pair.clone()).collect(),
    })
}

/// The paper's update: new rotation_distance = current × α.
#[must_use]
pub fn new_rotation_distance(current_mm: f64, scale: f64) -> f64 {
    current_mm * scale
}

/// Steps per mm for firmware that uses it: full_steps × microsteps × gear_ratio / rotation_distance.
#[must_use]
pub fn steps_per_mm(
    full_steps_per_rotation: u32,
    microsteps: u32,
    gear_ratio: f64,
    rotation_distance_mm: f64,
) -> f64 {
    f64::from(full_steps_per_rotation) * f64::from(microsteps) * gear_ratio / rotation_distance_mm
}

/// A group has converged when |α − 1| is below its precision bound.
#[must_use]
pub fn converged(scale: f64, precision: f64) -> bool {
    (scale - 1.0).abs() < precision
}

/// Compares two rounds' scales of the same groups (same order, `(label, α)`), the second printed
/// after applying the first's correction. When a correction made a group's error larger (by
/// more than `precision`), returns a warning that the two motors may be swapped.
#[must_use]
pub fn swap_warning(
    previous: &[(String, f64)],
    now: &[(String, f64)],
    precision: f64,
    motor_names: &str,
) -> Option<String> {
    let worse: Vec<String> = previous
        .iter()
        .filter_map(|(label, before)| {
            let (_, after) = now.iter().find(|(l, _)| l == label)?;
            let (eb, ea) = ((before - 1.0).abs(), (after - 1.0).abs());
            (ea > eb + precision)
                .then(|| format!("{label}: |α−1| {:.3} % → {:.3} %", eb * 100.0, ea * 100.0))
        })
        .collect();
    (!worse.is_empty()).then(|| {
        format!(
            "the last correction made the error larger ({}); {motor_names} may be swapped (check which stepper drives which direction)",
            worse.join("; ")
        )
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn pt(pair: &str, nominal_mm: f64, centre_mm: f64) -> PairPoint {
        PairPoint {
            pair: pair.into(),
            nominal_mm,
            centre_mm,
            u_mm: 0.0037,
        }
    }

    #[test]
    fn alpha_is_the_difference_of_readings_over_the_difference_of_nominals() {
        // seed 000 §2.2: α = (d2 − d1)/(D2 − D1), independent of pylon width.
        let g = group_scale(
            "A",
            45.0,
            &[pt("A-D1", 10.0, 10.05), pt("A-D2", 150.0, 150.33)],
        )
        .expect("valid group");
        assert!((g.scale - (150.33 - 10.05) / 140.0).abs() < 1e-12);
        assert!((g.uncertainty - 0.0037 * 2f64.sqrt() / 140.0).abs() < 1e-12);
        assert_eq!(g.pairs, vec!["A-D1", "A-D2"]);
    }

    #[test]
    fn the_far_pair_reading_shorter_is_an_error_naming_both_pairs() {
        let err = group_scale(
            "A",
            45.0,
            &[pt("A-D1", 10.0, 150.0), pt("A-D2", 150.0, 10.0)],
        )
        .unwrap_err();
        let msg = err.to_string();
        assert!(msg.contains("A-D1") && msg.contains("A-D2"), "{msg}");
    }

    #[test]
    fn a_scale_beyond_five_percent_is_rejected() {
        let err = group_scale(
            "B",
            -45.0,
            &[pt("B-D1", 10.0, 10.0), pt("B-D2", 150.0, 160.0)],
        )
        .unwrap_err();
        assert!(matches!(err, Error::ScaleOutOfRange { .. }));
        assert!(err.to_string().contains("B-D2"));
    }

    #[test]
    fn the_published_converged_result_maps_through_rotation_distance() {
        // seed README: one author converged at 40.10289 / 39.94284 from 40.
        let a = 40.10289 / 40.0;
        assert!((new_rotation_distance(40.0, a) - 40.10289).abs() < 1e-9);
        assert!((steps_per_mm(400, 64, 1.0, 40.0) - 640.0).abs() < 1e-12);
    }

    #[test]
    fn convergence_compares_against_the_precision_bound() {
        assert!(converged(1.0002, 2.5e-4));
        assert!(!converged(1.0003, 2.5e-4));
    }

    #[test]
    fn a_correction_that_made_things_worse_suggests_swapped_motors() {
        let before = vec![("A".to_string(), 1.01), ("B".to_string(), 0.99)];
        let after_swapped = vec![("A".to_string(), 1.02), ("B".to_string(), 0.98)];
        let after_good = vec![("A".to_string(), 1.0001), ("B".to_string(), 0.9999)];
        let w = swap_warning(&before, &after_swapped, 2.5e-4, "A and B").expect("warns");
        assert!(w.contains("A and B may be swapped"), "{w}");
        assert!(swap_warning(&before, &after_good, 2.5e-4, "A and B").is_none());
    }
}
