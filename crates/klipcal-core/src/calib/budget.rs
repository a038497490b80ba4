//! PURE: the paper's error budget (seed 000 §3): bounds on each reading's random error and the
//! resulting precision and accuracy of a differential scale. Numbers in, numbers out.

use serde::Serialize;

/// What the budget is computed from. Defaults are the paper's §3.7 conditions.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, serde::Deserialize)]
pub struct BudgetInputs {
    /// Build plate coefficient of thermal expansion, 1/K (paper: 1.2e-5, spring steel).
    pub plate_cte_per_k: f64,
    /// Bed temperature band, ±K (paper: 2).
    pub temp_band_k: f64,
    /// Length over which the plate's drift is charged to one reading, mm. The paper charges its
    /// per-100 mm figure (2.4 µm); the solver charges (D2 − D1)/2, which makes a uniform drift
    /// contribute exactly CTE × ΔT to the precision bound 2ε/(D2 − D1).
    pub bed_length_mm: f64,
    /// Local filament diameter tolerance, ±mm (paper: 0.01).
    pub filament_tolerance_mm: f64,
    /// Nominal filament diameter, mm.
    pub filament_diameter_mm: f64,
    /// Extrusion line width, mm (paper: 0.5).
    pub line_width_mm: f64,
    /// Stated caliper precision as a 3σ bound, mm (paper: 0.02).
    pub caliper_precision_3sigma_mm: f64,
    /// The caliper's last digit, mm: its rounding (r/√12, common to readings that agree)
    /// adds to the measurement term. The paper's budget has none (0); the solver passes
    /// `ab.caliper_resolution_mm`.
    #[serde(default)]
    pub caliper_resolution_mm: f64,
    /// Observed per-reading standard deviation, mm, when readings exist (the larger of this and
    /// the stated precision is used).
    pub observed_sigma_mm: Option<f64>,
    /// Readings per pair whose median is taken (paper: 5).
    pub readings_per_pair: usize,
    /// rotation_distance of the stepper driving the group, mm (paper: 40).
    pub rotation_distance_mm: f64,
    /// Full steps per rotation (paper: 400, 0.9° steppers).
    pub full_steps_per_rotation: u32,
    /// Microsteps (paper: 64).
    pub microsteps: u32,
    /// Klipper `gear_ratio` product (1 without a gearbox).
    pub gear_ratio: f64,
    /// Instrument trueness, ±mm (paper: 0.02).
    pub instrument_trueness_mm: f64,
    /// Near nominal distance, mm (paper: 10).
    pub d1_mm: f64,
    /// Far nominal distance, mm (paper: 150).
    pub d2_mm: f64,
}

impl Default for BudgetInputs {
    fn default() -> Self {
        Self {
            plate_cte_per_k: 1.2e-5,
            temp_band_k: 2.0,
            bed_length_mm: 70.0,
            filament_tolerance_mm: 0.01,
            filament_diameter_mm: 1.75,
            line_width_mm: 0.5,
            caliper_precision_3sigma_mm: 0.02,
            caliper_resolution_mm: 0.0,
            observed_sigma_mm: None,
            readings_per_pair: 5,
            rotation_distance_mm: 40.0,
            full_steps_per_rotation: 400,
            microsteps: 64,
            gear_ratio: 1.0,
            instrument_trueness_mm: 0.02,
            d1_mm: 10.0,
            d2_mm: 150.0,
        }
    }
}

/// The budget: each term is a bound on one reading's error, mm.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, serde::Deserialize)]
pub struct ErrorBudget {
    /// Plate thermal drift: CTE × temperature band × length.
    pub bed_mm: f64,
    /// Filament cross-section: half of (2ε/d) × line width reaches the face.
    pub filament_mm: f64,
    /// Measurement: 3 × √((1.253 σ/√n)² + r²/12): the 3σ bound of a median of n readings
    /// (σ the larger of the stated precision and the readings' own spread) and of the
    /// caliper's rounding to its last digit r ([`super::readings::centre_uncertainty`]).
    pub measurement_mm: f64,
    /// Motor resolution: half a microstep, rotation_distance / (full_steps × microsteps × gear_ratio) / 2.
    pub motor_mm: f64,
    /// Sum of the four.
    pub max_mm: f64,
    /// Bound on the scale error: 2 ε_max / (D2 − D1) (dimensionless).
    pub precision: f64,
    /// precision + instrument trueness / D2 (dimensionless).
    pub accuracy: f64,
}

/// Computes the error budget of seed 000 §3.
#[must_use]
pub fn error_budget(inp: &BudgetInputs) -> ErrorBudget {
    let bed_mm = inp.plate_cte_per_k * inp.temp_band_k * inp.bed_length_mm;
    let filament_mm = 0.5
        * (2.0 * inp.filament_tolerance_mm / inp.filament_diameter_mm.max(f64::MIN_POSITIVE))
        * inp.line_width_mm;
    let sigma = (inp.caliper_precision_3sigma_mm / 3.0).max(inp.observed_sigma_mm.unwrap_or(0.0));
    let measurement_mm = 3.0
        * (1.253 * sigma / (inp.readings_per_pair.max(1) as f64).sqrt())
            .hypot(inp.caliper_resolution_mm / 12f64.sqrt());
    let steps = f64::from(inp.full_steps_per_rotation.max(1))
        * f64::from(inp.microsteps.max(1))
        * inp.gear_ratio.max(f64::MIN_POSITIVE);
    let motor_mm = inp.rotation_distance_mm / steps / 2.0;
    let max_mm = bed_mm + filament_mm + measurement_mm + motor_mm;
    let span = (inp.d2_mm - inp.d1_mm).abs().max(f64::MIN_POSITIVE);
    let precision = 2.0 * max_mm / span;
    let accuracy = precision + inp.instrument_trueness_mm / inp.d2_mm.abs().max(f64::MIN_POSITIVE);
    ErrorBudget {
        bed_mm,
        filament_mm,
        measurement_mm,
        motor_mm,
        max_mm,
        precision,
        accuracy,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_papers_worked_example_is_reproduced() {
        // seed 000 §3.1–3.7: 2.4 µm per 100 mm (bed), ±2.9 µm (filament), 3σ_median 11.2 µm
        // (measurement, which the paper rounds to 10), 0.78 µm (motor) → ε_max ≈ 0.017 mm,
        // precision < 2.5e-4, accuracy 0.02/150 + precision ≈ 0.038 %.
        let b = error_budget(&BudgetInputs {
            bed_length_mm: 100.0,
            ..BudgetInputs::default()
        });
        assert!((b.bed_mm * 1e3 - 2.4).abs() < 0.01, "bed {}", b.bed_mm);
        assert!(
            (b.filament_mm * 1e3 - 2.9).abs() < 0.05,
            "filament {}",
            b.filament_mm
        );
        assert!(
            (b.measurement_mm * 1e3 - 11.2).abs() < 0.05,
            "meas {}",
            b.measurement_mm
        );
        assert!(
            (b.motor_mm * 1e3 - 0.78).abs() < 0.01,
            "motor {}",
            b.motor_mm
        );
        assert!((b.max_mm - 0.017).abs() < 0.0005, "eps_max {}", b.max_mm);
        assert!(b.precision < 2.5e-4, "precision {}", b.precision);
        assert!(
            (b.accuracy * 100.0 - 0.038).abs() < 0.0005,
            "accuracy {} %",
            b.accuracy * 100.0
        );
    }

    #[test]
    fn a_wider_observed_spread_replaces_the_stated_caliper_precision() {
        let stated = error_budget(&BudgetInputs::default());
        let wide = error_budget(&BudgetInputs {
            observed_sigma_mm: Some(0.02),
            ..BudgetInputs::default()
        });
        let narrow = error_budget(&BudgetInputs {
            observed_sigma_mm: Some(0.001),
            ..BudgetInputs::default()
        });
        assert!((wide.measurement_mm / stated.measurement_mm - 3.0).abs() < 1e-9);
        assert_eq!(narrow.measurement_mm, stated.measurement_mm);
    }

    #[test]
    fn a_shorter_d2_gives_a_larger_bound() {
        let short = error_budget(&BudgetInputs {
            d2_mm: 80.0,
            ..BudgetInputs::default()
        });
        assert!(short.precision > error_budget(&BudgetInputs::default()).precision * 1.9);
    }
}
