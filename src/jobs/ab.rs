//! The differential A/B (X/Y) rotation_distance calibration (paper 000): preflight → uploaded →
//! heating → soaking → printing → holding → measuring → solved → applying → applied → next
//! round or converged (and failed / cancelled, with the reason). Its states, its steps and its
//! remote methods; the session store, runner, guards, console and config transaction are the
//! shared core's (`session`, `console`, `soak`, `printer_config`).

use std::collections::BTreeMap;
use std::time::Duration;

use anyhow::{anyhow, Context};
use futures_util::future::BoxFuture;
use futures_util::FutureExt;
use serde::{Deserialize, Serialize};
use serde_json::{json, Value};
use tracing::{info, warn};

use super::console::{Button, Prompt};
use super::printer_config::{self, ApplyReport, ValueSet};
use super::registry::{Calibration, Hold};
use super::session::{now_unix, Core, Doc};
use super::soak::{BedSoak, SoakUpdate};
use super::table::{arg, parse_call, ArgKind, Args, Fields, Op, OpSpec};
use super::user;
use crate::calib::entry;
use crate::calib::metric::{Kinematics as CalibKinematics, ShearTo};
use crate::calib::soak::SoakParams;
use crate::calib::solve::{solve, MotionFacts, Solution, SolveOptions, StepperFacts};
use crate::config::AbConfig;
use crate::gcode::{self, LayoutKind};
use crate::klipper::{self, PrinterFacts};
use crate::layout::Layout;
use crate::store::SessionRow;

const BED: crate::jobs::table::ArgSpec = crate::jobs::table::bed_arg(
    "bed temperature, °C (0: unheated, no soak; default ab.bed_temp_c)",
);
const PAIR: crate::jobs::table::ArgSpec = arg(
    "pair",
    ArgKind::Text,
    "A-D1",
    "a pair of the layout, e.g. A-D1",
    "",
    "the pair measured, as the layout names it (A-D1)",
);

/// The A/B calibration's operations, each declared once (see [`crate::jobs::table`]).
pub static OPS: &[Op<AbCall>] = &[
    Op {
        spec: OpSpec::remote(
            "klipcal_ab_start",
            "KLIPCAL_AB_START",
            "ab/start",
            "print the pylons and calibrate stepper_x/stepper_y rotation_distance (BED=0 for an unheated bed, LAYOUT=paper or full)",
            &[
                BED,
                arg(
                    "extruder",
                    ArgKind::Number {
                        min: 150.0,
                        max: 320.0,
                    },
                    "215",
                    "a nozzle temperature from 150 to 320 °C",
                    "",
                    "nozzle temperature, °C (default ab.nozzle_temp_c)",
                ),
                arg(
                    "layout",
                    ArgKind::Choice(&["paper", "full"]),
                    "paper",
                    "paper or full",
                    "",
                    "paper: the paper's pylons; full: also observes shear",
                ),
            ],
        ),
        parse: |a| Ok(AbCall::Start(StartRequest::from_args(a)?)),
    },
    Op {
        spec: OpSpec::remote(
            "klipcal_measure",
            "KLIPCAL_MEASURE",
            "ab/measure",
            "enter caliper readings for one pair, e.g. PAIR=A-D1 VALUES=10.02,10.03,10.01,10.02,10.04 (CLEAR=1 removes the pair's readings)",
            &[
                PAIR,
                arg(
                    "values",
                    ArgKind::Readings,
                    "10.02,10.03,10.01",
                    "readings separated by commas, e.g. 10.02,10.03",
                    "",
                    "the readings as the caliper shows them: commas between, a dot as the decimal mark",
                ),
                arg(
                    "value",
                    ArgKind::Readings,
                    "10.02",
                    "one reading, e.g. 10.02",
                    "",
                    "one reading (its comma is the decimal mark: 10,02 is 10.02)",
                ),
                arg(
                    "clear",
                    ArgKind::Flag,
                    "1",
                    "1 or 0",
                    "0",
                    "1: remove the pair's readings first",
                ),
            ],
        ),
        parse: |a| Ok(AbCall::Measure(MeasureRequest::from_args(a)?)),
    },
    Op {
        spec: OpSpec::remote(
            "klipcal_ab_check",
            "KLIPCAL_AB_CHECK",
            "ab/check",
            "check readings for one pair without saving them, e.g. PAIR=A-D1 VALUES=10.02,10.03",
            &[
                PAIR,
                arg(
                    "values",
                    ArgKind::Readings,
                    "10.02,10.03",
                    "readings separated by commas, e.g. 10.02,10.03",
                    "",
                    "the readings, separated by commas",
                ),
            ],
        ),
        parse: |a| Ok(AbCall::Check(CheckRequest::from_args(a)?)),
    },
    Op {
        spec: OpSpec::remote(
            "klipcal_soak_choice",
            "KLIPCAL_SOAK_CHOICE",
            "ab/soak_choice",
            "the bed soak: CHOICE=print prints now (offered from the moment the bed is in its band, with what the surface may still warm) or CHOICE=wait (10 min more, at the soak limit's prompt)",
            &[arg(
                "choice",
                ArgKind::Choice(&["print", "wait"]),
                "wait",
                "print or wait",
                "wait",
                "print: print now; wait: 10 min more",
            )],
        ),
        parse: |a| {
            Ok(AbCall::SoakChoice(a.choice("choice")?.ok_or_else(|| {
                user("no CHOICE given; expected CHOICE=print or CHOICE=wait (KLIPCAL_CANCEL cancels)")
            })?))
        },
    },
    Op {
        spec: OpSpec::remote(
            "klipcal_solve",
            "KLIPCAL_AB_SOLVE",
            "ab/solve",
            "compute the new rotation distances from the readings",
            &[],
        ),
        parse: |_| Ok(AbCall::Solve),
    },
    Op {
        spec: OpSpec::remote(
            "klipcal_apply",
            "KLIPCAL_AB_APPLY",
            "ab/apply",
            "write the new rotation distances (backup, restart, verify, FORCE=1 for a change beyond the limit)",
            &[arg(
                "force",
                ArgKind::Flag,
                "1",
                "1 or 0",
                "0",
                "1: apply a change beyond ab.max_change_pct",
            )],
        ),
        parse: |a| Ok(AbCall::Apply(ApplyRequest::from_args(a)?)),
    },
];

/// An A/B call, typed at the boundary.
#[derive(Debug, Clone, PartialEq)]
pub enum AbCall {
    /// `klipcal_ab_start`.
    Start(StartRequest),
    /// `klipcal_measure`.
    Measure(MeasureRequest),
    /// `klipcal_ab_check`.
    Check(CheckRequest),
    /// `klipcal_soak_choice`: `print` or `wait`.
    SoakChoice(&'static str),
    /// `klipcal_solve`.
    Solve,
    /// `klipcal_apply`.
    Apply(ApplyRequest),
}

impl AbCall {
    /// Reads a call of `method` at the boundary.
    ///
    /// # Errors
    /// An unknown method, or a bad or unknown argument, named.
    pub fn parse(method: &str, args: &Value) -> anyhow::Result<Self> {
        parse_call(OPS, method, args)
    }
}

/// The store's kind.
pub const KIND: &str = "ab";

/// "Wait 10 min more" after a soak that ran past `soak_max_s`.
const SOAK_MORE_S: f64 = 600.0;

/// How the console names it.
const TITLE: &str = "A/B calibration";

/// A session's state.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum State {
    /// Checking the printer.
    Preflight,
    /// The job is on the printer.
    Uploaded,
    /// Bed heating to its target.
    Heating,
    /// Waiting for thermal equilibrium (bed power stops falling).
    Soaking,
    /// The job prints.
    Printing,
    /// Print done; the part cools on the hot bed.
    Holding,
    /// Waiting for caliper readings.
    Measuring,
    /// New values computed; waiting for Apply.
    Solved,
    /// Writing the values, restarting Klipper.
    Applying,
    /// Applied; the next round may start.
    Applied,
    /// Converged: done.
    Converged,
    /// Failed, with the reason.
    Failed,
    /// Cancelled, with the reason.
    Cancelled,
}

impl State {
    /// Whether the session is over.
    pub fn is_final(self) -> bool {
        matches!(self, State::Converged | State::Failed | State::Cancelled)
    }

    /// Whether the daemon drives this state by itself (as opposed to waiting for the user).
    fn is_automatic(self) -> bool {
        matches!(
            self,
            State::Preflight
                | State::Uploaded
                | State::Heating
                | State::Soaking
                | State::Printing
                | State::Holding
        )
    }

    /// The state's name as stored.
    pub fn name(self) -> String {
        serde_json::to_value(self)
            .ok()
            .and_then(|v| v.as_str().map(str::to_string))
            .unwrap_or_default()
    }
}

/// The stepper facts a round was printed with.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct StepperDoc {
    /// mm.
    pub rotation_distance_mm: f64,
    /// Microsteps.
    pub microsteps: u32,
    /// Full steps per rotation.
    pub full_steps_per_rotation: u32,
    /// Gear ratio product.
    pub gear_ratio: f64,
}

/// One print-measure-solve-apply round.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Round {
    /// 1-based.
    pub n: u32,
    /// The job under Moonraker's gcodes root.
    pub file: String,
    /// The printed layout.
    pub layout: Layout,
    /// `corexy` or `cartesian`.
    pub kinematics: String,
    /// stepper_x as printed.
    pub stepper_x: StepperDoc,
    /// stepper_y as printed.
    pub stepper_y: StepperDoc,
    /// The solver's result (stored in the `klipcal solve --json` shape).
    pub solution: Option<Solution>,
    /// What apply wrote.
    pub applied: Option<ApplyReport>,
    /// The layout diagram under the config root (where Mainsail/Fluidd's file browser shows
    /// it), when it was uploaded.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub diagram: Option<String>,
    /// How the prompt names the diagram to a user: its PNG twin (`config/klipcal/….png`), or
    /// the SVG when no PNG could be made.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub picture: Option<String>,
}

/// The whole session document, stored as JSON.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Session {
    /// Store id.
    pub id: i64,
    /// State.
    pub state: State,
    /// Why it failed or was cancelled.
    pub reason: Option<String>,
    /// The current step in words (with an ETA while soaking).
    pub progress: String,
    /// Settings: `[ab]` with the start call's arguments.
    pub options: AbConfig,
    /// Rounds so far; the last is the current one.
    pub rounds: Vec<Round>,
    /// Things the user should know (skew cleared, heaters turned off, …).
    pub notes: Vec<String>,
    /// Klipper's XY skew factor before the session cleared it.
    pub skew_before: Option<f64>,
    /// Unix time the print finished.
    pub print_done_unix: Option<f64>,
    /// The heaters were turned off by the hold limit.
    pub heaters_off: bool,
    /// The soak ran past `soak_max_s` and waits for the user's choice.
    #[serde(default)]
    pub soak_asking: bool,
    /// The user's answer (`print` or `wait`), taken by the runner.
    #[serde(default)]
    pub soak_choice: Option<String>,
    /// Since when the bed heats again after an apply that did not converge, so the next round's
    /// soak starts warm (Unix s); the hold limit bounds it.
    #[serde(default)]
    pub preheat_since_unix: Option<f64>,
    /// The last entry of readings saved: its pair and readings (a line sent again is told from
    /// new readings by it).
    #[serde(default)]
    pub last_entry: Option<(String, Vec<f64>)>,
}

impl Doc for Session {
    fn state_name(&self) -> String {
        self.state.name()
    }
}

/// The A/B calibration's settings: `[ab]` and `[soak]`.
#[derive(Debug, Clone, Default)]
pub struct AbSettings {
    /// `[ab]`: defaults of a session's options.
    pub defaults: AbConfig,
    /// `[soak]`: the bed soak detector.
    pub soak: SoakParams,
}

/// `klipcal_ab_start` / `KLIPCAL_AB_START`.
#[derive(Debug, Clone, PartialEq)]
pub struct StartRequest {
    /// Bed temperature, °C (0: unheated).
    pub bed_temp_c: Option<f64>,
    /// Nozzle temperature, °C.
    pub nozzle_temp_c: Option<f64>,
    /// `paper` or `full`.
    pub layout: Option<String>,
}

impl StartRequest {
    /// Reads the call's arguments.
    ///
    /// # Errors
    /// A bad or unknown argument, named.
    pub fn from_args(a: &Args) -> anyhow::Result<Self> {
        Ok(Self {
            bed_temp_c: a.num("bed")?,
            nozzle_temp_c: a.num("extruder")?,
            layout: a.choice("layout")?.map(str::to_string),
        })
    }
}

/// `klipcal_measure` / `KLIPCAL_MEASURE`.
#[derive(Debug, Clone, PartialEq)]
pub struct MeasureRequest {
    /// The pair id as typed.
    pub pair: String,
    /// The readings as typed, each with where it was typed ([`readings_typed`]).
    pub values: Vec<entry::Item>,
    /// Remove the pair's readings first (to enter them again, or to drop a wrong one).
    pub clear: bool,
}

impl MeasureRequest {
    /// Reads the call's arguments.
    ///
    /// # Errors
    /// No pair, a bad CLEAR, or an unknown argument.
    pub fn from_args(a: &Args) -> anyhow::Result<Self> {
        let pair = a.text("pair").ok_or_else(|| {
            user("no PAIR given; expected e.g. KLIPCAL_MEASURE PAIR=A-D1 VALUES=10.02,10.03,10.01")
        })?;
        let mut values = readings_typed(a.raw("values"), "VALUES");
        values.extend(readings_typed(a.raw("value"), "VALUE"));
        Ok(Self {
            pair,
            values,
            clear: a.flag("clear")?,
        })
    }
}

/// Readings as an argument carries them: a list of fields (the page, the API: one reading
/// each, a comma is its decimal mark), the console's `VALUES=` text (a list: commas separate,
/// a dot is the decimal mark) or `VALUE=` text (one reading).
fn readings_typed(v: Option<&Value>, key: &str) -> Vec<entry::Item> {
    match v {
        Some(Value::Array(list)) => list
            .iter()
            .enumerate()
            .filter_map(|(i, v)| match v {
                Value::String(s) => entry::field(s, i + 1),
                Value::Number(n) => n
                    .as_f64()
                    .map(|x| entry::sent_number(x, &format!("field {}", i + 1))),
                other => entry::field(&other.to_string(), i + 1),
            })
            .collect(),
        Some(Value::String(t)) if key == "VALUES" => entry::list(t),
        Some(Value::String(t)) => entry::single(t, key),
        Some(Value::Null) | None => Vec::new(),
        Some(Value::Number(n)) => n
            .as_f64()
            .map(|x| entry::sent_number(x, key))
            .into_iter()
            .collect(),
        Some(other) => entry::single(&other.to_string(), key),
    }
}

/// `klipcal_apply` / `KLIPCAL_AB_APPLY`.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct ApplyRequest {
    /// Apply a change beyond `ab.max_change_pct`.
    pub force: bool,
}

impl ApplyRequest {
    /// Reads the call's arguments.
    ///
    /// # Errors
    /// A bad FORCE, or an unknown argument.
    pub fn from_args(a: &Args) -> anyhow::Result<Self> {
        Ok(Self {
            force: a.flag("force")?,
        })
    }
}

/// `klipcal_ab_check` / `KLIPCAL_AB_CHECK`.
#[derive(Debug, Clone, PartialEq)]
pub struct CheckRequest {
    /// The pair id as typed.
    pub pair: String,
    /// The readings as typed, each with where it was typed.
    pub items: Vec<entry::Item>,
    /// The page's fields as sent (blank ones too), when the readings came as a list.
    pub fields: Option<Vec<String>>,
}

impl CheckRequest {
    /// Reads the call's arguments.
    ///
    /// # Errors
    /// No pair.
    pub fn from_args(a: &Args) -> anyhow::Result<Self> {
        let pair = a.text("pair").ok_or_else(|| {
            user("no PAIR given; expected e.g. KLIPCAL_AB_CHECK PAIR=A-D1 VALUES=10.02,10.03")
        })?;
        let fields = match a.fields("values") {
            Some(Fields::List(list)) => Some(list),
            _ => None,
        };
        Ok(Self {
            pair,
            items: readings_typed(a.raw("values"), "VALUES"),
            fields,
        })
    }
}

/// The A/B calibration over the shared core.
#[derive(Clone)]
pub struct Ab {
    core: Core,
    settings: AbSettings,
}

impl Ab {
    /// The calibration over `core`.
    #[must_use]
    pub fn new(core: Core, settings: AbSettings) -> Self {
        Self { core, settings }
    }

    fn load(&self, id: i64) -> anyhow::Result<Session> {
        self.core.load(id)
    }

    fn active(&self) -> anyhow::Result<Option<Session>> {
        Ok(self.core.active_of::<Session>(KIND)?.map(|(_, s)| s))
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
        let progress = progress.to_string();
        self.update(id, |s| {
            s.state = state;
            s.progress = progress;
            Ok(())
        })
        .await
    }

    /// After an apply that did not converge: Klipper's restart turned the bed off, so it heats
    /// again at once (the next round's soak then starts warm), owned by the session and bounded
    /// by the hold limit (klipcal's watchdog, and Klipper's idle timeout if klipcal is gone);
    /// a dialog offers the next round. Returns what the apply answer adds.
    async fn preheat_next_round(&self, s: &Session, round: usize) -> String {
        let bed = s.options.bed_temp_c;
        let hold_min = s.options.hold_max_s / 60.0;
        let mut said = String::new();
        if bed > 0.0 {
            let heated = async {
                BedSoak::heat(&self.core, bed).await?;
                self.core.hold_heaters_for(s.options.hold_max_s).await
            }
            .await;
            match heated {
                Ok(()) => {
                    let _ = self
                        .update(s.id, |d| {
                            d.preheat_since_unix = Some(now_unix());
                            d.heaters_off = false;
                            Ok(())
                        })
                        .await;
                    said = format!(
                        " The bed heats to {bed} °C again so that round {round} starts warm; \
                         it goes off after {hold_min:.0} min without KLIPCAL_AB_START \
                         (ab.hold_max_s), or with KLIPCAL_CANCEL."
                    );
                }
                Err(e) => {
                    warn!(error = %e, "no preheat for the next round");
                    let _ = self.core.heaters_off().await;
                }
            }
        }
        self.core
            .prompt(&Prompt {
                title: format!("klipcal: round {round}?"),
                lines: vec![format!(
                    "Not yet converged: round {round} prints new pylons with the new values{}.",
                    if said.is_empty() {
                        ""
                    } else {
                        " (the bed is heating again)"
                    }
                )],
                buttons: vec![Button::new(
                    &format!("Print round {round}"),
                    "KLIPCAL_AB_START",
                    "primary",
                )],
                footer: vec![Button::new("End", "_KLIPCAL_CANCEL_ASK", "secondary")],
            })
            .await;
        said
    }

    fn spawn_runner(&self, id: i64) {
        let (ab, ab2) = (self.clone(), self.clone());
        self.core.spawn_session(
            id,
            TITLE,
            move || {
                let ab = ab.clone();
                async move { ab.run(id).await }
            },
            move |msg| async move { ab2.fail(id, &msg).await },
        );
    }

    async fn fail(&self, id: i64, why: &str) {
        let off = self
            .core
            .heaters_off_once_back(&format!("{TITLE} failed: {why}"))
            .await;
        if let Err(e) = &off {
            warn!(session = id, error = %format!("{e:#}"), "heaters not turned off");
        }
        let _ = self
            .update(id, |s| {
                if !s.state.is_final() {
                    s.state = State::Failed;
                    s.reason = Some(why.to_string());
                    s.progress = "failed".into();
                }
                Ok(())
            })
            .await;
        self.core.prompt_end().await;
        let heaters = if off.is_ok() { "; heaters off" } else { "" };
        self.core
            .console_error(&format!("{TITLE} failed: {why}{heaters}"))
            .await;
    }

    /// Resumes a session after a daemon start or a reconnect.
    async fn resume_session(&self, id: i64) {
        let s = match self.load(id) {
            Ok(s) => s,
            Err(e) => {
                warn!(error = %e, "cannot read the active session");
                return;
            }
        };
        if s.state == State::Applying {
            // The apply was cut off: the files may or may not be edited; solve state is safe
            // to return to because apply checks what Klipper runs.
            let _ = self
                .update(s.id, |s| {
                    s.state = State::Solved;
                    s.notes.push(
                        "an apply was interrupted by a restart; check the values with \
                         KLIPCAL_STATUS and apply again"
                            .into(),
                    );
                    Ok(())
                })
                .await;
            return;
        }
        if s.state.is_automatic() {
            info!(session = s.id, state = %s.state.name(), "resuming session");
            self.spawn_runner(s.id);
        }
    }

    /// Sets the solved skew in Klipper, saves it as profile `klipcal` with SAVE_CONFIG, loads
    /// it, and says whether PRINT_START loads it at the next print (Klipper does not load skew
    /// profiles at start).
    async fn apply_skew(&self, set_skew: &str, start_macro: &str) -> anyhow::Result<String> {
        let m = self.core.m();
        m.gcode(set_skew).await?;
        m.gcode("SKEW_PROFILE SAVE=klipcal").await?;
        let (state, msg) =
            printer_config::restart_with(m, "SAVE_CONFIG", Duration::from_secs(60)).await?;
        if state != "ready" {
            return Err(anyhow!("Klipper is {state} after SAVE_CONFIG: {msg}"));
        }
        m.gcode("SKEW_PROFILE LOAD=klipcal").await?;
        let pc = printer_config::fetch(m, self.core.files()).await?;
        let configured = (!start_macro.is_empty()).then_some(start_macro);
        let saved = format!("skew saved as profile klipcal ({set_skew}) and loaded now");
        let add = "Klipper does not load skew profiles at start: add the line \
                   `SKEW_PROFILE LOAD=klipcal`";
        Ok(match klipper::find_start_macro(&pc.config, configured) {
            Ok(klipper::StartMacro::Found {
                command, section, ..
            }) => {
                let loads = pc
                    .config
                    .get(&section, "gcode")
                    .is_some_and(|g| g.to_uppercase().contains("SKEW_PROFILE LOAD=KLIPCAL"));
                if loads {
                    format!("skew saved as profile klipcal ({set_skew}); {command} loads it")
                } else {
                    format!("{saved}; {add} to your {command} macro")
                }
            }
            Ok(klipper::StartMacro::Ambiguous(names)) => format!(
                "{saved}; {add} to the start macro your slicer calls ({}; set ab.start_macro \
                 to name it)",
                names.join(" or ")
            ),
            Ok(klipper::StartMacro::NotFound) | Err(_) => {
                format!("{saved}; {add} to the start macro your slicer calls")
            }
        })
    }

    /// Sets Klipper's XY skew back to what it was before the session cleared it.
    async fn restore_skew(&self, xy_before: Option<f64>) {
        if let Some(cmd) = xy_before
            .filter(|v| *v != 0.0)
            .and_then(crate::calib::skew::set_skew_command)
        {
            if let Err(e) = self.core.m().gcode(&cmd).await {
                warn!(error = %e, "could not restore the skew correction");
            }
        }
    }

    /// Drives the automatic states until the session waits for the user or ends.
    async fn run(&self, id: i64) -> anyhow::Result<()> {
        loop {
            let s = self.load(id)?;
            match s.state {
                State::Preflight => self.preflight(s).await?,
                State::Uploaded => {
                    BedSoak::heat(&self.core, s.options.bed_temp_c).await?;
                    self.set_state(id, State::Heating, "bed heating").await?;
                }
                State::Heating | State::Soaking => self.soak(s).await?,
                State::Printing => self.print(s).await?,
                State::Holding => self.hold(s).await?,
                _ => return Ok(()),
            }
        }
    }

    /// Reads Klipper's current XY skew factor (GET_CURRENT_SKEW answers on the console).
    async fn current_skew(&self) -> Option<f64> {
        let mut rx = self.core.m().events();
        self.core.m().gcode("GET_CURRENT_SKEW").await.ok()?;
        let deadline = tokio::time::Instant::now() + Duration::from_secs(3);
        while let Ok(Ok(e)) = tokio::time::timeout_at(deadline, rx.recv()).await {
            if let crate::moonraker::Event::GcodeResponse(text) = e {
                if let Some(rest) = text.split("XY Skew:").nth(1) {
                    return rest.split_whitespace().next()?.parse().ok();
                }
            }
        }
        None
    }

    async fn preflight(&self, s: Session) -> anyhow::Result<()> {
        let id = s.id;
        self.core.printer_idle().await?;
        let pc = printer_config::fetch(self.core.m(), self.core.files()).await?;
        let facts = PrinterFacts::from_config(&pc.config)?;
        let mut missing = Vec::new();
        if !facts.has_virtual_sdcard {
            missing.push("[virtual_sdcard] (with path: ~/printer_data/gcodes)");
        }
        if !facts.has_respond {
            missing.push("[respond]");
        }
        if !facts.has_exclude_object {
            missing.push("[exclude_object]");
        }
        if s.options.shear_to == "klipper_skew" && !facts.has_skew_correction {
            missing.push("[skew_correction] (ab.shear_to = \"klipper_skew\")");
        }
        if !facts.has_heater_bed && s.options.bed_temp_c > 0.0 {
            missing.push("[heater_bed] (or start with BED=0)");
        }
        if !missing.is_empty() {
            return Err(user(format!(
                "the printer config lacks what the calibration needs; add to printer.cfg: {}",
                missing.join(", ")
            )));
        }
        let kinematics = match facts.kinematics {
            klipper::Kinematics::CoreXy => "corexy",
            klipper::Kinematics::Cartesian => "cartesian",
            klipper::Kinematics::Other(ref k) => {
                return Err(user(format!(
                    "kinematics `{k}`: klipcal calibrates corexy and cartesian printers"
                )))
            }
        };
        let mut notes = Vec::new();
        let mut skew_before = s.skew_before;
        if facts.has_skew_correction {
            let xy = self.current_skew().await.unwrap_or(0.0);
            if s.rounds.is_empty() {
                skew_before = Some(xy);
            }
            if xy != 0.0 {
                notes.push(format!(
                    "skew correction (XY factor {xy:.6}) cleared for the calibration print; it is restored afterwards"
                ));
            }
            self.core.m().gcode("SET_SKEW CLEAR=1").await?;
        }
        let gk = if kinematics == "corexy" {
            gcode::Kinematics::CoreXy
        } else {
            gcode::Kinematics::Cartesian
        };
        let machine = gcode::Machine::from_config(
            &pc.config,
            Some(gk),
            None,
            None,
            Some(s.options.start_macro.as_str()),
        )
        .map_err(|e| user(e.to_string()))?;
        let opts = gcode::Options {
            layout: if s.options.layout == "full" {
                LayoutKind::Full
            } else {
                LayoutKind::Paper
            },
            bed_temp_c: s.options.bed_temp_c,
            nozzle_temp_c: s.options.nozzle_temp_c,
            generated_at_unix_s: now_unix() as i64,
            ..gcode::Options::default()
        };
        let job = match gcode::generate(&machine, &opts) {
            Ok(j) => j,
            Err(gcode::Error::DoesNotFit {
                suggested_d2_mm: Some(d2),
                message,
            }) => {
                notes.push(format!(
                    "the default D2 does not fit this bed; using D2 = {d2} mm ({message})"
                ));
                gcode::generate(&machine, &gcode::Options { d2_mm: d2, ..opts })?
            }
            Err(e) => return Err(user(e.to_string())),
        };
        let n = s.rounds.len() as u32 + 1;
        let file = format!("klipcal/ab-s{id}-r{n}.gcode");
        let stepper = |st: &klipper::Stepper| StepperDoc {
            rotation_distance_mm: st.rotation_distance_mm,
            microsteps: st.microsteps,
            full_steps_per_rotation: st.full_steps_per_rotation,
            gear_ratio: st.gear_ratio,
        };
        let round = Round {
            n,
            file: file.clone(),
            layout: job.layout.clone(),
            kinematics: kinematics.into(),
            stepper_x: stepper(&facts.stepper_x),
            stepper_y: stepper(&facts.stepper_y),
            solution: None,
            applied: None,
            diagram: None,
            picture: None,
        };
        self.core
            .files()
            .upload("gcodes", &file, job.gcode.into_bytes())
            .await
            .context("uploading the pylon job")?;
        let diagram = format!("klipcal/ab-s{id}-r{n}.svg");
        let round = match self.core.save_picture(&diagram, job.svg).await {
            Some(shown) => Round {
                diagram: Some(diagram),
                picture: Some(shown),
                ..round
            },
            None => round,
        };
        let bed = if s.options.bed_temp_c > 0.0 {
            format!("heating the bed to {} °C", s.options.bed_temp_c)
        } else {
            "the bed stays unheated (BED=0)".to_string()
        };
        let msg = format!(
            "round {n}: {} pylons uploaded as {file}; {bed}",
            job.layout.pylons.len()
        );
        self.update(id, |s| {
            s.rounds.push(round);
            s.notes.extend(notes);
            s.skew_before = skew_before;
            s.state = State::Uploaded;
            s.progress = msg.clone();
            Ok(())
        })
        .await?;
        self.core.console(&format!("A/B calibration {msg}")).await;
        Ok(())
    }

    async fn soak(&self, s: Session) -> anyhow::Result<()> {
        let id = s.id;
        let hold_s = s.options.hold_max_s;
        let mut soak = BedSoak::new(
            self.settings.soak.clone(),
            s.options.bed_temp_c,
            s.options.soak_max_s,
            "ab.soak_max_s",
        );
        let mut last = String::new();
        let mut cost: Option<f64> = None;
        // Since when the soak question waits for an answer, and what it said.
        let mut asked: Option<(tokio::time::Instant, String)> = None;
        loop {
            let doc = self.load(id)?;
            // Print now, chosen while soaking (issue 29): from the moment the bed is in its band.
            if doc.soak_choice.as_deref() == Some("print") {
                if asked.is_some() {
                    self.core.prompt_end().await;
                }
                let words = cost.map_or_else(
                    || "what the surface may still warm is not known yet".to_string(),
                    |c| {
                        format!(
                            "the surface may still warm by up to {} (95 %)",
                            crate::calib::soak::kelvin_words(c)
                        )
                    },
                );
                let note = format!("the user chose to print now, before the bed settled: {words}");
                self.update(id, |s| {
                    s.soak_choice = None;
                    s.soak_asking = false;
                    s.notes.push(note.clone());
                    s.state = State::Printing;
                    s.progress = format!("printing now, as chosen ({words})");
                    Ok(())
                })
                .await?;
                self.core.console(&format!("{TITLE}: {note}")).await;
                return Ok(());
            }
            if let Some((_, line)) = &asked {
                if doc.soak_choice.as_deref() == Some("wait") {
                    self.core.prompt_end().await;
                    let note = format!("{line}; the user chose to wait 10 min more");
                    self.update(id, |s| {
                        s.soak_asking = false;
                        s.soak_choice = None;
                        s.notes.push(note);
                        s.progress = "soaking 10 min more, as chosen".into();
                        Ok(())
                    })
                    .await?;
                    soak.extend(SOAK_MORE_S);
                    asked = None;
                    last.clear();
                }
            }
            match soak.poll(&self.core, TITLE).await? {
                SoakUpdate::Stable { why } => {
                    if let Some((_, line)) = asked.take() {
                        // Settled while the question waited: what the user was waiting for.
                        self.core.prompt_end().await;
                        self.update(id, |s| {
                            s.soak_asking = false;
                            s.soak_choice = None;
                            s.notes
                                .push(format!("{line}; the bed settled while the question waited"));
                            Ok(())
                        })
                        .await?;
                    }
                    let n = s.rounds.len();
                    let path = format!("klipcal/ab-s{id}-r{n}-soak.svg");
                    let plot =
                        super::soak::save_soak_picture(&self.core, &self.settings.soak, &path)
                            .await
                            .map(|p| format!("; plot: {p}"))
                            .unwrap_or_default();
                    self.set_state(
                        id,
                        State::Printing,
                        &format!("bed stable ({why}){plot}; printing"),
                    )
                    .await?;
                    return Ok(());
                }
                SoakUpdate::Heating => {
                    if last != "heating" {
                        self.set_state(id, State::Heating, "bed heating").await?;
                        last = "heating".into();
                    }
                }
                SoakUpdate::Soaking {
                    text, print_now_c, ..
                } => {
                    cost = print_now_c.or(cost);
                    if asked.is_none() && last != text {
                        self.set_state(id, State::Soaking, &text).await?;
                        last = text;
                    }
                }
                SoakUpdate::TooLong {
                    minutes,
                    falling_pct_per_10min,
                } => match &asked {
                    None => {
                        // The question waits within the hold limit; the bed stays hot and the
                        // soak goes on meanwhile (Klipper owns the bed for that long: the
                        // extension sets its idle timeout), so that no answer costs nothing
                        // but time (issue 26 A.1).
                        soak.extend(hold_s);
                        let line = self
                            .ask_soak_choice(id, minutes, falling_pct_per_10min, hold_s)
                            .await?;
                        asked = Some((tokio::time::Instant::now(), line));
                    }
                    Some((since, line)) => {
                        self.core.prompt_end().await;
                        return Err(user(format!(
                            "no answer to the soak question within {:.0} min (ab.hold_max_s) \
                             and the bed has not settled ({line})",
                            since.elapsed().as_secs_f64() / 60.0
                        )));
                    }
                },
            }
            tokio::time::sleep(Duration::from_millis(250)).await;
        }
    }

    /// The bed is at its target but its power still moves after `soak_max_s`: asks print now
    /// / wait 10 min more / cancel, and says what happens without an answer (the bed stays hot
    /// and the soak goes on up to `hold_s`). The runner takes the answer; returns the line
    /// that says why it asks.
    ///
    /// # Errors
    /// Store failures.
    async fn ask_soak_choice(
        &self,
        id: i64,
        minutes: f64,
        falling: Option<f64>,
        hold_s: f64,
    ) -> anyhow::Result<String> {
        let line = match falling {
            Some(f) => format!(
                "bed power still {} by {:.1} % per 10 min after {minutes:.0} min (ab.soak_max_s)",
                if f < 0.0 { "rising" } else { "falling" },
                f.abs()
            ),
            None => format!("the bed has not settled after {minutes:.0} min (ab.soak_max_s)"),
        };
        let hold_min = (hold_s / 60.0).ceil();
        let how = format!(
            "waiting for your answer: KLIPCAL_SOAK_CHOICE CHOICE=print prints now, CHOICE=wait \
             waits 10 min more, KLIPCAL_CANCEL ends the session. Without an answer the bed stays \
             hot and the soak goes on (printing once it settles) for up to {hold_min:.0} min \
             (ab.hold_max_s), then the heaters go off"
        );
        self.update(id, |s| {
            s.soak_asking = true;
            s.soak_choice = None;
            s.progress = format!("{line}: {how}");
            Ok(())
        })
        .await?;
        self.core
            .say_and_prompt(
                &format!("{TITLE}: {line}: {how}"),
                &Prompt {
                    title: "klipcal: the bed has not settled".into(),
                    lines: vec![
                        line.clone(),
                        format!(
                            "Print now: the readings may carry some thermal drift. Wait: 10 more \
                             minutes. No answer: the bed stays hot and klipcal keeps waiting, up \
                             to {hold_min:.0} min. Cancel: heaters off."
                        ),
                    ],
                    buttons: vec![
                        Button::new("Print now", "KLIPCAL_SOAK_CHOICE CHOICE=print", "warning"),
                        Button::new("Wait 10 min", "KLIPCAL_SOAK_CHOICE CHOICE=wait", "primary"),
                    ],
                    footer: vec![Button::cancel_asking()],
                },
            )
            .await;
        Ok(line)
    }

    /// `klipcal_soak_choice CHOICE=print|wait`: answers the soak prompt.
    ///
    /// # Errors
    /// A bad CHOICE, or no soak waiting for one.
    pub async fn soak_choice(&self, choice: &'static str) -> anyhow::Result<Value> {
        let s = match self.active()? {
            Some(s) if s.soak_asking => s,
            // Print now is offered from the moment the bed is in its band (issue 29).
            Some(s) if s.state == State::Soaking && choice == "print" => s,
            _ => {
                return Err(user(
                    "nothing to choose: no bed soak is waiting for an answer (CHOICE=print is \
                     taken while the bed soaks at its target)",
                ))
            }
        };
        self.update(s.id, |d| {
            d.soak_choice = Some(choice.to_string());
            Ok(())
        })
        .await?;
        Ok(json!({"session": s.id, "choice": choice,
                  "message": if choice == "print" { "printing now" } else { "waiting 10 min more" }}))
    }

    async fn print(&self, s: Session) -> anyhow::Result<()> {
        let id = s.id;
        let round = s
            .rounds
            .last()
            .ok_or_else(|| anyhow!("session has no round"))?;
        let st = self
            .core
            .m()
            .objects_query(json!({"print_stats": ["state", "filename"]}))
            .await?;
        let ps = &st["print_stats"];
        let ours = ps["filename"].as_str() == Some(round.file.as_str());
        let state = ps["state"].as_str().unwrap_or("");
        if !(ours && matches!(state, "printing" | "paused" | "complete")) {
            self.core.printer_idle().await?;
            // Klipper keeps the heaters on while it prints; once the print ends, it turns them
            // off by itself after the hold limit if klipcal is not there to do it.
            self.core.hold_heaters_for(s.options.hold_max_s).await?;
            self.core.m().print_start(&round.file).await?;
            self.core
                .console(&format!("A/B calibration: printing {}", round.file))
                .await;
        }
        let mut standby = 0;
        loop {
            tokio::time::sleep(Duration::from_millis(500)).await;
            let st = match self
                .core
                .m()
                .objects_query(json!({"print_stats": ["state", "filename", "message"]}))
                .await
            {
                Ok(st) => st,
                Err(e) => {
                    // Klipper restarting or Moonraker away: keep watching; a shutdown shows up
                    // as print_stats error once Klipper is back.
                    warn!(error = %e, "print status unavailable");
                    continue;
                }
            };
            let ps = &st["print_stats"];
            match ps["state"].as_str().unwrap_or("") {
                "complete" => {
                    self.update(id, |s| {
                        s.state = State::Holding;
                        s.print_done_unix = Some(now_unix());
                        s.progress = "print done; the part cools on the hot bed".into();
                        Ok(())
                    })
                    .await?;
                    return Ok(());
                }
                "cancelled" => {
                    let _ = self.core.heaters_off().await;
                    self.update(id, |s| {
                        s.state = State::Cancelled;
                        s.reason = Some("the calibration print was cancelled".into());
                        s.progress = "cancelled".into();
                        Ok(())
                    })
                    .await?;
                    self.core
                        .console("A/B calibration cancelled: the print was cancelled; heaters off")
                        .await;
                    return Ok(());
                }
                "error" => {
                    return Err(anyhow!(
                        "the calibration print failed: {}",
                        ps["message"].as_str().unwrap_or("Klipper error")
                    ))
                }
                "standby" => {
                    // Klipper forgot the print: it shut down or restarted mid-print. Two looks
                    // a moment apart, so a print just being started is not mistaken for it.
                    standby += 1;
                    if standby >= 3 {
                        return Err(anyhow!(if self.core.klipper_ready().await {
                            "the calibration print stopped: Klipper restarted during the print"
                        } else {
                            "Klipper shut down during the calibration print"
                        }));
                    }
                }
                _ => standby = 0,
            }
        }
    }

    async fn hold(&self, s: Session) -> anyhow::Result<()> {
        let id = s.id;
        // Klipper itself turns the heaters off at the hold limit (counted from the print's
        // end, also when the hold resumes after an outage), even if klipcal stops.
        let done = s.print_done_unix.unwrap_or_else(now_unix);
        let hold = (done + s.options.hold_max_s - now_unix()).max(1.0);
        self.core.hold_heaters_for(hold).await?;
        let wait = (done + s.options.cooldown_s - now_unix()).max(0.0);
        if wait > 0.0 {
            self.core.console(&format!(
                "A/B calibration: print done; the part cools on the hot bed for {wait:.0} s before measuring"
            ))
            .await;
            tokio::time::sleep(Duration::from_secs_f64(wait)).await;
        }
        self.set_state(id, State::Measuring, "waiting for caliper readings")
            .await?;
        let s = self.load(id)?;
        // The console carries the whole guide; the dialog only what to do and where to look,
        // so the console does not read the guide twice.
        let guide = measuring_guide(&s, self.core.page());
        self.core
            .say_and_prompt(
                &guide.join("\n"),
                &Prompt {
                    title: format!("klipcal: measure the pylons (round {})", s.rounds.len()),
                    lines: measuring_dialog(&s),
                    buttons: vec![Button::new(
                        "Close and type readings",
                        "_KLIPCAL_PROMPT_CLOSE",
                        "primary",
                    )],
                    footer: Vec::new(),
                },
            )
            .await;
        Ok(())
    }

    fn readings(&self, s: &Session) -> anyhow::Result<BTreeMap<String, Vec<f64>>> {
        let n = s.rounds.len() as i64;
        let mut out: BTreeMap<String, Vec<f64>> = BTreeMap::new();
        for r in self.core.store().readings(s.id, n)? {
            out.entry(r.pair).or_default().push(r.value_mm);
        }
        Ok(out)
    }

    fn missing_lines(&self, s: &Session) -> anyhow::Result<Vec<String>> {
        let round = s.rounds.last().ok_or_else(|| anyhow!("no round"))?;
        let have = self.readings(s)?;
        let mut lines = Vec::new();
        for p in &round.layout.pairs {
            let got = have.get(&p.id).map_or(0, Vec::len);
            if got < s.options.readings_per_pair {
                lines.push(format!(
                    "{} ({}→{}, nominal {} mm): {} of {} readings; KLIPCAL_MEASURE PAIR={} VALUES={},…",
                    p.id,
                    p.from,
                    p.to,
                    entry::fmt_mm(p.nominal_mm),
                    got,
                    s.options.readings_per_pair,
                    p.id,
                    entry::example(p.nominal_mm)
                ));
            }
        }
        Ok(lines)
    }

    /// `klipcal_ab_start`: starts a session (or the next round of an applied one).
    ///
    /// # Errors
    /// A session already running, bad arguments, or a printer that is printing.
    pub async fn start(&self, req: &StartRequest) -> anyhow::Result<Value> {
        let d = &self.settings.defaults;
        let bed = req.bed_temp_c.unwrap_or(d.bed_temp_c);
        let nozzle = req.nozzle_temp_c.unwrap_or(d.nozzle_temp_c);
        let layout = req.layout.clone().unwrap_or_else(|| d.layout.clone());
        self.core.refuse_other_kind(KIND)?;
        self.core.printer_idle().await?;
        let next_round = {
            let _g = self.core.lock().await;
            match self.active()? {
                Some(mut s) if s.state == State::Applied => {
                    s.state = State::Preflight;
                    s.progress = format!("round {}: preflight", s.rounds.len() + 1);
                    s.options.bed_temp_c = bed;
                    s.options.nozzle_temp_c = nozzle;
                    s.options.layout.clone_from(&layout);
                    s.print_done_unix = None;
                    s.heaters_off = false;
                    s.preheat_since_unix = None;
                    self.core.save(s.id, &s)?;
                    Some(s.id)
                }
                _ => None,
            }
        };
        let id = match next_round {
            Some(id) => id,
            None => {
                let options = AbConfig {
                    layout,
                    bed_temp_c: bed,
                    nozzle_temp_c: nozzle,
                    ..d.clone()
                };
                let mut s = Session {
                    id: 0,
                    state: State::Preflight,
                    reason: None,
                    progress: "preflight".into(),
                    options,
                    rounds: Vec::new(),
                    notes: Vec::new(),
                    skew_before: None,
                    print_done_unix: None,
                    heaters_off: false,
                    soak_asking: false,
                    soak_choice: None,
                    preheat_since_unix: None,
                    last_entry: None,
                };
                self.core.create(KIND, &mut s, |s, id| s.id = id).await?
            }
        };
        self.spawn_runner(id);
        Ok(json!({"session": id, "state": "preflight",
                  "message": format!("{TITLE} session {id} started: checking the printer")}))
    }

    fn measuring(&self) -> anyhow::Result<Session> {
        match self.active()? {
            Some(s) if matches!(s.state, State::Measuring | State::Solved) => Ok(s),
            Some(s) => Err(user(format!(
                "session {} is {} ({}); readings are taken once the print is done and the part has cooled",
                s.id,
                s.state.name(),
                s.progress
            ))),
            None => Err(user("no calibration session; start one with KLIPCAL_AB_START")),
        }
    }

    /// `klipcal_measure`: saves one entry of readings for a pair, whole or not at all; with
    /// CLEAR=1 first removes the pair's readings (logged in the session's notes). Any change
    /// of the readings after solving drops the solution: apply waits for a new solve.
    ///
    /// # Errors
    /// No session waiting for readings, an unknown pair, or an entry refused (nothing saved).
    pub async fn measure(&self, req: &MeasureRequest) -> anyhow::Result<Value> {
        let s = self.measuring()?;
        let (pair, window) = pair_window(&s, &req.pair)?;
        let values = if req.values.is_empty() && req.clear {
            Vec::new()
        } else {
            entry::parse(&req.values, &pair.id, &window)
                .map_err(|e| user(format!("{}: nothing saved; {}", pair.id, e.0)))?
        };
        let n = s.rounds.len() as i64;
        let per_pair = s.options.readings_per_pair;
        if !req.clear && !values.is_empty() {
            // The last entry sent again (a re-sent console line, a double tap) would double the
            // pair's readings: refused, with the way to replace them. A new reading that
            // happens to equal an earlier one is not an entry sent again.
            let have = self.readings(&s)?.remove(&pair.id).unwrap_or_default();
            let again = s.last_entry.as_ref().is_some_and(|(p, last)| {
                *p == pair.id
                    && last.len() == values.len()
                    && last.iter().zip(&values).all(|(a, b)| (a - b).abs() < 1e-9)
            });
            if again && have.len() + values.len() > per_pair {
                return Err(user(format!(
                    "{}: nothing saved: these {} reading(s) are already saved (the same entry \
                     sent again?), {} of {per_pair} in all. To enter the pair again, replace its \
                     readings: KLIPCAL_MEASURE PAIR={} CLEAR=1 VALUES=…",
                    pair.id,
                    values.len(),
                    have.len(),
                    pair.id
                )));
            }
        }
        let mut notes = Vec::new();
        if req.clear {
            let old: Vec<String> = self
                .readings(&s)?
                .remove(&pair.id)
                .unwrap_or_default()
                .iter()
                .map(|v| entry::fmt_mm(*v))
                .collect();
            self.core.store().clear_readings(s.id, n, &pair.id)?;
            notes.push(format!(
                "{}: readings removed by CLEAR=1: {}",
                pair.id,
                if old.is_empty() {
                    "none".to_string()
                } else {
                    old.join(", ")
                }
            ));
        }
        if !values.is_empty() {
            self.core.store().add_readings(s.id, n, &pair.id, &values)?;
        }
        let was_solved = s.state == State::Solved;
        if was_solved {
            notes.push(
                "the readings changed after solving: the solution was dropped; solve again".into(),
            );
        }
        let logged = notes.clone();
        let entry = (!values.is_empty()).then(|| (pair.id.clone(), values.clone()));
        self.update(s.id, |s| {
            s.notes.extend(logged);
            if entry.is_some() || req.clear {
                s.last_entry.clone_from(&entry);
            }
            if s.state == State::Solved {
                s.state = State::Measuring;
                s.progress = "waiting for caliper readings".into();
                if let Some(r) = s.rounds.last_mut() {
                    r.solution = None;
                }
            }
            Ok(())
        })
        .await?;
        if was_solved {
            // The Apply prompt is no longer true.
            self.core.prompt_end().await;
        }
        let s = self.load(s.id)?;
        let have = self.readings(&s)?;
        let count = have.get(&pair.id).map_or(0, Vec::len);
        let missing = self.missing_lines(&s)?;
        let mut message = String::new();
        for n in &notes {
            message.push_str(n);
            message.push('\n');
        }
        message.push_str(&format!(
            "{}: {} reading(s) saved, {count} of {} in all",
            pair.id,
            values.len(),
            s.options.readings_per_pair
        ));
        if count > s.options.readings_per_pair && !values.is_empty() {
            message.push_str(&format!(
                " — more than the {} asked for (all are used); if some were wrong, replace \
                 them: KLIPCAL_MEASURE PAIR={} CLEAR=1 VALUES=…",
                s.options.readings_per_pair, pair.id
            ));
        }
        let round = s.rounds.last().ok_or_else(|| anyhow!("no round"))?;
        let progress = pairs_progress(&round.layout.pairs, &have, s.options.readings_per_pair);
        message.push('\n');
        message.push_str(&progress);
        if missing.is_empty() && s.state == State::Measuring {
            message.push_str("\nall pairs measured: KLIPCAL_AB_SOLVE computes the new values");
            // A decision its buttons can answer: solve now, or close and look again.
            self.core
                .prompt(&Prompt {
                    title: format!("klipcal: all pairs measured (round {})", s.rounds.len()),
                    lines: vec![progress.clone()],
                    buttons: vec![Button::new("Solve", "KLIPCAL_AB_SOLVE", "primary")],
                    footer: vec![Button::new("Close", "_KLIPCAL_PROMPT_CLOSE", "secondary")],
                })
                .await;
        }
        Ok(json!({"pair": pair.id, "saved": values, "count": count,
                  "readings": have.get(&pair.id).cloned().unwrap_or_default(),
                  "missing": missing, "message": message}))
    }

    /// `klipcal_ab_check`: judges an entry by the rules [`Ab::measure`] applies, field by field
    /// (a JSON list: one form field each; text: one item each) and as a whole; saves nothing
    /// (the page's live validation).
    ///
    /// # Errors
    /// No session waiting for readings, an unknown pair, or a bad argument.
    pub fn check(&self, req: &CheckRequest) -> anyhow::Result<Value> {
        let typed_items = &req.items;
        let s = self.measuring()?;
        let (pair, window) = pair_window(&s, &req.pair)?;
        // One answer per field as sent (blank fields too), so the page marks the field the
        // user typed in; a console list: one per item.
        let per_field: Vec<Value> = match &req.fields {
            Some(texts) => texts
                .iter()
                .enumerate()
                .map(|(i, t)| {
                    let item = typed_items
                        .iter()
                        .find(|it| it.label == format!("field {}", i + 1));
                    item_answer(t, item, &pair.id, &window)
                })
                .collect(),
            None => typed_items
                .iter()
                .map(|it| item_answer(&it.text, Some(it), &pair.id, &window))
                .collect(),
        };
        let whole = entry::parse(typed_items, &pair.id, &window);
        let message = match &whole {
            Ok(v) => format!(
                "{}: {} reading(s) would be accepted (plausible {:.2}–{:.2} mm); nothing saved",
                pair.id,
                v.len(),
                window.nominal_mm - window.half_width_mm(),
                window.nominal_mm + window.half_width_mm()
            ),
            Err(e) => format!("{}: would be refused; {}", pair.id, e.0),
        };
        let items = per_field;
        Ok(json!({
            "pair": pair.id,
            "nominal_mm": pair.nominal_mm,
            "window_mm": [window.nominal_mm - window.half_width_mm(),
                          window.nominal_mm + window.half_width_mm()],
            "valid": whole.is_ok(),
            "message": message,
            "items": items,
        }))
    }

    /// `klipcal_solve`: computes new rotation distances from the readings.
    ///
    /// # Errors
    /// Readings missing or inconsistent (the solver's message names the pair).
    pub async fn solve(&self) -> anyhow::Result<Value> {
        let s = self.measuring()?;
        let round = s.rounds.last().ok_or_else(|| anyhow!("no round"))?.clone();
        let raw = self.readings(&s)?;
        let stepper = |d: &StepperDoc| StepperFacts {
            rotation_distance_mm: d.rotation_distance_mm,
            microsteps: d.microsteps,
            full_steps_per_rotation: d.full_steps_per_rotation,
            gear_ratio: d.gear_ratio,
        };
        let facts = MotionFacts {
            kinematics: if round.kinematics == "corexy" {
                CalibKinematics::CoreXy
            } else {
                CalibKinematics::Cartesian
            },
            stepper_x: stepper(&round.stepper_x),
            stepper_y: stepper(&round.stepper_y),
        };
        let mut opts = SolveOptions {
            shear_to: if s.options.shear_to == "klipper_skew" {
                ShearTo::KlipperSkew
            } else {
                ShearTo::Motors
            },
            ..SolveOptions::default()
        };
        // The caliper's last digit is part of every reading's uncertainty.
        opts.rules.resolution_mm = s.options.caliper_resolution_mm;
        if s.rounds.len() > 1 {
            let prev = &s.rounds[s.rounds.len() - 2];
            opts.previous = prev.solution.as_ref().map(|sol| {
                sol.groups
                    .iter()
                    .map(|g| (g.group.clone(), g.scale))
                    .collect()
            });
        }
        let solution =
            solve(&round.layout, &raw, &facts, &opts).map_err(|e| user(e.to_string()))?;
        let decision = solution_text(&solution);
        let mut message = decision.clone();
        let sol = serde_json::to_value(&solution)?;
        self.update(s.id, |s| {
            if let Some(r) = s.rounds.last_mut() {
                r.solution = Some(solution);
            }
            s.state = State::Solved;
            s.progress = "solved; apply with KLIPCAL_AB_APPLY".into();
            Ok(())
        })
        .await?;
        // The rounds so far as a picture where Mainsail/Fluidd's file browser shows it.
        let doc = self.session_status(&self.load(s.id)?)?;
        if let Ok(svg) = crate::plots::convergence_of_status(&doc) {
            let path = format!("klipcal/ab-s{}-convergence.svg", s.id);
            if let Some(shown) = self.core.save_picture(&path, svg).await {
                message.push_str(&format!("\nplot of the rounds: {shown}"));
            }
        }
        self.core
            .prompt(&Prompt {
                title: "klipcal: new rotation distances".into(),
                lines: decision.lines().map(str::to_string).collect(),
                buttons: vec![Button::new("Apply", "KLIPCAL_AB_APPLY", "primary")],
                footer: vec![Button::new("Close", "_KLIPCAL_PROMPT_CLOSE", "secondary")],
            })
            .await;
        Ok(json!({"solution": sol, "message": message}))
    }

    /// `klipcal_apply`: writes the solved values, restarts Klipper, verifies, rolls back on
    /// failure.
    ///
    /// # Errors
    /// Nothing solved, a print running, an implausible change without FORCE, or Klipper failing
    /// on the new values (rolled back).
    pub async fn apply(&self, req: &ApplyRequest) -> anyhow::Result<Value> {
        let s = match self.active()? {
            Some(s) if s.state == State::Solved => s,
            Some(s) => {
                return Err(user(format!(
                    "session {} is {}; apply follows KLIPCAL_AB_SOLVE",
                    s.id,
                    s.state.name()
                )))
            }
            None => return Err(user("no calibration session to apply")),
        };
        self.core.printer_idle().await?;
        let round = s.rounds.last().ok_or_else(|| anyhow!("no round"))?.clone();
        let sol = round
            .solution
            .clone()
            .ok_or_else(|| anyhow!("no solution"))?;
        let mut values = Vec::new();
        for (name, st) in [("stepper_x", &sol.stepper_x), ("stepper_y", &sol.stepper_y)] {
            let change = (st.scale - 1.0).abs() * 100.0;
            if change > s.options.max_change_pct && !req.force {
                return Err(user(format!(
                    "{name}: a {change:.2} % change is implausible (limit {} %, ab.max_change_pct); \
                     check the readings, or apply with FORCE=1",
                    s.options.max_change_pct
                )));
            }
            values.push(ValueSet {
                section: name.into(),
                key: "rotation_distance".into(),
                value: entry::fmt_rd(st.rotation_distance_new),
            });
        }
        let unchanged = [
            (&sol.stepper_x, &round.stepper_x),
            (&sol.stepper_y, &round.stepper_y),
        ]
        .iter()
        .all(|(new, old)| {
            entry::fmt_rd(new.rotation_distance_new) == entry::fmt_rd(old.rotation_distance_mm)
        });
        // Closed at once: applying takes a Klipper restart, and Apply must not be pressed twice.
        self.core.prompt_end_now().await;
        if unchanged {
            let msg = format!(
                "already calibrated: stepper_x {} and stepper_y {} mm are what Klipper runs; \
                 nothing written, Klipper not restarted",
                entry::fmt_rd(round.stepper_x.rotation_distance_mm),
                entry::fmt_rd(round.stepper_y.rotation_distance_mm)
            );
            self.update(s.id, |s| {
                s.state = State::Converged;
                s.progress.clone_from(&msg);
                Ok(())
            })
            .await?;
            self.restore_skew(s.skew_before).await;
            return Ok(json!({"state": "converged", "message": msg}));
        }
        self.set_state(s.id, State::Applying, "writing the new rotation distances")
            .await?;
        let result = async {
            let pc = printer_config::fetch(self.core.m(), self.core.files()).await?;
            printer_config::apply(
                self.core.m(),
                self.core.files(),
                &pc,
                &values,
                &printer_config::stamp(now_unix() as u64),
            )
            .await
        }
        .await;
        match result {
            Ok(report) => {
                let converged = sol.converged;
                let next = if converged {
                    State::Converged
                } else {
                    State::Applied
                };
                let skew_before = s.skew_before;
                let msg = format!(
                    "applied: {}; backups in config/{}. {}{}",
                    report
                        .changes
                        .iter()
                        .map(|(sec, k, o, n)| format!("[{sec}] {k} {o} → {n}"))
                        .collect::<Vec<_>>()
                        .join(", "),
                    report.backup_dir,
                    report
                        .notes
                        .iter()
                        .map(|n| format!("{n}. "))
                        .collect::<String>(),
                    if converged {
                        "Converged: the calibration is done."
                    } else {
                        "Not yet converged: print the next round with KLIPCAL_AB_START."
                    }
                );
                let next_round = s.rounds.len() + 1;
                self.update(s.id, |s| {
                    if let Some(r) = s.rounds.last_mut() {
                        r.applied = Some(report.clone());
                    }
                    s.state = next;
                    s.progress = msg.clone();
                    Ok(())
                })
                .await?;
                // Klipper restarted: heaters are off and the idle timeout is the configured
                // one again. Then the skew: the new one, or the one from before the session.
                let skew_note = match sol.skew.set_skew.as_deref() {
                    Some(cmd) if sol.skew.applied => {
                        Some(match self.apply_skew(cmd, &s.options.start_macro).await {
                            Ok(note) => note,
                            Err(e) => format!(
                                "the rotation distances are applied, but the skew was not \
                             saved: {e:#}; set it by hand with {cmd}"
                            ),
                        })
                    }
                    _ => {
                        self.restore_skew(skew_before).await;
                        None
                    }
                };
                if let Some(note) = &skew_note {
                    self.update(s.id, |s| {
                        s.notes.push(note.clone());
                        Ok(())
                    })
                    .await?;
                    self.core.console(&format!("{TITLE}: {note}")).await;
                }
                let mut msg = msg;
                if next == State::Applied {
                    msg.push_str(&self.preheat_next_round(&s, next_round).await);
                }
                Ok(json!({"state": next.name(), "applied": report, "message": msg}))
            }
            Err(e) => {
                let why = format!("{e:#}");
                self.update(s.id, |s| {
                    s.state = State::Solved;
                    s.progress = format!("apply failed: {why}");
                    s.notes.push(format!("apply failed: {why}"));
                    Ok(())
                })
                .await?;
                Err(user(format!("apply failed: {why}")))
            }
        }
    }

    /// Cancels the session: its print cancelled, heaters off, skew restored, prompt closed.
    async fn cancel_session(&self, id: i64, reason: &str) -> anyhow::Result<Value> {
        let s = self.load(id)?;
        if s.state == State::Printing {
            let _ = self.core.m().gcode("CANCEL_PRINT").await;
        }
        let _ = self.core.heaters_off().await;
        self.update(s.id, |s| {
            s.state = State::Cancelled;
            s.reason = Some(reason.to_string());
            s.progress = "cancelled; heaters off".into();
            Ok(())
        })
        .await?;
        self.restore_skew(s.skew_before).await;
        self.core.prompt_end().await;
        Ok(json!({"session": s.id, "state": "cancelled",
                  "message": format!("session {} cancelled ({reason}); heaters off", s.id)}))
    }

    /// A session as `klipcal_status` shows it.
    fn session_status(&self, s: &Session) -> anyhow::Result<Value> {
        let readings = self.readings(s)?;
        let rounds: Vec<Value> = s
            .rounds
            .iter()
            .map(|r| {
                let sol = r.solution.as_ref();
                json!({
                    "n": r.n,
                    "file": r.file,
                    "rotation_distance": [r.stepper_x.rotation_distance_mm, r.stepper_y.rotation_distance_mm],
                    "rotation_distance_new": sol.map(|s| json!([s.stepper_x.rotation_distance_new, s.stepper_y.rotation_distance_new])),
                    "scale": sol.map(|s| json!([s.stepper_x.scale, s.stepper_y.scale])),
                    "error_um_per_100mm": sol.map(|s| {
                        ((s.stepper_x.scale - 1.0) * 1e5).abs().max(((s.stepper_y.scale - 1.0) * 1e5).abs())
                    }),
                    "uncertainty": sol.map(|s| json!([s.stepper_x.uncertainty, s.stepper_y.uncertainty])),
                    "converged": sol.map(|s| s.converged),
                    "applied": r.applied,
                })
            })
            .collect();
        Ok(json!({
            "id": s.id,
            "state": s.state.name(),
            "progress": s.progress,
            "reason": s.reason,
            "round": s.rounds.len(),
            "pairs": s.rounds.last().map(|r| json!(r.layout.pairs)),
            "file": s.rounds.last().map(|r| r.file.clone()),
            "readings": readings,
            "readings_per_pair": s.options.readings_per_pair,
            "bed_temp_c": s.options.bed_temp_c,
            "diagram": s.rounds.last().and_then(|r| r.diagram.clone()),
            "missing": if matches!(s.state, State::Measuring | State::Solved) { json!(self.missing_lines(s)?) } else { json!([]) },
            "rounds": rounds,
            "notes": s.notes,
            "heaters_off": s.heaters_off,
        }))
    }
}

impl Calibration for Ab {
    fn kind(&self) -> &'static str {
        KIND
    }

    fn title(&self) -> &'static str {
        "an A/B calibration"
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
            match AbCall::parse(method, args)? {
                AbCall::Start(r) => self.start(&r).await,
                AbCall::Measure(r) => self.measure(&r).await,
                AbCall::Solve => self.solve().await,
                AbCall::Apply(r) => self.apply(&r).await,
                AbCall::Check(r) => self.check(&r),
                AbCall::SoakChoice(c) => self.soak_choice(c).await,
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
        self.session_status(&s)
    }

    fn held(&self, row: &SessionRow) -> Option<Hold> {
        let s: Session = serde_json::from_value(row.doc.clone()).ok()?;
        let waiting = matches!(s.state, State::Holding | State::Measuring | State::Solved);
        if s.heaters_off {
            return None;
        }
        if s.state == State::Applied {
            // The bed heating again for the next round.
            return Some(Hold {
                since_unix: s.preheat_since_unix?,
                max_s: s.options.hold_max_s,
            });
        }
        waiting.then_some(Hold {
            since_unix: s.print_done_unix?,
            max_s: s.options.hold_max_s,
        })
    }

    fn heaters_turned_off<'a>(&'a self, row: &'a SessionRow) -> BoxFuture<'a, ()> {
        async move {
            let _ = self
                .update(row.id, |s| {
                    s.heaters_off = true;
                    s.notes.push(format!(
                        "heaters turned off: the hold limit of {} s after the {} passed (ab.hold_max_s)",
                        s.options.hold_max_s,
                        if s.state == State::Applied { "apply" } else { "print" }
                    ));
                    Ok(())
                })
                .await;
            self.core
                .console(&format!("{TITLE}: hold limit reached, heaters off"))
                .await;
        }
        .boxed()
    }
}

/// Every pair's count of readings in one line: `A-D1 5/5 ✓ · A-D2 2/5 · …`.
fn pairs_progress(
    pairs: &[crate::layout::Pair],
    have: &BTreeMap<String, Vec<f64>>,
    per_pair: usize,
) -> String {
    pairs
        .iter()
        .map(|p| {
            let n = have.get(&p.id).map_or(0, Vec::len);
            format!(
                "{} {n}/{per_pair}{}",
                p.id,
                if n >= per_pair { " ✓" } else { "" }
            )
        })
        .collect::<Vec<_>>()
        .join(" · ")
}

/// The check's answer for one field or item: its value, or the problem alone (the page
/// shows it beside the field).
fn item_answer(
    text: &str,
    item: Option<&entry::Item>,
    pair: &str,
    window: &entry::Window,
) -> Value {
    let one = item.map(|it| entry::one(it, pair, window));
    json!({
        "text": text,
        "values": one.as_ref().and_then(|r| r.as_ref().ok()).map(|v| vec![*v]),
        "error": one.and_then(Result::err),
    })
}

/// The round's pair named `typed` (any case) and its plausibility window.
fn pair_window(s: &Session, typed: &str) -> anyhow::Result<(crate::layout::Pair, entry::Window)> {
    let round = s.rounds.last().ok_or_else(|| anyhow!("no round"))?;
    let Some(pair) = round
        .layout
        .pairs
        .iter()
        .find(|p| p.id.eq_ignore_ascii_case(typed))
        .cloned()
    else {
        let ids: Vec<&str> = round.layout.pairs.iter().map(|p| p.id.as_str()).collect();
        return Err(user(format!(
            "unknown pair {typed:?}; this print's pairs are {}",
            ids.join(", ")
        )));
    };
    let window = entry::Window {
        nominal_mm: pair.nominal_mm,
        tolerance_mm: s.options.reading_tolerance_mm,
        max_change_pct: s.options.max_change_pct,
        resolution_mm: s.options.caliper_resolution_mm,
    };
    Ok((pair, window))
}

/// What to measure and how, for the console and the measuring prompt.
/// The measuring dialog's text: what to do and where the details are (the console has the
/// pairs and the commands; the dialog does not repeat them).
fn measuring_dialog(s: &Session) -> Vec<String> {
    let on = if s.options.bed_temp_c > 0.0 {
        "on the hot bed"
    } else {
        "on the bed"
    };
    let mut lines = vec![format!(
        "Calipers, part still {on}: {} readings per pair, outer face to outer face just below \
         the top chamfer. The pairs and what to type are on the console.",
        s.options.readings_per_pair
    )];
    if let Some(p) = s.rounds.last().and_then(|r| r.picture.clone()) {
        lines.push(format!("picture: {p}"));
    }
    lines
}

fn measuring_guide(s: &Session, page: Option<&str>) -> Vec<String> {
    let Some(round) = s.rounds.last() else {
        return Vec::new();
    };
    let on = if s.options.bed_temp_c > 0.0 {
        "with the part still on the hot bed"
    } else {
        "with the part still on the bed"
    };
    let mut lines = vec![format!(
        "{TITLE} round {}: measure the pylons now, {on}. For each pair, {} readings with \
         calipers from outer face to outer face, just below the top chamfer:",
        round.n, s.options.readings_per_pair
    )];
    for p in &round.layout.pairs {
        lines.push(format!(
            "{}: pylon {} to pylon {}, nominal {} mm: KLIPCAL_MEASURE PAIR={} VALUES={},…",
            p.id,
            p.from,
            p.to,
            entry::fmt_mm(p.nominal_mm),
            p.id,
            entry::example(p.nominal_mm)
        ));
    }
    let shown = round
        .picture
        .clone()
        .or_else(|| round.diagram.as_ref().map(|d| format!("config/{d}")));
    if let Some(p) = shown {
        lines.push(format!(
            "picture of the pylons and pairs: {p} (Mainsail/Fluidd: Machine → config files → klipcal)"
        ));
    }
    lines.push(format!(
        "type readings on the console (or on klipcal's page{}); a wrong one: KLIPCAL_MEASURE \
         PAIR=… CLEAR=1, then enter the pair again",
        page.map(|p| format!(", {p}")).unwrap_or_default()
    ));
    lines
}

/// The solver's result in a few console lines.
fn solution_text(sol: &Solution) -> String {
    let mut t = String::new();
    for (name, s) in [("stepper_x", &sol.stepper_x), ("stepper_y", &sol.stepper_y)] {
        t.push_str(&format!(
            "{name}: rotation_distance {} → {} (scale {:.5} ± {:.5})\n",
            entry::fmt_rd(s.rotation_distance_old),
            entry::fmt_rd(s.rotation_distance_new),
            s.scale,
            s.uncertainty,
        ));
    }
    t.push_str(if sol.converged {
        "converged: the values are within the error budget"
    } else {
        "not converged: apply, then print another round"
    });
    for w in &sol.warnings {
        t.push_str("\nwarning: ");
        t.push_str(w);
    }
    t
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::store::Store;

    #[test]
    fn the_measuring_progress_marks_complete_pairs() {
        let pair = |id: &str| crate::layout::Pair {
            id: id.into(),
            group: "A".into(),
            from: "A1".into(),
            to: "A2".into(),
            direction_deg: 45.0,
            nominal_mm: 10.0,
        };
        let mut have = BTreeMap::new();
        have.insert("A-D1".to_string(), vec![10.0; 5]);
        have.insert("A-D2".to_string(), vec![150.0; 2]);
        let line = pairs_progress(&[pair("A-D1"), pair("A-D2"), pair("B-D1")], &have, 5);
        assert_eq!(line, "A-D1 5/5 ✓ · A-D2 2/5 · B-D1 0/5");
    }

    #[test]
    fn rotation_distances_are_written_without_trailing_zeros() {
        assert_eq!(entry::fmt_rd(40.0), "40");
        assert_eq!(entry::fmt_rd(40.1028949), "40.102895");
        assert_eq!(entry::fmt_rd(39.94284), "39.94284");
    }

    #[test]
    fn start_arguments_are_typed_at_the_boundary() {
        let r = AbCall::parse(
            "klipcal_ab_start",
            &json!({"BED": "60", "extruder": 215, "layout": "Full"}),
        )
        .unwrap();
        assert_eq!(
            r,
            AbCall::Start(StartRequest {
                bed_temp_c: Some(60.0),
                nozzle_temp_c: Some(215.0),
                layout: Some("full".into())
            })
        );
        let e = AbCall::parse("klipcal_ab_start", &json!({"bed": "200"})).unwrap_err();
        assert!(e.to_string().starts_with("BED=200: expected"), "{e}");
        let e = AbCall::parse("klipcal_ab_start", &json!({"layout": "round"})).unwrap_err();
        assert_eq!(e.to_string(), "LAYOUT=round: expected paper or full");
        let apply = |v| AbCall::parse("klipcal_apply", &v).unwrap();
        assert_eq!(
            apply(json!({"FORCE": "1"})),
            AbCall::Apply(ApplyRequest { force: true })
        );
        assert_eq!(
            apply(json!({})),
            AbCall::Apply(ApplyRequest { force: false })
        );
        let measure = |v| match AbCall::parse("klipcal_measure", &v).unwrap() {
            AbCall::Measure(m) => m,
            other => panic!("{other:?}"),
        };
        let m = measure(json!({"pair": "A-D1", "values": "10.02, 10.03,10.01", "value": "10,04"}));
        let texts: Vec<(&str, &str)> = m
            .values
            .iter()
            .map(|i| (i.text.as_str(), i.label.as_str()))
            .collect();
        assert_eq!(
            texts,
            vec![
                ("10.02", "item 1"),
                ("10.03", "item 2"),
                ("10.01", "item 3"),
                ("10,04", "VALUE")
            ]
        );
        // The page's fields: one reading each, named by the field.
        let m = measure(json!({"pair": "A-D1", "values": ["", "10,10"]}));
        assert_eq!(m.values.len(), 1);
        assert_eq!(m.values[0].label, "field 2");
        assert!(m.values[0].comma_is_decimal);
        assert_eq!(
            AbCall::parse("klipcal_soak_choice", &json!({})).unwrap(),
            AbCall::SoakChoice("wait"),
            "the macro's field default is the daemon's"
        );
    }

    #[test]
    fn only_the_automatic_states_resume_by_themselves() {
        assert!(State::Printing.is_automatic());
        assert!(!State::Measuring.is_automatic());
        assert!(State::Cancelled.is_final());
        assert_eq!(State::Measuring.name(), "measuring");
    }

    fn fixture() -> Store {
        // Written by klipcal 0.1.0 (before the session core): three A/B sessions, measuring,
        // solved and applied, each with five readings per pair.
        let dir = tempfile::tempdir().unwrap();
        let src = std::path::Path::new(env!("CARGO_MANIFEST_DIR"))
            .join("tests/fixtures/sessions-v0.1.0.sqlite");
        std::fs::copy(&src, dir.path().join("klipcal.sqlite")).unwrap();
        let store = Store::open(dir.path()).unwrap();
        std::mem::forget(dir);
        store
    }

    #[test]
    fn sessions_saved_by_release_0_1_0_load_typed() {
        let store = fixture();
        let mut states = Vec::new();
        for id in 1..=3 {
            let row = store.session(id).unwrap().unwrap();
            let s: Session = serde_json::from_value(row.doc.clone()).unwrap();
            states.push(s.state);
            let r = &s.rounds[0];
            assert_eq!(r.layout.pairs.len(), 4);
            if let Some(sol) = &r.solution {
                // The fixture's readings scale group A by 1.002 and B by 0.998 with a constant
                // shrinkage of 0.1 mm that the differential cancels (seed 000 §2).
                assert!(
                    (sol.groups[0].scale - 1.002).abs() < 1e-6,
                    "{:?}",
                    sol.groups[0]
                );
                assert!(
                    (sol.groups[1].scale - 0.998).abs() < 1e-6,
                    "{:?}",
                    sol.groups[1]
                );
                assert!((sol.stepper_x.rotation_distance_old - 40.0).abs() < 1e-12);
            }
            // Saved back, it keeps the shape release 0.1.0 reads.
            let back = serde_json::to_value(&s).unwrap();
            assert_eq!(
                back["rounds"][0]["solution"],
                row.doc["rounds"][0]["solution"]
            );
            assert_eq!(back["state"], row.doc["state"]);
        }
        assert_eq!(
            states,
            vec![State::Measuring, State::Solved, State::Applied]
        );
        assert!(store.session(2).unwrap().unwrap().doc["rounds"][0]["solution"].is_object());
    }
}
