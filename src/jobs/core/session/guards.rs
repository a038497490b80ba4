//! The printer guards (idle, Klipper ready, heaters off, the heater hold) and klipcal's
//! console lines and dialog, on the [`Core`].

use super::*;

impl Core {
    /// Refuses unless Klipper is ready and no print is printing or paused.
    ///
    /// # Errors
    /// A user error saying what the printer is doing; Moonraker failures.
    pub(crate) async fn printer_idle(&self) -> anyhow::Result<()> {
        let info = self.inner.m.printer_info().await?;
        if !info.ready() {
            return Err(user(format!(
                "Klipper is not ready ({}): {}",
                if info.state.is_empty() {
                    "?"
                } else {
                    &info.state
                },
                info.state_message.trim()
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

    /// Whether Klipper answers ready.
    pub(crate) async fn klipper_ready(&self) -> bool {
        matches!(self.inner.m.printer_info().await, Ok(i) if i.ready())
    }

    /// Heaters off, and Klipper's idle timeout back to its configured value (a session may
    /// have stretched it over a hold window).
    ///
    /// # Errors
    /// Moonraker failures.
    pub(crate) async fn heaters_off(&self) -> anyhow::Result<()> {
        // Heaters first, the timeout after them, in one script (one console row fewer; issue
        // 40 item 6). Where the configured timeout cannot be read, the heaters go off alone.
        let restore = match self.restore_idle_timeout_script().await {
            Ok(r) => r,
            Err(e) => {
                self.inner.m.gcode("TURN_OFF_HEATERS").await?;
                return Err(e);
            }
        };
        let script = match restore {
            Some(r) => format!("TURN_OFF_HEATERS\n{r}"),
            None => "TURN_OFF_HEATERS".to_string(),
        };
        self.inner.m.gcode(&script).await?;
        Ok(())
    }

    /// [`Core::heaters_off`] on a safety path (a cancel, a capture's end, a failed preheat):
    /// a failure is logged and said on the console, never dropped. True when they went off.
    pub(crate) async fn heaters_off_reported(&self, what: &str) -> bool {
        match self.heaters_off().await {
            Ok(()) => true,
            Err(e) => {
                self.safety_failed(what, "TURN_OFF_HEATERS", &format!("{e:#}"))
                    .await;
                false
            }
        }
    }

    /// A safety command (`TURN_OFF_HEATERS`, `CANCEL_PRINT`) that failed: logged as an error and
    /// said on the console in red with what to do (the console may be unreachable too; the
    /// log keeps it then).
    pub(crate) async fn safety_failed(&self, what: &str, command: &str, e: &str) {
        tracing::error!(error = %e, "{what}: {command} failed");
        self.console_error(&format!(
            "{what}: {command} failed ({e}); run {command} yourself"
        ))
        .await;
    }

    /// [`Core::heaters_off`], waiting out a Moonraker outage however long it lasts (a failed or
    /// cancelled session's heaters go off once Moonraker is back). Says on the console that the
    /// heaters are off, after `what` ("A/B calibration failed: …").
    ///
    /// # Errors
    /// Klipper refusing (e.g. shut down: its heaters are off anyway), or shutdown.
    pub(crate) async fn heaters_off_once_back(&self, what: &str) -> anyhow::Result<()> {
        let mut waited = false;
        let mut klipper_waited = false;
        loop {
            match self.heaters_off().await {
                Ok(()) => break,
                Err(e) if self.unreachable(&e) => {
                    waited = true;
                    if !self.wait_back().await {
                        return Err(e);
                    }
                }
                // Klipper restarting (or shut down until the user restarts it): its heaters
                // are off, and neither the command nor the console reaches it; wait for it
                // once (a minute at most), so that the user hears what happened.
                Err(e) if !klipper_waited && !self.klipper_ready().await => {
                    klipper_waited = true;
                    if !self.wait_back().await {
                        return Err(e);
                    }
                }
                Err(e) => return Err(e),
            }
        }
        if waited {
            self.console_error(&format!("{what}; now that Moonraker is back: heaters off"))
                .await;
        }
        Ok(())
    }

    /// The script that sets the configured timeout again (none where the config has none).
    /// Kalico's `timeout: 0` (never) cannot be sent back as 0
    /// (`SET_IDLE_TIMEOUT` refuses it, which left the session's hold in force): it goes back
    /// as ten years, said on the console.
    async fn restore_idle_timeout_script(&self) -> anyhow::Result<Option<String>> {
        let cf = self.inner.m.configfile().await?;
        let Some(t) = cf.settings.idle_timeout.and_then(|i| i.timeout) else {
            return Ok(None);
        };
        let mut script = gcode_cmd::restore_idle_timeout(t)?;
        if t <= 0.0 {
            let why = crate::jobs::core::console::respond_line(
                "idle timeout back to off ([idle_timeout] timeout: 0; Klipper takes no 0 at run \
                 time, so ten years)",
            );
            script = format!("{why}\n{script}");
        }
        Ok(Some(script))
    }

    /// Lets Klipper itself turn the heaters off after `hold_s` of idling from now, even if
    /// klipcal (or Moonraker) is gone: the heater's owner while klipcal cannot be. Each call
    /// starts the count again. A 1 ms dwell follows, so that Klipper's idle timer runs even from
    /// its `Idle` state (where it only starts again with the next move).
    ///
    /// # Errors
    /// Moonraker failures.
    pub(crate) async fn hold_heaters_for(&self, hold_s: f64) -> anyhow::Result<()> {
        self.hold_heaters_with(hold_s, "").await
    }

    /// [`Core::hold_heaters_for`], then `then` (e.g. the bed's target), in one script: one
    /// console row, and the bound set before the heater. Every hold is sent, also the same
    /// value again: each one restarts Klipper's count from now (skipping a repeat within 5 s
    /// let the bed stay on 62 s after a 45 s hold in the fault matrix's A/B hold case).
    ///
    /// # Errors
    /// Moonraker failures.
    pub(crate) async fn hold_heaters_with(&self, hold_s: f64, then: &str) -> anyhow::Result<()> {
        let mut lines = vec![
            gcode_cmd::set_idle_timeout(hold_s.max(1.0).ceil())?,
            "G4 P1".to_string(),
        ];
        if !then.is_empty() {
            lines.push(then.to_string());
        }
        match self.inner.m.gcode(&lines.join("\n")).await {
            Ok(_) => Ok(()),
            // Kalico's uncalibrated MPC heater: the user's to fix, said in plain words.
            Err(e) => match crate::klipper::kalico::mpc_refusal(&e.to_string()) {
                Some(said) => Err(user(said)),
                None => Err(anyhow::Error::from(e)
                    .context("setting Klipper's idle timeout to the hold limit")),
            },
        }
    }

    /// A console message.
    pub(crate) async fn console(&self, msg: &str) {
        console::say(&self.inner.m, msg).await;
    }

    /// A console error (`RESPOND TYPE=error`, coloured by Mainsail and Fluidd).
    pub(crate) async fn console_error(&self, msg: &str) {
        console::error(&self.inner.m, msg).await;
    }

    /// Opens (or replaces) the prompt dialog. Within a call it goes to the console after the
    /// call's answer; the same dialog as the one showing is not sent again (a jog press does not
    /// repeat the whole dialog on the console).
    pub(crate) async fn prompt(&self, p: &Prompt) {
        let (script, fresh) = self.stamp(p);
        if !fresh {
            return;
        }
        self.set_open(Some(p.clone()));
        let change = console::PromptChange::Show(script);
        if !console::hold(change.clone()) {
            console::send_script(&self.inner.m, &change.script()).await;
        }
    }

    /// [`Core::prompt`], unless the user closed klipcal's dialog without answering (✕, a tap
    /// outside): then it stays closed, and `_KLIPCAL_PROMPT_BACK` brings this one back. A phone
    /// user closes the full-screen jog dialog to jog on klipcal's page while watching the
    /// camera (issue 40 item 2): a press there must not cover the page with it again.
    pub(crate) async fn prompt_unless_closed(&self, p: &Prompt) {
        {
            let mut open = self.open();
            if open.user_closed.is_some() {
                open.user_closed = Some(p.clone());
                return;
            }
        }
        self.prompt(p).await;
    }

    /// Closes klipcal's dialog (the flow moved on): within a call after its answer; nothing is
    /// sent when klipcal's dialog is known to be closed already.
    pub(crate) async fn prompt_end(&self) {
        self.retire_ask();
        if !self.mark_closed() {
            return;
        }
        if !console::hold(console::PromptChange::End) {
            console::send_script(&self.inner.m, console::PROMPT_END).await;
        }
    }

    /// Closes whatever dialog shows, also one klipcal did not open (the cancel question comes
    /// from `_KLIPCAL_CANCEL_ASK` in Klipper, and a front end may report klipcal's own dialog
    /// closed as it replaces it): a cancel always ends with no dialog.
    pub(crate) async fn prompt_end_any(&self) {
        self.retire_ask();
        self.mark_closed();
        if !console::hold(console::PromptChange::End) {
            console::send_script(&self.inner.m, console::PROMPT_END).await;
        }
    }

    /// Closes klipcal's dialog now, even within a call (before a long operation, so that its
    /// buttons cannot be pressed again meanwhile).
    pub(crate) async fn prompt_end_now(&self) {
        console::drop_held();
        self.retire_ask();
        if self.mark_closed() {
            console::send_script(&self.inner.m, console::PROMPT_END).await;
        }
    }

    /// Shows klipcal's dialog again (the Back of the cancel confirmation, which replaced it):
    /// false when klipcal has no dialog open.
    pub(crate) async fn prompt_again(&self) -> bool {
        let shown = self.shown().clone();
        let script = match shown {
            Some(Some(script)) => script,
            // Closed by the user's ✕ or tap outside: the helper the console named shows it.
            _ => match take_user_closed(self) {
                Some(p) => {
                    let script = p.script_asked(self.asked().in_force);
                    *self.shown() = Some(Some(script.clone()));
                    self.set_open(Some(p));
                    script
                }
                None => return false,
            },
        };
        let change = console::PromptChange::Show(script);
        if !console::hold(change.clone()) {
            console::send_script(&self.inner.m, &change.script()).await;
        }
        true
    }

    /// `p`'s script stamped with the number of its question ([`Prompt::script_asked`]), marked
    /// as showing, and whether it differs from the dialog showing (false: nothing to send).
    /// The same dialog keeps its number; any other asks a new question.
    fn stamp(&self, p: &Prompt) -> (String, bool) {
        let mut shown = self.shown();
        if let Some(n) = self.asked().in_force {
            let same = p.script_asked(Some(n));
            if shown
                .as_ref()
                .is_some_and(|s| s.as_deref() == Some(same.as_str()))
            {
                return (same, false);
            }
        }
        let n = self.ask_next();
        let script = p.script_asked(Some(n));
        *shown = Some(Some(script.clone()));
        (script, true)
    }

    /// The title of klipcal's dialog open now, as far as klipcal knows.
    pub(crate) fn dialog_title(&self) -> Option<String> {
        self.open().prompt.as_ref().map(|p| p.title.clone())
    }

    /// Marks klipcal's dialog closed; false when it was known to be closed already.
    fn mark_closed(&self) -> bool {
        let was_closed = {
            let mut shown = self.shown();
            let was_closed = matches!(*shown, Some(None));
            *shown = Some(None);
            was_closed
        };
        self.set_open(None);
        !was_closed
    }

    fn open(&self) -> std::sync::MutexGuard<'_, Open> {
        self.inner
            .open
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner)
    }

    fn set_open(&self, p: Option<Prompt>) {
        let mut open = self.open();
        open.prompt = p;
        open.user_closed = None;
    }

    /// Watches the console for a close of klipcal's dialog that klipcal did not send: the
    /// user's ✕ in Mainsail or tap outside in Fluidd (both send `action:prompt_end`). Then the
    /// console says what still waits and how to answer (issue 26 A.1). Every close klipcal
    /// sends is marked before it is sent, also the ones its helpers ask for
    /// (`_KLIPCAL_PROMPT_CLOSE` and `_KLIPCAL_PROMPT_BACK` only call klipcal, which closes or
    /// replaces the dialog), and every close klipcal sends is counted until its echo comes
    /// back ([`console::own_close_echo`]), so a close that is not one of klipcal's, seen while
    /// klipcal's dialog is marked open, is the user's: no time window decides, however loaded
    /// the host. Runs until shutdown.
    pub(crate) async fn watch_closes(self) {
        use tokio::sync::broadcast::error::RecvError;
        let mut rx = self.inner.m.events();
        loop {
            let ev = tokio::select! {
                () = self.inner.shutdown.cancelled() => return,
                ev = rx.recv() => ev,
            };
            match ev {
                Ok(crate::moonraker::Event::GcodeResponse(l))
                    if l.trim() == "// action:prompt_end" => {}
                Err(RecvError::Closed) => return,
                _ => continue,
            }
            // klipcal's own close (counted as it was sent, however late its echo comes).
            if console::own_close_echo(&self.inner.m) {
                continue;
            }
            // No dialog of klipcal's open.
            let Some(p) = self.open().prompt.clone() else {
                continue;
            };
            self.mark_closed();
            // Where a phone answers without a console (issue 40 item 3): the page.
            let mut notice = console::closed_notice(&p);
            if let Some(road) = self.page_road() {
                notice.push_str(&format!("; or answer on {road}"));
            }
            console::say(&self.inner.m, &notice).await;
            self.open().user_closed = Some(p);
        }
    }

    fn shown(&self) -> std::sync::MutexGuard<'_, Option<Option<String>>> {
        self.inner
            .shown
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner)
    }
}

/// The dialog the user closed, taken (the lock released before the caller goes on).
fn take_user_closed(core: &Core) -> Option<Prompt> {
    let mut open = core.open();
    open.user_closed.take()
}
