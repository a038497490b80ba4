//! The page's bed-mesh section: the session's meshes, the fitted models and the follower.

use std::fmt::Write as _;

use serde_json::Value;

use super::{esc, text};

pub(super) fn mesh_section(h: &mut String, s: &Value) {
    let state = s["state"].as_str().unwrap_or("");
    h.push_str("<section id=\"mesh\"><h2>Thermal mesh</h2>");
    if matches!(state, "soaking" | "capturing") {
        h.push_str(
            "<img id=\"soak\" class=\"plot\" alt=\"bed temperature and power\" src=\"/api/plots/soak.svg\">",
        );
    }
    let frames: Vec<String> = s["frame_c"]
        .as_array()
        .into_iter()
        .flatten()
        .filter_map(Value::as_f64)
        .map(|t| format!("{t:.2}"))
        .collect();
    let _ = write!(
        h,
        "<p>{} mesh(es){}</p>",
        frames.len(),
        if frames.is_empty() {
            String::new()
        } else {
            format!(" at frame {} °C", esc(&frames.join(", ")))
        }
    );
    let r = &s["result"];
    if !r.is_null() {
        let n = r["profiles_c"].as_array().map_or(0, Vec::len);
        let _ = write!(
            h,
            "<p>model <b>{}</b>; {n} profiles klipcal_* over {}–{} °C; worst step {} µm</p>",
            text(&r["model"]),
            r["range_c"][0]
                .as_f64()
                .map(|v| format!("{v:.2}"))
                .unwrap_or_default(),
            r["range_c"][1]
                .as_f64()
                .map(|v| format!("{v:.2}"))
                .unwrap_or_default(),
            r["max_quantisation_um"]
                .as_f64()
                .map(|v| format!("{v:.1}"))
                .unwrap_or_default()
        );
        h.push_str("<div class=\"scroll\"><table><tr><th>model</th><th>max µm</th><th>mean µm</th><th>RMS µm</th></tr>");
        for m in r["models"].as_array().into_iter().flatten() {
            let f = |k: usize| m[k].as_f64().map(|v| format!("{v:.1}")).unwrap_or_default();
            let _ = write!(
                h,
                "<tr><td>{}</td><td>{}</td><td>{}</td><td>{}</td></tr>",
                text(&m[0]),
                f(1),
                f(2),
                f(3)
            );
        }
        if let Some(v) = r["vgb"].as_array() {
            let f = |k: usize| {
                v.get(k)
                    .and_then(Value::as_f64)
                    .map(|x| format!("{x:.1}"))
                    .unwrap_or_default()
            };
            let _ = write!(
                h,
                "<tr><td>VGB two-mesh</td><td>{}</td><td>{}</td><td>{}</td></tr>",
                f(0),
                f(1),
                f(2)
            );
        }
        h.push_str("</table></div><p class=\"row\"><button data-op=\"mesh/follow\">Follow the frame</button>\
            <button class=\"quiet\" data-op=\"mesh/check\">Check against the bed</button></p>");
    }
    let f = &s["follow"];
    if f["following"] == Value::Bool(true) {
        let _ = write!(
            h,
            "<p>following: frame {} °C, profile {}, residual {} µm</p>",
            f["frame_c"]
                .as_f64()
                .map(|v| format!("{v:.2}"))
                .unwrap_or_default(),
            text(&f["loaded"]),
            f["residual_um"]
                .as_f64()
                .map(|v| format!("{v:.1}"))
                .unwrap_or_default()
        );
    } else if let Some(why) = f["stopped"].as_str() {
        let _ = write!(
            h,
            "<p class=\"msg error\">following stopped: {}</p>",
            esc(why)
        );
    }
    h.push_str("</section>");
}

#[cfg(test)]
mod tests {
    use crate::http::page::render;
    use serde_json::json;

    #[test]
    fn a_mesh_session_shows_its_meshes_models_and_follow_state() {
        let st = json!({"ok": true, "session": {"kind": "mesh", "id": 7, "state": "done", "progress": "written",
            "frame_c": [28.25, 28.9], "follow": {"following": true, "frame_c": 29.1, "loaded": "klipcal_29.05", "residual_um": 1.2},
            "result": {"model": "linear", "models": [["linear", 4.0, 1.5, 2.0]], "vgb": [9.0, 3.0, 4.0],
                       "range_c": [28.2, 29.4], "profiles_c": [28.3, 28.9, 29.3], "max_quantisation_um": 4.2}},
            "last": {}});
        let page = render(&st, None);
        assert!(
            page.contains("2 mesh(es) at frame 28.25, 28.90 °C"),
            "{page}"
        );
        assert!(page.contains("3 profiles klipcal_* over 28.20–29.40 °C"));
        assert!(page.contains("<td>VGB two-mesh</td><td>9.0</td>"));
        assert!(page.contains("profile klipcal_29.05, residual 1.2 µm"));
        assert!(page.contains("data-op=\"mesh/follow\""));
    }
}
