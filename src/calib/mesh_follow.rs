//! PURE: the follow policy of thermal bed-mesh compensation — given frame temperature samples
//! and their times, decides when to load which `klipcal_<T>` profile: only when the loaded one
//! is off the model by more than the tolerance, with hysteresis, at most once per interval,
//! never while homing/probing, refusing jumps over a limit, and stopping on a stale or
//! out-of-range sensor. No I/O, no clock: time comes in as `t_s`.

use super::mesh::{max_abs_diff_um, nearest, Fit};

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
    /// A sample further than this outside the captured range stops following, °C.
    pub range_margin_c: f64,
}

impl Default for FollowPolicy {
    fn default() -> Self {
        Self {
            tolerance_um: 5.0,
            hysteresis_c: 0.1,
            min_interval_s: 30.0,
            jump_limit_um: 50.0,
            stale_after_s: 30.0,
            range_margin_c: 1.0,
        }
    }
}

/// What the follower asks for after a sample.
#[derive(Debug, Clone, PartialEq)]
pub enum Decision {
    /// Nothing to do (`why` for status).
    Keep {
        /// Why nothing is loaded: "within tolerance", "busy", "interval".
        why: &'static str,
        /// Model minus loaded profile at this temperature, µm.
        residual_um: f64,
    },
    /// Load this profile.
    Load {
        /// Index into the profile list.
        index: usize,
        /// Its temperature, °C.
        temp_c: f64,
        /// Residual after the load, µm.
        residual_um: f64,
    },
    /// A load refused: it would change the mesh by more than the jump limit. Following stops.
    RefuseJump {
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

/// The follower's state.
#[derive(Debug, Clone)]
pub struct Follower {
    policy: FollowPolicy,
    temps_c: Vec<f64>,
    meshes: Vec<Vec<f64>>,
    active: Option<Vec<f64>>,
    loaded: Option<usize>,
    last_load_t_s: Option<f64>,
    last_sample_t_s: Option<f64>,
    stopped: Option<String>,
    range_c: (f64, f64),
}

impl Follower {
    /// A follower over profiles at `temps_c` (meshes from `fit`). `active` is the mesh active
    /// when following starts (None: no mesh yet, the first load is free).
    #[must_use]
    pub fn new(policy: FollowPolicy, fit: &Fit, temps_c: &[f64], active: Option<Vec<f64>>) -> Self {
        Self {
            policy,
            temps_c: temps_c.to_vec(),
            meshes: temps_c.iter().map(|&t| fit.predict(t).points_mm).collect(),
            active,
            loaded: None,
            last_load_t_s: None,
            last_sample_t_s: None,
            stopped: None,
            range_c: fit.range_c,
        }
    }

    /// The loaded profile's index.
    #[must_use]
    pub fn loaded(&self) -> Option<usize> {
        self.loaded
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

    /// One frame temperature sample. `busy` while homing or probing (never load then).
    pub fn push(&mut self, t_s: f64, temp_c: f64, model: &Fit, busy: bool) -> Decision {
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
        let want = model.predict(temp_c).points_mm;
        let cand = nearest(&self.temps_c, temp_c);
        let residual = |k: usize| max_abs_diff_um(&want, &self.meshes[k]);
        let current = self.loaded.map(&residual);
        if let (Some(i), Some(r)) = (self.loaded, current) {
            let closer = (temp_c - self.temps_c[i]).abs() - (temp_c - self.temps_c[cand]).abs();
            if cand == i || r <= self.policy.tolerance_um || closer < self.policy.hysteresis_c {
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
        let from = self
            .loaded
            .map(|i| self.meshes[i].clone())
            .or_else(|| self.active.clone());
        if let Some(from) = from {
            let jump = max_abs_diff_um(&from, &self.meshes[cand]);
            if jump > self.policy.jump_limit_um {
                self.stopped = Some(format!(
                    "loading profile at {:.2} °C would move the mesh by {jump:.0} µm (limit {:.0} µm): following toggled mid-print or the frame sensor failed; mesh following stopped",
                    self.temps_c[cand], self.policy.jump_limit_um
                ));
                return Decision::RefuseJump {
                    index: cand,
                    jump_um: jump,
                };
            }
        }
        self.loaded = Some(cand);
        self.last_load_t_s = Some(t_s);
        Decision::Load {
            index: cand,
            temp_c: self.temps_c[cand],
            residual_um: residual(cand),
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
            fo.push(0.0, 30.0, &f, false),
            Decision::Load { index: 5, .. }
        ));
        // 0.3 °C away: 3 µm, within tolerance.
        assert!(matches!(
            fo.push(1.0, 30.3, &f, false),
            Decision::Keep {
                why: "within tolerance",
                ..
            }
        ));
        // 0.8 °C away: 8 µm, but only 1 s since the last load.
        assert!(matches!(
            fo.push(2.0, 30.8, &f, false),
            Decision::Keep {
                why: "interval",
                ..
            }
        ));
        assert!(matches!(
            fo.push(31.0, 30.8, &f, false),
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
        fo.push(0.0, 30.0, &f, false);
        // 30.55: 5.5 µm off profile 30, but only 0.1 °C nearer 31 than 30 (< 0.2 hysteresis).
        assert!(matches!(
            fo.push(10.0, 30.55, &f, false),
            Decision::Keep {
                why: "within tolerance",
                ..
            }
        ));
        assert!(matches!(
            fo.push(20.0, 30.7, &f, true),
            Decision::Keep { why: "busy", .. }
        ));
        assert!(matches!(
            fo.push(30.0, 30.7, &f, false),
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
            fo.push(0.0, 40.0, &f, false),
            Decision::RefuseJump { index: 15, .. }
        ));
        assert!(matches!(
            fo.push(100.0, 40.0, &f, false),
            Decision::Stopped { .. }
        ));
    }

    #[test]
    fn a_stale_or_out_of_range_sensor_stops_following() {
        let f = model();
        let mut fo = Follower::new(FollowPolicy::default(), &f, &temps(), None);
        fo.push(0.0, 30.0, &f, false);
        assert!(fo.tick(10.0).is_none());
        let Some(Decision::Stopped { reason }) = fo.tick(31.0) else {
            panic!("not stopped")
        };
        assert!(reason.contains("stale"), "{reason}");
        let mut fo = Follower::new(FollowPolicy::default(), &f, &temps(), None);
        let Decision::Stopped { reason } = fo.push(0.0, 47.0, &f, false) else {
            panic!()
        };
        assert!(reason.contains("outside the captured range"), "{reason}");
    }
}
