//! `[ab]`: the defaults of a differential A/B calibration session and their ranges.

use serde::Deserialize;

use super::Error;

/// `[ab]`: defaults of a differential rotation_distance calibration session (each session
/// stores its own copy, with the start call's arguments).
#[derive(Debug, Clone, Deserialize, serde::Serialize, PartialEq)]
#[serde(default, deny_unknown_fields)]
pub struct AbConfig {
    /// `paper` (two groups along the motor directions) or `full` (four groups: also the
    /// in-plane shear from one print).
    pub layout: String,
    /// Bed temperature for the print and the readings; 0 prints on an unheated bed (no soak).
    pub bed_temp_c: f64,
    /// Nozzle temperature.
    pub nozzle_temp_c: f64,
    /// Readings per pair before the pair counts as measured.
    pub readings_per_pair: usize,
    /// Wait after the print for the part to cool on the hot bed before asking for readings.
    pub cooldown_s: f64,
    /// Longest the bed is held hot after the print; then heaters go off.
    pub hold_max_s: f64,
    /// A change of rotation_distance beyond this needs FORCE=1.
    pub max_change_pct: f64,
    /// Longest wait for the bed to reach equilibrium before printing anyway is refused.
    pub soak_max_s: f64,
    /// Readings further than this from a pair's nominal distance are refused, mm.
    pub reading_tolerance_mm: f64,
    /// The caliper's last digit, mm (0.01 for most digital calipers, 0.02 or 0.05 for a
    /// vernier): a reading is typed with at most its decimals, and its rounding enters the
    /// stated uncertainty.
    pub caliper_resolution_mm: f64,
    /// Where the in-plane shear goes: `motors` (A/B rotation distances absorb it, as the paper's
    /// iteration does; Cartesian printers still send it to Klipper's skew correction) or
    /// `klipper_skew` (Klipper's skew_correction takes it, saved as profile `klipcal`).
    pub shear_to: String,
    /// The start macro the slicer calls (e.g. `START_PRINT`); empty: klipcal looks for
    /// `PRINT_START` and `START_PRINT` ([`crate::klipper::find_start_macro`]).
    pub start_macro: String,
}

impl Default for AbConfig {
    fn default() -> Self {
        Self {
            layout: "paper".into(),
            bed_temp_c: 60.0,
            nozzle_temp_c: 215.0,
            readings_per_pair: 5,
            cooldown_s: 720.0,
            hold_max_s: 1800.0,
            max_change_pct: 3.0,
            soak_max_s: 5400.0,
            reading_tolerance_mm: 2.0,
            caliper_resolution_mm: 0.01,
            shear_to: "motors".into(),
            start_macro: String::new(),
        }
    }
}

impl AbConfig {
    /// Checks the `[ab]` values' ranges.
    ///
    /// # Errors
    /// The first key whose value is out of range.
    pub(super) fn validate(&self) -> Result<(), Error> {
        let ab = self;
        if !ab
            .start_macro
            .chars()
            .all(|c| c.is_ascii_alphanumeric() || c == '_')
        {
            return Err(Error::Invalid {
                key: "ab.start_macro",
                value: format!("{:?}", ab.start_macro),
                expected: "a Klipper macro name (letters, digits and '_'), or \"\" to find \
                           PRINT_START or START_PRINT",
            });
        }
        if !["paper", "full"].contains(&ab.layout.as_str()) {
            return Err(Error::Invalid {
                key: "ab.layout",
                value: format!("{:?}", ab.layout),
                expected: "\"paper\" or \"full\"",
            });
        }
        let ranges = [
            (
                "ab.bed_temp_c",
                ab.bed_temp_c,
                0.0,
                130.0,
                "°C from 0 (unheated) to 130",
            ),
            (
                "ab.nozzle_temp_c",
                ab.nozzle_temp_c,
                150.0,
                320.0,
                "°C from 150 to 320",
            ),
            (
                "ab.cooldown_s",
                ab.cooldown_s,
                0.0,
                7200.0,
                "seconds from 0 to 7200",
            ),
            (
                "ab.hold_max_s",
                ab.hold_max_s,
                0.0,
                14_400.0,
                "seconds from 0 to 14400",
            ),
            (
                "ab.max_change_pct",
                ab.max_change_pct,
                0.01,
                20.0,
                "a percentage from 0.01 to 20",
            ),
            (
                "ab.soak_max_s",
                ab.soak_max_s,
                0.0,
                14_400.0,
                "seconds from 0 to 14400",
            ),
            (
                "ab.reading_tolerance_mm",
                ab.reading_tolerance_mm,
                0.01,
                50.0,
                "mm from 0.01 to 50",
            ),
            (
                "ab.caliper_resolution_mm",
                ab.caliper_resolution_mm,
                0.001,
                0.1,
                "the caliper's last digit in mm, from 0.001 to 0.1 (0.01 for most digital \
                 calipers)",
            ),
        ];
        for (key, v, lo, hi, expected) in ranges {
            if !(v.is_finite() && (lo..=hi).contains(&v)) {
                return Err(Error::Invalid {
                    key,
                    value: v.to_string(),
                    expected,
                });
            }
        }
        if ab.cooldown_s >= ab.hold_max_s {
            return Err(Error::Invalid {
                key: "ab.cooldown_s",
                value: format!("{} (ab.hold_max_s = {})", ab.cooldown_s, ab.hold_max_s),
                expected: "a cool-down shorter than ab.hold_max_s: the hold limit turns the \
                           heaters off before the readings are asked for otherwise",
            });
        }
        if !(3..=20).contains(&ab.readings_per_pair) {
            return Err(Error::Invalid {
                key: "ab.readings_per_pair",
                value: ab.readings_per_pair.to_string(),
                expected: "a whole number from 3 to 20",
            });
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::super::Config;

    #[test]
    fn a_cooldown_not_shorter_than_the_hold_limit_is_refused_at_load() {
        let e = Config::parse("[ab]\ncooldown_s = 1800\nhold_max_s = 1800\n")
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("ab.cooldown_s") && e.contains("hold_max_s"),
            "{e}"
        );
        assert!(Config::parse("[ab]\ncooldown_s = 600\nhold_max_s = 1800\n").is_ok());
    }

    #[test]
    fn a_caliper_resolution_out_of_range_is_refused_by_name() {
        for bad in ["0", "0.5", "-0.01"] {
            let e = Config::parse(&format!("[ab]\ncaliper_resolution_mm = {bad}\n"))
                .unwrap_err()
                .to_string();
            assert!(
                e.contains("ab.caliper_resolution_mm") && e.contains("last digit"),
                "{e}"
            );
        }
        let c = Config::parse("[ab]\ncaliper_resolution_mm = 0.02\n").unwrap();
        assert_eq!(c.ab.caliper_resolution_mm, 0.02);
        assert_eq!(Config::default().ab.caliper_resolution_mm, 0.01);
    }

    #[test]
    fn ab_start_macro_is_a_macro_name_or_empty() {
        let c = Config::parse("[ab]\nstart_macro = \"START_PRINT\"\n").unwrap();
        assert_eq!(c.ab.start_macro, "START_PRINT");
        assert_eq!(Config::default().ab.start_macro, "");
        let err = Config::parse("[ab]\nstart_macro = \"START PRINT; G28\"\n").unwrap_err();
        assert!(err.to_string().contains("ab.start_macro"), "{err}");
    }
}
