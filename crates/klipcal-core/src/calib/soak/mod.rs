//! PURE: thermal soak detection from the bed heater's power (paper 000 §3.1): the bed is at
//! equilibrium when its power has stopped decreasing. No I/O and no clock: every sample carries
//! its own time.
//!
//! How it decides. The power is averaged over bins of `bin_s`, each sample held until the next
//! (so 1–4 Hz reports, gaps and a bang-bang heater's 0/max switching all give the true duty). A
//! bin counts once the temperature is within `temp_band_c` of the target and the heater has
//! headroom over the last minute (below `saturated_power` of its `max_power`); after `settle_s`
//! for the controller, every bin goes into the model of what a bed's power can do while its
//! temperature is held: a constant plus decaying exponentials with time constants on a grid
//! from one minute to `tau_max_s` (a temperature-clamped network of heat capacities draws a sum
//! of decays with positive amplitudes; the fastest, the controller's, may have either sign).
//! The bed is stable when the data rule out, by a likelihood-ratio test at about three standard
//! errors, every such model whose power still to fall now is `max_remaining` or more — whatever
//! its time constant up to `tau_max_s`. A decay too slow to resolve yet is one of those models,
//! so it is waited for, not ignored: the test needs the slope to be known well enough that even
//! the slowest allowed decay could not hide `max_remaining` in it. The model also has a column
//! for the temperature's rate of change over each bin: power that went into the bed's own heat
//! capacity (a bang-bang heater's on and off, a PID's derivative kick) is no heat flow to the
//! surroundings, so it is taken out instead of counted as noise. The noise level comes from
//! the scatter about the best fit, taken at the one-minute scale too, so correlated controller
//! noise and bang-bang cycling widen the test instead of fooling it.
//!
//! A long temperature excursion restarts the soak clock (with twice the settling) but keeps the
//! power history; a new target forgets everything. After an overshoot (out of the band, or
//! `OVERSHOOT_C` over the target inside it) the controller's integral winds back and lifts the
//! power for a while before the slow decay goes on: decays up to the overshoot's length may then
//! take either sign, so the rise cannot pass for "nothing left to fall". Only from equilibrium
//! are a clamped network's decays all positive: a bed first seen warm and out of the band (held
//! at another target before, perhaps long at full power) may have its plate ahead of its
//! surroundings, so decays up to a sixth of `tau_max_s` (the plate's) may then take either sign.
//!
//! After a step down (the temperature came into the band from above) the surroundings may be
//! warmer than they will be at the new target (the power rises while they cool) or still
//! colder (it falls): the same test is run on the negated power too, and both a rise and a fall
//! of `max_remaining` must be ruled out; so for a bed first seen inside the band. A heater off
//! over the last minute after a step down means the bed is still cooling.

use serde::{Deserialize, Serialize};

pub mod ask;
pub mod carry;
mod chamber;
mod coupling;
mod detector;
mod nnls;
mod stack;
#[cfg(test)]
mod test_beds;

pub use chamber::{
    flat_k_per_h, surface_share, CHAMBER_BUDGET_SHARE, CHAMBER_TAU_MAX_S, SURFACE_H_MAX_W_M2K,
};
pub use coupling::{Coupling, CouplingSource};
pub use detector::SoakDetector;
pub use detector::SoakStatus;
pub use stack::open_frame_reach;
pub use stack::{cost_words, kelvin_words, BED_PRESETS, OPEN_FRAME_TAU_MAX_S};

/// Thresholds of the soak detector. Every field has a default (see [`SoakParams::default`]),
/// so a `[soak]` table in the daemon's TOML may name only the keys it changes.
#[derive(Debug, Clone, PartialEq, Deserialize, Serialize)]
#[serde(default, deny_unknown_fields)]
pub struct SoakParams {
    /// The temperature counts as settled within ± this of the target. Default 2.0 °C
    /// (the paper's condition, 000 §3.7: plate within ±2 K of the set temperature).
    pub temp_band_c: f64,
    /// A target at or below this is an unheated bed: the soak is skipped. Default 30.0 °C.
    pub skip_below_c: f64,
    /// Mean power over the last minute at or above this fraction of the heater's `max_power`
    /// means it has no headroom left: the bed is still heating, whatever the temperature.
    /// Default 0.97.
    pub saturated_power: f64,
    /// Time after the temperature first enters the band that is left out of the model (the
    /// controller's overshoot and settling); twice this after the temperature left the band
    /// for more than three bins. Default 180 s.
    pub settle_s: f64,
    /// Samples are averaged over bins of this length before anything else. Default 10 s.
    pub bin_s: f64,
    /// Shortest soak (after `settle_s`) before the bed may be declared stable. Default 300 s.
    pub min_soak_s: f64,
    /// The print surface may still warm by at most this after the print starts, K. The power
    /// still to fall is turned into surface warming through the bed's coupling from thermistor
    /// to surface (see [`Coupling`]). Default 1.0 (1.2 µm/100 mm on steel, 2.3 on aluminium:
    /// half the paper's ±2 K).
    pub surface_budget_c: f64,
    /// The bed's build, whose coupling the rule uses (capped at the most a cold heat-up of this
    /// bed allows, which bounds it only from above): one of [`BED_PRESETS`] by name, "unknown"
    /// (the weakest coupling is assumed) or "" (not set: the first soak asks, and assumes the
    /// weakest meanwhile). Default "".
    pub bed: String,
    /// The slowest time constant the bed and its surroundings (plate, enclosure) may have: a
    /// decay this slow is ruled out before the bed is declared stable, so a longer value waits
    /// longer on every bed (on an open frame, `frame = "open"` caps it at the bed stack's own
    /// bound). Default 3600 s (1 h: a plate and an enclosure).
    pub tau_max_s: f64,
    /// The printer's frame: "open" (no enclosure: nothing around the bed warms for hours, so
    /// the slowest decay ruled out is the bed stack's own, [`OPEN_FRAME_TAU_MAX_S`], when that
    /// is below `tau_max_s`), "enclosed", "unknown", or "" (not set: the first soak asks).
    /// All but "open" use `tau_max_s`. Default "".
    pub frame: String,
    /// The chamber or enclosure thermometer whose trend rules the enclosure's slow warming in
    /// or out, as Klipper names its object (`temperature_sensor chamber`,
    /// `temperature_fan enclosure`); "" (the default) takes the first such sensor Klipper's
    /// config has, "none" reads none. Default "".
    pub chamber_sensor: String,
    /// The span of chamber readings whose trend says whether the air still warms, s: a longer
    /// one sees a slower warming through a noisier sensor, and waits that much longer before
    /// it can tell. Default 1200 s (20 min).
    pub chamber_window_s: f64,
    /// Issue 10's rule, for the bench's comparison only: stable once this much power (fraction
    /// of full power) is ruled out, whatever the surface. Not a setting.
    #[serde(skip)]
    pub fixed_remaining: Option<f64>,
    /// The bench's comparison only: never identify the coupling (as after a warm start).
    #[serde(skip)]
    pub no_identify: bool,
    /// What Klipper's config says of the bed's heater (`control: mpc` and its calibration):
    /// facts read by the daemon (and given by the benchmarks), not a setting.
    #[serde(skip)]
    pub heater: HeaterFacts,
}

/// What Klipper's (Kalico's) config says of the bed's heater, for the soak rule.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct HeaterFacts {
    /// `control: mpc` (Kalico's model-predictive control): after the band its power dips
    /// below its final value and keeps a limit cycle, so a heat-up's last minutes do not
    /// bound the bed's heat capacity by themselves.
    pub mpc: bool,
    /// MPC_CALIBRATE's `block_heat_capacity` over `heater_power`, full power·s/K: the heat
    /// capacity Kalico's own model of the bed has.
    pub mpc_heat_capacity: Option<f64>,
}

impl HeaterFacts {
    /// From `[heater_bed]`'s `control` being `mpc`, its `block_heat_capacity` (J/K) and
    /// `heater_power` (W); a capacity that is not finite and positive is left out.
    #[must_use]
    pub fn mpc(block_heat_capacity: Option<f64>, heater_power: Option<f64>) -> Self {
        let c = match (block_heat_capacity, heater_power) {
            (Some(c), Some(p)) if c.is_finite() && p.is_finite() && c > 0.0 && p > 0.0 => {
                Some(c / p)
            }
            _ => None,
        };
        HeaterFacts {
            mpc: true,
            mpc_heat_capacity: c,
        }
    }
}

impl Default for SoakParams {
    fn default() -> Self {
        SoakParams {
            temp_band_c: 2.0,
            skip_below_c: 30.0,
            saturated_power: 0.97,
            settle_s: 180.0,
            bin_s: 10.0,
            min_soak_s: 300.0,
            surface_budget_c: 1.0,
            bed: String::new(),
            tau_max_s: 3600.0,
            frame: String::new(),
            chamber_sensor: String::new(),
            chamber_window_s: 1200.0,
            fixed_remaining: None,
            no_identify: false,
            heater: HeaterFacts::default(),
        }
    }
}

/// `[soak]` keys of earlier versions that the detector no longer has (its statistics are no
/// longer knobs): read and ignored, with a warning, so an old settings file still loads.
pub const RETIRED_KEYS: &[&str] = &[
    "span_taus",
    "fit_taus",
    "trend_window_s",
    "max_drop_se",
    "max_window_drop",
    "tau_min_s",
    "max_remaining",
];

/// What `soak.frame` accepts, for its error.
const FRAME_NAMES: &str = "\"\" (not set: the first soak asks), \"open\" (no enclosure: up to 20 \
                           min), \"enclosed\" (up to tau_max_s) or \"unknown\" (as enclosed)";

/// What `soak.bed` accepts, for its error.
const BED_NAMES: &str = "\"\" (not set: the first soak asks), \"bare-plate\", \"steel-plate\", \
                         \"bare-pad\", \"steel-pad\", \"glass-plate\", \"glass-pad\" or \"unknown\" (the \
                         weakest)";

/// `soak.chamber_sensor`: "", "none", or `temperature_sensor <name>` / `temperature_fan
/// <name>`.
fn chamber_sensor_ok(v: &str) -> bool {
    let v = v.trim();
    v.is_empty()
        || v == "none"
        || v.split_once(char::is_whitespace)
            .is_some_and(|(kind, name)| {
                ["temperature_sensor", "temperature_fan"].contains(&kind)
                    && !name.trim().is_empty()
                    && !name.contains([';', '#', '*', '\n'])
            })
}

/// Likelihood-ratio threshold of the test in standard errors: a remaining fall of
/// `max_remaining` is ruled out once it costs the fit more than Z² σ².
pub const Z: f64 = 3.0;

/// A [`SoakParams`] value out of range.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[error("soak.{key} = {value}: expected {expected}")]
pub struct SoakParamsError {
    /// The key, e.g. `bin_s`.
    pub key: &'static str,
    /// The value found, as written.
    pub value: String,
    /// What would be accepted.
    pub expected: &'static str,
}

impl SoakParams {
    /// Checks every value's range.
    ///
    /// # Errors
    /// The first key out of range, with its value and what is expected.
    pub fn validate(&self) -> Result<(), SoakParamsError> {
        let check = |key, value: f64, ok: bool, expected| {
            if ok && value.is_finite() {
                Ok(())
            } else {
                Err(SoakParamsError {
                    key,
                    value: value.to_string(),
                    expected,
                })
            }
        };
        let p = self;
        check("temp_band_c", p.temp_band_c, p.temp_band_c > 0.0, "> 0 °C")?;
        check("skip_below_c", p.skip_below_c, true, "a temperature in °C")?;
        check(
            "saturated_power",
            p.saturated_power,
            p.saturated_power > 0.0 && p.saturated_power <= 1.0,
            "a fraction of full power above 0, at most 1",
        )?;
        check("settle_s", p.settle_s, p.settle_s >= 0.0, ">= 0 s")?;
        check(
            "bin_s",
            p.bin_s,
            p.bin_s > 0.0 && p.bin_s <= 60.0,
            "between 0 and 60 s",
        )?;
        check("min_soak_s", p.min_soak_s, p.min_soak_s >= 0.0, ">= 0 s")?;
        check(
            "surface_budget_c",
            p.surface_budget_c,
            p.surface_budget_c >= 0.1 && p.surface_budget_c <= 10.0,
            "between 0.1 and 10 K",
        )?;
        if !(ask::not_named(&p.bed) || BED_PRESETS.iter().any(|b| b.name == p.bed)) {
            return Err(SoakParamsError {
                key: "bed",
                value: format!("{:?}", p.bed),
                expected: BED_NAMES,
            });
        }
        check(
            "tau_max_s",
            p.tau_max_s,
            p.tau_max_s >= 20.0 * p.bin_s && p.tau_max_s <= 14_400.0,
            "at least 20 bins (bin_s) and at most 14400 s (4 h)",
        )?;
        if !["", "open", "enclosed", "unknown"].contains(&p.frame.as_str()) {
            return Err(SoakParamsError {
                key: "frame",
                value: format!("{:?}", p.frame),
                expected: FRAME_NAMES,
            });
        }
        check(
            "chamber_window_s",
            p.chamber_window_s,
            p.chamber_window_s >= 20.0 * p.bin_s && p.chamber_window_s <= 14_400.0,
            "at least 20 bins (bin_s) and at most 14400 s (4 h)",
        )?;
        if !chamber_sensor_ok(&p.chamber_sensor) {
            return Err(SoakParamsError {
                key: "chamber_sensor",
                value: format!("{:?}", p.chamber_sensor),
                expected: "\"\" (the first chamber or enclosure thermometer in Klipper's config), \
                           \"none\", or a Klipper object such as \"temperature_sensor chamber\" or \
                           \"temperature_fan enclosure\"",
            });
        }
        Ok(())
    }

    /// The chamber thermometer to read, from `chamber_sensor` and the ones Klipper's config has
    /// (see `moonraker::answers::chamber_sensors`, the plainest first): None for "none" or when
    /// there is none.
    #[must_use]
    pub fn chamber_sensor_from(&self, found: &[String]) -> Option<String> {
        match self.chamber_sensor.trim() {
            "none" => None,
            "" => found.first().cloned(),
            name => Some(name.split_whitespace().collect::<Vec<_>>().join(" ")),
        }
    }

    /// The slowest decay the rule rules out, s: `tau_max_s`, or on an open frame the bed
    /// stack's own bound when that is shorter.
    #[must_use]
    pub fn slowest_s(&self) -> f64 {
        if self.frame == "open" {
            self.tau_max_s.min(OPEN_FRAME_TAU_MAX_S)
        } else {
            self.tau_max_s
        }
    }

    /// Which slowest decay is ruled out, and why, in words.
    #[must_use]
    pub fn slowest_words(&self) -> String {
        let m = self.slowest_s() / 60.0;
        // Whole minutes for real beds; a test bench's seconds-long settings stay readable.
        let min = if m < 10.0 {
            format!("{m:.1}")
        } else {
            format!("{m:.0}")
        };
        match self.frame.as_str() {
            "open" if self.slowest_s() < self.tau_max_s => format!(
                "ruling out decays up to {min} min, the bed stack's own on an open frame \
                 (soak.frame = \"open\"; in an enclosure this may be early)"
            ),
            "open" => format!(
                "ruling out decays up to {min} min (soak.tau_max_s, already below the open \
                 frame's {:.0} min)",
                OPEN_FRAME_TAU_MAX_S / 60.0
            ),
            "enclosed" => format!(
                "ruling out decays up to {min} min (soak.tau_max_s; soak.frame = \"enclosed\")"
            ),
            _ if self.tau_max_s <= OPEN_FRAME_TAU_MAX_S => {
                format!("ruling out decays up to {min} min (soak.tau_max_s)")
            }
            _ => format!(
                "ruling out decays up to {min} min (soak.tau_max_s, for a plate and an \
                 enclosure; soak.frame = \"open\" shortens it to {:.0} min on an open frame)",
                OPEN_FRAME_TAU_MAX_S / 60.0
            ),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Every field's doc comment states its default, and states the one the code uses.
    #[test]
    fn the_doc_comments_state_the_real_defaults() {
        let src = include_str!("mod.rs");
        let start = src.find("pub struct SoakParams {").unwrap();
        let end = start + src[start..].find("\n}").unwrap();
        let defaults = serde_json::to_value(SoakParams::default()).unwrap();
        let mut doc = String::new();
        let mut checked = 0;
        for line in src[start..end].lines().skip(1) {
            let t = line.trim();
            if let Some(d) = t.strip_prefix("///") {
                doc.push_str(d);
                doc.push(' ');
            } else if let Some(field) = t.strip_prefix("pub ").and_then(|r| r.split(':').next()) {
                if defaults.get(field).is_none() {
                    // `#[serde(skip)]`: the benchmarks' knobs, not settings.
                    doc.clear();
                    continue;
                }
                match defaults[field].as_str() {
                    // A text setting: its doc says `Default "…"`.
                    Some(text) => assert!(
                        doc.contains(&format!("Default {text:?}")),
                        "soak.{field}: doc does not say Default {text:?}"
                    ),
                    None => {
                        let stated: f64 = doc
                            .split("Default ")
                            .nth(1)
                            .and_then(|r| r.split_whitespace().next())
                            .map(|n| n.trim_end_matches(['.', ',', ')']))
                            .and_then(|n| n.parse().ok())
                            .unwrap_or_else(|| {
                                panic!("soak.{field}: no \"Default N\" in its doc comment")
                            });
                        let real = defaults[field].as_f64().unwrap();
                        assert!(
                            (stated - real).abs() < 1e-12,
                            "soak.{field}: doc says {stated}, code {real}"
                        );
                    }
                }
                checked += 1;
                doc.clear();
            }
        }
        assert_eq!(checked, defaults.as_object().unwrap().len());
    }

    #[test]
    fn soak_params_read_from_toml_with_defaults_for_missing_keys() {
        let p: SoakParams =
            toml::from_str("surface_budget_c = 0.5\ntemp_band_c = 1.5\nbed = \"glass-pad\"\n")
                .unwrap();
        assert_eq!(p.surface_budget_c, 0.5);
        assert_eq!(p.bed, "glass-pad");
        assert_eq!(p.temp_band_c, 1.5);
        assert_eq!(p.min_soak_s, SoakParams::default().min_soak_s);
        assert!(toml::from_str::<SoakParams>("max_remainder = 0.005").is_err());
    }

    #[test]
    fn out_of_range_params_name_the_key_and_what_is_expected() {
        let p = SoakParams {
            bin_s: 0.0,
            ..SoakParams::default()
        };
        let err = p.validate().unwrap_err();
        assert_eq!(err.key, "bin_s");
        assert!(err.to_string().contains("soak.bin_s = 0"), "{err}");
        assert!(SoakParams::default().validate().is_ok());
    }

    #[test]
    fn soak_frame_is_read_and_refused_by_name_when_not_a_frame() {
        let p: SoakParams = toml::from_str("frame = \"open\"\n").expect("parses");
        assert_eq!(p.frame, "open");
        assert!(p.validate().is_ok());
        assert_eq!(p.slowest_s(), OPEN_FRAME_TAU_MAX_S);
        // A shorter tau_max_s still wins; "enclosed" and unknown keep tau_max_s.
        let short = SoakParams {
            tau_max_s: 900.0,
            ..p.clone()
        };
        assert_eq!(short.slowest_s(), 900.0);
        for frame in ["", "enclosed"] {
            let q = SoakParams {
                frame: frame.into(),
                ..SoakParams::default()
            };
            assert!(q.validate().is_ok());
            assert_eq!(q.slowest_s(), 3600.0);
        }
        for bad in ["Open", "opne", "closed"] {
            let q = SoakParams {
                frame: bad.into(),
                ..SoakParams::default()
            };
            let e = q.validate().expect_err(bad);
            assert_eq!(e.key, "frame");
            assert_eq!(e.value, format!("{bad:?}"));
            let msg = e.to_string();
            assert!(
                msg.starts_with("soak.frame = ")
                    && msg.contains("\"open\"")
                    && msg.contains("\"enclosed\""),
                "{msg}"
            );
        }
    }

    #[test]
    fn the_new_settings_are_refused_by_name_when_out_of_range() {
        for (p, key) in [
            (
                SoakParams {
                    surface_budget_c: 0.0,
                    ..SoakParams::default()
                },
                "surface_budget_c",
            ),
            (
                SoakParams {
                    surface_budget_c: f64::NAN,
                    ..SoakParams::default()
                },
                "surface_budget_c",
            ),
            (
                SoakParams {
                    surface_budget_c: 11.0,
                    ..SoakParams::default()
                },
                "surface_budget_c",
            ),
            (
                SoakParams {
                    bed: "granite".into(),
                    ..SoakParams::default()
                },
                "bed",
            ),
        ] {
            let e = p.validate().unwrap_err();
            assert_eq!(e.key, key);
            assert!(e.to_string().starts_with(&format!("soak.{key} = ")), "{e}");
        }
        let e = SoakParams {
            bed: "granite".into(),
            ..SoakParams::default()
        }
        .validate()
        .unwrap_err();
        assert!(e.to_string().contains("\"steel-plate\""), "{e}");
        for b in BED_PRESETS {
            let p = SoakParams {
                bed: b.name.into(),
                ..SoakParams::default()
            };
            assert!(p.validate().is_ok(), "{}", b.name);
        }
    }
}
