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
/// has most left).
pub(super) fn nnls(
    h: &DMatrix<f64>,
    b: &DVector<f64>,
    free: &[bool],
    pin: Option<(&DVector<f64>, f64)>,
) -> Option<DVector<f64>> {
    let k = b.len();
    let mut passive: Vec<bool> = free.to_vec();
    let mut x = DVector::zeros(k);
    if free.iter().all(|f| *f) {
        // Nothing constrained (after an excursion longer than the slowest decay every decay
        // may take either sign): plain least squares, with the pin if any.
        return solve_masked(h, b, free, pin);
    }
    if let Some((g, theta)) = pin {
        let j = (0..k)
            .filter(|i| !free[*i])
            .max_by(|a, c| g[*a].total_cmp(&g[*c]))?;
        if g[j] <= 0.0 {
            return None;
        }
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
