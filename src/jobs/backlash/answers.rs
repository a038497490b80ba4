//! The backlash operations' answers, typed (the JSON the page and the API read; `message` is
//! what the console shows).

use std::collections::BTreeMap;

use serde::Serialize;

use super::camera::Webcam;
use crate::calib::backlash::AxisResult;

/// `klipcal_backlash_set_point`: the camera point saved.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub(crate) struct PointSaved {
    /// X, Y, Z, mm.
    pub point: [f64; 3],
    /// What the console shows.
    pub message: String,
}

/// `klipcal_backlash_start`, `_camera`, `_click`: an axis being measured.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub(crate) struct AxisStarted {
    /// The session.
    pub session: i64,
    /// `measuring`.
    pub state: String,
    /// The axis (`x`, `a`, …).
    pub axis: &'static str,
    /// The dual carriage measured, when the printer has one.
    pub carriage: Option<u32>,
    /// The webcam read (the camera and the click measurement).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub webcam: Option<Webcam>,
    /// What the console shows.
    pub message: String,
}

/// `klipcal_backlash_jog`: the step the press made, or the axis measured.
#[derive(Debug, Clone, PartialEq, Serialize)]
#[serde(untagged)]
pub(crate) enum Jogged {
    /// The axis's last cycle is in.
    Measured {
        /// The session.
        session: i64,
        /// `measured`.
        state: String,
        /// Every axis measured so far.
        results: BTreeMap<String, AxisResult>,
        /// What the console shows.
        message: String,
    },
    /// The procedure goes on.
    Step {
        /// The session.
        session: i64,
        /// `measuring`.
        state: String,
        /// A position recorded by this press, mm.
        recorded: Option<f64>,
        /// The approach's phase.
        phase: String,
        /// Reading a crossing now.
        crossing: bool,
        /// Past pressed once in this crossing.
        past_once: bool,
        /// The cycle, 1-based.
        cycle: usize,
        /// What the console shows.
        message: String,
    },
}

/// `klipcal_backlash_apply`: what was set and written.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub(crate) struct Applied {
    /// The session.
    pub session: i64,
    /// `done`.
    pub state: String,
    /// The values set, mm per axis (absent when nothing needed compensation).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub values: Option<BTreeMap<String, f64>>,
    /// The smooth_time set, s (null on a branch without one; absent with no values).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub smooth_time_s: Option<Option<f64>>,
    /// What the console shows.
    pub message: String,
}

/// `_KLIPCAL_BACKLASH_TIP`: the click taken.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub(crate) struct Clicked {
    /// The snapshot clicked in.
    pub frame: u64,
    /// What the console shows.
    pub message: String,
}

#[cfg(test)]
mod tests {
    use super::*;
    use serde_json::json;

    #[test]
    fn the_answers_keep_the_shape_the_page_and_the_api_read() {
        // Nothing to write: no values and no smooth_time key; written: both, smooth_time null
        // on a branch without one.
        let none = Applied {
            session: 3,
            state: "done".into(),
            values: None,
            smooth_time_s: None,
            message: "m".into(),
        };
        assert_eq!(
            serde_json::to_value(&none).unwrap(),
            json!({"session": 3, "state": "done", "message": "m"})
        );
        let set = Applied {
            values: Some(BTreeMap::from([("x".to_string(), 0.05)])),
            smooth_time_s: Some(None),
            ..none
        };
        assert_eq!(
            serde_json::to_value(&set).unwrap(),
            json!({"session": 3, "state": "done", "values": {"x": 0.05},
                   "smooth_time_s": null, "message": "m"})
        );
        // A jog's step is flat (untagged), as the page reads it.
        let step = Jogged::Step {
            session: 3,
            state: "measuring".into(),
            recorded: None,
            phase: "Plus".into(),
            crossing: false,
            past_once: false,
            cycle: 1,
            message: String::new(),
        };
        let v = serde_json::to_value(&step).unwrap();
        assert_eq!(v["state"], "measuring");
        assert_eq!(v["recorded"], serde_json::Value::Null);
        assert_eq!(v["cycle"], 1);
        // The guided start has no webcam key; its carriage is null when there is none.
        let started = AxisStarted {
            session: 3,
            state: "measuring".into(),
            axis: "x",
            carriage: None,
            webcam: None,
            message: "m".into(),
        };
        assert_eq!(
            serde_json::to_value(&started).unwrap(),
            json!({"session": 3, "state": "measuring", "axis": "x", "carriage": null,
                   "message": "m"})
        );
    }
}
