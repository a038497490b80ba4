//! The pure side of a capture: when the next mesh is due, when the capture ends, and the
//! fit of a finished capture into the profiles it writes (`calib::mesh` does the math). No I/O.

use super::*;

/// Whether the next mesh is due: the frame moved `step_c` since the last one, or
/// `interval_s` passed.
#[must_use]
pub fn mesh_due(last_temp_c: f64, now_temp_c: f64, since_last_s: f64, o: &MeshConfig) -> bool {
    (now_temp_c - last_temp_c).abs() >= o.step_c || since_last_s >= o.interval_s
}

/// Why the capture ends now, if it does: enough meshes and a settled frame, the most meshes,
/// or the longest capture.
#[must_use]
pub fn capture_done(
    caps: &[CaptureDoc],
    now_unix: f64,
    started_unix: f64,
    o: &MeshConfig,
) -> Option<String> {
    if caps.len() >= o.max_meshes {
        return Some(format!("{} meshes taken (mesh.max_meshes)", caps.len()));
    }
    if now_unix - started_unix >= o.max_s {
        return Some(format!(
            "the longest capture of {:.0} s passed (mesh.max_s)",
            o.max_s
        ));
    }
    if caps.len() >= o.min_meshes {
        let last = caps.last()?;
        let mean = |c: &CaptureDoc| c.temps_c.iter().sum::<f64>() / c.temps_c.len().max(1) as f64;
        // The mesh one interval back (or the earliest) against the last.
        let back = caps
            .iter()
            .rev()
            .find(|c| last.at_unix - c.at_unix >= o.interval_s * 0.99);
        if let Some(b) = back {
            let moved = (mean(last) - mean(b)).abs();
            if moved < o.settle_c {
                return Some(format!(
                    "the frame settled ({moved:.2} °C over {:.0} min, below mesh.settle_c = {} °C)",
                    (last.at_unix - b.at_unix) / 60.0,
                    o.settle_c
                ));
            }
        }
    }
    None
}

pub(super) fn calib_captures(s: &Session) -> Vec<Capture> {
    s.captures
        .iter()
        .map(|c| Capture {
            name: format!("capture_{}", c.n),
            temps_c: c.temps_c.clone(),
            points_mm: c.points_mm.clone(),
            phase: if c.heating {
                Phase::Heating
            } else {
                Phase::Cooling
            },
        })
        .collect()
}

/// The fit of a session's captures: heating and cooling apart when they differ by more than
/// the session's tolerance, one model otherwise (`calib::mesh::select_directions`).
pub(super) fn fit_session(s: &Session) -> anyhow::Result<cm::DirectionalSelection> {
    let caps = calib_captures(s);
    let refs: Vec<&Capture> = caps.iter().collect();
    cm::select_directions(&refs, s.options.tolerance_um)
        .map_err(|e| user(format!("fitting the meshes: {e}")))
}

/// The profiles of one direction's model over its range.
pub(super) fn plan_direction(
    sel: &cm::Selection,
    tolerance_um: f64,
) -> anyhow::Result<cm::ProfilePlan> {
    let (lo, hi) = sel.fit.range_c;
    cm::plan_profiles(&sel.fit, lo, hi, tolerance_um).map_err(|e| user(e.to_string()))
}

pub(super) fn model_rows(sel: &cm::Selection) -> Vec<(String, f64, f64, f64)> {
    sel.models
        .iter()
        .map(|(k, e)| (k.name().to_string(), e.max_um, e.mean_um, e.rms_um))
        .collect()
}

/// The profiles a finished capture writes and its result (no backup yet): the heating (or
/// only) model's `klipcal_<T>` and, when heating and cooling differ, the cooling model's
/// `klipcal_cool_<T>`, each the fewest within the session's tolerance.
///
/// # Errors
/// No mesh parameters, or a fit that fails.
pub fn plan_session(s: &Session) -> anyhow::Result<(Vec<MeshProfile>, ResultDoc)> {
    let dsel = fit_session(s)?;
    let sel = &dsel.heating;
    let params = s
        .params
        .clone()
        .ok_or_else(|| anyhow!("no mesh parameters"))?;
    let plan = plan_direction(sel, s.options.tolerance_um)?;
    let cooling = match &dsel.cooling {
        Some(c) => Some((c, plan_direction(c, s.options.tolerance_um)?)),
        None => None,
    };
    // VGB's method is judged on the meshes of the heating model.
    let caps = calib_captures(s);
    let refs: Vec<&Capture> = caps
        .iter()
        .filter(|c| dsel.cooling.is_none() || c.phase == Phase::Heating)
        .collect();
    let vgb = cm::vgb_lomo(&refs).map(|e| (e.max_um, e.mean_um, e.rms_um));
    let profile = |phase: Phase, fit: &cm::Fit, t: f64| {
        let flat = fit.predict(t).points_mm;
        MeshProfile {
            name: direction_profile_name(phase, t),
            params: params.clone(),
            points_mm: flat.chunks(params.x_count).map(<[f64]>::to_vec).collect(),
        }
    };
    let mut profiles: Vec<MeshProfile> = plan
        .temps_c
        .iter()
        .map(|&t| profile(Phase::Heating, &sel.fit, t))
        .collect();
    if let Some((c, cplan)) = &cooling {
        profiles.extend(
            cplan
                .temps_c
                .iter()
                .map(|&t| profile(Phase::Cooling, &c.fit, t)),
        );
    }
    let result = ResultDoc {
        model: sel.fit.kind.name().to_string(),
        models: model_rows(sel),
        vgb,
        range_c: sel.fit.range_c,
        profiles_c: plan.temps_c,
        max_quantisation_um: plan.max_quantisation_um,
        backup: None,
        replaced: Vec::new(),
        directions: if s.imported {
            format!(
                "one model from the {} imported profiles (a VGB name gives the frame \
                 temperature, not whether it was rising or falling)",
                s.captures.len()
            )
        } else {
            dsel.directions.describe(s.options.tolerance_um)
        },
        cooling: cooling.map(|(c, cplan)| CoolingDoc {
            model: c.fit.kind.name().to_string(),
            models: model_rows(c),
            range_c: c.fit.range_c,
            profiles_c: cplan.temps_c,
            max_quantisation_um: cplan.max_quantisation_um,
        }),
    };
    Ok((profiles, result))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn opts() -> MeshConfig {
        MeshConfig {
            max_meshes: 10,
            max_s: 7200.0,
            ..MeshConfig::default()
        }
    }

    #[test]
    fn a_mesh_is_due_after_a_step_or_an_interval() {
        let o = opts();
        assert!(!mesh_due(30.0, 30.4, 100.0, &o));
        assert!(mesh_due(30.0, 30.5, 100.0, &o));
        assert!(mesh_due(30.0, 29.4, 100.0, &o));
        assert!(mesh_due(30.0, 30.0, 600.0, &o));
    }

    fn cap(n: usize, at: f64, t: f64) -> CaptureDoc {
        CaptureDoc {
            n,
            at_unix: at,
            temps_c: vec![t; 4],
            points_mm: vec![0.0; 4],
            heating: true,
        }
    }

    #[test]
    fn the_capture_ends_when_the_frame_settles_or_a_limit_is_reached() {
        let o = opts();
        // Still warming: 1 °C per interval.
        let warming = [cap(1, 0.0, 30.0), cap(2, 600.0, 31.0), cap(3, 1200.0, 32.0)];
        assert_eq!(capture_done(&warming, 1200.0, 0.0, &o), None);
        // Settled: 0.1 °C over the last interval.
        let settled = [cap(1, 0.0, 30.0), cap(2, 600.0, 33.0), cap(3, 1200.0, 33.1)];
        assert!(capture_done(&settled, 1200.0, 0.0, &o)
            .unwrap()
            .contains("settled"));
        // Too few meshes to stop on a settled frame.
        assert_eq!(capture_done(&settled[..2], 600.0, 0.0, &o), None);
        assert!(capture_done(&warming, 7300.0, 0.0, &o)
            .unwrap()
            .contains("mesh.max_s"));
        let many: Vec<CaptureDoc> = (0..10)
            .map(|k| cap(k + 1, k as f64 * 60.0, 30.0 + k as f64))
            .collect();
        assert!(capture_done(&many, 600.0, 0.0, &o)
            .unwrap()
            .contains("mesh.max_meshes"));
    }

    #[test]
    fn profile_names_carry_the_temperature_to_a_hundredth() {
        assert_eq!(profile_name(31.256), "klipcal_31.26");
    }

    /// A 3×3 capture session: heating 25 → 40 °C, then cooling 39 → 28.5 °C with the bow
    /// lagging `lag_c` behind (VGB's hysteresis), ±1 µm of noise.
    fn hysteresis_session(lag_c: f64) -> Session {
        let mut state = 11u64;
        let mut noise = move || {
            state = state
                .wrapping_mul(6_364_136_223_846_793_005)
                .wrapping_add(1_442_695_040_888_963_407);
            ((state >> 11) as f64 / (1u64 << 53) as f64 - 0.5) * 0.002
        };
        let gain = [0.3, 0.6, 0.3, 0.6, 1.0, 0.6, 0.3, 0.6, 0.3];
        let mut mesh = |n: usize, t: f64, bow_t: f64, heating: bool| CaptureDoc {
            n,
            at_unix: n as f64 * 600.0,
            temps_c: vec![t; 9],
            points_mm: gain
                .iter()
                .map(|g| -g * 0.006 * (bow_t - 25.0) + noise())
                .collect(),
            heating,
        };
        let mut captures: Vec<CaptureDoc> = (0..11)
            .map(|k| {
                let t = 25.0 + 1.5 * k as f64;
                mesh(k + 1, t, t, true)
            })
            .collect();
        for k in 0..8 {
            let t = 39.0 - 1.5 * k as f64;
            captures.push(mesh(12 + k, t, t + lag_c, false));
        }
        let mut s = Session::new(
            State::Writing,
            "",
            MeshBody {
                options: MeshConfig::default(),
                params: Some(MeshParams {
                    x_count: 3,
                    y_count: 3,
                    mesh_x_pps: 2,
                    mesh_y_pps: 2,
                    algo: "lagrange".into(),
                    tension: 0.2,
                    min_x: 20.0,
                    max_x: 280.0,
                    min_y: 20.0,
                    max_y: 280.0,
                }),
                captures,
                started_unix: Some(0.0),
                result: None,
                user_mesh: None,
                imported: false,
                following: false,
            },
        );
        s.id = 1;
        s
    }

    #[test]
    fn a_capture_whose_cooling_meshes_differ_writes_cooling_profiles_beside_the_heating_ones() {
        let (profiles, result) = plan_session(&hysteresis_session(3.0)).unwrap();
        let cooling = result.cooling.as_ref().expect("cooling kept apart");
        let heat: Vec<&MeshProfile> = profiles
            .iter()
            .filter(|p| !p.name.starts_with("klipcal_cool_"))
            .collect();
        let cool: Vec<&MeshProfile> = profiles
            .iter()
            .filter(|p| p.name.starts_with("klipcal_cool_"))
            .collect();
        assert_eq!(heat.len(), result.profiles_c.len());
        assert_eq!(cool.len(), cooling.profiles_c.len());
        assert!(!cool.is_empty() && heat[0].name.starts_with("klipcal_"));
        assert!(
            result.directions.contains("differ"),
            "{}",
            result.directions
        );
        // The cooling range is the cooling meshes' own.
        assert!((cooling.range_c.0 - 28.5).abs() < 1e-9 && (cooling.range_c.1 - 39.0).abs() < 1e-9);
        // At the same temperature the cooling profile sits ~18 µm (3 °C × 6 µm/°C) lower.
        let at = |name: String| {
            profiles
                .iter()
                .find(|p| p.name == name)
                .map(|p| p.points_mm[1][1])
        };
        let t = cooling.profiles_c[cooling.profiles_c.len() / 2];
        let hc = fit_session(&hysteresis_session(3.0)).unwrap();
        let heating_centre = hc.heating.fit.predict(t).points_mm[4];
        let cooling_centre = at(direction_profile_name(Phase::Cooling, t)).unwrap();
        assert!(
            (heating_centre - cooling_centre - 0.018).abs() < 0.004,
            "{heating_centre} vs {cooling_centre}"
        );
        // Klipper's names: klipcal's to replace, nothing else.
        let text = bed_mesh::replace_klipcal_profiles("[printer]\n", &profiles).unwrap();
        assert_eq!(text.matches("[bed_mesh klipcal_cool_").count(), cool.len());
    }

    #[test]
    fn a_capture_whose_directions_agree_writes_one_profile_set() {
        let (profiles, result) = plan_session(&hysteresis_session(0.0)).unwrap();
        assert!(result.cooling.is_none());
        assert!(result.directions.contains("agree"), "{}", result.directions);
        assert!(profiles.iter().all(|p| !p.name.contains("cool")));
    }
}
