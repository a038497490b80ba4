//! The number of the question klipcal's dialog asks: every button of the dialog carries it
//! (`ASK=<n>`, see [`Prompt::script_asked`]), and a press whose question klipcal no longer asks
//! is refused (issue 40: the "round 2?" dialog's End, still shown in a second front end,
//! cancelled the round 2 that had started meanwhile).

use serde_json::{json, Value};

use super::*;

/// The store's key of [`Asked`].
const KEY: &str = "prompt_ask";

/// The last question's number and the one klipcal's dialog asks now.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub(super) struct Asked {
    /// The last number given (numbers are never given twice, also across restarts).
    pub(super) last: u64,
    /// The question klipcal's dialog asks now (shown, or closed by the user without an
    /// answer); `None` once klipcal ended its dialog (answered, or the flow moved on).
    pub(super) in_force: Option<u64>,
}

impl Asked {
    /// As stored; none stored (or unreadable, logged) starts from nothing.
    pub(super) fn load(store: &Store) -> Self {
        match store.value(KEY) {
            Ok(Some(v)) => Self {
                last: v["last"].as_u64().unwrap_or(0),
                in_force: v["in_force"].as_u64(),
            },
            Ok(None) => Self::default(),
            Err(e) => {
                warn!(error = %e, "the dialog's question number is unreadable; starting anew");
                Self::default()
            }
        }
    }
}

impl Core {
    pub(super) fn asked(&self) -> std::sync::MutexGuard<'_, Asked> {
        self.inner
            .asked
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner)
    }

    /// A new question: its number, now in force.
    pub(super) fn ask_next(&self) -> u64 {
        let mut a = self.asked();
        a.last += 1;
        a.in_force = Some(a.last);
        self.keep_asked(*a);
        a.last
    }

    /// klipcal's dialog ended: no question of it is in force.
    pub(super) fn retire_ask(&self) {
        let mut a = self.asked();
        if a.in_force.take().is_some() {
            self.keep_asked(*a);
        }
    }

    fn keep_asked(&self, a: Asked) {
        if let Err(e) = self
            .inner
            .store
            .set_value(KEY, &json!({"last": a.last, "in_force": a.in_force}))
        {
            warn!(error = %e, "the dialog's question number not stored");
        }
    }

    /// Takes `ASK=<n>` out of a call's arguments (any case), refusing the call when question
    /// `n` is not the one klipcal's dialog asks now: then klipcal's own dialog shows again, or
    /// none when it has none (the stale dialog, or the cancel question it opened, goes away).
    /// `command` names the call in the refusal.
    ///
    /// # Errors
    /// A malformed `ASK`, or a question klipcal no longer asks, in words.
    pub(crate) async fn take_ask(&self, args: &Value, command: &str) -> anyhow::Result<Value> {
        let Value::Object(obj) = args else {
            return Ok(args.clone());
        };
        let mut rest = obj.clone();
        let keys: Vec<String> = obj
            .keys()
            .filter(|k| k.eq_ignore_ascii_case(console::ASK_ARG))
            .cloned()
            .collect();
        let Some(key) = keys.first() else {
            return Ok(args.clone());
        };
        if keys.len() > 1 {
            return Err(user(format!(
                "{command}: argument ASK given twice; give it once"
            )));
        }
        let raw = rest.remove(key).unwrap_or(Value::Null);
        let asked = match &raw {
            Value::Number(n) => n.as_u64(),
            Value::String(t) => t.trim().parse::<u64>().ok(),
            _ => None,
        }
        .ok_or_else(|| {
            user(format!(
                "{command}: ASK={} is not a dialog's question number (a whole number its \
                 buttons add); typed without ASK, {command} acts on the session as it is now",
                raw.as_str().map_or_else(|| raw.to_string(), str::to_string)
            ))
        })?;
        if self.asked().in_force == Some(asked) {
            return Ok(Value::Object(rest));
        }
        if !self.prompt_again().await {
            self.prompt_end_any().await;
        }
        Err(user(format!(
            "{command}: nothing done: pressed in an older klipcal dialog (question {asked}), \
             whose question was answered or has passed (the session moved on). KLIPCAL_STATUS \
             says what klipcal waits for; typed without ASK, {command} acts on the session as \
             it is now"
        )))
    }
}
