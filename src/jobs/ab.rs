//! The differential A/B (X/Y) rotation_distance session: preflight → uploaded → heating →
//! soaking → printing → holding → measuring → solved → applying → applied → next round or
//! converged (and failed / cancelled, with the reason). Every state is saved before its step
//! acts, so a restart of the daemon, Moonraker or Klipper resumes where it was. Heaters go off
//! when the session ends, fails or is abandoned, after at most the configured hold time.

use std::collections::BTreeMap;
use std::sync::Arc;
use std::time::{Duration, SystemTime, UNIX_EPOCH};

use anyhow::{anyhow, Context};
use serde::{Deserialize, Serialize};
use serde_json::{json, Value};
use tokio_util::sync::CancellationToken;
use tracing::{info, warn};

use super::printer_config::{self, ApplyReport, ValueSet};
use super::{user, UserError};
use crate::calib::metric::{Kinematics as CalibKinematics, ShearTo};
use crate::calib::soak::{SoakDetector, SoakParams, SoakStatus};
use crate::calib::solve::{solve, MotionFacts, SolveOptions, StepperFacts};
use crate::config::AbConfig;
use crate::gcode::{self, LayoutKind};
use crate::klipper::gcode_cmd::{self, GcodeCmd};
use crate::klipper::{self, PrinterFacts};
use crate::layout::Layout;
use crate::moonraker::{Files, Moonraker};
use crate::store::Store;

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
    /// The solver's result (`klipcal solve --json` shape).
    pub solution: Option<Value>,
    /// What apply wrote.
    pub applied: Option<ApplyReport>,
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
}

fn now_unix() -> f64 {
    SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .map_or(0.0, |d| d.as_secs_f64())
}

/// The calibration service: one active session at a time.
#[derive(Clone)]
pub struct Jobs {
    inner: Arc<Inner>,
}

struct Inner {
    m: Moonraker,
    files: Files,
    store: Store,
    defaults: AbConfig,
    soak: SoakParams,
    shutdown: CancellationToken,
    /// Serialises every change of a session document.
    lock: tokio::sync::Mutex<()>,
    runner: std::sync::Mutex<Option<CancellationToken>>,
}

fn num_arg(args: &Value, key: &str) -> anyhow::Result<Option<f64>> {
    let v = args
        .get(key)
        .or_else(|| args.get(key.to_uppercase()))
        .or_else(|| args.get(key.to_lowercase()));
    match v {
        None | Some(Value::Null) => Ok(None),
        Some(Value::Number(n)) => Ok(n.as_f64()),
        Some(Value::String(s)) if s.trim().is_empty() => Ok(None),
        Some(Value::String(s)) => s
            .trim()
            .parse::<f64>()
            .ok()
            .filter(|v| v.is_finite())
            .map(Some)
            .ok_or_else(|| {
                user(format!(
                    "{key}={s:?} is not a number; expected e.g. {key}=60"
                ))
            }),
        Some(other) => Err(user(format!("{key}={other} is not a number"))),
    }
}

fn str_arg(args: &Value, key: &str) -> Option<String> {
    let v = args
        .get(key)
        .or_else(|| args.get(key.to_uppercase()))
        .or_else(|| args.get(key.to_lowercase()))?;
    match v {
        Value::String(s) if !s.trim().is_empty() => Some(s.trim().to_string()),
        Value::Number(n) => Some(n.to_string()),
        Value::Bool(b) => Some(b.to_string()),
        _ => None,
    }
}

fn flag_arg(args: &Value, key: &str) -> bool {
    matches!(
        str_arg(args, key)
            .as_deref()
            .map(str::to_lowercase)
            .as_deref(),
        Some("1" | "true" | "yes")
    )
}

impl Jobs {
    /// Opens the store and builds the service; call [`Jobs::resume`] once connected.
    pub fn new(
        m: Moonraker,
        files: Files,
        store: Store,
        defaults: AbConfig,
        soak: SoakParams,
        shutdown: CancellationToken,
    ) -> Self {
        Self {
            inner: Arc::new(Inner {
                m,
                files,
                store,
                defaults,
                soak,
                shutdown,
                lock: tokio::sync::Mutex::new(()),
                runner: std::sync::Mutex::new(None),
            }),
        }
    }

    fn load(&self, id: i64) -> anyhow::Result<Session> {
        let row = self
            .inner
            .store
            .session(id)?
            .ok_or_else(|| anyhow!("session {id} is not in the database"))?;
        serde_json::from_value(row.doc).context("reading the stored session")
    }

    fn save(&self, s: &Session) -> anyhow::Result<()> {
        self.inner
            .store
            .save_session(s.id, &s.state.name(), &serde_json::to_value(s)?)?;
        Ok(())
    }

    fn active(&self) -> anyhow::Result<Option<Session>> {
        match self.inner.store.active_session()? {
            Some(row) => Ok(Some(serde_json::from_value(row.doc)?)),
            None => Ok(None),
        }
    }

    /// Changes the active session under the lock, saving it before returning.
    async fn update<T>(
        &self,
        id: i64,
        f: impl FnOnce(&mut Session) -> anyhow::Result<T>,
    ) -> anyhow::Result<T> {
        let _g = self.inner.lock.lock().await;
        let mut s = self.load(id)?;
        let out = f(&mut s)?;
        self.save(&s)?;
        Ok(out)
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

    async fn console(&self, msg: &str) {
        for line in msg.lines() {
            let cmd = GcodeCmd::new("RESPOND")
                .word("PREFIX", gcode_cmd::RESPOND_PREFIX)
                .text_lossy("MSG", line)
                .build();
            if let Ok(cmd) = cmd {
                if let Err(e) = self.inner.m.gcode(&cmd).await {
                    warn!(error = %e, "console message not shown");
                    return;
                }
            }
        }
    }

    /// A Mainsail/Fluidd prompt dialog: title, text lines, buttons `(label, gcode, style)`.
    async fn prompt(&self, title: &str, lines: &[String], buttons: &[(&str, &str, &str)]) {
        let mut actions = vec![format!("prompt_begin {title}")];
        actions.extend(lines.iter().map(|l| format!("prompt_text {l}")));
        for (label, gcode, style) in buttons {
            actions.push(format!("prompt_button {label}|{gcode}|{style}"));
        }
        actions.push("prompt_show".into());
        let mut script = Vec::new();
        for a in &actions {
            let safe = gcode_cmd::sanitize_text(a);
            if let Ok(line) = gcode_cmd::respond_action(&safe) {
                script.push(line);
            }
        }
        if let Err(e) = self.inner.m.gcode(&script.join("\n")).await {
            warn!(error = %e, "prompt not shown");
        }
    }

    /// Resumes the active session after a daemon start or a reconnect.
    pub async fn resume(&self) {
        let s = match self.active() {
            Ok(Some(s)) => s,
            Ok(None) => return,
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

    fn spawn_runner(&self, id: i64) {
        let token = self.inner.shutdown.child_token();
        if let Ok(mut r) = self.inner.runner.lock() {
            if let Some(old) = r.replace(token.clone()) {
                old.cancel();
            }
        }
        let jobs = self.clone();
        tokio::spawn(async move {
            let result = tokio::select! {
                () = token.cancelled() => return,
                r = jobs.run(id) => r,
            };
            if let Err(e) = result {
                let msg = format!("{e:#}");
                warn!(session = id, error = %msg, "session failed");
                jobs.fail(id, &msg).await;
            }
        });
    }

    async fn fail(&self, id: i64, why: &str) {
        let _ = self.heaters_off().await;
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
        self.console(&format!("A/B calibration failed: {why}"))
            .await;
    }

    /// Heaters off, and Klipper's idle timeout back to its configured value (the session
    /// stretched it over the measuring window).
    async fn heaters_off(&self) -> anyhow::Result<()> {
        self.inner.m.gcode("TURN_OFF_HEATERS").await?;
        let cf = self.inner.m.configfile().await?;
        if let Some(t) = cf["settings"]["idle_timeout"]["timeout"].as_f64() {
            self.inner.m.gcode(&gcode_cmd::set_idle_timeout(t)?).await?;
        }
        Ok(())
    }

    /// Sets the solved skew in Klipper, saves it as profile `klipcal` with SAVE_CONFIG, loads
    /// it, and says whether PRINT_START loads it at the next print (Klipper does not load skew
    /// profiles at start).
    async fn apply_skew(&self, set_skew: &str) -> anyhow::Result<String> {
        let m = &self.inner.m;
        m.gcode(set_skew).await?;
        m.gcode("SKEW_PROFILE SAVE=klipcal").await?;
        let (state, msg) =
            printer_config::restart_with(m, "SAVE_CONFIG", Duration::from_secs(60)).await?;
        if state != "ready" {
            return Err(anyhow!("Klipper is {state} after SAVE_CONFIG: {msg}"));
        }
        m.gcode("SKEW_PROFILE LOAD=klipcal").await?;
        let pc = printer_config::fetch(m, &self.inner.files).await?;
        let loads = pc
            .config
            .get("gcode_macro PRINT_START", "gcode")
            .is_some_and(|g| g.to_uppercase().contains("SKEW_PROFILE LOAD=KLIPCAL"));
        Ok(if loads {
            format!("skew saved as profile klipcal ({set_skew}); PRINT_START loads it")
        } else {
            format!(
                "skew saved as profile klipcal ({set_skew}) and loaded now; Klipper does not \
                 load skew profiles at start: add the line `SKEW_PROFILE LOAD=klipcal` to your \
                 PRINT_START macro"
            )
        })
    }

    /// Sets Klipper's XY skew back to what it was before the session cleared it.
    async fn restore_skew(&self, xy_before: Option<f64>) {
        if let Some(cmd) = xy_before
            .filter(|v| *v != 0.0)
            .and_then(crate::calib::skew::set_skew_command)
        {
            if let Err(e) = self.inner.m.gcode(&cmd).await {
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
                    let target = s.options.bed_temp_c;
                    self.inner
                        .m
                        .gcode(&gcode_cmd::set_heater_temperature("heater_bed", target)?)
                        .await?;
                    self.set_state(id, State::Heating, "bed heating").await?;
                }
                State::Heating | State::Soaking => self.soak(s).await?,
                State::Printing => self.print(s).await?,
                State::Holding => self.hold(s).await?,
                _ => return Ok(()),
            }
        }
    }

    async fn printer_idle(&self) -> anyhow::Result<()> {
        let info = self.inner.m.printer_info().await?;
        if info["state"] != "ready" {
            return Err(user(format!(
                "Klipper is not ready ({}): {}",
                info["state"].as_str().unwrap_or("?"),
                info["state_message"].as_str().unwrap_or("").trim()
            )));
        }
        let st = self
            .inner
            .m
            .objects_query(json!({"print_stats": ["state"]}))
            .await?;
        let ps = st["print_stats"]["state"].as_str().unwrap_or("");
        if ps == "printing" || ps == "paused" {
            return Err(user(format!(
                "a print is {ps}; klipcal does not move, heat, restart or edit while a print runs"
            )));
        }
        Ok(())
    }

    /// Reads Klipper's current XY skew factor (GET_CURRENT_SKEW answers on the console).
    async fn current_skew(&self) -> Option<f64> {
        let mut rx = self.inner.m.events();
        self.inner.m.gcode("GET_CURRENT_SKEW").await.ok()?;
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
        self.printer_idle().await?;
        let pc = printer_config::fetch(&self.inner.m, &self.inner.files).await?;
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
            self.inner.m.gcode("SET_SKEW CLEAR=1").await?;
        }
        let machine = crate::pylons_cmd::machine_with(&pc.config, Some(kinematics), None, None)?;
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
        };
        self.inner
            .files
            .upload("gcodes", &file, job.gcode.into_bytes())
            .await
            .context("uploading the pylon job")?;
        let msg = format!(
            "round {n}: {} pylons uploaded as {file}; heating the bed to {} °C",
            job.layout.pylons.len(),
            s.options.bed_temp_c
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
        self.console(&format!("A/B calibration {msg}")).await;
        Ok(())
    }

    async fn soak(&self, s: Session) -> anyhow::Result<()> {
        let id = s.id;
        let target = s.options.bed_temp_c;
        let mut detector = SoakDetector::new(self.inner.soak.clone());
        let start = std::time::Instant::now();
        let mut last_state = s.state;
        let mut last_report = 0.0_f64;
        loop {
            if start.elapsed().as_secs_f64() > s.options.soak_max_s {
                return Err(user(format!(
                    "the bed did not reach thermal equilibrium within {} s (ab.soak_max_s)",
                    s.options.soak_max_s
                )));
            }
            let st = self
                .inner
                .m
                .objects_query(json!({"heater_bed": ["temperature", "power", "target"]}))
                .await?;
            let hb = &st["heater_bed"];
            let t_s = start.elapsed().as_secs_f64();
            let status = detector.push(
                t_s,
                hb["power"].as_f64().unwrap_or(0.0),
                hb["temperature"].as_f64().unwrap_or(0.0),
                hb["target"].as_f64().unwrap_or(target),
            );
            match status {
                SoakStatus::Stable { .. } | SoakStatus::Skipped => {
                    let why = detector.explanation().to_string();
                    self.set_state(
                        id,
                        State::Printing,
                        &format!("bed stable ({why}); printing"),
                    )
                    .await?;
                    return Ok(());
                }
                SoakStatus::Heating => {
                    if last_state != State::Heating {
                        self.set_state(id, State::Heating, "bed heating").await?;
                        last_state = State::Heating;
                    }
                }
                SoakStatus::Soaking {
                    eta_s, progress, ..
                } => {
                    if last_state != State::Soaking || t_s - last_report > 5.0 {
                        let p = match eta_s {
                            Some(eta) => format!(
                                "bed soaking: {:.0} % done, about {:.0} s left",
                                progress * 100.0,
                                eta
                            ),
                            None => "bed soaking: waiting for the bed power to settle".into(),
                        };
                        self.set_state(id, State::Soaking, &p).await?;
                        last_state = State::Soaking;
                        last_report = t_s;
                    }
                }
            }
            tokio::time::sleep(Duration::from_millis(250)).await;
        }
    }

    async fn print(&self, s: Session) -> anyhow::Result<()> {
        let id = s.id;
        let round = s
            .rounds
            .last()
            .ok_or_else(|| anyhow!("session has no round"))?;
        let st = self
            .inner
            .m
            .objects_query(json!({"print_stats": ["state", "filename"]}))
            .await?;
        let ps = &st["print_stats"];
        let ours = ps["filename"].as_str() == Some(round.file.as_str());
        let state = ps["state"].as_str().unwrap_or("");
        if !(ours && matches!(state, "printing" | "paused" | "complete")) {
            self.printer_idle().await?;
            self.inner.m.print_start(&round.file).await?;
            self.console(&format!("A/B calibration: printing {}", round.file))
                .await;
        }
        let mut standby = 0;
        loop {
            tokio::time::sleep(Duration::from_millis(500)).await;
            let st = match self
                .inner
                .m
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
                    let _ = self.heaters_off().await;
                    self.update(id, |s| {
                        s.state = State::Cancelled;
                        s.reason = Some("the calibration print was cancelled".into());
                        s.progress = "cancelled".into();
                        Ok(())
                    })
                    .await?;
                    self.console("A/B calibration cancelled: the print was cancelled; heaters off")
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
                        return Err(anyhow!(if self.klipper_ready().await {
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

    async fn klipper_ready(&self) -> bool {
        matches!(self.inner.m.printer_info().await, Ok(i) if i["state"] == "ready")
    }

    async fn hold(&self, s: Session) -> anyhow::Result<()> {
        let id = s.id;
        // Klipper itself turns the heaters off after the hold limit, even if klipcal stops.
        let hold = s.options.hold_max_s.max(1.0);
        self.inner
            .m
            .gcode(&gcode_cmd::set_idle_timeout(hold)?)
            .await?;
        let done = s.print_done_unix.unwrap_or_else(now_unix);
        let wait = (done + s.options.cooldown_s - now_unix()).max(0.0);
        if wait > 0.0 {
            self.console(&format!(
                "A/B calibration: print done; the part cools on the hot bed for {wait:.0} s before measuring"
            ))
            .await;
            tokio::time::sleep(Duration::from_secs_f64(wait)).await;
        }
        self.set_state(id, State::Measuring, "waiting for caliper readings")
            .await?;
        let s = self.load(id)?;
        let lines = self.missing_lines(&s)?;
        self.console(&format!(
            "A/B calibration: measure the pylons now, on the hot bed.\n{}",
            lines.join("\n")
        ))
        .await;
        self.prompt(
            "klipcal: measure the pylons",
            &lines,
            &[
                ("Status", "KLIPCAL_STATUS", "secondary"),
                ("Cancel", "KLIPCAL_CANCEL", "error"),
            ],
        )
        .await;
        Ok(())
    }

    fn readings(&self, s: &Session) -> anyhow::Result<BTreeMap<String, Vec<f64>>> {
        let n = s.rounds.len() as i64;
        let mut out: BTreeMap<String, Vec<f64>> = BTreeMap::new();
        for r in self.inner.store.readings(s.id, n)? {
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
                    "{}: {} of {} readings (nominal {} mm): KLIPCAL_MEASURE PAIR={} VALUES=…",
                    p.id, got, s.options.readings_per_pair, p.nominal_mm, p.id
                ));
            }
        }
        Ok(lines)
    }

    /// `klipcal_ab_start`: starts a session (or the next round of an applied one).
    ///
    /// # Errors
    /// A session already running, bad arguments, or a printer that is printing.
    pub async fn start(&self, args: &Value) -> anyhow::Result<Value> {
        let d = &self.inner.defaults;
        let bed = num_arg(args, "bed")?.unwrap_or(d.bed_temp_c);
        let nozzle = num_arg(args, "extruder")?.unwrap_or(d.nozzle_temp_c);
        if !(0.0..=130.0).contains(&bed) {
            return Err(user(format!(
                "BED={bed}: expected a bed temperature from 0 (unheated) to 130 °C"
            )));
        }
        if !(150.0..=320.0).contains(&nozzle) {
            return Err(user(format!(
                "EXTRUDER={nozzle}: expected a nozzle temperature from 150 to 320 °C"
            )));
        }
        let layout = str_arg(args, "layout").unwrap_or_else(|| d.layout.clone());
        if layout != "paper" && layout != "full" {
            return Err(user(format!("LAYOUT={layout}: expected paper or full")));
        }
        self.printer_idle().await?;
        let _g = self.inner.lock.lock().await;
        let id = match self.active()? {
            Some(s) if s.state == State::Applied => {
                let mut s = s;
                s.state = State::Preflight;
                s.progress = format!("round {}: preflight", s.rounds.len() + 1);
                s.options.bed_temp_c = bed;
                s.options.nozzle_temp_c = nozzle;
                s.options.layout = layout;
                s.print_done_unix = None;
                s.heaters_off = false;
                self.save(&s)?;
                s.id
            }
            Some(s) => {
                return Err(user(format!(
                    "calibration session {} is {}; finish it or KLIPCAL_CANCEL first",
                    s.id,
                    s.state.name()
                )))
            }
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
                };
                let id = self.inner.store.create_session(
                    "ab",
                    "preflight",
                    &serde_json::to_value(&s)?,
                )?;
                s.id = id;
                self.save(&s)?;
                id
            }
        };
        drop(_g);
        self.spawn_runner(id);
        Ok(json!({"session": id, "state": "preflight",
                  "message": format!("A/B calibration session {id} started: checking the printer")}))
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

    /// `klipcal_measure`: saves readings for one pair, refusing bad ones one by one.
    ///
    /// # Errors
    /// No session waiting for readings, an unknown pair, or no value at all.
    pub async fn measure(&self, args: &Value) -> anyhow::Result<Value> {
        let s = self.measuring()?;
        let round = s.rounds.last().ok_or_else(|| anyhow!("no round"))?;
        let pair_id = str_arg(args, "pair").ok_or_else(|| {
            user("no PAIR given; expected e.g. KLIPCAL_MEASURE PAIR=A-D1 VALUES=10.02,10.03")
        })?;
        let Some(pair) = round
            .layout
            .pairs
            .iter()
            .find(|p| p.id.eq_ignore_ascii_case(&pair_id))
        else {
            let ids: Vec<&str> = round.layout.pairs.iter().map(|p| p.id.as_str()).collect();
            return Err(user(format!(
                "unknown pair {pair_id:?}; this print's pairs are {}",
                ids.join(", ")
            )));
        };
        let mut raw: Vec<String> = Vec::new();
        match args.get("values").or_else(|| args.get("VALUES")) {
            Some(Value::Array(a)) => raw.extend(a.iter().map(|v| match v {
                Value::String(s) => s.clone(),
                other => other.to_string(),
            })),
            Some(Value::String(t)) => raw.extend(
                t.split([',', ' ', ';'])
                    .filter(|p| !p.trim().is_empty())
                    .map(|p| p.trim().to_string()),
            ),
            Some(Value::Number(n)) => raw.push(n.to_string()),
            _ => {}
        }
        if let Some(v) = str_arg(args, "value") {
            raw.push(v);
        }
        if raw.is_empty() {
            return Err(user(format!(
                "no reading for {}; expected VALUES=10.02,10.03,… or VALUE=10.02 (mm)",
                pair.id
            )));
        }
        let tol = s.options.reading_tolerance_mm;
        let mut saved = Vec::new();
        let mut refused = Vec::new();
        for text in raw {
            match text.parse::<f64>() {
                Ok(v) if !v.is_finite() || v <= 0.0 => refused.push(format!(
                    "{}: {text} refused: a reading must be a distance above 0 mm",
                    pair.id
                )),
                Ok(v) if (v - pair.nominal_mm).abs() > tol => refused.push(format!(
                    "{}: {text} refused: more than {tol} mm from the nominal {} mm; measure outer face to outer face",
                    pair.id, pair.nominal_mm
                )),
                Ok(v) => {
                    self.inner
                        .store
                        .add_reading(s.id, s.rounds.len() as i64, &pair.id, v)?;
                    saved.push(v);
                }
                Err(_) => refused.push(format!(
                    "{}: {text:?} refused: not a number; expected mm such as {:.2}",
                    pair.id, pair.nominal_mm
                )),
            }
        }
        let s = self.load(s.id)?;
        let have = self.readings(&s)?;
        let count = have.get(&pair.id).map_or(0, Vec::len);
        let missing = self.missing_lines(&s)?;
        let mut message = format!(
            "{}: {} reading(s) saved, {count} in all",
            pair.id,
            saved.len()
        );
        for r in &refused {
            message.push('\n');
            message.push_str(r);
        }
        if missing.is_empty() {
            message.push_str("\nall pairs measured: KLIPCAL_AB_SOLVE computes the new values");
        }
        if saved.is_empty() {
            return Err(user(message));
        }
        Ok(
            json!({"pair": pair.id, "saved": saved, "refused": refused, "count": count,
                  "missing": missing, "message": message}),
        )
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
        if s.rounds.len() > 1 {
            let prev = &s.rounds[s.rounds.len() - 2];
            opts.previous = prev.solution.as_ref().and_then(|sol| {
                sol["groups"].as_array().map(|g| {
                    g.iter()
                        .filter_map(|g| {
                            Some((g["group"].as_str()?.to_string(), g["scale"].as_f64()?))
                        })
                        .collect()
                })
            });
        }
        let solution =
            solve(&round.layout, &raw, &facts, &opts).map_err(|e| user(e.to_string()))?;
        let sol = serde_json::to_value(&solution)?;
        let message = solution_text(&sol);
        self.update(s.id, |s| {
            if let Some(r) = s.rounds.last_mut() {
                r.solution = Some(sol.clone());
            }
            s.state = State::Solved;
            s.progress = "solved; apply with KLIPCAL_AB_APPLY".into();
            Ok(())
        })
        .await?;
        let lines: Vec<String> = message.lines().map(str::to_string).collect();
        self.prompt(
            "klipcal: new rotation distances",
            &lines,
            &[
                ("Apply", "KLIPCAL_AB_APPLY", "primary"),
                ("Cancel", "KLIPCAL_CANCEL", "error"),
            ],
        )
        .await;
        Ok(json!({"solution": sol, "message": message}))
    }

    /// `klipcal_apply`: writes the solved values, restarts Klipper, verifies, rolls back on
    /// failure.
    ///
    /// # Errors
    /// Nothing solved, a print running, an implausible change without FORCE, or Klipper failing
    /// on the new values (rolled back).
    pub async fn apply(&self, args: &Value) -> anyhow::Result<Value> {
        let force = flag_arg(args, "force");
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
        self.printer_idle().await?;
        let round = s.rounds.last().ok_or_else(|| anyhow!("no round"))?.clone();
        let sol = round
            .solution
            .clone()
            .ok_or_else(|| anyhow!("no solution"))?;
        let mut values = Vec::new();
        for name in ["stepper_x", "stepper_y"] {
            let scale = sol[name]["scale"].as_f64().unwrap_or(1.0);
            let new = sol[name]["rotation_distance_new"]
                .as_f64()
                .ok_or_else(|| anyhow!("solution lacks {name}"))?;
            let change = (scale - 1.0).abs() * 100.0;
            if change > s.options.max_change_pct && !force {
                return Err(user(format!(
                    "{name}: a {change:.2} % change is implausible (limit {} %, ab.max_change_pct); \
                     check the readings, or apply with FORCE=1",
                    s.options.max_change_pct
                )));
            }
            values.push(ValueSet {
                section: name.into(),
                key: "rotation_distance".into(),
                value: format_rd(new),
            });
        }
        self.set_state(s.id, State::Applying, "writing the new rotation distances")
            .await?;
        let result = async {
            let pc = printer_config::fetch(&self.inner.m, &self.inner.files).await?;
            printer_config::apply(
                &self.inner.m,
                &self.inner.files,
                &pc,
                &values,
                &printer_config::stamp(now_unix() as u64),
            )
            .await
        }
        .await;
        match result {
            Ok(report) => {
                let converged = sol["converged"].as_bool().unwrap_or(false);
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
                let skew_note = match sol["skew"]["set_skew"].as_str() {
                    Some(cmd) if sol["skew"]["applied"] == json!(true) => {
                        Some(match self.apply_skew(cmd).await {
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
                    self.console(&format!("A/B calibration: {note}")).await;
                }
                self.console(&format!("A/B calibration {msg}")).await;
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

    /// `klipcal_cancel`: stops the session safely (print cancelled, heaters off).
    ///
    /// # Errors
    /// No session to cancel.
    pub async fn cancel(&self, args: &Value) -> anyhow::Result<Value> {
        let s = self
            .active()?
            .ok_or_else(|| user("no calibration session to cancel"))?;
        if let Ok(mut r) = self.inner.runner.lock() {
            if let Some(t) = r.take() {
                t.cancel();
            }
        }
        if s.state == State::Printing {
            let _ = self.inner.m.gcode("CANCEL_PRINT").await;
        }
        let _ = self.heaters_off().await;
        let reason = str_arg(args, "reason").unwrap_or_else(|| "cancelled by the user".into());
        self.update(s.id, |s| {
            s.state = State::Cancelled;
            s.reason = Some(reason.clone());
            s.progress = "cancelled; heaters off".into();
            Ok(())
        })
        .await?;
        self.restore_skew(s.skew_before).await;
        let _ = self
            .inner
            .m
            .gcode("RESPOND TYPE=command MSG=action:prompt_end")
            .await;
        Ok(json!({"session": s.id, "state": "cancelled",
                  "message": format!("session {} cancelled ({reason}); heaters off", s.id)}))
    }

    /// The active (or latest) session for `klipcal_status`.
    ///
    /// # Errors
    /// A damaged database.
    pub fn status(&self) -> anyhow::Result<Value> {
        let row = match self.inner.store.active_session()? {
            Some(r) => Some(r),
            None => self.inner.store.latest_session()?,
        };
        let Some(row) = row else {
            return Ok(Value::Null);
        };
        let s: Session = serde_json::from_value(row.doc)?;
        let readings = self.readings(&s)?;
        let rounds: Vec<Value> = s
            .rounds
            .iter()
            .map(|r| {
                json!({
                    "n": r.n,
                    "file": r.file,
                    "rotation_distance": [r.stepper_x.rotation_distance_mm, r.stepper_y.rotation_distance_mm],
                    "scale": r.solution.as_ref().map(|s| json!([s["stepper_x"]["scale"], s["stepper_y"]["scale"]])),
                    "error_um_per_100mm": r.solution.as_ref().map(|s| {
                        let e = |k: &str| ((s[k]["scale"].as_f64().unwrap_or(1.0) - 1.0) * 1e5).abs();
                        e("stepper_x").max(e("stepper_y"))
                    }),
                    "uncertainty": r.solution.as_ref().map(|s| json!([s["stepper_x"]["uncertainty"], s["stepper_y"]["uncertainty"]])),
                    "converged": r.solution.as_ref().and_then(|s| s["converged"].as_bool()),
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
            "missing": if matches!(s.state, State::Measuring | State::Solved) { json!(self.missing_lines(&s)?) } else { json!([]) },
            "rounds": rounds,
            "notes": s.notes,
            "heaters_off": s.heaters_off,
        }))
    }

    /// Turns the heaters off once the hold limit has passed since the print finished, for a
    /// session still waiting on the user. Runs until shutdown.
    pub async fn hold_watchdog(self) {
        loop {
            tokio::select! {
                () = self.inner.shutdown.cancelled() => return,
                () = tokio::time::sleep(Duration::from_secs(1)) => {}
            }
            let Ok(Some(s)) = self.active() else { continue };
            let waiting = matches!(s.state, State::Holding | State::Measuring | State::Solved);
            let Some(done) = s.print_done_unix else {
                continue;
            };
            if !waiting || s.heaters_off || now_unix() < done + s.options.hold_max_s {
                continue;
            }
            if self.heaters_off().await.is_ok() {
                let _ = self
                    .update(s.id, |s| {
                        s.heaters_off = true;
                        s.notes.push(format!(
                            "heaters turned off: the hold limit of {} s after the print passed (ab.hold_max_s)",
                            s.options.hold_max_s
                        ));
                        Ok(())
                    })
                    .await;
                self.console("A/B calibration: hold limit reached, heaters off")
                    .await;
            }
        }
    }
}

fn format_rd(v: f64) -> String {
    let s = format!("{v:.6}");
    let s = s.trim_end_matches('0');
    s.trim_end_matches('.').to_string()
}

/// The solver's result in a few console lines.
fn solution_text(sol: &Value) -> String {
    let mut t = String::new();
    for name in ["stepper_x", "stepper_y"] {
        let s = &sol[name];
        t.push_str(&format!(
            "{name}: rotation_distance {} → {} (scale {:.5} ± {:.5})\n",
            s["rotation_distance_old"],
            s["rotation_distance_new"]
                .as_f64()
                .map_or("?".into(), format_rd),
            s["scale"].as_f64().unwrap_or(f64::NAN),
            s["uncertainty"].as_f64().unwrap_or(f64::NAN),
        ));
    }
    t.push_str(if sol["converged"].as_bool() == Some(true) {
        "converged: the values are within the error budget"
    } else {
        "not converged: apply, then print another round"
    });
    for w in sol["warnings"].as_array().into_iter().flatten() {
        if let Some(w) = w.as_str() {
            t.push_str("\nwarning: ");
            t.push_str(w);
        }
    }
    t
}

/// Whether an error is the user's (a 400 answer) rather than the daemon's.
pub fn is_user_error(e: &anyhow::Error) -> bool {
    e.downcast_ref::<UserError>().is_some()
        || e.chain().any(|c| c.downcast_ref::<UserError>().is_some())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn rotation_distances_are_written_without_trailing_zeros() {
        assert_eq!(format_rd(40.0), "40");
        assert_eq!(format_rd(40.1028949), "40.102895");
        assert_eq!(format_rd(39.94284), "39.94284");
    }

    #[test]
    fn macro_arguments_arrive_as_strings_and_are_parsed_with_clear_errors() {
        let args = json!({"bed": "60", "EXTRUDER": 215, "layout": "full"});
        assert_eq!(num_arg(&args, "bed").unwrap(), Some(60.0));
        assert_eq!(num_arg(&args, "extruder").unwrap(), Some(215.0));
        assert_eq!(str_arg(&args, "layout").as_deref(), Some("full"));
        let err = num_arg(&json!({"bed": "hot"}), "bed").unwrap_err();
        assert!(
            err.to_string().contains("bed=\"hot\" is not a number"),
            "{err}"
        );
        assert!(is_user_error(&err));
        assert!(flag_arg(&json!({"FORCE": "1"}), "force"));
        assert!(!flag_arg(&json!({}), "force"));
    }

    #[test]
    fn only_the_automatic_states_resume_by_themselves() {
        assert!(State::Printing.is_automatic());
        assert!(!State::Measuring.is_automatic());
        assert!(State::Cancelled.is_final());
        assert_eq!(State::Measuring.name(), "measuring");
    }
}
