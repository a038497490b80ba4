//! `klipcal_ab_apply`: the config transaction (backup, restart, verify, roll back) that
//! writes the solved values.

use super::*;

impl Ab {
    /// `klipcal_apply`: writes the solved values, restarts Klipper, verifies, rolls back on
    /// failure.
    ///
    /// # Errors
    /// Nothing solved, a print running, an implausible change without FORCE, or Klipper failing
    /// on the new values (rolled back).
    pub(crate) async fn apply(&self, req: &ApplyRequest) -> anyhow::Result<Applied> {
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
        let values = Self::values_to_write(&s, &sol, req.force)?;
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
            return Ok(Applied {
                state: State::Converged.name(),
                applied: None,
                message: msg,
            });
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
            Ok(report) => self.applied(&s, &sol, report).await,
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

    /// `stepper_x` and `stepper_y`'s new rotation_distance; refused when a change is beyond
    /// `ab.max_change_pct` and not forced.
    fn values_to_write(s: &Session, sol: &Solution, force: bool) -> anyhow::Result<Vec<ValueSet>> {
        let mut values = Vec::new();
        for (name, st) in [("stepper_x", &sol.stepper_x), ("stepper_y", &sol.stepper_y)] {
            let change = (st.scale - 1.0).abs() * 100.0;
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
                value: entry::fmt_rd(st.rotation_distance_new),
            });
        }
        Ok(values)
    }

    /// The values are written and Klipper runs them: the session is applied (or converged),
    /// the skew set or restored, and the next round's bed preheated when another is due.
    async fn applied(
        &self,
        s: &Session,
        sol: &Solution,
        report: ApplyReport,
    ) -> anyhow::Result<Applied> {
        let converged = sol.converged;
        let next = if converged {
            State::Converged
        } else {
            State::Applied
        };
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
        // Klipper restarted: heaters are off and the idle timeout is the configured one
        // again. Then the skew: the new one, or the one from before the session.
        let skew_note = self.skew_after_apply(s, sol).await;
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
            msg.push_str(&self.preheat_next_round(s, next_round).await);
        }
        Ok(Applied {
            state: next.name(),
            applied: Some(report),
            message: msg,
        })
    }

    /// After the apply's restart: the solved skew set and saved when it is to be applied (a
    /// note either way), else the skew from before the session restored.
    async fn skew_after_apply(&self, s: &Session, sol: &Solution) -> Option<String> {
        match sol.skew.set_skew.as_deref() {
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
                self.restore_skew(s.skew_before).await;
                None
            }
        }
    }
}
