//! PURE: XY skew — Klipper's skew_correction arithmetic (klippy/extras/skew_correction.py:
//! `calc_skew_factor`, the `x' = x − y·xy` transform), the SET_SKEW lengths that give a wanted
//! factor and Prusa's skew classes (seed 001). The skew itself is fitted by `calib::solve`;
//! Klipper's `calc_skew_factor` and its classic AC/BD/AD method are kept for the tests, as the
//! oracle the SET_SKEW lengths are checked against. No I/O.

use serde::Serialize;

#[cfg(test)]
use super::Error;

/// Klipper's `calc_skew_factor(ac, bd, ad)`, line for line: the other side of the
/// parallelogram from the diagonals, the angle between the sides, and tan(π/2 − angle).
/// Returns `None` when the lengths do not form a parallelogram (Klipper would raise).
#[cfg(test)]
#[must_use]
pub fn calc_skew_factor(ac: f64, bd: f64, ad: f64) -> Option<f64> {
    let side = (2.0 * ac * ac + 2.0 * bd * bd - 4.0 * ad * ad).sqrt() / 2.0;
    let cos = (ac * ac - side * side - ad * ad) / (2.0 * side * ad);
    let f = (std::f64::consts::FRAC_PI_2 - cos.acos()).tan();
    f.is_finite().then_some(f)
}

/// The `SET_SKEW XY=AC,BD,AD` lengths (mm) of a rhombus with sides `side_mm` whose
/// [`calc_skew_factor`] is `xy_factor`: AC = s√(2 + 2 sin ψ), BD = s√(2 − 2 sin ψ), AD = s,
/// ψ = atan(xy_factor).
#[must_use]
pub fn set_skew_lengths(xy_factor: f64, side_mm: f64) -> [f64; 3] {
    let sin = xy_factor.atan().sin();
    [
        side_mm * (2.0 + 2.0 * sin).sqrt(),
        side_mm * (2.0 - 2.0 * sin).sqrt(),
        side_mm,
    ]
}

/// The `SET_SKEW XY=…` command for a factor (lengths of a 100 mm rhombus, built by
/// `klipper::gcode_cmd` with up to 6 decimals, so Klipper's formula gives back the factor within
/// 1e-7); `None` for a non-finite factor.
#[must_use]
pub fn set_skew_command(xy_factor: f64) -> Option<String> {
    let [ac, bd, ad] = set_skew_lengths(xy_factor, 100.0);
    crate::klipper::gcode_cmd::set_skew_xy(ac, bd, ad).ok()
}

/// Klipper's toolhead (kinematic) XY for a commanded XY with skew factor `xy_factor` in the XY
/// plane and none in XZ/YZ (`calc_skew`: x' = x − y·xy, y' = y). This is what
/// `toolhead.get_position()` reports after `G1 X.. Y..` once `SET_SKEW` is active.
#[must_use]
pub fn klipper_toolhead_xy(commanded: [f64; 2], xy_factor: f64) -> [f64; 2] {
    [commanded[0] - commanded[1] * xy_factor, commanded[1]]
}

/// The XY skew factor Klipper applies now, from what its status reports, without
/// GET_CURRENT_SKEW (whose answer lands on the user's console; `[skew_correction]` has no
/// status of its own). `gcode` is `gcode_move.position` (before the skew transform), `toolhead`
/// is `toolhead.position` (after it): Klipper's `calc_skew` gives x' = x − y·xy − z·(xz − xy·yz)
/// and y' = y − z·yz, so at Z = 0 (within 1 µm) the factor is (x − x')/y, and a toolhead
/// exactly where the G-code put it at any Z means no skew (a non-zero XY factor cancelled to
/// the last bit by an XZ one is not a real printer). `None` where the positions cannot tell
/// (|Y| under 1 mm: unhomed or at the origin; Z above 0 with a skew active).
#[must_use]
pub fn xy_factor_from_positions(gcode: [f64; 3], toolhead: [f64; 3]) -> Option<f64> {
    let [x, y, z] = gcode;
    let [xt, yt, _] = toolhead;
    if !(x.is_finite() && y.is_finite() && z.is_finite() && xt.is_finite() && yt.is_finite()) {
        return None;
    }
    if y.abs() < 1.0 {
        return None;
    }
    if x == xt && y == yt {
        return Some(0.0);
    }
    if z.abs() > 1e-3 {
        return None;
    }
    Some((x - xt) / y)
}

/// Klipper's classic method: AC, BD, AD measured on a printed square → its skew factor.
///
/// # Errors
/// Non-positive lengths or lengths that do not form a parallelogram.
#[cfg(test)]
pub fn classic_skew_factor(ac_mm: f64, bd_mm: f64, ad_mm: f64) -> Result<f64, Error> {
    if !(ac_mm > 0.0 && bd_mm > 0.0 && ad_mm > 0.0) {
        return Err(Error::Fit(format!(
            "AC={ac_mm}, BD={bd_mm}, AD={ad_mm}: expected three positive lengths in mm"
        )));
    }
    calc_skew_factor(ac_mm, bd_mm, ad_mm).ok_or_else(|| {
        Error::Fit(format!(
            "AC={ac_mm}, BD={bd_mm}, AD={ad_mm} do not form a parallelogram; expected the two diagonals and one side of the printed square"
        ))
    })
}

/// Prusa firmware's skew classes (seed 001; its thresholds 0.12° and 0.25°).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, serde::Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum SkewClass {
    /// |skew| ≤ 0.12°.
    Perfect,
    /// 0.12° < |skew| ≤ 0.25°.
    Mild,
    /// |skew| > 0.25°.
    Extreme,
}

/// Classifies a skew angle with Prusa's thresholds.
#[must_use]
pub fn classify_skew(angle_deg: f64) -> SkewClass {
    match angle_deg.abs() {
        a if a > 0.25 => SkewClass::Extreme,
        a if a > 0.12 => SkewClass::Mild,
        _ => SkewClass::Perfect,
    }
}

#[cfg(test)]
mod tests {
    #[test]
    fn the_xy_factor_is_read_from_the_positions_where_they_tell_it() {
        use super::xy_factor_from_positions as f;
        let xy = 0.004_321;
        let at = |x: f64, y: f64, z: f64| f([x, y, z], [x - y * xy, y, z]);
        assert!((at(100.0, 120.0, 0.0).unwrap() - xy).abs() < 1e-12);
        assert!((at(10.0, -50.0, 0.0005).unwrap() - xy).abs() < 1e-12);
        // No skew: the toolhead where the G-code put it, at any height.
        assert_eq!(f([100.0, 120.0, 7.0], [100.0, 120.0, 7.3]), Some(0.0));
        // Cannot tell: Y at the origin (unhomed), Z above the bed with a skew active.
        assert_eq!(f([0.0, 0.0, 0.0], [0.0, 0.0, 0.0]), None);
        assert_eq!(at(100.0, 0.5, 0.0), None);
        assert_eq!(at(100.0, 120.0, 5.0), None);
        assert_eq!(f([f64::NAN, 120.0, 0.0], [100.0, 120.0, 0.0]), None);
    }

    use super::*;

    /// Physical XY of a commanded point on a machine whose frame shears x by `f`·y.
    fn sheared(c: [f64; 2], f: f64) -> [f64; 2] {
        [c[0] + f * c[1], c[1]]
    }

    #[test]
    fn set_skew_lengths_give_the_wanted_factor_through_klippers_formula() {
        for f in [-0.02, -0.00873, 0.0, 0.001, 0.00873, 0.03] {
            let [ac, bd, ad] = set_skew_lengths(f, 100.0);
            let back = calc_skew_factor(ac, bd, ad).expect("valid parallelogram");
            assert!((back - f).abs() < 1e-12, "{f} → {back}");
        }
    }

    #[test]
    fn the_printed_command_round_trips_within_a_tenth_of_a_micro_radian() {
        let f = 0.0061234;
        let cmd = set_skew_command(f).expect("finite factor");
        let nums: Vec<f64> = cmd
            .trim_start_matches("SET_SKEW XY=")
            .split(',')
            .map(|s| s.parse().expect("number"))
            .collect();
        let back = calc_skew_factor(nums[0], nums[1], nums[2]).expect("valid");
        assert!((back - f).abs() < 1e-7, "{cmd} → {back}");
    }

    #[test]
    fn a_square_printed_on_a_sheared_machine_measures_to_its_shear() {
        // Klipper's docs: A lower left, B upper left, C upper right, D lower right.
        let f = 0.0087; // ≈ 0.5°
        let (a, b, c, d) = (
            sheared([0.0, 0.0], f),
            sheared([0.0, 100.0], f),
            sheared([100.0, 100.0], f),
            sheared([100.0, 0.0], f),
        );
        let dist =
            |p: [f64; 2], q: [f64; 2]| ((p[0] - q[0]).powi(2) + (p[1] - q[1]).powi(2)).sqrt();
        let got = classic_skew_factor(dist(a, c), dist(b, d), dist(a, d)).expect("valid");
        assert!((got - f).abs() < 1e-12, "{got}");
        // …and Klipper's transform with that factor cancels the shear.
        let cmd = [100.0, 100.0];
        let phys = sheared(klipper_toolhead_xy(cmd, got), f);
        assert!((phys[0] - cmd[0]).abs() < 1e-9 && (phys[1] - cmd[1]).abs() < 1e-12);
    }

    #[test]
    fn a_positive_factor_moves_the_toolhead_to_smaller_x_for_positive_y() {
        let p = klipper_toolhead_xy([100.0, 100.0], 0.01);
        assert!((p[0] - 99.0).abs() < 1e-12 && p[1] == 100.0);
    }

    #[test]
    fn impossible_lengths_are_an_error() {
        assert!(classic_skew_factor(10.0, 10.0, 100.0).is_err());
        assert!(classic_skew_factor(0.0, 10.0, 10.0).is_err());
    }

    #[test]
    fn prusa_thresholds_classify_skew() {
        assert_eq!(classify_skew(0.1), SkewClass::Perfect);
        assert_eq!(classify_skew(-0.2), SkewClass::Mild);
        assert_eq!(classify_skew(0.3), SkewClass::Extreme);
    }
}
