//! PURE: thermal bed-mesh compensation (seed 002, VGB) — per mesh point, z as a function of
//! the frame temperature fitted from every capture; leave-one-mesh-out (LOMO) cross-validation
//! choosing between a linear (VGB) and a higher-order or piecewise model; VGB's two-mesh
//! method on the same data; the fewest profiles within a tolerance (adaptive spacing).
//! No I/O, no clock: captures come in as numbers.
//!
//! This file holds the captures and the per-point model fit; `select` judges the models
//! (LOMO) and picks one, `directions` fits heating and cooling apart when they differ, and
//! `profiles` places the fewest profile temperatures within a tolerance.

mod directions;
mod profiles;
mod select;

pub use directions::{select_directions, DirectionalSelection};
pub use profiles::{nearest, plan_profiles, quantisation_um, vgb_grid, ProfilePlan};
pub use select::{judge, lomo, select, vgb_lomo, vgb_two_mesh, ErrorStats, Selection};

use nalgebra::{DMatrix, DVector};

use super::Error;

/// Whether the frame was warming or cooling while a mesh was taken (VGB's appendix: the
/// bow differs between the two, so they are fitted apart when they differ).
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize)]
#[serde(rename_all = "lowercase")]
pub enum Phase {
    /// Frame temperature rising.
    Heating,
    /// Frame temperature falling.
    Cooling,
}

/// One mesh: z of every point (row-major, same order in every capture) and the frame
/// temperature at the moment each point was probed (VGB has one temperature per mesh: the
/// same value repeated).
#[derive(Debug, Clone, PartialEq)]
pub struct Capture {
    /// Name (`COLD27.3`, `capture_3`).
    pub name: String,
    /// Frame temperature per point, °C.
    pub temps_c: Vec<f64>,
    /// z per point, mm.
    pub points_mm: Vec<f64>,
    /// Heating or cooling.
    pub phase: Phase,
}

impl Capture {
    /// A mesh with one temperature for all points (VGB's profiles).
    #[must_use]
    pub fn uniform(name: &str, temp_c: f64, points_mm: Vec<f64>, phase: Phase) -> Self {
        Self {
            name: name.into(),
            temps_c: vec![temp_c; points_mm.len()],
            points_mm,
            phase,
        }
    }

    /// Mean frame temperature of the mesh, °C.
    #[must_use]
    pub fn mean_temp_c(&self) -> f64 {
        self.temps_c.iter().sum::<f64>() / self.temps_c.len().max(1) as f64
    }

    fn span_c(&self) -> (f64, f64) {
        let lo = self.temps_c.iter().copied().fold(f64::INFINITY, f64::min);
        let hi = self
            .temps_c
            .iter()
            .copied()
            .fold(f64::NEG_INFINITY, f64::max);
        (lo, hi)
    }
}

/// The per-point model family.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize)]
#[serde(rename_all = "lowercase")]
pub enum ModelKind {
    /// z = a + b·T (VGB's assumption).
    Linear,
    /// z = a + b·T + c·T².
    Quadratic,
    /// Linear interpolation between the samples, sorted by temperature.
    Piecewise,
}

impl ModelKind {
    /// All kinds, linear first (the default when nothing predicts better).
    pub const ALL: [ModelKind; 3] = [
        ModelKind::Linear,
        ModelKind::Quadratic,
        ModelKind::Piecewise,
    ];

    /// Lowercase name.
    #[must_use]
    pub fn name(self) -> &'static str {
        match self {
            ModelKind::Linear => "linear",
            ModelKind::Quadratic => "quadratic",
            ModelKind::Piecewise => "piecewise",
        }
    }

    fn min_captures(self) -> usize {
        match self {
            ModelKind::Linear | ModelKind::Piecewise => 2,
            ModelKind::Quadratic => 4,
        }
    }
}

#[derive(Debug, Clone, PartialEq)]
enum PointFit {
    /// Polynomial coefficients in (T − centre_c), lowest order first.
    Poly(Vec<f64>),
    /// (T, z) knots sorted by T.
    Knots(Vec<(f64, f64)>),
}

/// A fitted model: z(T) for every point, valid over `range_c` (clamped outside).
#[derive(Debug, Clone, PartialEq)]
pub struct Fit {
    /// Model family.
    pub kind: ModelKind,
    /// Captured temperature range, °C.
    pub range_c: (f64, f64),
    centre_c: f64,
    points: Vec<PointFit>,
}

/// A predicted mesh; `clamped` says the temperature was outside the captured range and the
/// edge of the range was used instead (never a silent extrapolation).
#[derive(Debug, Clone, PartialEq)]
pub struct Prediction {
    /// z per point, mm.
    pub points_mm: Vec<f64>,
    /// The temperature actually used, °C.
    pub used_temp_c: f64,
    /// True when `used_temp_c` differs from the one asked for.
    pub clamped: bool,
}

impl Fit {
    /// Number of mesh points.
    #[must_use]
    pub fn len(&self) -> usize {
        self.points.len()
    }

    /// True for a fit of no mesh points.
    #[must_use]
    pub fn is_empty(&self) -> bool {
        self.points.is_empty()
    }

    fn eval(&self, i: usize, t: f64) -> f64 {
        match &self.points[i] {
            PointFit::Poly(c) => {
                let x = t - self.centre_c;
                c.iter().rev().fold(0.0, |acc, k| acc * x + k)
            }
            PointFit::Knots(k) => interp(k, t),
        }
    }

    /// z of every point at `temp_c`, clamped to the captured range.
    #[must_use]
    pub fn predict(&self, temp_c: f64) -> Prediction {
        let used = temp_c.clamp(self.range_c.0, self.range_c.1);
        Prediction {
            points_mm: (0..self.len()).map(|i| self.eval(i, used)).collect(),
            used_temp_c: used,
            clamped: used != temp_c,
        }
    }

    /// z of point `i` at that point's own temperature (clamped).
    #[must_use]
    pub fn predict_point(&self, i: usize, temp_c: f64) -> f64 {
        self.eval(i, temp_c.clamp(self.range_c.0, self.range_c.1))
    }
}

/// Largest |a − b|, µm, of two meshes in mm.
#[must_use]
pub fn max_abs_diff_um(a: &[f64], b: &[f64]) -> f64 {
    a.iter()
        .zip(b)
        .map(|(x, y)| (x - y).abs() * 1000.0)
        .fold(0.0, f64::max)
}

fn interp(k: &[(f64, f64)], t: f64) -> f64 {
    if t <= k[0].0 {
        return k[0].1;
    }
    for w in k.windows(2) {
        if t <= w[1].0 {
            let span = w[1].0 - w[0].0;
            if span <= 0.0 {
                return w[1].1;
            }
            return w[0].1 + (w[1].1 - w[0].1) * (t - w[0].0) / span;
        }
    }
    k[k.len() - 1].1
}

fn check(caps: &[&Capture]) -> Result<usize, Error> {
    let Some(first) = caps.first() else {
        return Err(Error::Fit(
            "no meshes; expected at least two captures".into(),
        ));
    };
    let n = first.points_mm.len();
    for c in caps {
        if c.points_mm.len() != n || c.temps_c.len() != n || n == 0 {
            return Err(Error::Fit(format!(
                "mesh {} has {} points and {} temperatures; expected {n} of each like {}",
                c.name,
                c.points_mm.len(),
                c.temps_c.len(),
                first.name
            )));
        }
        if c.points_mm.iter().chain(&c.temps_c).any(|v| !v.is_finite()) {
            return Err(Error::Fit(format!(
                "mesh {} holds a value that is not a finite number",
                c.name
            )));
        }
    }
    Ok(n)
}

/// The least span of frame temperature between the coldest and the hottest mesh a fit takes, °C.
pub const MIN_SPAN_C: f64 = 0.5;

/// Fits `kind` to the captures, per point.
///
/// # Errors
/// Fewer captures than the model needs, meshes of different sizes, or all at one temperature.
pub fn fit(caps: &[&Capture], kind: ModelKind) -> Result<Fit, Error> {
    let n = check(caps)?;
    if caps.len() < kind.min_captures() {
        return Err(Error::Fit(format!(
            "the {} model needs at least {} meshes; {} given",
            kind.name(),
            kind.min_captures(),
            caps.len()
        )));
    }
    let lo = caps
        .iter()
        .map(|c| c.span_c().0)
        .fold(f64::INFINITY, f64::min);
    let hi = caps
        .iter()
        .map(|c| c.span_c().1)
        .fold(f64::NEG_INFINITY, f64::max);
    if hi - lo < MIN_SPAN_C {
        return Err(Error::Fit(format!(
            "the meshes span {lo:.2}..{hi:.2} °C; expected at least {MIN_SPAN_C} °C between the coldest and the hottest"
        )));
    }
    let centre = 0.5 * (lo + hi);
    let mut points = Vec::with_capacity(n);
    for i in 0..n {
        let samples: Vec<(f64, f64)> = caps
            .iter()
            .map(|c| (c.temps_c[i], c.points_mm[i]))
            .collect();
        points.push(match kind {
            ModelKind::Linear => PointFit::Poly(polyfit(&samples, centre, 1)?),
            ModelKind::Quadratic => PointFit::Poly(polyfit(&samples, centre, 2)?),
            ModelKind::Piecewise => {
                let mut k = samples;
                k.sort_by(|a, b| a.0.total_cmp(&b.0));
                PointFit::Knots(k)
            }
        });
    }
    Ok(Fit {
        kind,
        range_c: (lo, hi),
        centre_c: centre,
        points,
    })
}

fn polyfit(samples: &[(f64, f64)], centre: f64, order: usize) -> Result<Vec<f64>, Error> {
    let a = DMatrix::from_fn(samples.len(), order + 1, |r, c| {
        (samples[r].0 - centre).powi(c as i32)
    });
    let b = DVector::from_iterator(samples.len(), samples.iter().map(|s| s.1));
    let x = a
        .svd(true, true)
        .solve(&b, 1e-12)
        .map_err(|e| Error::Fit(format!("least squares failed: {e}")))?;
    Ok(x.iter().copied().collect())
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A 3-point mesh bowing as z = base + a·ΔT + q·ΔT².
    pub(super) fn synth(t: f64, q: f64) -> Capture {
        let d = t - 25.0;
        let pts = vec![0.01 - 0.004 * d - q * d * d, 0.0, -0.02 + 0.002 * d];
        Capture::uniform(&format!("m{t}"), t, pts, Phase::Heating)
    }

    #[test]
    fn two_linear_meshes_give_vgbs_coefficients_and_clamp_outside() {
        let (a, b) = (synth(25.0, 0.0), synth(35.0, 0.0));
        let f = fit(&[&a, &b], ModelKind::Linear).unwrap();
        let p = f.predict(30.0);
        assert!((p.points_mm[0] - (0.01 - 0.02)).abs() < 1e-12);
        let out = f.predict(40.0);
        assert!(out.clamped && out.used_temp_c == 35.0);
        assert!((out.points_mm[0] - b.points_mm[0]).abs() < 1e-12);
    }
    #[test]
    fn mismatched_meshes_are_refused_by_name() {
        let a = synth(25.0, 0.0);
        let mut b = synth(30.0, 0.0);
        b.points_mm.pop();
        let e = fit(&[&a, &b], ModelKind::Linear).unwrap_err().to_string();
        assert!(e.contains("m30") && e.contains("expected 3"), "{e}");
        let e = fit(&[&a, &a], ModelKind::Linear).unwrap_err().to_string();
        assert!(e.contains("0.5 °C"), "{e}");
    }
}
