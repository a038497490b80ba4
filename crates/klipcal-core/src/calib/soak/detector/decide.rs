//! PURE: the detector's likelihood-ratio test: the directions the power may still go, the
//! non-negative fit of the decays and the decision (stable, or what is still waited for).

use nalgebra::DVector;

use super::super::nnls::{bounded_ls, BoundedLsError};
use super::super::Z;
use super::*;

impl SoakDetector {
    /// The directions the power may still go, as the sign the model sees it with: after a
    /// heat-up (the temperature came up into the band) its surroundings only warm and the
    /// power only falls (+1). After a step down they may be warmer than they will be (the bed
    /// was held long at the higher target: the power rises while they cool) or still colder
    /// (it was not: the power falls), and so may a bed first seen already in the band: both
    /// are tested, the rise on the negated power (−1), and both must be ruled out.
    fn directions(&self) -> &'static [f64] {
        if self.approach_above == Some(false) {
            &[1.0]
        } else {
            &[1.0, -1.0]
        }
    }

    /// Which coefficients may take either sign: the constant and the controller's fast decays;
    /// on a bed first seen warm also the plate's (up to a sixth of `tau_max_s`). Only from
    /// equilibrium does a clamped RC network's power fall as a sum of decays that are all
    /// positive; a bed heated before may start with its plate ahead of its surroundings, and
    /// then the plate's part of the power rises while the surroundings' still falls.
    fn free(&self) -> Vec<bool> {
        let warm_free_s = if self.warm_start == Some(true) {
            self.params.tau_max_s / 6.0
        } else {
            0.0
        };
        // With the temperature's answer modelled, the controller's swing is in the data: no
        // decay is left that may take either sign but a warm start's or an excursion's.
        let fast_free = !self.temp_model();
        std::iter::once(true)
            .chain(self.taus.iter().map(|tau| {
                (fast_free && *tau < FREE_TAUS * grid_min_s(&self.params))
                            // An excursion's aftermath (the controller's integral winding back
                            // after an overshoot lifts the power) may go either way, on the
                            // excursion's own time scale.
                            || *tau <= self.excursion_len_s
                            || *tau <= warm_free_s
            }))
            .chain(std::iter::repeat(true).take(extra_cols(&self.params)))
            .collect()
    }

    /// Each coefficient's bounds: the constant and the temperature's rate free; a decay at
    /// most `DECAY_BOUND` times `max_power` either way, and not below 0 unless it is free
    /// (see [`SoakDetector::free`]); the high-passed temperature's (MPC) not below 0 after a
    /// heat-up (the answer of a clamped network to its thermistor's step), else free.
    fn bounds(&self) -> Vec<(f64, f64)> {
        let u = DECAY_BOUND * self.max_power;
        let free = self.free();
        (0..free.len())
            .map(|i| {
                if i > self.taus.len() + EXTRA_COLS && self.temp_model() {
                    (0.0, f64::INFINITY)
                } else if i == 0 || i > self.taus.len() {
                    (f64::NEG_INFINITY, f64::INFINITY)
                } else if free[i] {
                    (-u, u)
                } else {
                    (0.0, u)
                }
            })
            .collect()
    }

    /// Least squares on `sign`·power with the decays' bounds; with `pin` = (g, θ), also
    /// g·c = θ. `Err(true)` when no decays within their bounds meet the pin.
    fn solve(&self, sign: f64, pin: Option<(&DVector<f64>, f64)>) -> Result<Solution, bool> {
        let xty = &self.xty * sign;
        let coef = bounded_ls(&self.xtx, &xty, &self.bounds(), pin)
            .map_err(|e| e == BoundedLsError::PinOutOfBounds)?;
        let sse = (self.yty - 2.0 * coef.dot(&xty) + coef.dot(&(&self.xtx * &coef))).max(0.0);
        if sse.is_finite() && coef.iter().all(|c| c.is_finite()) {
            Ok(Solution { coef, sse })
        } else {
            Err(false)
        }
    }

    /// Noise variance of a bin about the fit: (white, long-run, blocks behind the long-run
    /// estimate). The long-run variance is the one the test needs (the decision rests on the
    /// slow part of the signal): bins' residuals are averaged over blocks as long as the data
    /// allow with at least `MIN_BLOCKS` of them, and the variance of those means is scaled back
    /// to one bin. A PID loop suppresses slow power noise (that is lower), a wandering or
    /// cycling heater has more of it (that is higher).
    fn noise(&self, sign: f64, coef: &DVector<f64>) -> (f64, f64, usize) {
        let k = coef.len();
        let residuals: Vec<f64> = self
            .points
            .iter()
            .zip(self.rows.chunks_exact(k))
            .map(|(p, row)| sign * p.power - nalgebra::DVectorView::from_slice(row, k).dot(coef))
            .collect();
        let n = residuals.len();
        let used = coef.iter().filter(|c| **c != 0.0).count();
        let white =
            residuals.iter().map(|r| r * r).sum::<f64>() / (n.saturating_sub(used)).max(1) as f64;
        let mut m = BLOCK_BINS;
        while n / (2 * m) >= MIN_BLOCKS {
            m *= 2;
        }
        let blocks: Vec<f64> = residuals
            .chunks_exact(m)
            .map(|c| c.iter().sum::<f64>() / m as f64)
            .collect();
        if blocks.len() < MIN_BLOCKS {
            return (white, white, blocks.len());
        }
        let long = m as f64 * blocks.iter().map(|b| b * b).sum::<f64>() / blocks.len() as f64;
        (white, long, blocks.len())
    }

    /// The decays' values at `t_s` (the constant's entry 0): g·c is the power still to fall.
    fn decays_at(&self, t_s: f64) -> DVector<f64> {
        let mut g = self.row(&Point {
            t_s,
            power: 0.0,
            rate_c_s: 0.0,
            hp: [0.0; HP_TAUS.len()],
        });
        g[0] = 0.0;
        // Right after the band is reached the stack is still charging: the surface lags the
        // power by its charge time, so a decay of time constant τ still holds (1 + charge/τ)
        // times more surface warming than its power says (the first-order lag's gain on a
        // decay, to first order); slow decays hold what ΔP / G says.
        // On an open frame, decays slower than the stack and the air are the carriage's and
        // the frame's, which reach the surface only in part (see `open_frame_reach`).
        if self.params.fixed_remaining.is_none() {
            let charge = self.coupling.charge_s;
            let reach = self.reach();
            for (k, tau) in self.taus.iter().enumerate() {
                g[k + 1] *= 1.0 + charge / tau;
                if let Some(r) = reach.filter(|r| *tau > r.whole_s) {
                    g[k + 1] *= r.slow_share;
                }
            }
        }
        g
    }

    /// The likelihood-ratio test in one direction (`sign` +1: what is still to fall; −1: what
    /// is still to rise): the best model, and how much worse the best one is that still has
    /// `max_remaining` to go now.
    fn test(&self, sign: f64, now_s: f64) -> Option<DirectionTest> {
        let best = self.solve(sign, None).ok()?;
        let (white, long, blocks) = self.noise(sign, &best.coef);
        // Few blocks make the one-minute scatter itself uncertain: widen it while they are few.
        let sigma2 = long * (1.0 + 2.0 / (blocks.max(1) as f64).sqrt());
        let g = self.decays_at(now_s);
        let r_hat = g.dot(&best.coef);
        let theta = self.threshold();
        let cost = if r_hat >= theta {
            0.0
        } else if g.amax() == 0.0 {
            // No decay of the model reaches the surface now (an open frame's slow decays on a
            // plate-sensed bed): nothing left to rule out.
            f64::INFINITY
        } else {
            match self.solve(sign, Some((&g, theta))) {
                Ok(s) => (s.sse - best.sse).max(0.0),
                // No decay within its bounds can still hold θ now: ruled out by the bounds.
                Err(true) => f64::INFINITY,
                Err(false) => 0.0,
            }
        };
        // The upper bound, from the cost of θ (exact for a linear model without active
        // constraints: cost = (θ − R̂)² / var R̂).
        let sd_r = if cost > 0.0 {
            (theta - r_hat) * sigma2.sqrt() / cost.sqrt()
        } else {
            f64::INFINITY
        };
        let remaining = r_hat.max(0.0);
        let remaining_upper = if r_hat >= theta {
            r_hat
        } else {
            (r_hat + Z * sd_r).max(remaining)
        };
        // What printing now may cost at 95 % (one-sided): the spread from the cost of a pin
        // above the best fit when θ itself is below it.
        let sd_95 = if sd_r.is_finite() {
            sd_r
        } else {
            let pin = r_hat.max(0.0) + theta;
            self.solve(sign, Some((&g, pin)))
                .ok()
                .map(|s| (s.sse - best.sse).max(0.0))
                .filter(|c| *c > 0.0)
                .map_or(f64::INFINITY, |c| (pin - r_hat) * sigma2.sqrt() / c.sqrt())
        };
        let remaining_95 = (r_hat + 1.645 * sd_95).max(remaining);
        Some(DirectionTest {
            sign,
            best,
            white,
            sigma2,
            remaining,
            remaining_upper,
            remaining_95,
            ruled_out: cost > Z * Z * sigma2,
        })
    }

    /// Soaking, with no fit to tell progress or a wait from yet: `reason`.
    fn soaking_without_a_fit(&mut self, reason: String) {
        self.status = SoakStatus::Soaking {
            progress: 0.0,
            eta_s: None,
            print_now_c: None,
            reason,
        };
        self.explanation = status_reason(&self.status);
    }

    pub(super) fn decide(&mut self, now_s: f64, t0: f64) {
        let p = self.params.clone();
        let span = now_s - t0;
        let Some((t, ruled_out)) = self.chosen_test(now_s) else {
            return;
        };
        let fit = self.decay_fit(&t, now_s);
        self.fit = Some(fit);
        let span_ok = span >= p.min_soak_s;
        let frozen_s = self.frozen_s(now_s);
        let frozen = frozen_s >= FROZEN_S;
        let saturated_recently = self
            .last_saturated_s
            .is_some_and(|t| now_s - t < p.min_soak_s);
        // Early in a soak (or on a bed whose power wanders) the best fit can head for a power
        // the heater cannot give; its numbers would only confuse: say so in words instead.
        let plausible = (-0.05..=self.max_power + 0.05).contains(&fit.final_power)
            && t.remaining <= self.max_power
            && t.remaining_upper <= self.max_power;
        let fit_words = self.fit_words(&fit, &t, plausible);
        let falling = if fit.rising { "rising" } else { "falling" };
        if span_ok && ruled_out && !saturated_recently && !frozen {
            self.status = SoakStatus::Stable { at_s: now_s };
            self.explanation = format!(
                "surface settled, power stopped {falling}: temperature within ±{:.1} °C of {:.1} \
                 °C, soaked {:.1} min; {fit_words}",
                p.temp_band_c,
                self.target_c.unwrap_or(f64::NAN),
                span / 60.0
            );
            return;
        }
        let mut waits = Vec::new();
        if !ruled_out {
            waits.push(still_changing(&fit, plausible, &fit_words));
        }
        if frozen {
            waits.push(format!(
                "the bed's power and temperature have not changed for {:.0} s: are Klipper and \
                 its heater still running?",
                frozen_s
            ));
        }
        if span < p.min_soak_s {
            waits.push(format!(
                "minimum soak: {:.1} of {:.1} min",
                span / 60.0,
                p.min_soak_s / 60.0
            ));
        }
        if saturated_recently {
            waits.push(if self.max_power < 1.0 {
                format!(
                    "the heater was at its max_power ({:.2}) within the minimum soak",
                    self.max_power
                )
            } else {
                "the heater was at full power within the minimum soak".into()
            });
        }
        let eta_s = self.eta_s(span, ruled_out, now_s);
        // The progress a user sees never goes back within a soak (the ETA may).
        let progress = eta_s
            .map_or(0.0, |eta| (span / (span + eta)).clamp(0.0, 1.0))
            .max(self.progress_floor);
        self.progress_floor = progress;
        let print_now_c = (plausible && fit.surface_95_c.is_finite())
            .then(|| self.print_now_bounded(fit.surface_95_c));
        self.status = SoakStatus::Soaking {
            progress,
            eta_s,
            print_now_c,
            reason: waits.join("; "),
        };
        self.explanation = status_reason(&self.status);
    }

    /// The direction test reported and whether every direction is ruled out, or `None` (the
    /// status then says why) while there are too few bins or nothing fits yet.
    fn chosen_test(&mut self, now_s: f64) -> Option<(DirectionTest, bool)> {
        if self.points.len() < MIN_POINTS {
            self.soaking_without_a_fit(format!(
                "collecting power readings ({} of {MIN_POINTS} bins of {:.0} s)",
                self.points.len(),
                self.params.bin_s
            ));
            return None;
        }
        let tests: Option<Vec<DirectionTest>> = self
            .directions()
            .iter()
            .map(|sign| self.test(*sign, now_s))
            .collect();
        let Some(tests) = tests else {
            self.soaking_without_a_fit("power readings do not fit a decay yet".into());
            return None;
        };
        let ruled_out = tests.iter().all(|t| t.ruled_out);
        self.update_projection(&tests, now_s);
        // What is reported: a direction still waited for, and of those (or of all, once
        // both are ruled out) the one that fits the data better.
        let t = tests.into_iter().max_by(|a, b| {
            (!a.ruled_out)
                .cmp(&!b.ruled_out)
                .then(b.best.sse.total_cmp(&a.best.sse))
        })?;
        Some((t, ruled_out))
    }

    /// The decay fit reported for the test `t`: the weighted τ of what is left, the final
    /// power, what may still change and the surface's bounds.
    fn decay_fit(&self, t: &DirectionTest, now_s: f64) -> DecayFit {
        let DirectionTest {
            sign,
            best,
            white,
            sigma2,
            remaining,
            remaining_upper,
            remaining_95,
            ..
        } = t;
        let (sign, white, sigma2) = (*sign, *white, *sigma2);
        let (remaining, remaining_upper, remaining_95) =
            (*remaining, *remaining_upper, *remaining_95);
        let theta = self.threshold();
        let g = self.decays_at(now_s);
        let contrib: Vec<(f64, f64)> = self
            .taus
            .iter()
            .enumerate()
            .map(|(k, tau)| (*tau, best.coef[k + 1] * g[k + 1]))
            .collect();
        let left: f64 = contrib.iter().map(|(_, c)| c.max(0.0)).sum();
        let tau_s = if left > 0.0 {
            contrib.iter().map(|(tau, c)| tau * c.max(0.0)).sum::<f64>() / left
        } else {
            // Nothing left: the τ of the largest decay fitted.
            self.taus
                .iter()
                .zip(best.coef.iter().skip(1))
                .max_by(|a, b| a.1.total_cmp(b.1))
                .map_or(grid_min_s(&self.params), |(tau, _)| *tau)
        };
        let slowest = contrib.last().map_or(0.0, |(_, c)| *c);
        DecayFit {
            tau_s,
            final_power: sign * best.coef[0],
            remaining,
            remaining_upper,
            amplitude: sign * best.coef.iter().skip(1).take(self.taus.len()).sum::<f64>(),
            rising: sign < 0.0,
            tau_unbounded: slowest > 0.5 * remaining.max(theta),
            noise_sd: white.sqrt(),
            test_sd: sigma2.sqrt(),
            noise_inflation: (sigma2 / white.max(1e-18)).sqrt().max(1.0),
            threshold: theta,
            surface_upper_c: self.surface_c(remaining_upper),
            surface_95_c: self.surface_c(remaining_95),
        }
    }

    /// How long the readings have not changed, s, with the heater between off and its cap
    /// (else 0). A heater there always moves a little, and so does a thermistor's reading:
    /// readings frozen for minutes are a stopped Klipper (a shutdown keeps logging its last
    /// values), not a settled bed.
    fn frozen_s(&self, now_s: f64) -> f64 {
        match (self.unchanged_since_s, self.reading) {
            (Some(since), Some((power, _)))
                if power > 0.0 && power < self.params.saturated_power * self.max_power =>
            {
                now_s - since
            }
            _ => 0.0,
        }
    }

    /// The fit in words: what the surface and the power may still do, or (an implausible
    /// fit) that the power is still changing too much to tell.
    fn fit_words(&self, fit: &DecayFit, t: &DirectionTest, plausible: bool) -> String {
        let budget = self.params.surface_budget_c;
        let theta = fit.threshold;
        let sigma2 = t.sigma2;
        let fall = if fit.rising { "rise" } else { "fall" };
        let surface = if fit.rising { "cool" } else { "warm" };
        if plausible {
            format!(
                "the print surface can still {surface} by at most {:.2} K (budget {budget:.1} K); \
                 power best fit {:.2} % still to {fall} (τ {:.1} min, towards {:.1} %), at most \
                 {:.2} % (allowed {:.2} %; power noise {:.2} %); {}; {}",
                fit.surface_upper_c,
                t.remaining * 100.0,
                fit.tau_s / 60.0,
                fit.final_power * 100.0,
                t.remaining_upper * 100.0,
                theta * 100.0,
                sigma2.sqrt() * 100.0,
                self.coupling.why,
                self.slowest_words()
            )
        } else {
            format!(
                "the power is still changing too much to tell where it settles (stable once less \
                 than {:.2} % can still {fall}, the surface's budget of {budget:.1} K; power \
                 noise {:.2} %); {}; {}",
                theta * 100.0,
                sigma2.sqrt() * 100.0,
                self.coupling.why,
                self.slowest_words()
            )
        }
    }

    /// The ETA, s: when the test would rule out what is still to fall (and to rise), were the
    /// best fit the truth and the noise to stay as it is (see [`SoakDetector::projected_s`]),
    /// counted down between its updates; at least the minimum soak's rest and a bin. None when
    /// even [`ETA_HORIZON_S`] is not enough: then the status says only "more than".
    fn eta_s(&self, span: f64, ruled_out: bool, now_s: f64) -> Option<f64> {
        let p = &self.params;
        let left = if ruled_out {
            Some(0.0)
        } else {
            self.projection
                .and_then(|(at, eta)| eta.map(|e| (e - (now_s - at)).max(0.0)))
        };
        left.map(|e| e.max(p.min_soak_s - span).max(p.bin_s))
    }

    /// Updates the projection ([`SoakDetector::projected_s`] over the directions not ruled
    /// out, the longest) once every [`ETA_EVERY_S`] of data.
    fn update_projection(&mut self, tests: &[DirectionTest], now_s: f64) {
        if self
            .projection
            .is_some_and(|(at, _)| now_s - at < ETA_EVERY_S)
        {
            return;
        }
        let mut eta = Some(0.0f64);
        for t in tests.iter().filter(|t| !t.ruled_out) {
            eta = match (eta, self.projected_s(t, now_s)) {
                (Some(a), Some(b)) => Some(a.max(b)),
                _ => None,
            };
        }
        self.projection = Some((now_s, eta));
    }

    /// How long from `now_s` until the test in `t`'s direction would rule out θ, were its best
    /// fit the truth and the noise to stay at `t`'s level: the data to come lie on the best
    /// fit, so the best fit stays the best and costs nothing more, while the model still
    /// holding θ then must also miss them. The data to come are bins on the model's own
    /// decays, summed in closed form; horizons on a grid of factors of 1.25 from one bin to
    /// [`ETA_HORIZON_S`] (more data only rule out more), searched from the last projection's
    /// place on it (it moves a step or two between updates), by halving when it moved far.
    /// None beyond the horizon.
    fn projected_s(&self, t: &DirectionTest, now_s: f64) -> Option<f64> {
        let bin = self.params.bin_s;
        let mut grid = vec![bin];
        while grid[grid.len() - 1] < ETA_HORIZON_S {
            let next = (grid[grid.len() - 1] * 1.25).max(grid[grid.len() - 1] + bin);
            grid.push(next.min(ETA_HORIZON_S));
        }
        let last = grid.len() - 1;
        let passes = |k: usize| self.passes_after(t, now_s, grid[k]);
        // The first grid point at or after the last projection, counted down.
        let guess = self
            .projection
            .and_then(|(at, eta)| eta.map(|e| e - (now_s - at)))
            .map(|e| grid.iter().position(|g| *g >= e).unwrap_or(last));
        let (mut lo, mut hi) = match guess {
            Some(k) if passes(k) => {
                // Down while it still passes, a few steps, then halve what is left.
                let mut k = k;
                let mut steps = 0;
                while k > 0 && steps < 3 && passes(k - 1) {
                    k -= 1;
                    steps += 1;
                }
                if k == 0 || steps < 3 {
                    return Some(grid[k]);
                }
                (0, k)
            }
            Some(k) => {
                let mut k = k;
                let mut steps = 0;
                while k < last && steps < 3 {
                    k += 1;
                    steps += 1;
                    if passes(k) {
                        return Some(grid[k]);
                    }
                }
                if k == last {
                    return None;
                }
                if !passes(last) {
                    return None;
                }
                (k, last)
            }
            None => {
                if !passes(last) {
                    return None;
                }
                if passes(0) {
                    return Some(grid[0]);
                }
                (0, last)
            }
        };
        while hi - lo > 1 {
            let mid = (lo + hi) / 2;
            if passes(mid) {
                hi = mid;
            } else {
                lo = mid;
            }
        }
        Some(grid[hi])
    }

    /// Whether the test in `t`'s direction rules θ out after `ahead_s` more of data on its best
    /// fit (see [`SoakDetector::projected_s`]).
    fn passes_after(&self, t: &DirectionTest, now_s: f64, ahead_s: f64) -> bool {
        let at = now_s + ahead_s;
        let g = self.decays_at(at);
        let theta = self.threshold();
        let c = &t.best.coef;
        if g.dot(c) >= theta {
            return false;
        }
        if g.amax() == 0.0 {
            return true;
        }
        let f = self.future_xtx(now_s, ahead_s);
        let h = &self.xtx + &f;
        let fc = &f * c;
        let b = &self.xty * t.sign + &fc;
        let yty = self.yty + c.dot(&fc);
        match bounded_ls(&h, &b, &self.bounds(), Some((&g, theta))) {
            Ok(x) => {
                let sse = (yty - 2.0 * x.dot(&b) + x.dot(&(&h * &x))).max(0.0);
                sse - t.best.sse > Z * Z * t.sigma2
            }
            Err(e) => e == BoundedLsError::PinOutOfBounds,
        }
    }

    /// XᵀX of the bins from `now_s` over the next `ahead_s` (their rows: 1, each decay, no
    /// temperature change), each entry a geometric sum.
    fn future_xtx(&self, now_s: f64, ahead_s: f64) -> nalgebra::DMatrix<f64> {
        let origin = self.origin_s.unwrap_or(now_s);
        let d0 = (now_s - origin).max(0.0);
        let b = self.params.bin_s;
        let k = (ahead_s / b).round().max(1.0);
        let rates: Vec<f64> = std::iter::once(0.0)
            .chain(self.taus.iter().map(|tau| 1.0 / tau))
            .collect();
        let sum = |a: f64| {
            if a * b < 1e-12 {
                k
            } else {
                let q = (-a * b).exp();
                (-a * d0).exp() * q * (1.0 - q.powf(k)) / (1.0 - q)
            }
        };
        let n = self.taus.len() + 1 + extra_cols(&self.params);
        nalgebra::DMatrix::from_fn(n, n, |i, j| {
            if i >= rates.len() || j >= rates.len() {
                0.0
            } else {
                sum(rates[i] + rates[j])
            }
        })
    }
}

/// The ETA's projection is updated once every this much data, s, and counted down between.
const ETA_EVERY_S: f64 = 120.0;
/// The longest the ETA looks ahead, s (8 h): beyond it the soak says "more than".
pub(super) const ETA_HORIZON_S: f64 = 8.0 * 3600.0;

/// The wait while a direction is not ruled out: a steady change whose end is not in sight, or
/// what the power may still do.
fn still_changing(fit: &DecayFit, plausible: bool, fit_words: &str) -> String {
    let (fall, falling) = if fit.rising {
        ("rise", "rising")
    } else {
        ("fall", "falling")
    };
    if plausible && fit.tau_unbounded && fit.remaining > fit.threshold {
        format!(
            "power still {falling} steadily ({:.3} %/min); the end of the decay is not \
             in sight yet ({fit_words})",
            fit.remaining / fit.tau_s * 6000.0
        )
    } else {
        format!("power may still {fall}: {fit_words}")
    }
}
