//! Heating against cooling (VGB's appendix: the bow differs, a hysteresis): the systematic
//! error of each direction's model, the comparison, and the model per direction.

use super::select::{held_out, select, Selection};
use super::{Capture, Error, Fit, ModelKind, Phase};

/// Per point, the mean of (model − measured) over the meshes inside the model's range (the
/// probe noise averages out, a systematic difference stays); the largest |mean|, µm, and how
/// many meshes it took.
fn bias_um(fit: &Fit, caps: &[&Capture]) -> (f64, usize) {
    let inside: Vec<&&Capture> = caps
        .iter()
        .filter(|c| {
            let (lo, hi) = c.span_c();
            lo >= fit.range_c.0 && hi <= fit.range_c.1 && c.points_mm.len() == fit.len()
        })
        .collect();
    if inside.is_empty() {
        return (0.0, 0);
    }
    let n = inside.len() as f64;
    let worst = (0..fit.len())
        .map(|i| {
            let sum: f64 = inside
                .iter()
                .map(|c| fit.predict_point(i, c.temps_c[i]) - c.points_mm[i])
                .sum();
            (sum / n).abs() * 1000.0
        })
        .fold(0.0, f64::max);
    (worst, inside.len())
}

/// [`bias_um`] of leave-one-mesh-out predictions within one direction (`kind` fitted to the
/// others each time): the systematic error a model of this kind makes on its own direction's
/// meshes, µm. `None` when no mesh lies inside the others' range.
fn lomo_bias_um(caps: &[&Capture], kind: ModelKind) -> Option<f64> {
    let n = caps.first()?.points_mm.len();
    let mut sums = vec![0.0; n];
    let mut count = 0usize;
    for (held, f) in held_out(caps, kind) {
        for (i, s) in sums.iter_mut().enumerate() {
            *s += f.predict_point(i, held.temps_c[i]) - held.points_mm[i];
        }
        count += 1;
    }
    (count > 0).then(|| {
        sums.iter()
            .map(|s| (s / count as f64).abs() * 1000.0)
            .fold(0.0, f64::max)
    })
}

/// How the meshes taken while the frame warmed compare with those taken while it cooled
/// (VGB's appendix: the bow differs, a hysteresis).
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize)]
pub struct DirectionComparison {
    /// Largest systematic error, µm, of one direction's model predicting the other
    /// direction's meshes — held out by construction, only those inside the model's range,
    /// averaged per point over the meshes so probe noise does not count.
    pub cross_um: f64,
    /// The same from each direction's own leave-one-mesh-out predictions (what noise and the
    /// model's own error give when the direction does not matter), µm; `None` when no mesh
    /// lies inside the range of the others of its direction.
    pub own_um: Option<f64>,
    /// Meshes predicted across the directions.
    pub n_cross: usize,
}

impl DirectionComparison {
    /// The directions differ: across, the models miss by more than `tolerance_um`, and by
    /// more than twice what they miss within a direction.
    #[must_use]
    pub fn differ(&self, tolerance_um: f64) -> bool {
        self.n_cross > 0
            && self.cross_um > tolerance_um
            && !matches!(self.own_um, Some(o) if self.cross_um <= 2.0 * o)
    }
}

/// Compares two directions, each with its chosen model.
#[must_use]
pub fn compare_directions(
    heating: &Selection,
    heat: &[&Capture],
    cooling: &Selection,
    cool: &[&Capture],
) -> DirectionComparison {
    let (hc, n_hc) = bias_um(&heating.fit, cool);
    let (ch, n_ch) = bias_um(&cooling.fit, heat);
    let own = [
        lomo_bias_um(heat, heating.fit.kind),
        lomo_bias_um(cool, cooling.fit.kind),
    ]
    .into_iter()
    .flatten()
    .reduce(f64::max);
    DirectionComparison {
        cross_um: hc.max(ch),
        own_um: own,
        n_cross: n_hc + n_ch,
    }
}

/// Which meshes the fit used, and why.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize)]
#[serde(rename_all = "snake_case", tag = "kind")]
pub enum Directions {
    /// One model for every direction. `cooling_fitted` false: the cooling meshes (too few to
    /// fit, or none inside the heating range) were judged, not fitted; true: fewer than two
    /// heating meshes, so all meshes were fitted together.
    Single {
        /// Heating meshes.
        heating: usize,
        /// Cooling meshes.
        cooling: usize,
        /// Whether the cooling meshes are in the model.
        cooling_fitted: bool,
    },
    /// Both directions fitted apart agree within the tolerance: one model from all meshes.
    Agree(DirectionComparison),
    /// They differ by more than the tolerance: a model (and profiles) per direction.
    Apart(DirectionComparison),
}

impl Directions {
    /// In words, for the session's notes and the console.
    #[must_use]
    pub fn describe(&self, tolerance_um: f64) -> String {
        let floor = |c: &DirectionComparison| {
            c.own_um
                .map(|o| format!(", {o:.1} µm within a direction"))
                .unwrap_or_default()
        };
        match self {
            Directions::Single {
                cooling: 0,
                heating,
                ..
            } => format!("all {heating} meshes taken while the frame warmed"),
            Directions::Single {
                heating,
                cooling,
                cooling_fitted: false,
            } => format!(
                "{cooling} mesh(es) taken while the frame cooled: too few, or none inside the \
                 heating range, to fit apart — judged, not fitted; the model is the {heating} \
                 heating meshes'"
            ),
            Directions::Single {
                heating, cooling, ..
            } => format!(
                "fewer than two meshes taken while the frame warmed: one model from all {} meshes",
                heating + cooling
            ),
            Directions::Agree(c) => format!(
                "heating and cooling agree (largest systematic difference {:.1} µm, tolerance \
                 {tolerance_um} µm{}): one model from all meshes",
                c.cross_um,
                floor(c)
            ),
            Directions::Apart(c) => format!(
                "heating and cooling differ by up to {:.1} µm (tolerance {tolerance_um} µm{}): a \
                 model and profiles for each direction, followed by the frame's trend",
                c.cross_um,
                floor(c)
            ),
        }
    }
}

/// The model per direction of the frame temperature.
#[derive(Debug, Clone, PartialEq)]
pub struct DirectionalSelection {
    /// The model followed while the frame warms — and in every direction when `cooling` is
    /// `None`.
    pub heating: Selection,
    /// The model followed while the frame cools, when the directions differ.
    pub cooling: Option<Selection>,
    /// Which meshes were fitted, and why.
    pub directions: Directions,
}

/// Fits the heating and the cooling meshes apart when both have enough meshes, and keeps
/// them apart only when they differ by more than `tolerance_um` ([`DirectionComparison`]);
/// otherwise one model (all meshes when the directions agree, the heating ones when the
/// cooling ones cannot be compared).
///
/// # Errors
/// As [`select`] on the meshes used.
pub fn select_directions(
    caps: &[&Capture],
    tolerance_um: f64,
) -> Result<DirectionalSelection, Error> {
    let heat: Vec<&Capture> = caps
        .iter()
        .copied()
        .filter(|c| c.phase == Phase::Heating)
        .collect();
    let cool: Vec<&Capture> = caps
        .iter()
        .copied()
        .filter(|c| c.phase == Phase::Cooling)
        .collect();
    let single = |cooling_fitted: bool| Directions::Single {
        heating: heat.len(),
        cooling: cool.len(),
        cooling_fitted,
    };
    let h = if heat.len() >= 2 {
        select(&heat).ok()
    } else {
        None
    };
    let Some(h) = h else {
        return Ok(DirectionalSelection {
            heating: select(caps)?,
            cooling: None,
            directions: single(!cool.is_empty()),
        });
    };
    let c = if cool.len() >= 2 {
        select(&cool).ok()
    } else {
        None
    };
    let Some(c) = c else {
        return Ok(DirectionalSelection {
            heating: h,
            cooling: None,
            directions: single(false),
        });
    };
    let cmp = compare_directions(&h, &heat, &c, &cool);
    if cmp.n_cross == 0 {
        return Ok(DirectionalSelection {
            heating: h,
            cooling: None,
            directions: single(false),
        });
    }
    if cmp.differ(tolerance_um) {
        return Ok(DirectionalSelection {
            heating: h,
            cooling: Some(c),
            directions: Directions::Apart(cmp),
        });
    }
    Ok(DirectionalSelection {
        heating: select(caps)?,
        cooling: None,
        directions: Directions::Agree(cmp),
    })
}

#[cfg(test)]
mod tests {
    use super::super::judge;
    use super::*;

    /// A 3×3 bed whose bow (6 µm/°C at the centre, less at the edges, slightly curved) lags
    /// by `lag_c` while the frame cools — the cooling mesh at T is the heating one at
    /// T + lag_c (VGB's appendix) — with ±1 µm of probe noise.
    fn hysteresis_set(lag_c: f64, seed: u64) -> Vec<Capture> {
        let mut state = seed;
        let mut noise = move || {
            state = state
                .wrapping_mul(6_364_136_223_846_793_005)
                .wrapping_add(1_442_695_040_888_963_407);
            ((state >> 11) as f64 / (1u64 << 53) as f64 - 0.5) * 0.002
        };
        let gain = [0.3, 0.6, 0.3, 0.6, 1.0, 0.6, 0.3, 0.6, 0.3];
        let mut mesh = |name: String, t: f64, phase: Phase| {
            let d = t - 25.0;
            let pts = gain
                .iter()
                .enumerate()
                .map(|(i, g)| 0.01 * (i as f64 - 4.0) - g * (0.006 * d + 0.0001 * d * d) + noise())
                .collect();
            Capture::uniform(&name, t, pts, phase)
        };
        let mut caps: Vec<Capture> = (0..11)
            .map(|k| {
                let t = 25.0 + 1.5 * f64::from(k);
                mesh(format!("h{t}"), t, Phase::Heating)
            })
            .collect();
        for k in 0..8 {
            let t = 39.0 - 1.5 * f64::from(k);
            let mut c = mesh(format!("c{t}"), t + lag_c, Phase::Cooling);
            c.temps_c = vec![t; c.points_mm.len()];
            caps.push(c);
        }
        caps
    }

    #[test]
    fn heating_and_cooling_that_differ_get_a_model_each() {
        let caps = hysteresis_set(3.0, 7);
        let refs: Vec<&Capture> = caps.iter().collect();
        let d = select_directions(&refs, 5.0).unwrap();
        let Directions::Apart(c) = d.directions else {
            panic!("not kept apart: {:?}", d.directions)
        };
        // 3 °C of lag at 6 µm/°C: ~18 µm at the centre, far above the noise floor.
        assert!(c.cross_um > 12.0 && c.own_um.unwrap() < 3.0, "{c:?}");
        let cooling = d.cooling.expect("a cooling model");
        let cool30 = caps.iter().find(|c| c.name == "c30").unwrap();
        let heat31 = caps.iter().find(|c| c.name == "h31").unwrap();
        // Each direction's model predicts its own meshes and misses the other's.
        assert!(judge(&cooling.fit, cool30).max_um < 3.0);
        assert!(judge(&d.heating.fit, heat31).max_um < 3.0);
        assert!(judge(&d.heating.fit, cool30).max_um > 12.0);
        assert!(judge(&cooling.fit, heat31).max_um > 12.0);
        assert!(d.directions.describe(5.0).contains("differ by up to"));
    }

    #[test]
    fn heating_and_cooling_within_the_tolerance_are_fitted_together() {
        for (lag, seed) in [(0.0, 1), (0.0, 2), (0.4, 3)] {
            let caps = hysteresis_set(lag, seed);
            let refs: Vec<&Capture> = caps.iter().collect();
            let d = select_directions(&refs, 5.0).unwrap();
            let Directions::Agree(c) = d.directions else {
                panic!("lag {lag}: {:?}", d.directions)
            };
            assert!(c.cross_um < 5.0, "lag {lag}: {c:?}");
            assert!(d.cooling.is_none());
            // One model for both: it predicts the cooling meshes too.
            let cool30 = caps.iter().find(|c| c.name == "c30").unwrap();
            assert!(judge(&d.heating.fit, cool30).max_um < 5.0, "lag {lag}");
        }
    }

    #[test]
    fn too_few_cooling_meshes_are_judged_and_not_fitted() {
        let caps = hysteresis_set(3.0, 5);
        // All the heating meshes and one cooling mesh.
        let refs: Vec<&Capture> = caps.iter().take(12).collect();
        let d = select_directions(&refs, 5.0).unwrap();
        assert_eq!(
            d.directions,
            Directions::Single {
                heating: 11,
                cooling: 1,
                cooling_fitted: false
            }
        );
        assert!(d.cooling.is_none());
        assert!(judge(&d.heating.fit, refs[11]).max_um > 12.0);
        let heat_only: Vec<&Capture> = caps.iter().take(11).collect();
        let d = select_directions(&heat_only, 5.0).unwrap();
        assert!(d.directions.describe(5.0).contains("all 11 meshes"));
        // Only cooling meshes: one model from them.
        let cool_only: Vec<&Capture> = caps.iter().skip(11).collect();
        let d = select_directions(&cool_only, 5.0).unwrap();
        assert!(matches!(
            d.directions,
            Directions::Single {
                cooling_fitted: true,
                ..
            }
        ));
        assert!(select_directions(&[], 5.0).is_err());
    }
}
