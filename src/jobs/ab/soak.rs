//! The bed soak before a round's print (with the user's choice when it takes long) and the
//! hold after it while the user measures.

use super::*;

/// The offer to print now while the bed soaks: what it said last and when, and whether the
/// user chose to wait.
#[derive(Default)]
struct Offer {
    words: String,
    at: Option<tokio::time::Instant>,
    declined: bool,
}

impl Ab {
    pub(super) async fn soak(&self, s: Session, just_heated: bool) -> anyhow::Result<()> {
        let id = s.id;
        let hold_s = s.options.hold_max_s;
        let params = self
            .settings
            .soak
            .for_soak(&self.core, "A/B calibration")
            .await;
        let mut soak = BedSoak::new(
            params.clone(),
            s.options.bed_temp_c,
            s.options.soak_max_s,
            "ab.soak_max_s",
        );
        if just_heated {
            soak = soak.bound_just_set();
        }
        soak = soak.resumed_from(self.load(id)?.soak_done);
        let mut last = String::new();
        let mut cost: Option<f64> = None;
        let mut offer = Offer::default();
        // Since when the soak question waits for an answer, and what it said.
        let mut asked: Option<(tokio::time::Instant, String)> = None;
        loop {
            let doc = self.load(id)?;
            // Print now, chosen while soaking (issue 29): from the moment the bed is in its band.
            if doc.soak_choice.as_deref() == Some("print") {
                return self
                    .soak_print_now(id, doc.rounds.len(), asked.is_some(), cost, &params)
                    .await;
            }
            if asked.is_none() && doc.soak_choice.as_deref() == Some("wait") {
                // Wait, chosen while soaking: the offer closes and the soak goes on.
                offer.declined = true;
                self.soak_wait_chosen(id).await?;
            }
            if let Some((_, line)) = &asked {
                if doc.soak_choice.as_deref() == Some("wait") {
                    self.soak_ten_more(id, line).await?;
                    soak.extend(SOAK_MORE_S);
                    asked = None;
                    last.clear();
                }
            }
            match soak.poll(&self.core, TITLE).await? {
                SoakUpdate::Stable { why } => {
                    return self.soak_settled(&s, &params, &why, asked.take()).await;
                }
                SoakUpdate::Heating => {
                    if last != "heating" {
                        self.set_state(id, State::Heating, "bed heating").await?;
                        last = "heating".into();
                    }
                }
                SoakUpdate::Soaking {
                    text,
                    print_now_c,
                    eta_s,
                    progress,
                } => {
                    cost = print_now_c.or(cost);
                    if asked.is_none() && last != text {
                        self.set_soaking(id, &text, progress).await?;
                        last = text;
                    }
                    if asked.is_none() {
                        self.offer_print_now(&mut offer, cost, eta_s).await;
                    }
                }
                SoakUpdate::TooLong {
                    minutes,
                    at_target_s,
                    falling_pct_per_10min,
                } => match &asked {
                    None => {
                        // The question waits within the hold limit; the bed stays hot and the
                        // soak goes on meanwhile (Klipper owns the bed for that long: the
                        // extension sets its idle timeout), so that no answer costs nothing
                        // but time (issue 26 A.1).
                        soak.extend(hold_s);
                        let line = self
                            .ask_soak_choice(
                                id,
                                soaked_words(minutes, at_target_s),
                                falling_pct_per_10min,
                                hold_s,
                            )
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

    /// The soak's line and how far it has got, kept for a daemon restarted mid-soak.
    async fn set_soaking(&self, id: i64, text: &str, done: f64) -> anyhow::Result<()> {
        tracing::info!(session = id, state = "soaking", "{text}");
        self.update(id, |s| {
            s.set(State::Soaking, text);
            s.soak_done = Some(done);
            Ok(())
        })
        .await
    }

    /// Print now, chosen while soaking: the session prints, its note says what the surface may
    /// still warm, and the soak so far is plotted.
    async fn soak_print_now(
        &self,
        id: i64,
        rounds: usize,
        asked: bool,
        cost: Option<f64>,
        params: &crate::calib::soak::SoakParams,
    ) -> anyhow::Result<()> {
        if asked {
            self.core.prompt_end().await;
        }
        let words = cost.map_or_else(
            || "what the surface may still warm is not known yet".to_string(),
            |c| {
                format!(
                    "the surface may still warm by up to {} (95 %)",
                    crate::calib::soak::cost_words(c)
                )
            },
        );
        let note = format!("the user chose to print now, before the bed settled: {words}");
        self.update(id, |s| {
            s.soak_choice = None;
            s.soak_asking = false;
            s.soak_done = None;
            s.notes.push(note.clone());
            s.state = State::Printing;
            s.progress = format!("printing now, as chosen ({words})");
            Ok(())
        })
        .await?;
        // The soak so far, plotted as for a settled bed (issue 40: none was saved).
        let path = format!("klipcal/ab-s{id}-r{}-soak.svg", rounds);
        let plot = crate::jobs::core::soak::save_soak_picture(&self.core, params, &path)
            .await
            .map(|p| format!("; plot: {p}"))
            .unwrap_or_default();
        self.core.console(&format!("{TITLE}: {note}{plot}")).await;
        Ok(())
    }

    /// Wait, chosen while soaking (no question asked): the choice is cleared and the console
    /// says how to print now instead.
    async fn soak_wait_chosen(&self, id: i64) -> anyhow::Result<()> {
        self.update(id, |s| {
            s.soak_choice = None;
            Ok(())
        })
        .await?;
        self.core
            .console(&format!(
                "{TITLE}: waiting until the bed has settled; KLIPCAL_SOAK_CHOICE \
                 CHOICE=print prints now"
            ))
            .await;
        Ok(())
    }

    /// Wait 10 min more, the answer to the soak question `line`: the question ends and the
    /// session says so.
    async fn soak_ten_more(&self, id: i64, line: &str) -> anyhow::Result<()> {
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
        Ok(())
    }

    /// The bed settled: the dialogs end (a question waiting is noted as answered by the bed),
    /// the soak is plotted when the bed was heated, and the session prints.
    async fn soak_settled(
        &self,
        s: &Session,
        params: &crate::calib::soak::SoakParams,
        why: &str,
        asked: Option<(tokio::time::Instant, String)>,
    ) -> anyhow::Result<()> {
        let id = s.id;
        if self.core.dialog_title().as_deref() == Some("klipcal: the bed is soaking") {
            self.core.prompt_end().await;
        }
        if let Some((_, line)) = asked {
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
        // A plot of a soak that did not happen (an unheated bed) says nothing.
        let heated = s.options.bed_temp_c > params.skip_below_c;
        let n = s.rounds.len();
        let path = format!("klipcal/ab-s{id}-r{n}-soak.svg");
        let plot = if heated {
            crate::jobs::core::soak::save_soak_picture(&self.core, params, &path)
                .await
                .map(|p| format!("; plot: {p}"))
                .unwrap_or_default()
        } else {
            String::new()
        };
        let line = format!("bed stable ({why}){plot}; printing");
        tracing::info!(session = id, state = "printing", "{line}");
        self.update(id, |s| {
            s.soak_done = None;
            s.set(State::Printing, line.clone());
            Ok(())
        })
        .await
    }

    /// From the moment the bed is in its band: the dialog offers *Print now* with its cost and
    /// *Wait* (issue 38 item 5). Shown once the soak question (if any) is out of the way; shown
    /// again when the cost said changes, at most every 5 min; not after *Wait*.
    async fn offer_print_now(&self, offer: &mut Offer, cost: Option<f64>, eta_s: Option<f64>) {
        use crate::jobs::core::soak_ask;
        if offer.declined || soak_ask::pending(&self.core) || soak_ask::showing(&self.core) {
            return;
        }
        let words = cost.map_or_else(
            || {
                "what the surface may still warm is worked out after a few minutes of the bed's \
                power"
                    .to_string()
            },
            |c| {
                format!(
                    "the surface may still warm by up to {}",
                    crate::calib::soak::cost_words(c)
                )
            },
        );
        let due = offer
            .at
            .map_or(true, |at| at.elapsed() >= Duration::from_secs(300));
        if offer.words == words || !due {
            return;
        }
        let wait = eta_s.map_or_else(
            || "once the bed has settled".to_string(),
            |e| {
                format!(
                    "once the bed has settled, about {:.0} min from now",
                    (e / 60.0).ceil()
                )
            },
        );
        self.core
            .prompt(&Prompt {
                title: "klipcal: the bed is soaking".into(),
                lines: vec![format!(
                    "Print now: {words}. Wait: klipcal prints {wait} (KLIPCAL_STATUS and \
                     klipcal's page follow it)."
                )],
                buttons: vec![
                    Button::new("Print now", "KLIPCAL_SOAK_CHOICE CHOICE=print", "warning"),
                    Button::new("Wait", "KLIPCAL_SOAK_CHOICE CHOICE=wait", "primary"),
                ],
                footer: vec![Button::cancel_asking()],
            })
            .await;
        offer.words = words;
        offer.at = Some(tokio::time::Instant::now());
    }

    /// The bed is at its target but its power still moves after `soak_max_s`: asks print now
    /// / wait 10 min more / cancel, and says what happens without an answer (the bed stays hot
    /// and the soak goes on up to `hold_s`). The runner takes the answer; returns the line
    /// that says why it asks.
    ///
    /// # Errors
    /// Store failures.
    pub(super) async fn ask_soak_choice(
        &self,
        id: i64,
        soaked: String,
        falling: Option<f64>,
        hold_s: f64,
    ) -> anyhow::Result<String> {
        let line = match falling {
            Some(f) => format!(
                "bed power still {} by {:.1} % per 10 min {soaked} (ab.soak_max_s)",
                if f < 0.0 { "rising" } else { "falling" },
                f.abs()
            ),
            None => format!("the bed has not settled {soaked} (ab.soak_max_s)"),
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
        // The dialog alone (issue 40 item 6: the console row said the same): its rows list
        // the question and its buttons' macros in the console too, STATUS and the page say how
        // to answer, and so does the console once the dialog is closed without an answer.
        self.core
            .prompt(&Prompt {
                title: "klipcal: the bed has not settled".into(),
                // One text row (issue 26 A.4: each prompt line is a console row).
                lines: vec![format!(
                    "{}{}. Print now: the readings may carry some thermal drift. Wait: 10 \
                         more minutes. No answer: the bed stays hot and klipcal keeps waiting, \
                         up to {hold_min:.0} min. Cancel: heaters off.",
                    line[..1].to_uppercase(),
                    &line[1..]
                )],
                buttons: vec![
                    Button::new("Print now", "KLIPCAL_SOAK_CHOICE CHOICE=print", "warning"),
                    Button::new("Wait 10 min", "KLIPCAL_SOAK_CHOICE CHOICE=wait", "primary"),
                ],
                footer: vec![Button::cancel_asking()],
            })
            .await;
        Ok(line)
    }

    /// `klipcal_soak_choice CHOICE=print|wait`: answers the soak prompt.
    ///
    /// # Errors
    /// A bad CHOICE, or no soak waiting for one.
    pub(crate) async fn soak_choice(&self, choice: &'static str) -> anyhow::Result<Chosen> {
        let s =
            match self.active()? {
                Some(s) if s.soak_asking => s,
                // Print now and Wait are offered from the moment the bed is in its band (issue 29,
                // issue 38 item 5: the macro's default CHOICE=wait answered "nothing to choose").
                Some(s) if s.state == State::Soaking => s,
                _ => return Err(user(
                    "nothing to choose: no bed soak is waiting for an answer (CHOICE=print and \
                     CHOICE=wait are taken while the bed soaks at its target)",
                )),
            };
        let asking = s.soak_asking;
        self.update(s.id, |d| {
            d.soak_choice = Some(choice.to_string());
            Ok(())
        })
        .await?;
        // The question is answered: its dialog closes with this answer, in the same script (the
        // runner's own close then has nothing to do; issue 26 A.4).
        self.core.prompt_end().await;
        let message = match (choice, asking) {
            ("print", _) => "printing now",
            (_, true) => "waiting 10 min more",
            _ => "waiting until the bed has settled",
        };
        Ok(Chosen {
            session: s.id,
            choice,
            message: message.into(),
        })
    }

    /// The part cools on the bed, then the measuring guide.
    pub(super) async fn hold(&self, s: Session) -> anyhow::Result<()> {
        let id = s.id;
        // Klipper itself turns the heaters off at the hold limit (counted from the print's
        // end, also when the hold resumes after an outage), even if klipcal stops. Set again
        // here even when the print's start set it (`held`): skipping it (issue 40 item 6, two
        // console rows) left the bed on past the hold limit with Moonraker down in the fault
        // matrix (A/B hold × Moonraker down 120 s: on 62 s after a 45 s hold).
        let done = s.print_done_unix.unwrap_or_else(now_unix);
        let since_end = now_unix() - done;
        let hold = (s.options.hold_max_s - since_end).max(1.0);
        self.core.hold_heaters_for(hold).await?;
        let wait = (done + s.options.cooldown_s - now_unix()).max(0.0);
        if wait > 0.0 {
            let bed = if s.options.bed_temp_c > 0.0 {
                "the hot bed"
            } else {
                "the bed"
            };
            self.core
                .console(&format!(
                    "A/B calibration: print done; the part cools on {bed} for {wait:.0} s before \
                     measuring"
                ))
                .await;
            tokio::time::sleep(Duration::from_secs_f64(wait)).await;
        }
        self.set_state(id, State::Measuring, "waiting for caliper readings")
            .await?;
        let s = self.load(id)?;
        // The console carries the guide (the pairs, what to type, the page's address); no
        // dialog: Mainsail's is modal and blocked the very console it asked the user to type
        // in until it was closed (issue 40 item 4). The readings' roads are the console and
        // klipcal's page (also its webcam tile on a phone); the next dialog offers Solve.
        let guide = measuring_guide(&s, self.core.page());
        self.core.console(&guide.join("\n")).await;
        Ok(())
    }
}

/// How long the bed has soaked, as the soak question says it: from when it reached its target
/// ("40 s after reaching its target"), with the time since it was set when that differs much
/// (issue 40: "after 1 min" read wrong 40 s after the bed reached its target).
fn soaked_words(minutes: f64, at_target_s: Option<f64>) -> String {
    let span = |s: f64| {
        if s < 120.0 {
            format!("{:.0} s", s.max(0.0))
        } else {
            format!("{:.0} min", s / 60.0)
        }
    };
    match at_target_s {
        Some(at) => format!(
            "{} after reaching its target ({} since it was set)",
            span(at),
            span(minutes * 60.0)
        ),
        None => format!("{} after its target was set", span(minutes * 60.0)),
    }
}

#[cfg(test)]
mod soaked_tests {
    use super::soaked_words;

    #[test]
    fn the_soak_question_counts_from_the_target_reached() {
        assert_eq!(
            soaked_words(1.0, Some(40.0)),
            "40 s after reaching its target (60 s since it was set)"
        );
        assert_eq!(
            soaked_words(25.0, Some(1200.0)),
            "20 min after reaching its target (25 min since it was set)"
        );
        assert_eq!(soaked_words(3.0, None), "3 min after its target was set");
    }
}
