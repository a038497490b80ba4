//! `klipcal_mesh_import`: VGB's profiles already in the config, fitted as a capture.

use super::*;

impl Mesh {
    /// `klipcal_mesh_import`: fits the VGB profiles already in the config (`COLDxx.x`,
    /// `HOTxx.x`; `TESTxx.x` are judged, never fitted) and writes klipcal's profiles from
    /// them, every profile's mesh parameters checked against the others.
    pub(super) async fn import(&self) -> anyhow::Result<Imported> {
        self.core.refuse_other_kind(KIND)?;
        self.core.printer_idle().await?;
        let pc = crate::jobs::core::printer_config::fetch(self.core.m(), self.core.files()).await?;
        let all = bed_mesh::profiles(&pc.config).map_err(|e| user(e.to_string()))?;
        let (fitted, tests) = vgb_profiles(&all)?;
        let now = now_unix();
        let captures: Vec<CaptureDoc> = fitted
            .iter()
            .enumerate()
            .map(|(k, (p, t))| {
                let flat = p.flat_mm();
                CaptureDoc {
                    n: k + 1,
                    at_unix: now,
                    temps_c: vec![*t; flat.len()],
                    points_mm: flat,
                    heating: true,
                }
            })
            .collect();
        let names: Vec<&str> = fitted.iter().map(|(p, _)| p.name.as_str()).collect();
        // VGB's TEST profiles are judged against the model fitted to the others.
        let (test_words, judged) = judge_tests(&fitted, &tests, self.settings.tolerance_um)?;
        // An earlier capture's (or import's) profiles are replaced by the write.
        let replaced: Vec<&str> = all
            .iter()
            .map(|p| p.name.as_str())
            .filter(|n| n.starts_with(bed_mesh::KLIPCAL_PREFIX))
            .collect();
        let replace_words = if replaced.is_empty() {
            String::new()
        } else {
            format!(
                "; this replaces the {} klipcal profiles in the config now ({}; printer.cfg is \
                 backed up first)",
                replaced.len(),
                replaced.join(", ")
            )
        };
        let mut notes = vec![format!("imported from the config: {}", names.join(", "))];
        if !test_words.is_empty() {
            notes.push(format!(
                "TEST profiles (judged, not fitted): {}",
                test_words.join("; ")
            ));
        }
        if !replaced.is_empty() {
            notes.push(format!(
                "replaces the klipcal profiles written before: {}",
                replaced.join(", ")
            ));
        }
        let mut doc = Session::new(
            State::Writing,
            format!("fitting {} imported VGB profiles", names.len()),
            MeshBody {
                options: self.settings.clone(),
                params: Some(fitted[0].0.params.clone()),
                captures,
                started_unix: Some(now),
                result: None,
                user_mesh: None,
                imported: true,
                following: false,
            },
        );
        doc.notes = notes;
        let id = self.core.create(KIND, &mut doc, |d, id| d.id = id).await?;
        self.spawn_runner(id);
        let tests_msg = if test_words.is_empty() {
            String::new()
        } else {
            format!("; {}", test_words.join("; "))
        };
        let msg = format!(
            "thermal mesh session {id}: fitting {} VGB profiles ({}){tests_msg}; klipcal_* profiles \
             follow{replace_words}",
            names.len(),
            names.join(", ")
        );
        Ok(Imported {
            session: id,
            state: State::Writing.name(),
            imported: names.iter().map(|n| n.to_string()).collect(),
            tests: judged,
            replaces: replaced.iter().map(|n| n.to_string()).collect(),
            message: msg,
        })
    }
}

/// A VGB profile to fit and its frame temperature, °C.
type Fitted<'a> = (&'a MeshProfile, f64);

/// The VGB profiles among `all`: those to fit (`COLDxx.x`, `HOTxx.x`, with their frame
/// temperatures; at least two) and the `TESTxx.x` ones to judge, every one's mesh parameters
/// the same.
fn vgb_profiles(all: &[MeshProfile]) -> anyhow::Result<(Vec<Fitted<'_>>, Vec<&MeshProfile>)> {
    let mut fitted: Vec<(&MeshProfile, f64)> = Vec::new();
    let mut tests: Vec<&MeshProfile> = Vec::new();
    for p in all {
        match bed_mesh::vgb_kind(&p.name) {
            Some((bed_mesh::VgbKind::Cold | bed_mesh::VgbKind::Hot, t)) => fitted.push((p, t)),
            Some((bed_mesh::VgbKind::Test, _)) => tests.push(p),
            None => {}
        }
    }
    if fitted.len() < 2 {
        return Err(user(format!(
            "found {} VGB profile(s) to fit ([bed_mesh COLDxx.x] / [bed_mesh HOTxx.x] in the \
             SAVE_CONFIG block); a fit needs at least two at different frame temperatures",
            fitted.len()
        )));
    }
    let refs: Vec<&MeshProfile> = fitted
        .iter()
        .map(|(p, _)| *p)
        .chain(tests.iter().copied())
        .collect();
    bed_mesh::check_same_params(&refs).map_err(|e| user(e.to_string()))?;
    Ok((fitted, tests))
}

/// The TEST profiles judged against the model fitted to the others (`tol` the tolerance,
/// µm): a sentence each, and each judged.
fn judge_tests(
    fitted: &[Fitted<'_>],
    tests: &[&MeshProfile],
    tol: f64,
) -> anyhow::Result<(Vec<String>, Vec<TestJudged>)> {
    let caps: Vec<Capture> = fitted
        .iter()
        .map(|(p, t)| {
            let flat = p.flat_mm();
            Capture {
                name: p.name.clone(),
                temps_c: vec![*t; flat.len()],
                points_mm: flat,
                phase: Phase::Heating,
            }
        })
        .collect();
    let refs: Vec<&Capture> = caps.iter().collect();
    let fit = cm::select_directions(&refs, tol)
        .map_err(|e| user(format!("fitting the imported profiles: {e}")))?
        .heating
        .fit;
    let (lo, hi) = fit.range_c;
    let judged: Vec<(String, f64, cm::ErrorStats)> = tests
        .iter()
        .filter_map(|p| {
            let (_, t) = bed_mesh::vgb_kind(&p.name)?;
            let flat = p.flat_mm();
            let c = Capture::uniform(&p.name, t, flat, Phase::Heating);
            Some((p.name.clone(), t, cm::judge(&fit, &c)))
        })
        .collect();
    let test_words: Vec<String> = judged
        .iter()
        .map(|(n, t, e)| {
            let verdict = if e.max_um <= tol {
                format!("within the {tol} µm tolerance")
            } else {
                format!("over the {tol} µm tolerance")
            };
            let outside = if *t < lo || *t > hi {
                format!(" ({t:.1} °C is outside the fitted {lo:.1}–{hi:.1} °C: the model's end is used)")
            } else {
                String::new()
            };
            format!(
                "{n} is {:.1} µm from the model at most (mean {:.1} µm), {verdict}{outside}",
                e.max_um, e.mean_um
            )
        })
        .collect();
    let tests: Vec<TestJudged> = judged
        .iter()
        .map(|(n, t, e)| TestJudged {
            name: n.to_string(),
            temp_c: *t,
            max_um: e.max_um,
            mean_um: e.mean_um,
            within_tolerance: e.max_um <= tol,
        })
        .collect();
    Ok((test_words, tests))
}
