//! PURE: pixels → machine mm for the nozzle camera (issue 27), from nozzle centres seen at
//! known moves, and the seed's backlash cycle from two centres.
//!
//! Each axis is moved to a few known positions (for example −0.5, 0, +0.5 mm about the
//! measurement point), every one approached moving the same way so the play stays taken up on
//! the same side and backlash does not enter the scale. A straight line through the centres
//! against the commanded positions gives that axis's direction in the image: its length is the
//! scale (px/mm), its angle the camera's rotation against the axis. The two axes' directions
//! make the 2×2 map image ← machine; its inverse takes a displacement in the image back to mm
//! with the rotation (and a mirror, the usual case for a camera looking up) taken out.
//!
//! Each axis gets its own line and offset: the other axis's play may sit on either side
//! between the two sets, which would shift a shared offset but not a slope.

use serde::{Deserialize, Serialize};

use super::backlash::{BacklashParams, Cycle};
use super::Error;

/// A nozzle centre seen at a commanded axis position.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub(crate) struct Sighting {
    /// Commanded position of the axis being calibrated, mm.
    pub commanded_mm: f64,
    /// The detected centre, px.
    pub centre_px: [f64; 2],
    /// The detection's uncertainty, 1 sd per image axis, px.
    pub uncertainty_px: f64,
}

/// One axis's direction in the image.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct AxisScale {
    /// Image displacement per mm of this axis, px/mm (x, y).
    pub direction_px_per_mm: [f64; 2],
    /// Length of that vector, px/mm.
    pub scale_px_per_mm: f64,
    /// Its uncertainty, 1 sd, px/mm.
    pub scale_sd_px_per_mm: f64,
    /// Angle of the axis in the image from the image's x axis (y down), degrees.
    pub angle_deg: f64,
    /// Its uncertainty, 1 sd, degrees.
    pub angle_sd_deg: f64,
    /// Rms distance of the centres from the fitted line, px (0 with two positions).
    pub residual_rms_px: f64,
}

/// Fits one axis's line through its sightings, weighted by their uncertainties.
///
/// # Errors
/// Fewer than two distinct positions, a non-finite number, or a line too short to measure.
pub(crate) fn fit_axis(axis: &str, s: &[Sighting]) -> Result<AxisScale, Error> {
    let bad = |m: String| Err(Error::CameraScale(format!("axis {axis}: {m}")));
    if s.iter().any(|v| {
        !(v.commanded_mm.is_finite()
            && v.centre_px.iter().all(|c| c.is_finite())
            && v.uncertainty_px.is_finite()
            && v.uncertainty_px > 0.0)
    }) {
        return bad("every sighting needs finite numbers and an uncertainty > 0".into());
    }
    let w: Vec<f64> = s.iter().map(|v| 1.0 / v.uncertainty_px.powi(2)).collect();
    let sw: f64 = w.iter().sum();
    let tm = s
        .iter()
        .zip(&w)
        .map(|(v, w)| w * v.commanded_mm)
        .sum::<f64>()
        / sw;
    let stt: f64 = s
        .iter()
        .zip(&w)
        .map(|(v, w)| w * (v.commanded_mm - tm).powi(2))
        .sum();
    let spread = s
        .iter()
        .map(|v| v.commanded_mm)
        .fold(f64::NEG_INFINITY, f64::max)
        - s.iter()
            .map(|v| v.commanded_mm)
            .fold(f64::INFINITY, f64::min);
    if s.len() < 2 || spread < 1e-6 || stt <= 0.0 {
        return bad(format!(
            "{} sighting(s) over {spread:.3} mm; expected at least two at different positions \
             (for example −0.5 and +0.5 mm)",
            s.len()
        ));
    }
    let mut a = [0.0; 2];
    let mut c0 = [0.0; 2];
    for k in 0..2 {
        let pm = s
            .iter()
            .zip(&w)
            .map(|(v, w)| w * v.centre_px[k])
            .sum::<f64>()
            / sw;
        a[k] = s
            .iter()
            .zip(&w)
            .map(|(v, w)| w * (v.commanded_mm - tm) * (v.centre_px[k] - pm))
            .sum::<f64>()
            / stt;
        c0[k] = pm - a[k] * tm;
    }
    let (mut chi2, mut rss) = (0.0, 0.0);
    for (v, wi) in s.iter().zip(&w) {
        for k in 0..2 {
            let r = v.centre_px[k] - (c0[k] + a[k] * v.commanded_mm);
            chi2 += wi * r * r;
            rss += r * r;
        }
    }
    let dof = 2 * s.len() - 4;
    // The stated uncertainties, widened when the points scatter more than they claim.
    let inflate = if dof > 0 {
        (chi2 / dof as f64).max(1.0).sqrt()
    } else {
        1.0
    };
    let slope_sd = inflate / stt.sqrt();
    let scale = a[0].hypot(a[1]);
    if scale < 3.0 * slope_sd || scale == 0.0 {
        return bad(format!(
            "the nozzle moved {:.2} px over {spread:.3} mm, within the detection's noise; \
             expected a visible move (is the camera looking at this nozzle, and the axis moving?)",
            scale * spread
        ));
    }
    Ok(AxisScale {
        direction_px_per_mm: a,
        scale_px_per_mm: scale,
        scale_sd_px_per_mm: slope_sd,
        angle_deg: a[1].atan2(a[0]).to_degrees(),
        angle_sd_deg: (slope_sd / scale).to_degrees(),
        residual_rms_px: if s.len() > 2 {
            (rss / (2 * s.len()) as f64).sqrt()
        } else {
            0.0
        },
    })
}

/// The camera against two machine axes.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct CameraScale {
    pub x: AxisScale,
    pub y: AxisScale,
    /// The camera's rotation: the X axis's angle in the image, degrees.
    pub rotation_deg: f64,
    /// The image is mirrored against the machine (a camera looking up at the nozzle).
    pub mirrored: bool,
    /// The angle between the two axes as the camera sees them, degrees (90 for a square
    /// camera and frame).
    pub axes_angle_deg: f64,
}

impl CameraScale {
    /// Combines two axes' fits.
    ///
    /// # Errors
    /// The two directions are (nearly) parallel: the map cannot be inverted.
    pub(crate) fn from_axes(x: AxisScale, y: AxisScale) -> Result<CameraScale, Error> {
        let [ax, ay] = [x.direction_px_per_mm, y.direction_px_per_mm];
        let det = ax[0] * ay[1] - ax[1] * ay[0];
        let sin = det / (x.scale_px_per_mm * y.scale_px_per_mm);
        if sin.abs() < 0.5 {
            return Err(Error::CameraScale(format!(
                "X and Y move the nozzle in nearly the same direction in the image ({:.0}° \
                 apart); expected roughly perpendicular moves",
                sin.asin().to_degrees().abs()
            )));
        }
        let dot = ax[0] * ay[0] + ax[1] * ay[1];
        Ok(CameraScale {
            x,
            y,
            rotation_deg: x.angle_deg,
            mirrored: det < 0.0,
            axes_angle_deg: det.abs().atan2(dot).to_degrees(),
        })
    }

    /// A displacement in the image, px, as a machine displacement (x, y), mm.
    pub fn to_mm(&self, d_px: [f64; 2]) -> [f64; 2] {
        let [ax, ay] = [self.x.direction_px_per_mm, self.y.direction_px_per_mm];
        let det = ax[0] * ay[1] - ax[1] * ay[0];
        [
            (ay[1] * d_px[0] - ay[0] * d_px[1]) / det,
            (-ax[1] * d_px[0] + ax[0] * d_px[1]) / det,
        ]
    }

    /// The detected centre `centre_px` relative to `reference_px`, in machine mm.
    pub(crate) fn position_mm(&self, centre_px: [f64; 2], reference_px: [f64; 2]) -> [f64; 2] {
        self.to_mm([
            centre_px[0] - reference_px[0],
            centre_px[1] - reference_px[1],
        ])
    }
}

/// Which machine axis a backlash cycle is taken on.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Axis {
    X,
    Y,
}

/// The seed's cycle from the camera: the nozzle commanded to `commanded_mm` once approached
/// moving + (centre `plus_px`) and once moving − (`minus_px`). Each reading is the commanded
/// position that would put the nozzle on `reference_px` (the seed's "back in the centre"), so
/// X1 − X2 is the backlash and [`super::backlash::analyse`] takes the cycles as they are.
pub(crate) fn cycle(
    scale: &CameraScale,
    axis: Axis,
    commanded_mm: f64,
    plus_px: [f64; 2],
    minus_px: [f64; 2],
    reference_px: [f64; 2],
) -> Cycle {
    let k = match axis {
        Axis::X => 0,
        Axis::Y => 1,
    };
    let p = scale.position_mm(plus_px, reference_px)[k];
    let m = scale.position_mm(minus_px, reference_px)[k];
    Cycle {
        x1_mm: commanded_mm - p,
        x2_mm: commanded_mm - m,
        fine_mm: None,
    }
}

/// The backlash statistics' settings for camera cycles: the reading resolution becomes the
/// camera's, so the noise floor and outlier limit of [`super::backlash::analyse`] are the
/// detection's (per cycle sd √2·u/scale, u the detection's px sd) instead of a jog step's, and
/// the scale's relative uncertainty (`scale_sd_px_per_mm / scale_px_per_mm`, from
/// [`fit_axis`]) enters the stated ± in proportion to the value.
pub(crate) fn camera_params(
    base: &BacklashParams,
    detection_sd_px: f64,
    scale_px_per_mm: f64,
    scale_sd_px_per_mm: f64,
) -> BacklashParams {
    let cycle_sd_mm = std::f64::consts::SQRT_2 * detection_sd_px / scale_px_per_mm;
    BacklashParams {
        // analyse's floor is jog_resolution/√6: make it the cycle sd.
        jog_resolution_mm: 6f64.sqrt() * cycle_sd_mm,
        prior_cycle_sd_mm: base
            .prior_cycle_sd_mm
            .min(3.0 * cycle_sd_mm)
            .max(cycle_sd_mm),
        scale_rel_sd: (scale_sd_px_per_mm / scale_px_per_mm).abs(),
        // The detection's sub-pixel error at the same two positions repeats in every cycle
        // (the bench's ±2u covered 87.5 % on a play-free axis without it).
        repeat_sd_mm: cycle_sd_mm,
        ..base.clone()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A camera at `s` px/mm, rotated `th`, mirrored or not; sightings at ±0.5 mm with noise.
    fn sightings(a: [f64; 2], noise: f64, rng: &mut fastrand::Rng) -> Vec<Sighting> {
        let g = |rng: &mut fastrand::Rng| {
            let u = 1.0 - rng.f64();
            (-2.0 * u.ln()).sqrt() * (std::f64::consts::TAU * rng.f64()).cos()
        };
        [-0.5, 0.0, 0.5]
            .iter()
            .map(|t| Sighting {
                commanded_mm: *t,
                centre_px: [
                    320.0 + a[0] * t + noise * g(rng),
                    240.0 + a[1] * t + noise * g(rng),
                ],
                uncertainty_px: noise,
            })
            .collect()
    }

    #[test]
    fn scale_and_rotation_are_recovered_within_their_stated_uncertainty() {
        let mut rng = fastrand::Rng::with_seed(9);
        let (mut in_scale, mut in_angle, n) = (0, 0, 200);
        for _ in 0..n {
            let s = 60.0 + 40.0 * rng.f64();
            let th = std::f64::consts::TAU * rng.f64();
            let m = if rng.bool() { -1.0 } else { 1.0 };
            let ax = [s * th.cos(), s * th.sin()];
            let ay = [-m * s * th.sin(), m * s * th.cos()];
            let x = fit_axis("x", &sightings(ax, 0.1, &mut rng)).unwrap();
            let y = fit_axis("y", &sightings(ay, 0.1, &mut rng)).unwrap();
            let cam = CameraScale::from_axes(x, y).unwrap();
            assert_eq!(cam.mirrored, m < 0.0);
            assert!((cam.axes_angle_deg - 90.0).abs() < 1.0, "{cam:?}");
            if (x.scale_px_per_mm - s).abs() <= 2.0 * x.scale_sd_px_per_mm {
                in_scale += 1;
            }
            let mut da = x.angle_deg - th.to_degrees();
            da = (da + 540.0).rem_euclid(360.0) - 180.0;
            if da.abs() <= 2.0 * x.angle_sd_deg {
                in_angle += 1;
            }
            // The map back to mm takes rotation and mirror out: a pure X move reads as X.
            let d = cam.to_mm([ax[0] * 0.1, ax[1] * 0.1]);
            assert!((d[0] - 0.1).abs() < 0.002 && d[1].abs() < 0.002, "{d:?}");
        }
        // ±2 sd covers about 95 %.
        assert!(
            in_scale >= 180 && in_angle >= 180,
            "{in_scale} {in_angle} of {n}"
        );
    }

    #[test]
    fn a_camera_cycle_is_the_seeds_backlash() {
        let ax = [0.0, 80.0];
        let ay = [-80.0, 0.0];
        let mut rng = fastrand::Rng::with_seed(1);
        let cam = CameraScale::from_axes(
            fit_axis("x", &sightings(ax, 0.01, &mut rng)).unwrap(),
            fit_axis("y", &sightings(ay, 0.01, &mut rng)).unwrap(),
        )
        .unwrap();
        // Approached moving +, the nozzle lags 0.03 mm short; moving −, 0.03 mm past.
        let r = [320.0, 240.0];
        let plus = [r[0], r[1] - 0.03 * 80.0];
        let minus = [r[0], r[1] + 0.03 * 80.0];
        let c = cycle(&cam, Axis::X, 100.0, plus, minus, r);
        assert!((c.backlash_mm() - 0.06).abs() < 1e-3, "{c:?}");
        let p = camera_params(&BacklashParams::default(), 0.1, 80.0, 0.08);
        let res = crate::calib::backlash::analyse("x", &[c, c, c], None, &p).unwrap();
        assert!((res.backlash_mm - 0.06).abs() < 1e-3);
        // The detection's error at the same two positions repeats in every cycle: identical
        // cycles still carry one cycle's detection sd (√2·0.1/80 mm), not a third of it.
        assert!(
            res.uncertainty_mm >= std::f64::consts::SQRT_2 * 0.1 / 80.0,
            "{res:?}"
        );
    }

    #[test]
    fn sightings_that_give_no_scale_are_refused() {
        let one = Sighting {
            commanded_mm: 0.0,
            centre_px: [1.0, 1.0],
            uncertainty_px: 0.1,
        };
        assert!(fit_axis("x", &[one, one]).is_err());
        let still = Sighting {
            commanded_mm: 0.5,
            ..one
        };
        let e = fit_axis("x", &[one, still]).unwrap_err().to_string();
        assert!(e.contains("within the detection's noise"), "{e}");
        let nan = Sighting {
            commanded_mm: f64::NAN,
            ..one
        };
        assert!(fit_axis("x", &[one, nan]).is_err());
    }
}
