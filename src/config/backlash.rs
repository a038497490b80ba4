//! `[backlash]`: the guided camera measurement's settings and the parameters of its
//! statistics (checked by `calib::backlash` and `calib::backlash_guide`).

use serde::Deserialize;

/// `[backlash]`: the guided camera measurement and its statistics (seed 004).
#[derive(Debug, Clone, Deserialize, PartialEq)]
#[serde(default, deny_unknown_fields)]
pub struct BacklashConfig {
    /// Cycles per axis (KLIPCAL_BACKLASH_START CYCLES= overrides).
    pub cycles: usize,
    /// Approach distance, mm (the seed's 1 mm).
    pub approach_mm: f64,
    /// Coarse jog, mm.
    pub coarse_mm: f64,
    /// Fine jog of odd cycles, mm (the reading resolution).
    pub fine_mm: f64,
    /// Fine jog of even cycles, mm (0: off); removes a stopping bias proportional to the jog.
    pub small_fine_mm: f64,
    /// Furthest a jog may take the nozzle from the camera point, mm.
    pub max_travel_mm: f64,
    /// "Centred" is refused while more than this short of the camera point, mm.
    pub plausible_mm: f64,
    /// At or below this no compensation is needed (seed: 0.01–0.02 mm).
    pub none_needed_max_mm: f64,
    /// From this compensation is needed (seed: ~0.05 mm).
    pub needed_from_mm: f64,
    /// The verdict's cut between the two.
    pub compensate_from_mm: f64,
    /// Per-cycle sd assumed with fewer than 3 cycles, mm.
    pub prior_cycle_sd_mm: f64,
    /// The compensation's extra acceleration 2·b/t² may use this fraction of max_accel.
    pub accel_budget_fraction: f64,
    /// Outlier cut, robust sd from the median.
    pub outlier_sigmas: f64,
    /// The nozzle camera's name in Moonraker's webcam list (KLIPCAL_BACKLASH_CAMERA); empty:
    /// the only webcam there is.
    pub webcam: String,
    /// After a move, wait this long before the first frame (vibration, camera latency), s.
    pub camera_settle_s: f64,
}

impl Default for BacklashConfig {
    fn default() -> Self {
        let p = crate::calib::backlash::BacklashParams::default();
        let g = crate::calib::backlash_guide::GuideParams::default();
        BacklashConfig {
            cycles: g.cycles,
            approach_mm: g.approach_mm,
            coarse_mm: g.coarse_mm,
            fine_mm: g.fine_mm,
            small_fine_mm: g.small_fine_mm,
            max_travel_mm: g.max_travel_mm,
            plausible_mm: g.plausible_mm,
            none_needed_max_mm: p.none_needed_max_mm,
            needed_from_mm: p.needed_from_mm,
            compensate_from_mm: p.compensate_from_mm,
            prior_cycle_sd_mm: p.prior_cycle_sd_mm,
            accel_budget_fraction: p.accel_budget_fraction,
            outlier_sigmas: p.outlier_sigmas,
            webcam: String::new(),
            camera_settle_s: 0.3,
        }
    }
}

impl BacklashConfig {
    /// The statistics' settings.
    pub fn params(&self) -> crate::calib::backlash::BacklashParams {
        crate::calib::backlash::BacklashParams {
            none_needed_max_mm: self.none_needed_max_mm,
            needed_from_mm: self.needed_from_mm,
            compensate_from_mm: self.compensate_from_mm,
            // The resolution of cycles that do not say their jog (a readings file: the
            // seed's own jogs, 0.01 mm), not the guided flow's big fine jog.
            jog_resolution_mm: crate::calib::backlash::BacklashParams::default().jog_resolution_mm,
            prior_cycle_sd_mm: self.prior_cycle_sd_mm,
            accel_budget_fraction: self.accel_budget_fraction,
            outlier_sigmas: self.outlier_sigmas,
            scale_rel_sd: 0.0,
            repeat_sd_mm: 0.0,
            step_mm: 0.0,
            mean_of_cycles: false,
        }
    }

    /// The guided procedure's settings.
    pub fn guide(&self) -> crate::calib::backlash_guide::GuideParams {
        crate::calib::backlash_guide::GuideParams {
            cycles: self.cycles,
            approach_mm: self.approach_mm,
            coarse_mm: self.coarse_mm,
            fine_mm: self.fine_mm,
            small_fine_mm: self.small_fine_mm,
            max_travel_mm: self.max_travel_mm,
            plausible_mm: self.plausible_mm,
            crossing: true,
        }
    }
}
