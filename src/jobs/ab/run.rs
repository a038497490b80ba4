//! Starting a calibration and its runner: the preflight, the round's pylon job printed, the
//! skew applied for the print and restored, the next round's preheat, resume after a restart.

use super::*;

impl Ab {
    /// After an apply that did not converge: Klipper's restart turned the bed off, so it heats
    /// again at once (the next round's soak then starts warm), owned by the session and bounded
    /// by the hold limit (klipcal's watchdog, and Klipper's idle timeout if klipcal is gone);
    /// a dialog offers the next round. Returns what the apply answer adds.
    pub(super) async fn preheat_next_round(&self, s: &Session, round: usize) -> String {
        let bed = s.options.bed_temp_c;
        let hold_min = s.options.hold_max_s / 60.0;
        let mut said = String::new();
        if bed > 0.0 {
            let heated = BedSoak::heat(&self.core, bed, s.options.hold_max_s).await;
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
                    self.core
                        .heaters_off_reported("no preheat for the next round")
                        .await;
                }
            }
        }
        self.core
            .prompt(&Prompt {
                // The why in the title, no text row (issue 40 item 6): the console row just
                // before says what was applied and that the bed heats again.
                title: format!("Not yet converged: round {round}?"),
                lines: Vec::new(),
                buttons: vec![Button::new(
                    &format!("Print round {round}"),
                    "KLIPCAL_AB_START",
                    "primary",
                )],
                footer: vec![Button::new("End", "_KLIPCAL_CANCEL_ASK", "info")],
            })
            .await;
        said
    }

    pub(super) fn spawn_runner(&self, id: i64) {
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

    pub(super) async fn fail(&self, id: i64, why: &str) {
        self.core
            .fail_session::<State, AbBody>(id, TITLE, why, true, |b| b.heaters_off = true)
            .await;
    }

    /// Resumes a session after a daemon start or a reconnect.
    pub(super) async fn resume_session(&self, id: i64) {
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
    pub(super) async fn apply_skew(
        &self,
        set_skew: &str,
        start_macro: &str,
    ) -> anyhow::Result<String> {
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
    pub(super) async fn restore_skew(&self, xy_before: Option<f64>) {
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
    pub(super) async fn run(&self, id: i64) -> anyhow::Result<()> {
        // The bed's target and its bound were just sent (not by a runner before a restart).
        let mut just_heated = false;
        loop {
            let s = self.load(id)?;
            match s.state {
                State::Preflight => self.preflight(s).await?,
                State::Uploaded => {
                    BedSoak::heat(
                        &self.core,
                        s.options.bed_temp_c,
                        s.options.soak_max_s + crate::jobs::soak::BOUND_SLACK_S,
                    )
                    .await?;
                    just_heated = true;
                    self.set_state(id, State::Heating, "bed heating").await?;
                }
                State::Heating | State::Soaking => self.soak(s, just_heated).await?,
                State::Printing => self.print(s).await?,
                State::Holding => self.hold(s).await?,
                _ => return Ok(()),
            }
        }
    }

    /// Reads Klipper's current XY skew factor: from the G-code and toolhead positions where
    /// they tell it (nothing on the console), else from GET_CURRENT_SKEW, whose four lines land
    /// on the user's console (`[skew_correction]` has no status to read) right after the
    /// session's "checking the printer", and the round's line just after them says what was
    /// done with it (issue 26 A.7; issue 40 item 6: a line before them was a row more). With
    /// `Some(none)` when GET_CURRENT_SKEW was asked: whether every plane's factor is 0.
    pub(super) async fn current_skew(&self) -> Option<(f64, Option<bool>)> {
        let st = self
            .core
            .m()
            .objects_query(json!({"gcode_move": ["position"], "toolhead": ["position"]}))
            .await
            .ok()?;
        let xyz = |v: &Value| -> Option<[f64; 3]> {
            Some([v[0].as_f64()?, v[1].as_f64()?, v[2].as_f64()?])
        };
        if let (Some(g), Some(t)) = (
            xyz(&st["gcode_move"]["position"]),
            xyz(&st["toolhead"]["position"]),
        ) {
            if let Some(xy) = crate::calib::skew::xy_factor_from_positions(g, t) {
                return Some((xy, None));
            }
        }
        // A report that changes nothing: on Klipper's API socket where klipcal uses it, so
        // that the script is no command row of its own (issue 40 item 6).
        let mut rx = self.core.m().events();
        self.core
            .m()
            .console_script("GET_CURRENT_SKEW")
            .await
            .ok()?;
        let deadline = tokio::time::Instant::now() + Duration::from_secs(3);
        while let Ok(Ok(e)) = tokio::time::timeout_at(deadline, rx.recv()).await {
            if let crate::moonraker::Event::GcodeResponse(text) = e {
                if let Some((xy, none)) = skew_report(&text) {
                    return Some((xy, Some(none)));
                }
            }
        }
        None
    }

    /// The round's preflight: the printer has what the calibration needs, the skew is cleared
    /// for the print, the pylon job is generated and uploaded with its picture, and the round
    /// is stored.
    pub(super) async fn preflight(&self, s: Session) -> anyhow::Result<()> {
        let id = s.id;
        self.core.printer_idle().await?;
        let pc = printer_config::fetch(self.core.m(), self.core.files()).await?;
        let facts = PrinterFacts::from_config(&pc.config)?;
        let running = crate::printer::running_features(self.core.m()).await?;
        let kinematics = check_printer(&s, &facts, &running)?;
        let mut notes = Vec::new();
        let skew_before = self.clear_skew(&s, &facts, &mut notes).await?;
        let job = pylon_job(&s, &pc, kinematics, &mut notes)?;
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
            print_started_unix: None,
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
        // What the round changed on the printer or in the layout is said with it.
        let said = std::iter::once(msg.clone())
            .chain(notes.iter().cloned())
            .collect::<Vec<_>>()
            .join("; ");
        self.update(id, |s| {
            s.rounds.push(round);
            s.notes.extend(notes);
            s.skew_before = skew_before;
            s.state = State::Uploaded;
            s.progress = msg.clone();
            Ok(())
        })
        .await?;
        self.core.console(&format!("A/B calibration {said}")).await;
        Ok(())
    }

    /// With `[skew_correction]`: the skew Klipper runs, cleared for the calibration print (a
    /// note says so when it was set). Returns the session's skew from before it (the first
    /// round's, restored at the end).
    async fn clear_skew(
        &self,
        s: &Session,
        facts: &PrinterFacts,
        notes: &mut Vec<String>,
    ) -> anyhow::Result<Option<f64>> {
        let mut skew_before = s.skew_before;
        if facts.has_skew_correction {
            let (xy, report) = self.current_skew().await.unwrap_or((0.0, None));
            if s.rounds.is_empty() {
                skew_before = Some(xy);
            }
            let above = if report.is_some() {
                " (GET_CURRENT_SKEW above)"
            } else {
                ""
            };
            let none = report == Some(true);
            if xy != 0.0 {
                notes.push(format!(
                    "skew correction (XY factor {xy:.6}) cleared for the calibration print{above}; it is restored afterwards"
                ));
            } else if none {
                notes.push(format!("no skew correction to turn off{above}"));
            }
            // Klipper said every factor is 0: nothing to clear (a row fewer; issue 40 item 6).
            if !none {
                self.core.m().gcode("SET_SKEW CLEAR=1").await?;
            }
        }
        Ok(skew_before)
    }

    /// The round's print: started (the heaters held for it), or followed when klipcal already
    /// started it, to its end.
    pub(super) async fn print(&self, s: Session) -> anyhow::Result<()> {
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
        // Once started, the print is followed to its end, whatever became of it while klipcal
        // could not watch (Moonraker down, the daemon restarted): it is never started again.
        let started = round.print_started_unix.is_some();
        let follow = ours
            && (matches!(state, "printing" | "paused" | "complete")
                || (started && matches!(state, "cancelled" | "error")));
        if !follow && started {
            return Err(anyhow!(
                "the calibration print {} stopped while klipcal could not follow it: Klipper \
                 shows {} (it restarted or shut down meanwhile, or another print ran); start \
                 the round again with KLIPCAL_AB_START",
                round.file,
                match ps["filename"].as_str() {
                    Some(f) if !f.is_empty() => format!("{state} {f}"),
                    _ => format!("{state}, no print"),
                }
            ));
        }
        if !follow {
            self.start_print(&s, round).await?;
        }
        self.follow_print(id).await
    }

    /// Starts the round's print. Klipper keeps the heaters on while it prints; once the print
    /// ends, it turns them off by itself after the hold limit if klipcal is not there to do it.
    async fn start_print(&self, s: &Session, round: &Round) -> anyhow::Result<()> {
        self.core.printer_idle().await?;
        // Nothing said of its own (issue 40 item 6): the print's command and Klipper's
        // "File opened:" rows name the file, the row before says why it prints now.
        self.core.hold_heaters_for(s.options.hold_max_s).await?;
        self.core.m().print_start(&round.file).await?;
        let now = now_unix();
        self.update(s.id, |s| {
            if let Some(r) = s.rounds.last_mut() {
                r.print_started_unix = Some(now);
            }
            Ok(())
        })
        .await
    }

    /// Follows the print to its end: complete (the part holds on the bed), cancelled (heaters
    /// off, the session ends), an error, or Klipper gone from under it.
    async fn follow_print(&self, id: i64) -> anyhow::Result<()> {
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
                    let e = anyhow::Error::new(e);
                    // Moonraker away: the runner waits for it, says so, and follows the print
                    // again from what Klipper shows then (above).
                    if self.core.unreachable(&e) {
                        return Err(e);
                    }
                    // Klipper restarting: keep watching; a shutdown shows up as print_stats
                    // error once Klipper is back.
                    warn!(error = %format!("{e:#}"), "print status unavailable");
                    continue;
                }
            };
            let ps = &st["print_stats"];
            match ps["state"].as_str().unwrap_or("") {
                "complete" => return self.print_complete(id).await,
                "cancelled" => return self.print_cancelled(id).await,
                "error" => {
                    let msg = ps["message"].as_str().unwrap_or("Klipper error");
                    // PRINT_START heating an uncalibrated MPC heater: what to run, not Kalico's text.
                    return Err(match crate::klipper::kalico::mpc_refusal(msg) {
                        Some(said) => user(format!("the calibration print failed: {said}")),
                        None => anyhow!("the calibration print failed: {msg}"),
                    });
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

    async fn print_complete(&self, id: i64) -> anyhow::Result<()> {
        self.update(id, |s| {
            s.state = State::Holding;
            s.print_done_unix = Some(now_unix());
            s.progress = if s.options.bed_temp_c > 0.0 {
                "print done; the part cools on the hot bed"
            } else {
                "print done; the part cools on the bed"
            }
            .into();
            Ok(())
        })
        .await
    }

    async fn print_cancelled(&self, id: i64) -> anyhow::Result<()> {
        let off = self.core.heaters_off_reported("A/B print cancelled").await;
        self.update(id, |s| {
            s.heaters_off |= off;
            s.state = State::Cancelled;
            s.reason = Some("the calibration print was cancelled".into());
            s.progress = "cancelled".into();
            Ok(())
        })
        .await?;
        self.core
            .console(if off {
                "A/B calibration cancelled: the print was cancelled; heaters off"
            } else {
                "A/B calibration cancelled: the print was cancelled"
            })
            .await;
        Ok(())
    }

    /// `klipcal_ab_start`: starts a session (or the next round of an applied one).
    ///
    /// # Errors
    /// A session already running, bad arguments, or a printer that is printing.
    pub(crate) async fn start(&self, req: &StartRequest) -> anyhow::Result<SessionAnswer> {
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
                let mut s = Session::new(
                    State::Preflight,
                    "preflight",
                    AbBody {
                        options,
                        rounds: Vec::new(),
                        skew_before: None,
                        print_done_unix: None,
                        heaters_off: false,
                        soak_asking: false,
                        soak_choice: None,
                        soak_done: None,
                        preheat_since_unix: None,
                        last_entry: None,
                    },
                );
                self.core.create(KIND, &mut s, |s, id| s.id = id).await?
            }
        };
        // The question of the dialog before ("round 2?") is answered, whatever road answered
        // it (its button, the macro typed, the page, the API): the dialog ends in every front
        // end, also after a reload (they rebuild it from the console), and its buttons stop
        // acting. Sent now, before the runner can show the round's first dialog.
        if next_round.is_some() {
            self.core.prompt_end_now().await;
        }
        self.spawn_runner(id);
        // The next round of a session is that round, not a new session (issue 26 B.7).
        let message = match next_round {
            Some(_) => {
                let n = self.load(id).map_or(0, |s| s.rounds.len()) + 1;
                format!("{TITLE} session {id}, round {n} started: checking the printer")
            }
            None => format!("{TITLE} session {id} started: checking the printer"),
        };
        Ok(SessionAnswer {
            session: id,
            state: State::Preflight.name(),
            message,
        })
    }
}

/// What the calibration needs of the printer, as Klipper runs it (not the config text: Kalico
/// loads `respond` and `exclude_object` without a section, and can switch either off while its
/// section stays), all named when something lacks. Returns the kinematics' name.
fn check_printer(
    s: &Session,
    facts: &PrinterFacts,
    running: &crate::printer::Features,
) -> anyhow::Result<&'static str> {
    let mut missing = Vec::new();
    if !facts.has_virtual_sdcard {
        missing.push("[virtual_sdcard] (with path: ~/printer_data/gcodes)");
    }
    if !running.respond {
        missing.push(if facts.has_respond {
            "[respond] (it is in the config, but Klipper has no RESPOND command: \
             enable_respond: False?)"
        } else {
            "[respond]"
        });
    }
    if !running.exclude_object {
        missing.push(if facts.has_exclude_object {
            "[exclude_object] (it is in the config, but Klipper has no EXCLUDE_OBJECT_DEFINE \
             command: enable_exclude_object: False?)"
        } else {
            "[exclude_object]"
        });
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
    match facts.kinematics {
        klipper::Kinematics::CoreXy => Ok("corexy"),
        klipper::Kinematics::Cartesian => Ok("cartesian"),
        klipper::Kinematics::Other(ref k) => Err(user(format!(
            "kinematics `{k}`: klipcal calibrates corexy and cartesian printers"
        ))),
    }
}

/// The round's pylon job for this printer and the session's settings; when the default D2
/// does not fit the bed, the one suggested (a note says so).
fn pylon_job(
    s: &Session,
    pc: &printer_config::PrinterConfig,
    kinematics: &str,
    notes: &mut Vec<String>,
) -> anyhow::Result<gcode::Job> {
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
    match gcode::generate(&machine, &opts) {
        Ok(j) => Ok(j),
        Err(gcode::Error::DoesNotFit {
            suggested_d2_mm: Some(d2),
            message,
        }) => {
            notes.push(format!(
                "the default D2 does not fit this bed; using D2 = {d2} mm ({message})"
            ));
            Ok(gcode::generate(
                &machine,
                &gcode::Options { d2_mm: d2, ..opts },
            )?)
        }
        Err(e) => Err(user(e.to_string())),
    }
}

/// GET_CURRENT_SKEW's answer: the XY factor, and whether every plane's factor is 0.
fn skew_report(text: &str) -> Option<(f64, bool)> {
    let factor = |plane: &str| -> Option<f64> {
        text.split(&format!("{plane} Skew:"))
            .nth(1)?
            .split_whitespace()
            .next()?
            .parse()
            .ok()
    };
    let xy = factor("XY")?;
    let none = ["XY", "XZ", "YZ"]
        .iter()
        .all(|p| factor(p).is_some_and(|f| f == 0.0));
    Some((xy, none))
}

#[cfg(test)]
mod report_tests {
    use super::*;

    #[test]
    fn a_skew_report_says_its_xy_factor_and_whether_nothing_is_set() {
        let zero = "// Current Printer Skew:\n// XY Skew: 0.000000 radians, 0.00 degrees\n\
                    // XZ Skew: 0.000000 radians, 0.00 degrees\n// YZ Skew: 0.000000 radians, 0.00 degrees";
        assert_eq!(skew_report(zero), Some((0.0, true)));
        let xz = zero.replacen("XZ Skew: 0.000000", "XZ Skew: 0.001000", 1);
        assert_eq!(skew_report(&xz), Some((0.0, false)));
        let xy = zero.replacen("XY Skew: 0.000000", "XY Skew: -0.002000", 1);
        assert_eq!(skew_report(&xy), Some((-0.002, false)));
        // Cut short: the planes not said are not taken for 0.
        assert_eq!(
            skew_report("// XY Skew: 0.000000 radians"),
            Some((0.0, false))
        );
        assert_eq!(
            skew_report("// idle_timeout: Timeout set to 600.00 s"),
            None
        );
    }
}
