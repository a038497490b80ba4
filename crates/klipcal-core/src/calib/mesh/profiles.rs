//! How many profiles, and at which temperatures: the fewest within a tolerance (adaptive
//! spacing), the error of using the nearest one, and VGB's fixed grid.

use super::{max_abs_diff_um, Error, Fit};

/// A profile set: temperatures and the worst error of using the nearest profile.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct ProfilePlan {
    /// Profile temperatures, °C, ascending.
    pub temps_c: Vec<f64>,
    /// Largest |model(T) − model(nearest profile)| over the range, µm.
    pub max_quantisation_um: f64,
}

const GRID_C: f64 = 0.01;

fn grid(lo: f64, hi: f64) -> Vec<f64> {
    let n = ((hi - lo) / GRID_C).ceil().max(1.0) as usize;
    (0..=n)
        .map(|k| lo + (hi - lo) * k as f64 / n as f64)
        .collect()
}

/// Worst error of using the nearest of `temps_c` anywhere in `[lo, hi]`, µm.
#[must_use]
pub fn quantisation_um(fit: &Fit, temps_c: &[f64], lo: f64, hi: f64) -> f64 {
    let meshes: Vec<Vec<f64>> = temps_c.iter().map(|&t| fit.predict(t).points_mm).collect();
    grid(lo, hi)
        .into_iter()
        .map(|t| {
            let k = nearest(temps_c, t);
            max_abs_diff_um(&fit.predict(t).points_mm, &meshes[k])
        })
        .fold(0.0, f64::max)
}

/// Index of the temperature nearest `t` (the lower one on a tie).
#[must_use]
pub fn nearest(temps_c: &[f64], t: f64) -> usize {
    let mut best = 0;
    for (k, &x) in temps_c.iter().enumerate() {
        if (x - t).abs() < (temps_c[best] - t).abs() {
            best = k;
        }
    }
    best
}

/// The fewest profile temperatures over `[lo, hi]` such that the nearest profile is within
/// `tolerance_um` of the model everywhere (greedy: each profile placed as far up as the
/// stretch below it allows, checked on a 0.01 °C grid).
///
/// # Errors
/// A tolerance that is not positive, or an empty range.
pub fn plan_profiles(fit: &Fit, lo: f64, hi: f64, tolerance_um: f64) -> Result<ProfilePlan, Error> {
    if tolerance_um.is_nan() || tolerance_um <= 0.0 {
        return Err(Error::Fit(format!(
            "tolerance {tolerance_um} µm; expected a positive number of µm (default 5)"
        )));
    }
    if hi.is_nan() || lo.is_nan() || hi <= lo {
        return Err(Error::Fit(format!(
            "temperature range {lo}..{hi} °C; expected from < to"
        )));
    }
    // ok(a, b, p): every T in [a, b] within tolerance of the profile at p.
    let ok = |a: f64, b: f64, p: f64| {
        let mp = fit.predict(p).points_mm;
        grid(a, b)
            .into_iter()
            .all(|t| max_abs_diff_um(&fit.predict(t).points_mm, &mp) <= tolerance_um)
    };
    // Largest x in [a, hi] with pred(x) true (pred monotone: true then false).
    let search = |a: f64, pred: &dyn Fn(f64) -> bool| {
        let (mut good, mut bad) = (a, hi);
        if pred(hi) {
            return hi;
        }
        while bad - good > GRID_C / 2.0 {
            let m = 0.5 * (good + bad);
            if pred(m) {
                good = m;
            } else {
                bad = m;
            }
        }
        good
    };
    let floor = |t: f64| ((t * 100.0 + 1e-6).floor() / 100.0).max(lo);
    let mut temps = vec![floor(search(lo, &|p| ok(lo, p, p)))];
    loop {
        let last = *temps.last().unwrap_or(&lo);
        if ok(last, hi, last) {
            break;
        }
        // Next profile p: below the midpoint `last` is nearest, above it p is.
        let pred = |p: f64| {
            let mid = 0.5 * (last + p);
            ok(last, mid, last) && ok(mid, p, p)
        };
        let p = floor(search(last, &pred)).max(last + GRID_C);
        temps.push(p.min(hi));
        if temps.len() > 100_000 {
            return Err(Error::Fit("profile plan does not converge".into()));
        }
    }
    let q = quantisation_um(fit, &temps, lo, hi);
    Ok(ProfilePlan {
        temps_c: temps,
        max_quantisation_um: q,
    })
}

/// VGB's fixed grid: one profile per `step_c` from `lo` to `hi` inclusive.
#[must_use]
pub fn vgb_grid(lo: f64, hi: f64, step_c: f64) -> Vec<f64> {
    let n = ((hi - lo) / step_c + 1e-9).floor() as usize;
    (0..=n).map(|k| lo + k as f64 * step_c).collect()
}

#[cfg(test)]
mod tests {
    use super::super::tests::synth;
    use super::super::{fit, Capture, ModelKind};
    use super::*;

    #[test]
    fn adaptive_profiles_stay_within_tolerance_with_fewer_than_a_fixed_grid() {
        let caps: Vec<Capture> = (0..6)
            .map(|k| synth(25.0 + 3.0 * f64::from(k), 0.0002))
            .collect();
        let refs: Vec<&Capture> = caps.iter().collect();
        let f = fit(&refs, ModelKind::Quadratic).unwrap();
        let plan = plan_profiles(&f, 25.0, 40.0, 5.0).unwrap();
        assert!(plan.max_quantisation_um <= 5.0 + 1e-6, "{plan:?}");
        // Slope ≤ 10 µm/°C: one profile covers ≥ 1 °C, so at most ~16 over 15 °C.
        assert!(
            plan.temps_c.len() <= 16 && plan.temps_c.len() >= 4,
            "{plan:?}"
        );
        assert_eq!(vgb_grid(25.0, 40.0, 0.1).len(), 151);
        assert!(plan_profiles(&f, 25.0, 40.0, 0.0).is_err());
    }
}
