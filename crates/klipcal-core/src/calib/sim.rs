//! The simulated machine and person of the metrology benchmark (`klipcal-bench metrology`) and
//! of the solver's tests: the pylon layout printed by a random machine (the faces model of
//! [`crate::calib::metric`]), and the caliper readings a person takes of it. Feature `sim` (and
//! this crate's tests) only: never in the printer's build.

use nalgebra::Matrix2;
use rand::rngs::StdRng;
use rand::Rng;

use crate::calib::metric::{face_scale, Kinematics};
use crate::calib::readings::RawReadings;
use crate::calib::solve::{MotionFacts, StepperFacts};
use crate::layout::{Layout, Pair, Pylon, LAYOUT_VERSION};

/// Group ids and directions of a layout: the motor directions first, then (full) the others.
#[must_use]
pub fn layout_groups(kin: Kinematics, full: bool) -> Vec<(&'static str, f64)> {
    let mut g = match kin {
        Kinematics::CoreXy => vec![("A", 45.0), ("B", -45.0)],
        Kinematics::Cartesian => vec![("X", 0.0), ("Y", 90.0)],
    };
    if full {
        g.extend(match kin {
            Kinematics::CoreXy => [("X", 0.0), ("Y", 90.0)],
            Kinematics::Cartesian => [("U", 45.0), ("V", -45.0)],
        });
    }
    g
}

/// A layout of the shape the pylon generator writes (issue 3): three slabs per group, pylon 1's
/// outer face to the far faces of pylons 2 and 3 at `d1_mm` and `d2_mm`. Used by the bench and
/// by tests; the real job's layout comes from `gcode`.
#[must_use]
pub fn simulated_layout(kin: Kinematics, full: bool, d1_mm: f64, d2_mm: f64) -> Layout {
    let thickness = 3.6;
    let mut pylons = Vec::new();
    let mut pairs = Vec::new();
    for (i, (g, deg)) in layout_groups(kin, full).into_iter().enumerate() {
        let t = f64::to_radians(deg);
        let (n, perp) = ([t.cos(), t.sin()], [-t.sin(), t.cos()]);
        let offset = 30.0 * (i as f64 - 1.5);
        let origin = [
            150.0 - n[0] * d2_mm / 2.0 + perp[0] * offset,
            150.0 - n[1] * d2_mm / 2.0 + perp[1] * offset,
        ];
        for (j, along) in [0.0, d1_mm - thickness, d2_mm - thickness]
            .into_iter()
            .enumerate()
        {
            pylons.push(Pylon {
                id: format!("{g}{}", j + 1),
                center: [origin[0] + n[0] * along, origin[1] + n[1] * along],
                normal_deg: deg,
                thickness,
                length: 53.6,
                height: 8.0,
            });
        }
        for (k, d) in [d1_mm, d2_mm].into_iter().enumerate() {
            pairs.push(Pair {
                id: format!("{g}-D{}", k + 1),
                group: g.into(),
                from: format!("{g}1"),
                to: format!("{g}{}", k + 2),
                direction_deg: deg,
                nominal_mm: d,
            });
        }
    }
    Layout {
        version: LAYOUT_VERSION,
        kinematics: match kin {
            Kinematics::CoreXy => "corexy".into(),
            Kinematics::Cartesian => "cartesian".into(),
        },
        pylons,
        pairs,
    }
}

/// Noise and range of the simulated machines (issue 4 §5).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SimParams {
    /// Motor scales drawn uniformly within 1 ± this.
    pub motor_scale_range: f64,
    /// Frame skew drawn uniformly within ± this, degrees.
    pub frame_skew_deg: f64,
    /// Shrinkage range (uniform).
    pub shrink: (f64, f64),
    /// Standard deviation of each pylon's printed width, mm.
    pub width_scatter_mm: f64,
    /// Standard deviation of the common extrusion width error, mm (cancels in differences).
    pub extrusion_mm: f64,
    /// Bed drift: CTE (1/K) and ± band (K, uniform).
    pub bed_cte_per_k: f64,
    /// ± K.
    pub bed_band_k: f64,
    /// Caliper noise, one σ per reading, mm.
    pub caliper_sigma_mm: f64,
    /// Readings per pair.
    pub readings_per_pair: usize,
    /// D1 and D2, mm.
    pub d_mm: (f64, f64),
    /// A person reading the caliper (else ideal Gaussian readings).
    pub human: Option<HumanReader>,
}

/// A model of a person reading a caliper: every reading rounded to the caliper's last digit,
/// a bias of their own (how they hold the jaws, the same on every pair of a print), and now
/// and then a reading squeezed or tilted (jaw pressure).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct HumanReader {
    /// The caliper's last digit, mm.
    pub resolution_mm: f64,
    /// Standard deviation of a person's bias across people, mm.
    pub bias_sigma_mm: f64,
    /// Chance that a reading is squeezed or tilted.
    pub pressure_chance: f64,
    /// Standard deviation of such a reading's extra error, mm.
    pub pressure_sigma_mm: f64,
}

impl Default for HumanReader {
    fn default() -> Self {
        Self {
            resolution_mm: 0.01,
            bias_sigma_mm: 0.01,
            pressure_chance: 0.1,
            pressure_sigma_mm: 0.02,
        }
    }
}

impl Default for SimParams {
    fn default() -> Self {
        Self {
            motor_scale_range: 0.02,
            frame_skew_deg: 0.5,
            shrink: (0.003, 0.01),
            width_scatter_mm: 0.003,
            extrusion_mm: 0.02,
            bed_cte_per_k: 1.2e-5,
            bed_band_k: 2.0,
            caliper_sigma_mm: 0.02 / 3.0,
            readings_per_pair: 5,
            d_mm: (10.0, 150.0),
            human: None,
        }
    }
}

pub fn normal(rng: &mut StdRng) -> f64 {
    // Box–Muller
    let u1: f64 = rng.random::<f64>().max(1e-300);
    let u2: f64 = rng.random();
    (-2.0 * u1.ln()).sqrt() * (std::f64::consts::TAU * u2).cos()
}

pub fn uniform(rng: &mut StdRng, lo: f64, hi: f64) -> f64 {
    lo + (hi - lo) * rng.random::<f64>()
}

/// Readings of one print of `layout` on a machine whose commanded→physical map is `m`
/// (the faces model: perpendicular distance between parallel faces, pylons shrinking about
/// their own centres, the plate drifting by `drift` between print and measurement).
#[must_use]
pub fn print_and_measure(
    layout: &Layout,
    m: &Matrix2<f64>,
    shrink: f64,
    drift: f64,
    p: &SimParams,
    rng: &mut StdRng,
) -> RawReadings {
    // The person measuring this print, with their own bias.
    let bias = p.human.map_or(0.0, |h| h.bias_sigma_mm * normal(rng));
    let extrusion = p.extrusion_mm * normal(rng);
    let widths: std::collections::HashMap<&str, f64> = layout
        .pylons
        .iter()
        .map(|py| (py.id.as_str(), p.width_scatter_mm * normal(rng)))
        .collect();
    let minv_t = m
        .try_inverse()
        .unwrap_or_else(Matrix2::identity)
        .transpose();
    let mut out = RawReadings::new();
    for pair in &layout.pairs {
        let pylon = |id: &str| layout.pylons.iter().find(|py| py.id == id);
        let (Some(a), Some(b)) = (pylon(&pair.from), pylon(&pair.to)) else {
            continue;
        };
        let t = pair.direction_deg.to_radians();
        let nv = minv_t * nalgebra::Vector2::new(t.cos(), t.sin());
        let unit = nv / nv.norm();
        let pa = m * nalgebra::Vector2::new(a.center[0], a.center[1]);
        let pb = m * nalgebra::Vector2::new(b.center[0], b.center[1]);
        let s_face = face_scale(m, pair.direction_deg);
        let half = |py: &Pylon| {
            0.5 * py.thickness * s_face * (1.0 - shrink)
                + 0.5 * (extrusion + widths.get(py.id.as_str()).copied().unwrap_or(0.0))
        };
        let d = (1.0 + drift) * (unit.dot(&(pb - pa)) + half(a) + half(b));
        let values = (0..p.readings_per_pair)
            .map(|_| {
                let v = d + p.caliper_sigma_mm * normal(rng);
                match p.human {
                    None => v,
                    Some(h) => {
                        let squeeze = if rng.random::<f64>() < h.pressure_chance {
                            h.pressure_sigma_mm * normal(rng)
                        } else {
                            0.0
                        };
                        let r = h.resolution_mm;
                        ((v + bias + squeeze) / r).round() * r
                    }
                }
            })
            .collect();
        out.insert(pair.id.clone(), values);
    }
    out
}

/// The paper's printer: rotation_distance 40, 0.9° steppers (400 steps), 64 microsteps.
#[must_use]
pub fn facts(kin: Kinematics) -> MotionFacts {
    let s = StepperFacts {
        rotation_distance_mm: 40.0,
        microsteps: 64,
        full_steps_per_rotation: 400,
        gear_ratio: 1.0,
    };
    MotionFacts {
        kinematics: kin,
        stepper_x: s,
        stepper_y: s,
    }
}
