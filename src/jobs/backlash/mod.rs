//! The guided backlash measurement (seed 004) through a nozzle camera: measuring → measured →
//! applying → done (and failed / cancelled, with the reason). KLIPCAL_BACKLASH_SET_POINT saves
//! the camera point once; KLIPCAL_BACKLASH_START AXIS=X|Y|Z|A|B [CYCLES=] runs
//! `calib::backlash_guide` with a prompt whose jog buttons (_KLIPCAL_BACKLASH_JOG PRESS=…) move
//! only in the approach direction, each step saved before the machine moves;
//! KLIPCAL_BACKLASH_APPLY sets the values (SET_BACKLASH_COMPENSATION with its reply checked on
//! PR 7259; PR 7157's `[backlash]` by config) and persists them through the shared config
//! transaction. Session store, runner, guards, console and config transaction are the core's.

mod answers;
mod apply;
pub mod camera;
pub mod click;
mod dual;
mod guide;
pub mod snapshot;

use std::collections::BTreeMap;

use anyhow::{anyhow, Context};
use serde::{Deserialize, Serialize};
use serde_json::{json, Value};

use crate::calib::backlash::{
    analyse, common_smooth_time_s, AxisResult, MoreCycles, MORE_CYCLES_TARGET_U_MM,
    SEED_SMOOTH_TIME_S,
};
use crate::calib::backlash_guide::{Guide, GuideAxis, Phase, Press, Step};
use crate::config::BacklashConfig;
use crate::jobs::core::answer::{reply, SessionAnswer};
use crate::jobs::core::console::{Button, Prompt};
use crate::jobs::core::printer_config::{self, ValueSet};
use crate::jobs::core::session::{now_unix, Core};
use crate::jobs::core::status::SessionStatus;
use crate::jobs::core::table::{arg, ArgKind, ArgSpec, Args, Op, OpSpec};
use crate::jobs::core::{Calibration, Declare, Hold};
use crate::jobs::core::{Envelope, SessionState};
use crate::jobs::user;
use crate::klipper::backlash::{self as kb, Branch, CarriageBacklash, Detection, SetBacklash};
use crate::klipper::GcodeCmd;
use crate::moonraker::ConfigFile;
use crate::store::SessionRow;
use answers::{Applied, AxisStarted, Jogged, PointSaved};

/// `CYCLES=`, shared by the guided and the camera measurement.
pub(super) const CYCLES_ARG: ArgSpec = arg(
    "cycles",
    ArgKind::Whole { min: 1, max: 50 },
    "5",
    "1..50",
    "",
    "approach cycles (default backlash.cycles)",
);
/// `AXIS=` of the guided measurement (the camera's has no Z: [`camera::AXIS_ARG`]).
const AXIS_ARG: ArgSpec = arg(
    "axis",
    ArgKind::Text,
    "X",
    "X, Y, Z, A or B",
    "",
    "the axis: X, Y, Z, or A/B (CoreXY motors)",
);
/// `PRESS=` of the jog dialog's buttons.
const PRESS_ARG: ArgSpec = arg(
    "press",
    ArgKind::Text,
    "fine",
    "coarse, fine, centred, past, short or overshot",
    "",
    "coarse, fine, centred, past, short or overshot",
);
/// Checks a number of cycles (`CYCLES=` or `backlash.cycles`) against `CYCLES=`'s declared
/// range, in its words.
///
/// # Errors
/// Outside the range.
pub(super) fn cycles_allowed(cycles: usize) -> anyhow::Result<()> {
    match CYCLES_ARG.kind {
        ArgKind::Whole { min, max }
            if !(min..=max).contains(&i64::try_from(cycles).unwrap_or(i64::MAX)) =>
        {
            Err(user(format!(
                "CYCLES={cycles}: expected {}",
                CYCLES_ARG.expect
            )))
        }
        _ => Ok(()),
    }
}

/// `CARRIAGE=`, shared by the guided and the camera measurement.
pub(super) const CARRIAGE_ARG: ArgSpec = arg(
    "carriage",
    ArgKind::Whole { min: 0, max: 1 },
    "1",
    "0 or 1",
    "",
    "the carriage on a dual_carriage printer",
);

/// The backlash measurement's operations, each declared once (see [`crate::jobs::core::table`]).
pub(crate) static OPS: &[Op<BacklashCall>] = &[
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
            &[AXIS_ARG, CYCLES_ARG, CARRIAGE_ARG],
        ),
        parse: |a| Ok(BacklashCall::Start(StartRequest::from_args(a)?)),
    },
    camera::OP,
    click::START_OP,
    click::TIP_OP,
    Op {
        spec: OpSpec::remote(
            "klipcal_backlash_jog",
            "_KLIPCAL_BACKLASH_JOG",
            "backlash/jog",
            "backlash prompt button, PRESS=coarse, fine, centred, past, short or overshot (moves only in the approach direction; from Centred on each press says what the nozzle looks like, until Past twice)",
            &[PRESS_ARG],
        ),
        parse: |a| {
            Press::parse(&a.text(&PRESS_ARG).unwrap_or_default())
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
pub(crate) enum BacklashCall {
    /// `klipcal_backlash_set_point`.
    SetPoint,
    /// `klipcal_backlash_start`.
    Start(StartRequest),
    /// `klipcal_backlash_jog`.
    Jog(Press),
    /// `klipcal_backlash_camera` and `klipcal_backlash_click`.
    Camera(camera::CameraRequest),
    /// `klipcal_backlash_tip`: a click in the snapshot on the page.
    Tip(click::TipRequest),
    /// `klipcal_backlash_apply`.
    Apply,
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
    pub(crate) fn from_args(a: &Args) -> anyhow::Result<Self> {
        let carriage = a.int(&CARRIAGE_ARG)?;
        let axis =
            GuideAxis::parse(&a.required_text(&AXIS_ARG)?).map_err(|e| user(e.to_string()))?;
        let cycles = a.count(&CYCLES_ARG)?;
        Ok(Self {
            axis,
            cycles,
            carriage,
        })
    }
}

/// The store's kind.
pub(crate) const KIND: &str = "backlash";
/// The store's key of the saved camera point (`{"point": [x, y, z]}`).
pub(crate) const POINT_KEY: &str = "backlash_point";
const TITLE: &str = "backlash measurement";
/// Jog and approach feed rate, mm/min.
const JOG_F: f64 = 1200.0;

/// A session's state.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub(crate) enum State {
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

impl SessionState for State {
    const ALL: &'static [Self] = &[
        State::Measuring,
        State::Measured,
        State::Applying,
        State::Done,
        State::Failed,
        State::Cancelled,
    ];
    const FINAL: [Self; 3] = [State::Done, State::Failed, State::Cancelled];
}

/// The stored session: the envelope around [`BacklashBody`].
pub(crate) type Session = Envelope<State, BacklashBody>;

/// The backlash session's own part of its document.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub(crate) struct BacklashBody {
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
    /// Axes read through the nozzle camera (KLIPCAL_BACKLASH_CAMERA): how, per result key.
    #[serde(default)]
    pub camera: BTreeMap<String, camera::CameraReport>,
    /// Axes read by jogging: the motor's microstep along each, mm, per result key (its share
    /// of the uncertainty does not average down). Absent where Klipper's settings do not say.
    #[serde(default)]
    pub step_mm: BTreeMap<String, f64>,
}

/// The saved camera point, as the store keeps it under [`POINT_KEY`].
#[derive(Debug, Clone, Serialize, Deserialize)]
struct PointDoc {
    point: [f64; 3],
}

/// A backlash session's own part of its status.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub(crate) struct BacklashStatus {
    /// The camera point (toolhead X, Y, Z).
    pub point: [f64; 3],
    /// What the printer's Klipper has.
    pub branch: Detection,
    /// The axis being measured.
    pub axis: Option<String>,
    /// Its cycle in progress, 1-based.
    pub cycle: Option<usize>,
    /// Finished axes: their cycles.
    pub cycles: BTreeMap<String, Vec<crate::calib::backlash::Cycle>>,
    /// For CoreXY: whether the motors or the axes carry the backlash, in words.
    pub corexy_answer: Option<String>,
    /// Finished axes: their results.
    pub results: BTreeMap<String, AxisResult>,
    /// The compensation active while measuring, per axis, mm.
    pub active_mm: BTreeMap<String, f64>,
    /// Axes read through the nozzle camera: how, per result key.
    pub camera: BTreeMap<String, camera::CameraReport>,
    /// The newest camera frame of this session (kept in memory since klipcal started), with
    /// what the detector found in it: `GET /api/backlash/snapshot.jpg?seq=` serves it.
    pub snapshot: Option<snapshot::SnapshotInfo>,
    /// The guided measurement's jog buttons as its dialog offers them now (the page shows
    /// them beside the live camera; each posts `backlash/jog` with its press); empty when no
    /// axis is being jogged.
    pub jog: Vec<JogButton>,
}

/// One jog button of the guided measurement: its label, the press it sends, its colour.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub(crate) struct JogButton {
    pub label: String,
    pub press: String,
    pub style: String,
}

impl JogButton {
    /// The jog buttons of the dialog the guide shows now (none without a guide).
    fn of(s: &Session) -> Vec<JogButton> {
        let Some(g) = &s.guide else {
            return Vec::new();
        };
        let now = Step {
            moves_mm: Vec::new(),
            phase: g.phase,
            cycle: (g.cycles.len() + 1).min(g.params.cycles),
            recorded: None,
            crossing: g.entry_mm.is_some(),
            past_once: g.answers.past_once,
        };
        Backlash::prompt_for(s, &now, None)
            .buttons
            .into_iter()
            .filter_map(|b| {
                let press = b.gcode.strip_prefix("_KLIPCAL_BACKLASH_JOG PRESS=")?;
                Some(JogButton {
                    press: press.to_string(),
                    label: b.label,
                    style: b.style,
                })
            })
            .collect()
    }
}

/// The backlash calibration.
pub(crate) struct Backlash {
    core: Core,
    settings: BacklashConfig,
    /// The camera frames the page shows (shared with the measurement's task).
    frames: std::sync::Arc<snapshot::Frames>,
    /// The snapshot waiting for the person's click (shared likewise).
    clicks: std::sync::Arc<click::Clicks>,
}

impl Backlash {
    /// Over the shared core, with `[backlash]`.
    pub(crate) fn new(core: Core, settings: BacklashConfig) -> Self {
        Self {
            core,
            settings,
            frames: std::sync::Arc::default(),
            clicks: std::sync::Arc::default(),
        }
    }

    /// Another handle on the same calibration (for a task that outlives the call).
    fn sibling(&self) -> Self {
        Self {
            core: self.core.clone(),
            settings: self.settings.clone(),
            frames: self.frames.clone(),
            clicks: self.clicks.clone(),
        }
    }

    /// The camera point saved by KLIPCAL_BACKLASH_SET_POINT, if any.
    fn saved_point(&self) -> anyhow::Result<Option<[f64; 3]>> {
        self.core
            .store()
            .value(POINT_KEY)?
            .map(serde_json::from_value::<PointDoc>)
            .transpose()
            .context("reading the saved camera point")
            .map(|d| d.map(|d| d.point))
    }

    fn active(&self) -> anyhow::Result<Option<Session>> {
        Ok(self.core.active_of::<Session>(KIND)?.map(|(_, s)| s))
    }

    async fn set_state(&self, id: i64, state: State, progress: &str) -> anyhow::Result<()> {
        self.core
            .set_state::<State, BacklashBody>(id, state, progress)
            .await
    }

    /// Ends a step in `state`, `why` its progress (and its reason, unless done).
    async fn finish(&self, id: i64, state: State, why: &str) -> anyhow::Result<()> {
        if state == State::Done {
            self.set_state(id, state, why).await
        } else {
            self.core
                .end_session::<State, BacklashBody>(id, state, why, why)
                .await
        }
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
                    let page = self.core.page_road();
                    self.core
                        .prompt(&Self::prompt_for(&s2, &step, page.as_deref()))
                        .await;
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

    /// The dialog closes in Calibrations::cancel, after every calibration's cancel.
    async fn cancel_session(&self, id: i64, reason: &str) -> anyhow::Result<SessionAnswer> {
        self.core
            .cancel_session::<State, BacklashBody>(
                id,
                reason,
                reason,
                format!("backlash session {id} cancelled ({reason})"),
            )
            .await
    }
}

/// What both starts, guided and camera, read from the printer for one axis
/// ([`Backlash::axis_printer`]).
pub(super) struct AxisPrinter {
    pub(super) detection: Detection,
    pub(super) kinematics: String,
    pub(super) max_accel_mm_s2: Option<f64>,
    /// The dual carriage measured (selected and parked by the start), if the axis has two.
    pub(super) carriage: Option<u32>,
    /// Where the axis's cycles are kept ([`result_key`]).
    pub(super) key: String,
    /// The compensation active while measuring ([`Backlash::active_values`]).
    pub(super) active_mm: BTreeMap<String, f64>,
    /// The motor's microstep along the axis from Klipper's settings ([`guide::step_along`]).
    pub(super) step_mm: Option<f64>,
}

impl Backlash {
    /// Moves the toolhead to `p` (absolute X Y Z, mm) at the jog speed.
    pub(super) async fn go(&self, p: [f64; 3]) -> anyhow::Result<()> {
        let line = GcodeCmd::new("G1")
            .axis('X', p[0])
            .axis('Y', p[1])
            .axis('Z', p[2])
            .axis('F', JOG_F)
            .build()?;
        self.core.m().gcode(&format!("G90\n{line}")).await?;
        Ok(())
    }

    /// The printer side of starting an axis, shared by the guided and the camera start: the
    /// compensation module and branch, A/B refused off CoreXY, max_accel, the carriage
    /// (CARRIAGE or the active one; parked and selected here), the compensation active now
    /// and the microstep along the axis.
    ///
    /// # Errors
    /// A/B on a printer that is not CoreXY, a CARRIAGE the printer does not have, or
    /// Moonraker's and Klipper's errors.
    pub(super) async fn axis_printer(
        &self,
        axis: GuideAxis,
        asked_carriage: Option<i64>,
    ) -> anyhow::Result<AxisPrinter> {
        let (detection, cf) = self.detect().await?;
        let kinematics = cf.settings.printer.kinematics.clone();
        if axis.is_motor() && kinematics != "corexy" {
            return Err(user(format!(
                "AXIS={} is a CoreXY motor direction; this printer's kinematics is {kinematics}",
                axis.name().to_uppercase()
            )));
        }
        let carriage = self
            .carriage_for(&detection, &cf, axis, asked_carriage)
            .await?;
        if let Some(n) = carriage {
            self.park_and_select(n).await?;
        }
        let key = result_key(axis, carriage);
        let active_mm = self
            .active_values(&detection, &cf, axis, carriage, &key)
            .await?;
        let step_mm = guide::step_along(&cf.settings, &kinematics, axis, carriage);
        Ok(AxisPrinter {
            detection,
            kinematics,
            max_accel_mm_s2: cf.settings.printer.max_accel,
            carriage,
            key,
            active_mm,
            step_mm,
        })
    }
}

/// What follows a measured axis: another axis (`again` is the command that measures one), then
/// APPLY; on a printer without a compensation module, what it lacks instead of an APPLY that
/// would be refused (issue 27's walk).
fn next_line(detection: &Detection, again: &str) -> String {
    if detection.can_apply() {
        format!("next: {again} AXIS=… for another axis, or KLIPCAL_BACKLASH_APPLY")
    } else {
        format!(
            "next: {again} AXIS=… for another axis; nothing can be applied here: {}",
            detection.why
        )
    }
}

/// Told when a measurement starts on a printer that cannot apply the result.
fn start_note(detection: &Detection) -> String {
    if detection.can_apply() {
        String::new()
    } else {
        format!(
            ". Note: this measures the play, but this printer cannot apply it: {}",
            detection.why
        )
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

impl Declare for Backlash {
    const KIND: &'static str = KIND;
    const TITLE: &'static str = "a backlash measurement";
    type State = State;
    type Session = Session;
    type Call = BacklashCall;
    const OPS: &'static [Op<BacklashCall>] = OPS;

    fn session_status(&self, s: &Session) -> anyhow::Result<SessionStatus> {
        let results = self.results(s).unwrap_or_default();
        let body = BacklashStatus {
            point: s.point,
            branch: s.detection.clone(),
            axis: s.guide.as_ref().map(|g| g.axis.name().to_string()),
            cycle: s.guide.as_ref().map(|g| g.cycles.len() + 1),
            cycles: s.cycles.clone(),
            corexy_answer: Self::corexy_answer(s, &results),
            results,
            active_mm: s.active_mm.clone(),
            camera: s.camera.clone(),
            snapshot: self.frames.newest(s.id).map(|mut f| {
                f.click = self.clicks.waiting(s.id, f.seq);
                if let Some((at, zoom)) = self.clicks.hint(s.id) {
                    f.hint_px = Some(at);
                    f.zoom = Some(zoom);
                }
                f
            }),
            jog: JogButton::of(s),
        };
        SessionStatus::new(KIND, s.head(), &body)
    }
}

impl Backlash {
    /// A frame taken now from the nozzle camera (`[backlash] webcam`), JPEG: the page's live
    /// picture beside its jog buttons.
    ///
    /// # Errors
    /// The webcam could not be chosen or did not answer (said which and why).
    pub(crate) async fn live_jpeg(&self) -> anyhow::Result<Vec<u8>> {
        let cam = self.webcam().await?;
        self.fetch(&self.http()?, &cam).await
    }
}

impl Calibration for Backlash {
    async fn handle(&self, call: BacklashCall) -> anyhow::Result<Value> {
        match call {
            BacklashCall::SetPoint => reply(self.set_point().await),
            BacklashCall::Start(r) => reply(self.start(&r).await),
            BacklashCall::Jog(p) => reply(self.jog(p).await),
            BacklashCall::Camera(r) => reply(self.camera(&r).await),
            BacklashCall::Tip(r) => reply(self.tip(&r)),
            BacklashCall::Apply => reply(self.apply().await),
        }
    }

    async fn resume(&self, row: &SessionRow) {
        self.resume_session(row.id).await;
    }

    async fn cancel(&self, row: &SessionRow, reason: &str) -> anyhow::Result<SessionAnswer> {
        self.cancel_session(row.id, reason).await
    }

    fn held(&self, _row: &SessionRow) -> Option<Hold> {
        None
    }

    fn snapshot_jpeg(&self, seq: Option<u64>) -> Option<Vec<u8>> {
        self.frames.jpeg(seq)
    }

    async fn heaters_turned_off(&self, _row: &SessionRow) {}
}
