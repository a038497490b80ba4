//! Thermal bed-mesh compensation (seed 002, VGB): capture → fit → profiles, then follow and
//! check. Capture: preflight → heating → soaking → capturing (a mesh each time the frame
//! moved by `mesh.step_c` or `mesh.interval_s` passed, each probe point stamped with the frame
//! temperature of the moment it was probed, every mesh stored the moment it completes) →
//! writing (`[bed_mesh klipcal_<T>]` profiles into the SAVE_CONFIG block: backup, restart,
//! verify, roll back) → done. Follow: loads the profile for the frame temperature only when
//! the model says it matters (`calib::mesh_follow`). Check: seed 001's 0.5 mm reference rule
//! before a print.

mod answers;
mod capture;
mod check;
mod follow;
mod import;
mod plan;

use answers::{CheckPoint, Checked, Following, Imported, TestJudged};
use plan::fit_session;
pub use plan::{capture_done, mesh_due, plan_session};

use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use anyhow::{anyhow, Context};
use serde::{Deserialize, Serialize};
use serde_json::{json, Value};
use tokio_util::sync::CancellationToken;
use tracing::{info, warn};

use crate::calib::mesh::{self as cm, Capture, Phase};
pub use crate::calib::mesh_capture::point_temps;
use crate::calib::mesh_follow::{Branch, Decision, Follower};
use crate::config::MeshConfig;
use crate::jobs::core::answer::{reply, SessionAnswer};
use crate::jobs::core::printer_config::FileWrite;
use crate::jobs::core::session::{now_unix, Core};
use crate::jobs::core::soak::{BedSoak, SoakSettings, SoakUpdate};
use crate::jobs::core::status::SessionStatus;
use crate::jobs::core::table::{arg, ArgKind, ArgSpec, MacroBody, Op, OpSpec};
use crate::jobs::core::{Calibration, Declare, Envelope, Hold, SessionState};
use crate::jobs::user;
use crate::klipper::bed_mesh::{self, MeshParams, MeshProfile};
use crate::store::SessionRow;

/// `BED=` of KLIPCAL_MESH_CAPTURE.
const BED_ARG: ArgSpec =
    crate::jobs::core::table::bed_arg("bed temperature, °C (0: unheated; default mesh.bed_temp_c)");
/// `ENABLE=` of KLIPCAL_MESH_FOLLOW.
const ENABLE_ARG: ArgSpec = arg(
    "enable",
    ArgKind::Choice(&["1", "0"]),
    "1",
    "1 (follow) or 0 (stop)",
    "1",
    "1: follow the frame temperature, 0: stop",
);

/// The thermal mesh's operations, each declared once (see [`crate::jobs::core::table`]).
pub(crate) static OPS: &[Op<MeshCall>] = &[
    Op {
        spec: OpSpec::remote(
            "klipcal_mesh_capture",
            "KLIPCAL_MESH_CAPTURE",
            "mesh/capture",
            "thermal bed mesh: heat the bed, then take meshes as the frame warms and write klipcal_<T> profiles (BED=0 for an unheated bed)",
            &[BED_ARG],
        ),
        parse: |a| {
            Ok(MeshCall::Capture {
                bed_c: a.num(&BED_ARG)?,
            })
        },
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
            &[ENABLE_ARG],
        ),
        parse: |a| {
            Ok(MeshCall::Follow {
                enable: a.choice(&ENABLE_ARG)? != Some("0"),
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
            by_agent: false,
            alias: None,
            echo: None,
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
pub(crate) enum MeshCall {
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

/// The store's kind.
pub(crate) const KIND: &str = "mesh";

/// klipcal.cfg's macro that keeps the user's `BED_MESH_OFFSET` (in its variables `x`, `y`) so
/// the follower can set it again after each load: Klipper's status does not show the offset,
/// and `BED_MESH_PROFILE LOAD=` drops it.
pub(crate) const OFFSET_MACRO: &str = "KLIPCAL_MESH_OFFSET";

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

impl SessionState for State {
    const ALL: &'static [Self] = &[
        State::Preflight,
        State::Soaking,
        State::Capturing,
        State::Writing,
        State::Done,
        State::Failed,
        State::Cancelled,
    ];
    const FINAL: [Self; 3] = [State::Done, State::Failed, State::Cancelled];
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

/// The session document: the envelope around [`MeshBody`].
pub(crate) type Session = Envelope<State, MeshBody>;

/// The thermal mesh session's own part of its document.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct MeshBody {
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
    /// The bed mesh active in Klipper when the capture started (`Some("")`: none), loaded
    /// again after each mesh and at the end; `None` for an import or an older session.
    #[serde(default)]
    pub user_mesh: Option<String>,
    /// The meshes are VGB's profiles imported from the config (whose names do not say whether
    /// the frame warmed or cooled), not a capture's.
    #[serde(default)]
    pub imported: bool,
    /// The user switched following on with this session's profiles (KLIPCAL_MESH_FOLLOW
    /// ENABLE=1) and not off since: a restarted daemon follows again.
    #[serde(default)]
    pub following: bool,
}

/// The profile klipcal's BED_MESH_CALIBRATE stores each capture mesh under: never the
/// user's `default` (a SAVE_CONFIG during the capture would write a capture mesh over it),
/// and a `klipcal_` name, so the next profile write removes it should it reach printer.cfg.
pub(crate) const CAPTURE_PROFILE: &str = "klipcal_capture";

/// The thermal mesh over the shared core.
#[derive(Clone)]
pub(crate) struct Mesh {
    core: Core,
    settings: MeshConfig,
    soak: SoakSettings,
    follow: Arc<Mutex<Option<CancellationToken>>>,
    follow_status: Arc<Mutex<FollowStatus>>,
}

impl Mesh {
    /// The calibration over `core`.
    #[must_use]
    pub(crate) fn new(core: Core, settings: MeshConfig, soak: SoakSettings) -> Self {
        Self {
            core,
            settings,
            soak,
            follow: Arc::new(Mutex::new(None)),
            follow_status: Arc::new(Mutex::new(FollowStatus::default())),
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
        self.core
            .set_state::<State, MeshBody>(id, state, progress)
            .await
    }

    async fn frame_temp(&self, sensor: &str) -> anyhow::Result<f64> {
        let obj = format!("temperature_sensor {sensor}");
        let st = self.core.m().heater(&obj, &["temperature"]).await?;
        st.temperature.ok_or_else(|| {
            user(format!(
                "[{obj}] reports no temperature; mesh.frame_sensor names the frame thermistor"
            ))
        })
    }

    async fn cancel_session(&self, id: i64, reason: &str) -> anyhow::Result<SessionAnswer> {
        self.core.stop_runner();
        self.core
            .heaters_off_reported("mesh session cancelled")
            .await;
        // A BED_MESH_CALIBRATE still probing holds Klipper's G-code queue: the user's mesh goes
        // back once it ends, without holding up the answer.
        if let Ok(s) = self.core.load::<Session>(id) {
            let me = self.clone();
            self.core
                .spawn(async move { me.put_back_user_mesh(&s, true).await });
        }
        self.core
            .cancel_session::<State, MeshBody>(
                id,
                reason,
                "cancelled; heaters off (meshes taken so far are kept)",
                format!("thermal mesh session {id} cancelled ({reason}); heaters off"),
            )
            .await
    }
}

/// A thermal mesh session's own part of its status.
#[derive(Debug, Clone, PartialEq, Serialize, Default)]
pub(crate) struct MeshStatus {
    /// Meshes taken.
    pub meshes: usize,
    /// Each mesh's mean frame temperature, °C.
    pub frame_c: Vec<f64>,
    /// The fit and the profiles written, once written.
    pub result: Option<ResultDoc>,
    /// The follower.
    pub follow: FollowStatus,
}

/// The follower's status: `{"following": false}`, or while following its frame temperature,
/// trend, loaded profile, offset and residual; `{"following": false, "stopped": why}` once
/// stopped.
#[derive(Debug, Clone, PartialEq, Serialize, Default)]
pub(crate) struct FollowStatus {
    /// Whether the follower runs.
    pub following: bool,
    /// Why it stopped, once stopped.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub stopped: Option<String>,
    /// Its last reading, while following.
    #[serde(flatten)]
    pub reading: Option<FollowReading>,
}

impl FollowStatus {
    /// Stopped, and why.
    pub(crate) fn stopped(why: &str) -> Self {
        Self {
            following: false,
            stopped: Some(why.to_string()),
            reading: None,
        }
    }
}

/// The follower's last reading and what it did with it.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub(crate) struct FollowReading {
    /// The frame temperature, °C.
    pub frame_c: f64,
    /// Whether the frame warms or cools.
    pub trend: Phase,
    /// The profile loaded, once one is.
    pub loaded: Option<String>,
    /// The offset set again after each load (`KLIPCAL_MESH_OFFSET`), mm.
    pub offset_mm: [f64; 2],
    /// How far the loaded profile is from the model at this temperature, µm (none when the
    /// reading was not used).
    pub residual_um: Option<f64>,
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
pub(crate) fn profile_name(temp_c: f64) -> String {
    format!("{}{temp_c:.2}", bed_mesh::KLIPCAL_PREFIX)
}

/// The profile of a direction: `klipcal_<T>` while heating (or for one model in every
/// direction), `klipcal_cool_<T>` for the cooling model kept apart.
#[must_use]
pub(crate) fn direction_profile_name(phase: Phase, temp_c: f64) -> String {
    match phase {
        Phase::Heating => profile_name(temp_c),
        Phase::Cooling => format!("{}cool_{temp_c:.2}", bed_mesh::KLIPCAL_PREFIX),
    }
}

/// The profiles written, by name ("2 profiles (klipcal_25.00, klipcal_31.40)"; the first and
/// the last of many), instead of a pattern a console may show garbled ("klipcal_*").
#[must_use]
pub(crate) fn profiles_words(phase: Phase, temps_c: &[f64]) -> String {
    let names: Vec<String> = temps_c
        .iter()
        .map(|t| direction_profile_name(phase, *t))
        .collect();
    let list = match names.as_slice() {
        [] => return "no profiles".into(),
        [one] => return format!("1 profile ({one})"),
        few if few.len() <= 4 => few.join(", "),
        [first, .., last] => format!("{first} … {last}"),
    };
    format!("{} profiles ({list})", names.len())
}

impl Declare for Mesh {
    const KIND: &'static str = KIND;
    const TITLE: &'static str = "a thermal mesh capture";
    type State = State;
    type Session = Session;
    type Call = MeshCall;
    const OPS: &'static [Op<MeshCall>] = OPS;

    fn session_status(&self, s: &Session) -> anyhow::Result<SessionStatus> {
        let follow = self
            .follow_status
            .lock()
            .map(|v| v.clone())
            .unwrap_or_default();
        let body = MeshStatus {
            meshes: s.captures.len(),
            frame_c: s
                .captures
                .iter()
                .map(|c| c.temps_c.iter().sum::<f64>() / c.temps_c.len().max(1) as f64)
                .collect(),
            result: s.result.clone(),
            follow,
        };
        SessionStatus::new(KIND, s.head(), &body)
    }
}

impl Calibration for Mesh {
    async fn handle(&self, call: MeshCall) -> anyhow::Result<Value> {
        match call {
            MeshCall::Capture { bed_c } => reply(self.capture(bed_c).await),
            MeshCall::Import => reply(self.import().await),
            MeshCall::Follow { enable } => reply(self.follow_cmd(enable).await),
            MeshCall::Check => reply(self.check().await),
        }
    }

    async fn resume(&self, row: &SessionRow) {
        let Ok(s) = self.core.load::<Session>(row.id) else {
            return;
        };
        if !s.state.is_final() {
            info!(session = s.id, state = %s.state.name(), "resuming thermal mesh session");
            self.spawn_runner(s.id);
        }
    }

    async fn cancel(&self, row: &SessionRow, reason: &str) -> anyhow::Result<SessionAnswer> {
        self.cancel_session(row.id, reason).await
    }

    fn held(&self, row: &SessionRow) -> Option<Hold> {
        // The capture holds the bed hot for at most mesh.max_s from its start.
        let s: Session = serde_json::from_value(row.doc.clone()).ok()?;
        (s.state == State::Capturing).then_some(Hold {
            since_unix: s.started_unix?,
            max_s: s.options.max_s + 600.0,
        })
    }

    async fn heaters_turned_off(&self, row: &SessionRow) {
        let _ = self
            .update(row.id, |s| {
                s.notes
                    .push("heaters turned off: the capture ran past mesh.max_s".into());
                Ok(())
            })
            .await;
    }

    async fn connected(&self) {
        // Following switched on by the user goes on after a daemon restart, and says so.
        let asked = self.following_was_on();
        if !(self.settings.follow || asked) {
            return;
        }
        match self.follow_cmd(true).await {
            Ok(r) if asked => {
                self.core
                    .console(&format!("klipcal started again; {}", r.message))
                    .await;
            }
            Ok(_) => {}
            Err(e) => {
                let e = format!("{e:#}");
                warn!(error = %e, "following was on but cannot start again");
                if asked {
                    self.core
                        .console_error(&format!(
                            "{TITLE}: following was on before klipcal restarted but \
                             cannot start again: {e}"
                        ))
                        .await;
                }
            }
        }
    }
}

#[cfg(test)]
mod words_tests {
    use super::{profiles_words, Phase};

    #[test]
    fn the_profiles_written_are_named_not_patterned() {
        assert_eq!(
            profiles_words(Phase::Heating, &[25.0, 31.4]),
            "2 profiles (klipcal_25.00, klipcal_31.40)"
        );
        assert_eq!(
            profiles_words(Phase::Cooling, &[30.0]),
            "1 profile (klipcal_cool_30.00)"
        );
        let many: Vec<f64> = (0..12).map(|k| 25.0 + f64::from(k)).collect();
        assert_eq!(
            profiles_words(Phase::Heating, &many),
            "12 profiles (klipcal_25.00 … klipcal_36.00)"
        );
        assert!(!profiles_words(Phase::Heating, &many).contains('*'));
    }
}
