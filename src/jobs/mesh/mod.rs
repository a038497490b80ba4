//! Thermal bed-mesh compensation (seed 002, VGB): capture → fit → profiles, then follow and
//! check. Capture: preflight → heating → soaking → capturing (a mesh each time the frame
//! moved by `mesh.step_c` or `mesh.interval_s` passed, each probe point stamped with the frame
//! temperature of the moment it was probed, every mesh stored the moment it completes) →
//! writing (`[bed_mesh klipcal_<T>]` profiles into the SAVE_CONFIG block: backup, restart,
//! verify, roll back) → done. Follow: loads the profile for the frame temperature only when
//! the model says it matters (`calib::mesh_follow`). Check: seed 001's 0.5 mm reference rule
//! before a print.

use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use anyhow::{anyhow, Context};
use futures_util::future::BoxFuture;
use futures_util::FutureExt;
use serde::{Deserialize, Serialize};
use serde_json::{json, Value};
use tokio_util::sync::CancellationToken;
use tracing::{info, warn};

use super::core::{Calibration, Hold};
use super::printer_config::FileWrite;
use super::session::{now_unix, Core, Doc};
use super::soak::{BedSoak, SoakUpdate};
use super::table::{arg, parse_call, ArgKind, MacroBody, Op, OpSpec};
use super::user;
use crate::calib::mesh::{self as cm, Capture, Phase};
use crate::calib::mesh_follow::{Branch, Decision, Follower};
use crate::calib::soak::SoakParams;
use crate::config::MeshConfig;
use crate::klipper::bed_mesh::{self, MeshParams, MeshProfile};
use crate::store::SessionRow;

/// The thermal mesh's operations, each declared once (see [`crate::jobs::table`]).
pub static OPS: &[Op<MeshCall>] = &[
    Op {
        spec: OpSpec::remote(
            "klipcal_mesh_capture",
            "KLIPCAL_MESH_CAPTURE",
            "mesh/capture",
            "thermal bed mesh: heat the bed, then take meshes as the frame warms and write klipcal_<T> profiles (BED=0 for an unheated bed)",
            &[crate::jobs::table::bed_arg(
                "bed temperature, °C (0: unheated; default mesh.bed_temp_c)",
            )],
        ),
        parse: |a| Ok(MeshCall::Capture { bed_c: a.num("bed")? }),
    },
    Op {
        spec: OpSpec::remote(
            "klipcal_mesh_import",
            "KLIPCAL_MESH_IMPORT",
            "mesh/import",
            "fit the VGB profiles already in the config (COLDxx.x, HOTxx.x, TESTxx.x are judged) and write klipcal_<T> profiles from them",
            &[],
        ),
        parse: |_| Ok(MeshCall::Import),
    },
    Op {
        spec: OpSpec::remote(
            "klipcal_mesh_follow",
            "KLIPCAL_MESH_FOLLOW",
            "mesh/follow",
            "load the thermal mesh profile for the frame temperature as it changes (ENABLE=1) or stop (ENABLE=0)",
            &[arg(
                "enable",
                ArgKind::Choice(&["1", "0"]),
                "1",
                "1 (follow) or 0 (stop)",
                "1",
                "1: follow the frame temperature, 0: stop",
            )],
        ),
        parse: |a| {
            Ok(MeshCall::Follow {
                enable: a.choice("enable")? != Some("0"),
            })
        },
    },
    Op {
        spec: OpSpec {
            method: None,
            macro_name: OFFSET_MACRO,
            http: None,
            summary: "BED_MESH_OFFSET X= Y= that thermal mesh following sets again after each profile load (a load drops a plain BED_MESH_OFFSET)",
            args: &[
                arg(
                    "x",
                    ArgKind::Number {
                        min: -1000.0,
                        max: 1000.0,
                    },
                    "5",
                    "a number of mm",
                    "",
                    "X offset, mm (default: the one kept)",
                ),
                arg(
                    "y",
                    ArgKind::Number {
                        min: -1000.0,
                        max: 1000.0,
                    },
                    "-3",
                    "a number of mm",
                    "",
                    "Y offset, mm (default: the one kept)",
                ),
            ],
            body: MacroBody::Local(&[
                "{% set sx = params.X|default(x)|string %}",
                "{% set sy = params.Y|default(y)|string %}",
                "{% set nx = sx|float(none) %}",
                "{% set ny = sy|float(none) %}",
                "{% if nx is none or not (-1000 < nx < 1000) %}",
                "{action_raise_error(\"KLIPCAL_MESH_OFFSET: X=\" ~ sx ~ \" is not a number of mm, expected e.g. X=5\")}",
                "{% endif %}",
                "{% if ny is none or not (-1000 < ny < 1000) %}",
                "{action_raise_error(\"KLIPCAL_MESH_OFFSET: Y=\" ~ sy ~ \" is not a number of mm, expected e.g. Y=-3\")}",
                "{% endif %}",
                "BED_MESH_OFFSET X={nx} Y={ny}",
                "SET_GCODE_VARIABLE MACRO=KLIPCAL_MESH_OFFSET VARIABLE=x VALUE={nx}",
                "SET_GCODE_VARIABLE MACRO=KLIPCAL_MESH_OFFSET VARIABLE=y VALUE={ny}",
            ]),
            variables: &[("x", "0.0"), ("y", "0.0")],
            comment: &[
                "The offset is kept here, in Klipper (a restart clears it, as it clears BED_MESH_OFFSET),",
                "klipcal reads x and y and sends BED_MESH_OFFSET with them right after each profile it loads.",
                "A value not given keeps the one kept before. Bad values stop the macro before anything is",
                "set or kept.",
            ],
        },
        parse: |_| Err(anyhow::anyhow!("KLIPCAL_MESH_OFFSET runs in Klipper")),
    },
    Op {
        spec: OpSpec {
            body: MacroBody::Remote {
                before: &[],
                // A remote call does not wait: the print pauses here and klipcal resumes it
                // when the bed matches (or cancels it).
                after: &[
                    "{% if printer.print_stats.state == \"printing\" %}",
                    "RESPOND PREFIX=klipcal MSG=\"print paused for the thermal mesh check, klipcal resumes it when the bed matches\"",
                    "PAUSE",
                    "{% endif %}",
                ],
            },
            ..OpSpec::remote(
                "klipcal_mesh_check",
                "KLIPCAL_MESH_CHECK",
                "mesh/check",
                "probe a few points and compare with the thermal mesh model, call it in PRINT_START (cancels the print when off by more than mesh.reference_limit_mm)",
                &[],
            )
        },
        parse: |_| Ok(MeshCall::Check),
    },
];

/// A thermal mesh call, typed at the boundary.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum MeshCall {
    /// `klipcal_mesh_capture`, with the bed temperature when given.
    Capture {
        /// °C (0: unheated).
        bed_c: Option<f64>,
    },
    /// `klipcal_mesh_import`.
    Import,
    /// `klipcal_mesh_follow`.
    Follow {
        /// Start (true) or stop following.
        enable: bool,
    },
    /// `klipcal_mesh_check`.
    Check,
}

impl MeshCall {
    /// Reads a call of `method` at the boundary.
    ///
    /// # Errors
    /// An unknown method, or a bad or unknown argument, named.
    pub fn parse(method: &str, args: &Value) -> anyhow::Result<Self> {
        parse_call(OPS, method, args)
    }
}

/// The store's kind.
pub const KIND: &str = "mesh";

/// klipcal.cfg's macro that keeps the user's `BED_MESH_OFFSET` (in its variables `x`, `y`) so
/// the follower can set it again after each load: Klipper's status does not show the offset,
/// and `BED_MESH_PROFILE LOAD=` drops it.
pub const OFFSET_MACRO: &str = "KLIPCAL_MESH_OFFSET";

const TITLE: &str = "thermal mesh";

/// A capture session's state.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum State {
    /// Checking the printer.
    Preflight,
    /// Bed heating and soaking.
    Soaking,
    /// Taking meshes as the frame warms.
    Capturing,
    /// Writing the profiles.
    Writing,
    /// Profiles written.
    Done,
    /// Failed, with the reason.
    Failed,
    /// Cancelled, with the reason.
    Cancelled,
}

impl State {
    fn name(self) -> String {
        serde_json::to_value(self)
            .ok()
            .and_then(|v| v.as_str().map(str::to_string))
            .unwrap_or_default()
    }

    fn is_final(self) -> bool {
        matches!(self, State::Done | State::Failed | State::Cancelled)
    }
}

/// One stored mesh.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct CaptureDoc {
    /// 1-based.
    pub n: usize,
    /// Unix time it completed.
    pub at_unix: f64,
    /// Frame temperature per point, °C (row-major like `points_mm`).
    pub temps_c: Vec<f64>,
    /// z per point, mm, row-major (y rows of x values).
    pub points_mm: Vec<f64>,
    /// Whether the frame was warming or cooling.
    pub heating: bool,
}

/// What the fit and the profile write gave.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ResultDoc {
    /// The chosen model.
    pub model: String,
    /// Leave-one-mesh-out errors per model: (name, max, mean, rms) µm.
    pub models: Vec<(String, f64, f64, f64)>,
    /// VGB's two-mesh method on the same data (max, mean, rms) µm.
    pub vgb: Option<(f64, f64, f64)>,
    /// Captured frame range, °C.
    pub range_c: (f64, f64),
    /// Profile temperatures written, °C.
    pub profiles_c: Vec<f64>,
    /// Worst error of using the nearest profile, µm.
    pub max_quantisation_um: f64,
    /// Where the backup of printer.cfg went.
    pub backup: Option<String>,
    /// The klipcal profiles printer.cfg held before the write, which it replaced.
    #[serde(default)]
    pub replaced: Vec<String>,
    /// Heating and cooling: which meshes were fitted, and why, in words.
    #[serde(default)]
    pub directions: String,
    /// The cooling direction's model and profiles (`klipcal_cool_<T>`), when heating and
    /// cooling differ by more than the tolerance; the fields above are then heating's.
    #[serde(default)]
    pub cooling: Option<CoolingDoc>,
}

/// The cooling direction's fit and profiles.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct CoolingDoc {
    /// The chosen model.
    pub model: String,
    /// Leave-one-mesh-out errors per model: (name, max, mean, rms) µm.
    pub models: Vec<(String, f64, f64, f64)>,
    /// Captured frame range of the cooling meshes, °C.
    pub range_c: (f64, f64),
    /// Profile temperatures written, °C.
    pub profiles_c: Vec<f64>,
    /// Worst error of using the nearest profile, µm.
    pub max_quantisation_um: f64,
}

/// The session document.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Session {
    /// Store id.
    pub id: i64,
    /// State.
    pub state: State,
    /// Why it failed or was cancelled.
    pub reason: Option<String>,
    /// The current step in words.
    pub progress: String,
    /// `[mesh]` as the session runs it.
    pub options: MeshConfig,
    /// The mesh parameters (from Klipper's `klipcal_capture` profile after the first mesh).
    pub params: Option<MeshParams>,
    /// Every mesh so far.
    pub captures: Vec<CaptureDoc>,
    /// Unix time the capture started (after the soak).
    pub started_unix: Option<f64>,
    /// The result, once written.
    pub result: Option<ResultDoc>,
    /// Things the user should know.
    pub notes: Vec<String>,
    /// The bed mesh active in Klipper when the capture started (`Some("")`: none), loaded
    /// again after each mesh and at the end; `None` for an import or an older session.
    #[serde(default)]
    pub user_mesh: Option<String>,
    /// The meshes are VGB's profiles imported from the config (whose names do not say whether
    /// the frame warmed or cooled), not a capture's.
    #[serde(default)]
    pub imported: bool,
}

/// The profile klipcal's BED_MESH_CALIBRATE stores each capture mesh under: never the
/// user's `default` (a SAVE_CONFIG during the capture would write a capture mesh over it),
/// and a `klipcal_` name, so the next profile write removes it should it reach printer.cfg.
pub const CAPTURE_PROFILE: &str = "klipcal_capture";

/// The mesh parameters of a profile in Klipper's `bed_mesh` status (`mesh_params`).
fn params_from_status(p: &Value) -> Option<MeshParams> {
    serde_json::from_value(p.clone()).ok()
}

impl Doc for Session {
    fn state_name(&self) -> String {
        self.state.name()
    }
}

/// The frame temperature of each point of a mesh probed in Klipper's order (rows along Y,
/// alternating direction along X) from temperature samples `(t_s, temp_c)` spanning the
/// mesh: the probes are taken as evenly spread over the samples' time span.
#[must_use]
pub fn point_temps(samples: &[(f64, f64)], x_count: usize, y_count: usize) -> Vec<f64> {
    let n = x_count * y_count;
    let mut out = vec![f64::NAN; n];
    if samples.is_empty() || n == 0 {
        return out;
    }
    let (t0, t1) = (samples[0].0, samples[samples.len() - 1].0);
    let at = |t: f64| -> f64 {
        match samples.iter().position(|s| s.0 >= t) {
            Some(0) => samples[0].1,
            Some(k) => {
                let (a, b) = (samples[k - 1], samples[k]);
                if b.0 > a.0 {
                    a.1 + (b.1 - a.1) * (t - a.0) / (b.0 - a.0)
                } else {
                    b.1
                }
            }
            None => samples[samples.len() - 1].1,
        }
    };
    for y in 0..y_count {
        for x in 0..x_count {
            let order = y * x_count + if y % 2 == 0 { x } else { x_count - 1 - x };
            let frac = if n > 1 {
                order as f64 / (n - 1) as f64
            } else {
                0.0
            };
            out[y * x_count + x] = at(t0 + (t1 - t0) * frac);
        }
    }
    out
}

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

fn calib_captures(s: &Session) -> Vec<Capture> {
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
fn fit_session(s: &Session) -> anyhow::Result<cm::DirectionalSelection> {
    let caps = calib_captures(s);
    let refs: Vec<&Capture> = caps.iter().collect();
    cm::select_directions(&refs, s.options.tolerance_um)
        .map_err(|e| user(format!("fitting the meshes: {e}")))
}

/// The profiles of one direction's model over its range.
fn plan_direction(sel: &cm::Selection, tolerance_um: f64) -> anyhow::Result<cm::ProfilePlan> {
    let (lo, hi) = sel.fit.range_c;
    cm::plan_profiles(&sel.fit, lo, hi, tolerance_um).map_err(|e| user(e.to_string()))
}

fn model_rows(sel: &cm::Selection) -> Vec<(String, f64, f64, f64)> {
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

/// The thermal mesh over the shared core.
#[derive(Clone)]
pub struct Mesh {
    core: Core,
    settings: MeshConfig,
    soak: SoakParams,
    follow: Arc<Mutex<Option<CancellationToken>>>,
    follow_status: Arc<Mutex<Value>>,
}

impl Mesh {
    /// The calibration over `core`.
    #[must_use]
    pub fn new(core: Core, settings: MeshConfig, soak: SoakParams) -> Self {
        Self {
            core,
            settings,
            soak,
            follow: Arc::new(Mutex::new(None)),
            follow_status: Arc::new(Mutex::new(json!({"following": false}))),
        }
    }

    async fn update<T>(
        &self,
        id: i64,
        f: impl FnOnce(&mut Session) -> anyhow::Result<T>,
    ) -> anyhow::Result<T> {
        self.core.update(id, f).await
    }

    async fn set_state(&self, id: i64, state: State, progress: &str) -> anyhow::Result<()> {
        info!(session = id, state = %state.name(), "{progress}");
        let p = progress.to_string();
        self.update(id, |s| {
            s.state = state;
            s.progress = p;
            Ok(())
        })
        .await
    }

    async fn frame_temp(&self, sensor: &str) -> anyhow::Result<f64> {
        let obj = format!("temperature_sensor {sensor}");
        let st = self
            .core
            .m()
            .objects_query(json!({ obj.clone(): ["temperature"] }))
            .await?;
        st[&obj]["temperature"].as_f64().ok_or_else(|| {
            user(format!(
                "[{obj}] reports no temperature; mesh.frame_sensor names the frame thermistor"
            ))
        })
    }

    /// `klipcal_mesh_capture`: starts a capture.
    async fn capture(&self, bed_c: Option<f64>) -> anyhow::Result<Value> {
        let mut options = self.settings.clone();
        if let Some(b) = bed_c {
            options.bed_temp_c = b;
        }
        self.core.refuse_other_kind(KIND)?;
        self.core.printer_idle().await?;
        self.preflight(&options).await?;
        self.stop_following("a capture starts").await;
        // The mesh the user has loaded now, to load again after each capture mesh.
        let st = self
            .core
            .m()
            .objects_query(json!({"bed_mesh": ["profile_name"]}))
            .await?;
        let user_mesh = st["bed_mesh"]["profile_name"]
            .as_str()
            .unwrap_or("")
            .to_string();
        let mut doc = Session {
            id: 0,
            state: State::Preflight,
            reason: None,
            progress: "starting".into(),
            options,
            params: None,
            captures: Vec::new(),
            started_unix: None,
            result: None,
            notes: Vec::new(),
            user_mesh: Some(user_mesh),
            imported: false,
        };
        let id = self.core.create(KIND, &mut doc, |d, id| d.id = id).await?;
        self.spawn_runner(id);
        let msg = format!(
            "thermal mesh capture started (session {id}): the bed heats to {} °C, then a mesh is \
             taken each time the frame moves {} °C or every {:.0} min until it settles",
            doc.options.bed_temp_c,
            doc.options.step_c,
            doc.options.interval_s / 60.0
        );
        Ok(json!({"session": id, "state": "preflight", "message": msg}))
    }

    /// `klipcal_mesh_import`: fits the VGB profiles already in the config (`COLDxx.x`,
    /// `HOTxx.x`; `TESTxx.x` are judged, never fitted) and writes klipcal's profiles from
    /// them, every profile's mesh parameters checked against the others.
    async fn import(&self) -> anyhow::Result<Value> {
        self.core.refuse_other_kind(KIND)?;
        self.core.printer_idle().await?;
        let pc = super::printer_config::fetch(self.core.m(), self.core.files()).await?;
        let all = bed_mesh::profiles(&pc.config).map_err(|e| user(e.to_string()))?;
        let mut fitted: Vec<(&MeshProfile, f64)> = Vec::new();
        let mut tests: Vec<&MeshProfile> = Vec::new();
        for p in &all {
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
        let tol = self.settings.tolerance_um;
        let caps: Vec<Capture> = captures
            .iter()
            .zip(&fitted)
            .map(|(c, (p, _))| Capture {
                name: p.name.clone(),
                temps_c: c.temps_c.clone(),
                points_mm: c.points_mm.clone(),
                phase: Phase::Heating,
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
        let tests_json: Vec<Value> = judged
            .iter()
            .map(|(n, t, e)| {
                json!({"name": n, "temp_c": t, "max_um": e.max_um, "mean_um": e.mean_um,
                       "within_tolerance": e.max_um <= tol})
            })
            .collect();
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
        let mut doc = Session {
            id: 0,
            state: State::Writing,
            reason: None,
            progress: format!("fitting {} imported VGB profiles", names.len()),
            options: self.settings.clone(),
            params: Some(fitted[0].0.params.clone()),
            captures,
            started_unix: Some(now),
            result: None,
            notes,
            user_mesh: None,
            imported: true,
        };
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
        Ok(
            json!({"session": id, "state": "writing", "imported": names, "tests": tests_json,
                  "replaces": replaced, "message": msg}),
        )
    }

    /// Refuses when the printer lacks what a capture needs, naming it.
    async fn preflight(&self, o: &MeshConfig) -> anyhow::Result<()> {
        let objects = self.core.m().objects_list().await?;
        let mut missing = Vec::new();
        let sensor = format!("temperature_sensor {}", o.frame_sensor);
        if !objects.contains(&sensor) {
            missing.push(format!(
                "[{sensor}] (the frame thermistor; mesh.frame_sensor names it)"
            ));
        }
        if !objects.iter().any(|x| x == "bed_mesh") {
            missing.push("[bed_mesh]".to_string());
        }
        if !objects.iter().any(|x| {
            x == "probe"
                || x.starts_with("bltouch")
                || x.starts_with("probe_eddy")
                || x.starts_with("beacon")
                || x.starts_with("cartographer")
        }) {
            missing.push("a probe ([probe], [bltouch], …)".to_string());
        }
        if o.bed_temp_c > 0.0 && !objects.iter().any(|x| x == "heater_bed") {
            missing.push("[heater_bed] (or capture with BED=0)".to_string());
        }
        if !missing.is_empty() {
            return Err(user(format!(
                "the printer lacks what a thermal mesh capture needs: {}",
                missing.join(", ")
            )));
        }
        Ok(())
    }

    fn spawn_runner(&self, id: i64) {
        let (me, me2) = (self.clone(), self.clone());
        self.core.spawn_session(
            id,
            TITLE,
            move || {
                let me = me.clone();
                async move { me.run(id).await }
            },
            move |msg| async move {
                let off = me2
                    .core
                    .heaters_off_once_back(&format!("{TITLE} failed: {msg}"))
                    .await;
                if let Err(e) = &off {
                    warn!(session = id, error = %format!("{e:#}"), "heaters not turned off");
                }
                let heaters = if off.is_ok() { "; heaters off" } else { "" };
                let _ = me2
                    .update(id, |s| {
                        if !s.state.is_final() {
                            s.state = State::Failed;
                            s.reason = Some(msg.clone());
                            s.progress = format!("failed{heaters}");
                        }
                        Ok(())
                    })
                    .await;
                me2.core
                    .console_error(&format!("{TITLE} failed: {msg}{heaters}"))
                    .await;
            },
        );
    }

    /// Runs the session's steps; when one fails, the user's mesh is loaded again before the
    /// error goes on.
    async fn run(&self, id: i64) -> anyhow::Result<()> {
        let r = self.run_steps(id).await;
        if r.is_err() {
            if let Ok(s) = self.core.load::<Session>(id) {
                self.put_back_user_mesh(&s, true).await;
            }
        }
        r
    }

    async fn run_steps(&self, id: i64) -> anyhow::Result<()> {
        loop {
            let s: Session = self.core.load(id)?;
            match s.state {
                State::Preflight => {
                    if s.options.bed_temp_c > 0.0 {
                        BedSoak::heat(&self.core, s.options.bed_temp_c).await?;
                    }
                    self.set_state(id, State::Soaking, "heating the bed")
                        .await?;
                }
                State::Soaking => self.soak_bed(&s).await?,
                State::Capturing => self.capture_loop(s).await?,
                State::Writing => self.write_profiles(s).await?,
                _ => return Ok(()),
            }
        }
    }

    async fn soak_bed(&self, s: &Session) -> anyhow::Result<()> {
        if s.options.bed_temp_c > 0.0 {
            // After a restart the bed may be cold again: heat (again) before watching.
            BedSoak::heat(&self.core, s.options.bed_temp_c).await?;
            let mut soak = BedSoak::new(
                self.soak.clone(),
                s.options.bed_temp_c,
                s.options.soak_max_s,
                "mesh.soak_max_s",
            );
            loop {
                match soak.poll(&self.core, "thermal mesh").await? {
                    SoakUpdate::Stable { .. } => break,
                    SoakUpdate::TooLong { minutes, .. } => {
                        return Err(user(format!(
                            "the bed had not settled after {minutes:.0} min (mesh.soak_max_s); \
                             the meshes would drift with it"
                        )))
                    }
                    SoakUpdate::Heating => {}
                    SoakUpdate::Soaking { text, .. } => {
                        let _ = self
                            .update(s.id, |d| {
                                d.progress = text;
                                Ok(())
                            })
                            .await;
                    }
                }
                tokio::time::sleep(Duration::from_secs(1)).await;
            }
        }
        // Between meshes the printer idles: Klipper's idle timeout must not end the capture,
        // yet still turns the heaters off if klipcal stops (at most an interval later).
        self.core
            .hold_heaters_for(s.options.interval_s + 600.0)
            .await?;
        let now = now_unix();
        self.update(s.id, |d| {
            d.state = State::Capturing;
            d.started_unix.get_or_insert(now);
            d.progress = "bed stable; taking the first mesh".into();
            Ok(())
        })
        .await
    }

    /// Loads the mesh that was active when the capture started (clears the mesh when none
    /// was), so klipcal's capture mesh never stays in use; `last` also drops the capture
    /// profile from Klipper's memory (and from what a SAVE_CONFIG would write). Nothing for a
    /// session that did not record the user's mesh (an import). Failures are logged: the
    /// capture's own outcome is what the user hears about.
    async fn put_back_user_mesh(&self, s: &Session, last: bool) {
        let Some(user_mesh) = &s.user_mesh else {
            return;
        };
        let load = if user_mesh.is_empty() || user_mesh == CAPTURE_PROFILE {
            Ok("BED_MESH_CLEAR".to_string())
        } else {
            crate::klipper::GcodeCmd::new("BED_MESH_PROFILE")
                .word("LOAD", user_mesh)
                .build()
        };
        let mut script = match load {
            Ok(l) => l,
            Err(e) => {
                warn!(profile = %user_mesh, error = %e, "the mesh active before the capture cannot be loaded by name");
                "BED_MESH_CLEAR".to_string()
            }
        };
        if last {
            let st = self
                .core
                .m()
                .objects_query(json!({"bed_mesh": ["profiles"]}))
                .await;
            let kept = st.map_or(true, |st| {
                !st["bed_mesh"]["profiles"][CAPTURE_PROFILE].is_null()
            });
            if kept {
                script.push_str(&format!("\nBED_MESH_PROFILE REMOVE={CAPTURE_PROFILE}"));
            }
        }
        if let Err(e) = self
            .core
            .m()
            .gcode_within(&script, Duration::from_secs(900))
            .await
        {
            warn!(session = s.id, error = %e, "loading the mesh active before the capture again");
        }
    }

    async fn homed(&self) -> anyhow::Result<()> {
        let st = self
            .core
            .m()
            .objects_query(json!({"toolhead": ["homed_axes"]}))
            .await?;
        if st["toolhead"]["homed_axes"].as_str().unwrap_or("") != "xyz" {
            self.core
                .m()
                .gcode_within("G28", Duration::from_secs(300))
                .await?;
        }
        Ok(())
    }

    /// One BED_MESH_CALIBRATE with the frame sampled while it runs.
    async fn take_mesh(&self, s: &Session) -> anyhow::Result<(CaptureDoc, MeshParams)> {
        self.homed().await?;
        let sensor = s.options.frame_sensor.clone();
        let me = self.clone();
        let stop = self.core.shutdown().child_token();
        let stop2 = stop.clone();
        let sampler = tokio::spawn(async move {
            let t0 = Instant::now();
            let mut out: Vec<(f64, f64)> = Vec::new();
            loop {
                if let Ok(t) = me.frame_temp(&sensor).await {
                    out.push((t0.elapsed().as_secs_f64(), t));
                }
                tokio::select! {
                    () = stop2.cancelled() => break,
                    () = tokio::time::sleep(Duration::from_millis(250)) => {}
                }
            }
            if let Ok(t) = me.frame_temp(&sensor).await {
                out.push((t0.elapsed().as_secs_f64(), t));
            }
            out
        });
        let calibrate = crate::klipper::GcodeCmd::new("BED_MESH_CALIBRATE")
            .word("PROFILE", CAPTURE_PROFILE)
            .build()
            .map_err(|e| anyhow!("{e}"))?;
        let done = self
            .core
            .m()
            .gcode_within(&calibrate, Duration::from_secs(900))
            .await;
        stop.cancel();
        let samples = sampler.await.unwrap_or_default();
        done.context("BED_MESH_CALIBRATE")?;
        let st = self
            .core
            .m()
            .objects_query(json!({"bed_mesh": ["probed_matrix", "profiles", "profile_name"]}))
            .await?;
        self.put_back_user_mesh(s, false).await;
        let bm = &st["bed_mesh"];
        let rows: Vec<Vec<f64>> = serde_json::from_value(bm["probed_matrix"].clone())
            .context("reading bed_mesh.probed_matrix")?;
        let params = params_from_status(&bm["profiles"][CAPTURE_PROFILE]["mesh_params"])
            .ok_or_else(|| {
                anyhow!("bed_mesh reports no mesh_params for profile {CAPTURE_PROFILE}")
            })?;
        if rows.len() != params.y_count || rows.iter().any(|r| r.len() != params.x_count) {
            return Err(anyhow!(
                "the probed mesh is not {}×{}",
                params.x_count,
                params.y_count
            ));
        }
        let temps = point_temps(&samples, params.x_count, params.y_count);
        if temps.iter().any(|t| !t.is_finite()) {
            return Err(user(format!(
                "the frame sensor [temperature_sensor {}] gave no reading during the mesh",
                s.options.frame_sensor
            )));
        }
        let first = samples.first().map_or(f64::NAN, |s| s.1);
        let last = samples.last().map_or(f64::NAN, |s| s.1);
        let prev = s
            .captures
            .last()
            .map(|c| c.temps_c.iter().sum::<f64>() / c.temps_c.len().max(1) as f64);
        let heating = match prev {
            Some(p) => (first + last) / 2.0 >= p,
            None => last >= first,
        };
        Ok((
            CaptureDoc {
                n: s.captures.len() + 1,
                at_unix: now_unix(),
                temps_c: temps,
                points_mm: rows.into_iter().flatten().collect(),
                heating,
            },
            params,
        ))
    }

    async fn capture_loop(&self, s: Session) -> anyhow::Result<()> {
        let id = s.id;
        let o = s.options.clone();
        let started = s.started_unix.unwrap_or_else(now_unix);
        if s.captures.is_empty() {
            self.mesh_now(id).await?;
        }
        loop {
            let s: Session = self.core.load(id)?;
            if let Some(why) = capture_done(&s.captures, now_unix(), started, &o) {
                let _ = self.core.heaters_off().await;
                self.put_back_user_mesh(&s, true).await;
                let msg = format!("{TITLE}: capture complete, {why}; heaters off; fitting");
                self.core.console(&msg).await;
                self.set_state(id, State::Writing, &msg).await?;
                return Ok(());
            }
            let last = s.captures.last().ok_or_else(|| anyhow!("no mesh"))?;
            let last_t = last.temps_c.iter().sum::<f64>() / last.temps_c.len().max(1) as f64;
            let now_t = self.frame_temp(&o.frame_sensor).await?;
            if mesh_due(last_t, now_t, now_unix() - last.at_unix, &o) {
                self.mesh_now(id).await?;
            } else {
                tokio::time::sleep(Duration::from_secs(1)).await;
            }
        }
    }

    async fn mesh_now(&self, id: i64) -> anyhow::Result<()> {
        let s: Session = self.core.load(id)?;
        let (cap, params) = self.take_mesh(&s).await?;
        let n = cap.n;
        let mean = cap.temps_c.iter().sum::<f64>() / cap.temps_c.len().max(1) as f64;
        if let Some(p) = &s.params {
            if p.x_count != params.x_count || p.y_count != params.y_count {
                return Err(user(format!(
                    "mesh {n} is {}×{} but the first was {}×{}: the [bed_mesh] settings changed during the capture",
                    params.x_count, params.y_count, p.x_count, p.y_count
                )));
            }
        }
        let msg = format!("{TITLE}: mesh {n} stored at frame {mean:.2} °C");
        self.update(id, |d| {
            d.captures.push(cap);
            d.params.get_or_insert(params);
            d.progress = msg.clone();
            Ok(())
        })
        .await?;
        self.core.console(&msg).await;
        Ok(())
    }

    /// Fits, plans the profiles and writes them into the SAVE_CONFIG block; rolls back when
    /// Klipper does not come back ready with every profile.
    async fn write_profiles(&self, s: Session) -> anyhow::Result<()> {
        let id = s.id;
        let (profiles, mut result) = plan_session(&s)?;
        self.core.printer_idle().await?;
        let (backup, replaced) = self.write_block(&profiles).await?;
        result.backup = Some(backup);
        result.replaced = replaced;
        let (lo, hi) = result.range_c;
        let cooling_words = match &result.cooling {
            Some(c) => format!(
                " and {} klipcal_cool_* for cooling over {:.2}–{:.2} °C (model {})",
                c.profiles_c.len(),
                c.range_c.0,
                c.range_c.1,
                c.model
            ),
            None => String::new(),
        };
        let replaced_words = if result.replaced.is_empty() {
            String::new()
        } else {
            format!(
                "; they replace the {} klipcal profiles of before ({}), kept in the backup {}",
                result.replaced.len(),
                result.replaced.join(", "),
                result.backup.as_deref().unwrap_or("")
            )
        };
        let msg = format!(
            "{TITLE}: {} profiles klipcal_* written for {lo:.2}–{hi:.2} °C (model {}, worst \
             step {:.1} µm){cooling_words}; {}{replaced_words}; KLIPCAL_MESH_FOLLOW ENABLE=1 \
             follows the frame",
            result.profiles_c.len(),
            result.model,
            result.max_quantisation_um,
            result.directions
        );
        self.update(id, |d| {
            d.result = Some(result);
            d.state = State::Done;
            d.progress = msg.clone();
            Ok(())
        })
        .await?;
        self.core.console(&msg).await;
        Ok(())
    }

    /// Replaces the klipcal profiles in printer.cfg's SAVE_CONFIG block: backup, upload,
    /// restart, verify each profile is known; on failure the backup goes back. The backup's
    /// path and the klipcal profiles replaced.
    async fn write_block(&self, profiles: &[MeshProfile]) -> anyhow::Result<(String, Vec<String>)> {
        let files = self.core.files();
        let old = files
            .download("config", "printer.cfg")
            .await
            .context("reading printer.cfg")?;
        let text =
            String::from_utf8(old.clone()).map_err(|_| anyhow!("printer.cfg is not UTF-8"))?;
        let new =
            bed_mesh::replace_klipcal_profiles(&text, profiles).map_err(|e| user(e.to_string()))?;
        let replaced = bed_mesh::klipcal_profile_names(&text);
        let stamp = super::printer_config::stamp(now_unix() as u64);
        let backup_dir = format!("klipcal_backups/{stamp}");
        let writes = [FileWrite {
            rel: "printer.cfg".into(),
            old: Some(old),
            new: new.into_bytes(),
        }];
        super::printer_config::transact(
            self.core.m(),
            files,
            &writes,
            &backup_dir,
            "RESTART",
            || self.verify_profiles(profiles),
        )
        .await?;
        Ok((format!("config/{backup_dir}/printer.cfg"), replaced))
    }

    /// After the restart with new profiles: every profile is known to Klipper and loads
    /// (`BED_MESH_PROFILE LOAD=`, which builds the mesh as a print would and applies
    /// `[bed_mesh]`'s fade checks); the mesh active before is put back. `Some(why)` names the
    /// first profile Klipper refused, in Klipper's words.
    async fn verify_profiles(&self, profiles: &[MeshProfile]) -> anyhow::Result<Option<String>> {
        let m = self.core.m();
        let st = m
            .objects_query(json!({"bed_mesh": ["profiles", "profile_name"]}))
            .await?;
        let bm = &st["bed_mesh"];
        if let Some(p) = profiles.iter().find(|p| bm["profiles"][&p.name].is_null()) {
            return Ok(Some(format!(
                "Klipper did not read profile {} from printer.cfg",
                p.name
            )));
        }
        let active = bm["profile_name"].as_str().unwrap_or("").to_string();
        let mut refused = None;
        for p in profiles {
            let load = crate::klipper::GcodeCmd::new("BED_MESH_PROFILE")
                .word("LOAD", &p.name)
                .build()
                .map_err(|e| anyhow!("{e}"))?;
            match m.gcode(&load).await {
                Ok(()) => {}
                Err(e) if e.is_refusal() => {
                    refused = Some(format!(
                        "Klipper refused to load profile {}: {}",
                        p.name,
                        klipper_message(&e)
                    ));
                    break;
                }
                Err(e) => return Err(e).context(format!("loading profile {}", p.name)),
            }
        }
        // Leave the mesh as the restart left it.
        let back = crate::klipper::GcodeCmd::new("BED_MESH_PROFILE")
            .word("LOAD", &active)
            .build()
            .ok()
            .filter(|_| !active.is_empty())
            .unwrap_or_else(|| "BED_MESH_CLEAR".to_string());
        if let Err(e) = m.gcode(&back).await {
            warn!(error = %e, "putting the mesh back after verifying the profiles");
        }
        Ok(refused)
    }

    /// The newest finished capture (`done`: its profiles are the ones written) and its fit. A
    /// capture still running is waited for; a newer one that failed or was cancelled wrote
    /// nothing (a failed write is rolled back), so the one before it rules.
    fn model(&self) -> anyhow::Result<(Session, cm::DirectionalSelection)> {
        if let Some((id, s)) = self.core.latest_of::<Session>(KIND)? {
            if !s.state.is_final() {
                return Err(user(format!(
                    "thermal mesh session {id} is {}; wait for it to finish (or KLIPCAL_CANCEL)",
                    s.state.name().replace('_', " ")
                )));
            }
        }
        let Some((_, s)) = self
            .core
            .latest_of_in::<Session>(KIND, &State::Done.name())?
        else {
            return Err(user(
                "no thermal mesh captured yet; run KLIPCAL_MESH_CAPTURE first",
            ));
        };
        let sel = fit_session(&s)?;
        Ok((s, sel))
    }

    async fn stop_following(&self, why: &str) {
        let t = self.follow.lock().ok().and_then(|mut f| f.take());
        if let Some(t) = t {
            t.cancel();
            if let Ok(mut st) = self.follow_status.lock() {
                *st = json!({"following": false, "stopped": why});
            }
            self.core
                .console(&format!("{TITLE}: following stopped ({why})"))
                .await;
        }
    }

    /// `klipcal_mesh_follow`: starts or stops following the frame temperature.
    async fn follow_cmd(&self, enable: bool) -> anyhow::Result<Value> {
        if !enable {
            self.stop_following("KLIPCAL_MESH_FOLLOW ENABLE=0").await;
            return Ok(json!({"following": false, "message": "thermal mesh following is off"}));
        }
        let (s, sel) = self.model()?;
        let temps = s
            .result
            .as_ref()
            .map(|r| r.profiles_c.clone())
            .unwrap_or_default();
        // The cooling profiles, when the session wrote them (the fit is the same: the same
        // captures and tolerance).
        let cooling = match (
            sel.cooling,
            s.result.as_ref().and_then(|r| r.cooling.as_ref()),
        ) {
            (Some(c), Some(doc)) if !doc.profiles_c.is_empty() => Some(Branch {
                phase: Phase::Cooling,
                fit: c.fit,
                temps_c: doc.profiles_c.clone(),
            }),
            _ => None,
        };
        if temps.is_empty() {
            return Err(user(
                "the last capture wrote no profiles; run KLIPCAL_MESH_CAPTURE again",
            ));
        }
        let cf = self.core.m().configfile().await?;
        let bm = &cf["settings"]["bed_mesh"];
        let fade_end = bm["fade_end"].as_f64().unwrap_or(0.0);
        let fade_start = bm["fade_start"].as_f64().unwrap_or(1.0);
        if fade_end > fade_start {
            return Err(user(format!(
                "[bed_mesh] fades the mesh out from {fade_start} to {fade_end} mm: a profile loaded mid-print \
                 would be faded differently from the one it replaces (VGB: IMPORTANT). Set fade_end: 0 in \
                 [bed_mesh] (or remove fade_start/fade_end), restart, then KLIPCAL_MESH_FOLLOW ENABLE=1"
            )));
        }
        let offset_note = if self.kept_offset().await.is_some() {
            format!(
                "; an offset set with {OFFSET_MACRO} X= Y= is set again after each load (a plain \
                 BED_MESH_OFFSET is dropped by the next load)"
            )
        } else {
            self.core
                .console_error(&format!(
                    "{TITLE}: klipcal.cfg has no {OFFSET_MACRO} (update klipcal.cfg): each profile \
                     load drops a BED_MESH_OFFSET and klipcal cannot set it again"
                ))
                .await;
            String::new()
        };
        self.stop_following("restarted").await;
        let token = self.core.shutdown().child_token();
        if let Ok(mut f) = self.follow.lock() {
            *f = Some(token.clone());
        }
        let me = self.clone();
        let sensor = s.options.frame_sensor.clone();
        let policy = self.settings.follow_policy();
        let directions = if cooling.is_some() {
            " (klipcal_* while the frame warms, klipcal_cool_* while it cools)"
        } else {
            ""
        };
        let heating = Branch {
            phase: Phase::Heating,
            fit: sel.heating.fit,
            temps_c: temps,
        };
        self.core.spawn(async move {
            me.follow_loop(token, sensor, policy, heating, cooling)
                .await;
        });
        let msg = format!(
            "{TITLE}: following the frame temperature with the profiles of session {}{directions}{offset_note}",
            s.id
        );
        Ok(json!({"following": true, "session": s.id, "message": msg}))
    }

    async fn follow_loop(
        &self,
        token: CancellationToken,
        sensor: String,
        policy: crate::calib::mesh_follow::FollowPolicy,
        heating: Branch,
        cooling: Option<Branch>,
    ) {
        let t0 = Instant::now();
        let fresh = || Follower::with_directions(policy, heating.clone(), cooling.clone(), None);
        let mut f = fresh();
        let mut offset_mm = (0.0, 0.0);
        loop {
            tokio::select! {
                () = token.cancelled() => return,
                () = tokio::time::sleep(Duration::from_secs(1)) => {}
            }
            let t = t0.elapsed().as_secs_f64();
            // A Klipper restart (or a manual load) replaces the mesh the follower loaded: start
            // over, so the right profile is loaded again.
            if let Some((phase, temp_c)) = f.loaded() {
                let active = self
                    .core
                    .m()
                    .objects_query(json!({"bed_mesh": ["profile_name"]}))
                    .await
                    .ok()
                    .and_then(|st| st["bed_mesh"]["profile_name"].as_str().map(str::to_string));
                if active.is_some_and(|a| a != direction_profile_name(phase, temp_c)) {
                    info!("the active mesh changed under the follower (Klipper restarted?); reloading");
                    f = fresh();
                }
            }
            let busy = self.busy().await;
            let d = match self.frame_temp(&sensor).await {
                Ok(temp) => {
                    let d = f.push(t, temp, busy);
                    if let Ok(mut st) = self.follow_status.lock() {
                        *st = json!({"following": true, "frame_c": temp,
                            "trend": f.trend(),
                            "loaded": f.loaded().map(|(p, t)| direction_profile_name(p, t)),
                            "offset_mm": [offset_mm.0, offset_mm.1],
                            "residual_um": match &d { Decision::Keep { residual_um, .. } | Decision::Load { residual_um, .. } => Some(*residual_um), _ => None }});
                    }
                    d
                }
                Err(_) => match f.tick(t) {
                    Some(d) => d,
                    None => continue,
                },
            };
            match d {
                Decision::Keep { .. } => {}
                Decision::Load {
                    phase,
                    temp_c,
                    residual_um,
                    ..
                } => {
                    let name = direction_profile_name(phase, temp_c);
                    // The load drops BED_MESH_OFFSET: the one kept by KLIPCAL_MESH_OFFSET is
                    // set again in the same script.
                    let kept = self.kept_offset().await.unwrap_or((0.0, 0.0));
                    match bed_mesh::load_script(&name, kept) {
                        Ok(script) => match self.core.m().gcode(&script).await {
                            Ok(()) => {
                                offset_mm = kept;
                                info!(profile = %name, residual_um, offset_x_mm = kept.0,
                                      offset_y_mm = kept.1, "mesh profile loaded");
                            }
                            Err(e) => {
                                warn!(profile = %name, error = %e, "mesh profile load failed");
                            }
                        },
                        Err(e) => {
                            self.core
                                .console_error(&format!(
                                    "{TITLE}: {OFFSET_MACRO} holds an offset klipcal cannot send \
                                     ({e}); {name} not loaded"
                                ))
                                .await;
                        }
                    }
                }
                Decision::RefuseJump {
                    phase,
                    index,
                    jump_um,
                } => {
                    let set = if phase == Phase::Cooling {
                        cooling.as_ref().unwrap_or(&heating)
                    } else {
                        &heating
                    };
                    let name = set
                        .temps_c
                        .get(index)
                        .map_or_else(String::new, |&t| direction_profile_name(phase, t));
                    self.core
                        .console_error(&format!(
                            "{TITLE}: loading {} would change the mesh by {jump_um:.0} µm (limit {:.0} µm, \
                             mesh.jump_limit_um): following stopped — was it switched on mid-print, or did the \
                             frame sensor jump?",
                            name,
                            policy.jump_limit_um
                        ))
                        .await;
                    self.stop_following("a jump over the limit").await;
                    return;
                }
                Decision::Stopped { reason } => {
                    self.core.console_error(&format!("{TITLE}: {reason}")).await;
                    if let Ok(mut st) = self.follow_status.lock() {
                        *st = json!({"following": false, "stopped": reason});
                    }
                    if let Ok(mut fl) = self.follow.lock() {
                        fl.take();
                    }
                    return;
                }
            }
        }
    }

    /// The offset `KLIPCAL_MESH_OFFSET` keeps, mm (X, Y); `None` when klipcal.cfg lacks the
    /// macro. A variable that is not a number counts as 0.
    async fn kept_offset(&self) -> Option<(f64, f64)> {
        let obj = format!("gcode_macro {OFFSET_MACRO}");
        let st = self
            .core
            .m()
            .objects_query(json!({ obj.clone(): ["x", "y"] }))
            .await
            .ok()?;
        // Klipper answers an object it does not have with `{}`.
        let vars = st.get(&obj).filter(|v| v.get("x").is_some())?;
        let num = |k: &str| vars[k].as_f64().filter(|v| v.is_finite()).unwrap_or(0.0);
        Some((num("x"), num("y")))
    }

    /// Homing or probing in progress (never load a mesh then).
    async fn busy(&self) -> bool {
        match self
            .core
            .m()
            .objects_query(json!({"idle_timeout": ["state"]}))
            .await
        {
            Ok(st) => {
                // "Printing" in idle_timeout means busy executing G-code (a move, a probe);
                // during a print the mesh is loaded between moves by Klipper's queue, which
                // is safe, so only an active print_stats print counts as not busy.
                let it = st["idle_timeout"]["state"].as_str().unwrap_or("");
                let ps = self
                    .core
                    .m()
                    .objects_query(json!({"print_stats": ["state"]}))
                    .await
                    .ok()
                    .and_then(|s| s["print_stats"]["state"].as_str().map(str::to_string))
                    .unwrap_or_default();
                it == "Printing" && ps != "printing"
            }
            Err(_) => true,
        }
    }

    /// `klipcal_mesh_check`: probes the mesh's corners and centre and compares each with the
    /// model at the current frame temperature (seed 001: a difference over the reference
    /// limit halts the print start).
    async fn check(&self) -> anyhow::Result<Value> {
        // From PRINT_START the macro pauses the print right after asking (a remote call does
        // not wait): wait for the pause, probe, then RESUME on a pass or CANCEL_PRINT on a fail.
        let in_print = self.paused_print().await?;
        let outcome = self.check_points().await;
        if in_print {
            let next = if outcome.is_ok() {
                "RESUME"
            } else {
                "CANCEL_PRINT"
            };
            if let Err(e) = self.core.m().gcode(next).await {
                warn!(error = %e, "{next} after the mesh check failed");
            }
        }
        outcome
    }

    /// Whether a print is paused for the check (waiting up to 20 s for the macro's PAUSE).
    async fn paused_print(&self) -> anyhow::Result<bool> {
        let deadline = Instant::now() + Duration::from_secs(20);
        loop {
            let st = self
                .core
                .m()
                .objects_query(json!({"print_stats": ["state"]}))
                .await?;
            match st["print_stats"]["state"].as_str().unwrap_or("") {
                "paused" => return Ok(true),
                "printing" if Instant::now() < deadline => {
                    tokio::time::sleep(Duration::from_millis(250)).await;
                }
                "printing" => {
                    return Err(user(
                        "a print is running and was not paused for the check: KLIPCAL_MESH_CHECK pauses \
                         the print itself when called from PRINT_START (use klipcal.cfg's macro)",
                    ))
                }
                _ => return Ok(false),
            }
        }
    }

    async fn check_points(&self) -> anyhow::Result<Value> {
        let (s, sel) = self.model()?;
        let params = s
            .params
            .clone()
            .ok_or_else(|| anyhow!("no mesh parameters"))?;
        let temp = self.frame_temp(&s.options.frame_sensor).await?;
        // A print start warms the frame: the heating model.
        let (lo, hi) = sel.heating.fit.range_c;
        let t_model = temp.clamp(lo, hi);
        let predicted = sel.heating.fit.predict(t_model).points_mm;
        self.homed().await?;
        let (xc, yc) = (params.x_count, params.y_count);
        let nodes = [
            (0, 0),
            (xc - 1, 0),
            (0, yc - 1),
            (xc - 1, yc - 1),
            (xc / 2, yc / 2),
        ];
        let at = |i: usize, n: usize, a: f64, b: f64| {
            if n > 1 {
                a + (b - a) * i as f64 / (n - 1) as f64
            } else {
                a
            }
        };
        let cf = self.core.m().configfile().await?;
        let probe = probe_settings(&cf["settings"]);
        let (ox, oy) = (
            probe["x_offset"].as_f64().unwrap_or(0.0),
            probe["y_offset"].as_f64().unwrap_or(0.0),
        );
        // bed_mesh stores each point as the probe's result less its z_offset: the same here.
        let z_offset = probe["z_offset"].as_f64().unwrap_or(0.0);
        let mut worst: (f64, String) = (0.0, String::new());
        let mut rows = Vec::new();
        for (ix, iy) in nodes {
            let (x, y) = (
                at(ix, xc, params.min_x, params.max_x),
                at(iy, yc, params.min_y, params.max_y),
            );
            let up = crate::klipper::GcodeCmd::new("G1")
                .axis('Z', 5.0)
                .axis('F', 600.0)
                .build()
                .map_err(|e| anyhow!("{e}"))?;
            let over = crate::klipper::GcodeCmd::new("G1")
                .axis('X', x - ox)
                .axis('Y', y - oy)
                .axis('F', 6000.0)
                .build()
                .map_err(|e| anyhow!("{e}"))?;
            self.core.m().gcode(&format!("G90\n{up}\n{over}")).await?;
            self.core
                .m()
                .gcode_within("PROBE", Duration::from_secs(120))
                .await?;
            let st = self
                .core
                .m()
                .objects_query(json!({"probe": ["last_z_result"]}))
                .await?;
            let z = st["probe"]["last_z_result"]
                .as_f64()
                .ok_or_else(|| anyhow!("probe gave no result"))?
                - z_offset;
            let want = predicted[iy * xc + ix];
            let diff = z - want;
            let label = format!("X{x:.1} Y{y:.1}");
            if diff.abs() > worst.0.abs() {
                worst = (diff, label.clone());
            }
            rows.push(json!({"x": x, "y": y, "probed_mm": z, "model_mm": want, "diff_mm": diff}));
        }
        let limit = self.settings.reference_limit_mm;
        let clamp_note = if (temp - t_model).abs() > 1e-9 {
            format!(" (frame {temp:.2} °C is outside the captured {lo:.2}–{hi:.2} °C: the model at {t_model:.2} °C was used)")
        } else {
            String::new()
        };
        if worst.0.abs() > limit {
            self.stop_following("the reference check failed").await;
            let msg = format!(
                "{TITLE} check: at {} the bed is {:+.3} mm from the model (limit {limit} mm, \
                 mesh.reference_limit_mm){clamp_note}: a swapped build plate or a loose probe? \
                 The print start is cancelled and following is off until a new KLIPCAL_MESH_CAPTURE",
                worst.1, worst.0
            );
            return Err(user(msg));
        }
        let msg = format!(
            "{TITLE} check passed: largest difference {:+.3} mm at {} (limit {limit} mm){clamp_note}",
            worst.0, worst.1
        );
        Ok(json!({"ok_check": true, "points": rows, "frame_c": temp, "message": msg}))
    }

    async fn cancel_session(&self, id: i64, reason: &str) -> anyhow::Result<Value> {
        self.core.stop_runner();
        let _ = self.core.heaters_off().await;
        // A BED_MESH_CALIBRATE still probing holds Klipper's G-code queue: the user's mesh goes
        // back once it ends, without holding up the answer.
        if let Ok(s) = self.core.load::<Session>(id) {
            let me = self.clone();
            self.core
                .spawn(async move { me.put_back_user_mesh(&s, true).await });
        }
        self.update(id, |s| {
            s.state = State::Cancelled;
            s.reason = Some(reason.to_string());
            s.progress = "cancelled; heaters off (meshes taken so far are kept)".into();
            Ok(())
        })
        .await?;
        Ok(json!({"session": id, "state": "cancelled",
                  "message": format!("thermal mesh session {id} cancelled ({reason}); heaters off")}))
    }

    fn session_status(&self, s: &Session) -> Value {
        let follow = self
            .follow_status
            .lock()
            .map(|v| v.clone())
            .unwrap_or(Value::Null);
        json!({
            "id": s.id,
            "state": s.state.name(),
            "progress": s.progress,
            "reason": s.reason,
            "meshes": s.captures.len(),
            "frame_c": s.captures.iter().map(|c| c.temps_c.iter().sum::<f64>() / c.temps_c.len().max(1) as f64).collect::<Vec<_>>(),
            "result": s.result,
            "notes": s.notes,
            "follow": follow,
        })
    }
}

/// The probe's section in Klipper's settings: `[probe]`, `[bltouch]`, `[smart_effector]`, an
/// eddy probe or another module's `[… probe]` — the first with a `z_offset`.
fn probe_settings(settings: &Value) -> Value {
    let Some(map) = settings.as_object() else {
        return Value::Null;
    };
    let is_probe = |name: &str| {
        name == "probe"
            || name == "bltouch"
            || name == "smart_effector"
            || name.starts_with("probe_eddy_current")
            || name.ends_with(" probe")
    };
    map.iter()
        .find(|(k, v)| is_probe(k) && v.get("z_offset").is_some())
        .map(|(_, v)| v.clone())
        .unwrap_or(Value::Null)
}

/// Klipper's own words in a refused G-code (Moonraker's message without the wrapping).
fn klipper_message(e: &crate::moonraker::Error) -> String {
    match e {
        crate::moonraker::Error::Rpc { message, .. } => message.trim().replace('\n', " "),
        other => other.to_string(),
    }
}

/// `klipcal_<T>` with T to 0.01 °C.
#[must_use]
pub fn profile_name(temp_c: f64) -> String {
    format!("{}{temp_c:.2}", bed_mesh::KLIPCAL_PREFIX)
}

/// The profile of a direction: `klipcal_<T>` while heating (or for one model in every
/// direction), `klipcal_cool_<T>` for the cooling model kept apart.
#[must_use]
pub fn direction_profile_name(phase: Phase, temp_c: f64) -> String {
    match phase {
        Phase::Heating => profile_name(temp_c),
        Phase::Cooling => format!("{}cool_{temp_c:.2}", bed_mesh::KLIPCAL_PREFIX),
    }
}

impl Calibration for Mesh {
    fn kind(&self) -> &'static str {
        KIND
    }

    fn title(&self) -> &'static str {
        "a thermal mesh capture"
    }

    fn ops(&self) -> Vec<&'static OpSpec> {
        crate::jobs::table::specs(OPS).collect()
    }

    fn call<'a>(
        &'a self,
        method: &'a str,
        args: &'a Value,
    ) -> BoxFuture<'a, anyhow::Result<Value>> {
        async move {
            match MeshCall::parse(method, args)? {
                MeshCall::Capture { bed_c } => self.capture(bed_c).await,
                MeshCall::Import => self.import().await,
                MeshCall::Follow { enable } => self.follow_cmd(enable).await,
                MeshCall::Check => self.check().await,
            }
        }
        .boxed()
    }

    fn resume<'a>(&'a self, row: &'a SessionRow) -> BoxFuture<'a, ()> {
        async move {
            let Ok(s) = self.core.load::<Session>(row.id) else {
                return;
            };
            if !s.state.is_final() {
                info!(session = s.id, state = %s.state.name(), "resuming thermal mesh session");
                self.spawn_runner(s.id);
            }
        }
        .boxed()
    }

    fn cancel<'a>(
        &'a self,
        row: &'a SessionRow,
        reason: &'a str,
    ) -> BoxFuture<'a, anyhow::Result<Value>> {
        self.cancel_session(row.id, reason).boxed()
    }

    fn status(&self, row: &SessionRow) -> anyhow::Result<Value> {
        let s: Session = serde_json::from_value(row.doc.clone())
            .with_context(|| format!("reading stored session {}", row.id))?;
        Ok(self.session_status(&s))
    }

    fn held(&self, row: &SessionRow) -> Option<Hold> {
        // The capture holds the bed hot for at most mesh.max_s from its start.
        let s: Session = serde_json::from_value(row.doc.clone()).ok()?;
        (s.state == State::Capturing).then_some(Hold {
            since_unix: s.started_unix?,
            max_s: s.options.max_s + 600.0,
        })
    }

    fn heaters_turned_off<'a>(&'a self, row: &'a SessionRow) -> BoxFuture<'a, ()> {
        async move {
            let _ = self
                .update(row.id, |s| {
                    s.notes
                        .push("heaters turned off: the capture ran past mesh.max_s".into());
                    Ok(())
                })
                .await;
        }
        .boxed()
    }

    fn connected(&self) -> BoxFuture<'_, ()> {
        async move {
            if self.settings.follow {
                if let Err(e) = self.follow_cmd(true).await {
                    warn!(error = %format!("{e:#}"), "mesh.follow is on but following cannot start");
                }
            }
        }
        .boxed()
    }
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
    fn each_point_gets_the_frame_temperature_of_its_moment_in_klippers_probe_order() {
        // 3×2 mesh probed over 5 s while the frame rose 1 °C/s: row 0 left→right, row 1
        // right→left (Klipper's zigzag).
        let samples: Vec<(f64, f64)> = (0..=5).map(|k| (k as f64, 30.0 + k as f64)).collect();
        let t = point_temps(&samples, 3, 2);
        assert_eq!(t, vec![30.0, 31.0, 32.0, 35.0, 34.0, 33.0]);
        assert!(point_temps(&[], 3, 2).iter().all(|v| v.is_nan()));
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
        Session {
            id: 1,
            state: State::Writing,
            reason: None,
            progress: String::new(),
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
            notes: Vec::new(),
            user_mesh: None,
            imported: false,
        }
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
