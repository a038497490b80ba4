//! Every rule judged on one four-node bed against its simulated surface: klipcal's detector,
//! the fixed preheats, and the surface's own moment.

use crate::calib::soak::{SoakDetector, SoakParams, SoakStatus};

use super::klipper::{autotune, heat_up};
use super::{Control, FourNode, Kind, Knobs};

/// What each rule said on one bed, s (None: not within the run).
#[derive(Debug, Clone, Default)]
pub(crate) struct BedResult {
    /// The surface moment: the last time the surface was more than the budget from its final
    /// temperature (∞ when still so at the end of the run).
    pub moment_s: f64,
    /// First reading within 2 °C of the target.
    pub reach_s: f64,
    /// klipcal's rule, issue 10's rule, the pwm-slope rule, the R-statistic test.
    pub rule: Option<f64>,
    /// See `rule`.
    pub today: Option<f64>,
    /// See `rule`.
    pub slope: Option<f64>,
    /// See `rule`.
    pub r_stat: Option<f64>,
    /// The coupling was identified (its lower end from the bed's own data).
    pub identified: bool,
    /// The heat-up gave an upper end of the coupling (identified, or bounding the fallback).
    pub bounded: bool,
    /// The reported interval (the G used to the upper end) held the true G.
    pub covered: bool,
    /// The G the rule used was at or below the true one (the conservative side).
    pub g_safe: bool,
    /// The true G and the G the rule used, full power per K.
    pub g_true: f64,
    /// See `g_true`.
    pub g_used: f64,
    /// The bin noise the detector's test used at its declaration (or the run's end).
    pub sigma: f64,
    /// klipcal's rule with `soak.bed` set to this kind's preset, when asked for.
    pub with_preset: Option<f64>,
    /// With the preset: the coupling was identified, its interval held the true G, and the G
    /// used was at or below it.
    pub preset_identified: bool,
    /// See `preset_identified`.
    pub preset_covered: bool,
    /// See `preset_identified`.
    pub preset_g_safe: bool,
    /// With the preset: the G the rule used, full power per K (NaN without the preset run).
    pub preset_g_used: f64,
    /// Surface left at klipcal's declaration, K.
    pub left_c: f64,
    /// klipcal's rule with `soak.frame = "open"` (on an enclosed bed: the user's error),
    /// without and with the kind's preset (when asked for).
    pub open: Option<f64>,
    /// See `open`.
    pub open_preset: Option<f64>,
    /// `open` and `open_preset` with the coupling not identified (the preset's or the
    /// weakest G, as after a warm start), when the preset is asked for.
    pub open_fixed: Option<f64>,
    /// See `open_fixed`.
    pub open_preset_fixed: Option<f64>,
    /// Surface left at the `open` and `open_preset` declarations, K (0 when not early).
    pub open_left_c: f64,
    /// The bed's slowest clamped time constant, s.
    pub slowest_s: f64,
    /// klipcal's rule with a chamber thermometer in the enclosure's air (`temperature_sensor
    /// chamber`, read once a second with 0.05 °C of noise), without and with the kind's preset.
    pub chamber: Option<f64>,
    /// See `chamber`.
    pub chamber_preset: Option<f64>,
    /// The detector's ETA minus the true time left, min, at 25, 50 and 75 % of its soak from
    /// reaching the target; with the defaults and with the kind's preset (and the frame).
    pub eta_err: [f64; 3],
    /// See `eta_err`.
    pub preset_eta_err: [f64; 3],
}

/// klipcal's rule with a chamber thermometer reading the air node.
fn with_chamber(samples: &[[f64; 6]], params: &SoakParams, rng: &mut fastrand::Rng) -> Option<f64> {
    let mut s = SoakDetector::new(params.clone()).with_chamber("temperature_sensor chamber");
    for x in samples {
        let air = x[5] + 0.05 * crate::cmd::soak_noise::gauss(rng);
        s.push_chamber(x[0], (air * 100.0).round() / 100.0);
        if let SoakStatus::Stable { at_s } = s.push(x[0], x[1], x[2], x[3]) {
            return Some(at_s);
        }
    }
    None
}

/// Runs the detector over the samples; the declaration and the detector.
fn detector(samples: &[[f64; 6]], params: &SoakParams) -> (Option<f64>, SoakDetector) {
    let (at, d, _) = detector_eta(samples, params);
    (at, d)
}

/// [`detector`], and the ETA it stated at each sample `(t_s, eta_s)`.
fn detector_eta(
    samples: &[[f64; 6]],
    params: &SoakParams,
) -> (Option<f64>, SoakDetector, Vec<(f64, f64)>) {
    let mut d = SoakDetector::new(params.clone());
    let mut etas = Vec::new();
    for s in samples {
        match d.push(s[0], s[1], s[2], s[3]) {
            SoakStatus::Stable { at_s } => return (Some(at_s), d, etas),
            SoakStatus::Soaking {
                eta_s: Some(eta), ..
            } => etas.push((s[0], eta)),
            _ => {}
        }
    }
    (None, d, etas)
}

/// The ETA's error (stated minus true time left, min) at 25, 50 and 75 % of the soak from the
/// band to the declaration (NaN where none was stated then or nothing was declared).
fn eta_errors(reach_s: f64, at: Option<f64>, etas: &[(f64, f64)]) -> [f64; 3] {
    let Some(at) = at else {
        return [f64::NAN; 3];
    };
    [0.25, 0.5, 0.75].map(|f| {
        let t = reach_s + f * (at - reach_s);
        etas.iter()
            .rev()
            .find(|e| e.0 <= t && t - e.0 <= 30.0)
            .map_or(f64::NAN, |e| (e.1 - (at - e.0)) / 60.0)
    })
}

/// Every rule on one bed.
#[must_use]
pub(crate) fn judge(bed: &FourNode, samples: &[[f64; 6]], params: &SoakParams) -> BedResult {
    let fin = bed.surface_final_c();
    let budget = params.surface_budget_c;
    let moment_s = match samples.iter().rposition(|s| fin - s[4] > budget) {
        Some(i) if i + 1 == samples.len() => f64::INFINITY,
        Some(i) => samples[i][0],
        None => 0.0,
    };
    let reach_s = samples
        .iter()
        .find(|s| (s[2] - s[3]).abs() <= 2.0)
        .map_or(f64::INFINITY, |s| s[0]);
    let (rule, d, etas) = detector_eta(samples, params);
    let c = d.coupling();
    let g = bed.g_true();
    let identified = c.source == crate::calib::soak::CouplingSource::Identified;
    let today = detector(
        samples,
        &SoakParams {
            fixed_remaining: Some(0.008),
            ..params.clone()
        },
    )
    .0;
    // 10-s means of the power after the target is reached.
    let bins: Vec<(f64, f64)> = samples
        .chunks(10)
        .filter(|c| c[0][0] >= reach_s)
        .map(|c| {
            (
                c[c.len() - 1][0],
                c.iter().map(|s| s[1]).sum::<f64>() / c.len() as f64,
            )
        })
        .collect();
    // pwm slope: the last minute's mean within 2 points of the mean two minutes before.
    let slope = (18..bins.len()).find_map(|i| {
        let m = |a: usize| bins[a - 5..=a].iter().map(|b| b.1).sum::<f64>() / 6.0;
        ((m(i) - m(i - 12)).abs() < 0.02).then_some(bins[i].0)
    });
    // Cao–Rhinehart R statistic on the 10-s means (λ1 0.2, λ2 = λ3 0.1; steady below 2.0,
    // after the filters have run for 5 min).
    let r_stat = {
        let (l1, l2, l3, crit) = (0.2, 0.1, 0.1, 2.0);
        let mut out = None;
        if let Some(&(_, first)) = bins.first() {
            let (mut xf, mut v2, mut d2, mut prev) = (first, 0.0, 0.0, first);
            for (i, &(t, x)) in bins.iter().enumerate().skip(1) {
                v2 = l2 * (x - xf).powi(2) + (1.0 - l2) * v2;
                xf = l1 * x + (1.0 - l1) * xf;
                d2 = l3 * (x - prev).powi(2) + (1.0 - l3) * d2;
                prev = x;
                if i >= 30 && d2 > 0.0 && (2.0 - l1) * v2 / d2 < crit {
                    out = Some(t);
                    break;
                }
            }
        }
        out
    };
    let left_at = |at: Option<f64>| {
        at.map_or(0.0, |at| {
            samples
                .iter()
                .find(|s| s[0] >= at)
                .map_or(0.0, |s| fin - s[4])
        })
    };
    let left_c = left_at(rule);
    let open = detector(
        samples,
        &SoakParams {
            frame: "open".into(),
            ..params.clone()
        },
    )
    .0;
    BedResult {
        moment_s,
        reach_s,
        rule,
        today,
        slope,
        r_stat,
        identified,
        bounded: identified || c.high > c.g,
        covered: c.low <= g && g <= c.high,
        g_safe: c.g <= g,
        g_true: g,
        g_used: c.g,
        sigma: d.fit().map_or(0.0, |f| f.test_sd),
        with_preset: None,
        preset_identified: false,
        preset_covered: false,
        preset_g_safe: false,
        preset_g_used: f64::NAN,
        left_c,
        open,
        open_preset: None,
        open_fixed: None,
        open_preset_fixed: None,
        open_left_c: left_at(open),
        slowest_s: bed.clamped_taus_s()[0],
        chamber: None,
        chamber_preset: None,
        eta_err: eta_errors(reach_s, rule, &etas),
        preset_eta_err: [f64::NAN; 3],
    }
}

/// The `soak.bed` preset a user of this kind of bed would set.
#[must_use]
pub(crate) fn preset_name(kind: Kind) -> &'static str {
    match (kind.glass, kind.pad_sensed) {
        (false, false) => "steel-plate",
        (false, true) => "steel-pad",
        (true, false) => "glass-plate",
        (true, true) => "glass-pad",
    }
}

/// One bed of `kind` from the knobs (random when None) under `control`, tuned (Klipper's
/// PID_CALIBRATE, Kalico's MPC_CALIBRATE) and run for `until_s`; with `preset`, klipcal's rule
/// is also run with `soak.bed` set to the kind's preset; with `chamber`, with a chamber
/// thermometer too. None when the tuning did not finish.
#[must_use]
#[allow(clippy::too_many_arguments)]
pub(crate) fn run_bed(
    kind: Kind,
    control: Control,
    knobs: Option<Knobs>,
    until_s: f64,
    params: &SoakParams,
    preset: bool,
    chamber: bool,
    rng: &mut fastrand::Rng,
) -> Option<BedResult> {
    let bed = match knobs {
        Some(k) => FourNode::new(kind, k, rng),
        None => FourNode::random(kind, rng),
    };
    let mut with_facts = params.clone();
    let samples = match control {
        Control::Pid => {
            let gains = autotune(&bed, rng)?;
            heat_up(&bed, gains, until_s, rng)
        }
        Control::Mpc => {
            let cal = super::kalico::calibrate(&bed, bed.p_max_w, rng).ok()?;
            // What the daemon reads from Kalico's configfile: control: mpc and its calibration.
            with_facts.heater = crate::calib::soak::HeaterFacts::mpc(
                Some(cal.profile.block_heat_capacity),
                Some(cal.profile.heater_power),
            );
            super::kalico::heat_up(&bed, cal.profile, until_s, rng).0
        }
    };
    let params = &with_facts;
    let mut r = judge(&bed, &samples, params);
    if chamber {
        r.chamber = with_chamber(&samples, params, rng);
        r.chamber_preset = with_chamber(
            &samples,
            &SoakParams {
                bed: preset_name(kind).into(),
                ..params.clone()
            },
            rng,
        );
    }
    if preset {
        let with = SoakParams {
            bed: preset_name(kind).into(),
            ..params.clone()
        };
        let (at, d, etas_with) = detector_eta(&samples, &with);
        r.with_preset = at;
        let c = d.coupling();
        r.preset_identified = c.source == crate::calib::soak::CouplingSource::Identified;
        r.preset_covered = c.low <= r.g_true && r.g_true <= c.high;
        r.preset_g_safe = c.g <= r.g_true;
        r.preset_g_used = c.g;
        if kind.enclosed {
            // "enclosed" rules out what an unknown frame does: the run above is the named one.
            r.preset_eta_err = eta_errors(r.reach_s, at, &etas_with);
            return Some(r);
        }
        let (open, _, etas) = detector_eta(
            &samples,
            &SoakParams {
                frame: "open".into(),
                ..with
            },
        );
        r.preset_eta_err = eta_errors(r.reach_s, open, &etas);
        r.open_preset = open;
        let fixed = |p: SoakParams| {
            detector(
                &samples,
                &SoakParams {
                    frame: "open".into(),
                    no_identify: true,
                    ..p
                },
            )
            .0
        };
        r.open_preset_fixed = fixed(SoakParams {
            bed: preset_name(kind).into(),
            ..params.clone()
        });
        r.open_fixed = fixed(params.clone());
        if let Some(at) = open {
            let fin = bed.surface_final_c();
            let left = samples
                .iter()
                .find(|s| s[0] >= at)
                .map_or(0.0, |s| fin - s[4]);
            r.open_left_c = r.open_left_c.max(left);
        }
    }
    Some(r)
}
