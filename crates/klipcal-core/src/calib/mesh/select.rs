//! Which model predicts best: prediction errors, leave-one-mesh-out (LOMO) cross-validation of
//! each model kind and of VGB's two-mesh method, and the choice between them.

use super::{check, fit, Capture, Error, Fit, ModelKind};

/// Prediction error statistics, µm.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize)]
pub struct ErrorStats {
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
pub fn judge(fit: &Fit, c: &Capture) -> ErrorStats {
    let e: Vec<f64> = (0..fit.len().min(c.points_mm.len()))
        .map(|i| fit.predict_point(i, c.temps_c[i]) - c.points_mm[i])
        .collect();
    ErrorStats::of(&e)
}

/// Leave-one-mesh-out cross-validation of `kind`: each capture whose temperatures lie inside
/// the others' range is predicted by a model fitted to the others (captures at either end are
/// not predicted: that would be extrapolation). `None` when no capture can be held out.
#[must_use]
pub fn lomo(caps: &[&Capture], kind: ModelKind) -> Option<ErrorStats> {
    let mut errors = Vec::new();
    for (held, f) in held_out(caps, kind) {
        errors
            .extend((0..f.len()).map(|i| f.predict_point(i, held.temps_c[i]) - held.points_mm[i]));
    }
    (!errors.is_empty()).then(|| ErrorStats::of(&errors))
}

/// Each capture inside the others' range, with the model of `kind` fitted to the others
/// (leave-one-mesh-out; a capture at either end is left out, predicting it would extrapolate).
pub(super) fn held_out<'a>(caps: &[&'a Capture], kind: ModelKind) -> Vec<(&'a Capture, Fit)> {
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
pub fn vgb_two_mesh(caps: &[&Capture]) -> Result<Fit, Error> {
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
pub fn vgb_lomo(caps: &[&Capture]) -> Option<ErrorStats> {
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
pub struct Selection {
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
pub fn select(caps: &[&Capture]) -> Result<Selection, Error> {
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

#[cfg(test)]
mod tests {
    use super::super::tests::synth;
    use super::*;

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
}
