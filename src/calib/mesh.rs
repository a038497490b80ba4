//! PURE: thermal bed-mesh compensation (seed 002, VGB) — per mesh point, z as a function of
//! the frame temperature fitted from every capture; leave-one-mesh-out (LOMO) cross-validation
//! choosing between a linear (VGB) and a higher-order or piecewise model; VGB's two-mesh
//! method on the same data; the fewest profiles within a tolerance (adaptive spacing).
//! No I/O, no clock: captures come in as numbers.

use nalgebra::{DMatrix, DVector};

use super::Error;

/// Whether the frame was warming or cooling while a mesh was taken (VGB's appendix: the
/// bow differs between the two, so they are fitted apart when they differ).
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize)]
#[serde(rename_all = "lowercase")]
pub(crate) enum Phase {
    /// Frame temperature rising.
    Heating,
    /// Frame temperature falling.
    Cooling,
}

/// One mesh: z of every point (row-major, same order in every capture) and the frame
/// temperature at the moment each point was probed (VGB has one temperature per mesh: the
/// same value repeated).
#[derive(Debug, Clone, PartialEq)]
pub(crate) struct Capture {
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
    pub(crate) fn uniform(name: &str, temp_c: f64, points_mm: Vec<f64>, phase: Phase) -> Self {
        Self {
            name: name.into(),
            temps_c: vec![temp_c; points_mm.len()],
            points_mm,
            phase,
        }
    }

    /// Mean frame temperature of the mesh, °C.
    #[must_use]
    pub(crate) fn mean_temp_c(&self) -> f64 {
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
    pub(crate) const ALL: [ModelKind; 3] = [
        ModelKind::Linear,
        ModelKind::Quadratic,
        ModelKind::Piecewise,
    ];

    /// Lowercase name.
    #[must_use]
    pub(crate) fn name(self) -> &'static str {
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
pub(crate) struct Prediction {
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
    pub(crate) fn len(&self) -> usize {
        self.points.len()
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
    pub(crate) fn predict(&self, temp_c: f64) -> Prediction {
        let used = temp_c.clamp(self.range_c.0, self.range_c.1);
        Prediction {
            points_mm: (0..self.len()).map(|i| self.eval(i, used)).collect(),
            used_temp_c: used,
            clamped: used != temp_c,
        }
    }

    /// z of point `i` at that point's own temperature (clamped).
    #[must_use]
    pub(crate) fn predict_point(&self, i: usize, temp_c: f64) -> f64 {
        self.eval(i, temp_c.clamp(self.range_c.0, self.range_c.1))
    }
}

/// Largest |a − b|, µm, of two meshes in mm.
#[must_use]
pub(crate) fn max_abs_diff_um(a: &[f64], b: &[f64]) -> f64 {
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
pub(crate) const MIN_SPAN_C: f64 = 0.5;

/// Fits `kind` to the captures, per point.
///
/// # Errors
/// Fewer captures than the model needs, meshes of different sizes, or all at one temperature.
pub(crate) fn fit(caps: &[&Capture], kind: ModelKind) -> Result<Fit, Error> {
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

/// Prediction error statistics, µm.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize)]
pub(crate) struct ErrorStats {
    /// Largest absolute error.
    pub max_um: f64,
    /// Mean absolute error.
    pub mean_um: f64,
    /// Root mean square error.
    pub rms_um: f64,
    /// Mean square error, mm² (VGB's figure).
    pub mse_mm2: f64,
    /// Number of predicted points.
    pub n: usize,
}

impl ErrorStats {
    fn of(errors_mm: &[f64]) -> Self {
        let n = errors_mm.len().max(1) as f64;
        let sq = errors_mm.iter().map(|e| e * e).sum::<f64>() / n;
        Self {
            max_um: errors_mm
                .iter()
                .map(|e| e.abs() * 1000.0)
                .fold(0.0, f64::max),
            mean_um: errors_mm.iter().map(|e| e.abs()).sum::<f64>() / n * 1000.0,
            rms_um: sq.sqrt() * 1000.0,
            mse_mm2: sq,
            n: errors_mm.len(),
        }
    }
}

/// Errors of `fit` against a measured mesh (each point at its own temperature).
#[must_use]
pub(crate) fn judge(fit: &Fit, c: &Capture) -> ErrorStats {
    let e: Vec<f64> = (0..fit.len().min(c.points_mm.len()))
        .map(|i| fit.predict_point(i, c.temps_c[i]) - c.points_mm[i])
        .collect();
    ErrorStats::of(&e)
}

/// Leave-one-mesh-out cross-validation of `kind`: each capture whose temperatures lie inside
/// the others' range is predicted by a model fitted to the others (captures at either end are
/// not predicted: that would be extrapolation). `None` when no capture can be held out.
#[must_use]
pub(crate) fn lomo(caps: &[&Capture], kind: ModelKind) -> Option<ErrorStats> {
    let mut errors = Vec::new();
    for (held, f) in held_out(caps, kind) {
        errors
            .extend((0..f.len()).map(|i| f.predict_point(i, held.temps_c[i]) - held.points_mm[i]));
    }
    (!errors.is_empty()).then(|| ErrorStats::of(&errors))
}

/// Each capture inside the others' range, with the model of `kind` fitted to the others
/// (leave-one-mesh-out; a capture at either end is left out, predicting it would extrapolate).
fn held_out<'a>(caps: &[&'a Capture], kind: ModelKind) -> Vec<(&'a Capture, Fit)> {
    let mut out = Vec::new();
    for (k, held) in caps.iter().enumerate() {
        let rest: Vec<&Capture> = caps
            .iter()
            .enumerate()
            .filter(|(j, _)| *j != k)
            .map(|(_, c)| *c)
            .collect();
        let Ok(f) = fit(&rest, kind) else { continue };
        let (lo, hi) = held.span_c();
        if lo < f.range_c.0 || hi > f.range_c.1 {
            continue;
        }
        out.push((*held, f));
    }
    out
}

/// VGB's method: a line per point through the coldest and the hottest mesh, each at its one
/// (mean) temperature.
///
/// # Errors
/// Fewer than two meshes, or meshes of different sizes.
pub(crate) fn vgb_two_mesh(caps: &[&Capture]) -> Result<Fit, Error> {
    check(caps)?;
    let cold = caps
        .iter()
        .min_by(|a, b| a.mean_temp_c().total_cmp(&b.mean_temp_c()))
        .ok_or_else(|| Error::Fit("no meshes".into()))?;
    let hot = caps
        .iter()
        .max_by(|a, b| a.mean_temp_c().total_cmp(&b.mean_temp_c()))
        .ok_or_else(|| Error::Fit("no meshes".into()))?;
    let two = [
        Capture::uniform(
            &cold.name,
            cold.mean_temp_c(),
            cold.points_mm.clone(),
            cold.phase,
        ),
        Capture::uniform(
            &hot.name,
            hot.mean_temp_c(),
            hot.points_mm.clone(),
            hot.phase,
        ),
    ];
    fit(&[&two[0], &two[1]], ModelKind::Linear)
}

/// VGB's two-mesh method, judged leave-one-out on the captures between its COLD and HOT
/// (its own two meshes excluded), each mesh at its one mean temperature.
#[must_use]
pub(crate) fn vgb_lomo(caps: &[&Capture]) -> Option<ErrorStats> {
    let f = vgb_two_mesh(caps).ok()?;
    let mut errors = Vec::new();
    for c in caps {
        let t = c.mean_temp_c();
        if t <= f.range_c.0 || t >= f.range_c.1 {
            continue;
        }
        errors.extend((0..f.len()).map(|i| f.predict_point(i, t) - c.points_mm[i]));
    }
    (!errors.is_empty()).then(|| ErrorStats::of(&errors))
}

/// The models tried, their LOMO errors, and the one chosen.
#[derive(Debug, Clone, PartialEq)]
pub(crate) struct Selection {
    /// (kind, LOMO errors) for every model that could be cross-validated.
    pub models: Vec<(ModelKind, ErrorStats)>,
    /// The chosen model fitted to all captures.
    pub fit: Fit,
}

/// Fits every model, cross-validates each, and keeps linear unless another predicts better:
/// RMS lower by at least 10 % and 0.5 µm, and max not worse.
///
/// # Errors
/// As [`fit`] for the linear model.
pub(crate) fn select(caps: &[&Capture]) -> Result<Selection, Error> {
    let linear = fit(caps, ModelKind::Linear)?;
    let mut models = Vec::new();
    for kind in ModelKind::ALL {
        if caps.len() >= kind.min_captures() {
            if let Some(s) = lomo(caps, kind) {
                models.push((kind, s));
            }
        }
    }
    let base = models
        .iter()
        .find(|m| m.0 == ModelKind::Linear)
        .map(|m| m.1);
    let mut best = (ModelKind::Linear, base);
    if let Some(b) = base {
        for (k, s) in &models {
            let cur = best.1.unwrap_or(b);
            if *k != ModelKind::Linear
                && s.rms_um < 0.9 * cur.rms_um
                && s.rms_um < cur.rms_um - 0.5
                && s.max_um <= cur.max_um
            {
                best = (*k, Some(*s));
            }
        }
    }
    let fit = if best.0 == ModelKind::Linear {
        linear
    } else {
        fit(caps, best.0)?
    };
    Ok(Selection { models, fit })
}

/// Per point, the mean of (model − measured) over the meshes inside the model's range (the
/// probe noise averages out, a systematic difference stays); the largest |mean|, µm, and how
/// many meshes it took.
fn bias_um(fit: &Fit, caps: &[&Capture]) -> (f64, usize) {
    let inside: Vec<&&Capture> = caps
        .iter()
        .filter(|c| {
            let (lo, hi) = c.span_c();
            lo >= fit.range_c.0 && hi <= fit.range_c.1 && c.points_mm.len() == fit.len()
        })
        .collect();
    if inside.is_empty() {
        return (0.0, 0);
    }
    let n = inside.len() as f64;
    let worst = (0..fit.len())
        .map(|i| {
            let sum: f64 = inside
                .iter()
                .map(|c| fit.predict_point(i, c.temps_c[i]) - c.points_mm[i])
                .sum();
            (sum / n).abs() * 1000.0
        })
        .fold(0.0, f64::max);
    (worst, inside.len())
}

/// [`bias_um`] of leave-one-mesh-out predictions within one direction (`kind` fitted to the
/// others each time): the systematic error a model of this kind makes on its own direction's
/// meshes, µm. `None` when no mesh lies inside the others' range.
fn lomo_bias_um(caps: &[&Capture], kind: ModelKind) -> Option<f64> {
    let n = caps.first()?.points_mm.len();
    let mut sums = vec![0.0; n];
    let mut count = 0usize;
    for (held, f) in held_out(caps, kind) {
        for (i, s) in sums.iter_mut().enumerate() {
            *s += f.predict_point(i, held.temps_c[i]) - held.points_mm[i];
        }
        count += 1;
    }
    (count > 0).then(|| {
        sums.iter()
            .map(|s| (s / count as f64).abs() * 1000.0)
            .fold(0.0, f64::max)
    })
}

/// How the meshes taken while the frame warmed compare with those taken while it cooled
/// (VGB's appendix: the bow differs, a hysteresis).
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize)]
pub(crate) struct DirectionComparison {
    /// Largest systematic error, µm, of one direction's model predicting the other
    /// direction's meshes — held out by construction, only those inside the model's range,
    /// averaged per point over the meshes so probe noise does not count.
    pub cross_um: f64,
    /// The same from each direction's own leave-one-mesh-out predictions (what noise and the
    /// model's own error give when the direction does not matter), µm; `None` when no mesh
    /// lies inside the range of the others of its direction.
    pub own_um: Option<f64>,
    /// Meshes predicted across the directions.
    pub n_cross: usize,
}

impl DirectionComparison {
    /// The directions differ: across, the models miss by more than `tolerance_um`, and by
    /// more than twice what they miss within a direction.
    #[must_use]
    pub(crate) fn differ(&self, tolerance_um: f64) -> bool {
        self.n_cross > 0
            && self.cross_um > tolerance_um
            && !matches!(self.own_um, Some(o) if self.cross_um <= 2.0 * o)
    }
}

/// Compares two directions, each with its chosen model.
#[must_use]
pub(crate) fn compare_directions(
    heating: &Selection,
    heat: &[&Capture],
    cooling: &Selection,
    cool: &[&Capture],
) -> DirectionComparison {
    let (hc, n_hc) = bias_um(&heating.fit, cool);
    let (ch, n_ch) = bias_um(&cooling.fit, heat);
    let own = [
        lomo_bias_um(heat, heating.fit.kind),
        lomo_bias_um(cool, cooling.fit.kind),
    ]
    .into_iter()
    .flatten()
    .reduce(f64::max);
    DirectionComparison {
        cross_um: hc.max(ch),
        own_um: own,
        n_cross: n_hc + n_ch,
    }
}

/// Which meshes the fit used, and why.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize)]
#[serde(rename_all = "snake_case", tag = "kind")]
pub(crate) enum Directions {
    /// One model for every direction. `cooling_fitted` false: the cooling meshes (too few to
    /// fit, or none inside the heating range) were judged, not fitted; true: fewer than two
    /// heating meshes, so all meshes were fitted together.
    Single {
        /// Heating meshes.
        heating: usize,
        /// Cooling meshes.
        cooling: usize,
        /// Whether the cooling meshes are in the model.
        cooling_fitted: bool,
    },
    /// Both directions fitted apart agree within the tolerance: one model from all meshes.
    Agree(DirectionComparison),
    /// They differ by more than the tolerance: a model (and profiles) per direction.
    Apart(DirectionComparison),
}

impl Directions {
    /// In words, for the session's notes and the console.
    #[must_use]
    pub(crate) fn describe(&self, tolerance_um: f64) -> String {
        let floor = |c: &DirectionComparison| {
            c.own_um
                .map(|o| format!(", {o:.1} µm within a direction"))
                .unwrap_or_default()
        };
        match self {
            Directions::Single {
                cooling: 0,
                heating,
                ..
            } => format!("all {heating} meshes taken while the frame warmed"),
            Directions::Single {
                heating,
                cooling,
                cooling_fitted: false,
            } => format!(
                "{cooling} mesh(es) taken while the frame cooled: too few, or none inside the \
                 heating range, to fit apart — judged, not fitted; the model is the {heating} \
                 heating meshes'"
            ),
            Directions::Single {
                heating, cooling, ..
            } => format!(
                "fewer than two meshes taken while the frame warmed: one model from all {} meshes",
                heating + cooling
            ),
            Directions::Agree(c) => format!(
                "heating and cooling agree (largest systematic difference {:.1} µm, tolerance \
                 {tolerance_um} µm{}): one model from all meshes",
                c.cross_um,
                floor(c)
            ),
            Directions::Apart(c) => format!(
                "heating and cooling differ by up to {:.1} µm (tolerance {tolerance_um} µm{}): a \
                 model and profiles for each direction, followed by the frame's trend",
                c.cross_um,
                floor(c)
            ),
        }
    }
}

/// The model per direction of the frame temperature.
#[derive(Debug, Clone, PartialEq)]
pub(crate) struct DirectionalSelection {
    /// The model followed while the frame warms — and in every direction when `cooling` is
    /// `None`.
    pub heating: Selection,
    /// The model followed while the frame cools, when the directions differ.
    pub cooling: Option<Selection>,
    /// Which meshes were fitted, and why.
    pub directions: Directions,
}

/// Fits the heating and the cooling meshes apart when both have enough meshes, and keeps
/// them apart only when they differ by more than `tolerance_um` ([`DirectionComparison`]);
/// otherwise one model (all meshes when the directions agree, the heating ones when the
/// cooling ones cannot be compared).
///
/// # Errors
/// As [`select`] on the meshes used.
pub(crate) fn select_directions(
    caps: &[&Capture],
    tolerance_um: f64,
) -> Result<DirectionalSelection, Error> {
    let heat: Vec<&Capture> = caps
        .iter()
        .copied()
        .filter(|c| c.phase == Phase::Heating)
        .collect();
    let cool: Vec<&Capture> = caps
        .iter()
        .copied()
        .filter(|c| c.phase == Phase::Cooling)
        .collect();
    let single = |cooling_fitted: bool| Directions::Single {
        heating: heat.len(),
        cooling: cool.len(),
        cooling_fitted,
    };
    let h = if heat.len() >= 2 {
        select(&heat).ok()
    } else {
        None
    };
    let Some(h) = h else {
        return Ok(DirectionalSelection {
            heating: select(caps)?,
            cooling: None,
            directions: single(!cool.is_empty()),
        });
    };
    let c = if cool.len() >= 2 {
        select(&cool).ok()
    } else {
        None
    };
    let Some(c) = c else {
        return Ok(DirectionalSelection {
            heating: h,
            cooling: None,
            directions: single(false),
        });
    };
    let cmp = compare_directions(&h, &heat, &c, &cool);
    if cmp.n_cross == 0 {
        return Ok(DirectionalSelection {
            heating: h,
            cooling: None,
            directions: single(false),
        });
    }
    if cmp.differ(tolerance_um) {
        return Ok(DirectionalSelection {
            heating: h,
            cooling: Some(c),
            directions: Directions::Apart(cmp),
        });
    }
    Ok(DirectionalSelection {
        heating: select(caps)?,
        cooling: None,
        directions: Directions::Agree(cmp),
    })
}

/// A profile set: temperatures and the worst error of using the nearest profile.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub(crate) struct ProfilePlan {
    /// Profile temperatures, °C, ascending.
    pub temps_c: Vec<f64>,
    /// Largest |model(T) − model(nearest profile)| over the range, µm.
    pub max_quantisation_um: f64,
}

const GRID_C: f64 = 0.01;

fn grid(lo: f64, hi: f64) -> Vec<f64> {
    let n = ((hi - lo) / GRID_C).ceil().max(1.0) as usize;
    (0..=n)
        .map(|k| lo + (hi - lo) * k as f64 / n as f64)
        .collect()
}

/// Worst error of using the nearest of `temps_c` anywhere in `[lo, hi]`, µm.
#[must_use]
pub(crate) fn quantisation_um(fit: &Fit, temps_c: &[f64], lo: f64, hi: f64) -> f64 {
    let meshes: Vec<Vec<f64>> = temps_c.iter().map(|&t| fit.predict(t).points_mm).collect();
    grid(lo, hi)
        .into_iter()
        .map(|t| {
            let k = nearest(temps_c, t);
            max_abs_diff_um(&fit.predict(t).points_mm, &meshes[k])
        })
        .fold(0.0, f64::max)
}

/// Index of the temperature nearest `t` (the lower one on a tie).
#[must_use]
pub(crate) fn nearest(temps_c: &[f64], t: f64) -> usize {
    let mut best = 0;
    for (k, &x) in temps_c.iter().enumerate() {
        if (x - t).abs() < (temps_c[best] - t).abs() {
            best = k;
        }
    }
    best
}

/// The fewest profile temperatures over `[lo, hi]` such that the nearest profile is within
/// `tolerance_um` of the model everywhere (greedy: each profile placed as far up as the
/// stretch below it allows, checked on a 0.01 °C grid).
///
/// # Errors
/// A tolerance that is not positive, or an empty range.
pub(crate) fn plan_profiles(
    fit: &Fit,
    lo: f64,
    hi: f64,
    tolerance_um: f64,
) -> Result<ProfilePlan, Error> {
    if tolerance_um.is_nan() || tolerance_um <= 0.0 {
        return Err(Error::Fit(format!(
            "tolerance {tolerance_um} µm; expected a positive number of µm (default 5)"
        )));
    }
    if hi.is_nan() || lo.is_nan() || hi <= lo {
        return Err(Error::Fit(format!(
            "temperature range {lo}..{hi} °C; expected from < to"
        )));
    }
    // ok(a, b, p): every T in [a, b] within tolerance of the profile at p.
    let ok = |a: f64, b: f64, p: f64| {
        let mp = fit.predict(p).points_mm;
        grid(a, b)
            .into_iter()
            .all(|t| max_abs_diff_um(&fit.predict(t).points_mm, &mp) <= tolerance_um)
    };
    // Largest x in [a, hi] with pred(x) true (pred monotone: true then false).
    let search = |a: f64, pred: &dyn Fn(f64) -> bool| {
        let (mut good, mut bad) = (a, hi);
        if pred(hi) {
            return hi;
        }
        while bad - good > GRID_C / 2.0 {
            let m = 0.5 * (good + bad);
            if pred(m) {
                good = m;
            } else {
                bad = m;
            }
        }
        good
    };
    let floor = |t: f64| ((t * 100.0 + 1e-6).floor() / 100.0).max(lo);
    let mut temps = vec![floor(search(lo, &|p| ok(lo, p, p)))];
    loop {
        let last = *temps.last().unwrap_or(&lo);
        if ok(last, hi, last) {
            break;
        }
        // Next profile p: below the midpoint `last` is nearest, above it p is.
        let pred = |p: f64| {
            let mid = 0.5 * (last + p);
            ok(last, mid, last) && ok(mid, p, p)
        };
        let p = floor(search(last, &pred)).max(last + GRID_C);
        temps.push(p.min(hi));
        if temps.len() > 100_000 {
            return Err(Error::Fit("profile plan does not converge".into()));
        }
    }
    let q = quantisation_um(fit, &temps, lo, hi);
    Ok(ProfilePlan {
        temps_c: temps,
        max_quantisation_um: q,
    })
}

/// VGB's fixed grid: one profile per `step_c` from `lo` to `hi` inclusive.
#[must_use]
pub(crate) fn vgb_grid(lo: f64, hi: f64, step_c: f64) -> Vec<f64> {
    let n = ((hi - lo) / step_c + 1e-9).floor() as usize;
    (0..=n).map(|k| lo + k as f64 * step_c).collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A 3-point mesh bowing as z = base + a·ΔT + q·ΔT².
    fn synth(t: f64, q: f64) -> Capture {
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
    fn lomo_prefers_the_quadratic_model_on_a_curved_bow_and_linear_on_a_straight_one() {
        let curved: Vec<Capture> = (0..8)
            .map(|k| synth(25.0 + 2.0 * f64::from(k), 0.0004))
            .collect();
        let refs: Vec<&Capture> = curved.iter().collect();
        let s = select(&refs).unwrap();
        assert_eq!(s.fit.kind, ModelKind::Quadratic);
        let vgb = vgb_lomo(&refs).unwrap();
        let chosen = s.models.iter().find(|m| m.0 == s.fit.kind).unwrap().1;
        assert!(
            chosen.max_um < 0.01 && vgb.max_um > 10.0,
            "{chosen:?} vs {vgb:?}"
        );
        let straight: Vec<Capture> = (0..8)
            .map(|k| synth(25.0 + 2.0 * f64::from(k), 0.0))
            .collect();
        let refs: Vec<&Capture> = straight.iter().collect();
        assert_eq!(select(&refs).unwrap().fit.kind, ModelKind::Linear);
    }

    #[test]
    fn adaptive_profiles_stay_within_tolerance_with_fewer_than_a_fixed_grid() {
        let caps: Vec<Capture> = (0..6)
            .map(|k| synth(25.0 + 3.0 * f64::from(k), 0.0002))
            .collect();
        let refs: Vec<&Capture> = caps.iter().collect();
        let f = fit(&refs, ModelKind::Quadratic).unwrap();
        let plan = plan_profiles(&f, 25.0, 40.0, 5.0).unwrap();
        assert!(plan.max_quantisation_um <= 5.0 + 1e-6, "{plan:?}");
        // Slope ≤ 10 µm/°C: one profile covers ≥ 1 °C, so at most ~16 over 15 °C.
        assert!(
            plan.temps_c.len() <= 16 && plan.temps_c.len() >= 4,
            "{plan:?}"
        );
        assert_eq!(vgb_grid(25.0, 40.0, 0.1).len(), 151);
        assert!(plan_profiles(&f, 25.0, 40.0, 0.0).is_err());
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

    /// A 3×3 bed whose bow (6 µm/°C at the centre, less at the edges, slightly curved) lags
    /// by `lag_c` while the frame cools — the cooling mesh at T is the heating one at
    /// T + lag_c (VGB's appendix) — with ±1 µm of probe noise.
    fn hysteresis_set(lag_c: f64, seed: u64) -> Vec<Capture> {
        let mut state = seed;
        let mut noise = move || {
            state = state
                .wrapping_mul(6_364_136_223_846_793_005)
                .wrapping_add(1_442_695_040_888_963_407);
            ((state >> 11) as f64 / (1u64 << 53) as f64 - 0.5) * 0.002
        };
        let gain = [0.3, 0.6, 0.3, 0.6, 1.0, 0.6, 0.3, 0.6, 0.3];
        let mut mesh = |name: String, t: f64, phase: Phase| {
            let d = t - 25.0;
            let pts = gain
                .iter()
                .enumerate()
                .map(|(i, g)| 0.01 * (i as f64 - 4.0) - g * (0.006 * d + 0.0001 * d * d) + noise())
                .collect();
            Capture::uniform(&name, t, pts, phase)
        };
        let mut caps: Vec<Capture> = (0..11)
            .map(|k| {
                let t = 25.0 + 1.5 * f64::from(k);
                mesh(format!("h{t}"), t, Phase::Heating)
            })
            .collect();
        for k in 0..8 {
            let t = 39.0 - 1.5 * f64::from(k);
            let mut c = mesh(format!("c{t}"), t + lag_c, Phase::Cooling);
            c.temps_c = vec![t; c.points_mm.len()];
            caps.push(c);
        }
        caps
    }

    #[test]
    fn heating_and_cooling_that_differ_get_a_model_each() {
        let caps = hysteresis_set(3.0, 7);
        let refs: Vec<&Capture> = caps.iter().collect();
        let d = select_directions(&refs, 5.0).unwrap();
        let Directions::Apart(c) = d.directions else {
            panic!("not kept apart: {:?}", d.directions)
        };
        // 3 °C of lag at 6 µm/°C: ~18 µm at the centre, far above the noise floor.
        assert!(c.cross_um > 12.0 && c.own_um.unwrap() < 3.0, "{c:?}");
        let cooling = d.cooling.expect("a cooling model");
        let cool30 = caps.iter().find(|c| c.name == "c30").unwrap();
        let heat31 = caps.iter().find(|c| c.name == "h31").unwrap();
        // Each direction's model predicts its own meshes and misses the other's.
        assert!(judge(&cooling.fit, cool30).max_um < 3.0);
        assert!(judge(&d.heating.fit, heat31).max_um < 3.0);
        assert!(judge(&d.heating.fit, cool30).max_um > 12.0);
        assert!(judge(&cooling.fit, heat31).max_um > 12.0);
        assert!(d.directions.describe(5.0).contains("differ by up to"));
    }

    #[test]
    fn heating_and_cooling_within_the_tolerance_are_fitted_together() {
        for (lag, seed) in [(0.0, 1), (0.0, 2), (0.4, 3)] {
            let caps = hysteresis_set(lag, seed);
            let refs: Vec<&Capture> = caps.iter().collect();
            let d = select_directions(&refs, 5.0).unwrap();
            let Directions::Agree(c) = d.directions else {
                panic!("lag {lag}: {:?}", d.directions)
            };
            assert!(c.cross_um < 5.0, "lag {lag}: {c:?}");
            assert!(d.cooling.is_none());
            // One model for both: it predicts the cooling meshes too.
            let cool30 = caps.iter().find(|c| c.name == "c30").unwrap();
            assert!(judge(&d.heating.fit, cool30).max_um < 5.0, "lag {lag}");
        }
    }

    #[test]
    fn too_few_cooling_meshes_are_judged_and_not_fitted() {
        let caps = hysteresis_set(3.0, 5);
        // All the heating meshes and one cooling mesh.
        let refs: Vec<&Capture> = caps.iter().take(12).collect();
        let d = select_directions(&refs, 5.0).unwrap();
        assert_eq!(
            d.directions,
            Directions::Single {
                heating: 11,
                cooling: 1,
                cooling_fitted: false
            }
        );
        assert!(d.cooling.is_none());
        assert!(judge(&d.heating.fit, refs[11]).max_um > 12.0);
        let heat_only: Vec<&Capture> = caps.iter().take(11).collect();
        let d = select_directions(&heat_only, 5.0).unwrap();
        assert!(d.directions.describe(5.0).contains("all 11 meshes"));
        // Only cooling meshes: one model from them.
        let cool_only: Vec<&Capture> = caps.iter().skip(11).collect();
        let d = select_directions(&cool_only, 5.0).unwrap();
        assert!(matches!(
            d.directions,
            Directions::Single {
                cooling_fitted: true,
                ..
            }
        ));
        assert!(select_directions(&[], 5.0).is_err());
    }
}
