//! PURE: a chamber thermometer read, not guessed (issue 38). The air and frame around an
//! enclosed bed warm for as long as they take, which may be far longer than `tau_max_s`: the
//! heater's power cannot show such a decay, a thermometer in the enclosure can.
//!
//! What the air's warming still to come does to the print surface: the surface sits between
//! the held thermistor (through the stack, conductance G) and the air (convection and
//! radiation, h), so it takes up h/(G + h) of the air's warming, at most
//! [`surface_share`] for the build. The air settles as a first-order decay whose time
//! constant is at most [`CHAMBER_TAU_MAX_S`], so what it still has to rise is at most its rate
//! times that. Its rate is the upper end (about three standard errors) of a straight line
//! through the last `soak.chamber_window_s` of readings (its mean slope over the window is at
//! least the rate now, the air's warming only slowing). The surface's share of what the air
//! may still rise is reserved out of `soak.surface_budget_c`, up to
//! [`CHAMBER_BUDGET_SHARE`] of it: the rule rules out what the bed's power may still do
//! against the rest. While the reserve would need more than that share the chamber is still
//! warming and the soak waits; once it needs no more, nothing around the bed can warm the
//! surface beyond its reserve, so the rule rules out the bed stack's own decays (as on an open
//! frame) instead of assuming `tau_max_s`.

use super::detector::{SoakDetector, SoakStatus};
use super::stack::{StackLimits, BED_PRESETS};
use super::{SoakParams, Z};

/// The slowest enclosure klipcal allows for: its air and frame settle with a time constant of
/// at most this, s. 6 h: a heavy frame and panels (120 kJ/K, ~130 kg of aluminium's worth)
/// behind well-insulated walls (6 W/K) settle in 5.6 h; a Voron-sized enclosure (10–40 kJ/K
/// behind 6–18 W/K) in 10 min to 2 h.
pub const CHAMBER_TAU_MAX_S: f64 = 6.0 * 3600.0;
/// The most a print surface exchanges with the air around it, W/m²K: natural convection
/// (5–10) and radiation (ε 0.95 at 110 °C: about 10).
pub const SURFACE_H_MAX_W_M2K: f64 = 20.0;
/// The most of `soak.surface_budget_c` the air's warming still to come may take; the rest is
/// the bed's own.
pub const CHAMBER_BUDGET_SHARE: f64 = 0.5;

/// The most of the air's warming the print surface takes up on the build `bed` names (the
/// weakest when it names none), whose coupling the rule uses now is `g_used` (full power per
/// K): h/(G + h) = h·R/(1 + h·R) with R the stack's resistance per m² from the thermistor to
/// the surface, at most the build's (or what `g_used` says at the densest heater, when
/// weaker).
#[must_use]
pub fn surface_share(bed: &str, g_used: f64) -> f64 {
    let weakest = BED_PRESETS[BED_PRESETS.len() - 1];
    let b = BED_PRESETS
        .iter()
        .find(|b| b.name == bed)
        .unwrap_or(&weakest);
    let g = if g_used.is_finite() && g_used > 0.0 {
        b.g.min(g_used)
    } else {
        b.g
    };
    let hr = SURFACE_H_MAX_W_M2K / (g * StackLimits::Q_MAX_W_M2);
    hr / (1.0 + hr)
}

/// The chamber's rise, K/h, at or below which its warming still to come reaches the surface
/// by at most its share of the budget (see the module's words).
#[must_use]
pub fn flat_k_per_h(params: &SoakParams, g_used: f64) -> f64 {
    CHAMBER_BUDGET_SHARE * params.surface_budget_c
        / (surface_share(&params.bed, g_used) * CHAMBER_TAU_MAX_S / 3600.0)
}

/// What the chamber's readings say.
#[derive(Debug, Clone, PartialEq)]
pub(crate) enum ChamberTrend {
    /// No reading, or none lately (a sensor that stopped), in words: as without a chamber.
    Unknown(String),
    /// Readings coming in, but less than a window of them yet, in words.
    Filling(String),
    /// Its rise over the window, K/h, and the most it can be (about three standard errors).
    Known {
        /// Fitted rise, K/h.
        k_per_h: f64,
        /// Its upper end at about three standard errors, K/h.
        high_k_per_h: f64,
    },
}

/// A chamber thermometer's readings, by name (`temperature_sensor chamber`, …).
#[derive(Debug, Clone)]
pub(crate) struct Chamber {
    name: String,
    window_s: f64,
    samples: Vec<(f64, f64)>,
    /// The bed's latest sample time: readings older than a quarter of the window by then are
    /// a sensor that stopped, and say nothing of the air now.
    now_s: f64,
    /// What the readings say (see [`Chamber::fit`]), worked out once per reading: the rule
    /// asks for the trend several times per bed sample.
    fitted: ChamberTrend,
}

/// How many means the window's line goes through.
const MEANS: usize = 20;

impl Chamber {
    /// No readings yet from the sensor named `name` (as Klipper's config names it), its trend
    /// taken over `window_s`.
    #[must_use]
    pub(crate) fn new(name: &str, window_s: f64) -> Self {
        Chamber {
            name: name.to_string(),
            window_s,
            samples: Vec::new(),
            now_s: f64::NEG_INFINITY,
            fitted: ChamberTrend::Unknown("no reading yet".into()),
        }
    }

    /// The bed's latest sample time (see `now_s`).
    pub(crate) fn set_now(&mut self, t_s: f64) {
        if t_s.is_finite() {
            self.now_s = self.now_s.max(t_s);
        }
    }

    /// One reading; not finite or not later than the last: ignored.
    pub(crate) fn push(&mut self, t_s: f64, temp_c: f64) {
        if !(t_s.is_finite() && temp_c.is_finite()) {
            return;
        }
        if self.samples.last().is_some_and(|(t, _)| t_s <= *t) {
            return;
        }
        self.samples.push((t_s, temp_c));
        let keep_from = t_s - 2.0 * self.window_s;
        let drop = self.samples.iter().take_while(|s| s.0 < keep_from).count();
        self.samples.drain(..drop);
        self.fitted = self.fit();
    }

    /// The trend over the last window: a straight line through [`MEANS`] means (one a minute
    /// at the default window, so a sensor read often with correlated noise is not taken for a
    /// precise one), its slope's standard error from their scatter about it.
    #[must_use]
    pub(crate) fn trend(&self) -> ChamberTrend {
        let Some(&(now, _)) = self.samples.last() else {
            return ChamberTrend::Unknown("no reading yet".into());
        };
        if self.now_s - now > 0.25 * self.window_s {
            return ChamberTrend::Unknown(format!("no reading for {}", minutes(self.now_s - now)));
        }
        self.fitted.clone()
    }

    /// The trend from the readings alone (no sensor-stopped check): see [`Chamber::trend`].
    /// The readings are in time order, so each mean's readings are one run of them, found by
    /// bisection.
    fn fit(&self) -> ChamberTrend {
        let Some(&(now, _)) = self.samples.last() else {
            return ChamberTrend::Unknown("no reading yet".into());
        };
        let from = now - self.window_s;
        let at = |t: f64| self.samples.partition_point(|s| s.0 < t);
        let first = self.samples.get(at(from)).map_or(now, |s| s.0);
        if now - first < 0.9 * self.window_s {
            return ChamberTrend::Filling(format!(
                "{} of {} of readings",
                minutes(now - first),
                minutes(self.window_s)
            ));
        }
        let step = self.window_s / MEANS as f64;
        let means: Vec<(f64, f64)> = (0..MEANS)
            .filter_map(|k| {
                let (a, b) = (from + step * k as f64, from + step * (k + 1) as f64);
                let i = at(a);
                let v = &self.samples[i..at(b).max(i)];
                let n = v.len() as f64;
                (!v.is_empty()).then(|| {
                    (
                        v.iter().map(|s| s.0).sum::<f64>() / n,
                        v.iter().map(|s| s.1).sum::<f64>() / n,
                    )
                })
            })
            .collect();
        fit_trend(&means)
    }
}

/// A span in words: minutes, or seconds below two minutes (a test's short window).
fn minutes(s: f64) -> String {
    if s < 120.0 {
        format!("{s:.0} s")
    } else {
        format!("{:.0} min", s / 60.0)
    }
}

/// The chamber beside the detector: the same rule with the slowest decay the bed stack's own
/// (as `soak.frame = "open"`), and the chamber's trend deciding between the two. While the
/// chamber still warms neither may end the soak; once it is flat either may, each with the
/// air's share reserved out of its budget; while its first window fills the soak waits for it;
/// without readings (none, or none lately), the settings' rule alone.
#[derive(Debug, Clone)]
pub(crate) struct ChamberGate {
    pub(super) chamber: Chamber,
    pub(super) stack: SoakDetector,
    pub(super) status: SoakStatus,
    pub(super) explanation: String,
    target_c: Option<f64>,
}

impl ChamberGate {
    pub(super) fn new(name: &str, stack: SoakDetector) -> Self {
        ChamberGate {
            chamber: Chamber::new(name, stack.params().chamber_window_s),
            stack,
            status: SoakStatus::Heating,
            explanation: "no samples yet".into(),
            target_c: None,
        }
    }

    /// The surface warming the air may still bring, K, at most the budget's share (which is
    /// what a chamber still warming holds the soak for): reserved out of the rule's budget;
    /// all of the share while the first window fills, none without readings.
    pub(super) fn reserve_c(&self, params: &SoakParams, g_used: f64) -> f64 {
        match self.chamber.trend() {
            ChamberTrend::Unknown(_) => 0.0,
            ChamberTrend::Filling(_) => CHAMBER_BUDGET_SHARE * params.surface_budget_c,
            ChamberTrend::Known { high_k_per_h, .. } => {
                (surface_share(&params.bed, g_used) * high_k_per_h.max(0.0) * CHAMBER_TAU_MAX_S
                    / 3600.0)
                    .min(CHAMBER_BUDGET_SHARE * params.surface_budget_c)
            }
        }
    }

    /// Whether the chamber is flat for the rule (`params`, coupling `g_used`).
    /// None without readings (the settings' rule alone, as without a chamber), false while
    /// the first window fills (the soak waits for it).
    fn flat(&self, params: &SoakParams, g_used: f64) -> Option<bool> {
        match self.chamber.trend() {
            ChamberTrend::Unknown(_) => None,
            ChamberTrend::Filling(_) => Some(false),
            ChamberTrend::Known { high_k_per_h, .. } => {
                Some(high_k_per_h <= flat_k_per_h(params, g_used))
            }
        }
    }

    /// The trend in words for the soak's lines, naming the sensor.
    pub(super) fn words(&self, params: &SoakParams, g_used: f64) -> String {
        let name = &self.chamber.name;
        let window = minutes(self.chamber.window_s);
        let flat = flat_k_per_h(params, g_used);
        let share = surface_share(&params.bed, g_used) * 100.0;
        match (self.chamber.trend(), self.flat(params, g_used)) {
            (ChamberTrend::Unknown(why), _) => {
                format!("chamber sensor {name}: not read ({why}): as without one")
            }
            (ChamberTrend::Filling(why), _) => {
                format!("chamber sensor {name}: not read long enough yet ({why}): waited for")
            }
            (ChamberTrend::Known { k_per_h, .. }, Some(false)) => format!(
                "chamber sensor {name}: still warming ({k_per_h:+.2} K/h over the last {window};                  flat is at most {flat:.2} K/h, where the {share:.0} % of the air's warming                  still to come that reaches the print surface is at most {:.2} K): the                  enclosure's slow warming is waited for",
                CHAMBER_BUDGET_SHARE * params.surface_budget_c
            ),
            (ChamberTrend::Known { high_k_per_h, .. }, _) => format!(
                "chamber sensor {name}: flat (at most {high_k_per_h:+.2} K/h over the last                  {window}; the air's warming still to come may warm the print surface by at                  most {:.2} K, kept out of the budget): nothing around the bed is warming for                  hours, so only the bed stack's own decays are ruled out",
                self.reserve_c(params, g_used)
            ),
        }
    }

    /// The status with the chamber's trend, from the settings' rule's (`main`, `why`, with its
    /// coupling `g_used`) and the stack's.
    pub(super) fn decide(&mut self, main: &SoakStatus, why: &str, target_c: f64, g_used: f64) {
        let params = self.stack.params().clone();
        let words = self.words(&params, g_used);
        let (status, why) = match (self.flat(&params, g_used), main, self.stack.status()) {
            (Some(false), SoakStatus::Stable { .. }, _)
            | (Some(false), _, SoakStatus::Stable { .. }) => (
                SoakStatus::Soaking {
                    progress: 0.0,
                    eta_s: None,
                    reason: words.clone(),
                    print_now_c: None,
                },
                words,
            ),
            (Some(true), _, s @ SoakStatus::Stable { .. }) => {
                (s.clone(), format!("{}; {words}", self.stack.explanation()))
            }
            (_, s, _) => (s.clone(), format!("{why}; {words}")),
        };
        // Once declared, it stays so until the target changes (as the detector's).
        let same = self.target_c.is_some_and(|t| (t - target_c).abs() <= 0.05);
        if !(same && matches!(self.status, SoakStatus::Stable { .. })) {
            self.status = status;
            self.explanation = why;
        }
        if target_c.is_finite() {
            self.target_c = Some(target_c);
        }
    }
}

/// The trend through the window's means (time s, °C): Filling while fewer than 8, else the
/// least-squares slope and its 3σ upper end, K/h.
fn fit_trend(means: &[(f64, f64)]) -> ChamberTrend {
    if means.len() < 8 {
        return ChamberTrend::Filling(format!("{} means of {MEANS}", means.len()));
    }
    let n = means.len() as f64;
    let (mt, my) = (
        means.iter().map(|m| m.0).sum::<f64>() / n,
        means.iter().map(|m| m.1).sum::<f64>() / n,
    );
    let sxx: f64 = means.iter().map(|m| (m.0 - mt).powi(2)).sum();
    let sxy: f64 = means.iter().map(|m| (m.0 - mt) * (m.1 - my)).sum();
    let slope = sxy / sxx;
    let sse: f64 = means
        .iter()
        .map(|m| (m.1 - my - slope * (m.0 - mt)).powi(2))
        .sum();
    // Readings come in 0.01 °C steps: never trust the slope better than that allows.
    let sd = (sse / (n - 2.0)).sqrt().max(0.01 / 12f64.sqrt());
    let se = sd / sxx.sqrt();
    ChamberTrend::Known {
        k_per_h: slope * 3600.0,
        high_k_per_h: (slope + Z * se) * 3600.0,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::calib::soak::test_beds::{run_bed, two_node_bed, TARGET_C};
    use crate::calib::soak::SoakParams;

    /// The same bed with a chamber thermometer that reads `chamber(t)`: when it is declared,
    /// and the last words.
    fn with_chamber(bed: &[[f64; 4]], chamber: impl Fn(f64) -> f64) -> (Option<f64>, String) {
        let mut s =
            SoakDetector::new(SoakParams::default()).with_chamber("temperature_sensor chamber");
        for x in bed {
            s.push_chamber(x[0], (chamber(x[0]) * 100.0).round() / 100.0);
            if let SoakStatus::Stable { at_s } = s.push(x[0], x[1], x[2], TARGET_C) {
                return (Some(at_s), s.explanation().to_string());
            }
        }
        (None, s.explanation().to_string())
    }

    #[test]
    fn a_chamber_that_keeps_warming_holds_the_soak_and_a_flat_one_lets_it_end() {
        let bed = two_node_bed(0.05, 0.4, 6.0, 0.002, 0.012, 0.03, 4.0 * 3600.0, 3);
        let (_, plain) = run_bed(SoakParams::default(), &bed, 0);
        let plain = plain.expect("the bed alone is declared");
        // An enclosure whose air still warms by 1.5 K/h (its decay far slower than tau_max_s):
        // the bed's power cannot show it, the thermometer does.
        let (warming, why) = with_chamber(&bed, |t| 28.0 + 1.5 * t / 3600.0);
        assert_eq!(warming, None, "declared while the chamber warmed: {why}");
        assert!(
            why.contains("temperature_sensor chamber") && why.contains("still warming"),
            "{why}"
        );
        // A flat chamber (an open frame, or an enclosure that has settled): the enclosure's
        // slow decay is ruled out, and the soak ends no later than without the sensor.
        let (flat, why) = with_chamber(&bed, |t| 28.0 + 0.02 * (t / 97.0).sin());
        let flat = flat.unwrap_or_else(|| panic!("never declared with a flat chamber: {why}"));
        assert!(flat <= plain, "flat chamber {flat} s, without {plain} s");
        assert!(
            why.contains("temperature_sensor chamber") && why.contains("flat"),
            "{why}"
        );
    }

    /// The trend as it was worked out before it was kept per reading: every mean's readings
    /// found by a scan of all of them. The kept one must be the same to the last bit.
    fn scanned(c: &Chamber) -> ChamberTrend {
        let Some(&(now, _)) = c.samples.last() else {
            return ChamberTrend::Unknown("no reading yet".into());
        };
        if c.now_s - now > 0.25 * c.window_s {
            return c.trend();
        }
        let from = now - c.window_s;
        let first = c.samples.iter().find(|s| s.0 >= from).map_or(now, |s| s.0);
        if now - first < 0.9 * c.window_s {
            return c.trend();
        }
        let step = c.window_s / MEANS as f64;
        let means: Vec<(f64, f64)> = (0..MEANS)
            .filter_map(|k| {
                let (a, b) = (from + step * k as f64, from + step * (k + 1) as f64);
                let v: Vec<&(f64, f64)> =
                    c.samples.iter().filter(|s| s.0 >= a && s.0 < b).collect();
                let n = v.len() as f64;
                (!v.is_empty()).then(|| {
                    (
                        v.iter().map(|s| s.0).sum::<f64>() / n,
                        v.iter().map(|s| s.1).sum::<f64>() / n,
                    )
                })
            })
            .collect();
        fit_trend(&means)
    }

    /// Readings at an uneven rate with gaps, on a warming and wobbling air: the trend kept per
    /// reading is, bit for bit, the one a scan of the readings gives, at every reading.
    #[test]
    fn the_trend_kept_per_reading_is_the_scanned_one() {
        let mut rng = fastrand::Rng::with_seed(7);
        let mut c = Chamber::new("temperature_sensor chamber", 300.0);
        let mut t = 0.0;
        let mut known = 0;
        for i in 0..3000 {
            t += if i % 500 == 499 {
                40.0
            } else {
                0.3 + rng.f64()
            };
            let air = 30.0 + 0.5 * t / 3600.0 + 0.05 * (t / 37.0).sin() + 0.02 * rng.f64();
            c.push(t, (air * 100.0).round() / 100.0);
            c.set_now(t + 0.5);
            let (kept, scan) = (c.trend(), scanned(&c));
            known += usize::from(matches!(kept, ChamberTrend::Known { .. }));
            match (&kept, &scan) {
                (
                    ChamberTrend::Known {
                        k_per_h: a,
                        high_k_per_h: b,
                    },
                    ChamberTrend::Known {
                        k_per_h: x,
                        high_k_per_h: y,
                    },
                ) => assert!(a.to_bits() == x.to_bits() && b.to_bits() == y.to_bits()),
                _ => assert_eq!(kept, scan, "at {t} s"),
            }
        }
        assert!(known > 2000, "{known}");
    }

    #[test]
    fn a_chamber_trend_needs_a_full_window_and_ignores_bad_readings() {
        let mut c = Chamber::new("temperature_fan chamber", 1200.0);
        for i in 0..600 {
            c.push(f64::from(i), 30.0);
        }
        assert!(
            matches!(c.trend(), ChamberTrend::Filling(_)),
            "{:?}",
            c.trend()
        );
        c.push(f64::NAN, 30.0);
        c.push(10.0, 80.0);
        for i in 600..1300 {
            c.push(f64::from(i), 30.0);
        }
        let ChamberTrend::Known { high_k_per_h, .. } = c.trend() else {
            panic!("{:?}", c.trend())
        };
        let p = SoakParams::default();
        assert!(high_k_per_h <= flat_k_per_h(&p, 1.0), "{high_k_per_h}");
        let gate = ChamberGate {
            chamber: c,
            stack: SoakDetector::new(p.clone()),
            status: SoakStatus::Heating,
            explanation: String::new(),
            target_c: None,
        };
        assert!(gate
            .words(&p, 1.0)
            .starts_with("chamber sensor temperature_fan chamber: flat"));
    }

    #[test]
    fn a_chamber_that_stopped_reporting_says_nothing_of_the_air_now() {
        let mut c = Chamber::new("temperature_sensor chamber", 1200.0);
        for i in 0..1300 {
            c.push(f64::from(i), 30.0);
        }
        c.set_now(1300.0);
        assert!(matches!(c.trend(), ChamberTrend::Known { .. }));
        c.set_now(1299.0 + 301.0);
        match c.trend() {
            ChamberTrend::Unknown(why) => assert_eq!(why, "no reading for 5 min"),
            other => panic!("{other:?}"),
        }
    }

    /// The surface's share of the air's warming is the most a build allows (glass on a
    /// pad-sensed plate the most, a bare plate the least), and a chamber flat enough leaves at
    /// most the budget's share for the air: the weakest build's flat rise is about 0.3 K/h.
    #[test]
    fn the_air_reaches_the_surface_by_the_builds_share_and_flat_reserves_at_most_its_share() {
        let weakest = surface_share("", f64::INFINITY);
        assert!((0.25..0.3).contains(&weakest), "{weakest}");
        assert!(surface_share("bare-plate", f64::INFINITY) < 0.02);
        assert!(surface_share("steel-pad", f64::INFINITY) < weakest);
        // A heat-up weaker than the build named widens the share.
        let steel = BED_PRESETS.iter().find(|b| b.name == "steel-pad").unwrap();
        assert!(surface_share("steel-pad", steel.g / 2.0) > surface_share("steel-pad", steel.g));
        let p = SoakParams::default();
        let flat = flat_k_per_h(&p, f64::INFINITY);
        assert!((0.25..0.35).contains(&flat), "{flat}");
        let left = weakest * flat * CHAMBER_TAU_MAX_S / 3600.0;
        assert!((left - CHAMBER_BUDGET_SHARE * p.surface_budget_c).abs() < 1e-9);
    }

    /// A test's window of seconds (soak.chamber_window_s) takes its means over a twentieth of
    /// it: a rise shows within it, a flat chamber is flat.
    #[test]
    fn a_short_window_reads_a_short_test_chamber() {
        let mut warm = Chamber::new("temperature_sensor chamber", 60.0);
        let mut flat = Chamber::new("temperature_sensor chamber", 60.0);
        for i in 0..200 {
            let t = f64::from(i) * 0.5;
            warm.push(t, ((30.0 + 0.01 * t) * 100.0f64).round() / 100.0);
            flat.push(t, 30.0);
        }
        let p = SoakParams {
            bed: "bare-plate".into(),
            surface_budget_c: 0.1,
            bin_s: 0.5,
            chamber_window_s: 60.0,
            ..SoakParams::default()
        };
        let limit = flat_k_per_h(&p, f64::INFINITY);
        match (warm.trend(), flat.trend()) {
            (ChamberTrend::Known { k_per_h, .. }, ChamberTrend::Known { high_k_per_h, .. }) => {
                assert!((k_per_h - 36.0).abs() < 1.0, "{k_per_h}");
                assert!(high_k_per_h <= limit, "{high_k_per_h} over {limit}");
            }
            other => panic!("{other:?}"),
        }
    }
}
