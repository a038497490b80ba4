//! The differential A/B (X/Y) rotation_distance calibration (paper 000): preflight → uploaded →
//! heating → soaking → printing → holding → measuring → solved → applying → applied → next
//! round or converged (and failed / cancelled, with the reason). Its states, its steps and its
//! remote methods; the session store, runner, guards, console and config transaction are the
//! shared core's (`session`, `console`, `soak`, `printer_config`).

mod answers;
mod apply;
mod readings;
mod requests;
mod run;
mod soak;
mod solve;
#[cfg(test)]
mod tests;

use answers::{Applied, Checked, Chosen, ItemAnswer, Saved, Solved};
use readings::measuring_guide;
pub use requests::{ApplyRequest, CheckRequest, MeasureRequest, StartRequest};
use requests::{CHECK_VALUES, CHOICE, CLEAR, EXTRUDER, FORCE, LAYOUT, VALUE, VALUES};

use std::collections::BTreeMap;
use std::time::Duration;

use anyhow::{anyhow, Context};
use serde::{Deserialize, Serialize};
use serde_json::{json, Value};
use tracing::{info, warn};

use crate::calib::entry;
use crate::calib::metric::{Kinematics as CalibKinematics, ShearTo};
use crate::calib::solve::{solve, MotionFacts, Solution, SolveOptions, StepperFacts};
use crate::config::AbConfig;
use crate::gcode::{self, LayoutKind};
use crate::jobs::core::answer::{reply, SessionAnswer};
use crate::jobs::core::console::{Button, Prompt};
use crate::jobs::core::printer_config::{self, ApplyReport, ValueSet};
use crate::jobs::core::session::{now_unix, Core};
use crate::jobs::core::soak::{BedSoak, SoakSettings, SoakUpdate};
use crate::jobs::core::status::SessionStatus;
use crate::jobs::core::table::{arg, Alias, ArgKind, Args, Fields, Op, OpSpec};
use crate::jobs::core::{Calibration, Declare, Envelope, Hold, SessionState};
use crate::jobs::user;
use crate::klipper::{self, PrinterFacts};
use crate::layout::Layout;
use crate::store::SessionRow;

const BED: crate::jobs::core::table::ArgSpec = crate::jobs::core::table::bed_arg(
    "bed temperature, °C (0: unheated, no soak; default ab.bed_temp_c)",
);
const PAIR: crate::jobs::core::table::ArgSpec = arg(
    "pair",
    ArgKind::Text,
    "A-D1",
    "a pair of the layout, e.g. A-D1",
    "",
    "the pair measured, as the layout names it (A-D1)",
);

/// The A/B calibration's operations, each declared once (see [`crate::jobs::core::table`]).
pub(crate) static OPS: &[Op<AbCall>] = &[
    Op {
        spec: OpSpec::remote(
            "klipcal_ab_start",
            "KLIPCAL_AB_START",
            "ab/start",
            "print the pylons and calibrate stepper_x/stepper_y rotation_distance (BED=0 for an unheated bed, LAYOUT=paper or full)",
            &[
                BED,
                EXTRUDER,
                LAYOUT,
            ],
        ),
        parse: |a| Ok(AbCall::Start(StartRequest::from_args(a)?)),
    },
    Op {
        spec: OpSpec {
            alias: Some(Alias {
                http: "ab/clear",
                sets: "clear",
            }),
            ..OpSpec::remote(
            "klipcal_measure",
            "KLIPCAL_MEASURE",
            "ab/measure",
            "enter caliper readings for one pair, e.g. PAIR=A-D1 VALUES=10.02,10.03,10.01,10.02,10.04 (CLEAR=1 removes the pair's readings)",
            &[
                PAIR,
                VALUES,
                VALUE,
                CLEAR,
            ],
        )
        },
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
                CHECK_VALUES,
            ],
        ),
        parse: |a| Ok(AbCall::Check(CheckRequest::from_args(a)?)),
    },
    Op {
        spec: OpSpec::remote(
            "klipcal_soak_choice",
            "KLIPCAL_SOAK_CHOICE",
            "ab/soak_choice",
            "the bed soak: CHOICE=print prints now (offered from the moment the bed is in its band, with what the surface may still warm) or CHOICE=wait (go on waiting for the bed to settle; 10 min more at the soak limit's prompt)",
            &[CHOICE],
        ),
        parse: |a| {
            Ok(AbCall::SoakChoice(a.choice(&CHOICE)?.ok_or_else(|| {
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
            &[FORCE],
        ),
        parse: |a| Ok(AbCall::Apply(ApplyRequest::from_args(a)?)),
    },
];

/// An A/B call, typed at the boundary.
#[derive(Debug, Clone, PartialEq)]
pub(crate) enum AbCall {
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

/// The store's kind.
pub(crate) const KIND: &str = "ab";

/// "Wait 10 min more" after a soak that ran past `soak_max_s`.
const SOAK_MORE_S: f64 = 600.0;

/// How the console names it.
const TITLE: &str = "A/B calibration";

/// A session's state.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub(crate) enum State {
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

impl SessionState for State {
    const ALL: &'static [Self] = &[
        State::Preflight,
        State::Uploaded,
        State::Heating,
        State::Soaking,
        State::Printing,
        State::Holding,
        State::Measuring,
        State::Solved,
        State::Applying,
        State::Applied,
        State::Converged,
        State::Failed,
        State::Cancelled,
    ];
    const FINAL: [Self; 3] = [State::Converged, State::Failed, State::Cancelled];

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
}

/// The stepper facts a round was printed with.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub(crate) struct StepperDoc {
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
pub(crate) struct Round {
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
    /// Unix time klipcal started this round's print: a session resumed after an outage or a
    /// restart follows that print, or says what became of it, and never starts it again.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub print_started_unix: Option<f64>,
}

/// The whole session document, stored as JSON: the envelope around [`AbBody`].
pub(crate) type Session = Envelope<State, AbBody>;

/// The A/B session's own part of its document.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub(crate) struct AbBody {
    /// Settings: `[ab]` with the start call's arguments.
    pub options: AbConfig,
    /// Rounds so far; the last is the current one.
    pub rounds: Vec<Round>,
    /// Klipper's XY skew factor before the session cleared it.
    pub skew_before: Option<f64>,
    /// Unix time the print finished.
    pub print_done_unix: Option<f64>,
    /// klipcal turned the heaters off: the hold limit passed, or the session was cancelled or
    /// failed.
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
    /// How far this round's soak had got (0..1), so a daemon restarted mid-soak goes on from
    /// it; cleared when the soak ends.
    #[serde(default)]
    pub soak_done: Option<f64>,
}

/// The A/B calibration's settings: `[ab]` and `[soak]`.
#[derive(Debug, Clone, Default)]
pub(crate) struct AbSettings {
    /// `[ab]`: defaults of a session's options.
    pub defaults: AbConfig,
    /// `[soak]`: the bed soak detector (read again when a soak starts).
    pub soak: SoakSettings,
}

/// The A/B calibration over the shared core.
#[derive(Clone)]
pub(crate) struct Ab {
    core: Core,
    settings: AbSettings,
}

impl Ab {
    /// The calibration over `core`.
    #[must_use]
    pub(crate) fn new(core: Core, settings: AbSettings) -> Self {
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
        self.core
            .set_state::<State, AbBody>(id, state, progress)
            .await
    }

    /// Cancels the session: its print cancelled, heaters off, skew restored, prompt closed.
    async fn cancel_session(&self, id: i64, reason: &str) -> anyhow::Result<SessionAnswer> {
        let s = self.load(id)?;
        if s.state == State::Printing {
            if let Err(e) = self.core.m().gcode("CANCEL_PRINT").await {
                self.core
                    .safety_failed("A/B session cancelled", "CANCEL_PRINT", &e.to_string())
                    .await;
            }
        }
        // The status says the heaters are off when they are (issue 26 B.7: the cancel said so
        // while `heaters_off` stayed false).
        if self
            .core
            .heaters_off_reported("A/B session cancelled")
            .await
        {
            let _ = self
                .update(id, |d| {
                    d.heaters_off = true;
                    Ok(())
                })
                .await;
        }
        let answer = self
            .core
            .cancel_session::<State, AbBody>(
                s.id,
                reason,
                "cancelled; heaters off",
                format!("session {} cancelled ({reason}); heaters off", s.id),
            )
            .await?;
        self.restore_skew(s.skew_before).await;
        // The dialog closes in Calibrations::cancel, after every calibration's cancel.
        Ok(answer)
    }
}

/// An A/B session's own part of its status.
#[derive(Debug, Clone, PartialEq, Serialize, Default)]
pub(crate) struct AbStatus {
    /// The current round, 1-based (0 before the first).
    pub round: usize,
    /// The current round's pairs.
    pub pairs: Option<Vec<crate::layout::Pair>>,
    /// The current round's job.
    pub file: Option<String>,
    /// The current round's readings per pair, mm.
    pub readings: BTreeMap<String, Vec<f64>>,
    /// Readings a pair needs.
    pub readings_per_pair: usize,
    /// Bed temperature, °C.
    pub bed_temp_c: f64,
    /// The layout diagram under the config root.
    pub diagram: Option<String>,
    /// What is still to measure, in words (while measuring or solved).
    pub missing: Vec<String>,
    /// Every round so far.
    pub rounds: Vec<AbRoundStatus>,
    /// klipcal turned the heaters off: the hold limit passed, or the session was cancelled or
    /// failed.
    pub heaters_off: bool,
}

/// One round as the status shows it.
#[derive(Debug, Clone, PartialEq, Serialize, Default)]
pub(crate) struct AbRoundStatus {
    /// 1-based.
    pub n: u32,
    /// The job.
    pub file: String,
    /// rotation_distance as printed, mm (X, Y).
    pub rotation_distance: [f64; 2],
    /// The solved rotation_distance, mm (X, Y).
    pub rotation_distance_new: Option<[f64; 2]>,
    /// The solved scale (X, Y).
    pub scale: Option<[f64; 2]>,
    /// The larger error of the two, µm per 100 mm.
    pub error_um_per_100mm: Option<f64>,
    /// The scale's uncertainty (X, Y).
    pub uncertainty: Option<[f64; 2]>,
    /// Whether the round converged.
    pub converged: Option<bool>,
    /// What apply wrote.
    pub applied: Option<ApplyReport>,
}

impl Declare for Ab {
    const KIND: &'static str = KIND;
    const TITLE: &'static str = "an A/B calibration";
    type State = State;
    type Session = Session;
    type Call = AbCall;
    const OPS: &'static [Op<AbCall>] = OPS;

    fn session_status(&self, s: &Session) -> anyhow::Result<SessionStatus> {
        let rounds = s
            .rounds
            .iter()
            .map(|r| {
                let sol = r.solution.as_ref();
                AbRoundStatus {
                    n: r.n,
                    file: r.file.clone(),
                    rotation_distance: [
                        r.stepper_x.rotation_distance_mm,
                        r.stepper_y.rotation_distance_mm,
                    ],
                    rotation_distance_new: sol.map(|s| {
                        [
                            s.stepper_x.rotation_distance_new,
                            s.stepper_y.rotation_distance_new,
                        ]
                    }),
                    scale: sol.map(|s| [s.stepper_x.scale, s.stepper_y.scale]),
                    error_um_per_100mm: sol.map(|s| {
                        ((s.stepper_x.scale - 1.0) * 1e5)
                            .abs()
                            .max(((s.stepper_y.scale - 1.0) * 1e5).abs())
                    }),
                    uncertainty: sol.map(|s| [s.stepper_x.uncertainty, s.stepper_y.uncertainty]),
                    converged: sol.map(|s| s.converged),
                    applied: r.applied.clone(),
                }
            })
            .collect();
        let body = AbStatus {
            round: s.rounds.len(),
            pairs: s.rounds.last().map(|r| r.layout.pairs.clone()),
            file: s.rounds.last().map(|r| r.file.clone()),
            readings: self.readings(s)?,
            readings_per_pair: s.options.readings_per_pair,
            bed_temp_c: s.options.bed_temp_c,
            diagram: s.rounds.last().and_then(|r| r.diagram.clone()),
            missing: if matches!(s.state, State::Measuring | State::Solved) {
                self.missing_lines(s)?
            } else {
                Vec::new()
            },
            rounds,
            heaters_off: s.heaters_off,
        };
        Ok(SessionStatus::new(KIND, s.head(), &body)?.with_console_lines(body.missing))
    }
}

impl Calibration for Ab {
    async fn handle(&self, call: AbCall) -> anyhow::Result<Value> {
        match call {
            AbCall::Start(r) => reply(self.start(&r).await),
            AbCall::Measure(r) => reply(self.measure(&r).await),
            AbCall::Solve => reply(self.solve().await),
            AbCall::Apply(r) => reply(self.apply(&r).await),
            AbCall::Check(r) => reply(self.check(&r)),
            AbCall::SoakChoice(c) => reply(self.soak_choice(c).await),
        }
    }

    async fn resume(&self, row: &SessionRow) {
        self.resume_session(row.id).await;
    }

    async fn cancel(&self, row: &SessionRow, reason: &str) -> anyhow::Result<SessionAnswer> {
        self.cancel_session(row.id, reason).await
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

    async fn heaters_turned_off(&self, row: &SessionRow) {
        {
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
    }
}
