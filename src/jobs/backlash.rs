//! The guided backlash measurement (seed 004) through a nozzle camera: measuring → measured →
//! applying → done (and failed / cancelled, with the reason). KLIPCAL_BACKLASH_SET_POINT saves
//! the camera point once; KLIPCAL_BACKLASH_START AXIS=X|Y|Z|A|B [CYCLES=] runs
//! `calib::backlash_guide` with a prompt whose jog buttons (_KLIPCAL_BACKLASH_JOG PRESS=…) move
//! only in the approach direction, each step saved before the machine moves;
//! KLIPCAL_BACKLASH_APPLY sets the values (SET_BACKLASH_COMPENSATION with its reply checked on
//! PR 7259; PR 7157's `[backlash]` by config) and persists them through the shared config
//! transaction. Session store, runner, guards, console and config transaction are the core's.

use std::collections::BTreeMap;

use anyhow::{anyhow, Context};
use futures_util::future::BoxFuture;
use futures_util::FutureExt;
use serde::{Deserialize, Serialize};
use serde_json::{json, Value};

use super::console::{Button, Prompt};
use super::printer_config::{self, ValueSet};
use super::registry::{Calibration, Hold};
use super::session::{now_unix, Core, Doc};
use super::table::{arg, parse_call, ArgKind, Args, Op, OpSpec};
use super::user;
use crate::calib::backlash::{analyse, common_smooth_time_s, AxisResult, SEED_SMOOTH_TIME_S};
use crate::calib::backlash_guide::{Guide, GuideAxis, Phase, Press, Step};
use crate::config::BacklashConfig;
use crate::klipper::backlash::{self as kb, Branch, CarriageBacklash, Detection, SetBacklash};
use crate::klipper::GcodeCmd;
use crate::store::SessionRow;

pub mod camera;

/// The backlash measurement's operations, each declared once (see [`crate::jobs::table`]).
pub static OPS: &[Op<BacklashCall>] = &[
    Op {
        spec: OpSpec::remote(
            "klipcal_backlash_set_point",
            "KLIPCAL_BACKLASH_SET_POINT",
            "backlash/set_point",
            "save the current position (nozzle centred on the camera mark) as the backlash camera point",
            &[],
        ),
        parse: |_| Ok(BacklashCall::SetPoint),
    },
    Op {
        spec: OpSpec::remote(
            "klipcal_backlash_start",
            "KLIPCAL_BACKLASH_START",
            "backlash/start",
            "measure backlash through the nozzle camera, AXIS=X, Y, Z, or A/B (CoreXY motors), CYCLES=5, CARRIAGE=0|1 on dual_carriage",
            &[
                arg(
                    "axis",
                    ArgKind::Text,
                    "X",
                    "X, Y, Z, A or B",
                    "",
                    "the axis: X, Y, Z, or A/B (CoreXY motors)",
                ),
                arg(
                    "cycles",
                    ArgKind::Whole { min: 1, max: 50 },
                    "5",
                    "1..50",
                    "",
                    "approach cycles (default backlash.cycles)",
                ),
                arg(
                    "carriage",
                    ArgKind::Whole { min: 0, max: 1 },
                    "1",
                    "0 or 1",
                    "",
                    "the carriage on a dual_carriage printer",
                ),
            ],
        ),
        parse: |a| Ok(BacklashCall::Start(StartRequest::from_args(a)?)),
    },
    camera::OP,
    Op {
        spec: OpSpec::remote(
            "klipcal_backlash_jog",
            "_KLIPCAL_BACKLASH_JOG",
            "backlash/jog",
            "backlash prompt button, PRESS=coarse, fine, centred or overshot (moves only in the approach direction)",
            &[arg(
                "press",
                ArgKind::Text,
                "fine",
                "coarse, fine, centred or overshot",
                "",
                "coarse, fine, centred or overshot",
            )],
        ),
        parse: |a| {
            Press::parse(&a.text("press").unwrap_or_default())
                .map(BacklashCall::Jog)
                .map_err(|e| user(e.to_string()))
        },
    },
    Op {
        spec: OpSpec::remote(
            "klipcal_backlash_apply",
            "KLIPCAL_BACKLASH_APPLY",
            "backlash/apply",
            "set the measured backlash compensation and write it to the config (backup, restart, verify)",
            &[],
        ),
        parse: |_| Ok(BacklashCall::Apply),
    },
];

/// A backlash call, typed at the boundary.
#[derive(Debug, Clone, PartialEq)]
pub enum BacklashCall {
    /// `klipcal_backlash_set_point`.
    SetPoint,
    /// `klipcal_backlash_start`.
    Start(StartRequest),
    /// `klipcal_backlash_jog`.
    Jog(Press),
    /// `klipcal_backlash_camera`.
    Camera(camera::CameraRequest),
    /// `klipcal_backlash_apply`.
    Apply,
}

impl BacklashCall {
    /// Reads a call of `method` at the boundary.
    ///
    /// # Errors
    /// An unknown method, or a bad or unknown argument, named.
    pub fn parse(method: &str, args: &Value) -> anyhow::Result<Self> {
        parse_call(OPS, method, args)
    }
}

/// `klipcal_backlash_start` / `KLIPCAL_BACKLASH_START`.
#[derive(Debug, Clone, PartialEq)]
pub struct StartRequest {
    /// The axis measured.
    pub axis: GuideAxis,
    /// Approach cycles, when given.
    pub cycles: Option<usize>,
    /// The dual_carriage carriage, when given.
    pub carriage: Option<i64>,
}

impl StartRequest {
    /// Reads the call's arguments.
    ///
    /// # Errors
    /// No or a bad axis, bad cycles or carriage.
    pub fn from_args(a: &Args) -> anyhow::Result<Self> {
        let carriage = a.int("carriage")?;
        let axis_text = a.text("axis").ok_or_else(|| {
            user("KLIPCAL_BACKLASH_START: AXIS is required; expected X, Y, Z, A or B")
        })?;
        let axis = GuideAxis::parse(&axis_text).map_err(|e| user(e.to_string()))?;
        let cycles = a
            .int("cycles")?
            .map(|c| usize::try_from(c).map_err(|_| user(format!("CYCLES={c}: expected 1..50"))))
            .transpose()?;
        Ok(Self {
            axis,
            cycles,
            carriage,
        })
    }
}

/// The store's kind.
pub const KIND: &str = "backlash";
/// The store's kind of the saved camera point (a finished document, one per SET_POINT).
pub const POINT_KIND: &str = "backlash_point";
const TITLE: &str = "backlash measurement";
/// Jog and approach feed rate, mm/min.
const JOG_F: f64 = 1200.0;

/// A session's state.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum State {
    /// The guided procedure runs for `axis`.
    Measuring,
    /// Every cycle of the last axis is in; another axis may start, or apply.
    Measured,
    /// Setting and writing the values.
    Applying,
    /// Applied (or nothing to apply).
    Done,
    /// Failed, with the reason.
    Failed,
    /// Cancelled, with the reason.
    Cancelled,
}

impl State {
    fn name(self) -> &'static str {
        match self {
            State::Measuring => "measuring",
            State::Measured => "measured",
            State::Applying => "applying",
            State::Done => "done",
            State::Failed => "failed",
            State::Cancelled => "cancelled",
        }
    }
}

/// The stored session.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct Session {
    /// Session id.
    pub id: i64,
    /// State.
    pub state: State,
    /// Why it failed or was cancelled.
    pub reason: Option<String>,
    /// The current step in words.
    pub progress: String,
    /// The camera point (toolhead X, Y, Z).
    pub point: [f64; 3],
    /// What the printer's Klipper has.
    pub detection: Detection,
    /// The compensation active while measuring, per axis (measurements are residuals).
    pub active_mm: BTreeMap<String, f64>,
    /// The procedure in progress (its readings included).
    pub guide: Option<Guide>,
    /// Finished axes: their cycles.
    pub cycles: BTreeMap<String, Vec<crate::calib::backlash::Cycle>>,
    /// [printer] max_accel, mm/s².
    pub max_accel_mm_s2: Option<f64>,
    /// The dual carriage selected for the axis in progress (`SET_DUAL_CARRIAGE CARRIAGE=`);
    /// its results are kept as `<axis>@<carriage>`, e.g. `x@1`.
    #[serde(default)]
    pub carriage: Option<u32>,
    /// `[printer] kinematics`, for the CoreXY answer.
    #[serde(default)]
    pub kinematics: String,
    /// Things the user should know.
    pub notes: Vec<String>,
    /// Axes read through the nozzle camera (KLIPCAL_BACKLASH_CAMERA): how, per result key.
    #[serde(default)]
    pub camera: BTreeMap<String, camera::CameraReport>,
}

impl Doc for Session {
    fn state_name(&self) -> String {
        self.state.name().to_string()
    }
}

#[derive(Debug, Clone, Serialize, Deserialize)]
struct PointDoc {
    point: [f64; 3],
    state: String,
}

impl Doc for PointDoc {
    fn state_name(&self) -> String {
        self.state.clone()
    }
}

/// The backlash calibration.
pub struct Backlash {
    core: Core,
    settings: BacklashConfig,
}

impl Backlash {
    /// Over the shared core, with `[backlash]`.
    pub fn new(core: Core, settings: BacklashConfig) -> Self {
        Self { core, settings }
    }

    fn active(&self) -> anyhow::Result<Option<Session>> {
        Ok(self.core.active_of::<Session>(KIND)?.map(|(_, s)| s))
    }

    async fn detect(&self) -> anyhow::Result<(Detection, Value)> {
        let help = self.core.m().call("printer.gcode.help", json!({})).await?;
        let cf = self.core.m().configfile().await?;
        Ok((kb::detect(&help, &cf["config"])?, cf))
    }

    /// The G-code console lines since the last call, newest last (for command replies).
    async fn console_tail(&self) -> anyhow::Result<String> {
        let store = self
            .core
            .m()
            .call("server.gcode_store", json!({"count": 30}))
            .await?;
        Ok(store["gcode_store"]
            .as_array()
            .into_iter()
            .flatten()
            .filter_map(|e| e["message"].as_str())
            .collect::<Vec<_>>()
            .join("\n"))
    }

    /// PR 7259's values now: the bare command's reply.
    async fn seed_values(&self) -> anyhow::Result<kb::BacklashReply> {
        self.core.m().gcode(kb::SET_CMD).await?;
        Ok(kb::parse_reply(&self.console_tail().await?)?)
    }

    async fn homed(&self, axis: GuideAxis) -> anyhow::Result<()> {
        let st = self
            .core
            .m()
            .objects_query(json!({"toolhead": ["homed_axes"]}))
            .await?;
        let homed = st["toolhead"]["homed_axes"].as_str().unwrap_or("");
        let need = match axis {
            GuideAxis::Z => "xyz",
            _ => "xy",
        };
        if need.chars().all(|c| homed.contains(c)) {
            Ok(())
        } else {
            Err(user(format!(
                "the printer is not homed ({need} needed, homed: '{homed}'); run G28 first"
            )))
        }
    }

    async fn move_along(&self, s: &Session, step: &Step) -> anyhow::Result<()> {
        let Some(g) = &s.guide else { return Ok(()) };
        for &along in &step.moves_mm {
            let p = g.axis.point_at(s.point, along);
            let line = GcodeCmd::new("G1")
                .axis('X', p[0])
                .axis('Y', p[1])
                .axis('Z', p[2])
                .axis('F', JOG_F)
                .build()?;
            self.core.m().gcode(&format!("G90\n{line}")).await?;
        }
        Ok(())
    }

    fn prompt_for(s: &Session, step: &Step) -> Prompt {
        let Some(g) = &s.guide else {
            return Prompt::default();
        };
        let (sign, dir) = if step.phase == Phase::Minus {
            ("-", "−")
        } else {
            ("+", "+")
        };
        let axis = g.axis.name().to_uppercase();
        Prompt {
            title: title_for(&axis, dir, s.carriage, step.cycle, g.params.cycles),
            lines: vec![
                format!(
                    "Jog {axis}{sign} until the nozzle is centred on the camera mark; never back."
                ),
                format!(
                    "Coarse {} mm, fine {} mm. Past the centre? Press Overshot: it starts the approach over from {} mm back.",
                    g.params.coarse_mm,
                    g.fine_mm(),
                    g.params.approach_mm
                ),
            ],
            buttons: vec![
                Button::new(
                    &format!("Coarse {axis}{sign}"),
                    "_KLIPCAL_BACKLASH_JOG PRESS=coarse",
                    "secondary",
                ),
                Button::new(
                    &format!("Fine {axis}{sign}"),
                    "_KLIPCAL_BACKLASH_JOG PRESS=fine",
                    "secondary",
                ),
                Button::new("Centred", "_KLIPCAL_BACKLASH_JOG PRESS=centred", "primary"),
                Button::new(
                    "Overshot - start over",
                    "_KLIPCAL_BACKLASH_JOG PRESS=overshot",
                    "warning",
                ),
            ],
            footer: vec![Button::cancel_asking()],
        }
    }

    fn results(&self, s: &Session) -> anyhow::Result<BTreeMap<String, AxisResult>> {
        let params = self.settings.params();
        s.cycles
            .iter()
            .map(|(axis, c)| {
                // Camera cycles are read to the camera's precision, not a jog's.
                let p = s
                    .camera
                    .get(axis)
                    .map_or(params.clone(), |r| r.params(&params));
                Ok((axis.clone(), analyse(axis, c, s.max_accel_mm_s2, &p)?))
            })
            .collect()
    }

    fn result_lines(&self, s: &Session) -> anyhow::Result<Vec<String>> {
        let mut out = Vec::new();
        let results = self.results(s)?;
        let corexy = Self::corexy_answer(s, &results);
        for (axis, r) in results {
            let active = s.active_mm.get(&axis).copied().unwrap_or(0.0);
            out.push(format!(
                "{}: {:.4} mm ± {:.4} over {} cycles{}{} — {}",
                key_words(&axis),
                r.backlash_mm,
                r.uncertainty_mm,
                r.cycles,
                if r.outliers.is_empty() {
                    String::new()
                } else {
                    format!(" (outlier cycles {:?})", r.outliers)
                },
                if active > 0.0 {
                    format!(" left with {active} mm compensation active")
                } else {
                    String::new()
                },
                if r.compensate {
                    format!(
                        "compensate; smooth_time {:.4} s adds {:.0} mm/s²",
                        r.smooth_time_s, r.extra_accel_mm_s2
                    )
                } else {
                    "no compensation needed".to_string()
                }
            ));
        }
        if let Some(t) = corexy {
            out.push(format!("CoreXY, x_backlash = y_backlash? {t}"));
        }
        Ok(out)
    }

    /// The seed's CoreXY question answered from the results (CoreXY printers only).
    fn corexy_answer(s: &Session, results: &BTreeMap<String, AxisResult>) -> Option<String> {
        (s.kinematics == "corexy")
            .then(|| crate::calib::backlash::corexy_xy_answer(results))
            .flatten()
    }

    /// `klipcal_backlash_set_point`: the current toolhead position becomes the camera point.
    ///
    /// # Errors
    /// A printer that is printing or not homed.
    pub async fn set_point(&self) -> anyhow::Result<Value> {
        self.core.printer_idle().await?;
        self.homed(GuideAxis::X).await?;
        let st = self
            .core
            .m()
            .objects_query(json!({"gcode_move": ["position"]}))
            .await?;
        let pos = &st["gcode_move"]["position"];
        let p = [0, 1, 2].map(|i| pos[i].as_f64().unwrap_or(f64::NAN));
        if p.iter().any(|v| !v.is_finite()) {
            return Err(anyhow!("Klipper reports no toolhead position: {pos}"));
        }
        let doc = PointDoc {
            point: p,
            state: "done".into(),
        };
        self.core
            .store()
            .create_session(POINT_KIND, "done", &serde_json::to_value(&doc)?)?;
        let msg = format!(
            "camera point saved: X{:.3} Y{:.3} Z{:.3}; KLIPCAL_BACKLASH_START AXIS=X begins",
            p[0], p[1], p[2]
        );
        Ok(json!({"point": p, "message": msg}))
    }

    /// `klipcal_backlash_start`: measures one axis (a new session, or the next axis of a
    /// measured one).
    ///
    /// # Errors
    /// Bad arguments, no camera point, another calibration running, a printing or unhomed
    /// printer, or A/B on a printer that is not CoreXY.
    pub async fn start(&self, req: &StartRequest) -> anyhow::Result<Value> {
        let carriage_arg = req.carriage;
        let axis = req.axis;
        let mut params = self.settings.guide();
        if let Some(c) = req.cycles {
            params.cycles = c;
        }
        params.validate().map_err(|e| user(e.to_string()))?;
        self.core.refuse_other_kind(KIND)?;
        self.core.printer_idle().await?;
        self.homed(axis).await?;
        let point = self
            .core
            .latest_of::<PointDoc>(POINT_KIND)?
            .map(|(_, d)| d.point)
            .ok_or_else(|| {
                user("no camera point saved: centre the nozzle on the camera mark, then KLIPCAL_BACKLASH_SET_POINT")
            })?;
        let (detection, cf) = self.detect().await?;
        let kin = cf["settings"]["printer"]["kinematics"]
            .as_str()
            .unwrap_or("");
        if axis.is_motor() && kin != "corexy" {
            return Err(user(format!(
                "AXIS={} is a CoreXY motor direction; this printer's kinematics is {kin}",
                axis.name().to_uppercase()
            )));
        }
        let max_accel = cf["settings"]["printer"]["max_accel"].as_f64();
        let carriage = self
            .carriage_for(&detection, &cf, axis, carriage_arg)
            .await?;
        if let Some(n) = carriage {
            self.park_and_select(n).await?;
        }
        let key = result_key(axis, carriage);
        let mut active_mm = BTreeMap::new();
        match detection.branch {
            Branch::Seed => {
                let r = self.seed_values().await?;
                active_mm.insert("x".into(), r.x_mm);
                active_mm.insert("y".into(), r.y_mm);
                active_mm.insert("z".into(), r.z_mm);
                if carriage.is_some() {
                    let own = match axis {
                        GuideAxis::Y => r.y_mm,
                        _ => r.x_mm,
                    };
                    active_mm.insert(key.clone(), own);
                }
            }
            Branch::Pr7157 { .. } => {
                if let Some(o) = cf["settings"]["backlash"].as_object() {
                    for (k, v) in o {
                        if let Some(f) = v.as_f64() {
                            active_mm.insert(k.clone(), f);
                        }
                    }
                }
            }
            Branch::Neither => {}
        }
        let (guide, step) =
            Guide::start(axis, axis.coord(point), params).map_err(|e| user(e.to_string()))?;
        let existing = {
            let _g = self.core.lock().await;
            match self.active()? {
                Some(mut s) if s.state == State::Measured => {
                    s.state = State::Measuring;
                    s.progress = format!("measuring {}", axis.name());
                    s.guide = Some(guide.clone());
                    s.point = point;
                    s.detection = detection.clone();
                    s.active_mm.extend(active_mm.clone());
                    s.carriage = carriage;
                    s.kinematics = kin.to_string();
                    self.core.save(s.id, &s)?;
                    Some(s)
                }
                Some(s) => {
                    return Err(user(format!(
                        "session {} is {}; finish the axis in progress or KLIPCAL_CANCEL",
                        s.id,
                        s.state.name()
                    )))
                }
                None => None,
            }
        };
        let s = match existing {
            Some(s) => s,
            None => {
                let mut s = Session {
                    id: 0,
                    state: State::Measuring,
                    reason: None,
                    progress: format!("measuring {}", axis.name()),
                    point,
                    detection,
                    active_mm,
                    guide: Some(guide),
                    cycles: BTreeMap::new(),
                    max_accel_mm_s2: max_accel,
                    notes: Vec::new(),
                    carriage,
                    kinematics: kin.to_string(),
                    camera: BTreeMap::new(),
                };
                s.id = self.core.create(KIND, &mut s, |s, id| s.id = id).await?;
                s
            }
        };
        self.move_along(&s, &step).await?;
        self.core.prompt(&Self::prompt_for(&s, &step)).await;
        let msg = format!(
            "{TITLE} session {}: {} from {} mm in −, jog only in + until centred",
            s.id,
            key_words(&key),
            s.guide.as_ref().map_or(1.0, |g| g.params.approach_mm)
        );
        Ok(
            json!({"session": s.id, "state": "measuring", "axis": axis.name(), "carriage": carriage, "message": msg}),
        )
    }

    /// `klipcal_backlash_jog PRESS=coarse|fine|centred|overshot`.
    ///
    /// # Errors
    /// No axis being measured, a bad PRESS, or a jog the procedure refuses (said why).
    pub async fn jog(&self, press: Press) -> anyhow::Result<Value> {
        // The press and its reading are saved before the machine moves.
        let (s, step) = {
            let _g = self.core.lock().await;
            let mut s =
                match self.active()? {
                    Some(s) if s.state == State::Measuring => s,
                    _ => return Err(user(
                        "no backlash axis is being measured; KLIPCAL_BACKLASH_START AXIS=X first",
                    )),
                };
            let g = s
                .guide
                .as_mut()
                .ok_or_else(|| anyhow!("measuring without a guide"))?;
            let step = g.press(press).map_err(|e| user(e.to_string()))?;
            if step.phase == Phase::Done {
                let key = result_key(g.axis, s.carriage);
                let cycles = g.cycles.clone();
                s.cycles.insert(key.clone(), cycles);
                s.camera.remove(&key);
                s.guide = None;
                s.carriage = None;
                s.state = State::Measured;
                s.progress = format!(
                    "{} measured; start another axis or KLIPCAL_BACKLASH_APPLY",
                    key_words(&key)
                );
            }
            self.core.save(s.id, &s)?;
            (s, step)
        };
        if step.phase == Phase::Done {
            self.core.prompt_end().await;
            let lines = self.result_lines(&s)?;
            let text = format!(
                "{TITLE}: {}\nnext: KLIPCAL_BACKLASH_START AXIS=… for another axis, or KLIPCAL_BACKLASH_APPLY",
                lines.join("\n")
            );
            return Ok(
                json!({"session": s.id, "state": "measured", "results": self.results(&s)?, "message": text}),
            );
        }
        self.move_along(&s, &step).await?;
        self.core.prompt(&Self::prompt_for(&s, &step)).await;
        // A jog answers nothing on the console (the camera shows it); a recorded position and a
        // new approach are said in one line.
        let message = match (step.recorded, press) {
            (Some(v), _) => format!(
                "{TITLE}: {v:.4} mm recorded; now cycle {}, moving only {}",
                step.cycle,
                if step.phase == Phase::Minus {
                    "−"
                } else {
                    "+"
                }
            ),
            (None, Press::Overshot) => format!(
                "{TITLE}: approaching again from {} mm back",
                s.guide.as_ref().map_or(1.0, |g| g.params.approach_mm)
            ),
            (None, _) => String::new(),
        };
        Ok(
            json!({"session": s.id, "state": "measuring", "recorded": step.recorded,
                  "phase": format!("{:?}", step.phase), "cycle": step.cycle, "message": message}),
        )
    }

    /// `klipcal_backlash_apply`: sets and persists the measured values.
    ///
    /// # Errors
    /// Nothing measured, a printer printing, neither branch (with the reason), a reply that
    /// disagrees, or a config Klipper rejects (rolled back).
    pub async fn apply(&self) -> anyhow::Result<Value> {
        let s = match self.active()? {
            Some(s) if s.state == State::Measured => s,
            _ => {
                return Err(user(
                    "nothing measured to apply; measure an axis first (KLIPCAL_BACKLASH_START)",
                ))
            }
        };
        self.core.printer_idle().await?;
        let (detection, _) = self.detect().await?;
        if !detection.can_apply() {
            return Err(user(format!("cannot apply: {}", detection.why)));
        }
        let results = self.results(&s)?;
        let mut values: BTreeMap<String, f64> = BTreeMap::new();
        for (axis, r) in &results {
            let active = s.active_mm.get(axis).copied().unwrap_or(0.0);
            if r.compensate || active > 0.0 {
                values.insert(axis.clone(), round_um(active + r.backlash_mm));
            }
        }
        if values.is_empty() {
            self.finish(
                s.id,
                State::Done,
                "nothing to apply: no axis needs compensation",
            )
            .await?;
            return Ok(
                json!({"session": s.id, "state": "done", "message": "no axis needs compensation; nothing written"}),
            );
        }
        let smooth =
            (detection.branch == Branch::Seed).then(|| common_smooth_time_s(results.values()));
        if detection.dual_carriage && detection.branch == Branch::Seed {
            return self
                .apply_dual(&s, &values, smooth.unwrap_or(SEED_SMOOTH_TIME_S))
                .await;
        }
        if let Some(k) = values.keys().find(|k| k.contains('@')) {
            return Err(user(format!(
                "{} was measured for a dual carriage, but this printer's config has no \
                 [dual_carriage] now; measure again",
                key_words(k)
            )));
        }
        let triples = kb::config_values(detection.branch, &values, smooth)
            .map_err(|e| user(e.to_string()))?;
        self.set_state(s.id, State::Applying, "applying").await?;
        let outcome = self
            .apply_values(&detection, &values, smooth, &triples)
            .await;
        self.settle(s.id, &values, smooth, outcome).await
    }

    /// Ends an apply: done with the message, or back to measured with the reason.
    async fn settle(
        &self,
        id: i64,
        values: &BTreeMap<String, f64>,
        smooth: Option<f64>,
        outcome: anyhow::Result<String>,
    ) -> anyhow::Result<Value> {
        match outcome {
            Ok(msg) => {
                self.finish(id, State::Done, &msg).await?;
                self.core.console(&format!("{TITLE}: {msg}")).await;
                Ok(
                    json!({"session": id, "state": "done", "values": values, "smooth_time_s": smooth, "message": msg}),
                )
            }
            Err(e) => {
                let why = format!("{e:#}");
                self.set_state(id, State::Measured, &format!("apply failed: {why}"))
                    .await?;
                self.core
                    .console_error(&format!("{TITLE}: apply failed: {why}"))
                    .await;
                Err(e)
            }
        }
    }

    async fn apply_values(
        &self,
        detection: &Detection,
        values: &BTreeMap<String, f64>,
        smooth: Option<f64>,
        triples: &[(String, String, String)],
    ) -> anyhow::Result<String> {
        let get = |k: &str| values.get(k).copied();
        let want = SetBacklash {
            x_mm: get("x"),
            y_mm: get("y"),
            z_mm: get("z"),
            smooth_time_s: smooth,
        };
        if detection.branch == Branch::Seed {
            self.set_checked(&want).await?;
        }
        let pc = printer_config::fetch(self.core.m(), self.core.files()).await?;
        let sets: Vec<ValueSet> = triples
            .iter()
            .map(|(section, key, value)| ValueSet {
                section: section.clone(),
                key: key.clone(),
                value: value.clone(),
            })
            .collect();
        let stamp = printer_config::stamp(now_unix() as u64);
        let report =
            printer_config::apply(self.core.m(), self.core.files(), &pc, &sets, &stamp).await?;
        if detection.branch == Branch::Seed {
            let after = self.seed_values().await?;
            if !after.agrees_with(&want) {
                return Err(anyhow!(
                    "after the restart SET_BACKLASH_COMPENSATION reports {after:?}, not the values written"
                ));
            }
        }
        Ok(format!(
            "written {} (backup in {})",
            report
                .changes
                .iter()
                .map(|(s, k, o, n)| format!("[{s}] {k}: {o} → {n}"))
                .collect::<Vec<_>>()
                .join(", "),
            report.backup_dir
        ))
    }

    /// The carriage an axis is measured on: `None` without a `[dual_carriage]` or for an axis
    /// both carriages share; else CARRIAGE (0 or 1), or the carriage active now.
    async fn carriage_for(
        &self,
        detection: &Detection,
        cf: &Value,
        axis: GuideAxis,
        asked: Option<i64>,
    ) -> anyhow::Result<Option<u32>> {
        if !detection.dual_carriage {
            return match asked {
                Some(n) => Err(user(format!(
                    "CARRIAGE={n}: this printer's config has no [dual_carriage]; leave CARRIAGE out"
                ))),
                None => Ok(None),
            };
        }
        let dc_axis = cf["settings"]["dual_carriage"]["axis"]
            .as_str()
            .unwrap_or("x")
            .to_ascii_lowercase();
        if axis.name() != dc_axis {
            return match asked {
                Some(n) => Err(user(format!(
                    "CARRIAGE={n}: only {} has two carriages; {} is shared by both, leave \
                     CARRIAGE out",
                    dc_axis.to_uppercase(),
                    axis.name().to_uppercase()
                ))),
                None => Ok(None),
            };
        }
        match asked {
            Some(n @ 0..=1) => Ok(Some(n as u32)),
            Some(n) => Err(user(format!(
                "CARRIAGE={n}: expected 0 or 1, the carriages SET_DUAL_CARRIAGE selects"
            ))),
            None => Ok(Some(self.active_carriage().await?)),
        }
    }

    /// The dual carriage Klipper moves now (`dual_carriage` status: `PRIMARY`).
    async fn active_carriage(&self) -> anyhow::Result<u32> {
        let st = self
            .core
            .m()
            .objects_query(json!({"dual_carriage": null}))
            .await?;
        let dc = &st["dual_carriage"];
        Ok(
            if dc["carriage_1"] == "PRIMARY" && dc["carriage_0"] != "PRIMARY" {
                1
            } else {
                0
            },
        )
    }

    async fn select_carriage(&self, n: u32) -> anyhow::Result<()> {
        let cmd = GcodeCmd::new("SET_DUAL_CARRIAGE")
            .word("CARRIAGE", &n.to_string())
            .build()?;
        self.core
            .m()
            .gcode(&cmd)
            .await
            .with_context(|| format!("selecting carriage {n} ({cmd})"))
    }

    /// Selects carriage `n` to be measured, the other first parked where it homes (a
    /// carriage may not pass the inactive one, so the camera point is reachable only with
    /// the other out of the way; Klipper's IDEX examples park the same way).
    async fn park_and_select(&self, n: u32) -> anyhow::Result<()> {
        let cf = self.core.m().configfile().await?;
        let other = 1 - n.min(1);
        let axis = cf["settings"]["dual_carriage"]["axis"]
            .as_str()
            .unwrap_or("x")
            .to_ascii_lowercase();
        let section = if other == 0 {
            format!("stepper_{axis}")
        } else {
            "dual_carriage".to_string()
        };
        let park = cf["settings"][section.as_str()]["position_endstop"]
            .as_f64()
            .ok_or_else(|| {
                anyhow!("[{section}] has no position_endstop to park carriage {other} at")
            })?;
        self.select_carriage(other).await?;
        let line = GcodeCmd::new("G1")
            .axis(if axis == "y" { 'Y' } else { 'X' }, park)
            .axis('F', JOG_F * 5.0)
            .build()?;
        self.core
            .m()
            .gcode(&format!("G90\n{line}"))
            .await
            .with_context(|| format!("parking carriage {other} ({line})"))?;
        self.select_carriage(n).await
    }

    /// `SET_BACKLASH_COMPENSATION` with `want`, refused unless Klipper's reply agrees.
    async fn set_checked(&self, want: &SetBacklash) -> anyhow::Result<()> {
        let cmd = kb::set_backlash_command(want)?;
        self.core
            .m()
            .gcode(&cmd)
            .await
            .context("SET_BACKLASH_COMPENSATION")?;
        let reply = kb::parse_reply(&self.console_tail().await?)?;
        if !reply.agrees_with(want) {
            return Err(anyhow!("Klipper answered {reply:?} to {cmd}"));
        }
        Ok(())
    }

    /// Each carriage's values as PR 7259 reports them (the active carriage selected again).
    async fn carriage_values(&self) -> anyhow::Result<[kb::BacklashReply; 2]> {
        let was = self.active_carriage().await?;
        let mut out = Vec::with_capacity(2);
        for n in 0..2 {
            self.select_carriage(n).await?;
            out.push(self.seed_values().await?);
        }
        self.select_carriage(was).await?;
        let [a, b]: [kb::BacklashReply; 2] = out
            .try_into()
            .map_err(|_| anyhow!("two carriages expected"))?;
        Ok([a, b])
    }

    /// Dual carriage with PR 7259 (the seed's recipe): non-zero values cannot sit in
    /// `[backlash_compensation]`, so each carriage's values are set at run time with the
    /// reply checked, then written into klipcal's `[delayed_gcode]` include (created and
    /// included on first use) through the config transaction, verified per carriage after
    /// the restart. Values not measured now stay as Klipper runs them.
    async fn apply_dual(
        &self,
        s: &Session,
        values: &BTreeMap<String, f64>,
        smooth_s: f64,
    ) -> anyhow::Result<Value> {
        let (_, cf) = self.detect().await?;
        let dc_axis = cf["settings"]["dual_carriage"]["axis"]
            .as_str()
            .unwrap_or("x")
            .to_ascii_lowercase();
        if let Some(k) = values.keys().find(|k| k.as_str() == dc_axis.as_str()) {
            return Err(user(format!(
                "{} was measured without naming a carriage; measure it again with \
                 KLIPCAL_BACKLASH_START AXIS={} CARRIAGE=0 (and 1)",
                key_words(k),
                dc_axis.to_uppercase()
            )));
        }
        self.set_state(s.id, State::Applying, "applying").await?;
        let outcome = self.apply_dual_values(values, smooth_s, &dc_axis).await;
        self.settle(s.id, values, Some(smooth_s), outcome).await
    }

    async fn apply_dual_values(
        &self,
        values: &BTreeMap<String, f64>,
        smooth_s: f64,
        dc_axis: &str,
    ) -> anyhow::Result<String> {
        let now = self.carriage_values().await?;
        let pick = |n: u32, axis: &str, current: f64| -> f64 {
            let own = if axis == dc_axis {
                values.get(&format!("{axis}@{n}"))
            } else {
                values.get(axis)
            };
            own.copied().unwrap_or(current)
        };
        let wanted: Vec<CarriageBacklash> = (0..2u32)
            .map(|n| {
                let r = &now[n as usize];
                CarriageBacklash {
                    carriage: n.to_string(),
                    values: SetBacklash {
                        x_mm: Some(pick(n, "x", r.x_mm)),
                        y_mm: Some(pick(n, "y", r.y_mm)),
                        z_mm: Some(pick(n, "z", r.z_mm)),
                        smooth_time_s: Some(smooth_s),
                    },
                }
            })
            .collect();
        // At run time first, each reply checked; the carriage active before selected again.
        let was = self.active_carriage().await?;
        for c in &wanted {
            self.select_carriage(c.carriage.parse()?).await?;
            self.set_checked(&c.values)
                .await
                .with_context(|| format!("carriage {}", c.carriage))?;
        }
        self.select_carriage(was).await?;
        // Then the include, through the config transaction.
        let include = kb::dual_carriage_include(&wanted[0], &wanted[1])?;
        let pc = printer_config::fetch(self.core.m(), self.core.files()).await?;
        let main = pc
            .config
            .files()
            .first()
            .ok_or_else(|| anyhow!("the config has no files"))?;
        let main_rel = pc.rel(&main.path)?;
        let dir = main_rel.rsplit_once('/').map_or("", |(d, _)| d);
        let inc_rel = if dir.is_empty() {
            kb::DUAL_CARRIAGE_INCLUDE.to_string()
        } else {
            format!("{dir}/{}", kb::DUAL_CARRIAGE_INCLUDE)
        };
        let included = pc
            .config
            .files()
            .iter()
            .any(|f| pc.rel(&f.path).ok().as_deref() == Some(inc_rel.as_str()));
        // A stale include not read now is still put back as it was on a rollback.
        let old_inc = match self.core.files().download("config", &inc_rel).await {
            Ok(b) => Some(b),
            Err(e) if e.to_string().contains("404") => None,
            Err(e) => return Err(e).context(format!("reading {inc_rel}")),
        };
        let mut writes = vec![printer_config::FileWrite {
            rel: inc_rel.clone(),
            old: old_inc,
            new: include.into_bytes(),
        }];
        if !included {
            writes.push(printer_config::FileWrite {
                rel: main_rel.clone(),
                old: Some(main.text.clone().into_bytes()),
                new: crate::klipper::add_include(
                    &main.text,
                    kb::DUAL_CARRIAGE_INCLUDE,
                    "klipcal: per-carriage backlash compensation (dual_carriage, PR 7259)",
                )
                .into_bytes(),
            });
        }
        let stamp = printer_config::stamp(now_unix() as u64);
        let backup_dir = format!("klipcal_backups/{stamp}");
        printer_config::transact(
            self.core.m(),
            self.core.files(),
            &writes,
            &backup_dir,
            "FIRMWARE_RESTART",
            || async {
                // The [delayed_gcode] runs 0.1 s after ready.
                tokio::time::sleep(std::time::Duration::from_millis(1500)).await;
                let after = self.carriage_values().await?;
                for (c, got) in wanted.iter().zip(after.iter()) {
                    if !got.agrees_with(&c.values) {
                        return Ok(Some(format!(
                            "after the restart carriage {} reports {got:?}, not the values \
                             written to {inc_rel}",
                            c.carriage
                        )));
                    }
                }
                Ok(None)
            },
        )
        .await?;
        Ok(format!(
            "{} written to {inc_rel}{} (backup in {backup_dir}); {}",
            wanted
                .iter()
                .map(|c| format!(
                    "carriage {}: X {} Y {} Z {} mm",
                    c.carriage,
                    c.values.x_mm.unwrap_or(0.0),
                    c.values.y_mm.unwrap_or(0.0),
                    c.values.z_mm.unwrap_or(0.0)
                ))
                .collect::<Vec<_>>()
                .join(", "),
            if included {
                String::new()
            } else {
                format!(", included from {main_rel}")
            },
            format_args!("smooth_time {smooth_s} s")
        ))
    }

    async fn set_state(&self, id: i64, state: State, progress: &str) -> anyhow::Result<()> {
        self.core
            .update::<Session, ()>(id, |s| {
                s.state = state;
                s.progress = progress.to_string();
                Ok(())
            })
            .await
    }

    async fn finish(&self, id: i64, state: State, why: &str) -> anyhow::Result<()> {
        self.core
            .update::<Session, ()>(id, |s| {
                s.state = state;
                s.progress = why.to_string();
                if state != State::Done {
                    s.reason = Some(why.to_string());
                }
                Ok(())
            })
            .await
    }

    async fn resume_session(&self, id: i64) {
        let Ok(s) = self.core.load::<Session>(id) else {
            return;
        };
        match s.state {
            State::Measuring if s.guide.is_none() => self.camera_interrupted(&s).await,
            State::Measuring => {
                // Position and last direction are unknown after a restart: start the approach
                // over from 1 mm back (the readings taken so far are kept).
                let mut s2 = s.clone();
                let Some(g) = s2.guide.as_mut() else { return };
                let step = g.resume();
                let axis = g.axis;
                if self.core.save(id, &s2).is_err() {
                    return;
                }
                if self.homed(axis).await.is_err() {
                    self.core
                        .console(&format!(
                            "{TITLE} session {id}: home (G28), then _KLIPCAL_BACKLASH_JOG PRESS=overshot to continue"
                        ))
                        .await;
                    return;
                }
                if let Some(n) = s2.carriage {
                    if self.park_and_select(n).await.is_err() {
                        return;
                    }
                }
                if self.move_along(&s2, &step).await.is_ok() {
                    self.core.prompt(&Self::prompt_for(&s2, &step)).await;
                }
            }
            State::Applying => {
                let _ = self
                    .finish(
                        id,
                        State::Measured,
                        "apply interrupted; KLIPCAL_BACKLASH_APPLY again",
                    )
                    .await;
            }
            _ => {}
        }
    }

    async fn cancel_session(&self, id: i64, reason: &str) -> anyhow::Result<Value> {
        self.finish(id, State::Cancelled, reason).await?;
        self.core.prompt_end().await;
        Ok(json!({"session": id, "state": "cancelled",
                  "message": format!("backlash session {id} cancelled ({reason})")}))
    }
}

/// Where an axis's cycles are kept: `x`, or `x@1` for dual carriage 1's X.
fn result_key(axis: GuideAxis, carriage: Option<u32>) -> String {
    match carriage {
        Some(n) => format!("{}@{n}", axis.name()),
        None => axis.name().to_string(),
    }
}

/// A result key in words: `X`, `X (carriage 1)`.
/// A jog dialog's title, what matters first: Mainsail cuts titles at its 400 px dialog width
/// (about 34 characters), and "backlash X — cycle 1/2, mo" lost the direction (issue 26 A.3).
fn title_for(axis: &str, dir: &str, carriage: Option<u32>, cycle: usize, cycles: usize) -> String {
    match carriage {
        Some(c) => format!("{axis}{dir} only · carriage {c} · {cycle}/{cycles}"),
        None => format!("{axis}{dir} only · backlash {cycle}/{cycles}"),
    }
}

fn key_words(key: &str) -> String {
    match key.split_once('@') {
        Some((axis, n)) => format!("{} (carriage {n})", axis.to_uppercase()),
        None => key.to_uppercase(),
    }
}

fn round_um(mm: f64) -> f64 {
    (mm * 1e4).round() / 1e4
}

impl Calibration for Backlash {
    fn kind(&self) -> &'static str {
        KIND
    }

    fn title(&self) -> &'static str {
        "a backlash measurement"
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
            match BacklashCall::parse(method, args)? {
                BacklashCall::SetPoint => self.set_point().await,
                BacklashCall::Start(r) => self.start(&r).await,
                BacklashCall::Jog(p) => self.jog(p).await,
                BacklashCall::Camera(r) => self.camera(&r).await,
                BacklashCall::Apply => self.apply().await,
            }
        }
        .boxed()
    }

    fn resume<'a>(&'a self, row: &'a SessionRow) -> BoxFuture<'a, ()> {
        self.resume_session(row.id).boxed()
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
        let results = self.results(&s).unwrap_or_default();
        Ok(json!({
            "id": s.id,
            "state": s.state.name(),
            "progress": s.progress,
            "reason": s.reason,
            "point": s.point,
            "branch": s.detection,
            "axis": s.guide.as_ref().map(|g| g.axis.name()),
            "cycle": s.guide.as_ref().map(|g| g.cycles.len() + 1),
            "cycles": s.cycles,
            "corexy_answer": Self::corexy_answer(&s, &results),
            "results": results,
            "active_mm": s.active_mm,
            "notes": s.notes,
            "camera": s.camera,
        }))
    }

    fn held(&self, _row: &SessionRow) -> Option<Hold> {
        None
    }

    fn heaters_turned_off<'a>(&'a self, _row: &'a SessionRow) -> BoxFuture<'a, ()> {
        async {}.boxed()
    }
}
