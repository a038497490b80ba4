//! PURE: least squares with non-negative coefficients (Lawson–Hanson) where the model says
//! so, optionally pinned to one linear constraint.

use nalgebra::{DMatrix, DVector};

/// Solves the least-squares problem restricted to the indices where `mask` is set (the others
/// 0), with `pin` = (g, θ) under gᵀx = θ (the KKT system, solved by LU).
fn solve_masked(
    h: &DMatrix<f64>,
    b: &DVector<f64>,
    mask: &[bool],
    pin: Option<(&DVector<f64>, f64)>,
) -> Option<DVector<f64>> {
    let idx: Vec<usize> = (0..mask.len()).filter(|i| mask[*i]).collect();
    let mut x = DVector::zeros(mask.len());
    if idx.is_empty() {
        return Some(x);
    }
    let m = idx.len();
    let extra = usize::from(pin.is_some());
    let mut kkt = DMatrix::zeros(m + extra, m + extra);
    let mut rhs = DVector::zeros(m + extra);
    // A tiny ridge: neighbouring decays of the grid are nearly collinear.
    let ridge = 1e-13 * (0..m).map(|i| h[(idx[i], idx[i])]).fold(1e-300, f64::max);
    for i in 0..m {
        for j in 0..m {
            kkt[(i, j)] = h[(idx[i], idx[j])];
        }
        kkt[(i, i)] += ridge;
        rhs[i] = b[idx[i]];
    }
    if let Some((g, theta)) = pin {
        for i in 0..m {
            kkt[(i, m)] = g[idx[i]];
            kkt[(m, i)] = g[idx[i]];
        }
        rhs[m] = theta;
    }
    let s = kkt
        .clone()
        .lu()
        .solve(&rhs)
        .filter(|s| s.iter().all(|v| v.is_finite()));
    let s = match s {
        Some(s) => s,
        None => kkt.svd(true, true).solve(&rhs, 1e-14).ok()?,
    };
    for (k, i) in idx.iter().enumerate() {
        x[*i] = s[k];
    }
    Some(x)
}

/// Least squares from the normal equations (`h` = XᵀX, `b` = Xᵀy) with `x[i] ≥ 0` wherever
/// `free[i]` is false, and with `pin` = (g, θ) also gᵀx = θ: Lawson and Hanson's active-set
/// method, started from a feasible point (with a pin: all of θ in the constrained decay that
/// has most left, else in the free one that has).
pub(super) fn nnls(
    h: &DMatrix<f64>,
    b: &DVector<f64>,
    free: &[bool],
    pin: Option<(&DVector<f64>, f64)>,
) -> Option<DVector<f64>> {
    // The pin scaled to its largest entry: a decay far into its fall holds a tiny share of its
    // amplitude now, and an unscaled pin on it is lost to rounding in the KKT system (the solve
    // then misses the pin, and a remaining fall that costs the fit dearly passes as free).
    let scaled = match pin {
        Some((g, theta)) => {
            let m = g.amax();
            if m <= 0.0 {
                return None;
            }
            Some((g / m, theta / m))
        }
        None => None,
    };
    let pin = scaled.as_ref().map(|(g, t)| (g, *t));
    let k = b.len();
    let mut passive: Vec<bool> = free.to_vec();
    let mut x = DVector::zeros(k);
    if free.iter().all(|f| *f) {
        // Nothing constrained (after an excursion longer than the slowest decay every decay
        // may take either sign): plain least squares, with the pin if any.
        return solve_masked(h, b, free, pin);
    }
    if let Some((g, theta)) = pin {
        // A constrained decay takes θ if one reaches the pin; else a free one (all the decays
        // the pin weighs may take either sign, as after an overshoot).
        let largest = |only_constrained: bool| {
            (0..k)
                .filter(|i| !only_constrained || !free[*i])
                .max_by(|a, c| g[*a].abs().total_cmp(&g[*c].abs()))
                .filter(|j| g[*j] != 0.0 && (!only_constrained || g[*j] > 0.0))
        };
        let j = largest(true).or_else(|| largest(false))?;
        x[j] = theta / g[j];
        passive[j] = true;
    }
    let tol = 1e-10 * h.diagonal().max().max(1.0) * 1e-3;
    let mut first = true;
    for _ in 0..4 * k {
        if !first {
            // The gradient of the Lagrangian: with a pin, its multiplier is the one that makes
            // the passive components' gradients zero (their mean, as they are all equal).
            let mut w = b - h * &x;
            if let Some((g, _)) = pin {
                let (mut num, mut den) = (0.0, 0.0);
                for i in (0..k).filter(|i| passive[*i]) {
                    num += w[i] * g[i];
                    den += g[i] * g[i];
                }
                if den > 0.0 {
                    let lambda = num / den;
                    w.axpy(-lambda, g, 1.0);
                }
            }
            let pick = (0..k)
                .filter(|i| !passive[*i])
                .max_by(|a, c| w[*a].total_cmp(&w[*c]));
            let Some(j) = pick.filter(|j| w[*j] > tol) else {
                break;
            };
            passive[j] = true;
        }
        first = false;
        for _ in 0..4 * k {
            let s = solve_masked(h, b, &passive, pin)?;
            let bad: Vec<usize> = (0..k)
                .filter(|i| passive[*i] && !free[*i] && s[*i] <= 0.0)
                .collect();
            if bad.is_empty() {
                x = s;
                break;
            }
            let alpha = bad
                .iter()
                .map(|i| x[*i] / (x[*i] - s[*i]))
                .fold(1.0, f64::min)
                .clamp(0.0, 1.0);
            x += (s - &x) * alpha;
            for i in 0..k {
                if passive[i] && !free[i] && x[i] <= 1e-15 {
                    passive[i] = false;
                    x[i] = 0.0;
                }
            }
        }
    }
    Some(x)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Three decays sampled over 60 bins: one fast and free, two slow and non-negative.
    fn problem() -> (DMatrix<f64>, DVector<f64>) {
        let taus = [3.0, 20.0, 40.0];
        let x = DMatrix::from_fn(60, 4, |i, j| {
            if j == 0 {
                1.0
            } else {
                (-(i as f64) / taus[j - 1]).exp()
            }
        });
        let y = DVector::from_fn(60, |i, _| 0.3 + 0.1 * (-(i as f64) / 20.0).exp());
        (x.transpose() * &x, x.transpose() * y)
    }

    /// A pin whose entries are all tiny (decays long into their fall) is still met: before the
    /// pin was scaled, the KKT system lost it to rounding and the solve missed it.
    #[test]
    fn a_pin_on_decays_far_into_their_fall_is_met() {
        let (h, b) = problem();
        let g = DVector::from_vec(vec![0.0, 1e-40, 3e-21, 2e-12]);
        let x = nnls(&h, &b, &[true, true, false, false], Some((&g, 0.05))).expect("solved");
        let got = g.dot(&x);
        assert!((got - 0.05).abs() < 1e-6 * 0.05, "g·x = {got}, pinned 0.05");
    }

    /// A pin that only free decays reach (every decay it weighs may take either sign) has a
    /// feasible start: before, the solve gave up.
    #[test]
    fn a_pin_only_free_decays_reach_is_met() {
        let (h, b) = problem();
        let g = DVector::from_vec(vec![0.0, 0.2, 0.0, 0.0]);
        let x = nnls(&h, &b, &[true, true, false, false], Some((&g, 0.05))).expect("solved");
        assert!((g.dot(&x) - 0.05).abs() < 1e-9, "g·x = {}", g.dot(&x));
        assert!(x[2] >= 0.0 && x[3] >= 0.0, "{x}");
    }

    /// A pin no decay reaches cannot be met.
    #[test]
    fn a_pin_no_decay_reaches_is_refused() {
        let (h, b) = problem();
        let g = DVector::zeros(4);
        assert!(nnls(&h, &b, &[true, true, false, false], Some((&g, 0.05))).is_none());
    }
}
