//! PURE: the in-plane geometry from every group at once. A machine maps commanded c to physical
//! M·c; calipers read the perpendicular distance between two parallel faces, so a group along
//! commanded unit normal n measures the scale s = 1/|M⁻ᵀn|, i.e. 1/s² = nᵀHn with H = (MᵀM)⁻¹,
//! linear in H's three entries. This file fits H by weighted least squares and maps the metric
//! G = MᵀM onto the corrections a printer has. No I/O.

use nalgebra::{DMatrix, DVector, Matrix2, Matrix3, Vector3};
use serde::Serialize;

use super::Error;

/// Motion system.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, serde::Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Kinematics {
    /// stepper_x moves A = x + y (direction +45°), stepper_y moves B = x − y (−45°).
    #[serde(rename = "corexy")]
    CoreXy,
    /// stepper_x moves X, stepper_y moves Y.
    Cartesian,
}

impl Kinematics {
    /// Parses `"corexy"` / `"cartesian"` (Klipper's names).
    ///
    /// # Errors
    /// Any other kinematics.
    pub fn parse(name: &str) -> Result<Self, Error> {
        match name.trim().to_ascii_lowercase().as_str() {
            "corexy" => Ok(Self::CoreXy),
            "cartesian" => Ok(Self::Cartesian),
            other => Err(Error::Facts(format!(
                "kinematics `{other}` is not supported; expected corexy or cartesian"
            ))),
        }
    }

    /// Unit vectors (commanded XY) of the directions stepper_x and stepper_y move the toolhead.
    #[must_use]
    pub fn motor_axes(self) -> [[f64; 2]; 2] {
        let r = std::f64::consts::FRAC_1_SQRT_2;
        match self {
            Self::CoreXy => [[r, r], [r, -r]],
            Self::Cartesian => [[1.0, 0.0], [0.0, 1.0]],
        }
    }

    /// Klipper's name: `corexy` or `cartesian`.
    #[must_use]
    pub fn name(self) -> &'static str {
        match self {
            Self::CoreXy => "corexy",
            Self::Cartesian => "cartesian",
        }
    }

    /// Names of the two motor directions, e.g. `("A", "B")`.
    #[must_use]
    pub fn motor_names(self) -> (&'static str, &'static str) {
        match self {
            Self::CoreXy => ("A", "B"),
            Self::Cartesian => ("X", "Y"),
        }
    }

    /// Matrix whose columns are the motor axes: commanded XY = R · motor coordinates.
    #[must_use]
    pub fn motor_basis(self) -> Matrix2<f64> {
        let [u, v] = self.motor_axes();
        Matrix2::new(u[0], v[0], u[1], v[1])
    }
}

/// One group's measured scale along a commanded direction.
#[derive(Debug, Clone, PartialEq)]
pub struct DirectionScale {
    /// Group id.
    pub group: String,
    /// Commanded measuring direction, degrees from +X.
    pub direction_deg: f64,
    /// Measured scale s (reading difference over nominal difference).
    pub scale: f64,
    /// Its standard uncertainty.
    pub uncertainty: f64,
}

/// A value with its standard uncertainty.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, serde::Deserialize)]
pub struct Estimate {
    /// The value.
    pub value: f64,
    /// Its standard uncertainty.
    pub uncertainty: f64,
}

/// A group's agreement with the fitted metric.
#[derive(Debug, Clone, PartialEq, Serialize, serde::Deserialize)]
pub struct GroupResidual {
    /// Group id.
    pub group: String,
    /// Measured scale.
    pub measured: f64,
    /// Scale the fitted metric predicts along the group's direction.
    pub fitted: f64,
    /// Standardised residual (residual over its own standard deviation); 0 when the fit has no
    /// redundancy.
    pub standardized: f64,
    /// |standardized| > 3: more than the group's noise explains (a bad reading, a warped pylon).
    pub flagged: bool,
}

/// The fitted metric.
#[derive(Debug, Clone, PartialEq)]
pub struct MetricFit {
    /// Motion system the fit is parameterised in.
    pub kinematics: Kinematics,
    /// H = (MᵀM)⁻¹ in the motor basis: [h11, h12, h22].
    pub h_motor: Vector3<f64>,
    /// Covariance of `h_motor`.
    pub cov: Matrix3<f64>,
    /// `true` when all three entries were observed (≥ 3 independent directions); `false` when
    /// only the two motor directions were measured and h12 is held at 0.
    pub full: bool,
    /// Per-group residuals.
    pub residuals: Vec<GroupResidual>,
    /// χ² of the weighted residuals and its degrees of freedom.
    pub chi2: f64,
    /// Degrees of freedom.
    pub dof: usize,
}

fn unit(direction_deg: f64) -> [f64; 2] {
    let t = direction_deg.to_radians();
    [t.cos(), t.sin()]
}

/// Fits H from the groups' scales by weighted least squares on 1/s² (weight 1/var(1/s²) with
/// var(1/s²) = (2 u_s / s³)²).
///
/// # Errors
/// The directions do not cover both motor directions (nothing to solve for one stepper).
pub fn fit_metric(kin: Kinematics, groups: &[DirectionScale]) -> Result<MetricFit, Error> {
    let [u, v] = kin.motor_axes();
    let rows: Vec<([f64; 3], f64, f64)> = groups
        .iter()
        .map(|g| {
            let n = unit(g.direction_deg);
            let (a, b) = (n[0] * u[0] + n[1] * u[1], n[0] * v[0] + n[1] * v[1]);
            let y = 1.0 / (g.scale * g.scale);
            let sy = 2.0 * g.uncertainty.max(1e-9) / g.scale.powi(3);
            ([a * a, 2.0 * a * b, b * b], y, sy)
        })
        .collect();
    let off_axis = rows.iter().any(|(r, _, _)| r[1].abs() > 0.05);
    let try_fit = |cols: &[usize]| -> Option<(DVector<f64>, DMatrix<f64>)> {
        let m = rows.len();
        let k = cols.len();
        let mut a = DMatrix::zeros(m, k);
        let mut y = DVector::zeros(m);
        for (i, (r, yi, sy)) in rows.iter().enumerate() {
            for (j, &c) in cols.iter().enumerate() {
                a[(i, j)] = r[c] / sy;
            }
            y[i] = yi / sy;
        }
        let n = a.transpose() * &a;
        let eig = n.clone().symmetric_eigen().eigenvalues;
        let (lo, hi) = eig.iter().fold((f64::INFINITY, 0.0f64), |(lo, hi), &e| {
            (lo.min(e), hi.max(e.abs()))
        });
        if m < k || lo.is_nan() || lo <= hi * 1e-10 {
            return None;
        }
        let cov = n.try_inverse()?;
        let p = &cov * (a.transpose() * y);
        Some((p, cov))
    };
    let (p, cov, full) = if off_axis {
        let (p, c) = try_fit(&[0, 1, 2]).ok_or_else(|| {
            Error::Layout(
                "the groups' directions do not determine the in-plane geometry; expected groups along both motor directions and at least one other direction".into(),
            )
        })?;
        (
            Vector3::new(p[0], p[1], p[2]),
            Matrix3::from_fn(|i, j| c[(i, j)]),
            true,
        )
    } else {
        let (p, c) = try_fit(&[0, 2]).ok_or_else(|| {
            let (a, b) = kin.motor_names();
            Error::Layout(format!(
                "expected groups along both motor directions {a} and {b}"
            ))
        })?;
        let mut cov = Matrix3::zeros();
        cov[(0, 0)] = c[(0, 0)];
        cov[(0, 2)] = c[(0, 1)];
        cov[(2, 0)] = c[(1, 0)];
        cov[(2, 2)] = c[(1, 1)];
        (Vector3::new(p[0], 0.0, p[1]), cov, false)
    };
    let k = if full { 3 } else { 2 };
    let dof = rows.len().saturating_sub(k);
    let mut chi2 = 0.0;
    let residuals = rows
        .iter()
        .zip(groups)
        .map(|((r, y, sy), g)| {
            let x = Vector3::new(r[0], r[1], r[2]);
            let pred = x.dot(&p);
            let res = y - pred;
            chi2 += (res / sy).powi(2);
            let leverage = (x.transpose() * cov * x)[(0, 0)] / (sy * sy);
            let denom = sy * (1.0 - leverage).max(0.0).sqrt();
            let standardized = if dof > 0 && denom > 1e-15 {
                res / denom
            } else {
                0.0
            };
            GroupResidual {
                group: g.group.clone(),
                measured: g.scale,
                fitted: 1.0 / pred.max(1e-12).sqrt(),
                standardized,
                flagged: standardized.abs() > 3.0,
            }
        })
        .collect();
    Ok(MetricFit {
        kinematics: kin,
        h_motor: p,
        cov,
        full,
        residuals,
        chi2,
        dof,
    })
}

/// G = MᵀM in commanded XY from H in the motor basis.
#[must_use]
pub fn metric_xy(kin: Kinematics, h_motor: &Vector3<f64>) -> Matrix2<f64> {
    let h = Matrix2::new(h_motor[0], h_motor[1], h_motor[1], h_motor[2]);
    let r = kin.motor_basis();
    let h_xy = r * h * r.transpose();
    h_xy.try_inverse().unwrap_or_else(Matrix2::identity)
}

/// Where the shear goes on a CoreXY.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, serde::Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum ShearTo {
    /// A and B rotation distances remove common scale and all shear (the paper's fixed point).
    Motors,
    /// Matched belts, skewed frame: one common scale for A and B, shear to Klipper's skew.
    KlipperSkew,
}

/// The corrections derived from a metric.
#[derive(Debug, Clone, PartialEq, Serialize, serde::Deserialize)]
pub struct Corrections {
    /// Scale factor (new/old rotation_distance) for stepper_x and stepper_y.
    pub stepper_scale: [Estimate; 2],
    /// Klipper xy skew factor to set (`None` when skew is not applied through Klipper).
    pub xy_factor: Option<Estimate>,
    /// The shear the print shows before correction, as Klipper's factor gxy/√det G (`None`
    /// when not observed).
    pub shear_factor: Option<Estimate>,
    /// X/Y anisotropy √(gxx/gyy) − 1 (`None` when not observed).
    pub anisotropy: Option<Estimate>,
    /// The anisotropy stays after these corrections (CoreXY: A/B cannot fix it).
    pub anisotropy_left: bool,
}

fn propagate(fit: &MetricFit, f: &dyn Fn(&Vector3<f64>) -> f64) -> Estimate {
    let value = f(&fit.h_motor);
    let mut grad = Vector3::zeros();
    for i in 0..3 {
        if !fit.full && i == 1 {
            continue;
        }
        let h = 1e-6 * fit.h_motor[i].abs().max(1e-3);
        let mut up = fit.h_motor;
        let mut dn = fit.h_motor;
        up[i] += h;
        dn[i] -= h;
        grad[i] = (f(&up) - f(&dn)) / (2.0 * h);
    }
    let var = (grad.transpose() * fit.cov * grad)[(0, 0)];
    Estimate {
        value,
        uncertainty: var.max(0.0).sqrt(),
    }
}

/// Maps a fitted metric onto stepper scales (new/old rotation_distance) and the total Klipper
/// skew factor to set, given the factor `current_xy` that was active during the print.
///
/// - CoreXY, [`ShearTo::Motors`]: kA = √G_AA, kB = √G_BB (motor basis): scale along A and B
///   becomes exactly 1 and the XY shear vanishes; X/Y anisotropy stays.
/// - CoreXY, [`ShearTo::KlipperSkew`] (full fit only): kA = kB = det(G)^¼, xy = gxy/gxx.
/// - Cartesian: kx = √gxx, ky = √(det G / gxx), xy = gxy/√det G, which makes the metric the
///   identity (physical = M·K⁻¹·S·c with S Klipper's x − y·xy); without shear observed, only
///   kx, ky from the two axes.
#[must_use]
pub fn corrections(fit: &MetricFit, shear_to: ShearTo, current_xy: f64) -> Corrections {
    let kin = fit.kinematics;
    // The print saw M·S(current); the corrections act on M = (M·S)·S(current)⁻¹.
    let s_inv = Matrix2::new(1.0, current_xy, 0.0, 1.0);
    let g = move |h: &Vector3<f64>| s_inv.transpose() * metric_xy(kin, h) * s_inv;
    let r = kin.motor_basis();
    let g_motor = move |h: &Vector3<f64>| r.transpose() * g(h) * r;
    let shear_factor = fit.full.then(|| {
        propagate(fit, &|h| {
            let g = g(h);
            g[(0, 1)] / g.determinant().sqrt()
        })
    });
    let anisotropy = fit.full.then(|| {
        propagate(fit, &|h| {
            let g = g(h);
            (g[(0, 0)] / g[(1, 1)]).sqrt() - 1.0
        })
    });
    match (kin, shear_to, fit.full) {
        (Kinematics::CoreXy, ShearTo::KlipperSkew, true) => {
            let k = propagate(fit, &|h| g(h).determinant().powf(0.25));
            Corrections {
                stepper_scale: [k, k],
                xy_factor: Some(propagate(fit, &|h| {
                    let g = g(h);
                    g[(0, 1)] / g[(0, 0)]
                })),
                shear_factor,
                anisotropy,
                anisotropy_left: true,
            }
        }
        (Kinematics::CoreXy, _, _) | (Kinematics::Cartesian, _, false) => Corrections {
            stepper_scale: [
                propagate(fit, &|h| g_motor(h)[(0, 0)].sqrt()),
                propagate(fit, &|h| g_motor(h)[(1, 1)].sqrt()),
            ],
            xy_factor: None,
            shear_factor,
            anisotropy,
            anisotropy_left: kin == Kinematics::CoreXy,
        },
        (Kinematics::Cartesian, _, true) => Corrections {
            stepper_scale: [
                propagate(fit, &|h| g(h)[(0, 0)].sqrt()),
                propagate(fit, &|h| {
                    let g = g(h);
                    (g.determinant() / g[(0, 0)]).sqrt()
                }),
            ],
            xy_factor: Some(propagate(fit, &|h| {
                let g = g(h);
                g[(0, 1)] / g.determinant().sqrt()
            })),
            shear_factor,
            anisotropy,
            anisotropy_left: false,
        },
    }
}

/// The machine matrix M of a motion system with motor scales (physical travel over commanded
/// travel of each motor direction) under a frame whose Y axis leans by `frame_skew_rad`
/// (physical x += tan(φ)·y).
#[must_use]
pub fn machine_matrix(kin: Kinematics, motor_scale: [f64; 2], frame_skew_rad: f64) -> Matrix2<f64> {
    let r = kin.motor_basis();
    let d = Matrix2::new(motor_scale[0], 0.0, 0.0, motor_scale[1]);
    let frame = Matrix2::new(1.0, frame_skew_rad.tan(), 0.0, 1.0);
    frame * r * d * r.transpose()
}

/// The effective machine after corrections: physical = M · R·diag(1/k)·Rᵀ · S · c, with S
/// Klipper's skew transform (x − y·xy).
#[must_use]
pub fn corrected_matrix(
    kin: Kinematics,
    m: &Matrix2<f64>,
    stepper_scale: [f64; 2],
    xy_factor: f64,
) -> Matrix2<f64> {
    let r = kin.motor_basis();
    let kinv = Matrix2::new(1.0 / stepper_scale[0], 0.0, 0.0, 1.0 / stepper_scale[1]);
    let s = Matrix2::new(1.0, -xy_factor, 0.0, 1.0);
    m * r * kinv * r.transpose() * s
}

/// Scale a pair of faces with commanded normal `direction_deg` reads on machine M: 1/|M⁻ᵀn|.
#[must_use]
pub fn face_scale(m: &Matrix2<f64>, direction_deg: f64) -> f64 {
    let n = unit(direction_deg);
    let minv_t = m
        .try_inverse()
        .unwrap_or_else(Matrix2::identity)
        .transpose();
    let v = minv_t * nalgebra::Vector2::new(n[0], n[1]);
    1.0 / v.norm()
}

/// Scale of motion along commanded direction `direction_deg` on machine M: |M u|.
#[must_use]
pub fn motion_scale(m: &Matrix2<f64>, direction_deg: f64) -> f64 {
    let n = unit(direction_deg);
    (m * nalgebra::Vector2::new(n[0], n[1])).norm()
}

#[cfg(test)]
mod tests {
    use super::*;

    fn observe(m: &Matrix2<f64>, dirs: &[f64]) -> Vec<DirectionScale> {
        dirs.iter()
            .map(|&d| DirectionScale {
                group: format!("{d}"),
                direction_deg: d,
                scale: face_scale(m, d),
                uncertainty: 3.8e-5,
            })
            .collect()
    }

    #[test]
    fn faces_read_differently_from_pylon_centres_on_a_mismatched_corexy() {
        // issue 4 §2: αA = 1.02, αB = 0.98 — a pair along X reads 0.9994 while centres move 1.0002.
        let m = machine_matrix(Kinematics::CoreXy, [1.02, 0.98], 0.0);
        let faces = face_scale(&m, 0.0);
        let centres = motion_scale(&m, 0.0);
        assert!((faces - 0.9994).abs() < 5e-5, "{faces}");
        assert!((centres - 1.0002).abs() < 5e-5, "{centres}");
        assert!(((centres - faces) * 150.0 * 1000.0 - 120.0).abs() < 10.0);
    }

    #[test]
    fn frame_skew_and_a_b_mismatch_give_the_same_shear() {
        // issue 4 §2: 0.5° skew ≈ A/B ±0.436 %; metrics agree to ~1e-5.
        let phi = 0.5f64.to_radians();
        let skewed = machine_matrix(Kinematics::CoreXy, [1.0, 1.0], phi);
        let belts = machine_matrix(Kinematics::CoreXy, [1.00436, 0.99564], 0.0);
        let (g1, g2) = (skewed.transpose() * skewed, belts.transpose() * belts);
        assert!((g1[(0, 1)] - g2[(0, 1)]).abs() < 2e-5, "{g1} {g2}");
        assert!((g1 - g2).abs().max() < 1e-4);
    }

    #[test]
    fn a_full_corexy_fit_recovers_the_motor_scales_in_one_step() {
        let kin = Kinematics::CoreXy;
        let m = machine_matrix(kin, [1.012, 0.991], 0.0);
        let fit = fit_metric(kin, &observe(&m, &[45.0, -45.0, 0.0, 90.0])).expect("fit");
        assert!(fit.full);
        let c = corrections(&fit, ShearTo::Motors, 0.0);
        assert!((c.stepper_scale[0].value - 1.012).abs() < 1e-9, "{c:?}");
        assert!((c.stepper_scale[1].value - 0.991).abs() < 1e-9);
        let after = corrected_matrix(
            kin,
            &m,
            [c.stepper_scale[0].value, c.stepper_scale[1].value],
            0.0,
        );
        for d in [0.0, 45.0, 90.0, -45.0] {
            assert!((motion_scale(&after, d) - 1.0).abs() < 1e-9);
        }
        assert!(c.stepper_scale[0].uncertainty > 0.0 && c.stepper_scale[0].uncertainty < 1e-4);
    }

    #[test]
    fn a_skewed_cartesian_is_made_square_through_klipper_skew() {
        let kin = Kinematics::Cartesian;
        let m = machine_matrix(kin, [1.006, 0.996], 0.4f64.to_radians());
        let fit = fit_metric(kin, &observe(&m, &[0.0, 90.0, 45.0, -45.0])).expect("fit");
        let c = corrections(&fit, ShearTo::Motors, 0.0);
        let f = c.xy_factor.expect("skew applied").value;
        assert!((f - 0.4f64.to_radians().tan()).abs() < 1e-4, "{f}");
        let after = corrected_matrix(
            kin,
            &m,
            [c.stepper_scale[0].value, c.stepper_scale[1].value],
            f,
        );
        let g = after.transpose() * after;
        assert!((g - Matrix2::identity()).abs().max() < 1e-9, "{g}");
    }

    #[test]
    fn a_second_round_with_skew_already_set_reports_the_total_factor() {
        let kin = Kinematics::Cartesian;
        let m = machine_matrix(kin, [1.01, 0.985], 0.4f64.to_radians());
        let fresh = corrections(
            &fit_metric(kin, &observe(&m, &[0.0, 90.0, 45.0, -45.0])).expect("fit"),
            ShearTo::Motors,
            0.0,
        );
        let half = 0.5 * fresh.xy_factor.expect("skew").value;
        let printed = corrected_matrix(kin, &m, [1.0, 1.0], half);
        let again = corrections(
            &fit_metric(kin, &observe(&printed, &[0.0, 90.0, 45.0, -45.0])).expect("fit"),
            ShearTo::Motors,
            half,
        );
        let (f1, f2) = (
            fresh.xy_factor.expect("skew").value,
            again.xy_factor.expect("skew").value,
        );
        assert!((f1 - f2).abs() < 1e-9, "{f1} {f2}");
        for i in 0..2 {
            assert!((fresh.stepper_scale[i].value - again.stepper_scale[i].value).abs() < 1e-9);
        }
    }

    #[test]
    fn corexy_shear_can_go_to_klipper_skew_instead() {
        let kin = Kinematics::CoreXy;
        let phi = 0.3f64.to_radians();
        let m = machine_matrix(kin, [1.004, 1.004], phi);
        let fit = fit_metric(kin, &observe(&m, &[45.0, -45.0, 0.0, 90.0])).expect("fit");
        let c = corrections(&fit, ShearTo::KlipperSkew, 0.0);
        let f = c.xy_factor.expect("skew").value;
        assert!((f - phi.tan()).abs() < 1e-6, "{f}");
        assert!((c.stepper_scale[0].value - 1.004).abs() < 1e-5);
        let after = corrected_matrix(
            kin,
            &m,
            [c.stepper_scale[0].value, c.stepper_scale[1].value],
            f,
        );
        let g = after.transpose() * after;
        assert!(g[(0, 1)].abs() < 1e-9);
    }

    #[test]
    fn two_motor_directions_fit_without_shear() {
        let kin = Kinematics::Cartesian;
        let m = machine_matrix(kin, [1.01, 0.99], 0.0);
        let fit = fit_metric(kin, &observe(&m, &[0.0, 90.0])).expect("fit");
        assert!(!fit.full);
        let c = corrections(&fit, ShearTo::Motors, 0.0);
        assert!(c.xy_factor.is_none() && c.shear_factor.is_none() && c.anisotropy.is_none());
        assert!((c.stepper_scale[0].value - 1.01).abs() < 1e-12);
        assert!(fit_metric(kin, &observe(&m, &[0.0])).is_err());
    }

    #[test]
    fn a_group_that_disagrees_with_the_others_is_flagged() {
        let kin = Kinematics::CoreXy;
        let m = machine_matrix(kin, [1.0, 1.0], 0.0);
        let mut obs = observe(&m, &[45.0, -45.0, 0.0, 90.0, 30.0]);
        obs[2].scale += 5e-4; // 13σ off
        let fit = fit_metric(kin, &obs).expect("fit");
        assert!(
            fit.residuals.iter().any(|r| r.flagged),
            "{:?}",
            fit.residuals
        );
        let clean = fit_metric(kin, &observe(&m, &[45.0, -45.0, 0.0, 90.0, 30.0])).expect("fit");
        assert!(clean.residuals.iter().all(|r| !r.flagged));
    }
}
