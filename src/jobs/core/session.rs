//! The session core every calibration shares: stored session documents of any kind, one active
//! session at a time across kinds, the runner that drives a session's automatic states, and the
//! printer guards (idle, ready, heaters off, hold limit). Nothing of any one calibration lives
//! here: a calibration keeps its own document type and its own steps (`jobs/ab.rs`, …).

mod ask;
mod guards;

use std::collections::BTreeMap;
use std::future::Future;
use std::sync::Arc;
use std::time::{SystemTime, UNIX_EPOCH};

use anyhow::{anyhow, Context};
use serde::de::DeserializeOwned;
use serde::Serialize;
use serde_json::json;
use tokio_util::sync::CancellationToken;

use tracing::{info, warn};

use super::console::{self, Prompt};
use super::user;
use crate::klipper::gcode_cmd;
use crate::moonraker::{Files, Moonraker};
use crate::store::{SessionRow, Store};

/// The name of the webcam `klipcal install` adds for the page (Mainsail and Fluidd show it as
/// a webcam tile, the way to the page on a phone).
pub(crate) const PAGE_WEBCAM: &str = "klipcal";

/// How long a session waits for Klipper to be ready once Moonraker is back after an outage,
/// before its steps look at the printer as it is.
const KLIPPY_BACK_LIMIT: std::time::Duration = std::time::Duration::from_secs(60);

/// A calibration's stored session document.
pub(crate) trait Doc: Serialize + DeserializeOwned + Send {
    /// The state's name as stored (the store's `state` column; final states end the session).
    fn state_name(&self) -> String;
}

/// Unix time now, in seconds.
#[must_use]
pub(crate) fn now_unix() -> f64 {
    SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .map_or(0.0, |d| d.as_secs_f64())
}

/// Whether the hold limit has passed: `hold_max_s` after `since_unix` (the print's end, the
/// capture's start, …).
#[must_use]
pub(crate) fn hold_expired(since_unix: Option<f64>, hold_max_s: f64, now_unix: f64) -> bool {
    since_unix.is_some_and(|t| now_unix >= t + hold_max_s)
}

/// The shared core: Moonraker, the files API, the store, and one runner at a time.
#[derive(Clone)]
pub struct Core {
    inner: Arc<Inner>,
}

struct Inner {
    m: Moonraker,
    files: Files,
    store: Store,
    shutdown: CancellationToken,
    /// Serialises every change of a session document, of any kind.
    lock: tokio::sync::Mutex<()>,
    runner: std::sync::Mutex<Option<CancellationToken>>,
    /// Kind → how a user calls it ("an A/B calibration"), for refusals.
    titles: std::sync::RwLock<BTreeMap<String, String>>,
    /// What klipcal's dialog shows, as far as klipcal knows: `None` after a start (unknown),
    /// `Some(None)` closed, `Some(Some(script))` showing that script.
    shown: std::sync::Mutex<Option<Option<String>>>,
    /// klipcal's dialog open now (as last sent): a close seen on the console while it is open
    /// is the user's (see [`Core::watch_closes`]).
    open: std::sync::Mutex<Open>,
    /// The number of the question klipcal's dialog asks (its buttons carry it), kept in the
    /// store so that a press after a restart is judged too.
    asked: std::sync::Mutex<ask::Asked>,
    /// Every task the core starts (runners, the follower, the watchdog, the resume), so that
    /// shutdown waits for them.
    tasks: tokio_util::task::TaskTracker,
    /// klipcal's page as a user opens it (set once the page is listening).
    page: std::sync::OnceLock<String>,
    /// Why the page is off when it could not start (its port taken, …).
    page_off: std::sync::OnceLock<String>,
    /// The soak question (what is on the bed, open or enclosed) and its answers.
    ask: std::sync::Mutex<super::soak_ask::AskState>,
}

impl Core {
    /// Builds the core; calibrations are registered on top of it by [`crate::jobs::Calibrations`].
    pub(crate) fn new(
        m: Moonraker,
        files: Files,
        store: Store,
        shutdown: CancellationToken,
    ) -> Self {
        let asked = ask::Asked::load(&store);
        Self {
            inner: Arc::new(Inner {
                m,
                files,
                store,
                shutdown,
                lock: tokio::sync::Mutex::new(()),
                runner: std::sync::Mutex::new(None),
                titles: std::sync::RwLock::new(BTreeMap::new()),
                shown: std::sync::Mutex::new(None),
                open: std::sync::Mutex::new(Open::default()),
                asked: std::sync::Mutex::new(asked),
                tasks: tokio_util::task::TaskTracker::new(),
                page: std::sync::OnceLock::new(),
                page_off: std::sync::OnceLock::new(),
                ask: std::sync::Mutex::new(super::soak_ask::AskState::default()),
            }),
        }
    }

    /// The soak question's state (held only briefly: never across an await).
    pub(crate) fn ask_state(&self) -> std::sync::MutexGuard<'_, super::soak_ask::AskState> {
        self.inner
            .ask
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner)
    }

    /// Moonraker.
    pub(crate) fn m(&self) -> &Moonraker {
        &self.inner.m
    }

    /// Moonraker's file API.
    pub(crate) fn files(&self) -> &Files {
        &self.inner.files
    }

    /// The database.
    pub(crate) fn store(&self) -> &Store {
        &self.inner.store
    }

    /// Saves a picture (SVG text, `path` ending in `.svg`) under Moonraker's config root, and
    /// beside it the same picture as PNG (`.png`, drawn by [`crate::plots::svg_to_png`]), which
    /// Mainsail's and Fluidd's file browsers show as an image. Returns how to name it to a user
    /// (`config/klipcal/….png`, or the `.svg` when the PNG could not be made), or `None` when
    /// nothing could be saved (logged: a picture never fails a calibration).
    pub(crate) async fn save_picture(&self, path: &str, svg: String) -> Option<String> {
        let png_path = path.strip_suffix(".svg").map(|stem| format!("{stem}.png"));
        let png = match &png_path {
            Some(_) => {
                let text = svg.clone();
                tokio::task::spawn_blocking(move || {
                    crate::plots::svg_to_png(&text, crate::plots::PNG_WIDTH_PX)
                })
                .await
                .map_err(anyhow::Error::from)
                .and_then(|r| r)
                .map_err(|e| tracing::warn!(error = %e, %path, "no PNG of the picture"))
                .ok()
            }
            None => None,
        };
        let svg_saved = match self.files().upload("config", path, svg.into_bytes()).await {
            Ok(_) => Some(format!("config/{path}")),
            Err(e) => {
                tracing::warn!(error = %e, %path, "the picture was not saved");
                None
            }
        };
        if let (Some(png_path), Some(png)) = (png_path, png) {
            match self.files().upload("config", &png_path, png).await {
                Ok(_) => return Some(format!("config/{png_path}")),
                Err(e) => tracing::warn!(error = %e, path = %png_path, "the PNG was not saved"),
            }
        }
        svg_saved
    }

    /// The daemon's shutdown token.
    pub(crate) fn shutdown(&self) -> &CancellationToken {
        &self.inner.shutdown
    }

    /// Starts a task shutdown waits for (see [`Core::stopped`]); it must end when the shutdown
    /// token is cancelled.
    pub(crate) fn spawn<F>(&self, fut: F)
    where
        F: Future<Output = ()> + Send + 'static,
    {
        self.inner.tasks.spawn(fut);
    }

    /// After shutdown: waits at most `limit` for every task the core started to end; false when
    /// some are still running then (named in the log by the caller).
    pub(crate) async fn stopped(&self, limit: std::time::Duration) -> bool {
        self.inner.tasks.close();
        tokio::time::timeout(limit, self.inner.tasks.wait())
            .await
            .is_ok()
    }

    /// How many tasks the core has running.
    #[must_use]
    pub(crate) fn running_tasks(&self) -> usize {
        self.inner.tasks.len()
    }

    /// Notes where klipcal's page is (`http://192.168.1.23:7150/`), for the console's answers.
    pub(crate) fn set_page(&self, address: String) {
        let _ = self.inner.page.set(address);
    }

    /// Notes why the page is off (it could not listen), for KLIPCAL_STATUS.
    pub(crate) fn set_page_off(&self, why: String) {
        let _ = self.inner.page_off.set(why);
    }

    /// Why the page is off, when it could not start.
    #[must_use]
    pub(crate) fn page_off(&self) -> Option<&str> {
        self.inner.page_off.get().map(String::as_str)
    }

    /// "on klipcal's page, http://…" for the console, or `None` when the page is off.
    #[must_use]
    pub(crate) fn page(&self) -> Option<&str> {
        self.inner.page.get().map(String::as_str)
    }

    /// Where a user typing or jogging finds the page, for a dialog or an answer: "klipcal's
    /// page, http://…, on a phone also its webcam tile 'klipcal'" (Mainsail's phone dashboard
    /// has no console; the page is under nav → Webcam), or `None` when the page is off.
    #[must_use]
    pub(crate) fn page_road(&self) -> Option<String> {
        self.page().map(|p| {
            format!("klipcal's page, {p}, on a phone also its webcam tile '{PAGE_WEBCAM}'")
        })
    }

    /// Names a kind for refusals ("an A/B calibration").
    pub(crate) fn register_kind(&self, kind: &str, title: &str) {
        if let Ok(mut t) = self.inner.titles.write() {
            t.insert(kind.to_string(), title.to_string());
        }
    }

    fn title(&self, kind: &str) -> String {
        self.inner
            .titles
            .read()
            .ok()
            .and_then(|t| t.get(kind).cloned())
            .unwrap_or_else(|| format!("a {kind} session"))
    }

    /// Takes the document lock (for a read-check-write that spans several calls).
    pub(crate) async fn lock(&self) -> tokio::sync::MutexGuard<'_, ()> {
        self.inner.lock.lock().await
    }

    /// Reads a stored document.
    ///
    /// # Errors
    /// No such session, or a document that does not read as `D`.
    pub(crate) fn load<D: Doc>(&self, id: i64) -> anyhow::Result<D> {
        let row = self
            .inner
            .store
            .session(id)?
            .ok_or_else(|| anyhow!("session {id} is not in the database"))?;
        read_doc(row)
    }

    /// Saves a document (its state column from [`Doc::state_name`]).
    ///
    /// # Errors
    /// SQLite failure.
    pub(crate) fn save<D: Doc>(&self, id: i64, doc: &D) -> anyhow::Result<()> {
        self.inner
            .store
            .save_session(id, &doc.state_name(), &serde_json::to_value(doc)?)?;
        Ok(())
    }

    /// Changes a document under the lock, saving it before returning.
    ///
    /// # Errors
    /// What `f` returns, or a store failure.
    pub(crate) async fn update<D: Doc, T>(
        &self,
        id: i64,
        f: impl FnOnce(&mut D) -> anyhow::Result<T>,
    ) -> anyhow::Result<T> {
        let _g = self.lock().await;
        let mut d: D = self.load(id)?;
        let out = f(&mut d)?;
        self.save(id, &d)?;
        Ok(out)
    }

    /// The active session of any kind.
    ///
    /// # Errors
    /// A damaged database.
    pub(crate) fn active(&self) -> anyhow::Result<Option<SessionRow>> {
        Ok(self.inner.store.active_session()?)
    }

    /// The active session when it is of `kind`, read as `D`.
    ///
    /// # Errors
    /// A damaged database or document.
    pub(crate) fn active_of<D: Doc>(&self, kind: &str) -> anyhow::Result<Option<(i64, D)>> {
        match self.active()? {
            Some(row) if row.kind == kind => Ok(Some((row.id, read_doc(row)?))),
            _ => Ok(None),
        }
    }

    /// The newest session of `kind`, active or not.
    ///
    /// # Errors
    /// A damaged database or document.
    pub(crate) fn latest_of<D: Doc>(&self, kind: &str) -> anyhow::Result<Option<(i64, D)>> {
        match self.inner.store.latest_session_of(kind)? {
            Some(row) => Ok(Some((row.id, read_doc(row)?))),
            None => Ok(None),
        }
    }

    /// The newest session of `kind` in state `state` (as the store names it).
    ///
    /// # Errors
    /// A damaged database or document.
    pub(crate) fn latest_of_in<D: Doc>(
        &self,
        kind: &str,
        state: &str,
    ) -> anyhow::Result<Option<(i64, D)>> {
        match self.inner.store.latest_session_of_in(kind, state)? {
            Some(row) => Ok(Some((row.id, read_doc(row)?))),
            None => Ok(None),
        }
    }

    /// Refuses when a session of another kind is active, naming it.
    ///
    /// # Errors
    /// A user error naming the running session.
    pub(crate) fn refuse_other_kind(&self, kind: &str) -> anyhow::Result<()> {
        match self.active()? {
            Some(row) if row.kind != kind => Err(user(format!(
                "{} (session {}) is {}; finish it or KLIPCAL_CANCEL first",
                self.title(&row.kind),
                row.id,
                row.state.replace('_', " ")
            ))),
            _ => Ok(()),
        }
    }

    /// Stores a new session of `kind` under the lock, refusing while any session is active;
    /// `set_id` writes the new id into the document, which is saved again with it.
    ///
    /// # Errors
    /// Another session active (named), or a store failure.
    pub(crate) async fn create<D: Doc>(
        &self,
        kind: &str,
        doc: &mut D,
        set_id: impl FnOnce(&mut D, i64),
    ) -> anyhow::Result<i64> {
        let _g = self.lock().await;
        if let Some(row) = self.active()? {
            return Err(user(format!(
                "{} (session {}) is {}; finish it or KLIPCAL_CANCEL first",
                self.title(&row.kind),
                row.id,
                row.state.replace('_', " ")
            )));
        }
        let id = self.inner.store.create_session(
            kind,
            &doc.state_name(),
            &serde_json::to_value(&*doc)?,
        )?;
        set_id(doc, id);
        self.save(id, doc)?;
        Ok(id)
    }

    /// Runs a session's automatic steps in the background, replacing (cancelling) any runner
    /// still going; it stops at [`Core::stop_runner`] or shutdown.
    pub(crate) fn spawn_runner<F>(&self, fut: F)
    where
        F: Future<Output = ()> + Send + 'static,
    {
        let token = self.inner.shutdown.child_token();
        if let Ok(mut r) = self.inner.runner.lock() {
            if let Some(old) = r.replace(token.clone()) {
                old.cancel();
            }
        }
        self.spawn(async move {
            tokio::select! {
                () = token.cancelled() => {}
                () = fut => {}
            }
        });
    }

    /// Runs session `id`'s automatic steps in the background ([`Core::spawn_runner`]), riding
    /// out Moonraker outages of any length: when `steps` ends on Moonraker being unreachable
    /// ([`Core::unreachable`]), the runner waits for it (and for Klipper) to be back, says so on
    /// the console, and runs `steps` again, which re-read the stored state and the printer and
    /// go on from there (or end the session, saying why). A step that fails while Klipper is not
    /// ready is run again the same way once Klipper is back (a minute at most), so that the
    /// session ends with what Klipper lost rather than the refused call. Only a real failure
    /// reaches `fail`, with its message.
    pub(crate) fn spawn_session<S, SF, F, FF>(
        &self,
        id: i64,
        title: &'static str,
        steps: S,
        fail: F,
    ) where
        S: Fn() -> SF + Send + 'static,
        SF: Future<Output = anyhow::Result<()>> + Send,
        F: FnOnce(String) -> FF + Send + 'static,
        FF: Future<Output = ()> + Send,
    {
        let core = self.clone();
        self.spawn_runner(async move {
            let mut klipper_waited = false;
            loop {
                let ran = std::time::Instant::now();
                let e = match steps().await {
                    Ok(()) => return,
                    Err(e) => e,
                };
                if ran.elapsed() > KLIPPY_BACK_LIMIT {
                    klipper_waited = false;
                }
                if !core.unreachable(&e) && !klipper_waited && !core.klipper_ready().await {
                    // Klipper went away under a step (FIRMWARE_RESTART, a shutdown, or
                    // Moonraker back before it reconnected to Klipper: "Method not found"):
                    // wait for it (a minute at most), then go on from the printer's state —
                    // which ends the session with the reason when Klipper lost what the step
                    // needs (a cold bed, no print).
                    klipper_waited = true;
                    warn!(session = id, error = %format!("{e:#}"), "Klipper not ready; the session waits for it");
                    if !core.wait_back().await {
                        return;
                    }
                    continue;
                }
                if !core.unreachable(&e) {
                    // Klipper still away: say so, not only the call it refused.
                    let why = if core.klipper_ready().await {
                        format!("{e:#}")
                    } else {
                        format!("Klipper stopped answering (a restart or a shutdown): {e:#}")
                    };
                    warn!(session = id, error = %why, "session failed");
                    fail(why).await;
                    return;
                }
                let why = format!("{e:#}");
                warn!(session = id, error = %why, "Moonraker unreachable; the session waits for it");
                let since = std::time::Instant::now();
                if !core.wait_back().await {
                    return;
                }
                let secs = since.elapsed().as_secs_f64();
                info!(session = id, outage_s = secs, "Moonraker is back; resuming the session");
                core.console(&format!(
                    "{title}: Moonraker was unreachable for {secs:.0} s ({why}); klipcal \
                     reconnected and goes on from the printer's state"
                ))
                .await;
            }
        });
    }

    /// Whether `e` says Moonraker is unreachable (connection refused or lost, no reply while
    /// disconnected) rather than a real failure: the one place that tells an outage from a
    /// failure ([`crate::moonraker::Error::is_unreachable`]).
    pub(crate) fn unreachable(&self, e: &anyhow::Error) -> bool {
        e.chain()
            .filter_map(|c| c.downcast_ref::<crate::moonraker::Error>())
            .any(|me| self.inner.m.is_unreachable(me))
    }

    /// Why Moonraker is unreachable now (its last connect error), or `None` when connected.
    pub(crate) fn unreachable_now(&self) -> Option<String> {
        match self.inner.m.state() {
            crate::moonraker::ConnState::Connected { .. } => None,
            crate::moonraker::ConnState::Connecting(why) => {
                Some(why.unwrap_or_else(|| "not connected yet".into()))
            }
            crate::moonraker::ConnState::Stopped => Some("klipcal is stopping".into()),
        }
    }

    /// Waits until Moonraker is back (and Klipper ready, or a minute spent waiting for it);
    /// false at shutdown.
    pub(crate) async fn wait_back(&self) -> bool {
        self.inner.m.wait_back(KLIPPY_BACK_LIMIT).await
    }

    /// Stops the running session's automatic steps.
    pub(crate) fn stop_runner(&self) {
        if let Ok(mut r) = self.inner.runner.lock() {
            if let Some(t) = r.take() {
                t.cancel();
            }
        }
    }
}

/// klipcal's dialog as the close watcher sees it.
#[derive(Default)]
pub(super) struct Open {
    /// The dialog open now, as last sent.
    prompt: Option<Prompt>,
    /// The dialog the user closed without answering, until klipcal's dialog changes.
    user_closed: Option<Prompt>,
}

fn read_doc<D: DeserializeOwned>(row: SessionRow) -> anyhow::Result<D> {
    let kind = row.kind.clone();
    serde_json::from_value(row.doc)
        .with_context(|| format!("reading stored session {} ({kind})", row.id))
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::time::Duration;

    /// A core whose Moonraker is never reached (nothing listens on port 9).
    pub(crate) fn offline_core() -> Core {
        let cancel = CancellationToken::new();
        let cfg = crate::config::Config::default();
        let mut opts = crate::app::client_options(&cfg);
        opts.url = "ws://127.0.0.1:9/websocket".into();
        let (m, _calls) = Moonraker::spawn(opts, cancel.clone());
        let files = Files::new("http://127.0.0.1:9", None, Duration::from_secs(1)).unwrap();
        Core::new(m, files, Store::in_memory().unwrap(), cancel)
    }

    #[tokio::test]
    async fn shutdown_waits_for_the_cores_tasks_and_gives_up_at_its_deadline() {
        let core = offline_core();
        let done = Arc::new(std::sync::atomic::AtomicBool::new(false));
        let (stop, flag) = (core.shutdown().clone(), done.clone());
        // A task that needs 200 ms to clean up after the token (a heater off, a last save).
        core.spawn(async move {
            stop.cancelled().await;
            tokio::time::sleep(Duration::from_millis(200)).await;
            flag.store(true, std::sync::atomic::Ordering::SeqCst);
        });
        assert_eq!(core.running_tasks(), 1);
        core.shutdown().cancel();
        assert!(core.stopped(Duration::from_secs(2)).await);
        assert!(
            done.load(std::sync::atomic::Ordering::SeqCst),
            "stopped() returned before the task ended"
        );
        // A task that ignores the token: the deadline ends the wait, and says so.
        let core = offline_core();
        core.spawn(std::future::pending());
        core.shutdown().cancel();
        let t0 = std::time::Instant::now();
        assert!(!core.stopped(Duration::from_millis(100)).await);
        assert!(t0.elapsed() < Duration::from_secs(1));
    }

    #[tokio::test]
    async fn a_runner_is_one_of_the_tasks_shutdown_waits_for() {
        let core = offline_core();
        core.spawn_runner(std::future::pending());
        assert_eq!(core.running_tasks(), 1);
        core.shutdown().cancel();
        assert!(core.stopped(Duration::from_secs(1)).await);
        assert_eq!(core.running_tasks(), 0);
    }

    #[derive(serde::Serialize, serde::Deserialize)]
    struct TestDoc {
        id: i64,
        state: String,
    }

    impl Doc for TestDoc {
        fn state_name(&self) -> String {
            self.state.clone()
        }
    }

    #[tokio::test]
    async fn a_second_calibration_of_another_kind_is_refused_naming_the_running_one() {
        let core = offline_core();
        core.store().add_final_states(["cancelled".to_string()]);
        core.register_kind("ab", "an A/B calibration");
        core.register_kind("mesh", "a thermal mesh calibration");
        let mut doc = TestDoc {
            id: 0,
            state: "measuring".into(),
        };
        let id = core
            .create("ab", &mut doc, |d, id| d.id = id)
            .await
            .unwrap();
        assert_eq!(core.load::<TestDoc>(id).unwrap().id, id);
        let e = core.refuse_other_kind("mesh").unwrap_err();
        assert_eq!(
            e.to_string(),
            format!(
                "an A/B calibration (session {id}) is measuring; finish it or KLIPCAL_CANCEL first"
            )
        );
        assert!(super::super::is_user_error(&e));
        core.refuse_other_kind("ab").unwrap();
        let mut other = TestDoc {
            id: 0,
            state: "capturing".into(),
        };
        let e = core
            .create("mesh", &mut other, |d, id| d.id = id)
            .await
            .unwrap_err();
        assert!(e.to_string().starts_with("an A/B calibration"), "{e}");
        // Once the first ends, the other kind may start, and status finds each kind's last.
        core.update::<TestDoc, ()>(id, |d| {
            d.state = "cancelled".into();
            Ok(())
        })
        .await
        .unwrap();
        let mid = core
            .create("mesh", &mut other, |d, id| d.id = id)
            .await
            .unwrap();
        assert_eq!(core.active_of::<TestDoc>("mesh").unwrap().unwrap().0, mid);
        assert!(core.active_of::<TestDoc>("ab").unwrap().is_none());
        assert_eq!(core.latest_of::<TestDoc>("ab").unwrap().unwrap().0, id);
    }

    #[test]
    fn the_hold_limit_counts_from_its_start() {
        assert!(!hold_expired(None, 10.0, 1e9));
        assert!(!hold_expired(Some(100.0), 10.0, 109.0));
        assert!(hold_expired(Some(100.0), 10.0, 110.0));
    }
}
