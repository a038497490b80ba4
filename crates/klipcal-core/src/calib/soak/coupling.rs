//! PURE: the coupling G from thermistor to print surface, identified from the bed's own
//! heat-up (its lag and heat capacity) or taken from its preset, with the interval the rule uses.

use nalgebra::{DMatrix, DVector};
use serde::Serialize;

use super::stack::BED_PRESETS;
use super::{SoakParams, Z};

/// Where the coupling the rule uses came from.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum CouplingSource {
    /// Identified from this bed's own data, lower end included. A heat-up bounds the coupling
    /// only from above (see `bounded_by_heat_up`), so the rule does not use this today.
    Identified,
    /// The user's `soak.bed` preset.
    Preset,
    /// Neither: the weakest coupling of any bed.
    Weakest,
}

/// The coupling G from the thermistor to the print surface, in full power per K: while the
/// thermistor is held at its target, each unit of power the heater no longer gives is a unit
/// less flowing through the stack to the surface, so the surface still warms by ΔP / G.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Coupling {
    /// The value the rule uses: the conservative (low) end.
    pub g: f64,
    /// The interval it lies in (identified: the 95 % interval; preset or weakest: the value).
    pub low: f64,
    /// See `low`.
    pub high: f64,
    /// The stack's own charge time between thermistor and surface, s.
    pub charge_s: f64,
    /// Where it came from.
    pub source: CouplingSource,
    /// Which, and why, in words.
    pub why: String,
    /// Identified: the bed's whole heat capacity at its low end, full power·s/K.
    #[serde(skip)]
    pub heat_capacity: Option<f64>,
}

impl Coupling {
    /// [`Coupling::short`], and why it was not identified when it was not (the benchmarks').
    #[must_use]
    pub fn short_why(&self) -> String {
        match self.why.find("not identified") {
            Some(i) if self.source != CouplingSource::Identified => {
                format!("{} ({})", self.short(), &self.why[i..])
            }
            _ => self.short(),
        }
    }

    /// The coupling in a few words, for a status line: its value, interval and source.
    #[must_use]
    pub fn short(&self) -> String {
        match self.source {
            CouplingSource::Identified => format!(
                "G identified from the heat-up: 1/{:.0} ({})",
                1.0 / self.g,
                if self.high.is_finite() {
                    format!("1/{:.0}–1/{:.0}", 1.0 / self.low, 1.0 / self.high)
                } else {
                    format!("at least 1/{:.0}", 1.0 / self.low)
                }
            ),
            CouplingSource::Preset => {
                format!("G 1/{:.0} from soak.bed, not identified", 1.0 / self.g)
            }
            CouplingSource::Weakest => {
                format!("G 1/{:.0}, the weakest, not identified", 1.0 / self.g)
            }
        }
    }

    /// From `soak.bed`, else the weakest coupling; `not_identified` says why the bed's own
    /// heat-up did not give it.
    #[must_use]
    pub fn fallback(params: &SoakParams, not_identified: &str) -> Self {
        let weakest = BED_PRESETS[BED_PRESETS.len() - 1];
        match BED_PRESETS.iter().find(|b| b.name == params.bed) {
            Some(b) => Coupling {
                g: b.g,
                low: b.g,
                high: b.g,
                charge_s: b.charge_s,
                source: CouplingSource::Preset,
                heat_capacity: None,
                why: format!(
                    "coupling 1/{:.0} of full power per K from soak.bed = \"{}\" ({}); \
                     {not_identified}",
                    1.0 / b.g,
                    b.name,
                    b.words
                ),
            },
            None => Coupling {
                g: weakest.g,
                low: weakest.g,
                high: weakest.g,
                charge_s: weakest.charge_s,
                source: CouplingSource::Weakest,
                heat_capacity: None,
                why: format!(
                    "the weakest coupling, 1/{:.0} of full power per K ({}), as soak.bed \
                     names no build; {not_identified}",
                    1.0 / weakest.g,
                    weakest.words
                ),
            },
        }
    }
}

/// Hold after the band is reached that the identification takes in, s (its "first minutes").
pub const ID_HOLD_S: f64 = 480.0;
/// Fewest heat-up bins the identification needs.
const ID_MIN_HEAT_BINS: usize = 12;

/// One τ's least-squares fit of the identification.
struct IdFit {
    tau: f64,
    coef: DVector<f64>,
    sse: f64,
    inv: DMatrix<f64>,
    res: Vec<f64>,
}

/// The heat-up's lag longer than this is no bed stack's (see [`OPEN_FRAME_TAU_MAX_S`]: the
/// slowest stack's modes add up to at most 10 min, a single layer's to about 5), s.
pub const LAG_MAX_S: f64 = 300.0;

/// Why [`lag_fit`] gave no lag.
#[derive(Debug)]
enum LagError {
    /// The best lag is longer than any bed stack's, s.
    TooSlow(f64),
    /// Anything else, in words.
    Other(String),
}

impl From<String> for LagError {
    fn from(s: String) -> Self {
        LagError::Other(s)
    }
}

impl From<&str> for LagError {
    fn from(s: &str) -> Self {
        LagError::Other(s.to_string())
    }
}

/// The first layer beyond the thermistor, as a heat-up shows it.
#[derive(Debug, Clone, Copy)]
struct Lag {
    /// Its coupling's 95 % interval, full power per K: the low end is the layer's own
    /// (β·G), the high end the most the heat-up allows to the surface (h + G).
    low: f64,
    high: f64,
}

/// The one-lag fit of a cold heat-up and the first minutes of hold, binned:
/// `(t_s, power, temp_c, rate_c_s)` from the first bin on (the bed at room temperature).
///
/// The model is two nodes: the thermistor's, with heat capacity C and losses h, and the
/// stack beyond it, which follows the thermistor through a first-order lag of time constant
/// τ (its heat capacity over G + its own losses h_s). The power balance at the thermistor,
/// `P = C·dT/dt + (h + G)·(T − T₀) − G·β·F_τ(T − T₀)` with F_τ the lag filter and
/// β = G / (G + h_s), is linear in C, a = h + G and b = G·β for each τ: so G lies in [b, a].
/// τ is scanned on a grid; every τ whose fit is within the 95 % profile of the best counts,
/// and the interval is the profile's: at each τ, b and a may move until the fit is worse than
/// the best by 2² σ² (σ from the scatter at the one-minute scale, so a PID's correlated noise
/// widens it). A layer behind the first one whose lag is short or whose share is small (a
/// steel sheet on its magnet) does not show: it only lowers G below b, by at most what its
/// build allows ([`BedPreset::hidden_s`]).
fn lag_fit(bins: &[[f64; 4]]) -> Result<Lag, LagError> {
    let n = bins.len();
    let t0 = heat_up_start(bins)?;
    let taus = tau_grid();
    let fits: Vec<IdFit> = taus
        .iter()
        .filter_map(|tau| one_lag_fit(bins, t0, *tau))
        .collect();
    let best = fits
        .iter()
        .min_by(|a, b| a.sse.total_cmp(&b.sse))
        .ok_or("the heat-up does not fit a bed's heat balance")?;
    if best.tau > LAG_MAX_S {
        return Err(LagError::TooSlow(best.tau));
    }
    // One lag must do: a stack of two layers that show apart (a plate under glass, sensed in
    // the pad) fits a second lag clearly better, and then the first lag is the nearer layer,
    // not the surface: its coupling would be too strong to be safe.
    let two = best_two_lags(bins, t0, &taus);
    // The noise is taken about the richer fit (two lags), so a one-lag model that misses a
    // layer cannot hide its own misfit in the noise it is judged by.
    let (sse2, res) = two.unwrap_or_else(|| (best.sse, best.res.clone()));
    let sigma2 = noise_sigma2(sse2, &res, n);
    if best.sse - sse2 > Z * Z * sigma2 {
        return Err(format!(
            "the heat-up shows more than one layer between the thermistor and the surface (two \
             lags fit it better by {:.0} σ²)",
            (best.sse - sse2) / sigma2
        )
        .into());
    }
    let (low, high) = profile_interval(&fits, best, sigma2);
    if !(low > 0.0 && high.is_finite()) {
        return Err(format!(
            "the heat-up's lag does not show (its low end {low:.4} is not above 0)"
        )
        .into());
    }
    Ok(Lag { low, high })
}

/// The heat-up's starting temperature T₀, once it is long enough and rose enough to identify
/// the coupling from.
fn heat_up_start(bins: &[[f64; 4]]) -> Result<f64, LagError> {
    let n = bins.len();
    if n < ID_MIN_HEAT_BINS + 6 {
        return Err(format!("too short a heat-up to identify the coupling ({n} bins)").into());
    }
    let t0 = bins[0][2];
    let rise = bins.iter().map(|b| b[2]).fold(f64::NEG_INFINITY, f64::max) - t0;
    if rise.is_nan() || rise <= 10.0 {
        return Err(format!(
            "the bed rose only {rise:.1} K from {t0:.1} °C in the part of its heat-up klipcal \
             saw: too little to identify the coupling"
        )
        .into());
    }
    Ok(t0)
}

/// The lag filter of T − T₀ for time constant τ, exact for a linear change within a bin.
fn lag_filtered(bins: &[[f64; 4]], t0: f64, tau: f64) -> Vec<f64> {
    let mut f = 0.0;
    let mut out = Vec::with_capacity(bins.len());
    for (i, b) in bins.iter().enumerate() {
        if i > 0 {
            let dt = b[0] - bins[i - 1][0];
            let x = 0.5 * (b[2] + bins[i - 1][2]) - t0;
            f += (1.0 - (-dt / tau).exp()) * (x - f);
        }
        out.push(f);
    }
    out
}

/// The τ grid the lag is scanned on: 10 s to 1 h, steps of 25 %.
fn tau_grid() -> Vec<f64> {
    let mut taus = Vec::new();
    let mut tau = 10.0;
    while tau <= 3600.0 {
        taus.push(tau);
        tau *= 1.25;
    }
    taus
}

/// The heat balance with one lag of time constant `tau` fitted by least squares (C, a, b),
/// or `None` when it is singular.
fn one_lag_fit(bins: &[[f64; 4]], t0: f64, tau: f64) -> Option<IdFit> {
    let n = bins.len();
    let f = lag_filtered(bins, t0, tau);
    let x = DMatrix::from_fn(n, 3, |i, j| match j {
        0 => bins[i][3],
        1 => bins[i][2] - t0,
        _ => -f[i],
    });
    let y = DVector::from_iterator(n, bins.iter().map(|b| b[1]));
    let xtx = x.transpose() * &x;
    let inv = xtx.clone().try_inverse()?;
    let coef = &inv * (x.transpose() * &y);
    let res: Vec<f64> = (0..n)
        .map(|i| y[i] - x.row(i).dot(&coef.transpose()))
        .collect();
    let sse = res.iter().map(|r| r * r).sum::<f64>();
    coef.iter().all(|c| c.is_finite()).then_some(IdFit {
        tau,
        coef,
        sse,
        inv,
        res,
    })
}

/// The heat balance with two lags `t1` and `t2`: its sum of squares and residuals.
fn two_lag_fit(bins: &[[f64; 4]], t0: f64, t1: f64, t2: f64) -> Option<(f64, Vec<f64>)> {
    let n = bins.len();
    let (f1, f2) = (lag_filtered(bins, t0, t1), lag_filtered(bins, t0, t2));
    let x = DMatrix::from_fn(n, 4, |i, j| match j {
        0 => bins[i][3],
        1 => bins[i][2] - t0,
        2 => -f1[i],
        _ => -f2[i],
    });
    let y = DVector::from_iterator(n, bins.iter().map(|b| b[1]));
    let coef = (x.transpose() * &x).try_inverse()? * (x.transpose() * &y);
    let r = &y - &x * &coef;
    coef.iter()
        .all(|c| c.is_finite())
        .then(|| (r.dot(&r), r.iter().copied().collect()))
}

/// The best two-lag fit over every other τ of the grid (the second lag at least two steps
/// beyond the first).
fn best_two_lags(bins: &[[f64; 4]], t0: f64, taus: &[f64]) -> Option<(f64, Vec<f64>)> {
    let mut two: Option<(f64, Vec<f64>)> = None;
    for (i, t1) in taus.iter().enumerate().step_by(2) {
        for t2 in taus.iter().skip(i + 2).step_by(2) {
            if let Some(v) = two_lag_fit(bins, t0, *t1, *t2) {
                if two.as_ref().map_or(true, |b| v.0 < b.0) {
                    two = Some(v);
                }
            }
        }
    }
    two
}

/// The noise variance σ² at the one-minute scale (blocks of 6 bins) and beyond, at least the
/// white one: a PID's noise is correlated, and single bins would understate it.
fn noise_sigma2(sse2: f64, res: &[f64], n: usize) -> f64 {
    let white = sse2 / (n - 4) as f64;
    let m = 6;
    let blocks: Vec<f64> = res
        .chunks_exact(m)
        .map(|c| c.iter().sum::<f64>() / m as f64)
        .collect();
    let long = if blocks.len() >= 4 {
        m as f64 * blocks.iter().map(|b| b * b).sum::<f64>() / blocks.len() as f64
    } else {
        white
    };
    white.max(long)
}

/// G's interval [b, a] over the 95 % profile: every τ whose fit is within 2² σ² of the best,
/// each widened by the exact profile at that τ.
fn profile_interval(fits: &[IdFit], best: &IdFit, sigma2: f64) -> (f64, f64) {
    let (mut low, mut high) = (f64::INFINITY, f64::NEG_INFINITY);
    for IdFit {
        coef: c, sse, inv, ..
    } in fits
    {
        // The 95 % profile: a fit worse than the best by more than 2² σ² is ruled out.
        if (sse - best.sse) > 4.0 * sigma2 {
            continue;
        }
        // The exact profile at this τ (the model is linear in the rest): b may move until the
        // fit has spent what is left of the 2² σ².
        let slack = (4.0 * sigma2 - (sse - best.sse)).max(0.0);
        let half = |k: usize| (slack * inv[(k, k)]).max(0.0).sqrt();
        low = low.min(c[2] - half(2));
        high = high.max(c[1] + half(1));
    }
    (low, high)
}

/// The bed's whole heat capacity, full power·s/K, at its low end, from the energy of a cold
/// heat-up and the first minutes of hold (binned as in [`lag_fit`]): what went in, less the
/// most that can have been lost, over the thermistor's rise. The losses are at most the last
/// two minutes' power per kelvin of rise (the power is still falling then) times the
/// integral of the thermistor's rise; the stack beyond a pad's thermistor is cooler than it
/// and not yet quite charged, so dividing by the thermistor's rise only lowers the answer.
///
/// That holds only while the bed is not giving heat back. Under a model-predictive control
/// (Kalico's MPC) the bed overshoots its band and then returns its stored heat: the power
/// dips below its final value while the temperature falls, so the last two minutes' power
/// is below the losses and the answer came out above the true heat capacity on about a
/// quarter of MPC beds (a correction by the thermistor's own fall was not enough: the
/// surface, further over its final temperature, falls faster). A thermistor that fell by
/// more than [`FALL_C`] over the last two minutes gives no heat capacity from its end: the
/// heat-up is then cut at its highest reading (the last one, where it first turned back), and
/// judged there. At its peak the thermistor's node neither takes nor gives heat, and the layers
/// that lag it (the plate and surface beyond a pad's thermistor, the surface beyond a
/// plate's) still take heat in; a pad on the far side of a plate's thermistor holds too little
/// to matter, and the two minutes' mean power before the peak is higher still: the power
/// taken for the losses is above them, as this bound needs.
fn heat_capacity_low(bins: &[[f64; 4]]) -> Result<f64, String> {
    match heat_capacity_to_end(bins) {
        Err(why) if why.starts_with("the bed fell") => {
            let peak = bins
                .iter()
                .enumerate()
                .fold(0, |m, (i, b)| if b[2] > bins[m][2] { i } else { m });
            let cut = &bins[..=peak];
            if peak + 1 < ID_MIN_HEAT_BINS + 6 || bins[peak][0] - bins[0][0] < 240.0 {
                return Err(why);
            }
            heat_capacity_to_end(cut).map_err(|_| why)
        }
        other => other,
    }
}

/// [`heat_capacity_low`] with the heat-up judged at its last bin.
fn heat_capacity_to_end(bins: &[[f64; 4]]) -> Result<f64, String> {
    let n = bins.len();
    let t0 = bins[0][2];
    let end = bins[n - 1][0];
    let tail: Vec<&[f64; 4]> = bins.iter().filter(|b| end - b[0] < 120.0).collect();
    let k = tail.len() as f64;
    let p_end = tail.iter().map(|b| b[1]).sum::<f64>() / k;
    let rise_end = tail.iter().map(|b| b[2]).sum::<f64>() / k - t0;
    let fall = tail[0][2] - tail[tail.len() - 1][2];
    if fall > FALL_C {
        return Err(format!(
            "the bed fell {fall:.2} K in the last two minutes of the hold (a controller that \
             overshot its band gives heat back, so its power is below the losses)"
        ));
    }
    let (mut energy, mut rise_s) = (0.0, 0.0);
    for w in bins.windows(2) {
        let dt = w[1][0] - w[0][0];
        energy += w[1][1] * dt;
        rise_s += 0.5 * (w[0][2] + w[1][2] - 2.0 * t0) * dt;
    }
    // A smaller fall still gives heat back: the losses are the power plus C times the fall
    // rate, C on both sides.
    let fall_rate = (-tail.iter().map(|b| b[3]).sum::<f64>() / k).max(0.0);
    let c = (energy - p_end / rise_end * rise_s) / (rise_end + rise_s * fall_rate / rise_end);
    if !(c.is_finite() && c > 0.0) {
        return Err(format!(
            "the heat-up's energy gives no heat capacity ({c:.2} full power·s/K)"
        ));
    }
    Ok(c)
}

/// Under Kalico's MPC (`control: mpc`) the heat-up's heat capacity is capped at the one
/// MPC_CALIBRATE gave Kalico's model of the bed (`block_heat_capacity / heater_power`): the
/// power's dip after the band can leave the heat-up's figure above the bed's, and a smaller
/// capacity only lowers the G used (the safe side).
fn mpc_capped(capacity: Result<f64, String>, params: &SoakParams) -> Result<f64, String> {
    match (capacity, params.heater.mpc_heat_capacity) {
        (Ok(c), Some(m)) if params.heater.mpc && m < c => Ok(m),
        (c, _) => c,
    }
}

/// A fall of the thermistor's reading over the last two minutes of the hold beyond which
/// the bed is giving heat back (more than a PID's limit cycle and the readings' noise), K.
const FALL_C: f64 = 0.15;

/// Identifies the coupling from a cold heat-up and the first minutes of hold, binned:
/// `(t_s, power, temp_c, rate_c_s)` from the first bin on (the bed at room temperature), for
/// the build `soak.bed` names (or the weakest, unnamed).
///
/// Its low end is the strongest of three lower bounds, each from the build's materials
/// ([`BedPreset`]): the weakest G such a build can have; C/(R·c)_max with C the bed's own heat
/// capacity ([`heat_capacity_low`]); and, where the layer a heat-up cannot show is a quick one
/// (a sheet on its magnet), the heat-up's own lag plus that layer, 1/(1/b + hidden/C). Its
/// high end is the lag's (h + G). A lag longer than any bed stack's (a plant this does not
/// describe) is not identified.
///
/// # Errors
/// Why the heat-up does not give the coupling, in words.
pub fn identify_coupling(bins: &[[f64; 4]], params: &SoakParams) -> Result<Coupling, String> {
    let lag = match lag_fit(bins) {
        Ok(l) => Some(l),
        Err(LagError::TooSlow(tau)) => {
            return Err(format!(
                "the heat-up shows a lag of {:.1} min, longer than any bed stack's ({:.0} min): \
                 something slower than the bed is in it",
                tau / 60.0,
                LAG_MAX_S / 60.0
            ))
        }
        Err(LagError::Other(why))
            if why.starts_with("too short") || why.starts_with("the bed rose") =>
        {
            return Err(why)
        }
        Err(LagError::Other(_)) => None,
    };
    let capacity = mpc_capped(heat_capacity_low(bins), params);
    let c = match (&capacity, lag) {
        (Ok(c), _) => *c,
        // Without a heat capacity only the lag and the build bound G from below.
        (Err(_), Some(_)) => 0.0,
        (Err(why), None) => return Err(why.clone()),
    };
    let named = BED_PRESETS.iter().find(|b| b.name == params.bed);
    let build = *named.unwrap_or(&BED_PRESETS[BED_PRESETS.len() - 1]);
    let from_c = c / build.rc_s;
    let from_lag = match (lag, build.hidden_s) {
        (Some(l), Some(h)) => 1.0 / (1.0 / l.low + h / c),
        _ => 0.0,
    };
    let high = lag.map_or(f64::INFINITY, |l| l.high);
    let mut low = build.g.max(from_c).max(from_lag);
    let mut note = String::new();
    if low > high {
        // The heat-up allows less than the build can have: the build is not what soak.bed
        // says (or this is not a bed stack); the heat-up's upper end is all that is left.
        low = high;
        note = format!(
            "; the heat-up allows at most 1/{:.0}, less than a {} can have: is soak.bed right?",
            1.0 / high,
            build.words
        );
    }
    let how = if low == from_lag && from_lag > 0.0 {
        format!(
            "its lag plus at most {:.0} s for a sheet on its magnet",
            build.hidden_s.unwrap_or(0.0)
        )
    } else if low == from_c {
        format!(
            "its heat capacity over the {:.0} s a {} takes at most",
            build.rc_s, build.words
        )
    } else if low == high {
        "the heat-up's upper end".to_string()
    } else {
        format!(
            "no more than the weakest {} (its heat-up allows no better)",
            build.words
        )
    };
    Ok(Coupling {
        g: low,
        low,
        high,
        charge_s: build.charge_s,
        source: CouplingSource::Identified,
        heat_capacity: capacity.as_ref().ok().copied(),
        why: format!(
            "G identified from the heat-up: at least 1/{:.0} of full power per K ({}; {}{}), up \
             to {}; the low end is used{note}",
            1.0 / low,
            how,
            match &capacity {
                Ok(c) if params.heater.mpc_heat_capacity == Some(*c) => format!(
                    "bed heat capacity {c:.1} full power·s/K, MPC_CALIBRATE's (control: mpc)"
                ),
                Ok(c) => format!("bed heat capacity {c:.1} full power·s/K"),
                Err(why) => format!("no heat capacity: {why}"),
            },
            if named.is_some() {
                format!(", soak.bed = \"{}\"", build.name)
            } else {
                ", soak.bed not set: any build".to_string()
            },
            if high.is_finite() {
                format!("1/{:.0}", 1.0 / high)
            } else {
                "an upper end the heat-up does not show".to_string()
            }
        ),
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::calib::soak::test_beds::{run_bed, surface_left, two_node_bed, TARGET_C};

    #[test]
    fn a_cold_heat_up_identifies_the_coupling_within_its_interval_and_questions_a_wrong_preset() {
        // Beds with a stack beyond the thermistor: couplings 1/10–1/40 (R·C 64–256 s).
        for (k, g) in [0.1, 1.0 / 20.0, 1.0 / 40.0].into_iter().enumerate() {
            let bed = two_node_bed(g, 0.4, 6.0, 0.002, 0.012, 0.05, 4.0 * 3600.0, k as u64);
            let (d, at) = run_bed(SoakParams::default(), &bed, 0);
            let c = d.coupling().clone();
            assert_eq!(c.source, CouplingSource::Identified, "G {g}: {}", c.why);
            assert!(
                c.low <= g && g <= c.high && c.g == c.low,
                "G {g} outside [{}, {}]",
                c.low,
                c.high
            );
            // Not weaker than the weakest build allows, and said with its interval.
            assert!(c.low >= BED_PRESETS[BED_PRESETS.len() - 1].g);
            assert!(
                c.why.starts_with("G identified from the heat-up: "),
                "{}",
                c.why
            );
            assert!(c
                .short()
                .contains(&format!("1/{:.0}–1/{:.0}", 1.0 / c.low, 1.0 / c.high)));
            let at = at.unwrap_or_else(|| panic!("G {g} never declared: {}", d.explanation()));
            let left = surface_left(&bed, at);
            assert!(
                left <= 1.0,
                "G {g}: declared at {at} s with {left:.2} K to go"
            );
            // A build stronger than the heat-up allows (a bare plate's 1/5 on these beds) is
            // not believed: the heat-up's upper end is used, and the user is asked.
            let strong = SoakParams {
                bed: "bare-plate".into(),
                ..SoakParams::default()
            };
            let (d, _) = run_bed(strong, &bed, 0);
            let p = d.coupling();
            assert_eq!(p.source, CouplingSource::Identified);
            assert!(p.g <= c.high + 1e-12, "G {g}: used {} over {}", p.g, c.high);
            if c.high < 0.2 {
                assert!(p.why.contains("is soak.bed right?"), "{}", p.why);
            }
        }
    }

    /// A bed whose surface lags its heater by 25 min, far more than any bed stack: the first
    /// minutes of hold cannot show such a lag, its energy shows only the part that charged
    /// (a low heat capacity, which only lowers the low end), and the interval still holds its
    /// G, at the weakest build's low end.
    #[test]
    fn a_heat_up_slower_than_any_bed_stack_still_gets_an_interval_that_holds_its_g() {
        let g = 0.02;
        let bed = two_node_bed(g, 0.4, 48.0, 0.002, 0.012, 0.05, 2.0 * 3600.0, 4);
        let (d, _) = run_bed(SoakParams::default(), &bed, 0);
        let c = d.coupling();
        assert!(c.low <= g && g <= c.high, "{}", c.why);
        assert!(
            c.source == CouplingSource::Weakest
                || (c.low - BED_PRESETS[BED_PRESETS.len() - 1].g).abs() < 1e-12,
            "{}",
            c.why
        );
    }

    #[test]
    fn a_warm_start_falls_back_to_the_preset_or_the_weakest_coupling_and_says_so() {
        let bed = two_node_bed(0.05, 0.4, 6.0, 0.002, 0.012, 0.05, 3.0 * 3600.0, 7);
        // First seen at its target (a daemon primed from the temperature store).
        let from = bed
            .iter()
            .position(|s| (s[2] - TARGET_C).abs() < 0.5)
            .unwrap();
        let (d, _) = run_bed(SoakParams::default(), &bed, from);
        let c = d.coupling();
        assert_eq!(c.source, CouplingSource::Weakest);
        assert!(c.why.contains("warm start"), "{}", c.why);
        assert!(
            d.explanation().contains("warm start"),
            "{}",
            d.explanation()
        );
        let preset = SoakParams {
            bed: "steel-pad".into(),
            ..SoakParams::default()
        };
        let (d, _) = run_bed(preset, &bed, from);
        assert_eq!(d.coupling().source, CouplingSource::Preset);
        let steel_pad = BED_PRESETS
            .iter()
            .find(|b| b.name == "steel-pad")
            .unwrap()
            .g;
        assert!((d.coupling().g - steel_pad).abs() < 1e-12);
        assert!(d.coupling().short().contains("not identified"));
        assert!(
            d.coupling().why.contains("soak.bed = \"steel-pad\""),
            "{}",
            d.coupling().why
        );
        assert!((d.threshold() - steel_pad).abs() < 1e-12);
    }
}
