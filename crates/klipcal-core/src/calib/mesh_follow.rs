//! PURE: the follow policy of thermal bed-mesh compensation — given frame temperature samples
//! and their times, decides when to load which `klipcal_<T>` profile: only when the loaded one
//! is off the model by more than the tolerance, with hysteresis, at most once per interval,
//! never while homing/probing, refusing jumps over a limit, and stopping on a stale or
//! out-of-range sensor. When heating and cooling have their own models and profiles, the
//! direction of the frame temperature's trend picks the set. No I/O, no clock: time comes in
//! as `t_s`.

use super::mesh::{max_abs_diff_um, nearest, Fit, Phase};

/// Settings of the follower (config `[mesh]`).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct FollowPolicy {
    /// Load only when the loaded profile is off the model by more than this, µm.
    pub tolerance_um: f64,
    /// The new profile must be nearer than the loaded one by at least this, °C.
    pub hysteresis_c: f64,
    /// At most one load per this many seconds.
    pub min_interval_s: f64,
    /// A load changing the mesh by more than this is refused, µm.
    pub jump_limit_um: f64,
    /// No sample for this long stops following, s.
    pub stale_after_s: f64,
    /// A sample further than this outside the captured range stops following, °C (config
    /// `mesh.range_margin_c`, 0 by default: beyond the range the bed keeps moving and no
    /// profile follows it).
    pub range_margin_c: f64,
    /// The frame counts as cooling once it fell this far below its highest reading since it
    /// last turned, and as heating again once it rose this far above its lowest, °C.
    pub trend_c: f64,
}

impl Default for FollowPolicy {
    fn default() -> Self {
        Self {
            tolerance_um: 5.0,
            hysteresis_c: 0.1,
            min_interval_s: 30.0,
            jump_limit_um: 50.0,
            stale_after_s: 30.0,
            range_margin_c: 0.0,
            trend_c: 0.3,
        }
    }
}

/// The direction of the frame temperature's trend, with a dead band so sensor noise does not
/// flip it: heating until the temperature fell `band_c` below the highest reading since the
/// last turn, then cooling until it rose `band_c` above the lowest. Starts as heating (a
/// print warms the frame).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Trend {
    phase: Phase,
    extreme_c: Option<f64>,
    band_c: f64,
}

impl Trend {
    /// A trend detector with a dead band of `band_c` °C.
    #[must_use]
    pub fn new(band_c: f64) -> Self {
        Self {
            phase: Phase::Heating,
            extreme_c: None,
            band_c,
        }
    }

    /// The direction so far.
    #[must_use]
    pub fn phase(&self) -> Phase {
        self.phase
    }

    /// One reading; returns the direction after it.
    pub fn push(&mut self, temp_c: f64) -> Phase {
        if !temp_c.is_finite() {
            return self.phase;
        }
        let e = *self.extreme_c.get_or_insert(temp_c);
        match self.phase {
            Phase::Heating if temp_c < e - self.band_c => {
                self.phase = Phase::Cooling;
                self.extreme_c = Some(temp_c);
            }
            Phase::Heating => self.extreme_c = Some(e.max(temp_c)),
            Phase::Cooling if temp_c > e + self.band_c => {
                self.phase = Phase::Heating;
                self.extreme_c = Some(temp_c);
            }
            Phase::Cooling => self.extreme_c = Some(e.min(temp_c)),
        }
        self.phase
    }
}

/// One direction's model and profiles.
#[derive(Debug, Clone, PartialEq)]
pub struct Branch {
    /// Heating or cooling.
    pub phase: Phase,
    /// Its model.
    pub fit: Fit,
    /// Its profile temperatures, °C.
    pub temps_c: Vec<f64>,
}

/// What the follower asks for after a sample.
#[derive(Debug, Clone, PartialEq)]
pub enum Decision {
    /// Nothing to do (`why` for status).
    Keep {
        /// Why nothing is loaded: "within tolerance", "busy", "interval".
        why: &'static str,
        /// The loaded profile's distance from the model at this temperature now, µm (beyond
        /// the captured range, from the model continued along its slope at the range's end).
        residual_um: f64,
    },
    /// Load this profile.
    Load {
        /// The direction whose profile it is.
        phase: Phase,
        /// Index into that direction's profile list.
        index: usize,
        /// Its temperature, °C.
        temp_c: f64,
        /// The loaded profile's distance from the model at this temperature after the load,
        /// µm (as in `Keep`).
        residual_um: f64,
    },
    /// A load refused: it would change the mesh by more than the jump limit. Following stops.
    RefuseJump {
        /// The direction whose profile it is.
        phase: Phase,
        /// The profile that would have been loaded.
        index: usize,
        /// The change it would make, µm.
        jump_um: f64,
    },
    /// Following stopped (stale or out-of-range sensor, or an earlier refusal).
    Stopped {
        /// Why, for the console.
        reason: String,
    },
}

/// The model's mesh at `temp_c`. Beyond the fitted range (which the range margin allows)
/// the model is continued along its slope at the range's end: the bed keeps moving there, and
/// the clamped model would call the end profile exact.
fn model_mesh(fit: &Fit, temp_c: f64) -> Vec<f64> {
    let p = fit.predict(temp_c);
    if !p.clamped {
        return p.points_mm;
    }
    let (lo, hi) = fit.range_c;
    let end = p.used_temp_c;
    let step = ((hi - lo) / 10.0).clamp(1e-3, 0.5);
    let inner_t = if end >= hi { end - step } else { end + step };
    let inner = fit.predict(inner_t);
    if inner.clamped || (end - inner.used_temp_c).abs() < 1e-9 {
        return p.points_mm;
    }
    let k = (temp_c - end) / (end - inner.used_temp_c);
    p.points_mm
        .iter()
        .zip(&inner.points_mm)
        .map(|(e, i)| e + (e - i) * k)
        .collect()
}

#[derive(Debug, Clone)]
struct Set {
    branch: Branch,
    meshes: Vec<Vec<f64>>,
}

/// The follower's state.
#[derive(Debug, Clone)]
pub struct Follower {
    policy: FollowPolicy,
    /// Heating first; a cooling set when the directions differ.
    sets: Vec<Set>,
    active: Option<Vec<f64>>,
    loaded: Option<(usize, usize)>,
    trend: Trend,
    last_load_t_s: Option<f64>,
    last_sample_t_s: Option<f64>,
    stopped: Option<String>,
    range_c: (f64, f64),
}

impl Follower {
    /// A follower over one profile set (every direction) at `temps_c`, meshes from `fit`.
    /// `active` is the mesh active when following starts (None: no mesh yet, the first load
    /// is free).
    #[must_use]
    pub fn new(policy: FollowPolicy, fit: &Fit, temps_c: &[f64], active: Option<Vec<f64>>) -> Self {
        Self::with_directions(
            policy,
            Branch {
                phase: Phase::Heating,
                fit: fit.clone(),
                temps_c: temps_c.to_vec(),
            },
            None,
            active,
        )
    }

    /// A follower over the heating profiles and, when heating and cooling differ, the
    /// cooling ones: the frame temperature's [`Trend`] picks the set.
    #[must_use]
    pub fn with_directions(
        policy: FollowPolicy,
        heating: Branch,
        cooling: Option<Branch>,
        active: Option<Vec<f64>>,
    ) -> Self {
        let mut range_c = heating.fit.range_c;
        let sets: Vec<Set> = std::iter::once(heating)
            .chain(cooling)
            .map(|b| {
                range_c = (
                    range_c.0.min(b.fit.range_c.0),
                    range_c.1.max(b.fit.range_c.1),
                );
                Set {
                    meshes: b
                        .temps_c
                        .iter()
                        .map(|&t| b.fit.predict(t).points_mm)
                        .collect(),
                    branch: b,
                }
            })
            .collect();
        Self {
            policy,
            sets,
            active,
            loaded: None,
            trend: Trend::new(policy.trend_c),
            last_load_t_s: None,
            last_sample_t_s: None,
            stopped: None,
            range_c,
        }
    }

    /// The loaded profile: its direction and temperature.
    #[must_use]
    pub fn loaded(&self) -> Option<(Phase, f64)> {
        self.loaded.map(|(s, k)| {
            let b = &self.sets[s].branch;
            (b.phase, b.temps_c[k])
        })
    }

    /// The direction of the frame temperature's trend so far.
    #[must_use]
    pub fn trend(&self) -> Phase {
        self.trend.phase()
    }

    fn stop(&mut self, reason: String) -> Decision {
        self.stopped = Some(reason.clone());
        Decision::Stopped { reason }
    }

    /// Checks the sensor is still reporting at `t_s` (call on a timer).
    pub fn tick(&mut self, t_s: f64) -> Option<Decision> {
        if let Some(r) = &self.stopped {
            return Some(Decision::Stopped { reason: r.clone() });
        }
        let last = self.last_sample_t_s?;
        (t_s - last > self.policy.stale_after_s).then(|| {
            self.stop(format!(
                "frame sensor stale: no reading for {:.0} s (limit {:.0} s); mesh following stopped",
                t_s - last,
                self.policy.stale_after_s
            ))
        })
    }

    /// The set for the trend's direction at `temp_c`: cooling's while cooling and inside its
    /// range (± margin), heating's otherwise.
    fn set_for(&self, phase: Phase, temp_c: f64) -> usize {
        let m = self.policy.range_margin_c;
        self.sets
            .iter()
            .position(|s| {
                let (lo, hi) = s.branch.fit.range_c;
                s.branch.phase == phase && temp_c >= lo - m && temp_c <= hi + m
            })
            .unwrap_or(0)
    }

    /// One frame temperature sample. `busy` while homing or probing (never load then).
    pub fn push(&mut self, t_s: f64, temp_c: f64, busy: bool) -> Decision {
        if let Some(d) = self.tick(t_s) {
            return d;
        }
        self.last_sample_t_s = Some(t_s);
        let (lo, hi) = self.range_c;
        let m = self.policy.range_margin_c;
        if !temp_c.is_finite() || temp_c < lo - m || temp_c > hi + m {
            return self.stop(format!(
                "frame temperature {temp_c:.2} °C is outside the captured range {lo:.2}..{hi:.2} °C (± {m} °C); mesh following stopped — capture again to cover it"
            ));
        }
        let phase = self.trend.push(temp_c);
        let s = self.set_for(phase, temp_c);
        let set = &self.sets[s];
        let want = model_mesh(&set.branch.fit, temp_c);
        let cand = nearest(&set.branch.temps_c, temp_c);
        let residual = |(si, k): (usize, usize)| max_abs_diff_um(&want, &self.sets[si].meshes[k]);
        let current = self.loaded.map(residual);
        if let (Some((ls, li)), Some(r)) = (self.loaded, current) {
            let temps = &set.branch.temps_c;
            let same = ls == s;
            let closer = if same {
                (temp_c - temps[li]).abs() - (temp_c - temps[cand]).abs()
            } else {
                f64::INFINITY
            };
            if (same && cand == li)
                || r <= self.policy.tolerance_um
                || closer < self.policy.hysteresis_c
            {
                return Decision::Keep {
                    why: "within tolerance",
                    residual_um: r,
                };
            }
        }
        if busy {
            return Decision::Keep {
                why: "busy",
                residual_um: current.unwrap_or(f64::NAN),
            };
        }
        if let Some(t0) = self.last_load_t_s {
            if t_s - t0 < self.policy.min_interval_s {
                return Decision::Keep {
                    why: "interval",
                    residual_um: current.unwrap_or(f64::NAN),
                };
            }
        }
        let branch_phase = self.sets[s].branch.phase;
        let cand_temp = self.sets[s].branch.temps_c[cand];
        let from = self
            .loaded
            .map(|(si, k)| self.sets[si].meshes[k].clone())
            .or_else(|| self.active.clone());
        if let Some(from) = from {
            let jump = max_abs_diff_um(&from, &self.sets[s].meshes[cand]);
            if jump > self.policy.jump_limit_um {
                self.stopped = Some(format!(
                    "loading profile at {cand_temp:.2} °C would move the mesh by {jump:.0} µm (limit {:.0} µm): following toggled mid-print or the frame sensor failed; mesh following stopped",
                    self.policy.jump_limit_um
                ));
                return Decision::RefuseJump {
                    phase: branch_phase,
                    index: cand,
                    jump_um: jump,
                };
            }
        }
        let after = residual((s, cand));
        self.loaded = Some((s, cand));
        self.last_load_t_s = Some(t_s);
        Decision::Load {
            phase: branch_phase,
            index: cand,
            temp_c: cand_temp,
            residual_um: after,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::calib::mesh::{fit, Capture, ModelKind, Phase};

    /// One point bowing 10 µm/°C from 25 to 45 °C.
    fn model() -> Fit {
        let a = Capture::uniform("a", 25.0, vec![0.0, 0.0], Phase::Heating);
        let b = Capture::uniform("b", 45.0, vec![-0.2, 0.0], Phase::Heating);
        fit(&[&a, &b], ModelKind::Linear).unwrap()
    }

    fn temps() -> Vec<f64> {
        (0..=20).map(|k| 25.0 + f64::from(k)).collect()
    }

    #[test]
    fn loads_only_when_off_by_more_than_the_tolerance_and_not_more_often_than_the_interval() {
        let f = model();
        let mut fo = Follower::new(FollowPolicy::default(), &f, &temps(), None);
        assert!(matches!(
            fo.push(0.0, 30.0, false),
            Decision::Load { index: 5, .. }
        ));
        // 0.3 °C away: 3 µm, within tolerance.
        assert!(matches!(
            fo.push(1.0, 30.3, false),
            Decision::Keep {
                why: "within tolerance",
                ..
            }
        ));
        // 0.8 °C away: 8 µm, but only 1 s since the last load.
        assert!(matches!(
            fo.push(2.0, 30.8, false),
            Decision::Keep {
                why: "interval",
                ..
            }
        ));
        assert!(matches!(
            fo.push(31.0, 30.8, false),
            Decision::Load { index: 6, .. }
        ));
    }

    #[test]
    fn never_loads_while_busy_and_hysteresis_holds_at_the_midpoint() {
        let f = model();
        let p = FollowPolicy {
            tolerance_um: 4.0,
            hysteresis_c: 0.2,
            min_interval_s: 5.0,
            ..FollowPolicy::default()
        };
        let mut fo = Follower::new(p, &f, &temps(), None);
        fo.push(0.0, 30.0, false);
        // 30.55: 5.5 µm off profile 30, but only 0.1 °C nearer 31 than 30 (< 0.2 hysteresis).
        assert!(matches!(
            fo.push(10.0, 30.55, false),
            Decision::Keep {
                why: "within tolerance",
                ..
            }
        ));
        assert!(matches!(
            fo.push(20.0, 30.7, true),
            Decision::Keep { why: "busy", .. }
        ));
        assert!(matches!(
            fo.push(30.0, 30.7, false),
            Decision::Load { index: 6, .. }
        ));
    }

    #[test]
    fn a_jump_over_the_limit_is_refused_and_following_stops() {
        let f = model();
        // Enabled mid-print while the active mesh is the cold one and the frame is at 40 °C.
        let cold = f.predict(25.0).points_mm;
        let mut fo = Follower::new(FollowPolicy::default(), &f, &temps(), Some(cold));
        assert!(matches!(
            fo.push(0.0, 40.0, false),
            Decision::RefuseJump { index: 15, .. }
        ));
        assert!(matches!(
            fo.push(100.0, 40.0, false),
            Decision::Stopped { .. }
        ));
    }

    #[test]
    fn a_stale_or_out_of_range_sensor_stops_following() {
        let f = model();
        let mut fo = Follower::new(FollowPolicy::default(), &f, &temps(), None);
        fo.push(0.0, 30.0, false);
        assert!(fo.tick(10.0).is_none());
        let Some(Decision::Stopped { reason }) = fo.tick(31.0) else {
            panic!("not stopped")
        };
        assert!(reason.contains("stale"), "{reason}");
        let mut fo = Follower::new(FollowPolicy::default(), &f, &temps(), None);
        let Decision::Stopped { reason } = fo.push(0.0, 47.0, false) else {
            panic!()
        };
        assert!(reason.contains("outside the captured range"), "{reason}");
    }

    #[test]
    fn the_trend_turns_only_past_its_dead_band() {
        let mut tr = Trend::new(0.3);
        // Rising with ±0.1 °C of noise: heating throughout.
        for (k, wiggle) in [0.0, 0.1, -0.1, 0.05, -0.05, 0.1].iter().enumerate() {
            assert_eq!(tr.push(30.0 + 0.2 * k as f64 + wiggle), Phase::Heating);
        }
        // Highest so far 31.1; 30.85 is within the band, 30.7 is past it.
        assert_eq!(tr.push(30.85), Phase::Heating);
        assert_eq!(tr.push(30.7), Phase::Cooling);
        assert_eq!(tr.push(30.9), Phase::Cooling);
        assert_eq!(tr.push(30.5), Phase::Cooling);
        assert_eq!(tr.push(30.75), Phase::Cooling);
        assert_eq!(tr.push(30.85), Phase::Heating);
        assert_eq!(tr.push(f64::NAN), Phase::Heating);
    }

    /// Heating: one point bowing 10 µm/°C from 25 to 45 °C. Cooling: the same bow lagging
    /// by 2 °C (20 µm lower at the same frame temperature), captured from 45 down to 29 °C.
    fn two_directions() -> (Branch, Branch) {
        let h = model();
        let a = Capture::uniform("a", 29.0, vec![-0.06, 0.0], Phase::Cooling);
        let b = Capture::uniform("b", 45.0, vec![-0.22, 0.0], Phase::Cooling);
        let c = fit(&[&a, &b], ModelKind::Linear).unwrap();
        (
            Branch {
                phase: Phase::Heating,
                fit: h,
                temps_c: temps(),
            },
            Branch {
                phase: Phase::Cooling,
                fit: c,
                temps_c: (29..=45).map(f64::from).collect(),
            },
        )
    }

    #[test]
    fn the_frames_trend_picks_the_heating_or_the_cooling_profiles() {
        let (heat, cool) = two_directions();
        let p = FollowPolicy {
            min_interval_s: 1.0,
            ..FollowPolicy::default()
        };
        let mut fo = Follower::with_directions(p, heat, Some(cool), None);
        // Warming to 40 °C: heating profiles.
        let mut last = None;
        for k in 0..=20 {
            let d = fo.push(f64::from(k) * 10.0, 35.0 + 0.25 * f64::from(k), false);
            if let Decision::Load { phase, temp_c, .. } = d {
                assert_eq!(phase, Phase::Heating);
                last = Some(temp_c);
            }
        }
        assert_eq!(last, Some(40.0));
        assert_eq!(fo.loaded(), Some((Phase::Heating, 40.0)));
        // A noise dip of 0.2 °C keeps heating (and the same profile).
        let d = fo.push(210.0, 39.8, false);
        assert!(matches!(d, Decision::Keep { .. }), "{d:?}");
        assert_eq!(fo.trend(), Phase::Heating);
        // Cooling past the band: the cooling profile at the same temperature (20 µm lower).
        let Decision::Load {
            phase,
            temp_c,
            residual_um,
            ..
        } = fo.push(220.0, 39.6, false)
        else {
            panic!("no switch to cooling")
        };
        assert_eq!((phase, temp_c), (Phase::Cooling, 40.0));
        assert!(residual_um < 5.0, "{residual_um}");
        assert_eq!(fo.trend(), Phase::Cooling);
        // Warming again: back to the heating profiles.
        let d = fo.push(230.0, 40.0, false);
        assert!(
            matches!(
                d,
                Decision::Load {
                    phase: Phase::Heating,
                    ..
                }
            ),
            "{d:?}"
        );
    }

    #[test]
    fn by_default_following_stops_at_the_captured_ranges_end() {
        // Issue 26 B.3: 0.3 °C past 45 °C the bed is 3 µm off the 45 °C profile, and 1 °C
        // past it 10 µm (over the 5 µm tolerance): no margin unless the user sets one.
        let mut fo = Follower::new(FollowPolicy::default(), &model(), &temps(), None);
        assert!(matches!(
            fo.push(0.0, 45.0, false),
            Decision::Load { index: 20, .. }
        ));
        let d = fo.push(1.0, 45.3, false);
        let Decision::Stopped { reason } = d else {
            panic!("following went on outside the range: {d:?}")
        };
        assert!(reason.contains("25.00..45.00"), "{reason}");
    }

    #[test]
    fn within_a_set_margin_the_residual_is_the_current_error_not_the_clamped_one() {
        // Issue 26 B.3: 10 µm/°C; beyond 45 °C the model goes on along its slope, so the
        // 45 °C profile is 8 µm off at 45.8 °C (the clamped model said 0).
        let p = FollowPolicy {
            range_margin_c: 1.0,
            ..FollowPolicy::default()
        };
        let mut fo = Follower::new(p, &model(), &temps(), None);
        fo.push(0.0, 44.0, false);
        let d = fo.push(30.0, 45.8, false);
        let Decision::Load {
            index, residual_um, ..
        } = d
        else {
            panic!("{d:?}")
        };
        assert_eq!(index, 20);
        assert!((residual_um - 8.0).abs() < 0.01, "{residual_um}");
        let Decision::Keep { residual_um, .. } = fo.push(31.0, 45.5, false) else {
            panic!("kept")
        };
        assert!((residual_um - 5.0).abs() < 0.01, "{residual_um}");
        // Inside the range: the distance from the model now (0.4 °C from the 44 °C profile).
        let mut fo = Follower::new(p, &model(), &temps(), None);
        fo.push(0.0, 44.0, false);
        let Decision::Keep { residual_um, .. } = fo.push(1.0, 44.4, false) else {
            panic!("kept")
        };
        assert!((residual_um - 4.0).abs() < 0.01, "{residual_um}");
        assert!(matches!(
            fo.push(2.0, 46.1, false),
            Decision::Stopped { .. }
        ));
    }

    #[test]
    fn cooling_below_the_cooling_range_falls_back_to_the_heating_profiles() {
        let (heat, cool) = two_directions();
        let p = FollowPolicy {
            min_interval_s: 1.0,
            range_margin_c: 0.5,
            ..FollowPolicy::default()
        };
        let mut fo = Follower::with_directions(p, heat, Some(cool), None);
        fo.push(0.0, 30.0, false);
        // 27 °C: cooling, below the cooling meshes (29 °C, margin 0.5) but inside heating's.
        let d = fo.push(10.0, 27.0, false);
        assert_eq!(fo.trend(), Phase::Cooling);
        assert!(
            matches!(
                d,
                Decision::Load {
                    phase: Phase::Heating,
                    temp_c,
                    ..
                } if temp_c == 27.0
            ),
            "{d:?}"
        );
    }
}
