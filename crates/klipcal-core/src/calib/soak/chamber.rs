//! PURE: a chamber thermometer read, not guessed (issue 38). The air and frame around an
//! enclosed bed warm for as long as they take, which may be far longer than `tau_max_s`: the
//! heater's power cannot show such a decay, a thermometer in the enclosure can. While it still
//! warms, the soak waits; once it is flat (its rise over the last [`CHAMBER_WINDOW_S`] at most
//! [`CHAMBER_FLAT_K_PER_H`] at about three standard errors), nothing around the bed is still
//! warming for hours, so the rule rules out the bed stack's own decays (as on an open frame)
//! instead of assuming `tau_max_s`.

use super::detector::{SoakDetector, SoakStatus};
use super::Z;

/// The span of chamber readings the trend is taken over, s.
pub const CHAMBER_WINDOW_S: f64 = 1200.0;
/// A chamber warming by at most this, K/h, is flat: with the slowest enclosure's time constant
/// (about 2 h) at most 1 K of air is left to come, and the weakest surface (glass on clips)
/// takes up at most a fifth of its air's warming.
pub const CHAMBER_FLAT_K_PER_H: f64 = 0.5;

/// What the chamber's readings say.
#[derive(Debug, Clone, PartialEq)]
pub(crate) enum ChamberTrend {
    /// Too few readings yet (less than the window), in words.
    Unknown(String),
    /// Still warming (or not shown flat yet): its rise, K/h, and the most it can be.
    Warming {
        /// Fitted rise, K/h.
        k_per_h: f64,
        /// Its upper end at about three standard errors, K/h.
        high_k_per_h: f64,
    },
    /// Flat: its rise at most `high_k_per_h`, K/h, at about three standard errors.
    Flat {
        /// Fitted rise, K/h.
        k_per_h: f64,
        /// See the variant.
        high_k_per_h: f64,
    },
}

/// A chamber thermometer's readings, by name (`temperature_sensor chamber`, …).
#[derive(Debug, Clone)]
pub(crate) struct Chamber {
    name: String,
    samples: Vec<(f64, f64)>,
}

impl Chamber {
    /// No readings yet from the sensor named `name` (as Klipper's config names it).
    #[must_use]
    pub(crate) fn new(name: &str) -> Self {
        Chamber {
            name: name.to_string(),
            samples: Vec::new(),
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
        let keep_from = t_s - 2.0 * CHAMBER_WINDOW_S;
        let drop = self.samples.iter().take_while(|s| s.0 < keep_from).count();
        self.samples.drain(..drop);
    }

    /// The trend over the last [`CHAMBER_WINDOW_S`]: a straight line through one-minute means
    /// (so a sensor read often with correlated noise is not taken for a precise one), its
    /// slope's standard error from their scatter about it.
    #[must_use]
    pub(crate) fn trend(&self) -> ChamberTrend {
        let Some(&(now, _)) = self.samples.last() else {
            return ChamberTrend::Unknown("no reading yet".into());
        };
        let from = now - CHAMBER_WINDOW_S;
        let first = self
            .samples
            .iter()
            .find(|s| s.0 >= from)
            .map_or(now, |s| s.0);
        if now - first < 0.9 * CHAMBER_WINDOW_S {
            return ChamberTrend::Unknown(format!(
                "{:.0} of {:.0} min of readings",
                (now - first) / 60.0,
                CHAMBER_WINDOW_S / 60.0
            ));
        }
        let mut means: Vec<(f64, f64)> = Vec::new();
        let mut k = 0;
        while k * 60 < CHAMBER_WINDOW_S as usize {
            let (a, b) = (from + 60.0 * k as f64, from + 60.0 * (k + 1) as f64);
            let v: Vec<&(f64, f64)> = self
                .samples
                .iter()
                .filter(|s| s.0 >= a && s.0 < b)
                .collect();
            if !v.is_empty() {
                let n = v.len() as f64;
                means.push((
                    v.iter().map(|s| s.0).sum::<f64>() / n,
                    v.iter().map(|s| s.1).sum::<f64>() / n,
                ));
            }
            k += 1;
        }
        if means.len() < 8 {
            return ChamberTrend::Unknown(format!("{} one-minute means", means.len()));
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
        let (k_per_h, high_k_per_h) = (slope * 3600.0, (slope + Z * se) * 3600.0);
        if high_k_per_h <= CHAMBER_FLAT_K_PER_H {
            ChamberTrend::Flat {
                k_per_h,
                high_k_per_h,
            }
        } else {
            ChamberTrend::Warming {
                k_per_h,
                high_k_per_h,
            }
        }
    }

    /// The trend in words for the soak's lines, naming the sensor.
    #[must_use]
    pub(crate) fn words(&self) -> String {
        match self.trend() {
            ChamberTrend::Unknown(why) => format!(
                "chamber sensor {}: not read long enough yet ({why})",
                self.name
            ),
            ChamberTrend::Warming { k_per_h, .. } => format!(
                "chamber sensor {}: still warming ({k_per_h:+.2} K/h over the last {:.0} min; \
                 flat is at most {CHAMBER_FLAT_K_PER_H} K/h): the enclosure's slow warming is \
                 waited for",
                self.name,
                CHAMBER_WINDOW_S / 60.0
            ),
            ChamberTrend::Flat { high_k_per_h, .. } => format!(
                "chamber sensor {}: flat (at most {high_k_per_h:+.2} K/h over the last {:.0} \
                 min): nothing around the bed is warming for hours, so only the bed stack's own \
                 decays are ruled out",
                self.name,
                CHAMBER_WINDOW_S / 60.0
            ),
        }
    }
}

/// The chamber beside the detector: the same rule with the slowest decay the bed stack's own
/// (as `soak.frame = "open"`), and the chamber's trend deciding between the two. While the
/// chamber still warms neither may end the soak; once it is flat either may; before the
/// chamber has been read for a window, the settings' rule alone.
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
            chamber: Chamber::new(name),
            stack,
            status: SoakStatus::Heating,
            explanation: "no samples yet".into(),
            target_c: None,
        }
    }

    /// The status with the chamber's trend, from the settings' rule's (`main`, `why`) and the
    /// stack's.
    pub(super) fn decide(&mut self, main: &SoakStatus, why: &str, target_c: f64) {
        let words = self.chamber.words();
        let (status, why) = match (self.chamber.trend(), main, self.stack.status()) {
            (ChamberTrend::Warming { .. }, SoakStatus::Stable { .. }, _)
            | (ChamberTrend::Warming { .. }, _, SoakStatus::Stable { .. }) => (
                SoakStatus::Soaking {
                    progress: 0.0,
                    eta_s: None,
                    reason: words.clone(),
                    print_now_c: None,
                },
                words,
            ),
            (ChamberTrend::Flat { .. }, _, s @ SoakStatus::Stable { .. }) => {
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

    #[test]
    fn a_chamber_trend_needs_a_full_window_and_ignores_bad_readings() {
        let mut c = Chamber::new("temperature_fan chamber");
        for i in 0..600 {
            c.push(f64::from(i), 30.0);
        }
        assert!(
            matches!(c.trend(), ChamberTrend::Unknown(_)),
            "{:?}",
            c.trend()
        );
        c.push(f64::NAN, 30.0);
        c.push(10.0, 80.0);
        for i in 600..1300 {
            c.push(f64::from(i), 30.0);
        }
        assert!(
            matches!(c.trend(), ChamberTrend::Flat { .. }),
            "{:?}",
            c.trend()
        );
        assert!(c
            .words()
            .starts_with("chamber sensor temperature_fan chamber: flat"));
    }
}
