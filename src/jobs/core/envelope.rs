//! The session envelope every calibration's stored document shares: id, state, reason,
//! progress and notes around the calibration's own body ([`Envelope`]), and what a calibration
//! says of its states ([`SessionState`]: which are final, which the daemon drives by itself,
//! how each is named). Setting a state, failing, cancelling, the status's common part
//! ([`StatusHead`]) and the store's notion of "final" all come from here.

use std::ops::{Deref, DerefMut};

use serde::de::DeserializeOwned;
use serde::{Deserialize, Serialize};

use super::session::{Core, Doc};

/// A calibration's session states.
pub trait SessionState:
    Copy + Eq + Serialize + DeserializeOwned + Send + Sync + std::fmt::Debug + 'static
{
    /// Every state, in the order a session meets them.
    const ALL: &'static [Self];
    /// The final states, in this order: the one a session succeeds in, the one it fails in, the
    /// one it is cancelled in.
    const FINAL: [Self; 3];
    /// The state a failed session ends in.
    const FAILED: Self = Self::FINAL[1];
    /// The state a cancelled session ends in.
    const CANCELLED: Self = Self::FINAL[2];

    /// Whether the session is over.
    fn is_final(self) -> bool {
        Self::FINAL.contains(&self)
    }

    /// Whether the daemon drives this state by itself (as opposed to waiting for the user).
    fn is_automatic(self) -> bool {
        false
    }

    /// The state's name as stored and shown (its serde name, `snake_case`).
    fn name(self) -> String {
        serde_json::to_value(self)
            .ok()
            .and_then(|v| v.as_str().map(str::to_string))
            .unwrap_or_default()
    }

    /// The names of the final states (what the store counts as ended).
    #[must_use]
    fn final_names() -> Vec<String> {
        Self::ALL
            .iter()
            .filter(|s| s.is_final())
            .map(|s| s.name())
            .collect()
    }
}

/// A stored session: the common part around the calibration's own `body`, which is flattened
/// into the same JSON object (the stored documents keep their shape).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Envelope<S, B> {
    /// Store id.
    pub id: i64,
    /// State.
    pub state: S,
    /// Why it failed or was cancelled.
    pub reason: Option<String>,
    /// The current step in words.
    pub progress: String,
    /// Things the user should know (skew cleared, heaters turned off, …).
    pub notes: Vec<String>,
    /// The calibration's own part.
    #[serde(flatten)]
    pub body: B,
}

impl<S: SessionState, B> Envelope<S, B> {
    /// A new session (id 0 until the store gives it one).
    pub(crate) fn new(state: S, progress: impl Into<String>, body: B) -> Self {
        Self {
            id: 0,
            state,
            reason: None,
            progress: progress.into(),
            notes: Vec::new(),
            body,
        }
    }

    /// Moves to `state`, saying what happens now.
    pub(crate) fn set(&mut self, state: S, progress: impl Into<String>) {
        self.state = state;
        self.progress = progress.into();
    }

    /// Ends the session in `state` (final) with `reason`.
    pub(crate) fn end(&mut self, state: S, reason: &str, progress: impl Into<String>) {
        self.state = state;
        self.reason = Some(reason.to_string());
        self.progress = progress.into();
    }

    /// The status's common part.
    #[must_use]
    pub(crate) fn head(&self) -> StatusHead {
        StatusHead {
            id: self.id,
            state: self.state.name(),
            progress: self.progress.clone(),
            reason: self.reason.clone(),
            notes: self.notes.clone(),
            finished: self.state.is_final(),
        }
    }
}

impl<S, B> Deref for Envelope<S, B> {
    type Target = B;
    fn deref(&self) -> &B {
        &self.body
    }
}

impl<S, B> DerefMut for Envelope<S, B> {
    fn deref_mut(&mut self) -> &mut B {
        &mut self.body
    }
}

impl<S: SessionState, B: Serialize + DeserializeOwned + Send> Doc for Envelope<S, B> {
    fn state_name(&self) -> String {
        self.state.name()
    }
}

/// What every session's status shows, whatever its kind.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct StatusHead {
    /// Session id.
    pub id: i64,
    /// State name.
    pub state: String,
    /// The current step in words.
    pub progress: String,
    /// Why it failed or was cancelled.
    pub reason: Option<String>,
    /// Things the user should know.
    pub notes: Vec<String>,
    /// The state is one of the calibration's final states (`converged`, `done`, `failed`,
    /// `cancelled`: each calibration declares its own): the page, the console and the API
    /// read this, never a list of state names of their own.
    #[serde(default)]
    pub finished: bool,
}

impl Core {
    /// Moves session `id` to `state`, saying what happens now (logged).
    ///
    /// # Errors
    /// No such session, a damaged document, or a store failure.
    pub(crate) async fn set_state<S, B>(
        &self,
        id: i64,
        state: S,
        progress: &str,
    ) -> anyhow::Result<()>
    where
        S: SessionState,
        B: Serialize + DeserializeOwned + Send,
    {
        tracing::info!(session = id, state = %state.name(), "{progress}");
        self.update::<Envelope<S, B>, ()>(id, |s| {
            s.set(state, progress);
            Ok(())
        })
        .await
    }

    /// Ends session `id` in `state` with `reason` (cancelled, failed, …).
    ///
    /// # Errors
    /// No such session, a damaged document, or a store failure.
    pub(crate) async fn end_session<S, B>(
        &self,
        id: i64,
        state: S,
        reason: &str,
        progress: &str,
    ) -> anyhow::Result<()>
    where
        S: SessionState,
        B: Serialize + DeserializeOwned + Send,
    {
        self.update::<Envelope<S, B>, ()>(id, |s| {
            s.end(state, reason, progress);
            Ok(())
        })
        .await
    }

    /// A session's runner failed: the heaters go off (once Moonraker is back), the session
    /// ends failed with `why` unless it ended already, the dialog closes when `close_prompt`,
    /// and the console says so (`"{title} failed: {why}; heaters off"`). When the heaters did go
    /// off, `heaters_off` marks it in the body (the calibrations whose status says so).
    pub(crate) async fn fail_session<S, B>(
        &self,
        id: i64,
        title: &str,
        why: &str,
        close_prompt: bool,
        heaters_off: impl FnOnce(&mut B) + Send,
    ) where
        S: SessionState,
        B: Serialize + DeserializeOwned + Send,
    {
        let off = self
            .heaters_off_once_back(&format!("{title} failed: {why}"))
            .await;
        if let Err(e) = &off {
            tracing::warn!(session = id, error = %format!("{e:#}"), "heaters not turned off");
        }
        let heaters = if off.is_ok() { "; heaters off" } else { "" };
        let _ = self
            .update::<Envelope<S, B>, ()>(id, |s| {
                if !s.state.is_final() {
                    s.end(S::FAILED, why, format!("failed{heaters}"));
                }
                if off.is_ok() {
                    heaters_off(&mut s.body);
                }
                Ok(())
            })
            .await;
        if close_prompt {
            self.prompt_end().await;
        }
        self.console_error(&format!("{title} failed: {why}{heaters}"))
            .await;
    }

    /// Ends session `id` cancelled with `reason` (after the calibration stopped what it runs)
    /// and the answer to the cancel: `{"session", "state": "cancelled", "message"}`.
    ///
    /// # Errors
    /// No such session, a damaged document, or a store failure.
    pub(crate) async fn cancel_session<S, B>(
        &self,
        id: i64,
        reason: &str,
        progress: &str,
        message: String,
    ) -> anyhow::Result<super::answer::SessionAnswer>
    where
        S: SessionState,
        B: Serialize + DeserializeOwned + Send,
    {
        self.end_session::<S, B>(id, S::CANCELLED, reason, progress)
            .await?;
        Ok(super::answer::SessionAnswer {
            session: id,
            state: S::CANCELLED.name(),
            message,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
    #[serde(rename_all = "snake_case")]
    enum St {
        Running,
        WaitingOnUser,
        Done,
        Failed,
        Cancelled,
    }

    impl SessionState for St {
        const ALL: &'static [Self] = &[
            St::Running,
            St::WaitingOnUser,
            St::Done,
            St::Failed,
            St::Cancelled,
        ];
        const FINAL: [Self; 3] = [St::Done, St::Failed, St::Cancelled];
    }

    #[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
    struct Body {
        rounds: Vec<u32>,
        #[serde(default)]
        later: Option<f64>,
    }

    #[test]
    fn the_body_is_flattened_into_one_document_and_reads_back() {
        let mut s = Envelope::new(
            St::WaitingOnUser,
            "waiting",
            Body {
                rounds: vec![1],
                later: None,
            },
        );
        s.id = 7;
        s.rounds.push(2);
        let v = serde_json::to_value(&s).unwrap();
        assert_eq!(
            v,
            serde_json::json!({"id": 7, "state": "waiting_on_user", "reason": null,
                               "progress": "waiting", "notes": [], "rounds": [1, 2],
                               "later": null})
        );
        // A document stored before a body field existed reads with its default.
        let old = serde_json::json!({"id": 7, "state": "done", "reason": null,
                                     "progress": "", "notes": ["n"], "rounds": [3]});
        let back: Envelope<St, Body> = serde_json::from_value(old).unwrap();
        assert_eq!(
            (back.state, back.rounds.clone(), back.later),
            (St::Done, vec![3], None)
        );
        assert_eq!(back.state_name(), "done");
    }

    #[test]
    fn the_final_states_and_names_come_from_the_trait() {
        assert_eq!(St::final_names(), vec!["done", "failed", "cancelled"]);
        assert_eq!((St::FAILED, St::CANCELLED), (St::Failed, St::Cancelled));
        assert!(!St::Running.is_final() && !St::WaitingOnUser.is_final());
        assert_eq!(St::WaitingOnUser.name(), "waiting_on_user");
        let mut s = Envelope::new(
            St::Running,
            "",
            Body {
                rounds: vec![],
                later: None,
            },
        );
        s.end(St::CANCELLED, "user", "cancelled");
        let h = s.head();
        assert_eq!(
            (h.state.as_str(), h.reason.as_deref()),
            ("cancelled", Some("user"))
        );
    }
}
