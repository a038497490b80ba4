//! The page: server-rendered HTML from the status document (the same JSON `/api/status`
//! answers), with a small inline script that polls the status, validates readings live
//! through `/api/ab/check` and posts the forms as JSON. No build step, no external resources
//! (printer hosts are often offline), fits a phone. Every text from a document is escaped.
//!
//! This file holds the frame (header, start form, session card, last sessions, every
//! operation); each calibration's section is its own file (`ab`, `mesh`, `backlash`), the bed
//! soak's (its line, its question, print now) is `soak`, the
//! style sheet and script are in `assets`.

use std::fmt::Write as _;

use serde_json::Value;

use ab::ab_sections;
use assets::{SCRIPT, STYLE};
use backlash::backlash_section;
use mesh::mesh_section;

mod ab;
mod assets;
mod backlash;
mod mesh;
mod soak;

/// Escapes text for HTML content and attribute values.
pub(super) fn esc(s: &str) -> String {
    let mut out = String::with_capacity(s.len());
    for c in s.chars() {
        match c {
            '&' => out.push_str("&amp;"),
            '<' => out.push_str("&lt;"),
            '>' => out.push_str("&gt;"),
            '"' => out.push_str("&quot;"),
            '\'' => out.push_str("&#39;"),
            c => out.push(c),
        }
    }
    out
}

pub(super) fn text(v: &Value) -> String {
    match v {
        Value::String(s) => esc(s),
        Value::Null => String::new(),
        other => esc(&other.to_string()),
    }
}

/// A distance with at most 3 decimals (as the console shows it).
pub(super) fn mm(v: f64) -> String {
    crate::calib::entry::fmt_mm(v)
}

/// The signature the script compares with each poll to know when to reload.
fn signature(session: &Value) -> String {
    if session.is_null() {
        return "|||{}|0||".into();
    }
    let readings = if session["readings"].is_null() {
        "{}".to_string()
    } else {
        session["readings"].to_string()
    };
    let camera_cycles: usize = session["camera"].as_object().map_or(0, |o| {
        o.values()
            .filter_map(|c| c["cycles"].as_array())
            .map(Vec::len)
            .sum()
    });
    // The guided backlash's jog buttons and cycle: a press in the dialog changes what the
    // page's buttons must offer.
    let jog: Vec<&str> = session["jog"]
        .as_array()
        .into_iter()
        .flatten()
        .filter_map(|b| b["press"].as_str())
        .collect();
    format!(
        "{}|{}|{}|{}|{camera_cycles}|{}|{}",
        session["id"]
            .as_i64()
            .map(|v| v.to_string())
            .unwrap_or_default(),
        session["state"].as_str().unwrap_or(""),
        session["round"]
            .as_i64()
            .map(|v| v.to_string())
            .unwrap_or_default(),
        readings,
        jog.join(","),
        session["cycle"]
            .as_u64()
            .map(|v| v.to_string())
            .unwrap_or_default()
    )
}

/// The whole page for a status answer (`{"ok", "session", "last", …}` or an error) and, while
/// readings are taken, the layout diagram.
#[must_use]
pub(crate) fn render(status: &Value, diagram_svg: Option<&str>) -> String {
    let session = status.get("session").cloned().unwrap_or(Value::Null);
    let mut h = String::new();
    let _ = write!(
        h,
        "<!doctype html><html lang=\"en\"><head><meta charset=\"utf-8\">\
         <meta name=\"viewport\" content=\"width=device-width,initial-scale=1\">\
         <title>klipcal</title><style>{STYLE}</style></head><body data-sig=\"{}\">",
        esc(&signature(&session))
    );
    let klippy = status["connection"]["klippy_state"]
        .as_str()
        .or_else(|| status["connection"]["moonraker"].as_str())
        .unwrap_or("unknown");
    let _ = write!(
        h,
        "<header><h1>klipcal</h1><span>Klipper: <b id=\"klippy\">{}</b></span>{}</header>\
         <div id=\"banner\">The session moved on. <a href=\"/\">Reload</a> (your unsaved \
         entries stay until you do).</div><main>",
        esc(klippy),
        status["daemon"]["version"]
            .as_str()
            .map(|v| format!("<small>v{}</small>", esc(v)))
            .unwrap_or_default()
    );
    if status["ok"] == Value::Bool(false) {
        let _ = write!(
            h,
            "<section><h2>Status unavailable</h2><p class=\"msg error\">{}</p></section>",
            text(&status["error"]["message"])
        );
    }
    if let Some(msg) = status["connection"]["message"].as_str() {
        // Moonraker unreachable: said at once; the session below still shows from the database.
        let _ = write!(
            h,
            "<p id=\"moonraker\" class=\"msg error\">{}</p>",
            esc(msg)
        );
    }
    h.push_str("<p id=\"opmsg\" class=\"msg\"></p>");
    // Each calibration's own final states decide (`StatusHead::finished`): a mesh or backlash
    // session ends in `done`, an A/B one in `converged`.
    let active = session["state"].is_string() && session["finished"] != Value::Bool(true);
    if session.is_null() || !active {
        start_form(&mut h);
    }
    if !session.is_null() {
        session_card(&mut h, &session, active);
        if active {
            soak::soak_section(&mut h, &status["soak"], &session);
        }
        if session["kind"] == "ab" {
            ab_sections(&mut h, &session, diagram_svg);
        }
        if session["kind"] == "mesh" {
            mesh_section(&mut h, &session);
        }
        if session["kind"] == "backlash" {
            backlash_section(&mut h, &session);
        }
    }
    last_results(&mut h, &status["last"], &session);
    operations(&mut h, crate::jobs::registry::all_ops());
    let _ = write!(h, "</main><script>{SCRIPT}</script></body></html>");
    h
}

/// Every operation of the command table as a form, with a field per argument (its help as the
/// field's hint, its choices as a list): whatever a macro can do, the page can (a phone without
/// a console reaches all of them). Folded away under the session's own controls.
fn operations(h: &mut String, ops: &[&crate::jobs::table::OpSpec]) {
    use crate::jobs::table::{arg_form, ArgKind};
    h.push_str(
        "<section id=\"operations\"><details><summary><b>Every operation</b> \
         <small>(the same as the macros)</small></summary>",
    );
    for op in ops {
        let Some(path) = op.http else { continue };
        let _ = write!(
            h,
            "<form class=\"op\" data-path=\"{}\"><p><b>{}</b> <small>{}</small></p><div class=\"fields\">",
            esc(path),
            esc(op.macro_name),
            esc(op.summary)
        );
        for a in op.args {
            let name = esc(a.name);
            let label = esc(&a.name.to_uppercase());
            let hint = esc(&format!("{} ({})", a.help, arg_form(a)));
            match a.kind {
                ArgKind::Choice(choices) => {
                    let _ = write!(
                        h,
                        "<label class=\"field\" title=\"{hint}\">{label}<select name=\"{name}\">\
                         <option value=\"\">{}</option>",
                        if a.default.is_empty() {
                            "default".to_string()
                        } else {
                            format!("default ({})", esc(a.default))
                        }
                    );
                    for c in choices {
                        let _ = write!(h, "<option>{}</option>", esc(c));
                    }
                    h.push_str("</select></label>");
                }
                ArgKind::Flag => {
                    let _ = write!(
                        h,
                        "<label class=\"field\" title=\"{hint}\"><span>{label}</span>\
                         <input type=\"checkbox\" name=\"{name}\" style=\"width:auto\"></label>"
                    );
                }
                _ => {
                    let _ = write!(
                        h,
                        "<label class=\"field\" title=\"{hint}\">{label}<input name=\"{name}\" \
                         placeholder=\"{}\" autocomplete=\"off\"></label>",
                        esc(a.example)
                    );
                }
            }
        }
        let _ = write!(
            h,
            "</div><p class=\"row\"><button class=\"quiet\" data-op=\"{}\" data-out=\"op-{}\" \
             data-confirm=\"Run {} now?\">Run</button><span id=\"op-{}\" class=\"msg\"></span></p></form>",
            esc(path),
            esc(&path.replace('/', "-")),
            esc(op.macro_name),
            esc(&path.replace('/', "-"))
        );
    }
    h.push_str("</details></section>");
}

fn start_form(h: &mut String) {
    h.push_str(
        "<section><h2>Start an A/B calibration</h2><form class=\"row\" id=\"start\">\
         <label>Bed °C <input name=\"bed\" inputmode=\"decimal\" placeholder=\"60\" size=\"4\" style=\"width:5em\"></label>\
         <label>Nozzle °C <input name=\"extruder\" inputmode=\"decimal\" placeholder=\"215\" style=\"width:5em\"></label>\
         <label>Layout <select name=\"layout\"><option value=\"\">default</option><option>paper</option><option>full</option></select></label>\
         <button data-op=\"ab/start\" data-out=\"startmsg\" data-confirm=\"Print the pylon job now? The bed heats and the printer moves.\">Start</button>\
         </form><p id=\"startmsg\" class=\"msg\"></p>\
         <p class=\"row\"><button class=\"quiet\" data-op=\"mesh/capture\" data-out=\"startmsg\" \
         data-confirm=\"Start a thermal mesh capture? The bed heats and the printer probes meshes for up to mesh.max_s.\">\
         Capture a thermal mesh</button></p></section>",
    );
}

fn session_card(h: &mut String, s: &Value, active: bool) {
    let state = s["state"].as_str().unwrap_or("?");
    let kind = match s["kind"].as_str() {
        Some("ab") => "A/B calibration",
        Some("backlash") => "backlash measurement",
        Some("mesh") => "thermal mesh",
        _ => "calibration",
    };
    let _ = write!(
        h,
        "<section id=\"session\"><h2>{kind} · session {}{} <span class=\"state {}\">{}</span></h2>\
         <p id=\"progress\">{}</p>",
        text(&s["id"]),
        // A backlash measurement has no rounds: "round measured" read as a broken line.
        if s["round"].is_null() {
            String::new()
        } else {
            format!(" · round {}", text(&s["round"]))
        },
        esc(state),
        esc(state),
        text(&s["progress"])
    );
    if let Some(r) = s["reason"].as_str() {
        let _ = write!(h, "<p class=\"msg error\">{}</p>", esc(r));
    }
    if let Some(notes) = s["notes"].as_array().filter(|n| !n.is_empty()) {
        h.push_str("<details><summary>Notes</summary><ul>");
        for n in notes {
            let _ = write!(h, "<li>{}</li>", text(n));
        }
        h.push_str("</ul></details>");
    }
    if active {
        h.push_str(
            "<p class=\"row\"><button class=\"danger\" data-op=\"cancel\" data-confirm=\"Cancel the session? \
             A running print is cancelled and the heaters go off.\">Cancel session</button></p>",
        );
    }
    h.push_str("</section>");
}

fn last_results(h: &mut String, last: &Value, shown: &Value) {
    let Some(map) = last.as_object().filter(|m| !m.is_empty()) else {
        return;
    };
    let rows: Vec<(&String, &Value)> = map.iter().filter(|(_, s)| s["id"] != shown["id"]).collect();
    if rows.is_empty() {
        return;
    }
    h.push_str("<section><h2>Last sessions</h2><table>");
    for (kind, s) in rows {
        let _ = write!(
            h,
            "<tr><td>{}</td><td>session {}</td><td>{}</td><td>{}</td></tr>",
            esc(kind),
            text(&s["id"]),
            text(&s["state"]),
            text(&s["progress"])
        );
    }
    h.push_str("</table></section>");
}

#[cfg(test)]
mod tests {
    use super::*;
    use serde_json::json;

    /// Every key anywhere in `v`.
    fn keys_of(v: &Value, out: &mut std::collections::BTreeSet<String>) {
        match v {
            Value::Object(o) => {
                for (k, x) in o {
                    out.insert(k.clone());
                    keys_of(x, out);
                }
            }
            Value::Array(a) => a.iter().for_each(|x| keys_of(x, out)),
            _ => {}
        }
    }

    /// A camera report with every part filled in.
    fn camera_report() -> crate::jobs::backlash::camera::CameraReport {
        use crate::calib::camera_scale::{fit_axis, CameraScale, Sighting};
        let sight = |dir: [f64; 2]| -> Vec<Sighting> {
            [-0.5, 0.0, 0.5]
                .map(|t| Sighting {
                    commanded_mm: t,
                    centre_px: [320.0 + 80.0 * t * dir[0], 240.0 + 80.0 * t * dir[1]],
                    uncertainty_px: 0.02,
                })
                .to_vec()
        };
        let scale = CameraScale::from_axes(
            fit_axis("x", &sight([1.0, 0.0])).unwrap(),
            fit_axis("y", &sight([0.0, 1.0])).unwrap(),
        )
        .unwrap();
        crate::jobs::backlash::camera::CameraReport {
            webcam: crate::jobs::backlash::camera::Webcam {
                name: "nozzle".into(),
                snapshot_url: String::new(),
            },
            scale: Some(scale),
            reference_px: Some([320.0, 240.0]),
            cycles: vec![crate::jobs::backlash::camera::CameraCycle {
                plus_px: [320.0, 240.0],
                minus_px: [326.0, 240.0],
                plus_mm: 0.0,
                minus_mm: 0.08,
                backlash_mm: 0.08,
            }],
            detection_sd_px: 0.02,
            axis_px_per_mm: 80.0,
            frames: 12,
            refused_frames: 0,
            last_px: None,
            clicks: 0,
            refined: 0,
            kept: Vec::new(),
        }
    }

    /// A status of each kind, built from the typed structs the agent serializes, with every
    /// nested part filled in.
    fn typed_status_keys() -> std::collections::BTreeSet<String> {
        use crate::agent::{Connection, DaemonInfo, PageInfo, StatusAnswer};
        use crate::jobs::core::envelope::StatusHead;
        use crate::jobs::core::status::{SessionStatus, SessionsStatus};
        let head = StatusHead {
            id: 1,
            state: "measuring".into(),
            progress: String::new(),
            reason: None,
            notes: vec![],
            finished: false,
        };
        let mut last = std::collections::BTreeMap::new();
        last.insert(
            "ab".into(),
            SessionStatus::new("ab", head.clone(), &typed_ab_status()).unwrap(),
        );
        last.insert(
            "mesh".into(),
            SessionStatus::new("mesh", head.clone(), &typed_mesh_status()).unwrap(),
        );
        last.insert(
            "backlash".into(),
            SessionStatus::new("backlash", head.clone(), &typed_backlash_status()).unwrap(),
        );
        let answer = StatusAnswer {
            page: Some(PageInfo {
                address: Some(String::new()),
                off: Some(String::new()),
            }),
            daemon: DaemonInfo {
                name: "klipcal",
                version: "0",
            },
            connection: Connection {
                moonraker: "unreachable",
                klippy_state: Some("ready".into()),
                last_error: Some(None),
                message: Some(String::new()),
            },
            printer: None,
            sessions: SessionsStatus {
                session: last.get("ab").cloned(),
                last,
                soak: Some(typed_soak_view()),
            },
        };
        let mut keys = std::collections::BTreeSet::new();
        keys_of(&serde_json::to_value(answer).unwrap(), &mut keys);
        keys
    }

    /// An A/B status with a pair and a round.
    fn typed_ab_status() -> crate::jobs::ab::AbStatus {
        use crate::jobs::ab::{AbRoundStatus, AbStatus};
        AbStatus {
            pairs: Some(vec![crate::layout::Pair {
                id: "A-D1".into(),
                group: "A".into(),
                from: "A1".into(),
                to: "A2".into(),
                direction_deg: 0.0,
                nominal_mm: 10.0,
            }]),
            rounds: vec![AbRoundStatus::default()],
            ..AbStatus::default()
        }
    }

    /// A mesh status with a result and a follower that has both a reading and a reason.
    fn typed_mesh_status() -> crate::jobs::mesh::MeshStatus {
        use crate::jobs::mesh::{FollowReading, FollowStatus, MeshStatus, ResultDoc};
        MeshStatus {
            result: Some(ResultDoc {
                model: "linear".into(),
                models: vec![],
                vgb: None,
                range_c: (25.0, 40.0),
                profiles_c: vec![],
                max_quantisation_um: 0.0,
                backup: None,
                replaced: vec![],
                directions: String::new(),
                cooling: None,
            }),
            // Both the reading and the reason, so that every key of the follower is listed.
            follow: FollowStatus {
                following: true,
                stopped: Some(String::new()),
                reading: Some(FollowReading {
                    frame_c: 0.0,
                    trend: crate::calib::mesh::Phase::Heating,
                    loaded: Some(String::new()),
                    offset_mm: [0.0; 2],
                    residual_um: Some(0.0),
                }),
            },
            ..MeshStatus::default()
        }
    }

    /// A backlash status with cycles, a result, a camera report, a snapshot and a jog button.
    fn typed_backlash_status() -> crate::jobs::backlash::BacklashStatus {
        use crate::jobs::backlash::BacklashStatus;
        let cycles = vec![0.1, 0.11, 0.1, 0.12, 0.1]
            .into_iter()
            .map(|b| crate::calib::backlash::Cycle {
                x1_mm: b,
                x2_mm: 0.0,
                fine_mm: None,
            })
            .collect::<Vec<_>>();
        let result = crate::calib::backlash::analyse(
            "x",
            &cycles,
            None,
            &crate::config::BacklashConfig::default().params(),
        )
        .unwrap();
        BacklashStatus {
            point: [0.0; 3],
            branch: crate::klipper::backlash::detect(&json!({}), &Default::default()).unwrap(),
            axis: None,
            cycle: None,
            cycles: [("x".to_string(), cycles)].into(),
            corexy_answer: None,
            results: [("x".to_string(), result)].into(),
            active_mm: Default::default(),
            camera: [("x".to_string(), camera_report())].into(),
            snapshot: Some(crate::jobs::backlash::snapshot::SnapshotInfo {
                seq: 1,
                width: 640,
                height: 480,
                what: String::new(),
                centre_px: Some([1.0, 2.0]),
                radius_px: Some(20.0),
                uncertainty_px: Some(0.03),
                refused: Some(String::new()),
                click: false,
                hint_px: Some([1.0, 2.0]),
                zoom: Some(4.0),
            }),
            jog: vec![crate::jobs::backlash::JogButton {
                label: String::new(),
                press: String::new(),
                style: String::new(),
            }],
        }
    }

    /// A soak view with a question and a live soak.
    fn typed_soak_view() -> crate::jobs::core::soak_ask::SoakView {
        crate::jobs::core::soak_ask::SoakView {
            question: Some(crate::jobs::core::soak_ask::QuestionStatus {
                title: String::new(),
                text: String::new(),
                answers: vec![crate::jobs::core::soak_ask::AnswerStatus {
                    label: String::new(),
                    arg: String::new(),
                    value: String::new(),
                }],
            }),
            live: Some(crate::jobs::core::soak::LiveSoak {
                progress: String::new(),
                derivation: String::new(),
                eta_s: Some(1.0),
                print_now_c: Some(1.0),
                fit: None,
                at: std::time::Instant::now(),
            }),
        }
    }

    /// The page of a status whose session is a fresh envelope of `kind` in `state`, built the
    /// way the agent builds it (the envelope's head, the status struct, JSON).
    fn page_in<S: crate::jobs::core::envelope::SessionState>(kind: &str, state: S) -> String {
        use crate::jobs::core::envelope::Envelope;
        use crate::jobs::core::status::SessionStatus;
        let head = Envelope::new(state, "", ()).head();
        let session = SessionStatus::new(kind, head, &serde_json::json!({})).unwrap();
        render(
            &serde_json::json!({"ok": true, "session": session, "last": {}}),
            None,
        )
    }

    #[test]
    fn a_finished_session_of_every_kind_shows_as_finished() {
        use crate::jobs::{ab, backlash, mesh};
        let finished = [
            page_in("mesh", mesh::State::Done),
            page_in("backlash", backlash::State::Done),
            page_in("ab", ab::State::Converged),
            page_in("mesh", mesh::State::Failed),
        ];
        for page in finished {
            assert!(page.contains("Start an A/B calibration"), "{page}");
            assert!(!page.contains("Cancel session</button>"), "{page}");
        }
        let running = page_in("mesh", mesh::State::Capturing);
        assert!(running.contains("Cancel session</button>"), "{running}");
        assert!(!running.contains("Start an A/B calibration"), "{running}");
    }

    #[test]
    fn every_status_key_the_page_reads_is_a_field_of_the_typed_status() {
        let source: String = [
            include_str!("mod.rs"),
            include_str!("ab.rs"),
            include_str!("mesh.rs"),
            include_str!("backlash.rs"),
            include_str!("soak.rs"),
        ]
        .iter()
        .map(|s| &s[..s.find("#[cfg(test)]").unwrap_or(s.len())])
        .collect();
        let source = source.as_str();
        let mut read = std::collections::BTreeSet::new();
        // The Rust side: `x["key"]`, `x["a"]["key"]` (not an array literal `["a", "b"]`).
        for (at, _) in source.match_indices("[\"") {
            let before = source[..at].chars().next_back().unwrap_or(' ');
            if !(before.is_ascii_alphanumeric() || before == '_' || before == ']') {
                continue;
            }
            let part = &source[at + 2..];
            if let Some(end) = part.find("\"]") {
                read.insert(part[..end].to_string());
            }
        }
        // The script's poll: `s.key` (the session), `j.key` and `j.connection.key`.
        let poll = &SCRIPT[SCRIPT.find("async function poll").unwrap()..];
        let poll = &poll[..poll.find("setInterval(poll").unwrap()];
        for prefix in ["s.", "j.", "j.connection."] {
            for part in poll.split(prefix).skip(1) {
                let key: String = part
                    .chars()
                    .take_while(|c| c.is_ascii_alphanumeric() || *c == '_')
                    .collect();
                if !key.is_empty() && !["textContent", "style", "json"].contains(&key.as_str()) {
                    read.insert(key);
                }
            }
        }
        assert!(
            read.len() > 40,
            "the page reads {} keys: {read:?}",
            read.len()
        );
        // `ok`, `error` and `message` are the answer's wrapping (`http::answer`), not the
        // status.
        let wrapping = ["ok", "error", "message"];
        let have = typed_status_keys();
        for follower in ["following", "stopped", "loaded", "residual_um", "frame_c"] {
            assert!(read.contains(follower), "the page reads {follower}");
        }
        let missing: Vec<&String> = read
            .iter()
            .filter(|k| !have.contains(*k))
            .filter(|k| !wrapping.contains(&k.as_str()))
            .collect();
        assert!(
            missing.is_empty(),
            "the page reads keys no typed status has: {missing:?}"
        );
    }

    pub(super) fn measuring() -> Value {
        json!({"ok": true, "daemon": {"version": "0.1.0"}, "connection": {"klippy_state": "ready"},
            "session": {"kind": "ab", "id": 4, "state": "measuring", "round": 1,
                "progress": "waiting for caliper readings <now>", "readings_per_pair": 5, "bed_temp_c": 0.0,
                "pairs": [{"id": "A-D1", "from": "A1", "to": "A2", "nominal_mm": 10.0},
                          {"id": "A-D2", "from": "A1", "to": "A3", "nominal_mm": 150.0}],
                "readings": {"A-D1": [10.02, 10.03]}, "missing": ["A-D1: 3 more", "A-D2: 5 more"],
                "rounds": [{"n": 1, "file": "klipcal/ab-s4-r1.gcode", "scale": null}], "notes": []},
            "last": {}})
    }

    #[test]
    fn document_text_is_escaped() {
        let page = render(&measuring(), None);
        assert!(page.contains("waiting for caliper readings &lt;now&gt;"));
        assert!(!page.contains("<now>"));
    }

    #[test]
    fn no_session_offers_the_start_form_and_an_error_is_shown() {
        let page = render(&json!({"ok": true, "session": null, "last": {}}), None);
        assert!(page.contains("data-op=\"ab/start\""));
        let page = render(
            &json!({"ok": false, "error": {"message": "no database"}}),
            None,
        );
        assert!(page.contains("Status unavailable") && page.contains("no database"));
    }

    #[test]
    fn every_operation_with_an_http_path_has_a_form_with_a_field_per_argument() {
        let page = render(&json!({"session": null, "last": {}}), None);
        for op in crate::jobs::registry::all_ops() {
            let Some(path) = op.http else { continue };
            assert!(
                page.contains(&format!("data-op=\"{path}\" data-out=\"op-")),
                "no form for {path}"
            );
            let form = page
                .split(&format!("data-path=\"{path}\""))
                .nth(1)
                .and_then(|f| f.split("</form>").next())
                .unwrap();
            for a in op.args {
                assert!(
                    form.contains(&format!("name=\"{}\"", a.name)),
                    "{path} has no field {}",
                    a.name
                );
            }
        }
        // The soak's answer, which the page once lacked (issue 24).
        assert!(page.contains("data-op=\"ab/soak_choice\""));
    }
}
