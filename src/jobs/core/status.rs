//! The status as typed structs: what `klipcal_status` (the agent's answer, `/api/status` and
//! the page) shows of the sessions. Each calibration's own part is its own `Serialize` struct
//! (`AbStatus`, `MeshStatus`, `BacklashStatus`), flattened beside the envelope's
//! [`StatusHead`]; the agent wraps [`SessionsStatus`] with the daemon, the connection and the
//! printer (`agent::StatusAnswer`).

use std::collections::BTreeMap;

use serde::Serialize;
use serde_json::Value;

use super::envelope::StatusHead;

/// One session as the status shows it.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct SessionStatus {
    /// The store's kind (`ab`, `mesh`, `backlash`).
    pub kind: String,
    /// Id, state, progress, reason, notes.
    #[serde(flatten)]
    pub head: StatusHead,
    /// The calibration's own part, serialized from its status struct (an object whose keys
    /// sit beside the head's).
    #[serde(flatten)]
    pub body: BTreeMap<String, Value>,
    /// Lines the console's status shows under the session (the A/B readings still missing);
    /// not in the JSON, where the body has them under its own name.
    #[serde(skip)]
    pub console_lines: Vec<String>,
}

impl SessionStatus {
    /// A session of `kind`: its head and its calibration's status struct `body` (which must
    /// serialize to an object).
    ///
    /// # Errors
    /// `body` does not serialize to a JSON object.
    pub(crate) fn new(kind: &str, head: StatusHead, body: &impl Serialize) -> anyhow::Result<Self> {
        let body = match serde_json::to_value(body)? {
            Value::Object(o) => o.into_iter().collect(),
            other => anyhow::bail!("a {kind} status is not an object: {other}"),
        };
        Ok(Self {
            kind: kind.to_string(),
            head,
            body,
            console_lines: Vec::new(),
        })
    }

    /// With `lines` shown under the session on the console.
    #[must_use]
    pub(crate) fn with_console_lines(mut self, lines: Vec<String>) -> Self {
        self.console_lines = lines;
        self
    }
}

/// The sessions part of the status.
#[derive(Debug, Clone, PartialEq, Serialize, Default)]
pub(crate) struct SessionsStatus {
    /// The active session of any kind, or else the newest one.
    pub session: Option<SessionStatus>,
    /// Per kind, its newest session, final or not.
    pub last: BTreeMap<String, SessionStatus>,
    /// The bed soak under way (its line, how it was worked out) and its question.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub soak: Option<super::soak_ask::SoakView>,
}
