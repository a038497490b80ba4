//! PURE: least squares with non-negative coefficients (Lawson–Hanson) where the model says
//! so, optionally pinned to one linear constraint.

use nalgebra::{DMatrix, DVector};

/// Solves the least-squares problem over the indices where `mask` is set, the others held at
/// their values in `x`, with `pin` = (g, θ) under gᵀx = θ (the KKT system, solved by LU).
fn solve_masked(
    h: &DMatrix<f64>,
    b: &DVector<f64>,
    mask: &[bool],
    x: &DVector<f64>,
    pin: Option<(&DVector<f64>, f64)>,
) -> Option<DVector<f64>> {
    let idx: Vec<usize> = (0..mask.len()).filter(|i| mask[*i]).collect();
    let mut out = x.clone();
    if idx.is_empty() {
        return Some(out);
    }
    let fixed: Vec<usize> = (0..mask.len())
        .filter(|i| !mask[*i] && x[*i] != 0.0)
        .collect();
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
        rhs[i] = b[idx[i]] - fixed.iter().map(|j| h[(idx[i], *j)] * x[*j]).sum::<f64>();
    }
    if let Some((g, theta)) = pin {
        for i in 0..m {
            kkt[(i, m)] = g[idx[i]];
            kkt[(m, i)] = g[idx[i]];
        }
        rhs[m] = theta - fixed.iter().map(|j| g[*j] * x[*j]).sum::<f64>();
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
        out[*i] = s[k];
    }
    Some(out)
}

/// Least squares from the normal equations (`h` = XᵀX, `b` = Xᵀy) with `x[i] ≥ 0` wherever
/// `free[i]` is false, and with `pin` = (g, θ) also gᵀx = θ (see [`bounded_ls`]).
#[cfg(test)]
pub(super) fn nnls(
    h: &DMatrix<f64>,
    b: &DVector<f64>,
    free: &[bool],
    pin: Option<(&DVector<f64>, f64)>,
) -> Option<DVector<f64>> {
    let bounds: Vec<(f64, f64)> = free
        .iter()
        .map(|f| {
            if *f {
                (f64::NEG_INFINITY, f64::INFINITY)
            } else {
                (0.0, f64::INFINITY)
            }
        })
        .collect();
    bounded_ls(h, b, &bounds, pin).ok()
}

/// Why [`bounded_ls`] gave no answer.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(super) enum BoundedLsError {
    /// No x within the bounds meets the pin.
    PinOutOfBounds,
    /// The linear algebra failed (a singular system no fallback solved).
    Failed,
}

/// The most gᵀx can reach (`sign` +1) or the least (−1) within the bounds.
fn pin_extreme(g: &DVector<f64>, bounds: &[(f64, f64)], sign: f64) -> f64 {
    g.iter()
        .zip(bounds)
        .map(|(gi, (lo, hi))| {
            let gi = gi * sign;
            if gi > 0.0 {
                gi * hi
            } else if gi < 0.0 {
                gi * lo
            } else {
                0.0
            }
        })
        .sum::<f64>()
        * sign
}

/// Least squares from the normal equations (`h` = XᵀX, `b` = Xᵀy) with each `x[i]` within
/// `bounds[i]` (lo ≤ 0 ≤ hi, either may be infinite), and with `pin` = (g, θ) also gᵀx = θ:
/// the bounded-variable active-set method of Stark and Parker (Lawson and Hanson's, with an
/// upper bound), started from a feasible point (with a pin: θ filled into the constrained
/// decays that reach it most, up to their bounds, else into a free one).
///
/// # Errors
/// [`BoundedLsError::PinOutOfBounds`] when no x within the bounds meets the pin (what the pin
/// asks is impossible under them), [`BoundedLsError::Failed`] when the linear algebra fails.
pub(super) fn bounded_ls(
    h: &DMatrix<f64>,
    b: &DVector<f64>,
    bounds: &[(f64, f64)],
    pin: Option<(&DVector<f64>, f64)>,
) -> Result<DVector<f64>, BoundedLsError> {
    use BoundedLsError::{Failed, PinOutOfBounds};
    // The pin scaled to its largest entry: a decay far into its fall holds a tiny share of its
    // amplitude now, and an unscaled pin on it is lost to rounding in the KKT system (the solve
    // then misses the pin, and a remaining fall that costs the fit dearly passes as free).
    let scaled = match pin {
        Some((g, theta)) => {
            let m = g.amax();
            if m <= 0.0 {
                return Err(PinOutOfBounds);
            }
            Some((g / m, theta / m))
        }
        None => None,
    };
    let pin = scaled.as_ref().map(|(g, t)| (g, *t));
    let k = b.len();
    let unbounded = |i: usize| bounds[i].0 == f64::NEG_INFINITY && bounds[i].1 == f64::INFINITY;
    // Passive: solved for; the others sit at a bound (their value in x).
    let mut passive: Vec<bool> = (0..k).map(|i| bounds[i].0 < 0.0).collect();
    let mut x = DVector::zeros(k);
    if (0..k).all(unbounded) {
        // Nothing constrained (after an excursion longer than the slowest decay every decay
        // may take either sign): plain least squares, with the pin if any.
        return solve_masked(h, b, &passive, &x, pin).ok_or(Failed);
    }
    if let Some((g, theta)) = pin {
        if pin_extreme(g, bounds, 1.0) < theta || pin_extreme(g, bounds, -1.0) > theta {
            return Err(PinOutOfBounds);
        }
        // θ into the constrained decays (lower bound 0) that reach it most, each up to its
        // bound; what is left into the free one that reaches it most, if any.
        let mut order: Vec<usize> = (0..k).filter(|i| g[*i] != 0.0).collect();
        order.sort_by(|a, c| {
            (bounds[*a].0 < 0.0)
                .cmp(&(bounds[*c].0 < 0.0))
                .then(g[*c].abs().total_cmp(&g[*a].abs()))
        });
        let mut left = theta;
        for j in order {
            if left == 0.0 {
                break;
            }
            let want = left / g[j];
            let v = want.clamp(bounds[j].0, bounds[j].1);
            x[j] = v;
            left -= g[j] * v;
            if v == want {
                left = 0.0;
            }
            // A decay filled to its bound stays there until the method frees it.
            passive[j] = v > bounds[j].0 && v < bounds[j].1;
        }
        if left.abs() > 1e-12 * theta.abs().max(1e-300) {
            return Err(PinOutOfBounds);
        }
        if !(0..k).any(|i| passive[i] && g[i] != 0.0) {
            // Every decay the pin weighs sits at a bound: one of them must be solved for to keep
            // the pin: the one it weighs most (the pin's multiplier needs a passive decay).
            if let Some(j) = (0..k)
                .filter(|i| x[*i] != 0.0)
                .max_by(|a, c| g[*a].abs().total_cmp(&g[*c].abs()))
            {
                passive[j] = true;
            }
        }
    }
    let tol = 1e-10 * h.diagonal().max().max(1.0) * 1e-3;
    let at_lo = |x: &DVector<f64>, i: usize| x[i] <= bounds[i].0;
    let mut first = true;
    for _ in 0..4 * k {
        if !first {
            // The gradient of the Lagrangian: with a pin, its multiplier is the one that makes
            // the passive components' gradients zero (their least-squares fit).
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
            // A variable at its lower bound that the fit would raise, or at its upper bound
            // that it would lower.
            let pick = (0..k)
                .filter(|i| !passive[*i])
                .map(|i| (i, if at_lo(&x, i) { w[i] } else { -w[i] }))
                .max_by(|a, c| a.1.total_cmp(&c.1));
            let Some((j, _)) = pick.filter(|(_, v)| *v > tol) else {
                break;
            };
            passive[j] = true;
        }
        first = false;
        for _ in 0..4 * k {
            let s = solve_masked(h, b, &passive, &x, pin).ok_or(Failed)?;
            let out = |i: usize| passive[i] && (s[i] < bounds[i].0 || s[i] > bounds[i].1);
            let bad: Vec<usize> = (0..k).filter(|i| out(*i)).collect();
            if bad.is_empty() {
                x = s;
                break;
            }
            let alpha = bad
                .iter()
                .map(|i| {
                    let bound = if s[*i] < bounds[*i].0 {
                        bounds[*i].0
                    } else {
                        bounds[*i].1
                    };
                    (bound - x[*i]) / (s[*i] - x[*i])
                })
                .fold(1.0, f64::min)
                .clamp(0.0, 1.0);
            x += (&s - &x) * alpha;
            for i in 0..k {
                if !passive[i] {
                    continue;
                }
                let (lo, hi) = bounds[i];
                let span = 1e-15 * (1.0 + x[i].abs());
                if lo.is_finite() && x[i] <= lo + span {
                    passive[i] = false;
                    x[i] = lo;
                } else if hi.is_finite() && x[i] >= hi - span {
                    passive[i] = false;
                    x[i] = hi;
                }
            }
        }
    }
    Ok(x)
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

    /// Every active set by brute force (each variable solved for, or at one of its finite
    /// bounds): the feasible one with the least squared error. The oracle for small problems.
    fn brute_force(
        h: &DMatrix<f64>,
        b: &DVector<f64>,
        bounds: &[(f64, f64)],
        pin: Option<(&DVector<f64>, f64)>,
    ) -> Option<(DVector<f64>, f64)> {
        let k = b.len();
        let mut best: Option<(DVector<f64>, f64)> = None;
        for code in 0..3usize.pow(k as u32) {
            let mut mask = vec![true; k];
            let mut x = DVector::zeros(k);
            let mut c = code;
            let mut ok = true;
            for i in 0..k {
                match c % 3 {
                    1 if bounds[i].0.is_finite() => {
                        mask[i] = false;
                        x[i] = bounds[i].0;
                    }
                    2 if bounds[i].1.is_finite() => {
                        mask[i] = false;
                        x[i] = bounds[i].1;
                    }
                    0 => {}
                    _ => ok = false,
                }
                c /= 3;
            }
            if !ok {
                continue;
            }
            let Some(s) = solve_masked(h, b, &mask, &x, pin) else {
                continue;
            };
            let inside = (0..k).all(|i| s[i] >= bounds[i].0 - 1e-9 && s[i] <= bounds[i].1 + 1e-9);
            let pinned = pin.map_or(true, |(g, t)| (g.dot(&s) - t).abs() < 1e-7);
            if !(inside && pinned) {
                continue;
            }
            let f = s.dot(&(h * &s)) - 2.0 * b.dot(&s);
            if best.as_ref().map_or(true, |(_, bf)| f < *bf) {
                best = Some((s, f));
            }
        }
        best
    }

    /// The bounded solve reaches the brute-force optimum on random problems with decays held
    /// at either bound, with and without a pin; a pin the bounds cannot reach is refused.
    #[test]
    fn bounded_ls_matches_brute_force_over_every_active_set() {
        let mut rng = fastrand::Rng::with_seed(7);
        let taus = [2.0, 4.0, 9.0, 20.0];
        let (mut at_hi, mut at_lo, mut refused) = (0, 0, 0);
        for case in 0..300 {
            let x = DMatrix::from_fn(40, 5, |i, j| {
                if j == 0 {
                    1.0
                } else {
                    (-(i as f64) / taus[j - 1]).exp()
                }
            });
            let truth = [
                0.3,
                1.5 * rng.f64() - 0.5,
                1.5 * rng.f64() - 0.2,
                rng.f64(),
                rng.f64(),
            ];
            let y = DVector::from_fn(40, |i, _| {
                (0..5).map(|j| truth[j] * x[(i, j)]).sum::<f64>() + 0.05 * (rng.f64() - 0.5)
            });
            let (h, b) = (x.transpose() * &x, x.transpose() * y);
            let bounds = [
                (f64::NEG_INFINITY, f64::INFINITY),
                (-0.6, 0.6),
                (0.0, 0.8),
                (0.0, 0.5),
                (0.0, f64::INFINITY),
            ];
            let g = DVector::from_vec(vec![0.0, 0.01, 0.1, 0.3, 0.6]);
            let pin = (case % 2 == 1).then(|| (&g, 0.4 * rng.f64()));
            let got = bounded_ls(&h, &b, &bounds, pin);
            let want = brute_force(&h, &b, &bounds, pin);
            match (got, want) {
                (Ok(got), Some((want, fw))) => {
                    let fg = got.dot(&(&h * &got)) - 2.0 * b.dot(&got);
                    assert!(
                        fg <= fw + 1e-9 * fw.abs().max(1.0),
                        "case {case}: {fg} > {fw}: {got} vs {want}"
                    );
                    for i in 0..5 {
                        assert!(
                            got[i] >= bounds[i].0 - 1e-12 && got[i] <= bounds[i].1 + 1e-12,
                            "case {case}: {got}"
                        );
                    }
                    if let Some((g, t)) = pin {
                        assert!(
                            (g.dot(&got) - t).abs() < 1e-9,
                            "case {case}: pin {} of {t}",
                            g.dot(&got)
                        );
                    }
                    at_hi += usize::from((1..5).any(|i| got[i] == bounds[i].1));
                    at_lo += usize::from((2..5).any(|i| got[i] == 0.0));
                }
                (Err(BoundedLsError::PinOutOfBounds), None) => refused += 1,
                (got, want) => panic!("case {case}: {got:?} vs {want:?}"),
            }
        }
        // The cases reach both bounds, so the test exercises them.
        assert!(at_hi > 20 && at_lo > 20, "{at_hi} {at_lo}");
        // A pin beyond what the bounds allow: 0.01·0.6 + 0.1·0.8 + 0.3·0.5 + 0.6·∞ is reachable,
        // so close the last decay's bound to make it not.
        let (h, b) = problem();
        let g = DVector::from_vec(vec![0.0, 0.2, 0.5, 0.5]);
        let tight = [
            (f64::NEG_INFINITY, f64::INFINITY),
            (-1.0, 1.0),
            (0.0, 0.1),
            (0.0, 0.1),
        ];
        assert_eq!(
            bounded_ls(&h, &b, &tight, Some((&g, 0.31))),
            Err(BoundedLsError::PinOutOfBounds)
        );
        assert!(bounded_ls(&h, &b, &tight, Some((&g, 0.29))).is_ok());
        let _ = refused;
    }
}
