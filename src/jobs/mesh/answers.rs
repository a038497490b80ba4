//! The thermal mesh operations' answers, typed (the JSON the page and the API read; `message`
//! is what the console shows).

use serde::Serialize;

/// `klipcal_mesh_follow`: following on or off.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub(crate) struct Following {
    /// Whether the follower runs now.
    pub following: bool,
    /// The session whose profiles it follows (absent when off).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub session: Option<i64>,
    /// What the console shows.
    pub message: String,
}

/// `klipcal_mesh_check`: every point probed against the model.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub(crate) struct Checked {
    /// The check passed (a failed one is an error).
    pub ok_check: bool,
    /// The points probed.
    pub points: Vec<CheckPoint>,
    /// The frame temperature, °C.
    pub frame_c: f64,
    /// What the console shows.
    pub message: String,
}

/// One probed point of the check.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub(crate) struct CheckPoint {
    /// mm.
    pub x: f64,
    /// mm.
    pub y: f64,
    /// The probe's height there, mm.
    pub probed_mm: f64,
    /// The model's, mm.
    pub model_mm: f64,
    /// Probed minus model, mm.
    pub diff_mm: f64,
}

/// `klipcal_mesh_import`: the session fitting the imported profiles.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub(crate) struct Imported {
    /// The session.
    pub session: i64,
    /// Its state (`writing`).
    pub state: String,
    /// The profiles fitted.
    pub imported: Vec<String>,
    /// The TEST profiles, judged against the fit.
    pub tests: Vec<TestJudged>,
    /// klipcal profiles the write replaces.
    pub replaces: Vec<String>,
    /// What the console shows.
    pub message: String,
}

/// A TEST profile judged against the fit.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub(crate) struct TestJudged {
    /// The profile.
    pub name: String,
    /// Its temperature, °C.
    pub temp_c: f64,
    /// Its largest distance from the model, µm.
    pub max_um: f64,
    /// Its mean distance, µm.
    pub mean_um: f64,
    /// Within the fit's tolerance.
    pub within_tolerance: bool,
}

#[cfg(test)]
mod tests {
    use super::*;
    use serde_json::json;

    #[test]
    fn following_off_has_no_session_and_on_names_it() {
        let off = Following {
            following: false,
            session: None,
            message: "off".into(),
        };
        assert_eq!(
            serde_json::to_value(&off).unwrap(),
            json!({"following": false, "message": "off"})
        );
        let on = Following {
            following: true,
            session: Some(4),
            message: "on".into(),
        };
        assert_eq!(
            serde_json::to_value(&on).unwrap(),
            json!({"following": true, "session": 4, "message": "on"})
        );
    }
}
