//! The A/B operations' answers, typed (the JSON the page and the API read; `message` is what
//! the console shows).

use serde::Serialize;

use crate::calib::solve::Solution;
use crate::jobs::core::printer_config::ApplyReport;

/// `klipcal_measure`: what was saved for the pair and what is still missing.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub(crate) struct Saved {
    /// The pair, as the layout names it.
    pub pair: String,
    /// The readings this entry saved, mm.
    pub saved: Vec<f64>,
    /// The pair's readings in all.
    pub count: usize,
    /// The pair's readings, mm.
    pub readings: Vec<f64>,
    /// What is still to measure, in words.
    pub missing: Vec<String>,
    /// What the console shows.
    pub message: String,
}

/// `klipcal_ab_check`: the entry judged as a whole and per field; nothing saved.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub(crate) struct Checked {
    /// The pair.
    pub pair: String,
    /// Its nominal distance, mm.
    pub nominal_mm: f64,
    /// The plausible readings, mm.
    pub window_mm: [f64; 2],
    /// Whether the entry would be accepted.
    pub valid: bool,
    /// What the console shows.
    pub message: String,
    /// One answer per field (or item).
    pub items: Vec<ItemAnswer>,
}

/// One field's (or item's) answer: its value, or the problem alone.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub(crate) struct ItemAnswer {
    /// The field as typed.
    pub text: String,
    /// Its reading, mm, when accepted.
    pub values: Option<Vec<f64>>,
    /// Why it is refused.
    pub error: Option<String>,
}

/// `klipcal_solve`: the solution (the `klipcal solve --json` shape).
#[derive(Debug, Clone, PartialEq, Serialize)]
pub(crate) struct Solved {
    /// The solver's result.
    pub solution: Solution,
    /// What the console shows.
    pub message: String,
}

/// `klipcal_apply`: the state the session is in now and what was written.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub(crate) struct Applied {
    /// `converged` (nothing to write) or the state after the write.
    pub state: String,
    /// What was written (absent when nothing was).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub applied: Option<ApplyReport>,
    /// What the console shows.
    pub message: String,
}

/// `klipcal_soak_choice`: the choice taken.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub(crate) struct Chosen {
    /// The session.
    pub session: i64,
    /// `print` or `wait`.
    pub choice: &'static str,
    /// What the console shows.
    pub message: String,
}

#[cfg(test)]
mod tests {
    use super::*;
    use serde_json::json;

    #[test]
    fn converged_without_a_write_has_no_applied_key() {
        let a = Applied {
            state: "converged".into(),
            applied: None,
            message: "already calibrated".into(),
        };
        assert_eq!(
            serde_json::to_value(&a).unwrap(),
            json!({"state": "converged", "message": "already calibrated"})
        );
        let i = ItemAnswer {
            text: "10,02".into(),
            values: None,
            error: Some("outside".into()),
        };
        assert_eq!(
            serde_json::to_value(&i).unwrap(),
            json!({"text": "10,02", "values": null, "error": "outside"})
        );
    }
}
