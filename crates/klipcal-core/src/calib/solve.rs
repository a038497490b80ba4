//! PURE: the solver behind `klipcal solve` — layout + readings + printer facts → one
//! [`Solution`] (stepper corrections, skew, anisotropy, error budget, warnings). No I/O: the
//! command reads the files and prints.

use serde::Serialize;

use super::budget::{error_budget, BudgetInputs, ErrorBudget};
use super::differential::{self, GroupScale, PairPoint};
use super::metric::{self, Corrections, DirectionScale, Estimate, Kinematics, ShearTo};
use super::readings::{self, CentreRules, PairCentre, RawReadings};
use super::skew;
use super::Error;
use crate::layout::Layout;

/// What the solver needs to know about one XY stepper.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, serde::Deserialize)]
pub struct StepperFacts {
    /// Klipper `rotation_distance`, mm.
    pub rotation_distance_mm: f64,
    /// Klipper `microsteps`.
    pub microsteps: u32,
    /// Klipper `full_steps_per_rotation` (200 unless set).
    pub full_steps_per_rotation: u32,
    /// Klipper `gear_ratio` product (1.0 without a gearbox).
    pub gear_ratio: f64,
}

/// The printer facts the solver needs (a subset of the Klipper config).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, serde::Deserialize)]
pub struct MotionFacts {
    /// Motion system.
    pub kinematics: Kinematics,
    /// `[stepper_x]`.
    pub stepper_x: StepperFacts,
    /// `[stepper_y]`.
    pub stepper_y: StepperFacts,
}

/// Solver options; defaults follow the paper.
#[derive(Debug, Clone, PartialEq)]
pub struct SolveOptions {
    /// How readings are reduced.
    pub rules: CentreRules,
    /// Where a CoreXY's shear goes.
    pub shear_to: ShearTo,
    /// Error budget inputs other than those taken from the layout, readings and facts.
    pub budget: BudgetInputs,
    /// The previous round's group scales (`(group, α)`), printed before applying its correction.
    pub previous: Option<Vec<(String, f64)>>,
    /// Klipper xy skew factor active while the job printed (0 when skew correction was off, as
    /// the paper asks); the skew reported is the total factor to set.
    pub current_xy_factor: f64,
}

impl Default for SolveOptions {
    fn default() -> Self {
        Self {
            rules: CentreRules::default(),
            shear_to: ShearTo::Motors,
            budget: BudgetInputs::default(),
            previous: None,
            current_xy_factor: 0.0,
        }
    }
}

/// One stepper's correction.
#[derive(Debug, Clone, PartialEq, Serialize, serde::Deserialize)]
pub struct StepperResult {
    /// Direction the stepper drives (`A`, `B`, `X`, `Y`).
    pub direction: String,
    /// Current rotation_distance, mm.
    pub rotation_distance_old: f64,
    /// New rotation_distance = old × scale, mm.
    pub rotation_distance_new: f64,
    /// Physical over commanded travel along its direction.
    pub scale: f64,
    /// Standard uncertainty of `scale`.
    pub uncertainty: f64,
    /// Steps/mm now (for other firmware).
    pub steps_per_mm_old: f64,
    /// Steps/mm after the correction.
    pub steps_per_mm_new: f64,
}

/// Skew result.
#[derive(Debug, Clone, PartialEq, Serialize, serde::Deserialize)]
pub struct SkewResult {
    /// Whether the print observed the shear (needs a group off the motor directions).
    pub observed: bool,
    /// Whether the correction goes through Klipper's skew_correction.
    pub applied: bool,
    /// Klipper's xy factor to set (x' = x − y·xy); 0 when the motors absorb the shear; `None`
    /// when not observed.
    pub xy_factor: Option<f64>,
    /// atan(xy_factor) in degrees (what GET_CURRENT_SKEW reports).
    pub angle_deg: Option<f64>,
    /// `SET_SKEW XY=AC,BD,AD` giving `xy_factor` through Klipper's calc_skew_factor.
    pub set_skew: Option<String>,
    /// Standard uncertainty of `xy_factor`.
    pub uncertainty: Option<f64>,
    /// The shear the print shows before correction, as a Klipper xy factor.
    pub measured_shear_factor: Option<f64>,
    /// Its angle in degrees.
    pub measured_shear_deg: Option<f64>,
    /// Standard uncertainty of the measured shear, degrees.
    pub measured_shear_uncertainty_deg: Option<f64>,
    /// Prusa's class of the measured shear.
    pub class: Option<skew::SkewClass>,
}

/// X/Y anisotropy (what A/B rotation distances cannot fix on a CoreXY).
#[derive(Debug, Clone, PartialEq, Serialize, serde::Deserialize)]
pub struct AnisotropyResult {
    /// Observed (needs a full layout).
    pub observed: bool,
    /// √(gxx/gyy) − 1: X travel over Y travel, minus 1.
    pub value: Option<f64>,
    /// Standard uncertainty.
    pub uncertainty: Option<f64>,
    /// |value| > 3 σ and above the precision bound.
    pub significant: bool,
    /// It remains after the corrections (CoreXY).
    pub left_after_correction: bool,
}

/// One pair's reduced readings.
#[derive(Debug, Clone, PartialEq, Serialize, serde::Deserialize)]
pub struct PairResult {
    /// Pair id.
    pub pair: String,
    /// Nominal mm.
    pub nominal_mm: f64,
    /// Centre (median of kept readings), mm.
    pub centre_mm: f64,
    /// Standard uncertainty of the centre, mm.
    pub u_mm: f64,
    /// Spread of kept readings, mm.
    pub spread_mm: f64,
    /// Rejected outliers, mm.
    pub rejected_mm: Vec<f64>,
}

/// One group's result.
#[derive(Debug, Clone, PartialEq, Serialize, serde::Deserialize)]
pub struct GroupResult {
    /// Group id.
    pub group: String,
    /// Direction, degrees from +X.
    pub direction_deg: f64,
    /// α measured from this group alone.
    pub scale: f64,
    /// Its standard uncertainty.
    pub uncertainty: f64,
    /// α the fitted geometry predicts.
    pub fitted: f64,
    /// Standardised residual.
    pub standardized_residual: f64,
    /// Residual beyond what its noise explains.
    pub flagged: bool,
    /// Precision bound 2ε_max/(D2 − D1).
    pub precision: f64,
    /// |α − 1| below the precision bound.
    pub converged: bool,
    /// Pairs.
    pub pairs: Vec<PairResult>,
}

/// Fit summary.
#[derive(Debug, Clone, PartialEq, Serialize, serde::Deserialize)]
pub struct FitSummary {
    /// All three metric entries observed.
    pub full: bool,
    /// χ² of the group residuals.
    pub chi2: f64,
    /// Degrees of freedom.
    pub dof: usize,
}

/// Everything `klipcal solve` reports.
#[derive(Debug, Clone, PartialEq, Serialize, serde::Deserialize)]
pub struct Solution {
    /// Motion system.
    pub kinematics: Kinematics,
    /// stepper_x correction.
    pub stepper_x: StepperResult,
    /// stepper_y correction.
    pub stepper_y: StepperResult,
    /// Skew.
    pub skew: SkewResult,
    /// Anisotropy.
    pub anisotropy: AnisotropyResult,
    /// The error budget of the least precise group (largest bound).
    pub error_budget: ErrorBudget,
    /// Every stepper scale within its precision bound of 1, and an applied skew factor within
    /// the bound of the factor that was active during the print.
    pub converged: bool,
    /// Per group.
    pub groups: Vec<GroupResult>,
    /// Fit summary.
    pub fit: FitSummary,
    /// Warnings, each naming what it is about.
    pub warnings: Vec<String>,
}

fn check_facts(name: &str, s: &StepperFacts) -> Result<(), Error> {
    if !(s.rotation_distance_mm.is_finite() && s.rotation_distance_mm > 0.0) {
        return Err(Error::Facts(format!(
            "{name}: rotation_distance {} is not a positive number of mm",
            s.rotation_distance_mm
        )));
    }
    if s.microsteps == 0
        || s.full_steps_per_rotation == 0
        || s.gear_ratio.is_nan()
        || s.gear_ratio <= 0.0
    {
        return Err(Error::Facts(format!(
            "{name}: microsteps, full_steps_per_rotation and gear_ratio must be positive"
        )));
    }
    Ok(())
}

/// Solves one round.
///
/// # Errors
/// Readings for pairs the layout lacks or missing for pairs it has, non-numbers, non-positive
/// readings, fewer than 3 per pair, a far pair not reading longer, a scale beyond ±5 %, a
/// layout whose kinematics differs from the printer's, or unusable printer facts.
pub fn solve(
    layout: &Layout,
    raw: &RawReadings,
    facts: &MotionFacts,
    opts: &SolveOptions,
) -> Result<Solution, Error> {
    check_facts("stepper_x", &facts.stepper_x)?;
    check_facts("stepper_y", &facts.stepper_y)?;
    let kin = facts.kinematics;
    check_layout(layout, raw, kin)?;
    let mut warnings = Vec::new();
    let scales = group_scales(layout, raw, opts, &mut warnings)?;
    let dirs: Vec<DirectionScale> = scales
        .iter()
        .map(|(g, _)| DirectionScale {
            group: g.group.clone(),
            direction_deg: g.direction_deg,
            scale: g.scale,
            uncertainty: g.uncertainty,
        })
        .collect();
    let fit = metric::fit_metric(kin, &dirs)?;
    let shear_to = shear_target(opts.shear_to, &fit, kin, &mut warnings);
    let corr: Corrections = metric::corrections(&fit, shear_to, opts.current_xy_factor);

    // Error budgets per group.
    let budgets: Vec<ErrorBudget> = scales
        .iter()
        .map(|(g, centres)| group_budget(kin, facts, opts, g, centres))
        .collect();
    let worst = budgets
        .iter()
        .copied()
        .max_by(|a, b| a.precision.total_cmp(&b.precision))
        .unwrap_or_else(|| error_budget(&opts.budget));
    let groups = group_results(&scales, &budgets, &fit, &mut warnings);

    let (na, nb) = kin.motor_names();
    let stepper_x = stepper_result(na, &facts.stepper_x, &corr.stepper_scale[0]);
    let stepper_y = stepper_result(nb, &facts.stepper_y, &corr.stepper_scale[1]);
    for s in [&stepper_x, &stepper_y] {
        if (s.scale - 1.0).abs() > differential::SCALE_LIMIT {
            return Err(Error::ScaleOutOfRange {
                group: s.direction.clone(),
                pairs: "all groups (fitted)".into(),
                scale: s.scale,
                pct: (s.scale - 1.0) * 100.0,
                limit_pct: differential::SCALE_LIMIT * 100.0,
            });
        }
    }
    let skew = skew_result(&corr, kin, &mut warnings);
    let anisotropy = anisotropy_result(&corr, worst.precision, &mut warnings);
    let converged = is_converged(
        kin,
        &scales,
        &budgets,
        worst.precision,
        opts,
        [&stepper_x, &stepper_y],
        &skew,
    );
    if let Some(prev) = &opts.previous {
        let now: Vec<(String, f64)> = groups.iter().map(|g| (g.group.clone(), g.scale)).collect();
        if let Some(w) =
            differential::swap_warning(prev, &now, worst.precision, &format!("{na} and {nb}"))
        {
            warnings.push(w);
        }
    }
    Ok(Solution {
        kinematics: kin,
        stepper_x,
        stepper_y,
        skew,
        anisotropy,
        error_budget: worst,
        converged,
        groups,
        fit: FitSummary {
            full: fit.full,
            chi2: fit.chi2,
            dof: fit.dof,
        },
        warnings,
    })
}

/// The layout is for this printer's kinematics and names every pair read.
fn check_layout(layout: &Layout, raw: &RawReadings, kin: Kinematics) -> Result<(), Error> {
    let layout_kin = Kinematics::parse(&layout.kinematics).map_err(|_| {
        Error::Layout(format!(
            "kinematics `{}` is not corexy or cartesian",
            layout.kinematics
        ))
    })?;
    if layout_kin != kin {
        return Err(Error::Layout(format!(
            "the layout was generated for {:?} but the printer config says {:?}; expected the layout of a job for this printer",
            layout_kin, kin
        )));
    }
    let known = layout
        .pairs
        .iter()
        .map(|p| p.id.as_str())
        .collect::<Vec<_>>()
        .join(", ");
    for pair in raw.keys() {
        if !layout.pairs.iter().any(|p| &p.id == pair) {
            return Err(Error::UnknownPair {
                pair: pair.clone(),
                known,
            });
        }
    }
    Ok(())
}

/// A group's scale and its pairs' centres with their nominal distances.
type ScaledGroup = (GroupScale, Vec<(PairCentre, f64)>);

/// Each group's scale from its pairs' readings, in layout order (the readings' warnings added
/// to `warnings`).
fn group_scales(
    layout: &Layout,
    raw: &RawReadings,
    opts: &SolveOptions,
    warnings: &mut Vec<String>,
) -> Result<Vec<ScaledGroup>, Error> {
    let mut group_ids: Vec<&str> = Vec::new();
    for p in &layout.pairs {
        if !group_ids.contains(&p.group.as_str()) {
            group_ids.push(&p.group);
        }
    }
    let mut scales: Vec<ScaledGroup> = Vec::new();
    for gid in &group_ids {
        let mut points = Vec::new();
        let mut centres = Vec::new();
        let pairs: Vec<_> = layout.pairs.iter().filter(|p| p.group == *gid).collect();
        let direction_deg = pairs.first().map_or(0.0, |p| p.direction_deg);
        for p in &pairs {
            let diff = (p.direction_deg - direction_deg).rem_euclid(180.0);
            if diff > 0.01 && diff < 179.99 {
                return Err(Error::Layout(format!(
                    "group {gid}: pair {} measures along {}° but the group along {direction_deg}°; expected one direction per group",
                    p.id, p.direction_deg
                )));
            }
            let values = raw
                .get(&p.id)
                .ok_or_else(|| Error::MissingPair { pair: p.id.clone() })?;
            let (c, w) = readings::centre(&p.id, values, &opts.rules)?;
            warnings.extend(w);
            points.push(PairPoint {
                pair: p.id.clone(),
                nominal_mm: p.nominal_mm,
                centre_mm: c.centre_mm,
                u_mm: c.u_mm,
            });
            centres.push((c, p.nominal_mm));
        }
        let g = differential::group_scale(gid, direction_deg, &points)?;
        scales.push((g, centres));
    }
    Ok(scales)
}

/// Where the shear goes: Klipper's skew only when the layout observes it and the printer is a
/// CoreXY; else the motors (with a warning when the skew was asked for and not observed).
fn shear_target(
    asked: ShearTo,
    fit: &metric::MetricFit,
    kin: Kinematics,
    warnings: &mut Vec<String>,
) -> ShearTo {
    if asked == ShearTo::KlipperSkew && (!fit.full || kin == Kinematics::Cartesian) {
        if !fit.full {
            warnings.push(
                "shear to Klipper skew was asked for, but this layout does not observe skew (print the `full` layout)".into(),
            );
        }
        ShearTo::Motors
    } else {
        asked
    }
}

/// One group's error budget: the stepper it runs along (off the motor axes the coarser
/// step), its span, distances and the readings' observed scatter.
fn group_budget(
    kin: Kinematics,
    facts: &MotionFacts,
    opts: &SolveOptions,
    g: &GroupScale,
    centres: &[(PairCentre, f64)],
) -> ErrorBudget {
    let [ua, ub] = kin.motor_axes();
    let n = [
        g.direction_deg.to_radians().cos(),
        g.direction_deg.to_radians().sin(),
    ];
    let along = |u: [f64; 2]| (n[0] * u[0] + n[1] * u[1]).abs();
    let stepper = if along(ua) > 0.99 {
        facts.stepper_x
    } else if along(ub) > 0.99 {
        facts.stepper_y
    } else {
        // off the motor axes both motors move: charge the coarser step
        let step = |s: &StepperFacts| {
            s.rotation_distance_mm
                / (f64::from(s.full_steps_per_rotation) * f64::from(s.microsteps) * s.gear_ratio)
        };
        if step(&facts.stepper_x) >= step(&facts.stepper_y) {
            facts.stepper_x
        } else {
            facts.stepper_y
        }
    };
    let observed = centres
        .iter()
        .map(|(c, _)| c.observed_sigma_mm)
        .fold(0.0, f64::max);
    let n_min = centres.iter().map(|(c, _)| c.n_used).min().unwrap_or(1);
    error_budget(&BudgetInputs {
        bed_length_mm: g.span_mm / 2.0,
        observed_sigma_mm: Some(observed),
        caliper_resolution_mm: opts.rules.resolution_mm,
        readings_per_pair: n_min,
        rotation_distance_mm: stepper.rotation_distance_mm,
        full_steps_per_rotation: stepper.full_steps_per_rotation,
        microsteps: stepper.microsteps,
        gear_ratio: stepper.gear_ratio,
        d1_mm: g.d1_mm,
        d2_mm: g.d2_mm,
        ..opts.budget
    })
}

/// Each group's result; a warning for each group the fit flags (with one redundant group,
/// one warning naming them all: which one is bad is unknown).
fn group_results(
    scales: &[ScaledGroup],
    budgets: &[ErrorBudget],
    fit: &metric::MetricFit,
    warnings: &mut Vec<String>,
) -> Vec<GroupResult> {
    let groups: Vec<GroupResult> = scales
        .iter()
        .zip(budgets)
        .zip(&fit.residuals)
        .map(|(((g, centres), b), r)| {
            if r.flagged && fit.dof >= 2 {
                warnings.push(format!(
                    "group {}: its scale {:.5} disagrees with the other groups' geometry ({:.5}) by {:.1} σ — a bad reading or a warped pylon; re-measure pairs {}",
                    g.group, g.scale, r.fitted, r.standardized, g.pairs.join(", ")
                ));
            }
            GroupResult {
                group: g.group.clone(),
                direction_deg: g.direction_deg,
                scale: g.scale,
                uncertainty: g.uncertainty,
                fitted: r.fitted,
                standardized_residual: r.standardized,
                flagged: r.flagged,
                precision: b.precision,
                converged: differential::converged(g.scale, b.precision),
                pairs: centres
                    .iter()
                    .map(|(c, nominal_mm)| PairResult {
                        pair: c.pair.clone(),
                        nominal_mm: *nominal_mm,
                        centre_mm: c.centre_mm,
                        u_mm: c.u_mm,
                        spread_mm: c.spread_mm,
                        rejected_mm: c.rejected_mm.clone(),
                    })
                    .collect(),
            }
        })
        .collect();
    // With one redundant group every residual is the same size: which group is bad is unknown.
    if fit.dof == 1 && fit.residuals.iter().any(|r| r.flagged) {
        warnings.push(format!(
            "the groups disagree with any one in-plane geometry by {:.1} σ (χ² {:.1} on 1 dof) — a bad reading or a warped pylon in one of groups {}; re-measure them",
            fit.chi2.sqrt(),
            fit.chi2,
            groups.iter().map(|g| g.group.as_str()).collect::<Vec<_>>().join(", ")
        ));
    }
    groups
}

/// A motor's correction: its scale `e` applied to its rotation_distance.
fn stepper_result(dir: &str, s: &StepperFacts, e: &Estimate) -> StepperResult {
    StepperResult {
        direction: dir.into(),
        rotation_distance_old: s.rotation_distance_mm,
        rotation_distance_new: differential::new_rotation_distance(s.rotation_distance_mm, e.value),
        scale: e.value,
        uncertainty: e.uncertainty,
        steps_per_mm_old: differential::steps_per_mm(
            s.full_steps_per_rotation,
            s.microsteps,
            s.gear_ratio,
            s.rotation_distance_mm,
        ),
        steps_per_mm_new: differential::steps_per_mm(
            s.full_steps_per_rotation,
            s.microsteps,
            s.gear_ratio,
            s.rotation_distance_mm * e.value,
        ),
    }
}

/// The skew: measured when the layout observes it, applied when the shear goes to Klipper's
/// skew (a Cartesian printer's `paper` layout is warned about: it cannot see skew).
fn skew_result(corr: &Corrections, kin: Kinematics, warnings: &mut Vec<String>) -> SkewResult {
    match (&corr.shear_factor, &corr.xy_factor) {
        (None, _) => {
            if kin == Kinematics::Cartesian {
                warnings.push(
                    "skew was not observed: the `paper` layout measures only X and Y; print the `full` layout to fit skew".into(),
                );
            }
            SkewResult {
                observed: false,
                applied: false,
                xy_factor: None,
                angle_deg: None,
                set_skew: None,
                uncertainty: None,
                measured_shear_factor: None,
                measured_shear_deg: None,
                measured_shear_uncertainty_deg: None,
                class: None,
            }
        }
        (Some(shear), xy) => {
            let shear_deg = shear.value.atan().to_degrees();
            let (applied, f, u) = match xy {
                Some(e) => (true, e.value, e.uncertainty),
                None => (false, 0.0, 0.0),
            };
            SkewResult {
                observed: true,
                applied,
                xy_factor: Some(f),
                angle_deg: Some(f.atan().to_degrees()),
                set_skew: if applied {
                    skew::set_skew_command(f)
                } else {
                    None
                },
                uncertainty: Some(u),
                measured_shear_factor: Some(shear.value),
                measured_shear_deg: Some(shear_deg),
                measured_shear_uncertainty_deg: Some(shear.uncertainty.to_degrees()),
                class: Some(skew::classify_skew(shear_deg)),
            }
        }
    }
}

/// X/Y anisotropy when observed: significant beyond 3 σ and the precision bound, warned about
/// when the correction leaves it.
fn anisotropy_result(
    corr: &Corrections,
    precision: f64,
    warnings: &mut Vec<String>,
) -> AnisotropyResult {
    match corr.anisotropy {
        Some(a) => {
            let significant = a.value.abs() > 3.0 * a.uncertainty && a.value.abs() > precision;
            if significant && corr.anisotropy_left {
                warnings.push(format!(
                    "X/Y anisotropy {:+.4} % (± {:.4} %): X and Y travel differ by more than the noise, which A/B rotation distances cannot fix (a frame or belt-path issue)",
                    a.value * 100.0,
                    a.uncertainty * 100.0
                ));
            }
            AnisotropyResult {
                observed: true,
                value: Some(a.value),
                uncertainty: Some(a.uncertainty),
                significant,
                left_after_correction: corr.anisotropy_left,
            }
        }
        None => AnisotropyResult {
            observed: false,
            value: None,
            uncertainty: None,
            significant: false,
            left_after_correction: false,
        },
    }
}

/// Every stepper scale within the precision bound of the groups along its motor (else the
/// worst group's), and an applied skew factor that no longer changes.
fn is_converged(
    kin: Kinematics,
    scales: &[ScaledGroup],
    budgets: &[ErrorBudget],
    worst: f64,
    opts: &SolveOptions,
    [stepper_x, stepper_y]: [&StepperResult; 2],
    skew: &SkewResult,
) -> bool {
    let [ua, ub] = kin.motor_axes();
    let prec_of = |dir: [f64; 2]| {
        scales
            .iter()
            .zip(budgets)
            .filter(|((g, _), _)| {
                let t = g.direction_deg.to_radians();
                (t.cos() * dir[0] + t.sin() * dir[1]).abs() > 0.99
            })
            .map(|(_, b)| b.precision)
            .fold(f64::NAN, f64::min)
    };
    let px = prec_of(ua);
    let py = prec_of(ub);
    let px = if px.is_nan() { worst } else { px };
    let py = if py.is_nan() { worst } else { py };
    // an applied skew has converged when the factor to set no longer changes
    let skew_settled =
        !skew.applied || (skew.xy_factor.unwrap_or(0.0) - opts.current_xy_factor).abs() < worst;
    differential::converged(stepper_x.scale, px)
        && differential::converged(stepper_y.scale, py)
        && skew_settled
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::calib::metric::machine_matrix;
    use crate::calib::sim::{facts, print_and_measure, simulated_layout, SimParams};
    use rand::SeedableRng;

    fn readings(
        kin: Kinematics,
        full: bool,
        alpha: [f64; 2],
        skew_deg: f64,
    ) -> (Layout, RawReadings) {
        let layout = simulated_layout(kin, full, 10.0, 150.0);
        let p = SimParams {
            width_scatter_mm: 0.0,
            caliper_sigma_mm: 0.0,
            ..SimParams::default()
        };
        let m = machine_matrix(kin, alpha, skew_deg.to_radians());
        let mut rng = rand::rngs::StdRng::seed_from_u64(7);
        let raw = print_and_measure(&layout, &m, 0.005, 0.0, &p, &mut rng);
        (layout, raw)
    }

    #[test]
    fn a_paper_corexy_round_gives_new_rotation_distances_and_the_json_fields() {
        let (layout, raw) = readings(Kinematics::CoreXy, false, [1.004, 0.997], 0.0);
        let sol = solve(
            &layout,
            &raw,
            &facts(Kinematics::CoreXy),
            &SolveOptions::default(),
        )
        .expect("solves");
        assert!((sol.stepper_x.rotation_distance_new - 40.0 * 1.004).abs() < 1e-6);
        assert!((sol.stepper_y.rotation_distance_new - 40.0 * 0.997).abs() < 1e-6);
        assert!(!sol.converged);
        assert!(!sol.skew.observed);
        let json = serde_json::to_value(&sol).expect("serialises");
        for key in [
            "stepper_x",
            "stepper_y",
            "skew",
            "anisotropy",
            "error_budget",
            "converged",
            "warnings",
        ] {
            assert!(json.get(key).is_some(), "missing {key}");
        }
        for key in [
            "rotation_distance_old",
            "rotation_distance_new",
            "scale",
            "uncertainty",
        ] {
            assert!(
                json["stepper_x"].get(key).is_some(),
                "missing stepper_x.{key}"
            );
        }
        for key in [
            "observed",
            "xy_factor",
            "angle_deg",
            "set_skew",
            "uncertainty",
        ] {
            assert!(json["skew"].get(key).is_some(), "missing skew.{key}");
        }
    }

    #[test]
    fn a_converged_machine_reports_converged() {
        let (layout, raw) = readings(Kinematics::CoreXy, true, [1.0, 1.0], 0.0);
        let sol = solve(
            &layout,
            &raw,
            &facts(Kinematics::CoreXy),
            &SolveOptions::default(),
        )
        .expect("solves");
        assert!(sol.converged, "{:?}", sol.stepper_x);
    }

    #[test]
    fn a_full_cartesian_round_sets_a_skew_that_klipper_turns_back_into_the_factor() {
        let (layout, raw) = readings(Kinematics::Cartesian, true, [1.003, 0.998], 0.3);
        let sol = solve(
            &layout,
            &raw,
            &facts(Kinematics::Cartesian),
            &SolveOptions::default(),
        )
        .expect("solves");
        assert!(sol.skew.observed && sol.skew.applied);
        let f = sol.skew.xy_factor.expect("factor");
        assert!((f - 0.3f64.to_radians().tan()).abs() < 1e-6, "{f}");
        let cmd = sol.skew.set_skew.expect("command");
        let n: Vec<f64> = cmd
            .trim_start_matches("SET_SKEW XY=")
            .split(',')
            .map(|s| s.parse().expect("number"))
            .collect();
        let back = skew::calc_skew_factor(n[0], n[1], n[2]).expect("valid");
        assert!((back - f).abs() < 1e-6);
    }

    #[test]
    fn a_paper_cartesian_round_says_skew_was_not_observed() {
        let (layout, raw) = readings(Kinematics::Cartesian, false, [1.003, 0.998], 0.3);
        let sol = solve(
            &layout,
            &raw,
            &facts(Kinematics::Cartesian),
            &SolveOptions::default(),
        )
        .expect("solves");
        assert!(!sol.skew.observed);
        assert!(sol
            .warnings
            .iter()
            .any(|w| w.contains("skew was not observed")));
    }

    #[test]
    fn bad_inputs_are_errors_that_name_the_pair() {
        let kin = Kinematics::CoreXy;
        let (layout, raw) = readings(kin, false, [1.0, 1.0], 0.0);
        let f = facts(kin);
        let o = SolveOptions::default();

        let mut r = raw.clone();
        r.insert("Z-D9".into(), vec![1.0, 1.0, 1.0]);
        let e = solve(&layout, &r, &f, &o).unwrap_err();
        assert!(matches!(e, Error::UnknownPair { .. }) && e.to_string().contains("Z-D9"));

        let mut r = raw.clone();
        r.remove("B-D2");
        let e = solve(&layout, &r, &f, &o).unwrap_err();
        assert!(e.to_string().contains("B-D2"), "{e}");

        let mut r = raw.clone();
        r.insert("A-D1".into(), vec![10.0, 10.01]);
        let e = solve(&layout, &r, &f, &o).unwrap_err();
        assert!(matches!(e, Error::TooFewReadings { .. }) && e.to_string().contains("A-D1"));

        let mut r = raw.clone();
        r.insert("A-D2".into(), vec![9.0, 9.0, 9.0]);
        let e = solve(&layout, &r, &f, &o).unwrap_err();
        assert!(matches!(e, Error::NotIncreasing { .. }) && e.to_string().contains("A-D2"));

        let mut r = raw.clone();
        let d1 = r["A-D1"][0];
        r.insert("A-D2".into(), vec![d1 + 150.0; 5]);
        let e = solve(&layout, &r, &f, &o).unwrap_err();
        assert!(matches!(e, Error::ScaleOutOfRange { .. }) && e.to_string().contains("A-D2"));

        let mut r = raw.clone();
        r.insert("B-D1".into(), vec![10.0, -10.0, 10.0]);
        let e = solve(&layout, &r, &f, &o).unwrap_err();
        assert!(e.to_string().contains("B-D1") && e.to_string().contains("positive"));

        let e = solve(&layout, &raw, &facts(Kinematics::Cartesian), &o).unwrap_err();
        assert!(e.to_string().contains("layout"), "{e}");
    }

    #[test]
    fn a_bad_reading_in_a_full_layout_is_flagged() {
        let kin = Kinematics::CoreXy;
        let (layout, mut raw) = readings(kin, true, [1.002, 0.999], 0.1);
        let clean = solve(&layout, &raw, &facts(kin), &SolveOptions::default()).expect("solves");
        assert!(
            !clean.warnings.iter().any(|w| w.contains("disagree")),
            "{:?}",
            clean.warnings
        );
        if let Some(v) = raw.get_mut("X-D2") {
            v.iter_mut().for_each(|x| *x += 0.05);
        }
        let bad = solve(&layout, &raw, &facts(kin), &SolveOptions::default()).expect("solves");
        assert!(
            bad.warnings
                .iter()
                .any(|w| w.contains("disagree") && w.contains('X')),
            "{:?}",
            bad.warnings
        );
    }

    #[test]
    fn a_correction_that_made_things_worse_warns_of_swapped_motors() {
        let (layout, raw) = readings(Kinematics::CoreXy, false, [1.008, 0.992], 0.0);
        let opts = SolveOptions {
            previous: Some(vec![("A".into(), 0.996), ("B".into(), 1.004)]),
            ..SolveOptions::default()
        };
        let sol = solve(&layout, &raw, &facts(Kinematics::CoreXy), &opts).expect("solves");
        assert!(
            sol.warnings
                .iter()
                .any(|w| w.contains("A and B may be swapped")),
            "{:?}",
            sol.warnings
        );
    }
}
